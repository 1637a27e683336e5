//! The per-tile inner loops of the rasteriser (`raster::forward`) and of
//! its backward (`backward::backward`), written in chunks of [`L`] pixels
//! of a row with no branches inside a chunk, so that the compiler turns
//! each into a few vector instructions: every pixel of the chunk computes
//! its alpha (with [`exp_neg`], a polynomial `exp`, where `libm`'s call
//! would stop the vectorising), and a mask says which pixels take it. The
//! rule of what a Gaussian adds to a pixel is the module docs' of
//! `raster`, exactly.
//!
//! Both walk, on each row a Gaussian reaches, only the span of columns
//! whose alpha may reach `min_alpha` ([`Splat2D::row_span`]): most
//! Gaussians are a few pixels wide, and a chunk then holds the whole span.
//! On x86-64 the code is compiled again for AVX2 and FMA, and chosen at
//! run time ([`Build`]). With AVX-512 a vector holds a tile's whole row of
//! 16 pixels: each row a Gaussian reaches is then one vector, with no span
//! to work out (a third build of the forward, the whole-row walk; a
//! Gaussian whose box is at most [`L`] columns of the tile still takes one
//! chunk). Tests check that every build gives the same bits.

use super::frame::{Frame, MAX_ALPHA, RasterCamera, RasterOptions, ScreenGrad, Splat2D, TILE};

