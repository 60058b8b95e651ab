//! The tracker on CI-sized generated sequences (rendered in memory, 160x120, depth grid 1/4):
//! ATE bounds on a survey and a loop, loop closure lowering the loop's ATE, bit-identical
//! single-thread runs, lost tracking and recovery around black, saturated and turbid frames,
//! errors for frames of the wrong size, and (at 320x240, where turbid water initialises) the
//! variance's consistency term on a turbid survey.
//!
//! Thresholds were measured with `cargo run --release --example track_sim` (same sequences):
//! survey 0.17 % of the path, loop 0.26 % with loop closure and 0.86 % without.

use crate::track_sim;

use duv_core::{Frame, FrameImage, ImageRgb8, Keyframe, PlaneF32};
use duv_eval::umeyama;
use duv_sim::{SimRenderer, TrajectoryKind, WaterPreset};
use duv_track::{LostReason, SeedKeyframe, TrackError, TrackNote, Tracker, TrackerSeed, TrackingState};
use nalgebra::Vector3;
use track_sim::{capacity, render_all, run, sim_config, small_tracker_config};

/// ATE RMSE bound on the survey, percent of path length (measured 0.17 %).
const SURVEY_ATE_PERCENT: f64 = 0.5;
/// ATE RMSE bound on the loop with loop closure, percent of path length (measured 0.26 %).
const LOOP_ATE_PERCENT: f64 = 0.5;
/// A seeded tracker's distance from the uninterrupted one, RMS over the frames after the
/// stop, as a fraction of the uninterrupted path over them (measured 0.029).
const SEEDED_GAP_FRACTION: f64 = 0.06;
/// Relative difference of the seeded and the uninterrupted tracker's scale (each aligned to
/// the truth over the frames after the stop; measured 0.023).
const SEEDED_SCALE_TOLERANCE: f64 = 0.05;

/// ATE bound on the 60-frame turbid survey at 320x240 with the level start, percent of path
/// (measured 0.25 %; 1.87 % from the collected start alone).
const TURBID_INIT_ATE_PERCENT: f64 = 0.6;
/// Bound on the attitude error between the first and the last keyframe of that survey,
/// degrees (measured 1.00; 23.5 from the collected start alone).
const TURBID_INIT_BEND_DEG: f64 = 2.5;

/// AUSE bound on the 100-frame turbid survey at 320x240 with the consistency term (measured
/// 0.113; 0.157 without the term, 0.822 for a random ordering).
const CONSISTENCY_AUSE: f64 = 0.15;

/// ATE bound on the 120-frame night loop with marine snow at 160x120, despeckled with a
/// one-pixel radius, percent of path (measured 0.93; 8.26 without).
const NIGHT_SNOW_ATE_PERCENT: f64 = 1.5;

/// ATE bound on the 2 frames/s survey through its first lane turn at 160x120, percent of path
/// (measured 0.51; without the turned predictions it is lost at the turn).
const LOW_FPS_TURN_ATE_PERCENT: f64 = 1.0;

/// ATE bound on the 120-frame survey under a static overlay with its pixels ignored, percent of
/// path (measured 0.433; unmasked it never initialises).
const OVERLAY_MASKED_ATE_PERCENT: f64 = 1.0;

/// The burst on the 100-frame loop at 160x120 (start and duration, s), the frames with a pose
/// at least and the ATE bound over them after the merge, percent of path (measured 100 frames,
/// 0.596 %; the loop without the burst 0.26 %).
const BURST_LOOP: (f64, f64) = (3.5, 1.5);
const BURST_LOOP_FRAMES: usize = 95;
const BURST_LOOP_ATE_PERCENT: f64 = 1.0;

/// The 100-frame loop at 160x120 with the `BURST_LOOP` turbidity burst.
fn burst_loop() -> (SimRenderer, Vec<Frame>) {
    let cfg = duv_sim::SimConfig {
        burst: Some(duv_sim::Burst { start_s: BURST_LOOP.0, duration_s: BURST_LOOP.1, factor: 8.0 }),
        ..sim_config(WaterPreset::Coastal, TrajectoryKind::Loop, 100, 160, 120, 1.0)
    };
    let renderer = SimRenderer::new(&cfg).unwrap();
    let frames = render_all(&renderer);
    (renderer, frames)
}

/// A keyframe buffer at `camera`'s size for `Tracker::next_final_keyframe`.
fn blank_keyframe(camera: &duv_core::PinholeCamera) -> Keyframe {
    let (w, h) = (camera.width, camera.height);
    Keyframe {
        index: u64::MAX,
        t_ns: duv_core::Timestamp::from_ns(0),
        image: ImageRgb8::new(w, h),
        world_from_cam: duv_core::Se3::identity(),
        camera: *camera,
        inv_depth: PlaneF32::new(w, h),
        inv_depth_variance: PlaneF32::new(w, h),
    }
}

fn survey(frames: usize) -> (SimRenderer, Vec<Frame>) {
    let r = SimRenderer::new(&sim_config(WaterPreset::Coastal, TrajectoryKind::Survey, frames, 160, 120, 0.5)).unwrap();
    let f = render_all(&r);
    (r, f)
}

#[test]
fn survey_ate_is_within_bound() {
    let (renderer, frames) = survey(80);
    let r = run(&renderer, &frames, &small_tracker_config(), capacity(2));
    assert_eq!(r.trajectory.frames.len(), 80);
    assert!(r.outputs.iter().skip(60).all(|o| o.state == TrackingState::Tracking), "tracking after initialisation");
    assert!(r.tracker.num_keyframes() >= 10, "keyframes {}", r.tracker.num_keyframes());
    assert!(r.ate_percent < SURVEY_ATE_PERCENT, "survey ATE {:.3} % of {:.2} m ({:.4} m)", r.ate_percent, r.path_m, r.ate_rmse_m);
    // Every live keyframe has a variance after its window BA, positive and finite.
    for k in r.tracker.keyframes() {
        let v = k.variance.expect("variance");
        assert!(v.data.iter().all(|x| x.is_finite() && *x > 0.0), "keyframe {}", k.id);
        assert!(k.inv_depth.data.iter().all(|d| d.is_finite() && *d > 0.0));
    }
}

#[test]
fn periodic_global_ba_runs_and_keeps_the_survey_accurate() {
    let (renderer, frames) = survey(80);
    let cfg = duv_track::TrackerConfig { global_ba_period: 2, global_iterations: 3, defer_rounds: false, ..small_tracker_config() };
    let r = run(&renderer, &frames, &cfg, capacity(2));
    assert!(r.tracker.counters().global_bas >= 1, "{:?}", r.tracker.counters());
    assert!(r.ate_percent < SURVEY_ATE_PERCENT, "survey ATE with global BA {:.3} %", r.ate_percent);
}

