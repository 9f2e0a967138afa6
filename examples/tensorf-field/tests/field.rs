//! The `tensorf` field's own checks: dfdx's gradients against finite differences on every
//! tensor, determinism over blocks and threads, samples outside the cube, growth, saved
//! states and the config.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use sos_core::camera::Vec3;
use sos_core::error::{BuildError, StateError};
use sos_core::plugin::{RadianceField, RadianceFieldConfig};
use sos_core::render::contraction::Contraction;
use sos_core::scene::SceneExtent;
use sos_example_tensorf::{TensorfConfig, TensorfField};

fn unit_box() -> SceneExtent {
    SceneExtent::Bounded { min: [-1.0; 3], max: [1.0; 3] }
}

/// A field small enough to check every tensor, with an opacity and initial values large
/// enough that every part of the graph has a sizeable gradient.
fn tiny() -> TensorfConfig {
    TensorfConfig {
        resolution: [5, 6, 7],
        initial_resolution: [5, 6, 7],
        upsample_at: vec![],
        density_components: 2,
        appearance_components: 3,
        features: 4,
        hidden: 5,
        view_frequencies: 1,
        alpha_init: 0.3,
        init_scale: 0.5,
        ..Default::default()
    }
}

fn build(config: &TensorfConfig, seed: u64) -> TensorfField {
    config.validate().expect("valid config");
    TensorfField::new(config.clone(), Contraction::new(&unit_box()), &unit_box(), seed)
}

fn samples(n: usize, seed: u64) -> (Vec<Vec3>, Vec<Vec3>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let p = (0..n).map(|_| [0; 3].map(|_| rng.gen_range(-0.95f32..0.95))).collect();
    let d = (0..n)
        .map(|_| {
            let v = [0; 3].map(|_| rng.gen_range(-1.0f32..1.0));
            let norm = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-3);
            v.map(|x| x / norm)
        })
        .collect();
    (p, d)
}

