//! Initialisation from the map (method.md 4.4). The initial image gets the
//! user's pose; its features that see the map get 3D points by intersecting
//! their viewing rays with the tangent planes of the LiDAR points they see,
//! **in the world frame** (right for any initial pose); a second image is
//! registered by PnP against those points, trying candidates in order of how
//! many of its verified matches with the initial image have such a point. The
//! PnP inliers become the first 3D points.
use std::collections::{BTreeMap, BTreeSet};

use nalgebra::{Matrix3, Vector2, Vector3};
use rand_chacha::ChaCha8Rng;

use super::associate::NearestNeighbourAssociator;
use super::focal::{sweep_focal, with_focal};
use super::geometry::intersect_ray_plane;
use super::options::{InitOptions, RegisterOptions, TriangulateOptions};
use super::register::{estimate_pose, focal_from_correspondences, pnp_score, PoseOutcome};
use super::state::MapState;
use crate::estimators::triangulation::{triangulate_point, PointObservation, TriangulationOptions};
use crate::map::grid::FrustumGrid;
use crate::map::projection::{project_map_at_pixels, ProjectionError};
use crate::scene::{Camera, CameraId, ImageId, Rigid3, TrackElement};

/// One second-image candidate that was tried.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct InitAttempt {
    pub image_id: u32,
    pub image_name: String,
    /// Verified matches with the initial image whose feature has a LiDAR
    /// point (all its verified matches in a start from a pair,
    /// [`initialize_from_pair`]).
    pub num_lidar_matches: usize,
    /// PnP inliers (0 when PnP did not run or found nothing); in a start
    /// from a pair, the points the pair triangulates.
    pub num_inliers: usize,
}

/// Why initialisation failed.
#[derive(Debug, thiserror::Error)]
pub enum InitError {
    #[error(transparent)]
    Projection(#[from] ProjectionError),
    #[error(
        "the initial image `{name}` (id {id}) sees no usable map point at its pose: \
         {num_hits} of its {num_features} features hit the map, {num_supported} got a 3D point \
         from a tangent plane (need {needed}). Is the initial pose in the map frame, \
         in metres and degrees (x,y,z,roll,pitch,yaw), and does the map cover the view?"
    )]
    NoMapSupport {
        name: String,
        id: ImageId,
        num_features: usize,
        num_hits: usize,
        num_supported: usize,
        needed: usize,
    },
    #[error(
        "no second image could be registered against the {num_supported} LiDAR-supported \
         features of the initial image `{name}` (id {id}); tried: {}",
        describe(.attempts, "matches with LiDAR points", "PnP inliers")
    )]
    NoSecondImage {
        name: String,
        id: ImageId,
        num_supported: usize,
        attempts: Vec<InitAttempt>,
    },
    #[error(
        "the initial image `{name}` (id {id}) sees almost none of the map from the rough pose: \
         {num_hits} of its {num_features} features hit the map (need {needed} to set the scale \
         of the run without the map's planes). Is the rough pose in the map frame, in metres \
         and degrees (x,y,z,roll,pitch,yaw), and does the map cover the view?"
    )]
    NoScale {
        name: String,
        id: ImageId,
        num_features: usize,
        num_hits: usize,
        needed: usize,
    },
    #[error(
        "no image makes a pair with the initial image `{name}` (id {id}) that triangulates \
         {needed} points from their essential matrix; tried: {}",
        describe(.attempts, "verified matches", "points")
    )]
    NoPair {
        name: String,
        id: ImageId,
        needed: usize,
        attempts: Vec<InitAttempt>,
    },
}

/// The attempts for an error message; `matches` and `inliers` name what
/// `num_lidar_matches` and `num_inliers` count.
fn describe(attempts: &[InitAttempt], matches: &str, inliers: &str) -> String {
    if attempts.is_empty() {
        return "no image shares verified matches with it".to_owned();
    }
    attempts
        .iter()
        .map(|a| {
            format!(
                "`{}` (id {}): {} {matches}, {} {inliers}",
                a.image_name, a.image_id, a.num_lidar_matches, a.num_inliers
            )
        })
        .collect::<Vec<_>>()
        .join("; ")
}

/// What initialisation did.
#[derive(Clone, Debug, serde::Serialize)]
pub struct InitSummary {
    pub initial_image: u32,
    pub second_image: u32,
    pub num_features: usize,
    pub num_map_hits: usize,
    pub num_supported: usize,
    pub num_points: usize,
    pub attempts: Vec<InitAttempt>,
    /// Guessed cameras of second-image candidates (by the id owning their
    /// intrinsics): the focal length at which PnP placed the candidate best
    /// against the initial image's map points, where its self-calibration
    /// started (pixels; see [`focal_from_correspondences`]).
    pub focal_from_points_px: BTreeMap<u32, f64>,
    /// Started from the pair's essential matrix ([`initialize_from_pair`]):
    /// the metres per unit of the pair's baseline that the map's depths at
    /// the rough pose gave (`num_supported` of the pair's points had one).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pair_scale: Option<f64>,
}

