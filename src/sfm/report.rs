//! `report.json`: what the mapper did, per image and per solve. Everything in
//! it is deterministic except the times (`time_s`, `*_time_s`, `wall_s`,
//! `solver_times`).
use std::collections::{BTreeMap, BTreeSet};

use serde::Serialize;

use super::bundle::{PoseUncertainty, SolveRecord};
use super::initialize::InitSummary;
use super::options::MapperOptions;
use super::state::MapState;
use crate::scene::correspondence_graph::CorrespondenceGraph;
use crate::scene::{Camera, CameraId, ImageId, Rigid3};
use crate::solver::PlaneFamily;

/// One image.
#[derive(Clone, Debug, Default, Serialize)]
pub struct ImageRecord {
    pub image_id: u32,
    pub name: String,
    pub registered: bool,
    /// 0 for the initial image, 1 for the second, ...
    pub registration_index: Option<usize>,
    /// Registration attempts (PnP runs), successful or not.
    pub attempts: usize,
    /// 2D-3D correspondences of the successful (or last) attempt.
    pub num_correspondences: usize,
    /// PnP inliers of the successful (or last) attempt.
    pub pnp_inliers: usize,
    /// Registered by being placed at its known pose (too few matches for PnP).
    pub placed_by_prior: bool,
    /// Came registered with the model the run extended (`--input-model`).
    pub from_input_model: bool,
    /// Observations of 3D points in the final model.
    pub num_observations: usize,
    /// Mean reprojection error of those observations, pixels.
    pub mean_reprojection_error_px: Option<f64>,
    /// Points it observes that are tied to a LiDAR plane, by kind (from the
    /// last solve that included them).
    pub num_projection_planes: usize,
    pub num_nearest_planes: usize,
    pub num_ground_planes: usize,
    /// Mean distance of those points to their planes, metres.
    pub mean_plane_distance_m: Option<f64>,
    /// The pose's uncertainty after the final solve (with LiDAR constraints).
    pub pose_uncertainty: Option<PoseUncertainty>,
    /// Why it is not in the model (`None` when registered).
    pub not_registered: Option<NotRegistered>,
}

/// Why an image is not in the model, in the order they are told apart.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
#[serde(tag = "reason", rename_all = "snake_case")]
pub enum NotRegistered {
    /// No verified image pair with any other image (no matches passed
    /// geometric verification, or it has no features).
    NoMatches,
    /// Its verified pairs link it only to images none of which is in the
    /// model: a group of `group_size` images (a connected component of the
    /// image graph; its smallest image id `group_first_image_id`) that
    /// shares no verified matches with the model's images. Such a group is
    /// mapped from one of its images at its pose in the map: in the same
    /// run (another `--init-image`, [`super::groups`]), or on its own and
    /// the models merged (`colmap-lidar merge`).
    OtherGroup {
        group_size: usize,
        group_first_image_id: u32,
    },
    /// In the model's group of images, but it never saw the 4 of the
    /// model's points a pose needs while images were registered, so no pose
    /// was tried (`points_seen`: how many it sees in the final model).
    TooFewModelPoints { points_seen: usize },
    /// A pose was tried and not found (`attempts`, `num_correspondences`
    /// and `pnp_inliers` of the last attempt).
    PoseNotFound,
    /// Given to the run of another group's initial image `init_image` (one
    /// `--init-image` per group, [`super::groups`]), and that run failed
    /// with `error`; the other groups' runs are in the model.
    GroupFailed { init_image: String, error: String },
}

/// The model a run extended, as it came.
#[derive(Clone, Debug, Default, Serialize)]
pub struct InputModelRecord {
    pub num_images: usize,
    /// Its points with two or more observations, as seeded.
    pub num_points: usize,
    /// Whether its images kept their poses and intrinsics (`--fix-existing-images`).
    pub held: bool,
    /// Share of (a sample of) its points within 2 cm of the map surface
    /// their images see: how well it sits in the map's frame.
    pub points_on_seen_surface_share: f64,
    /// Share of those points where the map shows a surface at their
    /// features in one of their images.
    pub map_coverage_share: f64,
    /// Share of the covered points that lie on the map (measured only
    /// below `association.min_points_on_map_share`).
    pub covered_fit_share: Option<f64>,
    /// Similarity-constraint ratio of the covered points' nearest planes
    /// (measured only below that share, see `mapper::covered_constraint`).
    pub covered_similarity_constraint_ratio: Option<f64>,
    /// Accepted below `association.min_points_on_map_share` as a model the
    /// map covers only in part (see the top-level `partial_map`).
    pub partial_map: bool,
    /// The whole-model alignment to the map as it came: applied unless held.
    pub alignment: Option<AlignmentRecord>,
}

