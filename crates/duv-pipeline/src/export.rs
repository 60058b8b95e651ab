//! Posed keyframes for offline splatting (`duv export`): a finished run folder's keyframes,
//! their poses and its map as a COLMAP text model and as a nerfstudio `transforms.json`, the
//! inputs of offline Gaussian-splatting and NeRF trainers.
//!
//! It lives here because it reads a run folder, whose layout this crate writes (`keyframes.txt`
//! and `calibration.txt` in [`outputs`](super::outputs) and [`dive_run`](super::dive_run), the
//! images through [`KeyframeFolder`](super::KeyframeFolder), `metric.json` in
//! [`metric`](super::metric), `map.ply` and `renders/` through [`mapping`](super::mapping)), and
//! it reads the map with duv-map's PLY reader, which duv-eval (core only) cannot see.
//!
//! What it reads from `RUN/`:
//! - `calibration.txt` (`fx fy cx cy width height`): the undistorted pinhole of the keyframe
//!   images (the tracker takes undistorted frames only; a dataset with lens distortion is
//!   undistorted by the source). A calibration with more fields (distortion) is refused.
//! - `keyframes.txt` (`id t tx ty tz qx qy qz qw`, `world_from_cam`) and `keyframes/NNNNNN.png`;
//!   with `restored`, the restored (water-free) panel of the mapper's `renders/NNNNNN.png`
//!   (input | render | restored | depth | uncertainty) instead.
//! - `map.ply` (3DGS layout): its Gaussian centres and base colours (`0.5 + SH_C0 f_dc`) become
//!   the sparse points; the file itself is copied.
//! - `metric.json`: the length unit (`m` or the tracker's `map` units; none: `map`).
//!
//! What it writes into `OUT/`:
//!
//! ```text
//! images/NNNNNN.png           the keyframe images (or the restored ones)
//! sparse/0/cameras.txt        COLMAP: 1 PINHOLE width height fx fy cx cy
//! sparse/0/images.txt         COLMAP: IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME (cam_from_world),
//!                             then an empty line (no 2D points)
//! sparse/0/points3D.txt       COLMAP: POINT3D_ID X Y Z R G B ERROR (error 0, empty track)
//! transforms.json             nerfstudio: PINHOLE fl_x fl_y cx cy w h, per frame file_path and
//!                             transform_matrix (camera-to-world, OpenGL camera axes)
//! points3D.ply                the same points, x y z + red green blue (nerfstudio's ply_file_path)
//! map.ply                     the run's Gaussian map, copied (for splat viewers and tools)
//! README.txt                  what is here and the length unit
//! ```
//!
//! Conventions, each converted once here:
//! - Our camera: x right, y down, z forward, pixel centres at integer coordinates. COLMAP's
//!   camera axes are ours; nerfstudio's are OpenGL's (x right, y up, z back):
//!   `transform_matrix = world_from_cam * diag(1, -1, -1, 1)`.
//! - COLMAP and nerfstudio put the image origin at the top-left *corner* (the first pixel's
//!   centre is (0.5, 0.5)): their `cx`, `cy` are ours plus 0.5 ([`PIXEL_CENTRE_OFFSET`]).
//! - COLMAP stores `cam_from_world` (the inverse of our `world_from_cam`), quaternion `qw`
//!   first (`qw >= 0` here).

use duv_core::io::png_io::{read_image, write_rgb8};
use duv_core::io::{fields, parse_finite_fields, read_text, write_atomic, IoError};
use duv_core::pose::se3_from_tum;
use duv_core::{ImageRgb8, PinholeCamera, Se3};
use duv_map::gaussians::SH_C0;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// Folder of the images in the export (COLMAP's and nerfstudio's usual name).
pub const IMAGES_DIR: &str = "images";
/// Folder of the COLMAP model in the export (the layout splatting trainers read).
pub const SPARSE_DIR: &str = "sparse/0";
/// What COLMAP's and nerfstudio's principal point adds to ours: their image origin is the
/// top-left corner of the first pixel, ours its centre.
pub const PIXEL_CENTRE_OFFSET: f64 = 0.5;
/// Panels in a render of `renders/` (input | render | restored | depth | uncertainty) and the
/// restored one's position.
const RENDER_PANELS: usize = 5;
const RESTORED_PANEL: usize = 2;
/// Gaussians a map may hold for the reader (far beyond any board's cap).
const MAP_CAPACITY: usize = 1 << 26;

/// Which models to write.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ExportFormat {
    /// COLMAP text model (`sparse/0/*.txt`).
    Colmap,
    /// nerfstudio `transforms.json` (and `points3D.ply`).
    Nerfstudio,
    /// Both.
    All,
}

impl ExportFormat {
    fn colmap(self) -> bool {
        matches!(self, ExportFormat::Colmap | ExportFormat::All)
    }
    fn nerfstudio(self) -> bool {
        matches!(self, ExportFormat::Nerfstudio | ExportFormat::All)
    }
}

/// How to export.
#[derive(Clone, Debug)]
pub struct ExportOptions {
    pub format: ExportFormat,
    /// The restored (water-free) images of the mapper's `renders/` instead of the captured
    /// keyframe images.
    pub restored: bool,
    /// Most sparse points written (the map's Gaussians evenly subsampled beyond it).
    pub max_points: usize,
}

impl Default for ExportOptions {
    fn default() -> Self {
        ExportOptions { format: ExportFormat::All, restored: false, max_points: 100_000 }
    }
}

