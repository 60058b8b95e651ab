//! The factor graph's edges (flow measurements between keyframes, kept for the window and the
//! global BA) and the Sim(3) pose graph that spreads a loop closure's correction, scale
//! included, over every keyframe.

use duv_core::pose::so3_exp;
use faer::dyn_stack::{MemBuffer, MemStack, StackReq};
use faer::linalg::cholesky::llt;
use faer::{MatMut, MatRef, Par};
use duv_core::{Image, Se3, Sim3};
use nalgebra::{Translation3, Vector3};

/// One directed edge `from -> to` (keyframe slots): for every pixel of `from`, its target in
/// `to` (depth-grid pixels) and the two axis weights.
pub(crate) struct EdgeSlot {
    pub from: usize,
    pub to: usize,
    /// A loop-closure edge (kept out of the local window's edge selection).
    pub is_loop: bool,
    pub target: Image<f32, 2>,
    pub weight: Image<f32, 2>,
}

/// Fixed-capacity edge table.
pub(crate) struct EdgeStore {
    pub edges: Vec<EdgeSlot>,
    /// Live edge indices, in insertion order.
    pub live: Vec<usize>,
    free: Vec<usize>,
}

impl EdgeStore {
    pub fn new(capacity: usize, low_w: usize, low_h: usize) -> Self {
        let edges = (0..capacity)
            .map(|_| EdgeSlot { from: 0, to: 0, is_loop: false, target: Image::new(low_w, low_h), weight: Image::new(low_w, low_h) })
            .collect();
        EdgeStore { edges, live: Vec::with_capacity(capacity), free: (0..capacity).rev().collect() }
    }

    /// The live edge `from -> to`, if any.
    pub fn find(&self, from: usize, to: usize) -> Option<usize> {
        self.live.iter().copied().find(|&e| self.edges[e].from == from && self.edges[e].to == to)
    }

    /// Adds (or returns the existing) edge `from -> to`; `None` when the table is full.
    pub fn add(&mut self, from: usize, to: usize, is_loop: bool) -> Option<usize> {
        if let Some(e) = self.find(from, to) {
            self.edges[e].is_loop |= is_loop;
            return Some(e);
        }
        let e = self.free.pop()?;
        let slot = &mut self.edges[e];
        slot.from = from;
        slot.to = to;
        slot.is_loop = is_loop;
        slot.weight.data.fill(0.0);
        self.live.push(e);
        Some(e)
    }

    /// Removes every edge touching keyframe slot `s`.
    pub fn remove_touching(&mut self, s: usize) {
        let mut i = 0;
        while i < self.live.len() {
            let e = self.live[i];
            if self.edges[e].from == s || self.edges[e].to == s {
                self.live.remove(i);
                self.free.push(e);
            } else {
                i += 1;
            }
        }
    }
}

/// Error of a relative Sim(3) measurement: `E = Z^-1 T_a^-1 T_b` as (translation, rotation
/// vector, log scale). Zero when the estimate agrees with the measurement.
fn sim3_error(z_inv: &Sim3, a: &Sim3, b: &Sim3) -> [f64; 7] {
    let e = z_inv * a.inverse() * b;
    let t = e.isometry.translation.vector;
    let r = e.isometry.rotation.scaled_axis();
    [t.x, t.y, t.z, r.x, r.y, r.z, e.scaling().ln()]
}

/// `T * Exp(delta)` with the retraction (translation, rotation vector, log scale).
fn sim3_retract(t: &Sim3, d: &[f64]) -> Sim3 {
    let inc = Sim3::from_parts(
        Translation3::new(d[0], d[1], d[2]),
        so3_exp(&Vector3::new(d[3], d[4], d[5])),
        d[6].exp(),
    );
    t * inc
}

/// A relative constraint of the pose graph between nodes `a` and `b` (`Z = T_a^-1 T_b`).
#[derive(Clone, Copy, Debug)]
pub(crate) struct PoseConstraint {
    pub a: usize,
    pub b: usize,
    pub z: Sim3,
    pub weight: f64,
}

/// Dense Gauss-Newton on Sim(3) with numerical Jacobians; node 0 is the gauge. Buffers are
/// sized once for `max_nodes` nodes and `max_constraints` constraints.
pub(crate) struct PoseGraph {
    pub nodes: Vec<Sim3>,
    pub constraints: Vec<PoseConstraint>,
    h: Vec<f64>,
    b: Vec<f64>,
    l: Vec<f64>,
    x: Vec<f64>,
    trial: Vec<Sim3>,
    max_nodes: usize,
    /// faer's Cholesky scratch, sized for the largest system.
    scratch: MemBuffer,
}

