//! A toy room with exact geometry: LiDAR samples of its six planes with
//! normals; random surface points seen by a short camera trajectory; their
//! projections (with noise) as keypoints; matches (with a few wrong ones) as
//! verified pairs. Everything in memory, no COLMAP.
use std::collections::BTreeMap;
use std::path::PathBuf;

use colmap_lidar::commands::map::{run as run_map, MapArgs};
use colmap_lidar::io::database::{DatabaseSnapshot, DbImage, TwoViewGeometry};
use colmap_lidar::map::PointCloud;
use colmap_lidar::scene::{Camera, CameraId, CameraModel, ImageId, Rigid3};
use colmap_lidar::sfm::body_pose::BodyPoseDeg;
use colmap_lidar::sfm::options::AssociationKind;
use colmap_lidar::sfm::{run_mapper, MapperOptions};
use nalgebra::{Vector2, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

/// Room [-5, 5] x [-4, 4] x [0, 3] shifted by this (a georeferenced map).
const ORIGIN: [f64; 3] = [512_000.0, 5_400_000.0, 230.0];

pub struct Toy {
    pub db: DatabaseSnapshot,
    pub cloud: PointCloud,
    pub gt: BTreeMap<ImageId, Rigid3>,
    pub init_pose: BodyPoseDeg,
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
        let body = BodyPoseDeg {
            position_m: origin() + Vector3::new(-2.0 + 4.0 * t, -1.0 + 0.5 * (t * 6.0).sin(), 1.4),
            roll_deg: 2.0 * (t * 5.0).cos(),
            pitch_deg: -8.0 + 4.0 * (t * 3.0).sin(),
            yaw_deg: 60.0 + 60.0 * t,
        };
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

#[test]
fn toy_room_registers_in_the_map_frame() {
    let scene = toy(14, 0.3, 0.03, 1);
    let options = MapperOptions::default();
    let init = scene.init_pose.to_cam_from_world();
    let out = run_mapper(
        &scene.db,
        &scene.cloud,
        ImageId(1),
        &init,
        &options,
        &mut |_, _| {},
    )
    .unwrap();
    let rec = &out.reconstruction;
    let err = max_centre_error(rec, &scene.gt);
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
fn toy_room_without_lidar_terms_keeps_the_initial_frame() {
    let scene = toy(10, 0.3, 0.0, 2);
    let mut options = MapperOptions::default();
    options.association.kind = AssociationKind::None;
    let init = scene.init_pose.to_cam_from_world();
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
        "toy room, no LiDAR terms: {}/{} registered, max centre error {err:.4} m",
        out.report.num_registered, out.report.num_images
    );
    assert_eq!(out.report.num_registered, 10);
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
    let away = BodyPoseDeg {
        position_m: origin() + Vector3::new(0.0, -30.0, 1.5),
        roll_deg: 0.0,
        pitch_deg: 0.0,
        yaw_deg: -90.0,
    };
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
        init_pose: Some("0,0,0,0,0,0".into()),
        ..Default::default()
    };
    let err = run_map(&args).unwrap_err();
    assert!(format!("{err:#}").contains("missing.db"), "{err:#}");
    assert!(!out.exists());
    let args = MapArgs {
        init_pose: Some("0,0,0,0,0".into()),
        ..args
    };
    let err = run_map(&args).unwrap_err();
    assert!(format!("{err:#}").contains("six numbers"), "{err:#}");
    assert!(!out.exists());
}
