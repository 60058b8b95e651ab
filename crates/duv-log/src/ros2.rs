//! The ROS 2 encoding of the log (`[log] format = "ros2"`): message definitions (`ros2msg`, as
//! rosbag2 stores them: the type's definition, then every dependency after a line of 80 `=`
//! and `MSG: pkg/Type`) and CDR bodies (little endian, the encapsulation header `00 01 00 00`,
//! each primitive aligned to its size counted from after that header).
//!
//! | topic | type |
//! |---|---|
//! | `/camera/image` | `sensor_msgs/msg/Image` (`rgb8`, `mono8`) or `sensor_msgs/msg/CompressedImage` (`jpeg`) |
//! | `/camera/camera_info` (the Foxglove format's `/camera/calibration`) | `sensor_msgs/msg/CameraInfo` |
//! | `/slam/pose`, `/keyframe/pose` | `geometry_msgs/msg/PoseStamped` |
//! | `/slam/odometry` | `nav_msgs/msg/Odometry` (the ROS 2 format only) |
//! | `/nav/sample` | `duv_msgs/msg/NavSample` |
//! | `/tf` | `tf2_msgs/msg/TFMessage` (`world` -> `camera`) |
//! | `/slam/state` | `duv_msgs/msg/TrackingState` |
//! | `/keyframe/image` | `sensor_msgs/msg/Image` (`rgb8`) |
//! | `/keyframe/inv_depth`, `/keyframe/variance` | `sensor_msgs/msg/Image` (`16FC1`: f16, [`PLANE_ENCODING`](super::schema::PLANE_ENCODING)) |
//! | `/map/gaussians` | `sensor_msgs/msg/PointCloud2` (x, y, z float32) |
//! | `/map/checkpoint` | `duv_msgs/msg/MapCheckpoint` |
//! | `/health` | `duv_msgs/msg/Health` |
//! | `/slam/window` | `duv_msgs/msg/TrackerWindow` |
//!
//! The CDR encoder is written here rather than taken from a crate: the serde-based ones (`cdr`,
//! `cdr-encoding`) serialise owned message structs, so every image would first be copied into
//! a `Vec<u8>` field (and `uint8[]` goes element by element), while the log writes borrowed
//! pixel planes straight into the one body buffer it reuses from message to message, which is
//! what keeps the writer allocation-free once warm. Readers ([`CdrReader`]) check every length
//! against the body before using it, so a damaged message is an error, never a panic or a large
//! allocation.

use super::jpeg::JpegEncoder;
use super::schema::{encode_jpeg_with, Encoded, FrameEncoding, LogItem, Pixels, Topic, TopicSchema, CAMERA_FRAME, PLANE_ENCODING, WORLD_FRAME};
use super::LogError;
pub use super::cdr::{
    decode_camera_info, decode_compressed_image, decode_health, decode_image, decode_nav_sample, decode_odometry, decode_pose_stamped, decode_tracking_state, decode_wrapped, is_cdr, CdrError, CdrReader, CdrWriter, RosImage, CDR_LE, MESSAGE_ENCODING, POINT_FIELD_FLOAT32, PROFILE, SCHEMA_ENCODING,
};
use duv_core::{FrameImage, Se3, Timestamp};
use std::fmt::Write as _;


