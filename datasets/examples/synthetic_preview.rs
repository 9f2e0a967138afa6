//! Writes a few views and masks of both synthetic rigs as PNGs, to look at the scene:
//! `cargo run --release -p sos-datasets --example synthetic_preview -- OUT_DIR`.

use sos_datasets::synthetic::{generate, Rig, SyntheticConfig};

fn main() {
    let out = std::path::PathBuf::from(std::env::args().nth(1).unwrap_or_else(|| "synthetic-preview".into()));
    for rig in [Rig::ObjectCentric, Rig::ForwardFacing] {
        let start = std::time::Instant::now();
        let scene = generate(&SyntheticConfig { rig, ..Default::default() });
        eprintln!(
            "{}: {} views in {:.2} s, extent {:?}",
            scene.name,
            scene.views.len(),
            start.elapsed().as_secs_f32(),
            scene.extent
        );
        // Detail proxy: PSNR of each view against itself shrunk 2x and 3x (box) and enlarged
        // back (bilinear); fine texture that a coarse grid cannot hold lowers it.
        for k in [2, 3] {
            let mut mse = 0.0f64;
            for v in &scene.views {
                let (w, h) = (v.image.width, v.image.height);
                let back = v.image.resized(w / k, h / k).resized(w, h);
                let e: f64 = v.image.data.iter().zip(&back.data).map(|(a, b)| ((a - b) as f64).powi(2)).sum();
                mse += e / v.image.data.len() as f64 / scene.views.len() as f64;
            }
            eprintln!("  {k}x down/up PSNR {:.1} dB", -10.0 * mse.log10());
        }
        for i in [0, 5, 10, 20] {
            let v = &scene.views[i];
            v.image.save_png(&out.join(&scene.name).join(format!("{}.png", v.name))).expect("write image");
            if let Some(m) = &v.mask {
                m.save_png(&out.join(&scene.name).join(format!("{}_mask.png", v.name))).expect("write mask");
            }
        }
    }
}
