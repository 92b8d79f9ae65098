//! Integration tests: camera_models.
//!
//! The Rust camera models (`Camera::project`/`unproject`) against the C++ twin
//! used by the solver (`cpp/camera_models.h`, through `project_points_cpp`),
//! against themselves (round trips) and against values computed by hand.
use std::f64::consts::PI;

use colmap_lidar::scene::{Camera, CameraId, CameraModel};
use colmap_lidar::solver::project_points_cpp;
use nalgebra::{Vector2, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Largest allowed |Rust - C++| per pixel coordinate.
const CPP_TOLERANCE_PX: f64 = 1e-9;
/// Largest allowed |project(unproject(p)) - p|.
const ROUND_TRIP_TOLERANCE_PX: f64 = 1e-6;

fn camera(model: CameraModel, width: u32, height: u32, params: &[f64]) -> Camera {
    assert_eq!(params.len(), model.num_params(), "{}", model.name());
    Camera {
        id: CameraId(1),
        model,
        width,
        height,
        params: params.to_vec(),
    }
}

/// One realistic camera per model, with strong distortion, 1920 x 1080, chosen
/// so that every pixel of the image lies inside the model's domain (before the
/// fold, within 90° of the axis).
fn realistic_cameras() -> Vec<Camera> {
    use CameraModel as M;
    let (w, h) = (1920, 1080);
    vec![
        camera(M::SimplePinhole, w, h, &[1000.0, 960.0, 540.0]),
        camera(M::Pinhole, w, h, &[1000.0, 1010.0, 955.3, 545.1]),
        // ~190 px of barrel distortion in the corners.
        camera(M::SimpleRadial, w, h, &[1400.0, 960.0, 540.0, -0.15]),
        camera(M::Radial, w, h, &[1400.0, 958.0, 541.0, -0.2, 0.05]),
        camera(
            M::OpenCv,
            w,
            h,
            &[1400.0, 1390.0, 962.0, 538.0, -0.25, 0.08, 0.001, -0.0015],
        ),
        camera(
            M::OpenCvFisheye,
            w,
            h,
            &[800.0, 801.0, 960.0, 540.0, 0.05, -0.02, 0.01, -0.002],
        ),
        camera(
            M::FullOpenCv,
            w,
            h,
            &[
                1400.0, 1390.0, 962.0, 538.0, -0.25, 0.08, 0.001, -0.0015, 0.01, 0.05, 0.01, 0.001,
            ],
        ),
        camera(M::Fov, w, h, &[800.0, 805.0, 960.0, 540.0, 0.9]),
        camera(M::SimpleRadialFisheye, w, h, &[800.0, 960.0, 540.0, 0.04]),
        camera(M::RadialFisheye, w, h, &[800.0, 960.0, 540.0, 0.04, -0.01]),
        camera(
            M::ThinPrismFisheye,
            w,
            h,
            &[
                800.0, 805.0, 960.0, 540.0, 0.05, -0.02, 0.001, -0.0015, 0.01, -0.002, 0.0008,
                -0.0006,
            ],
        ),
    ]
}

/// Extra cameras at the edges of the parameter space: very strong distortion,
/// FOV near its omega -> 0 limit, pure pinhole FOV.
fn edge_case_cameras() -> Vec<Camera> {
    use CameraModel as M;
    vec![
        camera(
            M::OpenCv,
            1280,
            960,
            &[600.0, 600.0, 640.0, 480.0, -0.35, 0.12, 0.0, 0.0],
        ),
        camera(
            M::FullOpenCv,
            1280,
            960,
            &[
                500.0, 500.0, 640.0, 480.0, 0.3, -0.05, -0.002, 0.001, 0.01, 0.6, 0.02, 0.005,
            ],
        ),
        camera(
            M::OpenCvFisheye,
            1280,
            960,
            &[620.0, 620.0, 640.0, 480.0, -0.05, 0.01, -0.002, 0.0003],
        ),
        camera(M::Fov, 640, 480, &[500.0, 500.0, 320.0, 240.0, 1e-9]),
        camera(M::Fov, 640, 480, &[500.0, 500.0, 320.0, 240.0, 0.0]),
        camera(M::Fov, 640, 480, &[700.0, 700.0, 320.0, 240.0, 2.5]),
    ]
}

fn all_cameras() -> Vec<Camera> {
    let mut cameras = realistic_cameras();
    cameras.extend(edge_case_cameras());
    cameras
}

/// Random camera-frame points in a generous frustum: up to 1.25x the image's
/// half field of view (at most 85°), depths 0.05..100 m; plus points on and
/// very near the optical axis (series branches), at the series thresholds, on
/// and behind the camera plane.
fn frustum_points(cam: &Camera, rng: &mut ChaCha8Rng, count: usize) -> Vec<[f64; 3]> {
    let max_angle_rad = (1.25 * cam.max_half_fov_rad().unwrap()).min(85f64.to_radians());
    let mut points: Vec<[f64; 3]> = (0..count)
        .map(|_| {
            let angle_rad: f64 = rng.gen_range(0.0..max_angle_rad);
            let azimuth_rad: f64 = rng.gen_range(0.0..2.0 * PI);
            let z: f64 = rng.gen_range(0.05..100.0);
            let r = angle_rad.tan();
            [z * r * azimuth_rad.cos(), z * r * azimuth_rad.sin(), z]
        })
        .collect();
    for r in [
        0.0,
        1e-300,
        1e-12,
        1e-6,
        0.01 - 1e-12,
        0.01,
        0.01 + 1e-12,
        0.02,
    ] {
        points.push([r, 0.0, 1.0]);
        points.push([0.6 * r * 3.0, -0.8 * r * 3.0, 3.0]);
    }
    points.push([0.1, 0.2, 0.0]);
    points.push([0.1, 0.2, -1.0]);
    points.push([0.1, 0.2, -1e-300]);
    points
}

fn rust_project(cam: &Camera, point: &[f64; 3]) -> Option<Vector2<f64>> {
    cam.project(&Vector3::from(*point))
}

#[test]
fn rust_and_cpp_projections_agree() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let mut max_diff_px: f64 = 0.0;
    for cam in all_cameras() {
        let points = frustum_points(&cam, &mut rng, 4000);
        let cpp = project_points_cpp(cam.model.id(), &cam.params, &points).unwrap();
        let mut projected = 0;
        for (point, cpp_pixel) in points.iter().zip(&cpp) {
            match rust_project(&cam, point) {
                Some(pixel) => {
                    let diff_px = (pixel.x - cpp_pixel[0])
                        .abs()
                        .max((pixel.y - cpp_pixel[1]).abs());
                    assert!(
                        diff_px <= CPP_TOLERANCE_PX,
                        "{} {:?}: Rust {pixel:?} C++ {cpp_pixel:?}",
                        cam.model.name(),
                        point
                    );
                    max_diff_px = max_diff_px.max(diff_px);
                    projected += 1;
                }
                None => assert!(
                    cpp_pixel[0].is_nan() && cpp_pixel[1].is_nan(),
                    "{} {:?}: Rust None, C++ {cpp_pixel:?}",
                    cam.model.name(),
                    point
                ),
            }
        }
        // Only the three points on or behind the camera plane are unprojectable.
        assert_eq!(projected, points.len() - 3, "{}", cam.model.name());
    }
    eprintln!("max |Rust - C++| = {max_diff_px:e} px");
}

