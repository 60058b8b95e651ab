//! Plain records of the log that both message formats carry: the tracking state's body and a
//! navigation sample built from its parts.

use duv_core::Timestamp;
use nalgebra::{Quaternion, UnitQuaternion};
use serde::{Deserialize, Serialize};

/// The JSON body of a `/slam/state` message.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StateMessage {
    pub seq: u64,
    pub t_ns: i64,
    pub state: String,
    pub tracked: bool,
    pub keyframe: Option<u64>,
    pub new_keyframe: Option<u64>,
    pub loop_closed: bool,
    /// The map segment the pose is in (logs written before segments read back as 0).
    #[serde(default)]
    pub segment: u32,
    /// Why the frame has no measured pose yet, with the value against its limit (logs
    /// written before these fields read back as `None`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub why: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub value: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub limit: Option<f64>,
}

/// A navigation sample from its parts (a quaternion as x, y, z, w; normalised).
pub(crate) fn nav_sample(t_ns: i64, depth_m: Option<f64>, altitude_m: Option<f64>, vel: Option<[f64; 3]>, q_xyzw: Option<[f64; 4]>) -> duv_core::nav::NavSample {
    duv_core::nav::NavSample {
        t_ns: Timestamp::from_ns(t_ns),
        depth_m,
        altitude_m,
        vel_cam_mps: vel.map(nalgebra::Vector3::from),
        world_from_cam_rot: q_xyzw.map(|[x, y, z, w]| UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z))),
    }
}