#[test]
fn background_global_ba_is_deterministic_and_as_accurate_as_the_inline_one() {
    let (renderer, frames) = survey(80);
    let base = duv_track::TrackerConfig { global_ba_period: 2, global_iterations: 3, defer_rounds: false, ..small_tracker_config() };
    let inline = run(&renderer, &frames, &duv_track::TrackerConfig { global_ba_lag_frames: 0, ..base.clone() }, capacity(2));
    let lagged = duv_track::TrackerConfig { global_ba_lag_frames: 4, ..base };
    let a = run(&renderer, &frames, &lagged, capacity(2));
    let b = run(&renderer, &frames, &lagged, capacity(2));
    // Applied at a frame count, not when the worker happens to finish: the same poses.
    assert_eq!(a.trajectory.frames.len(), b.trajectory.frames.len());
    for (x, y) in a.trajectory.frames.iter().zip(&b.trajectory.frames) {
        assert_eq!(x.world_from_cam, y.world_from_cam, "frame at {:?}", x.t_ns);
    }
    let (ci, ca) = (inline.tracker.counters(), a.tracker.counters());
    assert!(ca.global_bas >= 1 && ci.global_bas >= 1, "inline {ci:?}, background {ca:?}");
    assert!(a.ate_percent < SURVEY_ATE_PERCENT, "survey ATE with the global BA in the background {:.3} % (inline {:.3} %)", a.ate_percent, inline.ate_percent);
    assert!(a.ate_percent < 1.5 * inline.ate_percent + 0.05, "background {:.3} % against inline {:.3} %", a.ate_percent, inline.ate_percent);
}

#[test]
fn loop_closure_detects_the_loop_and_lowers_ate() {
    let renderer = SimRenderer::new(&sim_config(WaterPreset::Coastal, TrajectoryKind::Loop, 100, 160, 120, 1.0)).unwrap();
    let frames = render_all(&renderer);
    let with = run(&renderer, &frames, &small_tracker_config(), capacity(2));
    let cfg_without = duv_track::TrackerConfig { loop_closure: false, ..small_tracker_config() };
    let without = run(&renderer, &frames, &cfg_without, capacity(2));
    let loop_edges: Vec<_> = with.tracker.edges().filter(|e| e.2).collect();
    assert!(!loop_edges.is_empty(), "no loop edge");
    assert!(with.outputs.iter().any(|o| o.loop_closed));
    // Candidates went through the coarse screen first; the loop passed it.
    assert!(with.tracker.times().loop_screens >= 1, "{:?}", with.tracker.times());
    // The loop joins the start of the run to its end.
    let kf_seq = |id: u64| with.tracker.keyframes().find(|k| k.id == id).unwrap().seq;
    assert!(loop_edges.iter().any(|&(a, b, _)| kf_seq(a).abs_diff(kf_seq(b)) > 50), "{loop_edges:?}");
    assert!(without.tracker.edges().all(|e| !e.2));
    assert!(
        with.ate_percent < without.ate_percent,
        "loop closure: {:.3} % vs {:.3} % without",
        with.ate_percent,
        without.ate_percent
    );
    assert!(with.ate_percent < LOOP_ATE_PERCENT, "loop ATE {:.3} %", with.ate_percent);
}

/// Attitude error of the newest keyframe relative to the oldest, against the truth, degrees.
fn keyframe_bend_deg(tracker: &Tracker, renderer: &SimRenderer) -> f64 {
    let first = tracker.keyframes().next().expect("keyframes");
    let last = tracker.keyframes().last().expect("keyframes");
    let truth = renderer.pose(first.seq as usize).world_from_cam.inv_mul(&renderer.pose(last.seq as usize).world_from_cam);
    let estimate = first.world_from_cam.inv_mul(&last.world_from_cam);
    (truth.rotation.inverse() * estimate.rotation).angle().to_degrees()
}

/// Turbid water at 320x240: the first keyframes see a near strip of seabed, and the estimate
/// grown keyframe by keyframe from constant depth settles in the other two-view solution of a
/// near-planar scene, a camera pitching about 2.5 degrees per keyframe over a seabed bent to
/// match. The initial BA's second, level start ends at a far lower cost and is kept.
#[test]
fn turbid_initialisation_keeps_the_level_start_and_does_not_bend() {
    let renderer = SimRenderer::new(&sim_config(WaterPreset::Turbid, TrajectoryKind::Survey, 60, 320, 240, 0.5)).unwrap();
    let frames = render_all(&renderer);
    let r = run(&renderer, &frames, &small_tracker_config(), capacity(2));
    let bend = keyframe_bend_deg(&r.tracker, &renderer);
    println!("level start: ATE {:.3} %, bend {bend:.2} deg over {} keyframes", r.ate_percent, r.tracker.num_keyframes());
    assert!(r.tracker.counters().init_level_start, "{:?}", r.tracker.counters());
    assert!(r.tracker.num_keyframes() >= 8, "{} keyframes", r.tracker.num_keyframes());
    assert!(bend < TURBID_INIT_BEND_DEG, "bend {bend:.2} deg");
    assert!(r.ate_percent < TURBID_INIT_ATE_PERCENT, "turbid ATE {:.3} % of {:.2} m", r.ate_percent, r.path_m);
    // The collected start alone, for comparison: the bend the level start removes.
    let cfg = duv_track::TrackerConfig { init_level_start: false, ..small_tracker_config() };
    let collected = run(&renderer, &frames, &cfg, capacity(2));
    let collected_bend = keyframe_bend_deg(&collected.tracker, &renderer);
    println!("collected start: ATE {:.3} %, bend {collected_bend:.2} deg", collected.ate_percent);
    assert!(!collected.tracker.counters().init_level_start);
    assert!(collected_bend > 3.0 * bend.max(0.5), "collected bend {collected_bend:.2} deg against {bend:.2}");
}

/// One deferred stage per frame on the 1 m/s loop: keyframes come every two or three frames,
/// faster than their stages, so each new keyframe finishes the previous one's first. It must
/// start from the frame's pose re-anchored to the solved reference: from the pose measured
/// before the solve this loop drifted to 8.0 % of the path (measured 0.30 % now).
#[test]
fn stages_falling_behind_fast_motion_do_not_drift_the_map() {
    let renderer = SimRenderer::new(&sim_config(WaterPreset::Coastal, TrajectoryKind::Loop, 100, 160, 120, 1.0)).unwrap();
    let frames = render_all(&renderer);
    let cfg = duv_track::TrackerConfig { stages_per_frame: 1, ..small_tracker_config() };
    let r = run(&renderer, &frames, &cfg, capacity(2));
    assert!(r.tracker.counters().keyframes_inserted >= 40, "{:?}", r.tracker.counters());
    assert!(r.ate_percent < LOOP_ATE_PERCENT, "loop ATE with one stage per frame {:.3} %", r.ate_percent);
}

#[test]
fn one_thread_runs_are_bit_identical() {
    let (renderer, frames) = survey(64);
    let a = run(&renderer, &frames, &small_tracker_config(), capacity(1));
    let b = run(&renderer, &frames, &small_tracker_config(), capacity(1));
    assert!(a.outputs.last().unwrap().state == TrackingState::Tracking, "initialised");
    for (x, y) in a.trajectory.frames.iter().zip(&b.trajectory.frames) {
        let (px, py) = (x.world_from_cam.to_homogeneous(), y.world_from_cam.to_homogeneous());
        assert!(px.iter().zip(py.iter()).all(|(u, v)| u.to_bits() == v.to_bits()), "frame {:?} differs", x.t_ns);
    }
    for (ka, kb) in a.tracker.keyframes().zip(b.tracker.keyframes()) {
        assert_eq!(ka.inv_depth.data, kb.inv_depth.data);
    }
}

/// Every pixel set to `v`.
fn flat(width: usize, height: usize, v: u8) -> FrameImage {
    FrameImage::Rgb8(ImageRgb8 { width, height, data: vec![v; width * height * 3] })
}

