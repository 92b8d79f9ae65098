//! Writes a complete synthetic scene folder:
//!
//! ```text
//! DIR/images/frame_0000.jpg ...   rendered photos, trajectory order
//! DIR/lidar.ply                   map with normals (x y z double, nx ny nz float)
//! DIR/lidar_raw.ply               the same points without normals
//! DIR/gt/{cameras,images,points3D}.txt   COLMAP text model of the true cameras
//! DIR/init_pose.txt               first image's pose, exact and perturbed
//! DIR/scene.json                  what was generated (options, counts)
//! ```
//!
//! Every world coordinate (map points, poses) is shifted by `offset_m`.
//!
//! `init_pose.txt` holds comment lines (`#`) and two data lines,
//! `exact: x,y,z,roll_deg,pitch_deg,yaw_deg` and `perturbed: ...` (0.3 m and
//! 3 deg off, seeded), in the map convention of method.md section 2, ready for
//! `--init-pose` (see [`crate::scene::BodyPose`]).
use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use nalgebra::{Rotation3, Unit, Vector2, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use serde::Serialize;

use super::lidar::{sample_lidar, write_ply, LidarOptions, LidarPlatform};
use super::render::{render, RayTable, RenderSettings};
use super::scenes::{build_changed_scene, build_scene, trajectory, SceneKind};
use super::{lens, SynthError};
use crate::io::atomic::{write_dir_atomically, write_file_atomically};
use crate::scene::BodyPose;
use crate::scene::{Camera, CameraId, CameraModel, Rigid3};

/// Most objects `changes` may move (the scenes have fewer to remove or add;
/// `scene.json` says how many were).
pub const MAX_CHANGES: usize = 32;

/// Everything that defines a generated scene.
#[derive(Clone, Debug)]
pub struct SynthOptions {
    pub scene: SceneKind,
    /// Number of images. Default 24.
    pub num_images: usize,
    /// Image size in pixels. Default 640 x 480.
    pub width: u32,
    pub height: u32,
    /// Camera model of the true camera (SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL,
    /// RADIAL, OPENCV, SIMPLE_RADIAL_FISHEYE or OPENCV_FISHEYE). Default
    /// SIMPLE_RADIAL with k = -0.04.
    pub camera_model: CameraModel,
    /// Focal length as a fraction of the width. Default 0.8 (about 65 deg
    /// horizontal); [`FISHEYE_FOCAL_FACTOR`] suits the fisheye models.
    pub focal_factor: f64,
    /// Seed of textures, trajectory jitter, noise and LiDAR sampling. Default 0.
    pub seed: u64,
    /// Added to every world coordinate, metres. Default zero.
    pub offset_m: Vector3<f64>,
    /// Anti-aliasing rays per pixel along each axis. Default 2.
    pub supersample: u32,
    /// JPEG quality (1-100). Default 92.
    pub jpeg_quality: u8,
    /// Sensor noise sigma on 8-bit values. Default 2.0.
    pub noise_sigma_u8: f32,
    /// Relative amplitude of the per-image exposure variation. Default 0.15.
    pub exposure_variation: f32,
    pub lidar: LidarOptions,
    /// The scene changed since the scan: this many of its movable objects are
    /// in the map but not in the images, and up to this many new boxes are in
    /// the images but not in the map ([`build_changed_scene`]). Default 0.
    pub changes: usize,
}

impl Default for SynthOptions {
    fn default() -> Self {
        Self {
            scene: SceneKind::Yard,
            num_images: 24,
            width: 640,
            height: 480,
            camera_model: CameraModel::SimpleRadial,
            focal_factor: 0.8,
            seed: 0,
            offset_m: Vector3::zeros(),
            supersample: 2,
            jpeg_quality: 92,
            noise_sigma_u8: 2.0,
            exposure_variation: 0.15,
            lidar: LidarOptions::default(),
            changes: 0,
        }
    }
}

/// Focal length over width of a fisheye camera: 0.45 gives about 125 deg
/// horizontally and 156 deg across the diagonal (equidistant).
pub const FISHEYE_FOCAL_FACTOR: f64 = 0.45;

/// Largest angle from the optical axis a rendered pixel may see: rays are
/// cast as (x, y, 1), so a fisheye must stay well inside 90 degrees.
const MAX_HALF_FOV_DEG: f64 = 85.0;

/// Most images `synth` renders (a 400-image corridor is the largest scene
/// the benchmarks use).
pub const MAX_IMAGES: usize = 10_000;

impl SynthOptions {
    pub fn validate(&self) -> Result<(), SynthError> {
        let bad = |m: String| Err(SynthError::InvalidOption(m));
        if !lens::SUPPORTED_MODELS.contains(&self.camera_model) {
            return bad(format!(
                "camera model {} is not supported by the renderer (use one of {})",
                self.camera_model.name(),
                lens::SUPPORTED_MODELS.map(|m| m.name()).join(", ")
            ));
        }
        if self.changes > MAX_CHANGES {
            return bad(format!(
                "--changes must be at most {MAX_CHANGES}, got {}",
                self.changes
            ));
        }
        if !(2..=MAX_IMAGES).contains(&self.num_images) {
            return bad(format!(
                "--images must be 2..={MAX_IMAGES}, got {}",
                self.num_images
            ));
        }
        if !(16..=8192).contains(&self.width) || !(16..=8192).contains(&self.height) {
            return bad(format!(
                "image size {}x{} out of range 16..8192",
                self.width, self.height
            ));
        }
        if !(1..=8).contains(&self.supersample) {
            return bad(format!(
                "--supersample must be 1..8, got {}",
                self.supersample
            ));
        }
        if !(1..=100).contains(&self.jpeg_quality) {
            return bad(format!(
                "--jpeg-quality must be 1..100, got {}",
                self.jpeg_quality
            ));
        }
        if !(self.focal_factor > 0.1 && self.focal_factor < 10.0) {
            return bad(format!("focal factor {} out of range", self.focal_factor));
        }
        let camera = self.camera();
        let (w, h) = (f64::from(self.width), f64::from(self.height));
        for corner in [[0.0, 0.0], [w, 0.0], [0.0, h], [w, h]] {
            let angle_deg = camera
                .unproject(&Vector2::new(corner[0], corner[1]))
                .map_or(f64::INFINITY, |ray| ray.xy().norm().atan().to_degrees());
            if !(angle_deg < MAX_HALF_FOV_DEG) {
                return bad(format!(
                    "focal factor {} gives a {} camera a view {} deg or more from its axis \
                     at the image corners (at most {MAX_HALF_FOV_DEG}); use a longer focal length",
                    self.focal_factor,
                    self.camera_model.name(),
                    if angle_deg.is_finite() {
                        angle_deg.round()
                    } else {
                        90.0
                    }
                ));
            }
        }
        if !self.offset_m.iter().all(|c| c.is_finite()) {
            return bad("--offset must be finite".into());
        }
        if !((0.0..=255.0).contains(&self.noise_sigma_u8)
            && (0.0..=1.0).contains(&self.lidar.noise_sigma_m))
        {
            return bad(format!(
                "noise levels must be in 0..=255 (images) and 0..=1 m (LiDAR), got {} and {}",
                self.noise_sigma_u8, self.lidar.noise_sigma_m
            ));
        }
        if let Some(spacing) = self.lidar.spacing_m {
            if !(0.001..=10.0).contains(&spacing) {
                return bad(format!(
                    "--lidar-spacing must be in 0.001..=10 m, got {spacing}"
                ));
            }
        }
        if !(0.0..=0.5).contains(&self.lidar.outlier_fraction) {
            return bad(format!(
                "LiDAR outlier fraction {} must lie in 0..=0.5",
                self.lidar.outlier_fraction
            ));
        }
        Ok(())
    }

    /// The true camera (id 1).
    pub fn camera(&self) -> Camera {
        let f = self.focal_factor * f64::from(self.width);
        let (cx, cy) = (f64::from(self.width) / 2.0, f64::from(self.height) / 2.0);
        let params = match self.camera_model {
            CameraModel::SimplePinhole => vec![f, cx, cy],
            CameraModel::Pinhole => vec![f, f * 1.003, cx, cy],
            CameraModel::SimpleRadial => vec![f, cx, cy, -0.04],
            CameraModel::Radial => vec![f, cx, cy, -0.04, 0.01],
            CameraModel::SimpleRadialFisheye => vec![f, cx, cy, 0.02],
            CameraModel::OpenCvFisheye => {
                vec![f, f * 1.003, cx + 1.5, cy - 1.0, 0.03, -0.01, 0.002, -0.001]
            }
            _ => vec![
                f,
                f * 1.003,
                cx + 1.5,
                cy - 1.0,
                -0.04,
                0.01,
                0.0005,
                -0.0003,
            ],
        };
        Camera {
            id: CameraId(1),
            model: self.camera_model,
            width: self.width,
            height: self.height,
            params,
        }
    }
}

/// What [`generate_scene`] wrote.
#[derive(Clone, Debug, Serialize)]
pub struct SceneSummary {
    pub scene: SceneKind,
    pub seed: u64,
    pub num_images: usize,
    pub width: u32,
    pub height: u32,
    pub camera_model: String,
    pub camera_params: Vec<f64>,
    pub offset_m: [f64; 3],
    pub num_lidar_points: usize,
    pub lidar_spacing_m: f64,
    pub lidar_platform: LidarPlatform,
    pub init_pose_exact: [f64; 6],
    pub init_pose_perturbed: [f64; 6],
    /// Objects of the scan not in the images, and new ones in the images only.
    pub objects_removed: usize,
    pub objects_added: usize,
    pub render_seconds: f64,
}

/// Name of image `i` (trajectory order).
pub fn image_name(i: usize) -> String {
    format!("frame_{i:04}.jpg")
}

/// A body pose moved by `offset_m`.
fn shifted(pose: &BodyPose, offset_m: &Vector3<f64>) -> BodyPose {
    BodyPose {
        position_m: pose.position_m + offset_m,
        ..*pose
    }
}

/// The perturbed initial pose: 0.3 m in a random direction, 3 deg about a random axis.
fn perturb(pose: &BodyPose, seed: u64) -> BodyPose {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x1417_0005);
    let mut random_unit = || -> Vector3<f64> {
        let v: Vector3<f64> = Vector3::from_fn(|_, _| rng.sample(StandardNormal));
        v.normalize()
    };
    let dp = random_unit() * 0.3;
    let axis = Unit::new_normalize(random_unit());
    let r = Rotation3::from_axis_angle(&axis, 3f64.to_radians())
        * Rotation3::from_matrix_unchecked(pose.world_from_body_rotation());
    let (roll, pitch, yaw) = r.euler_angles();
    BodyPose {
        position_m: pose.position_m + dp,
        roll_rad: roll,
        pitch_rad: pitch,
        yaw_rad: yaw,
    }
}

