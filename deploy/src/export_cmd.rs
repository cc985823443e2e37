//! `ctxrace export`: a trained agent for use outside ctxrace (`ctxrace export onnx`, the
//! library `ctxrace_onnx`).

use anyhow::Result;
use clap::{Args, Subcommand};
use ctxrace_run::trained::CheckpointChoice;
use std::path::PathBuf;

/// The formats a trained agent is exported to.
#[derive(Subcommand)]
pub enum ExportCommand {
    /// An ONNX model of the agent's deterministic decision (one a call, its recurrent state
    /// or frame stack in and out), for onnxruntime.
    Onnx(OnnxArgs),
}

/// Arguments of `ctxrace export onnx`.
#[derive(Args)]
pub struct OnnxArgs {
    /// A trained agent: a run folder or one of its checkpoints.
    run_or_checkpoint: PathBuf,
    /// The model to write (`.onnx`).
    out: PathBuf,
    /// Which checkpoint of a run folder: best, latest, step-N or best-at-N.
    #[arg(long, default_value_t = CheckpointChoice::default())]
    checkpoint: CheckpointChoice,
}

/// Runs an export subcommand.
pub fn run(command: ExportCommand) -> Result<()> {
    match command {
        ExportCommand::Onnx(args) => {
            let model = ctxrace_onnx::export_path(&args.run_or_checkpoint, args.checkpoint)?;
            let bytes = model.write(&args.out)?;
            println!("wrote {} ({bytes} bytes): {model}", args.out.display());
            Ok(())
        }
    }
}
