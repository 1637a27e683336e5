//! The tile rasteriser of Gaussian splats (the 3DGS paper's, on the CPU):
//! each Gaussian is projected to a 2D Gaussian on the image (the EWA
//! splatting approximation, its 2D covariance dilated by 0.3 px² as the
//! paper's code does), the Gaussians are sorted front to back and binned
//! into 16x16-pixel tiles, and each tile composites its pixels in parallel
//! with the others.
//!
//! What a Gaussian adds to a pixel, exactly (the f64 reference in the tests
//! renders by this rule alone, pixel by pixel, with no tiles):
//! - the Gaussian lies in front of the camera (`z > near`) and its
//!   projected covariance is positive definite;
//! - the pixel centre `p` lies within the Gaussian's box: `|p - m| <=
//!   r sqrt(diag Σ')` on each axis, with `m` the projected mean, `Σ'` the
//!   dilated 2D covariance and `r = min(radius_sigmas, sqrt(2 ln(o /
//!   min_alpha)))` (beyond it the Gaussian's alpha is below `min_alpha`
//!   anyway, or the box is cut at `radius_sigmas` standard deviations);
//! - its alpha `a = min(0.99, o exp(-½ dᵀ Σ'⁻¹ d))` (`d = p - m`, `o` the
//!   opacity) is at least `min_alpha`;
//! - the pixel's transmittance after it, `T (1 - a)`, would not fall below
//!   `min_transmittance`; once it would, the pixel takes nothing more.
//!
//! The pixel's colour is `sum c_i a_i T_i + T_final * background`, in
//! order of the Gaussians' depth along the camera's axis (ties by index).

use rayon::prelude::*;

pub use super::frame::{
    DILATION, FRUSTUM_SLACK, Frame, MAX_ALPHA, Projected, RasterCamera, RasterOptions, Splat2D, TILE, pixel_rect,
};
use super::gaussians::{Layout, covariance, sh_colour, sigmoid};
use super::tile::{self, TileOut};
use crate::engine::nn::sh;

/// Projects Gaussian `i` of `params`.
pub fn project(
    layout: &Layout,
    params: &[f32],
    i: usize,
    pre: Option<&Intrinsics>,
    cam: &RasterCamera,
    opt: &RasterOptions,
    basis: &mut [f32; sh::WIDTH],
) -> Projected {
    let g = layout.get(params, i);
    let t = cam.to_camera(g.mean);
    let opacity = pre.map_or_else(|| sigmoid(g.opacity_logit), |pre| pre.opacity[i]);
    let mut p = Projected { t, opacity, ..Default::default() };
    if t[2].is_nan() || t[2] <= opt.near || opacity.is_nan() || opacity < opt.min_alpha {
        return p;
    }
    let (j, clamp) = jacobian(cam, t);
    let r = reach(opacity, opt);
    let mean = cam.pixel(t);
    let largest = pre.map_or_else(|| largest_scale(g.log_scale), |pre| pre.largest_scale[i]);
    if off_view(cam, &j, mean, r, largest) {
        return p;
    }
    let sigma = pre.map_or_else(|| covariance(g.log_scale, g.rotation).0, |pre| pre.sigma[i]);
    let cov = project_cov(&j, &cam.rot, &sigma);
    let cov = [cov[0] + DILATION, cov[1], cov[2] + DILATION];
    let det = cov[0] * cov[2] - cov[1] * cov[1];
    if det.is_nan() || det <= 0.0 || !det.is_finite() {
        return p;
    }
    p.conic = [cov[2] / det, -cov[1] / det, cov[0] / det];
    p.cov = cov;
    p.mean = mean;
    p.extent = [r * cov[0].sqrt(), r * cov[2].sqrt()];
    let rect = p.pixel_rect(cam.width as usize, cam.height as usize);
    p.visible = rect[0] < rect[1] && rect[2] < rect[3] && p.mean.iter().all(|m| m.is_finite());
    if !p.visible {
        // Nothing is drawn of it: its colour (the spherical harmonics, the
        // dearest part of a projection) is not needed.
        return p;
    }
    let dir = [g.mean[0] - cam.origin[0], g.mean[1] - cam.origin[1], g.mean[2] - cam.origin[2]];
    p.dist = (dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2]).sqrt();
    let rgb = sh_colour(&g, layout.k, dir, basis);
    p.clamped = clamp;
    for c in 0..3 {
        if rgb[c] < 0.0 {
            p.clamped |= 1 << c;
        }
        p.rgb[c] = rgb[c].max(0.0);
    }
    p
}

