//! The real-capture model's configuration (`models::capture`): every
//! tunable a scalar, so `--set key=value` reaches each; the checks that
//! name each field out of range; presets; and what the kind provides the
//! engine through [`ModelSpec`] (building, Adam, the memory footprint).

use super::{CaptureModel, KIND, layout};
use crate::engine::fields::space::{NdcFrame, Norm};
use crate::engine::geometry::scene::Scene;
use crate::engine::models::spec::{Checks, FieldValue, Footprint, ModelSpec};
use crate::engine::models::{Model, ModelError};
use crate::engine::nn::adam::AdamConfig;
use crate::engine::nn::hashgrid::{HashGrid, HashGridConfig};
use crate::engine::nn::linear::ParamLayout;
use crate::engine::nn::sh;
use crate::engine::sampling::proposal::{Anneal, ProposalError, Resampling};

/// The proposal networks and how their weights place the next level.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ProposalConfig {
    /// Intervals per ray of the first level, stratified in `s` (64).
    pub coarse_samples: usize,
    /// Intervals of the second level, drawn from the first's weights (32);
    /// 0: one proposal level only.
    pub fine_samples: usize,
    /// The first network's hash grid (5 levels, 2^15, 16 to 128).
    pub coarse_grid: HashGridConfig,
    /// The second network's (5 levels, 2^15, 16 to 256).
    pub fine_grid: HashGridConfig,
    /// Hidden width of both networks (16).
    pub hidden: usize,
    /// Added to every weight before drawing the next level (0.01,
    /// nerfacto's `histogram_padding`): no interval becomes unreachable.
    pub padding: f32,
    /// Steps over which the weights' exponent rises from 0 to 1 (500).
    pub anneal_steps: u64,
    /// How fast it rises at first (10).
    pub anneal_slope: f32,
}

/// Which map takes model space into the grids' cube (design section 2.3).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Space {
    /// Scene contraction (of norm `contraction`): all of space, for
    /// captures seen from any side.
    #[default]
    Contract,
    /// NDC of the training cameras' mean pose: their frustum from the
    /// dataset's near bound to infinity, depth spent as disparity. For
    /// forward-facing captures only (LLFF's); a model refuses others.
    Ndc,
}

