//! Depth maps of the LiDAR map for a model's images: against ray casting
//! through the synthetic scenes' exact surfaces, and `depth-maps` end to end.
use std::path::Path;
use std::process::Command;

use colmap_lidar::commands::depth_maps::SUMMARY_FILE;
use colmap_lidar::map::grid::{FrustumGrid, GridOptions};
use colmap_lidar::map::index::MapIndex;
use colmap_lidar::map::surface_depth::{
    render_surface_depth, DepthKind, MapSurface, PixelRays, SurfaceDepthOptions,
};
use colmap_lidar::sfm::associate::NearestNeighbourAssociator;
use colmap_lidar::sfm::mapper::options_for_map;
use colmap_lidar::sfm::options::MapperOptions;
use colmap_lidar::synth::generate::generate_scene;
use colmap_lidar::synth::scenes::{build_scene, trajectory};
use colmap_lidar::synth::{SceneKind, SynthOptions};
use nalgebra::Vector3;

use crate::common;

/// Errors of one scene's depth maps against ray casting.
#[derive(Debug, Default)]
struct Errors {
    /// |depth - true depth| of the pixels that have both, metres.
    abs: Vec<f64>,
    /// Pixels whose ray meets a surface within the depth range, and of
    /// those the ones with a depth.
    visible: usize,
    filled: usize,
}

impl Errors {
    fn quantile(&mut self, q: f64) -> f64 {
        self.abs.sort_by(f64::total_cmp);
        self.abs[((self.abs.len() - 1) as f64 * q) as usize]
    }
    fn share_within(&self, limit_m: f64) -> f64 {
        self.abs.iter().filter(|&&e| e <= limit_m).count() as f64 / self.abs.len() as f64
    }
}

/// Depth maps of `kind`'s seed-0 scene from four of its 24 poses, with the
/// surface-following depth (`reach` 4 splat half-widths) or each splat's
/// own (0), on a map drawn with `noise_m` along the normals.
fn errors_against_ray_casting(
    kind: SceneKind,
    noise_m: f64,
    reach: f64,
    local_planes: bool,
    drop_edges: bool,
) -> Errors {
    let scene = build_scene(kind, 0);
    let (cloud, _) = super::scan_without_holes(&scene, noise_m);
    let grid = FrustumGrid::build(&cloud, &GridOptions::default()).unwrap();
    let index = MapIndex::build(&cloud).unwrap();
    let adapted = options_for_map(&MapperOptions::default(), &cloud, &index);
    let planes = NearestNeighbourAssociator::new(&cloud, &index, adapted.options.association);
    let surface_at = |i: usize| {
        planes
            .plane_offset_at(i)
            .map_or(MapSurface::NoPlane, MapSurface::Plane)
    };
    let mut options = SurfaceDepthOptions {
        max_reach_half_widths: reach,
        drop_edges,
        ..Default::default()
    };
    options.splats_for_spacing(adapted.spacing_m.unwrap());
    let camera = SynthOptions::default().camera();
    let rays = PixelRays::new(&camera);
    let mut errors = Errors::default();
    for pose in trajectory(kind, 24, 0).iter().step_by(6) {
        let cam_from_world = pose.to_cam_from_world();
        let centre = cam_from_world.camera_center();
        let world_from_cam = cam_from_world.inverse();
        let depth = render_surface_depth(
            &cloud,
            &grid,
            &camera,
            &rays,
            &cam_from_world,
            &options,
            DepthKind::Z,
            local_planes.then_some(&surface_at as _),
        )
        .unwrap();
        for y in 0..camera.height {
            for x in 0..camera.width {
                let pixel = nalgebra::Vector2::new(f64::from(x) + 0.5, f64::from(y) + 0.5);
                let ray = camera.unproject(&pixel).unwrap();
                let dir = world_from_cam.rotation * ray.normalize();
                let Some(hit) = scene.cast(&centre, &dir, 1e-3, 100.0) else {
                    continue;
                };
                // z of the hit: its distance times the unit ray's z.
                let z = hit.t / ray.norm();
                // Clear of the depth range's ends (the map's points there
                // are in or out by their noise).
                if !(0.6..39.0).contains(&z) {
                    continue;
                }
                errors.visible += 1;
                let d = depth.depth_m[(y * camera.width + x) as usize];
                if d > 0.0 {
                    errors.filled += 1;
                    errors.abs.push((f64::from(d) - z).abs());
                }
            }
        }
    }
    errors
}

