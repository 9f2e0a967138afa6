//! Argument parsing and dispatch of every `sos` command.

use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

use crate::bench::cli::{BenchArgs, ExecArgs};
use crate::commands;
use crate::commands::export::{self, ExportOptions, Part};

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
        /// Then run `sos export` with these parts (comma-separated; all when given no value)
        /// into `<run>/export`.
        #[arg(long, value_enum, value_delimiter = ',', num_args = 0..=1, value_name = "WHAT")]
        export: Option<Vec<Part>>,
    },
    /// Export a run with a segmentation head: camera-path frames with masks overlaid and their
    /// GIF, the object's coloured point cloud (PLY) and mesh (PLY, OBJ), and masks of held-out
    /// views or of any cameras (`--poses`), into `<run>/export`.
    Export {
        /// Run configuration (TOML).
        config: PathBuf,
        #[command(flatten)]
        options: ExportOptions,
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
    /// Run a benchmark matrix (scenes x methods x seeds, sweeps), resumably, and write its
    /// report; `merge` joins result folders of several machines, `diff` compares two.
    Bench(BenchArgs),
    /// One run of a benchmark matrix (started by `sos bench` in its own process).
    #[command(hide = true)]
    BenchExec(ExecArgs),
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

/// Parses the command line and runs the command; errors print their causes and give exit
/// code 2 (3: a benchmark matrix that ran to its end with failed runs).
pub fn run() -> ExitCode {
    crate::allocator::keep_freed_memory();
    let cli = Cli::parse();
    let progress = !cli.quiet && std::io::stderr().is_terminal();
    let result = match cli.command {
        Command::Train { config, resume } => commands::train::run(&config, resume, progress),
        Command::Segment { config, checkpoint, masks_only } => {
            commands::segment::run(&config, checkpoint.as_deref(), masks_only, progress)
        }
        Command::Render { config, checkpoint, export } => {
            commands::render::run(&config, checkpoint.as_deref(), progress).and_then(|()| match export {
                Some(what) => {
                    let options = ExportOptions { checkpoint, what, progress, ..ExportOptions::default() };
                    export::run(&config, &options)
                }
                None => Ok(()),
            })
        }
        Command::Export { config, options } => export::run(&config, &ExportOptions { progress, ..options }),
        Command::Eval { config, checkpoint } => commands::eval::run(&config, checkpoint.as_deref()),
        Command::Compare { prediction, reference, out } => {
            commands::compare::run(&prediction, &reference, out.as_deref())
        }
        Command::Bench(args) => crate::bench::cli::run(args, progress),
        Command::BenchExec(args) => crate::bench::exec::run(&args),
        Command::List => commands::list::run(),
        Command::Init { path, scene, field } => commands::init::run(path.as_deref(), &scene, &field),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            match e.downcast_ref::<crate::bench::cli::RunsFailed>() {
                Some(_) => ExitCode::from(crate::bench::cli::RunsFailed::EXIT_CODE),
                None => ExitCode::from(2),
            }
        }
    }
}
