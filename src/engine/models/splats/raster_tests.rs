//! The rasteriser against ground truth: an f64 reference that renders by
//! the module's rule pixel by pixel (no tiles, no sorting shortcuts),
//! analytic cases, finite differences of the reference for every
//! parameter of the backward, and a rotated camera with a rotated scene.

use super::backward::backward;
use super::gaussians::{Layout, SH_C0};
use super::raster::{DILATION, FRUSTUM_SLACK, Frame, MAX_ALPHA, RasterCamera, RasterOptions, forward};
use crate::engine::geometry::camera::{Camera, look_at};
use crate::engine::geometry::math::Vec3;
use crate::engine::geometry::scene::Scene;
use crate::engine::models::RenderOptions;
use crate::engine::rng::Rng;

/// The f64 reference: every pixel, every Gaussian sorted by camera depth.
fn reference(layout: &Layout, params: &[f64], cam: &RasterCamera, opt: &RasterOptions, bg: [f64; 3]) -> Vec<f64> {
    let (w, h) = (cam.width as usize, cam.height as usize);
    let n = layout.n;
    let k = layout.k;
    struct P {
        z: f64,
        m: [f64; 2],
        conic: [f64; 3],
        ext: [f64; 2],
        o: f64,
        rgb: [f64; 3],
    }
    let rot = cam.rot.map(|r| r.map(f64::from));
    let org = cam.origin.map(f64::from);
    let (fx, fy, cx, cy) = (cam.fx as f64, cam.fy as f64, cam.cx as f64, cam.cy as f64);
    let mut ps = Vec::new();
    for i in 0..n {
        let p = [params[3 * i], params[3 * i + 1], params[3 * i + 2]];
        let d = [p[0] - org[0], p[1] - org[1], p[2] - org[2]];
        let t: Vec<f64> = (0..3).map(|r| rot[r][0] * d[0] + rot[r][1] * d[1] + rot[r][2] * d[2]).collect();
        let o = 1.0 / (1.0 + (-params[10 * n + i]).exp());
        if t[2] <= opt.near as f64 || o < opt.min_alpha as f64 {
            continue;
        }
        let q = &params[6 * n + 4 * i..6 * n + 4 * i + 4];
        let qn = (q.iter().map(|v| v * v).sum::<f64>()).sqrt();
        let [qw, qx, qy, qz] = [q[0] / qn, q[1] / qn, q[2] / qn, q[3] / qn];
        let r = [
            [1.0 - 2.0 * (qy * qy + qz * qz), 2.0 * (qx * qy - qw * qz), 2.0 * (qx * qz + qw * qy)],
            [2.0 * (qx * qy + qw * qz), 1.0 - 2.0 * (qx * qx + qz * qz), 2.0 * (qy * qz - qw * qx)],
            [2.0 * (qx * qz - qw * qy), 2.0 * (qy * qz + qw * qx), 1.0 - 2.0 * (qx * qx + qy * qy)],
        ];
        let s: Vec<f64> = (0..3).map(|j| params[3 * n + 3 * i + j].exp()).collect();
        let mut sigma = [[0.0; 3]; 3];
        for a in 0..3 {
            for b in 0..3 {
                sigma[a][b] = (0..3).map(|j| r[a][j] * s[j] * s[j] * r[b][j]).sum();
            }
        }
        let lim_x = FRUSTUM_SLACK as f64 * 0.5 * w as f64 / fx;
        let lim_y = FRUSTUM_SLACK as f64 * 0.5 * h as f64 / fy;
        let (u, v) = ((t[0] / t[2]).clamp(-lim_x, lim_x), (t[1] / t[2]).clamp(-lim_y, lim_y));
        let j = [[fx / t[2], 0.0, -fx * u / t[2]], [0.0, fy / t[2], -fy * v / t[2]]];
        let mut tm = [[0.0; 3]; 2];
        for a in 0..2 {
            for b in 0..3 {
                tm[a][b] = (0..3).map(|c| j[a][c] * rot[c][b]).sum();
            }
        }
        let mut cov = [[0.0; 2]; 2];
        for a in 0..2 {
            for b in 0..2 {
                cov[a][b] = (0..3)
                    .flat_map(|c| (0..3).map(move |e| (c, e)))
                    .map(|(c, e)| tm[a][c] * sigma[c][e] * tm[b][e])
                    .sum();
            }
        }
        let (ca, cb, cc) = (cov[0][0] + DILATION as f64, cov[0][1], cov[1][1] + DILATION as f64);
        let det = ca * cc - cb * cb;
        if det <= 0.0 {
            continue;
        }
        let reach = if opt.min_alpha > 0.0 {
            (2.0 * (o / opt.min_alpha as f64).ln()).max(0.0).sqrt().min(opt.radius_sigmas as f64)
        } else {
            opt.radius_sigmas as f64
        };
        let dn = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        // The basis in f64, from the unit direction.
        let (x, y, z) = (d[0] / dn, d[1] / dn, d[2] / dn);
        let b64 = sh_basis64(x, y, z);
        let mut rgb = [0.5; 3];
        for jj in 0..k {
            for c in 0..3 {
                let v = if jj == 0 {
                    params[11 * n + 3 * i + c]
                } else {
                    params[14 * n + 3 * (k - 1) * i + 3 * (jj - 1) + c]
                };
                rgb[c] += b64[jj] * v;
            }
        }
        ps.push(P {
            z: t[2],
            m: [fx * t[0] / t[2] + cx, fy * t[1] / t[2] + cy],
            conic: [cc / det, -cb / det, ca / det],
            ext: [reach * ca.sqrt(), reach * cc.sqrt()],
            o,
            rgb: rgb.map(|v| v.max(0.0)),
        });
    }
    ps.sort_by(|a, b| a.z.total_cmp(&b.z));
    let mut img = vec![0.0; w * h * 3];
    for y in 0..h {
        for x in 0..w {
            let (px, py) = (x as f64 + 0.5, y as f64 + 0.5);
            let mut tr = 1.0;
            let mut c = [0.0; 3];
            for p in &ps {
                let (dx, dy) = (px - p.m[0], py - p.m[1]);
                if dx.abs() > p.ext[0] || dy.abs() > p.ext[1] {
                    continue;
                }
                let power = -0.5 * (p.conic[0] * dx * dx + p.conic[2] * dy * dy) - p.conic[1] * dx * dy;
                if power > 0.0 {
                    continue;
                }
                let a = (p.o * power.exp()).min(MAX_ALPHA as f64);
                if a < opt.min_alpha as f64 {
                    continue;
                }
                if tr * (1.0 - a) < opt.min_transmittance as f64 {
                    break;
                }
                for ch in 0..3 {
                    c[ch] += p.rgb[ch] * a * tr;
                }
                tr *= 1.0 - a;
            }
            for ch in 0..3 {
                img[3 * (y * w + x) + ch] = c[ch] + tr * bg[ch];
            }
        }
    }
    img
}

