//! The splats model's configuration and what it provides the registry
//! (`models::spec::ModelSpec`).

use super::gaussians::Layout;
use super::{KIND, SplatsModel};
use crate::engine::geometry::scene::Scene;
use crate::engine::models::spec::{Checks, Footprint, ModelSpec};
use crate::engine::models::{Model, ModelError};
use crate::engine::nn::adam::AdamConfig;

/// The splats model's configuration. The number of Gaussians is not a
/// setting: it is what baking made (the parameters' length says it).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SplatsConfig {
    /// Degree of the colours' spherical harmonics (0 to 3): 0 is one colour
    /// in every direction, 3 the 3DGS paper's 16 coefficients per channel.
    /// 1 by default: a minute's bake is a few hundred steps, in which the
    /// higher degrees fit each photo's noise (60 s bakes, `eval --fit-steps
    /// 0`, 2-core Xeon VM, degree 1 against 3: fox 28.71 against 26.87 dB,
    /// gold_cape 17.70 against 16.92, fern 20.08 against 19.85, lego 29.71
    /// against 30.02), and a `.splat` (one colour) then loses less. Degree
    /// 0 loses more (at `ca07950`, fox from a 120 s source, seeds 1-2:
    /// 28.40 and 28.33 dB against 29.40 and 29.29).
    pub sh_degree: u32,
    /// The most Gaussians baking may make (300k: a view of that many draws
    /// in real time on a phone, and a longer bake gains nothing past it:
    /// `docs/design/splats.md`).
    pub max_gaussians: usize,
}

impl Default for SplatsConfig {
    fn default() -> Self {
        Self { sh_degree: 1, max_gaussians: 300_000 }
    }
}

impl ModelSpec for SplatsConfig {
    fn kind(&self) -> &'static str {
        KIND
    }

    fn check(&self, c: &mut Checks) {
        c.int("sh_degree", self.sh_degree, 0..=3);
        c.int("max_gaussians", self.max_gaussians, 1..=4_000_000);
    }

    /// Splats are baked from a trained model (`radiance bake`), not trained
    /// from rays: there is no fresh model to build.
    fn build(&self, _scene: Scene, _seed: u64) -> Result<Box<dyn Model>, ModelError> {
        Err(ModelError::Config {
            kind: KIND,
            message: "splats are baked from a trained instant or capture model (`radiance bake`), not trained from \
                      scratch"
                .into(),
        })
    }

    fn rebuild(&self, scene: Scene, params: Vec<f32>) -> Result<Box<dyn Model>, ModelError> {
        Ok(Box::new(SplatsModel::from_parts(self.clone(), scene, params)?))
    }

    fn trains_on_rays(&self) -> bool {
        false
    }

    /// The base rate `bake` scales block by block (its `BASE_LR`).
    fn adam(&self) -> AdamConfig {
        AdamConfig { lr: 4e-3, lr_end: 4e-3, beta1: 0.9, beta2: 0.999, eps: 1e-15 }
    }

    fn random_background(&self) -> bool {
        false
    }

    fn footprint(&self, _threads: u64) -> Footprint {
        let per = Layout::stride(super::gaussians::sh_coeffs(self.sh_degree)) as u64;
        // A view's projections (about 24 values a Gaussian) and its tile
        // lists (about 8 entries a Gaussian, 10 values each in the backward).
        Footprint {
            params: per * self.max_gaussians as u64,
            occupancy_cells: 0,
            activations: 104 * self.max_gaussians as u64,
        }
    }
}

/// This kind's presets, the default first.
pub const PRESETS: &[&str] = &["splats", "splats-dc"];

/// A named configuration:
/// - `splats`: colours of SH degree 1 (the default), up to 500k Gaussians;
/// - `splats-dc`: one colour per Gaussian (a quarter of the file).
pub fn preset(name: &str) -> Option<SplatsConfig> {
    match name {
        "splats" => Some(SplatsConfig::default()),
        "splats-dc" => Some(SplatsConfig { sh_degree: 0, ..SplatsConfig::default() }),
        _ => None,
    }
}
