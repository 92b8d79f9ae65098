//! `colmap-lidar prepare-map`: reads a raw point cloud (PLY, PCD, LAS/LAZ, E57),
//! downsamples it, estimates normals where they are missing or invalid, and
//! writes a binary PLY with normals (and planarity) that the mapper and
//! CloudCompare both read.
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use nalgebra::Vector3;

use crate::map::io::{read_point_cloud, write_ply, LoadReport};
use crate::map::prepare::{prepare, CropBox, NormalOrientation, PrepareOptions, PrepareReport};

#[derive(clap::Args, Debug, Clone)]
pub struct PrepareMapArgs {
    /// Raw point cloud: .ply, .pcd, .las, .laz or .e57 (every scan, each at its pose).
    #[arg(long, alias = "input_path")]
    pub input: PathBuf,
    /// Output binary PLY with normals.
    #[arg(long, alias = "output_path")]
    pub output: PathBuf,
    /// Voxel size for downsampling, metres (0 = keep every point).
    #[arg(long, default_value_t = 0.03)]
    pub voxel: f64,
    /// Neighbourhood radius for normal estimation, metres [default: 0.15,
    /// or 3 times the (downsampled) cloud's spacing when that is larger].
    #[arg(long = "normal-radius", alias = "normal_radius")]
    pub normal_radius: Option<f64>,
    /// Use the k nearest neighbours (within the radius) instead of all.
    #[arg(long = "normal-k", alias = "normal_k")]
    pub normal_k: Option<usize>,
    /// Re-estimate all normals, also valid ones read from the input.
    #[arg(long = "recompute-normals")]
    pub recompute_normals: bool,
    /// Orient normals towards this sensor position `x,y,z` (map frame,
    /// metres) instead of the default (up, then towards the map's centre).
    #[arg(long)]
    pub sensor: Option<String>,
    /// Keep only the points inside this box, `xmin,ymin,zmin,xmax,ymax,zmax`
    /// (map frame, metres, in the input's own coordinates), before
    /// downsampling: the part of a large survey the photos show.
    #[arg(long, allow_hyphen_values = true)]
    pub crop: Option<String>,
    /// Keep points whose normal could not be estimated (written with a zero
    /// normal).
    #[arg(long = "keep-without-normal")]
    pub keep_without_normal: bool,
}

/// Parses `x,y,z` (metres).
pub fn parse_position(text: &str) -> anyhow::Result<Vector3<f64>> {
    let values: Vec<f64> = text
        .split(',')
        .map(|s| s.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .with_context(|| format!("`{text}` is not `x,y,z`"))?;
    match values.as_slice() {
        [x, y, z] if values.iter().all(|v| v.is_finite()) => Ok(Vector3::new(*x, *y, *z)),
        _ => anyhow::bail!("`{text}` is not `x,y,z` (three finite numbers)"),
    }
}

impl PrepareMapArgs {
    /// The stage options (validated).
    pub fn options(&self) -> anyhow::Result<PrepareOptions> {
        let mut options = PrepareOptions {
            voxel_size_m: self.voxel,
            drop_without_normal: !self.keep_without_normal,
            ..Default::default()
        };
        if let Some(radius_m) = self.normal_radius {
            options.normals.radius_m = radius_m;
            options.radius_follows_spacing = false;
        }
        options.normals.k_nearest = self.normal_k;
        options.normals.recompute_all = self.recompute_normals;
        if let Some(sensor) = &self.sensor {
            options.normals.orientation =
                NormalOrientation::TowardsViewpoint(parse_position(sensor).context("--sensor")?);
        }
        if let Some(crop) = &self.crop {
            options.crop = Some(CropBox::parse(crop).context("--crop")?);
        }
        options.validate()?;
        Ok(options)
    }
}

/// The library entry point of the command: read, prepare, write.
pub fn prepare_map_file(
    input: &Path,
    output: &Path,
    options: &PrepareOptions,
) -> anyhow::Result<(LoadReport, PrepareReport)> {
    options.validate()?;
    let start = Instant::now();
    let (cloud, load) = read_point_cloud(input)?;
    log::info!(
        "read {} ({}): {} records, {} kept, {} dropped (NaN/inf), normals: {}{} in {:.2} s",
        input.display(),
        load.format,
        load.points_read,
        cloud.len(),
        load.dropped_non_finite,
        if load.had_normals { "yes" } else { "no" },
        if load.had_normals {
            format!(" ({} invalid)", load.normals_invalid)
        } else {
            String::new()
        },
        start.elapsed().as_secs_f64()
    );
    let start = Instant::now();
    let (cloud, report) =
        prepare(cloud, options).with_context(|| format!("preparing {}", input.display()))?;
    if options.crop.is_some() {
        log::info!(
            "crop box: {} of {} points inside, {} dropped",
            report.input_points - report.dropped_by_crop,
            report.input_points,
            report.dropped_by_crop
        );
    }
    log::info!(
        "prepared: {} -> {} points after the {} m voxel grid; normals kept {}, estimated {}, \
         failed {}; {} points dropped without a normal; {:.2} s",
        report.input_points - report.dropped_by_crop,
        report.after_voxel,
        options.voxel_size_m,
        report.normals.kept,
        report.normals.estimated,
        report.normals.failed,
        report.dropped_without_normal,
        start.elapsed().as_secs_f64()
    );
    if cloud.is_empty() {
        anyhow::bail!("{}: no point left to write", input.display());
    }
    let start = Instant::now();
    write_ply(output, &cloud)?;
    log::info!(
        "wrote {} ({} points) in {:.2} s",
        output.display(),
        cloud.len(),
        start.elapsed().as_secs_f64()
    );
    Ok((load, report))
}

pub fn run(args: &PrepareMapArgs) -> anyhow::Result<()> {
    let options = args.options()?;
    let (load, report) = prepare_map_file(&args.input, &args.output, &options)?;
    let cropped = if options.crop.is_some() {
        format!("{} outside the crop box, ", report.dropped_by_crop)
    } else {
        String::new()
    };
    println!(
        "{}: {} points read ({} dropped as NaN/inf), {cropped}{} after voxel grid, \
         {} normals estimated ({:.3} m radius), {} kept, {} points written to {}",
        args.input.display(),
        load.points_read,
        load.dropped_non_finite,
        report.after_voxel,
        report.normals.estimated,
        report.normal_radius_m,
        report.normals.kept,
        report.output_points,
        args.output.display()
    );
    Ok(())
}
