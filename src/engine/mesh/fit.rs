//! The texture fitted to the views: starting from the bake, the texels
//! that, read as a viewer reads them (bilinear, at each view's pixel
//! centres on the rasterised mesh), give the colours the views show with
//! the least squared error, held near the bake where few pixels see them.
//! The bake colours a point from the views' pixels nearest to it; the fit
//! asks what a view of the mesh itself shows, including where the mesh's
//! surface is a little off the model's.

use rayon::prelude::*;

use crate::engine::mesh::raster::{finer, hits, uv_at};
use crate::engine::mesh::views::SurfaceView;
use crate::engine::mesh::{TexturedMesh, bilinear};

/// What the fit saw and did.
#[derive(Clone, Debug, PartialEq)]
pub struct FitStats {
    /// Pixels fitted (solid in their view and covered by the mesh).
    pub pixels: usize,
    /// Texels those pixels read.
    pub texels: usize,
    /// Root mean squared error over those pixels, before and after.
    pub before: f32,
    pub after: f32,
}

/// The mesh pixels of every view, as rows of a sparse matrix: the texels
/// each pixel's samples read and their weights (summing to one), and the
/// colour its view shows there.
#[derive(Default)]
struct Pixels {
    /// Row `r`'s entries are `start[r]..start[r + 1]`.
    start: Vec<usize>,
    texels: Vec<u32>,
    weights: Vec<f32>,
    colour: Vec<[f32; 3]>,
}

impl Pixels {
    fn empty() -> Self {
        Self { start: vec![0], ..Default::default() }
    }

    /// A row; a texel read by several of its samples becomes one entry.
    fn push(&mut self, entries: impl IntoIterator<Item = (u32, f32)>, colour: [f32; 3]) {
        let from = *self.start.last().expect("starts at 0");
        for (t, w) in entries {
            match self.texels[from..].iter().position(|&u| u == t) {
                Some(k) => self.weights[from + k] += w,
                None => {
                    self.texels.push(t);
                    self.weights.push(w);
                }
            }
        }
        self.start.push(self.texels.len());
        self.colour.push(colour);
    }

    fn rows(&self) -> impl Iterator<Item = (&[u32], &[f32], [f32; 3])> + '_ {
        self.rows_in(0..self.colour.len())
    }

    fn rows_in(&self, rows: std::ops::Range<usize>) -> impl Iterator<Item = (&[u32], &[f32], [f32; 3])> + '_ {
        rows.map(|r| {
            let e = self.start[r]..self.start[r + 1];
            (&self.texels[e.clone()], &self.weights[e], self.colour[r])
        })
    }

    fn append(&mut self, other: Pixels) {
        let base = self.texels.len();
        self.start.extend(other.start.iter().skip(1).map(|s| s + base));
        self.texels.extend(other.texels);
        self.weights.extend(other.weights);
        self.colour.extend(other.colour);
    }
}

/// How strongly the texture is held to its bake, against one pixel's
/// squared error (chosen by a sweep: docs/design/mesh.md).
pub const PRIOR: f32 = 0.3;
/// Samples a side for each pixel of a photo: a photo's pixel is the mean
/// of its area, and the mesh's viewers draw it antialiased.
pub const PHOTO_SAMPLES: u32 = 3;
/// Conjugate gradient iterations.
pub const ITERATIONS: usize = 30;

/// Fits `mesh`'s texture to `views`, in place, each pixel drawn as the
/// mean of `samples x samples` samples (1: at its centre, as a field's
/// render is; more where a view's pixels are an area's mean, as a photo's
/// are): the least squares over the views' pixels plus `prior` times the
/// squared change from the texture given, by `iterations` of
/// preconditioned conjugate gradients, clamped to [0, 1].
pub fn fit(mesh: &mut TexturedMesh, views: &[SurfaceView], samples: u32, prior: f32, iterations: usize) -> FitStats {
    let mut px = pixels(mesh, views, samples);
    // Only the texels some pixel reads take part; the rest keep their bake.
    let mut local = vec![u32::MAX; mesh.texture.len()];
    let mut global = Vec::new();
    for t in px.texels.iter_mut() {
        if local[*t as usize] == u32::MAX {
            local[*t as usize] = global.len() as u32;
            global.push(*t);
        }
        *t = local[*t as usize];
    }
    let start: Vec<[f32; 3]> = global.iter().map(|&g| mesh.texture[g as usize]).collect();
    let solved = solve(&px, &start, prior, iterations);
    let fitted: Vec<[f32; 3]> = solved.iter().map(|x| x.map(|v| v.clamp(0.0, 1.0))).collect();
    let stats =
        FitStats { pixels: px.colour.len(), texels: global.len(), before: rms(&px, &start), after: rms(&px, &fitted) };
    for (j, &g) in global.iter().enumerate() {
        mesh.texture[g as usize] = fitted[j];
    }
    stats
}

