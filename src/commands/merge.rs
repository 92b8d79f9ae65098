//! `colmap-lidar merge`: models of the same map in one model. Models that
//! `map` wrote from the same LiDAR map share its frame and scale, so images
//! that no verified match links (groups of photos mapped each from its own
//! initial pose, see `report.json` → `not_registered`) go into one model as
//! they are: no alignment, nothing moved.
use std::collections::BTreeMap;
use std::path::PathBuf;

use anyhow::{bail, Context, Result};

use crate::io::atomic::write_dir_atomically;
use crate::io::model::{read_model, write_model, ModelFormat};
use crate::io::pose_ply::format_model_pose_ply;
pub use crate::scene::merge::{merge_models, MergeError, MergeSummary};

/// Put models of the same LiDAR map (outputs of `map`) into one model.
#[derive(Debug, clap::Args)]
pub struct MergeArgs {
    /// A model folder (text or binary); two or more, in order.
    #[arg(long = "input", value_name = "DIR", num_args = 1.., required = true)]
    pub inputs: Vec<PathBuf>,
    /// Output folder: the merged model and its `pose.ply`.
    #[arg(long)]
    pub output: PathBuf,
    /// Model files to write: text or binary.
    #[arg(
        long,
        visible_alias = "output_type",
        value_name = "text|binary",
        default_value = "text"
    )]
    pub output_type: String,
}

/// What the inputs' `report.json` (where `map` wrote one) say against
/// their being in one map's frame: a model mapped without the map's planes
/// (`association` "none": its frame is its initial pose's, its scale the
/// initial pair's), or models of maps with other numbers of points. An
/// input without a readable report is not checked.
pub fn map_frame_warnings(inputs: &[PathBuf]) -> Vec<String> {
    let mut warnings = Vec::new();
    let mut maps: BTreeMap<u64, Vec<String>> = BTreeMap::new();
    for dir in inputs {
        let path = dir.join("report.json");
        let Ok(text) = std::fs::read_to_string(&path) else {
            continue;
        };
        let Ok(report) = serde_json::from_str::<serde_json::Value>(&text) else {
            warnings.push(format!(
                "{}: not read as JSON; its map is not checked",
                path.display()
            ));
            continue;
        };
        if report["association"].as_str() == Some("none") {
            warnings.push(format!(
                "{} was mapped without the map's planes (--no-lidar-constraints): it is in its initial pose's frame at the initial pair's scale, not held by the map",
                dir.display()
            ));
        }
        if let Some(n) = report["map_points"].as_u64() {
            let file = report["map_file"].as_str().unwrap_or("?");
            maps.entry(n)
                .or_default()
                .push(format!("{} ({file})", dir.display()));
        }
    }
    if maps.len() > 1 {
        let list: Vec<String> = maps
            .iter()
            .map(|(n, dirs)| format!("{} from a map of {n} points", dirs.join(", ")))
            .collect();
        warnings.push(format!(
            "the inputs were mapped into different maps: {}; their frames agree only if those maps do",
            list.join("; ")
        ));
    }
    warnings
}

pub fn run(args: &MergeArgs) -> Result<()> {
    if args.inputs.len() < 2 {
        bail!(
            "merge needs two or more --input models, got {}",
            args.inputs.len()
        );
    }
    let format = match args.output_type.as_str() {
        "text" | "TXT" | "txt" => ModelFormat::Text,
        "binary" | "BIN" | "bin" => ModelFormat::Binary,
        other => bail!("--output-type must be text or binary, got `{other}`"),
    };
    // The output replaces its folder: never an input's.
    let output = std::fs::canonicalize(&args.output).ok();
    for dir in &args.inputs {
        if output.is_some() && std::fs::canonicalize(dir).ok() == output {
            bail!(
                "--output {} is one of the inputs: write the merged model to another folder",
                args.output.display()
            );
        }
    }
    super::map::check_output(&args.output)?;
    let mut models = Vec::with_capacity(args.inputs.len());
    for dir in &args.inputs {
        let model =
            read_model(dir).with_context(|| format!("reading the model {}", dir.display()))?;
        models.push((dir.display().to_string(), model));
    }
    for warning in map_frame_warnings(&args.inputs) {
        log::warn!("{warning}");
    }
    let (merged, summary) = merge_models(&models)?;
    for (k, old, new) in &summary.cameras_renumbered {
        log::warn!(
            "{}: camera {} has other intrinsics than the earlier model's camera {}; it is camera {} in the merged model",
            models[*k].0,
            old.0,
            old.0,
            new.0
        );
    }
    for (k, old, new) in &summary.images_renumbered {
        log::warn!(
            "{}: image id {} is taken by another image (models of different databases?); it is image {} in the merged model and its pose.ply line",
            models[*k].0,
            old.0,
            new.0
        );
    }
    write_dir_atomically(&args.output, |tmp| -> Result<()> {
        write_model(tmp, &merged, format)?;
        std::fs::write(tmp.join("pose.ply"), format_model_pose_ply(&merged))?;
        Ok(())
    })
    .with_context(|| format!("writing the merged model to {}", args.output.display()))?;
    println!(
        "merged {} models: {} images, {} points, {} cameras; model in {}",
        models.len(),
        merged.num_registered_images(),
        merged.points3d.len(),
        merged.cameras.len(),
        args.output.display()
    );
    Ok(())
}
