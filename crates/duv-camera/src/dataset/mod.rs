//! Dataset folder readers (TUM, EuRoC, TartanAir, plain folder) behind one [`Dataset`] type.
//!
//! A dataset is opened from a spec `KIND:DIR[,OPTION=VALUE]...` (see [`open_dataset`]). Opening
//! reads every list, calibration and ground-truth file and checks that every image it names
//! exists; images themselves are decoded lazily, one per [`FrameSource::next_frame`] of a
//! [`DatasetSource`]. Every pose is `world_from_cam` with the camera x right, y down, z forward,
//! whatever convention the dataset stores. Navigation-sensor data (`nav.csv`, see
//! [`duv_core::nav`]) is read beside any layout, or from `nav=FILE`.

mod calib;
mod euroc;
mod folder;
pub mod npy;
mod tartanair;
mod tum;

pub use calib::{format_calibration, parse_calibration, read_calibration, read_medium};
pub use folder::FOLDER_DEFAULT_FPS;
pub use tartanair::{ned_to_cam, TARTANAIR_DEFAULT_FPS};

use super::{CameraError, FrameSource};
use duv_core::io::IoError;
use duv_core::nav::{read_nav_csv, NavTrack};
use duv_core::{Frame, FrameImage, MediumParams, PinholeCamera, PlaneF32, Se3, StampedPose, Timestamp};
use std::fmt;
use std::path::{Path, PathBuf};

/// Which reader opened a dataset.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DatasetKind {
    /// TUM RGB-D layout (`rgb.txt`, `depth.txt`, `groundtruth.txt`), as our generator writes it.
    Tum,
    /// EuRoC / ASL folder format (`mav0/cam0/data.csv`, `sensor.yaml`).
    Euroc,
    /// TartanAir sequence (`image_left/`, `pose_left.txt` in NED).
    TartanAir,
    /// A plain folder of PNG images with a calibration file.
    Folder,
}

/// The kinds a spec may name, for error messages.
pub const DATASET_KINDS: &str = "tum, euroc, tartanair, folder";

impl DatasetKind {
    /// The spec prefix of this kind (`tum`, `euroc`, `tartanair`, `folder`).
    pub fn name(self) -> &'static str {
        match self {
            DatasetKind::Tum => "tum",
            DatasetKind::Euroc => "euroc",
            DatasetKind::TartanAir => "tartanair",
            DatasetKind::Folder => "folder",
        }
    }

    fn from_name(name: &str) -> Option<Self> {
        match name {
            "tum" => Some(DatasetKind::Tum),
            "euroc" => Some(DatasetKind::Euroc),
            "tartanair" => Some(DatasetKind::TartanAir),
            "folder" => Some(DatasetKind::Folder),
            _ => None,
        }
    }

    /// The options a spec of this kind accepts.
    fn options(self) -> &'static [&'static str] {
        match self {
            DatasetKind::Tum => &["calib", "depth_scale", "fov", "downsample", "nav", "mask"],
            DatasetKind::Euroc => &["cam", "nav", "mask"],
            DatasetKind::TartanAir => &["calib", "fps", "nav", "mask"],
            DatasetKind::Folder => &["calib", "fps", "fov", "downsample", "nav", "mask"],
        }
    }
}

impl fmt::Display for DatasetKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// One image (or depth map) of a dataset: its time stamp and the full path of its file.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct DatasetFrame {
    pub t_ns: Timestamp,
    pub path: PathBuf,
}

/// How the depth files of a dataset encode metres.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum DepthFormat {
    /// 16-bit grey PNG holding `metres * units_per_metre` (TUM: 5000); 0 means no depth.
    PngU16 { units_per_metre: f64 },
    /// `.npy` little-endian float32 2-D array in metres (TartanAir).
    NpyF32Metres,
}

/// The depth maps of a dataset and their encoding.
#[derive(Clone, Debug, PartialEq)]
pub struct DepthTrack {
    pub frames: Vec<DatasetFrame>,
    pub format: DepthFormat,
}

/// Default TUM depth scale: PNG value per metre.
pub const TUM_DEPTH_UNITS_PER_METRE: f64 = 5000.0;
/// Largest time difference at which [`Dataset::load_depth_for_frame`] pairs a depth map with
/// an image (the TUM `associate.py` default, 20 ms).
pub const DEPTH_ASSOCIATION_MAX_DT_NS: i64 = 20_000_000;

