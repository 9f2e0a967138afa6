//! Times each pass of the `tensorf` field at its full resolution on a batch of samples:
//! `cargo run --release -p sos-example-tensorf --example speed -- [samples] [resolution]`.

use std::time::Instant;

use sos_core::plugin::RadianceFieldConfig;
use sos_core::scene::SceneExtent;
use sos_example_tensorf::TensorfConfig;

/// The `sos` binary's allocator, so the timings match a training run.
#[global_allocator]
static ALLOCATOR: sos_core::train::memory::MiMalloc = sos_core::train::memory::MiMalloc;

fn main() {
    let arg = |i: usize, default: usize| std::env::args().nth(i).map_or(default, |s| s.parse().expect("a number"));
    let (n, res) = (arg(1, 80_000), arg(2, 64));
    let extent = SceneExtent::Bounded { min: [-1.0; 3], max: [1.0; 3] };
    let config = TensorfConfig { resolution: [res; 3], upsample_at: vec![], ..Default::default() };
    let mut field = config.build(&extent, 0).expect("valid config");
    let positions: Vec<[f32; 3]> = (0..n)
        .map(|i| {
            let t = i as f32 * 0.618;
            [t.sin() * 0.9, (t * 1.3).cos() * 0.9, (t * 0.7).sin() * 0.9]
        })
        .collect();
    let directions = vec![[0.0, 0.6, 0.8]; n];
    let (mut density, mut rgb) = (vec![0.0; n], vec![[0.0; 3]; n]);
    let mut seg = vec![0.0; n * field.seg_input_dim()];
    for _ in 0..2 {
        let t = Instant::now();
        field.density(&positions, &mut density);
        let t_density = t.elapsed();
        let t = Instant::now();
        field.forward(&positions, &directions, &mut density, &mut rgb, true);
        let t_forward = t.elapsed();
        let t = Instant::now();
        field.backward(&positions, &directions, None, &density, &rgb);
        let t_backward = t.elapsed();
        let t = Instant::now();
        field.step(1.0);
        let t_step = t.elapsed();
        let t = Instant::now();
        field.seg_input(&positions, &mut seg);
        let t_seg = t.elapsed();
        println!(
            "{n} samples at {res}^3: density {t_density:.2?}, forward {t_forward:.2?}, backward {t_backward:.2?}, \
             step {t_step:.2?}, seg_input {t_seg:.2?}"
        );
    }
}
