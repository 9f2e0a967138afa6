//! Writes the repository's compact copy of the ViT reference fixtures (what the parity tests
//! of `sos-backbones` read in a clone without the shared folder).
//!
//! `cargo run --release -p sos-tools --bin vit_fixture_pack [SHARED_FIXTURES] [REPO_FIXTURES]`
//! (defaults `../shared/fixtures` and `fixtures`). Writes
//! - `vit_tiny/weights.json`: every tensor of `vit_tiny/weights.safetensors`;
//! - `vit_tiny/io.json`: the inputs and expected outputs of `vit_tiny/io.json`;
//! - `vit_tiny_sharp/io.json`: the expected outputs of the sharp variant, after checking that
//!   its weights are `vit_tiny`'s with `blocks.*.attn.qkv.weight` multiplied by 8 (exactly),
//!   which the tests rebuild instead of storing a second copy.
//!
//! Every value of the reference files is exactly a float32, so the copy is lossless.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use sos_backbones::dino_vit::StateDict;
use sos_backbones::fixture::{CompactFixture, F32Array};

const INPUTS: [&str; 2] = ["x224", "x64"];
const OUTPUTS: [&str; 6] = ["tokens224", "normed224", "cls_attn224", "tokens64", "normed64", "cls_attn64"];
/// Factor of the sharp variant's qkv weights.
const SHARP_QKV: f32 = 8.0;

fn weights(path: &Path) -> Result<Vec<(String, F32Array)>, String> {
    let sd = StateDict::load(path).map_err(|e| e.to_string())?;
    sd.names()
        .map(|name| {
            let data = sd.f32(name).map_err(|e| e.to_string())?;
            Ok((name.to_string(), F32Array { shape: sd.shape(name).expect("listed").to_vec(), data }))
        })
        .collect()
}

fn reference_io(path: &Path) -> Result<(String, serde_json::Value), String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let value: serde_json::Value = serde_json::from_str(&text).map_err(|e| format!("{}: {e}", path.display()))?;
    Ok((value["doc"].as_str().unwrap_or_default().to_string(), value))
}

fn pack(shared: &Path, repo: &Path) -> Result<(), String> {
    let tiny = weights(&shared.join("vit_tiny/weights.safetensors"))?;
    let from_pth = weights(&shared.join("vit_tiny/weights.pth"))?;
    if tiny != from_pth {
        return Err("vit_tiny: weights.pth and weights.safetensors differ".into());
    }
    let sharp = weights(&shared.join("vit_tiny_sharp/weights.safetensors"))?;
    if sharp.len() != tiny.len() {
        return Err("vit_tiny_sharp has other tensors than vit_tiny".into());
    }
    for ((name, a), (name_b, b)) in tiny.iter().zip(&sharp) {
        let factor = if name.ends_with("attn.qkv.weight") { SHARP_QKV } else { 1.0 };
        let same = name == name_b && a.shape == b.shape && a.data.iter().zip(&b.data).all(|(x, y)| x * factor == *y);
        if !same {
            return Err(format!("vit_tiny_sharp `{name}` is not vit_tiny's times {factor}"));
        }
    }
    let mut w = CompactFixture {
        doc: "Weights of ../shared/fixtures/vit_tiny (DINO ViT, patch 16, dim 64, depth 2, 2 heads), every tensor of \
              weights.safetensors by its state-dict name. vit_tiny_sharp's weights are these with every \
              blocks.N.attn.qkv.weight multiplied by 8. Written by `vit_fixture_pack`."
            .into(),
        ..Default::default()
    };
    w.arrays.extend(tiny);
    std::fs::create_dir_all(repo.join("vit_tiny")).map_err(|e| e.to_string())?;
    std::fs::create_dir_all(repo.join("vit_tiny_sharp")).map_err(|e| e.to_string())?;
    std::fs::write(repo.join("vit_tiny/weights.json"), w.to_text()).map_err(|e| e.to_string())?;

    for (variant, names) in [("vit_tiny", [&INPUTS[..], &OUTPUTS[..]].concat()), ("vit_tiny_sharp", OUTPUTS.to_vec())] {
        let (doc, value) = reference_io(&shared.join(variant).join("io.json"))?;
        let mut fx = CompactFixture {
            doc: format!(
                "Copy of ../shared/fixtures/{variant}/io.json{}. Original doc: {doc}",
                if variant == "vit_tiny_sharp" { " (outputs only: the inputs are vit_tiny's)" } else { "" }
            ),
            ..Default::default()
        };
        for name in names {
            let a = F32Array::from_reference_json(&value[name]).map_err(|e| format!("{variant} `{name}`: {e}"))?;
            fx.arrays.insert(name.to_string(), a);
        }
        if variant == "vit_tiny_sharp" {
            let (_, tiny_io) = reference_io(&shared.join("vit_tiny/io.json"))?;
            for name in INPUTS {
                if tiny_io[name] != value[name] {
                    return Err(format!("vit_tiny_sharp input `{name}` differs from vit_tiny's"));
                }
            }
        }
        let path = repo.join(variant).join("io.json");
        std::fs::write(&path, fx.to_text()).map_err(|e| e.to_string())?;
        println!("wrote {}", path.display());
    }
    Ok(())
}

fn main() -> ExitCode {
    let mut args = std::env::args().skip(1);
    let shared = args.next().map(PathBuf::from).unwrap_or_else(|| PathBuf::from("../shared/fixtures"));
    let repo = args.next().map(PathBuf::from).unwrap_or_else(|| PathBuf::from("fixtures"));
    match pack(&shared, &repo) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("vit_fixture_pack: {e}");
            ExitCode::FAILURE
        }
    }
}
