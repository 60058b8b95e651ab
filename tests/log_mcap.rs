//! The MCAP black box on its own: round trip, the independent Python reader, rotation,
//! truncation at many points (recovery keeps every synced chunk), corruption (byte flips,
//! broken lengths: every intact chunk salvaged, counted against the mcap crate's index), oversized records against the memory budget, inspect, JPEG-logged frames
//! (size against raw, decode PSNR, replay, the Python reader).

use duv_core::alloc::{peak_bytes, reset_peak_bytes, CountingAllocator};
use duv_core::{Frame, FrameImage, ImageRgb8, Keyframe, PinholeCamera, PlaneF32, Se3, Timestamp};
use duv_log::reader::ReadLimits;
use duv_log::recover::{is_finished, recover_segment};
use duv_log::schema::{decode_frame, PoseRecord};
use duv_camera::FrameSource;
use duv_log::{inspect_log, list_segments, ChunkCompression, read_log_keyframes, read_segment, FrameEncoding, LogConfig, LogError, LogItem, SegmentWriter, Topic};
use duv_log::replay::McapSource;
use duv_sim::{SimConfig, SimRenderer, TrajectoryKind, WaterPreset};
use nalgebra::{Translation3, UnitQuaternion};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Duration;

#[path = "common/python.rs"]
mod python;

#[global_allocator]
static GLOBAL: CountingAllocator = CountingAllocator;

const W: usize = 40;
const H: usize = 30;

fn frame(seq: u64, t_ns: i64) -> Frame {
    let mut img = ImageRgb8::new(W, H);
    for (i, v) in img.data.iter_mut().enumerate() {
        *v = ((i as u64 * 31 + seq * 7) % 251) as u8;
    }
    Frame { t_ns: Timestamp::from_ns(t_ns), seq, image: FrameImage::Rgb8(img) }
}

fn pose(seq: u64, t_ns: i64) -> PoseRecord {
    let p = Se3::from_parts(Translation3::new(0.1 * seq as f64, 0.0, 0.02 * seq as f64), UnitQuaternion::from_euler_angles(0.0, 0.01 * seq as f64, 0.0));
    PoseRecord { t_ns: Timestamp::from_ns(t_ns), seq, world_from_cam: p, state: "tracking", tracked: true, keyframe: Some(0), new_keyframe: None, loop_closed: false, segment: 0, why: None, value: None, limit: None }
}

fn camera() -> PinholeCamera {
    PinholeCamera::new(30.0, 30.0, 19.5, 14.5, W, H).unwrap()
}

fn keyframe(index: u64, t_ns: i64) -> Keyframe {
    let mut f = frame(index, t_ns);
    let FrameImage::Rgb8(image) = std::mem::replace(&mut f.image, FrameImage::Gray8(duv_core::ImageGray8::new(1, 1))) else { unreachable!() };
    Keyframe {
        index,
        t_ns: Timestamp::from_ns(t_ns),
        image,
        world_from_cam: Se3::identity(),
        camera: camera(),
        // Values f16 holds exactly (the log stores the planes as f16), so that keyframes read
        // back equal.
        inv_depth: PlaneF32::filled(W, H, [0.5]),
        inv_depth_variance: PlaneF32::filled(W, H, [0.0078125]),
    }
}

/// Writes `frames` frames at 10 Hz with poses, two keyframes, health and a map checkpoint,
/// syncing every `sync_every` frames. Returns the sync points (path, messages, bytes).
fn write_log(dir: &Path, frames: u64, sync_every: u64, segment_max_bytes: u64) -> Vec<(PathBuf, u64, u64)> {
    write_log_with(dir, frames, sync_every, segment_max_bytes, ChunkCompression::Zstd)
}