/// The pose uncertainties over all images (see `bundle::PoseUncertainty`).
#[derive(Clone, Debug, Default, Serialize)]
pub struct UncertaintySummary {
    /// Standard deviation of a unit-weight residual, as the fit estimates it
    /// (pixels): the scale of every uncertainty.
    pub residual_sigma_px: f64,
    /// Over the images: the centre's sigma along its least determined
    /// direction, metres.
    pub median_centre_sigma_major_m: f64,
    pub max_centre_sigma_major_m: f64,
    /// Over the images: the rotation's sigma about its least determined axis.
    pub median_rotation_sigma_deg: f64,
    pub max_rotation_sigma_deg: f64,
    /// The same of the cluster-robust estimate
    /// (`bundle.uncertainty_cluster_m`), when computed.
    pub median_clustered_centre_sigma_major_m: Option<f64>,
    pub max_clustered_centre_sigma_major_m: Option<f64>,
    pub median_clustered_rotation_sigma_deg: Option<f64>,
    /// 3D points whose own position the data do not fully fix.
    pub num_degenerate_points: usize,
    pub time_s: f64,
}

impl UncertaintySummary {
    /// Medians and maxima over the images' uncertainties `poses`; the other
    /// fields as given.
    pub fn over<'a>(
        poses: impl IntoIterator<Item = &'a PoseUncertainty>,
        residual_sigma_px: f64,
        num_degenerate_points: usize,
        time_s: f64,
    ) -> Self {
        let poses: Vec<&PoseUncertainty> = poses.into_iter().collect();
        let major: Vec<f64> = poses.iter().map(|u| u.centre_sigma_major_m).collect();
        let rotation: Vec<f64> = poses.iter().map(|u| u.rotation_sigma_deg).collect();
        let clustered_major: Vec<f64> = poses
            .iter()
            .filter_map(|u| u.clustered_centre_sigma_major_m)
            .collect();
        let clustered_rotation: Vec<f64> = poses
            .iter()
            .filter_map(|u| u.clustered_rotation_sigma_deg)
            .collect();
        let median = |v: &[f64]| crate::eval::Stats::of(v).map_or(0.0, |s| s.median);
        let max_of = |v: &[f64]| v.iter().copied().fold(0.0, f64::max);
        let if_any = |v: &[f64], f: &dyn Fn(&[f64]) -> f64| (!v.is_empty()).then(|| f(v));
        Self {
            residual_sigma_px,
            median_centre_sigma_major_m: median(&major),
            max_centre_sigma_major_m: max_of(&major),
            median_rotation_sigma_deg: median(&rotation),
            max_rotation_sigma_deg: max_of(&rotation),
            median_clustered_centre_sigma_major_m: if_any(&clustered_major, &median),
            max_clustered_centre_sigma_major_m: if_any(&clustered_major, &max_of),
            median_clustered_rotation_sigma_deg: if_any(&clustered_rotation, &median),
            num_degenerate_points,
            time_s,
        }
    }
}

/// The whole-model alignment to the map (see `sfm::align`).
#[derive(Clone, Debug, Default, Serialize)]
pub struct AlignmentRecord {
    pub scale: f64,
    pub rotation_deg: f64,
    /// How far the similarity moves the model's centroid, metres.
    pub translation_m: f64,
    /// Points within 2 cm of the map before and after.
    pub points_on_map_before: usize,
    pub points_on_map_after: usize,
    /// Whether the move is within `sfm::align`'s bounds (scale, rotation,
    /// centroid shift).
    pub within_bounds: bool,
    /// Applied only when more points end on the map (the initial pair's:
    /// at least 1 % more), within bounds, and the initial image is not held
    /// at its given pose (then a trial only).
    pub applied: bool,
    /// When the map covers less than 90 % of the model's points: the number
    /// of points (of a sample) the map covers, the only ones the alignment
    /// used and counted.
    pub covered_points_only: Option<usize>,
    pub time_s: f64,
}

/// One stage of the run.
#[derive(Clone, Debug, Serialize)]
pub struct StageRecord {
    pub name: String,
    pub time_s: f64,
    /// The process's peak resident memory at the stage's end, MB (the most
    /// it held so far, not what the stage added; Linux only).
    pub peak_memory_mb: Option<f64>,
}

impl StageRecord {
    pub fn new(name: &str, time_s: f64) -> Self {
        StageRecord {
            name: name.to_owned(),
            time_s,
            peak_memory_mb: peak_memory_mb(),
        }
    }
}

/// One run of the mapper within a `map` call (the first run, the runs from
/// its looks and from where it ended, the retries, the search's): how it
/// ended and where its time went ([`MapReport::runs`]).
#[derive(Clone, Debug, Serialize)]
pub struct RunStagesRecord {
    /// Its place in the order the runs were made, from 0.
    pub index: usize,
    /// Whether the model written is this run's (one per group of photos).
    pub kept: bool,
    /// How the run itself ended: "finished", "stopped at its look" (to be
    /// mapped again from there) or "failed: " and the error. A finished run
    /// may still be set aside by what follows (a retry, a restart, the
    /// search's choice, a check of its initial image's change): `kept` says
    /// which model was written, the `retry`, `restart`, `early_restart` and
    /// `init_search` records why.
    pub outcome: String,
    /// Wall time from the run's start to its end, seconds.
    pub time_s: f64,
    /// The stages it went through, each with its time.
    pub stages: Vec<StageRecord>,
    /// Its solves as far as it got, for a run whose model was not kept (the
    /// kept run's are [`MapReport::solves`]): why a run stopped or was set
    /// aside can be read from them (for example the initial image's change
    /// at each solve).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub solves: Vec<SolveRecord>,
}