/// An opened dataset folder: everything but the pixels.
#[derive(Clone, Debug, PartialEq)]
pub struct Dataset {
    pub kind: DatasetKind,
    /// The folder the spec named.
    pub root: PathBuf,
    /// Model of the images as stored (with distortion where the dataset has it).
    pub camera: PinholeCamera,
    /// Images in time order, time stamps strictly increasing.
    pub frames: Vec<DatasetFrame>,
    pub depth: Option<DepthTrack>,
    /// `world_from_cam` poses, camera x right / y down / z forward.
    pub ground_truth: Option<Vec<StampedPose>>,
    /// Water parameters from `medium.json`, where the dataset has one.
    pub medium: Option<MediumParams>,
    /// Camera-to-body extrinsics (EuRoC `T_BS`), where the dataset has them.
    pub body_from_cam: Option<Se3>,
    /// `downsample=N` (1: frames as stored) and the stored image size it applies to.
    pub downsample: usize,
    pub source_size: Option<(usize, usize)>,
    /// Navigation-sensor samples (depth, altitude, DVL velocity, AHRS attitude) from
    /// `nav=FILE` or `DIR/nav.csv`, on the clock of the images, with what was rejected.
    pub nav: Option<NavTrack>,
    /// `mask=FILE`: pixels to ignore (burned-in overlays, the vehicle's own frame in view), 1
    /// per ignored pixel, row-major at the frames' size (after `downsample`: a block with any
    /// ignored pixel is ignored).
    pub ignore_mask: Option<Vec<u8>>,
}

/// A parsed spec `KIND:DIR[,OPTION=VALUE]...`; see [`open_dataset`] for the syntax.
#[derive(Clone, Debug, PartialEq)]
pub struct DatasetSpec {
    pub kind: DatasetKind,
    pub dir: PathBuf,
    /// `calib=FILE`: calibration file in our `calibration.txt` format.
    pub calib: Option<PathBuf>,
    /// `fps=F`: frame rate used to time-stamp frames as `i / F`.
    pub fps: Option<f64>,
    /// `depth_scale=F`: TUM depth PNG value per metre.
    pub depth_scale: Option<f64>,
    /// `cam=NAME`: EuRoC camera folder under `mav0/`.
    pub cam: Option<String>,
    /// `fov=DEG`: intrinsics unknown: a pinhole camera with this horizontal field of view,
    /// square pixels, the principal point in the image centre, no distortion (used when no
    /// calibration file is given or found).
    pub fov_deg: Option<f64>,
    /// `downsample=N`: frames averaged over N x N pixel blocks (and the camera scaled to
    /// match), for footage larger than the board's tracking resolution.
    pub downsample: Option<usize>,
    /// `nav=FILE`: navigation-sensor file in the `nav.csv` format (default: `DIR/nav.csv`
    /// when present).
    pub nav: Option<PathBuf>,
    /// `mask=FILE`: an image of the stored frames' size, non-zero (any channel) where pixels
    /// are to be ignored.
    pub mask: Option<PathBuf>,
}

impl DatasetSpec {
    /// Parses a spec; an unknown kind is [`CameraError::UnknownSource`], a bad directory or
    /// option [`CameraError::BadSpec`].
    pub fn parse(spec: &str) -> Result<Self, CameraError> {
        let unknown = || CameraError::UnknownSource { spec: spec.to_string(), kinds: DATASET_KINDS };
        let (kind_name, rest) = spec.split_once(':').ok_or_else(unknown)?;
        let kind = DatasetKind::from_name(kind_name.trim()).ok_or_else(unknown)?;
        let bad = |problem: String| CameraError::BadSpec { spec: spec.to_string(), problem };
        let mut parts = rest.split(',');
        let dir = parts.next().unwrap_or("").trim();
        if dir.is_empty() {
            return Err(bad("no directory after the kind".into()));
        }
        let mut out = DatasetSpec { kind, dir: PathBuf::from(dir), calib: None, fps: None, depth_scale: None, cam: None, fov_deg: None, downsample: None, nav: None, mask: None };
        let mut seen: Vec<&str> = Vec::new();
        for part in parts {
            let (key, value) = part
                .split_once('=')
                .map(|(k, v)| (k.trim(), v.trim()))
                .ok_or_else(|| bad(format!("option {part:?} is not KEY=VALUE")))?;
            if !kind.options().contains(&key) {
                let accepted = kind.options().join(", ");
                return Err(bad(format!("unknown option {key:?} for {kind} (accepted: {accepted})")));
            }
            if seen.contains(&key) {
                return Err(bad(format!("option {key:?} given twice")));
            }
            seen.push(key);
            if value.is_empty() {
                return Err(bad(format!("option {key:?} has no value")));
            }
            let positive = |what: &str| -> Result<f64, CameraError> {
                match value.parse::<f64>() {
                    Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
                    _ => Err(bad(format!("{what}={value:?} is not a positive number"))),
                }
            };
            match key {
                "calib" => out.calib = Some(PathBuf::from(value)),
                "nav" => out.nav = Some(PathBuf::from(value)),
                "mask" => out.mask = Some(PathBuf::from(value)),
                "fps" => out.fps = Some(positive("fps")?),
                "depth_scale" => out.depth_scale = Some(positive("depth_scale")?),
                "downsample" => match value.parse::<usize>() {
                    Ok(n) if (1..=8).contains(&n) => out.downsample = Some(n),
                    _ => return Err(bad(format!("downsample={value:?} must be a whole factor 1 to 8"))),
                },
                "fov" => {
                    let fov = positive("fov")?;
                    if !(1.0..=170.0).contains(&fov) {
                        return Err(bad(format!("fov={value:?} must be a horizontal field of view in degrees, 1 to 170")));
                    }
                    out.fov_deg = Some(fov);
                }
                "cam" => {
                    if value.contains(['/', '\\']) || value == ".." || value == "." {
                        return Err(bad(format!("cam={value:?} must be a folder name such as cam0")));
                    }
                    out.cam = Some(value.to_string());
                }
                other => return Err(bad(format!("unknown option {other:?}"))),
            }
        }
        if !out.dir.is_dir() {
            return Err(bad(format!("{} is not a directory", out.dir.display())));
        }
        Ok(out)
    }
}

