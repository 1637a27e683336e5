//! Tiny procedurally generated scenes for tests and examples: an analytic
//! radiance field rendered exactly into posed images around the origin.

use crate::engine::dataset::{Dataset, DatasetFormat, Frame, Image, MaskUse};
use crate::engine::geometry::camera::{Camera, look_at};
use crate::engine::geometry::math::{Aabb, Ray, Vec3};

/// A coloured ball (red on +x, green on +y, blue on +z) in an otherwise empty
/// box, seen from `views` cameras on a ring; images are RGBA with a
/// transparent background.
pub struct BallScene {
    pub radius: f32,
    pub size: u32,
    pub views: usize,
    /// World units per unit of the canonical scene (tests of scale invariance).
    pub scale: f32,
}

impl Default for BallScene {
    fn default() -> Self {
        Self { radius: 0.6, size: 24, views: 16, scale: 1.0 }
    }
}

impl BallScene {
    /// The demo scene (`radiance demo`, `POST /v1/demo`): large enough to
    /// look at (64x64, 32 views), small enough to train in seconds.
    pub fn demo() -> Self {
        Self { size: 64, views: 32, ..Default::default() }
    }

    /// Colour and coverage of the ray, in canonical units.
    fn shade(&self, ray: &Ray) -> Option<[f32; 3]> {
        let b = ray.origin.dot(ray.dir);
        let c = ray.origin.dot(ray.origin) - self.radius * self.radius;
        let disc = b * b - c;
        if disc < 0.0 {
            return None;
        }
        let t = -b - disc.sqrt();
        let p = ray.at(t) * (1.0 / self.radius);
        Some([0.5 + 0.45 * p.x, 0.5 + 0.45 * p.y, 0.5 + 0.45 * p.z])
    }

    fn camera(&self, k: usize, n: usize) -> Camera {
        let a = k as f32 / n as f32 * std::f32::consts::TAU;
        let elev = if (k / 2).is_multiple_of(2) { 0.5 } else { -0.3 };
        let eye = Vec3::new(3.0 * a.cos(), 3.0 * a.sin(), 3.0 * elev);
        let pose = look_at(eye, Vec3::splat(0.0), Vec3::new(0.0, 0.0, 1.0)).unwrap_or([[0.0; 4]; 3]);
        Camera::from_fov(self.size, self.size, 0.9, pose)
    }

    /// Renders the dataset: `views` training views and 4 test views between them.
    pub fn dataset(&self) -> Dataset {
        let mut frames = Vec::new();
        for k in 0..self.views + RING_TEST_VIEWS {
            let cam = self.camera(ring_slot(k, self.views), 2 * self.views);
            let mut rgba = Vec::with_capacity((self.size * self.size * 4) as usize);
            for j in 0..self.size {
                for i in 0..self.size {
                    match self.shade(&cam.pixel_ray(i, j)) {
                        Some(c) => rgba.extend(c.iter().map(|v| (v * 255.0).round() as u8).chain([255])),
                        None => rgba.extend([0, 0, 0, 0]),
                    }
                }
            }
            let mut cam = cam;
            for row in &mut cam.c2w {
                row[3] *= self.scale;
            }
            frames.push(ring_frame(k, cam, self.size, rgba));
        }
        let s = self.scale;
        ring_dataset(frames, self.views, [1.0 * s, 5.0 * s], Aabb { min: Vec3::splat(-s), max: Vec3::splat(s) })
    }
}

/// Held-out views of a generated ring of cameras.
pub(crate) const RING_TEST_VIEWS: usize = 4;

/// Where view `k` of a ring of `views` training cameras (then
/// [`RING_TEST_VIEWS`] held out) sits, among `2 * views` places: the
/// training cameras on the even ones, the held-out ones half way between.
pub(crate) fn ring_slot(k: usize, views: usize) -> usize {
    if k < views { 2 * k } else { 2 * (k - views) * views / RING_TEST_VIEWS + 1 }
}

/// View `k` of a generated scene: a square RGBA image named `r_k`.
pub(crate) fn ring_frame(k: usize, camera: Camera, size: u32, rgba: Vec<u8>) -> Frame {
    Frame {
        name: format!("r_{k}"),
        path: format!("r_{k}.png").into(),
        camera,
        image: Image { width: size, height: size, rgba, has_alpha: true },
        mask: None,
    }
}

/// A generated Blender-format dataset: `frames` are `views` training views
/// then the held-out ones, composited on white.
pub(crate) fn ring_dataset(frames: Vec<Frame>, views: usize, [near, far]: [f32; 2], aabb: Aabb) -> Dataset {
    let total = frames.len();
    Dataset {
        format: DatasetFormat::Blender,
        root: ".".into(),
        frames,
        train: (0..views).collect(),
        val: (views..total).collect(),
        test: (views..total).collect(),
        near,
        far,
        aabb,
        background: [1.0; 3],
        warnings: Vec::new(),
        masks: MaskUse::Off,
        mask_folder: None,
    }
}

