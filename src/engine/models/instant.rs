//! The fast model: a multiresolution hash grid, a tiny density MLP and a
//! tiny colour MLP on spherical-harmonics directions (Instant-NGP), marched
//! with a constant step through the cells an occupancy grid marks occupied.
//!
//! What a scene does not need is skipped: rays are clipped to the scene box,
//! empty cells are stepped over, and when rendering the colour network runs
//! only on samples in front of the point where transmittance falls below
//! `min_transmittance`.

use rayon::prelude::*;

use crate::engine::geometry::math::{Ray, Vec3};
use crate::engine::geometry::scene::Scene;
use crate::engine::models::{BatchStats, Model, RayOutput, StepCtx, TrainRay};
use crate::engine::nn::hashgrid::{HashGrid, HashGridConfig};
use crate::engine::nn::linear::{Linear, ParamLayout, relu, relu_backward, sigmoid};
use crate::engine::nn::sh;
use crate::engine::render::composite::{composite, composite_backward};
use crate::engine::rng::Rng;
use crate::engine::sampling::occupancy::{OccupancyConfig, OccupancyGrid, Probe};

/// The fast model's configuration. `Default` is what `radiance train` uses.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct InstantConfig {
    pub grid: HashGridConfig,
    /// Hidden width of both MLPs (64).
    pub hidden: usize,
    /// Outputs of the density MLP: log-density and geometry features (16).
    pub geo_features: usize,
    pub occupancy: OccupancyConfig,
    /// Marching steps along the scene box's diagonal (384).
    pub steps_per_diagonal: usize,
    /// Upper bound of samples per ray.
    pub max_samples: usize,
    /// Network samples per training step; the number of rays adapts.
    pub samples_per_step: usize,
    /// Transmittance below which rendering stops (1e-4).
    pub min_transmittance: f32,
    /// Rendering skips the colour of samples whose weights, summed along a
    /// ray, stay below this (1e-3, a quarter of an 8-bit step): a pixel
    /// changes by at most this much.
    #[serde(default = "default_max_dropped_weight")]
    pub max_dropped_weight: f32,
    /// Training rays processed together by one thread (256: enough samples
    /// that each hash-grid level's table is reused from cache while all of
    /// them visit it).
    pub chunk_rays: usize,
}

impl Default for InstantConfig {
    fn default() -> Self {
        Self {
            grid: HashGridConfig::default(),
            hidden: 64,
            geo_features: 16,
            occupancy: OccupancyConfig {
                resolution: 128,
                threshold: 0.0, // set from the step size in `InstantModel::new`
                decay: 0.95,
                update_every: 16,
                sweep: 8,
                warmup_steps: 32,
                full_updates_until: 128,
                empty_sweep: 64,
                // Decided from the scene in `InstantModel::new`.
                dilate: None,
            },
            steps_per_diagonal: 384,
            max_samples: 1024,
            samples_per_step: 1 << 14,
            min_transmittance: 1e-4,
            max_dropped_weight: default_max_dropped_weight(),
            chunk_rays: 256,
        }
    }
}

fn default_max_dropped_weight() -> f32 {
    1e-3
}

thread_local! {
    /// Each worker thread's activation and sample buffers, kept across
    /// steps and views: fresh ones cost page faults and zero-filling every
    /// step (about 6% of training time in the profile).
    static SCRATCH: std::cell::RefCell<(Ctx, Marched)> = std::cell::RefCell::new(Default::default());
}

/// Runs `f` with this thread's scratch buffers (fresh ones if they are in
/// use further up the stack).
fn with_scratch<R>(f: impl FnOnce(&mut Ctx, &mut Marched) -> R) -> R {
    SCRATCH.with(|s| match s.try_borrow_mut() {
        Ok(mut s) => {
            let (c, m) = &mut *s;
            f(c, m)
        }
        Err(_) => f(&mut Ctx::default(), &mut Marched::default()),
    })
}

/// Rays rendered together by one thread (in rounds of samples).
const RENDER_CHUNK_RAYS: usize = 256;

/// Density activation: `exp` of the clamped input (its derivative is the
/// density itself, which stays finite).
#[inline]
fn density(raw: f32) -> f32 {
    raw.clamp(-15.0, 15.0).exp()
}

/// The networks over a flat parameter buffer.
struct Nets {
    grid: HashGrid,
    d1: Linear,
    d2: Linear,
    c1: Linear,
    c2: Linear,
    c3: Linear,
}

