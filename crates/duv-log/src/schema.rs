//! Topics, their schemas, and the encoding of [`LogItem`]s into MCAP messages.
//!
//! Images, calibration, poses, transforms and point clouds use the Foxglove protobuf schemas
//! from the `foxglove` crate, so a log opens in Foxglove with the camera, the trajectory and the
//! Gaussian centres visible. Our own records (tracking state, health) are JSON with a JSON
//! schema; map checkpoints are the mapper's checksummed bytes on a schemaless channel.
//! In the ROS 2 format ([`LogFormat::Ros2`]) every topic has a ROS 2 type and CDR bodies
//! ([`super::ros2`]); the decoders here read both, telling them apart by the body's first
//! bytes (a CDR body starts `00 01 00 00`, which no protobuf, JSON or duv record does).

use super::window::TrackerWindow;
use super::jpeg::{JpegEncoder, JpegError};
use super::LogError;
use duv_core::{CameraModelError, Frame, FrameImage, Keyframe, PinholeCamera, PlaneF32, Se3, Timestamp};
use foxglove::messages as fg;
use foxglove::Encode;
use nalgebra::{Quaternion, Translation3, UnitQuaternion};
use serde::{Deserialize, Serialize};

/// What a protobuf message body that does not parse gives (`prost`'s error, through
/// `foxglove`).
pub type ProtobufError = <fg::RawImage as foxglove::Decode>::Error;

