//! The fast model's field (Instant-NGP): a multiresolution hash grid over
//! the scene box, a tiny density MLP whose first output is log-density and
//! the rest geometry features, and a tiny colour MLP on those features and
//! the spherical-harmonics encoding of the direction.

use super::size;
use super::{Field, Points};
use crate::engine::geometry::math::Vec3;
use crate::engine::nn::hashgrid::{HashGrid, HashGridConfig};
use crate::engine::nn::linear::{Linear, ParamLayout, relu, relu_backward, sigmoid};
use crate::engine::nn::move_rows;
use crate::engine::nn::sh;
use crate::engine::rng::Rng;

/// Density activation: `exp` of the clamped input (its derivative is the
/// density itself, which stays finite).
#[inline]
fn density(raw: f32) -> f32 {
    raw.clamp(-15.0, 15.0).exp()
}

/// The networks over a flat parameter buffer.
struct Nets {
    grid: HashGrid,
    d1: Linear,
    d2: Linear,
    c1: Linear,
    c2: Linear,
    c3: Linear,
}

/// Activations of a forward pass over `n` samples.
#[derive(Default)]
pub struct Ctx {
    n: usize,
    unit: Vec<f32>,
    enc: Vec<f32>,
    h1: Vec<f32>,
    geo: Vec<f32>,
    sigma: Vec<f32>,
    shd: Vec<f32>,
    a1: Vec<f32>,
    a2: Vec<f32>,
    rgb: Vec<f32>,
    // backward scratch
    d_a: Vec<f32>,
    d_b: Vec<f32>,
    d_geo: Vec<f32>,
    d_enc: Vec<f32>,
    // input gradients (`HashGridField::backward_with_input_grads` only)
    d_shd: Vec<f32>,
    d_pos: Vec<f32>,
    d_dirs: Vec<f32>,
}

impl Ctx {
    /// Drops the density-pass activations of samples not in `keep`.
    fn compact(&mut self, keep: &[usize], grid_width: usize, hidden: usize, geo: usize) {
        move_rows(&mut self.unit, 3, keep);
        move_rows(&mut self.enc, grid_width, keep);
        move_rows(&mut self.h1, hidden, keep);
        move_rows(&mut self.geo, geo, keep);
        move_rows(&mut self.sigma, 1, keep);
        self.n = keep.len();
    }
}

impl Nets {
    fn new(layout: &mut ParamLayout, grid: HashGridConfig, hidden: usize, geo: usize) -> Self {
        let grid = HashGrid::new(layout, grid);
        let d1 = Linear::new(layout, "density.0", grid.width(), hidden);
        let d2 = Linear::new(layout, "density.1", hidden, geo);
        let c1 = Linear::new(layout, "color.0", geo + sh::WIDTH, hidden);
        let c2 = Linear::new(layout, "color.1", hidden, hidden);
        let c3 = Linear::new(layout, "color.2", hidden, 3);
        Self { grid, d1, d2, c1, c2, c3 }
    }

    /// Density of `n` unit-cube points; keeps what backward needs.
    fn forward_density(&self, p: &[f32], ctx: &mut Ctx) {
        let n = ctx.n;
        let (gw, h, g) = (self.grid.width(), self.d1.outputs, self.d2.outputs);
        size(&mut ctx.enc, n * gw);
        self.grid.forward(p, &ctx.unit[..n * 3], &mut ctx.enc);
        size(&mut ctx.h1, n * h);
        self.d1.forward(p, &[(&ctx.enc, gw)], n, &mut ctx.h1);
        relu(&mut ctx.h1[..n * h]);
        size(&mut ctx.geo, n * g);
        self.d2.forward(p, &[(&ctx.h1, h)], n, &mut ctx.geo);
        size(&mut ctx.sigma, n);
        for (s, row) in ctx.sigma[..n].iter_mut().zip(ctx.geo.chunks_exact(g)) {
            *s = density(row[0]);
        }
    }