/// The real SH basis (degree 3) of a unit direction, in f64 (the 3DGS
/// paper's constants).
fn sh_basis64(x: f64, y: f64, z: f64) -> [f64; 16] {
    let (xx, yy, zz) = (x * x, y * y, z * z);
    [
        0.28209479177387814,
        -0.4886025119029199 * y,
        0.4886025119029199 * z,
        -0.4886025119029199 * x,
        1.0925484305920792 * x * y,
        -1.0925484305920792 * y * z,
        0.31539156525252005 * (2.0 * zz - xx - yy),
        -1.0925484305920792 * x * z,
        0.5462742152960396 * (xx - yy),
        -0.5900435899266435 * y * (3.0 * xx - yy),
        2.890611442640554 * x * y * z,
        -0.4570457994644658 * y * (4.0 * zz - xx - yy),
        0.3731763325901154 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
        -0.4570457994644658 * x * (4.0 * zz - xx - yy),
        1.445305721320277 * z * (xx - yy),
        -0.5900435899266435 * x * (xx - 3.0 * yy),
    ]
}

/// A camera `dist` from the origin looking at it from `eye_dir`, `w x h`.
pub(super) fn camera(eye: [f32; 3], w: u32, h: u32, fov_deg: f32) -> Camera {
    let c2w = look_at(Vec3::from_array(eye), Vec3::splat(0.0), Vec3::new(0.0, 0.0, 1.0)).unwrap();
    Camera::from_fov(w, h, fov_deg.to_radians(), c2w)
}

pub(super) fn unit_scene() -> Scene {
    Scene::from_bounds(crate::engine::geometry::math::Aabb { min: Vec3::splat(-1.0), max: Vec3::splat(1.0) }, 0.0, 10.0)
}

/// `n` random Gaussians near the origin, inside the view of
/// [`camera`]`([0, -4, 0.5], ..)`.
pub(super) fn random_gaussians(n: usize, degree: u32, seed: u64, max_opacity: f32) -> (Layout, Vec<f32>) {
    let l = Layout::new(n, degree);
    let mut rng = Rng::new(seed);
    let mut p = vec![0.0f32; l.len()];
    for i in 0..n {
        for c in 0..3 {
            p[3 * i + c] = (rng.f32() - 0.5) * 1.2;
            p[3 * n + 3 * i + c] = -2.2 + 0.8 * rng.f32();
        }
        for c in 0..4 {
            p[6 * n + 4 * i + c] = rng.normal();
        }
        let o = 0.2 + (max_opacity - 0.2) * rng.f32();
        p[10 * n + i] = (o / (1.0 - o)).ln();
        for c in 0..3 {
            p[11 * n + 3 * i + c] = 1.5 * (rng.f32() - 0.3);
        }
        for j in 1..l.k {
            for c in 0..3 {
                p[14 * n + 3 * (l.k - 1) * i + 3 * (j - 1) + c] = 0.25 * rng.normal();
            }
        }
    }
    (l, p)
}