/// Errors of the `schema` module: a logged message that does not decode into what its topic
/// holds. (Encoding errors are the crate's [`LogError::Encode`].)
#[derive(Debug, thiserror::Error)]
pub enum DecodeError {
    /// The body is not the protobuf message `schema`.
    #[error("not a {schema}: {source}")]
    Protobuf { schema: &'static str, source: ProtobufError },
    /// A raw image whose row stride is not its width times the pixel size.
    #[error("{encoding} step {step} for width {width}")]
    Step { encoding: &'static str, step: u32, width: usize },
    /// A raw image whose data is not its width x height pixels.
    #[error("{bytes} bytes for a {width}x{height} {encoding} image")]
    ImageSize { encoding: &'static str, bytes: usize, width: usize, height: usize },
    #[error("unsupported image encoding {encoding:?}")]
    UnsupportedEncoding { encoding: String },
    #[error("unsupported compressed image format {format:?} (this build reads jpeg)")]
    UnsupportedFormat { format: String },
    /// The JPEG stream does not decode (cut short, damaged, unsupported).
    #[error("jpeg: {source}")]
    Jpeg { source: zune_jpeg::errors::DecodeErrors },
    #[error("jpeg: no dimensions")]
    JpegNoDimensions,
    #[error("jpeg: decoded size differs from {width}x{height} {colour}")]
    JpegSize { width: usize, height: usize, colour: &'static str },
    /// A depth or variance plane of another encoding than `16FC1` or `32FC1`.
    #[error("encoding {encoding:?}, expected \"16FC1\" or \"32FC1\"")]
    PlaneEncoding { encoding: String },
    #[error("{bytes} bytes with step {step} for a {width}x{height} {encoding} image")]
    PlaneSize { encoding: &'static str, bytes: usize, step: u32, width: usize, height: usize },
    #[error("K has {entries} entries, expected 9")]
    CalibrationK { entries: usize },
    #[error(transparent)]
    Calibration(#[from] CameraModelError),
    #[error("pose missing or not finite")]
    BadPose,
    /// The body is not the CDR message `schema` (a log in the ROS 2 format).
    #[error("not a {schema}: {source}")]
    Cdr { schema: &'static str, source: super::cdr::CdrError },
    /// A `/slam/state` body that is neither JSON nor CDR.
    #[error("not a tracking state: {0}")]
    StateJson(#[from] serde_json::Error),
}

/// Which message schemas a log is written in (the board's `[log] format`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum LogFormat {
    /// Foxglove protobuf schemas and JSON records: opens in Foxglove.
    #[default]
    Foxglove,
    /// A ROS 2 bag: MCAP profile `ros2`, `ros2msg` schemas, CDR messages, and a
    /// `metadata.yaml` in the log folder ([`super::ros2`], [`super::bag`]).
    Ros2,
}

impl LogFormat {
    /// Every format, by name.
    pub const ALL: [LogFormat; 2] = [LogFormat::Foxglove, LogFormat::Ros2];

    pub fn name(self) -> &'static str {
        match self {
            LogFormat::Foxglove => "foxglove",
            LogFormat::Ros2 => "ros2",
        }
    }

    /// The MCAP header profile of the format.
    pub fn profile(self) -> &'static str {
        match self {
            LogFormat::Foxglove => "",
            LogFormat::Ros2 => super::cdr::PROFILE,
        }
    }
}

/// Frame id of the world (the tracker's map frame).
pub const WORLD_FRAME: &str = "world";
/// Frame id of the camera.
pub const CAMERA_FRAME: &str = "camera";

/// The calibration's topic in the ROS 2 format.
pub const CAMERA_INFO_TOPIC: &str = "/camera/camera_info";

/// Every topic the log writes. `sequence` in the MCAP message header is the frame `seq` for
/// per-frame topics and the keyframe id for keyframe topics.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Topic {
    CameraImage,
    CameraCalibration,
    Pose,
    Transform,
    State,
    KeyframeImage,
    KeyframeInvDepth,
    KeyframeVariance,
    KeyframePose,
    MapGaussians,
    MapCheckpoint,
    Health,
    TrackerWindow,
    /// The vehicle's navigation sensors (depth, altitude, DVL velocity, attitude), on the
    /// frames' clock: what replay and resume give the metric alignment.
    Nav,
    /// The pose with its velocity since the previous frame (`nav_msgs/msg/Odometry`); written
    /// in the ROS 2 format only.
    Odometry,
}

pub const ALL_TOPICS: [Topic; 15] = [
    Topic::CameraImage,
    Topic::CameraCalibration,
    Topic::Pose,
    Topic::Transform,
    Topic::State,
    Topic::KeyframeImage,
    Topic::KeyframeInvDepth,
    Topic::KeyframeVariance,
    Topic::KeyframePose,
    Topic::MapGaussians,
    Topic::MapCheckpoint,
    Topic::Health,
    Topic::TrackerWindow,
    Topic::Nav,
    Topic::Odometry,
];

/// Schema of a topic: name, schema encoding, schema bytes, message encoding.
pub struct TopicSchema {
    pub name: String,
    pub encoding: String,
    pub data: Vec<u8>,
    pub message_encoding: String,
}

const NAV_SCHEMA: &str = r#"{"title":"duv.NavSample","type":"object","description":"one navigation sample on the frames' clock; a missing field is a sensor without a sample","properties":{"t_ns":{"type":"integer"},"depth_m":{"type":"number","description":"pressure depth, positive down"},"altitude_m":{"type":"number","description":"range to the seabed along gravity"},"vel_cam_mps":{"type":"array","items":{"type":"number"},"description":"velocity over ground in the camera frame (x right, y down, z forward)"},"world_from_cam_xyzw":{"type":"array","items":{"type":"number"},"description":"the AHRS camera-to-world rotation, world z up"}}}"#;
const HEALTH_SCHEMA: &str = r#"{"title":"duv.Health","type":"object","description":"once a second: queue depths and drops, per-stage latency, budget headroom, host memory"}"#;

fn foxglove_schema<T: Encode>() -> TopicSchema {
    let s = T::get_schema().expect("foxglove messages carry their schema");
    TopicSchema { name: s.name, encoding: s.encoding, data: s.data.into_owned(), message_encoding: T::get_message_encoding() }
}

fn json_schema(name: &str, schema: &str) -> TopicSchema {
    TopicSchema { name: name.into(), encoding: "jsonschema".into(), data: schema.as_bytes().to_vec(), message_encoding: "json".into() }
}

/// How input frames are stored on [`Topic::CameraImage`] (the board's `[log] frame_encoding`).
/// Keyframe images are always raw: refinement reads them back and must get what mapping got.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum FrameEncoding {
    /// `foxglove.RawImage`, `rgb8` or `mono8`: lossless, 3 bytes per RGB pixel.
    #[default]
    Raw,
    /// `foxglove.CompressedImage`, format `jpeg`, at this quality (1..=100; below 90 the
    /// chroma is subsampled 4:2:0, from 90 on it is kept at full resolution).
    Jpeg { quality: u8 },
}

/// Lowest and highest JPEG quality [`FrameEncoding::Jpeg`] accepts.
pub const JPEG_QUALITY_RANGE: std::ops::RangeInclusive<u8> = 1..=100;

impl Topic {
    pub fn name(self) -> &'static str {
        match self {
            Topic::CameraImage => "/camera/image",
            Topic::CameraCalibration => "/camera/calibration",
            Topic::Pose => "/slam/pose",
            Topic::Transform => "/tf",
            Topic::State => "/slam/state",
            Topic::KeyframeImage => "/keyframe/image",
            Topic::KeyframeInvDepth => "/keyframe/inv_depth",
            Topic::KeyframeVariance => "/keyframe/variance",
            Topic::KeyframePose => "/keyframe/pose",
            Topic::MapGaussians => "/map/gaussians",
            Topic::MapCheckpoint => "/map/checkpoint",
            Topic::Health => "/health",
            Topic::TrackerWindow => "/slam/window",
            Topic::Nav => "/nav/sample",
            Topic::Odometry => "/slam/odometry",
        }
    }

    /// The topic's name in `format`: the ROS 2 format names the calibration
    /// `/camera/camera_info`, beside `/camera/image` as ROS tools (image_transport, rviz's
    /// camera display) look for it; every other name is [`Topic::name`].
    pub fn name_in(self, format: LogFormat) -> &'static str {
        match (self, format) {
            (Topic::CameraCalibration, LogFormat::Ros2) => CAMERA_INFO_TOPIC,
            _ => self.name(),
        }
    }

    /// The topic of a channel name in either format.
    pub fn from_name(name: &str) -> Option<Topic> {
        if name == CAMERA_INFO_TOPIC {
            return Some(Topic::CameraCalibration);
        }
        ALL_TOPICS.into_iter().find(|t| t.name() == name)
    }

    /// The schema; `None` for the schemaless channels (map checkpoint, tracker window).
    pub fn schema(self) -> Option<TopicSchema> {
        Some(match self {
            Topic::CameraImage | Topic::KeyframeImage | Topic::KeyframeInvDepth | Topic::KeyframeVariance => foxglove_schema::<fg::RawImage>(),
            Topic::CameraCalibration => foxglove_schema::<fg::CameraCalibration>(),
            Topic::Pose | Topic::KeyframePose => foxglove_schema::<fg::PoseInFrame>(),
            Topic::Transform => foxglove_schema::<fg::FrameTransform>(),
            Topic::MapGaussians => foxglove_schema::<fg::PointCloud>(),
            Topic::State => json_schema("duv.TrackingState", duv_core::pose::TRACKING_STATE_SCHEMA),
            Topic::Health => json_schema("duv.Health", HEALTH_SCHEMA),
            Topic::Nav => json_schema("duv.NavSample", NAV_SCHEMA),
            // The odometry is written in the ROS 2 format only.
            Topic::MapCheckpoint | Topic::TrackerWindow | Topic::Odometry => return None,
        })
    }

    /// The schema of the topic as a writer with `frames` writes it: `/camera/image` is
    /// `foxglove.CompressedImage` when frames are JPEG, [`Topic::schema`] otherwise.
    pub fn schema_for(self, frames: FrameEncoding) -> Option<TopicSchema> {
        match (self, frames) {
            (Topic::CameraImage, FrameEncoding::Jpeg { .. }) => Some(foxglove_schema::<fg::CompressedImage>()),
            _ => self.schema(),
        }
    }


    /// Message encoding of a schemaless topic.
    pub fn schemaless_encoding(self) -> &'static str {
        match self {
            Topic::TrackerWindow => super::window::WINDOW_ENCODING,
            _ => "duv.map_checkpoint",
        }
    }

