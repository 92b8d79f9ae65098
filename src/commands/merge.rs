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
        for img in model.registered_images() {
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
                    let free = CameraId(out.cameras.keys().map(|c| c.0).max().unwrap_or(0) + 1);
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
        for img in model.registered_images() {
            let new_id = if out.images.contains_key(&img.id) {
                let free = ImageId(out.images.keys().map(|i| i.0).max().unwrap_or(0) + 1);
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
    let mut models = Vec::with_capacity(args.inputs.len());
    for dir in &args.inputs {
        let model =
            read_model(dir).with_context(|| format!("reading the model {}", dir.display()))?;
        models.push((dir.clone(), model));
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
