//! Options of the mapper, one struct per stage, each with documented defaults
//! (units in the names) and a `validate()`. All of them deserialise from the
//! `[mapper]` table of a TOML options file (missing keys keep their defaults,
//! unknown keys are errors).
use serde::{Deserialize, Serialize};

use crate::map::projection::{widen_splats_for_spacing, ProjectionOptions, SplatOptions};

/// An option out of range: names the option and the value.
#[derive(Debug, thiserror::Error)]
#[error("invalid mapper option `{name}`: {message}")]
pub struct OptionsError {
    pub name: String,
    pub message: String,
}

fn check(ok: bool, name: &str, message: impl Into<String>) -> Result<(), OptionsError> {
    if ok {
        Ok(())
    } else {
        Err(OptionsError {
            name: name.to_owned(),
            message: message.into(),
        })
    }
}

/// Magnitudes beyond which no option of the mapper means anything, and
/// whose squares (loss scales, weights) would overflow or underflow inside
/// the solver: a Cauchy scale of 1e200 px made every cost NaN.
const OPTION_MAGNITUDE: (f64, f64) = (1e-100, 1e100);

/// `v` as an error message shows it: plain, or in scientific notation when
/// very small or large (not 300 digits).
fn show(v: f64) -> String {
    if v != 0.0 && v.is_finite() && !(1e-4..1e6).contains(&v.abs()) {
        format!("{v:e}")
    } else {
        format!("{v}")
    }
}

fn positive(name: &str, v: f64) -> Result<(), OptionsError> {
    let (lo, hi) = OPTION_MAGNITUDE;
    check(
        v.is_finite() && (lo..=hi).contains(&v),
        name,
        format!("must be > 0, in [{lo:e}, {hi:e}], got {}", show(v)),
    )
}

fn non_negative(name: &str, v: f64) -> Result<(), OptionsError> {
    let (lo, hi) = OPTION_MAGNITUDE;
    check(
        v == 0.0 || (v.is_finite() && (lo..=hi).contains(&v)),
        name,
        format!("must be 0 or in [{lo:e}, {hi:e}], got {}", show(v)),
    )
}

/// Most RANSAC iterations of a registration (`register.max_iterations`).
const MAX_RANSAC_ITERATIONS: usize = 1_000_000;

/// Largest plane neighbourhood (`association.plane_radius_m`,
/// `plane_window_m`), metres: each plane's offset averages the map within
/// it, so 100 m averaged the whole map for every plane. (The radius grows
/// with a sparse map's spacing, 2.5 times it: a 4 m map is the sparsest
/// that passes, far sparser than any the tool can use.)
const MAX_PLANE_RADIUS_M: f64 = 10.0;

/// Initialisation from the map (method.md 4.4).
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct InitOptions {
    /// Map points closer than this along the optical axis are ignored, metres
    /// (a fisheye camera's: closer than this to it). Default 0.5.
    pub min_depth_m: f64,
    /// Map points deeper than this are ignored, metres. Default 40.
    pub max_depth_m: f64,
    /// Rays closer than this angle to the tangent plane are rejected, degrees. Default 10.
    pub min_ray_plane_angle_deg: f64,
    /// The ray-plane intersection may lie at most this far from the LiDAR
    /// point whose plane it uses, metres (and never farther than the half
    /// diagonal of that point's splat). Default 0.5.
    pub max_plane_extrapolation_m: f64,
    /// Fewest LiDAR-supported features the initial image needs. Default 30.
    pub min_lidar_features: usize,
    /// Second-image candidates tried before giving up. Default 20.
    pub max_candidates: usize,
    /// Half-width of the surface patch a map point stands for when the map
    /// is seen from a camera (its square splat, see
    /// [`crate::map::projection::SplatOptions`]), metres; raised to
    /// [`crate::map::projection::SPLAT_PER_SPACING`] times the map's spacing for sparser maps (so a
    /// camera does not see through the map's surfaces). Default 0.02632
    /// (the reference implementation's splat).
    pub splat_half_width_m: f64,
    /// Half-width of that patch at every depth, also nearer than 2 m where
    /// the reference's splat stops growing (there a camera would see
    /// between a map's points), metres; raised to
    /// [`crate::map::projection::SPLAT_PER_SPACING`] times the map's
    /// spacing (so it cannot be switched off: on a 2 cm map it matters
    /// nearer than about 0.7 m). Default 0.
    pub splat_near_half_width_m: f64,
}

impl Default for InitOptions {
    fn default() -> Self {
        Self {
            min_depth_m: 0.5,
            max_depth_m: 40.0,
            min_ray_plane_angle_deg: 10.0,
            max_plane_extrapolation_m: 0.5,
            min_lidar_features: 30,
            max_candidates: 20,
            splat_half_width_m: SplatOptions::default().patch_half_width_m,
            splat_near_half_width_m: 0.0,
        }
    }
}

impl InitOptions {
    /// How the map is seen from a camera (its depth range and splat size):
    /// for the initial image and for the behind-map filter.
    pub fn projection(&self) -> ProjectionOptions {
        ProjectionOptions {
            min_depth_m: self.min_depth_m,
            max_depth_m: self.max_depth_m,
            splat: SplatOptions {
                patch_half_width_m: self.splat_half_width_m,
                near_half_width_m: self.splat_near_half_width_m,
                ..Default::default()
            },
        }
    }

    pub fn validate(&self) -> Result<(), OptionsError> {
        positive("init.min_depth_m", self.min_depth_m)?;
        non_negative("init.splat_half_width_m", self.splat_half_width_m)?;
        non_negative("init.splat_near_half_width_m", self.splat_near_half_width_m)?;
        check(
            self.max_depth_m.is_finite() && self.max_depth_m > self.min_depth_m,
            "init.max_depth_m",
            "must be finite and > min_depth_m",
        )?;
        check(
            (0.0..90.0).contains(&self.min_ray_plane_angle_deg),
            "init.min_ray_plane_angle_deg",
            "must be in [0, 90)",
        )?;
        positive(
            "init.max_plane_extrapolation_m",
            self.max_plane_extrapolation_m,
        )?;
        check(
            self.min_lidar_features >= 4,
            "init.min_lidar_features",
            "must be >= 4",
        )?;
        check(
            self.max_candidates >= 1,
            "init.max_candidates",
            "must be >= 1",
        )
    }
}

/// Registration of an image by PnP (P3P in LO-RANSAC, then refinement).
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct RegisterOptions {
    /// RANSAC inlier threshold on the reprojection error, pixels. Default 4.
    pub max_error_px: f64,
    /// Fewest inliers for a registration. Default 30.
    pub min_num_inliers: usize,
    /// Smallest inlier ratio for a registration. Default 0.25.
    pub min_inlier_ratio: f64,
    /// RANSAC confidence. Default 0.9999.
    pub confidence: f64,
    /// Fewest RANSAC iterations. Default 100.
    pub min_iterations: usize,
    /// Most RANSAC iterations. Default 10000.
    pub max_iterations: usize,
    /// Huber scale of the pose refinement, pixels. Default 1.
    pub refine_huber_px: f64,
    /// Levels of the visibility pyramid for next-best-view scoring. Default 6.
    pub pyramid_levels: usize,
    /// An image that failed is retried only once it sees this many more 3D
    /// points than at its last failure. Default 10.
    pub retry_min_new_points: usize,
}

impl Default for RegisterOptions {
    fn default() -> Self {
        Self {
            max_error_px: 4.0,
            min_num_inliers: 30,
            min_inlier_ratio: 0.25,
            confidence: 0.9999,
            min_iterations: 100,
            max_iterations: 10_000,
            refine_huber_px: 1.0,
            pyramid_levels: 6,
            retry_min_new_points: 10,
        }
    }
}

impl RegisterOptions {
    pub fn validate(&self) -> Result<(), OptionsError> {
        positive("register.max_error_px", self.max_error_px)?;
        check(
            self.min_num_inliers >= 4,
            "register.min_num_inliers",
            "must be >= 4",
        )?;
        check(
            (0.0..=1.0).contains(&self.min_inlier_ratio),
            "register.min_inlier_ratio",
            "must be in [0, 1]",
        )?;
        check(
            self.confidence > 0.0 && self.confidence < 1.0,
            "register.confidence",
            "must be in (0, 1)",
        )?;
        check(
            self.min_iterations >= 1
                && self.max_iterations >= self.min_iterations
                && self.max_iterations <= MAX_RANSAC_ITERATIONS,
            "register.max_iterations",
            format!("need 1 <= min_iterations <= max_iterations <= {MAX_RANSAC_ITERATIONS}"),
        )?;
        positive("register.refine_huber_px", self.refine_huber_px)?;
        check(
            (1..=12).contains(&self.pyramid_levels),
            "register.pyramid_levels",
            "must be in 1..=12",
        )
    }
}

/// Triangulation, track continuation and merging.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct TriangulateOptions {
    /// Largest reprojection error of an observation of a new point, pixels. Default 4.
    pub max_error_px: f64,
    /// Smallest triangulation angle of a new point, degrees. Default 1.5.
    pub min_angle_deg: f64,
    /// Largest reprojection error when continuing or merging tracks, pixels. Default 4.
    pub max_merge_error_px: f64,
}

impl Default for TriangulateOptions {
    fn default() -> Self {
        Self {
            max_error_px: 4.0,
            min_angle_deg: 1.5,
            max_merge_error_px: 4.0,
        }
    }
}

impl TriangulateOptions {
    pub fn validate(&self) -> Result<(), OptionsError> {
        positive("triangulate.max_error_px", self.max_error_px)?;
        non_negative("triangulate.min_angle_deg", self.min_angle_deg)?;
        positive("triangulate.max_merge_error_px", self.max_merge_error_px)
    }
}