    /// Index into per-topic tables.
    pub fn index(self) -> usize {
        self as usize
    }
}

pub use duv_core::PoseRecord;

pub use super::records::StateMessage;

/// What the other stages hand to the log writer.
#[derive(Clone, Debug)]
pub enum LogItem {
    /// An input frame, as delivered by the source (shared with tracking, not copied).
    Frame(std::sync::Arc<Frame>),
    Calibration { t_ns: Timestamp, camera: PinholeCamera },
    Pose(PoseRecord),
    Keyframe(std::sync::Arc<Keyframe>),
    /// A map checkpoint: the mapper's bytes and the Gaussian centres (world frame) for display.
    /// `last`: the run's final map, logged whatever the budget says.
    Map { t_ns: Timestamp, centres_in_world: Vec<[f32; 3]>, checkpoint: Vec<u8>, last: bool },
    /// A health record, already JSON.
    Health { t_ns: Timestamp, json: String },
    /// The tracker's newest keyframes (what a resume seeds a tracker with).
    Window(std::sync::Arc<TrackerWindow>),
    /// A navigation sample, on the frames' clock.
    Nav(duv_core::nav::NavSample),
}

impl LogItem {
    /// Bytes this item holds (what the byte-bounded log queue counts).
    pub fn approx_bytes(&self) -> usize {
        let base = std::mem::size_of::<LogItem>();
        base + match self {
            LogItem::Frame(f) => match &f.image {
                FrameImage::Rgb8(i) => i.data.len(),
                FrameImage::Gray8(i) => i.data.len(),
            },
            LogItem::Calibration { .. } | LogItem::Pose(_) | LogItem::Nav(_) => 0,
            LogItem::Keyframe(k) => k.image.data.len() + 2 * (k.inv_depth.data.len() + k.inv_depth_variance.data.len()),
            LogItem::Map { centres_in_world, checkpoint, .. } => 12 * centres_in_world.len() + checkpoint.len(),
            LogItem::Health { json, .. } => json.len(),
            LogItem::Window(w) => w.encoded_len(),
        }
    }

    pub fn t_ns(&self) -> Timestamp {
        match self {
            LogItem::Frame(f) => f.t_ns,
            LogItem::Calibration { t_ns, .. } | LogItem::Map { t_ns, .. } | LogItem::Health { t_ns, .. } => *t_ns,
            LogItem::Pose(p) => p.t_ns,
            LogItem::Keyframe(k) => k.t_ns,
            LogItem::Window(w) => w.t_ns,
            LogItem::Nav(n) => n.t_ns,
        }
    }
}

/// Foxglove time stamp of `t_ns` (negative times clamp to 0).
pub fn fg_time(t_ns: Timestamp) -> fg::Timestamp {
    let ns = t_ns.t_ns().max(0) as u64;
    fg::Timestamp::new((ns / 1_000_000_000).min(u32::MAX as u64) as u32, (ns % 1_000_000_000) as u32)
}

fn fg_pose(p: &Se3) -> fg::Pose {
    let t = p.translation.vector;
    let q = p.rotation.quaternion();
    fg::Pose {
        position: Some(fg::Vector3 { x: t.x, y: t.y, z: t.z }),
        orientation: Some(fg::Quaternion { x: q.i, y: q.j, z: q.k, w: q.w }),
    }
}

/// The pose a `foxglove.Pose` holds; `None` when a part is missing or not finite.
pub fn se3_from_fg(p: &fg::Pose) -> Option<Se3> {
    let t = p.position.as_ref()?;
    let q = p.orientation.as_ref()?;
    let v = [t.x, t.y, t.z, q.x, q.y, q.z, q.w];
    if v.iter().any(|x| !x.is_finite()) || (q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w) < 1e-12 {
        return None;
    }
    Some(Se3::from_parts(Translation3::new(t.x, t.y, t.z), UnitQuaternion::from_quaternion(Quaternion::new(q.w, q.x, q.y, q.z))))
}

fn encode<T: Encode>(msg: &T, what: &'static str, out: &mut Vec<u8>) -> Result<(), LogError> {
    out.clear();
    msg.encode(out).map_err(|e| LogError::Encode { what, problem: e.to_string() })
}

/// Messages whose strings are set once, so that encoding one allocates nothing: only their
/// numbers change from item to item.
pub(crate) struct Templates {
    image: fg::RawImage,
    compressed: fg::CompressedImage,
    pose: fg::PoseInFrame,
    transform: fg::FrameTransform,
    /// The JPEG encoder for the board's quality (its tables, built once).
    pub(crate) jpeg: Option<JpegEncoder>,
}

