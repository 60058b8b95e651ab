//! Navigation-sensor samples (pressure depth, altimeter or DVL altitude, DVL velocity, AHRS
//! attitude) and their file form, `nav.csv` (issue 40).
//!
//! ```text
//! t_s,depth_m,altitude_m,vel_x_mps,vel_y_mps,vel_z_mps,qx,qy,qz,qw
//! 0.100000000,23.0412,1.9873,0.0061,-0.0012,0.4987,-0.8433,0.1421,-0.0765,0.5131
//! 0.200000000,23.0391,,,,,,,,
//! ```
//!
//! One row per sensor sample, comma-separated, the header exactly as above (lines starting
//! with `#` and blank lines are skipped):
//! - `t_s`: seconds on the clock of the dataset's `rgb.txt`, parsed digit by digit to integer
//!   nanoseconds like every other time stamp ([`Timestamp::from_str`]);
//! - `depth_m`: pressure depth below the sea surface, metres, positive down;
//! - `altitude_m`: range to the seabed along gravity (altimeter or DVL bottom lock), metres;
//! - `vel_x_mps, vel_y_mps, vel_z_mps`: velocity over ground in the camera frame (x right,
//!   y down, z forward), m/s;
//! - `qx, qy, qz, qw`: the camera-to-world rotation from the AHRS (Hamilton), world z up; the
//!   heading may drift.
//!
//! An empty cell means that sensor has no sample in this row. The velocity (three cells) and
//! the quaternion (four cells) are all or nothing: a partly filled group is an error.
//!
//! Reading ([`read_nav_csv`]): a missing or wrong header, a row with the wrong number of
//! cells, a cell that is not a number or a partly filled group is an error naming the file,
//! the line and the column. Bad *values* are rejected and counted in [`NavRejections`], never
//! fatal, so one glitching sensor does not stop a dive:
//! - a non-finite value (`NaN`, `inf`): that sensor's value of the row (a non-finite `t_s`:
//!   the whole row);
//! - a time that goes back before, or repeats, the previous kept row's: the whole row;
//! - a quaternion whose norm is more than [`QUATERNION_NORM_TOLERANCE`] off 1 (closer ones
//!   are normalised, as for TUM poses);
//! - a depth outside [`DEPTH_RANGE_M`] (a little above the surface, for waves and sensor
//!   offset, down to the deepest trench), an altitude outside [`ALTITUDE_RANGE_M`], a speed
//!   above [`MAX_SPEED_MPS`];
//! - a depth spike: a depth more than [`DEPTH_SPIKE_M`] from the median of the depth samples
//!   within [`DEPTH_SPIKE_WINDOW_NS`] either side, itself included (judged only where at least
//!   [`DEPTH_SPIKE_MIN_NEIGHBOURS`] other samples lie in that window, so a sensor slower than
//!   1 Hz is never judged). No vehicle changes depth by 5 m in a second; a pressure glitch does.
//!
//! Rows left without any sensor value are dropped.

use crate::io::{read_text, write_atomic, IoError};
use crate::Timestamp;
use nalgebra::{Quaternion, UnitQuaternion, Vector3};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::str::FromStr;

/// The header line of `nav.csv`.
pub const NAV_CSV_HEADER: &str = "t_s,depth_m,altitude_m,vel_x_mps,vel_y_mps,vel_z_mps,qx,qy,qz,qw";
/// The column names of `nav.csv`, in order.
pub const NAV_CSV_COLUMNS: [&str; 10] = ["t_s", "depth_m", "altitude_m", "vel_x_mps", "vel_y_mps", "vel_z_mps", "qx", "qy", "qz", "qw"];

/// Accepted pressure depth, metres: from 1 m above the surface (waves, a sensor offset at the
/// surface) to 11 000 m (below the Challenger Deep).
pub const DEPTH_RANGE_M: (f64, f64) = (-1.0, 11_000.0);
/// Accepted altitude, metres: no sonar altimeter or DVL locks on beyond 1000 m.
pub const ALTITUDE_RANGE_M: (f64, f64) = (0.0, 1000.0);
/// Accepted speed over ground (norm of the DVL velocity), m/s.
pub const MAX_SPEED_MPS: f64 = 20.0;
/// Quaternions whose norm is within this of 1 are normalised; others are rejected.
pub const QUATERNION_NORM_TOLERANCE: f64 = 0.01;
/// A depth this far (metres) from the median of its neighbours is a spike.
pub const DEPTH_SPIKE_M: f64 = 5.0;
/// Neighbours of a depth sample for the spike test: samples within this time either side.
pub const DEPTH_SPIKE_WINDOW_NS: i64 = 1_000_000_000;
/// The spike test judges a depth sample only when it has at least this many neighbours.
pub const DEPTH_SPIKE_MIN_NEIGHBOURS: usize = 2;

