//! The rasteriser's backward ([`raster::forward`](super::raster::forward)'s
//! derivative): from the gradient of a loss with respect to a view's
//! colours to every Gaussian's parameters. Each tile walks its pixels'
//! Gaussians back to front (the 3DGS paper's order, which needs no stored
//! per-pixel lists: the transmittance is divided back out) and keeps one
//! gradient per entry of its list; the entries are then summed per
//! Gaussian, and each Gaussian's projection is differentiated on its own.

use rayon::prelude::*;

pub use super::frame::ScreenGrad;
use super::frame::{Frame, Projected, RasterCamera, RasterOptions};
use super::gaussians::{Layout, SH_C0, covariance, rotation_backward, rotation_matrix, unit_quat};
use super::raster::{jacobian, jw, sym};
use super::tile;
use crate::engine::nn::sh;

/// Adds to `grads` (laid out as the parameters) the gradient of a loss
/// whose gradient with respect to `frame`'s colours (`[h x w x 3]`) is
/// `d_rgb`. Returns each Gaussian's screen-space gradient (for
/// densification: the norm of its first two entries says how much the loss
/// wants it to move on the image).
pub fn backward(
    layout: &Layout,
    params: &[f32],
    cam: &RasterCamera,
    opt: &RasterOptions,
    frame: &Frame,
    d_rgb: &[f32],
    grads: &mut [f32],
) -> Vec<ScreenGrad> {
    let screen = screen_grads(cam, opt, frame, d_rgb, layout.n);
    // Each block of the parameters (laid out as `Layout` says) in runs of
    // `RUN` Gaussians: a task adds its run's gradients in every block.
    let n = layout.n;
    let rest_width = 3 * layout.k - 3;
    let (means, more) = grads.split_at_mut(3 * n);
    let (scales, more) = more.split_at_mut(3 * n);
    let (rotations, more) = more.split_at_mut(4 * n);
    let (opacities, more) = more.split_at_mut(n);
    let (dc, more) = more.split_at_mut(3 * n);
    let rest = &mut more[..rest_width * n];
    let runs = n.div_ceil(RUN);
    fn split(block: &mut [f32], width: usize, runs: usize) -> Vec<&mut [f32]> {
        match width {
            0 => (0..runs).map(|_| Default::default()).collect(),
            w => block.chunks_mut(w * RUN).collect(),
        }
    }
    let tasks: Vec<_> = split(means, 3, runs)
        .into_iter()
        .zip(split(scales, 3, runs))
        .zip(split(rotations, 4, runs))
        .zip(split(opacities, 1, runs))
        .zip(split(dc, 3, runs))
        .zip(split(rest, rest_width, runs))
        .collect();
    tasks.into_par_iter().enumerate().for_each_init(
        || [0.0f32; sh::WIDTH],
        |basis, (run, (((((mean, scale), rotation), opacity), dc), rest))| {
            for j in 0..opacity.len() {
                let i = run * RUN + j;
                let p = &frame.projected[i];
                if !p.visible || screen[i] == [0.0; 9] {
                    continue;
                }
                let g = gaussian_backward(layout, params, i, cam, p, &screen[i], basis);
                for c in 0..3 {
                    mean[3 * j + c] += g.mean[c];
                    scale[3 * j + c] += g.log_scale[c];
                    dc[3 * j + c] += g.sh[c];
                }
                for c in 0..4 {
                    rotation[4 * j + c] += g.rotation[c];
                }
                opacity[j] += g.opacity_logit;
                for (s, v) in rest[rest_width * j..rest_width * (j + 1)].iter_mut().zip(&g.sh[3..]) {
                    *s += v;
                }
            }
        },
    );
    screen
}

/// Gaussians a task of the parameters' backward takes.
pub(super) const RUN: usize = 2048;

