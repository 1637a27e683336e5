//! `/v1/scenes`: upload a dataset (an archive, or multipart files with their
//! relative paths), list, get, delete.
//!
//! An upload is extracted (or its parts written) into its staging folder
//! (the artifact store's `staging_dir`: `tmp/ID/data` for the embedded
//! store), loaded and validated by the engine's loader, its files put in the
//! artifact store, and only then is its record inserted in the job store,
//! which makes it visible: a scene either exists whole or not at all, and a
//! failed upload leaves nothing behind.

use std::path::{Path, PathBuf};

use axum::Json;
use axum::body::Bytes;
use axum::extract::multipart::MultipartError;
use axum::extract::rejection::QueryRejection;
use axum::extract::{FromRequest, Multipart, Path as UrlPath, Query, Request, State};
use axum::http::{StatusCode, header::CONTENT_TYPE};
use serde::Deserialize;

use super::archive::{self, ArchiveKind, Limit, Limits};
use super::{ApiError, ApiResult, AppState, Code};
use crate::backend::Artifact;
use crate::backend::{ArtifactStore, NewJob};
use crate::datadir::{ScenePart, new_id, now_ms};
use crate::engine::front::{Dataset, DatasetError, DatasetFormat, LoadOptions, detect_format};
use crate::jobs::{JobSpec, PosesSpec, poses as poses_job};
use crate::poses::photos;
use crate::records::{SceneInfo, ScenePoses, SceneStatus, SplitCounts, ViewDefaults};

/// `POST /v1/scenes?name=`: what the upload is called (the archive's file
/// name, or the folder's), shown to people; optional.
#[derive(Debug, Deserialize)]
pub struct UploadQuery {
    pub name: Option<String>,
}

pub async fn create(
    State(s): State<AppState>,
    q: Result<Query<UploadQuery>, QueryRejection>,
    req: Request,
) -> ApiResult<(StatusCode, Json<SceneInfo>)> {
    let Query(q) = q?;
    let name = q.name.as_deref().and_then(clean_name);
    let ct = req.headers().get(CONTENT_TYPE).and_then(|v| v.to_str().ok()).unwrap_or("").to_string();
    let limits = Limits { max_unpacked_bytes: s.config.max_unpacked_bytes, max_entries: s.config.max_archive_entries };
    let too_large = |s: &AppState| {
        let max = s.config.max_upload_bytes;
        ApiError::too_large(format!("upload is larger than {max} bytes"), Limit::Bytes(max))
    };
    let info = if ct.to_ascii_lowercase().starts_with("multipart/form-data") {
        let multipart = Multipart::from_request(req, &()).await.map_err(|e| ApiError::bad_request(e.body_text()))?;
        let (id, staging) = staging(&*s.artifacts);
        let data = staging.join(ScenePart::Data.dir_name());
        let received = receive_parts(multipart, &data, limits).await.map_err(|e| match e {
            PartError::Api(e) => e,
            PartError::Multipart(e) if e.status() == StatusCode::PAYLOAD_TOO_LARGE => too_large(&s),
            PartError::Multipart(e) => {
                ApiError::bad_request(format!("reading the multipart upload: {}", e.body_text()))
            }
        });
        match received {
            Ok((size, folder)) => ingest(&s, id, staging, name.or(folder), move |_| Ok(size)).await?,
            Err(e) => {
                remove_staging(staging).await;
                return Err(e);
            }
        }
    } else {
        let kind = ArchiveKind::from_content_type(&ct).ok_or_else(|| {
            ApiError::new(
                Code::UnsupportedMediaType,
                format!(
                    "Content-Type '{ct}' is not an accepted upload (application/zip, application/x-tar, \
                     application/gzip, or multipart/form-data with one part per file)"
                ),
            )
        })?;
        let body = Bytes::from_request(req, &()).await.map_err(|e| {
            if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
                too_large(&s)
            } else {
                ApiError::bad_request(format!("reading the upload: {}", e.body_text()))
            }
        })?;
        if body.is_empty() {
            return Err(ApiError::bad_request("empty upload: send the archive as the request body"));
        }
        let (id, staging) = staging(&*s.artifacts);
        ingest(&s, id, staging, name, move |data| Ok(archive::extract(kind, &body, data, limits)?)).await?
    };
    tracing::info!(scene = %info.id, format = %info.format, train = info.images.train, "scene stored");
    Ok((StatusCode::CREATED, Json(info)))
}