#[test]
fn forward_matches_the_f64_reference() {
    let scene = unit_scene();
    let cam = RasterCamera::new(&camera([0.3, -4.0, 0.8], 61, 47, 40.0), &scene);
    // The last (`stops`): so many nearly opaque Gaussians that whole tiles
    // stop taking them before their lists end.
    let cases = [(0, 40, 1, 0.95, false), (3, 120, 2, 0.95, false), (1, 300, 3, 0.95, false), (1, 1500, 4, 0.99, true)];
    for (degree, n, seed, most, stops) in cases {
        let (l, p) = random_gaussians(n, degree, seed, most);
        let opt = RasterOptions::default();
        let bg = [0.2, 0.5, 0.9];
        let f = forward(&l, &p, &cam, &opt, bg);
        let r = reference(&l, &p.iter().map(|&v| v as f64).collect::<Vec<_>>(), &cam, &opt, bg.map(f64::from));
        let diffs: Vec<f64> = f.rgb.iter().zip(&r).map(|(a, b)| (*a as f64 - b).abs()).collect();
        let max = diffs.iter().cloned().fold(0.0, f64::max);
        let mean = diffs.iter().sum::<f64>() / diffs.len() as f64;
        // f32 rounding; a pixel on the edge of a threshold (min_alpha, a
        // box's edge) may take a Gaussian in one and not the other, by at
        // most min_alpha of a colour.
        let over = diffs.iter().filter(|&&d| d > 1e-4).count();
        assert!(
            mean < 2e-5 && over * 200 <= diffs.len() && max < 0.02,
            "degree {degree}: mean {mean}, max {max}, {over} over"
        );
        assert!(f.opacity.iter().any(|&o| o > 0.5), "the scene is in view");
        if stops {
            // A tile all of whose pixels stopped well before its list's end.
            let stopped = (0..f.tile_ranges.len()).any(|t| {
                let [x0, x1, y0, y1] = crate::engine::models::splats::tile::tile_rect(&cam, t);
                let end = f.tile_ranges[t].len() as u32;
                (y0..y1)
                    .all(|y| (x0..x1).all(|x| f.final_t[y * f.width + x] < 1e-3 && f.last[y * f.width + x] + 50 < end))
            });
            assert!(stopped, "no tile stopped early");
        }
    }
}

#[test]
fn one_gaussians_footprint_is_the_analytic_one() {
    // An isotropic Gaussian of scale s at distance z on the axis: on the
    // image, a Gaussian of variance (f s / z)^2 + DILATION around the
    // principal point.
    let scene = unit_scene();
    let c = camera([0.0, -4.0, 0.0], 64, 64, 50.0);
    let cam = RasterCamera::new(&c, &scene);
    let l = Layout::new(1, 0);
    let s = 0.05f32;
    let o = 0.8f32;
    let mut p = vec![0.0; l.len()];
    p[3..6].copy_from_slice(&[s.ln(); 3]);
    p[6] = 1.0;
    p[10] = (o / (1.0 - o)).ln();
    let colour = [0.9f32, 0.3, 0.1];
    for ch in 0..3 {
        p[11 + ch] = (colour[ch] - 0.5) / SH_C0;
    }
    let opt = RasterOptions { min_alpha: 0.0, ..Default::default() };
    let bg = [0.0, 0.0, 1.0];
    let f = forward(&l, &p, &cam, &opt, bg);
    let var = (c.fx * s / 4.0).powi(2) + DILATION;
    let mut checked = 0;
    for y in 0..64 {
        for x in 0..64 {
            let (dx, dy) = (x as f32 + 0.5 - 32.0, y as f32 + 0.5 - 32.0);
            let r2 = dx * dx + dy * dy;
            let inside = dx.abs() <= 3.0 * var.sqrt() && dy.abs() <= 3.0 * var.sqrt();
            let a = if inside { o * (-0.5 * r2 / var).exp() } else { 0.0 };
            for ch in 0..3 {
                let want = a * colour[ch] + (1.0 - a) * bg[ch];
                let got = f.rgb[3 * (y * 64 + x) + ch];
                assert!((got - want).abs() < 2e-5, "({x}, {y}) {ch}: {got} vs {want}");
            }
            checked += inside as usize;
        }
    }
    assert!(checked > 20, "the footprint covers {checked} pixels");
}

