//! Integration tests: frustum culling against brute force, projection of the
//! map at query pixels against exact ray casting on a synthetic scene of
//! planes (all camera models), determinism, the dense depth image and its PNG.
//! Also the projection benchmark (`#[ignore]`, see `scripts/bench_projection.sh`).
use std::collections::BTreeSet;

use colmap_lidar::map::depth_image::{colourise, render_depth_image, write_png};
use colmap_lidar::map::grid::{Frustum, FrustumGrid, GridOptions};
use colmap_lidar::map::projection::{
    project_map_at_pixels, project_map_at_pixels_reference, project_visible_points, LidarHit,
    ProjectionOptions, SplatOptions,
};
use colmap_lidar::map::PointCloud;
use colmap_lidar::scene::camera::{Camera, CameraModel};
use colmap_lidar::scene::ids::CameraId;
use colmap_lidar::scene::pose::Rigid3;
use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector2, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::index::{uniform_cloud, utm_origin};

/// `cam_from_world` of a camera at `centre_in_map` with the body convention
/// of method.md (x forward, y left, z up; `R = Rz(yaw) Ry(pitch) Rx(roll)`).
pub fn camera_pose(centre_in_map: Vector3<f64>, roll: f64, pitch: f64, yaw: f64) -> Rigid3 {
    let world_from_body = Rotation3::from_euler_angles(roll, pitch, yaw).into_inner();
    // Columns: the camera axes in body coordinates (x_cam = -y_body,
    // y_cam = -z_body, z_cam = x_body).
    let body_from_cam = Matrix3::new(0.0, 0.0, 1.0, -1.0, 0.0, 0.0, 0.0, -1.0, 0.0);
    let world_from_cam = world_from_body * body_from_cam;
    let cam_from_world = world_from_cam.transpose();
    Rigid3::from_rotation_matrix(&cam_from_world, -(cam_from_world * centre_in_map))
}

fn camera(model: CameraModel, width: u32, height: u32, params: Vec<f64>) -> Camera {
    assert_eq!(params.len(), model.num_params());
    Camera {
        id: CameraId(1),
        model,
        width,
        height,
        params,
    }
}

/// One camera of every model, 400 x 300, focal ~300 px, mild distortion.
fn cameras_all_models() -> Vec<Camera> {
    use CameraModel as M;
    let (w, h) = (400, 300);
    let (f, cx, cy) = (300.0, 200.0, 150.0);
    vec![
        camera(M::SimplePinhole, w, h, vec![f, cx, cy]),
        camera(M::Pinhole, w, h, vec![f, 310.0, cx, cy]),
        camera(M::SimpleRadial, w, h, vec![f, cx, cy, -0.05]),
        camera(M::Radial, w, h, vec![f, cx, cy, -0.06, 0.01]),
        camera(
            M::OpenCv,
            w,
            h,
            vec![f, 305.0, cx, cy, -0.08, 0.01, 0.0005, -0.0003],
        ),
        camera(
            M::OpenCvFisheye,
            w,
            h,
            vec![f, f, cx, cy, 0.02, -0.01, 0.002, -0.001],
        ),
        camera(
            M::FullOpenCv,
            w,
            h,
            vec![
                f, f, cx, cy, -0.05, 0.01, 0.0004, 0.0002, 0.001, 0.01, 0.0, 0.0,
            ],
        ),
        camera(M::Fov, w, h, vec![f, f, cx, cy, 0.4]),
        camera(M::SimpleRadialFisheye, w, h, vec![f, cx, cy, 0.02]),
        camera(M::RadialFisheye, w, h, vec![f, cx, cy, 0.02, -0.005]),
        camera(
            M::ThinPrismFisheye,
            w,
            h,
            vec![
                f, f, cx, cy, 0.02, -0.01, 0.0005, 0.0002, 0.001, 0.0, 0.0005, -0.0005,
            ],
        ),
    ]
}

/// A fisheye seeing more than 170 degrees across (side bounds impossible).
fn wide_fisheye() -> Camera {
    camera(
        CameraModel::OpenCvFisheye,
        400,
        400,
        vec![110.0, 110.0, 200.0, 200.0, 0.0, 0.0, 0.0, 0.0],
    )
}

