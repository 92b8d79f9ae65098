//! A toy room with exact geometry: LiDAR samples of its six planes with
//! normals; random surface points seen by a short camera trajectory; their
//! projections (with noise) as keypoints; matches (with a few wrong ones) as
//! verified pairs. Everything in memory, no COLMAP.
use std::collections::{BTreeMap, BTreeSet};
use std::path::PathBuf;

use colmap_lidar::commands::map::{run as run_map, MapArgs};
use colmap_lidar::io::database::{DatabaseSnapshot, DbImage, TwoViewGeometry};
use colmap_lidar::map::PointCloud;
use colmap_lidar::scene::BodyPose;
use colmap_lidar::scene::{Camera, CameraId, CameraModel, ImageId, Rigid3};
use colmap_lidar::sfm::options::{AssociationKind, IntrinsicsRefinement, PrincipalPointRefinement};
use colmap_lidar::sfm::{
    run_mapper, run_mapper_with_priors, KnownPose, MapperInputs, MapperOptions,
};
use nalgebra::{UnitQuaternion, Vector2, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

/// Room [-5, 5] x [-4, 4] x [0, 3] shifted by this (a georeferenced map).
const ORIGIN: [f64; 3] = [512_000.0, 5_400_000.0, 230.0];

pub struct Toy {
    pub db: DatabaseSnapshot,
    pub cloud: PointCloud,
    pub gt: BTreeMap<ImageId, Rigid3>,
    pub init_pose: BodyPose,
}

fn origin() -> Vector3<f64> {
    Vector3::from(ORIGIN)
}

/// A random point on one of the six room planes, with its plane index.
fn surface_point(rng: &mut ChaCha8Rng) -> Vector3<f64> {
    let face = rng.gen_range(0..6);
    let (u, v) = (rng.gen_range(0.0..1.0), rng.gen_range(0.0..1.0));
    let p = match face {
        0 => Vector3::new(-5.0 + 10.0 * u, 4.0, 3.0 * v),
        1 => Vector3::new(-5.0 + 10.0 * u, -4.0, 3.0 * v),
        2 => Vector3::new(5.0, -4.0 + 8.0 * u, 3.0 * v),
        3 => Vector3::new(-5.0, -4.0 + 8.0 * u, 3.0 * v),
        4 => Vector3::new(-5.0 + 10.0 * u, -4.0 + 8.0 * v, 0.0),
        _ => Vector3::new(-5.0 + 10.0 * u, -4.0 + 8.0 * v, 3.0),
    };
    p + origin()
}

fn lidar_cloud(spacing_m: f64) -> PointCloud {
    let mut points = Vec::new();
    let mut normals = Vec::new();
    let mut push = |p: Vector3<f64>, n: [f32; 3]| {
        points.push([p.x as f32, p.y as f32, p.z as f32]);
        normals.push(n);
    };
    let steps = |len: f64| (len / spacing_m).round() as usize;
    for i in 0..=steps(10.0) {
        for j in 0..=steps(3.0) {
            let (x, z) = (-5.0 + i as f64 * spacing_m, j as f64 * spacing_m);
            push(Vector3::new(x, 4.0, z), [0.0, -1.0, 0.0]);
            push(Vector3::new(x, -4.0, z), [0.0, 1.0, 0.0]);
        }
    }
    for i in 0..=steps(8.0) {
        for j in 0..=steps(3.0) {
            let (y, z) = (-4.0 + i as f64 * spacing_m, j as f64 * spacing_m);
            push(Vector3::new(5.0, y, z), [-1.0, 0.0, 0.0]);
            push(Vector3::new(-5.0, y, z), [1.0, 0.0, 0.0]);
        }
    }
    for i in 0..=steps(10.0) {
        for j in 0..=steps(8.0) {
            let (x, y) = (-5.0 + i as f64 * spacing_m, -4.0 + j as f64 * spacing_m);
            push(Vector3::new(x, y, 0.0), [0.0, 0.0, 1.0]);
            push(Vector3::new(x, y, 3.0), [0.0, 0.0, -1.0]);
        }
    }
    PointCloud {
        origin: origin(),
        points,
        normals: Some(normals),
        planarity: None,
    }
}

/// The toy scene: `num_images` cameras walking along x, looking at the +y
/// wall and turning slowly, with `noise_px` keypoint noise and a fraction
/// `wrong` of wrong matches.
pub fn toy(num_images: usize, noise_px: f64, wrong: f64, seed: u64) -> Toy {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let camera = Camera {
        id: CameraId(1),
        model: CameraModel::from_name("SIMPLE_RADIAL").expect("known model"),
        width: 640,
        height: 480,
        params: vec![450.0, 320.0, 240.0, 0.01],
    };
    let surface: Vec<Vector3<f64>> = (0..6000).map(|_| surface_point(&mut rng)).collect();
    let noise = Normal::new(0.0, noise_px.max(1e-12)).expect("valid sigma");
    let mut db = DatabaseSnapshot {
        path: PathBuf::from("toy.db"),
        ..Default::default()
    };
    db.cameras.insert(CameraId(1), camera.clone());
    let mut gt = BTreeMap::new();
    // Which surface point each keypoint shows, per image.
    let mut seen: BTreeMap<ImageId, Vec<usize>> = BTreeMap::new();
    let mut init_pose = None;
    for i in 0..num_images {
        let t = i as f64 / (num_images.max(2) - 1) as f64;
        let body = BodyPose::from_degrees(
            origin() + Vector3::new(-2.0 + 4.0 * t, -1.0 + 0.5 * (t * 6.0).sin(), 1.4),
            2.0 * (t * 5.0).cos(),
            -8.0 + 4.0 * (t * 3.0).sin(),
            60.0 + 60.0 * t,
        );
        if i == 0 {
            init_pose = Some(body);
        }
        let cam_from_world = body.to_cam_from_world();
        let id = ImageId(i as u32 + 1);
        let mut keypoints = Vec::new();
        let mut which = Vec::new();
        for (s, p) in surface.iter().enumerate() {
            let pc = cam_from_world.transform_point(p);
            if pc.z < 0.3 {
                continue;
            }
            let Some(x) = camera.project(&pc) else {
                continue;
            };
            if x.x < 1.0 || x.y < 1.0 || x.x > 639.0 || x.y > 479.0 {
                continue;
            }
            keypoints.push(x + Vector2::new(noise.sample(&mut rng), noise.sample(&mut rng)));
            which.push(s);
        }
        // Random extra keypoints without a match.
        for _ in 0..100 {
            keypoints.push(Vector2::new(
                rng.gen_range(0.0..640.0),
                rng.gen_range(0.0..480.0),
            ));
            which.push(usize::MAX);
        }
        db.images.insert(
            id,
            DbImage {
                id,
                name: format!("img_{i:03}.png"),
                camera_id: CameraId(1),
            },
        );
        db.keypoints.insert(id, keypoints);
        seen.insert(id, which);
        gt.insert(id, cam_from_world);
    }
    let ids: Vec<ImageId> = seen.keys().copied().collect();
    for a in 0..ids.len() {
        for b in a + 1..ids.len() {
            let (wa, wb) = (&seen[&ids[a]], &seen[&ids[b]]);
            let index_b: BTreeMap<usize, u32> = wb
                .iter()
                .enumerate()
                .filter(|(_, s)| **s != usize::MAX)
                .map(|(k, s)| (*s, k as u32))
                .collect();
            let mut matches: Vec<[u32; 2]> = Vec::new();
            for (k, s) in wa.iter().enumerate() {
                if let Some(&kb) = index_b.get(s) {
                    matches.push([k as u32, kb]);
                }
            }
            if matches.len() < 30 {
                continue;
            }
            let num_wrong = (matches.len() as f64 * wrong) as usize;
            for _ in 0..num_wrong {
                let m = rng.gen_range(0..matches.len());
                matches[m][1] = rng.gen_range(0..wb.len() as u32);
            }
            matches.sort();
            matches.dedup_by_key(|m| m[1]);
            db.two_view_geometries.push(TwoViewGeometry {
                image_id1: ids[a],
                image_id2: ids[b],
                config: 2,
                inlier_matches: matches,
                fundamental: None,
                essential: None,
            });
        }
    }
    Toy {
        db,
        cloud: lidar_cloud(0.05),
        gt,
        init_pose: init_pose.expect("at least one image"),
    }
}

/// Largest camera-centre error of the registered images against gt, metres.
fn max_centre_error(
    rec: &colmap_lidar::scene::Reconstruction,
    gt: &BTreeMap<ImageId, Rigid3>,
) -> f64 {
    rec.registered_images()
        .map(|img| {
            (img.cam_from_world.expect("registered").camera_center() - gt[&img.id].camera_center())
                .norm()
        })
        .fold(0.0, f64::max)
}

/// Runs the mapper on a toy from image 1 at its initial pose; the output
/// and the largest camera-centre error.
fn map_toy(scene: &Toy, options: &MapperOptions) -> (colmap_lidar::sfm::MapperOutput, f64) {
    map_toy_from(scene, &scene.init_pose.to_cam_from_world(), options)
}

/// [`map_toy`] from image 1 at `given`.
fn map_toy_from(
    scene: &Toy,
    given: &Rigid3,
    options: &MapperOptions,
) -> (colmap_lidar::sfm::MapperOutput, f64) {
    let out = run_mapper(
        &scene.db,
        &scene.cloud,
        ImageId(1),
        given,
        options,
        &mut |_, _| {},
    )
    .unwrap();
    let err = max_centre_error(&out.reconstruction, &scene.gt);
    (out, err)
}

/// The initial image given 10 cm off and held through registration
/// (`fix_initial_for`, no alignment to the map; every registration solve's
/// record shows it at its given pose): held through the final
/// rounds too it stays exactly where it was given; freed there
/// (`hold_initial_in_final_rounds = false`) the map moves it back, and the
/// whole model with it.
#[test]
fn initial_image_held_through_registration_can_be_freed_for_the_final_rounds() {
    let scene = toy(14, 0.3, 0.03, 1);
    let given = initial_pose_off(&scene, Vector3::new(0.1, 0.0, 0.0), 0.0);
    let run = |hold_in_final: bool| {
        let mut options = MapperOptions::default();
        options.bundle.fix_initial_for = 1000;
        options.bundle.hold_initial_in_final_rounds = hold_in_final;
        options.bundle.align_to_map = false;
        options.bundle.retry_holding_initial = false;
        // One run: its solves' records are from the given pose.
        options.bundle.restart_from_refined_pose = false;
        let (out, err) = map_toy_from(&scene, &given, &options);
        let moved = out.report.initial_pose_change.as_ref().unwrap().moved_m;
        // Each solve records where the initial image was: through
        // registration exactly at its given pose.
        let solves = &out.report.solves;
        let registration: Vec<f64> = solves
            .iter()
            .filter(|s| !s.kind.is_final())
            .map(|s| s.initial_image_change.expect("recorded").moved_m)
            .collect();
        assert!(registration.len() > 10, "{}", registration.len());
        assert!(registration.iter().all(|&m| m < 1e-9), "{registration:?}");
        // The final rounds' records show where it ended (within the last
        // round's move; a discarded intrinsics probe is not in the model).
        let last = solves
            .iter()
            .rev()
            .find(|s| s.kind.is_final() && !s.discarded)
            .unwrap();
        let last_moved = last.initial_image_change.unwrap().moved_m;
        assert!(
            (last_moved - moved).abs() < 0.002,
            "{last_moved} vs {moved}"
        );
        (moved, err)
    };
    let (held_moved, held_err) = run(true);
    let (freed_moved, freed_err) = run(false);
    eprintln!("held: moved {held_moved:.4} m, max error {held_err:.4} m; freed: moved {freed_moved:.4} m, max error {freed_err:.4} m");
    assert!(held_moved < 1e-9, "{held_moved}");
    assert!(held_err > 0.05, "{held_err}");
    assert!(freed_moved > 0.05, "{freed_moved}");
    assert!(freed_err < 0.5 * held_err, "{freed_err} vs {held_err}");
}

/// The initial pose given `by` off (in the map frame) and turned
/// `turn_deg` about the map's vertical axis through the camera centre.
fn initial_pose_off(scene: &Toy, by: Vector3<f64>, turn_deg: f64) -> Rigid3 {
    let truth = scene.init_pose.to_cam_from_world();
    let turn = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), turn_deg.to_radians());
    // cam_from_world of a camera turned in the world: R * turn^-1.
    Rigid3::from_rotation_and_center(
        truth.rotation * turn.inverse(),
        &(truth.camera_center() + by),
    )
}

