//! The classic NeRF model: a coarse and a fine network, stratified coarse
//! samples and fine samples drawn from the coarse weights, both trained with
//! an L2 loss on colour.

use crate::engine::geometry::math::Ray;
use crate::engine::geometry::scene::Scene;
use crate::engine::models::{BatchStats, Model, RayOutput, StepCtx, TrainRay};
use crate::engine::nn::linear::ParamLayout;
use crate::engine::nn::nerf_net::{NerfNet, NetConfig, NetCtx};
use crate::engine::render::composite::{composite, composite_backward};
use crate::engine::rng::Rng;
use crate::engine::sampling::occupancy::{OccupancyConfig, OccupancyGrid, Segments};
use crate::engine::sampling::stratified::{deltas, edges, merge_sorted, sample_pdf, stratified};

/// The classic model's configuration. `Default` is the paper's.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct NerfConfig {
    pub net: NetConfig,
    /// Stratified samples per ray for the coarse network (64).
    pub coarse_samples: usize,
    /// Extra samples per ray from the coarse weights (128); the fine network
    /// sees these and the coarse ones.
    pub fine_samples: usize,
    /// Rays processed together through the networks by one thread.
    pub chunk_rays: usize,
    /// Transmittance below which rendering stops marching a ray (1e-4).
    pub min_transmittance: f32,
    /// Skip empty space with an occupancy grid (`None`: sample the whole
    /// clipped ray, as the paper does).
    pub occupancy: Option<OccupancyConfig>,
}

impl Default for NerfConfig {
    fn default() -> Self {
        Self {
            net: NetConfig::default(),
            coarse_samples: 64,
            fine_samples: 128,
            chunk_rays: 8,
            min_transmittance: 1e-4,
            occupancy: Some(OccupancyConfig::default()),
        }
    }
}

/// The classic NeRF.
pub struct NerfModel {
    pub config: NerfConfig,
    scene: Scene,
    coarse: NerfNet,
    fine: NerfNet,
    params: Vec<f32>,
    grid: Option<OccupancyGrid>,
}

/// Reusable buffers of one thread.
#[derive(Default)]
struct Work {
    ctx: NetCtx,
    pts: Vec<f32>,
    dirs: Vec<f32>,
    /// distance along the ray of each sample (for depth)
    tr: Vec<f32>,
    /// per ray: offset into the sample arrays and sample count
    spans: Vec<(usize, usize)>,
    delta: Vec<f32>,
    weights: Vec<f32>,
    dsigma: Vec<f32>,
    drgb: Vec<f32>,
    tmp: Vec<f32>,
    ed: Vec<f32>,
}

/// One ray of a chunk that has something to sample. Samples are placed in
/// occupied-length coordinates `s` in `[near, far] = [0, length]` and mapped
/// to distances along the ray through `segs`.
struct Hit {
    ray: Ray,
    segs: Segments,
    near: f32,
    far: f32,
    target: [f32; 3],
    background: [f32; 3],
}

impl NerfModel {
    pub fn new(config: NerfConfig, scene: Scene, seed: u64) -> Self {
        let mut layout = ParamLayout::default();
        let coarse = NerfNet::new(&mut layout, "coarse", config.net.clone());
        let fine = NerfNet::new(&mut layout, "fine", config.net.clone());
        let mut params = vec![0.0; layout.len];
        let mut rng = Rng::new(seed);
        coarse.init(&mut params, &mut rng);
        fine.init(&mut params, &mut rng);
        let grid = config.occupancy.clone().map(|c| OccupancyGrid::new(c, scene.aabb()));
        Self { config, scene, coarse, fine, params, grid }
    }

    /// Rebuilds a model from saved parts.
    pub fn from_parts(config: NerfConfig, scene: Scene, params: Vec<f32>) -> Result<Self, String> {
        let m = Self::new(config, scene, 0);
        if params.len() != m.params.len() {
            return Err(format!("expected {} parameters, found {}", m.params.len(), params.len()));
        }
        Ok(Self { params, ..m })
    }

    /// The occupied part of a ray, or `None` when it has nothing to sample.
    fn hit(&self, ray: &Ray, target: [f32; 3], background: [f32; 3]) -> Option<Hit> {
        let (t0, t1) = self.scene.clip(ray)?;
        let segs = match &self.grid {
            Some(g) => g.segments(ray, t0, t1),
            None => Segments::single(t0, t1),
        };
        let far = segs.length();
        (far > 0.0).then_some(Hit { ray: *ray, segs, near: 0.0, far, target, background })
    }

    /// Uses another model's occupancy grid (same configuration).
    pub fn copy_grid_from(&mut self, other: &NerfModel) {
        self.grid = other.grid.clone();
    }

