//! The medium network (Eq. 10) on the GPU: the twin of [`crate::map::medium::MediumWorkspace`]
//! with a direction grid. (Being written.)