#[test]
fn two_gaussians_composite_in_depth_order() {
    let scene = unit_scene();
    let cam = RasterCamera::new(&camera([0.0, -4.0, 0.0], 32, 32, 50.0), &scene);
    let l = Layout::new(2, 0);
    let (o1, o2) = (0.6f32, 0.7f32);
    let (c1, c2) = ([1.0f32, 0.0, 0.0], [0.0f32, 1.0, 0.0]);
    let bg = [0.0, 0.0, 1.0];
    // Both on the camera axis; the nearer one's colour comes first.
    for (y1, y2) in [(-0.5f32, 0.5f32), (0.5, -0.5)] {
        let mut p = vec![0.0; l.len()];
        p[1] = y1;
        p[4] = y2;
        p[6..12].copy_from_slice(&[(0.3f32).ln(); 6]);
        p[12] = 1.0;
        p[16] = 1.0;
        p[20] = (o1 / (1.0 - o1)).ln();
        p[21] = (o2 / (1.0 - o2)).ln();
        for ch in 0..3 {
            p[22 + ch] = (c1[ch] - 0.5) / SH_C0;
            p[25 + ch] = (c2[ch] - 0.5) / SH_C0;
        }
        let f = forward(&l, &p, &cam, &RasterOptions::default(), bg);
        let centre = &f.rgb[3 * (16 * 32 + 16)..3 * (16 * 32 + 16) + 3];
        // At the centre pixel each alpha is its opacity times exp(-r²/2σ²)
        // of a half-pixel offset: compute both exactly.
        let alpha = |o: f32, y: f32| {
            let z = 4.0 + y;
            let var = (cam.fx * 0.3 / z).powi(2) + DILATION;
            o * (-0.5 * 0.5 / var).exp()
        };
        let (a1, a2) = (alpha(o1, y1), alpha(o2, y2));
        let (front, back, af, ab) = if y1 < y2 { (c1, c2, a1, a2) } else { (c2, c1, a2, a1) };
        for ch in 0..3 {
            let want = front[ch] * af + back[ch] * ab * (1.0 - af) + bg[ch] * (1.0 - af) * (1.0 - ab);
            assert!((centre[ch] - want).abs() < 1e-5, "{y1}: {ch}: {} vs {want}", centre[ch]);
        }
    }
}

#[test]
fn backward_matches_finite_differences_for_every_parameter() {
    let scene = unit_scene();
    let cam = RasterCamera::new(&camera([0.4, -4.0, 0.6], 28, 22, 35.0), &scene);
    // No thresholds near the test's values: every Gaussian reaches every
    // pixel smoothly (the box is 10 standard deviations wide, nothing is
    // cut by min_alpha or the transmittance floor).
    let opt = RasterOptions { min_alpha: 0.0, min_transmittance: 0.0, radius_sigmas: 10.0, near: 0.01 };
    for (degree, seed) in [(3, 7), (0, 8)] {
        let (l, mut p) = random_gaussians(4, degree, seed, 0.8);
        // Larger Gaussians, so that each covers many pixels of this small view.
        for v in &mut p[l.log_scales()] {
            *v += 1.0;
        }
        let bg = [0.3f32, 0.1, 0.7];
        let mut rng = Rng::new(seed + 100);
        let weights: Vec<f32> = (0..28 * 22 * 3).map(|_| rng.normal()).collect();
        let f = forward(&l, &p, &cam, &opt, bg);
        let mut grads = vec![0.0f32; l.len()];
        backward(&l, &p, &cam, &opt, &f, &weights, &mut grads);
        let loss = |q: &[f64]| -> f64 {
            let img = reference(&l, q, &cam, &opt, bg.map(f64::from));
            img.iter().zip(&weights).map(|(a, &w)| a * w as f64).sum()
        };
        let p64: Vec<f64> = p.iter().map(|&v| v as f64).collect();
        let names = [
            ("mean", l.means()),
            ("log_scale", l.log_scales()),
            ("rotation", l.rotations()),
            ("opacity", l.opacities()),
            ("sh_dc", l.sh_dc()),
            ("sh_rest", l.sh_rest()),
        ];
        for (name, range) in names {
            for i in range {
                let h = 1e-5;
                let (mut a, mut b) = (p64.clone(), p64.clone());
                a[i] += h;
                b[i] -= h;
                let fd = (loss(&a) - loss(&b)) / (2.0 * h);
                let an = grads[i] as f64;
                let tol = 2e-3 * fd.abs().max(an.abs()) + 2e-3;
                assert!((an - fd).abs() <= tol, "degree {degree}, {name} [{i}]: analytic {an}, differences {fd}");
            }
        }
    }
}

