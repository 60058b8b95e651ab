//! The mapper (`map::stage::MappingStage`; it renders on the Vulkan kernels or the CPU reference, see
//! [`GaussianMapping::use_device`]) bound to the pipeline's mapping thread through [`MapStage`].
//!
//! - A keyframe from tracking is written into the run's keyframe folder (`keyframes/NNNNNN.png`,
//!   `_invdepth.pfm`, `_variance.pfm`, the layout `duv refine --keyframes` reads; its one writer
//!   is [`KeyframeFolder`]) and handed to the stage, which optimises within its per-keyframe
//!   budget.
//! - While no keyframe waits, `step` runs one more iteration, at most `idle_iterations` after
//!   each keyframe (so a deterministic run, which steps until idle, ends).
//! - Checkpoints are the mapper's own checkpoint bytes (Gaussians, medium weights, Adam moments,
//!   keyframes): the file for resume embeds the keyframes' pixels, the logged one refers to
//!   the keyframes' own log messages; `restore` rebuilds the stage from the file.
//! - `finish` sets the final keyframe poses, optimises `final_iterations` more and exports
//!   `map.ply`, `map.ckpt`, `medium.json` and `renders/`.

use super::keyframe_folder::KeyframeFolder;
use super::{MapCheckpoint, MapStage, MapStageError};
use duv_core::{Keyframe, Se3, Sim3};
use duv_map::GpuOptions;
use duv_map::checkpoint::KeyframePixels;
use duv_map::stage::{MappingBudget, MappingStage};
use duv_map::backend::MapperDevice;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// The Gaussian-splat map as the pipeline's mapping stage: duv-map's [`MappingStage`] (the
/// mapper with its budget) behind [`MapStage`] (the pipeline's seam; [`super::NoMapping`] is
/// the other side of it), with the keyframe folder, the checkpoint scratch and idle iterations.
pub struct GaussianMapping {
    stage: MappingStage,
    budget: MappingBudget,
    keyframe_folder: KeyframeFolder,
    scratch: PathBuf,
    idle_iterations: u64,
    idle_left: u64,
    final_iterations: u64,
    fed: usize,
    dirty: bool,
    time: Duration,
    /// The renderer asked for, applied again to a stage rebuilt by `restore`.
    device: Option<(MapperDevice, GpuOptions)>,
    /// Keyframe folder writes that failed (reported once).
    folder_failures: u64,
    /// The frame the exports are written in ([`MapStage::set_output_frame`]).
    output_frame: Option<Sim3>,
    /// Time and count of checkpoints made (the map's bytes) and written to disk, and of
    /// keyframe folder writes: the mapping thread's work beside the mapper's own
    /// ([`duv_map::mapper::MapperTimes`]).
    checkpoint_made: (Duration, u64),
    checkpoint_written: (Duration, u64),
    folder_written: Duration,
}

impl GaussianMapping {
    /// `keyframe_folder` receives every keyframe handed over; `scratch` is a file path the
    /// checkpoint bytes pass through.
    pub fn new(stage: MappingStage, keyframe_folder: KeyframeFolder, scratch: PathBuf, idle_iterations: u64, final_iterations: u64) -> Self {
        let budget = stage.budget();
        GaussianMapping { stage, budget, keyframe_folder, scratch, idle_iterations, idle_left: 0, final_iterations, fed: 0, dirty: false, time: Duration::ZERO, device: None, folder_failures: 0, output_frame: None, checkpoint_made: (Duration::ZERO, 0), checkpoint_written: (Duration::ZERO, 0), folder_written: Duration::ZERO }
    }

    /// Renders with `device` from now on, also after a `restore` (see
    /// [`duv_map::mapper::Mapper::use_device`]); the renderer in use, one line.
    pub fn use_device(&mut self, device: MapperDevice, gpu: GpuOptions) -> Result<String, MapStageError> {
        let what = self.stage.mapper_mut().use_device(device, &gpu)?;
        self.device = Some((device, gpu));
        Ok(what)
    }

    pub fn stage(&self) -> &MappingStage {
        &self.stage
    }