/// Pixels over the whole image: a grid including borders and corners, plus
/// random pixels.
fn image_pixels(cam: &Camera, rng: &mut ChaCha8Rng) -> Vec<Vector2<f64>> {
    let (width, height) = (f64::from(cam.width), f64::from(cam.height));
    let mut pixels = Vec::new();
    for i in 0..=64 {
        for j in 0..=36 {
            pixels.push(Vector2::new(
                width * f64::from(i) / 64.0,
                height * f64::from(j) / 36.0,
            ));
        }
    }
    for _ in 0..2000 {
        pixels.push(Vector2::new(
            rng.gen_range(0.0..width),
            rng.gen_range(0.0..height),
        ));
    }
    pixels
}

#[test]
fn project_of_unproject_is_identity_over_the_image() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let mut max_err_px: f64 = 0.0;
    for cam in all_cameras() {
        for pixel in image_pixels(&cam, &mut rng) {
            let ray = cam
                .unproject(&pixel)
                .unwrap_or_else(|| panic!("{}: unproject {pixel:?} failed", cam.model.name()));
            assert_eq!(ray.z, 1.0);
            // Any point along the ray projects to the same pixel.
            for depth_m in [0.3, 7.0] {
                let back = cam
                    .project(&(ray * depth_m))
                    .unwrap_or_else(|| panic!("{}: project failed", cam.model.name()));
                let err_px = (back - pixel).norm();
                assert!(
                    err_px <= ROUND_TRIP_TOLERANCE_PX,
                    "{}: {pixel:?} -> {ray:?} -> {back:?}",
                    cam.model.name()
                );
                max_err_px = max_err_px.max(err_px);
            }
        }
    }
    eprintln!("max |project(unproject(p)) - p| = {max_err_px:e} px");
}