/// Activations of a forward pass over `n` samples.
#[derive(Default)]
struct Ctx {
    n: usize,
    unit: Vec<f32>,
    enc: Vec<f32>,
    h1: Vec<f32>,
    geo: Vec<f32>,
    sigma: Vec<f32>,
    shd: Vec<f32>,
    a1: Vec<f32>,
    a2: Vec<f32>,
    rgb: Vec<f32>,
    // backward scratch
    d_a: Vec<f32>,
    d_b: Vec<f32>,
    d_geo: Vec<f32>,
    d_enc: Vec<f32>,
}

/// Makes `v` hold at least `n` values. Buffers never shrink, so reusing
/// one for chunks of varying size does not zero-fill it again (that was 4%
/// of training time); readers take the first `ctx.n` rows.
fn size(v: &mut Vec<f32>, n: usize) {
    if v.len() < n {
        v.resize(n, 0.0);
    }
}

/// Moves rows `keep` (sorted) of a row-major buffer with `width` columns
/// to its front (the rows after them are stale).
fn move_rows(v: &mut [f32], width: usize, keep: &[usize]) {
    for (dst, &src) in keep.iter().enumerate() {
        if dst != src {
            v.copy_within(src * width..(src + 1) * width, dst * width);
        }
    }
}

/// Keeps rows `keep` (sorted) of a row-major buffer with `width` columns.
fn gather_rows(v: &mut Vec<f32>, width: usize, keep: &[usize]) {
    move_rows(v, width, keep);
    v.truncate(keep.len() * width);
}

/// Indices of the samples in front of the point where each ray's
/// transmittance falls below `min_t` (from the densities alone).
fn visible(spans: &[(usize, usize)], sigma: &[f32], delta: &[f32], min_t: f32, keep: &mut Vec<usize>) {
    keep.clear();
    for &(o, k) in spans {
        let mut tau = 0.0f32;
        for i in o..o + k {
            if (-tau).exp() < min_t {
                break;
            }
            keep.push(i);
            tau += crate::engine::render::composite::optical_depth(sigma[i], delta[i]);
        }
    }
}

impl Ctx {
    /// Drops the density-pass activations of samples not in `keep`.
    fn compact(&mut self, keep: &[usize], grid_width: usize, hidden: usize, geo: usize) {
        move_rows(&mut self.unit, 3, keep);
        move_rows(&mut self.enc, grid_width, keep);
        move_rows(&mut self.h1, hidden, keep);
        move_rows(&mut self.geo, geo, keep);
        move_rows(&mut self.sigma, 1, keep);
        self.n = keep.len();
    }
}

impl Marched {
    /// Keeps samples `keep` (sorted), updating each ray's span.
    fn compact(&mut self, keep: &[usize]) {
        let mut j = 0;
        for span in &mut self.spans {
            let (o, k) = *span;
            let start = j;
            while j < keep.len() && keep[j] < o + k {
                j += 1;
            }
            *span = (start, j - start);
        }
        gather_rows(&mut self.t, 1, keep);
        gather_rows(&mut self.delta, 1, keep);
        gather_rows(&mut self.dirs, 3, keep);
    }
}

impl Nets {
    fn new(layout: &mut ParamLayout, c: &InstantConfig) -> Self {
        let grid = HashGrid::new(layout, c.grid.clone());
        let d1 = Linear::new(layout, "density.0", grid.width(), c.hidden);
        let d2 = Linear::new(layout, "density.1", c.hidden, c.geo_features);
        let c1 = Linear::new(layout, "color.0", c.geo_features + sh::WIDTH, c.hidden);
        let c2 = Linear::new(layout, "color.1", c.hidden, c.hidden);
        let c3 = Linear::new(layout, "color.2", c.hidden, 3);
        Self { grid, d1, d2, c1, c2, c3 }
    }

    /// Density of `n` unit-cube points; keeps what backward needs.
    fn forward_density(&self, p: &[f32], ctx: &mut Ctx) {
        let n = ctx.n;
        let (gw, h, g) = (self.grid.width(), self.d1.outputs, self.d2.outputs);
        size(&mut ctx.enc, n * gw);
        self.grid.forward(p, &ctx.unit[..n * 3], &mut ctx.enc);
        size(&mut ctx.h1, n * h);
        self.d1.forward(p, &[(&ctx.enc, gw)], n, &mut ctx.h1);
        relu(&mut ctx.h1[..n * h]);
        size(&mut ctx.geo, n * g);
        self.d2.forward(p, &[(&ctx.h1, h)], n, &mut ctx.geo);
        size(&mut ctx.sigma, n);
        for (s, row) in ctx.sigma[..n].iter_mut().zip(ctx.geo.chunks_exact(g)) {
            *s = density(row[0]);
        }
    }

