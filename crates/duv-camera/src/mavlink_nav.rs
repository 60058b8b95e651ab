//! The vehicle's navigation sensors, live, from its autopilot over MAVLink on UDP (ArduSub on a
//! BlueROV2 and most research vehicles; `--nav mavlink:udpin:0.0.0.0:14550`).
//!
//! Messages read (the `ardupilotmega` dialect of the `mavlink` crate, which includes `common`):
//! - depth: `SCALED_PRESSURE2` (ArduSub's external pressure sensor, e.g. a Bar30), else
//!   `SCALED_PRESSURE`, else `GLOBAL_POSITION_INT.relative_alt`, else `VFR_HUD.alt` (ArduSub
//!   reports depth as a negative altitude in both); `depth=` picks one. Pressure becomes depth
//!   through `surface_pa=` (default 101325 Pa) and `density=` (default 1025 kg/m³, sea water;
//!   997 for fresh water) with g = 9.80665 m/s²;
//! - attitude: `ATTITUDE_QUATERNION`, else `ATTITUDE` (body FRD to NED; the heading may drift,
//!   the fusion uses gravity only), turned into the camera's rotation through the board's
//!   `[nav] camera_rpy_deg` mounting;
//! - altitude: `DISTANCE_SENSOR` facing down (`MAV_SENSOR_ROTATION_PITCH_270`: echo sounders
//!   and the DVL's bottom lock) and `RANGEFINDER`;
//! - DVL velocity: `VISION_POSITION_DELTA` as the Water Linked DVL driver sends it (the body-frame
//!   position change over `time_delta_usec`; samples with `confidence` below `min_confidence=`,
//!   default 50 %, are dropped), turned into the camera frame.
//!
//! Samples are stamped when they arrive, on the run's clock ([`NavReceiver::finish`] moves them
//! onto the frames' clock); the autopilot's boot clock is not used. Only the rotation between the
//! body and the camera is applied: the sensors' lever arms are taken as zero.
//!
//! The socket and the datagram parsing are ours (std's `UdpSocket` with a read timeout, so the
//! receiver stops when the run does); the `mavlink` crate decodes and checks each frame.

use duv_core::nav::{validate_samples, NavSample, NavTrack};
use duv_core::Timestamp;
use mavlink::dialects::ardupilotmega::{MavMessage, MavSensorOrientation};
use mavlink::MavlinkReader;
use nalgebra::{UnitQuaternion, Vector3};
use std::io::Read;
use std::net::{SocketAddr, UdpSocket};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Standard gravity, m/s².
const G_MPS2: f64 = 9.80665;

/// Why a MAVLink navigation input could not be set up.
#[derive(Debug, thiserror::Error)]
pub enum MavlinkNavError {
    #[error("{spec}: {why}")]
    Spec { spec: String, why: String },
    #[error("{spec}: cannot listen on {addr}: {source}")]
    Bind { spec: String, addr: SocketAddr, source: std::io::Error },
    #[error("{spec}: the receiver thread did not start: {source}")]
    Thread { spec: String, source: std::io::Error },
}

/// Which message gives the depth.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DepthSource {
    /// The first of these that the stream carries, in this order.
    Auto,
    Pressure2,
    Pressure,
    GlobalPosition,
    VfrHud,
}

const DEPTH_KINDS: [DepthSource; 4] = [DepthSource::Pressure2, DepthSource::Pressure, DepthSource::GlobalPosition, DepthSource::VfrHud];

/// A parsed `mavlink:[udpin:]HOST:PORT[,depth=...][,surface_pa=P][,density=RHO][,min_confidence=C]`.
#[derive(Clone, Debug, PartialEq)]
pub struct MavlinkNavSpec {
    pub spec: String,
    pub listen: SocketAddr,
    pub depth: DepthSource,
    pub surface_pa: f64,
    pub density_kg_m3: f64,
    /// DVL samples below this confidence (0..1) are dropped.
    pub min_confidence: f64,
}