/// One row of navigation data: whatever sensors sampled at `t_ns`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NavSample {
    /// On the clock of the images (`rgb.txt`).
    pub t_ns: Timestamp,
    /// Pressure depth below the sea surface, metres, positive down.
    pub depth_m: Option<f64>,
    /// Range to the seabed along gravity (altimeter or DVL bottom lock), metres.
    pub altitude_m: Option<f64>,
    /// Velocity over ground in the camera frame (x right, y down, z forward), m/s.
    pub vel_cam_mps: Option<Vector3<f64>>,
    /// Camera-to-world rotation from the AHRS, world z up (the heading may drift).
    pub world_from_cam_rot: Option<UnitQuaternion<f64>>,
}

impl NavSample {
    /// A sample at `t_ns` with no sensor value.
    pub fn empty(t_ns: Timestamp) -> Self {
        NavSample { t_ns, depth_m: None, altitude_m: None, vel_cam_mps: None, world_from_cam_rot: None }
    }

    /// Whether no sensor has a value in this sample.
    pub fn is_empty(&self) -> bool {
        self.depth_m.is_none() && self.altitude_m.is_none() && self.vel_cam_mps.is_none() && self.world_from_cam_rot.is_none()
    }
}

/// How many values or rows [`read_nav_csv`] rejected, by reason. Value counts are per sensor
/// per row (a row's depth, its velocity group, ...); time problems reject whole rows.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct NavRejections {
    /// Values that were `NaN` or infinite (a non-finite `t_s` counts once and drops the row).
    pub non_finite: usize,
    /// Rows whose time goes back before the previous kept row's.
    pub out_of_order: usize,
    /// Rows with the same time as the previous kept row.
    pub duplicate_time: usize,
    /// Quaternions further than [`QUATERNION_NORM_TOLERANCE`] from unit norm.
    pub bad_quaternion: usize,
    /// Depths outside [`DEPTH_RANGE_M`].
    pub depth_out_of_range: usize,
    /// Depths further than [`DEPTH_SPIKE_M`] from the median of their neighbours.
    pub depth_spike: usize,
    /// Altitudes outside [`ALTITUDE_RANGE_M`].
    pub altitude_out_of_range: usize,
    /// Velocities faster than [`MAX_SPEED_MPS`].
    pub velocity_out_of_range: usize,
}

impl NavRejections {
    /// All rejections together.
    pub fn total(&self) -> usize {
        self.non_finite
            + self.out_of_order
            + self.duplicate_time
            + self.bad_quaternion
            + self.depth_out_of_range
            + self.depth_spike
            + self.altitude_out_of_range
            + self.velocity_out_of_range
    }

    /// The non-zero counts, e.g. `2 non-finite, 1 depth spike`; `none` when all are zero.
    pub fn describe(&self) -> String {
        let parts: Vec<String> = [
            (self.non_finite, "non-finite"),
            (self.out_of_order, "out of order"),
            (self.duplicate_time, "duplicate time"),
            (self.bad_quaternion, "bad quaternion"),
            (self.depth_out_of_range, "depth out of range"),
            (self.depth_spike, "depth spike"),
            (self.altitude_out_of_range, "altitude out of range"),
            (self.velocity_out_of_range, "velocity out of range"),
        ]
        .iter()
        .filter(|(n, _)| *n > 0)
        .map(|(n, what)| format!("{n} {what}"))
        .collect();
        if parts.is_empty() {
            "none".into()
        } else {
            parts.join(", ")
        }
    }
}

/// The navigation data of a dataset: samples in strictly increasing time, and what was
/// rejected on the way in.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct NavTrack {
    pub samples: Vec<NavSample>,
    pub rejected: NavRejections,
}