fn write_log_with(dir: &Path, frames: u64, sync_every: u64, segment_max_bytes: u64, compression: ChunkCompression) -> Vec<(PathBuf, u64, u64)> {
    let mut cfg = LogConfig::new(dir);
    cfg.compression = compression;
    cfg.segment_max_bytes = segment_max_bytes;
    cfg.chunk_interval = Duration::from_secs(3600);
    cfg.metadata.push(("duv.board".into(), [("toml".to_string(), "name = \"test\"".to_string())].into_iter().collect::<BTreeMap<_, _>>()));
    let mut w = SegmentWriter::create(cfg).unwrap();
    let syncs = Arc::new(Mutex::new(Vec::new()));
    let s2 = syncs.clone();
    w.set_on_sync(move |p, m, b| s2.lock().unwrap().push((p.to_path_buf(), m, b)));
    w.write(&LogItem::Calibration { t_ns: Timestamp::from_ns(0), camera: camera() }).unwrap();
    for seq in 0..frames {
        let t = seq as i64 * 100_000_000;
        w.write(&LogItem::Frame(std::sync::Arc::new(frame(seq, t)))).unwrap();
        w.write(&LogItem::Pose(pose(seq, t))).unwrap();
        if seq % 20 == 5 {
            w.write(&LogItem::Keyframe(std::sync::Arc::new(keyframe(seq, t)))).unwrap();
        }
        if seq % 10 == 9 {
            w.write(&LogItem::Health { t_ns: Timestamp::from_ns(t), json: format!("{{\"frames\":{seq}}}") }).unwrap();
        }
        if (seq + 1) % sync_every == 0 {
            w.sync_now().unwrap();
        }
    }
    w.write(&LogItem::Map { t_ns: Timestamp::from_ns(frames as i64 * 100_000_000), centres_in_world: vec![[0.0, 1.0, 2.0]; 10], checkpoint: vec![7u8; 100], last: true }).unwrap();
    let (stats, r) = w.finish();
    r.unwrap();
    assert!(stats.failure.is_none());
    let v = syncs.lock().unwrap().clone();
    v
}

fn topic_counts(path: &Path) -> (BTreeMap<String, u64>, duv_log::ReadOutcome) {
    let mut counts = BTreeMap::new();
    let outcome = read_segment(path, ReadLimits::default(), |m| *counts.entry(m.channel.topic.clone()).or_insert(0) += 1).unwrap();
    (counts, outcome)
}


fn python_check(files: &[PathBuf]) -> Option<serde_json::Value> {
    let py = python::python_with("mcap.reader", "mcap")?;
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/py/check_mcap.py");
    let out = std::process::Command::new(&py).arg(&script).args(files).output().unwrap();
    assert!(out.status.success(), "python mcap failed: {}", String::from_utf8_lossy(&out.stderr));
    Some(serde_json::from_slice(&out.stdout).unwrap())
}

#[test]
fn round_trip_and_independent_python_reader() {
    let dir = tempfile::tempdir().unwrap();
    write_log(dir.path(), 60, 10, 1 << 30);
    let segs = list_segments(dir.path()).unwrap();
    assert_eq!(segs.len(), 1);
    let path = &segs[0].1;
    assert!(is_finished(path).unwrap());
    let (counts, outcome) = topic_counts(path);
    assert!(outcome.complete && outcome.damage.is_none(), "{outcome:?}");
    assert_eq!(counts["/camera/image"], 60);
    assert_eq!(counts["/slam/pose"], 60);
    assert_eq!(counts["/tf"], 60);
    assert_eq!(counts["/slam/state"], 60);
    assert_eq!(counts["/keyframe/inv_depth"], 3);
    assert_eq!(counts["/health"], 6);
    assert_eq!(counts["/map/checkpoint"], 1);
    assert_eq!(counts["/camera/calibration"], 1);
    // Frames decode to what was written.
    let mut seen = 0;
    read_segment(path, ReadLimits::default(), |m| {
        if m.channel.topic == Topic::CameraImage.name() {
            let f = decode_frame(m.data, m.sequence as u64, m.log_time_ns).unwrap();
            assert_eq!(f, frame(m.sequence as u64, m.sequence as i64 * 100_000_000));
            seen += 1;
        }
    })
    .unwrap();
    assert_eq!(seen, 60);

    if let Some(v) = python_check(std::slice::from_ref(path)) {
        let f = &v[path.to_str().unwrap()];
        for (topic, n) in &counts {
            assert_eq!(f["counts"][topic].as_u64(), Some(*n), "python count of {topic}");
        }
        assert_eq!(f["schemas"]["/camera/image"], "foxglove.RawImage");
        assert_eq!(f["schemas"]["/slam/pose"], "foxglove.PoseInFrame");
        assert_eq!(f["schemas"]["/tf"], "foxglove.FrameTransform");
        assert_eq!(f["schemas"]["/map/gaussians"], "foxglove.PointCloud");
        assert_eq!(f["schemas"]["/camera/calibration"], "foxglove.CameraCalibration");
        assert_eq!(f["indexed"], true);
        assert_eq!(f["statistics_messages"].as_u64(), Some(outcome.messages));
        assert!(f["metadata"].as_array().unwrap().iter().any(|m| m == "duv.board"));
    }
}

