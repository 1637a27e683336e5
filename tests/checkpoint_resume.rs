//! Checkpoints restore a run exactly, and training is deterministic.

mod common {
    //! The parts of `tests/common` this binary uses: the rest (its HTTP,
    //! browser and database clients) would be compiled here for nothing.
    #![allow(dead_code)]
    pub mod tiny;
}

use std::sync::atomic::AtomicBool;

use common::tiny::{self, NerfModel};
use radiance::engine::dataset::Dataset;
use radiance::engine::dataset::synthetic::BallScene;
use radiance::engine::models::Model;
use radiance::engine::nn::adam::{Adam, AdamConfig};
use radiance::engine::train::persist;
use radiance::engine::train::trainer::{TrainState, Trainer};

fn trainer(ds: &Dataset, steps: u64) -> Trainer<'_> {
    let model = NerfModel::new(tiny::nerf_micro(true), ds.scene(), 3);
    let adam = Adam::new(AdamConfig { lr: 5e-3, lr_end: 5e-4, ..Default::default() }, model.params().len());
    let cfg = tiny::train_config(9, 64, steps);
    Trainer::new(Box::new(model), adam, cfg, TrainState::default(), ds)
}

#[test]
fn resuming_from_a_checkpoint_continues_exactly() {
    let ds = BallScene { size: 12, views: 8, ..Default::default() }.dataset();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.ckpt");
    let no = AtomicBool::new(false);

    let mut straight = trainer(&ds, 40);
    straight.run(&no, |_, _| true);

    let mut first = trainer(&ds, 40);
    first.run(&no, |t, p| {
        if p.step == 20 {
            persist::save(&path, &*t.model, &t.adam, &t.config, &t.state, t.transients.as_ref()).unwrap();
            return false;
        }
        true
    });
    let r = persist::load(&path).unwrap();
    assert_eq!(r.state.step, 20);
    let mut resumed = Trainer::new(r.model, r.adam, r.train, r.state, &ds);
    resumed.run(&no, |_, _| true);
    assert_eq!(resumed.state.step, 40);
    assert_eq!(resumed.model.params(), straight.model.params(), "parameters differ after resuming");
    assert_eq!(resumed.adam.m, straight.adam.m);
    assert_eq!(resumed.model.state_tensors(), straight.model.state_tensors(), "occupancy grid differs");
}

#[test]
fn same_seed_same_model() {
    let ds = BallScene { size: 12, views: 8, ..Default::default() }.dataset();
    let no = AtomicBool::new(false);
    let mut a = trainer(&ds, 15);
    a.run(&no, |_, _| true);
    let mut b = trainer(&ds, 15);
    b.run(&no, |_, _| true);
    assert_eq!(a.model.params(), b.model.params());
    let mut c = trainer(&ds, 15);
    c.config.seed = 10;
    c.run(&no, |_, _| true);
    assert_ne!(a.model.params(), c.model.params(), "another seed gives another model");
}

#[test]
fn corrupt_checkpoints_are_clear_errors() {
    let ds = BallScene { size: 12, views: 8, ..Default::default() }.dataset();
    let t = trainer(&ds, 1);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.ckpt");
    persist::save(&path, &*t.model, &t.adam, &t.config, &t.state, t.transients.as_ref()).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
    let e = persist::load(&path).err().expect("truncated file must not load").to_string();
    assert!(e.contains("m.ckpt") && e.contains("truncated"), "{e}");
    let mut flipped = bytes.clone();
    flipped[bytes.len() / 2] ^= 0x10;
    std::fs::write(&path, &flipped).unwrap();
    let e = persist::load(&path).err().expect("corrupted file must not load").to_string();
    assert!(e.contains("checksum"), "{e}");
}

#[test]
fn non_finite_parameters_are_never_saved() {
    let ds = BallScene { size: 12, views: 8, ..Default::default() }.dataset();
    let mut t = trainer(&ds, 1);
    t.model.params_mut()[5] = f32::NAN;
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.ckpt");
    assert!(persist::save(&path, &*t.model, &t.adam, &t.config, &t.state, t.transients.as_ref()).is_err());
    assert!(!path.exists());
}

#[test]
fn a_stripped_checkpoint_renders_the_same_and_cannot_resume() {
    use radiance::engine::view::render_view;
    let ds = BallScene { size: 12, views: 8, ..Default::default() }.dataset();
    let mut t = trainer(&ds, 12);
    t.run(&AtomicBool::new(false), |_, _| true);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.ckpt");
    persist::save(&path, &*t.model, &t.adam, &t.config, &t.state, t.transients.as_ref()).unwrap();
    let full_len = std::fs::metadata(&path).unwrap().len();
    let camera = &ds.frames[ds.train[0]].camera;
    let before = persist::load(&path).unwrap();
    assert!(!before.render_only);
    let want = render_view(&*before.model, camera, [1.0; 3]);

    assert!(persist::strip_training_state(&path).unwrap(), "the first strip rewrites the file");
    let stripped_len = std::fs::metadata(&path).unwrap().len();
    // Adam's two moments go: two f32 per parameter.
    let moments = 8 * before.model.params().len() as u64;
    assert!(full_len - stripped_len >= moments, "{full_len} -> {stripped_len} bytes, moments {moments}");
    let after = persist::load(&path).unwrap();
    assert!(after.render_only);
    assert_eq!(after.model.params(), before.model.params());
    assert_eq!(after.model.state_tensors(), before.model.state_tensors());
    assert_eq!((after.adam.t, after.adam.m.iter().all(|&x| x == 0.0)), (0, true), "a fresh Adam");
    let got = render_view(&*after.model, camera, [1.0; 3]);
    assert_eq!((got.rgb, got.depth, got.opacity), (want.rgb, want.depth, want.opacity));

    // Stripping again writes nothing; resuming is refused with a clear error.
    assert!(!persist::strip_training_state(&path).unwrap());
    assert_eq!(std::fs::metadata(&path).unwrap().len(), stripped_len);
    let e = persist::load_resumable(&path).err().expect("a render-only checkpoint must not resume").to_string();
    assert!(e.contains("m.ckpt") && e.contains("render-only"), "{e}");
    assert_eq!(dir.path().read_dir().unwrap().count(), 1, "no temporary file is left");
}
