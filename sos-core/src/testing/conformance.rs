//! The conformance suite: what every implementation of a plugin role must do, checked on any
//! registered kind without a list of kinds to edit. A plugin crate runs it from a test:
//!
//! ```text
//! use my_plugin as _; // links the kinds
//! use sos_plugins as _; // the built-in teacher, miner, losses and datasets a run needs
//!
//! #[test]
//! fn my_field_conforms() {
//!     sos_core::testing::conformance::check_field_kind("my-field");
//! }
//! ```
//!
//! Every check panics with the kind and what broke, so a failing plugin shows as a failing
//! test. A kind whose default config needs a resource that is absent (teacher weights) is
//! reported on stderr as not checkable here rather than failed: the resource, not the code, is
//! missing.

use std::path::Path;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::camera::Vec3;
use crate::config::RunConfig;
use crate::error::BuildError;
use crate::image::RgbImage;
use crate::plugin::field::plain;
use crate::plugin::{
    BuildContext, ContrastiveLossConfig, DatasetConfig, FeatureExtractorConfig, PairMinerConfig, PatchBatch,
    RadianceField, RadianceFieldConfig,
};
use crate::registry::{find, registrations};
use crate::scene::SceneExtent;

/// Samples every field check evaluates (small: the finite-difference check runs the forward
/// pass twice per checked parameter).
const SAMPLES: usize = 48;
/// Parameters whose gradient is compared with a finite difference: the largest gradients (where
/// a wrong backward shows first) and a few drawn at random.
const CHECKED_LARGEST: usize = 24;
const CHECKED_RANDOM: usize = 8;

/// The extent every field check builds for: the unit box around the origin.
fn unit_box() -> SceneExtent {
    SceneExtent::Bounded { min: [-1.0; 3], max: [1.0; 3] }
}

/// Runs every check on every registered kind of every role.
pub fn check_all() {
    let fields: Vec<_> = registrations::<dyn RadianceFieldConfig>().iter().map(|r| r.kind).collect();
    assert!(!fields.is_empty(), "no radiance field is linked: add `use sos_plugins as _;`");
    for kind in fields {
        check_field_kind(kind);
    }
    for r in registrations::<dyn FeatureExtractorConfig>() {
        check_extractor_kind(r.kind);
    }
    for r in registrations::<dyn PairMinerConfig>() {
        check_miner_kind(r.kind);
    }
    for r in registrations::<dyn ContrastiveLossConfig>() {
        check_loss_kind(r.kind);
    }
    for r in registrations::<dyn DatasetConfig>() {
        check_dataset_kind(r.kind);
    }
}

/// A dataset's default config, pointed at an empty folder, either opens a valid scene (a
/// generator) or fails with an error that says what is missing: never a panic.
pub fn check_dataset_kind(kind: &str) {
    let registration = find::<dyn DatasetConfig>(kind).unwrap_or_else(|| panic!("no dataset `{kind}` is registered"));
    let config = (registration.default_config)();
    let empty = std::env::temp_dir().join(format!("sos-conformance-empty-{}-{kind}", std::process::id()));
    std::fs::create_dir_all(&empty).expect("a temporary folder");
    let opened = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| config.open(&empty)));
    let _ = std::fs::remove_dir_all(&empty);
    match opened {
        Err(_) => panic!("dataset `{kind}`: opening its default config in an empty folder panics"),
        Ok(Ok(scene)) => {
            if let Err(e) = scene.validate() {
                panic!("dataset `{kind}`: its default scene is invalid: {e}");
            }
        }
        Ok(Err(e)) => assert!(!e.to_string().trim().is_empty(), "dataset `{kind}`: an error without a message"),
    }
}

/// Every field check on the registered kind's default config, then a few-step two-stage run
/// on a tiny built-in scene with the head attached.
pub fn check_field_kind(kind: &str) {
    let registration = find::<dyn RadianceFieldConfig>(kind)
        .unwrap_or_else(|| panic!("no radiance field `{kind}` is registered (is its crate linked?)"));
    let config = (registration.default_config)();
    round_trips_through_toml(kind, &*config);
    let started = std::time::Instant::now();
    check_field(kind, &*config);
    // The same field with every capability hidden: the core's plain path must carry it.
    let bare = format!("{kind} without capabilities");
    check_built(&bare, &|seed| Box::new(Bare(build_for_checks(kind, &*config, seed))));
    let checked = started.elapsed().as_secs_f64();
    check_two_stage_run(kind, &*config, false);
    check_two_stage_run(kind, &*config, true);
    eprintln!(
        "conformance: field `{kind}`: checks {checked:.1} s, two-stage runs with and without capabilities {:.1} s",
        started.elapsed().as_secs_f64() - checked
    );
}