/// A turbidity burst: the image blended `amount` of the way to a uniform green-grey veil.
fn turbid(image: &FrameImage, amount: f32) -> FrameImage {
    let FrameImage::Rgb8(img) = image else { unreachable!() };
    let veil = [70.0, 110.0, 95.0];
    let data = img.data.iter().enumerate().map(|(i, &v)| ((1.0 - amount) * v as f32 + amount * veil[i % 3]).round() as u8).collect();
    FrameImage::Rgb8(ImageRgb8 { width: img.width, height: img.height, data })
}

#[test]
fn bad_frames_are_lost_then_tracking_recovers_and_the_map_is_untouched() {
    let (renderer, mut frames) = survey(90);
    let (w, h) = (160, 120);
    // Black frames, a saturated one, then a turbidity burst (contrast collapse).
    for i in [64, 65, 66] {
        frames[i].image = flat(w, h, 0);
    }
    frames[67].image = flat(w, h, 255);
    for (i, amount) in [(72, 0.97), (73, 0.99), (74, 0.97)] {
        frames[i].image = turbid(&frames[i].image, amount);
    }
    let bad: Vec<usize> = vec![64, 65, 66, 67, 72, 73, 74];
    let mut tracker = Tracker::new(renderer.camera(), &small_tracker_config(), capacity(2)).unwrap();
    let mut states = Vec::new();
    let mut keyframes_before_bad = 0;
    for (i, f) in frames.iter().enumerate() {
        if i == 64 {
            keyframes_before_bad = tracker.num_keyframes();
        }
        let out = tracker.track(f).unwrap();
        if bad.contains(&i) {
            assert!(out.new_keyframe.is_none() && out.anchor.is_none(), "frame {i} touched the map");
            assert!(out.world_from_cam.translation.vector.iter().all(|v| v.is_finite()));
        }
        states.push(out.state);
    }
    assert_eq!(states[63], TrackingState::Tracking);
    for i in [64, 65, 66] {
        assert_eq!(states[i], TrackingState::Lost(LostReason::Black), "frame {i}");
    }
    assert_eq!(states[67], TrackingState::Lost(LostReason::Saturated));
    for i in [72, 73, 74] {
        assert!(matches!(states[i], TrackingState::Lost(LostReason::LowContrast | LostReason::LowConfidence)), "frame {i}: {:?}", states[i]);
    }
    assert!(matches!(states[68], TrackingState::Relocalised), "frame 68: {:?}", states[68]);
    assert!(matches!(states[75], TrackingState::Relocalised), "frame 75: {:?}", states[75]);
    assert!(states[80..].iter().all(|s| *s == TrackingState::Tracking), "{:?}", &states[80..]);
    // No keyframe from a bad frame, none lost while the view was bad.
    assert!(tracker.num_keyframes() >= keyframes_before_bad);
    assert!(tracker.keyframes().all(|k| !bad.contains(&(k.seq as usize))));
    assert!(tracker.counters().lost_frames >= bad.len() as u64);
    // The whole run is still accurate (bad frames interpolated).
    let mut rec = duv_track::TrajectoryRecorder::new();
    let mut tracker2 = Tracker::new(renderer.camera(), &small_tracker_config(), capacity(2)).unwrap();
    for f in &frames {
        rec.record(&tracker2.track(f).unwrap());
    }
    let fin = rec.finish(&mut tracker2);
    let (_, percent, _) = track_sim::ate(renderer.poses(), &fin.frames);
    assert!(percent < 2.0 * SURVEY_ATE_PERCENT, "ATE with bad frames {percent:.3} %");
}

/// While it initialises, every frame says what the tracker waits for: the same view again has
/// no parallax (a mean flow near 0 px against the 2.5-px-per-grid-cell threshold), a featureless
/// frame no confident flow, and a moved view a keyframe counted against the eight it takes.
#[test]
fn initialising_frames_say_what_the_tracker_waits_for() {
    let (renderer, frames) = survey(40);
    let mut t = Tracker::new(renderer.camera(), &small_tracker_config(), capacity(1)).unwrap();
    let first = t.track(&frames[0]).unwrap();
    assert_eq!(first.note, TrackNote::None);
    let same = Frame { seq: 1, t_ns: frames[1].t_ns, image: frames[0].image.clone() };
    let out = t.track(&same).unwrap();
    let TrackNote::InitSmallFlow { flow_px, needed_px } = out.note else { panic!("{:?}", out.note) };
    assert!(flow_px < 0.5 && needed_px >= 2.0, "{flow_px} {needed_px}");
    assert!(out.note.to_string().contains("waiting for parallax"));
    // A grey frame with a faint gradient: no texture to trust (contrast above the lost
    // threshold, so it reaches the flow).
    let (w, h) = (renderer.camera().width, renderer.camera().height);
    let mut grad = ImageRgb8::new(w, h);
    for (i, v) in grad.data.iter_mut().enumerate() {
        *v = (90 + ((i / 3) % w) * 60 / w) as u8;
    }
    let out = t.track(&Frame { seq: 2, t_ns: frames[2].t_ns, image: FrameImage::Rgb8(grad) }).unwrap();
    assert!(matches!(out.note, TrackNote::InitLowConfidence { .. } | TrackNote::None) || matches!(out.state, TrackingState::Lost(_)), "{:?} {:?}", out.note, out.state);
    // Real motion: sooner or later a keyframe, counted.
    let mut counted = None;
    for f in &frames[3..] {
        let o = t.track(f).unwrap();
        if let TrackNote::InitKeyframe { keyframes, needed } = o.note {
            counted = Some((keyframes, needed));
            break;
        }
    }
    let (k, n) = counted.expect("an initialisation keyframe within 40 frames");
    assert!(k >= 2 && n == 8, "{k} of {n}");
}

/// An initialisation that started on a view the vehicle never sees again (here the first
/// frame of another seabed) starts again from the current frame after `init_restart_after`
/// unmatched frames, initialises, and leaves the frames before the restart without a pose
/// (`PoseSource::None`, out of the trajectory); without the restart it waits for ever.
#[test]
fn an_initialisation_that_cannot_match_its_first_view_starts_again() {
    let (renderer, mut frames) = survey(60);
    let other_cfg = duv_sim::SimConfig { seed: 7, ..track_sim::sim_config(WaterPreset::Coastal, TrajectoryKind::Loop, 1, 160, 120, 0.5) };
    let alien = SimRenderer::new(&other_cfg).unwrap().render(0);
    frames[0].image = FrameImage::Rgb8(alien.rgb);
    let run = |restart_after: usize| {
        let cfg = duv_track::TrackerConfig { init_restart_after: restart_after, ..small_tracker_config() };
        let mut t = Tracker::new(renderer.camera(), &cfg, capacity(1)).unwrap();
        let mut rec = duv_track::TrajectoryRecorder::new();
        let outs: Vec<_> = frames.iter().map(|f| t.track(f).unwrap()).collect();
        outs.iter().for_each(|o| rec.record(o));
        let fin = rec.finish(&mut t);
        (outs, fin, t.counters())
    };
    let (outs, fin, counters) = run(3);
    let restart = outs.iter().position(|o| matches!(o.note, TrackNote::InitRestarted { .. })).expect("a restart");
    let TrackNote::InitRestarted { failed_frames, dropped_keyframes } = outs[restart].note else { unreachable!() };
    assert_eq!((restart, failed_frames, dropped_keyframes), (3, 3, 1), "{:?}", outs[restart].note);
    assert!(outs[restart].note.to_string().contains("restarted"));
    assert_eq!(counters.init_restarts, 1);
    let first_tracked = outs.iter().position(|o| o.state == TrackingState::Tracking).expect("initialised after the restart");
    // As many frames after the restart as an initialisation from frame 0 takes.
    let mut plain = Tracker::new(renderer.camera(), &small_tracker_config(), capacity(1)).unwrap();
    let (_, clean) = survey(60);
    let plain_first = clean.iter().position(|f| plain.track(f).unwrap().state == TrackingState::Tracking).expect("initialises");
    assert!(first_tracked - restart <= plain_first + 2, "initialised {} frames after the restart, {plain_first} from frame 0", first_tracked - restart);
    // Frames before the restart have no pose; the restart frame on is estimated.
    assert!(fin.sources[..restart].iter().all(|s| *s == duv_track::PoseSource::None), "{:?}", &fin.sources[..restart]);
    assert!(fin.sources[restart..].iter().all(|s| s.has_pose()), "{:?}", &fin.sources[restart..]);
    let estimated: Vec<_> = fin.estimated();
    let (_, percent, _) = track_sim::ate(&renderer.poses()[restart..], &estimated);
    assert!(percent < 2.0 * SURVEY_ATE_PERCENT, "ATE after the restart {percent:.3} %");
    // Without the restart it never leaves the first view.
    let (outs, fin, counters) = run(0);
    assert_eq!(counters.init_restarts, 0);
    assert!(outs.iter().all(|o| o.state == TrackingState::Initializing), "{:?}", outs.iter().map(|o| o.state).collect::<Vec<_>>());
    assert!(outs[1..].iter().all(|o| matches!(o.note, TrackNote::InitLowConfidence { .. } | TrackNote::InitPoseFailed)));
    assert!(fin.sources.iter().all(|s| *s == duv_track::PoseSource::None));
}

