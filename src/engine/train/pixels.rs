//! The pixels training draws its rays from: every pixel of the training
//! frames, or, when the dataset's masks say to ignore the outside
//! ([`MaskUse::Ignore`]), only the pixels whose mask is at least
//! [`masks::INSIDE`].
//!
//! Draws are uniform over the pool, so every pixel in it is as likely as
//! any other whatever its frame. With masks, each training frame keeps the
//! list of its pixels inside (4 bytes per pixel, [`PixelPool::bytes`];
//! `train::estimate` counts them); without, nothing is stored and a draw
//! is the same as it always was, so runs without masks are unchanged bit
//! for bit.

use crate::engine::dataset::{Dataset, MaskUse, masks};

/// The training pixels of a dataset, numbered `0..total()` frame by frame.
#[derive(Clone, Debug)]
pub struct PixelPool {
    /// Pixels of the pool in the training frames up to each one (inclusive).
    cumulative: Vec<u64>,
    /// With masks to ignore: each training frame's pixels inside its mask
    /// (row-major indices, ascending).
    inside: Option<Vec<Vec<u32>>>,
}

impl PixelPool {
    /// The pool of `ds`'s training frames: all their pixels, or those inside
    /// their masks when `ds.masks` is `Ignore`. (Decoded images are far
    /// below 2^32 pixels, so a pixel's index fits in `u32`.)
    pub fn new(ds: &Dataset) -> Self {
        let inside = (ds.masks == MaskUse::Ignore).then(|| {
            ds.train
                .iter()
                .map(|&i| match &ds.frames[i].mask {
                    Some(m) => (0..m.len() as u32).filter(|&p| m[p as usize] >= masks::INSIDE).collect(),
                    // Every frame has a mask when masks are in effect; a
                    // frame built without one keeps all its pixels.
                    None => {
                        let c = &ds.frames[i].camera;
                        (0..c.width * c.height).collect()
                    }
                })
                .collect::<Vec<Vec<u32>>>()
        });
        let mut total = 0u64;
        let cumulative = ds
            .train
            .iter()
            .enumerate()
            .map(|(k, &i)| {
                let c = &ds.frames[i].camera;
                total += match &inside {
                    Some(lists) => lists[k].len() as u64,
                    None => c.width as u64 * c.height as u64,
                };
                total
            })
            .collect();
        Self { cumulative, inside }
    }

    /// Pixels in the pool.
    pub fn total(&self) -> u64 {
        self.cumulative.last().copied().unwrap_or(0)
    }

    /// Pixel `p` of the pool (`p < total()`): the position of its frame in
    /// the training split and its row-major index in that frame.
    pub fn pixel(&self, p: u64) -> (usize, u64) {
        let k = self.cumulative.partition_point(|&c| c <= p);
        let local = p - if k == 0 { 0 } else { self.cumulative[k - 1] };
        match &self.inside {
            Some(lists) => (k, lists[k][local as usize] as u64),
            None => (k, local),
        }
    }