    /// Colour of the first `n` samples of the last density pass, seen along
    /// `dirs` (`[n x 3]`).
    fn forward_color(&self, p: &[f32], dirs: &[f32], ctx: &mut Ctx) {
        let n = ctx.n;
        let (h, g) = (self.c1.outputs, self.d2.outputs);
        size(&mut ctx.shd, n * sh::WIDTH);
        sh::encode(&dirs[..n * 3], &mut ctx.shd);
        size(&mut ctx.a1, n * h);
        self.c1.forward(p, &[(&ctx.geo, g), (&ctx.shd, sh::WIDTH)], n, &mut ctx.a1);
        relu(&mut ctx.a1[..n * h]);
        size(&mut ctx.a2, n * h);
        self.c2.forward(p, &[(&ctx.a1, h)], n, &mut ctx.a2);
        relu(&mut ctx.a2[..n * h]);
        size(&mut ctx.rgb, n * 3);
        self.c3.forward(p, &[(&ctx.a2, h)], n, &mut ctx.rgb);
        for v in &mut ctx.rgb[..n * 3] {
            *v = sigmoid(*v);
        }
    }

    /// Backward of both passes given dL/dsigma and dL/drgb.
    fn backward(&self, p: &[f32], ctx: &mut Ctx, dsigma: &[f32], drgb: &[f32], grads: &mut [f32]) {
        let n = ctx.n;
        let (h, g, gw) = (self.c1.outputs, self.d2.outputs, self.grid.width());
        let draw: Vec<f32> = drgb[..n * 3].iter().zip(&ctx.rgb).map(|(&d, &s)| d * s * (1.0 - s)).collect();
        size(&mut ctx.d_a, n * h);
        self.c3.backward(p, &[(&ctx.a2, h)], &draw, n, grads, &mut [Some(&mut ctx.d_a)]);
        relu_backward(&ctx.a2[..n * h], &mut ctx.d_a[..n * h]);
        size(&mut ctx.d_b, n * h);
        self.c2.backward(p, &[(&ctx.a1, h)], &ctx.d_a, n, grads, &mut [Some(&mut ctx.d_b)]);
        relu_backward(&ctx.a1[..n * h], &mut ctx.d_b[..n * h]);
        size(&mut ctx.d_geo, n * g);
        self.c1.backward(
            p,
            &[(&ctx.geo, g), (&ctx.shd, sh::WIDTH)],
            &ctx.d_b,
            n,
            grads,
            &mut [Some(&mut ctx.d_geo), None],
        );
        for ((row, &ds), &s) in ctx.d_geo.chunks_exact_mut(g).zip(dsigma).zip(&ctx.sigma) {
            row[0] += ds * s;
        }
        size(&mut ctx.d_a, n * h);
        self.d2.backward(p, &[(&ctx.h1, h)], &ctx.d_geo, n, grads, &mut [Some(&mut ctx.d_a)]);
        relu_backward(&ctx.h1[..n * h], &mut ctx.d_a[..n * h]);
        size(&mut ctx.d_enc, n * gw);
        self.d1.backward(p, &[(&ctx.enc, gw)], &ctx.d_a, n, grads, &mut [Some(&mut ctx.d_enc)]);
        self.grid.backward(&ctx.unit[..n * 3], &ctx.d_enc, grads);
    }
}

/// The fast model.
pub struct InstantModel {
    pub config: InstantConfig,
    scene: Scene,
    nets: Nets,
    params: Vec<f32>,
    pub grid: OccupancyGrid,
    /// Running mean of samples per training ray (sets the batch size).
    samples_per_ray: f64,
    dt: f32,
}

/// Samples of a chunk of rays, packed flat.
#[derive(Default)]
struct Marched {
    /// per ray: first sample and count
    spans: Vec<(usize, usize)>,
    t: Vec<f32>,
    delta: Vec<f32>,
    dirs: Vec<f32>,
    skipped: u64,
}

/// Lays out the fast model's parameters for `config` (without allocating
/// them): what [`InstantModel::new`] allocates.
pub fn layout(layout: &mut ParamLayout, config: &InstantConfig) {
    Nets::new(layout, config);
}