/// Two more kinds of bad input: a frame filled with marine snow (a cloud of particles close to
/// the lens, 5000 per m^3 under lamps) and a frame after a 3 s gap in the stream (the vehicle
/// moved on). Neither writes a false pose: the snowy frame is tracked or reported lost without
/// touching the map, and after the gap tracking goes on (relocalised, or in a new map segment)
/// with every pose, each segment aligned on its own, close to the truth.
#[test]
fn a_snow_filled_frame_and_a_frame_after_a_long_gap_write_no_false_pose() {
    let cfg = sim_config(WaterPreset::Coastal, TrajectoryKind::Survey, 200, 160, 120, 0.5);
    let renderer = SimRenderer::new(&cfg).unwrap();
    let mut frames = render_all(&renderer);
    let snowy = SimRenderer::new(&duv_sim::SimConfig { lamps: true, snow_per_m3: 5000.0, ..cfg.clone() }).unwrap();
    let snow_at = 75;
    frames[snow_at].image = FrameImage::Rgb8(snowy.render(snow_at).rgb);
    // 30 frames (3 s) never arrive.
    let gap = 100..130;
    let kept: Vec<Frame> = frames.iter().filter(|f| !gap.contains(&(f.seq as usize))).cloned().collect();
    let mut tracker = Tracker::new(renderer.camera(), &small_tracker_config(), capacity(2)).unwrap();
    let mut rec = duv_track::TrajectoryRecorder::new();
    let outs: Vec<_> = kept.iter().map(|f| tracker.track(f).unwrap()).collect();
    outs.iter().for_each(|o| rec.record(o));
    let fin = rec.finish(&mut tracker);
    let by_seq = |seq: usize| outs.iter().position(|o| o.seq as usize == seq).unwrap();
    // The snowy frame: tracked, or lost without touching the map.
    let o = &outs[by_seq(snow_at)];
    assert!(o.state.is_tracked() || (o.anchor.is_none() && o.new_keyframe.is_none()), "{:?}", o);
    // After the gap: relocalised where the old view still overlaps, or a new segment; either
    // way every pose, each segment aligned on its own, stays close to the truth.
    let after = by_seq(gap.end);
    eprintln!("after the gap: {:?}", outs[after..after + 6].iter().map(|o| (o.seq, o.state, o.segment)).collect::<Vec<_>>());
    // (Measured: lost on the 3 frames after the gap, segment 1 from the 4th; segment 0 100
    // frames with a pose at 0.216 % of path, segment 1 67 at 0.353 %.)
    assert!(outs[after..after + 6].iter().any(|o| o.state.is_tracked() || matches!(o.note, TrackNote::NewSegment { .. })), "neither relocalised nor a new segment");
    let counts = fin.segment_counts();
    let poses = renderer.poses();
    for &(segment, n) in &counts {
        let est = fin.estimated_in(segment);
        let (_, percent, _) = track_sim::ate(poses, &est);
        eprintln!("segment {segment}: {n} frames with a pose, ATE {percent:.3} % of path");
        assert!(percent < 2.0 * SURVEY_ATE_PERCENT, "segment {segment}: ATE {percent:.3} %");
    }
    let with_pose: usize = counts.iter().map(|c| c.1).sum();
    assert!(with_pose >= kept.len() - 60, "{with_pose} of {} frames with a pose", kept.len());
}

/// Keyframe emission across map segments: only segment 0's are handed on; another segment's
/// is skipped when it is due, so nothing piles up waiting (a caller holds each waiting
/// keyframe's frame: a queue that grew with an unmerged segment drained the frame pool and
/// stopped the capture of a real dive). After the merge the keyframes are segment 0's again.
#[test]
fn keyframes_of_another_segment_are_skipped_not_held() {
    let (renderer, frames) = burst_loop();
    let lag = 2;
    let mut t = Tracker::new(renderer.camera(), &small_tracker_config(), capacity(2)).unwrap();
    t.emit_keyframes_after(lag);
    let mut kf = blank_keyframe(renderer.camera());
    let mut emitted = Vec::new();
    let mut most_waiting = 0;
    for f in &frames {
        t.track(f).unwrap();
        while let Some(id) = t.next_final_keyframe(false, &mut kf) {
            emitted.push(id);
        }
        most_waiting = most_waiting.max(t.keyframes_waiting().len());
    }
    while let Some(id) = t.next_final_keyframe(true, &mut kf) {
        emitted.push(id);
    }
    let c = t.counters();
    assert!(c.segments_started >= 1 && c.segments_merged >= 1, "{c:?}");
    assert!(t.keyframes_of_other_segments() >= 1, "no keyframe of segment 1 was due before the merge");
    // Never more waiting than the initialisation's keyframes (none is final before its BA) and
    // the lag; held back, the 37 keyframes of segment 1 would have waited for the merge.
    assert!(most_waiting <= small_tracker_config().init_keyframes + lag, "{most_waiting} keyframes waited");
    // Every live keyframe is segment 0's now; the emitted ones were segment 0's when due.
    assert!(t.keyframes().all(|k| k.segment == 0));
    assert!(emitted.windows(2).all(|w| w[0] < w[1]), "{emitted:?}");
    assert!(emitted.len() as u64 + t.keyframes_of_other_segments() <= c.keyframes_inserted);
    assert!(emitted.len() >= 20, "{} keyframes emitted", emitted.len());
}