#[test]
fn segments_rotate_by_size_and_each_is_valid() {
    let dir = tempfile::tempdir().unwrap();
    // Uncompressed, so that the sizes below are the records' own.
    write_log_with(dir.path(), 200, 5, 200_000, ChunkCompression::None);
    let segs = list_segments(dir.path()).unwrap();
    assert!(segs.len() >= 3, "{} segments", segs.len());
    let mut frames = 0;
    for (_, p) in &segs {
        assert!(is_finished(p).unwrap());
        let (counts, outcome) = topic_counts(p);
        assert!(outcome.complete && outcome.damage.is_none());
        // Every segment carries the calibration (replayable on its own).
        assert_eq!(counts.get("/camera/calibration"), Some(&1), "{}", p.display());
        frames += counts.get("/camera/image").copied().unwrap_or(0);
        let len = std::fs::metadata(p).unwrap().len();
        assert!(len < 200_000 + 150_000, "{} is {len} bytes", p.display());
    }
    assert_eq!(frames, 200);
    let summary = inspect_log(dir.path(), ReadLimits::default()).unwrap();
    assert_eq!(summary.topics["/camera/image"].messages, 200);
    assert!(summary.gaps.is_empty());
    assert_eq!(summary.span_ns(), Some((0, 200 * 100_000_000)));
}

#[test]
fn truncated_segments_read_up_to_the_damage_and_recover_every_synced_chunk() {
    let dir = tempfile::tempdir().unwrap();
    let syncs = write_log(dir.path(), 80, 4, 1 << 30);
    let path = list_segments(dir.path()).unwrap()[0].1.clone();
    let full = std::fs::read(&path).unwrap();
    let (_, whole) = topic_counts(&path);
    let cut_dir = tempfile::tempdir().unwrap();
    let mut rng = 12345u64;
    let mut cuts: Vec<usize> = (0..30)
        .map(|_| {
            rng = rng.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (rng >> 33) as usize % full.len()
        })
        .collect();
    cuts.extend([0, 3, 8, 9, full.len() - 1, full.len() - 8]);
    for (i, &cut) in cuts.iter().enumerate() {
        let p = cut_dir.path().join(format!("segment-{i:06}.mcap"));
        std::fs::write(&p, &full[..cut]).unwrap();
        // What was synced at or before this length must be readable.
        let must = syncs.iter().filter(|s| s.2 as usize <= cut).map(|s| s.1).max().unwrap_or(0);
        let (_, outcome) = topic_counts(&p);
        assert!(outcome.messages >= must, "cut at {cut}: read {} messages, {must} were synced", outcome.messages);
        assert!(outcome.messages <= whole.messages);
        assert!(!outcome.complete || cut >= full.len() - 8);
        if cut < full.len() - 8 {
            assert!(outcome.damage.is_some(), "cut at {cut}: no damage reported");
        }
        if cut < 8 {
            continue;
        }
        let rep = recover_segment(&p, ReadLimits::default()).unwrap();
        assert_eq!(rep.messages_kept, outcome.messages, "cut at {cut}");
        assert!(is_finished(&p).unwrap());
        let (_, again) = topic_counts(&p);
        assert!(again.complete && again.damage.is_none(), "recovered file at cut {cut}: {again:?}");
        assert_eq!(again.messages, outcome.messages);
    }
    // The recovered files also open in the independent reader, and inspect reports them.
    let files: Vec<PathBuf> = list_segments(cut_dir.path()).unwrap().into_iter().map(|(_, p)| p).filter(|p| std::fs::metadata(p).unwrap().len() > 8).collect();
    if let Some(v) = python_check(&files) {
        for f in &files {
            let (counts, _) = topic_counts(f);
            for (topic, n) in &counts {
                assert_eq!(v[f.to_str().unwrap()]["counts"][topic].as_u64(), Some(*n), "{} {topic}", f.display());
            }
        }
    }
    let summary = inspect_log(cut_dir.path(), ReadLimits::default()).unwrap();
    assert!(summary.segments.iter().filter(|s| s.recovered.is_some()).count() >= 30);
    assert!(summary.render().contains("recovered ("));
}

/// The chunks of a finished MCAP file as the `mcap` crate's indexed reader sees them (an
/// independent count): (start offset, length, messages).
fn chunks_of(bytes: &[u8]) -> Vec<(u64, u64, u64)> {
    let summary = mcap::read::Summary::read(bytes).unwrap().expect("a summary");
    summary
        .chunk_indexes
        .iter()
        .map(|ci| (ci.chunk_start_offset, ci.chunk_length, summary.stream_chunk(bytes, ci).unwrap().count() as u64))
        .collect()
}

/// Messages the intact chunks of `chunks` hold: whole within the first `cut` bytes, and not
/// containing any of the `flipped` bytes.
fn intact_messages(chunks: &[(u64, u64, u64)], cut: u64, flipped: &[u64]) -> u64 {
    chunks.iter().filter(|(o, l, _)| o + l <= cut && !flipped.iter().any(|f| (*o..o + l).contains(f))).map(|c| c.2).sum()
}