#[test]
fn frustum_grid_never_misses_a_visible_point() {
    let cloud = uniform_cloud(60_000, 50.0, 21);
    let grid = FrustumGrid::build(&cloud, &GridOptions::default()).unwrap();
    assert_eq!(grid.num_points(), cloud.len());
    let mut rng = ChaCha8Rng::seed_from_u64(22);
    let (near, far, margin_px) = (0.5, 40.0, 12.0);
    let mut cameras = cameras_all_models();
    cameras.push(wide_fisheye());
    let mut checked = 0;
    for cam in &cameras {
        let fold_sq = cam.max_normalized_radius().unwrap().powi(2);
        for _ in 0..4 {
            let centre = utm_origin()
                + Vector3::new(
                    rng.gen_range(-30.0..30.0),
                    rng.gen_range(-30.0..30.0),
                    rng.gen_range(-10.0..10.0),
                );
            let pose = camera_pose(
                centre,
                rng.gen_range(-0.5..0.5),
                rng.gen_range(-0.8..0.8),
                rng.gen_range(-3.1..3.1),
            );
            let frustum = Frustum::from_camera(cam, &pose, near, far, margin_px);
            let culled: BTreeSet<u32> = grid.points_in_frustum(&frustum).into_iter().collect();
            let mut visible = 0;
            for i in 0..cloud.len() {
                let p = pose.transform_point(&cloud.point_in_map(i));
                if p.z < near || p.z > far || p.norm() > far {
                    continue;
                }
                if (p.x * p.x + p.y * p.y) / (p.z * p.z) > fold_sq {
                    continue;
                }
                let Some(px) = cam.project(&p) else { continue };
                let inside = px.x >= -margin_px
                    && px.y >= -margin_px
                    && px.x <= cam.width as f64 + margin_px
                    && px.y <= cam.height as f64 + margin_px;
                if inside {
                    visible += 1;
                    assert!(
                        culled.contains(&(i as u32)),
                        "{}: point {i} projects to {px:?} but was culled",
                        cam.model.name()
                    );
                }
            }
            if cam.model != CameraModel::OpenCvFisheye || cam.width != 400 || cam.params[0] > 200.0
            {
                // Narrow cameras: the cull must actually cull (a 40 m sphere
                // around the camera holds ~3/4 of this box's points).
                assert!(
                    culled.len() < cloud.len() / 2,
                    "{}: {} of {} points kept",
                    cam.model.name(),
                    culled.len(),
                    cloud.len()
                );
            }
            checked += visible;
        }
    }
    assert!(checked > 10_000, "only {checked} visible points checked");
}

/// A fisheye's near limit is on the range, a perspective camera's on the
/// depth: points 0.6 m and 0.45 m from the camera, 75 deg off the axis (0.16
/// and 0.12 m along it), with the default 0.5 m limit. The fisheye sees the
/// first and not the second; a perspective camera as wide (SIMPLE_PINHOLE,
/// the same points inside its image) sees neither. The fisheye's splat is
/// sized at `r / θ` (0.44 m for the first), not at its depth (0.16 m).
#[test]
fn fisheye_near_limit_is_on_the_range() {
    let off_axis = 75f64.to_radians();
    let at = |range: f64| {
        let p = Vector3::new(off_axis.sin(), 0.0, off_axis.cos()) * range;
        [p.x as f32, p.y as f32, p.z as f32]
    };
    let cloud = PointCloud {
        origin: Vector3::zeros(),
        points: vec![at(0.6), at(0.45)],
        normals: None,
        planarity: None,
    };
    let grid = FrustumGrid::build(&cloud, &GridOptions::default()).unwrap();
    // Splats 5 cm either side at every depth (no saturation).
    let options = test_options(0.05);
    assert_eq!(options.min_depth_m, 0.5);
    // 75 deg off the axis is 1.31 rad: at f = 200 px, 262 px from the centre.
    let fisheye = camera(
        CameraModel::OpenCvFisheye,
        640,
        480,
        vec![200.0, 200.0, 320.0, 240.0, 0.0, 0.0, 0.0, 0.0],
    );
    let seen =
        project_visible_points(&cloud, &grid, &fisheye, &Rigid3::identity(), &options).unwrap();
    assert_eq!(seen.len(), 1, "{seen:?}");
    assert_eq!(seen[0].point_idx, 0);
    // The grid keeps points in cell-local coordinates (0.004 px here).
    let x = seen[0].pixel.x;
    assert!((x - (320.0 + 200.0 * off_axis)).abs() < 0.05, "{x}");
    // 200 px * 0.05 m / 0.444 m = 22.5 px (by the depth, 0.155 m: 64 px).
    let splat_depth = 0.6 * off_axis.sin() / off_axis;
    let want = 200.0 * 0.05 / splat_depth;
    assert!(
        (seen[0].half_size_px - want).abs() < 0.01,
        "{} px, {want} px at r / θ",
        seen[0].half_size_px
    );
    // tan 75 = 3.73: at f = 80 px, 299 px from the centre, in the image.
    let pinhole = camera(
        CameraModel::SimplePinhole,
        640,
        480,
        vec![80.0, 320.0, 240.0],
    );
    let seen =
        project_visible_points(&cloud, &grid, &pinhole, &Rigid3::identity(), &options).unwrap();
    assert!(seen.is_empty(), "{seen:?}");
    let mut near = options.clone();
    near.min_depth_m = 0.1;
    let seen = project_visible_points(&cloud, &grid, &pinhole, &Rigid3::identity(), &near).unwrap();
    assert_eq!(
        seen.len(),
        2,
        "the points are in the perspective image: {seen:?}"
    );
}