/// A frame that cannot be matched while the initialisation has collected enough keyframes
/// (`init_min_keyframes`) runs the initial BA on them at once and is tracked as after a loss:
/// the keyframes are kept (not dropped by a restart) and tracking goes on from the next frame.
#[test]
fn a_collection_interrupted_after_enough_keyframes_initialises_early() {
    let (renderer, clean) = survey(60);
    // Where the clean run has collected 4 keyframes.
    let mut t = Tracker::new(renderer.camera(), &small_tracker_config(), capacity(1)).unwrap();
    let outs: Vec<_> = clean.iter().map(|f| t.track(f).unwrap()).collect();
    let fourth = outs.iter().position(|o| matches!(o.note, TrackNote::InitKeyframe { keyframes: 4, .. })).expect("4 keyframes collected");
    let plain_first = outs.iter().position(|o| o.state == TrackingState::Tracking).expect("initialises");
    assert!(plain_first > fourth + 3, "the clean run initialises at {plain_first}, 4 keyframes at {fourth}");
    // A featureless frame with contrast (a smooth gradient: sediment close to the lens): it
    // passes the image checks, and no flow matches it.
    let mut frames = clean.clone();
    let at = fourth + 2;
    let (w, h) = (160usize, 120usize);
    frames[at].image = FrameImage::Rgb8(ImageRgb8 { width: w, height: h, data: (0..w * h * 3).map(|i| (40 + (i / 3 % w) * 160 / w) as u8).collect() });
    let run = |init_min_keyframes: usize| {
        let cfg = duv_track::TrackerConfig { init_min_keyframes, ..small_tracker_config() };
        let mut t = Tracker::new(renderer.camera(), &cfg, capacity(1)).unwrap();
        let mut rec = duv_track::TrajectoryRecorder::new();
        let outs: Vec<_> = frames.iter().map(|f| t.track(f).unwrap()).collect();
        outs.iter().for_each(|o| rec.record(o));
        (outs, rec.finish(&mut t), t.counters())
    };
    let (outs, fin, counters) = run(4);
    assert_eq!(counters.init_early, 1, "{:?}", outs[fourth..at + 3].iter().map(|o| (o.seq, o.state, o.note)).collect::<Vec<_>>());
    assert!(matches!(outs[at].note, TrackNote::InitEarly { keyframes: 4, needed: 8 }), "{:?}", outs[at].note);
    assert!(outs[at].note.to_string().contains("initialised early"));
    assert!(matches!(outs[at].state, TrackingState::Lost(_)), "{:?}", outs[at].state);
    assert!(outs[at + 1..].iter().all(|o| o.state.is_tracked()), "{:?}", outs[at + 1..].iter().map(|o| o.state).collect::<Vec<_>>());
    assert_eq!(counters.init_restarts, 0);
    let est = fin.estimated();
    assert!(est.len() >= 58, "{} frames with a pose", est.len());
    let (_, percent, _) = track_sim::ate(renderer.poses(), &est);
    assert!(percent < 2.0 * SURVEY_ATE_PERCENT, "ATE {percent:.3} %");
    // Off: the frame waits, and the collection goes on to init_keyframes.
    let (outs, _, counters) = run(0);
    assert_eq!(counters.init_early, 0);
    assert!(matches!(outs[at].note, TrackNote::InitLowConfidence { .. }), "{:?}", outs[at].note);
}

/// Marine snow on a lamp-lit night loop (the generator's `--night`: lamps, their glow in the
/// water, 150 particles per m^3 near the camera): with the specks taken out of the grey image
/// (`despeckle`, the default) the loop tracks as it does in clear water; without, the
/// particles' parallax bends the map.
#[test]
fn marine_snow_is_taken_out_before_the_flow() {
    let mut cfg = track_sim::sim_config(WaterPreset::Coastal, TrajectoryKind::Loop, 120, 160, 120, 0.5);
    cfg.apply_night();
    let renderer = SimRenderer::new(&cfg).unwrap();
    let frames = render_all(&renderer);
    let run = |despeckle: bool| {
        // At 160x120 the automatic radius is off: one pixel (3-pixel specks) is asked for.
        let tc = duv_track::TrackerConfig { despeckle, despeckle_radius_px: 1, ..small_tracker_config() };
        let r = track_sim::run(&renderer, &frames, &tc, capacity(2));
        let est: Vec<_> = r.trajectory.estimated();
        assert!(est.len() >= 100, "{} of 120 frames with a pose", est.len());
        let (_, percent, _) = track_sim::ate(renderer.poses(), &est);
        percent
    };
    let (with, without) = (run(true), run(false));
    eprintln!("night loop with snow, 120 frames at 160x120: ATE {with:.3} % of path with despeckle, {without:.3} % without");
    assert!(with < NIGHT_SNOW_ATE_PERCENT, "ATE with despeckle {with:.3} %");
    assert!(without > 2.0 * with, "without despeckle {without:.3} %, with {with:.3} %");
}

/// A survey's lane turn at 2 frames/s turns the camera about 9.5 degrees a frame while the
/// motion model predicts the straight lane's; the turned predictions (`turn_search_deg`) keep
/// it tracked through the turn, where without them it is lost for good.
#[test]
fn a_fast_turn_at_a_low_frame_rate_is_tracked_through() {
    let cfg = duv_sim::SimConfig { fps: 2.0, ..track_sim::sim_config(WaterPreset::Coastal, TrajectoryKind::Survey, 70, 160, 120, 0.5) };
    let renderer = SimRenderer::new(&cfg).unwrap();
    let frames = render_all(&renderer);
    let run = |turn_search_deg: f32| {
        let tc = duv_track::TrackerConfig { turn_search_deg, ..small_tracker_config() };
        let r = track_sim::run(&renderer, &frames, &tc, capacity(2));
        let est: Vec<_> = r.trajectory.estimated();
        let percent = if est.len() >= 3 { track_sim::ate(renderer.poses(), &est).1 } else { f64::NAN };
        (est.len(), percent, r.tracker.counters().turns_found)
    };
    let (with_pose, percent, turns) = run(8.0);
    let (without_pose, _, no_turns) = run(0.0);
    eprintln!("2 fps survey through a lane turn, 70 frames at 160x120: {with_pose} frames with a pose ({turns} found turned), ATE {percent:.3} % of path; without turns {without_pose}");
    // One turned prediction is enough: the pose it finds gives the motion model the turn rate.
    assert!(with_pose >= 68 && turns >= 1, "{with_pose} frames with a pose, {turns} turns");
    assert!(percent < LOW_FPS_TURN_ATE_PERCENT, "ATE {percent:.3} %");
    assert!(without_pose < 60 && no_turns == 0, "without turns {without_pose} frames with a pose");
}

