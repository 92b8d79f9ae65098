//! `colmap-lidar evaluate`: compare a model's image poses with reference poses.
use std::path::PathBuf;

use anyhow::Context;

use std::collections::BTreeMap;

use crate::eval::{evaluate, load_poses, Alignment, ReportedSigma};
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
    let mut report = evaluate(&model, &reference, args.align)?;
    // A model written by `map` reports its own pose uncertainty: with no
    // alignment, say how the true errors compare with it (an optional extra:
    // a report that cannot be read is skipped with a warning).
    let own = args.model.join("report.json");
    if args.align == Alignment::None && own.is_file() {
        match reported_sigmas(&own) {
            Ok(sigmas) => report.compare_with_uncertainty(&sigmas),
            Err(e) => log::warn!(
                "{}: uncertainties not read ({e:#}); errors not compared with them",
                own.display()
            ),
        }
    }
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

/// Per image name, the sigmas of `report.json` (`images[].pose_uncertainty`);
/// empty when the report has none.
fn reported_sigmas(path: &std::path::Path) -> anyhow::Result<BTreeMap<String, ReportedSigma>> {
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(path)?)?;
    let mut out = BTreeMap::new();
    for image in report["images"].as_array().into_iter().flatten() {
        let u = &image["pose_uncertainty"];
        if let (Some(name), Some(c), Some(r)) = (
            image["name"].as_str(),
            u["centre_sigma_major_m"].as_f64(),
            u["rotation_sigma_deg"].as_f64(),
        ) {
            out.insert(
                name.to_string(),
                ReportedSigma {
                    centre_m: c,
                    rotation_deg: r,
                },
            );
        }
    }
    Ok(out)
}
