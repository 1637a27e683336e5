//! Image quality metrics: PSNR and SSIM.
//!
//! Both are computed in f64 and follow the reference evaluation script
//! `tools/nerf_eval.py` (the numbers agree to well within 0.01 dB / 1e-4):
//!
//! * PSNR is `-10 log10(mse)` over all elements of two images with values in
//!   `[0, 1]` (no per-channel weighting); identical images give `+inf`.
//! * SSIM uses an 11x11 Gaussian window with sigma 1.5 applied separably
//!   with 'valid' boundaries (no padding, so the SSIM map is
//!   `(w - 10) x (h - 10)`), constants `c1 = 0.01^2`, `c2 = 0.03^2` (data
//!   range 1), the mean of the SSIM map per channel, then the mean over
//!   channels.
//!
//! Images are interleaved row-major slices of shape `(height, width,
//! channels)`. Non-finite inputs propagate into a NaN result.
//!
//! Both can also be taken inside a mask (`inside`: one flag per pixel),
//! for captures whose masks single out the object:
//!
//! * [`psnr_inside`]: `-10 log10(sum over inside pixels and channels of
//!   (a - b)^2 / (channels * count))`;
//! * [`SsimMap::mean_inside`]: the mean of the SSIM map over the map pixels
//!   whose window is centred on an inside pixel (the map's pixel `(x, y)` is
//!   the window centred on image pixel `(x + 5, y + 5)`, so a mask pixel
//!   within 5 pixels of the border has no SSIM value), per channel, then the
//!   mean over channels.

/// SSIM window size and Gaussian sigma.
pub const SSIM_WINDOW: usize = 11;
pub const SSIM_SIGMA: f64 = 1.5;
pub(crate) const C1: f64 = 0.01 * 0.01;
pub(crate) const C2: f64 = 0.03 * 0.03;

/// Why a metric could not be computed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum MetricsError {
    #[error("image buffers have {a} and {b} values, expected {expected} ({width}x{height}x{channels})")]
    SizeMismatch { a: usize, b: usize, expected: usize, width: usize, height: usize, channels: usize },
    #[error("image is {width}x{height}, SSIM needs at least 11x11 pixels (11x11 Gaussian window, no padding)")]
    TooSmall { width: usize, height: usize },
    #[error("image has no channels")]
    NoChannels,
    #[error("image buffers have {a} and {b} values, expected {channels} per mask flag ({flags} flags)")]
    MaskValues { a: usize, b: usize, flags: usize, channels: usize },
    #[error("the mask has {flags} flags, expected one per pixel ({pixels})")]
    MaskFlags { flags: usize, pixels: usize },
}

/// Converts a mean squared error (of values in `[0, 1]`) to PSNR in dB;
/// `mse == 0` gives `+inf`.
pub fn mse_to_psnr(mse: f64) -> f64 {
    if mse == 0.0 { f64::INFINITY } else { -10.0 * mse.log10() }
}

/// Mean squared error over all elements, accumulated in f64.
///
/// # Panics
/// If the slices differ in length or are empty.
pub fn mse(a: &[f32], b: &[f32]) -> f64 {
    assert_eq!(a.len(), b.len(), "mse: images differ in size");
    assert!(!a.is_empty(), "mse: empty images");
    let sum: f64 = a
        .iter()
        .zip(b)
        .map(|(&x, &y)| {
            let d = x as f64 - y as f64;
            d * d
        })
        .sum();
    sum / a.len() as f64
}

/// PSNR in dB of two images with values in `[0, 1]` (any channel count; the
/// MSE is the mean over all elements). Identical images give `+inf`.
///
/// # Panics
/// If the slices differ in length or are empty.
pub fn psnr(a: &[f32], b: &[f32]) -> f64 {
    mse_to_psnr(mse(a, b))
}

