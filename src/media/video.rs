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

    const BACKGROUND_SPAN: u32 = 200;

    /// Frame `t` of a test clip: a smooth gradient (more than 256 colours
    /// once frames are 32x24 or larger) with an 8x8 red square moving
    /// right and down by 2 pixels a frame.
    fn frame(t: u32, width: u32, height: u32) -> RgbImage {
        RgbImage::from_fn(width, height, |x, y| {
            let (sx, sy) = ((2 * t) % width.saturating_sub(8).max(1), t % height.saturating_sub(8).max(1));
            if (sx..sx + 8).contains(&x) && (sy..sy + 8).contains(&y) {
                image::Rgb([220, 30, 40])
            } else {
                let r = 20 + x * BACKGROUND_SPAN / width;
                let g = 40 + y * BACKGROUND_SPAN / height;
                image::Rgb([r as u8, g as u8, 120])
            }
        })
    }

    fn clip(n: u32, width: u32, height: u32) -> Vec<RgbImage> {
        (0..n).map(|t| frame(t, width, height)).collect()
    }

    /// Mean absolute difference per channel of `b`'s top-left corner (the
    /// size of `a`) against `a`.
    fn mean_abs_error(a: &RgbImage, b: &RgbImage) -> f64 {
        let mut sum = 0u64;
        for (x, y, p) in a.enumerate_pixels() {
            let q = b.get_pixel(x, y);
            sum += (0..3).map(|c| u64::from(p.0[c].abs_diff(q.0[c]))).sum::<u64>();
        }
        sum as f64 / (3 * a.width() * a.height()) as f64
    }

    /// Mean difference of `b`'s top-left corner (the size of `a`) minus `a`,
    /// per channel: a colour shift, which encoding noise does not cause.
    fn mean_error(a: &RgbImage, b: &RgbImage) -> [f64; 3] {
        let mut sum = [0i64; 3];
        for (x, y, p) in a.enumerate_pixels() {
            let q = b.get_pixel(x, y);
            for (s, (&b, &a)) in sum.iter_mut().zip(q.0.iter().zip(&p.0)) {
                *s += i64::from(b) - i64::from(a);
            }
        }
        sum.map(|s| s as f64 / f64::from(a.width() * a.height()))
    }

    /// The frames of a GIF, as RGB, and their delays in milliseconds.
    fn decode_gif(bytes: &[u8]) -> Vec<(RgbImage, u32)> {
        use image::AnimationDecoder;
        use image::codecs::gif::GifDecoder;

        let frames = GifDecoder::new(std::io::Cursor::new(bytes)).unwrap().into_frames();
        frames
            .map(|f| {
                let f = f.unwrap();
                let (ms, denom) = f.delay().numer_denom_ms();
                assert_eq!(denom, 1);
                (image::DynamicImage::ImageRgba8(f.into_buffer()).to_rgb8(), ms)
            })
            .collect()
    }

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
    fn gif_decodes_back_to_the_frames() {
        let frames = clip(10, 32, 24);
        let bytes = encode(VideoFormat::Gif, &frames, 25).unwrap();
        assert_eq!(&bytes[..6], b"GIF89a");
        // Loops forever: the NETSCAPE2.0 extension with a loop count of 0.
        let netscape = bytes.windows(11).position(|w| w == b"NETSCAPE2.0").expect("loop extension");
        assert_eq!(&bytes[netscape + 11..netscape + 15], [3, 1, 0, 0]);

        let decoded = decode_gif(&bytes);
        assert_eq!(decoded.len(), frames.len());
        for (i, ((rgb, delay), f)) in decoded.iter().zip(&frames).enumerate() {
            assert_eq!(*delay, 40, "frame {i}");
            assert_eq!(rgb.dimensions(), (32, 24));
            // 256 colours for a 768-colour gradient: about 4 to 6.
            let err = mean_abs_error(f, rgb);
            assert!(err < 8.0, "frame {i}: mean abs error {err}");
            let bias = mean_error(f, rgb);
            assert!(bias.iter().all(|b| b.abs() < 2.5), "frame {i}: colour shift {bias:?}");
            // The square is there, in red.
            let (sx, sy) = (2 * i as u32, i as u32);
            let p = rgb.get_pixel(sx + 4, sy + 4).0;
            assert!(p[0] > 200 && p[1] < 60 && p[2] < 60, "frame {i}: {p:?}");
        }
    }

    #[test]
    fn gif_with_few_colours_is_exact() {
        // Two colours per frame: the palette holds them exactly.
        let frames: Vec<RgbImage> =
            (0..6)
                .map(|t| {
                    RgbImage::from_fn(20, 10, |x, _| {
                        if x / 4 == t { image::Rgb([250, 200, 7]) } else { image::Rgb([3, 90, 160]) }
                    })
                })
                .collect();
        let bytes = encode(VideoFormat::Gif, &frames, 60).unwrap();
        let decoded = decode_gif(&bytes);
        assert_eq!(decoded.len(), 6);
        for ((rgb, delay), f) in decoded.iter().zip(&frames) {
            assert_eq!(rgb, f);
            // 60 fps is shown at 50 fps.
            assert_eq!(*delay, 20);
        }
    }

    #[test]
    fn gif_speed_samples_enough_pixels() {
        assert_eq!(gif_speed(32, 24), 1);
        assert_eq!(gif_speed(100, 100), 2);
        assert_eq!(gif_speed(200, 200), GIF_SPEED);
        assert_eq!(gif_speed(4000, 4000), GIF_SPEED);
        assert_eq!(gif_speed(65535, 65535), GIF_SPEED);
    }

    #[test]
    fn error_cases() {
        let check = |format: VideoFormat, frames: &[RgbImage], fps: u32, expected: &str| {
            let err = encode(format, frames, fps).unwrap_err();
            assert!(err.to_string().contains(expected), "{format}: {err}");
            err
        };
        for format in [VideoFormat::Gif, VideoFormat::Mp4] {
            assert!(matches!(check(format, &[], 10, "at least one frame"), VideoError::NoFrames));
            let mut frames = clip(3, 32, 24);
            frames[2] = frame(2, 32, 26);
            let err = check(format, &frames, 10, "frame 2 is 32x26 but frame 0 is 32x24");
            assert!(matches!(err, VideoError::SizeMismatch { index: 2, .. }));
            let frames = clip(2, 32, 24);
            if format.is_available() {
                for fps in [0, 61, u32::MAX] {
                    let err = check(format, &frames, fps, "fps must be from 1 to 60");
                    assert!(matches!(err, VideoError::FpsOutOfRange(f) if f == fps));
                }
            }
        }
        let err =
            check(VideoFormat::Gif, &[RgbImage::new(0, 5)], 10, "GIF frames must be at least 1x1 pixels, got 0x5");
        assert!(matches!(err, VideoError::TooSmall { .. }));
        check(VideoFormat::Gif, &[RgbImage::new(65536, 1)], 10, "GIF frames of 65536x1 pixels are too large");
        assert!(validate(VideoFormat::Gif, 65535, 65535, 60).is_ok());
        #[cfg(feature = "mp4")]
        {
            let err =
                check(VideoFormat::Mp4, &clip(2, 15, 24), 10, "MP4 frames must be at least 16x16 pixels, got 15x24");
            assert!(matches!(err, VideoError::TooSmall { .. }));
            check(VideoFormat::Mp4, &[RgbImage::new(3842, 16)], 10, "too large (at most 3840x2160 or 2160x3840)");
            assert!(validate(VideoFormat::Mp4, 3839, 2159, 30).is_ok());
            assert!(validate(VideoFormat::Mp4, 2160, 3840, 30).is_ok());
            assert!(validate(VideoFormat::Mp4, 2161, 3840, 30).is_err());
        }
        #[cfg(not(feature = "mp4"))]
        {
            let err =
                check(VideoFormat::Mp4, &clip(2, 32, 24), 10, "MP4 support was not compiled in (cargo feature `mp4`)");
            assert!(matches!(err, VideoError::Mp4NotCompiled));
            assert!(matches!(validate(VideoFormat::Mp4, 32, 24, 10), Err(VideoError::Mp4NotCompiled)));
        }
    }

    /// 60 frames of 200x200 at 30 fps: the generated clip, or the first 60
    /// PNGs (in natural order, composited on white) of the folder named by
    /// `RADIANCE_VIDEO_BENCH_DIR`, e.g. a NeRF synthetic test split (an orbit).
    fn bench_frames() -> Vec<RgbImage> {
        let Some(dir) = std::env::var_os("RADIANCE_VIDEO_BENCH_DIR") else { return clip(60, 200, 200) };
        let mut paths: Vec<_> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.extension().is_some_and(|e| e == "png"))
            .collect();
        paths.sort_by_key(|p| (p.as_os_str().len(), p.clone()));
        paths
            .iter()
            .take(60)
            .map(|p| {
                let rgba = image::open(p).unwrap().to_rgba8();
                RgbImage::from_fn(rgba.width(), rgba.height(), |x, y| {
                    let [r, g, b, a] = rgba.get_pixel(x, y).0;
                    let over = |c: u8| ((u32::from(c) * u32::from(a) + 255 * (255 - u32::from(a)) + 127) / 255) as u8;
                    image::Rgb([over(r), over(g), over(b)])
                })
            })
            .collect()
    }

    fn psnr(a: &RgbImage, b: &RgbImage) -> f64 {
        let mut se = 0.0;
        for (x, y, p) in a.enumerate_pixels() {
            let q = b.get_pixel(x, y);
            se += (0..3).map(|c| (f64::from(p.0[c]) - f64::from(q.0[c])).powi(2)).sum::<f64>();
        }
        10.0 * (255.0f64.powi(2) / (se / f64::from(3 * a.width() * a.height()))).log10()
    }

    /// Encoding time, size and PSNR of each format. By hand, in release:
    /// `cargo test --release --lib media::video::tests::bench -- --ignored --nocapture`
    #[test]
    #[ignore = "a measurement: run it by hand in release"]
    fn bench_60_frames_200x200() {
        let frames = bench_frames();
        for format in VideoFormat::ALL.into_iter().filter(|f| f.is_available()) {
            let start = std::time::Instant::now();
            let bytes = encode(format, &frames, 30).unwrap();
            let seconds = start.elapsed().as_secs_f64();
            let decoded: Vec<RgbImage> = match format {
                VideoFormat::Gif => decode_gif(&bytes).into_iter().map(|(rgb, _)| rgb).collect(),
                #[cfg(feature = "mp4")]
                VideoFormat::Mp4 => mp4::decode_file(&bytes),
                #[cfg(not(feature = "mp4"))]
                VideoFormat::Mp4 => unreachable!(),
            };
            assert_eq!(decoded.len(), frames.len());
            let mean_psnr = frames.iter().zip(&decoded).map(|(f, d)| psnr(f, d)).sum::<f64>() / frames.len() as f64;
            println!(
                "{format}: {} frames of {}x{} in {seconds:.3} s, {} bytes, mean PSNR {mean_psnr:.2} dB",
                frames.len(),
                frames[0].width(),
                frames[0].height(),
                bytes.len()
            );
        }
    }

    #[cfg(feature = "mp4")]
    mod mp4 {
        use super::*;

        /// Decodes an MP4 file written by [`encode`].
        pub(super) fn decode_file(bytes: &[u8]) -> Vec<RgbImage> {
            decode(&parse(bytes))
        }

        /// A box: its type and the byte range of its payload in the file.
        #[derive(Clone, Copy, Debug)]
        struct Bx {
            kind: [u8; 4],
            start: usize,
            end: usize,
        }

        /// The boxes in `data[start..end]`, in order.
        fn children(data: &[u8], start: usize, end: usize) -> Vec<Bx> {
            let mut out = Vec::new();
            let mut at = start;
            while at < end {
                assert!(at + 8 <= end, "truncated box header at {at}");
                let mut size = u32::from_be_bytes(data[at..at + 4].try_into().unwrap()) as usize;
                let kind: [u8; 4] = data[at + 4..at + 8].try_into().unwrap();
                let mut header = 8;
                if size == 1 {
                    size = u64::from_be_bytes(data[at + 8..at + 16].try_into().unwrap()) as usize;
                    header = 16;
                }
                assert!(size >= header && at + size <= end, "box {} at {at} overruns", String::from_utf8_lossy(&kind));
                out.push(Bx { kind, start: at + header, end: at + size });
                at += size;
            }
            out
        }

        fn find(data: &[u8], parent: Bx, kind: &[u8; 4]) -> Bx {
            children(data, parent.start, parent.end)
                .into_iter()
                .find(|b| &b.kind == kind)
                .unwrap_or_else(|| panic!("no {} box", String::from_utf8_lossy(kind)))
        }

        fn path(data: &[u8], root: Bx, kinds: &[&[u8; 4]]) -> Bx {
            kinds.iter().fold(root, |b, k| find(data, b, k))
        }

        fn be32(data: &[u8], at: usize) -> u32 {
            u32::from_be_bytes(data[at..at + 4].try_into().unwrap())
        }

        /// What a test reads back from an MP4 file.
        struct Parsed {
            top: Vec<[u8; 4]>,
            timescale: u32,
            media_duration: u32,
            /// Width and height in `avc1` and `tkhd`.
            size: (u32, u32),
            tkhd_size: (u32, u32),
            durations: Vec<u32>,
            sync_samples: Vec<u32>,
            /// `avcC`: profile, compatibility, level, SPS and PPS.
            profile: (u8, u8, u8),
            sps: Vec<u8>,
            pps: Vec<u8>,
            /// The samples' bytes (4-byte length-prefixed NAL units).
            samples: Vec<Vec<u8>>,
        }

        fn parse(data: &[u8]) -> Parsed {
            let top = children(data, 0, data.len());
            let file = Bx { kind: *b"file", start: 0, end: data.len() };
            let trak = path(data, file, &[b"moov", b"trak"]);
            let mdhd = path(data, trak, &[b"mdia", b"mdhd"]);
            assert_eq!(data[mdhd.start], 0, "mdhd version 0");
            let stbl = path(data, trak, &[b"mdia", b"minf", b"stbl"]);
            let tkhd = find(data, trak, b"tkhd");
            let tkhd_size = (be32(data, tkhd.end - 8) >> 16, be32(data, tkhd.end - 4) >> 16);

            let stsd = find(data, stbl, b"stsd");
            assert_eq!(be32(data, stsd.start + 4), 1, "one sample entry");
            let avc1 = children(data, stsd.start + 8, stsd.end)[0];
            assert_eq!(&avc1.kind, b"avc1");
            let size = (
                u32::from(u16::from_be_bytes([data[avc1.start + 24], data[avc1.start + 25]])),
                u32::from(u16::from_be_bytes([data[avc1.start + 26], data[avc1.start + 27]])),
            );
            let avcc =
                children(data, avc1.start + 78, avc1.end).into_iter().find(|b| &b.kind == b"avcC").expect("avcC");
            let c = &data[avcc.start..avcc.end];
            assert_eq!(c[0], 1, "avcC configurationVersion");
            assert_eq!(c[4] & 3, 3, "4-byte NAL lengths");
            assert_eq!(c[5] & 0x1f, 1, "one SPS");
            let sps_len = usize::from(u16::from_be_bytes([c[6], c[7]]));
            let sps = c[8..8 + sps_len].to_vec();
            assert_eq!(c[8 + sps_len], 1, "one PPS");
            let pps_at = 9 + sps_len;
            let pps_len = usize::from(u16::from_be_bytes([c[pps_at], c[pps_at + 1]]));
            let pps = c[pps_at + 2..pps_at + 2 + pps_len].to_vec();
            assert_eq!(sps[0] & 0x1f, 7);
            assert_eq!(pps[0] & 0x1f, 8);

            let stts = find(data, stbl, b"stts");
            let mut durations = Vec::new();
            for e in 0..be32(data, stts.start + 4) as usize {
                let at = stts.start + 8 + 8 * e;
                durations.extend(std::iter::repeat_n(be32(data, at + 4), be32(data, at) as usize));
            }
            let stss = find(data, stbl, b"stss");
            let sync_samples =
                (0..be32(data, stss.start + 4) as usize).map(|e| be32(data, stss.start + 8 + 4 * e)).collect();

            let stsz = find(data, stbl, b"stsz");
            let fixed = be32(data, stsz.start + 4);
            let count = be32(data, stsz.start + 8) as usize;
            let sizes: Vec<usize> = (0..count)
                .map(|i| if fixed != 0 { fixed } else { be32(data, stsz.start + 12 + 4 * i) } as usize)
                .collect();
            let stco = find(data, stbl, b"stco");
            let offsets: Vec<usize> =
                (0..be32(data, stco.start + 4) as usize).map(|i| be32(data, stco.start + 8 + 4 * i) as usize).collect();
            let stsc = find(data, stbl, b"stsc");
            let runs: Vec<(usize, usize)> = (0..be32(data, stsc.start + 4) as usize)
                .map(|e| {
                    let at = stsc.start + 8 + 12 * e;
                    (be32(data, at) as usize, be32(data, at + 4) as usize)
                })
                .collect();
            let mdat = top.iter().find(|b| &b.kind == b"mdat").expect("mdat");
            let mut samples = Vec::new();
            let mut next = sizes.iter();
            for (chunk, &offset) in offsets.iter().enumerate() {
                let per_chunk = runs.iter().rev().find(|r| r.0 <= chunk + 1).expect("stsc covers chunk").1;
                let mut at = offset;
                for _ in 0..per_chunk {
                    let &len = next.next().expect("more samples in chunks than in stsz");
                    assert!(at >= mdat.start && at + len <= mdat.end, "sample outside mdat");
                    samples.push(data[at..at + len].to_vec());
                    at += len;
                }
            }
            assert_eq!(samples.len(), count, "samples in chunks");

            Parsed {
                top: top.iter().map(|b| b.kind).collect(),
                timescale: be32(data, mdhd.start + 12),
                media_duration: be32(data, mdhd.start + 16),
                size,
                tkhd_size,
                durations,
                sync_samples,
                profile: (c[1], c[2], c[3]),
                sps,
                pps,
                samples,
            }
        }

        /// Decodes the samples with OpenH264, parameter sets from `avcC`
        /// first, into RGB frames.
        fn decode(p: &Parsed) -> Vec<RgbImage> {
            use openh264::decoder::Decoder;
            use openh264::formats::YUVSource;

            let annex_b = |nal: &[u8]| [&[0, 0, 0, 1][..], nal].concat();
            let mut decoder = Decoder::new().unwrap();
            let mut out = Vec::new();
            let mut keep = |yuv: openh264::decoder::DecodedYUV<'_>| {
                let (w, h) = yuv.dimensions();
                let mut rgb = vec![0; w * h * 3];
                yuv.write_rgb8(&mut rgb);
                out.push(RgbImage::from_raw(w as u32, h as u32, rgb).unwrap());
            };
            assert!(decoder.decode(&[annex_b(&p.sps), annex_b(&p.pps)].concat()).unwrap().is_none());
            for sample in &p.samples {
                let mut stream = Vec::new();
                let mut at = 0;
                while at < sample.len() {
                    let len = be32(sample, at) as usize;
                    stream.extend(annex_b(&sample[at + 4..at + 4 + len]));
                    at += 4 + len;
                }
                assert_eq!(at, sample.len(), "NAL lengths add up");
                if let Some(yuv) = decoder.decode(&stream).unwrap() {
                    keep(yuv);
                }
            }
            for yuv in decoder.flush_remaining().unwrap() {
                keep(yuv);
            }
            out
        }

        #[test]
        fn mp4_structure_timing_and_decoded_colours() {
            let frames = clip(10, 32, 24);
            let fps = 25;
            let bytes = encode(VideoFormat::Mp4, &frames, fps).unwrap();
            let p = parse(&bytes);
            // ftyp, then moov before mdat ("fast start").
            assert_eq!(p.top.first(), Some(b"ftyp"));
            let pos = |k: &[u8; 4]| p.top.iter().position(|b| b == k).unwrap();
            assert!(pos(b"moov") < pos(b"mdat"));
            assert_eq!(&bytes[8..12], b"isom", "major brand");
            // H.264 baseline (constrained: constraint_set1), 32x24.
            assert_eq!(p.profile.0, 66, "baseline profile");
            assert_eq!(p.sps[1], 66);
            assert_eq!(p.size, (32, 24));
            assert_eq!(p.tkhd_size, (32, 24));
            // One sample per frame, each 1/25 s, the first a key frame.
            assert_eq!(p.samples.len(), frames.len());
            assert_eq!(p.timescale, 90_000);
            assert!(p.durations.iter().all(|&d| d == 90_000 / fps), "{:?}", p.durations);
            assert_eq!(p.media_duration, 10 * 90_000 / fps);
            assert_eq!(p.sync_samples[0], 1);

            let decoded = decode(&p);
            assert_eq!(decoded.len(), frames.len());
            for (i, (d, f)) in decoded.iter().zip(&frames).enumerate() {
                assert_eq!(d.dimensions(), (32, 24));
                // QP 26 and 4:2:0 chroma across the square's edges: about 3 to 6.
                let err = mean_abs_error(f, d);
                assert!(err < 9.0, "frame {i}: mean abs error {err}");
                let bias = mean_error(f, d);
                assert!(bias.iter().all(|b| b.abs() < 2.5), "frame {i}: colour shift {bias:?}");
                let (sx, sy) = (2 * i as u32, i as u32);
                let q = d.get_pixel(sx + 4, sy + 4).0;
                assert!(q[0] > 190 && q[1] < 70 && q[2] < 70, "frame {i}: {q:?}");
            }
        }

        #[test]
        fn mp4_pads_odd_sizes_by_repeating_the_edge() {
            let frames = clip(4, 33, 25);
            let p = parse(&encode(VideoFormat::Mp4, &frames, 30).unwrap());
            assert_eq!(p.size, (34, 26));
            let decoded = decode(&p);
            assert_eq!(decoded.len(), 4);
            for (d, f) in decoded.iter().zip(&frames) {
                assert_eq!(d.dimensions(), (34, 26));
                let err = mean_abs_error(f, d);
                assert!(err < 9.0, "mean abs error {err}");
                // The extra column and row repeat the last ones.
                let last_column = RgbImage::from_fn(1, 25, |_, y| *f.get_pixel(32, y));
                let extra_column = RgbImage::from_fn(1, 25, |_, y| *d.get_pixel(33, y));
                let err = mean_abs_error(&last_column, &extra_column);
                assert!(err < 8.0, "extra column: mean abs error {err}");
                let last_row = RgbImage::from_fn(33, 1, |x, _| *f.get_pixel(x, 24));
                let extra_row = RgbImage::from_fn(33, 1, |x, _| *d.get_pixel(x, 25));
                let err = mean_abs_error(&last_row, &extra_row);
                assert!(err < 8.0, "extra row: mean abs error {err}");
            }
        }

        #[test]
        fn mp4_single_frame_lasts_one_frame() {
            let frames = clip(1, 32, 24);
            let p = parse(&encode(VideoFormat::Mp4, &frames, 10).unwrap());
            assert_eq!(p.samples.len(), 2);
            assert_eq!(p.durations, [4500, 4500]);
            assert_eq!(p.media_duration, 9000);
            let decoded = decode(&p);
            assert_eq!(decoded.len(), 2);
            assert!(mean_abs_error(&frames[0], &decoded[1]) < 4.0);
        }

        #[test]
        fn mp4_keyframes_every_two_seconds_and_timing_at_odd_rates() {
            let frames = clip(20, 32, 24);
            let p = parse(&encode(VideoFormat::Mp4, &frames, 7).unwrap());
            assert_eq!(p.samples.len(), 20);
            assert_eq!(p.sync_samples, [1, 15]);
            // 90000/7 is not whole: durations of 12857 and 12858 ticks.
            assert!(p.durations.iter().all(|&d| d == 12857 || d == 12858), "{:?}", p.durations);
            let total: u32 = p.durations.iter().sum();
            assert!(total.abs_diff(20 * 90_000 / 7) <= 1, "{total}");
            assert_eq!(decode(&p).len(), 20);
        }
    }
}
