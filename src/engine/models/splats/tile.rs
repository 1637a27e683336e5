//! The per-tile inner loops of the rasteriser (`raster::forward`) and of
//! its backward (`backward::backward`), written a row of [`TILE`] pixels
//! at a time with no branches inside a row, so that the compiler turns each
//! row into a few vector instructions: every pixel of the row computes its
//! alpha (with [`exp_neg`], a polynomial `exp`, where `libm`'s call would
//! stop the vectorising), and a mask says which pixels take it. The rule of
//! what a Gaussian adds to a pixel is the module docs' of `raster`, exactly.
//!
//! On x86-64 with AVX2 and FMA the backward's code is compiled a second
//! time for those instructions and chosen at run time (as `nn::gemm`
//! does); a test checks that both give the same bits. The forward walks
//! each Gaussian's box pixel by pixel instead (most boxes are a few pixels
//! wide, where a row of lanes would mostly compute nothing).

use super::backward::ScreenGrad;
use super::raster::{Frame, MAX_ALPHA, RasterCamera, RasterOptions, Splat2D, TILE};

/// `exp(x)` for `x <= 0` (larger `x` are taken as 0), within 2 units in the
/// last place of f32 down to `x = -87`, below which it is that of `-87`
/// (about 1.6e-38, an alpha far below any cut). A range reduction to
/// `x = n ln 2 + r` with `|r| <= ln 2 / 2`, and `exp(r)` by its Taylor
/// series to `r^6` (the first left out, `r^7 / 7!`, is below 1.2e-7 of it).
#[inline(always)]
pub fn exp_neg(x: f32) -> f32 {
    const LOG2E: f32 = std::f32::consts::LOG2_E;
    // ln 2 in two parts, the first exact in few bits so `n * LN2_HI` is.
    const LN2_HI: f32 = 0.693_145_75;
    const LN2_LO: f32 = 1.428_606_8e-6;
    // 1.5 * 2^23: adding it rounds to the nearest integer, which the low
    // bits of the sum then hold (integer operations only, which vectorise
    // where a float-to-integer cast does not).
    const ROUND: f32 = 12_582_912.0;
    let x = x.clamp(-87.0, 0.0);
    let big = x * LOG2E + ROUND;
    let n = big - ROUND;
    let k = big.to_bits().wrapping_sub(ROUND.to_bits());
    let r = x - n * LN2_HI - n * LN2_LO;
    let p = 1.0 + r * (1.0 + r * (0.5 + r * (1.0 / 6.0 + r * (1.0 / 24.0 + r * (1.0 / 120.0 + r * (1.0 / 720.0))))));
    p * f32::from_bits(k.wrapping_add(127) << 23)
}

/// One pixel's result of the forward.
#[derive(Clone, Copy, Debug, Default)]
pub struct PixelOut {
    pub rgb: [f32; 3],
    pub depth: f32,
    pub t: f32,
    pub last: u32,
}

/// A tile's pixels, row by row (`w` wide).
pub struct TileOut {
    pub w: usize,
    pub pixels: Vec<PixelOut>,
}

/// The pixel rectangle of tile `t`: `[x0, x1, y0, y1]`.
pub fn tile_rect(cam: &RasterCamera, t: usize) -> [usize; 4] {
    let tx = cam.tiles_x();
    let (x0, y0) = ((t % tx) * TILE, (t / tx) * TILE);
    [x0, (x0 + TILE).min(cam.width as usize), y0, (y0 + TILE).min(cam.height as usize)]
}

/// Pixels a vector of lanes holds: a tile's row is two.
const L: usize = 8;
/// Chunks of [`L`] lanes in a tile's row.
const CHUNKS: usize = TILE / L;

/// What Gaussian `p` gives the [`L`] pixels whose centres are `xs` on a
/// row `dy` below its mean: each pixel's alpha (0 where it adds nothing:
/// outside its box or the lanes `cols`, or below `min_alpha`), its value
/// before the cap, and its offset from the mean in x.
#[inline(always)]
fn lanes_alpha(p: &Splat2D, xs: &[f32; L], dy: f32, cols: (usize, usize), min_alpha: f32) -> [[f32; L]; 3] {
    let (mut a, mut raw, mut dx) = ([0.0f32; L], [0.0f32; L], [0.0f32; L]);
    let [c0, c1, c2] = p.conic;
    let y_in = dy.abs() <= p.extent[1];
    for k in 0..L {
        let d = xs[k] - p.mean[0];
        let power = -0.5 * (c0 * d * d + c2 * dy * dy) - c1 * d * dy;
        let r = p.opacity * exp_neg(power);
        let v = r.min(MAX_ALPHA);
        let inside = y_in & (k >= cols.0) & (k < cols.1) & (d.abs() <= p.extent[0]) & (power <= 0.0) & (v >= min_alpha);
        a[k] = if inside { v } else { 0.0 };
        raw[k] = r;
        dx[k] = d;
    }
    [a, raw, dx]
}