/// Whether a Gaussian centred at `mean` on the image (pixels), with the
/// projection's Jacobian `j` there, reach `r` (standard deviations) and
/// largest scale `s`, surely reaches no pixel centre: its box is then
/// beyond the view's edge even at its widest, with a pixel to spare. The
/// box's half-width in x is `r sqrt(Σ'xx)`, and `Σ'xx = j₀ W Σ Wᵀ j₀ᵀ +
/// DILATION` is at most `|j₀|² s² + DILATION` for the largest scale `s`
/// (`W` is a rotation, and `Σ`'s largest eigenvalue is `s²`); so in y. A
/// cheap test that spares an unseen Gaussian its covariance and colour.
#[inline]
pub(super) fn off_view(cam: &RasterCamera, j: &[[f32; 3]; 2], mean: [f32; 2], r: f32, s: f32) -> bool {
    let s2 = s * s;
    let bx = r * ((j[0][0] * j[0][0] + j[0][2] * j[0][2]) * s2 + DILATION).sqrt() + 1.0;
    let by = r * ((j[1][1] * j[1][1] + j[1][2] * j[1][2]) * s2 + DILATION).sqrt() + 1.0;
    // NaNs compare false: such a Gaussian is left to the exact rule.
    mean[0] + bx < 0.0 || mean[0] - bx > cam.width as f32 || mean[1] + by < 0.0 || mean[1] - by > cam.height as f32
}

/// A Gaussian's largest scale, from its log scales.
pub fn largest_scale(log_scale: [f32; 3]) -> f32 {
    log_scale[0].max(log_scale[1]).max(log_scale[2]).exp()
}

/// What a view's projection derives from each Gaussian's parameters alone
/// (its opacity, largest scale and 3D covariance), worked out once for a
/// model whose parameters stay as they are (a splats model's views), where
/// each view would work it out again. The same functions give the same
/// bits as [`project`] works them out without it.
pub struct Intrinsics {
    pub opacity: Vec<f32>,
    pub largest_scale: Vec<f32>,
    pub sigma: Vec<[f32; 6]>,
}

impl Intrinsics {
    pub fn of(layout: &Layout, params: &[f32]) -> Self {
        let (opacity, (largest_scale, sigma)) = (0..layout.n)
            .into_par_iter()
            .map(|i| {
                let g = layout.get(params, i);
                (sigmoid(g.opacity_logit), (largest_scale(g.log_scale), covariance(g.log_scale, g.rotation).0))
            })
            .unzip();
        Self { opacity, largest_scale, sigma }
    }
}

/// How far a Gaussian of opacity `o` reaches, in standard deviations.
pub fn reach(o: f32, opt: &RasterOptions) -> f32 {
    if opt.min_alpha > 0.0 {
        (2.0 * (o / opt.min_alpha).ln()).max(0.0).sqrt().min(opt.radius_sigmas)
    } else {
        opt.radius_sigmas
    }
}

/// The Jacobian of the perspective projection at `t` (rows: `[fx/z, 0,
/// -fx u/z]`, `[0, fy/z, -fy v/z]`, with `u = x/z` and `v = y/z` held
/// within [`FRUSTUM_SLACK`] times the half field of view) and which of `u`,
/// `v` were held (bits 3 and 4).
pub fn jacobian(cam: &RasterCamera, t: [f32; 3]) -> ([[f32; 3]; 2], u8) {
    let lim_x = FRUSTUM_SLACK * 0.5 * cam.width as f32 / cam.fx;
    let lim_y = FRUSTUM_SLACK * 0.5 * cam.height as f32 / cam.fy;
    let (u, v) = (t[0] / t[2], t[1] / t[2]);
    let mut flags = 0;
    if u.abs() > lim_x {
        flags |= 1 << 3;
    }
    if v.abs() > lim_y {
        flags |= 1 << 4;
    }
    let (u, v) = (u.clamp(-lim_x, lim_x), v.clamp(-lim_y, lim_y));
    let z = t[2];
    ([[cam.fx / z, 0.0, -cam.fx * u / z], [0.0, cam.fy / z, -cam.fy * v / z]], flags)
}

/// `T Σ Tᵀ` with `T = J W` (`xx xy yy`), for the symmetric `sigma` (`xx xy
/// xz yy yz zz`).
pub fn project_cov(j: &[[f32; 3]; 2], w: &[[f32; 3]; 3], sigma: &[f32; 6]) -> [f32; 3] {
    let t = jw(j, w);
    let s = sym(sigma);
    let ts = |r: usize| -> [f32; 3] { [0, 1, 2].map(|c| t[r][0] * s[0][c] + t[r][1] * s[1][c] + t[r][2] * s[2][c]) };
    let (a, b) = (ts(0), ts(1));
    let dot = |x: [f32; 3], y: [f32; 3]| x[0] * y[0] + x[1] * y[1] + x[2] * y[2];
    [dot(a, t[0]), dot(a, t[1]), dot(b, t[1])]
}

