//! End to end on the synthetic scenes of the `synth` module with real COLMAP
//! databases: `map` (the command, in process) registers the images in the
//! map frame; checked against the ground truth without any alignment.
//! Skipped loudly when `colmap` is not installed.
use std::path::{Path, PathBuf};

use std::collections::{BTreeMap, BTreeSet};

use colmap_lidar::commands::map::{run as run_map, MapArgs};
use colmap_lidar::commands::plot::{read_report, PlotArgs, PlotData};
use colmap_lidar::eval::model_poses::load_poses;
use colmap_lidar::eval::{evaluate, Alignment, EvaluationReport};
use colmap_lidar::io::database::read_database;
use colmap_lidar::io::model::{read_model, write_model, ModelFormat};
use colmap_lidar::io::pose_ply::{read_pose_ply, write_pose_ply};
use colmap_lidar::scene::{BodyPose, CameraId, CameraModel, ImageId};
use colmap_lidar::synth::colmap_harness::{
    copy_with_guessed_camera, make_database, run_matcher, HarnessOptions, Matcher,
};
use colmap_lidar::synth::generate::{
    generate_scene, image_name, read_init_pose, SynthOptions, FISHEYE_FOCAL_FACTOR,
};
use colmap_lidar::synth::lidar::{
    sample_lidar, write_ply as write_synth_ply, LidarOptions, LidarPlatform,
};
use colmap_lidar::synth::scenes::{build_scene, SceneKind};

use crate::common::have_colmap;

/// A scene with its COLMAP database in `dir` (reused when already there).
pub fn scene_with_database(
    dir: &Path,
    kind: SceneKind,
    num_images: usize,
    max_features: usize,
) -> PathBuf {
    let db = dir.join("database.db");
    if db.is_file() && dir.join("lidar.ply").is_file() {
        return db;
    }
    let opts = SynthOptions {
        scene: kind,
        num_images,
        ..Default::default()
    };
    generate_scene(&opts, dir).expect("scene generation");
    make_database(
        dir,
        &HarnessOptions {
            max_num_features: max_features,
            ..Default::default()
        },
    )
    .expect("colmap database")
}

pub struct Run {
    pub report: serde_json::Value,
    pub none: EvaluationReport,
    pub seconds: f64,
}

/// `map`'s arguments for a scene folder: its database and map, the first
/// trajectory image at `init_pose`, the model written to `out`.
pub fn scene_args(scene: &Path, out: &Path, init_pose: &[f64; 6]) -> MapArgs {
    MapArgs {
        database: Some(scene.join("database.db")),
        lidar: Some(scene.join("lidar.ply")),
        output: Some(out.to_path_buf()),
        init_pose: vec![init_pose.map(|v| v.to_string()).join(",")],
        // The pose is that of the first trajectory image; COLMAP's ids need not follow names.
        init_image: vec![image_name(0)],
        ..Default::default()
    }
}

/// Runs `map` on a scene folder into `out`, evaluates against `gt/`.
pub fn map_scene(scene: &Path, out: &Path, extra: impl FnOnce(&mut MapArgs)) -> Run {
    let (exact, perturbed) = read_init_pose(&scene.join("init_pose.txt")).expect("init pose");
    let exact = if std::env::var("MAPPER_PERTURBED").is_ok_and(|v| v == "1") {
        perturbed
    } else {
        exact
    };
    map_scene_from(scene, out, &exact, extra)
}

/// Runs `map` on a scene folder from `init_pose` into `out`, evaluates
/// against `gt/`.
pub fn map_scene_from(
    scene: &Path,
    out: &Path,
    init_pose: &[f64; 6],
    extra: impl FnOnce(&mut MapArgs),
) -> Run {
    let mut args = scene_args(scene, out, init_pose);
    extra(&mut args);
    run_evaluated(&args, &scene.join("gt")).expect("map")
}

/// Runs `map` with `args` and evaluates the model it wrote against the
/// reference model in `gt` (no alignment); `map`'s error if it failed.
pub fn run_evaluated(args: &MapArgs, gt: &Path) -> anyhow::Result<Run> {
    let t = std::time::Instant::now();
    run_map(args)?;
    let seconds = t.elapsed().as_secs_f64();
    let out = args.output.as_deref().expect("an output folder");
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    let model = load_poses(out).expect("model poses");
    let gt = load_poses(gt).expect("gt poses");
    let none = evaluate(&model, &gt, Alignment::None).expect("evaluate");
    Ok(Run {
        report,
        none,
        seconds,
    })
}

/// A JSON array of numbers.
fn json_numbers(array: &serde_json::Value) -> Vec<f64> {
    array
        .as_array()
        .unwrap_or_else(|| panic!("not an array: {array}"))
        .iter()
        .map(|v| v.as_f64().unwrap_or_else(|| panic!("not a number: {v}")))
        .collect()
}

fn print_run(label: &str, r: &Run) {
    let c = r.none.centre_error_m.as_ref();
    eprintln!(
        "{label}: registered {}/{} ({:.0}%), mean reprojection {:.3} px, points {}, \
         centre error (no alignment) median {:.4} m / max {:.4} m, rotation median {:.3} deg, Sim3 scale {:.5}, {:.1} s",
        r.none.num_registered,
        r.none.num_reference,
        100.0 * r.none.registered_share,
        r.report["mean_reprojection_error_px"].as_f64().unwrap_or(f64::NAN),
        r.report["num_points"],
        c.map_or(f64::NAN, |s| s.median),
        c.map_or(f64::NAN, |s| s.max),
        r.none.rotation_error_deg.as_ref().map_or(f64::NAN, |s| s.median),
        r.none.sim3_scale.unwrap_or(f64::NAN),
        r.seconds
    );
}

fn check_run(r: &Run) {
    assert!(
        r.none.registered_share >= 0.95,
        "registered {:.2}",
        r.none.registered_share
    );
    let reproj = r.report["mean_reprojection_error_px"].as_f64().unwrap();
    assert!(reproj < 0.7, "mean reprojection error {reproj} px");
    let c = r.none.centre_error_m.as_ref().unwrap();
    // Issue 6's bar without any alignment: median under 1 cm, p90 under
    // 2 cm (measured 4-5 mm on the 24-image yard, exact and perturbed
    // initial pose); a wrong frame or scale is metres off.
    assert!(c.median < 0.01 && c.p90 < 0.02, "centre errors {c:?}");
    let rot = r.none.rotation_error_deg.as_ref().unwrap();
    assert!(rot.median < 0.05, "rotation errors {rot:?}");
    let s = r.none.sim3_scale.unwrap();
    assert!((s - 1.0).abs() < 0.03, "Sim3 scale {s}");
    // With the map's constraints: most points lie on the surface their
    // images see (0.95 measured on the seed-7 yard, 0.87-0.97 on the
    // synthetic scenes; models in the wrong place 0.32-0.79).
    if let Some(seen) = r.report["points_on_seen_surface_share"].as_f64() {
        assert!(seen > 0.85, "points on the seen surface: {seen}");
    }
    // Every map here has a planarity (the file's, or scored by `map` when the
    // map came with normals only): along the scenes' creases and borders a
    // share of its points give no plane (9-18 % on the synthetic scenes),
    // none when the map is not used for planes.
    let below = r.report["map_points_below_planarity"].as_u64().unwrap();
    let share = below as f64 / r.report["map_points"].as_u64().unwrap() as f64;
    if r.report["association"] == "none" {
        assert_eq!(below, 0);
    } else {
        assert!(
            share > 0.01 && share < 0.5,
            "below the planarity gate: {share}"
        );
    }
}

/// report.json's pose uncertainties: one per registered image, finite, and
/// of the size of the actual errors. They are formal (from the final solve's
/// information, scaled by its residual variance): on the 24-image scenes the
/// median centre error measured 1.0-3.8x the median sigma along the least
/// determined direction (systematic errors are not in the noise model), so
/// the bound is loose; a unit or conversion slip is off by orders of magnitude.
fn check_uncertainty(r: &Run) {
    let summary = &r.report["pose_uncertainty"];
    let sigma_px = summary["residual_sigma_px"].as_f64().unwrap();
    assert!(
        (0.05..1.0).contains(&sigma_px),
        "residual sigma {sigma_px} px"
    );
    let mut majors = Vec::new();
    let mut clustered_majors = Vec::new();
    for image in r.report["images"].as_array().unwrap() {
        let u = &image["pose_uncertainty"];
        if !image["registered"].as_bool().unwrap() {
            assert!(u.is_null());
            continue;
        }
        let major = u["centre_sigma_major_m"].as_f64().unwrap();
        let axes = json_numbers(&u["centre_sigma_m"]);
        // The largest per-axis sigma cannot exceed the major one.
        let largest = axes.iter().copied().fold(0.0, f64::max);
        assert!(largest > 0.0 && largest <= major * (1.0 + 1e-9), "{u}");
        let rotation = u["rotation_sigma_deg"].as_f64().unwrap();
        assert!(rotation > 0.0 && rotation < 1.0, "{u}");
        majors.push(major);
        // The cluster-robust estimate (default 1 m cubes): its major sigma
        // is the largest eigenvalue of the covariance it reports.
        let clustered = u["clustered_centre_sigma_major_m"].as_f64().unwrap();
        let cov: Vec<Vec<f64>> = u["clustered_centre_covariance_m2"]
            .as_array()
            .unwrap()
            .iter()
            .map(|row| {
                row.as_array()
                    .unwrap()
                    .iter()
                    .map(|v| v.as_f64().unwrap())
                    .collect()
            })
            .collect();
        let m = nalgebra::Matrix3::from_fn(|i, j| cov[i][j]);
        let top = m.symmetric_eigen().eigenvalues.max().sqrt();
        assert!(
            (clustered - top).abs() <= 1e-9 * top && clustered > 0.0,
            "{u}"
        );
        let clustered_rotation = u["clustered_rotation_sigma_deg"].as_f64().unwrap();
        assert!(clustered_rotation > 0.0 && clustered_rotation < 1.0, "{u}");
        clustered_majors.push(clustered);
    }
    majors.sort_by(f64::total_cmp);
    clustered_majors.sort_by(f64::total_cmp);
    let median_sigma = majors[majors.len() / 2];
    let median_clustered = clustered_majors[clustered_majors.len() / 2];
    let median_error = r.none.centre_error_m.as_ref().unwrap().median;
    let ratio = median_error / median_sigma;
    eprintln!(
        "pose uncertainty: median sigma {:.2} mm (cluster-robust {:.2} mm), median error {:.2} mm (ratio {ratio:.1}), residual sigma {sigma_px:.3} px",
        median_sigma * 1e3,
        median_clustered * 1e3,
        median_error * 1e3
    );
    assert!((0.2..10.0).contains(&ratio), "error / sigma {ratio}");
    let clustered_ratio = median_error / median_clustered;
    assert!(
        (0.1..5.0).contains(&clustered_ratio),
        "error / cluster-robust sigma {clustered_ratio}"
    );
    let summary_median = summary["median_clustered_centre_sigma_major_m"]
        .as_f64()
        .unwrap();
    let expected = colmap_lidar::eval::Stats::of(&clustered_majors)
        .unwrap()
        .median;
    assert!((summary_median - expected).abs() <= 1e-12, "{summary}");
}

/// A video-like database: COLMAP's sequential matcher (overlap 5 in name
/// order, COLMAP's default quadratic overlap, no loop detection) over the
/// shared yard's features. The shared database's raw matches stay (COLMAP
/// only verifies the pairs it lists whose matches are there, the same
/// matches it would compute): its verified pairs are the sequential ones.
/// The same bar as with every pair matched.
#[test]
fn yard_with_sequential_matches() {
    let Some(shared) = crate::common::yard_db() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("sequential.db");
    std::fs::copy(&shared.database, &db).unwrap();
    rusqlite::Connection::open(&db)
        .unwrap()
        .execute_batch("DELETE FROM two_view_geometries;")
        .unwrap();
    run_matcher(
        &db,
        &HarnessOptions {
            matcher: Matcher::Sequential { overlap: 5 },
            ..Default::default()
        },
    )
    .unwrap();
    let snapshot = read_database(&db).unwrap();
    let frame = |id: &ImageId| -> i64 {
        let name = &snapshot.images[id].name;
        (0..crate::common::YARD_IMAGES)
            .find(|&k| image_name(k) == *name)
            .unwrap() as i64
    };
    let pairs = &snapshot.two_view_geometries;
    assert!(
        pairs.len() >= crate::common::YARD_IMAGES,
        "{} pairs",
        pairs.len()
    );
    for p in pairs {
        // Image i with i + 1..=5 and (quadratic overlap) i + 8, i + 16.
        let gap = (frame(&p.image_id1) - frame(&p.image_id2)).abs();
        assert!(
            [1, 2, 3, 4, 5, 8, 16].contains(&gap),
            "pair {gap} frames apart"
        );
    }
    let exhaustive = read_database(&shared.database).unwrap();
    eprintln!(
        "sequential matcher: {} verified pairs (exhaustive: {})",
        pairs.len(),
        exhaustive.two_view_geometries.len()
    );
    let run = map_scene(&shared.scene, &dir.path().join("out"), |args| {
        args.database = Some(db.clone());
    });
    print_run("yard, sequential matches", &run);
    check_run(&run);
}

