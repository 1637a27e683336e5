//! What a run will cost before it starts: peak memory and checkpoint size,
//! computed from the configuration and the dataset's size alone (nothing is
//! allocated), so a service can refuse a job that would not fit.
//!
//! The figures follow what the code allocates:
//! - parameters `P` floats, Adam's two moments (`2P`), the divergence
//!   guard's snapshot of all three (`3P`), one gradient buffer per worker
//!   thread (`threads * P`), and while a checkpoint is written, a copy of
//!   the parameters and moments (`3P`);
//! - the occupancy grid (a density and a few bits per cell);
//! - each worker thread's activation buffers, sized for the largest chunk
//!   of samples it processes (they never shrink), and for the capture
//!   model its part's record of the main grid's deferred backward and a
//!   buffer for one level of its gradient;
//! - the dataset, every frame held as 8-bit RGBA, with a byte per pixel
//!   for frames with a mask and 4 bytes per training pixel inside the
//!   masks when training ignores the outside (`train::pixels`);
//! - a fixed allowance for the process itself (code, allocator, stacks);
//! - the allocator's slack on the activations: blocks up to 32 MiB come
//!   from glibc's heaps (`tune_malloc` in `main.rs`), and the free space
//!   between a step's blocks of many sizes fragments them. `tests/estimate.rs`
//!   measured up to a fifth of the activations on top of them (the capture
//!   model with large chunks: 397 MiB with glibc's defaults, 449-468 MiB
//!   with the heap thresholds); a quarter is counted.
//!
//! `tests/estimate.rs` trains small and large configurations, and bakes,
//! and checks the measured peak (`VmHWM`) against this estimate.

use crate::engine::dataset::{Dataset, MaskUse, masks};
use crate::engine::models::config::ModelConfig;

/// The size of a dataset in memory: every frame of every split.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct DataSize {
    pub frames: usize,
    /// Pixels summed over all frames.
    pub pixels: u64,
    /// Pixels of the frames that hold a mask (a byte each).
    pub mask_pixels: u64,
    /// Training pixels inside the masks, when training ignores the outside
    /// (the trainer lists them, 4 bytes each).
    pub inside_pixels: u64,
}

impl DataSize {
    /// `frames` frames of `width` x `height`, without masks.
    pub fn uniform(frames: usize, width: u32, height: u32) -> Self {
        Self { frames, pixels: frames as u64 * width as u64 * height as u64, mask_pixels: 0, inside_pixels: 0 }
    }

    /// The size of a loaded dataset, masks included.
    pub fn of(ds: &Dataset) -> Self {
        let size = |f: &crate::engine::dataset::Frame| f.camera.width as u64 * f.camera.height as u64;
        let inside_pixels = if ds.masks == MaskUse::Ignore {
            let inside = |m: &Vec<u8>| m.iter().filter(|&&v| v >= masks::INSIDE).count() as u64;
            ds.train.iter().filter_map(|&i| ds.frames[i].mask.as_ref()).map(inside).sum()
        } else {
            0
        };
        Self {
            frames: ds.frames.len(),
            pixels: ds.frames.iter().map(size).sum(),
            mask_pixels: ds.frames.iter().filter(|f| f.mask.is_some()).map(size).sum(),
            inside_pixels,
        }
    }
}

/// An estimate: the parts of the peak memory, in bytes, and the size of the
/// checkpoint the run writes.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Estimate {
    /// Trainable parameters.
    pub params: u64,
    /// Peak resident memory, bytes: the sum of `parts`.
    pub memory_bytes: u64,
    /// What makes up the peak, largest first: `(what, bytes)`.
    pub parts: Vec<(String, u64)>,
    /// Bytes the run writes to disk: the checkpoint, or the video.
    pub disk_bytes: u64,
}

/// Memory of the process before any model or data: code, allocator arenas,
/// thread stacks, the async runtime.
pub const BASE_BYTES: u64 = 24 << 20;

/// Bytes per pixel of a loaded frame (8-bit RGBA).
const PIXEL_BYTES: u64 = 4;

/// Bytes per pixel of a mask, and per entry of the trainer's lists of
/// pixels inside the masks.
const MASK_BYTES: u64 = 1;
const INSIDE_BYTES: u64 = 4;

const F32: u64 = 4;

impl Estimate {
    fn new(params: u64, state_floats: u64, mut parts: Vec<(&str, u64)>) -> Self {
        parts.push(("process", BASE_BYTES));
        parts.retain(|p| p.1 > 0);
        parts.sort_by_key(|p| std::cmp::Reverse(p.1));
        let memory_bytes = parts.iter().map(|p| p.1).sum();
        // params + Adam's moments + model state, and a small header.
        let disk_bytes = (3 * params + state_floats) * F32 + (64 << 10);
        Self { params, memory_bytes, parts: parts.into_iter().map(|(k, v)| (k.to_string(), v)).collect(), disk_bytes }
    }

