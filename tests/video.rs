//! Orbit videos encoded and read back: GIFs decode to their frames and
//! delays, MP4s hold one H.264 sample per frame with the right timing and
//! decode to their frames (through the tests' MP4 reader), and bad input is
//! refused with a clear error.

mod common {
    //! The parts of `tests/common` this binary uses: the rest (its HTTP,
    //! browser and database clients) would be compiled here for nothing.
    #![allow(dead_code)]
    pub mod mp4;
    pub mod psnr;
}

#[cfg(feature = "mp4")]
use common::mp4;
use common::psnr::rgb8_psnr;
use image::RgbImage;
use radiance::media::video::{VideoError, VideoFormat, encode, validate};

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
    let frames: Vec<RgbImage> = (0..6)
        .map(|t| {
            RgbImage::from_fn(
                20,
                10,
                |x, _| {
                    if x / 4 == t { image::Rgb([250, 200, 7]) } else { image::Rgb([3, 90, 160]) }
                },
            )
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
    let err = check(VideoFormat::Gif, &[RgbImage::new(0, 5)], 10, "GIF frames must be at least 1x1 pixels, got 0x5");
    assert!(matches!(err, VideoError::TooSmall { .. }));
    check(VideoFormat::Gif, &[RgbImage::new(65536, 1)], 10, "GIF frames of 65536x1 pixels are too large");
    assert!(validate(VideoFormat::Gif, 65535, 65535, 60).is_ok());
    #[cfg(feature = "mp4")]
    {
        let err = check(VideoFormat::Mp4, &clip(2, 15, 24), 10, "MP4 frames must be at least 16x16 pixels, got 15x24");
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

/// Encoding time, size and PSNR of each format. By hand, in release:
/// `cargo test --release --test video bench -- --ignored --nocapture`
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
            VideoFormat::Mp4 => mp4::decode(&mp4::parse(&bytes)),
            #[cfg(not(feature = "mp4"))]
            VideoFormat::Mp4 => unreachable!(),
        };
        assert_eq!(decoded.len(), frames.len());
        let mean_psnr = frames.iter().zip(&decoded).map(|(f, d)| rgb8_psnr(f, d)).sum::<f64>() / frames.len() as f64;
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
mod h264 {
    use super::*;
    use common::mp4::{decode, parse};

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
