//! Unit tests of the hash grid (kept apart so the module reads in one sitting).

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
/// the per-point corner formula evaluated in f64. Two whole groups have no
/// output gradient (the backward pass skips them; the second is the last
/// whole group, ending the pipeline of groups).
#[test]
fn batched_passes_match_the_per_point_formula() {
    let (g, n) = small();
    let mut rng = Rng::new(8);
    let params: Vec<f32> = (0..n).map(|_| rng.normal()).collect();
    let count = 45;
    let mut pts: Vec<f32> = (0..count * 3).map(|_| rng.f32() * 1.2 - 0.1).collect();
    pts[5] = f32::NAN;
    pts[7] = 1.0;
    let mut dout: Vec<f32> = (0..count * g.width()).map(|_| rng.normal()).collect();
    for row in (16..24).chain(32..40) {
        dout[row * g.width()..(row + 1) * g.width()].fill(0.0);
    }
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

/// The encoding of one point in f64, from the vertex formula
/// ([`HashGrid::index`]), for finite differences.
fn forward64(g: &HashGrid, params: &[f32], u: [f64; 3]) -> Vec<f64> {
    let mut out = Vec::with_capacity(g.width());
    for level in &g.levels {
        let res = level.res as f64;
        let cell: [(u32, f64); 3] = std::array::from_fn(|a| {
            let v = u[a].clamp(0.0, 1.0) * res;
            let f = v.floor().min(res - 1.0);
            (f as u32, v - f)
        });
        let mut f = [0.0f64; 2];
        for c in 0..8u32 {
            let bits = [(c >> 2) & 1, (c >> 1) & 1, c & 1];
            let w: f64 = (0..3).map(|a| if bits[a] == 1 { cell[a].1 } else { 1.0 - cell[a].1 }).product();
            let i = HashGrid::index(level, cell[0].0 + bits[0], cell[1].0 + bits[1], cell[2].0 + bits[2]);
            let k = g.params.start + level.offset + FEATURES * i;
            f[0] += w * params[k] as f64;
            f[1] += w * params[k + 1] as f64;
        }
        out.extend_from_slice(&f);
    }
    out
}

/// Random points in the unit cube at least `margin` cells away from every
/// cell face of every level (the encoding's derivative jumps on faces).
fn points_off_faces(g: &HashGrid, rng: &mut Rng, count: usize, margin: f32) -> Vec<f32> {
    let mut pts = Vec::with_capacity(3 * count);
    while pts.len() < 3 * count {
        let p = [rng.f32(), rng.f32(), rng.f32()];
        let clear = g.levels.iter().all(|l| {
            p.iter().all(|&v| {
                let x = v * l.res as f32;
                (x - x.round()).abs() > margin
            })
        });
        if clear {
            pts.extend_from_slice(&p);
        }
    }
    pts
}

/// dL/du of a random linear functional `L = Σ r · encoding` against central
/// differences: of the f64 encoding (tight; it is first checked against
/// `forward`), and of `forward` itself in f32 (loose, rounding-limited).
#[test]
fn input_grad_matches_finite_differences() {
    let (g, n) = small();
    assert!(g.levels.iter().any(|l| l.dense) && g.levels.iter().any(|l| !l.dense));
    let mut rng = Rng::new(21);
    let params: Vec<f32> = (0..n).map(|_| rng.normal()).collect();
    let count = 37;
    let pts = points_off_faces(&g, &mut rng, count, 0.02);
    let r: Vec<f32> = (0..count * g.width()).map(|_| rng.normal()).collect();
    let mut dpts = vec![f32::NAN; 3 * count];
    g.input_grad(&params, &pts, &r, &mut dpts);

    let mut out = vec![0.0f32; count * g.width()];
    g.forward(&params, &pts, &mut out);
    let functional = |u: [f64; 3], i: usize| -> f64 {
        forward64(&g, &params, u).iter().zip(&r[i * g.width()..]).map(|(f, r)| f * *r as f64).sum()
    };
    for (i, q) in pts.chunks(3).enumerate() {
        let u = [q[0] as f64, q[1] as f64, q[2] as f64];
        let f64_out = forward64(&g, &params, u);
        for (k, want) in f64_out.iter().enumerate() {
            let got = out[i * g.width() + k] as f64;
            assert!((got - want).abs() < 1e-5 * (1.0 + want.abs()), "point {i} output {k}: {got} vs {want}");
        }
        for a in 0..3 {
            let h = 1e-7;
            let (mut up, mut down) = (u, u);
            up[a] += h;
            down[a] -= h;
            let num = (functional(up, i) - functional(down, i)) / (2.0 * h);
            let got = dpts[3 * i + a] as f64;
            assert!((got - num).abs() < 1e-4 * (1.0 + num.abs()), "point {i} axis {a}: {got} vs {num}");
        }
    }
    // The real forward pass (AVX2 groups and scalar tail alike), perturbing
    // one axis of every point at once: each point's outputs depend on that
    // point only.
    let h = 2e-4f32;
    let objective = |p: &[f32]| -> Vec<f64> {
        let mut o = vec![0.0f32; count * g.width()];
        g.forward(&params, p, &mut o);
        o.chunks(g.width())
            .zip(r.chunks(g.width()))
            .map(|(o, r)| o.iter().zip(r).map(|(a, b)| (a * b) as f64).sum())
            .collect()
    };
    for a in 0..3 {
        let (mut up, mut down) = (pts.clone(), pts.clone());
        for i in 0..count {
            up[3 * i + a] += h;
            down[3 * i + a] -= h;
        }
        let (fu, fd) = (objective(&up), objective(&down));
        for i in 0..count {
            // The step actually taken, after f32 rounding of the coordinates.
            let step = (up[3 * i + a] - down[3 * i + a]) as f64;
            let num = (fu[i] - fd[i]) / step;
            let got = dpts[3 * i + a] as f64;
            assert!((got - num).abs() < 2e-2 * (1.0 + num.abs()), "f32 forward, point {i} axis {a}: {got} vs {num}");
        }
    }
    assert!(dpts.iter().all(|v| v.abs() > 1e-3), "every point has a gradient: {dpts:?}");
}

/// The table gradients of `backward_with_input_grad` are `backward`'s, bit
/// for bit (accumulated onto the same non-zero buffer), and `dpts` is
/// overwritten, whatever it held.
#[test]
fn backward_with_input_grad_keeps_the_table_gradients_bit_equal() {
    let (g, n) = small();
    let mut rng = Rng::new(22);
    let params: Vec<f32> = (0..n).map(|_| rng.normal()).collect();
    let count = 37;
    let mut pts: Vec<f32> = (0..count * 3).map(|_| rng.f32() * 1.2 - 0.1).collect();
    pts[4] = f32::NAN;
    pts[9] = 1.0;
    pts[10] = 0.0;
    let mut dout: Vec<f32> = (0..count * g.width()).map(|_| rng.normal()).collect();
    dout[g.width()..2 * g.width()].fill(0.0);
    let start: Vec<f32> = (0..n).map(|_| rng.normal()).collect();
    let mut want = start.clone();
    g.backward(&pts, &dout, &mut want);
    let mut got = start.clone();
    let mut dpts = vec![f32::NAN; 3 * count];
    g.backward_with_input_grad(&params, &pts, &dout, &mut got, &mut dpts);
    assert!(got.iter().zip(&want).all(|(a, b)| a.to_bits() == b.to_bits()), "table gradients differ");
    assert_ne!(got, start);
    let mut alone = vec![0.0f32; 3 * count];
    g.input_grad(&params, &pts, &dout, &mut alone);
    assert_eq!(dpts, alone);
    assert!(dpts.iter().all(|v| v.is_finite()));
    assert_eq!(&dpts[3..6], &[0.0; 3], "a point with no output gradient has none");
}

/// A coordinate the forward pass clamps has no gradient; the others have
/// the gradient of the clamped point.
#[test]
fn clamped_coordinates_get_no_gradient() {
    let (g, n) = small();
    let mut rng = Rng::new(23);
    let params: Vec<f32> = (0..n).map(|_| rng.normal()).collect();
    let pts = [-0.5f32, 0.31, 0.62, 0.0, 0.31, 0.62, 0.47, 1.5, f32::NAN, 0.47, 1.0, 0.0];
    let dout: Vec<f32> = (0..4).flat_map(|_| (0..g.width()).map(|k| 1.0 + k as f32 * 0.1)).collect();
    let mut d = vec![0.0f32; 12];
    g.input_grad(&params, &pts, &dout, &mut d);
    assert_eq!(d[0], 0.0, "below 0");
    assert_eq!((d[1], d[2]), (d[4], d[5]), "the other axes as at the clamped point");
    assert!(d[1] != 0.0 && d[2] != 0.0);
    assert_eq!((d[7], d[8]), (0.0, 0.0), "above 1 and NaN");
    assert_eq!(d[6], d[9], "as at the clamped point (1, 0)");
    assert!(d[6] != 0.0);
}

/// `v` rounded to the nearest IEEE binary16 value (ties to even), in f64,
/// by its quantum: the reference for the half tables' rounding.
fn round_half(v: f32) -> f64 {
    let v = f64::from(v).clamp(-65504.0, 65504.0);
    if v == 0.0 {
        return 0.0;
    }
    // Normal binary16 values have 10 fraction bits; below 2^-14 the quantum
    // stays 2^-24 (subnormals).
    let e = v.abs().log2().floor().max(-14.0);
    let q = (e - 10.0).exp2();
    let r = v / q;
    let rounded = if (r - r.trunc()).abs() == 0.5 { 2.0 * (r / 2.0).round() } else { r.round() };
    rounded * q
}

/// The half table's encoding is the f32 encoding of the table rounded to
/// binary16 (checked against the per-point formula in f64 over the rounded
/// values, for dense and hashed levels, a grid at an odd offset, a count
/// that is not a multiple of 8, NaN and out-of-range points, and values
/// beyond binary16's range), and within the rounding of the f32 one.
#[test]
fn half_table_forward_is_the_forward_of_the_rounded_table() {
    let (g, n) = small();
    assert_eq!(g.params.start % 2, 1, "the test grid starts at an odd offset");
    let mut rng = Rng::new(21);
    let mut params: Vec<f32> = (0..n).map(|_| rng.normal() * 0.5).collect();
    // Subnormal and huge values, and an exact tie.
    params[g.params.start] = 3e-6;
    params[g.params.start + 1] = 1e6;
    params[g.params.start + 2] = -7e4;
    params[g.params.start + 3] = 1.0 + 2f32.powi(-11);
    let Some(table) = g.half_table(&params) else {
        assert!(!half_tables_supported(), "no half table on a CPU that supports them");
        eprintln!("this CPU has no AVX2/FMA/F16C: half tables are not built, nothing to compare");
        return;
    };
    assert_eq!(table.words.len(), g.params.len() / 2, "one word per entry");
    let count = 45;
    let mut pts: Vec<f32> = (0..count * 3).map(|_| rng.f32() * 1.2 - 0.1).collect();
    pts[4] = f32::NAN;
    pts[9] = 1.0;
    // A point at the origin reads entry 0 of the dense level 0 (the
    // special values) with weight 1.
    pts[12..15].fill(0.0);
    let mut half = vec![0.0f32; count * g.width()];
    g.forward_half(&table, &pts, &mut half);
    let mut full = vec![0.0f32; count * g.width()];
    g.forward(&params, &pts, &mut full);
    let max_abs = params[g.params.clone()].iter().map(|v| v.abs()).filter(|&v| v <= 65504.0).fold(0.0f32, f32::max);
    let mut hit_special = false;
    for (i, q) in pts.chunks(3).enumerate() {
        for (l, level) in g.levels.iter().enumerate() {
            let (idx, w) = g.corners(level, [q[0], q[1], q[2]]);
            hit_special |= idx.contains(&g.params.start);
            for k in 0..2 {
                let want: f64 = (0..8).map(|c| f64::from(w[c]) * round_half(params[idx[c] + k])).sum();
                let got = f64::from(half[i * g.width() + 2 * l + k]);
                assert!((got - want).abs() < 1e-5 * (1.0 + want.abs()), "point {i} level {l}: {got} vs {want}");
                // Unless a corner holds a value beyond the range, within
                // half a quantum of the largest value of the f32 encoding.
                if idx.iter().all(|&c| params[c + k].abs() <= 65504.0) {
                    let f = full[i * g.width() + 2 * l + k];
                    assert!(
                        (got as f32 - f).abs() <= max_abs * 2f32.powi(-11) + 1e-6,
                        "point {i} level {l}: {got} vs {f}"
                    );
                }
            }
        }
    }
    // The rounding reference itself: ties to even, subnormals, the clamp.
    assert_eq!(round_half(1.0 + 2f32.powi(-11)), 1.0);
    assert_eq!(round_half(1.0 + 3.0 * 2f32.powi(-11)), 1.0 + 2f64.powi(-9));
    assert_eq!(round_half(3e-6), (3e-6f64 / 2f64.powi(-24)).round() * 2f64.powi(-24));
    assert_eq!(round_half(1e6), 65504.0);
    assert!(hit_special, "no point read the special values");
}

/// Forward passes with the table of other parameters are refused, and a
/// table does not follow its parameters (its owner drops it).
#[test]
fn half_table_of_another_grid_is_refused() {
    let (g, n) = small();
    let params = vec![0.25f32; n];
    let mut layout = ParamLayout::default();
    let other = HashGrid::new(
        &mut layout,
        HashGridConfig { levels: 2, log2_table: 8, base_resolution: 2, finest_resolution: 4 },
    );
    let Some(table) = other.half_table(&vec![0.0; layout.len]) else {
        assert!(!half_tables_supported());
        return;
    };
    let pts = [0.5f32; 3];
    let mut out = vec![0.0; g.width()];
    let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| g.forward_half(&table, &pts, &mut out)));
    assert!(r.is_err(), "a table of another grid was accepted");
    let mine = g.half_table(&params).unwrap();
    g.forward_half(&mine, &pts, &mut out);
    assert!(out.iter().all(|&v| v == 0.25), "{out:?}");
}
