//! Space maps: where a point `x` of model space lands in the unit cube
//! `u ∈ [0, 1]^3` a hash grid covers, for scenes that do not fit in a box
//! (`docs/design/real-captures.md`, sections 2.2 and 2.3).
//!
//! - **Contraction** (mip-NeRF 360, Eq. 10; the L∞ variant of nerfacto and
//!   MERF): the unit ball of the norm stays as it is and everything beyond
//!   is squeezed into the shell out to radius 2, `y = (2 - 1/m) x / m` with
//!   `m = ‖x‖`; then `u = (y + 2) / 4`. Distance beyond the ball is spent
//!   like disparity, so infinity lands on the cube's faces (L∞) or on the
//!   ball inscribed in the cube (L2).
//! - **NDC** (NeRF's normalised device coordinates, written per point) for
//!   forward-facing captures: the frustum of a reference camera, from its
//!   near plane to infinity, becomes `P ∈ [-1, 1]^3` with depth spent as
//!   disparity; `u = (P + 1) / 2`.
//!
//! Each map comes with its vector-Jacobian product `vjp(x, dL/du) = J^T
//! dL/du = dL/dx`, exact, so position gradients (camera pose refinement)
//! can flow through it, and with its inverse, which places points of the
//! cube back in model space (occupancy-grid updates in contracted space).
//! Scalar forms take one point; `_batch` forms take slices of points, as
//! the fields' loops do. f32 throughout, arranged so that huge coordinates
//! neither overflow nor round out of the cube.

use serde::{Deserialize, Serialize};

/// The norm a contraction measures distance with.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Norm {
    /// `max |x_i|`: the unit cube stays, space beyond fills `[-2, 2]^3`
    /// (nerfacto, MERF). The whole grid cube is used.
    Linf,
    /// Euclidean: the unit ball stays, space beyond fills the ball of
    /// radius 2 (mip-NeRF 360); the cube's corners stay unused.
    L2,
}

/// How a model maps model space into its grid's unit cube, as a checkpoint
/// stores it: `{"kind": "contract", "norm": "linf"}` or `{"kind": "ndc",
/// "rotation": ..., "centre": ..., "near": ..., "fx": ..., "fy": ...,
/// "width": ..., "height": ...}`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum SpaceMap {
    /// Scene contraction: `u = (contract(x) + 2) / 4`.
    Contract { norm: Norm },
    /// NDC of a reference camera: `u = (P(x) + 1) / 2`.
    Ndc(NdcFrame),
}

/// Why an NDC camera cannot define a space map.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum SpaceError {
    #[error("NDC camera: {field} must be a finite number above 0, not {value}")]
    NotPositive { field: &'static str, value: f32 },
    #[error("NDC camera: the image size must be at least 1x1, not {width}x{height}")]
    Size { width: u32, height: u32 },
    #[error("NDC camera: the centre must be finite, not {0:?}")]
    Centre([f32; 3]),
    #[error("NDC camera: {rotation:?} is not a rotation matrix ({reason})")]
    Rotation { rotation: [[f32; 3]; 3], reason: &'static str },
}

/// The reference camera of NDC, as plain data (what a checkpoint stores;
/// [`NdcFrame::new`] checks it).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NdcCamera {
    /// Camera-to-model rotation `R0`, by rows: its columns are the camera's
    /// right, up and backward axes (OpenGL: the camera looks down `-z`).
    pub rotation: [[f32; 3]; 3],
    /// Camera centre `c0` in model space.
    pub centre: [f32; 3],
    /// Near-plane depth `n` in model units: depth `n` maps to `P_z = -1`,
    /// infinity to `P_z = 1`.
    pub near: f32,
    /// Focal lengths in pixels.
    pub fx: f32,
    pub fy: f32,
    /// Image size in pixels: the image's edges map to `P_x, P_y = ±1`.
    pub width: u32,
    pub height: u32,
}

/// A checked [`NdcCamera`] with the scales its map uses.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "NdcCamera", into = "NdcCamera")]
pub struct NdcFrame {
    camera: NdcCamera,
    /// `2 fx / W` and `2 fy / H`.
    sx: f32,
    sy: f32,
}