impl InstantModel {
    pub fn new(mut config: InstantConfig, scene: Scene, seed: u64) -> Self {
        let mut layout = ParamLayout::default();
        let nets = Nets::new(&mut layout, &config);
        let mut params = vec![0.0; layout.len];
        let mut rng = Rng::new(seed);
        nets.grid.init(&mut params, &mut rng);
        for l in [&nets.d1, &nets.d2, &nets.c1, &nets.c2, &nets.c3] {
            l.init(&mut params, &mut rng);
        }
        let aabb = scene.aabb();
        let dt = (aabb.max - aabb.min).norm() / config.steps_per_diagonal.max(1) as f32;
        if config.occupancy.threshold <= 0.0 {
            // Empty: less than 1% opacity over one marching step.
            config.occupancy.threshold = 0.01 / dt;
        }
        if config.occupancy.dilate.is_none() {
            // The marcher tests each sample's own cell, so dilation only adds
            // a shell of cells the threshold called empty. Where transparent
            // training pixels teach that the space around the object is
            // empty, skipping that shell is both faster and sharper (lego,
            // 60 s: 30.4 dB and 15 samples per ray, against 29.6 dB and 22);
            // a capture without them may need faint density in that shell
            // to explain its background (fox: 22.0 dB undilated, 24.0 dB
            // dilated), so it keeps it.
            config.occupancy.dilate = Some(!scene.transparent);
        }
        let grid = OccupancyGrid::new(config.occupancy.clone(), aabb);
        let spr = 64.0;
        Self { config, scene, nets, params, grid, samples_per_ray: spr, dt }
    }

    pub fn from_parts(config: InstantConfig, scene: Scene, params: Vec<f32>) -> Result<Self, String> {
        let m = Self::new(config, scene, 0);
        if params.len() != m.params.len() {
            return Err(format!("expected {} parameters, found {}", m.params.len(), params.len()));
        }
        Ok(Self { params, ..m })
    }

    /// Restores the occupancy grid and batch-size state from a checkpoint.
    pub fn set_state(&mut self, density: Vec<f32>, samples_per_ray: f64, step: u64) -> Result<(), String> {
        if density.len() != self.grid.density.len() {
            return Err(format!("occupancy grid has {} cells, expected {}", density.len(), self.grid.density.len()));
        }
        self.grid.density = density;
        self.grid.apply(step, &[], &[]);
        if samples_per_ray.is_finite() && samples_per_ray > 0.0 {
            self.samples_per_ray = samples_per_ray;
        }
        Ok(())
    }

    pub fn samples_per_ray(&self) -> f64 {
        self.samples_per_ray
    }

    /// Samples along each ray at a constant step through occupied cells.
    fn march(&self, rays: &[Ray], mut rng: Option<&mut Rng>, m: &mut Marched) {
        m.spans.clear();
        m.t.clear();
        m.delta.clear();
        m.dirs.clear();
        m.skipped = 0;
        for ray in rays {
            let start = m.t.len();
            if let Some((t0, t1)) = self.scene.clip(ray) {
                let jitter = rng.as_deref_mut().map_or(0.5, |r| r.f32());
                let mut t = t0 + jitter * self.dt;
                self.march_segment(ray, &mut t, t1, self.config.max_samples, m);
            }
            m.spans.push((start, m.t.len() - start));
        }
    }

    /// Appends up to `limit` samples of `ray` from `t` on (stepping over
    /// empty cells) and advances `t` past them.
    fn march_segment(&self, ray: &Ray, t: &mut f32, t1: f32, limit: usize, m: &mut Marched) -> usize {
        let (dt, dir) = (self.dt, [ray.dir.x, ray.dir.y, ray.dir.z]);
        let gr = self.grid.grid_ray(ray);
        let (count, skipped) = self.grid.march(&gr, t, t1, dt, limit, |t| {
            m.t.push(t);
            m.delta.push(dt);
            m.dirs.extend_from_slice(&dir);
        });
        m.skipped += skipped;
        count
    }

    /// Unit-cube coordinates of the samples (one span per ray).
    fn unit_points(&self, rays: &[Ray], m: &Marched, out: &mut Vec<f32>) {
        self.unit_points_of(rays, 0..rays.len(), m, out);
    }