/// Opens a dataset from a spec `KIND:DIR[,OPTION=VALUE]...`.
///
/// Kinds and their options (options are comma-separated after the directory, so `DIR` cannot
/// contain a comma; an option a kind does not take, or one given twice, is an error; relative
/// paths are relative to the working directory):
///
/// - `tum:DIR[,calib=FILE][,depth_scale=F][,fov=DEG]`: `DIR/rgb.txt` (required), `DIR/depth.txt`,
///   `DIR/groundtruth.txt`, `DIR/medium.json` (optional), calibration from `calib=FILE` or else
///   `DIR/calibration.txt` (required unless `fov=DEG` guesses it: one line `fx fy cx cy width height`, optionally followed by
///   `k1 k2 p1 p2 k3`). Depth PNGs hold metres x `depth_scale` (default 5000).
/// - `euroc:DIR[,cam=NAME]`: `DIR/mav0/NAME/` (or `DIR/NAME/` when `DIR` is the `mav0` folder),
///   `NAME` default `cam0`: `data.csv`, `data/`, `sensor.yaml`; ground truth from
///   `mav0/state_groundtruth_estimate0/data.csv` when present, as camera poses
///   `world_from_body * T_BS`.
/// - `tartanair:DIR[,calib=FILE][,fps=F]`: `DIR/image_left/NNNNNN_left.png`, `DIR/pose_left.txt`
///   (NED, converted to camera axes), `DIR/depth_left/NNNNNN_left_depth.npy` when present;
///   camera fx = fy = 320, cx = 320, cy = 240, 640x480 unless `calib=FILE` or
///   `DIR/calibration.txt` says otherwise; time stamps `i / fps`, fps default 10.
/// - `folder:DIR[,calib=FILE][,fps=F][,fov=DEG]`: every `*.png`, `*.jpg` or `*.jpeg` in `DIR`
///   (or in `DIR/images/` when `DIR` holds none), calibration from `calib=FILE` or
///   `DIR/calibration.txt`, or else guessed from `fov=DEG` (horizontal field of view, for
///   footage whose intrinsics are unknown). Time stamps from the file stems when every stem is a
///   19-digit integer (nanoseconds), every stem is a decimal number with a point (seconds), or
///   every stem ends in a video time `HH_MM_SS.mmm` after a common prefix
///   (`frame_00_01_05.250`), frames then ordered by time; otherwise, or when `fps=F` is given,
///   frames are ordered by name and stamped `i / fps` (default 10). `DIR/groundtruth.txt` (TUM)
///   and `DIR/medium.json` are read when present.
///
/// Images are PNG (8-bit, or 16-bit reduced to 8) or JPEG in every layout. `tum:` and `folder:`
/// also take `downsample=N` (1-8): frames averaged over N x N blocks, the camera scaled.
///
/// Every kind takes `mask=FILE`: an image of the stored frames' size, non-zero where pixels are
/// to be ignored (a burned-in time stamp, the vehicle's frame in view); the tracker gives them
/// no weight ([`Dataset::ignore_mask`]).
///
/// Every kind takes `nav=FILE`: navigation-sensor samples in the `nav.csv` format
/// ([`duv_core::nav`]: `t_s,depth_m,altitude_m,vel_x_mps,vel_y_mps,vel_z_mps,qx,qy,qz,qw`, times
/// on the clock of the images); without it `DIR/nav.csv` is read when present. A file that
/// cannot be read (missing when named, wrong header, a cell that is not a number) is an error
/// naming it; bad values in it are rejected and counted in [`NavTrack::rejected`].
pub fn open_dataset(spec: &str) -> Result<Dataset, CameraError> {
    open_spec(&DatasetSpec::parse(spec)?)
}

