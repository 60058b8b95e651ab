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
//! bytes 20..20+n payload
//! last 8 bytes   FNV-1a 64 checksum of the payload, u64 little endian
//! ```
//! Version 5 (written) is version 4 with each channel's flag of the medium prior a bit mask
//! of the coefficients it holds ([`super::medium_estimate::Coefficients::bits`]: 1 `beta_D`,
//! 2 `beta_B`, 4 `B_inf`); a version 3 or 4 flag of 1 holds all three.
//! Version 4 (still read) is version 3 followed by the Gaussians' footprints
//! ([`super::gaussians::GaussianGrads::fold_footprint`]: what the seeding of a full map
//! evicts by) as a u64 count and f32 values; older versions restore them as 0.
//! Version 3 (still read) is version 2 followed by the medium estimate's state (the keyframe count
//! of the next estimate and the prior that holds the medium near the accepted one: a u64 count,
//! 0 or 17, then channels as 0/1 and the prior's numbers as f64 bits). Version 2 (still read): a binary payload, little endian, in the order of the `Payload` struct
//! below: the config as TOML text, then numbers as u64 / f64 and arrays as a u64 count followed
//! by their f32 (or u32, u8) values, so a float takes its 4 bytes and nothing is lost. It is
//! written straight from the mapper's buffers into one buffer of its exact size
//! ([`Mapper::checkpoint_bytes`]). Version 1 (still read): the same fields as UTF-8 JSON with
//! floats as their bit patterns in decimal, about 2.7 times larger. The file is written through
//! a temporary sibling, fsync and rename ([`write_atomic`]).
//!
//! A checkpoint carries its keyframes' pixels ([`KeyframePixels::Embedded`], the files a resume
//! reads) or only each keyframe's index, time, camera and the mapper's pose for it
//! ([`KeyframePixels::Referenced`], the same layout with empty image, depth and variance
//! arrays). The log stores the second kind: the pixels are already the keyframes' own
//! `/keyframe/*` messages, and without them a map at the board's caps fits the log queue (a
//! 50k-Gaussian, 64-keyframe map at 320x240: 15 MB instead of 68.6 MB). Restoring one needs
//! those keyframes back ([`RestoreOptions::keyframes`], matched by time stamp and size).
//! A referenced checkpoint also leaves out the Gaussians' Adam moments (empty arrays, the step
//! counts kept; two thirds of a map's bytes): restored, it is the same map and renders the same,
//! and its optimiser starts again from zero moments, so its next iteration is not the stopped
//! run's. (Resume reads the embedded files in `checkpoints/`, which keep everything.)

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::gaussians::ParamGroup;
use super::mapper::{Mapper, MapperCapacity, MapperConfig, MapperError};
use super::medium::{MediumCheckpoint, MediumNet, MEDIUM_CHECKPOINT_VERSION};
use super::medium_estimate::{Coefficients, MediumPrior};
use duv_core::rng::Rng;
use duv_core::{ImageRgb8, Keyframe, MediumParams, PinholeCamera, PlaneF32, Se3, Timestamp};
use duv_core::io::le::{LeError, LeReader};
use duv_core::io::{write_atomic, IoError};

/// File magic.
pub const CHECKPOINT_MAGIC: &[u8; 8] = b"DUVMAPCK";
/// Format version this build writes (it reads this and versions 4, 3, 2 and 1).
pub const CHECKPOINT_VERSION: u32 = 5;
/// The binary format whose medium prior holds whole channels.
const CHECKPOINT_VERSION_CHANNEL_PRIOR: u32 = 4;
/// The binary format without the Gaussians' footprints.
const CHECKPOINT_VERSION_NO_FOOTPRINT: u32 = 3;
/// The binary format without the medium estimate's state.
const CHECKPOINT_VERSION_NO_MEDIUM_STATE: u32 = 2;
/// The JSON format of the first builds.
const CHECKPOINT_VERSION_JSON: u32 = 1;

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
    /// A binary payload that does not read back (damaged, or written by a broken build).
    #[error("{path}: payload: {source}")]
    Payload { path: String, source: PayloadError },
    #[error("restoring the mapper: {0}")]
    Mapper(#[from] MapperError),
    /// The mapper's state could not be encoded ([`Mapper::checkpoint_bytes`]).
    #[error("{path}: {source}")]
    Encode { path: String, source: EncodeError },
}

