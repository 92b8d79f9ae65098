//! `colmap-lidar evaluate`: compare a model's image poses with reference poses.
use std::path::PathBuf;

use anyhow::Context;

use crate::eval::{evaluate, load_poses, Alignment};
use crate::io::atomic::write_file_atomically;

/// Compare a model with reference poses (matched by image name).
#[derive(Debug, clap::Args)]
pub struct EvaluateArgs {
    /// Model folder to evaluate (images.bin or images.txt).
    #[arg(long, alias = "input_path")]
    pub model: PathBuf,
    /// Reference model folder (e.g. a synthetic scene's gt/).
    #[arg(long, alias = "gt")]
    pub reference: PathBuf,
    /// Alignment before measuring: none (map-frame output) or sim3 (best case for SfM).
    #[arg(long, value_enum, default_value = "none")]
    pub align: Alignment,
    /// Also write the full report (with per-image errors) as JSON.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

pub fn run(args: &EvaluateArgs) -> anyhow::Result<()> {
    let model = load_poses(&args.model).context("cannot read the model")?;
    let reference = load_poses(&args.reference).context("cannot read the reference")?;
    let report = evaluate(&model, &reference, args.align)?;
    print!("{}", report.table());
    if let Some(path) = &args.json {
        write_file_atomically(path, |w| -> std::io::Result<()> {
            serde_json::to_writer_pretty(&mut *w, &report)?;
            std::io::Write::write_all(w, b"\n")
        })
        .with_context(|| format!("cannot write {}", path.display()))?;
    }
    Ok(())
}