/// Every view's pixels that its view drew solid and the mesh covers (all
/// of their samples).
fn pixels(mesh: &TexturedMesh, views: &[SurfaceView], samples: u32) -> Pixels {
    let k = samples.max(1) as usize;
    let per_view: Vec<Pixels> = views
        .par_iter()
        .map(|view| {
            let mut out = Pixels::empty();
            let fine = hits(&mesh.positions, &mesh.triangles, &finer(&view.camera, k as u32));
            let w = view.camera.width as usize;
            for (i, solid) in view.surface.iter().enumerate() {
                let (x, y) = (i % w, i / w);
                let at = |j: usize| fine[(y * k + j / k) * w * k + x * k + j % k];
                if solid.is_none() || (0..k * k).any(|j| at(j).is_none()) {
                    continue;
                }
                let entries = (0..k * k).filter_map(at).flat_map(|(t, l)| {
                    let (u, v) = uv_at(mesh.uvs[t], l);
                    let (texels, weights) = bilinear(mesh.texture_size, u, v);
                    (0..4).map(move |n| (texels[n] as u32, weights[n] / (k * k) as f32))
                });
                out.push(entries, view.rgb[i]);
            }
            out
        })
        .collect();
    let mut all = Pixels::empty();
    per_view.into_iter().for_each(|p| all.append(p));
    all
}

/// Root mean squared error of the pixels read from `texture` (local texels).
fn rms(px: &Pixels, texture: &[[f32; 3]]) -> f32 {
    let n = px.colour.len().max(1) as f64;
    let sum: f64 = px
        .rows()
        .map(|(t, w, col)| {
            (0..3)
                .map(|c| {
                    let got: f32 = t.iter().zip(w).map(|(t, w)| w * texture[*t as usize][c]).sum();
                    ((got - col[c]) as f64).powi(2)
                })
                .sum::<f64>()
        })
        .sum();
    (sum / (3.0 * n)).sqrt() as f32
}

