//! ROS 2 bags in: a rosbag2 folder (`metadata.yaml` and its `*.mcap` files) or one `.mcap`
//! file as a [`FrameSource`] (`--source rosbag:PATH[,OPTION=VALUE]...`), with the camera from
//! the bag's `sensor_msgs/msg/CameraInfo` and the vehicle's navigation sensors where the bag
//! has them.
//!
//! **Topics.** Every channel with message encoding `cdr` is listed with its schema name
//! ([`RosbagSource::topics`]). The image topic is `image=/topic`, else the only
//! `sensor_msgs/msg/Image` or `sensor_msgs/msg/CompressedImage` topic (several: an error
//! listing them). The camera: `calib=FILE` (read by the caller) wins; else the first
//! `sensor_msgs/msg/CameraInfo` of `camera_info=/topic` or of the image's namespace
//! (`/cam/image_raw` and `/cam/image_raw/compressed` look for `/cam/image_raw/camera_info`,
//! then `/cam/camera_info`); else `fov=DEG` (a pinhole guess at the images' size); else an
//! error. Distortion `plumb_bob` (k1 k2 p1 p2 k3) is kept on the camera, and the pipeline
//! undistorts as for datasets; `rational_polynomial` is accepted when its denominator terms
//! (k4 k5 k6) are zero (then it is plumb_bob), other models are an error naming them.
//!
//! **Images.** `sensor_msgs/msg/Image` encodings `rgb8`, `bgr8`, `rgba8`, `bgra8` (colour),
//! `mono8`/`8UC1`, `mono16`/`16UC1` (grey, the high byte kept, as for 16-bit dataset images)
//! and `bayer_rggb8`, `bayer_bggr8`, `bayer_gbrg8`, `bayer_grbg8` (one colour per 2x2 cell, as
//! the live cameras' Bayer conversion); `CompressedImage` holding JPEG or PNG (told by the
//! data's signature, not the free-form `format` string). The header stamp is the frame time;
//! frames come in the bag's order (the order rosbag2 received them, by log time); a frame
//! whose stamp does not increase is skipped and counted, a frame that cannot be decoded is
//! skipped, counted and its reason kept ([`RosbagSource::bad_frames`]). Pacing is the
//! pipeline's (`--speed 1`: recorded timing; none: as fast as the tracker takes them).
//!
//! **Navigation** ([`RosbagSource::nav`]), mapped to [`duv_core::nav`] rows and judged by
//! [`judge_nav_rows`] exactly like `nav.csv` rows (bad values rejected and counted):
//! - depth: `sensor_msgs/msg/FluidPressure`, depth = (pressure - `surface_pressure`) /
//!   (`water_density` x 9.80665), defaults 101 325 Pa and 1025 kg/m^3 (mean sea water);
//!   `depth=/topic` may also name a `nav_msgs/msg/Odometry`,
//!   `geometry_msgs/msg/PoseWithCovarianceStamped` or `PoseStamped` topic, whose position z
//!   (a world with z up and 0 at the surface) gives depth = -z. Only pressure is picked by
//!   type: a vehicle's odometry is often in a local frame whose z is not depth;
//! - altitude: `sensor_msgs/msg/Range` (`range`, metres);
//! - DVL velocity: `geometry_msgs/msg/TwistWithCovarianceStamped` or `TwistStamped`
//!   (`linear`, m/s);
//! - attitude: `sensor_msgs/msg/Imu` `orientation` (skipped where `orientation_covariance[0]`
//!   is -1, the ROS "no orientation" mark).
//!
//! Each is picked by type when the bag has exactly one such topic (several: none is used, and
//! [`RosbagSource::notes`] says which to name), or named by `depth=`, `altitude=`, `dvl=`,
//! `imu=` (`none` turns one off). **Extrinsics are identity:** velocity and orientation are
//! taken as given in the camera frame (x right, y down, z forward) and the world with z up,
//! the frames `nav.csv` uses; a vehicle whose sensors publish in other frames must transform
//! them first. Stamps are the message header stamps, the images' clock; per topic a stamp that
//! goes back or repeats is rejected and counted as in `nav.csv`; samples of different sensors
//! at the same stamp share a row.
//!
//! **CDR** is read by a hand-written reader ([`Cdr`]) rather than a serde crate (`cdr`): the
//! messages read here are a dozen fixed ROS 2 types of which only a few leading fields are
//! needed; the reader borrows the image bytes from the message instead of copying them into a
//! `Vec`, and names the field a truncated message ends in. It follows the encapsulation header
//! (`00 00` big-endian, `00 01` little-endian plain CDR; parameter lists and XCDR2 are an
//! error) and ROS 2's alignment: each primitive aligned to its size (8 for `float64`),
//! offsets counted from the end of the 4-byte header.
//!
//! **Files.** The folder's `metadata.yaml` lists its files in order (`relative_file_paths`);
//! without it every `*.mcap` in the folder is read in natural name order. SQLite bags
//! (`*.db3`) are not read (`ros2 bag convert` writes MCAP). Chunks are read by the log's
//! salvaging reader ([`SegmentReader`]): uncompressed, zstd (rosbag2's default) or lz4; other
//! chunk compressions are an error naming them.
//!
//! Memory: opening reads the bag once, keeps the first CameraInfo messages and the first image
//! of each topic, and decodes the navigation messages into rows at once; frames are then read
//! one message at a time. Like the `mcap:`
//! replay, each frame is a new image (no pooling).

use crate::reader::OwnedEvent;
use crate::{ReadLimits, SegmentReader};
use duv_core::nav::{judge_nav_rows, NavRow, NavTrack};
use duv_core::source::{CameraError, FrameSource};
use duv_core::{Frame, FrameImage, ImageGray8, ImageRgb8, PinholeCamera, RadTan, Timestamp};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Standard gravity, m/s^2 (pressure to depth).
pub const GRAVITY_MPS2: f64 = 9.80665;
/// Default water density, kg/m^3 (mean sea water; fresh water is about 1000).
pub const DEFAULT_WATER_DENSITY_KG_M3: f64 = 1025.0;
/// Default pressure at the surface, Pa (one standard atmosphere).
pub const DEFAULT_SURFACE_PRESSURE_PA: f64 = 101_325.0;
/// The options a `rosbag:` spec takes.
pub const ROSBAG_OPTIONS: &str = "image, camera_info, calib, fov, depth, altitude, dvl, imu, water_density, surface_pressure";