/// How far `R0^T R0` may be from the identity (entry-wise): rotations built
/// from normalised cross products in f32 are within 1e-6; the inverse map
/// uses the transpose, so it is as exact as the rotation is orthonormal.
const ORTHONORMAL_TOLERANCE: f32 = 1e-4;

impl NdcFrame {
    /// Checks `camera`: positive finite near depth and focal lengths, a
    /// non-empty image, a finite centre and a proper rotation.
    pub fn new(camera: NdcCamera) -> Result<Self, SpaceError> {
        for (field, value) in [("near", camera.near), ("fx", camera.fx), ("fy", camera.fy)] {
            if !(value.is_finite() && value > 0.0) {
                return Err(SpaceError::NotPositive { field, value });
            }
        }
        if camera.width == 0 || camera.height == 0 {
            return Err(SpaceError::Size { width: camera.width, height: camera.height });
        }
        if !camera.centre.iter().all(|v| v.is_finite()) {
            return Err(SpaceError::Centre(camera.centre));
        }
        check_rotation(&camera.rotation)?;
        let sx = 2.0 * camera.fx / camera.width as f32;
        let sy = 2.0 * camera.fy / camera.height as f32;
        if !(sx.is_finite() && sx > 0.0 && sy.is_finite() && sy > 0.0) {
            return Err(SpaceError::NotPositive { field: "focal length over image size", value: sx.min(sy) });
        }
        Ok(Self { camera, sx, sy })
    }

    /// The camera this frame was made from.
    pub fn camera(&self) -> &NdcCamera {
        &self.camera
    }

    /// `x` in the camera's axes: `R0^T (x - c0)`.
    fn to_camera(&self, x: [f32; 3]) -> [f32; 3] {
        let (r, c) = (&self.camera.rotation, self.camera.centre);
        let d = [x[0] - c[0], x[1] - c[1], x[2] - c[2]];
        std::array::from_fn(|i| r[0][i] * d[0] + r[1][i] * d[1] + r[2][i] * d[2])
    }

    /// `R0 v`: a camera-axes vector in model axes.
    fn to_model(&self, v: [f32; 3]) -> [f32; 3] {
        let r = &self.camera.rotation;
        std::array::from_fn(|i| r[i][0] * v[0] + r[i][1] * v[1] + r[i][2] * v[2])
    }

    /// The depth coordinate the map divides by: `z_c`, but never closer to
    /// the camera than half the near depth. Points nearer than that (and
    /// behind the camera) are mapped as if at `z_c = -n/2`, which lands on
    /// the plane `P_z = -3`, outside the cube like every point in front of
    /// the near plane, instead of dividing by zero.
    fn depth(&self, zc: f32) -> f32 {
        zc.min(-0.5 * self.camera.near)
    }

    /// NDC of a model-space point, with `(x_c, y_c, z_c) = R0^T (x - c0)`:
    /// `P = (-(2 fx / W) x_c / z_c, -(2 fy / H) y_c / z_c, 1 + 2 n / z_c)`.
    /// The frustum beyond the near plane maps to `[-1, 1]^3`; lines map to
    /// lines. NaN coordinates give NaN.
    pub fn project(&self, x: [f32; 3]) -> [f32; 3] {
        let c = self.to_camera(x);
        let z = self.depth(c[2]);
        [-self.sx * c[0] / z, -self.sy * c[1] / z, 1.0 + 2.0 * self.camera.near / z]
    }

    /// The model-space point whose NDC is `p`; `None` unless `p` is finite
    /// and `-3 <= P_z < 1` (the image of [`NdcFrame::project`]; `P_z = 1` is
    /// infinitely far). On the plane `P_z = -3` it returns the point at
    /// depth `n/2`, one of the points that map there.
    pub fn unproject(&self, p: [f32; 3]) -> Option<[f32; 3]> {
        if !(p.iter().all(|v| v.is_finite()) && (-3.0..1.0).contains(&p[2])) {
            return None;
        }
        let z = 2.0 * self.camera.near / (p[2] - 1.0);
        let v = self.to_model([-p[0] * z / self.sx, -p[1] * z / self.sy, z]);
        let c = self.camera.centre;
        Some([v[0] + c[0], v[1] + c[1], v[2] + c[2]])
    }