#[test]
fn unproject_of_project_recovers_the_ray() {
    let mut rng = ChaCha8Rng::seed_from_u64(13);
    for cam in realistic_cameras() {
        let half_fov_rad = cam.max_half_fov_rad().unwrap();
        for _ in 0..2000 {
            let angle_rad: f64 = rng.gen_range(0.0..half_fov_rad);
            let azimuth_rad: f64 = rng.gen_range(0.0..2.0 * PI);
            let r = angle_rad.tan();
            let normalized = Vector3::new(r * azimuth_rad.cos(), r * azimuth_rad.sin(), 1.0);
            let pixel = cam.project(&(normalized * 4.0)).unwrap();
            let ray = cam
                .unproject(&pixel)
                .unwrap_or_else(|| panic!("{}: unproject {pixel:?}", cam.model.name()));
            assert!(
                (ray - normalized).norm() <= 1e-10 * (1.0 + r * r),
                "{}: {normalized:?} -> {pixel:?} -> {ray:?}",
                cam.model.name()
            );
        }
    }
}

#[test]
fn unproject_of_principal_point_is_the_optical_axis() {
    for cam in all_cameras() {
        let ray = cam.unproject(&cam.principal_point()).unwrap();
        assert!(
            ray.xy().norm() <= 1e-15 && ray.z == 1.0,
            "{}: {ray:?}",
            cam.model.name()
        );
        let pixel = cam.project(&Vector3::new(0.0, 0.0, 2.5)).unwrap();
        assert!((pixel - cam.principal_point()).norm() <= 1e-12);
    }
}

/// Both implementations against a value computed by hand.
fn assert_projects_to(cam: &Camera, point: [f64; 3], expected: [f64; 2]) {
    let rust = rust_project(cam, &point).unwrap();
    let cpp = project_points_cpp(cam.model.id(), &cam.params, &[point]).unwrap()[0];
    for (name, got) in [("Rust", [rust.x, rust.y]), ("C++", cpp)] {
        assert!(
            (got[0] - expected[0]).abs() <= 1e-9 && (got[1] - expected[1]).abs() <= 1e-9,
            "{} {name}: {got:?} != {expected:?}",
            cam.model.name()
        );
    }
    // And back.
    let ray = cam.unproject(&Vector2::from(expected)).unwrap();
    let expected_ray = Vector3::new(point[0] / point[2], point[1] / point[2], 1.0);
    assert!(
        (ray - expected_ray).norm() <= 1e-10,
        "{}: {ray:?} != {expected_ray:?}",
        cam.model.name()
    );
}