/// Finite-difference step of the numerical Jacobians.
const PG_DIFF_STEP: f64 = 1e-6;

impl PoseGraph {
    pub fn new(max_nodes: usize, max_constraints: usize) -> Self {
        let dim = 7 * max_nodes;
        PoseGraph {
            nodes: Vec::with_capacity(max_nodes),
            constraints: Vec::with_capacity(max_constraints),
            h: vec![0.0; dim * dim],
            b: vec![0.0; dim],
            l: vec![0.0; dim * dim],
            x: vec![0.0; dim],
            trial: Vec::with_capacity(max_nodes),
            max_nodes,
            scratch: MemBuffer::new(StackReq::any_of(&[
                llt::factor::cholesky_in_place_scratch::<f64>(dim, Par::Seq, Default::default()),
                llt::solve::solve_in_place_scratch::<f64>(dim, 1, Par::Seq),
            ])),
        }
    }

    pub fn clear(&mut self) {
        self.nodes.clear();
        self.constraints.clear();
    }

    /// Adds a node; false when full.
    pub fn add_node(&mut self, world_from_cam: &Se3) -> bool {
        if self.nodes.len() >= self.max_nodes {
            return false;
        }
        self.nodes.push(Sim3::from_isometry(*world_from_cam, 1.0));
        true
    }

    /// Adds a constraint; false when full.
    pub fn add_constraint(&mut self, c: PoseConstraint) -> bool {
        if self.constraints.len() >= self.constraints.capacity() {
            return false;
        }
        self.constraints.push(c);
        true
    }

    fn cost(&self, nodes: &[Sim3]) -> f64 {
        self.constraints
            .iter()
            .map(|c| {
                let e = sim3_error(&c.z.inverse(), &nodes[c.a], &nodes[c.b]);
                c.weight * e.iter().map(|v| v * v).sum::<f64>()
            })
            .sum()
    }

    /// Levenberg-Marquardt over every node but the first. Returns the final cost.
    pub fn optimize(&mut self, iterations: usize) -> f64 {
        let n = self.nodes.len();
        if n < 2 || self.constraints.is_empty() {
            return 0.0;
        }
        let dim = 7 * (n - 1);
        let mut lambda = 1e-4;
        let mut cost = self.cost(&self.nodes);
        for _ in 0..iterations {
            self.h[..dim * dim].fill(0.0);
            self.b[..dim].fill(0.0);
            for c in &self.constraints {
                let z_inv = c.z.inverse();
                let e0 = sim3_error(&z_inv, &self.nodes[c.a], &self.nodes[c.b]);
                // Jacobian columns for the free node dofs touched by this constraint.
                let mut jac = [[0.0f64; 7]; 14];
                let mut idx = [usize::MAX; 14];
                for (side, node) in [c.a, c.b].into_iter().enumerate() {
                    if node == 0 {
                        continue;
                    }
                    for k in 0..7 {
                        let mut d = [0.0; 7];
                        d[k] = PG_DIFF_STEP;
                        let plus = sim3_retract(&self.nodes[node], &d);
                        d[k] = -PG_DIFF_STEP;
                        let minus = sim3_retract(&self.nodes[node], &d);
                        let (ep, em) = if side == 0 {
                            (sim3_error(&z_inv, &plus, &self.nodes[c.b]), sim3_error(&z_inv, &minus, &self.nodes[c.b]))
                        } else {
                            (sim3_error(&z_inv, &self.nodes[c.a], &plus), sim3_error(&z_inv, &self.nodes[c.a], &minus))
                        };
                        for r in 0..7 {
                            jac[side * 7 + k][r] = (ep[r] - em[r]) / (2.0 * PG_DIFF_STEP);
                        }
                        idx[side * 7 + k] = 7 * (node - 1) + k;
                    }
                }
                for p in 0..14 {
                    if idx[p] == usize::MAX {
                        continue;
                    }
                    let gp: f64 = (0..7).map(|r| jac[p][r] * e0[r]).sum();
                    self.b[idx[p]] -= c.weight * gp;
                    for q in 0..14 {
                        if idx[q] == usize::MAX {
                            continue;
                        }
                        let v: f64 = (0..7).map(|r| jac[p][r] * jac[q][r]).sum();
                        self.h[idx[p] * dim + idx[q]] += c.weight * v;
                    }
                }
            }
            let mut accepted = false;
            while lambda < 1e10 {
                if !damped_solve(&self.h, &self.b, dim, lambda, &mut self.l, &mut self.x, &mut self.scratch) {
                    lambda *= 10.0;
                    continue;
                }
                self.trial.clear();
                self.trial.push(self.nodes[0]);
                for k in 1..n {
                    let d = &self.x[7 * (k - 1)..7 * k];
                    self.trial.push(sim3_retract(&self.nodes[k], d));
                }
                let trial_cost = self.cost(&self.trial);
                if trial_cost.is_finite() && trial_cost < cost {
                    self.nodes.copy_from_slice(&self.trial);
                    let decrease = (cost - trial_cost) / cost.max(1e-300);
                    cost = trial_cost;
                    lambda = (lambda * 0.1).max(1e-12);
                    accepted = decrease > 1e-10;
                    break;
                }
                lambda *= 10.0;
            }
            if !accepted {
                break;
            }
        }
        cost
    }
}

