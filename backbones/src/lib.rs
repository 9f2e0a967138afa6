//! 2D feature extractors (teachers) for nerf-sos.