#[test]
fn a_corrupt_chunk_is_skipped_and_every_intact_chunk_after_it_is_read() {
    let dir = tempfile::tempdir().unwrap();
    write_log(dir.path(), 60, 4, 1 << 30);
    let path = list_segments(dir.path()).unwrap()[0].1.clone();
    let original = std::fs::read(&path).unwrap();
    let chunks = chunks_of(&original);
    let total: u64 = chunks.iter().map(|c| c.2).sum();
    assert!(chunks.len() >= 10, "{} chunks", chunks.len());
    // One flipped bit inside an early chunk of the finished file (summary intact).
    let (o, l, lost) = chunks[2];
    let at = o + l / 2;
    let mut bytes = original.clone();
    bytes[at as usize] ^= 0x10;
    std::fs::write(&path, &bytes).unwrap();
    let (_, outcome) = topic_counts(&path);
    assert_eq!(outcome.messages, total - lost, "{outcome:?}");
    assert_eq!(outcome.skipped.len(), 1, "{:?}", outcome.skipped);
    assert!(outcome.skipped[0].from_byte == o && outcome.skipped[0].to_byte == o + l, "{:?}", outcome.skipped);
    assert!(outcome.damage.as_deref().unwrap().contains("chunk CRC mismatch"), "{:?}", outcome.damage);

    // A corrupted chunk length (the 8 bytes after the opcode): the reader resynchronises on
    // the next chunk.
    let mut bytes = original.clone();
    let (o, _, lost) = chunks[4];
    bytes[o as usize + 1..o as usize + 9].copy_from_slice(&u64::MAX.to_le_bytes());
    std::fs::write(&path, &bytes).unwrap();
    let (_, outcome) = topic_counts(&path);
    assert_eq!(outcome.messages, total - lost);

    // Unfinished (cut at 80 %, no summary) with a flipped byte and a zeroed length: every
    // intact chunk before the cut is read, and recovery keeps exactly those, in a file the
    // mcap crate reads through its index.
    let cut = original.len() as u64 * 4 / 5;
    let flip = chunks[1].0 + chunks[1].1 / 3;
    let (zo, _, _) = chunks[6];
    let mut bytes = original[..cut as usize].to_vec();
    bytes[flip as usize] ^= 0x01;
    bytes[zo as usize + 1..zo as usize + 9].fill(0);
    std::fs::write(&path, &bytes).unwrap();
    let expect = intact_messages(&chunks, cut, &[flip, zo + 1]);
    let (_, outcome) = topic_counts(&path);
    assert_eq!(outcome.messages, expect, "{:?}", outcome.skipped);
    assert!(!outcome.complete);
    let rep = recover_segment(&path, ReadLimits::default()).unwrap();
    assert_eq!(rep.messages_kept, expect);
    assert!(rep.skipped_ranges >= 2 && rep.left_in_place.is_none(), "{rep:?}");
    let recovered = std::fs::read(&path).unwrap();
    let recovered_chunks = chunks_of(&recovered);
    assert_eq!(recovered_chunks.iter().map(|c| c.2).sum::<u64>(), expect);
}

#[test]
fn random_byte_flips_and_cuts_lose_only_the_damaged_chunks() {
    let dir = tempfile::tempdir().unwrap();
    write_log(dir.path(), 80, 3, 1 << 30);
    let path = list_segments(dir.path()).unwrap()[0].1.clone();
    let original = std::fs::read(&path).unwrap();
    let chunks = chunks_of(&original);
    let first_chunk = chunks[0].0;
    let data_end = chunks.iter().map(|c| c.0 + c.1).max().unwrap();
    let work = tempfile::tempdir().unwrap();
    let mut rng = 777u64;
    let mut next = |n: u64| {
        rng = rng.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (rng >> 33) % n
    };
    let (mut salvaged, mut expected) = (0u64, 0u64);
    for i in 0..40 {
        // Cut somewhere in the data (or keep it whole), flip 1-3 bytes after the channel
        // records (a lost channel record is not a chunk's fault).
        let cut = if i % 4 == 0 { original.len() as u64 } else { first_chunk + next(data_end - first_chunk) };
        let flips: Vec<u64> = (0..1 + next(3)).map(|_| first_chunk + next(cut.min(data_end) - first_chunk)).collect();
        let mut bytes = original[..cut as usize].to_vec();
        for &f in &flips {
            bytes[f as usize] ^= 1 << next(8);
        }
        let p = work.path().join(format!("segment-{i:06}.mcap"));
        std::fs::write(&p, &bytes).unwrap();
        let expect = intact_messages(&chunks, cut, &flips);
        let (_, outcome) = topic_counts(&p);
        // A flip in a message index or a chunk's time range costs nothing.
        assert!(outcome.messages >= expect, "case {i}: read {}, {expect} intact; {:?}; cut {cut}, flips {flips:?}, chunks {chunks:?}", outcome.messages, outcome.skipped);
        assert!(outcome.messages <= chunks.iter().map(|c| c.2).sum::<u64>());
        if cut < original.len() as u64 {
            let rep = recover_segment(&p, ReadLimits::default()).unwrap();
            assert_eq!(rep.messages_kept, outcome.messages, "case {i}");
            assert!(is_finished(&p).unwrap());
        }
        salvaged += outcome.messages;
        expected += expect;
    }
    eprintln!("salvaged {salvaged} messages from 40 damaged copies; {expected} in chunks the damage did not touch");
}

