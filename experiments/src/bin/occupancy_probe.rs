//! What the baked occupancy grid's one-cell margin costs a frozen field's views, and what
//! skipping without it changes. A frozen field skips empty space with a grid probed once per
//! cell and then dilated by one cell (`Session::bake_occupancy`); this compares, on one run's
//! checkpoint:
//! - the checkpoint's grid (one probe a cell, dilated);
//! - one probe a cell, not dilated;
//! - the maximum of 8 jittered probes a cell, not dilated (thin surfaces between probes are what
//!   the margin guards against);
//! - 8 probes, dilated.
//!
//! For each: the occupied share of the grid, candidates per ray of the first held-out view, a
//! view with its mask at WIDTHxHEIGHT (median of REPEATS), the pixels whose mask differs from the
//! checkpoint grid's, and the held-out PSNR, mIoU and NV-ARI as `sos eval` measures them.
//!
//! `cargo run --release --manifest-path experiments/Cargo.toml --bin occupancy_probe -- CONFIG CHECKPOINT [WIDTH HEIGHT] [REPEATS]`

use std::time::Instant;

use rand::SeedableRng;
use sos_core::render::occupancy::OccupancyGrid;
use sos_core::render::rays::RayBatch;
use sos_core::render::renderer::render;
use sos_core::segment::evaluate::evaluate_masks;
use sos_core::segment::infer::{saliency_extractor, MaskInference};
use sos_core::train::Session;
use sos_experiments::{args_or_usage, open_with_head};
use sos_plugins as _;

fn main() {
    sos_benchmarks::setup();
    let args = args_or_usage(2, "occupancy_probe CONFIG CHECKPOINT [WIDTH HEIGHT] [REPEATS]");
    let number = |i: usize, default: u32| args.get(i).map_or(default, |s| s.parse().expect("a number"));
    let (width, height, repeats) = (number(2, 504), number(3, 378), number(4, 3));
    let (mut session, head) = open_with_head(&args[0], &args[1]);
    let baked = session.occupancy.clone().expect("the run skips with an occupancy grid");

    let mut variants: Vec<(&str, OccupancyGrid)> = vec![("checkpoint (1 probe, dilated)", baked)];
    session.refresh_occupancy(0.0);
    variants.push(("1 probe, no margin", session.occupancy.clone().unwrap()));
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let t = Instant::now();
    for _ in 0..7 {
        let grid = session.occupancy.as_mut().unwrap();
        grid.update(session.field.as_ref(), &session.contraction, 1.0, &mut rng);
    }
    let probes_seconds = t.elapsed().as_secs_f64();
    let eight = session.occupancy.clone().unwrap();
    let mut eight_dilated = eight.clone();
    eight_dilated.dilate();
    variants.push(("8 probes, no margin", eight));
    variants.push(("8 probes, dilated", eight_dilated));
    println!("7 more probes a cell took {probes_seconds:.2} s");

    let mut reference: Option<Vec<bool>> = None;
    for (label, grid) in variants {
        let occupied = grid.occupancy();
        session.occupancy = Some(grid);
        let extractor = saliency_extractor(&session).expect("extractor");
        let inference = MaskInference::new(&session, &head, extractor.as_deref()).expect("inference");
        let (seconds, foreground) = timed_view(&session, &inference, width, height, repeats);
        let reference = reference.get_or_insert_with(|| foreground.clone());
        let differ = foreground.iter().zip(reference.iter()).filter(|(a, b)| a != b).count();
        let eval = evaluate_masks(&session, &inference, false).expect("held-out views");
        let json = serde_json::to_value(&eval).expect("serialisable");
        let seg = &json["segmentation"];
        println!(
            "{label}: occupied {:.1}%, {:.1} candidates a ray, view with mask {seconds:.3} s, mask differs in {differ} px; \
             held-out PSNR {:.3} dB, mIoU {:.4}, NV-ARI {:.4}",
            100.0 * occupied,
            candidates_per_ray(&session, width, height),
            eval.image.psnr_of_mean_mse().unwrap_or(f64::NAN),
            seg["miou"].as_f64().unwrap_or(f64::NAN),
            seg["mean_ari"].as_f64().unwrap_or(f64::NAN),
        );
    }
}

/// The median time of a view with its mask at `width`x`height`, and its foreground.
fn timed_view(session: &Session, inference: &MaskInference, width: u32, height: u32, repeats: u32) -> (f64, Vec<bool>) {
    let view = &session.scene.views[session.scene.test[0]];
    let camera = view.camera.resized(width, height);
    let mut times = Vec::new();
    let mut foreground = Vec::new();
    for _ in 0..repeats.max(1) {
        let t = Instant::now();
        foreground = inference.segment(&camera, &view.name).expect("mask").foreground;
        times.push(t.elapsed().as_secs_f64());
    }
    times.sort_by(f64::total_cmp);
    (times[times.len() / 2], foreground)
}

/// Candidates the march places per ray of the first held-out view.
fn candidates_per_ray(session: &Session, width: u32, height: u32) -> f64 {
    let camera = session.scene.views[session.scene.test[0]].camera.resized(width, height);
    let rays = RayBatch::full_image(&camera);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let mut candidates = 0usize;
    let mut start = 0;
    while start < rays.len() {
        let end = (start + session.config.render.chunk).min(rays.len());
        let r = render(
            session.field.as_ref(),
            session.render_context(),
            &rays.slice(start, end),
            session.render_options(false),
            false,
            &mut rng,
        );
        candidates += r.timing.candidates;
        start = end;
    }
    candidates as f64 / rays.len() as f64
}