/// Per tile, back to front: each list entry's screen gradient, summed per
/// Gaussian.
pub(super) fn screen_grads(
    cam: &RasterCamera,
    opt: &RasterOptions,
    frame: &Frame,
    d_rgb: &[f32],
    n: usize,
) -> Vec<ScreenGrad> {
    // Each tile's slice of the per-entry gradients.
    let mut entries = vec![[0.0f32; 9]; frame.list.len()];
    let mut slices = Vec::with_capacity(frame.tile_ranges.len());
    let mut rest: &mut [ScreenGrad] = &mut entries;
    for r in &frame.tile_ranges {
        let (a, b) = rest.split_at_mut(r.len());
        slices.push(a);
        rest = b;
    }
    slices
        .into_par_iter()
        .enumerate()
        .for_each(|(t, out)| tile::tile_backward(tile::BackwardTile { cam, opt, frame, d_rgb, t }, out));
    let mut screen = vec![[0.0f32; 9]; n];
    for (&k, e) in frame.list.iter().zip(&entries) {
        let s = &mut screen[frame.order[k as usize] as usize];
        for c in 0..9 {
            s[c] += e[c];
        }
    }
    screen
}

/// One Gaussian's parameter gradients (`sh`: the first `3 k`).
#[derive(Clone, Debug)]
pub(super) struct GaussianGrad {
    pub(super) mean: [f32; 3],
    pub(super) log_scale: [f32; 3],
    pub(super) rotation: [f32; 4],
    pub(super) opacity_logit: f32,
    pub(super) sh: [f32; 3 * sh::WIDTH],
}

impl Default for GaussianGrad {
    fn default() -> Self {
        Self { mean: [0.0; 3], log_scale: [0.0; 3], rotation: [0.0; 4], opacity_logit: 0.0, sh: [0.0; 3 * sh::WIDTH] }
    }
}

/// Differentiates Gaussian `i`'s projection, given its screen gradient `s`.
pub(super) fn gaussian_backward(
    layout: &Layout,
    params: &[f32],
    i: usize,
    cam: &RasterCamera,
    p: &Projected,
    s: &ScreenGrad,
    basis: &mut [f32; sh::WIDTH],
) -> GaussianGrad {
    let g = layout.get(params, i);
    let mut out = GaussianGrad::default();
    let d_dir = colour_backward(layout.k, g.sh_rest, p, [s[6], s[7], s[8]], g.mean, cam.origin, &mut out.sh, basis);
    out.opacity_logit = s[5] * p.opacity * (1.0 - p.opacity);
    let d_cov = conic_backward(p.cov, [s[2], s[3], s[4]]);
    let (sigma, m) = covariance(g.log_scale, g.rotation);
    let (d_t, d_sigma) = projection_backward(cam, p.t, &sigma, d_cov, [s[0], s[1]]);
    let w = &cam.rot;
    for c in 0..3 {
        out.mean[c] = d_dir[c] + w[0][c] * d_t[0] + w[1][c] * d_t[1] + w[2][c] * d_t[2];
    }
    // Σ = M Mᵀ with M = R S: dM = 2 dΣ M; dR = dM S, dS = diag(Rᵀ dM).
    let r = rotation_matrix(unit_quat(g.rotation));
    let mut d_r = [[0.0f32; 3]; 3];
    for a in 0..3 {
        for b in 0..3 {
            let dm = 2.0 * (d_sigma[a][0] * m[0][b] + d_sigma[a][1] * m[1][b] + d_sigma[a][2] * m[2][b]);
            let s_b = g.log_scale[b].exp();
            d_r[a][b] = dm * s_b;
            out.log_scale[b] += dm * r[a][b] * s_b;
        }
    }
    out.rotation = rotation_backward(g.rotation, d_r);
    out
}

/// The colour's backward: writes the SH coefficients' gradient into
/// `d_sh` (`[k x 3]`, the DC terms first) and returns the position's
/// (through the viewing direction); `sh_rest` are the coefficients beyond
/// DC.
/// Clamped channels pass nothing.
#[allow(clippy::too_many_arguments)]
fn colour_backward(
    k: usize,
    sh_rest: &[f32],
    p: &Projected,
    mut d_rgb: [f32; 3],
    mean: [f32; 3],
    origin: [f32; 3],
    d_sh: &mut [f32],
    basis: &mut [f32; sh::WIDTH],
) -> [f32; 3] {
    for (c, d) in d_rgb.iter_mut().enumerate() {
        if p.clamped & (1 << c) != 0 {
            *d = 0.0;
        }
    }
    for c in 0..3 {
        d_sh[c] = SH_C0 * d_rgb[c];
    }
    if k == 1 {
        return [0.0; 3];
    }
    let dir = [mean[0] - origin[0], mean[1] - origin[1], mean[2] - origin[2]];
    sh::encode_one(dir, basis);
    let mut d_basis = [0.0f32; sh::WIDTH];
    for j in 1..k {
        for c in 0..3 {
            d_sh[3 * j + c] = basis[j] * d_rgb[c];
            d_basis[j] += sh_rest[3 * (j - 1) + c] * d_rgb[c];
        }
    }
    sh::encode_backward_one(dir, &d_basis)
}

