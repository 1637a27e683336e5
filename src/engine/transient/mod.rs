//! Transient occluders found from training's own residuals (RobustNeRF,
//! SpotLessSplats), checked against the neighbouring photos: each training
//! photo is cut into square cells, each cell keeps the mean squared error
//! of the rays drawn from it and where they met a surface (taken over its
//! three by three block while its own rays are few), and a cell
//! whose error is several times what the photos taken nearest to it show
//! where that surface falls in them, in a region of such cells, stops
//! pulling on the field. A surface the field draws badly (a thin edge,
//! fur) is as bad in the neighbouring photos; something that was in one
//! photo only is not, and the field, fitting it, puts it where the other
//! photos see through or do not look. What was tried and measured:
//! `docs/design/transients.md`.

use crate::engine::dataset::Dataset;
use crate::engine::dataset::occlude::Pasted;
use crate::engine::geometry::camera::Camera;
use crate::engine::geometry::math::Vec3;

mod report;
pub use report::{FoundMasks, MOSTLY_MASKED, PhotoShare, TransientReport};

/// The most pixels a cell's side has: about sixteen cells across the
/// shorter side of a photo, at least four pixels wide.
pub const CELL: u32 = 16;
/// Residuals are recorded from this share of the budget on: the first
/// steps' errors are large everywhere.
pub const RECORD_FROM: f64 = 0.03;
/// Cells are judged from this share of the budget on: early, before the
/// field makes an occluder into a floater in front of its photo's camera
/// that no other photo sees, and that stays after its cells are dropped.
pub const JUDGE_FROM: f64 = 0.06;
/// Rays a cell needs before it is judged: its own, or while they are
/// fewer, its three by three block's together ([`TransientMaps::error`]).
const MIN_SAMPLES: f32 = 8.0;
/// The neighbouring photos a cell is compared with: those whose cameras
/// are nearest, looking within [`MAX_TURN_COS`] (30 degrees) of its own
/// direction.
const NEAREST: usize = 4;
const MAX_TURN_COS: f32 = 0.866;
/// A cell is transient when its error is this many times the reference
/// (the median over the neighbouring photos of the mean error of the
/// three by three cells around where its surface falls in each, or the
/// same place of the frame where it falls outside it)...
const SEED_RATIO: f32 = 6.0;
/// ...with at least [`NEIGHBOURS`] of its eight neighbours this many times
/// theirs; the cells this many times out of line that touch a transient
/// one join it, and theirs in turn ([`GROW_ERROR`]): an occluder's edge
/// covers part of a cell, and its far side is fitted better than its
/// seeds.
const GROW_RATIO: f32 = 3.0;
const NEIGHBOURS: usize = 2;
/// Past the first ring around the seeds, a cell joins only with a mean
/// squared error of at least this (an RMS error of 0.07 a channel): early
/// in training every cell's ratio is loose, and a region would otherwise
/// spread over a well-fitted static scene.
const GROW_ERROR: f32 = 0.005;
/// A cell's mean squared error must also reach this (an RMS error of 0.1 a
/// channel) to be transient: a capture fitted well everywhere has nothing
/// out of line worth dropping.
const MIN_ERROR: f32 = 0.01;
/// A cell whose surface the neighbouring photos do not see
/// ([`TransientMaps::unseen`]) counts as this many times further out of
/// line.
const UNSEEN_WEIGHT: f32 = 3.0;
/// A point nearer a camera than this share of the surface that camera sees
/// in its direction lies in the camera's free space.
const FREE_SPACE: f32 = 0.8;

/// One training photo's cells.
#[derive(Clone, Debug)]
struct Cells {
    name: String,
    width: u32,
    height: u32,
    cell: u32,
    nx: u32,
    ny: u32,
    sum: Vec<f32>,
    count: Vec<f32>,
    transient: Vec<bool>,
    /// The sum of the world points where the cell's rays met a surface,
    /// and how many did.
    points: Vec<[f32; 3]>,
    hits: Vec<f32>,
    /// The photos compared with, nearest first.
    nearest: Vec<usize>,
    /// The photo's camera, to find where another photo's point falls in it.
    camera: Option<Camera>,
}

/// A training photo as the maps see it: its name, its size, where its
/// camera is and which way it looks (world units).
#[derive(Clone, Debug)]
pub struct Photo {
    pub name: String,
    pub width: u32,
    pub height: u32,
    pub origin: [f32; 3],
    pub forward: [f32; 3],
    /// Its camera, when known: another photo's cell is then compared with
    /// the place its surface point falls in this photo, rather than the
    /// same place of the frame.
    pub camera: Option<Camera>,
}

/// The cells of every training photo.
#[derive(Clone, Debug)]
pub struct TransientMaps {
    photos: Vec<Cells>,
}

impl TransientMaps {
    /// Maps for `ds`'s training photos (in `ds.train`'s order), nothing
    /// transient.
    pub fn for_dataset(ds: &Dataset) -> Self {
        let photos: Vec<Photo> = ds
            .train
            .iter()
            .map(|&f| {
                let c = &ds.frames[f].camera;
                Photo {
                    name: ds.frames[f].name.clone(),
                    width: c.width,
                    height: c.height,
                    origin: c.origin().to_array(),
                    forward: c.rotate(Vec3::new(0.0, 0.0, -1.0)).to_array(),
                    camera: Some(c.clone()),
                }
            })
            .collect();
        Self::new(&photos)
    }