    /// The parts as text: `parameters 12.0 MiB, ...`.
    pub fn describe(&self) -> String {
        self.parts.iter().map(|(k, v)| format!("{k} {}", mib(*v))).collect::<Vec<_>>().join(", ")
    }
}

/// `12.3 MiB`.
pub fn mib(bytes: u64) -> String {
    format!("{:.1} MiB", bytes as f64 / (1u64 << 20) as f64)
}

/// Peak memory and checkpoint size of training `config` on `data` with
/// `threads` worker threads.
pub fn training(config: &ModelConfig, data: DataSize, threads: usize) -> Estimate {
    let threads = threads.max(1) as u64;
    let f = config.spec().footprint(threads);
    let p = f.params * F32;
    let parts = vec![
        ("parameters", p),
        ("optimiser moments", 2 * p),
        ("divergence snapshot", 3 * p),
        ("per-thread gradients", threads * p),
        ("checkpoint copy", 3 * p),
        ("occupancy grid", f.occupancy_cells * (F32 + 2)),
        ("per-thread activations", threads * f.activations * F32),
        ("allocator slack on the activations", threads * f.activations * F32 / 4),
        ("dataset", data.pixels * PIXEL_BYTES),
        ("masks", data.mask_pixels * MASK_BYTES),
        ("training pixels inside the masks", data.inside_pixels * INSIDE_BYTES),
    ];
    Estimate::new(f.params, f.occupancy_cells, parts)
}

/// What each of the rays that place a bake's Gaussians keeps until they are
/// placed (`bake::place`): the Gaussian it places (28 bytes), its
/// photo and whether it is in a margin (5), its cell of the photo's depth
/// grid (4), the neighbour search's entries (its size, cell list entry
/// and result: 16, and the hash map's cells) and carving's verdict (1),
/// rounded up for the map's slack.
const PLACING_RAY_BYTES: u64 = 100;

/// A worker thread's buffers while it renders a tile of rays (the samples
/// of [`crate::engine::view`]'s tiles), for any model.
const RENDER_THREAD_BYTES: u64 = 4 << 20;

/// Peak memory and checkpoint size of baking a model of `source` (loaded
/// with its optimiser state) into splats of `splats` against the training
/// photos of `data` (`bake`), placing `initial` Gaussians
/// (`BakeSettings::initial_for`): the source model and its rendering of
/// the rays that place them (a tile of samples per thread, as a view's,
/// not its training's activations), what each of those rays keeps, the
/// splats at their most Gaussians with Adam's moments, one gradient and
/// the rasteriser's buffers, the dataset and the photos as f32 targets, at
/// full and half size. The most Gaussians are counted because densifying may reach
/// them: a bake that stops short of them peaks lower (`tests/estimate.rs`
/// holds the estimate to within 2.5 times of the peak of bakes whose
/// placing already fills them).
pub fn bake(source: &ModelConfig, splats: &ModelConfig, initial: usize, data: DataSize, threads: usize) -> Estimate {
    let threads = threads.max(1) as u64;
    let src = source.spec().footprint(threads);
    let f = splats.spec().footprint(threads);
    let p = f.params * F32;
    let parts = vec![
        ("source model and its state", 6 * src.params * F32),
        ("source occupancy grid", src.occupancy_cells * (F32 + 2)),
        ("source render buffers", threads * RENDER_THREAD_BYTES),
        ("placing rays", crate::engine::bake::placing_rays(initial) * PLACING_RAY_BYTES),
        ("splats", p),
        ("optimiser moments", 2 * p),
        ("gradient", p),
        ("checkpoint copy", 3 * p),
        ("rasteriser buffers", f.activations * F32),
        ("dataset", data.pixels * PIXEL_BYTES),
        ("photos as targets", data.pixels * 3 * F32),
        ("photos as targets at half size", data.pixels / 4 * 3 * F32),
    ];
    Estimate::new(f.params, 0, parts)
}