#[test]
fn an_oversized_record_is_refused_without_allocating_it() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("hostile.mcap");
    // Magic, then a record that claims 2 GiB.
    let mut bytes = mcap::MAGIC.to_vec();
    bytes.push(0x05);
    bytes.extend_from_slice(&(2u64 << 30).to_le_bytes());
    bytes.extend_from_slice(&[0u8; 4096]);
    std::fs::write(&p, &bytes).unwrap();
    let limits = ReadLimits { max_record_bytes: 1 << 20 };
    reset_peak_bytes();
    let before = duv_core::alloc::live_bytes();
    let outcome = read_segment(&p, limits, |_| {}).unwrap();
    let grew = peak_bytes().saturating_sub(before);
    let d = outcome.damage.expect("an oversized record is damage");
    assert!(d.contains("limit") || d.contains("large"), "{d}");
    assert_eq!(outcome.messages, 0);
    // Other tests may allocate concurrently; 64 MiB is far below the 2 GiB the record claims.
    assert!(grew < 64 << 20, "reading allocated {grew} bytes");
}

#[test]
fn inspect_reports_gaps() {
    let dir = tempfile::tempdir().unwrap();
    let mut w = SegmentWriter::create(LogConfig::new(dir.path())).unwrap();
    w.write(&LogItem::Calibration { t_ns: Timestamp::from_ns(0), camera: camera() }).unwrap();
    for seq in 0..30u64 {
        let t = seq as i64 * 100_000_000 + if seq >= 20 { 2_000_000_000 } else { 0 };
        w.write(&LogItem::Frame(std::sync::Arc::new(frame(seq, t)))).unwrap();
    }
    w.finish().1.unwrap();
    let s = inspect_log(dir.path(), ReadLimits::default()).unwrap();
    assert_eq!(s.gaps, vec![(1_900_000_000, 4_000_000_000)]);
    assert!(s.render().contains("gaps in /camera/image: 1"));
}

/// PSNR (dB) of two 8-bit images of the same size.
fn psnr_u8(a: &[u8], b: &[u8]) -> f64 {
    assert_eq!(a.len(), b.len());
    let mse = a.iter().zip(b).map(|(&x, &y)| (x as f64 - y as f64).powi(2)).sum::<f64>() / a.len() as f64;
    10.0 * (255.0f64 * 255.0 / mse.max(1e-12)).log10()
}

/// Lowest decode PSNR accepted for JPEG-logged frames at quality 90 (generated coastal survey
/// frames with sensor noise, 640x480; measured 40.3 dB when this bound was set).
const JPEG_Q90_MIN_PSNR_DB: f64 = 38.0;

/// Writes `frames` with their calibration and poses; returns the bytes per `/camera/image`
/// message (what `duv inspect` counts).
fn write_frames(dir: &Path, camera: PinholeCamera, frames: &[Frame], encoding: FrameEncoding) -> u64 {
    let mut cfg = LogConfig::new(dir);
    cfg.frame_encoding = encoding;
    let mut w = SegmentWriter::create(cfg).unwrap();
    w.write(&LogItem::Calibration { t_ns: Timestamp::from_ns(0), camera }).unwrap();
    for f in frames {
        w.write(&LogItem::Frame(std::sync::Arc::new(f.clone()))).unwrap();
        w.write(&LogItem::Pose(pose(f.seq, f.t_ns.t_ns()))).unwrap();
    }
    w.finish().1.unwrap();
    let s = inspect_log(dir, ReadLimits::default()).unwrap();
    let t = &s.topics["/camera/image"];
    assert_eq!(t.messages, frames.len() as u64);
    t.bytes / t.messages
}

