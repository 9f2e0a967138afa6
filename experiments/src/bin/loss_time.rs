//! Time of stage 2's losses at the main job's sizes (8 patches of 64x64 rays, 2 logit
//! channels): the geometry loss over every pixel pair and over its default drawn pixels
//! (`samples`), and the appearance loss.
//!
//! `cargo run --release --manifest-path experiments/Cargo.toml --bin loss_time [repeats]`

use std::time::Instant;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use sos_core::plugin::{ContrastiveLossConfig, FeatureMap, PatchBatch};
use sos_losses::appearance::appearance_loss;
use sos_losses::geometry::geometry_loss;
use sos_losses::{AppearanceConfig, GeometryConfig, PatchShape};

fn main() {
    let repeats: usize = std::env::args().nth(1).and_then(|a| a.parse().ok()).unwrap_or(5);
    let shape = PatchShape { n_patches: 8, d_seg: 2, patch: 64 };
    let m = shape.pixels();
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let points: Vec<f32> = (0..shape.n_patches * 3 * m).map(|_| rng.gen_range(-2.0..2.0)).collect();
    let logits: Vec<f32> = (0..shape.logits_len()).map(|_| rng.gen_range(-1.0..1.0)).collect();
    let negatives: Vec<usize> = (0..shape.n_patches).map(|k| (k + 3) % shape.n_patches).collect();
    let features: Vec<FeatureMap> = (0..shape.n_patches)
        .map(|_| FeatureMap {
            channels: 43,
            height: 32,
            width: 32,
            data: (0..43 * 32 * 32).map(|_| rng.gen_range(-1.0..1.0)).collect(),
            cls: vec![0.0; 43],
            saliency: None,
        })
        .collect();
    let (geometry, appearance) = (GeometryConfig::default(), AppearanceConfig::default());
    let u: Vec<[f32; 2]> =
        (0..shape.n_patches * 121).map(|_| [rng.gen_range(-1.0..1.0), rng.gen_range(-1.0..1.0)]).collect();
    let sampled = geometry.build().expect("default geometry loss");
    let batch = PatchBatch {
        n_patches: shape.n_patches,
        patch: shape.patch,
        d_seg: shape.d_seg,
        logits: &logits,
        points: &points,
        features: &[],
        negatives: &negatives,
    };
    for _ in 0..repeats {
        let mut grad = vec![0.0f32; logits.len()];
        let t = Instant::now();
        let g = geometry_loss(&geometry, &points, &logits, shape, &negatives, 1.0, Some(&mut grad));
        let t_geometry = t.elapsed().as_secs_f64();
        let mut sampled_grad = vec![0.0f32; logits.len()];
        let t = Instant::now();
        sampled.loss_and_grad(&batch, &mut rng, 1.0, &mut sampled_grad);
        let t_sampled = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let a = appearance_loss(&appearance, &features, &logits, shape, &negatives, &u, &u, 1.0, Some(&mut grad));
        let t_appearance = t.elapsed().as_secs_f64();
        println!(
            "geometry: every pair {:.3} s ({:.6}), {}² drawn pixels {:.4} s; appearance {:.4} s ({:.6}), grad sum {:.6e}",
            t_geometry,
            g.total,
            geometry.samples,
            t_sampled,
            t_appearance,
            a.total,
            grad.iter().map(|&v| f64::from(v)).sum::<f64>()
        );
    }
}
