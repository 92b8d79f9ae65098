//! Registration of the next image (method.md 4.5): next-best-view choice,
//! P3P inside LO-RANSAC with a seeded RNG, non-linear refinement, inlier checks.
use std::collections::BTreeMap;

use nalgebra::{Vector2, Vector3};
use rand::seq::index::sample;
use rand_chacha::ChaCha8Rng;

use super::focal::{sweep_focal, truncated_reprojection_score, with_focal};
use super::geometry::{refine_pose, reprojection_error_sq};
use super::options::RegisterOptions;
use super::state::MapState;
use crate::estimators::p3p::p3p;
use crate::scene::{Camera, ImageId, Point3DId, Rigid3, TrackElement};

/// What an absolute-pose estimate gave.
#[derive(Clone, Debug, PartialEq)]
pub enum PoseOutcome {
    /// Pose found; `inliers` indexes the correspondences.
    Found {
        cam_from_world: Rigid3,
        inliers: Vec<usize>,
    },
    /// Fewer 2D-3D correspondences than the minimum number of inliers.
    TooFewCorrespondences { found: usize, needed: usize },
    /// The best model had too few inliers (or too small a ratio).
    TooFewInliers {
        inliers: usize,
        correspondences: usize,
    },
}

/// Robust absolute pose: P3P in LO-RANSAC (local optimisation: the refined
/// pose of the inliers of every new best model), then refinement on the final
/// inliers and a last inlier count. `guess` (a known pose of the image, e.g.
/// a pose prior) gives the first hypotheses: the guess itself and the guess
/// refined (robustly) on the correspondences within 3 and 10 times the
/// threshold of it, scored and locally optimised like sampled ones; the best
/// sets the number of iterations RANSAC still needs, and RANSAC's samples
/// replace it only with more inliers. `rng` makes the run reproducible.
pub fn estimate_pose(
    camera: &Camera,
    pixels: &[Vector2<f64>],
    points_in_world: &[Vector3<f64>],
    guess: Option<&Rigid3>,
    options: &RegisterOptions,
    rng: &mut ChaCha8Rng,
) -> PoseOutcome {
    let n = pixels.len();
    if n < options.min_num_inliers.max(4) {
        return PoseOutcome::TooFewCorrespondences {
            found: n,
            needed: options.min_num_inliers.max(4),
        };
    }
    let bearings: Vec<Option<Vector3<f64>>> = pixels
        .iter()
        .map(|x| camera.unproject(x).map(|v| v.normalize()))
        .collect();
    let thr_sq = options.max_error_px * options.max_error_px;
    // Correspondences reprojecting within sqrt(max_sq) pixels of `pose`.
    let within = |pose: &Rigid3, max_sq: f64| -> Vec<usize> {
        (0..n)
            .filter(|&i| {
                reprojection_error_sq(camera, pose, &points_in_world[i], &pixels[i])
                    .is_some_and(|e| e < max_sq)
            })
            .collect()
    };
    let inliers_of = |pose: &Rigid3| within(pose, thr_sq);
    let refine_on = |pose: &Rigid3, idx: &[usize], iterations: usize| -> Rigid3 {
        let px: Vec<Vector2<f64>> = idx.iter().map(|&i| pixels[i]).collect();
        let pw: Vec<Vector3<f64>> = idx.iter().map(|&i| points_in_world[i]).collect();
        refine_pose(camera, pose, &px, &pw, options.refine_huber_px, iterations)
    };
    let mut best: Option<(Rigid3, Vec<usize>)> = None;
    let mut needed = options.max_iterations;
    // Scores a hypothesis; a new best is locally optimised and sets the
    // iterations still needed for `options.confidence`.
    let consider = |pose: Rigid3, best: &mut Option<(Rigid3, Vec<usize>)>, needed: &mut usize| {
        let inl = inliers_of(&pose);
        if best.as_ref().is_some_and(|(_, b)| inl.len() <= b.len()) || inl.len() < 4 {
            return;
        }
        let refined = refine_on(&pose, &inl, 10);
        let inl_refined = inliers_of(&refined);
        let (pose, inl) = if inl_refined.len() >= inl.len() {
            (refined, inl_refined)
        } else {
            (pose, inl)
        };
        let ratio = inl.len() as f64 / n as f64;
        let p_fail = 1.0 - ratio.powi(3);
        *needed = if p_fail <= 1e-12 {
            0
        } else {
            ((1.0 - options.confidence).ln() / p_fail.ln()).ceil() as usize
        };
        *best = Some((pose, inl));
    };
    if let Some(guess) = guess {
        // A guess a little off (a prior 0.5 deg off moves pixels by more
        // than the threshold) is first refined on the correspondences within
        // wider thresholds.
        consider(*guess, &mut best, &mut needed);
        for widen in [3.0f64, 10.0] {
            let near = within(guess, thr_sq * widen * widen);
            if near.len() >= 6 {
                consider(refine_on(guess, &near, 20), &mut best, &mut needed);
            }
        }
    }
    let mut it = 0;
    while it < options.max_iterations && (it < options.min_iterations || it < needed) {
        it += 1;
        let s = sample(rng, n, 3);
        let idx = [s.index(0), s.index(1), s.index(2)];
        let (Some(b0), Some(b1), Some(b2)) = (bearings[idx[0]], bearings[idx[1]], bearings[idx[2]])
        else {
            continue;
        };
        let pts = [
            points_in_world[idx[0]],
            points_in_world[idx[1]],
            points_in_world[idx[2]],
        ];
        for pose in p3p(&[b0, b1, b2], &pts) {
            consider(pose, &mut best, &mut needed);
        }
    }
    let Some((pose, inliers)) = best else {
        return PoseOutcome::TooFewInliers {
            inliers: 0,
            correspondences: n,
        };
    };
    let pose = refine_on(&pose, &inliers, 50);
    let inliers = inliers_of(&pose);
    if inliers.len() < options.min_num_inliers
        || (inliers.len() as f64) < options.min_inlier_ratio * n as f64
    {
        return PoseOutcome::TooFewInliers {
            inliers: inliers.len(),
            correspondences: n,
        };
    }
    PoseOutcome::Found {
        cam_from_world: pose,
        inliers,
    }
}