    fn train_chunk(
        &self,
        rays: &[TrainRay],
        ctx: &StepCtx,
        grads: &mut [f32],
        c: &mut Ctx,
        m: &mut Marched,
    ) -> BatchStats {
        let mut stats = BatchStats { rays: rays.len() as u64, ..Default::default() };
        let plain: Vec<Ray> = rays.iter().map(|r| r.ray).collect();
        let mut rng = Rng::stream(ctx.seed, ctx.step, rays.first().map_or(0, |r| r.index));
        self.march(&plain, Some(&mut rng), m);
        self.unit_points(&plain, m, &mut c.unit);
        let n = m.t.len();
        c.n = n;
        stats.samples = n as u64;
        stats.skipped = m.skipped;
        if n > 0 {
            self.nets.forward_density(&self.params, c);
            // Samples behind the point where transmittance falls below the
            // threshold contribute less than it: skip their colour and backward.
            let mut keep = Vec::with_capacity(n);
            visible(&m.spans, &c.sigma, &m.delta, self.config.min_transmittance, &mut keep);
            if keep.len() < n {
                stats.skipped += (n - keep.len()) as u64;
                c.compact(&keep, self.nets.grid.width(), self.nets.d1.outputs, self.nets.d2.outputs);
                m.compact(&keep);
            }
            self.nets.forward_color(&self.params, &m.dirs, c);
        }
        let n = m.t.len();
        let scale = 1.0 / (ctx.batch_rays.max(1) as f32 * 3.0);
        let mut weights = vec![0.0f32; n];
        let mut dsigma = vec![0.0f32; n];
        let mut drgb = vec![0.0f32; 3 * n];
        for (r, &(o, k)) in rays.iter().zip(&m.spans) {
            let sig = &c.sigma[o..o + k];
            let rgb = &c.rgb[3 * o..3 * (o + k)];
            let (t, d) = (&m.t[o..o + k], &m.delta[o..o + k]);
            let comp = composite(sig, rgb, t, d, r.background, 0.0, &mut weights[o..o + k]);
            let err = [comp.rgb[0] - r.target[0], comp.rgb[1] - r.target[1], comp.rgb[2] - r.target[2]];
            let sq = err.iter().map(|e| (*e as f64).powi(2)).sum::<f64>() / 3.0;
            stats.sq_err += sq;
            stats.loss += sq;
            if k > 0 {
                let g = [2.0 * scale * err[0], 2.0 * scale * err[1], 2.0 * scale * err[2]];
                composite_backward(
                    sig,
                    rgb,
                    t,
                    d,
                    &weights[o..o + k],
                    r.background,
                    comp.used,
                    g,
                    0.0,
                    &mut dsigma[o..o + k],
                    &mut drgb[3 * o..3 * (o + k)],
                );
            }
        }
        if n > 0 {
            self.nets.backward(&self.params, c, &dsigma, &drgb, grads);
        }
        stats
    }

    /// Densities at model-space points (for the occupancy grid).
    fn densities(&self, pts: &[f32]) -> Vec<f32> {
        const CHUNK: usize = 4096;
        let lo = Vec3::from_array(self.scene.aabb_min);
        let ext = Vec3::from_array(self.scene.aabb_max) - lo;
        let mut out = vec![0.0f32; pts.len() / 3];
        out.par_chunks_mut(CHUNK).zip(pts.par_chunks(3 * CHUNK)).for_each(|(o, p)| {
            let mut c = Ctx { n: o.len(), ..Default::default() };
            c.unit = p
                .chunks_exact(3)
                .flat_map(|q| [(q[0] - lo.x) / ext.x, (q[1] - lo.y) / ext.y, (q[2] - lo.z) / ext.z])
                .collect();
            self.nets.forward_density(&self.params, &mut c);
            o.copy_from_slice(&c.sigma[..o.len()]);
        });
        out
    }
}

impl Model for InstantModel {
    fn kind(&self) -> &'static str {
        "instant"
    }
    fn scene(&self) -> &Scene {
        &self.scene
    }
    fn params(&self) -> &[f32] {
        &self.params
    }
    fn params_mut(&mut self) -> &mut [f32] {
        &mut self.params
    }
    fn as_any(&self) -> &dyn std::any::Any {
        self
    }
    fn config_json(&self) -> serde_json::Value {
        serde_json::to_value(&self.config).unwrap_or(serde_json::Value::Null)
    }

    fn train_rays(&self, rays: &[TrainRay], ctx: &StepCtx, grads: &mut [f32]) -> BatchStats {
        with_scratch(|c, m| {
            let mut stats = BatchStats::default();
            for chunk in rays.chunks(self.config.chunk_rays.max(1)) {
                stats.add(&self.train_chunk(chunk, ctx, grads, c, m));
            }
            stats
        })
    }

    fn after_step(&mut self, step: u64, seed: u64, stats: &BatchStats) {
        if stats.rays > 0 {
            let spr = stats.samples as f64 / stats.rays as f64;
            self.samples_per_ray = 0.9 * self.samples_per_ray + 0.1 * spr.max(1.0);
        }
        if self.grid.due(step) {
            let (cells, pts) = self.grid.update_points(step, seed);
            let sigma = self.densities(&pts);
            self.grid.apply(step, &cells, &sigma);
        }
    }

    fn batch_rays(&self) -> Option<usize> {
        let n = self.config.samples_per_step as f64 / self.samples_per_ray.max(1.0);
        Some((n as usize).clamp(64, 1 << 16))
    }

    fn state_tensors(&self) -> Vec<(String, Vec<f32>)> {
        vec![
            ("occupancy.density".to_string(), self.grid.density.clone()),
            ("samples_per_ray".to_string(), vec![self.samples_per_ray as f32]),
        ]
    }

    /// Marches all rays of a chunk together in rounds of a few samples per
    /// ray: densities first, rays retire once transmittance falls below the
    /// threshold, and only the samples in front of that point get colours.
    fn render_rays(&self, rays: &[Ray], background: [f32; 3], out: &mut [RayOutput]) -> BatchStats {
        with_scratch(|c, m| self.render_with(rays, background, out, c, m))
    }
}

