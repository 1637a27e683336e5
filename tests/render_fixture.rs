//! Checkpoints written by the engine as it was before its parts were made
//! composable (commit 136a768) must render to the same bytes ever after.
//!
//! `tests/fixtures/*.ckpt` are tiny models of the generated ball scene, trained
//! and saved once by `write_fixtures` (ignored; it was run by hand on that
//! commit). The expected hashes below were printed by the same run. A change
//! to the engine that moves a single bit of a rendered colour, depth or
//! opacity, or of the PNG the service would send, fails this test.

use std::path::{Path, PathBuf};

use radiance::engine::geometry::camera::{Camera, look_at};
use radiance::engine::geometry::math::Vec3;
use radiance::engine::train::persist;
use radiance::engine::view::{View, render_view};
use radiance::media::png;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures").join(name)
}

/// FNV-1a, 64 bits: stable across platforms and Rust versions.
fn fnv(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, &b| (h ^ b as u64).wrapping_mul(0x0100_0000_01b3))
}

fn f32_bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// The views each fixture is rendered from: two of the ball scene's cameras
/// (one above, one below the equator) at 32x24, and a close, tilted one that
/// cuts through the scene box.
fn cameras() -> Vec<Camera> {
    let up = Vec3::new(0.0, 0.0, 1.0);
    let poses = [
        look_at(Vec3::new(3.0, 0.4, 1.5), Vec3::splat(0.0), up),
        look_at(Vec3::new(-1.2, 2.6, -0.9), Vec3::splat(0.0), up),
        look_at(Vec3::new(0.9, -0.8, 0.5), Vec3::new(0.1, 0.2, -0.1), up),
    ];
    poses.into_iter().map(|p| Camera::from_fov(32, 24, 0.9, p.expect("a valid pose"))).collect()
}

/// Hashes of one view: colour, depth and opacity as f32 bytes, and the RGB
/// PNG the API would send.
fn hashes(view: &View) -> [u64; 4] {
    let rgb_png = png::encode_rgb(view.width, view.height, &png::quantise_rgb(&view.rgb)).expect("encode");
    [fnv(&f32_bytes(&view.rgb)), fnv(&f32_bytes(&view.depth)), fnv(&f32_bytes(&view.opacity)), fnv(&rgb_png)]
}

fn rendered(name: &str) -> Vec<[u64; 4]> {
    let restored = persist::load(&fixture(name)).unwrap_or_else(|e| panic!("{name}: {e}"));
    let mut out = Vec::new();
    for cam in cameras() {
        for bg in [[1.0, 1.0, 1.0], [0.0, 0.0, 0.0]] {
            out.push(hashes(&render_view(&*restored.model, &cam, bg)));
        }
    }
    out
}

/// Per fixture: (file, hashes of each camera on white then black).
const EXPECTED: &[(&str, [[u64; 4]; 6])] = &[
    (
        "instant-ball.ckpt",
        [
            [10704424757800253008, 5887234454913792395, 17617220445947902943, 703136566326307212],
            [15231256673390240472, 5887234454913792395, 17617220445947902943, 713341733404479375],
            [11946900814921909313, 15643767142614969836, 13633083504228338077, 5778855316662816578],
            [13811314864379648841, 15643767142614969836, 13633083504228338077, 7363259770255177896],
            [6623714795021530262, 14880027442210593763, 10259420593864254150, 8353567583502850216],
            [11262260676482790340, 14880027442210593763, 10259420593864254150, 6018132737014386330],
        ],
    ),
    (
        "nerf-ball.ckpt",
        [
            [18236670156268293341, 14007074845809944653, 3072780234921549358, 10149927806962480584],
            [7492838836204201505, 14007074845809944653, 3072780234921549358, 11886014957030640512],
            [17316344003222232901, 2479514909346476671, 16337369428735006442, 15499002583692074944],
            [17300710193585193109, 2479514909346476671, 16337369428735006442, 14710332508678609245],
            [3615917203464840761, 17342111821583174759, 11897973779140250836, 919577875529812928],
            [10273065095468501552, 17342111821583174759, 11897973779140250836, 7163906739505694269],
        ],
    ),
    (
        "nerf-dense-ball.ckpt",
        [
            [13509977447027620613, 3130197927889181727, 48483115131901863, 8923931856889937854],
            [7222115726320855940, 3130197927889181727, 48483115131901863, 3176136595180765756],
            [7367727635635721969, 16061376733426080804, 8838319087032327963, 12171872831061745388],
            [13472213227113999344, 16061376733426080804, 8838319087032327963, 9741514485365824179],
            [2125266361242454282, 13000954493653071487, 13463596831877785650, 9198026213351116685],
            [1825244001781817675, 13000954493653071487, 13463596831877785650, 17849433934256469439],
        ],
    ),
];