/// Why a run folder could not be exported.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    #[error("{path}: not a run folder (no such folder)")]
    NoRun { path: PathBuf },
    #[error("{path}: missing ({what})")]
    Missing { path: PathBuf, what: &'static str },
    #[error("{path}: {fields} fields: the camera has lens distortion; the export writes undistorted pinhole models only (a run's calibration has 6: fx fy cx cy width height)")]
    Distorted { path: PathBuf, fields: usize },
    #[error("{path}: no keyframes listed")]
    NoKeyframes { path: PathBuf },
    #[error("{path}: keyframe {id} listed twice")]
    DuplicateKeyframe { path: PathBuf, id: u64 },
    #[error("{path}: {width}x{height}, the calibration says {expected_width}x{expected_height}")]
    ImageSize { path: PathBuf, width: usize, height: usize, expected_width: usize, expected_height: usize },
    #[error("{path}: {width}x{height}, not the {panels} panels of {expected_width}x{expected_height} (input | render | restored | depth | uncertainty, under their labels) a render holds")]
    RenderSize { path: PathBuf, width: usize, height: usize, panels: usize, expected_width: usize, expected_height: usize },
    #[error("{dir}: no restored keyframe image for any keyframe (renders/NNNNNN.png, written by the mapper at the end of a run that was not stopped)")]
    NoRestored { dir: PathBuf },
    #[error("{path}: the map has no Gaussians")]
    EmptyMap { path: PathBuf },
    #[error("max_points = 0: the export needs at least 1 point")]
    NoPoints,
    #[error("{path}: the export folder is the run folder (its map.ply would be copied onto itself); choose another")]
    OutIsRun { path: PathBuf },
    #[error("creating {path}: {source}")]
    Create { path: PathBuf, source: std::io::Error },
    #[error("copying {from} to {to}: {source}")]
    Copy { from: PathBuf, to: PathBuf, source: std::io::Error },
    #[error(transparent)]
    Io(#[from] IoError),
}

/// A keyframe as the export writes it.
#[derive(Clone, Debug, PartialEq)]
pub struct ExportedImage {
    /// The run's keyframe id.
    pub keyframe: u64,
    /// COLMAP's IMAGE_ID (1, 2, ... in keyframe order).
    pub image_id: u32,
    /// Its file name in `images/`.
    pub name: String,
    pub t_s: f64,
    pub world_from_cam: Se3,
}

/// A sparse point: a Gaussian's centre and base colour.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ExportedPoint {
    pub xyz: [f64; 3],
    pub rgb: [u8; 3],
}

/// What [`export_run`] wrote.
#[derive(Clone, Debug)]
pub struct ExportSummary {
    /// The images (keyframes), in order.
    pub images: Vec<ExportedImage>,
    /// Keyframes left out with `restored` because the run has no render of them.
    pub without_render: Vec<u64>,
    /// Sparse points written, and the Gaussians of the map they were taken from.
    pub points: usize,
    pub gaussians: usize,
    /// The pinhole of the images (our pixel convention).
    pub camera: PinholeCamera,
    /// `m` or `map`.
    pub length_unit: String,
    /// Files and folders written, relative to the export folder.
    pub written: Vec<String>,
}

/// Reads `RUN/calibration.txt`: the keyframe images' undistorted pinhole.
pub fn read_run_camera(run: &Path) -> Result<PinholeCamera, ExportError> {
    let path = run.join("calibration.txt");
    if !path.exists() {
        return Err(ExportError::Missing { path, what: "the keyframe images' intrinsics, written by `duv run`" });
    }
    let text = read_text(&path)?;
    let Some((no, line)) = text.lines().enumerate().find(|(_, l)| !l.trim().is_empty() && !l.trim_start().starts_with('#')) else {
        return Err(IoError::invalid(&path, "no calibration line").into());
    };
    let n = fields(line).count();
    if n > 6 {
        return Err(ExportError::Distorted { path, fields: n });
    }
    let v = parse_finite_fields(&path, no + 1, line, 6, "fx fy cx cy width height")?;
    if v[4] < 1.0 || v[5] < 1.0 || v[4].fract() != 0.0 || v[5].fract() != 0.0 {
        return Err(IoError::parse(&path, no + 1, format!("image size {}x{} is not positive whole pixels", v[4], v[5])).into());
    }
    PinholeCamera::new(v[0], v[1], v[2], v[3], v[4] as usize, v[5] as usize).map_err(|e| IoError::parse(&path, no + 1, e.to_string()).into())
}

/// Reads `RUN/keyframes.txt`: `(id, t_s, world_from_cam)` in file order.
pub fn read_run_keyframes(run: &Path) -> Result<Vec<(u64, f64, Se3)>, ExportError> {
    let path = run.join("keyframes.txt");
    if !path.exists() {
        return Err(ExportError::Missing { path, what: "the keyframe poses, written at the end of `duv run`" });
    }
    let text = read_text(&path)?;
    let mut out: Vec<(u64, f64, Se3)> = Vec::new();
    for (no, line) in text.lines().enumerate() {
        let l = line.trim();
        if l.is_empty() || l.starts_with('#') {
            continue;
        }
        let v = parse_finite_fields(&path, no + 1, l, 9, "id timestamp tx ty tz qx qy qz qw")?;
        if v[0] < 0.0 || v[0].fract() != 0.0 || v[0] > 9.0e15 {
            return Err(IoError::parse(&path, no + 1, format!("keyframe id {} is not a non-negative integer", v[0])).into());
        }
        let id = v[0] as u64;
        if out.iter().any(|k| k.0 == id) {
            return Err(ExportError::DuplicateKeyframe { path, id });
        }
        let pose = se3_from_tum([v[2], v[3], v[4], v[5], v[6], v[7], v[8]]).map_err(|e| IoError::parse(&path, no + 1, e.to_string()))?;
        out.push((id, v[1], pose));
    }
    if out.is_empty() {
        return Err(ExportError::NoKeyframes { path });
    }
    Ok(out)
}

