//! Gathering: the photos (or a video's frames) put into the dataset's
//! `images` folder, or those a run before a crash gathered taken up again.

use super::*;

/// What gathering the photos (or a video's frames) into the dataset's
/// `images` folder works with.
pub(super) struct GatherStep<'a> {
    pub(super) work: &'a Work,
    pub(super) input: &'a Path,
    pub(super) dataset: &'a Path,
    pub(super) tools: &'a Tools,
    pub(super) opts: &'a PoseOptions,
    pub(super) deadline: Instant,
    pub(super) cancel: &'a AtomicBool,
}

impl GatherStep<'_> {
    /// The photos or frames in `dataset/images`: those a run before a crash
    /// gathered, when `saved` says they are all there, else gathered anew
    /// (what an earlier run left is removed first) and saved as done.
    pub(super) fn gather_or_resume(
        &self,
        saved: &mut Saved,
        save: &dyn Fn(&Saved) -> Result<(), PoseError>,
        report_stage: &mut dyn FnMut(Stage, f32),
    ) -> Result<Gathered, PoseError> {
        let images = self.dataset.join("images");
        if let Some(g) = saved.gathered.clone()
            && images.is_dir()
        {
            report_stage(if g.source == "video" { Stage::Frames } else { Stage::Photos }, 1.0);
            let source = if g.source == "video" { "video" } else { "photos" };
            return Ok(Gathered { source, names: g.names, size: g.size });
        }
        let work = &self.work.dir;
        for d in [self.dataset.to_path_buf(), work.join("candidates"), work.join("colmap")] {
            let _ = std::fs::remove_dir_all(d);
        }
        *saved = Saved::default();
        let (input, tools, opts) = (self.input, self.tools, self.opts);
        let g = gather(input, work, &images, tools, opts, self.deadline, self.cancel, report_stage)?;
        saved.gathered = Some(SavedGather { source: g.source.into(), names: g.names.clone(), size: g.size });
        save(saved)?;
        Ok(g)
    }
}

/// What [`gather`] put into the image folder.
pub(super) struct Gathered {
    /// `photos` or `video`.
    pub(super) source: &'static str,
    pub(super) names: Vec<String>,
    /// The images' shared size.
    pub(super) size: (u32, u32),
}

/// Puts the photos (or the video's frames) into `images`.
#[allow(clippy::too_many_arguments)]
fn gather(
    input: &Path,
    work: &Path,
    images: &Path,
    tools: &Tools,
    opts: &PoseOptions,
    deadline: Instant,
    cancel: &AtomicBool,
    report: &mut dyn FnMut(Stage, f32),
) -> Result<Gathered, PoseError> {
    let (root, found) = if input.is_dir() {
        (input.to_path_buf(), photos::scan(input)?)
    } else if input.is_file() && photos::has_extension(input, &photos::VIDEO_EXTENSIONS) {
        (
            input.parent().unwrap_or(Path::new(".")).to_path_buf(),
            photos::Found { videos: vec![input.to_path_buf()], ..Default::default() },
        )
    } else if input.exists() {
        return Err(PoseError::Input(format!(
            "'{}' is neither a folder of photos nor a video ({})",
            input.display(),
            photos::VIDEO_EXTENSIONS.join(", ")
        )));
    } else {
        return Err(PoseError::Input(format!("'{}' does not exist", input.display())));
    };
    match found.source()? {
        None => {
            let ignored = if found.ignored.is_empty() {
                String::new()
            } else {
                format!(" (found only: {})", outcome::list(&found.ignored))
            };
            Err(PoseError::Input(format!(
                "no photos (JPEG or PNG) and no video ({}) in '{}'{ignored}",
                photos::VIDEO_EXTENSIONS.join(", "),
                input.display()
            )))
        }
        Some(photos::Source::Video(clip)) => {
            let ffmpeg = tools.ffmpeg.as_ref().ok_or_else(|| {
                PoseError::Tool("a video needs ffmpeg, which was not found (apt-get install ffmpeg)".into())
            })?;
            report(Stage::Frames, 0.0);
            let names = video::extract(
                ffmpeg,
                clip,
                images,
                &work.join("candidates"),
                opts.frames,
                opts.max_size,
                deadline,
                cancel,
                &mut |f| report(Stage::Frames, f),
            )?;
            let first = image::image_dimensions(images.join(&names[0]))
                .map_err(|e| PoseError::Io { path: images.join(&names[0]), message: e.to_string() })?;
            Ok(Gathered { source: "video", names, size: first })
        }
        Some(photos::Source::Photos(list)) => {
            report(Stage::Photos, 0.0);
            let prepared = photos::prepare(&root, list, images, opts.max_size)?;
            report(Stage::Photos, 1.0);
            let size = (prepared[0].width, prepared[0].height);
            Ok(Gathered { source: "photos", names: prepared.into_iter().map(|p| p.name).collect(), size })
        }
    }
}
