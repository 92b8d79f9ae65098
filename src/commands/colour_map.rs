//! `colmap-lidar colour-map`: the LiDAR map coloured by the photos of a
//! model, as a PLY (the map's points with `red green blue` and `views`, the
//! number of images that gave the colour). See [`crate::map::colour`] for
//! how a point's colour is chosen and when a surface in front hides it.
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context};

use crate::io::atomic::output_replaces_input;
use crate::io::images::{check_image_folder, read_rgb, ExpectedImage};
use crate::io::model::read_model;
use crate::map::colour::{seen_points, MapColourOptions, MapColours};
use crate::map::grid::{FrustumGrid, GridOptions};
use crate::map::index::MapIndex;
use crate::map::io::ply::{write_ply_with_colours, PlyColours};
use crate::map::projection::ProjectionOptions;
use crate::map::PointCloud;

#[derive(clap::Args, Debug, Clone)]
pub struct ColourMapArgs {
    /// LiDAR map: .ply, .pcd, .las, .laz or .e57 (normals, when it has them, leave
    /// out grazing views).
    #[arg(long, alias = "lidar_path")]
    pub lidar: PathBuf,
    /// COLMAP model folder (text or binary) in the map's frame, e.g. the
    /// output of `map`; its registered images give the colours.
    #[arg(long, alias = "input_path")]
    pub model: PathBuf,
    /// Folder of the images (names as in the model; subfolders allowed).
    #[arg(long = "image-path", alias = "image_path")]
    pub image_path: PathBuf,
    /// Output PLY (binary; coordinates as double when the map's are large).
    #[arg(long, alias = "output_path")]
    pub output: PathBuf,
    /// Also write the points no image sees (grey, `views` 0); by default
    /// only the coloured points are written.
    #[arg(long = "keep-unseen", alias = "keep_unseen")]
    pub keep_unseen: bool,
    /// Views farther than this from a point's normal give it no colour, degrees.
    #[arg(
        long = "max-view-angle",
        alias = "max_view_angle",
        default_value_t = 75.0
    )]
    pub max_view_angle: f64,
    /// A point is hidden when the surface seen at its pixel lies more than
    /// this in front of it along its normal, metres (plus the splats'
    /// reach); about three times the map's noise.
    #[arg(
        long = "occlusion-margin",
        alias = "occlusion_margin",
        default_value_t = 0.05
    )]
    pub occlusion_margin: f64,
    /// Points closer than this along the optical axis are not coloured,
    /// metres (a fisheye: closer than this to the camera).
    #[arg(long = "min-depth", alias = "min_depth", default_value_t = 0.5)]
    pub min_depth: f64,
    /// Points deeper than this are not coloured, metres.
    #[arg(long = "max-depth", alias = "max_depth", default_value_t = 40.0)]
    pub max_depth: f64,
}

impl ColourMapArgs {
    /// The colouring options (validated).
    pub fn options(&self) -> anyhow::Result<MapColourOptions> {
        let options = MapColourOptions {
            projection: ProjectionOptions {
                min_depth_m: self.min_depth,
                max_depth_m: self.max_depth,
                ..Default::default()
            },
            occlusion_margin_m: self.occlusion_margin,
            max_view_angle_deg: self.max_view_angle,
            ..Default::default()
        };
        options.validate()?;
        Ok(options)
    }
}

/// Grey of the points no image sees (with `--keep-unseen`).
const UNSEEN_GREY: [u8; 3] = [128, 128, 128];

