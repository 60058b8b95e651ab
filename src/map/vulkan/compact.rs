//! Pruning on the GPU: stream compaction of the map and its optimiser moments, the twin of
//! [`crate::map::gaussians::Gaussians::retain`]. (Being written.)