/// Message definitions, without comments: `(type, definition)`, types as `pkg/Type`.
pub mod defs {
    pub const TIME: (&str, &str) = ("builtin_interfaces/Time", "int32 sec\nuint32 nanosec\n");
    pub const HEADER: (&str, &str) = ("std_msgs/Header", "builtin_interfaces/Time stamp\nstring frame_id\n");
    pub const IMAGE: (&str, &str) = ("sensor_msgs/Image", "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\nuint32 step\nuint8[] data\n");
    pub const COMPRESSED_IMAGE: (&str, &str) = ("sensor_msgs/CompressedImage", "std_msgs/Header header\nstring format\nuint8[] data\n");
    pub const ROI: (&str, &str) = ("sensor_msgs/RegionOfInterest", "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n");
    pub const CAMERA_INFO: (&str, &str) = (
        "sensor_msgs/CameraInfo",
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\nfloat64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\nuint32 binning_y\nsensor_msgs/RegionOfInterest roi\n",
    );
    pub const POINT: (&str, &str) = ("geometry_msgs/Point", "float64 x\nfloat64 y\nfloat64 z\n");
    pub const VECTOR3: (&str, &str) = ("geometry_msgs/Vector3", "float64 x\nfloat64 y\nfloat64 z\n");
    pub const QUATERNION: (&str, &str) = ("geometry_msgs/Quaternion", "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n");
    pub const POSE: (&str, &str) = ("geometry_msgs/Pose", "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation\n");
    pub const POSE_STAMPED: (&str, &str) = ("geometry_msgs/PoseStamped", "std_msgs/Header header\ngeometry_msgs/Pose pose\n");
    pub const TRANSFORM: (&str, &str) = ("geometry_msgs/Transform", "geometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation\n");
    pub const TRANSFORM_STAMPED: (&str, &str) = ("geometry_msgs/TransformStamped", "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/Transform transform\n");
    pub const TF_MESSAGE: (&str, &str) = ("tf2_msgs/TFMessage", "geometry_msgs/TransformStamped[] transforms\n");
    pub const POINT_FIELD: (&str, &str) = (
        "sensor_msgs/PointField",
        "uint8 INT8=1\nuint8 UINT8=2\nuint8 INT16=3\nuint8 UINT16=4\nuint8 INT32=5\nuint8 UINT32=6\nuint8 FLOAT32=7\nuint8 FLOAT64=8\nstring name\nuint32 offset\nuint8 datatype\nuint32 count\n",
    );
    pub const POINT_CLOUD2: (&str, &str) = (
        "sensor_msgs/PointCloud2",
        "std_msgs/Header header\nuint32 height\nuint32 width\nsensor_msgs/PointField[] fields\nbool is_bigendian\nuint32 point_step\nuint32 row_step\nuint8[] data\nbool is_dense\n",
    );
    pub const TRACKING_STATE: (&str, &str) = (
        "duv_msgs/TrackingState",
        "# The tracker's state for one frame (/slam/state).\n\
         std_msgs/Header header\n\
         uint64 seq\n\
         int64 t_ns\n\
         # tracking, lost (black frame), initialising, ...\n\
         string state\n\
         # Whether the pose was measured (tracking or relocalised).\n\
         bool tracked\n\
         # The keyframe the pose was measured against (when has_keyframe).\n\
         bool has_keyframe\n\
         uint64 keyframe\n\
         # The keyframe this frame became (when has_new_keyframe).\n\
         bool has_new_keyframe\n\
         uint64 new_keyframe\n\
         bool loop_closed\n\
         # The map segment of the pose (a new one after a loss; 0 is the dive's first).\n\
         uint32 segment\n\
         # Why the frame has no measured pose yet ('' when it has), with the measured value\n\
         # and its limit (NaN when not given).\n\
         string why\n\
         float64 value\n\
         float64 limit\n",
    );
    pub const HEALTH: (&str, &str) = ("duv_msgs/Health", "# Once a second: queue depths and drops, per-stage latency, budget headroom, host memory.\nstd_msgs/Header header\n# The record as JSON.\nstring json\n");
    pub const POSE_WITH_COVARIANCE: (&str, &str) = ("geometry_msgs/PoseWithCovariance", "geometry_msgs/Pose pose\nfloat64[36] covariance\n");
    pub const TWIST: (&str, &str) = ("geometry_msgs/Twist", "geometry_msgs/Vector3 linear\ngeometry_msgs/Vector3 angular\n");
    pub const TWIST_WITH_COVARIANCE: (&str, &str) = ("geometry_msgs/TwistWithCovariance", "geometry_msgs/Twist twist\nfloat64[36] covariance\n");
    pub const ODOMETRY: (&str, &str) = (
        "nav_msgs/Odometry",
        "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/PoseWithCovariance pose\ngeometry_msgs/TwistWithCovariance twist\n",
    );
    pub const NAV_SAMPLE: (&str, &str) = (
        "duv_msgs/NavSample",
        "# One navigation sample on the frames' clock (/nav/sample); NaN: the sensor has no sample here.\n\
         std_msgs/Header header\n\
         # Pressure depth below the surface, metres, positive down.\n\
         float64 depth_m\n\
         # Range to the seabed along gravity (altimeter, DVL bottom lock), metres.\n\
         float64 altitude_m\n\
         # Velocity over ground in the camera frame (x right, y down, z forward), m/s.\n\
         geometry_msgs/Vector3 vel_cam_mps\n\
         # The AHRS camera-to-world rotation, world z up (the heading may drift).\n\
         geometry_msgs/Quaternion world_from_cam\n",
    );
    pub const TRACKER_WINDOW: (&str, &str) = (
        "duv_msgs/TrackerWindow",
        "# The tracker's newest keyframes, what a resume seeds a tracker with (/slam/window).\nstd_msgs/Header header\n# The window in the duv.tracker_window layout (little endian; see duv-log window.rs).\nuint8[] data\n",
    );
    pub const MAP_CHECKPOINT: (&str, &str) = (
        "duv_msgs/MapCheckpoint",
        "# A map checkpoint (/map/checkpoint): the mapper's checksummed bytes, keyframes referring\n# to their /keyframe/* messages.\nstd_msgs/Header header\nuint8[] data\n",
    );
}

