//! The views a mesh is made from: the model rendered from where its
//! training cameras stood, each turned to look at the crop box and framed
//! to hold it, so that every view is one the model learnt to draw. Their
//! depths make the surface and their colours its texture.

use std::sync::atomic::AtomicBool;

use crate::engine::dataset::{Dataset, Frame, Split};
use crate::engine::geometry::camera::{Camera, look_at};
use crate::engine::geometry::math::{Ray, Vec3};
use crate::engine::mesh::MeshError;
use crate::engine::models::splats::SplatsModel;
use crate::engine::models::splats::crop::{self, CropBox, crop_around};
use crate::engine::models::{Model, RenderOptions};
use crate::engine::view::{render_rays_until, render_view_until};

/// Opacity from which a pixel's ray counts as meeting a surface.
const SOLID: f32 = 0.5;

/// A rendered view, as the mesh uses it.
#[derive(Clone)]
pub struct SurfaceView {
    pub camera: Camera,
    /// Per pixel, how far along its ray the surface is (world units), or
    /// `None` where the ray meets none (a photo's: `Some(NaN)` where it
    /// shows the object, at a distance not known).
    pub surface: Vec<Option<f32>>,
    /// Per pixel, the surface's colour (not darkened by partial opacity).
    pub rgb: Vec<[f32; 3]>,
}

/// Up to `n` cameras of `size x size` pixels: where the model knows its
/// training cameras, from their centres (evenly chosen) looking the way
/// each looked, so that every view shows what a photo showed; else from a
/// sphere around the box (its upper part, `up` being the box's z axis)
/// looking at its centre. Each is as wide as the box seen from there, but
/// no wider than the training photos (a box larger than the object would
/// leave it small).
pub fn cameras(model: &dyn Model, crop: &CropBox, n: usize, size: u32) -> Vec<Camera> {
    let centre = Vec3::from_array(crop.centre);
    let up = Vec3::from_array(crop.axes[2]);
    let radius = Vec3::from_array(crop.half).norm();
    let rig = model.scene().rig.as_ref();
    let widest = rig.map(|r| r.fov_deg.to_radians()).filter(|f| *f > 0.0).unwrap_or(1.75);
    // (eye, the direction it looks)
    let mut poses: Vec<(Vec3, Vec3)> = rig
        .map(|r| r.frames.as_slice())
        .unwrap_or_default()
        .iter()
        .map(|f| (Vec3::from_array(f.centre), Vec3::from_array(f.axis)))
        .filter(|&(e, _)| (e - centre).norm() > 0.1 * radius)
        .collect();
    if poses.is_empty() {
        // Inside the model's ray range: a field draws nothing past its far plane.
        let far = model.scene().far / model.scene().scale;
        let dist = (3.0 * radius).min(0.5 * far).max(1.2 * radius);
        poses = sphere(n.max(1)).into_iter().map(|d| (centre + turn_up(d, up) * dist, -turn_up(d, up))).collect();
    }
    let mut out = Vec::new();
    for &(eye, look) in evenly(&poses, n) {
        let up_hint =
            if look.normalized().is_some_and(|d| d.dot(up).abs() > 0.99) { Vec3::from_array(crop.axes[1]) } else { up };
        let Some(c2w) = look_at(eye, eye + look, up_hint) else { continue };
        // The box's sphere filling the frame; at most 100 degrees across from inside it.
        let fov = 2.0 * (radius / (eye - centre).norm()).min(0.766).asin() * 1.05;
        out.push(Camera::from_fov(size, size, fov.min(widest).max(0.2), c2w));
    }
    out
}

/// Unit directions spread over the upper three quarters of a sphere
/// around +z (a Fibonacci spiral): what an object on a table shows.
fn sphere(n: usize) -> Vec<Vec3> {
    let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
    (0..n)
        .map(|i| {
            let z = 1.0 - 1.5 * (i as f32 + 0.5) / n as f32;
            let r = (1.0 - z * z).max(0.0).sqrt();
            let a = golden * i as f32;
            Vec3::new(r * a.cos(), r * a.sin(), z)
        })
        .collect()
}

/// `d` (around +z) turned to be around `up`.
fn turn_up(d: Vec3, up: Vec3) -> Vec3 {
    let helper = if up.x.abs() < 0.9 { Vec3::new(1.0, 0.0, 0.0) } else { Vec3::new(0.0, 1.0, 0.0) };
    let x = up.cross(helper).normalized().unwrap_or(helper);
    let y = up.cross(x);
    x * d.x + y * d.y + up * d.z
}