/// The runs of one `map` call as they end ([`MapReport::runs`]); shared by
/// every run through [`super::mapper::MapperInputs::run_log`].
#[derive(Debug, Default)]
pub struct RunLog(std::sync::Mutex<Vec<RunStagesRecord>>);

impl RunLog {
    /// Adds a run that ended with `outcome` after `time_s` seconds and went
    /// through `stages` and `solves` (not kept until [`Self::records`] says
    /// so); returns its index.
    pub fn push(
        &self,
        outcome: String,
        time_s: f64,
        stages: Vec<StageRecord>,
        solves: Vec<SolveRecord>,
    ) -> usize {
        let mut runs = self.0.lock().unwrap_or_else(|e| e.into_inner());
        let index = runs.len();
        runs.push(RunStagesRecord {
            index,
            kept: false,
            outcome,
            time_s,
            stages,
            solves,
        });
        index
    }

    /// Every run so far, those whose index is in `kept` marked kept and
    /// without their solves (the report's own).
    pub fn records(&self, kept: &BTreeSet<usize>) -> Vec<RunStagesRecord> {
        let runs = self.0.lock().unwrap_or_else(|e| e.into_inner());
        runs.iter()
            .map(|r| {
                let kept = kept.contains(&r.index);
                RunStagesRecord {
                    kept,
                    outcome: r.outcome.clone(),
                    stages: r.stages.clone(),
                    solves: if kept { Vec::new() } else { r.solves.clone() },
                    ..*r
                }
            })
            .collect()
    }
}

/// The process's peak resident memory so far, MB (`VmHWM` of
/// `/proc/self/status`; `None` where there is none).
pub fn peak_memory_mb() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find_map(|l| l.strip_prefix("VmHWM:"))?;
    let kb: f64 = line.trim().strip_suffix("kB")?.trim().parse().ok()?;
    Some(kb / 1024.0)
}

