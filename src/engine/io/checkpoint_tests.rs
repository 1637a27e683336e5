//! Unit tests of `checkpoint.rs` (kept apart so the module reads in one sitting).

use super::*;
use proptest::prelude::*;
use serde_json::json;

fn sample() -> Checkpoint {
    let mut c = Checkpoint::new("instant", 12345);
    c.meta = json!({"config": {"levels": 16, "lr": 0.01}, "scene": {"scale": 0.33, "offset": [0.5, 0.5, 0.5]}, "note": "ünïcode"});
    c.insert(
        "params",
        vec![1.0f32, -2.5, 0.0, -0.0, f32::NAN, f32::INFINITY, f32::NEG_INFINITY, f32::MIN_POSITIVE / 2.0],
    );
    c.insert("adam.m", vec![0.125f32; 5]);
    c.insert("grid", vec![0u8, 1, 255, 7]);
    c.insert("rng", vec![0u64, 1, u64::MAX, 0x0123_4567_89ab_cdef]);
    c.insert("empty", Vec::<f32>::new());
    c
}

/// Bitwise comparison (NaN payloads and signed zeros included).
fn assert_same(a: &Checkpoint, b: &Checkpoint) {
    assert_eq!(a.kind, b.kind);
    assert_eq!(a.step, b.step);
    assert_eq!(a.meta, b.meta);
    assert_eq!(a.tensors.len(), b.tensors.len());
    for ((na, ta), (nb, tb)) in a.tensors.iter().zip(&b.tensors) {
        assert_eq!(na, nb);
        match (ta, tb) {
            (Tensor::F32(x), Tensor::F32(y)) => {
                let xb: Vec<u32> = x.iter().map(|v| v.to_bits()).collect();
                let yb: Vec<u32> = y.iter().map(|v| v.to_bits()).collect();
                assert_eq!(xb, yb, "{na}");
            }
            _ => assert_eq!(ta, tb, "{na}"),
        }
    }
}

/// Builds a file with a hand-written header and a valid checksum.
fn craft(version: u32, header: &[u8], payload: &[u8]) -> Vec<u8> {
    let mut v = MAGIC.to_vec();
    v.extend_from_slice(&version.to_le_bytes());
    v.extend_from_slice(&(header.len() as u32).to_le_bytes());
    v.extend_from_slice(header);
    v.extend_from_slice(payload);
    let crc = crc32fast::hash(&v);
    v.extend_from_slice(&crc.to_le_bytes());
    v
}

#[test]
fn round_trip_all_tensor_types() {
    let c = sample();
    let bytes = c.to_bytes();
    let d = Checkpoint::from_bytes(&bytes).unwrap();
    assert_same(&c, &d);
    assert_eq!(d.to_bytes(), bytes, "re-encoding is byte-identical");
    assert!(d.f32("params").unwrap()[4].is_nan());
    assert_eq!(d.u8("grid").unwrap(), &[0, 1, 255, 7]);
    assert_eq!(d.u64("rng").unwrap()[2], u64::MAX);
    assert!(d.f32("empty").unwrap().is_empty());
}

#[test]
fn round_trip_minimal_and_large() {
    let c = Checkpoint::new("", 0);
    assert_same(&c, &Checkpoint::from_bytes(&c.to_bytes()).unwrap());

    // Larger than one write chunk, so the chunked writer is exercised.
    let mut c = Checkpoint::new("nerf", u64::MAX);
    c.insert("params", (0..100_003).map(|i| i as f32 * 0.5 - 7.0).collect::<Vec<f32>>());
    c.insert("ids", (0..40_001u64).map(|i| i.wrapping_mul(0x9E37_79B9_7F4A_7C15)).collect::<Vec<u64>>());
    let bytes = c.to_bytes();
    let expected_len = 16 + c.header_json().len() + 100_003 * 4 + 40_001 * 8 + 4;
    assert_eq!(bytes.len(), expected_len);
    assert_same(&c, &Checkpoint::from_bytes(&bytes).unwrap());
}

