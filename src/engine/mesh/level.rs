//! The surface of a field as a level set of its own density, for a model
//! that exposes one (`Model::density`): sharper than depths fused from
//! views (thin parts and a turntable's crown survive; docs/design/mesh.md).
//! The level is the density the views' own surfaces show: of the points
//! where the views' rays become half opaque, all but [`QUANTILE`] are at a
//! density at least this high, so the level set passes through (or just
//! outside) the surfaces the views drew.

use crate::engine::mesh::fuse::Volume;
use crate::engine::mesh::isosurface::{Grid, Mesh};
use crate::engine::mesh::views::SurfaceView;

/// Densities at world points (per world unit), `None` when there are none.
pub type Density<'a> = &'a dyn Fn(&[[f32; 3]]) -> Option<Vec<f32>>;

/// The share of the views' surface points at a density below the level
/// (chosen by a sweep: docs/design/mesh.md).
pub const QUANTILE: f32 = 0.10;
/// Rounds of [`refine`] on each vertex.
pub const REFINE_STEPS: usize = 3;
/// Surface points sampled for the level, at most.
const SAMPLES: usize = 200_000;

/// The density level of the views' surfaces; `None` when the model has no
/// density or the views met no surface.
pub fn level(density: Density, views: &[SurfaceView]) -> Option<f32> {
    let hits: usize = views.iter().map(|v| v.surface.iter().flatten().count()).sum();
    let every = hits.div_ceil(SAMPLES).max(1);
    let points: Vec<[f32; 3]> =
        views.iter().flat_map(SurfaceView::points).skip(every - 1).step_by(every).map(|p| p.to_array()).collect();
    let mut d = density(&points)?;
    if d.is_empty() {
        return None;
    }
    d.sort_by(f32::total_cmp);
    let at = d[((d.len() - 1) as f32 * QUANTILE) as usize];
    (at > 0.0).then_some(at)
}

/// `(level - density) / level` on `volume`'s points (negative inside, as
/// [`crate::engine::mesh::isosurface`] takes it), with a border of outside
/// so that the surface closes at the box; queried a slab at a time.
pub fn grid(density: Density, volume: &Volume, level: f32) -> Option<Grid> {
    let [nx, ny, nz] = volume.dims;
    let mut grid = Grid::bordered(volume.dims);
    for z in 0..nz {
        let slab: Vec<[f32; 3]> =
            (0..nx * ny).map(|i| volume.world([(i % nx) as f32, (i / nx) as f32, z as f32])).collect();
        for (i, s) in density(&slab)?.into_iter().enumerate() {
            grid.set_inner(i % nx, i / nx, z, (level - s) / level);
        }
    }
    Some(grid)
}

/// Moves each vertex of `mesh` (grid coordinates of `grid`, made by
/// [`crate::engine::mesh::isosurface::extract_on_edges`] with `edges`)
/// along its grid edge to where the density itself crosses `level`: `steps`
/// rounds of regula falsi (Illinois) from the grid's linear guess, the crossing kept
/// bracketed by the edge's two signs, so no vertex leaves its edge. A
/// vertex on an edge to the border (outside by fiat) stays where it is.
pub fn refine(
    density: Density,
    volume: &Volume,
    level: f32,
    grid: &Grid,
    mesh: &mut Mesh,
    edges: &[[usize; 2]],
    steps: usize,
) -> Option<()> {
    let on = volume.padded();
    let inner = |p: [f32; 3]| (0..3).all(|k| p[k] >= 1.0 && p[k] <= (grid.dims[k] - 2) as f32);
    let mut moving: Vec<Crossing> = edges
        .iter()
        .enumerate()
        .filter_map(|(vertex, &[a, b])| {
            let ends = [grid.point(a), grid.point(b)];
            let f = [grid.value(a), grid.value(b)];
            (inner(ends[0]) && inner(ends[1])).then_some(Crossing { vertex, ends, t: [0.0, 1.0], f, kept: None })
        })
        .collect();
    for _ in 0..steps {
        let points: Vec<[f32; 3]> = moving.iter().map(|c| on.world(c.point())).collect();
        let d = density(&points).filter(|d| d.len() == points.len())?;
        for (c, s) in moving.iter_mut().zip(d) {
            c.narrow((level - s) / level);
        }
    }
    for c in moving {
        mesh.positions[c.vertex] = c.point();
    }
    Some(())
}