/// The ROS 2 message types of the log, as [`Ros2Type::name`] gives them (`pkg/msg/Type`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Ros2Type {
    Image,
    CompressedImage,
    CameraInfo,
    PoseStamped,
    TfMessage,
    PointCloud2,
    TrackingState,
    Health,
    TrackerWindow,
    MapCheckpoint,
    NavSample,
    Odometry,
}

impl Ros2Type {
    fn def(self) -> (&'static str, &'static str) {
        use defs::*;
        match self {
            Ros2Type::Image => IMAGE,
            Ros2Type::CompressedImage => COMPRESSED_IMAGE,
            Ros2Type::CameraInfo => CAMERA_INFO,
            Ros2Type::PoseStamped => POSE_STAMPED,
            Ros2Type::TfMessage => TF_MESSAGE,
            Ros2Type::PointCloud2 => POINT_CLOUD2,
            Ros2Type::TrackingState => TRACKING_STATE,
            Ros2Type::Health => HEALTH,
            Ros2Type::TrackerWindow => TRACKER_WINDOW,
            Ros2Type::MapCheckpoint => MAP_CHECKPOINT,
            Ros2Type::NavSample => NAV_SAMPLE,
            Ros2Type::Odometry => ODOMETRY,
        }
    }

    /// Dependencies in the order rosbag2 lists them (depth first, each once).
    fn deps(self) -> &'static [(&'static str, &'static str)] {
        use defs::*;
        match self {
            Ros2Type::Image | Ros2Type::CompressedImage | Ros2Type::Health | Ros2Type::TrackerWindow | Ros2Type::MapCheckpoint | Ros2Type::TrackingState => &[HEADER, TIME],
            Ros2Type::CameraInfo => &[HEADER, TIME, ROI],
            Ros2Type::PoseStamped => &[HEADER, TIME, POSE, POINT, QUATERNION],
            Ros2Type::TfMessage => &[TRANSFORM_STAMPED, HEADER, TIME, TRANSFORM, VECTOR3, QUATERNION],
            Ros2Type::PointCloud2 => &[HEADER, TIME, POINT_FIELD],
            Ros2Type::NavSample => &[HEADER, TIME, VECTOR3, QUATERNION],
            Ros2Type::Odometry => &[HEADER, TIME, POSE_WITH_COVARIANCE, POSE, POINT, QUATERNION, TWIST_WITH_COVARIANCE, TWIST, VECTOR3],
        }
    }

    /// The type name as rosbag2 writes it: `sensor_msgs/msg/Image`.
    pub fn name(self) -> String {
        let (t, _) = self.def();
        let (pkg, ty) = t.split_once('/').expect("pkg/Type");
        format!("{pkg}/msg/{ty}")
    }

    /// The `ros2msg` schema text: the definition, then each dependency after a separator line.
    pub fn schema_text(self) -> String {
        let mut s = String::from(self.def().1);
        for (name, def) in self.deps() {
            let _ = write!(s, "{}\nMSG: {name}\n{def}", "=".repeat(80));
        }
        s
    }
}

