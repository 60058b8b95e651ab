//! `duv-tools convert --source SPEC --out DIR`: any readable dataset to our TUM layout:
//! `rgb/*.png` (8-bit RGB), `depth/*.png` (16-bit, metres x 5000) where the source has depth,
//! `rgb.txt`, `depth.txt`, `groundtruth.txt`, `calibration.txt`, `medium.json` when known.
//! Distorted images (and depth maps) are undistorted, and the undistorted intrinsics written.

use anyhow::{bail, Context};
use duv_camera::dataset::{format_calibration, open_dataset, Dataset};
use duv_core::{ImageGray16, ImageRgb8, PlaneF32};
use duv_core::io::png_io::{write_gray16, write_rgb8};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// Depth PNG units per metre in the written layout (TUM).
pub const DEPTH_UNITS_PER_METRE: f64 = 5000.0;

#[derive(clap::Args)]
pub struct ConvertArgs {
    /// Dataset spec, e.g. euroc:MH_01_easy, tartanair:abandonedfactory/P000,fps=10.
    #[arg(long)]
    source: String,
    /// Output folder; created, and must be empty if it exists.
    #[arg(long)]
    out: PathBuf,
}

/// What a conversion wrote.
#[derive(Debug, Clone, PartialEq)]
pub struct ConvertReport {
    pub frames: usize,
    pub depth_maps: usize,
    /// Depth pixels beyond the 16-bit range (13.1 m at 5000 per metre), written as 0 (no depth).
    pub depth_out_of_range: usize,
    pub ground_truth_poses: usize,
    pub undistorted: bool,
    pub medium: bool,
}

pub fn run(args: ConvertArgs) -> anyhow::Result<()> {
    let dataset = open_dataset(&args.source).with_context(|| format!("opening {}", args.source))?;
    let total = dataset.frames.len() + dataset.depth.as_ref().map_or(0, |t| t.frames.len());
    let bar = indicatif::ProgressBar::new(total as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template("converting {bar:40} {pos}/{len} files, {elapsed} elapsed, eta {eta}")
            .expect("static progress template"),
    );
    let report = convert(&dataset, &args.out, &mut |_| bar.inc(1))?;
    bar.finish_and_clear();
    println!(
        "wrote {}: {} frames{}, {} depth maps ({} pixels beyond 16-bit range set to 0), {} ground-truth poses{}",
        args.out.display(),
        report.frames,
        if report.undistorted { " (undistorted)" } else { "" },
        report.depth_maps,
        report.depth_out_of_range,
        report.ground_truth_poses,
        if report.medium { ", medium.json" } else { "" },
    );
    Ok(())
}