/// A turbidity burst in the middle of a loop: tracking is lost, relocalisation finds nothing
/// where the vehicle came out of it, so a new map segment starts (`new_segment_after`); when
/// the loop comes back over its start, a keyframe of the new segment matches one of the first
/// and the two merge with the Sim(3) the match measures. The final trajectory is one segment
/// and scores like the loop without the burst; without new segments the run never tracks again.
#[test]
fn a_new_segment_after_a_loss_merges_when_the_loop_returns() {
    let (renderer, frames) = burst_loop();
    let run_with = |new_segment_after: usize| {
        let tc = duv_track::TrackerConfig { new_segment_after, ..small_tracker_config() };
        track_sim::run(&renderer, &frames, &tc, capacity(2))
    };
    let r = run_with(3);
    let c = r.tracker.counters();
    let started = r.outputs.iter().position(|o| matches!(o.note, TrackNote::NewSegment { .. })).expect("a new segment");
    let TrackNote::NewSegment { segment, failed_frames } = r.outputs[started].note else { unreachable!() };
    assert_eq!((segment, failed_frames), (1, 3), "{:?}", r.outputs[started].note);
    assert!(r.outputs[started].note.to_string().contains("segment 1"));
    // Live, the frames after it are in segment 1 until the merge puts them in segment 0.
    let merged = r.outputs.iter().position(|o| o.loop_closed && o.seq as usize > started).expect("a merge");
    assert!(r.outputs[started..merged].iter().all(|o| o.segment == 1), "{:?}", r.outputs[started..merged].iter().map(|o| o.segment).collect::<Vec<_>>());
    assert!(r.outputs[merged..].iter().all(|o| o.segment == 0));
    assert!(c.segments_started >= 1 && c.segments_merged >= 1, "{c:?}");
    assert_eq!(r.tracker.live_segments(), 1);
    let counts = r.trajectory.segment_counts();
    assert_eq!(counts.len(), 1, "{counts:?}");
    let est = r.trajectory.estimated();
    let (_, percent, _) = track_sim::ate(renderer.poses(), &est);
    // Only frames in the burst may lack a pose (after the merge its frames lie between two
    // measured poses of one segment, less than 2 s apart, and are interpolated).
    let burst = (BURST_LOOP.0 * 10.0) as usize..((BURST_LOOP.0 + BURST_LOOP.1) * 10.0) as usize;
    let without_pose: Vec<usize> = (0..frames.len()).filter(|&i| !r.trajectory.sources[i].has_pose()).collect();
    eprintln!("loop with a burst, 100 frames at 160x120: {} frames with a pose, segments {counts:?}, {c:?}, ATE {percent:.3} % of path; without a pose {without_pose:?}", est.len());
    assert!(est.len() >= BURST_LOOP_FRAMES, "{} frames with a pose", est.len());
    assert!(percent < BURST_LOOP_ATE_PERCENT, "ATE {percent:.3} %");
    // Without new segments it stays lost after the burst.
    let r0 = run_with(0);
    let est0 = r0.trajectory.estimated();
    assert_eq!(r0.tracker.counters().segments_started, 0);
    assert!(est0.len() + 20 < est.len(), "{} frames with a pose without new segments, {} with", est0.len(), est.len());
    assert!(without_pose.iter().all(|i| burst.contains(i)), "frames outside the burst without a pose: {without_pose:?}");
}

/// A static textured overlay (a burned-in display, the vehicle's frame in view) over a
/// quarter of every frame: its zero flow holds the motion back unless its pixels are ignored
/// (`Tracker::set_ignore_mask`); with the mask the survey tracks as it does without overlay.
#[test]
fn an_ignore_mask_keeps_a_static_overlay_out_of_the_flow() {
    let (renderer, mut frames) = survey(120);
    let (w, h) = (renderer.camera().width, renderer.camera().height);
    let mut mask = vec![0u8; w * h];
    for f in &mut frames {
        let FrameImage::Rgb8(img) = &mut f.image else { unreachable!() };
        for y in h / 2..h {
            for x in 0..w / 2 {
                let v = if ((x / 4) + (y / 4)) % 2 == 0 { 40 } else { 210 };
                img.data[(y * w + x) * 3..(y * w + x) * 3 + 3].fill(v);
                mask[y * w + x] = 1;
            }
        }
    }
    let run = |masked: bool| {
        let mut t = Tracker::new(renderer.camera(), &small_tracker_config(), capacity(2)).unwrap();
        if masked {
            t.set_ignore_mask(&mask).unwrap();
        }
        let mut rec = duv_track::TrajectoryRecorder::new();
        for f in &frames {
            rec.record(&t.track(f).unwrap());
        }
        let fin = rec.finish(&mut t);
        let est: Vec<_> = fin.estimated();
        let percent = if est.len() >= 3 { track_sim::ate(renderer.poses(), &est).1 } else { f64::NAN };
        (est.len(), percent)
    };
    let (with_pose, masked) = run(true);
    let (without_pose, unmasked) = run(false);
    eprintln!("survey under a static overlay, 120 frames at 160x120: masked {with_pose} frames with a pose, ATE {masked:.3} %; unmasked {without_pose} frames, ATE {unmasked:.3} %");
    assert!(with_pose >= 90 && masked < OVERLAY_MASKED_ATE_PERCENT, "masked: {with_pose} frames, ATE {masked:.3} %");
    // Unmasked it never initialises here (the overlay's zero flow holds the parallax down).
    assert!(without_pose < with_pose / 2 || unmasked > 2.0 * masked, "unmasked: {without_pose} frames, ATE {unmasked:.3} %");
    // A mask of the wrong size is an error naming the sizes.
    let mut t = Tracker::new(renderer.camera(), &small_tracker_config(), capacity(1)).unwrap();
    let e = t.set_ignore_mask(&[0u8; 7]).unwrap_err();
    assert!(e.to_string().contains("7 pixels") && e.to_string().contains("160x120"), "{e}");
}

#[test]
fn wrong_frame_size_is_an_error_not_a_panic() {
    let (renderer, frames) = survey(2);
    let mut tracker = Tracker::new(renderer.camera(), &small_tracker_config(), capacity(1)).unwrap();
    tracker.track(&frames[0]).unwrap();
    let small = Frame { t_ns: frames[1].t_ns, seq: 1, image: flat(80, 60, 128) };
    assert!(matches!(tracker.track(&small), Err(TrackError::FrameSize { width: 80, height: 60, .. })));
    tracker.track(&frames[1]).unwrap();
}

/// Keyframes of `tracker` as the pipeline logs them (full-resolution inverse depth and
/// variance, the frame's image), without the newest `lag` (still in the BA window: not logged
/// yet); the newest `count` of the rest, oldest first, with their frame seq.
fn logged_keyframes(tracker: &Tracker, frames: &[Frame], lag: usize, count: usize) -> Vec<(u64, Keyframe)> {
    let cam = *tracker.camera();
    let views: Vec<(u64, u64, duv_core::Timestamp, duv_core::Se3)> = tracker.keyframes().map(|k| (k.id, k.seq, k.t_ns, k.world_from_cam)).collect();
    let logged = &views[..views.len().saturating_sub(lag)];
    logged[logged.len().saturating_sub(count)..]
        .iter()
        .map(|&(id, seq, t_ns, world_from_cam)| {
            let mut inv_depth = PlaneF32::new(cam.width, cam.height);
            let mut inv_depth_variance = PlaneF32::new(cam.width, cam.height);
            tracker.upsample_keyframe(id, &mut inv_depth, &mut inv_depth_variance).unwrap();
            (seq, Keyframe { index: id, t_ns, image: frames[seq as usize].image.to_rgb8(), world_from_cam, camera: cam, inv_depth, inv_depth_variance })
        })
        .collect()
}

/// Positions of `poses` (seq, pose) and of the ground truth at the same frames.
fn positions(poses: &[(u64, duv_core::Se3)], gt: &[duv_core::StampedPose]) -> (Vec<Vector3<f64>>, Vec<Vector3<f64>>) {
    poses.iter().map(|(s, p)| (p.translation.vector, gt[*s as usize].world_from_cam.translation.vector)).unzip()
}

