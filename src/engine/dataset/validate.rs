//! Pose and image validation (being written).
