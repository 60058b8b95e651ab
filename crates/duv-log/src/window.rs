//! The tracker's sliding window as the log keeps it (`/slam/window`): what a resume after a
//! power cut seeds a new tracker with.
//!
//! Keyframes reach `/keyframe/*` only after they leave the BA window, so a run that is cut
//! every second or two never logs one. Twice a second (frame time) tracking logs its newest
//! keyframes instead, small: per keyframe the id, the frame number of its image (the image is
//! on `/camera/image` already), its pose in the logged world frame and the inverse depth and
//! variance on the tracker's depth grid (1/8 of the input resolution by default).
//!
//! Body (schemaless channel, encoding [`WINDOW_ENCODING`], little endian):
//! `b"DUVW"`, `u32` version (1), `u64` frame seq, `i64` t_ns, `u32` keyframes, `u32` grid
//! width, `u32` grid height, then per keyframe `u64` id, `u64` seq, `i64` t_ns, 7 x `f64` pose
//! (tx ty tz qx qy qz qw), `u8` has variance, width x height `f32` inverse depth, and the same
//! again for the variance when it has one.

use duv_core::io::le::{LeError, LeReader};
use duv_core::pose::PoseError;
use duv_core::{PlaneF32, Se3, Timestamp};

/// Message encoding of the `/slam/window` channel.
pub const WINDOW_ENCODING: &str = "duv.tracker_window";
const MAGIC: &[u8; 4] = b"DUVW";
const VERSION: u32 = 1;
const HEADER_BYTES: usize = 4 + 4 + 8 + 8 + 4 + 4 + 4;
const KEYFRAME_HEADER_BYTES: usize = 8 + 8 + 8 + 7 * 8 + 1;