/// Writes `dataset` to `out` in our TUM layout; `progress` is called once per file written.
pub fn convert(dataset: &Dataset, out: &Path, progress: &mut dyn FnMut(usize)) -> anyhow::Result<ConvertReport> {
    prepare_out_dir(out)?;
    let camera = dataset.camera;
    let map = camera.distortion.map(|_| camera.undistort_map());

    std::fs::create_dir_all(out.join("rgb")).with_context(|| format!("creating {}", out.join("rgb").display()))?;
    let mut rgb_txt = format!("# color images converted from {}\n# timestamp filename\n", dataset.describe());
    let mut undistorted = ImageRgb8::new(camera.width, camera.height);
    for index in 0..dataset.frames.len() {
        let frame = dataset.load_frame(index).context("converting (run `duv dataset SPEC --check` to list bad frames)")?;
        let rgb = frame.image.to_rgb8();
        let image = match &map {
            Some(m) => {
                m.apply_rgb8(&rgb, &mut undistorted);
                &undistorted
            }
            None => &rgb,
        };
        let name = format!("rgb/{}.png", frame.t_ns);
        write_rgb8(&out.join(&name), image)?;
        writeln!(rgb_txt, "{} {name}", frame.t_ns)?;
        progress(index);
    }
    write_text(&out.join("rgb.txt"), &rgb_txt)?;

    let mut report = ConvertReport {
        frames: dataset.frames.len(),
        depth_maps: 0,
        depth_out_of_range: 0,
        ground_truth_poses: 0,
        undistorted: map.is_some(),
        medium: false,
    };
    if let Some(track) = &dataset.depth {
        std::fs::create_dir_all(out.join("depth")).with_context(|| format!("creating {}", out.join("depth").display()))?;
        let mut depth_txt = format!("# depth maps (metres x {DEPTH_UNITS_PER_METRE}, 0 = none)\n# timestamp filename\n");
        for (k, f) in track.frames.iter().enumerate() {
            let metres = dataset.load_depth(k)?;
            let metres = match &map {
                Some(m) => remap_nearest(&metres, &m.source_xy),
                None => metres,
            };
            let (raw, out_of_range) = quantise_depth(&metres);
            report.depth_out_of_range += out_of_range;
            let name = format!("depth/{}.png", f.t_ns);
            write_gray16(&out.join(&name), &raw)?;
            writeln!(depth_txt, "{} {name}", f.t_ns)?;
            progress(dataset.frames.len() + k);
        }
        write_text(&out.join("depth.txt"), &depth_txt)?;
        report.depth_maps = track.frames.len();
    }
    if let Some(gt) = &dataset.ground_truth {
        duv_core::io::tum::write_trajectory(&out.join("groundtruth.txt"), gt)?;
        report.ground_truth_poses = gt.len();
    }
    write_text(&out.join("calibration.txt"), &format_calibration(&camera.undistorted()))?;
    if let Some(m) = &dataset.medium {
        write_text(&out.join("medium.json"), &(serde_json::to_string_pretty(m)? + "\n"))?;
        report.medium = true;
    }
    Ok(report)
}

fn prepare_out_dir(out: &Path) -> anyhow::Result<()> {
    if out.exists() {
        let mut entries = std::fs::read_dir(out).with_context(|| format!("reading {}", out.display()))?;
        if entries.next().is_some() {
            bail!("{} is not empty; convert writes into a new or empty folder", out.display());
        }
    }
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))
}

fn write_text(path: &Path, text: &str) -> anyhow::Result<()> {
    std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))
}

/// Nearest-neighbour remap (depth must not be blended across edges); outside is 0.
fn remap_nearest(input: &PlaneF32, source_xy: &[[f32; 2]]) -> PlaneF32 {
    let (w, h) = (input.width, input.height);
    let data = source_xy
        .iter()
        .map(|&[sx, sy]| {
            let (x, y) = (sx.round(), sy.round());
            if x >= 0.0 && y >= 0.0 && x < w as f32 && y < h as f32 {
                input.data[y as usize * w + x as usize]
            } else {
                0.0
            }
        })
        .collect();
    PlaneF32 { width: w, height: h, data }
}

/// Metres to TUM 16-bit units; 0 stays 0, values beyond the range become 0 and are counted.
fn quantise_depth(metres: &PlaneF32) -> (ImageGray16, usize) {
    let mut out_of_range = 0;
    let data = metres
        .data
        .iter()
        .map(|&m| {
            let units = (m as f64 * DEPTH_UNITS_PER_METRE).round();
            if units.is_nan() || units < 1.0 {
                0
            } else if units > u16::MAX as f64 {
                out_of_range += 1;
                0
            } else {
                units as u16
            }
        })
        .collect();
    (ImageGray16 { width: metres.width, height: metres.height, data }, out_of_range)
}

#[cfg(test)]
mod tests {
    use super::*;
    use duv_camera::dataset::npy::write_npy_f32;
    use duv_core::{FrameImage, ImageGray8};
    use nalgebra::Vector3;

    const W: usize = 16;
    const H: usize = 12;
    const T0: i64 = 1_403_636_579_763_555_584;

    fn grey(k: usize) -> ImageGray8 {
        ImageGray8 { width: W, height: H, data: (0..W * H).map(|i| ((i * 3 + k * 50) % 256) as u8).collect() }
    }