impl MavlinkNavSpec {
    pub fn parse(spec: &str) -> Result<Self, MavlinkNavError> {
        let bad = |why: String| MavlinkNavError::Spec { spec: spec.to_string(), why };
        let rest = spec.strip_prefix("mavlink:").ok_or_else(|| bad("not a mavlink: spec".into()))?;
        let mut parts = rest.split(',');
        let addr = parts.next().unwrap_or("");
        let addr = addr.strip_prefix("udpin:").unwrap_or(addr);
        if addr.starts_with("udpout:") || addr.starts_with("tcp") || addr.starts_with("serial:") {
            return Err(bad(format!("{addr}: only udpin:HOST:PORT is read (the autopilot sends to us)")));
        }
        let listen: SocketAddr = addr.parse().map_err(|_| bad(format!("{addr:?} is not HOST:PORT (e.g. udpin:0.0.0.0:14550)")))?;
        let mut out = MavlinkNavSpec { spec: spec.to_string(), listen, depth: DepthSource::Auto, surface_pa: 101_325.0, density_kg_m3: 1025.0, min_confidence: 0.5 };
        for opt in parts {
            let (k, v) = opt.split_once('=').ok_or_else(|| bad(format!("option {opt:?} is not KEY=VALUE")))?;
            let number = |lo: f64, hi: f64| -> Result<f64, MavlinkNavError> {
                v.parse::<f64>().ok().filter(|x| x.is_finite() && (lo..=hi).contains(x)).ok_or_else(|| bad(format!("{k}={v}: must be a number in [{lo}, {hi}]")))
            };
            match k {
                "depth" => {
                    out.depth = match v {
                        "auto" => DepthSource::Auto,
                        "pressure2" => DepthSource::Pressure2,
                        "pressure" => DepthSource::Pressure,
                        "global_position" => DepthSource::GlobalPosition,
                        "vfr_hud" => DepthSource::VfrHud,
                        _ => return Err(bad(format!("depth={v}: one of auto, pressure2, pressure, global_position, vfr_hud"))),
                    }
                }
                "surface_pa" => out.surface_pa = number(50_000.0, 150_000.0)?,
                "density" => out.density_kg_m3 = number(900.0, 1100.0)?,
                "min_confidence" => out.min_confidence = number(0.0, 1.0)?,
                _ => return Err(bad(format!("unknown option {k:?} (depth, surface_pa, density, min_confidence)"))),
            }
        }
        Ok(out)
    }
}

/// Messages seen and used, by kind.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct MavlinkCounts {
    pub datagrams: u64,
    pub messages: u64,
    /// Read errors other than a timeout (the decoder itself skips frames whose CRC fails).
    pub undecoded: u64,
    pub depth: [u64; 4],
    pub attitude: u64,
    pub altitude: u64,
    pub velocity: u64,
    /// DVL samples below the confidence floor.
    pub low_confidence: u64,
    /// Samples past the buffer ([`NavSettings::max_samples`](duv_core::config::board::NavSettings)).
    pub over_capacity: u64,
}

/// What one message says, converted to the camera frame (`None`: nothing for navigation).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum NavReading {
    Depth { kind: DepthSource, depth_m: f64 },
    Attitude { world_from_cam: UnitQuaternion<f64> },
    Altitude { altitude_m: f64 },
    Velocity { vel_cam_mps: Vector3<f64>, confidence: f64 },
}

/// The camera's rotation in a world with z up (north, west, up) from the autopilot's body
/// attitude (body FRD to NED) and the camera's mounting (camera to body).
pub fn world_from_cam(ned_from_body: UnitQuaternion<f64>, body_from_cam: UnitQuaternion<f64>) -> UnitQuaternion<f64> {
    let nwu_from_ned = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
    nwu_from_ned * ned_from_body * body_from_cam
}