/// Opens a dataset from a parsed spec.
pub fn open_spec(spec: &DatasetSpec) -> Result<Dataset, CameraError> {
    let mut dataset = match spec.kind {
        DatasetKind::Tum => tum::open(spec),
        DatasetKind::Euroc => euroc::open(spec),
        DatasetKind::TartanAir => tartanair::open(spec),
        DatasetKind::Folder => folder::open(spec),
    }?;
    dataset.nav = optional_nav(spec)?;
    if let Some(n) = spec.downsample.filter(|&n| n > 1) {
        let c = dataset.camera;
        if c.distortion.is_some() {
            return Err(CameraError::BadSpec { spec: format!("{}:{}", spec.kind, spec.dir.display()), problem: "downsample= needs a camera without distortion".into() });
        }
        let k = n as f64;
        dataset.source_size = Some((c.width, c.height));
        dataset.camera = PinholeCamera { fx: c.fx / k, fy: c.fy / k, cx: (c.cx + 0.5) / k - 0.5, cy: (c.cy + 0.5) / k - 0.5, width: c.width / n, height: c.height / n, distortion: None };
        dataset.downsample = n;
    }
    if let Some(path) = &spec.mask {
        dataset.ignore_mask = Some(read_ignore_mask(spec, path, &dataset)?);
    }
    tracing::debug!(
        depth = dataset.depth.is_some(),
        ground_truth = dataset.ground_truth.is_some(),
        nav_samples = dataset.nav.as_ref().map_or(0, NavTrack::len),
        "opened {}",
        dataset.describe()
    );
    Ok(dataset)
}

/// `mask=FILE` read at the stored frames' size and brought to the frames' (see
/// [`Dataset::ignore_mask`]); an unreadable file, a wrong size or a distorted camera is an
/// error naming the file.
fn read_ignore_mask(spec: &DatasetSpec, path: &Path, dataset: &Dataset) -> Result<Vec<u8>, CameraError> {
    let bad = |problem: String| CameraError::BadSpec { spec: format!("{}:{}", spec.kind, spec.dir.display()), problem: format!("mask={}: {problem}", path.display()) };
    if dataset.camera.distortion.is_some() {
        return Err(bad("a mask needs a camera without distortion (give undistorted frames)".into()));
    }
    let image = read_image_file(path).map_err(|e| bad(e.to_string()))?.to_rgb8();
    let (w, h) = dataset.source_size.unwrap_or((dataset.camera.width, dataset.camera.height));
    if image.width != w || image.height != h {
        return Err(bad(format!("{}x{}, the frames are {w}x{h} as stored", image.width, image.height)));
    }
    let n = dataset.downsample.max(1);
    let (ow, oh) = (dataset.camera.width, dataset.camera.height);
    let mut out = vec![0u8; ow * oh];
    for y in 0..oh * n {
        for x in 0..ow * n {
            if image.data[(y * w + x) * 3..(y * w + x) * 3 + 3].iter().any(|&v| v > 0) {
                out[(y / n) * ow + x / n] = 1;
            }
        }
    }
    let ignored = out.iter().filter(|&&m| m == 1).count();
    if ignored == out.len() {
        return Err(bad("every pixel is masked".into()));
    }
    tracing::info!("{}: {ignored} of {} pixels ignored ({:.1}%)", path.display(), out.len(), 100.0 * ignored as f64 / out.len() as f64);
    Ok(out)
}

impl Dataset {
    /// One line: kind, folder, frame count and image size.
    pub fn describe(&self) -> String {
        format!(
            "{} dataset {} ({} frames, {}x{})",
            self.kind,
            self.root.display(),
            self.frames.len(),
            self.camera.width,
            self.camera.height
        )
    }