    /// `dL/dx` from `dL/dP` at `x`: in the camera's axes
    /// `dL/dx_c = -(2 fx / W) g_0 / z_c`, `dL/dy_c = -(2 fy / H) g_1 / z_c`,
    /// `dL/dz_c = ((2 fx / W) g_0 x_c + (2 fy / H) g_1 y_c - 2 n g_2) / z_c^2`
    /// (0 where the depth is held at `n/2`), then rotated by `R0`. Zero for
    /// a non-finite `x`.
    pub fn project_vjp(&self, x: [f32; 3], dp: [f32; 3]) -> [f32; 3] {
        if !x.iter().all(|v| v.is_finite()) {
            return [0.0; 3];
        }
        let c = self.to_camera(x);
        let z = self.depth(c[2]);
        let (gx, gy) = (self.sx * dp[0], self.sy * dp[1]);
        let dz = if c[2] > z {
            // Held depth: z does not move with z_c.
            0.0
        } else {
            (gx * c[0] + gy * c[1] - 2.0 * self.camera.near * dp[2]) / (z * z)
        };
        self.to_model([-gx / z, -gy / z, dz])
    }
}

impl TryFrom<NdcCamera> for NdcFrame {
    type Error = SpaceError;
    fn try_from(camera: NdcCamera) -> Result<Self, SpaceError> {
        Self::new(camera)
    }
}

impl From<NdcFrame> for NdcCamera {
    fn from(frame: NdcFrame) -> Self {
        frame.camera
    }
}

/// Refuses non-finite, non-orthonormal and reflecting matrices.
fn check_rotation(r: &[[f32; 3]; 3]) -> Result<(), SpaceError> {
    let fail = |reason| Err(SpaceError::Rotation { rotation: *r, reason });
    if !r.iter().flatten().all(|v| v.is_finite()) {
        return fail("not finite");
    }
    for i in 0..3 {
        for j in 0..3 {
            let dot: f32 = (0..3).map(|k| r[k][i] * r[k][j]).sum();
            let want = if i == j { 1.0 } else { 0.0 };
            if (dot - want).abs() > ORTHONORMAL_TOLERANCE {
                return fail("its columns are not orthonormal");
            }
        }
    }
    let det = r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1]) - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
        + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0]);
    if det < 0.0 {
        return fail("it is a reflection: determinant -1");
    }
    Ok(())
}

/// `max |x_i|` (NaN components are skipped by `max`, so only an all-NaN
/// point gives NaN).
fn max_abs(x: [f32; 3]) -> f32 {
    x[0].abs().max(x[1].abs()).max(x[2].abs())
}

/// `x / m` for `m = max |x_i| > 0`: every component in `[-1, 1]`, the
/// largest exactly ±1. For an infinite `m` the limit direction: ±1 for the
/// infinite components, 0 for the others.
fn scaled(x: [f32; 3], m: f32) -> [f32; 3] {
    if m.is_infinite() { x.map(|v| if v.is_infinite() { v.signum() } else { 0.0 }) } else { x.map(|v| v / m) }
}

/// The Euclidean norm of a point already scaled by [`scaled`] (no overflow).
fn norm2(s: [f32; 3]) -> f32 {
    (s[0] * s[0] + s[1] * s[1] + s[2] * s[2]).sqrt()
}

fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