impl InstantModel {
    fn render_with(
        &self,
        rays: &[Ray],
        background: [f32; 3],
        out: &mut [RayOutput],
        c: &mut Ctx,
        m: &mut Marched,
    ) -> BatchStats {
        const ROUND: usize = 16;
        let min_t = self.config.min_transmittance;
        let mut stats = BatchStats { rays: rays.len() as u64, ..Default::default() };
        let per = RENDER_CHUNK_RAYS;
        for (chunk, outc) in rays.chunks(per).zip(out.chunks_mut(per)) {
            // per ray: next t, end, optical depth, samples so far, live
            let mut state: Vec<(f32, f32, f32, usize, bool)> = chunk
                .iter()
                .map(|r| match self.scene.clip(r) {
                    Some((t0, t1)) => (t0 + 0.5 * self.dt, t1, 0.0, 0, true),
                    None => (0.0, 0.0, 0.0, 0, false),
                })
                .collect();
            // per ray: the weight of the samples whose colour was skipped
            let mut dropped = vec![0.0f32; chunk.len()];
            let max_dropped = self.config.max_dropped_weight;
            // kept samples: ray, weight, t; geometry rows and directions for the colour pass
            let (mut k_ray, mut k_w, mut k_t) = (Vec::new(), Vec::new(), Vec::new());
            let (mut k_geo, mut k_dirs) = (Vec::new(), Vec::new());
            let g = self.nets.d2.outputs;
            loop {
                m.spans.clear();
                m.t.clear();
                m.delta.clear();
                m.dirs.clear();
                let mut owners = Vec::new();
                for (r, (ray, st)) in chunk.iter().zip(state.iter_mut()).enumerate() {
                    if !st.4 {
                        continue;
                    }
                    let start = m.t.len();
                    let limit = ROUND.min(self.config.max_samples - st.3);
                    let n = self.march_segment(ray, &mut st.0, st.1, limit, m);
                    st.3 += n;
                    // Live while the ray may have more samples.
                    st.4 = n > 0 && st.0 < st.1 && st.3 < self.config.max_samples;
                    if n > 0 {
                        m.spans.push((start, n));
                        owners.push(r);
                    }
                }
                stats.skipped += std::mem::take(&mut m.skipped);
                if m.t.is_empty() {
                    break;
                }
                self.unit_points_of(chunk, owners.iter().copied(), m, &mut c.unit);
                c.n = m.t.len();
                stats.samples += c.n as u64;
                self.nets.forward_density(&self.params, c);
                for (&r, &(o, n)) in owners.iter().zip(&m.spans) {
                    let st = &mut state[r];
                    for i in o..o + n {
                        let trans = (-st.2).exp();
                        if trans < min_t {
                            st.4 = false;
                            stats.skipped += (o + n - i) as u64;
                            break;
                        }
                        st.2 += crate::engine::render::composite::optical_depth(c.sigma[i], m.delta[i]);
                        let w = trans - (-st.2).exp();
                        if dropped[r] + w <= max_dropped {
                            // Nearly empty space: its colour cannot matter.
                            dropped[r] += w;
                            continue;
                        }
                        k_ray.push(r);
                        k_w.push(w);
                        k_t.push(m.t[i]);
                        k_geo.extend_from_slice(&c.geo[i * g..(i + 1) * g]);
                        k_dirs.extend_from_slice(&m.dirs[3 * i..3 * i + 3]);
                    }
                    if (-st.2).exp() < min_t {
                        st.4 = false;
                    }
                }
            }
            for o in outc.iter_mut() {
                *o = RayOutput::default();
            }
            if !k_ray.is_empty() {
                c.n = k_ray.len();
                c.geo = k_geo;
                self.nets.forward_color(&self.params, &k_dirs, c);
                for (i, &r) in k_ray.iter().enumerate() {
                    let o = &mut outc[r];
                    for ch in 0..3 {
                        o.rgb[ch] += k_w[i] * c.rgb[3 * i + ch];
                    }
                    o.depth += k_w[i] * k_t[i];
                }
            }
            for (o, st) in outc.iter_mut().zip(&state) {
                let trans = (-st.2).exp();
                o.opacity = 1.0 - trans;
                for ch in 0..3 {
                    o.rgb[ch] += trans * background[ch];
                }
            }
        }
        stats
    }
}