#[test]
fn layout_is_as_documented() {
    let mut c = Checkpoint::new("nerf", 7);
    c.meta = json!({"a": 1});
    c.insert("w", vec![1.0f32, 2.0]);
    c.insert("g", vec![9u8]);
    c.insert("s", vec![3u64]);
    let b = c.to_bytes();
    assert_eq!(&b[..8], b"RADIANCE");
    assert_eq!(read_u32(&b, 8), 1);
    let hl = read_u32(&b, 12) as usize;
    let header: serde_json::Value = serde_json::from_slice(&b[16..16 + hl]).unwrap();
    assert_eq!(
        header,
        json!({"kind": "nerf", "step": 7, "meta": {"a": 1}, "tensors": [
            {"name": "w", "dtype": "f32", "len": 2},
            {"name": "g", "dtype": "u8", "len": 1},
            {"name": "s", "dtype": "u64", "len": 1}]})
    );
    let mut payload = Vec::new();
    payload.extend_from_slice(&1.0f32.to_le_bytes());
    payload.extend_from_slice(&2.0f32.to_le_bytes());
    payload.push(9);
    payload.extend_from_slice(&3u64.to_le_bytes());
    assert_eq!(&b[16 + hl..b.len() - 4], &payload[..]);
    let crc = crc32fast::hash(&b[..b.len() - 4]);
    assert_eq!(&b[b.len() - 4..], &crc.to_le_bytes());
}

#[test]
fn every_truncation_is_a_truncated_error() {
    let bytes = sample().to_bytes();
    let hl = read_u32(&bytes, 12) as u64;
    for cut in 0..bytes.len() {
        match Checkpoint::from_bytes(&bytes[..cut]) {
            Err(CheckpointError::Truncated { expected, found, path: None }) => {
                assert_eq!(found, cut as u64);
                assert!(expected > found, "cut {cut}: expected {expected}");
                if cut as u64 >= 16 + hl + 4 {
                    assert_eq!(expected, bytes.len() as u64, "cut {cut}");
                }
            }
            other => panic!("cut at {cut}: {other:?}"),
        }
    }
    let msg = Checkpoint::from_bytes(&bytes[..bytes.len() - 1]).unwrap_err().to_string();
    assert_eq!(msg, format!("truncated: expected {} bytes, found {}", bytes.len(), bytes.len() - 1));
}

#[test]
fn every_single_bit_flip_is_an_error() {
    let bytes = sample().to_bytes();
    let mut corrupt = bytes.clone();
    for i in 0..bytes.len() {
        for bit in 0..8 {
            corrupt[i] ^= 1 << bit;
            let r = Checkpoint::from_bytes(&corrupt);
            assert!(r.is_err(), "flip of byte {i} bit {bit} went undetected");
            // Past the preamble every flip is caught by the checksum or
            // a size check.
            if i >= 16 {
                assert!(
                    matches!(r, Err(CheckpointError::ChecksumMismatch { .. } | CheckpointError::Truncated { .. })),
                    "byte {i} bit {bit}: {r:?}"
                );
            }
            corrupt[i] ^= 1 << bit;
        }
    }
    assert_eq!(corrupt, bytes);
    // A payload flip is a checksum error.
    let last_payload = bytes.len() - 5;
    corrupt[last_payload] ^= 0x10;
    assert_eq!(Checkpoint::from_bytes(&corrupt).unwrap_err().to_string(), "checksum mismatch: file is corrupted");
}

#[test]
fn wrong_magic() {
    let mut bytes = sample().to_bytes();
    bytes[0] = b'X';
    let err = Checkpoint::from_bytes(&bytes).unwrap_err();
    assert!(matches!(err, CheckpointError::NotACheckpoint { .. }));
    assert_eq!(err.to_string(), "not a radiance checkpoint");
    assert!(matches!(Checkpoint::from_bytes(b"PK\x03\x04"), Err(CheckpointError::NotACheckpoint { .. })));
    assert!(matches!(
        Checkpoint::from_bytes(b"{\"kind\": \"nerf\", \"step\": 1}"),
        Err(CheckpointError::NotACheckpoint { .. })
    ));
}

