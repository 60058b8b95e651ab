//! Underwater sequence generator.