/// The backward adds each Gaussian's gradients in runs of Gaussians, in
/// parallel: the same bits as adding them one Gaussian after another,
/// with several runs and a last one cut short.
#[test]
fn the_backward_in_runs_adds_each_gaussians_gradients_where_they_belong() {
    use super::backward::{RUN, gaussian_backward, screen_grads};
    let scene = unit_scene();
    let cam = RasterCamera::new(&camera([0.4, -4.0, 0.6], 64, 48, 35.0), &scene);
    let opt = RasterOptions::default();
    for degree in [0, 1, 3] {
        let (l, p) = random_gaussians(2 * RUN + 300, degree, 11 + degree as u64, 0.6);
        let mut rng = Rng::new(5);
        let weights: Vec<f32> = (0..64 * 48 * 3).map(|_| rng.normal()).collect();
        let f = forward(&l, &p, &cam, &opt, [0.2, 0.4, 0.6]);
        // Something there already, which the backward adds to.
        let start: Vec<f32> = (0..l.len()).map(|_| rng.normal()).collect();
        let mut got = start.clone();
        backward(&l, &p, &cam, &opt, &f, &weights, &mut got);
        let mut want = start;
        let screen = screen_grads(&cam, &opt, &f, &weights, l.n);
        let (n, rest) = (l.n, 3 * l.k - 3);
        let mut basis = [0.0f32; crate::engine::nn::sh::WIDTH];
        let mut touched = 0;
        for i in 0..n {
            let pr = &f.projected[i];
            if !pr.visible || screen[i] == [0.0; 9] {
                continue;
            }
            touched += 1;
            let g = gaussian_backward(&l, &p, i, &cam, pr, &screen[i], &mut basis);
            for c in 0..3 {
                want[3 * i + c] += g.mean[c];
                want[3 * n + 3 * i + c] += g.log_scale[c];
                want[11 * n + 3 * i + c] += g.sh[c];
            }
            for c in 0..4 {
                want[6 * n + 4 * i + c] += g.rotation[c];
            }
            want[10 * n + i] += g.opacity_logit;
            for c in 0..rest {
                want[14 * n + rest * i + c] += g.sh[3 + c];
            }
        }
        // Most Gaussians are seen, in every run.
        assert!(touched > n / 2, "{touched} of {n} seen");
        let differ = got.iter().zip(&want).filter(|(a, b)| a.to_bits() != b.to_bits()).count();
        assert_eq!(differ, 0, "degree {degree}: {differ} of {} values differ", got.len());
    }
}

#[test]
fn a_rotated_camera_sees_a_rotated_scene_alike() {
    // Rotating both the Gaussians and the camera about the origin leaves
    // the image as it was (colours of degree 0: they do not turn).
    let scene = unit_scene();
    let (l, p) = random_gaussians(60, 0, 5, 0.9);
    let c = camera([0.5, -4.0, 1.0], 40, 30, 45.0);
    let opt = RasterOptions::default();
    let bg = [0.1, 0.2, 0.3];
    let base = forward(&l, &p, &RasterCamera::new(&c, &scene), &opt, bg);
    let q = crate::engine::geometry::quat::Quat::from_axis_angle([0.3, 0.8, -0.5], 1.1).normalized();
    let m = q.to_matrix();
    let rot = |v: [f32; 3]| -> [f32; 3] {
        [0, 1, 2].map(|r| (m[r][0] * v[0] as f64 + m[r][1] * v[1] as f64 + m[r][2] * v[2] as f64) as f32)
    };
    let mut p2 = p.clone();
    let n = l.n;
    for i in 0..n {
        let v = rot([p[3 * i], p[3 * i + 1], p[3 * i + 2]]);
        p2[3 * i..3 * i + 3].copy_from_slice(&v);
        let g = l.get(&p, i);
        let [w, x, y, z] = g.rotation.map(f64::from);
        let r = q.times(crate::engine::geometry::quat::Quat { w, x, y, z });
        p2[6 * n + 4 * i..6 * n + 4 * i + 4].copy_from_slice(&[r.w as f32, r.x as f32, r.y as f32, r.z as f32]);
    }
    let mut c2 = c.clone();
    for r in 0..3 {
        for k in 0..3 {
            c2.c2w[r][k] = (0..3).map(|j| m[r][j] as f32 * c.c2w[j][k]).sum();
        }
    }
    let o = rot(c.origin().to_array());
    for r in 0..3 {
        c2.c2w[r][3] = o[r];
    }
    let turned = forward(&l, &p2, &RasterCamera::new(&c2, &scene), &opt, bg);
    let max = base.rgb.iter().zip(&turned.rgb).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
    let mean: f32 = base.rgb.iter().zip(&turned.rgb).map(|(a, b)| (a - b).abs()).sum::<f32>() / base.rgb.len() as f32;
    assert!(mean < 1e-4 && max < 0.02, "mean {mean}, max {max}");
    assert!(base.opacity.iter().filter(|&&o| o > 0.1).count() > 100);
}