/// The run's length unit from `RUN/metric.json` (`map` without one).
fn run_length_unit(run: &Path) -> Result<String, ExportError> {
    Ok(super::metric::MetricRecord::read(run)?.map_or_else(|| "map".to_string(), |m| m.length_unit))
}

/// The sparse points of a map: every Gaussian with a finite centre and colour, evenly
/// subsampled to at most `max_points` (deterministic: the same map gives the same points).
pub fn map_points(gaussians: &duv_map::gaussians::Gaussians, max_points: usize) -> Vec<ExportedPoint> {
    let all: Vec<ExportedPoint> = (0..gaussians.len())
        .map(|i| gaussians.get(i))
        .filter(|g| g.mean.iter().chain(&g.f_dc).all(|v| v.is_finite()))
        .map(|g| ExportedPoint {
            xyz: [g.mean[0] as f64, g.mean[1] as f64, g.mean[2] as f64],
            rgb: g.f_dc.map(|c| ((0.5 + SH_C0 * c as f64).clamp(0.0, 1.0) * 255.0).round() as u8),
        })
        .collect();
    if all.len() <= max_points {
        return all;
    }
    (0..max_points).map(|k| all[k * all.len() / max_points]).collect()
}

/// `cameras.txt`: one PINHOLE camera (id 1) in COLMAP's pixel convention.
pub fn colmap_cameras_txt(camera: &PinholeCamera) -> String {
    let c = camera;
    format!(
        "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n# Number of cameras: 1\n1 PINHOLE {} {} {} {} {} {}\n",
        c.width,
        c.height,
        c.fx,
        c.fy,
        c.cx + PIXEL_CENTRE_OFFSET,
        c.cy + PIXEL_CENTRE_OFFSET
    )
}

/// `cam_from_world` of a pose as COLMAP writes it: `[qw, qx, qy, qz]` (`qw >= 0`) and `t`.
pub fn colmap_pose(world_from_cam: &Se3) -> ([f64; 4], [f64; 3]) {
    let cam_from_world = world_from_cam.inverse();
    let mut q = *cam_from_world.rotation.quaternion();
    if q.w < 0.0 {
        q = -q;
    }
    let t = cam_from_world.translation.vector;
    // `+ 0.0` writes a negative zero as 0.
    ([q.w + 0.0, q.i + 0.0, q.j + 0.0, q.k + 0.0], [t.x + 0.0, t.y + 0.0, t.z + 0.0])
}

/// `images.txt`: one line per image (camera 1) and an empty line of 2D points.
pub fn colmap_images_txt(images: &[ExportedImage], length_unit: &str) -> String {
    let mut s = format!(
        "# Image list with two lines of data per image:\n#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n#   POINTS2D[] as (X, Y, POINT3D_ID)\n# Number of images: {}, mean observations per image: 0\n# duv-slam export: cam_from_world, length unit {length_unit}\n",
        images.len()
    );
    for im in images {
        let (q, t) = colmap_pose(&im.world_from_cam);
        let _ = writeln!(s, "{} {} {} {} {} {} {} {} 1 {}\n", im.image_id, q[0], q[1], q[2], q[3], t[0], t[1], t[2], im.name);
    }
    s
}

/// `points3D.txt`: one line per point, error 0 (none measured) and an empty track.
pub fn colmap_points_txt(points: &[ExportedPoint], length_unit: &str) -> String {
    let mut s = format!(
        "# 3D point list with one line of data per point:\n#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n# Number of points: {}, mean track length: 0\n# duv-slam export: Gaussian centres of map.ply, length unit {length_unit}\n",
        points.len()
    );
    for (i, p) in points.iter().enumerate() {
        let _ = writeln!(s, "{} {} {} {} {} {} {} 0", i + 1, p.xyz[0], p.xyz[1], p.xyz[2], p.rgb[0], p.rgb[1], p.rgb[2]);
    }
    s
}

/// nerfstudio's `transform_matrix` of a pose: camera-to-world with OpenGL camera axes (x right,
/// y up, z back), `world_from_cam * diag(1, -1, -1, 1)`, rows.
pub fn nerfstudio_matrix(world_from_cam: &Se3) -> [[f64; 4]; 4] {
    let m = world_from_cam.to_homogeneous() * nalgebra::Matrix4::from_diagonal(&nalgebra::Vector4::new(1.0, -1.0, -1.0, 1.0));
    std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]))
}

/// `transforms.json` (nerfstudio's dataset format): the camera in its pixel convention, a frame
/// per image, the sparse points' PLY and the unit.
pub fn nerfstudio_transforms(camera: &PinholeCamera, images: &[ExportedImage], points_ply: Option<&str>, map_ply: Option<&str>, length_unit: &str) -> serde_json::Value {
    let frames: Vec<serde_json::Value> = images
        .iter()
        .map(|im| {
            serde_json::json!({
                "file_path": format!("{IMAGES_DIR}/{}", im.name),
                "transform_matrix": nerfstudio_matrix(&im.world_from_cam),
                "colmap_im_id": im.image_id,
                "duv_keyframe_id": im.keyframe,
                "duv_timestamp_s": im.t_s,
            })
        })
        .collect();
    let mut v = serde_json::json!({
        "camera_model": "PINHOLE",
        "fl_x": camera.fx,
        "fl_y": camera.fy,
        "cx": camera.cx + PIXEL_CENTRE_OFFSET,
        "cy": camera.cy + PIXEL_CENTRE_OFFSET,
        "w": camera.width,
        "h": camera.height,
        "duv_length_unit": length_unit,
        "frames": frames,
    });
    if let Some(p) = points_ply {
        v["ply_file_path"] = p.into();
    }
    if let Some(p) = map_ply {
        v["duv_gaussian_map"] = p.into();
    }
    v
}

