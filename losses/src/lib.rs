//! Pair miners and contrastive losses of nerf-sos.
