//! The runs of the mapper: what [`super::mapper`]'s single run is wrapped in
//! so that a user's rough or wrong initial pose still ends in the right model
//! or a clear error.
//!
//! * [`run_mapper_with_priors`]: the run from the given pose; the retries
//!   when the map did not hold the model (`bundle.retry_holding_initial`); a
//!   second run from where the initial image ended
//!   (`bundle.restart_from_refined_pose`) after the retry's run free from the
//!   start, and after the first run only with `bundle.restart_first_run`
//!   or in a database of `bundle.restart_first_run_from_images` or more,
//!   with an early look that maps again from where the initial image is once
//!   the model holds it (`bundle.restart_early_at_images`).
//! * [`run_mapper_from_pose`]: that, followed by a search of the map around
//!   the pose when the run fails as if the pose were off.
//! * [`run_mapper_searching`]: the model mapped without the map's planes,
//!   placed on the map by [`search_placement`], then mapped from each close
//!   placement; the best fit kept.
use std::collections::{BTreeMap, BTreeSet};
use std::time::Instant;

use super::align::{SimilarityConstraint, MIN_SIMILARITY_CONSTRAINT, WEAK_SIMILARITY_CONSTRAINT};
use super::associate::NearestNeighbourAssociator;
use super::localise::{
    search_placement, Search, SearchError, SearchOptions, SearchRegion, SAME_PLACE_M,
    SPARSE_MAP_RADIUS_PER_SPACING,
};
use super::mapper::{
    beyond, firmly_held, initial_pose_moved_far, map_once, map_until, options_for_map, pose_change,
    pose_change_beyond, EndLook, LookPlan, MapperError, MapperInputs, MapperOutput, Progress,
    RunEnd, Start, EARLY_LOOK_MIN_CHANGE, EARLY_LOOK_MIN_TURN_DEG, EARLY_LOOK_STEADY,
    GOOD_FIT_SHARE, SEARCH_MIN_CONSTRAINT,
};
use super::options::{AssociationKind, MapperOptions};
use super::report::{EarlyLookRecord, PoseChangeRecord, RestartRecord, RetryRecord};
use crate::estimators::similarity::Sim3;
use crate::io::database::DatabaseSnapshot;
use crate::map::index::MapIndex;
use crate::map::PointCloud;
use crate::scene::{ImageId, Rigid3};

/// Runs the whole mapper without pose priors.
pub fn run_mapper(
    db: &DatabaseSnapshot,
    cloud: &PointCloud,
    init_image: ImageId,
    init_cam_from_world: &Rigid3,
    options: &MapperOptions,
    progress: Progress<'_>,
) -> Result<MapperOutput, MapperError> {
    let inputs = MapperInputs {
        db,
        cloud,
        known_poses: &BTreeMap::new(),
        held_cameras: &BTreeSet::new(),
        run_log: None,
        image_dir: None,
    };
    run_mapper_with_priors(inputs, init_image, init_cam_from_world, options, progress)
}

/// Runs the whole mapper. `inputs.known_poses` become soft prior residuals
/// in every solve (weights `bundle.prior_position_weight`, `bundle.prior_rotation_weight`);
/// an image with a full known pose that PnP could not register is placed at
/// it at the end (flagged `placed_by_prior` in the report) and refined by the
/// final bundle adjustments. When the map did not hold the model, the run is
/// repeated with the initial image held at its given pose
/// (`bundle.retry_holding_initial`, see [`retry_reason`]); when the initial
/// image ended far from its given pose, it is mapped again from where it
/// ended (`bundle.restart_from_refined_pose`, see [`restart_reason`]).
pub fn run_mapper_with_priors(
    inputs: MapperInputs<'_>,
    init_image: ImageId,
    init_cam_from_world: &Rigid3,
    options: &MapperOptions,
    progress: Progress<'_>,
) -> Result<MapperOutput, MapperError> {
    let runs = PoseRuns {
        inputs,
        init_image,
        given: *init_cam_from_world,
        options,
    };
    let num_images = inputs.db.images.len();
    let start = runs.start();

    // The first run, which may stop early to map again from where the
    // initial image is (`bundle.restart_early_at_images`), when it is to
    // be mapped again at all (`bundle.restart_first_run`, or a database of
    // `bundle.restart_first_run_from_images` or more).
    let restart_first = options.bundle.restarts_first_run(num_images);
    let look_at = early_look_at(num_images, options).filter(|_| restart_first);
    let end_look = first_run_end_look(options).filter(|_| restart_first);
    let started = Instant::now();
    let early = map_until(inputs, &start, options, look_at, end_look, &mut *progress);
    let early_s = started.elapsed().as_secs_f64();
    let (first_outcome, failed_early) = match early {
        Ok(RunEnd::Moved {
            cam_from_world,
            look,
        }) => match runs.run_from_first_look(cam_from_world, look, early_s, &mut *progress) {
            Ok(out) => return Ok(out),
            Err(failed) => (None, Some(*failed)),
        },
        Ok(RunEnd::Finished(out)) => (Some((Ok(*out), early_s)), None),
        Err(e) => (Some((Err(e), early_s)), None),
    };

    // The first run to its end (as it finished, or again after a failed
    // early restart), with the retries.
    let started = Instant::now();
    // A run that finished at once was timed then.
    let finished_s = first_outcome.as_ref().map_or(0.0, |(_, s)| *s);
    let first_outcome = first_outcome.unwrap_or_else(|| {
        let outcome = map_once(inputs, &start, options, &mut *progress);
        (outcome, started.elapsed().as_secs_f64())
    });
    let run = |which: RetryRun, run_options: &MapperOptions| {
        let started = Instant::now();
        let outcome = match which {
            RetryRun::Held => map_once(inputs, &start, run_options, &mut *progress),
            RetryRun::Free => runs.free_run(run_options, &mut *progress),
        };
        (outcome, started.elapsed().as_secs_f64())
    };
    let mut first = run_with_retries(options, num_images, first_outcome, run)?;
    let first_run_s = finished_s + started.elapsed().as_secs_f64();
    if let Some((record, look)) = failed_early {
        first.report.early_restart = Some(record);
        first.report.early_look = Some(look);
    }
    Ok(match restart_reason(&first, num_images, options) {
        Some(change) => runs.restart_from_end(first, change, first_run_s, &mut *progress),
        None => first,
    })
}

/// The runs of [`run_mapper_with_priors`] from one given pose of the
/// initial image (`given`, as the user gave it) and what they share.
struct PoseRuns<'a> {
    inputs: MapperInputs<'a>,
    init_image: ImageId,
    given: Rigid3,
    options: &'a MapperOptions,
}