/// The 2D-3D correspondences of an unregistered image: each keypoint with the
/// distinct 3D points its correspondences observe (sorted by point id).
pub fn correspondences_2d3d(state: &MapState, image: ImageId) -> Vec<(u32, Point3DId)> {
    let img = &state.images[&image];
    let mut out = Vec::new();
    for k in 0..img.keypoints.len() as u32 {
        let mut ids: Vec<Point3DId> = state
            .graph
            .correspondences(image, k)
            .iter()
            .filter_map(|c| state.point_of(*c))
            .collect();
        ids.sort();
        ids.dedup();
        out.extend(ids.into_iter().map(|p| (k, p)));
    }
    out
}

/// What registering one image gave.
#[derive(Clone, Debug, PartialEq)]
pub enum RegistrationOutcome {
    Registered {
        num_correspondences: usize,
        num_inliers: usize,
    },
    Failed(PoseOutcome),
}

/// Registers `image` against the current 3D points: on success sets its pose
/// and adds its inlier keypoints to the tracks of their points. `known` (a
/// known pose of the image) is PnP's first hypothesis ([`estimate_pose`]).
pub fn register_image(
    state: &mut MapState,
    image: ImageId,
    known: Option<&Rigid3>,
    options: &RegisterOptions,
    rng: &mut ChaCha8Rng,
) -> RegistrationOutcome {
    let (corrs, pixels, points) = correspondence_arrays(state, image);
    let camera = state.camera_of(image).clone();
    match estimate_pose(&camera, &pixels, &points, known, options, rng) {
        PoseOutcome::Found {
            cam_from_world,
            inliers,
        } => {
            state.register(image, cam_from_world);
            let added = add_observations(state, image, &corrs, &inliers);
            log::debug!(
                "image {image}: {} inliers, {added} observations added",
                inliers.len()
            );
            RegistrationOutcome::Registered {
                num_correspondences: corrs.len(),
                num_inliers: inliers.len(),
            }
        }
        other => RegistrationOutcome::Failed(other),
    }
}

