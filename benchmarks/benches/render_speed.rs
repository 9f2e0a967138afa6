//! Rays per second when rendering full held-out views of the built-in synthetic scene after a
//! short stage-1 fit (so the occupancy grid and early termination see realistic geometry).
//!
//! `cargo run --release -p sos-benchmarks --bin render_speed [stage-1 steps]`

use std::path::Path;
use std::time::Instant;

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

fn main() {
    sos_benchmarks::allocate_like_sos();
    let steps: usize = std::env::args().nth(1).and_then(|s| s.parse().ok()).unwrap_or(800);
    let mut config = RunConfig::parse(CONFIG, Path::new("render_speed.toml")).expect("built-in config parses");
    config.train.steps = steps;
    let dir = std::env::temp_dir().join("sos-render-speed");
    let mut session = Session::from_config(config, &dir).expect("synthetic scene builds");
    let started = Instant::now();
    let stats = train_photometric(&mut session).expect("training runs");
    println!(
        "stage 1: {steps} steps in {:.1} s (last batch PSNR {:.2} dB)",
        started.elapsed().as_secs_f64(),
        stats.psnr
    );
    let mut rays = 0usize;
    let started = Instant::now();
    for &i in &session.scene.test {
        let cam = &session.scene.views[i].camera;
        let (img, _) = session.render_view(cam);
        rays += img.width * img.height;
    }
    let seconds = started.elapsed().as_secs_f64();
    println!(
        "render: {} held-out views of {}x{} = {rays} rays in {seconds:.2} s -> {:.0} rays/s",
        session.scene.test.len(),
        session.scene.views[0].camera.width,
        session.scene.views[0].camera.height,
        rays as f64 / seconds
    );
    std::fs::remove_dir_all(&dir).ok();
}
