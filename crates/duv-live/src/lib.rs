//! The live view over the tether: a Foxglove WebSocket server (the `foxglove` crate's, on its own
//! tokio runtime) that streams what the vehicle is doing while it does it.
//!
//! | topic | schema | what |
//! |---|---|---|
//! | `/slam/pose` | `foxglove.PoseInFrame` | every tracked frame's `world_from_cam` |
//! | `/tf` | `foxglove.FrameTransform` | the same as `world` -> `camera` |
//! | `/slam/state` | JSON `duv.TrackingState` | the tracking state, as the log holds it |
//! | `/camera/image` | `foxglove.CompressedImage` (JPEG) | the input, downscaled, at the board's `live.image_hz` |
//! | `/slam/keyframes` | `foxglove.PosesInFrame` | the poses of the keyframes handed to mapping |
//! | `/map/gaussians` | `foxglove.PointCloud` | Gaussian centres (x, y, z, rgba), at map checkpoints |
//!
//! [`LiveServer::publish`] takes one [`LiveItem`] at a time on the caller's thread (the
//! pipeline's `live` thread, fed through a bounded queue the tracking thread never waits on),
//! encodes it into buffers it reuses, and hands the bytes to the server if the bandwidth
//! [`budget`] allows; what it drops is counted per class in [`LiveStats`]. Nothing is encoded
//! for a topic no client subscribes to.
//!
//! The stages never meet here: what arrives is plain `duv-core` types.

pub mod budget;
mod image;

pub use budget::{Budget, Class};

use duv_core::config::board::LiveSettings;
use duv_core::jpeg::{JpegEncoder, JpegError};
pub use duv_core::PoseRecord;
use duv_core::{Frame, Se3, Timestamp};
use foxglove::messages as fg;
use foxglove::websocket::ServerListener;
use foxglove::{Context, Encode, RawChannel, WebSocketServer, WebSocketServerHandle};
use serde::Serialize;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Frame id of the world (the tracker's map frame), as in the log.
pub const WORLD_FRAME: &str = "world";
/// Frame id of the camera, as in the log.
pub const CAMERA_FRAME: &str = "camera";

/// The topics, in [`Topic`] order.
pub const TOPICS: [&str; 6] = ["/slam/pose", "/tf", "/slam/state", "/camera/image", "/slam/keyframes", "/map/gaussians"];

/// Bytes each message costs besides its body: the message-data header (opcode, subscription
/// id, log time) and the WebSocket frame header.
pub const MESSAGE_OVERHEAD_BYTES: usize = 1 + 4 + 8 + 4;

/// How long [`LiveServer::stop`] lets the server close its connections before it leaves them.
pub const STOP_GRACE: Duration = Duration::from_millis(300);

/// The live view's channels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Topic {
    Pose,
    Transform,
    State,
    Camera,
    Keyframes,
    Gaussians,
}

impl Topic {
    pub const ALL: [Topic; 6] = [Topic::Pose, Topic::Transform, Topic::State, Topic::Camera, Topic::Keyframes, Topic::Gaussians];

    pub fn name(self) -> &'static str {
        TOPICS[self as usize]
    }
}