/// An axis-aligned or slanted rectangle: origin, two edges, plane id.
struct Rect {
    origin: Vector3<f64>,
    u: Vector3<f64>,
    v: Vector3<f64>,
}

impl Rect {
    fn normal(&self) -> Vector3<f64> {
        self.u.cross(&self.v).normalize()
    }

    /// Ray parameter of the intersection with the rectangle, if any.
    fn intersect(&self, centre: &Vector3<f64>, dir: &Vector3<f64>) -> Option<f64> {
        let n = self.normal();
        let denom = n.dot(dir);
        if denom.abs() < 1e-12 {
            return None;
        }
        let t = n.dot(&(self.origin - centre)) / denom;
        if t <= 0.0 {
            return None;
        }
        let q = centre + t * dir - self.origin;
        let a = q.dot(&self.u) / self.u.norm_squared();
        let b = q.dot(&self.v) / self.v.norm_squared();
        ((0.0..=1.0).contains(&a) && (0.0..=1.0).contains(&b)).then_some(t)
    }
}

/// Floor, back wall, side wall, a frontal occluder panel and a slanted one,
/// sampled on lattices of spacing `spacing_m`; map coordinates offset by
/// [`utm_origin`]. Returns the cloud (with normals), the plane of each point
/// and the rectangles in the map's local frame.
fn planes_scene(spacing_m: f64) -> (PointCloud, Vec<usize>, Vec<Rect>) {
    let d = |x: f64, y: f64, z: f64| Vector3::new(x, y, z);
    let rects = vec![
        Rect {
            origin: d(0.0, -12.0, 0.0),
            u: d(25.0, 0.0, 0.0),
            v: d(0.0, 24.0, 0.0),
        },
        Rect {
            origin: d(20.0, -12.0, 0.0),
            u: d(0.0, 24.0, 0.0),
            v: d(0.0, 0.0, 5.0),
        },
        Rect {
            origin: d(0.0, 6.0, 0.0),
            u: d(20.0, 0.0, 0.0),
            v: d(0.0, 0.0, 5.0),
        },
        Rect {
            origin: d(7.0, -1.5, 0.3),
            u: d(0.0, 2.5, 0.0),
            v: d(0.0, 0.0, 2.5),
        },
        Rect {
            origin: d(10.0, -6.0, 0.0),
            u: d(1.8, 2.4, 0.0),
            v: d(0.0, 0.0, 3.0),
        },
    ];
    let mut points = Vec::new();
    let mut normals = Vec::new();
    let mut plane_of = Vec::new();
    for (k, r) in rects.iter().enumerate() {
        let (nu, nv) = (
            (r.u.norm() / spacing_m).round() as usize,
            (r.v.norm() / spacing_m).round() as usize,
        );
        let n = r.normal();
        for i in 0..nu {
            for j in 0..nv {
                let p = r.origin
                    + r.u * ((i as f64 + 0.5) / nu as f64)
                    + r.v * ((j as f64 + 0.5) / nv as f64);
                points.push([p.x as f32, p.y as f32, p.z as f32]);
                normals.push([n.x as f32, n.y as f32, n.z as f32]);
                plane_of.push(k);
            }
        }
    }
    let cloud = PointCloud {
        origin: utm_origin(),
        points,
        normals: Some(normals),
        planarity: None,
    };
    (cloud, plane_of, rects)
}

/// First rectangle hit by the ray (centre and direction in the local frame).
fn ray_cast(rects: &[Rect], centre: &Vector3<f64>, dir: &Vector3<f64>) -> Option<(usize, f64)> {
    rects
        .iter()
        .enumerate()
        .filter_map(|(k, r)| r.intersect(centre, dir).map(|t| (k, t)))
        .min_by(|a, b| a.1.total_cmp(&b.1))
}

/// Splats as large as the sampling spacing (no angular margin), so that a
/// point covers its own lattice cell: the projection then reproduces ray
/// casting up to about the spacing.
fn test_options(spacing_m: f64) -> ProjectionOptions {
    ProjectionOptions {
        min_depth_m: 0.5,
        max_depth_m: 40.0,
        splat: SplatOptions {
            patch_half_width_m: spacing_m,
            angular_margin_rad: 0.0,
            saturation_depth_m: 0.0,
            min_half_size_px: 0.5,
            max_half_size_px: 64.0,
            near_half_width_m: 0.0,
        },
    }
}

