//! Where a run's frames come from: every kind of `--source` (`sim:` generated in memory,
//! dataset folders, `mcap:` recorded logs, with an optional replay loop for soak tests, `rosbag:`
//! ROS 2 bags, and the live cameras `duv_camera::open_source` knows) behind one type, [`Source`], with the ground
//! truth (poses, depth) where the source has it; [`RunSource`] is it as the pipeline's
//! [`FrameSource`]. Here, in the crate that wires the stages, because it needs both the camera
//! stage (datasets, cameras, the generator) and the log stage (replay).

use duv_camera::dataset::{open_dataset, Dataset, DATASET_KINDS};
use duv_camera::sim::SimSpec;
use duv_camera::{open_source, CameraError, FrameSource};
use duv_core::config::board::Board;
use duv_core::{Frame, FrameImage, ImageRgb8, PinholeCamera, PlaneF32, StampedPose};
use duv_log::replay::{McapSource, ReplayError};
use duv_log::rosbag_source::{RosbagError, RosbagSource, RosbagSpec};
use duv_log::ReadLimits;
use duv_sim::{SimConfig, SimError, SimRenderer};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// Why a run's source could not be opened or read.
#[derive(Debug, thiserror::Error)]
pub enum RunSourceError {
    #[error("source {spec}")]
    Replay { spec: String, source: ReplayError },
    #[error("source {spec}")]
    Sim { spec: String, source: SimError },
    #[error("source {spec}")]
    Rosbag { spec: String, source: RosbagError },
    #[error("reopening {path} for lap {lap}")]
    Reopen { path: PathBuf, lap: u64, source: ReplayError },
    #[error(transparent)]
    Camera(#[from] CameraError),
    /// A run option that does not fit the source (names the option).
    #[error("{0}")]
    Options(String),
}

/// `err` and its causes as one line, `outer: cause: ...`.
fn error_chain(err: &dyn std::error::Error) -> String {
    let mut line = err.to_string();
    let mut cause = err.source();
    while let Some(c) = cause {
        let text = c.to_string();
        if !line.ends_with(&text) {
            line.push_str(": ");
            line.push_str(&text);
        }
        cause = c.source();
    }
    line
}

/// What a run asks of its source beyond the spec.
#[derive(Clone, Debug, Default)]
pub struct SourceOptions {
    /// At most this many frames (a `sim:` source generates this many).
    pub frames: Option<usize>,
    /// Image size of a `sim:` source [default: the board's camera].
    pub width: Option<usize>,
    pub height: Option<usize>,
    /// Seed of a `sim:` source (its `seed=S` option wins).
    pub seed: u64,
    /// Soak tests: an `mcap:` source starts over at its end until this many seconds passed.
    pub loop_for_s: Option<f64>,
}

/// Where frames come from, with what ground truth.
pub enum Source {
    /// `nav`: the spec asked for the generator's navigation sensors (`nav=on`).
    Sim { renderer: Box<SimRenderer>, next: usize, count: usize, nav: bool },
    Dataset { dataset: Box<Dataset>, next: usize, count: usize, undistort: Option<(duv_core::camera::UndistortMap, ImageRgb8)> },
    /// `path`: the log (its navigation samples are read on demand, [`Source::nav`]).
    Mcap { replay: Box<McapSource>, count: usize, looping: Option<Box<ReplayLoop>>, path: PathBuf },
    /// A ROS 2 bag: frames undistorted like a dataset's where its camera has distortion.
    Rosbag { bag: Box<RosbagSource>, count: usize, undistort: Option<(duv_core::camera::UndistortMap, ImageRgb8)> },
    /// Live cameras (`v4l2:`, `aravis:`) and every other kind `camera::open_source` knows.
    Live { source: Box<dyn FrameSource>, next: usize, count: usize },
}

/// A recorded log replayed over and over (soak tests): each lap continues the time stamps and
/// sequence numbers of the last, one recorded frame period after its last frame.
pub struct ReplayLoop {
    path: PathBuf,
    until: std::time::Instant,
    laps: u64,
    /// Added to the recorded time stamps and sequence numbers of this lap.
    offset_ns: i64,
    offset_seq: u64,
    /// Recorded time stamps of the log's first two frames (the lap period's start and step).
    first_t_ns: Option<i64>,
    period_ns: i64,
    last_t_ns: i64,
    last_seq: u64,
}

impl Source {
    /// `start`: the first frame index (resume continues after the recorded frames).
    pub fn open(spec: &str, options: &SourceOptions, board: &Board, start: usize) -> Result<Source, RunSourceError> {
        if let Some(path) = spec.strip_prefix("mcap:") {
            let replay = McapSource::open(Path::new(path), ReadLimits::default()).map_err(|source| RunSourceError::Replay { spec: spec.to_string(), source })?.with_max_frames(options.frames);
            let looping = match options.loop_for_s {
                Some(s) => {
                    if !(s.is_finite() && s > 0.0) {
                        return Err(RunSourceError::Options(format!("--loop-for-s must be > 0, got {s}")));
                    }
                    Some(Box::new(ReplayLoop {
                        path: PathBuf::from(path),
                        until: std::time::Instant::now() + Duration::from_secs_f64(s),
                        laps: 0,
                        offset_ns: 0,
                        offset_seq: 0,
                        first_t_ns: None,
                        period_ns: 0,
                        last_t_ns: 0,
                        last_seq: 0,
                    }))
                }
                None => None,
            };
            return Ok(Source::Mcap { replay: Box::new(replay), count: options.frames.unwrap_or(usize::MAX), looping, path: PathBuf::from(path) });
        }
        if let Some(rest) = spec.strip_prefix("rosbag:") {
            if options.width.is_some() || options.height.is_some() {
                return Err(RunSourceError::Options("--width/--height apply to sim: sources only".into()));
            }
            let wrap = |source| RunSourceError::Rosbag { spec: spec.to_string(), source };
            let parsed = RosbagSpec::parse(rest).map_err(wrap)?;
            let calibration = parsed.calib.as_deref().map(duv_camera::dataset::read_calibration).transpose()?;
            let bag = RosbagSource::open(&parsed, calibration).map_err(wrap)?.with_max_frames(options.frames);
            let camera = *bag.camera();
            let undistort = camera.distortion.is_some().then(|| (camera.undistort_map(), ImageRgb8::new(camera.width, camera.height)));
            return Ok(Source::Rosbag { bag: Box::new(bag), count: options.frames.unwrap_or(usize::MAX), undistort });
        }
        if let Some(preset) = spec.strip_prefix("sim:") {
            let sim = SimSpec::parse(spec, preset)?;
            let mut cfg = SimConfig::preset(sim.water, sim.trajectory);
            cfg.width = options.width.unwrap_or(board.camera.width as usize);
            cfg.height = options.height.unwrap_or(board.camera.height as usize);
            match (sim.frames, options.frames) {
                (Some(a), Some(b)) if a != b => return Err(RunSourceError::Options(format!("{spec}: frames={a} and --frames {b} disagree"))),
                (Some(n), _) | (None, Some(n)) => cfg.frames = n,
                (None, None) => {}
            }
            cfg.seed = sim.seed.unwrap_or(options.seed);
            sim.apply(&mut cfg);
            let renderer = SimRenderer::new(&cfg).map_err(|source| RunSourceError::Sim { spec: spec.to_string(), source })?;
            let count = renderer.len();
            return Ok(Source::Sim { renderer: Box::new(renderer), next: start, count, nav: sim.nav });
        }
        if options.width.is_some() || options.height.is_some() {
            return Err(RunSourceError::Options("--width/--height apply to sim: sources only".into()));
        }
        if !DATASET_KINDS.split(", ").any(|k| spec.split(':').next() == Some(k)) {
            let source = open_source(spec, board)?;
            return Ok(Source::Live { source, next: 0, count: options.frames.unwrap_or(usize::MAX) });
        }
        let dataset = open_dataset(spec)?;
        let count = options.frames.unwrap_or(usize::MAX).min(dataset.frames.len());
        let undistort = dataset.camera.distortion.is_some().then(|| {
            let map = dataset.camera.undistort_map();
            let buf = ImageRgb8::new(dataset.camera.width, dataset.camera.height);
            (map, buf)
        });
        Ok(Source::Dataset { dataset: Box::new(dataset), next: start, count, undistort })
    }