/// Errors of the `nav` module. Each names the file, and the line and column where there is one.
#[derive(Debug, thiserror::Error)]
pub enum NavError {
    #[error(transparent)]
    Io(#[from] IoError),
    #[error("{path}: empty; a nav file starts with the header `{NAV_CSV_HEADER}`")]
    NoHeader { path: PathBuf },
    #[error("{path}, line {line}: expected the header `{NAV_CSV_HEADER}`, found {found:?}")]
    BadHeader { path: PathBuf, line: usize, found: String },
    #[error("{path}, line {line}: expected {expected} comma-separated cells, found {found}")]
    CellCount { path: PathBuf, line: usize, expected: usize, found: usize },
    #[error("{path}, line {line}, column {column}: {text:?} is not a number")]
    BadCell { path: PathBuf, line: usize, column: &'static str, text: String },
    #[error("{path}, line {line}, column t_s: the time is empty")]
    NoTime { path: PathBuf, line: usize },
    /// Part of the velocity or quaternion group is filled and part is empty.
    #[error("{path}, line {line}: columns {columns} must be all filled or all empty; {empty} is empty")]
    PartialGroup { path: PathBuf, line: usize, columns: &'static str, empty: &'static str },
}

impl NavTrack {
    /// Number of samples.
    pub fn len(&self) -> usize {
        self.samples.len()
    }

    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// The samples with `t0 <= t_ns < t1` (consecutive intervals share no sample).
    pub fn between(&self, t0: Timestamp, t1: Timestamp) -> &[NavSample] {
        let a = self.samples.partition_point(|s| s.t_ns < t0);
        let b = self.samples.partition_point(|s| s.t_ns < t1).max(a);
        &self.samples[a..b]
    }

    /// Depth at `t_ns`, linearly interpolated between the nearest depth samples at or before
    /// and at or after it, when they are at most `max_gap_ns` apart; `None` otherwise.
    pub fn depth_at(&self, t_ns: Timestamp, max_gap_ns: i64) -> Option<f64> {
        self.interpolate(t_ns, max_gap_ns, |s| s.depth_m, |a, b, w| a + (b - a) * w)
    }

    /// Altitude at `t_ns`, as [`NavTrack::depth_at`].
    pub fn altitude_at(&self, t_ns: Timestamp, max_gap_ns: i64) -> Option<f64> {
        self.interpolate(t_ns, max_gap_ns, |s| s.altitude_m, |a, b, w| a + (b - a) * w)
    }

    /// Camera-frame velocity at `t_ns`, as [`NavTrack::depth_at`].
    pub fn vel_cam_mps_at(&self, t_ns: Timestamp, max_gap_ns: i64) -> Option<Vector3<f64>> {
        self.interpolate(t_ns, max_gap_ns, |s| s.vel_cam_mps, |a, b, w| a + (b - a) * w)
    }

    /// AHRS attitude at `t_ns`, spherically interpolated, as [`NavTrack::depth_at`].
    pub fn world_from_cam_rot_at(&self, t_ns: Timestamp, max_gap_ns: i64) -> Option<UnitQuaternion<f64>> {
        self.interpolate(t_ns, max_gap_ns, |s| s.world_from_cam_rot, |a, b, w| a.try_slerp(&b, w, 1e-9).unwrap_or(a))
    }

    fn interpolate<T: Copy>(
        &self,
        t_ns: Timestamp,
        max_gap_ns: i64,
        get: impl Fn(&NavSample) -> Option<T>,
        mix: impl Fn(T, T, f64) -> T,
    ) -> Option<T> {
        let i = self.samples.partition_point(|s| s.t_ns < t_ns);
        // Nearest sample with a value at or after t, then at or before t; the search stops once
        // it is further than the gap allows.
        let after = self.samples[i..].iter().take_while(|s| s.t_ns.t_ns() - t_ns.t_ns() <= max_gap_ns).find_map(|s| get(s).map(|v| (s.t_ns, v)))?;
        if after.0 == t_ns {
            return Some(after.1);
        }
        let before = self.samples[..i].iter().rev().take_while(|s| t_ns.t_ns() - s.t_ns.t_ns() <= max_gap_ns).find_map(|s| get(s).map(|v| (s.t_ns, v)))?;
        let span = after.0.t_ns() - before.0.t_ns();
        if span > max_gap_ns {
            return None;
        }
        let w = (t_ns.t_ns() - before.0.t_ns()) as f64 / span as f64;
        Some(mix(before.1, after.1, w))
    }
}

/// Judges samples that did not come from a file (a live autopilot stream, a bag) as
/// [`parse_nav_csv`] judges rows: sorted by time (a repeated time keeps the first), values
/// out of range, not finite or off unit norm rejected and counted, depth spikes cleared.
pub fn validate_samples(mut raw: Vec<NavSample>) -> NavTrack {
    raw.sort_by_key(|s| s.t_ns);
    judge_nav_rows(raw.into_iter().map(|s| NavRow {
        t_ns: Some(s.t_ns),
        depth_m: s.depth_m,
        altitude_m: s.altitude_m,
        vel: s.vel_cam_mps.map(|v| [v.x, v.y, v.z]),
        q: s.world_from_cam_rot.map(|q| [q.i, q.j, q.k, q.w]),
    }))
}

/// Reads `nav.csv`; see the module documentation for the format and what is rejected.
pub fn read_nav_csv(path: &Path) -> Result<NavTrack, NavError> {
    parse_nav_csv(path, &read_text(path)?)
}

/// Parses the text of a `nav.csv`; `path` is for the messages.
pub fn parse_nav_csv(path: &Path, text: &str) -> Result<NavTrack, NavError> {
    let mut rows: Vec<NavRow> = Vec::new();
    let mut header_seen = false;
    for (i, raw) in text.lines().enumerate() {
        let line_no = i + 1;
        let line = raw.trim();
        let line = if i == 0 { line.trim_start_matches('\u{feff}') } else { line };
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        if !header_seen {
            let names: Vec<&str> = line.split(',').map(str::trim).collect();
            if names != NAV_CSV_COLUMNS {
                return Err(NavError::BadHeader { path: path.to_path_buf(), line: line_no, found: line.to_string() });
            }
            header_seen = true;
            continue;
        }
        rows.push(parse_row(path, line_no, line)?);
    }
    if !header_seen {
        return Err(NavError::NoHeader { path: path.to_path_buf() });
    }
    Ok(judge_nav_rows(rows))
}

/// Judges rows of sensor values as [`read_nav_csv`] does (see the module documentation: what
/// is rejected and counted), for every source of navigation samples (a `nav.csv`, a ROS 2 bag's
/// sensor topics); rows in the order they were recorded.
pub fn judge_nav_rows(rows: impl IntoIterator<Item = NavRow>) -> NavTrack {
    let mut rejected = NavRejections::default();
    let mut samples: Vec<NavSample> = Vec::new();
    for row in rows {
        let Some(t_ns) = row.t_ns else {
            rejected.non_finite += 1;
            continue;
        };
        if row.is_blank() {
            continue;
        }
        if let Some(prev) = samples.last() {
            if t_ns < prev.t_ns {
                rejected.out_of_order += 1;
                continue;
            }
            if t_ns == prev.t_ns {
                rejected.duplicate_time += 1;
                continue;
            }
        }
        let mut s = NavSample::empty(t_ns);
        s.depth_m = row.depth_m.and_then(|d| {
            let ok = check_finite(d, &mut rejected) && check_range(d, DEPTH_RANGE_M, &mut rejected.depth_out_of_range);
            ok.then_some(d)
        });
        s.altitude_m = row.altitude_m.and_then(|a| {
            let ok = check_finite(a, &mut rejected) && check_range(a, ALTITUDE_RANGE_M, &mut rejected.altitude_out_of_range);
            ok.then_some(a)
        });
        s.vel_cam_mps = row.vel.and_then(|v| {
            if !v.iter().all(|x| check_finite(*x, &mut rejected)) {
                return None;
            }
            let v = Vector3::from(v);
            if v.norm() > MAX_SPEED_MPS {
                rejected.velocity_out_of_range += 1;
                return None;
            }
            Some(v)
        });
        s.world_from_cam_rot = row.q.and_then(|q| {
            if !q.iter().all(|x| check_finite(*x, &mut rejected)) {
                return None;
            }
            let q = Quaternion::new(q[3], q[0], q[1], q[2]);
            if (q.norm() - 1.0).abs() > QUATERNION_NORM_TOLERANCE {
                rejected.bad_quaternion += 1;
                return None;
            }
            Some(UnitQuaternion::from_quaternion(q))
        });
        if s.is_empty() {
            continue;
        }
        samples.push(s);
    }
    rejected.depth_spike = reject_depth_spikes(&mut samples);
    samples.retain(|s| !s.is_empty());
    NavTrack { samples, rejected }
}

/// Counts a non-finite value (a group with several counts once: callers stop at the first).
fn check_finite(v: f64, rejected: &mut NavRejections) -> bool {
    if v.is_finite() {
        true
    } else {
        rejected.non_finite += 1;
        false
    }
}

fn check_range(v: f64, (lo, hi): (f64, f64), count: &mut usize) -> bool {
    if (lo..=hi).contains(&v) {
        true
    } else {
        *count += 1;
        false
    }
}

/// The values of one row, read but not yet judged ([`judge_nav_rows`]). `t_ns` is `None` for
/// a non-finite time; `vel` in the camera frame, m/s; `q` is `[qx, qy, qz, qw]` as in `nav.csv`.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct NavRow {
    pub t_ns: Option<Timestamp>,
    pub depth_m: Option<f64>,
    pub altitude_m: Option<f64>,
    pub vel: Option<[f64; 3]>,
    pub q: Option<[f64; 4]>,
}

impl NavRow {
    /// No sensor value is filled.
    pub fn is_blank(&self) -> bool {
        self.depth_m.is_none() && self.altitude_m.is_none() && self.vel.is_none() && self.q.is_none()
    }
}

fn parse_row(path: &Path, line: usize, text: &str) -> Result<NavRow, NavError> {
    let cells: Vec<&str> = text.split(',').map(str::trim).collect();
    if cells.len() != NAV_CSV_COLUMNS.len() {
        return Err(NavError::CellCount { path: path.to_path_buf(), line, expected: NAV_CSV_COLUMNS.len(), found: cells.len() });
    }
    let number = |k: usize| -> Result<Option<f64>, NavError> {
        let c = cells[k];
        if c.is_empty() {
            return Ok(None);
        }
        c.parse::<f64>().map(Some).map_err(|_| NavError::BadCell { path: path.to_path_buf(), line, column: NAV_CSV_COLUMNS[k], text: c.to_string() })
    };
    let t_ns = {
        let c = cells[0];
        if c.is_empty() {
            return Err(NavError::NoTime { path: path.to_path_buf(), line });
        }
        match Timestamp::from_str(c) {
            Ok(t) => Some(t),
            // `1.5e9`, `nan`: through f64; a non-finite time drops the row.
            Err(_) => match number(0)? {
                Some(v) if v.is_finite() && v.abs() < 9.0e9 => Some(Timestamp::from_secs_f64(v)),
                Some(v) if v.is_finite() => return Err(NavError::BadCell { path: path.to_path_buf(), line, column: "t_s", text: c.to_string() }),
                _ => None,
            },
        }
    };
    let group = |range: std::ops::Range<usize>, columns: &'static str| -> Result<Option<Vec<f64>>, NavError> {
        let vals: Vec<Option<f64>> = range.clone().map(number).collect::<Result<_, _>>()?;
        let filled = vals.iter().filter(|v| v.is_some()).count();
        if filled == 0 {
            return Ok(None);
        }
        if filled < vals.len() {
            let empty = range.clone().find(|&k| cells[k].is_empty()).map_or("?", |k| NAV_CSV_COLUMNS[k]);
            return Err(NavError::PartialGroup { path: path.to_path_buf(), line, columns, empty });
        }
        Ok(Some(vals.into_iter().flatten().collect()))
    };
    let depth_m = number(1)?;
    let altitude_m = number(2)?;
    let vel = group(3..6, "vel_x_mps,vel_y_mps,vel_z_mps")?.map(|v| [v[0], v[1], v[2]]);
    let q = group(6..10, "qx,qy,qz,qw")?.map(|v| [v[0], v[1], v[2], v[3]]);
    Ok(NavRow { t_ns, depth_m, altitude_m, vel, q })
}