#[test]
fn projection_matches_ray_casting_on_planes() {
    let spacing = 0.05;
    let (cloud, plane_of, rects) = planes_scene(spacing);
    let grid = FrustumGrid::build(&cloud, &GridOptions::default()).unwrap();
    let options = test_options(spacing);
    let centre_local = Vector3::new(0.5, -0.5, 1.6);
    let pose = camera_pose(utm_origin() + centre_local, 0.02, 0.12, 0.15);
    let world_from_cam = pose.inverse();
    let mut rng = ChaCha8Rng::seed_from_u64(31);
    for cam in cameras_all_models() {
        let name = cam.model.name();
        let f = cam.mean_focal_length();
        let ray_of = |px: &Vector2<f64>| -> Option<Vector3<f64>> {
            let r = cam.unproject(px)?;
            Some((world_from_cam.rotation * r).normalize())
        };
        let queries: Vec<Vector2<f64>> = (0..1500)
            .map(|_| {
                Vector2::new(
                    rng.gen_range(0.0..cam.width as f64),
                    rng.gen_range(0.0..cam.height as f64),
                )
            })
            .collect();
        let hits = project_map_at_pixels(&cloud, &grid, &cam, &pose, &queries, &options).unwrap();
        assert_eq!(hits.len(), queries.len());
        let (mut compared, mut empty) = (0, 0);
        for (q, hit) in queries.iter().zip(&hits) {
            let Some(dir) = ray_of(q) else { continue };
            let expected = ray_cast(&rects, &centre_local, &dir);
            // Skip queries near an occlusion or plane edge: any point within
            // a few splat sizes may legitimately win there.
            let h = match expected {
                Some((_, t)) => options.splat.half_size_px(t.min(40.0) * 0.5, f),
                None => 8.0,
            };
            let mut near_edge = false;
            for k in 0..16 {
                let a = k as f64 * std::f64::consts::PI / 8.0;
                for radius in [1.5 * h + 1.0, 3.0 * h + 2.0] {
                    let p = q + radius * Vector2::new(a.cos(), a.sin());
                    let other = ray_of(&p).and_then(|d| ray_cast(&rects, &centre_local, &d));
                    if other.map(|o| o.0) != expected.map(|e| e.0) {
                        near_edge = true;
                    }
                }
            }
            if near_edge {
                continue;
            }
            match (expected, hit) {
                (None, None) => empty += 1,
                (None, Some(h)) => panic!("{name}: query {q:?} sees nothing but got {h:?}"),
                (Some((k, t)), None) => {
                    assert!(
                        t > 39.0,
                        "{name}: query {q:?} sees plane {k} at {t} m, got nothing"
                    )
                }
                (Some((k, t)), Some(h)) => {
                    let LidarHit {
                        point_idx,
                        range_m,
                        point_in_map,
                        normal_in_map,
                        ..
                    } = h;
                    assert_eq!(
                        plane_of[*point_idx as usize], k,
                        "{name}: query {q:?}: got a point of plane {} instead of {k} \
                         (ranges {range_m} vs {t})",
                        plane_of[*point_idx as usize]
                    );
                    // Range error: the spacing, plus the splat's footprint on
                    // an oblique plane (grows with the tangent of incidence).
                    let n = rects[k].normal();
                    let cos_inc = n.dot(&dir).abs();
                    let tan_inc = (1.0 - cos_inc * cos_inc).sqrt() / cos_inc;
                    let depth = (pose.rotation * dir).z * t;
                    let tol = spacing * (1.5 + 2.0 * (t / depth) * (1.0 + tan_inc));
                    assert!(
                        (range_m - t).abs() <= tol,
                        "{name}: query {q:?}: range {range_m} vs ray cast {t} (tol {tol})"
                    );
                    assert!((point_in_map - cloud.point_in_map(*point_idx as usize)).norm() < 1e-9);
                    assert!((pose.transform_point(point_in_map).norm() - range_m).abs() < 1e-6);
                    let normal = normal_in_map.expect("the scene has normals");
                    assert!((normal - n).norm() < 1e-6);
                    compared += 1;
                }
            }
        }
        assert!(compared > 700, "{name}: only {compared} queries compared");
        assert!(empty > 10, "{name}: only {empty} empty queries");
    }
}

#[test]
fn projection_is_deterministic_across_threads() {
    let spacing = 0.05;
    let (cloud, _, _) = planes_scene(spacing);
    let grid = FrustumGrid::build(&cloud, &GridOptions::default()).unwrap();
    let options = ProjectionOptions::default();
    let pose = camera_pose(utm_origin() + Vector3::new(0.5, -0.5, 1.6), 0.0, 0.1, 0.1);
    let cam = &cameras_all_models()[4];
    let mut rng = ChaCha8Rng::seed_from_u64(41);
    let queries: Vec<Vector2<f64>> = (0..3000)
        .map(|_| Vector2::new(rng.gen_range(0.0..400.0), rng.gen_range(0.0..300.0)))
        .collect();
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| {
                project_map_at_pixels(&cloud, &grid, cam, &pose, &queries, &options).unwrap()
            })
    };
    let one = run(1);
    assert!(one.iter().filter(|h| h.is_some()).count() > 1000);
    assert_eq!(run(2), one);
    assert_eq!(run(3), one);
    assert_eq!(run(2), one);
    let depth = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| render_depth_image(&cloud, &grid, cam, &pose, &options).unwrap())
    };
    assert_eq!(depth(1), depth(2));
}