#[test]
fn future_and_past_versions() {
    let mut bytes = sample().to_bytes();
    bytes[8..12].copy_from_slice(&7u32.to_le_bytes());
    let err = Checkpoint::from_bytes(&bytes).unwrap_err();
    assert!(matches!(err, CheckpointError::UnsupportedVersion { found: 7, .. }));
    assert_eq!(err.to_string(), "checkpoint format version 7 is newer than this build supports (1)");
    // Only the preamble is needed to tell.
    assert!(matches!(Checkpoint::from_bytes(&bytes[..12]), Err(CheckpointError::UnsupportedVersion { found: 7, .. })));
    bytes[8..12].copy_from_slice(&0u32.to_le_bytes());
    let err = Checkpoint::from_bytes(&bytes).unwrap_err();
    assert_eq!(err.to_string(), "checkpoint format version 0 is not supported (this build reads version 1)");
}

#[test]
fn absurd_header_length_is_truncated_not_allocated() {
    let mut bytes = sample().to_bytes();
    bytes[12..16].copy_from_slice(&u32::MAX.to_le_bytes());
    match Checkpoint::from_bytes(&bytes) {
        Err(CheckpointError::Truncated { expected, found, .. }) => {
            assert_eq!(expected, 16 + u32::MAX as u64 + 4);
            assert_eq!(found, bytes.len() as u64);
        }
        other => panic!("{other:?}"),
    }
}

