//! Integration tests: synthetic scenes (ground truth, LiDAR, projections), the
//! COLMAP database harness and the evaluate command.
use std::collections::BTreeMap;
use std::io::Read;
use std::path::Path;

use colmap_lidar::eval::{evaluate, load_poses, Alignment};
use colmap_lidar::io::database::read_database;
use colmap_lidar::scene::{CameraModel, Rigid3};
use colmap_lidar::synth::generate::FISHEYE_FOCAL_FACTOR;
use colmap_lidar::synth::geometry::{Scene, SolidBox};
use colmap_lidar::synth::lidar::{sample_lidar, LidarOptions, LidarPlatform, AIRBORNE_WALL_SHARE};
use colmap_lidar::synth::scenes::{build_changed_scene, build_scene, trajectory};
use colmap_lidar::synth::{
    generate_scene, lens, read_init_pose, BodyPose, SceneKind, SynthOptions,
};
use nalgebra::{Vector2, Vector3};

const OFFSET: [f64; 3] = [500000.0, 4400000.0, 200.0];

fn small_options(scene: SceneKind, n: usize) -> SynthOptions {
    let mut opts = SynthOptions {
        scene,
        num_images: n,
        width: 320,
        height: 240,
        seed: 3,
        offset_m: Vector3::from(OFFSET),
        ..SynthOptions::default()
    };
    opts.lidar.max_points = 150_000;
    opts
}

/// Minimal reader of the generator's binary PLY: (points, normals if present).
fn read_ply(path: &Path) -> (Vec<Vector3<f64>>, Option<Vec<Vector3<f32>>>) {
    let mut bytes = Vec::new();
    std::fs::File::open(path)
        .unwrap()
        .read_to_end(&mut bytes)
        .unwrap();
    let (header, end) = crate::common::ply_header(&bytes);
    assert!(header.contains("format binary_little_endian 1.0"));
    let n: usize = header
        .lines()
        .find_map(|l| l.strip_prefix("element vertex "))
        .unwrap()
        .parse()
        .unwrap();
    let with_normals = header.contains("property float nx");
    let stride = if with_normals { 36 } else { 24 };
    assert_eq!(bytes.len() - end, n * stride, "{}", path.display());
    let f64_at = |o: usize| f64::from_le_bytes(bytes[o..o + 8].try_into().unwrap());
    let f32_at = |o: usize| f32::from_le_bytes(bytes[o..o + 4].try_into().unwrap());
    let mut points = Vec::with_capacity(n);
    let mut normals = Vec::new();
    for i in 0..n {
        let o = end + i * stride;
        points.push(Vector3::new(f64_at(o), f64_at(o + 8), f64_at(o + 16)));
        if with_normals {
            normals.push(Vector3::new(f32_at(o + 24), f32_at(o + 28), f32_at(o + 32)));
        }
    }
    (points, with_normals.then_some(normals))
}