/// `[field]` alone, to read a config back.
#[derive(serde::Deserialize)]
struct FieldTable {
    field: Box<dyn RadianceFieldConfig>,
}

/// A field config written as a run config's `[field]` table.
fn field_table(kind: &str, config: &dyn RadianceFieldConfig) -> String {
    #[derive(serde::Serialize)]
    struct Table<'a> {
        field: &'a dyn RadianceFieldConfig,
    }
    toml::to_string(&Table { field: config }).unwrap_or_else(|e| panic!("{kind}: config does not serialise: {e}"))
}

/// The default config written as TOML reads back to the same TOML.
fn round_trips_through_toml(kind: &str, config: &dyn RadianceFieldConfig) {
    let text = field_table(kind, config);
    let back: FieldTable = toml::from_str(&text)
        .unwrap_or_else(|e| panic!("{kind}: its own default config does not read back:\n{text}\n{e}"));
    assert_eq!(text, field_table(kind, &*back.field), "{kind}: default config changes through TOML");
}

/// The field checks on one config: shapes and finiteness, gradients against finite
/// differences, the gradient hooks, the step, save/load, determinism and every capability.
pub fn check_field(kind: &str, config: &dyn RadianceFieldConfig) {
    check_built(kind, &|seed| build_for_checks(kind, config, seed));
}

fn build_for_checks(kind: &str, config: &dyn RadianceFieldConfig, seed: u64) -> Box<dyn RadianceField> {
    config.build(&unit_box(), seed).unwrap_or_else(|e| panic!("{kind}: default config does not build: {e}"))
}

/// The field checks on fields `build` makes from a seed.
fn check_built(kind: &str, build: &dyn Fn(u64) -> Box<dyn RadianceField>) {
    let mut field = build(0);
    let (positions, directions) = samples(7);
    outputs_have_their_shapes_and_are_finite(kind, field.as_ref(), &positions, &directions);
    determinism(kind, field.as_ref(), &*build(0), &positions, &directions);
    gradients_match_finite_differences(kind, field.as_mut(), &positions, &directions);
    gradient_hooks(kind, field.as_mut(), &positions, &directions);
    state_round_trips(kind, field.as_ref(), &mut *build(1), &positions, &directions);
    // Last: a growing field is at full size afterwards.
    capabilities_equal_the_plain_path(kind, field.as_mut(), &positions, &directions);
}

/// Points spread through the unit box and unit directions, from a fixed seed.
fn samples(seed: u64) -> (Vec<Vec3>, Vec<Vec3>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let positions = (0..SAMPLES).map(|_| [0; 3].map(|_| rng.gen_range(-0.9f32..0.9))).collect();
    let directions = (0..SAMPLES)
        .map(|_| loop {
            let d = [0; 3].map(|_| rng.gen_range(-1.0f32..1.0));
            let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            if n > 0.1 {
                break d.map(|v| v / n);
            }
        })
        .collect();
    (positions, directions)
}

struct Outputs {
    density: Vec<f32>,
    rgb: Vec<[f32; 3]>,
}

