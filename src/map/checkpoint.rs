//! Map checkpoints: the complete mapper state (Gaussians, densification statistics, medium
//! weights, the Adam moments and step counts of every group, the keyframes, the iteration
//! count and the RNG state), so that a restored mapper renders bit-identically and runs the
//! same next iteration.
//!
//! # File format (version [`CHECKPOINT_VERSION`])
//! ```text
//! bytes 0..8     magic "DUVMAPCK"
//! bytes 8..12    format version, u32 little endian
//! bytes 12..20   payload length n, u64 little endian
//! bytes 20..20+n payload: UTF-8 JSON (the `Payload` struct below)
//! last 8 bytes   FNV-1a 64 checksum of the payload, u64 little endian
//! ```
//! Floats in the payload are stored as their IEEE-754 bit patterns (`f32::to_bits`,
//! `f64::to_bits`), so nothing is lost in decimal; the config is embedded as TOML text. The
//! file is written through a temporary sibling, fsync and rename ([`write_atomic`]).

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::gaussians::ParamGroup;
use super::mapper::{Mapper, MapperCapacity, MapperConfig, MapperError};
use super::medium::{MediumCheckpoint, MediumNet, MEDIUM_CHECKPOINT_VERSION};
use crate::core::rng::Rng;
use crate::core::{ImageRgb8, Keyframe, PinholeCamera, PlaneF32, Se3, Timestamp};
use crate::io::{write_atomic, IoError};

/// File magic.
pub const CHECKPOINT_MAGIC: &[u8; 8] = b"DUVMAPCK";
/// Format version this build writes and reads.
pub const CHECKPOINT_VERSION: u32 = 1;

