//! The mapping stage as the pipeline drives it: keyframes in (image, `world_from_cam`, inverse
//! depth, variance, the plain [`Keyframe`] of `core/`), a bounded optimisation after each one,
//! and the exports.
//!
//! * [`MappingStage::on_keyframe`] stores the keyframe in the [`Mapper`] (seeding Gaussians
//!   from its confident depth) and then optimises for [`MappingBudget::iterations_per_keyframe`]
//!   iterations or until [`MappingBudget::millis_per_keyframe`] has passed, whichever comes
//!   first: the onboard mapping thread calls it once per keyframe it pops from the
//!   tracking -> mapping queue, so the time budget bounds how far mapping can fall behind.
//! * [`MappingStage::optimise`] runs more iterations (the idle time of the mapping thread, or the
//!   end of a run); [`MappingStage::set_keyframe_pose`] takes a corrected pose from tracking
//!   (after a loop closure or a global BA).
//! * [`MappingStage::export`] writes `map.ply` (3DGS layout), `map.ckpt` (the full mapper
//!   checkpoint), `medium.json` (the medium along the newest keyframe's optical axis, the
//!   generator's keys `beta_D`, `beta_B`, `B_inf`) and `renders/NNNNNN.png`, one panel per
//!   stored keyframe: input | render | restored | depth | uncertainty, labelled (the restored
//!   view is the keyframe's image restored with the map's range and medium, [`crate::restore`]).
//!
//! Every buffer is sized by [`MapperCapacity`], which [`MapperCapacity::from_board`] takes from
//! the board (`max_gaussians`, `max_keyframes`) and the camera.

use std::path::Path;
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};

use super::checkpoint::CheckpointError;
use super::mapper::{IterationReport, Mapper, MapperCapacity, MapperConfig, MapperError};
use super::ply::write_ply_in;
use super::render::RenderOutput;
use duv_core::config::Board;
use duv_core::{ImageRgb8, ImageRgbF32, Keyframe, MediumParams, PlaneF32, Se3};
use duv_core::io::png_io::write_rgb8;
use duv_core::io::{write_atomic, IoError};

