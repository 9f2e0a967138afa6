//! Where a trained field spends its samples, per held-out view of a checkpoint: the share of
//! occupied cells, candidates and kept samples per ray, samples above the head's weight
//! threshold (1e-3), held-out PSNR, and the fog in front of each opaque ray's surface (the
//! weight before 95% of its median depth, in five bins of depth / median depth). With an
//! `ALPHA`, the occupancy grid is baked anew at that opacity per candidate step first, to see
//! what a coarser skip of a frozen field costs and saves.
//!
//! `cargo run --release --manifest-path experiments/Cargo.toml --bin fog_probe -- CONFIG CHECKPOINT [ALPHA]`

use rand::SeedableRng;
use sos_core::metrics::psnr_from_mse;
use sos_core::render::occupancy::OccupancyGrid;
use sos_core::render::rays::RayBatch;
use sos_core::render::renderer::{render, Rendered};
use sos_core::train::Session;
use sos_plugins as _;

/// Weight below which the head is not run (`segment.weight_threshold`'s default).
const HEAD_THRESHOLD: f32 = 1e-3;
/// Bins of depth / median depth over [0, 0.95) for the fog's position along the ray.
const FOG_BINS: usize = 5;

/// Sums over one view's rays.
#[derive(Default)]
struct ViewStats {
    rays: usize,
    squared_error: f64,
    candidates: usize,
    kept: usize,
    above_threshold: usize,
    opaque: usize,
    fog: [f64; FOG_BINS],
}

impl ViewStats {
    fn add(&mut self, r: &Rendered, targets: &[[f32; 3]]) {
        self.candidates += r.n_candidates;
        for (ray, target) in targets.iter().enumerate() {
            self.rays += 1;
            let c = r.colours[ray].rgb;
            self.squared_error += (0..3).map(|j| f64::from(c[j] - target[j]).powi(2)).sum::<f64>();
            let range = r.samples.range(ray);
            let weights = &r.weights[range.clone()];
            self.kept += weights.len();
            self.above_threshold += weights.iter().filter(|&&w| w > HEAD_THRESHOLD).count();
            let total: f32 = weights.iter().sum();
            if total <= 0.5 {
                continue;
            }
            self.opaque += 1;
            let mut acc = 0.0;
            let median = range
                .clone()
                .find(|&k| {
                    acc += r.weights[k];
                    acc >= 0.5 * total
                })
                .map_or(f32::MAX, |k| r.samples.t[k]);
            for k in range {
                let f = r.samples.t[k] / median;
                if f < 0.95 {
                    self.fog[((f / 0.95 * FOG_BINS as f32) as usize).min(FOG_BINS - 1)] += f64::from(r.weights[k]);
                }
            }
        }
    }
}

fn main() {
    sos_benchmarks::setup();
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (config, checkpoint) = match &args[..] {
        [c, k] | [c, k, _] => (c, k),
        _ => {
            eprintln!("usage: fog_probe CONFIG CHECKPOINT [ALPHA]");
            std::process::exit(2);
        }
    };
    let rebake: Option<f32> = args.get(2).map(|a| a.parse().expect("ALPHA is a number"));
    let mut session = Session::open(config.as_ref()).expect("config opens");
    session.load_checkpoint(Some(checkpoint.as_ref())).expect("checkpoint loads");
    if let Some(alpha) = rebake {
        session.occupancy = Some(Session::occupancy_grid(&session.config, &session.scene, alpha));
        session.bake_occupancy();
    }
    println!("occupied cells {:.3}", session.occupancy.as_ref().map_or(1.0, OccupancyGrid::occupancy));
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    for &i in &session.scene.test {
        let view = &session.scene.views[i];
        let rays = RayBatch::full_image(&view.camera);
        let width = view.camera.width as usize;
        let mut stats = ViewStats::default();
        for start in (0..rays.len()).step_by(8192) {
            let end = (start + 8192).min(rays.len());
            let chunk = rays.slice(start, end);
            let options = session.render_options(false);
            let mut r = render(session.field.as_ref(), session.render_context(), &chunk, options, false, &mut rng);
            r.composite();
            let targets: Vec<[f32; 3]> = (start..end).map(|p| view.image.pixel(p % width, p / width)).collect();
            stats.add(&r, &targets);
        }
        let per_ray = |x: usize| x as f64 / stats.rays as f64;
        let opaque = stats.opaque.max(1) as f64;
        println!(
            "{}: PSNR {:.2} dB, candidates/ray {:.1}, kept/ray {:.1}, w > {HEAD_THRESHOLD}/ray {:.1}, opaque {:.3}, \
             fog in front {:.4} by depth/median {:?}",
            view.name,
            psnr_from_mse(stats.squared_error / (3 * stats.rays) as f64),
            per_ray(stats.candidates),
            per_ray(stats.kept),
            per_ray(stats.above_threshold),
            per_ray(stats.opaque),
            stats.fog.iter().sum::<f64>() / opaque,
            stats.fog.map(|b| (b / opaque * 1000.0).round() / 1000.0),
        );
    }
}