/// Errors of the ROS 2 bag source; each names the file, topic or field it is about.
#[derive(Debug, thiserror::Error)]
pub enum RosbagError {
    #[error("rosbag:{spec}: {problem}")]
    BadSpec { spec: String, problem: String },
    #[error("{path}: not found")]
    NotFound { path: PathBuf },
    #[error("{path}: no .mcap file here{hint}")]
    NoMcap { path: PathBuf, hint: String },
    #[error("{path}: metadata.yaml names {file}, which is missing")]
    MissingFile { path: PathBuf, file: PathBuf },
    #[error("{path}: chunks compressed with {compression} cannot be read (uncompressed, zstd or lz4 only)")]
    Compressed { path: PathBuf, compression: String },
    #[error("{path}: no sensor_msgs/msg/Image or CompressedImage topic; topics: {topics}")]
    NoImageTopic { path: PathBuf, topics: String },
    #[error("several image topics: {candidates}; name one with image=/topic")]
    AmbiguousImage { candidates: String },
    #[error("{option}={topic}: no such topic in the bag; {candidates}")]
    TopicNotFound { option: &'static str, topic: String, candidates: String },
    #[error("{option}={topic}: its type is {found}, expected {expected}")]
    WrongType { option: &'static str, topic: String, found: String, expected: &'static str },
    #[error("{topic}: message encoding {encoding:?}, expected cdr")]
    NotCdr { topic: String, encoding: String },
    #[error("no camera for {image_topic}: no sensor_msgs/msg/CameraInfo at {looked_for}{other}; name one with camera_info=/topic, or give calib=FILE or fov=DEG")]
    NoCamera { image_topic: String, looked_for: String, other: String },
    #[error("{topic}: {problem}")]
    CameraInfo { topic: String, problem: String },
    #[error("{topic}: no message decodes as an image (first problem: {problem})")]
    NoFrames { topic: String, problem: String },
    #[error("{topic}: the camera is {camera_width}x{camera_height}, the images {width}x{height}")]
    ImageSize { topic: String, width: usize, height: usize, camera_width: usize, camera_height: usize },
    /// A message that cannot be decoded, with where it is.
    #[error("{topic}, message {index}: {source}")]
    InMessage { topic: String, index: u64, source: Box<RosbagError> },
    #[error("the message ends inside {field} (needs {needed} bytes at offset {offset}, has {len})")]
    Truncated { field: &'static str, offset: usize, needed: usize, len: usize },
    #[error("CDR encapsulation {kind:#06x} is not plain CDR (0x0000 big-endian, 0x0001 little-endian)")]
    Encapsulation { kind: u16 },
    #[error("{field}: {problem}")]
    BadField { field: &'static str, problem: String },
    #[error("image encoding {encoding:?} is not read (rgb8, bgr8, rgba8, bgra8, mono8, mono16, bayer_rggb8/bggr8/gbrg8/grbg8)")]
    UnknownEncoding { encoding: String },
    #[error("compressed image format {format:?}: the data is neither JPEG nor PNG")]
    UnknownCompressedFormat { format: String },
    #[error("{problem}")]
    Decode { problem: String },
    #[error(transparent)]
    Log(#[from] crate::LogError),
}

impl From<RosbagError> for CameraError {
    fn from(e: RosbagError) -> Self {
        CameraError::BadSpec { spec: "rosbag:".into(), problem: e.to_string() }
    }
}

/// A parsed `rosbag:PATH[,OPTION=VALUE]...` spec (the part after `rosbag:`).
#[derive(Clone, Debug, PartialEq)]
pub struct RosbagSpec {
    /// A rosbag2 folder or one `.mcap` file.
    pub path: PathBuf,
    /// `image=/topic`: the image topic (default: the bag's only one).
    pub image: Option<String>,
    /// `camera_info=/topic` (default: the image's namespace).
    pub camera_info: Option<String>,
    /// `calib=FILE`: a `calibration.txt`, read by the caller (it wins over CameraInfo).
    pub calib: Option<PathBuf>,
    /// `fov=DEG`: a pinhole guess when the bag has no CameraInfo.
    pub fov_deg: Option<f64>,
    /// `depth=`, `altitude=`, `dvl=`, `imu=`: topics; `Some("none")` turns a sensor off.
    pub depth: Option<String>,
    pub altitude: Option<String>,
    pub dvl: Option<String>,
    pub imu: Option<String>,
    /// `water_density=KG_M3` [default 1025].
    pub water_density_kg_m3: f64,
    /// `surface_pressure=PA` [default 101325].
    pub surface_pressure_pa: f64,
}

impl RosbagSpec {
    /// Parses the part of a spec after `rosbag:`.
    pub fn parse(rest: &str) -> Result<Self, RosbagError> {
        let bad = |problem: String| RosbagError::BadSpec { spec: rest.to_string(), problem };
        let mut parts = rest.split(',');
        let path = parts.next().unwrap_or("").trim();
        if path.is_empty() {
            return Err(bad("no bag folder or .mcap file after rosbag:".into()));
        }
        let mut s = RosbagSpec {
            path: PathBuf::from(path),
            image: None,
            camera_info: None,
            calib: None,
            fov_deg: None,
            depth: None,
            altitude: None,
            dvl: None,
            imu: None,
            water_density_kg_m3: DEFAULT_WATER_DENSITY_KG_M3,
            surface_pressure_pa: DEFAULT_SURFACE_PRESSURE_PA,
        };
        let mut seen: Vec<String> = Vec::new();
        for part in parts {
            let (key, value) = part.split_once('=').map(|(k, v)| (k.trim(), v.trim())).ok_or_else(|| bad(format!("option {part:?} is not KEY=VALUE")))?;
            if seen.iter().any(|k| k == key) {
                return Err(bad(format!("option {key:?} given twice")));
            }
            seen.push(key.to_string());
            if value.is_empty() {
                return Err(bad(format!("option {key:?} has no value")));
            }
            let number = |lo: f64, hi: f64, what: &str| -> Result<f64, RosbagError> {
                match value.parse::<f64>() {
                    Ok(v) if v.is_finite() && (lo..=hi).contains(&v) => Ok(v),
                    _ => Err(bad(format!("{key}={value:?} must be {what}, {lo} to {hi}"))),
                }
            };
            let topic = || -> Result<Option<String>, RosbagError> {
                if value != "none" && !value.starts_with('/') {
                    return Err(bad(format!("{key}={value:?}: a topic starts with /")));
                }
                Ok(Some(value.to_string()))
            };
            match key {
                "image" => s.image = topic()?,
                "camera_info" => s.camera_info = topic()?,
                "depth" => s.depth = topic()?,
                "altitude" => s.altitude = topic()?,
                "dvl" => s.dvl = topic()?,
                "imu" => s.imu = topic()?,
                "calib" => s.calib = Some(PathBuf::from(value)),
                "fov" => s.fov_deg = Some(number(1.0, 170.0, "a horizontal field of view in degrees")?),
                "water_density" => s.water_density_kg_m3 = number(900.0, 1100.0, "a water density in kg/m^3")?,
                "surface_pressure" => s.surface_pressure_pa = number(50_000.0, 150_000.0, "a surface pressure in Pa")?,
                other => return Err(bad(format!("unknown option {other:?} (accepted: {ROSBAG_OPTIONS})"))),
            }
        }
        if s.image.as_deref() == Some("none") {
            return Err(bad("image=none: a bag source needs an image topic".into()));
        }
        Ok(s)
    }
}

/// A topic of the bag.
#[derive(Clone, Debug, PartialEq)]
pub struct BagTopic {
    pub topic: String,
    /// Schema name, e.g. `sensor_msgs/msg/Image`.
    pub schema: String,
    pub message_encoding: String,
    pub messages: u64,
}

/// The ROS 2 message types this source reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum MsgType {
    Image,
    CompressedImage,
    CameraInfo,
    FluidPressure,
    Range,
    Imu,
    TwistStamped,
    TwistWithCovarianceStamped,
    Odometry,
    PoseWithCovarianceStamped,
    PoseStamped,
}

impl MsgType {
    /// From a schema name, `pkg/msg/Type` (or `pkg/Type`).
    fn from_schema(name: &str) -> Option<Self> {
        let mut it = name.split('/');
        let pkg = it.next()?;
        let ty = it.next_back()?;
        Some(match (pkg, ty) {
            ("sensor_msgs", "Image") => MsgType::Image,
            ("sensor_msgs", "CompressedImage") => MsgType::CompressedImage,
            ("sensor_msgs", "CameraInfo") => MsgType::CameraInfo,
            ("sensor_msgs", "FluidPressure") => MsgType::FluidPressure,
            ("sensor_msgs", "Range") => MsgType::Range,
            ("sensor_msgs", "Imu") => MsgType::Imu,
            ("geometry_msgs", "TwistStamped") => MsgType::TwistStamped,
            ("geometry_msgs", "TwistWithCovarianceStamped") => MsgType::TwistWithCovarianceStamped,
            ("nav_msgs", "Odometry") => MsgType::Odometry,
            ("geometry_msgs", "PoseWithCovarianceStamped") => MsgType::PoseWithCovarianceStamped,
            ("geometry_msgs", "PoseStamped") => MsgType::PoseStamped,
            _ => return None,
        })
    }

    fn is_image(self) -> bool {
        matches!(self, MsgType::Image | MsgType::CompressedImage)
    }

    fn is_nav(self) -> bool {
        !self.is_image() && self != MsgType::CameraInfo
    }
}

/// The four navigation sensors: option name, types picked automatically, types accepted when
/// named, in words.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Sensor {
    Depth,
    Altitude,
    Dvl,
    Imu,
}

impl Sensor {
    const ALL: [Sensor; 4] = [Sensor::Depth, Sensor::Altitude, Sensor::Dvl, Sensor::Imu];

    fn option(self) -> &'static str {
        match self {
            Sensor::Depth => "depth",
            Sensor::Altitude => "altitude",
            Sensor::Dvl => "dvl",
            Sensor::Imu => "imu",
        }
    }

    fn picked_by_type(self, t: MsgType) -> bool {
        match self {
            Sensor::Depth => t == MsgType::FluidPressure,
            Sensor::Altitude => t == MsgType::Range,
            Sensor::Dvl => matches!(t, MsgType::TwistStamped | MsgType::TwistWithCovarianceStamped),
            Sensor::Imu => t == MsgType::Imu,
        }
    }

    fn accepts(self, t: MsgType) -> bool {
        self.picked_by_type(t) || (self == Sensor::Depth && matches!(t, MsgType::Odometry | MsgType::PoseWithCovarianceStamped | MsgType::PoseStamped))
    }

    fn expected(self) -> &'static str {
        match self {
            Sensor::Depth => "sensor_msgs/msg/FluidPressure, nav_msgs/msg/Odometry, geometry_msgs/msg/PoseWithCovarianceStamped or PoseStamped",
            Sensor::Altitude => "sensor_msgs/msg/Range",
            Sensor::Dvl => "geometry_msgs/msg/TwistWithCovarianceStamped or TwistStamped",
            Sensor::Imu => "sensor_msgs/msg/Imu",
        }
    }

