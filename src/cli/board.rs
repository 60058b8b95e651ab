//! `duv board`: validate board profiles and show what they allow.

use anyhow::Context;
use duv_core::config::board::FrameLogEncoding;
use duv_core::config::Board;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct BoardArgs {
    /// Board files to check; default: every `boards/*.toml`.
    files: Vec<PathBuf>,
}

pub fn run(args: BoardArgs) -> anyhow::Result<()> {
    let files = if args.files.is_empty() {
        Board::files_in(std::path::Path::new("boards")).context("listing boards/ (run from the repository root or name files)")?
    } else {
        args.files
    };
    let mut failed = 0;
    for path in &files {
        match Board::load(path) {
            Ok(b) => {
                let c = &b.camera;
                let bu = &b.budgets;
                let frames = match b.log.frame_encoding {
                    FrameLogEncoding::Raw => "raw".to_string(),
                    FrameLogEncoding::Jpeg => format!("jpeg q{}", b.log.jpeg_quality),
                };
                println!(
                    "ok    {:<24} {}x{} @ {} fps {:?} from {} | host {} MiB, GPU {} MiB, {} Gaussians, {} keyframes (window {}, mapper {}), queues {}/{}/{} MiB | threads {}+{} | log frames {frames}",
                    b.name, c.width, c.height, c.fps, c.pixel_format, c.source, bu.host_mb, bu.gpu_mb, bu.max_gaussians,
                    bu.max_keyframes, bu.ba_window, bu.map_keyframes, bu.frame_queue, bu.keyframe_queue, bu.log_queue_mb, b.threads.tracking, b.threads.mapping
                );
            }
            Err(e) => {
                failed += 1;
                println!("error {e}");
            }
        }
    }
    anyhow::ensure!(failed == 0, "{failed} of {} board files are invalid", files.len());
    Ok(())
}