    /// Camera of the frames handed to the tracker (undistorted).
    pub fn camera(&self) -> PinholeCamera {
        match self {
            Source::Sim { renderer, .. } => *renderer.camera(),
            Source::Dataset { dataset, .. } => dataset.camera.undistorted(),
            Source::Mcap { replay, .. } => *replay.camera(),
            Source::Rosbag { bag, .. } => bag.camera().undistorted(),
            Source::Live { source, .. } => *source.camera(),
        }
    }

    pub fn len(&self) -> usize {
        match self {
            Source::Sim { count, .. } | Source::Dataset { count, .. } | Source::Mcap { count, .. } | Source::Rosbag { count, .. } | Source::Live { count, .. } => *count,
        }
    }

    /// The next frame; `Ok(None)` at the end. A dataset frame that cannot be decoded is
    /// reported and skipped.
    pub fn next(&mut self) -> Result<Option<Frame>, RunSourceError> {
        match self {
            Source::Sim { renderer, next, count, .. } => {
                if *next >= *count {
                    return Ok(None);
                }
                let f = renderer.render(*next);
                let frame = Frame { t_ns: f.t_ns, seq: *next as u64, image: FrameImage::Rgb8(f.rgb) };
                *next += 1;
                Ok(Some(frame))
            }
            Source::Dataset { dataset, next, count, undistort } => loop {
                if *next >= *count {
                    return Ok(None);
                }
                let i = *next;
                *next += 1;
                match dataset.load_frame(i) {
                    Ok(mut frame) => {
                        if let Some((map, buf)) = undistort {
                            let rgb = frame.image.to_rgb8();
                            map.apply_rgb8(&rgb, buf);
                            frame.image = FrameImage::Rgb8(buf.clone());
                        }
                        return Ok(Some(frame));
                    }
                    Err(e) => tracing::warn!("skipping a frame: {e}"),
                }
            },
            Source::Rosbag { bag, undistort, .. } => {
                let Some(mut frame) = bag.next_frame()? else { return Ok(None) };
                if let Some((map, buf)) = undistort {
                    let rgb = frame.image.to_rgb8();
                    map.apply_rgb8(&rgb, buf);
                    frame.image = FrameImage::Rgb8(buf.clone());
                }
                Ok(Some(frame))
            }
            Source::Mcap { replay, looping: None, .. } => Ok(replay.next_frame()?),
            Source::Mcap { replay, looping: Some(lp), .. } => loop {
                if let Some(mut frame) = replay.next_frame()? {
                    let recorded = frame.t_ns.t_ns();
                    match lp.first_t_ns {
                        None => lp.first_t_ns = Some(recorded),
                        Some(first) if lp.period_ns == 0 && lp.laps == 0 => lp.period_ns = (recorded - first).max(1),
                        Some(_) => {}
                    }
                    frame.t_ns = frame.t_ns.offset_ns(lp.offset_ns);
                    frame.seq += lp.offset_seq;
                    lp.last_t_ns = frame.t_ns.t_ns();
                    lp.last_seq = frame.seq;
                    return Ok(Some(frame));
                }
                if std::time::Instant::now() >= lp.until || lp.first_t_ns.is_none() {
                    return Ok(None);
                }
                // Start the next lap one frame period after this one's last frame.
                lp.laps += 1;
                lp.offset_ns = lp.last_t_ns + lp.period_ns - lp.first_t_ns.unwrap_or(0);
                lp.offset_seq = lp.last_seq + 1;
                let again = McapSource::open(&lp.path, ReadLimits::default()).map_err(|source| RunSourceError::Reopen { path: lp.path.clone(), lap: lp.laps + 1, source })?;
                **replay = again;
            },
            Source::Live { source, next, count } => {
                if *next >= *count {
                    return Ok(None);
                }
                *next += 1;
                Ok(source.next_frame()?)
            }
        }
    }