/// The whole report.
#[derive(Clone, Debug, Default, Serialize)]
pub struct MapReport {
    pub seed: u64,
    pub association: String,
    /// The map's sample spacing on its surfaces, metres
    /// ([`crate::map::index::MapIndex::surface_spacing_m`]); splats and
    /// plane radii grow with it ([`crate::sfm::options::MapperOptions::for_map_spacing`]).
    pub map_spacing_m: Option<f64>,
    /// The same over the map's steep points (normals within 30 deg of
    /// horizontal: walls); walls sparser than 1.5 times the map's spacing
    /// widen the smallest association radius
    /// ([`crate::sfm::options::MapperOptions::for_steep_spacing`]).
    pub map_steep_spacing_m: Option<f64>,
    /// The map's range noise along its normals, metres
    /// ([`crate::sfm::associate::NearestNeighbourAssociator::plane_noise_m`]);
    /// plane windows grow with it
    /// ([`crate::sfm::options::MapperOptions::for_map_noise`]).
    pub map_noise_m: Option<f64>,
    pub num_images: usize,
    pub num_registered: usize,
    pub num_points: usize,
    pub num_observations: usize,
    pub mean_track_length: f64,
    pub mean_reprojection_error_px: f64,
    pub init: Option<InitSummary>,
    /// With `--init-search`: where the search put the initial image, from
    /// the rough pose (the run's `init` starts there).
    pub init_search: Option<super::localise::SearchRecord>,
    /// With no initial pose: how the images' GPS positions placed the
    /// model (the search then started there, `init_search`).
    pub positions: Option<super::positions::PositionsRecord>,
    /// The model the run extended (`--input-model`), instead of `init`.
    pub input_model: Option<InputModelRecord>,
    /// The initial image and its given pose (not written): each solve
    /// records how far the image is from it.
    #[serde(skip)]
    pub initial_given: Option<(ImageId, Rigid3)>,
    /// How far the initial image ended from its given pose (with LiDAR
    /// constraints; a warning beyond half the accepted change).
    pub initial_pose_change: Option<PoseChangeRecord>,
    /// When the run was mapped again with the initial image held at its
    /// given pose (`bundle.retry_holding_initial`): why, and which run this
    /// model is. The stages and solves are those of the kept run.
    pub retry: Option<RetryRecord>,
    /// When the run was mapped again from where its initial image ended
    /// (`bundle.restart_from_refined_pose`: after the retry's run free from
    /// the start, and after the first run with `bundle.restart_first_run`):
    /// how far the run before moved it, and whether this model is the
    /// second run's. The stages and solves
    /// are those of the kept run; the second run's solves record the
    /// initial image's change from where the first run ended, while
    /// `initial_pose_change` is from the given pose. Also when the retry's
    /// run free from the start stopped at its look and was mapped again
    /// from there (`first_stopped_at_images`; `retry.free_kept` then).
    pub restart: Option<RestartRecord>,
    /// When the first run stopped early to map again from where its initial
    /// image was (`bundle.restart_early_at_images`; it had turned more than
    /// 1 deg there, within the accepted change): how far it had moved,
    /// and whether this model comes from that run (`second_kept`; then a
    /// `restart` after it is from where that run ended) or it failed (or
    /// called for the held retry: `second_error` says why) and the first run
    /// was mapped again from the given pose to its end.
    pub early_restart: Option<RestartRecord>,
    /// The first run's early look (`bundle.restart_early_at_images`), when
    /// it happened: where the initial image was, and whether the model had
    /// settled there (when it had and the image had turned more than 1 deg,
    /// within the accepted change, the run stopped there: `early_restart`).
    pub early_look: Option<EarlyLookRecord>,
    /// The alignment of the initial pair's model to the map, when run.
    pub initial_alignment: Option<AlignmentRecord>,
    /// The whole-model alignment to the map before the final rounds, when run.
    pub alignment: Option<AlignmentRecord>,
    /// Share of the final 3D points within 2 cm of a map surface (with LiDAR
    /// constraints).
    pub points_on_map_share: Option<f64>,
    /// Share of the final 3D points within 2 cm of the surface the map shows
    /// at their feature in at least one of their images (with LiDAR
    /// constraints; over at most 20000 of them, every k-th by id).
    pub points_on_seen_surface_share: Option<f64>,
    /// That share counting the points removed for lying behind the map as
    /// off it: what `min_points_on_map_share` is checked against.
    pub fit_share: Option<f64>,
    /// Share of (the same sample of) the final 3D points for which at least
    /// one of their images sees a map surface at their feature: how much of
    /// what the photos show the map covers.
    pub map_coverage_share: Option<f64>,
    /// `fit_share` over the points the map covers (those removed behind the
    /// map counted as off it).
    pub covered_fit_share: Option<f64>,
    /// The model fit the map below `min_points_on_map_share` over all its
    /// points but well where the map covers it, and was accepted as partly
    /// mapped (a warning).
    pub partial_map: bool,
    /// How well the final planes fix the model's similarity (a warning below
    /// `MIN_SIMILARITY_CONSTRAINT`).
    pub similarity_constraint: Option<super::align::SimilarityConstraint>,
    /// Points deleted before the final rounds because they lie behind the
    /// surface the map shows at their features (with LiDAR constraints).
    pub points_behind_map_removed: Option<usize>,
    /// The tracked keypoints' photometric refinement on the map's planes
    /// after the final rounds (with the images and LiDAR constraints), after
    /// which the rounds ran again.
    pub keypoint_refinement: Option<crate::sfm::keypoints::RefinementRecord>,
    /// Pose uncertainties after the final solve (with LiDAR constraints, up
    /// to `bundle.uncertainty_max_images` images).
    pub pose_uncertainty: Option<UncertaintySummary>,
    /// Each camera's intrinsics: as the database gave them, where they were
    /// refined, and as written.
    pub intrinsics: Vec<IntrinsicsRecord>,
    pub images: Vec<ImageRecord>,
    pub solves: Vec<SolveRecord>,
    /// How far the camera centres moved in each final round, metres (the
    /// rounds run again, `pass` 2, when the probe of a given focal length
    /// found it off).
    pub final_rounds: Vec<RoundRecord>,
    /// The kept run's stages. After an early look, a restart, a retry or a
    /// search the other runs' time is not in them: [`Self::runs`] has every
    /// run's, [`Self::mapping_s`] the whole time.
    pub stages: Vec<StageRecord>,
    /// Every run the `map` call made, in order, with its outcome and stages
    /// (the kept one marked); set by `map` (empty when the mapper is called
    /// as a library without a [`RunLog`]; not written then, nor in a
    /// group's own report).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub runs: Vec<RunStagesRecord>,
    /// This run's index among [`Self::runs`] (not written).
    #[serde(skip)]
    pub run_index: Option<usize>,
    /// Wall time of the whole mapping, seconds: every run made (first run,
    /// the runs from its looks and its end, the retries, the search), from
    /// the database and map in memory to the final model; set by `map`
    /// (`None` when the mapper is called as a library).
    pub mapping_s: Option<f64>,
    /// The LiDAR map the model is in: its file and number of points, as
    /// loaded; set by `map` (`merge` warns when its inputs name different
    /// maps).
    pub map_file: Option<String>,
    pub map_points: Option<usize>,
    /// Of `map_points`, those whose planarity is below the association's
    /// `min_planarity` and so give no plane (the planarity the file gave,
    /// or `map`'s own score); set by `map`.
    pub map_points_below_planarity: Option<usize>,
    /// When the map file's coordinates were not in metres: the unit they
    /// were converted from, and where it was read (the model, like the map
    /// as loaded, is in metres; [`crate::map::io::units`]).
    pub map_units: Option<String>,
    /// The points' colours from the images (`--image-path`), when given.
    pub point_colours: Option<crate::io::images::ColourSummary>,
    /// The options the run used, adapted to the map's spacing (the TOML
    /// file's `[mapper]` sections, as JSON).
    pub options: Option<MapperOptions>,
    /// With one initial image per group of images ([`super::groups`]):
    /// each group's run, in the order run (largest group first, ties in the
    /// order given). The counts and means, `images`, `intrinsics` and
    /// `pose_uncertainty` above cover the whole model; the other fields are
    /// the first run's, and each further run's own report is in its record.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub groups: Vec<GroupRunRecord>,
}

