//! The files a finished run leaves in its folder, written in one place: `trajectory.txt`
//! (every frame, TUM), `keyframes.txt`, the keyframes' full-resolution inverse depth and
//! variance (PFM), `states.txt`. A resumed dive's poses are put in the recorded frame here,
//! once ([`finish_trajectory`]).

use duv_core::io::pfm::write_pfm;
use duv_core::pose::se3_to_tum;
use duv_core::{PlaneF32, Sim3, Timestamp};
use duv_track::{FinalTrajectory, KeyframeView, RecordedFrame, TrackError, Tracker, TrajectoryRecorder};
use std::fmt::Write as _;
use std::path::Path;
use std::time::Duration;

/// Why a run's output files could not be written.
#[derive(Debug, thiserror::Error)]
pub enum OutputError {
    #[error(transparent)]
    Io(#[from] duv_core::io::IoError),
    #[error("keyframe {id}: upsampling its depth: {source}")]
    Upsample { id: u64, source: TrackError },
}

/// The final poses of the run ([`TrajectoryRecorder::finish`]), in the recorded map frame when
/// the run resumed a dive (`world_from_tracker`, the resume's alignment).
pub fn finish_trajectory(recorder: &TrajectoryRecorder, tracker: &Tracker, world_from_tracker: Option<&Sim3>) -> FinalTrajectory {
    let mut fin = recorder.finish(tracker);
    if let Some(a) = world_from_tracker {
        for f in &mut fin.frames {
            f.world_from_cam = duv_core::pose::sim3_apply_to_pose(a, &f.world_from_cam);
        }
        for k in &mut fin.keyframes {
            k.world_from_cam = duv_core::pose::sim3_apply_to_pose(a, &k.world_from_cam);
        }
    }
    fin
}

/// Writes `trajectory.txt`, `keyframes.txt` (with `mapped`, only the keyframes whose image the
/// mapping stage wrote into `keyframes/`, so `duv refine --keyframes` reads the folder), the
/// inverse depth and variance of the keyframes still in the tracker's graph, and `states.txt`
/// (`frames` and `latencies` as the tracking thread recorded them). Returns the live keyframes'
/// `(id, frame seq)`; `inv`/`var` are full-resolution scratch planes.
#[allow(clippy::too_many_arguments)]
pub fn write_tracking_outputs(
    out: &Path,
    fin: &FinalTrajectory,
    frames: &[RecordedFrame],
    latencies: &[Duration],
    tracker: &Tracker,
    mapped: bool,
    inv: &mut PlaneF32,
    var: &mut PlaneF32,
) -> Result<Vec<(u64, u64)>, OutputError> {
    let kf_dir = out.join("keyframes");
    duv_core::io::tum::write_trajectory(&out.join("trajectory.txt"), &fin.frames)?;
    let mut kf_text = String::from("# keyframe_id timestamp tx ty tz qx qy qz qw\n");
    for k in &fin.keyframes {
        // With mapping on, the keyframe folder lists the keyframes mapping received (their
        // images are written as they arrive), so `duv refine --keyframes` can read it.
        if mapped && !kf_dir.join(format!("{:06}.png", k.id)).exists() {
            continue;
        }
        let _ = writeln!(kf_text, "{} {}", k.id, tum_line(k.t_ns, &k.world_from_cam));
    }
    duv_core::io::write_atomic(&out.join("keyframes.txt"), kf_text.as_bytes())?;
    let live: Vec<(u64, u64)> = tracker.keyframes().map(|k: KeyframeView| (k.id, k.seq)).collect();
    for &(id, _) in &live {
        tracker.upsample_keyframe(id, inv, var).map_err(|source| OutputError::Upsample { id, source })?;
        write_pfm(&kf_dir.join(format!("{id:06}_invdepth.pfm")), inv)?;
        write_pfm(&kf_dir.join(format!("{id:06}_variance.pfm")), var)?;
    }
    let mut states_text = String::from("# seq timestamp state tracker_ms\n");
    for ((f, s), dt) in frames.iter().zip(&fin.states).zip(latencies) {
        let _ = writeln!(states_text, "{} {:.9} {} {:.3}", f.seq, f.t_ns.as_secs_f64(), s.name().replace(' ', "_"), dt.as_secs_f64() * 1e3);
    }
    duv_core::io::write_atomic(&out.join("states.txt"), states_text.as_bytes())?;
    Ok(live)
}

fn tum_line(t_ns: Timestamp, pose: &duv_core::Se3) -> String {
    let v = se3_to_tum(pose);
    format!("{:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9}", t_ns.as_secs_f64(), v[0], v[1], v[2], v[3], v[4], v[5], v[6])
}
