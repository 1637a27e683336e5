//! Per-image appearance (NeRF in the Wild's latent codes, nerfacto's
//! appearance embedding; design `real-captures.md` 2.6): a learned vector
//! per training image, so differences of exposure and white balance between
//! photos are explained by the image rather than by floaters and mottled
//! colour in the scene.
//!
//! The embedding `e_img` (`dim` values) would be a third input block of the
//! colour network's first layer, next to the geometry features and the
//! direction code. Since it is the same for every sample of an image, that
//! block's contribution `W_app^T e_img` is a constant per image: it is folded
//! into the layer's bias. A batch of samples computes one bias row per image
//! it holds ([`Appearance::gather`]) and adds it to each sample's
//! pre-activation ([`Appearance::add_bias`]): one `width`-wide add per
//! sample, whatever `dim` is. The backward pass sums the pre-activation
//! gradients of each image's samples into `dB_img` and then
//! `dW_app += e_img dB_img^T`, `de_img = W_app dB_img`
//! ([`Appearance::backward`]).
//!
//! Parameters: the table `E` (`[images x dim]`, zero at first, so every
//! image starts with the same appearance and moves only as far as its
//! photos ask) and the projection `W_app` (`[dim x width]`, He-uniform).
//! The table has a fixed number of rows (`images`) so the parameter layout
//! does not depend on the dataset; images beyond it get no embedding (a
//! zero bias). `dim = 0` has no parameters and adds nothing.

use std::ops::Range;

use super::linear::ParamLayout;
use crate::engine::rng::Rng;

/// The slot of a sample whose image has no embedding.
pub const NO_SLOT: u32 = u32::MAX;

/// A table of per-image embeddings and their projection into a layer's
/// bias, over a flat parameter buffer.
#[derive(Clone, Debug)]
pub struct Appearance {
    /// Rows of the table: images `0..images` have an embedding.
    pub images: usize,
    /// Values per embedding.
    pub dim: usize,
    /// Outputs of the layer whose bias it adds to.
    pub width: usize,
    /// `E`, `[images x dim]`, row-major.
    pub table: Range<usize>,
    /// `W_app`, `[dim x width]`, row-major.
    pub proj: Range<usize>,
    /// Inputs of the whole layer (its other blocks and this one), for the
    /// He-uniform bound of `W_app`.
    fan_in: usize,
}

/// The per-image biases of one batch of samples: the distinct images it
/// holds (its slots), each sample's slot, each slot's bias row and, after a
/// backward pass, its gradient. One per thread, reused from batch to batch.
#[derive(Clone, Debug, Default)]
pub struct AppearanceBatch {
    /// Per image of the table, its slot in this batch (or [`NO_SLOT`]).
    slot_of: Vec<u32>,
    /// The image of each slot.
    present: Vec<u32>,
    /// Per sample, the slot of its image (or [`NO_SLOT`]).
    slots: Vec<u32>,
    /// `[slots x width]`: `W_app^T e_img` of each slot's image.
    bias: Vec<f32>,
    /// `[slots x width]`: dL/dB of each slot.
    dbias: Vec<f32>,
}

impl AppearanceBatch {
    /// Samples in the batch.
    pub fn len(&self) -> usize {
        self.slots.len()
    }

    pub fn is_empty(&self) -> bool {
        self.slots.is_empty()
    }

    /// Forgets the samples (the next pass has no per-image appearance).
    pub fn clear_samples(&mut self) {
        self.slots.clear();
    }

    /// Keeps samples `keep` (sorted indices), in order.
    pub fn compact(&mut self, keep: &[usize]) {
        for (dst, &src) in keep.iter().enumerate() {
            self.slots[dst] = self.slots[src];
        }
        self.slots.truncate(keep.len());
    }

    /// The images of the batch, one per slot.
    pub fn images(&self) -> &[u32] {
        &self.present
    }
}

impl Appearance {
    /// Lays out `E` (`{name}.embedding`) and `W_app` (`{name}.proj`) for
    /// `images` images of `dim` values, feeding a layer with `width` outputs
    /// and `fan_in` inputs in all. With `dim = 0` nothing is laid out.
    pub fn new(layout: &mut ParamLayout, name: &str, images: usize, dim: usize, width: usize, fan_in: usize) -> Self {
        let (table, proj) = if dim == 0 {
            (0..0, 0..0)
        } else {
            (layout.add(&format!("{name}.embedding"), images * dim), layout.add(&format!("{name}.proj"), dim * width))
        };
        Self { images, dim, width, table, proj, fan_in: fan_in.max(1) }
    }

    /// Whether it adds anything (`dim > 0`).
    pub fn enabled(&self) -> bool {
        self.dim > 0
    }