/// The ROS 2 type of a topic as a writer with `frames` writes it.
pub fn topic_type(topic: Topic, frames: FrameEncoding) -> Ros2Type {
    match topic {
        Topic::CameraImage => match frames {
            FrameEncoding::Raw => Ros2Type::Image,
            FrameEncoding::Jpeg { .. } => Ros2Type::CompressedImage,
        },
        Topic::KeyframeImage | Topic::KeyframeInvDepth | Topic::KeyframeVariance => Ros2Type::Image,
        Topic::CameraCalibration => Ros2Type::CameraInfo,
        Topic::Pose | Topic::KeyframePose => Ros2Type::PoseStamped,
        Topic::Transform => Ros2Type::TfMessage,
        Topic::MapGaussians => Ros2Type::PointCloud2,
        Topic::State => Ros2Type::TrackingState,
        Topic::Health => Ros2Type::Health,
        Topic::TrackerWindow => Ros2Type::TrackerWindow,
        Topic::MapCheckpoint => Ros2Type::MapCheckpoint,
        Topic::Nav => Ros2Type::NavSample,
        Topic::Odometry => Ros2Type::Odometry,
    }
}


/// The schema of `topic` in the ROS 2 format.
pub fn topic_schema(topic: Topic, frames: FrameEncoding) -> TopicSchema {
    let t = topic_type(topic, frames);
    TopicSchema { name: t.name(), encoding: SCHEMA_ENCODING.into(), data: t.schema_text().into_bytes(), message_encoding: MESSAGE_ENCODING.into() }
}

fn xyz_xyzw(p: &Se3) -> ([f64; 3], [f64; 4]) {
    let t = p.translation.vector;
    let q = p.rotation.quaternion();
    ([t.x, t.y, t.z], [q.i, q.j, q.k, q.w])
}

/// `sensor_msgs/Image` of `pixels`.
#[allow(clippy::too_many_arguments)]
fn image(out: &mut Vec<u8>, t_ns: Timestamp, width: usize, height: usize, encoding: &str, step: usize, pixels: Pixels<'_>) {
    let mut w = CdrWriter::new(out);
    w.header(t_ns.t_ns(), CAMERA_FRAME);
    w.u32(height as u32);
    w.u32(width as u32);
    w.string(encoding);
    w.u8(0);
    w.u32(step as u32);
    match pixels {
        Pixels::Bytes(b) => w.bytes(b),
        Pixels::F32(v) => w.f32_bytes(v),
        Pixels::F16(v) => w.f16_bytes(v),
    }
}

fn pose_stamped(out: &mut Vec<u8>, t_ns: Timestamp, p: &Se3) {
    let mut w = CdrWriter::new(out);
    w.header(t_ns.t_ns(), WORLD_FRAME);
    let (t, q) = xyz_xyzw(p);
    w.pose(t, q);
}

/// A `duv_msgs` record of a header and a `uint8[]`.
fn wrapped(out: &mut Vec<u8>, t_ns: Timestamp, bytes: &[u8]) {
    let mut w = CdrWriter::new(out);
    w.header(t_ns.t_ns(), "");
    w.bytes(bytes);
}