/// One group's run of a `map` given one initial image per group.
#[derive(Clone, Debug, Default, Serialize)]
pub struct GroupRunRecord {
    pub init_image_id: u32,
    pub init_image: String,
    /// The images the run was given: the group's, and for the first run
    /// also every image of a group without an initial image (placed at a
    /// known pose, or left out with the reason).
    pub num_images: usize,
    pub num_registered: usize,
    pub num_points: usize,
    /// Cameras whose intrinsics this run held at the values an earlier
    /// group's run gave them (one set of intrinsics per camera in the model).
    pub cameras_held: Vec<u32>,
    /// Wall time of the group's runs, seconds.
    pub mapping_s: f64,
    /// Why the run failed (its images are then left out of the model, each
    /// saying so); `None` for a run in the model.
    pub error: Option<String>,
    /// The run's own report (`None` for the first, which is the top level).
    pub report: Option<Box<MapReport>>,
}

/// A pose's change: its centre's move and its rotation's angle.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct PoseChangeRecord {
    pub moved_m: f64,
    pub turned_deg: f64,
}

/// The early look at the initial image during a run.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct EarlyLookRecord {
    /// Images registered at the look.
    pub registered: usize,
    /// The initial image's change from its given pose there.
    pub change: PoseChangeRecord,
    /// Its change from where the sphere solve before left it (`None` at
    /// the first sphere solve after its release); in a database of fewer
    /// than three times `bundle.restart_early_at_images` images the look
    /// waits for it to be at most 1 cm and 0.1 deg, with the map holding
    /// the model along every direction (`similarity_ratio` at least 1e-2).
    pub step: Option<PoseChangeRecord>,
    /// The similarity-constraint ratio of the model there (how firmly the
    /// map's planes hold it along its weakest direction).
    pub similarity_ratio: Option<f64>,
    /// How far the whole model's alignment to the map (stage 5's, as a
    /// trial) would move the initial image from there; `None` with
    /// `bundle.align_to_map` off.
    pub alignment_would_move: Option<PoseChangeRecord>,
    /// Whether the model had settled (the alignment would move the image
    /// less than 2 cm and 0.2 deg): only then may the run stop to map again
    /// from there.
    pub settled: bool,
    /// Whether the look came at the end of registration, before the final
    /// stage, and not at a sphere solve (see `bundle.restart_early_at_images`).
    /// Then `change` is where the whole model's alignment to the map puts
    /// the image (`alignment_would_move` from where registration left it),
    /// which is where the run is mapped again from when it stops there, and
    /// `settled` says only whether that alignment moves it.
    pub end_of_registration: bool,
    /// At the end of registration: the share of the points on the surfaces
    /// their images see, after that alignment (the run stops there only at
    /// 0.8 or more).
    pub seen_share: Option<f64>,
}

/// A second run started from where the first run's initial image ended,
/// when that was far from its given pose.
#[derive(Clone, Debug, Default, Serialize)]
pub struct RestartRecord {
    /// How far the first run's initial image ended (or was, when it stopped
    /// early) from where that run started it: the given pose, or, for a
    /// `restart` after a kept `early_restart`, the early look's pose.
    pub first_change: PoseChangeRecord,
    /// When the first run stopped early (`bundle.restart_early_at_images`),
    /// at a sphere solve or at the end of its registration (before its final
    /// stage): the number of images it had registered.
    pub first_stopped_at_images: Option<usize>,
    /// The first run's `fit_share` (none when it stopped early), and the
    /// second's when it finished.
    pub first_fit_share: Option<f64>,
    pub second_fit_share: Option<f64>,
    /// True when this model is the second run's; false when that run failed
    /// (`second_error`) and the first run is kept.
    pub second_kept: bool,
    pub second_error: Option<String>,
    /// In an `early_restart`: the look the run from the early look took
    /// itself, whether it stopped that run or the run went on (the slide
    /// look of a run from a look taken mid-slide, or the look at the end of
    /// its registration). The top-level `early_look` is the first run's.
    pub second_look: Option<EarlyLookRecord>,
    /// When the first run came from the retry (its run free from the start
    /// kept) and the second is kept: the retry's record.
    pub first_retry: Option<Box<RetryRecord>>,
    /// Wall time of each run, seconds (the first's with its retry). A
    /// `restart` after a kept `early_restart` has that record's second run
    /// as its first: the two fields are the same run, counted once.
    pub first_run_s: f64,
    pub second_run_s: f64,
}