impl PoseRuns<'_> {
    /// The run from the given pose.
    fn start(&self) -> Start<'static> {
        self.start_at(self.given)
    }

    /// A run with the initial image at `cam_from_world`.
    fn start_at(&self, cam_from_world: Rigid3) -> Start<'static> {
        Start::InitialPose {
            image: self.init_image,
            cam_from_world,
            rough: false,
            pair_scale: None,
        }
    }

    /// A run from where the initial image ended (or was, when a run
    /// stopped early): kept only within the accepted change from the pose
    /// the user gave, as the first run is, and its change measured from
    /// there. With `look` it may stop at its own look, with `end` at the end
    /// of its registration ([`EndLook`]).
    fn run_from_until(
        &self,
        refined: &Rigid3,
        look: Option<LookPlan>,
        end: Option<EndLook>,
        progress: &mut dyn FnMut(usize, usize),
    ) -> Result<RunEnd, MapperError> {
        let start = self.start_at(*refined);
        let mut out = match map_until(self.inputs, &start, self.options, look, end, progress)? {
            RunEnd::Finished(out) => out,
            moved => return Ok(moved),
        };
        let change = out
            .reconstruction
            .pose(self.init_image)
            .map(|pose| pose_change(&pose, &self.given));
        if let Some(c) = change.filter(|c| pose_change_beyond(c, &self.options.bundle, 1.0)) {
            return Err(MapperError::InitialPoseFarOff {
                moved_m: c.moved_m,
                turned_deg: c.turned_deg,
                max_m: self.options.bundle.max_initial_pose_change_m,
                max_deg: self.options.bundle.max_initial_pose_change_deg,
                fit: None,
            });
        }
        out.report.initial_pose_change = change;
        Ok(RunEnd::Finished(out))
    }

    /// [`Self::run_from_until`] without a look: to its end.
    fn run_from(
        &self,
        refined: &Rigid3,
        progress: &mut dyn FnMut(usize, usize),
    ) -> Result<MapperOutput, MapperError> {
        match self.run_from_until(refined, None, None, progress)? {
            RunEnd::Finished(out) => Ok(*out),
            RunEnd::Moved { .. } => unreachable!("a run without a look finishes"),
        }
    }

    /// Maps `first` (`first_run_s` seconds) again from where its initial
    /// image ended, `change` from where it started; keeps `first` when that
    /// run fails.
    fn restart_from_end(
        &self,
        mut first: MapperOutput,
        change: PoseChangeRecord,
        first_run_s: f64,
        progress: &mut dyn FnMut(usize, usize),
    ) -> MapperOutput {
        let refined = first
            .reconstruction
            .pose(self.init_image)
            .expect("a run that moved the initial image has its pose");
        log::info!(
            "the initial image ended {:.3} m and {:.2} deg from where the run started it: mapping again from where it ended (option bundle.restart_from_refined_pose)",
            change.moved_m,
            change.turned_deg
        );
        let started = Instant::now();
        let second = self.run_from(&refined, progress);
        let mut record = RestartRecord {
            first_change: change,
            first_fit_share: first.report.fit_share,
            first_run_s,
            second_run_s: started.elapsed().as_secs_f64(),
            ..Default::default()
        };
        match second {
            Ok(mut out) => {
                record.second_fit_share = out.report.fit_share;
                record.second_kept = true;
                record.first_retry = first.report.retry.take().map(Box::new);
                out.report.early_restart = first.report.early_restart.take();
                out.report.early_look = first.report.early_look.take();
                out.report.restart = Some(record);
                out
            }
            Err(e) => {
                log::warn!(
                    "the run from where the initial image ended failed; kept the run before: {e}"
                );
                record.second_error = Some(e.to_string());
                first.report.restart = Some(record);
                first
            }
        }
    }

    /// The first run stopped at its look (`look`, after `early_s` seconds)
    /// with the initial image at `cam_from_world`: the run from there, kept
    /// or mapped once more, or, when it failed or had not settled, the
    /// record of that (`early_restart`) and the look for the first run to
    /// its end.
    fn run_from_first_look(
        &self,
        cam_from_world: Rigid3,
        look: EarlyLookRecord,
        early_s: f64,
        progress: &mut dyn FnMut(usize, usize),
    ) -> Result<MapperOutput, Box<(RestartRecord, EarlyLookRecord)>> {
        let EarlyLookRecord {
            registered, change, ..
        } = look;
        log::info!(
            "{} the initial image is {:.3} m and {:.2} deg from its given pose: mapping again from there (options bundle.restart_from_refined_pose, restart_early_at_images)",
            if look.end_of_registration {
                format!("at the end of registration ({registered} images, before the final stage)")
            } else {
                format!("at {registered} images")
            },
            change.moved_m,
            change.turned_deg
        );
        let started = Instant::now();
        // A run the retry would follow ([`retry_reason`]: the map leaves
        // the model nearly free and the image moved far) counts as failed
        // here: the first run from the given pose, with the retries,
        // decides then. It stops at the end of its registration when it
        // moved the image as far again ([`LOOK_RUN_END_LOOK`]).
        let second = self.run_from_until(
            &cam_from_world,
            look_run_plan(self.inputs.db.images.len(), &look, self.options),
            LOOK_RUN_END_LOOK,
            &mut *progress,
        );
        let second_run_s = started.elapsed().as_secs_f64();
        let mut record = RestartRecord {
            first_change: change,
            first_stopped_at_images: Some(registered),
            first_run_s: early_s,
            second_run_s,
            // That run's own look, stopped there or not (every kept
            // result below gets the first run's look as `early_look`).
            second_look: match &second {
                Ok(RunEnd::Moved { look: again, .. }) => Some(*again),
                Ok(RunEnd::Finished(out)) => out.report.early_look,
                Err(_) => None,
            },
            ..Default::default()
        };
        // The run from there must leave the image where the look put it
        // (within the look's own bar). One that moves it that far again
        // was started from a model that had not settled, and counts as
        // failed: the seed-2 60-image corridor from 0.3 m / 3 deg off was
        // looked at at 17 images mid-slide along the corridor (0.38 m
        // from the given pose), its run from there moved the image 0.55 m
        // further, and mapped once more from that run's end it came out
        // 0.63 m off along the corridor without an error (fit 0.85); its
        // first run to the end had left the image 0.300 m / 3.00 deg from
        // the given pose, right. Unless the look's rotation held and the
        // run fits the map ([`slid_back`]): then the look was taken
        // mid-slide and the run undid the slide, and it is mapped again
        // from where it ended, as a first run that moved the image is.
        // The run from the look stopped at the end of its registration
        // having moved the image that far again ([`LOOK_RUN_END_LOOK`]:
        // it fits the map there), or once it slid after a look taken
        // while the image was moving or loosely held
        // ([`look_run_plan`]): the same,
        // before the rest of that run, if the image is still within half
        // the accepted change of the given pose (each look measures from
        // where its own run started; two looks must not add up to a
        // place the first run would not have been allowed to go).
        let second = match second {
            Ok(RunEnd::Moved {
                cam_from_world: moved_to,
                look: again,
            }) if again.change.turned_deg < EARLY_LOOK_MIN_TURN_DEG
                && !initial_pose_moved_far(
                    &pose_change(&moved_to, &self.given),
                    &self.options.bundle,
                ) =>
            {
                log::info!(
                    "the run from where the initial image was at {registered} images moved it {:.3} m and {:.2} deg again by {} and fits the map ({:.1} % of the points on the surfaces their images see): the look was taken mid-slide, so it is mapped again from there",
                    again.change.moved_m,
                    again.change.turned_deg,
                    stopped_at(&again),
                    again.seen_share.unwrap_or(f64::NAN) * 100.0
                );
                record.second_kept = true;
                let started = Instant::now();
                match self.run_from(&moved_to, &mut *progress) {
                    Ok(mut out) => {
                        out.report.restart = Some(RestartRecord {
                            first_change: again.change,
                            first_stopped_at_images: Some(again.registered),
                            first_run_s: second_run_s,
                            second_run_s: started.elapsed().as_secs_f64(),
                            second_fit_share: out.report.fit_share,
                            second_kept: true,
                            ..Default::default()
                        });
                        out.report.early_restart = Some(record);
                        out.report.early_look = Some(look);
                        return Ok(out);
                    }
                    Err(e) => {
                        record.second_kept = false;
                        Err(format!(
                            "it moved the initial image {:.3} m and {:.2} deg again, and the run from there failed: {e}",
                            again.change.moved_m, again.change.turned_deg
                        ))
                    }
                }
            }
            Ok(RunEnd::Moved {
                cam_from_world: moved_to,
                look: again,
            }) => {
                let from_given = pose_change(&moved_to, &self.given);
                Err(format!(
                    "its initial image moved {:.3} m and {:.2} deg again from where the look put it by {} ({:.3} m and {:.2} deg from the given pose): the model had not settled",
                    again.change.moved_m,
                    again.change.turned_deg,
                    stopped_at(&again),
                    from_given.moved_m,
                    from_given.turned_deg
                ))
            }
            Ok(RunEnd::Finished(out)) => checked_look_run(Ok(*out), self.options),
            Err(e) => checked_look_run(Err(e), self.options),
        };
        let moved = second.as_ref().ok().and_then(|out| {
            out.reconstruction
                .pose(self.init_image)
                .map(|pose| pose_change(&pose, &cam_from_world))
                .filter(|c| beyond(c, EARLY_LOOK_MIN_CHANGE))
        });
        let second = match (second, moved) {
            (Ok(mut out), Some(c)) if slid_back(&c, &out) => {
                log::info!(
                    "the run from where the initial image was at {registered} images moved it {:.3} m and {:.2} deg again and fits the map (fit {:.3}): the look was taken mid-slide, so it is mapped again from where that run ended",
                    c.moved_m,
                    c.turned_deg,
                    out.report.fit_share.unwrap_or(f64::NAN)
                );
                record.second_fit_share = out.report.fit_share;
                record.second_kept = true;
                out.report.early_restart = Some(record);
                out.report.early_look = Some(look);
                return Ok(self.restart_from_end(out, c, second_run_s, &mut *progress));
            }
            (Ok(out), Some(c)) => Err(format!(
                "its initial image moved {:.3} m and {:.2} deg again from where the look put it (fit {:.3}): the model had not settled",
                c.moved_m,
                c.turned_deg,
                out.report.fit_share.unwrap_or(f64::NAN)
            )),
            (second, _) => second,
        };
        match second {
            Ok(mut out) => {
                record.second_fit_share = out.report.fit_share;
                record.second_kept = true;
                out.report.early_restart = Some(record);
                out.report.early_look = Some(look);
                Ok(out)
            }
            Err(e) => {
                log::warn!(
                    "the run from where the initial image was at {registered} images failed: {e}\nmapping from the given pose to the end"
                );
                record.second_error = Some(e);
                Err(Box::new((record, look)))
            }
        }
    }

    /// The retry's run free from the start (`run_options`), stopped at its
    /// look ([`free_run_look`]) and mapped again from there.
    fn free_run(
        &self,
        run_options: &MapperOptions,
        progress: &mut dyn FnMut(usize, usize),
    ) -> Result<MapperOutput, MapperError> {
        let started = Instant::now();
        let look = free_run_look(self.inputs.db.images.len(), run_options);
        let end = first_run_end_look(run_options);
        let (cam_from_world, look) = match map_until(
            self.inputs,
            &self.start(),
            run_options,
            look,
            end,
            &mut *progress,
        )? {
            RunEnd::Finished(out) => return Ok(*out),
            RunEnd::Moved {
                cam_from_world,
                look,
            } => (cam_from_world, look),
        };
        let look_s = started.elapsed().as_secs_f64();
        log::info!(
            "the run free from the start: at {} the initial image is {:.3} m and {:.2} deg from its given pose: mapping again from there",
            stopped_at(&look),
            look.change.moved_m,
            look.change.turned_deg
        );
        let from_look = Instant::now();
        match self.run_from(&cam_from_world, &mut *progress) {
            Ok(out) => Ok(kept_run_from_free_look(
                out,
                self.init_image,
                &cam_from_world,
                (look, look_s, from_look.elapsed().as_secs_f64()),
                |out, change, first_run_s| {
                    self.restart_from_end(out, change, first_run_s, &mut *progress)
                },
            )),
            Err(e) => {
                log::warn!(
                    "the run from where the run free from the start put the initial image failed: {e}\nthe run free from the start to its end"
                );
                map_once(self.inputs, &self.start(), run_options, progress)
            }
        }
    }
}

/// The first run's look at the end of its registration ([`EndLook`]): with
/// the early look on (`bundle.restart_early_at_images` not 0, the restart
/// on, the map's planes used), a first run whose initial image turned more
/// than [`EARLY_LOOK_MIN_TURN_DEG`] from its given pose would be mapped
/// again from where it ends ([`RESTART_MIN_CHANGE`]): it stops before its
/// final stage (whose result the run from there replaces) and is mapped
/// again from where the whole-model alignment puts the image. Only a turn
/// counts, as at the early look: the final stage brings back what moved
/// less. From exact poses the seed-0 yard's image had turned 0.24 deg at
/// the end of registration and ended 0.02 deg from its given pose; from
/// 0.3 m / 3 deg off the images had turned 2.9-3.5 deg there. Not with
/// `bundle.hold_initial_in_final_rounds`.
fn first_run_end_look(options: &MapperOptions) -> Option<EndLook> {
    let b = &options.bundle;
    // With `hold_initial_in_final_rounds` the run ends with the image at its
    // given pose and is not mapped again.
    (b.restart_from_refined_pose
        && b.restart_early_at_images != 0
        && !b.hold_initial_in_final_rounds
        && options.association.kind != AssociationKind::None)
        .then_some(EndLook {
            beyond: RESTART_MIN_CHANGE,
            min_turn_deg: EARLY_LOOK_MIN_TURN_DEG,
        })
}

/// The look at the end of registration of the run from the early look: it
/// stops there when it moved the image as far again as the look's own bar
/// ([`EARLY_LOOK_MIN_CHANGE`]), which the finished run would then be judged
/// by (mapped again from where it ended, or failed).
const LOOK_RUN_END_LOOK: Option<EndLook> = Some(EndLook {
    beyond: EARLY_LOOK_MIN_CHANGE,
    min_turn_deg: 0.0,
});

/// Where a run stopped at `look`, for the log: "the end of its
/// registration" or "N images".
fn stopped_at(look: &EarlyLookRecord) -> String {
    if look.end_of_registration {
        "the end of its registration".to_string()
    } else {
        format!("{} images", look.registered)
    }
}

/// A finished run from the early look, or its error, as the look's
/// outcome: a run the retry would follow ([`retry_reason`]) counts as
/// failed.
fn checked_look_run(
    run: Result<MapperOutput, MapperError>,
    options: &MapperOptions,
) -> Result<MapperOutput, String> {
    match retry_reason(&run, options) {
        Some(why) => Err(why),
        None => run.map_err(|e| e.to_string()),
    }
}

/// Whether a run from the early look that moved the initial image
/// `change` again from where the look put it (beyond
/// [`EARLY_LOOK_MIN_CHANGE`]) undid a slide: the image kept the look's
/// rotation (turned less than [`EARLY_LOOK_MIN_TURN_DEG`]; the map's normals
/// fix the rotation where a corridor leaves the position free) and the
/// model fits the map ([`GOOD_FIT_SHARE`]). The fresh seed-0 100-image
/// corridor from 0.3 m / 3 deg off was looked at with the model 0.23 m
/// along the corridor (settled by the trial); its run from there moved the
/// image 0.294 m and 0.03 deg, to 0.30 m / 3.0 deg from the given pose
/// (right), fit 0.929, and came out 2.4 mm off where a run from its end
/// gives 1.2 mm. The seed-2 60-image corridor's wrong run from its look fit
/// 0.85.
fn slid_back(change: &PoseChangeRecord, out: &MapperOutput) -> bool {
    change.turned_deg < EARLY_LOOK_MIN_TURN_DEG
        && out.report.fit_share.is_some_and(|f| f >= GOOD_FIT_SHARE)
}

