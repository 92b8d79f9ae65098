//! Initialisation from the map (method.md 4.4). The initial image gets the
//! user's pose; its features that see the map get 3D points by intersecting
//! their viewing rays with the tangent planes of the LiDAR points they see,
//! **in the world frame** (right for any initial pose); a second image is
//! registered by PnP against those points, trying candidates in order of how
//! many of its verified matches with the initial image have such a point. The
//! PnP inliers become the first 3D points.
use std::collections::{BTreeMap, BTreeSet};

use nalgebra::{Vector2, Vector3};
use rand_chacha::ChaCha8Rng;

use super::associate::NearestNeighbourAssociator;
use super::focal::{sweep_focal, with_focal};
use super::geometry::intersect_ray_plane;
use super::options::{InitOptions, RegisterOptions};
use super::register::{estimate_pose, focal_from_correspondences, pnp_score, PoseOutcome};
use super::state::MapState;
use crate::map::grid::FrustumGrid;
use crate::map::projection::{project_map_at_pixels, ProjectionError};
use crate::scene::{Camera, CameraId, ImageId, Rigid3, TrackElement};

/// One second-image candidate that was tried.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct InitAttempt {
    pub image_id: u32,
    pub image_name: String,
    /// Verified matches with the initial image whose feature has a LiDAR point.
    pub num_lidar_matches: usize,
    /// PnP inliers (0 when PnP did not run or found nothing).
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
        describe(.attempts)
    )]
    NoSecondImage {
        name: String,
        id: ImageId,
        num_supported: usize,
        attempts: Vec<InitAttempt>,
    },
}

fn describe(attempts: &[InitAttempt]) -> String {
    if attempts.is_empty() {
        return "no image shares verified matches with it".to_owned();
    }
    attempts
        .iter()
        .map(|a| {
            format!(
                "`{}` (id {}): {} matches with LiDAR points, {} PnP inliers",
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
}
