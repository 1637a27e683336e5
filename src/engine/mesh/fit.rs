//! The texture fitted to the views: starting from the bake, the texels
//! that, read as a viewer reads them (bilinear, at each view's pixel
//! centres on the rasterised mesh), give the colours the views show with
//! the least squared error, held near the bake where few pixels see them.
//! The bake colours a point from the views' pixels nearest to it; the fit
//! asks what a view of the mesh itself shows, including where the mesh's
//! surface is a little off the model's.

use rayon::prelude::*;

use crate::engine::mesh::raster::hits;
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

/// The mesh pixels of every view: the four texels each reads and their
/// weights, and the colour its view shows there.
struct Pixels {
    texels: Vec<[u32; 4]>,
    weights: Vec<[f32; 4]>,
    colour: Vec<[f32; 3]>,
}

/// How strongly the texture is held to its bake, against one pixel's
/// squared error (chosen by a sweep: docs/design/mesh.md).
pub const PRIOR: f32 = 0.3;
/// Conjugate gradient iterations.
pub const ITERATIONS: usize = 30;

/// Fits `mesh`'s texture to `views`, in place: the least squares over
/// the views' pixels plus `prior` times the squared change from the
/// texture given, by `iterations` of preconditioned conjugate gradients,
/// clamped to [0, 1].
pub fn fit(mesh: &mut TexturedMesh, views: &[SurfaceView], prior: f32, iterations: usize) -> FitStats {
    let px = pixels(mesh, views);
    // Only the texels some pixel reads take part; the rest keep their bake.
    let mut local = vec![u32::MAX; mesh.texture.len()];
    let mut global = Vec::new();
    let texels: Vec<[u32; 4]> = px
        .texels
        .iter()
        .map(|t| {
            t.map(|g| {
                if local[g as usize] == u32::MAX {
                    local[g as usize] = global.len() as u32;
                    global.push(g);
                }
                local[g as usize]
            })
        })
        .collect();
    let px = Pixels { texels, ..px };
    let start: Vec<[f32; 3]> = global.iter().map(|&g| mesh.texture[g as usize]).collect();
    let solved: Vec<Vec<f32>> = (0..3)
        .into_par_iter()
        .map(|c| {
            let x0: Vec<f32> = start.iter().map(|s| s[c]).collect();
            solve(&px, c, &x0, prior, iterations)
        })
        .collect();
    let fitted: Vec<[f32; 3]> = (0..global.len()).map(|j| [0, 1, 2].map(|c| solved[c][j].clamp(0.0, 1.0))).collect();
    let stats =
        FitStats { pixels: px.colour.len(), texels: global.len(), before: rms(&px, &start), after: rms(&px, &fitted) };
    for (j, &g) in global.iter().enumerate() {
        mesh.texture[g as usize] = fitted[j];
    }
    stats
}

/// Every view's pixels that its model drew solid and the mesh covers.
fn pixels(mesh: &TexturedMesh, views: &[SurfaceView]) -> Pixels {
    let per_view: Vec<Pixels> = views
        .par_iter()
        .map(|v| {
            let mut out = Pixels { texels: Vec::new(), weights: Vec::new(), colour: Vec::new() };
            for (i, hit) in hits(&mesh.positions, &mesh.triangles, &v.camera).into_iter().enumerate() {
                let (Some((t, l)), Some(_)) = (hit, v.surface[i]) else { continue };
                let uv = mesh.uvs[t];
                let u = l[0] * uv[0][0] + l[1] * uv[1][0] + l[2] * uv[2][0];
                let w = l[0] * uv[0][1] + l[1] * uv[1][1] + l[2] * uv[2][1];
                let (at, wt) = bilinear(mesh.texture_size, u, w);
                out.texels.push(at.map(|a| a as u32));
                out.weights.push(wt);
                out.colour.push(v.rgb[i]);
            }
            out
        })
        .collect();
    let mut all = Pixels { texels: Vec::new(), weights: Vec::new(), colour: Vec::new() };
    for p in per_view {
        all.texels.extend(p.texels);
        all.weights.extend(p.weights);
        all.colour.extend(p.colour);
    }
    all
}

/// Root mean squared error of the pixels read from `texture` (local texels).
fn rms(px: &Pixels, texture: &[[f32; 3]]) -> f32 {
    let n = px.colour.len().max(1) as f64;
    let sum: f64 = (0..px.colour.len())
        .map(|i| {
            (0..3)
                .map(|c| {
                    let got: f32 = (0..4).map(|k| px.weights[i][k] * texture[px.texels[i][k] as usize][c]).sum();
                    ((got - px.colour[i][c]) as f64).powi(2)
                })
                .sum::<f64>()
        })
        .sum();
    (sum / (3.0 * n)).sqrt() as f32
}

