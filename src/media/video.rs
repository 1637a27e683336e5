//! Orbit videos: a sequence of rendered views encoded as an animated GIF or
//! an H.264 MP4, returned as bytes (the caller writes them, atomically, with
//! [`crate::engine::io::fsio::write_atomic`]).
//!
//! - **GIF** goes through the `image` crate's encoder: one 256-colour palette
//!   per frame (exact when a frame has at most 256 colours, NeuQuant at
//!   [`GIF_SPEED`] otherwise, slower for small frames), looping forever. GIF
//!   delays are whole centiseconds, so frame `i` starts at `round(100 i /
//!   fps)` cs and the average rate is exact; browsers slow delays under 2 cs
//!   down to 10 cs, so no frame is shorter than 2 cs and rates above 50 fps
//!   play at 50 fps.
//! - **MP4** (cargo feature `mp4`, on by default): H.264 constrained baseline
//!   profile, 4:2:0 (`yuv420p`), limited-range BT.601 colour signalled in the
//!   stream, encoded by OpenH264 (built from source) and muxed by `muxide`
//!   with `moov` before `mdat` ("fast start", so browsers can play while
//!   downloading), a 90 kHz timescale and one sample per frame, frame `i` at
//!   `i / fps` seconds. H.264 4:2:0 needs even dimensions: an odd width or
//!   height is padded by one column or row that repeats the edge pixels (the
//!   video is one pixel wider or taller than the frames; nothing rendered is
//!   cut off). A single frame is stored as two samples of half a frame each,
//!   because the muxer takes the last sample's duration from the one before.

use std::fmt;
use std::str::FromStr;

use image::RgbImage;
use serde::{Deserialize, Serialize};

/// The lowest frame rate accepted.
pub const MIN_FPS: u32 = 1;
/// The highest frame rate accepted.
pub const MAX_FPS: u32 = 60;
/// NeuQuant's speed for GIF frames with more than 256 colours (1 is the
/// slowest and best, 30 the fastest): 10 quantises 60 frames of 200x200 in
/// about half a second. NeuQuant learns from one pixel in `speed`, so small
/// frames get a lower speed: see [`gif_speed`].
pub const GIF_SPEED: i32 = 10;

/// Pixels NeuQuant should learn from in each frame, at least.
const GIF_MIN_SAMPLES: u32 = 4000;

/// The NeuQuant speed for frames of `width` x `height`: [`GIF_SPEED`], or
/// lower so that at least 4000 pixels are sampled (1 below 8000 pixels).
fn gif_speed(width: u32, height: u32) -> i32 {
    let samples_at_speed_1 = width.saturating_mul(height) / GIF_MIN_SAMPLES;
    samples_at_speed_1.clamp(1, GIF_SPEED as u32) as i32
}

/// A video container and codec.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum VideoFormat {
    /// Animated GIF, looping forever.
    Gif,
    /// H.264 in an MP4 container (needs the cargo feature `mp4`).
    Mp4,
}

impl VideoFormat {
    pub const ALL: [VideoFormat; 2] = [VideoFormat::Gif, VideoFormat::Mp4];

    /// The lowercase name used in requests and files (`gif`, `mp4`).
    pub fn name(self) -> &'static str {
        match self {
            VideoFormat::Gif => "gif",
            VideoFormat::Mp4 => "mp4",
        }
    }

    /// The HTTP `Content-Type` of the encoded bytes.
    pub fn content_type(self) -> &'static str {
        match self {
            VideoFormat::Gif => "image/gif",
            VideoFormat::Mp4 => "video/mp4",
        }
    }

    /// The file extension, without the dot.
    pub fn extension(self) -> &'static str {
        self.name()
    }

    /// Whether this build can encode the format (MP4 needs the cargo feature
    /// `mp4`), so a request can be refused before any frame is rendered.
    pub fn is_available(self) -> bool {
        match self {
            VideoFormat::Gif => true,
            VideoFormat::Mp4 => cfg!(feature = "mp4"),
        }
    }

    /// The smallest frame size the format takes, `(width, height)`.
    pub fn min_size(self) -> (u32, u32) {
        match self {
            VideoFormat::Gif => (1, 1),
            // OpenH264 refuses pictures under one macroblock.
            VideoFormat::Mp4 => (16, 16),
        }
    }

    /// Whether a `width` x `height` frame is small enough for the format:
    /// GIF stores sizes in 16 bits; OpenH264 encodes up to 3840x2160, in
    /// either orientation (checked after padding odd sizes to even).
    fn fits(self, width: u32, height: u32) -> bool {
        match self {
            VideoFormat::Gif => width <= u32::from(u16::MAX) && height <= u32::from(u16::MAX),
            VideoFormat::Mp4 => {
                let (w, h) = (width.next_multiple_of(2), height.next_multiple_of(2));
                w.max(h) <= 3840 && w.min(h) <= 2160
            }
        }
    }

    /// How the format is named in messages.
    fn label(self) -> &'static str {
        match self {
            VideoFormat::Gif => "GIF",
            VideoFormat::Mp4 => "MP4",
        }
    }
}