#[test]
fn hand_computed_projections() {
    use CameraModel as M;
    let (w, h) = (1000, 800);

    // SIMPLE_PINHOLE / PINHOLE: f * x / z + c.
    let cam = camera(M::SimplePinhole, w, h, &[1000.0, 500.0, 400.0]);
    assert_projects_to(&cam, [0.6, -0.8, 2.0], [800.0, 0.0]);
    let cam = camera(M::Pinhole, w, h, &[1000.0, 500.0, 510.0, 390.0]);
    assert_projects_to(&cam, [0.6, -0.8, 2.0], [810.0, 190.0]);

    // SIMPLE_RADIAL, k = -0.1, (u, v) = (0.3, 0.4): r² = 0.25, factor 0.975.
    let cam = camera(M::SimpleRadial, w, h, &[1000.0, 500.0, 400.0, -0.1]);
    assert_projects_to(&cam, [0.3, 0.4, 1.0], [792.5, 790.0]);

    // RADIAL, k1 = -0.1, k2 = 0.04: factor 1 - 0.025 + 0.0025 = 0.9775.
    let cam = camera(M::Radial, w, h, &[1000.0, 500.0, 400.0, -0.1, 0.04]);
    assert_projects_to(&cam, [0.6, 0.8, 2.0], [793.25, 791.0]);

    // OPENCV at (u, v) = (0.2, -0.1): r² = 0.05, radial 1.005025,
    // tangential (-0.00004 + 0.00026, -0.00008 + 0.00007) = (0.00022, -0.00001),
    // distorted (0.201225, -0.1005125).
    let cam = camera(
        M::OpenCv,
        w,
        h,
        &[800.0, 810.0, 320.0, 240.0, 0.1, 0.01, 0.001, 0.002],
    );
    assert_projects_to(&cam, [0.4, -0.2, 2.0], [480.98, 158.584875]);

    // FULL_OPENCV, k1 = 0.1, k4 = 0.2 at u = 0.5: factor 1.025 / 1.05.
    let cam = camera(
        M::FullOpenCv,
        w,
        h,
        &[
            800.0, 810.0, 320.0, 240.0, 0.1, 0.0, 0.0, 0.0, 0.0, 0.2, 0.0, 0.0,
        ],
    );
    assert_projects_to(
        &cam,
        [0.5, 0.0, 1.0],
        [320.0 + 800.0 * 0.5 * 1.025 / 1.05, 240.0],
    );

    // Fisheye models at 45° (u = 1, θ = π/4): equidistant radius π/4.
    let theta = PI / 4.0;
    let theta_sq = theta * theta;
    let cam = camera(M::SimpleRadialFisheye, w, h, &[500.0, 500.0, 400.0, 0.1]);
    let x = theta * (1.0 + 0.1 * theta_sq);
    assert_projects_to(&cam, [2.0, 0.0, 2.0], [500.0 + 500.0 * x, 400.0]);
    let cam = camera(M::RadialFisheye, w, h, &[500.0, 500.0, 400.0, 0.1, -0.05]);
    let y = theta * (1.0 + 0.1 * theta_sq - 0.05 * theta_sq * theta_sq);
    assert_projects_to(&cam, [0.0, 2.0, 2.0], [500.0, 400.0 + 500.0 * y]);
    let cam = camera(
        M::OpenCvFisheye,
        w,
        h,
        &[500.0, 510.0, 500.0, 400.0, 0.1, -0.05, 0.01, -0.002],
    );
    let x = theta
        * (1.0 + 0.1 * theta_sq - 0.05 * theta_sq.powi(2) + 0.01 * theta_sq.powi(3)
            - 0.002 * theta_sq.powi(4));
    assert_projects_to(&cam, [-1.0, 0.0, 1.0], [500.0 - 500.0 * x, 400.0]);
    // THIN_PRISM_FISHEYE with only sx1, sy1: (θ + sx1 θ², sy1 θ²).
    let cam = camera(
        M::ThinPrismFisheye,
        w,
        h,
        &[
            500.0, 510.0, 500.0, 400.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.01, -0.02,
        ],
    );
    assert_projects_to(
        &cam,
        [1.0, 0.0, 1.0],
        [
            500.0 + 500.0 * (theta + 0.01 * theta_sq),
            400.0 - 510.0 * 0.02 * theta_sq,
        ],
    );

    // FOV, ω = π/2 (2 tan(ω/2) = 2): at r = √3/2, atan(√3) = π/3 and the
    // distorted radius is (π/3) / (π/2) = 2/3.
    let cam = camera(M::Fov, w, h, &[500.0, 510.0, 500.0, 400.0, PI / 2.0]);
    let r = 3f64.sqrt() / 2.0;
    assert_projects_to(&cam, [0.0, r, 1.0], [500.0, 400.0 + 510.0 * 2.0 / 3.0]);
    assert_projects_to(
        &cam,
        [0.6 * r, 0.8 * r, 1.0],
        [
            500.0 + 500.0 * 0.6 * 2.0 / 3.0,
            400.0 + 510.0 * 0.8 * 2.0 / 3.0,
        ],
    );
    // FOV with ω = 0 is a pinhole.
    let cam = camera(M::Fov, w, h, &[500.0, 510.0, 500.0, 400.0, 0.0]);
    assert_projects_to(&cam, [0.3, -0.2, 1.0], [650.0, 298.0]);
}

