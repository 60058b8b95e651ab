//! Tracking stage: dense correspondences between frames (flow) and the bundle adjustment that
//! turns them into keyframe poses, inverse depth maps and their uncertainty (paper §3.1).
//! Tracking never imports another stage; what it hands on (poses, keyframes with depth and
//! variance) are plain `core` types.

pub mod ba;
pub mod flow;
