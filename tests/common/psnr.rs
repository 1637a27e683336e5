//! PSNR in the tests.

use image::RgbImage;

/// The PSNR (dB) of `b` against `a`, over `a`'s size.
pub fn rgb8_psnr(a: &RgbImage, b: &RgbImage) -> f64 {
    let mut se = 0.0;
    for (x, y, p) in a.enumerate_pixels() {
        let q = b.get_pixel(x, y);
        se += (0..3).map(|c| (f64::from(p.0[c]) - f64::from(q.0[c])).powi(2)).sum::<f64>();
    }
    10.0 * (255.0f64.powi(2) / (se / f64::from(3 * a.width() * a.height()))).log10()
}
