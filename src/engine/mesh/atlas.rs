//! A texture atlas of triangle pairs: triangles two by two in square cells
//! of `s x s` texels, each a right triangle whose legs lie on the cell's
//! outermost texel centres, one in each corner. Bilinear sampling inside a
//! triangle reads only texels of that triangle (each texel of a cell
//! belongs to the triangle nearest to it), so no colour bleeds across
//! triangles or cells, and every UV is inside [0, 1] by construction.
//! MobileNeRF textures its quads the same way. A triangle gets the same
//! texels whatever its area: at a budget where triangles are a pixel or two
//! on screen, that is detail enough (docs/design/mesh.md).

/// Where each triangle's corners are in the texture.
#[derive(Clone, Debug, PartialEq)]
pub struct Atlas {
    /// Texture side, texels.
    pub size: u32,
    /// Cell side, texels.
    pub cell: u32,
    /// Cells in a row (and rows).
    pub per_row: u32,
    /// Per triangle, its corners' texture coordinates in [0, 1] (u right,
    /// v down: glTF's convention).
    pub uvs: Vec<[[f32; 2]; 3]>,
}

/// Smallest cell: legs of `cell - 3` texels leave a triangle 1 texel leg.
pub const MIN_CELL: u32 = 4;

/// Why an atlas cannot be made.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum AtlasError {
    #[error("a {size}x{size} texture cannot hold {triangles} triangles (at most {most})")]
    TooManyTriangles { size: u32, triangles: usize, most: usize },
}

/// The most triangles a `size x size` texture holds.
pub fn capacity(size: u32) -> usize {
    let per_row = (size / MIN_CELL) as usize;
    2 * per_row * per_row
}

/// Lays out `triangles` triangles in a `size x size` texture, the largest
/// cells that fit.
pub fn layout(triangles: usize, size: u32) -> Result<Atlas, AtlasError> {
    let cells = triangles.div_ceil(2);
    let per_row = ((cells as f64).sqrt().ceil() as u32).max(1);
    let cell = size / per_row;
    if cell < MIN_CELL {
        return Err(AtlasError::TooManyTriangles { size, triangles, most: capacity(size) });
    }
    let leg = (cell - 3) as f32;
    let s = size as f32;
    let uvs = (0..triangles)
        .map(|t| {
            let c = (t / 2) as u32;
            let (x0, y0) = ((c % per_row * cell) as f32, (c / per_row * cell) as f32);
            let corners = if t % 2 == 0 {
                let o = [x0 + 0.5, y0 + 0.5];
                [o, [o[0] + leg, o[1]], [o[0], o[1] + leg]]
            } else {
                let o = [x0 + cell as f32 - 0.5, y0 + cell as f32 - 0.5];
                [o, [o[0] - leg, o[1]], [o[0], o[1] - leg]]
            };
            corners.map(|[x, y]| [x / s, y / s])
        })
        .collect();
    Ok(Atlas { size, cell, per_row, uvs })
}

impl Atlas {
    /// The texels of each triangle: for every texel of the texture, the
    /// triangle it belongs to (`None` outside every cell) and its
    /// barycentric coordinates there, clamped to the triangle (texels
    /// between the two triangles of a cell take their nearest edge's
    /// colour: the padding that keeps sampling from bleeding).
    pub fn texel(&self, x: u32, y: u32) -> Option<(usize, [f32; 3])> {
        let per_row = self.per_row;
        let (cx, cy) = (x / self.cell, y / self.cell);
        if cx >= per_row || cy >= per_row {
            return None;
        }
        let (lx, ly) = (x % self.cell, y % self.cell);
        let second = lx + ly + 1 > self.cell - 1;
        let t = ((cy * per_row + cx) * 2 + second as u32) as usize;
        if t >= self.uvs.len() {
            return None;
        }
        let p = [(x as f32 + 0.5) / self.size as f32, (y as f32 + 0.5) / self.size as f32];
        Some((t, closest_barycentric(self.uvs[t], p)))
    }
}