/// Bundle adjustment schedule and losses.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct BundleOptions {
    /// Images co-visible with the new one that join its local BA. Default 5.
    pub local_num_neighbours: usize,
    /// Levenberg-Marquardt iterations of a local BA. Default 30.
    pub local_max_iterations: usize,
    /// Levenberg-Marquardt iterations of a global BA. Default 50.
    pub global_max_iterations: usize,
    /// Run a global BA after this many new registrations. Default 20 (the
    /// reference: 5; with the map holding the gauge, 20 measured the same
    /// accuracy on the 24-image scenes and a 100-image corridor in less time).
    pub global_every_images: usize,
    /// Also run a global BA when the model grew by this fraction. Default 0.1
    /// (frequent while the model is small: that is when a perturbed initial
    /// pose gets pulled into the map; 0.5 left the demo yard 36 cm off).
    pub global_growth_ratio: f64,
    /// The growth rule applies while fewer images than this are registered
    /// (afterwards only `global_every_images`): the map has pulled the model
    /// in by then, and frequent global BAs of a large model cost the most
    /// time. Default 30.
    pub global_growth_until_images: usize,
    /// Stop a solve when the relative cost decrease falls below this.
    /// Default 1e-5: on the 100-image corridor, 1e-6 (Ceres' default) took
    /// 45 % more iterations (1152 against 794 over the run's solves) and
    /// 164 s against 103 s for the same model (camera centres 1.1 against
    /// 1.0 mm median): the final rounds re-associate and solve again until
    /// the cameras stop moving, so a solve that stops a little earlier only
    /// hands its last small steps on.
    pub function_tolerance: f64,
    /// Soft-L1 scale on reprojection residuals, pixels. Default 1.
    pub reprojection_loss_px: f64,
    /// Which solves refine the cameras' focal length and distortion (the
    /// principal point is held unless `refine_principal_point`). Default `auto`: every
    /// solve for a camera whose database row marks its focal length as a
    /// guess (`prior_focal_length = 0`); the others are probed after the
    /// final rounds (see [`IntrinsicsRefinement::Auto`]). In TOML also
    /// `true` (= `final`, the old meaning) or `false` (= `fixed`).
    pub refine_intrinsics: IntrinsicsRefinement,
    /// Whose principal point the solves that refine a camera refine too
    /// (COLMAP: `--Mapper.ba_refine_principal_point`, off). Default `auto`:
    /// the cameras whose focal length the database marks as a guess
    /// (`prior_focal_length = 0`), whose principal point is then COLMAP's
    /// guess too (the image centre); `never` holds every principal point, as
    /// COLMAP does, `always` refines it wherever the focal length is refined.
    /// The map holds the cameras' rotations against the scene, which is what
    /// separates a principal point from a turn of the camera. Measured on
    /// databases whose camera was replaced by COLMAP's guess (24 images,
    /// perturbed pose; held / refined): a fisheye room 11.9 / 1.0 mm and
    /// 0.33 / 0.013 deg, OPENCV room 5.9 / 3.6 mm, OPENCV yard 10.0 / 10.0 mm
    /// (p90 22.8 / 13.7 mm; principal point 1.5 and -1 px off the centre in
    /// all three), SIMPLE_RADIAL yard (principal point at the centre) 3.2 /
    /// 3.1 mm.
    pub refine_principal_point: PrincipalPointRefinement,
    /// With `auto`, a given focal length is refined only when one solve with
    /// it free, after the final rounds, moves it by more than this fraction
    /// (then the rounds run again with it free). Default 0.001: refined in
    /// the final rounds, the true camera (given) moved by up to 0.00058 on
    /// the nine 24-image scenes, and five of them got worse by up to 1.9 mm
    /// (yard seed 0: 3.8 -> 5.7 mm), three better by at most 0.2 mm; an EXIF
    /// focal length is off by more.
    pub refine_intrinsics_min_change: f64,
    /// Levenberg-Marquardt iterations of that probing solve (at most
    /// `global_max_iterations`). It only
    /// has to show whether the focal length moves; when it does, the rounds
    /// run again with it free. Default 5: on the seed-0 corridor with the
    /// focal length given 1 % and 0.2 % too long, 5 iterations found 97 %
    /// and 98 % of the change the uncapped probe found (3: 83 %, 85 %); on
    /// the 200-image corridor the uncapped probe took 8 iterations.
    pub probe_max_iterations: usize,
    /// Cameras with the same model, size and parameters in the database
    /// share one set of intrinsics in every solve (COLMAP's extractor makes
    /// one camera per image unless `--ImageReader.single_camera 1`). Measured
    /// on the seed-0 corridor with 24 such cameras at COLMAP's guess (768 px
    /// for 512): refined one by one, one image's focal length fell to 58 px
    /// and the run failed; shared, see docs/guide.md (Intrinsics). Default true.
    pub share_identical_intrinsics: bool,
    /// The initial image stays fixed for this many registrations (when LiDAR
    /// constraints hold the gauge), at its pose after the initial pair's
    /// alignment to the map, then only its soft prior below holds it.
    /// Default 8, as the reference. Free from the start, the first solves
    /// slid the model along the corridor: with the exact pose the seed-0
    /// corridor's initial image was 0.53 m off after the initial pair's
    /// solve and 0.95 m after the fourth image's (forward motion: the few
    /// surfaces across the corridor are far and the near ones parallel to
    /// the walk); the 400-image corridor stayed 1.2 m off and needed the
    /// held retry. Held for 8: the same slide after release is 0.14 /
    /// 0.39 m and comes back as the model grows. (Before the initial pair's
    /// alignment existed, holding for 8 locked a pose 0.3 m / 3 deg off in:
    /// the seed-2 corridor and room ended 0.36 and 0.55 m off.)
    pub fix_initial_for: usize,
    /// Whether an initial image held by `fix_initial_for` (at least the
    /// number of images registered by then) stays held through the final
    /// stage (whole-model alignment, final rounds, intrinsics probe, pose
    /// uncertainty). False frees it there, under its soft prior: held
    /// through registration, the model cannot drift; freed at the end, the
    /// map can correct the given pose. True with `fix_initial_for` at least
    /// the image count holds it throughout (the held retry's setting), for a
    /// pose trusted more than the map: from poses 0.3 m / 3 deg off four of
    /// nine table scenes then end 0.22-0.30 m off without an error (see
    /// docs/guide.md, Holding the initial image). Default false (a run of at
    /// most `fix_initial_for` images is held through registration only).
    pub hold_initial_in_final_rounds: bool,
    /// The initial image has a soft prior at its given pose with this
    /// standard deviation of the position, metres: after `fix_initial_for`
    /// it only matters along directions the map does not fix. 0 disables.
    /// Default 0.3 (the initial pose is trusted to a few decimetres).
    pub initial_prior_position_m: f64,
    /// Standard deviation of the prior's rotation, degrees. 0 disables.
    /// Default 3.
    pub initial_prior_rotation_deg: f64,
    /// The run fails (no output) when the initial image ends farther than
    /// this from its given position, metres: the given pose was too far off
    /// for the result to be trusted. Measured on the seed-7 yard from poses
    /// 0.57-1.2 m and 0-8 deg off, before the alignment could move a model
    /// more than 2 m: four runs ended 1.6-2.0 m off at a wrong scale with
    /// 62-79 % of their points on the surface their images see (above
    /// `min_points_on_map_share`), their initial image 1.1-1.8 m from the
    /// given pose. 0 disables. Default 1 (3.3 sigmas of the default prior).
    pub max_initial_pose_change_m: f64,
    /// The same for the rotation, degrees. 0 disables. Default 10.
    pub max_initial_pose_change_deg: f64,
    /// When the map did not hold the model (the fit check or the initial
    /// pose's limit failed; or the final planes leave a similarity nearly
    /// free and the initial image moved farther than its prior's standard
    /// deviation), map again with the initial image held at its given pose
    /// throughout, and keep that run if it passes the checks (and, when the
    /// first passed too, fits the map at least as well; where its planes
    /// fix the whole model, only if its alignment trial finds nothing to
    /// move: see `runs::pick_run`). On the seed-0 yard
    /// changed since the scan (`synth --changes 3`; the map shows only the
    /// ground and two facades through one corner) the model slid 0.98 m and
    /// failed the fit check; held, it ended 1.4 mm off (fit 80 %); from the
    /// perturbed pose the held run fits 50 % and the run fails as before.
    /// Default true.
    pub retry_holding_initial: bool,
    /// When the initial image ended more than 2 cm or 0.2 deg from its given
    /// pose (the pose was off; runs from exact poses move it 1-2 mm and
    /// 0.01-0.02 deg), map again from where it ended and keep that run if
    /// it passes the checks. The initial image is held for its first
    /// `fix_initial_for` registrations, so a model started from a pose 0.3 m
    /// off is built around that error and only freed from it later, and it
    /// ends where the map's grazing-angle bias lets it settle: the seed-0
    /// corridor from 0.3 m / 3 deg off ended 2.4 mm off (scale 0.99959);
    /// mapped again from where its initial image ended, 0.9 mm (scale
    /// 0.999995), as from the exact pose. Costs a second run when the pose
    /// was off. Not after a retry (`retry_holding_initial`). Default true.
    /// Since session 63 only the run the retry freed from the start is
    /// mapped again by default; the first run, which held the image, is
    /// only with `restart_first_run`.
    pub restart_from_refined_pose: bool,
    /// With `restart_from_refined_pose`, the first run (the initial image
    /// held at its given pose for its first `fix_initial_for` registrations)
    /// is mapped again from where its initial image ended too, and the early
    /// look and the look at the end of registration
    /// (`restart_early_at_images`) come with it. Default false: the second
    /// run made the result the exact pose's (to 0.14 mm) but no more
    /// accurate. Session 63, the fifteen 24-image scenes from 0.3 m / 3
    /// deg off: sum of medians 22.6 mm in one run against 22.4 mm mapped
    /// again (each within 0.4 mm either way); from 0.7 m / 7 deg off (14
    /// mapped) 22.06 mm against 22.11 mm; the 100-image corridor 1.1 mm
    /// either way; 12-41 % less time (the seed-4 corridor 21.2 s against
    /// 36.0 s). The run the retry freed from the start held no image and
    /// is mapped again whatever this says (`restart_from_refined_pose`):
    /// the seed-0 corridor changed since the scan, 3.0 mm as it ended, 1.4
    /// mm mapped again. See also `restart_first_run_from_images`, which
    /// makes it the default in large databases.
    pub restart_first_run: bool,
    /// `restart_first_run` in a database of at least this many images
    /// (0: by `restart_first_run` alone). Default 48, three times
    /// `restart_early_at_images`' default, where the early look comes at a
    /// fixed image count. At 60 images the one run's shape is the second
    /// run's but its placement is not: from 0.3 m / 3 deg off, the seed-4
    /// corridor 1.37 mm in one run against 1.00 mm mapped again (`colmap
    /// mapper` + oracle 0.76 mm), seed 0 2.54 against 2.23 mm, seed 3 0.98
    /// against 0.77 mm (oracle 0.72 mm), each then its exact pose's
    /// value; the seed-3 room and yard unchanged (sessions 64-65); a fresh
    /// seed-4 database 1.52 against 1.14 mm (exact 1.11, oracle 0.75; session
    /// 66). At 24 images it bought nothing (above), at 48 and 100 images
    /// nothing either (0.84 / 0.87 mm, 0.98 / 1.07 mm; oracle 0.66, 1.25
    /// mm), for none to 1.7 times the one run's time (100 images: ratio
    /// 0.81 to `colmap mapper`).
    pub restart_first_run_from_images: usize,
    /// With `restart_from_refined_pose`, the run looks at its initial image
    /// once, at the first sphere solve with at least this many images
    /// registered and the image released (`fix_initial_for`): when it has
    /// already turned more than 1 deg from its given pose (within the
    /// accepted change) and the model has settled (its alignment to the map,
    /// tried there, would not move the image 2 cm / 0.2 deg), the run stops
    /// there and maps again from that pose, instead of finishing first and
    /// mapping again from where it ended. Only a turn counts: the map's
    /// normals fix the rotation early, while a move may be a slide along a
    /// corridor that the growing model undoes (the seed-0 100-image corridor
    /// from its exact pose: 0.149 m and 0.04 deg at 17 images, back at the
    /// end). A run from there that moves the image 10 cm or 1 deg again
    /// counts as failed, and the first run is mapped from the given pose to
    /// its end as without the look (session 40: the seed-2 60-image
    /// corridor, looked at mid-slide, ended 0.63 m off along the corridor
    /// without an error when that run was mapped once more from its end),
    /// unless it kept the look's rotation and fits the map (fit at least
    /// 0.9): then it slid back from a look taken mid-slide and is mapped
    /// again from where it ended (the seed-0 100-image corridor from 0.3 m /
    /// 3 deg off: three runs instead of four).
    /// In a database of fewer than three times this many images the look
    /// comes from a third of them on (after the release), at the first
    /// sphere solve that moved the image at most 1 cm and 0.1 deg from where
    /// the one before left it while the map holds the model along every
    /// direction, and not after two thirds of them; with the defaults not
    /// at all in a database of fewer than 15 (`runs::early_look_at`).
    /// A first run that did not stop there looks once more at the end of its
    /// registration: when the image has turned more than 1 deg from its
    /// given pose (the run would be mapped again from where it ends), it
    /// stops before its final stage and is mapped again from where the whole
    /// model's alignment to the map puts the image, if that is still more
    /// than 2 cm or 0.2 deg from the given pose, under half the accepted
    /// change, and at least 80 % of the points lie on the surfaces their
    /// images see there; the run from a look stops at the end of its own
    /// registration when it moved the image 10 cm or 1 deg again (the
    /// rule above, without its final stage). A run from a look taken while
    /// the image was still moving (more than 1 cm or 0.1 deg since the
    /// sphere solve before) or while the map held the model loosely
    /// (similarity-constraint ratio below 1e-2, or none: only the look of a
    /// database of three times this many images or more can be either)
    /// looks once more, at its first such steady and
    /// firm sphere solve after the image's release (up to 32 images): when
    /// the image slid more than 0.3 m from the look's pose without turning
    /// and 90 % of the points lie on the surfaces their images see, it stops
    /// there and is mapped again from that pose. 0 looks only at the end of
    /// the finished run. Default 16.
    pub restart_early_at_images: usize,
    /// When the run from the given initial pose failed as if that pose were
    /// off (the fit check, the initial pose's limit, the slid-along check,
    /// or no map support or second image at that pose; also after the held
    /// retry), search the map within this many metres of the given pose
    /// (vertically at most 1 m) and map again from what the search finds,
    /// as `map --init-search` does; its own checks still apply, and the
    /// first run's error is in `report.json` → `init_search.after_failure`.
    /// The mapper's own basin is about 0.5 m and 5 deg; the search, 2 m and
    /// 20-30 deg on the seed-0 scenes (`docs/results.md`, sessions 35-38).
    /// Not with `--init-search` (already a search) or
    /// `--no-lidar-constraints`. 0 disables. Default 2.
    pub fallback_search_m: f64,
    /// The heading range of that search, degrees either way (180: any).
    /// Default 30.
    pub fallback_search_deg: f64,
    /// After the initial pair and again before the final rounds, move the
    /// whole model (shape held) onto the map: point-to-plane ICP over a
    /// similarity, coarse to fine (1 m to 0.1 m), kept only when more points
    /// end within 2 cm of the map (the initial pair's: at least 1 % more,
    /// see `mapper::INITIAL_PAIR_MIN_GAIN`; before the final rounds, never while the
    /// initial image is held: a trial only). It undoes a placement that is wrong as a
    /// whole, which the solves do not (measured with the initial pose 0.3 m /
    /// 3 deg off: seed-2 corridor 0.36 m -> 1.7 mm, yard 0.58 m -> 12 mm
    /// before the final rounds; on the re-rendered seed-2 yard the model
    /// ended 7 % small and 0.57 m off until the initial pair was aligned
    /// too: 1.1 mm). Default true.
    pub align_to_map: bool,
    /// Most final global bundle adjustments, each after a re-association (an
    /// ICP-like loop: the map pulls the model a little further each round
    /// along directions it constrains weakly). Default 12.
    pub final_rounds: usize,
    /// The final rounds stop once half the camera centres moved less than
    /// this in a round, metres. Default 0.0002. (The median, not the
    /// largest move: a slide of the whole model moves every camera alike,
    /// but in a large model a few cameras always move a little as points
    /// change planes. On a 200-image corridor the largest move stayed at
    /// 0.2-0.45 mm from the third round to the seventh while the cost
    /// changed by 0.1 %. On the 24-image scenes 17 of 18 runs ended within
    /// 0.2 mm of the old rule's error; the seed-2 yard from a perturbed pose,
    /// which never settles (median move 0.2-0.8 mm a round), stopped at a
    /// dip after 3 rounds at 1.5 mm, where 12 rounds had ended at 1.0 mm.)
    pub final_stop_change_m: f64,
    /// A final round after one that moved half the camera centres more than
    /// this, metres, takes a Huber loss (at `association.final_loss_scale_m`,
    /// the smallest radius as in every round after the first) instead of
    /// `association.final_loss`; 0: never. A model that arrives from
    /// registration decimetres off (a run from a pose that was off) is far
    /// beyond the Cauchy loss's centimetre scale, where each point's pull
    /// fades: the seed-3 room from the perturbed pose crawled 1-6 cm a round
    /// for ten rounds (33 s of a 70 s mapping). Default 0.01: most runs
    /// from exact poses move their cameras a few millimetres in the first
    /// round and go on as before; the yards' sparse maps move them over
    /// 1 cm, and their models changed by at most 0.02 mm.
    pub final_huber_above_move_m: f64,
    /// Weight of a known image position (pose file, database), pixel
    /// equivalents per metre: 100 makes 1 cm count like 1 px. 0 disables.
    /// Default 100.
    pub prior_position_weight: f64,
    /// Weight of a known image rotation, pixel equivalents per degree.
    /// 0 disables. Default 10.
    pub prior_rotation_weight: f64,
    /// Passes of each local BA, each after a re-association: the first with
    /// the robust plane losses, the others plain (the reference's schedule
    /// has two). Measured on the 24-image yard, room and corridor: the same
    /// accuracy (within 0.1 mm) for 1.5x the time, hence default 1.
    pub local_passes: usize,
    /// Periodic global BAs vary the images whose centres lie within this
    /// distance of the newest image (the others are held), metres. Default 40.
    pub global_radius_m: f64,
    /// ... and at most this many of them, the nearest to the newest image
    /// (0: no cap). A long model then costs each periodic BA the same, not
    /// more with every image: the final rounds solve the whole model anyway.
    /// Default 60.
    pub global_max_images: usize,
    /// Threads of the Ceres solver. More than one may change the last bits
    /// between runs. Default 1 (byte-identical output).
    pub num_threads: usize,
    /// After the final rounds, each image's pose uncertainty (report.json)
    /// is computed when at most this many images are registered (a dense
    /// matrix of 6 rows per image is inverted: 300 images take a few
    /// seconds). 0 disables. Default 300.
    pub uncertainty_max_images: usize,
    /// The pose uncertainty is also given cluster-robust: the final solve's
    /// residuals are grouped by the cube of this side, metres, that their
    /// point lies in, and the scatter of the groups' pulls on the poses,
    /// not the residuals' count, says how well the data fix them (see
    /// `solver::clustered_pose_covariances`). The map's noise shared by
    /// neighbouring points and a feature bias common to a surface then
    /// count once per cube, not once per point. On the nine 24-image scenes
    /// (session 40, exact initial pose) the true centre errors were 0.41-3.63
    /// times the formal sigma (median 1.80; 0.67-1.54 is what calibrated
    /// sigmas give) and 0.17-2.03 times the 1 m clustered sigma (median
    /// 0.93; 0.3 m cubes: 1.45). 0 turns it off. Default 1.
    pub uncertainty_cluster_m: f64,
}