/// A scene's name as given, made fit to show: control characters dropped,
/// spaces trimmed, at most 120 characters; `None` when nothing is left.
pub(super) fn clean_name(name: &str) -> Option<String> {
    let kept: String = name.chars().filter(|c| !c.is_control()).take(120).collect();
    let kept = kept.trim();
    (!kept.is_empty()).then(|| kept.to_string())
}

/// A new scene id and its staging folder (not yet created).
pub(super) fn staging(artifacts: &dyn ArtifactStore) -> (String, PathBuf) {
    let id = new_id("scn");
    let dir = artifacts.staging_dir(&id);
    (id, dir)
}

/// Removes what a failed upload staged.
async fn remove_staging(staging: PathBuf) {
    let _ = tokio::task::spawn_blocking(move || std::fs::remove_dir_all(staging)).await;
}

enum PartError {
    Api(ApiError),
    Multipart(MultipartError),
}

impl From<MultipartError> for PartError {
    fn from(e: MultipartError) -> Self {
        PartError::Multipart(e)
    }
}

impl From<std::io::Error> for PartError {
    fn from(e: std::io::Error) -> Self {
        PartError::Api(ApiError::internal(e))
    }
}

/// Writes each part of a multipart upload to `data/PATH`, where PATH is the
/// part's field name, or its file name when the field is named `file` or
/// `files` (as `curl -F 'file=@x;filename=images/x.png'` sends). Paths are
/// checked as archive entries are; the same limits apply. Returns the bytes
/// written and the one folder every part is in, when they are all in one
/// (a folder chosen in a browser: the scene's name).
async fn receive_parts(
    mut multipart: Multipart,
    data: &Path,
    limits: Limits,
) -> Result<(u64, Option<String>), PartError> {
    use tokio::io::AsyncWriteExt;
    let bad = |m: String| PartError::Api(ApiError::bad_request(m));
    tokio::fs::create_dir_all(data).await?;
    let (mut total, mut entries) = (0u64, 0usize);
    // The first folder of every path so far: None before the first part,
    // Some(None) once two parts disagree or a part is at the top.
    let mut top: Option<Option<String>> = None;
    while let Some(mut field) = multipart.next_field().await? {
        let name = match (field.name(), field.file_name()) {
            (Some("file" | "files") | None, Some(f)) => f.to_string(),
            (Some(n), _) => n.to_string(),
            (None, None) => return Err(bad("a multipart part has neither a field name nor a file name".into())),
        };
        entries += 1;
        if entries > limits.max_entries {
            let max = limits.max_entries;
            return Err(PartError::Api(ApiError::too_large(
                format!("upload has more than {max} files"),
                Limit::Entries(max),
            )));
        }
        let rel = archive::safe_relative(&name)
            .map_err(|e| bad(e.to_string().replace("archive entry", "uploaded file")))?
            .ok_or_else(|| bad(format!("uploaded file '{name}' has an empty path")))?;
        let mut parts = rel.components();
        let first = parts.next().map(|c| c.as_os_str().to_string_lossy().into_owned());
        let folder = if parts.next().is_some() { first } else { None };
        top = Some(match top {
            None => folder,
            Some(t) if t == folder => t,
            Some(_) => None,
        });
        let dest = data.join(rel);
        if let Some(p) = dest.parent() {
            tokio::fs::create_dir_all(p).await?;
        }
        let mut f = match tokio::fs::OpenOptions::new().write(true).create_new(true).open(&dest).await {
            Ok(f) => f,
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                return Err(bad(format!("uploaded file '{name}' appears twice (or is also a folder)")));
            }
            Err(e) => return Err(e.into()),
        };
        while let Some(chunk) = field.chunk().await? {
            total += chunk.len() as u64;
            if total > limits.max_unpacked_bytes {
                let max = limits.max_unpacked_bytes;
                return Err(PartError::Api(ApiError::too_large(
                    format!("upload holds more than {max} bytes"),
                    Limit::Bytes(max),
                )));
            }
            f.write_all(&chunk).await?;
        }
        f.flush().await?;
    }
    if entries == 0 {
        return Err(bad("empty multipart upload: send one part per file of the dataset".into()));
    }
    Ok((total, top.flatten().as_deref().and_then(clean_name)))
}