/// Clears the depth of every sample further than [`DEPTH_SPIKE_M`] from the median of the
/// depths within [`DEPTH_SPIKE_WINDOW_NS`] either side, itself included (all judged against
/// the same, unfiltered neighbours); returns how many.
fn reject_depth_spikes(samples: &mut [NavSample]) -> usize {
    let depths: Vec<(i64, f64)> = samples.iter().filter_map(|s| s.depth_m.map(|d| (s.t_ns.t_ns(), d))).collect();
    let mut spike_times: Vec<i64> = Vec::new();
    let mut window: Vec<f64> = Vec::new();
    let (mut lo, mut hi) = (0usize, 0usize);
    for &(t, d) in &depths {
        while depths[lo].0 < t.saturating_sub(DEPTH_SPIKE_WINDOW_NS) {
            lo += 1;
        }
        while hi < depths.len() && depths[hi].0 <= t.saturating_add(DEPTH_SPIKE_WINDOW_NS) {
            hi += 1;
        }
        // The sample itself is in the window: with two neighbours, one of them a spike, the
        // median is still a good depth.
        if hi - lo - 1 < DEPTH_SPIKE_MIN_NEIGHBOURS {
            continue;
        }
        window.clear();
        window.extend(depths[lo..hi].iter().map(|&(_, v)| v));
        if (d - median(&mut window)).abs() > DEPTH_SPIKE_M {
            spike_times.push(t);
        }
    }
    let mut cleared = 0;
    let mut next = spike_times.iter().peekable();
    for s in samples.iter_mut() {
        if next.peek().is_some_and(|&&t| t == s.t_ns.t_ns()) && s.depth_m.is_some() {
            s.depth_m = None;
            cleared += 1;
            next.next();
        }
    }
    cleared
}

