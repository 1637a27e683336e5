//! Pose estimation in tests: the real COLMAP and ffmpeg (a test that needs
//! them fails when they are missing, it does not skip), and photos of noise,
//! which no two of share a feature.

use std::time::Duration;

use radiance::jobs::poses::PosesSetup;
use radiance::poses::{Tools, colmap, video};

pub fn tools() -> Tools {
    let colmap = colmap::find(None).unwrap_or_else(|e| panic!("this test needs COLMAP: {e}"));
    let ffmpeg = video::find(None).unwrap_or_else(|e| panic!("this test needs ffmpeg: {e}"));
    Tools { colmap, ffmpeg: Some(ffmpeg) }
}

/// What a service with COLMAP runs photo-only uploads with.
pub fn setup() -> PosesSetup {
    PosesSetup { tools: tools(), max_size: 800, time_limit: Duration::from_secs(300) }
}

/// `n` PNGs of 160x120 random colours, `n0.png`, `n1.png`, ...
pub fn noise_pngs(n: usize) -> Vec<(String, Vec<u8>)> {
    let mut state = 0x2545f4914f6cdd1du64;
    (0..n)
        .map(|k| {
            let img = image::RgbImage::from_fn(160, 120, |_, _| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                image::Rgb([(state >> 24) as u8, (state >> 32) as u8, (state >> 40) as u8])
            });
            let mut png = Vec::new();
            img.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png).unwrap();
            (format!("n{k}.png"), png)
        })
        .collect()
}