fn forward(field: &dyn RadianceField, p: &[Vec3], d: &[Vec3]) -> Outputs {
    let mut density = vec![0.0; p.len()];
    let mut rgb = vec![[0.0; 3]; p.len()];
    let tape = field.forward(p, d, &mut density, &mut rgb, false);
    drop(tape);
    Outputs { density, rgb }
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

fn rgb_bits(v: &[[f32; 3]]) -> Vec<u32> {
    v.iter().flatten().map(|x| x.to_bits()).collect()
}

fn outputs_have_their_shapes_and_are_finite(kind: &str, field: &dyn RadianceField, p: &[Vec3], d: &[Vec3]) {
    let out = forward(field, p, d);
    for (i, (&sigma, c)) in out.density.iter().zip(&out.rgb).enumerate() {
        assert!(
            sigma.is_finite() && sigma >= 0.0,
            "{kind}: density of sample {i} is {sigma} (must be finite and >= 0)"
        );
        assert!(
            c.iter().all(|v| v.is_finite() && (0.0..=1.0).contains(v)),
            "{kind}: colour of sample {i} is {c:?} (must lie in [0, 1])"
        );
    }
    let mut cheap = vec![0.0; p.len()];
    field.density(p, &mut cheap);
    for (i, (&a, &b)) in cheap.iter().zip(&out.density).enumerate() {
        assert!(
            (a - b).abs() <= 1e-5 * (1.0 + a.abs().max(b.abs())),
            "{kind}: density() and forward() disagree at sample {i}: {a} against {b}"
        );
    }
    let dim = field.seg_input_dim();
    assert!(dim > 0, "{kind}: the segmentation input must have at least one channel");
    let mut seg = vec![f32::NAN; p.len() * dim];
    field.seg_input(p, &mut seg);
    assert!(seg.iter().all(|v| v.is_finite()), "{kind}: the segmentation input is not finite (or not fully written)");
    assert_eq!(field.parameters().len(), field.num_parameters(), "{kind}: parameters() and num_parameters() disagree");
    assert_eq!(field.gradients().len(), field.num_parameters(), "{kind}: gradients() is not laid out as parameters()");
    // The empty batch is a valid call.
    field.density(&[], &mut []);
    let _ = field.forward(&[], &[], &mut [], &mut [], false);
}

/// Seeded builds agree; results depend neither on the thread count nor on how samples are
/// split into calls.
fn determinism(kind: &str, field: &dyn RadianceField, twin: &dyn RadianceField, p: &[Vec3], d: &[Vec3]) {
    assert_eq!(bits(&field.parameters()), bits(&twin.parameters()), "{kind}: two builds from one seed differ");
    let on = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("a thread pool");
        pool.install(|| forward(field, p, d))
    };
    let (one, two) = (on(1), on(2));
    assert_eq!(bits(&one.density), bits(&two.density), "{kind}: density differs between 1 and 2 threads");
    assert_eq!(rgb_bits(&one.rgb), rgb_bits(&two.rgb), "{kind}: colour differs between 1 and 2 threads");
    let half = p.len() / 2;
    let (a, b) = (forward(field, &p[..half], &d[..half]), forward(field, &p[half..], &d[half..]));
    let split: Vec<f32> = a.density.iter().chain(&b.density).copied().collect();
    assert_eq!(bits(&split), bits(&one.density), "{kind}: density depends on how samples are split into calls");
    let split_rgb: Vec<[f32; 3]> = a.rgb.iter().chain(&b.rgb).copied().collect();
    assert_eq!(rgb_bits(&split_rgb), rgb_bits(&one.rgb), "{kind}: colour depends on how samples are split into calls");
}