impl std::fmt::Debug for Templates {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Templates").field("jpeg_quality", &self.jpeg.as_ref().map(|e| e.quality())).finish_non_exhaustive()
    }
}

impl Default for Templates {
    fn default() -> Self {
        Templates {
            image: fg::RawImage { frame_id: CAMERA_FRAME.into(), encoding: String::with_capacity(8), ..Default::default() },
            compressed: fg::CompressedImage { frame_id: CAMERA_FRAME.into(), format: "jpeg".into(), ..Default::default() },
            pose: fg::PoseInFrame { frame_id: WORLD_FRAME.into(), ..Default::default() },
            transform: fg::FrameTransform { parent_frame_id: WORLD_FRAME.into(), child_frame_id: CAMERA_FRAME.into(), ..Default::default() },
            jpeg: None,
        }
    }
}

/// Pixel data of a `foxglove.RawImage`: bytes, or f32 samples written little endian as f32
/// or as f16 ([`PLANE_ENCODING`]).
pub(crate) enum Pixels<'a> {
    Bytes(&'a [u8]),
    #[allow(dead_code)]
    F32(&'a [f32]),
    F16(&'a [f32]),
}

/// The encoding of the logged keyframe inverse depth and variance: IEEE half floats
/// (`half::f16`), little endian, 2 bytes a pixel (the name OpenCV gives the type; ROS and
/// Foxglove define `32FC1` but no half-float encoding, so a viewer may not display these
/// planes). What it costs: 11 significant bits, a relative error of at most 2^-11 (0.049 %)
/// for magnitudes in [6.1e-5, 65504]; below 6.1e-5 (subnormal) an absolute error of at most
/// 2^-25 (3.0e-8); finite values beyond 65504 are stored as 65504 (an inverse-depth variance
/// that large, in m^-2, means "unknown" just as well), infinities and NaN as themselves. The
/// tracker's inverse depth (1/m, 0.01-10 underwater) and its variance carry less precision
/// than that. Logs written as `32FC1` (before this) are read as they are.
pub const PLANE_ENCODING: &str = "16FC1";

/// One plane sample as f16 bits (see [`PLANE_ENCODING`]); in [`super::cdr`], whose CDR
/// writer packs planes too.
pub use super::cdr::plane_sample_f16;

/// Encodes a `foxglove.RawImage` into `out` without building the message's `data` (a copy of
/// every pixel): the other fields through the template, then field 6 (`data`, length
/// delimited) appended from `pixels`. Protobuf readers take fields in any order.
#[allow(clippy::too_many_arguments)]
fn encode_raw_image(tpl: &mut fg::RawImage, t_ns: Timestamp, width: usize, height: usize, encoding: &str, step: usize, pixels: Pixels<'_>, what: &'static str, out: &mut Vec<u8>) -> Result<(), LogError> {
    tpl.timestamp = Some(fg_time(t_ns));
    tpl.width = width as u32;
    tpl.height = height as u32;
    tpl.encoding.clear();
    tpl.encoding.push_str(encoding);
    tpl.step = step as u32;
    encode(&*tpl, what, out)?;
    match pixels {
        Pixels::Bytes(b) => append_bytes_field(6, b, out),
        Pixels::F32(v) => {
            field_header(6, 4 * v.len(), out);
            for x in v {
                out.extend_from_slice(&x.to_le_bytes());
            }
        }
        Pixels::F16(v) => {
            field_header(6, 2 * v.len(), out);
            for &x in v {
                out.extend_from_slice(&plane_sample_f16(x).to_le_bytes());
            }
        }
    }
    Ok(())
}

/// A `32FC1` `foxglove.RawImage` as logs before [`PLANE_ENCODING`] held them (for tests).
#[cfg(test)]
#[allow(clippy::too_many_arguments)]
pub(crate) fn encode_raw_image_for_test(tpl: &mut fg::RawImage, t_ns: Timestamp, width: usize, height: usize, encoding: &str, step: usize, data: &[f32], out: &mut Vec<u8>) {
    encode_raw_image(tpl, t_ns, width, height, encoding, step, Pixels::F32(data), "test", out).unwrap();
}

/// One encoded MCAP message: topic, header sequence, log time, body in the caller's buffer.
pub struct Encoded {
    pub topic: Topic,
    pub sequence: u32,
    pub log_time_ns: u64,
}


/// Compresses `image` into `out` (cleared first; its capacity is reused) with a one-off
/// encoder; the log keeps one per quality ([`ItemEncoder`](super::encoder::ItemEncoder)).
pub fn encode_jpeg(image: &FrameImage, quality: u8, out: &mut Vec<u8>) -> Result<(), LogError> {
    let problem = |e: JpegError| LogError::Encode { what: "frame (jpeg)", problem: e.to_string() };
    let encoder = JpegEncoder::new(quality).map_err(problem)?;
    encode_jpeg_with(&encoder, image, out)
}

pub(crate) fn encode_jpeg_with(encoder: &JpegEncoder, image: &FrameImage, out: &mut Vec<u8>) -> Result<(), LogError> {
    let problem = |e: JpegError| LogError::Encode { what: "frame (jpeg)", problem: e.to_string() };
    match image {
        FrameImage::Rgb8(i) => encoder.encode(&i.data, i.width, i.height, 3, out),
        FrameImage::Gray8(i) => encoder.encode(&i.data, i.width, i.height, 1, out),
    }
    .map_err(problem)
}

/// Appends the key and length of protobuf field `field` (length delimited, `len` bytes).
fn field_header(field: u32, len: usize, out: &mut Vec<u8>) {
    out.push(((field << 3) | 2) as u8);
    let mut v = len as u64;
    while v >= 0x80 {
        out.push((v as u8 & 0x7f) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

/// Appends protobuf field `field` (length delimited) holding `bytes` to `out`.
fn append_bytes_field(field: u32, bytes: &[u8], out: &mut Vec<u8>) {
    field_header(field, bytes.len(), out);
    out.extend_from_slice(bytes);
}

pub(crate) fn encode_item(item: &LogItem, frames: FrameEncoding, scratch: &mut Vec<u8>, jpeg: &mut Vec<u8>, tpl: &mut Templates, mut emit: impl FnMut(Encoded, &[u8]) -> Result<(), LogError>) -> Result<(), LogError> {
    let log_time_ns = item.t_ns().t_ns().max(0) as u64;
    match item {
        LogItem::Frame(f) => {
            match frames {
                FrameEncoding::Raw => match &f.image {
                    FrameImage::Rgb8(i) => encode_raw_image(&mut tpl.image, f.t_ns, i.width, i.height, "rgb8", i.width * 3, Pixels::Bytes(&i.data), "frame", scratch)?,
                    FrameImage::Gray8(i) => encode_raw_image(&mut tpl.image, f.t_ns, i.width, i.height, "mono8", i.width, Pixels::Bytes(&i.data), "frame", scratch)?,
                },
                FrameEncoding::Jpeg { quality } => {
                    if tpl.jpeg.as_ref().is_none_or(|e| e.quality() != quality) {
                        let e = JpegEncoder::new(quality).map_err(|e| LogError::Encode { what: "frame (jpeg)", problem: e.to_string() })?;
                        tpl.jpeg = Some(e);
                    }
                    encode_jpeg_with(tpl.jpeg.as_ref().expect("set above"), &f.image, jpeg)?;
                    // The template's fields, then `data` (field 2) appended from the JPEG buffer.
                    tpl.compressed.timestamp = Some(fg_time(f.t_ns));
                    encode(&tpl.compressed, "frame", scratch)?;
                    append_bytes_field(2, jpeg, scratch);
                }
            }
            emit(Encoded { topic: Topic::CameraImage, sequence: f.seq as u32, log_time_ns }, scratch)
        }
        LogItem::Calibration { t_ns, camera } => {
            let (fx, fy, cx, cy) = (camera.fx, camera.fy, camera.cx, camera.cy);
            let (model, d) = match &camera.distortion {
                Some(rt) => ("plumb_bob".to_string(), vec![rt.k1, rt.k2, rt.p1, rt.p2, rt.k3]),
                None => (String::new(), Vec::new()),
            };
            let msg = fg::CameraCalibration {
                timestamp: Some(fg_time(*t_ns)),
                frame_id: CAMERA_FRAME.into(),
                width: camera.width as u32,
                height: camera.height as u32,
                distortion_model: model,
                d,
                k: vec![fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0],
                r: vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                p: vec![fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0],
            };
            encode(&msg, "calibration", scratch)?;
            emit(Encoded { topic: Topic::CameraCalibration, sequence: 0, log_time_ns }, scratch)
        }
        LogItem::Pose(p) => {
            let sequence = p.seq as u32;
            tpl.pose.timestamp = Some(fg_time(p.t_ns));
            tpl.pose.pose = Some(fg_pose(&p.world_from_cam));
            encode(&tpl.pose, "pose", scratch)?;
            emit(Encoded { topic: Topic::Pose, sequence, log_time_ns }, scratch)?;
            let t = p.world_from_cam.translation.vector;
            let q = p.world_from_cam.rotation.quaternion();
            tpl.transform.timestamp = Some(fg_time(p.t_ns));
            tpl.transform.translation = Some(fg::Vector3 { x: t.x, y: t.y, z: t.z });
            tpl.transform.rotation = Some(fg::Quaternion { x: q.i, y: q.j, z: q.k, w: q.w });
            encode(&tpl.transform, "transform", scratch)?;
            emit(Encoded { topic: Topic::Transform, sequence, log_time_ns }, scratch)?;
            let state = p.state_record();
            scratch.clear();
            serde_json::to_writer(&mut *scratch, &state).map_err(|e| LogError::Encode { what: "state", problem: e.to_string() })?;
            emit(Encoded { topic: Topic::State, sequence, log_time_ns }, scratch)
        }
        LogItem::Keyframe(k) => {
            let sequence = k.index as u32;
            let (w, h) = (k.image.width, k.image.height);
            encode_raw_image(&mut tpl.image, k.t_ns, w, h, "rgb8", w * 3, Pixels::Bytes(&k.image.data), "keyframe image", scratch)?;
            emit(Encoded { topic: Topic::KeyframeImage, sequence, log_time_ns }, scratch)?;
            let (dw, dh) = (k.inv_depth.width, k.inv_depth.height);
            encode_raw_image(&mut tpl.image, k.t_ns, dw, dh, PLANE_ENCODING, dw * 2, Pixels::F16(&k.inv_depth.data), "keyframe inverse depth", scratch)?;
            emit(Encoded { topic: Topic::KeyframeInvDepth, sequence, log_time_ns }, scratch)?;
            let (vw, vh) = (k.inv_depth_variance.width, k.inv_depth_variance.height);
            encode_raw_image(&mut tpl.image, k.t_ns, vw, vh, PLANE_ENCODING, vw * 2, Pixels::F16(&k.inv_depth_variance.data), "keyframe variance", scratch)?;
            emit(Encoded { topic: Topic::KeyframeVariance, sequence, log_time_ns }, scratch)?;
            tpl.pose.timestamp = Some(fg_time(k.t_ns));
            tpl.pose.pose = Some(fg_pose(&k.world_from_cam));
            encode(&tpl.pose, "keyframe pose", scratch)?;
            emit(Encoded { topic: Topic::KeyframePose, sequence, log_time_ns }, scratch)
        }
        LogItem::Map { t_ns, centres_in_world, checkpoint, .. } => {
            let mut data = Vec::with_capacity(centres_in_world.len() * 12);
            for c in centres_in_world {
                for v in c {
                    data.extend_from_slice(&v.to_le_bytes());
                }
            }
            let field = |name: &str, offset: u32| fg::PackedElementField { name: name.into(), offset, r#type: fg::packed_element_field::NumericType::Float32 as i32 };
            let msg = fg::PointCloud {
                timestamp: Some(fg_time(*t_ns)),
                frame_id: WORLD_FRAME.into(),
                pose: Some(fg_pose(&Se3::identity())),
                point_stride: 12,
                fields: vec![field("x", 0), field("y", 4), field("z", 8)],
                data: data.into(),
            };
            encode(&msg, "map point cloud", scratch)?;
            emit(Encoded { topic: Topic::MapGaussians, sequence: 0, log_time_ns }, scratch)?;
            emit(Encoded { topic: Topic::MapCheckpoint, sequence: 0, log_time_ns }, checkpoint)
        }
        LogItem::Health { json, .. } => emit(Encoded { topic: Topic::Health, sequence: 0, log_time_ns }, json.as_bytes()),
        LogItem::Window(w) => {
            w.encode(scratch)?;
            emit(Encoded { topic: Topic::TrackerWindow, sequence: w.seq as u32, log_time_ns }, scratch)
        }
        LogItem::Nav(n) => {
            scratch.clear();
            serde_json::to_writer(&mut *scratch, &NavJson::from(n)).map_err(|e| LogError::Encode { what: "navigation sample", problem: e.to_string() })?;
            emit(Encoded { topic: Topic::Nav, sequence: 0, log_time_ns }, scratch)
        }
    }
}

/// A `/nav/sample` message in the Foxglove format (JSON).
#[derive(Serialize, Deserialize)]
struct NavJson {
    t_ns: i64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    depth_m: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    altitude_m: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    vel_cam_mps: Option<[f64; 3]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    world_from_cam_xyzw: Option<[f64; 4]>,
}

impl From<&duv_core::nav::NavSample> for NavJson {
    fn from(n: &duv_core::nav::NavSample) -> Self {
        NavJson {
            t_ns: n.t_ns.t_ns(),
            depth_m: n.depth_m,
            altitude_m: n.altitude_m,
            vel_cam_mps: n.vel_cam_mps.map(|v| [v.x, v.y, v.z]),
            world_from_cam_xyzw: n.world_from_cam_rot.map(|q| [q.i, q.j, q.k, q.w]),
        }
    }
}

pub(crate) use super::records::nav_sample;

/// Decodes a `/nav/sample` message (JSON in the Foxglove format, `duv_msgs/msg/NavSample` in
/// the ROS 2 format).
pub fn decode_nav(data: &[u8]) -> Result<duv_core::nav::NavSample, DecodeError> {
    if super::cdr::is_cdr(data) {
        return super::cdr::decode_nav_sample(data).map_err(|source| DecodeError::Cdr { schema: "duv_msgs/msg/NavSample", source });
    }
    let j: NavJson = serde_json::from_slice(data)?;
    Ok(nav_sample(j.t_ns, j.depth_m, j.altitude_m, j.vel_cam_mps, j.world_from_cam_xyzw))
}

/// The wire type of field 2 of a protobuf message: `foxglove.RawImage` has its `width` there
/// (fixed32, wire type 5), `foxglove.CompressedImage` its `data` (length-delimited, wire type
/// 2). `None` when the field is absent or the bytes are not protobuf.
pub(crate) fn field2_wire_type(mut data: &[u8]) -> Option<u8> {
    fn varint(d: &mut &[u8]) -> Option<u64> {
        let mut v = 0u64;
        for shift in (0..64).step_by(7) {
            let (&b, rest) = d.split_first()?;
            *d = rest;
            v |= u64::from(b & 0x7f) << shift;
            if b & 0x80 == 0 {
                return Some(v);
            }
        }
        None
    }
    while !data.is_empty() {
        let key = varint(&mut data)?;
        let wire = (key & 7) as u8;
        if key >> 3 == 2 {
            return Some(wire);
        }
        let skip = match wire {
            0 => {
                varint(&mut data)?;
                0
            }
            1 => 8,
            2 => usize::try_from(varint(&mut data)?).ok()?,
            5 => 4,
            _ => return None,
        };
        data = data.get(skip..)?;
    }
    None
}

/// Decodes a logged frame: a `foxglove.RawImage` (`rgb8` or `mono8`) or a
/// `foxglove.CompressedImage` in format `jpeg` (colour or grey), whichever the message is.
pub fn decode_frame(data: &[u8], seq: u64, log_time_ns: u64) -> Result<Frame, DecodeError> {
    if super::cdr::is_cdr(data) {
        return decode_ros2_frame(data, seq);
    }
    if field2_wire_type(data) == Some(2) {
        return decode_jpeg_frame(data, seq, log_time_ns);
    }
    use foxglove::Decode;
    let img = fg::RawImage::decode(data).map_err(|source| DecodeError::Protobuf { schema: "foxglove.RawImage", source })?;
    let (w, h) = (img.width as usize, img.height as usize);
    let t_ns = timestamp_or(img.timestamp, log_time_ns);
    let image = raw_frame_image(&img.encoding, img.step, w, h, &img.data)?;
    Ok(Frame { t_ns, seq, image })
}


/// A raw `rgb8` or `mono8` image of `w` x `h` with rows of `step` bytes (the Foxglove
/// `RawImage` and the ROS 2 `sensor_msgs/Image` carry the same fields).
fn raw_frame_image(encoding: &str, step: u32, w: usize, h: usize, data: &[u8]) -> Result<FrameImage, DecodeError> {
    let size = |encoding| DecodeError::ImageSize { encoding, bytes: data.len(), width: w, height: h };
    Ok(match encoding {
        "rgb8" => {
            if step as usize != w * 3 {
                return Err(DecodeError::Step { encoding: "rgb8", step, width: w });
            }
            FrameImage::Rgb8(duv_core::ImageRgb8::from_vec(w, h, data.to_vec()).ok_or_else(|| size("rgb8"))?)
        }
        "mono8" => {
            if step as usize != w {
                return Err(DecodeError::Step { encoding: "mono8", step, width: w });
            }
            FrameImage::Gray8(duv_core::ImageGray8::from_vec(w, h, data.to_vec()).ok_or_else(|| size("mono8"))?)
        }
        other => return Err(DecodeError::UnsupportedEncoding { encoding: other.to_string() }),
    })
}

fn timestamp_or(t: Option<fg::Timestamp>, log_time_ns: u64) -> Timestamp {
    match t {
        Some(t) => Timestamp::from_ns(t.sec() as i64 * 1_000_000_000 + t.nsec() as i64),
        None => Timestamp::from_ns(log_time_ns as i64),
    }
}

/// Decodes a `foxglove.CompressedImage` holding a JPEG into a frame: grey JPEGs give grey
/// frames, colour ones RGB.
fn decode_jpeg_frame(data: &[u8], seq: u64, log_time_ns: u64) -> Result<Frame, DecodeError> {
    use foxglove::Decode;
    let img = fg::CompressedImage::decode(data).map_err(|source| DecodeError::Protobuf { schema: "foxglove.CompressedImage", source })?;
    if !img.format.eq_ignore_ascii_case("jpeg") && !img.format.eq_ignore_ascii_case("jpg") {
        return Err(DecodeError::UnsupportedFormat { format: img.format });
    }
    let t_ns = timestamp_or(img.timestamp, log_time_ns);
    let image = decode_jpeg(&img.data)?;
    Ok(Frame { t_ns, seq, image })
}

/// Decodes a JPEG stream into a frame.
fn decode_jpeg_bytes(jpeg: &[u8], t_ns: Timestamp, seq: u64) -> Result<Frame, DecodeError> {
    Ok(Frame { t_ns, seq, image: decode_jpeg(jpeg)? })
}

/// Decodes a JPEG (strictly: a damaged stream is an error): grey JPEGs give grey images,
/// colour ones RGB.
pub(crate) fn decode_jpeg(data: &[u8]) -> Result<FrameImage, DecodeError> {
    use zune_jpeg::zune_core::colorspace::ColorSpace;
    use zune_jpeg::zune_core::options::DecoderOptions;
    let mut probe = zune_jpeg::JpegDecoder::new_with_options(data, DecoderOptions::new_safe());
    probe.decode_headers().map_err(|source| DecodeError::Jpeg { source })?;
    let grey = probe.get_input_colorspace() == Some(ColorSpace::Luma);
    let (w, h) = probe.dimensions().ok_or(DecodeError::JpegNoDimensions)?;
    let out = if grey { ColorSpace::Luma } else { ColorSpace::RGB };
    // Strict: a damaged stream is an error, not a frame with a grey lower half.
    let options = DecoderOptions::new_safe().jpeg_set_out_colorspace(out).set_strict_mode(true);
    let mut decoder = zune_jpeg::JpegDecoder::new_with_options(data, options);
    let pixels = decoder.decode().map_err(|source| DecodeError::Jpeg { source })?;
    let size = |colour| DecodeError::JpegSize { width: w, height: h, colour };
    Ok(if grey {
        FrameImage::Gray8(duv_core::ImageGray8::from_vec(w, h, pixels).ok_or_else(|| size("grey"))?)
    } else {
        FrameImage::Rgb8(duv_core::ImageRgb8::from_vec(w, h, pixels).ok_or_else(|| size("rgb"))?)
    })
}

/// Decodes a `foxglove.RawImage` (or a ROS 2 `sensor_msgs/msg/Image`) of encoding `16FC1`
/// (little-endian f16, as the keyframe depth and variance are logged, [`PLANE_ENCODING`]) or
/// `32FC1` (little-endian f32, older logs) into a plane.
pub fn decode_plane_f32(data: &[u8]) -> Result<PlaneF32, DecodeError> {
    if super::cdr::is_cdr(data) {
        let img = super::cdr::decode_image(data).map_err(|source| DecodeError::Cdr { schema: "sensor_msgs/msg/Image", source })?;
        return plane_from_le(img.width as usize, img.height as usize, img.encoding, img.step, img.data);
    }
    use foxglove::Decode;
    let img = fg::RawImage::decode(data).map_err(|source| DecodeError::Protobuf { schema: "foxglove.RawImage", source })?;
    let (w, h) = (img.width as usize, img.height as usize);
    plane_from_le(w, h, &img.encoding, img.step, &img.data)
}

/// A `16FC1` or `32FC1` plane from its little-endian samples.
fn plane_from_le(w: usize, h: usize, encoding: &str, step: u32, bytes: &[u8]) -> Result<PlaneF32, DecodeError> {
    let (name, sample) = match encoding {
        "16FC1" => ("16FC1", 2),
        "32FC1" => ("32FC1", 4),
        _ => return Err(DecodeError::PlaneEncoding { encoding: encoding.to_string() }),
    };
    let size = || DecodeError::PlaneSize { encoding: name, bytes: bytes.len(), step, width: w, height: h };
    let n = w.checked_mul(h).and_then(|n| n.checked_mul(sample));
    if w.checked_mul(sample) != Some(step as usize) || n != Some(bytes.len()) {
        return Err(size());
    }
    let data = if sample == 2 {
        bytes.chunks_exact(2).map(|b| half::f16::from_bits(u16::from_le_bytes([b[0], b[1]])).to_f32()).collect()
    } else {
        bytes.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect()
    };
    PlaneF32::from_vec(w, h, data).ok_or_else(size)
}

/// Decodes a `foxglove.CameraCalibration` into a pinhole camera (distortion dropped: the log
/// holds undistorted frames).
pub fn decode_calibration(data: &[u8]) -> Result<PinholeCamera, DecodeError> {
    if super::cdr::is_cdr(data) {
        let (w, h, k) = super::cdr::decode_camera_info(data).map_err(|source| DecodeError::Cdr { schema: "sensor_msgs/msg/CameraInfo", source })?;
        return Ok(PinholeCamera::new(k[0], k[4], k[2], k[5], w as usize, h as usize)?);
    }
    use foxglove::Decode;
    let c = fg::CameraCalibration::decode(data).map_err(|source| DecodeError::Protobuf { schema: "foxglove.CameraCalibration", source })?;
    if c.k.len() != 9 {
        return Err(DecodeError::CalibrationK { entries: c.k.len() });
    }
    Ok(PinholeCamera::new(c.k[0], c.k[4], c.k[2], c.k[5], c.width as usize, c.height as usize)?)
}

/// Decodes a `foxglove.PoseInFrame`.
pub fn decode_pose(data: &[u8]) -> Result<Se3, DecodeError> {
    if super::cdr::is_cdr(data) {
        let (_, t, q) = super::cdr::decode_pose_stamped(data).map_err(|source| DecodeError::Cdr { schema: "geometry_msgs/msg/PoseStamped", source })?;
        let p = fg::Pose { position: Some(fg::Vector3 { x: t[0], y: t[1], z: t[2] }), orientation: Some(fg::Quaternion { x: q[0], y: q[1], z: q[2], w: q[3] }) };
        return se3_from_fg(&p).ok_or(DecodeError::BadPose);
    }
    use foxglove::Decode;
    let p = fg::PoseInFrame::decode(data).map_err(|source| DecodeError::Protobuf { schema: "foxglove.PoseInFrame", source })?;
    p.pose.as_ref().and_then(se3_from_fg).ok_or(DecodeError::BadPose)
}

/// Decodes a `/slam/state` message: JSON (`duv.TrackingState`) or CDR
/// (`duv_msgs/msg/TrackingState`).
pub fn decode_state(data: &[u8]) -> Result<StateMessage, DecodeError> {
    if super::cdr::is_cdr(data) {
        return super::cdr::decode_tracking_state(data).map_err(|source| DecodeError::Cdr { schema: "duv_msgs/msg/TrackingState", source });
    }
    Ok(serde_json::from_slice(data)?)
}

/// The payload of a `/map/checkpoint` or `/slam/window` message: the body itself in the
/// Foxglove format (schemaless channels), the `data` field of the `duv_msgs` message in the
/// ROS 2 format.
pub fn decode_payload(data: &[u8]) -> Result<&[u8], DecodeError> {
    if super::cdr::is_cdr(data) {
        return super::cdr::decode_wrapped(data).map_err(|source| DecodeError::Cdr { schema: "duv_msgs/msg/MapCheckpoint", source });
    }
    Ok(data)
}

/// Decodes a `sensor_msgs/msg/Image` (`rgb8`, `mono8`) or a `sensor_msgs/msg/CompressedImage`
/// (`jpeg`) into a frame. A compressed image is recognised by parsing as one to the last byte
/// (a raw image does not: its height would be read as the format's length).
fn decode_ros2_frame(data: &[u8], seq: u64) -> Result<Frame, DecodeError> {
    if let Ok((t_ns, format, jpeg)) = super::cdr::decode_compressed_image(data) {
        if !format.eq_ignore_ascii_case("jpeg") && !format.eq_ignore_ascii_case("jpg") {
            return Err(DecodeError::UnsupportedFormat { format: format.to_string() });
        }
        return decode_jpeg_bytes(jpeg, Timestamp::from_ns(t_ns), seq);
    }
    let img = super::cdr::decode_image(data).map_err(|source| DecodeError::Cdr { schema: "sensor_msgs/msg/Image", source })?;
    let (w, h) = (img.width as usize, img.height as usize);
    let image = raw_frame_image(img.encoding, img.step, w, h, img.data)?;
    Ok(Frame { t_ns: Timestamp::from_ns(img.t_ns), seq, image })
}

