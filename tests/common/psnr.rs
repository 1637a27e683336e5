//! PSNR in the tests: of a model on a dataset's test split, and between two
//! 8-bit images.

use image::RgbImage;
use radiance::engine::dataset::{Dataset, Split};
use radiance::engine::metrics::psnr;
use radiance::engine::models::Model;
use radiance::engine::view::render_view;

/// Frame `k`'s pixels on the dataset's background, row by row, three floats
/// each (the layout of a rendered view's `rgb`).
pub fn ground_truth(ds: &Dataset, k: usize) -> Vec<f32> {
    let f = &ds.frames[k];
    (0..f.camera.height)
        .flat_map(|j| (0..f.camera.width).map(move |i| (i, j)))
        .flat_map(|(i, j)| f.image.rgb_on(i, j, ds.background))
        .collect()
}

/// The mean PSNR (dB) of `model`'s renders of the test views.
pub fn test_psnr(model: &dyn Model, ds: &Dataset) -> f64 {
    let test = ds.split(Split::Test);
    let mut total = 0.0;
    for &k in test {
        let v = render_view(model, &ds.frames[k].camera, ds.background);
        total += psnr(&v.rgb, &ground_truth(ds, k));
    }
    total / test.len() as f64
}

/// The PSNR (dB) of `b` against `a`, over `a`'s size.
pub fn rgb8_psnr(a: &RgbImage, b: &RgbImage) -> f64 {
    let mut se = 0.0;
    for (x, y, p) in a.enumerate_pixels() {
        let q = b.get_pixel(x, y);
        se += (0..3).map(|c| (f64::from(p.0[c]) - f64::from(q.0[c])).powi(2)).sum::<f64>();
    }
    10.0 * (255.0f64.powi(2) / (se / f64::from(3 * a.width() * a.height()))).log10()
}