/// What `msg` says for navigation, in the camera frame.
pub fn reading(msg: &MavMessage, spec: &MavlinkNavSpec, body_from_cam: UnitQuaternion<f64>) -> Option<NavReading> {
    let pressure_depth = |hpa: f32| (hpa as f64 * 100.0 - spec.surface_pa) / (spec.density_kg_m3 * G_MPS2);
    match msg {
        MavMessage::SCALED_PRESSURE2(d) => Some(NavReading::Depth { kind: DepthSource::Pressure2, depth_m: pressure_depth(d.press_abs) }),
        MavMessage::SCALED_PRESSURE(d) => Some(NavReading::Depth { kind: DepthSource::Pressure, depth_m: pressure_depth(d.press_abs) }),
        MavMessage::GLOBAL_POSITION_INT(d) => Some(NavReading::Depth { kind: DepthSource::GlobalPosition, depth_m: -(d.relative_alt as f64) / 1000.0 }),
        MavMessage::VFR_HUD(d) => Some(NavReading::Depth { kind: DepthSource::VfrHud, depth_m: -(d.alt as f64) }),
        MavMessage::ATTITUDE_QUATERNION(d) => {
            let q = nalgebra::Quaternion::new(d.q1 as f64, d.q2 as f64, d.q3 as f64, d.q4 as f64);
            let norm = q.norm();
            (norm.is_finite() && (norm - 1.0).abs() < 0.01).then(|| NavReading::Attitude { world_from_cam: world_from_cam(UnitQuaternion::from_quaternion(q), body_from_cam) })
        }
        MavMessage::ATTITUDE(d) => {
            let ned_from_body = UnitQuaternion::from_euler_angles(d.roll as f64, d.pitch as f64, d.yaw as f64);
            Some(NavReading::Attitude { world_from_cam: world_from_cam(ned_from_body, body_from_cam) })
        }
        MavMessage::DISTANCE_SENSOR(d) if d.orientation == MavSensorOrientation::MAV_SENSOR_ROTATION_PITCH_270 => {
            // 0 and readings outside the sensor's own range mean no echo.
            let cm = d.current_distance;
            (cm > 0 && cm >= d.min_distance && (d.max_distance == 0 || cm <= d.max_distance)).then(|| NavReading::Altitude { altitude_m: cm as f64 / 100.0 })
        }
        MavMessage::RANGEFINDER(d) => (d.distance > 0.0).then(|| NavReading::Altitude { altitude_m: d.distance as f64 }),
        MavMessage::VISION_POSITION_DELTA(d) => {
            let dt_s = d.time_delta_usec as f64 * 1e-6;
            if dt_s <= 0.0 {
                return None;
            }
            let v_body = Vector3::new(d.position_delta[0] as f64, d.position_delta[1] as f64, d.position_delta[2] as f64) / dt_s;
            // The Water Linked driver sends its confidence in percent.
            let confidence = if d.confidence > 1.0 { d.confidence as f64 / 100.0 } else { d.confidence as f64 };
            Some(NavReading::Velocity { vel_cam_mps: body_from_cam.inverse_transform_vector(&v_body), confidence })
        }
        _ => None,
    }
}

/// One datagram at a time as a byte stream (a MAVLink frame never spans two datagrams); a read
/// that times out returns `TimedOut`, so the reader loop can look at its stop flag.
struct Datagrams {
    socket: UdpSocket,
    buf: Box<[u8; 65_536]>,
    start: usize,
    end: usize,
    received: u64,
}

impl Read for Datagrams {
    fn read(&mut self, out: &mut [u8]) -> std::io::Result<usize> {
        if self.start == self.end {
            let n = self.socket.recv(&mut self.buf[..])?;
            self.received += 1;
            (self.start, self.end) = (0, n);
        }
        let n = out.len().min(self.end - self.start);
        out[..n].copy_from_slice(&self.buf[self.start..self.start + n]);
        self.start += n;
        Ok(n)
    }
}

/// What the receiver thread keeps: samples stamped on the run's clock, depths by kind.
struct Collected {
    samples: Vec<NavSample>,
    depths: [Vec<(i64, f64)>; 4],
    counts: MavlinkCounts,
    capacity: usize,
    /// Handed every sample as it arrives (the run's log); depths only of the kind in use.
    tap: Option<NavTap>,
    /// The best depth kind seen so far (index in [`DEPTH_KINDS`]), for the tap.
    depth_in_use: Option<usize>,
}

/// Where a receiver hands each sample as it arrives (stamped with the run's clock).
pub type NavTap = Box<dyn FnMut(NavSample) + Send>;

/// The receiving thread of a live MAVLink stream, collecting samples until [`NavReceiver::finish`].
pub struct NavReceiver {
    spec: MavlinkNavSpec,
    local: SocketAddr,
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<Collected>>,
}

/// The dive's navigation samples from the stream, on the frames' clock, with what was seen.
#[derive(Debug)]
pub struct MavlinkNav {
    pub track: NavTrack,
    pub counts: MavlinkCounts,
    /// The depth messages used.
    pub depth_source: Option<DepthSource>,
}

