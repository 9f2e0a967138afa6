//! Segmentation and image-quality metrics, matching the reference implementation.
