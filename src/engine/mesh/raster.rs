//! Our own renderer of a textured mesh: each triangle rasterised with a
//! depth buffer at pixel centres, its texture coordinates interpolated
//! perspective-correctly and the texture read bilinearly without mipmaps
//! (as the GLB's sampler asks of a viewer). What the mesh is scored with
//! against the model it came from.

use crate::engine::geometry::camera::Camera;
use crate::engine::geometry::math::Vec3;
use crate::engine::mesh::TexturedMesh;

/// A view of a mesh: RGB (`[h x w x 3]`) composited on the background,
/// and the share of each pixel the mesh covers.
pub struct MeshView {
    pub rgb: Vec<f32>,
    pub coverage: Vec<f32>,
}

/// [`render`] with `k x k` samples a pixel (`k` = 1: one at its centre),
/// averaged: edges antialiased as a viewer's multisampling draws them, and
/// as the model's own renders and the photos have them.
pub fn render_antialiased(mesh: &TexturedMesh, camera: &Camera, background: [f32; 3], k: u32) -> MeshView {
    let k = k.max(1);
    let (w, h) = (camera.width as usize, camera.height as usize);
    let big = render(mesh, &finer(camera, k), background);
    let (fw, n) = (w * k as usize, (k * k) as f32);
    let mut rgb = vec![0.0f32; w * h * 3];
    let mut coverage = vec![0.0f32; w * h];
    for fy in 0..h * k as usize {
        for fx in 0..fw {
            let (i, f) = ((fy / k as usize) * w + fx / k as usize, fy * fw + fx);
            (0..3).for_each(|c| rgb[i * 3 + c] += big.rgb[f * 3 + c] / n);
            coverage[i] += big.coverage[f] / n;
        }
    }
    MeshView { rgb, coverage }
}

/// `camera` with `k x k` pixels for each of its own: pixel `(x, y)`'s
/// samples are the fine pixels `(k x + i, k y + j)`.
pub fn finer(camera: &Camera, k: u32) -> Camera {
    camera.resized(camera.width * k, camera.height * k, k as f32)
}

/// Renders `mesh` from `camera` (lens distortion ignored) over `background`.
pub fn render(mesh: &TexturedMesh, camera: &Camera, background: [f32; 3]) -> MeshView {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let hit = hits(&mesh.positions, &mesh.triangles, camera);
    let mut rgb = Vec::with_capacity(w * h * 3);
    let mut coverage = Vec::with_capacity(w * h);
    for px in &hit {
        match px {
            Some((t, l)) => {
                let (u, v) = uv_at(mesh.uvs[*t], *l);
                rgb.extend(mesh.sample(u, v));
                coverage.push(1.0);
            }
            None => {
                rgb.extend(background);
                coverage.push(0.0);
            }
        }
    }
    MeshView { rgb, coverage }
}

/// The texture coordinates at barycentric `l` on a triangle whose corners have `uv`.
pub fn uv_at(uv: [[f32; 2]; 3], l: [f32; 3]) -> (f32, f32) {
    (l[0] * uv[0][0] + l[1] * uv[1][0] + l[2] * uv[2][0], l[0] * uv[0][1] + l[1] * uv[1][1] + l[2] * uv[2][1])
}

/// What each pixel centre of `camera` sees of the triangles (lens
/// distortion ignored): the nearest triangle and the point's barycentric
/// coordinates on it (perspective-correct), row-major.
pub fn hits(positions: &[[f32; 3]], triangles: &[[u32; 3]], camera: &Camera) -> Vec<Option<(usize, [f32; 3])>> {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let m = &camera.c2w;
    let o = camera.origin();
    // Each vertex in camera coordinates.
    let cam: Vec<[f32; 3]> = positions
        .iter()
        .map(|p| {
            let d = Vec3::from_array(*p) - o;
            [0, 1, 2].map(|k| Vec3::new(m[0][k], m[1][k], m[2][k]).dot(d))
        })
        .collect();
    let mut depth = vec![f32::INFINITY; w * h];
    let mut hit: Vec<Option<(usize, [f32; 3])>> = vec![None; w * h];
    let near = 1e-4f32;
    for (t, tri) in triangles.iter().enumerate() {
        let c = tri.map(|v| cam[v as usize]);
        if c.iter().any(|p| -p[2] <= near) {
            continue; // a triangle crossing the camera plane is left out
        }
        let s = c.map(|p| {
            let z = -p[2];
            [camera.fx * p[0] / z + camera.cx, -camera.fy * p[1] / z + camera.cy, 1.0 / z]
        });
        let area = edge(s[0], s[1], s[2]);
        if area.abs() < 1e-12 {
            continue;
        }
        let x0 = s.iter().map(|p| p[0]).fold(f32::MAX, f32::min).floor().max(0.0) as usize;
        let x1 = (s.iter().map(|p| p[0]).fold(f32::MIN, f32::max).ceil().max(0.0) as usize).min(w);
        let y0 = s.iter().map(|p| p[1]).fold(f32::MAX, f32::min).floor().max(0.0) as usize;
        let y1 = (s.iter().map(|p| p[1]).fold(f32::MIN, f32::max).ceil().max(0.0) as usize).min(h);
        for y in y0..y1 {
            for x in x0..x1 {
                let p = [x as f32 + 0.5, y as f32 + 0.5, 0.0];
                let l = [edge(s[1], s[2], p) / area, edge(s[2], s[0], p) / area, edge(s[0], s[1], p) / area];
                if l.iter().any(|&v| v < 0.0) {
                    continue;
                }
                // Perspective-correct: interpolate 1/z, and attributes over z.
                let inv_z = l[0] * s[0][2] + l[1] * s[1][2] + l[2] * s[2][2];
                let z = 1.0 / inv_z;
                let i = y * w + x;
                if z < depth[i] {
                    depth[i] = z;
                    hit[i] = Some((t, [0, 1, 2].map(|k| l[k] * s[k][2] * z)));
                }
            }
        }
    }
    hit
}