#[test]
fn jpeg_frames_are_compressed_images_that_decode_replay_and_shrink_the_log() {
    // 640x480, the real boards' resolution: the generated coastal survey with sensor noise.
    let mut sim = SimConfig::preset(WaterPreset::Coastal, TrajectoryKind::Survey);
    (sim.width, sim.height, sim.frames) = (640, 480, 4);
    let r = SimRenderer::new(&sim).unwrap();
    let camera = *r.camera();
    let frames: Vec<Frame> = (0..r.len()).map(|i| Frame { t_ns: r.pose(i).t_ns, seq: i as u64, image: FrameImage::Rgb8(r.render(i).rgb) }).collect();

    let raw_dir = tempfile::tempdir().unwrap();
    let jpeg_dir = tempfile::tempdir().unwrap();
    let raw = write_frames(raw_dir.path(), camera, &frames, FrameEncoding::Raw);
    let jpeg = write_frames(jpeg_dir.path(), camera, &frames, FrameEncoding::Jpeg { quality: 90 });
    eprintln!("640x480 bytes per /camera/image message: raw {raw}, jpeg q90 {jpeg} ({:.1}x smaller)", raw as f64 / jpeg as f64);
    // For the boards' comments: a lower quality, and the encode time (the log thread's cost).
    let mut buf = Vec::new();
    for q in [75u8, 90] {
        let t0 = std::time::Instant::now();
        let mut bytes = 0;
        for f in &frames {
            duv_log::schema::encode_jpeg(&f.image, q, &mut buf).unwrap();
            bytes += buf.len();
        }
        eprintln!("jpeg q{q}: {} bytes per frame, {:.1} ms per frame to encode", bytes / frames.len(), t0.elapsed().as_secs_f64() * 1e3 / frames.len() as f64);
    }
    // Raw: the 921,600 pixel bytes and a few dozen bytes of protobuf around them.
    assert!((640 * 480 * 3..640 * 480 * 3 + 100).contains(&raw), "raw {raw} bytes per frame");
    assert!(jpeg * 8 < raw, "jpeg {jpeg} bytes per frame against raw {raw}");

    // Every frame decodes to the original within the bound, in order, with its time stamp.
    let path = list_segments(jpeg_dir.path()).unwrap()[0].1.clone();
    let mut psnrs = Vec::new();
    read_segment(&path, ReadLimits::default(), |m| {
        if m.channel.topic == Topic::CameraImage.name() {
            let f = decode_frame(m.data, m.sequence as u64, m.log_time_ns).unwrap();
            let orig = &frames[m.sequence as usize];
            assert_eq!((f.t_ns, f.image.width(), f.image.height()), (orig.t_ns, 640, 480));
            let (FrameImage::Rgb8(a), FrameImage::Rgb8(b)) = (&f.image, &orig.image) else { panic!("a colour frame came back grey") };
            psnrs.push(psnr_u8(&a.data, &b.data));
        }
    })
    .unwrap();
    eprintln!("jpeg q90 decode PSNR per frame (dB): {psnrs:.2?}");
    assert_eq!(psnrs.len(), frames.len());
    assert!(psnrs.iter().all(|&p| p > JPEG_Q90_MIN_PSNR_DB), "{psnrs:?}");

    // Replay (`--source mcap:`, `duv replay`) delivers the same frames.
    let mut src = McapSource::open(jpeg_dir.path(), ReadLimits::default()).unwrap();
    assert_eq!(*src.camera(), camera);
    let mut n = 0;
    while let Some(f) = src.next_frame().unwrap() {
        let orig = &frames[n];
        assert_eq!((f.seq, f.t_ns), (orig.seq, orig.t_ns));
        let (FrameImage::Rgb8(a), FrameImage::Rgb8(b)) = (&f.image, &orig.image) else { panic!("grey") };
        assert!((psnr_u8(&a.data, &b.data) - psnrs[n]).abs() < 1e-9);
        n += 1;
    }
    assert_eq!(n, frames.len());

    // `duv inspect` and the independent reader see the CompressedImage schema and whole JPEGs.
    let summary = inspect_log(jpeg_dir.path(), ReadLimits::default()).unwrap();
    assert_eq!(summary.topics["/camera/image"].schema, "foxglove.CompressedImage");
    assert_eq!(inspect_log(raw_dir.path(), ReadLimits::default()).unwrap().topics["/camera/image"].schema, "foxglove.RawImage");
    if let Some(v) = python_check(std::slice::from_ref(&path)) {
        let f = &v[path.to_str().unwrap()];
        assert_eq!(f["schemas"]["/camera/image"], "foxglove.CompressedImage");
        assert_eq!(f["counts"]["/camera/image"].as_u64(), Some(frames.len() as u64));
        assert_eq!(f["jpeg"]["/camera/image"].as_u64(), Some(frames.len() as u64), "python: whole JPEG streams");
        assert_eq!(f["schemas"]["/slam/pose"], "foxglove.PoseInFrame");
        assert_eq!(f["indexed"], true);
    }
}