    /// Decodes frame `index` (its position in [`Dataset::frames`], also its `seq`). The error
    /// is [`CameraError::BadFrame`] naming the file.
    pub fn load_frame(&self, index: usize) -> Result<Frame, CameraError> {
        let f = &self.frames[index];
        let wrap = |e: CameraError| CameraError::BadFrame { index, path: f.path.clone(), source: Box::new(e) };
        let image = read_image_file(&f.path).map_err(wrap)?;
        let image = if self.downsample > 1 {
            let (w, h) = self.source_size.unwrap_or((0, 0));
            if image.width() != w || image.height() != h {
                return Err(wrap(CameraError::ImageSize { path: f.path.clone(), width: image.width(), height: image.height(), expected_width: w, expected_height: h }));
            }
            downsample_image(&image, self.downsample)
        } else {
            image
        };
        self.check_size(&f.path, image.width(), image.height()).map_err(wrap)?;
        Ok(Frame { t_ns: f.t_ns, seq: index as u64, image })
    }

    fn check_size(&self, path: &Path, width: usize, height: usize) -> Result<(), CameraError> {
        if width != self.camera.width || height != self.camera.height {
            return Err(CameraError::ImageSize {
                path: path.to_path_buf(),
                width,
                height,
                expected_width: self.camera.width,
                expected_height: self.camera.height,
            });
        }
        Ok(())
    }

    /// Loads depth map `depth_index` (its position in the depth track) in metres; 0 marks
    /// pixels without depth (zero, negative or non-finite values in the file).
    pub fn load_depth(&self, depth_index: usize) -> Result<PlaneF32, CameraError> {
        let track = self.depth.as_ref().ok_or_else(|| CameraError::NoDepth { root: self.root.clone() })?;
        let f = &track.frames[depth_index];
        let plane = match track.format {
            DepthFormat::PngU16 { units_per_metre } => {
                let raw = duv_core::io::png_io::read_gray16(&f.path)?;
                let scale = 1.0 / units_per_metre;
                let data = raw.data.iter().map(|&v| if v == 0 { 0.0 } else { (v as f64 * scale) as f32 }).collect();
                PlaneF32 { width: raw.width, height: raw.height, data }
            }
            DepthFormat::NpyF32Metres => {
                let mut plane = npy::read_npy_f32(&f.path)?;
                for v in &mut plane.data {
                    if !(v.is_finite() && *v > 0.0) {
                        *v = 0.0;
                    }
                }
                plane
            }
        };
        self.check_size(&f.path, plane.width, plane.height)?;
        Ok(plane)
    }

    /// The depth map nearest in time to `t_ns`, if one lies within `max_dt_ns`.
    pub fn depth_index_for(&self, t_ns: Timestamp, max_dt_ns: i64) -> Option<usize> {
        let frames = &self.depth.as_ref()?.frames;
        let i = frames.partition_point(|f| f.t_ns < t_ns);
        [i.checked_sub(1), (i < frames.len()).then_some(i)]
            .into_iter()
            .flatten()
            .map(|k| (k, (frames[k].t_ns.t_ns() - t_ns.t_ns()).abs()))
            .filter(|&(_, dt)| dt <= max_dt_ns)
            .min_by_key(|&(_, dt)| dt)
            .map(|(k, _)| k)
    }

    /// The depth map (metres, 0 = invalid) paired with frame `frame_index`: the nearest in time
    /// within [`DEPTH_ASSOCIATION_MAX_DT_NS`]. `Ok(None)` when the dataset has no depth or none
    /// is close enough.
    pub fn load_depth_for_frame(&self, frame_index: usize) -> Result<Option<PlaneF32>, CameraError> {
        match self.depth_index_for(self.frames[frame_index].t_ns, DEPTH_ASSOCIATION_MAX_DT_NS) {
            Some(k) => self.load_depth(k).map(Some),
            None => Ok(None),
        }
    }

    /// The navigation-sensor samples, where the dataset has them.
    pub fn nav(&self) -> Option<&NavTrack> {
        self.nav.as_ref()
    }

    /// A frame source over this dataset, starting at the first frame.
    pub fn into_source(self) -> DatasetSource {
        DatasetSource::new(self)
    }
}

/// A [`Dataset`] as a [`FrameSource`]: decodes one image per `next_frame`. A frame that fails
/// is returned as an error and skipped; the next call continues with the following frame.
/// `Frame::seq` is the frame's index in the dataset, so skipped frames leave gaps.
#[derive(Debug)]
pub struct DatasetSource {
    dataset: Dataset,
    next_index: usize,
}

