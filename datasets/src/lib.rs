//! Dataset adapters and the synthetic scene generator of nerf-sos.
