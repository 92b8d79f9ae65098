//! `colmap-lidar evaluate`: compare a model's image poses with reference poses.
use std::path::{Path, PathBuf};

use anyhow::Context;

use std::collections::BTreeMap;

use super::map::load_map;
use crate::eval::intrinsics::focal_errors;
use crate::eval::map_agreement::{map_agreement, MapAgreement};
use crate::eval::model_poses::{load_model, poses_of};
use crate::eval::{evaluate, Alignment, ReportedSigma, Sim3};
use crate::io::atomic::write_file_atomically;
use crate::io::model::read_model;
use crate::map::index::MapIndex;
use crate::map::PointCloud;
use crate::scene::{Camera, CameraId, CameraModel, Rigid3};
use crate::sfm::associate::NearestNeighbourAssociator;
use crate::sfm::mapper::options_for_map;
use crate::sfm::MapperOptions;

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
    /// LiDAR map (.ply, .pcd, .las, .laz or .e57): also measure how far the model's tracks,
    /// triangulated at the reference poses, and the model's own points lie
    /// from the map's surfaces, by the incidence at which they were seen
    /// (what the images themselves say about the map, apart from the solve;
    /// the map's planes as `map` found them, with the options in the
    /// model's report.json, or the defaults).
    #[arg(long)]
    pub lidar: Option<PathBuf>,
}

pub fn run(args: &EvaluateArgs) -> anyhow::Result<()> {
    if let Some(path) = &args.json {
        crate::io::atomic::check_output_location(path, false)?;
    }
    let model_rec = load_model(&args.model).context("cannot read the model")?;
    let reference_rec = load_model(&args.reference).context("cannot read the reference")?;
    let model = poses_of(&model_rec, &args.model).context("cannot read the model")?;
    let reference =
        poses_of(&reference_rec, &args.reference).context("cannot read the reference")?;
    if !model.keys().any(|name| reference.contains_key(name)) {
        anyhow::bail!(
            "no image of the model {} ({} images) is in the reference {} ({} images) by name: is it the reference of the same images?",
            args.model.display(),
            model.len(),
            args.reference.display(),
            reference.len()
        );
    }
    // The map is read first, so that a bad one stops the command before
    // anything is printed.
    let cloud = match &args.lidar {
        Some(path) => Some((load_map(path)?, path)),
        None => None,
    };
    let mut report = evaluate(&model, &reference, args.align)?;
    report.focal_lengths = focal_errors(&model_rec, &reference_rec);
    // A model written by `map` reports its own uncertainties: say how the
    // true errors compare with them (the poses' with no alignment only; an
    // optional extra: a report that cannot be read is skipped with a
    // warning).
    let own = args.model.join("report.json");
    if own.is_file() {
        match reported_sigmas(&own) {
            Ok((formal, clustered, focal)) => {
                if args.align == Alignment::None {
                    report.error_over_sigma = report.errors_over(&formal);
                    report.error_over_clustered_sigma = report.errors_over(&clustered);
                }
                for e in &mut report.focal_lengths {
                    // Only where the report's camera is this one (its final
                    // focal length the model's to rounding).
                    let Some(&(focal_px, sigma, clustered)) = focal.get(&e.camera_id) else {
                        continue;
                    };
                    if (focal_px - e.focal_px).abs() <= 1e-9 * e.focal_px {
                        (e.sigma_px, e.clustered_sigma_px) = (sigma, clustered);
                    } else {
                        log::warn!(
                            "{}: camera {} has a final focal length of {focal_px} px there and {} px in the model; its sigmas not used",
                            own.display(),
                            e.camera_id,
                            e.focal_px
                        );
                    }
                }
            }
            Err(e) => log::warn!(
                "{}: uncertainties not read ({e:#}); errors not compared with them",
                own.display()
            ),
        }
    }
    print!("{}", report.table());
    let agreement = match &cloud {
        Some((cloud, path)) => {
            // `--align sim3` failed above without a similarity.
            let sim3 = report.sim3.filter(|_| args.align == Alignment::Sim3);
            Some(agreement_with_map(
                &args.model,
                &reference,
                sim3,
                cloud,
                path,
            )?)
        }
        None => None,
    };
    if let Some(a) = &agreement {
        print!("{}", a.table());
    }
    if let Some(path) = &args.json {
        let mut value = serde_json::to_value(&report)?;
        if let Some(a) = &agreement {
            value["map_agreement"] = serde_json::to_value(a)?;
        }
        write_file_atomically(path, |w| -> std::io::Result<()> {
            serde_json::to_writer_pretty(&mut *w, &value)?;
            std::io::Write::write_all(w, b"\n")
        })
        .with_context(|| format!("cannot write {}", path.display()))?;
    }
    Ok(())
}

