//! What the capture model offers besides rendering and training: its
//! per-photo appearance embeddings, the held-out pose its refinement's
//! common drift gives, and its main grid's gradient recorded for later.

use super::CaptureModel;
use crate::engine::batch::{BatchStats, StepCtx, TrainRay};
use crate::engine::geometry::so3;
use crate::engine::models::{Appearance, DeferredGrid, PoseRefinement, RayMeasure, RenderOptions};
use crate::engine::nn::hashgrid::{GridRecord, HashGrid};
use crate::engine::nn::pose_report::PoseReport;

impl Appearance for CaptureModel {
    fn images(&self) -> Vec<u32> {
        self.seen_images()
    }

    fn row(&self, image: u32) -> Option<std::ops::Range<usize>> {
        let a = self.field.appearance();
        let start = a.embedding(&self.params, image).map(|_| a.table.start + image as usize * a.dim)?;
        Some(start..start + a.dim)
    }

    /// An image's embedding (none beyond the table: a zero bias), or the
    /// mean of the images trained on.
    fn embedding(&self, options: &RenderOptions) -> Option<Vec<f32>> {
        match options.image {
            Some(i) => self.field.appearance().embedding(&self.params, i).map(<[f32]>::to_vec),
            None => Some(self.mean_embedding()),
        }
    }
}

impl PoseRefinement for CaptureModel {
    /// The camera moved by the training cameras' common drift (design 2.7):
    /// its centre `c` (model space) by `ω_g × c + t_g`, its axes turned by
    /// `exp(ω_g)`. The pose itself without pose refinement.
    fn heldout_pose(&self, c2w: [[f32; 4]; 3]) -> [[f32; 4]; 3] {
        let Some(_) = &self.pose else { return c2w };
        let g = self.pose_gauge();
        let scale = f64::from(self.scene.scale);
        let centre: [f64; 3] =
            std::array::from_fn(|a| (f64::from(c2w[a][3]) - f64::from(self.scene.centre[a])) * scale);
        let shift = g.translation_at(centre);
        let turn = so3::exp(g.omega);
        let axes: so3::Mat3 = std::array::from_fn(|i| std::array::from_fn(|j| f64::from(c2w[i][j])));
        let turned = so3::mul(&turn, &axes);
        std::array::from_fn(|i| {
            let moved = f64::from(c2w[i][3]) + shift[i] / scale;
            [turned[i][0] as f32, turned[i][1] as f32, turned[i][2] as f32, moved as f32]
        })
    }

    fn report(&self) -> Option<PoseReport> {
        self.pose_report()
    }
}

impl DeferredGrid for CaptureModel {
    fn grid(&self) -> HashGrid {
        self.field.grid().clone()
    }

    fn train_rays_deferred_measured(
        &self,
        rays: &[TrainRay],
        ctx: &StepCtx,
        grads: &mut [f32],
        record: &mut GridRecord,
        errors: &mut [RayMeasure],
    ) -> BatchStats {
        record.clear();
        // A posed model records nothing (its passes need the grid's input
        // gradient at once): it is not offered as deferring, but stays
        // right when called all the same.
        let record = self.defers_grid().then_some(record);
        self.train(rays, ctx, grads, record, Some(errors))
    }
}