/// Why the mapping stage failed.
#[derive(Debug, thiserror::Error)]
pub enum StageError {
    #[error("mapper: {0}")]
    Mapper(#[from] MapperError),
    #[error("checkpoint: {0}")]
    Checkpoint(#[from] CheckpointError),
    #[error("{0}")]
    Io(#[from] IoError),
    #[error("creating {path}: {source}")]
    CreateDir { path: String, source: std::io::Error },
    #[error("medium.json: {0}")]
    Json(String),
    #[error(transparent)]
    Restore(#[from] crate::restore::RestoreError),
    #[error("mapping budget: {field} = {value} {why}")]
    InvalidBudget { field: &'static str, value: f64, why: &'static str },
}

/// How much optimisation each keyframe buys. Defaults live in [`MappingBudget::default`].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MappingBudget {
    /// Iterations after each new keyframe (at most).
    pub iterations_per_keyframe: u64,
    /// Wall-time limit of the optimisation after each keyframe, ms; 0 = no limit.
    pub millis_per_keyframe: u64,
}

impl Default for MappingBudget {
    fn default() -> Self {
        MappingBudget { iterations_per_keyframe: 30, millis_per_keyframe: 0 }
    }
}

/// What one call of [`MappingStage::on_keyframe`] or [`MappingStage::optimise`] did.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct MappingStep {
    /// Gaussians seeded from the new keyframe (0 for `optimise`).
    pub added: usize,
    /// Iterations run.
    pub iterations: u64,
    /// The last iteration's report, if any ran.
    pub last: Option<IterationReport>,
    /// Wall time of the call.
    pub elapsed: Duration,
}

impl MapperCapacity {
    /// The board's caps (`budgets.max_gaussians`, `budgets.map_keyframes`) for keyframes of
    /// `width x height` pixels.
    pub fn from_board(board: &Board, width: usize, height: usize) -> Self {
        MapperCapacity { max_gaussians: board.budgets.max_gaussians as usize, max_keyframes: board.budgets.map_keyframes as usize, width, height }
    }
}

/// The mapping stage: a [`Mapper`] with a per-keyframe budget and the exports.
pub struct MappingStage {
    mapper: Mapper,
    budget: MappingBudget,
    /// (iteration, Gaussians) after every keyframe and every `optimise` call, capacity fixed.
    history: Vec<(u64, usize)>,
    history_cap: usize,
    /// How the restored panels of `renders/` trust the map.
    restore: crate::restore::RestoreConfig,
}

impl MappingStage {
    /// An empty map sized by `capacity`.
    pub fn new(config: MapperConfig, capacity: MapperCapacity, budget: MappingBudget) -> Result<Self, StageError> {
        if budget.iterations_per_keyframe > 1_000_000 {
            return Err(StageError::InvalidBudget { field: "iterations_per_keyframe", value: budget.iterations_per_keyframe as f64, why: "must be at most 1e6" });
        }
        let mapper = Mapper::new(config, capacity)?;
        // One entry per keyframe and per optimise call: 4 per keyframe of capacity is plenty;
        // past it the history keeps every other entry.
        let history_cap = 4 * capacity.max_keyframes.max(16);
        Ok(MappingStage { mapper, budget, history: Vec::with_capacity(history_cap), history_cap, restore: crate::restore::RestoreConfig::default() })
    }

    /// A stage restored from a map checkpoint (`map.ckpt`).
    pub fn from_checkpoint(path: &Path, budget: MappingBudget) -> Result<Self, StageError> {
        let mapper = Mapper::load_checkpoint(path)?;
        let history_cap = 4 * mapper.capacity().max_keyframes.max(16);
        Ok(MappingStage { mapper, budget, history: Vec::with_capacity(history_cap), history_cap, restore: crate::restore::RestoreConfig::default() })
    }

    pub fn mapper(&self) -> &Mapper {
        &self.mapper
    }
    pub fn mapper_mut(&mut self) -> &mut Mapper {
        &mut self.mapper
    }
    /// The restoration of the `renders/` panels (and of the run's map report).
    pub fn restore_config(&self) -> crate::restore::RestoreConfig {
        self.restore
    }
    pub fn budget(&self) -> MappingBudget {
        self.budget
    }
    /// (iteration, Gaussian count) after each keyframe and each `optimise` call.
    pub fn gaussians_over_time(&self) -> &[(u64, usize)] {
        &self.history
    }

    fn record(&mut self) {
        if self.history.len() == self.history_cap {
            // Halve the resolution instead of growing.
            let mut k = 0;
            for i in (0..self.history.len()).step_by(2) {
                self.history[k] = self.history[i];
                k += 1;
            }
            self.history.truncate(k);
        }
        self.history.push((self.mapper.iteration(), self.mapper.gaussians().len()));
    }

    /// Takes a keyframe from tracking and optimises within the budget.
    pub fn on_keyframe(&mut self, keyframe: impl std::borrow::Borrow<Keyframe>) -> Result<MappingStep, StageError> {
        let keyframe: &Keyframe = keyframe.borrow();
        let _span = tracing::debug_span!("map.keyframe", index = keyframe.index).entered();
        let start = Instant::now();
        let added = self.mapper.add_keyframe(keyframe)?;
        let limit = (self.budget.millis_per_keyframe > 0).then(|| Duration::from_millis(self.budget.millis_per_keyframe));
        let mut step = self.run(self.budget.iterations_per_keyframe, limit, start)?;
        step.added = added;
        Ok(step)
    }

    /// Runs up to `iterations` more iterations, stopping early after `time_limit`.
    pub fn optimise(&mut self, iterations: u64, time_limit: Option<Duration>) -> Result<MappingStep, StageError> {
        self.run(iterations, time_limit, Instant::now())
    }

    fn run(&mut self, iterations: u64, limit: Option<Duration>, start: Instant) -> Result<MappingStep, StageError> {
        let mut last = None;
        let mut done = 0;
        while done < iterations {
            if limit.is_some_and(|l| start.elapsed() >= l) {
                break;
            }
            last = Some(self.mapper.iterate()?);
            done += 1;
        }
        self.record();
        Ok(MappingStep { added: 0, iterations: done, last, elapsed: start.elapsed() })
    }

    /// Replaces the pose of stored keyframe `index` (a correction from tracking); false when
    /// no such keyframe is stored.
    pub fn set_keyframe_pose(&mut self, index: u64, world_from_cam: Se3) -> Result<bool, StageError> {
        Ok(self.mapper.set_keyframe_pose(index, world_from_cam)?)
    }

    /// The medium along the optical axis of the newest keyframe (identity pose without one).
    pub fn medium_summary(&self) -> MediumParams {
        let n = self.mapper.keyframe_count();
        let pose = n.checked_sub(1).and_then(|s| self.mapper.keyframe(s)).map_or_else(Se3::identity, |k| k.world_from_cam);
        self.mapper.medium_summary(&pose)
    }

    /// Writes `map.ply`, `map.ckpt`, `medium.json` and `renders/` into `dir` (created).
    pub fn export(&mut self, dir: &Path) -> Result<(), StageError> {
        self.export_with(dir, true)
    }

    /// [`Self::export`], the keyframe renders only when `renders` (a stopped run leaves them
    /// out: rendering every keyframe takes seconds on a CPU).
    pub fn export_with(&mut self, dir: &Path, with_renders: bool) -> Result<(), StageError> {
        self.export_in(dir, with_renders, None)
    }

    /// [`Self::export_with`] with `map.ply` and `medium.json` in the frame and unit of
    /// `to_from_map` (e.g. metres from the navigation sensors): the Gaussians moved
    /// ([`crate::ply::transform_gaussian`]), the medium's coefficients (per unit length) divided
    /// by its scale. `map.ckpt` stays in the map's own frame (it is the mapper's state).
    pub fn export_in(&mut self, dir: &Path, with_renders: bool, to_from_map: Option<&duv_core::Sim3>) -> Result<(), StageError> {
        let _span = tracing::debug_span!("map.export").entered();
        // The device map's values (Vulkan) come to the host first.
        self.mapper.sync_from_device()?;
        write_ply_in(&dir.join("map.ply"), self.mapper.gaussians(), to_from_map)?;
        self.mapper.save_checkpoint(&dir.join("map.ckpt"))?;
        let mut medium = self.medium_summary();
        if let Some(a) = to_from_map {
            let s = a.scaling();
            medium.beta_d.iter_mut().chain(medium.beta_b.iter_mut()).for_each(|b| *b /= s);
        }
        let json = serde_json::to_string_pretty(&medium).map_err(|e| StageError::Json(e.to_string()))?;
        write_atomic(&dir.join("medium.json"), json.as_bytes())?;
        if !with_renders {
            return Ok(());
        }
        let renders = dir.join("renders");
        std::fs::create_dir_all(&renders).map_err(|source| StageError::CreateDir { path: renders.display().to_string(), source })?;
        let cap = self.mapper.capacity();
        let mut restored = ImageRgbF32::new(cap.width, cap.height);
        for slot in 0..self.mapper.keyframe_count() {
            let Some(kf) = self.mapper.keyframe(slot) else { continue };
            let (index, image, camera) = (kf.index, kf.image.clone(), kf.camera);
            let captured = image.to_rgb_f32();
            self.mapper.render_keyframe(slot)?;
            self.mapper.restore_last(&captured, &camera, &self.restore, &mut restored)?;
            write_rgb8(&renders.join(format!("{index:06}.png")), &render_panel(&image, self.mapper.last_render(), &restored))?;
        }
        Ok(())
    }
}

/// A grey image of `plane` scaled to its range over the pixels where `valid > 0.5` (black
/// elsewhere).
pub fn gray_panel(plane: &PlaneF32, valid: &PlaneF32) -> ImageRgb8 {
    let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
    for (&v, &a) in plane.data.iter().zip(&valid.data) {
        if a > 0.5 && v.is_finite() {
            lo = lo.min(v);
            hi = hi.max(v);
        }
    }
    let span = if hi > lo { hi - lo } else { 1.0 };
    let mut out = ImageRgb8::new(plane.width, plane.height);
    for (i, (&v, &a)) in plane.data.iter().zip(&valid.data).enumerate() {
        let g = if a > 0.5 && lo.is_finite() && v.is_finite() { (((v - lo) / span).clamp(0.0, 1.0) * 255.0).round() as u8 } else { 0 };
        out.data[i * 3..i * 3 + 3].fill(g);
    }
    out
}

/// Images of the same size side by side.
pub fn hconcat(panels: &[&ImageRgb8]) -> ImageRgb8 {
    let (w, h) = (panels[0].width, panels[0].height);
    let mut out = ImageRgb8::new(w * panels.len(), h);
    for (k, p) in panels.iter().enumerate() {
        for y in 0..h {
            let dst = (y * out.width + k * w) * 3;
            out.data[dst..dst + w * 3].copy_from_slice(p.row(y));
        }
    }
    out
}

/// The labels over the five parts of a [`render_panel`].
pub const PANEL_LABELS: [&str; 5] = ["input", "render", "restored", "depth", "uncertainty"];

/// The render panel of a view: input | render | restored | depth | uncertainty (the rendered
/// depth's standard deviation), each labelled above ([`PANEL_LABELS`]); depth and uncertainty
/// scaled to their range where the map covers the pixel. `restored` is the water-free view
/// (`Mapper::restore_last`).
pub fn render_panel(input: &ImageRgb8, out: &RenderOutput, restored: &ImageRgbF32) -> ImageRgb8 {
    let std = PlaneF32 { width: out.depth_var.width, height: out.depth_var.height, data: out.depth_var.data.iter().map(|v| v.max(0.0).sqrt()).collect() };
    let row = hconcat(&[input, &out.colour.to_rgb8(), &restored.to_rgb8(), &gray_panel(&out.depth, &out.alpha), &gray_panel(&std, &out.alpha)]);
    with_labels(&row, input.width, &PANEL_LABELS)
}

/// 5x7 glyphs of the letters the panel labels use (rows top to bottom, bit 4 the left column).
const GLYPHS: [(char, [u8; 7]); 14] = [
    ('a', [0b00000, 0b00000, 0b01110, 0b00001, 0b01111, 0b10001, 0b01111]),
    ('c', [0b00000, 0b00000, 0b01110, 0b10000, 0b10000, 0b10001, 0b01110]),
    ('d', [0b00001, 0b00001, 0b01101, 0b10011, 0b10001, 0b10011, 0b01101]),
    ('e', [0b00000, 0b00000, 0b01110, 0b10001, 0b11111, 0b10000, 0b01110]),
    ('h', [0b10000, 0b10000, 0b10110, 0b11001, 0b10001, 0b10001, 0b10001]),
    ('i', [0b00100, 0b00000, 0b01100, 0b00100, 0b00100, 0b00100, 0b01110]),
    ('n', [0b00000, 0b00000, 0b10110, 0b11001, 0b10001, 0b10001, 0b10001]),
    ('o', [0b00000, 0b00000, 0b01110, 0b10001, 0b10001, 0b10001, 0b01110]),
    ('p', [0b00000, 0b00000, 0b11110, 0b10001, 0b11110, 0b10000, 0b10000]),
    ('r', [0b00000, 0b00000, 0b10110, 0b11001, 0b10000, 0b10000, 0b10000]),
    ('s', [0b00000, 0b00000, 0b01111, 0b10000, 0b01110, 0b00001, 0b11110]),
    ('t', [0b01000, 0b01000, 0b11100, 0b01000, 0b01000, 0b01001, 0b00110]),
    ('u', [0b00000, 0b00000, 0b10001, 0b10001, 0b10001, 0b10011, 0b01101]),
    ('y', [0b00000, 0b00000, 0b10001, 0b10001, 0b01111, 0b00001, 0b01110]),
];

fn label_scale(part_width: usize) -> usize {
    if part_width >= 240 {
        2
    } else {
        1
    }
}

/// Rows of the label strip [`with_labels`] puts over parts `part_width` wide (readers of a
/// panel find the images below it).
pub fn label_strip_height(part_width: usize) -> usize {
    7 * label_scale(part_width) + 4
}

/// `row` (parts `part_width` wide) under a black strip with `labels[k]` in white over part `k`
/// (glyphs scaled by 2 where a part is at least 240 pixels wide; letters without a glyph are
/// left blank).
pub fn with_labels(row: &ImageRgb8, part_width: usize, labels: &[&str]) -> ImageRgb8 {
    let scale = label_scale(part_width);
    let strip = label_strip_height(part_width);
    let mut out = ImageRgb8::new(row.width, row.height + strip);
    out.data[strip * row.width * 3..].copy_from_slice(&row.data);
    for (k, label) in labels.iter().enumerate() {
        let mut x0 = k * part_width + 2;
        for ch in label.chars() {
            if let Some((_, rows)) = GLYPHS.iter().find(|g| g.0 == ch) {
                for (gy, bits) in rows.iter().enumerate() {
                    for gx in 0..5 {
                        if bits & (0b10000 >> gx) == 0 {
                            continue;
                        }
                        for (sy, sx) in (0..scale).flat_map(|a| (0..scale).map(move |b| (a, b))) {
                            let (x, y) = (x0 + gx * scale + sx, 2 + gy * scale + sy);
                            if x < (k + 1) * part_width && x < out.width {
                                out.data[(y * out.width + x) * 3..][..3].fill(255);
                            }
                        }
                    }
                }
            }
            x0 += 6 * scale;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn panels_are_labelled_above_the_images() {
        let row = ImageRgb8 { width: 2 * 100, height: 10, data: vec![40; 2 * 100 * 10 * 3] };
        let out = with_labels(&row, 100, &["input", "restored"]);
        assert_eq!((out.width, out.height), (200, 10 + 11));
        assert_eq!(&out.data[11 * 200 * 3..], &row.data[..], "the images are kept below the strip");
        let white_in = |x0: usize, x1: usize| (0..11).flat_map(|y| (x0..x1).map(move |x| (y, x))).filter(|&(y, x)| out.data[(y * 200 + x) * 3] == 255).count();
        // "input": i n p u t; "restored": 8 glyphs; every glyph has set pixels; none past a part.
        assert!(white_in(0, 100) > 5 * 8 && white_in(100, 200) > 8 * 8, "{} {}", white_in(0, 100), white_in(100, 200));
        assert_eq!(white_in(2 + 5 * 6, 100), 0, "nothing after the fifth letter of the first label");
    }

    #[test]
    fn history_stays_within_its_capacity() {
        let cap = MapperCapacity { max_gaussians: 10, max_keyframes: 1, width: 8, height: 8 };
        let mut s = MappingStage::new(MapperConfig::default(), cap, MappingBudget::default()).unwrap();
        for _ in 0..200 {
            s.record();
        }
        assert!(s.history.len() <= s.history_cap && s.history.capacity() == s.history_cap);
        assert!(matches!(
            MappingStage::new(MapperConfig::default(), cap, MappingBudget { iterations_per_keyframe: 2_000_000, ..MappingBudget::default() }),
            Err(StageError::InvalidBudget { .. })
        ));
    }
}