/// The culled projection (front-to-back cells, tile and super-tile bounds,
/// strips) against the straightforward reference, bit for bit (same point,
/// same range and depth) on random scenes: planes and clutter, every camera
/// model, random poses, cell sizes, depth ranges and splats, query pixels
/// anywhere (also outside the image, duplicated, on tile edges), 1 to 3 threads.
#[test]
fn culled_projection_equals_reference_on_random_scenes() {
    let (planes, _, _) = planes_scene(0.1);
    let mut cameras = cameras_all_models();
    cameras.push(wide_fisheye());
    let mut hits_total = 0;
    for seed in 0..4u64 {
        let mut rng = ChaCha8Rng::seed_from_u64(100 + seed);
        let mut cloud = planes.clone();
        let normals = cloud.normals.as_mut().unwrap();
        for _ in 0..20_000 {
            cloud.points.push([
                rng.gen_range(-5.0..30.0),
                rng.gen_range(-15.0..15.0),
                rng.gen_range(-1.0..6.0),
            ]);
            normals.push([0.0, 0.0, 1.0]);
        }
        // Exact duplicates: ties broken by index.
        for k in 0..500 {
            let p = cloud.points[k * 37];
            cloud.points.push(p);
            normals.push([0.0, 0.0, 1.0]);
        }
        let cell_size_m = [0.5, 1.0, 2.0, 4.0][seed as usize];
        let grid = FrustumGrid::build(&cloud, &GridOptions { cell_size_m }).unwrap();
        for (k, cam) in cameras.iter().enumerate() {
            let centre = utm_origin()
                + Vector3::new(
                    rng.gen_range(-3.0..8.0),
                    rng.gen_range(-5.0..5.0),
                    rng.gen_range(0.5..3.0),
                );
            let pose = camera_pose(
                centre,
                rng.gen_range(-0.3..0.3),
                rng.gen_range(-0.4..0.4),
                rng.gen_range(-1.0..1.0),
            );
            let mut options = match k % 3 {
                0 => ProjectionOptions::default(),
                1 => test_options(0.1),
                _ => {
                    // The splats the mapper uses on a 10 cm map (near floor too).
                    let mut o = ProjectionOptions::default();
                    colmap_lidar::map::projection::widen_splats_for_spacing(&mut o.splat, 0.1);
                    o
                }
            };
            options.min_depth_m = rng.gen_range(0.1..1.5);
            options.max_depth_m = rng.gen_range(5.0..40.0);
            let (w, h) = (cam.width as f64, cam.height as f64);
            let mut queries: Vec<Vector2<f64>> = (0..2000)
                .map(|_| {
                    Vector2::new(
                        rng.gen_range(-20.0..w + 20.0),
                        rng.gen_range(-20.0..h + 20.0),
                    )
                })
                .collect();
            for i in 0..100 {
                queries.push(queries[i]);
                queries.push(Vector2::new((8 * (i % 50)) as f64, (8 * (i % 37)) as f64));
            }
            let reference =
                project_map_at_pixels_reference(&cloud, &grid, cam, &pose, &queries, &options)
                    .unwrap();
            for threads in [1, 2, 3] {
                let fast = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap()
                    .install(|| {
                        project_map_at_pixels(&cloud, &grid, cam, &pose, &queries, &options)
                            .unwrap()
                    });
                for (i, (f, r)) in fast.iter().zip(&reference).enumerate() {
                    assert_eq!(
                        f,
                        r,
                        "{} seed {seed}, {threads} threads, query {i} {:?}",
                        cam.model.name(),
                        queries[i]
                    );
                }
                assert_eq!(fast.len(), reference.len());
            }
            hits_total += reference.iter().filter(|h| h.is_some()).count();
        }
    }
    assert!(hits_total > 20_000, "{hits_total} hits");
}

#[test]
fn ties_go_to_the_smaller_index() {
    // Two copies of the same point, and a third farther behind.
    let cloud = PointCloud {
        origin: utm_origin(),
        points: vec![[5.0, 0.0, 1.0], [5.0, 0.0, 1.0], [6.0, 0.0, 1.0]],
        normals: None,
        planarity: None,
    };
    let grid = FrustumGrid::build(&cloud, &GridOptions::default()).unwrap();
    let pose = camera_pose(utm_origin() + Vector3::new(0.0, 0.0, 1.0), 0.0, 0.0, 0.0);
    let cam = &cameras_all_models()[0];
    let centre = Vector2::new(200.0, 150.0);
    let hits = project_map_at_pixels(
        &cloud,
        &grid,
        cam,
        &pose,
        &[centre, Vector2::new(-5.0, 3.0)],
        &ProjectionOptions::default(),
    )
    .unwrap();
    let h = hits[0].as_ref().unwrap();
    assert_eq!(h.point_idx, 0);
    assert!((h.range_m - 5.0).abs() < 1e-6 && (h.depth_m - 5.0).abs() < 1e-6);
    assert!(h.normal_in_map.is_none());
    assert!(hits[1].is_none(), "a query outside the image sees nothing");
}