/// Solves `(H + lambda diag(H)) x = b` by Cholesky into `l` (factor scratch) and `x`.
/// False when the damped system is not positive definite.
fn damped_solve(h: &[f64], b: &[f64], n: usize, lambda: f64, l: &mut [f64], x: &mut [f64], scratch: &mut MemBuffer) -> bool {
    // faer's blocked Cholesky (H is symmetric: row- or column-major alike); the hand-written
    // `cholesky_in_place` below is the slow reference it is tested against. Over a 64-keyframe
    // loop (a 441-unknown system, 20 iterations) the hand-written one took about 100 ms of
    // the loop-closure frame.
    l[..n * n].copy_from_slice(&h[..n * n]);
    for i in 0..n {
        l[i * n + i] = l[i * n + i] * (1.0 + lambda) + 1e-9;
    }
    let a = MatMut::from_column_major_slice_mut(&mut l[..n * n], n, n);
    if llt::factor::cholesky_in_place(a, Default::default(), Par::Seq, MemStack::new(scratch), Default::default()).is_err() {
        return false;
    }
    x[..n].copy_from_slice(&b[..n]);
    let factor = MatRef::from_column_major_slice(&l[..n * n], n, n);
    llt::solve::solve_in_place(factor, MatMut::from_column_major_slice_mut(&mut x[..n], n, 1), Par::Seq, MemStack::new(scratch));
    x[..n].iter().all(|v| v.is_finite())
}

/// Lower Cholesky factor in place (row-major, lower triangle used). False if not PD. The slow
/// exact reference of `damped_solve`'s faer factorisation.
#[cfg(test)]
pub(crate) fn cholesky_in_place(a: &mut [f64], n: usize) -> bool {
    for j in 0..n {
        let mut d = a[j * n + j];
        for k in 0..j {
            d -= a[j * n + k] * a[j * n + k];
        }
        if !(d > 0.0 && d.is_finite()) {
            return false;
        }
        let d = d.sqrt();
        a[j * n + j] = d;
        for i in j + 1..n {
            let mut s = a[i * n + j];
            for k in 0..j {
                s -= a[i * n + k] * a[j * n + k];
            }
            a[i * n + j] = s / d;
        }
    }
    true
}

/// Solves `L L^T x = b` in place.
#[cfg(test)]
pub(crate) fn cholesky_solve(l: &[f64], n: usize, x: &mut [f64]) {
    for i in 0..n {
        let mut s = x[i];
        for k in 0..i {
            s -= l[i * n + k] * x[k];
        }
        x[i] = s / l[i * n + i];
    }
    for i in (0..n).rev() {
        let mut s = x[i];
        for k in i + 1..n {
            s -= l[k * n + i] * x[k];
        }
        x[i] = s / l[i * n + i];
    }
}

/// A Sim(3) relative measurement from a rigid relative pose and a scale.
pub(crate) fn sim3_relative(a_from_b: &Se3, scale: f64) -> Sim3 {
    Sim3::from_isometry(*a_from_b, scale)
}

