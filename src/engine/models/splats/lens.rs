//! Cameras with lens distortion, for a rasteriser that draws pinhole
//! images: a distorted view is drawn through a pinhole camera wide enough
//! to hold it and resampled (bilinear) at each pixel's undistorted
//! position, and a distorted photo is resampled into its own pinhole
//! camera the same way before a bake fits splats to it.

use rayon::prelude::*;

use crate::engine::geometry::camera::{Camera, Distortion};

/// The pinhole camera (the same focal lengths, no distortion) whose image
/// holds every undistorted pixel centre of `camera`, with a pixel's margin
/// for the bilinear reads; at most twice `camera`'s size a side.
pub fn pinhole_around(camera: &Camera) -> Camera {
    let (w, h) = (camera.width as f32, camera.height as f32);
    let (mut lo, mut hi) = ([f32::INFINITY; 2], [f32::NEG_INFINITY; 2]);
    let steps = 64;
    for s in 0..=steps {
        let f = s as f32 / steps as f32;
        for (u, v) in [(f * w, 0.0), (f * w, h), (0.0, f * h), (w, f * h)] {
            let (x, y) = undistorted(camera, u, v);
            lo = [lo[0].min(x), lo[1].min(y)];
            hi = [hi[0].max(x), hi[1].max(y)];
        }
    }
    let (fx, fy) = (camera.fx, camera.fy);
    // A wild distortion's edge may run off: the size is capped below, and
    // the pixels past it are filled.
    let lo = [lo[0].max(-2.0 * w / fx), lo[1].max(-2.0 * h / fy)];
    // The principal point moves by whole pixels, so that where the lens
    // hardly distorts (the centre) a pixel reads one pinhole pixel, not the
    // mean of four: a fractional shift blurs every view by half a pixel.
    let shift = [(-lo[0] * fx + 1.5 - camera.cx).ceil(), (-lo[1] * fy + 1.5 - camera.cy).ceil()];
    let width = ((hi[0] - lo[0]) * fx).ceil() as u32 + 4;
    let height = ((hi[1] - lo[1]) * fy).ceil() as u32 + 4;
    Camera {
        width: width.min(2 * camera.width),
        height: height.min(2 * camera.height),
        fx,
        fy,
        cx: camera.cx + shift[0],
        cy: camera.cy + shift[1],
        distortion: Distortion::default(),
        c2w: camera.c2w,
    }
}

