//! `colmap-lidar synth`: render a synthetic scene with exact ground truth.
use std::path::PathBuf;

use anyhow::Context;
use nalgebra::Vector3;

use crate::scene::CameraModel;
use crate::synth::generate::FISHEYE_FOCAL_FACTOR;
use crate::synth::lidar::LidarPlatform;
use crate::synth::{generate_scene, SceneKind, SynthOptions};

/// Render a synthetic scene (images, LiDAR map, true cameras, initial pose).
#[derive(Debug, clap::Args)]
pub struct SynthArgs {
    /// Which scene to build.
    #[arg(long, value_enum)]
    pub scene: SceneKind,
    /// Output folder: replaced atomically as a whole, so an existing one must
    /// hold only a scene (what `synth` and `scripts/make_database.sh` write).
    #[arg(long, short = 'o', alias = "output_path")]
    pub output: PathBuf,
    /// Number of images along the trajectory.
    #[arg(long, default_value_t = 24)]
    pub images: usize,
    /// Seed of textures, trajectory jitter, noise and LiDAR sampling.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Image width in pixels.
    #[arg(long, default_value_t = 640)]
    pub width: u32,
    /// Image height in pixels.
    #[arg(long, default_value_t = 480)]
    pub height: u32,
    /// World offset added to every coordinate, "X,Y,Z" in metres (e.g. 500000,4400000,200).
    #[arg(long, value_parser = super::parse_xyz, allow_hyphen_values = true)]
    pub offset: Option<[f64; 3]>,
    /// COLMAP camera model of the true camera: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL,
    /// OPENCV, SIMPLE_RADIAL_FISHEYE, OPENCV_FISHEYE.
    #[arg(long, default_value = "SIMPLE_RADIAL")]
    pub camera_model: String,
    /// Focal length as a fraction of the image width (default 0.8, about 65 deg
    /// horizontally; fisheye models 0.45, about 125 deg).
    #[arg(long)]
    pub focal_factor: Option<f64>,
    /// Anti-aliasing rays per pixel along each axis.
    #[arg(long, default_value_t = 2)]
    pub supersample: u32,
    /// JPEG quality.
    #[arg(long, default_value_t = 92)]
    pub jpeg_quality: u8,
    /// LiDAR sample spacing in metres (default: the smallest >= 2 cm within --lidar-max-points).
    #[arg(long)]
    pub lidar_spacing: Option<f64>,
    /// Upper bound on the number of LiDAR surface samples.
    #[arg(long, default_value_t = 1_500_000)]
    pub lidar_max_points: usize,
    /// Standard deviation of the LiDAR range noise along the surface normal, metres.
    #[arg(long, default_value_t = 0.015)]
    pub lidar_noise: f64,
    /// Fraction of LiDAR outliers (random points with random normals in the scene's box).
    #[arg(long, default_value_t = 0.001)]
    pub lidar_outliers: f64,
    /// Where the LiDAR scan was taken from: terrestrial (every surface alike) or
    /// airborne (flat ground and roofs dense, walls at 0.15 of that, nothing
    /// facing down; with --lidar-spacing 0.1-0.3 and --lidar-noise 0.03 as a
    /// drone or aircraft survey gives).
    #[arg(long, value_enum, default_value_t = LidarPlatform::Terrestrial)]
    pub lidar_platform: LidarPlatform,
    /// The scene changed since the scan: N of its objects are in the map but
    /// not in the images, and up to N new boxes in the images but not in the map.
    #[arg(long, default_value_t = 0)]
    pub changes: usize,
}

impl SynthArgs {
    /// The validated options.
    pub fn to_options(&self) -> anyhow::Result<SynthOptions> {
        let camera_model = CameraModel::from_name(&self.camera_model.to_uppercase())
            .with_context(|| format!("unknown camera model {:?}", self.camera_model))?;
        let mut opts = SynthOptions {
            scene: self.scene,
            num_images: self.images,
            width: self.width,
            height: self.height,
            camera_model,
            seed: self.seed,
            offset_m: self
                .offset
                .map(Vector3::from)
                .unwrap_or_else(Vector3::zeros),
            supersample: self.supersample,
            jpeg_quality: self.jpeg_quality,
            changes: self.changes,
            ..SynthOptions::default()
        };
        opts.focal_factor = self.focal_factor.unwrap_or(if camera_model.is_fisheye() {
            FISHEYE_FOCAL_FACTOR
        } else {
            opts.focal_factor
        });
        opts.lidar.spacing_m = self.lidar_spacing;
        opts.lidar.max_points = self.lidar_max_points;
        opts.lidar.noise_sigma_m = self.lidar_noise;
        opts.lidar.outlier_fraction = self.lidar_outliers;
        opts.lidar.platform = self.lidar_platform;
        opts.validate()?;
        Ok(opts)
    }
}