fn fmt_pose(p: &[f64; 6]) -> String {
    p.iter()
        .map(|v| format!("{v:.9}"))
        .collect::<Vec<_>>()
        .join(",")
}

/// Writes the COLMAP text model of the true cameras (no 3D points).
fn write_gt(
    dir: &Path,
    camera: &Camera,
    names: &[String],
    poses: &[Rigid3],
) -> std::io::Result<()> {
    fs::create_dir_all(dir)?;
    write_file_atomically(&dir.join("cameras.txt"), |w| {
        writeln!(w, "# Camera list with one line of data per camera:")?;
        writeln!(w, "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]")?;
        writeln!(w, "# Number of cameras: 1")?;
        let params: Vec<String> = camera.params.iter().map(|p| format!("{p}")).collect();
        writeln!(
            w,
            "{} {} {} {} {}",
            camera.id,
            camera.model.name(),
            camera.width,
            camera.height,
            params.join(" ")
        )
    })?;
    write_file_atomically(&dir.join("images.txt"), |w| -> std::io::Result<()> {
        writeln!(w, "# Image list with two lines of data per image:")?;
        writeln!(
            w,
            "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME"
        )?;
        writeln!(w, "#   POINTS2D[] as (X, Y, POINT3D_ID)")?;
        writeln!(
            w,
            "# Number of images: {}, mean observations per image: 0",
            names.len()
        )?;
        for (i, (name, pose)) in names.iter().zip(poses).enumerate() {
            let q = pose.quaternion_wxyz();
            let t = pose.translation;
            writeln!(
                w,
                "{} {} {} {} {} {} {} {} {} {}",
                i + 1,
                q[0],
                q[1],
                q[2],
                q[3],
                t.x,
                t.y,
                t.z,
                camera.id,
                name
            )?;
            writeln!(w)?;
        }
        Ok(())
    })?;
    write_file_atomically(&dir.join("points3D.txt"), |w| {
        writeln!(w, "# 3D point list with one line of data per point:")?;
        writeln!(
            w,
            "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)"
        )?;
        writeln!(w, "# Number of points: 0, mean track length: 0")
    })
}

