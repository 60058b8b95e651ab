//! The CPU tests of the algorithms in one binary (one link): BA, tracking, rendering and its
//! gradients, the mapper, the generator, the dataset readers, the boards and the evaluator.

#[path = "../common/ba_scene.rs"]
mod ba_scene;
#[path = "../common/render_scene.rs"]
mod render_scene;
#[path = "../common/track_sim.rs"]
mod track_sim;

mod ba;
mod boards;
mod datasets;
mod eval_reference;
mod map_gradients;
mod mapper;
mod metric;
mod render;
mod sim;
mod tracker;