/// Encodes `item` as CDR messages (the ROS 2 format); the buffers are the [`ItemEncoder`]'s.
/// [`ItemEncoder`]: super::encoder::ItemEncoder
pub(crate) fn encode_item(item: &LogItem, frames: FrameEncoding, scratch: &mut Vec<u8>, jpeg: &mut Vec<u8>, jpeg_encoder: &mut Option<JpegEncoder>, odometry_prev: &mut Option<(Timestamp, Se3)>, mut emit: impl FnMut(Encoded, &[u8]) -> Result<(), LogError>) -> Result<(), LogError> {
    let log_time_ns = item.t_ns().t_ns().max(0) as u64;
    match item {
        LogItem::Frame(f) => {
            match frames {
                FrameEncoding::Raw => match &f.image {
                    FrameImage::Rgb8(i) => image(scratch, f.t_ns, i.width, i.height, "rgb8", i.width * 3, Pixels::Bytes(&i.data)),
                    FrameImage::Gray8(i) => image(scratch, f.t_ns, i.width, i.height, "mono8", i.width, Pixels::Bytes(&i.data)),
                },
                FrameEncoding::Jpeg { quality } => {
                    if jpeg_encoder.as_ref().is_none_or(|e| e.quality() != quality) {
                        let e = JpegEncoder::new(quality).map_err(|e| LogError::Encode { what: "frame (jpeg)", problem: e.to_string() })?;
                        *jpeg_encoder = Some(e);
                    }
                    encode_jpeg_with(jpeg_encoder.as_ref().expect("set above"), &f.image, jpeg)?;
                    let mut w = CdrWriter::new(scratch);
                    w.header(f.t_ns.t_ns(), CAMERA_FRAME);
                    w.string("jpeg");
                    w.bytes(jpeg);
                }
            }
            emit(Encoded { topic: Topic::CameraImage, sequence: f.seq as u32, log_time_ns }, scratch)
        }
        LogItem::Calibration { t_ns, camera } => {
            let (fx, fy, cx, cy) = (camera.fx, camera.fy, camera.cx, camera.cy);
            let mut w = CdrWriter::new(scratch);
            w.header(t_ns.t_ns(), CAMERA_FRAME);
            w.u32(camera.height as u32);
            w.u32(camera.width as u32);
            match &camera.distortion {
                Some(rt) => {
                    w.string("plumb_bob");
                    w.f64_seq(&[rt.k1, rt.k2, rt.p1, rt.p2, rt.k3]);
                }
                None => {
                    w.string("");
                    w.f64_seq(&[]);
                }
            }
            w.f64_array(&[fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0]);
            w.f64_array(&[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]);
            w.f64_array(&[fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0]);
            w.u32(0);
            w.u32(0);
            for _ in 0..4 {
                w.u32(0);
            }
            w.bool(false);
            emit(Encoded { topic: Topic::CameraCalibration, sequence: 0, log_time_ns }, scratch)
        }
        LogItem::Pose(p) => {
            let sequence = p.seq as u32;
            pose_stamped(scratch, p.t_ns, &p.world_from_cam);
            emit(Encoded { topic: Topic::Pose, sequence, log_time_ns }, scratch)?;
            let mut w = CdrWriter::new(scratch);
            w.u32(1);
            w.header(p.t_ns.t_ns(), WORLD_FRAME);
            w.string(CAMERA_FRAME);
            let (t, q) = xyz_xyzw(&p.world_from_cam);
            w.pose(t, q);
            emit(Encoded { topic: Topic::Transform, sequence, log_time_ns }, scratch)?;
            // nav_msgs/Odometry: the pose, and the velocity since the previous pose in the
            // camera frame; covariances all zero (ROS: unknown).
            let (linear, angular) = match odometry_prev.replace((p.t_ns, p.world_from_cam)) {
                Some((t0, prev)) if p.t_ns > t0 => {
                    let dt = (p.t_ns.t_ns() - t0.t_ns()) as f64 * 1e-9;
                    let v = p.world_from_cam.rotation.inverse() * (p.world_from_cam.translation.vector - prev.translation.vector) / dt;
                    let w = (prev.rotation.inverse() * p.world_from_cam.rotation).scaled_axis() / dt;
                    ([v.x, v.y, v.z], [w.x, w.y, w.z])
                }
                _ => ([0.0; 3], [0.0; 3]),
            };
            let mut w = CdrWriter::new(scratch);
            w.header(p.t_ns.t_ns(), WORLD_FRAME);
            w.string(CAMERA_FRAME);
            let (t, q) = xyz_xyzw(&p.world_from_cam);
            w.pose(t, q);
            w.f64_array(&[0.0; 36]);
            w.f64_array(&linear);
            w.f64_array(&angular);
            w.f64_array(&[0.0; 36]);
            emit(Encoded { topic: Topic::Odometry, sequence, log_time_ns }, scratch)?;
            let mut w = CdrWriter::new(scratch);
            w.header(p.t_ns.t_ns(), CAMERA_FRAME);
            w.u64(p.seq);
            w.i64(p.t_ns.t_ns());
            w.string(p.state);
            w.bool(p.tracked);
            w.bool(p.keyframe.is_some());
            w.u64(p.keyframe.unwrap_or(0));
            w.bool(p.new_keyframe.is_some());
            w.u64(p.new_keyframe.unwrap_or(0));
            w.bool(p.loop_closed);
            w.u32(p.segment);
            w.string(p.why.unwrap_or(""));
            w.f64(p.value.unwrap_or(f64::NAN));
            w.f64(p.limit.unwrap_or(f64::NAN));
            emit(Encoded { topic: Topic::State, sequence, log_time_ns }, scratch)
        }
        LogItem::Keyframe(k) => {
            let sequence = k.index as u32;
            let (w, h) = (k.image.width, k.image.height);
            image(scratch, k.t_ns, w, h, "rgb8", w * 3, Pixels::Bytes(&k.image.data));
            emit(Encoded { topic: Topic::KeyframeImage, sequence, log_time_ns }, scratch)?;
            let (dw, dh) = (k.inv_depth.width, k.inv_depth.height);
            image(scratch, k.t_ns, dw, dh, PLANE_ENCODING, dw * 2, Pixels::F16(&k.inv_depth.data));
            emit(Encoded { topic: Topic::KeyframeInvDepth, sequence, log_time_ns }, scratch)?;
            let (vw, vh) = (k.inv_depth_variance.width, k.inv_depth_variance.height);
            image(scratch, k.t_ns, vw, vh, PLANE_ENCODING, vw * 2, Pixels::F16(&k.inv_depth_variance.data));
            emit(Encoded { topic: Topic::KeyframeVariance, sequence, log_time_ns }, scratch)?;
            pose_stamped(scratch, k.t_ns, &k.world_from_cam);
            emit(Encoded { topic: Topic::KeyframePose, sequence, log_time_ns }, scratch)
        }
        LogItem::Map { t_ns, centres_in_world, checkpoint, .. } => {
            let mut w = CdrWriter::new(scratch);
            w.header(t_ns.t_ns(), WORLD_FRAME);
            w.u32(1);
            w.u32(centres_in_world.len() as u32);
            w.u32(3);
            for (i, name) in ["x", "y", "z"].into_iter().enumerate() {
                w.string(name);
                w.u32(4 * i as u32);
                w.u8(POINT_FIELD_FLOAT32);
                w.u32(1);
            }
            w.bool(false);
            w.u32(12);
            w.u32(12 * centres_in_world.len() as u32);
            w.u32(12 * centres_in_world.len() as u32);
            for c in centres_in_world {
                for v in c {
                    w.out.extend_from_slice(&v.to_le_bytes());
                }
            }
            w.bool(true);
            emit(Encoded { topic: Topic::MapGaussians, sequence: 0, log_time_ns }, scratch)?;
            wrapped(scratch, *t_ns, checkpoint);
            emit(Encoded { topic: Topic::MapCheckpoint, sequence: 0, log_time_ns }, scratch)
        }
        LogItem::Health { t_ns, json } => {
            let mut w = CdrWriter::new(scratch);
            w.header(t_ns.t_ns(), "");
            w.string(json);
            emit(Encoded { topic: Topic::Health, sequence: 0, log_time_ns }, scratch)
        }
        LogItem::Window(win) => {
            win.encode(jpeg)?;
            wrapped(scratch, win.t_ns, jpeg);
            emit(Encoded { topic: Topic::TrackerWindow, sequence: win.seq as u32, log_time_ns }, scratch)
        }
        LogItem::Nav(n) => {
            let mut w = CdrWriter::new(scratch);
            w.header(n.t_ns.t_ns(), CAMERA_FRAME);
            w.f64(n.depth_m.unwrap_or(f64::NAN));
            w.f64(n.altitude_m.unwrap_or(f64::NAN));
            let v = n.vel_cam_mps.map_or([f64::NAN; 3], |v| [v.x, v.y, v.z]);
            v.into_iter().for_each(|x| w.f64(x));
            let q = n.world_from_cam_rot.map_or([f64::NAN; 4], |q| [q.i, q.j, q.k, q.w]);
            q.into_iter().for_each(|x| w.f64(x));
            emit(Encoded { topic: Topic::Nav, sequence: 0, log_time_ns }, scratch)
        }
    }
}