/// Fills `staging/data` with `fill` (returning the bytes written), then
/// loads, validates and stores the dataset: its files in the artifact
/// store, then its record (and a photo-only upload's pose estimation job)
/// in the job store, which makes it visible. Removes everything staged on
/// failure. `name` is what the scene is called (see [`SceneInfo::name`]).
pub(super) async fn ingest(
    s: &AppState,
    id: String,
    staging: PathBuf,
    name: Option<String>,
    fill: impl FnOnce(&Path) -> ApiResult<u64> + Send + 'static,
) -> ApiResult<SceneInfo> {
    let (s2, staging2) = (s.clone(), staging.clone());
    let checked = tokio::task::spawn_blocking(move || check_upload(&s2, &id, &staging2, fill)).await;
    let stored = match checked {
        Ok(Ok(mut upload)) => {
            upload.info.name = name;
            store(s, &staging, upload).await
        }
        Ok(Err(e)) => Err(e),
        Err(e) => Err(e.into()),
    };
    if stored.is_err() {
        remove_staging(staging).await;
    }
    stored
}

/// An upload, checked and ready to store.
struct Checked {
    info: SceneInfo,
    /// For photos without poses: what was uploaded, and the job that
    /// estimates the poses (the record names it).
    posing: Option<(PhotoUpload, NewJob)>,
}

/// Fills `staging/data` with `fill` and checks it: a dataset that loads
/// with training views, or photos (or a video) to estimate poses for.
fn check_upload(
    s: &AppState,
    id: &str,
    staging: &Path,
    fill: impl FnOnce(&Path) -> ApiResult<u64>,
) -> ApiResult<Checked> {
    let data = staging.join(ScenePart::Data.dir_name());
    std::fs::create_dir_all(&data)?;
    let size = fill(&data)?;
    let root = archive::dataset_root(&data);
    if matches!(detect_format(&root), Err(DatasetError::UnknownFormat(_)))
        && let Some(upload) = photo_upload(s, &data)?
    {
        return Ok(posing(id, size, upload));
    }
    check_images(&data, s.config.scheduler.max_job_memory_bytes)?;
    let ds = Dataset::load(&root, &LoadOptions::default()).map_err(|e| {
        // Name files relative to the upload, not the server's folders.
        let mut e = ApiError::from(e);
        let prefix = format!("{}/", data.display());
        e.message = e.message.replace(&prefix, "").replace(&*data.to_string_lossy(), ".");
        e
    })?;
    if ds.train.is_empty() {
        return Err(ApiError::new(Code::InvalidDataset, "the dataset has no training views"));
    }
    let rel = root.strip_prefix(staging).unwrap_or(Path::new("data")).to_string_lossy().into_owned();
    Ok(Checked { info: SceneInfo::from_dataset(id, &ds, size, rel), posing: None })
}

/// Reads the header of every image in an upload (a dataset's images and
/// masks), before the loader decodes them: none may declare more than
/// `photos::MAX_PIXELS`, and all of them decoded (8-bit RGBA, as the loader
/// holds them) must fit in what the server allows a job, `max_bytes`.
fn check_images(data: &Path, max_bytes: u64) -> ApiResult<()> {
    fn walk(dir: &Path, out: &mut Vec<PathBuf>) -> std::io::Result<()> {
        for e in std::fs::read_dir(dir)? {
            let e = e?;
            if e.file_type()?.is_dir() {
                walk(&e.path(), out)?;
            } else if photos::has_extension(&e.path(), &photos::PHOTO_EXTENSIONS) {
                out.push(e.path());
            }
        }
        Ok(())
    }
    let mut images = Vec::new();
    walk(data, &mut images)?;
    let rel = |p: &Path| p.strip_prefix(data).unwrap_or(p).display().to_string();
    let mut total = 0u64;
    for p in &images {
        // Unreadable images are left for the loader to name.
        let Ok(header) = photos::read_header(p) else { continue };
        header.check_pixels().map_err(|e| ApiError::new(Code::InvalidDataset, format!("image '{}' {e}", rel(p))))?;
        total = total.saturating_add(header.pixels() * 4);
    }
    if total > max_bytes {
        return Err(ApiError::new(
            Code::ResourceLimit,
            format!(
                "the upload's {} images decode to {} MiB, more than the server allows a job ({} MiB, \
                 --max-job-memory-mb): send fewer or smaller images",
                images.len(),
                total >> 20,
                max_bytes >> 20
            ),
        )
        .with_details(serde_json::json!({ "estimate_bytes": total, "limit_bytes": max_bytes })));
    }
    Ok(())
}