#[test]
fn fov_is_continuous_across_its_small_omega_limit() {
    // Omega just below and above the series threshold (ω²/4 = 1e-4, ω = 0.02)
    // and far below it: the projection changes smoothly with ω.
    let point = Vector3::new(0.7, -0.4, 1.0);
    let project = |omega: f64| {
        camera(
            CameraModel::Fov,
            640,
            480,
            &[500.0, 500.0, 320.0, 240.0, omega],
        )
        .project(&point)
        .unwrap()
    };
    for omega in [0.02, 1e-6] {
        let below = project(omega * (1.0 - 1e-9));
        let above = project(omega * (1.0 + 1e-9));
        assert!(
            (below - above).norm() < 1e-9,
            "{omega}: {below:?} {above:?}"
        );
    }
    // As ω -> 0 the model tends to the pinhole: factor 1 + ω²/12 - ω² r²/3 + O(ω⁴).
    let omega: f64 = 1e-3;
    let r_sq = point.xy().norm_squared();
    let factor = 1.0 + omega * omega / 12.0 - omega * omega * r_sq / 3.0;
    let expected = Vector2::new(320.0 + 500.0 * 0.7 * factor, 240.0 - 500.0 * 0.4 * factor);
    assert!((project(omega) - expected).norm() < 1e-9);
}

#[test]
fn unproject_outside_the_domain_is_none() {
    use CameraModel as M;
    // SIMPLE_RADIAL, k = -0.3: the distorted radius peaks at 2/(3 sqrt(0.9)) ≈ 0.703.
    let cam = camera(M::SimpleRadial, 640, 480, &[100.0, 320.0, 240.0, -0.3]);
    assert!(cam.unproject(&Vector2::new(320.0 + 69.0, 240.0)).is_some());
    assert!(cam.unproject(&Vector2::new(320.0 + 71.0, 240.0)).is_none());
    // Fisheye: equidistant radius π/2 is 90° from the axis.
    let cam = camera(
        M::SimpleRadialFisheye,
        640,
        480,
        &[100.0, 320.0, 240.0, 0.0],
    );
    assert!(cam.unproject(&Vector2::new(320.0 + 156.0, 240.0)).is_some());
    assert!(cam.unproject(&Vector2::new(320.0 + 158.0, 240.0)).is_none());
    // FOV, ω = π/2: the distorted radius of a ray at 90° is 1.
    let cam = camera(M::Fov, 640, 480, &[100.0, 100.0, 320.0, 240.0, PI / 2.0]);
    assert!(cam.unproject(&Vector2::new(320.0, 240.0 + 99.0)).is_some());
    assert!(cam.unproject(&Vector2::new(320.0, 240.0 + 101.0)).is_none());
    // Non-finite pixels.
    assert!(cam.unproject(&Vector2::new(f64::NAN, 240.0)).is_none());
}