    /// Maps for these training photos, nothing transient.
    pub fn new(photos: &[Photo]) -> Self {
        let dist = |a: &Photo, b: &Photo| (0..3).map(|c| (a.origin[c] - b.origin[c]).powi(2)).sum::<f32>();
        let cos = |a: &Photo, b: &Photo| {
            let (na, nb) = (norm(a.forward), norm(b.forward));
            (0..3).map(|c| a.forward[c] * b.forward[c]).sum::<f32>() / (na * nb).max(1e-12)
        };
        let photos = photos
            .iter()
            .enumerate()
            .map(|(p, ph)| {
                let mut others: Vec<usize> =
                    (0..photos.len()).filter(|&q| q != p && cos(ph, &photos[q]) >= MAX_TURN_COS).collect();
                others.sort_by(|&a, &b| dist(ph, &photos[a]).total_cmp(&dist(ph, &photos[b])));
                others.truncate(NEAREST);
                Cells { nearest: others, camera: ph.camera.clone(), ..Cells::empty(&ph.name, ph.width, ph.height) }
            })
            .collect();
        Self { photos }
    }

    /// The training photos' names and sizes, in order.
    pub fn photos(&self) -> Vec<SavedPhoto> {
        self.photos.iter().map(|c| SavedPhoto { name: c.name.clone(), width: c.width, height: c.height }).collect()
    }

    /// Every photo's cells one after the other: the errors' sums, the
    /// rays counted and the verdicts (1 transient), as a checkpoint keeps
    /// them ([`TransientMaps::from_saved`] reads them back).
    pub fn cells(&self) -> (Vec<f32>, Vec<f32>, Vec<u8>) {
        let sum = self.photos.iter().flat_map(|c| c.sum.iter().copied()).collect();
        let count = self.photos.iter().flat_map(|c| c.count.iter().copied()).collect();
        let flags = self.photos.iter().flat_map(|c| c.transient.iter().map(|&t| t as u8)).collect();
        (sum, count, flags)
    }

    /// Every photo's cells one after the other: the sums of the surface
    /// points their rays met (three values a cell) and how many met one, as
    /// a checkpoint keeps them ([`TransientMaps::set_surfaces`] reads them
    /// back).
    pub fn surfaces(&self) -> (Vec<f32>, Vec<f32>) {
        let points = self.photos.iter().flat_map(|c| c.points.iter().flatten().copied()).collect();
        let hits = self.photos.iter().flat_map(|c| c.hits.iter().copied()).collect();
        (points, hits)
    }

    /// Takes back the surfaces [`TransientMaps::surfaces`] gave.
    pub fn set_surfaces(&mut self, points: &[f32], hits: &[f32]) -> Result<(), String> {
        let n: usize = self.photos.iter().map(|c| c.hits.len()).sum();
        if (points.len(), hits.len()) != (3 * n, n) {
            return Err(format!(
                "transient maps: {n} cells need {} surface values and {n} counts, but {} and {} were saved",
                3 * n,
                points.len(),
                hits.len()
            ));
        }
        let mut at = 0;
        for c in &mut self.photos {
            for k in 0..c.hits.len() {
                c.points[k] = [points[3 * at], points[3 * at + 1], points[3 * at + 2]];
                c.hits[k] = hits[at];
                at += 1;
            }
        }
        Ok(())
    }

    /// Maps as [`TransientMaps::photos`] and [`TransientMaps::cells`] gave
    /// them; they compare no photos (for reading the masks, or for
    /// [`TransientMaps::resume_from`]).
    pub fn from_saved(photos: &[SavedPhoto], sum: &[f32], count: &[f32], flags: &[u8]) -> Result<Self, String> {
        let mut cells: Vec<Cells> = photos.iter().map(|p| Cells::empty(&p.name, p.width, p.height)).collect();
        let n: usize = cells.iter().map(|c| c.sum.len()).sum();
        if (sum.len(), count.len(), flags.len()) != (n, n, n) {
            return Err(format!(
                "transient maps: {} photos have {n} cells, but {} sums, {} counts and {} verdicts were saved",
                photos.len(),
                sum.len(),
                count.len(),
                flags.len()
            ));
        }
        let mut at = 0;
        for c in &mut cells {
            let r = at..at + c.sum.len();
            c.sum.copy_from_slice(&sum[r.clone()]);
            c.count.copy_from_slice(&count[r.clone()]);
            c.transient = flags[r].iter().map(|&f| f != 0).collect();
            at += c.sum.len();
        }
        Ok(Self { photos: cells })
    }

    /// Whether these are maps of `ds`'s training photos (the same names and
    /// sizes, in `ds.train`'s order).
    pub fn fits(&self, ds: &Dataset) -> bool {
        self.photos.len() == ds.train.len()
            && self.photos.iter().zip(&ds.train).all(|(c, &f)| {
                let (frame, cam) = (&ds.frames[f], &ds.frames[f].camera);
                (c.name.as_str(), c.width, c.height) == (frame.name.as_str(), cam.width, cam.height)
            })
    }

    /// Takes the cells of `saved` (a resumed run's), which must be of the
    /// same photos, keeping the photos this map compares.
    pub fn resume_from(&mut self, saved: &TransientMaps) -> Result<(), String> {
        if saved.photos() != self.photos() {
            return Err("transient maps: the checkpoint's training photos are not this dataset's".into());
        }
        for (c, s) in self.photos.iter_mut().zip(&saved.photos) {
            (c.sum, c.count, c.transient) = (s.sum.clone(), s.count.clone(), s.transient.clone());
            (c.points, c.hits) = (s.points.clone(), s.hits.clone());
        }
        Ok(())
    }

    fn cell(&self, photo: usize, i: u32, j: u32) -> Option<(&Cells, usize)> {
        let c = self.photos.get(photo)?;
        let (x, y) = (i / c.cell, j / c.cell);
        (x < c.nx && y < c.ny).then_some((c, (y * c.nx + x) as usize))
    }

    /// The loss weight of training photo `photo`'s pixel `(i, j)`: 0 where
    /// it is transient, else 1.
    pub fn weight(&self, photo: usize, i: u32, j: u32) -> f32 {
        match self.cell(photo, i, j) {
            Some((c, k)) if c.transient[k] => 0.0,
            _ => 1.0,
        }
    }

