//! Judging what the mapper made: which model to keep, and whether it is good
//! enough to train on.
//!
//! COLMAP may leave photos out (too blurry, too little overlap) or split the
//! set into several unconnected models. The largest model is kept when it
//! holds at least [`FAIL_BELOW`] of the photos and, if there are others, at
//! least [`WARN_BELOW`] of them; under [`WARN_BELOW`] the result carries a
//! warning naming the photos left out.

use std::path::PathBuf;

use super::PoseError;

/// Fewer photos posed than this fraction is a failure.
pub const FAIL_BELOW: f64 = 0.5;

/// Fewer posed than this is a warning (and with several models, a failure:
/// the photos make separate scenes, and which one the user meant is theirs to
/// say).
pub const WARN_BELOW: f64 = 0.9;

/// How many names a message lists before "and N more".
const LIST: usize = 12;

/// One model the mapper wrote.
#[derive(Debug, Clone)]
pub struct Candidate {
    pub dir: PathBuf,
    /// The names of the photos it registered.
    pub images: Vec<String>,
    pub points: usize,
}

/// The model kept and what to tell the user about it.
#[derive(Debug)]
pub struct Verdict {
    pub chosen: usize,
    /// Photos not in the chosen model, sorted.
    pub unregistered: Vec<String>,
    pub warnings: Vec<String>,
}

/// Picks the model to keep among `models`, made from `photos`.
pub fn judge(photos: &[String], models: &[Candidate]) -> Result<Verdict, PoseError> {
    let total = photos.len();
    let Some((chosen, best)) = models.iter().enumerate().max_by_key(|(i, m)| (m.images.len(), std::cmp::Reverse(*i)))
    else {
        return Err(PoseError::Reconstruction(
            "COLMAP could not start a reconstruction: no two photos share enough matching features. The photos \
             must overlap (every part of the scene in three or more of them, neighbours sharing more than half \
             their view), be sharp, and show a textured, static scene"
                .into(),
        ));
    };
    let registered = best.images.len();
    let fraction = registered as f64 / total.max(1) as f64;
    let mut unregistered: Vec<String> = photos.iter().filter(|p| !best.images.contains(p)).cloned().collect();
    unregistered.sort();
    let percent = 100.0 * fraction;
    if models.len() > 1 && fraction < WARN_BELOW {
        let mut sizes: Vec<usize> = models.iter().map(|m| m.images.len()).collect();
        sizes.sort_unstable_by(|a, b| b.cmp(a));
        return Err(PoseError::Reconstruction(format!(
            "COLMAP split the photos into {} separate reconstructions (of {} photos); the largest holds {registered} \
             of {total} ({percent:.0}%): {}. Photos in between the groups are missing: take more overlapping photos, \
             or upload only one group",
            models.len(),
            sizes.iter().map(|s| s.to_string()).collect::<Vec<_>>().join(", "),
            list(&sorted(&best.images)),
        )));
    }
    if fraction < FAIL_BELOW {
        return Err(PoseError::Reconstruction(format!(
            "only {registered} of {total} photos ({percent:.0}%) could be posed, fewer than the {:.0}% needed; not \
             posed: {}. Photos need more overlap, more texture or less blur",
            100.0 * FAIL_BELOW,
            list(&unregistered),
        )));
    }
    let mut warnings = Vec::new();
    if fraction < WARN_BELOW {
        warnings.push(format!(
            "only {registered} of {total} photos ({percent:.0}%) were posed; the others are left out: {}",
            list(&unregistered)
        ));
    }
    if models.len() > 1 {
        let others: usize = models.iter().enumerate().filter(|(i, _)| *i != chosen).map(|(_, m)| m.images.len()).sum();
        warnings.push(format!(
            "COLMAP also made {} smaller reconstruction{} ({others} photos) not connected to the main one; only the \
             largest is kept",
            models.len() - 1,
            if models.len() == 2 { "" } else { "s" }
        ));
    }
    Ok(Verdict { chosen, unregistered, warnings })
}

fn sorted(v: &[String]) -> Vec<String> {
    let mut v = v.to_vec();
    v.sort();
    v
}

/// `a, b, c` or `a, b, ... and 7 more`.
pub fn list(names: &[String]) -> String {
    let shown = names.iter().take(LIST).cloned().collect::<Vec<_>>().join(", ");
    if names.len() > LIST { format!("{shown} and {} more", names.len() - LIST) } else { shown }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(r: std::ops::Range<usize>) -> Vec<String> {
        r.map(|i| format!("p{i:02}.jpg")).collect()
    }

    fn model(r: std::ops::Range<usize>) -> Candidate {
        Candidate { dir: PathBuf::new(), images: names(r), points: 100 }
    }

    #[test]
    fn all_posed_is_a_clean_result() {
        let v = judge(&names(0..20), &[model(0..20)]).unwrap();
        assert_eq!(v.chosen, 0);
        assert!(v.unregistered.is_empty() && v.warnings.is_empty());
    }

    #[test]
    fn thresholds_warn_and_fail() {
        let photos = names(0..20);
        // 18/20 = 90%: clean.
        assert!(judge(&photos, &[model(0..18)]).unwrap().warnings.is_empty());
        // 17/20 = 85%: a warning that names the three left out.
        let v = judge(&photos, &[model(0..17)]).unwrap();
        assert_eq!(v.unregistered, ["p17.jpg", "p18.jpg", "p19.jpg"]);
        assert!(v.warnings[0].contains("only 17 of 20 photos (85%)") && v.warnings[0].contains("p19.jpg"));
        // 10/20 = 50%: still kept; 9/20: refused.
        assert!(judge(&photos, &[model(0..10)]).is_ok());
        let e = judge(&photos, &[model(0..9)]).unwrap_err().to_string();
        assert!(e.contains("only 9 of 20 photos (45%)") && e.contains("p09.jpg, p10.jpg"), "{e}");
    }

    #[test]
    fn several_models_fail_unless_the_largest_holds_nearly_all() {
        let photos = names(0..20);
        let e = judge(&photos, &[model(0..8), model(8..20)]).unwrap_err().to_string();
        assert!(e.contains("2 separate reconstructions (of 12, 8 photos)"), "{e}");
        assert!(e.contains("the largest holds 12 of 20 (60%): p08.jpg, p09.jpg"), "{e}");
        let v = judge(&photos, &[model(0..2), model(2..20)]).unwrap();
        assert_eq!(v.chosen, 1);
        assert!(v.warnings.iter().any(|w| w.contains("1 smaller reconstruction (2 photos)")), "{:?}", v.warnings);
    }

    #[test]
    fn no_model_says_why() {
        let e = judge(&names(0..5), &[]).unwrap_err().to_string();
        assert!(e.contains("could not start a reconstruction") && e.contains("overlap"), "{e}");
    }

    #[test]
    fn long_lists_are_cut() {
        assert_eq!(list(&names(0..14)).matches(", ").count(), 11);
        assert!(list(&names(0..14)).ends_with("p11.jpg and 2 more"));
    }
}
