//! What robust training dropped, as the training report and `bench` tell it.

/// A photo mostly masked: at least this share of its pixels dropped (the
/// training report names it).
pub const MOSTLY_MASKED: f64 = 0.5;

/// What robust training dropped ([`TransientMaps::report`]).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TransientReport {
    /// Share of all the training pixels dropped.
    pub dropped: f64,
    /// Each training photo's share of pixels dropped, in training order.
    pub photos: Vec<PhotoShare>,
}

/// One training photo's share of pixels dropped.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PhotoShare {
    pub name: String,
    pub share: f64,
}

impl TransientReport {
    /// The photos mostly masked ([`MOSTLY_MASKED`]), most masked first.
    pub fn mostly_masked(&self) -> Vec<&PhotoShare> {
        let mut v: Vec<&PhotoShare> = self.photos.iter().filter(|p| p.share >= MOSTLY_MASKED).collect();
        v.sort_by(|a, b| b.share.total_cmp(&a.share));
        v
    }

    /// One line: the share dropped, the most masked photos.
    pub fn summary(&self) -> String {
        let mut by_share: Vec<&PhotoShare> = self.photos.iter().filter(|p| p.share > 0.0).collect();
        by_share.sort_by(|a, b| b.share.total_cmp(&a.share));
        let mut s = format!(
            "{:.2}% of the training pixels dropped, in {} of {} photos",
            100.0 * self.dropped,
            by_share.len(),
            self.photos.len()
        );
        if !by_share.is_empty() {
            let most: Vec<String> =
                by_share.iter().take(3).map(|p| format!("{} {:.0}%", p.name, 100.0 * p.share)).collect();
            s += &format!(" (most: {})", most.join(", "));
        }
        let mostly = self.mostly_masked();
        if !mostly.is_empty() {
            let names: Vec<&str> = mostly.iter().map(|p| p.name.as_str()).collect();
            s += &format!("; mostly masked, consider retaking: {}", names.join(", "));
        }
        s
    }
}

/// Transient masks found, against known occluders ([`TransientMaps::score`]).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FoundMasks {
    /// Share of the occluders' pixels found transient.
    pub recall: f64,
    /// Share of the other pixels (the static scene) found transient.
    pub static_share: f64,
}