/// Why a checkpoint could not be made from the mapper ([`Mapper::checkpoint_bytes`]).
#[derive(Debug, thiserror::Error)]
pub enum EncodeError {
    #[error("syncing the optimiser state from the device: {0}")]
    Device(#[from] MapperError),
    #[error("encoding the mapper config as TOML: {0}")]
    Config(#[from] toml::ser::Error),
}

/// What is wrong inside a binary payload ([`CheckpointError::Payload`]).
#[derive(Debug, thiserror::Error)]
pub enum PayloadError {
    /// The payload ends early or claims an array it does not hold.
    #[error(transparent)]
    Read(#[from] LeError),
    #[error("size {value} does not fit in usize")]
    Size { value: u64 },
    #[error("config: {0}")]
    ConfigText(#[from] std::string::FromUtf8Error),
    #[error("medium prior channel flag {flag} is not a mask of 3 coefficients")]
    PriorFlag { flag: u64 },
    #[error("medium prior has {found} values, expected 0 or {PRIOR_WORDS}")]
    PriorLength { found: usize },
    #[error("{bytes} bytes after the last keyframe")]
    TrailingBytes { bytes: usize },
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
    /// Version 3 on; absent in older checkpoints.
    #[serde(default)]
    medium_state: Option<MediumStateRecord>,
    /// Version 4 on (f32 bits, one per Gaussian); empty in older checkpoints.
    #[serde(default)]
    footprint: Vec<u32>,
}

/// Number of u64 in a stored [`MediumPrior`]: 3 channel masks, 9 coefficients, weight and two stds.
const PRIOR_WORDS: usize = 15;

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct MediumStateRecord {
    estimate_at: u64,
    /// Empty (no prior) or [`PRIOR_WORDS`] values: per channel the held coefficients' mask, then `beta_D`, `beta_B`,
    /// `B_inf` (R G B each), weight, rel_std, b_inf_std as f64 bits.
    prior: Vec<u64>,
}

impl MediumStateRecord {
    fn of(m: &Mapper) -> Self {
        let prior = match &m.medium_prior {
            None => Vec::new(),
            Some(p) => {
                let mut v: Vec<u64> = p.held.iter().map(|h| h.bits() as u64).collect();
                let md = &p.medium;
                v.extend(md.beta_d.iter().chain(&md.beta_b).chain(&md.b_inf).chain(&[p.weight, p.rel_std, p.b_inf_std]).map(|x| x.to_bits()));
                v
            }
        };
        MediumStateRecord { estimate_at: m.medium_estimate_at as u64, prior }
    }
    fn prior(&self, version: u32) -> Result<Option<MediumPrior>, PayloadError> {
        let held_of = |flag: u64| match (version <= CHECKPOINT_VERSION_CHANNEL_PRIOR, flag) {
            (true, 0) => Ok(Coefficients::NONE),
            (true, _) => Ok(Coefficients::ALL),
            (false, 0..=7) => Ok(Coefficients::from_bits(flag as u32)),
            (false, _) => Err(PayloadError::PriorFlag { flag }),
        };
        match self.prior.len() {
            0 => Ok(None),
            PRIOR_WORDS => {
                let f = |i: usize| f64::from_bits(self.prior[i]);
                let three = |i: usize| [f(i), f(i + 1), f(i + 2)];
                Ok(Some(MediumPrior {
                    held: [held_of(self.prior[0])?, held_of(self.prior[1])?, held_of(self.prior[2])?],
                    medium: MediumParams { beta_d: three(3), beta_b: three(6), b_inf: three(9) },
                    weight: f(12),
                    rel_std: f(13),
                    b_inf_std: f(14),
                }))
            }
            found => Err(PayloadError::PriorLength { found }),
        }
    }
}

/// Whether a checkpoint holds its keyframes' pixels or refers to them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum KeyframePixels {
    /// Image, inverse depth and variance in the checkpoint (the files a resume reads).
    Embedded,
    /// Index, time, camera and pose only; the pixels are the keyframes' own log messages.
    Referenced,
}

/// How [`Mapper::from_checkpoint_bytes`] rebuilds a mapper.
#[derive(Clone, Copy, Default)]
pub struct RestoreOptions<'a> {
    /// Where the pixels of referenced keyframes come from (e.g. the log's keyframes),
    /// matched by time stamp and size; the checkpoint's index and pose are kept.
    pub keyframes: &'a [Keyframe],
    /// At least this capacity (offshore refinement with a higher Gaussian cap): the Gaussian
    /// and keyframe caps are the larger of this and the checkpoint's; the image size must be
    /// the checkpoint's.
    pub capacity: Option<MapperCapacity>,
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

fn floats(v: &[u32]) -> Vec<f32> {
    v.iter().map(|&x| f32::from_bits(x)).collect()
}

fn put_u64(w: &mut Vec<u8>, v: u64) {
    w.extend_from_slice(&v.to_le_bytes());
}
fn put_bytes(w: &mut Vec<u8>, v: &[u8]) {
    put_u64(w, v.len() as u64);
    w.extend_from_slice(v);
}
fn put_f32s(w: &mut Vec<u8>, v: &[f32]) {
    put_u64(w, v.len() as u64);
    for x in v {
        w.extend_from_slice(&x.to_le_bytes());
    }
}
fn put_u32s(w: &mut Vec<u8>, v: &[u32]) {
    put_u64(w, v.len() as u64);
    for x in v {
        w.extend_from_slice(&x.to_le_bytes());
    }
}
fn put_adam(w: &mut Vec<u8>, g: &super::adam::AdamGroup) {
    let (m, v) = g.moments();
    put_u64(w, g.steps());
    put_f32s(w, m);
    put_f32s(w, v);
}

/// Reads a version 2, 3, 4 or 5 payload; every count is checked against the bytes left before anything
/// is allocated, so a damaged file cannot ask for more memory than it holds.
fn decode_binary(body: &[u8], version: u32) -> Result<Payload, PayloadError> {
    let mut r = LeReader::new(body);
    let size = |r: &mut LeReader<'_>| -> Result<usize, PayloadError> {
        let value = r.u64()?;
        usize::try_from(value).map_err(|_| PayloadError::Size { value })
    };
    let bytes = |r: &mut LeReader<'_>| -> Result<Vec<u8>, LeError> {
        let n = r.count(1)?;
        Ok(r.take(n)?.to_vec())
    };
    let words = |r: &mut LeReader<'_>| -> Result<Vec<u32>, LeError> {
        let n = r.count(4)?;
        Ok(r.words(n)?.collect())
    };
    let adam_of = |r: &mut LeReader<'_>| -> Result<AdamRecord, LeError> { Ok(AdamRecord { steps: r.u64()?, m: words(r)?, v: words(r)? }) };
    let config_toml = String::from_utf8(bytes(&mut r)?)?;
    let capacity = MapperCapacity { max_gaussians: size(&mut r)?, max_keyframes: size(&mut r)?, width: size(&mut r)?, height: size(&mut r)? };
    let iteration = r.u64()?;
    let rng_state = [r.u64()?, r.u64()?, r.u64()?, r.u64()?];
    let gaussians = ParamGroup::ALL.iter().map(|_| words(&mut r)).collect::<Result<Vec<_>, _>>()?;
    let densify_grad_norm = words(&mut r)?;
    let pixels_touched = words(&mut r)?;
    let views = words(&mut r)?;
    let adam = ParamGroup::ALL.iter().map(|_| adam_of(&mut r)).collect::<Result<Vec<_>, _>>()?;
    let medium_pe_frequencies = size(&mut r)?;
    let medium_params = words(&mut r)?;
    let medium_adam = adam_of(&mut r)?;
    let n = r.count(15 * 8)?;
    let mut keyframes = Vec::with_capacity(n);
    for _ in 0..n {
        let index = r.u64()?;
        let t_ns = r.u64()? as i64;
        let (width, height) = (size(&mut r)?, size(&mut r)?);
        let mut v = [0u64; 11];
        for x in v.iter_mut() {
            *x = r.u64()?;
        }
        keyframes.push(KeyframeRecord {
            index,
            t_ns,
            width,
            height,
            intrinsics: [v[0], v[1], v[2], v[3]],
            translation: [v[4], v[5], v[6]],
            rotation_xyzw: [v[7], v[8], v[9], v[10]],
            image: bytes(&mut r)?,
            inv_depth: words(&mut r)?,
            inv_depth_variance: words(&mut r)?,
        });
    }
    let medium_state = if version > CHECKPOINT_VERSION_NO_MEDIUM_STATE {
        let estimate_at = r.u64()?;
        let n = r.count(8)?;
        Some(MediumStateRecord { estimate_at, prior: (0..n).map(|_| r.u64()).collect::<Result<_, _>>()? })
    } else {
        None
    };
    let footprint = if version > CHECKPOINT_VERSION_NO_FOOTPRINT { words(&mut r)? } else { Vec::new() };
    if r.remaining() != 0 {
        return Err(PayloadError::TrailingBytes { bytes: r.remaining() });
    }
    Ok(Payload { config_toml, capacity, iteration, rng_state, gaussians, densify_grad_norm, pixels_touched, views, adam, medium_pe_frequencies, medium_params, medium_adam, keyframes, medium_state, footprint })
}