/// Median of a non-empty slice (the mean of the middle two for an even length); reorders it.
fn median(v: &mut [f64]) -> f64 {
    let n = v.len();
    let (_, &mut upper, _) = v.select_nth_unstable_by(n / 2, f64::total_cmp);
    if n % 2 == 1 {
        upper
    } else {
        let lower = v[..n / 2].iter().copied().fold(f64::NEG_INFINITY, f64::max);
        0.5 * (lower + upper)
    }
}

/// Formats samples as `nav.csv` text: the header, then one row per sample; numbers in the
/// shortest form that reads back to the same `f64`, time stamps with nine decimals.
pub fn format_nav_csv(samples: &[NavSample]) -> String {
    let mut s = String::with_capacity(64 * (samples.len() + 1));
    s.push_str(NAV_CSV_HEADER);
    s.push('\n');
    let opt = |s: &mut String, v: Option<f64>| {
        s.push(',');
        if let Some(v) = v {
            let _ = write!(s, "{v}");
        }
    };
    for n in samples {
        let _ = write!(s, "{}", n.t_ns);
        opt(&mut s, n.depth_m);
        opt(&mut s, n.altitude_m);
        for k in 0..3 {
            opt(&mut s, n.vel_cam_mps.map(|v| v[k]));
        }
        let q = n.world_from_cam_rot.map(|q| {
            // Canonical sign, as for TUM poses.
            let q = *q.quaternion();
            if q.w < 0.0 { -q } else { q }
        });
        for v in [q.map(|q| q.i), q.map(|q| q.j), q.map(|q| q.k), q.map(|q| q.w)] {
            opt(&mut s, v);
        }
        s.push('\n');
    }
    s
}

/// Writes `nav.csv` atomically (temporary sibling, fsync, rename).
pub fn write_nav_csv(path: &Path, samples: &[NavSample]) -> Result<(), NavError> {
    Ok(write_atomic(path, format_nav_csv(samples).as_bytes())?)
}

#[cfg(test)]
mod tests {
    use super::*;

    const H: &str = "t_s,depth_m,altitude_m,vel_x_mps,vel_y_mps,vel_z_mps,qx,qy,qz,qw\n";

    fn parse(body: &str) -> Result<NavTrack, NavError> {
        parse_nav_csv(Path::new("dive/nav.csv"), &format!("{H}{body}"))
    }