#[test]
fn depth_image_agrees_with_queries_at_pixel_centres() {
    let spacing = 0.1;
    let (cloud, _, _) = planes_scene(spacing);
    let grid = FrustumGrid::build(&cloud, &GridOptions::default()).unwrap();
    let options = ProjectionOptions::default();
    let pose = camera_pose(utm_origin() + Vector3::new(0.5, -0.5, 1.6), 0.0, 0.1, 0.1);
    let cam = camera(
        CameraModel::OpenCv,
        80,
        60,
        vec![60.0, 61.0, 40.0, 30.0, -0.05, 0.01, 0.0, 0.0],
    );
    let depth = render_depth_image(&cloud, &grid, &cam, &pose, &options).unwrap();
    assert_eq!(depth.range_m.len(), 80 * 60);
    let centres: Vec<Vector2<f64>> = (0..60)
        .flat_map(|y| (0..80).map(move |x| Vector2::new(x as f64 + 0.5, y as f64 + 0.5)))
        .collect();
    let hits = project_map_at_pixels(&cloud, &grid, &cam, &pose, &centres, &options).unwrap();
    let mut filled = 0;
    for (k, hit) in hits.iter().enumerate() {
        let r = depth.range_m[k];
        match hit {
            None => assert!(r.is_infinite(), "pixel {k}: depth {r} but no query hit"),
            Some(h) => {
                assert!((f64::from(r) - h.range_m).abs() < 1e-4, "pixel {k}");
                filled += 1;
            }
        }
    }
    assert!(filled > 80 * 60 / 2 && filled < 80 * 60, "{filled} filled");

    // The PNG: right size, black where empty, markers drawn.
    let queries = vec![Vector2::new(40.0, 45.0), Vector2::new(40.0, 2.0)];
    let hit = vec![true, false];
    let img = colourise(&depth, 40.0, &queries, &hit);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("depth.png");
    write_png(&img, &path).unwrap();
    let back = image::open(&path).unwrap().to_rgb8();
    assert_eq!(back.dimensions(), (80, 60));
    assert_eq!(back, img);
    assert_eq!(back.get_pixel(42, 46).0, [0, 255, 0]);
    assert_eq!(back.get_pixel(42, 3).0, [255, 0, 0]);
    let empty_pixel = (0..80 * 60)
        .find(|&k| depth.range_m[k].is_infinite())
        .unwrap();
    assert_eq!(
        back.get_pixel((empty_pixel % 80) as u32, (empty_pixel / 80) as u32)
            .0,
        [0, 0, 0]
    );
    // No temporary files left beside the output.
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
}

#[test]
fn bad_inputs_are_errors_not_panics() {
    let (cloud, _, _) = planes_scene(0.2);
    let grid = FrustumGrid::build(&cloud, &GridOptions::default()).unwrap();
    let pose = camera_pose(utm_origin(), 0.0, 0.0, 0.0);
    let mut cam = cameras_all_models()[4].clone();
    cam.params.pop();
    let q = [Vector2::new(1.0, 1.0)];
    let opts = ProjectionOptions::default();
    assert!(project_map_at_pixels(&cloud, &grid, &cam, &pose, &q, &opts).is_err());
    let cam = cameras_all_models()[0].clone();
    let mut bad = opts.clone();
    bad.max_depth_m = 0.1;
    assert!(project_map_at_pixels(&cloud, &grid, &cam, &pose, &q, &bad).is_err());
    let other = uniform_cloud(10, 1.0, 5);
    assert!(project_map_at_pixels(&other, &grid, &cam, &pose, &q, &opts).is_err());
    let _ = UnitQuaternion::<f64>::identity();
}

