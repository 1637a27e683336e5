//! Unit tests of `capture.rs`: every parameter gradient of the field
//! (density, compaction, colour, appearance) against central differences in
//! f64, in contracted and NDC space; the view appearance against per-image
//! appearance; the initial density and the NDC selector.

use super::*;
use crate::engine::fields::space::{Norm, test_ndc};

fn config(appearance_dim: usize) -> CaptureFieldConfig {
    CaptureFieldConfig {
        grid: HashGridConfig { levels: 3, log2_table: 6, base_resolution: 2, finest_resolution: 8 },
        hidden: 8,
        geo_features: 4,
        init_density: 0.3,
        max_images: 5,
        appearance_dim,
    }
}

/// Points at log-uniform distances (inside the unit cube and far out in
/// the contracted shell), or in the NDC camera's frustum.
fn points(space: &SpaceMap, rng: &mut Rng, n: usize) -> Vec<f32> {
    (0..n)
        .flat_map(|_| match space {
            SpaceMap::Contract { .. } => {
                let r = 10f32.powf(2.0 * rng.f32() - 1.0);
                [rng.normal() * r, rng.normal() * r, rng.normal() * r]
            }
            SpaceMap::Ndc(_) => {
                let z = -0.6 - 20.0 * rng.f32();
                [(rng.f32() - 0.5) * z, (rng.f32() - 0.5) * 0.7 * z, z]
            }
        })
        .collect()
}

/// A field with random parameters (embeddings too), and its layout.
fn field(space: SpaceMap, appearance_dim: usize, seed: u64) -> (CaptureField, ParamLayout, Vec<f32>) {
    let mut layout = ParamLayout::default();
    let f = CaptureField::new(&mut layout, space, &config(appearance_dim));
    let mut rng = Rng::new(seed);
    let mut params = vec![0.0f32; layout.len];
    f.init(&mut params, &mut rng);
    for p in params.iter_mut() {
        *p += 0.3 * rng.normal();
    }
    (f, layout, params)
}

/// `L = Σ gs σ + Σ gc rgb` of a density pass over `pos` with `image`, a
/// compaction to `keep`, and a colour pass along `dirs` (of the kept
/// samples); summed in f64.
struct Pass<'a> {
    pos: &'a [f32],
    dirs: &'a [f32],
    image: &'a [u32],
    keep: &'a [usize],
    gs: &'a [f32],
    gc: &'a [f32],
}

impl Pass<'_> {
    fn run(&self, f: &CaptureField, params: &[f32], ctx: &mut Ctx) -> f64 {
        let all_dirs: Vec<f32> = vec![0.0; self.pos.len()];
        f.density(params, Points { pos: self.pos, dirs: &all_dirs, image: self.image }, ctx);
        f.compact(ctx, self.keep);
        f.color(params, self.dirs, ctx);
        f.sigma(ctx).iter().zip(self.gs).map(|(a, b)| *a as f64 * *b as f64).sum::<f64>()
            + f.rgb(ctx).iter().zip(self.gc).map(|(a, b)| *a as f64 * *b as f64).sum::<f64>()
    }
}

#[test]
fn parameter_gradients_match_finite_differences_in_f64() {
    for (k, space) in [SpaceMap::Contract { norm: Norm::Linf }, SpaceMap::Contract { norm: Norm::L2 }, test_ndc()]
        .into_iter()
        .enumerate()
    {
        let (f, layout, params) = field(space.clone(), 3, 5 + k as u64);
        let mut rng = Rng::new(40 + k as u64);
        let n = 9;
        let pos = points(&space, &mut rng, n);
        // Images 0, 2 and 3 (4 and 1 absent), and one beyond the table.
        let image = [2u32, 0, 2, 3, 7, 0, 3, 2, 0];
        let keep = [0usize, 1, 3, 4, 6, 7, 8];
        let dirs: Vec<f32> = (0..3 * keep.len()).map(|_| rng.normal()).collect();
        let gs: Vec<f32> = keep.iter().map(|_| rng.normal() * 0.3).collect();
        let gc: Vec<f32> = (0..3 * keep.len()).map(|_| rng.normal()).collect();
        let pass = Pass { pos: &pos, dirs: &dirs, image: &image, keep: &keep, gs: &gs, gc: &gc };
        let mut ctx = Ctx::default();
        pass.run(&f, &params, &mut ctx);
        let mut grads = vec![0.0f32; layout.len];
        f.backward(&params, &mut ctx, &gs, &gc, &mut grads);
        let mut checked = 0;
        let mut by_name = Vec::new();
        for (name, range) in &layout.names {
            let mut largest = 0.0f64;
            for i in range.clone() {
                let diff = |h: f32| {
                    let mut p = params.clone();
                    p[i] += h;
                    let fp = pass.run(&f, &p, &mut Ctx::default());
                    p[i] -= 2.0 * h;
                    let fm = pass.run(&f, &p, &mut Ctx::default());
                    (fp - fm) / (2.0 * h as f64)
                };
                let ana = grads[i] as f64;
                let close = |num: f64| (num - ana).abs() < 2e-3 + 2e-2 * num.abs();
                // A ReLU kink within the step spoils the wider difference;
                // the narrower one is then clear of it.
                let h = 1e-3f32 * (1.0 + params[i].abs());
                let num = diff(h);
                assert!(
                    close(num) || close(diff(0.25 * h)),
                    "{space:?} {name}[{}]: numeric {num} (and {} with a quarter step), analytic {ana}",
                    i - range.start,
                    diff(0.25 * h)
                );
                largest = largest.max(num.abs());
                checked += 1;
            }
            by_name.push((name.clone(), largest));
        }
        // Every range has gradients worth checking (no range passes by
        // being all zero on both sides).
        for (name, largest) in &by_name {
            assert!(*largest > 1e-2, "{space:?} {name}: every gradient is tiny ({largest})");
        }
        assert!(checked > 500, "{checked}");
        // The embeddings of absent images (1, 4) get exactly nothing.
        let a = f.appearance();
        for img in [1usize, 4] {
            assert!(grads[a.table.start + 3 * img..a.table.start + 3 * img + 3].iter().all(|&g| g == 0.0));
        }
    }
}

