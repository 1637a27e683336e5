//! What the training and bake jobs share: a stored scene's dataset loaded,
//! and a model scored on its held-out views.

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};

use crate::engine::front::{
    Dataset, DatasetError, LoadOptions, MaskUse, Model, Split, held_out_options, psnr, render_heldout_view,
};
use crate::records::SceneInfo;

/// Loads a stored scene's dataset (all splits) from the scene's folder, its
/// masks read as `masks` asks.
pub fn load_dataset(scene_dir: &Path, scene: &SceneInfo, masks: MaskUse) -> Result<Dataset, DatasetError> {
    let root = scene_dir.join(&scene.root);
    Dataset::load(&root, &LoadOptions { masks, ..Default::default() })
}

/// Mean PSNR over up to `max_views` held-out views (test split, else val),
/// each rendered with the appearance `eval` scores it with by default
/// (`held_out_options`: the nearest training camera's), as the held-out
/// chart (`HeldOutPixels`) does.
pub(crate) fn evaluate(model: &dyn Model, ds: &Dataset, max_views: usize, cancel: &AtomicBool) -> Option<(f64, usize)> {
    let split = if ds.test.is_empty() { Split::Val } else { Split::Test };
    let mut sum = 0.0;
    let mut n = 0;
    for f in ds.split_frames(split).take(max_views) {
        if cancel.load(Ordering::Relaxed) {
            return None;
        }
        let v = render_heldout_view(model, &f.camera, ds.background, &held_out_options(model, &f.camera));
        let gt: Vec<f32> = (0..f.camera.height)
            .flat_map(|j| (0..f.camera.width).map(move |i| (i, j)))
            .flat_map(|(i, j)| f.image.rgb_on(i, j, ds.background))
            .collect();
        sum += psnr(&v.rgb, &gt);
        n += 1;
    }
    (n > 0).then(|| (sum / n as f64, n))
}
