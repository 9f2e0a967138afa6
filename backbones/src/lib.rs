//! 2D feature extractors (teachers) for nerf-sos.
//!
//! - [`cell_stats`]: `kind = "cell-stats"`, weight-free colour and texture statistics per
//!   cell, the offline fallback for DINO.
//! - [`dino_vit`]: `kind = "dino-vit"`, the reference's DINO ViT (S/16, S/8, B/16, B/8) run
//!   natively from the official `.pth` or `.safetensors` weights.
//! - [`efficientnet_lite`]: `kind = "efficientnet-lite"`, the ImageNet-trained CNN
//!   EfficientNet-Lite0 run natively from its published (legacy-format) `.pth` weights.
//! - `onnx` (cargo feature `onnx`): `kind = "onnx"`, any exported backbone through ONNX
//!   Runtime, loaded dynamically at run time.
//! - [`checkpoint`]: the weight-file readers the teachers share (PyTorch's zip and legacy
//!   `.pth` formats, `.safetensors`).
//! - [`fixture`]: the compact numeric fixture format of the parity tests.

pub mod cell_stats;
pub mod checkpoint;
pub mod dino_vit;
pub mod efficientnet_lite;
pub mod fixture;
#[cfg(feature = "onnx")]
pub mod onnx;

pub use cell_stats::{CellStats, CellStatsConfig, SaliencyScale};
pub use dino_vit::{DinoVit, DinoVitConfig};
pub use efficientnet_lite::{EfficientNetLite, EfficientNetLiteConfig};
