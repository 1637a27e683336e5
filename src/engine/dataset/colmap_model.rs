//! COLMAP's sparse reconstruction files: `cameras`, `images` and `points3D`,
//! as binary (`.bin`) or text (`.txt`), read into one [`Model`] either way.
//!
//! The binary reader trusts no count: every count is checked against the
//! bytes left before anything is allocated, so a truncated or corrupt file
//! is an error naming it, never a panic or a huge allocation.

use std::path::{Path, PathBuf};

use super::DatasetError;

/// A COLMAP camera model: its name and number of parameters, by the id the
/// binary format uses (COLMAP's `src/colmap/sensor/models.h`).
pub const CAMERA_MODELS: [(&str, usize); 11] = [
    ("SIMPLE_PINHOLE", 3),
    ("PINHOLE", 4),
    ("SIMPLE_RADIAL", 4),
    ("RADIAL", 5),
    ("OPENCV", 8),
    ("OPENCV_FISHEYE", 8),
    ("FULL_OPENCV", 12),
    ("FOV", 5),
    ("SIMPLE_RADIAL_FISHEYE", 4),
    ("RADIAL_FISHEYE", 5),
    ("THIN_PRISM_FISHEYE", 12),
];

/// One camera (intrinsics shared by some images).
#[derive(Clone, Debug, PartialEq)]
pub struct CameraModel {
    pub id: u32,
    /// Its name in [`CAMERA_MODELS`].
    pub model: &'static str,
    pub width: u64,
    pub height: u64,
    pub params: Vec<f64>,
}

/// One registered image: the world-to-camera rotation (unit quaternion
/// `w, x, y, z`) and translation, in OpenCV's camera axes.
#[derive(Clone, Debug, PartialEq)]
pub struct ImagePose {
    pub id: u32,
    pub qvec: [f64; 4],
    pub tvec: [f64; 3],
    pub camera_id: u32,
    /// The file name, relative to the image folder.
    pub name: String,
}

/// A sparse reconstruction.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Model {
    pub cameras: Vec<CameraModel>,
    pub images: Vec<ImagePose>,
    /// The sparse points' positions.
    pub points: Vec<[f64; 3]>,
}

/// Reads the model in `dir`: `cameras.bin`, `images.bin` and `points3D.bin`,
/// or the three `.txt` files.
pub fn read(dir: &Path) -> Result<Model, DatasetError> {
    let bin = dir.join("cameras.bin").is_file();
    let ext = if bin { "bin" } else { "txt" };
    let file = |name: &str| dir.join(format!("{name}.{ext}"));
    let read = |p: &PathBuf| std::fs::read(p).map_err(|e| DatasetError::Io { path: p.clone(), source: e });
    let (cams, imgs, pts) = (file("cameras"), file("images"), file("points3D"));
    let (cb, ib, pb) = (read(&cams)?, read(&imgs)?, read(&pts)?);
    if bin {
        Ok(Model { cameras: cameras_bin(&cb, &cams)?, images: images_bin(&ib, &imgs)?, points: points_bin(&pb, &pts)? })
    } else {
        Ok(Model {
            cameras: cameras_txt(text(&cb, &cams)?, &cams)?,
            images: images_txt(text(&ib, &imgs)?, &imgs)?,
            points: points_txt(text(&pb, &pts)?, &pts)?,
        })
    }
}

fn text<'a>(bytes: &'a [u8], path: &Path) -> Result<&'a str, DatasetError> {
    std::str::from_utf8(bytes).map_err(|e| invalid(path, format!("not UTF-8 text: {e}")))
}

fn invalid(path: &Path, message: String) -> DatasetError {
    DatasetError::Invalid { path: path.to_path_buf(), message }
}

/// A bounds-checked little-endian reader.
struct Bytes<'a> {
    b: &'a [u8],
    at: usize,
    path: &'a Path,
}

impl<'a> Bytes<'a> {
    fn new(b: &'a [u8], path: &'a Path) -> Self {
        Self { b, at: 0, path }
    }

    fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8], DatasetError> {
        if self.b.len() - self.at < n {
            let msg = format!("truncated: {what} at byte {} needs {n} bytes, {} left", self.at, self.b.len() - self.at);
            return Err(invalid(self.path, msg));
        }
        let s = &self.b[self.at..self.at + n];
        self.at += n;
        Ok(s)
    }

    fn u64(&mut self, what: &str) -> Result<u64, DatasetError> {
        Ok(u64::from_le_bytes(self.take(8, what)?.try_into().unwrap_or_default()))
    }

    fn i32(&mut self, what: &str) -> Result<i32, DatasetError> {
        Ok(i32::from_le_bytes(self.take(4, what)?.try_into().unwrap_or_default()))
    }

    fn f64(&mut self, what: &str) -> Result<f64, DatasetError> {
        Ok(f64::from_le_bytes(self.take(8, what)?.try_into().unwrap_or_default()))
    }

    fn f64s<const N: usize>(&mut self, what: &str) -> Result<[f64; N], DatasetError> {
        let mut out = [0.0; N];
        for v in &mut out {
            *v = self.f64(what)?;
        }
        Ok(out)
    }

    /// A count of records of at least `min_bytes` each, refused when the
    /// bytes left cannot hold them.
    fn count(&mut self, what: &str, min_bytes: usize) -> Result<usize, DatasetError> {
        let n = self.u64(what)?;
        let left = (self.b.len() - self.at) as u64;
        if n.saturating_mul(min_bytes as u64) > left {
            return Err(invalid(self.path, format!("{what} is {n}, but only {left} bytes follow")));
        }
        Ok(n as usize)
    }

    fn end(&self) -> Result<(), DatasetError> {
        match self.b.len() - self.at {
            0 => Ok(()),
            n => Err(invalid(self.path, format!("{n} bytes after the last record"))),
        }
    }
}

/// A record id that must fit our `u32` ids.
fn id(v: i64, what: &str, path: &Path) -> Result<u32, DatasetError> {
    u32::try_from(v).map_err(|_| invalid(path, format!("{what} {v} is not a valid id")))
}

/// A camera model by its text name.
fn camera_model(name: &str) -> Option<(&'static str, usize)> {
    CAMERA_MODELS.iter().copied().find(|(n, _)| *n == name)
}

fn cameras_bin(b: &[u8], path: &Path) -> Result<Vec<CameraModel>, DatasetError> {
    let mut r = Bytes::new(b, path);
    let n = r.count("number of cameras", 24)?;
    let mut out = Vec::with_capacity(n);
    for _ in 0..n {
        let cid = id(r.i32("camera id")? as i64, "camera id", path)?;
        let model_id = r.i32("camera model")?;
        let (model, np) = usize::try_from(model_id)
            .ok()
            .and_then(|i| CAMERA_MODELS.get(i).copied())
            .ok_or_else(|| invalid(path, format!("camera {cid}: unknown camera model id {model_id}")))?;
        let (width, height) = (r.u64("width")?, r.u64("height")?);
        let params = (0..np).map(|_| r.f64("camera parameter")).collect::<Result<_, _>>()?;
        out.push(CameraModel { id: cid, model, width, height, params });
    }
    r.end()?;
    Ok(out)
}

