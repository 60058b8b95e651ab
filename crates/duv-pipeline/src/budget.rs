//! The host-memory plan of a run, from the board: what the queues and the keyframe store need
//! at the configured resolution, checked against `budgets.host_mb` before anything starts.

use super::PipelineError;
use duv_core::config::board::Board;
use serde::Serialize;

/// Bytes the pipeline plans to hold at most, by consumer.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct BudgetPlan {
    pub width: usize,
    pub height: usize,
    /// One RGB frame.
    pub frame_bytes: usize,
    /// One keyframe as handed to the mapper (image, inverse depth, variance at full size).
    pub keyframe_bytes: usize,
    /// Pooled frames beside those the log queue holds: the capture -> tracking queue at
    /// capacity, the keyframes waiting out the BA window, and those in flight
    /// ([`FRAME_SLOTS_IN_FLIGHT`](super::FRAME_SLOTS_IN_FLIGHT)).
    pub frame_queue_bytes: usize,
    /// Pooled keyframes: the tracking -> mapping queue at capacity and those in mapping and
    /// the log ([`KEYFRAME_SLOTS_IN_FLIGHT`](super::KEYFRAME_SLOTS_IN_FLIGHT)).
    pub keyframe_queue_bytes: usize,
    /// The tracker's keyframe store (image pyramid as f32 plus colour, per keyframe).
    pub keyframe_store_bytes: usize,
    /// The mapper's keyframes (`budgets.map_keyframes`: 8-bit and f32 image, inverse depth,
    /// its variance and the masked target variance at full size, per keyframe).
    pub map_keyframe_bytes: usize,
    /// Log queue budget.
    pub log_queue_bytes: usize,
    pub total_bytes: usize,
    pub host_budget_bytes: usize,
}

impl BudgetPlan {
    pub fn headroom_bytes(&self) -> i64 {
        self.host_budget_bytes as i64 - self.total_bytes as i64
    }
}

/// The plan for `width x height` frames on `board`, or an error with the numbers when the
/// board's budgets cannot hold it.
pub fn plan(board: &Board, width: usize, height: usize) -> Result<BudgetPlan, PipelineError> {
    let b = &board.budgets;
    let px = width * height;
    let frame_bytes = px * 3;
    let keyframe_bytes = px * 3 + px * 4 * 2;
    // Grey f32 pyramid (4/3 of the base level) plus the colour image, per stored keyframe.
    let per_stored_keyframe = px * 4 * 4 / 3 + px * 3;
    let per_map_keyframe = px * 3 + px * 4 * 2 + px * 4 * 3 + px * 4;
    let plan = BudgetPlan {
        width,
        height,
        frame_bytes,
        keyframe_bytes,
        frame_queue_bytes: (b.frame_queue as usize + b.ba_window as usize + super::FRAME_SLOTS_IN_FLIGHT) * frame_bytes,
        keyframe_queue_bytes: (b.keyframe_queue as usize + super::KEYFRAME_SLOTS_IN_FLIGHT) * keyframe_bytes,
        keyframe_store_bytes: b.max_keyframes as usize * per_stored_keyframe,
        map_keyframe_bytes: b.map_keyframes as usize * per_map_keyframe,
        log_queue_bytes: b.log_queue_mb as usize * (1 << 20),
        total_bytes: 0,
        host_budget_bytes: b.host_mb as usize * (1 << 20),
    };
    let total = plan.frame_queue_bytes + plan.keyframe_queue_bytes + plan.keyframe_store_bytes + plan.map_keyframe_bytes + plan.log_queue_bytes;
    let plan = BudgetPlan { total_bytes: total, ..plan };
    let mib = |x: usize| x as f64 / (1 << 20) as f64;
    if plan.log_queue_bytes < keyframe_bytes + 2 * frame_bytes {
        return Err(PipelineError::Budget {
            board: board.name.clone(),
            problem: format!(
                "budgets.log_queue_mb = {} cannot hold one {width}x{height} keyframe record ({:.2} MiB) and two frames ({:.2} MiB)",
                b.log_queue_mb,
                mib(keyframe_bytes),
                mib(2 * frame_bytes)
            ),
        });
    }
    if total > plan.host_budget_bytes {
        return Err(PipelineError::Budget {
            board: board.name.clone(),
            problem: format!(
                "{width}x{height} needs {:.1} MiB of host memory but budgets.host_mb = {}: frames (queue, BA window, in flight) {} x {:.2} MiB = {:.1} MiB, keyframes (queue, in flight) {} x {:.2} MiB = {:.1} MiB, keyframe store {} x {:.2} MiB = {:.1} MiB, mapper keyframes {} x {:.2} MiB = {:.1} MiB, log queue {:.1} MiB",
                mib(total),
                b.host_mb,
                b.frame_queue as usize + b.ba_window as usize + super::FRAME_SLOTS_IN_FLIGHT,
                mib(frame_bytes),
                mib(plan.frame_queue_bytes),
                b.keyframe_queue as usize + super::KEYFRAME_SLOTS_IN_FLIGHT,
                mib(keyframe_bytes),
                mib(plan.keyframe_queue_bytes),
                b.max_keyframes,
                mib(per_stored_keyframe),
                mib(plan.keyframe_store_bytes),
                b.map_keyframes,
                mib(per_map_keyframe),
                mib(plan.map_keyframe_bytes),
                mib(plan.log_queue_bytes)
            ),
        });
    }
    Ok(plan)
}
