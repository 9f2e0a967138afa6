//! The `dino-vit` extractor against the reference fixtures (committed compact copy in
//! `fixtures/vit_tiny*`), its checkpoint readers on files written here, its errors, and (with
//! the `onnx` feature) the `onnx` extractor on the same network.

mod support;

use std::path::Path;

use sos_backbones::dino_vit::{
    feature_maps, Arch, CheckpointError, DinoVit, DinoVitConfig, Preprocess, StateDict, Vit, VitShape,
};
use sos_backbones::fixture::F32Array;
use sos_core::error::BuildError;
use sos_core::image::RgbImage;
use sos_core::plugin::{BuildContext, FeatureExtractor, FeatureExtractorConfig};
use support::writers::{pth_bytes, safetensors_bytes, write_pth, write_safetensors, PthOptions, PthTensor};
use support::{io, max_abs_diff, temp_dir, weights};

const TOL: f32 = 1e-4;
const VARIANTS: [&str; 2] = ["vit_tiny", "vit_tiny_sharp"];

/// The tiny fixture network has 2 heads of width 32 (DINO's default would be 64/64 = 1).
fn tiny_model(sd: &StateDict) -> Vit {
    let shape = VitShape::detect(sd, Some(2)).expect("tiny ViT shape");
    assert_eq!(shape, VitShape { patch: 16, dim: 64, depth: 2, heads: 2, mlp_hidden: 256, grid: 14 });
    Vit::from_state_dict(sd, shape).expect("tiny ViT loads")
}

/// Max errors of tokens, normed tokens and \[CLS\] attention at both fixture resolutions.
fn parity(model: &Vit, variant: &str) -> Vec<(String, f32)> {
    let inputs = io("vit_tiny");
    let expected = io(variant);
    let mut errors = Vec::new();
    for res in [224usize, 64] {
        let x = inputs.get(&format!("x{res}")).unwrap();
        let batch = x.shape[0];
        let out = model.forward(&x.data, batch, res, res);
        let normed = model.final_norm(&out.tokens);
        for (name, got) in [("tokens", &out.tokens), ("normed", &normed), ("cls_attn", &out.cls_attn)] {
            let want = expected.get(&format!("{name}{res}")).unwrap();
            assert_eq!(got.len(), want.numel(), "{variant} {name}{res} size");
            errors.push((format!("{variant} {name}{res}"), max_abs_diff(got, &want.data)));
        }
    }
    errors
}

fn assert_parity(errors: &[(String, f32)], how: &str) {
    for (what, err) in errors {
        eprintln!("{how}: {what}: max |error| {err:.2e}");
        assert!(*err <= TOL, "{how}: {what} differs from the reference by {err}");
    }
}

#[test]
fn native_forward_matches_the_reference_from_pth_and_safetensors() {
    let dir = temp_dir("parity");
    for variant in VARIANTS {
        let w = weights(variant);
        let pth = dir.join(format!("{variant}.pth"));
        let st = dir.join(format!("{variant}.safetensors"));
        write_pth(&pth, &w, &PthOptions::default());
        write_safetensors(&st, &w);
        let from_pth = tiny_model(&StateDict::load(&pth).unwrap());
        let from_st = tiny_model(&StateDict::load(&st).unwrap());
        assert_eq!(from_pth, from_st, "{variant}: both formats give the same model");
        assert_parity(&parity(&from_pth, variant), "native");
    }
    // The sharp variant's attention is peaked: the test exercises the softmax.
    let sharp = io("vit_tiny_sharp");
    let peak = sharp.get("cls_attn224").unwrap().data.iter().copied().fold(0.0f32, f32::max);
    assert!(peak > 0.05, "sharp [CLS] attention peak {peak}");
}