    /// An EuRoC-like folder: three grey 16x12 frames, radial-tangential distortion (or none),
    /// a T_BS with rotation, ground truth for every frame.
    fn write_euroc(root: &Path, distortion: [f64; 4]) {
        let cam = root.join("mav0/cam0");
        std::fs::create_dir_all(cam.join("data")).unwrap();
        let mut csv = String::from("#timestamp [ns],filename\n");
        let mut gt = String::from("#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []\n");
        for k in 0..3 {
            let t = T0 + k as i64 * 50_000_000;
            duv_core::io::png_io::write_gray8(&cam.join(format!("data/{t}.png")), &grey(k)).unwrap();
            writeln!(csv, "{t},{t}.png").unwrap();
            writeln!(gt, "{t},{},0.5,-1,0.9800665778,0,0,0.1986693308", 0.2 * k as f64).unwrap();
        }
        std::fs::write(cam.join("data.csv"), csv).unwrap();
        let [k1, k2, p1, p2] = distortion;
        let yaml = format!(
            "sensor_type: camera\nT_BS:\n  cols: 4\n  rows: 4\n  data: [0.0, 0.0, 1.0, 0.1,\n        -1.0, 0.0, 0.0, 0.0,\n         0.0, -1.0, 0.0, 0.0,\n         0.0, 0.0, 0.0, 1.0]\nresolution: [{W}, {H}]\ncamera_model: pinhole\nintrinsics: [12.0, 12.5, 7.5, 5.5] #fu, fv, cu, cv\ndistortion_model: radial-tangential\ndistortion_coefficients: [{k1}, {k2}, {p1}, {p2}]\n"
        );
        std::fs::write(cam.join("sensor.yaml"), yaml).unwrap();
        std::fs::create_dir_all(root.join("mav0/state_groundtruth_estimate0")).unwrap();
        std::fs::write(root.join("mav0/state_groundtruth_estimate0/data.csv"), gt).unwrap();
    }

    fn convert_spec(spec: &str, out: &Path) -> (Dataset, ConvertReport, Dataset) {
        let source = open_dataset(spec).unwrap();
        let mut calls = 0;
        let report = convert(&source, out, &mut |_| calls += 1).unwrap();
        assert_eq!(calls, report.frames + report.depth_maps);
        let back = open_dataset(&format!("tum:{}", out.display())).unwrap();
        (source, report, back)
    }

    #[test]
    fn euroc_with_distortion_becomes_an_undistorted_tum_layout() {
        let dir = tempfile::tempdir().unwrap();
        let src_dir = dir.path().join("euroc");
        let out = dir.path().join("tum");
        write_euroc(&src_dir, [-0.2, 0.05, 0.001, -0.0005]);
        let (source, report, back) = convert_spec(&format!("euroc:{}", src_dir.display()), &out);
        assert_eq!(report, ConvertReport { frames: 3, depth_maps: 0, depth_out_of_range: 0, ground_truth_poses: 3, undistorted: true, medium: false });

        // Same time stamps; the undistorted intrinsics; the camera poses (already through T_BS).
        assert_eq!(back.frames.iter().map(|f| f.t_ns).collect::<Vec<_>>(), source.frames.iter().map(|f| f.t_ns).collect::<Vec<_>>());
        assert_eq!(back.camera, source.camera.undistorted());
        assert!(back.camera.distortion.is_none() && back.depth.is_none() && back.medium.is_none());
        let (a, b) = (source.ground_truth.as_ref().unwrap(), back.ground_truth.as_ref().unwrap());
        for (p, q) in a.iter().zip(b) {
            assert_eq!(p.t_ns, q.t_ns);
            assert!((p.world_from_cam.to_homogeneous() - q.world_from_cam.to_homogeneous()).abs().max() < 1e-8);
        }
        // Body at (0.2, 0.5, -1) yawed 22.9 degrees; camera 0.1 m along body x, looking along it.
        let yaw = 2.0 * 0.1986693308f64.atan2(0.9800665778);
        let fwd = Vector3::new(yaw.cos(), yaw.sin(), 0.0);
        assert!((b[1].world_from_cam.rotation * Vector3::z() - fwd).norm() < 1e-8);
        assert!((b[1].world_from_cam.translation.vector - (Vector3::new(0.2, 0.5, -1.0) + 0.1 * fwd)).norm() < 1e-8);

        // Images: RGB, each the undistortion of the grey source.
        let map = source.camera.undistort_map();
        for k in 0..3 {
            let FrameImage::Rgb8(img) = back.load_frame(k).unwrap().image else { panic!("converted frames are RGB") };
            let mut expected = ImageRgb8::new(W, H);
            map.apply_rgb8(&grey(k).to_rgb8(), &mut expected);
            assert_eq!(img, expected);
            assert_ne!(img, grey(k).to_rgb8(), "distortion must change the image");
        }

        // The output folder now holds files: converting into it again is refused.
        let e = convert(&source, &out, &mut |_| {}).unwrap_err();
        assert!(e.to_string().contains("is not empty"), "{e}");
    }