    /// Bytes the pool holds beyond its per-frame counts: the lists of
    /// pixels inside the masks.
    pub fn bytes(&self) -> u64 {
        self.inside.as_ref().map_or(0, |l| l.iter().map(|v| v.len() as u64 * 4).sum())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::dataset::synthetic::BallScene;

    use crate::engine::batch::TrainRay;
    use crate::engine::models::config::ModelConfig;
    use crate::engine::models::training::Budget;
    use crate::engine::train::trainer::{TrainState, Trainer};

    #[test]
    fn without_masks_the_pool_is_every_training_pixel_in_order() {
        let ds = BallScene { size: 5, views: 3, ..Default::default() }.dataset();
        let pool = PixelPool::new(&ds);
        assert_eq!((pool.total(), pool.bytes()), (75, 0));
        let all: Vec<(usize, u64)> = (0..75).map(|p| pool.pixel(p)).collect();
        let want: Vec<(usize, u64)> = (0..3).flat_map(|k| (0..25).map(move |q| (k, q))).collect();
        assert_eq!(all, want);
    }

    #[test]
    fn with_masks_to_ignore_the_pool_is_the_pixels_inside() {
        let mut ds = BallScene { size: 4, views: 3, ..Default::default() }.dataset();
        // Frame 0: pixels 1 and 14 inside; frame 1: none (an empty mask);
        // frame 2: the last row, where 127 is outside and 128 inside.
        let masks: [Vec<u8>; 3] = [
            (0..16).map(|p| if p == 1 || p == 14 { 255 } else { 0 }).collect(),
            vec![0; 16],
            (0..16).map(|p| if p >= 12 { 127 + (p % 2) as u8 } else { 0 }).collect(),
        ];
        for (f, m) in ds.frames.iter_mut().zip(masks) {
            f.mask = Some(m);
        }
        // Scoring leaves the pool whole.
        ds.masks = MaskUse::Score;
        assert_eq!(PixelPool::new(&ds).total(), 48);
        ds.masks = MaskUse::Ignore;
        let pool = PixelPool::new(&ds);
        assert_eq!((pool.total(), pool.bytes()), (4, 16));
        let all: Vec<(usize, u64)> = (0..4).map(|p| pool.pixel(p)).collect();
        assert_eq!(all, [(0, 1), (0, 14), (2, 13), (2, 15)]);
    }

    /// The frame pixel a training ray was cast through (the ray is compared
    /// with every pixel's, computed the same way, so they are equal).
    fn pixel_of(t: &Trainer<'_>, ds: &Dataset, r: &TrainRay) -> (usize, u32, u32) {
        let f = &ds.frames[r.image as usize];
        let scene = t.model.scene();
        let (w, h) = (f.camera.width, f.camera.height);
        let (i, j) = (0..h)
            .flat_map(|j| (0..w).map(move |i| (i, j)))
            .find(|&(i, j)| scene.to_model(&f.camera.pixel_ray(i, j)) == r.ray)
            .expect("the ray of a pixel");
        (r.image as usize, i, j)
    }

    #[test]
    fn the_trainers_batches_come_only_from_inside_the_masks_for_every_model() {
        let mut ds = BallScene { size: 12, views: 4, ..Default::default() }.dataset();
        // Inside: a diagonal pattern, plus the whole of frame 1.
        for (k, f) in ds.frames.iter_mut().enumerate() {
            f.mask = Some((0..144u32).map(|p| if k == 1 || (p % 12 + p / 12) % 3 == 0 { 255 } else { 0 }).collect());
        }
        let inside = |(k, i, j): (usize, u32, u32)| ds.frames[k].mask.as_ref().unwrap()[(j * 12 + i) as usize] >= 128;
        for preset in ["instant-tiny", "nerf-tiny"] {
            for masks in [MaskUse::Ignore, MaskUse::Score] {
                ds.masks = masks;
                let cfg = ModelConfig::preset(preset).unwrap();
                let (model, adam) = cfg.build_with_adam(ds.scene(), 0, None).unwrap();
                let budget = Budget { steps: Some(10), seconds: None };
                let t = Trainer::new(model, adam, cfg.train_config(3, 128, budget), TrainState::default(), &ds);
                let drawn: Vec<(usize, u32, u32)> =
                    (0..8).flat_map(|step| t.batch(step)).map(|r| pixel_of(&t, &ds, &r)).collect();
                assert!(drawn.len() >= 8 * 64, "{preset}: {} rays", drawn.len());
                let outside = drawn.iter().filter(|&&p| !inside(p)).count();
                let distinct: std::collections::BTreeSet<_> = drawn.iter().collect();
                let frames: std::collections::BTreeSet<usize> = drawn.iter().map(|p| p.0).collect();
                assert_eq!(frames, (0..4).collect(), "{preset} {masks}: every training frame is drawn from");
                if masks == MaskUse::Ignore {
                    assert_eq!(outside, 0, "{preset}: drew {outside} pixels outside the masks");
                    assert!(distinct.len() > 150, "{preset}: {} distinct pixels", distinct.len());
                } else {
                    // Scoring trains on every pixel: a third of them inside
                    // (and all of frame 1), so about half of the draws are out.
                    assert!(outside * 3 > drawn.len(), "{preset}: {outside} of {} outside", drawn.len());
                }
            }
        }
    }
}