/// Minimises |A x - b|^2 + prior |x - x0|^2 from `x0`, each channel on
/// its own, with A the pixels' reads and b their colours (conjugate
/// gradients on the normal equations, Jacobi-preconditioned; the three
/// channels share A, so one pass over it serves all three).
fn solve(px: &Pixels, x0: &[[f32; 3]], prior: f32, iterations: usize) -> Vec<[f32; 3]> {
    let n = x0.len();
    let chunk = px.colour.len().div_ceil(rayon::current_num_threads().max(1)).max(1);
    // (A^T A + prior I) x, the rows split between the threads.
    let apply = |x: &[[f32; 3]]| {
        let parts: Vec<Vec<[f32; 3]>> = (0..px.colour.len())
            .step_by(chunk)
            .collect::<Vec<_>>()
            .into_par_iter()
            .map(|from| {
                let mut y = vec![[0.0f32; 3]; n];
                for (t, w, _) in px.rows_in(from..(from + chunk).min(px.colour.len())) {
                    let mut r = [0.0f32; 3];
                    t.iter().zip(w).for_each(|(t, w)| (0..3).for_each(|c| r[c] += w * x[*t as usize][c]));
                    t.iter().zip(w).for_each(|(t, w)| (0..3).for_each(|c| y[*t as usize][c] += w * r[c]));
                }
                y
            })
            .collect();
        let mut y: Vec<[f32; 3]> = x.iter().map(|v| v.map(|v| prior * v)).collect();
        for part in parts {
            y.iter_mut().zip(part).for_each(|(y, p)| (0..3).for_each(|c| y[c] += p[c]));
        }
        y
    };
    let mut diag = vec![prior; n];
    let mut rhs: Vec<[f32; 3]> = x0.iter().map(|v| v.map(|v| prior * v)).collect();
    for (t, w, col) in px.rows() {
        for (a, wa) in t.iter().zip(w) {
            diag[*a as usize] += wa * wa;
            (0..3).for_each(|c| rhs[*a as usize][c] += wa * col[c]);
        }
    }
    let precondition =
        |r: &[[f32; 3]]| -> Vec<[f32; 3]> { r.iter().zip(&diag).map(|(r, d)| r.map(|v| v / d.max(1e-12))).collect() };
    let mut x = x0.to_vec();
    let ax = apply(&x);
    let mut r: Vec<[f32; 3]> = rhs.iter().zip(&ax).map(|(b, a)| [0, 1, 2].map(|c| b[c] - a[c])).collect();
    let mut z = precondition(&r);
    let mut p = z.clone();
    let mut rz = dot3(&r, &z);
    for _ in 0..iterations {
        let ap = apply(&p);
        let pap = dot3(&p, &ap);
        // A channel that has converged (or has nothing to fit) stays put.
        let alpha = [0, 1, 2].map(|c| if rz[c] > 0.0 && pap[c] > 0.0 { (rz[c] / pap[c]) as f32 } else { 0.0 });
        for i in 0..n {
            (0..3).for_each(|c| {
                x[i][c] += alpha[c] * p[i][c];
                r[i][c] -= alpha[c] * ap[i][c];
            });
        }
        z = precondition(&r);
        let next = dot3(&r, &z);
        let beta = [0, 1, 2].map(|c| if rz[c] > 0.0 { (next[c] / rz[c]) as f32 } else { 0.0 });
        p.iter_mut().zip(&z).for_each(|(p, z)| (0..3).for_each(|c| p[c] = z[c] + beta[c] * p[c]));
        rz = next;
    }
    x
}