#[test]
fn batches_give_the_same_result_as_single_images() {
    let dir = temp_dir("batch");
    let path = dir.join("w.safetensors");
    write_safetensors(&path, &weights("vit_tiny_sharp"));
    let model = tiny_model(&StateDict::load(&path).unwrap());
    let x = io("vit_tiny").get("x64").unwrap().clone();
    let both = model.forward(&x.data, 2, 64, 64);
    let per = 3 * 64 * 64;
    for b in 0..2 {
        let one = model.forward(&x.data[b * per..(b + 1) * per], 1, 64, 64);
        let n = one.tokens.len();
        assert!(max_abs_diff(&one.tokens, &both.tokens[b * n..(b + 1) * n]) < 1e-5);
        assert!(max_abs_diff(&one.cls_attn, &both.cls_attn[b * 17..(b + 1) * 17]) < 1e-6);
    }
    // A non-square input with an interpolated grid: shapes, finite values, attention sums to 1.
    let img: Vec<f32> = (0..3 * 48 * 80).map(|i| ((i * 7919) % 1000) as f32 / 500.0 - 1.0).collect();
    let out = model.forward(&img, 1, 48, 80);
    assert_eq!((out.grid_h, out.grid_w, out.tokens.len()), (3, 5, 16 * 64));
    assert!(out.tokens.iter().all(|v| v.is_finite()));
    assert!((out.cls_attn.iter().sum::<f32>() - 1.0).abs() < 1e-5);
}

fn tiny_config(weights: &Path) -> DinoVitConfig {
    DinoVitConfig { weights: weights.into(), heads: Some(2), ..Default::default() }
}

#[test]
fn extractor_features_follow_the_reference_preprocessing() {
    let dir = temp_dir("extractor");
    let path = dir.join("tiny.pth");
    write_pth(&path, &weights("vit_tiny_sharp"), &PthOptions::default());
    let text = format!("kind = \"dino-vit\"\nweights = {:?}\nheads = 2\n", path.display().to_string());
    let cfg: Box<dyn FeatureExtractorConfig> = toml::from_str(&text).unwrap();
    let ex = cfg.build(&BuildContext::default()).unwrap();

    // A 64x64 rendered patch: resized to 224 through 384, normalised twice.
    let mut patch = RgbImage::new(64, 64);
    for r in 0..64 {
        for c in 0..64 {
            patch.set_pixel(c, r, [r as f32 / 63.0, c as f32 / 63.0, ((r * c) % 17) as f32 / 16.0]);
        }
    }
    let view = RgbImage { width: 250, height: 230, data: (0..250 * 230 * 3).map(|i| (i % 97) as f32 / 96.0).collect() };
    let maps = ex.extract(&[patch.clone(), view.clone(), RgbImage::new(0, 0), patch.clone()]).unwrap();
    assert_eq!(maps.len(), 4);
    let model = tiny_model(&StateDict::load(&path).unwrap());
    let pre = Preprocess { ..Preprocess::reference(16) };
    let t = pre.apply(&patch);
    assert_eq!((t.height, t.width), (224, 224));
    let want = &feature_maps(&model.forward(&t.data, 1, 224, 224))[0];
    let got = &maps[0];
    assert_eq!((got.channels, got.height, got.width), (64, 14, 14));
    assert!(max_abs_diff(&got.data, &want.data) < 1e-5);
    assert!(max_abs_diff(&got.cls, &want.cls) < 1e-5);
    let sal = got.saliency.as_ref().unwrap();
    assert_eq!(sal.len(), 196);
    assert!(max_abs_diff(sal, want.saliency.as_ref().unwrap()) < 1e-6);
    assert_eq!(&maps[3], got, "same patch, same features");
    // The whole view keeps its size (230x250 → 14x15 patches, position embedding interpolated).
    assert_eq!((maps[1].height, maps[1].width), (14, 15));
    let tv = pre.apply(&view);
    let want_view = &feature_maps(&model.forward(&tv.data, 1, tv.height, tv.width))[0];
    assert!(max_abs_diff(&maps[1].data, &want_view.data) < 1e-5);
    // An empty image gives a 1x1 map of zeros instead of failing.
    assert_eq!((maps[2].height, maps[2].width, maps[2].channels), (1, 1, 64));

    // Identity names the weights (by hash) and the settings.
    let id = ex.identity();
    assert!(id.starts_with("dino-vit/v1 weights="), "{id}");
    assert!(id.contains("dim=64 patch=16 depth=2 heads=2 input_size=224 resize=patches"), "{id}");
    let other = dir.join("other.pth");
    write_pth(&other, &weights("vit_tiny"), &PthOptions::default());
    let ex2 = tiny_config(&other).build(&BuildContext::default()).unwrap();
    assert_ne!(ex2.identity(), id, "other weights, other identity");
    let single =
        DinoVitConfig { double_normalize: false, ..tiny_config(&path) }.build(&BuildContext::default()).unwrap();
    assert!(single.identity().ends_with("double_normalize=false"));
    assert_ne!(single.extract(std::slice::from_ref(&patch)).unwrap()[0], *got);
}