    /// Colour of the first `n` samples of the last density pass, seen along
    /// `dirs` (`[n x 3]`).
    fn forward_color(&self, p: &[f32], dirs: &[f32], ctx: &mut Ctx) {
        let n = ctx.n;
        let (h, g) = (self.c1.outputs, self.d2.outputs);
        size(&mut ctx.shd, n * sh::WIDTH);
        sh::encode(&dirs[..n * 3], &mut ctx.shd);
        size(&mut ctx.a1, n * h);
        self.c1.forward(p, &[(&ctx.geo, g), (&ctx.shd, sh::WIDTH)], n, &mut ctx.a1);
        relu(&mut ctx.a1[..n * h]);
        size(&mut ctx.a2, n * h);
        self.c2.forward(p, &[(&ctx.a1, h)], n, &mut ctx.a2);
        relu(&mut ctx.a2[..n * h]);
        size(&mut ctx.rgb, n * 3);
        self.c3.forward(p, &[(&ctx.a2, h)], n, &mut ctx.rgb);
        for v in &mut ctx.rgb[..n * 3] {
            *v = sigmoid(*v);
        }
    }

    /// Backward of both passes given dL/dsigma and dL/drgb. Given `dirs`
    /// (`[n x 3]`, the directions of the colour pass), also the input
    /// gradients: dL/du of the unit-cube points into `ctx.d_pos` and
    /// dL/d(direction) into `ctx.d_dirs`. Without, it makes exactly the calls
    /// it always made; with, the parameter gradients are the same.
    fn backward(
        &self,
        p: &[f32],
        ctx: &mut Ctx,
        dsigma: &[f32],
        drgb: &[f32],
        grads: &mut [f32],
        dirs: Option<&[f32]>,
    ) {
        let n = ctx.n;
        let (h, g, gw) = (self.c1.outputs, self.d2.outputs, self.grid.width());
        let draw: Vec<f32> = drgb[..n * 3].iter().zip(&ctx.rgb).map(|(&d, &s)| d * s * (1.0 - s)).collect();
        size(&mut ctx.d_a, n * h);
        self.c3.backward(p, &[(&ctx.a2, h)], &draw, n, grads, &mut [Some(&mut ctx.d_a)]);
        relu_backward(&ctx.a2[..n * h], &mut ctx.d_a[..n * h]);
        size(&mut ctx.d_b, n * h);
        self.c2.backward(p, &[(&ctx.a1, h)], &ctx.d_a, n, grads, &mut [Some(&mut ctx.d_b)]);
        relu_backward(&ctx.a1[..n * h], &mut ctx.d_b[..n * h]);
        size(&mut ctx.d_geo, n * g);
        let d_shd = match dirs {
            Some(_) => {
                size(&mut ctx.d_shd, n * sh::WIDTH);
                Some(&mut ctx.d_shd[..])
            }
            None => None,
        };
        self.c1.backward(
            p,
            &[(&ctx.geo, g), (&ctx.shd, sh::WIDTH)],
            &ctx.d_b,
            n,
            grads,
            &mut [Some(&mut ctx.d_geo), d_shd],
        );
        for ((row, &ds), &s) in ctx.d_geo.chunks_exact_mut(g).zip(dsigma).zip(&ctx.sigma) {
            row[0] += ds * s;
        }
        size(&mut ctx.d_a, n * h);
        self.d2.backward(p, &[(&ctx.h1, h)], &ctx.d_geo, n, grads, &mut [Some(&mut ctx.d_a)]);
        relu_backward(&ctx.h1[..n * h], &mut ctx.d_a[..n * h]);
        size(&mut ctx.d_enc, n * gw);
        self.d1.backward(p, &[(&ctx.enc, gw)], &ctx.d_a, n, grads, &mut [Some(&mut ctx.d_enc)]);
        let Some(dirs) = dirs else {
            self.grid.backward(&ctx.unit[..n * 3], &ctx.d_enc, grads);
            return;
        };
        size(&mut ctx.d_pos, n * 3);
        self.grid.backward_with_input_grad(p, &ctx.unit[..n * 3], &ctx.d_enc, grads, &mut ctx.d_pos);
        ctx.d_dirs.clear();
        ctx.d_dirs.resize(n * 3, 0.0);
        sh::encode_backward(&dirs[..n * 3], &ctx.d_shd[..n * sh::WIDTH], &mut ctx.d_dirs);
    }
}