impl Mapper {
    /// Writes the complete state to `path` (temporary file, fsync, rename).
    pub fn save_checkpoint(&mut self, path: &Path) -> Result<(), CheckpointError> {
        let bytes = self.checkpoint_bytes().map_err(|source| CheckpointError::Encode { path: path.display().to_string(), source })?;
        write_atomic(path, &bytes)?;
        Ok(())
    }

    /// The complete state as checkpoint file bytes (header, binary payload, checksum), written
    /// from the mapper's buffers into one buffer of the exact size.
    pub fn checkpoint_bytes(&mut self) -> Result<Vec<u8>, EncodeError> {
        self.checkpoint_bytes_with(KeyframePixels::Embedded)
    }

    /// [`Mapper::checkpoint_bytes`] with the keyframes' pixels embedded or referenced (the
    /// device's optimiser state is synced first, [`Mapper::sync_from_device`]).
    pub fn checkpoint_bytes_with(&mut self, pixels: KeyframePixels) -> Result<Vec<u8>, EncodeError> {
        self.sync_from_device()?;
        let embed = pixels == KeyframePixels::Embedded;
        let config_toml = toml::to_string(&self.config)?;
        let kf_bytes: usize = self
            .keyframes
            .iter()
            .map(|k| 8 * 15 + 8 + 16 + if embed { k.kf.image.data.len() + 4 * (k.kf.inv_depth.data.len() + k.kf.inv_depth_variance.data.len()) } else { 0 })
            .sum();
        let groups: usize = ParamGroup::ALL.iter().map(|&g| 8 + 4 * self.gaussians.group(g).len()).sum();
        let adam: usize = self.adam.iter().map(|a| 24 + if embed { 8 * a.moments().0.len() } else { 0 }).sum::<usize>() + 24 + 8 * self.medium_adam.moments().0.len();
        let n = self.grads.densify_grad_norm().len();
        let medium_state = MediumStateRecord::of(self);
        let payload_len = 8 + config_toml.len() + 32 + 8 + 32 + groups + 3 * 8 + 12 * n + adam + 8 + 8 + 4 * self.medium.params().len() + 8 + kf_bytes + 16 + 8 * medium_state.prior.len() + 8 + 4 * n;
        let mut out = Vec::with_capacity(20 + payload_len + 8);
        out.extend_from_slice(CHECKPOINT_MAGIC);
        out.extend_from_slice(&CHECKPOINT_VERSION.to_le_bytes());
        out.extend_from_slice(&0u64.to_le_bytes());
        let w = &mut out;
        put_bytes(w, config_toml.as_bytes());
        let c = self.capacity;
        for v in [c.max_gaussians, c.max_keyframes, c.width, c.height] {
            put_u64(w, v as u64);
        }
        put_u64(w, self.iteration);
        for v in self.rng.state() {
            put_u64(w, v);
        }
        for &g in ParamGroup::ALL.iter() {
            put_f32s(w, self.gaussians.group(g));
        }
        put_f32s(w, self.grads.densify_grad_norm());
        put_u32s(w, self.grads.pixels_touched());
        put_u32s(w, self.grads.views());
        for a in &self.adam {
            if embed {
                put_adam(w, a);
            } else {
                put_u64(w, a.steps());
                put_f32s(w, &[]);
                put_f32s(w, &[]);
            }
        }
        put_u64(w, self.medium.pe_frequencies() as u64);
        put_f32s(w, self.medium.params());
        put_adam(w, &self.medium_adam);
        put_u64(w, self.keyframes.len() as u64);
        for k in &self.keyframes {
            let kf = &k.kf;
            let q = kf.world_from_cam.rotation.coords;
            let t = kf.world_from_cam.translation.vector;
            put_u64(w, kf.index);
            put_u64(w, kf.t_ns.t_ns() as u64);
            put_u64(w, kf.camera.width as u64);
            put_u64(w, kf.camera.height as u64);
            for v in [kf.camera.fx, kf.camera.fy, kf.camera.cx, kf.camera.cy, t.x, t.y, t.z, q.x, q.y, q.z, q.w] {
                put_u64(w, v.to_bits());
            }
            if embed {
                put_bytes(w, &kf.image.data);
                put_f32s(w, &kf.inv_depth.data);
                put_f32s(w, &kf.inv_depth_variance.data);
            } else {
                put_bytes(w, &[]);
                put_f32s(w, &[]);
                put_f32s(w, &[]);
            }
        }
        put_u64(w, medium_state.estimate_at);
        put_u64(w, medium_state.prior.len() as u64);
        for &v in &medium_state.prior {
            put_u64(w, v);
        }
        put_f32s(w, self.grads.footprint());
        debug_assert_eq!(out.len(), 20 + payload_len, "checkpoint size computed wrongly");
        let n = out.len() - 20;
        out[12..20].copy_from_slice(&(n as u64).to_le_bytes());
        let sum = fnv1a64(&out[20..]);
        out.extend_from_slice(&sum.to_le_bytes());
        Ok(out)
    }