#[test]
fn training_checkpoints_and_strided_tensors_are_read() {
    let dir = temp_dir("nested");
    let w = weights("vit_tiny");
    // DINO's full checkpoint layout: {"teacher": {"module.backbone.<name>": ...}, "epoch", "args"}.
    let path = dir.join("full_checkpoint.pth");
    let options = PthOptions { prefix: "dino_full".into(), as_training_checkpoint: true, ..Default::default() };
    write_pth(&path, &w, &options);
    let sd = StateDict::load(&path).unwrap();
    assert_eq!(sd.len(), w.len());
    assert!(sd.names().all(|n| !n.starts_with("module.")));
    let plain = dir.join("plain.pth");
    write_pth(&plain, &w, &PthOptions::default());
    assert_eq!(tiny_model(&sd), tiny_model(&StateDict::load(&plain).unwrap()));

    // A transposed view with an offset into a larger storage is gathered correctly.
    let (name, a) = w.iter().find(|(n, _)| n == "blocks.0.mlp.fc1.weight").unwrap();
    let mut tensors: Vec<PthTensor> = w.iter().map(|(n, a)| PthTensor::f32(n, a)).collect();
    let i = tensors.iter().position(|t| &t.name == name).unwrap();
    tensors[i] = PthTensor::f32_transposed_view(name, a, 5);
    let strided = dir.join("strided.pth");
    std::fs::write(&strided, pth_bytes(&tensors, &PthOptions::default())).unwrap();
    let sd = StateDict::load(&strided).unwrap();
    assert_eq!(sd.f32(name).unwrap(), a.data);
    assert_eq!(sd.entry(name).unwrap().stride, vec![1, 256]);
}

#[test]
fn relative_weights_resolve_against_the_config_folder() {
    let dir = temp_dir("relative");
    std::fs::create_dir_all(dir.join("models")).unwrap();
    write_pth(&dir.join("models/tiny.pth"), &weights("vit_tiny"), &PthOptions::default());
    let cfg = tiny_config(Path::new("models/tiny.pth"));
    // Found from the config's folder, whatever the working directory.
    let ex = cfg.build(&BuildContext::new(&dir)).unwrap();
    let absolute = tiny_config(&dir.join("models/tiny.pth")).build(&BuildContext::new("elsewhere")).unwrap();
    assert_eq!(ex.identity(), absolute.identity(), "absolute paths are kept as they are");
    // A missing relative file is named where it was looked for.
    let msg = match tiny_config(Path::new("models/absent.pth")).build(&BuildContext::new(&dir)) {
        Ok(_) => panic!("absent weights built"),
        Err(e) => e.to_string(),
    };
    assert!(
        msg.contains(&dir.join("models/absent.pth").display().to_string()) && msg.contains("config file's folder"),
        "{msg}"
    );
    std::fs::remove_dir_all(dir).ok();
}

fn build_error(cfg: &DinoVitConfig) -> String {
    match cfg.build(&BuildContext::default()) {
        Ok(_) => panic!("{:?} should not build", cfg.weights),
        Err(e) => e.to_string(),
    }
}

