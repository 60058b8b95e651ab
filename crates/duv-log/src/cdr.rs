//! CDR, the encoding of ROS 2 messages: the writer and reader of one body (little-endian
//! writing, both byte orders reading, ROS 2 alignment), the ROS 2 format's names, and the
//! decoding of the messages our readers take back from a ROS 2 bag into plain values.
//! [`super::ros2`] writes the messages; this module knows no log item, so the log's decoders
//! ([`super::schema`]) and the tracker window can use it without a circle.
//!
//! Hand-written: the serde-based CDR crates copy every image into an owned struct before
//! writing it, where this writer puts the pixel planes straight into the one reused buffer.

use super::records::StateMessage;

/// Errors of the `cdr` module: a CDR body that does not parse.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum CdrError {
    #[error("not a little-endian CDR body (encapsulation header {found:02x?}, expected 00 01 00 00)")]
    Header { found: [u8; 4] },
    #[error("cut short: {need} bytes needed at byte {at} of {len}")]
    Truncated { at: usize, need: usize, len: usize },
    #[error("string at byte {at} is not NUL-terminated UTF-8")]
    BadString { at: usize },
    #[error("{trailing} bytes after the end of the message")]
    Trailing { trailing: usize },
}

/// The encapsulation header of a little-endian plain CDR body.
pub const CDR_LE: [u8; 4] = [0, 1, 0, 0];

/// Whether `data` starts like a little-endian CDR body. Nothing else the log writes does: a
/// protobuf message never starts with a 0 byte (field number 0 is invalid), JSON starts with
/// `{`, the tracker window with `DUVW`, a map checkpoint with `DUVMAPCK`.
pub fn is_cdr(data: &[u8]) -> bool {
    data.len() >= 4 && data[..4] == CDR_LE
}

/// Writes one CDR body into a reused buffer.
pub struct CdrWriter<'a> {
    pub(crate) out: &'a mut Vec<u8>,
}

impl<'a> CdrWriter<'a> {
    /// Clears `out` (its capacity is kept) and writes the encapsulation header.
    pub fn new(out: &'a mut Vec<u8>) -> Self {
        out.clear();
        out.extend_from_slice(&CDR_LE);
        CdrWriter { out }
    }

    fn align(&mut self, n: usize) {
        while !(self.out.len() - 4).is_multiple_of(n) {
            self.out.push(0);
        }
    }
    pub fn u8(&mut self, v: u8) {
        self.out.push(v);
    }
    pub fn bool(&mut self, v: bool) {
        self.out.push(v as u8);
    }
    pub fn u32(&mut self, v: u32) {
        self.align(4);
        self.out.extend_from_slice(&v.to_le_bytes());
    }
    pub fn i32(&mut self, v: i32) {
        self.align(4);
        self.out.extend_from_slice(&v.to_le_bytes());
    }
    pub fn u64(&mut self, v: u64) {
        self.align(8);
        self.out.extend_from_slice(&v.to_le_bytes());
    }
    pub fn i64(&mut self, v: i64) {
        self.align(8);
        self.out.extend_from_slice(&v.to_le_bytes());
    }
    pub fn f64(&mut self, v: f64) {
        self.align(8);
        self.out.extend_from_slice(&v.to_le_bytes());
    }
    pub fn string(&mut self, s: &str) {
        self.u32(s.len() as u32 + 1);
        self.out.extend_from_slice(s.as_bytes());
        self.out.push(0);
    }
    /// A `uint8[]`.
    pub fn bytes(&mut self, b: &[u8]) {
        self.u32(b.len() as u32);
        self.out.extend_from_slice(b);
    }
    /// A `uint8[]` holding `v` as little-endian f32 samples.
    pub fn f32_bytes(&mut self, v: &[f32]) {
        self.u32(4 * v.len() as u32);
        for x in v {
            self.out.extend_from_slice(&x.to_le_bytes());
        }
    }
    /// f32 samples as a `uint8[]` of little-endian f16 ([`plane_sample_f16`]).
    pub fn f16_bytes(&mut self, v: &[f32]) {
        self.u32(2 * v.len() as u32);
        for &x in v {
            self.out.extend_from_slice(&plane_sample_f16(x).to_le_bytes());
        }
    }
    /// A `float64[]`.
    pub fn f64_seq(&mut self, v: &[f64]) {
        self.u32(v.len() as u32);
        for &x in v {
            self.f64(x);
        }
    }
    /// A `float64[N]` (no length).
    pub fn f64_array(&mut self, v: &[f64]) {
        for &x in v {
            self.f64(x);
        }
    }
    /// `builtin_interfaces/Time` of a time in ns (negative clamps to 0).
    pub fn time(&mut self, t_ns: i64) {
        let ns = t_ns.max(0) as u64;
        self.i32((ns / 1_000_000_000).min(i32::MAX as u64) as i32);
        self.u32((ns % 1_000_000_000) as u32);
    }
    /// `std_msgs/Header`.
    pub fn header(&mut self, t_ns: i64, frame_id: &str) {
        self.time(t_ns);
        self.string(frame_id);
    }
    /// `geometry_msgs/Pose` (or `Transform`: the same layout): position, then orientation
    /// x, y, z, w.
    pub fn pose(&mut self, t: [f64; 3], q_xyzw: [f64; 4]) {
        self.f64_array(&t);
        self.f64_array(&q_xyzw);
    }
}