/// The real-capture model's configuration: every tunable is a scalar, so
/// `--set key=value` reaches each.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CaptureConfig {
    /// The space the grids live in: `contract` (the default) or `ndc`.
    /// Configurations from before it existed read `contract`.
    #[serde(default)]
    pub space: Space,
    /// With `space: ndc`, the reference camera in model units: not a
    /// setting, but derived from the training cameras when a model is built
    /// (`space::resolve`) and stored with its configuration, so a
    /// checkpoint reloads, resumes and renders with the map it was trained
    /// with. `None` (and not written) otherwise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ndc_camera: Option<NdcFrame>,
    /// The norm of the scene contraction: `linf` (the whole grid cube is
    /// used) or `l2`.
    pub contraction: Norm,
    /// Model units from the focus to the cameras (their median distance):
    /// the unit cube around the focus, which the contraction leaves as it
    /// is, reaches that far (1).
    pub camera_radius: f32,
    /// The ray interval in model units (0.05 to 1000). With
    /// `near_from_data`, `near` rises to the dataset's near bound when the
    /// model is built, and the checkpoint stores the result. With `space:
    /// contract`, a ray starting nearer the focus than `camera_radius`
    /// starts nearer in proportion, no nearer than 0.05
    /// (`capture_pass::RayInterval`).
    pub near: f32,
    pub far: f32,
    /// Whether the ray interval starts no nearer than the dataset's near
    /// bound where it has one (LLFF's `poses_bounds.npy`, and for a COLMAP
    /// model 0.9 times the nearest depth at which a camera sees its sparse
    /// points; with `space: contract` only, NDC has its own near plane).
    /// It acts when a model is built: `near` is raised then, and a
    /// checkpoint (or a model's stored configuration) holds the raised
    /// value. Close-ups keep their subject (`near` above). On by default
    /// (also when a configuration omits it): measured on the 2-core VM,
    /// `train --steps 4000`, gold_cape's held-out PSNR (nearest appearance)
    /// rose from 21.16 / 21.25 dB (seeds 0 / 1, near 0.05) to 21.29 / 21.35
    /// at its bound (0.38 model units); near 0.2 gave 21.37 / 21.25, 0.4
    /// 21.36 / 21.47, and 0.6 20.85 (it cuts into the scene). Space near a
    /// camera that no photo shows anything in is where floaters grow. Off,
    /// `near` is used as set.
    #[serde(default = "yes")]
    pub near_from_data: bool,
    /// The main hash grid (16 levels, 2^16, 16 to 2048: the contraction
    /// spends most of the cube on the background, so the finest level is
    /// finer than the fast model's).
    pub grid: HashGridConfig,
    /// Hidden width of both MLPs (32; nerfacto's 64 costs 2.5 times the
    /// multiply-adds per sample: on gold_cape after 1200 steps 32 scored as
    /// 64 did (19.19 against 19.20 dB), on fox after 1000 steps 0.1 dB
    /// below (27.02 against 27.13), for a fifth less CPU time per step).
    pub hidden: usize,
    /// Outputs of the density MLP: log-density and geometry features (16).
    pub geo_features: usize,
    /// Density of the untrained field (1). nerfacto starts nearly
    /// transparent (0.01) for fewer early floaters over its 30k steps; in
    /// the few thousand steps of a CPU budget, a field that starts
    /// transparent explains the photos by what it paints far away (the
    /// opaque last interval) before it builds the foreground, and generalises
    /// worse: on `tests/train_capture.rs`'s scene, `capture-tiny` reaches
    /// 15.5/13.9/15.2 dB held out (seeds 1-3) from 0.01, 19.8/19.4/17.6
    /// from 0.1 and 21.6/20.7/19.1 from 1. To be measured on real captures.
    pub init_density: f32,
    /// Values of each image's appearance embedding (16; 0: none).
    pub appearance_dim: usize,
    /// Images with an embedding (2000, `radiance poses`' limit); frames
    /// beyond it are trained with a zero embedding.
    pub max_images: usize,
    pub proposal: ProposalConfig,
    /// Main-field samples (final intervals) per ray (24). Measured on this
    /// project's 2-core VM, 120 s of training, against 32: the same
    /// held-out PSNR within run-to-run noise (fox 31.06 against 30.88 dB,
    /// fern 25.46 against 25.56, gold_cape (2^18 table) 21.17 against
    /// 21.21) for 12-15% less time per view (546/800/869 against
    /// 617/929/1023 ms) and 10-12% more steps.
    pub samples: usize,
    /// Rays per training step (1024).
    pub rays_per_step: usize,
    /// Training rays processed together by one thread (256).
    pub chunk_rays: usize,
    /// Weight of the interlevel loss, the proposals' training signal (1).
    pub interlevel: f32,
    /// Weight of the distortion loss (0.002; 0.004 in the `capture-360` preset).
    pub distortion: f32,
    /// Transmittance below which rendering stops, and behind which
    /// training skips a ray's samples (1e-4).
    pub min_transmittance: f32,
    /// Weight per ray that rendering may leave uncoloured (1e-3).
    pub max_dropped_weight: f32,
    /// Whether each training image's camera pose is refined (design 2.7:
    /// six parameters per image, `max_images` rows after the networks'),
    /// off by default: measured on the 2-core VM (hidden 32, seed 0, 5
    /// held-out views), refinement lowered held-out PSNR on fox (1000
    /// steps: 25.30 dB against 27.02 off) and gold_cape (1200 steps: 18.82
    /// against 19.55): at these short budgets the corrections move (0.3 deg
    /// mean on gold_cape) while the field is still forming. `--set
    /// pose_refine=true` turns it on. Off, the model is the one of before
    /// pose refinement, bit for bit (and checkpoints from before it read
    /// as off).
    #[serde(default)]
    pub pose_refine: bool,
    /// The pose corrections' learning rate as a fraction of the networks'
    /// (0.1: 1e-3 decaying to 3e-4; nerfacto's `camera_opt` decays
    /// to 1e-4).
    #[serde(default = "default_pose_lr_scale")]
    pub pose_lr_scale: f32,
    /// Whether rendering reads the main hash grid from a copy of its table
    /// in half precision (true; `HashGrid::half_table`): half the memory
    /// traffic of the gathers, and the same held-out PSNR to 0.01 dB on
    /// the benchmark scenes. Training always uses f32. Checkpoints from
    /// before it read true.
    #[serde(default = "yes")]
    pub half_render: bool,
}

/// The learning rate at the end of training ([`ModelSpec::adam`]).
const LR_END: f32 = 3e-3;

fn yes() -> bool {
    true
}

/// [`CaptureConfig::pose_lr_scale`]'s default.
fn default_pose_lr_scale() -> f32 {
    0.1
}