/// Renders `camera` with the model's mean appearance, or `None` once
/// `cancel` is set. A pixel meets a surface where the model draws it at
/// least half opaque: for a field, where along the ray its opacity reaches
/// one half (the median depth: the expected depth, a mean, lies between a
/// soft surface and what is behind it); for splats, which have no median,
/// the expected depth over the opacity.
pub fn render(model: &dyn Model, camera: &Camera, cancel: &AtomicBool) -> Option<SurfaceView> {
    if model.rasteriser().is_none() {
        return render_field(model, camera, cancel);
    }
    let view = render_view_until(model, camera, [0.0; 3], &RenderOptions::default(), cancel)?;
    let mut surface = Vec::with_capacity(view.opacity.len());
    let mut rgb = Vec::with_capacity(view.opacity.len());
    for (i, &a) in view.opacity.iter().enumerate() {
        let solid = a >= SOLID && view.depth[i].is_finite();
        surface.push(solid.then(|| view.depth[i] / a));
        rgb.push(unpremultiplied(view.rgb[3 * i..3 * i + 3].try_into().expect("three channels"), a));
    }
    Some(SurfaceView { camera: camera.clone(), surface, rgb })
}

/// A field's view, its surface at each ray's median depth.
fn render_field(model: &dyn Model, camera: &Camera, cancel: &AtomicBool) -> Option<SurfaceView> {
    let (w, h) = (camera.width, camera.height);
    let rays: Vec<Ray> = (0..h).flat_map(|y| (0..w).map(move |x| camera.pixel_ray(x, y))).collect();
    let (out, _) = render_rays_until(model, &rays, [0.0; 3], &RenderOptions::default(), cancel)?;
    // Ray distances come in model units.
    let to_world = 1.0 / model.scene().scale;
    let surface = out
        .iter()
        .map(|o| (o.opacity >= SOLID && o.median > 0.0 && o.median.is_finite()).then_some(o.median * to_world))
        .collect();
    let rgb = out.iter().map(|o| unpremultiplied(o.rgb, o.opacity)).collect();
    Some(SurfaceView { camera: camera.clone(), surface, rgb })
}

/// A colour drawn over black at `opacity`, as the surface's own.
fn unpremultiplied(c: [f32; 3], opacity: f32) -> [f32; 3] {
    if opacity > 1e-3 { c.map(|k| (k / opacity).clamp(0.0, 1.0)) } else { [0.0; 3] }
}

/// Most cameras [`auto_crop`] renders, and the width it renders them at.
const CROP_CAMERAS: usize = 60;
const CROP_WIDTH: u32 = 96;

/// The automatic crop for any model: what the model draws solid, seen from
/// (up to 60 of) its training `cameras` at a low resolution, boxed as the
/// splats' automatic crop boxes their Gaussians (`crop_around`: the
/// points nearly every camera has in its frame, standing on `up`).
pub fn auto_crop(
    model: &dyn Model,
    cameras: &[Camera],
    up: [f32; 3],
    cancel: &AtomicBool,
) -> Result<CropBox, MeshError> {
    let mut points = Vec::new();
    for c in evenly(cameras, CROP_CAMERAS) {
        let k = (CROP_WIDTH as f32 / c.width as f32).min(1.0);
        let (w, h) = [c.width, c.height].map(|n| ((n as f32 * k).round() as u32).max(1)).into();
        let small = Camera { distortion: Default::default(), ..c.resized(w, h, k) };
        let view = render(model, &small, cancel).ok_or(MeshError::Cancelled)?;
        points.extend(view.points());
    }
    Ok(crop_around(&points, cameras, up)?)
}

/// The automatic crop for `ds`'s training cameras and rig, for any model: a
/// splats model's from its Gaussians (`crop::auto_crop_for`), another's from
/// its views ([`auto_crop`]); `None` for a capture with no rig or a
/// forward-facing one (nothing was walked around).
pub fn auto_crop_for(model: &dyn Model, ds: &Dataset, cancel: &AtomicBool) -> Result<Option<CropBox>, MeshError> {
    if let Some(splats) = model.as_any().downcast_ref::<SplatsModel>() {
        return Ok(crop::auto_crop_for(splats, ds)?);
    }
    let Some(rig) = ds.rig().filter(|r| !r.forward_facing) else { return Ok(None) };
    let cameras: Vec<Camera> = ds.split_frames(Split::Train).map(|f| f.camera.clone()).collect();
    auto_crop(model, &cameras, rig.up, cancel).map(Some)
}

/// The scene's box in world units, its z the world axis nearest the
/// capture's up (world z without a rig).
pub fn scene_box(model: &dyn Model) -> CropBox {
    let s = model.scene();
    let up = s.rig.as_ref().map_or([0.0, 0.0, 1.0], |r| r.up);
    let z = (0..3).max_by(|&i, &j| up[i].abs().total_cmp(&up[j].abs())).unwrap_or(2);
    let sign = if up[z] < 0.0 { -1.0 } else { 1.0 };
    let (x, y) = ((z + 1) % 3, (z + 2) % 3);
    let unit = |i: usize, s: f32| std::array::from_fn(|k| if k == i { s } else { 0.0 });
    let lo = s.point_to_world(s.aabb_min);
    let hi = s.point_to_world(s.aabb_max);
    let centre = std::array::from_fn(|k| 0.5 * (lo[k] + hi[k]));
    // A right-handed frame: x, then y = z cross x (flipped with z).
    CropBox {
        centre,
        axes: [unit(x, 1.0), unit(y, sign), unit(z, sign)],
        half: [x, y, z].map(|k| 0.5 * (hi[k] - lo[k])),
    }
}

