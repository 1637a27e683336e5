//! The crop volume: an oriented box in world units around the object a
//! capture was made of, found from the cameras alone, and the splats inside
//! it.
//!
//! A walk around an object keeps the object in every photo and each part
//! of the room behind it in some: the Gaussians the training cameras see
//! (in front of them, inside their frame) in nearly all photos are the
//! object and what it stands on. The box stands on the rig's up; its other
//! axes are the principal axes of those Gaussians across it; its extent
//! holds 98% of them along each axis (opaque ones only, so that thin haze
//! does not stretch it), with a margin.

use super::SplatsModel;
use super::gaussians::sigmoid;
use crate::engine::dataset::{Dataset, Split};
use crate::engine::geometry::camera::Camera;
use crate::engine::geometry::math::Vec3;
use crate::engine::models::{Model, ModelError};

/// An oriented box: `centre`, unit orthogonal `axes` (rows: the box's x,
/// y, z in world coordinates) and the half extent along each.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CropBox {
    pub centre: [f32; 3],
    pub axes: [[f32; 3]; 3],
    pub half: [f32; 3],
}

/// Why a crop cannot be made or used.
#[derive(Debug, thiserror::Error)]
pub enum CropError {
    /// A field of the box is wrong: the field and why.
    #[error("crop {0}: {1}")]
    Field(&'static str, String),
    #[error("the crop keeps none of the {0} Gaussians")]
    Empty(usize),
    #[error("no training camera sees anything solid: no crop can be found")]
    Unseen,
    #[error(transparent)]
    Model(#[from] ModelError),
}

/// The share of the training cameras that must see a Gaussian for the
/// automatic crop to count it as the object.
pub const SEEN_BY: f32 = 0.9;
/// Opacity from which a Gaussian shapes the box.
const OPAQUE: f32 = 0.3;
/// The box's margin, a share of its size on each side: a thinner one cuts
/// an object's edges (docs/design/object.md).
const MARGIN: f32 = 0.15;

impl CropBox {
    /// The box's errors, naming the field.
    pub fn check(&self) -> Result<(), CropError> {
        if self.centre.iter().any(|v| !v.is_finite()) {
            return Err(CropError::Field("centre", "is not finite".into()));
        }
        if self.half.iter().any(|v| !(v.is_finite() && *v > 0.0)) {
            return Err(CropError::Field("half", format!("{:?}: each half extent must be positive", self.half)));
        }
        let axes = self.axes.map(Vec3::from_array);
        for i in 0..3 {
            for j in 0..3 {
                let want = if i == j { 1.0 } else { 0.0 };
                if !(axes[i].dot(axes[j]) - want).abs().lt(&1e-3) {
                    return Err(CropError::Field("axes", "must be three orthogonal unit vectors".into()));
                }
            }
        }
        Ok(())
    }

    /// Whether world point `p` is inside.
    pub fn contains(&self, p: [f32; 3]) -> bool {
        let d = Vec3::from_array(p) - Vec3::from_array(self.centre);
        (0..3).all(|a| Vec3::from_array(self.axes[a]).dot(d).abs() <= self.half[a])
    }
}

/// Each Gaussian's centre in world units.
pub fn world_centres(model: &SplatsModel) -> Vec<[f32; 3]> {
    let (l, s) = (model.layout(), model.scene());
    (0..l.n).map(|i| s.point_to_world(l.get(model.params(), i).mean)).collect()
}

/// The box around what nearly every one of `cameras` sees, standing on `up`.
pub fn auto_crop(model: &SplatsModel, cameras: &[Camera], up: [f32; 3]) -> Result<CropBox, CropError> {
    let l = model.layout();
    let opaque: Vec<Vec3> = world_centres(model)
        .iter()
        .enumerate()
        .filter(|&(i, _)| sigmoid(l.get(model.params(), i).opacity_logit) >= OPAQUE)
        .map(|(_, p)| Vec3::from_array(*p))
        .collect();
    crop_around(&opaque, cameras, up)
}

/// The box around those of `points` (world units: what a model draws
/// solid) that nearly every one of `cameras` has in its frame, standing on
/// `up`.
pub fn crop_around(points: &[Vec3], cameras: &[Camera], up: [f32; 3]) -> Result<CropBox, CropError> {
    let need = (SEEN_BY * cameras.len() as f32).ceil() as usize;
    let object: Vec<Vec3> = points
        .iter()
        .filter(|p| cameras.iter().filter(|c| c.project(p.to_array()).is_some()).count() >= need.max(1))
        .copied()
        .collect();
    if object.is_empty() {
        return Err(CropError::Unseen);
    }
    let z = Vec3::from_array(up).normalized().ok_or(CropError::Field("up", "is not a direction".into()))?;
    let (x, y) = horizontal_axes(&object, z);
    let axes = [x, y, z];
    let mut centre = Vec3::new(0.0, 0.0, 0.0);
    let mut half = [0.0; 3];
    for a in 0..3 {
        let mut t: Vec<f32> = object.iter().map(|p| axes[a].dot(*p)).collect();
        t.sort_unstable_by(f32::total_cmp);
        let (lo, hi) = (t[t.len() / 100], t[(t.len() * 99) / 100]);
        let pad = MARGIN * (hi - lo).max(1e-6);
        half[a] = 0.5 * (hi - lo) + pad;
        centre = centre + axes[a] * (0.5 * (lo + hi));
    }
    Ok(CropBox { centre: centre.to_array(), axes: axes.map(Vec3::to_array), half })
}

/// The principal axes of `points` across `z` (the larger spread first),
/// a right-handed `x, y` with `z`.
fn horizontal_axes(points: &[Vec3], z: Vec3) -> (Vec3, Vec3) {
    // Any basis of the plane, then the 2x2 covariance's eigenvectors in it.
    let seed = if z.x.abs() < 0.9 { Vec3::new(1.0, 0.0, 0.0) } else { Vec3::new(0.0, 1.0, 0.0) };
    let e1 = z.cross(seed).normalized().expect("a vector not along z");
    let e2 = z.cross(e1);
    let n = points.len() as f64;
    let (mut m1, mut m2) = (0.0f64, 0.0f64);
    for p in points {
        m1 += e1.dot(*p) as f64;
        m2 += e2.dot(*p) as f64;
    }
    let (m1, m2) = (m1 / n, m2 / n);
    let (mut a, mut b, mut c) = (0.0f64, 0.0f64, 0.0f64);
    for p in points {
        let (u, v) = (e1.dot(*p) as f64 - m1, e2.dot(*p) as f64 - m2);
        a += u * u;
        b += u * v;
        c += v * v;
    }
    let angle = 0.5 * (2.0 * b).atan2(a - c);
    let x = e1 * angle.cos() as f32 + e2 * angle.sin() as f32;
    (x, z.cross(x))
}

/// [`auto_crop`] for `ds`'s training cameras and rig; `None` for a capture
/// with no rig or a forward-facing one (nothing was walked around).
pub fn auto_crop_for(model: &SplatsModel, ds: &Dataset) -> Result<Option<CropBox>, CropError> {
    let Some(rig) = ds.rig().filter(|r| !r.forward_facing) else { return Ok(None) };
    let cameras: Vec<Camera> = ds.split_frames(Split::Train).map(|f| f.camera.clone()).collect();
    auto_crop(model, &cameras, rig.up).map(Some)
}

/// `model` with only the Gaussians whose centres are inside `b`, and how
/// many went.
pub fn crop(model: &SplatsModel, b: &CropBox) -> Result<(SplatsModel, usize), CropError> {
    b.check()?;
    let keep: Vec<usize> =
        world_centres(model).iter().enumerate().filter(|(_, p)| b.contains(**p)).map(|(i, _)| i).collect();
    let n = model.layout().n;
    if keep.is_empty() {
        return Err(CropError::Empty(n));
    }
    Ok((model.keeping(&keep)?, n - keep.len()))
}

/// `model` as views under the crop `b` draw it: a splats model's Gaussians
/// inside `b` ([`crop`]); `None` for a model of another kind, whose views
/// the crop leaves as they are (its box is still checked).
pub fn crop_model(model: &dyn Model, b: &CropBox) -> Result<Option<SplatsModel>, CropError> {
    match model.as_any().downcast_ref::<SplatsModel>() {
        Some(splats) => crop(splats, b).map(|(m, _)| Some(m)),
        None => b.check().map(|()| None),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::geometry::camera::look_at;
    use crate::engine::geometry::math::{Aabb, Vec3};
    use crate::engine::models::splats::SplatsConfig;
    use crate::engine::models::splats::gaussians::Layout;

    /// Opaque Gaussians at world `points` (the scene's space is shifted
    /// and scaled, so world and model units differ).
    fn model(points: &[[f32; 3]]) -> SplatsModel {
        let scene = crate::engine::geometry::scene::Scene::from_bounds(
            Aabb { min: Vec3::new(-3.0, -3.0, -1.0), max: Vec3::new(5.0, 5.0, 3.0) },
            0.0,
            20.0,
        );
        let l = Layout::new(points.len(), 0);
        let mut p = vec![0.0; l.len()];
        for (i, q) in points.iter().enumerate() {
            for c in 0..3 {
                p[3 * i + c] = (q[c] - scene.centre[c]) * scene.scale;
            }
            p[3 * l.n + 3 * i..3 * l.n + 3 * i + 3].fill(-4.0);
            p[6 * l.n + 4 * i] = 1.0;
            p[10 * l.n + i] = 3.0;
        }
        SplatsModel::from_parts(SplatsConfig { sh_degree: 0, ..Default::default() }, scene, p).unwrap()
    }

    /// 24 cameras on a ring of radius 4 at height 1 around (1, 1, 0.5),
    /// z up, looking at it with a 60 degree field of view.
    fn ring() -> Vec<Camera> {
        (0..24)
            .map(|k| {
                let a = k as f32 * std::f32::consts::TAU / 24.0;
                let eye = Vec3::new(1.0 + 4.0 * a.cos(), 1.0 + 4.0 * a.sin(), 1.5);
                let pose = look_at(eye, Vec3::new(1.0, 1.0, 0.5), Vec3::new(0.0, 0.0, 1.0)).unwrap();
                Camera::from_fov(64, 48, 60f32.to_radians(), pose)
            })
            .collect()
    }

    #[test]
    fn the_focus_projects_to_the_frame_centre_and_what_is_behind_nowhere() {
        let cams = ring();
        let (u, v) = cams[0].project([1.0, 1.0, 0.5]).unwrap();
        assert!((u - 32.0).abs() < 1e-3 && (v - 24.0).abs() < 1e-3, "{u} {v}");
        // Above the focus is up in the photo (smaller v).
        assert!(cams[0].project([1.0, 1.0, 0.8]).unwrap().1 < 24.0);
        assert!(cams[0].project([1.0 + 8.0, 1.0, 1.5]).is_none(), "behind the camera");
    }

    #[test]
    fn the_automatic_crop_keeps_the_object_and_drops_the_room() {
        // The object: a 0.6 x 0.4 x 0.5 block of points at the focus. The
        // room: walls at distance 7, each seen by a few cameras only.
        let mut pts = Vec::new();
        for i in 0..7 {
            for j in 0..5 {
                for k in 0..6 {
                    pts.push([0.7 + 0.1 * i as f32, 0.8 + 0.1 * j as f32, 0.25 + 0.1 * k as f32]);
                }
            }
        }
        let object = pts.len();
        for k in 0..72 {
            let a = k as f32 * std::f32::consts::TAU / 72.0;
            for h in 0..3 {
                pts.push([1.0 + 7.0 * a.cos(), 1.0 + 7.0 * a.sin(), h as f32 * 0.6]);
            }
        }
        let m = model(&pts);
        let b = auto_crop(&m, &ring(), [0.0, 0.0, 2.0]).unwrap();
        b.check().unwrap();
        assert!((0..object).all(|i| b.contains(pts[i])), "the object is inside: {b:?}");
        assert!(pts[object..].iter().all(|p| !b.contains(*p)), "the room is outside: {b:?}");
        assert!((b.axes[2][2] - 1.0).abs() < 1e-5, "the box stands on up");
        // Cropped, the object alone remains, its Gaussians as they were.
        let (c, removed) = crop(&m, &b).unwrap();
        assert_eq!((c.layout().n, removed), (object, pts.len() - object));
        assert_eq!(c.params()[..3 * object], m.params()[..3 * object]);
    }

    #[test]
    fn bad_boxes_are_errors_naming_the_field() {
        let good =
            CropBox { centre: [0.0; 3], axes: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], half: [1.0; 3] };
        good.check().unwrap();
        let field = |b: CropBox| match b.check() {
            Err(CropError::Field(f, _)) => f,
            other => panic!("{other:?}"),
        };
        assert_eq!(field(CropBox { centre: [f32::NAN, 0.0, 0.0], ..good }), "centre");
        assert_eq!(field(CropBox { half: [1.0, 0.0, 1.0], ..good }), "half");
        assert_eq!(field(CropBox { half: [1.0, -2.0, 1.0], ..good }), "half");
        assert_eq!(field(CropBox { half: [1.0, f32::INFINITY, 1.0], ..good }), "half");
        assert_eq!(field(CropBox { axes: [[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], ..good }), "axes");
        // A box that keeps nothing.
        let m = model(&[[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]]);
        let far = CropBox { centre: [10.0, 10.0, 10.0], ..good };
        assert!(matches!(crop(&m, &far), Err(CropError::Empty(2))));
        assert!(matches!(crop(&m, &CropBox { half: [0.0; 3], ..good }), Err(CropError::Field("half", _))));
    }

    #[test]
    fn views_of_a_splats_model_keep_what_is_inside_and_a_field_stays_whole() {
        let good =
            CropBox { centre: [0.0; 3], axes: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], half: [0.3; 3] };
        let m = model(&[[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.1, -0.2, 0.25]]);
        let kept = crop_model(&m, &good).unwrap().expect("splats are cropped");
        assert_eq!(kept.layout().n, 2);
        assert!(matches!(crop_model(&m, &CropBox { centre: [9.0; 3], ..good }), Err(CropError::Empty(3))));
        // A field model: nothing to cut, but the box is still checked.
        let ds = crate::engine::dataset::synthetic::BallScene { size: 4, views: 2, ..Default::default() }.dataset();
        let config = crate::engine::models::config::ModelConfig::preset("nerf-tiny").unwrap();
        let field = config.build(ds.scene(), 0).unwrap();
        assert!(crop_model(&*field, &good).unwrap().is_none());
        assert!(matches!(crop_model(&*field, &CropBox { half: [-1.0; 3], ..good }), Err(CropError::Field("half", _))));
    }
}