/// Stores a checked upload: its files (a photo-only upload's as `upload/`,
/// waiting for pose estimation), then its record, with the photo-only
/// upload's `poses` job (both or neither).
async fn store(s: &AppState, staging: &Path, checked: Checked) -> ApiResult<SceneInfo> {
    let Checked { info, posing } = checked;
    let part = if posing.is_some() { ScenePart::Upload } else { ScenePart::Data };
    s.artifacts.put_scene_files(&info.id, part, &staging.join(ScenePart::Data.dir_name())).await?;
    let (upload, job) = posing.unzip();
    let job = s.jobs.insert_scene(info.clone(), job).await?;
    if let (Some(upload), Some(job)) = (upload, job) {
        tracing::info!(scene = %info.id, job = %job.id, source = upload.source, photos = upload.photos, "photo-only scene queued for pose estimation");
    }
    Ok(info)
}

/// What a photo-only upload holds.
struct PhotoUpload {
    /// `photos` or `video`.
    source: &'static str,
    photos: usize,
    /// Of the first photo, as uploaded (0x0 for a video).
    resolution: [u32; 2],
    /// The `poses` job's memory estimate.
    memory: u64,
}

/// `Some` when `data` (an upload in no dataset format) holds photos or a
/// video to estimate poses for; checks what can be checked at once (enough
/// photos, each an image, pose estimation available), so a bad upload is
/// refused now rather than failing in its job.
fn photo_upload(s: &AppState, data: &Path) -> ApiResult<Option<PhotoUpload>> {
    let invalid = |m: String| ApiError::new(Code::InvalidDataset, m);
    let found = photos::scan(data).map_err(|e| invalid(e.to_string()))?;
    let source = match found.source() {
        Ok(None) => return Ok(None),
        other => other,
    };
    let rel = |p: &Path| p.strip_prefix(data).unwrap_or(p).display().to_string();
    let Some(setup) = &s.config.scheduler.poses else {
        return Err(invalid(
            "the upload holds photos without camera poses, and pose estimation is disabled on this server: COLMAP \
             was not found when it started (install it, e.g. `apt-get install colmap`, or give `radiance serve \
             --colmap PATH`). Upload a posed dataset instead (Blender, transforms.json, LLFF or COLMAP)"
                .into(),
        ));
    };
    match source.map_err(|e| invalid(e.to_string()))? {
        None => Ok(None),
        Some(photos::Source::Video(_)) if setup.tools.ffmpeg.is_none() => Err(invalid(
            "the upload is a video, and this server cannot read videos: ffmpeg was not found when it started \
             (apt-get install ffmpeg); upload photos instead"
                .into(),
        )),
        Some(photos::Source::Video(clip)) => {
            // Probed now (frames there, decodable, distinct), so a video
            // that cannot give views is refused here, saying why.
            let ffmpeg = setup.tools.ffmpeg.as_ref().ok_or_else(|| invalid("this server cannot read videos".into()))?;
            let deadline = std::time::Instant::now() + VIDEO_PROBE_LIMIT;
            let probe =
                crate::poses::video::probe(ffmpeg, clip, &rel(clip), deadline).map_err(|e| invalid(e.to_string()))?;
            let memory = poses_job::memory_estimate(crate::poses::video::decode_memory(probe.width, probe.height));
            check_job_memory(s, memory)?;
            Ok(Some(PhotoUpload { source: "video", photos: 0, resolution: [0, 0], memory }))
        }
        Some(photos::Source::Photos(list)) => {
            let n = list.len();
            if n < photos::MIN_PHOTOS {
                return Err(invalid(format!(
                    "the upload holds {n} photo{} and no camera poses; pose estimation needs at least {} \
                     overlapping photos",
                    if n == 1 { "" } else { "s" },
                    photos::MIN_PHOTOS
                )));
            }
            // Headers only: a photo's pixels are decoded by its job, once
            // its declared size passed the limit here.
            let mut sizes = Vec::with_capacity(n);
            let mut largest = 0u64;
            for p in list {
                let header = photos::read_header(p)
                    .map_err(|e| invalid(format!("'{}' is not a readable JPEG or PNG image: it {e}", rel(p))))?;
                header.check_pixels().map_err(|e| invalid(format!("photo '{}' {e}", rel(p))))?;
                largest = largest.max(header.decoded_bytes());
                let (w, h) = header.prepared_size(setup.max_size);
                sizes.push((rel(p), w, h, header.width, header.height));
            }
            let named: Vec<(&str, u32, u32)> = sizes.iter().map(|(n, w, h, ..)| (n.as_str(), *w, *h)).collect();
            photos::check_sizes(&named).map_err(invalid)?;
            let memory = poses_job::memory_estimate(photos::prepare_memory(largest, rayon::current_num_threads()));
            check_job_memory(s, memory)?;
            let resolution = [sizes[0].3, sizes[0].4];
            Ok(Some(PhotoUpload { source: "photos", photos: n, resolution, memory }))
        }
    }
}