/// Errors of the live view.
#[derive(Debug, thiserror::Error)]
pub enum LiveError {
    /// `live.bind` (or `--live-view ADDR`) is not `HOST:PORT`.
    #[error("live view: bind address {bind:?} is not HOST:PORT")]
    BadBind { bind: String },
    /// The server could not start (the port is taken, the address is not this machine's).
    #[error("live view: cannot serve on {bind}: {problem}")]
    Start { bind: String, problem: String },
    #[error("live view: channel {topic}: {problem}")]
    Channel { topic: &'static str, problem: String },
    #[error("live view: {0}")]
    Jpeg(#[from] JpegError),
}

/// What the pipeline hands to the live view.
#[derive(Clone, Debug)]
pub enum LiveItem {
    Pose(PoseRecord),
    /// An input frame (shared with tracking, not copied); downscaled and compressed here.
    Frame(Arc<Frame>),
    /// A keyframe handed to mapping: its pose joins `/slam/keyframes`.
    Keyframe { id: u64, t_ns: Timestamp, world_from_cam: Se3 },
    /// The map's Gaussian centres (world frame) and their colours (RGB, one per centre, or empty:
    /// coloured by height).
    Cloud { t_ns: Timestamp, centres_in_world: Vec<[f32; 3]>, colours: Vec<[u8; 3]> },
}

impl LiveItem {
    pub fn class(&self) -> Class {
        match self {
            LiveItem::Pose(_) => Class::Pose,
            LiveItem::Frame(_) => Class::Camera,
            LiveItem::Keyframe { .. } => Class::Keyframes,
            LiveItem::Cloud { .. } => Class::Cloud,
        }
    }
}

/// Counts per [`Class`] (pose, keyframes, cloud, camera).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct PerClass {
    pub pose: u64,
    pub keyframes: u64,
    pub cloud: u64,
    pub camera: u64,
}

impl PerClass {
    fn add(&mut self, class: Class, n: u64) {
        match class {
            Class::Pose => self.pose += n,
            Class::Keyframes => self.keyframes += n,
            Class::Cloud => self.cloud += n,
            Class::Camera => self.camera += n,
        }
    }
    pub fn get(&self, class: Class) -> u64 {
        match class {
            Class::Pose => self.pose,
            Class::Keyframes => self.keyframes,
            Class::Cloud => self.cloud,
            Class::Camera => self.camera,
        }
    }
    pub fn total(&self) -> u64 {
        self.pose + self.keyframes + self.cloud + self.camera
    }
}

/// What the live view did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct LiveStats {
    /// Messages handed to the server (a pose is three: pose, transform, state).
    pub messages_sent: u64,
    /// Their bytes, bodies and [`MESSAGE_OVERHEAD_BYTES`], times the clients they went to.
    pub bytes_sent: u64,
    /// Items sent, per class (for keyframes: lists of keyframe poses).
    pub sent: PerClass,
    /// Items the bandwidth budget dropped, per class (for keyframes: lists refused when a
    /// keyframe arrived; its pose goes with the next list).
    pub dropped_budget: PerClass,
    /// Items that arrived while no client watched their topic (nothing encoded).
    pub unwatched: u64,
    /// Clients connected now, and the most at once.
    pub clients: usize,
    pub clients_max: usize,
}

/// Counts connections (the server's listener).
#[derive(Default)]
struct ClientCount {
    now: AtomicUsize,
    max: AtomicUsize,
}

impl ServerListener for ClientCount {
    fn on_client_connect(&self) {
        let n = self.now.fetch_add(1, Ordering::Relaxed) + 1;
        self.max.fetch_max(n, Ordering::Relaxed);
    }
    fn on_client_disconnect(&self) {
        let _ = self.now.fetch_update(Ordering::Relaxed, Ordering::Relaxed, |n| Some(n.saturating_sub(1)));
    }
}

/// Foxglove time of `t_ns` (negative times clamp to 0).
fn fg_time(t_ns: Timestamp) -> fg::Timestamp {
    let ns = t_ns.t_ns().max(0) as u64;
    fg::Timestamp::new((ns / 1_000_000_000).min(u32::MAX as u64) as u32, (ns % 1_000_000_000) as u32)
}

fn fg_pose(p: &Se3) -> fg::Pose {
    let t = p.translation.vector;
    let q = p.rotation.quaternion();
    fg::Pose { position: Some(fg::Vector3 { x: t.x, y: t.y, z: t.z }), orientation: Some(fg::Quaternion { x: q.i, y: q.j, z: q.k, w: q.w }) }
}

/// The server, its channels, and the buffers and message templates reused from item to item.
pub struct LiveServer {
    handle: Option<WebSocketServerHandle>,
    addr: SocketAddr,
    /// Owns the channels (kept alive with the server).
    _context: Arc<Context>,
    channels: Vec<Arc<RawChannel>>,
    clients: Arc<ClientCount>,
    budget: Budget,
    settings: LiveSettings,
    jpeg: JpegEncoder,
    body: [Vec<u8>; 3],
    jpeg_out: Vec<u8>,
    small: Vec<u8>,
    cloud: Vec<u8>,
    pose_tpl: fg::PoseInFrame,
    tf_tpl: fg::FrameTransform,
    image_tpl: fg::CompressedImage,
    keyframes: fg::PosesInFrame,
    /// Keyframes whose pose joined the list since it last went.
    keyframes_pending: u64,
    stats: LiveStats,
}