/// The toy mapped from `given` without the alignment to the map (so the
/// initial image is held there for its first 8 registrations), the first
/// run mapped again from where its initial image ended
/// (`bundle.restart_first_run`), looking at it early at `look_at` images
/// (`bundle.restart_early_at_images`; 0 only at the end).
fn map_toy_looking_at(
    scene: &Toy,
    given: &Rigid3,
    look_at: usize,
) -> (colmap_lidar::sfm::MapperOutput, f64) {
    let mut options = MapperOptions::default();
    options.bundle.align_to_map = false;
    options.bundle.restart_first_run = true;
    options.bundle.restart_early_at_images = look_at;
    map_toy_from(scene, given, &options)
}

/// The initial image given 15 cm and 2 deg off (no alignment to the map,
/// so it is held there for its first 8 registrations): with
/// `bundle.restart_early_at_images`, the first run looks at it once it is
/// released and the model has that many images, sees it turned, stops and
/// maps again from there; looking only at the end maps the whole first run.
/// Both come out right; in a database of fewer than three times its image
/// count the look waits for the image to be steady.
#[test]
fn a_run_whose_initial_image_turned_early_is_mapped_again_from_there() {
    let scene = toy(30, 0.3, 0.03, 1);
    let given = initial_pose_off(&scene, Vector3::new(0.15, 0.0, 0.0), 2.0);
    let run = |look_at: usize| map_toy_looking_at(&scene, &given, look_at);
    let (early, early_err) = run(10);
    let (full, full_err) = run(0);
    eprintln!(
        "early restart: max error {early_err:.4} m, {:?}; full: {full_err:.4} m, {:?}",
        early.report.early_restart, full.report.restart
    );
    let record = early
        .report
        .early_restart
        .as_ref()
        .expect("an early restart");
    let at = record.first_stopped_at_images.expect("stopped early");
    assert!((10..30).contains(&at), "{at}");
    assert!(
        record.second_kept && record.second_error.is_none(),
        "{record:?}"
    );
    assert!(record.first_fit_share.is_none());
    assert!(record.first_change.turned_deg > 1.0, "{record:?}");
    // The look that stopped it, in the kept run's report: without the
    // alignment to the map there is no trial to tell an unsettled model.
    let look = early.report.early_look.expect("the look is reported");
    assert_eq!(look.registered, at);
    assert_eq!(look.change.moved_m, record.first_change.moved_m);
    assert!(
        look.settled && look.alignment_would_move.is_none(),
        "{look:?}"
    );
    assert_eq!(early.report.num_registered, 30);
    // The run from the look kept the image where the look put it: kept as
    // it is, not mapped again from its end, and no look of its own.
    assert!(early.report.restart.is_none());
    assert!(record.second_look.is_none(), "{record:?}");
    // Measured from the given pose, as without the restart.
    let change = early.report.initial_pose_change.expect("measured");
    assert!((change.moved_m - 0.15).abs() < 0.02, "{change:?}");
    assert!((change.turned_deg - 2.0).abs() < 0.2, "{change:?}");
    assert!(early_err < 0.02, "{early_err}");
    // Looking only at the end: the whole first run, then the restart.
    assert!(full.report.early_restart.is_none());
    let restart = full.report.restart.as_ref().expect("a restart");
    assert!(restart.first_stopped_at_images.is_none() && restart.second_kept);
    assert!(full_err < 0.02, "{full_err}");
    // 30 images are fewer than three times 11: the look comes from a third
    // of them on (10), once a sphere solve moved the image less than 1 cm
    // and 0.1 deg, and up to two thirds (20).
    let (steady, steady_err) = run(11);
    eprintln!(
        "steady look: {:?}, {:?}, max error {steady_err:.4} m",
        steady.report.early_look, steady.report.early_restart
    );
    let look = steady.report.early_look.expect("the look is reported");
    assert!((10..=20).contains(&look.registered), "{look:?}");
    let step = look.step.expect("a sphere solve before the look");
    assert!(step.moved_m < 0.01 && step.turned_deg < 0.1, "{look:?}");
    assert!(steady
        .report
        .early_restart
        .as_ref()
        .is_some_and(|r| r.second_kept));
    assert!(steady_err < 0.02, "{steady_err}");
}

/// By default (`bundle.restart_first_run` off, and a database of fewer than
/// 48 images) the first run from a pose 15 cm and 2 deg off is kept as it
/// ended: one run, with no look and no second run, its initial image where
/// the map put it (15 cm and 2 deg from the given pose), and as right as
/// the run mapped again from its end.
#[test]
fn a_first_run_from_a_pose_off_is_kept_as_it_ended_by_default() {
    let scene = toy(30, 0.3, 0.03, 1);
    let given = initial_pose_off(&scene, Vector3::new(0.15, 0.0, 0.0), 2.0);
    let mut options = MapperOptions::default();
    options.bundle.align_to_map = false;
    let (out, err) = map_toy_from(&scene, &given, &options);
    let (again, again_err) = map_toy_looking_at(&scene, &given, 0);
    eprintln!("one run: max error {err:.4} m; mapped again: {again_err:.4} m");
    assert!(out.report.restart.is_none(), "{:?}", out.report.restart);
    assert!(out.report.early_look.is_none() && out.report.early_restart.is_none());
    assert!(again.report.restart.as_ref().is_some_and(|r| r.second_kept));
    let change = out.report.initial_pose_change.expect("measured");
    assert!((change.moved_m - 0.15).abs() < 0.02, "{change:?}");
    assert!((change.turned_deg - 2.0).abs() < 0.2, "{change:?}");
    assert_eq!(out.report.num_registered, 30);
    assert!(
        err < 0.02 && err < again_err + 0.005,
        "{err} vs {again_err}"
    );
}

/// The initial image given 15 cm and 2 deg off and held for its first 20
/// registrations (no alignment to the map), so that 30 images leave no
/// room for the early look: the first run looks at the end of its
/// registration, sees the image turned back, and is mapped again from there
/// without its final stage; as right as the whole first run and its
/// restart (`bundle.restart_early_at_images = 0`).
#[test]
fn a_run_whose_initial_image_turned_stops_at_the_end_of_registration() {
    let scene = toy(30, 0.3, 0.03, 1);
    let given = initial_pose_off(&scene, Vector3::new(0.15, 0.0, 0.0), 2.0);
    let run = |look_at: usize| {
        let mut options = MapperOptions::default();
        options.bundle.align_to_map = false;
        options.bundle.fix_initial_for = 20;
        options.bundle.restart_first_run = true;
        options.bundle.restart_early_at_images = look_at;
        map_toy_from(&scene, &given, &options)
    };
    let (stopped, err) = run(16);
    let look = stopped.report.early_look.expect("the look is reported");
    eprintln!(
        "stopped: max error {err:.4} m, {look:?}, {:?}",
        stopped.report.early_restart
    );
    assert!(
        look.end_of_registration && look.registered == 30,
        "{look:?}"
    );
    assert!(look.step.is_none() && look.alignment_would_move.is_none());
    assert!(look.change.turned_deg > 1.0, "{look:?}");
    assert!(look.seen_share.is_some_and(|s| s >= 0.8), "{look:?}");
    let record = stopped
        .report
        .early_restart
        .as_ref()
        .expect("mapped again from there");
    assert_eq!(record.first_stopped_at_images, Some(30));
    assert_eq!(record.first_change.turned_deg, look.change.turned_deg);
    assert!(record.second_kept && record.first_fit_share.is_none());
    // The run from there kept the image where the look put it.
    assert!(stopped.report.restart.is_none());
    let change = stopped.report.initial_pose_change.expect("measured");
    assert!((change.moved_m - 0.15).abs() < 0.02, "{change:?}");
    assert!((change.turned_deg - 2.0).abs() < 0.2, "{change:?}");
    assert!(err < 0.02, "{err}");
    // Without the look: the whole first run, then the restart.
    let (full, full_err) = run(0);
    assert!(full.report.early_look.is_none() && full.report.early_restart.is_none());
    let restart = full.report.restart.as_ref().expect("a restart");
    assert!(restart.first_fit_share.is_some() && restart.second_kept);
    assert!(full_err < 0.02, "{full_err}");
}

/// The initial image given 40 cm and 2 deg off: at the early look (10
/// images) it has turned back but moved only part of the way (0.28 m),
/// and the run from there moves it the rest (0.12 m, 0.06 deg) without
/// turning it and fits the map: the look came mid-slide, so that run is
/// mapped again from where it ended (`runs::slid_back`), not thrown away
/// for the first run to its end. It has moved the image that far by the
/// end of its registration, so it stops there, before its final stage.
#[test]
fn a_run_from_the_look_that_slid_back_is_mapped_again_from_its_end() {
    let scene = toy(30, 0.3, 0.03, 1);
    let given = initial_pose_off(&scene, Vector3::new(0.4, 0.0, 0.0), 2.0);
    let (out, err) = map_toy_looking_at(&scene, &given, 10);
    let early = out.report.early_restart.as_ref().expect("an early restart");
    let restart = out.report.restart.as_ref().expect("a restart");
    eprintln!("slid back: max error {err:.4} m; early {early:?}; restart {restart:?}");
    assert!(early.first_stopped_at_images.is_some() && early.second_kept);
    assert!(early.first_change.turned_deg > 1.0, "{early:?}");
    // The restart's first run is the run from the look: moved from the
    // look's pose, beyond the look's bar, without a turn, by the end of its
    // registration, where it stopped (so no fit share of a finished run).
    assert_eq!(restart.first_stopped_at_images, Some(30));
    assert!(restart.second_kept, "{restart:?}");
    assert!(
        restart.first_change.moved_m > 0.1 && restart.first_change.turned_deg < 1.0,
        "{restart:?}"
    );
    assert!(restart.first_fit_share.is_none() && early.second_fit_share.is_none());
    assert_eq!(restart.first_run_s, early.second_run_s);
    assert!(out.report.early_look.is_some_and(|l| l.settled));
    // That run's own look, which stopped it, in the early restart's record
    // (the top-level look is the first run's, at 10 images).
    let own = early.second_look.expect("the run from the look looked");
    assert!(own.end_of_registration && own.registered == 30, "{own:?}");
    assert_eq!(own.change.moved_m, restart.first_change.moved_m);
    // Measured from the given pose.
    let change = out.report.initial_pose_change.expect("measured");
    assert!((change.moved_m - 0.4).abs() < 0.02, "{change:?}");
    assert!((change.turned_deg - 2.0).abs() < 0.2, "{change:?}");
    assert_eq!(out.report.num_registered, 30);
    assert!(err < 0.02, "{err}");
}

/// The initial image given 15 cm off and not turned: at the early look it
/// has moved (more than the 10 cm a run from there must keep it within) but
/// not turned, which may be a slide that the growing model undoes, so the
/// run goes on to its end and is mapped again from where the image ended,
/// the same run as looking only at the end.
#[test]
fn a_run_whose_initial_image_only_moved_early_goes_on_to_its_end() {
    let scene = toy(30, 0.3, 0.03, 1);
    let given = initial_pose_off(&scene, Vector3::new(0.15, 0.0, 0.0), 0.0);
    let run = |look_at: usize| map_toy_looking_at(&scene, &given, look_at);
    let (looked, err) = run(10);
    let look = looked.report.early_look.expect("the look is reported");
    eprintln!("look {look:?}, max error {err:.4} m");
    assert!((10..30).contains(&look.registered), "{look:?}");
    assert!(
        look.change.moved_m > 0.1 && look.change.turned_deg < 1.0,
        "{look:?}"
    );
    assert!(looked.report.early_restart.is_none());
    let restart = looked.report.restart.as_ref().expect("a restart");
    assert!(restart.first_stopped_at_images.is_none() && restart.second_kept);
    assert!(err < 0.02, "{err}");
    let (full, _) = run(0);
    assert_eq!(
        looked.reconstruction.pose(ImageId(1)),
        full.reconstruction.pose(ImageId(1))
    );
}