/// `J W`.
pub fn jw(j: &[[f32; 3]; 2], w: &[[f32; 3]; 3]) -> [[f32; 3]; 2] {
    [0, 1].map(|r| [0, 1, 2].map(|c| j[r][0] * w[0][c] + j[r][1] * w[1][c] + j[r][2] * w[2][c]))
}

/// The full matrix of a symmetric `xx xy xz yy yz zz`.
pub fn sym(s: &[f32; 6]) -> [[f32; 3]; 3] {
    [[s[0], s[1], s[2]], [s[1], s[3], s[4]], [s[2], s[4], s[5]]]
}

/// Renders `params` (laid out as `layout`) from `cam`.
pub fn forward(
    layout: &Layout,
    params: &[f32],
    cam: &RasterCamera,
    opt: &RasterOptions,
    background: [f32; 3],
) -> Frame {
    forward_with(layout, params, None, cam, opt, background)
}

/// [`forward`], with the Gaussians' [`Intrinsics`] if they were worked
/// out (the same bits).
pub fn forward_with(
    layout: &Layout,
    params: &[f32],
    pre: Option<&Intrinsics>,
    cam: &RasterCamera,
    opt: &RasterOptions,
    background: [f32; 3],
) -> Frame {
    let projected = project_all(layout, params, pre, cam, opt);
    let Binned { order, drawn, tile_ranges, list } = bin(&projected, cam, opt);
    let (w, h) = (cam.width as usize, cam.height as usize);
    let mut frame = Frame {
        width: w,
        height: h,
        rgb: vec![0.0; w * h * 3],
        depth: vec![0.0; w * h],
        opacity: vec![0.0; w * h],
        last: vec![0; w * h],
        final_t: vec![1.0; w * h],
        projected,
        order,
        drawn,
        tile_ranges,
        list,
        background,
    };
    let tiles: Vec<TileOut> =
        (0..frame.tile_ranges.len()).into_par_iter().map(|t| tile::composite_tile(&frame, cam, opt, t)).collect();
    // Each row of tiles writes its own band of the image.
    let (tx, band) = (cam.tiles_x(), TILE * w);
    let Frame { rgb, depth, opacity, last, final_t, .. } = &mut frame;
    rgb.par_chunks_mut(3 * band)
        .zip(depth.par_chunks_mut(band))
        .zip(opacity.par_chunks_mut(band))
        .zip(last.par_chunks_mut(band))
        .zip(final_t.par_chunks_mut(band))
        .zip(tiles.par_chunks(tx))
        .for_each(|(((((rgb, depth), opacity), last), final_t), row)| {
            for (j, out) in row.iter().enumerate() {
                for (k, p) in out.pixels.iter().enumerate() {
                    let i = (k / out.w) * w + j * TILE + k % out.w;
                    for c in 0..3 {
                        rgb[3 * i + c] = p.rgb[c] + p.t * background[c];
                    }
                    depth[i] = p.depth;
                    opacity[i] = 1.0 - p.t;
                    final_t[i] = p.t;
                    last[i] = p.last;
                }
            }
        });
    frame
}

/// Every Gaussian's projection, in parallel.
pub fn project_all(
    layout: &Layout,
    params: &[f32],
    pre: Option<&Intrinsics>,
    cam: &RasterCamera,
    opt: &RasterOptions,
) -> Vec<Projected> {
    (0..layout.n)
        .into_par_iter()
        .map_init(|| [0.0f32; sh::WIDTH], |basis, i| project(layout, params, i, pre, cam, opt, basis))
        .collect()
}

/// A view's drawn Gaussians, sorted and binned into tiles ([`bin`]).
pub struct Binned {
    /// The visible Gaussians, front to back.
    pub order: Vec<u32>,
    /// Their projections, in that order.
    pub drawn: Vec<Splat2D>,
    /// Each tile's range of `list`.
    pub tile_ranges: Vec<std::ops::Range<usize>>,
    /// The Gaussians of each tile, front to back, as positions in `order`.
    pub list: Vec<u32>,
}