    /// The occupancy grid, when the model skips empty space.
    pub fn grid(&self) -> Option<&OccupancyGrid> {
        self.grid.as_ref()
    }

    /// Replaces the grid's running densities (from a checkpoint).
    pub fn set_grid_state(&mut self, density: Vec<f32>, step: u64) -> Result<(), String> {
        let Some(g) = self.grid.as_mut() else { return Ok(()) };
        if density.len() != g.density.len() {
            return Err(format!("occupancy grid has {} cells, expected {}", density.len(), g.density.len()));
        }
        g.density = density;
        g.apply(step, &[], &[]);
        Ok(())
    }

    /// Densities of both networks (their maximum) at model-space points.
    fn max_density(&self, pts: &[f32]) -> Vec<f32> {
        use rayon::prelude::*;
        const CHUNK: usize = 1024;
        let mut out = vec![0.0f32; pts.len() / 3];
        out.par_chunks_mut(CHUNK).zip(pts.par_chunks(3 * CHUNK)).for_each(|(o, p)| {
            let n = o.len();
            let dirs = [0.0f32, 0.0, 1.0].repeat(n);
            let mut ctx = NetCtx::default();
            self.coarse.forward(&self.params, p, &dirs, n, &mut ctx);
            o.copy_from_slice(&ctx.sigma);
            self.fine.forward(&self.params, p, &dirs, n, &mut ctx);
            for (a, b) in o.iter_mut().zip(&ctx.sigma) {
                *a = a.max(*b);
            }
        });
        out
    }

    pub fn macs_per_sample(&self) -> usize {
        self.coarse.macs_per_sample()
    }

    /// Lays the samples `t` of each hit ray out as points and directions.
    fn gather(w: &mut Work, hits: &[Hit], ts: &[Vec<f32>]) {
        w.pts.clear();
        w.dirs.clear();
        w.spans.clear();
        w.tr.clear();
        for (h, t) in hits.iter().zip(ts) {
            w.spans.push((w.pts.len() / 3, t.len()));
            for &si in t {
                let ti = h.segs.to_t(si);
                w.tr.push(ti);
                let p = h.ray.at(ti);
                w.pts.extend_from_slice(&[p.x, p.y, p.z]);
                w.dirs.extend_from_slice(&[h.ray.dir.x, h.ray.dir.y, h.ray.dir.z]);
            }
        }
    }

    /// Composites every ray of the last forward pass; with `train`, also
    /// writes dL/dsigma and dL/drgb for an L2 loss scaled by `loss_scale`.
    /// Returns per-ray composites and the summed squared error.
    fn composite_all(
        w: &mut Work,
        hits: &[Hit],
        ts: &[Vec<f32>],
        min_t: f32,
        grad_scale: Option<f32>,
        out: &mut Vec<crate::engine::render::composite::Composite>,
    ) -> f64 {
        let total = w.pts.len() / 3;
        w.weights.resize(total, 0.0);
        if grad_scale.is_some() {
            w.dsigma.resize(total, 0.0);
            w.drgb.resize(total * 3, 0.0);
        }
        out.clear();
        let mut sq = 0.0f64;
        for (k, (h, t)) in hits.iter().zip(ts).enumerate() {
            let (o, n) = w.spans[k];
            deltas(t, h.near, h.far, &mut w.delta);
            let sigma = &w.ctx.sigma[o..o + n];
            let rgb = &w.ctx.rgb[3 * o..3 * (o + n)];
            let tr = &w.tr[o..o + n];
            let c = composite(sigma, rgb, tr, &w.delta, h.background, min_t, &mut w.weights[o..o + n]);
            let err = [c.rgb[0] - h.target[0], c.rgb[1] - h.target[1], c.rgb[2] - h.target[2]];
            sq += err.iter().map(|e| (*e as f64) * (*e as f64)).sum::<f64>() / 3.0;
            if let Some(s) = grad_scale {
                let g = [2.0 * s * err[0], 2.0 * s * err[1], 2.0 * s * err[2]];
                composite_backward(
                    sigma,
                    rgb,
                    tr,
                    &w.delta,
                    &w.weights[o..o + n],
                    h.background,
                    c.used,
                    g,
                    0.0,
                    &mut w.dsigma[o..o + n],
                    &mut w.drgb[3 * o..3 * (o + n)],
                );
            }
            out.push(c);
        }
        sq
    }

    /// Fine sample positions for each ray from the coarse weights.
    fn fine_samples(
        &self,
        w: &mut Work,
        hits: &[Hit],
        coarse_t: &[Vec<f32>],
        rngs: &mut [Option<Rng>],
    ) -> Vec<Vec<f32>> {
        let mut out = Vec::with_capacity(hits.len());
        for (k, (h, t)) in hits.iter().zip(coarse_t).enumerate() {
            let (o, n) = w.spans[k];
            edges(t, h.near, h.far, &mut w.ed);
            w.tmp.clear();
            sample_pdf(&w.ed, &w.weights[o..o + n], self.config.fine_samples, rngs[k].as_mut(), &mut w.tmp);
            let mut merged = Vec::new();
            merge_sorted(t, &w.tmp, &mut merged);
            out.push(merged);
        }
        out
    }