#[test]
fn missing_or_foreign_weights_are_refused_helpfully() {
    let dir = temp_dir("errors");
    // Missing file: where the official weights are and where to put them.
    let missing = dir.join("weights/dino_deitsmall16_pretrain.pth");
    let msg = build_error(&tiny_config(&missing));
    for part in [
        "not found",
        "dino_deitsmall16_pretrain.pth",
        "https://dl.fbaipublicfiles.com/dino/dino_deitsmall16_pretrain/dino_deitsmall16_pretrain.pth",
        "github.com/facebookresearch/dino",
        "`weights`",
        "cell-stats",
    ] {
        assert!(msg.contains(part), "missing-file message lacks {part:?}: {msg}");
    }
    assert!(msg.contains(&missing.display().to_string()), "{msg}");
    let vitb8 = build_error(&DinoVitConfig { arch: Arch::Vitb8, ..tiny_config(&missing) });
    assert!(vitb8.contains("dino_vitbase8_pretrain/dino_vitbase8_pretrain.pth"), "{vitb8}");

    let w = weights("vit_tiny");
    let good = pth_bytes(&w.iter().map(|(n, a)| PthTensor::f32(n, a)).collect::<Vec<_>>(), &PthOptions::default());
    let write = |name: &str, bytes: &[u8]| {
        let p = dir.join(name);
        std::fs::write(&p, bytes).unwrap();
        p
    };

    // Truncated download.
    let p = write("truncated.pth", &good[..good.len() / 2]);
    let msg = build_error(&tiny_config(&p));
    assert!(msg.contains("truncated") && msg.contains("truncated.pth"), "{msg}");
    assert!(msg.contains("dino_deitsmall16_pretrain.pth"), "{msg}");
    // An HTML page saved instead of the file.
    let p = write("page.pth", b"<!DOCTYPE html><html>Not Found</html>");
    assert!(build_error(&tiny_config(&p)).contains("not a PyTorch zip checkpoint"));
    // Re-zipped with compression.
    let compressed = pth_bytes(
        &w.iter().map(|(n, a)| PthTensor::f32(n, a)).collect::<Vec<_>>(),
        &PthOptions { claim_compressed: true, ..Default::default() },
    );
    let p = write("rezipped.pth", &compressed);
    assert!(build_error(&tiny_config(&p)).contains("compressed"));

    // A float16 tensor: named, with the fix.
    let mut tensors: Vec<PthTensor> = w.iter().map(|(n, a)| PthTensor::f32(n, a)).collect();
    let t = tensors.iter_mut().find(|t| t.name == "blocks.1.attn.qkv.weight").unwrap();
    t.storage_type = "HalfStorage".into();
    t.storage.truncate(t.storage.len() / 2);
    let p = write("half.pth", &pth_bytes(&tensors, &PthOptions::default()));
    let msg = build_error(&tiny_config(&p));
    assert!(
        msg.contains("blocks.1.attn.qkv.weight") && msg.contains("HalfStorage") && msg.contains("float32"),
        "{msg}"
    );
    let sd = StateDict::load(&p).unwrap();
    assert!(matches!(sd.f32("blocks.1.attn.qkv.weight"), Err(CheckpointError::DType { .. })));
    let st = safetensors_bytes(&w, |n| if n == "norm.weight" { "F16" } else { "F32" });
    let p = write("half.safetensors", &st);
    let msg = build_error(&tiny_config(&p));
    assert!(msg.contains("norm.weight") && msg.contains("F16"), "{msg}");

    // A state dict of another network.
    let resnet: Vec<(String, F32Array)> =
        [("conv1.weight", vec![64, 3, 7, 7]), ("bn1.weight", vec![64]), ("fc.weight", vec![10, 64])]
            .into_iter()
            .map(|(n, s)| (n.to_string(), F32Array { data: vec![0.5; s.iter().product()], shape: s }))
            .collect();
    let p = dir.join("resnet.pth");
    write_pth(&p, &resnet, &PthOptions::default());
    let msg = build_error(&tiny_config(&p));
    assert!(
        msg.contains("not a DINO ViT checkpoint") && msg.contains("cls_token") && msg.contains("conv1.weight"),
        "{msg}"
    );
    // A DINO ViT with a block tensor of the wrong shape.
    let mut broken = w.clone();
    broken.iter_mut().find(|(n, _)| n == "blocks.1.mlp.fc2.weight").unwrap().1.shape = vec![256, 64];
    let p = dir.join("broken.safetensors");
    write_safetensors(&p, &broken);
    let msg = build_error(&tiny_config(&p));
    assert!(msg.contains("not a DINO ViT checkpoint") && msg.contains("blocks.1.mlp.fc2.weight"), "{msg}");

    // A named architecture that the checkpoint is not.
    let p = dir.join("tiny.safetensors");
    write_safetensors(&p, &w);
    match (DinoVitConfig { arch: Arch::Vits16, ..tiny_config(&p) }).build(&BuildContext::default()) {
        Err(BuildError::Invalid { key, reason, .. }) => {
            assert_eq!(key, "arch");
            assert!(reason.contains("width 64") && reason.contains("vits16"), "{reason}");
        }
        other => panic!("expected an arch error, got {:?}", other.map(|e| e.identity())),
    }
    // Settings out of range name their key.
    for (cfg, key) in [
        (DinoVitConfig { batch: 0, ..tiny_config(&p) }, "batch"),
        (DinoVitConfig { input_size: 4, ..tiny_config(&p) }, "input_size"),
        // Within the general range, but smaller than one of this model's 16-px patches.
        (DinoVitConfig { input_size: 8, ..tiny_config(&p) }, "input_size"),
        (DinoVitConfig { heads: Some(0), ..tiny_config(&p) }, "heads"),
    ] {
        assert!(
            matches!(cfg.build(&BuildContext::default()), Err(BuildError::Invalid { key: k, .. }) if k == key),
            "{key}"
        );
    }
    // Unknown keys are rejected by name.
    let err = toml::from_str::<Box<dyn FeatureExtractorConfig>>("kind = \"dino-vit\"\nweight = \"x.pth\"").unwrap_err();
    assert!(err.to_string().contains("weight"), "{err}");
}