impl Default for CaptureConfig {
    fn default() -> Self {
        Self {
            space: Space::Contract,
            ndc_camera: None,
            contraction: Norm::Linf,
            camera_radius: 1.0,
            near: 0.05,
            far: 1000.0,
            near_from_data: true,
            grid: HashGridConfig { levels: 16, log2_table: 16, base_resolution: 16, finest_resolution: 2048 },
            hidden: 32,
            geo_features: 16,
            init_density: 1.0,
            appearance_dim: 16,
            max_images: 2000,
            proposal: ProposalConfig {
                coarse_samples: 64,
                fine_samples: 32,
                coarse_grid: HashGridConfig { levels: 5, log2_table: 15, base_resolution: 16, finest_resolution: 128 },
                fine_grid: HashGridConfig { levels: 5, log2_table: 15, base_resolution: 16, finest_resolution: 256 },
                hidden: 16,
                padding: 0.01,
                anneal_steps: 500,
                anneal_slope: 10.0,
            },
            samples: 24,
            rays_per_step: 1024,
            chunk_rays: 256,
            interlevel: 1.0,
            distortion: 0.002,
            min_transmittance: 1e-4,
            max_dropped_weight: 1e-3,
            pose_refine: false,
            pose_lr_scale: default_pose_lr_scale(),
            half_render: true,
        }
    }
}

impl CaptureConfig {
    /// A small model for previews and tests: 8 grid levels up to 256,
    /// narrow MLPs, proposals of 16 and 8 intervals and 8 final samples;
    /// no pose refinement (the tests that want it turn it on).
    pub fn tiny() -> Self {
        let d = Self::default();
        Self {
            grid: HashGridConfig { levels: 8, log2_table: 12, base_resolution: 8, finest_resolution: 256 },
            hidden: 32,
            geo_features: 8,
            appearance_dim: 8,
            proposal: ProposalConfig {
                coarse_samples: 16,
                fine_samples: 8,
                coarse_grid: HashGridConfig { levels: 4, log2_table: 12, base_resolution: 8, finest_resolution: 64 },
                fine_grid: HashGridConfig { levels: 4, log2_table: 12, base_resolution: 8, finest_resolution: 128 },
                hidden: 16,
                ..d.proposal
            },
            samples: 8,
            rays_per_step: 512,
            chunk_rays: 128,
            pose_refine: false,
            ..d
        }
    }

    /// Intervals per ray at each proposal level, then the final level.
    pub(super) fn intervals(&self) -> Vec<usize> {
        let p = &self.proposal;
        let mut v = vec![p.coarse_samples];
        if p.fine_samples > 0 {
            v.push(p.fine_samples);
        }
        v.push(self.samples);
        v
    }

    /// The weights' exponent and padding at training step `step`.
    pub(super) fn resampling(&self, step: u64) -> Result<Resampling, ProposalError> {
        let p = &self.proposal;
        Resampling::new(Anneal::new(p.anneal_steps, p.anneal_slope)?.exponent(step), p.padding)
    }
}

/// Records a float field that must be finite and positive.
fn positive(c: &mut Checks, field: &'static str, value: f32, allowed: &str) {
    if !(value.is_finite() && value > 0.0) {
        c.fail(field, FieldValue::Float(value), allowed.into());
    }
}

/// Records a float field that must be finite and not negative.
fn non_negative(c: &mut Checks, field: &'static str, value: f32) {
    if !(value.is_finite() && value >= 0.0) {
        c.fail(field, FieldValue::Float(value), "a finite number >= 0".into());
    }
}