/// The chunks of a tile's row that Gaussian `p` reaches, each with the
/// lanes it reaches there, for the tile whose columns start at `x0`
/// (`cols`: the tile's columns it reaches, from `x0`).
#[inline(always)]
fn chunks(cols: (usize, usize)) -> impl Iterator<Item = (usize, (usize, usize))> {
    let (c0, c1) = cols;
    let (h0, h1) = if c1 > c0 { (c0 / L, (c1 - 1) / L + 1) } else { (0, 0) };
    (h0..h1).map(move |h| (h, (c0.saturating_sub(h * L), (c1 - h * L).min(L))))
}

/// The pixel centres' x of the tile's columns starting at `x0`, by chunk.
#[inline(always)]
fn centres(x0: usize) -> [[f32; L]; CHUNKS] {
    std::array::from_fn(|h| std::array::from_fn(|k| (x0 + h * L + k) as f32 + 0.5))
}

/// The forward of tile `t`: its pixels, composited front to back.
pub fn composite_tile(frame: &Frame, cam: &RasterCamera, opt: &RasterOptions, t: usize) -> TileOut {
    // Pixel by pixel over each Gaussian's box: most boxes are a few pixels
    // wide, where a row of lanes would mostly compute nothing (lego, 81k
    // Gaussians at 200x200: 30-40 ms a view so, 58-62 ms by lanes).
    let [x0, x1, y0, y1] = tile_rect(cam, t);
    let w = x1 - x0;
    let mut px = vec![PixelOut { t: 1.0, ..Default::default() }; w * (y1 - y0)];
    let mut live = vec![true; px.len()];
    let mut n_live = px.len();
    let (width, height) = (cam.width as usize, cam.height as usize);
    for (pos, &g) in frame.list[frame.tile_ranges[t].clone()].iter().enumerate() {
        if n_live == 0 {
            break;
        }
        let p = &frame.drawn[g as usize];
        let [gx0, gx1, gy0, gy1] = p.pixel_rect(width, height);
        let [c0, c1, c2] = p.conic;
        for y in gy0.max(y0)..gy1.min(y1) {
            let dy = y as f32 + 0.5 - p.mean[1];
            if dy.abs() > p.extent[1] {
                continue;
            }
            for x in gx0.max(x0)..gx1.min(x1) {
                let k = (y - y0) * w + (x - x0);
                let dx = x as f32 + 0.5 - p.mean[0];
                let power = -0.5 * (c0 * dx * dx + c2 * dy * dy) - c1 * dx * dy;
                if !live[k] || dx.abs() > p.extent[0] || power > 0.0 {
                    continue;
                }
                let a = (p.opacity * exp_neg(power)).min(MAX_ALPHA);
                if a < opt.min_alpha {
                    continue;
                }
                let o = &mut px[k];
                let next_t = o.t * (1.0 - a);
                if next_t < opt.min_transmittance {
                    live[k] = false;
                    n_live -= 1;
                    continue;
                }
                let wgt = a * o.t;
                for c in 0..3 {
                    o.rgb[c] += wgt * p.rgb[c];
                }
                o.depth += wgt * p.dist;
                o.t = next_t;
                o.last = pos as u32 + 1;
            }
        }
    }
    TileOut { w, pixels: px }
}

/// Per-pixel state of the backward's walk, back to front (a chunk of
/// lanes each): the loss's gradient there, how many of the tile's list the
/// pixel took, its final transmittance, the background's share of the
/// gradient, the transmittance in front of the current Gaussian, the colour
/// behind it, and the last alpha and colour seen.
#[derive(Clone, Copy, Default)]
struct BackLanes {
    g: [[f32; L]; 3],
    last: [u32; L],
    t_final: [f32; L],
    bg_dot: [f32; L],
    tr: [f32; L],
    accum: [[f32; L]; 3],
    last_a: [f32; L],
    last_c: [[f32; L]; 3],
}

/// The states of the tile `[x0, x1) x [y0, y1)`'s chunks before the walk,
/// and the deepest position of the tile's list any pixel took.
fn back_lanes(frame: &Frame, d_rgb: &[f32], [x0, x1, y0, y1]: [usize; 4]) -> (Vec<BackLanes>, usize) {
    let bg = frame.background;
    let mut deepest = 0;
    let mut lanes = vec![BackLanes::default(); (y1 - y0) * CHUNKS];
    for y in y0..y1 {
        for x in x0..x1 {
            let (s, k) = (&mut lanes[(y - y0) * CHUNKS + (x - x0) / L], (x - x0) % L);
            let i = y * frame.width + x;
            let g = [d_rgb[3 * i], d_rgb[3 * i + 1], d_rgb[3 * i + 2]];
            let last = if g == [0.0; 3] { 0 } else { frame.last[i] };
            deepest = deepest.max(last as usize);
            for c in 0..3 {
                s.g[c][k] = g[c];
            }
            s.last[k] = last;
            s.t_final[k] = frame.final_t[i];
            s.tr[k] = frame.final_t[i];
            s.bg_dot[k] = bg[0] * g[0] + bg[1] * g[1] + bg[2] * g[2];
        }
    }
    (lanes, deepest)
}