    fn spec_topic(self, spec: &RosbagSpec) -> Option<&str> {
        match self {
            Sensor::Depth => spec.depth.as_deref(),
            Sensor::Altitude => spec.altitude.as_deref(),
            Sensor::Dvl => spec.dvl.as_deref(),
            Sensor::Imu => spec.imu.as_deref(),
        }
    }
}

/// A topic chosen for a navigation sensor and how many samples it gave.
#[derive(Clone, Debug, PartialEq)]
pub struct NavTopic {
    pub sensor: &'static str,
    pub topic: String,
    pub schema: String,
    pub messages: u64,
}

/// Frames (and the camera, and the navigation samples) of a ROS 2 bag.
pub struct RosbagSource {
    path: PathBuf,
    files: Vec<PathBuf>,
    limits: ReadLimits,
    topics: Vec<BagTopic>,
    image_topic: String,
    compressed: bool,
    /// The camera of the images as stored (with distortion where the bag's CameraInfo has it).
    camera: PinholeCamera,
    camera_from: String,
    nav: NavTrack,
    nav_topics: Vec<NavTopic>,
    notes: Vec<String>,
    // Reading state.
    next_file: usize,
    reader: Option<SegmentReader>,
    /// Messages seen on the image topic so far (the frame's `seq`).
    image_index: u64,
    last_t: Option<Timestamp>,
    frames: u64,
    bad_frames: u64,
    out_of_order_frames: u64,
    last_problem: Option<String>,
    max_frames: Option<u64>,
}

/// CameraInfo messages kept per topic while opening (the first that decodes is used).
const CAMERA_INFO_KEPT: usize = 4;

/// A navigation topic's messages, decoded while opening (rows in bag order, the bad counted).
#[derive(Default)]
struct NavDecoded {
    rows: Vec<NavRow>,
    bad: u64,
    first_problem: Option<String>,
}