/// Channel `c`: minimises |A x - b|^2 + prior |x - x0|^2 from `x0`, with
/// A the pixels' bilinear reads and b their colours (conjugate gradients
/// on the normal equations, Jacobi-preconditioned).
fn solve(px: &Pixels, c: usize, x0: &[f32], prior: f32, iterations: usize) -> Vec<f32> {
    let n = x0.len();
    // (A^T A + prior I) x
    let apply = |x: &[f32]| {
        let mut y: Vec<f32> = x.iter().map(|v| prior * v).collect();
        for (t, w) in px.texels.iter().zip(&px.weights) {
            let r: f32 = (0..4).map(|k| w[k] * x[t[k] as usize]).sum();
            (0..4).for_each(|k| y[t[k] as usize] += w[k] * r);
        }
        y
    };
    let mut diag = vec![prior; n];
    let mut rhs: Vec<f32> = x0.iter().map(|v| prior * v).collect();
    for ((t, w), col) in px.texels.iter().zip(&px.weights).zip(&px.colour) {
        for k in 0..4 {
            diag[t[k] as usize] += w[k] * w[k];
            rhs[t[k] as usize] += w[k] * col[c];
        }
    }
    let mut x = x0.to_vec();
    let ax = apply(&x);
    let mut r: Vec<f32> = rhs.iter().zip(&ax).map(|(b, a)| b - a).collect();
    let mut z: Vec<f32> = r.iter().zip(&diag).map(|(r, d)| r / d.max(1e-12)).collect();
    let mut p = z.clone();
    let mut rz: f64 = dot(&r, &z);
    for _ in 0..iterations {
        if rz <= 0.0 {
            break;
        }
        let ap = apply(&p);
        let pap = dot(&p, &ap);
        if pap <= 0.0 {
            break;
        }
        let alpha = (rz / pap) as f32;
        x.iter_mut().zip(&p).for_each(|(x, p)| *x += alpha * p);
        r.iter_mut().zip(&ap).for_each(|(r, a)| *r -= alpha * a);
        z = r.iter().zip(&diag).map(|(r, d)| r / d.max(1e-12)).collect();
        let rz_next = dot(&r, &z);
        let beta = (rz_next / rz) as f32;
        p.iter_mut().zip(&z).for_each(|(p, z)| *p = z + beta * *p);
        rz = rz_next;
    }
    x
}

fn dot(a: &[f32], b: &[f32]) -> f64 {
    a.iter().zip(b).map(|(x, y)| *x as f64 * *y as f64).sum()
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
        let camera = camera(eye, 40);
        let (mut surface, mut rgb) = (Vec::new(), Vec::new());
        for y in 0..40 {
            for x in 0..40 {
                let r = camera.pixel_ray(x, y);
                let t = -r.origin.z / r.dir.z;
                surface.push((t > 0.0).then_some(t));
                rgb.push(paint(r.at(t)));
            }
        }
        SurfaceView { camera, surface, rgb }
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
        let mut mesh = square(16);
        let views = [Vec3::new(0.2, 0.1, 2.5), Vec3::new(-0.5, 0.3, 2.2), Vec3::new(0.4, -0.6, 2.4)].map(plane_view);
        let stats = fit(&mut mesh, &views, 1e-3, 200);
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

    /// The normal equations solved directly in f64 (Gauss-Jordan).
    fn direct(px: &Pixels, c: usize, x0: &[f32], prior: f64) -> Vec<f64> {
        let n = x0.len();
        let mut m = vec![vec![0.0f64; n + 1]; n];
        for (j, row) in m.iter_mut().enumerate() {
            row[j] = prior;
            row[n] = prior * x0[j] as f64;
        }
        for ((t, w), col) in px.texels.iter().zip(&px.weights).zip(&px.colour) {
            for a in 0..4 {
                for b in 0..4 {
                    m[t[a] as usize][t[b] as usize] += w[a] as f64 * w[b] as f64;
                }
                m[t[a] as usize][n] += w[a] as f64 * col[c] as f64;
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
        // 40 pixels reading 4 of 12 texels each, pseudo-random.
        let mut s = 12345u64;
        let mut next = || {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (s >> 33) as f32 / (1u64 << 31) as f32
        };
        let mut px = Pixels { texels: Vec::new(), weights: Vec::new(), colour: Vec::new() };
        for _ in 0..40 {
            let first = (next() * 9.0) as u32;
            let (fx, fy) = (next(), next());
            px.texels.push([first, first + 1, first + 2, first + 3]);
            px.weights.push([(1.0 - fx) * (1.0 - fy), fx * (1.0 - fy), (1.0 - fx) * fy, fx * fy]);
            px.colour.push([next(), next(), next()]);
        }
        let x0: Vec<f32> = (0..12).map(|_| next()).collect();
        for prior in [0.01f32, 0.3, 3.0] {
            let want = direct(&px, 1, &x0, prior as f64);
            let got = solve(&px, 1, &x0, prior, 60);
            for (g, w) in got.iter().zip(&want) {
                assert!((*g as f64 - w).abs() < 1e-3, "prior {prior}: {got:?} against {want:?}");
            }
        }
    }
}
