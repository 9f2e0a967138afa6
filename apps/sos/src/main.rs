//! `sos`: the nerf-sos command line.
//!
//! Every failure prints the chain of causes (file, key, what to do) and exits with code 2.

mod commands;

use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

/// An allocator that keeps freed pages for the next training step (see `train::memory`).
#[global_allocator]
static ALLOCATOR: sos_core::train::memory::MiMalloc = sos_core::train::memory::MiMalloc;

// Force-link every plugin crate so their registrations are present.
use sos_plugins as _;

/// Unsupervised object segmentation in any view of a 3D scene (NeRF-SOS) on the CPU.
#[derive(Parser)]
#[command(name = "sos", version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
    /// Hide progress bars (they are hidden anyway when stderr is not a terminal).
    #[arg(long, global = true)]
    quiet: bool,
}

#[derive(Subcommand)]
enum Command {
    /// Fit the radiance field (stage 1), evaluate, then train the segmentation head (stage 2,
    /// when `segment.steps > 0`) and write masks and metrics.
    Train {
        /// Run configuration (TOML).
        config: PathBuf,
        /// Continue from the run's checkpoint instead of starting over.
        #[arg(long)]
        resume: bool,
    },
    /// Train the segmentation head (stage 2) from a stage-1 checkpoint, then write masks and metrics.
    Segment {
        /// Run configuration (TOML).
        config: PathBuf,
        /// Stage-1 checkpoint (default: the run's own); the head is saved to the run's checkpoint.
        #[arg(long)]
        checkpoint: Option<PathBuf>,
        /// Skip training: infer masks with the head already saved in the checkpoint.
        #[arg(long)]
        masks_only: bool,
    },
    /// Render held-out views and the novel camera path from a checkpoint (with masks when it
    /// holds a segmentation head).
    Render {
        /// Run configuration (TOML).
        config: PathBuf,
        /// Checkpoint to render (default: the run's own).
        #[arg(long)]
        checkpoint: Option<PathBuf>,
    },
    /// Compute PSNR (and segmentation metrics when available) on held-out views; writes metrics.json.
    Eval {
        /// Run configuration (TOML).
        config: PathBuf,
        /// Checkpoint to evaluate (default: the run's own).
        #[arg(long)]
        checkpoint: Option<PathBuf>,
    },
    /// IoU and ARI of a predicted mask PNG against a reference mask (resized to the
    /// prediction's size, nearest-neighbour).
    Compare {
        /// Predicted mask (e.g. `runs/flower/masks/image000.png`).
        prediction: PathBuf,
        /// Reference mask (any size; white = foreground).
        reference: PathBuf,
        /// Also write the figures to this JSON file.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// List every registered plugin kind, per role.
    List,
    /// Write a complete default configuration.
    Init {
        /// Where to write it (stdout when omitted).
        path: Option<PathBuf>,
        /// Dataset kind of the default config.
        #[arg(long, default_value = "synthetic")]
        scene: String,
        /// Field kind of the default config.
        #[arg(long, default_value = "voxel-grid")]
        field: String,
    },
}

fn main() -> ExitCode {
    sos_core::train::memory::keep_freed_memory();
    let cli = Cli::parse();
    let progress = !cli.quiet && std::io::stderr().is_terminal();
    let result = match cli.command {
        Command::Train { config, resume } => commands::train::run(&config, resume, progress),
        Command::Segment { config, checkpoint, masks_only } => {
            commands::segment::run(&config, checkpoint.as_deref(), masks_only, progress)
        }
        Command::Render { config, checkpoint } => commands::render::run(&config, checkpoint.as_deref()),
        Command::Eval { config, checkpoint } => commands::eval::run(&config, checkpoint.as_deref()),
        Command::Compare { prediction, reference, out } => {
            commands::compare::run(&prediction, &reference, out.as_deref())
        }
        Command::List => commands::list::run(),
        Command::Init { path, scene, field } => commands::init::run(path.as_deref(), &scene, &field),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::from(2)
        }
    }
}