impl fmt::Display for VideoFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for VideoFormat {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        VideoFormat::ALL
            .into_iter()
            .find(|v| v.name() == s)
            .ok_or_else(|| format!("unknown video format '{s}' (expected gif or mp4)"))
    }
}

/// Why a video could not be encoded.
#[derive(Debug, thiserror::Error)]
pub enum VideoError {
    #[error("a video needs at least one frame")]
    NoFrames,
    #[error(
        "frame {index} is {width}x{height} but frame 0 is {expected_width}x{expected_height}: all frames must have the same size"
    )]
    SizeMismatch { index: usize, width: u32, height: u32, expected_width: u32, expected_height: u32 },
    #[error("fps must be from {MIN_FPS} to {MAX_FPS}, got {0}")]
    FpsOutOfRange(u32),
    #[error("{} frames must be at least {min_width}x{min_height} pixels, got {width}x{height}", .format.label())]
    TooSmall { format: VideoFormat, width: u32, height: u32, min_width: u32, min_height: u32 },
    #[error("{} frames of {width}x{height} pixels are too large ({})", .format.label(), max_size_text(*.format))]
    TooLarge { format: VideoFormat, width: u32, height: u32 },
    #[error("{} encoding failed: {message}", .format.label())]
    Encoder { format: VideoFormat, message: String },
    #[error("MP4 support was not compiled in (cargo feature `mp4`)")]
    Mp4NotCompiled,
}

fn max_size_text(format: VideoFormat) -> &'static str {
    match format {
        VideoFormat::Gif => "at most 65535 pixels each way",
        VideoFormat::Mp4 => "at most 3840x2160 or 2160x3840",
    }
}

impl VideoError {
    fn encoder(format: VideoFormat, err: impl fmt::Display) -> Self {
        VideoError::Encoder { format, message: err.to_string() }
    }
}

/// Checks a video's parameters before its frames exist (so a job can refuse
/// a request before rendering anything): the format is compiled in, the frame
/// size suits it and `fps` is in [`MIN_FPS`]`..=`[`MAX_FPS`].
pub fn validate(format: VideoFormat, width: u32, height: u32, fps: u32) -> Result<(), VideoError> {
    if !format.is_available() {
        return Err(VideoError::Mp4NotCompiled);
    }
    if !(MIN_FPS..=MAX_FPS).contains(&fps) {
        return Err(VideoError::FpsOutOfRange(fps));
    }
    let (min_width, min_height) = format.min_size();
    if width < min_width || height < min_height {
        return Err(VideoError::TooSmall { format, width, height, min_width, min_height });
    }
    if !format.fits(width, height) {
        return Err(VideoError::TooLarge { format, width, height });
    }
    Ok(())
}

/// Encodes `frames`, shown `fps` times a second, as a complete GIF or MP4
/// file. All frames must have the same size; see the module documentation
/// for what each format does with them.
pub fn encode(format: VideoFormat, frames: &[RgbImage], fps: u32) -> Result<Vec<u8>, VideoError> {
    let first = frames.first().ok_or(VideoError::NoFrames)?;
    let (width, height) = first.dimensions();
    if let Some((index, frame)) = frames.iter().enumerate().find(|(_, f)| f.dimensions() != (width, height)) {
        return Err(VideoError::SizeMismatch {
            index,
            width: frame.width(),
            height: frame.height(),
            expected_width: width,
            expected_height: height,
        });
    }
    validate(format, width, height, fps)?;
    match format {
        VideoFormat::Gif => encode_gif(frames, fps),
        #[cfg(feature = "mp4")]
        VideoFormat::Mp4 => mp4::encode(frames, fps),
        #[cfg(not(feature = "mp4"))]
        VideoFormat::Mp4 => Err(VideoError::Mp4NotCompiled),
    }
}

/// The delay of GIF frame `index` in centiseconds: frame `i` starts at
/// `round(100 i / fps)`, so the average rate is exact, and no delay is under
/// 2 cs, which browsers would stretch to 10 cs.
fn gif_delay_cs(index: usize, fps: u32) -> u32 {
    let start = |i: u64| (200 * i + u64::from(fps)) / (2 * u64::from(fps));
    let i = index as u64;
    ((start(i + 1) - start(i)) as u32).max(2)
}

