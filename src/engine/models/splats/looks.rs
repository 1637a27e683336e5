//! Each training photo's colour correction: what the capture model's
//! per-photo appearance embedding is to the field, for the splats. A photo's
//! exposure and white balance differ from its neighbours' (a phone's
//! auto-exposure); fitted with one look, the splats average them. So a bake
//! fits, at each photo it takes, the affine map `M c + b` of the drawn
//! colours that best matches that photo, drawn towards the identity by a
//! ridge, and fits the splats to the mapped view, and a share of the view
//! as drawn (`fit::FitLoss::own_weight`): the ridge alone lets the splats'
//! own look drift, the share keeps it at the photos' common one. A new
//! view takes the nearest training camera's correction
//! (`view::appearance`'s `nearest`), or none (`mean`: what the exports and
//! the browser draw). The bake maps the view composited on the dataset's
//! background; a render on that background is mapped the same way, one on
//! any other (or a transparent one) maps its foreground alone, so that the
//! background stays as asked.

/// An affine colour map, `c' = M c + b`: rows `[m0 m1 m2 b]` per channel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ColourCorrection(pub [[f32; 4]; 3]);

impl ColourCorrection {
    pub const IDENTITY: Self = Self([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]);

    /// Maps one colour.
    pub fn map(&self, c: [f32; 3]) -> [f32; 3] {
        self.0.map(|r| r[0] * c[0] + r[1] * c[1] + r[2] * c[2] + r[3])
    }

    /// Maps the foreground of a view composited on `background` (`rgb`,
    /// `[.. x 3]`, with each pixel's `opacity`) in place, leaving the
    /// background as it is: `M f + α b + (1 - α) bg` for the foreground
    /// `f = c - (1 - α) bg`, which is the map of the composited colour where
    /// the view is opaque, and keeps a transparent view premultiplied.
    pub fn apply_foreground(&self, rgb: &mut [f32], opacity: &[f32], background: [f32; 3]) {
        for (px, &a) in rgb.chunks_exact_mut(3).zip(opacity) {
            let fg: [f32; 3] = std::array::from_fn(|k| px[k] - (1.0 - a) * background[k]);
            let m = self.0.map(|r| r[0] * fg[0] + r[1] * fg[1] + r[2] * fg[2] + a * r[3]);
            for k in 0..3 {
                px[k] = m[k] + (1.0 - a) * background[k];
            }
        }
    }

    /// Maps every colour of `rgb` (`[.. x 3]`) in place.
    pub fn apply(&self, rgb: &mut [f32]) {
        for px in rgb.chunks_exact_mut(3) {
            let c = self.map([px[0], px[1], px[2]]);
            px.copy_from_slice(&c);
        }
    }

    /// A gradient with respect to the mapped colours (`[.. x 3]`) taken
    /// back to the colours before the map, in place: `Mᵀ d`.
    pub fn pull_back(&self, d: &mut [f32]) {
        let m = &self.0;
        for px in d.chunks_exact_mut(3) {
            let g = [px[0], px[1], px[2]];
            for (k, v) in px.iter_mut().enumerate() {
                *v = m[0][k] * g[0] + m[1][k] * g[1] + m[2][k] * g[2];
            }
        }
    }

    /// The map that minimises, over the pixels where `target` has no NaN,
    /// the squared error of the mapped `drawn` against `target` plus
    /// `ridge` times the number of those pixels times the squared distance
    /// of the map's twelve values from the identity's: least squares in
    /// closed form (f64). The identity when no pixel is valid.
    pub fn fit(drawn: &[f32], target: &[f32], ridge: f64) -> Self {
        // Normal equations: (XᵀX + λn I) W = XᵀT + λn W₀, X's rows [c, 1].
        let mut xtx = [[0.0f64; 4]; 4];
        let mut xtt = [[0.0f64; 3]; 4];
        let mut n = 0usize;
        for (c, t) in drawn.chunks_exact(3).zip(target.chunks_exact(3)) {
            if t.iter().any(|v| v.is_nan()) {
                continue;
            }
            let x = [c[0] as f64, c[1] as f64, c[2] as f64, 1.0];
            for i in 0..4 {
                for j in 0..4 {
                    xtx[i][j] += x[i] * x[j];
                }
                for k in 0..3 {
                    xtt[i][k] += x[i] * t[k] as f64;
                }
            }
            n += 1;
        }
        let lambda = ridge.max(1e-9) * n as f64;
        if n == 0 {
            return Self::IDENTITY;
        }
        for i in 0..4 {
            xtx[i][i] += lambda;
            for k in 0..3 {
                xtt[i][k] += lambda * Self::IDENTITY.0[k][i] as f64;
            }
        }
        let w = solve4(xtx, xtt);
        Self(std::array::from_fn(|k| std::array::from_fn(|i| w[i][k] as f32)))
    }
}