    /// The checkpoint's bytes and the map's points for the log and the live view.
    fn checkpoint_untimed(&mut self) -> Option<MapCheckpoint> {
        let mapper = self.stage.mapper_mut();
        // Straight from the mapper's buffers, each into one buffer of its exact size.
        let made = mapper.checkpoint_bytes_with(KeyframePixels::Embedded).and_then(|file| Ok((file, mapper.checkpoint_bytes_with(KeyframePixels::Referenced)?)));
        let (file, logged) = match made {
            Ok(b) => b,
            Err(e) => {
                tracing::warn!("map checkpoint not made: {e}");
                return None;
            }
        };
        let g = mapper.gaussians();
        let centres_in_world = (0..g.len()).map(|i| g.get(i).mean).collect();
        // The degree-0 colour (what the live view shows), as the renderer takes it.
        let c0 = duv_map::gaussians::SH_C0 as f32;
        let colours = (0..g.len()).map(|i| g.get(i).f_dc.map(|f| ((0.5 + c0 * f).clamp(0.0, 1.0) * 255.0).round() as u8)).collect();
        Some(MapCheckpoint { file, logged, centres_in_world, colours })
    }

    /// Keyframes handed over so far.
    pub fn keyframes_fed(&self) -> usize {
        self.fed
    }
}

impl MapStage for GaussianMapping {
    fn add_keyframe(&mut self, kf: &Keyframe) -> Result<(), MapStageError> {
        let id = kf.index;
        // The keyframe folder is written as keyframes arrive; a write that fails (a full disk)
        // is reported once and mapping goes on (the keyframes are in the log).
        let t_folder = Instant::now();
        let written = self.keyframe_folder.write_keyframe(kf);
        self.folder_written += t_folder.elapsed();
        if let Err(e) = written {
            self.folder_failures += 1;
            if self.folder_failures == 1 {
                tracing::error!("keyframe folder not written: {e}; mapping goes on");
            }
        }
        let t0 = Instant::now();
        self.stage.on_keyframe(kf).map_err(|source| MapStageError::Keyframe { id, source })?;
        self.time += t0.elapsed();
        self.fed += 1;
        self.idle_left = self.idle_iterations;
        self.dirty = true;
        Ok(())
    }

    fn step(&mut self) -> Result<bool, MapStageError> {
        if self.idle_left == 0 || self.fed == 0 {
            return Ok(false);
        }
        let t0 = Instant::now();
        self.stage.optimise(1, None)?;
        self.time += t0.elapsed();
        self.idle_left -= 1;
        self.dirty = true;
        Ok(true)
    }

    fn final_checkpoint(&mut self) -> Option<MapCheckpoint> {
        self.dirty |= self.fed > 0;
        self.checkpoint()
    }

    fn checkpoint(&mut self) -> Option<MapCheckpoint> {
        if !std::mem::take(&mut self.dirty) {
            return None;
        }
        let t0 = Instant::now();
        let made = self.checkpoint_untimed();
        self.checkpoint_made.0 += t0.elapsed();
        self.checkpoint_made.1 += made.is_some() as u64;
        made
    }

    fn checkpoint_written(&mut self, took: Duration) {
        self.checkpoint_written.0 += took;
        self.checkpoint_written.1 += 1;
    }

    fn newest_keyframe(&self) -> Option<u64> {
        let m = self.stage.mapper();
        (0..m.keyframe_count()).filter_map(|slot| m.keyframe(slot).map(|k| k.index)).max()
    }

    fn restore(&mut self, bytes: &[u8]) -> Result<(), MapStageError> {
        duv_core::io::write_atomic(&self.scratch, bytes)?;
        // The old stage (and its GPU memory) goes before the restored one opens the device.
        self.stage = MappingStage::from_checkpoint(&self.scratch, self.budget)?;
        if let Some((device, gpu)) = &self.device {
            self.stage.mapper_mut().use_device(*device, gpu)?;
        }
        self.fed = self.stage.mapper().keyframe_count();
        Ok(())
    }

    fn gaussians(&self) -> Option<usize> {
        Some(self.stage.mapper().gaussians().len())
    }

    fn mapper_mut(&mut self) -> Option<(&mut duv_map::mapper::Mapper, duv_map::restore::RestoreConfig)> {
        (self.fed > 0).then(|| {
            let restore = self.stage.restore_config();
            (self.stage.mapper_mut(), restore)
        })
    }

    fn set_output_frame(&mut self, to_from_map: Option<Sim3>) {
        self.output_frame = to_from_map;
    }

