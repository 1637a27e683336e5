//! Training is bit for bit what it was: 60 steps of each model kind on a
//! generated scene, on 2 threads with a fixed seed, hashed over the
//! parameters, Adam's moments and the trainer's state (the checkpoint's
//! identity bytes, `persist::identity_bytes`). The hashes were recorded by
//! this same test at commit 8b13e57, before the engine was reorganised into
//! one direction (models in folders, one compositor); a change that moves a
//! single bit of training fails here. A change meant to change training
//! records the new hashes, and says why in its commit.

mod common {
    //! The parts of `tests/common` this binary uses: the rest (its HTTP,
    //! browser and database clients) would be compiled here for nothing.
    #![allow(dead_code)]
    pub mod tiny;
}

use common::tiny::in_pool;
use radiance::engine::dataset::Dataset;
use radiance::engine::dataset::textured::TexturedScene;
use radiance::engine::models::config::ModelConfig;
use radiance::engine::train::persist;
use sha2::{Digest, Sha256};

/// A textured ball on a textured ground from a ring of 12 cameras at 24x18.
fn dataset() -> Dataset {
    TexturedScene { width: 24, height: 18, views: 12, fov: 0.9 }.dataset()
}

/// The sha256 of the identity bytes of preset `preset` after 60 steps.
fn trained_hash(ds: &Dataset, preset: &str) -> String {
    let config = ModelConfig::preset(preset).unwrap();
    in_pool(2, || {
        let mut t = common::tiny::trainer(&config, ds, 5, 60);
        for _ in 0..60 {
            t.step();
        }
        assert_eq!(t.state.step, 60, "{preset}: every step taken");
        let c = persist::to_checkpoint(t.model.as_ref(), &t.adam, &t.config, &t.state, t.transients.as_ref());
        let bytes = persist::identity_bytes(&c);
        Sha256::digest(&bytes).iter().map(|b| format!("{b:02x}")).collect()
    })
}

#[test]
fn sixty_steps_of_each_kind_train_as_before() {
    let ds = dataset();
    let expected = [
        ("instant-tiny", "22edd218fd746610564207a04cd7ae44a78a7ef8a9c16143081503698b06399b"),
        ("nerf-tiny", "36bcd364afbeab840dc487cb0cab15990f86b27e4ff5ff3b7805e203f200b8c2"),
        ("capture-tiny", "e6611a65c55eaa4b849175abbef85a0a275389cac184599f5491dbb19ebabee9"),
    ];
    let mut wrong = Vec::new();
    for (preset, want) in expected {
        let got = trained_hash(&ds, preset);
        println!("{preset}: {got}");
        if got != want {
            wrong.push(format!("{preset}: {got}, expected {want}"));
        }
    }
    assert!(wrong.is_empty(), "training changed:\n{}", wrong.join("\n"));
}