/// PSNR in dB over the pixels flagged in `inside` (one flag per pixel of
/// two interleaved images of `channels` channels): the mean squared error
/// over those pixels' channels. `None` when no pixel is inside; identical
/// pixels give `+inf`.
///
/// Errors if `channels` is 0 or the buffers do not hold `channels` values
/// per flag.
pub fn psnr_inside(a: &[f32], b: &[f32], channels: usize, inside: &[bool]) -> Result<Option<f64>, MetricsError> {
    if channels == 0 {
        return Err(MetricsError::NoChannels);
    }
    if a.len() != inside.len() * channels || b.len() != a.len() {
        return Err(MetricsError::MaskValues { a: a.len(), b: b.len(), flags: inside.len(), channels });
    }
    let (mut sum, mut count) = (0.0f64, 0usize);
    for ((pa, pb), _) in a.chunks_exact(channels).zip(b.chunks_exact(channels)).zip(inside).filter(|(_, m)| **m) {
        for (&x, &y) in pa.iter().zip(pb) {
            let d = x as f64 - y as f64;
            sum += d * d;
        }
        count += 1;
    }
    Ok((count > 0).then(|| mse_to_psnr(sum / (count * channels) as f64)))
}

/// The normalised 1-D Gaussian of the SSIM window, computed exactly as the
/// reference does.
pub(crate) fn gaussian_kernel() -> [f64; SSIM_WINDOW] {
    let mut k = [0.0; SSIM_WINDOW];
    let half = (SSIM_WINDOW - 1) as f64 / 2.0;
    for (i, v) in k.iter_mut().enumerate() {
        let x = i as f64 - half;
        *v = (-(x * x) / (2.0 * SSIM_SIGMA * SSIM_SIGMA)).exp();
    }
    let s: f64 = k.iter().sum();
    k.iter_mut().for_each(|v| *v /= s);
    k
}

/// Mean SSIM of two `width x height x channels` interleaved images with
/// values in `[0, 1]`: the mean of each channel's SSIM map, then the mean
/// over channels ([`SsimMap::mean`]).
///
/// Errors if the buffers do not match the given shape, if `channels` is 0,
/// or if either dimension is smaller than the 11-pixel window (the reference
/// uses 'valid' filtering, which has no output for such images).
pub fn ssim(a: &[f32], b: &[f32], width: usize, height: usize, channels: usize) -> Result<f64, MetricsError> {
    Ok(ssim_map(a, b, width, height, channels)?.mean())
}

/// The SSIM maps of two images, one per channel: `(width - 10) x (height -
/// 10)` values each ('valid' filtering), the value at `(x, y)` that of the
/// window centred on image pixel `(x + 5, y + 5)`.
#[derive(Clone, Debug, PartialEq)]
pub struct SsimMap {
    pub width: usize,
    pub height: usize,
    pub channels: usize,
    /// Channel-major: channel `c`'s map is `values[c * width * height..]`,
    /// row-major.
    pub values: Vec<f64>,
}

/// How far the map's pixels are from the image's: half the window.
const SSIM_HALF: usize = (SSIM_WINDOW - 1) / 2;

impl SsimMap {
    /// The mean SSIM: each channel's map averaged, then the channels.
    pub fn mean(&self) -> f64 {
        let n = self.width * self.height;
        let total: f64 = self
            .values
            .chunks_exact(n)
            .map(|map| {
                let mut sum = 0.0;
                for v in map {
                    sum += v;
                }
                sum / n as f64
            })
            .sum();
        total / self.channels as f64
    }

    /// The mean SSIM over the map pixels whose window is centred on a pixel
    /// flagged in `inside` (one flag per pixel of the `(width + 10) x
    /// (height + 10)` image), per channel, then over the channels. `None`
    /// when no such map pixel exists.
    ///
    /// Errors if `inside` does not have one flag per image pixel.
    pub fn mean_inside(&self, inside: &[bool]) -> Result<Option<f64>, MetricsError> {
        let (iw, ih) = (self.width + 2 * SSIM_HALF, self.height + 2 * SSIM_HALF);
        if inside.len() != iw * ih {
            return Err(MetricsError::MaskFlags { flags: inside.len(), pixels: iw * ih });
        }
        let at = |x: usize, y: usize| inside[(y + SSIM_HALF) * iw + x + SSIM_HALF];
        let cells: Vec<usize> = (0..self.height)
            .flat_map(|y| (0..self.width).map(move |x| (x, y)))
            .filter(|&(x, y)| at(x, y))
            .map(|(x, y)| y * self.width + x)
            .collect();
        if cells.is_empty() {
            return Ok(None);
        }
        let n = self.width * self.height;
        let total: f64 = self
            .values
            .chunks_exact(n)
            .map(|map| cells.iter().map(|&k| map[k]).sum::<f64>() / cells.len() as f64)
            .sum();
        Ok(Some(total / self.channels as f64))
    }
}