fn encode_gif(frames: &[RgbImage], fps: u32) -> Result<Vec<u8>, VideoError> {
    use image::codecs::gif::{GifEncoder, Repeat};
    use image::{Delay, Frame, RgbaImage};

    let fail = |e: image::ImageError| VideoError::encoder(VideoFormat::Gif, e);
    let mut out = Vec::new();
    {
        let mut encoder = GifEncoder::new_with_speed(&mut out, gif_speed(frames[0].width(), frames[0].height()));
        encoder.set_repeat(Repeat::Infinite).map_err(fail)?;
        for (i, rgb) in frames.iter().enumerate() {
            let rgba = RgbaImage::from_fn(rgb.width(), rgb.height(), |x, y| {
                let [r, g, b] = rgb.get_pixel(x, y).0;
                image::Rgba([r, g, b, 255])
            });
            let delay = Delay::from_numer_denom_ms(10 * gif_delay_cs(i, fps), 1);
            encoder.encode_frame(Frame::from_parts(rgba, 0, 0, delay)).map_err(fail)?;
        }
        // Dropping the encoder writes the GIF trailer.
    }
    Ok(out)
}

/// H.264 through OpenH264, muxed into MP4 by muxide.
#[cfg(feature = "mp4")]
mod mp4 {
    use image::RgbImage;
    use muxide::api::{MuxerBuilder, VideoCodec};
    use openh264::OpenH264API;
    use openh264::encoder::{
        Encoder, EncoderConfig, FrameRate, FrameType, IntraFramePeriod, Profile, RateControlMode, VuiConfig,
    };
    use openh264::formats::YUVSlices;

    use super::{VideoError, VideoFormat};

    fn fail(e: impl std::fmt::Display) -> VideoError {
        VideoError::encoder(VideoFormat::Mp4, e)
    }

    pub(super) fn encode(frames: &[RgbImage], fps: u32) -> Result<Vec<u8>, VideoError> {
        let (width, height) = frames[0].dimensions();
        let (w, h) = (width.next_multiple_of(2), height.next_multiple_of(2));
        let config = EncoderConfig::new()
            .profile(Profile::Baseline)
            // Constant quality: OpenH264's base QP (26) on every frame (about
            // 31.5 dB PSNR on the lego test views, which are sharper than
            // renders). Its bitrate modes would drop frames, or print a
            // warning on every video when dropping is off.
            .rate_control_mode(RateControlMode::Off)
            .max_frame_rate(FrameRate::from_hz(fps as f32))
            // Every frame must come out as a picture: one sample per frame.
            .skip_frames(false)
            // A key frame every two seconds, for seeking.
            .intra_frame_period(IntraFramePeriod::from_num_frames(2 * fps))
            // One thread: deterministic output, and the caller decides the
            // parallelism (rendering uses every core).
            .num_threads(1)
            .vui(VuiConfig::bt601());
        let mut encoder = Encoder::with_api_config(OpenH264API::from_source(), config).map_err(fail)?;
        let mut muxer = MuxerBuilder::new(Vec::new())
            .video(VideoCodec::H264, w, h, f64::from(fps))
            .with_fast_start(true)
            .build()
            .map_err(fail)?;

        let mut yuv = I420::new(w, h);
        let frame_seconds = 1.0 / f64::from(fps);
        // The muxer takes the last sample's duration from the previous
        // sample, so a lone frame goes in twice, half a frame each.
        let (count, step) = if frames.len() == 1 { (2, frame_seconds / 2.0) } else { (frames.len(), frame_seconds) };
        for i in 0..count {
            yuv.fill_from(&frames[i.min(frames.len() - 1)]);
            let stream = encoder.encode(&yuv.slices()).map_err(fail)?;
            let keyframe = match stream.frame_type() {
                FrameType::IDR => true,
                FrameType::I | FrameType::P => false,
                other => return Err(fail(format!("OpenH264 returned a {other:?} frame for frame {i}"))),
            };
            muxer.write_video(i as f64 * step, &stream.to_vec(), keyframe).map_err(fail)?;
        }
        muxer.finish_in_place().map_err(fail)?;
        Ok(muxer.into_writer())
    }

    /// A 4:2:0 picture with planes Y (w x h), U and V (w/2 x h/2), `w` and
    /// `h` even.
    struct I420 {
        width: usize,
        height: usize,
        y: Vec<u8>,
        u: Vec<u8>,
        v: Vec<u8>,
    }

