//! Groups of images that no verified match links (photos of two rooms, or
//! two walks that never saw the same thing), each mapped from its own
//! initial image at its pose, in one model. All runs place their models by
//! the same map, so they share its frame and scale and the models go
//! together as they are ([`crate::scene::merge`]).
//!
//! Each group's run is a run on the database of that group's images alone
//! (the first also gets the images of groups without an initial image, so
//! that images with a known pose there are placed at it and the others say
//! why they are not in the model). A camera whose images are in two groups
//! keeps the intrinsics the earlier group's run gave it: the later runs
//! hold it there, so the model has one set of intrinsics per camera.
use std::collections::{BTreeMap, BTreeSet};
use std::time::Instant;

use super::localise::SearchRegion;
use super::mapper::{KnownPose, MapperError, MapperInputs, MapperOutput, Progress};
use super::options::MapperOptions;
use super::report::{GroupRunRecord, MapReport};
use super::runs::{run_mapper_from_pose, run_mapper_searching};
use crate::scene::merge::merge_models;
use crate::scene::{CameraId, ImageId, Rigid3};

/// Where one group's run starts: its initial image at its pose (or around
/// it, with a search region).
#[derive(Clone, Copy, Debug)]
pub struct GroupStart {
    pub image: ImageId,
    pub cam_from_world: Rigid3,
}

/// Maps the database from each of `starts`, one per group of images, and
/// returns one model. With one start this is the run from it, unchanged
/// (the whole database, no merge). `search`: each start is rough, searched
/// for on the map as `--init-search` does.
pub fn map_groups(
    inputs: MapperInputs<'_>,
    starts: &[GroupStart],
    search: Option<&SearchRegion>,
    options: &MapperOptions,
    progress: Progress<'_>,
) -> Result<MapperOutput, MapperError> {
    let run = |inputs: MapperInputs<'_>, start: &GroupStart, progress: Progress<'_>| {
        run_from(inputs, start, search, options, progress)
    };
    match starts {
        [] => return Err(MapperError::NoInitialImage),
        [one] => return run(inputs, one, progress),
        _ => {}
    }
    let db = inputs.db;
    let name = |id: ImageId| {
        db.images
            .get(&id)
            .map_or_else(|| format!("id {}", id.0), |img| img.name.clone())
    };
    let sets = group_image_sets(inputs, starts)?;
    let total = db.images.len();
    let mut held: BTreeMap<CameraId, Vec<f64>> = BTreeMap::new();
    let mut runs: Vec<(GroupRunRecord, MapperOutput)> = Vec::with_capacity(starts.len());
    let mut done = 0usize;
    for (start, images) in starts.iter().zip(&sets) {
        let mut group_db = db.restricted_to(images);
        // Cameras an earlier run refined, at its values.
        let used: BTreeSet<CameraId> = group_db.images.values().map(|i| i.camera_id).collect();
        let held_here: BTreeSet<CameraId> = used
            .into_iter()
            .filter(|id| held.contains_key(id))
            .collect();
        for id in &held_here {
            if let Some(camera) = group_db.cameras.get_mut(id) {
                camera.params = held[id].clone();
            }
            group_db.cameras_without_focal_prior.remove(id);
        }
        let known: BTreeMap<ImageId, KnownPose> = inputs
            .known_poses
            .iter()
            .filter(|(id, _)| images.contains(id))
            .map(|(&id, pose)| (id, *pose))
            .collect();
        let group_inputs = MapperInputs {
            db: &group_db,
            cloud: inputs.cloud,
            known_poses: &known,
            held_cameras: &held_here,
        };
        log::info!(
            "group of image {} ({} images): mapping it from its initial pose",
            name(start.image),
            images.len()
        );
        let started = Instant::now();
        let mut group_progress = |registered: usize, _: usize| progress(done + registered, total);
        let out =
            run(group_inputs, start, &mut group_progress).map_err(|e| MapperError::Group {
                image: name(start.image),
                images: images.len(),
                error: Box::new(e),
            })?;
        done += out.report.num_registered;
        for img in out.reconstruction.registered_images() {
            if let Some(camera) = out.reconstruction.cameras.get(&img.camera_id) {
                held.entry(img.camera_id)
                    .or_insert_with(|| camera.params.clone());
            }
        }
        let record = GroupRunRecord {
            init_image_id: start.image.0,
            init_image: name(start.image),
            num_images: images.len(),
            num_registered: out.report.num_registered,
            num_points: out.report.num_points,
            cameras_held: held_here.iter().map(|c| c.0).collect(),
            mapping_s: started.elapsed().as_secs_f64(),
            report: None,
        };
        runs.push((record, out));
    }
    merge_runs(runs, total)
}