/// One vertex's crossing along its grid edge: the bracket `t` (0 at the
/// edge's first end, 1 at its second) and the values `f` at its ends, of
/// opposite signs.
struct Crossing {
    vertex: usize,
    ends: [[f32; 3]; 2],
    t: [f32; 2],
    f: [f32; 2],
    /// The bracket end kept by the last step (for the Illinois rule).
    kept: Option<usize>,
}

impl Crossing {
    fn guess(&self) -> f32 {
        let (t, f) = (self.t, self.f);
        t[0] + (t[1] - t[0]) * f[0] / (f[0] - f[1])
    }

    /// The guess in grid coordinates.
    fn point(&self) -> [f32; 3] {
        let (t, [a, b]) = (self.guess(), self.ends);
        [0, 1, 2].map(|k| a[k] + t * (b[k] - a[k]))
    }

    /// The bracket narrowed to the guess, whose value is `v`. An end kept
    /// twice in a row has its value halved (the Illinois rule), so that a
    /// curved field does not leave one end stuck far from the crossing.
    fn narrow(&mut self, v: f32) {
        let t = self.guess();
        if !v.is_finite() {
            // A density that is not a number says nothing: the bracket stays.
            return;
        }
        if v == 0.0 {
            (self.t, self.f) = ([t, t], [-f32::MIN_POSITIVE, f32::MIN_POSITIVE]);
            return;
        }
        let moved = if (v < 0.0) == (self.f[0] < 0.0) { 0 } else { 1 };
        (self.t[moved], self.f[moved]) = (t, v);
        let kept = 1 - moved;
        if self.kept == Some(kept) {
            self.f[kept] *= 0.5;
        }
        self.kept = Some(kept);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::geometry::camera::{Camera, look_at};
    use crate::engine::geometry::math::Vec3;
    use crate::engine::mesh::isosurface::{extract, extract_on_edges};
    use crate::engine::models::splats::crop::CropBox;

    /// A soft ball of radius `r`: dense inside, falling by e over a twentieth of the radius.
    fn ball(r: f32) -> impl Fn(&[[f32; 3]]) -> Option<Vec<f32>> {
        move |p: &[[f32; 3]]| {
            let s =
                |q: &[f32; 3]| 200.0 / (1.0 + ((q.iter().map(|x| x * x).sum::<f32>().sqrt() - r) / (0.05 * r)).exp());
            Some(p.iter().map(s).collect())
        }
    }

    /// Views of the ball, each ray's surface where its opacity reaches one
    /// half (found by marching the density, as a field's render does).
    fn views(density: Density, n: usize) -> Vec<SurfaceView> {
        (0..n)
            .map(|i| {
                let (az, el) = (i as f32 * 1.3, ((i % 3) as f32 - 1.0) * 0.5);
                let eye = Vec3::new(az.cos() * el.cos(), el.sin(), az.sin() * el.cos()) * 2.0;
                let camera =
                    Camera::from_fov(24, 24, 0.9, look_at(eye, Vec3::splat(0.0), Vec3::new(0.0, 1.0, 0.0)).unwrap());
                let surface = (0..24 * 24)
                    .map(|k| {
                        let r = camera.pixel_ray(k % 24, k / 24);
                        let d = r.dir.normalized().unwrap();
                        let dt = 0.002;
                        let ts: Vec<f32> = (0..2000).map(|j| (j as f32 + 0.5) * dt).collect();
                        let pts: Vec<[f32; 3]> = ts.iter().map(|&t| (r.origin + d * t).to_array()).collect();
                        let mut depth = 0.0;
                        for (t, s) in ts.iter().zip(density(&pts).unwrap()) {
                            depth += s * dt;
                            if depth >= std::f32::consts::LN_2 {
                                return Some(*t);
                            }
                        }
                        None
                    })
                    .collect();
                SurfaceView { camera, surface, rgb: vec![[0.5; 3]; 24 * 24] }
            })
            .collect()
    }

    #[test]
    fn a_soft_balls_level_set_is_where_its_views_see_it() {
        let r = 0.5;
        let density = ball(r);
        let seen = views(&density, 6);
        let level = level(&density, &seen).expect("the views see the ball");
        // Within the soft edge's fall from 200 to 0 (rays that graze the
        // ball reach half opacity further out, at lower densities).
        assert!((5.0..195.0).contains(&level), "level {level}");
        let crop =
            CropBox { centre: [0.0; 3], axes: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], half: [0.8; 3] };
        let volume = Volume::over(&crop, 64);
        let g = grid(&density, &volume, level).unwrap();
        let mesh = extract(&g);
        assert!(mesh.is_closed());
        // The level set is a ball (every vertex at one radius, within a
        // grid step) between the ball a view sees head on (its centre
        // pixel's surface, 2 from the centre) and the farthest out any ray
        // of the views becomes half opaque.
        let head_on = 2.0 - seen[0].surface[12 * 24 + 12].unwrap();
        let outermost = seen.iter().flat_map(SurfaceView::points).map(|p| p.norm()).fold(0.0f32, f32::max);
        let on = volume.padded();
        let radii: Vec<f32> = mesh.positions.iter().map(|p| Vec3::from_array(on.world(*p)).norm()).collect();
        let (lo, hi) = radii.iter().fold((f32::MAX, f32::MIN), |(l, h), &d| (l.min(d), h.max(d)));
        assert!(hi - lo < volume.spacing, "radii from {lo} to {hi}");
        assert!(
            lo > head_on - volume.spacing && hi < outermost + volume.spacing,
            "{lo}..{hi}: seen {head_on}..{outermost}"
        );
    }