fn images_bin(b: &[u8], path: &Path) -> Result<Vec<ImagePose>, DatasetError> {
    let mut r = Bytes::new(b, path);
    // id, pose, camera id, an empty name's NUL and the point count.
    let n = r.count("number of images", 4 + 56 + 4 + 1 + 8)?;
    let mut out = Vec::with_capacity(n);
    for _ in 0..n {
        let iid = id(r.i32("image id")? as i64, "image id", path)?;
        let qvec = r.f64s::<4>("rotation")?;
        let tvec = r.f64s::<3>("translation")?;
        let camera_id = id(r.i32("camera id")? as i64, "camera id", path)?;
        let rest = &r.b[r.at..];
        let len = rest
            .iter()
            .position(|&c| c == 0)
            .ok_or_else(|| invalid(path, format!("image {iid}: unterminated name")))?;
        let name = String::from_utf8(r.take(len, "name")?.to_vec())
            .map_err(|_| invalid(path, format!("image {iid}: the name is not UTF-8")))?;
        r.take(1, "name terminator")?;
        let points = r.count("number of 2D points", 24)?;
        r.take(points * 24, "2D points")?;
        out.push(ImagePose { id: iid, qvec, tvec, camera_id, name });
    }
    r.end()?;
    Ok(out)
}

fn points_bin(b: &[u8], path: &Path) -> Result<Vec<[f64; 3]>, DatasetError> {
    let mut r = Bytes::new(b, path);
    // id, position, colour, error and the track length.
    let n = r.count("number of points", 8 + 24 + 3 + 8 + 8)?;
    let mut out = Vec::with_capacity(n);
    for _ in 0..n {
        r.u64("point id")?;
        out.push(r.f64s::<3>("point position")?);
        r.take(3, "point colour")?;
        r.f64("point error")?;
        let track = r.count("track length", 8)?;
        r.take(track * 8, "track")?;
    }
    r.end()?;
    Ok(out)
}

/// The data lines of a text file (comments and blank lines dropped), with
/// their line numbers.
fn lines(s: &str) -> impl Iterator<Item = (usize, &str)> {
    s.lines().enumerate().map(|(i, l)| (i + 1, l.trim())).filter(|(_, l)| !l.is_empty() && !l.starts_with('#'))
}

fn num<T: std::str::FromStr>(field: Option<&str>, what: &str, line: usize, path: &Path) -> Result<T, DatasetError> {
    field
        .and_then(|f| f.parse().ok())
        .ok_or_else(|| invalid(path, format!("line {line}: {what} is missing or not a number")))
}

fn cameras_txt(s: &str, path: &Path) -> Result<Vec<CameraModel>, DatasetError> {
    let mut out = Vec::new();
    for (line, l) in lines(s) {
        let mut f = l.split_whitespace();
        let cid: u32 = num(f.next(), "camera id", line, path)?;
        let name = f.next().ok_or_else(|| invalid(path, format!("line {line}: no camera model")))?;
        let (model, np) =
            camera_model(name).ok_or_else(|| invalid(path, format!("line {line}: unknown camera model '{name}'")))?;
        let width = num(f.next(), "width", line, path)?;
        let height = num(f.next(), "height", line, path)?;
        let params: Vec<f64> = f.map(|v| num(Some(v), "a parameter", line, path)).collect::<Result<_, _>>()?;
        if params.len() != np {
            return Err(invalid(path, format!("line {line}: {model} has {np} parameters, found {}", params.len())));
        }
        out.push(CameraModel { id: cid, model, width, height, params });
    }
    Ok(out)
}

fn images_txt(s: &str, path: &Path) -> Result<Vec<ImagePose>, DatasetError> {
    // Two lines per image; the second (its 2D points) may be empty, so it is
    // found by position in the raw lines rather than among the data lines.
    let raw: Vec<&str> = s.lines().collect();
    let mut out = Vec::new();
    let mut i = 0;
    while i < raw.len() {
        let l = raw[i].trim();
        let line = i + 1;
        if l.is_empty() || l.starts_with('#') {
            i += 1;
            continue;
        }
        let mut f = l.split_whitespace();
        let iid: u32 = num(f.next(), "image id", line, path)?;
        let mut q = [0.0; 4];
        for v in &mut q {
            *v = num(f.next(), "rotation", line, path)?;
        }
        let mut t = [0.0; 3];
        for v in &mut t {
            *v = num(f.next(), "translation", line, path)?;
        }
        let camera_id = num(f.next(), "camera id", line, path)?;
        // Names may contain spaces: the rest of the line.
        let name = f.collect::<Vec<_>>().join(" ");
        if name.is_empty() {
            return Err(invalid(path, format!("line {line}: image {iid} has no name")));
        }
        out.push(ImagePose { id: iid, qvec: q, tvec: t, camera_id, name });
        i += 2;
    }
    Ok(out)
}