    fn finish(&mut self, final_poses: &[(u64, Se3)], out: &Path, optimise: bool) -> Result<Option<String>, MapStageError> {
        if self.fed == 0 {
            return Ok(Some("mapped 0 keyframes: no map exported".into()));
        }
        for (id, pose) in final_poses {
            self.stage.set_keyframe_pose(*id, *pose)?;
        }
        // Where the mapping thread's time went before the final optimisation: the run, and the
        // keyframes fed from the log after it (those a full queue deferred).
        let during_run = format!(
            "mapping before the final optimisation: {}; checkpoints made {:.2} s ({}), written {:.2} s ({}); keyframe folder {:.2} s",
            self.stage.mapper().times().summary(),
            self.checkpoint_made.0.as_secs_f64(),
            self.checkpoint_made.1,
            self.checkpoint_written.0.as_secs_f64(),
            self.checkpoint_written.1,
            self.folder_written.as_secs_f64()
        );
        let t0 = Instant::now();
        if optimise {
            self.stage.optimise(self.final_iterations, None)?;
        }
        self.time += t0.elapsed();
        self.stage.export_in(out, optimise, self.output_frame.as_ref()).map_err(|source| MapStageError::Export { path: out.to_path_buf(), source })?;
        let iterations = self.stage.mapper().iteration();
        let mut m = self.stage.medium_summary();
        let unit = match &self.output_frame {
            Some(a) => {
                m.beta_d.iter_mut().chain(m.beta_b.iter_mut()).for_each(|b| *b /= a.scaling());
                "per metre"
            }
            None => "per map unit",
        };
        let f = |v: [f64; 3]| format!("[{:.3} {:.3} {:.3}]", v[0], v[1], v[2]);
        Ok(Some(format!(
            "mapped {} keyframes: {} iterations in {:.2} s ({:.1} ms per iteration), {} Gaussians (cap {}); medium along the last keyframe's axis ({}): beta_D {} beta_B {} B_inf {}",
            self.fed,
            iterations,
            self.time.as_secs_f64(),
            self.time.as_secs_f64() * 1e3 / iterations.max(1) as f64,
            self.stage.mapper().gaussians().len(),
            self.stage.mapper().capacity().max_gaussians,
            unit,
            f(m.beta_d),
            f(m.beta_b),
            f(m.b_inf)
        ) + "\n" + &during_run))
    }
}

/// What [`feed_unmapped_keyframes`] did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Refed {
    pub keyframes: usize,
    /// Why it stopped early (a keyframe the stage refused, an unreadable log).
    pub problem: Option<String>,
}

/// Feeds `map` the keyframes logged in `log_dir` that it does not cover: those after
/// `newest_fed` (a restored checkpoint's newest; `None`: all when the stage holds none) and
/// those whose image `keyframe_folder` does not hold (every keyframe mapping receives is
/// written there; the missing ones were deferred by a full keyframe queue, or came after the
/// newest checkpoint of a stopped run). One keyframe at a time from the log: the map then
/// covers every logged keyframe.
pub fn feed_unmapped_keyframes(map: &mut dyn MapStage, log_dir: &Path, keyframe_folder: &KeyframeFolder, newest_fed: Option<u64>) -> Refed {
    let unmapped = |id: u64| newest_fed.is_none_or(|n| id > n) || !keyframe_folder.has_image(id);
    feed_logged_keyframes(map, log_dir, unmapped)
}

/// Feeds `map` the keyframes logged in `log` (a log folder or one segment) whose id `wanted`
/// accepts, one at a time.
pub fn feed_logged_keyframes(map: &mut dyn MapStage, log: &Path, wanted: impl Fn(u64) -> bool) -> Refed {
    let mut out = Refed::default();
    let read = duv_log::for_each_log_keyframe(log, duv_log::ReadLimits::default(), wanted, |kf| {
        if out.problem.is_none() {
            match map.add_keyframe(&kf) {
                Ok(()) => out.keyframes += 1,
                Err(e) => out.problem = Some(format!("keyframe {}: {e}", kf.index)),
            }
        }
    });
    match read {
        Ok(_) | Err(duv_log::LogError::NoKeyframes { .. }) => {}
        Err(e) => {
            out.problem.get_or_insert(e.to_string());
        }
    }
    out
}