#[test]
fn synth_scene_writes_ground_truth_images_and_init_pose() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("yard");
    let opts = small_options(SceneKind::Yard, 8);
    let summary = generate_scene(&opts, &out).unwrap();
    assert_eq!(summary.num_images, 8);
    // Images: 8 JPEGs of the right size, in trajectory order.
    let mut names: Vec<String> = std::fs::read_dir(out.join("images"))
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    names.sort();
    assert_eq!(
        names,
        (0..8)
            .map(|i| format!("frame_{i:04}.jpg"))
            .collect::<Vec<_>>()
    );
    let img = image::open(out.join("images").join(&names[3])).unwrap();
    assert_eq!((img.width(), img.height()), (320, 240));
    // Not flat: the pixel values spread widely.
    let gray = img.to_luma8();
    let (lo, hi) = gray
        .pixels()
        .fold((255u8, 0u8), |(lo, hi), p| (lo.min(p.0[0]), hi.max(p.0[0])));
    assert!(hi - lo > 100, "{lo} {hi}");

    // Ground truth: the trajectory shifted by the offset, exactly.
    let gt = load_poses(&out.join("gt")).unwrap();
    let truth = trajectory(SceneKind::Yard, 8, opts.seed);
    assert_eq!(gt.len(), 8);
    for (i, pose) in truth.iter().enumerate() {
        let shifted = BodyPose {
            position_m: pose.position_m + Vector3::from(OFFSET),
            ..*pose
        };
        let expected = shifted.to_cam_from_world();
        let got = gt[&format!("frame_{i:04}.jpg")];
        assert!((got.camera_center() - shifted.position_m).norm() < 1e-6);
        assert!(got.rotation.angle_to(&expected.rotation) < 1e-9);
    }
    let cameras = std::fs::read_to_string(out.join("gt/cameras.txt")).unwrap();
    assert!(
        cameras
            .lines()
            .any(|l| l.starts_with("1 SIMPLE_RADIAL 320 240 256 160 120 -0.04")),
        "{cameras}"
    );

    // init_pose.txt: exact = first gt pose in body convention; perturbed 0.3 m / 3 deg away.
    let (exact, perturbed) = read_init_pose(&out.join("init_pose.txt")).unwrap();
    let to_pose = |a: [f64; 6]| {
        BodyPose::from_degrees(Vector3::new(a[0], a[1], a[2]), a[3], a[4], a[5]).to_cam_from_world()
    };
    let first = gt["frame_0000.jpg"];
    let e = to_pose(exact);
    assert!((e.camera_center() - first.camera_center()).norm() < 1e-6);
    assert!(e.rotation.angle_to(&first.rotation).to_degrees() < 1e-6);
    let p = to_pose(perturbed);
    assert!(((p.camera_center() - first.camera_center()).norm() - 0.3).abs() < 1e-6);
    assert!((p.rotation.angle_to(&first.rotation).to_degrees() - 3.0).abs() < 1e-5);
}

/// Distance from each LiDAR point to the nearest surface of the scene.
fn surface_distances(scene: &Scene, points: &[Vector3<f64>], step: usize) -> Vec<f64> {
    points
        .iter()
        .step_by(step)
        .map(|p| scene.distance_to_surfaces(p))
        .collect()
}

#[test]
fn synth_lidar_points_lie_on_the_surfaces() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("room");
    let opts = small_options(SceneKind::Room, 2);
    let summary = generate_scene(&opts, &out).unwrap();
    let (points, normals) = read_ply(&out.join("lidar.ply"));
    let (raw, raw_normals) = read_ply(&out.join("lidar_raw.ply"));
    assert!(raw_normals.is_none());
    assert_eq!(points.len(), summary.num_lidar_points);
    assert_eq!(raw, points);
    let normals = normals.unwrap();
    assert!(normals.iter().all(|n| (n.norm() - 1.0).abs() < 1e-5));
    let scene = build_scene(SceneKind::Room, opts.seed);
    let local: Vec<Vector3<f64>> = points.iter().map(|p| p - Vector3::from(OFFSET)).collect();
    let mut d = surface_distances(&scene, &local, 7);
    d.sort_by(f64::total_cmp);
    let n = d.len();
    // |N(0, 1.5 cm)|: median 1.01 cm, 99th percentile 3.9 cm; the 0.1 % outliers sit beyond.
    let median = d[n / 2];
    assert!((median - 0.0101).abs() < 0.0015, "median {median}");
    let p99 = d[n * 99 / 100];
    assert!(p99 > 0.03 && p99 < 0.05, "p99 {p99}");
    let far = d.iter().filter(|&&x| x > 0.1).count() as f64 / n as f64;
    assert!(far > 0.0002 && far < 0.003, "outlier share {far}");
    // Points were dropped inside the holes: fewer than area / spacing^2.
    let area: f64 = scene.quads.iter().map(|q| q.area_m2()).sum();
    assert!((points.len() as f64) < 0.99 * area / summary.lidar_spacing_m.powi(2));
}

/// The centre of a box's top face.
fn top_centre(b: &SolidBox) -> Vector3<f64> {
    Vector3::new(b.center_xy_m[0], b.center_xy_m[1], b.base_z_m + b.size_m[2])
}

fn same_box(a: &SolidBox, b: &SolidBox) -> bool {
    a.center_xy_m == b.center_xy_m && a.size_m == b.size_m && a.yaw_rad == b.yaw_rad
}

