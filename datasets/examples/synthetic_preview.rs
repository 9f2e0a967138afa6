//! Writes a few views and masks of both synthetic rigs as PNGs, to look at the scene:
//! `cargo run --release -p sos-datasets --example synthetic_preview -- OUT_DIR`.

use sos_datasets::synthetic::{generate, Rig, SyntheticConfig};

fn main() {
    let out = std::path::PathBuf::from(
        std::env::args()
            .nth(1)
            .unwrap_or_else(|| "synthetic-preview".into()),
    );
    for rig in [Rig::ObjectCentric, Rig::ForwardFacing] {
        let start = std::time::Instant::now();
        let scene = generate(&SyntheticConfig {
            rig,
            ..Default::default()
        });
        eprintln!(
            "{}: {} views in {:.2} s, extent {:?}",
            scene.name,
            scene.views.len(),
            start.elapsed().as_secs_f32(),
            scene.extent
        );
        for i in [0, 5, 10, 20] {
            let v = &scene.views[i];
            v.image
                .save_png(&out.join(&scene.name).join(format!("{}.png", v.name)))
                .expect("write image");
            if let Some(m) = &v.mask {
                m.save_png(&out.join(&scene.name).join(format!("{}_mask.png", v.name)))
                    .expect("write mask");
            }
        }
    }
}