impl Default for BundleOptions {
    fn default() -> Self {
        Self {
            local_num_neighbours: 5,
            final_rounds: 12,
            local_passes: 1,
            global_radius_m: 40.0,
            global_max_images: 60,
            prior_position_weight: 100.0,
            prior_rotation_weight: 10.0,
            final_stop_change_m: 0.0002,
            final_huber_above_move_m: 0.01,
            local_max_iterations: 30,
            global_max_iterations: 50,
            global_every_images: 20,
            global_growth_ratio: 0.1,
            global_growth_until_images: 30,
            function_tolerance: 1e-5,
            reprojection_loss_px: 1.0,
            refine_intrinsics: IntrinsicsRefinement::Auto,
            refine_principal_point: PrincipalPointRefinement::Auto,
            refine_intrinsics_min_change: 0.001,
            probe_max_iterations: 5,
            share_identical_intrinsics: true,
            fix_initial_for: 8,
            hold_initial_in_final_rounds: false,
            initial_prior_position_m: 0.3,
            initial_prior_rotation_deg: 3.0,
            max_initial_pose_change_m: 1.0,
            max_initial_pose_change_deg: 10.0,
            retry_holding_initial: true,
            restart_from_refined_pose: true,
            restart_first_run: false,
            restart_first_run_from_images: 48,
            restart_early_at_images: 16,
            fallback_search_m: 2.0,
            fallback_search_deg: 30.0,
            align_to_map: true,
            num_threads: 1,
            uncertainty_max_images: 300,
            uncertainty_cluster_m: 1.0,
        }
    }
}