    /// Frame `seq` read again as the tracker saw it, with its water-free view where the
    /// source knows it (the generator's; a dataset folder's `clear/` image of the same name, as
    /// `duv sim` writes them): for the map report. `None`: this source cannot read a frame again
    /// (the run's own log can, `map_report`); a dataset that is undistorted or downsampled is
    /// `None` too.
    pub fn frame_again(&self, seq: u64) -> Option<(ImageRgb8, Option<ImageRgb8>)> {
        match self {
            Source::Sim { renderer, count, .. } if (seq as usize) < *count => {
                let f = renderer.render(seq as usize);
                Some((f.rgb, Some(f.clear)))
            }
            Source::Dataset { dataset, undistort: None, .. } if dataset.downsample <= 1 && (seq as usize) < dataset.frames.len() => {
                let frame = dataset.load_frame(seq as usize).ok()?;
                let path = &dataset.frames[seq as usize].path;
                let clear = path.file_name().and_then(|name| {
                    let p = dataset.root.join("clear").join(name);
                    match duv_camera::dataset::read_image_file(&p) {
                        Ok(FrameImage::Rgb8(i)) if (i.width, i.height) == (frame.image.width(), frame.image.height()) => Some(i),
                        _ => None,
                    }
                });
                Some((frame.image.to_rgb8(), clear))
            }
            _ => None,
        }
    }