/// How well PnP places an image seen through `camera` against the
/// correspondences: [`truncated_reprojection_score`] at the pose
/// [`estimate_pose`] finds (its RANSAC seeded with `seed`), 1 when it finds
/// none. The score of both focal-length sweeps.
pub fn pnp_score(
    camera: &Camera,
    pixels: &[Vector2<f64>],
    points_in_world: &[Vector3<f64>],
    options: &RegisterOptions,
    seed: u64,
) -> f64 {
    let mut rng = <ChaCha8Rng as rand::SeedableRng>::seed_from_u64(seed);
    match estimate_pose(camera, pixels, points_in_world, None, options, &mut rng) {
        PoseOutcome::Found { cam_from_world, .. } => {
            truncated_reprojection_score(camera, &cam_from_world, pixels, points_in_world)
        }
        _ => 1.0,
    }
}

/// The focal length at which PnP places `image` best against the model's 3D
/// points, for the first image of a camera whose focal length is a guess (as
/// COLMAP's registration samples focal lengths for such a camera): the pose
/// found by [`estimate_pose`] at each focal length of [`sweep_focal`]'s grid
/// around the camera's value, scored by
/// [`truncated_reprojection_score`] over all of the image's 2D-3D
/// correspondences (1 where PnP finds no pose). Returns (focal length, its
/// score, the score at the camera's value; the camera's value when no grid
/// point scores better); `None` with too few
/// correspondences or no clear best. Every PnP's RANSAC is seeded with `seed`.
pub fn focal_from_points(
    state: &MapState,
    image: ImageId,
    options: &RegisterOptions,
    seed: u64,
) -> Option<(f64, f64, f64)> {
    let (_, pixels, points) = correspondence_arrays(state, image);
    focal_from_correspondences(state.camera_of(image), &pixels, &points, options, seed)
}

/// [`focal_from_points`] for given 2D-3D correspondences (`pixels[i]` sees
/// `points[i]`) of an image taken with `camera`.
pub fn focal_from_correspondences(
    camera: &Camera,
    pixels: &[Vector2<f64>],
    points: &[Vector3<f64>],
    options: &RegisterOptions,
    seed: u64,
) -> Option<(f64, f64, f64)> {
    if pixels.len() < options.min_num_inliers.max(4) {
        return None;
    }
    let score = |f: f64| pnp_score(&with_focal(camera, f), pixels, points, options, seed);
    let current = camera.mean_focal_length();
    let (f, best) = sweep_focal(current, score)?;
    let at_current = score(current);
    // The grid need not hold the camera's own value.
    Some(if at_current <= best {
        (current, at_current, at_current)
    } else {
        (f, best, at_current)
    })
}