    /// Adds a ray's mean squared error (non-finite ones are left out) and
    /// the world point where it met a surface, if it did.
    pub fn record(&mut self, photo: usize, i: u32, j: u32, err: f32, point: Option<[f32; 3]>) {
        if !err.is_finite() {
            return;
        }
        let Some((_, k)) = self.cell(photo, i, j) else { return };
        let c = &mut self.photos[photo];
        c.sum[k] += err;
        c.count[k] += 1.0;
        if let Some(p) = point.filter(|p| p.iter().all(|v| v.is_finite())) {
            (0..3).for_each(|a| c.points[k][a] += p[a]);
            c.hits[k] += 1.0;
        }
    }

    /// Photo `p`'s cell `k`'s mean surface point, once enough rays met
    /// one: its own, or while they are too few, its three by three block's
    /// (as [`TransientMaps::error`]).
    fn surface(&self, p: usize, k: usize) -> Option<Vec3> {
        let c = &self.photos[p];
        let (mut sum, mut hits) = ([0.0f32; 3], 0.0f32);
        for m in c.pooled(k, c.hits[k]) {
            (0..3).for_each(|a| sum[a] += c.points[m][a]);
            hits += c.hits[m];
        }
        (hits >= MIN_SAMPLES).then(|| Vec3::from_array(sum.map(|v| v / hits)))
    }

    /// Photo `p`'s cell `k`'s mean squared error and the rays behind it:
    /// its own once it has [`MIN_SAMPLES`], else its three by three
    /// block's. A step draws about a ray per hundred cells of a capture of
    /// a hundred photos, so a cell has its own few only after a third of
    /// the budget, when the field has long fitted an occluder; its block
    /// has them nine times as early. Each judging decides afresh, so a
    /// cell beside an occluder that its block's error took in is given
    /// back once its own rays say so.
    fn error(&self, p: usize, k: usize) -> (f32, f32) {
        let c = &self.photos[p];
        let (sum, count) = c.pooled(k, c.count[k]).fold((0.0f32, 0.0f32), |(s, n), m| (s + c.sum[m], n + c.count[m]));
        (sum / count.max(1.0), count)
    }

    /// Where photo `p`'s cell `k` lies in photo `q`'s grid: where its
    /// surface point falls in `q`'s frame, or the same place of the frame
    /// when either is unknown or the point falls outside it.
    fn place_in(&self, p: usize, k: usize, q: usize) -> (i64, i64) {
        let (c, o) = (&self.photos[p], &self.photos[q]);
        let seen = o.camera.as_ref().zip(self.surface(p, k)).and_then(|(cam, point)| cam.project(point.to_array()));
        match seen {
            Some((u, v)) => ((u / o.cell as f32) as i64, (v / o.cell as f32) as i64),
            None => {
                let (x, y) = (k as u32 % c.nx, k as u32 / c.nx);
                ((x * o.nx / c.nx) as i64, (y * o.ny / c.ny) as i64)
            }
        }
    }

    /// Whether photo `p`'s cell `k` shows a surface its neighbouring photos
    /// do not see: its point lies outside all their frames, or in the free
    /// space in front of what at least half of those that frame it see
    /// there. What the field fitted to one photo alone (an occluder made
    /// into a floater before its cells were judged) is so; a surface the
    /// field draws badly in every photo is not.
    fn unseen(&self, p: usize, k: usize) -> bool {
        let Some(point) = self.surface(p, k) else { return false };
        // Neighbours with a camera, those whose frame holds the point, and
        // of those, the ones whose surface there is known and which see
        // through the point.
        let (mut cameras, mut inside, mut known, mut free) = (0, 0, 0, 0);
        for &q in &self.photos[p].nearest {
            let o = &self.photos[q];
            let Some(cam) = &o.camera else { continue };
            cameras += 1;
            let Some((u, v)) = cam.project(point.to_array()) else { continue };
            inside += 1;
            // In the frame, so in the grid.
            let Some((_, m)) = self.cell(q, u as u32, v as u32) else { continue };
            let Some(theirs) = self.surface(q, m) else { continue };
            known += 1;
            let origin = cam.origin();
            free += ((point - origin).norm() < FREE_SPACE * (theirs - origin).norm()) as u32;
        }
        // A neighbour that frames the point but has not yet met a surface
        // there says nothing either way.
        cameras > 0 && (inside == 0 || (known == inside && 2 * free >= known))
    }

    /// Judges every cell again from the errors recorded so far.
    pub fn judge(&mut self) {
        let errors: Vec<Vec<(f32, f32)>> =
            (0..self.photos.len()).map(|p| (0..self.photos[p].sum.len()).map(|k| self.error(p, k)).collect()).collect();
        let ratios: Vec<Vec<f32>> = (0..self.photos.len()).map(|p| self.ratios(p, &errors[p])).collect();
        for ((c, r), errors) in self.photos.iter_mut().zip(ratios).zip(errors) {
            let neighbours = |k: usize| c.block(k).filter(move |&n| n != k);
            let mean = |k: usize| errors[k].0;
            // Seeds: far out of line, large, among cells out of line.
            let seeds: Vec<bool> = (0..r.len())
                .map(|k| {
                    r[k] >= SEED_RATIO
                        && mean(k) >= MIN_ERROR
                        && neighbours(k).filter(|&n| r[n] >= GROW_RATIO).count() >= NEIGHBOURS
                })
                .collect();
            // Grown into the neighbours out of line too, ring by ring while
            // any joins (past the first ring, only cells of some error): an
            // occluder is one region, whose cells far from its seeds are
            // often only a few times out of line.
            let mut grown = seeds;
            for ring in 0.. {
                let joins = |k: usize| r[k] >= GROW_RATIO && (ring == 0 || mean(k) >= GROW_ERROR);
                let next: Vec<bool> =
                    (0..r.len()).map(|k| grown[k] || (joins(k) && neighbours(k).any(|n| grown[n]))).collect();
                if next == grown {
                    break;
                }
                grown = next;
            }
            c.transient = grown;
        }
    }