/// A map sampled every 15 cm (the defaults suit 2-5 cm): the mapper finds
/// the spacing and widens its splats and plane radii
/// (`MapperOptions::for_map_spacing`); without that, cameras see through the
/// map's surfaces between its splats (measured: this toy's run failed, 59.6 %
/// of its points on the surface their images see, below the check's 60 %).
#[test]
fn toy_room_on_a_sparse_map() {
    let mut scene = toy(14, 0.3, 0.03, 1);
    scene.cloud = lidar_cloud(0.15);
    let (out, err) = map_toy(&scene, &MapperOptions::default());
    let spacing = out.report.map_spacing_m.expect("a spacing");
    eprintln!(
        "toy room, 15 cm map: spacing {spacing:.3} m, {}/{} registered, max centre error {err:.4} m",
        out.report.num_registered, out.report.num_images
    );
    // A square grid's estimate: sqrt(pi / 4) of its spacing.
    assert!((0.12..0.15).contains(&spacing), "{spacing}");
    assert_eq!(out.report.num_registered, 14);
    assert!(err < 0.03, "max centre error {err} m");
    assert!(out.report.points_on_seen_surface_share.expect("share") > 0.8);
}

#[test]
fn toy_room_registers_in_the_map_frame() {
    let scene = toy(14, 0.3, 0.03, 1);
    let options = MapperOptions::default();
    let (out, err) = map_toy(&scene, &options);
    let rec = &out.reconstruction;
    eprintln!(
        "toy room: {}/{} registered, {} points, mean reprojection {:.3} px, max centre error {:.4} m",
        out.report.num_registered,
        out.report.num_images,
        out.report.num_points,
        out.report.mean_reprojection_error_px,
        err
    );
    assert_eq!(out.report.num_registered, 14);
    assert!(out.report.mean_reprojection_error_px < 0.7);
    assert!(err < 0.03, "max centre error {err} m");
    // Every registered image has its pose uncertainty, and the largest
    // sigma is not far below the largest error (the toy's noise is the
    // model's: 0.3 px, map 3 cm).
    let unc = out.report.pose_uncertainty.as_ref().expect("uncertainty");
    assert_eq!(
        out.report
            .images
            .iter()
            .filter(|r| r.pose_uncertainty.is_some())
            .count(),
        14
    );
    assert!(
        unc.max_centre_sigma_major_m > 0.0 && err < 10.0 * unc.max_centre_sigma_major_m,
        "max error {err} m, max sigma {} m",
        unc.max_centre_sigma_major_m
    );
    // Every stage after registration is timed under its own name.
    let stages: Vec<&str> = out.report.stages.iter().map(|s| s.name.as_str()).collect();
    let tail = &stages[stages.len() - 6..];
    assert_eq!(
        tail,
        [
            "incremental registration",
            "retriangulation, alignment to the map",
            "points behind the map",
            "final bundle adjustment",
            "fit to the map",
            "pose uncertainty"
        ],
        "{stages:?}"
    );
    // And says the process's peak memory so far (Linux): a high-water
    // mark, so never falling, and more than a megabyte.
    if cfg!(target_os = "linux") {
        let peaks: Vec<f64> = out
            .report
            .stages
            .iter()
            .map(|s| s.peak_memory_mb.expect("peak memory"))
            .collect();
        assert!(peaks.windows(2).all(|w| w[0] <= w[1]), "{peaks:?}");
        assert!(peaks[0] > 1.0, "{peaks:?}");
    }
    // Nearly every point lies on the wall its images see there.
    let seen = out.report.points_on_seen_surface_share.unwrap();
    assert!(seen > 0.9, "points on the seen surface: {seen}");
    // Points lie on the room's planes (the map holds them).
    let o = origin();
    let mut off = 0usize;
    for p in rec.points3d.values() {
        let q = p.xyz - o;
        let d = [q.y - 4.0, q.y + 4.0, q.x - 5.0, q.x + 5.0, q.z, q.z - 3.0]
            .iter()
            .fold(f64::INFINITY, |m, v| m.min(v.abs()));
        if d > 0.05 {
            off += 1;
        }
    }
    assert!(
        off * 20 < rec.points3d.len(),
        "{off} of {} points off the planes",
        rec.points3d.len()
    );
}

#[test]
fn toy_room_initial_pose_off() {
    // The initial image given 0.25 m and 2.5 deg (yaw) away from its pose.
    // In this room the initial pair sees enough planes for its own solve to
    // pull it onto the map, so the initial pair's alignment finds nothing
    // left to move (on the seed-2 yard it undid 7 % of scale and 0.69 m:
    // colmap_e2e and the session notes); what the report says of it must be
    // consistent, and in the map's coordinates (the toy sits 4400 km from
    // the origin: a similarity's own translation would read hundreds of m).
    let scene = toy(14, 0.3, 0.03, 1);
    let mut off = scene.init_pose;
    off.position_m += Vector3::new(0.15, -0.15, 0.12);
    off.yaw_rad += 2.5f64.to_radians();
    let run = |align: bool| {
        let mut options = MapperOptions::default();
        options.bundle.align_to_map = align;
        let out = run_mapper(
            &scene.db,
            &scene.cloud,
            ImageId(1),
            &off.to_cam_from_world(),
            &options,
            &mut |_, _| {},
        )
        .unwrap();
        let err = max_centre_error(&out.reconstruction, &scene.gt);
        (out, err)
    };
    let (out, err) = run(true);
    let a = out.report.initial_alignment.expect("initial alignment");
    eprintln!("toy room, initial pose off: max centre error {err:.4} m; initial alignment {a:?}");
    assert_eq!(
        a.applied,
        a.points_on_map_after > a.points_on_map_before
            && a.points_on_map_after as f64
                >= colmap_lidar::sfm::mapper::INITIAL_PAIR_MIN_GAIN * a.points_on_map_before as f64
            && a.within_bounds
    );
    assert!(a.translation_m < 0.05 && a.rotation_deg < 0.5, "{a:?}");
    assert_eq!(out.report.num_registered, 14);
    assert!(err < 0.03, "max centre error {err} m");
    let (out, _) = run(false);
    assert!(out.report.initial_alignment.is_none() && out.report.alignment.is_none());
}

#[test]
fn toy_room_without_lidar_terms_keeps_the_initial_frame() {
    let scene = toy(10, 0.3, 0.0, 2);
    let mut options = MapperOptions::default();
    options.association.kind = AssociationKind::None;
    let (out, err) = map_toy(&scene, &options);
    eprintln!(
        "toy room, no LiDAR terms: {}/{} registered, max centre error {err:.4} m",
        out.report.num_registered, out.report.num_images
    );
    assert_eq!(out.report.num_registered, 10);
    // Without the map no uncertainty in its frame is reported, and no
    // alignment or behind-map stage runs.
    assert!(out.report.pose_uncertainty.is_none());
    let stages: Vec<&str> = out.report.stages.iter().map(|s| s.name.as_str()).collect();
    assert_eq!(
        &stages[stages.len() - 3..],
        [
            "incremental registration",
            "retriangulation",
            "final bundle adjustment"
        ],
        "{stages:?}"
    );
    // The first two images (fixed) carry the map's frame and scale.
    assert!(err < 0.1, "max centre error {err} m");
}

#[test]
fn toy_room_is_deterministic() {
    let scene = toy(8, 0.3, 0.03, 3);
    let init = scene.init_pose.to_cam_from_world();
    let run = || {
        run_mapper(
            &scene.db,
            &scene.cloud,
            ImageId(1),
            &init,
            &MapperOptions::default(),
            &mut |_, _| {},
        )
        .unwrap()
        .reconstruction
    };
    let (a, b) = (run(), run());
    assert_eq!(a, b);
    let dir = tempfile::tempdir().unwrap();
    for (name, rec) in [("a", &a), ("b", &b)] {
        colmap_lidar::io::model::write_model(
            &dir.path().join(name),
            rec,
            colmap_lidar::io::model::ModelFormat::Binary,
        )
        .unwrap();
    }
    for f in ["cameras.bin", "images.bin", "points3D.bin"] {
        let x = std::fs::read(dir.path().join("a").join(f)).unwrap();
        let y = std::fs::read(dir.path().join("b").join(f)).unwrap();
        assert!(x == y, "{f} differs between two runs");
    }
}

#[test]
fn toy_bad_inputs_fail_clearly() {
    let scene = toy(6, 0.3, 0.0, 4);
    let options = MapperOptions::default();
    // Initial pose looking away from the room: outside it, facing away.
    let away = BodyPose::from_degrees(origin() + Vector3::new(0.0, -30.0, 1.5), 0.0, 0.0, -90.0);
    let err = run_mapper(
        &scene.db,
        &scene.cloud,
        ImageId(1),
        &away.to_cam_from_world(),
        &options,
        &mut |_, _| {},
    )
    .err()
    .expect("must fail");
    let msg = err.to_string();
    assert!(
        msg.contains("sees no usable map point") && msg.contains("img_000.png"),
        "{msg}"
    );
    // No verified pairs.
    let mut db = scene.db.clone();
    db.two_view_geometries.clear();
    let err = run_mapper(
        &db,
        &scene.cloud,
        ImageId(1),
        &scene.init_pose.to_cam_from_world(),
        &options,
        &mut |_, _| {},
    )
    .err()
    .expect("must fail");
    assert!(err.to_string().contains("no verified image pairs"), "{err}");
    // Unknown image id.
    let err = run_mapper(
        &scene.db,
        &scene.cloud,
        ImageId(99),
        &scene.init_pose.to_cam_from_world(),
        &options,
        &mut |_, _| {},
    )
    .err()
    .expect("must fail");
    assert!(err.to_string().contains("99"), "{err}");
    // The command refuses an unknown image name before writing anything.
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let args = MapArgs {
        database: Some(dir.path().join("missing.db")),
        lidar: Some(dir.path().join("missing.ply")),
        output: Some(out.clone()),
        init_pose: vec!["0,0,0,0,0,0".into()],
        ..Default::default()
    };
    let err = run_map(&args).unwrap_err();
    assert!(format!("{err:#}").contains("missing.db"), "{err:#}");
    assert!(!out.exists());
    let args = MapArgs {
        init_pose: vec!["0,0,0,0,0".into()],
        ..args
    };
    let err = run_map(&args).unwrap_err();
    assert!(format!("{err:#}").contains("six numbers"), "{err:#}");
    assert!(!out.exists());
}

mod units {
    //! Track continuation, merging and filtering on a small exact scene.
    use super::*;
    use colmap_lidar::scene::TrackElement;
    use colmap_lidar::sfm::filter::{filter_observations, filter_small_angle_points};
    use colmap_lidar::sfm::options::TriangulateOptions;
    use colmap_lidar::sfm::register::next_best_images;
    use colmap_lidar::sfm::state::MapState;
    use colmap_lidar::sfm::triangulate::{triangulate_image, try_merge};

    fn e(image: u32, k: u32) -> TrackElement {
        TrackElement {
            image_id: ImageId(image),
            point2d_idx: k,
        }
    }

    /// The toy scene with its first three images registered at their true poses.
    fn three_registered() -> (Toy, MapState) {
        let scene = toy(6, 0.0, 0.0, 9);
        let mut state = MapState::new(&scene.db, 4);
        for i in 1..=3 {
            state.register(ImageId(i), scene.gt[&ImageId(i)]);
        }
        (scene, state)
    }

    #[test]
    fn triangulation_creates_exact_points_and_continues_tracks() {
        let (scene, mut state) = three_registered();
        let options = TriangulateOptions::default();
        let stats = triangulate_image(&mut state, ImageId(2), &options);
        assert!(stats.created > 100, "{stats:?}");
        // Exact keypoints: every point lies on a room plane, and reprojects exactly.
        for id in state.points.keys().copied().collect::<Vec<_>>() {
            assert!(state.point_error_px(id).unwrap() < 1e-6);
            assert!(state.points[&id].track.len() >= 2);
        }
        // Registering image 4 and triangulating it continues existing tracks.
        let before: usize = state.points.values().map(|p| p.track.len()).sum();
        state.register(ImageId(4), scene.gt[&ImageId(4)]);
        let stats4 = triangulate_image(&mut state, ImageId(4), &options);
        let after: usize = state.points.values().map(|p| p.track.len()).sum();
        assert!(stats4.continued > 50, "{stats4:?}");
        assert!(after > before);
        // Every keypoint/point link is consistent both ways.
        for (id, p) in &state.points {
            for t in &p.track {
                assert_eq!(state.point_of(*t), Some(*id));
            }
        }
    }

