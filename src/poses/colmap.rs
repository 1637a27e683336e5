//! COLMAP as a subprocess: finding it, its three steps (feature extraction,
//! matching, mapping) with their progress read from its output, and the
//! statistics of the model it made.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

use super::process::{self, RunError};

/// The environment variable naming the COLMAP binary.
pub const ENV: &str = "RADIANCE_COLMAP";

/// A COLMAP binary that answered.
#[derive(Debug, Clone)]
pub struct Colmap {
    pub path: PathBuf,
    /// Its name and version, e.g. `COLMAP 3.8`.
    pub version: String,
}

/// Finds COLMAP: `explicit` (a `--colmap` option), else `$RADIANCE_COLMAP`,
/// else `colmap` on `PATH`; and checks that it runs.
pub fn find(explicit: Option<&Path>) -> Result<Colmap, String> {
    let (path, from) = match (explicit, std::env::var_os(ENV)) {
        (Some(p), _) => (p.to_path_buf(), "--colmap"),
        (None, Some(p)) if !p.is_empty() => (PathBuf::from(p), ENV),
        _ => (PathBuf::from("colmap"), "PATH"),
    };
    let mut cmd = Command::new(&path);
    cmd.arg("help");
    headless(&mut cmd);
    let result = process::first_lines(cmd, Duration::from_secs(20), 50);
    let hint = "install it (Debian/Ubuntu: `apt-get install colmap`) or name the binary with --colmap PATH or \
                RADIANCE_COLMAP";
    match result {
        Err(RunError::Spawn { source, .. }) => {
            Err(format!("COLMAP not found (looked for '{}' from {from}: {source}); {hint}", path.display()))
        }
        Err(e) => Err(format!("COLMAP at '{}' (from {from}) does not run: {e}", path.display())),
        Ok(lines) => match lines.iter().find(|l| l.trim_start().starts_with("COLMAP ")) {
            // "COLMAP 3.8 -- Structure-from-Motion and Multi-View Stereo"
            Some(v) => Ok(Colmap { path, version: v.split(" -- ").next().unwrap_or(v).trim().to_string() }),
            None => Err(format!("'{}' (from {from}) ran but does not say it is COLMAP; {hint}", path.display())),
        },
    }
}

/// COLMAP's Qt parts must not look for a display on a server.
fn headless(cmd: &mut Command) {
    cmd.env("QT_QPA_PLATFORM", "offscreen");
}

/// How images are paired for matching.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Matcher {
    /// Every pair: the most robust, quadratic in the number of photos.
    Exhaustive,
    /// Each photo with the next [`SEQUENTIAL_OVERLAP`] in name order, and
    /// every pair among [`KEYFRAMES`] evenly spaced photos so the end of a
    /// walk-around meets its start (loop closure; COLMAP's own needs a
    /// vocabulary tree file it would download): about linear, for frames of
    /// a video or photos taken in a sequence.
    Sequential,
}

impl Matcher {
    pub fn name(self) -> &'static str {
        match self {
            Self::Exhaustive => "exhaustive",
            Self::Sequential => "sequential",
        }
    }
}

/// Sequential matching runs in about this many parts, for its progress.
pub const PAIR_CHUNKS: usize = 20;

/// The fewest pairs a part of sequential matching holds (each part starts
/// COLMAP once more).
const MIN_PAIR_CHUNK: usize = 50;

/// Neighbours in name order each photo is matched with (sequential).
pub const SEQUENTIAL_OVERLAP: usize = 10;

/// Evenly spaced photos matched with each other (sequential).
pub const KEYFRAMES: usize = 40;

/// The pairs (indices into the photos in name order, `i < j`) sequential
/// matching matches: each photo with the next `overlap`, and every pair of
/// `keyframes` evenly spaced ones.
pub fn sequential_pairs(n: usize, overlap: usize, keyframes: usize) -> Vec<(usize, usize)> {
    let mut pairs = std::collections::BTreeSet::new();
    for i in 0..n {
        for j in i + 1..(i + 1 + overlap).min(n) {
            pairs.insert((i, j));
        }
    }
    let k = keyframes.min(n);
    let key: Vec<usize> = (0..k).map(|a| a * n / k).collect();
    for (a, &i) in key.iter().enumerate() {
        for &j in &key[a + 1..] {
            pairs.insert((i, j));
        }
    }
    pairs.into_iter().collect()
}

/// The three steps of a reconstruction.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Step {
    Features,
    Matching,
    Mapping,
}

impl Step {
    pub fn name(self) -> &'static str {
        match self {
            Self::Features => "feature extraction",
            Self::Matching => "matching",
            Self::Mapping => "mapping",
        }
    }
}

/// One run's settings.
pub struct Run<'a> {
    pub colmap: &'a Colmap,
    /// Holds `database.db` and the `sparse/` output.
    pub work: &'a Path,
    pub images: &'a Path,
    /// The photos' file names in `images`, in name order.
    pub names: &'a [String],
    pub threads: usize,
    pub matcher: Matcher,
    pub deadline: Instant,
    pub cancel: &'a AtomicBool,
}

