//! Writes the synthetic scene in every dataset layout, with masks, and reopens each to check it:
//! `cargo run --release -p sos-datasets --example write_layouts -- [OUT_DIR] [RIG] [WxH] [VIEWS]`.
//!
//! `OUT_DIR` defaults to `runs/layouts` (a config with `[scene] kind` and `path` reads each), `RIG`
//! to `object-centric` (or `forward-facing`, which the NSVF layout cannot hold). By default the
//! scene is the default `synthetic` one (400x300, 40 views, every 8th held out, seed 0), as in
//! `configs/synthetic.toml`, so a run on any layout can be compared with a run on the
//! generator itself; `WxH` and `VIEWS` make a smaller one for quick checks.

use std::path::PathBuf;
use std::process::ExitCode;

use sos_datasets::layouts::Format;
use sos_datasets::synthetic::{generate, Rig, SyntheticConfig};

fn main() -> ExitCode {
    let mut args = std::env::args().skip(1);
    let out = PathBuf::from(args.next().unwrap_or_else(|| "runs/layouts".into()));
    let rig = match args.next().as_deref() {
        None | Some("object-centric") => Rig::ObjectCentric,
        Some("forward-facing") => Rig::ForwardFacing,
        Some(other) => {
            eprintln!("error: unknown rig {other:?}; use object-centric or forward-facing");
            return ExitCode::from(2);
        }
    };
    let mut cfg = SyntheticConfig { rig, ..Default::default() };
    if let Some(size) = args.next() {
        let parsed = size.split_once('x').and_then(|(w, h)| Some((w.parse().ok()?, h.parse().ok()?)));
        let Some((w, h)) = parsed else {
            eprintln!("error: size {size:?} must read WIDTHxHEIGHT, e.g. 80x60");
            return ExitCode::from(2);
        };
        (cfg.width, cfg.height) = (w, h);
    }
    if let Some(views) = args.next() {
        let Ok(v) = views.parse() else {
            eprintln!("error: VIEWS {views:?} must be a number");
            return ExitCode::from(2);
        };
        cfg.views = v;
    }
    if let Err(e) = cfg.check() {
        eprintln!("error: {e}");
        return ExitCode::from(2);
    }
    let scene = generate(&cfg);
    eprintln!(
        "{}: {} views ({} held out), extent {:?}, near {:.4}",
        scene.name,
        scene.views.len(),
        scene.test.len(),
        scene.extent,
        scene.near
    );
    let mut failed = false;
    for f in Format::ALL {
        let dir = out.join(f.name());
        std::fs::remove_dir_all(&dir).ok();
        let written = f.write(&scene, &dir).and_then(|_| f.open_raw(&dir, None));
        match written {
            Ok(loaded) => eprintln!(
                "{:>16}: {} ({} views, {} held out)",
                f.name(),
                f.scene_dir(&dir).display(),
                loaded.views.len(),
                loaded.test.len()
            ),
            Err(e) => {
                eprintln!("{:>16}: error: {e}", f.name());
                failed = true;
            }
        }
    }
    if failed {
        ExitCode::from(2)
    } else {
        ExitCode::SUCCESS
    }
}