    #[test]
    fn merging_joins_split_tracks_and_refuses_bad_merges() {
        let (_scene, mut state) = three_registered();
        // A keypoint seen in images 1, 2 and 3: find one through the graph.
        let (k1, k2, k3) = (0..state.images[&ImageId(1)].keypoints.len() as u32)
            .find_map(|k| {
                let c = state.graph.correspondences(ImageId(1), k);
                let a = c.iter().find(|t| t.image_id == ImageId(2))?;
                let b = c.iter().find(|t| t.image_id == ImageId(3))?;
                Some((k, a.point2d_idx, b.point2d_idx))
            })
            .expect("a track over three images");
        let options = TriangulateOptions::default();
        let views_a = [e(1, k1), e(2, k2)];
        let (xa, _) =
            colmap_lidar::sfm::triangulate::triangulate_views(&state, &views_a, &options).unwrap();
        // Split: one point on (1, 2), another on (3).
        let a = state.add_point(xa, views_a.to_vec());
        // 1 m away: the merged position would not fit the observations.
        let far = state.add_point(xa + Vector3::new(1.0, 1.0, 0.0), vec![e(3, k3)]);
        assert!(!try_merge(&mut state, a, far, &options));
        assert!(state.points.contains_key(&far));
        state.delete_point(far);
        // 1 mm away: merged into one track of three.
        let b = state.add_point(xa + Vector3::new(0.001, 0.0, 0.0), vec![e(3, k3)]);
        assert!(try_merge(&mut state, a, b, &options));
        assert!(!state.points.contains_key(&b));
        assert_eq!(state.points[&a].track, vec![e(1, k1), e(2, k2), e(3, k3)]);
        assert_eq!(state.point_of(e(3, k3)), Some(a));
    }

    #[test]
    fn filters_remove_what_they_report() {
        let (_scene, mut state) = three_registered();
        let options = TriangulateOptions::default();
        triangulate_image(&mut state, ImageId(2), &options);
        let n_points = state.points.len();
        let n_obs: usize = state.points.values().map(|p| p.track.len()).sum();
        // Exact data: nothing to remove.
        assert_eq!(filter_observations(&mut state, None, 1.0), 0);
        // Move one point 0.5 m: all its observations go, and the point with them.
        let (&id, p) = state.points.iter().next().unwrap();
        let len = p.track.len();
        state.points.get_mut(&id).unwrap().xyz += Vector3::new(0.0, 0.0, 0.5);
        let removed = filter_observations(&mut state, None, 1.0);
        assert_eq!(removed, len);
        assert!(!state.points.contains_key(&id));
        assert_eq!(state.points.len(), n_points - 1);
        let n_obs_after: usize = state.points.values().map(|p| p.track.len()).sum();
        assert_eq!(n_obs_after, n_obs - len);
        // An absurd angle threshold removes every point that is not anchored.
        let removed = filter_small_angle_points(&mut state, 179.0);
        assert_eq!(removed, n_points - 1);
        assert!(state.points.is_empty());
        // Next-best view: image 4 sees no point now; with points back it ranks first among the unregistered.
        assert!(next_best_images(&state, &Default::default(), &Default::default()).is_empty());
        triangulate_image(&mut state, ImageId(2), &options);
        let ranked = next_best_images(&state, &Default::default(), &Default::default());
        assert_eq!(ranked.first(), Some(&ImageId(4)), "{ranked:?}");
    }
}

/// Prints the toy room's accuracy under a few option variants (debugging aid).
#[test]
#[ignore]
fn toy_room_option_sweep() {
    let noise: f64 = std::env::var("TOY_NOISE")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(0.3);
    let wrong: f64 = std::env::var("TOY_WRONG")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(0.03);
    let scene = toy(14, noise, wrong, 1);
    let init = scene.init_pose.to_cam_from_world();
    type Variant = (&'static str, Box<dyn Fn(&mut MapperOptions)>);
    let variants: Vec<Variant> = vec![
        ("default", Box::new(|_| {})),
        (
            "initial fixed",
            Box::new(|o| {
                o.bundle.fix_initial_for = 1000;
                o.bundle.hold_initial_in_final_rounds = true;
            }),
        ),
        (
            "gate 5 cm",
            Box::new(|o| o.association.max_plane_distance_m = 0.05),
        ),
        (
            "radius 0.3 m",
            Box::new(|o| o.association.max_radius_m = 0.3),
        ),
        (
            "weight 100",
            Box::new(|o| {
                o.association.weight = 100.0;
                o.association.ground_weight = 100.0
            }),
        ),
        (
            "no lidar",
            Box::new(|o| o.association.kind = AssociationKind::None),
        ),
        (
            "init gate 0.05 m",
            Box::new(|o| o.init.max_plane_extrapolation_m = 0.05),
        ),
        (
            "w1000, Huber 0.2 m",
            Box::new(|o| o.association.loss_scale_m = 0.2),
        ),
        (
            "w1000, Huber 2 mm",
            Box::new(|o| o.association.loss_scale_m = 0.002),
        ),
        (
            "tolerance 1e-12",
            Box::new(|o| {
                o.bundle.function_tolerance = 1e-12;
                o.bundle.global_max_iterations = 500;
                o.bundle.local_max_iterations = 500;
            }),
        ),
        (
            "no initial prior, fixed 3",
            Box::new(|o| o.bundle.fix_initial_for = 3),
        ),
    ];
    for (name, f) in variants {
        let mut options = MapperOptions::default();
        f(&mut options);
        let out = run_mapper(
            &scene.db,
            &scene.cloud,
            ImageId(1),
            &init,
            &options,
            &mut |_, _| {},
        )
        .unwrap();
        let err = max_centre_error(&out.reconstruction, &scene.gt);
        eprintln!(
            "{name}: {}/{} registered, {} points, reprojection {:.3} px, max centre error {:.4} m",
            out.report.num_registered,
            out.report.num_images,
            out.report.num_points,
            out.report.mean_reprojection_error_px,
            err
        );
    }
}

#[test]
fn options_file_and_command_line_merge() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("map.toml");
    std::fs::write(
        &file,
        "database = \"a.db\"\nlidar = \"m.ply\"\noutput = \"out\"\ninit_image = 3\n\
         init_pose = \"1,2,3,0,0,90\"\noutput_type = \"binary\"\nimage_path = \"photos\"\n\
         input_units = \"us-ft\"\n[mapper]\nseed = 5\n[mapper.register]\nmax_error_px = 3.0\n",
    )
    .unwrap();
    let args = MapArgs {
        options: Some(file.clone()),
        output: Some(PathBuf::from("cli-out")),
        seed: Some(9),
        ..Default::default()
    };
    let c = args.config().unwrap();
    assert_eq!(c.database, PathBuf::from("a.db"));
    assert_eq!(c.output, PathBuf::from("cli-out"));
    assert_eq!(c.init_images, vec!["3".to_string()]);
    assert_eq!(c.image_path, Some(PathBuf::from("photos")));
    assert_eq!(c.options.seed, 9);
    assert_eq!(c.options.register.max_error_px, 3.0);
    assert_eq!(c.format, colmap_lidar::io::model::ModelFormat::Binary);
    assert_eq!(
        c.input_units,
        colmap_lidar::map::io::InputUnits::UsSurveyFoot
    );
    let feet = MapArgs {
        input_units: Some("ft".into()),
        ..args.clone()
    };
    assert_eq!(
        feet.config().unwrap().input_units,
        colmap_lidar::map::io::InputUnits::Foot
    );
    let bad = MapArgs {
        input_units: Some("yards".into()),
        ..args.clone()
    };
    let err = format!("{:#}", bad.config().unwrap_err());
    assert!(
        err.contains("--input-units") && err.contains("yards"),
        "{err}"
    );
    assert!((c.init_poses[0].to_degrees_array()[5] - 90.0).abs() < 1e-12);
    // One initial image per group: lists in the file, repeated flags on the
    // command line; as many poses as images, or none.
    std::fs::write(
        &file,
        "database = \"a.db\"\nlidar = \"m.ply\"\noutput = \"out\"\ninit_image = [\"a.png\", 7]\n\
         init_pose = [\"1,2,3,0,0,90\", \"4,5,6,0,0,-90\"]\n",
    )
    .unwrap();
    let c = args.config().unwrap();
    assert_eq!(c.init_images, vec!["a.png".to_string(), "7".to_string()]);
    assert_eq!(c.input_units, colmap_lidar::map::io::InputUnits::Auto);
    assert_eq!(c.init_poses[1].to_degrees_array()[..3], [4.0, 5.0, 6.0]);
    // Poses as arrays of numbers, one or a list; other values say what is
    // expected.
    for (poses, images) in [
        ("[1, 2.5, 3, 0, 0, 90]", "\"a.png\""),
        (
            "[[1, 2.5, 3, 0, 0, 90], \"4,5,6,0,0,-90\"]",
            "[\"a.png\", 7]",
        ),
    ] {
        std::fs::write(
            &file,
            format!("database = \"a.db\"\nlidar = \"m.ply\"\noutput = \"out\"\ninit_image = {images}\ninit_pose = {poses}\n"),
        )
        .unwrap();
        let c = args.config().unwrap();
        assert_eq!(c.init_poses[0].to_degrees_array()[..3], [1.0, 2.5, 3.0]);
        assert!((c.init_poses[0].to_degrees_array()[5] - 90.0).abs() < 1e-12);
    }
    // An empty list: no pose (each image's known pose).
    std::fs::write(
        &file,
        "database = \"a.db\"\nlidar = \"m.ply\"\noutput = \"out\"\ninit_pose = []\n",
    )
    .unwrap();
    assert!(args.config().unwrap().init_poses.is_empty());
    for (poses, says) in [
        ("true", "[x, y, z, roll, pitch, yaw]"),
        ("[[1, \"a\", 3, 0, 0, 90]]", "must be numbers"),
    ] {
        std::fs::write(
            &file,
            format!(
                "database = \"a.db\"\nlidar = \"m.ply\"\noutput = \"out\"\ninit_pose = {poses}\n"
            ),
        )
        .unwrap();
        let err = format!("{:#}", args.config().unwrap_err());
        assert!(err.contains(says), "{poses}: {err}");
    }
    let one_pose = MapArgs {
        init_image: vec!["a.png".into(), "b.png".into()],
        init_pose: vec!["1,2,3,0,0,90".into()],
        ..args.clone()
    };
    let err = format!("{:#}", one_pose.config().unwrap_err());
    assert!(err.contains("1 --init-pose for 2 --init-image"), "{err}");
    let no_pose = MapArgs {
        init_pose: Vec::new(),
        ..one_pose
    };
    std::fs::write(
        &file,
        "database = \"a.db\"\nlidar = \"m.ply\"\noutput = \"out\"\n",
    )
    .unwrap();
    assert_eq!(no_pose.config().unwrap().init_poses.len(), 0);
    std::fs::write(
        &file,
        "database = \"a.db\"\nlidar = \"m.ply\"\noutput = \"out\"\ninit_pose = [1, 2]\n",
    )
    .unwrap();
    let err = format!(
        "{:#}",
        MapArgs {
            options: Some(file.clone()),
            ..Default::default()
        }
        .config()
        .unwrap_err()
    );
    assert!(err.contains("expected six numbers"), "{err}");
    // Unknown keys and bad values are errors naming the problem.
    std::fs::write(&file, "[mapper.register]\nmax_eror_px = 3.0\n").unwrap();
    let err = format!("{:#}", args.config().unwrap_err());
    assert!(err.contains("max_eror_px"), "{err}");
    std::fs::write(&file, "database = \"a.db\"\nlidar = \"m.ply\"\n[mapper.filter]\nmax_reprojection_error_px = -1.0\n").unwrap();
    let err = format!("{:#}", args.config().unwrap_err());
    assert!(err.contains("filter.max_reprojection_error_px"), "{err}");
    // Missing required paths.
    let err = format!("{:#}", MapArgs::default().config().unwrap_err());
    assert!(err.contains("--database"), "{err}");
    // A model to extend, from the file; an initial pose beside it, or
    // holding existing images without one, is an error.
    std::fs::write(
        &file,
        "database = \"a.db\"\nlidar = \"m.ply\"\noutput = \"out\"\n\
         input_model = \"sparse/0\"\nfix_existing_images = true\n",
    )
    .unwrap();
    let c = args.config().unwrap();
    assert_eq!(c.input_model, Some(PathBuf::from("sparse/0")));
    assert!(c.fix_existing_images);
    let with_pose = MapArgs {
        init_pose: vec!["1,2,3,0,0,90".into()],
        ..args.clone()
    };
    let err = format!("{:#}", with_pose.config().unwrap_err());
    assert!(err.contains("not used with --input-model"), "{err}");
    let hold_only = MapArgs {
        database: Some("a.db".into()),
        lidar: Some("m.ply".into()),
        output: Some("out".into()),
        fix_existing_images: true,
        ..Default::default()
    };
    let err = format!("{:#}", hold_only.config().unwrap_err());
    assert!(err.contains("needs --input-model"), "{err}");
}

