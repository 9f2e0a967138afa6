//! A converged-looking `nerf` checkpoint (reference sizes) for the stage-2 speed benchmark,
//! obtained by distilling a trained `voxel-grid` of the same scene into both NeRF networks.
//!
//! Why: the stage-2 cost of a frozen NeRF depends on how empty its free space is. The paper's
//! checkpoint had 150k photometric steps; a few hundred steps, all a 2-core machine affords,
//! leave thick fog everywhere (median density 2.5/m after 500 steps), so nothing can be
//! skipped. Regressing the networks onto the voxel grid's density and colour at random points
//! (half uniform in the scene box, half near its surfaces) gives them a crisp geometry in
//! minutes. The result is an ordinary `nerf` checkpoint (both networks), saved in the layout
//! `sos` and the `nerf_stage2` study (`experiments/`) read.
//!
//! `cargo run --release -p sos-tools --bin nerf_distill -- <voxel checkpoint> <out dir> [steps]`
//! where the voxel checkpoint comes from `configs/voxel_synthetic_small.toml` (the 160x120
//! object-centric synthetic scene of `configs/nerf_synthetic_small.toml`). Threads:
//! `RAYON_NUM_THREADS` (default 2).

use std::path::{Path, PathBuf};
use std::time::Instant;

use rand::{Rng, SeedableRng};
use sos_core::camera::Vec3;
use sos_core::config::RunConfig;
use sos_core::plugin::RadianceField;
use sos_core::train::evaluate::evaluate_views;
use sos_core::train::Session;
use sos_plugins::nerf::{NerfConfig, NerfField};

const SCENE: &str = r#"
[scene]
kind = "synthetic"
rig = "object-centric"
width = 160
height = 120
views = 40
hold_out_every = 8
"#;

/// The same allocator as the `sos` binary: distillation allocates and frees large batches.
#[global_allocator]
static ALLOCATOR: sos::allocator::MiMalloc = sos::allocator::MiMalloc;

/// Interval over which the density target is expressed as an opacity (the stage-2 candidate
/// spacing of the small scene: its box diagonal over 192).
const DELTA: f32 = 0.037;

fn session(field: &str, extra: &str, out: &Path) -> Session {
    let text = format!(
        "name = \"nerf-distilled\"\noutput_dir = \"{}\"\nseed = 0\n{SCENE}\n[field]\nkind = \"{field}\"\n{extra}",
        out.display()
    );
    let config = RunConfig::parse(&text, Path::new("nerf_distill.toml")).expect("config parses");
    Session::from_config(config, Path::new(".")).expect("scene builds")
}