/// Renders and writes a scene into `output` (replaced atomically).
pub fn generate_scene(opts: &SynthOptions, output: &Path) -> Result<SceneSummary, SynthError> {
    opts.validate()?;
    // The map is scanned from `scene`, the images are taken of `photographed`.
    let scene = build_scene(opts.scene, opts.seed);
    let (photographed, objects_removed, objects_added) =
        build_changed_scene(opts.scene, opts.seed, opts.changes);
    let poses_local = trajectory(opts.scene, opts.num_images, opts.seed);
    let camera = opts.camera();
    let names: Vec<String> = (0..poses_local.len()).map(image_name).collect();
    let mut summary = None;
    write_dir_atomically(output, |dir: &Path| -> Result<(), SynthError> {
        let images_dir = dir.join("images");
        fs::create_dir_all(&images_dir).map_err(|e| SynthError::io(&images_dir, e))?;
        let t0 = Instant::now();
        let table = RayTable::new(&camera, opts.supersample);
        for (i, pose) in poses_local.iter().enumerate() {
            let phase = (opts.seed % 1000) as f32 * 0.37;
            let gain = 1.0
                + opts.exposure_variation
                    * (0.7 * (i as f32 * 0.45 + phase).sin() + 0.3 * (i as f32 * 1.7).cos());
            let settings = RenderSettings {
                supersample: opts.supersample,
                exposure_gain: gain,
                noise_sigma_u8: opts.noise_sigma_u8,
                noise_seed: super::texture::hash64(opts.seed ^ (i as u64 + 1)),
            };
            let rgb = render(&photographed, &table, &pose.to_cam_from_world(), &settings);
            let path = images_dir.join(&names[i]);
            write_jpeg(&path, &rgb, opts.width, opts.height, opts.jpeg_quality)?;
            log::debug!("rendered {}", path.display());
        }
        let render_seconds = t0.elapsed().as_secs_f64();
        log::info!(
            "rendered {} images in {:.1} s",
            poses_local.len(),
            render_seconds
        );

        let mut lidar_opts = opts.lidar.clone();
        lidar_opts.seed ^= opts.seed;
        let map = sample_lidar(&scene, &lidar_opts);
        for (name, normals) in [("lidar.ply", true), ("lidar_raw.ply", false)] {
            let path = dir.join(name);
            write_file_atomically(&path, |w| write_ply(w, &map, &opts.offset_m, normals))
                .map_err(|e| SynthError::io(&path, e))?;
        }
        log::info!(
            "LiDAR map: {} points at {:.3} m spacing",
            map.points.len(),
            map.spacing_m
        );

        let poses_world: Vec<BodyPose> = poses_local
            .iter()
            .map(|p| shifted(p, &opts.offset_m))
            .collect();
        let cams: Vec<Rigid3> = poses_world
            .iter()
            .map(BodyPose::to_cam_from_world)
            .collect();
        let gt = dir.join("gt");
        write_gt(&gt, &camera, &names, &cams).map_err(|e| SynthError::io(&gt, e))?;

        let exact = poses_world[0].to_degrees_array();
        let perturbed = perturb(&poses_world[0], opts.seed).to_degrees_array();
        let path = dir.join("init_pose.txt");
        write_file_atomically(&path, |w| {
            writeln!(w, "# Pose of the first image ({}) in the map frame (method.md section 2):", names[0])?;
            writeln!(w, "# x,y,z (camera centre, m), roll,pitch,yaw (deg); R_world_from_body = Rz(yaw) Ry(pitch) Rx(roll),")?;
            writeln!(w, "# body x forward (optical axis), y left, z up. Pass as --init-pose x,y,z,roll,pitch,yaw.")?;
            writeln!(w, "# 'perturbed' is 0.3 m and 3 deg away from 'exact'.")?;
            writeln!(w, "exact: {}", fmt_pose(&exact))?;
            writeln!(w, "perturbed: {}", fmt_pose(&perturbed))
        })
        .map_err(|e| SynthError::io(&path, e))?;

        let s = SceneSummary {
            scene: opts.scene,
            seed: opts.seed,
            num_images: names.len(),
            width: opts.width,
            height: opts.height,
            camera_model: camera.model.name().to_string(),
            camera_params: camera.params.clone(),
            offset_m: [opts.offset_m.x, opts.offset_m.y, opts.offset_m.z],
            num_lidar_points: map.points.len(),
            lidar_spacing_m: map.spacing_m,
            lidar_platform: opts.lidar.platform,
            init_pose_exact: exact,
            init_pose_perturbed: perturbed,
            objects_removed,
            objects_added,
            render_seconds,
        };
        let path = dir.join("scene.json");
        write_file_atomically(&path, |w| -> std::io::Result<()> {
            serde_json::to_writer_pretty(&mut *w, &s)?;
            writeln!(w)
        })
        .map_err(|e| SynthError::io(&path, e))?;
        summary = Some(s);
        Ok(())
    })?;
    // Set inside the closure, which returned Ok.
    Ok(summary.expect("summary is written on success"))
}

