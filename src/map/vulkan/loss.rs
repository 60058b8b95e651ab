//! The mapping losses (Eq. 12-14) on the GPU: the twin of [`crate::map::loss::total_loss`].
//! (Being written.)