/// Against the scenes' exact surfaces, from four poses each of the seed-0
/// room and yard (640 x 480):
/// * with a noise-free map, the depth follows the surfaces to within
///   micrometres at the median, where each splat's own depth is off by
///   millimetres (a splat is flat, facing the camera);
/// * with the synthetic scan's 15 mm noise, the planes through the mean of
///   each point's neighbours put the median error well below the noise,
///   where each point's own tangent plane (through its noisy position,
///   crossed at a slant) is off by more than the noise;
/// * the pixels off by more than 10 cm (occluding edges, where the splats
///   of the surface in front reach past it) are few, and nearly every pixel
///   that sees a surface has a depth; with the pixels beside steps between
///   surfaces dropped, almost none is off, and 9 in 10 keep their depth.
#[test]
fn depth_maps_agree_with_ray_casting() {
    for kind in [SceneKind::Room, SceneKind::Yard] {
        let mut exact = errors_against_ray_casting(kind, 0.0, 4.0, true, false);
        let mut flat = errors_against_ray_casting(kind, 0.0, 0.0, false, false);
        let mut noisy = errors_against_ray_casting(kind, 0.015, 4.0, true, false);
        let mut noisy_own = errors_against_ray_casting(kind, 0.015, 4.0, false, false);
        let mut noisy_flat = errors_against_ray_casting(kind, 0.015, 0.0, false, false);
        let mut noisy_no_edges = errors_against_ray_casting(kind, 0.015, 4.0, true, true);
        let coverage = exact.filled as f64 / exact.visible as f64;
        println!(
            "{}: {} pixels see a surface, {:.2} % with a depth",
            kind.name(),
            exact.visible,
            100.0 * coverage
        );
        for (what, e) in [
            ("noise-free, local planes", &mut exact),
            ("noise-free, splats' own depths", &mut flat),
            ("15 mm, local planes", &mut noisy),
            ("15 mm, each point's tangent plane", &mut noisy_own),
            ("15 mm, splats' own depths", &mut noisy_flat),
            ("15 mm, local planes, edges dropped", &mut noisy_no_edges),
        ] {
            println!(
                "  {what}: median {:.3} mm, p90 {:.2} mm, {:.2} % off by more than 10 cm, \
                 {:.1} % with a depth",
                1e3 * e.quantile(0.5),
                1e3 * e.quantile(0.9),
                100.0 * (1.0 - e.share_within(0.1)),
                100.0 * e.filled as f64 / e.visible as f64
            );
        }
        let name = kind.name();
        assert!(exact.visible > 500_000, "{name}");
        assert!(coverage > 0.995, "{name}: {coverage}");
        let median = exact.quantile(0.5);
        assert!(median < 1e-4, "{name}: {median}");
        assert!(flat.quantile(0.5) > 10.0 * median.max(1e-5), "{name}");
        assert!(exact.quantile(0.9) < flat.quantile(0.9), "{name}");
        let noisy_median = noisy.quantile(0.5);
        assert!(noisy_median < 0.004, "{name}: {noisy_median}");
        assert!(noisy_median < 0.5 * noisy_own.quantile(0.5), "{name}");
        assert!(noisy_median < 0.5 * noisy_flat.quantile(0.5), "{name}");
        // Without the pixels beside steps between surfaces: almost none off.
        let kept = noisy_no_edges.filled as f64 / noisy_no_edges.visible as f64;
        assert!(kept > 0.9, "{name}: {kept}");
        assert!(noisy_no_edges.share_within(0.1) > 0.998, "{name}");
        assert!(noisy_no_edges.quantile(0.5) <= noisy_median, "{name}");
        for e in [&exact, &noisy] {
            assert!(e.share_within(0.1) > 0.9825, "{name}");
        }
    }
}

