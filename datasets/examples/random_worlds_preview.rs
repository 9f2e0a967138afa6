//! Writes a contact sheet per random world, to look at the family:
//! `cargo run --release -p sos-datasets --example random_worlds_preview -- OUT_DIR [SEEDS] [RIG]`
//! (12 seeds and `rig = "random"` by default).
//!
//! Each `OUT_DIR/world_<seed>.png` shows four views of the world's 40 (400x300) in its top row,
//! their ground-truth masks below, and the masks outlined in red over the views in the bottom
//! row. `OUT_DIR/worlds.txt` describes every world (rig, object, hard case, distractors,
//! surroundings), with its generation time and foreground shares.

use std::fmt::Write as _;
use std::path::PathBuf;

use sos_core::image::{GrayImage, RgbImage};
use sos_datasets::synthetic::{describe, generate, Rig, SyntheticConfig, WorldKind};

/// Size of one tile of the sheet.
const TILE: [usize; 2] = [200, 150];
/// Views shown per world.
const SHOWN: [usize; 4] = [0, 10, 20, 30];

fn rig_named(name: &str) -> Rig {
    let all = [Rig::ObjectCentric, Rig::ForwardFacing, Rig::Unbounded, Rig::Hemisphere, Rig::Grazing, Rig::Random];
    all.into_iter().find(|r| r.name() == name).unwrap_or_else(|| {
        let names: Vec<&str> = all.iter().map(|r| r.name()).collect();
        eprintln!("unknown rig `{name}`; rigs: {}", names.join(", "));
        std::process::exit(2)
    })
}

/// Copies `img` into `sheet` with its top-left corner at `(x, y)`.
fn blit(sheet: &mut RgbImage, img: &RgbImage, x: usize, y: usize) {
    for row in 0..img.height {
        for col in 0..img.width {
            sheet.set_pixel(x + col, y + row, img.pixel(col, row));
        }
    }
}

/// The mask as a grey image.
fn mask_image(m: &GrayImage) -> RgbImage {
    let mut out = RgbImage::new(m.width, m.height);
    for (i, &v) in m.data.iter().enumerate() {
        out.set_pixel(i % m.width, i / m.width, [v; 3]);
    }
    out
}

/// The view with the mask's boundary drawn in red and the background slightly darkened.
fn outline(img: &RgbImage, m: &GrayImage) -> RgbImage {
    let mut out = img.clone();
    let at = |c: usize, r: usize| m.data[r * m.width + c] > 0.5;
    for r in 0..m.height {
        for c in 0..m.width {
            let inside = at(c, r);
            let edge = inside
                && [(c.wrapping_sub(1), r), (c + 1, r), (c, r.wrapping_sub(1)), (c, r + 1)]
                    .iter()
                    .any(|&(cc, rr)| cc >= m.width || rr >= m.height || !at(cc, rr));
            let p = img.pixel(c, r);
            out.set_pixel(
                c,
                r,
                if edge {
                    [1.0, 0.0, 0.0]
                } else if inside {
                    p
                } else {
                    p.map(|v| 0.55 * v)
                },
            );
        }
    }
    out
}

fn main() {
    let mut args = std::env::args().skip(1);
    let out = PathBuf::from(args.next().unwrap_or_else(|| "random-worlds-preview".into()));
    let seeds: u64 = args.next().map_or(12, |s| {
        s.parse().unwrap_or_else(|_| {
            eprintln!("SEEDS must be a number, got `{s}`");
            std::process::exit(2)
        })
    });
    let rig = rig_named(&args.next().unwrap_or_else(|| "random".into()));
    std::fs::create_dir_all(&out).unwrap_or_else(|e| {
        eprintln!("cannot create {}: {e}", out.display());
        std::process::exit(2)
    });
    let mut notes = String::new();
    for seed in 0..seeds {
        let cfg = SyntheticConfig { world: WorldKind::Random, rig, seed, ..Default::default() };
        let start = std::time::Instant::now();
        let scene = generate(&cfg);
        let secs = start.elapsed().as_secs_f32();
        let [tw, th] = TILE;
        let mut sheet = RgbImage::new(tw * SHOWN.len(), th * 3);
        let mut shares = Vec::new();
        for (k, &i) in SHOWN.iter().enumerate() {
            let v = &scene.views[i.min(scene.views.len() - 1)];
            let m = v.mask.as_ref().expect("random worlds have masks");
            let rows =
                (0..m.height).filter(|r| m.data[r * m.width..(r + 1) * m.width].iter().any(|&x| x > 0.5)).count();
            shares.push(format!("{:.2}", rows as f32 / m.height as f32));
            let small_mask = m.resized_nearest(tw, th);
            blit(&mut sheet, &v.image.resized(tw, th), k * tw, 0);
            blit(&mut sheet, &mask_image(&small_mask), k * tw, th);
            blit(&mut sheet, &outline(&v.image.resized(tw, th), &small_mask), k * tw, 2 * th);
        }
        let path = out.join(format!("world_{seed:03}.png"));
        sheet.save_png(&path).unwrap_or_else(|e| {
            eprintln!("cannot write {}: {e}", path.display());
            std::process::exit(2)
        });
        let _ = writeln!(
            notes,
            "seed {seed}: {} ({} views in {secs:.2} s, extent {:?}, near {:.3})\n{}\nforeground height shares of the shown views: {}\n",
            scene.name,
            scene.views.len(),
            scene.extent,
            scene.near,
            describe(&cfg),
            shares.join(", ")
        );
        eprintln!("{}: {secs:.2} s -> {}", scene.name, path.display());
    }
    let notes_path = out.join("worlds.txt");
    std::fs::write(&notes_path, &notes).unwrap_or_else(|e| {
        eprintln!("cannot write {}: {e}", notes_path.display());
        std::process::exit(2)
    });
    print!("{notes}");
}