impl BundleOptions {
    /// Whether a first run (the initial image held at first) in a database
    /// of `num_images` images is mapped again from where its image ended:
    /// `restart_first_run`, or a database of `restart_first_run_from_images`
    /// or more.
    pub fn restarts_first_run(&self, num_images: usize) -> bool {
        self.restart_first_run
            || (self.restart_first_run_from_images > 0
                && num_images >= self.restart_first_run_from_images)
    }

    pub fn validate(&self) -> Result<(), OptionsError> {
        check(
            self.local_max_iterations >= 1,
            "bundle.local_max_iterations",
            "must be >= 1",
        )?;
        check(
            self.global_max_iterations >= 1,
            "bundle.global_max_iterations",
            "must be >= 1",
        )?;
        check(
            self.probe_max_iterations >= 1,
            "bundle.probe_max_iterations",
            "must be >= 1",
        )?;
        check(
            self.global_every_images >= 1,
            "bundle.global_every_images",
            "must be >= 1",
        )?;
        non_negative("bundle.global_growth_ratio", self.global_growth_ratio)?;
        non_negative(
            "bundle.refine_intrinsics_min_change",
            self.refine_intrinsics_min_change,
        )?;
        positive("bundle.reprojection_loss_px", self.reprojection_loss_px)?;
        check(
            self.uncertainty_cluster_m == 0.0 || (1e-3..=1e6).contains(&self.uncertainty_cluster_m),
            "bundle.uncertainty_cluster_m",
            format!(
                "must be 0 (off) or in [0.001, 1e6] metres, got {}",
                show(self.uncertainty_cluster_m)
            ),
        )?;
        positive("bundle.function_tolerance", self.function_tolerance)?;
        non_negative(
            "bundle.initial_prior_position_m",
            self.initial_prior_position_m,
        )?;
        non_negative(
            "bundle.initial_prior_rotation_deg",
            self.initial_prior_rotation_deg,
        )?;
        non_negative(
            "bundle.max_initial_pose_change_m",
            self.max_initial_pose_change_m,
        )?;
        non_negative(
            "bundle.max_initial_pose_change_deg",
            self.max_initial_pose_change_deg,
        )?;
        check(
            (0.0..=crate::sfm::localise::MAX_RADIUS_M).contains(&self.fallback_search_m),
            "bundle.fallback_search_m",
            "must be in 0..=10 (metres; 0 disables)",
        )?;
        check(
            (0.0..=180.0).contains(&self.fallback_search_deg),
            "bundle.fallback_search_deg",
            "must be in 0..=180 (degrees)",
        )?;
        check(
            (1..=256).contains(&self.num_threads),
            "bundle.num_threads",
            "must be in 1..=256",
        )?;
        check(
            (1..=100).contains(&self.final_rounds),
            "bundle.final_rounds",
            "must be in 1..=100",
        )?;
        non_negative("bundle.prior_position_weight", self.prior_position_weight)?;
        check(
            (1..=10).contains(&self.local_passes),
            "bundle.local_passes",
            "must be in 1..=10",
        )?;
        positive("bundle.global_radius_m", self.global_radius_m)?;
        non_negative("bundle.prior_rotation_weight", self.prior_rotation_weight)?;
        non_negative("bundle.final_stop_change_m", self.final_stop_change_m)?;
        non_negative(
            "bundle.final_huber_above_move_m",
            self.final_huber_above_move_m,
        )
    }
}

/// Which bundle adjustments refine the cameras' focal length and distortion.
///
/// A focal length 3.5 % off (530 px for 512, k1 = 0 for -0.04) and held put
/// the seed-0 corridor 9 cm off; refined in the final rounds it ended at
/// 3.4 mm, focal 511.98 px. From COLMAP's guess without EXIF data (1.2 x the
/// larger side: 768 px, 50 % off) only refinement in every solve, local ones
/// included, reached the map (4.3 mm, focal 512.00 px); refined in the
/// periodic and final solves only, the run ended 2.7 m off and failed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum IntrinsicsRefinement {
    /// `all` for the cameras the database marks as uncalibrated
    /// (`prior_focal_length = 0`); the others are held unless one solve with
    /// them free, after the final rounds, moves their focal length by more
    /// than `refine_intrinsics_min_change` (then `final`).
    Auto,
    /// Never: the database's intrinsics are exact (a calibrated camera).
    Fixed,
    /// In the final rounds only.
    Final,
    /// In every solve, local ones included (as COLMAP's mapper does).
    All,
}

impl IntrinsicsRefinement {
    pub const NAMES: [&'static str; 4] = ["auto", "fixed", "final", "all"];

    pub fn name(self) -> &'static str {
        match self {
            Self::Auto => "auto",
            Self::Fixed => "fixed",
            Self::Final => "final",
            Self::All => "all",
        }
    }
}

impl std::str::FromStr for IntrinsicsRefinement {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "auto" => Ok(Self::Auto),
            "fixed" => Ok(Self::Fixed),
            "final" => Ok(Self::Final),
            "all" => Ok(Self::All),
            _ => Err(format!(
                "unknown intrinsics refinement '{s}' (expected one of: {})",
                Self::NAMES.join(", ")
            )),
        }
    }
}

impl Serialize for IntrinsicsRefinement {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.name())
    }
}

/// A value an options file gives as a name or as `true` / `false`.
#[derive(Deserialize)]
#[serde(untagged)]
enum FlagOrName {
    Flag(bool),
    Name(String),
}

impl<'de> Deserialize<'de> for IntrinsicsRefinement {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        match FlagOrName::deserialize(d)? {
            FlagOrName::Flag(true) => Ok(Self::Final),
            FlagOrName::Flag(false) => Ok(Self::Fixed),
            FlagOrName::Name(s) => s.parse().map_err(serde::de::Error::custom),
        }
    }
}

/// Whose principal point is refined with the rest of its intrinsics
/// (`[mapper.bundle] refine_principal_point`: "auto", "never", "always";
/// also `true` = always and `false` = never, as COLMAP's flag).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum PrincipalPointRefinement {
    /// The cameras whose focal length is a guess.
    Auto,
    /// None: every principal point stays where the database has it.
    Never,
    /// Every camera whose focal length and distortion a solve refines.
    Always,
}

impl<'de> Deserialize<'de> for PrincipalPointRefinement {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        match FlagOrName::deserialize(d)? {
            FlagOrName::Flag(true) => Ok(Self::Always),
            FlagOrName::Flag(false) => Ok(Self::Never),
            FlagOrName::Name(s) => match s.as_str() {
                "auto" => Ok(Self::Auto),
                "never" => Ok(Self::Never),
                "always" => Ok(Self::Always),
                _ => Err(serde::de::Error::custom(format!(
                    "unknown principal point refinement '{s}' (expected auto, never, always, true or false)"
                ))),
            },
        }
    }
}

/// How 3D points are tied to the map during BA.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum AssociationKind {
    /// No LiDAR terms: plain SfM with the gauge fixed by the first two images.
    None,
    /// Nearest map point within a shrinking radius, its tangent plane.
    Nearest,
    /// Short tracks: the map point seen at the feature (projection into the
    /// track's images); longer tracks: nearest.
    Projection,
}

/// Robust loss on the plane residuals of the final bundle adjustments.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum PlaneLoss {
    /// Quadratic within the scale, linear beyond: a far point still pulls
    /// with a constant force.
    Huber,
    /// Logarithmic: the pull of a point falls off beyond the scale (as
    /// scale^2 / distance), so points that do not lie on any surface (at
    /// occlusion boundaries) barely move the model.
    Cauchy,
}