impl LiveServer {
    /// Starts the server on `settings.bind` (port 0: any free port, see
    /// [`LiveServer::local_addr`]) with the channels of [`Topic::ALL`].
    pub fn start(settings: &LiveSettings) -> Result<Self, LiveError> {
        let bind: SocketAddr = settings.bind.parse().map_err(|_| LiveError::BadBind { bind: settings.bind.clone() })?;
        let context = Context::new();
        let mut channels = Vec::with_capacity(Topic::ALL.len());
        for topic in Topic::ALL {
            let (schema, encoding) = match topic {
                Topic::Pose => (fg::PoseInFrame::get_schema(), fg::PoseInFrame::get_message_encoding()),
                Topic::Transform => (fg::FrameTransform::get_schema(), fg::FrameTransform::get_message_encoding()),
                Topic::State => (Some(foxglove::Schema::new("duv.TrackingState", "jsonschema", duv_core::pose::TRACKING_STATE_SCHEMA.as_bytes())), "json".to_string()),
                Topic::Camera => (fg::CompressedImage::get_schema(), fg::CompressedImage::get_message_encoding()),
                Topic::Keyframes => (fg::PosesInFrame::get_schema(), fg::PosesInFrame::get_message_encoding()),
                Topic::Gaussians => (fg::PointCloud::get_schema(), fg::PointCloud::get_message_encoding()),
            };
            let channel = context
                .channel_builder(topic.name())
                .schema(schema)
                .message_encoding(encoding)
                .build_raw()
                .map_err(|e| LiveError::Channel { topic: topic.name(), problem: e.to_string() })?;
            channels.push(channel);
        }
        let clients = Arc::new(ClientCount::default());
        let handle = WebSocketServer::new()
            .context(&context)
            .name("duv-slam")
            .bind(bind.ip().to_string(), bind.port())
            .listener(clients.clone())
            .message_backlog_size(settings.queue as usize * 4)
            .start_blocking()
            .map_err(|e| LiveError::Start { bind: settings.bind.clone(), problem: e.to_string() })?;
        let addr = SocketAddr::new(bind.ip(), handle.port());
        tracing::info!(%addr, "live view serving");
        Ok(LiveServer {
            handle: Some(handle),
            addr,
            _context: context,
            channels,
            clients,
            budget: Budget::new(settings.max_kb_per_s as u64 * 1024),
            settings: settings.clone(),
            jpeg: JpegEncoder::new(settings.jpeg_quality)?,
            body: [Vec::with_capacity(256), Vec::with_capacity(256), Vec::with_capacity(512)],
            jpeg_out: Vec::new(),
            small: Vec::new(),
            cloud: Vec::new(),
            pose_tpl: fg::PoseInFrame { frame_id: WORLD_FRAME.into(), ..Default::default() },
            tf_tpl: fg::FrameTransform { parent_frame_id: WORLD_FRAME.into(), child_frame_id: CAMERA_FRAME.into(), ..Default::default() },
            image_tpl: fg::CompressedImage { frame_id: CAMERA_FRAME.into(), format: "jpeg".into(), ..Default::default() },
            keyframes: fg::PosesInFrame { frame_id: WORLD_FRAME.into(), ..Default::default() },
            keyframes_pending: 0,
            stats: LiveStats::default(),
        })
    }

