//! Writes a DINO ViT checkpoint as an ONNX model for the `onnx` extractor (no Python needed).
//!
//! `cargo run --release -p sos-tools --bin vit_onnx_export WEIGHTS OUT.onnx [SIZE] [HEADS]`
//!
//! WEIGHTS is an official DINO `.pth` (or the state dict as `.safetensors`); SIZE the square
//! input side (default 224); HEADS the attention heads (default width / 64, as every DINO ViT).
//! The model's input is `image` `[batch, 3, SIZE, SIZE]` (symbolic batch, already normalised),
//! its outputs `tokens` (last block, before the final norm) and `cls_attn`; use it with
//! `tokens = "tokens"`, `prefix_tokens = 1`, `saliency = "cls_attn"`, `input_size = SIZE`.

use std::path::PathBuf;
use std::process::ExitCode;

use sos_backbones::dino_vit::onnx_export::write_vit;
use sos_backbones::dino_vit::{StateDict, Vit, VitShape};

fn run(args: &[String]) -> Result<String, String> {
    let (Some(weights), Some(out)) = (args.first(), args.get(1)) else {
        return Err("usage: vit_onnx_export WEIGHTS OUT.onnx [SIZE] [HEADS]".into());
    };
    let size = match args.get(2) {
        Some(s) => s.parse().map_err(|_| format!("SIZE `{s}` is not a number"))?,
        None => 224,
    };
    let heads = match args.get(3) {
        Some(s) => Some(s.parse().map_err(|_| format!("HEADS `{s}` is not a number"))?),
        None => None,
    };
    let sd = StateDict::load(&PathBuf::from(weights)).map_err(|e| e.to_string())?;
    let shape = VitShape::detect(&sd, heads).map_err(|e| format!("{weights}: {e}"))?;
    if size < shape.patch {
        return Err(format!("SIZE {size} is smaller than one {}-px patch", shape.patch));
    }
    let model = Vit::from_state_dict(&sd, shape).map_err(|e| format!("{weights}: {e}"))?;
    write_vit(&model, size, None, &PathBuf::from(out)).map_err(|e| format!("{out}: {e}"))?;
    Ok(format!(
        "wrote {out}: ViT width {} patch {} depth {} heads {}, input image [batch, 3, {size}, {size}], outputs tokens, cls_attn",
        shape.dim, shape.patch, shape.depth, shape.heads
    ))
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    match run(&args) {
        Ok(msg) => {
            println!("{msg}");
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("vit_onnx_export: {e}");
            ExitCode::FAILURE
        }
    }
}
