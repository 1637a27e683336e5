//! Fuzzing the upload extractor: random bytes and corrupted valid archives
//! (zip, tar, tar.gz) never panic or hang, and nothing is ever written
//! outside the destination folder.

use std::io::Write;
use std::path::Path;

use proptest::prelude::*;
use radiance::api::archive::{ArchiveKind, Limits, extract};

const LIMITS: Limits = Limits { max_unpacked_bytes: 1 << 20, max_entries: 64 };

fn valid_tar() -> Vec<u8> {
    let mut b = tar::Builder::new(Vec::new());
    for (name, body) in [("scene/transforms_train.json", &b"{\"frames\": []}"[..]), ("scene/train/r_0.png", b"png?")] {
        let mut h = tar::Header::new_gnu();
        h.set_size(body.len() as u64);
        h.set_mode(0o644);
        h.set_cksum();
        b.append_data(&mut h, name, body).unwrap();
    }
    b.into_inner().unwrap()
}

fn valid_tar_gz() -> Vec<u8> {
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    e.write_all(&valid_tar()).unwrap();
    e.finish().unwrap()
}

fn valid_zip() -> Vec<u8> {
    let mut z = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let opts = zip::write::SimpleFileOptions::default();
    z.start_file("scene/transforms_train.json", opts).unwrap();
    z.write_all(b"{\"frames\": []}").unwrap();
    z.start_file("scene/train/r_0.png", opts).unwrap();
    z.write_all(b"png?").unwrap();
    z.finish().unwrap().into_inner()
}

/// Extracts into `root/dest` and checks nothing appeared beside `dest`.
fn check(kind: ArchiveKind, bytes: &[u8]) {
    let root = tempfile::tempdir().unwrap();
    let dest = root.path().join("dest");
    std::fs::create_dir(&dest).unwrap();
    let _ = extract(kind, bytes, &dest, LIMITS);
    let outside: Vec<_> = std::fs::read_dir(root.path()).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert_eq!(outside, vec![std::ffi::OsString::from("dest")], "files written outside the destination");
    assert!(dir_bytes(&dest) <= LIMITS.max_unpacked_bytes, "unpacked past the limit");
}

fn dir_bytes(p: &Path) -> u64 {
    std::fs::read_dir(p)
        .map(|rd| {
            rd.flatten()
                .map(|e| {
                    let m = e.metadata().unwrap();
                    if m.is_dir() { dir_bytes(&e.path()) } else { m.len() }
                })
                .sum()
        })
        .unwrap_or(0)
}

const KINDS: [ArchiveKind; 3] = [ArchiveKind::Zip, ArchiveKind::Tar, ArchiveKind::TarGz];

#[test]
fn valid_archives_extract() {
    for (kind, bytes) in
        [(ArchiveKind::Zip, valid_zip()), (ArchiveKind::Tar, valid_tar()), (ArchiveKind::TarGz, valid_tar_gz())]
    {
        let root = tempfile::tempdir().unwrap();
        extract(kind, &bytes, root.path(), LIMITS).unwrap();
        assert!(root.path().join("scene/train/r_0.png").is_file(), "{kind:?}");
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 96, ..ProptestConfig::default() })]

    #[test]
    fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..2048), k in 0usize..3) {
        check(KINDS[k], &bytes);
    }

    #[test]
    fn corrupted_archives_never_panic(
        k in 0usize..3,
        flips in proptest::collection::vec((any::<usize>(), any::<u8>()), 1..8),
        cut in any::<usize>(),
        truncate in any::<bool>(),
    ) {
        let mut bytes = match k { 0 => valid_zip(), 1 => valid_tar(), _ => valid_tar_gz() };
        for (at, v) in flips {
            let n = bytes.len();
            bytes[at % n] ^= v;
        }
        if truncate {
            let n = bytes.len();
            bytes.truncate(cut % n);
        }
        check(KINDS[k], &bytes);
    }
}