/// Reads one CDR body.
pub struct CdrReader<'a> {
    data: &'a [u8],
    pos: usize,
}

impl<'a> CdrReader<'a> {
    /// Checks the encapsulation header.
    pub fn new(data: &'a [u8]) -> Result<Self, CdrError> {
        if !is_cdr(data) {
            let mut found = [0u8; 4];
            for (f, b) in found.iter_mut().zip(data) {
                *f = *b;
            }
            return Err(CdrError::Header { found });
        }
        Ok(CdrReader { data, pos: 4 })
    }

    fn align(&mut self, n: usize) {
        let r = (self.pos - 4) % n;
        if r != 0 {
            self.pos += n - r;
        }
    }
    fn take(&mut self, n: usize) -> Result<&'a [u8], CdrError> {
        let end = self.pos.checked_add(n).filter(|&e| e <= self.data.len());
        let Some(end) = end else { return Err(CdrError::Truncated { at: self.pos, need: n, len: self.data.len() }) };
        let s = &self.data[self.pos..end];
        self.pos = end;
        Ok(s)
    }
    pub fn u8(&mut self) -> Result<u8, CdrError> {
        Ok(self.take(1)?[0])
    }
    pub fn bool(&mut self) -> Result<bool, CdrError> {
        Ok(self.u8()? != 0)
    }
    pub fn u32(&mut self) -> Result<u32, CdrError> {
        self.align(4);
        Ok(u32::from_le_bytes(self.take(4)?.try_into().expect("4 bytes")))
    }
    pub fn i32(&mut self) -> Result<i32, CdrError> {
        Ok(self.u32()? as i32)
    }
    pub fn u64(&mut self) -> Result<u64, CdrError> {
        self.align(8);
        Ok(u64::from_le_bytes(self.take(8)?.try_into().expect("8 bytes")))
    }
    pub fn i64(&mut self) -> Result<i64, CdrError> {
        Ok(self.u64()? as i64)
    }
    pub fn f64(&mut self) -> Result<f64, CdrError> {
        Ok(f64::from_bits(self.u64()?))
    }
    pub fn string(&mut self) -> Result<&'a str, CdrError> {
        let n = self.u32()? as usize;
        let at = self.pos;
        let b = self.take(n)?;
        match b.split_last() {
            Some((0, s)) => std::str::from_utf8(s).map_err(|_| CdrError::BadString { at }),
            _ => Err(CdrError::BadString { at }),
        }
    }
    /// A `uint8[]`.
    pub fn bytes(&mut self) -> Result<&'a [u8], CdrError> {
        let n = self.u32()? as usize;
        self.take(n)
    }
    /// A `float64[]`; its length is checked against the body before anything is allocated.
    pub fn f64_seq(&mut self) -> Result<Vec<f64>, CdrError> {
        let n = self.u32()? as usize;
        if n.saturating_mul(8) > self.data.len() - self.pos {
            return Err(CdrError::Truncated { at: self.pos, need: n.saturating_mul(8), len: self.data.len() });
        }
        (0..n).map(|_| self.f64()).collect()
    }
    pub fn f64_array<const N: usize>(&mut self) -> Result<[f64; N], CdrError> {
        let mut a = [0.0; N];
        for x in &mut a {
            *x = self.f64()?;
        }
        Ok(a)
    }
    /// `builtin_interfaces/Time` in ns.
    pub fn time(&mut self) -> Result<i64, CdrError> {
        let sec = self.i32()? as i64;
        let nsec = self.u32()? as i64;
        Ok(sec * 1_000_000_000 + nsec)
    }
    /// `std_msgs/Header`: time in ns and frame id.
    pub fn header(&mut self) -> Result<(i64, &'a str), CdrError> {
        Ok((self.time()?, self.string()?))
    }
    /// The message must end here (up to alignment padding a writer may leave).
    pub fn finish(&self) -> Result<(), CdrError> {
        let trailing = self.data.len() - self.pos;
        if trailing > 7 {
            return Err(CdrError::Trailing { trailing });
        }
        Ok(())
    }
}