/// The points as a binary PLY of `x y z` (float) and `red green blue` (uchar), the point cloud
/// nerfstudio initialises splats from.
pub fn points_ply(points: &[ExportedPoint]) -> Vec<u8> {
    let header = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n",
        points.len()
    );
    let mut out = header.into_bytes();
    out.reserve(points.len() * 15);
    for p in points {
        for v in p.xyz {
            out.extend_from_slice(&(v as f32).to_le_bytes());
        }
        out.extend_from_slice(&p.rgb);
    }
    out
}

fn create_dir(path: &Path) -> Result<(), ExportError> {
    std::fs::create_dir_all(path).map_err(|source| ExportError::Create { path: path.to_path_buf(), source })
}

/// The restored panel of a render (`renders/NNNNNN.png`), checked against the camera's size.
fn restored_panel(path: &Path, camera: &PinholeCamera) -> Result<ImageRgb8, ExportError> {
    let panel = read_image(path)?.to_rgb8();
    let (w, h) = (camera.width, camera.height);
    // Under the label strip (`duv_map::stage::with_labels`); renders of older runs have none.
    let strip = duv_map::stage::label_strip_height(w);
    if panel.width != w * RENDER_PANELS || (panel.height != h && panel.height != h + strip) {
        return Err(ExportError::RenderSize { path: path.to_path_buf(), width: panel.width, height: panel.height, panels: RENDER_PANELS, expected_width: w, expected_height: h });
    }
    let top = panel.height - h;
    let mut out = ImageRgb8::new(w, h);
    for y in 0..h {
        let src = ((top + y) * panel.width + RESTORED_PANEL * w) * 3;
        out.data[y * w * 3..(y + 1) * w * 3].copy_from_slice(&panel.data[src..src + w * 3]);
    }
    Ok(out)
}

/// Exports the run folder `run` into `out` (created; files there of the same names are
/// replaced): see the module docs for what is read and written.
pub fn export_run(run: &Path, out: &Path, opts: &ExportOptions) -> Result<ExportSummary, ExportError> {
    if !run.is_dir() {
        return Err(ExportError::NoRun { path: run.to_path_buf() });
    }
    if opts.max_points == 0 {
        return Err(ExportError::NoPoints);
    }
    if out.canonicalize().is_ok_and(|o| run.canonicalize().is_ok_and(|r| r == o)) {
        return Err(ExportError::OutIsRun { path: out.to_path_buf() });
    }
    let camera = read_run_camera(run)?;
    let keyframes = read_run_keyframes(run)?;
    let length_unit = run_length_unit(run)?;
    let map_path = run.join("map.ply");
    if !map_path.exists() {
        return Err(ExportError::Missing { path: map_path, what: "the run's Gaussian map, the sparse points; a run with --no-map has none" });
    }
    let gaussians = duv_map::ply::read_ply(&map_path, MAP_CAPACITY)?;
    if gaussians.is_empty() {
        return Err(ExportError::EmptyMap { path: map_path });
    }
    let points = map_points(&gaussians, opts.max_points);

    // Every input is checked (the images decoded) before anything is written.
    let renders = run.join("renders");
    let mut without_render = Vec::new();
    let mut sources: Vec<(u64, f64, Se3, PathBuf)> = Vec::new();
    for &(id, t_s, pose) in &keyframes {
        let name = format!("{id:06}.png");
        if opts.restored {
            let p = renders.join(&name);
            if p.exists() {
                restored_panel(&p, &camera)?;
                sources.push((id, t_s, pose, p));
            } else {
                without_render.push(id);
            }
        } else {
            let p = run.join(super::keyframe_folder::KEYFRAME_DIR).join(&name);
            if !p.exists() {
                return Err(ExportError::Missing { path: p, what: "the image of a keyframe listed in keyframes.txt" });
            }
            let img = read_image(&p)?;
            let (w, h) = (img.width(), img.height());
            if (w, h) != (camera.width, camera.height) {
                return Err(ExportError::ImageSize { path: p, width: w, height: h, expected_width: camera.width, expected_height: camera.height });
            }
            sources.push((id, t_s, pose, p));
        }
    }
    if sources.is_empty() {
        return Err(ExportError::NoRestored { dir: renders });
    }

    create_dir(out)?;
    let images_dir = out.join(IMAGES_DIR);
    create_dir(&images_dir)?;
    let mut images = Vec::with_capacity(sources.len());
    for (k, (id, t_s, pose, src)) in sources.iter().enumerate() {
        let name = format!("{id:06}.png");
        let dst = images_dir.join(&name);
        if opts.restored {
            write_rgb8(&dst, &restored_panel(src, &camera)?)?;
        } else {
            std::fs::copy(src, &dst).map_err(|source| ExportError::Copy { from: src.clone(), to: dst.clone(), source })?;
        }
        images.push(ExportedImage { keyframe: *id, image_id: k as u32 + 1, name, t_s: *t_s, world_from_cam: *pose });
    }
    let mut written = vec![format!("{IMAGES_DIR}/ ({} images)", images.len())];

    let map_copy = out.join("map.ply");
    std::fs::copy(&map_path, &map_copy).map_err(|source| ExportError::Copy { from: map_path.clone(), to: map_copy.clone(), source })?;
    written.push("map.ply".into());
    if opts.format.colmap() {
        let sparse = out.join(SPARSE_DIR);
        create_dir(&sparse)?;
        write_atomic(&sparse.join("cameras.txt"), colmap_cameras_txt(&camera).as_bytes())?;
        write_atomic(&sparse.join("images.txt"), colmap_images_txt(&images, &length_unit).as_bytes())?;
        write_atomic(&sparse.join("points3D.txt"), colmap_points_txt(&points, &length_unit).as_bytes())?;
        written.push(format!("{SPARSE_DIR}/cameras.txt, images.txt, points3D.txt"));
    }
    if opts.format.nerfstudio() {
        write_atomic(&out.join("points3D.ply"), &points_ply(&points))?;
        let json = nerfstudio_transforms(&camera, &images, Some("points3D.ply"), Some("map.ply"), &length_unit);
        let text = serde_json::to_string_pretty(&json).map_err(|e| IoError::invalid(&out.join("transforms.json"), e.to_string()))?;
        write_atomic(&out.join("transforms.json"), text.as_bytes())?;
        written.push("transforms.json".into());
        written.push("points3D.ply".into());
    }
    let readme = readme_text(run, &images, points.len(), gaussians.len(), &length_unit, opts);
    write_atomic(&out.join("README.txt"), readme.as_bytes())?;
    written.push("README.txt".into());
    Ok(ExportSummary { images, without_render, points: points.len(), gaussians: gaussians.len(), camera, length_unit, written })
}