    /// Rows of depth only, 10 Hz from t = 0: `depth(k)`.
    fn depth_rows(n: usize, depth: impl Fn(usize) -> f64) -> String {
        (0..n).map(|k| format!("{}.{},{},,,,,,,,\n", k / 10, k % 10, depth(k))).collect()
    }

    fn sample(k: i64) -> NavSample {
        let kf = k as f64;
        NavSample {
            t_ns: Timestamp(1_305_031_098_665_900_000 + k * 33_333_333),
            depth_m: (k % 3 != 0).then_some(23.0 + 0.01 * kf),
            altitude_m: (k % 4 != 1).then_some(2.0 - 0.001 * kf),
            vel_cam_mps: (k % 2 == 0).then_some(Vector3::new(0.01 * kf, -0.002, 0.5)),
            world_from_cam_rot: (k != 3).then(|| UnitQuaternion::from_euler_angles(0.1 * kf, -0.7, 2.0 + 0.05 * kf)),
        }
    }

    #[test]
    fn round_trip_is_exact() {
        let samples: Vec<NavSample> = (0..12).map(sample).collect();
        let text = format_nav_csv(&samples);
        assert!(text.starts_with(H), "{text}");
        assert!(text.lines().nth(4).unwrap().starts_with("1305031098.765899999,,1.997,,,,"), "{text}");
        let back = parse_nav_csv(Path::new("nav.csv"), &text).unwrap();
        assert_eq!(back.rejected, NavRejections::default());
        assert_eq!(back.len(), 12);
        for (a, b) in samples.iter().zip(&back.samples) {
            assert_eq!((a.t_ns, a.depth_m, a.altitude_m, a.vel_cam_mps), (b.t_ns, b.depth_m, b.altitude_m, b.vel_cam_mps));
            match (a.world_from_cam_rot, b.world_from_cam_rot) {
                (Some(qa), Some(qb)) => assert!(qa.angle_to(&qb) < 1e-12, "{qa:?} {qb:?}"),
                (qa, qb) => assert_eq!(qa, qb),
            }
        }
        // Through a file, atomically.
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("nav.csv");
        write_nav_csv(&path, &samples).unwrap();
        assert_eq!(read_nav_csv(&path).unwrap(), back);
        assert!(!dir.path().join("nav.csv.tmp").exists());
    }

    #[test]
    fn empty_cells_are_missing_sensors_and_comments_are_skipped() {
        let t = parse("# from the vehicle log\n0.5,12.25,,,,,,,,\n0.6,,3.5,,,,,,,\n\n0.7,,,0.1,0.2,0.3,,,,\n0.8,,,,,,0,0,0,1\n0.9,,,,,,,,,\n").unwrap();
        assert_eq!(t.len(), 4, "the all-empty row at 0.9 s is dropped");
        assert_eq!(t.samples[0].t_ns, Timestamp(500_000_000));
        assert_eq!((t.samples[0].depth_m, t.samples[0].altitude_m), (Some(12.25), None));
        assert_eq!(t.samples[1].altitude_m, Some(3.5));
        assert_eq!(t.samples[2].vel_cam_mps, Some(Vector3::new(0.1, 0.2, 0.3)));
        assert_eq!(t.samples[3].world_from_cam_rot, Some(UnitQuaternion::identity()));
        assert_eq!(t.rejected.total(), 0);
        assert_eq!(t.rejected.describe(), "none");
    }

    #[test]
    fn header_errors_name_file_and_line() {
        let p = Path::new("dive/nav.csv");
        let e = parse_nav_csv(p, "").unwrap_err();
        assert_eq!(e.to_string(), format!("dive/nav.csv: empty; a nav file starts with the header `{NAV_CSV_HEADER}`"));
        let e = parse_nav_csv(p, "# only a comment\n").unwrap_err();
        assert!(matches!(e, NavError::NoHeader { .. }), "{e}");
        let e = parse_nav_csv(p, "# c\nt_s,depth_m,altitude_m,vel_x_mps,vel_y_mps,vel_z_mps,qw,qx,qy,qz\n").unwrap_err();
        assert!(matches!(&e, NavError::BadHeader { line: 2, .. }), "{e}");
        assert!(e.to_string().starts_with("dive/nav.csv, line 2: expected the header `t_s,depth_m,"), "{e}");
        // Data without a header.
        let e = parse_nav_csv(p, "0.1,2.0,,,,,,,,\n").unwrap_err();
        assert!(matches!(&e, NavError::BadHeader { line: 1, found, .. } if found == "0.1,2.0,,,,,,,,"), "{e}");
        // Spaces around names and CRLF endings are fine.
        let t = parse_nav_csv(p, "t_s, depth_m, altitude_m, vel_x_mps, vel_y_mps, vel_z_mps, qx, qy, qz, qw\r\n1, 2,,,,,,,,\r\n").unwrap();
        assert_eq!(t.samples[0].depth_m, Some(2.0));
    }

