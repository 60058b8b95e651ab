//! Plain types every stage shares: time, frames, the camera model, poses, ground-truth
//! records. Nothing here depends on any stage.

pub mod align;
pub mod alloc;
pub mod camera;
pub mod frame;
pub mod jpeg;
pub mod keyframe;
pub mod nav;
pub mod pose;
pub mod rng;
pub mod source;
pub mod time;

pub mod config;
pub mod io;

pub use camera::{CameraModelError, PinholeCamera, RadTan};
pub use keyframe::Keyframe;
pub use frame::{Frame, FrameImage, Image, ImageGray16, ImageGray8, ImageRgb8, ImageRgbF32, PlaneF32};
pub use pose::{PoseRecord, Se3, Sim3};
pub use time::Timestamp;

/// A time-stamped pose, `world_from_cam` (camera-to-world), as in a TUM trajectory file.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StampedPose {
    pub t_ns: Timestamp,
    pub world_from_cam: Se3,
}

/// Per-channel underwater medium parameters of the image formation model
/// `I = J exp(-beta_D r) + B_inf (1 - exp(-beta_B r))`, channels R, G, B, coefficients in 1/m.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MediumParams {
    /// Attenuation of the direct signal per metre of range.
    #[serde(rename = "beta_D")]
    pub beta_d: [f64; 3],
    /// Attenuation governing backscatter build-up per metre of range.
    #[serde(rename = "beta_B")]
    pub beta_b: [f64; 3],
    /// Veiling light (backscatter at infinite range), in [0, 1].
    #[serde(rename = "B_inf")]
    pub b_inf: [f64; 3],
}

impl MediumParams {
    /// `|self - truth| / truth` per coefficient: rows `beta_D`, `beta_B`, `B_inf`; columns R G B.
    pub fn rel_error(&self, truth: &MediumParams) -> [[f64; 3]; 3] {
        let e = |r: [f64; 3], t: [f64; 3]| [0, 1, 2].map(|c| (r[c] - t[c]).abs() / t[c].abs().max(1e-9));
        [e(self.beta_d, truth.beta_d), e(self.beta_b, truth.beta_b), e(self.b_inf, truth.b_inf)]
    }
    /// The largest of [`Self::rel_error`].
    pub fn worst_rel_error(&self, truth: &MediumParams) -> f64 {
        self.rel_error(truth).iter().flatten().fold(0.0, |m, &v| m.max(v))
    }
}
