//! `c = a b + beta c` for the layer shapes of the fast model's tiny MLPs,
//! where a general GEMM spends much of its time packing.
//!
//! The products there are tall and narrow: activations `[n x k]` times
//! weights `[k x out]` with `k, out <= 64` (forward and `dx`), and
//! `[k x n] [n x out]` reductions over the samples (`dW`). The weights fit in
//! L1, so an AVX2/FMA kernel reads the operands in place: a tile of up to 6
//! rows by 16 columns of `c` lives in 12 registers while it accumulates
//! broadcast elements of `a` times rows of `b`. Long reductions are split
//! into blocks of rows that stay in L2 while the tiles pass over them.
//!
//! Everything else (wide layers of the classic model, CPUs without AVX2/FMA,
//! column counts that are not a multiple of 8) goes to `matrixmultiply`.

/// Largest `k x out` weight block (and `m x out` gradient block) the kernel
/// takes: 64 x 64 f32 is 16 KiB, half of L1.
const SMALL: usize = 64 * 64;

/// Rows of the reduction dimension per block (two operand blocks of
/// 512 rows x 64 columns are 256 KiB together, within L2).
const KC: usize = 512;

/// `c = a b + beta c` for row-major views with explicit strides: `a` is
/// `[m x k]` with strides `(rsa, csa)`, `b` is `[k x n]`, `c` is `[m x n]`.
/// `beta` is 0 (overwrite) or 1 (accumulate) on the fast path; any value is
/// correct.
#[allow(clippy::too_many_arguments)]
#[inline]
pub fn gemm(
    m: usize,
    k: usize,
    n: usize,
    a: &[f32],
    (rsa, csa): (isize, isize),
    b: &[f32],
    (rsb, csb): (isize, isize),
    beta: f32,
    c: &mut [f32],
    (rsc, csc): (isize, isize),
) {
    if m == 0 || n == 0 {
        return;
    }
    let span = |rows: usize, cols: usize, rs: isize, cs: isize| {
        (rows.saturating_sub(1)) * rs as usize + (cols.saturating_sub(1)) * cs as usize + 1
    };
    assert!(rsa >= 0 && csa >= 0 && rsb >= 0 && csb >= 0 && rsc >= 0 && csc >= 0, "gemm: negative stride");
    assert!(a.len() >= span(m, k, rsa, csa) || k == 0, "gemm: a too short");
    assert!(b.len() >= span(k, n, rsb, csb) || k == 0, "gemm: b too short");
    assert!(c.len() >= span(m, n, rsc, csc), "gemm: c too short");
    if fast_path_applies(m, k, n, (rsb, csb), beta, csc) {
        #[cfg(target_arch = "x86_64")]
        {
            small::gemm(
                m,
                k,
                n,
                a,
                (rsa as usize, csa as usize),
                b,
                (rsb as usize, csb as usize),
                beta,
                c,
                rsc as usize,
            );
            return;
        }
    }
    general(m, k, n, a, (rsa, csa), b, (rsb, csb), beta, c, (rsc, csc));
}

/// Whether the AVX2 kernel takes this product: a CPU with AVX2 and FMA,
/// contiguous rows of `c`, a column count that is a multiple of 8, beta 0
/// or 1, and a small `b` (weights) or small `c` (weight gradients).
fn fast_path_applies(m: usize, k: usize, n: usize, (rsb, csb): (isize, isize), beta: f32, csc: isize) -> bool {
    let small_b = k * n <= SMALL && (csb == 1 || rsb == 1);
    let small_c = m * n <= SMALL && csb == 1;
    has_avx2_fma() && csc == 1 && n.is_multiple_of(8) && (beta == 0.0 || beta == 1.0) && (small_b || small_c)
}

/// Whether this CPU runs the engine's AVX2/FMA paths (this kernel and the
/// hash grid's).
#[cfg(target_arch = "x86_64")]
pub(crate) fn has_avx2_fma() -> bool {
    // Cached by std after the first call.
    is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma")
}

#[cfg(not(target_arch = "x86_64"))]
pub(crate) fn has_avx2_fma() -> bool {
    false
}

/// The general product, through `matrixmultiply`.
#[allow(clippy::too_many_arguments)]
pub fn general(
    m: usize,
    k: usize,
    n: usize,
    a: &[f32],
    (rsa, csa): (isize, isize),
    b: &[f32],
    (rsb, csb): (isize, isize),
    beta: f32,
    c: &mut [f32],
    (rsc, csc): (isize, isize),
) {
    // SAFETY: `gemm` asserted that every index the kernel touches lies
    // inside the slices, with non-negative strides.
    unsafe {
        matrixmultiply::sgemm(m, k, n, 1.0, a.as_ptr(), rsa, csa, b.as_ptr(), rsb, csb, beta, c.as_mut_ptr(), rsc, csc);
    }
}

