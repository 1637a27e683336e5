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

/// A PNG of a few kilobytes whose header declares `w`x`h` 8-bit RGB pixels
/// (gigabytes decoded); its compressed data, zeros, end long before that.
pub fn bomb_png(w: u32, h: u32) -> Vec<u8> {
    fn chunk(out: &mut Vec<u8>, kind: &[u8], data: &[u8]) {
        out.extend((data.len() as u32).to_be_bytes());
        let start = out.len();
        out.extend(kind);
        out.extend(data);
        let crc = crc32fast::hash(&out[start..]);
        out.extend(crc.to_be_bytes());
    }
    let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut ihdr = Vec::new();
    ihdr.extend(w.to_be_bytes());
    ihdr.extend(h.to_be_bytes());
    ihdr.extend([8, 2, 0, 0, 0]);
    chunk(&mut png, b"IHDR", &ihdr);
    let mut z = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::best());
    std::io::Write::write_all(&mut z, &vec![0u8; 4 << 20]).unwrap();
    chunk(&mut png, b"IDAT", &z.finish().unwrap());
    chunk(&mut png, b"IEND", &[]);
    png
}

/// The peak resident memory (`VmHWM`) of process `pid`, bytes.
pub fn peak_rss(pid: u32) -> u64 {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    let line = s.lines().find(|l| l.starts_with("VmHWM:")).unwrap();
    line.split_whitespace().nth(1).unwrap().parse::<u64>().unwrap() * 1024
}