/// 3D points of the initial image's features from the map: keypoint index ->
/// point in the world frame. Returns (points, number of features that hit the map).
pub fn lidar_points_of_image(
    state: &MapState,
    image: ImageId,
    cam_from_world: &Rigid3,
    map: &NearestNeighbourAssociator,
    grid: &FrustumGrid,
    options: &InitOptions,
) -> Result<(BTreeMap<u32, Vector3<f64>>, usize), ProjectionError> {
    lidar_points_with_camera(
        state.camera_of(image),
        &state.images[&image].keypoints,
        cam_from_world,
        map,
        grid,
        options,
    )
}

/// [`lidar_points_of_image`] for the keypoints of an image seen through
/// `camera` (which need not be the image's own: the focal-length sweep tries
/// several).
fn lidar_points_with_camera(
    camera: &Camera,
    keypoints: &[Vector2<f64>],
    cam_from_world: &Rigid3,
    map: &NearestNeighbourAssociator,
    grid: &FrustumGrid,
    options: &InitOptions,
) -> Result<(BTreeMap<u32, Vector3<f64>>, usize), ProjectionError> {
    let projection = options.projection();
    let hits = project_map_at_pixels(
        map.cloud,
        grid,
        camera,
        cam_from_world,
        keypoints,
        &projection,
    )?;
    let world_from_cam = cam_from_world.inverse();
    let centre = cam_from_world.camera_center();
    let focal_px = camera.mean_focal_length();
    let min_cos = options.min_ray_plane_angle_deg.to_radians().sin();
    let mut out = BTreeMap::new();
    let mut num_hits = 0;
    for (k, hit) in hits.iter().enumerate() {
        let Some(hit) = hit else { continue };
        num_hits += 1;
        let Some(normal) = hit.normal_in_map.and_then(|n| n.try_normalize(1e-9)) else {
            continue;
        };
        let Some(ray_in_cam) = camera.unproject(&keypoints[k]) else {
            continue;
        };
        let dir = world_from_cam.rotation * ray_in_cam;
        // The plane of the map's surface there, not through the hit itself:
        // the nearest of the splats at a pixel is one that the map's noise
        // moved toward the camera (see `plane_offset_at`).
        let Some(offset) = map.plane_offset_at(hit.point_idx as usize) else {
            continue;
        };
        // A feature inside the LiDAR point's splat lies within the splat's
        // half-diagonal of the point (in the plane through it); farther
        // means the ray hit another surface (depth edges): its plane is the
        // wrong one.
        let through_hit = normal.dot(&hit.point_in_map);
        let Some(on_hit_plane) = intersect_ray_plane(&centre, &dir, &normal, through_hit, min_cos)
        else {
            continue;
        };
        let splat_m = projection.splat.half_size_px(hit.depth_m, focal_px) * hit.depth_m / focal_px
            * std::f64::consts::SQRT_2;
        if (on_hit_plane - hit.point_in_map).norm() > splat_m.min(options.max_plane_extrapolation_m)
        {
            continue;
        }
        let Some(x) = intersect_ray_plane(&centre, &dir, &normal, offset, min_cos) else {
            continue;
        };
        out.insert(k as u32, x);
    }
    Ok((out, num_hits))
}

/// The verified matches `(keypoint of image, keypoint of other)` of
/// `image`'s keypoints `keys` with each other image that `keep` accepts,
/// most matches first (ties by id).
fn matches_per_image(
    state: &MapState,
    image: ImageId,
    keys: impl Iterator<Item = u32>,
    keep: impl Fn(ImageId) -> bool,
) -> Vec<(ImageId, Vec<(u32, u32)>)> {
    let mut per_image: BTreeMap<ImageId, Vec<(u32, u32)>> = BTreeMap::new();
    for k in keys {
        for c in state.graph.correspondences(image, k) {
            if c.image_id != image && keep(c.image_id) {
                per_image
                    .entry(c.image_id)
                    .or_default()
                    .push((k, c.point2d_idx));
            }
        }
    }
    let mut out: Vec<(ImageId, Vec<(u32, u32)>)> = per_image.into_iter().collect();
    out.sort_by(|a, b| b.1.len().cmp(&a.1.len()).then(a.0.cmp(&b.0)));
    out
}