#[cfg(test)]
mod tests {
    use super::*;


    #[test]
    fn cdr_aligns_from_after_the_header_and_round_trips() {
        let mut buf = Vec::new();
        let mut w = CdrWriter::new(&mut buf);
        w.u8(7);
        w.u64(0x0102_0304_0506_0708);
        w.string("rgb8");
        w.bool(true);
        w.f64(-1.5);
        w.bytes(&[1, 2, 3]);
        w.f64_seq(&[0.25, 4.0]);
        // u8 at 4, u64 aligned to 8 after the header (byte 12), string at 20.
        assert_eq!(&buf[..5], &[0, 1, 0, 0, 7]);
        assert_eq!(&buf[12..20], &0x0102_0304_0506_0708u64.to_le_bytes());
        assert_eq!(&buf[20..29], b"\x05\0\0\0rgb8\0");
        let mut r = CdrReader::new(&buf).unwrap();
        assert_eq!(r.u8().unwrap(), 7);
        assert_eq!(r.u64().unwrap(), 0x0102_0304_0506_0708);
        assert_eq!(r.string().unwrap(), "rgb8");
        assert!(r.bool().unwrap());
        assert_eq!(r.f64().unwrap(), -1.5);
        assert_eq!(r.bytes().unwrap(), &[1, 2, 3]);
        assert_eq!(r.f64_seq().unwrap(), vec![0.25, 4.0]);
        r.finish().unwrap();
    }