/// `exp(x)` for `x <= 0` (larger `x` are taken as 0), within 2 units in the
/// last place of f32 down to `x = -87`, below which it is that of `-87`
/// (about 1.6e-38, an alpha far below any cut). A range reduction to
/// `x = n ln 2 + r` with `|r| <= ln 2 / 2`, and `exp(r)` by its Taylor
/// series to `r^6` (the first left out, `r^7 / 7!`, is below 1.2e-7 of it).
/// Its steps are fused multiply-adds: one instruction in the vector builds;
/// in the portable build on a CPU without FMA, a call to the correctly
/// rounded `fmaf` (slow, but the same bits).
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
    let big = x.mul_add(LOG2E, ROUND);
    let n = big - ROUND;
    let k = big.to_bits().wrapping_sub(ROUND.to_bits());
    let r = (-n).mul_add(LN2_LO, (-n).mul_add(LN2_HI, x));
    let mut p: f32 = 1.0 / 720.0;
    for c in [1.0 / 120.0, 1.0 / 24.0, 1.0 / 6.0, 0.5, 1.0, 1.0] {
        p = p.mul_add(r, c);
    }
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
fn lanes_alpha<const N: usize>(
    p: &Splat2D,
    xs: &[f32; N],
    dy: f32,
    cols: (usize, usize),
    min_alpha: f32,
) -> [[f32; N]; 3] {
    let (mut a, mut raw, mut dx) = ([0.0f32; N], [0.0f32; N], [0.0f32; N]);
    let [c0, c1, c2] = p.conic;
    let y_in = dy.abs() <= p.extent[1];
    // The lanes' bounds as floats, and each test a choice of its own:
    // every test of a lane is then a comparison of 32-bit floats and a
    // mask of them (a mix of tests of other widths, or their conjunction as
    // booleans, costs conversions between mask widths). Small integers are
    // exact in f32.
    let (from, to) = (cols.0 as f32, cols.1 as f32);
    let lanes: [f32; N] = std::array::from_fn(|k| k as f32);
    for k in 0..N {
        let d = xs[k] - p.mean[0];
        let power = -0.5 * (c0 * d * d + c2 * dy * dy) - c1 * d * dy;
        let r = p.opacity * exp_neg(power);
        let mut v = r.min(MAX_ALPHA);
        v = if v >= min_alpha { v } else { 0.0 };
        v = if power <= 0.0 { v } else { 0.0 };
        v = if d.abs() <= p.extent[0] { v } else { 0.0 };
        v = if lanes[k] >= from { v } else { 0.0 };
        v = if lanes[k] < to { v } else { 0.0 };
        a[k] = if y_in { v } else { 0.0 };
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

/// Columns a row of the forward's tile state holds: a chunk of [`L`]
/// lanes may start at any of the tile's columns.
const ROW: usize = TILE + L;

/// The forward's state of a tile's pixels, row by row ([`ROW`] apart; the
/// columns past the tile's are never taken): transmittance, colour, depth,
/// how many of the tile's list the pixel took, and whether it still takes
/// any (1.0) or its transmittance would have fallen too low (0.0).
struct Composite {
    t: [f32; TILE * ROW],
    rgb: [[f32; TILE * ROW]; 3],
    depth: [f32; TILE * ROW],
    last: [u32; TILE * ROW],
    live: [f32; TILE * ROW],
}

/// A build of the tile loops: the portable one, or one compiled for a
/// CPU's vector instructions and chosen at run time (as `nn::gemm` does).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Build {
    /// Chunks of [`L`] lanes, for any CPU.
    Portable,
    /// The portable code compiled for AVX2 and FMA (same bits).
    Avx2,
    /// The forward's whole-row walk, a tile's row of 16 pixels as one
    /// vector of AVX-512 (F, VL) with FMA (same bits); the backward is the
    /// AVX2 build's.
    Avx512,
}

impl Build {
    /// The fastest build this CPU runs.
    pub fn best() -> Build {
        [Build::Avx512, Build::Avx2].into_iter().find(|b| b.available()).unwrap_or(Build::Portable)
    }

    /// Whether this CPU runs it (std caches the answers).
    pub fn available(self) -> bool {
        #[cfg(target_arch = "x86_64")]
        let (avx2, avx512) = (
            crate::engine::nn::gemm::has_avx2_fma(),
            is_x86_feature_detected!("avx512f") && is_x86_feature_detected!("avx512vl"),
        );
        #[cfg(not(target_arch = "x86_64"))]
        let (avx2, avx512) = (false, false);
        match self {
            Build::Portable => true,
            Build::Avx2 => avx2,
            Build::Avx512 => avx2 && avx512,
        }
    }
}

/// The forward of tile `t`: its pixels, composited front to back.
pub fn composite_tile(frame: &Frame, cam: &RasterCamera, opt: &RasterOptions, t: usize) -> TileOut {
    composite_tile_in(Build::best(), frame, cam, opt, t)
}

/// [`composite_tile`] in the given build, which the CPU must run.
pub fn composite_tile_in(build: Build, frame: &Frame, cam: &RasterCamera, opt: &RasterOptions, t: usize) -> TileOut {
    assert!(build.available(), "this CPU does not run the {build:?} build");
    match build {
        // SAFETY (both): the CPU has the features the function is compiled
        // for (asserted).
        #[cfg(target_arch = "x86_64")]
        Build::Avx512 => unsafe { composite_tile_avx512(frame, cam, opt, t) },
        #[cfg(target_arch = "x86_64")]
        Build::Avx2 => unsafe { composite_tile_avx2(frame, cam, opt, t) },
        _ => composite_tile_any(frame, cam, opt, t),
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn composite_tile_avx2(frame: &Frame, cam: &RasterCamera, opt: &RasterOptions, t: usize) -> TileOut {
    composite_tile_any(frame, cam, opt, t)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
unsafe fn composite_tile_avx512(frame: &Frame, cam: &RasterCamera, opt: &RasterOptions, t: usize) -> TileOut {
    composite_tile_rows(frame, cam, opt, t)
}

/// The forward of tile `t` a whole row of [`TILE`] lanes at a time: with
/// vectors of 16 lanes, a Gaussian's row of the tile is one vector, and
/// its span ([`Splat2D::row_span`]) is not worth working out. The same
/// arithmetic per pixel as [`composite_tile_any`], so the same bits.
#[inline(always)]
pub(super) fn composite_tile_rows(frame: &Frame, cam: &RasterCamera, opt: &RasterOptions, t: usize) -> TileOut {
    let [x0, x1, y0, _] = tile_rect(cam, t);
    let xs: [f32; TILE] = std::array::from_fn(|k| (x0 + k) as f32 + 0.5);
    walk_tile(
        frame,
        cam,
        t,
        #[inline(always)]
        |st, p, [gx0, gx1, ry0, ry1], took| {
            let cols = (gx0.max(x0) - x0, gx1.min(x1).max(x0) - x0);
            if cols.1 - cols.0 <= L {
                // A narrow box: its columns of the tile fit a half vector.
                let narrow: [f32; L] = std::array::from_fn(|k| xs[cols.0] + k as f32);
                for y in ry0..ry1 {
                    let dy = y as f32 + 0.5 - p.mean[1];
                    let base = (y - y0) * ROW + cols.0;
                    composite_lanes(p, st, base, &narrow, (0, cols.1 - cols.0), dy, took, opt);
                }
            } else {
                for y in ry0..ry1 {
                    let dy = y as f32 + 0.5 - p.mean[1];
                    composite_lanes(p, st, (y - y0) * ROW, &xs, cols, dy, took, opt);
                }
            }
        },
    )
}

/// The forward of tile `t`, walked a Gaussian at a time over the rows it
/// reaches; on each row, only the span whose alpha may reach `min_alpha`
/// ([`Splat2D::row_span`]), in chunks of [`L`] lanes from its first column.
#[inline(always)]
pub(super) fn composite_tile_any(frame: &Frame, cam: &RasterCamera, opt: &RasterOptions, t: usize) -> TileOut {
    let [x0, x1, y0, _] = tile_rect(cam, t);
    let half: [f32; L] = std::array::from_fn(|k| k as f32 + 0.5);
    walk_tile(
        frame,
        cam,
        t,
        #[inline(always)]
        |st, p, [gx0, gx1, ry0, ry1], took| {
            for y in ry0..ry1 {
                let dy = y as f32 + 0.5 - p.mean[1];
                if dy.abs() > p.extent[1] {
                    continue;
                }
                let (sx0, sx1) = p.row_span(dy, gx0.max(x0), gx1.min(x1));
                let mut x = sx0;
                while x < sx1 {
                    let base = (y - y0) * ROW + (x - x0);
                    let xs: [f32; L] = std::array::from_fn(|k| x as f32 + half[k]);
                    composite_lanes(p, st, base, &xs, (0, sx1 - x), dy, took, opt);
                    x += L;
                }
            }
        },
    )
}

/// The walk both forwards share: tile `t`'s list front to back, each
/// Gaussian drawn by `draw(state, gaussian, [x0, x1, y0, y1], took)` (its
/// box's columns in the image, the tile's rows it reaches, and what a
/// pixel's `last` becomes where it takes it), then the tile's pixels.
#[inline(always)]
fn walk_tile(
    frame: &Frame,
    cam: &RasterCamera,
    t: usize,
    mut draw: impl FnMut(&mut Composite, &Splat2D, [usize; 4], u32),
) -> TileOut {
    let [x0, x1, y0, y1] = tile_rect(cam, t);
    let w = x1 - x0;
    let mut st = Box::new(Composite {
        t: [1.0; TILE * ROW],
        rgb: [[0.0; TILE * ROW]; 3],
        depth: [0.0; TILE * ROW],
        last: [0; TILE * ROW],
        live: [1.0; TILE * ROW],
    });
    let (width, height) = (cam.width as usize, cam.height as usize);
    let list = &frame.list[frame.tile_ranges[t].clone()];
    for (pos, &g) in list.iter().enumerate() {
        // Every so many Gaussians: whether any pixel still takes them (a
        // count kept per chunk would cost a sum across its lanes each
        // time; a stopped pixel takes nothing, so a later stop changes no
        // bit).
        if pos % STOP_CHECK == 0 && (0..y1 - y0).all(|r| st.live[r * ROW..r * ROW + w].iter().all(|&l| l == 0.0)) {
            break;
        }
        // The list's Gaussians lie far apart in `drawn`: ask for one a few
        // places ahead while this one is drawn.
        if let Some(&ahead) = list.get(pos + PREFETCH) {
            prefetch(&frame.drawn[ahead as usize]);
        }
        let p = &frame.drawn[g as usize];
        let [gx0, gx1, gy0, gy1] = p.pixel_rect(width, height);
        draw(&mut st, p, [gx0, gx1, gy0.max(y0), gy1.min(y1)], pos as u32 + 1);
    }
    let mut pixels = Vec::with_capacity(w * (y1 - y0));
    for r in 0..y1 - y0 {
        for k in r * ROW..r * ROW + w {
            let rgb = [st.rgb[0][k], st.rgb[1][k], st.rgb[2][k]];
            pixels.push(PixelOut { rgb, depth: st.depth[k], t: st.t[k], last: st.last[k] });
        }
    }
    TileOut { w, pixels }
}

/// How many places of a tile's list ahead the forward asks for a
/// Gaussian's projection.
const PREFETCH: usize = 8;

/// How many Gaussians of a tile's list the forward draws between its
/// checks of whether all its pixels stopped.
const STOP_CHECK: usize = 16;

/// Asks the CPU to bring `p` into its cache (a hint only).
#[inline(always)]
fn prefetch(p: &Splat2D) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: a prefetch reads nothing and changes nothing; its address is
    // a reference's.
    #[allow(unused_unsafe)]
    unsafe {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        _mm_prefetch::<_MM_HINT_T0>((p as *const Splat2D).cast());
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = p;
}

/// Composites Gaussian `p` over the first `n` of the [`L`] pixels from
/// `base` of the tile's state (centres `xs`, `dy` below its mean), with no
/// branches: the rule of the module docs, lane by lane. `took` is what a
/// pixel's `last` becomes where it takes `p`.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn composite_lanes<const N: usize>(
    p: &Splat2D,
    st: &mut Composite,
    base: usize,
    xs: &[f32; N],
    cols: (usize, usize),
    dy: f32,
    took: u32,
    opt: &RasterOptions,
) {
    let lanes = base..base + N;
    fn get<T: Copy + Default, const N: usize>(v: &[T]) -> [T; N] {
        let mut out = [T::default(); N];
        out.copy_from_slice(&v[..N]);
        out
    }
    let [a, _, _] = lanes_alpha(p, xs, dy, cols, opt.min_alpha);
    let (mut t, mut live, mut last): ([f32; N], [f32; N], [u32; N]) =
        (get(&st.t[lanes.clone()]), get(&st.live[lanes.clone()]), get(&st.last[lanes.clone()]));
    let mut depth: [f32; N] = get(&st.depth[lanes.clone()]);
    // Spelt out: `[0, 1, 2].map(..)` here became calls to `memcpy`.
    let mut rgb: [[f32; N]; 3] =
        [get(&st.rgb[0][lanes.clone()]), get(&st.rgb[1][lanes.clone()]), get(&st.rgb[2][lanes.clone()])];
    // Arithmetic where it gives the same bits as a choice (colours and
    // depths only grow from 0, and `x (1 - 0) = x`), so that the loop
    // vectorises.
    for k in 0..N {
        let a1 = a[k] * live[k];
        let stop = t[k] * (1.0 - a1) < opt.min_transmittance;
        let a2 = if stop { 0.0 } else { a1 };
        let wgt = a2 * t[k];
        for c in 0..3 {
            rgb[c][k] += wgt * p.rgb[c];
        }
        depth[k] += wgt * p.dist;
        t[k] *= 1.0 - a2;
        last[k] = if a2 != 0.0 { took } else { last[k] };
        live[k] = if stop { 0.0 } else { live[k] };
    }
    st.t[lanes.clone()].copy_from_slice(&t);
    st.live[lanes.clone()].copy_from_slice(&live);
    st.last[lanes.clone()].copy_from_slice(&last);
    st.depth[lanes.clone()].copy_from_slice(&depth);
    for c in 0..3 {
        st.rgb[c][lanes.clone()].copy_from_slice(&rgb[c]);
    }
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
    /// The most any of the chunk's pixels took (the walk passes it by
    /// until then).
    took: u32,
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
            s.took = s.took.max(last);
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
    // The whole-row walk does not pay here: most of a backward step is per
    // Gaussian, and a narrow Gaussian would take a whole row of lanes.
    tile_backward_in(if Build::Avx2.available() { Build::Avx2 } else { Build::Portable }, job, out)
}

/// [`tile_backward`] in the given build (the AVX-512 one is the AVX2 one),
/// which the CPU must run.
pub fn tile_backward_in(build: Build, job: BackwardTile<'_>, out: &mut [ScreenGrad]) {
    assert!(build.available(), "this CPU does not run the {build:?} build");
    match build {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: the CPU has the features the function is compiled for
        // (asserted).
        Build::Avx2 | Build::Avx512 => unsafe { tile_backward_avx2(job, out) },
        _ => tile_backward_any(job, out),
    }
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
        // Back to front, the walk asks for the Gaussian a few places
        // nearer the front while this one is drawn, as the forward does.
        if let Some(&ahead) = pos.checked_sub(PREFETCH).map(|k| &list[k]) {
            prefetch(&frame.drawn[ahead as usize]);
        }
        let p = &frame.drawn[list[pos] as usize];
        let [gx0, gx1, gy0, gy1] = p.pixel_rect(frame.width, frame.height);
        let mut e = [[0.0f32; L]; 9];
        for y in gy0.max(y0)..gy1.min(y1) {
            let dy = y as f32 + 0.5 - p.mean[1];
            // Lanes outside the row's span take nothing and add nothing.
            let (sx0, sx1) = p.row_span(dy, gx0.max(x0), gx1.min(x1));
            let cols = (sx0.saturating_sub(x0), sx1.saturating_sub(x0));
            for (h, on_lanes) in chunks(cols) {
                let s = &mut lanes[(y - y0) * CHUNKS + h];
                if pos as u32 >= s.took {
                    // Every pixel of the chunk stopped before this Gaussian.
                    continue;
                }
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
    // The chunk's state in locals, chosen lane by lane and stored back
    // whole: updated in place, a lane's "keep the old value" became masked
    // loads and stores.
    let (mut tr, mut accum, mut last_a, mut last_c) = (s.tr, s.accum, s.last_a, s.last_c);
    for k in 0..L {
        let on = (pos < s.last[k]) & (a[k] != 0.0);
        // One division for both transmittances divided back out.
        let inv = 1.0 / (1.0 - a[k]);
        let t = if on { tr[k] * inv } else { tr[k] };
        tr[k] = t;
        let mut d_a = 0.0;
        for c in 0..3 {
            let acc = last_a[k] * last_c[c][k] + (1.0 - last_a[k]) * accum[c][k];
            accum[c][k] = if on { acc } else { accum[c][k] };
            e[6 + c][k] += if on { a[k] * t * s.g[c][k] } else { 0.0 };
            d_a += (p.rgb[c] - acc) * s.g[c][k];
            last_c[c][k] = if on { p.rgb[c] } else { last_c[c][k] };
        }
        let d_a = d_a * t - s.t_final[k] * inv * s.bg_dot[k];
        last_a[k] = if on { a[k] } else { last_a[k] };
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
    (s.tr, s.accum, s.last_a, s.last_c) = (tr, accum, last_a, last_c);
}
