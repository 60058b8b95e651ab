//! duv-slam: dense underwater visual SLAM with depth uncertainty and medium modelling.
//!
//! The module tree is the architecture (see `ARCHITECTURE.md`): `core` holds the plain types
//! every stage shares; `config` the board profiles; `camera` the frame sources (dataset
//! readers today, live cameras later); `sim` the underwater sequence generator; `track` the
//! tracking stage (flow, bundle adjustment); `map` the mapping stage (Gaussians, rendering,
//! medium, losses, optimiser); `eval` the metrics; `io` the file formats.
//! Stages never import one another.

pub mod camera;
pub mod config;
pub mod core;
pub mod eval;
pub mod gpu;
pub mod io;
pub mod log;
pub mod map;
pub mod pipeline;
pub mod replay;
pub mod sim;
pub mod track;