#[test]
fn cpp_rejects_bad_input() {
    let point = [[0.1, 0.2, 1.0]];
    let err = project_points_cpp(4, &[500.0, 500.0, 320.0, 240.0], &point).unwrap_err();
    assert!(err.contains("takes 8 parameters, got 4"), "{err}");
    for bad_id in [11, -1, 1000] {
        let err = project_points_cpp(bad_id, &[500.0, 320.0, 240.0], &point).unwrap_err();
        assert!(err.contains("unknown camera model id"), "{err}");
    }
    // An empty point list is fine.
    assert_eq!(
        project_points_cpp(0, &[500.0, 320.0, 240.0], &[]).unwrap(),
        Vec::<[f64; 2]>::new()
    );
}

/// Include directories for Eigen (pkg-config, else Debian's default path).
fn eigen_include_dirs() -> Vec<String> {
    let dirs: Vec<String> = std::process::Command::new("pkg-config")
        .args(["--cflags-only-I", "eigen3"])
        .output()
        .ok()
        .filter(|out| out.status.success())
        .map(|out| {
            String::from_utf8_lossy(&out.stdout)
                .split_whitespace()
                .filter_map(|flag| flag.strip_prefix("-I").map(str::to_owned))
                .collect()
        })
        .unwrap_or_default();
    if dirs.is_empty() {
        vec!["/usr/include/eigen3".to_owned()]
    } else {
        dirs
    }
}

/// Compiles and runs `cpp/camera_models_jet_check.cc`: Ceres autodiff through
/// `ProjectPoint` gives finite derivatives equal to finite differences for
/// every model, also on the optical axis (r = 0) and at the series thresholds;
/// and the solver's closed-form reprojection Jacobians (`cpp/reprojection.h`)
/// equal autodiff of the same residual for every model and several poses.
#[test]
fn cpp_autodiff_derivatives_are_finite_and_correct() {
    let compiler = std::env::var("CXX").unwrap_or_else(|_| "c++".to_owned());
    let manifest_dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let dir = tempfile::tempdir().unwrap();
    let exe = dir.path().join("camera_models_jet_check");
    let mut command = std::process::Command::new(&compiler);
    command
        .args(["-std=c++17", "-O1", "-o"])
        .arg(&exe)
        .arg(manifest_dir.join("cpp/camera_models_jet_check.cc"))
        .arg(format!("-I{}", manifest_dir.join("cpp").display()));
    for include in eigen_include_dirs() {
        command.arg(format!("-I{include}"));
    }
    let compiled = match command.output() {
        Ok(out) => out,
        Err(err) => {
            // The crate itself cannot build without a C++ compiler, so this
            // only happens when CXX names something odd.
            eprintln!("\n!!!!! SKIPPED: cannot run C++ compiler `{compiler}`: {err} !!!!!\n");
            return;
        }
    };
    assert!(
        compiled.status.success(),
        "compiling camera_models_jet_check.cc failed:\n{}",
        String::from_utf8_lossy(&compiled.stderr)
    );
    let run = std::process::Command::new(&exe).output().unwrap();
    let stdout = String::from_utf8_lossy(&run.stdout);
    eprintln!("{stdout}");
    assert!(run.status.success(), "autodiff check failed:\n{stdout}");
    assert!(stdout.contains(" 0 failures"), "{stdout}");
}