#[test]
fn the_polynomial_exp_is_within_two_ulp_of_f64s() {
    let mut worst = 0.0f64;
    let mut x = -87.0f32;
    while x <= 0.0 {
        let want = (x as f64).exp();
        let got = super::tile::exp_neg(x) as f64;
        worst = worst.max((got - want).abs() / want);
        x += 0.000_731;
    }
    assert!(worst < 2.5e-7, "relative error {worst}");
    assert_eq!(super::tile::exp_neg(0.0), 1.0);
    assert!(super::tile::exp_neg(-1e30) < 1e-37 && super::tile::exp_neg(-1e30) >= 0.0);
    assert_eq!(super::tile::exp_neg(f32::NEG_INFINITY), super::tile::exp_neg(-87.0));
}

/// The view on which the AVX2 and portable builds of the tile loops are
/// compared: 200 random Gaussians of degree 3 in front of the camera.
fn builds_view() -> (RasterCamera, RasterOptions, Frame) {
    let scene = unit_scene();
    let cam = RasterCamera::new(&camera([0.3, -4.0, 0.8], 53, 41, 40.0), &scene);
    let opt = RasterOptions::default();
    let (l, p) = random_gaussians(200, 3, 7, 0.99);
    let f = forward(&l, &p, &cam, &opt, [0.2, 0.5, 0.9]);
    (cam, opt, f)
}

#[test]
fn every_build_of_the_backward_gives_the_portable_ones_bits() {
    // `tile_backward_any` called from here is the portable build.
    use super::backward::ScreenGrad;
    use super::tile::{self, BackwardTile, Build};
    let (cam, opt, f) = builds_view();
    let mut rng = Rng::new(3);
    let d_rgb: Vec<f32> = f.rgb.iter().map(|_| rng.normal()).collect();
    let bits = |g: &Vec<ScreenGrad>| g.iter().flat_map(|e| e.map(f32::to_bits)).collect::<Vec<_>>();
    let mut nonzero = 0;
    let mut checked = Vec::new();
    for t in 0..f.tile_ranges.len() {
        let n = f.tile_ranges[t].len();
        let job = BackwardTile { cam: &cam, opt: &opt, frame: &f, d_rgb: &d_rgb, t };
        let mut want = vec![[0.0f32; 9]; n];
        tile::tile_backward_any(job, &mut want);
        for build in [Build::Avx2, Build::Avx512] {
            if build.available() {
                let mut got = vec![[0.0f32; 9]; n];
                tile::tile_backward_in(build, job, &mut got);
                assert_eq!(bits(&got), bits(&want), "tile {t}, {build:?}");
                if t == 0 {
                    checked.push(build);
                }
            }
        }
        nonzero += want.iter().filter(|e| e.iter().any(|&v| v != 0.0)).count();
    }
    assert!(nonzero > 100, "the scene is in view: {nonzero} entries with a gradient");
    eprintln!("vector builds checked on this CPU: {checked:?}");
}

#[test]
fn every_build_of_the_forward_gives_the_portable_ones_bits() {
    // The whole-row walk (the AVX-512 build's), compiled portably, runs
    // on any CPU; each vector build this CPU runs is checked too.
    use super::tile::{self, Build};
    let (cam, opt, f) = builds_view();
    let bits = |o: &tile::TileOut| {
        let values = o.pixels.iter().flat_map(|p| [p.rgb[0], p.rgb[1], p.rgb[2], p.depth, p.t].map(f32::to_bits));
        values.chain(o.pixels.iter().map(|p| p.last)).collect::<Vec<_>>()
    };
    let mut taken = 0;
    let mut checked = Vec::new();
    for t in 0..f.tile_ranges.len() {
        let want = tile::composite_tile_any(&f, &cam, &opt, t);
        assert_eq!(bits(&tile::composite_tile_rows(&f, &cam, &opt, t)), bits(&want), "tile {t}, whole rows");
        for build in [Build::Avx2, Build::Avx512] {
            if build.available() {
                assert_eq!(
                    bits(&tile::composite_tile_in(build, &f, &cam, &opt, t)),
                    bits(&want),
                    "tile {t}, {build:?}"
                );
                if t == 0 {
                    checked.push(build);
                }
            }
        }
        taken += want.pixels.iter().filter(|p| p.last > 0).count();
    }
    assert!(taken > 500, "the scene is in view: {taken} pixels took a Gaussian");
    eprintln!("vector builds checked on this CPU: {checked:?}");
}