/// Up to `n` of `items`, evenly spread (all of them when there are no more).
fn evenly<T>(items: &[T], n: usize) -> impl Iterator<Item = &T> {
    let stride = (items.len() as f64 / n.max(1) as f64).max(1.0);
    std::iter::successors(Some(0.0f64), move |i| Some(i + stride))
        .map(|i| i as usize)
        .take_while(move |&i| i < items.len())
        .take(n.max(1))
        .map(move |i| &items[i])
}

/// Photos wider or taller than this are box-averaged down for the fit.
const PHOTO_SIDE: u32 = 512;
/// Solid photo pixels fitted, at most (the fit's time grows with them).
const PHOTO_PIXELS: usize = 2_000_000;

/// The training photos of `ds` as views for the texture's fit
/// ([`crate::engine::mesh::fit`]): each from its camera as the model
/// places a held-out view, solid where its mask (or, without masks, its alpha) says
/// the object is (its surface distance NaN: not known), everywhere in a
/// photo with neither. A photo larger than
/// 512 pixels is averaged down by a whole factor, which keeps each pixel
/// the mean of an area, as the fit draws it. Photos with lens distortion
/// are left out (the mesh's rasteriser draws a pinhole).
pub fn photos(model: &dyn Model, ds: &Dataset) -> Vec<SurfaceView> {
    let all: Vec<SurfaceView> = ds
        .split_frames(Split::Train)
        .filter(|f| f.camera.distortion == Default::default())
        .map(|f| photo_view(f, crate::engine::models::heldout_pose(model, f.camera.c2w)))
        .collect();
    // As many as the budget of solid pixels holds, evenly chosen.
    let solid: usize = all.iter().map(|v| v.surface.iter().flatten().count()).sum();
    let keep = (PHOTO_PIXELS as f64 * all.len() as f64 / solid.max(1) as f64).floor() as usize;
    evenly(&all, keep.clamp(1, all.len().max(1))).cloned().collect()
}

/// Training photo `f` as a view for the fit, seen from `c2w`, averaged
/// down by a whole factor when larger than [`PHOTO_SIDE`].
fn photo_view(f: &Frame, c2w: [[f32; 4]; 3]) -> SurfaceView {
    let (w, h) = (f.image.width, f.image.height);
    let k = w.max(h).div_ceil(PHOTO_SIDE).max(1);
    let (sw, sh) = (w / k, h / k);
    let camera = Camera { distortion: Default::default(), c2w, ..f.camera.resized(sw, sh, 1.0 / k as f32) };
    let (mut surface, mut rgb) = (Vec::new(), Vec::new());
    for y in 0..sh {
        for x in 0..sw {
            // The mean over the block's samples on the object (the rest show what is behind it).
            let (mut sum, mut inside) = ([0.0f32; 3], 0usize);
            for (i, j) in (0..k * k).map(|n| (x * k + n % k, y * k + n / k)) {
                let p = (j * w + i) as usize;
                let px = &f.image.rgba[4 * p..4 * p + 4];
                let on = match &f.mask {
                    Some(m) => m[p] > 127,
                    None => !f.image.has_alpha || px[3] > 127,
                };
                if on {
                    (0..3).for_each(|q| sum[q] += px[q] as f32 / 255.0);
                    inside += 1;
                }
            }
            surface.push((2 * inside > (k * k) as usize).then_some(f32::NAN));
            rgb.push(sum.map(|s| s / inside.max(1) as f32));
        }
    }
    SurfaceView { camera, surface, rgb }
}