fn main() {
    sos::allocator::keep_freed_memory();
    let args: Vec<String> = std::env::args().collect();
    let (Some(teacher_ckpt), Some(out)) = (args.get(1), args.get(2)) else {
        eprintln!("usage: nerf_distill <voxel-grid checkpoint> <output dir> [steps]");
        std::process::exit(2);
    };
    let steps: usize = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(1500);
    let threads: usize = std::env::var("RAYON_NUM_THREADS").ok().and_then(|s| s.trim().parse().ok()).unwrap_or(2);
    rayon::ThreadPoolBuilder::new().num_threads(threads).build_global().expect("rayon pool");
    let out = PathBuf::from(out);

    let mut teacher = session("voxel-grid", "[segment]\nsteps = 0", &out);
    teacher.load_checkpoint(Some(Path::new(teacher_ckpt))).expect("voxel-grid checkpoint");
    let student_extra = "[train]\nsteps = 800\nsamples_per_ray = 192\nearly_stop = 0.0\nweight_threshold = 0.0\n\
                         occupancy = true\noccupancy_resolution = 128\noccupancy_warmup = 800\n[render]\nchunk = 4096\n\
                         [segment]\nsteps = 0";
    let mut student = session("nerf", student_extra, &out);
    let nerf = NerfConfig { lr: 1e-3, ..NerfConfig::default() };
    let mut field = NerfField::new(nerf, student.contraction, student.config.seed);

    // A pool of points near surfaces: uniform probes where the teacher is dense.
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let contraction = student.contraction;
    let uniform = |rng: &mut rand_chacha::ChaCha8Rng| contraction.from_unit([rng.gen(), rng.gen(), rng.gen()]);
    let probes: Vec<Vec3> = (0..2_000_000).map(|_| uniform(&mut rng)).collect();
    let mut sigma = vec![0.0; probes.len()];
    teacher.field.density(&probes, &mut sigma);
    let surface: Vec<Vec3> = probes.iter().zip(&sigma).filter(|(_, &s)| s * DELTA > 0.05).map(|(p, _)| *p).collect();
    eprintln!("{} of {} probes are near surfaces", surface.len(), probes.len());

    let batch = 8192;
    let started = Instant::now();
    for step in 0..steps {
        let mut points = Vec::with_capacity(batch);
        for i in 0..batch {
            if i % 2 == 0 || surface.is_empty() {
                points.push(uniform(&mut rng));
            } else {
                let p = surface[rng.gen_range(0..surface.len())];
                points.push([0, 1, 2].map(|k| p[k] + 0.03 * (rng.gen::<f32>() - 0.5)));
            }
        }
        let dirs: Vec<Vec3> = (0..batch)
            .map(|_| {
                let z: f32 = rng.gen_range(-1.0..1.0);
                let phi: f32 = rng.gen_range(0.0..std::f32::consts::TAU);
                let r = (1.0 - z * z).sqrt();
                [r * phi.cos(), r * phi.sin(), z]
            })
            .collect();
        let (mut st, mut ct) = (vec![0.0; batch], vec![[0.0; 3]; batch]);
        teacher.field.forward(&points, &dirs, &mut st, &mut ct, false);
        let at: Vec<f32> = st.iter().map(|s| -(-s * DELTA).exp_m1()).collect();
        let mut losses = [0.0f64; 2];
        for (n, net) in field.networks_mut().into_iter().enumerate() {
            let (mut ss, mut cs) = (vec![0.0; batch], vec![[0.0; 3]; batch]);
            let tape = net.forward(&points, &dirs, &mut ss, &mut cs, true);
            let mut gd = vec![0.0; batch];
            let mut gc = vec![[0.0; 3]; batch];
            let scale = 1.0 / batch as f32;
            for i in 0..batch {
                // Opacity over DELTA: bounded, and exactly zero in free space.
                let e = (-ss[i] * DELTA).exp();
                let a = 1.0 - e;
                let da = a - at[i];
                losses[n] += (da * da) as f64;
                gd[i] = scale * 2.0 * da * DELTA * e;
                for k in 0..3 {
                    let dc = cs[i][k] - ct[i][k];
                    losses[n] += (at[i] * dc * dc) as f64;
                    gc[i][k] = scale * 2.0 * at[i] * dc;
                }
            }
            net.backward(&points, &dirs, tape, &gd, &gc);
            let lr_factor = 0.1f32.powf(step as f32 / steps as f32);
            net.step(lr_factor);
        }
        if step % 100 == 0 || step + 1 == steps {
            eprintln!(
                "distill step {step}/{steps}: loss fine {:.5} coarse {:.5}, {:.0} s",
                losses[0] / batch as f64,
                losses[1] / batch as f64,
                started.elapsed().as_secs_f64()
            );
        }
    }
    student.field = Box::new(field);
    student.step = 800;
    student.save_checkpoint().expect("checkpoint written");
    println!("distilled checkpoint: {}", student.checkpoint_path().display());
    student.bake_occupancy();
    if let Some(occ) = &student.occupancy {
        println!("baked occupancy: {:.1}% of {}³ cells", 100.0 * occ.occupancy(), occ.resolution());
    }
    let t = Instant::now();
    let eval = evaluate_views(&student, false).expect("evaluation");
    println!(
        "held-out PSNR of the distilled nerf {:.2} dB (mean per view {:.2}), SSIM {:.4}, {} views, {:.0} s",
        eval.psnr,
        eval.psnr_mean_per_view,
        eval.ssim,
        eval.views.len(),
        t.elapsed().as_secs_f64()
    );
}