/// Every capability a field offers equals the plain path bit for bit, and behaves as its
/// trait documents.
fn capabilities_equal_the_plain_path(kind: &str, field: &mut dyn RadianceField, p: &[Vec3], d: &[Vec3]) {
    let n = p.len();
    let plain_out = forward(field, p, d);
    let dim = field.seg_input_dim();
    let mut plain_seg = vec![0.0; n * dim];
    field.seg_input(p, &mut plain_seg);
    if let Some(fast) = field.frozen_pass() {
        let (mut density, mut rgb, mut seg) = (vec![0.0; n], vec![[0.0; 3]; n], vec![0.0; n * dim]);
        fast.forward_with_seg_input(p, d, &mut density, &mut rgb, &mut seg);
        assert_eq!(
            bits(&density),
            bits(&plain_out.density),
            "{kind}: fused forward_with_seg_input changes the density"
        );
        assert_eq!(rgb_bits(&rgb), rgb_bits(&plain_out.rgb), "{kind}: fused forward_with_seg_input changes the colour");
        assert_eq!(bits(&seg), bits(&plain_seg), "{kind}: fused forward_with_seg_input changes the segmentation input");
        let width = fast.density_state_dim();
        if width > 0 {
            let (mut density, mut state) = (vec![0.0; n], vec![0.0; n * width]);
            fast.density_with_state(p, &mut density, &mut state);
            let mut cheap = vec![0.0; n];
            field.density(p, &mut cheap);
            assert_eq!(bits(&density), bits(&cheap), "{kind}: density_with_state changes the density");
            // Every other sample, read through row indices.
            let rows: Vec<u32> = (0..n as u32).step_by(2).collect();
            let pick = |v: &[Vec3]| rows.iter().map(|&r| v[r as usize]).collect::<Vec<_>>();
            let (sp, sd) = (pick(p), pick(d));
            let (mut rgb, mut seg) = (vec![[0.0; 3]; rows.len()], vec![0.0; rows.len() * dim]);
            fast.colour_from_state(&sp, &sd, &state, &rows, &mut rgb, Some(&mut seg));
            let want_rgb: Vec<[f32; 3]> = rows.iter().map(|&r| plain_out.rgb[r as usize]).collect();
            let want_seg: Vec<f32> = rows
                .iter()
                .flat_map(|&r| plain_seg[r as usize * dim..(r as usize + 1) * dim].iter().copied())
                .collect();
            assert_eq!(rgb_bits(&rgb), rgb_bits(&want_rgb), "{kind}: colour_from_state changes the colour");
            assert_eq!(bits(&seg), bits(&want_seg), "{kind}: colour_from_state changes the segmentation input");
        }
    }
    if let Some(h) = field.hierarchical() {
        let s = h.sampling();
        assert!(s.coarse_samples > 0, "{kind}: hierarchical sampling with no proposal samples");
        if let Some(proposal) = h.proposal() {
            outputs_have_their_shapes_and_are_finite(&format!("{kind} (proposal)"), proposal, p, d);
        }
    }
    if let Some(growing) = field.coarse_to_fine() {
        let start = growing.detail_fraction();
        assert!(start > 0.0 && start <= 1.0, "{kind}: detail_fraction {start} outside (0, 1]");
        let total = 10;
        let mut last = start;
        for step in 0..total {
            plain::begin_step(field, step, total);
            let now = plain::detail_fraction(field);
            assert!(now >= last && now <= 1.0, "{kind}: detail_fraction went from {last} to {now} at step {step}");
            last = now;
        }
        outputs_have_their_shapes_and_are_finite(&format!("{kind} (grown)"), field, p, d);
    }
    if field.regularized().is_some() {
        let (positions, directions) = (p.to_vec(), d.to_vec());
        backward_of_weighted_sum(field, &positions, &directions, &loss_weights(n));
        let value = plain::regularize(field);
        assert!(value.is_finite() && value >= 0.0, "{kind}: regulariser value {value}");
        assert!(field.gradients_finite(), "{kind}: the regulariser made the gradients non-finite");
        field.discard_gradients();
    }
}

/// Fixed weights of the scalar `L = Σ a·density + Σ b·rgb` the gradient checks differentiate.
fn loss_weights(n: usize) -> (Vec<f32>, Vec<[f32; 3]>) {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let a = (0..n).map(|_| rng.gen_range(-1.0f32..1.0)).collect();
    let b = (0..n).map(|_| [0; 3].map(|_| rng.gen_range(-1.0f32..1.0))).collect();
    (a, b)
}

fn weighted_sum(field: &dyn RadianceField, p: &[Vec3], d: &[Vec3], (a, b): &(Vec<f32>, Vec<[f32; 3]>)) -> f64 {
    let out = forward(field, p, d);
    let density: f64 = out.density.iter().zip(a).map(|(&s, &w)| s as f64 * w as f64).sum();
    let colour: f64 =
        out.rgb.iter().zip(b).flat_map(|(c, w)| c.iter().zip(w).map(|(&c, &w)| c as f64 * w as f64)).sum();
    density + colour
}

fn backward_of_weighted_sum(field: &mut dyn RadianceField, p: &[Vec3], d: &[Vec3], (a, b): &(Vec<f32>, Vec<[f32; 3]>)) {
    let (mut density, mut rgb) = (vec![0.0; p.len()], vec![[0.0; 3]; p.len()]);
    let tape = field.forward(p, d, &mut density, &mut rgb, true);
    field.backward(p, d, tape, a, b);
}