    impl I420 {
        fn new(width: u32, height: u32) -> Self {
            let (width, height) = (width as usize, height as usize);
            let chroma = (width / 2) * (height / 2);
            I420 { width, height, y: vec![0; width * height], u: vec![0; chroma], v: vec![0; chroma] }
        }

        /// Converts `rgb` (at most one pixel smaller each way: the last
        /// column and row repeat) to limited-range BT.601, chroma averaged
        /// over 2x2 blocks, with rounding.
        fn fill_from(&mut self, rgb: &RgbImage) {
            let (rw, rh) = (rgb.width() as usize, rgb.height() as usize);
            let raw = rgb.as_raw();
            let px = |x: usize, y: usize| {
                let o = 3 * (y.min(rh - 1) * rw + x.min(rw - 1));
                [i32::from(raw[o]), i32::from(raw[o + 1]), i32::from(raw[o + 2])]
            };
            for y in 0..self.height {
                for x in 0..self.width {
                    let [r, g, b] = px(x, y);
                    self.y[y * self.width + x] = (((66 * r + 129 * g + 25 * b + 128) >> 8) + 16) as u8;
                }
            }
            let cw = self.width / 2;
            for cy in 0..self.height / 2 {
                for cx in 0..cw {
                    let (mut u, mut v) = (0, 0);
                    for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                        let [r, g, b] = px(2 * cx + dx, 2 * cy + dy);
                        u += -38 * r - 74 * g + 112 * b;
                        v += 112 * r - 94 * g - 18 * b;
                    }
                    // Four pixels, each scaled by 256: divide by 1024, rounding.
                    self.u[cy * cw + cx] = (((u + 512) >> 10) + 128).clamp(0, 255) as u8;
                    self.v[cy * cw + cx] = (((v + 512) >> 10) + 128).clamp(0, 255) as u8;
                }
            }
        }

        fn slices(&self) -> YUVSlices<'_> {
            YUVSlices::new(
                (&self.y, &self.u, &self.v),
                (self.width, self.height),
                (self.width, self.width / 2, self.width / 2),
            )
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn format_names_types_and_parsing() {
        assert_eq!(VideoFormat::Gif.name(), "gif");
        assert_eq!(VideoFormat::Mp4.name(), "mp4");
        assert_eq!(VideoFormat::Gif.content_type(), "image/gif");
        assert_eq!(VideoFormat::Mp4.content_type(), "video/mp4");
        assert_eq!(VideoFormat::Gif.extension(), "gif");
        assert_eq!(VideoFormat::Mp4.extension(), "mp4");
        for f in VideoFormat::ALL {
            assert_eq!(f.name().parse::<VideoFormat>(), Ok(f));
            assert_eq!(f.to_string(), f.name());
            let json = serde_json::to_string(&f).unwrap();
            assert_eq!(json, format!("\"{}\"", f.name()));
            assert_eq!(serde_json::from_str::<VideoFormat>(&json).unwrap(), f);
        }
        let err = "webm".parse::<VideoFormat>().unwrap_err();
        assert!(err.contains("'webm'") && err.contains("gif or mp4"), "{err}");
        assert!(serde_json::from_str::<VideoFormat>("\"GIF\"").is_err());
        assert!(VideoFormat::Gif.is_available());
        assert_eq!(VideoFormat::Mp4.is_available(), cfg!(feature = "mp4"));
    }

    #[test]
    fn gif_delays_keep_the_average_rate_and_a_2cs_minimum() {
        let total = |fps: u32, n: usize| (0..n).map(|i| gif_delay_cs(i, fps)).sum::<u32>();
        assert_eq!((0..4).map(|i| gif_delay_cs(i, 25)).collect::<Vec<_>>(), [4, 4, 4, 4]);
        assert_eq!(total(30, 30), 100);
        assert_eq!(total(24, 24), 100);
        assert_eq!(total(7, 7), 100);
        assert_eq!(total(1, 3), 300);
        // 60 fps cannot be shown: 2 cs (50 fps) is the shortest delay.
        assert!((0..60).all(|i| gif_delay_cs(i, 60) == 2));
    }

    #[test]
    fn gif_speed_samples_enough_pixels() {
        assert_eq!(gif_speed(32, 24), 1);
        assert_eq!(gif_speed(100, 100), 2);
        assert_eq!(gif_speed(200, 200), GIF_SPEED);
        assert_eq!(gif_speed(4000, 4000), GIF_SPEED);
        assert_eq!(gif_speed(65535, 65535), GIF_SPEED);
    }
}