impl DatasetSource {
    pub fn new(dataset: Dataset) -> Self {
        DatasetSource { dataset, next_index: 0 }
    }
    pub fn dataset(&self) -> &Dataset {
        &self.dataset
    }
    /// Frames not yet delivered.
    pub fn remaining(&self) -> usize {
        self.dataset.frames.len() - self.next_index
    }
}

impl FrameSource for DatasetSource {
    fn camera(&self) -> &PinholeCamera {
        &self.dataset.camera
    }

    fn next_frame(&mut self) -> Result<Option<Frame>, CameraError> {
        if self.next_index >= self.dataset.frames.len() {
            return Ok(None);
        }
        let index = self.next_index;
        self.next_index += 1;
        let frame = self.dataset.load_frame(index)?;
        tracing::trace!(seq = frame.seq, t_ns = frame.t_ns.t_ns(), "dataset frame");
        Ok(Some(frame))
    }

    fn describe(&self) -> String {
        self.dataset.describe()
    }
}

// ---- helpers shared by the readers ----

/// Time stamp of frame `i` at `fps` frames per second, to the nearest nanosecond.
fn time_at_fps(i: usize, fps: f64) -> Timestamp {
    Timestamp::from_ns((i as f64 * 1e9 / fps).round() as i64)
}

/// Errors unless `t_ns` is after the previous time stamp.
fn check_increasing(list: &Path, line: usize, prev: Option<Timestamp>, t_ns: Timestamp) -> Result<(), CameraError> {
    match prev {
        Some(p) if t_ns <= p => {
            Err(duv_core::io::IoError::parse(list, line, format!("time stamp {t_ns} is not after the previous one ({p})")).into())
        }
        _ => Ok(()),
    }
}

/// Errors unless `path` (named on line `line` of `list`) is an existing file.
fn check_exists(list: &Path, line: usize, path: &Path) -> Result<(), CameraError> {
    if path.is_file() {
        Ok(())
    } else {
        Err(CameraError::MissingFile { list: list.to_path_buf(), line, missing: path.to_path_buf() })
    }
}

/// The calibration a spec asks for (`calib=FILE`) or else `default_path`; `None` when neither
/// the option is given nor the default file exists.
fn optional_calibration(spec: &DatasetSpec, default_path: &Path) -> Result<Option<PinholeCamera>, CameraError> {
    match &spec.calib {
        Some(p) => read_calibration(p).map(Some),
        None if default_path.exists() => read_calibration(default_path).map(Some),
        None => Ok(None),
    }
}

/// Like [`optional_calibration`], but a missing file is an error naming the file looked for,
/// unless the spec gives `fov=DEG`: then a pinhole guess at the size of `first_image`.
fn required_calibration(spec: &DatasetSpec, default_path: &Path, first_image: Option<&Path>) -> Result<PinholeCamera, CameraError> {
    if let Some(c) = optional_calibration(spec, default_path)? {
        return Ok(c);
    }
    match (spec.fov_deg, first_image) {
        (Some(fov), Some(image)) => {
            let img = read_image_file(image)?;
            let c = camera_from_fov(fov, img.width(), img.height());
            tracing::warn!("{}: no calibration; guessed from fov={fov} deg: fx = fy = {:.1} px, centre ({:.1}, {:.1}), no distortion", spec.dir.display(), c.fx, c.cx, c.cy);
            Ok(c)
        }
        _ => Err(CameraError::MissingCalibration {
            path: default_path.to_path_buf(),
            hint: "write one line `fx fy cx cy width height` there, add calib=FILE to the source spec, or guess the intrinsics with fov=DEG",
        }),
    }
}

/// A pinhole camera of `width x height` with horizontal field of view `fov_deg`, square
/// pixels and the principal point at the image centre.
pub fn camera_from_fov(fov_deg: f64, width: usize, height: usize) -> PinholeCamera {
    let f = 0.5 * width as f64 / (0.5 * fov_deg.to_radians()).tan();
    PinholeCamera { fx: f, fy: f, cx: 0.5 * width as f64 - 0.5, cy: 0.5 * height as f64 - 0.5, width, height, distortion: None }
}

