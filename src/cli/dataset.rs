//! `duv dataset SPEC [--check]`: open a dataset through the readers and summarise it; with
//! `--check`, decode every image (and depth map) and report the ones that fail.

use anyhow::Context;
use duv_camera::dataset::{open_dataset, Dataset, DepthFormat};
use duv_camera::{CameraError, FrameSource};

#[derive(clap::Args)]
pub struct DatasetArgs {
    /// Dataset spec KIND:DIR[,OPTION=VALUE]...: tum:DIR[,calib=FILE][,depth_scale=F],
    /// euroc:DIR[,cam=cam0], tartanair:DIR[,calib=FILE][,fps=10], folder:DIR[,calib=FILE][,fps=10].
    spec: String,
    /// Decode every image and depth map; list the bad ones and exit non-zero if there are any.
    #[arg(long)]
    check: bool,
}

pub fn run(args: DatasetArgs) -> anyhow::Result<()> {
    let dataset = open_dataset(&args.spec).with_context(|| format!("opening {}", args.spec))?;
    print!("{}", summary(&dataset));
    if args.check {
        check(dataset)?;
    }
    Ok(())
}

fn summary(d: &Dataset) -> String {
    use std::fmt::Write as _;
    let mut s = String::new();
    let c = &d.camera;
    let _ = writeln!(s, "kind          {}", d.kind);
    let _ = writeln!(s, "root          {}", d.root.display());
    let (first, last) = (d.frames[0].t_ns, d.frames[d.frames.len() - 1].t_ns);
    let span = last.secs_since(first);
    let rate = if span > 0.0 { format!("{:.3} Hz", (d.frames.len() - 1) as f64 / span) } else { "n/a".into() };
    let _ = writeln!(s, "frames        {} from {first} to {last} s ({span:.3} s), mean rate {rate}", d.frames.len());
    let _ = writeln!(s, "resolution    {}x{}", c.width, c.height);
    let _ = writeln!(s, "intrinsics    fx {} fy {} cx {} cy {}", c.fx, c.fy, c.cx, c.cy);
    match c.distortion {
        Some(k) => {
            let _ = writeln!(s, "distortion    radial-tangential k1 {} k2 {} p1 {} p2 {} k3 {}", k.k1, k.k2, k.p1, k.p2, k.k3);
        }
        None => s.push_str("distortion    none\n"),
    }
    match &d.depth {
        Some(t) => {
            let format = match t.format {
                DepthFormat::PngU16 { units_per_metre } => format!("16-bit PNG, {units_per_metre} per metre"),
                DepthFormat::NpyF32Metres => ".npy float32 metres".to_string(),
            };
            let _ = writeln!(s, "depth         yes: {} maps, {format}", t.frames.len());
        }
        None => s.push_str("depth         no\n"),
    }
    match &d.ground_truth {
        Some(gt) if !gt.is_empty() => {
            let length: f64 =
                gt.windows(2).map(|w| (w[1].world_from_cam.translation.vector - w[0].world_from_cam.translation.vector).norm()).sum();
            let gt_span = gt[gt.len() - 1].t_ns.secs_since(gt[0].t_ns);
            let _ = writeln!(s, "ground truth  {} poses over {gt_span:.3} s, path length {length:.3} m", gt.len());
        }
        _ => s.push_str("ground truth  none\n"),
    }
    match &d.medium {
        Some(m) => {
            let _ = writeln!(s, "medium        beta_D {:?} beta_B {:?} B_inf {:?}", m.beta_d, m.beta_b, m.b_inf);
        }
        None => s.push_str("medium        unknown\n"),
    }
    if let Some(t) = &d.body_from_cam {
        let v = duv_core::pose::se3_to_tum(t);
        let _ = writeln!(s, "body_from_cam t [{:.6}, {:.6}, {:.6}] q(xyzw) [{:.6}, {:.6}, {:.6}, {:.6}]", v[0], v[1], v[2], v[3], v[4], v[5], v[6]);
    }
    s
}

/// Decodes everything; prints each failure once and returns an error if there was any.
fn check(dataset: Dataset) -> anyhow::Result<()> {
    let depth_maps = dataset.depth.as_ref().map_or(0, |t| t.frames.len());
    let mut bad_depth = 0;
    for k in 0..depth_maps {
        if let Err(e) = dataset.load_depth(k) {
            println!("bad depth {k}: {e}");
            bad_depth += 1;
        }
    }
    let images = dataset.frames.len();
    let mut source = dataset.into_source();
    let mut bad_images = 0;
    loop {
        match source.next_frame() {
            Ok(Some(_)) => {}
            Ok(None) => break,
            Err(e @ CameraError::BadFrame { .. }) => {
                println!("bad {e}");
                bad_images += 1;
            }
            Err(e) => return Err(e).context("reading frames"),
        }
    }
    let (checked, bad) = if depth_maps > 0 {
        (format!("{images} images, {depth_maps} depth maps"), format!("{bad_images} bad images, {bad_depth} bad depth maps"))
    } else {
        (format!("{images} images"), format!("{bad_images} bad images"))
    };
    println!("checked       {checked}: {bad}");
    if bad_images + bad_depth > 0 {
        let depth_part = if depth_maps > 0 { format!(" and {bad_depth} of {depth_maps} depth maps") } else { String::new() };
        anyhow::bail!("could not read {bad_images} of {images} images{depth_part}");
    }
    Ok(())
}