impl Norm {
    /// `y = x` inside the unit ball of the norm, `y = (2 - 1/m) x / m`
    /// beyond (`m = ‖x‖`), so `‖y‖ < 2` for every finite `x` and `‖y‖ -> 2`
    /// as `m -> ∞`. Continuous with a continuous Jacobian at `m = 1`.
    /// Infinite coordinates go to their limit on the boundary; NaN
    /// coordinates stay NaN.
    pub fn contract(self, x: [f32; 3]) -> [f32; 3] {
        let m = max_abs(x);
        if m == 0.0 || m.is_nan() {
            return x;
        }
        let s = scaled(x, m);
        match self {
            Norm::Linf if m > 1.0 => s.map(|v| (2.0 - 1.0 / m) * v),
            Norm::Linf => x,
            Norm::L2 => {
                // r = m q with q in [1, sqrt 3]: no overflow before the
                // division, and |s_i / q| <= 1 exactly, so |y| <= 2.
                let q = norm2(s);
                let r = m * q;
                if r > 1.0 { s.map(|v| (2.0 - 1.0 / r) * (v / q)) } else { x }
            }
        }
    }

    /// The inverse of [`Norm::contract`]: `x = y` inside the unit ball,
    /// `x = y / (m' (2 - m'))` beyond (`m' = ‖y‖`); `None` for `‖y‖ >= 2`
    /// (infinitely far) or a non-finite `y`.
    pub fn uncontract(self, y: [f32; 3]) -> Option<[f32; 3]> {
        if !y.iter().all(|v| v.is_finite()) {
            return None;
        }
        let m = match self {
            Norm::Linf => max_abs(y),
            Norm::L2 => norm2(y),
        };
        if m <= 1.0 {
            return Some(y);
        }
        if m >= 2.0 {
            return None;
        }
        // ‖x‖ = 1 / (2 - m'), and x points along y.
        let k = 1.0 / (2.0 - m) / m;
        Some(y.map(|v| v * k))
    }

    /// `dL/dx = J^T dL/dy` at `x`. Beyond the unit ball, with `m = ‖x‖`:
    /// - L∞ (`k` = the first index of the largest `|x_k|`, `s = sign x_k`):
    ///   `J = ((2m - 1)/m^2) I + (2(1 - m)/m^3) s x e_k^T`, so
    ///   `(J^T g)_j = ((2m - 1)/m^2) g_j + [j = k] (2(1 - m)/m^3) s (x · g)`;
    /// - L2: `J = ((2m - 1)/m^2) I + (2(1 - m)/m^4) x x^T`.
    ///
    /// Inside it `J = I`. Zero for a non-finite `x` (the map is constant at
    /// infinity). On the faces where the largest `|x_k|` switches axis the
    /// L∞ map has one-sided derivatives; this takes the first axis's.
    pub fn contract_vjp(self, x: [f32; 3], dy: [f32; 3]) -> [f32; 3] {
        if !x.iter().all(|v| v.is_finite()) {
            return [0.0; 3];
        }
        let m = max_abs(x);
        let s = scaled(x, m);
        // Written in 1/m (or 1/r) and the scaled point, so that nothing
        // overflows for huge x: (2m - 1)/m^2 = (2 - 1/m)/m and
        // 2(1 - m)/m^3 (x · g) = -2 (1 - 1/m)/m (s · g).
        match self {
            Norm::Linf if m > 1.0 => {
                let inv = 1.0 / m;
                let a = (2.0 - inv) * inv;
                let b = -2.0 * (1.0 - inv) * inv * dot(s, dy);
                let k = if x[0].abs() == m {
                    0
                } else if x[1].abs() == m {
                    1
                } else {
                    2
                };
                let mut dx = dy.map(|g| a * g);
                dx[k] += b * s[k];
                dx
            }
            Norm::L2 if m > 0.0 => {
                let q = norm2(s);
                let r = m * q;
                // x is finite and not 0 here, so r is a number.
                if r <= 1.0 {
                    return dy;
                }
                let inv = 1.0 / r;
                let a = (2.0 - inv) * inv;
                let n = s.map(|v| v / q);
                let b = -2.0 * (1.0 - inv) * inv * dot(n, dy);
                std::array::from_fn(|j| a * dy[j] + b * n[j])
            }
            _ => dy,
        }
    }
}

