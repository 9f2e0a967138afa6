//! Interruption: `sos train` killed with SIGKILL at pseudo-random moments of both stages and
//! restarted with `--resume` each time ends with exactly the metrics of an uninterrupted run,
//! and leaves no partial file (temporary checkpoint, lock) in its folder. Stage 1 resumes from
//! its last checkpoint (field, optimiser, occupancy grid and random stream); stage 2, which
//! saves once at its end, starts over from the finished stage 1.

mod common;

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use common::{sos, temp_dir, text};
use sos_core::train::checkpoint;

const SOS: &str = env!("CARGO_BIN_EXE_sos");
const STAGE1_STEPS: usize = 240;
/// Kills in each stage.
const KILLS_PER_STAGE: usize = 5;

fn config(name: &str) -> String {
    format!(
        "name = \"{name}\"\nseed = 5\n\
         [scene]\nkind = \"synthetic\"\nwidth = 64\nheight = 48\nviews = 10\nhold_out_every = 5\n\
         [field]\nkind = \"voxel-grid\"\nresolution = [24, 24, 24]\ninitial_resolution = [12, 12, 12]\n\
         [train]\nsteps = {STAGE1_STEPS}\nrays_per_step = 1024\ncheckpoint_every = 20\n\
         [render]\nchunk = 4096\n\
         [segment]\nsteps = 24\npatches = 4\npatch_size = 16\nstride = 2\n"
    )
}

fn spawn(dir: &Path, file: &str) -> Child {
    Command::new(SOS)
        .args(["train", "--resume", "--quiet", file])
        .current_dir(dir)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("the sos binary starts")
}

/// Stage-1 steps in the run's checkpoint (0 without one).
fn checkpointed_steps(run: &Path) -> usize {
    checkpoint::load(&run.join("checkpoint.bin")).map_or(0, |c| c.meta.step)
}

/// A fixed sequence of fractions in [0, 1) (an LCG), so failures reproduce.
struct Fractions(u64);

impl Fractions {
    fn next(&mut self) -> f64 {
        self.0 = self.0.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// Kills `child` after `delay` unless it ended first; whether it was killed.
fn kill_after(child: &mut Child, delay: Duration) -> bool {
    let until = Instant::now() + delay;
    while Instant::now() < until {
        if child.try_wait().expect("waiting works").is_some() {
            return false;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    let killed = child.try_wait().expect("waiting works").is_none() && child.kill().is_ok();
    child.wait().ok();
    killed
}

/// The held-out metrics of a finished run, timings left out.
fn results(run: &Path) -> serde_json::Value {
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("metrics.json")).expect("metrics.json")).unwrap();
    let test = &json["stage2"]["test"];
    serde_json::json!({ "image": test["image"], "segmentation": test["segmentation"] })
}

#[test]
fn runs_killed_in_both_stages_resume_to_the_uninterrupted_result() {
    let dir = temp_dir("sos-interrupt", "kills");
    std::fs::write(dir.join("whole.toml"), config("whole")).unwrap();
    std::fs::write(dir.join("killed.toml"), config("killed")).unwrap();

    let started = Instant::now();
    let out = sos(&["train", "--quiet", "whole.toml"], &dir);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let whole_time = started.elapsed();
    let expected = results(&dir.join("runs/whole"));
    // Kill moments follow the uninterrupted run's stages: its stage 1, and what came before
    // it (loading, the scene, the teacher), which every restart pays again.
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("runs/whole/metrics.json")).unwrap()).unwrap();
    let seconds = |pointer: &str| json.pointer(pointer).and_then(serde_json::Value::as_f64).unwrap_or(0.0);
    let stage1 = Duration::from_secs_f64(seconds("/timing/stage1_seconds"));
    let stage2 = Duration::from_secs_f64(seconds("/stage2/train_seconds"));
    let startup =
        whole_time.saturating_sub(stage1 + stage2 + Duration::from_secs_f64(seconds("/stage2/masks_seconds")));

    let run = dir.join("runs/killed");
    let mut fractions = Fractions(7);
    let (mut stage1_kills, mut stage2_kills) = (0, 0);
    // Stage 1: kills at moments spread over an uninterrupted stage's length.
    for _ in 0..4 * KILLS_PER_STAGE {
        if stage1_kills == KILLS_PER_STAGE || checkpointed_steps(&run) == STAGE1_STEPS {
            break;
        }
        let mut child = spawn(&dir, "killed.toml");
        let delay = startup + stage1.mul_f64(0.05 + 0.15 * fractions.next());
        let killed = kill_after(&mut child, delay);
        let steps = checkpointed_steps(&run);
        eprintln!("stage 1: killed {killed} after {delay:?} at checkpointed step {steps}");
        if killed && steps < STAGE1_STEPS {
            stage1_kills += 1;
        }
    }
    // Stage 2: each run finishes stage 1, then is killed somewhere in stage 2.
    for _ in 0..2 * KILLS_PER_STAGE {
        if stage2_kills == KILLS_PER_STAGE {
            break;
        }
        let mut child = spawn(&dir, "killed.toml");
        while checkpointed_steps(&run) < STAGE1_STEPS && child.try_wait().unwrap().is_none() {
            std::thread::sleep(Duration::from_millis(20));
        }
        let delay = stage2.mul_f64(0.1 + 0.8 * fractions.next());
        if kill_after(&mut child, delay) {
            stage2_kills += 1;
        }
    }
    assert!(
        stage1_kills >= 3 && stage2_kills >= 3 && stage1_kills + stage2_kills >= 10,
        "the run was killed {stage1_kills} times in stage 1 and {stage2_kills} in stage 2"
    );
    let mut last = spawn(&dir, "killed.toml");
    let status = last.wait().unwrap();
    let mut stderr = String::new();
    std::io::Read::read_to_string(last.stderr.as_mut().unwrap(), &mut stderr).ok();
    assert!(status.success(), "the final resume failed: {stderr}");

    assert_eq!(results(&run), expected, "the resumed run's results differ from the uninterrupted run's");
    let leftovers: Vec<String> = std::fs::read_dir(&run)
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".tmp") || n == "run.lock")
        .collect();
    assert!(leftovers.is_empty(), "partial files left in the run folder: {leftovers:?}");
    std::fs::remove_dir_all(dir).ok();
}