/// A second run with the initial image held at its given pose.
#[derive(Clone, Debug, Default, Serialize)]
pub struct RetryRecord {
    /// What the first run showed (its error, or a nearly free direction with
    /// the initial image moved).
    pub reason: String,
    /// True when this model is the held run's.
    pub held_kept: bool,
    /// True when this model is the run with the initial image free from the
    /// start (mapped when the first run held it for its first
    /// `fix_initial_for` registrations and failed).
    pub free_kept: bool,
    /// What was decided, and why.
    pub outcome: String,
    /// Wall time of the first run, of the free run and of the held run
    /// (each when it ran), seconds (`stages` and `solves` are the kept
    /// run's; the whole call took them all).
    pub first_run_s: f64,
    pub free_run_s: Option<f64>,
    pub held_run_s: Option<f64>,
}

/// One camera's intrinsics (COLMAP's parameter order for its model).
#[derive(Clone, Debug, Default, Serialize)]
pub struct IntrinsicsRecord {
    pub camera_id: u32,
    pub model: String,
    /// "every solve", "final rounds" or "held" (a given focal length that
    /// the probe found right, or with `fixed`); "probed" only before the
    /// probe ran.
    pub refined: String,
    /// A given focal length (`auto`): its relative change in one solve with
    /// the intrinsics free after the final rounds; above
    /// `bundle.refine_intrinsics_min_change` it is refined, else held.
    pub probe_focal_change: Option<f64>,
    /// A guessed focal length: the value the pairs' fundamental matrices
    /// gave (pixels), where self-calibration started unless the map gave
    /// one (`focal_from_map_px`).
    pub focal_from_pairs_px: Option<f64>,
    /// A guessed focal length of the initial image's camera (and of the
    /// guessed cameras of the same model and image size): the value that
    /// makes the map and the initial pair agree best, where
    /// self-calibration started (pixels; it replaces the pairs' value).
    pub focal_from_map_px: Option<f64>,
    /// A guessed focal length of another camera: the value at which PnP
    /// placed its first image best against the model's points, where its
    /// self-calibration started (pixels).
    pub focal_from_points_px: Option<f64>,
    /// Solves whose refinement took these intrinsics out of COLMAP's bounds
    /// (each solved again with them held); from 2 on they were held for the
    /// rest of the run.
    pub implausible_refinements: u32,
    pub database_params: Vec<f64>,
    pub final_params: Vec<f64>,
    /// Final mean focal length over the database's, minus 1.
    pub focal_change: f64,
    /// A focal length refined to the end: one standard deviation of its
    /// final value (mean of fx and fy where the model has both), pixels,
    /// from the same final solve as the images' `pose_uncertainty` (with
    /// the poses and points marginalised); `None` when held or not computed.
    pub focal_sigma_px: Option<f64>,
    /// The same, cluster-robust (`bundle.uncertainty_cluster_m`).
    pub clustered_focal_sigma_px: Option<f64>,
    /// Then also each parameter's sigma, in `final_params`' order (`null`
    /// for the held ones, e.g. the principal point).
    pub params_sigma: Option<Vec<Option<f64>>>,
    /// The same, cluster-robust.
    pub clustered_params_sigma: Option<Vec<Option<f64>>>,
}

/// One final round: how far its solve moved the camera centres, metres.
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct RoundRecord {
    /// 1, or 2 for the rounds after the probe of given focal lengths.
    pub pass: u32,
    pub median_move_m: f64,
    pub max_move_m: f64,
}

impl MapReport {
    /// `focal_px` as the PnP sweep's value (`focal_from_points_px`) of `cameras`.
    pub fn record_focal_from_points(&mut self, cameras: &[CameraId], focal_px: f64) {
        for rec in &mut self.intrinsics {
            if cameras.contains(&CameraId(rec.camera_id)) {
                rec.focal_from_points_px = Some(focal_px);
            }
        }
    }