impl NavReceiver {
    /// Listens on the spec's address and collects from now on; `epoch` is the run's clock
    /// (samples are stamped with the time since it), `body_from_cam` the camera's mounting,
    /// `max_samples` the buffer (allocated here).
    /// `tap`, when given, gets every sample as it arrives (depths only of the message kind in
    /// use), e.g. for the log.
    pub fn start(spec: MavlinkNavSpec, body_from_cam: UnitQuaternion<f64>, max_samples: usize, epoch: Instant, tap: Option<NavTap>) -> Result<Self, MavlinkNavError> {
        let socket = UdpSocket::bind(spec.listen).map_err(|source| MavlinkNavError::Bind { spec: spec.spec.clone(), addr: spec.listen, source })?;
        let local = socket.local_addr().map_err(|source| MavlinkNavError::Bind { spec: spec.spec.clone(), addr: spec.listen, source })?;
        socket.set_read_timeout(Some(Duration::from_millis(100))).map_err(|source| MavlinkNavError::Bind { spec: spec.spec.clone(), addr: spec.listen, source })?;
        let stop = Arc::new(AtomicBool::new(false));
        let s = stop.clone();
        let sp = spec.clone();
        let thread = std::thread::Builder::new()
            .name("nav".into())
            .spawn(move || receive(socket, &sp, body_from_cam, max_samples, epoch, &s, tap))
            .map_err(|source| MavlinkNavError::Thread { spec: spec.spec.clone(), source })?;
        tracing::info!(spec = spec.spec, %local, "navigation: listening for MAVLink");
        Ok(NavReceiver { spec, local, stop, thread: Some(thread) })
    }

    /// The address it listens on (the port the OS chose for port 0).
    pub fn local_addr(&self) -> SocketAddr {
        self.local
    }

    /// Stops receiving; the samples, judged like `nav.csv` rows, with their arrival times
    /// (run clock, ns) moved onto the frames' clock by `frame_time_ns`.
    pub fn finish(mut self, frame_time_ns: impl Fn(i64) -> i64) -> MavlinkNav {
        self.stop.store(true, Ordering::Relaxed);
        let collected = self.thread.take().and_then(|t| t.join().ok());
        let Some(mut c) = collected else {
            tracing::error!(spec = self.spec.spec, "navigation: the MAVLink receiver failed; no samples");
            return MavlinkNav { track: NavTrack { samples: Vec::new(), rejected: Default::default() }, counts: MavlinkCounts::default(), depth_source: None };
        };
        let chosen = match self.spec.depth {
            DepthSource::Auto => DEPTH_KINDS.iter().zip(&c.depths).find(|(_, d)| !d.is_empty()).map(|(k, _)| *k),
            k => Some(k),
        };
        if let Some(k) = chosen {
            let i = DEPTH_KINDS.iter().position(|d| *d == k).unwrap_or(0);
            let depths = std::mem::take(&mut c.depths[i]);
            c.samples.extend(depths.into_iter().map(|(t, d)| NavSample { depth_m: Some(d), ..NavSample::empty(Timestamp::from_ns(t)) }));
        }
        for s in &mut c.samples {
            s.t_ns = Timestamp::from_ns(frame_time_ns(s.t_ns.t_ns()));
        }
        MavlinkNav { track: validate_samples(c.samples), counts: c.counts, depth_source: chosen }
    }
}

impl Drop for NavReceiver {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
    }
}

fn receive(socket: UdpSocket, spec: &MavlinkNavSpec, body_from_cam: UnitQuaternion<f64>, capacity: usize, epoch: Instant, stop: &AtomicBool, tap: Option<NavTap>) -> Collected {
    let depth_capacity = capacity / 4 + 1;
    let mut c = Collected {
        samples: Vec::with_capacity(capacity),
        depths: std::array::from_fn(|_| Vec::with_capacity(depth_capacity)),
        counts: MavlinkCounts::default(),
        capacity,
        tap,
        depth_in_use: match spec.depth {
            DepthSource::Auto => None,
            k => DEPTH_KINDS.iter().position(|d| *d == k),
        },
    };
    let mut reader = MavlinkReader::new(Datagrams { socket, buf: Box::new([0; 65_536]), start: 0, end: 0, received: 0 });
    while !stop.load(Ordering::Relaxed) {
        match reader.read_any_message::<MavMessage>() {
            Ok((_, msg)) => {
                c.counts.messages += 1;
                let t_ns = epoch.elapsed().as_nanos() as i64;
                if let Some(r) = reading(&msg, spec, body_from_cam) {
                    keep(&mut c, t_ns, r, spec.min_confidence, spec.depth == DepthSource::Auto);
                }
            }
            Err(mavlink::error::MessageReadError::Io(e)) if matches!(e.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut) => {}
            Err(mavlink::error::MessageReadError::Io(e)) => {
                tracing::error!(spec = spec.spec, "navigation: MAVLink socket: {e}; receiving stops");
                break;
            }
            Err(_) => c.counts.undecoded += 1,
        }
    }
    c.counts.datagrams = reader.get_ref().received;
    c
}

