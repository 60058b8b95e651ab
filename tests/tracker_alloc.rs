//! No allocation per frame after warm-up: the tracker, run inside its pool as a tracking
//! thread runs it (`Tracker::run_in_pool`), is driven through frames under a counting global
//! allocator. The counted frames include plain frames (flow + motion-only BA), keyframe
//! insertions (flow/BA rounds over the window, covariance, pruning check), evictions from a
//! full keyframe store, a black frame (lost) and the relocalisation after it, and, on a loop
//! sequence, the loop closure (verification, Sim(3) pose graph, dense global BA); and a tracker
//! seeded with logged keyframes (resume) tracking on, inserting and evicting.
//!
//! Not covered: `Tracker::new` (the start-up allocation), `upsample_keyframe` (output, called
//! by the writer; allocation-free too but not counted here), the caller's frame decoding and
//! `TrajectoryRecorder` (it grows with the run by design).

#[path = "common/track_sim.rs"]
mod track_sim;

use duv_core::{Frame, FrameImage, ImageRgb8, Keyframe, PlaneF32};
use duv_sim::{SimRenderer, TrajectoryKind, WaterPreset};
use duv_track::{SeedKeyframe, TrackOutput, Tracker, TrackerCapacity, TrackerSeed, TrackingState};
use duv_core::alloc::{self, CountScope, CountingAllocator};

#[global_allocator]
static GLOBAL: CountingAllocator = CountingAllocator;

/// The counts see every thread (rayon workers included), so a test setting up beside a
/// counting one would be counted: the tests of this binary run one at a time.
static SERIAL: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn serial() -> std::sync::MutexGuard<'static, ()> {
    SERIAL.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

fn count(f: impl FnOnce()) -> usize {
    alloc::count_allocations(CountScope::AllThreads, f)
}

/// Tracks `frames[..warm]` uncounted, then `frames[warm..]` counted; returns the allocation
/// count and the counted outputs.
fn counted_run(renderer: &SimRenderer, frames: &[Frame], warm: usize, cap: TrackerCapacity) -> (usize, Vec<TrackOutput>) {
    let mut tracker = Tracker::new(renderer.camera(), &track_sim::small_tracker_config(), cap).unwrap();
    tracker.run_in_pool(|t| {
        for f in &frames[..warm] {
            t.track(f).unwrap();
        }
        let probe = count(|| {
            rayon::join(|| std::hint::black_box(vec![1u8; 64]), || std::hint::black_box(vec![2u8; 64]));
        });
        assert!(probe >= 2, "counting allocator missed allocations: {probe}");
        let mut outputs: Vec<TrackOutput> = Vec::with_capacity(frames.len());
        let n = count(|| {
            for f in &frames[warm..] {
                outputs.push(t.track(f).unwrap());
            }
        });
        (n, outputs)
    })
}

#[test]
fn tracking_keyframes_eviction_and_relocalisation_do_not_allocate() {
    let _serial = serial();
    let renderer = SimRenderer::new(&track_sim::sim_config(WaterPreset::Coastal, TrajectoryKind::Survey, 110, 160, 120, 0.5)).unwrap();
    let mut frames = track_sim::render_all(&renderer);
    frames[95].image = FrameImage::Rgb8(ImageRgb8 { width: 160, height: 120, data: vec![0; 160 * 120 * 3] });
    // A store of 11 keyframes fills during warm-up: the counted insertions evict.
    let cap = TrackerCapacity { max_keyframes: 11, ba_window: 8, threads: 2 };
    let (n, outputs) = counted_run(&renderer, &frames, 70, cap);
    let keyframes = outputs.iter().filter(|o| o.new_keyframe.is_some()).count();
    let evicted = outputs.iter().filter(|o| o.evicted.is_some()).count();
    assert!(keyframes >= 3, "only {keyframes} keyframe insertions counted");
    assert!(evicted >= 1, "no eviction counted");
    assert!(outputs.iter().any(|o| matches!(o.state, TrackingState::Lost(_))));
    assert!(outputs.iter().any(|o| o.state == TrackingState::Relocalised));
    assert_eq!(n, 0, "{n} allocations in {} frames ({keyframes} keyframes, {evicted} evictions)", outputs.len());
}