/// The undistorted normalised coordinates of `camera`'s image point `(u,
/// v)` (pixels).
fn undistorted(camera: &Camera, u: f32, v: f32) -> (f32, f32) {
    camera.distortion.undistort((u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy)
}

/// Bilinear read of channel-interleaved `img` (`w x h x ch`) at continuous
/// pixel coordinates `(u, v)` (pixel `(i, j)`'s centre at `(i + 0.5, j +
/// 0.5)`), or `None` outside the pixel centres' hull.
fn bilinear(img: &[f32], w: usize, h: usize, ch: usize, u: f32, v: f32, out: &mut [f32]) -> bool {
    let (x, y) = (u - 0.5, v - 0.5);
    if !(x >= 0.0 && y >= 0.0 && x <= (w - 1) as f32 && y <= (h - 1) as f32) {
        return false;
    }
    let (i, j) = ((x as usize).min(w.saturating_sub(2)), (y as usize).min(h.saturating_sub(2)));
    let (fx, fy) = (x - i as f32, y - j as f32);
    let (i1, j1) = ((i + 1).min(w - 1), (j + 1).min(h - 1));
    for c in 0..ch {
        let at = |a: usize, b: usize| img[(b * w + a) * ch + c];
        let top = at(i, j) * (1.0 - fx) + at(i1, j) * fx;
        let bottom = at(i, j1) * (1.0 - fx) + at(i1, j1) * fx;
        out[c] = top * (1.0 - fy) + bottom * fy;
    }
    true
}

/// Where each of a distorted camera's pixel centres lies in the image of
/// its pinhole camera ([`pinhole_around`]): worked out once a view, for
/// each image the view resamples (colours, distances, opacities).
pub struct Resampling {
    width: usize,
    /// The pinhole image's size.
    pin: (usize, usize),
    /// Per pixel, row by row: its position in the pinhole image (pixels).
    at: Vec<[f32; 2]>,
}

impl Resampling {
    /// `camera`'s pixels in `pin`'s image (the rows in parallel: undoing a
    /// distortion is an iteration per pixel).
    pub fn new(camera: &Camera, pin: &Camera) -> Self {
        let (w, h) = (camera.width as usize, camera.height as usize);
        let mut at = vec![[0.0f32; 2]; w * h];
        at.par_chunks_mut(w.max(1)).enumerate().for_each(|(j, row)| {
            for (i, a) in row.iter_mut().enumerate() {
                let (x, y) = undistorted(camera, i as f32 + 0.5, j as f32 + 0.5);
                *a = [x * pin.fx + pin.cx, y * pin.fy + pin.cy];
            }
        });
        Self { width: w, pin: (pin.width as usize, pin.height as usize), at }
    }

    /// The distorted view of `image` (`ch` channels), drawn by the pinhole
    /// camera; `fill` where a pixel falls outside it.
    pub fn apply(&self, image: &[f32], ch: usize, fill: &[f32]) -> Vec<f32> {
        let mut out = vec![0.0f32; self.at.len() * ch];
        let (pw, ph) = self.pin;
        out.par_chunks_mut((self.width * ch).max(1)).zip(self.at.par_chunks(self.width.max(1))).for_each(
            |(row, at)| {
                for (px, &[u, v]) in row.chunks_exact_mut(ch).zip(at) {
                    if !bilinear(image, pw, ph, ch, u, v, px) {
                        px.copy_from_slice(fill);
                    }
                }
            },
        );
        out
    }
}

/// A distorted camera's photo (`rgb`, `[h x w x 3]`) as its pinhole part
/// (the same camera, no distortion) would have taken it: NaN where the
/// photo does not reach.
pub fn undistort_photo(camera: &Camera, rgb: &[f32]) -> Vec<f32> {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let mut out = vec![f32::NAN; w * h * 3];
    for j in 0..h {
        for i in 0..w {
            let x = (i as f32 + 0.5 - camera.cx) / camera.fx;
            let y = (j as f32 + 0.5 - camera.cy) / camera.fy;
            let (xd, yd) = camera.distortion.distort(x, y);
            let (u, v) = (xd * camera.fx + camera.cx, yd * camera.fy + camera.cy);
            let px = &mut out[(j * w + i) * 3..(j * w + i + 1) * 3];
            if !bilinear(rgb, w, h, 3, u, v, px) {
                px.fill(f32::NAN);
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::geometry::camera::look_at;
    use crate::engine::geometry::math::Vec3;

    fn distorted() -> Camera {
        let c2w = look_at(Vec3::new(0.0, -3.0, 0.0), Vec3::splat(0.0), Vec3::new(0.0, 0.0, 1.0)).unwrap();
        let mut c = Camera::from_fov(60, 40, 1.0, c2w);
        c.cx += 2.5;
        c.distortion = Distortion { k1: 0.12, k2: -0.03, p1: 0.004, p2: -0.002 };
        c
    }

    /// An image that is a smooth function of the viewing direction.
    fn of_direction(camera: &Camera, undistorted_rays: bool) -> Vec<f32> {
        let mut img = Vec::new();
        for j in 0..camera.height {
            for i in 0..camera.width {
                let (u, v) = (i as f32 + 0.5, j as f32 + 0.5);
                let (x, y) = if undistorted_rays {
                    undistorted(camera, u, v)
                } else {
                    ((u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy)
                };
                img.extend_from_slice(&[0.5 + 0.4 * (2.0 * x).sin(), 0.5 + 0.4 * (1.5 * y).cos(), x * y]);
            }
        }
        img
    }

    #[test]
    fn a_distorted_view_is_its_pinhole_image_resampled() {
        let cam = distorted();
        let pin = pinhole_around(&cam);
        assert!(pin.distortion.is_identity() && pin.width >= cam.width && pin.height >= cam.height);
        // What the pinhole camera sees of a direction-coloured world,
        // resampled, is what the distorted camera sees of it.
        let got = Resampling::new(&cam, &pin).apply(&of_direction(&pin, false), 3, &[9.0; 3]);
        let want = of_direction(&cam, true);
        let worst = got.iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(0.0, f32::max);
        assert!(worst < 2e-3, "worst difference {worst}");
    }

    #[test]
    fn where_the_lens_hardly_distorts_a_pixel_reads_one_pinhole_pixel() {
        let cam = distorted();
        let pin = pinhole_around(&cam);
        let at = Resampling::new(&cam, &pin);
        // The pixel at the principal point: its ray is undistorted, so it
        // lands on a pinhole pixel's centre (a bilinear read of one pixel),
        // not between pixels (the mean of up to four: a blur).
        let (i, j) = (cam.cx.floor() as usize, cam.cy.floor() as usize);
        let [u, v] = at.at[j * cam.width as usize + i];
        let off = |p: f32| (p - 0.5 - (p - 0.5).round()).abs();
        let (du, dv) = ((i as f32 + 0.5 - cam.cx) / cam.fx, (j as f32 + 0.5 - cam.cy) / cam.fy);
        // Near the centre the distortion moves a pixel by under 1e-2 px.
        assert!(du.abs() < 0.02 && dv.abs() < 0.02);
        assert!(off(u) < 0.01 && off(v) < 0.01, "pixel ({i}, {j}) reads the pinhole image at ({u}, {v})");
    }

    #[test]
    fn an_undistorted_photo_is_the_pinhole_cameras_view() {
        let cam = distorted();
        let mut pin_part = cam.clone();
        pin_part.distortion = Distortion::default();
        let photo = of_direction(&cam, true);
        let got = undistort_photo(&cam, &photo);
        let want = of_direction(&pin_part, false);
        let (mut worst, mut missing) = (0.0f32, 0);
        for (a, b) in got.iter().zip(&want) {
            if a.is_nan() {
                missing += 1;
            } else {
                worst = worst.max((a - b).abs());
            }
        }
        assert!(worst < 2e-3, "worst difference {worst}");
        // Pincushion distortion: the pinhole image's corners are past the
        // photo's edge, and only those.
        assert!(missing > 0 && missing < got.len() / 10, "{missing} of {} missing", got.len());
    }
}
