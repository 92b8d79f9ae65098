//! `colmap-lidar depth-maps`: the LiDAR map's depth at every pixel of every
//! registered image of a model ([`crate::map::surface_depth`]), as 16-bit
//! PNGs in millimetres or float32 `.npy` arrays in metres, with
//! `depth_maps.json` saying what they hold. For depth-supervised NeRF or
//! Gaussian splatting on the model, or to check a dense reconstruction
//! against the scan.
use std::collections::HashMap;
use std::io::Write;
use std::path::{Component, Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context};
use image::{ImageBuffer, ImageFormat, Luma};

use crate::io::atomic::{output_replaces_input, write_dir_atomically, OutputSnapshot};
use crate::io::model::read_model;
use crate::map::grid::{FrustumGrid, GridOptions};
use crate::map::index::MapIndex;
use crate::map::projection::ProjectionOptions;
use crate::map::surface_depth::{
    render_surface_depth, DepthKind, DepthMap, MapSurface, PixelRays, SurfaceDepthOptions,
};
use crate::scene::{Camera, CameraModel};
use crate::sfm::associate::NearestNeighbourAssociator;
use crate::sfm::mapper::options_for_map;
use crate::sfm::options::MapperOptions;

/// The summary file in the output folder; a folder holding it is a previous
/// output of this command and may be replaced.
pub const SUMMARY_FILE: &str = "depth_maps.json";

/// How the depth maps are stored.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum DepthFormat {
    /// 16-bit greyscale PNG, `--png-units-per-metre` per metre (1000:
    /// millimetres), 0 where the image sees no map surface.
    Png16,
    /// NumPy `.npy`, float32 metres, row-major (height x width), 0 where the
    /// image sees no map surface.
    Npy,
}

impl DepthFormat {
    fn extension(self) -> &'static str {
        match self {
            DepthFormat::Png16 => "png",
            DepthFormat::Npy => "npy",
        }
    }
}

#[derive(clap::Args, Debug, Clone)]
pub struct DepthMapsArgs {
    /// LiDAR map: .ply, .pcd, .las, .laz or .e57.
    #[arg(long, alias = "lidar_path")]
    pub lidar: PathBuf,
    /// COLMAP model folder (text or binary) in the map's frame.
    #[arg(long, alias = "input_path")]
    pub model: PathBuf,
    /// Output folder: one depth map per registered image, named as the image
    /// with the format's extension (`sub/frame_0001.jpg` -> `sub/frame_0001.png`),
    /// and depth_maps.json. Replaced as a whole.
    #[arg(long, alias = "output_path")]
    pub output: PathBuf,
    /// png16: 16-bit PNG (--png-units-per-metre, millimetres by default);
    /// npy: float32 metres. Either holds 0 where the image sees no map surface.
    #[arg(long, value_enum, default_value_t = DepthFormat::Png16)]
    pub format: DepthFormat,
    /// z: along the optical axis (NeRF, Gaussian splatting, COLMAP); range:
    /// from the camera centre.
    #[arg(long, value_enum, default_value_t = DepthKind::Z)]
    pub depth: DepthKind,
    /// A PNG's value per metre of depth (1000: millimetres, up to 65.535 m;
    /// 5000: TUM RGB-D's, up to 13.1 m).
    #[arg(
        long = "png-units-per-metre",
        alias = "png_units_per_metre",
        default_value_t = 1000.0
    )]
    pub png_units_per_metre: f64,
    /// Points closer than this along the optical axis are ignored, metres
    /// (a fisheye: closer than this to the camera).
    #[arg(long = "min-depth", alias = "min_depth", default_value_t = 0.5)]
    pub min_depth: f64,
    /// Points deeper than this are ignored, metres.
    #[arg(long = "max-depth", alias = "max_depth", default_value_t = 40.0)]
    pub max_depth: f64,
    /// Views farther than this from a map point's normal take the point's
    /// own depth instead of its tangent plane's, degrees.
    #[arg(
        long = "max-view-angle",
        alias = "max_view_angle",
        default_value_t = 85.0
    )]
    pub max_view_angle: f64,
    /// No depth beside a step between surfaces (occluding edges, corners,
    /// where the map ends), within the splat's reach of it: the splats of a
    /// surface in front may reach past its edge there. For depth losses
    /// that should not see those pixels.
    #[arg(long = "drop-edges", alias = "drop_edges")]
    pub drop_edges: bool,
}