/// Places `image` at a known pose that PnP could not find: the pose is
/// refined from there against its 2D-3D correspondences (robust, Huber at
/// `max_error_px`) when at least 6 of them agree with the refined pose within
/// `max_error_px`, and those become observations. Returns the number of
/// observations added (0: the image stays at the known pose as given).
pub fn register_at_known_pose(
    state: &mut MapState,
    image: ImageId,
    known_cam_from_world: &Rigid3,
    options: &RegisterOptions,
) -> usize {
    let (corrs, pixels, points) = correspondence_arrays(state, image);
    let camera = state.camera_of(image).clone();
    let max_sq = options.max_error_px * options.max_error_px;
    let inliers_of = |pose: &Rigid3| -> Vec<usize> {
        (0..corrs.len())
            .filter(|&i| {
                super::geometry::reprojection_error_sq(&camera, pose, &points[i], &pixels[i])
                    .is_some_and(|e2| e2 <= max_sq)
            })
            .collect()
    };
    let mut pose = *known_cam_from_world;
    let mut inliers = Vec::new();
    if corrs.len() >= 6 {
        let refined = super::geometry::refine_pose(
            &camera,
            known_cam_from_world,
            &pixels,
            &points,
            options.max_error_px,
            100,
        );
        let refined_inliers = inliers_of(&refined);
        if refined_inliers.len() >= 6 {
            pose = refined;
            inliers = refined_inliers;
        }
    }
    state.register(image, pose);
    add_observations(state, image, &corrs, &inliers)
}

/// The 2D-3D correspondences of `image` with their pixels and 3D points.
#[allow(clippy::type_complexity)]
fn correspondence_arrays(
    state: &MapState,
    image: ImageId,
) -> (Vec<(u32, Point3DId)>, Vec<Vector2<f64>>, Vec<Vector3<f64>>) {
    let corrs = correspondences_2d3d(state, image);
    let img = &state.images[&image];
    let pixels = corrs
        .iter()
        .map(|(k, _)| img.keypoints[*k as usize])
        .collect();
    let points = corrs.iter().map(|(_, p)| state.points[p].xyz).collect();
    (corrs, pixels, points)
}

/// Adds the correspondences `inliers` of the registered `image` to the
/// tracks of their points; returns how many were added.
fn add_observations(
    state: &mut MapState,
    image: ImageId,
    corrs: &[(u32, Point3DId)],
    inliers: &[usize],
) -> usize {
    let mut added = 0;
    for &i in inliers {
        let (k, p) = corrs[i];
        if state.add_observation(
            p,
            TrackElement {
                image_id: image,
                point2d_idx: k,
            },
        ) {
            added += 1;
        }
    }
    added
}