    /// Each of photo `p`'s cells' error over its reference (0 where either
    /// is unknown).
    fn ratios(&self, p: usize, errors: &[(f32, f32)]) -> Vec<f32> {
        let c = &self.photos[p];
        let mut refs = Vec::with_capacity(NEAREST);
        (0..c.sum.len())
            .map(|k| {
                // A cell no ray of its own reached is not judged: its
                // block's figures stand in only for a few rays of its own
                // (outside a user's mask it never gets any).
                let (own, count) = errors[k];
                if count < MIN_SAMPLES || c.count[k] == 0.0 {
                    return 0.0;
                }
                refs.clear();
                for &q in &c.nearest {
                    let o = &self.photos[q];
                    let (qx, qy) = self.place_in(p, k, q);
                    let (mut sum, mut cells, mut pooled) = (0.0f32, 0.0f32, (0.0f32, 0.0f32));
                    for b in qy - 1..=qy + 1 {
                        for a in qx - 1..=qx + 1 {
                            if a < 0 || b < 0 || a >= o.nx as i64 || b >= o.ny as i64 {
                                continue;
                            }
                            let m = (b * o.nx as i64 + a) as usize;
                            pooled = (pooled.0 + o.sum[m], pooled.1 + o.count[m]);
                            if o.count[m] >= MIN_SAMPLES {
                                sum += o.sum[m] / o.count[m];
                                cells += 1.0;
                            }
                        }
                    }
                    if cells > 0.0 {
                        refs.push(sum / cells);
                    } else if pooled.1 >= MIN_SAMPLES {
                        // No cell there has its own few rays yet: their
                        // block's together.
                        refs.push(pooled.0 / pooled.1);
                    }
                }
                if refs.is_empty() {
                    return 0.0;
                }
                let reference = median(&refs).max(1e-6);
                let unseen = if self.unseen(p, k) { UNSEEN_WEIGHT } else { 1.0 };
                own / reference * unseen
            })
            .collect()
    }

    /// The share of training photo `photo`'s cells that are transient.
    pub fn share(&self, photo: usize) -> f64 {
        self.photos
            .get(photo)
            .map_or(0.0, |c| c.transient.iter().filter(|&&t| t).count() as f64 / c.transient.len().max(1) as f64)
    }

    /// Training photo `photo`'s pixels dropped, as a share of its own.
    fn pixel_share(&self, photo: usize) -> f64 {
        let Some(c) = self.photos.get(photo) else { return 0.0 };
        let dropped: u64 = (0..c.transient.len())
            .filter(|&k| c.transient[k])
            .map(|k| {
                let (x, y) = (k as u32 % c.nx, k as u32 / c.nx);
                let w = c.cell.min(c.width.saturating_sub(x * c.cell));
                let h = c.cell.min(c.height.saturating_sub(y * c.cell));
                w as u64 * h as u64
            })
            .sum();
        dropped as f64 / (c.width as u64 * c.height as u64).max(1) as f64
    }

    /// What was dropped: each photo's share of pixels, and the whole's.
    pub fn report(&self) -> TransientReport {
        let photos: Vec<PhotoShare> = (0..self.photos.len())
            .map(|p| PhotoShare { name: self.photos[p].name.clone(), share: self.pixel_share(p) })
            .collect();
        let pixels = |c: &Cells| c.width as f64 * c.height as f64;
        let all: f64 = self.photos.iter().map(pixels).sum();
        let dropped: f64 = self.photos.iter().zip(&photos).map(|(c, p)| pixels(c) * p.share).sum();
        TransientReport { dropped: dropped / all.max(1.0), photos }
    }

    /// Training photo `photo`'s mask as an 8-bit image of its size, in the
    /// layout of the masks a dataset gives (`masks/`): 255 where the pixel
    /// was trained on, 0 where it was dropped. `None` for no such photo.
    pub fn mask_image(&self, photo: usize) -> Option<(u32, u32, Vec<u8>)> {
        let c = self.photos.get(photo)?;
        let m = self.mask(photo, c.width, c.height);
        Some((c.width, c.height, m.into_iter().map(|t| if t { 0 } else { 255 }).collect()))
    }

    /// The index of the training photo named `name`.
    pub fn index_of(&self, name: &str) -> Option<usize> {
        self.photos.iter().position(|c| c.name == name)
    }

    /// Training photo `photo`'s mask at its pixels (`w x h`, row by row):
    /// true where transient.
    pub fn mask(&self, photo: usize, w: u32, h: u32) -> Vec<bool> {
        (0..h).flat_map(|j| (0..w).map(move |i| (i, j))).map(|(i, j)| self.weight(photo, i, j) == 0.0).collect()
    }

    /// How the masks compare with the occluders `pasted` into `ds`'s
    /// training photos (the maps' photos, in the same order).
    pub fn score(&self, ds: &Dataset, pasted: &[Pasted]) -> FoundMasks {
        let (mut hit, mut truth, mut wrong, mut other) = (0u64, 0u64, 0u64, 0u64);
        for (k, &f) in ds.train.iter().enumerate() {
            let cam = &ds.frames[f].camera;
            let pasted = pasted.iter().find(|p| p.frame == f);
            for (i, found) in self.mask(k, cam.width, cam.height).into_iter().enumerate() {
                let occluded = pasted.is_some_and(|p| p.mask[i] == 255);
                (truth, other) = (truth + occluded as u64, other + !occluded as u64);
                (hit, wrong) = (hit + (found && occluded) as u64, wrong + (found && !occluded) as u64);
            }
        }
        FoundMasks { recall: hit as f64 / truth.max(1) as f64, static_share: wrong as f64 / other.max(1) as f64 }
    }
}