/// Resume, tracker side: a tracker seeded with the keyframes a stopped run had logged
/// continues that run's trajectory in its frame and scale (no alignment), as close to an
/// uninterrupted tracker as the uninterrupted tracker is to the truth.
#[test]
fn a_seeded_tracker_continues_in_the_recorded_frame_and_scale() {
    const STOP: usize = 110;
    const LAG: usize = 8;
    let (renderer, frames) = survey(160);
    let gt = renderer.poses();
    // The uninterrupted run; what it had logged when frame STOP was tracked.
    let mut a = Tracker::new(renderer.camera(), &small_tracker_config(), capacity(2)).unwrap();
    let mut a_poses = Vec::new();
    let mut logged = Vec::new();
    for f in &frames {
        a_poses.push((f.seq, a.track(f).unwrap().world_from_cam));
        if f.seq as usize == STOP {
            logged = logged_keyframes(&a, &frames, LAG, LAG);
        }
    }
    assert!(logged.len() >= 4, "{} keyframes logged by frame {STOP}", logged.len());
    let seeds: Vec<SeedKeyframe> = logged.iter().map(|(seq, k)| SeedKeyframe { seq: *seq, keyframe: k }).collect();
    let newest = seeds[seeds.len() - 1].seq as usize;
    let mut b = Tracker::new(renderer.camera(), &small_tracker_config(), capacity(2)).unwrap();
    b.seed(&TrackerSeed { keyframes: &seeds, frames: &[], resume: None, next_keyframe_id: 500 }).unwrap();
    assert_eq!(b.num_keyframes(), logged.len());
    assert!(b.keyframes().zip(&logged).all(|(v, (seq, k))| v.id == k.index && v.seq == *seq && v.world_from_cam == k.world_from_cam));
    assert!(b.edges().count() >= 2 * (logged.len() - 1), "{} edges between the seeded keyframes", b.edges().count());
    // Track the logged frames after the newest seeded keyframe again, then the new ones.
    let mut b_poses = Vec::new();
    for f in &frames[newest + 1..] {
        let out = b.track(f).unwrap();
        assert!(out.state.is_tracked(), "frame {}: {:?}", f.seq, out.state);
        if let Some(id) = out.new_keyframe {
            assert!(id >= 500, "new keyframe id {id}");
        }
        if f.seq as usize > STOP {
            b_poses.push((f.seq, out.world_from_cam));
        }
    }
    let after = &a_poses[STOP + 1..];
    // Same frame, no alignment: the seeded run's positions against the uninterrupted run's.
    let a_path: f64 = after.windows(2).map(|w| (w[1].1.translation.vector - w[0].1.translation.vector).norm()).sum();
    let gap = (b_poses.iter().zip(after).map(|((_, p), (_, q))| (p.translation.vector - q.translation.vector).norm_squared()).sum::<f64>() / after.len() as f64).sqrt();
    // Same scale: each run's segment aligned to the truth by Sim(3).
    let (pa, ga) = positions(after, gt);
    let (pb, gb) = positions(&b_poses, gt);
    let (sa, sb) = (umeyama(&pa, &ga, true).unwrap().scaling(), umeyama(&pb, &gb, true).unwrap().scaling());
    // And as close to the truth: ATE of the whole run, the seeded continuation after STOP.
    let combined: Vec<(u64, duv_core::Se3)> = a_poses[..=STOP].iter().copied().chain(b_poses.iter().copied()).collect();
    let ate = |poses: &[(u64, duv_core::Se3)]| {
        let (p, g) = positions(poses, gt);
        let s = umeyama(&p, &g, true).unwrap();
        (p.iter().zip(&g).map(|(p, g)| (s.transform_point(&(*p).into()).coords - g).norm_squared()).sum::<f64>() / p.len() as f64).sqrt()
    };
    let (ate_a, ate_combined) = (ate(&a_poses), ate(&combined));
    eprintln!("seeded at frame {newest} (stop {STOP}): gap {gap:.4} over a {a_path:.3} path, scale {sb:.4} vs {sa:.4}, ATE combined {ate_combined:.4} m vs uninterrupted {ate_a:.4} m");
    assert!(gap < SEEDED_GAP_FRACTION * a_path, "seeded run {gap} from the uninterrupted one over a {a_path} path");
    assert!((sb / sa - 1.0).abs() < SEEDED_SCALE_TOLERANCE, "scale {sb} seeded vs {sa} uninterrupted");
    assert!(ate_combined <= 1.5 * ate_a, "ATE combined {ate_combined} m vs uninterrupted {ate_a} m");
}

/// Bad seeds are errors naming the keyframe; a failed seed leaves the tracker usable.
#[test]
fn seeding_with_bad_keyframes_is_an_error_and_changes_nothing() {
    let (renderer, frames) = survey(2);
    let cam = *renderer.camera();
    let kf = |index: u64, seq: usize, w: usize, h: usize| Keyframe {
        index,
        t_ns: frames[seq].t_ns,
        image: frames[seq].image.to_rgb8(),
        world_from_cam: renderer.poses()[seq].world_from_cam,
        camera: cam,
        inv_depth: PlaneF32::filled(w, h, [0.2]),
        inv_depth_variance: PlaneF32::filled(w, h, [1e-3]),
    };
    let (k0, k1, small) = (kf(3, 0, 160, 120), kf(4, 1, 160, 120), kf(4, 1, 80, 60));
    let mut t = Tracker::new(&cam, &small_tracker_config(), capacity(1)).unwrap();
    fn seed<'a>(ks: &[(u64, &'a Keyframe)]) -> Vec<SeedKeyframe<'a>> {
        ks.iter().map(|&(seq, keyframe)| SeedKeyframe { seq, keyframe }).collect()
    }
    let try_seed = |t: &mut Tracker, ks: &[SeedKeyframe]| t.seed(&TrackerSeed { keyframes: ks, frames: &[], resume: None, next_keyframe_id: 0 });
    assert!(matches!(try_seed(&mut t, &[]), Err(TrackError::NoSeedKeyframes)));
    let e = try_seed(&mut t, &seed(&[(0, &k0), (1, &small)])).unwrap_err();
    assert!(matches!(e, TrackError::SeedSize { id: 4, width: 80, height: 60, .. }), "{e}");
    assert_eq!(e.to_string(), "seed keyframe 4: inverse depth is 80x60, the tracker was built for 160x120");
    let e = try_seed(&mut t, &seed(&[(1, &k1), (0, &k0)])).unwrap_err();
    assert!(matches!(e, TrackError::BadSeedKeyframe { id: 3, .. }), "{e}");
    assert_eq!(t.num_keyframes(), 0);
    try_seed(&mut t, &seed(&[(0, &k0), (1, &k1)])).unwrap();
    assert_eq!(t.keyframes().map(|k| (k.id, k.seq)).collect::<Vec<_>>(), vec![(3, 0), (4, 1)]);
    assert!(matches!(try_seed(&mut t, &seed(&[(0, &k0)])), Err(TrackError::NotEmpty)));
    // A tracker that has tracked is not seeded either.
    let mut u = Tracker::new(&cam, &small_tracker_config(), capacity(1)).unwrap();
    u.track(&frames[0]).unwrap();
    assert!(matches!(try_seed(&mut u, &seed(&[(0, &k0)])), Err(TrackError::NotEmpty)));
}