/// Splits a corrected Sim(3) node into a rigid pose and its scale.
pub(crate) fn sim3_split(t: &Sim3) -> (Se3, f64) {
    let iso = Se3::from_parts(Translation3::from(t.isometry.translation.vector), t.isometry.rotation);
    (iso, t.scaling())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pose_graph_recovers_a_loop_from_a_drifted_start() {
        // Eight nodes on a circle. The constraints (consecutive and one loop) are exact; the
        // initial estimate drifts in position, heading and scale, as monocular odometry does.
        let truth: Vec<Sim3> = (0..8)
            .map(|k| {
                let a = k as f64 * std::f64::consts::TAU / 8.0;
                Sim3::from_parts(Translation3::new(3.0 * a.cos(), 3.0 * a.sin(), 0.0), so3_exp(&Vector3::new(0.0, 0.0, a)), 1.0)
            })
            .collect();
        let mut pg = PoseGraph::new(8, 16);
        for (k, t) in truth.iter().enumerate() {
            let drift = Sim3::from_parts(
                Translation3::new(0.05 * k as f64, -0.03 * k as f64, 0.01 * k as f64),
                so3_exp(&Vector3::new(0.0, 0.01 * k as f64, 0.02 * k as f64)),
                1.0,
            );
            let (pose, _) = sim3_split(&(drift * t));
            pg.add_node(&pose);
            pg.nodes[k] = Sim3::from_isometry(pose, 1.04f64.powi(k as i32));
        }
        pg.nodes[0] = truth[0];
        for k in 1..8 {
            pg.add_constraint(PoseConstraint { a: k - 1, b: k, z: truth[k - 1].inverse() * truth[k], weight: 1.0 });
        }
        pg.add_constraint(PoseConstraint { a: 0, b: 7, z: truth[0].inverse() * truth[7], weight: 1.0 });
        let err = |pg: &PoseGraph| -> f64 { (0..8).map(|k| (pg.nodes[k].isometry.translation.vector - truth[k].isometry.translation.vector).norm()).sum() };
        let before = err(&pg);
        let cost = pg.optimize(30);
        let after = err(&pg);
        assert!(before > 0.5, "{before}");
        assert!(after < 1e-4 && cost < 1e-10, "before {before} after {after} cost {cost}");
        for k in 0..8 {
            assert!((pg.nodes[k].scaling() - 1.0).abs() < 1e-6, "node {k} scale {}", pg.nodes[k].scaling());
        }
    }

    #[test]
    fn cholesky_solves_spd() {
        let a = [4.0, 1.0, 0.5, 1.0, 3.0, 0.2, 0.5, 0.2, 2.0];
        let mut l = a;
        assert!(cholesky_in_place(&mut l, 3));
        let mut x = [1.0, 2.0, 3.0];
        cholesky_solve(&l, 3, &mut x);
        for i in 0..3 {
            let r: f64 = (0..3).map(|k| a[i * 3 + k] * x[k]).sum();
            assert!((r - [1.0, 2.0, 3.0][i]).abs() < 1e-12);
        }
    }

    #[test]
    fn damped_solve_matches_the_reference_cholesky() {
        // A 70-unknown SPD system (A^T A + I from a deterministic pseudo-random A).
        let n = 70;
        let mut seed = 12345u64;
        let mut rnd = || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((seed >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        };
        let m: Vec<f64> = (0..n * n).map(|_| rnd()).collect();
        let mut h = vec![0.0; n * n];
        for i in 0..n {
            for j in 0..n {
                h[i * n + j] = (0..n).map(|k| m[k * n + i] * m[k * n + j]).sum::<f64>() + if i == j { 1.0 } else { 0.0 };
            }
        }
        let b: Vec<f64> = (0..n).map(|_| rnd()).collect();
        let lambda = 1e-3;
        let dim = n;
        let mut scratch = MemBuffer::new(StackReq::any_of(&[
            llt::factor::cholesky_in_place_scratch::<f64>(dim, Par::Seq, Default::default()),
            llt::solve::solve_in_place_scratch::<f64>(dim, 1, Par::Seq),
        ]));
        let (mut l, mut x) = (vec![0.0; n * n], vec![0.0; n]);
        assert!(damped_solve(&h, &b, n, lambda, &mut l, &mut x, &mut scratch));
        let mut reference = h.clone();
        for i in 0..n {
            reference[i * n + i] = reference[i * n + i] * (1.0 + lambda) + 1e-9;
        }
        assert!(cholesky_in_place(&mut reference, n));
        let mut x_ref = b.clone();
        cholesky_solve(&reference, n, &mut x_ref);
        let err = x.iter().zip(&x_ref).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
        let size = x_ref.iter().map(|v| v.abs()).fold(0.0, f64::max);
        assert!(size > 1e-3 && err < 1e-10 * size.max(1.0), "max difference {err} (solution size {size})");
        // Not positive definite: refused, like the reference.
        let mut bad = h.clone();
        bad[0] = -1.0;
        assert!(!damped_solve(&bad, &b, n, 0.0, &mut l, &mut x, &mut scratch));
    }
}