/// Schema encoding of the ROS 2 format.
pub const SCHEMA_ENCODING: &str = "ros2msg";
/// Message encoding of the ROS 2 format.
pub const MESSAGE_ENCODING: &str = "cdr";
/// MCAP header profile of the ROS 2 format.
pub const PROFILE: &str = "ros2";

/// A `nav_msgs/Odometry`: time, position, orientation (x, y, z, w), linear and angular velocity
/// in the child (camera) frame.
pub fn decode_odometry(data: &[u8]) -> Result<(i64, [f64; 3], [f64; 4], [f64; 3], [f64; 3]), CdrError> {
    let mut r = CdrReader::new(data)?;
    let (t_ns, _) = r.header()?;
    let _child = r.string()?;
    let p = r.f64_array::<3>()?;
    let q = r.f64_array::<4>()?;
    let _ = r.f64_array::<36>()?;
    let v = r.f64_array::<3>()?;
    let w = r.f64_array::<3>()?;
    let _ = r.f64_array::<36>()?;
    r.finish()?;
    Ok((t_ns, p, q, v, w))
}

/// A `duv_msgs/NavSample`: NaN fields are sensors without a sample.
pub fn decode_nav_sample(data: &[u8]) -> Result<duv_core::nav::NavSample, CdrError> {
    let mut r = CdrReader::new(data)?;
    let (t_ns, _) = r.header()?;
    let depth = r.f64()?;
    let altitude = r.f64()?;
    let v = r.f64_array::<3>()?;
    let q = r.f64_array::<4>()?;
    r.finish()?;
    let some = |x: f64| (!x.is_nan()).then_some(x);
    let all = |a: &[f64]| a.iter().all(|x| !x.is_nan());
    Ok(super::records::nav_sample(t_ns, some(depth), some(altitude), all(&v).then_some(v), all(&q).then_some(q)))
}

/// `sensor_msgs/PointField` datatype of float32.
pub const POINT_FIELD_FLOAT32: u8 = 7;

/// A `sensor_msgs/Image`, borrowed from its body.
#[derive(Debug)]
pub struct RosImage<'a> {
    pub t_ns: i64,
    pub height: u32,
    pub width: u32,
    pub encoding: &'a str,
    pub step: u32,
    pub data: &'a [u8],
}