    /// The address the server listens on (the port it was given when `bind` asked for 0).
    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }

    /// Clients connected now.
    pub fn clients(&self) -> usize {
        self.clients.now.load(Ordering::Relaxed)
    }

    /// Whether some client subscribes to `topic`.
    pub fn watched(&self, topic: Topic) -> bool {
        self.channels[topic as usize].has_sinks()
    }

    pub fn budget(&self) -> &Budget {
        &self.budget
    }

    pub fn stats(&self) -> LiveStats {
        LiveStats { clients: self.clients(), clients_max: self.clients.max.load(Ordering::Relaxed), ..self.stats }
    }

    /// Publishes `item` now.
    pub fn publish(&mut self, item: &LiveItem) {
        self.publish_at(item, Instant::now());
    }

    /// Publishes `item` with the budget at `now`: encoded and sent, or dropped and counted.
    pub fn publish_at(&mut self, item: &LiveItem, now: Instant) {
        let class = item.class();
        match item {
            LiveItem::Pose(p) => {
                if !(self.watched(Topic::Pose) || self.watched(Topic::Transform) || self.watched(Topic::State)) {
                    self.stats.unwatched += 1;
                    return;
                }
                self.encode_pose(p);
                let bytes: usize = self.body.iter().map(|b| b.len() + MESSAGE_OVERHEAD_BYTES).sum();
                if self.spend(class, bytes, now) {
                    for (i, topic) in [Topic::Pose, Topic::Transform, Topic::State].into_iter().enumerate() {
                        self.send(topic, i);
                    }
                    self.stats.sent.add(class, 1);
                }
            }
            LiveItem::Frame(frame) => {
                if !self.watched(Topic::Camera) {
                    self.stats.unwatched += 1;
                    return;
                }
                // Not even a small frame would go: drop before the work of encoding.
                if !self.budget.may_send(class, now) {
                    self.stats.dropped_budget.add(class, 1);
                    return;
                }
                if let Err(e) = self.encode_frame(frame) {
                    tracing::warn!("live camera frame {} not encoded: {e}", frame.seq);
                    return;
                }
                if self.spend(class, self.body[0].len() + MESSAGE_OVERHEAD_BYTES, now) {
                    self.send(Topic::Camera, 0);
                    self.stats.sent.add(class, 1);
                }
            }
            LiveItem::Keyframe { world_from_cam, t_ns, .. } => {
                self.keyframes.poses.push(fg_pose(world_from_cam));
                self.keyframes.timestamp = Some(fg_time(*t_ns));
                self.keyframes_pending += 1;
                self.flush_keyframes(now, true);
            }
            LiveItem::Cloud { t_ns, centres_in_world, colours } => {
                if !self.watched(Topic::Gaussians) {
                    self.stats.unwatched += 1;
                    return;
                }
                self.encode_cloud(*t_ns, centres_in_world, colours);
                if self.spend(class, self.body[0].len() + MESSAGE_OVERHEAD_BYTES, now) {
                    self.send(Topic::Gaussians, 0);
                    self.stats.sent.add(class, 1);
                }
            }
        }
        // A keyframe list the budget held back goes with a later item.
        if self.keyframes_pending > 0 && class != Class::Keyframes && self.budget.may_send(Class::Keyframes, now) {
            self.flush_keyframes(now, false);
        }
    }

    /// Stops the server: its connections get [`STOP_GRACE`] to close, then are left.
    pub fn stop(mut self) -> LiveStats {
        let stats = self.stats();
        if let Some(handle) = self.handle.take() {
            let shutdown = handle.stop();
            let waiter = std::thread::Builder::new().name("live-stop".into()).spawn(move || shutdown.wait_blocking());
            if let Ok(waiter) = waiter {
                let t0 = Instant::now();
                while !waiter.is_finished() && t0.elapsed() < STOP_GRACE {
                    std::thread::sleep(Duration::from_millis(5));
                }
            }
        }
        stats
    }

    /// Sends the keyframe list (every keyframe so far) if the budget allows. A list the budget
    /// refuses is counted once (`count_drop`, when a keyframe arrives), and goes later, with a
    /// later item, holding the keyframes that came meanwhile.
    fn flush_keyframes(&mut self, now: Instant, count_drop: bool) {
        if !self.watched(Topic::Keyframes) {
            self.stats.unwatched += std::mem::take(&mut self.keyframes_pending);
            return;
        }
        encode_into(&self.keyframes, &mut self.body[0]);
        let class = Class::Keyframes;
        let bytes = self.body[0].len() + MESSAGE_OVERHEAD_BYTES;
        if self.budget.try_spend(class, bytes * self.clients().max(1), now) {
            self.account(bytes);
            self.send(Topic::Keyframes, 0);
            self.stats.sent.add(class, 1);
            self.keyframes_pending = 0;
        } else if count_drop {
            self.stats.dropped_budget.add(class, 1);
        }
    }

    /// Charges `bytes` (per client) of `class` to the budget; counts a drop when it refuses.
    fn spend(&mut self, class: Class, bytes: usize, now: Instant) -> bool {
        if self.budget.try_spend(class, bytes * self.clients().max(1), now) {
            self.account(bytes);
            true
        } else {
            self.stats.dropped_budget.add(class, 1);
            false
        }
    }

    fn account(&mut self, bytes: usize) {
        self.stats.bytes_sent += (bytes * self.clients().max(1)) as u64;
    }

    fn send(&mut self, topic: Topic, body: usize) {
        self.channels[topic as usize].log(&self.body[body]);
        self.stats.messages_sent += 1;
    }

    fn encode_pose(&mut self, p: &PoseRecord) {
        let stamp = Some(fg_time(p.t_ns));
        self.pose_tpl.timestamp = stamp;
        self.pose_tpl.pose = Some(fg_pose(&p.world_from_cam));
        encode_into(&self.pose_tpl, &mut self.body[0]);
        let t = p.world_from_cam.translation.vector;
        let q = p.world_from_cam.rotation.quaternion();
        self.tf_tpl.timestamp = stamp;
        self.tf_tpl.translation = Some(fg::Vector3 { x: t.x, y: t.y, z: t.z });
        self.tf_tpl.rotation = Some(fg::Quaternion { x: q.i, y: q.j, z: q.k, w: q.w });
        encode_into(&self.tf_tpl, &mut self.body[1]);
        let state = p.state_record();
        self.body[2].clear();
        if let Err(e) = serde_json::to_writer(&mut self.body[2], &state) {
            tracing::warn!("live state of frame {} not encoded: {e}", p.seq);
        }
    }

    fn encode_frame(&mut self, frame: &Frame) -> Result<(), JpegError> {
        let (w, h) = image::live_size(frame.image.width(), frame.image.height(), self.settings.image_scale, self.settings.image_max_width as usize);
        let channels = image::downscale(&frame.image, w, h, &mut self.small);
        self.jpeg.encode(&self.small, w, h, channels, &mut self.jpeg_out)?;
        self.image_tpl.timestamp = Some(fg_time(frame.t_ns));
        encode_into(&self.image_tpl, &mut self.body[0]);
        // `data` (field 2) appended from the JPEG buffer, without copying it into the message.
        append_bytes_field(2, &self.jpeg_out, &mut self.body[0]);
        Ok(())
    }

    /// A `foxglove.PointCloud` of at most `cloud_max_points` centres (and at most a quarter of
    /// the budget's bucket), evenly subsampled: x, y, z as f32, then red, green, blue, alpha as u8.
    fn encode_cloud(&mut self, t_ns: Timestamp, centres: &[[f32; 3]], colours: &[[u8; 3]]) {
        const STRIDE: usize = 16;
        // At most the gap between the cloud's reserve and the camera's: a cloud never needs a
        // fuller bucket than a camera frame does, so clouds go before the camera as it fills.
        let gap = (Class::Camera.reserve() - Class::Cloud.reserve()) * self.budget.capacity_bytes();
        let fit = (gap as usize / self.clients().max(1)).saturating_sub(256) / STRIDE;
        let keep = centres.len().min(self.settings.cloud_max_points as usize).min(fit.max(1));
        let step = centres.len() as f64 / keep.max(1) as f64;
        let (z_lo, z_hi) = centres.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), c| (lo.min(c[2]), hi.max(c[2])));
        self.cloud.clear();
        for k in 0..keep {
            let i = ((k as f64 * step) as usize).min(centres.len() - 1);
            let c = centres[i];
            for v in c {
                self.cloud.extend_from_slice(&v.to_le_bytes());
            }
            let rgb = match colours.get(i) {
                Some(rgb) if colours.len() == centres.len() => *rgb,
                _ => image::height_colour(c[2], z_lo, z_hi),
            };
            self.cloud.extend_from_slice(&[rgb[0], rgb[1], rgb[2], 255]);
        }
        let field = |name: &str, offset: u32, t: fg::packed_element_field::NumericType| fg::PackedElementField { name: name.into(), offset, r#type: t as i32 };
        use fg::packed_element_field::NumericType::{Float32, Uint8};
        let msg = fg::PointCloud {
            timestamp: Some(fg_time(t_ns)),
            frame_id: WORLD_FRAME.into(),
            pose: Some(fg_pose(&Se3::identity())),
            point_stride: STRIDE as u32,
            fields: vec![field("x", 0, Float32), field("y", 4, Float32), field("z", 8, Float32), field("red", 12, Uint8), field("green", 13, Uint8), field("blue", 14, Uint8), field("alpha", 15, Uint8)],
            data: Default::default(),
        };
        encode_into(&msg, &mut self.body[0]);
        append_bytes_field(6, &self.cloud, &mut self.body[0]);
    }
}

impl Drop for LiveServer {
    fn drop(&mut self) {
        if let Some(handle) = self.handle.take() {
            // Connections are cut at once (a stop that waits is `stop`).
            drop(handle.stop());
        }
    }
}

fn encode_into<T: Encode>(msg: &T, out: &mut Vec<u8>) {
    out.clear();
    // Encoding into a Vec cannot run out of room; the messages have no required fields.
    let _ = msg.encode(out);
}

/// Appends protobuf field `field` (length delimited) holding `bytes` to `out`.
fn append_bytes_field(field: u32, bytes: &[u8], out: &mut Vec<u8>) {
    out.push(((field << 3) | 2) as u8);
    let mut v = bytes.len() as u64;
    while v >= 0x80 {
        out.push((v as u8 & 0x7f) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
    out.extend_from_slice(bytes);
}