    #[test]
    fn euroc_without_distortion_keeps_pixels() {
        let dir = tempfile::tempdir().unwrap();
        write_euroc(&dir.path().join("e"), [0.0; 4]);
        let (_, report, back) = convert_spec(&format!("euroc:{}", dir.path().join("e").display()), &dir.path().join("t"));
        assert!(!report.undistorted);
        for k in 0..3 {
            assert_eq!(back.load_frame(k).unwrap().image, FrameImage::Rgb8(grey(k).to_rgb8()));
        }
    }

    #[test]
    fn tartanair_depth_and_medium_carry_over() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("ta");
        std::fs::create_dir_all(root.join("image_left")).unwrap();
        std::fs::create_dir_all(root.join("depth_left")).unwrap();
        for k in 0..2 {
            duv_core::io::png_io::write_rgb8(&root.join(format!("image_left/{k:06}_left.png")), &grey(k).to_rgb8()).unwrap();
            let mut depth = PlaneF32 { width: W, height: H, data: (0..W * H).map(|i| 0.5 + i as f32 * 0.01).collect() };
            depth.data[0] = f32::NAN;
            depth.data[1] = 20.0;
            write_npy_f32(&root.join(format!("depth_left/{k:06}_left_depth.npy")), &depth).unwrap();
        }
        std::fs::write(root.join("calibration.txt"), format!("12 12 7.5 5.5 {W} {H}\n")).unwrap();
        std::fs::write(root.join("pose_left.txt"), "0 0 0 0 0 0 1\n1 0 0 0 0 0 1\n").unwrap();
        std::fs::write(root.join("medium.json"), r#"{"beta_D":[0.4,0.1,0.05],"beta_B":[0.3,0.1,0.06],"B_inf":[0.05,0.3,0.4]}"#).unwrap();
        let (source, report, back) = convert_spec(&format!("tartanair:{},fps=5", root.display()), &dir.path().join("out"));
        assert_eq!((report.depth_maps, report.depth_out_of_range, report.medium), (2, 2, true));
        assert_eq!(back.medium, source.medium);
        assert_eq!(back.frames[1].t_ns.t_ns(), 200_000_000);
        let (a, b) = (source.load_depth_for_frame(1).unwrap().unwrap(), back.load_depth_for_frame(1).unwrap().unwrap());
        assert_eq!((b.data[0], b.data[1]), (0.0, 0.0), "NaN and beyond-range depth become 0");
        for (x, y) in a.data.iter().zip(&b.data).skip(2) {
            assert!((x - y).abs() <= 0.5 / DEPTH_UNITS_PER_METRE as f32 + 1e-6, "{x} {y}");
        }
        // Forward in NED (+x) is +z in the converted camera world.
        let gt = back.ground_truth.unwrap();
        assert!((gt[1].world_from_cam.translation.vector - Vector3::z()).norm() < 1e-9);
    }

    #[test]
    fn nearest_remap_and_quantisation() {
        let plane = PlaneF32 { width: 2, height: 2, data: vec![1.0, 2.0, 3.0, 4.0] };
        let r = remap_nearest(&plane, &[[0.4, 0.4], [0.6, 0.0], [-0.6, 1.0], [1.2, 0.9]]);
        assert_eq!(r.data, vec![1.0, 2.0, 0.0, 4.0]);
        let (q, n) = quantise_depth(&PlaneF32 { width: 4, height: 1, data: vec![0.0, 1.0, 13.107, 13.2] });
        assert_eq!((q.data, n), (vec![0, 5000, 65535, 0], 1));
    }
}