/// What the map says about the focal length of the initial image's camera.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct MapFocalEstimate {
    pub focal_px: f64,
    /// Second images scored (placed by PnP at some focal lengths, maybe not
    /// at all).
    pub num_images: usize,
    /// Mean truncated squared reprojection error (0: every correspondence
    /// exact, 1: none within the truncation) at the estimate and at the
    /// sweep's centre (the database's guess).
    pub score: f64,
    pub score_at_guess: f64,
}

/// How well the map explains the initial pair at focal length `f` (given to
/// every camera whose intrinsics are in `swept`): the
/// initial image's features are cut with the map's planes at the given pose
/// seen through `f`, each candidate is registered against those points by
/// PnP with `f`, and the score is the mean over candidates of the mean
/// truncated squared reprojection error `min(e^2, t^2) / t^2` over all its
/// LiDAR matches (1 for a candidate PnP does not place). At a wrong `f` the
/// points land in the wrong places on the map and no pose of the candidate
/// reprojects them onto its features.
#[allow(clippy::too_many_arguments)]
fn focal_score(
    state: &MapState,
    image: ImageId,
    candidates: &[(ImageId, Vec<(u32, u32)>)],
    f: f64,
    cam_from_world: &Rigid3,
    map: &NearestNeighbourAssociator,
    grid: &FrustumGrid,
    options: &InitOptions,
    register: &RegisterOptions,
    seed: u64,
    swept: &BTreeSet<CameraId>,
) -> f64 {
    let with_f = |c: &Camera| -> Camera {
        if swept.contains(&state.intrinsics_of(c.id)) {
            with_focal(c, f)
        } else {
            c.clone()
        }
    };
    let camera = with_f(state.camera_of(image));
    let Ok((lidar, _)) = lidar_points_with_camera(
        &camera,
        &state.images[&image].keypoints,
        cam_from_world,
        map,
        grid,
        options,
    ) else {
        return 1.0;
    };
    let mut total = 0.0;
    for (other, matches) in candidates {
        let keypoints = &state.images[other].keypoints;
        let (pixels, points): (Vec<Vector2<f64>>, Vec<Vector3<f64>>) = matches
            .iter()
            .filter_map(|(k1, k2)| Some((keypoints[*k2 as usize], *lidar.get(k1)?)))
            .unzip();
        total += pnp_score(
            &with_f(state.camera_of(*other)),
            &pixels,
            &points,
            register,
            seed,
        );
    }
    total / candidates.len().max(1) as f64
}

/// The intrinsics (owners) whose focal length the sweep at `image` sets:
/// the image's own, and every guessed one (in `guessed`) of the same model
/// and image size, which is taken to be the same kind of camera with the
/// same unknown focal length (COLMAP guesses 1.2 x the larger side for all
/// of them; with `share_identical_intrinsics` off each image has its own).
pub fn swept_cameras(
    state: &MapState,
    image: ImageId,
    guessed: &BTreeSet<CameraId>,
) -> BTreeSet<CameraId> {
    let owner = state.intrinsics_of(state.images[&image].camera_id);
    let first = &state.cameras[&owner];
    state
        .cameras
        .values()
        .map(|c| state.intrinsics_of(c.id))
        .filter(|&id| {
            let c = &state.cameras[&id];
            id == owner
                || (guessed.contains(&id)
                    && c.model == first.model
                    && (c.width, c.height) == (first.width, first.height))
        })
        .collect()
}

/// How [`focal_from_map`] searches.
#[derive(Clone, Copy, Debug)]
pub struct InitialPairFocalSweep<'a> {
    /// The grid spans a third to three times this focal length, pixels.
    pub centre_px: f64,
    /// Second images scored: those with most verified matches with the
    /// initial image.
    pub num_candidates: usize,
    /// Cameras whose focal length is a guess: one of another model or image
    /// size than the initial image's is no candidate (its own focal length
    /// is as unknown); the others take the swept focal length too
    /// ([`swept_cameras`]).
    pub guessed: &'a BTreeSet<CameraId>,
    /// Seed of every PnP's RANSAC.
    pub seed: u64,
}