/// Peak memory of rendering a video of `frames` frames of `width` x
/// `height` from a model of `config` (loaded with its optimiser state).
pub fn video(config: &ModelConfig, frames: u32, width: u32, height: u32, threads: usize) -> Estimate {
    let f = config.spec().footprint(threads.max(1) as u64);
    let (params, occupancy) = (f.params, f.occupancy_cells);
    let pixels = width as u64 * height as u64;
    let parts = vec![
        // The checkpoint is read whole, then parameters and moments are copied out of it.
        ("model and optimiser state", 6 * params * F32),
        ("occupancy grid", occupancy * (F32 + 2)),
        // A view's colour, depth and opacity, and each thread's samples.
        ("render buffers", pixels * 5 * F32 + threads.max(1) as u64 * RENDER_THREAD_BYTES),
        // Every frame as 8-bit RGB, then the encoded file.
        ("frames", 2 * frames as u64 * pixels * 3),
    ];
    let mut e = Estimate::new(params, occupancy, parts);
    // At most the raw frames: both formats compress.
    e.disk_bytes = frames as u64 * pixels * 3;
    e
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::dataset::synthetic::BallScene;

    #[test]
    fn parameter_counts_match_the_built_models() {
        let ds = BallScene { size: 8, views: 2, ..Default::default() }.dataset();
        for name in crate::engine::models::config::trainable_presets() {
            let c = ModelConfig::preset(name).unwrap();
            let m = c.build(ds.scene(), 1).unwrap();
            let e = training(&c, DataSize::uniform(2, 8, 8), 2);
            assert_eq!(e.params, m.params().len() as u64, "{name}");
        }
    }

    #[test]
    fn parts_add_up_and_grow_with_what_they_count() {
        let c = ModelConfig::preset("instant").unwrap();
        let small = training(&c, DataSize::uniform(10, 100, 100), 2);
        assert_eq!(small.memory_bytes, small.parts.iter().map(|p| p.1).sum::<u64>());
        assert!(small.parts.windows(2).all(|w| w[0].1 >= w[1].1), "largest first: {:?}", small.parts);
        // The dataset part is exactly its RGBA bytes.
        let more_data = training(&c, DataSize::uniform(20, 100, 100), 2);
        assert_eq!(more_data.memory_bytes - small.memory_bytes, 10 * 100 * 100 * 4);
        // A thread more adds one gradient buffer (and may add activations).
        let more_threads = training(&c, DataSize::uniform(10, 100, 100), 3);
        assert!(more_threads.memory_bytes >= small.memory_bytes + small.params * 4);
        // The checkpoint holds parameters and both moments.
        assert!(small.disk_bytes >= 3 * small.params * 4);
    }

    #[test]
    fn masks_count_a_byte_per_pixel_and_the_inside_lists_four() {
        let mut ds = BallScene { size: 8, views: 4, ..Default::default() }.dataset();
        let plain = DataSize::of(&ds);
        assert_eq!(plain, DataSize::uniform(8, 8, 8));
        // Masks on every frame, 10 pixels inside each.
        for f in &mut ds.frames {
            f.mask = Some((0..64).map(|p| if p < 10 { 255 } else { 0 }).collect());
        }
        ds.masks = MaskUse::Score;
        let scored = DataSize::of(&ds);
        assert_eq!((scored.mask_pixels, scored.inside_pixels), (8 * 64, 0));
        ds.masks = MaskUse::Ignore;
        let ignored = DataSize::of(&ds);
        assert_eq!((ignored.mask_pixels, ignored.inside_pixels), (8 * 64, 4 * 10));
        // The trainer's lists are exactly what the estimate counts.
        let pool = crate::engine::train::pixels::PixelPool::new(&ds);
        assert_eq!(pool.bytes(), ignored.inside_pixels * INSIDE_BYTES);
        let c = ModelConfig::preset("instant").unwrap();
        let (a, b) = (training(&c, plain, 2), training(&c, ignored, 2));
        assert_eq!(b.memory_bytes - a.memory_bytes, 8 * 64 + 4 * 10 * 4);
        assert!(b.parts.iter().any(|(k, v)| k == "masks" && *v == 8 * 64), "{:?}", b.parts);
    }

    #[test]
    fn the_twelve_gigabyte_config_of_issue_14_is_seen_as_such() {
        let ModelConfig::Instant(mut c) = ModelConfig::preset("instant").unwrap() else { unreachable!() };
        c.grid.levels = 32;
        c.grid.log2_table = 24;
        c.grid.finest_resolution = 8192;
        c.hidden = 256;
        c.geo_features = 64;
        c.samples_per_step = 1 << 20;
        c.chunk_rays = 4096;
        let e = training(&ModelConfig::Instant(c), DataSize::uniform(100, 200, 200), 2);
        // 32 levels of up to 2^24 entries of 2 features (the coarse ones are
        // dense and smaller): 651 M parameters, 2.4 GiB, times
        // (1 + 2 + 3 + 2 + 3) for the copies training keeps: more than
        // this 24 GiB machine has.
        assert!(e.params > 600_000_000, "{}", e.params);
        assert!(e.memory_bytes > 24 << 30, "{}", e.describe());
    }
}