#[test]
fn loop_closure_does_not_allocate() {
    let _serial = serial();
    let renderer = SimRenderer::new(&track_sim::sim_config(WaterPreset::Coastal, TrajectoryKind::Loop, 100, 160, 120, 1.0)).unwrap();
    let frames = track_sim::render_all(&renderer);
    let (n, outputs) = counted_run(&renderer, &frames, 60, track_sim::capacity(2));
    assert!(outputs.iter().any(|o| o.loop_closed), "no loop closed in the counted frames");
    assert_eq!(n, 0, "{n} allocations in {} frames with a loop closure", outputs.len());
}

#[test]
fn a_seeded_tracker_does_not_allocate_per_frame() {
    let _serial = serial();
    let renderer = SimRenderer::new(&track_sim::sim_config(WaterPreset::Coastal, TrajectoryKind::Survey, 110, 160, 120, 0.5)).unwrap();
    let frames = track_sim::render_all(&renderer);
    let cam = *renderer.camera();
    // A first tracker's newest keyframes at frame 60 as the pipeline logs them (full resolution).
    let mut a = Tracker::new(&cam, &track_sim::small_tracker_config(), track_sim::capacity(2)).unwrap();
    for f in &frames[..=60] {
        a.track(f).unwrap();
    }
    let ids: Vec<(u64, u64)> = a.keyframes().map(|k| (k.id, k.seq)).collect();
    let logged: Vec<(u64, Keyframe)> = ids[ids.len().saturating_sub(8)..]
        .iter()
        .map(|&(id, seq)| {
            let view = a.keyframes().find(|k| k.id == id).unwrap();
            let (mut inv_depth, mut inv_depth_variance) = (PlaneF32::new(160, 120), PlaneF32::new(160, 120));
            a.upsample_keyframe(id, &mut inv_depth, &mut inv_depth_variance).unwrap();
            (seq, Keyframe { index: id, t_ns: view.t_ns, image: frames[seq as usize].image.to_rgb8(), world_from_cam: view.world_from_cam, camera: cam, inv_depth, inv_depth_variance })
        })
        .collect();
    assert!(logged.len() >= 4, "{} keyframes to seed", logged.len());
    let seeds: Vec<SeedKeyframe> = logged.iter().map(|(seq, k)| SeedKeyframe { seq: *seq, keyframe: k }).collect();
    let first = seeds[seeds.len() - 1].seq as usize + 1;
    // A small store, so the counted insertions evict seeded keyframes too.
    let mut b = Tracker::new(&cam, &track_sim::small_tracker_config(), TrackerCapacity { max_keyframes: 11, ba_window: 8, threads: 2 }).unwrap();
    b.seed(&TrackerSeed { keyframes: &seeds, frames: &[], resume: None, next_keyframe_id: 100 }).unwrap();
    let (n, outputs) = b.run_in_pool(|t| {
        for f in &frames[first..first + 10] {
            t.track(f).unwrap();
        }
        let mut outputs: Vec<TrackOutput> = Vec::with_capacity(frames.len());
        let n = count(|| {
            for f in &frames[first + 10..] {
                outputs.push(t.track(f).unwrap());
            }
        });
        (n, outputs)
    });
    let keyframes = outputs.iter().filter(|o| o.new_keyframe.is_some()).count();
    assert!(keyframes >= 3, "only {keyframes} keyframe insertions counted");
    assert!(outputs.iter().any(|o| o.evicted.is_some()), "no eviction counted");
    assert!(outputs.iter().all(|o| o.state.is_tracked()));
    assert_eq!(n, 0, "{n} allocations in {} frames after seeding ({keyframes} keyframes)", outputs.len());
}
