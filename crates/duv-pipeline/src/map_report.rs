//! The map's figures at the end of every run that maps (`duv run`, `duv replay`, `duv demo`):
//! the map rendered from the tracked poses of up to [`MAX_SCORED_VIEWS`] frames between
//! keyframes (frames it was never optimised on, chosen evenly over the dive), scored against
//! those frames; their restored (water-free) views against the truth where the source knows
//! it (a `sim:` source, a dataset folder with the generator's `clear/`); the medium with its
//! unit, the Gaussians, iterations and coverage. Written as `DIR/map/report.json`,
//! `DIR/map/report.md` and a labelled panel `DIR/map/NNNNNN.png` per scored frame, and into
//! the evaluation report's `map` where the run has one. `duv bench map` scores its views
//! with the same [`score_views`].
//!
//! Coverage: the mean over the scored frames of the share of their pixels the map covers
//! (rendered alpha >= 0.5), and the share of those frames at least half covered.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use duv_core::{ImageRgb8, ImageRgbF32, PinholeCamera, Se3, Sim3};
use duv_eval::image::SsimConvention;
use duv_eval::map_quality::{score_view, summarise_restored, MapQuality, MapViewScore, LPIPS_MISSING};
use duv_map::mapper::Mapper;
use duv_map::restore::{albedo, RestoreConfig};
use duv_map::stage::render_panel;

/// Frames scored per run at most (the run's cost stays bounded: one render each).
pub const MAX_SCORED_VIEWS: usize = 8;