/// The focal length of the initial image's camera that makes the map and
/// the initial pair agree best: the initial image's features cut with the
/// map's planes through each focal length, the candidates placed by PnP
/// against them, scored by their truncated reprojection error; searched by
/// [`sweep_focal`] (a log grid over a third to three times
/// `sweep.centre_px` in 8 % steps, then 1 % steps around the best). `None`
/// when there is no candidate, no candidate could be placed at any focal
/// length, or the best lies on the edge of the grid.
#[allow(clippy::too_many_arguments)]
pub fn focal_from_map(
    state: &MapState,
    image: ImageId,
    cam_from_world: &Rigid3,
    map: &NearestNeighbourAssociator,
    grid: &FrustumGrid,
    options: &InitOptions,
    register: &RegisterOptions,
    sweep: &InitialPairFocalSweep,
) -> Option<MapFocalEstimate> {
    state.images.get(&image)?;
    let swept = swept_cameras(state, image, sweep.guessed);
    let usable = |other: ImageId| {
        let of = state.intrinsics_of(state.images[&other].camera_id);
        swept.contains(&of) || !sweep.guessed.contains(&of)
    };
    // The candidates' matches with every feature of the initial image; which
    // of them have a map point depends on the focal length.
    let mut candidates = matches_per_image(
        state,
        image,
        0..state.images[&image].keypoints.len() as u32,
        usable,
    );
    candidates.truncate(sweep.num_candidates);
    if candidates.is_empty() {
        return None;
    }
    let score = |f: f64| {
        focal_score(
            state,
            image,
            &candidates,
            f,
            cam_from_world,
            map,
            grid,
            options,
            register,
            sweep.seed,
            &swept,
        )
    };
    let (focal_px, best) = sweep_focal(sweep.centre_px, &score)?;
    Some(MapFocalEstimate {
        focal_px,
        num_images: candidates.len(),
        score: best,
        score_at_guess: score(sweep.centre_px),
    })
}

/// Registers the initial image at `cam_from_world` and a second image by PnP
/// against its LiDAR-supported features; creates the first 3D points. A
/// candidate whose camera's intrinsics are owned by one in `sweep` (a
/// guessed focal length the map's sweep did not set) gets its focal length
/// from a sweep of that PnP first (every PnP's RANSAC seeded with `seed`).
#[allow(clippy::too_many_arguments)]
pub fn initialize(
    state: &mut MapState,
    image: ImageId,
    cam_from_world: &Rigid3,
    map: &NearestNeighbourAssociator,
    grid: &FrustumGrid,
    options: &InitOptions,
    register: &RegisterOptions,
    sweep: &BTreeSet<CameraId>,
    seed: u64,
    rng: &mut ChaCha8Rng,
) -> Result<InitSummary, InitError> {
    let (lidar, num_hits) =
        lidar_points_of_image(state, image, cam_from_world, map, grid, options)?;
    let name = state.images[&image].name.clone();
    let num_features = state.images[&image].keypoints.len();
    if lidar.len() < options.min_lidar_features {
        return Err(InitError::NoMapSupport {
            name,
            id: image,
            num_features,
            num_hits,
            num_supported: lidar.len(),
            needed: options.min_lidar_features,
        });
    }
    // Candidates: matches of LiDAR-supported features per other image.
    let candidates = matches_per_image(state, image, lidar.keys().copied(), |_| true);
    let mut attempts = Vec::new();
    let mut focal_sweeps = BTreeMap::new();
    for (other, pairs) in candidates.into_iter().take(options.max_candidates) {
        let img = &state.images[&other];
        let pixels: Vec<_> = pairs
            .iter()
            .map(|(_, k2)| img.keypoints[*k2 as usize])
            .collect();
        let points: Vec<_> = pairs.iter().map(|(k1, _)| lidar[k1]).collect();
        let mut attempt = InitAttempt {
            image_id: other.0,
            image_name: img.name.clone(),
            num_lidar_matches: pairs.len(),
            num_inliers: 0,
        };
        let owner = state.intrinsics_of(img.camera_id);
        if sweep.contains(&owner) && !focal_sweeps.contains_key(&owner.0) {
            let camera = state.camera_of(other);
            let guess = camera.mean_focal_length();
            if let Some((f, score, at_guess)) =
                focal_from_correspondences(camera, &pixels, &points, register, seed)
            {
                log::info!(
                    "camera {}: `{}` is placed best on the initial image's map points at a focal length of {f:.1} px (was {guess:.1} px; score {score:.4} there, {at_guess:.4} before)",
                    owner.0,
                    attempt.image_name
                );
                state.set_focal_length(owner, f);
                focal_sweeps.insert(owner.0, f);
            }
        }
        let camera = state.camera_of(other).clone();
        let outcome = estimate_pose(&camera, &pixels, &points, None, register, rng);
        match outcome {
            PoseOutcome::Found {
                cam_from_world: pose2,
                inliers,
            } => {
                attempt.num_inliers = inliers.len();
                attempts.push(attempt);
                state.register(image, *cam_from_world);
                state.register(other, pose2);
                for i in &inliers {
                    let (k1, k2) = pairs[*i];
                    let id = state.add_point(
                        lidar[&k1],
                        vec![
                            TrackElement {
                                image_id: image,
                                point2d_idx: k1,
                            },
                            TrackElement {
                                image_id: other,
                                point2d_idx: k2,
                            },
                        ],
                    );
                    if let Some(p) = state.points.get_mut(&id) {
                        p.anchored = true;
                    }
                }
                return Ok(InitSummary {
                    initial_image: image.0,
                    second_image: other.0,
                    num_features,
                    num_map_hits: num_hits,
                    num_supported: lidar.len(),
                    num_points: state.points.len(),
                    attempts,
                    focal_from_points_px: focal_sweeps,
                    pair_scale: None,
                });
            }
            PoseOutcome::TooFewInliers { inliers, .. } => {
                attempt.num_inliers = inliers;
                log::info!(
                    "initialisation: `{}` failed ({} LiDAR matches, {} inliers)",
                    attempt.image_name,
                    attempt.num_lidar_matches,
                    inliers
                );
                attempts.push(attempt);
            }
            PoseOutcome::TooFewCorrespondences { .. } => {
                log::info!(
                    "initialisation: `{}` has only {} LiDAR matches",
                    attempt.image_name,
                    attempt.num_lidar_matches
                );
                attempts.push(attempt);
            }
        }
    }
    Err(InitError::NoSecondImage {
        name,
        id: image,
        num_supported: lidar.len(),
        attempts,
    })
}