/// The longest a video upload is probed (`poses::video::probe`).
const VIDEO_PROBE_LIMIT: std::time::Duration = std::time::Duration::from_secs(120);

/// Refuses a pose estimation whose estimate passes the per-job limit.
fn check_job_memory(s: &AppState, memory: u64) -> ApiResult<()> {
    let limit = s.config.scheduler.max_job_memory_bytes;
    if memory > limit {
        return Err(ApiError::new(
            Code::ResourceLimit,
            format!(
                "estimating these photos' poses would need about {} MiB of memory, more than the server allows a \
                 job ({} MiB, --max-job-memory-mb): send smaller photos",
                memory >> 20,
                limit >> 20
            ),
        )
        .with_details(serde_json::json!({ "estimate_bytes": memory, "limit_bytes": limit })));
    }
    Ok(())
}

/// A photo-only upload as a `posing` scene (its files go to `upload/`)
/// and the `poses` job its record names.
fn posing(id: &str, size: u64, upload: PhotoUpload) -> Checked {
    let [w, h] = upload.resolution;
    let job_id = new_id("job");
    let info = SceneInfo {
        id: id.to_string(),
        name: None,
        status: SceneStatus::Posing,
        error: None,
        poses: Some(ScenePoses {
            job_id: job_id.clone(),
            source: upload.source.into(),
            photos: upload.photos,
            report: None,
        }),
        format: DatasetFormat::Colmap,
        images: SplitCounts::default(),
        resolution: [w, h],
        warnings: Vec::new(),
        created_at: now_ms(),
        size_bytes: size,
        root: poses_job::DATA_DIR.into(),
        view: ViewDefaults {
            width: w,
            height: h,
            fov: 0.0,
            centre: [0.0; 3],
            up: [0.0, 0.0, 1.0],
            radius: 0.0,
            far: 0.0,
            near: None,
            elevation: 0.0,
            front: None,
            spiral: None,
            arc: None,
        },
        mask_folder: None,
        kind: None,
    };
    let job = NewJob {
        id: Some(job_id),
        spec: JobSpec::Poses(PosesSpec { scene_id: id.to_string() }),
        model_id: None,
        memory_estimate: upload.memory,
    };
    Checked { info, posing: Some((upload, job)) }
}

pub async fn list(State(s): State<AppState>) -> ApiResult<Json<Vec<SceneInfo>>> {
    Ok(Json(s.jobs.list_scenes().await?))
}

pub async fn get_one(State(s): State<AppState>, UrlPath(id): UrlPath<String>) -> ApiResult<Json<SceneInfo>> {
    s.jobs.get_scene(&id).await?.map(Json).ok_or_else(|| ApiError::not_found("scene", &id))
}

/// Deletes a scene unless a queued or running job uses it (409). Models
/// trained on it stay usable.
pub async fn delete(State(s): State<AppState>, UrlPath(id): UrlPath<String>) -> ApiResult<StatusCode> {
    s.jobs.delete_scene(&id).await?;
    super::remove_artifact(&s, Artifact::Scene(&id)).await;
    Ok(StatusCode::NO_CONTENT)
}