/// A hash grid's fields, named by `names` (levels, log2_table,
/// base_resolution, finest_resolution).
fn check_grid(c: &mut Checks, g: &HashGridConfig, names: [&'static str; 4]) {
    c.int(names[0], g.levels, 1..=32);
    c.int(names[1], g.log2_table, 8..=24);
    c.int(names[2], g.base_resolution, 2..=4096);
    c.int(names[3], g.finest_resolution, u64::from(g.base_resolution)..=8192);
}

impl ModelSpec for CaptureConfig {
    fn kind(&self) -> &'static str {
        KIND
    }

    fn check(&self, c: &mut Checks) {
        positive(c, "camera_radius", self.camera_radius, "a finite number > 0");
        positive(c, "near", self.near, "a finite number > 0");
        // Beyond the near bound (beyond 0 when that is itself refused, so
        // each message names one field).
        let floor = if self.near.is_finite() && self.near > 0.0 { self.near } else { 0.0 };
        if !(self.far.is_finite() && self.far > floor) {
            c.fail("far", FieldValue::Float(self.far), format!("a finite number > {floor}"));
        }
        check_grid(c, &self.grid, ["grid.levels", "grid.log2_table", "grid.base_resolution", "grid.finest_resolution"]);
        c.int("hidden", self.hidden, 1..=256);
        c.int("geo_features", self.geo_features, 1..=64);
        positive(c, "init_density", self.init_density, "a finite number > 0");
        c.int("appearance_dim", self.appearance_dim, 0..=64);
        c.int("max_images", self.max_images, 1..=100_000);
        let p = &self.proposal;
        c.int("proposal.coarse_samples", p.coarse_samples, 1..=1024);
        c.int("proposal.fine_samples", p.fine_samples, 0..=1024);
        let coarse = ["proposal.coarse_grid.levels", "proposal.coarse_grid.log2_table"];
        let coarse_res = ["proposal.coarse_grid.base_resolution", "proposal.coarse_grid.finest_resolution"];
        check_grid(c, &p.coarse_grid, [coarse[0], coarse[1], coarse_res[0], coarse_res[1]]);
        let fine = ["proposal.fine_grid.levels", "proposal.fine_grid.log2_table"];
        let fine_res = ["proposal.fine_grid.base_resolution", "proposal.fine_grid.finest_resolution"];
        check_grid(c, &p.fine_grid, [fine[0], fine[1], fine_res[0], fine_res[1]]);
        c.int("proposal.hidden", p.hidden, 1..=256);
        non_negative(c, "proposal.padding", p.padding);
        positive(c, "proposal.anneal_slope", p.anneal_slope, "a finite number > 0");
        c.int("samples", self.samples, 1..=1024);
        c.int("rays_per_step", self.rays_per_step, 1..=(1 << 16));
        c.int("chunk_rays", self.chunk_rays, 1..=4096);
        non_negative(c, "interlevel", self.interlevel);
        non_negative(c, "distortion", self.distortion);
        c.unit_open("min_transmittance", self.min_transmittance);
        c.unit_open("max_dropped_weight", self.max_dropped_weight);
        non_negative(c, "pose_lr_scale", self.pose_lr_scale);
    }

    fn build(&self, scene: Scene, seed: u64) -> Result<Box<dyn Model>, ModelError> {
        Ok(Box::new(CaptureModel::new(self.clone(), scene, seed)?))
    }

    fn rebuild(&self, scene: Scene, params: Vec<f32>) -> Result<Box<dyn Model>, ModelError> {
        Ok(Box::new(CaptureModel::from_parts(self.clone(), scene, params)?))
    }

    /// Instant-NGP's (nerfacto's fields use the same 1e-2 and epsilon),
    /// but decaying to 3e-3 rather than 1e-3: a CPU budget is a few
    /// thousand steps, and the field is still learning at the end of it.
    /// Measured on the 2-core VM when `763a36c` made the change (`train
    /// --steps 4000` then `eval`, nearest camera's appearance): gold_cape
    /// 20.92 -> 21.16 dB (seed 0) and 20.82 -> 21.25 (seed 1), fox 30.31
    /// -> 30.39, fern 24.84 -> 24.85, SSIM higher on all four.
    fn adam(&self) -> AdamConfig {
        AdamConfig { lr: 1e-2, lr_end: LR_END, beta1: 0.9, beta2: 0.99, eps: 1e-15 }
    }

    /// Photographs are opaque: the last interval of every ray is too, and
    /// RGBA images are trained on the dataset's background.
    fn random_background(&self) -> bool {
        false
    }

    /// One training thread's chunk: `chunk_rays` rays (or fewer, when a
    /// step's rays split between the threads are fewer) with every level's
    /// samples, the networks' activations and gradients, and the pass's
    /// per-sample buffers. Rendering uses the same buffers, for fewer
    /// samples.
    fn footprint(&self, threads: u64) -> Footprint {
        let mut ps = ParamLayout::default();
        layout(&mut ps, self);
        // With pose refinement, each main sample's input gradients: grid
        // coordinates, SH code, position and direction.
        let pose = if self.pose_refine { 3 + sh::WIDTH as u64 + 3 + 3 } else { 0 };
        let rays = (self.chunk_rays as u64).min((self.rays_per_step as u64).div_ceil(threads.max(1))).max(1);
        let width = |g: &HashGridConfig| HashGrid::new(&mut ParamLayout::default(), g.clone()).width() as u64;
        // Samples (t, delta, position, direction) and edges in s and t,
        // twice: they are pushed, and a growing vector may hold up to twice
        // what it was given.
        let sample = 2 * (8 + 2);
        // Proposal: unit position, encoding and its gradient, hidden and its
        // gradient, raw and density, weight, dL/dw, dL/dsigma, colours (zero),
        // and the backward pass's index of the row (8 bytes).
        let proposal = |g: &HashGridConfig| sample + 3 + 2 * width(g) + 2 * self.proposal.hidden as u64 + 2 + 3 + 3 + 2;
        let p = &self.proposal;
        let mut per_ray = p.coarse_samples as u64 * proposal(&p.coarse_grid);
        if p.fine_samples > 0 {
            per_ray += p.fine_samples as u64 * proposal(&p.fine_grid);
        }
        let (h, g, gw) = (self.hidden as u64, self.geo_features as u64, width(&self.grid));
        // Main: as the fast model's sample (unit position, encoding,
        // hidden, features, density, SH code, two colour hiddens, colour;
        // their gradients), the image and its slot, and the pass's weight,
        // gradients, full weights and kept index.
        let main = sample + (3 + gw + h + g + 1 + sh::WIDTH as u64 + 2 * h + 3) + (3 + 2 * h + g + gw) + 2 + 8 + pose;
        per_ray += self.samples as u64 * main;
        // The main grid's deferred backward (without pose refinement): the
        // part's samples' positions and encoding gradients, in the thread's
        // record (up to twice what it was given: a growing vector), and the
        // thread's buffer for one level's gradient when it is scattered
        // (two features per entry, a level at most `2^log2_table` entries).
        let part_rays = (self.rays_per_step as u64).div_ceil(threads.max(1));
        let level = 2u64 << self.grid.log2_table.min(40);
        let record = if self.pose_refine { 0 } else { 2 * part_rays * self.samples as u64 * (3 + gw) + level };
        Footprint { params: ps.len as u64, occupancy_cells: 0, activations: rays * per_ray + record }
    }
}