impl Cells {
    /// Cell `k` and its neighbours within the grid (a three by three block).
    fn block(&self, k: usize) -> impl Iterator<Item = usize> + use<> {
        let (nx, ny) = (self.nx as i64, self.ny as i64);
        let (x, y) = ((k as i64) % nx, (k as i64) / nx);
        (-1..=1i64)
            .flat_map(move |dy| (-1..=1i64).map(move |dx| (x + dx, y + dy)))
            .filter(move |&(a, b)| a >= 0 && b >= 0 && a < nx && b < ny)
            .map(move |(a, b)| (b * nx + a) as usize)
    }

    /// The cells whose rays stand for cell `k`'s, which has `own` of them:
    /// itself once they reach [`MIN_SAMPLES`], else its block.
    fn pooled(&self, k: usize, own: f32) -> impl Iterator<Item = usize> + use<> {
        let alone = own >= MIN_SAMPLES;
        self.block(k).filter(move |&m| !alone || m == k)
    }

    /// A `width x height` photo's cells, nothing recorded: about sixteen
    /// across the shorter side.
    fn empty(name: &str, width: u32, height: u32) -> Self {
        let cell = (width.min(height) / 16).clamp(4, CELL);
        let (nx, ny) = (width.div_ceil(cell).max(1), height.div_ceil(cell).max(1));
        let n = (nx * ny) as usize;
        Cells {
            name: name.to_string(),
            width,
            height,
            cell,
            nx,
            ny,
            sum: vec![0.0; n],
            count: vec![0.0; n],
            transient: vec![false; n],
            points: vec![[0.0; 3]; n],
            hits: vec![0.0; n],
            nearest: Vec::new(),
            camera: None,
        }
    }
}

/// A training photo of the maps: its name (the image file's stem) and size.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SavedPhoto {
    pub name: String,
    pub width: u32,
    pub height: u32,
}

fn norm(v: [f32; 3]) -> f32 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