impl RosbagSource {
    /// Opens the bag `spec` names. `calibration`: the camera of `calib=FILE`, read by the
    /// caller (it wins over the bag's CameraInfo).
    pub fn open(spec: &RosbagSpec, calibration: Option<PinholeCamera>) -> Result<Self, RosbagError> {
        let limits = ReadLimits::default();
        let files = bag_files(&spec.path)?;
        // One pass over the bag: topics, counts, the small messages, the first image per topic.
        let mut topics: BTreeMap<String, BagTopic> = BTreeMap::new();
        // Per topic: the first CameraInfo messages (index, data); navigation messages decoded
        // at once, so a long dive's IMU is kept as rows, not as messages.
        let mut infos: BTreeMap<String, Vec<(u64, Vec<u8>)>> = BTreeMap::new();
        let mut decoded: BTreeMap<String, NavDecoded> = BTreeMap::new();
        let mut first_image: BTreeMap<String, Vec<u8>> = BTreeMap::new();
        for f in &files {
            let mut r = SegmentReader::open(f, limits)?;
            let mut schemas: BTreeMap<u16, String> = BTreeMap::new();
            while let Some(e) = r.next_event() {
                match e {
                    OwnedEvent::Schema(s) => {
                        schemas.insert(s.id, s.name);
                    }
                    OwnedEvent::Channel(c) => {
                        let schema = schemas.get(&c.schema_id).cloned().unwrap_or_default();
                        topics.entry(c.topic.clone()).or_insert(BagTopic { topic: c.topic, schema, message_encoding: c.message_encoding, messages: 0 });
                    }
                    OwnedEvent::Message { channel_id, data, .. } => {
                        let Some(c) = r.channel(channel_id) else { continue };
                        let Some(t) = topics.get_mut(&c.topic) else { continue };
                        let index = t.messages;
                        t.messages += 1;
                        match MsgType::from_schema(&t.schema) {
                            Some(MsgType::CameraInfo) => {
                                let v = infos.entry(t.topic.clone()).or_default();
                                if v.len() < CAMERA_INFO_KEPT {
                                    v.push((index, data));
                                }
                            }
                            Some(m) if m.is_nav() => {
                                let d = decoded.entry(t.topic.clone()).or_default();
                                match decode_nav(&data, m, spec) {
                                    Ok(Some(row)) => d.rows.push(row),
                                    Ok(None) => {}
                                    Err(e) => {
                                        d.bad += 1;
                                        d.first_problem.get_or_insert_with(|| RosbagError::InMessage { topic: t.topic.clone(), index, source: Box::new(e) }.to_string());
                                    }
                                }
                            }
                            Some(_) => {
                                first_image.entry(t.topic.clone()).or_insert(data);
                            }
                            None => {}
                        }
                    }
                    OwnedEvent::Metadata { .. } => {}
                }
            }
            let outcome = r.outcome();
            if let Some(s) = outcome.skipped.iter().find(|s| s.why.contains("compressed with")) {
                let compression = s.why.split("compressed with ").nth(1).and_then(|w| w.split_whitespace().next()).unwrap_or("?").to_string();
                return Err(RosbagError::Compressed { path: f.clone(), compression });
            }
            if let Some(d) = &outcome.damage {
                tracing::warn!("{}: {d}", f.display());
            }
        }
        let topics: Vec<BagTopic> = topics.into_values().collect();
        let typed = |t: &BagTopic| MsgType::from_schema(&t.schema);
        let listing = |pred: &dyn Fn(&BagTopic) -> bool| -> String {
            let v: Vec<String> = topics.iter().filter(|t| pred(t)).map(|t| format!("{} ({}, {} messages)", t.topic, t.schema, t.messages)).collect();
            if v.is_empty() { "none".into() } else { v.join(", ") }
        };
        let find = |option: &'static str, topic: &str, pred: &dyn Fn(&BagTopic) -> bool, what: &str| -> Result<&BagTopic, RosbagError> {
            topics.iter().find(|t| t.topic == topic).ok_or_else(|| RosbagError::TopicNotFound { option, topic: topic.to_string(), candidates: format!("{what}: {}", listing(pred)) })
        };
        let cdr = |t: &BagTopic| -> Result<(), RosbagError> {
            if t.message_encoding != "cdr" {
                return Err(RosbagError::NotCdr { topic: t.topic.clone(), encoding: t.message_encoding.clone() });
            }
            Ok(())
        };
        let is_image = |t: &BagTopic| typed(t).is_some_and(MsgType::is_image);
        // The image topic.
        let image = match &spec.image {
            Some(name) => {
                let t = find("image", name, &is_image, "image topics")?;
                if !is_image(t) {
                    return Err(RosbagError::WrongType { option: "image", topic: name.clone(), found: t.schema.clone(), expected: "sensor_msgs/msg/Image or sensor_msgs/msg/CompressedImage" });
                }
                t
            }
            None => {
                let c: Vec<&BagTopic> = topics.iter().filter(|t| is_image(t)).collect();
                match c.as_slice() {
                    [] => return Err(RosbagError::NoImageTopic { path: spec.path.clone(), topics: listing(&|_| true) }),
                    [one] => *one,
                    _ => return Err(RosbagError::AmbiguousImage { candidates: listing(&is_image) }),
                }
            }
        };
        cdr(image)?;
        let image_topic = image.topic.clone();
        let compressed = typed(image) == Some(MsgType::CompressedImage);
        // The first image: its size and that its encoding is one we read.
        let first = first_image.get(&image_topic).ok_or_else(|| RosbagError::NoFrames { topic: image_topic.clone(), problem: "the topic has no messages".into() })?;
        let (_, first) = decode_image_message(first, compressed).map_err(|e| RosbagError::InMessage { topic: image_topic.clone(), index: 0, source: Box::new(e) })?;
        let (width, height) = (first.width(), first.height());
        // The camera.
        let is_info = |t: &BagTopic| typed(t) == Some(MsgType::CameraInfo);
        let (camera, camera_from) = if let Some(c) = calibration {
            (c, "calib=".to_string())
        } else {
            let info_topic: Option<&BagTopic> = match &spec.camera_info {
                Some(name) => {
                    let t = find("camera_info", name, &is_info, "CameraInfo topics")?;
                    if !is_info(t) {
                        return Err(RosbagError::WrongType { option: "camera_info", topic: name.clone(), found: t.schema.clone(), expected: "sensor_msgs/msg/CameraInfo" });
                    }
                    Some(t)
                }
                None => namespace_candidates(&image_topic).iter().find_map(|n| topics.iter().find(|t| &t.topic == n && is_info(t))),
            };
            match (info_topic, spec.fov_deg) {
                (Some(t), _) => {
                    cdr(t)?;
                    let mut problem = None;
                    let mut cam = None;
                    for (index, data) in infos.get(&t.topic).into_iter().flatten() {
                        match decode_camera_info(data) {
                            Ok(c) => {
                                cam = Some(c);
                                break;
                            }
                            Err(e) => {
                                problem.get_or_insert_with(|| RosbagError::InMessage { topic: t.topic.clone(), index: *index, source: Box::new(e) }.to_string());
                            }
                        }
                    }
                    let cam = cam.ok_or_else(|| RosbagError::CameraInfo { topic: t.topic.clone(), problem: problem.unwrap_or_else(|| "no message".into()) })?;
                    (cam, t.topic.clone())
                }
                (None, Some(fov)) => {
                    let c = PinholeCamera::from_hfov(fov, width, height).map_err(|e| RosbagError::BadSpec { spec: format!("fov={fov}"), problem: e.to_string() })?;
                    tracing::warn!("{}: no CameraInfo; guessed from fov={fov} deg: fx = fy = {:.1} px, centre ({:.1}, {:.1}), no distortion", spec.path.display(), c.fx, c.cx, c.cy);
                    (c, format!("fov={fov}"))
                }
                (None, None) => {
                    let others: Vec<&str> = topics.iter().filter(|t| is_info(t)).map(|t| t.topic.as_str()).collect();
                    let other = if others.is_empty() { String::new() } else { format!(" (the bag has {})", others.join(", ")) };
                    return Err(RosbagError::NoCamera { image_topic, looked_for: namespace_candidates(&image.topic).join(" or "), other });
                }
            }
        };
        if camera.width != width || camera.height != height {
            return Err(RosbagError::ImageSize { topic: image_topic, width, height, camera_width: camera.width, camera_height: camera.height });
        }
        // Navigation topics.
        let mut notes = Vec::new();
        let mut nav_topics = Vec::new();
        let mut chosen: Vec<(Sensor, MsgType, &BagTopic)> = Vec::new();
        for sensor in Sensor::ALL {
            match sensor.spec_topic(spec) {
                Some("none") => {}
                Some(name) => {
                    let t = find(sensor.option(), name, &|t: &BagTopic| typed(t).is_some_and(|m| sensor.accepts(m)), "topics of that kind")?;
                    let m = typed(t).filter(|&m| sensor.accepts(m)).ok_or_else(|| RosbagError::WrongType { option: sensor.option(), topic: name.to_string(), found: t.schema.clone(), expected: sensor.expected() })?;
                    cdr(t)?;
                    chosen.push((sensor, m, t));
                }
                None => {
                    let c: Vec<&BagTopic> = topics.iter().filter(|t| t.message_encoding == "cdr" && typed(t).is_some_and(|m| sensor.picked_by_type(m))).collect();
                    match c.as_slice() {
                        [] => {}
                        [one] => chosen.push((sensor, typed(one).expect("typed above"), *one)),
                        several => {
                            let names: Vec<&str> = several.iter().map(|t| t.topic.as_str()).collect();
                            let note = format!("{} not used: several topics ({}); name one with {}=/topic", sensor.option(), names.join(", "), sensor.option());
                            tracing::warn!("{}: {note}", spec.path.display());
                            notes.push(note);
                        }
                    }
                }
            }
        }
        let mut rows: Vec<NavRow> = Vec::new();
        let mut pre = duv_core::nav::NavRejections::default();
        for (sensor, _, t) in &chosen {
            let mut last: Option<Timestamp> = None;
            let mut used = 0u64;
            let d = decoded.remove(&t.topic).unwrap_or_default();
            for row in d.rows {
                let ts = row.t_ns.expect("decode_nav stamps every row");
                match last {
                    Some(l) if ts < l => pre.out_of_order += 1,
                    Some(l) if ts == l => pre.duplicate_time += 1,
                    _ => {
                        last = Some(ts);
                        used += 1;
                        rows.push(row);
                    }
                }
            }
            if d.bad > 0 {
                let why = d.first_problem.unwrap_or_default();
                tracing::warn!("{why}");
                notes.push(format!("{}: {} message(s) could not be decoded (first: {why})", t.topic, d.bad));
            }
            nav_topics.push(NavTopic { sensor: sensor.option(), topic: t.topic.clone(), schema: t.schema.clone(), messages: used });
        }
        rows.sort_by_key(|r| r.t_ns);
        // Samples of different sensors at the same stamp share a row.
        let mut merged: Vec<NavRow> = Vec::with_capacity(rows.len());
        for r in rows {
            if let Some(m) = merged.last_mut().filter(|m| m.t_ns == r.t_ns) {
                let free = (m.depth_m.is_none() || r.depth_m.is_none()) && (m.altitude_m.is_none() || r.altitude_m.is_none()) && (m.vel.is_none() || r.vel.is_none()) && (m.q.is_none() || r.q.is_none());
                if free {
                    m.depth_m = m.depth_m.or(r.depth_m);
                    m.altitude_m = m.altitude_m.or(r.altitude_m);
                    m.vel = m.vel.or(r.vel);
                    m.q = m.q.or(r.q);
                    continue;
                }
            }
            merged.push(r);
        }
        let mut nav = judge_nav_rows(merged);
        nav.rejected.out_of_order += pre.out_of_order;
        nav.rejected.duplicate_time += pre.duplicate_time;
        if !nav.is_empty() || nav.rejected.total() > 0 {
            tracing::info!("{}: {} navigation samples ({} rejected: {})", spec.path.display(), nav.len(), nav.rejected.total(), nav.rejected.describe());
        }
        Ok(RosbagSource {
            path: spec.path.clone(),
            files,
            limits,
            topics,
            image_topic,
            compressed,
            camera,
            camera_from,
            nav,
            nav_topics,
            notes,
            next_file: 0,
            reader: None,
            image_index: 0,
            last_t: None,
            frames: 0,
            bad_frames: 0,
            out_of_order_frames: 0,
            last_problem: None,
            max_frames: None,
        })
    }

    /// Stop after `n` frames.
    pub fn with_max_frames(mut self, n: Option<usize>) -> Self {
        self.max_frames = n.map(|n| n as u64);
        self
    }

    /// Every topic of the bag with its schema, encoding and message count.
    pub fn topics(&self) -> &[BagTopic] {
        &self.topics
    }

    pub fn image_topic(&self) -> &str {
        &self.image_topic
    }

    /// Where the camera came from: a CameraInfo topic, `calib=` or `fov=...`.
    pub fn camera_from(&self) -> &str {
        &self.camera_from
    }

    /// The navigation samples (possibly none) and what was rejected.
    pub fn nav(&self) -> &NavTrack {
        &self.nav
    }

    /// The topics the navigation samples came from.
    pub fn nav_topics(&self) -> &[NavTopic] {
        &self.nav_topics
    }

    /// What was noticed on opening (sensors left out, undecodable messages).
    pub fn notes(&self) -> &[String] {
        &self.notes
    }

    /// Frames skipped because they could not be decoded, and the last reason.
    pub fn bad_frames(&self) -> (u64, Option<&str>) {
        (self.bad_frames, self.last_problem.as_deref())
    }

    /// Frames skipped because their stamp did not increase.
    pub fn out_of_order_frames(&self) -> u64 {
        self.out_of_order_frames
    }

    /// The bag's files, in reading order.
    pub fn files(&self) -> &[PathBuf] {
        &self.files
    }
}