impl SpaceMap {
    /// The grid coordinates `u` of a model-space point. Contractions keep
    /// every finite point in `[0, 1]^3`; NDC keeps its frustum beyond the
    /// near plane there, and sends other points outside (a field gives
    /// them no density).
    pub fn map(&self, x: [f32; 3]) -> [f32; 3] {
        match self {
            SpaceMap::Contract { norm } => norm.contract(x).map(|y| (y + 2.0) * 0.25),
            SpaceMap::Ndc(frame) => frame.project(x).map(|p| (p + 1.0) * 0.5),
        }
    }

    /// The model-space point at grid coordinates `u`; `None` where no finite
    /// point maps to `u` (see [`Norm::uncontract`], [`NdcFrame::unproject`]).
    pub fn unmap(&self, u: [f32; 3]) -> Option<[f32; 3]> {
        match self {
            SpaceMap::Contract { norm } => norm.uncontract(u.map(|v| 4.0 * v - 2.0)),
            SpaceMap::Ndc(frame) => frame.unproject(u.map(|v| 2.0 * v - 1.0)),
        }
    }

    /// `dL/dx` at `x` from `dL/du` (see [`Norm::contract_vjp`],
    /// [`NdcFrame::project_vjp`]; `du/dy = 1/4`, `du/dP = 1/2`).
    pub fn vjp(&self, x: [f32; 3], du: [f32; 3]) -> [f32; 3] {
        match self {
            SpaceMap::Contract { norm } => norm.contract_vjp(x, du.map(|g| 0.25 * g)),
            SpaceMap::Ndc(frame) => frame.project_vjp(x, du.map(|g| 0.5 * g)),
        }
    }

    /// [`SpaceMap::map`] of every point of `xs` into `us`.
    ///
    /// # Panics
    /// If the slices differ in length (a caller's bug: it sizes both).
    pub fn map_batch(&self, xs: &[[f32; 3]], us: &mut [[f32; 3]]) {
        assert_eq!(xs.len(), us.len(), "space map: {} points but {} outputs", xs.len(), us.len());
        // One match per batch, not per point.
        match self {
            SpaceMap::Contract { norm } => {
                for (x, u) in xs.iter().zip(us) {
                    *u = norm.contract(*x).map(|y| (y + 2.0) * 0.25);
                }
            }
            SpaceMap::Ndc(frame) => {
                for (x, u) in xs.iter().zip(us) {
                    *u = frame.project(*x).map(|p| (p + 1.0) * 0.5);
                }
            }
        }
    }

    /// [`SpaceMap::vjp`] of every point: `dxs[i] = J(xs[i])^T dus[i]`.
    ///
    /// # Panics
    /// If the slices differ in length (a caller's bug: it sizes them).
    pub fn vjp_batch(&self, xs: &[[f32; 3]], dus: &[[f32; 3]], dxs: &mut [[f32; 3]]) {
        assert!(
            xs.len() == dus.len() && xs.len() == dxs.len(),
            "space map: {} points, {} gradients and {} outputs",
            xs.len(),
            dus.len(),
            dxs.len()
        );
        match self {
            SpaceMap::Contract { norm } => {
                for ((x, du), dx) in xs.iter().zip(dus).zip(dxs) {
                    *dx = norm.contract_vjp(*x, du.map(|g| 0.25 * g));
                }
            }
            SpaceMap::Ndc(frame) => {
                for ((x, du), dx) in xs.iter().zip(dus).zip(dxs) {
                    *dx = frame.project_vjp(*x, du.map(|g| 0.5 * g));
                }
            }
        }
    }
}

/// For tests: NDC of a 64x48 forward-facing camera at the origin looking
/// down -z (near 0.5, focal 40).
#[cfg(test)]
pub(crate) fn test_ndc() -> SpaceMap {
    let camera = NdcCamera {
        rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        centre: [0.0, 0.0, 0.0],
        near: 0.5,
        fx: 40.0,
        fy: 40.0,
        width: 64,
        height: 48,
    };
    SpaceMap::Ndc(NdcFrame::new(camera).unwrap())
}

#[cfg(test)]
#[path = "space_tests.rs"]
mod tests;