/// `A⁻¹ B` for a symmetric positive definite 4x4 `A` (Gaussian elimination
/// with partial pivoting).
fn solve4(mut a: [[f64; 4]; 4], mut b: [[f64; 3]; 4]) -> [[f64; 3]; 4] {
    for col in 0..4 {
        let pivot = (col..4).max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs())).unwrap_or(col);
        a.swap(col, pivot);
        b.swap(col, pivot);
        for row in col + 1..4 {
            let f = a[row][col] / a[col][col];
            for k in col..4 {
                a[row][k] -= f * a[col][k];
            }
            for k in 0..3 {
                b[row][k] -= f * b[col][k];
            }
        }
    }
    let mut x = [[0.0f64; 3]; 4];
    for row in (0..4).rev() {
        for k in 0..3 {
            let s: f64 = (row + 1..4).map(|j| a[row][j] * x[j][k]).sum();
            x[row][k] = (b[row][k] - s) / a[row][row];
        }
    }
    x
}

/// The training photos' corrections a bake fitted, by dataset frame index
/// (ascending), saved with the splats.
#[derive(Clone, Debug, PartialEq)]
pub struct Looks {
    pub images: Vec<u32>,
    pub corrections: Vec<ColourCorrection>,
    /// The background the photos were fitted on: a view on it is mapped
    /// whole, as the bake mapped it ([`Looks::correct`]).
    pub background: [f32; 3],
}

/// The names of a splats checkpoint's looks.
pub const IMAGES: &str = "looks.images";
pub const CORRECTIONS: &str = "looks.corrections";
pub const BACKGROUND: &str = "looks.background";

impl Looks {
    /// Photo `image`'s correction, if it has one.
    pub fn of(&self, image: u32) -> Option<&ColourCorrection> {
        self.images.binary_search(&image).ok().map(|k| &self.corrections[k])
    }

    /// As checkpoint tensors: the images (exact in f32 below 2^24) and
    /// twelve values each.
    pub fn tensors(&self) -> Vec<(String, Vec<f32>)> {
        let values = self.corrections.iter().flat_map(|c| c.0.iter().flatten().copied()).collect();
        vec![
            (IMAGES.into(), self.images.iter().map(|&i| i as f32).collect()),
            (CORRECTIONS.into(), values),
            (BACKGROUND.into(), self.background.to_vec()),
        ]
    }

    /// Maps a view (`rgb`, with its `opacity`) drawn on `background` by
    /// `correction`: whole on the background the bake fitted on (as it was
    /// fitted), its foreground alone on any other
    /// ([`ColourCorrection::apply_foreground`]: a transparent view stays
    /// premultiplied, another colour stays that colour).
    pub fn correct(&self, correction: &ColourCorrection, rgb: &mut [f32], opacity: &[f32], background: [f32; 3]) {
        if background == self.background {
            correction.apply(rgb);
        } else {
            correction.apply_foreground(rgb, opacity, background);
        }
    }

