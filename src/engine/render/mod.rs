//! Volume rendering, the parts every model renders and trains with:
//! `composite` (volume rendering of one ray, forward and backward), `loss`
//! (the photometric loss), `regularize` (losses on a ray's weights:
//! distortion and interlevel), `rounds` (the one render loop). Whole views
//! of a model are `view`'s.

pub mod composite;
pub mod loss;
pub mod regularize;
pub mod rounds;

/// Why a per-ray function of `composite` or `regularize` refused its
/// inputs: the slices of one ray must fit each other, and interval edges
/// must be sorted. Checked once per ray, so a caller's mistake is an error
/// that names the slice rather than an out-of-bounds panic.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum InputError {
    #[error("{what} has {got} values, expected {expected}")]
    Length { what: &'static str, expected: usize, got: usize },
    #[error("{what}: value {index} ({value}) is not finite or is below the one before it")]
    Unsorted { what: &'static str, index: usize, value: f32 },
}

impl InputError {
    /// `Ok` when slice `what` has `expected` values.
    pub fn check_len(what: &'static str, expected: usize, got: usize) -> Result<(), Self> {
        if expected == got { Ok(()) } else { Err(Self::Length { what, expected, got }) }
    }

    /// `Ok` when `v` is finite and non-decreasing.
    pub fn check_sorted(what: &'static str, v: &[f32]) -> Result<(), Self> {
        let mut prev = f32::NEG_INFINITY;
        for (index, &value) in v.iter().enumerate() {
            if !(value.is_finite() && value >= prev) {
                return Err(Self::Unsorted { what, index, value });
            }
            prev = value;
        }
        Ok(())
    }
}