impl InstantModel {
    /// Renders model-space `rays` the slow, obvious way, as a reference for
    /// the marcher: every lattice point of each clipped ray (no occupancy
    /// grid, no early termination, every colour). Also says, per ray, what
    /// the occupancy grid would have skipped: the lattice points in cells it
    /// marks empty, how many of them hold a density at or above its cutoff,
    /// and the sum of their opacities, which bounds how much skipping them
    /// changes the pixel.
    pub fn reference_rays(&self, rays: &[Ray], background: [f32; 3]) -> Vec<ReferenceRay> {
        rays.par_iter()
            .map(|ray| {
                let mut m = Marched::default();
                if let Some((t0, t1)) = self.scene.clip(ray) {
                    let mut t = t0 + 0.5 * self.dt;
                    while t < t1 && m.t.len() < self.config.max_samples {
                        m.t.push(t);
                        t += self.dt;
                    }
                }
                let n = m.t.len();
                let mut r = ReferenceRay::default();
                if n == 0 {
                    r.out.rgb = background;
                    return r;
                }
                m.spans.push((0, n));
                m.delta = vec![self.dt; n];
                m.dirs = (0..n).flat_map(|_| [ray.dir.x, ray.dir.y, ray.dir.z]).collect();
                let mut c = Ctx { n, ..Default::default() };
                self.unit_points_of(std::slice::from_ref(ray), [0], &m, &mut c.unit);
                self.nets.forward_density(&self.params, &mut c);
                self.nets.forward_color(&self.params, &m.dirs, &mut c);
                // The marcher's own test of a point, so the two cannot round
                // differently at a cell's face.
                let gr = self.grid.grid_ray(ray);
                for (&t, &s) in m.t.iter().zip(&c.sigma[..n]) {
                    if !matches!(self.grid.probe(&gr, t), Probe::Occupied { .. }) {
                        r.skipped += 1;
                        r.skipped_above_cutoff += (s >= self.grid.cutoff) as usize;
                        r.skipped_opacity += 1.0 - (-crate::engine::render::composite::optical_depth(s, self.dt)).exp();
                    }
                }
                let mut w = vec![0.0; n];
                let comp = composite(&c.sigma[..n], &c.rgb[..3 * n], &m.t, &m.delta, background, 0.0, &mut w);
                r.out = RayOutput { rgb: comp.rgb, depth: comp.depth, opacity: comp.opacity };
                r
            })
            .collect()
    }
}

/// One ray of [`InstantModel::reference_rays`].
#[derive(Clone, Debug, Default)]
pub struct ReferenceRay {
    /// The ray rendered from every lattice point.
    pub out: RayOutput,
    /// Lattice points in cells the occupancy grid marks empty...
    pub skipped: usize,
    /// ... of which these hold a density at or above the grid's cutoff...
    pub skipped_above_cutoff: usize,
    /// ... and the sum of their opacities.
    pub skipped_opacity: f32,
}