    /// Read back from [`Looks::tensors`]; an error names what does not fit.
    pub fn from_tensors(images: &[f32], values: &[f32], background: &[f32]) -> Result<Self, String> {
        let background: [f32; 3] = background
            .try_into()
            .ok()
            .filter(|b: &[f32; 3]| b.iter().all(|v| v.is_finite()))
            .ok_or("the corrections' background is not three finite values")?;
        if values.len() != 12 * images.len() {
            return Err(format!("{} corrections' values for {} images (12 each)", values.len(), images.len()));
        }
        let ok = |v: &f32| v.fract() == 0.0 && (0.0..16_777_216.0).contains(v);
        if !images.iter().all(ok) || !images.windows(2).all(|w| w[0] < w[1]) {
            return Err("the corrections' images are not ascending frame indices".into());
        }
        if !values.iter().all(|v| v.is_finite()) {
            return Err("a colour correction is not finite".into());
        }
        let corrections = values
            .chunks_exact(12)
            .map(|v| ColourCorrection(std::array::from_fn(|k| std::array::from_fn(|i| v[4 * k + i]))))
            .collect();
        Ok(Self { images: images.iter().map(|&i| i as u32).collect(), corrections, background })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::rng::Rng;

    fn random_colours(n: usize, seed: u64) -> Vec<f32> {
        let mut rng = Rng::new(seed);
        (0..3 * n).map(|_| rng.f32()).collect()
    }

    /// The objective [`ColourCorrection::fit`] minimises, in f64.
    fn objective(m: &[[f64; 4]; 3], drawn: &[f32], target: &[f32], ridge: f64) -> f64 {
        let mut sum = 0.0;
        let mut n = 0;
        for (c, t) in drawn.chunks_exact(3).zip(target.chunks_exact(3)) {
            if t.iter().any(|v| v.is_nan()) {
                continue;
            }
            for k in 0..3 {
                let mapped = m[k][0] * c[0] as f64 + m[k][1] * c[1] as f64 + m[k][2] * c[2] as f64 + m[k][3];
                sum += (mapped - t[k] as f64).powi(2);
            }
            n += 1;
        }
        let id = ColourCorrection::IDENTITY.0;
        let dist: f64 =
            (0..3).flat_map(|k| (0..4).map(move |i| (k, i))).map(|(k, i)| (m[k][i] - id[k][i] as f64).powi(2)).sum();
        sum + ridge * n as f64 * dist
    }

    #[test]
    fn a_known_map_is_recovered_and_masked_pixels_are_left_out() {
        let drawn = random_colours(500, 1);
        let known = ColourCorrection([[1.2, 0.1, 0.0, -0.05], [0.0, 0.9, 0.05, 0.02], [0.03, -0.1, 1.1, 0.1]]);
        let mut target = drawn.clone();
        known.apply(&mut target);
        // A tenth of the pixels masked out with wild values beside the NaN.
        for p in (0..500).step_by(10) {
            target[3 * p..3 * p + 3].copy_from_slice(&[f32::NAN, 50.0, -50.0]);
        }
        let fitted = ColourCorrection::fit(&drawn, &target, 1e-9);
        for (a, b) in fitted.0.iter().flatten().zip(known.0.iter().flatten()) {
            assert!((a - b).abs() < 1e-4, "{fitted:?} against {known:?}");
        }
    }

    #[test]
    fn a_heavy_ridge_keeps_the_identity_and_no_pixel_gives_it() {
        let (drawn, target) = (random_colours(100, 2), random_colours(100, 3));
        let heavy = ColourCorrection::fit(&drawn, &target, 1e9);
        for (a, b) in heavy.0.iter().flatten().zip(ColourCorrection::IDENTITY.0.iter().flatten()) {
            assert!((a - b).abs() < 1e-6, "{heavy:?}");
        }
        assert_eq!(ColourCorrection::fit(&drawn, &vec![f32::NAN; 300], 0.1), ColourCorrection::IDENTITY);
    }

    /// Property: the fitted map is the minimiser. Every one of its twelve
    /// values moved either way raises the objective, for random scenes
    /// and ridges.
    #[test]
    fn the_fitted_map_minimises_the_ridged_error() {
        for seed in 0..8u64 {
            let drawn = random_colours(200, 10 + seed);
            let target = random_colours(200, 20 + seed);
            let ridge = [0.0, 0.01, 0.1, 1.0][seed as usize % 4];
            let fitted = ColourCorrection::fit(&drawn, &target, ridge);
            let m: [[f64; 4]; 3] = fitted.0.map(|r| r.map(f64::from));
            let best = objective(&m, &drawn, &target, ridge);
            for k in 0..3 {
                for i in 0..4 {
                    for d in [-1e-3, 1e-3] {
                        let mut moved = m;
                        moved[k][i] += d;
                        let o = objective(&moved, &drawn, &target, ridge);
                        assert!(o > best - 1e-9 * best, "seed {seed}: [{k}][{i}] {d:+}: {o} below {best}");
                    }
                }
            }
        }
    }

    #[test]
    fn pulling_back_is_the_maps_transpose() {
        // The gradient of <g, M c + b> with respect to c, by differences.
        let m = ColourCorrection([[1.2, 0.1, -0.3, 0.5], [0.2, 0.9, 0.05, 0.0], [0.0, -0.4, 1.1, 0.1]]);
        let (c, g) = ([0.3f32, 0.6, 0.2], [0.7f32, -1.1, 0.4]);
        let mut d = g;
        m.pull_back(&mut d);
        let dot = |c: [f32; 3]| m.map(c).iter().zip(&g).map(|(a, b)| (a * b) as f64).sum::<f64>();
        for k in 0..3 {
            let (mut up, mut down) = (c, c);
            up[k] += 1e-2;
            down[k] -= 1e-2;
            let fd = (dot(up) - dot(down)) / 2e-2;
            assert!((fd - d[k] as f64).abs() < 1e-4, "[{k}]: {} against {fd}", d[k]);
        }
    }

    #[test]
    fn a_render_maps_its_foreground_and_keeps_its_background() {
        let m = ColourCorrection([[1.2, 0.1, 0.0, 0.05], [0.0, 0.9, 0.05, -0.02], [0.03, -0.1, 1.1, 0.1]]);
        let bg = [0.2, 0.7, 0.4];
        let c = [0.3f32, 0.5, 0.8];
        // Opaque: the map of the colour; empty: the background as it was.
        let mut rgb = [c, bg].concat();
        m.apply_foreground(&mut rgb, &[1.0, 0.0], bg);
        let want = [m.map(c), bg].concat();
        assert!(rgb.iter().zip(&want).all(|(a, b)| (a - b).abs() < 1e-6), "{rgb:?} against {want:?}");
        // Half transparent on no background (premultiplied): half the map
        // of the colour the foreground has unpremultiplied.
        let mut half: Vec<f32> = c.iter().map(|v| 0.5 * v).collect();
        m.apply_foreground(&mut half, &[0.5], [0.0; 3]);
        let want: Vec<f32> = m.map(c).iter().map(|v| 0.5 * v).collect();
        assert!(half.iter().zip(&want).all(|(a, b)| (a - b).abs() < 1e-6), "{half:?} against {want:?}");
    }

    #[test]
    fn a_view_on_the_bakes_background_is_mapped_whole_and_on_another_its_foreground() {
        let m = ColourCorrection([[1.2, 0.1, 0.0, 0.05], [0.0, 0.9, 0.05, -0.02], [0.03, -0.1, 1.1, 0.1]]);
        let looks = Looks { images: vec![0], corrections: vec![m], background: [1.0; 3] };
        let (rgb, opacity) = ([0.9f32, 0.8, 0.95, 0.4, 0.5, 0.6], [0.3f32, 1.0]);
        let mut on_bake = rgb;
        looks.correct(&m, &mut on_bake, &opacity, [1.0; 3]);
        let mut whole = rgb;
        m.apply(&mut whole);
        assert_eq!(on_bake, whole);
        let mut other = rgb;
        looks.correct(&m, &mut other, &opacity, [0.0; 3]);
        let mut fg = rgb;
        m.apply_foreground(&mut fg, &opacity, [0.0; 3]);
        assert_eq!(other, fg);
        assert!(other != whole);
    }

    #[test]
    fn looks_come_back_from_their_tensors_and_bad_ones_are_named() {
        let looks = Looks {
            images: vec![0, 3, 9],
            corrections: vec![
                ColourCorrection::IDENTITY,
                ColourCorrection([[2.0; 4]; 3]),
                ColourCorrection([[0.5; 4]; 3]),
            ],
            background: [1.0, 0.5, 0.0],
        };
        let t = looks.tensors();
        assert_eq!(Looks::from_tensors(&t[0].1, &t[1].1, &t[2].1).unwrap(), looks);
        assert_eq!(looks.of(3), Some(&ColourCorrection([[2.0; 4]; 3])));
        assert!(looks.of(4).is_none());
        let short = Looks::from_tensors(&t[0].1, &t[1].1[..30], &t[2].1).unwrap_err();
        assert!(short.contains("30 corrections' values for 3 images"), "{short}");
        assert!(Looks::from_tensors(&[3.0, 0.0, 9.0], &t[1].1, &t[2].1).unwrap_err().contains("ascending"));
        let mut nan = t[1].1.clone();
        nan[5] = f32::NAN;
        assert!(Looks::from_tensors(&t[0].1, &nan, &t[2].1).unwrap_err().contains("not finite"));
        assert!(Looks::from_tensors(&t[0].1, &t[1].1, &[1.0, 1.0]).unwrap_err().contains("background"));
    }
}
