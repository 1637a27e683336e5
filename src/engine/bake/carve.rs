//! Free-space carving of the placed Gaussians (the module docs of `bake`,
//! stage 1): what another photo sees through is a floater.

use super::{Placed, in_frame};
use crate::engine::geometry::math::Vec3;
use crate::engine::models::splats::raster::RasterCamera;

/// Carving's margin: a Gaussian nearer than this fraction of the distance
/// a photo's ray saw is in its free space.
const CARVE_MARGIN: f32 = 0.8;

/// What a photo's placement rays saw: the distance along each ray of a
/// jittered grid (`spacing` pixels a cell) to what it hit (infinite where
/// it hit nothing, NaN where it is unsure).
pub(super) struct DepthGrid {
    pub nx: usize,
    pub ny: usize,
    /// The grid's top-left corner on the image (pixels; negative: the
    /// grid starts past the photo's edge).
    pub origin: [f32; 2],
    pub spacing: f32,
    pub depth: Vec<f32>,
}

/// Drops the placed Gaussians that another photo sees through (free-space
/// carving): one that lies well in front (nearer than [`CARVE_MARGIN`]
/// times) of what photo `b` saw in each grid cell around its pixel there
/// is a floater in `b`'s free space. `owners`: the photo each was placed
/// from, whose own rays are not asked. One placed `outside` its photo's
/// frame also goes when another photo saw it within its frame (that photo
/// placed its own there): the margins fill only what no photo saw.
pub(super) fn carve(
    placed: Vec<Placed>,
    owners: &[u32],
    outside: &[bool],
    grids: &[DepthGrid],
    cams: &[RasterCamera],
) -> Vec<Placed> {
    use rayon::prelude::*;
    let keep: Vec<bool> = placed
        .par_iter()
        .zip(owners)
        .zip(outside)
        .map(|((p, &owner), &outside)| {
            let mut seen = false;
            for (b, (cam, g)) in cams.iter().zip(grids).enumerate() {
                if b == owner as usize {
                    continue;
                }
                let t = cam.to_camera(p.at);
                if t[2] <= 0.0 {
                    continue;
                }
                let [u, v] = cam.pixel(t);
                let (gx, gy) = ((u - g.origin[0]) / g.spacing, (v - g.origin[1]) / g.spacing);
                if !(gx >= 0.0 && gy >= 0.0 && gx < g.nx as f32 && gy < g.ny as f32) {
                    continue;
                }
                let (gx, gy) = (gx as usize, gy as usize);
                let mut nearest = f32::INFINITY;
                let mut known = true;
                for y in gy.saturating_sub(1)..(gy + 2).min(g.ny) {
                    for x in gx.saturating_sub(1)..(gx + 2).min(g.nx) {
                        let d = g.depth[y * g.nx + x];
                        known &= !d.is_nan();
                        nearest = nearest.min(d);
                    }
                }
                let dist = Vec3::from_array(t).norm();
                if known && dist < CARVE_MARGIN * nearest {
                    return false;
                }
                seen |= outside
                    && in_frame(u, v, cam.width as f32, cam.height as f32)
                    && dist < g.depth[gy * g.nx + gx] / CARVE_MARGIN;
            }
            !seen
        })
        .collect();
    placed.into_iter().zip(keep).filter_map(|(p, k)| k.then_some(p)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::bake::testutil::facing_camera;

    #[test]
    fn carving_drops_what_another_photo_sees_through_and_keeps_what_it_sees() {
        let (_, cam) = facing_camera();
        // Both photos look at the origin from 4 units away along -y; photo
        // 1 saw a wall 4 units away everywhere (3x3 cells of 10 px), photo
        // 0 is unsure of all its depths.
        let cams = vec![cam; 2];
        let grid = |d: f32| DepthGrid { nx: 3, ny: 3, origin: [0.0; 2], spacing: 10.0, depth: vec![d; 9] };
        let grids = [grid(f32::NAN), grid(4.0)];
        let placed: Vec<Placed> = vec![
            Placed::ball([0.0, -2.0, 0.0], 0.1, [1.0; 3]), // halfway: photo 1's free space
            Placed::ball([0.0, 0.0, 0.0], 0.1, [1.0; 3]),  // on the wall
            Placed::ball([0.0, 1.0, 0.0], 0.1, [1.0; 3]),  // behind it
            Placed::ball([0.0, -2.0, 0.0], 0.1, [1.0; 3]), // halfway, but photo 1's own
        ];
        let kept = carve(placed.clone(), &[0, 0, 0, 1], &[false; 4], &grids, &cams);
        assert_eq!(kept, vec![placed[1], placed[2], placed[3]]);
        // One that saw nothing (infinitely far) carves all it sees.
        let empty = [grid(f32::INFINITY), grid(f32::INFINITY)];
        assert_eq!(carve(placed.clone(), &[1, 1, 1, 1], &[false; 4], &empty, &cams), vec![]);
        // Placed past photo 0's frame: the one on the wall, which photo 1
        // saw within its frame, goes; one beside the wall, past photo 1's
        // frame too (its half-width there is 4 tan 0.5 = 2.2), stays.
        let beside: Placed = Placed::ball([3.0, 0.0, 0.0], 0.1, [1.0; 3]);
        let margin = vec![placed[1], beside];
        assert_eq!(carve(margin.clone(), &[0, 0], &[true, true], &grids, &cams), vec![beside]);
        assert_eq!(carve(margin.clone(), &[0, 0], &[false, false], &grids, &cams), margin);
    }
}