    /// One line on the images not in the model, by reason (with their
    /// names, the first few of each), or `None` when every image is in it.
    pub fn not_registered_summary(&self) -> Option<String> {
        let missing: Vec<&ImageRecord> = self.images.iter().filter(|r| !r.registered).collect();
        if missing.is_empty() {
            return None;
        }
        let names = |keep: &dyn Fn(&NotRegistered) -> bool| -> (usize, String) {
            let all: Vec<String> = missing
                .iter()
                .filter(|r| r.not_registered.as_ref().is_some_and(keep))
                .map(|r| r.name.clone())
                .collect();
            (all.len(), first_few(all, ", "))
        };
        let mut parts = Vec::new();
        let (n, list) = names(&|w| matches!(w, NotRegistered::NoMatches));
        if n > 0 {
            parts.push(format!(
                "{n} without verified matches to any image ({list})"
            ));
        }
        let mut groups: BTreeMap<u32, usize> = BTreeMap::new();
        for r in &missing {
            if let Some(NotRegistered::OtherGroup {
                group_size,
                group_first_image_id,
            }) = &r.not_registered
            {
                groups.insert(*group_first_image_id, *group_size);
            }
        }
        if !groups.is_empty() {
            let n: usize = groups.values().sum();
            let listed: Vec<String> = groups
                .iter()
                .map(|(id, size)| {
                    let name = self
                        .images
                        .iter()
                        .find(|r| r.image_id == *id)
                        .map_or(String::new(), |r| format!(" ({})", r.name));
                    format!("{size} images from id {id}{name}")
                })
                .collect();
            parts.push(format!(
                "{n} in {} group{} matched among themselves but not to the model's images ({}): give one of each group's images as another --init-image, with its --init-pose, and each group is mapped from it into the same model",
                groups.len(),
                if groups.len() == 1 { "" } else { "s" },
                first_few(listed, "; ")
            ));
        }
        let (n, list) = names(&|w| matches!(w, NotRegistered::GroupFailed { .. }));
        if n > 0 {
            parts.push(format!(
                "{n} given to a group's run that failed ({list}; report.json: groups[].error)"
            ));
        }
        let (n, list) = names(&|w| matches!(w, NotRegistered::TooFewModelPoints { .. }));
        if n > 0 {
            parts.push(format!(
                "{n} in the model's group of images but never seeing the 4 of its points a pose needs ({list})"
            ));
        }
        let (n, list) = names(&|w| matches!(w, NotRegistered::PoseNotFound));
        if n > 0 {
            parts.push(format!("{n} whose pose was not found ({list})"));
        }
        Some(format!(
            "{} of {} images not registered: {} (report.json: images -> not_registered)",
            missing.len(),
            self.images.len(),
            parts.join("; ")
        ))
    }

    /// The model's counts, with the mean track length and reprojection
    /// error from the observations and their summed reprojection errors.
    pub fn set_totals(
        &mut self,
        num_images: usize,
        num_registered: usize,
        num_points: usize,
        observations: usize,
        error_sum_px: f64,
    ) {
        self.num_images = num_images;
        self.num_registered = num_registered;
        self.num_points = num_points;
        self.num_observations = observations;
        self.mean_track_length = if num_points > 0 {
            observations as f64 / num_points as f64
        } else {
            0.0
        };
        self.mean_reprojection_error_px = if observations > 0 {
            error_sum_px / observations as f64
        } else {
            0.0
        };
    }

    pub fn record_mut(&mut self, image: ImageId) -> Option<&mut ImageRecord> {
        self.images.iter_mut().find(|r| r.image_id == image.0)
    }

    /// Fills the final per-image and global numbers from the state.
    pub fn finish(&mut self, state: &MapState) {
        let mut total_err = 0.0;
        let mut total_obs = 0usize;
        let groups = ImageGroups::of(state);
        for rec in &mut self.images {
            let id = ImageId(rec.image_id);
            let img = &state.images[&id];
            rec.registered = img.is_registered();
            rec.registration_index = state.registration_order.iter().position(|&i| i == id);
            rec.not_registered = (!rec.registered)
                .then(|| groups.why_not_registered(id, rec.attempts, img.num_visible));
            let mut sum = 0.0;
            let mut n = 0usize;
            let mut plane_sum = 0.0;
            let (mut n_proj, mut n_near, mut n_ground) = (0usize, 0usize, 0usize);
            if let Some(pose) = img.cam_from_world {
                for (k, p) in img.point3d.iter().enumerate() {
                    let Some(p) = p else { continue };
                    let point = &state.points[p];
                    if let Some(plane) = &point.plane {
                        plane_sum += plane.distance_m(&point.xyz);
                        match plane.family {
                            PlaneFamily::Projection => n_proj += 1,
                            PlaneFamily::Ground => n_ground += 1,
                            _ => n_near += 1,
                        }
                    }
                    if let Some(e2) = super::geometry::reprojection_error_sq(
                        state.camera_of(id),
                        &pose,
                        &state.points[p].xyz,
                        &img.keypoints[k],
                    ) {
                        sum += e2.sqrt();
                        n += 1;
                    }
                }
            }
            rec.num_observations = n;
            rec.num_projection_planes = n_proj;
            rec.num_nearest_planes = n_near;
            rec.num_ground_planes = n_ground;
            let n_planes = n_proj + n_near + n_ground;
            rec.mean_plane_distance_m = (n_planes > 0).then(|| plane_sum / n_planes as f64);
            rec.mean_reprojection_error_px = (n > 0).then(|| sum / n as f64);
            total_err += sum;
            total_obs += n;
        }
        self.set_totals(
            state.images.len(),
            state.num_registered(),
            state.points.len(),
            total_obs,
            total_err,
        );
        for rec in &mut self.intrinsics {
            if let Some(c) = state.cameras.get(&CameraId(rec.camera_id)) {
                let before = Camera {
                    params: rec.database_params.clone(),
                    ..c.clone()
                };
                rec.final_params = c.params.clone();
                rec.implausible_refinements = state
                    .implausible_refinements
                    .get(&state.intrinsics_of(c.id))
                    .copied()
                    .unwrap_or(0);
                rec.focal_change = c.mean_focal_length() / before.mean_focal_length() - 1.0;
            }
        }
    }
}