#[test]
fn logged_keyframes_read_back_whole_and_up_to_the_damage() {
    let dir = tempfile::tempdir().unwrap();
    write_log(dir.path(), 60, 4, 1 << 30);
    let expected: Vec<Keyframe> = [5u64, 25, 45].iter().map(|&i| keyframe(i, i as i64 * 100_000_000)).collect();
    let got = read_log_keyframes(dir.path(), ReadLimits::default()).unwrap();
    assert_eq!(got.keyframes, expected);
    assert!(got.damage.is_empty() && got.skipped.is_empty() && got.renumbered.is_empty(), "{got:?}");
    assert_eq!(got.segments.len(), 1);

    // Cut anywhere: the keyframes before the cut come back exactly, the one the cut splits is
    // left out and named, and damage is reported; with none left it is an error naming the log.
    let path = list_segments(dir.path()).unwrap()[0].1.clone();
    let full = std::fs::read(&path).unwrap();
    let mut seen_counts = std::collections::BTreeSet::new();
    let mut last = 0;
    for k in 1..40 {
        let cut = full.len() * k / 40;
        let cut_dir = tempfile::tempdir().unwrap();
        std::fs::write(cut_dir.path().join("segment-000000.mcap"), &full[..cut]).unwrap();
        match read_log_keyframes(cut_dir.path(), ReadLimits::default()) {
            Ok(got) => {
                let n = got.keyframes.len();
                assert_eq!(got.keyframes[..], expected[..n], "cut at {cut}");
                assert_eq!(got.damage.len(), 1, "cut at {cut}: {:?}", got.damage);
                assert!(got.damage[0].contains("no footer"), "{}", got.damage[0]);
                assert!(got.skipped.len() <= 1 && got.skipped.iter().all(|(i, why)| expected.get(n).is_some_and(|k| k.index == *i) && why.contains("no /keyframe/")), "cut at {cut}: {:?}", got.skipped);
                assert!(n >= last, "cut at {cut}: {n} keyframes after {last} at a shorter cut");
                last = n;
                seen_counts.insert(n);
            }
            Err(e) => {
                assert!(matches!(e, LogError::NoKeyframes { .. }), "cut at {cut}: {e}");
                assert_eq!(last, 0, "cut at {cut}: no keyframes after a shorter cut had some");
                let msg = e.to_string();
                assert!(msg.contains(cut_dir.path().to_str().unwrap()) && msg.contains("no keyframes") && msg.contains("damaged"), "{msg}");
                seen_counts.insert(0);
            }
        }
    }
    assert_eq!(seen_counts.into_iter().collect::<Vec<_>>(), vec![0, 1, 2, 3]);

    // A log without keyframes, and a folder without a log, are errors that name the folder.
    let frames_only = tempfile::tempdir().unwrap();
    let mut w = SegmentWriter::create(LogConfig::new(frames_only.path())).unwrap();
    w.write(&LogItem::Calibration { t_ns: Timestamp::from_ns(0), camera: camera() }).unwrap();
    w.write(&LogItem::Frame(std::sync::Arc::new(frame(0, 0)))).unwrap();
    w.finish().1.unwrap();
    let e = read_log_keyframes(frames_only.path(), ReadLimits::default()).unwrap_err();
    assert!(matches!(e, LogError::NoKeyframes { segments: 1, .. }), "{e}");
    assert!(e.to_string().starts_with(frames_only.path().to_str().unwrap()) && !e.to_string().contains("damaged"), "{e}");
    // A keyframe whose depth does not fit the calibration is left out, with why.
    let misfit = tempfile::tempdir().unwrap();
    let mut w = SegmentWriter::create(LogConfig::new(misfit.path())).unwrap();
    w.write(&LogItem::Calibration { t_ns: Timestamp::from_ns(0), camera: camera() }).unwrap();
    let mut bad = keyframe(7, 0);
    bad.inv_depth = PlaneF32::filled(10, 10, [0.5]);
    w.write(&LogItem::Keyframe(std::sync::Arc::new(bad))).unwrap();
    w.write(&LogItem::Keyframe(std::sync::Arc::new(keyframe(8, 100)))).unwrap();
    w.finish().1.unwrap();
    let got = read_log_keyframes(misfit.path(), ReadLimits::default()).unwrap();
    assert_eq!(got.keyframes.iter().map(|k| k.index).collect::<Vec<_>>(), vec![8]);
    assert_eq!(got.skipped, vec![(7, "image 40x30 or depth 10x10 differs from the calibration 40x30".to_string())]);
    let empty = tempfile::tempdir().unwrap();
    let e = read_log_keyframes(empty.path(), ReadLimits::default()).unwrap_err();
    assert!(matches!(e, LogError::NotALog { .. }) && e.to_string().contains("segment-NNNNNN.mcap"), "{e}");
}