#[test]
fn checkpoints_from_before_the_refactor_render_to_the_same_bytes() {
    assert_eq!(EXPECTED.len(), 3, "one entry per fixture");
    for (name, want) in EXPECTED {
        let got = rendered(name);
        for (k, (g, w)) in got.iter().zip(want).enumerate() {
            assert_eq!(g, w, "{name}: view {k} (camera {}, {} background)", k / 2, ["white", "black"][k % 2]);
        }
    }
}

/// Trains the fixtures and prints their hashes. Run by hand only, on the
/// commit the module comment names:
/// `cargo test --test render_fixture -- --ignored --nocapture`.
#[test]
#[ignore = "writes tests/fixtures; run once by hand"]
fn write_fixtures() {
    // Kept as it ran, so the fixtures can be understood (and regenerated only
    // if the checkpoint format itself ever changes).
    use radiance::engine::dataset::synthetic::BallScene;

    use radiance::engine::models::Model;
    use radiance::engine::models::instant::{InstantConfig, InstantModel};
    use radiance::engine::models::nerf::{NerfConfig, NerfModel};
    use radiance::engine::models::training::{Budget, TrainConfig};
    use radiance::engine::nn::adam::{Adam, AdamConfig};
    use radiance::engine::nn::hashgrid::HashGridConfig;
    use radiance::engine::nn::nerf_net::NetConfig;
    use radiance::engine::sampling::occupancy::OccupancyConfig;
    use radiance::engine::train::trainer::{TrainState, Trainer};
    use std::sync::atomic::AtomicBool;

    let ds = BallScene { size: 24, views: 12, ..Default::default() }.dataset();
    let scene = ds.scene();
    let instant = InstantConfig {
        grid: HashGridConfig { levels: 6, log2_table: 11, base_resolution: 4, finest_resolution: 64 },
        hidden: 16,
        geo_features: 8,
        occupancy: OccupancyConfig {
            resolution: 16,
            update_every: 4,
            sweep: 4,
            warmup_steps: 8,
            full_updates_until: 32,
            ..InstantConfig::default().occupancy
        },
        samples_per_step: 1 << 12,
        ..Default::default()
    };
    let net = NetConfig { pos_freqs: 4, dir_freqs: 2, width: 16, depth: 3, skip: 1, dir_width: 8 };
    let grid = OccupancyConfig { resolution: 8, update_every: 4, sweep: 2, warmup_steps: 8, ..Default::default() };
    let nerf = |occupancy| NerfConfig {
        net: net.clone(),
        coarse_samples: 16,
        fine_samples: 16,
        occupancy,
        ..Default::default()
    };
    let models: Vec<(&str, Box<dyn Model>, u64)> = vec![
        ("instant-ball.ckpt", Box::new(InstantModel::new(instant, scene.clone(), 1)), 300),
        ("nerf-ball.ckpt", Box::new(NerfModel::new(nerf(Some(grid)), scene.clone(), 2)), 150),
        ("nerf-dense-ball.ckpt", Box::new(NerfModel::new(nerf(None), scene.clone(), 3)), 100),
    ];
    std::fs::create_dir_all(fixture("")).unwrap();
    for (name, model, steps) in models {
        let adam = Adam::new(AdamConfig { lr: 1e-2, lr_end: 1e-3, ..Default::default() }, model.params().len());
        let cfg = TrainConfig {
            seed: 7,
            batch_rays: 256,
            budget: Budget { steps: Some(steps), seconds: None },
            ..Default::default()
        };
        let mut t = Trainer::new(model, adam, cfg, TrainState::default(), &ds);
        t.run(&AtomicBool::new(false), |_, _| true);
        persist::save(&fixture(name), &*t.model, &t.adam, &t.config, &t.state, None).unwrap();
        println!("(\"{name}\", {:?}),", rendered(name));
    }
}