fn points_txt(s: &str, path: &Path) -> Result<Vec<[f64; 3]>, DatasetError> {
    let mut out = Vec::new();
    for (line, l) in lines(s) {
        let mut f = l.split_whitespace();
        let _: u64 = num(f.next(), "point id", line, path)?;
        let mut p = [0.0; 3];
        for v in &mut p {
            *v = num(f.next(), "point position", line, path)?;
        }
        out.push(p);
    }
    Ok(out)
}

/// Writes `model` in either format (for tests and for `radiance poses`
/// output checks): the files COLMAP itself would write, without 2D points
/// or tracks.
pub fn write(model: &Model, dir: &Path, binary: bool) -> std::io::Result<()> {
    std::fs::create_dir_all(dir)?;
    if binary {
        let mut c = (model.cameras.len() as u64).to_le_bytes().to_vec();
        for cam in &model.cameras {
            let mid = CAMERA_MODELS.iter().position(|(n, _)| *n == cam.model).unwrap_or(usize::MAX) as i32;
            c.extend((cam.id as i32).to_le_bytes());
            c.extend(mid.to_le_bytes());
            c.extend(cam.width.to_le_bytes());
            c.extend(cam.height.to_le_bytes());
            cam.params.iter().for_each(|p| c.extend(p.to_le_bytes()));
        }
        let mut im = (model.images.len() as u64).to_le_bytes().to_vec();
        for i in &model.images {
            im.extend((i.id as i32).to_le_bytes());
            i.qvec.iter().chain(&i.tvec).for_each(|v| im.extend(v.to_le_bytes()));
            im.extend((i.camera_id as i32).to_le_bytes());
            im.extend(i.name.as_bytes());
            im.push(0);
            im.extend(0u64.to_le_bytes());
        }
        let mut p = (model.points.len() as u64).to_le_bytes().to_vec();
        for (k, pt) in model.points.iter().enumerate() {
            p.extend((k as u64 + 1).to_le_bytes());
            pt.iter().for_each(|v| p.extend(v.to_le_bytes()));
            p.extend([128u8, 128, 128]);
            p.extend(0.5f64.to_le_bytes());
            p.extend(0u64.to_le_bytes());
        }
        std::fs::write(dir.join("cameras.bin"), c)?;
        std::fs::write(dir.join("images.bin"), im)?;
        std::fs::write(dir.join("points3D.bin"), p)
    } else {
        let mut c = String::from("# Camera list with one line of data per camera:\n");
        for cam in &model.cameras {
            let params: Vec<String> = cam.params.iter().map(|p| format!("{p:?}")).collect();
            c += &format!("{} {} {} {} {}\n", cam.id, cam.model, cam.width, cam.height, params.join(" "));
        }
        let mut im = String::from("# Image list with two lines of data per image:\n");
        for i in &model.images {
            let [qw, qx, qy, qz] = i.qvec;
            let [tx, ty, tz] = i.tvec;
            im += &format!("{} {qw:?} {qx:?} {qy:?} {qz:?} {tx:?} {ty:?} {tz:?} {} {}\n\n", i.id, i.camera_id, i.name);
        }
        let mut p = String::from("# 3D point list with one line of data per point:\n");
        for (k, pt) in model.points.iter().enumerate() {
            p += &format!("{} {:?} {:?} {:?} 128 128 128 0.5\n", k + 1, pt[0], pt[1], pt[2]);
        }
        std::fs::write(dir.join("cameras.txt"), c)?;
        std::fs::write(dir.join("images.txt"), im)?;
        std::fs::write(dir.join("points3D.txt"), p)
    }
}