/// What `synth` writes into its output folder, and the database
/// `scripts/make_database.sh` adds there: a folder holding anything else is
/// not a scene and is not replaced.
const SCENE_ENTRIES: [&str; 9] = [
    "scene.json",
    "images",
    "gt",
    "lidar.ply",
    "lidar_raw.ply",
    "init_pose.txt",
    "database.db",
    "database.db-shm",
    "database.db-wal",
];

/// Refuses an output that exists and is not a folder holding only a scene
/// ([`SCENE_ENTRIES`]): the output is replaced as a whole.
fn check_scene_output(dir: &std::path::Path) -> anyhow::Result<()> {
    super::check_replaceable_output(dir, &SCENE_ENTRIES, "part of a synthetic scene")
}

pub fn run(args: &SynthArgs) -> anyhow::Result<()> {
    let opts = args.to_options()?;
    check_scene_output(&args.output)?;
    let summary = generate_scene(&opts, &args.output)
        .with_context(|| format!("cannot write scene to {}", args.output.display()))?;
    println!(
        "{}: {} images {}x{} ({:.1} s), {} LiDAR points at {:.3} m, written to {}",
        summary.scene.name(),
        summary.num_images,
        summary.width,
        summary.height,
        summary.render_seconds,
        summary.num_lidar_points,
        summary.lidar_spacing_m,
        args.output.display()
    );
    if opts.changes > 0 {
        println!(
            "changed since the scan: {} objects in the map only, {} new ones in the images only",
            summary.objects_removed, summary.objects_added
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        args: SynthArgs,
    }

    fn options(extra: &[&str]) -> anyhow::Result<SynthOptions> {
        let mut argv = vec!["synth", "--scene", "room", "--output", "out"];
        argv.extend_from_slice(extra);
        Cli::try_parse_from(argv)?.args.to_options()
    }

    #[test]
    fn lidar_noise_and_outliers_reach_the_options_and_are_checked() {
        let defaults = options(&[]).unwrap();
        assert_eq!(defaults.lidar.noise_sigma_m, 0.015);
        assert_eq!(defaults.lidar.outlier_fraction, 0.001);
        let clean = options(&["--lidar-noise", "0", "--lidar-outliers", "0"]).unwrap();
        assert_eq!(clean.lidar.noise_sigma_m, 0.0);
        assert_eq!(clean.lidar.outlier_fraction, 0.0);
        assert!(options(&["--lidar-noise=-0.01"]).is_err());
        assert!(options(&["--lidar-outliers", "0.7"]).is_err());
        assert!(options(&["--lidar-outliers", "NaN"]).is_err());
        // Session 64's review: these panicked, aborted or wrote a NaN map.
        for bad in [
            &["--lidar-noise", "inf"][..],
            &["--lidar-spacing", "0"],
            &["--lidar-spacing", "-1"],
            &["--lidar-spacing", "NaN"],
            &["--lidar-spacing", "inf"],
            &["--images", "1000000000000000000"],
        ] {
            assert!(options(bad).is_err(), "{bad:?}");
        }
        assert!(options(&["--lidar-spacing", "0.05", "--images", "400"]).is_ok());
    }

    #[test]
    fn only_a_scene_folder_is_replaced() {
        let root = tempfile::tempdir().unwrap();
        let scene = root.path().join("scene");
        std::fs::create_dir_all(scene.join("images")).unwrap();
        std::fs::write(scene.join("database.db"), "").unwrap();
        std::fs::write(scene.join("scene.json"), "{}").unwrap();
        check_scene_output(&scene).unwrap();
        check_scene_output(&root.path().join("new")).unwrap();
        std::fs::write(scene.join("notes.txt"), "mine").unwrap();
        let err = check_scene_output(&scene).unwrap_err().to_string();
        assert!(
            err.contains("`notes.txt`") && err.contains("refusing"),
            "{err}"
        );
        let err = check_scene_output(&scene.join("notes.txt"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("is not a folder"), "{err}");
    }
}