/// LiDAR point-to-plane associations.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct AssociationOptions {
    /// Default: nearest.
    pub kind: AssociationKind,
    /// Search radius of a point that has not yet been in a global BA, metres. Default 1.5.
    pub max_radius_m: f64,
    /// The radius shrinks by this much per global BA the point took part in, metres. Default 0.2.
    pub radius_drop_m: f64,
    /// Smallest radius, metres; every point's radius in the final rounds after the first
    /// (there `max_plane_distance_m` above 0.1 m gates nothing). Default 0.1.
    pub min_radius_m: f64,
    /// Largest point-to-plane distance of an association, metres. Default 0.2.
    pub max_plane_distance_m: f64,
    /// Weight of a nearest-neighbour plane residual (pixel equivalents per
    /// metre: 1000 makes 1 mm count like 1 px). Default 1000.
    pub weight: f64,
    /// Weight of a projection plane residual (kind `projection`). Default 10.
    pub projection_weight: f64,
    /// Tracks with at most this many observations use projection
    /// associations (kind `projection`). Default 3.
    pub projection_max_track_len: usize,
    /// Weight of a ground plane (normal within `ground_max_tilt_deg` of
    /// vertical). Default 1000.
    pub ground_weight: f64,
    /// Default 5.7.
    pub ground_max_tilt_deg: f64,
    /// Huber scale on plane residuals, metres (times the weight in pixel
    /// equivalents). Default 0.02.
    pub loss_scale_m: f64,
    /// Weight of a plane residual in the final bundle adjustments. The
    /// strong weights above pull the model into the map's basin during
    /// registration; at the end they would bend the structure onto planes
    /// (measured: a 0.2-0.4 deg tilt of the whole model on the yard scene at
    /// 1000), so the final solves use a weight near the noise ratio
    /// (reprojection noise, about 0.3 px, over plane noise, 5-30 mm).
    /// Default 30: over three seeds of the 24-image yard, room and corridor
    /// (exact initial pose) the camera-centre median was at most 6.2 mm
    /// (mean 3.3) against 11.7 mm (mean 4.3) at 10 and 9.3 mm at 50.
    pub final_weight: f64,
    /// Weight of a ground plane in the final bundle adjustments. Default 30.
    pub final_ground_weight: f64,
    /// Scale of the robust loss on plane residuals in the final bundle
    /// adjustments (`final_loss`), metres. Default 0.01.
    pub final_loss_scale_m: f64,
    /// Robust loss of the final bundle adjustments' plane residuals (other
    /// solves use Huber). Default cauchy: a point the images place off every
    /// surface of the map (a feature on an occlusion boundary, about a tenth
    /// of the points on the synthetic scenes; an object moved since the
    /// scan) then hardly pulls the model, where under Huber each pulled
    /// with a constant force. Over the 24-image yard, room and corridor,
    /// three seeds, exact and perturbed initial pose (fresh databases of
    /// session 14), camera-centre medians: Huber 5 mm summed 32.7 mm (worst
    /// 4.1), Cauchy 10 mm 31.4 mm (worst 4.3): corridor 0 4.0 / 3.8 -> 3.3 /
    /// 3.1 mm, room 0 1.5 / 1.4 -> 1.2 / 1.2, yard 1 1.8 / 1.9 -> 2.2 / 2.2;
    /// Cauchy 5 mm 33.5 (the yards 0.1-1.1 mm worse), 2 mm worse still.
    pub final_loss: PlaneLoss,
    /// The first round of the final bundle adjustment uses a Huber loss at
    /// this scale, metres, instead of `final_loss`; 0: `final_loss` in every
    /// round. The model arrives from registration up to a few centimetres
    /// off, and from there a Cauchy solve took many more iterations. On the
    /// 200-image corridor (seed 0, sequential matching, session 15's
    /// database) the final stage took 63.9 s against 72.9 s with Cauchy in
    /// every round (1.3 mm median camera-centre error both); over the
    /// 24-image yard, room and corridor, three seeds, exact and perturbed,
    /// the medians summed 30.5 mm against 31.4 mm (each within 0.3 mm). On
    /// the 100-image corridor it gained no time and ended 2.3 mm off against
    /// 1.9 mm (2.1 mm with more rounds: the rounds end in slightly different
    /// places depending on where they start). Default 0.005.
    pub final_first_round_huber_m: f64,
    /// In the final bundle adjustments a plane is kept only when the point,
    /// moved to the best place on that plane, still reprojects within this
    /// RMS error over its observations, pixels (a point that cannot lie on
    /// the plane: a wrong association or a feature that is not on a surface,
    /// e.g. at an occlusion boundary). 0 turns the test off. Default 0:
    /// measured no better (24-image scenes, 1 px, final weight 10: room 3.8
    /// -> 3.7 mm, yard 5.0 -> 5.4, corridor 1.1 -> 1.8; weight 30, three
    /// seeds each: mean 3.29 -> 3.31 mm); with strong final weights (100) it
    /// removes most of their harm (room 3.9 -> 2.5 mm, corridor 7.9 -> 7.4,
    /// yard 2.4).
    pub final_max_on_plane_error_px: f64,
    /// Map points whose planarity is below this give no plane (a map with
    /// a planarity per point: one whose normals were estimated, by
    /// `prepare-map` or by `map` itself). Planarity is `(l2 - l3) / l1` of
    /// the neighbourhood's covariance: about 1 on a flat patch, lower where
    /// the fit straddles an edge and its normal is unreliable, but also at
    /// a surface's border (a half disc reads about 0.3) and on strips
    /// narrower than the normal radius, which give no plane either (a
    /// flatness without that, `1 - l3 / l2`, measured worse: 36.4 mm
    /// against 32.7 mm over the runs below from raw maps). A map that came
    /// with normals but no planarity is scored by `map` as it loads it (the
    /// fits `prepare-map` makes; the normals are kept as given; about 2 s
    /// per million points): map points near creases then give no plane
    /// either (see `docs/results.md`, session 80). Refitted neighbourhoods
    /// (`prepare-map`'s robust refit) are scored by their refit. 0 keeps
    /// all (and `map` scores nothing).
    /// Default 0.7: the 24-image yards, rooms and corridors (3 seeds, exact
    /// and perturbed, normals estimated with the robust refit) summed
    /// 34.1 mm of camera-centre medians without it, 30.9 mm with it (31.3
    /// at 0.8; true normals: 30.2), e.g. room 1 1.9 -> 1.0 mm; the seed-1
    /// yard on a 20 cm map without normals 11.3 -> 6.8 mm (true normals
    /// 6.8), on a 10 cm one 4.9 -> 5.1 mm (4.5).
    pub min_planarity: f64,
    /// Map points searched per association (the one whose tangent plane
    /// lies closest to the 3D point gives the normal). Default 10.
    pub num_neighbours: usize,
    /// Map points whose normals are within this angle share the plane (its
    /// offset is their mean), degrees. Default 15.
    pub same_plane_max_angle_deg: f64,
    /// A plane's offset is the mean over the map points on it within this
    /// distance of the plane's map point, measured along the surface,
    /// metres: the map's range noise shrinks by the square root of their
    /// number (about 80 at 2 cm spacing). A few times the map's spacing:
    /// raised to [`PLANE_RADIUS_PER_SPACING`] times it for sparser maps.
    /// Default 0.1.
    pub plane_radius_m: f64,
    /// ... and within this distance of the plane along its normal, metres
    /// (several sigmas of the map's noise; less than the depth of the
    /// smallest step between parallel surfaces). Raised to
    /// [`PLANE_WINDOW_PER_NOISE`] times the map's measured noise for noisier
    /// maps ([`MapperOptions::for_map_noise`]). Default 0.1.
    pub plane_window_m: f64,
    /// A plane's offset may come from a least-squares plane fitted over a
    /// patch of the map up to this radius (metres; patches of twice, four
    /// times ... the plane radius in turn, each taken while it agrees with
    /// the narrower one within the map's noise, and used where it is known
    /// better than the plane radius's mean and agrees with it): a flat wall
    /// or floor then averages
    /// thousands of map points instead of tens, a curved or stepped
    /// surface keeps its local plane ([`crate::map::surfels`]). 0 (or
    /// anything under twice the plane radius) turns it off. Default 0
    /// (off): 1.2 m took most of the synthetic yard's 15 mm noise out of
    /// its plane offsets (0.5 mm RMS from the truth where a fit was taken,
    /// 0.8 mm over all, instead of 3.3 mm) and the seed-0 yards closer
    /// to the truth (640 x 480: 3.9 -> 3.0 mm; 1024 x 768: 2.15 -> 1.57
    /// mm), but the corridors came out worse (their grazing-angle feature
    /// bias, which the noisier local offsets partly absorbed) and so did
    /// maps of 30-50 mm noise prepared by `prepare-map` (session 72,
    /// `docs/results.md`).
    pub plane_fit_max_radius_m: f64,
    /// A map point gives no plane when fewer map points than this (itself
    /// included) lie on its plane inside that cylinder and window, and
    /// inside one of twice the radius: a stray point (a LiDAR outlier:
    /// dust, a bird, a multipath return) whose normal, estimated or given
    /// with the map, is no surface's. A surface at the map's spacing has at
    /// least about 20 in the first (the radius is at least 2.5 spacings),
    /// half that at its border; the second keeps parts of the map up to
    /// about three times sparser than its spacing. 0 keeps all. Default 5:
    /// the synthetic maps carry 0.1 % outliers uniform in the scene's box
    /// with random normals, which moved the seed-3 24-image corridor
    /// 2.5 mm along the corridor (1.0 mm with 5). Over fifteen 24-image
    /// databases 5 is level in sum at 0.1 % (22.7 against 22.3 mm, exact
    /// pose; the seed-0 corridor 0.8 -> 3.2 mm, which its noise- and
    /// outlier-free map gives too, the 0.1 % having hidden a bias), and
    /// with 1 % outliers it keeps the corridors where they were (seeds 0-3
    /// summed 5.6 mm, against 11.0 mm with 0) where rooms do not care (4.8
    /// against 4.6 mm). Session 61, `docs/results.md`.
    pub min_plane_support: usize,
    /// The run fails (no output) when fewer of the final model's 3D points
    /// than this share lie within 2 cm of the map surface seen at their
    /// feature in one of their images: the model does not fit the map (an
    /// initial pose far off, a map of another place). 0 turns the check
    /// off. Default 0.6: right models of the synthetic scenes measured
    /// 0.78-0.97; the seed-7 yard mapped from an initial pose 2.2 m and
    /// 12 deg off, a model 439 times too small, 0.32 (with 0.997 within
    /// 2 cm of the nearest surface, the test this replaced); from poses
    /// 1.1-1.7 m and 8 deg off 0.35-0.39. Real maps with more noise, or places
    /// changed since the scan, may need less.
    pub min_points_on_map_share: f64,
}

