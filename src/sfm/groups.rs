//! Groups of images that no verified match links (photos of two rooms, or
//! two walks that never saw the same thing), each mapped from its own
//! initial image at its pose, in one model. All runs place their models by
//! the same map, so they share its frame and scale and the models go
//! together as they are ([`crate::scene::merge`]).
//!
//! Each group's run is a run on the database of that group's images alone,
//! largest group first (the first also gets the images of groups without an
//! initial image, so that images with a known pose there are placed at it
//! and the others say why they are not in the model). A camera whose images are in two groups
//! keeps the intrinsics the earlier group's run gave it, and so do the
//! cameras identical to it in the database (COLMAP gives each image its own
//! camera unless told otherwise): the later runs hold them there, so the
//! model has one set of intrinsics per camera as one run would give it.
use std::collections::{BTreeMap, BTreeSet};
use std::time::Instant;

use super::localise::SearchRegion;
use super::mapper::{KnownPose, MapperError, MapperInputs, MapperOutput, Progress};
use super::options::{AssociationKind, IntrinsicsRefinement, MapperOptions};
use super::report::{
    GroupRunRecord, ImageRecord, IntrinsicsRecord, MapReport, NotRegistered, UncertaintySummary,
};
use super::runs::{run_mapper_from_pose, run_mapper_searching};
use super::state::{intrinsics_key, IntrinsicsKey};
use crate::io::database::DatabaseSnapshot;
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
    let group_runs = group_runs(inputs, starts)?;
    if options.association.kind == AssociationKind::None {
        log::warn!(
            "without the map's planes (--no-lidar-constraints) each group's model is in its own initial pose's frame at its own initial pair's scale: the {} groups are not in one frame",
            starts.len()
        );
    }
    let total = db.images.len();
    let mut held = HeldIntrinsics::new(db, options);
    let mut runs: Vec<(GroupRunRecord, MapperOutput)> = Vec::with_capacity(starts.len());
    let mut failed: Vec<FailedRun> = Vec::new();
    let mut done = 0usize;
    for (start, images) in &group_runs {
        let mut group_db = db.restricted_to(images);
        let held_here = held.apply(&mut group_db);
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
            run_log: inputs.run_log,
            image_dir: inputs.image_dir,
        };
        log::info!(
            "group of image {} ({} images): mapping it from its initial pose",
            name(start.image),
            images.len()
        );
        let started = Instant::now();
        let mut group_progress = |registered: usize, _: usize| progress(done + registered, total);
        let result = run(group_inputs, start, &mut group_progress);
        let mut record = GroupRunRecord {
            init_image_id: start.image.0,
            init_image: name(start.image),
            num_images: images.len(),
            num_registered: 0,
            num_points: 0,
            cameras_held: held_here.iter().map(|c| c.0).collect(),
            mapping_s: started.elapsed().as_secs_f64(),
            error: None,
            report: None,
        };
        let mut out = match result {
            Ok(out) => out,
            Err(e) => {
                let error = MapperError::Group {
                    image: name(start.image),
                    images: images.len(),
                    error: Box::new(e),
                };
                log::warn!("{error}: its images are left out of the model");
                failed.push((record, images.clone(), error));
                continue;
            }
        };
        // Registration order goes on from the earlier groups'.
        for rec in &mut out.report.images {
            if let Some(k) = &mut rec.registration_index {
                *k += done;
            }
        }
        done += out.report.num_registered;
        held.record(&out);
        record.num_registered = out.report.num_registered;
        record.num_points = out.report.num_points;
        runs.push((record, out));
    }
    if runs.is_empty() {
        // Every run failed: the first's error.
        let (_, _, error) = failed
            .into_iter()
            .next()
            .ok_or(MapperError::NoInitialImage)?;
        return Err(error);
    }
    let mut out = merge_runs(db, runs)?;
    add_failed_runs(db, &mut out.report, failed);
    Ok(out)
}

/// A failed group's run (its record, its images, its error).
type FailedRun = (GroupRunRecord, BTreeSet<ImageId>, MapperError);