/// One run from `start` (the search's, with a region).
fn run_from(
    inputs: MapperInputs<'_>,
    start: &GroupStart,
    search: Option<&SearchRegion>,
    options: &MapperOptions,
    progress: Progress<'_>,
) -> Result<MapperOutput, MapperError> {
    match search {
        Some(region) => run_mapper_searching(
            inputs,
            start.image,
            &start.cam_from_world,
            region,
            options,
            progress,
        ),
        None => run_mapper_from_pose(
            inputs,
            start.image,
            &start.cam_from_world,
            options,
            progress,
        ),
    }
}

/// The images of each start's run: its group's, and for the first also
/// those of every group without a start. An error when a start is not in
/// the database or two starts are in one group.
fn group_image_sets(
    inputs: MapperInputs<'_>,
    starts: &[GroupStart],
) -> Result<Vec<BTreeSet<ImageId>>, MapperError> {
    let db = inputs.db;
    let graph = db.correspondence_graph();
    let group_of = graph.image_groups(db.images.keys().copied());
    let mut members: BTreeMap<ImageId, BTreeSet<ImageId>> = BTreeMap::new();
    for (&image, &group) in &group_of {
        members.entry(group).or_default().insert(image);
    }
    let mut started: BTreeMap<ImageId, ImageId> = BTreeMap::new();
    let mut sets = Vec::with_capacity(starts.len());
    for start in starts {
        let group = *group_of
            .get(&start.image)
            .ok_or(MapperError::UnknownImage(start.image))?;
        if let Some(first) = started.insert(group, start.image) {
            return Err(MapperError::SameGroup {
                first: db.images[&first].name.clone(),
                second: db.images[&start.image].name.clone(),
            });
        }
        sets.push(members[&group].clone());
    }
    for (group, images) in &members {
        if !started.contains_key(group) {
            sets[0].extend(images);
        }
    }
    Ok(sets)
}

/// The groups' models in one, with one report: the first run's, its counts,
/// images and intrinsics over the whole model, and a record of every run.
fn merge_runs(
    runs: Vec<(GroupRunRecord, MapperOutput)>,
    total_images: usize,
) -> Result<MapperOutput, MapperError> {
    let labelled: Vec<(String, crate::scene::Reconstruction)> = runs
        .iter()
        .map(|(record, out)| {
            (
                format!("the run from image {}", record.init_image),
                out.reconstruction.clone(),
            )
        })
        .collect();
    let (reconstruction, summary) = merge_models(&labelled)?;
    // Disjoint images and held cameras: nothing is renumbered.
    if !summary.cameras_renumbered.is_empty() || !summary.images_renumbered.is_empty() {
        log::warn!("the groups' models were renumbered in the merge: {summary:?}");
    }
    let mut records = Vec::with_capacity(runs.len());
    let mut report: Option<MapReport> = None;
    let (mut observations, mut error_sum) = (0usize, 0.0);
    for (mut record, out) in runs {
        let mut own = out.report;
        observations += own.num_observations;
        error_sum += own.mean_reprojection_error_px * own.num_observations as f64;
        match &mut report {
            None => report = Some(own),
            Some(top) => {
                top.images.extend(own.images.iter().cloned());
                for rec in &own.intrinsics {
                    if !top.intrinsics.iter().any(|r| r.camera_id == rec.camera_id) {
                        top.intrinsics.push(rec.clone());
                    }
                }
                own.options = None;
                record.report = Some(Box::new(own));
            }
        }
        records.push(record);
    }
    let Some(mut report) = report else {
        return Err(MapperError::NoInitialImage);
    };
    report.images.sort_by_key(|r| r.image_id);
    report.intrinsics.sort_by_key(|r| r.camera_id);
    report.num_images = total_images;
    report.num_registered = reconstruction.num_registered_images();
    report.num_points = reconstruction.points3d.len();
    report.num_observations = observations;
    report.mean_track_length = if report.num_points > 0 {
        observations as f64 / report.num_points as f64
    } else {
        0.0
    };
    report.mean_reprojection_error_px = if observations > 0 {
        error_sum / observations as f64
    } else {
        0.0
    };
    report.groups = records;
    Ok(MapperOutput {
        reconstruction,
        report,
    })
}