/// Benchmark (not a timed test): one projection at ~8000 query pixels, 1 MP
/// camera, ~2 million map points in view, inside a 20-million-point
/// building-like map (`COLMAP_LIDAR_BENCH_POINTS`). Also the dense depth
/// image. Run it in release mode through `scripts/bench_projection.sh`.
#[test]
#[ignore]
fn bench_projection() {
    use colmap_lidar::map::projection::project_visible_points;
    use std::time::Instant;

    let n: usize = std::env::var("COLMAP_LIDAR_BENCH_POINTS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(20_000_000);
    let cloud = super::index::building_cloud(n, 0.005, 7);
    let t = Instant::now();
    let grid = FrustumGrid::build(&cloud, &GridOptions::default()).unwrap();
    println!(
        "BENCH grid of {} points: {:.2} s",
        cloud.len(),
        t.elapsed().as_secs_f64()
    );
    // Inside the building, ground floor, looking along the long axis.
    let pose = camera_pose(
        utm_origin() + Vector3::new(1.0, 25.0, 1.5),
        0.0,
        0.05,
        -0.35,
    );
    let (w, h) = (1152u32, 864u32);
    let cams = [
        // A 33-degree lens: about 2 million of the 20 million points in view
        // (the case); then a 45-degree one with about 4 million.
        camera(
            CameraModel::Pinhole,
            w,
            h,
            vec![1950.0, 1950.0, 576.0, 432.0],
        ),
        camera(
            CameraModel::OpenCv,
            w,
            h,
            vec![1950.0, 1950.0, 576.0, 432.0, -0.1, 0.02, 0.0005, -0.0005],
        ),
        camera(
            CameraModel::Pinhole,
            w,
            h,
            vec![1400.0, 1400.0, 576.0, 432.0],
        ),
    ];
    let options = ProjectionOptions::default();
    let mut rng = ChaCha8Rng::seed_from_u64(51);
    let queries: Vec<Vector2<f64>> = (0..8000)
        .map(|_| Vector2::new(rng.gen_range(0.0..w as f64), rng.gen_range(0.0..h as f64)))
        .collect();
    for cam in &cams {
        let visible = project_visible_points(&cloud, &grid, cam, &pose, &options)
            .unwrap()
            .len();
        for threads in [1, 2] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let mut times = Vec::new();
            let mut found = 0;
            for _ in 0..7 {
                let t = Instant::now();
                let hits = pool.install(|| {
                    project_map_at_pixels(&cloud, &grid, cam, &pose, &queries, &options).unwrap()
                });
                times.push(t.elapsed().as_secs_f64() * 1e3);
                found = hits.iter().filter(|h| h.is_some()).count();
            }
            times.sort_by(f64::total_cmp);
            println!(
                "BENCH projection {} {w}x{h} f = {} px, {} queries, {visible} points in view: \
                 median {:.1} ms, best {:.1} ms ({threads} threads; {found} queries hit)",
                cam.model.name(),
                cam.params[0],
                queries.len(),
                times[times.len() / 2],
                times[0]
            );
        }
        let t = Instant::now();
        let reference =
            project_map_at_pixels_reference(&cloud, &grid, cam, &pose, &queries, &options).unwrap();
        println!(
            "BENCH reference (unculled) projection {}: {:.1} ms ({} threads); culled result \
             equal: {}",
            cam.model.name(),
            t.elapsed().as_secs_f64() * 1e3,
            rayon::current_num_threads(),
            reference
                == project_map_at_pixels(&cloud, &grid, cam, &pose, &queries, &options).unwrap()
        );
        let t = Instant::now();
        let depth = render_depth_image(&cloud, &grid, cam, &pose, &options).unwrap();
        println!(
            "BENCH dense depth image {}: {:.0} ms ({:.0}% filled)",
            cam.model.name(),
            t.elapsed().as_secs_f64() * 1e3,
            100.0 * depth.num_filled() as f64 / depth.range_m.len() as f64
        );
    }
}

/// The `depth` command end to end (through its library entry point; the
/// binary's wiring is the lead's): a PLY map and a text model in, a PNG out.
#[test]
fn depth_command_writes_png() {
    use colmap_lidar::commands::depth::{run, DepthArgs};
    use colmap_lidar::io::model::{write_model, ModelFormat};
    use colmap_lidar::map::io::write_ply;
    use colmap_lidar::scene::ids::ImageId;
    use colmap_lidar::scene::reconstruction::{Image, Point2D, Reconstruction};

    let (cloud, _, _) = planes_scene(0.1);
    let dir = tempfile::tempdir().unwrap();
    let map = dir.path().join("map.ply");
    write_ply(&map, &cloud).unwrap();
    let cam = camera(
        CameraModel::Pinhole,
        160,
        120,
        vec![120.0, 120.0, 80.0, 60.0],
    );
    let pose = camera_pose(utm_origin() + Vector3::new(0.5, -0.5, 1.6), 0.0, 0.1, 0.1);
    let mut rec = Reconstruction::default();
    rec.cameras.insert(cam.id, cam.clone());
    let points2d = vec![
        Point2D {
            xy: Vector2::new(80.5, 100.5),
            point3d_id: None,
        },
        Point2D {
            xy: Vector2::new(10.0, 5.0),
            point3d_id: None,
        },
    ];
    rec.images.insert(
        ImageId(1),
        Image {
            id: ImageId(1),
            name: "a.jpg".into(),
            camera_id: cam.id,
            cam_from_world: Some(pose),
            points2d,
        },
    );
    let model = dir.path().join("model");
    write_model(&model, &rec, ModelFormat::Text).unwrap();
    let output = dir.path().join("out").join("depth.png");
    let mut args = DepthArgs {
        lidar: map,
        model,
        image: "a.jpg".into(),
        output: output.clone(),
        min_depth: 0.5,
        max_depth: 40.0,
    };
    run(&args).unwrap();
    let img = image::open(&output).unwrap().to_rgb8();
    assert_eq!(img.dimensions(), (160, 120));
    // The floor is seen below the horizon: not black there.
    assert_ne!(img.get_pixel(80, 110).0, [0, 0, 0]);
    // The same image by its id: the same PNG.
    let by_name = std::fs::read(&output).unwrap();
    args.image = "1".into();
    args.output = dir.path().join("by_id.png");
    run(&args).unwrap();
    assert_eq!(std::fs::read(&args.output).unwrap(), by_name);
    // Unknown image: a clear error, no output.
    args.image = "missing.jpg".into();
    args.output = dir.path().join("none.png");
    let err = run(&args).unwrap_err();
    assert!(format!("{err:#}").contains("missing.jpg"));
    assert!(!args.output.exists());
}

