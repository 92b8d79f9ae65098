//! `colmap-lidar depth`: the map seen from one image of a COLMAP model, as a
//! colour-mapped depth PNG with the image's features drawn on top (green: the
//! feature sees a LiDAR point, red: it does not). The paper's depth figure: a
//! quick look at whether a pose and the map agree.
use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use nalgebra::Vector2;

use crate::io::atomic::output_replaces_input;
use crate::io::model::read_model;
use crate::map::depth_image::{colourise, render_depth_image, write_png};
use crate::map::grid::{FrustumGrid, GridOptions};
use crate::map::index::MapIndex;
use crate::map::io::read_point_cloud;
use crate::map::projection::{project_map_at_pixels, widen_splats_for_spacing, ProjectionOptions};
use crate::map::PointCloud;

#[derive(clap::Args, Debug, Clone)]
pub struct DepthArgs {
    /// LiDAR map: .ply, .pcd, .las, .laz or .e57.
    #[arg(long, alias = "lidar_path")]
    pub lidar: PathBuf,
    /// COLMAP model folder (text or binary) holding the image and its pose.
    #[arg(long, alias = "input_path")]
    pub model: PathBuf,
    /// The image in the model: its name (as in images.txt) or its id.
    #[arg(long, alias = "image_name", value_name = "NAME|ID")]
    pub image: String,
    /// Output PNG.
    #[arg(long, alias = "output_path")]
    pub output: PathBuf,
    /// Points closer than this along the optical axis are ignored, metres
    /// (a fisheye: closer than this to the camera).
    #[arg(long = "min-depth", alias = "min_depth", default_value_t = 0.5)]
    pub min_depth: f64,
    /// Points deeper than this are ignored, metres; also the far end of the
    /// colour scale.
    #[arg(long = "max-depth", alias = "max_depth", default_value_t = 40.0)]
    pub max_depth: f64,
}

impl DepthArgs {
    /// The projection options (validated).
    pub fn options(&self) -> anyhow::Result<ProjectionOptions> {
        let options = ProjectionOptions {
            min_depth_m: self.min_depth,
            max_depth_m: self.max_depth,
            ..Default::default()
        };
        options.validate()?;
        Ok(options)
    }
}

/// Widens the splats of `options` for the map's spacing by the mapper's rule
/// ([`widen_splats_for_spacing`], as `MapperOptions::for_map_spacing`).
/// Returns the spacing (`None` when it cannot be estimated: options
/// unchanged).
pub fn widen_splats_for_map(options: &mut ProjectionOptions, cloud: &PointCloud) -> Option<f64> {
    let spacing = MapIndex::spacing_of(cloud)?;
    widen_splats_for_spacing(&mut options.splat, spacing);
    Some(spacing)
}

pub fn run(args: &DepthArgs) -> anyhow::Result<()> {
    let options = args.options()?;
    crate::io::atomic::check_output_location(&args.output, false)?;
    if let Some(why) = output_replaces_input(&args.output, false, &[&args.lidar], &[&args.model]) {
        anyhow::bail!(why);
    }
    super::check_output_extension(&args.output, "png", "a PNG image")?;
    let start = Instant::now();
    let model = read_model(&args.model)
        .with_context(|| format!("reading the COLMAP model {}", args.model.display()))?;
    let image = model
        .image_by_name(&args.image)
        .or_else(|| {
            let id = args.image.trim().parse::<u32>().ok()?;
            model.images.get(&crate::scene::ImageId(id))
        })
        .with_context(|| {
            format!(
                "no image of name or id `{}` in the model {} ({} images)",
                args.image,
                args.model.display(),
                model.images.len()
            )
        })?;
    let cam_from_world = image.cam_from_world.with_context(|| {
        format!(
            "image `{}` is not registered in {} (no pose)",
            args.image,
            args.model.display()
        )
    })?;
    let camera = model.cameras.get(&image.camera_id).with_context(|| {
        format!(
            "image `{}` refers to camera {}, missing from {}",
            args.image,
            image.camera_id,
            args.model.display()
        )
    })?;
    let (cloud, _report) = read_point_cloud(&args.lidar)
        .with_context(|| format!("reading the LiDAR map {}", args.lidar.display()))?;
    log::info!(
        "read {} map points and the model ({:.1} s)",
        cloud.len(),
        start.elapsed().as_secs_f64()
    );
    let mut options = options;
    if let Some(spacing) = widen_splats_for_map(&mut options, &cloud) {
        log::info!(
            "map spacing about {spacing:.3} m: splat half-width {:.3} m ({:.3} m near)",
            options.splat.patch_half_width_m,
            options.splat.near_half_width_m
        );
    }
    let t = Instant::now();
    let grid = FrustumGrid::build(&cloud, &GridOptions::default())
        .with_context(|| format!("indexing the LiDAR map {}", args.lidar.display()))?;
    log::info!(
        "grid: {} cells ({:.1} s)",
        grid.num_cells(),
        t.elapsed().as_secs_f64()
    );
    let t = Instant::now();
    let query_pixels: Vec<Vector2<f64>> = image.points2d.iter().map(|p| p.xy).collect();
    let hits = project_map_at_pixels(
        &cloud,
        &grid,
        camera,
        &cam_from_world,
        &query_pixels,
        &options,
    )?;
    let hit: Vec<bool> = hits.iter().map(|h| h.is_some()).collect();
    let depth = render_depth_image(&cloud, &grid, camera, &cam_from_world, &options)?;
    log::info!(
        "{} of {} features see a LiDAR point; {:.1}% of the pixels see the map ({:.2} s)",
        hit.iter().filter(|&&h| h).count(),
        hit.len(),
        100.0 * depth.num_filled() as f64 / (depth.range_m.len().max(1)) as f64,
        t.elapsed().as_secs_f64()
    );
    let img = colourise(&depth, options.max_depth_m, &query_pixels, &hit);
    write_png(&img, &args.output)?;
    log::info!("wrote {}", args.output.display());
    Ok(())
}