/// Lists the failed runs in `report.groups` (after the runs in the model)
/// with their errors, and each of their images not in the report as not
/// registered for that reason.
fn add_failed_runs(db: &DatabaseSnapshot, report: &mut MapReport, failed: Vec<FailedRun>) {
    let mut listed: BTreeSet<u32> = report.images.iter().map(|r| r.image_id).collect();
    for (mut record, images, error) in failed {
        let message = match &error {
            MapperError::Group { error, .. } => error.to_string(),
            other => other.to_string(),
        };
        for id in images.iter().filter(|id| listed.insert(id.0)) {
            report.images.push(ImageRecord {
                image_id: id.0,
                name: db
                    .images
                    .get(id)
                    .map_or_else(String::new, |i| i.name.clone()),
                not_registered: Some(NotRegistered::GroupFailed {
                    init_image: record.init_image.clone(),
                    error: message.clone(),
                }),
                ..Default::default()
            });
        }
        record.error = Some(message);
        report.groups.push(record);
    }
    report.images.sort_by_key(|r| r.image_id);
}

/// The intrinsics earlier groups' runs gave the cameras of their registered
/// images, to hold in the later runs: by camera id, and, where identical
/// cameras share intrinsics (`bundle.share_identical_intrinsics`), by what
/// the database says of the camera (model, size, parameters, guessed), as
/// [`super::state::MapState::share_identical_intrinsics`] groups them.
struct HeldIntrinsics<'a> {
    db: &'a DatabaseSnapshot,
    /// Whether identical cameras share intrinsics, and whether a guessed
    /// focal length sets a camera apart (`auto` only).
    share: bool,
    guessed_apart: bool,
    by_id: BTreeMap<CameraId, Vec<f64>>,
    by_kind: BTreeMap<IntrinsicsKey, Vec<f64>>,
}

impl<'a> HeldIntrinsics<'a> {
    fn new(db: &'a DatabaseSnapshot, options: &MapperOptions) -> Self {
        Self {
            db,
            share: options.bundle.share_identical_intrinsics,
            guessed_apart: options.bundle.refine_intrinsics == IntrinsicsRefinement::Auto,
            by_id: BTreeMap::new(),
            by_kind: BTreeMap::new(),
        }
    }

    fn kind(&self, id: CameraId) -> Option<IntrinsicsKey> {
        let c = self.db.cameras.get(&id)?;
        let guessed = self.guessed_apart && self.db.cameras_without_focal_prior.contains(&id);
        Some(intrinsics_key(c, guessed))
    }

    /// The held intrinsics for camera `id`, if an earlier run gave them.
    fn get(&self, id: CameraId) -> Option<&Vec<f64>> {
        self.by_id.get(&id).or_else(|| {
            self.share
                .then(|| self.kind(id).and_then(|k| self.by_kind.get(&k)))
                .flatten()
        })
    }

    /// Sets the held cameras of `group_db`'s images to their intrinsics,
    /// given (no longer guessed); returns them.
    fn apply(&self, group_db: &mut DatabaseSnapshot) -> BTreeSet<CameraId> {
        let used: BTreeSet<CameraId> = group_db.images.values().map(|i| i.camera_id).collect();
        let mut held = BTreeSet::new();
        for id in used {
            let Some(params) = self.get(id) else { continue };
            if let Some(camera) = group_db.cameras.get_mut(&id) {
                camera.params = params.clone();
                group_db.cameras_without_focal_prior.remove(&id);
                held.insert(id);
            }
        }
        held
    }

    /// The intrinsics `out` gave the cameras of its registered images (the
    /// first run to give a camera its intrinsics keeps them).
    fn record(&mut self, out: &MapperOutput) {
        for img in out.reconstruction.registered_images() {
            let Some(camera) = out.reconstruction.cameras.get(&img.camera_id) else {
                continue;
            };
            self.by_id
                .entry(img.camera_id)
                .or_insert_with(|| camera.params.clone());
            if let Some(kind) = self.kind(img.camera_id) {
                self.by_kind
                    .entry(kind)
                    .or_insert_with(|| camera.params.clone());
            }
        }
    }
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

/// The runs, largest group first (ties in the order given): each start and
/// its run's images, its group's and for the first run also those of every
/// group without a start. An error when a start is not in the database,
/// has no verified pair, or shares its group with another start.
fn group_runs<'s>(
    inputs: MapperInputs<'_>,
    starts: &'s [GroupStart],
) -> Result<Vec<(&'s GroupStart, BTreeSet<ImageId>)>, MapperError> {
    let db = inputs.db;
    let graph = db.correspondence_graph();
    let group_of = graph.image_groups(db.images.keys().copied());
    let mut members: BTreeMap<ImageId, BTreeSet<ImageId>> = BTreeMap::new();
    for (&image, &group) in &group_of {
        members.entry(group).or_default().insert(image);
    }
    let mut started: BTreeMap<ImageId, ImageId> = BTreeMap::new();
    let mut runs = Vec::with_capacity(starts.len());
    for start in starts {
        let group = *group_of
            .get(&start.image)
            .ok_or(MapperError::UnknownImage(start.image))?;
        if members[&group].len() < 2 {
            return Err(MapperError::InitialImageAlone(
                db.images[&start.image].name.clone(),
            ));
        }
        if let Some(first) = started.insert(group, start.image) {
            return Err(MapperError::SameGroup {
                first: db.images[&first].name.clone(),
                second: db.images[&start.image].name.clone(),
            });
        }
        runs.push((start, members[&group].clone()));
    }
    // The largest group's run first: it sets the shared cameras' intrinsics.
    runs.sort_by_key(|(_, images)| std::cmp::Reverse(images.len()));
    for (group, images) in &members {
        if !started.contains_key(group) {
            runs[0].1.extend(images);
        }
    }
    Ok(runs)
}