impl Run<'_> {
    fn command(&self, sub: &str) -> Command {
        let mut cmd = Command::new(&self.colmap.path);
        cmd.arg(sub).arg("--database_path").arg(self.work.join("database.db"));
        headless(&mut cmd);
        cmd
    }

    /// Runs `step`, calling `progress` with its completed fraction as
    /// COLMAP's output tells it.
    pub fn step(&self, step: Step, progress: &mut dyn FnMut(f32)) -> Result<(), RunError> {
        let threads = self.threads.to_string();
        let n = self.names.len();
        let cmd = match step {
            Step::Features => {
                let mut c = self.command("feature_extractor");
                c.arg("--image_path").arg(self.images);
                c.args(["--ImageReader.single_camera", "1", "--ImageReader.camera_model", "OPENCV"]);
                c.args(["--SiftExtraction.use_gpu", "0", "--SiftExtraction.num_threads", &threads]);
                c
            }
            Step::Matching => match self.matcher {
                Matcher::Exhaustive => {
                    let mut c = self.command("exhaustive_matcher");
                    c.args(["--SiftMatching.use_gpu", "0", "--SiftMatching.num_threads", &threads]);
                    // Blocks of 25 photos: progress in steps of 1/16 up to 100 photos.
                    c.args(["--ExhaustiveMatching.block_size", "25"]);
                    c
                }
                Matcher::Sequential => return self.match_pairs(progress),
            },
            Step::Mapping => {
                let sparse = self.work.join("sparse");
                std::fs::create_dir_all(&sparse)
                    .map_err(|source| RunError::Spawn { program: "colmap mapper".into(), source })?;
                let mut c = self.command("mapper");
                c.arg("--image_path").arg(self.images).arg("--output_path").arg(sparse);
                c.args(["--Mapper.num_threads", &threads]);
                // As nerfstudio does: a looser tolerance for global bundle
                // adjustment, several times faster, poses as good for NeRF.
                c.args(["--Mapper.ba_global_function_tolerance", "0.000001"]);
                c
            }
        };
        let mut on_line = |line: &str| {
            if let Some(f) = parse_progress(step, line, n) {
                progress(f);
            }
        };
        process::run(cmd, self.deadline, self.cancel, &mut on_line)
    }

    /// Sequential matching: the pairs of [`sequential_pairs`] given to
    /// `matches_importer` in [`PAIR_CHUNKS`] lists, one run each, so that
    /// progress moves as each is done (COLMAP 3.8 matches a list in blocks
    /// of 1225 pairs and says nothing in between).
    fn match_pairs(&self, progress: &mut dyn FnMut(f32)) -> Result<(), RunError> {
        let pairs = sequential_pairs(self.names.len(), SEQUENTIAL_OVERLAP, KEYFRAMES);
        let chunk = pairs.len().div_ceil(PAIR_CHUNKS).max(MIN_PAIR_CHUNK);
        let chunks: Vec<_> = pairs.chunks(chunk).collect();
        let threads = self.threads.to_string();
        for (k, chunk) in chunks.iter().enumerate() {
            let list = self.work.join(format!("pairs-{k:03}.txt"));
            let text: String = chunk.iter().map(|&(i, j)| format!("{} {}\n", self.names[i], self.names[j])).collect();
            std::fs::write(&list, text)
                .map_err(|source| RunError::Spawn { program: "colmap matches_importer".into(), source })?;
            let mut c = self.command("matches_importer");
            c.arg("--match_list_path").arg(&list).args(["--match_type", "pairs"]);
            c.args(["--SiftMatching.use_gpu", "0", "--SiftMatching.num_threads", &threads]);
            let n = chunks.len() as f32;
            let mut on_line = |line: &str| {
                if let Some(f) = parse_progress(Step::Matching, line, self.names.len()) {
                    progress((k as f32 + f) / n);
                }
            };
            process::run(c, self.deadline, self.cancel, &mut on_line)?;
            let _ = std::fs::remove_file(&list);
            progress((k + 1) as f32 / n);
        }
        Ok(())
    }

    /// The models the mapper wrote (`sparse/0`, `sparse/1`, ...).
    pub fn models(&self) -> Vec<PathBuf> {
        let mut dirs: Vec<(u32, PathBuf)> = std::fs::read_dir(self.work.join("sparse"))
            .into_iter()
            .flatten()
            .flatten()
            .filter_map(|e| Some((e.file_name().to_str()?.parse().ok()?, e.path())))
            .filter(|(_, p): &(u32, PathBuf)| p.join("images.bin").is_file())
            .collect();
        dirs.sort();
        dirs.into_iter().map(|(_, p)| p).collect()
    }

    /// The mean reprojection error of a model in pixels, as COLMAP's
    /// `model_analyzer` reports it (`None` if it does not).
    pub fn mean_reprojection_error(&self, model: &Path) -> Option<f64> {
        let mut cmd = Command::new(&self.colmap.path);
        cmd.arg("model_analyzer").arg("--path").arg(model);
        headless(&mut cmd);
        let mut found = None;
        let deadline = self.deadline.min(Instant::now() + Duration::from_secs(60));
        process::run(cmd, deadline, self.cancel, &mut |l| {
            if let Some(v) = l.split("Mean reprojection error:").nth(1) {
                found = v.trim().trim_end_matches("px").trim().parse().ok();
            }
        })
        .ok()?;
        found
    }
}