#[test]
fn toy_room_projection_associations_and_report() {
    let scene = toy(14, 0.3, 0.03, 4);
    let mut options = MapperOptions::default();
    options.association.kind = AssociationKind::Projection;
    let (out, err) = map_toy(&scene, &options);
    eprintln!("toy room, projection associations: max centre error {err:.4} m");
    assert_eq!(out.report.num_registered, 14);
    assert!(err < 0.03, "max centre error {err} m");
    let report = &out.report;
    assert_eq!(report.association, "projection+nearest");
    // Every solve's planes add up by kind; short tracks got projection planes.
    for s in &report.solves {
        assert_eq!(
            s.num_planes,
            s.num_projection_planes + s.num_nearest_planes + s.num_ground_planes
        );
        assert!(s.plane_distance_before_m.median <= s.plane_distance_before_m.mean * 10.0 + 1e-12);
    }
    assert!(report.solves.iter().any(|s| s.num_projection_planes > 0));
    // The last solve leaves the points on their planes (the toy map is exact)
    // and the reprojection error near the keypoint noise.
    let last = report.solves.last().unwrap();
    assert!(last.plane_distance_after_m.median < 0.01, "{last:?}");
    assert!(last.reprojection_after_px.mean < 0.7, "{last:?}");
    assert!(last.reprojection_after_px.count > 1000);
    // Per image: association counts and the mean distance of its points.
    for rec in report.images.iter().filter(|r| r.registered) {
        let tied = rec.num_projection_planes + rec.num_nearest_planes + rec.num_ground_planes;
        assert!(tied > 0 && tied <= rec.num_observations, "{rec:?}");
        assert!(rec.mean_plane_distance_m.unwrap() < 0.02, "{rec:?}");
    }
}

/// The keypoints' refinement reads the registered images after mapping,
/// within its memory budget: from a folder without the images nothing is
/// read or refined and the model is the one mapped without a folder; over
/// the budget nothing is read at all.
#[test]
fn toy_room_keypoint_refinement_reads_the_images_within_its_budget() {
    let scene = toy(14, 0.3, 0.03, 4);
    let init = scene.init_pose.to_cam_from_world();
    let empty = tempfile::tempdir().unwrap();
    let run = |image_dir: Option<&std::path::Path>, options: &MapperOptions| {
        let inputs = MapperInputs {
            db: &scene.db,
            cloud: &scene.cloud,
            known_poses: &BTreeMap::new(),
            held_cameras: &BTreeSet::new(),
            run_log: None,
            image_dir,
        };
        run_mapper_with_priors(inputs, ImageId(1), &init, options, &mut |_, _| {}).unwrap()
    };
    let options = MapperOptions::default();
    let without = run(None, &options);
    assert!(without.report.keypoint_refinement.is_none());
    let with = run(Some(empty.path()), &options);
    assert_eq!(with.report.num_registered, 14);
    let record = with.report.keypoint_refinement.as_ref().unwrap();
    let cam = scene.db.cameras.values().next().unwrap();
    let megabytes = 14.0 * f64::from(cam.width * cam.height) / 1_048_576.0;
    assert!(
        (record.image_memory_mb - megabytes).abs() < 1e-9,
        "{record:?}"
    );
    assert!(!record.over_memory_budget);
    assert_eq!((record.images_read, record.refined), (0, 0), "{record:?}");
    for (id, img) in &without.reconstruction.images {
        assert_eq!(
            img.cam_from_world,
            with.reconstruction.images[id].cam_from_world
        );
    }
    // A budget below the registered images' size: nothing is read.
    let mut small = MapperOptions::default();
    small.keypoints.max_image_memory_mb = 0.5 * megabytes;
    let over = run(Some(empty.path()), &small);
    let record = over.report.keypoint_refinement.as_ref().unwrap();
    assert!(record.over_memory_budget, "{record:?}");
    assert_eq!((record.images_read, record.observations), (0, 0));
    assert_eq!(over.report.num_registered, 14);
}

#[test]
fn toy_room_image_with_too_few_matches_is_placed_at_its_known_pose() {
    let mut scene = toy(14, 0.3, 0.0, 5);
    // Image 9 keeps 20 matches per pair: too few for PnP (30 inliers).
    let lonely = ImageId(9);
    for g in &mut scene.db.two_view_geometries {
        if g.image_id1 == lonely || g.image_id2 == lonely {
            g.inlier_matches.truncate(20);
        }
    }
    // Weak priors (10 px-equivalents per metre, 1 per degree): the image's
    // own matches decide where it ends up.
    let mut options = MapperOptions::default();
    options.bundle.prior_position_weight = 10.0;
    options.bundle.prior_rotation_weight = 1.0;
    let init = scene.init_pose.to_cam_from_world();
    let without = run_mapper(
        &scene.db,
        &scene.cloud,
        ImageId(1),
        &init,
        &options,
        &mut |_, _| {},
    )
    .unwrap();
    assert!(without
        .reconstruction
        .images
        .get(&lonely)
        .is_none_or(|i| !i.is_registered()));
    // Its true pose, 5 cm and 1 deg off, as a known pose.
    let truth = scene.gt[&lonely];
    let mut body = BodyPose::from_cam_from_world(&truth);
    body.position_m += Vector3::new(0.05, 0.0, 0.0);
    body.yaw_rad += 1f64.to_radians();
    let known = BTreeMap::from([(
        lonely,
        KnownPose {
            cam_from_world: body.to_cam_from_world(),
            has_rotation: true,
        },
    )]);
    let inputs = MapperInputs {
        db: &scene.db,
        cloud: &scene.cloud,
        known_poses: &known,
        held_cameras: &BTreeSet::new(),
        run_log: None,
        image_dir: None,
    };
    let out = run_mapper_with_priors(inputs, ImageId(1), &init, &options, &mut |_, _| {}).unwrap();
    let rec = out
        .report
        .images
        .iter()
        .find(|r| r.image_id == lonely.0)
        .unwrap();
    assert!(rec.registered && rec.placed_by_prior, "{rec:?}");
    let placed = out.reconstruction.images[&lonely].cam_from_world.unwrap();
    let centre_error = (placed.camera_center() - truth.camera_center()).norm();
    // Refined from the known pose against its few 2D-3D matches (the
    // prior alone would leave it 5 cm off).
    assert!(
        centre_error < 0.02,
        "centre error {centre_error} m, {rec:?}"
    );
    // The other images are unaffected.
    assert_eq!(out.report.num_registered, 14);
}

#[test]
fn toy_room_refines_a_wrong_focal_length_and_holds_the_principal_point() {
    // Keypoints made with f = 450 px; the database says 454.5 (1 % off).
    let mut scene = toy(14, 0.3, 0.0, 3);
    let camera = scene.db.cameras.get_mut(&CameraId(1)).expect("camera 1");
    camera.params[0] = 454.5;
    let mut fixed = MapperOptions::default();
    fixed.bundle.refine_intrinsics = IntrinsicsRefinement::Fixed;
    let (out_fixed, err_fixed) = map_toy(&scene, &fixed);
    let mut refine = MapperOptions::default();
    refine.bundle.refine_intrinsics = IntrinsicsRefinement::Final;
    let (out, err) = map_toy(&scene, &refine);
    // The default finds the given focal length 1 % off (one solve with it
    // free after the final rounds) and refines it.
    let (out_auto, err_auto) = map_toy(&scene, &MapperOptions::default());
    let rec = &out_auto.report.intrinsics[0];
    let probe = rec
        .probe_focal_change
        .expect("a given focal length is probed");
    assert!((-0.0105..-0.0085).contains(&probe), "{rec:?}");
    assert_eq!(
        (rec.camera_id, rec.refined.as_str(), rec.database_params[0]),
        (1, "final rounds", 454.5)
    );
    assert!((rec.final_params[0] - 450.0).abs() < 0.9, "{rec:?}");
    // Refined to the end: its uncertainty is in the report, and the truth
    // lies within a few sigmas of it (measured: 450.022 px, sigma 0.132 px,
    // cluster-robust 0.138 px, so 0.17 sigma off).
    let sigma = rec.focal_sigma_px.expect("a refined focal length's sigma");
    let clustered = rec.clustered_focal_sigma_px.expect("cluster-robust too");
    assert!(sigma > 0.0 && clustered > 0.0, "{rec:?}");
    assert!(
        (rec.final_params[0] - 450.0).abs() < 4.0 * sigma.max(clustered),
        "{rec:?}"
    );
    // Per parameter: the focal length's the same, the held principal
    // point's none.
    let params = rec.params_sigma.as_ref().expect("per parameter");
    assert_eq!(params.len(), rec.final_params.len());
    assert_eq!(params[0], Some(sigma));
    assert_eq!((params[1], params[2]), (None, None), "{rec:?}");
    assert!((rec.focal_change - (rec.final_params[0] / 454.5 - 1.0)).abs() < 1e-15);
    assert!(err_auto < err_fixed, "{err_auto} vs {err_fixed}");
    // Given right, it is held: the probe moves it less than 0.1 % and the
    // model is the one of the rounds with it held.
    let right = toy(14, 0.3, 0.0, 3);
    let (held, _) = map_toy(&right, &MapperOptions::default());
    let rec = &held.report.intrinsics[0];
    assert!(rec.probe_focal_change.unwrap().abs() < 0.001, "{rec:?}");
    assert_eq!(rec.refined, "held");
    assert_eq!(
        (rec.focal_sigma_px, rec.clustered_focal_sigma_px),
        (None, None)
    );
    assert_eq!(rec.params_sigma, None);
    // The probe (the last solve, discarded) is capped; Ceres counts its
    // starting point as one successful step.
    let probe_solve = held.report.solves.last().expect("solves");
    let cap = MapperOptions::default().bundle.probe_max_iterations;
    assert!(
        probe_solve.discarded && probe_solve.iterations <= cap + 1,
        "{probe_solve:?}"
    );
    assert_eq!(held.reconstruction.cameras[&CameraId(1)].params[0], 450.0);
    let (fixed_right, _) = map_toy(&right, &fixed);
    assert_eq!(held.reconstruction, fixed_right.reconstruction);
    let refined = &out.reconstruction.cameras[&CameraId(1)];
    eprintln!(
        "toy room, focal 1 % off: refined f = {:.2} px (true 450), max centre error {err:.4} m \
         (held at 454.5: {err_fixed:.4} m)",
        refined.params[0]
    );
    assert_eq!(out.report.num_registered, 14);
    assert_eq!(
        out_fixed.reconstruction.cameras[&CameraId(1)].params[0],
        454.5
    );
    assert!(
        (refined.params[0] - 450.0).abs() < 0.9,
        "refined f {}",
        refined.params[0]
    );
    assert_eq!(
        refined.params[1..3],
        [320.0, 240.0],
        "principal point moved"
    );
    assert!(err < err_fixed, "{err} vs {err_fixed}");
}

/// The toy room (14 images) with a second camera, whose focal length is
/// COLMAP's guess (768 px for 450) and that has no distortion, for the images
/// whose id `uses_it` picks; camera 1 (the true one) is given.
fn toy_with_guessed_camera(uses_it: impl Fn(u32) -> bool) -> Toy {
    let mut scene = toy(14, 0.3, 0.0, 3);
    let mut guessed = scene.db.cameras[&CameraId(1)].clone();
    guessed.id = CameraId(2);
    guessed.params[0] = 768.0;
    guessed.params[3] = 0.0;
    scene.db.cameras.insert(CameraId(2), guessed);
    scene.db.cameras_without_focal_prior.insert(CameraId(2));
    for (id, image) in scene.db.images.iter_mut() {
        if uses_it(id.0) {
            image.camera_id = CameraId(2);
        }
    }
    scene
}

