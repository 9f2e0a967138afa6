//! Stage 2: the segmentation head attached to every field, strided patch sampling, training
//! with the collaborative contrastive loss, and mask inference with k-means.

pub mod border_split;
pub mod cleanup;
pub mod cluster_space;
pub mod colour_refine;
pub mod defaults;
pub mod diagnostics;
pub mod evaluate;
pub mod frozen_render;
pub mod head;
pub mod head_pass;
pub mod infer;
pub mod patches;
pub mod ray_cache;
pub mod stability;
pub mod store;
pub mod support_plane;
pub mod surface;
pub mod teacher;
pub mod train;