#[test]
fn absurd_tensor_lengths_are_truncated_not_allocated() {
    for (dtype, len) in
        [("f32", 1u64 << 40), ("u64", 1u64 << 61), ("u64", u64::MAX), ("f32", u64::MAX / 4 + 1), ("u8", u64::MAX - 10)]
    {
        let header =
            format!(r#"{{"kind":"x","step":0,"meta":null,"tensors":[{{"name":"a","dtype":"{dtype}","len":{len}}}]}}"#);
        let bytes = craft(1, header.as_bytes(), &[0u8; 64]);
        match Checkpoint::from_bytes(&bytes) {
            Err(CheckpointError::Truncated { expected, found, .. }) => {
                assert!(expected > found, "{dtype} {len}");
            }
            other => panic!("{dtype} {len}: {other:?}"),
        }
    }
}

#[test]
fn header_errors() {
    let cases: [(&[u8], &str); 6] = [
        (b"not json", "expected"),
        (b"{\"kind\":\"x\",\"step\":0,\"meta\":null}", "missing field `tensors`"),
        (b"{\"kind\":\"x\",\"step\":-1,\"meta\":null,\"tensors\":[]}", "invalid value"),
        (
            b"{\"kind\":\"x\",\"step\":0,\"meta\":null,\"tensors\":[{\"name\":\"a\",\"dtype\":\"f16\",\"len\":0}]}",
            "tensor \"a\" has unknown dtype \"f16\"",
        ),
        (b"{\"kind\":\"x\",\"step\":0,\"meta\":null,\"tensors\":[]} trailing", "trailing characters"),
        (b"\xff\xfe", "expected"),
    ];
    for (header, needle) in cases {
        let err = Checkpoint::from_bytes(&craft(1, header, &[])).unwrap_err();
        assert!(matches!(err, CheckpointError::Header { .. }), "{err:?}");
        let msg = err.to_string();
        assert!(msg.starts_with("invalid checkpoint header: "), "{msg}");
        assert!(msg.contains(needle), "{msg} lacks {needle}");
    }
    // Unknown extra header fields are tolerated (forward-compatible additions).
    let ok = craft(1, br#"{"kind":"x","step":3,"meta":{},"tensors":[],"extra":1}"#, &[]);
    assert_eq!(Checkpoint::from_bytes(&ok).unwrap().step, 3);
}

#[test]
fn trailing_bytes() {
    let mut bytes = sample().to_bytes();
    bytes.extend_from_slice(b"junk");
    let err = Checkpoint::from_bytes(&bytes).unwrap_err();
    assert!(matches!(err, CheckpointError::TrailingBytes { extra: 4, .. }), "{err:?}");
    assert_eq!(err.to_string(), "4 unexpected bytes after the end of the checkpoint");
    // Two checkpoints back to back.
    let one = sample().to_bytes();
    let two = [one.clone(), one.clone()].concat();
    assert!(matches!(
        Checkpoint::from_bytes(&two),
        Err(CheckpointError::TrailingBytes { extra, .. }) if extra == one.len() as u64
    ));
}

#[test]
fn accessors_and_errors() {
    let mut c = sample();
    assert_eq!(c.tensor("grid").map(Tensor::dtype), Some("u8"));
    assert!(c.tensor("nope").is_none());
    assert_eq!(c.f32("adam.m").unwrap(), &[0.125; 5]);
    let err = c.f32("nope").unwrap_err();
    assert!(matches!(&err, CheckpointError::MissingTensor { name, .. } if name == "nope"));
    assert_eq!(err.to_string(), "checkpoint has no tensor named \"nope\"");
    let err = c.u64("grid").unwrap_err();
    assert!(matches!(err, CheckpointError::WrongType { expected: "u64", found: "u8", .. }));
    assert_eq!(err.to_string(), "tensor \"grid\" has dtype u8, expected u64");
    assert!(matches!(c.u8("params"), Err(CheckpointError::WrongType { .. })));
    let err = c.u8("params").unwrap_err().with_path(Path::new("m.ckpt"));
    assert_eq!(err.to_string(), "m.ckpt: tensor \"params\" has dtype f32, expected u8");
    assert_eq!(err.path(), Some(Path::new("m.ckpt")));

    // take_f32 moves the buffer out without copying and removes the entry.
    let ptr = c.f32("adam.m").unwrap().as_ptr();
    let names_before: Vec<String> = c.tensors.iter().map(|(n, _)| n.clone()).collect();
    let m = c.take_f32("adam.m").unwrap();
    assert_eq!(m.as_ptr(), ptr);
    assert!(matches!(c.f32("adam.m"), Err(CheckpointError::MissingTensor { .. })));
    assert!(matches!(c.take_f32("adam.m"), Err(CheckpointError::MissingTensor { .. })));
    // A wrong-type take leaves the tensor where it was.
    assert!(matches!(c.take_f32("grid"), Err(CheckpointError::WrongType { .. })));
    let names_after: Vec<&str> = c.tensors.iter().map(|(n, _)| n.as_str()).collect();
    let expected: Vec<&str> = names_before.iter().map(String::as_str).filter(|n| *n != "adam.m").collect();
    assert_eq!(names_after, expected);
    assert_eq!(c.take_u8("grid").unwrap(), vec![0, 1, 255, 7]);
    assert_eq!(c.take_u64("rng").unwrap()[3], 0x0123_4567_89ab_cdef);

    // insert replaces in place.
    c.insert("params", vec![1u8]);
    assert_eq!(c.tensors[0].0, "params");
    assert_eq!(c.u8("params").unwrap(), &[1]);
    if let Some(Tensor::U8(v)) = c.tensor_mut("params") {
        v.push(2);
    }
    assert_eq!(c.tensor("params").unwrap().len(), 2);
    assert_eq!(Tensor::U64(vec![1, 2]).byte_len(), 16);
    assert!(Tensor::F32(vec![]).is_empty());
}

#[test]
fn save_and_load_through_temp_dir() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("model.ckpt");
    let c = sample();
    c.save(&path).unwrap();
    assert_same(&c, &Checkpoint::load(&path).unwrap());
    assert_eq!(std::fs::read(&path).unwrap(), c.to_bytes());

    // Overwrite with a later step.
    let mut c2 = c.clone();
    c2.step += 1;
    c2.save(&path).unwrap();
    assert_eq!(Checkpoint::load(&path).unwrap().step, c.step + 1);

    let entries: Vec<_> =
        std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name().into_string().unwrap()).collect();
    assert_eq!(entries, vec!["model.ckpt"]);
}