/// Per channel, the dot product of two fields of colours, in f64.
fn dot3(a: &[[f32; 3]], b: &[[f32; 3]]) -> [f64; 3] {
    let mut s = [0.0f64; 3];
    for (x, y) in a.iter().zip(b) {
        (0..3).for_each(|c| s[c] += x[c] as f64 * y[c] as f64);
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::geometry::camera::{Camera, look_at};
    use crate::engine::geometry::math::Vec3;
    use crate::engine::mesh::atlas::layout;
    use crate::engine::mesh::raster::render;

    /// A smooth paint on the plane z = 0 (a bilinear texture holds it).
    fn paint(p: Vec3) -> [f32; 3] {
        [0.5 + 0.4 * p.x, 0.5 - 0.3 * p.y, 0.2 + 0.2 * p.x * p.y]
    }

    fn camera(eye: Vec3, size: u32) -> Camera {
        Camera::from_fov(size, size, 1.0, look_at(eye, Vec3::splat(0.0), Vec3::new(0.0, 1.0, 0.0)).unwrap())
    }

    /// The plane's view from `eye`, solid and painted wherever its rays meet it.
    fn plane_view(eye: Vec3) -> SurfaceView {
        crate::engine::mesh::views::plane_view(camera(eye, 40), &paint)
    }

    /// The square of side 2 at z = 0, two triangles, a grey `size` texture.
    fn square(size: u32) -> TexturedMesh {
        let atlas = layout(3, size).unwrap();
        TexturedMesh {
            // A third triangle far behind the views: no pixel reads its texels.
            positions: vec![
                [-1.0, -1.0, 0.0],
                [1.0, -1.0, 0.0],
                [1.0, 1.0, 0.0],
                [-1.0, 1.0, 0.0],
                [50.0, 0.0, -1.0],
                [51.0, 0.0, -1.0],
                [50.0, 1.0, -1.0],
            ],
            triangles: vec![[0, 1, 2], [0, 2, 3], [4, 5, 6]],
            uvs: atlas.uvs,
            texture: vec![[0.5; 3]; (size * size) as usize],
            texture_size: size,
        }
    }

    #[test]
    fn a_grey_square_fits_its_views_paint_and_shows_it_from_a_new_view() {
        for samples in [1, 3] {
            let mut mesh = square(16);
            let views =
                [Vec3::new(0.2, 0.1, 2.5), Vec3::new(-0.5, 0.3, 2.2), Vec3::new(0.4, -0.6, 2.4)].map(plane_view);
            let stats = fit(&mut mesh, &views, samples, 1e-3, 200);
            assert!(stats.before > 0.1 && stats.after < 0.005, "{stats:?}");
            // The third triangle's texels (the second cell's upper left) keep their grey.
            assert!(stats.texels > 0 && (0..8).all(|y| mesh.texture[y * 16 + 8] == [0.5; 3]));
            // A view none was fitted to shows the paint.
            let cam = camera(Vec3::new(0.1, -0.2, 2.0), 40);
            let drawn = render(&mesh, &cam, [0.0; 3]);
            let mut checked = 0;
            for i in 0..40 * 40 {
                let r = cam.pixel_ray(i % 40, i / 40);
                let p = r.at(-r.origin.z / r.dir.z);
                if p.x.abs() > 0.8 || p.y.abs() > 0.8 {
                    continue; // near the edges the views' pixels are few
                }
                let want = paint(p);
                let got = &drawn.rgb[3 * i as usize..3 * i as usize + 3];
                assert!((0..3).all(|k| (got[k] - want[k]).abs() < 0.02), "pixel {i} at {p:?}: {got:?}, want {want:?}");
                checked += 1;
            }
            assert!(checked > 400, "{checked} pixels checked");
        }
    }

    /// The normal equations solved directly in f64 (Gauss-Jordan).
    fn direct(px: &Pixels, c: usize, x0: &[f32], prior: f64) -> Vec<f64> {
        let n = x0.len();
        let mut m = vec![vec![0.0f64; n + 1]; n];
        for (j, row) in m.iter_mut().enumerate() {
            row[j] = prior;
            row[n] = prior * x0[j] as f64;
        }
        for (t, w, col) in px.rows() {
            for (a, wa) in t.iter().zip(w) {
                for (b, wb) in t.iter().zip(w) {
                    m[*a as usize][*b as usize] += *wa as f64 * *wb as f64;
                }
                m[*a as usize][n] += *wa as f64 * col[c] as f64;
            }
        }
        for k in 0..n {
            let p = m[k][k];
            let pivot = m[k].clone();
            for (i, row) in m.iter_mut().enumerate() {
                if i != k {
                    let f = row[k] / p;
                    row.iter_mut().zip(&pivot).for_each(|(r, q)| *r -= f * q);
                }
            }
        }
        (0..n).map(|k| m[k][n] / m[k][k]).collect()
    }

    #[test]
    fn conjugate_gradients_reach_the_direct_least_squares_solution() {
        // 40 pixels of two samples each, reading 12 texels, pseudo-random.
        let mut s = 12345u64;
        let mut next = || {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (s >> 33) as f32 / (1u64 << 31) as f32
        };
        let mut px = Pixels::empty();
        for _ in 0..40 {
            // Two bilinear reads of 4 neighbours, some texels read twice.
            let first = [(next() * 9.0) as u32, (next() * 9.0) as u32];
            let entries: Vec<(u32, f32)> = first
                .iter()
                .flat_map(|&f| {
                    let (fx, fy) = (next(), next());
                    let w = [(1.0 - fx) * (1.0 - fy), fx * (1.0 - fy), (1.0 - fx) * fy, fx * fy];
                    (0..4).map(move |k| (f + k as u32, 0.5 * w[k]))
                })
                .collect();
            px.push(entries, [next(), next(), next()]);
        }
        let x0: Vec<[f32; 3]> = (0..12).map(|_| [next(), next(), next()]).collect();
        for prior in [0.01f32, 0.3, 3.0] {
            let got = solve(&px, &x0, prior, 60);
            for c in 0..3 {
                let channel: Vec<f32> = x0.iter().map(|v| v[c]).collect();
                let want = direct(&px, c, &channel, prior as f64);
                for (g, w) in got.iter().zip(&want) {
                    assert!((g[c] as f64 - w).abs() < 1e-3, "prior {prior}, channel {c}: {got:?} against {want:?}");
                }
            }
        }
    }
}
