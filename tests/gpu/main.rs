//! The GPU tests in one binary (one link): every kernel against its CPU reference on the Vulkan device
//! (lavapipe in CI; a missing device fails when `CI` is set), and the Vulkan mapper.

#[path = "../gpu_common/mod.rs"]
mod gpu_common;
#[path = "../common/render_scene.rs"]
mod render_scene;

mod gpu_compact;
mod gpu_loss;
mod gpu_map;
mod gpu_mapper;
mod gpu_medium;
mod gpu_optimiser;
mod gpu_primitives;