fn keep(c: &mut Collected, t_ns: i64, r: NavReading, min_confidence: f64, auto_depth: bool) {
    let t = Timestamp::from_ns(t_ns);
    let sample = match r {
        NavReading::Depth { kind, depth_m } => {
            let i = DEPTH_KINDS.iter().position(|d| *d == kind).unwrap_or(0);
            c.counts.depth[i] += 1;
            if auto_depth && c.depth_in_use.is_none_or(|u| i < u) {
                c.depth_in_use = Some(i);
            }
            if c.depth_in_use == Some(i) {
                if let Some(tap) = c.tap.as_mut() {
                    tap(NavSample { depth_m: Some(depth_m), ..NavSample::empty(t) });
                }
            }
            let v = &mut c.depths[i];
            if v.len() < v.capacity() {
                v.push((t_ns, depth_m));
            } else {
                c.counts.over_capacity += 1;
            }
            return;
        }
        NavReading::Attitude { world_from_cam } => {
            c.counts.attitude += 1;
            NavSample { world_from_cam_rot: Some(world_from_cam), ..NavSample::empty(t) }
        }
        NavReading::Altitude { altitude_m } => {
            c.counts.altitude += 1;
            NavSample { altitude_m: Some(altitude_m), ..NavSample::empty(t) }
        }
        NavReading::Velocity { vel_cam_mps, confidence } => {
            c.counts.velocity += 1;
            if confidence < min_confidence {
                c.counts.low_confidence += 1;
                return;
            }
            NavSample { vel_cam_mps: Some(vel_cam_mps), ..NavSample::empty(t) }
        }
    };
    if let Some(tap) = c.tap.as_mut() {
        tap(sample);
    }
    if c.samples.len() < c.capacity {
        c.samples.push(sample);
    } else {
        c.counts.over_capacity += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mavlink::dialects::ardupilotmega as ap;
    use mavlink::{MavHeader, MavlinkVersion};

    fn spec(extra: &str) -> MavlinkNavSpec {
        MavlinkNavSpec::parse(&format!("mavlink:udpin:127.0.0.1:0{extra}")).unwrap()
    }

    /// The camera pitched 40 degrees down, as the generator's.
    fn down40() -> UnitQuaternion<f64> {
        duv_core::config::board::NavSettings { camera_rpy_deg: [0.0, -40.0, 0.0], ..Default::default() }.body_from_cam()
    }

    #[test]
    fn specs_are_read_and_bad_ones_named() {
        let s = MavlinkNavSpec::parse("mavlink:udpin:0.0.0.0:14550,depth=pressure2,density=997,surface_pa=100000").unwrap();
        assert_eq!((s.listen.port(), s.depth, s.density_kg_m3, s.surface_pa, s.min_confidence), (14550, DepthSource::Pressure2, 997.0, 100_000.0, 0.5));
        assert_eq!(MavlinkNavSpec::parse("mavlink:127.0.0.1:14551").unwrap().listen.port(), 14551);
        for (bad, says) in [
            ("mavlink:udpout:1.2.3.4:14550", "only udpin"),
            ("mavlink:udpin:nowhere", "is not HOST:PORT"),
            ("mavlink:udpin:0.0.0.0:14550,density=5", "density=5: must be a number in [900, 1100]"),
            ("mavlink:udpin:0.0.0.0:14550,depth=sonar", "depth=sonar: one of"),
            ("mavlink:udpin:0.0.0.0:14550,speed=2", "unknown option \"speed\""),
        ] {
            let e = MavlinkNavSpec::parse(bad).unwrap_err().to_string();
            assert!(e.starts_with(bad) && e.contains(says), "{bad}: {e}");
        }
    }

    #[test]
    fn each_message_becomes_its_reading_in_the_camera_frame() {
        let s = spec("");
        // 12.5 m of sea water above the sensor.
        let hpa = ((101_325.0 + 1025.0 * G_MPS2 * 12.5) / 100.0) as f32;
        let r = reading(&MavMessage::SCALED_PRESSURE2(ap::SCALED_PRESSURE2_DATA { press_abs: hpa, ..Default::default() }), &s, down40());
        let Some(NavReading::Depth { kind: DepthSource::Pressure2, depth_m }) = r else { panic!("{r:?}") };
        assert!((depth_m - 12.5).abs() < 1e-3, "{depth_m}");
        let r = reading(&MavMessage::GLOBAL_POSITION_INT(ap::GLOBAL_POSITION_INT_DATA { relative_alt: -7_250, ..Default::default() }), &s, down40());
        assert_eq!(r, Some(NavReading::Depth { kind: DepthSource::GlobalPosition, depth_m: 7.25 }));
        // Level, heading north: the optical axis points north and 40 degrees down (world z up).
        let level = MavMessage::ATTITUDE_QUATERNION(ap::ATTITUDE_QUATERNION_DATA { q1: 1.0, ..Default::default() });
        let Some(NavReading::Attitude { world_from_cam }) = reading(&level, &s, down40()) else { panic!() };
        let axis = world_from_cam * Vector3::z();
        let (c, sn) = (40f64.to_radians().cos(), 40f64.to_radians().sin());
        assert!((axis - Vector3::new(c, 0.0, -sn)).norm() < 1e-6, "{axis}");
        // Gravity in the camera frame does not depend on the heading.
        let turned = ap::ATTITUDE_DATA { roll: 0.0, pitch: 0.0, yaw: 1.2, ..Default::default() };
        let Some(NavReading::Attitude { world_from_cam: w2 }) = reading(&MavMessage::ATTITUDE(turned), &s, down40()) else { panic!() };
        assert!((world_from_cam.inverse_transform_vector(&Vector3::z()) - w2.inverse_transform_vector(&Vector3::z())).norm() < 1e-6);
        // Pitched nose-up 10 degrees: the optical axis is 30 degrees below the horizon.
        let up10 = ap::ATTITUDE_DATA { pitch: 10f32.to_radians(), ..Default::default() };
        let Some(NavReading::Attitude { world_from_cam: w3 }) = reading(&MavMessage::ATTITUDE(up10), &s, down40()) else { panic!() };
        assert!(((w3 * Vector3::z()).z + 30f64.to_radians().sin()).abs() < 1e-6);
        // Altitude: a down-facing sensor in cm; another orientation is not an altimeter.
        let down = ap::DISTANCE_SENSOR_DATA { current_distance: 231, min_distance: 10, max_distance: 5000, orientation: ap::MavSensorOrientation::MAV_SENSOR_ROTATION_PITCH_270, ..Default::default() };
        assert_eq!(reading(&MavMessage::DISTANCE_SENSOR(down.clone()), &s, down40()), Some(NavReading::Altitude { altitude_m: 2.31 }));
        let ahead = ap::DISTANCE_SENSOR_DATA { orientation: ap::MavSensorOrientation::MAV_SENSOR_ROTATION_NONE, ..down };
        assert_eq!(reading(&MavMessage::DISTANCE_SENSOR(ahead), &s, down40()), None);
        // DVL: 5 cm forward in 0.1 s at 87 % confidence; ahead-looking camera: +z at 0.5 m/s.
        let dvl = ap::VISION_POSITION_DELTA_DATA { time_delta_usec: 100_000, position_delta: [0.05, 0.0, 0.0], confidence: 87.0, ..Default::default() };
        let Some(NavReading::Velocity { vel_cam_mps, confidence }) = reading(&MavMessage::VISION_POSITION_DELTA(dvl), &s, NavSettingsAhead::get()) else { panic!() };
        assert!((vel_cam_mps - Vector3::new(0.0, 0.0, 0.5)).norm() < 1e-6 && (confidence - 0.87).abs() < 1e-6, "{vel_cam_mps} {confidence}");
    }

    struct NavSettingsAhead;
    impl NavSettingsAhead {
        fn get() -> UnitQuaternion<f64> {
            duv_core::config::board::NavSettings::default().body_from_cam()
        }
    }

    fn frame(seq: u8, msg: &MavMessage) -> Vec<u8> {
        let mut out = Vec::new();
        mavlink::write_versioned_msg(&mut out, MavlinkVersion::V2, MavHeader { system_id: 1, component_id: 1, sequence: seq }, msg).unwrap();
        out
    }

    #[test]
    fn a_udp_stream_from_an_autopilot_is_collected_and_judged() {
        let epoch = Instant::now();
        let rx = NavReceiver::start(spec(""), down40(), 1000, epoch, None).unwrap();
        let to = rx.local_addr();
        let tx = UdpSocket::bind("127.0.0.1:0").unwrap();
        let hpa = |d: f64| ((101_325.0 + 1025.0 * G_MPS2 * d) / 100.0) as f32;
        for i in 0..20u8 {
            let depth = 10.0 + 0.01 * i as f64;
            let mut datagram = frame(i, &MavMessage::SCALED_PRESSURE2(ap::SCALED_PRESSURE2_DATA { press_abs: hpa(depth), ..Default::default() }));
            // Two messages in one datagram, as routers send them; and messages that say nothing.
            datagram.extend(frame(i, &MavMessage::VFR_HUD(ap::VFR_HUD_DATA { alt: -99.0, ..Default::default() })));
            datagram.extend(frame(i, &MavMessage::HEARTBEAT(ap::HEARTBEAT_DATA::default())));
            tx.send_to(&datagram, to).unwrap();
            let range = ap::RANGEFINDER_DATA { distance: 2.0 + 0.1 * i as f32, voltage: 0.0 };
            tx.send_to(&frame(i, &MavMessage::RANGEFINDER(range)), to).unwrap();
            // A damaged frame (one payload byte flipped: the CRC fails).
            let mut bad = frame(i, &MavMessage::RANGEFINDER(ap::RANGEFINDER_DATA { distance: 50.0, voltage: 0.0 }));
            bad[12] ^= 0x55;
            tx.send_to(&bad, to).unwrap();
            let low = ap::VISION_POSITION_DELTA_DATA { time_delta_usec: 100_000, position_delta: [0.05, 0.0, 0.0], confidence: if i % 2 == 0 { 90.0 } else { 10.0 }, ..Default::default() };
            tx.send_to(&frame(i, &MavMessage::VISION_POSITION_DELTA(low)), to).unwrap();
            std::thread::sleep(Duration::from_millis(2));
        }
        std::thread::sleep(Duration::from_millis(150));
        let nav = rx.finish(|t| t);
        let c = nav.counts;
        assert_eq!((c.depth[0], c.depth[3], c.altitude, c.velocity, c.low_confidence), (20, 20, 20, 20, 10), "{c:?}");
        assert_eq!((c.datagrams, c.messages), (80, 100), "a damaged frame is skipped by the decoder (its CRC fails), not read: {c:?}");
        assert_eq!(nav.depth_source, Some(DepthSource::Pressure2), "the pressure sensor wins over VFR_HUD");
        let depths: Vec<f64> = nav.track.samples.iter().filter_map(|s| s.depth_m).collect();
        assert_eq!(depths.len(), 20);
        assert!(depths.iter().enumerate().all(|(i, d)| (d - (10.0 + 0.01 * i as f64)).abs() < 2e-3), "{depths:?}");
        let alts: Vec<f64> = nav.track.samples.iter().filter_map(|s| s.altitude_m).collect();
        assert_eq!(alts.len(), 20, "no 50 m reading from a damaged frame: {alts:?}");
        assert_eq!(nav.track.samples.iter().filter(|s| s.vel_cam_mps.is_some()).count(), 10);
        assert!(nav.track.samples.windows(2).all(|w| w[0].t_ns < w[1].t_ns));
        let span_ms = (nav.track.samples.last().unwrap().t_ns.t_ns() - nav.track.samples[0].t_ns.t_ns()) as f64 * 1e-6;
        assert!(span_ms > 30.0 && span_ms < 5_000.0, "stamped on arrival: {span_ms} ms");
    }

    #[test]
    fn a_busy_port_is_an_error_naming_it() {
        let taken = UdpSocket::bind("127.0.0.1:0").unwrap();
        let port = taken.local_addr().unwrap().port();
        let e = NavReceiver::start(spec("").clone_with_port(port), down40(), 10, Instant::now(), None).err().unwrap().to_string();
        assert!(e.contains(&format!("cannot listen on 127.0.0.1:{port}")), "{e}");
    }

    impl MavlinkNavSpec {
        fn clone_with_port(mut self, port: u16) -> Self {
            self.listen.set_port(port);
            self
        }
    }
}