    /// Zero embeddings and a He-uniform projection (bound `sqrt(6 /
    /// fan_in)`, as `Linear::init` for the whole layer).
    pub fn init(&self, params: &mut [f32], rng: &mut Rng) {
        params[self.table.clone()].fill(0.0);
        let bound = (6.0 / self.fan_in as f32).sqrt();
        for p in &mut params[self.proj.clone()] {
            *p = (rng.f32() * 2.0 - 1.0) * bound;
        }
    }

    /// The embedding of `image` (`[dim]`; `None` beyond the table).
    pub fn embedding<'p>(&self, params: &'p [f32], image: u32) -> Option<&'p [f32]> {
        let i = image as usize;
        (i < self.images && self.enabled()).then(|| &params[self.table.start + i * self.dim..][..self.dim])
    }

    /// The mean embedding of `images` (those beyond the table are left
    /// out; zeros when none is left): the appearance of a new view, as
    /// nerfacto renders with the mean of the training images' embeddings.
    pub fn mean_embedding(&self, params: &[f32], images: impl IntoIterator<Item = u32>) -> Vec<f32> {
        let mut sum = vec![0.0f64; self.dim];
        let mut count = 0usize;
        for img in images {
            if let Some(e) = self.embedding(params, img) {
                for (s, &v) in sum.iter_mut().zip(e) {
                    *s += v as f64;
                }
                count += 1;
            }
        }
        sum.iter().map(|&s| if count > 0 { (s / count as f64) as f32 } else { 0.0 }).collect()
    }

    /// Writes `W_app^T e` (`[width]`) into `out` for an embedding `e`
    /// (`[dim]`).
    pub fn bias_of(&self, params: &[f32], e: &[f32], out: &mut [f32]) {
        let w = &params[self.proj.clone()];
        let out = &mut out[..self.width];
        out.fill(0.0);
        for (a, &ea) in e.iter().enumerate().take(self.dim) {
            for (o, &wv) in out.iter_mut().zip(&w[a * self.width..(a + 1) * self.width]) {
                *o += ea * wv;
            }
        }
    }

    /// Prepares `batch` for samples of `images` (`[n]`, the image of each
    /// sample): a slot per distinct image and its bias row.
    pub fn gather(&self, params: &[f32], images: &[u32], batch: &mut AppearanceBatch) {
        for &img in &batch.present {
            batch.slot_of[img as usize] = NO_SLOT;
        }
        batch.present.clear();
        batch.slots.clear();
        if !self.enabled() {
            batch.slots.resize(images.len(), NO_SLOT);
            return;
        }
        batch.slot_of.resize(self.images, NO_SLOT);
        for &img in images {
            let slot = match batch.slot_of.get_mut(img as usize) {
                Some(s) if *s != NO_SLOT => *s,
                Some(s) => {
                    *s = batch.present.len() as u32;
                    batch.present.push(img);
                    *s
                }
                None => NO_SLOT,
            };
            batch.slots.push(slot);
        }
        let (k, w) = (batch.present.len(), self.width);
        batch.bias.resize(k * w, 0.0);
        for (s, &img) in batch.present.iter().enumerate() {
            let e = &params[self.table.start + img as usize * self.dim..][..self.dim];
            self.bias_of(params, e, &mut batch.bias[s * w..(s + 1) * w]);
        }
    }

    /// Adds each sample's bias row to its row of `pre` (`[n x width]`, `n`
    /// = the batch's samples).
    pub fn add_bias(&self, batch: &AppearanceBatch, pre: &mut [f32]) {
        if !self.enabled() {
            return;
        }
        let w = self.width;
        for (row, &slot) in pre.chunks_exact_mut(w).zip(&batch.slots) {
            if slot != NO_SLOT {
                for (p, &b) in row.iter_mut().zip(&batch.bias[slot as usize * w..][..w]) {
                    *p += b;
                }
            }
        }
    }

    /// Accumulates into `grads` the gradient of `E` and `W_app` given the
    /// gradient `dpre` (`[n x width]`) of the pre-activations
    /// [`Appearance::add_bias`] added to.
    pub fn backward(&self, params: &[f32], batch: &mut AppearanceBatch, dpre: &[f32], grads: &mut [f32]) {
        if !self.enabled() || batch.present.is_empty() {
            return;
        }
        let (k, w, d) = (batch.present.len(), self.width, self.dim);
        batch.dbias.clear();
        batch.dbias.resize(k * w, 0.0);
        for (row, &slot) in dpre.chunks_exact(w).zip(&batch.slots) {
            if slot != NO_SLOT {
                for (g, &v) in batch.dbias[slot as usize * w..][..w].iter_mut().zip(row) {
                    *g += v;
                }
            }
        }
        let proj = &params[self.proj.clone()];
        for (s, &img) in batch.present.iter().enumerate() {
            let db = &batch.dbias[s * w..(s + 1) * w];
            let e0 = self.table.start + img as usize * d;
            for a in 0..d {
                let ea = params[e0 + a];
                let wa = &proj[a * w..(a + 1) * w];
                // dE[img][a] = W_app[a] . dB;  dW_app[a] += e[a] dB.
                let mut de = 0.0f32;
                for ((g, &wv), &b) in grads[self.proj.start + a * w..][..w].iter_mut().zip(wa).zip(db) {
                    de += wv * b;
                    *g += ea * b;
                }
                grads[e0 + a] += de;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::nn::linear::Linear;

    /// A layer `y = x W + b` with the appearance folded into its bias, and
    /// the same layer with the embedding as an explicit third input block.
    struct Setup {
        layout: ParamLayout,
        folded: Linear,
        app: Appearance,
        params: Vec<f32>,
        x: Vec<f32>,
        images: Vec<u32>,
        g: Vec<f32>,
    }

    const N: usize = 9;
    const IN: usize = 4;
    const OUT: usize = 5;
    const DIM: usize = 3;
    const IMAGES: usize = 6;

    fn setup() -> Setup {
        let mut layout = ParamLayout::default();
        let folded = Linear::new(&mut layout, "l", IN, OUT);
        let app = Appearance::new(&mut layout, "app", IMAGES, DIM, OUT, IN + DIM);
        let mut rng = Rng::new(11);
        let mut params = vec![0.0f32; layout.len];
        folded.init(&mut params, &mut rng);
        app.init(&mut params, &mut rng);
        assert!(params[app.table.clone()].iter().all(|&v| v == 0.0), "embeddings start at zero");
        // Random embeddings and biases, so every gradient term is exercised.
        for p in params.iter_mut() {
            *p += 0.5 * rng.normal();
        }
        let x: Vec<f32> = (0..N * IN).map(|_| rng.normal()).collect();
        // Images 1, 4 and 2, one beyond the table (7) which gets no bias.
        let images = vec![1, 4, 1, 2, 7, 4, 4, 1, 2];
        let g: Vec<f32> = (0..N * OUT).map(|_| rng.normal()).collect();
        Setup { layout, folded, app, params, x, images, g }
    }

    /// `sum(y * g)` in f64 straight from the definition: the embedding as
    /// a third input block of the layer.
    fn objective(s: &Setup, p: &[f64]) -> f64 {
        let mut total = 0.0;
        for r in 0..N {
            let img = s.images[r] as usize;
            for o in 0..OUT {
                let mut acc = p[s.folded.b.start + o];
                for i in 0..IN {
                    acc += s.x[r * IN + i] as f64 * p[s.folded.w.start + i * OUT + o];
                }
                if img < IMAGES {
                    for a in 0..DIM {
                        acc += p[s.app.table.start + img * DIM + a] * p[s.app.proj.start + a * OUT + o];
                    }
                }
                total += acc * s.g[r * OUT + o] as f64;
            }
        }
        total
    }

    fn forward(s: &Setup, batch: &mut AppearanceBatch) -> Vec<f32> {
        let mut y = vec![0.0f32; N * OUT];
        s.folded.forward(&s.params, &[(&s.x, IN)], N, &mut y);
        s.app.gather(&s.params, &s.images, batch);
        s.app.add_bias(batch, &mut y);
        y
    }

    #[test]
    fn the_folded_bias_is_the_explicit_third_input_block() {
        let s = setup();
        let mut batch = AppearanceBatch::default();
        let y = forward(&s, &mut batch);
        assert_eq!(batch.images(), &[1, 4, 2], "one slot per image present, in order of appearance");
        // The same layer with [x, e_img] as its input (zeros beyond the table).
        let mut layout = ParamLayout::default();
        let explicit = Linear::new(&mut layout, "l", IN + DIM, OUT);
        let mut p = vec![0.0f32; layout.len];
        p[explicit.w.start..explicit.w.start + IN * OUT].copy_from_slice(&s.params[s.folded.w.clone()]);
        p[explicit.w.start + IN * OUT..explicit.w.end].copy_from_slice(&s.params[s.app.proj.clone()]);
        p[explicit.b.clone()].copy_from_slice(&s.params[s.folded.b.clone()]);
        let e: Vec<f32> = s
            .images
            .iter()
            .flat_map(|&img| s.app.embedding(&s.params, img).map_or(vec![0.0; DIM], |e| e.to_vec()))
            .collect();
        let mut want = vec![0.0f32; N * OUT];
        explicit.forward(&p, &[(&s.x, IN), (&e, DIM)], N, &mut want);
        for (a, b) in y.iter().zip(&want) {
            assert!((a - b).abs() < 1e-5 * (1.0 + b.abs()), "{a} vs {b}");
        }
        let f = objective(&s, &s.params.iter().map(|&v| v as f64).collect::<Vec<_>>());
        let fy: f64 = y.iter().zip(&s.g).map(|(a, b)| *a as f64 * *b as f64).sum();
        assert!((f - fy).abs() < 1e-4 * (1.0 + f.abs()), "{f} vs {fy}");
    }

    #[test]
    fn embedding_and_projection_gradients_match_finite_differences_in_f64() {
        let s = setup();
        let mut batch = AppearanceBatch::default();
        forward(&s, &mut batch);
        let mut grads = vec![0.0f32; s.layout.len];
        s.app.backward(&s.params, &mut batch, &s.g, &mut grads);
        let p64: Vec<f64> = s.params.iter().map(|&v| v as f64).collect();
        let h = 1e-6;
        let mut nonzero = 0;
        for i in s.app.table.start..s.app.proj.end {
            let mut pp = p64.clone();
            pp[i] += h;
            let fp = objective(&s, &pp);
            pp[i] -= 2.0 * h;
            let fm = objective(&s, &pp);
            let num = (fp - fm) / (2.0 * h);
            let ana = grads[i] as f64;
            assert!((num - ana).abs() < 1e-4 * (1.0 + num.abs()), "param {i}: numeric {num}, analytic {ana}");
            nonzero += (num.abs() > 1e-3) as usize;
        }
        // Images 0, 3 and 5 are absent: their rows get exactly 0.
        for img in [0usize, 3, 5] {
            let row = s.app.table.start + img * DIM..s.app.table.start + (img + 1) * DIM;
            assert!(grads[row].iter().all(|&g| g == 0.0), "image {img}");
        }
        // Three present rows and the whole projection.
        assert_eq!(nonzero, 3 * DIM + DIM * OUT);
        assert!(grads[..s.app.table.start].iter().all(|&g| g == 0.0), "the layer's own ranges are not touched");
    }

    #[test]
    fn compaction_keeps_each_samples_slot_and_the_mean_skips_unknown_images() {
        let s = setup();
        let mut batch = AppearanceBatch::default();
        forward(&s, &mut batch);
        let before = batch.slots.clone();
        batch.compact(&[1, 4, 8]);
        assert_eq!(batch.slots, vec![before[1], before[4], before[8]]);
        assert_eq!(batch.slots[1], NO_SLOT);
        // A second batch reuses the buffers: slots start again from 0.
        s.app.gather(&s.params, &[2, 2, 0], &mut batch);
        assert_eq!((batch.images(), batch.slots.as_slice()), (&[2u32, 0][..], &[0u32, 0, 1][..]));
        let mean = s.app.mean_embedding(&s.params, [1, 2, 99]);
        for a in 0..DIM {
            let want = 0.5 * (s.app.embedding(&s.params, 1).unwrap()[a] + s.app.embedding(&s.params, 2).unwrap()[a]);
            assert!((mean[a] - want).abs() < 1e-6);
        }
        assert_eq!(s.app.mean_embedding(&s.params, [99]), vec![0.0; DIM]);
    }

    /// A batch that served a larger table gives a smaller one's images
    /// beyond its table no slot (and reads nothing outside it).
    #[test]
    fn a_batch_reused_by_a_smaller_table_keeps_to_its_rows() {
        let s = setup();
        let mut batch = AppearanceBatch::default();
        let mut layout = ParamLayout::default();
        let big = Appearance::new(&mut layout, "big", 50, DIM, OUT, IN);
        big.gather(&vec![0.0; layout.len], &[40, 3], &mut batch);
        assert_eq!(batch.images(), &[40, 3]);
        s.app.gather(&s.params, &[40, 3, 5, 40], &mut batch);
        assert_eq!((batch.images(), batch.slots.as_slice()), (&[3u32, 5][..], &[NO_SLOT, 0, 1, NO_SLOT][..]));
    }

    #[test]
    fn zero_dimensions_lay_out_nothing_and_add_nothing() {
        let mut layout = ParamLayout::default();
        let app = Appearance::new(&mut layout, "app", 10, 0, 4, 4);
        assert_eq!((layout.len, layout.names.len()), (0, 0));
        let mut batch = AppearanceBatch::default();
        app.gather(&[], &[1, 2], &mut batch);
        let mut pre = vec![1.0f32; 8];
        app.add_bias(&batch, &mut pre);
        assert_eq!(pre, vec![1.0; 8]);
        assert_eq!(batch.len(), 2);
        assert!(app.embedding(&[], 1).is_none());
    }
}