fn write_jpeg(
    path: &Path,
    rgb: &[u8],
    width: u32,
    height: u32,
    quality: u8,
) -> Result<(), SynthError> {
    let file = fs::File::create(path).map_err(|e| SynthError::io(path, e))?;
    let mut w = std::io::BufWriter::new(file);
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut w, quality)
        .encode(rgb, width, height, image::ExtendedColorType::Rgb8)
        .map_err(|e| SynthError::Image {
            path: path.to_path_buf(),
            message: e.to_string(),
        })?;
    w.flush().map_err(|e| SynthError::io(path, e))
}

/// Reads `init_pose.txt`: returns (exact, perturbed) as
/// `[x, y, z, roll_deg, pitch_deg, yaw_deg]`.
pub fn read_init_pose(path: &Path) -> Result<([f64; 6], [f64; 6]), SynthError> {
    let text = fs::read_to_string(path).map_err(|e| SynthError::io(path, e))?;
    let parse = |key: &str| -> Result<[f64; 6], SynthError> {
        let bad = |m: &str| SynthError::Parse {
            path: PathBuf::from(path),
            message: format!("{key}: {m}"),
        };
        let line = text
            .lines()
            .find_map(|l| l.strip_prefix(key))
            .ok_or_else(|| bad("line missing"))?;
        let vals: Vec<f64> = line
            .trim()
            .split(',')
            .map(|s| s.trim().parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|_| bad("not six numbers"))?;
        vals.try_into().map_err(|_| bad("not six numbers"))
    };
    Ok((parse("exact:")?, parse("perturbed:")?))
}