/// [`map_agreement`] of the model with the map `cloud` (read from `path`), its planes found
/// as the mapper finds them with the options that made the model (its
/// `report.json`; the defaults without one), adapted to the map's spacing. With `sim3` (the pose
/// comparison's similarity) the model's own points are moved by it first.
fn agreement_with_map(
    model_dir: &Path,
    reference: &BTreeMap<String, Rigid3>,
    sim3: Option<Sim3>,
    cloud: &PointCloud,
    path: &Path,
) -> anyhow::Result<MapAgreement> {
    let mut model = read_model(model_dir)
        .with_context(|| format!("reading the model {}", model_dir.display()))?;
    if let Some(sim3) = sim3 {
        for point in model.points3d.values_mut() {
            point.xyz = sim3.transform_point(&point.xyz);
        }
    }
    let index = MapIndex::build(cloud)
        .with_context(|| format!("indexing the LiDAR map {}", path.display()))?;
    let own = model_dir.join("report.json");
    let options = match options_of_run(&own) {
        Ok(Some(options)) => {
            log::info!(
                "the map's planes as found with the options in {}",
                own.display()
            );
            options
        }
        Ok(None) => MapperOptions::default(),
        Err(e) => {
            log::warn!(
                "{}: options not read ({e:#}); the map's planes as found with the defaults",
                own.display()
            );
            MapperOptions::default()
        }
    };
    let options = options_for_map(&options, cloud, &index).options;
    let planes = NearestNeighbourAssociator::new(cloud, &index, options.association);
    Ok(map_agreement(&model, reference, &planes))
}

/// The options a `map` run used (`report.json` -> `options`); `None` when
/// there is no report or it has no options (older reports).
fn options_of_run(path: &Path) -> anyhow::Result<Option<MapperOptions>> {
    if !path.is_file() {
        return Ok(None);
    }
    let mut report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(path)?)?;
    match report.get_mut("options").map(serde_json::Value::take) {
        None | Some(serde_json::Value::Null) => Ok(None),
        Some(options) => {
            let options: MapperOptions = serde_json::from_value(options)?;
            options.validate()?;
            Ok(Some(options))
        }
    }
}

/// Sigmas by image name.
type Sigmas = BTreeMap<String, ReportedSigma>;
/// Per camera id, its final mean focal length and the formal and the
/// cluster-robust sigma of it, px.
type FocalSigmas = BTreeMap<u32, (f64, Option<f64>, Option<f64>)>;

/// Per image name, the formal and the cluster-robust sigmas of `report.json`
/// (`images[].pose_uncertainty`), and per camera id those of its focal
/// length (`intrinsics[]`); empty when the report has none.
fn reported_sigmas(path: &std::path::Path) -> anyhow::Result<(Sigmas, Sigmas, FocalSigmas)> {
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(path)?)?;
    let focal = report["intrinsics"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(|c| {
            let id = u32::try_from(c["camera_id"].as_u64()?).ok()?;
            let model = CameraModel::from_name(c["model"].as_str()?)?;
            let params = c["final_params"]
                .as_array()?
                .iter()
                .map(serde_json::Value::as_f64)
                .collect::<Option<Vec<f64>>>()
                .filter(|p| p.len() == model.num_params())?;
            let camera = Camera {
                id: CameraId(id),
                model,
                width: 0,
                height: 0,
                params,
            };
            let sigmas = (
                camera.mean_focal_length(),
                c["focal_sigma_px"].as_f64(),
                c["clustered_focal_sigma_px"].as_f64(),
            );
            Some((id, sigmas))
        })
        .collect();
    let mut formal = BTreeMap::new();
    let mut clustered = BTreeMap::new();
    for image in report["images"].as_array().into_iter().flatten() {
        let u = &image["pose_uncertainty"];
        let Some(name) = image["name"].as_str() else {
            continue;
        };
        for (out, centre, rotation) in [
            (&mut formal, "centre_sigma_major_m", "rotation_sigma_deg"),
            (
                &mut clustered,
                "clustered_centre_sigma_major_m",
                "clustered_rotation_sigma_deg",
            ),
        ] {
            if let (Some(c), Some(r)) = (u[centre].as_f64(), u[rotation].as_f64()) {
                out.insert(
                    name.to_string(),
                    ReportedSigma {
                        centre_m: c,
                        rotation_deg: r,
                    },
                );
            }
        }
    }
    Ok((formal, clustered, focal))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn options_come_from_the_runs_report() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("report.json");
        assert!(options_of_run(&path).unwrap().is_none());
        let mut options = MapperOptions::default();
        options.association.min_planarity = 0.4;
        options.association.plane_radius_m = 0.3;
        let report = serde_json::json!({"seed": 0, "solves": [], "options": options});
        std::fs::write(&path, report.to_string()).unwrap();
        assert_eq!(options_of_run(&path).unwrap(), Some(options));
        // An older report without options, and one whose options do not parse.
        std::fs::write(&path, r#"{"seed": 0, "options": null}"#).unwrap();
        assert!(options_of_run(&path).unwrap().is_none());
        std::fs::write(
            &path,
            r#"{"options": {"association": {"no_such_option": 1}}}"#,
        )
        .unwrap();
        let err = format!("{:#}", options_of_run(&path).unwrap_err());
        assert!(err.contains("no_such_option"), "{err}");
    }
}