/// The projection's backward: from the gradients of the 2D covariance
/// (`d_cov`) and of the projected mean (`d_mean`) to those of the centre
/// in the camera's frame and of the 3D covariance `sigma`.
fn projection_backward(
    cam: &RasterCamera,
    t: [f32; 3],
    sigma: &[f32; 6],
    d_cov: [f32; 3],
    d_mean: [f32; 2],
) -> ([f32; 3], [[f32; 3]; 3]) {
    let (fx, fy, z) = (cam.fx, cam.fy, t[2]);
    let mut d_t = [d_mean[0] * fx / z, d_mean[1] * fy / z, -(d_mean[0] * fx * t[0] + d_mean[1] * fy * t[1]) / (z * z)];
    let (j, clamp) = jacobian(cam, t);
    let tm = jw(&j, &cam.rot);
    let sg = sym(sigma);
    // cov2 = T Σ Tᵀ: dΣ = Tᵀ G T, dT = 2 G T Σ, with G the symmetric
    // gradient (the off-diagonal entry's split between its two places).
    let gm = [[d_cov[0], 0.5 * d_cov[1]], [0.5 * d_cov[1], d_cov[2]]];
    let mut d_sigma = [[0.0f32; 3]; 3];
    for a in 0..3 {
        for b in 0..3 {
            d_sigma[a][b] =
                (0..2).flat_map(|r| (0..2).map(move |q| (r, q))).map(|(r, q)| tm[r][a] * gm[r][q] * tm[q][b]).sum();
        }
    }
    let mut d_tm = [[0.0f32; 3]; 2];
    for r in 0..2 {
        for c in 0..3 {
            d_tm[r][c] = 2.0
                * (0..2)
                    .flat_map(|q| (0..3).map(move |k| (q, k)))
                    .map(|(q, k)| gm[r][q] * tm[q][k] * sg[k][c])
                    .sum::<f32>();
        }
    }
    // T = J W: dJ = dT Wᵀ.
    let w = &cam.rot;
    let d_j = [0, 1].map(|r| [0, 1, 2].map(|k| d_tm[r][0] * w[k][0] + d_tm[r][1] * w[k][1] + d_tm[r][2] * w[k][2]));
    let (u, v) = (-j[0][2] * z / fx, -j[1][2] * z / fy);
    let z2 = z * z;
    d_t[2] += d_j[0][0] * (-fx / z2) + d_j[0][2] * (fx * u / z2) + d_j[1][1] * (-fy / z2) + d_j[1][2] * (fy * v / z2);
    let (d_u, d_v) = (d_j[0][2] * (-fx / z), d_j[1][2] * (-fy / z));
    if clamp & (1 << 3) == 0 {
        d_t[0] += d_u / z;
        d_t[2] -= d_u * t[0] / z2;
    }
    if clamp & (1 << 4) == 0 {
        d_t[1] += d_v / z;
        d_t[2] -= d_v * t[1] / z2;
    }
    (d_t, d_sigma)
}

/// From the gradient with respect to the conic (`xx xy yy` of the inverse)
/// to that with respect to the covariance `(a, b, c)` it inverts, `b`
/// counted once.
fn conic_backward(cov: [f32; 3], g: [f32; 3]) -> [f32; 3] {
    let [a, b, c] = cov;
    let det = a * c - b * b;
    let d2 = det * det;
    [
        (-c * c * g[0] + b * c * g[1] - b * b * g[2]) / d2,
        (2.0 * b * c * g[0] - (det + 2.0 * b * b) * g[1] + 2.0 * a * b * g[2]) / d2,
        (-b * b * g[0] + a * b * g[1] - a * a * g[2]) / d2,
    ]
}