/// The SSIM maps of two `width x height x channels` interleaved images with
/// values in `[0, 1]` (see [`SsimMap`]); errors as [`ssim`].
pub fn ssim_map(a: &[f32], b: &[f32], width: usize, height: usize, channels: usize) -> Result<SsimMap, MetricsError> {
    if channels == 0 {
        return Err(MetricsError::NoChannels);
    }
    let expected = width.checked_mul(height).and_then(|n| n.checked_mul(channels));
    if expected != Some(a.len()) || expected != Some(b.len()) {
        return Err(MetricsError::SizeMismatch {
            a: a.len(),
            b: b.len(),
            expected: expected.unwrap_or(usize::MAX),
            width,
            height,
            channels,
        });
    }
    if width < SSIM_WINDOW || height < SSIM_WINDOW {
        return Err(MetricsError::TooSmall { width, height });
    }
    let k = gaussian_kernel();
    let (wo, ho) = (width - (SSIM_WINDOW - 1), height - (SSIM_WINDOW - 1));
    let mut values = Vec::with_capacity(channels * wo * ho);
    for c in 0..channels {
        values.extend(ssim_channel(a, b, width, height, channels, c, &k));
    }
    Ok(SsimMap { width: wo, height: ho, channels, values })
}

/// The SSIM map of one channel, row-major.
fn ssim_channel(
    a: &[f32],
    b: &[f32],
    width: usize,
    height: usize,
    channels: usize,
    c: usize,
    k: &[f64; SSIM_WINDOW],
) -> Vec<f64> {
    let wo = width - (SSIM_WINDOW - 1);
    let ho = height - (SSIM_WINDOW - 1);

    // Horizontal pass of x, y, x*x, y*y, x*y (the reference filters each row
    // first, then each column).
    let mut hx = vec![0.0f64; height * wo];
    let mut hy = vec![0.0f64; height * wo];
    let mut hxx = vec![0.0f64; height * wo];
    let mut hyy = vec![0.0f64; height * wo];
    let mut hxy = vec![0.0f64; height * wo];
    let mut rx = vec![0.0f64; width];
    let mut ry = vec![0.0f64; width];
    for r in 0..height {
        for i in 0..width {
            let idx = (r * width + i) * channels + c;
            rx[i] = a[idx] as f64;
            ry[i] = b[idx] as f64;
        }
        let o = r * wo;
        for j in 0..wo {
            let (mut sx, mut sy, mut sxx, mut syy, mut sxy) = (0.0, 0.0, 0.0, 0.0, 0.0);
            for (t, &kt) in k.iter().enumerate() {
                let x = rx[j + t];
                let y = ry[j + t];
                sx += kt * x;
                sy += kt * y;
                sxx += kt * (x * x);
                syy += kt * (y * y);
                sxy += kt * (x * y);
            }
            hx[o + j] = sx;
            hy[o + j] = sy;
            hxx[o + j] = sxx;
            hyy[o + j] = syy;
            hxy[o + j] = sxy;
        }
    }

    // Vertical pass, one output row at a time.
    let mut acc = vec![[0.0f64; 5]; wo];
    let mut out = Vec::with_capacity(wo * ho);
    for i in 0..ho {
        acc.iter_mut().for_each(|v| *v = [0.0; 5]);
        for (t, &kt) in k.iter().enumerate() {
            let o = (i + t) * wo;
            for (j, v) in acc.iter_mut().enumerate() {
                v[0] += kt * hx[o + j];
                v[1] += kt * hy[o + j];
                v[2] += kt * hxx[o + j];
                v[3] += kt * hyy[o + j];
                v[4] += kt * hxy[o + j];
            }
        }
        for &[mx, my, fxx, fyy, fxy] in &acc {
            let sxx = fxx - mx * mx;
            let syy = fyy - my * my;
            let sxy = fxy - mx * my;
            let num = (2.0 * mx * my + C1) * (2.0 * sxy + C2);
            let den = (mx * mx + my * my + C1) * (sxx + syy + C2);
            out.push(num / den);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A deterministic pseudo-random stream in [0, 1).
    fn lcg(seed: &mut u64) -> f32 {
        *seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((*seed >> 40) as f32) / (1u64 << 24) as f32
    }

    fn smooth_image(w: usize, h: usize, c: usize) -> Vec<f32> {
        let mut v = Vec::with_capacity(w * h * c);
        for y in 0..h {
            for x in 0..w {
                for ch in 0..c {
                    let t = (x as f32 * 0.3 + ch as f32).sin() * (y as f32 * 0.2).cos();
                    v.push(0.5 + 0.4 * t);
                }
            }
        }
        v
    }

    fn add_noise(img: &[f32], amp: f32, seed: u64) -> Vec<f32> {
        let mut s = seed;
        img.iter().map(|&v| (v + amp * (lcg(&mut s) - 0.5)).clamp(0.0, 1.0)).collect()
    }

    #[test]
    fn psnr_constant_offset_is_20_db() {
        let a = vec![0.25f32; 300];
        let b: Vec<f32> = a.iter().map(|v| v + 0.1).collect();
        // f32 rounding of 0.35 perturbs the offset by ~1e-8.
        assert!((psnr(&a, &b) - 20.0).abs() < 1e-5, "{}", psnr(&a, &b));
        assert!((mse_to_psnr(0.01) - 20.0).abs() < 1e-12);
        assert!((mse_to_psnr(1.0)).abs() < 1e-12);
        assert!((mse_to_psnr(1e-4) - 40.0).abs() < 1e-12);
    }

    #[test]
    fn psnr_identical_is_infinite() {
        let a = smooth_image(7, 5, 3);
        assert_eq!(psnr(&a, &a), f64::INFINITY);
        assert_eq!(mse_to_psnr(0.0), f64::INFINITY);
    }

    #[test]
    fn psnr_is_mean_over_all_elements() {
        // One channel off by 1.0 in one of four elements: mse = 0.25 -> 6.02 dB.
        let a = [0.0f32, 0.0, 0.0, 0.0];
        let b = [1.0f32, 0.0, 0.0, 0.0];
        assert!((psnr(&a, &b) - (-10.0 * 0.25f64.log10())).abs() < 1e-12);
        assert!((mse(&a, &b) - 0.25).abs() < 1e-15);
    }

    #[test]
    #[should_panic(expected = "differ in size")]
    fn psnr_size_mismatch_panics() {
        psnr(&[0.0; 3], &[0.0; 4]);
    }

    #[test]
    fn gaussian_kernel_is_normalised_and_symmetric() {
        let k = gaussian_kernel();
        assert!((k.iter().sum::<f64>() - 1.0).abs() < 1e-15);
        for i in 0..SSIM_WINDOW {
            assert_eq!(k[i], k[SSIM_WINDOW - 1 - i]);
        }
        assert!(k[5] > k[4] && k[4] > k[0]);
    }

    #[test]
    fn ssim_identical_is_one() {
        for c in [1, 3, 4] {
            let a = smooth_image(23, 17, c);
            let s = ssim(&a, &a, 23, 17, c).unwrap();
            assert!((s - 1.0).abs() < 1e-12, "{s}");
        }
        // Constant images too (zero variance: the constants keep it defined).
        let a = vec![0.3f32; 11 * 11];
        assert!((ssim(&a, &a, 11, 11, 1).unwrap() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn ssim_is_symmetric() {
        let a = smooth_image(20, 14, 3);
        let b = add_noise(&a, 0.3, 9);
        let ab = ssim(&a, &b, 20, 14, 3).unwrap();
        let ba = ssim(&b, &a, 20, 14, 3).unwrap();
        assert!((ab - ba).abs() < 1e-12, "{ab} {ba}");
    }

    #[test]
    fn ssim_drops_with_noise() {
        let a = smooth_image(32, 24, 3);
        let mut last = 1.0;
        for amp in [0.02f32, 0.1, 0.3, 0.8] {
            let b = add_noise(&a, amp, 42);
            let s = ssim(&a, &b, 32, 24, 3).unwrap();
            assert!(s < last, "amp {amp}: {s} !< {last}");
            assert!(s > -1.0 && s < 1.0);
            last = s;
        }
        assert!(last < 0.5, "{last}");
    }

    #[test]
    fn ssim_channels_are_averaged() {
        // Channel 0 identical, channel 1 noisy: the 2-channel SSIM is the mean
        // of the two single-channel values.
        let (w, h) = (15, 13);
        let g0 = smooth_image(w, h, 1);
        let g1 = add_noise(&g0, 0.4, 3);
        let a: Vec<f32> = g0.iter().flat_map(|&v| [v, v]).collect();
        let b: Vec<f32> = g0.iter().zip(&g1).flat_map(|(&v, &n)| [v, n]).collect();
        let s1 = ssim(&g0, &g1, w, h, 1).unwrap();
        let s = ssim(&a, &b, w, h, 2).unwrap();
        assert!((s - (1.0 + s1) / 2.0).abs() < 1e-12, "{s} {s1}");
    }

    #[test]
    fn ssim_errors() {
        let a = vec![0.0f32; 10 * 20];
        assert_eq!(ssim(&a, &a, 10, 20, 1), Err(MetricsError::TooSmall { width: 10, height: 20 }));
        assert_eq!(ssim(&a, &a, 20, 10, 1), Err(MetricsError::TooSmall { width: 20, height: 10 }));
        assert!(matches!(ssim(&a, &a[1..], 10, 20, 1), Err(MetricsError::SizeMismatch { .. })));
        assert!(matches!(ssim(&a, &a, 10, 10, 1), Err(MetricsError::SizeMismatch { .. })));
        assert!(matches!(ssim(&a, &a, usize::MAX, 3, 1), Err(MetricsError::SizeMismatch { .. })));
        assert_eq!(ssim(&[], &[], 11, 11, 0), Err(MetricsError::NoChannels));
        let msg = MetricsError::TooSmall { width: 8, height: 8 }.to_string();
        assert!(msg.contains("8x8") && msg.contains("11x11"), "{msg}");
    }

    /// `ssim` after it became the mean of `ssim_map`: bit for bit the
    /// values the single-pass implementation before the refactor (commit
    /// 25e7248) gave on the same inputs, printed with `to_bits()`.
    #[test]
    fn ssim_is_unchanged_by_the_map_refactor() {
        let (w, h, ch) = (16usize, 16usize, 3usize);
        let (mut a, mut b) = (Vec::new(), Vec::new());
        for y in 0..h {
            for x in 0..w {
                for c in 0..ch {
                    let av = ((x * 7 + y * 13 + c * 5) % 65) as i64;
                    let bv = (av + ((x * 3 + y * 5 + c) % 9) as i64 - 4).clamp(0, 64);
                    a.push(av as f32 / 64.0);
                    b.push(bv as f32 / 64.0);
                }
            }
        }
        assert_eq!(ssim(&a, &b, w, h, ch).unwrap().to_bits(), 0x3fefb28800706705);
        let (w, h, ch) = (29usize, 19usize, 3usize);
        let mut seed = 5u64;
        let a: Vec<f32> = (0..w * h * ch).map(|_| lcg(&mut seed)).collect();
        let b: Vec<f32> = a.iter().map(|&v| (0.8 * v + 0.2 * lcg(&mut seed)).min(1.0)).collect();
        assert_eq!(ssim(&a, &b, w, h, ch).unwrap().to_bits(), 0x3fee647cff543e59);
        // The map has the 'valid' size, one map per channel.
        let m = ssim_map(&a, &b, w, h, ch).unwrap();
        assert_eq!((m.width, m.height, m.channels, m.values.len()), (19, 9, 3, 19 * 9 * 3));
    }

    #[test]
    fn psnr_inside_is_the_psnr_of_the_inside_pixels() {
        // Three RGB pixels, the first two inside: squared errors 3 * 0.01
        // and 0.09, so mse = 0.12 / (3 * 2) = 0.02; the third (off by 1.0
        // everywhere) does not count.
        let a = [0.0f32; 9];
        let b = [0.1f32, 0.1, 0.1, 0.3, 0.0, 0.0, 1.0, 1.0, 1.0];
        let p = psnr_inside(&a, &b, 3, &[true, true, false]).unwrap().unwrap();
        assert!((p - (-10.0 * 0.02f64.log10())).abs() < 1e-6, "{p}");
        // Against `psnr` of the inside pixels gathered by hand.
        let mut seed = 11u64;
        let (a, b): (Vec<f32>, Vec<f32>) = (0..7 * 5 * 3).map(|_| (lcg(&mut seed), lcg(&mut seed))).unzip();
        let inside: Vec<bool> = (0..35).map(|k| k % 3 != 1).collect();
        let pick = |v: &[f32]| -> Vec<f32> {
            v.chunks(3).zip(&inside).filter(|(_, m)| **m).flat_map(|(p, _)| p.to_vec()).collect()
        };
        let want = psnr(&pick(&a), &pick(&b));
        assert!((psnr_inside(&a, &b, 3, &inside).unwrap().unwrap() - want).abs() < 1e-12);
        assert!((psnr_inside(&a, &b, 3, &[true; 35]).unwrap().unwrap() - psnr(&a, &b)).abs() < 1e-12);
        assert_eq!(psnr_inside(&a, &b, 3, &[false; 35]).unwrap(), None);
        assert_eq!(psnr_inside(&a, &a, 3, &inside).unwrap(), Some(f64::INFINITY));
        assert!(matches!(psnr_inside(&a, &b, 3, &[true; 34]), Err(MetricsError::MaskValues { flags: 34, .. })));
        assert!(matches!(psnr_inside(&a, &b[1..], 3, &[true; 35]), Err(MetricsError::MaskValues { .. })));
        assert_eq!(psnr_inside(&a, &b, 0, &[true; 35]), Err(MetricsError::NoChannels));
    }

    #[test]
    fn ssim_inside_the_mask_averages_the_map_there() {
        // Identical on the left 14 columns, noisy on the right 16: windows
        // centred on columns 5..=8 see only the identical part.
        let (w, h) = (30usize, 16usize);
        let a = smooth_image(w, h, 3);
        let noisy = add_noise(&a, 0.5, 4);
        let b: Vec<f32> = (0..w * h * 3).map(|k| if (k / 3) % w < 14 { a[k] } else { noisy[k] }).collect();
        let map = ssim_map(&a, &b, w, h, 3).unwrap();
        assert!(map.mean() < 0.9, "{}", map.mean());
        let left: Vec<bool> = (0..w * h).map(|k| (5..=8).contains(&(k % w))).collect();
        let s = map.mean_inside(&left).unwrap().unwrap();
        assert!((s - 1.0).abs() < 1e-12, "{s}");
        // Everything inside is the plain mean; one pixel inside, its value.
        assert!((map.mean_inside(&vec![true; w * h]).unwrap().unwrap() - map.mean()).abs() < 1e-15);
        let mut one = vec![false; w * h];
        one[(5 + 3) * w + 5 + 7] = true;
        let want = (0..3).map(|c| map.values[c * map.width * map.height + 3 * map.width + 7]).sum::<f64>() / 3.0;
        assert!((map.mean_inside(&one).unwrap().unwrap() - want).abs() < 1e-15);
        // A mask only along the border has no window centred in it.
        let border: Vec<bool> = (0..w * h).map(|k| k % w < 5 || k / w >= h - 5).collect();
        assert_eq!(map.mean_inside(&border).unwrap(), None);
        assert_eq!(map.mean_inside(&[true; 3]), Err(MetricsError::MaskFlags { flags: 3, pixels: w * h }));
    }

    /// The 16x16x3 pattern and the expected values come from running the
    /// reference functions of /work/shared/tools/nerf_eval.py (numpy 2.4.6)
    /// on the same arrays:
    ///
    /// ```python
    /// av = (x*7 + y*13 + c*5) % 65; bv = clip(av + (x*3 + y*5 + c) % 9 - 4, 0, 64)
    /// a[y, x, c] = av / 64; b[y, x, c] = bv / 64
    /// ne.ssim(a, b) -> 0.9905433662963511; ne.psnr(a, b) -> 28.022394915090885
    /// ```
    ///
    /// The values k/64 are exact in f32, so both sides see identical inputs.
    #[test]
    fn matches_numpy_reference_rgb_16x16() {
        let (w, h, ch) = (16usize, 16usize, 3usize);
        let mut a = Vec::new();
        let mut b = Vec::new();
        for y in 0..h {
            for x in 0..w {
                for c in 0..ch {
                    let av = ((x * 7 + y * 13 + c * 5) % 65) as i64;
                    let bv = (av + ((x * 3 + y * 5 + c) % 9) as i64 - 4).clamp(0, 64);
                    a.push(av as f32 / 64.0);
                    b.push(bv as f32 / 64.0);
                }
            }
        }
        let s = ssim(&a, &b, w, h, ch).unwrap();
        let p = psnr(&a, &b);
        assert!((s - 0.9905433662963511).abs() < 1e-9, "ssim {s}");
        assert!((p - 28.022394915090885).abs() < 1e-9, "psnr {p}");
    }

    /// Single channel, non-square (20 wide, 12 high), from the same numpy
    /// reference:
    ///
    /// ```python
    /// a[y, x, 0] = ((x*x + 2*y) % 33) / 32; b[y, x, 0] = ((x*x + 2*y + (x ^ y) % 3) % 33) / 32
    /// ne.ssim(a, b) -> 0.8545651763877705; ne.psnr(a, b) -> 17.664354672057353
    /// ```
    #[test]
    fn matches_numpy_reference_gray_20x12() {
        let (w, h) = (20usize, 12usize);
        let mut a = Vec::new();
        let mut b = Vec::new();
        for y in 0..h {
            for x in 0..w {
                a.push(((x * x + 2 * y) % 33) as f32 / 32.0);
                b.push(((x * x + 2 * y + (x ^ y) % 3) % 33) as f32 / 32.0);
            }
        }
        let s = ssim(&a, &b, w, h, 1).unwrap();
        let p = psnr(&a, &b);
        assert!((s - 0.8545651763877705).abs() < 1e-9, "ssim {s}");
        assert!((p - 17.664354672057353).abs() < 1e-9, "psnr {p}");
    }

    /// Runs the reference script itself on two generated PNGs when python3
    /// with numpy and Pillow is available (otherwise prints a note and checks
    /// nothing; the hard-coded tests above cover that case).
    #[test]
    fn cross_check_with_reference_script() {
        let script = std::env::var_os("NERF_EVAL_PY")
            .map(std::path::PathBuf::from)
            .unwrap_or_else(|| "/work/shared/tools/nerf_eval.py".into());
        if !script.is_file() {
            eprintln!("note: {} not found, skipping the cross-check", script.display());
            return;
        }
        let have_deps = std::process::Command::new("python3")
            .args(["-c", "import numpy, PIL"])
            .output()
            .map(|o| o.status.success())
            .unwrap_or(false);
        if !have_deps {
            eprintln!("note: python3 with numpy and Pillow not available, skipping the cross-check");
            return;
        }

        let (w, h) = (37u32, 29u32);
        let gt_f = smooth_image(w as usize, h as usize, 3);
        let out_f = add_noise(&gt_f, 0.25, 7);
        let to_u8 = |v: &[f32]| -> Vec<u8> { v.iter().map(|&x| (x * 255.0).round() as u8).collect() };
        let (gt8, out8) = (to_u8(&gt_f), to_u8(&out_f));

        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        std::fs::create_dir_all(root.join("test")).unwrap();
        std::fs::create_dir_all(root.join("renders")).unwrap();
        std::fs::write(
            root.join("transforms_test.json"),
            r#"{"camera_angle_x": 0.69, "frames": [{"file_path": "./test/r_0"}]}"#,
        )
        .unwrap();
        image::RgbImage::from_raw(w, h, gt8.clone()).unwrap().save(root.join("test/r_0.png")).unwrap();
        image::RgbImage::from_raw(w, h, out8.clone()).unwrap().save(root.join("renders/r_0.png")).unwrap();

        let out = std::process::Command::new("python3")
            .arg(&script)
            .arg(root)
            .arg(root.join("renders"))
            .arg("--json")
            .output()
            .unwrap();
        assert!(out.status.success(), "script failed: {}", String::from_utf8_lossy(&out.stderr));
        let res: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        let py_psnr = res["psnr"].as_f64().unwrap();
        let py_ssim = res["ssim"].as_f64().unwrap();
        assert_eq!(res["views"], 1);

        let a: Vec<f32> = out8.iter().map(|&v| v as f32 / 255.0).collect();
        let b: Vec<f32> = gt8.iter().map(|&v| v as f32 / 255.0).collect();
        let rs_psnr = psnr(&a, &b);
        let rs_ssim = ssim(&a, &b, w as usize, h as usize, 3).unwrap();
        eprintln!(
            "cross-check: PSNR rust {rs_psnr:.10} python {py_psnr:.10} (diff {:.1e}); \
             SSIM rust {rs_ssim:.10} python {py_ssim:.10} (diff {:.1e})",
            (rs_psnr - py_psnr).abs(),
            (rs_ssim - py_ssim).abs()
        );
        assert!((rs_psnr - py_psnr).abs() < 0.01, "psnr {rs_psnr} vs {py_psnr}");
        assert!((rs_ssim - py_ssim).abs() < 1e-4, "ssim {rs_ssim} vs {py_ssim}");
        // In practice they agree far more closely (only the f32 inputs differ).
        assert!((rs_psnr - py_psnr).abs() < 1e-5 && (rs_ssim - py_ssim).abs() < 1e-6);
    }
}