    #[test]
    fn cell_errors_name_file_line_and_column() {
        let e = parse("0.1,2.0,,,,,,,,\n0.2,2.0,abc,,,,,,,\n").unwrap_err();
        assert_eq!(e.to_string(), "dive/nav.csv, line 3, column altitude_m: \"abc\" is not a number");
        let e = parse("0.1,2.0,,,,,,,\n").unwrap_err();
        assert_eq!(e.to_string(), "dive/nav.csv, line 2: expected 10 comma-separated cells, found 9");
        let e = parse("1:02,2.0,,,,,,,,\n").unwrap_err();
        assert_eq!(e.to_string(), "dive/nav.csv, line 2, column t_s: \"1:02\" is not a number");
        let e = parse(",2.0,,,,,,,,\n").unwrap_err();
        assert_eq!(e.to_string(), "dive/nav.csv, line 2, column t_s: the time is empty");
        let e = parse("0.1,,,0.1,,0.3,,,,\n").unwrap_err();
        assert_eq!(e.to_string(), "dive/nav.csv, line 2: columns vel_x_mps,vel_y_mps,vel_z_mps must be all filled or all empty; vel_y_mps is empty");
        let e = parse("0.1,,,,,,0,0,0,\n").unwrap_err();
        assert!(matches!(&e, NavError::PartialGroup { line: 2, empty: "qw", .. }), "{e}");
        // A time in exponent notation is read through f64; one beyond any clock is an error.
        assert_eq!(parse("1.5e3,2.0,,,,,,,,\n").unwrap().samples[0].t_ns, Timestamp(1_500_000_000_000));
        let e = parse("1e300,2.0,,,,,,,,\n").unwrap_err();
        assert!(matches!(&e, NavError::BadCell { column: "t_s", line: 2, .. }), "{e}");
    }

    #[test]
    fn non_finite_values_are_rejected_per_sensor_and_counted() {
        let t = parse("0.1,NaN,2.0,,,,,,,\n0.2,3.0,inf,0.1,-inf,0.3,0,0,0,1\nnan,3.0,,,,,,,,\n0.3,,,,,,0,NaN,0,1\n").unwrap();
        // Depth NaN, altitude inf, a velocity with -inf, a time NaN (whole row), a quaternion NaN.
        assert_eq!(t.rejected.non_finite, 5);
        assert_eq!(t.rejected.total(), 5);
        assert_eq!(t.len(), 2, "row 0.3 s has nothing left");
        assert_eq!((t.samples[0].depth_m, t.samples[0].altitude_m), (None, Some(2.0)));
        assert_eq!((t.samples[1].depth_m, t.samples[1].altitude_m, t.samples[1].vel_cam_mps), (Some(3.0), None, None));
        assert!(t.samples[1].world_from_cam_rot.is_some());
        assert_eq!(t.rejected.describe(), "5 non-finite");
    }

    #[test]
    fn out_of_order_and_duplicate_times_are_rejected_and_counted() {
        let t = parse("1.0,5.0,,,,,,,,\n1.1,5.1,,,,,,,,\n1.05,5.2,,,,,,,,\n1.1,5.3,,,,,,,,\n1.100000000,5.4,,,,,,,,\n1.2,5.5,,,,,,,,\n").unwrap();
        assert_eq!((t.rejected.out_of_order, t.rejected.duplicate_time), (1, 2));
        let d: Vec<f64> = t.samples.iter().map(|s| s.depth_m.unwrap()).collect();
        assert_eq!(d, [5.0, 5.1, 5.5]);
        assert_eq!(t.rejected.describe(), "1 out of order, 2 duplicate time");
    }

    #[test]
    fn quaternion_far_from_unit_is_rejected_near_unit_normalised() {
        let t = parse("0.1,,,,,,0,0,0,1.005\n0.2,,,,,,0,0,0,1.2\n0.3,,,,,,0,0,0,0\n0.4,,,,,,0.1,0,0,0.9\n").unwrap();
        assert_eq!(t.rejected.bad_quaternion, 3);
        assert_eq!(t.len(), 1);
        assert_eq!(t.samples[0].world_from_cam_rot.unwrap().quaternion().w, 1.0);
    }

    #[test]
    fn depth_altitude_and_speed_out_of_range_are_rejected() {
        let t = parse("0.1,-1.5,2,,,,,,,\n0.2,11001,-0.1,,,,,,,\n0.3,-0.5,1000.5,,,,,,,\n0.4,10999,0,,,,,,,\n0.5,,,15,15,0,,,,\n0.6,,,0,0,19.9,,,,\n").unwrap();
        assert_eq!((t.rejected.depth_out_of_range, t.rejected.altitude_out_of_range, t.rejected.velocity_out_of_range), (2, 2, 1));
        assert_eq!(t.samples.iter().filter_map(|s| s.depth_m).collect::<Vec<_>>(), [-0.5, 10999.0]);
        assert_eq!(t.samples.iter().filter_map(|s| s.altitude_m).collect::<Vec<_>>(), [2.0, 0.0]);
        assert_eq!(t.samples.iter().filter_map(|s| s.vel_cam_mps).count(), 1);
    }