impl BallScene {
    /// Writes the scene as a Blender-format dataset (`transforms_train.json`,
    /// `transforms_test.json`, RGBA PNGs) into `dir`.
    pub fn write_blender(&self, dir: &std::path::Path) -> std::io::Result<()> {
        write_blender(&self.dataset(), dir)
    }

    /// Writes the scene as an instant-ngp `transforms.json` dataset (one
    /// file for all views, explicit intrinsics, RGBA PNGs in `images/`),
    /// with `scale`/`offset` chosen so the box holds the ball.
    pub fn write_ngp(&self, dir: &std::path::Path) -> std::io::Result<()> {
        let ds = self.dataset();
        std::fs::create_dir_all(dir.join("images"))?;
        let mut frames = Vec::new();
        for f in &ds.frames {
            let img = image::RgbaImage::from_raw(f.image.width, f.image.height, f.image.rgba.clone())
                .ok_or_else(|| std::io::Error::other("image size"))?;
            img.save(dir.join("images").join(format!("{}.png", f.name))).map_err(std::io::Error::other)?;
            let m = &f.camera.c2w;
            frames.push(serde_json::json!({
                "file_path": format!("images/{}.png", f.name),
                "transform_matrix": [m[0], m[1], m[2], [0.0, 0.0, 0.0, 1.0]],
            }));
        }
        let c = &ds.frames[0].camera;
        // The box [-1.5, 1.5]^3 (world) is the unit cube: p * scale + offset.
        let scale = 1.0 / (3.0 * self.scale);
        let json = serde_json::json!({
            "fl_x": c.fx, "fl_y": c.fy, "cx": c.cx, "cy": c.cy, "w": c.width, "h": c.height,
            "aabb_scale": 1, "scale": scale, "offset": [0.5, 0.5, 0.5], "frames": frames,
        });
        std::fs::write(dir.join("transforms.json"), serde_json::to_vec_pretty(&json)?)
    }

    /// Writes the scene as an LLFF dataset: `poses_bounds.npy` and RGB PNGs
    /// (composited on white) in `images/`, in the LLFF axis order
    /// [down, right, backwards].
    pub fn write_llff(&self, dir: &std::path::Path) -> std::io::Result<()> {
        let ds = self.dataset();
        std::fs::create_dir_all(dir.join("images"))?;
        let mut rows = Vec::new();
        for (k, f) in ds.frames.iter().enumerate() {
            let (w, h) = (f.image.width, f.image.height);
            save_on_white(&f.image, &dir.join("images").join(format!("img{k:03}.png")))?;
            let m = &f.camera.c2w;
            let mut row = Vec::with_capacity(17);
            for r in m {
                // columns: down = -up, right, backwards, translation, [H, W, focal]
                let hwf = [h as f32, w as f32, f.camera.fx][row.len() / 5];
                row.extend([-r[1], r[0], r[2], r[3], hwf].map(f64::from));
            }
            let dist = f.camera.origin().norm() / self.scale;
            row.extend([(dist - 1.0) * self.scale, (dist + 1.0) * self.scale].map(f64::from));
            rows.extend(row);
        }
        let shape = [ds.frames.len(), 17];
        std::fs::write(dir.join("poses_bounds.npy"), crate::engine::dataset::npy::npy_bytes(&shape, &rows, 1))
    }
}

/// Writes a generated dataset (square views of one field of view) in the
/// Blender layout: `transforms_train.json`, `transforms_test.json` and RGBA
/// PNGs, into `dir`.
pub fn write_blender(ds: &Dataset, dir: &std::path::Path) -> std::io::Result<()> {
    for (split, idx) in [("train", &ds.train), ("test", &ds.test)] {
        std::fs::create_dir_all(dir.join(split))?;
        let mut frames = Vec::new();
        for &i in idx.iter() {
            let f = &ds.frames[i];
            let img = image::RgbaImage::from_raw(f.image.width, f.image.height, f.image.rgba.clone())
                .ok_or_else(|| std::io::Error::other("image size"))?;
            img.save(dir.join(split).join(format!("{}.png", f.name))).map_err(std::io::Error::other)?;
            let m = &f.camera.c2w;
            frames.push(serde_json::json!({
                "file_path": format!("./{split}/{}", f.name),
                "transform_matrix": [m[0], m[1], m[2], [0.0, 0.0, 0.0, 1.0]],
            }));
        }
        let c = &ds.frames[0].camera;
        let fov = 2.0 * (0.5 * c.width as f32 / c.fx).atan();
        let json = serde_json::json!({ "camera_angle_x": fov, "near": ds.near, "far": ds.far, "frames": frames });
        std::fs::write(dir.join(format!("transforms_{split}.json")), serde_json::to_vec_pretty(&json)?)?;
    }
    Ok(())
}