/// This kind's presets, the default first.
pub const PRESETS: &[&str] = &["capture", "capture-360", "capture-tiny"];

/// A named configuration:
/// - `capture`: the real-capture model (photographs of unbounded scenes);
/// - `capture-360`: the same with 4x the hash table (2^18 entries per
///   level) and a finest level twice as fine (4096), for captures whose
///   cameras go all around the subject: they see more of the scene in
///   detail than a one-sided or forward-facing capture, and a 2^16 table
///   collides (gold_cape: +0.2 dB at equal CPU time; fox, one-sided,
///   loses 0.4 dB with it). The finest level, measured on the 2-core VM
///   with `train --steps 4000` (about the same time): gold_cape's
///   held-out PSNR 21.29 / 21.35 dB (seeds 0 / 1) at 2048, 21.40 / 21.48
///   at 4096 (SSIM 0.687 / 0.686 to 0.709 / 0.714, inside the masks
///   20.38 / 20.45 to 20.76 / 20.89 dB), 21.27 at 8192 (seed 0); on fox
///   4096 scored 30.22 against 30.39, on fern 24.94 against 24.92, so
///   `capture` keeps 2048. Its distortion weight is 0.004, twice
///   `capture`'s: gold_cape at `--steps 4000`, seeds 0-4, held-out PSNR
///   21.52 / 21.61 / 21.55 / 21.52 / 21.57 dB at 0.002 and 21.62 /
///   21.85 / 21.51 / 21.89 / 21.70 at 0.004 (mean +0.16; with the mean
///   appearance +0.28, higher on every seed; SSIM higher on every seed),
///   21.18 at 0.001, 21.44 at 0.008, 19.62 at 0.016 (seed 0); fox lost
///   0.07 and fern 0.11 with 0.004, so `capture` keeps 0.002;
/// - `capture-tiny`: a small one, for previews and tests.
pub fn preset(name: &str) -> Option<CaptureConfig> {
    match name {
        "capture" => Some(CaptureConfig::default()),
        "capture-360" => {
            let d = CaptureConfig::default();
            let grid = HashGridConfig { log2_table: 18, finest_resolution: 4096, ..d.grid };
            Some(CaptureConfig { grid, distortion: 0.004, ..d })
        }
        "capture-tiny" => Some(CaptureConfig::tiny()),
        _ => None,
    }
}