/// `backward` against central finite differences of `L = Σ a·density + Σ b·rgb`, on the
/// parameters with the largest gradients and a few random ones, compared normwise: an f32
/// forward pass carries rounding of order ε·Σ|terms| in `L`, and activation kinks between
/// `θ ± h` bend single entries, which a normwise bound tolerates and a wrong backward does not.
fn gradients_match_finite_differences(kind: &str, field: &mut dyn RadianceField, p: &[Vec3], d: &[Vec3]) {
    let weights = loss_weights(p.len());
    field.discard_gradients();
    backward_of_weighted_sum(field, p, d, &weights);
    let grads = field.gradients();
    assert!(grads.iter().all(|g| g.is_finite()), "{kind}: non-finite gradients on an ordinary batch");
    assert!(field.gradients_finite(), "{kind}: gradients_finite() says no on finite gradients");
    assert!(grads.iter().any(|&g| g != 0.0), "{kind}: backward wrote no gradient at all");
    let theta = field.parameters();
    let mut order: Vec<usize> = (0..grads.len()).collect();
    order.sort_by(|&i, &j| grads[j].abs().total_cmp(&grads[i].abs()));
    let mut checked: Vec<usize> = order.iter().copied().take(CHECKED_LARGEST).collect();
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    for _ in 0..CHECKED_RANDOM {
        checked.push(rng.gen_range(0..grads.len()));
    }
    let (mut err, mut norm) = (0.0f64, 0.0f64);
    let mut worst = (0, 0.0f64, 0.0f64);
    for &i in &checked {
        let h = 1e-2 * theta[i].abs().max(0.1);
        let mut shifted = theta.clone();
        shifted[i] = theta[i] + h;
        field.set_parameters(&shifted).unwrap_or_else(|e| panic!("{kind}: set_parameters refuses its own layout: {e}"));
        let up = weighted_sum(field, p, d, &weights);
        let high = shifted[i];
        shifted[i] = theta[i] - h;
        field.set_parameters(&shifted).expect("same layout");
        let down = weighted_sum(field, p, d, &weights);
        // The step actually taken, after rounding to f32.
        let fd = (up - down) / (high as f64 - shifted[i] as f64);
        let g = grads[i] as f64;
        if (fd - g).abs() > worst.1 {
            worst = (i, (fd - g).abs(), fd);
        }
        err += (fd - g) * (fd - g);
        norm += g * g;
    }
    field.set_parameters(&theta).expect("same layout");
    let (err, norm) = (err.sqrt(), norm.sqrt());
    assert!(
        err <= 0.05 * norm + 1e-4,
        "{kind}: gradients disagree with finite differences: |fd - g| = {err:.3e} against |g| = {norm:.3e} \
         (worst: parameter {} with g = {:.4e}, fd = {:.4e})",
        worst.0,
        grads[worst.0],
        worst.2
    );
    field.discard_gradients();
}

/// `gradients_finite` sees a NaN, `discard_gradients` drops it, `step` applies and clears.
fn gradient_hooks(kind: &str, field: &mut dyn RadianceField, p: &[Vec3], d: &[Vec3]) {
    let n = p.len();
    let poisoned = (vec![f32::NAN; n], vec![[f32::NAN; 3]; n]);
    backward_of_weighted_sum(field, p, d, &poisoned);
    assert!(!field.gradients_finite(), "{kind}: gradients_finite() misses a NaN gradient");
    field.discard_gradients();
    assert!(field.gradients_finite(), "{kind}: discard_gradients() leaves non-finite gradients");
    assert!(field.gradients().iter().all(|&g| g == 0.0), "{kind}: discard_gradients() leaves gradients behind");
    let before = field.parameters();
    backward_of_weighted_sum(field, p, d, &loss_weights(n));
    field.step(1.0);
    assert!(field.gradients().iter().all(|&g| g == 0.0), "{kind}: step() does not clear the gradients");
    let after = field.parameters();
    assert!(after.iter().all(|v| v.is_finite()), "{kind}: step() made a parameter non-finite");
    assert_ne!(bits(&before), bits(&after), "{kind}: step() changed no parameter");
}