    #[test]
    fn damaged_cdr_is_an_error() {
        assert!(matches!(CdrReader::new(&[0x0a, 1, 2]), Err(CdrError::Header { .. })));
        let mut buf = Vec::new();
        CdrWriter::new(&mut buf).bytes(&[9; 100]);
        let cut = &buf[..50];
        let mut r = CdrReader::new(cut).unwrap();
        assert!(matches!(r.bytes(), Err(CdrError::Truncated { .. })));
        // A float64[] claiming more elements than the body holds allocates nothing.
        let mut buf = Vec::new();
        CdrWriter::new(&mut buf).u32(u32::MAX);
        assert!(matches!(CdrReader::new(&buf).unwrap().f64_seq(), Err(CdrError::Truncated { .. })));
        let mut buf = Vec::new();
        let mut w = CdrWriter::new(&mut buf);
        w.u32(3);
        buf.extend_from_slice(b"ab");
        buf.push(b'c');
        assert!(matches!(CdrReader::new(&buf).unwrap().string(), Err(CdrError::BadString { .. })));
    }

    #[test]
    fn schema_text_lists_dependencies_after_separators() {
        let s = Ros2Type::PoseStamped.schema_text();
        assert!(s.starts_with("std_msgs/Header header\ngeometry_msgs/Pose pose\n"), "{s}");
        let sep = format!("{}\nMSG: geometry_msgs/Pose\n", "=".repeat(80));
        assert!(s.contains(&sep), "{s}");
        assert_eq!(s.matches("\nMSG: ").count(), 5);
        assert_eq!(Ros2Type::TfMessage.name(), "tf2_msgs/msg/TFMessage");
        assert_eq!(Ros2Type::TrackingState.name(), "duv_msgs/msg/TrackingState");
    }
}