/// When the first run looks at its initial image (`bundle.restart_early_at_images`,
/// see [`run_mapper_with_priors`]) in a database of `num_images`: from
/// `restart_early_at_images` (16) images on in a database of at least three
/// times that many, at the first sphere solve after the image's release
/// (`bundle.fix_initial_for`). In a smaller database from a third of its
/// images on (and after the release), and only at a sphere solve that moved
/// the image at most [`super::mapper::EARLY_LOOK_STEADY`] from where the
/// one before left it (it converges over the first few images after its
/// release, so never at the first solve after it) while the map holds the
/// model firmly ([`LookPlan`]), and not after two thirds of the database
/// (the partial run would save little). With `restart_early_at_images`
/// raised above 16 a database of 48 images or more may take this rule too,
/// and past 30 images sphere solves come only every
/// `bundle.global_every_images`, so its window holds few of them. `None`
/// without the map's planes, with the look or the restart turned off, or
/// when the database is too small for the second sphere solve after the
/// release to come before two thirds of it.
///
/// Session 45, the nine 24-image scenes from 0.3 m / 3 deg off: see
/// `docs/results.md`. Until then the look was kept out of databases under
/// three times its image count, because (session 39, before the settled
/// check of session 41 and the turn rule of session 42) at 17 of 24 images
/// the corridor's initial image was still 0.2 m from where it ended.
pub(super) fn early_look_at(num_images: usize, options: &MapperOptions) -> Option<LookPlan> {
    let b = &options.bundle;
    if !b.restart_from_refined_pose
        || b.restart_early_at_images == 0
        || options.association.kind == AssociationKind::None
    {
        return None;
    }
    if num_images >= b.restart_early_at_images.saturating_mul(3) {
        return Some(LookPlan {
            from: b.restart_early_at_images,
            steady_until: None,
            slide: false,
        });
    }
    LookPlan::steady(num_images / 3, 2 * num_images / 3, b.fix_initial_for, false)
}

/// The look of the run from an early look that may have come mid-slide:
/// the look (`look`, at a sphere solve, not at the end of registration)
/// had moved the image more than [`super::mapper::EARLY_LOOK_STEADY`] since
/// the sphere solve before, or came while the map held the model loosely
/// (not [`firmly_held`]: similarity-constraint ratio below
/// [`super::mapper::EARLY_LOOK_FIRM`], or unknown).
/// Only the look of a large database may come then ([`early_look_at`]: the
/// small database's look waits for a steady, firmly held solve). That run
/// looks at the first sphere solve after the image's release
/// (`bundle.fix_initial_for`) that moved it at most `EARLY_LOOK_STEADY`
/// from where the one before left it while the map holds the model firmly,
/// as in a small database, up to twice `bundle.restart_early_at_images`
/// images and two thirds of the database, and stops when the image slid
/// farther than [`super::mapper::LOOK_RUN_SLIDE_M`] from the look's pose
/// ([`LookPlan::slide`]): the look came mid-slide, and the run is mapped
/// again from there, as it is when it moved the image that far by the end
/// of its registration ([`LOOK_RUN_END_LOOK`]), without the rest of its
/// registration.
///
/// A steady look is no proof along a corridor: the fresh seed-3 100-image
/// corridor from 0.3 m / 3 deg off (session 52) was looked at at 17 images
/// with the image 0.602 m from its given pose, steady (8 mm since the solve
/// before) but loosely held (ratio 4.4e-3); its run from there moved the
/// image 0.444-0.484 m back at every sphere solve from 10 images on and was
/// stopped only at the end of its registration (a 34.6 s run). At the slide
/// look, as at any early look, an image that turned more than
/// [`EARLY_LOOK_MIN_TURN_DEG`] stops the run too, and that counts as failed
/// (the first run goes to its end from the given pose). After a steady,
/// firmly held look, or one at the end of registration, `None`: while its
/// model is small a run's image strays along a corridor (0.207 m at 10
/// images on the seed-0 24-image corridor, from a look at the end of
/// registration that was right to 5 mm), and a run started from there is
/// no better.
fn look_run_plan(
    num_images: usize,
    look: &EarlyLookRecord,
    options: &MapperOptions,
) -> Option<LookPlan> {
    let moving = look.step.is_some_and(|s| beyond(&s, EARLY_LOOK_STEADY));
    if look.end_of_registration || (!moving && firmly_held(look.similarity_ratio)) {
        return None;
    }
    let b = &options.bundle;
    let until = (2 * b.restart_early_at_images).min(2 * num_images / 3);
    LookPlan::steady(b.fix_initial_for + 1, until, b.fix_initial_for, true)
}

/// A run whose initial image ended farther than this from its given pose
/// (metres, degrees) is mapped again from where it ended
/// (`bundle.restart_from_refined_pose`). Runs from exact poses moved it
/// 0.9-2.0 mm and 0.009-0.016 deg on the seed-0 scenes; from the search's
/// placements, 3.5-7.6 mm and 0.02-0.07 deg.
pub(super) const RESTART_MIN_CHANGE: (f64, f64) = (0.02, 0.2);

/// How far a finished run's initial image ended from its given pose, when
/// far enough to map again from there (see [`RESTART_MIN_CHANGE`]): not
/// without LiDAR constraints (the image stays where it was given), not
/// when the retry's held run is kept (held at the given pose), and not for
/// a run that was already mapped again from where an earlier one put the
/// image (`restart` set: [`kept_run_from_free_look`]). The run the
/// retry freed from the start is (the seed-0 corridor from 0.9 m / 8 deg
/// off: 3.4 mm, its initial image 0.90 m from the given pose); a run that
/// held the image for its first registrations only with
/// `bundle.restart_first_run`, or in a database of `num_images` at least
/// `bundle.restart_first_run_from_images`.
fn restart_reason(
    out: &MapperOutput,
    num_images: usize,
    options: &MapperOptions,
) -> Option<PoseChangeRecord> {
    let freed = out.report.retry.as_ref().is_some_and(|r| r.free_kept);
    if !options.bundle.restart_from_refined_pose
        || !(freed || options.bundle.restarts_first_run(num_images))
        || options.association.kind == AssociationKind::None
        || out.report.retry.as_ref().is_some_and(|r| r.held_kept)
        || out.report.restart.is_some()
    {
        return None;
    }
    let change = out.report.initial_pose_change?;
    beyond(&change, RESTART_MIN_CHANGE).then_some(change)
}

/// Runs the whole mapper from a given initial pose
/// ([`run_mapper_with_priors`]); when that fails as if the pose were off
/// ([`MapperError::may_be_a_pose_off`]), searches the map around it
/// ([`run_mapper_searching`] within `bundle.fallback_search_m` and `_deg`)
/// and maps from what it finds. The report's `init_search.after_failure`
/// says that the search followed a failure, and which.
pub fn run_mapper_from_pose(
    inputs: MapperInputs<'_>,
    init_image: ImageId,
    init_cam_from_world: &Rigid3,
    options: &MapperOptions,
    progress: Progress<'_>,
) -> Result<MapperOutput, MapperError> {
    let started = Instant::now();
    let first = run_mapper_with_priors(
        inputs,
        init_image,
        init_cam_from_world,
        options,
        &mut *progress,
    );
    let first_run_s = started.elapsed().as_secs_f64();
    let region = SearchRegion::around(
        options.bundle.fallback_search_m,
        options.bundle.fallback_search_deg,
    );
    let first_error = match first {
        Err(e)
            if e.may_be_a_pose_off()
                && region.radius_m > 0.0
                && options.association.kind != AssociationKind::None =>
        {
            e
        }
        other => return other,
    };
    log::warn!(
        "the run from the given initial pose failed: {first_error}\nsearching the map within {} m and {} deg of that pose (options bundle.fallback_search_m and _deg)",
        region.radius_m,
        region.yaw_deg
    );
    match run_mapper_searching(
        inputs,
        init_image,
        init_cam_from_world,
        &region,
        options,
        progress,
    ) {
        Ok(mut out) => {
            let record = out
                .report
                .init_search
                .as_mut()
                .expect("a searched run has its record");
            log::warn!(
                "the search found the initial image {:.2} m and {:.1} deg from the given pose, and the model mapped from there passed the checks",
                record.moved_m,
                record.turned_deg
            );
            record.after_failure = Some(first_error.to_string());
            record.first_run_s = Some(first_run_s);
            Ok(out)
        }
        Err(search) => Err(MapperError::FallbackSearchFailed {
            first: Box::new(first_error),
            region,
            search: Box::new(search),
        }),
    }
}

/// Two mapped models from the search's placements count as the same fit
/// within this share of their points (`fit_share`); as one place with
/// their initial cameras within [`super::localise::SAME_PLACE_M`].
const SEARCH_SAME_FIT: f64 = 0.02;

/// Runs the whole mapper from an initial pose known only to within `region`
/// ([`super::localise`]): the database mapped without the map's planes from
/// the rough pose (the initial pair from its essential matrix, the map's
/// depths there giving only its scale:
/// [`initialize_from_pair`](super::initialize::initialize_from_pair)), that
/// model placed on the map by [`search_placement`], and then
/// [`run_mapper_with_priors`] from the initial image's pose there. When
/// other placements come close, the database is mapped from each and the
/// finished model that fits the map best is kept; an error when two in
/// different places fit alike. The report's `init_search` says what the
/// search found.
pub fn run_mapper_searching(
    inputs: MapperInputs<'_>,
    init_image: ImageId,
    rough_cam_from_world: &Rigid3,
    region: &SearchRegion,
    options: &MapperOptions,
    progress: Progress<'_>,
) -> Result<MapperOutput, MapperError> {
    let started = Instant::now();
    log::info!(
        "searching within {} m (vertically {} m) and {} deg of the rough initial pose: mapping without the map's planes first",
        region.radius_m,
        region.vertical_m,
        region.yaw_deg
    );
    let plain = plain_run(
        inputs,
        init_image,
        rough_cam_from_world,
        None,
        options,
        &mut *progress,
    )?;
    let plain = PlainModel::new(
        &plain,
        init_image,
        rough_cam_from_world,
        &Sim3::identity(),
        started.elapsed().as_secs_f64(),
    );
    search_and_map(
        inputs,
        init_image,
        &plain,
        region,
        &SearchOptions::default(),
        options,
        None,
        progress,
    )
}

/// The database mapped without the map's planes and without the pose
/// priors (the search places the model by the map alone), the initial
/// image held at `rough_cam_from_world` and the pair's scale `pair_scale`
/// (else the map's depths seen from there).
pub(super) fn plain_run(
    inputs: MapperInputs<'_>,
    init_image: ImageId,
    rough_cam_from_world: &Rigid3,
    pair_scale: Option<f64>,
    options: &MapperOptions,
    progress: Progress<'_>,
) -> Result<MapperOutput, MapperError> {
    let mut plain_options = options.clone();
    plain_options.association.kind = AssociationKind::None;
    let start = Start::InitialPose {
        image: init_image,
        cam_from_world: *rough_cam_from_world,
        rough: true,
        pair_scale,
    };
    let no_priors = BTreeMap::new();
    let plain_inputs = MapperInputs {
        known_poses: &no_priors,
        ..inputs
    };
    map_once(plain_inputs, &start, &plain_options, progress)
        .map_err(|e| MapperError::PlainRun(Box::new(e)))
}

/// What the search needs of a model mapped without the map's planes, moved
/// into the map's frame by a similarity.
pub(super) struct PlainModel {
    /// Its 3D points.
    points: Vec<nalgebra::Vector3<f64>>,
    /// The initial image's pose in it.
    rough: Rigid3,
    /// The cameras' right-hand axes.
    right_axes: Vec<nalgebra::Vector3<f64>>,
    /// The run's initial pair: the second image, the pair's scale and
    /// its baseline in the model.
    second_image: u32,
    pair_scale: Option<f64>,
    pair_baseline: Option<f64>,
    /// Wall time of the run, seconds.
    run_s: f64,
}

impl PlainModel {
    /// The initial camera's centre in the map's frame, as moved.
    pub(super) fn rough_centre(&self) -> nalgebra::Vector3<f64> {
        self.rough.camera_center()
    }