/// Twice the signed area of `(a, b, p)` on screen.
fn edge(a: [f32; 3], b: [f32; 3], p: [f32; 3]) -> f32 {
    (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::geometry::camera::look_at;

    /// A square of side 2 at z = 0, textured with a 2x2 checker
    /// (red, green / blue, white).
    fn square() -> TexturedMesh {
        let texture = vec![[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0, 1.0]];
        TexturedMesh {
            positions: vec![[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]],
            triangles: vec![[0, 1, 2], [0, 2, 3]],
            // Texel centres at 0.25 and 0.75: each quarter of the square one colour.
            uvs: vec![[[0.25, 0.75], [0.75, 0.75], [0.75, 0.25]], [[0.25, 0.75], [0.75, 0.25], [0.25, 0.25]]],
            texture,
            texture_size: 2,
        }
    }

    /// The colour `square`'s texture gives its point `(x, y)`: bilinear
    /// between the four texel centres at its corners.
    fn expected(x: f32, y: f32) -> [f32; 3] {
        let (fx, fy) = ((x + 1.0) / 2.0, 1.0 - (y + 1.0) / 2.0);
        let t = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 1.0, 1.0]];
        let w = [(1.0 - fx) * (1.0 - fy), fx * (1.0 - fy), (1.0 - fx) * fy, fx * fy];
        [0, 1, 2].map(|k| (0..4).map(|i| w[i] * t[i][k]).sum())
    }

    fn check(mesh: &TexturedMesh, eye: Vec3) {
        let cam = Camera::from_fov(
            40,
            40,
            std::f32::consts::FRAC_PI_2,
            look_at(eye, Vec3::splat(0.0), Vec3::new(0.0, 1.0, 0.0)).unwrap(),
        );
        let view = render(mesh, &cam, [0.5; 3]);
        let mut inside = 0;
        for y in 0..40u32 {
            for x in 0..40u32 {
                let r = cam.pixel_ray(x, y);
                let p = r.at(-r.origin.z / r.dir.z);
                let i = (y * 40 + x) as usize;
                let got = [0, 1, 2].map(|k| view.rgb[i * 3 + k]);
                if p.x.abs() < 0.98 && p.y.abs() < 0.98 {
                    let want = expected(p.x, p.y);
                    assert!(
                        view.coverage[i] == 1.0 && (0..3).all(|k| (got[k] - want[k]).abs() < 0.01),
                        "pixel ({x}, {y}) at {p:?}: {got:?}, want {want:?}"
                    );
                    inside += 1;
                }
            }
        }
        assert!(inside > 300, "{inside} pixels checked");
    }

    #[test]
    fn a_square_seen_head_on_and_at_an_angle_shows_its_texture() {
        let mesh = square();
        check(&mesh, Vec3::new(0.0, 0.0, 2.0));
        check(&mesh, Vec3::new(0.6, -0.4, 1.8));
        let cam = Camera::from_fov(
            40,
            40,
            std::f32::consts::FRAC_PI_2,
            look_at(Vec3::new(0.0, 0.0, 2.0), Vec3::splat(0.0), Vec3::new(0.0, 1.0, 0.0)).unwrap(),
        );
        let view = render(&mesh, &cam, [0.5; 3]);
        // 90 degrees across at distance 2: the square spans the middle half.
        assert_eq!(view.coverage.iter().filter(|&&c| c == 1.0).count(), 400);
        assert_eq!(&view.rgb[..3], &[0.5; 3]);
    }

    #[test]
    fn the_nearer_surface_hides_the_farther() {
        let mut mesh = square();
        // A larger square behind the first, all one texel (red).
        let far: Vec<[f32; 3]> = mesh.positions.iter().map(|p| [p[0] * 3.0, p[1] * 3.0, -1.0]).collect();
        mesh.positions.extend(far);
        mesh.triangles.extend([[4, 5, 6], [4, 6, 7]]);
        mesh.uvs.extend([[[0.25, 0.25]; 3]; 2]);
        check(&mesh, Vec3::new(0.3, 0.2, 2.0));
    }

    #[test]
    fn antialiased_edges_cover_their_share_of_a_pixel() {
        let mut mesh = square();
        // Moved half a pixel right: its right edge cuts pixel column 30 in half.
        mesh.positions.iter_mut().for_each(|p| p[0] += 0.05);
        let cam = Camera::from_fov(
            40,
            40,
            std::f32::consts::FRAC_PI_2,
            look_at(Vec3::new(0.05, 0.0, 2.0), Vec3::new(0.05, 0.0, 0.0), Vec3::new(0.0, 1.0, 0.0)).unwrap(),
        );
        let cam = Camera { cx: 20.5, ..cam };
        let view = render_antialiased(&mesh, &cam, [0.5; 3], 4);
        let row = 20 * 40;
        assert_eq!(view.coverage[row + 29], 1.0);
        assert!((view.coverage[row + 30] - 0.5).abs() < 1e-6, "{}", view.coverage[row + 30]);
        assert_eq!(view.coverage[row + 31], 0.0);
        // Its colour: half the square's (nearly pure green along that edge), half the background's.
        let g = view.rgb[(row + 30) * 3 + 1];
        assert!((g - 0.75).abs() < 0.01, "{g}");
    }
}