/// `image` averaged over `n x n` blocks (the last partial row and column of blocks dropped).
pub fn downsample_image(image: &FrameImage, n: usize) -> FrameImage {
    fn avg(data: &[u8], w: usize, h: usize, ch: usize, n: usize) -> (usize, usize, Vec<u8>) {
        let (ow, oh) = (w / n, h / n);
        let mut out = vec![0u8; ow * oh * ch];
        for y in 0..oh {
            for x in 0..ow {
                for c in 0..ch {
                    let mut sum = 0u32;
                    for dy in 0..n {
                        let row = (y * n + dy) * w;
                        for dx in 0..n {
                            sum += data[(row + x * n + dx) * ch + c] as u32;
                        }
                    }
                    out[(y * ow + x) * ch + c] = ((sum + (n * n / 2) as u32) / (n * n) as u32) as u8;
                }
            }
        }
        (ow, oh, out)
    }
    match image {
        FrameImage::Rgb8(i) => {
            let (width, height, data) = avg(&i.data, i.width, i.height, 3, n);
            FrameImage::Rgb8(duv_core::ImageRgb8 { width, height, data })
        }
        FrameImage::Gray8(i) => {
            let (width, height, data) = avg(&i.data, i.width, i.height, 1, n);
            FrameImage::Gray8(duv_core::ImageGray8 { width, height, data })
        }
    }
}

/// Whether `path` names an image the readers decode: PNG, JPEG or TIFF, by extension.
pub fn is_image_file(path: &Path) -> bool {
    path.extension().and_then(|e| e.to_str()).is_some_and(|e| ["png", "jpg", "jpeg", "tif", "tiff"].iter().any(|x| e.eq_ignore_ascii_case(x)))
}

/// Decodes a PNG (8-bit grey or colour; 16-bit reduced to 8), a baseline or progressive JPEG
/// (to RGB, through `zune-jpeg`) or a TIFF (8- or 16-bit grey or colour, [`read_tiff`]), chosen
/// by the file's extension.
pub fn read_image_file(path: &Path) -> Result<FrameImage, CameraError> {
    let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("");
    let is = |x: &str| ext.eq_ignore_ascii_case(x);
    if is("tif") || is("tiff") {
        return read_tiff(path);
    }
    let is_jpeg = is("jpg") || is("jpeg");
    if !is_jpeg {
        return Ok(duv_core::io::png_io::read_image(path)?);
    }
    use zune_jpeg::zune_core::colorspace::ColorSpace;
    use zune_jpeg::zune_core::options::DecoderOptions;
    let bytes = std::fs::read(path).map_err(|e| IoError::file(path, e))?;
    let bad = |problem: String| CameraError::Dataset { path: path.to_path_buf(), problem };
    let options = DecoderOptions::new_safe().jpeg_set_out_colorspace(ColorSpace::RGB);
    let mut decoder = zune_jpeg::JpegDecoder::new_with_options(&bytes, options);
    let data = decoder.decode().map_err(|e| bad(format!("JPEG: {e:?}")))?;
    let (width, height) = decoder.dimensions().ok_or_else(|| bad("JPEG without dimensions".into()))?;
    if data.len() != width * height * 3 {
        return Err(bad(format!("JPEG decoded to {} bytes, {width}x{height} RGB is {}", data.len(), width * height * 3)));
    }
    Ok(FrameImage::Rgb8(duv_core::ImageRgb8 { width, height, data }))
}

/// Decodes a TIFF through the `tiff` crate (uncompressed, LZW or Deflate): 8- or 16-bit grey,
/// grey with alpha, RGB or RGBA, the first image of the file. 16-bit samples keep their high
/// byte, as 16-bit PNGs do: the full range maps to 0-255, the same for every frame (a
/// per-frame stretch would change the brightness between frames the flow compares). Float,
/// palette and CMYK images are refused by name.
pub fn read_tiff(path: &Path) -> Result<FrameImage, CameraError> {
    use tiff::decoder::{Decoder, DecodingResult};
    use tiff::ColorType;
    let bad = |problem: String| CameraError::Dataset { path: path.to_path_buf(), problem };
    let file = std::fs::File::open(path).map_err(|e| IoError::file(path, e))?;
    let mut decoder = Decoder::new(std::io::BufReader::new(file)).map_err(|e| bad(format!("TIFF: {e}")))?;
    let (w, h) = decoder.dimensions().map_err(|e| bad(format!("TIFF: {e}")))?;
    let (width, height) = (w as usize, h as usize);
    let colour = decoder.colortype().map_err(|e| bad(format!("TIFF: {e}")))?;
    let channels = match colour {
        ColorType::Gray(8 | 16) => 1,
        ColorType::GrayA(8 | 16) => 2,
        ColorType::RGB(8 | 16) => 3,
        ColorType::RGBA(8 | 16) => 4,
        other => return Err(bad(format!("TIFF colour type {other:?} is not read (8- or 16-bit grey or RGB, with or without alpha)"))),
    };
    let samples: Vec<u8> = match decoder.read_image().map_err(|e| bad(format!("TIFF: {e}")))? {
        DecodingResult::U8(v) => v,
        DecodingResult::U16(v) => v.iter().map(|s| (s >> 8) as u8).collect(),
        _ => return Err(bad("TIFF sample format is not 8- or 16-bit unsigned".into())),
    };
    if samples.len() != width * height * channels {
        return Err(bad(format!("TIFF decoded to {} samples, {width}x{height} with {channels} channel(s) is {}", samples.len(), width * height * channels)));
    }
    Ok(match channels {
        1 => FrameImage::Gray8(duv_core::ImageGray8 { width, height, data: samples }),
        2 => FrameImage::Gray8(duv_core::ImageGray8 { width, height, data: samples.chunks_exact(2).map(|p| p[0]).collect() }),
        3 => FrameImage::Rgb8(duv_core::ImageRgb8 { width, height, data: samples }),
        _ => FrameImage::Rgb8(duv_core::ImageRgb8 { width, height, data: samples.chunks_exact(4).flat_map(|p| [p[0], p[1], p[2]]).collect() }),
    })
}