#[cfg(target_arch = "x86_64")]
mod small {
    use std::arch::x86_64::*;
    use std::cell::RefCell;

    use super::KC;

    thread_local! {
        /// A contiguous copy of a transposed `b` (at most 64 x 64).
        static BT: RefCell<Vec<f32>> = const { RefCell::new(Vec::new()) };
    }

    /// See [`crate::engine::nn::gemm`]; the caller checked the shapes, strides and CPU.
    #[allow(clippy::too_many_arguments)]
    pub fn gemm(
        m: usize,
        k: usize,
        n: usize,
        a: &[f32],
        (rsa, csa): (usize, usize),
        b: &[f32],
        (rsb, csb): (usize, usize),
        beta: f32,
        c: &mut [f32],
        ldc: usize,
    ) {
        if csb == 1 {
            run(m, k, n, a, (rsa, csa), b, rsb, beta, c, ldc);
        } else {
            // b is a transposed weight block: copy it to rows first.
            BT.with_borrow_mut(|bt| {
                bt.clear();
                for p in 0..k {
                    bt.extend((0..n).map(|j| b[p * rsb + j * csb]));
                }
                run(m, k, n, a, (rsa, csa), bt, n, beta, c, ldc);
            });
        }
    }

    #[allow(clippy::too_many_arguments)]
    fn run(
        m: usize,
        k: usize,
        n: usize,
        a: &[f32],
        (rsa, csa): (usize, usize),
        b: &[f32],
        ldb: usize,
        beta: f32,
        c: &mut [f32],
        ldc: usize,
    ) {
        // Bounds: every element read or written lies inside the slices.
        assert!(k == 0 || a.len() > (m - 1) * rsa + (k - 1) * csa);
        assert!(k == 0 || b.len() >= (k - 1) * ldb + n);
        assert!(c.len() >= (m - 1) * ldc + n && n.is_multiple_of(8));
        let mut p0 = 0;
        loop {
            let kc = KC.min(k - p0);
            // The first block applies beta; later blocks accumulate.
            let zero = beta == 0.0 && p0 == 0;
            let mut i = 0;
            while i < m {
                let rows = (m - i).min(6);
                let mut j = 0;
                while j < n {
                    let wide = n - j >= 16;
                    // SAFETY: AVX2 and FMA were detected by the caller; the
                    // tile's rows i..i+rows, columns j..j+8 or j..j+16 and
                    // reduction rows p0..p0+kc are inside the slices (asserted
                    // above).
                    unsafe {
                        let ap = a.as_ptr().add(i * rsa + p0 * csa);
                        let bp = b.as_ptr().add(p0 * ldb + j);
                        let cp = c.as_mut_ptr().add(i * ldc + j);
                        tile(rows, wide, kc, ap, rsa, csa, bp, ldb, cp, ldc, zero);
                    }
                    j += if wide { 16 } else { 8 };
                }
                i += rows;
            }
            p0 += kc;
            if p0 >= k {
                break;
            }
        }
    }