#[test]
fn a_resumed_runs_repeated_keyframe_index_is_renumbered() {
    let dir = tempfile::tempdir().unwrap();
    for run in 0..2 {
        let mut w = SegmentWriter::create(LogConfig::new(dir.path())).unwrap();
        w.write(&LogItem::Calibration { t_ns: Timestamp::from_ns(0), camera: camera() }).unwrap();
        w.write(&LogItem::Keyframe(std::sync::Arc::new(keyframe(5, run * 1_000_000_000)))).unwrap();
        w.finish().1.unwrap();
    }
    // The run-level folder (`RUN/log`) is found from `RUN` too.
    let run_dir = tempfile::tempdir().unwrap();
    std::fs::rename(dir.path(), run_dir.path().join("log")).unwrap();
    let got = read_log_keyframes(run_dir.path(), ReadLimits::default()).unwrap();
    assert_eq!(got.segments.len(), 2);
    assert_eq!(got.keyframes.iter().map(|k| (k.index, k.t_ns.t_ns())).collect::<Vec<_>>(), vec![(5, 0), (6, 1_000_000_000)]);
    assert_eq!(got.renumbered, vec![(5, 6)]);
}

/// The byte budget: map checkpoints (incompressible, 1 MB each, two a second) are logged only
/// when the bucket covers them, the final one always, and the log keeps the budget on average;
/// `duv inspect` reads the budget from the board in the log and reports bytes per topic.
#[test]
fn map_checkpoints_are_logged_within_the_byte_budget_and_inspect_reports_it() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = LogConfig::new(dir.path());
    cfg.max_mb_per_s = Some(1.0);
    let board = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("boards/jetson-orin-nx-16gb.toml")).unwrap();
    let board = board.replace("max_mb_per_s = 8 ", "max_mb_per_s = 1 ");
    assert!(board.contains("max_mb_per_s = 1 "));
    cfg.metadata.push(("duv.board".into(), [("toml".to_string(), board)].into_iter().collect::<BTreeMap<_, _>>()));
    let mut w = SegmentWriter::create(cfg).unwrap();
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let mut noise = |n: usize| -> Vec<u8> {
        (0..n)
            .map(|_| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                state as u8
            })
            .collect()
    };
    let (seconds, maps_per_s) = (10u64, 2u64);
    for seq in 0..seconds * 10 {
        let t = seq as i64 * 100_000_000;
        w.write(&LogItem::Frame(Arc::new(frame(seq, t)))).unwrap();
        w.write(&LogItem::Pose(pose(seq, t))).unwrap();
        if seq % (10 / maps_per_s) == 0 {
            let last = seq == seconds * 10 - 1;
            w.write(&LogItem::Map { t_ns: Timestamp::from_ns(t), centres_in_world: vec![[0.0; 3]; 10], checkpoint: noise(1_000_000), last }).unwrap();
        }
    }
    let t_end = seconds as i64 * 1_000_000_000;
    w.write(&LogItem::Map { t_ns: Timestamp::from_ns(t_end), centres_in_world: vec![[0.0; 3]; 10], checkpoint: noise(1_000_000), last: true }).unwrap();
    let (stats, r) = w.finish();
    r.unwrap();
    let offered = seconds * maps_per_s + 1;
    assert_eq!(stats.maps_logged + stats.maps_skipped, offered);
    // 10 s at 1 MB/s: the frames take little, so about 4 maps besides the final one fit.
    assert!(stats.maps_skipped >= 12 && stats.maps_logged >= 3, "{stats:?}");
    let mb_s = stats.mb_per_s().unwrap();
    assert!(mb_s <= 1.0 && mb_s > 0.5, "{mb_s} MB/s");
    let summary = inspect_log(dir.path(), ReadLimits::default()).unwrap();
    assert_eq!(summary.topics["/map/checkpoint"].messages, stats.maps_logged);
    assert_eq!(summary.topics["/map/checkpoint"].last_ns, t_end as u64, "the final map is logged");
    assert_eq!((summary.board.as_deref(), summary.budget_mb_per_s), (Some("jetson-orin-nx-16gb"), Some(1.0)));
    // Incompressible checkpoints: on disk about their size; every topic's share adds up.
    let ckpt = &summary.topics["/map/checkpoint"];
    assert!(ckpt.stored_bytes > 0.99 * ckpt.bytes as f64 && ckpt.stored_bytes < 1.01 * ckpt.bytes as f64, "{ckpt:?}");
    let stored: f64 = summary.topics.values().map(|t| t.stored_bytes).sum();
    let file: u64 = summary.segments.iter().map(|g| g.bytes).sum();
    assert!(stored < file as f64 && stored > 0.95 * file as f64, "{stored} of {file}");
    let text = summary.render();
    assert!(text.contains("budget 1 MB/s (jetson-orin-nx-16gb): under by"), "{text}");
    assert!(text.contains("MB/s") && text.contains("on disk"), "{text}");
}