/// The fraction of `step` done that a line of COLMAP 3.x's output tells:
/// `Processed file [i/n]` (features), `Matching block [a/A, b/B]`
/// (exhaustive), `Matching block [i/n]` (a list of pairs), `Matching image
/// [i/n]` (COLMAP's sequential matcher), `Registering image #id
/// (k)` with k images registered so far (mapping).
pub fn parse_progress(step: Step, line: &str, images: usize) -> Option<f32> {
    let line = line.trim();
    let bracket = |prefix: &str| -> Option<Vec<(f32, f32)>> {
        let inner = line.strip_prefix(prefix)?.trim_start().strip_prefix('[')?.split(']').next()?;
        inner
            .split(',')
            .map(|part| {
                let (a, b) = part.trim().split_once('/')?;
                let (a, b): (f32, f32) = (a.trim().parse().ok()?, b.trim().parse().ok()?);
                (b > 0.0 && a >= 1.0 && a <= b).then_some((a, b))
            })
            .collect()
    };
    let f = match step {
        Step::Features => bracket("Processed file").and_then(|v| v.first().map(|&(a, b)| a / b)),
        Step::Matching => {
            if let Some(v) = bracket("Matching block") {
                // Blocks are visited row by row: [row/rows, col/cols].
                match v[..] {
                    [(r, rs), (c, cs)] => Some(((r - 1.0) * cs + c) / (rs * cs)),
                    // A list of pairs, in blocks.
                    [(b, bs)] => Some(b / bs),
                    _ => None,
                }
            } else {
                bracket("Matching image").and_then(|v| v.first().map(|&(a, b)| a / b))
            }
        }
        Step::Mapping => {
            let rest = line.strip_prefix("Registering image #")?;
            let k: f32 = rest.split('(').nth(1)?.split(')').next()?.trim().parse().ok()?;
            (images > 0).then(|| k / images as f32)
        }
    };
    f.map(|f| f.clamp(0.0, 1.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn progress_lines_of_each_step() {
        assert_eq!(parse_progress(Step::Features, "Processed file [12/48]", 48), Some(0.25));
        assert_eq!(parse_progress(Step::Features, "  Name:            0001.jpg", 48), None);
        assert_eq!(parse_progress(Step::Matching, "Matching block [1/5, 1/5] in 2.1s", 48), Some(1.0 / 25.0));
        assert_eq!(parse_progress(Step::Matching, "Matching block [2/5, 3/5] in 2.1s", 48), Some(8.0 / 25.0));
        assert_eq!(parse_progress(Step::Matching, "Matching block [5/5, 5/5] in 2.1s", 48), Some(1.0));
        assert_eq!(parse_progress(Step::Matching, "Matching image [30/120] in 0.4s", 120), Some(0.25));
        assert_eq!(parse_progress(Step::Mapping, "Registering image #16 (3)", 50), Some(0.06));
        assert_eq!(parse_progress(Step::Mapping, "Registering image #16 (50)", 50), Some(1.0));
        // Nonsense is ignored, not a panic or a fraction out of range.
        assert_eq!(parse_progress(Step::Matching, "Matching block [3/4] in 1.0s", 48), Some(0.75));
        for junk in
            ["Processed file [0/0]", "Processed file [9/3]", "Matching block [1/2, 3]", "Registering image #", ""]
        {
            for step in [Step::Features, Step::Matching, Step::Mapping] {
                assert_eq!(parse_progress(step, junk, 0), None, "{junk:?}");
            }
        }
    }

    #[test]
    fn sequential_pairs_join_neighbours_and_close_the_loop() {
        let p = sequential_pairs(6, 2, 3);
        // Neighbours (0,1) (0,2) (1,2) ... and keyframes 0, 2, 4 with each other.
        assert_eq!(p, [(0, 1), (0, 2), (0, 4), (1, 2), (1, 3), (2, 3), (2, 4), (3, 4), (3, 5), (4, 5)]);
        // Few photos: every pair, once.
        assert_eq!(sequential_pairs(4, 10, 40).len(), 6);
        // Many: about n * overlap + keyframes^2 / 2, and the first meets the last keyframe.
        let p = sequential_pairs(1000, 10, 40);
        assert!(p.len() < 1000 * 10 + 40 * 39 / 2 && p.len() > 9000, "{}", p.len());
        assert!(p.contains(&(0, 975)));
        assert!(p.iter().all(|&(i, j)| i < j && j < 1000));
    }

    #[test]
    fn a_missing_binary_is_named_with_the_way_to_install_it() {
        let e = find(Some(Path::new("/nonexistent/colmap"))).unwrap_err();
        assert!(e.contains("COLMAP not found") && e.contains("/nonexistent/colmap") && e.contains("apt-get"), "{e}");
        let e = find(Some(Path::new("/bin/true"))).unwrap_err();
        assert!(e.contains("does not say it is COLMAP"), "{e}");
    }
}