/// The hash-grid field over a box of model space (mapped to the unit cube
/// the grid covers).
pub struct HashGridField {
    nets: Nets,
    lo: Vec3,
    inv: Vec3,
}

impl HashGridField {
    /// Lays out the field's parameters in `layout`: the hash grid, then
    /// `density.0-1` and `color.0-2`.
    pub fn new(
        layout: &mut ParamLayout,
        grid: HashGridConfig,
        hidden: usize,
        geo_features: usize,
        aabb: (Vec3, Vec3),
    ) -> Self {
        let nets = Nets::new(layout, grid, hidden, geo_features);
        let (lo, hi) = aabb;
        let ext = hi - lo;
        Self { nets, lo, inv: Vec3::new(1.0 / ext.x, 1.0 / ext.y, 1.0 / ext.z) }
    }

    /// Initialises the field's ranges of `params`.
    pub fn init(&self, params: &mut [f32], rng: &mut Rng) {
        let n = &self.nets;
        n.grid.init(params, rng);
        for l in [&n.d1, &n.d2, &n.c1, &n.c2, &n.c3] {
            l.init(params, rng);
        }
    }

    /// [`Field::backward`] (the same parameter gradients), and also the
    /// gradients with respect to the inputs of the last density pass (after
    /// any [`Field::compact`]) and colour pass: read them with
    /// [`HashGridField::input_grads`]. `dirs` are the directions the colour
    /// pass was given (`[n x 3]`). Not for colours from
    /// [`Field::color_rows`], which keep no positions.
    ///
    /// The positions' gradient flows through both outputs: the density and
    /// the colour's geometry features both come from the hash grid
    /// ([`HashGrid::backward_with_input_grad`]), then through the box map
    /// `u = (x - lo) / (hi - lo)`. The directions' gradient comes from the
    /// colour network's spherical-harmonics input ([`sh::encode_backward`]).
    pub fn backward_with_input_grads(
        &self,
        params: &[f32],
        ctx: &mut Ctx,
        dirs: &[f32],
        dsigma: &[f32],
        drgb: &[f32],
        grads: &mut [f32],
    ) {
        self.nets.backward(params, ctx, dsigma, drgb, grads, Some(dirs));
        let inv = self.inv;
        for d in ctx.d_pos[..3 * ctx.n].chunks_exact_mut(3) {
            d[0] *= inv.x;
            d[1] *= inv.y;
            d[2] *= inv.z;
        }
    }

    /// dL/d(position) (model space) and dL/d(direction), `[n x 3]` each, of
    /// the last [`HashGridField::backward_with_input_grads`].
    pub fn input_grads<'c>(&self, ctx: &'c Ctx) -> (&'c [f32], &'c [f32]) {
        (&ctx.d_pos[..3 * ctx.n], &ctx.d_dirs[..3 * ctx.n])
    }
}

impl Field for HashGridField {
    type Ctx = Ctx;

    fn density(&self, params: &[f32], pts: Points<'_>, ctx: &mut Ctx) {
        let (lo, inv) = (self.lo, self.inv);
        ctx.unit.clear();
        for q in pts.pos.chunks_exact(3) {
            let p = Vec3::new(q[0], q[1], q[2]) - lo;
            ctx.unit.extend_from_slice(&[p.x * inv.x, p.y * inv.y, p.z * inv.z]);
        }
        ctx.n = pts.pos.len() / 3;
        self.nets.forward_density(params, ctx);
    }

    fn compact(&self, ctx: &mut Ctx, keep: &[usize]) {
        let n = &self.nets;
        ctx.compact(keep, n.grid.width(), n.d1.outputs, n.d2.outputs);
    }

    fn color(&self, params: &[f32], dirs: &[f32], ctx: &mut Ctx) {
        self.nets.forward_color(params, dirs, ctx);
    }

