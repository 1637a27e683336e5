//! Loader (being written).
use std::path::Path;

use super::{Dataset, DatasetError, LoadOptions};

pub fn load(root: &Path, _opts: &LoadOptions) -> Result<Dataset, DatasetError> {
    Err(DatasetError::UnknownFormat(root.to_path_buf()))
}
