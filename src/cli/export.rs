//! `duv export --run RUN --out DIR`: a finished run's keyframes with their poses and its map
//! as a COLMAP text model and a nerfstudio `transforms.json`, for offline splatting
//! (`duv_pipeline::export`).

use anyhow::Context;
use duv_pipeline::export::{export_run, ExportFormat, ExportOptions, SPARSE_DIR};
use std::path::PathBuf;

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum Format {
    /// COLMAP text model: sparse/0/cameras.txt, images.txt, points3D.txt.
    Colmap,
    /// nerfstudio: transforms.json and points3D.ply.
    Nerfstudio,
    /// Both.
    All,
}

#[derive(clap::Args)]
pub struct ExportArgs {
    /// A finished `duv run` folder (calibration.txt, keyframes.txt, keyframes/, map.ply).
    #[arg(long, value_name = "RUN_DIR")]
    run: PathBuf,
    /// Export folder: images/, the models, a copy of map.ply and README.txt (with the length
    /// unit: metres when the run's metric.json says so, else map units). Files of the same
    /// names are replaced.
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// Which models to write. Both use the undistorted pinhole of the run with the image origin
    /// at the first pixel's corner (their convention); COLMAP stores world-to-camera poses,
    /// nerfstudio camera-to-world with OpenGL camera axes (y up, z back).
    #[arg(long, value_enum, default_value_t = Format::All)]
    format: Format,
    /// Use the restored (water-free) keyframe images the mapper rendered (the third panel of
    /// RUN/renders/NNNNNN.png) instead of the captured ones; keyframes without a render are
    /// left out; a run without renders is an error.
    #[arg(long)]
    restored: bool,
    /// Most points in points3D.txt / points3D.ply (the map's Gaussian centres, evenly
    /// subsampled beyond it).
    #[arg(long, default_value_t = 100_000)]
    max_points: usize,
}

pub fn run(args: ExportArgs) -> anyhow::Result<()> {
    let format = match args.format {
        Format::Colmap => ExportFormat::Colmap,
        Format::Nerfstudio => ExportFormat::Nerfstudio,
        Format::All => ExportFormat::All,
    };
    let opts = ExportOptions { format, restored: args.restored, max_points: args.max_points };
    let s = export_run(&args.run, &args.out, &opts).with_context(|| format!("exporting {}", args.run.display()))?;
    let c = &s.camera;
    println!(
        "exported {} keyframes ({}x{}, fx {} fy {}{}) and {} points (of {} Gaussians) to {}, length unit {}",
        s.images.len(),
        c.width,
        c.height,
        c.fx,
        c.fy,
        if args.restored { ", restored images" } else { "" },
        s.points,
        s.gaussians,
        args.out.display(),
        s.length_unit
    );
    if !s.without_render.is_empty() {
        println!("left out {} keyframes without a render: {:?}", s.without_render.len(), s.without_render);
    }
    println!("wrote {}", s.written.join(", "));
    if matches!(format, ExportFormat::Colmap | ExportFormat::All) {
        println!("COLMAP model: {}", args.out.join(SPARSE_DIR).display());
    }
    Ok(())
}