    /// The fine pass for rendering, in rounds of a few samples per ray, so
    /// that a ray's samples stop being evaluated once its transmittance falls
    /// below `min_t`. Returns the composites and the samples evaluated.
    fn fine_in_rounds(
        &self,
        w: &mut Work,
        hits: &[Hit],
        fine_t: &[Vec<f32>],
        min_t: f32,
    ) -> (Vec<crate::engine::render::composite::Composite>, u64) {
        const ROUND: usize = 32;
        struct State {
            next: usize,
            tau: f32,
            rgb: [f32; 3],
            depth: f32,
            live: bool,
            delta: Vec<f32>,
        }
        let mut st: Vec<State> = hits
            .iter()
            .zip(fine_t)
            .map(|(h, t)| {
                let mut delta = Vec::new();
                deltas(t, h.near, h.far, &mut delta);
                State { next: 0, tau: 0.0, rgb: [0.0; 3], depth: 0.0, live: !t.is_empty(), delta }
            })
            .collect();
        let mut samples = 0u64;
        loop {
            w.pts.clear();
            w.dirs.clear();
            w.tr.clear();
            // (ray, its first sample in this round, count)
            let mut owners = Vec::new();
            for (k, (h, s)) in hits.iter().zip(&st).enumerate() {
                if !s.live {
                    continue;
                }
                let t = &fine_t[k];
                let end = (s.next + ROUND).min(t.len());
                for &si in &t[s.next..end] {
                    let ti = h.segs.to_t(si);
                    w.tr.push(ti);
                    let p = h.ray.at(ti);
                    w.pts.extend_from_slice(&[p.x, p.y, p.z]);
                    w.dirs.extend_from_slice(&[h.ray.dir.x, h.ray.dir.y, h.ray.dir.z]);
                }
                owners.push((k, s.next, end - s.next));
            }
            if owners.is_empty() {
                break;
            }
            let n = w.pts.len() / 3;
            samples += n as u64;
            self.fine.forward(&self.params, &w.pts, &w.dirs, n, &mut w.ctx);
            let mut o = 0;
            for &(k, first, cnt) in &owners {
                let s = &mut st[k];
                for j in 0..cnt {
                    let trans = (-s.tau).exp();
                    if trans < min_t {
                        break;
                    }
                    s.tau += crate::engine::render::composite::optical_depth(w.ctx.sigma[o + j], s.delta[first + j]);
                    let wgt = trans - (-s.tau).exp();
                    for c in 0..3 {
                        s.rgb[c] += wgt * w.ctx.rgb[3 * (o + j) + c];
                    }
                    s.depth += wgt * w.tr[o + j];
                }
                s.next = first + cnt;
                s.live = s.next < fine_t[k].len() && (-s.tau).exp() >= min_t;
                o += cnt;
            }
        }
        let comps = hits
            .iter()
            .zip(st)
            .map(|(h, s)| {
                let trans = (-s.tau).exp();
                crate::engine::render::composite::Composite {
                    rgb: [
                        s.rgb[0] + trans * h.background[0],
                        s.rgb[1] + trans * h.background[1],
                        s.rgb[2] + trans * h.background[2],
                    ],
                    depth: s.depth,
                    opacity: 1.0 - trans,
                    used: s.next,
                }
            })
            .collect();
        (comps, samples)
    }