impl DepthMapsArgs {
    /// The rendering options (validated), and the format's limits.
    pub fn options(&self) -> anyhow::Result<SurfaceDepthOptions> {
        let options = SurfaceDepthOptions {
            projection: ProjectionOptions {
                min_depth_m: self.min_depth,
                max_depth_m: self.max_depth,
                ..Default::default()
            },
            max_view_angle_deg: self.max_view_angle,
            drop_edges: self.drop_edges,
            ..Default::default()
        };
        options.validate()?;
        if self.format == DepthFormat::Png16 {
            let units = self.png_units_per_metre;
            if !(units > 0.0 && units.is_finite()) {
                bail!("--png-units-per-metre must be a positive number, not {units}");
            }
            // Every depth written, along the axis or from the camera, is
            // within --max-depth (the points drawn are, and so are the
            // planes' crossings kept).
            if self.max_depth * units > f64::from(u16::MAX) {
                bail!(
                    "--max-depth {} m at {units} per metre is beyond what a 16-bit PNG holds \
                     ({:.3} m): lower --max-depth or --png-units-per-metre, or use --format npy",
                    self.max_depth,
                    f64::from(u16::MAX) / units
                );
            }
        }
        Ok(options)
    }
}

/// What `depth_maps.json` says of one image.
#[derive(Debug, serde::Serialize)]
struct ImageSummary {
    image_id: u32,
    name: String,
    file: String,
    width: u32,
    height: u32,
    /// Share of the pixels with a depth.
    filled_share: f64,
    /// Share of those whose depth is a tangent plane's crossing.
    tangent_plane_share: f64,
    median_depth_m: Option<f64>,
}

#[derive(Debug, serde::Serialize)]
struct Summary {
    format: DepthFormat,
    depth: DepthKind,
    /// A stored value divided by this is metres.
    units_per_metre: f64,
    /// The value of pixels that see no map surface.
    empty_value: u32,
    /// Whether pixels beside steps between surfaces were left empty.
    edges_dropped: bool,
    lidar: String,
    model: String,
    images: Vec<ImageSummary>,
}

/// A map point without another within this many times the map's spacing is
/// a stray return (dust, a bird, multipath), not drawn in the depth maps.
const STRAY_RADIUS_PER_SPACING: f64 = 3.0;

/// The spacing assumed for a map whose own cannot be measured, metres.
const DEFAULT_SPACING_M: f64 = 0.03;

/// What makes two cameras' pixel rays the same: model, size, parameters.
type IntrinsicsKey = (CameraModel, u32, u32, Vec<u64>);

fn intrinsics_key(camera: &Camera) -> IntrinsicsKey {
    let params = camera.params.iter().map(|p| p.to_bits()).collect();
    (camera.model, camera.width, camera.height, params)
}

/// The depth map's file for image `name`: its relative path with the
/// format's extension. An error for a name that would leave the output
/// folder (absolute, or with `..`).
fn depth_file_name(name: &str, format: DepthFormat) -> anyhow::Result<PathBuf> {
    let path = Path::new(name);
    let plain = path.components().all(|c| matches!(c, Component::Normal(_)));
    if !plain || name.is_empty() {
        bail!("image name `{name}` is not a relative path inside the image folder");
    }
    Ok(path.with_extension(format.extension()))
}

/// `depth` (metres) as a 16-bit PNG's values: `units_per_metre` per metre,
/// rounded; 0 where empty. `None` when a depth does not fit.
pub fn to_png16_values(depth: &DepthMap, units_per_metre: f64) -> Option<Vec<u16>> {
    depth
        .depth_m
        .iter()
        .map(|&d| {
            let v = (f64::from(d) * units_per_metre).round();
            (d >= 0.0 && v <= f64::from(u16::MAX)).then_some(v as u16)
        })
        .collect()
}