/// Camera 2's report record and final intrinsics.
fn camera_two(
    out: &colmap_lidar::sfm::MapperOutput,
) -> (&colmap_lidar::sfm::report::IntrinsicsRecord, &Camera) {
    let rec = out
        .report
        .intrinsics
        .iter()
        .find(|r| r.camera_id == 2)
        .expect("camera 2 has a record");
    (rec, &out.reconstruction.cameras[&CameraId(2)])
}

/// Two cameras: the initial pair's is given (the true one), the odd images
/// after the first are taken with a second camera whose focal length is
/// COLMAP's guess (768 px for 450). Its first image's PnP sweeps focal
/// lengths and self-calibration starts there. (The toy converges from the
/// guess too: this checks the sweep's value and where it is used.)
#[test]
fn toy_room_second_guessed_camera_starts_from_the_pnp_sweep() {
    // Odd images after the first: the initial pair (1 and its neighbour 2)
    // is of the given camera.
    let scene = toy_with_guessed_camera(|id| id % 2 == 1 && id > 1);
    let (out, err) = map_toy(&scene, &MapperOptions::default());
    assert_eq!(out.report.init.as_ref().map(|i| i.second_image), Some(2));
    let (rec, refined) = camera_two(&out);
    eprintln!(
        "toy room, second camera guessed at 768 px: PnP sweep {:?} px, refined f = {:.3} px, k = {:.4} (true 450, 0.01), max centre error {err:.4} m",
        rec.focal_from_points_px, refined.params[0], refined.params[3]
    );
    assert_eq!(out.report.num_registered, 14);
    assert_eq!(rec.refined, "every solve");
    let from_points = rec.focal_from_points_px.expect("the PnP sweep ran");
    assert!((from_points - 450.0).abs() < 0.1 * 450.0, "{from_points}");
    assert!(rec.focal_from_map_px.is_none());
    assert!((refined.params[0] - 450.0).abs() < 0.9, "{refined:?}");
    assert!(err < 0.01, "max centre error {err} m");
    // The given camera keeps the map's sweep out of it.
    let first = &out.report.intrinsics[0];
    assert_eq!(first.camera_id, 1);
    assert!(first.focal_from_map_px.is_none() && first.focal_from_points_px.is_none());
}

/// The initial pair's second image is of a guessed camera (768 px for 450)
/// other than the initial image's (given): its focal length is swept by PnP
/// against the initial image's map points before it is placed.
#[test]
fn toy_room_initial_pairs_guessed_camera_starts_from_the_pnp_sweep() {
    let scene = toy_with_guessed_camera(|id| id % 2 == 0);
    let (out, err) = map_toy(&scene, &MapperOptions::default());
    let init = out.report.init.as_ref().expect("initialised");
    assert_eq!(init.second_image, 2);
    let swept = init.focal_from_points_px.get(&2).copied();
    let (rec, refined) = camera_two(&out);
    eprintln!(
        "toy room, initial pair's second camera guessed at 768 px: PnP sweep {swept:?} px, refined f = {:.3} px (true 450), max centre error {err:.4} m",
        refined.params[0]
    );
    let swept = swept.expect("the initial pair's PnP sweep ran");
    assert!((swept - 450.0).abs() < 0.1 * 450.0, "{swept}");
    assert_eq!(rec.focal_from_points_px, Some(swept));
    assert_eq!(out.report.num_registered, 14);
    assert!((refined.params[0] - 450.0).abs() < 0.9, "{refined:?}");
    assert!(err < 0.01, "max centre error {err} m");
    // Only the guessed camera is swept.
    assert_eq!(init.focal_from_points_px.len(), 1);
}

/// One camera per image, all at the same guess (COLMAP's extractor without
/// `single_camera`): by default they share one set of intrinsics, refined
/// from every image's points; each refined alone is not (or worse).
#[test]
fn toy_room_shares_identical_cameras() {
    let mut scene = toy(14, 0.3, 0.0, 3);
    let mut camera = scene.db.cameras[&CameraId(1)].clone();
    camera.params[0] = 500.0;
    camera.params[3] = 0.0;
    scene.db.cameras.clear();
    for (id, image) in scene.db.images.iter_mut() {
        let cam = CameraId(id.0);
        image.camera_id = cam;
        scene.db.cameras.insert(
            cam,
            Camera {
                id: cam,
                ..camera.clone()
            },
        );
        scene.db.cameras_without_focal_prior.insert(cam);
    }
    let (shared, err_shared) = map_toy(&scene, &MapperOptions::default());
    let focals: Vec<f64> = shared
        .reconstruction
        .cameras
        .values()
        .map(|c| c.params[0])
        .collect();
    assert_eq!(focals.len(), 14);
    assert!(focals.iter().all(|&f| f == focals[0]), "{focals:?}");
    assert!((focals[0] - 450.0).abs() < 0.9, "{focals:?}");
    assert!(err_shared < 0.01, "max centre error {err_shared} m");
    let mut alone = MapperOptions::default();
    alone.bundle.share_identical_intrinsics = false;
    let init = scene.init_pose.to_cam_from_world();
    if let Ok(out) = run_mapper(
        &scene.db,
        &scene.cloud,
        ImageId(1),
        &init,
        &alone,
        &mut |_, _| {},
    ) {
        let err_alone = max_centre_error(&out.reconstruction, &scene.gt);
        let spread = out
            .reconstruction
            .cameras
            .values()
            .map(|c| (c.params[0] - 450.0).abs())
            .fold(0.0, f64::max);
        eprintln!(
            "toy room, 14 cameras at 500 px: shared f {:.3}, error {err_shared:.4} m; \
             alone: largest focal error {spread:.2} px, error {err_alone:.4} m",
            focals[0]
        );
        assert!(
            spread > 1.0 || err_alone > err_shared,
            "{spread} {err_alone}"
        );
    }
}

#[test]
fn toy_room_self_calibrates_a_camera_the_database_marks_as_uncalibrated() {
    // Keypoints made with f = 450 px, k = 0.01; the database holds a guess
    // (f 20 % off, no distortion) and says so (prior_focal_length = 0), as
    // COLMAP does when it finds no focal length.
    let mut scene = toy(14, 0.3, 0.0, 3);
    let camera = scene.db.cameras.get_mut(&CameraId(1)).expect("camera 1");
    camera.params[0] = 540.0;
    camera.params[3] = 0.0;
    scene.db.cameras_without_focal_prior.insert(CameraId(1));
    let (out, err) = map_toy(&scene, &MapperOptions::default());
    let refined = &out.reconstruction.cameras[&CameraId(1)];
    eprintln!(
        "toy room, uncalibrated (f 540, k 0): refined f = {:.3} px, k = {:.4} (true 450, 0.01), \
         max centre error {err:.4} m",
        refined.params[0], refined.params[3]
    );
    assert_eq!(out.report.num_registered, 14);
    assert!((refined.params[0] - 450.0).abs() < 0.9, "{refined:?}");
    assert!((refined.params[3] - 0.01).abs() < 0.003, "{refined:?}");
    // COLMAP's guess of the principal point (the centre, here the truth) is
    // refined with the focal length and stays near it.
    for (k, want) in [(1, 320.0), (2, 240.0)] {
        assert!(
            (refined.params[k] - want).abs() < 0.5,
            "principal point moved: {refined:?}"
        );
    }
    assert!(err < 0.01, "max centre error {err} m");
    assert_eq!(out.report.intrinsics[0].refined, "every solve");
    // Self-calibration started from the focal length the map and the
    // initial pair agree on, much nearer the truth than the guess.
    let from_map = out.report.intrinsics[0]
        .focal_from_map_px
        .expect("the map gives a focal length");
    eprintln!("focal length from the map: {from_map:.1} px");
    assert!((from_map - 450.0).abs() < 0.25 * 90.0, "{from_map}");
    // With `never`, COLMAP's behaviour, it stays where the database has it.
    let mut never = MapperOptions::default();
    never.bundle.refine_principal_point = PrincipalPointRefinement::Never;
    let (held_centre, _) = map_toy(&scene, &never);
    assert_eq!(
        held_centre.reconstruction.cameras[&CameraId(1)].params[1..3],
        [320.0, 240.0]
    );
    // Held at the guess, the same run cannot place the images.
    let mut fixed = MapperOptions::default();
    fixed.bundle.refine_intrinsics = IntrinsicsRefinement::Fixed;
    let init = scene.init_pose.to_cam_from_world();
    if let Ok(out) = run_mapper(
        &scene.db,
        &scene.cloud,
        ImageId(1),
        &init,
        &fixed,
        &mut |_, _| {},
    ) {
        let err_fixed = max_centre_error(&out.reconstruction, &scene.gt);
        assert!(
            err_fixed > 5.0 * err,
            "held: {err_fixed} m, refined: {err} m"
        );
    }
}

/// The toy room's map with only the points where `keep` (room coordinates,
/// metres) holds.
fn cut_cloud(cloud: &PointCloud, keep: impl Fn([f32; 3]) -> bool) -> PointCloud {
    let normals = cloud.normals.as_ref().expect("the toy map has normals");
    let (points, normals): (Vec<_>, Vec<_>) = cloud
        .points
        .iter()
        .zip(normals)
        .filter(|(p, _)| keep(**p))
        .map(|(p, n)| (*p, *n))
        .unzip();
    PointCloud {
        origin: cloud.origin,
        points,
        normals: Some(normals),
        planarity: None,
    }
}

/// A map that covers only the part x > 1 m of the room the walk sees: the
/// full run is accepted as partly mapped, and so is the model of its first
/// half when it is extended with the rest (held or free), where it was
/// refused for its fit over all its points (52 %, under 60 %). A model moved
/// 0.3 m off the cut map is still refused, with the coverage in the error.
#[test]
fn toy_room_partly_mapped_model_is_extended() {
    use colmap_lidar::sfm::existing::match_to_database;
    use colmap_lidar::sfm::{extend_model, MapperError};
    let mut scene = toy(16, 0.3, 0.03, 2);
    scene.cloud = cut_cloud(&scene.cloud, |p| p[0] > 1.0);
    let options = MapperOptions::default();
    let (full, err) = map_toy(&scene, &options);
    let report = &full.report;
    eprintln!(
        "toy room, map cut at x = 1 m: {}/{} registered, max error {err:.4} m, fit {:?}, coverage {:?}, covered fit {:?}, ratio {:?}",
        report.num_registered,
        report.num_images,
        report.fit_share,
        report.map_coverage_share,
        report.covered_fit_share,
        report.similarity_constraint.as_ref().map(|c| c.ratio)
    );
    assert!(report.partial_map);
    assert_eq!(report.num_registered, 16);
    assert!(err < 0.02, "max centre error {err} m");
    let half = crate::common::part_of_model(&full.reconstruction, |img| img.id.0 <= 8);
    let inputs = MapperInputs {
        db: &scene.db,
        cloud: &scene.cloud,
        known_poses: &BTreeMap::new(),
        held_cameras: &BTreeSet::new(),
        run_log: None,
        image_dir: None,
    };
    for hold in [true, false] {
        let model = match_to_database(&half, &scene.db, hold).unwrap();
        let out = extend_model(inputs, &model, &options, &mut |_, _| {}).unwrap();
        let input = out.report.input_model.as_ref().expect("an input model");
        let err = max_centre_error(&out.reconstruction, &scene.gt);
        eprintln!(
            "  half extended (held: {hold}): {}/16 registered, max error {err:.4} m, input on the map {:.3}, covered {:.3}",
            out.report.num_registered, input.points_on_seen_surface_share, input.map_coverage_share
        );
        assert!(input.partial_map && out.report.partial_map);
        assert!(input.points_on_seen_surface_share < options.association.min_points_on_map_share);
        assert!((0.1..0.9).contains(&input.map_coverage_share));
        // Accepted on a finished run's terms (measured 0.99 and 0.09).
        assert!(input.covered_fit_share.unwrap() >= 0.9, "{input:?}");
        assert!(
            input.covered_similarity_constraint_ratio.unwrap() >= 1e-2,
            "{input:?}"
        );
        assert_eq!(out.report.num_registered, 16);
        assert!(err < 0.02, "max centre error {err} m");
    }
    // The whole partly mapped model, held: no new image, no final solve,
    // the fit measured on the covered points' nearest planes; kept as it came.
    let model = match_to_database(&full.reconstruction, &scene.db, true).unwrap();
    let out = extend_model(inputs, &model, &options, &mut |_, _| {}).unwrap();
    assert!(out.report.partial_map);
    let ratio = out.report.similarity_constraint.as_ref().unwrap().ratio;
    assert!(ratio >= 1e-2, "{ratio}");
    for img in full.reconstruction.registered_images() {
        assert_eq!(
            out.reconstruction.pose(img.id),
            img.cam_from_world,
            "{}",
            img.name
        );
    }
    // The same half moved 0.3 m along y: off the cut map's surfaces.
    let mut moved = half.clone();
    let shift = Rigid3::new(UnitQuaternion::identity(), Vector3::new(0.0, 0.3, 0.0));
    for img in moved.images.values_mut() {
        let pose = img.cam_from_world.expect("registered");
        img.cam_from_world = Some(pose.compose(&shift.inverse()));
    }
    for p in moved.points3d.values_mut() {
        p.xyz = shift.transform_point(&p.xyz);
    }
    let model = match_to_database(&moved, &scene.db, true).unwrap();
    match extend_model(inputs, &model, &options, &mut |_, _| {}) {
        Err(e @ MapperError::InputModelOffMap { .. }) => {
            let msg = e.to_string();
            eprintln!("  moved 0.3 m: {msg}");
            // The coverage the half measured in place (52 %): a shift along
            // the wall keeps what the map shows at the features.
            let coverage: f64 = msg
                .split("the map shows a surface at the features of ")
                .nth(1)
                .and_then(|rest| rest.split(" %").next())
                .and_then(|n| n.parse().ok())
                .expect("the coverage in the message");
            assert!((30.0..70.0).contains(&coverage), "{msg}");
            assert!(
                msg.contains("accepted when it covers at least 10 %"),
                "{msg}"
            );
        }
        other => panic!(
            "a model moved off the map was taken: {:?}",
            other.map(|o| o.report.num_registered)
        ),
    }
}

