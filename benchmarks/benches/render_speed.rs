//! Rays per second when rendering full held-out views of the built-in synthetic scene after a
//! short stage-1 fit (so the occupancy grid and early termination see realistic geometry).
//!
//! Group `render_speed`, benchmark `held_out_views`: one pass over every held-out view. The fit
//! (`RENDER_SPEED_STEPS` stage-1 steps, default 800) runs once, before and outside the timing.
//! Criterion's throughput is rays (elements per second); after the group a summary prints the
//! views, their rays and rays/s from criterion's median.
//!
//! `cargo bench -p sos-benchmarks --bench render_speed`; threads: `RAYON_NUM_THREADS` (default 2).

use std::path::Path;
use std::time::Instant;

use criterion::{criterion_group, criterion_main, Criterion, SamplingMode, Throughput};
use sos_benchmarks::GroupResults;
use sos_core::config::RunConfig;
use sos_core::train::photometric::train_photometric;
use sos_core::train::Session;

// Force-link the plugins so their registrations exist.
use sos_plugins as _;

const CONFIG: &str = r#"
name = "render-speed"
output_dir = "runs"
[scene]
kind = "synthetic"
rig = "object-centric"
[field]
kind = "voxel-grid"
[train]
checkpoint_every = 0
[segment]
steps = 0
"#;

fn bench(c: &mut Criterion) {
    let threads = sos_benchmarks::setup();
    let steps: usize = std::env::var("RENDER_SPEED_STEPS").ok().and_then(|s| s.parse().ok()).unwrap_or(800);
    let mut config = RunConfig::parse(CONFIG, Path::new("render_speed.toml")).expect("built-in config parses");
    config.train.steps = steps;
    let dir = std::env::temp_dir().join(format!("sos-render-speed-{}", std::process::id()));
    let mut session = Session::from_config(config, &dir).expect("synthetic scene builds");
    let started = Instant::now();
    let stats = train_photometric(&mut session).expect("training runs");
    println!(
        "render_speed: stage 1, {steps} steps in {:.1} s (last batch PSNR {:.2} dB), {threads} rayon threads",
        started.elapsed().as_secs_f64(),
        stats.psnr
    );
    let views = &session.scene.test;
    let rays: usize = views
        .iter()
        .map(|&i| {
            let camera = &session.scene.views[i].camera;
            camera.width as usize * camera.height as usize
        })
        .sum();

    let results = GroupResults::new("render_speed");
    let mut group = c.benchmark_group("render_speed");
    group.sampling_mode(SamplingMode::Flat).throughput(Throughput::Elements(rays as u64));
    group.bench_function("held_out_views", |b| {
        b.iter(|| {
            for &i in views {
                std::hint::black_box(session.render_view(&session.scene.views[i].camera));
            }
        })
    });
    group.finish();

    if let Some(seconds) = results.median("held_out_views") {
        let camera = &session.scene.views[0].camera;
        println!(
            "render: {} held-out views of {}x{} = {rays} rays in {seconds:.2} s -> {:.0} rays/s (criterion median)",
            views.len(),
            camera.width,
            camera.height,
            rays as f64 / seconds
        );
    }
    std::fs::remove_dir_all(&dir).ok();
}

criterion_group! {
    name = benches;
    config = sos_benchmarks::criterion(10, 5.0, 70.0);
    targets = bench
}
criterion_main!(benches);
