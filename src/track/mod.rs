//! Tracking: dense correspondence between keyframes (`flow`) feeding bundle adjustment.

pub mod flow;