    /// The vehicle's navigation samples, sorted by time, where the source has them: a
    /// dataset's `nav.csv` (or `nav=FILE`), the generator's sensors for `sim:...,nav=on`
    /// (seeded like its images), a bag's navigation topics, a replayed log's `/nav/sample`.
    /// `Ok(None)`: no navigation input.
    pub fn nav(&self) -> Result<Option<Vec<duv_core::nav::NavSample>>, RunSourceError> {
        match self {
            Source::Sim { renderer, nav: true, .. } => {
                let seed = renderer.config().seed;
                duv_sim::nav::simulate(renderer, &duv_sim::NavNoise::default(), seed).map(Some).map_err(|source| RunSourceError::Sim { spec: "sim: navigation sensors".into(), source })
            }
            Source::Dataset { dataset, .. } => Ok(dataset.nav().map(|t| t.samples.clone())),
            Source::Rosbag { bag, .. } => Ok((!bag.nav().is_empty()).then(|| bag.nav().samples.clone())),
            // A replayed log: the samples it logged (`/nav/sample`), as the recorded run had them.
            Source::Mcap { path, .. } => {
                let (samples, _undecodable) = duv_log::read_log_nav(path, ReadLimits::default()).map_err(|source| RunSourceError::Replay { spec: format!("mcap:{}", path.display()), source: source.into() })?;
                Ok((!samples.is_empty()).then_some(samples))
            }
            _ => Ok(None),
        }
    }

    /// Pixels to ignore in every frame (a dataset's or a live camera's `mask=FILE`), 1 per
    /// ignored pixel at the frames' size.
    pub fn ignore_mask(&self) -> Option<&[u8]> {
        match self {
            Source::Dataset { dataset, .. } => dataset.ignore_mask.as_deref(),
            Source::Live { source, .. } => source.ignore_mask(),
            _ => None,
        }
    }

    pub fn ground_truth(&self) -> Option<Vec<StampedPose>> {
        match self {
            Source::Sim { renderer, count, .. } => Some(renderer.poses()[..*count].to_vec()),
            Source::Dataset { dataset, .. } => dataset.ground_truth.clone(),
            Source::Mcap { .. } | Source::Rosbag { .. } => None,
            Source::Live { source, .. } => source.ground_truth().map(<[_]>::to_vec),
        }
    }

    /// Ground-truth depth (metres, 0 = none) of frame `seq`, where the source has it.
    pub fn depth(&self, seq: u64) -> Option<PlaneF32> {
        match self {
            Source::Sim { renderer, .. } => Some(renderer.render(seq as usize).depth_m),
            Source::Dataset { dataset, .. } => dataset.load_depth_for_frame(seq as usize).ok().flatten(),
            Source::Mcap { .. } | Source::Rosbag { .. } | Source::Live { .. } => None,
        }
    }

    pub fn describe(&self) -> String {
        match self {
            Source::Sim { renderer, count, .. } => {
                let c = renderer.config();
                format!("sim {} water, {} path, {count} frames {}x{}", c.water, c.trajectory, c.width, c.height)
            }
            Source::Dataset { dataset, .. } => dataset.describe(),
            Source::Mcap { replay, .. } => replay.describe(),
            Source::Rosbag { bag, .. } => bag.describe(),
            Source::Live { source, .. } => source.describe(),
        }
    }
}

/// A [`Source`] as the pipeline's [`FrameSource`].
pub struct RunSource {
    pub inner: Source,
    pub camera: PinholeCamera,
    pub spec: String,
}

impl FrameSource for RunSource {
    fn camera(&self) -> &PinholeCamera {
        &self.camera
    }
    fn next_frame(&mut self) -> Result<Option<Frame>, CameraError> {
        self.inner.next().map_err(|e| CameraError::BadSpec { spec: self.spec.clone(), problem: error_chain(&e) })
    }
    /// Live cameras decode into the pipeline's pooled frame (no allocation per frame).
    fn next_frame_into(&mut self, frame: &mut Frame) -> Result<bool, CameraError> {
        match &mut self.inner {
            Source::Live { source, next, count } => {
                if *next >= *count {
                    return Ok(false);
                }
                *next += 1;
                source.next_frame_into(frame)
            }
            _ => match self.next_frame()? {
                Some(f) => {
                    *frame = f;
                    Ok(true)
                }
                None => Ok(false),
            },
        }
    }
    fn describe(&self) -> String {
        self.inner.describe()
    }
}