/// Adds to `db` a copy of image `from` (its camera and keypoints, no
/// pairs) as image `id` named `name`.
fn copy_image(db: &mut DatabaseSnapshot, from: ImageId, id: ImageId, name: &str) {
    let mut img = db.images[&from].clone();
    img.id = id;
    img.name = name.to_owned();
    db.images.insert(id, img);
    let keypoints = db.keypoints[&from].clone();
    db.keypoints.insert(id, keypoints);
}

/// Adds to `db` a copy of each verified pair whose two images `copy_of`
/// maps to copies, between those copies; how many.
fn copy_pairs(db: &mut DatabaseSnapshot, copy_of: impl Fn(ImageId) -> Option<ImageId>) -> usize {
    let copies: Vec<TwoViewGeometry> = db
        .two_view_geometries
        .iter()
        .filter_map(|g| {
            Some(TwoViewGeometry {
                image_id1: copy_of(g.image_id1)?,
                image_id2: copy_of(g.image_id2)?,
                ..g.clone()
            })
        })
        .collect();
    let n = copies.len();
    db.two_view_geometries.extend(copies);
    n
}

/// Images the run cannot register say why, in `report.json` and in one
/// line: a copy of images 1-3 matched only among themselves (another group),
/// an image without any verified pair, and one matched to the model by 3
/// matches (too few of its points for a pose).
#[test]
fn toy_room_says_why_images_are_not_registered() {
    use colmap_lidar::sfm::report::NotRegistered;
    let mut scene = toy(10, 0.3, 0.03, 1);
    let db = &mut scene.db;
    for id in 1..=3 {
        copy_image(
            db,
            ImageId(id),
            ImageId(100 + id),
            &format!("copy_{id}.png"),
        );
    }
    let copied = copy_pairs(db, |id| (id.0 <= 3).then_some(ImageId(100 + id.0)));
    assert_eq!(copied, 3);
    copy_image(db, ImageId(4), ImageId(200), "lone.png");
    copy_image(db, ImageId(5), ImageId(300), "weak.png");
    db.two_view_geometries.push(TwoViewGeometry {
        image_id1: ImageId(5),
        image_id2: ImageId(300),
        config: 2,
        inlier_matches: vec![[0, 0], [1, 1], [2, 2]],
        fundamental: None,
        essential: None,
    });
    // `inspect` shows the groups before any run.
    let text = colmap_lidar::commands::inspect::summary(&scene.db, false);
    assert!(
        text.contains("Image groups  2 (11 images from id 1 (img_000.png), 3 images from id 101 (copy_1.png)): no verified pair links one to another")
            && text.contains("; 1 image in none (no verified pair)"),
        "{text}"
    );
    let (out, _) = map_toy(&scene, &MapperOptions::default());
    let report = &out.report;
    assert_eq!(report.num_registered, 10);
    let why = |name: &str| {
        let rec = report.images.iter().find(|r| r.name == name).unwrap();
        (rec.registered, rec.not_registered.clone())
    };
    for id in 1..=10 {
        assert_eq!(why(&format!("img_{:03}.png", id - 1)), (true, None));
    }
    for id in 1..=3 {
        assert_eq!(
            why(&format!("copy_{id}.png")),
            (
                false,
                Some(NotRegistered::OtherGroup {
                    group_size: 3,
                    group_first_image_id: 101
                })
            )
        );
    }
    assert_eq!(why("lone.png"), (false, Some(NotRegistered::NoMatches)));
    match why("weak.png") {
        (false, Some(NotRegistered::TooFewModelPoints { points_seen })) => {
            assert!(points_seen <= 3, "{points_seen}")
        }
        other => panic!("weak.png: {other:?}"),
    }
    let summary = report.not_registered_summary().expect("a summary");
    eprintln!("{summary}");
    assert!(summary.starts_with("5 of 15 images not registered: 1 without verified matches to any image (lone.png); 3 in 1 group matched among themselves but not to the model's images (3 images from id 101 (copy_1.png))"), "{summary}");
    assert!(
        summary.contains(
            "1 in the model's group of images but never seeing the 4 of its points a pose needs (weak.png)"
        ),
        "{summary}"
    );
    let json = serde_json::to_value(&report.images).unwrap();
    let copy = json
        .as_array()
        .unwrap()
        .iter()
        .find(|r| r["name"] == "copy_2.png")
        .unwrap();
    assert_eq!(copy["not_registered"]["reason"], "other_group");
    assert_eq!(copy["not_registered"]["group_size"], 3);
}

/// One run from one initial image per group (`map_groups`): the toy's 10
/// images and a copy of them under other names and ids and with their own
/// camera (identical in the database, as COLMAP gives each image one), no
/// verified match between the two, a third group of 3 copies with no
/// initial image and an image without any pair. One model with both groups
/// at the truth, one set of intrinsics (the focal length, given 1 % off,
/// refined by the first group's run and held by the second's for the
/// identical camera), a report over all 24 images with a record per run;
/// two initial images in one group, or one without any verified pair, are
/// refused; a group whose run fails is left out with its error, the others
/// kept.
#[test]
fn toy_room_groups_mapped_in_one_run() {
    use colmap_lidar::sfm::report::NotRegistered;
    use colmap_lidar::sfm::{map_groups, GroupStart, MapperError};
    let mut scene = toy(10, 0.3, 0.03, 4);
    scene.db.cameras.get_mut(&CameraId(1)).unwrap().params[0] = 454.5;
    let db = &mut scene.db;
    let mut twin = db.cameras[&CameraId(1)].clone();
    twin.id = CameraId(2);
    db.cameras.insert(CameraId(2), twin);
    for id in (1..=10).map(ImageId) {
        let copy = ImageId(id.0 + 100);
        copy_image(db, id, copy, &format!("copy_{:03}.png", id.0));
        db.images.get_mut(&copy).unwrap().camera_id = CameraId(2);
        scene.gt.insert(copy, scene.gt[&id]);
    }
    copy_pairs(db, |id| Some(ImageId(id.0 + 100)));
    for id in (1..=3).map(ImageId) {
        copy_image(
            db,
            id,
            ImageId(id.0 + 200),
            &format!("third_{:03}.png", id.0),
        );
    }
    copy_pairs(db, |id| (id.0 <= 3).then_some(ImageId(id.0 + 200)));
    copy_image(db, ImageId(4), ImageId(300), "lone.png");
    let pose = scene.init_pose.to_cam_from_world();
    let start = |id: u32| GroupStart {
        image: ImageId(id),
        cam_from_world: pose,
    };
    let known = BTreeMap::new();
    let inputs = MapperInputs {
        db: &scene.db,
        cloud: &scene.cloud,
        known_poses: &known,
        held_cameras: &BTreeSet::new(),
        run_log: None,
        image_dir: None,
    };
    let options = MapperOptions::default();
    let mut seen = Vec::new();
    let out = map_groups(
        inputs,
        &[start(1), start(101)],
        None,
        &options,
        &mut |done, total| seen.push((done, total)),
    )
    .unwrap();
    let report = &out.report;
    assert_eq!(
        (report.num_images, report.num_registered),
        (24, 20),
        "{:?}",
        report.groups
    );
    assert_eq!(out.reconstruction.num_registered_images(), 20);
    let err = max_centre_error(&out.reconstruction, &scene.gt);
    assert!(err < 0.03, "max centre error {err} m");
    // Progress counts on over the runs, to all 20.
    assert!(seen.windows(2).all(|w| w[0].0 <= w[1].0), "{seen:?}");
    assert_eq!(seen.last(), Some(&(20, 24)));
    // The runs: the first over its group, the third and the lone image.
    let runs_of = |report: &colmap_lidar::sfm::report::MapReport| {
        report
            .groups
            .iter()
            .map(|g| {
                (
                    g.init_image_id,
                    g.num_images,
                    g.num_registered,
                    g.cameras_held.clone(),
                    g.report.is_some(),
                )
            })
            .collect::<Vec<_>>()
    };
    let runs = runs_of(report);
    assert_eq!(
        runs,
        vec![(1, 14, 10, vec![], false), (101, 10, 10, vec![2], true)]
    );
    // One set of intrinsics: refined by the first run, held by the second
    // for the identical camera; a record for each camera from its run.
    let first = &report.intrinsics[0];
    assert_eq!(
        (first.camera_id, first.refined.as_str()),
        (1, "final rounds")
    );
    assert!((first.final_params[0] - 450.0).abs() < 0.9, "{first:?}");
    let second = report.groups[1].report.as_ref().unwrap();
    assert!(second.options.is_none() && second.groups.is_empty());
    let held = &report.intrinsics[1];
    assert_eq!((held.camera_id, held.refined.as_str()), (2, "held"));
    assert_eq!(held.database_params, first.final_params);
    assert_eq!(held.final_params, first.final_params);
    assert_eq!(second.intrinsics.len(), 1);
    assert_eq!(second.intrinsics[0].camera_id, 2);
    assert_eq!(out.reconstruction.cameras.len(), 2);
    for camera in out.reconstruction.cameras.values() {
        assert_eq!(camera.params, first.final_params);
    }
    // Every image once in the report, in id order, registration indices
    // going on over the runs; the third group and the lone image say why.
    let ids: Vec<u32> = report.images.iter().map(|r| r.image_id).collect();
    let want: Vec<u32> = (1..=10)
        .chain(101..=110)
        .chain(201..=203)
        .chain([300])
        .collect();
    assert_eq!(ids, want);
    let mut order: Vec<usize> = report
        .images
        .iter()
        .filter_map(|r| r.registration_index)
        .collect();
    order.sort_unstable();
    assert_eq!(order, (0..20).collect::<Vec<_>>());
    for rec in &report.images {
        let why = match rec.image_id {
            300 => Some(NotRegistered::NoMatches),
            201.. => Some(NotRegistered::OtherGroup {
                group_size: 3,
                group_first_image_id: 201,
            }),
            _ => None,
        };
        assert_eq!(
            (rec.registered, &rec.not_registered),
            (why.is_none(), &why),
            "{rec:?}"
        );
    }
    let obs: usize = out
        .reconstruction
        .points3d
        .values()
        .map(|p| p.track.len())
        .sum();
    assert_eq!(report.num_observations, obs);
    // The pose uncertainties over both groups' images, each from its run.
    let sigma = |r: &colmap_lidar::sfm::report::MapReport| -> Vec<f64> {
        r.images
            .iter()
            .filter_map(|r| r.pose_uncertainty.as_ref())
            .map(|u| u.centre_sigma_major_m)
            .collect()
    };
    let all = sigma(report);
    assert_eq!(all.len(), 20);
    assert_eq!(&all[10..], &sigma(second)[..]);
    let u = report.pose_uncertainty.as_ref().unwrap();
    assert_eq!(
        u.max_centre_sigma_major_m,
        all.iter().copied().fold(0.0, f64::max)
    );
    assert_eq!(report.num_points, out.reconstruction.points3d.len());
    // Two initial images of one group; one without any verified pair.
    let maps = |starts: &[GroupStart]| map_groups(inputs, starts, None, &options, &mut |_, _| {});
    let fails = |starts: &[GroupStart]| -> MapperError {
        match maps(starts) {
            Ok(_) => panic!("{starts:?} were mapped"),
            Err(e) => e,
        }
    };
    let err = fails(&[start(1), start(5)]);
    assert!(matches!(err, MapperError::SameGroup { .. }), "{err}");
    assert!(
        err.to_string()
            .contains("img_000.png and img_004.png are in one group"),
        "{err}"
    );
    let err = fails(&[start(1), start(300)]);
    assert!(
        err.to_string().contains("lone.png has no verified pair"),
        "{err}"
    );
    // A group whose run fails (its initial pose 30 m outside the room,
    // facing away) is left out, each of its images saying why, and the
    // other group's model is kept; when every run fails, the first's error.
    let away = BodyPose::from_degrees(origin() + Vector3::new(0.0, -30.0, 1.5), 0.0, 0.0, -90.0)
        .to_cam_from_world();
    let lost = |id: u32| GroupStart {
        image: ImageId(id),
        cam_from_world: away,
    };
    let out = maps(&[start(1), lost(101)]).unwrap();
    assert_eq!((out.report.num_registered, out.report.num_images), (10, 24));
    assert_eq!(out.reconstruction.num_registered_images(), 10);
    assert!(out
        .reconstruction
        .images
        .keys()
        .all(|id| id.0 <= 10 || id.0 > 200));
    let failed = &out.report.groups[1];
    assert_eq!(
        (
            failed.init_image_id,
            failed.num_images,
            failed.num_registered
        ),
        (101, 10, 0)
    );
    let error = failed.error.clone().expect("the failed run's error");
    assert!(
        error.contains("`copy_001.png` (id 101) sees no usable map point"),
        "{error}"
    );
    assert!(out.report.groups[0].error.is_none());
    let ids: Vec<u32> = out.report.images.iter().map(|r| r.image_id).collect();
    assert_eq!(ids, want);
    for rec in out
        .report
        .images
        .iter()
        .filter(|r| (101..=110).contains(&r.image_id))
    {
        assert_eq!(
            rec.not_registered,
            Some(NotRegistered::GroupFailed {
                init_image: "copy_001.png".to_string(),
                error: error.clone(),
            })
        );
    }
    let summary = out.report.not_registered_summary().unwrap();
    assert!(
        summary.contains("10 given to a group's run that failed"),
        "{summary}"
    );
    let err = fails(&[lost(1), lost(101)]);
    assert!(
        matches!(err, MapperError::Group { ref image, .. } if image == "img_000.png"),
        "{err}"
    );
    // The largest group runs first whatever the order given: it sets the
    // camera's intrinsics, which the small group's run holds; the first run
    // also gets the images of the group without an initial image.
    let out = maps(&[start(201), start(1)]).unwrap();
    assert_eq!(
        runs_of(&out.report),
        vec![(1, 21, 10, vec![], false), (201, 3, 3, vec![1], true)]
    );
}

