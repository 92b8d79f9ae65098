//! `colmap-lidar prepare-map`: reads a raw point cloud (PLY, PCD, LAS/LAZ, E57)
//! or several (the tiles of a survey, merged), downsamples it, estimates
//! normals where they are missing or invalid, and writes a binary PLY with
//! normals (and planarity) that the mapper and CloudCompare both read.
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use nalgebra::Vector3;

use crate::map::io::{
    read_point_cloud_with, write_ply, InputUnits, LoadReport, ReadOptions,
    PRECISION_WARNING_OFFSET_M,
};
use crate::map::prepare::{
    prepare, CropBox, NormalOrientation, PrepareError, PrepareOptions, PrepareReport,
    KEEP_WHOLE_MAX_POINTS,
};
use crate::map::PointCloud;

/// `--voxel`'s default, metres.
const DEFAULT_VOXEL_M: f64 = 0.03;

#[derive(clap::Args, Debug, Clone)]
pub struct PrepareMapArgs {
    /// Raw point cloud: .ply, .pcd, .las, .laz or .e57 (every scan, each at
    /// its pose). Given again, or a folder (its files of these kinds, by
    /// name), the clouds are merged into one map: the tiles of a survey,
    /// all in one frame.
    #[arg(long, alias = "input_path", required = true)]
    pub input: Vec<PathBuf>,
    /// Output binary PLY with normals.
    #[arg(long, alias = "output_path")]
    pub output: PathBuf,
    /// Voxel size for downsampling, metres (0 = keep every point)
    /// [default: every point kept up to 20 M points (after --crop), 0.03
    /// for a larger cloud].
    #[arg(long)]
    pub voxel: Option<f64>,
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
    /// (the input's own coordinates, in metres: converted like the points
    /// when they are in feet, see --input-units), before downsampling: the
    /// part of a large survey the photos show.
    #[arg(long, allow_hyphen_values = true)]
    pub crop: Option<String>,
    /// LAS/LAZ classes whose points are left out, `c1,c2,...`, or `none`
    /// [default: 7,18, the ASPRS noise classes; points flagged withheld are
    /// always left out].
    #[arg(long = "drop-classes", alias = "drop_classes")]
    pub drop_classes: Option<String>,
    /// The inputs' length unit: auto (a LAS/LAZ file's coordinate reference
    /// system; metres for the other formats and LAS files without one), m,
    /// ft (0.3048 m) or us-ft (1200/3937 m). Coordinates are converted to
    /// metres; a LAS file in longitude and latitude is refused unless a unit
    /// is given.
    #[arg(long = "input-units", alias = "input_units", default_value = "auto")]
    pub input_units: String,
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

/// Parses `--drop-classes`: `none`, or classes 0-255 separated by commas.
pub fn parse_classes(text: &str) -> anyhow::Result<Vec<u8>> {
    if text.trim().eq_ignore_ascii_case("none") {
        return Ok(Vec::new());
    }
    text.split(',')
        .map(|c| {
            c.trim().parse::<u8>().map_err(|_| {
                anyhow::anyhow!("`{text}` is not `none` or LAS classes 0-255 separated by commas")
            })
        })
        .collect()
}

/// The value of `--input-units` (`prepare-map`, `map`).
pub(crate) fn parse_input_units(text: &str) -> anyhow::Result<InputUnits> {
    InputUnits::parse(text)
        .map_err(anyhow::Error::msg)
        .context("--input-units")
}

impl PrepareMapArgs {
    /// What the readers leave out (validated).
    pub fn read_options(&self) -> anyhow::Result<ReadOptions> {
        let mut options = ReadOptions::default();
        if let Some(classes) = &self.drop_classes {
            options.drop_las_classes = parse_classes(classes).context("--drop-classes")?;
        }
        options.units = parse_input_units(&self.input_units)?;
        Ok(options)
    }