/// On a map sampled every 10 cm (sparser than the default splats suit),
/// a camera 6.5 m from the frontal panel sees the wall behind it through
/// the gaps between the default splats, and one 1.2 m from it too (the
/// reference's splat stops growing nearer than 2 m); `widen_splats_for_map`
/// (the depth command's and, through `MapperOptions::for_map_spacing`, the
/// mapper's rule) closes the panel at both distances.
#[test]
fn sparse_map_splats_are_widened_to_close_surfaces() {
    use colmap_lidar::commands::depth::widen_splats_for_map;
    let (cloud, _, rects) = planes_scene(0.1);
    let grid = FrustumGrid::build(&cloud, &GridOptions::default()).unwrap();
    let cam = camera(
        CameraModel::Pinhole,
        320,
        240,
        vec![400.0, 400.0, 160.0, 120.0],
    );
    // Share of the pixels whose ray meets the panel (rectangle 3, x = 7 m)
    // that see something else (farther, or nothing), from `centre_local`
    // looking along +x.
    let see_through = |options: &ProjectionOptions, centre_local: Vector3<f64>| -> f64 {
        let pose = camera_pose(utm_origin() + centre_local, 0.0, 0.0, 0.0);
        let world_from_cam = pose.inverse();
        let depth = render_depth_image(&cloud, &grid, &cam, &pose, options).unwrap();
        let (mut on_panel, mut through) = (0usize, 0usize);
        for y in 0..240 {
            for x in 0..320 {
                let px = Vector2::new(x as f64 + 0.5, y as f64 + 0.5);
                let dir = (world_from_cam.rotation * cam.unproject(&px).unwrap()).normalize();
                if let Some((3, t)) = ray_cast(&rects, &centre_local, &dir) {
                    on_panel += 1;
                    let range = f64::from(depth.range_m[y * 320 + x]);
                    if !(range < t + 0.5) {
                        through += 1;
                    }
                }
            }
        }
        assert!(on_panel > 10_000, "{on_panel} panel pixels");
        through as f64 / on_panel as f64
    };
    let default = ProjectionOptions::default();
    let mut widened = default.clone();
    let spacing = widen_splats_for_map(&mut widened, &cloud).expect("a spacing");
    // A square lattice's estimate: sqrt(pi / 4) of its spacing.
    assert!((0.08..0.1).contains(&spacing), "{spacing}");
    assert!(widened.splat.patch_half_width_m > default.splat.patch_half_width_m);
    for (label, centre, min_before) in [
        ("6.5 m", Vector3::new(0.5, -0.5, 1.6), 0.05),
        ("1.2 m", Vector3::new(5.8, -0.25, 1.55), 0.3),
    ] {
        let (before, after) = (see_through(&default, centre), see_through(&widened, centre));
        eprintln!("10 cm map, camera {label} from the panel: {before:.4} of its pixels see through it with the default splats, {after:.4} widened");
        assert!(before > min_before, "{label}: {before}");
        assert!(after < 0.005, "{label}: {after}");
    }
    // The far-field splat saturating at 2 m (the width above) alone leaves
    // the near camera seeing through.
    let mut saturating = widened.clone();
    saturating.splat.near_half_width_m = 0.0;
    let gaps = see_through(&saturating, Vector3::new(5.8, -0.25, 1.55));
    assert!(gaps > 0.1, "{gaps}");
    // A dense map keeps the reference's splat, with a floor that only
    // matters nearer than about 0.8 m.
    let (dense, _, _) = planes_scene(0.02);
    let mut kept = default.clone();
    let dense_spacing = widen_splats_for_map(&mut kept, &dense).expect("a spacing");
    assert_eq!(
        kept.splat.patch_half_width_m,
        default.splat.patch_half_width_m
    );
    assert!((kept.splat.near_half_width_m - 0.6 * dense_spacing).abs() < 1e-12);
    assert_eq!(
        kept.splat.half_size_px(1.0, 400.0),
        default.splat.half_size_px(1.0, 400.0)
    );
}
