//! Parity of the ViT teachers with the reference fixtures AS PUBLISHED: reads the real
//! `weights.pth` and `weights.safetensors` of `vit_tiny` and `vit_tiny_sharp` and checks the
//! native forward against `io.json` (tokens, normed tokens, \[CLS\] attention at 224 and 64 px);
//! with the `onnx` feature also runs each `model.onnx` under ONNX Runtime (224 px). Also
//! checks that the repository's compact copy (`fixtures/vit_tiny*`) equals the reference.
//!
//! `cargo run --release -p sos-tools [--features onnx] --bin vit_parity [FIXTURES_DIR] [REPO_FIXTURES]`
//! (defaults `../shared/fixtures` and `fixtures`). Exit status 1 if any error exceeds 1e-4 or
//! a file cannot be read.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use sos_backbones::dino_vit::{StateDict, Vit, VitShape};
use sos_backbones::fixture::{CompactFixture, F32Array};

const TOL: f32 = 1e-4;
const VARIANTS: [&str; 2] = ["vit_tiny", "vit_tiny_sharp"];
/// Heads of the fixture network (not DINO's width/64).
const HEADS: usize = 2;

struct Report {
    rows: Vec<(String, f32)>,
    failures: Vec<String>,
}

impl Report {
    fn check(&mut self, what: String, got: &[f32], want: &F32Array) {
        if got.len() != want.data.len() {
            self.failures.push(format!("{what}: {} values, expected {}", got.len(), want.data.len()));
            return;
        }
        let err = got.iter().zip(&want.data).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        if err.is_nan() || err > TOL {
            self.failures.push(format!("{what}: max |error| {err:.3e} > {TOL:e}"));
        }
        self.rows.push((what, err));
    }
}

fn load_io(path: &Path) -> Result<serde_json::Value, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    serde_json::from_str(&text).map_err(|e| format!("{}: {e}", path.display()))
}

fn array(io: &serde_json::Value, name: &str) -> Result<F32Array, String> {
    F32Array::from_reference_json(&io[name]).map_err(|e| format!("io.json `{name}`: {e}"))
}

fn native(dir: &Path, variant: &str, io: &serde_json::Value, report: &mut Report) -> Result<(), String> {
    for file in ["weights.pth", "weights.safetensors"] {
        let path = dir.join(variant).join(file);
        let sd = StateDict::load(&path).map_err(|e| e.to_string())?;
        let shape = VitShape::detect(&sd, Some(HEADS)).map_err(|e| format!("{}: {e}", path.display()))?;
        let model = Vit::from_state_dict(&sd, shape).map_err(|e| format!("{}: {e}", path.display()))?;
        for res in [224usize, 64] {
            let x = array(io, &format!("x{res}"))?;
            let out = model.forward(&x.data, x.shape[0], res, res);
            let normed = model.final_norm(&out.tokens);
            for (name, got) in [("tokens", &out.tokens), ("normed", &normed), ("cls_attn", &out.cls_attn)] {
                report.check(format!("native {variant}/{file} {name}{res}"), got, &array(io, &format!("{name}{res}"))?);
            }
        }
    }
    Ok(())
}

#[cfg(feature = "onnx")]
fn onnx(dir: &Path, variant: &str, io: &serde_json::Value, report: &mut Report) -> Result<(), String> {
    use sos_backbones::onnx::OnnxModel;
    let path = dir.join(variant).join("model.onnx");
    let model = OnnxModel::load(&path, None, "image", 2).map_err(|e| e.to_string())?;
    let x = array(io, "x224")?;
    let out = model.run(x.data.clone(), &x.shape, &["tokens", "cls_attn"])?;
    report.check(format!("onnx {variant}/model.onnx tokens224"), &out[0].data, &array(io, "tokens224")?);
    report.check(format!("onnx {variant}/model.onnx cls_attn224"), &out[1].data, &array(io, "cls_attn224")?);
    Ok(())
}

#[cfg(not(feature = "onnx"))]
fn onnx(_: &Path, variant: &str, _: &serde_json::Value, _: &mut Report) -> Result<(), String> {
    println!("onnx {variant}: skipped (build with `--features onnx` and set ORT_DYLIB_PATH)");
    Ok(())
}

/// The committed compact copy holds exactly the reference values.
fn compact_copy(dir: &Path, repo: &Path, report: &mut Report) -> Result<(), String> {
    let read = |p: PathBuf| -> Result<CompactFixture, String> {
        let text = std::fs::read_to_string(&p).map_err(|e| format!("{}: {e}", p.display()))?;
        CompactFixture::parse(&text).map_err(|e| format!("{}: {e}", p.display()))
    };
    let weights = read(repo.join("vit_tiny/weights.json"))?;
    let sd = StateDict::load(&dir.join("vit_tiny/weights.safetensors")).map_err(|e| e.to_string())?;
    let mut worst = 0.0f32;
    for name in sd.names() {
        let want = sd.f32(name).map_err(|e| e.to_string())?;
        let got = weights.get(name)?;
        if got.data != want {
            report.failures.push(format!("compact copy: weight `{name}` differs from the reference"));
            worst = f32::NAN;
        }
    }
    for variant in VARIANTS {
        let io = load_io(&dir.join(variant).join("io.json"))?;
        let copy = read(repo.join(variant).join("io.json"))?;
        for (name, a) in &copy.arrays {
            let want = array(&io, name)?;
            if a != &want {
                report.failures.push(format!("compact copy: {variant} `{name}` differs from the reference"));
                worst = f32::NAN;
            }
        }
    }
    report.rows.push(("compact copy in the repository (exact)".into(), worst));
    Ok(())
}

fn main() -> ExitCode {
    let mut args = std::env::args().skip(1);
    let dir = args.next().map(PathBuf::from).unwrap_or_else(|| PathBuf::from("../shared/fixtures"));
    let repo = args.next().map(PathBuf::from).unwrap_or_else(|| PathBuf::from("fixtures"));
    let mut report = Report { rows: Vec::new(), failures: Vec::new() };
    for variant in VARIANTS {
        let result = load_io(&dir.join(variant).join("io.json")).and_then(|io| {
            native(&dir, variant, &io, &mut report)?;
            onnx(&dir, variant, &io, &mut report)
        });
        if let Err(e) = result {
            report.failures.push(format!("{variant}: {e}"));
        }
    }
    if repo.join("vit_tiny/weights.json").exists() {
        if let Err(e) = compact_copy(&dir, &repo, &mut report) {
            report.failures.push(e);
        }
    }
    for (what, err) in &report.rows {
        println!("{what:<55} max |error| {err:.2e}");
    }
    if report.failures.is_empty() {
        println!("vit parity: {} checks passed (tolerance {TOL:e})", report.rows.len());
        ExitCode::SUCCESS
    } else {
        for f in &report.failures {
            eprintln!("FAIL {f}");
        }
        ExitCode::FAILURE
    }
}