#[test]
fn changed_scenes_move_objects_between_scan_and_photos() {
    for kind in [SceneKind::Yard, SceneKind::Room, SceneKind::Corridor] {
        let scan = build_scene(kind, 0);
        let (same, removed, added) = build_changed_scene(kind, 0, 0);
        assert_eq!((removed, added), (0, 0));
        assert_eq!(same.quads.len(), scan.quads.len());
        let (photo, removed, added) = build_changed_scene(kind, 0, 3);
        assert_eq!((removed, added), (3, 3), "{kind:?}");
        let new: Vec<&SolidBox> = photo
            .solids
            .iter()
            .filter(|b| !scan.solids.iter().any(|s| same_box(s, b)))
            .collect();
        let gone: Vec<&SolidBox> = scan
            .solids
            .iter()
            .filter(|s| !photo.solids.iter().any(|b| same_box(s, b)))
            .collect();
        assert_eq!((new.len(), gone.len()), (3, 3), "{kind:?}");
        // New boxes stand clear of the scan's surfaces, removed ones are
        // only in the scan.
        for b in &new {
            let top = top_centre(b);
            assert!(photo.distance_to_surfaces(&top) < 1e-9);
            assert!(scan.distance_to_surfaces(&top) > 0.1, "{kind:?} {b:?}");
            assert!(scan.solids.iter().all(|s| !s.contains(&top, -0.1)));
        }
        for b in &gone {
            let top = top_centre(b);
            assert!(scan.distance_to_surfaces(&top) < 1e-9);
            assert!(photo.distance_to_surfaces(&top) > 0.05, "{kind:?} {b:?}");
        }
        // The default 24-image walk sees them: in the room all six, in the
        // yard the three new boxes and two of the removed objects (only two
        // of its objects are in view of that walk).
        let camera = SynthOptions::default().camera();
        let poses = trajectory(kind, 24, 0);
        // Its top's or its middle's centre in an image.
        let in_view = |b: &SolidBox| {
            let top = top_centre(b);
            let mid = top - Vector3::new(0.0, 0.0, 0.5 * b.size_m[2]);
            poses.iter().any(|pose| {
                [top, mid].iter().any(|x| {
                    let c = pose.to_cam_from_world().transform_point(x);
                    c.z > 0.3
                        && camera.project(&c).is_some_and(|px| {
                            (0.0..640.0).contains(&px.x) && (0.0..480.0).contains(&px.y)
                        })
                })
            })
        };
        let seen = |boxes: &[&SolidBox]| boxes.iter().filter(|b| in_view(b)).count();
        match kind {
            SceneKind::Room => assert_eq!((seen(&new), seen(&gone)), (3, 3)),
            SceneKind::Yard => assert_eq!((seen(&new), seen(&gone)), (3, 2)),
            SceneKind::Corridor | SceneKind::Aerial | SceneKind::Orbit => {}
        }
    }
    // The map is sampled from the scan, the images from the changed scene.
    let dir = tempfile::tempdir().unwrap();
    let mut opts = small_options(SceneKind::Yard, 3);
    let plain = generate_scene(&opts, &dir.path().join("plain")).unwrap();
    opts.changes = 3;
    let changed = generate_scene(&opts, &dir.path().join("changed")).unwrap();
    assert_eq!((changed.objects_removed, changed.objects_added), (3, 3));
    assert_eq!((plain.objects_removed, plain.objects_added), (0, 0));
    let read = |d: &str, f: &str| std::fs::read(dir.path().join(d).join(f)).unwrap();
    assert!(read("plain", "lidar.ply") == read("changed", "lidar.ply"));
    let differ = (0..3)
        .filter(|&i| {
            let f = format!("images/frame_{i:04}.jpg");
            read("plain", &f) != read("changed", &f)
        })
        .count();
    assert!(differ > 0, "the first images see the changes");
}

#[test]
fn synth_projections_agree_with_ray_casting() {
    projections_agree_with_ray_casting(small_options(SceneKind::Corridor, 6));
    // A fisheye (rays up to 78 deg off the axis).
    let fisheye = SynthOptions {
        camera_model: CameraModel::OpenCvFisheye,
        focal_factor: FISHEYE_FOCAL_FACTOR,
        ..small_options(SceneKind::Corridor, 6)
    };
    let camera = fisheye.camera();
    let corner = lens::unproject(&camera, &Vector2::new(0.0, 0.0));
    assert!(corner.xy().norm().atan().to_degrees() > 75.0, "{corner}");
    projections_agree_with_ray_casting(fisheye);
}

