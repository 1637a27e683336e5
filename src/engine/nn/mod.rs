//! Neural-network building blocks over one flat parameter buffer with named
//! ranges: linear layers and their GEMM, encodings (frequency, spherical
//! harmonics, multiresolution hash grid), the classic NeRF MLP, Adam (with learning-rate
//! scales for ranges), per-image appearance embeddings folded into a layer's
//! bias, and per-image camera pose corrections (`pose`, `pose_report`).

pub mod adam;
pub mod appearance;
pub mod encoding;
pub mod gemm;
pub mod hashgrid;
pub mod linear;
pub mod nerf_net;
pub mod pose;
pub mod pose_report;
pub mod sh;

/// Whether no value is NaN or infinite, in integer operations the compiler
/// vectorises: a float is not finite exactly when its exponent bits are all
/// ones, and adding one to that exponent carries into the top bit. (The
/// float test it replaces, a sum of `v * 0.0`, was one serial chain of
/// additions: 15% of a capture model's training step.)
pub fn all_finite(values: &[f32]) -> bool {
    const EXPONENT: u32 = 0x7f80_0000;
    const ONE: u32 = 0x0080_0000;
    values.iter().fold(0u32, |acc, v| acc | ((v.to_bits() & EXPONENT) + ONE)) & 0x8000_0000 == 0
}

/// Moves rows `keep` (sorted) of a row-major buffer with `width` columns to
/// its front (the rows after them are stale).
pub fn move_rows(v: &mut [f32], width: usize, keep: &[usize]) {
    for (dst, &src) in keep.iter().enumerate() {
        if dst != src {
            v.copy_within(src * width..(src + 1) * width, dst * width);
        }
    }
}

/// Keeps rows `keep` (sorted) of a row-major buffer with `width` columns.
pub fn gather_rows(v: &mut Vec<f32>, width: usize, keep: &[usize]) {
    move_rows(v, width, keep);
    v.truncate(keep.len() * width);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn all_finite_finds_every_non_finite_value_anywhere() {
        let finite = [0.0f32, -0.0, 1.0, -1.0, f32::MAX, f32::MIN, f32::MIN_POSITIVE, 1e-45, -1e-45, 3.0e38];
        let bad = [f32::NAN, -f32::NAN, f32::INFINITY, f32::NEG_INFINITY, f32::from_bits(0x7fc0_0001)];
        let base: Vec<f32> = (0..37).map(|i| finite[i % finite.len()]).collect();
        assert!(all_finite(&base));
        assert!(all_finite(&[]));
        for at in 0..base.len() {
            for b in bad {
                let mut v = base.clone();
                v[at] = b;
                assert!(!all_finite(&v), "{b} at {at}");
                assert_eq!(all_finite(&v), v.iter().all(|x| x.is_finite()));
            }
        }
    }
}
