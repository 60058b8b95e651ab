//! The keyframe the tracker hands to the mapper: the image, its pose, and the tracker's dense
//! inverse depth with its variance (paper §3.1-3.2). A plain type so that `track` and `map`
//! never import one another.

use super::{ImageRgb8, PinholeCamera, PlaneF32, Se3, Timestamp};

/// One keyframe. `inv_depth` and `inv_depth_variance` have the image's full resolution;
/// an inverse depth of 0 marks a pixel without a depth estimate (its variance is ignored).
#[derive(Clone, Debug, PartialEq)]
pub struct Keyframe {
    /// Keyframe number assigned by the tracker, increasing.
    pub index: u64,
    /// Capture time of the image.
    pub t_ns: Timestamp,
    /// The (undistorted) camera image.
    pub image: ImageRgb8,
    /// Camera-to-world pose: `p_in_world = world_from_cam * p_in_cam`.
    pub world_from_cam: Se3,
    /// Intrinsics of `image` (no distortion).
    pub camera: PinholeCamera,
    /// Inverse depth `1/z` along the optical axis, 1/m; 0 = unknown.
    pub inv_depth: PlaneF32,
    /// Variance of `inv_depth`, (1/m)^2.
    pub inv_depth_variance: PlaneF32,
}

impl Keyframe {
    /// True when the image, depth and variance planes all match the camera's size.
    pub fn is_consistent(&self) -> bool {
        let (w, h) = (self.camera.width, self.camera.height);
        self.image.width == w
            && self.image.height == h
            && self.image.data.len() == w * h * 3
            && self.inv_depth.width == w
            && self.inv_depth.height == h
            && self.inv_depth.data.len() == w * h
            && self.inv_depth_variance.width == w
            && self.inv_depth_variance.height == h
            && self.inv_depth_variance.data.len() == w * h
    }
}
