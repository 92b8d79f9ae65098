//! `colmap-lidar merge`: models of the same map in one model. Models that
//! `map` wrote from the same LiDAR map share its frame and scale, so images
//! that no verified match links (groups of photos mapped each from its own
//! initial pose, see `report.json` → `not_registered`) go into one model as
//! they are: no alignment, nothing moved.
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};

use crate::io::atomic::write_dir_atomically;
use crate::io::model::{read_model, write_model, ModelFormat};
use crate::io::pose_ply::format_model_pose_ply;
use crate::scene::{CameraId, ImageId, Point3DId, Reconstruction, TrackElement};

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

/// What [`merge_models`] did besides the union.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct MergeSummary {
    /// Cameras of a later model given a new id because the same id held
    /// other intrinsics (model index, old id, new id).
    pub cameras_renumbered: Vec<(usize, CameraId, CameraId)>,
    /// Images of a later model given a new id because the id was taken
    /// (model index, old id, new id).
    pub images_renumbered: Vec<(usize, ImageId, ImageId)>,
}

/// The registered images of `models` (and the points they see) in one
/// model. Images are matched by name: one name in two models is an error
/// (which pose would it keep?). Ids are kept where they are free: a camera
/// id that a later model uses for other intrinsics, or an image id taken by
/// another image, gets the next free id. 3D points are numbered from 1 in
/// the models' order.
pub fn merge_models(
    models: &[(PathBuf, Reconstruction)],
) -> Result<(Reconstruction, MergeSummary)> {
    let mut out = Reconstruction::default();
    let mut summary = MergeSummary::default();
    let mut names: BTreeMap<String, &Path> = BTreeMap::new();
    let mut next_point = 1u64;
    for (k, (dir, model)) in models.iter().enumerate() {
        if model.num_registered_images() == 0 {
            bail!(
                "{} has no registered image: nothing to merge",
                dir.display()
            );
        }
        let mut own: BTreeSet<&str> = BTreeSet::new();
        for img in model.registered_images() {
            if !own.insert(img.name.as_str()) {
                bail!(
                    "{}: image {} is in it twice (a model has one pose per image)",
                    dir.display(),
                    img.name
                );
            }
            if let Some(first) = names.insert(img.name.clone(), dir) {
                bail!(
                    "image {} is in both {} and {}: merge models of different images (one pose per image)",
                    img.name,
                    first.display(),
                    dir.display()
                );
            }
        }
        let mut camera_ids: BTreeMap<CameraId, CameraId> = BTreeMap::new();
        let used: BTreeSet<CameraId> = model.registered_images().map(|img| img.camera_id).collect();
        // A new id is free in the merged model and not one of this model's
        // own, which keep theirs where they can.
        let mut cameras_taken: BTreeSet<u32> =
            out.cameras.keys().chain(&used).map(|c| c.0).collect();
        for id in used {
            let camera = model.cameras.get(&id).with_context(|| {
                format!(
                    "{}: camera {} of its images is missing",
                    dir.display(),
                    id.0
                )
            })?;
            let new_id = match out.cameras.get(&id) {
                None => id,
                Some(c) if c == camera => id,
                Some(_) => {
                    let free = CameraId(
                        next_free(&mut cameras_taken).context("no camera id left to give")?,
                    );
                    summary.cameras_renumbered.push((k, id, free));
                    free
                }
            };
            let mut camera = camera.clone();
            camera.id = new_id;
            out.cameras.insert(new_id, camera);
            camera_ids.insert(id, new_id);
        }
        let mut image_ids: BTreeMap<ImageId, ImageId> = BTreeMap::new();
        let mut images_taken: BTreeSet<u32> = out
            .images
            .keys()
            .copied()
            .chain(model.registered_images().map(|img| img.id))
            .map(|i| i.0)
            .collect();
        for img in model.registered_images() {
            let new_id = if out.images.contains_key(&img.id) {
                let free =
                    ImageId(next_free(&mut images_taken).context("no image id left to give")?);
                summary.images_renumbered.push((k, img.id, free));
                free
            } else {
                img.id
            };
            image_ids.insert(img.id, new_id);
        }
        let mut point_ids: BTreeMap<Point3DId, Point3DId> = BTreeMap::new();
        for (&id, point) in &model.points3d {
            let track: Vec<TrackElement> = point
                .track
                .iter()
                .filter_map(|e| {
                    Some(TrackElement {
                        image_id: *image_ids.get(&e.image_id)?,
                        point2d_idx: e.point2d_idx,
                    })
                })
                .collect();
            if track.is_empty() {
                continue;
            }
            let new_id = Point3DId(next_point);
            next_point += 1;
            let mut point = point.clone();
            point.track = track;
            out.points3d.insert(new_id, point);
            point_ids.insert(id, new_id);
        }
        for img in model.registered_images() {
            let mut img = img.clone();
            img.id = image_ids[&img.id];
            img.camera_id = camera_ids[&img.camera_id];
            for p in &mut img.points2d {
                p.point3d_id = p.point3d_id.and_then(|id| point_ids.get(&id).copied());
            }
            out.images.insert(img.id, img);
        }
    }
    Ok((out, summary))
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

/// The smallest id above every id in `taken`, which it joins (`None` past
/// `u32::MAX`).
fn next_free(taken: &mut BTreeSet<u32>) -> Option<u32> {
    let id = taken.last().map_or(Some(1), |&max| max.checked_add(1))?;
    taken.insert(id);
    Some(id)
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
        models.push((dir.clone(), model));
    }
    for warning in map_frame_warnings(&args.inputs) {
        log::warn!("{warning}");
    }
    let (merged, summary) = merge_models(&models)?;
    for (k, old, new) in &summary.cameras_renumbered {
        log::warn!(
            "{}: camera {} has other intrinsics than the earlier model's camera {}; it is camera {} in the merged model",
            models[*k].0.display(),
            old.0,
            old.0,
            new.0
        );
    }
    for (k, old, new) in &summary.images_renumbered {
        log::warn!(
            "{}: image id {} is taken by another image (models of different databases?); it is image {} in the merged model and its pose.ply line",
            models[*k].0.display(),
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