/// The groups' models in one, with one report: the first run's, its counts,
/// images and intrinsics over the whole model, and a record of every run.
fn merge_runs(
    db: &DatabaseSnapshot,
    runs: Vec<(GroupRunRecord, MapperOutput)>,
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
    let mut intrinsics = Intrinsics::default();
    let mut uncertainties = Vec::new();
    for (mut record, out) in runs {
        let mut own = out.report;
        intrinsics.add(db, &own);
        if let Some(u) = &own.pose_uncertainty {
            uncertainties.push((own.num_observations, u.clone()));
        }
        observations += own.num_observations;
        error_sum += own.mean_reprojection_error_px * own.num_observations as f64;
        match &mut report {
            None => report = Some(own),
            Some(top) => {
                top.images.extend(own.images.iter().cloned());
                own.options = None;
                record.report = Some(Box::new(own));
            }
        }
        records.push(record);
    }
    let Some(mut report) = report else {
        return Err(MapperError::NoInitialImage);
    };
    report.intrinsics = intrinsics.records();
    report.images.sort_by_key(|r| r.image_id);
    report.set_totals(
        db.images.len(),
        reconstruction.num_registered_images(),
        reconstruction.points3d.len(),
        observations,
        error_sum,
    );
    report.pose_uncertainty = merged_uncertainty(&report, &uncertainties);
    report.groups = records;
    Ok(MapperOutput {
        reconstruction,
        report,
    })
}

/// The pose uncertainties over every group's images (`report`'s, merged):
/// medians and maxima over the images, the residual sigma as the runs' root
/// mean square weighted by their observations, degenerate points and times
/// summed. `runs`: each run's observations and summary; `None` when no run
/// computed one.
fn merged_uncertainty(
    report: &MapReport,
    runs: &[(usize, UncertaintySummary)],
) -> Option<UncertaintySummary> {
    if runs.is_empty() {
        return None;
    }
    let weight: f64 = runs.iter().map(|(n, _)| *n as f64).sum();
    let variance: f64 = runs
        .iter()
        .map(|(n, u)| *n as f64 * u.residual_sigma_px.powi(2))
        .sum();
    Some(UncertaintySummary::over(
        report
            .images
            .iter()
            .filter_map(|r| r.pose_uncertainty.as_ref()),
        if weight > 0.0 {
            (variance / weight).sqrt()
        } else {
            0.0
        },
        runs.iter().map(|(_, u)| u.num_degenerate_points).sum(),
        runs.iter().map(|(_, u)| u.time_s).sum(),
    ))
}

/// One intrinsics record per camera: from the first run that registered an
/// image of it (the run whose values the model has; later runs held it),
/// else from the first run that had it.
#[derive(Default)]
struct Intrinsics {
    registered: BTreeMap<u32, IntrinsicsRecord>,
    other: BTreeMap<u32, IntrinsicsRecord>,
}

impl Intrinsics {
    /// The records of one run's report (before it is merged).
    fn add(&mut self, db: &DatabaseSnapshot, report: &MapReport) {
        let used: BTreeSet<u32> = report
            .images
            .iter()
            .filter(|r| r.registered)
            .filter_map(|r| db.images.get(&ImageId(r.image_id)))
            .map(|img| img.camera_id.0)
            .collect();
        for rec in &report.intrinsics {
            let records = if used.contains(&rec.camera_id) {
                &mut self.registered
            } else {
                &mut self.other
            };
            records.entry(rec.camera_id).or_insert_with(|| rec.clone());
        }
    }

    fn records(mut self) -> Vec<IntrinsicsRecord> {
        for (id, rec) in self.other {
            self.registered.entry(id).or_insert(rec);
        }
        self.registered.into_values().collect()
    }
}