pub fn decode_image(data: &[u8]) -> Result<RosImage<'_>, CdrError> {
    let mut r = CdrReader::new(data)?;
    let (t_ns, _) = r.header()?;
    let height = r.u32()?;
    let width = r.u32()?;
    let encoding = r.string()?;
    let _bigendian = r.u8()?;
    let step = r.u32()?;
    let pixels = r.bytes()?;
    r.finish()?;
    Ok(RosImage { t_ns, height, width, encoding, step, data: pixels })
}

/// A `sensor_msgs/CompressedImage`: time, format, data.
pub fn decode_compressed_image(data: &[u8]) -> Result<(i64, &str, &[u8]), CdrError> {
    let mut r = CdrReader::new(data)?;
    let (t_ns, _) = r.header()?;
    let format = r.string()?;
    let bytes = r.bytes()?;
    r.finish()?;
    Ok((t_ns, format, bytes))
}

/// A `sensor_msgs/CameraInfo`: width, height, K (row major).
pub fn decode_camera_info(data: &[u8]) -> Result<(u32, u32, [f64; 9]), CdrError> {
    let mut r = CdrReader::new(data)?;
    r.header()?;
    let height = r.u32()?;
    let width = r.u32()?;
    r.string()?;
    r.f64_seq()?;
    let k = r.f64_array::<9>()?;
    Ok((width, height, k))
}

/// A `geometry_msgs/PoseStamped`: time, position, orientation (x, y, z, w).
pub fn decode_pose_stamped(data: &[u8]) -> Result<(i64, [f64; 3], [f64; 4]), CdrError> {
    let mut r = CdrReader::new(data)?;
    let (t_ns, _) = r.header()?;
    let t = r.f64_array::<3>()?;
    let q = r.f64_array::<4>()?;
    r.finish()?;
    Ok((t_ns, t, q))
}

/// A `duv_msgs/TrackingState`.
pub fn decode_tracking_state(data: &[u8]) -> Result<StateMessage, CdrError> {
    let mut r = CdrReader::new(data)?;
    r.header()?;
    let seq = r.u64()?;
    let t_ns = r.i64()?;
    let state = r.string()?.to_string();
    let tracked = r.bool()?;
    let has_keyframe = r.bool()?;
    let keyframe = r.u64()?;
    let has_new = r.bool()?;
    let new_keyframe = r.u64()?;
    let loop_closed = r.bool()?;
    let segment = r.u32()?;
    let why = r.string()?;
    let value = r.f64()?;
    let limit = r.f64()?;
    r.finish()?;
    Ok(StateMessage {
        seq,
        t_ns,
        state,
        tracked,
        keyframe: has_keyframe.then_some(keyframe),
        new_keyframe: has_new.then_some(new_keyframe),
        loop_closed,
        segment,
        why: (!why.is_empty()).then(|| why.to_string()),
        value: (!value.is_nan()).then_some(value),
        limit: (!limit.is_nan()).then_some(limit),
    })
}

/// The `uint8[] data` of a `duv_msgs/TrackerWindow` or `duv_msgs/MapCheckpoint`.
pub fn decode_wrapped(data: &[u8]) -> Result<&[u8], CdrError> {
    let mut r = CdrReader::new(data)?;
    r.header()?;
    let bytes = r.bytes()?;
    r.finish()?;
    Ok(bytes)
}

/// The JSON of a `duv_msgs/Health`.
pub fn decode_health(data: &[u8]) -> Result<&str, CdrError> {
    let mut r = CdrReader::new(data)?;
    r.header()?;
    let json = r.string()?;
    r.finish()?;
    Ok(json)
}

/// One keyframe plane sample as f16 bits (`schema::PLANE_ENCODING`, which states the
/// precision): finite values clamped to the f16 range, infinities and NaN kept.
pub fn plane_sample_f16(x: f32) -> u16 {
    let x = if x.is_finite() { x.clamp(-65504.0, 65504.0) } else { x };
    half::f16::from_f32(x).to_bits()
}