#[test]
fn registered_with_the_reference_defaults() {
    let reg = sos_core::registry::find::<dyn FeatureExtractorConfig>("dino-vit").expect("dino-vit is registered");
    assert!(reg.summary.contains("DINO"));
    let text = toml::to_string(&(reg.default_config)()).unwrap();
    for part in [
        "kind = \"dino-vit\"",
        "weights = \"weights/dino_deitsmall16_pretrain.pth\"",
        "arch = \"auto\"",
        "input_size = 224",
        "resize = \"patches\"",
        "reference_upsample = 384",
        "double_normalize = true",
    ] {
        assert!(text.contains(part), "default config lacks {part}: {text}");
    }
    // Without the weights the default refuses with the download hint (it never panics).
    if !Path::new("weights/dino_deitsmall16_pretrain.pth").exists() {
        let err = (reg.default_config)().build(&BuildContext::default()).err().expect("no weights here").to_string();
        assert!(err.contains("dl.fbaipublicfiles.com"), "{err}");
    }
    // A random ViT-S/16 has the reference's feature grid for a 64-px patch.
    let vit = Vit::random(VitShape::dino(384, 16, 1, 6), 3);
    let ex = DinoVit::new(vit, Preprocess::reference(16), "random".into(), 8);
    let maps = ex.extract(&[RgbImage::new(64, 64)]).unwrap();
    assert_eq!((maps[0].channels, maps[0].height, maps[0].width, maps[0].cls.len()), (384, 14, 14, 384));
}

#[cfg(feature = "onnx")]
mod onnx_runtime {
    //! Needs ONNX Runtime: `ORT_DYLIB_PATH` must point to `libonnxruntime.so*` (see
    //! backbones/README.md); without it these tests fail with that instruction.

    use super::*;
    use sos_backbones::dino_vit::onnx_export::write_vit;
    use sos_backbones::dino_vit::Resize;
    use sos_backbones::onnx::{OnnxConfig, OnnxExtractor, OnnxModel};

    fn tiny(variant: &str, dir: &Path) -> Vit {
        let p = dir.join(format!("{variant}.safetensors"));
        write_safetensors(&p, &weights(variant));
        tiny_model(&StateDict::load(&p).unwrap())
    }

    fn unwrap_build<T>(r: Result<T, BuildError>) -> T {
        r.unwrap_or_else(|e| panic!("{e}"))
    }