/// Reads a 16-bit greyscale PNG's values.
fn read_png16(path: &Path) -> (u32, u32, Vec<u16>) {
    let img = image::open(path).unwrap();
    assert!(
        matches!(img, image::DynamicImage::ImageLuma16(_)),
        "{}: not 16-bit grey",
        path.display()
    );
    let img = img.into_luma16();
    (img.width(), img.height(), img.into_raw())
}

/// Reads a float32 `.npy` written by `depth-maps`: (height, width, values).
fn read_npy(path: &Path) -> (usize, usize, Vec<f32>) {
    let bytes = std::fs::read(path).unwrap();
    assert_eq!(&bytes[..8], b"\x93NUMPY\x01\x00");
    let len = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
    let header = std::str::from_utf8(&bytes[10..10 + len]).unwrap();
    let shape = header.split("'shape': (").nth(1).unwrap();
    let shape: Vec<usize> = shape
        .split(')')
        .next()
        .unwrap()
        .split(',')
        .map(|s| s.trim().parse().unwrap())
        .collect();
    let values: Vec<f32> = bytes[10 + len..]
        .chunks(4)
        .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
        .collect();
    assert_eq!(values.len(), shape[0] * shape[1]);
    (shape[0], shape[1], values)
}

/// `depth-maps` of `model` in `lidar` into `output`, with `extra` arguments.
fn depth_maps(lidar: &Path, model: &Path, output: &Path, extra: &[&str]) -> std::process::Output {
    Command::new(common::bin())
        .arg("depth-maps")
        .arg("--lidar")
        .arg(lidar)
        .arg("--model")
        .arg(model)
        .arg("--output")
        .arg(output)
        .args(extra)
        .output()
        .unwrap()
}