/// Fewest points the initial pair must triangulate (in front of both
/// cameras, within the reprojection and angle limits) to start a run from
/// its essential matrix.
pub const MIN_PAIR_POINTS: usize = 50;

/// Fewest map hits at the initial image's features that set the scale of a
/// run started from a pair.
const MIN_SCALE_HITS: usize = 10;

/// Each verified pair's (fundamental, essential) matrix as the database has
/// them (row-major), keyed by (smaller image id, larger image id).
pub type PairMatrices = BTreeMap<(ImageId, ImageId), (Option<[f64; 9]>, Option<[f64; 9]>)>;

/// A pair's triangulated points: (keypoint in the initial image, keypoint in
/// the other, point in the initial camera's frame).
type PairPoints = Vec<(u32, u32, Vector3<f64>)>;

/// The four relative poses `cam2_from_cam1 = (R, t)` (`|t| = 1`) an
/// essential matrix `E = [t]x R` (`x2^T E x1 = 0`) allows: two rotations,
/// each with `t` and `-t`. `None` when `E` is not finite or of rank below 2.
pub fn poses_from_essential(e: &Matrix3<f64>) -> Option<[Rigid3; 4]> {
    if !e.iter().all(|v| v.is_finite()) {
        return None;
    }
    let svd = e.try_svd(true, true, f64::EPSILON, 1000)?;
    // nalgebra does not sort the singular values: the null direction is the
    // smallest one's.
    let order = {
        let mut o = [0usize, 1, 2];
        o.sort_by(|&a, &b| svd.singular_values[b].total_cmp(&svd.singular_values[a]));
        o
    };
    let (u0, v0) = (svd.u?, svd.v_t?.transpose());
    if !(svd.singular_values[order[1]] > 1e-9 * svd.singular_values[order[0]]) {
        return None;
    }
    let pick = |m: &Matrix3<f64>| {
        Matrix3::from_columns(&[m.column(order[0]), m.column(order[1]), m.column(order[2])])
    };
    let (mut u, mut v) = (pick(&u0), pick(&v0));
    if u.determinant() < 0.0 {
        u = -u;
    }
    if v.determinant() < 0.0 {
        v = -v;
    }
    let w = Matrix3::new(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0);
    let (r1, r2) = (u * w * v.transpose(), u * w.transpose() * v.transpose());
    let t: Vector3<f64> = u.column(2).into();
    Some([
        Rigid3::from_rotation_matrix(&r1, t),
        Rigid3::from_rotation_matrix(&r1, -t),
        Rigid3::from_rotation_matrix(&r2, t),
        Rigid3::from_rotation_matrix(&r2, -t),
    ])
}