fn median(v: &[f32]) -> f32 {
    let mut v = v.to_vec();
    let mid = v.len() / 2;
    *v.select_nth_unstable_by(mid, |a, b| a.total_cmp(b)).1
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::geometry::math::Ray;
    use crate::engine::rng::Rng;

    /// Three 256x256 photos (16x16 cells of 16 pixels) from cameras side
    /// by side, looking the same way: every other pixel of every other row
    /// drawn 5 times, its squared error `base` times a random factor in
    /// [0.5, 1.5), and `bad` in the pixels `bad_at` says.
    fn recorded(base: f32, bad: f32, bad_at: impl Fn(usize, u32, u32) -> bool) -> TransientMaps {
        let mut t = TransientMaps::new(&three());
        let mut rng = Rng::new(3);
        for photo in 0..3 {
            for j in (0..256).step_by(2) {
                for i in (0..256).step_by(2) {
                    for _ in 0..5 {
                        let err = if bad_at(photo, i, j) { bad } else { base * (0.5 + rng.f32()) };
                        t.record(photo, i, j, err, None);
                    }
                }
            }
        }
        t.judge();
        t
    }

    /// A `width x height` photo named `name` from a camera at `(x, 0, 0)`
    /// looking along `forward`, its camera not given to the maps.
    fn photo(name: &str, width: u32, height: u32, x: f32, forward: [f32; 3]) -> Photo {
        Photo { name: name.into(), width, height, origin: [x, 0.0, 0.0], forward, camera: None }
    }

    fn three() -> Vec<Photo> {
        [0.0, 0.1, 0.2].map(|x| photo(&format!("p{x}"), 256, 256, x, [0.0, 0.0, -1.0])).to_vec()
    }

    #[test]
    fn saved_cells_read_back_as_the_same_masks_and_resume_only_on_the_same_photos() {
        let square = |p: usize, i: u32, j: u32| p == 1 && (32..80).contains(&i) && (32..80).contains(&j);
        let t = recorded(0.004, 0.09, square);
        let (sum, count, flags) = t.cells();
        assert_eq!(flags.iter().filter(|&&f| f == 1).count(), 9);
        let back = TransientMaps::from_saved(&t.photos(), &sum, &count, &flags).unwrap();
        assert_eq!(back.cells(), t.cells());
        for p in 0..3 {
            assert_eq!(back.mask(p, 256, 256), t.mask(p, 256, 256));
        }
        // A resumed run's maps take the cells and judge them as before.
        let mut resumed = TransientMaps::new(&three());
        resumed.resume_from(&back).unwrap();
        resumed.judge();
        assert_eq!(resumed.cells(), t.cells());
        // Cells that do not fit the photos, or other photos, are refused.
        let e = TransientMaps::from_saved(&t.photos(), &sum[1..], &count, &flags).err().unwrap();
        assert!(e.contains("3 photos have 768 cells, but 767 sums"), "{e}");
        let mut other = three();
        other[2].width = 128;
        assert!(TransientMaps::new(&other).resume_from(&back).is_err());
        other[2].width = 256;
        other[0].name = "elsewhere".into();
        assert!(TransientMaps::new(&other).resume_from(&back).is_err());
    }

    #[test]
    fn cells_with_few_rays_are_judged_by_their_blocks_until_they_have_their_own() {
        // Photo 1's 80x80 square at (64, 64): cells 4..=8 both ways, far out
        // of line; `rays` drawn at the centre of every cell of each photo.
        let square = |p: usize, i: u32, j: u32| p == 1 && (64..144).contains(&i) && (64..144).contains(&j);
        let mut rng = Rng::new(4);
        let mut draw = |t: &mut TransientMaps, rays: usize| {
            for photo in 0..3 {
                for (i, j) in (0..16).flat_map(|y| (0..16).map(move |x| (16 * x + 8, 16 * y + 8))) {
                    for _ in 0..rays {
                        let err = if square(photo, i, j) { 0.09 } else { 0.004 * (0.5 + rng.f32()) };
                        t.record(photo, i, j, err, None);
                    }
                }
            }
        };
        // Cells (x, y) of photo `p` that are transient.
        let found = |t: &TransientMaps, p: usize| -> Vec<(u32, u32)> {
            (0..16)
                .flat_map(|y| (0..16).map(move |x| (x, y)))
                .filter(|&(x, y)| t.weight(p, 16 * x, 16 * y) == 0.0)
                .collect()
        };
        let within =
            |lo: u32, hi: u32| -> Vec<(u32, u32)> { (lo..=hi).flat_map(|y| (lo..=hi).map(move |x| (x, y))).collect() };
        // One ray a cell: none has enough of its own, a block inside the
        // frame has nine. The square is found, with the ring of cells whose
        // blocks reach into it: its sides surely (three of their block's
        // nine cells in the square), its corners by chance (one of nine,
        // about three times the reference), nothing beyond.
        let mut t = TransientMaps::new(&three());
        draw(&mut t, 1);
        t.judge();
        let f = found(&t, 1);
        let corners = [(3, 3), (3, 9), (9, 3), (9, 9)];
        let sides = within(3, 9).into_iter().filter(|c| !within(4, 8).contains(c) && !corners.contains(c));
        assert!(within(4, 8).into_iter().chain(sides).all(|c| f.contains(&c)), "{f:?}");
        assert!(f.iter().all(|c| within(3, 9).contains(c)), "{f:?}");
        assert!(found(&t, 0).is_empty() && found(&t, 2).is_empty());
        // With their own rays, the ring's cells are given back.
        draw(&mut t, 8);
        t.judge();
        assert_eq!(found(&t, 1), within(4, 8));
        assert!(found(&t, 0).is_empty() && found(&t, 2).is_empty());
    }

    #[test]
    fn the_report_counts_pixels_and_names_photos_mostly_masked() {
        // 48x48 of photo 1's 256x256 pixels; photo 2's bottom half.
        let bad = |p: usize, i: u32, j: u32| {
            (p == 1 && (32..80).contains(&i) && (32..80).contains(&j)) || (p == 2 && j >= 128)
        };
        let t = recorded(0.004, 0.09, bad);
        let r = t.report();
        assert_eq!(r.photos.iter().map(|p| p.name.as_str()).collect::<Vec<_>>(), ["p0", "p0.1", "p0.2"]);
        assert_eq!(r.photos[0].share, 0.0);
        assert_eq!(r.photos[1].share, 48.0 * 48.0 / 65536.0);
        assert_eq!(r.photos[2].share, 0.5);
        assert!((r.dropped - (48.0 * 48.0 + 128.0 * 256.0) / (3.0 * 65536.0)).abs() < 1e-12);
        assert_eq!(r.mostly_masked(), vec![&r.photos[2]]);
        let line = r.summary();
        assert!(line.contains("in 2 of 3 photos") && line.contains("consider retaking: p0.2"), "{line}");
        // The image: 255 kept, 0 dropped, the photo's size.
        let (w, h, img) = t.mask_image(1).unwrap();
        assert_eq!((w, h, img.len()), (256, 256, 65536));
        assert_eq!((img[40 * 256 + 40], img[10 * 256 + 10]), (0, 255));
        assert!(t.mask_image(3).is_none());
        assert_eq!((t.index_of("p0.1"), t.index_of("nope")), (Some(1), None));
    }

    #[test]
    fn a_region_out_of_line_with_the_neighbouring_photos_is_transient_and_the_rest_is_not() {
        // Photo 1's 48x48 square at (32, 32): cells 2..=4 both ways.
        let square = |p: usize, i: u32, j: u32| p == 1 && (32..80).contains(&i) && (32..80).contains(&j);
        let t = recorded(0.004, 0.09, square);
        for photo in 0..3 {
            for j in 0..256 {
                for i in 0..256 {
                    assert_eq!(t.weight(photo, i, j) == 0.0, square(photo, i, j), "photo {photo} ({i}, {j})");
                }
            }
        }
        assert_eq!((t.share(0), t.share(1), t.share(2)), (0.0, 9.0 / 256.0, 0.0));
        let mask = t.mask(1, 256, 256);
        assert_eq!(mask.iter().filter(|&&m| m).count(), 48 * 48);
        assert!(mask[40 * 256 + 40] && !mask[10 * 256 + 10]);
    }

    #[test]
    fn what_every_photo_gets_wrong_in_the_same_place_is_not_transient() {
        // A surface the field draws badly (a thin edge, fur): as bad in the
        // neighbouring photos as in each.
        let square = |_: usize, i: u32, j: u32| (32..80).contains(&i) && (32..80).contains(&j);
        let t = recorded(0.004, 0.09, square);
        assert_eq!((t.share(0), t.share(1), t.share(2)), (0.0, 0.0, 0.0));
    }

    #[test]
    fn an_occluders_edge_cells_join_it() {
        // The square from (46, 46) to (66, 66) fills cell (3, 3), an eighth
        // of the four cells beside it (an error of about 0.015, under the
        // floor a seed needs) and a sixty-fourth of the corner ones (0.005).
        let square = |p: usize, i: u32, j: u32| p == 1 && (46..66).contains(&i) && (46..66).contains(&j);
        let t = recorded(0.004, 0.09, square);
        let cell = |x: u32, y: u32| t.weight(1, 16 * x + 8, 16 * y + 8) == 0.0;
        assert!(cell(3, 3) && cell(2, 3) && cell(4, 3) && cell(3, 2) && cell(3, 4));
        assert!(!cell(2, 2) && !cell(4, 4) && !cell(1, 3) && !cell(5, 3));
        assert_eq!(t.share(1), 5.0 / 256.0);
    }

    #[test]
    fn a_region_grows_from_its_seeds_through_every_cell_out_of_line() {
        // A square far out of line (error 0.09 against about 0.004) with a
        // strip of cells 4 times out of line running 4 cells on from it (an
        // occluder's part the field has half fitted); another such strip
        // touching no seed. Below the square, where every photo is fitted
        // well (0.001), a row of cells 4 times out of line at 0.008 and
        // rows 4 times out of line at 0.004 under it (a static surface a
        // little worse in one photo).
        let square = |p: usize, i: u32, j: u32| p == 1 && (32..64).contains(&i) && (32..64).contains(&j);
        let strip = |p: usize, i: u32, j: u32, x0: u32| p == 1 && (x0..x0 + 64).contains(&i) && (48..64).contains(&j);
        let below = |p: usize, i: u32, j: u32| match (p, j) {
            (1, 64..80) if (32..64).contains(&i) => Some(0.008),
            (1, 80..128) if (32..64).contains(&i) => Some(0.004),
            (0 | 2, 64..128) if (16..80).contains(&i) => Some(0.001),
            _ => None,
        };
        let mut t = TransientMaps::new(&three());
        let mut rng = Rng::new(3);
        for photo in 0..3 {
            for j in (0..256).step_by(2) {
                for i in (0..256).step_by(2) {
                    let err = if square(photo, i, j) {
                        0.09
                    } else if strip(photo, i, j, 64) || strip(photo, i, j, 176) {
                        0.016
                    } else if let Some(e) = below(photo, i, j) {
                        e
                    } else {
                        0.004 * (0.5 + rng.f32())
                    };
                    (0..5).for_each(|_| t.record(photo, i, j, err, None));
                }
            }
        }
        t.judge();
        let cell = |x: u32, y: u32| t.weight(1, 16 * x + 8, 16 * y + 8) == 0.0;
        assert!((2..4).all(|x| (2..4).all(|y| cell(x, y))), "the seeds");
        assert!((4..8).all(|x| cell(x, 3)), "the strip touching them, to its far end");
        assert!((11..15).all(|x| !cell(x, 3)), "the strip touching no seed");
        assert!(!cell(8, 3) && !cell(5, 5), "the static scene around");
        assert!(cell(2, 4) && cell(3, 4), "the first ring, whatever its error");
        assert!(!cell(2, 5) && !cell(3, 5), "past it, cells out of line but of little error");
    }

    #[test]
    fn a_lone_cell_out_of_line_stays() {
        // One cell (a highlight, a reflection) is not an occluder:
        // occluders are regions.
        let cell = |p: usize, i: u32, j: u32| p == 2 && (64..80).contains(&i) && (16..32).contains(&j);
        let t = recorded(0.004, 0.09, cell);
        assert_eq!(t.share(2), 0.0);
    }

    #[test]
    fn a_capture_fitted_well_everywhere_drops_nothing() {
        // Far out of line, but every error below the floor: a good fit's
        // worst cells are not occluders.
        let square = |p: usize, i: u32, j: u32| p == 0 && i < 64 && j < 64;
        let t = recorded(1e-4, 0.009, square);
        assert_eq!(t.share(0), 0.0);
        // Nothing is judged before errors are recorded, and non-finite
        // errors are not recorded.
        let lone = photo("", 256, 256, 0.0, [0.0, 0.0, -1.0]);
        let mut t = TransientMaps::new(&[lone.clone(), lone]);
        for _ in 0..100 {
            t.record(0, 5, 5, f32::NAN, None);
            t.record(0, 5, 5, f32::INFINITY, Some([0.0; 3]));
        }
        t.judge();
        assert_eq!(t.share(0), 0.0);
    }

    #[test]
    fn photos_are_compared_with_the_nearest_that_look_the_same_way() {
        let at = |x: f32, forward: [f32; 3]| photo("", 32, 32, x, forward);
        let ahead = [0.0, 0.0, -1.0];
        let photos =
            [at(0.0, ahead), at(5.0, ahead), at(1.0, ahead), at(0.5, [0.0, 1.0, 0.0]), at(2.0, ahead), at(3.0, ahead)];
        let t = TransientMaps::new(&photos);
        // Photo 3 looks 90 degrees away; the fifth nearest is left out.
        assert_eq!(t.photos[0].nearest, vec![2, 4, 5, 1]);
        assert!(t.photos[3].nearest.is_empty());
    }

    /// Three 256x256 photos from cameras 0.5 apart along x, looking down
    /// -z at a wall at z = -2 (focal length 128 pixels: the wall moves 32
    /// pixels, two cells, from one photo to the next), with the cameras
    /// given to the maps when `cameras`.
    fn wall_photos(cameras: bool) -> (Vec<Camera>, Vec<Photo>) {
        let cams: Vec<Camera> = (0..3)
            .map(|p| {
                let c2w = [[1.0, 0.0, 0.0, 0.5 * p as f32], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]];
                Camera { fx: 128.0, fy: 128.0, ..Camera::from_fov(256, 256, 1.0, c2w) }
            })
            .collect();
        let photos = (0..3)
            .map(|p| Photo {
                name: format!("w{p}"),
                width: 256,
                height: 256,
                origin: cams[p].origin().to_array(),
                forward: [0.0, 0.0, -1.0],
                camera: cameras.then(|| cams[p].clone()),
            })
            .collect();
        (cams, photos)
    }

    /// [`wall_photos`]' photos, every other pixel of every other row drawn
    /// 5 times, each draw's error and surface point what `draw(photo, ray,
    /// where the ray meets the wall)` says; judged.
    fn wall_drawn(cameras: bool, mut draw: impl FnMut(usize, &Ray, Vec3) -> (f32, Option<Vec3>)) -> TransientMaps {
        let (cams, photos) = wall_photos(cameras);
        let mut t = TransientMaps::new(&photos);
        for (p, cam) in cams.iter().enumerate() {
            for j in (0..256).step_by(2) {
                for i in (0..256).step_by(2) {
                    let ray = cam.pixel_ray(i, j);
                    let hit = ray.origin + ray.dir * (-2.0 / ray.dir.z);
                    for _ in 0..5 {
                        let (err, at) = draw(p, &ray, hit);
                        t.record(p, i, j, err, at.map(|v| v.to_array()));
                    }
                }
            }
        }
        t.judge();
        t
    }

    /// [`wall_drawn`] with a squared error of 0.004 times a random factor
    /// in [0.5, 1.5), the ray meeting the wall; where `bad_at(photo, wall x,
    /// wall y)` says, an error of `bad` and the ray meeting a surface at
    /// `floater` along it if given (what the field made of something in one
    /// photo).
    fn wall(cameras: bool, bad: f32, floater: Option<f32>, bad_at: impl Fn(usize, f32, f32) -> bool) -> TransientMaps {
        let mut rng = Rng::new(5);
        wall_drawn(cameras, |p, ray, hit| match bad_at(p, hit.x, hit.y) {
            true => (bad, Some(floater.map_or(hit, |d| ray.origin + ray.dir * d))),
            false => (0.004 * (0.5 + rng.f32()), Some(hit)),
        })
    }

    #[test]
    fn cells_are_compared_where_their_surface_falls_in_the_other_photos() {
        // A patch of the wall every photo gets wrong (a thin edge the field
        // draws badly), seen at a different place of each frame.
        let patch = |x: f32, y: f32| (0.2..0.95).contains(&x) && (0.2..0.95).contains(&y);
        let t = wall(true, 0.09, None, |_, x, y| patch(x, y));
        assert_eq!((t.share(0), t.share(1), t.share(2)), (0.0, 0.0, 0.0));
        // Compared with the same place of the frame, the patch is out of
        // line in the outer photos: their neighbours see the wall beside it
        // there.
        let blind = wall(false, 0.09, None, |_, x, y| patch(x, y));
        assert!(blind.share(0) > 0.0 && blind.share(2) > 0.0, "{:?}", [0, 1, 2].map(|p| blind.share(p)));
        // Something in photo 1 alone is still found, and only there.
        let t = wall(true, 0.09, None, |p, x, y| p == 1 && patch(x, y));
        assert!(t.share(1) >= 9.0 / 256.0, "{}", t.share(1));
        assert_eq!((t.share(0), t.share(2)), (0.0, 0.0));
    }

    #[test]
    fn what_the_neighbouring_photos_see_through_needs_less_to_be_transient() {
        // Photo 1's patch at 4 times the wall's error: under the seed's
        // ratio while it lies on the wall...
        let patch = |p: usize, x: f32, y: f32| p == 1 && (0.2..0.95).contains(&x) && (0.2..0.95).contains(&y);
        let on_wall = wall(true, 0.016, None, patch);
        assert_eq!([0, 1, 2].map(|p| on_wall.share(p)), [0.0; 3]);
        // ...but found when its surface is a floater 0.8 in front of photo
        // 1's camera, where photos 0 and 2 see the wall behind it or do not
        // look.
        let floater = wall(true, 0.016, Some(0.8), patch);
        assert!(floater.share(1) >= 9.0 / 256.0, "{}", floater.share(1));
        assert_eq!((floater.share(0), floater.share(2)), (0.0, 0.0));
        // Without cameras nothing says where a surface lies.
        let blind = wall(false, 0.016, Some(0.8), patch);
        assert_eq!(blind.share(1), 0.0);
        // Nor while the neighbours that frame the point have met no surface
        // there yet.
        let early = wall_drawn(true, |p, ray, hit| match patch(p, hit.x, hit.y) {
            true => (0.016, Some(ray.origin + ray.dir * 0.8)),
            false => (0.004, (p == 1).then_some(hit)),
        });
        assert_eq!(early.share(1), 0.0);
    }

    #[test]
    fn surfaces_read_back_and_resume_to_the_same_verdicts() {
        let patch = |p: usize, x: f32, y: f32| p == 1 && (0.2..0.95).contains(&x) && (0.2..0.95).contains(&y);
        let t = wall(true, 0.016, Some(0.8), patch);
        let (sum, count, flags) = t.cells();
        let (points, hits) = t.surfaces();
        let mut back = TransientMaps::from_saved(&t.photos(), &sum, &count, &flags).unwrap();
        back.set_surfaces(&points, &hits).unwrap();
        assert_eq!(back.surfaces(), t.surfaces());
        let mut resumed = TransientMaps::new(&wall_photos(true).1);
        resumed.resume_from(&back).unwrap();
        resumed.judge();
        assert_eq!(resumed.cells(), t.cells());
        let e = back.set_surfaces(&points[1..], &hits).err().unwrap();
        assert!(e.contains("768 cells need 2304 surface values and 768 counts, but 2303 and 768"), "{e}");
    }

    #[test]
    fn pixels_off_the_maps_weigh_one() {
        let t = recorded(0.004, 0.09, |p, _, _| p == 0);
        // Photo 3 does not exist; (256, 0) is past photo 0's edge.
        assert_eq!((t.weight(3, 0, 0), t.weight(0, 256, 0)), (1.0, 1.0));
        // A photo smaller than a cell still has one.
        let small = photo("", 3, 2, 0.0, [0.0, 0.0, -1.0]);
        assert_eq!(TransientMaps::new(&[small]).mask(0, 3, 2), vec![false; 6]);
    }
}