impl FrameSource for RosbagSource {
    fn camera(&self) -> &PinholeCamera {
        &self.camera
    }

    fn next_frame(&mut self) -> Result<Option<Frame>, CameraError> {
        if self.max_frames.is_some_and(|m| self.frames >= m) {
            return Ok(None);
        }
        loop {
            if self.reader.is_none() {
                let Some(f) = self.files.get(self.next_file) else { return Ok(None) };
                self.next_file += 1;
                self.reader = Some(SegmentReader::open(f, self.limits).map_err(RosbagError::from)?);
            }
            let r = self.reader.as_mut().expect("opened above");
            let Some(e) = r.next_event() else {
                self.reader = None;
                continue;
            };
            let OwnedEvent::Message { channel_id, data, .. } = e else { continue };
            if r.channel(channel_id).is_none_or(|c| c.topic != self.image_topic) {
                continue;
            }
            let index = self.image_index;
            self.image_index += 1;
            match decode_image_message(&data, self.compressed) {
                Ok((t_ns, image)) => {
                    if image.width() != self.camera.width || image.height() != self.camera.height {
                        let e = RosbagError::ImageSize { topic: self.image_topic.clone(), width: image.width(), height: image.height(), camera_width: self.camera.width, camera_height: self.camera.height };
                        self.skip(index, e);
                        continue;
                    }
                    if self.last_t.is_some_and(|l| t_ns <= l) {
                        self.out_of_order_frames += 1;
                        tracing::warn!("{}, message {index}: stamp {t_ns} does not follow the previous frame's: skipped", self.image_topic);
                        continue;
                    }
                    self.last_t = Some(t_ns);
                    self.frames += 1;
                    return Ok(Some(Frame { t_ns, seq: index, image }));
                }
                Err(e) => self.skip(index, e),
            }
        }
    }

    fn describe(&self) -> String {
        let nav: Vec<String> = self.nav_topics.iter().map(|n| format!("{} {}", n.sensor, n.topic)).collect();
        let nav = if nav.is_empty() { "no navigation topics".to_string() } else { format!("navigation: {}", nav.join(", ")) };
        format!("ROS 2 bag {} ({} file(s), {}, {}x{}, camera from {}; {nav})", self.path.display(), self.files.len(), self.image_topic, self.camera.width, self.camera.height, self.camera_from)
    }
}

impl RosbagSource {
    fn skip(&mut self, index: u64, e: RosbagError) {
        let e = RosbagError::InMessage { topic: self.image_topic.clone(), index, source: Box::new(e) };
        tracing::warn!("{e}: frame skipped");
        self.bad_frames += 1;
        self.last_problem = Some(e.to_string());
    }
}

/// Topics where the CameraInfo of `image_topic` would be: `<ns>/camera_info` for each
/// enclosing namespace, innermost first (`/cam/image_raw/compressed`:
/// `/cam/image_raw/camera_info`, `/cam/camera_info`, `/camera_info`).
fn namespace_candidates(image_topic: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut ns = image_topic;
    while let Some(i) = ns.rfind('/') {
        ns = &ns[..i];
        out.push(format!("{ns}/camera_info"));
        if ns.is_empty() {
            break;
        }
    }
    out
}

/// The bag's MCAP files in reading order.
fn bag_files(path: &Path) -> Result<Vec<PathBuf>, RosbagError> {
    if path.is_file() {
        return Ok(vec![path.to_path_buf()]);
    }
    if !path.is_dir() {
        return Err(RosbagError::NotFound { path: path.to_path_buf() });
    }
    let meta = path.join("metadata.yaml");
    if let Ok(text) = std::fs::read_to_string(&meta) {
        let listed = metadata_files(&text);
        if !listed.is_empty() {
            let mut out = Vec::new();
            for f in listed {
                let p = path.join(&f);
                if !p.is_file() {
                    return Err(RosbagError::MissingFile { path: meta, file: PathBuf::from(f) });
                }
                if p.extension().is_some_and(|e| e == "mcap") {
                    out.push(p);
                }
            }
            if !out.is_empty() {
                return Ok(out);
            }
        }
    }
    let io = |source| RosbagError::Log(crate::LogError::Io { path: path.to_path_buf(), source });
    let mut names: Vec<String> = Vec::new();
    let mut db3 = false;
    for e in std::fs::read_dir(path).map_err(io)? {
        let e = e.map_err(io)?;
        let name = e.file_name().to_string_lossy().to_string();
        if name.ends_with(".mcap") && e.path().is_file() {
            names.push(name);
        } else if name.ends_with(".db3") {
            db3 = true;
        }
    }
    if names.is_empty() {
        let hint = if db3 { "; this is a SQLite bag (.db3): convert it to MCAP (ros2 bag convert)".to_string() } else { String::new() };
        return Err(RosbagError::NoMcap { path: path.to_path_buf(), hint });
    }
    names.sort_by_key(|n| natural_key(n));
    Ok(names.into_iter().map(|n| path.join(n)).collect())
}

/// `name_10.mcap` after `name_9.mcap`: the name with its last run of digits as a number.
fn natural_key(name: &str) -> (String, u64, String) {
    let stem = name.trim_end_matches(".mcap");
    let digits = stem.len() - stem.trim_end_matches(|c: char| c.is_ascii_digit()).len();
    let (head, num) = stem.split_at(stem.len() - digits);
    (head.to_string(), num.parse().unwrap_or(0), name.to_string())
}

/// The `relative_file_paths` of a rosbag2 `metadata.yaml`: the `- name` lines after the key
/// (or an inline `[a, b]` list). Enough YAML for what rosbag2 writes.
fn metadata_files(text: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut lines = text.lines();
    while let Some(l) = lines.next() {
        let t = l.trim();
        let Some(rest) = t.strip_prefix("relative_file_paths:") else { continue };
        let rest = rest.trim();
        let unquote = |s: &str| s.trim().trim_matches(|c| c == '"' || c == '\'').to_string();
        if let Some(inline) = rest.strip_prefix('[') {
            return inline.trim_end_matches(']').split(',').map(unquote).filter(|s| !s.is_empty()).collect();
        }
        for l in lines.by_ref() {
            match l.trim().strip_prefix("- ") {
                Some(item) => out.push(unquote(item)),
                None => break,
            }
        }
        break;
    }
    out
}

/// A reader of one CDR message body (see the module documentation).
pub struct Cdr<'a> {
    /// The message after the 4-byte encapsulation header.
    body: &'a [u8],
    pos: usize,
    little_endian: bool,
}

