//! Mapping stage (paper §3.2-3.3): the 3D Gaussian map with the neural medium, rendered and
//! optimised against the keyframes the tracker hands over (image, pose, inverse depth and its
//! variance). Mapping never imports another stage.
//!
//! CPU references, the oracles the GPU kernels are compared with, so their loops keep the
//! kernels' shape (per Gaussian, per tile, per pixel, per row for separable filters):
//! [`gaussians`] holds the map in fixed-capacity SoA buffers; [`render`] is the splatting
//! renderer with the medium (Eq. 6-9, 11), forward and backward; [`medium`] the medium network
//! (Eq. 10); [`loss`] the mapping losses and their gradients (Eq. 12-14); [`adam`] the
//! optimiser; [`mapper`] the mapping stage that ties them together ([`densify`] and
//! [`schedule`] are its density control and keyframe schedule); [`restore`] the water-free view of a captured frame; [`stage`] is what the pipeline
//! drives: keyframes in with a per-keyframe budget, and the exports. [`real`] makes the medium and losses generic over `f32` (runtime) and `f64`
//! (finite-difference gradient checks).

pub mod adam;
pub mod backend;
pub mod checkpoint;
pub mod densify;
pub mod gaussians;
pub mod loss;
pub mod mapper;
pub mod medium;
pub mod medium_estimate;
pub mod ply;
pub mod pose_refine;
pub mod real;
pub mod render;
pub mod restore;
pub mod schedule;
pub mod stage;
pub mod vulkan;

/// The device options the mapper opens its Vulkan device with (`Mapper::use_device`); re-exported
/// so that the pipeline and the binary name the mapper, not the device layer.
pub use duv_gpu::GpuOptions;