/// Why a checkpoint could not be written or read.
#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    #[error(transparent)]
    Io(#[from] IoError),
    #[error("{path}: not a map checkpoint (bad magic)")]
    BadMagic { path: String },
    #[error("{path}: checkpoint version {found}, this build reads {expected}")]
    UnsupportedVersion { path: String, found: u32, expected: u32 },
    #[error("{path}: truncated checkpoint ({len} bytes, header says {expected})")]
    Truncated { path: String, len: usize, expected: usize },
    #[error("{path}: checksum mismatch (saved {saved:016x}, calculated {calculated:016x})")]
    BadChecksum { path: String, saved: u64, calculated: u64 },
    #[error("{path}: payload: {why}")]
    BadPayload { path: String, why: String },
    #[error("restoring the mapper: {0}")]
    Mapper(#[from] MapperError),
}

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct AdamRecord {
    steps: u64,
    m: Vec<u32>,
    v: Vec<u32>,
}

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct KeyframeRecord {
    index: u64,
    t_ns: i64,
    width: usize,
    height: usize,
    /// fx, fy, cx, cy as f64 bits.
    intrinsics: [u64; 4],
    /// Translation x y z as f64 bits.
    translation: [u64; 3],
    /// Rotation quaternion x y z w as f64 bits.
    rotation_xyzw: [u64; 4],
    image: Vec<u8>,
    inv_depth: Vec<u32>,
    inv_depth_variance: Vec<u32>,
}

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Payload {
    config_toml: String,
    capacity: MapperCapacity,
    iteration: u64,
    rng_state: [u64; 4],
    /// Per [`ParamGroup::ALL`] entry, the live values as f32 bits.
    gaussians: Vec<Vec<u32>>,
    densify_grad_norm: Vec<u32>,
    pixels_touched: Vec<u32>,
    views: Vec<u32>,
    adam: Vec<AdamRecord>,
    medium_pe_frequencies: usize,
    medium_params: Vec<u32>,
    medium_adam: AdamRecord,
    keyframes: Vec<KeyframeRecord>,
}

/// FNV-1a, 64 bit.
pub fn fnv1a64(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in bytes {
        h ^= b as u64;
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}
fn floats(v: &[u32]) -> Vec<f32> {
    v.iter().map(|&x| f32::from_bits(x)).collect()
}

fn adam_record(g: &super::adam::AdamGroup) -> AdamRecord {
    let (m, v) = g.moments();
    AdamRecord { steps: g.steps(), m: bits(m), v: bits(v) }
}

impl Mapper {
    /// Writes the complete state to `path` (temporary file, fsync, rename).
    pub fn save_checkpoint(&self, path: &Path) -> Result<(), CheckpointError> {
        let bad = |why: String| CheckpointError::BadPayload { path: path.display().to_string(), why };
        let payload = Payload {
            config_toml: toml::to_string(&self.config).map_err(|e| bad(e.to_string()))?,
            capacity: self.capacity,
            iteration: self.iteration,
            rng_state: self.rng.state(),
            gaussians: ParamGroup::ALL.iter().map(|&g| bits(self.gaussians.group(g))).collect(),
            densify_grad_norm: bits(self.grads.densify_grad_norm()),
            pixels_touched: self.grads.pixels_touched().to_vec(),
            views: self.grads.views().to_vec(),
            adam: self.adam.iter().map(adam_record).collect(),
            medium_pe_frequencies: self.medium.pe_frequencies(),
            medium_params: bits(self.medium.params()),
            medium_adam: adam_record(&self.medium_adam),
            keyframes: self
                .keyframes
                .iter()
                .map(|k| {
                    let kf = &k.kf;
                    let q = kf.world_from_cam.rotation.coords;
                    let t = kf.world_from_cam.translation.vector;
                    KeyframeRecord {
                        index: kf.index,
                        t_ns: kf.t_ns.t_ns(),
                        width: kf.camera.width,
                        height: kf.camera.height,
                        intrinsics: [kf.camera.fx, kf.camera.fy, kf.camera.cx, kf.camera.cy].map(f64::to_bits),
                        translation: [t.x, t.y, t.z].map(f64::to_bits),
                        rotation_xyzw: [q.x, q.y, q.z, q.w].map(f64::to_bits),
                        image: kf.image.data.clone(),
                        inv_depth: bits(&kf.inv_depth.data),
                        inv_depth_variance: bits(&kf.inv_depth_variance.data),
                    }
                })
                .collect(),
        };
        let json = serde_json::to_vec(&payload).map_err(|e| bad(e.to_string()))?;
        let mut bytes = Vec::with_capacity(json.len() + 28);
        bytes.extend_from_slice(CHECKPOINT_MAGIC);
        bytes.extend_from_slice(&CHECKPOINT_VERSION.to_le_bytes());
        bytes.extend_from_slice(&(json.len() as u64).to_le_bytes());
        bytes.extend_from_slice(&json);
        bytes.extend_from_slice(&fnv1a64(&json).to_le_bytes());
        write_atomic(path, &bytes)?;
        Ok(())
    }

    /// Reads a checkpoint written by [`Mapper::save_checkpoint`], checking magic, version,
    /// length and checksum, and rebuilds the mapper.
    pub fn load_checkpoint(path: &Path) -> Result<Mapper, CheckpointError> {
        let p = path.display().to_string();
        let bytes = std::fs::read(path).map_err(|e| IoError::file(path, e))?;
        if bytes.len() < 20 || &bytes[..8] != CHECKPOINT_MAGIC {
            return Err(CheckpointError::BadMagic { path: p });
        }
        let version = u32::from_le_bytes(bytes[8..12].try_into().unwrap_or([0; 4]));
        if version != CHECKPOINT_VERSION {
            return Err(CheckpointError::UnsupportedVersion { path: p, found: version, expected: CHECKPOINT_VERSION });
        }
        let n = u64::from_le_bytes(bytes[12..20].try_into().unwrap_or([0; 8])) as usize;
        let expected = 20usize.saturating_add(n).saturating_add(8);
        if bytes.len() != expected {
            return Err(CheckpointError::Truncated { path: p, len: bytes.len(), expected });
        }
        let json = &bytes[20..20 + n];
        let saved = u64::from_le_bytes(bytes[20 + n..].try_into().unwrap_or([0; 8]));
        let calculated = fnv1a64(json);
        if saved != calculated {
            return Err(CheckpointError::BadChecksum { path: p, saved, calculated });
        }
        let bad = |why: String| CheckpointError::BadPayload { path: p.clone(), why };
        let payload: Payload = serde_json::from_slice(json).map_err(|e| bad(e.to_string()))?;
        let config: MapperConfig = toml::from_str(&payload.config_toml).map_err(|e| bad(e.to_string()))?;
        let mut m = Mapper::new(config, payload.capacity)?;
        if payload.gaussians.len() != ParamGroup::ALL.len() || payload.adam.len() != ParamGroup::ALL.len() {
            return Err(bad("wrong number of parameter groups".into()));
        }
        let len = payload.gaussians[0].len() / 3;
        if len > payload.capacity.max_gaussians {
            return Err(bad(format!("{len} Gaussians exceed the capacity {}", payload.capacity.max_gaussians)));
        }
        for (k, g) in ParamGroup::ALL.iter().enumerate() {
            if payload.gaussians[k].len() != len * g.width() {
                return Err(bad(format!("group {} has {} values, expected {}", g.name(), payload.gaussians[k].len(), len * g.width())));
            }
        }
        m.gaussians.clear();
        for i in 0..len {
            let mut a = [0.0f32; super::gaussians::PARAMS_PER_GAUSSIAN];
            for (k, g) in ParamGroup::ALL.iter().enumerate() {
                let w = g.width();
                for j in 0..w {
                    a[g.offset() + j] = f32::from_bits(payload.gaussians[k][i * w + j]);
                }
            }
            m.gaussians.push(&super::gaussians::GaussianParam::from_array(&a)).map_err(MapperError::from)?;
        }
        for (k, rec) in payload.adam.iter().enumerate() {
            m.adam[k].set_state(rec.steps, &floats(&rec.m), &floats(&rec.v)).map_err(MapperError::from)?;
            if m.adam[k].len() != len {
                return Err(bad(format!("Adam group {k} holds {} items, the map {len}", m.adam[k].len())));
            }
        }
        m.grads.reset(len).map_err(MapperError::from)?;
        m.grads
            .set_densify_stats(&floats(&payload.densify_grad_norm), &payload.pixels_touched, &payload.views)
            .map_err(MapperError::from)?;
        m.medium = MediumNet::from_checkpoint(&MediumCheckpoint {
            schema_version: MEDIUM_CHECKPOINT_VERSION,
            pe_frequencies: payload.medium_pe_frequencies,
            params: floats(&payload.medium_params),
        })
        .map_err(MapperError::from)?;
        let ma = &payload.medium_adam;
        m.medium_adam.set_state(ma.steps, &floats(&ma.m), &floats(&ma.v)).map_err(MapperError::from)?;
        for r in &payload.keyframes {
            let [fx, fy, cx, cy] = r.intrinsics.map(f64::from_bits);
            let camera = PinholeCamera { fx, fy, cx, cy, width: r.width, height: r.height, distortion: None };
            let [tx, ty, tz] = r.translation.map(f64::from_bits);
            let [qx, qy, qz, qw] = r.rotation_xyzw.map(f64::from_bits);
            let rotation = nalgebra::UnitQuaternion::new_unchecked(nalgebra::Quaternion::new(qw, qx, qy, qz));
            let world_from_cam = Se3::from_parts(nalgebra::Translation3::new(tx, ty, tz), rotation);
            let image = ImageRgb8::from_vec(r.width, r.height, r.image.clone()).ok_or_else(|| bad(format!("keyframe {}: image size", r.index)))?;
            let inv_depth = PlaneF32::from_vec(r.width, r.height, floats(&r.inv_depth)).ok_or_else(|| bad(format!("keyframe {}: depth size", r.index)))?;
            let inv_depth_variance =
                PlaneF32::from_vec(r.width, r.height, floats(&r.inv_depth_variance)).ok_or_else(|| bad(format!("keyframe {}: variance size", r.index)))?;
            let kf = Keyframe { index: r.index, t_ns: Timestamp(r.t_ns), image, world_from_cam, camera, inv_depth, inv_depth_variance };
            if !kf.is_consistent() {
                return Err(bad(format!("keyframe {}: inconsistent sizes", r.index)));
            }
            m.push_restored_keyframe(&kf);
        }
        m.iteration = payload.iteration;
        m.rng = Rng::from_state(payload.rng_state);
        Ok(m)
    }
}
