//! Schur complement onto the poses (Eq. 3), the dense Cholesky solve of the reduced system
//! (faer, in place, scratch from the workspace's `MemBuffer`), and depth back-substitution.

use faer::dyn_stack::MemStack;
use faer::linalg::cholesky::llt;
use faer::{MatMut, Par};
use nalgebra::Matrix6;

use super::linearize::add_block;
use super::workspace::{Reduced, Structure, System, Window};
use super::BaError;

/// Forms the damped reduced system in `red.s` / `red.rhs`:
/// `S = H_pp' - H_pd H_dd'^-1 H_dp`, `g = b_p - H_pd H_dd'^-1 b_d`, where `'` marks the
/// diagonal scaled by `1 + lambda` (`lambda = 0`: the undamped system of Eq. 4). Pixels with
/// undamped `H_dd < min_depth_hessian` are frozen (`red.inv_hdd = 0`).
pub(crate) fn reduce(win: &Window, st: &Structure, sys: &System, lambda: f64, min_depth_hessian: f64, red: &mut Reduced) {
    let n_pix = win.n_pixels;
    let dim = 6 * st.n_free;
    let s = &mut red.s[..dim * dim];
    s.copy_from_slice(&sys.h_pp[..dim * dim]);
    for r in 0..dim {
        s[r * dim + r] *= 1.0 + lambda;
    }
    red.rhs[..dim].copy_from_slice(&sys.b_p[..dim]);
    for q in 0..win.n_keyframes * n_pix {
        let h = sys.h_dd[q];
        red.inv_hdd[q] = if h >= min_depth_hessian { 1.0 / (h * (1.0 + lambda)) } else { 0.0 };
    }
    for k in 0..win.n_keyframes {
        let inv = &red.inv_hdd[k * n_pix..(k + 1) * n_pix];
        let b_d = &sys.b_d[k * n_pix..(k + 1) * n_pix];
        let cs = st.couplings_of(k);
        for (a, ca) in cs.iter().enumerate() {
            let ha = &sys.h_pd[ca.slot * n_pix * 6..(ca.slot + 1) * n_pix * 6];
            // g_a -= sum_p h_a(p) b_d(p) / H_dd(p)
            let mut g = [0.0; 6];
            for ((pa, &f), &b) in ha.chunks_exact(6).zip(inv).zip(b_d) {
                let fb = f * b;
                for (x, &a) in g.iter_mut().zip(pa) {
                    *x += a * fb;
                }
            }
            for (x, gr) in red.rhs[6 * ca.free..6 * ca.free + 6].iter_mut().zip(g) {
                *x -= gr;
            }
            // S_ab -= sum_p h_a(p) h_b(p)^T / H_dd(p), for b >= a (S_ba is the transpose).
            for cb in &cs[a..] {
                let hb = &sys.h_pd[cb.slot * n_pix * 6..(cb.slot + 1) * n_pix * 6];
                let mut acc = [[0.0f64; 6]; 6];
                for ((pa, pb), &f) in ha.chunks_exact(6).zip(hb.chunks_exact(6)).zip(inv) {
                    if f == 0.0 {
                        continue;
                    }
                    for (col, &b) in acc.iter_mut().zip(pb) {
                        let fb = f * b;
                        for (x, &a) in col.iter_mut().zip(pa) {
                            *x += a * fb;
                        }
                    }
                }
                let block = -Matrix6::from_fn(|r, c| acc[c][r]);
                add_block(s, dim, ca.free, cb.free, &block);
                if cb.free != ca.free {
                    add_block(s, dim, cb.free, ca.free, &block.transpose());
                }
            }
        }
    }
}

/// Factors `red.s` in place (lower Cholesky factor). `Err(pivot)` if not positive definite.
pub(crate) fn factor(red: &mut Reduced, dim: usize) -> Result<(), usize> {
    if dim == 0 {
        return Ok(());
    }
    let a = MatMut::from_column_major_slice_mut(&mut red.s[..dim * dim], dim, dim);
    let stack = MemStack::new(&mut red.scratch);
    llt::factor::cholesky_in_place(a, Default::default(), Par::Seq, stack, Default::default())
        .map(|_| ())
        .map_err(|llt::factor::LltError::NonPositivePivot { index }| index)
}

/// Solves the damped reduced system for the pose step and back-substitutes the depth step
/// `dd = H_dd'^-1 (b_d - H_dp dxi)`.
pub(crate) fn solve_step(win: &Window, st: &Structure, sys: &System, lambda: f64, min_depth_hessian: f64, red: &mut Reduced) -> Result<(), BaError> {
    let dim = 6 * st.n_free;
    reduce(win, st, sys, lambda, min_depth_hessian, red);
    factor(red, dim).map_err(|pivot| BaError::SingularSystem { dim, pivot, damping: lambda })?;
    if dim > 0 {
        let l = faer::MatRef::from_column_major_slice(&red.s[..dim * dim], dim, dim);
        let rhs = MatMut::from_column_major_slice_mut(&mut red.rhs[..dim], dim, 1);
        let stack = MemStack::new(&mut red.scratch);
        llt::solve::solve_in_place(l, rhs, Par::Seq, stack);
    }
    red.step_pose[..dim].copy_from_slice(&red.rhs[..dim]);
    let n_pix = win.n_pixels;
    for k in 0..win.n_keyframes {
        let range = k * n_pix..(k + 1) * n_pix;
        let (inv, b_d) = (&red.inv_hdd[range.clone()], &sys.b_d[range.clone()]);
        let dd = &mut red.step_inv_depth[range];
        dd.copy_from_slice(b_d);
        for c in st.couplings_of(k) {
            let h = &sys.h_pd[c.slot * n_pix * 6..(c.slot + 1) * n_pix * 6];
            let x = &red.step_pose[6 * c.free..6 * c.free + 6];
            for p in 0..n_pix {
                let hp = &h[6 * p..6 * p + 6];
                dd[p] -= hp[0] * x[0] + hp[1] * x[1] + hp[2] * x[2] + hp[3] * x[3] + hp[4] * x[4] + hp[5] * x[5];
            }
        }
        for (x, f) in dd.iter_mut().zip(inv) {
            *x *= f;
        }
    }
    Ok(())
}
