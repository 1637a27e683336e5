//! The zero level set of a sampled field as a triangle mesh, by marching
//! tetrahedra: each grid cube is cut into six tetrahedra around its main
//! diagonal, the same cut in every cube, so neighbouring cubes split their
//! shared face along the same diagonal and their triangles meet edge to
//! edge. No case table; the surface is closed wherever the field's border
//! is positive, every triangle faces the positive side (outside), and a
//! vertex is shared by every triangle that crosses its grid edge.

use std::collections::HashMap;

/// Values on a grid of points, x fastest: negative inside, positive
/// outside.
#[derive(Clone, Debug)]
pub struct Grid {
    pub dims: [usize; 3],
    pub values: Vec<f32>,
}

/// A triangle mesh: positions and counter-clockwise triangles seen from
/// outside.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    pub positions: Vec<[f32; 3]>,
    pub triangles: Vec<[u32; 3]>,
}

/// The six tetrahedra of a cube (corner `c` at `(c & 1, c >> 1 & 1, c >> 2)`),
/// each the diagonal 0-7 and one path along three edges from 0 to 7.
const TETS: [[usize; 4]; 6] = [[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 5, 7], [0, 4, 6, 7]];

impl Grid {
    /// A grid of `inner` points inside a border of outside (so that the
    /// surface closes where it meets the grid's box), every point outside
    /// until set with [`Grid::set_inner`].
    pub fn bordered(inner: [usize; 3]) -> Self {
        let dims = inner.map(|d| d + 2);
        Self { dims, values: vec![1.0; dims.iter().product()] }
    }

    /// Sets inner point `(x, y, z)` of a [`Grid::bordered`] grid.
    pub fn set_inner(&mut self, x: usize, y: usize, z: usize, v: f32) {
        let i = self.index(x + 1, y + 1, z + 1);
        self.values[i] = v;
    }

    fn index(&self, x: usize, y: usize, z: usize) -> usize {
        (z * self.dims[1] + y) * self.dims[0] + x
    }

    pub(crate) fn point(&self, i: usize) -> [f32; 3] {
        let [nx, ny, _] = self.dims;
        [(i % nx) as f32, (i / nx % ny) as f32, (i / (nx * ny)) as f32]
    }

    /// A value as the surface sees it: exact zeros count as outside, a
    /// hair's breadth from the grid point, so that no edge is cut at its end.
    pub(crate) fn value(&self, i: usize) -> f32 {
        let v = self.values[i];
        if v == 0.0 { f32::MIN_POSITIVE } else { v }
    }
}

/// Vertices on grid edges, one per edge, computed from the edge's lower
/// end so that every tetrahedron sharing it gets the same bits.
struct Vertices<'a> {
    grid: &'a Grid,
    ids: HashMap<u64, u32>,
    positions: Vec<[f32; 3]>,
    /// Each vertex's grid edge (its ends' indices, lower first).
    edges: Vec<[usize; 2]>,
}

impl Vertices<'_> {
    fn on_edge(&mut self, a: usize, b: usize) -> u32 {
        let (a, b) = if a < b { (a, b) } else { (b, a) };
        let key = a as u64 * self.grid.values.len() as u64 + b as u64;
        let next = self.positions.len() as u32;
        let id = *self.ids.entry(key).or_insert(next);
        if id == next {
            let (va, vb) = (self.grid.value(a), self.grid.value(b));
            let t = va / (va - vb);
            let (pa, pb) = (self.grid.point(a), self.grid.point(b));
            self.positions.push([0, 1, 2].map(|k| pa[k] + t * (pb[k] - pa[k])));
            self.edges.push([a, b]);
        }
        id
    }
}

/// The surface where the grid's values cross zero, in grid coordinates
/// (grid point `(x, y, z)` at `[x, y, z]`).
pub fn extract(grid: &Grid) -> Mesh {
    extract_on_edges(grid).0
}

/// [`extract`], and the grid edge each vertex lies on (its ends' indices
/// into the grid's values, lower first), where it sits at the linear
/// guess of the crossing.
pub fn extract_on_edges(grid: &Grid) -> (Mesh, Vec<[usize; 2]>) {
    let [nx, ny, nz] = grid.dims;
    assert_eq!(grid.values.len(), nx * ny * nz, "grid values do not match its dims");
    let mut verts = Vertices { grid, ids: HashMap::new(), positions: Vec::new(), edges: Vec::new() };
    let mut triangles = Vec::new();
    for z in 0..nz.saturating_sub(1) {
        for y in 0..ny.saturating_sub(1) {
            for x in 0..nx.saturating_sub(1) {
                let corners: [usize; 8] =
                    std::array::from_fn(|c| grid.index(x + (c & 1), y + (c >> 1 & 1), z + (c >> 2)));
                let inside = corners.iter().filter(|&&i| grid.value(i) < 0.0).count();
                if inside == 0 || inside == 8 {
                    continue;
                }
                for tet in TETS {
                    march_tet(&mut verts, &mut triangles, tet.map(|c| corners[c]));
                }
            }
        }
    }
    (Mesh { positions: verts.positions, triangles }, verts.edges)
}