/// The seed-0 yard changed since the scan (`synth --changes 3`): three of
/// its objects are in the map but not in the images, three new boxes in the
/// images but not in the map. What is left on the map in view is the ground
/// and two facades through one corner, which leave the model's scale about
/// that corner free; the changes pull it along (measured: 0.98 m off, 45 %
/// fit, or 375 mm off with a warning on another database). From the exact
/// pose the mapper maps again with the initial image held there and meets
/// the bar; from a pose 0.3 m and 3 deg off nothing can place the model
/// along the free direction, and the run fails without writing anything,
/// or, on some databases, places it right.
#[test]
fn changed_yard_is_held_at_its_given_pose() {
    if !have_colmap() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("changed_yard");
    let options = SynthOptions {
        scene: SceneKind::Yard,
        seed: 0,
        changes: 3,
        ..Default::default()
    };
    generate_scene(&options, &scene).expect("scene generation");
    make_database(&scene, &HarnessOptions::default()).expect("colmap database");
    let exact = map_scene(&scene, &dir.path().join("exact"), |_| {});
    print_run("yard changed since the scan, exact initial pose", &exact);
    let c = exact.none.centre_error_m.as_ref().unwrap();
    let rot = exact.none.rotation_error_deg.as_ref().unwrap();
    let retry = &exact.report["retry"];
    let alignment = &exact.report["alignment"];
    assert!(exact.none.registered_share >= 0.95);
    assert!(
        c.median < 0.01 && c.p90 < 0.02 && rot.median < 0.05,
        "{c:?} {rot:?}\nretry: {retry}\nalignment: {alignment}"
    );
    assert_eq!(retry["held_kept"].as_bool(), Some(true), "{retry}");
    // The held run's whole-model alignment is a trial only (applied, such
    // a trial most likely left one CI database's run 25 mm off in scale).
    assert_eq!(alignment["applied"].as_bool(), Some(false), "{alignment}");
    assert!(!retry["reason"].as_str().unwrap().is_empty(), "{retry}");
    // Held early, the first run failed; so did the run free from the start
    // (mapped before the held one).
    assert_eq!(retry["free_kept"].as_bool(), Some(false), "{retry}");
    assert!(
        retry["free_run_s"].as_f64().is_some_and(|s| s > 0.0),
        "{retry}"
    );
    // The runs' times; the stages are the held run's, within its time.
    let first_s = retry["first_run_s"].as_f64().unwrap();
    let held_s = retry["held_run_s"].as_f64().unwrap();
    let stages_s: f64 = exact.report["stages"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["time_s"].as_f64().unwrap())
        .sum();
    assert!(
        first_s > 0.0 && stages_s > 0.0 && stages_s <= held_s,
        "{retry}"
    );
    // The whole mapping's time holds all three runs.
    let free_s = retry["free_run_s"].as_f64().unwrap();
    let mapping_s = exact.report["mapping_s"].as_f64().unwrap();
    assert!(
        mapping_s >= first_s + free_s + held_s,
        "mapping {mapping_s} s\n{retry}"
    );
    // Every run's record: the first (failed, or finished and retried), the
    // free one (failed; either may have stopped at a look first), the held
    // one last, the only one kept, its stages the report's.
    let runs = exact.report["runs"].as_array().unwrap();
    assert!(runs.len() >= 3, "{runs:?}");
    let kept: Vec<usize> = (0..runs.len())
        .filter(|&k| runs[k]["kept"].as_bool().unwrap())
        .collect();
    assert_eq!(kept, [runs.len() - 1], "{runs:?}");
    let outcome = |k: usize| runs[k]["outcome"].as_str().unwrap();
    assert!(
        outcome(0) == "finished"
            || outcome(0).starts_with("failed: ")
            || outcome(0) == "stopped at its look",
        "{}",
        outcome(0)
    );
    assert!(
        (1..runs.len() - 1).any(|k| outcome(k).starts_with("failed: ")),
        "{runs:?}"
    );
    let held_run = &runs[runs.len() - 1];
    assert_eq!(held_run["outcome"], "finished");
    // The runs set aside keep the solves they made (at least one got as far
    // as a solve), each at no more images than the database holds; the kept
    // run's are the report's own.
    assert!(held_run.get("solves").is_none(), "{held_run}");
    let set_aside: Vec<&serde_json::Value> = runs[..runs.len() - 1]
        .iter()
        .filter_map(|r| r.get("solves"))
        .flat_map(|s| s.as_array().unwrap())
        .collect();
    assert!(!set_aside.is_empty(), "{runs:?}");
    let num_images = exact.report["num_images"].as_u64().unwrap();
    assert!(
        set_aside.iter().all(|s| s["kind"].is_string()
            && s["num_registered"]
                .as_u64()
                .is_some_and(|n| n >= 2 && n <= num_images)),
        "{set_aside:?}"
    );
    // (`map` adds a "point colours" stage to the report's when asked.)
    let kept_stages = held_run["stages"].as_array().unwrap();
    assert!(!kept_stages.is_empty());
    assert_eq!(
        kept_stages[..],
        exact.report["stages"].as_array().unwrap()[..kept_stages.len()]
    );
    let time = |run: &serde_json::Value| run["time_s"].as_f64().unwrap();
    for run in runs {
        let stages: f64 = run["stages"]
            .as_array()
            .unwrap()
            .iter()
            .map(|s| s["time_s"].as_f64().unwrap())
            .sum();
        assert!(stages <= time(run), "{run}");
    }
    // The retry's clock also holds the run's set-up.
    assert!(time(held_run) <= held_s, "{retry}");
    let runs_s: f64 = runs.iter().map(time).sum();
    assert!(
        runs_s <= mapping_s,
        "{runs_s} s of runs, mapping {mapping_s} s"
    );
    let moved = exact.report["initial_pose_change"]["moved_m"].as_f64();
    assert!(moved.is_some_and(|m| m < 1e-6), "{moved:?}");
    assert!(exact.report["fit_share"].as_f64().unwrap() > 0.6);

    // From the perturbed pose without the search of the map that follows a
    // failed run (`bundle.fallback_search_m = 0`): on this scene the search
    // maps its two close placements and refuses both (measured: one 17 %
    // fit, the other 85 % with constraint ratio 3.2e-3, the loose model
    // `a_loose_searched_model_is_refused` checks), 4.5 of the test's 8.5
    // minutes; the yard test covers the search that follows a failed run.
    let (_, perturbed) = read_init_pose(&scene.join("init_pose.txt")).unwrap();
    let out = dir.path().join("perturbed");
    let no_search = dir.path().join("no_search.toml");
    std::fs::write(&no_search, "[mapper.bundle]\nfallback_search_m = 0\n").unwrap();
    let err = match run_map(&MapArgs {
        options: Some(no_search),
        ..scene_args(&scene, &out, &perturbed)
    }) {
        Err(err) => err,
        Ok(()) => {
            // Some databases place it (session 59, a CI database, 24/24):
            // then it must be right, never a wrong model without an error.
            let model = load_poses(&out).expect("model poses");
            let gt = load_poses(&scene.join("gt")).expect("gt poses");
            let none = evaluate(&model, &gt, Alignment::None).expect("evaluate");
            let c = none.centre_error_m.as_ref().unwrap();
            let rot = none.rotation_error_deg.as_ref().unwrap();
            eprintln!(
                "yard changed since the scan, perturbed initial pose: placed, {}/{}, centre error median {:.4} m, p90 {:.4} m, rotation median {:.3} deg",
                none.num_registered, none.num_reference, c.median, c.p90, rot.median
            );
            assert!(none.registered_share >= 0.95);
            assert!(
                c.median < 0.01 && c.p90 < 0.02 && rot.median < 0.05,
                "placed from the perturbed pose but wrong: {c:?} {rot:?}"
            );
            return;
        }
    };
    let message = format!("{err:#}");
    assert!(
        message.contains("does not fit the map") || message.contains("from its given pose"),
        "{message}"
    );
    // The first run failed, so it was mapped again held at the perturbed
    // pose, and the message says that this failed as well.
    assert!(
        message.contains(
            "Mapped again with the initial image held at its given pose; that run failed too"
        ),
        "{message}"
    );
    assert!(!message.contains("Searched the map"), "{message}");
    assert!(!out.exists());
}

/// A database made without the camera: COLMAP's extractor finds no focal
/// length in the images and guesses one (1.2 x the larger side, SIMPLE_RADIAL
/// with no distortion, `prior_focal_length = 0`); the shared yard's features
/// and matches with that camera, every pair verified again under it (what a
/// fresh extraction without the camera gives). The default refinement
/// self-calibrates such a camera in every solve and must meet the same bar,
/// with the focal length and distortion found.
#[test]
fn yard_self_calibrates_colmaps_guessed_camera() {
    let Some(shared) = crate::common::yard_db() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let db = dir.path().join("guessed_camera.db");
    copy_with_guessed_camera(
        &shared.database,
        &shared.scene.join("images").join(image_name(0)),
        &db,
        &HarnessOptions::default(),
    )
    .unwrap();
    let truth = read_model(&shared.scene.join("gt")).unwrap().cameras
        [&colmap_lidar::scene::CameraId(1)]
        .clone();
    let snapshot = read_database(&db).unwrap();
    assert_eq!(snapshot.cameras.len(), 1);
    let (id, guess) = snapshot.cameras.iter().next().unwrap();
    assert_eq!(guess.model.name(), "SIMPLE_RADIAL");
    assert_eq!(guess.params, [768.0, 320.0, 240.0, 0.0], "COLMAP's guess");
    assert!(snapshot.cameras_without_focal_prior.contains(id));
    // Verified again under the guess: without a focal length it trusts,
    // COLMAP calls no pair calibrated (config 2); with the true camera it
    // called 20 of the seed-7 yard's 170 verified pairs so. The pairs are
    // the same (measured: 170 either way; the rest planar, config 6).
    let shared_pairs = read_database(&shared.database).unwrap().two_view_geometries;
    let calibrated = |pairs: &[colmap_lidar::io::database::TwoViewGeometry]| {
        pairs.iter().filter(|p| p.config == 2).count()
    };
    assert!(calibrated(&shared_pairs) > 0);
    assert_eq!(calibrated(&snapshot.two_view_geometries), 0);
    let (n, m) = (snapshot.two_view_geometries.len(), shared_pairs.len());
    assert!(n.abs_diff(m) * 10 <= m, "{n} pairs verified again of {m}");
    let run = map_scene(&shared.scene, &dir.path().join("out"), |args| {
        args.database = Some(db.clone());
    });
    print_run("yard, COLMAP's guessed camera", &run);
    let rec = &run.report["intrinsics"][0];
    let refined = json_numbers(&rec["final_params"]);
    let from_pairs = rec["focal_from_pairs_px"].as_f64();
    let from_map = rec["focal_from_map_px"].as_f64();
    eprintln!(
        "refined camera {refined:?}, truth {:?}, focal length from the pairs {from_pairs:?}, from the map {from_map:?}",
        truth.params
    );
    assert_eq!(rec["refined"], "every solve");
    // Self-calibration started from the focal length the map and the
    // initial pair agree on, at most half as far from the truth as COLMAP's
    // guess (measured 531-564 px for 512 on four databases; the pairs'
    // fundamental matrices, most of them of nearly planar views, gave
    // 295-403 px on the same databases and are not used).
    let from_map = from_map.expect("the map gives a focal length");
    assert!(
        (from_map - truth.params[0]).abs() < 0.5 * (guess.params[0] - truth.params[0]).abs(),
        "focal length from the map {from_map} (truth {}, guess {})",
        truth.params[0],
        guess.params[0]
    );
    assert!(
        (refined[0] / truth.params[0] - 1.0).abs() < 0.003,
        "focal {} (truth {})",
        refined[0],
        truth.params[0]
    );
    assert!(
        (refined[3] - truth.params[3]).abs() < 0.005,
        "k {}",
        refined[3]
    );
    // Its uncertainty (one sigma, px): the data fix it well under a pixel
    // (measured: 511.68 px for 512, sigma 0.135 px, cluster-robust 0.146 px;
    // six 24-image scenes with a given focal length refined: 0.06-0.20 px).
    let sigma = rec["focal_sigma_px"].as_f64().expect("focal_sigma_px");
    let clustered = rec["clustered_focal_sigma_px"]
        .as_f64()
        .expect("clustered_focal_sigma_px");
    eprintln!(
        "focal length sigma {sigma:.3} px, cluster-robust {clustered:.3} px; error {:.2} of those",
        (refined[0] - truth.params[0]) / clustered
    );
    assert!(
        sigma > 0.0 && sigma < 1.0 && clustered > 0.0 && clustered < 1.0,
        "{rec}"
    );
    // Every parameter refined here (the principal point with a guessed
    // focal length) has its own sigma, the focal length's the one above
    // (measured: f 0.135, cx 0.064, cy 0.090 px, k 8.5e-5).
    let params = json_numbers(&rec["params_sigma"]);
    eprintln!("parameter sigmas {params:?}");
    assert_eq!(params.len(), refined.len(), "{rec}");
    assert_eq!(params[0], sigma);
    assert!(params.iter().all(|s| *s > 0.0), "{rec}");
    // COLMAP's guessed principal point (the centre) is refined with the
    // rest; here the truth is the centre, and it stays within a pixel
    // (measured 0.03 / 0.08 px on a database like it).
    for k in [1, 2] {
        assert!(
            (refined[k] - truth.params[k]).abs() < 1.0,
            "principal point {refined:?} (truth {:?})",
            truth.params
        );
    }
    check_run(&run);
    // From a rough pose with --init-search the run without the map's planes
    // starts from the initial pair with the guessed camera (its essential
    // matrix, or K2^T F K1 with the guess) and self-calibrates too: the same
    // bar (the seed-0 yard's guessed camera measured 5.4 mm from 1.3 m /
    // 15 deg off against 4.1 mm with the true camera, focal 512.2 px).
    let searched = map_scene(&shared.scene, &dir.path().join("searched"), |args| {
        args.database = Some(db.clone());
        args.init_pose = vec![rough_pose(&shared.scene).map(|v| v.to_string()).join(",")];
        args.init_search = Some("2,30".to_owned());
    });
    print_run(
        "yard, COLMAP's guessed camera, from a rough pose",
        &searched,
    );
    assert!(searched.report["init_search"]["plain_pair_scale"].is_f64());
    let focal = searched.report["intrinsics"][0]["final_params"][0]
        .as_f64()
        .unwrap();
    assert!(
        (focal / truth.params[0] - 1.0).abs() < 0.003,
        "focal {focal} (truth {})",
        truth.params[0]
    );
    check_as_from_the_exact_pose(&searched, &run);
}

