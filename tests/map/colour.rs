//! The map coloured by images: which map points an image sees, against
//! ray casting through the synthetic scenes' exact surfaces.
use std::collections::BTreeSet;

use colmap_lidar::map::colour::{seen_points, MapColourOptions};
use colmap_lidar::map::grid::{FrustumGrid, GridOptions};
use colmap_lidar::synth::scenes::{build_scene, trajectory};
use colmap_lidar::synth::{SceneKind, SynthOptions};
use image::RgbImage;
use nalgebra::Vector3;

/// In a room and a yard (seed 0, the synthetic LiDAR's 15 mm noise), seen
/// from four of each trajectory's poses:
/// * of the points an image is said to see, the scene's surfaces hide
///   almost none (the ray from the camera to the point meets a surface
///   more than 10 cm before it);
/// * of the points in view that ray casting finds unhidden (nothing within
///   2 cm before them) and no more than 70° off their normal, almost all
///   are seen; those lost lie at occluding edges, where the splats of the
///   surface in front reach past its edge.
#[test]
fn the_points_an_image_sees_are_those_ray_casting_finds() {
    for kind in [SceneKind::Room, SceneKind::Yard] {
        let scene = build_scene(kind, 0);
        // The scan's 15 mm noise.
        let (cloud, spacing_m) = super::scan_without_holes(&scene, 0.015);
        let grid = FrustumGrid::build(&cloud, &GridOptions::default()).unwrap();
        let mut options = MapColourOptions::default();
        options.widen_splats_for_spacing(spacing_m);
        let camera = SynthOptions::default().camera();
        let blank = RgbImage::new(camera.width, camera.height);
        let max_radius = camera.max_normalized_radius();
        let poses = trajectory(kind, 24, 0);
        let (mut said_seen, mut hidden, mut visible, mut missed) = (0usize, 0usize, 0usize, 0usize);
        for pose in poses.iter().step_by(6) {
            let cam_from_world = pose.to_cam_from_world();
            let centre = cam_from_world.camera_center();
            let (seen, _) =
                seen_points(&cloud, &grid, &camera, &cam_from_world, &blank, &options).unwrap();
            // The nearest surface along the ray to point `i`, and the range.
            let cast = |i: usize| {
                let p = cloud.point_in_map(i);
                let range = (p - centre).norm();
                let dir = (p - centre) / range;
                let t = scene
                    .cast(&centre, &dir, 1e-3, range + 1.0)
                    .map_or(f64::INFINITY, |h| h.t);
                (t, range, dir)
            };
            for s in &seen {
                let (t, range, _) = cast(s.point_idx as usize);
                said_seen += 1;
                if t < range - 0.1 {
                    hidden += 1;
                }
            }
            let seen: BTreeSet<u32> = seen.iter().map(|s| s.point_idx).collect();
            // Every 5th map point, for time.
            for i in (0..cloud.len()).step_by(5) {
                let p_cam = cam_from_world.transform_point(&cloud.point_in_map(i));
                if !(0.6..39.0).contains(&p_cam.z) {
                    continue;
                }
                // (Beyond the lens's largest radius the distortion folds
                // points back into the image.)
                let radius = (p_cam.x / p_cam.z).hypot(p_cam.y / p_cam.z);
                if max_radius.is_some_and(|r| radius > r) {
                    continue;
                }
                let Some(px) = camera.project(&p_cam) else {
                    continue;
                };
                let inside = |v: f64, n: u32| v > 1.0 && v < f64::from(n) - 1.0;
                if !(inside(px.x, camera.width) && inside(px.y, camera.height)) {
                    continue;
                }
                let (t, range, dir) = cast(i);
                let n = cloud.normals.as_ref().unwrap()[i];
                let cos = Vector3::new(f64::from(n[0]), f64::from(n[1]), f64::from(n[2]))
                    .dot(&dir)
                    .abs();
                if t > range - 0.02 && cos > 70f64.to_radians().cos() {
                    visible += 1;
                    if !seen.contains(&(i as u32)) {
                        missed += 1;
                    }
                }
            }
        }
        let hidden_share = hidden as f64 / said_seen as f64;
        let missed_share = missed as f64 / visible as f64;
        println!(
            "{}: {said_seen} seen, {:.3} % hidden; {visible} visible, {:.2} % missed",
            kind.name(),
            100.0 * hidden_share,
            100.0 * missed_share
        );
        assert!(said_seen > 50_000 && visible > 5_000, "{}", kind.name());
        // Measured: room 0.33 % hidden, 5.5 % missed; yard 0.87 %, 1.6 %
        // (with the mapper's splats, 0.6 x the spacing: the yard 1.4 %
        // hidden, through gaps in the facades' splats).
        assert!(hidden_share < 0.012, "{}", kind.name());
        assert!(missed_share < 0.08, "{}", kind.name());
    }
}