/// Barycentric coordinates of the point of triangle `tri` nearest to `p`.
pub fn closest_barycentric(tri: [[f32; 2]; 3], p: [f32; 2]) -> [f32; 3] {
    let [a, b, c] = tri;
    let bary = |p: [f32; 2]| {
        let (v0, v1, v2) = ([b[0] - a[0], b[1] - a[1]], [c[0] - a[0], c[1] - a[1]], [p[0] - a[0], p[1] - a[1]]);
        let den = v0[0] * v1[1] - v1[0] * v0[1];
        let v = (v2[0] * v1[1] - v1[0] * v2[1]) / den;
        let w = (v0[0] * v2[1] - v2[0] * v0[1]) / den;
        [1.0 - v - w, v, w]
    };
    let l = bary(p);
    if l.iter().all(|&x| x >= 0.0) {
        return l;
    }
    // Outside: the nearest point on the nearest edge.
    let mut best = (f32::INFINITY, [0.0; 3]);
    for (i, j) in [(0, 1), (1, 2), (2, 0)] {
        let (e0, e1) = (tri[i], tri[j]);
        let d = [e1[0] - e0[0], e1[1] - e0[1]];
        let len2 = d[0] * d[0] + d[1] * d[1];
        let s = (((p[0] - e0[0]) * d[0] + (p[1] - e0[1]) * d[1]) / len2).clamp(0.0, 1.0);
        let q = [e0[0] + s * d[0], e0[1] + s * d[1]];
        let dist = (q[0] - p[0]).powi(2) + (q[1] - p[1]).powi(2);
        if dist < best.0 {
            let mut l = [0.0; 3];
            l[i] = 1.0 - s;
            l[j] = s;
            best = (dist, l);
        }
    }
    best.1
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Twice the signed area of a UV triangle.
    fn area2(t: [[f32; 2]; 3]) -> f32 {
        (t[1][0] - t[0][0]) * (t[2][1] - t[0][1]) - (t[2][0] - t[0][0]) * (t[1][1] - t[0][1])
    }

    #[test]
    fn uvs_are_inside_the_texture_and_no_two_triangles_overlap_or_bleed() {
        let mut rng = crate::engine::rng::Rng::new(3);
        for (n, size) in [(1usize, 16u32), (7, 64), (1000, 256), (5000, 512)] {
            let atlas = layout(n, size).unwrap();
            assert_eq!(atlas.uvs.len(), n);
            let mut owner = vec![None; (size * size) as usize];
            for (t, tri) in atlas.uvs.iter().enumerate() {
                assert!(tri.iter().flatten().all(|&v| (0.0..=1.0).contains(&v)));
                assert!(area2(*tri).abs() > 0.0);
                // The texel centres inside the triangle: none inside another.
                let px = tri.map(|c| c.map(|v| v * size as f32));
                let lo = [0, 1].map(|k| px.iter().map(|c| c[k]).fold(f32::MAX, f32::min).floor() as u32);
                let hi = [0, 1].map(|k| px.iter().map(|c| c[k]).fold(f32::MIN, f32::max).ceil() as u32);
                for y in lo[1]..hi[1].min(size) {
                    for x in lo[0]..hi[0].min(size) {
                        let p = [(x as f32 + 0.5) / size as f32, (y as f32 + 0.5) / size as f32];
                        let l = closest_barycentric(*tri, p);
                        let q = [0, 1].map(|k| l[0] * tri[0][k] + l[1] * tri[1][k] + l[2] * tri[2][k]);
                        if (q[0] - p[0]).abs() < 1e-6 && (q[1] - p[1]).abs() < 1e-6 {
                            let o = &mut owner[(y * size + x) as usize];
                            assert_eq!(*o, None, "texel ({x}, {y}) lies in triangles {o:?} and {t}");
                            *o = Some(t);
                        }
                    }
                }
                // Bilinear samples anywhere in the triangle read only its texels.
                for _ in 0..20 {
                    let (a, b) = (rng.f32(), rng.f32());
                    let (a, b) = if a + b > 1.0 { (1.0 - a, 1.0 - b) } else { (a, b) };
                    let p = [0, 1].map(|k| (1.0 - a - b) * px[0][k] + a * px[1][k] + b * px[2][k] - 0.5);
                    let (x0, y0) = (p[0].floor(), p[1].floor());
                    let (fx, fy) = (p[0] - x0, p[1] - y0);
                    for (dx, dy, w) in [
                        (0, 0, (1.0 - fx) * (1.0 - fy)),
                        (1, 0, fx * (1.0 - fy)),
                        (0, 1, (1.0 - fx) * fy),
                        (1, 1, fx * fy),
                    ] {
                        if w > 1e-4 {
                            let (x, y) = (x0 as u32 + dx, y0 as u32 + dy);
                            assert_eq!(
                                atlas.texel(x, y).map(|(o, _)| o),
                                Some(t),
                                "triangle {t} reads texel ({x}, {y})"
                            );
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn too_many_triangles_for_the_texture_is_an_error() {
        assert_eq!(capacity(64), 512);
        assert!(layout(512, 64).is_ok());
        assert_eq!(layout(513, 64), Err(AtlasError::TooManyTriangles { size: 64, triangles: 513, most: 512 }));
    }

    #[test]
    fn closest_barycentric_is_exact_inside_and_on_the_edge_outside() {
        let tri = [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]];
        let l = closest_barycentric(tri, [0.25, 0.25]);
        assert!((l[0] - 0.5).abs() < 1e-6 && (l[1] - 0.25).abs() < 1e-6);
        let l = closest_barycentric(tri, [1.0, 1.0]);
        assert!((l[1] - 0.5).abs() < 1e-6 && (l[2] - 0.5).abs() < 1e-6 && l[0].abs() < 1e-6);
        let l = closest_barycentric(tri, [-1.0, -2.0]);
        assert_eq!(l, [1.0, 0.0, 0.0]);
    }
}