/// A fisheye camera (OPENCV_FISHEYE, 125 deg across, 156 deg on the
/// diagonal; rays up to 78 deg off the axis) through the whole chain: COLMAP's
/// features and matches on the distorted images, the map seen through the
/// equidistant model (initial depths, projection association, the fit
/// check), the solver's fisheye reprojection terms, and a model COLMAP reads.
/// Measured on the seed-0 24-image room: 0.34 mm median from the perturbed
/// pose (`colmap mapper` + oracle 0.25 mm); this 16-image room 0.5 mm.
#[test]
fn fisheye_room_is_mapped_in_the_map_frame() {
    if !have_colmap() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("room");
    let options = SynthOptions {
        scene: SceneKind::Room,
        num_images: FISHEYE_IMAGES,
        camera_model: CameraModel::OpenCvFisheye,
        focal_factor: FISHEYE_FOCAL_FACTOR,
        ..Default::default()
    };
    generate_scene(&options, &scene).expect("scene generation");
    let db = make_database(&scene, &HarnessOptions::default()).expect("colmap database");
    let truth = read_model(&scene.join("gt")).unwrap().cameras[&CameraId(1)].clone();
    let snapshot = read_database(&db).unwrap();
    let in_db: Vec<_> = snapshot.cameras.values().collect();
    assert_eq!(in_db.len(), 1);
    assert_eq!(in_db[0].model, CameraModel::OpenCvFisheye);
    assert_eq!(
        in_db[0].params, truth.params,
        "COLMAP keeps the given camera"
    );
    let (_, perturbed) = read_init_pose(&scene.join("init_pose.txt")).unwrap();
    let out = dir.path().join("out");
    let run = map_scene_from(&scene, &out, &perturbed, |_| {});
    print_run("fisheye room, perturbed pose", &run);
    check_run(&run);
    assert_eq!(run.none.num_registered, FISHEYE_IMAGES);
    let c = run.none.centre_error_m.as_ref().unwrap();
    assert!(c.median < 0.002, "centre errors {c:?}");
    // The given camera is held: the final probe does not find it off.
    let model = read_model(&out).unwrap();
    let camera = &model.cameras[&CameraId(1)];
    assert_eq!(camera.model, CameraModel::OpenCvFisheye);
    for (k, (a, b)) in camera.params.iter().zip(&truth.params).enumerate() {
        assert!(
            (a - b).abs() <= 1e-3 * b.abs().max(1.0),
            "parameter {k}: {a} (truth {b})"
        );
    }
    let text = crate::common::run_colmap([
        "model_analyzer".as_ref(),
        "--path".as_ref(),
        out.as_os_str(),
    ]);
    assert!(
        text.contains(&format!("Registered images: {FISHEYE_IMAGES}")),
        "{text}"
    );
    // The same features with COLMAP's guess for the camera (768 px, the image
    // centre, no distortion; prior_focal_length = 0): self-calibrated from
    // the focal length the map gives, principal point included (it is 1.5 px
    // and -1 px off the centre; held there, the 24-image room ended 11.9 mm
    // and 0.33 deg off, refined 1.0 mm and 0.013 deg).
    let guessed_db = dir.path().join("guessed.db");
    std::fs::copy(&db, &guessed_db).unwrap();
    let guess: Vec<u8> = [768.0f64, 768.0, 320.0, 240.0, 0.0, 0.0, 0.0, 0.0]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    rusqlite::Connection::open(&guessed_db)
        .unwrap()
        .execute(
            "UPDATE cameras SET params = ?1, prior_focal_length = 0",
            [guess],
        )
        .unwrap();
    let guessed_out = dir.path().join("guessed");
    let guessed = map_scene_from(&scene, &guessed_out, &perturbed, |args| {
        args.database = Some(guessed_db.clone());
    });
    print_run("fisheye room, COLMAP's guessed camera", &guessed);
    check_run(&guessed);
    let rec = &guessed.report["intrinsics"][0];
    assert_eq!(rec["refined"], "every solve");
    let refined = json_numbers(&rec["final_params"]);
    eprintln!("refined fisheye {refined:?}, truth {:?}", truth.params);
    for k in 0..2 {
        assert!(
            (refined[k] / truth.params[k] - 1.0).abs() < 0.003,
            "focal length {k}: {refined:?} (truth {:?})",
            truth.params
        );
    }
    for k in 2..4 {
        assert!(
            (refined[k] - truth.params[k]).abs() < 0.5,
            "principal point: {refined:?} (truth {:?})",
            truth.params
        );
    }
    let c = guessed.none.centre_error_m.as_ref().unwrap();
    assert!(c.median < 0.003, "centre errors {c:?}");
}
const FISHEYE_IMAGES: usize = 16;

/// A scan of 50 mm range noise (a mobile scanner's, or passes that disagree
/// by that much), prepared by `prepare-map` as a user would and mapped.
/// `prepare-map` reads the noise and widens its normal radius to 8 times it
/// (at the default 0.15 m the flat surfaces' planarity fell to about 0.53,
/// under the mapper's gate of 0.7), and `map` reads it again and widens its
/// plane window to 3 times it. Before both (session 69's code), this
/// 12-image room failed the fit check with 55 % of its points on the map;
/// now 3.2 mm median off (p90 3.9 mm, 0.020 deg, fit 0.85; the true normals
/// 2.0 mm). On another fresh database the final probe moved the focal length
/// by +0.103 %, just over its 0.1 % bar, refined it, and the model came out
/// 5.2 mm (p90 6.1 mm), 0.052 deg off at a scale of 1.0022: the bounds
/// below allow for that.
#[test]
fn a_noisy_scan_is_prepared_and_mapped() {
    if !have_colmap() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("room");
    let mut options = SynthOptions {
        scene: SceneKind::Room,
        num_images: NOISY_SCAN_IMAGES,
        ..Default::default()
    };
    options.lidar.noise_sigma_m = 0.05;
    generate_scene(&options, &scene).expect("scene generation");
    make_database(&scene, &HarnessOptions::default()).expect("colmap database");
    let prepared = dir.path().join("prepared.ply");
    let text = run_prepare_map(&scene.join("lidar_raw.ply"), &prepared);
    let radius = number_before(&text, " m radius");
    let noise = number_before(&text, " mm)");
    assert!((0.35..0.45).contains(&radius), "{text}");
    assert!((45.0..58.0).contains(&noise), "{text}");
    let run = map_scene(&scene, &dir.path().join("out"), |args| {
        args.lidar = Some(prepared.clone());
    });
    print_run("room, 50 mm scan", &run);
    assert_eq!(run.none.num_registered, NOISY_SCAN_IMAGES);
    let read = run.report["map_noise_m"].as_f64().unwrap();
    assert!((0.045..0.058).contains(&read), "map noise {read}");
    let fit = run.report["fit_share"].as_f64().unwrap();
    assert!(fit > 0.75, "fit {fit}");
    let c = run.none.centre_error_m.as_ref().unwrap();
    assert!(c.median < 0.008 && c.p90 < 0.012, "centre errors {c:?}");
    let rot = run.none.rotation_error_deg.as_ref().unwrap();
    assert!(rot.median < 0.08, "rotation errors {rot:?}");
}
const NOISY_SCAN_IMAGES: usize = 12;

