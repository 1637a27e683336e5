//! The one MP4 (ISO BMFF) reader of the tests: the boxes of a file, the
//! single H.264 track our encoder writes parsed into what tests check
//! (timing, sizes, parameter sets, samples), and those samples decoded back
//! to RGB frames.

/// A box: its type and the byte range of its payload in the file.
#[derive(Clone, Copy, Debug)]
struct Bx {
    kind: [u8; 4],
    start: usize,
    end: usize,
}

/// The boxes in `data[start..end]`, in order; they must fill the range.
fn children(data: &[u8], start: usize, end: usize) -> Vec<Bx> {
    let mut out = Vec::new();
    let mut at = start;
    while at < end {
        assert!(at + 8 <= end, "truncated box header at {at}");
        let mut size = be32(data, at) as usize;
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

/// The boxes of an MP4 buffer at one level: `(type, payload)`.
pub fn boxes(b: &[u8]) -> Vec<(String, &[u8])> {
    let kind = |k: &[u8; 4]| String::from_utf8_lossy(k).into_owned();
    children(b, 0, b.len()).into_iter().map(|x| (kind(&x.kind), &b[x.start..x.end])).collect()
}

/// The payload of the box at `path` (e.g. `["moov", "trak", "tkhd"]`).
pub fn child<'a>(b: &'a [u8], path: &[&str]) -> &'a [u8] {
    let mut cur = b;
    for name in path {
        cur = boxes(cur).into_iter().find(|(k, _)| k == name).unwrap_or_else(|| panic!("no {name} box")).1;
    }
    cur
}

/// The width and height in an MP4's track header (16.16 fixed point, at the
/// end of `tkhd`).
pub fn track_size(b: &[u8]) -> (u32, u32) {
    let tkhd = child(b, &["moov", "trak", "tkhd"]);
    (be32(tkhd, tkhd.len() - 8) >> 16, be32(tkhd, tkhd.len() - 4) >> 16)
}

/// What a test reads back from an MP4 file of one H.264 track.
pub struct Parsed {
    pub top: Vec<[u8; 4]>,
    pub timescale: u32,
    pub media_duration: u32,
    /// Width and height in `avc1` and `tkhd`.
    pub size: (u32, u32),
    pub tkhd_size: (u32, u32),
    pub durations: Vec<u32>,
    pub sync_samples: Vec<u32>,
    /// `avcC`: profile, compatibility, level, SPS and PPS.
    pub profile: (u8, u8, u8),
    pub sps: Vec<u8>,
    pub pps: Vec<u8>,
    /// The samples' bytes (4-byte length-prefixed NAL units).
    pub samples: Vec<Vec<u8>>,
}

/// What the sample entry (`avc1` and its `avcC`) says about the stream.
struct AvcConfig {
    size: (u32, u32),
    profile: (u8, u8, u8),
    sps: Vec<u8>,
    pps: Vec<u8>,
}

fn avc_config(data: &[u8], stbl: Bx) -> AvcConfig {
    let stsd = find(data, stbl, b"stsd");
    assert_eq!(be32(data, stsd.start + 4), 1, "one sample entry");
    let avc1 = children(data, stsd.start + 8, stsd.end)[0];
    assert_eq!(&avc1.kind, b"avc1");
    let size = (
        u32::from(u16::from_be_bytes([data[avc1.start + 24], data[avc1.start + 25]])),
        u32::from(u16::from_be_bytes([data[avc1.start + 26], data[avc1.start + 27]])),
    );
    let avcc = children(data, avc1.start + 78, avc1.end).into_iter().find(|b| &b.kind == b"avcC").expect("avcC");
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
    AvcConfig { size, profile: (c[1], c[2], c[3]), sps, pps }
}

/// The bytes of every sample, found through the chunk offsets (`stco`),
/// samples per chunk (`stsc`) and sizes (`stsz`); each must lie in `mdat`.
fn sample_bytes(data: &[u8], stbl: Bx, mdat: Bx) -> Vec<Vec<u8>> {
    let stsz = find(data, stbl, b"stsz");
    let fixed = be32(data, stsz.start + 4);
    let count = be32(data, stsz.start + 8) as usize;
    let sizes: Vec<usize> =
        (0..count).map(|i| if fixed != 0 { fixed } else { be32(data, stsz.start + 12 + 4 * i) } as usize).collect();
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
    samples
}

/// Parses an MP4 file of one H.264 track, checking its structure on the way.
pub fn parse(data: &[u8]) -> Parsed {
    let top = children(data, 0, data.len());
    let file = Bx { kind: *b"file", start: 0, end: data.len() };
    let trak = path(data, file, &[b"moov", b"trak"]);
    let mdhd = path(data, trak, &[b"mdia", b"mdhd"]);
    assert_eq!(data[mdhd.start], 0, "mdhd version 0");
    let stbl = path(data, trak, &[b"mdia", b"minf", b"stbl"]);
    let AvcConfig { size, profile, sps, pps } = avc_config(data, stbl);

    let stts = find(data, stbl, b"stts");
    let mut durations = Vec::new();
    for e in 0..be32(data, stts.start + 4) as usize {
        let at = stts.start + 8 + 8 * e;
        durations.extend(std::iter::repeat_n(be32(data, at + 4), be32(data, at) as usize));
    }
    let stss = find(data, stbl, b"stss");
    let sync_samples = (0..be32(data, stss.start + 4) as usize).map(|e| be32(data, stss.start + 8 + 4 * e)).collect();
    let mdat = *top.iter().find(|b| &b.kind == b"mdat").expect("mdat");

    Parsed {
        top: top.iter().map(|b| b.kind).collect(),
        timescale: be32(data, mdhd.start + 12),
        media_duration: be32(data, mdhd.start + 16),
        size,
        tkhd_size: track_size(data),
        durations,
        sync_samples,
        profile,
        sps,
        pps,
        samples: sample_bytes(data, stbl, mdat),
    }
}

/// Decodes the samples with OpenH264, parameter sets from `avcC` first,
/// into RGB frames.
#[cfg(feature = "mp4")]
pub fn decode(p: &Parsed) -> Vec<image::RgbImage> {
    use openh264::decoder::Decoder;
    use openh264::formats::YUVSource;

    let annex_b = |nal: &[u8]| [&[0, 0, 0, 1][..], nal].concat();
    let mut decoder = Decoder::new().unwrap();
    let mut out = Vec::new();
    let mut keep = |yuv: openh264::decoder::DecodedYUV<'_>| {
        let (w, h) = yuv.dimensions();
        let mut rgb = vec![0; w * h * 3];
        yuv.write_rgb8(&mut rgb);
        out.push(image::RgbImage::from_raw(w as u32, h as u32, rgb).unwrap());
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