fn readme_text(run: &Path, images: &[ExportedImage], points: usize, gaussians: usize, length_unit: &str, opts: &ExportOptions) -> String {
    let unit = match length_unit {
        "m" => "metres".to_string(),
        "map" => "the tracker's map units (scale unknown; see the run's metric.json)".to_string(),
        other => other.to_string(),
    };
    let mut s = format!("Posed keyframes exported by `duv export` from {}.\n\nLength unit: {unit} ({length_unit}).\n", run.display());
    let _ = writeln!(s, "Images: {} keyframes in {IMAGES_DIR}/, undistorted{}.", images.len(), if opts.restored { ", restored (the water removed by the mapper)" } else { "" });
    let _ = writeln!(s, "Points: {points} Gaussian centres of map.ply (of {gaussians}), colours their base colour.");
    if opts.format.colmap() {
        let _ = writeln!(s, "COLMAP text model: {SPARSE_DIR}/ (PINHOLE, cam_from_world poses).");
    }
    if opts.format.nerfstudio() {
        let _ = writeln!(s, "nerfstudio: transforms.json (camera-to-world, OpenGL camera axes), points3D.ply.");
    }
    s.push_str("map.ply: the run's Gaussian map (3DGS PLY), in the same frame and unit.\n");
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use duv_map::gaussians::{GaussianParam, Gaussians};
    use nalgebra::{Matrix4, Point3, Translation3, UnitQuaternion, Vector3, Vector4};

    /// Reprojection agreement between the written models and our camera model, px.
    const REPROJECTION_TOL_PX: f64 = 1e-6;

    fn camera() -> PinholeCamera {
        PinholeCamera::new(101.5, 99.25, 80.3, 59.7, 160, 120).unwrap()
    }

    /// Three poses looking down at the points from different places and attitudes.
    fn poses() -> Vec<Se3> {
        let look = |t: [f64; 3], roll: f64, pitch: f64, yaw: f64| {
            // Camera z down the world's -z (a downward-looking camera), then a small turn.
            let down = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
            Se3::from_parts(Translation3::new(t[0], t[1], t[2]), UnitQuaternion::from_euler_angles(roll, pitch, yaw) * down)
        };
        vec![look([0.0, 0.0, 3.0], 0.0, 0.0, 0.0), look([0.4, -0.3, 2.5], 0.1, -0.05, 0.7), look([-0.5, 0.6, 3.2], -0.08, 0.12, -2.4)]
    }

    fn points() -> Vec<[f64; 3]> {
        let mut v = Vec::new();
        for i in 0..7 {
            for j in 0..5 {
                v.push([-0.6 + 0.2 * i as f64, -0.4 + 0.2 * j as f64, 0.1 * ((i * j) % 3) as f64]);
            }
        }
        v
    }

    /// A run folder holding `camera`, `poses`, one image per keyframe and a map whose Gaussians
    /// sit at `points` (ids 3, 7, 11, ...).
    fn write_run(dir: &Path, camera: &PinholeCamera, poses: &[Se3], pts: &[[f64; 3]]) -> Vec<u64> {
        std::fs::create_dir_all(dir.join("keyframes")).unwrap();
        let c = camera;
        std::fs::write(dir.join("calibration.txt"), format!("{} {} {} {} {} {}\n", c.fx, c.fy, c.cx, c.cy, c.width, c.height)).unwrap();
        let mut list = String::from("# keyframe_id timestamp tx ty tz qx qy qz qw\n");
        let ids: Vec<u64> = (0..poses.len() as u64).map(|k| 3 + 4 * k).collect();
        for (id, pose) in ids.iter().zip(poses) {
            let v = duv_core::pose::se3_to_tum(pose);
            list.push_str(&format!("{id} {} {} {} {} {} {} {} {}\n", *id as f64 * 0.1, v[0], v[1], v[2], v[3], v[4], v[5], v[6]));
            let mut img = ImageRgb8::new(c.width, c.height);
            img.data.iter_mut().enumerate().for_each(|(i, v)| *v = (i as u64 * 7 + id) as u8);
            write_rgb8(&dir.join("keyframes").join(format!("{id:06}.png")), &img).unwrap();
        }
        std::fs::write(dir.join("keyframes.txt"), list).unwrap();
        let mut g = Gaussians::with_capacity(pts.len());
        for (i, p) in pts.iter().enumerate() {
            let q = GaussianParam::<f32> {
                mean: p.map(|v| v as f32),
                f_dc: [0.3, -0.2, (i as f32) * 0.05 - 0.5],
                opacity_logit: 0.5,
                log_scale: [-3.0; 3],
                rotation: [1.0, 0.0, 0.0, 0.0],
                ..Default::default()
            };
            g.push(&q).unwrap();
        }
        duv_map::ply::write_ply(&dir.join("map.ply"), &g).unwrap();
        ids
    }

    fn data_lines(text: &str) -> Vec<&str> {
        text.lines().filter(|l| !l.starts_with('#')).collect()
    }

    fn nums(line: &str) -> Vec<f64> {
        line.split_whitespace().map(|v| v.parse().unwrap()).collect()
    }

    #[test]
    fn both_conventions_reproject_the_points_as_our_camera_does() {
        let tmp = tempfile::tempdir().unwrap();
        let (run, out) = (tmp.path().join("run"), tmp.path().join("export"));
        let (cam, poses, pts) = (camera(), poses(), points());
        let ids = write_run(&run, &cam, &poses, &pts);
        let summary = export_run(&run, &out, &ExportOptions::default()).unwrap();
        assert_eq!(summary.images.len(), 3);
        assert_eq!((summary.points, summary.gaussians), (pts.len(), pts.len()));
        assert_eq!(summary.length_unit, "map", "no metric.json");

        // The expected pixels: our camera model, where the point is in front and in view.
        let mut expected: Vec<Vec<Option<[f64; 2]>>> = Vec::new();
        let mut in_view = 0;
        for pose in &poses {
            let row: Vec<Option<[f64; 2]>> = pts
                .iter()
                .map(|p| {
                    let pc = pose.inverse_transform_point(&Point3::from(*p)).coords;
                    cam.project(&pc).filter(|uv| cam.contains(uv)).map(|uv| [uv.x, uv.y])
                })
                .collect();
            in_view += row.iter().flatten().count();
            expected.push(row);
        }
        assert!(in_view >= 80, "the scene is mostly in view ({in_view} of {})", 3 * pts.len());

        // COLMAP: x_cam = R X + t, pixel = K x_cam / z, origin at the first pixel's corner.
        let sparse = out.join(SPARSE_DIR);
        let cameras = std::fs::read_to_string(sparse.join("cameras.txt")).unwrap();
        let cam_lines = data_lines(&cameras);
        assert_eq!(cam_lines.len(), 1);
        let f: Vec<&str> = cam_lines[0].split_whitespace().collect();
        assert_eq!(&f[..4], &["1", "PINHOLE", "160", "120"]);
        let k: Vec<f64> = f[4..].iter().map(|v| v.parse().unwrap()).collect();
        let images_txt = std::fs::read_to_string(sparse.join("images.txt")).unwrap();
        let lines = data_lines(&images_txt);
        assert_eq!(lines.len(), 6, "a pose line and an empty points line per image:\n{images_txt}");
        let mut worst = 0.0f64;
        let mut compared = 0;
        for (n, pair) in lines.chunks(2).enumerate() {
            assert_eq!(pair[1], "", "no 2D points");
            let f: Vec<&str> = pair[0].split_whitespace().collect();
            assert_eq!(f.len(), 10);
            assert_eq!((f[0], f[8], f[9]), (&*(n + 1).to_string(), "1", &*format!("{:06}.png", ids[n])));
            let v = nums(&f[1..8].join(" "));
            assert!(v[0] >= 0.0, "qw first, non-negative");
            let r = UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(v[0], v[1], v[2], v[3]));
            let t = Vector3::new(v[4], v[5], v[6]);
            for (p, want) in pts.iter().zip(&expected[n]) {
                let xc = r * Vector3::from(*p) + t;
                let uv = [k[0] * xc.x / xc.z + k[2] - PIXEL_CENTRE_OFFSET, k[1] * xc.y / xc.z + k[3] - PIXEL_CENTRE_OFFSET];
                if let Some(w) = want {
                    worst = worst.max((uv[0] - w[0]).abs()).max((uv[1] - w[1]).abs());
                    compared += 1;
                }
            }
        }
        assert_eq!(compared, in_view);
        eprintln!("COLMAP: {compared} projections, largest difference {worst:e} px");
        assert!(worst < REPROJECTION_TOL_PX, "COLMAP reprojection off by {worst} px");

        // nerfstudio: invert camera-to-world, OpenGL axes back to ours (y, z flipped).
        let json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("transforms.json")).unwrap()).unwrap();
        assert_eq!(json["camera_model"], "PINHOLE");
        assert_eq!((json["w"].as_u64(), json["h"].as_u64()), (Some(160), Some(120)));
        assert_eq!(json["duv_length_unit"], "map");
        assert_eq!(json["ply_file_path"], "points3D.ply");
        let (fx, fy, cx, cy) = (json["fl_x"].as_f64().unwrap(), json["fl_y"].as_f64().unwrap(), json["cx"].as_f64().unwrap(), json["cy"].as_f64().unwrap());
        let frames = json["frames"].as_array().unwrap();
        assert_eq!(frames.len(), 3);
        let mut worst = 0.0f64;
        for (n, fr) in frames.iter().enumerate() {
            assert_eq!(fr["file_path"], format!("images/{:06}.png", ids[n]));
            assert!(out.join(fr["file_path"].as_str().unwrap()).is_file());
            let rows = fr["transform_matrix"].as_array().unwrap();
            let c2w = Matrix4::from_fn(|r, c| rows[r][c].as_f64().unwrap());
            assert_eq!(c2w.row(3).clone_owned(), nalgebra::RowVector4::new(0.0, 0.0, 0.0, 1.0));
            let w2c = c2w.try_inverse().unwrap();
            for (p, want) in pts.iter().zip(&expected[n]) {
                let x_gl = w2c * Vector4::new(p[0], p[1], p[2], 1.0);
                let xc = Vector3::new(x_gl.x, -x_gl.y, -x_gl.z);
                if let Some(w) = want {
                    let uv = [fx * xc.x / xc.z + cx - PIXEL_CENTRE_OFFSET, fy * xc.y / xc.z + cy - PIXEL_CENTRE_OFFSET];
                    worst = worst.max((uv[0] - w[0]).abs()).max((uv[1] - w[1]).abs());
                }
            }
        }
        eprintln!("nerfstudio: largest difference {worst:e} px");
        assert!(worst < REPROJECTION_TOL_PX, "nerfstudio reprojection off by {worst} px");

        // The points: the map's centres and base colours; their PLY holds the same.
        let points_txt = std::fs::read_to_string(sparse.join("points3D.txt")).unwrap();
        let rows = data_lines(&points_txt);
        assert_eq!(rows.len(), pts.len());
        for (i, (row, p)) in rows.iter().zip(&pts).enumerate() {
            let v = nums(row);
            assert_eq!(v.len(), 8, "no track: {row}");
            assert_eq!(v[0], (i + 1) as f64);
            for a in 0..3 {
                assert!((v[1 + a] - p[a]).abs() < 1e-6, "{row} vs {p:?}");
            }
            let dc = [0.3f32, -0.2, (i as f32) * 0.05 - 0.5];
            for c in 0..3 {
                assert_eq!(v[4 + c], ((0.5 + SH_C0 * dc[c] as f64).clamp(0.0, 1.0) * 255.0).round(), "{row}");
            }
        }
        let ply = std::fs::read(out.join("points3D.ply")).unwrap();
        let header_end = ply.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
        assert_eq!(ply.len() - header_end, pts.len() * 15);
        assert_eq!(std::fs::read(out.join("map.ply")).unwrap(), std::fs::read(run.join("map.ply")).unwrap(), "the map copied as it is");
        // The images copied byte for byte.
        for id in &ids {
            let name = format!("{id:06}.png");
            assert_eq!(std::fs::read(out.join("images").join(&name)).unwrap(), std::fs::read(run.join("keyframes").join(&name)).unwrap());
        }
        let readme = std::fs::read_to_string(out.join("README.txt")).unwrap();
        assert!(readme.contains("Length unit: the tracker's map units"), "{readme}");
    }

    #[test]
    fn one_format_writes_only_its_files_and_the_unit_comes_from_metric_json() {
        let tmp = tempfile::tempdir().unwrap();
        let run = tmp.path().join("run");
        write_run(&run, &camera(), &poses(), &points());
        super::super::metric::MetricRecord::map_units("test", 0).write(&run).unwrap();
        let mut record: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("metric.json")).unwrap()).unwrap();
        record["length_unit"] = "m".into();
        std::fs::write(run.join("metric.json"), record.to_string()).unwrap();
        let colmap = tmp.path().join("colmap");
        let opts = ExportOptions { format: ExportFormat::Colmap, max_points: 10, ..ExportOptions::default() };
        let s = export_run(&run, &colmap, &opts).unwrap();
        assert_eq!((s.points, s.gaussians, s.length_unit.as_str()), (10, 35, "m"));
        assert!(colmap.join("sparse/0/images.txt").is_file() && !colmap.join("transforms.json").exists() && !colmap.join("points3D.ply").exists());
        assert!(std::fs::read_to_string(colmap.join("sparse/0/images.txt")).unwrap().contains("length unit m"));
        // Evenly subsampled: every 3rd or 4th of the 35, the first one first.
        let rows = std::fs::read_to_string(colmap.join("sparse/0/points3D.txt")).unwrap();
        let first = nums(data_lines(&rows)[0]);
        assert_eq!(&first[1..4], &[-0.6f32 as f64, -0.4f32 as f64, 0.0]);
        let ns = tmp.path().join("ns");
        export_run(&run, &ns, &ExportOptions { format: ExportFormat::Nerfstudio, ..ExportOptions::default() }).unwrap();
        assert!(ns.join("transforms.json").is_file() && !ns.join("sparse").exists());
    }

    #[test]
    fn restored_images_are_the_third_panel_of_the_renders() {
        let tmp = tempfile::tempdir().unwrap();
        let run = tmp.path().join("run");
        let cam = camera();
        let ids = write_run(&run, &cam, &poses(), &points());
        let opts = ExportOptions { restored: true, ..ExportOptions::default() };
        let e = export_run(&run, &tmp.path().join("x"), &opts).unwrap_err();
        assert!(matches!(e, ExportError::NoRestored { .. }), "{e}");
        assert!(e.to_string().contains("renders"), "{e}");
        std::fs::create_dir_all(run.join("renders")).unwrap();
        // Renders of the first two keyframes only: panel k filled with 40 k + 1.
        // The first as the mapper writes it (under its label strip), the second as older
        // runs did (no labels).
        for (k, id) in ids[..2].iter().enumerate() {
            let mut panel = ImageRgb8::new(cam.width * 5, cam.height);
            for (i, px) in panel.data.chunks_exact_mut(3).enumerate() {
                px.fill(((i % (cam.width * 5)) / cam.width * 40 + 1) as u8);
            }
            let panel = if k == 0 { duv_map::stage::with_labels(&panel, cam.width, &duv_map::stage::PANEL_LABELS) } else { panel };
            write_rgb8(&run.join("renders").join(format!("{id:06}.png")), &panel).unwrap();
        }
        let out = tmp.path().join("restored");
        let s = export_run(&run, &out, &opts).unwrap();
        assert_eq!(s.images.iter().map(|i| i.keyframe).collect::<Vec<_>>(), ids[..2].to_vec());
        assert_eq!(s.without_render, vec![ids[2]]);
        let img = read_image(&out.join("images").join(format!("{:06}.png", ids[0]))).unwrap().to_rgb8();
        assert_eq!((img.width, img.height), (cam.width, cam.height));
        assert!(img.data.iter().all(|&v| v == 81), "the restored panel");
        let img = read_image(&out.join("images").join(format!("{:06}.png", ids[1]))).unwrap().to_rgb8();
        assert!(img.data.iter().all(|&v| v == 81), "the restored panel of an unlabelled render");
        // A render of the wrong size is refused, naming it.
        write_rgb8(&run.join("renders").join(format!("{:06}.png", ids[2])), &ImageRgb8::new(cam.width, cam.height)).unwrap();
        let e = export_run(&run, &out, &opts).unwrap_err();
        assert!(matches!(e, ExportError::RenderSize { .. }) && e.to_string().contains(&format!("{:06}.png", ids[2])), "{e}");
    }

    #[test]
    fn bad_run_folders_are_refused_naming_the_file() {
        let tmp = tempfile::tempdir().unwrap();
        let run = tmp.path().join("run");
        let out = tmp.path().join("out");
        let opts = ExportOptions::default();
        let msg = |e: ExportError| e.to_string();
        assert!(msg(export_run(&run, &out, &opts).unwrap_err()).contains("not a run folder"));
        let ids = write_run(&run, &camera(), &poses(), &points());
        let e = msg(export_run(&run, &run.join("."), &opts).unwrap_err());
        assert!(e.contains("the export folder is the run folder"), "{e}");
        assert!(msg(export_run(&run, &out, &ExportOptions { max_points: 0, ..ExportOptions::default() }).unwrap_err()).contains("max_points = 0"));

        std::fs::rename(run.join("map.ply"), run.join("map.bak")).unwrap();
        let e = msg(export_run(&run, &out, &opts).unwrap_err());
        assert!(e.contains("map.ply: missing"), "{e}");
        std::fs::rename(run.join("map.bak"), run.join("map.ply")).unwrap();

        std::fs::rename(run.join("keyframes.txt"), run.join("kf.bak")).unwrap();
        let e = msg(export_run(&run, &out, &opts).unwrap_err());
        assert!(e.contains("keyframes.txt: missing"), "{e}");
        std::fs::write(run.join("keyframes.txt"), "# nothing\n").unwrap();
        assert!(msg(export_run(&run, &out, &opts).unwrap_err()).contains("keyframes.txt: no keyframes listed"));
        std::fs::write(run.join("keyframes.txt"), "3 0.1 0 0 1 0 0 0 1\n4 0.2 0 0 one 0 0 0 1\n").unwrap();
        let e = msg(export_run(&run, &out, &opts).unwrap_err());
        assert!(e.contains("keyframes.txt") && e.contains("line 2"), "{e}");
        std::fs::rename(run.join("kf.bak"), run.join("keyframes.txt")).unwrap();

        let calib = std::fs::read_to_string(run.join("calibration.txt")).unwrap();
        std::fs::write(run.join("calibration.txt"), format!("{} 0.1 -0.05 0 0\n", calib.trim())).unwrap();
        let e = msg(export_run(&run, &out, &opts).unwrap_err());
        assert!(e.contains("calibration.txt: 10 fields") && e.contains("distortion"), "{e}");
        std::fs::write(run.join("calibration.txt"), "100 100 80 60 320 240\n").unwrap();
        let e = msg(export_run(&run, &out, &opts).unwrap_err());
        assert!(e.contains("160x120, the calibration says 320x240"), "{e}");
        std::fs::write(run.join("calibration.txt"), calib).unwrap();

        std::fs::remove_file(run.join("keyframes").join(format!("{:06}.png", ids[1]))).unwrap();
        let e = msg(export_run(&run, &out, &opts).unwrap_err());
        assert!(e.contains(&format!("{:06}.png: missing", ids[1])), "{e}");
        assert!(!out.exists(), "nothing written before the inputs are checked");
    }

    #[test]
    fn the_opengl_matrix_flips_y_and_z_of_the_camera() {
        let pose = poses()[1];
        let m = nerfstudio_matrix(&pose);
        let r = pose.rotation.to_rotation_matrix();
        for row in 0..3 {
            assert!((m[row][0] - r[(row, 0)]).abs() < 1e-15);
            assert!((m[row][1] + r[(row, 1)]).abs() < 1e-15);
            assert!((m[row][2] + r[(row, 2)]).abs() < 1e-15);
            assert!((m[row][3] - pose.translation.vector[row]).abs() < 1e-15);
        }
        // COLMAP's pose is the inverse: the camera centre is -R^T t.
        let (q, t) = colmap_pose(&pose);
        let r = UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q[0], q[1], q[2], q[3]));
        let centre = -(r.inverse() * Vector3::from(t));
        assert!((centre - pose.translation.vector).norm() < 1e-12);
    }
}