    /// `plain` moved by `map_from_plain`; `rough` is the initial image's
    /// pose when the run did not register it.
    pub(super) fn new(
        plain: &MapperOutput,
        init_image: ImageId,
        rough: &Rigid3,
        map_from_plain: &Sim3,
        run_s: f64,
    ) -> Self {
        let rec = &plain.reconstruction;
        let centre = |id: u32| rec.pose(ImageId(id)).map(|p| p.camera_center());
        let init = plain.report.init.as_ref();
        Self {
            points: rec
                .points3d
                .values()
                .map(|p| map_from_plain.transform_point(&p.xyz))
                .collect(),
            // Without the map's planes the initial image stays at the rough pose.
            rough: rec
                .pose(init_image)
                .map_or(*rough, |p| map_from_plain.transform_pose(&p)),
            right_axes: rec
                .registered_images()
                .filter_map(|img| img.cam_from_world)
                .map(|pose| {
                    map_from_plain.rotation * (pose.rotation.inverse() * nalgebra::Vector3::x())
                })
                .collect(),
            second_image: init.map_or(0, |i| i.second_image),
            pair_scale: init.and_then(|i| i.pair_scale),
            pair_baseline: init.and_then(|i| {
                centre(i.initial_image)
                    .zip(centre(i.second_image))
                    .map(|(a, b)| map_from_plain.scale * (a - b).norm())
            }),
            run_s,
        }
    }
}