/// Unregistered images ranked for registration: visibility-pyramid score,
/// then number of visible points, then id. Images that failed are left out
/// until they see `retry_min_new_points` more points than at their failure
/// (`failed`: image -> visible points at the last failure).
pub fn next_best_images(
    state: &MapState,
    failed: &BTreeMap<ImageId, usize>,
    options: &RegisterOptions,
) -> Vec<ImageId> {
    let mut ranked: Vec<(u64, usize, ImageId)> = state
        .images
        .values()
        .filter(|img| !img.is_registered() && img.num_visible >= 4)
        .filter(|img| {
            failed
                .get(&img.id)
                .is_none_or(|&n| img.num_visible >= n + options.retry_min_new_points)
        })
        .map(|img| (img.pyramid.score(), img.num_visible, img.id))
        .collect();
    ranked.sort_by(|a, b| b.0.cmp(&a.0).then(b.1.cmp(&a.1)).then(a.2.cmp(&b.2)));
    ranked.into_iter().map(|(_, _, id)| id).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{CameraId, CameraModel};
    use nalgebra::UnitQuaternion;
    use rand::{Rng, SeedableRng};

    fn pinhole() -> Camera {
        Camera {
            id: CameraId(1),
            model: CameraModel::from_name("PINHOLE").unwrap(),
            width: 640,
            height: 480,
            params: vec![500.0, 500.0, 320.0, 240.0],
        }
    }

    /// `n` 2D-3D correspondences of `pose` (points 3-10 m in front): those
    /// with `is_inlier(i)` project within `noise_px` (uniform per axis), the
    /// others are random pixels.
    fn correspondences(
        camera: &Camera,
        pose: &Rigid3,
        n: usize,
        seed: u64,
        is_inlier: impl Fn(usize) -> bool,
        noise_px: f64,
    ) -> (Vec<Vector2<f64>>, Vec<Vector3<f64>>) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut pixels = Vec::new();
        let mut points = Vec::new();
        for i in 0..n {
            let pc = Vector3::new(
                rng.gen_range(-3.0..3.0),
                rng.gen_range(-2.0..2.0),
                rng.gen_range(3.0..10.0),
            );
            let x = camera.project(&pc).unwrap();
            let x = if is_inlier(i) {
                x + Vector2::new(
                    rng.gen_range(-noise_px..noise_px),
                    rng.gen_range(-noise_px..noise_px),
                )
            } else {
                Vector2::new(rng.gen_range(0.0..640.0), rng.gen_range(0.0..480.0))
            };
            pixels.push(x);
            points.push(pose.inverse().transform_point(&pc));
        }
        (pixels, points)
    }

    #[test]
    fn lo_ransac_finds_pose_among_outliers() {
        let camera = pinhole();
        let pose = Rigid3::new(
            UnitQuaternion::from_euler_angles(0.1, -0.3, 0.2),
            Vector3::new(0.5, -0.2, 1.0),
        );
        // 40% outliers: random pixels.
        let (pixels, points) = correspondences(&camera, &pose, 200, 11, |i| i % 5 >= 2, 0.5);
        let options = RegisterOptions::default();
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let PoseOutcome::Found {
            cam_from_world,
            inliers,
        } = estimate_pose(&camera, &pixels, &points, None, &options, &mut rng)
        else {
            panic!("no pose");
        };
        assert!(
            inliers.len() >= 120 && inliers.len() <= 130,
            "{}",
            inliers.len()
        );
        assert!(cam_from_world.rotation.angle_to(&pose.rotation) < 2e-3);
        assert!((cam_from_world.camera_center() - pose.camera_center()).norm() < 0.02);
        // Too few correspondences.
        let out = estimate_pose(
            &camera,
            &pixels[..10],
            &points[..10],
            None,
            &options,
            &mut rng,
        );
        assert_eq!(
            out,
            PoseOutcome::TooFewCorrespondences {
                found: 10,
                needed: 30
            }
        );
    }

    #[test]
    fn known_pose_guess_finds_pose_ransac_misses() {
        // 300 correspondences, 4 % inliers: 200 P3P samples almost never
        // draw three inliers; a guess 3 cm and 0.5 deg off does.
        let camera = pinhole();
        let pose = Rigid3::new(
            UnitQuaternion::from_euler_angles(0.2, 0.1, -0.4),
            Vector3::new(-0.3, 0.4, 2.0),
        );
        let (pixels, points) = correspondences(&camera, &pose, 300, 5, |i| i % 25 == 0, 0.3);
        let options = RegisterOptions {
            min_num_inliers: 10,
            min_inlier_ratio: 0.03,
            min_iterations: 200,
            max_iterations: 200,
            ..RegisterOptions::default()
        };
        let guess = Rigid3::new(
            UnitQuaternion::from_euler_angles(0.0, 0.5f64.to_radians(), 0.0) * pose.rotation,
            pose.translation + Vector3::new(0.02, -0.02, 0.01),
        );
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let without = estimate_pose(&camera, &pixels, &points, None, &options, &mut rng);
        assert!(!matches!(without, PoseOutcome::Found { .. }), "{without:?}");
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let PoseOutcome::Found {
            cam_from_world,
            inliers,
        } = estimate_pose(&camera, &pixels, &points, Some(&guess), &options, &mut rng)
        else {
            panic!("no pose from the guess");
        };
        let true_inliers = inliers.iter().filter(|&&i| i % 25 == 0).count();
        assert!(true_inliers == 12 && inliers.len() <= 14, "{inliers:?}");
        assert!(cam_from_world.rotation.angle_to(&pose.rotation) < 2e-3);
        assert!((cam_from_world.camera_center() - pose.camera_center()).norm() < 0.02);
    }
}