/// The bytes of a NumPy `.npy` file (format 1.0) of a `height` x `width`
/// little-endian float32 array, row-major.
pub fn npy_bytes(values: &[f32], width: u32, height: u32) -> Vec<u8> {
    let mut header =
        format!("{{'descr': '<f4', 'fortran_order': False, 'shape': ({height}, {width}), }}");
    // Magic (6), version (2), header length (2), header: a multiple of 64
    // bytes in all, the header ending in a newline.
    let unpadded = 10 + header.len() + 1;
    header.push_str(&" ".repeat(unpadded.next_multiple_of(64) - unpadded));
    header.push('\n');
    let mut bytes = Vec::with_capacity(10 + header.len() + 4 * values.len());
    bytes.extend_from_slice(b"\x93NUMPY\x01\x00");
    bytes.extend_from_slice(&(header.len() as u16).to_le_bytes());
    bytes.extend_from_slice(header.as_bytes());
    for v in values {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    bytes
}

fn write_depth_map(
    path: &Path,
    depth: &DepthMap,
    format: DepthFormat,
    units_per_metre: f64,
) -> anyhow::Result<()> {
    let bytes = match format {
        DepthFormat::Png16 => {
            let values = to_png16_values(depth, units_per_metre).with_context(|| {
                format!(
                    "a depth in {} is beyond what a 16-bit PNG holds at {units_per_metre} per \
                     metre: lower --max-depth or --png-units-per-metre, or use --format npy",
                    path.display()
                )
            })?;
            let img: ImageBuffer<Luma<u16>, Vec<u16>> =
                ImageBuffer::from_raw(depth.width, depth.height, values)
                    .context("a depth map of the wrong size")?;
            let mut bytes = std::io::Cursor::new(Vec::new());
            img.write_to(&mut bytes, ImageFormat::Png)
                .with_context(|| format!("encoding {} as PNG", path.display()))?;
            bytes.into_inner()
        }
        DepthFormat::Npy => npy_bytes(&depth.depth_m, depth.width, depth.height),
    };
    if let Some(parent) = path.parent() {
        std::fs::create_dir_all(parent)
            .with_context(|| format!("creating {}", parent.display()))?;
    }
    let mut file =
        std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
    file.write_all(&bytes)
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}

/// Refuses an existing output folder that is neither empty nor a previous
/// output of this command (holding [`SUMMARY_FILE`]).
fn check_replaceable(dir: &Path) -> anyhow::Result<()> {
    crate::io::atomic::check_output_location(dir, true)?;
    if !dir.is_dir() || dir.join(SUMMARY_FILE).is_file() {
        return Ok(());
    }
    let mut entries =
        std::fs::read_dir(dir).with_context(|| format!("reading {}", dir.display()))?;
    if let Some(entry) = entries.next() {
        let entry = entry.with_context(|| format!("reading {}", dir.display()))?;
        bail!(
            "the output folder {} holds `{}` and no {SUMMARY_FILE}: it is not a previous \
             output of depth-maps, refusing to replace it",
            dir.display(),
            entry.file_name().to_string_lossy()
        );
    }
    Ok(())
}

pub fn run(args: &DepthMapsArgs) -> anyhow::Result<()> {
    let mut options = args.options()?;
    check_replaceable(&args.output)?;
    if let Some(why) = output_replaces_input(&args.output, true, &[&args.lidar], &[&args.model]) {
        bail!(why);
    }
    let output_before = OutputSnapshot::take(&args.output);
    let start = Instant::now();
    let model = read_model(&args.model)
        .with_context(|| format!("reading the COLMAP model {}", args.model.display()))?;
    let mut images = Vec::new();
    let mut files: HashMap<PathBuf, &str> = HashMap::new();
    for (image, camera) in super::registered_with_cameras(&model, &args.model)? {
        let file = depth_file_name(&image.name, args.format)
            .with_context(|| format!("in the model {}", args.model.display()))?;
        if let Some(other) = files.insert(file.clone(), &image.name) {
            bail!(
                "images `{other}` and `{}` would both write {}: rename one of them",
                image.name,
                file.display()
            );
        }
        images.push((image, camera, file));
    }
    if images.is_empty() {
        bail!("the model {} has no registered image", args.model.display());
    }
    let cloud = super::map::load_map(&args.lidar)?;
    let index_error = || format!("indexing the LiDAR map {}", args.lidar.display());
    let index = MapIndex::build(&cloud).with_context(index_error)?;
    // Each map point's plane: the mean of its neighbours', as the mapper's
    // (radius and window from the map's spacing and noise).
    let adapted = options_for_map(&MapperOptions::default(), &cloud, &index);
    if let Some(spacing) = adapted.spacing_m {
        options.splats_for_spacing(spacing);
        log::info!(
            "map spacing about {spacing:.3} m: splat half-width {:.3} m",
            options.projection.splat.patch_half_width_m
        );
    }
    let planes = NearestNeighbourAssociator::new(&cloud, &index, adapted.options.association);
    let stray_radius = STRAY_RADIUS_PER_SPACING * adapted.spacing_m.unwrap_or(DEFAULT_SPACING_M);
    let surface_at = |i: usize| match planes.plane_offset_at(i) {
        Some(d) => MapSurface::Plane(d),
        None if index
            .k_nearest_within(&cloud.point_in_map(i), 2, stray_radius)
            .len()
            < 2 =>
        {
            MapSurface::Stray
        }
        None => MapSurface::NoPlane,
    };
    let grid = FrustumGrid::build(&cloud, &GridOptions::default()).with_context(index_error)?;
    log::info!(
        "read {} map points and {} registered images ({:.1} s)",
        cloud.len(),
        images.len(),
        start.elapsed().as_secs_f64()
    );
    let units_per_metre = match args.format {
        DepthFormat::Png16 => args.png_units_per_metre,
        DepthFormat::Npy => 1.0,
    };
    let bar = super::image_progress_bar(images.len(), "images");
    let mut summaries = Vec::with_capacity(images.len());
    // The last camera's pixel rays (8 bytes a pixel): COLMAP makes a camera
    // per image unless told otherwise, so they are kept for one set of
    // intrinsics at a time, not per camera.
    let mut rays: Option<(IntrinsicsKey, PixelRays)> = None;
    let mut any_filled = false;
    let written = write_dir_atomically::<anyhow::Error>(&args.output, |dir| {
        for (image, camera, file) in &images {
            let pose = image.cam_from_world.expect("registered");
            let key = intrinsics_key(camera);
            if rays.as_ref().is_none_or(|(k, _)| *k != key) {
                rays = Some((key, PixelRays::new(camera)));
            }
            let rays = &rays.as_ref().expect("just set").1;
            let depth = render_surface_depth(
                &cloud,
                &grid,
                camera,
                rays,
                &pose,
                &options,
                args.depth,
                Some(&surface_at),
            )
            .with_context(|| format!("the depth map of image `{}`", image.name))?;
            write_depth_map(&dir.join(file), &depth, args.format, units_per_metre)?;
            let filled = depth.num_filled();
            any_filled |= filled > 0;
            let pixels = depth.depth_m.len().max(1) as f64;
            log::debug!(
                "{}: {:.1} % of the pixels see the map",
                image.name,
                100.0 * filled as f64 / pixels
            );
            summaries.push(ImageSummary {
                image_id: image.id.0,
                name: image.name.clone(),
                file: file.to_string_lossy().into_owned(),
                width: depth.width,
                height: depth.height,
                filled_share: filled as f64 / pixels,
                tangent_plane_share: depth.num_on_tangent_planes as f64 / filled.max(1) as f64,
                median_depth_m: depth.median_m(),
            });
            if let Some(bar) = &bar {
                bar.inc(1);
            }
        }
        if !any_filled {
            bail!(
                "no image of {} sees a point of the LiDAR map {}: is the model in the map's frame?",
                args.model.display(),
                args.lidar.display()
            );
        }
        let summary = Summary {
            format: args.format,
            depth: args.depth,
            units_per_metre,
            empty_value: 0,
            edges_dropped: args.drop_edges,
            lidar: args.lidar.display().to_string(),
            model: args.model.display().to_string(),
            images: std::mem::take(&mut summaries),
        };
        let json = serde_json::to_string_pretty(&summary)?;
        std::fs::write(dir.join(SUMMARY_FILE), json + "\n")
            .with_context(|| format!("writing {SUMMARY_FILE}"))?;
        // Not over what another run wrote there meanwhile.
        output_before.check_unchanged(&args.output)?;
        Ok(())
    });
    if let Some(bar) = &bar {
        bar.finish_and_clear();
    }
    written.with_context(|| format!("writing the depth maps to {}", args.output.display()))?;
    log::info!(
        "wrote {} depth maps to {} ({:.1} s)",
        images.len(),
        args.output.display(),
        start.elapsed().as_secs_f64()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn npy_header_is_aligned_and_says_the_shape() {
        let bytes = npy_bytes(&[1.5, 0.0, -2.0, 4.25, 7.0, 8.0], 3, 2);
        assert_eq!(&bytes[..8], b"\x93NUMPY\x01\x00");
        let len = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
        assert_eq!((10 + len) % 64, 0);
        let header = std::str::from_utf8(&bytes[10..10 + len]).unwrap();
        assert!(header.starts_with("{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), }"));
        assert!(header.ends_with('\n'));
        let data: Vec<f32> = bytes[10 + len..]
            .chunks(4)
            .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
            .collect();
        assert_eq!(data, vec![1.5, 0.0, -2.0, 4.25, 7.0, 8.0]);
    }

    #[test]
    fn png_values_round_and_refuse_what_does_not_fit() {
        let depth = DepthMap {
            width: 3,
            height: 1,
            depth_m: vec![0.0, 1.2344, 65.5349],
            num_on_tangent_planes: 0,
        };
        assert_eq!(to_png16_values(&depth, 1000.0), Some(vec![0, 1234, 65535]));
        assert_eq!(to_png16_values(&depth, 5000.0), None);
    }

    #[test]
    fn file_names_stay_inside_the_folder() {
        let f = |n| depth_file_name(n, DepthFormat::Png16).map_err(|e| e.to_string());
        assert_eq!(f("a/b.jpg").unwrap(), PathBuf::from("a/b.png"));
        assert_eq!(f("frame").unwrap(), PathBuf::from("frame.png"));
        assert!(f("../x.jpg").unwrap_err().contains("not a relative path"));
        assert!(f("/abs/x.jpg").is_err());
    }
}