/// [`run_mapper_searching`] after its plain run: `plain` placed on the map
/// within `region` of its initial camera, and mapped from each close
/// placement.
#[allow(clippy::too_many_arguments)]
pub(super) fn search_and_map(
    inputs: MapperInputs<'_>,
    init_image: ImageId,
    plain: &PlainModel,
    region: &SearchRegion,
    search: &SearchOptions,
    options: &MapperOptions,
    confirms: Option<&dyn Fn(&MapperOutput) -> bool>,
    progress: Progress<'_>,
) -> Result<MapperOutput, MapperError> {
    let cloud = inputs.cloud;
    let searched = Instant::now();
    let index = MapIndex::build(cloud)?;
    // The planes as the mapper will see them: plane radii and windows
    // follow the map's spacing and noise.
    let adapted = options_for_map(options, cloud, &index);
    let nearest =
        NearestNeighbourAssociator::new(cloud, &index, adapted.options.association.clone());
    let rough = plain.rough;
    let search = &SearchOptions {
        min_radius_m: search
            .min_radius_m
            .max(SPARSE_MAP_RADIUS_PER_SPACING * adapted.spacing_m.unwrap_or(0.0)),
        ..search.clone()
    };
    let Search {
        contenders,
        mut record,
    } = search_placement(
        &plain.points,
        &plain.right_axes,
        &rough.camera_center(),
        &nearest,
        region,
        search,
    )?;
    record.plain_run_s = plain.run_s;
    record.plain_second_image = plain.second_image;
    record.plain_pair_scale = plain.pair_scale;
    record.plain_pair_baseline = plain.pair_baseline;
    record.search_s = searched.elapsed().as_secs_f64();
    log::info!(
        "the search placed the initial image {:.2} m and {:.1} deg from the rough pose (the plain model's scale {:.3}; {} of {} points on the map, the next placement {}; {} placements, {:.1} s + {:.1} s){}",
        record.moved_m,
        record.turned_deg,
        record.scale,
        record.on_map,
        record.num_checked,
        record
            .runner_up_on_map
            .map_or_else(|| "none".to_owned(), |n| n.to_string()),
        record.placements,
        record.plain_run_s,
        record.search_s,
        if contenders.len() > 1 {
            format!(
                "; {} placements come close, each is mapped",
                contenders.len()
            )
        } else {
            String::new()
        }
    );
    // Each close placement mapped; the map's fit of the finished models decides.
    let mut runs: Vec<(Rigid3, Result<MapperOutput, MapperError>)> = Vec::new();
    let mut finished: Vec<Option<(Option<f64>, nalgebra::Vector3<f64>)>> = Vec::new();
    // Of each run refused as loose with `confirms` given, whether the
    // positions placed it (kept) or not (no place at all).
    let mut by_positions: Vec<Option<bool>> = Vec::new();
    for (_, map_from_plain) in &contenders {
        let found = map_from_plain.transform_pose(&rough);
        let c = found.camera_center();
        log::info!(
            "mapping from the initial image at ({:.3}, {:.3}, {:.3})",
            c.x,
            c.y,
            c.z
        );
        let out = run_mapper_with_priors(inputs, init_image, &found, options, &mut *progress);
        // A finished model's fit and initial camera centre, kept even when
        // it is refused as loose: it still counts as a second place below.
        finished.push(out.as_ref().ok().map(|o| {
            let centre = o.reconstruction.pose(init_image).unwrap_or(found);
            let centre = centre.camera_center();
            (judged_fit(o, o.report.partial_map), centre)
        }));
        // A model the map holds loosely is still kept when `confirms`
        // (the photos' GPS positions) places it independently.
        let mut placed = None;
        let out = out.and_then(|o| match loose_searched_model(&o, init_image) {
            Some(e) => {
                placed = confirms.map(|agrees| agrees(&o));
                if placed == Some(true) {
                    Ok(o)
                } else {
                    Err(e)
                }
            }
            None => Ok(o),
        });
        by_positions.push(placed);
        if let Err(e) = &out {
            log::info!(
                "the run from placement {} of {} failed: {e}",
                runs.len() + 1,
                contenders.len()
            );
        }
        runs.push((found, out));
    }
    record.contender_fits = finished.iter().map(|f| f.and_then(|f| f.0)).collect();
    let fits = record.contender_fits.clone();
    let Some(best) = (0..runs.len())
        .filter(|&i| runs[i].1.is_ok())
        .max_by(|&a, &b| {
            let f = |i: usize| fits[i].unwrap_or(0.0);
            f(a).total_cmp(&f(b)).then(b.cmp(&a))
        })
    else {
        // The loose model's error says the most: a model was mapped.
        let loose = runs
            .iter()
            .position(|(_, r)| matches!(r, Err(MapperError::LooseSearchedModel { .. })))
            .unwrap_or(0);
        return runs.swap_remove(loose).1;
    };
    let centre = |i: usize| finished[i].map_or(runs[i].0.camera_center(), |f| f.1);
    let best_fit = fits[best].unwrap_or(0.0);
    // Another finished model (refused as loose or not) in another place that
    // fits about as well: the map cannot tell them apart. One that the
    // positions refused to place is no place.
    if let Some(other) = (0..runs.len()).find(|&i| {
        i != best
            && finished[i].is_some()
            && by_positions[i] != Some(false)
            && fits[i].unwrap_or(0.0) >= best_fit - SEARCH_SAME_FIT
            && (centre(i) - centre(best)).norm() > SAME_PLACE_M
    }) {
        let (a, b) = (centre(best), centre(other));
        return Err(MapperError::Search(SearchError::Ambiguous {
            best_fit,
            other_fit: fits[other].unwrap_or(0.0),
            best_centre: [a.x, a.y, a.z],
            other_centre: [b.x, b.y, b.z],
        }));
    }
    // Models that fit alike are in one place (else the error above): the
    // same model, mapped from placements the run corrected. Keep the one
    // from the search's best placement among them (its fit within
    // [`SEARCH_SAME_FIT`] of the best): on the CI yard a contender 1 m off,
    // which the run moved back (and mapped again from there,
    // `bundle.restart_from_refined_pose`), fitted 0.95748 against the best
    // placement's 0.95733.
    let best = (0..runs.len())
        .find(|&i| runs[i].1.is_ok() && fits[i].unwrap_or(0.0) >= best_fit - SEARCH_SAME_FIT)
        .unwrap_or(best);
    let best_fit = fits[best].unwrap_or(0.0);
    if best != 0 {
        log::warn!(
            "kept the model mapped from the search's placement {} of {} (fit {:.1} % against {})",
            best + 1,
            runs.len(),
            best_fit * 100.0,
            fits.iter()
                .map(|f| f.map_or_else(|| "failed".to_owned(), |f| format!("{:.1} %", f * 100.0)))
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    record.kept_by_positions = by_positions[best] == Some(true);
    let (found, out) = runs.swap_remove(best);
    let mut out = out?;
    let c = found.camera_center();
    record.found_centre = [c.x, c.y, c.z];
    record.moved_m = (c - rough.camera_center()).norm();
    record.turned_deg = (found.rotation * rough.rotation.inverse())
        .angle()
        .to_degrees();
    record.scale = contenders[best].1.scale;
    record.on_map = contenders[best].0;
    // The kept placement first.
    record.contenders_on_map.swap(0, best);
    record.contender_fits.swap(0, best);
    out.report.init_search = Some(record);
    Ok(out)
}

/// The error for a model mapped from a placement of `--init-search` that
/// fits the map below [`GOOD_FIT_SHARE`] while the map holds it only
/// weakly in one direction (similarity-constraint ratio below
/// [`SEARCH_MIN_CONSTRAINT`]): the search may have put it off along that
/// direction, and the run from there cannot tell (it starts where the
/// search put it, so [`check_initial_pose`](super::mapper::check_initial_pose)
/// sees no move). [`search_and_map`] keeps such a model when the photos'
/// GPS positions agree with it.
pub(super) fn loose_searched_model(out: &MapperOutput, init_image: ImageId) -> Option<MapperError> {
    let share = judged_fit(out, out.report.partial_map)?;
    // No ratio: no map terms (`--no-lidar-constraints`), or too few points
    // on planes for one.
    let c = out.report.similarity_constraint.as_ref()?;
    if share >= GOOD_FIT_SHARE || c.ratio >= SEARCH_MIN_CONSTRAINT {
        return None;
    }
    let centre = out.reconstruction.pose(init_image)?.camera_center();
    Some(MapperError::LooseSearchedModel {
        // (+ 0.0: no "-0.00" in the message.)
        centre: [centre.x + 0.0, centre.y + 0.0, centre.z + 0.0],
        share,
        ratio: c.ratio,
        weakest: rounded_weakest(c),
    })
}

/// The least fixed direction for a message, to two decimals (+ 0.0: no
/// "-0.0").
fn rounded_weakest(c: &SimilarityConstraint) -> Vec<f64> {
    c.weakest
        .iter()
        .map(|w| (w * 100.0).round() / 100.0 + 0.0)
        .collect()
}

/// Which run of the retry schedule ([`run_with_retries`]) is asked for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum RetryRun {
    /// The initial image free from the start (`fix_initial_for` 0); it may
    /// stop at its look ([`free_run_look`]) and be mapped again from there.
    Free,
    /// The initial image held at its given pose throughout.
    Held,
}

/// The look of the retry's run free from the start: as a small database's
/// early look ([`early_look_at`]), at the first sphere solve from
/// `restart_early_at_images` images (16; a third of a smaller database) on
/// that moved the initial image at most
/// [`super::mapper::EARLY_LOOK_STEADY`] while the map holds the model
/// firmly, up to two thirds of the database; `None` where the first run
/// has no early look. That run follows a first run that slid or did not
/// fit; to its end, and mapped again from where it ended, it cost two full
/// runs: on the fresh seed-2 100-image corridor from 0.3 m / 3 deg off
/// (session 53) its image was 0.295-0.300 m and 2.99 deg from the given
/// pose at every sphere solve from 15 images on (the truth: 0.30 m, 3.0
/// deg), steady and held at ratios 1.4e-2 to 1.8e-2.
fn free_run_look(num_images: usize, options: &MapperOptions) -> Option<LookPlan> {
    let b = &options.bundle;
    early_look_at(num_images, options)?;
    LookPlan::steady(
        b.restart_early_at_images.min(num_images / 3),
        2 * num_images / 3,
        b.fix_initial_for,
        false,
    )
}

/// The run from the look of the retry's run free from the start
/// ([`free_run_look`]; `look_pose` the initial image's pose there, `look_s`
/// the run to it, `run_s` the run from it), as that run's outcome. A run
/// that moved the initial image again beyond [`EARLY_LOOK_MIN_CHANGE`] from
/// where the look put it had started from a model that had not settled: it
/// is mapped again from where it ended (`restart`), as the free run to its
/// end would have been. Else it is kept, the look and the two runs in its
/// `early_look` and `restart` (so [`restart_reason`] maps it no more).
fn kept_run_from_free_look(
    mut out: MapperOutput,
    init_image: ImageId,
    look_pose: &Rigid3,
    (look, look_s, run_s): (EarlyLookRecord, f64, f64),
    restart: impl FnOnce(MapperOutput, PoseChangeRecord, f64) -> MapperOutput,
) -> MapperOutput {
    out.report.early_look = Some(look);
    let again = out
        .reconstruction
        .pose(init_image)
        .map(|pose| pose_change(&pose, look_pose));
    if let Some(change) = again.filter(|c| beyond(c, EARLY_LOOK_MIN_CHANGE)) {
        return restart(out, change, run_s);
    }
    out.report.restart = Some(RestartRecord {
        first_change: look.change,
        first_stopped_at_images: Some(look.registered),
        first_run_s: look_s,
        second_run_s: run_s,
        second_fit_share: out.report.fit_share,
        second_kept: true,
        ..Default::default()
    });
    out
}

/// The retry schedule of [`run_mapper_with_priors`] after `first` (the run
/// as configured and its wall time, seconds), with `run` (one mapper run with
/// the given options and its wall time) for a database of `num_images`
/// images: `first`; when [`retry_reason`] calls
/// for it and the initial image was held only early, the run free from the
/// start; when that fails too, or when there was no early hold, the run with
/// the initial image held throughout, and [`pick_run`] between the two.
fn run_with_retries(
    options: &MapperOptions,
    num_images: usize,
    (first, first_run_s): (Result<MapperOutput, MapperError>, f64),
    mut run: impl FnMut(RetryRun, &MapperOptions) -> (Result<MapperOutput, MapperError>, f64),
) -> Result<MapperOutput, MapperError> {
    let holds_already =
        options.bundle.fix_initial_for >= num_images && options.bundle.hold_initial_in_final_rounds;
    let Some(reason) = retry_reason(&first, options).filter(|_| !holds_already) else {
        return first;
    };
    // Held early (`fix_initial_for`) at a pose that is off, the model can be
    // built around it and stay there: the seed-7 yard from 0.6 m / 4 deg off
    // ended 0.27 m off (the slid-along-a-weak-direction error), free from the
    // start 2.4 mm. So a failed early-held run is first mapped again free,
    // as before session 28; only if that fails too, held throughout.
    let early_hold =
        options.bundle.fix_initial_for > 0 && options.bundle.fix_initial_for < num_images;
    let (first, free_run_s, held_reason) = if early_hold {
        log::warn!("{reason}: mapping again with the initial image free from the start");
        let mut free = options.clone();
        free.bundle.fix_initial_for = 0;
        let (mut free_run, free_run_s) = run(RetryRun::Free, &free);
        // An error that holding cannot mend goes on to the held run too.
        let why = retry_reason(&free_run, &free)
            .or_else(|| free_run.as_ref().err().map(|e| e.to_string()));
        match why {
            None => {
                let note = "kept the run with the initial image free from the start".to_owned();
                log::warn!("{note}");
                if let Ok(out) = &mut free_run {
                    out.report.retry = Some(RetryRecord {
                        reason,
                        held_kept: false,
                        free_kept: true,
                        outcome: note,
                        first_run_s,
                        free_run_s: Some(free_run_s),
                        held_run_s: None,
                    });
                }
                return free_run;
            }
            Some(why) => (free_run, Some(free_run_s), why),
        }
    } else {
        (first, None, reason.clone())
    };
    log::warn!("{held_reason}: mapping again with the initial image held at its given pose");
    let mut held = options.clone();
    held.bundle.fix_initial_for = num_images;
    held.bundle.hold_initial_in_final_rounds = true;
    let (held_run, held_run_s) = run(RetryRun::Held, &held);
    let (mut outcome, held_kept, note) =
        pick_run(first, held_run, options.bundle.initial_prior_position_m);
    log::warn!("{note}");
    if let Ok(out) = &mut outcome {
        let note = match free_run_s {
            Some(_) => format!("the run free from the start: {held_reason}; {note}"),
            None => note,
        };
        out.report.retry = Some(RetryRecord {
            reason,
            held_kept,
            free_kept: free_run_s.is_some() && !held_kept,
            outcome: note,
            first_run_s,
            free_run_s,
            held_run_s: Some(held_run_s),
        });
    }
    outcome
}

/// The most a held run's whole-model alignment trial may move it for the
/// map to count as agreeing with the given pose (see [`pick_run`]): centroid
/// shift, metres; rotation, degrees; scale's departure from 1. The held
/// 400-image corridor measured 0.8 mm, 0.0008 deg and 7e-5.
const HELD_SETTLED: (f64, f64, f64) = (0.02, 0.1, 2e-3);

/// Whether a held run's whole-model alignment found nothing to move and at
/// least `GOOD_FIT_SHARE` of its points fit the map: the model built around
/// the given pose sits where the map holds it. The trial alone does not
/// tell: held throughout at poses 0.3 m and 3 deg off, the room 0 and yard 0
/// table runs ended 0.28 and 0.22 m off with trials that moved 1 mm and
/// under 0.1 deg, but fitted 65 % and 60 % (right held runs 86-96 %, the
/// 400-image corridor 93.7 %).
fn held_run_settled(out: &MapperOutput) -> bool {
    let (max_m, max_deg, max_scale) = HELD_SETTLED;
    let fits = judged_fit(out, out.report.partial_map).is_some_and(|f| f >= GOOD_FIT_SHARE);
    fits && out.report.alignment.as_ref().is_some_and(|a| {
        a.translation_m <= max_m && a.rotation_deg <= max_deg && (a.scale - 1.0).abs() <= max_scale
    })
}

/// How well a run fits the map for choosing between runs: `fit_share`, or
/// over the points the map covers (`covered_fit_share`) when `by_covered`
/// (a partly mapped run: its `fit_share` is low by what the map lacks).
fn judged_fit(out: &MapperOutput, by_covered: bool) -> Option<f64> {
    if by_covered {
        out.report.covered_fit_share
    } else {
        out.report.fit_share
    }
}

/// Of a first run and the run with the initial image held, the one to keep,
/// whether it is the held one, and what was decided (for the log and the
/// report): the held run when it passed its checks, its planes leave a
/// direction nearly free or, where the map fixes the whole model, it is
/// settled ([`held_run_settled`]: its alignment trial found nothing to move
/// and it fits the map well; else the map disagrees with
/// the given pose: the seed-7 yard from a pose 1.1 m and 8 deg off must
/// fail; the 400-image corridor, which slid 1.18 m in its first run, is
/// right held: 1.1 mm), and the first failed or fits the map less (a
/// smaller `fit_share`, or `covered_fit_share` when either is partly mapped);
/// the first otherwise, except that a first the map leaves nearly free
/// ([`free_along_weak_direction`]) is an error when the held run failed
/// (both errors when both failed).
fn pick_run(
    first: Result<MapperOutput, MapperError>,
    held: Result<MapperOutput, MapperError>,
    prior_m: f64,
) -> (Result<MapperOutput, MapperError>, bool, String) {
    let by_covered = [&first, &held]
        .iter()
        .any(|run| run.as_ref().is_ok_and(|out| out.report.partial_map));
    let fit = |out: &MapperOutput| 100.0 * judged_fit(out, by_covered).unwrap_or(0.0);
    let points = if by_covered {
        "of the points the map covers"
    } else {
        "of its points"
    };
    let ratio = |out: &MapperOutput| {
        out.report
            .similarity_constraint
            .as_ref()
            .map_or(0.0, |c| c.ratio)
    };
    match (first, held) {
        (first, Ok(held))
            if ratio(&held) >= MIN_SIMILARITY_CONSTRAINT && !held_run_settled(&held) =>
        {
            let trial = held.report.alignment.as_ref().map_or_else(
                || "no alignment trial (bundle.align_to_map off)".to_owned(),
                |a| {
                    format!(
                        "its alignment trial moved it {:.3} m, {:.2} deg, scale {:.4}",
                        a.translation_m, a.rotation_deg, a.scale
                    )
                },
            );
            let note = format!(
                "with the initial image held at its given pose the map fixes the whole model (constraint ratio {:.1e}), {trial} and {:.1} % {points} fit the map (at most {:.3} m, {:.2} deg, {:.1} % in scale and at least {:.0} % fitting show that the map and that pose agree): kept the first run's outcome",
                ratio(&held),
                fit(&held),
                HELD_SETTLED.0,
                HELD_SETTLED.1,
                HELD_SETTLED.2 * 100.0,
                GOOD_FIT_SHARE * 100.0
            );
            (first, false, note)
        }
        (Ok(first), Ok(held)) if fit(&held) < fit(&first) => {
            let note = format!(
                "the run with the initial image held fits the map less ({:.1} % against {:.1} % {points}): kept the first",
                fit(&held),
                fit(&first)
            );
            (Ok(first), false, note)
        }
        (_, Ok(held)) => {
            let why = if ratio(&held) >= MIN_SIMILARITY_CONSTRAINT {
                let weak = if ratio(&held) < WEAK_SIMILARITY_CONSTRAINT {
                    "; the map holds one direction only weakly, along which the model is only as right as the given pose"
                } else {
                    ""
                };
                format!(
                    "the map fixes the whole model (constraint ratio {:.1e}), its alignment to the map found nothing to move and the model fits it well: the map and the given pose agree{weak}",
                    ratio(&held)
                )
            } else {
                "along the directions the map leaves free the model is only as right as the given pose".to_owned()
            };
            let note = format!(
                "kept the run with the initial image held at its given pose ({:.1} % {points} on the map): {why}",
                fit(&held)
            );
            (Ok(held), true, note)
        }
        // The first was retried for a nearly free direction (see
        // `retry_reason`): with the given pose failing too, nothing places it.
        (Ok(first), Err(e)) => match free_along_weak_direction(&first, prior_m) {
            Some(loose) => {
                let note = format!(
                    "holding the initial image at its given pose did not help, and the first run is not held by the map: {e}"
                );
                let error = MapperError::RetryFailed {
                    first: Box::new(loose),
                    held: Box::new(e),
                };
                (Err(error), false, note)
            }
            None => {
                let note = format!("holding the initial image at its given pose did not help: {e}");
                (Ok(first), false, note)
            }
        },
        (Err(first), Err(held)) => {
            let note = "holding the initial image at its given pose did not help".to_owned();
            let error = MapperError::RetryFailed {
                first: Box::new(first),
                held: Box::new(held),
            };
            (Err(error), false, note)
        }
    }
}

/// The error for a finished run whose planes leave a direction nearly free
/// (similarity-constraint ratio below [`MIN_SIMILARITY_CONSTRAINT`]) and
/// whose initial image moved farther than `prior_m` (the prior's position
/// sigma; 0, no position prior: never) from its given pose, the retry's reason
/// (see [`retry_reason`]); `None` when the map holds it or the image only
/// turned (the planes' normals fix a rotation even where they leave a slide
/// free, so a turn back from a pose that was off is not along the free
/// direction).
fn free_along_weak_direction(out: &MapperOutput, prior_m: f64) -> Option<MapperError> {
    let c = out.report.similarity_constraint.as_ref()?;
    let change = out.report.initial_pose_change.as_ref()?;
    let loose = c.ratio < MIN_SIMILARITY_CONSTRAINT && prior_m > 0.0 && change.moved_m > prior_m;
    loose.then(|| MapperError::FreeAlongWeakDirection {
        moved_m: change.moved_m,
        turned_deg: change.turned_deg,
        share: out.report.fit_share.unwrap_or(0.0),
        ratio: c.ratio,
        weakest: rounded_weakest(c),
    })
}

/// Why a run's outcome calls for mapping again with the initial image held
/// at its given pose: the model did not fit the map, or the initial image
/// ended beyond the accepted change, or the final planes leave a similarity
/// of the model nearly free while the initial image moved farther than its
/// prior's standard deviation (a right model moves it back by the given
/// pose's error; along a free direction nothing but that pose places the
/// model). `None` without LiDAR constraints, with the retry off, or for any
/// other error.
fn retry_reason(
    outcome: &Result<MapperOutput, MapperError>,
    options: &MapperOptions,
) -> Option<String> {
    if !options.bundle.retry_holding_initial || options.association.kind == AssociationKind::None {
        return None;
    }
    match outcome {
        Err(
            e @ (MapperError::OffMap { .. }
            | MapperError::InitialPoseFarOff { .. }
            | MapperError::SlidAlongWeakDirection { .. }
            | MapperError::SlidMidRun { .. }),
        ) => Some(e.to_string()),
        Err(_) => None,
        Ok(out) => {
            let change = out.report.initial_pose_change.as_ref()?;
            let ratio = out.report.similarity_constraint.as_ref()?.ratio;
            let b = &options.bundle;
            let moved = (b.initial_prior_position_m > 0.0
                && change.moved_m > b.initial_prior_position_m)
                || (b.initial_prior_rotation_deg > 0.0
                    && change.turned_deg > b.initial_prior_rotation_deg);
            (ratio < MIN_SIMILARITY_CONSTRAINT && moved).then(|| {
                format!(
                    "the map's planes leave the model nearly free in one direction (constraint ratio {ratio:.1e}) and the initial image ended {:.2} m and {:.1} deg from its given pose",
                    change.moved_m, change.turned_deg
                )
            })
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::Reconstruction;
    use crate::sfm::mapper::tests::line_of_images;
    use crate::sfm::mapper::LookNow;
    use crate::sfm::report::{AlignmentRecord, MapReport};

    /// The early look: from `restart_early_at_images` (16) on in a database
    /// of 48 images or more; in a smaller one from a third of it on, once
    /// the image is steady, until two thirds; not without the restart, the
    /// look or the map's planes.
    #[test]
    fn the_early_look_in_a_small_database_waits_for_a_steady_image() {
        let options = MapperOptions::default();
        assert_eq!(options.bundle.restart_early_at_images, 16);
        assert_eq!(options.bundle.fix_initial_for, 8);
        let plan = |from, steady_until| {
            Some(LookPlan {
                from,
                steady_until,
                slide: false,
            })
        };
        let at = |n: usize| early_look_at(n, &options);
        assert_eq!(at(100), plan(16, None));
        assert_eq!(at(48), plan(16, None));
        assert_eq!(at(47), plan(15, Some(31)));
        assert_eq!(at(24), plan(8, Some(16)));
        // Released after 8: the second sphere solve after it comes at 10 or
        // later, two thirds of 15.
        assert_eq!(at(15), plan(5, Some(10)));
        assert_eq!(at(14), None);
        assert_eq!(at(2), None);
        let with = |change: fn(&mut MapperOptions)| {
            let mut o = options.clone();
            change(&mut o);
            early_look_at(100, &o)
        };
        assert_eq!(
            with(|o| o.bundle.restart_early_at_images = 20),
            plan(20, None)
        );
        assert_eq!(with(|o| o.bundle.restart_early_at_images = 0), None);
        assert_eq!(with(|o| o.bundle.restart_from_refined_pose = false), None);
        assert_eq!(with(|o| o.association.kind = AssociationKind::None), None);
        // Held longer, a small database has no room for the look.
        let mut held = options.clone();
        held.bundle.fix_initial_for = 12;
        assert_eq!(early_look_at(21, &held), plan(7, Some(14)));
        assert_eq!(early_look_at(20, &held), None);
    }

    /// A searched model is refused when it fits below 90 % and the map holds
    /// it with a ratio below 7e-3, and kept when either is better.
    #[test]
    fn a_loose_searched_model_is_refused() {
        use crate::sfm::align::SimilarityConstraint;
        let output = |fit: f64, ratio: f64| {
            let state = line_of_images();
            let mut out = MapperOutput {
                reconstruction: state.to_reconstruction(),
                report: MapReport::default(),
            };
            out.report.fit_share = Some(fit);
            out.report.similarity_constraint = Some(SimilarityConstraint {
                num_points: 1000,
                ratio,
                weakest: [0.0, 0.0, 0.0, 0.784, 0.0, 0.239, 0.572],
            });
            out
        };
        let err = loose_searched_model(&output(0.82, 4.96e-3), ImageId(2)).expect("refused");
        let MapperError::LooseSearchedModel { centre, share, .. } = &err else {
            panic!("{err}");
        };
        assert_eq!(*centre, [1.0, 0.0, 0.0]);
        assert_eq!(*share, 0.82);
        let message = err.to_string();
        for part in [
            "(1.00, 0.00, 0.00)",
            "82 %",
            "ratio 4.96e-3",
            "below the 7e-3",
            "[0.0, 0.0, 0.0, 0.78, 0.0, 0.24, 0.57]",
        ] {
            assert!(message.contains(part), "{part}: {message}");
        }
        assert!(loose_searched_model(&output(0.86, 0.032), ImageId(2)).is_none());
        assert!(loose_searched_model(&output(0.82, 0.0103), ImageId(2)).is_none());
        assert!(loose_searched_model(&output(0.82, 0.0071), ImageId(2)).is_none());
        assert!(loose_searched_model(&output(0.94, 3.4e-3), ImageId(2)).is_none());
        assert!(loose_searched_model(&output(0.82, 0.0069), ImageId(2)).is_some());
        // No fit measured: nothing to judge.
        let mut unmeasured = output(0.5, 1e-4);
        unmeasured.report.fit_share = None;
        assert!(loose_searched_model(&unmeasured, ImageId(2)).is_none());
    }
    /// The off-map error of the yard that slid (45 % of its points on the map).
    fn off_map() -> Result<MapperOutput, MapperError> {
        Err(MapperError::OffMap {
            share: 0.45,
            points: 10494,
            removed: 4791,
            min_share: 0.6,
            coverage: 0.98,
            covered_fit: 0.46,
            ratio: Some(0.02),
            before_final: false,
        })
    }

    /// A finished run with these checks' results.
    fn finished_run(ratio: f64, moved_m: f64, turned_deg: f64, fit: f64) -> MapperOutput {
        MapperOutput {
            reconstruction: Reconstruction::default(),
            report: MapReport {
                initial_pose_change: Some(PoseChangeRecord {
                    moved_m,
                    turned_deg,
                }),
                similarity_constraint: Some(crate::sfm::align::SimilarityConstraint {
                    num_points: 1000,
                    ratio,
                    weakest: [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
                }),
                fit_share: Some(fit),
                ..Default::default()
            },
        }
    }

    /// The seed-0 100-image corridor's run from its look (0.294 m and 0.03
    /// deg again, fit 0.929) undid a slide; one that turned again, or the
    /// seed-2 60-image corridor's (fit 0.85), did not.
    #[test]
    fn a_run_from_the_look_that_kept_its_rotation_and_fits_undid_a_slide() {
        let change = |moved_m, turned_deg| PoseChangeRecord {
            moved_m,
            turned_deg,
        };
        let run = |fit| finished_run(0.01, 0.3, 3.0, fit);
        assert!(slid_back(&change(0.294, 0.03), &run(0.929)));
        assert!(!slid_back(&change(0.294, 0.03), &run(0.85)));
        assert!(!slid_back(&change(0.05, 1.5), &run(0.95)));
        let mut unfitted = run(0.95);
        unfitted.report.fit_share = None;
        assert!(!slid_back(&change(0.294, 0.03), &unfitted));
    }

    /// The first run looks at the end of its registration with the early
    /// look and the restart on and the map's planes used, for a turn of
    /// more than 1 deg (exact poses turned the seed-0 yard's image 0.24 deg
    /// there); the run from the early look for a move as far as the look's
    /// own bar.
    #[test]
    fn the_first_run_looks_at_the_end_of_registration_for_a_turn() {
        let options = MapperOptions::default();
        let end = first_run_end_look(&options).expect("on by default");
        assert_eq!(end.beyond, RESTART_MIN_CHANGE);
        assert_eq!(end.min_turn_deg, 1.0);
        assert_eq!(
            LOOK_RUN_END_LOOK.map(|e| (e.beyond, e.min_turn_deg)),
            Some(((0.1, 1.0), 0.0))
        );
        let off = |f: fn(&mut MapperOptions)| {
            let mut o = MapperOptions::default();
            f(&mut o);
            first_run_end_look(&o)
        };
        assert_eq!(off(|o| o.bundle.restart_from_refined_pose = false), None);
        assert_eq!(off(|o| o.bundle.restart_early_at_images = 0), None);
        assert_eq!(off(|o| o.bundle.hold_initial_in_final_rounds = true), None);
        assert_eq!(off(|o| o.association.kind = AssociationKind::None), None);
        assert!(off(|o| o.association.kind = AssociationKind::Projection).is_some());
    }

    /// The retry's run free from the start looks at its steady, firmly held
    /// initial image from 16 images on (a third of a smaller database) up to
    /// two thirds of the database, released from the start; not where the
    /// first run has no look.
    #[test]
    fn the_retrys_free_run_looks_once_the_image_is_steady() {
        let mut free = MapperOptions::default();
        free.bundle.fix_initial_for = 0;
        let plan = |n, o: &MapperOptions| free_run_look(n, o);
        assert_eq!(
            plan(100, &free),
            Some(LookPlan {
                from: 16,
                steady_until: Some(66),
                slide: false,
            })
        );
        assert_eq!(
            plan(24, &free).map(|p| (p.from, p.steady_until)),
            Some((8, Some(16)))
        );
        let steady = |moved_m| {
            Some(PoseChangeRecord {
                moved_m,
                turned_deg: 0.0,
            })
        };
        let p = plan(100, &free).unwrap();
        // Released from the start: at 17 images steady and firm, it looks;
        // moving, loosely held or too early, it waits; past 66, never.
        for (registered, step_m, ratio, now) in [
            (17, 0.005, 1.8e-2, LookNow::Look),
            (17, 0.05, 1.8e-2, LookNow::Wait),
            (17, 0.005, 8e-3, LookNow::Wait),
            (15, 0.005, 1.8e-2, LookNow::Wait),
            (67, 0.005, 1.8e-2, LookNow::Never),
        ] {
            assert_eq!(
                p.decide(registered, true, steady(step_m), || Some(ratio)),
                now,
                "{registered} images, step {step_m} m, ratio {ratio}"
            );
        }
        let off = |f: fn(&mut MapperOptions)| {
            let mut o = free.clone();
            f(&mut o);
            plan(100, &o)
        };
        assert_eq!(off(|o| o.bundle.restart_early_at_images = 0), None);
        assert_eq!(off(|o| o.bundle.restart_from_refined_pose = false), None);
        assert_eq!(off(|o| o.association.kind = AssociationKind::None), None);
    }

    /// The run from the free run's look is kept as it is when it left the
    /// initial image within the look's bar of where the look put it, and is
    /// then not mapped again; one that moved it farther goes to `restart`.
    #[test]
    fn the_run_from_the_free_runs_look_is_kept_or_mapped_again() {
        use nalgebra::{UnitQuaternion, Vector3};
        let init = ImageId(1);
        let at = |x: f64| {
            Rigid3::from_rotation_and_center(UnitQuaternion::identity(), &Vector3::new(x, 0.0, 0.0))
        };
        let look_pose = at(0.0);
        let run_ending_at = |x: f64| {
            let mut out = finished_run(1.8e-2, 0.3, 3.0, 0.94);
            out.reconstruction.images.insert(
                init,
                crate::scene::Image {
                    id: init,
                    name: "frame_0000.jpg".into(),
                    camera_id: crate::scene::CameraId(1),
                    cam_from_world: Some(at(x)),
                    points2d: Vec::new(),
                },
            );
            out
        };
        let look = EarlyLookRecord {
            registered: 19,
            change: PoseChangeRecord {
                moved_m: 0.298,
                turned_deg: 2.99,
            },
            step: None,
            similarity_ratio: Some(1.8e-2),
            alignment_would_move: None,
            settled: true,
            end_of_registration: false,
            seen_share: None,
        };
        let options = MapperOptions::default();
        // The kept run, and what was mapped again from where (the change
        // from the look, the run's time), for a run ending `x` from the look.
        let judged = |x: f64| {
            let mut restarted = None;
            let out = kept_run_from_free_look(
                run_ending_at(x),
                init,
                &look_pose,
                (look, 16.5, 60.0),
                |out, c, s| {
                    restarted = Some((c, s));
                    out
                },
            );
            (out, restarted)
        };
        // 5 cm from the look: kept, with the look and both runs recorded.
        let (out, restarted) = judged(0.05);
        assert!(restarted.is_none());
        assert_eq!(out.report.early_look, Some(look));
        let record = out.report.restart.as_ref().expect("recorded");
        assert_eq!(record.first_stopped_at_images, Some(19));
        assert_eq!((record.first_run_s, record.second_run_s), (16.5, 60.0));
        assert!(record.second_kept);
        assert_eq!(record.second_fit_share, Some(0.94));
        // A run from an earlier run's end is not mapped once more.
        assert!(restart_reason(&out, 24, &options).is_none());
        let mut first_too = options.clone();
        first_too.bundle.restart_first_run = true;
        assert!(restart_reason(&finished_run(1.8e-2, 0.3, 3.0, 0.94), 24, &first_too).is_some());
        // 0.2 m from the look: mapped again from where it ended.
        let (out, restarted) = judged(0.2);
        let (c, s) = restarted.expect("mapped again");
        assert!(
            (c.moved_m - 0.2).abs() < 1e-9 && c.turned_deg < 1e-9,
            "{c:?}"
        );
        assert_eq!(s, 60.0);
        assert!(out.report.restart.is_none());
    }

    /// The seed-3 100-image corridor from 0.3 m / 3 deg off: its look at 17
    /// images came with the image still moving 7.4 cm a sphere solve
    /// (session 50), or steady but loosely held (ratio 4.4e-3, session 52),
    /// so the run from there looks again once the image is steady after its
    /// release; looks that were steady and firmly held, or at the end of
    /// registration, do not.
    #[test]
    fn the_run_from_a_look_taken_mid_slide_looks_again() {
        let options = MapperOptions::default();
        let firm = |mut look: EarlyLookRecord| {
            look.similarity_ratio = Some(1.2e-2);
            look
        };
        let look = |step: Option<(f64, f64)>, end_of_registration| EarlyLookRecord {
            registered: 17,
            change: PoseChangeRecord {
                moved_m: 0.543,
                turned_deg: 3.01,
            },
            step: step.map(|(moved_m, turned_deg)| PoseChangeRecord {
                moved_m,
                turned_deg,
            }),
            similarity_ratio: Some(4.1e-3),
            alignment_would_move: None,
            settled: true,
            end_of_registration,
            seen_share: None,
        };
        let moving = look(Some((0.074, 0.007)), false);
        assert_eq!(
            look_run_plan(100, &moving, &options),
            Some(LookPlan {
                from: 9,
                steady_until: Some(32),
                slide: true,
            })
        );
        // Turning counts as moving too (firmly held); a small database stops
        // earlier.
        let turning = firm(look(Some((0.005, 0.3)), false));
        assert_eq!(
            look_run_plan(36, &turning, &options).and_then(|p| p.steady_until),
            Some(24)
        );
        // Steady, but the map held the model loosely (or no ratio): looks again.
        let steady = look(Some((0.008, 0.004)), false);
        assert_eq!(
            look_run_plan(100, &steady, &options),
            look_run_plan(100, &moving, &options)
        );
        let mut unknown = steady;
        unknown.similarity_ratio = None;
        assert!(look_run_plan(100, &unknown, &options).is_some());
        // Steady and firmly held (at the bar itself too), or at the end of
        // registration: no.
        assert_eq!(look_run_plan(100, &firm(steady), &options), None);
        let mut at_bar = steady;
        at_bar.similarity_ratio = Some(super::super::mapper::EARLY_LOOK_FIRM);
        assert_eq!(look_run_plan(100, &at_bar, &options), None);
        assert_eq!(look_run_plan(100, &firm(look(None, false)), &options), None);
        assert!(look_run_plan(100, &firm(moving), &options).is_some());
        assert_eq!(look_run_plan(100, &look(None, true), &options), None);
        assert_eq!(
            look_run_plan(100, &look(Some((0.074, 0.007)), true), &options),
            None
        );
        // No room for a steady solve after the release.
        assert_eq!(look_run_plan(14, &moving, &options), None);
    }

    #[test]
    fn a_run_whose_initial_image_moved_is_mapped_again_from_where_it_ended() {
        // By default the first run (its image held at first) is kept as it
        // ended; the run the retry freed from the start is mapped again.
        let defaults = MapperOptions::default();
        assert!(restart_reason(&finished_run(0.03, 0.3, 3.0, 0.9), 24, &defaults).is_none());
        // ... in a database of fewer than 48 images; from 48 on it is
        // mapped again too.
        assert!(restart_reason(&finished_run(0.03, 0.3, 3.0, 0.9), 47, &defaults).is_none());
        assert!(restart_reason(&finished_run(0.03, 0.3, 3.0, 0.9), 48, &defaults).is_some());
        let mut never = defaults.clone();
        never.bundle.restart_first_run_from_images = 0;
        assert!(restart_reason(&finished_run(0.03, 0.3, 3.0, 0.9), 500, &never).is_none());
        let mut options = defaults.clone();
        options.bundle.restart_first_run = true;
        let moved = |m, deg| restart_reason(&finished_run(0.03, m, deg, 0.9), 24, &options);
        // From the exact pose (the seed-0 scenes: 0.9-2.0 mm, 0.009-0.016
        // deg) or a search's placement (3.5-7.6 mm, 0.02-0.07 deg): no.
        assert!(moved(0.002, 0.016).is_none());
        assert!(moved(0.0076, 0.074).is_none());
        assert!(moved(0.02, 0.2).is_none());
        // From a pose 0.3 m / 3 deg off, or off in either alone: yes.
        let change = moved(0.2997, 3.01).unwrap();
        assert_eq!((change.moved_m, change.turned_deg), (0.2997, 3.01));
        assert!(moved(0.021, 0.0).is_some());
        assert!(moved(0.0, 0.21).is_some());
        // After the retry: when its run free from the start is kept, yes;
        // when its held run is, no (at the given pose).
        let mut freed = finished_run(0.03, 0.9, 8.0, 0.9);
        freed.report.retry = Some(RetryRecord {
            free_kept: true,
            ..Default::default()
        });
        assert!(restart_reason(&freed, 24, &options).is_some());
        assert!(restart_reason(&freed, 24, &defaults).is_some());
        // Not when turned off, without the map's planes, or held.
        let mut off = options.clone();
        off.bundle.restart_from_refined_pose = false;
        assert!(restart_reason(&finished_run(0.03, 0.3, 3.0, 0.9), 24, &off).is_none());
        let mut plain = options.clone();
        plain.association.kind = AssociationKind::None;
        assert!(restart_reason(&finished_run(0.03, 0.3, 3.0, 0.9), 24, &plain).is_none());
        let mut held = finished_run(0.03, 0.3, 3.0, 0.9);
        held.report.retry = Some(RetryRecord {
            held_kept: true,
            ..Default::default()
        });
        assert!(restart_reason(&held, 24, &options).is_none());
    }

    #[test]
    fn a_run_the_map_did_not_hold_is_retried_with_the_initial_image_held() {
        let options = MapperOptions::default();
        let reason = retry_reason(&off_map(), &options).unwrap();
        assert!(reason.contains("does not fit the map"), "{reason}");
        let far = Err(MapperError::InitialPoseFarOff {
            moved_m: 1.2,
            turned_deg: 0.5,
            max_m: 1.0,
            max_deg: 10.0,
            fit: None,
        });
        assert!(retry_reason(&far, &options).is_some());
        let slid = Err(MapperError::SlidAlongWeakDirection {
            moved_m: 0.75,
            turned_deg: 6.0,
            max_m: 1.0,
            max_deg: 10.0,
            share: 0.74,
            ratio: 1.5e-3,
        });
        assert!(retry_reason(&slid, &options)
            .unwrap()
            .contains("may have slid"));
        // Errors that holding the initial image cannot mend.
        assert!(retry_reason(&Err(MapperError::EmptyMap), &options).is_none());
        // Finished runs: a nearly free direction (ratio below 1e-3) and the
        // initial image beyond its prior's 0.3 m or 3 deg; the 18 table
        // runs measured ratios 0.019-0.043, a perturbed pose moves back by
        // 0.3 m and 3 deg.
        let weak = MIN_SIMILARITY_CONSTRAINT / 4.0;
        let reason = retry_reason(&Ok(finished_run(weak, 0.45, 0.1, 0.77)), &options).unwrap();
        assert!(reason.contains("ended 0.45 m and 0.1 deg"), "{reason}");
        assert!(retry_reason(&Ok(finished_run(weak, 0.1, 3.5, 0.77)), &options).is_some());
        assert!(retry_reason(&Ok(finished_run(weak, 0.29, 2.9, 0.77)), &options).is_none());
        assert!(retry_reason(&Ok(finished_run(0.02, 0.45, 4.0, 0.77)), &options).is_none());
        // Off, without map terms, and (in the caller) when already held.
        let mut no_retry = options.clone();
        no_retry.bundle.retry_holding_initial = false;
        assert!(retry_reason(&off_map(), &no_retry).is_none());
        let mut plain = options.clone();
        plain.association.kind = AssociationKind::None;
        assert!(retry_reason(&off_map(), &plain).is_none());
    }

    #[test]
    fn the_held_run_is_kept_when_it_passes_and_fits_at_least_as_well() {
        // The initial pose prior's position sigma (the default).
        const PRIOR: f64 = 0.3;
        assert_eq!(
            MapperOptions::default().bundle.initial_prior_position_m,
            PRIOR
        );
        let run = |fit: f64| Ok(finished_run(1e-4, 0.45, 0.1, fit));
        let fit_of = |r: &Result<MapperOutput, MapperError>| r.as_ref().unwrap().report.fit_share;
        // The first failed: the held run when it passed, else the first's error.
        let (kept, held, _) = pick_run(off_map(), run(0.80), PRIOR);
        assert!(held && fit_of(&kept) == Some(0.80));
        let (kept, held, _) = pick_run(off_map(), off_map(), PRIOR);
        assert!(!held);
        let Err(MapperError::RetryFailed { first, held }) = kept else {
            panic!("not both failures: {:?}", kept.err())
        };
        assert!(matches!(*first, MapperError::OffMap { .. }));
        assert!(matches!(*held, MapperError::OffMap { .. }));
        // Both failures are in the message, the first's first.
        let both = MapperError::RetryFailed { first, held }.to_string();
        assert_eq!(
            both.matches("does not fit the map: 45 %").count(),
            2,
            "{both}"
        );
        assert!(both.starts_with("the model does not fit the map"), "{both}");
        assert!(
            both.contains("?\nMapped again with the initial image held at its given pose; that run failed too: the model"),
            "{both}"
        );
        // Both passed: the better fit, the held run on a tie.
        let (kept, held, _) = pick_run(run(0.77), run(0.80), PRIOR);
        assert!(held && fit_of(&kept) == Some(0.80));
        let (kept, held, note) = pick_run(run(0.90), run(0.62), PRIOR);
        assert!(!held && fit_of(&kept) == Some(0.90));
        assert!(
            note.contains("(62.0 % against 90.0 % of its points)"),
            "{note}"
        );
        let (_, held, _) = pick_run(run(0.80), run(0.80), PRIOR);
        assert!(held);
        // The held run failed: the first as it was when it only turned back
        // (3.5 deg, 0.1 m: the planes fix a rotation) or the map holds it
        // (ratio 2e-3; not retried for a weak direction then)...
        for first in [
            finished_run(1e-4, 0.1, 3.5, 0.77),
            finished_run(2e-3, 0.45, 0.1, 0.77),
        ] {
            let (kept, held, note) = pick_run(Ok(first), off_map(), PRIOR);
            assert!(!held && fit_of(&kept) == Some(0.77));
            assert!(
                note.starts_with(
                    "holding the initial image at its given pose did not help: the model does not fit"
                ),
                "{note}"
            );
        }
        // (Without a position prior the retry never asks for a move.)
        let (kept, held, _) = pick_run(run(0.77), off_map(), 0.0);
        assert!(!held && fit_of(&kept) == Some(0.77));
        // ...else neither can be trusted: a first 0.45 m along a nearly free
        // direction (the changed yard, ratio 2e-4) is an error with both
        // reasons, which may mean a pose off (the search follows).
        let (kept, held, _) = pick_run(run(0.77), off_map(), PRIOR);
        assert!(!held);
        let Err(error) = kept else {
            panic!("a loose first run kept")
        };
        assert!(error.may_be_a_pose_off());
        let message = error.to_string();
        assert!(
            message.starts_with("the map's planes leave the model nearly free in one direction (similarity-constraint ratio 1.0e-4, below 1e-3; weakest [rotation, translation, scale] [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]) and the initial image ended 0.45 m and 0.1 deg from its given pose (77 % of its points on the surfaces their images see)"),
            "{message}"
        );
        assert!(
            message.contains("cannot be trusted\nMapped again with the initial image held at its given pose; that run failed too: the model does not fit the map"),
            "{message}"
        );
        // The map fixes the held model in every direction: the given pose
        // disagrees with the map, the first outcome stands.
        let fixed = || Ok(finished_run(0.02, 0.0, 0.0, 0.95));
        let (kept, held, note) = pick_run(off_map(), fixed(), PRIOR);
        assert!(!held && kept.is_err());
        assert!(note.contains("constraint ratio 2.0e-2"), "{note}");
        let (kept, held, _) = pick_run(run(0.77), fixed(), PRIOR);
        assert!(!held && fit_of(&kept) == Some(0.77));
        // Unless its alignment to the map found nothing to move: the map and
        // the given pose agree (the 400-image corridor held: 0.8 mm,
        // 0.0008 deg, scale 0.99993; its first run slid 1.18 m).
        let aligned = |translation_m: f64, rotation_deg: f64, scale: f64| {
            let mut out = finished_run(3.4e-3, 0.004, 0.03, 0.94);
            out.report.alignment = Some(AlignmentRecord {
                scale,
                rotation_deg,
                translation_m,
                ..Default::default()
            });
            Ok(out)
        };
        let (kept, held, note) = pick_run(off_map(), aligned(0.0008, 0.0008, 0.99993), PRIOR);
        assert!(held && fit_of(&kept) == Some(0.94), "{note}");
        assert!(note.contains("the map and the given pose agree"), "{note}");
        // Still the better fit of two that passed.
        let (kept, held, _) = pick_run(run(0.96), aligned(0.0008, 0.0008, 0.99993), PRIOR);
        assert!(!held && fit_of(&kept) == Some(0.96));
        // A trial that moves nothing but a fit below 90 %: the room 0 table
        // run held at a pose 0.3 m off (0.28 m wrong, trial 1 mm, fit 65 %).
        let mut loose = aligned(0.001, 0.07, 1.00001);
        if let Ok(out) = &mut loose {
            out.report.fit_share = Some(0.65);
        }
        let (kept, held, note) = pick_run(off_map(), loose, PRIOR);
        assert!(!held && kept.is_err(), "{note}");
        assert!(note.contains("65.0 % of its points fit"), "{note}");
        // A trial that would move it in any of the three: the first stands.
        for (t, r, sc) in [(0.05, 0.0, 1.0), (0.0, 0.5, 1.0), (0.0, 0.0, 0.99)] {
            let (kept, held, note) = pick_run(off_map(), aligned(t, r, sc), PRIOR);
            assert!(!held && kept.is_err(), "{note}");
            assert!(note.contains("its alignment trial moved it"), "{note}");
        }
        // A partly mapped held run is judged by the points the map covers:
        // 34 % on the map over all, 93 % over the covered ones, settled.
        let partial = |covered_fit: f64| {
            let mut out = aligned(0.0008, 0.0008, 0.99993);
            if let Ok(out) = &mut out {
                out.report.fit_share = Some(0.34);
                out.report.covered_fit_share = Some(covered_fit);
                out.report.partial_map = true;
            }
            out
        };
        let (kept, held, note) = pick_run(off_map(), partial(0.93), PRIOR);
        assert!(held && fit_of(&kept) == Some(0.34), "{note}");
        assert!(
            note.contains("93.0 % of the points the map covers"),
            "{note}"
        );
        let (kept, held, note) = pick_run(off_map(), partial(0.85), PRIOR);
        assert!(!held && kept.is_err(), "{note}");
        assert!(
            note.contains("85.0 % of the points the map covers fit"),
            "{note}"
        );
        // Against a first run that passed, like with like: covered fits.
        let mut first = finished_run(3.4e-3, 0.004, 0.03, 0.36);
        first.report.covered_fit_share = Some(0.91);
        first.report.partial_map = true;
        let (kept, held, note) = pick_run(Ok(first), partial(0.93), PRIOR);
        assert!(held && kept.is_ok(), "{note}");
    }

    /// The retry schedule, each run's outcome given by the options it was
    /// called with (which of the three runs it is): the run as configured
    /// (initial image held for its first 8 registrations), free from the
    /// start, held throughout.
    #[test]
    fn a_failed_early_held_run_is_mapped_free_then_held() {
        const N: usize = 24;
        let options = MapperOptions::default();
        assert!(options.bundle.fix_initial_for > 0 && options.bundle.fix_initial_for < N);
        // A held run the map agrees with (see `pick_run`).
        let settled = || {
            let mut out = finished_run(0.02, 0.0, 0.0, 0.94);
            out.report.alignment = Some(AlignmentRecord {
                scale: 1.00001,
                rotation_deg: 0.001,
                translation_m: 0.001,
                ..Default::default()
            });
            Ok(out)
        };
        #[derive(Clone, Copy, Debug, PartialEq)]
        enum Which {
            First,
            Free,
            Held,
        }
        let which = |o: &MapperOptions| match (
            o.bundle.fix_initial_for,
            o.bundle.hold_initial_in_final_rounds,
        ) {
            (0, false) => Which::Free,
            (n, true) if n == N => Which::Held,
            (n, false) if n == options.bundle.fix_initial_for => Which::First,
            other => panic!("unexpected run {other:?}"),
        };
        // Runs the schedule; each run takes (its index + 1) seconds.
        let schedule =
            |options: &MapperOptions,
             outcome: &dyn Fn(Which) -> Result<MapperOutput, MapperError>| {
                let mut calls = Vec::new();
                let mut run = |o: &MapperOptions| {
                    calls.push(which(o));
                    (outcome(which(o)), calls.len() as f64)
                };
                let first = run(options);
                let result = run_with_retries(options, N, first, |asked, o: &MapperOptions| {
                    let expected = match asked {
                        RetryRun::Free => Which::Free,
                        RetryRun::Held => Which::Held,
                    };
                    assert_eq!(which(o), expected, "asked for {asked:?}");
                    run(o)
                });
                (result, calls)
            };

        // A good first run is all.
        let (kept, calls) = schedule(&options, &|_| Ok(finished_run(0.02, 0.0, 0.0, 0.9)));
        assert_eq!(calls, [Which::First]);
        assert!(kept.unwrap().report.retry.is_none());

        // The first off the map, the free run right: the free run, and no held run.
        let (kept, calls) = schedule(&options, &|w| match w {
            Which::Free => Ok(finished_run(0.02, 0.0, 0.0, 0.88)),
            _ => off_map(),
        });
        assert_eq!(calls, [Which::First, Which::Free]);
        let report = kept.unwrap().report;
        assert_eq!(report.fit_share, Some(0.88));
        let retry = report.retry.unwrap();
        assert!(retry.free_kept && !retry.held_kept, "{retry:?}");
        assert!(
            retry.reason.contains("does not fit the map"),
            "{}",
            retry.reason
        );
        assert_eq!(
            (retry.first_run_s, retry.free_run_s, retry.held_run_s),
            (1.0, Some(2.0), None)
        );

        // The free run fails too, on the map or with an error holding cannot
        // mend: the held run, which the map agrees with, is kept.
        let empty_map = || Err(MapperError::EmptyMap);
        for free_error in [
            off_map as fn() -> Result<MapperOutput, MapperError>,
            empty_map,
        ] {
            let free_message = free_error().err().unwrap().to_string();
            let (kept, calls) = schedule(&options, &|w| match w {
                Which::Held => settled(),
                Which::Free => free_error(),
                Which::First => off_map(),
            });
            assert_eq!(calls, [Which::First, Which::Free, Which::Held]);
            let report = kept.unwrap().report;
            assert_eq!(report.fit_share, Some(0.94));
            let retry = report.retry.unwrap();
            assert!(retry.held_kept && !retry.free_kept, "{retry:?}");
            assert_eq!(
                (retry.first_run_s, retry.free_run_s, retry.held_run_s),
                (1.0, Some(2.0), Some(3.0))
            );
            assert!(
                retry.outcome.starts_with(&format!("the run free from the start: {free_message}; kept the run with the initial image held")),
                "{}",
                retry.outcome
            );
        }

        // The held run fails as well: both errors, the free run's first.
        let (kept, calls) = schedule(&options, &|w| match w {
            Which::Free => Err(MapperError::EmptyMap),
            _ => off_map(),
        });
        assert_eq!(calls, [Which::First, Which::Free, Which::Held]);
        let Err(MapperError::RetryFailed { first, held }) = kept else {
            panic!("not both failures: {:?}", kept.err())
        };
        assert!(matches!(*first, MapperError::EmptyMap), "{first}");
        assert!(matches!(*held, MapperError::OffMap { .. }), "{held}");

        // Without the early hold there is no free rerun: straight to held.
        let mut free_from_start = options.clone();
        free_from_start.bundle.fix_initial_for = 0;
        let (kept, calls) = schedule(&free_from_start, &|w| match w {
            Which::Held => settled(),
            _ => off_map(),
        });
        assert_eq!(calls, [Which::Free, Which::Held]);
        let retry = kept.unwrap().report.retry.unwrap();
        assert!(retry.held_kept && retry.free_run_s.is_none(), "{retry:?}");

        // Already held throughout, or the retry off: the first outcome stands.
        let mut no_retry = options.clone();
        no_retry.bundle.retry_holding_initial = false;
        let (kept, calls) = schedule(&no_retry, &|_| off_map());
        assert_eq!(calls, [Which::First]);
        assert!(matches!(kept, Err(MapperError::OffMap { .. })));
        let mut held = options.clone();
        held.bundle.fix_initial_for = N;
        held.bundle.hold_initial_in_final_rounds = true;
        let (kept, calls) = schedule(&held, &|_| off_map());
        assert_eq!(calls, [Which::Held]);
        assert!(matches!(kept, Err(MapperError::OffMap { .. })));
    }
}
