//! Ray sampling, empty-space skipping and volume compositing.