impl<'a> Cdr<'a> {
    /// Reads the encapsulation header.
    pub fn new(message: &'a [u8]) -> Result<Self, RosbagError> {
        if message.len() < 4 {
            return Err(RosbagError::Truncated { field: "the encapsulation header", offset: 0, needed: 4, len: message.len() });
        }
        let kind = u16::from_be_bytes([message[0], message[1]]);
        let little_endian = match kind {
            0x0000 => false,
            0x0001 => true,
            _ => return Err(RosbagError::Encapsulation { kind }),
        };
        Ok(Cdr { body: &message[4..], pos: 0, little_endian })
    }

    fn take(&mut self, n: usize, align: usize, field: &'static str) -> Result<&'a [u8], RosbagError> {
        let start = self.pos.next_multiple_of(align);
        let end = start.checked_add(n).filter(|&e| e <= self.body.len()).ok_or(RosbagError::Truncated { field, offset: start + 4, needed: n, len: self.body.len() + 4 })?;
        self.pos = end;
        Ok(&self.body[start..end])
    }

    fn array<const N: usize>(&mut self, field: &'static str) -> Result<[u8; N], RosbagError> {
        let mut b: [u8; N] = self.take(N, N, field)?.try_into().expect("N bytes");
        if !self.little_endian {
            b.reverse();
        }
        Ok(b)
    }

    pub fn u8(&mut self, field: &'static str) -> Result<u8, RosbagError> {
        Ok(self.take(1, 1, field)?[0])
    }
    pub fn u32(&mut self, field: &'static str) -> Result<u32, RosbagError> {
        Ok(u32::from_le_bytes(self.array(field)?))
    }
    pub fn i32(&mut self, field: &'static str) -> Result<i32, RosbagError> {
        Ok(i32::from_le_bytes(self.array(field)?))
    }
    pub fn f32(&mut self, field: &'static str) -> Result<f32, RosbagError> {
        Ok(f32::from_le_bytes(self.array(field)?))
    }
    pub fn f64(&mut self, field: &'static str) -> Result<f64, RosbagError> {
        Ok(f64::from_le_bytes(self.array(field)?))
    }
    pub fn f64s<const N: usize>(&mut self, field: &'static str) -> Result<[f64; N], RosbagError> {
        let mut out = [0.0; N];
        for v in &mut out {
            *v = self.f64(field)?;
        }
        Ok(out)
    }
    /// A sequence length, checked against what is left (each element at least `min_bytes`).
    fn len(&mut self, field: &'static str, min_bytes: usize) -> Result<usize, RosbagError> {
        let n = self.u32(field)? as usize;
        let left = self.body.len() - self.pos;
        if n.saturating_mul(min_bytes) > left + 8 {
            return Err(RosbagError::Truncated { field, offset: self.pos + 4, needed: n.saturating_mul(min_bytes), len: self.body.len() + 4 });
        }
        Ok(n)
    }
    /// A `string`: length with its terminating NUL, the bytes, the NUL.
    pub fn string(&mut self, field: &'static str) -> Result<&'a str, RosbagError> {
        let n = self.len(field, 1)?;
        let b = self.take(n, 1, field)?;
        let b = b.strip_suffix(&[0]).unwrap_or(b);
        std::str::from_utf8(b).map_err(|_| RosbagError::BadField { field, problem: "not UTF-8".into() })
    }
    /// A `uint8[]`, borrowed.
    pub fn bytes(&mut self, field: &'static str) -> Result<&'a [u8], RosbagError> {
        let n = self.len(field, 1)?;
        self.take(n, 1, field)
    }
    /// A `float64[]`.
    pub fn f64_seq(&mut self, field: &'static str) -> Result<Vec<f64>, RosbagError> {
        let n = self.len(field, 8)?;
        (0..n).map(|_| self.f64(field)).collect()
    }
    /// A `std_msgs/Header`: the stamp (the frame id is skipped).
    pub fn header(&mut self) -> Result<Timestamp, RosbagError> {
        let sec = self.i32("header.stamp.sec")?;
        let nanosec = self.u32("header.stamp.nanosec")?;
        if nanosec >= 1_000_000_000 {
            return Err(RosbagError::BadField { field: "header.stamp.nanosec", problem: format!("{nanosec} is not below 1e9") });
        }
        self.string("header.frame_id")?;
        Ok(Timestamp::from_ns(sec as i64 * 1_000_000_000 + nanosec as i64))
    }
}

/// Decodes a `sensor_msgs/msg/Image` (or, `compressed`, a `CompressedImage`) into its header
/// stamp and an RGB or grey image.
pub fn decode_image_message(data: &[u8], compressed: bool) -> Result<(Timestamp, FrameImage), RosbagError> {
    let mut c = Cdr::new(data)?;
    let t = c.header()?;
    if compressed {
        let format = c.string("format")?;
        let bytes = c.bytes("data")?;
        let image = if bytes.starts_with(&[0xFF, 0xD8]) {
            crate::schema::decode_jpeg(bytes).map_err(|e| RosbagError::Decode { problem: format!("JPEG: {e}") })?
        } else if bytes.starts_with(&[0x89, b'P', b'N', b'G']) {
            decode_png(bytes)?
        } else {
            return Err(RosbagError::UnknownCompressedFormat { format: format.to_string() });
        };
        return Ok((t, image));
    }
    let height = c.u32("height")? as usize;
    let width = c.u32("width")? as usize;
    let encoding = c.string("encoding")?;
    let big_endian = c.u8("is_bigendian")? != 0;
    let step = c.u32("step")? as usize;
    let data = c.bytes("data")?;
    let layout = |problem: String| RosbagError::BadField { field: "data", problem };
    let enc = encoding.to_ascii_lowercase();
    let bpp = match enc.as_str() {
        "rgb8" | "bgr8" => 3,
        "rgba8" | "bgra8" => 4,
        "mono8" | "8uc1" | "bayer_rggb8" | "bayer_bggr8" | "bayer_gbrg8" | "bayer_grbg8" => 1,
        "mono16" | "16uc1" => 2,
        _ => return Err(RosbagError::UnknownEncoding { encoding: encoding.to_string() }),
    };
    if width < 2 || height < 2 || width > 1 << 15 || height > 1 << 15 {
        return Err(layout(format!("image size {width}x{height}")));
    }
    if step < width * bpp {
        return Err(layout(format!("step {step} is less than a row of {width} {encoding} pixels")));
    }
    let needed = step * (height - 1) + width * bpp;
    if data.len() < needed {
        return Err(layout(format!("{} bytes, {width}x{height} {encoding} with step {step} needs {needed}", data.len())));
    }
    let row = |y: usize| &data[y * step..y * step + width * bpp];
    let image = match enc.as_str() {
        "rgb8" | "bgr8" | "rgba8" | "bgra8" => {
            let mut img = ImageRgb8::new(width, height);
            let swap = enc.starts_with('b');
            for y in 0..height {
                for (o, p) in img.data[y * width * 3..(y + 1) * width * 3].chunks_exact_mut(3).zip(row(y).chunks_exact(bpp)) {
                    o.copy_from_slice(&if swap { [p[2], p[1], p[0]] } else { [p[0], p[1], p[2]] });
                }
            }
            FrameImage::Rgb8(img)
        }
        "mono8" | "8uc1" => {
            let mut img = ImageGray8::new(width, height);
            for y in 0..height {
                img.data[y * width..(y + 1) * width].copy_from_slice(row(y));
            }
            FrameImage::Gray8(img)
        }
        "mono16" | "16uc1" => {
            let mut img = ImageGray8::new(width, height);
            for y in 0..height {
                for (o, p) in img.data[y * width..(y + 1) * width].iter_mut().zip(row(y).chunks_exact(2)) {
                    *o = if big_endian { p[0] } else { p[1] };
                }
            }
            FrameImage::Gray8(img)
        }
        bayer => {
            if !width.is_multiple_of(2) || !height.is_multiple_of(2) {
                return Err(layout(format!("{encoding} needs an even image size, got {width}x{height}")));
            }
            FrameImage::Rgb8(debayer(data, width, height, step, &bayer.as_bytes()[6..10]))
        }
    };
    Ok((t, image))
}

/// Bayer 8-bit to RGB, one colour per 2x2 cell (as the live cameras' `bayer_rg8_to_rgb8`):
/// every pixel of a cell gets the cell's R, the mean of its two G (rounded up) and its B.
/// `pattern`: the cell's colours in row order, e.g. `rggb`.
fn debayer(src: &[u8], width: usize, height: usize, step: usize, pattern: &[u8]) -> ImageRgb8 {
    let mut dst = ImageRgb8::new(width, height);
    let at = |c: u8| -> Vec<usize> { pattern.iter().enumerate().filter(|(_, &p)| p == c).map(|(i, _)| i).collect() };
    let (r, g, b) = (at(b'r')[0], at(b'g'), at(b'b')[0]);
    for cy in 0..height / 2 {
        for cx in 0..width / 2 {
            let px = |k: usize| src[(2 * cy + k / 2) * step + 2 * cx + k % 2];
            let rgb = [px(r), (px(g[0]) as u16 + px(g[1]) as u16).div_ceil(2) as u8, px(b)];
            for k in 0..4 {
                let i = ((2 * cy + k / 2) * width + 2 * cx + k % 2) * 3;
                dst.data[i..i + 3].copy_from_slice(&rgb);
            }
        }
    }
    dst
}

/// A PNG from memory: 8-bit colour or grey (alpha dropped, 16-bit reduced to the high byte).
fn decode_png(bytes: &[u8]) -> Result<FrameImage, RosbagError> {
    let bad = |e: png::DecodingError| RosbagError::Decode { problem: format!("PNG: {e}") };
    let mut decoder = png::Decoder::new(std::io::Cursor::new(bytes));
    decoder.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
    let mut reader = decoder.read_info().map_err(bad)?;
    let size = reader.output_buffer_size().ok_or_else(|| RosbagError::Decode { problem: "PNG: image too large".into() })?;
    let mut buf = vec![0u8; size];
    let info = reader.next_frame(&mut buf).map_err(bad)?;
    buf.truncate(info.buffer_size());
    let (w, h) = (info.width as usize, info.height as usize);
    let channels = match info.color_type {
        png::ColorType::Grayscale => 1,
        png::ColorType::GrayscaleAlpha => 2,
        png::ColorType::Rgb => 3,
        png::ColorType::Rgba => 4,
        other => return Err(RosbagError::Decode { problem: format!("PNG colour type {other:?}") }),
    };
    let short = || RosbagError::Decode { problem: "PNG: fewer pixels than its size".into() };
    Ok(if channels <= 2 {
        let data: Vec<u8> = buf.chunks_exact(channels).map(|p| p[0]).collect();
        FrameImage::Gray8(ImageGray8::from_vec(w, h, data).ok_or_else(short)?)
    } else {
        let data: Vec<u8> = buf.chunks_exact(channels).flat_map(|p| [p[0], p[1], p[2]]).collect();
        FrameImage::Rgb8(ImageRgb8::from_vec(w, h, data).ok_or_else(short)?)
    })
}

/// Decodes a `sensor_msgs/msg/CameraInfo` into a camera (with its plumb_bob distortion).
pub fn decode_camera_info(data: &[u8]) -> Result<PinholeCamera, RosbagError> {
    let mut c = Cdr::new(data)?;
    c.header()?;
    let height = c.u32("height")? as usize;
    let width = c.u32("width")? as usize;
    let model = c.string("distortion_model")?.to_string();
    let d = c.f64_seq("d")?;
    let k: [f64; 9] = c.f64s("k")?;
    let _r: [f64; 9] = c.f64s("r")?;
    let _p: [f64; 12] = c.f64s("p")?;
    let binning_x = c.u32("binning_x")?;
    let binning_y = c.u32("binning_y")?;
    let bad = |field, problem: String| RosbagError::BadField { field, problem };
    if binning_x > 1 || binning_y > 1 {
        return Err(bad("binning_x", format!("binning {binning_x}x{binning_y} is not read")));
    }
    let cam = PinholeCamera::new(k[0], k[4], k[2], k[5], width, height).map_err(|e| bad("k", e.to_string()))?;
    let coeff = |i: usize| d.get(i).copied().unwrap_or(0.0);
    let radtan = match model.as_str() {
        _ if d.iter().all(|&v| v == 0.0) => None,
        "plumb_bob" if d.len() <= 5 => Some(RadTan { k1: coeff(0), k2: coeff(1), p1: coeff(2), p2: coeff(3), k3: coeff(4) }),
        "rational_polynomial" if d.iter().skip(5).all(|&v| v == 0.0) => Some(RadTan { k1: coeff(0), k2: coeff(1), p1: coeff(2), p2: coeff(3), k3: coeff(4) }),
        "rational_polynomial" => return Err(bad("d", format!("rational_polynomial with k4..k6 {:?} is not modelled (only k1 k2 p1 p2 k3)", &d[5..d.len().min(8)]))),
        other => return Err(bad("distortion_model", format!("{other:?} with {} coefficients is not modelled (plumb_bob, rational_polynomial)", d.len()))),
    };
    match radtan {
        Some(r) => cam.with_distortion(r).map_err(|e| bad("d", e.to_string())),
        None => Ok(cam),
    }
}

/// Decodes one navigation message into a row (`None`: nothing to take, e.g. an IMU without
/// orientation).
fn decode_nav(data: &[u8], m: MsgType, spec: &RosbagSpec) -> Result<Option<NavRow>, RosbagError> {
    let mut c = Cdr::new(data)?;
    let t = c.header()?;
    let mut row = NavRow { t_ns: Some(t), ..Default::default() };
    let vec3 = |c: &mut Cdr<'_>, f: &'static str| -> Result<[f64; 3], RosbagError> { c.f64s::<3>(f) };
    match m {
        MsgType::FluidPressure => {
            let p = c.f64("fluid_pressure")?;
            row.depth_m = Some((p - spec.surface_pressure_pa) / (spec.water_density_kg_m3 * GRAVITY_MPS2));
        }
        MsgType::Odometry | MsgType::PoseWithCovarianceStamped | MsgType::PoseStamped => {
            if m == MsgType::Odometry {
                c.string("child_frame_id")?;
            }
            let p = vec3(&mut c, "pose.position")?;
            row.depth_m = Some(-p[2]);
        }
        MsgType::Range => {
            c.u8("radiation_type")?;
            let _fov = c.f32("field_of_view")?;
            let _min = c.f32("min_range")?;
            let _max = c.f32("max_range")?;
            row.altitude_m = Some(c.f32("range")? as f64);
        }
        MsgType::TwistStamped | MsgType::TwistWithCovarianceStamped => row.vel = Some(vec3(&mut c, "twist.linear")?),
        MsgType::Imu => {
            let q: [f64; 4] = c.f64s("orientation")?;
            let cov: [f64; 9] = c.f64s("orientation_covariance")?;
            if cov[0] == -1.0 {
                return Ok(None);
            }
            row.q = Some(q);
        }
        MsgType::Image | MsgType::CompressedImage | MsgType::CameraInfo => return Ok(None),
    }
    Ok(Some(row))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A CDR writer of either byte order, for the tests.
    struct W {
        b: Vec<u8>,
        le: bool,
    }
    impl W {
        fn new(le: bool) -> Self {
            W { b: vec![0, le as u8, 0, 0], le }
        }
        fn pad(&mut self, a: usize) {
            while !(self.b.len() - 4).is_multiple_of(a) {
                self.b.push(0);
            }
        }
        fn raw(&mut self, le: &[u8]) {
            self.pad(le.len());
            if self.le {
                self.b.extend_from_slice(le);
            } else {
                self.b.extend(le.iter().rev());
            }
        }
        fn u32(&mut self, v: u32) {
            self.raw(&v.to_le_bytes());
        }
        fn f64(&mut self, v: f64) {
            self.raw(&v.to_le_bytes());
        }
        fn string(&mut self, s: &str) {
            self.u32(s.len() as u32 + 1);
            self.b.extend_from_slice(s.as_bytes());
            self.b.push(0);
        }
        fn header(&mut self, sec: i32, ns: u32) {
            self.raw(&sec.to_le_bytes());
            self.u32(ns);
            self.string("cam");
        }
    }

    fn image(le: bool, encoding: &str, w: u32, h: u32, step: u32, data: &[u8]) -> Vec<u8> {
        let mut m = W::new(le);
        m.header(12, 345);
        m.u32(h);
        m.u32(w);
        m.string(encoding);
        m.b.push(u8::from(!le));
        m.u32(step);
        m.u32(data.len() as u32);
        m.b.extend_from_slice(data);
        m.b
    }

    #[test]
    fn both_byte_orders_and_alignment() {
        for le in [true, false] {
            // An IMU: header (frame id "cam": 4+4+4+4 bytes), then f64 aligned to 8.
            let mut m = W::new(le);
            m.header(-2, 999_999_999);
            for v in [0.1, -0.2, 0.3, 0.9] {
                m.f64(v);
            }
            for _ in 0..9 {
                m.f64(0.0);
            }
            assert_eq!(m.b.len(), 4 + 16 + 13 * 8, "header ends at 16: no padding before the f64s");
            let spec = RosbagSpec::parse("x").unwrap();
            let row = decode_nav(&m.b, MsgType::Imu, &spec).unwrap().unwrap();
            assert_eq!(row.t_ns, Some(Timestamp::from_ns(-1_000_000_001)));
            assert_eq!(row.q, Some([0.1, -0.2, 0.3, 0.9]));
            // Range: u8 then f32s aligned to 4.
            let mut m = W::new(le);
            m.header(5, 0);
            m.b.push(1);
            for v in [0.5f32, 0.1, 30.0, 2.25] {
                m.raw(&v.to_le_bytes());
            }
            let row = decode_nav(&m.b, MsgType::Range, &spec).unwrap().unwrap();
            assert_eq!(row.altitude_m, Some(2.25));
            // A frame id of 5 bytes + NUL: the f64 after it is padded to 8.
            let mut m = W::new(le);
            m.raw(&1i32.to_le_bytes());
            m.u32(0);
            m.string("depth");
            m.f64(101_325.0 + 1025.0 * GRAVITY_MPS2 * 10.0);
            assert_eq!(m.b.len(), 4 + 8 + 4 + 6 + 6 + 8, "18 bytes of header padded to 24");
            let row = decode_nav(&m.b, MsgType::FluidPressure, &spec).unwrap().unwrap();
            assert!((row.depth_m.unwrap() - 10.0).abs() < 1e-12, "{row:?}");
            // Images of every byte order, bgr8 with padding in the rows.
            let data = [10, 20, 30, 40, 50, 60, 0, 0, 1, 2, 3, 4, 5, 6, 0, 0];
            let (t, img) = decode_image_message(&image(le, "bgr8", 2, 2, 8, &data), false).unwrap();
            assert_eq!(t, Timestamp::from_ns(12_000_000_345));
            let FrameImage::Rgb8(img) = img else { panic!() };
            assert_eq!(img.data, [30, 20, 10, 60, 50, 40, 3, 2, 1, 6, 5, 4]);
            // mono16 keeps its high byte in either byte order.
            let data: Vec<u8> = [0x1234u16, 0xABCD, 0x0F00, 0xFF01].iter().flat_map(|v| if le { v.to_le_bytes() } else { v.to_be_bytes() }).collect();
            let (_, img) = decode_image_message(&image(le, "mono16", 2, 2, 4, &data), false).unwrap();
            assert_eq!(img, FrameImage::Gray8(ImageGray8::from_vec(2, 2, vec![0x12, 0xAB, 0x0F, 0xFF]).unwrap()));
        }
    }

    #[test]
    fn bayer_patterns_give_the_cell_colour() {
        // One 2x2 cell of each pattern holding R = 200, G = 100 and 51, B = 10.
        for (pattern, cell) in [("rggb", [200, 100, 51, 10]), ("bggr", [10, 100, 51, 200]), ("gbrg", [100, 10, 200, 51]), ("grbg", [100, 200, 10, 51])] {
            let (_, img) = decode_image_message(&image(true, &format!("bayer_{pattern}8"), 2, 2, 2, &cell), false).unwrap();
            assert_eq!(img, FrameImage::Rgb8(ImageRgb8::from_vec(2, 2, [200, 76, 10].repeat(4)).unwrap()), "{pattern}");
        }
    }

    #[test]
    fn bad_messages_are_errors_naming_the_field() {
        let m = image(true, "rgb8", 4, 4, 12, &[0; 48]);
        for cut in [2, 10, 30, m.len() - 1] {
            let e = decode_image_message(&m[..cut], false).unwrap_err();
            assert!(matches!(e, RosbagError::Truncated { .. }), "{cut}: {e}");
        }
        let e = decode_image_message(&m[..m.len() - 1], false).unwrap_err();
        assert_eq!(e.to_string(), "the message ends inside data (needs 48 bytes at offset 48, has 95)");
        let e = decode_image_message(&image(true, "yuv422", 4, 4, 8, &[0; 32]), false).unwrap_err();
        assert!(e.to_string().starts_with("image encoding \"yuv422\" is not read"), "{e}");
        let e = decode_image_message(&image(true, "rgb8", 4, 4, 12, &[0; 40]), false).unwrap_err();
        assert_eq!(e.to_string(), "data: 40 bytes, 4x4 rgb8 with step 12 needs 48");
        let mut pl = m.clone();
        pl[1] = 3;
        assert_eq!(decode_image_message(&pl, false).unwrap_err().to_string(), "CDR encapsulation 0x0003 is not plain CDR (0x0000 big-endian, 0x0001 little-endian)");
        // A sequence length far beyond the message is refused before anything is allocated.
        let mut huge = W::new(true);
        huge.header(0, 0);
        huge.u32(u32::MAX);
        assert!(matches!(decode_camera_info(&huge.b), Err(RosbagError::Truncated { .. })));
    }

    #[test]
    fn spec_options_and_file_order() {
        let s = RosbagSpec::parse("bags/dive,image=/cam/image_raw,depth=none,water_density=1000,fov=80").unwrap();
        assert_eq!((s.image.as_deref(), s.depth.as_deref(), s.water_density_kg_m3, s.fov_deg), (Some("/cam/image_raw"), Some("none"), 1000.0, Some(80.0)));
        assert_eq!(s.surface_pressure_pa, DEFAULT_SURFACE_PRESSURE_PA);
        for (bad, needle) in [("d,image=cam", "starts with /"), ("d,speed=2", "unknown option \"speed\""), ("d,fov=0", "fov"), ("d,imu=/a,imu=/b", "twice"), ("", "no bag"), ("d,image", "KEY=VALUE")] {
            let e = RosbagSpec::parse(bad).unwrap_err().to_string();
            assert!(e.contains(needle), "{bad}: {e}");
        }
        assert_eq!(metadata_files("rosbag2_bagfile_information:\n  relative_file_paths:\n    - dive_0.mcap\n    - dive_1.mcap\n  starting_time:\n"), ["dive_0.mcap", "dive_1.mcap"]);
        assert_eq!(metadata_files("  relative_file_paths: [a_0.mcap, 'a_1.mcap']\n"), ["a_0.mcap", "a_1.mcap"]);
        let mut names = vec!["d_10.mcap", "d_2.mcap", "d_0.mcap"];
        names.sort_by_key(|n| natural_key(n));
        assert_eq!(names, ["d_0.mcap", "d_2.mcap", "d_10.mcap"]);
        assert_eq!(namespace_candidates("/cam/image_raw/compressed"), ["/cam/image_raw/camera_info", "/cam/camera_info", "/camera_info"]);
    }
}
