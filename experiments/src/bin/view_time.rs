//! Where the time of one view with its mask goes. Renders the first held-out view of a run at a
//! chosen size (504x378 by default, the size of LLFF's `images_8`) and prints:
//! - the colour render with inference-time skipping (early termination, a weight threshold)
//!   against the render without it: seconds, PSNR between the two, rays whose visible surface
//!   moved;
//! - the phases of a view with logits (march, density pass, filter, full pass, compositing,
//!   head, logit sums), with candidates, kept samples and head samples per ray;
//! - how spread out each ray's compositing weight is (samples holding 90/99/99.9% of it, and the
//!   weighted standard deviation of the sample distances);
//! - the whole view with its mask, as `sos` infers it.
//!
//! `VIEW_ONLY=1` times only the whole view with its mask (for a profiler).
//!
//! `cargo run --release --manifest-path experiments/Cargo.toml --bin view_time -- CONFIG CHECKPOINT [WIDTH HEIGHT] [REPEATS]`

use std::time::Instant;

use rand::SeedableRng;
use sos_core::camera::Camera;
use sos_core::render::density_pass::stop_depth;
use sos_core::render::rays::RayBatch;
use sos_core::render::renderer::{render, render_inference, RenderOptions, Rendered};
use sos_core::segment::head::SegHead;
use sos_core::segment::head_pass;
use sos_core::segment::infer::{render_logits, saliency_extractor, MaskInference};
use sos_core::train::Session;
use sos_experiments::{args_or_usage, open_with_head};
use sos_plugins as _;

fn main() {
    sos_benchmarks::setup();
    let args = args_or_usage(2, "view_time CONFIG CHECKPOINT [WIDTH HEIGHT] [REPEATS]");
    let number = |i: usize, default: u32| args.get(i).map_or(default, |s| s.parse().expect("a number"));
    let (width, height, repeats) = (number(2, 504), number(3, 378), number(4, 3));
    let (session, head) = open_with_head(&args[0], &args[1]);
    let view = &session.scene.views[session.scene.test[0]];
    let camera = view.camera.resized(width, height);
    let extractor = saliency_extractor(&session).expect("extractor");
    let inference = MaskInference::new(&session, &head, extractor.as_deref()).expect("inference");
    // `VIEW_ONLY=1`: only the whole view with its mask, `repeats` times (for a profiler).
    if std::env::var_os("VIEW_ONLY").is_some() {
        for _ in 0..repeats {
            let t = Instant::now();
            inference.segment(&camera, &view.name).expect("mask");
            println!("{width}x{height}: view with mask {:.3} s", t.elapsed().as_secs_f64());
        }
        return;
    }
    colour_with_skipping(&session, &camera);
    for _ in 0..repeats {
        phases(&session, &head, &camera);
        let t = Instant::now();
        let logits = render_logits(&session, &head, &camera);
        let render = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let mask = inference.segment(&camera, &view.name).expect("mask");
        let whole = t.elapsed().as_secs_f64();
        println!(
            "{width}x{height}: render with logits {render:.3} s ({:.0} rays/s), view with mask {whole:.3} s, {} foreground pixels, {} logit channels",
            (width * height) as f64 / render,
            mask.foreground.iter().filter(|&&f| f).count(),
            logits.channels
        );
    }
}

/// Colour renders with inference-time skipping against the render without it.
fn colour_with_skipping(session: &Session, camera: &Camera) {
    let rays = RayBatch::full_image(camera);
    let base = session.render_options(false);
    let settings =
        [(base.early_stop, 0.0), (base.early_stop, 1e-4), (base.early_stop, 1e-3), (1e-3, 1e-3), (1e-2, 1e-3)];
    let mut reference = None;
    for (early_stop, min_weight) in settings {
        let options = RenderOptions { early_stop, min_weight, ..base };
        let t = Instant::now();
        let ctx = session.render_context();
        let (colours, _) =
            render_inference(session.field.as_ref(), ctx, &rays, options, session.config.render.chunk, None);
        let seconds = t.elapsed().as_secs_f64();
        let reference = reference.get_or_insert_with(|| colours.clone());
        let squared: f64 = colours
            .iter()
            .zip(reference.iter())
            .map(|(a, b)| (0..3).map(|k| ((a.rgb[k] - b.rgb[k]) as f64).powi(2)).sum::<f64>())
            .sum();
        let psnr = -10.0 * (squared / (3.0 * colours.len() as f64)).max(1e-20).log10();
        let moved = colours
            .iter()
            .zip(reference.iter())
            .filter(|(a, b)| (a.median_depth - b.median_depth).abs() > 0.01 * b.median_depth.abs())
            .count();
        println!(
            "early_stop {early_stop:e}, min_weight {min_weight:e}: colour {seconds:.3} s, {psnr:.1} dB against the first, {moved} rays whose surface moved by over 1%"
        );
    }
}

