//! Keyframes with ground-truth poses and inverse depth from the generator, so that mapping can
//! be evaluated without the tracker.

use super::render::SimRenderer;
use duv_core::{ImageRgb8, Keyframe, PlaneF32};

/// Relative standard deviation given to the ground-truth inverse depth of a simulated keyframe.
pub const SIM_INV_DEPTH_REL_STD: f32 = 0.01;

/// A simulated keyframe and the water-free image of the same view (the restoration target).
#[derive(Clone, Debug)]
pub struct SimKeyframe {
    pub keyframe: Keyframe,
    pub clear: ImageRgb8,
}

/// Renders every `every`-th frame (at most `max` of them) as a keyframe: exact pose, inverse
/// depth `1/z` where the ray hit the scene (0 elsewhere) with variance
/// `(SIM_INV_DEPTH_REL_STD / z)^2`.
pub fn sim_keyframes(renderer: &SimRenderer, every: usize, max: usize) -> Vec<SimKeyframe> {
    let every = every.max(1);
    (0..renderer.len())
        .step_by(every)
        .take(max)
        .map(|i| {
            let f = renderer.render(i);
            let mut inv_depth = PlaneF32::new(f.depth_m.width, f.depth_m.height);
            let mut inv_depth_variance = PlaneF32::new(f.depth_m.width, f.depth_m.height);
            for ((d, v), &z) in inv_depth.data.iter_mut().zip(inv_depth_variance.data.iter_mut()).zip(&f.depth_m.data) {
                if z > 0.0 && z.is_finite() {
                    *d = 1.0 / z;
                    *v = (SIM_INV_DEPTH_REL_STD / z).powi(2);
                }
            }
            SimKeyframe {
                keyframe: Keyframe {
                    index: i as u64,
                    t_ns: f.t_ns,
                    image: f.rgb,
                    world_from_cam: f.world_from_cam,
                    camera: *renderer.camera(),
                    inv_depth,
                    inv_depth_variance,
                },
                clear: f.clear,
            }
        })
        .collect()
}