    /// Runs the coarse and fine passes over a chunk of hit rays; with
    /// `grads`, also backpropagates the L2 loss scaled by `grad_scale`.
    fn run_chunk(
        &self,
        w: &mut Work,
        hits: &[Hit],
        mut rngs: Vec<Option<Rng>>,
        mut grads: Option<(&mut [f32], f32)>,
        min_t: f32,
    ) -> (Vec<crate::engine::render::composite::Composite>, BatchStats) {
        let mut stats = BatchStats::default();
        let coarse_t: Vec<Vec<f32>> = hits
            .iter()
            .zip(rngs.iter_mut())
            .map(|(h, r)| {
                let mut t = Vec::new();
                stratified(h.near, h.far, self.config.coarse_samples, r.as_mut(), &mut t);
                t
            })
            .collect();
        let scale = grads.as_ref().map(|g| g.1);
        let mut comps = Vec::new();
        // Coarse pass.
        Self::gather(w, hits, &coarse_t);
        let n = w.pts.len() / 3;
        self.coarse.forward(&self.params, &w.pts, &w.dirs, n, &mut w.ctx);
        let sq_c = Self::composite_all(w, hits, &coarse_t, min_t, scale, &mut comps);
        stats.samples += n as u64;
        if let Some((g, _)) = grads.as_mut() {
            self.coarse.backward(&self.params, &mut w.ctx, &w.dsigma, &w.drgb, g);
        }
        // Fine pass.
        let fine_t = self.fine_samples(w, hits, &coarse_t, &mut rngs);
        if grads.is_none() && min_t > 0.0 {
            let (comps, n) = self.fine_in_rounds(w, hits, &fine_t, min_t);
            stats.samples += n;
            return (comps, stats);
        }
        Self::gather(w, hits, &fine_t);
        let n = w.pts.len() / 3;
        self.fine.forward(&self.params, &w.pts, &w.dirs, n, &mut w.ctx);
        let sq_f = Self::composite_all(w, hits, &fine_t, min_t, scale, &mut comps);
        stats.samples += n as u64;
        if let Some((g, _)) = grads.as_mut() {
            self.fine.backward(&self.params, &mut w.ctx, &w.dsigma, &w.drgb, g);
        }
        stats.sq_err = sq_f;
        stats.loss = sq_c + sq_f;
        (comps, stats)
    }
}

impl Model for NerfModel {
    fn kind(&self) -> &'static str {
        "nerf"
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
        let mut w = Work::default();
        let mut stats = BatchStats::default();
        let scale = 1.0 / (ctx.batch_rays.max(1) as f32 * 3.0);
        for chunk in rays.chunks(self.config.chunk_rays.max(1)) {
            let mut hits = Vec::with_capacity(chunk.len());
            let mut rngs = Vec::with_capacity(chunk.len());
            for r in chunk {
                stats.rays += 1;
                match self.hit(&r.ray, r.target, r.background) {
                    Some(h) => {
                        hits.push(h);
                        rngs.push(Some(Rng::stream(ctx.seed, ctx.step, r.index)));
                    }
                    None => {
                        // The ray sees only the background: no gradient, but it counts in the loss.
                        let e: f64 =
                            (0..3).map(|k| ((r.background[k] - r.target[k]) as f64).powi(2)).sum::<f64>() / 3.0;
                        stats.sq_err += e;
                        stats.loss += 2.0 * e;
                    }
                }
            }
            if hits.is_empty() {
                continue;
            }
            let (_, s) = self.run_chunk(&mut w, &hits, rngs, Some((grads, scale)), 0.0);
            stats.add(&BatchStats { rays: 0, ..s });
        }
        stats.skipped = (stats.rays * self.dense_samples()).saturating_sub(stats.samples);
        stats
    }

    fn after_step(&mut self, step: u64, seed: u64, _stats: &BatchStats) {
        let Some(g) = self.grid.as_ref() else { return };
        if !g.due(step) {
            return;
        }
        let (cells, pts) = g.update_points(step, seed);
        let sigma = self.max_density(&pts);
        if let Some(g) = self.grid.as_mut() {
            g.apply(step, &cells, &sigma);
        }
    }

    fn state_tensors(&self) -> Vec<(String, Vec<f32>)> {
        self.grid.iter().map(|g| ("occupancy.density".to_string(), g.density.clone())).collect()
    }

    fn render_rays(&self, rays: &[Ray], background: [f32; 3], out: &mut [RayOutput]) -> BatchStats {
        let mut w = Work::default();
        let mut stats = BatchStats::default();
        let per_chunk = self.config.chunk_rays.max(1) * 8;
        for (chunk, outc) in rays.chunks(per_chunk).zip(out.chunks_mut(per_chunk)) {
            let mut hits = Vec::new();
            let mut idx = Vec::new();
            for (i, r) in chunk.iter().enumerate() {
                stats.rays += 1;
                match self.hit(r, [0.0; 3], background) {
                    Some(h) => {
                        hits.push(h);
                        idx.push(i);
                    }
                    None => outc[i] = RayOutput { rgb: background, depth: 0.0, opacity: 0.0 },
                }
            }
            if hits.is_empty() {
                continue;
            }
            let rngs = vec![None; hits.len()];
            let (comps, s) = self.run_chunk(&mut w, &hits, rngs, None, self.config.min_transmittance);
            stats.samples += s.samples;
            for (&i, c) in idx.iter().zip(comps) {
                outc[i] = RayOutput { rgb: c.rgb, depth: c.depth, opacity: c.opacity };
            }
        }
        stats.skipped = (stats.rays * self.dense_samples()).saturating_sub(stats.samples);
        stats
    }
}

impl NerfModel {
    /// Network evaluations per ray without skipping (coarse + fine + coarse again).
    pub fn dense_samples(&self) -> u64 {
        (2 * self.config.coarse_samples + self.config.fine_samples) as u64
    }
}