#[test]
fn synth_refuses_a_fisheye_wider_than_it_can_render() {
    let with = |model: CameraModel, focal_factor: f64| SynthOptions {
        camera_model: model,
        focal_factor,
        ..SynthOptions::default()
    };
    assert!(with(CameraModel::OpenCvFisheye, FISHEYE_FOCAL_FACTOR)
        .validate()
        .is_ok());
    assert!(with(CameraModel::SimpleRadialFisheye, FISHEYE_FOCAL_FACTOR)
        .validate()
        .is_ok());
    // 640 x 480 at f = 192 px: the corners are 2.08 focal lengths from the
    // centre, rays about 113 deg off the axis, which (x, y, 1) rays cannot be.
    let err = with(CameraModel::OpenCvFisheye, 0.3)
        .validate()
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("OPENCV_FISHEYE") && err.contains("at most 85"),
        "{err}"
    );
    assert!(err.contains("90 deg or more"), "{err}");
    assert!(with(CameraModel::SimplePinhole, 0.8).validate().is_ok());
}

/// Noise-free samples projected into the true cameras (read from gt/) must
/// land on a pixel whose ray, cast through the scene, hits the sample or
/// something in front of it (occlusion), never anything behind it.
fn projections_agree_with_ray_casting(opts: SynthOptions) {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("corridor");
    generate_scene(&opts, &out).unwrap();
    let gt = load_poses(&out.join("gt")).unwrap();
    let camera = opts.camera();
    let scene = build_scene(SceneKind::Corridor, opts.seed);
    let map = sample_lidar(
        &scene,
        &LidarOptions {
            spacing_m: Some(0.1),
            noise_sigma_m: 0.0,
            num_holes: 0,
            outlier_fraction: 0.0,
            ..LidarOptions::default()
        },
    );
    let offset = Vector3::from(OFFSET);
    // Points outside the field of view can fold back into the image through
    // the radial distortion: keep those within the image corners' ray radius.
    let max_radius = [(0.0, 0.0), (320.0, 0.0), (0.0, 240.0), (320.0, 240.0)]
        .iter()
        .map(|&(u, v)| lens::unproject(&camera, &Vector2::new(u, v)).xy().norm())
        .fold(0.0, f64::max);
    let (mut visible, mut occluded) = (0usize, 0usize);
    for pose in gt.values() {
        // gt is in the offset world; the scene is local.
        let cam_from_local = Rigid3::new(pose.rotation, pose.translation + pose.rotation * offset);
        let centre = cam_from_local.camera_center();
        for p in &map.points {
            let pc = cam_from_local.transform_point(p);
            if pc.z <= 0.0 || (pc.xy() / pc.z).norm() > max_radius {
                continue;
            }
            let Some(px) = lens::project(&camera, &pc) else {
                continue;
            };
            if px.x < 0.0 || px.y < 0.0 || px.x >= 320.0 || px.y >= 240.0 {
                continue;
            }
            let ray = lens::unproject(&camera, &Vector2::new(px.x, px.y));
            let dir_world = cam_from_local.rotation.inverse() * ray.normalize();
            let range = (p - centre).norm();
            let hit = scene
                .cast(&centre, &dir_world, 1e-4, 1e4)
                .expect("a closed corridor: every ray hits");
            assert!(
                hit.t < range + 1e-6,
                "hit behind the sample: {} > {range}",
                hit.t
            );
            if hit.t > range - 1e-6 {
                visible += 1;
            } else {
                occluded += 1;
            }
        }
    }
    assert!(
        visible > 5000 && occluded > 100,
        "{}: visible {visible} occluded {occluded}",
        opts.camera_model.name()
    );
}