/// A drone's survey (`synth --scene aerial`: the yard from 24 m, the
/// camera looking straight down, three strips) from the photos' GPS
/// positions alone (0.3 m / 1 m, one 40 m off): the positions say the
/// photos look down, the model is turned upright, searched for and mapped
/// within the bar of issue 6 (measured 3.5 mm; 2.4-2.7 mm with 24 images,
/// also from the exact and a perturbed initial pose). Then the same into an
/// airborne scan prepared by `prepare-map` (10 cm, sparse walls, 3 cm of
/// noise): its wall normals from widened radii, the search's planes and
/// radii from its spacing, the final rounds' radius from its walls', and the
/// model the map holds loosely confirmed by the positions.
#[test]
fn aerial_survey_from_gps() {
    if !have_colmap() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("aerial");
    let options = SynthOptions {
        scene: SceneKind::Aerial,
        num_images: AERIAL_IMAGES,
        ..Default::default()
    };
    generate_scene(&options, &scene).expect("scene generation");
    make_database(
        &scene,
        &HarnessOptions {
            max_num_features: 4096,
            ..Default::default()
        },
    )
    .expect("colmap database");
    let wrong = image_name(5);
    let db = database_with_gps(
        &scene,
        dir.path(),
        "gps.db",
        [500_000.0, 4_400_000.0, 200.0],
        (0.3, 1.0),
        Some(&wrong),
    );
    let out = dir.path().join("out");
    let args = MapArgs {
        database: Some(db),
        lidar: Some(scene.join("lidar.ply")),
        output: Some(out.clone()),
        map_crs: Some("utm:33n".to_owned()),
        map_origin: Some("500000,4400000,200".to_owned()),
        ..Default::default()
    };
    let run = run_evaluated(&args, &scene.join("gt")).expect("map from the GPS positions");
    print_run("aerial survey from its GPS positions", &run);
    let positions = &run.report["positions"];
    eprintln!("positions: {positions}");
    assert_eq!(positions["camera_tilt"], "nadir", "{positions}");
    // The positions put the up within their uncertainty (about 7 deg: 1 m
    // over the strips' 4.1 m spread, two independent); the cameras' axes
    // then set it.
    let tilt = positions["tilt_deg"].as_f64().unwrap();
    let sigma = positions["tilt_sigma_deg"].as_f64().unwrap();
    assert!(
        (tilt - 90.0).abs() < 3.0 * sigma && sigma < 20.0,
        "{positions}"
    );
    assert_eq!(
        positions["num_inliers"].as_u64(),
        Some(AERIAL_IMAGES as u64 - 1)
    );
    let max = positions["final_horizontal_max_m"].as_f64().unwrap();
    assert!((max - 40.0).abs() < 2.0, "{positions}");
    check_run(&run);
    assert_eq!(run.none.num_registered, AERIAL_IMAGES);
    // Upright: the cameras look down, as in truth.
    let model = read_model(&out).unwrap();
    for image in model.registered_images() {
        let axis = image.cam_from_world.unwrap().rotation.inverse() * nalgebra::Vector3::z();
        assert!(axis.z < -0.99, "{}: optical axis {axis:?}", image.name);
    }

    // The same photos in an airborne scan, as a drone survey's LiDAR gives
    // it: a point every 10 cm on the ground and roofs, walls at 0.15 of
    // that, 3 cm of noise, no normals, prepared by `prepare-map`.
    let scan = sample_lidar(
        &build_scene(SceneKind::Aerial, options.seed),
        &LidarOptions {
            spacing_m: Some(0.1),
            noise_sigma_m: 0.03,
            platform: LidarPlatform::Airborne,
            seed: 9,
            ..LidarOptions::default()
        },
    );
    let raw = dir.path().join("airborne_raw.ply");
    let mut file = std::io::BufWriter::new(std::fs::File::create(&raw).unwrap());
    write_synth_ply(&mut file, &scan, &nalgebra::Vector3::zeros(), false).unwrap();
    file.into_inner().unwrap();
    let prepared = dir.path().join("airborne.ply");
    let text = run_prepare_map(&raw, &prepared);
    assert!(text.contains("where the map is sparser"), "{text}");
    let args = MapArgs {
        lidar: Some(prepared),
        output: Some(dir.path().join("airborne_out")),
        ..args
    };
    let run = run_evaluated(&args, &scene.join("gt")).expect("map into the airborne scan");
    print_run("aerial survey from GPS, airborne scan", &run);
    let positions = &run.report["positions"];
    eprintln!(
        "positions: {positions}\nsimilarity constraint: {}",
        run.report["similarity_constraint"]
    );
    // The map loosely holds the model across the strips (a similarity
    // ratio of 5.6e-3 measured, fit 0.86): a searched model below 7e-3
    // (`SEARCH_MIN_CONSTRAINT`) and a 90 % fit is kept only because the
    // positions place it.
    assert_eq!(positions["confirms_placement"], true, "{positions}");
    let ratio = run.report["similarity_constraint"]["ratio"]
        .as_f64()
        .unwrap();
    let fit = run.report["fit_share"].as_f64().unwrap();
    assert_eq!(
        run.report["init_search"]["kept_by_positions"].as_bool(),
        Some(ratio < 7e-3 && fit < 0.9),
        "ratio {ratio}, fit {fit}"
    );
    // The walls read about 2.3 times the map's spacing, and the smallest
    // association radius follows them.
    let spacing = run.report["map_spacing_m"].as_f64().unwrap();
    let walls = run.report["map_steep_spacing_m"].as_f64().unwrap();
    assert!(walls > 1.5 * spacing, "walls {walls} m, map {spacing} m");
    assert_eq!(run.none.num_registered, AERIAL_IMAGES);
    // Measured 10.5 mm median, 11.7 mm max (17.5 mm with the final rounds'
    // 0.1 m radius, which finds the roofs' edges instead of the walls); on
    // another run's database (COLMAP's matching is not the same from run to
    // run) 8.0 mm and 13.6 mm.
    let c = run.none.centre_error_m.as_ref().unwrap();
    assert!(c.median < 0.02 && c.p90 < 0.025, "centre errors {c:?}");
    // Rotation: 0.021 deg and 0.0501 deg on two runs' databases. Only the
    // sparse walls hold the heading of these 12 nadir photos, so the bar
    // here is twice the terrestrial scenes'.
    let rot = run.none.rotation_error_deg.as_ref().unwrap();
    assert!(rot.median < 0.1, "rotation errors {rot:?}");
}
const AERIAL_IMAGES: usize = 12;

/// The CI yard's rough initial pose for `--init-search`: the exact one moved
/// (1.0, -0.8, 0.2) m and turned (4, -3, 15) deg in roll, pitch and yaw.
fn rough_pose(scene: &Path) -> [f64; 6] {
    let (mut rough, _) = read_init_pose(&scene.join("init_pose.txt")).unwrap();
    for (k, d) in ROUGH_OFFSET.iter().enumerate() {
        rough[k] += d;
    }
    rough
}
const ROUGH_OFFSET: [f64; 6] = [1.0, -0.8, 0.2, 4.0, -3.0, 15.0];

