//! Fuzzing the dataset parsers.

use std::path::Path;

use proptest::prelude::*;
use radiance::engine::dataset::{Dataset, LoadOptions, parse_npy};

/// Loads `root` on another thread: must return (Ok or Err) within 10 s.
fn load_no_hang(root: &Path) -> Result<Dataset, String> {
    let root = root.to_path_buf();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let r = std::panic::catch_unwind(|| Dataset::load(&root, &LoadOptions::default()).map_err(|e| e.to_string()));
        let _ = tx.send(r);
    });
    match rx.recv_timeout(std::time::Duration::from_secs(10)) {
        Ok(Ok(r)) => r,
        Ok(Err(_)) => panic!("Dataset::load panicked"),
        Err(_) => panic!("Dataset::load hung"),
    }
}

fn tiny_png(path: &Path) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    image::RgbaImage::from_pixel(4, 3, image::Rgba([10, 200, 30, 128])).save(path).unwrap();
}

/// JSON values that stress number handling.
fn nasty_json_number() -> impl Strategy<Value = String> {
    prop_oneof![
        Just("0".to_string()),
        Just("-1".to_string()),
        Just("1e308".to_string()),
        Just("-1e308".to_string()),
        Just("1e-320".to_string()),
        Just("1e400".to_string()),
        Just("18446744073709551616".to_string()),
        Just("4294967296".to_string()),
        Just("null".to_string()),
        Just("\"x\"".to_string()),
        Just("[]".to_string()),
        Just("{}".to_string()),
        Just("true".to_string()),
        (-1e3f64..1e3).prop_map(|v| v.to_string()),
        Just("1".to_string()),
        Just("0.5".to_string()),
    ]
}

/// A Blender or ngp transforms file whose numbers are replaced by nasty values.
fn mutated_transforms(ngp: bool) -> impl Strategy<Value = String> {
    (proptest::collection::vec(nasty_json_number(), 40), proptest::collection::vec(any::<bool>(), 40)).prop_map(
        move |(vals, keep)| {
            // `keep[i]` leaves the i-th number of a valid document alone.
            let mut k = 0;
            let mut v = |good: &str| {
                let out = if keep[k % keep.len()] { good.to_string() } else { vals[k % vals.len()].clone() };
                k += 1;
                out
            };
            let m = format!(
                "[[{},{},{},{}],[{},{},{},{}],[{},{},{},{}],[{},{},{},{}]]",
                v("1"), v("0"), v("0"), v("0.5"), v("0"), v("1"), v("0"), v("0"), v("0"), v("0"), v("1"), v("4"), v("0"), v("0"), v("0"), v("1")
            );
            if ngp {
                format!(
                    r#"{{"fl_x":{},"fl_y":{},"cx":{},"cy":{},"w":{},"h":{},"k1":{},"p1":{},"aabb_scale":{},"scale":{},"offset":[{},{},{}],"frames":[{{"file_path":"img.png","transform_matrix":{m}}},{{"file_path":"img.png","transform_matrix":{m},"fl_x":{}}}]}}"#,
                    v("3"), v("3"), v("2"), v("1.5"), v("4"), v("3"), v("0.1"), v("0.01"), v("4"), v("0.33"), v("0.5"), v("0.5"), v("0.5"), v("2")
                )
            } else {
                format!(
                    r#"{{"camera_angle_x":{},"near":{},"far":{},"frames":[{{"file_path":"./img","transform_matrix":{m}}},{{"file_path":"img.png","transform_matrix":{m},"cx":{}}}]}}"#,
                    v("0.7"), v("2"), v("6"), v("1")
                )
            }
        },
    )
}

/// A valid npy header for shape `(rows, 17)` followed by `data`.
fn npy_bytes(rows: usize, data: &[f64]) -> Vec<u8> {
    let mut header = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': ({rows}, 17), }}");
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut b = b"\x93NUMPY\x01\x00".to_vec();
    b.extend_from_slice(&(header.len() as u16).to_le_bytes());
    b.extend_from_slice(header.as_bytes());
    for v in data {
        b.extend_from_slice(&v.to_le_bytes());
    }
    b
}

fn nasty_f64() -> impl Strategy<Value = f64> {
    prop_oneof![
        Just(0.0),
        Just(1.0),
        Just(-1.0),
        Just(f64::NAN),
        Just(f64::INFINITY),
        Just(1e300),
        Just(1e-300),
        Just(f64::MAX),
        -10.0f64..10.0,
        any::<f64>(),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    #[test]
    fn random_bytes_as_transforms_json_never_panic(
        bytes in prop_oneof![
            proptest::collection::vec(any::<u8>(), 0..512),
            "[ -~]{0,300}".prop_map(String::into_bytes),
            mutated_transforms(false).prop_map(String::into_bytes),
        ],
        cut in any::<prop::sample::Index>(),
        truncate in any::<bool>(),
    ) {
        let dir = tempfile::tempdir().unwrap();
        tiny_png(&dir.path().join("img.png"));
        let bytes = if truncate && !bytes.is_empty() { bytes[..cut.index(bytes.len())].to_vec() } else { bytes };
        std::fs::write(dir.path().join("transforms_train.json"), &bytes).unwrap();
        let _ = load_no_hang(dir.path());
    }

    #[test]
    fn random_bytes_as_ngp_transforms_never_panic(
        bytes in prop_oneof![
            proptest::collection::vec(any::<u8>(), 0..512),
            mutated_transforms(true).prop_map(String::into_bytes),
        ],
    ) {
        let dir = tempfile::tempdir().unwrap();
        tiny_png(&dir.path().join("img.png"));
        std::fs::write(dir.path().join("transforms.json"), &bytes).unwrap();
        if let Ok(ds) = load_no_hang(dir.path()) {
            prop_assert!(ds.aabb.min.is_finite() && ds.aabb.max.is_finite() && ds.far.is_finite());
        }
    }

    #[test]
    fn random_bytes_as_poses_bounds_never_panic(
        bytes in prop_oneof![
            proptest::collection::vec(any::<u8>(), 0..600),
            // a valid header with random values, sometimes short
            (proptest::collection::vec(nasty_f64(), 17), 0usize..3).prop_map(|(row, drop)| {
                let mut b = npy_bytes(1, &row);
                b.truncate(b.len() - drop * 3);
                b
            }),
            // a plausible row with one nasty entry
            (nasty_f64(), 0usize..17).prop_map(|(x, i)| {
                let mut row = [0.0, 1.0, 0.0, 0.5, 3.0, -1.0, 0.0, 0.0, 0.0, 4.0, 0.0, 0.0, 1.0, 2.0, 3.5, 1.0, 5.0];
                row[i] = x;
                npy_bytes(1, &row)
            }),
            // random header text after the magic
            "[ -~]{0,120}".prop_map(|h| {
                let mut b = b"\x93NUMPY\x01\x00".to_vec();
                b.extend_from_slice(&(h.len() as u16).to_le_bytes());
                b.extend_from_slice(h.as_bytes());
                b
            }),
        ],
    ) {
        let _ = parse_npy(&bytes, Path::new("poses_bounds.npy"));
        let dir = tempfile::tempdir().unwrap();
        tiny_png(&dir.path().join("images_8/a.png"));
        std::fs::write(dir.path().join("poses_bounds.npy"), &bytes).unwrap();
        if let Ok(ds) = load_no_hang(dir.path()) {
            prop_assert!(ds.aabb.min.is_finite() && ds.aabb.max.is_finite() && ds.near > 0.0 && ds.far > ds.near);
        }
    }
}
