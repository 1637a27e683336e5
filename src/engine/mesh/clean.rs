//! Tidying a surface: small disconnected pieces (floaters the views agree
//! on) dropped, and the rest simplified to a triangle budget with
//! meshoptimizer (the `meshopt` crate: the quadric simplifier glTF tools
//! use, kept up to date, compiled from its C++ with no other dependency).

use crate::engine::mesh::isosurface::Mesh;

/// `mesh` without the connected pieces whose area is under `min_share`
/// of the whole, and without vertices no triangle uses.
pub fn drop_small_pieces(mesh: &Mesh, min_share: f64) -> Mesh {
    let n = mesh.positions.len();
    let mut parent: Vec<u32> = (0..n as u32).collect();
    fn root(parent: &mut [u32], mut v: u32) -> u32 {
        while parent[v as usize] != v {
            parent[v as usize] = parent[parent[v as usize] as usize];
            v = parent[v as usize];
        }
        v
    }
    for t in &mesh.triangles {
        let r0 = root(&mut parent, t[0]);
        for &v in &t[1..] {
            let r = root(&mut parent, v);
            parent[r as usize] = r0;
        }
    }
    let areas: Vec<f64> = mesh.triangles.iter().map(|t| triangle_area(mesh, t)).collect();
    let mut piece_area = vec![0.0f64; n];
    for (t, a) in mesh.triangles.iter().zip(&areas) {
        piece_area[root(&mut parent, t[0]) as usize] += a;
    }
    let total: f64 = areas.iter().sum();
    let kept: Vec<[u32; 3]> = mesh
        .triangles
        .iter()
        .filter(|t| piece_area[root(&mut parent, t[0]) as usize] >= min_share * total)
        .copied()
        .collect();
    compact(&mesh.positions, &kept)
}

fn triangle_area(mesh: &Mesh, t: &[u32; 3]) -> f64 {
    let one = Mesh { positions: t.map(|v| mesh.positions[v as usize]).to_vec(), triangles: vec![[0, 1, 2]] };
    one.area()
}

/// The vertices `triangles` use, renumbered in order of first use.
pub fn compact(positions: &[[f32; 3]], triangles: &[[u32; 3]]) -> Mesh {
    let mut map = vec![u32::MAX; positions.len()];
    let mut out = Mesh::default();
    for t in triangles {
        let nt = t.map(|v| {
            if map[v as usize] == u32::MAX {
                map[v as usize] = out.positions.len() as u32;
                out.positions.push(positions[v as usize]);
            }
            map[v as usize]
        });
        out.triangles.push(nt);
    }
    out
}

/// `mesh` with at most `budget` triangles: unchanged when it has no more,
/// else simplified (shape kept as well as the budget allows; where the
/// simplifier cannot keep the mesh's topology within the budget, by
/// clustering instead).
pub fn simplify(mesh: &Mesh, budget: usize) -> Mesh {
    if mesh.triangles.len() <= budget {
        return mesh.clone();
    }
    let bytes: Vec<u8> = mesh.positions.iter().flatten().flat_map(|v| v.to_le_bytes()).collect();
    let indices: Vec<u32> = mesh.triangles.iter().flatten().copied().collect();
    let adapter = meshopt::VertexDataAdapter::new(&bytes, 12, 0).expect("12 bytes a vertex");
    let mut out = meshopt::simplify(&indices, &adapter, 3 * budget, 1.0, meshopt::SimplifyOptions::None, None);
    if out.len() > 3 * budget {
        out = meshopt::simplify_sloppy(&indices, &adapter, 3 * budget, 1.0, None);
    }
    let triangles: Vec<[u32; 3]> = out.chunks_exact(3).take(budget).map(|c| [c[0], c[1], c[2]]).collect();
    compact(&mesh.positions, &triangles)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::mesh::isosurface::{Grid, extract};

    fn two_spheres(n: usize) -> Mesh {
        let h = 2.0 / (n - 1) as f32;
        let mut values = Vec::new();
        for z in 0..n {
            for y in 0..n {
                for x in 0..n {
                    let p = [x, y, z].map(|i| -1.0 + i as f32 * h);
                    let d = |c: [f32; 3], r: f32| {
                        ((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2) + (p[2] - c[2]).powi(2)).sqrt() - r
                    };
                    values.push(d([-0.3, 0.0, 0.0], 0.5).min(d([0.7, 0.7, 0.7], 0.1)));
                }
            }
        }
        extract(&Grid { dims: [n; 3], values })
    }

    #[test]
    fn small_pieces_go_and_the_large_one_stays_whole() {
        let mesh = two_spheres(48);
        let kept = drop_small_pieces(&mesh, 0.1);
        assert!(kept.triangles.len() < mesh.triangles.len());
        assert!(kept.is_closed());
        // The small sphere's area is 4% of the whole: it goes, the large one stays.
        let ratio = kept.area() / mesh.area();
        assert!((ratio - 25.0 / 26.0).abs() < 0.01, "kept {ratio} of the area");
        assert_eq!(drop_small_pieces(&mesh, 0.01).triangles.len(), mesh.triangles.len());
    }

    #[test]
    fn simplification_meets_the_budget_and_keeps_the_shape() {
        let mesh = drop_small_pieces(&two_spheres(48), 0.1);
        let small = simplify(&mesh, 2000);
        assert!(small.triangles.len() <= 2000 && small.triangles.len() > 1500, "{} triangles", small.triangles.len());
        assert!(small.is_closed());
        assert!(
            (small.volume() / mesh.volume() - 1.0).abs() < 0.02,
            "volume {} against {}",
            small.volume(),
            mesh.volume()
        );
        assert_eq!(simplify(&mesh, mesh.triangles.len()), mesh);
    }
}
