//! What the rasteriser's stages share, and nothing else: the camera and
//! the rules of a view, a Gaussian's projection as the tiles read it, a
//! drawn frame, and a Gaussian's screen-space gradient. A leaf, so that
//! the projection (`raster`), the tiles' loops (`tile`) and the backward
//! (`backward`) each use it and none of them uses another in a circle.

use crate::engine::geometry::camera::Camera;
use crate::engine::geometry::scene::Scene;

/// The gradient of a loss with respect to one Gaussian's projection:
/// mean (2), conic (3), opacity, colour (3).
pub type ScreenGrad = [f32; 9];

/// Side of a tile in pixels.
pub const TILE: usize = 16;

/// The rules of what a Gaussian adds to a pixel (module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RasterOptions {
    /// Alpha below which a Gaussian adds nothing to a pixel (1/255).
    pub min_alpha: f32,
    /// Transmittance below which a pixel takes nothing more (1e-4).
    pub min_transmittance: f32,
    /// The farthest a Gaussian reaches, in standard deviations (3).
    pub radius_sigmas: f32,
    /// Gaussians nearer the camera plane than this (model units) are not
    /// drawn.
    pub near: f32,
}

impl Default for RasterOptions {
    fn default() -> Self {
        Self { min_alpha: 1.0 / 255.0, min_transmittance: 1e-4, radius_sigmas: 3.0, near: 0.01 }
    }
}

impl RasterOptions {
    /// The defaults, drawing nothing nearer than `scene`'s near bound, as
    /// the field the splats come from draws nothing nearer (its rays start
    /// there): a Gaussian just in front of a new view, which no photo saw
    /// from that close, is not drawn over it.
    pub fn for_scene(scene: &Scene) -> Self {
        let default = Self::default();
        Self { near: scene.near.max(default.near), ..default }
    }
}

/// The largest alpha a Gaussian takes (the 3DGS paper's, which keeps the
/// backward's division by `1 - alpha` finite).
pub const MAX_ALPHA: f32 = 0.99;
/// Added to the projected covariance's diagonal (px²): a Gaussian covers at
/// least about a pixel (the paper's low-pass filter).
pub const DILATION: f32 = 0.3;
/// How far outside the view (as a multiple of the half field of view) a
/// Gaussian's centre may lie before its projection's Jacobian is taken at
/// the view's edge instead (the paper's 1.3).
pub const FRUSTUM_SLACK: f32 = 1.3;

/// A pinhole camera in model space, as the rasteriser uses it: its frame
/// has x right, y down and z forward (the COLMAP convention; [`Camera`] is
/// OpenGL's, y up and looking down -z).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RasterCamera {
    pub width: u32,
    pub height: u32,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    /// Model-to-camera rotation (rows).
    pub rot: [[f32; 3]; 3],
    /// The camera's centre in model space.
    pub origin: [f32; 3],
}

impl RasterCamera {
    /// `camera` (world units, any distortion ignored) in `scene`'s model
    /// space.
    pub fn new(camera: &Camera, scene: &Scene) -> Self {
        let m = &camera.c2w;
        let col = |j: usize, s: f32| [s * m[0][j], s * m[1][j], s * m[2][j]];
        let o = camera.origin();
        let origin = [
            (o.x - scene.centre[0]) * scene.scale,
            (o.y - scene.centre[1]) * scene.scale,
            (o.z - scene.centre[2]) * scene.scale,
        ];
        Self {
            width: camera.width,
            height: camera.height,
            fx: camera.fx,
            fy: camera.fy,
            cx: camera.cx,
            cy: camera.cy,
            rot: [col(0, 1.0), col(1, -1.0), col(2, -1.0)],
            origin,
        }
    }

    /// A model-space point in the camera's frame.
    pub fn to_camera(&self, p: [f32; 3]) -> [f32; 3] {
        let d = [p[0] - self.origin[0], p[1] - self.origin[1], p[2] - self.origin[2]];
        let r = &self.rot;
        [
            r[0][0] * d[0] + r[0][1] * d[1] + r[0][2] * d[2],
            r[1][0] * d[0] + r[1][1] * d[1] + r[1][2] * d[2],
            r[2][0] * d[0] + r[2][1] * d[1] + r[2][2] * d[2],
        ]
    }

    /// Where camera-space point `t` (in front: `t[2] > 0`) falls on the
    /// image, in pixels.
    #[inline(always)]
    pub fn pixel(&self, t: [f32; 3]) -> [f32; 2] {
        [self.fx * t[0] / t[2] + self.cx, self.fy * t[1] / t[2] + self.cy]
    }

    pub fn tiles_x(&self) -> usize {
        (self.width as usize).div_ceil(TILE)
    }
    pub fn tiles_y(&self) -> usize {
        (self.height as usize).div_ceil(TILE)
    }
}

/// One Gaussian as a camera sees it.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Projected {
    /// The projected centre (pixels).
    pub mean: [f32; 2],
    /// The inverse of the dilated 2D covariance (`xx xy yy`).
    pub conic: [f32; 3],
    /// The dilated 2D covariance (`xx xy yy`).
    pub cov: [f32; 3],
    pub opacity: f32,
    /// Colour, clamped at 0.
    pub rgb: [f32; 3],
    /// Which colour channels were clamped (bits 0-2) and whether the
    /// Jacobian's x (bit 3) or y (bit 4) was taken at the view's edge.
    pub clamped: u8,
    /// The centre in the camera's frame.
    pub t: [f32; 3],
    /// Distance from the camera centre (model units).
    pub dist: f32,
    /// Half-widths of the box the Gaussian reaches (pixels).
    pub extent: [f32; 2],
    pub visible: bool,
}