/// Mean AUSE (inverse depth) over the final keyframes with a variance, and of a random
/// ordering of the same errors, against the true depth; inverse depth scaled into metres by
/// the trajectory's Sim(3) alignment.
fn keyframe_ause(r: &track_sim::RunResult, renderer: &SimRenderer) -> (f64, f64, usize) {
    use duv_eval::trajectory::{evaluate_trajectory, TrajectoryOptions};
    use duv_eval::{ause, AuseOptions};
    let ev = evaluate_trajectory(&renderer.poses()[..r.trajectory.frames.len()], &r.trajectory.frames, &TrajectoryOptions::default(), "gt", "est").unwrap();
    let scale = ev.report.alignment.scale;
    let cam = *renderer.camera();
    let (mut inv, mut var) = (PlaneF32::new(cam.width, cam.height), PlaneF32::new(cam.width, cam.height));
    let (mut sum, mut sum_random, mut n) = (0.0, 0.0, 0);
    let ids: Vec<(u64, u64)> = r.tracker.keyframes().filter(|k| k.variance.is_some()).map(|k| (k.id, k.seq)).collect();
    for (id, seq) in ids {
        r.tracker.upsample_keyframe(id, &mut inv, &mut var).unwrap();
        let depth = renderer.render(seq as usize).depth_m;
        let (mut errors, mut unc) = (Vec::new(), Vec::new());
        for ((&z, &d), &v) in depth.data.iter().zip(&inv.data).zip(&var.data) {
            if z > 0.0 && v < f32::MAX {
                errors.push((1.0 / z as f64 - d as f64 / scale).abs());
                unc.push(v as f64);
            }
        }
        let a = ause(&errors, &unc, &AuseOptions::default()).unwrap();
        sum += a.ause;
        sum_random += a.ause_random;
        n += 1;
    }
    (sum / n as f64, sum_random / n as f64, n)
}

/// The variance's multi-view consistency term ranks the depth error better on a turbid
/// survey, where haze biases the far seabed's flow (Eq. 4 cannot see it), and changes nothing
/// of the tracking itself (same trajectory to the bit: the motion-only BA does not use it).
#[test]
fn the_consistency_term_ranks_turbid_depth_errors_better_and_leaves_tracking_alone() {
    let renderer = SimRenderer::new(&sim_config(WaterPreset::Turbid, TrajectoryKind::Survey, 100, 320, 240, 0.5)).unwrap();
    let frames = render_all(&renderer);
    let on = run(&renderer, &frames, &small_tracker_config(), capacity(1));
    let off_cfg = duv_track::TrackerConfig { consistency_neighbours: 0, ..small_tracker_config() };
    let off = run(&renderer, &frames, &off_cfg, capacity(1));
    assert!(on.trajectory.frames.iter().zip(&off.trajectory.frames).all(|(a, b)| a.world_from_cam == b.world_from_cam));
    let (a_on, random, n) = keyframe_ause(&on, &renderer);
    let (a_off, _, _) = keyframe_ause(&off, &renderer);
    assert!(n >= 10, "{n} keyframes with a variance");
    assert!(a_on < CONSISTENCY_AUSE && a_on < 0.8 * a_off && a_on < 0.5 * random, "AUSE {a_on:.4} with the term, {a_off:.4} without, random {random:.4}");
}

/// Flow and BA settings the tracker cannot run with are refused by `Tracker::new`, by name,
/// instead of leaving it initialising for ever; a partial `[ba]` table takes the defaults for
/// the rest.
#[test]
fn bad_flow_and_ba_settings_are_refused_at_start_by_name() {
    let cfg = sim_config(WaterPreset::Coastal, TrajectoryKind::Survey, 4, 160, 120, 0.5);
    let camera = *SimRenderer::new(&cfg).unwrap().camera();
    let good = small_tracker_config();
    assert!(Tracker::new(&camera, &good, capacity(1)).is_ok());
    let mut cases: Vec<(duv_track::TrackerConfig, &str)> = Vec::new();
    let mut c = good.clone();
    c.ba.fixed_poses = 0;
    cases.push((c, "fixed_poses"));
    let mut c = good.clone();
    c.ba.huber_threshold = -1.0;
    cases.push((c, "huber_threshold"));
    let mut c = good.clone();
    c.ba.min_inv_depth = f64::NAN;
    cases.push((c, "min_inv_depth"));
    let mut c = good.clone();
    c.flow.patch_size = 2;
    cases.push((c, "patch_size"));
    for (cfg, field) in cases {
        let e = Tracker::new(&camera, &cfg, capacity(1)).err().unwrap_or_else(|| panic!("{field}: accepted"));
        assert!(matches!(e, TrackError::Ba(_) | TrackError::Flow(_)), "{field}: {e}");
        assert!(e.to_string().contains(field), "{field}: {e}");
    }
    // A partial [ba] table: the named key set, the others the defaults.
    let parsed: duv_track::TrackerConfig = toml::from_str("[ba]\nfixed_poses = 2\n").unwrap();
    assert_eq!(parsed.ba.fixed_poses, 2);
    assert_eq!(parsed.ba.huber_threshold, duv_track::TrackerConfig::default().ba.huber_threshold);
}

/// The tracker hands each keyframe on once `lag` newer ones were inserted, oldest first,
/// with the depth and pose it holds at that moment written into the caller's buffer; at the
/// end of the stream the rest follow; nothing is queued when emission is off.
#[test]
fn keyframes_are_emitted_once_final_in_insertion_order() {
    let (renderer, frames) = survey(60);
    let lag = 2;
    let mut t = Tracker::new(renderer.camera(), &small_tracker_config(), capacity(2)).unwrap();
    t.emit_keyframes_after(lag);
    let (w, h) = (renderer.camera().width, renderer.camera().height);
    let mut kf = blank_keyframe(renderer.camera());
    let (mut inserted, mut emitted) = (Vec::new(), Vec::new());
    let (mut inv, mut var) = (duv_core::PlaneF32::new(w, h), duv_core::PlaneF32::new(w, h));
    for f in &frames {
        let out = t.track(f).unwrap();
        inserted.extend(out.new_keyframe);
        while let Some(id) = t.next_final_keyframe(false, &mut kf) {
            assert_eq!(kf.index, id);
            // Emitted only once `lag` newer keyframes exist.
            let newer = inserted.iter().filter(|&&k| k > id).count();
            assert!(newer >= lag, "keyframe {id} emitted with {newer} newer");
            // The depth and pose the tracker holds now, bit for bit.
            t.upsample_keyframe(id, &mut inv, &mut var).unwrap();
            assert!(inv.data == kf.inv_depth.data && var.data == kf.inv_depth_variance.data, "keyframe {id}: depth differs");
            let view = t.keyframes().find(|k| k.id == id).unwrap();
            assert_eq!(view.world_from_cam, kf.world_from_cam);
            assert!(kf.inv_depth.data.iter().any(|&d| d > 0.0), "keyframe {id}: no depth");
            emitted.push(id);
        }
        assert_eq!(t.keyframes_waiting().len(), inserted.len() - emitted.len());
    }
    assert!(inserted.len() >= lag + 3, "only {} keyframes", inserted.len());
    assert_eq!(emitted[..], inserted[..emitted.len()], "emitted out of order");
    assert_eq!(emitted.len(), inserted.len() - lag);
    while let Some(id) = t.next_final_keyframe(true, &mut kf) {
        emitted.push(id);
    }
    assert_eq!(emitted, inserted);
    assert_eq!(t.keyframes_overflowed(), 0);
    // Off by default: nothing waits, nothing is emitted.
    let mut off = Tracker::new(renderer.camera(), &small_tracker_config(), capacity(2)).unwrap();
    for f in &frames[..30] {
        off.track(f).unwrap();
    }
    assert!(off.num_keyframes() > 0);
    assert_eq!(off.keyframes_waiting().len(), 0);
    assert_eq!(off.next_final_keyframe(true, &mut kf), None);
}
