//! Mapping stage (paper §3.2-3.3): the 3D Gaussian map with the neural medium, rendered and
//! optimised against the keyframes the tracker hands over (image, pose, inverse depth and its
//! variance).
//!
//! This part holds the CPU references of the medium network ([`medium`]), the mapping losses
//! and their gradients ([`loss`]) and the optimiser ([`adam`]); they are the oracles the GPU
//! kernels are compared with, so their loops keep the kernels' shape (per pixel, per row for
//! separable filters, rows in parallel). [`real`] makes them generic over `f32` (runtime) and
//! `f64` (finite-difference gradient checks). Mapping never imports another stage.

pub mod adam;
pub mod loss;
pub mod medium;
pub mod real;