    #[test]
    fn exported_network_matches_the_reference_under_onnx_runtime() {
        let dir = temp_dir("onnx-parity");
        let x = io("vit_tiny").get("x224").unwrap().clone();
        for variant in VARIANTS {
            let model_path = dir.join(format!("{variant}.onnx"));
            write_vit(&tiny(variant, &dir), 224, None, &model_path).unwrap();
            let model = unwrap_build(OnnxModel::load(&model_path, None, "image", 2));
            let out = model.run(x.data.clone(), &[1, 3, 224, 224], &["tokens", "cls_attn"]).unwrap();
            let expected = io(variant);
            let errors = vec![
                (format!("{variant} tokens224"), max_abs_diff(&out[0].data, &expected.get("tokens224").unwrap().data)),
                (
                    format!("{variant} cls_attn224"),
                    max_abs_diff(&out[1].data, &expected.get("cls_attn224").unwrap().data),
                ),
            ];
            assert_eq!(out[0].dims, vec![1, 197, 64]);
            assert_parity(&errors, "onnx");
        }
    }

    #[test]
    fn onnx_extractor_agrees_with_the_native_one() {
        let dir = temp_dir("onnx-extractor");
        let vit = tiny("vit_tiny_sharp", &dir);
        let model_path = dir.join("tiny_b2.onnx");
        write_vit(&vit, 224, Some(2), &model_path).unwrap();
        let config = OnnxConfig {
            model: model_path.clone(),
            resize: Resize::Always,
            reference_upsample: 384,
            double_normalize: true,
            saliency: Some("cls_attn".into()),
            ..Default::default()
        };
        let onnx = unwrap_build(OnnxExtractor::new(config.clone()));
        let native = DinoVit::new(vit, Preprocess::reference(16), "x".into(), 8);
        let images: Vec<RgbImage> = (0..3)
            .map(|k| RgbImage {
                width: 64,
                height: 64,
                data: (0..64 * 64 * 3).map(|i| ((i * (k + 3)) % 101) as f32 / 100.0).collect(),
            })
            .collect();
        let (a, b) = (onnx.extract(&images).unwrap(), native.extract(&images).unwrap());
        for (x, y) in a.iter().zip(&b) {
            assert_eq!((x.channels, x.height, x.width), (y.channels, y.height, y.width));
            assert!(max_abs_diff(&x.data, &y.data) < TOL);
            assert!(max_abs_diff(&x.cls, &y.cls) < TOL);
            assert!(max_abs_diff(x.saliency.as_ref().unwrap(), y.saliency.as_ref().unwrap()) < TOL);
        }
        assert!(onnx.identity().starts_with("onnx/v1 model="));
        // Output names are checked against the model.
        let bad = OnnxConfig { saliency: Some("attention".into()), ..config.clone() };
        match OnnxExtractor::new(bad) {
            Err(BuildError::Invalid { key, reason, .. }) => {
                assert_eq!(key, "saliency");
                assert!(reason.contains("cls_attn"), "{reason}");
            }
            other => panic!("expected a saliency error, got {:?}", other.err()),
        }
    }

    #[test]
    fn missing_runtime_or_model_says_how_to_get_them() {
        let dir = temp_dir("onnx-missing");
        let model = dir.join("m.onnx");
        write_vit(&Vit::random(VitShape::dino(64, 16, 1, 2), 1), 64, Some(1), &model).unwrap();
        let cfg =
            OnnxConfig { model: model.clone(), runtime: Some(dir.join("libonnxruntime.so")), ..Default::default() };
        let msg = OnnxExtractor::new(cfg).err().expect("no runtime there").to_string();
        assert!(msg.contains("pip install onnxruntime") && msg.contains("ORT_DYLIB_PATH"), "{msg}");
        let cfg = OnnxConfig { model: dir.join("absent.onnx"), ..Default::default() };
        let msg = OnnxExtractor::new(cfg).err().expect("no model").to_string();
        assert!(msg.contains("absent.onnx") && msg.contains("not found") && msg.contains("export"), "{msg}");
    }
}