#[test]
fn synth_evaluate_command_on_ground_truth() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("yard");
    generate_scene(&small_options(SceneKind::Yard, 5), &out).unwrap();
    let json = dir.path().join("eval.json");
    let args = colmap_lidar::commands::evaluate::EvaluateArgs {
        model: out.join("gt"),
        reference: out.join("gt"),
        align: Alignment::Sim3,
        json: Some(json.clone()),
        lidar: None,
    };
    colmap_lidar::commands::evaluate::run(&args).unwrap();
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(json).unwrap()).unwrap();
    assert_eq!(v["num_registered"], 5);
    assert!((v["sim3_scale"].as_f64().unwrap() - 1.0).abs() < 1e-9);
    assert!(v["centre_error_m"]["max"].as_f64().unwrap() < 1e-6);
    assert_eq!(v["within"][0]["count"], 5);
    // A reference of other images (by name): an error, not "0 registered",
    // and no report written.
    let renamed = dir.path().join("renamed");
    std::fs::create_dir(&renamed).unwrap();
    for file in ["cameras.txt", "images.txt", "points3D.txt"] {
        let text = std::fs::read_to_string(out.join("gt").join(file)).unwrap();
        std::fs::write(renamed.join(file), text.replace(".jpg", "_b.jpg")).unwrap();
    }
    let json_b = dir.path().join("eval_b.json");
    let err =
        colmap_lidar::commands::evaluate::run(&colmap_lidar::commands::evaluate::EvaluateArgs {
            reference: renamed,
            json: Some(json_b.clone()),
            ..args
        })
        .unwrap_err();
    assert!(
        format!("{err:#}").contains("no image of the model"),
        "{err:#}"
    );
    assert!(!json_b.exists());
    // Georeferenced ground truth against itself moved by 1 cm: every centre error is 1 cm.
    let gt = load_poses(&out.join("gt")).unwrap();
    let moved: BTreeMap<String, Rigid3> = gt
        .iter()
        .map(|(k, p)| {
            let c = p.camera_center() + Vector3::new(0.01, 0.0, 0.0);
            (k.clone(), Rigid3::from_rotation_and_center(p.rotation, &c))
        })
        .collect();
    let rep = evaluate(&moved, &gt, Alignment::None).unwrap();
    let c = rep.centre_error_m.unwrap();
    assert!((c.median - 0.01).abs() < 1e-6 && (c.max - 0.01).abs() < 1e-6);
}

#[test]
fn synth_colmap_harness_gives_features_and_matches() {
    // The shared yard scene, rendered and run through COLMAP once.
    let Some(scene) = crate::common::yard_db() else {
        return;
    };
    let snap = read_database(&scene.database).unwrap();
    assert_eq!(snap.images.len(), crate::common::YARD_IMAGES);
    let id_by_name: BTreeMap<String, _> = snap
        .images
        .values()
        .map(|im| (im.name.clone(), im.id))
        .collect();
    for (name, id) in &id_by_name {
        let n = snap.num_keypoints(*id);
        assert!(n > 1000, "{name}: only {n} keypoints");
    }
    let inliers: BTreeMap<_, usize> = snap
        .two_view_geometries
        .iter()
        .map(|g| ((g.image_id1, g.image_id2), g.inlier_matches.len()))
        .collect();
    for i in 0..crate::common::YARD_IMAGES - 1 {
        let a = id_by_name[&format!("frame_{i:04}.jpg")];
        let b = id_by_name[&format!("frame_{:04}.jpg", i + 1)];
        let key = if a < b { (a, b) } else { (b, a) };
        let n = inliers.get(&key).copied().unwrap_or(0);
        assert!(
            n > 100,
            "frames {i} and {}: only {n} verified matches",
            i + 1
        );
    }
}

/// The corridor walk stays inside the 40 m corridor however many images it
/// has (400 images walked through its end wall before), 0.45 m apart up to
/// 200 images and closer beyond.
#[test]
fn corridor_walk_fits_the_corridor() {
    let (lo, hi) = build_scene(SceneKind::Corridor, 0).bounding_box();
    for n in [24, 200, 201, 400, 1000] {
        let poses = trajectory(SceneKind::Corridor, n, 0);
        assert_eq!(poses.len(), n);
        for p in &poses {
            let x = p.position_m;
            for k in 0..3 {
                assert!(
                    x[k] > lo[k] + 0.3 && x[k] < hi[k] - 0.3,
                    "{n} images: {x:?}"
                );
            }
        }
        // The forward leg's step (jitter is at most 2 cm a coordinate).
        let step = poses[1].position_m.x - poses[0].position_m.x;
        let expected = if n <= 200 {
            0.45
        } else {
            36.0 / ((n - n / 5) / 2) as f64
        };
        assert!((step - expected).abs() < 0.041, "{n} images: step {step}");
    }
}