/// save_state → load_state into a differently seeded field restores it bit for bit; damaged
/// states are refused with an error, never a panic.
fn state_round_trips(kind: &str, field: &dyn RadianceField, other: &mut dyn RadianceField, p: &[Vec3], d: &[Vec3]) {
    let state = field.save_state();
    other.load_state(&state).unwrap_or_else(|e| panic!("{kind}: its own state does not load: {e}"));
    assert_eq!(bits(&other.parameters()), bits(&field.parameters()), "{kind}: parameters change through save/load");
    let (a, b) = (forward(field, p, d), forward(other, p, d));
    assert_eq!(bits(&a.density), bits(&b.density), "{kind}: a loaded field renders another density");
    assert_eq!(rgb_bits(&a.rgb), rgb_bits(&b.rgb), "{kind}: a loaded field renders another colour");
    for cut in [0, state.len() / 2, state.len().saturating_sub(1)] {
        if cut < state.len() {
            assert!(
                other.load_state(&state[..cut]).is_err(),
                "{kind}: a state cut at byte {cut} of {} loads",
                state.len()
            );
        }
    }
    let wrong = vec![0.5; field.num_parameters() + 1];
    assert!(other.set_parameters(&wrong).is_err(), "{kind}: set_parameters accepts a vector of the wrong length");
    // The check a restored checkpoint gets finds the first bad parameter where
    // `parameters()` has it.
    let mut theta = field.parameters();
    assert_eq!(other.first_non_finite_parameter(), None, "{kind}: a finite field reports a non-finite parameter");
    let last = theta.len().checked_sub(1);
    for (i, bad) in last.into_iter().flat_map(|last| [(last, f32::INFINITY), (last / 2, f32::NAN)]) {
        theta[i] = bad;
        other.set_parameters(&theta).expect("same layout");
        assert_eq!(other.first_non_finite_parameter(), Some(i), "{kind}: parameter {i} set to {bad} is not found");
    }
}

