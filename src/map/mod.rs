//! The mapping stage (paper §3.2-3.3): the 3D Gaussian map with the underwater medium,
//! rendered and differentiated for the joint optimisation of Gaussians and medium.
//!
//! `gaussians` holds the map in fixed-capacity SoA buffers; `render` is the CPU reference of
//! the splatting renderer with the medium (Eq. 6-9, 11), forward and backward, structured as
//! the GPU kernels.

pub mod gaussians;
pub mod render;
