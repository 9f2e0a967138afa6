//! Test helpers: the committed compact fixtures, a temp folder, and small writers of PyTorch
//! zip checkpoints and safetensors files (so the readers are tested on files made here).

#![allow(dead_code)]

pub mod writers;

use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};

use sos_backbones::fixture::{CompactFixture, F32Array};

/// The committed weights of the tiny reference ViT, by state-dict name.
pub fn tiny_weights() -> Vec<(String, F32Array)> {
    let fx = CompactFixture::parse(include_str!("../../../fixtures/vit_tiny/weights.json")).expect("weights fixture");
    fx.arrays.into_iter().collect()
}

/// The sharp variant: `blocks.*.attn.qkv.weight` times 8.
pub fn sharp_weights() -> Vec<(String, F32Array)> {
    tiny_weights()
        .into_iter()
        .map(|(name, mut a)| {
            if name.ends_with("attn.qkv.weight") {
                a.data.iter_mut().for_each(|v| *v *= 8.0);
            }
            (name, a)
        })
        .collect()
}

/// Inputs and outputs of a variant (`vit_tiny` has inputs, the sharp one outputs only).
pub fn io(variant: &str) -> CompactFixture {
    let text = match variant {
        "vit_tiny" => include_str!("../../../fixtures/vit_tiny/io.json"),
        "vit_tiny_sharp" => include_str!("../../../fixtures/vit_tiny_sharp/io.json"),
        other => panic!("no fixture {other}"),
    };
    CompactFixture::parse(text).expect("io fixture")
}

/// The weights of a variant.
pub fn weights(variant: &str) -> Vec<(String, F32Array)> {
    match variant {
        "vit_tiny" => tiny_weights(),
        _ => sharp_weights(),
    }
}

/// A fresh empty folder in Cargo's scratch folder for integration tests (`target/tmp`), unique
/// to this call; emptied first, so reruns of the suite reuse it instead of adding copies.
pub fn temp_dir(test: &str) -> PathBuf {
    static COUNT: AtomicUsize = AtomicUsize::new(0);
    let n = COUNT.fetch_add(1, Ordering::SeqCst);
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(format!("backbones-{test}-{n}"));
    std::fs::remove_dir_all(&dir).ok();
    std::fs::create_dir_all(&dir).expect("temp dir");
    dir
}

/// Largest absolute difference.
pub fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len(), "length");
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
}
