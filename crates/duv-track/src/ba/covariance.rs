//! State uncertainty (Eq. 4) from the undamped reduced system at the current estimate:
//! `Sigma_P = S^-1` and `var_d(p) = 1/H_dd + (1/H_dd)^2 b^T S^-1 b`, `b = H_pd[:, p]`.
//!
//! These are the blocks of the inverse of the full Hessian
//! `H = [[H_pp, H_pd], [H_dp, H_dd]]`: with `C = H_dd` diagonal and `E = H_pd`
//! (`6 n_free x n_depth`), `(H^-1)_dd = C^-1 + C^-1 E^T S^-1 E C^-1`, whose diagonal entry for
//! pixel `p` is `1/c_p + (1/c_p)^2 e_p^T S^-1 e_p` with `e_p` the *column* `p` of `E` (not a
//! row of `E^T S^-1 E` taken the other way round).
//!
//! These are in the units the flow weights give: with weights that are relative confidences
//! rather than inverse pixel variances, multiply them by the a posteriori variance of unit
//! weight ([`BaWorkspace::unit_variance`]), which the same call computes from the residuals.

use faer::dyn_stack::MemStack;
use faer::linalg::cholesky::llt;
use faer::{MatMut, MatRef, Par};

use super::schur::{factor, reduce};
use super::workspace::BaWorkspace;
use super::{BaConfig, BaError};

impl BaWorkspace {
    /// Computes the pose covariance and every inverse-depth variance at the current estimate
    /// (relinearising only if the state changed since the last linearisation; Huber weights
    /// at the current residuals). Read them with [`pose_covariance`](Self::pose_covariance),
    /// [`pose_cross_covariance`](Self::pose_cross_covariance) and
    /// [`inv_depth_variance`](Self::inv_depth_variance). Allocation-free.
    pub fn compute_covariance(&mut self, config: &BaConfig) -> Result<(), BaError> {
        let _span = tracing::debug_span!("track.ba.covariance").entered();
        self.prepare(config)?;
        self.linearize_current(config);
        self.cov.valid = false;
        let dim = 6 * self.st.n_free;
        reduce(&self.win, &self.st, &self.sys, 0.0, config.min_depth_hessian, &mut self.red);
        factor(&mut self.red, dim).map_err(|pivot| BaError::SingularSystem { dim, pivot, damping: 0.0 })?;
        let sigma = &mut self.cov.pose[..dim * dim];
        if dim > 0 {
            let l = MatRef::from_column_major_slice(&self.red.s[..dim * dim], dim, dim);
            let out = MatMut::from_column_major_slice_mut(&mut *sigma, dim, dim);
            let stack = MemStack::new(&mut self.red.scratch);
            // Writes the lower triangle of S^-1; mirror it.
            llt::inverse::inverse(out, l, Par::Seq, stack);
            for c in 0..dim {
                for r in 0..c {
                    sigma[c * dim + r] = sigma[r * dim + c];
                }
            }
        }
        let n_pix = self.win.n_pixels;
        for k in 0..self.win.n_keyframes {
            let cs = self.st.couplings_of(k);
            let var = &mut self.cov.inv_depth_var[k * n_pix..(k + 1) * n_pix];
            let inv = &self.red.inv_hdd[k * n_pix..(k + 1) * n_pix];
            for (v, &ih) in var.iter_mut().zip(inv) {
                *v = if ih > 0.0 { ih } else { f64::INFINITY };
            }
            // Quadratic form b^T S^-1 b summed block pair by block pair:
            // sum_a h_a^T S_aa h_a + 2 sum_{a<b} h_a^T S_ab h_b.
            for (a, ca) in cs.iter().enumerate() {
                let ha = &self.sys.h_pd[ca.slot * n_pix * 6..(ca.slot + 1) * n_pix * 6];
                for cb in &cs[a..] {
                    let hb = &self.sys.h_pd[cb.slot * n_pix * 6..(cb.slot + 1) * n_pix * 6];
                    let mut block = [[0.0; 6]; 6];
                    for (c, col) in block.iter_mut().enumerate() {
                        for (r, x) in col.iter_mut().enumerate() {
                            *x = sigma[(6 * cb.free + c) * dim + 6 * ca.free + r];
                        }
                    }
                    let scale = if cb.free == ca.free { 1.0 } else { 2.0 };
                    for (((pa, pb), &ih), v) in ha.chunks_exact(6).zip(hb.chunks_exact(6)).zip(inv).zip(var.iter_mut()) {
                        if ih == 0.0 {
                            continue;
                        }
                        let mut q = 0.0;
                        for (col, &b) in block.iter().zip(pb) {
                            let mut t = 0.0;
                            for (&s, &a) in col.iter().zip(pa) {
                                t += a * s;
                            }
                            q += t * b;
                        }
                        *v += scale * ih * ih * q;
                    }
                }
            }
        }
        let unknowns = dim + self.sys.observed_depths;
        self.cov.unit_variance = (self.sys.residuals > unknowns).then(|| self.sys.weighted_sq_residual / (self.sys.residuals - unknowns) as f64);
        self.cov.valid = true;
        Ok(())
    }
}