#[test]
fn yard_with_colmap_database() {
    // The shared yard and its real COLMAP database (made once per run).
    let Some(shared) = crate::common::yard_db() else {
        return;
    };
    let scene = shared.scene.clone();
    let dir = tempfile::tempdir().unwrap();
    let with_images = |args: &mut MapArgs| args.image_path = Some(scene.join("images"));
    let a = map_scene(&scene, &dir.path().join("a"), with_images);
    print_run("yard (shared CI scene)", &a);
    check_run(&a);
    check_uncertainty(&a);
    check_colours(&scene, &dir.path().join("a"), &a.report, dir.path());
    check_refinement(&a.report);
    check_map_colours(&scene, &dir.path().join("a"), dir.path());
    check_extension(&scene, &dir.path().join("a"), dir.path());
    check_partial_map(&scene, dir.path());
    check_groups(&scene, dir.path(), &a);
    check_init_search(&scene, dir.path(), &a);
    check_gps(&scene, dir.path(), &a);
    // `evaluate` compares the errors with the model's own sigmas.
    let eval_json = dir.path().join("evaluation.json");
    colmap_lidar::commands::evaluate::run(&colmap_lidar::commands::evaluate::EvaluateArgs {
        model: dir.path().join("a"),
        reference: scene.join("gt"),
        align: Alignment::None,
        json: Some(eval_json.clone()),
        lidar: Some(scene.join("lidar.ply")),
    })
    .unwrap();
    let evaluation: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&eval_json).unwrap()).unwrap();
    let over = &evaluation["error_over_sigma"];
    assert_eq!(over["count"].as_u64(), Some(a.none.num_registered as u64));
    let median = over["centre"]["median"].as_f64().unwrap();
    assert!((0.2..10.0).contains(&median), "{over}");
    let clustered = &evaluation["error_over_clustered_sigma"];
    assert_eq!(
        clustered["count"].as_u64(),
        Some(a.none.num_registered as u64)
    );
    assert!(
        clustered["centre"]["median"].as_f64().unwrap() > 0.0,
        "{clustered}"
    );
    // And the focal length with the reference's (one camera, the true one
    // given): exact where the probe held it, else within its sigmas' reach.
    let focal = &evaluation["focal_lengths"];
    assert_eq!(focal.as_array().map(Vec::len), Some(1), "{focal}");
    assert_eq!(
        focal[0]["num_images"].as_u64(),
        Some(a.none.num_registered as u64)
    );
    let relative = focal[0]["relative_error"].as_f64().unwrap();
    if a.report["intrinsics"][0]["refined"] == "held" {
        assert!(relative.abs() < 1e-12, "{focal}");
        assert!(focal[0]["clustered_sigma_px"].is_null(), "{focal}");
    } else {
        assert!(relative.abs() < 0.002, "{focal}");
        assert!(focal[0]["clustered_sigma_px"].as_f64().unwrap() > 0.0);
    }
    // The tracks at the true poses and the model's points lie on the map
    // where seen head-on (measured: medians within 0.25 mm; the map's
    // noise is 15 mm, its planes average it).
    let agreement = &evaluation["map_agreement"];
    let head_on = &agreement["classes"][4];
    assert_eq!(head_on["min_cos"].as_f64(), Some(0.7), "{agreement}");
    for side in ["reference", "model"] {
        assert!(
            head_on[format!("{side}_count")].as_u64().unwrap() > 1000,
            "{agreement}"
        );
        let m = head_on[format!("{side}_median_m")].as_f64().unwrap();
        assert!(m.abs() < 0.001, "{side}: {agreement}");
    }
    // The map fixes the whole model (no warning), the initial image stays at
    // its exact pose, and the fit counts the points removed behind the map.
    let report = &a.report;
    let ratio = report["similarity_constraint"]["ratio"].as_f64().unwrap();
    assert!(
        ratio > colmap_lidar::sfm::align::MIN_SIMILARITY_CONSTRAINT,
        "{ratio}"
    );
    assert!(report["initial_pose_change"]["moved_m"].as_f64().unwrap() < 0.02);
    let fit = report["fit_share"].as_f64().unwrap();
    let seen = report["points_on_seen_surface_share"].as_f64().unwrap();
    let (n, removed) = (
        report["num_points"].as_f64().unwrap(),
        report["points_behind_map_removed"].as_f64().unwrap(),
    );
    assert!(
        (fit - seen * n / (n + removed)).abs() < 1e-9 && fit > 0.6,
        "{fit} {seen}"
    );
    // The map covers the model (measured 0.95-0.996 on the fully mapped
    // scenes); the fit over the covered points is the same sample's on-surface
    // share over the covered share, the removed points counted against it.
    let coverage = report["map_coverage_share"].as_f64().unwrap();
    let covered_fit = report["covered_fit_share"].as_f64().unwrap();
    assert!(coverage > 0.9 && coverage <= 1.0, "{coverage}");
    let covered_n = (coverage * n).round();
    let expected = seen / coverage * covered_n / (covered_n + removed);
    assert!(
        (covered_fit - expected).abs() < 1e-9 && covered_fit >= fit,
        "{covered_fit} {expected} {fit}"
    );
    assert_eq!(report["partial_map"].as_bool(), Some(false));
    assert_eq!(
        report["alignment"]["covered_points_only"],
        serde_json::Value::Null
    );

    // The run's figures; every local solve brings its points to the planes
    // (the paper's second figure; the seed-0 corridor: 0.7-7 mm before,
    // 0.003-0.06 mm after).
    let figures = dir.path().join("figures");
    colmap_lidar::commands::plot::run(&PlotArgs {
        report: dir.path().join("a"),
        output: figures.clone(),
        run: None,
    })
    .unwrap();
    for name in [
        "planes.svg",
        "plane_distance.svg",
        "reprojection.svg",
        "images.svg",
    ] {
        let svg = std::fs::read_to_string(figures.join(name)).unwrap();
        assert!(
            svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"),
            "{name}"
        );
    }
    let (_, report) = read_report(&dir.path().join("a").join("report.json")).unwrap();
    let data = PlotData::from_report(&report).unwrap();
    assert!(data.local.planes.len() >= a.none.num_registered - 2);
    for (before, after) in data
        .local
        .distance_before_mm
        .iter()
        .zip(&data.local.distance_after_mm)
    {
        assert!(
            after.1 < 0.5 * before.1 && after.1 < 0.5,
            "{before:?} -> {after:?}"
        );
    }
    assert_eq!(data.images.nearest.len(), a.none.num_registered);

    // Same inputs and seed: byte-identical model files, whatever the number
    // of threads the parallel parts (association, projection, statistics) run
    // on: the second run has one.
    let one_thread = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let b = one_thread.install(|| map_scene(&scene, &dir.path().join("b"), with_images));
    for f in ["cameras.txt", "images.txt", "points3D.txt"] {
        let x = std::fs::read(dir.path().join("a").join(f)).unwrap();
        let y = std::fs::read(dir.path().join("b").join(f)).unwrap();
        assert!(
            x == y,
            "{f} differs between two runs (the second on one thread)"
        );
    }
    assert_eq!(
        a.report["solves"].as_array().map(Vec::len),
        b.report["solves"].as_array().map(Vec::len)
    );
    // pose.ply: the model's poses at full precision, line k = image id k.
    let exported = read_pose_ply(&dir.path().join("a").join("pose.ply")).unwrap();
    let model = read_model(&dir.path().join("a")).unwrap();
    assert_eq!(
        exported.len(),
        model.images.values().filter(|i| i.is_registered()).count()
    );
    for (id, pose) in &exported {
        let truth = model.images[id].cam_from_world.unwrap();
        let back = pose.to_cam_from_world();
        assert!((back.camera_center() - truth.camera_center()).norm() < 1e-9);
        assert!(back.rotation.angle_to(&truth.rotation) < 1e-9);
    }

    // The initial pose 0.3 m and 3 deg off, nothing else known: the map
    // pulls the model in (issue 6 asks for the same bar as with the exact
    // pose); report.json says whether the whole-model alignment moved it.
    let (exact, perturbed) = read_init_pose(&scene.join("init_pose.txt")).unwrap();
    let perturbed_run = map_scene(&scene, &dir.path().join("perturbed"), |args| {
        args.init_pose = vec![perturbed.map(|v| v.to_string()).join(",")];
    });
    print_run("yard, perturbed initial pose", &perturbed_run);
    check_run(&perturbed_run);
    for key in ["initial_alignment", "alignment"] {
        let alignment = &perturbed_run.report[key];
        let (before, after) = (
            alignment["points_on_map_before"].as_u64().unwrap(),
            alignment["points_on_map_after"].as_u64().unwrap(),
        );
        // The initial pair's needs at least 1 % more points (noise moves
        // were locked in by the early hold).
        let min_gain = if key == "initial_alignment" {
            colmap_lidar::sfm::mapper::INITIAL_PAIR_MIN_GAIN
        } else {
            1.0
        };
        assert_eq!(
            alignment["applied"].as_bool(),
            Some(after > before && after as f64 >= min_gain * before as f64),
            "{key}: {alignment}"
        );
        // The model's centroid moves by at most about the initial pose's error.
        assert!(
            alignment["translation_m"].as_f64().unwrap() < 1.5,
            "{alignment}"
        );
    }

    // Known poses (the true ones, as a user's pose.ply) with the perturbed
    // initial pose: soft priors in every solve.
    let db = read_database(&scene.join("database.db")).unwrap();
    let gt = load_poses(&scene.join("gt")).unwrap();
    let known: BTreeMap<ImageId, BodyPose> = gt
        .iter()
        .map(|(name, pose)| {
            (
                db.image_by_name(name).unwrap().id,
                BodyPose::from_cam_from_world(pose),
            )
        })
        .collect();
    let pose_file = dir.path().join("known_pose.ply");
    write_pose_ply(&pose_file, &known).unwrap();
    let with_priors = map_scene(&scene, &dir.path().join("priors"), |args| {
        args.pose_priors = Some(pose_file.clone());
        args.init_pose = vec![perturbed.map(|v| v.to_string()).join(",")];
    });
    print_run(
        "yard, perturbed initial pose, true poses as priors",
        &with_priors,
    );
    check_run(&with_priors);

    // Bad inputs on a real database: nothing written.
    let out = dir.path().join("bad");
    let base = scene_args(&scene, &out, &exact);
    let err = run_map(&MapArgs {
        init_image: vec!["no_such_image.jpg".into()],
        ..base.clone()
    })
    .unwrap_err();
    assert!(
        format!("{err:#}").contains("unknown initial image `no_such_image.jpg`"),
        "{err:#}"
    );
    assert!(!out.exists());
    // Looking straight up from far above the scene: no map point in view.
    let away = format!("{},{},{},0,-90,0", exact[0], exact[1], exact[2] + 500.0);
    let err = run_map(&MapArgs {
        init_pose: vec![away],
        ..base.clone()
    })
    .unwrap_err();
    assert!(
        format!("{err:#}").contains("sees no usable map point"),
        "{err:#}"
    );
    assert!(!out.exists());
    // An initial pose 1.1 m and 8 deg off: the run from it fails, never a
    // wrong model without an error. The initial image cannot end within the
    // default 1 m of that pose and be right; from such poses the map pulls
    // the model in on some databases and draws it to a wrong place on
    // others (the seed-7 yard of one COLMAP run: 1.54 m off with enough
    // points near map surfaces to pass that test), which COLMAP's
    // matching, different run to run, decides. The mapper then searches the
    // map within 2 m and 30 deg of that pose (`bundle.fallback_search_m`)
    // and maps from what it finds: as right as from the exact pose.
    let mut far = exact;
    far[0] += 1.0;
    far[1] -= 0.5;
    far[5] += 8.0;
    let far_run = map_scene_from(&scene, &dir.path().join("far"), &far, |_| {});
    print_run(
        "yard from 1.1 m / 8 deg off, the search after the failed run",
        &far_run,
    );
    let search = &far_run.report["init_search"];
    eprintln!("init_search: {search}");
    let msg = search["after_failure"]
        .as_str()
        .expect("the run from the pose failed first");
    assert!(
        msg.contains("from its given pose") || msg.contains("does not fit the map"),
        "{msg}"
    );
    // A moved initial image's error says how well the model fits the map.
    if msg.contains("from its given pose (") {
        assert!(
            msg.contains(
                "of its points on the surfaces their images see, similarity-constraint ratio"
            ),
            "{msg}"
        );
    }
    assert!(
        search["first_run_s"].as_f64().is_some_and(|s| s > 0.0),
        "{search}"
    );
    assert_eq!(search["region"]["radius_m"].as_f64(), Some(2.0), "{search}");
    check_run(&far_run);
    check_as_from_the_exact_pose(&far_run, &a);
    // The check itself: a share no real model reaches fails the run, names
    // the inputs, and nothing is written.
    let strict = dir.path().join("strict.toml");
    // (Without the search that follows a failed run: every placement's
    // model would fail the same check.)
    std::fs::write(
        &strict,
        "[mapper.association]\nmin_points_on_map_share = 1.0\n[mapper.bundle]\nfallback_search_m = 0\n",
    )
    .unwrap();
    let err = run_map(&MapArgs {
        options: Some(strict),
        ..base.clone()
    })
    .unwrap_err();
    let msg = format!("{err:#}");
    assert!(
        msg.contains("does not fit the map")
            && msg.contains("database.db")
            && msg.contains("lidar.ply"),
        "{msg}"
    );
    assert!(!out.exists());
    // A pose file with a bad line: the file and the line are named.
    let text = std::fs::read_to_string(&pose_file).unwrap();
    let bad_pose_file = dir.path().join("bad_pose.ply");
    std::fs::write(
        &bad_pose_file,
        text.replacen("end_header\n", "end_header\n1 2 x 4 5 6\n", 1),
    )
    .unwrap();
    let err = run_map(&MapArgs {
        pose_priors: Some(bad_pose_file.clone()),
        ..base.clone()
    })
    .unwrap_err();
    let msg = format!("{err:#}");
    assert!(
        msg.contains("bad_pose.ply") && msg.contains("line 13"),
        "{msg}"
    );
    assert!(!out.exists());
    // An image folder without one of the database's images: named, before
    // the run, nothing written.
    let partial = dir.path().join("partial_images");
    std::fs::create_dir(&partial).unwrap();
    std::fs::copy(
        scene.join("images").join(image_name(0)),
        partial.join(image_name(0)),
    )
    .unwrap();
    let err = run_map(&MapArgs {
        image_path: Some(partial),
        ..base.clone()
    })
    .unwrap_err();
    let msg = format!("{err:#}");
    // The check goes in database id order, and COLMAP's feature extractor
    // on two threads does not always give the images their ids in name
    // order (a CI run named frame_0002): the first missing one by id.
    let first_missing = db
        .images
        .values()
        .map(|img| &img.name)
        .find(|name| **name != image_name(0))
        .unwrap();
    let named_missing = msg.contains(&format!("`{first_missing}`"));
    assert!(
        named_missing && msg.contains("not in the image folder"),
        "{msg}"
    );
    assert!(!out.exists());
    // The same through the binary.
    let run_bin = |extra: &[&str]| {
        let mut cmd = std::process::Command::new(crate::common::bin());
        cmd.arg("map")
            .arg("--database_path")
            .arg(scene.join("database.db"))
            .arg("--lidar")
            .arg(scene.join("lidar.ply"))
            .arg("--output_path")
            .arg(&out)
            .arg(format!(
                "--init-pose={}",
                exact.map(|v| v.to_string()).join(",")
            ))
            .arg("--image_path")
            .arg(scene.join("images"))
            .args(extra);
        cmd.output().unwrap()
    };
    let o = run_bin(&["--init-image", "no_such_image.jpg"]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("unknown initial image"));
    assert!(!out.exists());
    let o = run_bin(&["--init-image", "frame_0000.jpg", "--input-units", "yd"]);
    assert!(!o.status.success());
    let msg = String::from_utf8_lossy(&o.stderr);
    assert!(
        msg.contains("--input-units") && msg.contains("`yd`"),
        "{msg}"
    );
    assert!(!out.exists());
    // A map said to be in metres is read as it is: the same model.
    let o = run_bin(&["--init-image", "frame_0000.jpg", "--input-units", "m"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for f in ["cameras.txt", "images.txt", "points3D.txt"] {
        let x = std::fs::read(dir.path().join("a").join(f)).unwrap();
        let y = std::fs::read(out.join(f)).unwrap();
        assert!(x == y, "{f}: the binary and the library disagree");
    }
}

/// `prepare-map --input raw --output prepared` run as a user would (the
/// binary, default options); its standard output, printed. Fails the test
/// when it fails.
fn run_prepare_map(raw: &Path, prepared: &Path) -> String {
    let out = std::process::Command::new(crate::common::bin())
        .args(["prepare-map", "--input"])
        .arg(raw)
        .arg("--output")
        .arg(prepared)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout).into_owned();
    eprintln!("prepare-map: {text}");
    assert!(
        out.status.success(),
        "{text}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    text
}

/// The number before `after` in `text` (`after` names what follows it).
fn number_before(text: &str, after: &str) -> f64 {
    let end = text
        .find(after)
        .unwrap_or_else(|| panic!("{after:?} in {text}"));
    let head = text[..end].trim_end();
    let start = head
        .rfind(|c: char| !(c.is_ascii_digit() || c == '.' || c == '-' || c == 'e'))
        .map_or(0, |i| i + 1);
    head[start..]
        .parse()
        .unwrap_or_else(|_| panic!("number before {after:?} in {text}"))
}

/// The yard's map cut at x = 3 m (`prepare-map --crop`): the photos facing
/// +x see no map. Most points the map does cover fit it (measured 86-97 %),
/// but the surfaces they lie on hold the model's similarity only weakly
/// (ratio 2.8e-3 to 4.5e-3 measured, under the 1e-2 a partly mapped model
/// needs: cut at 2-7 m the yard ended 16-74 mm and 0.2-0.5 deg off), so the
/// run is refused with both numbers in the error and nothing written.
/// A rough initial pose (1.3 m off, heading 15 deg, roll 4 deg, pitch 3
/// deg) with `--init-search 2,30`: the search puts the initial image where
/// it is, and the run ends as right as the one from the exact pose (`exact`).
fn check_init_search(scene: &Path, work: &Path, exact_run: &Run) {
    let (exact, _) = read_init_pose(&scene.join("init_pose.txt")).unwrap();
    let rough = rough_pose(scene);
    let off = &ROUGH_OFFSET[..3];
    let out = work.join("searched");
    let run = map_scene_from(scene, &out, &rough, |args| {
        args.init_search = Some("2,30".to_owned())
    });
    let gt = load_poses(&scene.join("gt")).unwrap();
    print_run("yard from a rough pose, --init-search 2,30", &run);
    let search = &run.report["init_search"];
    eprintln!("init_search: {search}");
    // Asked for: no run from the rough pose first.
    assert!(search["after_failure"].is_null() && search["first_run_s"].is_null());
    let found: Vec<f64> = search["found_centre"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    let miss = (0..3)
        .map(|k| (found[k] - exact[k]).powi(2))
        .sum::<f64>()
        .sqrt();
    assert!(
        miss < 0.05,
        "the search put the initial camera {miss:.3} m from it"
    );
    let moved = search["moved_m"].as_f64().unwrap();
    let off_m = off.iter().map(|d| d * d).sum::<f64>().sqrt();
    assert!(
        (moved - off_m).abs() < 0.05,
        "moved {moved:.3} m of {off_m:.3}"
    );
    assert!(search["on_map"].as_u64().unwrap() > search["runner_up_on_map"].as_u64().unwrap_or(0));
    // The run without the map's planes started from the initial image and
    // a second one by their essential matrix, at a scale from the map's
    // depths that the search then corrected: the pair's baseline in the
    // finished plain model (its solves hold it only softly), placed on the
    // map by the search's scale.
    let model = read_model(&out).unwrap();
    let name_of = |id: u64| model.images[&ImageId(id as u32)].name.clone();
    let second = name_of(search["plain_second_image"].as_u64().unwrap());
    let first = name_of(run.report["init"]["initial_image"].as_u64().unwrap());
    let baseline = (gt[&second].camera_center() - gt[&first].camera_center()).norm();
    let found = search["scale"].as_f64().unwrap()
        * search["plain_pair_baseline"]
            .as_f64()
            .expect("the plain run started from a pair");
    assert!(
        (found / baseline - 1.0).abs() < 0.02,
        "the pair's baseline {found:.4} m in the search's placement, {baseline:.4} m in truth"
    );
    check_as_from_the_exact_pose(&run, exact_run);
}

/// A copy of the scene's database in `work` whose images carry GPS
/// positions as COLMAP 3.8's feature extractor stores them from EXIF
/// (`prior_t*` = latitude, longitude, altitude, no rotation): the true
/// centres in UTM 33N, the map's (0, 0, 0) at `origin`, with Gaussian
/// noise of `sigma_h` / `sigma_v` metres and, with `wrong`, one image's
/// position 40 m off.
fn database_with_gps(
    scene: &Path,
    work: &Path,
    name: &str,
    origin: [f64; 3],
    (sigma_h, sigma_v): (f64, f64),
    wrong: Option<&str>,
) -> PathBuf {
    use colmap_lidar::geo::TransverseMercator;
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};
    let db = work.join(name);
    std::fs::copy(scene.join("database.db"), &db).unwrap();
    let gt = load_poses(&scene.join("gt")).unwrap();
    let utm = TransverseMercator::utm(33, true);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    let (h, v) = (
        Normal::new(0.0, sigma_h).unwrap(),
        Normal::new(0.0, sigma_v).unwrap(),
    );
    let conn = rusqlite::Connection::open(&db).unwrap();
    for (image, pose) in &gt {
        let c = pose.camera_center();
        let mut e = [
            c.x + origin[0] + h.sample(&mut rng),
            c.y + origin[1] + h.sample(&mut rng),
            c.z + origin[2] + v.sample(&mut rng),
        ];
        if wrong == Some(image.as_str()) {
            e[0] += 40.0;
        }
        let (lat, lon) = utm.inverse(e[0], e[1]);
        let changed = conn
            .execute(
                "UPDATE images SET prior_qw = NULL, prior_qx = NULL, prior_qy = NULL, prior_qz = NULL, \
                 prior_tx = ?1, prior_ty = ?2, prior_tz = ?3 WHERE name = ?4",
                rusqlite::params![lat, lon, e[2], image],
            )
            .unwrap();
        assert_eq!(changed, 1, "{image}");
    }
    db
}

/// No initial pose: the images' GPS positions (0.3 m horizontally, 1 m
/// vertically, one 40 m off; the map shifted from UTM 33N) place the model
/// as the exact pose does; positions that scatter more than the photos
/// spread, or no --map-crs, are errors that say so.
fn check_gps(scene: &Path, work: &Path, exact_run: &Run) {
    let origin = [500_000.0, 4_400_000.0, 200.0];
    let wrong = image_name(5);
    let db = database_with_gps(scene, work, "gps.db", origin, (0.3, 1.0), Some(&wrong));
    let out = work.join("gps");
    let gps_args = |db: &Path, out: &Path, crs: bool| MapArgs {
        database: Some(db.to_path_buf()),
        lidar: Some(scene.join("lidar.ply")),
        output: Some(out.to_path_buf()),
        map_crs: crs.then(|| "EPSG:32633".to_owned()),
        map_origin: crs.then(|| "500000,4400000,200".to_owned()),
        ..Default::default()
    };
    let run = run_evaluated(&gps_args(&db, &out, true), &scene.join("gt"))
        .expect("map from the GPS positions");
    let gt = load_poses(&scene.join("gt")).unwrap();
    print_run(
        "yard from its GPS positions (0.3 m / 1 m, one 40 m off)",
        &run,
    );
    let positions = &run.report["positions"];
    eprintln!("positions: {positions}");
    assert_eq!(positions["crs"], "EPSG:32633");
    assert_eq!(positions["num_images"].as_u64(), Some(gt.len() as u64));
    // The wrong position is left out of the fit, the others kept.
    assert_eq!(positions["num_inliers"].as_u64(), Some(gt.len() as u64 - 1));
    let sigma = positions["horizontal_sigma_m"].as_f64().unwrap();
    assert!((0.15..0.8).contains(&sigma), "{positions}");
    // The search looked where the fit said, a few degrees about its heading.
    let region = &positions["region"];
    assert_eq!(&run.report["init_search"]["region"], region);
    assert!(region["yaw_deg"].as_f64().unwrap() < 45.0, "{region}");
    // The finished model against the positions: their noise, and the
    // wrong one 40 m off.
    let median = positions["final_horizontal_median_m"].as_f64().unwrap();
    let max = positions["final_horizontal_max_m"].as_f64().unwrap();
    assert!(median < 0.6 && (max - 40.0).abs() < 2.0, "{positions}");
    check_as_from_the_exact_pose(&run, exact_run);

    // The same positions without the map's CRS: the error says what to give.
    let err = run_map(&gps_args(&db, &work.join("gps_no_crs"), false))
        .expect_err("no initial pose")
        .to_string();
    assert!(
        err.contains("--map-crs")
            && err.contains(&format!("{} images have a GPS position", gt.len())),
        "{err}"
    );
    // The map's shift forgotten: the positions are 4400 km off, an error
    // before any mapping.
    let mut unshifted = gps_args(&db, &work.join("gps_unshifted"), true);
    unshifted.map_origin = None;
    let err = format!("{:#}", run_map(&unshifted).expect_err("far from the map"));
    assert!(
        err.contains("lie 4") && err.contains("--map-origin"),
        "{err}"
    );
    // Positions scattered by 3 m over photos 2-3 m apart fix no heading.
    let loose = database_with_gps(scene, work, "gps3.db", origin, (3.0, 3.0), None);
    let err = format!(
        "{:#}",
        run_map(&gps_args(&loose, &work.join("gps_loose"), true)).expect_err("too loose")
    );
    assert!(
        err.contains("do not fix its heading") && err.contains("--init-search"),
        "{err}"
    );
    for out in ["gps_loose", "gps_no_crs", "gps_unshifted"] {
        assert!(!work.join(out).exists(), "{out}");
    }
}

/// A run from a rough pose meets the bar of the run from the exact one: the
/// same images registered, the camera-centre median under 1 cm and within
/// 1.5 times the exact run's + 1 mm.
fn check_as_from_the_exact_pose(run: &Run, exact_run: &Run) {
    assert_eq!(run.none.num_registered, exact_run.none.num_registered);
    let median = |r: &Run| r.none.centre_error_m.as_ref().unwrap().median;
    assert!(
        median(run) < 0.01 && median(run) < 1.5 * median(exact_run) + 0.001,
        "{:.4} m from the rough pose, {:.4} m from the exact one",
        median(run),
        median(exact_run)
    );
}

fn check_partial_map(scene: &Path, work: &Path) {
    use colmap_lidar::commands::prepare_map::prepare_map_file;
    use colmap_lidar::map::prepare::{CropBox, PrepareOptions};
    let cut = work.join("lidar_x3.ply");
    let (_, prepared) = prepare_map_file(
        &scene.join("lidar.ply"),
        &cut,
        &PrepareOptions {
            voxel_size_m: 0.0,
            crop: Some(CropBox::parse("-100,-100,-100,3,100,100").unwrap()),
            ..Default::default()
        },
    )
    .unwrap();
    assert!(
        prepared.dropped_by_crop > prepared.input_points / 4
            && prepared.output_points > prepared.input_points / 4,
        "{prepared:?}"
    );
    let once = work.join("no_retry.toml");
    std::fs::write(
        &once,
        "[mapper.bundle]\nretry_holding_initial = false\nfallback_search_m = 0\n",
    )
    .unwrap();
    let (exact, _) = read_init_pose(&scene.join("init_pose.txt")).unwrap();
    let out = work.join("cut_at_x3");
    let mut args = scene_args(scene, &out, &exact);
    args.lidar = Some(cut);
    args.options = Some(once);
    let msg = format!("{:#}", run_map(&args).unwrap_err());
    eprintln!("yard, map cut at x = 3 m: {msg}");
    let coverage = number_before(&msg, "% of them, and");
    let covered_fit = number_before(&msg, "% of those are on it");
    let ratio = number_before(&msg, "(a map that covers only part");
    assert!((10.0..50.0).contains(&coverage), "{msg}");
    // Most of the covered points fit (86-97 % measured on two databases):
    // it is the ratio that refuses the model.
    assert!(covered_fit >= 70.0, "{msg}");
    assert!(ratio < 1e-2, "{msg}");
    assert!(msg.contains("lidar_x3.ply"), "{msg}");
    assert!(!out.exists());
}

/// `map --input-model`: half the yard's model (its first 12 trajectory
/// images) extended with the other 12 from the same database, held and free;
/// a model moved off the map is refused.
/// One `map` run with one initial image per group: a copy of the yard's
/// database without any verified pair (nor match) between frames 0-11 and
/// 12-23, each group from its first frame's true pose. Every image in one
/// model at the truth (as the connected database's run: the bar of
/// `check_run`), `report.json` with both runs and the whole model's counts,
/// `pose.ply` with every image, COLMAP reads it; one initial image maps its
/// group alone and says why the others are not in.
fn check_groups(scene: &Path, work: &Path, connected: &Run) {
    let db = work.join("groups.db");
    std::fs::copy(scene.join("database.db"), &db).unwrap();
    let conn = rusqlite::Connection::open(&db).unwrap();
    let first: BTreeSet<i64> = (0..12)
        .map(|k| {
            conn.query_row(
                "SELECT image_id FROM images WHERE name = ?1",
                [image_name(k)],
                |row| row.get(0),
            )
            .unwrap()
        })
        .collect();
    let mut cut = 0;
    for table in ["two_view_geometries", "matches"] {
        let pairs: Vec<i64> = conn
            .prepare(&format!("SELECT pair_id FROM {table}"))
            .unwrap()
            .query_map([], |row| row.get(0))
            .unwrap()
            .map(Result::unwrap)
            .collect();
        for pair in pairs {
            let (a, b) = (pair / 2147483647, pair % 2147483647);
            if first.contains(&a) != first.contains(&b) {
                cut += conn
                    .execute(&format!("DELETE FROM {table} WHERE pair_id = ?1"), [pair])
                    .unwrap();
            }
        }
    }
    drop(conn);
    assert!(cut > 10, "{cut} rows deleted");
    let gt = load_poses(&scene.join("gt")).unwrap();
    let pose_of = |k: usize| {
        BodyPose::from_cam_from_world(&gt[&image_name(k)])
            .to_degrees_array()
            .map(|v| v.to_string())
            .join(",")
    };
    let exact = |k: usize| -> [f64; 6] {
        BodyPose::from_cam_from_world(&gt[&image_name(k)]).to_degrees_array()
    };
    let out = work.join("groups");
    let both = map_scene_from(scene, &out, &exact(0), |args| {
        args.database = Some(db.clone());
        args.init_image.push(image_name(12));
        args.init_pose.push(pose_of(12));
    });
    print_run("yard in two groups, one run", &both);
    // Each half of the yard holds its model less than the whole (measured:
    // 6.9 mm median, p90 9.5 mm, rotation 0.048 deg against 2.4 mm and
    // 0.014 deg connected; each group as in its own run): issue 6's centre
    // bar, and twice its rotation bar.
    assert_eq!(both.none.num_registered, 24);
    let c = both.none.centre_error_m.as_ref().unwrap();
    assert!(c.median < 0.01 && c.p90 < 0.02, "centre errors {c:?}");
    let rot = both.none.rotation_error_deg.as_ref().unwrap();
    assert!(rot.median < 0.1, "rotation errors {rot:?}");
    let c0 = connected.none.centre_error_m.as_ref().unwrap();
    eprintln!(
        "two groups: median {:.2} mm, p90 {:.2} mm (connected database {:.2} / {:.2} mm)",
        c.median * 1e3,
        c.p90 * 1e3,
        c0.median * 1e3,
        c0.p90 * 1e3
    );
    let report = &both.report;
    assert_eq!(report["num_registered"].as_u64(), Some(24));
    assert_eq!(report["images"].as_array().unwrap().len(), 24);
    let groups = report["groups"].as_array().unwrap();
    assert_eq!(groups.len(), 2);
    for (g, k) in groups.iter().zip([0, 12]) {
        assert_eq!(g["init_image"].as_str(), Some(image_name(k).as_str()));
        assert_eq!(
            (g["num_images"].as_u64(), g["num_registered"].as_u64()),
            (Some(12), Some(12)),
            "{g}"
        );
    }
    assert!(groups[0]["report"].is_null());
    assert_eq!(groups[1]["report"]["num_registered"].as_u64(), Some(12));
    let points = report["num_points"].as_u64().unwrap();
    assert_eq!(
        points,
        groups[0]["num_points"].as_u64().unwrap() + groups[1]["num_points"].as_u64().unwrap()
    );
    assert_eq!(read_pose_ply(&out.join("pose.ply")).unwrap().len(), 24);
    if have_colmap() {
        let text = crate::common::run_colmap([
            "model_analyzer".as_ref(),
            "--path".as_ref(),
            out.as_os_str(),
        ]);
        assert!(text.contains("Registered images: 24"), "{text}");
    }
    // One initial image: its group, and the other named.
    let one = work.join("groups_one");
    let args = MapArgs {
        database: Some(db.clone()),
        ..scene_args(scene, &one, &exact(0))
    };
    run_map(&args).unwrap();
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(one.join("report.json")).unwrap()).unwrap();
    assert_eq!(report["num_registered"].as_u64(), Some(12));
    assert!(report.get("groups").is_none());
    let other = report["images"]
        .as_array()
        .unwrap()
        .iter()
        .find(|r| r["name"] == image_name(12).as_str())
        .unwrap();
    assert_eq!(other["not_registered"]["reason"], "other_group", "{other}");
    // The first group where its own run puts it (measured: the same errors
    // to 0.01 mm).
    let (together, alone) = (load_poses(&out).unwrap(), load_poses(&one).unwrap());
    assert_eq!(alone.len(), 12);
    for (name, pose) in &alone {
        let moved = (together[name].camera_center() - pose.camera_center()).norm();
        assert!(moved < 1e-3, "{name}: {moved} m from its own run");
    }
    // Two initial images of one group: an error naming both, nothing written.
    let same = work.join("groups_same");
    let args = MapArgs {
        database: Some(db.clone()),
        init_image: vec![image_name(0), image_name(3)],
        init_pose: vec![pose_of(0), pose_of(3)],
        ..scene_args(scene, &same, &exact(0))
    };
    let err = format!("{:#}", run_map(&args).unwrap_err());
    assert!(
        err.contains(&format!(
            "{} and {} are in one group",
            image_name(0),
            image_name(3)
        )),
        "{err}"
    );
    assert!(!same.exists());
}