/// Sorts the visible Gaussians by depth (ties by index) and lists them per
/// tile, front to back.
pub fn bin(projected: &[Projected], cam: &RasterCamera, opt: &RasterOptions) -> Binned {
    // Depths are positive, so their bits sort as the numbers do: a key of
    // the depth's bits over the index sorts by depth, ties by index.
    let mut keys: Vec<u64> = projected
        .par_iter()
        .enumerate()
        .filter(|(_, p)| p.visible)
        .map(|(i, p)| (u64::from(p.t[2].to_bits()) << 32) | i as u64)
        .collect();
    keys.par_sort_unstable();
    let order: Vec<u32> = keys.par_iter().map(|&k| k as u32).collect();
    let (tx, ty) = (cam.tiles_x(), cam.tiles_y());
    let (w, h) = (cam.width as usize, cam.height as usize);
    // Each drawn Gaussian's projection, gathered in drawing order, and the
    // tiles it reaches. The gather reads `projected` out of order: each
    // read is asked for a few places ahead, so that the reads overlap.
    let mut drawn = vec![Splat2D::default(); order.len()];
    let mut rects = vec![[0u32; 4]; order.len()];
    drawn.par_chunks_mut(GATHER).zip(rects.par_chunks_mut(GATHER)).zip(order.par_chunks(GATHER)).for_each(
        |((drawn, rects), order)| {
            for (j, &i) in order.iter().enumerate() {
                if let Some(&ahead) = order.get(j + GATHER_AHEAD) {
                    prefetch_projected(&projected[ahead as usize]);
                }
                let p = Splat2D::of(&projected[i as usize], opt.min_alpha);
                let [x0, x1, y0, y1] = p.pixel_rect(w, h);
                rects[j] = [x0 / TILE, (x1 - 1) / TILE + 1, y0 / TILE, (y1 - 1) / TILE + 1].map(|v| v as u32);
                drawn[j] = p;
            }
        },
    );
    // The lists: the drawn Gaussians in parts, each part counting how many
    // of its Gaussians each tile takes, so that each part then writes its
    // own places of each tile's list, the parts in parallel.
    let tiles = tx * ty;
    let part = rects.len().div_ceil(rayon::current_num_threads().max(1) * 4).max(GATHER);
    let counts: Vec<Vec<u32>> = rects
        .par_chunks(part)
        .map(|rects| {
            let mut count = vec![0u32; tiles];
            for_each_tile(rects, tx, |t, _| count[t] += 1);
            count
        })
        .collect();
    let mut tile_ranges = Vec::with_capacity(tiles);
    // Where each part's first entry of each tile goes.
    let mut starts: Vec<Vec<usize>> = vec![vec![0; tiles]; counts.len()];
    let mut at = 0;
    for t in 0..tiles {
        let begin = at;
        for (c, count) in counts.iter().enumerate() {
            starts[c][t] = at;
            at += count[t] as usize;
        }
        tile_ranges.push(begin..at);
    }
    let mut list = vec![0u32; at];
    let out = SharedSlots(list.as_mut_ptr(), list.len());
    rects.par_chunks(part).zip(starts.par_iter_mut()).enumerate().for_each(|(c, (rects, next))| {
        for_each_tile(rects, tx, |t, j| {
            // SAFETY: part `c`'s places of tile `t` are `starts[c][t]..` for
            // its count of the tile, which no other part's range meets and
            // which lie within `list` (the counts sum to its length).
            unsafe { out.write(next[t], (c * part + j) as u32) };
            next[t] += 1;
        });
    });
    Binned { order, drawn, tile_ranges, list }
}

/// Drawn Gaussians a task of [`bin`]'s gather takes.
const GATHER: usize = 1024;
/// How many places ahead the gather asks for a projection.
const GATHER_AHEAD: usize = 16;

/// Calls `f(tile, j)` for each tile the `j`-th of `rects` (tile
/// rectangles `[x0, x1, y0, y1]`) reaches, row by row.
#[inline]
fn for_each_tile(rects: &[[u32; 4]], tx: usize, mut f: impl FnMut(usize, usize)) {
    for (j, r) in rects.iter().enumerate() {
        for y in r[2] as usize..r[3] as usize {
            for x in r[0] as usize..r[1] as usize {
                f(y * tx + x, j);
            }
        }
    }
}

/// A slice's places that tasks write in parallel, each to places no other
/// task writes.
#[derive(Clone, Copy)]
struct SharedSlots(*mut u32, usize);

// SAFETY: the writers' places are disjoint (each `write`'s caller says so).
unsafe impl Send for SharedSlots {}
unsafe impl Sync for SharedSlots {}

impl SharedSlots {
    /// # Safety
    /// No other task reads or writes place `i` meanwhile.
    unsafe fn write(&self, i: usize, v: u32) {
        assert!(i < self.1, "place {i} of {}", self.1);
        // SAFETY: in bounds (checked), and the caller's.
        unsafe { self.0.add(i).write(v) };
    }
}

/// Asks the CPU to bring `p` into its cache (a hint only).
#[inline(always)]
fn prefetch_projected(p: &Projected) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: a prefetch reads nothing and changes nothing; its addresses
    // are within the reference's object or just past it.
    unsafe {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        let at: *const i8 = (p as *const Projected).cast();
        _mm_prefetch::<_MM_HINT_T0>(at);
        _mm_prefetch::<_MM_HINT_T0>(at.wrapping_add(std::mem::size_of::<Projected>() - 1));
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = p;
}
