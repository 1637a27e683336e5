//! Unit tests of `hashgrid.rs` (kept apart so the module reads in one sitting).

use super::*;
use crate::engine::nn::linear::ParamLayout;
use crate::engine::rng::Rng;

fn small() -> (HashGrid, usize) {
    let mut layout = ParamLayout::default();
    layout.add("pad", 5);
    let g = HashGrid::new(
        &mut layout,
        HashGridConfig { levels: 4, log2_table: 8, base_resolution: 2, finest_resolution: 20 },
    );
    (g, layout.len)
}

#[test]
fn levels_grow_and_switch_to_hashing() {
    let (g, _) = small();
    let res: Vec<u32> = g.levels.iter().map(|l| l.res).collect();
    assert_eq!(res.first(), Some(&2));
    assert!(res.windows(2).all(|w| w[0] < w[1]), "{res:?}");
    assert!(g.levels[0].dense && !g.levels[3].dense);
}

#[test]
fn interpolates_corner_values_exactly() {
    let (g, n) = small();
    let mut params = vec![0.0f32; n];
    Rng::new(1).f32();
    for (i, p) in params.iter_mut().enumerate() {
        *p = (i % 17) as f32;
    }
    // At a grid vertex the encoding equals that vertex's features.
    let level = g.levels[0];
    let p = [0.5f32, 0.0, 1.0]; // vertex (1, 0, 2) at resolution 2
    let mut out = vec![0.0; g.width()];
    g.forward(&params, &p, &mut out);
    let k = g.params.start + level.offset + FEATURES * HashGrid::index(&level, 1, 0, 2);
    assert!((out[0] - params[k]).abs() < 1e-5 && (out[1] - params[k + 1]).abs() < 1e-5);
}

/// The per-axis index terms give the vertex indices of the plain
/// formula, on dense and hashed levels alike.
#[test]
fn corner_indices_match_the_vertex_formula() {
    let (g, _) = small();
    let mut rng = Rng::new(4);
    for level in &g.levels {
        for _ in 0..50 {
            let p = [rng.f32(), rng.f32(), rng.f32()];
            let (idx, w) = g.corners(level, p);
            let base: Vec<u32> = p.iter().map(|&v| ((v * level.res as f32) as u32).min(level.res - 1)).collect();
            for c in 0..8 {
                let (dx, dy, dz) = ((c >> 2) & 1, (c >> 1) & 1, c & 1);
                let i = HashGrid::index(level, base[0] + dx, base[1] + dy, base[2] + dz);
                assert_eq!(idx[c as usize], g.params.start + level.offset + FEATURES * i);
            }
            assert!((w.iter().sum::<f32>() - 1.0).abs() < 1e-5);
        }
    }
}

#[test]
fn backward_matches_finite_differences_in_f64() {
    let (g, n) = small();
    let mut rng = Rng::new(2);
    let params: Vec<f32> = (0..n).map(|_| rng.normal()).collect();
    let pts: Vec<f32> = (0..4 * 3).map(|_| rng.f32()).collect();
    let dout: Vec<f32> = (0..4 * g.width()).map(|_| rng.normal()).collect();
    let mut grads = vec![0.0f32; n];
    g.backward(&pts, &dout, &mut grads);
    // The encoding is linear in the parameters: an f64 objective
    // sum(out * dout) from the corner weights, differentiated numerically.
    let objective = |p: &[f64]| -> f64 {
        let mut total = 0.0;
        for (q, gd) in pts.chunks(3).zip(dout.chunks(g.width())) {
            for (l, level) in g.levels.iter().enumerate() {
                let (idx, w) = g.corners(level, [q[0], q[1], q[2]]);
                for c in 0..8 {
                    total += w[c] as f64 * (p[idx[c]] * gd[2 * l] as f64 + p[idx[c] + 1] * gd[2 * l + 1] as f64);
                }
            }
        }
        total
    };
    let p64: Vec<f64> = params.iter().map(|&v| v as f64).collect();
    let mut nonzero = 0;
    for i in 0..n {
        let mut a = p64.clone();
        a[i] += 1e-6;
        let mut b = p64.clone();
        b[i] -= 1e-6;
        let num = (objective(&a) - objective(&b)) / 2e-6;
        assert!((num - grads[i] as f64).abs() < 1e-4 * (1.0 + num.abs()), "param {i}: {num} vs {}", grads[i]);
        nonzero += (num != 0.0) as usize;
    }
    assert!(nonzero > 20);
    // And the forward pass is that same linear function.
    let mut out = vec![0.0f32; 4 * g.width()];
    g.forward(&params, &pts, &mut out);
    let f: f64 = out.iter().zip(&dout).map(|(a, b)| *a as f64 * *b as f64).sum();
    assert!((f - objective(&p64)).abs() < 1e-4 * (1.0 + f.abs()));
}

/// Forward and backward over many points (whole groups of 8 take the
/// AVX2 path where the CPU has it, the tail the scalar one) agree with
/// the per-point corner formula evaluated in f64.
#[test]
fn batched_passes_match_the_per_point_formula() {
    let (g, n) = small();
    let mut rng = Rng::new(8);
    let params: Vec<f32> = (0..n).map(|_| rng.normal()).collect();
    let count = 37;
    let mut pts: Vec<f32> = (0..count * 3).map(|_| rng.f32() * 1.2 - 0.1).collect();
    pts[5] = f32::NAN;
    pts[7] = 1.0;
    let dout: Vec<f32> = (0..count * g.width()).map(|_| rng.normal()).collect();
    let mut out = vec![0.0f32; count * g.width()];
    g.forward(&params, &pts, &mut out);
    let mut grads = vec![0.0f32; n];
    g.backward(&pts, &dout, &mut grads);
    let mut want_grads = vec![0.0f64; n];
    for (i, q) in pts.chunks(3).enumerate() {
        for (l, level) in g.levels.iter().enumerate() {
            let (idx, w) = g.corners(level, [q[0], q[1], q[2]]);
            let mut f = [0.0f64; 2];
            for c in 0..8 {
                for k in 0..2 {
                    f[k] += w[c] as f64 * params[idx[c] + k] as f64;
                    want_grads[idx[c] + k] += w[c] as f64 * dout[i * g.width() + 2 * l + k] as f64;
                }
            }
            for k in 0..2 {
                let got = out[i * g.width() + 2 * l + k] as f64;
                assert!((got - f[k]).abs() < 1e-5 * (1.0 + f[k].abs()), "point {i} level {l}: {got} vs {}", f[k]);
            }
        }
    }
    for (i, (&a, &b)) in grads.iter().zip(&want_grads).enumerate() {
        assert!((a as f64 - b).abs() < 1e-4 * (1.0 + b.abs()), "param {i}: {a} vs {b}");
    }
    assert!(want_grads.iter().filter(|v| **v != 0.0).count() > 50);
}

#[test]
fn out_of_range_points_are_clamped_not_nan() {
    let (g, n) = small();
    let params = vec![1.0f32; n];
    let pts = [-5.0f32, 1e30, f32::NAN, 1.0, 1.0, 1.0];
    let mut out = vec![0.0; 2 * g.width()];
    g.forward(&params, &pts, &mut out);
    assert!(out.iter().all(|v| (v - 1.0).abs() < 1e-5), "{out:?}");
}