impl Default for AssociationOptions {
    fn default() -> Self {
        Self {
            kind: AssociationKind::Nearest,
            max_radius_m: 1.5,
            radius_drop_m: 0.2,
            min_radius_m: 0.1,
            max_plane_distance_m: 0.2,
            weight: 1000.0,
            projection_weight: 10.0,
            projection_max_track_len: 3,
            ground_weight: 1000.0,
            ground_max_tilt_deg: 5.7,
            loss_scale_m: 0.02,
            final_weight: 30.0,
            final_ground_weight: 30.0,
            final_loss_scale_m: 0.01,
            final_loss: PlaneLoss::Cauchy,
            final_first_round_huber_m: 0.005,
            final_max_on_plane_error_px: 0.0,
            min_planarity: 0.7,
            num_neighbours: 10,
            same_plane_max_angle_deg: 15.0,
            plane_radius_m: 0.1,
            plane_window_m: 0.1,
            plane_fit_max_radius_m: 0.0,
            min_plane_support: 5,
            min_points_on_map_share: 0.6,
        }
    }
}

/// Weights and robust-loss scale of the plane terms of one solve.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlaneWeights {
    pub projection_weight: f64,
    pub weight: f64,
    pub ground_weight: f64,
    pub loss_scale_m: f64,
    pub loss: PlaneLoss,
}

impl PlaneWeights {
    /// The robust loss of a plane residual of `weight` (pixel equivalents
    /// per metre): its scale is `loss_scale_m` in pixel equivalents.
    pub fn loss(&self, weight: f64) -> crate::solver::LossFunction {
        let scale = (weight * self.loss_scale_m).max(1e-6);
        match self.loss {
            PlaneLoss::Huber => crate::solver::LossFunction::Huber { scale },
            PlaneLoss::Cauchy => crate::solver::LossFunction::Cauchy { scale },
        }
    }
}

impl AssociationOptions {
    /// The weights of a solve of `kind`.
    pub fn weights(&self, kind: crate::sfm::associate::SolveKind) -> PlaneWeights {
        use crate::sfm::associate::SolveKind;
        match kind {
            SolveKind::Final => PlaneWeights {
                projection_weight: self.final_weight,
                weight: self.final_weight,
                ground_weight: self.final_ground_weight,
                loss_scale_m: self.final_loss_scale_m,
                loss: self.final_loss,
            },
            SolveKind::FinalFirst if self.final_first_round_huber_m > 0.0 => PlaneWeights {
                loss_scale_m: self.final_first_round_huber_m,
                loss: PlaneLoss::Huber,
                ..self.weights(SolveKind::Final)
            },
            SolveKind::FinalFirst => self.weights(SolveKind::Final),
            SolveKind::FinalMoving => PlaneWeights {
                loss: PlaneLoss::Huber,
                ..self.weights(SolveKind::Final)
            },
            SolveKind::Local | SolveKind::LocalRefine | SolveKind::Global => PlaneWeights {
                projection_weight: self.projection_weight,
                weight: self.weight,
                ground_weight: self.ground_weight,
                loss_scale_m: self.loss_scale_m,
                loss: PlaneLoss::Huber,
            },
        }
    }

    pub fn validate(&self) -> Result<(), OptionsError> {
        positive("association.max_radius_m", self.max_radius_m)?;
        non_negative("association.radius_drop_m", self.radius_drop_m)?;
        check(
            self.min_radius_m > 0.0 && self.min_radius_m <= self.max_radius_m,
            "association.min_radius_m",
            "need 0 < min_radius_m <= max_radius_m",
        )?;
        positive(
            "association.max_plane_distance_m",
            self.max_plane_distance_m,
        )?;
        non_negative("association.weight", self.weight)?;
        non_negative("association.projection_weight", self.projection_weight)?;
        non_negative("association.ground_weight", self.ground_weight)?;
        check(
            (0.0..90.0).contains(&self.ground_max_tilt_deg),
            "association.ground_max_tilt_deg",
            "must be in [0, 90)",
        )?;
        positive("association.loss_scale_m", self.loss_scale_m)?;
        non_negative("association.final_weight", self.final_weight)?;
        non_negative("association.final_ground_weight", self.final_ground_weight)?;
        positive("association.final_loss_scale_m", self.final_loss_scale_m)?;
        non_negative(
            "association.final_first_round_huber_m",
            self.final_first_round_huber_m,
        )?;
        check(
            (0.0..=1.0).contains(&self.min_planarity),
            "association.min_planarity",
            "must be in [0, 1]",
        )?;
        non_negative(
            "association.final_max_on_plane_error_px",
            self.final_max_on_plane_error_px,
        )?;
        check(
            (1..=256).contains(&self.num_neighbours),
            "association.num_neighbours",
            "must be in 1..=256",
        )?;
        check(
            (0.0..=90.0).contains(&self.same_plane_max_angle_deg),
            "association.same_plane_max_angle_deg",
            "must be in [0, 90]",
        )?;
        for (name, v) in [
            ("association.plane_radius_m", self.plane_radius_m),
            ("association.plane_window_m", self.plane_window_m),
        ] {
            check(
                v > 0.0 && v <= MAX_PLANE_RADIUS_M,
                name,
                format!("must be in (0, {MAX_PLANE_RADIUS_M}] metres (a plane's neighbourhood), got {v}"),
            )?;
        }
        check(
            self.plane_fit_max_radius_m >= 0.0 && self.plane_fit_max_radius_m <= MAX_PLANE_RADIUS_M,
            "association.plane_fit_max_radius_m",
            format!(
                "must be in [0, {MAX_PLANE_RADIUS_M}] metres, got {}",
                self.plane_fit_max_radius_m
            ),
        )?;
        check(
            (0.0..=1.0).contains(&self.min_points_on_map_share),
            "association.min_points_on_map_share",
            "must be in [0, 1]",
        )
    }
}

/// Outlier filtering after each BA.
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct FilterOptions {
    /// Observations with a larger reprojection error are removed, pixels. Default 4.
    pub max_reprojection_error_px: f64,
    /// Points whose largest triangulation angle is smaller are removed
    /// (points held by the map are kept), degrees. Default 1.5.
    pub min_triangulation_angle_deg: f64,
    /// Before the final bundle adjustments (with LiDAR constraints), delete
    /// the points that in at least half of their views lie behind the
    /// surface the map shows at their feature, by more than
    /// `max(behind_map_margin_m, behind_map_margin_ratio * range)`: features
    /// on occlusion boundaries triangulated behind a wall. Default true.
    pub remove_behind_map: bool,
    /// Metres. Default 0.05 (the map's noise and the points' depth noise at
    /// a few metres stay well inside).
    pub behind_map_margin_m: f64,
    /// Share of the point's range from the camera. Default 0.02 (a far
    /// point's depth is less certain).
    pub behind_map_margin_ratio: f64,
}

impl Default for FilterOptions {
    fn default() -> Self {
        Self {
            max_reprojection_error_px: 4.0,
            min_triangulation_angle_deg: 1.5,
            remove_behind_map: true,
            behind_map_margin_m: 0.05,
            behind_map_margin_ratio: 0.02,
        }
    }
}

impl FilterOptions {
    pub fn validate(&self) -> Result<(), OptionsError> {
        positive(
            "filter.max_reprojection_error_px",
            self.max_reprojection_error_px,
        )?;
        non_negative(
            "filter.min_triangulation_angle_deg",
            self.min_triangulation_angle_deg,
        )?;
        non_negative("filter.behind_map_margin_m", self.behind_map_margin_m)?;
        non_negative(
            "filter.behind_map_margin_ratio",
            self.behind_map_margin_ratio,
        )
    }
}

/// Photometric refinement of the tracked keypoints on the map's planes
/// ([`crate::sfm::keypoints`]), after the final rounds, when the images are
/// given (`map --image-path`).
#[derive(Clone, Debug, PartialEq, Deserialize, Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct KeypointOptions {
    /// Refine the keypoints and run the final rounds again. Default true
    /// (only with the images).
    pub refine: bool,
    /// Half the side of the square patch aligned, pixels of the reference
    /// image. Default 7 (15 x 15 pixels; 5 gave 0.69 / 0.76 mm against 0.55
    /// / 0.91 mm on two 24-image scenes).
    pub patch_half_px: u32,
    /// A refined position is kept only where the aligned patches' normalised
    /// cross-correlation reaches this. Default 0.8.
    pub min_ncc: f64,
    /// ... and where it lies at most this far from the keypoint, pixels.
    /// Default 1.5.
    pub max_shift_px: f64,
    /// The registered images are read as grey values (a byte a pixel) for
    /// the refinement and dropped after it; when they would take more than
    /// this many megabytes the keypoints are not refined (with a warning).
    /// Default 8192 (about 700 12-megapixel photos).
    pub max_image_memory_mb: f64,
}