/// The essential matrix relating `image` to `other` (`x_other^T E x_image =
/// 0`, normalised coordinates) from the pair's verified geometry: COLMAP's
/// `E` for a calibrated pair, else `K_other^T F K_image` with the cameras'
/// current intrinsics (distortion ignored: the run's solves refine it).
/// `geometries` holds the database's rows keyed by (smaller id, larger id).
pub fn essential_of_pair(
    state: &MapState,
    geometries: &PairMatrices,
    image: ImageId,
    other: ImageId,
) -> Option<Matrix3<f64>> {
    let (a, b) = (image.min(other), image.max(other));
    let &(fundamental, essential) = geometries.get(&(a, b))?;
    let e_ab = match (essential, fundamental) {
        (Some(e), _) => Matrix3::from_row_slice(&e),
        (None, Some(f)) => {
            let k = |id: ImageId| {
                let camera = state.camera_of(id);
                let c = camera.principal_point();
                let f = camera.mean_focal_length();
                Matrix3::new(f, 0.0, c.x, 0.0, f, c.y, 0.0, 0.0, 1.0)
            };
            k(b).transpose() * Matrix3::from_row_slice(&f) * k(a)
        }
        (None, None) => return None,
    };
    Some(if image == a { e_ab } else { e_ab.transpose() })
}

/// The initial pair's points from one relative pose: (keypoint in image,
/// keypoint in other, point in the initial camera's frame) for each match
/// that triangulates in front of both cameras within the limits.
fn triangulate_pair(
    image_camera: &Camera,
    other_camera: &Camera,
    image_keys: &[Vector2<f64>],
    other_keys: &[Vector2<f64>],
    pairs: &[(u32, u32)],
    other_from_image: &Rigid3,
    options: &TriangulationOptions,
) -> PairPoints {
    pairs
        .iter()
        .filter_map(|&(k1, k2)| {
            let o1 =
                PointObservation::new(image_camera, Rigid3::identity(), image_keys[k1 as usize])?;
            let o2 =
                PointObservation::new(other_camera, *other_from_image, other_keys[k2 as usize])?;
            triangulate_point(&[o1, o2], options)
                .ok()
                .map(|p| (k1, k2, p.point_in_world))
        })
        .collect()
}