    #[test]
    fn refined_vertices_sit_where_the_density_crosses_the_level() {
        let r = 0.5;
        let density = ball(r);
        let level = 50.0;
        // Where 200 / (1 + e^((d - r) / 0.05 r)) = 50.
        let want = r + 0.05 * r * 3f32.ln();
        let crop =
            CropBox { centre: [0.0; 3], axes: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], half: [0.8; 3] };
        let volume = Volume::over(&crop, 24);
        let g = grid(&density, &volume, level).unwrap();
        let (linear, edges) = extract_on_edges(&g);
        let mut refined = linear.clone();
        refine(&density, &volume, level, &g, &mut refined, &edges, REFINE_STEPS).unwrap();
        assert_eq!(refined.triangles, linear.triangles);
        let on = volume.padded();
        let worst = |m: &Mesh| {
            m.positions.iter().map(|p| (Vec3::from_array(on.world(*p)).norm() - want).abs()).fold(0.0f32, f32::max)
        };
        let (before, after) = (worst(&linear), worst(&refined));
        // Within a hundredth of a grid step, where the linear guess is off by nearly half of one.
        assert!(
            after < 0.01 * volume.spacing && before > 30.0 * after,
            "off the level by {before} linear, {after} refined (grid step {})",
            volume.spacing
        );
        // Every vertex stays on its grid edge.
        for (p, [a, b]) in refined.positions.iter().zip(&edges) {
            let (pa, pb) = (g.point(*a), g.point(*b));
            let along: Vec<f32> =
                (0..3).filter(|&k| pa[k] != pb[k]).map(|k| (p[k] - pa[k]) / (pb[k] - pa[k])).collect();
            let on_edge = along.windows(2).all(|w| (w[0] - w[1]).abs() < 1e-4)
                && along.iter().all(|t| (-1e-6..=1.0 + 1e-6).contains(t))
                && (0..3).all(|k| pa[k] != pb[k] || p[k] == pa[k]);
            assert!(on_edge, "{p:?} off the edge {pa:?} - {pb:?}");
        }
    }

    #[test]
    fn a_density_that_is_not_a_number_leaves_its_vertices_on_their_edges() {
        let ball = ball(0.5);
        let density = |p: &[[f32; 3]]| {
            // NaN on one side, infinite on another.
            let d = ball(p)?;
            Some(
                p.iter()
                    .zip(d)
                    .map(|(q, s)| {
                        if q[0] > 0.2 {
                            f32::NAN
                        } else if q[1] > 0.2 {
                            f32::INFINITY
                        } else {
                            s
                        }
                    })
                    .collect(),
            )
        };
        let crop =
            CropBox { centre: [0.0; 3], axes: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], half: [0.8; 3] };
        let volume = Volume::over(&crop, 24);
        let g = grid(&ball, &volume, 50.0).unwrap();
        let (mut mesh, edges) = extract_on_edges(&g);
        refine(&density, &volume, 50.0, &g, &mut mesh, &edges, REFINE_STEPS).unwrap();
        assert!(mesh.positions.iter().flatten().all(|v| v.is_finite()));
        // A density of the wrong length is no density.
        let short = |p: &[[f32; 3]]| Some(vec![1.0; p.len() / 2]);
        assert_eq!(refine(&short, &volume, 50.0, &g, &mut mesh, &edges, 1), None);
    }

    #[test]
    fn no_density_or_no_surface_gives_no_level() {
        let none = |_: &[[f32; 3]]| None;
        let density = ball(0.5);
        assert_eq!(level(&none, &views(&density, 2)), None);
        let empty = |p: &[[f32; 3]]| Some(vec![0.0; p.len()]);
        assert_eq!(level(&empty, &views(&empty, 2)), None);
    }
}