/// The first four of `items` joined by `separator`, and how many more.
fn first_few(items: Vec<String>, separator: &str) -> String {
    const SHOWN: usize = 4;
    let more = items.len().saturating_sub(SHOWN);
    let mut list = items
        .into_iter()
        .take(SHOWN)
        .collect::<Vec<_>>()
        .join(separator);
    if more > 0 {
        list.push_str(&format!("{separator}and {more} more"));
    }
    list
}

/// The image graph's connected components (images linked by verified
/// pairs), and which of them hold a registered image.
struct ImageGroups {
    /// Image -> its group's smallest image id.
    group_of: BTreeMap<ImageId, ImageId>,
    /// Group -> its number of images.
    sizes: BTreeMap<ImageId, usize>,
    /// Groups with a registered image.
    in_model: BTreeSet<ImageId>,
}

impl ImageGroups {
    fn of(state: &MapState) -> Self {
        let group_of = state.graph.image_groups(state.images.keys().copied());
        let sizes = CorrespondenceGraph::group_sizes(&group_of);
        let in_model = state
            .images
            .values()
            .filter(|img| img.is_registered())
            .map(|img| group_of[&img.id])
            .collect();
        Self {
            group_of,
            sizes,
            in_model,
        }
    }

    /// Why `image` (not registered; `attempts` pose trials, seeing
    /// `points_seen` of the model's points) is not in the model.
    fn why_not_registered(
        &self,
        image: ImageId,
        attempts: usize,
        points_seen: usize,
    ) -> NotRegistered {
        let group = self.group_of[&image];
        let size = self.sizes[&group];
        if size == 1 {
            NotRegistered::NoMatches
        } else if !self.in_model.contains(&group) {
            NotRegistered::OtherGroup {
                group_size: size,
                group_first_image_id: group.0,
            }
        } else if attempts == 0 {
            NotRegistered::TooFewModelPoints { points_seen }
        } else {
            NotRegistered::PoseNotFound
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sfm::associate::SolveKind;

    /// Images 1-2 (in the model), 3 linked to them, 4-5 a group of their
    /// own, 6 alone.
    fn groups() -> ImageGroups {
        let id = ImageId;
        let group_of: BTreeMap<ImageId, ImageId> = [(1, 1), (2, 1), (3, 1), (4, 4), (5, 4), (6, 6)]
            .into_iter()
            .map(|(a, b)| (id(a), id(b)))
            .collect();
        ImageGroups {
            group_of,
            sizes: [(id(1), 3), (id(4), 2), (id(6), 1)].into_iter().collect(),
            in_model: [id(1)].into_iter().collect(),
        }
    }

    #[test]
    fn the_run_log_numbers_the_runs_and_marks_the_kept_ones() {
        let log = RunLog::default();
        let push = |outcome: &str| {
            let stages = vec![StageRecord::new("map index", 0.5)];
            log.push(
                outcome.to_owned(),
                1.5,
                stages,
                vec![SolveRecord::empty(SolveKind::Local, outcome.len())],
            )
        };
        assert_eq!(push("finished"), 0);
        assert_eq!(push("failed: off the map"), 1);
        assert_eq!(push("finished"), 2);
        let records = log.records(&BTreeSet::from([2]));
        let summary: Vec<(usize, bool, &str)> = records
            .iter()
            .map(|r| (r.index, r.kept, r.outcome.as_str()))
            .collect();
        assert_eq!(
            summary,
            [
                (0, false, "finished"),
                (1, false, "failed: off the map"),
                (2, true, "finished")
            ]
        );
        assert_eq!(records[1].stages[0].name, "map index");
        // The runs set aside keep their solves; the kept one's are the
        // report's own.
        let solved: Vec<Vec<usize>> = records
            .iter()
            .map(|r| r.solves.iter().map(|s| s.num_registered).collect())
            .collect();
        assert_eq!(solved, [vec![8], vec![19], vec![]]);
        let json = serde_json::to_value(&records).unwrap();
        assert_eq!(json[1]["solves"][0]["num_registered"], 19);
        assert!(json[2].get("solves").is_none(), "{}", json[2]);
        let none = log.records(&BTreeSet::new());
        assert!(none.iter().all(|r| !r.kept && r.solves.len() == 1));
    }

    #[test]
    fn an_image_tried_in_the_models_group_is_a_pose_not_found() {
        let g = groups();
        assert_eq!(
            g.why_not_registered(ImageId(3), 2, 40),
            NotRegistered::PoseNotFound
        );
        assert_eq!(
            g.why_not_registered(ImageId(3), 0, 2),
            NotRegistered::TooFewModelPoints { points_seen: 2 }
        );
        // Another group's image is that whatever it was tried.
        assert_eq!(
            g.why_not_registered(ImageId(5), 0, 0),
            NotRegistered::OtherGroup {
                group_size: 2,
                group_first_image_id: 4
            }
        );
        assert_eq!(
            g.why_not_registered(ImageId(6), 0, 0),
            NotRegistered::NoMatches
        );
    }
}