    /// Dispatches to the kernel of this tile shape.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    unsafe fn tile(
        rows: usize,
        wide: bool,
        kc: usize,
        a: *const f32,
        rsa: usize,
        csa: usize,
        b: *const f32,
        ldb: usize,
        c: *mut f32,
        ldc: usize,
        zero: bool,
    ) {
        macro_rules! go {
            ($r:literal) => {
                if wide {
                    kernel::<$r, 2>(kc, a, rsa, csa, b, ldb, c, ldc, zero)
                } else {
                    kernel::<$r, 1>(kc, a, rsa, csa, b, ldb, c, ldc, zero)
                }
            };
        }
        // SAFETY: forwarded from the caller.
        unsafe {
            match rows {
                6 => go!(6),
                5 => go!(5),
                4 => go!(4),
                3 => go!(3),
                2 => go!(2),
                _ => go!(1),
            }
        }
    }

    /// `c[R x 8W] (=|+=) sum_p a[r][p] b[p][..]` with the tile of `c` in
    /// registers.
    #[allow(clippy::too_many_arguments)]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn kernel<const R: usize, const W: usize>(
        kc: usize,
        a: *const f32,
        rsa: usize,
        csa: usize,
        b: *const f32,
        ldb: usize,
        c: *mut f32,
        ldc: usize,
        zero: bool,
    ) {
        // SAFETY (whole body): the caller guarantees the tile is in bounds.
        unsafe {
            let mut acc = [[_mm256_setzero_ps(); W]; R];
            for p in 0..kc {
                let bp = b.add(p * ldb);
                let mut bv = [_mm256_setzero_ps(); W];
                for w in 0..W {
                    bv[w] = _mm256_loadu_ps(bp.add(8 * w));
                }
                let ap = a.add(p * csa);
                for r in 0..R {
                    let av = _mm256_broadcast_ss(&*ap.add(r * rsa));
                    for w in 0..W {
                        acc[r][w] = _mm256_fmadd_ps(av, bv[w], acc[r][w]);
                    }
                }
            }
            for r in 0..R {
                for w in 0..W {
                    let cp = c.add(r * ldc + 8 * w);
                    let v = if zero { acc[r][w] } else { _mm256_add_ps(_mm256_loadu_ps(cp), acc[r][w]) };
                    _mm256_storeu_ps(cp, v);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::rng::Rng;

    /// f64 reference of `alpha a b + beta c`.
    #[allow(clippy::too_many_arguments)]
    fn reference(
        m: usize,
        k: usize,
        n: usize,
        a: &[f32],
        (rsa, csa): (usize, usize),
        b: &[f32],
        (rsb, csb): (usize, usize),
        beta: f32,
        c: &[f32],
        ldc: usize,
    ) -> Vec<f64> {
        let mut out: Vec<f64> = c.iter().map(|&v| v as f64).collect();
        for i in 0..m {
            for j in 0..n {
                let mut s = 0.0f64;
                for p in 0..k {
                    s += a[i * rsa + p * csa] as f64 * b[p * rsb + j * csb] as f64;
                }
                out[i * ldc + j] = s + beta as f64 * c[i * ldc + j] as f64;
            }
        }
        out
    }

    /// Every layer shape of the fast model (forward, dx with a transposed
    /// weight, dW over a long reduction) and ragged sizes, with beta 0 and
    /// 1, agree with an f64 reference, whichever path they take.
    #[test]
    fn products_match_an_f64_reference() {
        let mut rng = Rng::new(11);
        let mut cases = vec![];
        // (m, k, n, a transposed, b transposed)
        for &(k, n) in &[(32, 64), (64, 16), (16, 64), (64, 64), (64, 3), (3, 64), (16, 8), (5, 24)] {
            for &m in &[1, 5, 6, 7, 13, 100] {
                cases.push((m, k, n, false, false)); // y = x W
                cases.push((m, n, k, false, true)); // dx = dy W^T
            }
            cases.push((k, 1300, n, true, false)); // dW = x^T dy: two reduction blocks
        }
        cases.push((70, 70, 72, false, false)); // too big for the kernel
        let mut fast_taken = 0;
        for (m, k, n, at, bt) in cases {
            let a: Vec<f32> = (0..m * k).map(|_| rng.normal()).collect();
            let (rsa, csa) = if at { (1, m) } else { (k, 1) };
            let b: Vec<f32> = (0..k * n).map(|_| rng.normal()).collect();
            let (rsb, csb) = if bt { (1, k) } else { (n, 1) };
            for beta in [0.0f32, 1.0] {
                let ldc = n + 3; // rows of c with padding between them
                let c0: Vec<f32> = (0..m * ldc).map(|_| rng.normal()).collect();
                let want = reference(m, k, n, &a, (rsa, csa), &b, (rsb, csb), beta, &c0, ldc);
                let mut c = c0.clone();
                let st = |r: usize, c: usize| (r as isize, c as isize);
                gemm(m, k, n, &a, st(rsa, csa), &b, st(rsb, csb), beta, &mut c, st(ldc, 1));
                fast_taken += fast_path_applies(m, k, n, st(rsb, csb), beta, 1) as usize;
                for i in 0..m {
                    for j in 0..ldc {
                        let (got, w) = (c[i * ldc + j] as f64, want[i * ldc + j]);
                        let tol = 1e-4 * (1.0 + (k as f64).sqrt() * 4.0);
                        if j < n {
                            assert!(
                                (got - w).abs() < tol,
                                "m{m} k{k} n{n} at{at} bt{bt} beta{beta} [{i},{j}]: {got} vs {w}"
                            );
                        } else {
                            assert_eq!(c[i * ldc + j], c0[i * ldc + j], "padding column {j} untouched");
                        }
                    }
                }
            }
        }
        if has_avx2_fma() {
            assert!(fast_taken > 50, "the kernel was exercised: {fast_taken}");
        }
    }
}