impl InstantModel {
    /// Unit-cube coordinates of samples whose spans belong to rays `owners`.
    fn unit_points_of(&self, rays: &[Ray], owners: impl IntoIterator<Item = usize>, m: &Marched, out: &mut Vec<f32>) {
        let lo = Vec3::from_array(self.scene.aabb_min);
        let ext = Vec3::from_array(self.scene.aabb_max) - lo;
        let inv = Vec3::new(1.0 / ext.x, 1.0 / ext.y, 1.0 / ext.z);
        out.clear();
        for (r, &(o, n)) in owners.into_iter().zip(&m.spans) {
            for &t in &m.t[o..o + n] {
                let p = rays[r].at(t) - lo;
                out.extend_from_slice(&[p.x * inv.x, p.y * inv.y, p.z * inv.z]);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The preset leaves dilation to the scene: none behind transparent
    /// training pixels, dilated otherwise; explicit settings and configs
    /// written before the setting existed are kept (those are dilated).
    #[test]
    fn occupancy_dilation_follows_the_scene_unless_set() {
        use crate::engine::dataset::synthetic::BallScene;
        let mut ds = BallScene { size: 8, views: 2, ..Default::default() }.dataset();
        let transparent = Scene::from_dataset(&ds);
        assert!(transparent.transparent);
        for f in &mut ds.frames {
            f.image.rgba.chunks_exact_mut(4).for_each(|p| p[3] = 255);
        }
        let opaque = Scene::from_dataset(&ds);
        assert!(!opaque.transparent);
        let built = |c: InstantConfig, s: &Scene| InstantModel::new(c, s.clone(), 0).config.occupancy.dilate;
        assert_eq!(InstantConfig::default().occupancy.dilate, None);
        assert_eq!(built(InstantConfig::default(), &transparent), Some(false));
        assert_eq!(built(InstantConfig::default(), &opaque), Some(true));
        let mut set = InstantConfig::default();
        set.occupancy.dilate = Some(true);
        assert_eq!(built(set.clone(), &transparent), Some(true));
        set.occupancy.dilate = Some(false);
        assert_eq!(built(set, &opaque), Some(false));
        // A stored config without the field (older checkpoints) is dilated.
        let mut json = serde_json::to_value(InstantConfig::default()).unwrap();
        json["occupancy"].as_object_mut().unwrap().remove("dilate");
        let old: InstantConfig = serde_json::from_value(json).unwrap();
        assert_eq!(built(old, &transparent), Some(true));
        // And the choice changes the bits: dilated grids mark more cells.
        let grid = |d: bool| {
            let mut c = InstantConfig::default();
            c.occupancy.resolution = 16;
            c.occupancy.dilate = Some(d);
            let mut m = InstantModel::new(c, transparent.clone(), 0);
            let n = m.grid.density.len();
            let density: Vec<f32> = (0..n).map(|i| if i == n / 2 + 8 * 16 + 8 { 1e3 } else { 0.0 }).collect();
            m.set_state(density, 16.0, 1000).unwrap();
            m.grid.occupancy()
        };
        assert!(grid(true) > 20.0 * grid(false) && grid(false) > 0.0, "{} {}", grid(true), grid(false));
    }

    #[test]
    fn network_gradients_match_finite_differences_in_f64() {
        // Compare the analytic gradient of sum(sigma*gs + rgb*gc) with central
        // differences of the same f32 forward evaluated in f64 accumulation:
        // the network is evaluated with tiny perturbations on a small config,
        // so we use a relative tolerance suited to f32 forward passes.
        let cfg = InstantConfig {
            grid: HashGridConfig { levels: 3, log2_table: 6, base_resolution: 2, finest_resolution: 8 },
            hidden: 8,
            geo_features: 4,
            ..Default::default()
        };
        let mut layout = ParamLayout::default();
        let nets = Nets::new(&mut layout, &cfg);
        let mut rng = Rng::new(5);
        let mut params = vec![0.0f32; layout.len];
        for l in [&nets.d1, &nets.d2, &nets.c1, &nets.c2, &nets.c3] {
            l.init(&mut params, &mut rng);
        }
        for p in params.iter_mut() {
            *p += 0.3 * rng.normal();
        }
        let n = 4;
        let unit: Vec<f32> = (0..n * 3).map(|_| rng.f32()).collect();
        let dirs: Vec<f32> = (0..n).flat_map(|i| [0.6f32, 0.1 * i as f32, 0.8]).collect();
        let gs: Vec<f32> = (0..n).map(|_| rng.normal() * 0.1).collect();
        let gc: Vec<f32> = (0..n * 3).map(|_| rng.normal()).collect();
        let run = |p: &[f32]| -> (f64, Ctx) {
            let mut c = Ctx { n, unit: unit.clone(), ..Default::default() };
            nets.forward_density(p, &mut c);
            nets.forward_color(p, &dirs, &mut c);
            let v = c.sigma.iter().zip(&gs).map(|(a, b)| *a as f64 * *b as f64).sum::<f64>()
                + c.rgb.iter().zip(&gc).map(|(a, b)| *a as f64 * *b as f64).sum::<f64>();
            (v, c)
        };
        let (_, mut c) = run(&params);
        let mut grads = vec![0.0f32; layout.len];
        nets.backward(&params, &mut c, &gs, &gc, &mut grads);
        let mut checked = 0;
        for (name, range) in &layout.names {
            for i in range.clone() {
                let h = 1e-3f32 * (1.0 + params[i].abs());
                let mut p = params.clone();
                p[i] += h;
                let fp = run(&p).0;
                p[i] -= 2.0 * h;
                let fm = run(&p).0;
                let num = (fp - fm) / (2.0 * h as f64);
                let ana = grads[i] as f64;
                assert!((num - ana).abs() < 2e-3 + 2e-2 * num.abs(), "{name}[{i}]: numeric {num}, analytic {ana}");
                checked += 1;
            }
        }
        assert!(checked > 200);
    }
}