/// `depth-maps` on a georeferenced synthetic yard's true model (4 images,
/// 320 x 240, the world 500 km / 4400 km away): one 16-bit PNG in
/// millimetres per image whose values are the library's depths rounded,
/// and `.npy` files with its float32 depths exactly; `depth_maps.json`
/// says so; the PNGs' depths meet ray casting; bad requests are errors that
/// leave no output.
#[test]
fn depth_maps_command_writes_png_and_npy() {
    let dir = tempfile::tempdir().unwrap();
    let scene_dir = dir.path().join("yard");
    let mut opts = SynthOptions {
        scene: SceneKind::Yard,
        num_images: 4,
        width: 320,
        height: 240,
        seed: 0,
        offset_m: Vector3::new(500000.0, 4400000.0, 200.0),
        ..SynthOptions::default()
    };
    opts.lidar.max_points = 300_000;
    generate_scene(&opts, &scene_dir).unwrap();
    let (lidar, model) = (scene_dir.join("lidar.ply"), scene_dir.join("gt"));
    let png_dir = dir.path().join("depth_png");
    let out = depth_maps(&lidar, &model, &png_dir, &[]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let npy_dir = dir.path().join("depth_npy");
    let out = depth_maps(&lidar, &model, &npy_dir, &["--format", "npy"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );

    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(png_dir.join(SUMMARY_FILE)).unwrap()).unwrap();
    assert_eq!(summary["format"], "png16");
    assert_eq!(summary["depth"], "z");
    assert_eq!(summary["units_per_metre"], 1000.0);
    let images = summary["images"].as_array().unwrap();
    assert_eq!(images.len(), 4);
    let scene = build_scene(SceneKind::Yard, 0);
    let camera = opts.camera();
    let poses = trajectory(SceneKind::Yard, 4, 0);
    let mut errors = Vec::new();
    for (k, entry) in images.iter().enumerate() {
        let name = format!("frame_{k:04}");
        assert_eq!(entry["name"], format!("{name}.jpg"));
        assert_eq!(entry["file"], format!("{name}.png"));
        assert!(entry["filled_share"].as_f64().unwrap() > 0.5, "{entry}");
        let (w, h, mm) = read_png16(&png_dir.join(format!("{name}.png")));
        assert_eq!((w, h), (320, 240));
        let (rows, cols, metres) = read_npy(&npy_dir.join(format!("{name}.npy")));
        assert_eq!((rows, cols), (240, 320));
        for (&m, &v) in metres.iter().zip(&mm) {
            // The PNG holds the npy's depths in millimetres, rounded.
            assert_eq!(v, (f64::from(m) * 1000.0).round() as u16);
        }
        // Against the scene (in its own frame: the trajectory's poses).
        let cam_from_world = poses[k].to_cam_from_world();
        let world_from_cam = cam_from_world.inverse();
        for y in (0..240).step_by(3) {
            for x in (0..320).step_by(3) {
                let v = mm[(y * 320 + x) as usize];
                if v == 0 {
                    continue;
                }
                let pixel = nalgebra::Vector2::new(f64::from(x) + 0.5, f64::from(y) + 0.5);
                let ray = camera.unproject(&pixel).unwrap();
                let dir = world_from_cam.rotation * ray.normalize();
                let hit = scene.cast(&cam_from_world.camera_center(), &dir, 1e-3, 100.0);
                let Some(hit) = hit else { continue };
                errors.push((f64::from(v) / 1000.0 - hit.t / ray.norm()).abs());
            }
        }
    }
    // The map has the synthetic scan's holes (0.25-1 m wide), where the
    // depth is the surface behind, and its 15 mm noise.
    errors.sort_by(f64::total_cmp);
    let (median, p90) = (errors[errors.len() / 2], errors[errors.len() * 9 / 10]);
    println!(
        "{} pixels: median error {:.2} mm, p90 {:.1} mm",
        errors.len(),
        1e3 * median,
        1e3 * p90
    );
    assert!(errors.len() > 10_000, "{}", errors.len());
    assert!(median < 0.008, "{median}");
    assert!(p90 < 0.03, "{p90}");

    // With the pixels beside steps between surfaces dropped: fewer pixels,
    // each one of those written without.
    let edges_dir = dir.path().join("depth_no_edges");
    let out = depth_maps(&lidar, &model, &edges_dir, &["--drop-edges"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let edges: serde_json::Value =
        serde_json::from_slice(&std::fs::read(edges_dir.join(SUMMARY_FILE)).unwrap()).unwrap();
    assert_eq!(edges["edges_dropped"], true);
    assert_eq!(summary["edges_dropped"], false);
    for (k, entry) in edges["images"].as_array().unwrap().iter().enumerate() {
        let (all, kept) = (
            images[k]["filled_share"].as_f64().unwrap(),
            entry["filled_share"].as_f64().unwrap(),
        );
        assert!(kept < all && kept > 0.7 * all, "{kept} {all}");
        let name = format!("frame_{k:04}.png");
        let (_, _, with) = read_png16(&png_dir.join(&name));
        let (_, _, without) = read_png16(&edges_dir.join(&name));
        assert!(with.iter().zip(&without).all(|(a, b)| *b == 0 || a == b));
    }

    // A depth range a 16-bit PNG cannot hold in millimetres: an error that
    // says so, and nothing written.
    let refused = dir.path().join("refused");
    let out = depth_maps(&lidar, &model, &refused, &["--max-depth", "80"]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        stderr.contains("beyond what a 16-bit PNG holds"),
        "{stderr}"
    );
    assert!(!refused.exists());
    // A folder that is not a previous output is not replaced.
    let out = depth_maps(&lidar, &model, &scene_dir.join("images"), &[]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        stderr.contains("not a previous output of depth-maps"),
        "{stderr}"
    );
    assert!(scene_dir.join("images/frame_0000.jpg").is_file());
    // A previous output is replaced: the npy folder as PNGs.
    let out = depth_maps(&lidar, &model, &npy_dir, &[]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(npy_dir.join("frame_0000.png").is_file());
    assert!(!npy_dir.join("frame_0000.npy").exists());
}