    /// The stage options (validated).
    pub fn options(&self) -> anyhow::Result<PrepareOptions> {
        let mut options = PrepareOptions {
            voxel_size_m: self.voxel.unwrap_or(DEFAULT_VOXEL_M),
            voxel_above_points: match self.voxel {
                Some(_) => 0,
                None => KEEP_WHOLE_MAX_POINTS,
            },
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

/// The point-cloud files of a command line's `--input` values: a file as
/// given, a folder as the files in it that a map reader reads (by extension,
/// sorted by name; hidden files and subfolders left out). A folder without
/// any, a file named twice, an output that is one of the inputs, or an
/// output inside an input folder (the next run would read it as a tile) is
/// an error.
pub fn input_files(inputs: &[PathBuf], output: &Path) -> anyhow::Result<Vec<PathBuf>> {
    let output_folder = output
        .parent()
        .map(|p| {
            if p.as_os_str().is_empty() {
                Path::new(".")
            } else {
                p
            }
        })
        .and_then(|p| p.canonicalize().ok());
    let mut files = Vec::new();
    for input in inputs {
        if !input.is_dir() {
            files.push(input.clone());
            continue;
        }
        if output_folder.is_some() && input.canonicalize().ok() == output_folder {
            anyhow::bail!(
                "the output {} is inside the input folder {}: write it elsewhere (a later run \
                 would read it as one of the folder's point clouds)",
                output.display(),
                input.display()
            );
        }
        let listing = || format!("reading the folder {}", input.display());
        let mut found = Vec::new();
        for entry in std::fs::read_dir(input).with_context(listing)? {
            let path = entry.with_context(listing)?.path();
            let hidden = path
                .file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with('.'));
            if !hidden && path.is_file() && is_point_cloud_name(&path) {
                found.push(path);
            }
        }
        if found.is_empty() {
            anyhow::bail!(
                "the folder {} holds no point cloud (.ply, .pcd, .las, .laz or .e57 file; \
                 subfolders are not searched)",
                input.display()
            );
        }
        found.sort();
        files.extend(found);
    }
    let key = |path: &Path| path.canonicalize().unwrap_or_else(|_| path.to_path_buf());
    let output_key = output.exists().then(|| key(output));
    let mut seen: Vec<(PathBuf, &PathBuf)> = Vec::new();
    for file in &files {
        let file_key = key(file);
        if output_key.as_ref() == Some(&file_key) {
            anyhow::bail!(
                "the output {} is one of the inputs: write the map elsewhere",
                output.display()
            );
        }
        if let Some((_, first)) = seen.iter().find(|(k, _)| *k == file_key) {
            anyhow::bail!(
                "the point cloud {} is given twice (also as {}): each tile once",
                file.display(),
                first.display()
            );
        }
        seen.push((file_key, file));
    }
    Ok(files)
}

/// Whether a file name has the extension of a cloud the map readers read.
fn is_point_cloud_name(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase())
        .is_some_and(|e| ["ply", "pcd", "las", "laz", "e57"].contains(&e.as_str()))
}

/// The library entry point of the command for one input: read, prepare,
/// write.
pub fn prepare_map_file(
    input: &Path,
    output: &Path,
    options: &PrepareOptions,
) -> anyhow::Result<(LoadReport, PrepareReport)> {
    let (mut loads, report) = prepare_map_files(
        &[input.to_path_buf()],
        output,
        options,
        &ReadOptions::default(),
    )?;
    Ok((loads.remove(0), report))
}

/// Reads every input (each cropped on its own when a box is given, so a
/// large survey's points outside it are held only while their tile is
/// read), merges them into one cloud ([`PointCloud::concatenate`]), prepares
/// it and writes it. One load report per input.
pub fn prepare_map_files(
    inputs: &[PathBuf],
    output: &Path,
    options: &PrepareOptions,
    read: &ReadOptions,
) -> anyhow::Result<(Vec<LoadReport>, PrepareReport)> {
    options.validate()?;
    anyhow::ensure!(!inputs.is_empty(), "no input point cloud given");
    let mut clouds = Vec::with_capacity(inputs.len());
    let mut loads = Vec::with_capacity(inputs.len());
    let mut input_points = 0;
    let mut dropped_by_crop = 0;
    let mut spans: Option<(Vector3<f64>, Vector3<f64>)> = None;
    for input in inputs {
        let start = Instant::now();
        let (mut cloud, load) = read_point_cloud_with(input, read)?;
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
        input_points += cloud.len();
        if let Some(crop) = &options.crop {
            if let Some((lo, hi)) = cloud.bounds() {
                spans = Some(match spans {
                    Some((l, h)) => (l.inf(&lo), h.sup(&hi)),
                    None => (lo, hi),
                });
            }
            dropped_by_crop += crop.retain(&mut cloud);
        }
        clouds.push(cloud);
        loads.push(load);
    }
    if let (Some(crop), Some(spans)) = (&options.crop, spans) {
        if dropped_by_crop == input_points {
            return Err(PrepareError::CropHoldsNothing {
                points: input_points,
                crop: *crop,
                spans,
            })
            .with_context(|| format!("cropping {}", names(inputs)));
        }
        log::info!(
            "crop box: {} of {} points inside, {} dropped",
            input_points - dropped_by_crop,
            input_points,
            dropped_by_crop
        );
    }
    let cloud = PointCloud::concatenate(clouds);
    if inputs.len() > 1 {
        let offset = cloud.max_offset_m();
        if offset > PRECISION_WARNING_OFFSET_M {
            log::warn!(
                "the {} inputs reach {offset:.0} m from the local origin {:?}; coordinates that \
                 far keep only {:.1} mm resolution (are they all in one frame?)",
                inputs.len(),
                cloud.origin.as_slice(),
                1000.0 * offset / f64::from(1u32 << 24)
            );
        }
    }
    let start = Instant::now();
    let cropped = PrepareOptions {
        crop: None,
        ..options.clone()
    };
    let (cloud, mut report) =
        prepare(cloud, &cropped).with_context(|| format!("preparing {}", names(inputs)))?;
    report.input_points = input_points;
    report.dropped_by_crop = dropped_by_crop;
    let kept_in_crop = report.input_points - report.dropped_by_crop;
    let grid = if report.kept_whole {
        format!(
            "kept whole (at most {} points; --voxel thins it)",
            options.voxel_above_points
        )
    } else if options.voxel_size_m > 0.0 {
        format!("after the {} m voxel grid", options.voxel_size_m)
    } else {
        "kept whole (--voxel 0)".to_string()
    };
    log::info!(
        "prepared: {} -> {} points {grid}; normals kept {}, estimated {}, \
         failed {}; {} points dropped without a normal; {:.2} s",
        kept_in_crop,
        report.after_voxel,
        report.normals.kept,
        report.normals.estimated,
        report.normals.failed,
        report.dropped_without_normal,
        start.elapsed().as_secs_f64()
    );
    // A voxel chosen finer than the default that merged nothing: said, as
    // a tiny value may be a unit slip (the default on a sparse map is not).
    let voxel = options.voxel_size_m;
    if voxel > 0.0
        && voxel < DEFAULT_VOXEL_M
        && kept_in_crop > 1
        && report.after_voxel == kept_in_crop
    {
        log::warn!(
            "the {voxel} m voxel grid merged no two of the {kept_in_crop} points: it is finer than \
             the map's spacing and only cost time (--voxel 0 keeps every point; without \
             --voxel a cloud of up to {KEEP_WHOLE_MAX_POINTS} points is kept whole and a \
             larger one thinned at {DEFAULT_VOXEL_M} m)"
        );
    }
    if cloud.is_empty() {
        anyhow::bail!("{}: no point left to write", names(inputs));
    }
    let start = Instant::now();
    write_ply(output, &cloud)?;
    log::info!(
        "wrote {} ({} points) in {:.2} s",
        output.display(),
        cloud.len(),
        start.elapsed().as_secs_f64()
    );
    Ok((loads, report))
}

/// The inputs as a message names them: the file, or how many and the first.
fn names(inputs: &[PathBuf]) -> String {
    match inputs {
        [one] => one.display().to_string(),
        [first, ..] => format!("{} point clouds ({}, ...)", inputs.len(), first.display()),
        [] => "no point cloud".into(),
    }
}

pub fn run(args: &PrepareMapArgs) -> anyhow::Result<()> {
    let options = args.options()?;
    let read = args.read_options()?;
    crate::io::atomic::check_output_location(&args.output, false)?;
    let inputs = input_files(&args.input, &args.output)?;
    super::check_output_extension(&args.output, "ply", "a binary PLY point cloud")?;
    let (loads, report) = prepare_map_files(&inputs, &args.output, &options, &read)?;
    let by_class: u64 = loads.iter().map(|l| l.dropped_by_class).sum();
    let withheld: u64 = loads.iter().map(|l| l.dropped_withheld).sum();
    let mut left_out = String::new();
    if by_class > 0 {
        let classes: Vec<String> = read.drop_las_classes.iter().map(u8::to_string).collect();
        left_out += &format!(", {by_class} of the classes {}", classes.join(","));
    }
    if withheld > 0 {
        left_out += &format!(", {withheld} flagged withheld");
    }
    let cropped = if options.crop.is_some() {
        format!("{} outside the crop box, ", report.dropped_by_crop)
    } else {
        String::new()
    };
    let noise = report.noise_m.map_or(String::new(), |n| {
        format!(", map noise about {:.1} mm", n * 1e3)
    });
    let grid = if report.kept_whole {
        format!(
            " (kept whole: at most {} M points; --voxel {DEFAULT_VOXEL_M} thins it)",
            KEEP_WHOLE_MAX_POINTS / 1_000_000
        )
    } else {
        String::new()
    };
    println!(
        "{}: {} points read ({} dropped as NaN/inf{left_out}), {cropped}{} after voxel grid{grid}, \
         {} normals estimated ({:.3} m radius{noise}){}, {} kept, {} points written to {}",
        names(&inputs),
        loads.iter().map(|l| l.points_read).sum::<u64>(),
        loads.iter().map(|l| l.dropped_non_finite).sum::<u64>(),
        report.after_voxel,
        report.normals.estimated,
        report.normal_radius_m,
        report.normals.widened_note(),
        report.normals.kept,
        report.output_points,
        args.output.display()
    );
    for (input, load) in inputs.iter().zip(&loads) {
        if let Some(units) = &load.units {
            println!(
                "{}: coordinates in {units}, converted to metres",
                input.display()
            );
        }
    }
    Ok(())
}