fn forward(field: &dyn RadianceField, p: &[Vec3], d: &[Vec3]) -> (Vec<f32>, Vec<[f32; 3]>) {
    let mut sigma = vec![0.0; p.len()];
    let mut rgb = vec![[0.0; 3]; p.len()];
    field.forward(p, d, &mut sigma, &mut rgb, false);
    (sigma, rgb)
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

#[test]
fn gradients_match_finite_differences_in_every_tensor() {
    let mut field = build(&tiny(), 3);
    let (p, d) = samples(40, 1);
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let a: Vec<f32> = (0..p.len()).map(|_| rng.gen_range(-1.0..1.0)).collect();
    let b: Vec<[f32; 3]> = (0..p.len()).map(|_| [0; 3].map(|_| rng.gen_range(-1.0..1.0))).collect();
    let loss = |f: &TensorfField| -> f64 {
        let (s, c) = forward(f, &p, &d);
        let ds: f64 = s.iter().zip(&a).map(|(&s, &w)| s as f64 * w as f64).sum();
        let dc: f64 = c.iter().zip(&b).flat_map(|(c, w)| c.iter().zip(w).map(|(&c, &w)| c as f64 * w as f64)).sum();
        ds + dc
    };
    field.backward(&p, &d, None, &a, &b);
    let grads = field.gradients();
    let theta = field.parameters();
    let mut offset = 0;
    for (name, [rows, cols]) in field.tensor_shapes() {
        let range = offset..offset + rows * cols;
        offset = range.end;
        // The three largest gradients of the tensor and one drawn at random.
        let mut idx: Vec<usize> = range.clone().collect();
        idx.sort_by(|&i, &j| grads[j].abs().total_cmp(&grads[i].abs()));
        idx.truncate(3);
        idx.push(rng.gen_range(range.clone()));
        assert!(grads[idx[0]] != 0.0, "{name}: no gradient at all");
        let (mut err, mut norm) = (0.0f64, 0.0f64);
        for &i in &idx {
            let h = 1e-2 * theta[i].abs().max(0.1);
            let mut shifted = theta.clone();
            shifted[i] = theta[i] + h;
            field.set_parameters(&shifted).unwrap();
            let up = loss(&field);
            shifted[i] = theta[i] - h;
            field.set_parameters(&shifted).unwrap();
            let down = loss(&field);
            let fd = (up - down) / (2.0 * h as f64);
            err += (fd - grads[i] as f64).powi(2);
            norm += (grads[i] as f64).powi(2);
        }
        field.set_parameters(&theta).unwrap();
        let (err, norm) = (err.sqrt(), norm.sqrt());
        assert!(err <= 0.02 * norm + 1e-4, "{name}: |fd - g| = {err:.3e} against |g| = {norm:.3e}");
    }
    assert_eq!(offset, field.num_parameters());
}

#[test]
fn results_do_not_depend_on_blocks_calls_or_threads() {
    // More samples than one block, so calls split inside and across blocks.
    let field = build(&tiny(), 5);
    let (p, d) = samples(5000, 7);
    let on = |threads: usize, split: usize| {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        pool.install(|| {
            let (mut s, mut c) = forward(&field, &p[..split], &d[..split]);
            let (s2, c2) = forward(&field, &p[split..], &d[split..]);
            s.extend(s2);
            c.extend(c2);
            (s, c)
        })
    };
    let (s1, c1) = on(1, 0);
    for (threads, split) in [(2, 0), (2, 1000), (1, 2049), (2, 4999)] {
        let (s, c) = on(threads, split);
        assert_eq!(bits(&s), bits(&s1), "density with {threads} threads, split at {split}");
        assert_eq!(bits(c.as_flattened()), bits(c1.as_flattened()), "colour with {threads} threads, split at {split}");
    }
    let mut cheap = vec![0.0; p.len()];
    field.density(&p, &mut cheap);
    assert_eq!(bits(&cheap), bits(&s1), "density() and forward() agree bit for bit");
    // The gradient sums over blocks in block order: the same on any thread count.
    let grads_on = |threads: usize| {
        let mut f = build(&tiny(), 5);
        let (a, b) = (vec![0.3; p.len()], vec![[0.1, -0.2, 0.4]; p.len()]);
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        pool.install(|| f.backward(&p, &d, None, &a, &b));
        f.gradients()
    };
    assert_eq!(bits(&grads_on(1)), bits(&grads_on(2)), "gradients differ between 1 and 2 threads");
}

#[test]
fn samples_outside_the_cube_are_empty_and_get_no_gradient() {
    let mut field = build(&tiny(), 1);
    let p = vec![[1.5, 0.0, 0.0], [0.0, -1.01, 0.2], [f32::NAN, 0.0, 0.0]];
    let d = vec![[0.0, 0.0, 1.0]; 3];
    let (s, c) = forward(&field, &p, &d);
    assert_eq!(s, vec![0.0; 3]);
    assert_eq!(c, vec![[0.0; 3]; 3]);
    field.backward(&p, &d, None, &[1.0; 3], &[[1.0; 3]; 3]);
    assert!(field.gradients().iter().all(|&g| g == 0.0));
    let mut seg = vec![f32::NAN; 3 * field.seg_input_dim()];
    field.seg_input(&p[..2], &mut seg[..2 * field.seg_input_dim()]);
    assert!(seg[..2 * field.seg_input_dim()].iter().all(|v| v.is_finite()));
}

#[test]
fn a_few_steps_fit_a_target() {
    let mut field = build(&TensorfConfig { lr_network: 0.05, ..tiny() }, 2);
    let (p, d) = samples(200, 3);
    let target = [0.9f32, 0.2, 0.1];
    let loss_and_grad = |f: &TensorfField| {
        let (_, c) = forward(f, &p, &d);
        let loss: f32 = c.iter().flat_map(|c| (0..3).map(move |k| (c[k] - target[k]).powi(2))).sum();
        let g: Vec<[f32; 3]> = c.iter().map(|c| std::array::from_fn(|k| 2.0 * (c[k] - target[k]))).collect();
        (loss, g)
    };
    let (first, _) = loss_and_grad(&field);
    for _ in 0..30 {
        let (_, g) = loss_and_grad(&field);
        field.backward(&p, &d, None, &vec![0.0; p.len()], &g);
        assert!(field.gradients_finite());
        field.step(1.0);
    }
    let (last, _) = loss_and_grad(&field);
    assert!(last < 0.1 * first, "colour loss {first} -> {last}");
}

#[test]
fn growth_resamples_without_changing_the_field_at_shared_vertices() {
    let config =
        TensorfConfig { resolution: [5, 5, 9], initial_resolution: [3, 3, 5], upsample_at: vec![0.5], ..tiny() };
    let mut field = build(&config, 4);
    assert_eq!(field.resolution(), [3, 3, 5]);
    let growing = field.coarse_to_fine_mut().expect("the field grows");
    assert!((growing.detail_fraction() - 11.0 / 19.0).abs() < 1e-6);
    assert!(!growing.begin_step(4, 10));
    // Vertices of the coarse grid are vertices of the fine one: the field is unchanged there.
    let p: Vec<Vec3> = (0..27).map(|i| [i % 3, (i / 3) % 3, i / 9].map(|k| -1.0 + k as f32)).collect();
    let d = vec![[0.0, 0.0, 1.0]; p.len()];
    let (before, before_rgb) = forward(&field, &p, &d);
    assert!(field.coarse_to_fine_mut().unwrap().begin_step(5, 10));
    assert_eq!(field.resolution(), [5, 5, 9]);
    assert_eq!(field.coarse_to_fine().unwrap().detail_fraction(), 1.0);
    let (after, after_rgb) = forward(&field, &p, &d);
    for i in 0..p.len() {
        assert!((before[i] - after[i]).abs() <= 1e-4 * before[i].abs().max(1.0), "density at {:?}", p[i]);
        for k in 0..3 {
            assert!((before_rgb[i][k] - after_rgb[i][k]).abs() <= 1e-4, "colour at {:?}", p[i]);
        }
    }
    // A grown state loads into a fresh (coarse) field at its own resolution.
    let mut fresh = build(&config, 9);
    fresh.load_state(&field.save_state()).unwrap();
    assert_eq!(fresh.resolution(), [5, 5, 9]);
    assert_eq!(bits(&fresh.parameters()), bits(&field.parameters()));
    assert!(!fresh.coarse_to_fine_mut().unwrap().begin_step(9, 10), "the growth count is restored");
}

#[test]
fn states_round_trip_and_damaged_ones_are_refused() {
    let field = build(&tiny(), 1);
    let state = field.save_state();
    let mut other = build(&tiny(), 2);
    assert_ne!(bits(&other.parameters()), bits(&field.parameters()));
    other.load_state(&state).unwrap();
    assert_eq!(bits(&other.parameters()), bits(&field.parameters()));
    for cut in [0, 5, 20, state.len() - 1] {
        assert!(matches!(other.load_state(&state[..cut]), Err(StateError::Truncated { .. })), "cut at {cut}");
    }
    let mut longer = state.clone();
    longer.extend_from_slice(&[0; 4]);
    assert!(matches!(other.load_state(&longer), Err(StateError::Malformed { .. })));
    let mut wider = build(&TensorfConfig { appearance_components: 4, ..tiny() }, 1);
    match wider.load_state(&state) {
        Err(StateError::Mismatch { reason, .. }) => assert!(reason.contains("appearance_plane_xy"), "{reason}"),
        other => panic!("expected a mismatch, got {other:?}"),
    }
    assert!(other.set_parameters(&[0.0; 3]).is_err());
}

#[test]
fn config_reads_from_toml_and_invalid_keys_are_named() {
    let config: TensorfConfig = toml::from_str("resolution = [16, 16, 8]\nhidden = 32").unwrap();
    assert_eq!(config.resolution, [16, 16, 8]);
    assert_eq!(config.hidden, 32);
    assert_eq!(config.features, TensorfConfig::default().features);
    assert!(toml::from_str::<TensorfConfig>("resolutoin = [16, 16, 16]").is_err(), "unknown keys are refused");
    for (config, key) in [
        (TensorfConfig { resolution: [1, 8, 8], ..Default::default() }, "resolution"),
        (TensorfConfig { initial_resolution: [256, 8, 8], ..Default::default() }, "initial_resolution"),
        (TensorfConfig { upsample_at: vec![0.5, 0.2], ..Default::default() }, "upsample_at"),
        (TensorfConfig { appearance_components: 0, ..Default::default() }, "appearance_components"),
        (TensorfConfig { alpha_init: 1.0, ..Default::default() }, "alpha_init"),
        (TensorfConfig { lr_grid: -0.1, ..Default::default() }, "lr_grid"),
    ] {
        match config.build(&unit_box(), 0) {
            Err(BuildError::Invalid { key: k, .. }) => assert_eq!(k, key),
            Err(e) => panic!("unexpected error {e}"),
            Ok(_) => panic!("{key} should be refused"),
        }
    }
    assert_eq!(TensorfConfig::KIND, "tensorf");
}