    fn sigma<'c>(&self, ctx: &'c Ctx) -> &'c [f32] {
        &ctx.sigma[..ctx.n]
    }

    fn rgb<'c>(&self, ctx: &'c Ctx) -> &'c [f32] {
        &ctx.rgb[..3 * ctx.n]
    }

    fn save_row(&self, ctx: &Ctx, i: usize, rows: &mut Vec<f32>) {
        let g = self.nets.d2.outputs;
        rows.extend_from_slice(&ctx.geo[i * g..(i + 1) * g]);
    }

    fn color_rows(&self, params: &[f32], rows: Vec<f32>, dirs: &[f32], ctx: &mut Ctx) {
        ctx.n = dirs.len() / 3;
        ctx.geo = rows;
        self.nets.forward_color(params, dirs, ctx);
    }

    fn backward(&self, params: &[f32], ctx: &mut Ctx, dsigma: &[f32], drgb: &[f32], grads: &mut [f32]) {
        self.nets.backward(params, ctx, dsigma, drgb, grads, None);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn network_gradients_match_finite_differences_in_f64() {
        // Compare the analytic gradient of sum(sigma*gs + rgb*gc) with central
        // differences of the same f32 forward evaluated in f64 accumulation:
        // the network is evaluated with tiny perturbations on a small config,
        // so we use a relative tolerance suited to f32 forward passes.
        let grid = HashGridConfig { levels: 3, log2_table: 6, base_resolution: 2, finest_resolution: 8 };
        let mut layout = ParamLayout::default();
        let nets = Nets::new(&mut layout, grid, 8, 4);
        let mut rng = Rng::new(5);
        let mut params = vec![0.0f32; layout.len];
        for l in [&nets.d1, &nets.d2, &nets.c1, &nets.c2, &nets.c3] {
            l.init(&mut params, &mut rng);
        }
        for p in params.iter_mut() {
            *p += 0.3 * rng.normal();
        }
        let n = 4;
        let unit: Vec<f32> = (0..n * 3).map(|_| rng.f32()).collect();
        let dirs: Vec<f32> = (0..n).flat_map(|i| [0.6f32, 0.1 * i as f32, 0.8]).collect();
        let gs: Vec<f32> = (0..n).map(|_| rng.normal() * 0.1).collect();
        let gc: Vec<f32> = (0..n * 3).map(|_| rng.normal()).collect();
        let run = |p: &[f32]| -> (f64, Ctx) {
            let mut c = Ctx { n, unit: unit.clone(), ..Default::default() };
            nets.forward_density(p, &mut c);
            nets.forward_color(p, &dirs, &mut c);
            let v = c.sigma.iter().zip(&gs).map(|(a, b)| *a as f64 * *b as f64).sum::<f64>()
                + c.rgb.iter().zip(&gc).map(|(a, b)| *a as f64 * *b as f64).sum::<f64>();
            (v, c)
        };
        let (_, mut c) = run(&params);
        let mut grads = vec![0.0f32; layout.len];
        nets.backward(&params, &mut c, &gs, &gc, &mut grads, None);
        let mut checked = 0;
        for (name, range) in &layout.names {
            for i in range.clone() {
                let h = 1e-3f32 * (1.0 + params[i].abs());
                let mut p = params.clone();
                p[i] += h;
                let fp = run(&p).0;
                p[i] -= 2.0 * h;
                let fm = run(&p).0;
                let num = (fp - fm) / (2.0 * h as f64);
                let ana = grads[i] as f64;
                assert!((num - ana).abs() < 2e-3 + 2e-2 * num.abs(), "{name}[{i}]: numeric {num}, analytic {ana}");
                checked += 1;
            }
        }
        assert!(checked > 200);
    }

    /// Random points of the box `lo..hi` whose unit-cube coordinates keep
    /// `margin` cells clear of the cell faces of every resolution up to
    /// `max_res` (the hash grid's derivative jumps on faces).
    fn points_off_faces(rng: &mut Rng, count: usize, lo: Vec3, hi: Vec3, max_res: u32, margin: f32) -> Vec<f32> {
        let mut pts = Vec::with_capacity(3 * count);
        while pts.len() < 3 * count {
            let u = [rng.f32(), rng.f32(), rng.f32()];
            let clear = (1..=max_res).all(|r| {
                u.iter().all(|&v| {
                    let x = v * r as f32;
                    (x - x.round()).abs() > margin
                })
            });
            if clear {
                let (lo, ext) = (lo.to_array(), (hi - lo).to_array());
                pts.extend((0..3).map(|a| lo[a] + u[a] * ext[a]));
            }
        }
        pts
    }

    /// dL/dx and dL/d(direction) of `L = Σ gs σ + Σ gc rgb` through the whole
    /// field (density, compaction, colour) against central differences of
    /// its f32 forward passes; the parameter gradients stay `backward`'s.
    #[test]
    fn input_gradients_through_the_field_match_finite_differences() {
        let grid = HashGridConfig { levels: 3, log2_table: 6, base_resolution: 2, finest_resolution: 8 };
        // A box that is not a cube, so the box map's scales matter.
        let (lo, hi) = (Vec3::new(-1.0, -2.0, -0.5), Vec3::new(1.0, 2.0, 1.5));
        let mut layout = ParamLayout::default();
        let field = HashGridField::new(&mut layout, grid, 8, 4, (lo, hi));
        let mut rng = Rng::new(7);
        let mut params = vec![0.0f32; layout.len];
        field.init(&mut params, &mut rng);
        for p in params.iter_mut() {
            *p += 0.3 * rng.normal();
        }
        let n = 7;
        let pos = points_off_faces(&mut rng, n, lo, hi, 8, 0.05);
        let dirs: Vec<f32> = (0..3 * n).map(|_| rng.normal()).collect();
        let keep = [0usize, 2, 3, 5, 6];
        let kept_dirs: Vec<f32> = keep.iter().flat_map(|&i| dirs[3 * i..3 * i + 3].to_vec()).collect();
        let gs: Vec<f32> = keep.iter().map(|_| rng.normal() * 0.1).collect();
        let gc: Vec<f32> = (0..3 * keep.len()).map(|_| rng.normal()).collect();
        let run = |pos: &[f32], kd: &[f32]| -> (f64, Ctx) {
            let mut ctx = Ctx::default();
            field.density(&params, Points { pos, dirs: &dirs, image: &[] }, &mut ctx);
            field.compact(&mut ctx, &keep);
            field.color(&params, kd, &mut ctx);
            let v = field.sigma(&ctx).iter().zip(&gs).map(|(a, b)| *a as f64 * *b as f64).sum::<f64>()
                + field.rgb(&ctx).iter().zip(&gc).map(|(a, b)| *a as f64 * *b as f64).sum::<f64>();
            (v, ctx)
        };
        let (_, mut ctx) = run(&pos, &kept_dirs);
        let mut grads = vec![0.0f32; layout.len];
        field.backward_with_input_grads(&params, &mut ctx, &kept_dirs, &gs, &gc, &mut grads);
        let (dpos, ddirs) = field.input_grads(&ctx);
        assert_eq!((dpos.len(), ddirs.len()), (3 * keep.len(), 3 * keep.len()));

        let (_, mut plain) = run(&pos, &kept_dirs);
        let mut want = vec![0.0f32; layout.len];
        field.backward(&params, &mut plain, &gs, &gc, &mut want);
        assert!(grads.iter().zip(&want).all(|(a, b)| a.to_bits() == b.to_bits()), "parameter gradients differ");

        let h = 1e-3f32;
        let check = |what: &str, got: &[f32], input: &[f32], rows: &[usize], eval: &dyn Fn(&[f32]) -> f64| {
            let mut largest = 0.0f64;
            for (j, &i) in rows.iter().enumerate() {
                for a in 0..3 {
                    let (mut up, mut down) = (input.to_vec(), input.to_vec());
                    up[3 * i + a] += h;
                    down[3 * i + a] -= h;
                    let step = (up[3 * i + a] - down[3 * i + a]) as f64;
                    let num = (eval(&up) - eval(&down)) / step;
                    let ana = got[3 * j + a] as f64;
                    largest = largest.max(num.abs());
                    assert!(
                        (num - ana).abs() < 2e-3 + 2e-2 * num.abs(),
                        "{what} of sample {i}, axis {a}: numeric {num}, analytic {ana}"
                    );
                }
            }
            assert!(largest > 0.05, "{what}: every gradient is tiny ({largest})");
        };
        check("dL/dx", dpos, &pos, &keep, &|p| run(p, &kept_dirs).0);
        let all: Vec<usize> = (0..keep.len()).collect();
        check("dL/d(direction)", ddirs, &kept_dirs, &all, &|d| run(&pos, d).0);
    }
}