pub fn run(args: &ColourMapArgs) -> anyhow::Result<()> {
    let mut options = args.options()?;
    crate::io::atomic::check_output_location(&args.output, false)?;
    if let Some(why) = output_replaces_input(
        &args.output,
        false,
        &[&args.lidar],
        &[&args.model, &args.image_path],
    ) {
        bail!(why);
    }
    super::check_output_extension(&args.output, "ply", "a binary PLY point cloud")?;
    let start = Instant::now();
    let model = read_model(&args.model)
        .with_context(|| format!("reading the COLMAP model {}", args.model.display()))?;
    let images = super::registered_with_cameras(&model, &args.model)?;
    if images.is_empty() {
        bail!("the model {} has no registered image", args.model.display());
    }
    // Every image is there and of its camera's size before anything is
    // computed (nothing is written when one is not).
    check_image_folder(
        &args.image_path,
        images
            .iter()
            .map(|(image, camera)| ExpectedImage::new(&image.name, camera)),
    )?;
    // Normals that are missing or invalid are estimated as `map` does: the
    // view-angle limit needs them, and the coloured map carries them.
    let cloud = super::map::load_map(&args.lidar)?;
    if let Some(spacing) = MapIndex::spacing_of(&cloud) {
        options.widen_splats_for_spacing(spacing);
        log::info!(
            "map spacing about {spacing:.3} m: splat half-width {:.3} m ({:.3} m near)",
            options.projection.splat.patch_half_width_m,
            options.projection.splat.near_half_width_m
        );
    }
    let grid = FrustumGrid::build(&cloud, &GridOptions::default())
        .with_context(|| format!("indexing the LiDAR map {}", args.lidar.display()))?;
    log::info!(
        "read {} map points and {} registered images ({:.1} s)",
        cloud.len(),
        images.len(),
        start.elapsed().as_secs_f64()
    );
    let bar = super::image_progress_bar(images.len(), "images");
    let mut colours = MapColours::new(cloud.len());
    for (image, camera) in &images {
        let pose = image.cam_from_world.expect("registered");
        let rgb = read_rgb(&args.image_path, &ExpectedImage::new(&image.name, camera))?;
        let (seen, in_view) = seen_points(&cloud, &grid, camera, &pose, &rgb, &options)
            .with_context(|| format!("colouring the map from image `{}`", image.name))?;
        colours.add(&seen);
        log::debug!(
            "{}: {in_view} map points in view, {} seen",
            image.name,
            seen.len()
        );
        if let Some(bar) = &bar {
            bar.inc(1);
        }
    }
    if let Some(bar) = &bar {
        bar.finish_and_clear();
    }
    let seen = colours.num_seen();
    if seen == 0 {
        bail!(
            "no image of {} sees a point of the LiDAR map {}: is the model in the map's frame?",
            args.model.display(),
            args.lidar.display()
        );
    }
    let keep: Vec<usize> = (0..cloud.len())
        .filter(|&i| args.keep_unseen || colours.views(i) > 0)
        .collect();
    let out = subset(&cloud, &keep);
    let rgb: Vec<[u8; 3]> = keep
        .iter()
        .map(|&i| colours.colour(i).unwrap_or(UNSEEN_GREY))
        .collect();
    let views: Vec<u16> = keep.iter().map(|&i| colours.views(i)).collect();
    write_ply_with_colours(
        &args.output,
        &out,
        Some(PlyColours {
            rgb: &rgb,
            views: &views,
        }),
    )?;
    log::info!(
        "coloured {seen} of {} map points ({:.1} %) from {} images; wrote {} points to {} ({:.1} s)",
        cloud.len(),
        100.0 * seen as f64 / cloud.len() as f64,
        images.len(),
        out.len(),
        args.output.display(),
        start.elapsed().as_secs_f64()
    );
    Ok(())
}

/// The points `keep` of `cloud` (in that order), with their normals and
/// planarity.
fn subset(cloud: &PointCloud, keep: &[usize]) -> PointCloud {
    PointCloud {
        origin: cloud.origin,
        points: keep.iter().map(|&i| cloud.points[i]).collect(),
        normals: cloud
            .normals
            .as_ref()
            .map(|n| keep.iter().map(|&i| n[i]).collect()),
        planarity: cloud
            .planarity
            .as_ref()
            .map(|p| keep.iter().map(|&i| p[i]).collect()),
    }
}