/// A few steps of both stages on a tiny built-in scene with the field's default config: the
/// segmentation head attaches, its logits and a held-out mask come out whole and finite.
fn check_two_stage_run(kind: &str, config: &dyn RadianceFieldConfig, hide_capabilities: bool) {
    if find::<dyn DatasetConfig>("synthetic").is_none() {
        panic!("{kind}: the built-in `synthetic` scene is not linked: add `use sos_plugins as _;` to the test");
    }
    let field_toml = field_table(kind, config);
    let dir = std::env::temp_dir().join(format!("sos-conformance-{}-{kind}-{hide_capabilities}", std::process::id()));
    let text = format!(
        "name = \"conformance\"\noutput_dir = {:?}\n\
         [scene]\nkind = \"synthetic\"\nwidth = 24\nheight = 18\nviews = 4\nhold_out_every = 2\n\
         [train]\nsteps = 3\nrays_per_step = 32\nsamples_per_ray = 64\ncheckpoint_every = 0\noccupancy_resolution = 16\n\
         [segment]\nsteps = 2\npatches = 2\npatch_size = 8\nstride = 1\n\n{field_toml}",
        dir.display().to_string()
    );
    let run_config =
        RunConfig::parse(&text, Path::new("conformance.toml")).unwrap_or_else(|e| panic!("{kind}: {e}\n{text}"));
    let mut session = crate::train::Session::from_config(run_config, Path::new(""))
        .unwrap_or_else(|e| panic!("{kind}: a run cannot start: {e}"));
    if hide_capabilities {
        let field = config.build(&session.scene.extent, session.config.seed).expect("built once already");
        session.field = Box::new(Bare(field));
    }
    crate::train::photometric::train_photometric(&mut session).unwrap_or_else(|e| panic!("{kind}: stage 1 fails: {e}"));
    let mut seg = crate::segment::train::Segmenter::build(&session)
        .unwrap_or_else(|e| panic!("{kind}: stage 2 cannot start: {e}"));
    let stats = crate::segment::train::train_segmentation(&mut session, &mut seg)
        .unwrap_or_else(|e| panic!("{kind}: stage 2 fails: {e}"));
    assert!(stats.total.is_finite(), "{kind}: stage-2 loss {}", stats.total);
    let view = session.scene.test.first().copied().unwrap_or(0);
    let camera = session.scene.views[view].camera.clone();
    let logits = crate::segment::infer::render_logits(&session, &seg.head, &camera);
    assert!(logits.logits.iter().all(|v| v.is_finite()), "{kind}: rendered segmentation logits are not finite");
    let inference = crate::segment::infer::MaskInference::new(&session, &seg.head, None)
        .unwrap_or_else(|e| panic!("{kind}: mask inference cannot start: {e}"));
    let mask = inference.segment(&camera, "conformance").unwrap_or_else(|e| panic!("{kind}: no mask: {e}"));
    let image = mask.mask_image();
    assert_eq!((image.width, image.height), (camera.width as usize, camera.height as usize), "{kind}: mask size");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Where default configs' relative resource paths (teacher weights) resolve: the folder named
/// by `SOS_CONFORMANCE_CONFIG_DIR`, so a CI step that has fetched weights can check those
/// teachers too, or the working directory.
fn resource_context() -> BuildContext {
    std::env::var_os("SOS_CONFORMANCE_CONFIG_DIR").map(BuildContext::new).unwrap_or_default()
}

/// Builds a kind's default config, or reports on stderr that a resource it needs is absent.
fn build_or_report<T>(role: &str, kind: &str, built: Result<T, BuildError>) -> Option<T> {
    match built {
        Ok(v) => Some(v),
        Err(BuildError::Resource { message, .. }) => {
            eprintln!("conformance: {role} `{kind}` not checkable here: {message}");
            None
        }
        Err(e) => panic!("{role} `{kind}`: default config does not build: {e}"),
    }
}

/// A teacher's default config accepts the settings it derives for 64-ray patches, builds (or
/// names the missing resource), and its features have the documented shapes, are finite and
/// reproduce on 1 and 2 threads.
pub fn check_extractor_kind(kind: &str) {
    let registration =
        find::<dyn FeatureExtractorConfig>(kind).unwrap_or_else(|| panic!("no extractor `{kind}` is registered"));
    let mut config = (registration.default_config)();
    let patch = crate::derived::PatchFacts { patch_size: 64, stride: 6, views_look_one_way: false };
    config.derive_for(&patch);
    if let Err(e) = config.check_for(&patch) {
        panic!("extractor `{kind}`: the settings it derives for 64-ray patches are refused: {e}");
    }
    let Some(extractor) = build_or_report("extractor", kind, config.build(&resource_context())) else {
        return;
    };
    let images: Vec<RgbImage> = (0..2)
        .map(|k| {
            let mut im = RgbImage::new(64 + 8 * k, 48);
            for (i, v) in im.data.iter_mut().enumerate() {
                *v = ((i * 37 + k * 11) % 101) as f32 / 100.0;
            }
            im
        })
        .collect();
    let on = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("a thread pool");
        pool.install(|| extractor.extract(&images)).unwrap_or_else(|e| panic!("extractor `{kind}`: {e}"))
    };
    let (one, two) = (on(1), on(2));
    assert_eq!(one.len(), images.len(), "extractor `{kind}`: one map per image");
    for (m, m2) in one.iter().zip(&two) {
        assert_eq!(
            m.data.len(),
            m.channels * m.height * m.width,
            "extractor `{kind}`: data is not [channels, height, width]"
        );
        assert!(m.channels > 0 && m.height > 0 && m.width > 0, "extractor `{kind}`: empty feature map");
        assert!(m.data.iter().chain(&m.cls).all(|v| v.is_finite()), "extractor `{kind}`: non-finite features");
        if let Some(s) = &m.saliency {
            assert_eq!(s.len(), m.height * m.width, "extractor `{kind}`: saliency is not [height, width]");
        }
        assert_eq!(m, m2, "extractor `{kind}`: features differ between 1 and 2 threads");
    }
    assert!(!extractor.identity().is_empty(), "extractor `{kind}`: empty identity (the cache key)");
}

/// A miner's default config builds; each patch gets a valid partner, reproducibly per seed.
pub fn check_miner_kind(kind: &str) {
    let registration = find::<dyn PairMinerConfig>(kind).unwrap_or_else(|| panic!("no miner `{kind}` is registered"));
    let Some(miner) = build_or_report("miner", kind, (registration.default_config)().build()) else {
        return;
    };
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let cls: Vec<Vec<f32>> = (0..6).map(|_| (0..8).map(|_| rng.gen_range(-1.0f32..1.0)).collect()).collect();
    let pick = || miner.negatives(&cls, &mut ChaCha8Rng::seed_from_u64(9));
    let negatives = pick();
    assert_eq!(negatives.len(), cls.len(), "miner `{kind}`: one negative per patch");
    assert!(negatives.iter().all(|&j| j < cls.len()), "miner `{kind}`: a negative outside the batch");
    assert_eq!(negatives, pick(), "miner `{kind}`: not reproducible from its seed");
    // Degenerate input: zero-norm and identical descriptors still give valid partners.
    let zeros = vec![vec![0.0; 8]; 4];
    let n = miner.negatives(&zeros, &mut ChaCha8Rng::seed_from_u64(9));
    assert!(n.len() == 4 && n.iter().all(|&j| j < 4), "miner `{kind}`: zero descriptors break it");
}