/// A sample of image `i` and the same sample rendered with image `i`'s
/// embedding as the view appearance have the same colour; without either,
/// the colour is the zero embedding's.
#[test]
fn the_view_appearance_is_the_images_appearance() {
    let space = SpaceMap::Contract { norm: Norm::Linf };
    let (f, _, params) = field(space.clone(), 3, 9);
    let mut rng = Rng::new(2);
    let pos = points(&space, &mut rng, 4);
    let dirs: Vec<f32> = (0..12).map(|_| rng.normal()).collect();
    let colours = |image: &[u32], view: Option<&[f32]>| {
        let mut ctx = Ctx::default();
        f.set_view_appearance(&params, view, &mut ctx);
        f.density(&params, Points { pos: &pos, dirs: &dirs, image }, &mut ctx);
        f.color(&params, &dirs, &mut ctx);
        (f.sigma(&ctx).to_vec(), f.rgb(&ctx).to_vec())
    };
    let e3 = f.appearance().embedding(&params, 3).unwrap().to_vec();
    let (s_img, c_img) = colours(&[3; 4], None);
    let (s_view, c_view) = colours(&[], Some(&e3));
    assert_eq!(s_img, s_view, "appearance does not change density");
    for (a, b) in c_img.iter().zip(&c_view) {
        assert!((a - b).abs() < 1e-6, "{c_img:?} vs {c_view:?}");
    }
    let (_, c_other) = colours(&[1; 4], None);
    assert!(c_other.iter().zip(&c_img).any(|(a, b)| (a - b).abs() > 1e-3), "images look different");
    // No image and no view appearance: the zero embedding (an image beyond the table).
    let (_, c_none) = colours(&[], None);
    let (_, c_beyond) = colours(&[99; 4], None);
    assert_eq!(c_none, c_beyond);
    // A wrong-sized embedding is ignored rather than read out of bounds.
    let (_, c_bad) = colours(&[], Some(&[1.0; 7]));
    assert_eq!(c_bad, c_none);

    // `color_rows` colours saved rows as `color` does, with the view appearance.
    let mut ctx = Ctx::default();
    f.set_view_appearance(&params, Some(&e3), &mut ctx);
    f.density(&params, Points { pos: &pos, dirs: &dirs, image: &[] }, &mut ctx);
    let mut rows = Vec::new();
    for i in 0..4 {
        f.save_row(&ctx, i, &mut rows);
    }
    f.color_rows(&params, rows, &dirs, &mut ctx);
    assert_eq!(f.rgb(&ctx), &c_view[..]);
}

#[test]
fn an_untrained_network_has_the_initial_density_and_ndc_selects_its_frustum() {
    let mut layout = ParamLayout::default();
    let f = CaptureField::new(&mut layout, test_ndc(), &config(2));
    let params = vec![0.0f32; layout.len];
    let mut ctx = Ctx::default();
    // In front of the camera; behind it; beside the frustum.
    let pos = [0.0, 0.0, -2.0, 0.0, 0.0, 3.0, 50.0, 0.0, -2.0];
    f.density(&params, Points { pos: &pos, dirs: &[0.0; 9], image: &[] }, &mut ctx);
    assert_eq!(f.sigma(&ctx), &[0.3, 0.0, 0.0]);
    // Outside points get no gradient either.
    let (f, layout, params) = field(test_ndc(), 2, 4);
    let mut ctx = Ctx::default();
    f.density(&params, Points { pos: &pos[3..], dirs: &[0.0; 6], image: &[0, 1] }, &mut ctx);
    f.color(&params, &[0.0, 0.0, 1.0, 0.0, 1.0, 0.0], &mut ctx);
    let mut grads = vec![0.0f32; layout.len];
    f.backward(&params, &mut ctx, &[1.0, 1.0], &[0.0; 6], &mut grads);
    assert!(grads.iter().all(|&g| g == 0.0), "density gradient outside the frustum");
}