#[test]
fn a_rows_span_holds_every_pixel_whose_alpha_reaches_the_cut() {
    // Against the rule itself, pixel by pixel over each drawn Gaussian's
    // box, for Gaussians of every opacity, size and tilt, some far off
    // the view's centre.
    let scene = unit_scene();
    let opt = RasterOptions::default();
    let mut inside = 0;
    for seed in 0..4 {
        let cam = RasterCamera::new(&camera([0.3, -4.0, 0.8 + seed as f32], 61, 47, 45.0), &scene);
        let (l, p) = random_gaussians(300, 1, seed, 0.99);
        let f = forward(&l, &p, &cam, &opt, [0.0; 3]);
        let (w, h) = (cam.width as usize, cam.height as usize);
        for g in &f.drawn {
            let [x0, x1, y0, y1] = g.pixel_rect(w, h);
            let [c0, c1, c2] = g.conic;
            for y in y0..y1 {
                let dy = y as f32 + 0.5 - g.mean[1];
                let (s0, s1) = g.row_span(dy, x0, x1);
                for x in x0..x1 {
                    let dx = x as f32 + 0.5 - g.mean[0];
                    let power = -0.5 * (c0 * dx * dx + c2 * dy * dy) - c1 * dx * dy;
                    let a = (g.opacity * (power as f64).exp() as f32).min(super::raster::MAX_ALPHA);
                    if power <= 0.0 && a >= opt.min_alpha * 0.999 {
                        inside += 1;
                        assert!((s0..s1).contains(&x), "pixel ({x}, {y}), alpha {a}, outside the span {s0}..{s1}");
                    }
                }
            }
        }
    }
    assert!(inside > 2000, "{inside} pixels checked");
}

#[test]
fn a_gaussian_culled_before_its_covariance_reaches_no_pixel() {
    // Gaussians of every size, tilt and opacity scattered far around
    // views from several places: each one `off_view` culls, projected in
    // full, has a box that holds no pixel centre.
    use super::gaussians::{covariance, sigmoid};
    use super::raster::{jacobian, largest_scale, off_view, pixel_rect, project_cov, reach};
    let scene = unit_scene();
    let opt = RasterOptions::default();
    let (mut culled, mut kept_unseen) = (0, 0);
    for seed in 0..4u64 {
        let cam = RasterCamera::new(&camera([0.3 + seed as f32, -4.0, 0.8], 61, 47, 30.0 + 10.0 * seed as f32), &scene);
        let (l, mut p) = random_gaussians(3000, 1, 10 + seed, 0.99);
        let mut rng = Rng::new(seed);
        for i in 0..l.n {
            for c in 0..3 {
                p[3 * i + c] = (rng.f32() - 0.5) * 12.0;
                p[3 * l.n + 3 * i + c] = -4.0 + 4.5 * rng.f32();
            }
        }
        let (w, h) = (cam.width as usize, cam.height as usize);
        for i in 0..l.n {
            let g = l.get(&p, i);
            let t = cam.to_camera(g.mean);
            let o = sigmoid(g.opacity_logit);
            if t[2] <= opt.near || o < opt.min_alpha {
                continue;
            }
            let (j, _) = jacobian(&cam, t);
            let r = reach(o, &opt);
            let mean = [cam.fx * t[0] / t[2] + cam.cx, cam.fy * t[1] / t[2] + cam.cy];
            let cov = project_cov(&j, &cam.rot, &covariance(g.log_scale, g.rotation).0);
            let extent = [r * (cov[0] + DILATION).sqrt(), r * (cov[2] + DILATION).sqrt()];
            let [x0, x1, y0, y1] = pixel_rect(mean, extent, w, h);
            let unseen = x0 >= x1 || y0 >= y1;
            if off_view(&cam, &j, mean, r, largest_scale(g.log_scale)) {
                culled += 1;
                assert!(unseen, "Gaussian {i} culled, but its box holds pixels {x0}..{x1} x {y0}..{y1}");
            } else if unseen {
                kept_unseen += 1;
            }
        }
    }
    // The bound culls most of the unseen, and is not a no-op.
    assert!(culled > 2000 && culled > 2 * kept_unseen, "{culled} culled, {kept_unseen} unseen but kept");
}