impl Default for KeypointOptions {
    fn default() -> Self {
        Self {
            refine: true,
            patch_half_px: 7,
            min_ncc: 0.8,
            max_shift_px: 1.5,
            max_image_memory_mb: 8192.0,
        }
    }
}

impl KeypointOptions {
    pub fn validate(&self) -> Result<(), OptionsError> {
        check(
            (1..=32).contains(&self.patch_half_px),
            "keypoints.patch_half_px",
            format!("must be 1-32, got {}", self.patch_half_px),
        )?;
        check(
            self.min_ncc.is_finite() && self.min_ncc <= 1.0,
            "keypoints.min_ncc",
            format!("must be at most 1, got {}", show(self.min_ncc)),
        )?;
        positive("keypoints.max_shift_px", self.max_shift_px)?;
        positive("keypoints.max_image_memory_mb", self.max_image_memory_mb)
    }
}

/// Everything the mapper needs, one struct per stage.
#[derive(Clone, Debug, PartialEq, Default, Deserialize, Serialize)]
#[serde(default, deny_unknown_fields)]
pub struct MapperOptions {
    /// Seed of every random choice. Default 0.
    pub seed: u64,
    pub init: InitOptions,
    pub register: RegisterOptions,
    pub triangulate: TriangulateOptions,
    pub bundle: BundleOptions,
    pub association: AssociationOptions,
    pub filter: FilterOptions,
    pub keypoints: KeypointOptions,
}

/// Plane-offset radius per map spacing (see [`MapperOptions::for_map_spacing`]).
pub const PLANE_RADIUS_PER_SPACING: f64 = 2.5;

/// Steep surfaces sampled more sparsely than this many times the map's
/// spacing widen the smallest association radius
/// ([`MapperOptions::for_steep_spacing`]); an airborne scan's walls at 0.15
/// of its ground's density read about 2.2 times its spacing.
pub const SPARSE_STEEP_PER_SPACING: f64 = 1.5;

/// Plane window per unit of the map's noise ([`MapperOptions::for_map_noise`]).
pub const PLANE_WINDOW_PER_NOISE: f64 = 3.0;

impl MapperOptions {
    /// The options for a map whose surface samples lie about `spacing_m`
    /// apart ([`crate::map::index::MapIndex::surface_spacing_m`]): the splat
    /// half-width, far and near ([`crate::map::projection::widen_splats_for_spacing`]), is at
    /// least [`crate::map::projection::SPLAT_PER_SPACING`] and the plane-offset
    /// radius at least [`PLANE_RADIUS_PER_SPACING`] times the spacing. The
    /// defaults suit maps of 2-5 cm (the reference's advice: 3-5 cm voxels);
    /// on a sparser map the cameras would see through its surfaces between
    /// the splats and its planes would average a handful of points. The
    /// seed-1 yard on a 10 cm map (database of the 5.4 cm one): with the
    /// defaults 3 % of the points fitted the map and the run failed.
    pub fn for_map_spacing(&self, spacing_m: f64) -> MapperOptions {
        let mut adapted = self.clone();
        if spacing_m.is_finite() && spacing_m > 0.0 {
            let init = &mut adapted.init;
            let mut splat = init.projection().splat;
            widen_splats_for_spacing(&mut splat, spacing_m);
            init.splat_half_width_m = splat.patch_half_width_m;
            init.splat_near_half_width_m = splat.near_half_width_m;
            let assoc = &mut adapted.association;
            assoc.plane_radius_m = assoc
                .plane_radius_m
                .max(PLANE_RADIUS_PER_SPACING * spacing_m);
        }
        adapted
    }

    /// The options for a map whose steep surfaces (walls) are sampled about
    /// `steep_spacing_m` apart ([`crate::map::index::MapIndex::steep_spacing_m`])
    /// where the whole map's spacing is `spacing_m`: when the walls are
    /// sparser than [`SPARSE_STEEP_PER_SPACING`] times the map (an airborne
    /// scan), the smallest association radius is at least their spacing.
    /// A 3D point on a wall otherwise finds no wall sample within the final
    /// rounds' 0.1 m, only the roof's or the ground's at its edges, whose
    /// planes stretch the model vertically: the 24-image aerial scene
    /// (seed 0) in an airborne scan of 10 cm (walls at 0.15 of the ground's
    /// density, 3 cm noise, `prepare-map`) came out 7.7 mm off at a scale
    /// of 1.0002 with 0.1 m, 1.6 mm with 0.25 m (the same scan without
    /// noise: 5.2 and 2.2 mm; one with walls as dense as the ground: 2.5
    /// mm); at 20 cm 11.4 mm against 5.2 mm with 0.45 m. A terrestrial
    /// map's walls are as dense as its floors, and its radius stays. The
    /// same radius finds the planes of the fit checks' "near a surface"
    /// counts and of the behind-the-map filter, which on such a map would
    /// otherwise miss the walls as well.
    pub fn for_steep_spacing(&self, spacing_m: f64, steep_spacing_m: f64) -> MapperOptions {
        let mut adapted = self.clone();
        if spacing_m > 0.0 && steep_spacing_m > SPARSE_STEEP_PER_SPACING * spacing_m {
            let assoc = &mut adapted.association;
            assoc.min_radius_m = assoc.min_radius_m.max(steep_spacing_m);
            assoc.max_radius_m = assoc.max_radius_m.max(assoc.min_radius_m);
        }
        adapted
    }

    /// The options for a map whose range noise along its normals is about
    /// `noise_m` ([`crate::sfm::associate::NearestNeighbourAssociator::plane_noise_m`]):
    /// the plane window reaches at least [`PLANE_WINDOW_PER_NOISE`] times
    /// the noise either side of a plane. A narrower window cuts the noise's
    /// tails on one side and pulls each plane's offset toward its own map
    /// point: on maps of 50 mm noise prepared by `prepare-map`, the 24-image
    /// rooms' and corridors' models fitted 50-56 % of their points and
    /// failed the fit check with the default 0.1 m. Maps of up to 33 mm
    /// keep the default: a window of 4 times the noise (0.12 m at 30 mm)
    /// left those four scenes' models 0.1-0.9 mm further off, true normals
    /// or estimated, though they fit a little better (the offsets no longer
    /// follow the points).
    ///
    /// The plane radius does not follow the noise: averaging about 150 map
    /// points instead of 30-80 (radii of 0.22-0.25 m for 50 mm; tried with
    /// the window at 4 times the noise) moved those models by up to 1.5 mm
    /// either way, summing to about the same (20.8 against 19.7 mm over
    /// eight runs).
    pub fn for_map_noise(&self, noise_m: f64) -> MapperOptions {
        let mut adapted = self.clone();
        if noise_m.is_finite() && noise_m > 0.0 {
            let assoc = &mut adapted.association;
            assoc.plane_window_m = assoc
                .plane_window_m
                .max((PLANE_WINDOW_PER_NOISE * noise_m).min(MAX_PLANE_RADIUS_M));
        }
        adapted
    }