/// Registers the initial image at its rough `cam_from_world` and a second
/// image from their essential matrix, for a run that does not use the map's
/// planes ([`super::runs::run_mapper_searching`]): the map need not be
/// seen from a rough pose, which may even lie outside the mapped space. The
/// candidate with the most triangulated points is taken (of the
/// `max_candidates` with the most verified matches); the pair's scale is the
/// median over its points of the map's depth at their features seen from
/// the rough pose over their triangulated depth (the map's median depth over
/// the points' median depth where too few features see the map), which the
/// search's scale range then corrects; `given_scale` instead when given.
#[allow(clippy::too_many_arguments)]
pub fn initialize_from_pair(
    state: &mut MapState,
    image: ImageId,
    cam_from_world: &Rigid3,
    geometries: &PairMatrices,
    map: &NearestNeighbourAssociator,
    grid: &FrustumGrid,
    options: &InitOptions,
    triangulate: &TriangulateOptions,
    given_scale: Option<f64>,
) -> Result<InitSummary, InitError> {
    let name = state.images[&image].name.clone();
    let keypoints = state.images[&image].keypoints.clone();
    let num_features = keypoints.len();
    let hits = project_map_at_pixels(
        map.cloud,
        grid,
        state.camera_of(image),
        cam_from_world,
        &keypoints,
        &options.projection(),
    )?;
    let depth_at: Vec<Option<f64>> = hits.iter().map(|h| h.as_ref().map(|h| h.depth_m)).collect();
    let num_hits = depth_at.iter().flatten().count();
    let tri = TriangulationOptions {
        max_reprojection_error_px: triangulate.max_error_px,
        min_angle_deg: triangulate.min_angle_deg,
        ..Default::default()
    };
    let candidates = matches_per_image(state, image, 0..num_features as u32, |_| true);
    let mut attempts = Vec::new();
    let mut best: Option<(ImageId, Rigid3, PairPoints)> = None;
    for (other, pairs) in candidates.into_iter().take(options.max_candidates) {
        let mut attempt = InitAttempt {
            image_id: other.0,
            image_name: state.images[&other].name.clone(),
            num_lidar_matches: pairs.len(),
            num_inliers: 0,
        };
        if let Some(poses) = essential_of_pair(state, geometries, image, other)
            .and_then(|e| poses_from_essential(&e))
        {
            let (camera1, camera2) = (state.camera_of(image), state.camera_of(other));
            let other_keys = &state.images[&other].keypoints;
            let (pose, points) = poses
                .iter()
                .map(|p| {
                    (
                        *p,
                        triangulate_pair(camera1, camera2, &keypoints, other_keys, &pairs, p, &tri),
                    )
                })
                .max_by_key(|(_, pts)| pts.len())
                .expect("four poses");
            attempt.num_inliers = points.len();
            if points.len() >= MIN_PAIR_POINTS
                && best.as_ref().is_none_or(|b| points.len() > b.2.len())
            {
                best = Some((other, pose, points));
            }
        }
        log::info!(
            "initialisation from a pair: `{}`, {} verified matches, {} triangulated",
            attempt.image_name,
            attempt.num_lidar_matches,
            attempt.num_inliers
        );
        attempts.push(attempt);
    }
    let Some((other, other_from_image, points)) = best else {
        return Err(InitError::NoPair {
            name,
            id: image,
            needed: MIN_PAIR_POINTS,
            attempts,
        });
    };
    let median = |mut v: Vec<f64>| -> Option<f64> {
        (!v.is_empty()).then(|| {
            v.sort_by(f64::total_cmp);
            v[v.len() / 2]
        })
    };
    let ratios: Vec<f64> = points
        .iter()
        .filter_map(|(k1, _, p)| depth_at[*k1 as usize].map(|d| d / p.z))
        .collect();
    let num_supported = ratios.len();
    let scale = if let Some(given) = given_scale {
        Some(given)
    } else if ratios.len() >= MIN_SCALE_HITS {
        median(ratios)
    } else if num_hits >= MIN_SCALE_HITS {
        let map_depth = median(depth_at.iter().flatten().copied().collect());
        let own_depth = median(points.iter().map(|(_, _, p)| p.z).collect());
        map_depth.zip(own_depth).map(|(m, o)| m / o)
    } else {
        None
    };
    let Some(scale) = scale.filter(|s| s.is_finite() && *s > 0.0) else {
        return Err(InitError::NoScale {
            name,
            id: image,
            num_features,
            num_hits,
            needed: MIN_SCALE_HITS,
        });
    };
    let world_from_cam = cam_from_world.inverse();
    let other_from_image = Rigid3::new(
        other_from_image.rotation,
        other_from_image.translation * scale,
    );
    state.register(image, *cam_from_world);
    state.register(other, other_from_image.compose(cam_from_world));
    for (k1, k2, p) in &points {
        state.add_point(
            world_from_cam.transform_point(&(p * scale)),
            vec![
                TrackElement {
                    image_id: image,
                    point2d_idx: *k1,
                },
                TrackElement {
                    image_id: other,
                    point2d_idx: *k2,
                },
            ],
        );
    }
    Ok(InitSummary {
        initial_image: image.0,
        second_image: other.0,
        num_features,
        num_map_hits: num_hits,
        num_supported,
        num_points: state.points.len(),
        attempts,
        focal_from_points_px: BTreeMap::new(),
        pair_scale: Some(scale),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::database::{DatabaseSnapshot, DbImage};
    use crate::map::grid::GridOptions;
    use crate::map::index::MapIndex;
    use crate::scene::CameraId;
    use crate::sfm::associate::plane_offset_tests::noisy_floor;
    use crate::sfm::associate::tests::test_camera;
    use crate::sfm::options::AssociationOptions;
    use nalgebra::{Matrix3, Vector2};

    #[test]
    fn initial_points_lie_on_the_maps_surface_not_on_the_nearest_splat() {
        // A camera 2 m above the noisy floor (15 mm noise, georeferenced),
        // looking straight down, with features on a grid of pixels.
        let (cloud, _) = noisy_floor();
        let index = MapIndex::build(&cloud).unwrap();
        let grid = FrustumGrid::build(&cloud, &GridOptions::default()).unwrap();
        let map = NearestNeighbourAssociator::new(&cloud, &index, AssociationOptions::default());
        let mut db = DatabaseSnapshot::default();
        db.cameras.insert(CameraId(1), test_camera());
        let id = ImageId(1);
        db.images.insert(
            id,
            DbImage {
                id,
                name: "down.png".into(),
                camera_id: CameraId(1),
            },
        );
        let pixels: Vec<Vector2<f64>> = (0..30)
            .flat_map(|i| {
                (0..40).map(move |j| Vector2::new(10.0 + 16.0 * j as f64, 5.0 + 16.0 * i as f64))
            })
            .collect();
        db.keypoints.insert(id, pixels);
        let state = MapState::new(&db, 1);
        let down = Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, -1.0));
        let centre = cloud.origin + Vector3::new(0.1, -0.2, 2.0);
        let pose = Rigid3::from_rotation_matrix(&down, -(down * centre));
        let (points, hits) =
            lidar_points_of_image(&state, id, &pose, &map, &grid, &InitOptions::default()).unwrap();
        assert_eq!(hits, 1200);
        assert!(
            points.len() > 1000,
            "{} of 1200 features got a point",
            points.len()
        );
        // The floor is z = 200 (the map's own noise averages out): the nearest
        // splat at a pixel sits about a sigma above it.
        let mean_z = points.values().map(|p| p.z - 200.0).sum::<f64>() / points.len() as f64;
        assert!(
            mean_z.abs() < 0.001,
            "initial points {mean_z} m off the floor"
        );
    }

    #[test]
    fn an_essential_matrix_gives_back_its_pose_among_four() {
        for (k, (axis, angle, t)) in [
            (
                Vector3::new(0.1, 1.0, 0.2),
                0.3,
                Vector3::new(-1.0, 0.1, 0.05),
            ),
            (
                Vector3::new(1.0, 0.0, 0.0),
                -0.05,
                Vector3::new(0.0, 0.0, 2.0),
            ),
            (
                Vector3::new(0.3, -0.2, 1.0),
                2.5,
                Vector3::new(0.4, -3.0, 1.0),
            ),
        ]
        .into_iter()
        .enumerate()
        {
            let r =
                nalgebra::Rotation3::from_axis_angle(&nalgebra::Unit::new_normalize(axis), angle);
            // Any scale and sign of E.
            let e = t.cross_matrix() * r.matrix() * (-0.7 * (k as f64 + 1.0));
            let poses = poses_from_essential(&e).expect("rank 2");
            let unit = t.normalize();
            let found = poses.iter().filter(|p| {
                (p.rotation_matrix() - r.matrix()).norm() < 1e-9
                    && (p.translation - unit).norm() < 1e-9
            });
            assert_eq!(found.count(), 1, "pose {k}: {poses:?}");
            for p in &poses {
                // Each of the four satisfies E's epipolar constraint up to scale.
                let ep = p.translation.cross_matrix() * p.rotation_matrix();
                let (a, b) = (ep.normalize(), e.normalize());
                assert!((a - b).norm().min((a + b).norm()) < 1e-9, "pose {k}");
            }
        }
        assert!(poses_from_essential(&Matrix3::zeros()).is_none());
        assert!(poses_from_essential(&(Vector3::x() * Vector3::y().transpose())).is_none());
    }

    #[test]
    fn a_pairs_essential_matrix_comes_from_its_fundamental_either_way_round() {
        let mut db = DatabaseSnapshot::default();
        db.cameras.insert(CameraId(1), test_camera());
        for id in [1, 2] {
            db.images.insert(
                ImageId(id),
                DbImage {
                    id: ImageId(id),
                    name: format!("{id}.png"),
                    camera_id: CameraId(1),
                },
            );
            db.keypoints.insert(ImageId(id), Vec::new());
        }
        let state = MapState::new(&db, 1);
        // cam2_from_cam1 and the pixel-space F of the pair (1, 2).
        let r = nalgebra::Rotation3::from_euler_angles(0.05, -0.2, 0.1);
        let t = Vector3::new(0.8, -0.1, 0.3);
        let e12 = t.cross_matrix() * r.matrix();
        let k = Matrix3::new(500.0, 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0);
        let k_inv = k.try_inverse().unwrap();
        let f = k_inv.transpose() * e12 * k_inv * 3.0;
        let row_major = |m: &Matrix3<f64>| {
            let mut out = [0.0; 9];
            for i in 0..3 {
                for j in 0..3 {
                    out[3 * i + j] = m[(i, j)];
                }
            }
            out
        };
        let same = |a: &Matrix3<f64>, b: &Matrix3<f64>| {
            let (a, b) = (a.normalize(), b.normalize());
            (a - b).norm().min((a + b).norm()) < 1e-9
        };
        let from_f = BTreeMap::from([((ImageId(1), ImageId(2)), (Some(row_major(&f)), None))]);
        let e = essential_of_pair(&state, &from_f, ImageId(1), ImageId(2)).unwrap();
        assert!(same(&e, &e12), "{e}");
        let e = essential_of_pair(&state, &from_f, ImageId(2), ImageId(1)).unwrap();
        assert!(same(&e, &e12.transpose()), "{e}");
        // The database's E wins over F.
        let both = BTreeMap::from([(
            (ImageId(1), ImageId(2)),
            (Some(row_major(&Matrix3::identity())), Some(row_major(&e12))),
        )]);
        let e = essential_of_pair(&state, &both, ImageId(2), ImageId(1)).unwrap();
        assert!(same(&e, &e12.transpose()), "{e}");
        assert!(essential_of_pair(&state, &BTreeMap::new(), ImageId(1), ImageId(2)).is_none());
    }
}