fn check_extension(scene: &Path, model_dir: &Path, work: &Path) {
    let full = read_model(model_dir).unwrap();
    let first: BTreeSet<String> = (0..12).map(image_name).collect();
    let half = crate::common::part_of_model(&full, |img| first.contains(&img.name));
    assert_eq!(half.images.len(), 12);
    let half_dir = work.join("half");
    write_model(&half_dir, &half, ModelFormat::Text).unwrap();
    let extend = |out: &str, model: &Path, hold: bool| {
        let args = MapArgs {
            database: Some(scene.join("database.db")),
            lidar: Some(scene.join("lidar.ply")),
            output: Some(work.join(out)),
            input_model: Some(model.to_path_buf()),
            fix_existing_images: hold,
            ..Default::default()
        };
        run_evaluated(&args, &scene.join("gt"))
    };
    for hold in [true, false] {
        let out = if hold {
            "extended-held"
        } else {
            "extended-free"
        };
        let r = extend(out, &half_dir, hold).expect("extending the half model");
        print_run(&format!("yard, half its model extended (held: {hold})"), &r);
        check_run(&r);
        assert_eq!(r.none.num_registered, full.num_registered_images());
        let input = &r.report["input_model"];
        assert_eq!(input["num_images"].as_u64(), Some(12), "{input}");
        assert_eq!(input["held"].as_bool(), Some(hold), "{input}");
        assert!(r.report["init"].is_null());
        let flagged: BTreeSet<String> = r.report["images"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|i| i["from_input_model"].as_bool() == Some(true))
            .map(|i| i["name"].as_str().unwrap().to_owned())
            .collect();
        assert_eq!(flagged, first);
        let extended = read_model(&work.join(out)).unwrap();
        let mut moved_mm: f64 = 0.0;
        for img in half.images.values() {
            let given = img.cam_from_world.unwrap();
            let now = extended
                .image_by_name(&img.name)
                .unwrap()
                .cam_from_world
                .unwrap();
            moved_mm = moved_mm.max((now.camera_center() - given.camera_center()).norm() * 1e3);
            if hold {
                // Held: the very pose it came with (the text model is exact).
                assert_eq!(now, given, "{}", img.name);
            }
        }
        if hold {
            assert_eq!(extended.cameras, half.cameras);
        } else {
            // Free: refined with the new images, by about the model's error.
            assert!(moved_mm > 0.0 && moved_mm < 5.0, "moved {moved_mm} mm");
        }
    }
    // Every image already in the model, held: nothing to register or
    // solve; the poses come out as they went in.
    let r = extend("extended-none", model_dir, true).expect("a complete held model");
    assert_eq!(r.none.num_registered, full.num_registered_images());
    let same = read_model(&work.join("extended-none")).unwrap();
    for img in full.registered_images() {
        assert_eq!(same.images[&img.id].cam_from_world, img.cam_from_world);
    }
    // The half model moved by a similarity (scale about its first camera).
    let moved = |name: &str, shift: [f64; 3], scale: f64| -> PathBuf {
        let mut m = half.clone();
        let d = nalgebra::Vector3::from(shift);
        let o = m
            .images
            .values()
            .next()
            .unwrap()
            .cam_from_world
            .unwrap()
            .camera_center();
        let to = |x: nalgebra::Vector3<f64>| o + (x - o) * scale + d;
        for img in m.images.values_mut() {
            let pose = img.cam_from_world.as_mut().unwrap();
            let c = to(pose.camera_center());
            pose.translation = -(pose.rotation * c);
        }
        for p in m.points3d.values_mut() {
            p.xyz = to(p.xyz);
        }
        let dir = work.join(name);
        write_model(&dir, &m, ModelFormat::Text).unwrap();
        dir
    };
    // 0.3 m off: free, the map moves it back first (measured on the seed-0
    // yard and room from 0.09-0.73 m off: the same errors as in place);
    // held, it is refused before any work, with how far the map would move it.
    let off = moved("half-off", [0.2, 0.2, 0.1], 1.0);
    let r = extend("extended-off", &off, false).expect("a model 0.3 m off, free");
    print_run("yard, half its model 0.3 m off, extended free", &r);
    check_run(&r);
    let a = &r.report["input_model"]["alignment"];
    assert_eq!(a["applied"].as_bool(), Some(true), "{a}");
    let t = a["translation_m"].as_f64().unwrap();
    assert!((t - 0.3).abs() < 0.01, "{a}");
    let err = extend("extended-off-held", &off, true)
        .map(|_| ())
        .unwrap_err();
    let msg = format!("{err:#}");
    assert!(
        msg.contains("not in the map's frame") && msg.contains("would move the held input model"),
        "{msg}"
    );
    assert!(!work.join("extended-off-held").exists());
    // In another frame altogether (as plain SfM leaves it: scale 0.7):
    // refused, free as well.
    let foreign = moved("half-foreign", [1.0, -2.0, 0.5], 0.7);
    let err = extend("extended-foreign", &foreign, false)
        .map(|_| ())
        .unwrap_err();
    let msg = format!("{err:#}");
    assert!(msg.contains("not in the map's frame"), "{msg}");
    assert!(!work.join("extended-foreign").exists());
}