#[test]
fn each_tiles_list_holds_the_gaussians_reaching_it_front_to_back() {
    // Enough Gaussians that the lists are built by several parts in
    // parallel; against a plain walk of the drawn Gaussians, tile by tile.
    let scene = unit_scene();
    let cam = RasterCamera::new(&camera([0.3, -4.0, 0.8], 97, 75, 40.0), &scene);
    let opt = RasterOptions::default();
    let (l, p) = random_gaussians(20_000, 0, 5, 0.9);
    let f = forward(&l, &p, &cam, &opt, [0.0; 3]);
    assert!(f.drawn.len() > 10_000, "{} drawn", f.drawn.len());
    let (w, h) = (cam.width as usize, cam.height as usize);
    let tx = cam.tiles_x();
    let mut want: Vec<Vec<u32>> = vec![Vec::new(); f.tile_ranges.len()];
    for (k, g) in f.drawn.iter().enumerate() {
        let [x0, x1, y0, y1] = g.pixel_rect(w, h);
        for ty in y0 / super::raster::TILE..(y1 - 1) / super::raster::TILE + 1 {
            for txi in x0 / super::raster::TILE..(x1 - 1) / super::raster::TILE + 1 {
                want[ty * tx + txi].push(k as u32);
            }
        }
    }
    for (t, r) in f.tile_ranges.iter().enumerate() {
        assert_eq!(&f.list[r.clone()], &want[t][..], "tile {t}");
    }
    // Drawn front to back.
    let depth = |k: usize| f.projected[f.order[k] as usize].t[2];
    assert!((1..f.order.len()).all(|k| depth(k - 1) <= depth(k)));
}

#[test]
fn a_models_views_with_its_intrinsics_worked_out_once_are_the_same_bits() {
    // A splats model works out each Gaussian's opacity, largest scale and
    // covariance once for all its views; changing its parameters must
    // drop them.
    use super::raster::{Intrinsics, forward_with};
    use super::{SplatsConfig, SplatsModel};
    use crate::engine::models::Model;
    let scene = unit_scene();
    let camera = camera([0.3, -4.0, 0.8], 61, 47, 40.0);
    let cam = RasterCamera::new(&camera, &scene);
    let opt = RasterOptions::default();
    let (l, p) = random_gaussians(400, 1, 9, 0.95);
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    let plain = forward(&l, &p, &cam, &opt, [0.0; 3]);
    let pre = Intrinsics::of(&l, &p);
    assert_eq!(bits(&forward_with(&l, &p, Some(&pre), &cam, &opt, [0.0; 3]).rgb), bits(&plain.rgb));
    let config = SplatsConfig { sh_degree: 1, ..SplatsConfig::default() };
    let mut model = SplatsModel::from_parts(config.clone(), scene.clone(), p.clone()).unwrap();
    assert_eq!(bits(&model.render_view(&camera, [0.0; 3], &RenderOptions::default()).0), bits(&plain.rgb));
    // Every Gaussian twice as opaque in logit, through `params_mut`.
    let ops = l.opacities();
    for v in &mut model.params_mut()[ops.clone()] {
        *v += 2.0;
    }
    let mut q = p.clone();
    for v in &mut q[ops] {
        *v += 2.0;
    }
    let fresh = SplatsModel::from_parts(config, scene, q).unwrap();
    let (after, want) = (
        model.render_view(&camera, [0.0; 3], &RenderOptions::default()).0,
        fresh.render_view(&camera, [0.0; 3], &RenderOptions::default()).0,
    );
    assert_ne!(bits(&after), bits(&plain.rgb), "the change shows");
    assert_eq!(bits(&after), bits(&want));
}

#[test]
fn a_models_views_draw_nothing_nearer_than_its_scenes_near_bound() {
    // Its source's rays start at the near bound; a Gaussian just in front
    // of a new view, nearer than that, is left out as the field leaves it.
    use super::{SplatsConfig, SplatsModel};
    let camera = camera([0.0, -4.0, 0.0], 32, 32, 40.0);
    let (l, mut p) = random_gaussians(1, 0, 3, 0.9);
    // One opaque grey Gaussian on the camera's axis, 2 units in front of it.
    p[l.means()].copy_from_slice(&[0.0, -2.0, 0.0]);
    p[l.log_scales()].fill(-2.0);
    p[l.opacities()].fill(4.0);
    p[l.sh_dc()].fill(0.0);
    let centre = |near: f32| {
        let scene = Scene::from_bounds(
            crate::engine::geometry::math::Aabb { min: Vec3::splat(-1.0), max: Vec3::splat(1.0) },
            near,
            10.0,
        );
        assert_eq!(scene.scale, 1.0, "model units are world units here");
        let config = SplatsConfig { sh_degree: 0, ..SplatsConfig::default() };
        let model = SplatsModel::from_parts(config, scene, p.clone()).unwrap();
        let rgb = model.render_view(&camera, [0.0; 3], &RenderOptions::default()).0;
        rgb[3 * (16 * 32 + 16)]
    };
    assert!(centre(0.0) > 0.4, "drawn with no near bound: {}", centre(0.0));
    assert!(centre(1.9) > 0.4, "drawn from 1.9 units on: {}", centre(1.9));
    assert_eq!(centre(2.1), 0.0, "not drawn from 2.1 units on");
}