/// What a tile's backward reads: the view, its rules, the loss's gradient
/// with respect to its colours (`[h x w x 3]`) and the tile's number.
#[derive(Clone, Copy)]
pub struct BackwardTile<'a> {
    pub cam: &'a RasterCamera,
    pub opt: &'a RasterOptions,
    pub frame: &'a Frame,
    pub d_rgb: &'a [f32],
    pub t: usize,
}

/// The backward of a tile: each entry of its list gets its screen
/// gradient in `out` (the 3DGS paper's walk back to front, which divides
/// the transmittance back out instead of storing it).
pub fn tile_backward(job: BackwardTile<'_>, out: &mut [ScreenGrad]) {
    #[cfg(target_arch = "x86_64")]
    if crate::engine::nn::gemm::has_avx2_fma() {
        // SAFETY: the CPU has the features the function is compiled for.
        return unsafe { tile_backward_avx2(job, out) };
    }
    tile_backward_any(job, out)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn tile_backward_avx2(job: BackwardTile<'_>, out: &mut [ScreenGrad]) {
    tile_backward_any(job, out)
}

#[inline(always)]
pub(super) fn tile_backward_any(job: BackwardTile<'_>, out: &mut [ScreenGrad]) {
    let BackwardTile { cam, opt, frame, d_rgb, t } = job;
    let rect @ [x0, x1, y0, y1] = tile_rect(cam, t);
    let list = &frame.list[frame.tile_ranges[t].clone()];
    let (mut lanes, deepest) = back_lanes(frame, d_rgb, rect);
    let xs = centres(x0);
    for pos in (0..deepest).rev() {
        let p = &frame.drawn[list[pos] as usize];
        let [gx0, gx1, gy0, gy1] = p.pixel_rect(frame.width, frame.height);
        let cols = (gx0.max(x0) - x0, gx1.min(x1).saturating_sub(x0));
        let mut e = [[0.0f32; L]; 9];
        for y in gy0.max(y0)..gy1.min(y1) {
            let dy = y as f32 + 0.5 - p.mean[1];
            for (h, on_lanes) in chunks(cols) {
                let s = &mut lanes[(y - y0) * CHUNKS + h];
                let [a, raw, dx] = lanes_alpha(p, &xs[h], dy, on_lanes, opt.min_alpha);
                walk_back(p, pos as u32, s, [a, raw, dx], dy, &mut e);
            }
        }
        let entry = &mut out[pos];
        for (sum, lanes) in entry.iter_mut().zip(&e) {
            for v in lanes {
                *sum += v;
            }
        }
    }
}

/// One step of the backward's walk for a chunk's pixels: Gaussian `p`, at
/// position `pos` of the tile's list, with alphas `a` (`raw` before the
/// cap) at offsets `dx`, `dy`; its screen gradient is added to `e`'s lanes.
#[inline(always)]
fn walk_back(p: &Splat2D, pos: u32, s: &mut BackLanes, [a, raw, dx]: [[f32; L]; 3], dy: f32, e: &mut [[f32; L]; 9]) {
    let [c0, c1, c2] = p.conic;
    for k in 0..L {
        let on = (pos < s.last[k]) & (a[k] != 0.0);
        let tr = if on { s.tr[k] / (1.0 - a[k]) } else { s.tr[k] };
        s.tr[k] = tr;
        let mut d_a = 0.0;
        for c in 0..3 {
            let acc = s.last_a[k] * s.last_c[c][k] + (1.0 - s.last_a[k]) * s.accum[c][k];
            s.accum[c][k] = if on { acc } else { s.accum[c][k] };
            e[6 + c][k] += if on { a[k] * tr * s.g[c][k] } else { 0.0 };
            d_a += (p.rgb[c] - acc) * s.g[c][k];
            s.last_c[c][k] = if on { p.rgb[c] } else { s.last_c[c][k] };
        }
        let d_a = d_a * tr - s.t_final[k] / (1.0 - a[k]) * s.bg_dot[k];
        s.last_a[k] = if on { a[k] } else { s.last_a[k] };
        // Where alpha is held at its maximum, it has no gradient;
        // a = o exp(power): da/do = a / o, da/dpower = a.
        let gp = if on & (raw[k] < MAX_ALPHA) { d_a * a[k] } else { 0.0 };
        e[5][k] += gp / p.opacity;
        e[2][k] += -0.5 * dx[k] * dx[k] * gp;
        e[3][k] += -dx[k] * dy * gp;
        e[4][k] += -0.5 * dy * dy * gp;
        e[0][k] += gp * (c0 * dx[k] + c1 * dy);
        e[1][k] += gp * (c2 * dy + c1 * dx[k]);
    }
}