/// Saves `image` composited on white as an RGB PNG.
fn save_on_white(image: &Image, path: &std::path::Path) -> std::io::Result<()> {
    let (w, h) = (image.width, image.height);
    let rgb: Vec<u8> = (0..h)
        .flat_map(|j| (0..w).map(move |i| (i, j)))
        .flat_map(|(i, j)| image.rgb_on(i, j, [1.0; 3]))
        .map(|v| (v * 255.0).round() as u8)
        .collect();
    let img = image::RgbImage::from_raw(w, h, rgb).ok_or_else(|| std::io::Error::other("image size"))?;
    img.save(path).map_err(std::io::Error::other)
}

impl BallScene {
    /// Writes the scene as a COLMAP dataset: a model in `sparse/0` (binary
    /// or text; one PINHOLE camera, points on the ball) and RGB PNGs
    /// (composited on white) in `images/`.
    pub fn write_colmap(&self, dir: &std::path::Path, binary: bool) -> std::io::Result<()> {
        use crate::engine::dataset::colmap_model::{self, CameraModel, ImagePose, Model};
        let ds = self.dataset();
        std::fs::create_dir_all(dir.join("images"))?;
        let c0 = &ds.frames[0].camera;
        let params = vec![c0.fx as f64, c0.fy as f64, c0.cx as f64, c0.cy as f64];
        let camera = CameraModel { id: 1, model: "PINHOLE", width: c0.width as u64, height: c0.height as u64, params };
        let mut images = Vec::new();
        for (k, f) in ds.frames.iter().enumerate() {
            let name = format!("img{k:03}.png");
            save_on_white(&f.image, &dir.join("images").join(&name))?;
            let (qvec, tvec) = colmap_pose(&f.camera.c2w);
            images.push(ImagePose { id: k as u32 + 1, qvec, tvec, camera_id: 1, name });
        }
        let r = (self.radius * self.scale) as f64;
        let points = (0..64)
            .map(|i| {
                let (a, b) = (i as f64 * 0.7, i as f64 * 0.3);
                [r * a.cos() * b.sin(), r * a.sin() * b.sin(), r * b.cos()]
            })
            .collect();
        colmap_model::write(&Model { cameras: vec![camera], images, points }, &dir.join("sparse/0"), binary)
    }
}

/// A rotation matrix as a unit quaternion `w, x, y, z` (Shepperd's method;
/// independent of the loader's quaternion -> matrix).
pub fn quaternion(r: [[f64; 3]; 3]) -> [f64; 4] {
    let tr = r[0][0] + r[1][1] + r[2][2];
    if tr > 0.0 {
        let s = 2.0 * (1.0 + tr).sqrt();
        [0.25 * s, (r[2][1] - r[1][2]) / s, (r[0][2] - r[2][0]) / s, (r[1][0] - r[0][1]) / s]
    } else if r[0][0] > r[1][1] && r[0][0] > r[2][2] {
        let s = 2.0 * (1.0 + r[0][0] - r[1][1] - r[2][2]).sqrt();
        [(r[2][1] - r[1][2]) / s, 0.25 * s, (r[0][1] + r[1][0]) / s, (r[0][2] + r[2][0]) / s]
    } else if r[1][1] > r[2][2] {
        let s = 2.0 * (1.0 + r[1][1] - r[0][0] - r[2][2]).sqrt();
        [(r[0][2] - r[2][0]) / s, (r[0][1] + r[1][0]) / s, 0.25 * s, (r[1][2] + r[2][1]) / s]
    } else {
        let s = 2.0 * (1.0 + r[2][2] - r[0][0] - r[1][1]).sqrt();
        [(r[1][0] - r[0][1]) / s, (r[0][2] + r[2][0]) / s, (r[1][2] + r[2][1]) / s, 0.25 * s]
    }
}

/// COLMAP's world-to-camera pose (OpenCV axes) of an OpenGL camera-to-world.
pub fn colmap_pose(c2w: &[[f32; 4]; 3]) -> ([f64; 4], [f64; 3]) {
    // OpenCV camera-to-world: flip the y and z axes; R is its transpose.
    let sign = [1.0, -1.0, -1.0];
    let mut r = [[0.0f64; 3]; 3];
    for a in 0..3 {
        for b in 0..3 {
            r[b][a] = sign[b] * c2w[a][b] as f64;
        }
    }
    let c = [c2w[0][3] as f64, c2w[1][3] as f64, c2w[2][3] as f64];
    let t = [0, 1, 2].map(|k| -(0..3).map(|j| r[k][j] * c[j]).sum::<f64>());
    (quaternion(r), t)
}