    pub fn validate(&self) -> Result<(), OptionsError> {
        self.init.validate()?;
        self.register.validate()?;
        self.triangulate.validate()?;
        self.bundle.validate()?;
        self.association.validate()?;
        self.filter.validate()?;
        self.keypoints.validate()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Walls sparser than 1.5 times the map's spacing raise the smallest
    /// association radius to their spacing; walls as dense as the map, or
    /// no spacing known, change nothing.
    #[test]
    fn the_smallest_radius_follows_sparse_walls() {
        let o = MapperOptions::default();
        let airborne = o.for_steep_spacing(0.108, 0.252);
        assert_eq!(airborne.association.min_radius_m, 0.252);
        assert_eq!(
            airborne.association.max_radius_m,
            o.association.max_radius_m
        );
        airborne.validate().unwrap();
        for (spacing, steep) in [(0.108, 0.16), (0.057, 0.057), (0.0, 0.3), (0.2, 0.0)] {
            assert_eq!(o.for_steep_spacing(spacing, steep), o, "{spacing} {steep}");
        }
        let very_sparse = o.for_steep_spacing(0.5, 2.0);
        assert_eq!(very_sparse.association.max_radius_m, 2.0);
        very_sparse.validate().unwrap();
    }

    /// 50 mm of noise: a window of 0.15 m; 33 mm and less, no noise or a
    /// NaN change nothing; a map of 10 m noise stays within the bound.
    #[test]
    fn the_plane_window_follows_the_noise() {
        let o = MapperOptions::default();
        let noisy = o.for_map_noise(0.05);
        assert!((noisy.association.plane_window_m - 0.15).abs() < 1e-12);
        assert_eq!(
            noisy.association.plane_radius_m,
            o.association.plane_radius_m
        );
        noisy.validate().unwrap();
        for noise in [0.015, 0.03, 0.033, 0.0, -1.0, f64::NAN] {
            assert_eq!(o.for_map_noise(noise), o, "{noise}");
        }
        let wild = o.for_map_noise(10.0);
        assert_eq!(wild.association.plane_window_m, MAX_PLANE_RADIUS_M);
        wild.validate().unwrap();
    }

    #[test]
    fn defaults_validate_and_toml_overrides() {
        MapperOptions::default().validate().unwrap();
        let o: MapperOptions = toml::from_str(
            "seed = 3\n[register]\nmax_error_px = 2.5\n[association]\nkind = \"none\"\n",
        )
        .unwrap();
        assert_eq!(o.seed, 3);
        assert_eq!(o.register.max_error_px, 2.5);
        assert_eq!(o.register.min_num_inliers, 30);
        assert_eq!(o.association.kind, AssociationKind::None);
        assert!(toml::from_str::<MapperOptions>("[register]\nmax_eror_px = 2.5\n").is_err());
        let mut bad = MapperOptions::default();
        bad.filter.max_reprojection_error_px = -1.0;
        let err = bad.validate().unwrap_err().to_string();
        assert!(err.contains("filter.max_reprojection_error_px"), "{err}");
        let mut bad = MapperOptions::default();
        bad.bundle.probe_max_iterations = 0;
        let err = bad.validate().unwrap_err().to_string();
        assert!(err.contains("bundle.probe_max_iterations"), "{err}");
        let o: MapperOptions = toml::from_str("[association]\nmin_planarity = 0.5\n").unwrap();
        assert_eq!(o.association.min_planarity, 0.5);
        let mut bad = MapperOptions::default();
        bad.association.min_planarity = 1.5;
        let err = bad.validate().unwrap_err().to_string();
        assert!(err.contains("association.min_planarity"), "{err}");
        // Values that passed before and then hung a run, made every cost
        // NaN or made a sigma meaningless (session 64's review).
        type Spoil = fn(&mut MapperOptions);
        let spoilt: [(Spoil, &str); 8] = [
            (
                |o| o.register.max_iterations = 1_000_000_000_000_000,
                "register.max_iterations",
            ),
            (
                |o| o.association.plane_radius_m = 100.0,
                "association.plane_radius_m",
            ),
            (
                |o| o.association.plane_fit_max_radius_m = 100.0,
                "association.plane_fit_max_radius_m",
            ),
            (
                |o| o.association.plane_fit_max_radius_m = f64::NAN,
                "association.plane_fit_max_radius_m",
            ),
            (|o| o.bundle.reprojection_loss_px = 1e200, "got 1e200"),
            (|o| o.bundle.uncertainty_cluster_m = 1e-300, "got 1e-300"),
            (
                |o| o.bundle.initial_prior_position_m = 1e-320,
                "bundle.initial_prior_position_m",
            ),
            (
                |o| o.filter.max_reprojection_error_px = f64::INFINITY,
                "got inf",
            ),
        ];
        for (spoil, says) in spoilt {
            let mut bad = MapperOptions::default();
            spoil(&mut bad);
            let err = bad.validate().unwrap_err().to_string();
            assert!(err.contains(says), "{says}: {err}");
        }
        // 0 still turns these off; ordinary values still pass.
        let mut off = MapperOptions::default();
        off.bundle.uncertainty_cluster_m = 0.0;
        off.bundle.initial_prior_position_m = 0.0;
        off.association.plane_radius_m = 0.3;
        off.validate().unwrap();
        assert_eq!(show(0.3), "0.3");
        assert_eq!(show(1e-300), "1e-300");
    }

    #[test]
    fn principal_point_refinement_reads_names_and_colmaps_flag() {
        let read = |value: &str| {
            toml::from_str::<MapperOptions>(&format!(
                "[bundle]\nrefine_principal_point = {value}\n"
            ))
            .map(|o| o.bundle.refine_principal_point)
        };
        use PrincipalPointRefinement as P;
        assert_eq!(
            MapperOptions::default().bundle.refine_principal_point,
            P::Auto
        );
        assert_eq!(read("\"auto\"").unwrap(), P::Auto);
        assert_eq!(read("\"never\"").unwrap(), P::Never);
        assert_eq!(read("\"always\"").unwrap(), P::Always);
        assert_eq!(read("true").unwrap(), P::Always);
        assert_eq!(read("false").unwrap(), P::Never);
        let err = read("\"sometimes\"").unwrap_err().to_string();
        assert!(err.contains("'sometimes'") && err.contains("auto"), "{err}");
        // Written as it is read (report.json's options).
        let text = toml::to_string(&MapperOptions::default().bundle).unwrap();
        assert!(text.contains("refine_principal_point = \"auto\""), "{text}");
    }

    #[test]
    fn splats_and_plane_radii_follow_the_maps_spacing() {
        // An options file's floors, raised by a 10 cm map, kept by a 1 cm one.
        let o: MapperOptions =
            toml::from_str("[init]\nsplat_half_width_m = 0.03\nsplat_near_half_width_m = 0.02\n")
                .unwrap();
        let sparse = o.for_map_spacing(0.1);
        assert!((sparse.init.splat_half_width_m - 0.06).abs() < 1e-12);
        assert!((sparse.init.splat_near_half_width_m - 0.06).abs() < 1e-12);
        assert!((sparse.association.plane_radius_m - 0.25).abs() < 1e-12);
        let splat = sparse.init.projection().splat;
        assert_eq!(splat.near_half_width_m, sparse.init.splat_near_half_width_m);
        let dense = o.for_map_spacing(0.01);
        assert_eq!(dense.init.splat_half_width_m, 0.03);
        assert_eq!(dense.init.splat_near_half_width_m, 0.02);
        assert_eq!(dense.association.plane_radius_m, 0.1);
        // No spacing: the options as given.
        assert_eq!(o.for_map_spacing(f64::NAN), o);
        let mut bad = MapperOptions::default();
        bad.init.splat_near_half_width_m = -0.01;
        assert!(bad.validate().is_err());
    }

    #[test]
    fn final_plane_losses_are_read_and_used_only_in_final_solves() {
        use crate::sfm::associate::SolveKind;
        use crate::solver::LossFunction;
        let o = AssociationOptions::default();
        // Final: Cauchy at weight 30 times 10 mm = 0.3 pixel equivalents.
        let fin = o.weights(SolveKind::Final);
        assert_eq!(fin.loss(fin.weight), LossFunction::Cauchy { scale: 0.3 });
        // Registration: Huber at weight 1000 times 2 cm.
        let local = o.weights(SolveKind::Local);
        assert_eq!(
            local.loss(local.weight),
            LossFunction::Huber { scale: 20.0 }
        );
        assert_eq!(o.weights(SolveKind::Global).loss, PlaneLoss::Huber);
        // First final round: the final weights, Huber at 30 times 5 mm.
        let first = o.weights(SolveKind::FinalFirst);
        assert_eq!(first.weight, 30.0);
        assert_eq!(
            first.loss(first.weight),
            LossFunction::Huber { scale: 0.15 }
        );
        // A round while the model still moves: the final weights, Huber at
        // the final scale (30 times 10 mm).
        let moving = o.weights(SolveKind::FinalMoving);
        assert_eq!(moving.weight, 30.0);
        assert_eq!(moving.ground_weight, 30.0);
        assert_eq!(
            moving.loss(moving.weight),
            LossFunction::Huber { scale: 0.3 }
        );
        assert_eq!(
            MapperOptions::default().bundle.final_huber_above_move_m,
            0.01
        );
        let mut bad = MapperOptions::default();
        bad.bundle.final_huber_above_move_m = -1.0;
        let err = bad.validate().unwrap_err().to_string();
        assert!(err.contains("final_huber_above_move_m"), "{err}");
        let off: MapperOptions =
            toml::from_str("[association]\nfinal_first_round_huber_m = 0.0\n").unwrap();
        assert_eq!(
            off.association.weights(SolveKind::FinalFirst),
            off.association.weights(SolveKind::Final)
        );
        let mut bad = MapperOptions::default();
        bad.association.final_first_round_huber_m = -0.001;
        let err = bad.validate().unwrap_err().to_string();
        assert!(err.contains("final_first_round_huber_m"), "{err}");
        let read: MapperOptions =
            toml::from_str("[association]\nfinal_loss = \"huber\"\nfinal_loss_scale_m = 0.005\n")
                .unwrap();
        let fin = read.association.weights(SolveKind::Final);
        assert_eq!(fin.loss(30.0), LossFunction::Huber { scale: 0.15 });
        assert!(
            toml::from_str::<MapperOptions>("[association]\nfinal_loss = \"tukey\"\n").is_err()
        );
    }

    #[test]
    fn intrinsics_refinement_reads_names_and_the_old_flag() {
        let read = |v: &str| -> Result<IntrinsicsRefinement, String> {
            toml::from_str::<MapperOptions>(&format!("[bundle]\nrefine_intrinsics = {v}\n"))
                .map(|o| o.bundle.refine_intrinsics)
                .map_err(|e| e.to_string())
        };
        assert_eq!(
            MapperOptions::default().bundle.refine_intrinsics,
            IntrinsicsRefinement::Auto
        );
        for name in IntrinsicsRefinement::NAMES {
            let mode = read(&format!("\"{name}\"")).unwrap();
            assert_eq!(mode.name(), name);
            assert_eq!(name.parse::<IntrinsicsRefinement>(), Ok(mode));
        }
        // The old boolean: true meant the final rounds, false never.
        assert_eq!(read("true"), Ok(IntrinsicsRefinement::Final));
        assert_eq!(read("false"), Ok(IntrinsicsRefinement::Fixed));
        let err = read("\"always\"").unwrap_err();
        assert!(
            err.contains("'always'") && err.contains("auto, fixed, final, all"),
            "{err}"
        );
        assert!(read("3").is_err());
    }

    #[test]
    fn options_round_trip_through_json_and_toml() {
        // report.json records the options; reading them back gives the same
        // options, non-default values included, and so does TOML.
        let mut options = MapperOptions::default().for_map_spacing(0.1);
        options.seed = 7;
        options.bundle.refine_intrinsics = IntrinsicsRefinement::Final;
        options.association.kind = AssociationKind::Projection;
        options.association.min_planarity = 0.55;
        options.association.final_loss = PlaneLoss::Huber;
        assert_ne!(options, MapperOptions::default());
        for o in [MapperOptions::default(), options] {
            let json = serde_json::to_string(&o).unwrap();
            assert_eq!(serde_json::from_str::<MapperOptions>(&json).unwrap(), o);
            let toml_text = toml::to_string(&o).unwrap();
            assert_eq!(toml::from_str::<MapperOptions>(&toml_text).unwrap(), o);
        }
        let json = serde_json::to_value(MapperOptions::default()).unwrap();
        assert_eq!(json["bundle"]["refine_intrinsics"], "auto");
        assert_eq!(json["association"]["kind"], "nearest");
    }
}