/// `medium.json` in `dir`, when present.
fn optional_medium(dir: &Path) -> Result<Option<MediumParams>, CameraError> {
    let path = dir.join("medium.json");
    if path.exists() {
        read_medium(&path).map(Some)
    } else {
        Ok(None)
    }
}

/// The navigation file a spec names (`nav=FILE`, which must exist) or else `DIR/nav.csv` when
/// present. Rejected values are counted in the track and logged once.
fn optional_nav(spec: &DatasetSpec) -> Result<Option<NavTrack>, CameraError> {
    let path = match &spec.nav {
        Some(p) => p.clone(),
        None => {
            let p = spec.dir.join("nav.csv");
            if !p.exists() {
                return Ok(None);
            }
            p
        }
    };
    let track = read_nav_csv(&path)?;
    if track.rejected.total() > 0 {
        tracing::warn!("{}: {} navigation value(s) rejected ({}); {} samples kept", path.display(), track.rejected.total(), track.rejected.describe(), track.len());
    }
    Ok(Some(track))
}

/// A TUM trajectory file, when present.
fn optional_trajectory(path: &Path) -> Result<Option<Vec<StampedPose>>, CameraError> {
    if path.exists() {
        Ok(Some(duv_core::io::tum::read_trajectory(path)?))
    } else {
        Ok(None)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spec_parsing() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path().display().to_string();
        let s = DatasetSpec::parse(&format!("folder:{d},fps=30,calib=cal.txt")).unwrap();
        assert_eq!(s.kind, DatasetKind::Folder);
        assert_eq!(s.fps, Some(30.0));
        assert_eq!(s.calib, Some(PathBuf::from("cal.txt")));
        assert!(matches!(DatasetSpec::parse(&format!("kitti:{d}")), Err(CameraError::UnknownSource { .. })));
        assert!(matches!(DatasetSpec::parse(&d), Err(CameraError::UnknownSource { .. })));
        for bad in [
            format!("tum:{d},fps=10"),
            format!("folder:{d},fps=0"),
            format!("folder:{d},fps=10,fps=20"),
            format!("folder:{d},fps"),
            format!("euroc:{d},cam=../x"),
            "tum:".to_string(),
            format!("tum:{d}/nope"),
        ] {
            let e = DatasetSpec::parse(&bad).unwrap_err();
            assert!(matches!(e, CameraError::BadSpec { .. }), "{bad}: {e}");
        }
    }

    #[test]
    fn depth_association_picks_nearest_within_limit() {
        let cam = PinholeCamera::new(1.0, 1.0, 0.0, 0.0, 2, 2).unwrap();
        let f = |t| DatasetFrame { t_ns: Timestamp(t), path: PathBuf::new() };
        let ds = Dataset {
            kind: DatasetKind::Tum,
            root: PathBuf::new(),
            camera: cam,
            frames: vec![],
            depth: Some(DepthTrack { frames: vec![f(0), f(100), f(200)], format: DepthFormat::NpyF32Metres }),
            ground_truth: None,
            medium: None,
            body_from_cam: None,
            downsample: 1,
            source_size: None,
            nav: None,
            ignore_mask: None,
        };
        assert_eq!(ds.depth_index_for(Timestamp(140), 50), Some(1));
        assert_eq!(ds.depth_index_for(Timestamp(160), 50), Some(2));
        assert_eq!(ds.depth_index_for(Timestamp(-10), 50), Some(0));
        assert_eq!(ds.depth_index_for(Timestamp(300), 50), None);
        assert_eq!(ds.depth_index_for(Timestamp(250), 50), Some(2));
    }
}