/// Two groups of images that no verified match links (the toy's 10 images
/// and a copy of them under other names and ids), mapped each from its own
/// initial image at its pose, and `merge`d: one model with every image at
/// the pose its own run gave it, the points of both, and one camera; the
/// copy's camera with other intrinsics becomes a second camera; an image in
/// both models is refused.
#[test]
fn toy_room_groups_mapped_apart_merge_into_one_model() {
    use colmap_lidar::commands::merge::{merge_models, run as merge, MergeArgs};
    use colmap_lidar::io::model::{read_model, write_model, ModelFormat};
    let mut scene = toy(10, 0.3, 0.03, 4);
    let copy_of = |id: ImageId| ImageId(id.0 + 100);
    let db = &mut scene.db;
    for id in (1..=10).map(ImageId) {
        copy_image(db, id, copy_of(id), &format!("copy_{:03}.png", id.0));
        scene.gt.insert(copy_of(id), scene.gt[&id]);
    }
    copy_pairs(db, |id| Some(copy_of(id)));
    let options = MapperOptions::default();
    let pose = scene.init_pose.to_cam_from_world();
    let group = |init: ImageId| {
        let out = run_mapper(
            &scene.db,
            &scene.cloud,
            init,
            &pose,
            &options,
            &mut |_, _| {},
        )
        .unwrap();
        assert_eq!(out.report.num_registered, 10);
        out.reconstruction
    };
    let (a, b) = (group(ImageId(1)), group(ImageId(101)));
    let dir = tempfile::tempdir().unwrap();
    let (dir_a, dir_b) = (dir.path().join("a"), dir.path().join("b"));
    write_model(&dir_a, &a, ModelFormat::Binary).unwrap();
    write_model(&dir_b, &b, ModelFormat::Binary).unwrap();
    let out = dir.path().join("merged");
    merge(&MergeArgs {
        inputs: vec![dir_a.clone(), dir_b.clone()],
        output: out.clone(),
        output_type: "binary".into(),
    })
    .unwrap();
    let merged = read_model(&out).unwrap();
    assert_eq!(merged.num_registered_images(), 20);
    assert_eq!(merged.cameras.len(), 1);
    assert_eq!(merged.points3d.len(), a.points3d.len() + b.points3d.len());
    for source in [&a, &b] {
        for img in source.registered_images() {
            let m = &merged.images[&img.id];
            assert_eq!((&m.name, m.cam_from_world), (&img.name, img.cam_from_world));
            // The same observations of the same points, renumbered.
            assert_eq!(img.points2d.len(), m.points2d.len());
            for (p, q) in img.points2d.iter().zip(&m.points2d) {
                assert_eq!(p.xy, q.xy);
                let (Some(p), Some(q)) = (p.point3d_id, q.point3d_id) else {
                    assert_eq!(p.point3d_id.is_some(), q.point3d_id.is_some());
                    continue;
                };
                assert_eq!(source.points3d[&p].xyz, merged.points3d[&q].xyz);
            }
        }
    }
    let err = max_centre_error(&merged, &scene.gt);
    assert!(err < 0.03, "max centre error {err} m");
    let poses = colmap_lidar::io::pose_ply::read_pose_ply(&out.join("pose.ply")).unwrap();
    assert!(poses.keys().eq(merged.images.keys()));
    if crate::common::have_colmap() {
        let text = crate::common::run_colmap([
            "model_analyzer".as_ref(),
            "--path".as_ref(),
            out.as_os_str(),
        ]);
        assert!(text.contains("Registered images: 20"), "{text}");
    }
    // Other intrinsics under the same camera id: a second camera.
    let mut b2 = b.clone();
    b2.cameras.get_mut(&CameraId(1)).unwrap().params[0] += 1.0;
    let label = |dir: &PathBuf| dir.display().to_string();
    let models = vec![(label(&dir_a), a.clone()), (label(&dir_b), b2)];
    let (merged, summary) = merge_models(&models).unwrap();
    assert_eq!(
        summary.cameras_renumbered,
        vec![(1, CameraId(1), CameraId(2))]
    );
    assert!(merged
        .images
        .values()
        .all(|img| img.camera_id == CameraId(if img.id.0 > 100 { 2 } else { 1 })));
    // The copy's images under ids 5-14, of which 5-10 are taken by the first
    // model: those get ids past every id of both (15-20), 11-14 keep theirs.
    let to = |id: ImageId| ImageId(id.0 - 96);
    let mut b3 = b.clone();
    b3.images = b
        .images
        .values()
        .map(|img| {
            let mut img = img.clone();
            img.id = to(img.id);
            (img.id, img)
        })
        .collect();
    for p in b3.points3d.values_mut() {
        for e in &mut p.track {
            e.image_id = to(e.image_id);
        }
    }
    let models = vec![(label(&dir_a), a.clone()), (label(&dir_b), b3)];
    let (merged, summary) = merge_models(&models).unwrap();
    let renumbered: Vec<(u32, u32)> = summary
        .images_renumbered
        .iter()
        .map(|(k, old, new)| {
            assert_eq!(*k, 1);
            (old.0, new.0)
        })
        .collect();
    assert_eq!(
        renumbered,
        (5..=10).map(|i| (i, i + 10)).collect::<Vec<_>>()
    );
    assert_eq!(merged.num_registered_images(), 20);
    for img in b.registered_images() {
        let id = img.id.0 - 96;
        let new = ImageId(if id <= 10 { id + 10 } else { id });
        let m = &merged.images[&new];
        assert_eq!((&m.name, m.cam_from_world), (&img.name, img.cam_from_world));
    }
    // Every track element points at an image that sees the point there.
    for (id, p) in &merged.points3d {
        for e in &p.track {
            let seen = merged.images[&e.image_id].points2d[e.point2d_idx as usize].point3d_id;
            assert_eq!(seen, Some(*id));
        }
    }
    // What the inputs' reports say against one frame: nothing without
    // reports; a run without the map's planes, other maps.
    use colmap_lidar::commands::merge::map_frame_warnings;
    let both = [dir_a.clone(), dir_b.clone()];
    assert!(map_frame_warnings(&both).is_empty());
    let report = |dir: &std::path::Path, json: &str| {
        std::fs::write(dir.join("report.json"), json).unwrap();
    };
    report(
        &dir_a,
        r#"{"association": "nearest", "map_file": "a.ply", "map_points": 5000}"#,
    );
    report(
        &dir_b,
        r#"{"association": "nearest", "map_file": "a.ply", "map_points": 5000}"#,
    );
    assert!(map_frame_warnings(&both).is_empty());
    report(
        &dir_b,
        r#"{"association": "none", "map_file": "b.ply", "map_points": 4000}"#,
    );
    let warnings = map_frame_warnings(&both);
    assert_eq!(warnings.len(), 2, "{warnings:?}");
    assert!(
        warnings[0].contains("without the map's planes"),
        "{warnings:?}"
    );
    assert!(
        warnings[1].contains("from a map of 4000 points") && warnings[1].contains("(b.ply)"),
        "{warnings:?}"
    );
    // The output folder is never an input's (it would replace it).
    let e = merge(&MergeArgs {
        inputs: vec![dir_a.clone(), dir_b.clone()],
        output: dir_b.clone(),
        output_type: "binary".into(),
    })
    .unwrap_err();
    assert!(format!("{e:#}").contains("is one of the inputs"), "{e:#}");
    assert_eq!(read_model(&dir_b).unwrap(), b);
    // A folder holding anything but model files is not replaced.
    let notes = dir.path().join("notes");
    std::fs::create_dir(&notes).unwrap();
    std::fs::write(notes.join("todo.txt"), "keep me").unwrap();
    let e = merge(&MergeArgs {
        inputs: vec![dir_a.clone(), dir_b.clone()],
        output: notes.clone(),
        output_type: "text".into(),
    })
    .unwrap_err();
    assert!(
        format!("{e:#}").contains("which is not a model file"),
        "{e:#}"
    );
    assert_eq!(
        std::fs::read_to_string(notes.join("todo.txt")).unwrap(),
        "keep me"
    );
    // One holding an earlier model and the figures `plot` drew from it is
    // replaced as a whole, figures too.
    let figures = dir.path().join("figures");
    std::fs::create_dir(&figures).unwrap();
    std::fs::write(figures.join("report.json"), "{}").unwrap();
    std::fs::write(figures.join("planes.svg"), "<svg/>").unwrap();
    merge(&MergeArgs {
        inputs: vec![dir_a.clone(), dir_b.clone()],
        output: figures.clone(),
        output_type: "text".into(),
    })
    .unwrap();
    assert!(figures.join("images.txt").is_file() && !figures.join("planes.svg").exists());
    // One image in both: refused, naming it and both folders; nothing written.
    let refused = dir.path().join("refused");
    let e = merge(&MergeArgs {
        inputs: vec![dir_a.clone(), dir_a.clone()],
        output: refused.clone(),
        output_type: "text".into(),
    })
    .unwrap_err();
    let msg = format!("{e:#}");
    assert!(msg.contains("image img_000.png is in both"), "{msg}");
    assert!(!refused.exists());
}