/// The phases of a view with logits (as `render_logits` runs them), timed one by one, and the
/// spread of the compositing weights.
fn phases(session: &Session, head: &SegHead, camera: &Camera) {
    let rays = RayBatch::full_image(camera);
    let min_weight = session.config.masks.head_min_weight.unwrap_or(session.config.segment.weight_threshold);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let mut seconds = [0.0f64; 7];
    let (mut candidates, mut kept, mut to_head) = (0usize, 0usize, 0usize);
    // March steps up to each ray's termination (all of them for rays that never terminate).
    let mut march_steps = (0usize, 0usize);
    let steps = session.render_options(false).march.steps;
    let stop_at = stop_depth(session.config.train.early_stop);
    let mut spread = WeightSpread::default();
    let mut start = 0;
    while start < rays.len() {
        let end = (start + session.config.render.chunk).min(rays.len());
        let ctx = session.render_context();
        let mut r = render(
            session.field.as_ref(),
            ctx,
            &rays.slice(start, end),
            session.render_options(false),
            false,
            &mut rng,
        );
        for (s, t) in seconds.iter_mut().zip([r.timing.march, r.timing.density, r.timing.filter, r.timing.forward]) {
            *s += t;
        }
        candidates += r.timing.candidates;
        kept += r.timing.kept;
        for ray in 0..r.samples.n_rays() {
            let range = r.samples.range(ray);
            let optical: f32 = range.clone().map(|k| r.density[k] * r.samples.delta[k]).sum();
            march_steps.1 += steps;
            march_steps.0 += match range.last() {
                Some(last) if optical > stop_at => (r.samples.s[last] * steps as f32) as usize + 1,
                _ => steps,
            };
        }
        let t = Instant::now();
        r.composite();
        seconds[4] += t.elapsed().as_secs_f64();
        spread.add(&r);
        let t = Instant::now();
        let positions: Vec<[f32; 3]> =
            (0..r.samples.len()).filter(|&k| r.weights[k] > min_weight).map(|k| r.samples.positions[k]).collect();
        to_head += positions.len();
        let values = head_pass::sample_logits(session.field.as_ref(), head, &positions);
        seconds[5] += t.elapsed().as_secs_f64();
        let t = Instant::now();
        let _ = r.composite_values(&values, head.outputs(), |k| r.weights[k] > min_weight);
        seconds[6] += t.elapsed().as_secs_f64();
        start = end;
    }
    let n = rays.len() as f64;
    let [march, density, filter, forward, composite, head_s, sums] = seconds;
    println!(
        "phases: march {march:.3} s, density {density:.3} s, filter {filter:.3} s, full pass {forward:.3} s, composite {composite:.3} s, head {head_s:.3} s, logit sums {sums:.3} s; per ray {:.1} candidates, {:.1} kept, {:.1} to the head",
        candidates as f64 / n,
        kept as f64 / n,
        to_head as f64 / n
    );
    spread.print(n);
    println!("march steps up to termination: {:.1}% of all", 100.0 * march_steps.0 as f64 / march_steps.1 as f64);
}

/// How many samples hold most of each ray's weight, and how far apart they lie.
#[derive(Default)]
struct WeightSpread {
    /// Samples holding 90%, 99% and 99.9% of the weight, summed over rays.
    holding: [usize; 3],
    /// Weighted standard deviation of the sample distances, the mean distance and the step, per
    /// ray of opacity over one half.
    deviations: Vec<(f32, f32, f32)>,
}

impl WeightSpread {
    fn add(&mut self, r: &Rendered) {
        for ray in 0..r.samples.n_rays() {
            let range = r.samples.range(ray);
            let (w, t) = (&r.weights[range.clone()], &r.samples.t[range.clone()]);
            let mut sorted = w.to_vec();
            sorted.sort_by(|a, b| b.total_cmp(a));
            let total: f32 = sorted.iter().sum();
            for (q, share) in [0.9f32, 0.99, 0.999].into_iter().enumerate() {
                let (mut sum, mut needed) = (0.0, 0);
                while needed < sorted.len() && sum < share * total {
                    sum += sorted[needed];
                    needed += 1;
                }
                self.holding[q] += needed;
            }
            if total > 0.5 {
                let mean = w.iter().zip(t).map(|(w, t)| w * t).sum::<f32>() / total;
                let var = w.iter().zip(t).map(|(w, t)| w * (t - mean) * (t - mean)).sum::<f32>() / total;
                self.deviations.push((var.sqrt(), mean, r.samples.delta[range.start]));
            }
        }
    }

    fn print(&mut self, rays: f64) {
        let [a, b, c] = self.holding.map(|h| h as f64 / rays);
        println!("samples per ray holding 90% / 99% / 99.9% of its weight: {a:.1} / {b:.1} / {c:.1}");
        self.deviations.sort_by(|a, b| a.0.total_cmp(&b.0));
        for q in [0.25, 0.5, 0.75, 0.9] {
            let Some(&(sd, mean, step)) = self.deviations.get(((self.deviations.len().max(1) - 1) as f64 * q) as usize)
            else {
                continue;
            };
            println!("quantile {q} of the weight's spread: {sd:.3} at distance {mean:.3} (step {step:.4})");
        }
    }
}