/// Errors of the `window` module: a window that cannot be encoded, a body that cannot be
/// decoded.
#[derive(Debug, thiserror::Error)]
pub enum WindowError {
    /// A keyframe's depth or variance plane is not the size of the window's grid.
    #[error("keyframe {id}: depth grid differs from the window's {width}x{height}")]
    GridMismatch { id: u64, width: usize, height: usize },
    /// The body ends early or claims an array it does not hold.
    #[error(transparent)]
    Read(#[from] LeError),
    #[error("not a tracker window (magic)")]
    BadMagic,
    #[error("tracker window version {found}, this build reads {VERSION}")]
    UnsupportedVersion { found: u32 },
    #[error("depth grid {width}x{height} overflows")]
    GridOverflow { width: usize, height: usize },
    #[error("{count} keyframes of a {width}x{height} grid do not fit in {bytes} bytes")]
    TooManyKeyframes { count: usize, width: usize, height: usize, bytes: usize },
    #[error("keyframe {id}: pose: {source}")]
    BadPose { id: u64, source: PoseError },
    #[error("keyframe {id}: variance flag {flag}")]
    BadVarianceFlag { id: u64, flag: u8 },
    #[error("{bytes} bytes after the last keyframe")]
    TrailingBytes { bytes: usize },
    /// A `duv_msgs/msg/TrackerWindow` (a log in the ROS 2 format) that does not parse.
    #[error("not a duv_msgs/msg/TrackerWindow: {0}")]
    Cdr(#[from] crate::cdr::CdrError),
}

/// One keyframe of the window.
#[derive(Clone, Debug, PartialEq)]
pub struct WindowKeyframe {
    pub id: u64,
    /// Frame number of its image.
    pub seq: u64,
    pub t_ns: Timestamp,
    pub world_from_cam: Se3,
    /// Inverse depth on the depth grid, 1/m.
    pub inv_depth: PlaneF32,
    /// Its variance, (1/m)^2, when `has_variance` (not before the keyframe's first
    /// covariance; the plane is kept either way, so a reused record never reallocates).
    pub variance: PlaneF32,
    pub has_variance: bool,
}

impl WindowKeyframe {
    /// The variance plane when the keyframe has one.
    pub fn variance(&self) -> Option<&PlaneF32> {
        self.has_variance.then_some(&self.variance)
    }
}

/// The newest keyframes of the tracker after frame `seq`, oldest first.
#[derive(Clone, Debug, PartialEq)]
pub struct TrackerWindow {
    pub seq: u64,
    pub t_ns: Timestamp,
    pub keyframes: Vec<WindowKeyframe>,
}

impl TrackerWindow {
    /// Bytes of the encoded body.
    pub fn encoded_len(&self) -> usize {
        let grid = self.keyframes.first().map_or(0, |k| k.inv_depth.data.len());
        HEADER_BYTES
            + self
                .keyframes
                .iter()
                .map(|k| KEYFRAME_HEADER_BYTES + 4 * grid * (1 + k.has_variance as usize))
                .sum::<usize>()
    }

    /// Encodes into `out` (cleared first). Every keyframe must have the grid size of the first.
    pub fn encode(&self, out: &mut Vec<u8>) -> Result<(), WindowError> {
        let (w, h) = self
            .keyframes
            .first()
            .map_or((0, 0), |k| (k.inv_depth.width, k.inv_depth.height));
        for k in &self.keyframes {
            let planes = std::iter::once(&k.inv_depth).chain(k.variance());
            if planes
                .into_iter()
                .any(|p| p.width != w || p.height != h || p.data.len() != w * h)
            {
                return Err(WindowError::GridMismatch { id: k.id, width: w, height: h });
            }
        }
        out.clear();
        out.reserve(self.encoded_len());
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&VERSION.to_le_bytes());
        out.extend_from_slice(&self.seq.to_le_bytes());
        out.extend_from_slice(&self.t_ns.t_ns().to_le_bytes());
        for v in [self.keyframes.len(), w, h] {
            out.extend_from_slice(&(v as u32).to_le_bytes());
        }
        for k in &self.keyframes {
            out.extend_from_slice(&k.id.to_le_bytes());
            out.extend_from_slice(&k.seq.to_le_bytes());
            out.extend_from_slice(&k.t_ns.t_ns().to_le_bytes());
            for v in duv_core::pose::se3_to_tum(&k.world_from_cam) {
                out.extend_from_slice(&v.to_le_bytes());
            }
            out.push(k.has_variance as u8);
            for p in std::iter::once(&k.inv_depth).chain(k.variance()) {
                for x in &p.data {
                    out.extend_from_slice(&x.to_le_bytes());
                }
            }
        }
        Ok(())
    }

    /// Decodes a body; the error says what is wrong with it. Sizes are checked against the
    /// body before anything is allocated, so a damaged message cannot ask for more memory
    /// than it holds.
    /// A `duv_msgs/msg/TrackerWindow` (CDR, the ROS 2 format) is unwrapped first.
    pub fn decode(data: &[u8]) -> Result<TrackerWindow, WindowError> {
        let data = if crate::cdr::is_cdr(data) { crate::cdr::decode_wrapped(data)? } else { data };
        let mut r = LeReader::new(data);
        if r.take(4)? != MAGIC {
            return Err(WindowError::BadMagic);
        }
        let version = r.u32()?;
        if version != VERSION {
            return Err(WindowError::UnsupportedVersion { found: version });
        }
        let seq = r.u64()?;
        let t_ns = Timestamp::from_ns(r.i64()?);
        let (n, w, h) = (r.u32()? as usize, r.u32()? as usize, r.u32()? as usize);
        let grid = w.checked_mul(h).ok_or(WindowError::GridOverflow { width: w, height: h })?;
        if n.saturating_mul(KEYFRAME_HEADER_BYTES.saturating_add(grid.saturating_mul(4))) > data.len() {
            return Err(WindowError::TooManyKeyframes { count: n, width: w, height: h, bytes: data.len() });
        }
        let mut keyframes = Vec::with_capacity(n);
        for _ in 0..n {
            let id = r.u64()?;
            let kf_seq = r.u64()?;
            let kf_t = Timestamp::from_ns(r.i64()?);
            let mut tum = [0.0f64; 7];
            for v in tum.iter_mut() {
                *v = r.f64()?;
            }
            let world_from_cam = duv_core::pose::se3_from_tum(tum)
                .map_err(|source| WindowError::BadPose { id, source })?;
            let has_variance = match r.u8()? {
                0 => false,
                1 => true,
                flag => return Err(WindowError::BadVarianceFlag { id, flag }),
            };
            let mut plane = || -> Result<PlaneF32, LeError> {
                let bytes = r.take(4 * grid)?;
                let mut p = PlaneF32::new(w, h);
                for (x, b) in p.data.iter_mut().zip(bytes.chunks_exact(4)) {
                    *x = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
                }
                Ok(p)
            };
            let inv_depth = plane()?;
            let variance = if has_variance { plane()? } else { PlaneF32::new(0, 0) };
            keyframes.push(WindowKeyframe {
                id,
                seq: kf_seq,
                t_ns: kf_t,
                world_from_cam,
                inv_depth,
                variance,
                has_variance,
            });
        }
        if r.remaining() != 0 {
            return Err(WindowError::TrailingBytes { bytes: r.remaining() });
        }
        Ok(TrackerWindow {
            seq,
            t_ns,
            keyframes,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    fn window() -> TrackerWindow {
        let kf = |id: u64, var: bool| {
            let mut inv = PlaneF32::new(5, 3);
            inv.data
                .iter_mut()
                .enumerate()
                .for_each(|(i, x)| *x = 0.1 + i as f32 * 0.01 + id as f32);
            let mut variance = PlaneF32::new(5, 3);
            variance
                .data
                .iter_mut()
                .enumerate()
                .for_each(|(i, x)| *x = 1e-3 * (i + 1) as f32);
            WindowKeyframe {
                id,
                seq: 10 * id + 3,
                t_ns: Timestamp::from_ns(1_000_000 * id as i64),
                world_from_cam: Se3::from_parts(
                    Translation3::new(id as f64, -0.5, 2.0),
                    UnitQuaternion::from_euler_angles(0.1, -0.2, 0.3 * id as f64),
                ),
                inv_depth: inv,
                variance,
                has_variance: var,
            }
        };
        TrackerWindow {
            seq: 77,
            t_ns: Timestamp::from_ns(7_700_000),
            keyframes: vec![kf(4, true), kf(5, true), kf(7, false)],
        }
    }

    #[test]
    fn round_trip_keeps_every_field() {
        let w = window();
        let mut body = Vec::new();
        w.encode(&mut body).unwrap();
        assert_eq!(body.len(), w.encoded_len());
        // 3 keyframes of 15 cells: 5 planes of 60 bytes, keyframe headers of 81 bytes, 36 bytes of header.
        assert_eq!(body.len(), 36 + 3 * 81 + 5 * 60);
        let back = TrackerWindow::decode(&body).unwrap();
        assert_eq!(back.seq, 77);
        assert_eq!(back.keyframes.len(), 3);
        for (a, b) in w.keyframes.iter().zip(&back.keyframes) {
            assert_eq!((a.id, a.seq, a.t_ns), (b.id, b.seq, b.t_ns));
            assert_eq!(a.inv_depth, b.inv_depth);
            assert_eq!(a.variance(), b.variance());
            let d = a.world_from_cam.inv_mul(&b.world_from_cam);
            assert!(d.translation.vector.norm() < 1e-12 && d.rotation.angle() < 1e-12);
        }
    }

    #[test]
    fn damaged_bodies_are_refused_with_the_reason() {
        let mut body = Vec::new();
        window().encode(&mut body).unwrap();
        let truncated = TrackerWindow::decode(&body[..body.len() - 7]).unwrap_err().to_string();
        assert!(truncated.contains("truncated"), "{truncated}");
        let mut huge = body.clone();
        huge[24..28].copy_from_slice(&u32::MAX.to_le_bytes());
        let e = TrackerWindow::decode(&huge).unwrap_err().to_string();
        assert!(e.contains("do not fit"), "{e}");
        let mut flag = body.clone();
        flag[36 + 80] = 9;
        assert!(TrackerWindow::decode(&flag)
            .unwrap_err()
            .to_string()
            .contains("variance flag 9"));
        assert!(TrackerWindow::decode(b"JUNKJUNK")
            .unwrap_err()
            .to_string()
            .contains("magic"));
        let mut longer = body;
        longer.push(0);
        assert!(TrackerWindow::decode(&longer)
            .unwrap_err()
            .to_string()
            .contains("after the last keyframe"));
    }

    #[test]
    fn keyframes_of_different_grids_are_not_encoded() {
        let mut w = window();
        w.keyframes[1].inv_depth = PlaneF32::new(4, 3);
        assert!(w
            .encode(&mut Vec::new())
            .unwrap_err()
            .to_string()
            .contains("keyframe 5"));
    }
}
