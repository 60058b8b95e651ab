//! The damped Gauss-Newton (Levenberg-Marquardt) loop over the window.

use super::linearize::{linearize, window_cost};
use super::schur::solve_step;
use super::workspace::BaWorkspace;
use super::{BaConfig, BaError};
use duv_core::pose::se3_exp;
use nalgebra::Vector6;

/// After a rejected step the damping becomes at least this (so a zero initial damping still
/// escapes a bad step).
pub(crate) const MIN_DAMPING_AFTER_REJECT: f64 = 1e-6;
/// Accepted steps shrink the damping down to this floor (or to the initial damping, if lower).
pub(crate) const DAMPING_FLOOR: f64 = 1e-12;

/// Damping after an accepted step.
#[inline]
pub(crate) fn damping_after_accept(lambda: f64, config: &BaConfig) -> f64 {
    (lambda * config.damping_decrease).max(DAMPING_FLOOR.min(config.initial_damping))
}

/// Damping after a rejected step (or a failed factorisation).
#[inline]
pub(crate) fn damping_after_reject(lambda: f64, config: &BaConfig) -> f64 {
    (lambda * config.damping_increase).max(MIN_DAMPING_AFTER_REJECT)
}

/// Why the loop stopped.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Termination {
    /// The step or the relative cost decrease fell below the tolerances.
    Converged,
    /// `max_iterations` steps were tried.
    MaxIterations,
    /// No step lowered the cost before the damping reached `max_damping`.
    DampingLimit,
}

/// Summary of one `solve` call.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BaReport {
    /// Steps computed (accepted or rejected).
    pub iterations: usize,
    /// Steps that lowered the cost.
    pub accepted: usize,
    pub initial_cost: f64,
    pub final_cost: f64,
    /// Damping lambda at the end.
    pub final_damping: f64,
    pub termination: Termination,
}

impl BaWorkspace {
    /// Runs damped Gauss-Newton on the loaded window: updates the free poses and every
    /// inverse depth in place. Allocation-free (the `track.ba` span allocates nothing unless
    /// a subscriber that records spans is installed).
    pub fn solve(&mut self, config: &BaConfig) -> Result<BaReport, BaError> {
        let _span = tracing::debug_span!("track.ba", keyframes = self.win.n_keyframes, edges = self.win.n_edges).entered();
        self.prepare(config)?;
        let mut cost = self.linearize_current(config);
        let initial_cost = cost;
        let mut lambda = config.initial_damping;
        let mut report = BaReport { iterations: 0, accepted: 0, initial_cost, final_cost: cost, final_damping: lambda, termination: Termination::MaxIterations };
        while report.iterations < config.max_iterations {
            report.iterations += 1;
            cost = self.linearize_current(config);
            match self.compute_step_unchecked(config, lambda) {
                Ok(()) => {}
                Err(BaError::SingularSystem { .. }) if damping_after_reject(lambda, config) <= config.max_damping => {
                    lambda = damping_after_reject(lambda, config);
                    continue;
                }
                Err(e) => return Err(e),
            }
            if self.step_is_small(config) {
                report.termination = Termination::Converged;
                break;
            }
            self.apply_step_to_trial(config);
            let trial_cost = window_cost(&self.win, &self.trial.world_from_cam, &self.trial.inv_depth, config);
            tracing::trace!(iteration = report.iterations, cost, trial_cost, lambda, "ba step");
            if trial_cost.is_finite() && trial_cost < cost {
                let n_kf = self.win.n_keyframes;
                let n_depth = n_kf * self.win.n_pixels;
                self.win.world_from_cam[..n_kf].copy_from_slice(&self.trial.world_from_cam[..n_kf]);
                self.win.inv_depth[..n_depth].copy_from_slice(&self.trial.inv_depth[..n_depth]);
                self.invalidate();
                report.accepted += 1;
                let decrease = (cost - trial_cost) / cost.max(f64::MIN_POSITIVE);
                cost = trial_cost;
                lambda = damping_after_accept(lambda, config);
                if decrease < config.cost_tolerance {
                    report.termination = Termination::Converged;
                    break;
                }
            } else {
                lambda = damping_after_reject(lambda, config);
                if lambda > config.max_damping {
                    report.termination = Termination::DampingLimit;
                    break;
                }
            }
        }
        report.final_cost = cost;
        report.final_damping = lambda;
        tracing::debug!(iterations = report.iterations, accepted = report.accepted, initial_cost, final_cost = cost, "ba done");
        Ok(report)
    }

    /// Builds the undamped normal equations at the current state (a no-op when they are
    /// current for this config) and returns the cost there. Exposed for diagnostics and tests.
    pub fn linearize(&mut self, config: &BaConfig) -> Result<f64, BaError> {
        self.prepare(config)?;
        Ok(self.linearize_current(config))
    }

    /// Computes one damped step (`H_ii <- H_ii (1 + damping)`) from the current
    /// linearisation without applying it; read it with [`step_pose`](Self::step_pose) and
    /// [`step_inv_depth`](Self::step_inv_depth).
    pub fn compute_step(&mut self, config: &BaConfig, damping: f64) -> Result<(), BaError> {
        if !(damping.is_finite() && damping >= 0.0) {
            return Err(BaError::InvalidConfig { field: "damping", value: damping, why: "must be finite and >= 0" });
        }
        self.prepare(config)?;
        self.linearize_current(config);
        self.compute_step_unchecked(config, damping)
    }

    pub(crate) fn linearize_current(&mut self, config: &BaConfig) -> f64 {
        match self.linearized {
            Some((c, cost)) if c == *config => cost,
            _ => {
                let cost = linearize(&self.win, &self.st, config, &mut self.sys);
                self.linearized = Some((*config, cost));
                self.step_valid = false;
                self.cov.valid = false;
                cost
            }
        }
    }

    fn compute_step_unchecked(&mut self, config: &BaConfig, lambda: f64) -> Result<(), BaError> {
        self.step_valid = false;
        solve_step(&self.win, &self.st, &self.sys, lambda, config.min_depth_hessian, &mut self.red)?;
        self.step_valid = true;
        Ok(())
    }

    fn step_is_small(&self, config: &BaConfig) -> bool {
        let tol = config.step_tolerance;
        let dim = 6 * self.st.n_free;
        let n_depth = self.win.n_keyframes * self.win.n_pixels;
        self.red.step_pose[..dim].iter().all(|v| v.abs() < tol)
            && self.red.step_inv_depth[..n_depth].iter().zip(&self.win.inv_depth[..n_depth]).all(|(dd, d)| dd.abs() < tol * d)
    }

    fn apply_step_to_trial(&mut self, config: &BaConfig) {
        let n_kf = self.win.n_keyframes;
        for k in 0..n_kf {
            self.trial.world_from_cam[k] = match self.st.free_index(k) {
                Some(f) => {
                    let xi = Vector6::from_column_slice(&self.red.step_pose[6 * f..6 * f + 6]);
                    let mut pose = self.win.world_from_cam[k] * se3_exp(&xi);
                    pose.rotation.renormalize();
                    pose
                }
                None => self.win.world_from_cam[k],
            };
        }
        let n_depth = n_kf * self.win.n_pixels;
        for ((t, d), dd) in self.trial.inv_depth[..n_depth].iter_mut().zip(&self.win.inv_depth[..n_depth]).zip(&self.red.step_inv_depth[..n_depth]) {
            *t = (d + dd).max(config.min_inv_depth);
        }
    }
}