/// Runs the real `colmap color_extractor` on `model` with `images`; returns
/// its points' colours.
fn colmap_colours(model: &Path, images: &Path, out: &Path) -> BTreeMap<u64, [u8; 3]> {
    std::fs::create_dir_all(out).unwrap();
    crate::common::run_colmap([
        "color_extractor".as_ref(),
        "--input_path".as_ref(),
        model.as_os_str(),
        "--output_path".as_ref(),
        out.as_os_str(),
        "--image_path".as_ref(),
        images.as_os_str(),
    ]);
    read_model(out)
        .unwrap()
        .points3d
        .iter()
        .map(|(id, p)| (id.0, p.color))
        .collect()
}

/// How two colourings of the same points differ.
struct ColourDifferences {
    /// Largest absolute channel difference, and the point that has it.
    max: i32,
    worst: colmap_lidar::scene::Point3DId,
    /// Mean absolute channel difference.
    mean: f64,
    /// Share of points whose three channels agree exactly.
    exact: f64,
}

fn colour_differences(
    ours: &colmap_lidar::scene::Reconstruction,
    theirs: &BTreeMap<u64, [u8; 3]>,
) -> ColourDifferences {
    assert_eq!(ours.points3d.len(), theirs.len());
    let (mut max, mut worst, mut sum, mut exact) = (-1, None, 0.0, 0);
    for (id, p) in &ours.points3d {
        let t = theirs[&id.0];
        let d: Vec<i32> = (0..3)
            .map(|k| (i32::from(p.color[k]) - i32::from(t[k])).abs())
            .collect();
        let largest = *d.iter().max().unwrap();
        if largest > max {
            (max, worst) = (largest, Some(*id));
        }
        sum += f64::from(d.iter().sum::<i32>()) / 3.0;
        exact += usize::from(largest == 0);
    }
    let n = ours.points3d.len() as f64;
    ColourDifferences {
        max,
        worst: worst.expect("the model has points"),
        mean: sum / n,
        exact: exact as f64 / n,
    }
}

/// A PLY written by `colour-map`: per point (its coordinates' bits), the
/// colour and the number of views.
fn read_coloured_ply(path: &Path) -> BTreeMap<[u64; 3], ([u8; 3], u16)> {
    let bytes = std::fs::read(path).unwrap();
    let (header, end) = crate::common::ply_header(&bytes);
    let mut count = 0;
    let mut props: Vec<(String, usize)> = Vec::new();
    for line in header.lines() {
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            ["element", "vertex", n] => count = n.parse().unwrap(),
            ["property", ty, name] => {
                let size = match *ty {
                    "double" => 8,
                    "float" => 4,
                    "ushort" => 2,
                    "uchar" => 1,
                    other => panic!("{other}"),
                };
                props.push((name.to_string(), size));
            }
            _ => {}
        }
    }
    let stride: usize = props.iter().map(|p| p.1).sum();
    assert_eq!(bytes.len() - end, count * stride, "{}", path.display());
    let offset = |name: &str| {
        let k = props.iter().position(|p| p.0 == name).unwrap();
        (props[..k].iter().map(|p| p.1).sum::<usize>(), props[k].1)
    };
    let value = |row: &[u8], name: &str| -> f64 {
        let (o, size) = offset(name);
        match size {
            8 => f64::from_le_bytes(row[o..o + 8].try_into().unwrap()),
            4 => f64::from(f32::from_le_bytes(row[o..o + 4].try_into().unwrap())),
            2 => f64::from(u16::from_le_bytes(row[o..o + 2].try_into().unwrap())),
            _ => f64::from(row[o]),
        }
    };
    bytes[end..]
        .chunks(stride)
        .map(|row| {
            let key = ["x", "y", "z"].map(|c| value(row, c).to_bits());
            let rgb = ["red", "green", "blue"].map(|c| value(row, c) as u8);
            (key, (rgb, value(row, "views") as u16))
        })
        .collect()
}

/// Mean over the points both colour of the mean absolute difference of
/// their channels, and the number of those points.
fn map_colour_difference(
    a: &BTreeMap<[u64; 3], ([u8; 3], u16)>,
    b: &BTreeMap<[u64; 3], ([u8; 3], u16)>,
) -> (f64, usize) {
    let (mut sum, mut n) = (0.0, 0);
    for (key, (ca, _)) in a {
        if let Some((cb, _)) = b.get(key) {
            sum += (0..3)
                .map(|k| (f64::from(ca[k]) - f64::from(cb[k])).abs())
                .sum::<f64>()
                / 3.0;
            n += 1;
        }
    }
    (sum / n.max(1) as f64, n)
}

/// `colour-map` with the model's poses colours the map as the true poses
/// do (measured 0.30 levels apart on average; room 0 of session 30: 0.42),
/// and poses 2 cm off do not (4.3 levels; room 0: 8.4); the coloured PLY reads back as a map; a missing
/// image is an error that names it, with nothing written.
fn check_map_colours(scene: &Path, model_dir: &Path, work: &Path) {
    use colmap_lidar::commands::colour_map::{run as colour_map, ColourMapArgs};
    let args = |model: &Path, output: &Path| ColourMapArgs {
        lidar: scene.join("lidar.ply"),
        model: model.to_path_buf(),
        image_path: scene.join("images"),
        output: output.to_path_buf(),
        keep_unseen: false,
        max_view_angle: 75.0,
        occlusion_margin: 0.05,
        min_depth: 0.5,
        max_depth: 40.0,
    };
    let coloured = |model: &Path, name: &str| {
        let out = work.join(name);
        colour_map(&args(model, &out)).unwrap();
        read_coloured_ply(&out)
    };
    let ours = coloured(model_dir, "map_ours.ply");
    let truth = coloured(&scene.join("gt"), "map_truth.ply");
    // The model 2 cm off along every camera's x axis.
    let mut shifted = read_model(model_dir).unwrap();
    for image in shifted.images.values_mut() {
        if let Some(pose) = &mut image.cam_from_world {
            pose.translation.x += 0.02;
        }
    }
    let shifted_dir = work.join("shifted_model");
    colmap_lidar::io::model::write_model(
        &shifted_dir,
        &shifted,
        colmap_lidar::io::model::ModelFormat::Text,
    )
    .unwrap();
    let off = coloured(&shifted_dir, "map_shifted.ply");
    let (d_ours, n_ours) = map_colour_difference(&ours, &truth);
    let (d_off, _) = map_colour_difference(&off, &truth);
    eprintln!(
        "map colours: {} points coloured (truth {}), {n_ours} in both, {d_ours:.2} levels from the \
         true poses' colours (2 cm off: {d_off:.2})",
        ours.len(),
        truth.len()
    );
    assert!(n_ours as f64 > 0.98 * truth.len() as f64);
    assert!(d_ours < 1.5 && d_off > 3.0 * d_ours, "{d_ours} {d_off}");
    assert!(ours.values().all(|(_, views)| *views > 0));
    // The coloured map is a map: its points and normals read back.
    let (cloud, _) = colmap_lidar::map::io::read_point_cloud(&work.join("map_ours.ply")).unwrap();
    assert_eq!(cloud.len(), ours.len());
    assert!(cloud.normals.is_some());
    // `--keep-unseen` writes the whole map, the unseen points grey.
    let all = work.join("map_all.ply");
    colour_map(&ColourMapArgs {
        keep_unseen: true,
        ..args(model_dir, &all)
    })
    .unwrap();
    let all = read_coloured_ply(&all);
    let (map, _) = colmap_lidar::map::io::read_point_cloud(&scene.join("lidar.ply")).unwrap();
    assert_eq!(all.len(), map.len());
    let unseen: Vec<_> = all.values().filter(|(_, views)| *views == 0).collect();
    assert_eq!(unseen.len(), map.len() - ours.len());
    assert!(unseen.iter().all(|(rgb, _)| *rgb == [128; 3]));
    // An image missing from the folder: an error naming it, nothing written.
    let partial = work.join("colour_map_images");
    std::fs::create_dir_all(&partial).unwrap();
    let model = read_model(model_dir).unwrap();
    let mut names: Vec<&str> = model.registered_images().map(|i| i.name.as_str()).collect();
    names.sort();
    for name in &names[1..] {
        std::fs::copy(scene.join("images").join(name), partial.join(name)).unwrap();
    }
    let out = work.join("map_partial.ply");
    let output = std::process::Command::new(crate::common::bin())
        .arg("colour-map")
        .args(["--lidar".as_ref(), scene.join("lidar.ply").as_os_str()])
        .args(["--model".as_ref(), model_dir.as_os_str()])
        .args(["--image-path".as_ref(), partial.as_os_str()])
        .args(["--output".as_ref(), out.as_os_str()])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success());
    assert!(
        stderr.contains(names[0]) && stderr.contains("not in the image folder"),
        "{stderr}"
    );
    assert!(!out.exists());
}