/// Why the map could not be scored.
#[derive(Debug, thiserror::Error)]
pub enum MapReportError {
    #[error("rendering frame {seq}: {source}")]
    Render { seq: u64, source: duv_map::mapper::MapperError },
    #[error("restoring frame {seq}: {source}")]
    Restore { seq: u64, source: duv_map::restore::RestoreError },
    #[error("scoring frame {seq}: {source}")]
    Score { seq: u64, source: duv_eval::EvalError },
    #[error("frame {seq} is {width}x{height}, the map's camera {map_width}x{map_height}")]
    Size { seq: u64, width: usize, height: usize, map_width: usize, map_height: usize },
    #[error(transparent)]
    Io(#[from] duv_core::io::IoError),
    #[error("creating {path}: {source}")]
    CreateDir { path: PathBuf, source: std::io::Error },
    #[error("reading the frames again from the run's log {0}")]
    Log(String),
    #[error("map report: {0}")]
    Json(#[from] serde_json::Error),
}

/// A frame to score: its captured image, the pose to render it from, and its water-free truth
/// where known.
#[derive(Clone, Debug)]
pub struct ScoreView {
    pub seq: u64,
    pub world_from_cam: Se3,
    pub captured: ImageRgb8,
    pub clear: Option<ImageRgb8>,
}

/// The frames halfway between consecutive keyframes (`keyframe_seqs`, at least two frames
/// apart) that have a pose in `frames` (seq, `world_from_cam`), up to `max` of them chosen
/// evenly over the dive.
pub fn pick_heldout(frames: &[(u64, Se3)], keyframe_seqs: &BTreeSet<u64>, max: usize) -> Vec<(u64, Se3)> {
    let kfs: Vec<u64> = keyframe_seqs.iter().copied().collect();
    let candidates: Vec<(u64, Se3)> = kfs
        .windows(2)
        .filter(|w| w[1] >= w[0] + 2)
        .filter_map(|w| {
            let mid = (w[0] + w[1]) / 2;
            frames.binary_search_by_key(&mid, |f| f.0).ok().map(|i| frames[i])
        })
        .collect();
    if candidates.len() <= max {
        return candidates;
    }
    (0..max).map(|k| candidates[(2 * k + 1) * candidates.len() / (2 * max)]).collect()
}

/// Renders each view from its pose, restores its captured image, scores both (against the
/// image, and against the truth where known) and, with `panels`, writes its labelled panel
/// `NNNNNN.png` there. One render and one restored image per view; `scratch` is reused.
pub fn score_views(mapper: &mut Mapper, camera: &PinholeCamera, views: &[ScoreView], restore: &RestoreConfig, panels: Option<&Path>) -> Result<Vec<MapViewScore>, MapReportError> {
    let (w, h) = (camera.width, camera.height);
    let (mut restored, mut albedo_img) = (ImageRgbF32::new(w, h), ImageRgbF32::new(w, h));
    let mut out = Vec::with_capacity(views.len());
    for v in views {
        let seq = v.seq;
        for im in std::iter::once(&v.captured).chain(v.clear.as_ref()) {
            if (im.width, im.height) != (w, h) {
                return Err(MapReportError::Size { seq, width: im.width, height: im.height, map_width: w, map_height: h });
            }
        }
        let captured = v.captured.to_rgb_f32();
        mapper.render(camera, &v.world_from_cam).map_err(|source| MapReportError::Render { seq, source })?;
        let stats = mapper.restore_last(&captured, camera, restore, &mut restored).map_err(|source| MapReportError::Restore { seq, source })?;
        let r = mapper.last_render();
        albedo(&captured, r, restore.min_alpha, &mut albedo_img);
        let clear = v.clear.as_ref().map(|c| c.to_rgb_f32());
        let (psnr_db, ssim, restored_score) = score_view(&r.colour, &captured, &restored, &albedo_img, clear.as_ref()).map_err(|source| MapReportError::Score { seq, source })?;
        let coverage = r.alpha.data.iter().filter(|&&a| a >= 0.5).count() as f64 / (w * h).max(1) as f64;
        if let Some(dir) = panels {
            duv_core::io::png_io::write_rgb8(&dir.join(format!("{seq:06}.png")), &render_panel(&v.captured, r, &restored))?;
        }
        out.push(MapViewScore { seq, psnr_db, ssim, coverage, restore_confidence: stats.mean_confidence, restored: restored_score });
    }
    Ok(out)
}

/// The map's figures from its scored views: `metric` the map-to-metric Sim(3) of the outputs
/// (its scale divides the medium's coefficients), `panels` the panel files relative to the run
/// folder, `restored_missing` why no view has a truth.
pub fn map_quality(mapper: &Mapper, per_view: Vec<MapViewScore>, metric: Option<&Sim3>, panels: Vec<String>, restored_missing: Option<String>) -> MapQuality {
    let n = per_view.len().max(1) as f64;
    let newest = mapper.keyframe_count().checked_sub(1).and_then(|s| mapper.keyframe(s)).map_or_else(Se3::identity, |k| k.world_from_cam);
    let mut medium = mapper.medium_summary(&newest);
    let medium_unit = match metric {
        Some(m) => {
            let s = m.scaling();
            medium.beta_d.iter_mut().chain(medium.beta_b.iter_mut()).for_each(|b| *b /= s);
            "1/m".to_string()
        }
        None => "1/map unit".to_string(),
    };
    let restored = summarise_restored(&per_view);
    MapQuality {
        selection: format!(
            "Up to {MAX_SCORED_VIEWS} frames halfway between consecutive keyframes (never optimised on), evenly over the dive, each rendered from its tracked pose; \
             restored: the captured frame with the map's range and medium inverted (transmission gain at most x{:.0}), fused per channel with the map's albedo by their variances, the captured colour where the map does not cover the pixel",
            RestoreConfig::default().max_gain
        ),
        views: per_view.len(),
        psnr_mean_db: per_view.iter().map(|v| v.psnr_db).sum::<f64>() / n,
        ssim_mean: per_view.iter().map(|v| v.ssim).sum::<f64>() / n,
        ssim_convention: SsimConvention::Skimage,
        lpips_mean: None,
        lpips_missing: Some(LPIPS_MISSING.to_string()),
        coverage: per_view.iter().map(|v| v.coverage).sum::<f64>() / n,
        views_covered: per_view.iter().filter(|v| v.coverage >= 0.5).count() as f64 / n,
        restored_missing: if restored.is_none() { restored_missing.or_else(|| Some("the source does not know the water-free view".into())) } else { None },
        restored,
        medium,
        medium_unit,
        gaussians: mapper.gaussians().len(),
        max_gaussians: mapper.capacity().max_gaussians,
        iterations: mapper.iteration(),
        keyframes: mapper.keyframe_count(),
        per_view,
        panels,
    }
}

/// The map report of a finished run in `out`: the held-out frames ([`pick_heldout`] over
/// `frames`, `(seq, world_from_cam)` in the map's frame, sorted by seq, and the mapped
/// `keyframe_seqs`), read again from `source` or else from the run's own log (`out/log`),
/// scored, their panels and `out/map/report.{json,md}` written. `Ok(None)`: the run kept no map.
#[allow(clippy::too_many_arguments)]
pub fn score_run_map(
    map: &mut dyn crate::MapStage,
    source: &crate::source::Source,
    out: &Path,
    frames: &[(u64, Se3)],
    keyframe_seqs: &BTreeSet<u64>,
    camera: &PinholeCamera,
    metric: Option<&Sim3>,
) -> Result<Option<MapQuality>, MapReportError> {
    let Some((mapper, restore)) = map.mapper_mut() else { return Ok(None) };
    let picked = pick_heldout(frames, keyframe_seqs, MAX_SCORED_VIEWS);
    let mut views = Vec::with_capacity(picked.len());
    let mut from_log: Vec<(u64, Se3)> = Vec::new();
    for &(seq, world_from_cam) in &picked {
        match source.frame_again(seq) {
            Some((captured, clear)) => views.push(ScoreView { seq, world_from_cam, captured, clear }),
            None => from_log.push((seq, world_from_cam)),
        }
    }
    if !from_log.is_empty() {
        use duv_core::source::FrameSource as _;
        let log = out.join("log");
        let mut replay = duv_log::replay::McapSource::open(&log, duv_log::ReadLimits::default()).map_err(|e| MapReportError::Log(format!("{}: {e}", log.display())))?;
        while let Some(f) = replay.next_frame().map_err(|e| MapReportError::Log(format!("{}: {e}", log.display())))? {
            if let Some(&(seq, world_from_cam)) = from_log.iter().find(|v| v.0 == f.seq) {
                views.push(ScoreView { seq, world_from_cam, captured: f.image.to_rgb8(), clear: None });
                if views.len() == picked.len() {
                    break;
                }
            }
        }
    }
    views.sort_by_key(|v| v.seq);
    let dir = out.join("map");
    std::fs::create_dir_all(&dir).map_err(|source| MapReportError::CreateDir { path: dir.clone(), source })?;
    let scores = score_views(mapper, camera, &views, &restore, Some(&dir))?;
    let panels = scores.iter().map(|s| format!("map/{:06}.png", s.seq)).collect();
    let missing = (!from_log.is_empty()).then(|| "the source does not know the water-free view (a `sim:` source or a generated dataset folder with `clear/` does)".to_string());
    let q = map_quality(mapper, scores, metric, panels, missing);
    write_map_quality(out, &q)?;
    Ok(Some(q))
}

/// Writes `dir/map/report.json` and `dir/map/report.md`.
pub fn write_map_quality(dir: &Path, q: &MapQuality) -> Result<(), MapReportError> {
    let map_dir = dir.join("map");
    std::fs::create_dir_all(&map_dir).map_err(|source| MapReportError::CreateDir { path: map_dir.clone(), source })?;
    duv_core::io::write_atomic(&map_dir.join("report.json"), serde_json::to_string_pretty(q)?.as_bytes())?;
    let md = format!("# Map report\n{}", q.markdown().replace("](map/", "]("));
    duv_core::io::write_atomic(&map_dir.join("report.md"), md.as_bytes())?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn held_out_frames_lie_between_keyframes_and_are_bounded() {
        let frames: Vec<(u64, Se3)> = (0..100).map(|s| (s, Se3::identity())).collect();
        let kfs: BTreeSet<u64> = [0, 4, 5, 10, 30].into_iter().collect();
        let picked: Vec<u64> = pick_heldout(&frames, &kfs, 8).iter().map(|f| f.0).collect();
        assert_eq!(picked, vec![2, 7, 20]);
        let many: BTreeSet<u64> = (0..100).step_by(4).collect();
        let picked: Vec<u64> = pick_heldout(&frames, &many, 8).iter().map(|f| f.0).collect();
        assert_eq!(picked.len(), 8);
        assert!(picked.iter().all(|s| s % 4 == 2), "{picked:?}");
        assert!(picked[0] < 12 && *picked.last().unwrap() > 84, "spread over the dive: {picked:?}");
    }
}