/// A loss's default config builds; on a random batch its value and gradient are finite, the
/// gradient matches finite differences of the value, and it reproduces per seed.
pub fn check_loss_kind(kind: &str) {
    let registration =
        find::<dyn ContrastiveLossConfig>(kind).unwrap_or_else(|| panic!("no loss `{kind}` is registered"));
    let Some(loss) = build_or_report("loss", kind, (registration.default_config)().build()) else {
        return;
    };
    let (n_patches, patch, d_seg) = (2, 4, 2);
    let rays = patch * patch;
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let logits: Vec<f32> = (0..n_patches * d_seg * rays).map(|_| rng.gen_range(-2.0f32..2.0)).collect();
    let points: Vec<f32> = (0..n_patches * 3 * rays).map(|_| rng.gen_range(-1.0f32..1.0)).collect();
    let features: Vec<crate::plugin::FeatureMap> = (0..n_patches)
        .map(|_| crate::plugin::FeatureMap {
            channels: 3,
            height: patch,
            width: patch,
            data: (0..3 * rays).map(|_| rng.gen_range(-1.0f32..1.0)).collect(),
            cls: vec![1.0, 0.0],
            saliency: None,
        })
        .collect();
    let negatives = vec![1, 0];
    let value = |logits: &[f32], grad: &mut [f32]| {
        let batch =
            PatchBatch { n_patches, patch, d_seg, logits, points: &points, features: &features, negatives: &negatives };
        loss.loss_and_grad(&batch, &mut ChaCha8Rng::seed_from_u64(4), 1.0, grad)
    };
    let mut grad = vec![0.0; logits.len()];
    let v = value(&logits, &mut grad);
    assert!(v.total.is_finite() && v.terms.iter().all(|t| t.1.is_finite()), "loss `{kind}`: non-finite value {v:?}");
    assert!(grad.iter().all(|g| g.is_finite()), "loss `{kind}`: non-finite gradient");
    let mut again = vec![0.0; logits.len()];
    assert_eq!(
        value(&logits, &mut again).total.to_bits(),
        v.total.to_bits(),
        "loss `{kind}`: not reproducible from its seed"
    );
    let (mut err, mut norm) = (0.0f64, 0.0f64);
    let mut scratch = vec![0.0; logits.len()];
    // The loss is computed in f64 from f32 logits: a small step keeps the clamps' kinks
    // (STEGO clamps correlations at 0) out of nearly every difference.
    for i in 0..logits.len() {
        let h = 1e-3f32;
        let mut shifted = logits.clone();
        shifted[i] = logits[i] + h;
        let up = value(&shifted, &mut scratch).total;
        let step = shifted[i];
        shifted[i] = logits[i] - h;
        let down = value(&shifted, &mut scratch).total;
        let fd = (up - down) / (step as f64 - shifted[i] as f64);
        err += (fd - grad[i] as f64).powi(2);
        norm += (grad[i] as f64).powi(2);
    }
    let (err, norm) = (err.sqrt(), norm.sqrt());
    assert!(
        err <= 0.05 * norm + 1e-4,
        "loss `{kind}`: gradient disagrees with finite differences ({err:.3e} against {norm:.3e})"
    );
}

/// A field seen through its required methods only: every capability getter keeps its default
/// (`None`), so the core takes its plain path.
struct Bare(Box<dyn RadianceField>);

impl RadianceField for Bare {
    crate::pass_on_field_methods!(0);

    fn forward(
        &self,
        positions: &[Vec3],
        directions: &[Vec3],
        density: &mut [f32],
        rgb: &mut [[f32; 3]],
        record: bool,
    ) -> crate::plugin::FieldTape {
        self.0.forward(positions, directions, density, rgb, record)
    }
    fn backward(
        &mut self,
        positions: &[Vec3],
        directions: &[Vec3],
        tape: crate::plugin::FieldTape,
        grad_density: &[f32],
        grad_rgb: &[[f32; 3]],
    ) {
        self.0.backward(positions, directions, tape, grad_density, grad_rgb)
    }
    fn step(&mut self, lr_factor: f32) {
        self.0.step(lr_factor)
    }
}