    #[test]
    fn depth_spikes_are_rejected_against_the_neighbour_median() {
        // 5 s at 10 Hz descending at 0.5 m/s from 20 m; a 100 m spike at 2.0 s, a 6 m one at
        // 3.0 s, two adjacent at 4.0 and 4.1 s; a 4 m step at 1.0 s is within the threshold.
        let depth = |k: usize| match k {
            20 => 120.0,
            30 => 21.5 + 6.0,
            40 | 41 => 600.0,
            10 => 20.5 + 4.0,
            _ => 20.0 + 0.05 * k as f64,
        };
        let t = parse(&depth_rows(50, depth)).unwrap();
        assert_eq!(t.rejected.depth_spike, 4);
        assert_eq!(t.rejected.total(), 4);
        assert_eq!(t.len(), 46, "the spiked rows had only a depth");
        assert!(t.samples.iter().all(|s| s.depth_m.unwrap() < 25.0));
        assert!(t.samples.iter().any(|s| s.depth_m == Some(24.5)));
        // Too few neighbours to judge (1 Hz with a gap): kept.
        let t = parse("0,20,,,,,,,,\n1,120,,,,,,,,\n3,20,,,,,,,,\n").unwrap();
        assert_eq!(t.rejected.depth_spike, 0);
        // A spike row keeps its other sensors.
        let t = parse("0,20,3,,,,,,,\n0.5,20,3,,,,,,,\n1,220,3,,,,,,,\n1.5,20,3,,,,,,,\n2,20,3,,,,,,,\n").unwrap();
        assert_eq!((t.rejected.depth_spike, t.len()), (1, 5));
        assert_eq!((t.samples[2].depth_m, t.samples[2].altitude_m), (None, Some(3.0)));
    }

    #[test]
    fn between_and_interpolation() {
        let t = parse("1.0,10,2,,,,0,0,0,1\n1.5,,,,,,,,,\n2.0,11,,0,0,1,,,,\n4.0,15,,,,,0,0,1,0\n").unwrap();
        assert_eq!(t.len(), 3);
        let s = |v: f64| Timestamp::from_secs_f64(v);
        assert_eq!(t.between(s(1.0), s(2.0)).len(), 1);
        assert_eq!(t.between(s(1.0), s(2.0001)).len(), 2);
        assert_eq!(t.between(s(3.0), s(1.0)).len(), 0);
        let gap = 1_000_000_000;
        assert!((t.depth_at(s(1.25), gap).unwrap() - 10.25).abs() < 1e-12);
        assert_eq!(t.depth_at(s(2.0), gap), Some(11.0));
        assert_eq!(t.depth_at(s(3.0), gap), None, "2 s between samples");
        assert!((t.depth_at(s(3.0), 2 * gap).unwrap() - 13.0).abs() < 1e-12);
        assert_eq!(t.depth_at(s(0.9), gap), None);
        assert_eq!(t.altitude_at(s(1.0), gap), Some(2.0));
        assert_eq!(t.altitude_at(s(1.1), gap), None);
        assert_eq!(t.vel_cam_mps_at(s(2.0), 0), Some(Vector3::new(0.0, 0.0, 1.0)));
        // Half way between identity and 180 degrees about z: 90 degrees.
        let q = t.world_from_cam_rot_at(s(2.5), 3 * gap).unwrap();
        assert!((q.angle() - std::f64::consts::FRAC_PI_2).abs() < 1e-9, "{q:?}");
    }

    #[test]
    fn live_samples_are_judged_like_file_rows() {
        let t = |s: f64| Timestamp::from_secs_f64(s);
        let depth = |s: f64, d: f64| NavSample { depth_m: Some(d), ..NavSample::empty(t(s)) };
        let mut raw: Vec<NavSample> = (0..10).map(|i| depth(0.1 * i as f64, 10.0 + 0.01 * i as f64)).collect();
        raw[4].depth_m = Some(110.0); // a spike
        raw.push(depth(0.25, f64::NAN)); // not finite
        raw.push(depth(0.3, 10.5)); // a repeated time: the first one stays
        raw.push(NavSample { altitude_m: Some(-3.0), ..NavSample::empty(t(0.35)) }); // out of range
        raw.push(NavSample { vel_cam_mps: Some(Vector3::new(30.0, 0.0, 0.0)), ..NavSample::empty(t(0.45)) });
        raw.push(NavSample { altitude_m: Some(2.5), ..NavSample::empty(t(0.05)) }); // out of order: sorted in
        let track = validate_samples(raw);
        let r = track.rejected;
        assert_eq!((r.depth_spike, r.non_finite, r.duplicate_time, r.altitude_out_of_range, r.velocity_out_of_range), (1, 1, 1, 1, 1));
        assert_eq!(track.samples.len(), 10, "9 depths and the altitude");
        assert_eq!(track.samples[1].altitude_m, Some(2.5));
        assert!(track.samples.windows(2).all(|w| w[0].t_ns < w[1].t_ns));
        assert_eq!(track.samples.iter().filter_map(|s| s.depth_m).fold(0.0, f64::max), 10.09);
    }
}
