//! A copy of a BA window's state (keyframe poses, inverse depths and the flow measurements of
//! its edges), sized once, so that a solve from another start can be tried and undone: the
//! second start of the monocular initialisation (see `init_level_start` in
//! [`TrackerConfig`](super::TrackerConfig)).

use super::graph::EdgeStore;
use super::keyframes::KeyframeStore;
use duv_core::{Image, PlaneF32, Se3};

/// Poses, depths and edge measurements of up to `max_keyframes` keyframes and `max_edges`
/// edges (depth grid `low_w x low_h`). Nothing is allocated after [`WindowSnapshot::new`].
pub(crate) struct WindowSnapshot {
    poses: Vec<Se3>,
    inv_depth: Vec<PlaneF32>,
    target: Vec<Image<f32, 2>>,
    weight: Vec<Image<f32, 2>>,
    n_keyframes: usize,
    n_edges: usize,
}

impl WindowSnapshot {
    pub fn new(max_keyframes: usize, max_edges: usize, low_w: usize, low_h: usize) -> Self {
        WindowSnapshot {
            poses: vec![Se3::identity(); max_keyframes],
            inv_depth: (0..max_keyframes).map(|_| PlaneF32::new(low_w, low_h)).collect(),
            target: (0..max_edges).map(|_| Image::new(low_w, low_h)).collect(),
            weight: (0..max_edges).map(|_| Image::new(low_w, low_h)).collect(),
            n_keyframes: 0,
            n_edges: 0,
        }
    }

    /// Copies the state of the keyframe slots `window` and the edges `edges`. Returns false
    /// (and keeps nothing) when they do not fit.
    pub fn save(&mut self, kfs: &KeyframeStore, edge_store: &EdgeStore, window: &[usize], edges: &[usize]) -> bool {
        if window.len() > self.poses.len() || edges.len() > self.target.len() {
            self.n_keyframes = 0;
            self.n_edges = 0;
            return false;
        }
        for (k, &s) in window.iter().enumerate() {
            let kf = &kfs.slots[s];
            self.poses[k] = kf.world_from_cam;
            self.inv_depth[k].data.copy_from_slice(&kf.inv_depth.data);
        }
        for (i, &e) in edges.iter().enumerate() {
            let ed = &edge_store.edges[e];
            self.target[i].data.copy_from_slice(&ed.target.data);
            self.weight[i].data.copy_from_slice(&ed.weight.data);
        }
        self.n_keyframes = window.len();
        self.n_edges = edges.len();
        true
    }

    /// Writes the saved state back into the same `window` slots and `edges` it was saved from.
    pub fn restore(&self, kfs: &mut KeyframeStore, edge_store: &mut EdgeStore, window: &[usize], edges: &[usize]) {
        debug_assert!(window.len() == self.n_keyframes && edges.len() == self.n_edges, "restored into another window");
        for (k, &s) in window.iter().enumerate().take(self.n_keyframes) {
            let kf = &mut kfs.slots[s];
            kf.world_from_cam = self.poses[k];
            kf.inv_depth.data.copy_from_slice(&self.inv_depth[k].data);
        }
        for (i, &e) in edges.iter().enumerate().take(self.n_edges) {
            let ed = &mut edge_store.edges[e];
            ed.target.data.copy_from_slice(&self.target[i].data);
            ed.weight.data.copy_from_slice(&self.weight[i].data);
        }
    }
}