/// `--image-path`: the keypoints were refined on the map's planes from
/// every registered image, read after mapping (the 24-image scenes refine
/// 89-94 % of the observations they try, the 100-image corridor 77 %, by
/// 0.2-0.3 px median).
fn check_refinement(report: &serde_json::Value) {
    let r = &report["keypoint_refinement"];
    let registered = report["num_registered"].as_u64().unwrap();
    assert_eq!(r["images_read"].as_u64(), Some(registered), "{r}");
    assert_eq!(r["over_memory_budget"].as_bool(), Some(false), "{r}");
    let tried = r["observations"].as_u64().unwrap();
    let refined = r["refined"].as_u64().unwrap();
    assert!(tried > 1000 && 2 * refined > tried, "{r}");
    let shift = r["median_shift_px"].as_f64().unwrap();
    assert!(shift > 0.02 && shift < 1.0, "{r}");
}

/// `--image-path`: every point has the colour COLMAP's own
/// `color_extractor` gives it. From the JPEG images the two decoders differ
/// by a level or two (measured on a yard: mean 0.95, largest 4); from PNG
/// copies (the same pixels for both) they agree exactly but for rounding
/// (measured: 1 point of 15089 off by 1).
fn check_colours(scene: &Path, model_dir: &Path, report: &serde_json::Value, work: &Path) {
    let model = read_model(model_dir).unwrap();
    let summary = &report["point_colours"];
    assert_eq!(
        summary["images_read"].as_u64(),
        Some(model.registered_images().count() as u64),
        "{summary}"
    );
    assert_eq!(
        summary["points_coloured"].as_u64(),
        Some(model.points3d.len() as u64)
    );
    assert_eq!(summary["unread"].as_array().map(Vec::len), Some(0));
    let grey = model
        .points3d
        .values()
        .filter(|p| p.color == [128; 3])
        .count();
    assert!(grey * 100 < model.points3d.len(), "{grey} grey points");
    let jpeg = colmap_colours(model_dir, &scene.join("images"), &work.join("colours_jpeg"));
    let ColourDifferences { max, mean, .. } = colour_differences(&model, &jpeg);
    eprintln!("colours against COLMAP's color_extractor (JPEG): largest {max}, mean {mean:.2}");
    assert!(max <= 8 && mean < 2.0, "largest {max}, mean {mean}");

    let png = work.join("png_images");
    std::fs::create_dir_all(&png).unwrap();
    for img in model.images.values() {
        let copy = png.join(&img.name);
        std::fs::create_dir_all(copy.parent().unwrap()).unwrap();
        image::open(scene.join("images").join(&img.name))
            .unwrap()
            .save_with_format(copy, image::ImageFormat::Png)
            .unwrap();
    }
    let mut ours = model.clone();
    ours.points3d.values_mut().for_each(|p| p.color = [0; 3]);
    let summary = colmap_lidar::io::images::colour_points(&mut ours, &png).unwrap();
    assert_eq!(summary.points_coloured, model.points3d.len());
    let theirs = colmap_colours(model_dir, &png, &work.join("colours_png"));
    let ColourDifferences {
        max,
        worst,
        mean,
        exact,
    } = colour_differences(&ours, &theirs);
    eprintln!(
        "colours against COLMAP's color_extractor (PNG): largest {max}, mean {mean:.4}, exact {exact:.4}"
    );
    let p = &ours.points3d[&worst];
    let keypoints: Vec<_> = p
        .track
        .iter()
        .map(|t| ours.images[&t.image_id].points2d[t.point2d_idx as usize].xy)
        .collect();
    assert!(
        max <= 1 && exact > 0.999,
        "largest {max} (point {worst}: ours {:?}, COLMAP {:?}, keypoints {keypoints:?}), exact share {exact}",
        p.color,
        theirs[&worst.0]
    );
}

/// The numbers of the issue: yard and room, 24 images, full feature count,
/// each once. `cargo test --release --test tests mapper::colmap_e2e::numbers -- --ignored --nocapture`;
/// scenes cached in `$MAPPER_SCENES` (default a temporary folder).
#[test]
#[ignore]
fn numbers() {
    if !have_colmap() {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let root =
        std::env::var_os("MAPPER_SCENES").map_or_else(|| tmp.path().to_path_buf(), PathBuf::from);
    for kind in [SceneKind::Yard, SceneKind::Room] {
        let scene = root.join(kind.name());
        scene_with_database(&scene, kind, 24, 8192);
        let r = map_scene(
            &scene,
            &tmp.path().join(format!("{}-map", kind.name())),
            |_| {},
        );
        print_run(kind.name(), &r);
        // `colmap mapper` on the same database, in the same run.
        let sparse = tmp.path().join(format!("{}-colmap", kind.name()));
        std::fs::create_dir_all(&sparse).unwrap();
        let t = std::time::Instant::now();
        let status = std::process::Command::new("colmap")
            .args(["mapper", "--database_path"])
            .arg(scene.join("database.db"))
            .arg("--image_path")
            .arg(scene.join("images"))
            .arg("--output_path")
            .arg(&sparse)
            .args(["--Mapper.num_threads", "2"])
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .status()
            .unwrap();
        let colmap_s = t.elapsed().as_secs_f64();
        assert!(status.success());
        eprintln!(
            "{}: colmap-lidar map {:.1} s, colmap mapper {:.1} s, ratio {:.2}",
            kind.name(),
            r.seconds,
            colmap_s,
            r.seconds / colmap_s
        );
        let r2 = map_scene(
            &scene,
            &tmp.path().join(format!("{}-nolidar", kind.name())),
            |a| a.no_lidar_constraints = true,
        );
        print_run(&format!("{} (no LiDAR terms)", kind.name()), &r2);
        std::env::set_var("MAPPER_PERTURBED", "1");
        let r3 = map_scene(
            &scene,
            &tmp.path().join(format!("{}-perturbed", kind.name())),
            |_| {},
        );
        std::env::remove_var("MAPPER_PERTURBED");
        print_run(
            &format!("{} (initial pose 0.3 m, 3 deg off)", kind.name()),
            &r3,
        );
    }
}

/// Runs `map` on the scene folder `$MAPPER_SCENE` (with database.db) into
/// `$MAPPER_OUT` and prints the evaluation; `MAPPER_NO_LIDAR=1` disables the
/// LiDAR terms. A debugging aid until the binary has the command wired.
#[test]
#[ignore]
fn map_one() {
    let (Some(scene), Some(out)) = (
        std::env::var_os("MAPPER_SCENE"),
        std::env::var_os("MAPPER_OUT"),
    ) else {
        eprintln!("set MAPPER_SCENE and MAPPER_OUT");
        return;
    };
    let no_lidar = std::env::var("MAPPER_NO_LIDAR").is_ok_and(|v| v == "1");
    let _ = env_logger::builder().is_test(true).try_init();
    let options = std::env::var_os("MAPPER_OPTIONS").map(PathBuf::from);
    let r = map_scene(Path::new(&scene), Path::new(&out), |a| {
        a.no_lidar_constraints = no_lidar;
        a.options = options;
    });
    print_run(&Path::new(&scene).display().to_string(), &r);
    let model = load_poses(Path::new(&out)).unwrap();
    let gt = load_poses(&Path::new(&scene).join("gt")).unwrap();
    for e in &r.none.images {
        // World-frame rotation offset W with R_model = R_gt W, as an axis-angle in degrees.
        let w = gt[&e.name].rotation.inverse() * model[&e.name].rotation;
        let d = w.scaled_axis() * 180.0 / std::f64::consts::PI;
        let dc = model[&e.name].camera_center() - gt[&e.name].camera_center();
        eprintln!(
            "  {} centre {:.4} m rotation {:.3} deg, W = [{:.3} {:.3} {:.3}] deg, dC = [{:.4} {:.4} {:.4}] m",
            e.name, e.centre_error_m, e.rotation_error_deg, d.x, d.y, d.z, dc.x, dc.y, dc.z
        );
    }
    let sim3 = evaluate(&model, &gt, Alignment::Sim3).unwrap();
    eprintln!(
        "after Sim3 alignment: centre median {:.4} m, rotation median {:.3} deg, scale {:.5}",
        sim3.centre_error_m.as_ref().unwrap().median,
        sim3.rotation_error_deg.as_ref().unwrap().median,
        sim3.sim3_scale.unwrap()
    );
}

/// Debugging aid: the rigid correction (small rotation about the centroid,
/// translation) that the LiDAR plane associations alone ask of the model in
/// `$MAPPER_OUT`, with the map of `$MAPPER_SCENE`.
#[test]
#[ignore]
fn plane_bias() {
    use colmap_lidar::map::index::MapIndex;
    use colmap_lidar::sfm::associate::{AssociationQuery, NearestNeighbourAssociator, SolveKind};
    use nalgebra::{Matrix6, Vector3, Vector6};
    let (Some(scene), Some(out)) = (
        std::env::var_os("MAPPER_SCENE"),
        std::env::var_os("MAPPER_OUT"),
    ) else {
        return;
    };
    let rec = colmap_lidar::io::model::read_model(Path::new(&out)).unwrap();
    let cloud =
        colmap_lidar::commands::map::load_map(&Path::new(&scene).join("lidar.ply")).unwrap();
    let index = MapIndex::build(&cloud).unwrap();
    let assoc = NearestNeighbourAssociator::new(&cloud, &index, Default::default());
    let pts: Vec<Vector3<f64>> = rec.points3d.values().map(|p| p.xyz).collect();
    let queries: Vec<AssociationQuery> = pts
        .iter()
        .enumerate()
        .map(|(i, p)| AssociationQuery {
            point_idx: i as u32,
            point_id: colmap_lidar::scene::Point3DId(i as u64),
            position_in_world: *p,
            num_global_ba: 10,
            track_len: 2,
        })
        .collect();
    let planes = assoc.associate_points(SolveKind::Final, &queries);
    let c = pts.iter().sum::<Vector3<f64>>() / pts.len() as f64;
    let mut a = Matrix6::<f64>::zeros();
    let mut b = Vector6::<f64>::zeros();
    let mut sum_abs = 0.0;
    for p in &planes {
        let x = pts[p.point_idx as usize];
        let n = Vector3::from(p.normal);
        let r = n.dot(&x) - p.offset_m;
        sum_abs += r.abs();
        let j = Vector6::new(
            ((x - c).cross(&n)).x,
            ((x - c).cross(&n)).y,
            ((x - c).cross(&n)).z,
            n.x,
            n.y,
            n.z,
        );
        a += j * j.transpose();
        b += j * r;
    }
    let d = a.try_inverse().unwrap() * (-b);
    eprintln!(
        "{} planes for {} points, mean |d| {:.4} m; correction: rotation [{:.3} {:.3} {:.3}] deg, translation [{:.4} {:.4} {:.4}] m",
        planes.len(),
        pts.len(),
        sum_abs / planes.len() as f64,
        d[0].to_degrees(),
        d[1].to_degrees(),
        d[2].to_degrees(),
        d[3],
        d[4],
        d[5]
    );
}