#[test]
fn load_errors_name_the_path() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("model.ckpt");
    let mut bytes = sample().to_bytes();
    let n = bytes.len();
    bytes[n - 10] ^= 1;
    std::fs::write(&path, &bytes).unwrap();
    let err = Checkpoint::load(&path).unwrap_err();
    assert_eq!(err.path(), Some(path.as_path()));
    assert_eq!(err.to_string(), format!("{}: checksum mismatch: file is corrupted", path.display()));

    std::fs::write(&path, &bytes[..n - 3]).unwrap();
    let msg = Checkpoint::load(&path).unwrap_err().to_string();
    assert!(msg.starts_with(&format!("{}: truncated: expected {n} bytes", path.display())), "{msg}");

    std::fs::write(&path, b"").unwrap();
    let msg = Checkpoint::load(&path).unwrap_err().to_string();
    assert_eq!(msg, format!("{}: truncated: expected 20 bytes, found 0", path.display()));

    let missing = dir.path().join("missing.ckpt");
    let err = Checkpoint::load(&missing).unwrap_err();
    assert!(matches!(&err, CheckpointError::Io { source, .. } if source.kind() == io::ErrorKind::NotFound));
    assert!(err.to_string().starts_with(&format!("{}: ", missing.display())));
}

#[test]
fn save_into_missing_directory_fails_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("no").join("model.ckpt");
    let err = sample().save(&path).unwrap_err();
    assert!(matches!(err, CheckpointError::Io { .. }));
    assert!(err.to_string().contains("model.ckpt"));
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
}

#[test]
fn loading_a_large_checkpoint_is_fast() {
    // 64 MB of f32 payload; decoding should be bulk conversion, far from
    // the time limit even on a loaded machine.
    let mut c = Checkpoint::new("instant", 1);
    c.insert("params", vec![0.5f32; 16 << 20]);
    let bytes = c.to_bytes();
    let t = std::time::Instant::now();
    let d = Checkpoint::from_bytes(&bytes).unwrap();
    let elapsed = t.elapsed();
    assert_eq!(d.f32("params").unwrap().len(), 16 << 20);
    eprintln!("decoded a 64 MiB checkpoint in {elapsed:?}");
    assert!(elapsed.as_secs_f64() < 5.0, "{elapsed:?}");
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..512)) {
        let _ = Checkpoint::from_bytes(&bytes);
    }

    #[test]
    fn random_bytes_after_valid_preamble_never_panic(
        header_len in any::<u32>(),
        rest in proptest::collection::vec(any::<u8>(), 0..512),
    ) {
        let mut bytes = MAGIC.to_vec();
        bytes.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
        bytes.extend_from_slice(&(header_len % 600).to_le_bytes());
        bytes.extend_from_slice(&rest);
        let _ = Checkpoint::from_bytes(&bytes);
    }

    #[test]
    fn round_trip_random(
        kind in ".{0,12}",
        step in any::<u64>(),
        f in proptest::collection::vec(any::<u32>(), 0..64),
        b in proptest::collection::vec(any::<u8>(), 0..64),
        u in proptest::collection::vec(any::<u64>(), 0..64),
    ) {
        let mut c = Checkpoint::new(kind, step);
        c.meta = json!({"n": f.len()});
        c.insert("f", f.iter().map(|&x| f32::from_bits(x)).collect::<Vec<f32>>());
        c.insert("b", b);
        c.insert("u", u);
        let bytes = c.to_bytes();
        let d = Checkpoint::from_bytes(&bytes).unwrap();
        assert_same(&c, &d);
    }
}