    /// Reads a checkpoint written by [`Mapper::save_checkpoint`], checking magic, version,
    /// length and checksum, and rebuilds the mapper.
    pub fn load_checkpoint(path: &Path) -> Result<Mapper, CheckpointError> {
        let bytes = std::fs::read(path).map_err(|e| IoError::file(path, e))?;
        Mapper::from_checkpoint_bytes(&bytes, &path.display().to_string(), RestoreOptions::default())
    }

    /// Rebuilds a mapper from checkpoint bytes (`what` names them in errors), checking magic,
    /// version, length and checksum; referenced keyframes are taken from `options.keyframes`.
    pub fn from_checkpoint_bytes(bytes: &[u8], what: &str, options: RestoreOptions<'_>) -> Result<Mapper, CheckpointError> {
        let p = what.to_string();
        if bytes.len() < 20 || &bytes[..8] != CHECKPOINT_MAGIC {
            return Err(CheckpointError::BadMagic { path: p });
        }
        let version = u32::from_le_bytes(bytes[8..12].try_into().unwrap_or([0; 4]));
        if ![CHECKPOINT_VERSION, CHECKPOINT_VERSION_CHANNEL_PRIOR, CHECKPOINT_VERSION_NO_FOOTPRINT, CHECKPOINT_VERSION_NO_MEDIUM_STATE, CHECKPOINT_VERSION_JSON].contains(&version) {
            return Err(CheckpointError::UnsupportedVersion { path: p, found: version, expected: CHECKPOINT_VERSION });
        }
        let n = u64::from_le_bytes(bytes[12..20].try_into().unwrap_or([0; 8])) as usize;
        let expected = 20usize.saturating_add(n).saturating_add(8);
        if bytes.len() != expected {
            return Err(CheckpointError::Truncated { path: p, len: bytes.len(), expected });
        }
        let body = &bytes[20..20 + n];
        let saved = u64::from_le_bytes(bytes[20 + n..].try_into().unwrap_or([0; 8]));
        let calculated = fnv1a64(body);
        if saved != calculated {
            return Err(CheckpointError::BadChecksum { path: p, saved, calculated });
        }
        let bad = |why: String| CheckpointError::BadPayload { path: p.clone(), why };
        let unreadable = |source: PayloadError| CheckpointError::Payload { path: p.clone(), source };
        let payload: Payload = if version == CHECKPOINT_VERSION_JSON { serde_json::from_slice(body).map_err(|e| bad(e.to_string()))? } else { decode_binary(body, version).map_err(unreadable)? };
        let config: MapperConfig = toml::from_str(&payload.config_toml).map_err(|e| bad(e.to_string()))?;
        let c = payload.capacity;
        let capacity = match options.capacity {
            Some(o) if o.width == c.width && o.height == c.height => MapperCapacity { max_gaussians: o.max_gaussians.max(c.max_gaussians), max_keyframes: o.max_keyframes.max(c.max_keyframes), ..c },
            Some(o) => return Err(bad(format!("the checkpoint's images are {}x{}, not {}x{}", c.width, c.height, o.width, o.height))),
            None => c,
        };
        let mut m = Mapper::new(config, capacity)?;
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
            if rec.m.is_empty() && rec.v.is_empty() && len > 0 {
                // A referenced (logged) checkpoint: the moments start from zero.
                let zeros = vec![0.0f32; len * ParamGroup::ALL[k].width()];
                m.adam[k].set_state(rec.steps, &zeros, &zeros).map_err(MapperError::from)?;
            } else {
                m.adam[k].set_state(rec.steps, &floats(&rec.m), &floats(&rec.v)).map_err(MapperError::from)?;
            }
            if m.adam[k].len() != len {
                return Err(bad(format!("Adam group {k} holds {} items, the map {len}", m.adam[k].len())));
            }
        }
        m.grads.reset(len).map_err(MapperError::from)?;
        m.grads
            .set_densify_stats(&floats(&payload.densify_grad_norm), &payload.pixels_touched, &payload.views)
            .map_err(MapperError::from)?;
        if !payload.footprint.is_empty() && payload.footprint.len() != len {
            return Err(bad(format!("{} footprints for {len} Gaussians", payload.footprint.len())));
        }
        for i in 0..len {
            m.grads.set_footprint(i, payload.footprint.get(i).map_or(0.0, |&b| f32::from_bits(b)));
        }
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
            let referenced = r.image.is_empty() && r.inv_depth.is_empty() && r.inv_depth_variance.is_empty() && r.width * r.height > 0;
            let (image, inv_depth, inv_depth_variance) = if referenced {
                let found = options.keyframes.iter().find(|k| k.t_ns.t_ns() == r.t_ns && k.camera.width == r.width && k.camera.height == r.height).ok_or_else(|| {
                    bad(format!("keyframe {} (t = {} ns) is referenced, not embedded, and was not supplied (a logged checkpoint: restore it with the log's keyframes)", r.index, r.t_ns))
                })?;
                (found.image.clone(), found.inv_depth.clone(), found.inv_depth_variance.clone())
            } else {
                (
                    ImageRgb8::from_vec(r.width, r.height, r.image.clone()).ok_or_else(|| bad(format!("keyframe {}: image size", r.index)))?,
                    PlaneF32::from_vec(r.width, r.height, floats(&r.inv_depth)).ok_or_else(|| bad(format!("keyframe {}: depth size", r.index)))?,
                    PlaneF32::from_vec(r.width, r.height, floats(&r.inv_depth_variance)).ok_or_else(|| bad(format!("keyframe {}: variance size", r.index)))?,
                )
            };
            let kf = Keyframe { index: r.index, t_ns: Timestamp(r.t_ns), image, world_from_cam, camera, inv_depth, inv_depth_variance };
            if !kf.is_consistent() {
                return Err(bad(format!("keyframe {}: inconsistent sizes", r.index)));
            }
            m.push_restored_keyframe(&kf);
        }
        m.iteration = payload.iteration;
        match &payload.medium_state {
            Some(state) => {
                m.medium_estimate_at = usize::try_from(state.estimate_at).map_err(|_| unreadable(PayloadError::Size { value: state.estimate_at }))?;
                m.medium_prior = state.prior(version).map_err(unreadable)?;
            }
            // An older checkpoint with at least as many keyframes as the first medium estimate
            // needs: its optimised medium is not replaced by a new estimate.
            None if m.keyframes.len() >= m.config.estimate_medium_at_keyframes => m.medium_estimate_at = 0,
            None => {}
        }
        m.rng = Rng::from_state(payload.rng_state);
        Ok(m)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn small() -> Vec<u8> {
        let mut m = Mapper::new(MapperConfig::default(), MapperCapacity { max_gaussians: 64, max_keyframes: 2, width: 8, height: 6 }).unwrap();
        m.checkpoint_bytes().unwrap()
    }

    #[test]
    fn the_medium_prior_holds_coefficients_by_mask_and_older_flags_hold_whole_channels() {
        let medium = MediumParams { beta_d: [0.4, 0.1, 0.08], beta_b: [0.3, 0.07, 0.05], b_inf: [0.03, 0.2, 0.45] };
        let held = [Coefficients::ALL, Coefficients::NONE, Coefficients { beta_d: true, beta_b: false, b_inf: true }];
        let mut m = Mapper::new(MapperConfig::default(), MapperCapacity { max_gaussians: 64, max_keyframes: 2, width: 8, height: 6 }).unwrap();
        m.medium_prior = Some(MediumPrior { medium, held, weight: 0.5, rel_std: 0.1, b_inf_std: 0.02 });
        let record = MediumStateRecord::of(&m);
        assert_eq!(&record.prior[..3], &[7, 0, 5]);
        assert_eq!(record.prior(CHECKPOINT_VERSION).unwrap(), m.medium_prior);
        // Versions 3 and 4 wrote 0/1 per channel: 1 is all three.
        let mut old = MediumStateRecord { estimate_at: 0, prior: record.prior.clone() };
        old.prior[..3].copy_from_slice(&[1, 0, 1]);
        let p = old.prior(CHECKPOINT_VERSION_CHANNEL_PRIOR).unwrap().unwrap();
        assert_eq!(p.held, [Coefficients::ALL, Coefficients::NONE, Coefficients::ALL]);
        old.prior[0] = 9;
        let e = old.prior(CHECKPOINT_VERSION).unwrap_err().to_string();
        assert!(e.contains("flag 9"), "{e}");
    }

    #[test]
    fn binary_payload_round_trips_and_damage_is_named() {
        let bytes = small();
        let body = &bytes[20..bytes.len() - 8];
        let p = decode_binary(body, CHECKPOINT_VERSION).unwrap();
        assert_eq!((p.capacity.max_gaussians, p.capacity.max_keyframes, p.capacity.width, p.capacity.height), (64, 2, 8, 6));
        assert!(p.keyframes.is_empty() && p.gaussians.iter().all(|g| g.is_empty()));
        // A count far beyond the payload: refused before anything is allocated.
        let mut huge = body.to_vec();
        huge[..8].copy_from_slice(&u64::MAX.to_le_bytes());
        assert!(decode_binary(&huge, CHECKPOINT_VERSION).err().unwrap().to_string().contains("does not fit"));
        let cut = decode_binary(&body[..body.len() - 3], CHECKPOINT_VERSION).err().unwrap().to_string();
        assert!(cut.contains("truncated") || cut.contains("does not fit"), "{cut}");
        let mut longer = body.to_vec();
        longer.push(0);
        assert!(decode_binary(&longer, CHECKPOINT_VERSION).err().unwrap().to_string().contains("after the last keyframe"));
    }
}