impl SurfaceView {
    /// The world points where its rays meet the surface, pixel by pixel.
    pub fn points(&self) -> impl Iterator<Item = Vec3> + '_ {
        let w = self.camera.width;
        self.surface
            .iter()
            .enumerate()
            .filter_map(move |(i, s)| s.map(|t| self.camera.pixel_ray(i as u32 % w, i as u32 / w).at(t)))
    }

    /// Where world point `p` falls in this view (continuous pixels) and
    /// its distance from the camera, if in front and inside the frame.
    pub fn project(&self, p: Vec3) -> Option<(f32, f32, f32)> {
        self.camera.project(p.to_array()).map(|(u, v)| (u, v, (p - self.camera.origin()).norm()))
    }

    /// The colour at continuous pixel `(u, v)`, bilinear between the
    /// surface pixels around it.
    pub fn colour(&self, u: f32, v: f32) -> [f32; 3] {
        let (w, h) = (self.camera.width as i64, self.camera.height as i64);
        let (x, y) = (u - 0.5, v - 0.5);
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let mut sum = [0.0f32; 3];
        let mut total = 0.0;
        for (dx, dy, wt) in
            [(0, 0, (1.0 - fx) * (1.0 - fy)), (1, 0, fx * (1.0 - fy)), (0, 1, (1.0 - fx) * fy), (1, 1, fx * fy)]
        {
            let (px, py) = ((x0 as i64 + dx).clamp(0, w - 1), (y0 as i64 + dy).clamp(0, h - 1));
            let i = (py * w + px) as usize;
            if self.surface[i].is_some() && wt > 0.0 {
                (0..3).for_each(|k| sum[k] += wt * self.rgb[i][k]);
                total += wt;
            }
        }
        if total > 0.0 { sum.map(|s| s / total) } else { self.rgb[(v as i64 * w + u as i64) as usize] }
    }

    /// The surface distance at the pixel holding continuous `(u, v)`.
    pub fn surface_at(&self, u: f32, v: f32) -> Option<f32> {
        self.surface[v as usize * self.camera.width as usize + u as usize]
    }
}

/// A view of the plane z = 0 painted by `paint`, from `camera`: solid
/// wherever its rays meet the plane (for tests).
#[cfg(test)]
pub(crate) fn plane_view(camera: Camera, paint: &dyn Fn(Vec3) -> [f32; 3]) -> SurfaceView {
    let (mut surface, mut rgb) = (Vec::new(), Vec::new());
    for y in 0..camera.height {
        for x in 0..camera.width {
            let r = camera.pixel_ray(x, y);
            let t = -r.origin.z / r.dir.z;
            surface.push((t > 0.0).then_some(t));
            rgb.push(paint(r.at(t)));
        }
    }
    SurfaceView { camera, surface, rgb }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::dataset::Image;

    /// A `w x h` frame: red up to its middle column, blue after, green added
    /// in its bottom half; its mask
    /// (when `masked`) or alpha keeps the top half.
    fn frame(w: u32, h: u32, masked: bool) -> Frame {
        let pose = look_at(Vec3::new(0.0, 0.0, 3.0), Vec3::splat(0.0), Vec3::new(0.0, 1.0, 0.0)).unwrap();
        let mut rgba = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let top = y < h / 2;
                rgba.extend([
                    if x <= w / 2 { 255 } else { 0 },
                    if top { 0 } else { 255 },
                    if x <= w / 2 { 0 } else { 255 },
                ]);
                rgba.push(if top || masked { 255 } else { 0 });
            }
        }
        let mask = masked.then(|| (0..w * h).map(|i| if i / w < h / 2 { 255 } else { 0 }).collect());
        Frame {
            name: "f".into(),
            path: "f.png".into(),
            camera: Camera::from_fov(w, h, 1.0, pose),
            image: Image { width: w, height: h, rgba, has_alpha: !masked },
            mask,
        }
    }

    #[test]
    fn a_large_photo_is_averaged_down_and_keeps_its_rays() {
        for masked in [true, false] {
            let f = frame(1200, 40, masked);
            let v = photo_view(&f, f.camera.c2w);
            // 1200 wide: averaged by 3, to 400 x 13.
            assert_eq!((v.camera.width, v.camera.height), (400, 13));
            // Pixel (x, y)'s centre is the centre of the photo's 3x3 block around (3x + 1, 3y + 1).
            for (x, y) in [(0, 0), (123, 7), (399, 12)] {
                let (a, b) = (v.camera.pixel_ray(x, y).dir, f.camera.pixel_ray(3 * x + 1, 3 * y + 1).dir);
                assert!((a - b).norm() < 1e-5, "({x}, {y}): {a:?} against {b:?}");
            }
            let at = |x: usize, y: usize| (v.surface[y * 400 + x].is_some(), v.rgb[y * 400 + x]);
            assert_eq!(at(10, 2), (true, [1.0, 0.0, 0.0]));
            assert_eq!(at(390, 5), (true, [0.0, 0.0, 1.0]));
            // Rows 18 to 20 of the photo: two of the three in its kept top
            // half, whose colour alone it takes (no green from row 20).
            assert_eq!(at(10, 6), (true, [1.0, 0.0, 0.0]));
            assert!(!at(10, 7).0 && !at(390, 12).0, "masked: {masked}");
            // The block across the colours' border (photo columns 600 to 602): a third red.
            let (_, c) = at(200, 0);
            assert!((c[0] - 1.0 / 3.0).abs() < 1e-6 && (c[2] - 2.0 / 3.0).abs() < 1e-6, "{c:?}");
        }
    }
}
