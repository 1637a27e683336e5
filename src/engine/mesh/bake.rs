//! The texture: every texel's point on the mesh coloured from the views
//! that see it, weighted towards those that face it.

use rayon::prelude::*;

use crate::engine::geometry::math::Vec3;
use crate::engine::mesh::atlas::Atlas;
use crate::engine::mesh::isosurface::{Mesh, cross, sub};
use crate::engine::mesh::views::SurfaceView;

/// Grey, for a texel no view faces.
const UNSEEN: [f32; 3] = [0.5; 3];
/// Views at a grazing angle (cosine under this) do not colour a point.
const GRAZING: f32 = 0.1;

/// The `atlas.size` square texture (RGB, row-major, values in [0, 1]) of
/// `mesh`, from `views`; a view sees a point when its surface is within
/// `tolerance` (world units) of it.
pub fn texture(mesh: &Mesh, atlas: &Atlas, views: &[SurfaceView], tolerance: f32) -> Vec<[f32; 3]> {
    let normals: Vec<Vec3> = mesh
        .triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|v| mesh.positions[v as usize]);
            Vec3::from_array(cross(sub(b, a), sub(c, a))).normalized().unwrap_or(Vec3::splat(0.0))
        })
        .collect();
    let size = atlas.size as usize;
    let mut out = vec![UNSEEN; size * size];
    out.par_chunks_mut(size).enumerate().for_each(|(y, row)| {
        for (x, texel) in row.iter_mut().enumerate() {
            let Some((t, l)) = atlas.texel(x as u32, y as u32) else { continue };
            let corners = mesh.triangles[t].map(|v| Vec3::from_array(mesh.positions[v as usize]));
            let p = corners[0] * l[0] + corners[1] * l[1] + corners[2] * l[2];
            *texel = colour_at(p, normals[t], views, tolerance);
        }
    });
    out
}

/// The colour of surface point `p` (normal `n`): the mean over the views
/// that see it, each weighted by the squared cosine between its line of
/// sight and the normal; where none sees it (hidden in every view), the
/// view that faces it most.
pub fn colour_at(p: Vec3, n: Vec3, views: &[SurfaceView], tolerance: f32) -> [f32; 3] {
    let mut sum = [0.0f32; 3];
    let mut total = 0.0f32;
    let mut facing: Option<(f32, [f32; 3])> = None;
    for v in views {
        let Some((u, y, dist)) = v.project(p) else { continue };
        let cos = n.dot(v.camera.origin() - p) / dist.max(1e-12);
        if cos < GRAZING {
            continue;
        }
        let c = v.colour(u, y);
        if facing.is_none_or(|(best, _)| cos > best) {
            facing = Some((cos, c));
        }
        if v.surface_at(u, y).is_some_and(|s| (s - dist).abs() <= tolerance) {
            let w = cos * cos;
            (0..3).for_each(|k| sum[k] += w * c[k]);
            total += w;
        }
    }
    if total > 0.0 { sum.map(|s| s / total) } else { facing.map_or(UNSEEN, |(_, c)| c) }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::geometry::camera::{Camera, look_at};
    use crate::engine::mesh::atlas::layout;

    /// A view of the plane z = 0 coloured by `paint`, from `eye`.
    fn plane_view(eye: Vec3, paint: &dyn Fn(Vec3) -> [f32; 3]) -> SurfaceView {
        let camera = Camera::from_fov(48, 48, 1.2, look_at(eye, Vec3::splat(0.0), Vec3::new(0.0, 1.0, 0.0)).unwrap());
        crate::engine::mesh::views::plane_view(camera, paint)
    }

    #[test]
    fn a_painted_plane_bakes_into_its_colours() {
        // Red on the left half (x < 0), blue on the right, seen from two sides.
        let paint = |p: Vec3| if p.x < 0.0 { [0.9, 0.1, 0.1] } else { [0.1, 0.2, 0.8] };
        let views = [plane_view(Vec3::new(0.3, 0.2, 2.0), &paint), plane_view(Vec3::new(-0.4, -0.1, 1.5), &paint)];
        let mesh = Mesh {
            positions: vec![[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.5, 0.5, 0.0], [-0.5, 0.5, 0.0]],
            triangles: vec![[0, 1, 2], [0, 2, 3]],
        };
        let atlas = layout(2, 64).unwrap();
        let tex = texture(&mesh, &atlas, &views, 0.01);
        let mut checked = 0;
        for y in 0..64u32 {
            for x in 0..64u32 {
                let Some((t, l)) = atlas.texel(x, y) else { continue };
                let p: Vec3 = mesh.triangles[t]
                    .iter()
                    .zip(l)
                    .fold(Vec3::splat(0.0), |s, (&v, w)| s + Vec3::from_array(mesh.positions[v as usize]) * w);
                if p.x.abs() < 0.05 {
                    continue; // bilinear blends at the paint's edge
                }
                let want = paint(p);
                let got = tex[(y * 64 + x) as usize];
                assert!(
                    (0..3).all(|k| (got[k] - want[k]).abs() < 1e-3),
                    "texel ({x}, {y}) at {p:?}: {got:?}, want {want:?}"
                );
                checked += 1;
            }
        }
        assert!(checked > 1000, "{checked} texels checked");
    }

    #[test]
    fn a_point_hidden_from_a_view_takes_its_colour_from_the_others() {
        let paint_a = |_: Vec3| [1.0, 0.0, 0.0];
        let paint_b = |_: Vec3| [0.0, 1.0, 0.0];
        let sees = plane_view(Vec3::new(0.0, 0.0, 2.0), &paint_a);
        let mut hidden = plane_view(Vec3::new(0.1, 0.0, 2.0), &paint_b);
        // Something in front of the plane in the second view.
        hidden.surface.iter_mut().for_each(|s| *s = s.map(|d| d * 0.5));
        let c = colour_at(Vec3::splat(0.0), Vec3::new(0.0, 0.0, 1.0), &[sees, hidden], 0.01);
        assert_eq!(c, [1.0, 0.0, 0.0]);
    }
}