/// The drone's scenes: the survey looks straight down from 24 m onto the
/// yard, three strips 5 m apart; the orbit looks 45 deg down towards the
/// yard's middle from a full circle 14 m about it at 16 m. Every image's
/// centre pixel sees the yard's ground or a roof, 16-40 m away.
#[test]
fn drone_flights_look_at_the_yard() {
    for (kind, n) in [
        (SceneKind::Aerial, 24),
        (SceneKind::Aerial, 7),
        (SceneKind::Orbit, 24),
    ] {
        let scene = build_scene(kind, 0);
        let poses = trajectory(kind, n, 0);
        assert_eq!(poses.len(), n);
        let mut strips = std::collections::BTreeSet::new();
        for p in &poses {
            let cam = p.to_cam_from_world();
            let axis = cam.rotation.inverse() * Vector3::z();
            let centre = p.position_m;
            let down_deg = (-axis.z).clamp(-1.0, 1.0).asin().to_degrees();
            match kind {
                SceneKind::Aerial => {
                    assert!(down_deg > 88.0, "{down_deg}");
                    assert!((centre.z - 24.0).abs() < 0.03);
                    strips.insert((centre.y / 5.0).round() as i64);
                }
                _ => {
                    assert!((down_deg - 45.0).abs() < 2.0, "{down_deg}");
                    let inward = Vector3::new(-centre.x, -0.5 - centre.y, 0.0).normalize();
                    assert!(axis.xy().normalize().dot(&inward.xy()) > 0.999, "{axis:?}");
                    assert!(((centre.xy() - Vector2::new(0.0, -0.5)).norm() - 14.0).abs() < 0.05);
                }
            }
            let hit = scene
                .cast(&centre, &axis, 0.1, 100.0)
                .expect("sees the yard");
            assert!((16.0..40.0).contains(&hit.t), "{kind:?}: {}", hit.t);
        }
        if kind == SceneKind::Aerial {
            assert_eq!(strips.into_iter().collect::<Vec<_>>(), vec![-1, 0, 1]);
        }
    }
}

/// An airborne scan of the yard (`--lidar-platform airborne`): flat ground
/// and roofs as dense as from the ground, walls at 0.15 of it, nothing that
/// faces down. (The terrestrial map is sampled as before: session 76 checked
/// `synth`'s `lidar.ply` byte for byte against session 75's.)
#[test]
fn an_airborne_scan_thins_the_walls() {
    let scene = build_scene(SceneKind::Yard, 0);
    let options = |platform| LidarOptions {
        spacing_m: Some(0.1),
        num_holes: 0,
        outlier_fraction: 0.0,
        platform,
        seed: 5,
        ..LidarOptions::default()
    };
    let terrestrial = sample_lidar(&scene, &options(LidarPlatform::Terrestrial));
    let airborne = sample_lidar(&scene, &options(LidarPlatform::Airborne));
    // Points facing up (z > 0.9), sideways (|z| < 0.1) and down (z < -0.5).
    let count = |map: &colmap_lidar::synth::lidar::LidarMap| {
        let mut c = [0usize; 3];
        for n in &map.normals {
            if n.z > 0.9 {
                c[0] += 1;
            } else if n.z.abs() < 0.1 {
                c[1] += 1;
            } else if n.z < -0.5 {
                c[2] += 1;
            }
        }
        c
    };
    let (t, a) = (count(&terrestrial), count(&airborne));
    eprintln!("terrestrial up/side/down {t:?}, airborne {a:?}");
    assert!(t[1] > 10_000, "{t:?}");
    let up = a[0] as f64 / t[0] as f64;
    assert!((up - 1.0).abs() < 0.01, "{up}");
    let side = a[1] as f64 / t[1] as f64;
    assert!((side - AIRBORNE_WALL_SHARE).abs() < 0.01, "{side}");
    assert_eq!(a[2], 0);
    // The yard has no surface facing down; a ceiling would get no point.
    assert_eq!(LidarPlatform::Airborne.density(&-Vector3::z()), 0.0);
    assert_eq!(LidarPlatform::Terrestrial.density(&-Vector3::z()), 1.0);
}