/// The one or two triangles where a tetrahedron's values cross zero.
fn march_tet(verts: &mut Vertices, out: &mut Vec<[u32; 3]>, tet: [usize; 4]) {
    let (inside, outside): (Vec<usize>, Vec<usize>) = tet.iter().partition(|&&i| verts.grid.value(i) < 0.0);
    let tris: Vec<[(usize, usize); 3]> = match (inside.as_slice(), outside.as_slice()) {
        ([a], [b, c, d]) | ([b, c, d], [a]) => vec![[(*a, *b), (*a, *c), (*a, *d)]],
        ([a, b], [c, d]) => {
            // The quad through the four cut edges, in order around it.
            vec![[(*a, *c), (*a, *d), (*b, *d)], [(*a, *c), (*b, *d), (*b, *c)]]
        }
        _ => return,
    };
    // Outward: from the inside corners' centroid towards the outside ones'.
    let centroid = |ids: &[usize]| {
        let mut s = [0.0f32; 3];
        for &i in ids {
            let p = verts.grid.point(i);
            (0..3).for_each(|k| s[k] += p[k] / ids.len() as f32);
        }
        s
    };
    let (ci, co) = (centroid(&inside), centroid(&outside));
    let out_dir = [0, 1, 2].map(|k| co[k] - ci[k]);
    for edges in tris {
        let mut t = edges.map(|(a, b)| verts.on_edge(a, b));
        if t[0] == t[1] || t[1] == t[2] || t[0] == t[2] {
            continue;
        }
        let [p0, p1, p2] = t.map(|v| verts.positions[v as usize]);
        let n = cross(sub(p1, p0), sub(p2, p0));
        if dot(n, out_dir) < 0.0 {
            t.swap(1, 2);
        }
        out.push(t);
    }
}

pub(crate) fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

pub(crate) fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

pub(crate) fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

impl Mesh {
    /// Total area, in f64.
    pub fn area(&self) -> f64 {
        self.triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|v| self.positions[v as usize].map(f64::from));
                let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
                let v = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
                let n = [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]];
                0.5 * (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt()
            })
            .sum()
    }

    /// Enclosed volume (divergence theorem), in f64: positive for a closed
    /// mesh facing outwards.
    pub fn volume(&self) -> f64 {
        self.triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|v| self.positions[v as usize].map(f64::from));
                (a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0])
                    + a[2] * (b[0] * c[1] - b[1] * c[0]))
                    / 6.0
            })
            .sum()
    }

    /// Whether every edge is used once in each direction: closed, with
    /// consistent orientation.
    pub fn is_closed(&self) -> bool {
        let mut directed: HashMap<(u32, u32), u32> = HashMap::new();
        for t in &self.triangles {
            for k in 0..3 {
                *directed.entry((t[k], t[(k + 1) % 3])).or_default() += 1;
            }
        }
        directed.iter().all(|(&(a, b), &n)| n == 1 && directed.get(&(b, a)) == Some(&1))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A signed distance sampled on an `n^3` grid over `[-1, 1]^3`.
    fn sampled(n: usize, f: impl Fn([f32; 3]) -> f32) -> (Grid, f32) {
        let h = 2.0 / (n - 1) as f32;
        let mut values = Vec::with_capacity(n * n * n);
        for z in 0..n {
            for y in 0..n {
                for x in 0..n {
                    values.push(f([x, y, z].map(|i| -1.0 + i as f32 * h)));
                }
            }
        }
        (Grid { dims: [n; 3], values }, h)
    }

    #[test]
    fn a_sphere_has_its_area_and_volume_and_is_closed() {
        let r = 0.7f64;
        let (grid, h) = sampled(72, |p| (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt() - r as f32);
        let mesh = extract(&grid);
        let (h, h3) = (h as f64, (h as f64).powi(3));
        let area = mesh.area() * h * h;
        let volume = mesh.volume() * h3;
        let (want_a, want_v) = (4.0 * std::f64::consts::PI * r * r, 4.0 / 3.0 * std::f64::consts::PI * r.powi(3));
        assert!((area / want_a - 1.0).abs() < 0.01, "area {area} against {want_a}");
        assert!((volume / want_v - 1.0).abs() < 0.01, "volume {volume} against {want_v}");
        assert!(mesh.is_closed());
    }

    #[test]
    fn a_box_and_a_torus_are_closed_and_face_outwards() {
        let cube = |p: [f32; 3]| p.iter().map(|v| v.abs() - 0.55).fold(f32::MIN, f32::max);
        let torus = |p: [f32; 3]| {
            let q = (p[0] * p[0] + p[1] * p[1]).sqrt() - 0.6;
            (q * q + p[2] * p[2]).sqrt() - 0.2
        };
        for (name, f, want) in [
            ("box", &cube as &dyn Fn([f32; 3]) -> f32, 1.1f64.powi(3)),
            ("torus", &torus, 2.0 * std::f64::consts::PI.powi(2) * 0.6 * 0.04),
        ] {
            let (grid, h) = sampled(48, f);
            let mesh = extract(&grid);
            assert!(mesh.is_closed(), "{name} is not closed");
            let v = mesh.volume() * (h as f64).powi(3);
            assert!((v / want - 1.0).abs() < 0.03, "{name}: volume {v} against {want}");
        }
    }

    #[test]
    fn random_fields_give_closed_meshes_and_empty_fields_none() {
        let mut rng = crate::engine::rng::Rng::new(5);
        for _ in 0..20 {
            let n = 9;
            // Outside on the border, so every surface closes.
            let values = (0..n * n * n)
                .map(|i| {
                    let (x, y, z) = (i % n, i / n % n, i / (n * n));
                    let border = [x, y, z].iter().any(|&c| c == 0 || c == n - 1);
                    if border { 1.0 } else { rng.f32() - 0.5 }
                })
                .collect();
            let mesh = extract(&Grid { dims: [n; 3], values });
            assert!(mesh.is_closed());
            assert!(mesh.volume() > 0.0);
        }
        assert!(extract(&Grid { dims: [4; 3], values: vec![1.0; 64] }).triangles.is_empty());
        assert!(extract(&Grid { dims: [1, 1, 1], values: vec![-1.0] }).triangles.is_empty());
    }
}