impl Projected {
    /// The pixels `[x0, x1) x [y0, y1)` whose centres lie in the box.
    pub fn pixel_rect(&self, width: usize, height: usize) -> [usize; 4] {
        pixel_rect(self.mean, self.extent, width, height)
    }
}

const _: () = assert!(std::mem::size_of::<Splat2D>() == 64);

/// The pixels `[x0, x1) x [y0, y1)` whose centres lie in the box of
/// half-widths `extent` around `mean`.
#[inline]
pub fn pixel_rect(mean: [f32; 2], extent: [f32; 2], width: usize, height: usize) -> [usize; 4] {
    // Pixel i's centre is i + 0.5: inside when |i + 0.5 - m| <= e.
    let lo = |m: f32, e: f32| (m - e - 0.5).ceil().max(0.0) as usize;
    let hi = |m: f32, e: f32, n: usize| (((m + e - 0.5).floor() + 1.0).max(0.0) as usize).min(n);
    let [mx, my] = mean;
    let [ex, ey] = extent;
    [lo(mx, ex), hi(mx, ex, width), lo(my, ey), hi(my, ey, height)]
}

/// What the tiles read of a drawn Gaussian's projection, packed and kept
/// in drawing order so that a tile's walk reads memory in one direction.
/// Its 64 bytes are one cache line, aligned as one, so that a tile's one
/// prefetch brings all of it.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[repr(C, align(64))]
pub struct Splat2D {
    pub mean: [f32; 2],
    pub conic: [f32; 3],
    pub opacity: f32,
    pub rgb: [f32; 3],
    pub dist: f32,
    pub extent: [f32; 2],
    /// Where the rows' spans lie: on the row `dy` below the mean, the
    /// pixels whose alpha reaches `min_alpha` are those `dx` with `(dx -
    /// shift dy)² <= spread (reach - dy² / Σ'yy)`, the 2D Gaussian's
    /// conditional mean and variance of x given y (`shift = Σ'xy / Σ'yy`,
    /// `spread = det Σ' / Σ'yy`) and `reach = 2 ln(o / min_alpha)`; the
    /// last is kept as `reach - dy² / Σ'yy` at `dy = 0` and `1 / Σ'yy`.
    pub shift: f32,
    pub spread: f32,
    pub reach: f32,
    pub inv_yy: f32,
}

impl Splat2D {
    pub(super) fn of(p: &Projected, min_alpha: f32) -> Self {
        let [xx, xy, yy] = p.cov;
        Self {
            mean: p.mean,
            conic: p.conic,
            opacity: p.opacity,
            rgb: p.rgb,
            dist: p.dist,
            extent: p.extent,
            shift: xy / yy,
            spread: (xx * yy - xy * xy) / yy,
            reach: 2.0 * (p.opacity / min_alpha).ln(),
            inv_yy: 1.0 / yy,
        }
    }

    /// The columns `[x0, x1)` of the row whose centres lie `dy` below the
    /// mean that may take this Gaussian: a superset, by at least a pixel,
    /// of those whose alpha reaches `min_alpha` (f32's rounding of the
    /// span is far below that), within `[lo, hi)`.
    #[inline(always)]
    pub fn row_span(&self, dy: f32, lo: usize, hi: usize) -> (usize, usize) {
        let room = self.reach - dy * dy * self.inv_yy;
        if room.is_nan() {
            // Take the whole row, whose pixels the exact rule then judges.
            return (lo, hi);
        }
        if room < 0.0 {
            // No pixel of the row reaches min_alpha.
            return (lo, lo);
        }
        let half = (self.spread * room).sqrt() * 1.001 + 1.0;
        let c = self.mean[0] + self.shift * dy - 0.5;
        let x0 = (c - half).ceil().max(lo as f32) as usize;
        let x1 = ((c + half).floor() + 1.0).max(0.0) as usize;
        (x0.max(lo), x1.min(hi))
    }

    pub fn pixel_rect(&self, width: usize, height: usize) -> [usize; 4] {
        pixel_rect(self.mean, self.extent, width, height)
    }
}

/// A rendered view and what its backward needs.
#[derive(Clone, Debug, Default)]
pub struct Frame {
    pub width: usize,
    pub height: usize,
    /// `[h x w x 3]`, composited on the background.
    pub rgb: Vec<f32>,
    /// Expected distance from the camera (model units; 0 where nothing was
    /// drawn).
    pub depth: Vec<f32>,
    /// `1 - T_final`.
    pub opacity: Vec<f32>,
    /// Each Gaussian's projection.
    pub projected: Vec<Projected>,
    /// The drawn Gaussians, front to back.
    pub order: Vec<u32>,
    /// Their projections, in that order.
    pub drawn: Vec<Splat2D>,
    /// Each tile's range of `list`.
    pub tile_ranges: Vec<std::ops::Range<usize>>,
    /// The Gaussians of each tile, front to back, as positions in `order`.
    pub list: Vec<u32>,
    /// Per pixel: the position in its tile's list after the last Gaussian
    /// it took (relative to the tile's range start).
    pub last: Vec<u32>,
    /// Per pixel: transmittance after the last Gaussian.
    pub final_t: Vec<f32>,
    pub background: [f32; 3],
}
