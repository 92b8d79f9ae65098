//! `colmap-lidar map`: incremental structure-from-motion of a COLMAP
//! database inside a LiDAR map; writes a COLMAP model in the map frame and a
//! `report.json`, atomically (a failed run leaves nothing behind).
//!
//! With one `--init-image` (and `--init-pose`) per group of images that no
//! verified match links, each group is mapped from its own and the models
//! put in one ([`crate::sfm::groups`]).
//!
//! Every option can also come from a TOML file (`--options FILE`): top-level
//! keys `database`, `lidar`, `output`, `image_path`, `init_image`, `init_pose`
//! (each one value or a list), `init_search`,
//! `pose_priors`, `input_model`, `fix_existing_images`, `output_type`,
//! `no_lidar_constraints`, `input_units`, and a `[mapper]` table with the
//! stage options of [`MapperOptions`] (`seed`, `[mapper.register]`, ...).
//! Command-line values win over the file.
use std::collections::{BTreeMap, BTreeSet};
use std::f64::consts::TAU;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use serde::Deserialize;

use crate::commands::prepare_map::parse_input_units;
use crate::geo::MapCrs;
use crate::io::atomic::output_replaces_input;
use crate::io::database::{read_database, DatabaseSnapshot};
use crate::io::images::{check_image_folder, colour_points, ExpectedImage};
use crate::io::model::{read_model, write_model, ModelFormat};
use crate::io::pose_ply::{format_model_pose_ply, read_pose_ply};
use crate::map::io::{read_point_cloud_with, InputUnits, LoadReport, ReadOptions};
use crate::map::prepare::{
    estimate_normals, score_planarity as planarity_of, widen_normal_radius, NormalOptions,
};
use crate::map::PointCloud;
use crate::scene::{BodyPose, ImageId, Rigid3};
use crate::sfm::associate::median_in_place;
use crate::sfm::existing::{match_to_database, ExistingModel};
use crate::sfm::localise::SearchRegion;
use crate::sfm::options::{AssociationKind, IntrinsicsRefinement};
use crate::sfm::positions::run_mapper_from_positions;
use crate::sfm::report::{RunLog, StageRecord};
use crate::sfm::{extend_model, map_groups, GroupStart, KnownPose, MapperInputs, MapperOptions};

/// Known poses: the database's pose priors, overridden by the pose file.
fn known_poses(
    db: &DatabaseSnapshot,
    pose_file: Option<&Path>,
    hints: &mut Vec<String>,
) -> Result<BTreeMap<ImageId, KnownPose>> {
    let mut known = BTreeMap::new();
    for (&id, prior) in &db.pose_priors {
        if let Some(pose) = prior.cam_from_world {
            known.insert(
                id,
                KnownPose {
                    cam_from_world: pose,
                    has_rotation: true,
                },
            );
        } else if prior.is_gps() {
            // Latitude and longitude: see [`gps_positions`].
            continue;
        } else if let Some(p) = prior.position {
            // Position only: the centre of an identity-rotation pose.
            let centre = nalgebra::Vector3::from(p);
            known.insert(
                id,
                KnownPose {
                    cam_from_world: Rigid3::new(nalgebra::UnitQuaternion::identity(), -centre),
                    has_rotation: false,
                },
            );
        }
    }
    if let Some(path) = pose_file {
        let poses = read_pose_ply(path)?;
        hints.extend(crate::io::pose_ply::degrees_suspected(path, &poses));
        for (id, pose) in poses {
            if !db.images.contains_key(&id) {
                bail!(
                    "the pose file {} has a pose for image id {}, which is not in the database {}",
                    path.display(),
                    id.0,
                    db.path.display()
                );
            }
            known.insert(
                id,
                KnownPose {
                    cam_from_world: pose.to_cam_from_world(),
                    has_rotation: true,
                },
            );
        }
    }
    if !known.is_empty() {
        log::info!("{} images with a known pose", known.len());
    }
    Ok(known)
}

/// The images' GPS positions (the database's priors in latitude, longitude
/// and altitude) in the map's frame, with `crs`; none without it (logged
/// when the database has some).
fn gps_positions(
    db: &DatabaseSnapshot,
    crs: Option<&MapCrs>,
) -> BTreeMap<ImageId, nalgebra::Vector3<f64>> {
    let gps: Vec<(ImageId, [f64; 3])> = db
        .pose_priors
        .iter()
        .filter(|(_, p)| p.is_gps())
        .filter_map(|(&id, p)| Some((id, p.position?)))
        .collect();
    match crs {
        Some(crs) => {
            if gps.is_empty() {
                log::warn!(
                    "--map-crs {} is given, but no image in {} has a GPS position",
                    crs.name,
                    db.path.display()
                );
            }
            let positions: BTreeMap<ImageId, nalgebra::Vector3<f64>> = gps
                .iter()
                .map(|&(id, [lat, lon, alt])| (id, crs.to_map(lat, lon, alt)))
                .filter(|(_, p)| p.iter().all(|v| v.is_finite()))
                .collect();
            if positions.len() < gps.len() {
                log::warn!(
                    "{} GPS positions of {} lie where --map-crs {} does not reach (left out)",
                    gps.len() - positions.len(),
                    db.path.display(),
                    crs.name
                );
            }
            positions
        }
        None => {
            if !gps.is_empty() {
                log::info!(
                    "{} images of {} have a GPS position; they are not used without the map's CRS (--map-crs)",
                    gps.len(),
                    db.path.display()
                );
            }
            BTreeMap::new()
        }
    }
}

/// GPS positions farther than this from the map's bounding box, metres,
/// are taken for a wrong CRS or origin.
const MAX_GPS_BEYOND_MAP_M: f64 = 1000.0;

/// An error when the images' GPS positions (map frame) lie far from the
/// map: a wrong `--map-crs` or `--map-origin`, or positions that are no
/// latitudes and longitudes.
fn check_positions_near_map(
    gps: &BTreeMap<ImageId, nalgebra::Vector3<f64>>,
    cloud: &PointCloud,
    config: &MapConfig,
) -> Result<()> {
    let (Some((lo, hi)), Some(crs)) = (cloud.bounds(), config.map_crs.as_ref()) else {
        return Ok(());
    };
    if gps.is_empty() {
        return Ok(());
    }
    // The median on each axis: a few wrong positions do not move it.
    let median = |k: usize| {
        let mut values: Vec<f64> = gps.values().map(|p| p[k]).collect();
        median_in_place(&mut values)
    };
    let (x, y) = (median(0), median(1));
    let beyond = |v: f64, k: usize| (lo[k] - v).max(v - hi[k]).max(0.0);
    let distance = beyond(x, 0).hypot(beyond(y, 1));
    if distance > MAX_GPS_BEYOND_MAP_M {
        bail!(
            "the images' GPS positions, taken by --map-crs {} with the map's origin at ({}, {}, {}), lie {distance:.0} m from the LiDAR map {} (their median at ({x:.1}, {y:.1}); the map spans ({:.1}, {:.1}) to ({:.1}, {:.1})): is the CRS the map's, are its coordinates shifted (--map-origin, the CRS coordinates of the map's (0, 0, 0)), and are the database's positions the photos' GPS (COLMAP 3.8 stores a prior translation without a rotation as latitude, longitude and altitude)?",
            crs.name,
            crs.origin[0],
            crs.origin[1],
            crs.origin[2],
            config.lidar.display(),
            lo.x,
            lo.y,
            hi.x,
            hi.y
        );
    }
    Ok(())
}

/// Hints on the initial poses as given: roll, pitch and yaw all within
/// ±2π (6.28) may be radians, where degrees are read (warned now, repeated
/// if the run fails).
fn init_pose_hints(poses: &[BodyPose]) -> Vec<String> {
    let mut hints = Vec::new();
    for pose in poses {
        let d = pose.to_degrees_array();
        let angles = &d[3..];
        if angles.iter().any(|a| *a != 0.0) && angles.iter().all(|a| a.abs() <= TAU) {
            let hint = format!(
                "--init-pose {}: roll, pitch and yaw are read in degrees, and these are all within ±6.28 (2π); if they are radians, give {:.4},{:.4},{:.4}",
                d.map(|v| v.to_string()).join(","),
                angles[0].to_degrees(),
                angles[1].to_degrees(),
                angles[2].to_degrees()
            );
            log::warn!("{hint}");
            hints.push(hint);
        }
    }
    hints
}

/// Hints on initial poses whose camera centre lies outside the box of the
/// map's points, by how much on each axis (a camera may be outside it, e.g.
/// above a map of the ground; a centre below the map's lowest point, or a
/// COLMAP `tvec` given as the centre, usually is not meant).
fn outside_the_map(poses: &[BodyPose], cloud: &PointCloud) -> Vec<String> {
    let Some((lo, hi)) = cloud.bounds().filter(|_| !poses.is_empty()) else {
        return Vec::new();
    };
    let mut hints = Vec::new();
    for pose in poses {
        let c = pose.position_m;
        let beyond: Vec<String> = (0..3)
            .filter_map(|k| {
                let axis = ["x", "y", "z"][k];
                if c[k] < lo[k] {
                    Some(format!(
                        "{axis} {:.2} m below the map's least",
                        lo[k] - c[k]
                    ))
                } else if c[k] > hi[k] {
                    Some(format!(
                        "{axis} {:.2} m beyond the map's greatest",
                        c[k] - hi[k]
                    ))
                } else {
                    None
                }
            })
            .collect();
        if !beyond.is_empty() {
            hints.push(format!(
                "--init-pose puts the camera at {:.3},{:.3},{:.3}, outside the box of the map's points ({}; the box {:.2},{:.2},{:.2} to {:.2},{:.2},{:.2}): the camera centre is expected (not COLMAP's tvec), in the map's frame",
                c.x, c.y, c.z,
                beyond.join(", "),
                lo.x, lo.y, lo.z, hi.x, hi.y, hi.z
            ));
        }
    }
    hints
}

/// `error` followed by the `hints` that may explain it, one per line.
fn with_hints(error: anyhow::Error, hints: &[String]) -> anyhow::Error {
    if hints.is_empty() {
        return error;
    }
    let list: Vec<String> = hints.iter().map(|h| format!("  - {h}")).collect();
    anyhow::anyhow!("{error:#}\nwhat may explain it:\n{}", list.join("\n"))
}

#[derive(clap::Args, Debug, Clone, Default)]
pub struct MapArgs {
    /// COLMAP database with features and verified matches (opened read-only).
    #[arg(long, visible_alias = "database_path", value_name = "DB")]
    pub database: Option<PathBuf>,
    /// LiDAR map: .ply, .pcd, .las, .laz or .e57 (normals estimated when missing).
    #[arg(long, visible_alias = "lidar_path", value_name = "MAP")]
    pub lidar: Option<PathBuf>,
    /// Output folder of the COLMAP model and report.json (replaced atomically).
    #[arg(long, visible_alias = "output_path", value_name = "DIR")]
    pub output: Option<PathBuf>,
    /// Folder of the images (as given to COLMAP's feature extractor; JPEG,
    /// PNG, TIFF, BMP): every 3D point gets the mean colour of its keypoints,
    /// as COLMAP's `color_extractor` gives it. Checked before the run (each
    /// image there, of its camera's size). Without it the points are grey
    /// (128, 128, 128).
    #[arg(long, visible_alias = "image_path", value_name = "DIR")]
    pub image_path: Option<PathBuf>,
    /// Initial image, by name or id. Default: the smallest image id. Given
    /// again (one per group of images that no verified match links, see
    /// `inspect`), each group is mapped from its own and the models are put
    /// in one.
    #[arg(long, visible_alias = "init_image", value_name = "NAME|ID")]
    pub init_image: Vec<String>,
    /// Pose of the initial image in the map frame: x,y,z (camera centre, m),
    /// roll,pitch,yaw (degrees); body x forward, y left, z up. Default: the
    /// image's known pose (the database's pose prior, or --pose-priors).
    /// With several --init-image, one per image in the same order (or none).
    #[arg(
        long,
        visible_alias = "init_pose",
        value_name = "X,Y,Z,ROLL,PITCH,YAW",
        allow_hyphen_values = true
    )]
    pub init_pose: Vec<String>,
    /// The initial pose is known only roughly: within METRES of its camera
    /// centre horizontally, VERTICAL_METRES vertically (default: METRES, at
    /// most 1 m) and DEGREES of its heading (180: any), roll and pitch
    /// within about 10 deg. The database
    /// is first mapped without the map's planes and that model searched for
    /// on the map (report.json: init_search); an error when nothing fits or
    /// two placements fit alike. Up to 10 m.
    #[arg(
        long,
        visible_alias = "init_search",
        value_name = "METRES,DEGREES[,VERTICAL_METRES]",
        allow_hyphen_values = true
    )]
    pub init_search: Option<String>,
    /// Known poses of images in the reference's pose.ply layout (line k =
    /// image id k: x y z roll pitch yaw, metres and radians, `nan` = none):
    /// soft priors in every solve; images PnP cannot register are placed at
    /// them. The database's pose priors are used too (the file wins).
    #[arg(long, visible_alias = "pose_priors", value_name = "FILE")]
    pub pose_priors: Option<PathBuf>,
    /// An earlier model of this database in the map's frame (e.g. an earlier
    /// `map` output, text or binary) to extend with the database's other
    /// images, as COLMAP's mapper does with --input_path: its images are
    /// matched by name and start at their poses, no initial pose is needed.
    #[arg(long, visible_alias = "input_path", value_name = "DIR")]
    pub input_model: Option<PathBuf>,
    /// With --input-model: its images keep their poses and intrinsics in
    /// every solve (only the new images and the points move); otherwise the
    /// map holds the model and they are refined with the new ones.
    #[arg(long, visible_alias = "fix_existing_images")]
    pub fix_existing_images: bool,
    /// The map's coordinate reference system, to place the model from the
    /// images' GPS positions (COLMAP's feature extractor stores them from
    /// the photos' EXIF) when no initial pose is given: EPSG:CODE (a UTM
    /// zone or another transverse Mercator grid on WGS84/GRS80, e.g.
    /// EPSG:32633), utm:ZONE (e.g. utm:33n) or enu:LAT,LON,HEIGHT (a local
    /// east-north-up frame). Only differences of altitude are used.
    #[arg(long, visible_alias = "map_crs", value_name = "CRS")]
    pub map_crs: Option<String>,
    /// With --map-crs: the CRS coordinates of the map's (0, 0, 0), when its
    /// coordinates are shifted (map = CRS - origin; default 0,0,0).
    #[arg(
        long,
        visible_alias = "map_origin",
        value_name = "X,Y,Z",
        allow_hyphen_values = true
    )]
    pub map_origin: Option<String>,
    /// TOML options file; command-line values win.
    #[arg(long, value_name = "FILE")]
    pub options: Option<PathBuf>,
    /// Model format: text (default) or binary.
    #[arg(long, visible_alias = "output_type", value_name = "text|binary")]
    pub output_type: Option<String>,
    /// Seed of every random choice (default 0).
    #[arg(long)]
    pub seed: Option<u64>,
    /// Plain SfM: no LiDAR point-to-plane terms in BA.
    #[arg(long, visible_alias = "no_lidar_constraints")]
    pub no_lidar_constraints: bool,
    /// Which bundle adjustments refine focal length and distortion (the
    /// principal point with them only where the focal length is a guess, or
    /// as [mapper.bundle] refine_principal_point says): auto (default: every solve
    /// for cameras the database marks as uncalibrated, prior_focal_length =
    /// 0; the others are held unless one solve after the final rounds moves
    /// their focal length by more than 0.1 %), fixed (calibrated cameras),
    /// final, all (every solve, as COLMAP's mapper; the flag alone means all).
    #[arg(
        long,
        visible_alias = "refine_intrinsics",
        value_name = "auto|fixed|final|all",
        num_args = 0..=1,
        default_missing_value = "all"
    )]
    pub refine_intrinsics: Option<IntrinsicsRefinement>,
    /// Ceres threads (default 1: byte-identical output).
    #[arg(long)]
    pub threads: Option<usize>,
    /// The map's length unit, as `prepare-map --input-units`: auto (default:
    /// a LAS/LAZ file's coordinate reference system; metres otherwise), m,
    /// ft or us-ft. The map is converted to metres; the model, --init-pose,
    /// --pose-priors and the options are in metres.
    #[arg(
        long = "input-units",
        visible_alias = "input_units",
        value_name = "auto|m|ft|us-ft"
    )]
    pub input_units: Option<String>,
}

/// The options file.
#[derive(Debug, Default, Deserialize)]
#[serde(default, deny_unknown_fields)]
struct OptionsFile {
    database: Option<PathBuf>,
    lidar: Option<PathBuf>,
    output: Option<PathBuf>,
    image_path: Option<PathBuf>,
    init_image: Option<toml::Value>,
    init_pose: Option<toml::Value>,
    init_search: Option<String>,
    pose_priors: Option<PathBuf>,
    input_model: Option<PathBuf>,
    fix_existing_images: Option<bool>,
    output_type: Option<String>,
    no_lidar_constraints: Option<bool>,
    input_units: Option<String>,
    map_crs: Option<String>,
    map_origin: Option<String>,
    mapper: MapperOptions,
}

/// The validated configuration of a run.
#[derive(Debug, Clone)]
pub struct MapConfig {
    pub database: PathBuf,
    pub lidar: PathBuf,
    pub output: PathBuf,
    pub image_path: Option<PathBuf>,
    /// The initial images (one per group of images; none: the smallest id).
    pub init_images: Vec<String>,
    /// Their poses, in the same order (none: their known poses).
    pub init_poses: Vec<BodyPose>,
    /// `--init-search`: where to search for the initial pose around it.
    pub init_search: Option<SearchRegion>,
    pub pose_priors: Option<PathBuf>,
    /// The model to extend, and whether its images are held.
    pub input_model: Option<PathBuf>,
    pub fix_existing_images: bool,
    pub format: ModelFormat,
    /// The map's length unit (`--input-units`).
    pub input_units: InputUnits,
    /// The map's CRS (`--map-crs`, `--map-origin`).
    pub map_crs: Option<MapCrs>,
    pub options: MapperOptions,
}

impl MapArgs {
    /// Merges the options file (if any) and the command line, validates.
    pub fn config(&self) -> Result<MapConfig> {
        let file: OptionsFile = match &self.options {
            Some(path) => {
                let text = std::fs::read_to_string(path)
                    .with_context(|| format!("reading the options file {}", path.display()))?;
                toml::from_str(&text)
                    .with_context(|| format!("parsing the options file {}", path.display()))?
            }
            None => OptionsFile::default(),
        };
        let need = |cli: &Option<PathBuf>, file: &Option<PathBuf>, flag: &str| -> Result<PathBuf> {
            cli.clone()
                .or_else(|| file.clone())
                .with_context(|| format!("missing --{flag} (or `{flag}` in the options file)"))
        };
        let database = need(&self.database, &file.database, "database")?;
        let lidar = need(&self.lidar, &file.lidar, "lidar")?;
        let output = need(&self.output, &file.output, "output")?;
        let init_images = if self.init_image.is_empty() {
            file_images(file.init_image)?
        } else {
            self.init_image.clone()
        };
        let init_pose_text = if self.init_pose.is_empty() {
            file_poses(file.init_pose)?
        } else {
            self.init_pose.clone()
        };
        let init_poses = init_pose_text
            .iter()
            .map(|s| BodyPose::parse_degrees(s).map_err(|e| anyhow::anyhow!("--init-pose {e}")))
            .collect::<Result<Vec<_>>>()?;
        if !init_poses.is_empty() && init_poses.len() != init_images.len().max(1) {
            bail!(
                "{} --init-pose for {} --init-image: give one pose per initial image, in the same order (or none: their known poses)",
                init_poses.len(),
                init_images.len()
            );
        }
        let init_search = self
            .init_search
            .clone()
            .or(file.init_search)
            .map(|s| SearchRegion::parse(&s).map_err(|e| anyhow::anyhow!("--init-search: {e}")))
            .transpose()?;
        let format = match self.output_type.clone().or(file.output_type).as_deref() {
            None | Some("text") | Some("TXT") | Some("txt") => ModelFormat::Text,
            Some("binary") | Some("BIN") | Some("bin") => ModelFormat::Binary,
            Some(other) => bail!("--output-type must be text or binary, got `{other}`"),
        };
        let input_units = match self.input_units.clone().or(file.input_units) {
            Some(text) => parse_input_units(&text)?,
            None => InputUnits::Auto,
        };
        let origin = match self.map_origin.clone().or(file.map_origin) {
            Some(text) => Some(parse_origin(&text)?),
            None => None,
        };
        let map_crs = match self.map_crs.clone().or(file.map_crs) {
            Some(text) => Some(
                MapCrs::parse(&text, origin.unwrap_or([0.0; 3]))
                    .map_err(|e| anyhow::anyhow!("--map-crs {e}"))?,
            ),
            None if origin.is_some() => {
                bail!("--map-origin needs --map-crs (the CRS whose coordinates it gives)")
            }
            None => None,
        };
        let mut options = file.mapper;
        if let Some(seed) = self.seed {
            options.seed = seed;
        }
        if self.no_lidar_constraints || file.no_lidar_constraints == Some(true) {
            options.association.kind = AssociationKind::None;
        }
        if let Some(mode) = self.refine_intrinsics {
            options.bundle.refine_intrinsics = mode;
        }
        if let Some(t) = self.threads {
            options.bundle.num_threads = t;
        }
        options.validate()?;
        let input_model = self.input_model.clone().or(file.input_model);
        let fix_existing_images =
            self.fix_existing_images || file.fix_existing_images == Some(true);
        if input_model.is_some() && (!init_images.is_empty() || !init_poses.is_empty()) {
            bail!(
                "--init-image and --init-pose are not used with --input-model: the model's images start at their poses"
            );
        }
        if input_model.is_some() && init_search.is_some() {
            bail!("--init-search is not used with --input-model: the model's images start at their poses");
        }
        if fix_existing_images && input_model.is_none() {
            bail!("--fix-existing-images needs --input-model (the model whose images to hold)");
        }
        Ok(MapConfig {
            database,
            lidar,
            output,
            image_path: self.image_path.clone().or(file.image_path),
            init_images,
            init_poses,
            init_search,
            pose_priors: self.pose_priors.clone().or(file.pose_priors),
            input_model,
            fix_existing_images,
            format,
            input_units,
            map_crs,
            options,
        })
    }
}

/// `--map-origin X,Y,Z`.
fn parse_origin(text: &str) -> Result<[f64; 3]> {
    super::parse_xyz(text)
        .ok()
        .filter(|v| v.iter().all(|c| c.is_finite()))
        .with_context(|| {
            format!("--map-origin expects three finite numbers X,Y,Z (metres), got `{text}`")
        })
}

/// `init_image` of the options file: a name or an id, or an array of them.
fn file_images(value: Option<toml::Value>) -> Result<Vec<String>> {
    let one = |v: toml::Value| -> Result<String> {
        match v {
            toml::Value::String(s) => Ok(s),
            toml::Value::Integer(i) => Ok(i.to_string()),
            other => bail!("init_image in the options file must be a name or an id, got {other}"),
        }
    };
    match value {
        None => Ok(Vec::new()),
        Some(toml::Value::Array(items)) => items.into_iter().map(one).collect(),
        Some(v) => Ok(vec![one(v)?]),
    }
}

/// `init_pose` of the options file as `--init-pose` texts: a string
/// `"x,y,z,roll,pitch,yaw"` or an array of six numbers (one pose), or an
/// array of either (one per initial image).
fn file_poses(value: Option<toml::Value>) -> Result<Vec<String>> {
    use toml::Value;
    let number = |v: &Value| match v {
        Value::Integer(i) => Some(i.to_string()),
        Value::Float(f) => Some(f.to_string()),
        _ => None,
    };
    let pose = |v: Value| -> Result<String> {
        match v {
            Value::String(s) => Ok(s),
            Value::Array(items) => {
                let numbers: Option<Vec<String>> = items.iter().map(number).collect();
                numbers.map(|n| n.join(",")).with_context(|| {
                    format!("init_pose in the options file: a pose's values must be numbers, got {}", Value::Array(items))
                })
            }
            other => bail!(
                "init_pose in the options file must be \"x,y,z,roll,pitch,yaw\" or [x, y, z, roll, pitch, yaw] (or a list of them), got {other}"
            ),
        }
    };
    match value {
        None => Ok(Vec::new()),
        Some(Value::Array(items)) if items.is_empty() => Ok(Vec::new()),
        // One pose as six numbers, or a list of poses.
        Some(Value::Array(items)) if items.iter().all(|v| number(v).is_some()) => {
            Ok(vec![pose(Value::Array(items))?])
        }
        Some(Value::Array(items)) => items.into_iter().map(pose).collect(),
        Some(v) => Ok(vec![pose(v)?]),
    }
}

/// The initial image: by exact name first, then by id; default the smallest id.
pub fn resolve_init_image(db: &DatabaseSnapshot, spec: Option<&str>) -> Result<ImageId> {
    match spec {
        None => db
            .images
            .keys()
            .next()
            .copied()
            .with_context(|| format!("the database {} has no images", db.path.display())),
        Some(s) => {
            if let Some(img) = db.image_by_name(s) {
                return Ok(img.id);
            }
            if let Ok(id) = s.trim().parse::<u32>() {
                if db.images.contains_key(&ImageId(id)) {
                    return Ok(ImageId(id));
                }
            }
            let examples: Vec<&str> = db
                .images
                .values()
                .take(3)
                .map(|i| i.name.as_str())
                .collect();
            bail!(
                "unknown initial image `{s}`: no image of that name or id in {} ({} images, e.g. {})",
                db.path.display(),
                db.images.len(),
                examples.join(", ")
            )
        }
    }
}

/// Where a run starts.
enum RunStart {
    /// One initial image per group of images, at its pose.
    InitialPoses(Vec<GroupStart>),
    Model(ExistingModel),
    /// No initial pose: the model placed from the images' GPS positions.
    Positions(ImageId),
}

/// The initial image when the run starts from the images' GPS positions:
/// no --init-pose, at most one --init-image and no known pose of it, and
/// some positions.
fn positions_start(
    db: &DatabaseSnapshot,
    config: &MapConfig,
    known: &BTreeMap<ImageId, KnownPose>,
    gps: &BTreeMap<ImageId, nalgebra::Vector3<f64>>,
) -> Result<Option<ImageId>> {
    if gps.is_empty() || !config.init_poses.is_empty() || config.init_images.len() > 1 {
        return Ok(None);
    }
    let image = resolve_init_image(db, config.init_images.first().map(String::as_str))?;
    Ok((!known.get(&image).is_some_and(|p| p.has_rotation)).then_some(image))
}

/// The initial images at their poses: given ones, else their known poses
/// (the database's pose priors, or the pose file).
fn group_starts(
    db: &DatabaseSnapshot,
    config: &MapConfig,
    known: &BTreeMap<ImageId, KnownPose>,
) -> Result<Vec<GroupStart>> {
    let specs: Vec<Option<&str>> = if config.init_images.is_empty() {
        vec![None]
    } else {
        config
            .init_images
            .iter()
            .map(|s| Some(s.as_str()))
            .collect()
    };
    let mut starts = Vec::with_capacity(specs.len());
    for (k, spec) in specs.into_iter().enumerate() {
        let image = resolve_init_image(db, spec)?;
        if starts.iter().any(|s: &GroupStart| s.image == image) {
            bail!(
                "image `{}` is given twice as --init-image",
                db.images[&image].name
            );
        }
        let cam_from_world = match config.init_poses.get(k) {
            Some(p) => p.to_cam_from_world(),
            None => match known.get(&image).filter(|p| p.has_rotation) {
                Some(p) => p.cam_from_world,
                None => bail!(
                    "no initial pose for image `{}`: pass --init-pose x,y,z,roll,pitch,yaw (map frame, metres, degrees){}{}",
                    db.images[&image].name,
                    if k > 0 { ", one per --init-image" } else { "" },
                    match db.pose_priors.values().filter(|p| p.is_gps()).count() {
                        0 => String::new(),
                        n if config.map_crs.is_none() => format!(
                            "; {n} images have a GPS position: with the map's CRS (--map-crs) they place the model"
                        ),
                        _ => String::new(),
                    }
                ),
            },
        };
        starts.push(GroupStart {
            image,
            cam_from_world,
        });
    }
    Ok(starts)
}

/// Files we may replace in an existing output folder (besides the figures
/// `plot` draws from its report: the guide suggests the model's own folder
/// for them, and they describe the report being replaced).
const REPLACEABLE: [&str; 8] = [
    "pose.ply",
    "cameras.txt",
    "images.txt",
    "points3D.txt",
    "cameras.bin",
    "images.bin",
    "points3D.bin",
    "report.json",
];

/// Refuses an output folder that holds anything but the files `map` (or
/// `merge`) writes: it is replaced as a whole.
pub(crate) fn check_output(dir: &Path) -> Result<()> {
    let replaceable: Vec<&str> = REPLACEABLE
        .iter()
        .chain(&super::plot::FIGURES)
        .copied()
        .collect();
    super::check_replaceable_output(dir, &replaceable, "a model file or a figure of `plot`")
}

/// Reads the map; estimates normals where missing, over a radius that
/// follows the map's spacing and noise ([`widen_normal_radius`]).
pub fn load_map(path: &Path) -> Result<PointCloud> {
    Ok(load_map_reporting(path, InputUnits::Auto, 0.0)?.0)
}

/// The map points whose planarity is below `gate` (they give no plane);
/// `None` when the map has no planarity.
fn points_below_planarity(cloud: &PointCloud, gate: f64) -> Option<usize> {
    let planarity = cloud.planarity.as_ref()?;
    Some(planarity.iter().filter(|&&v| f64::from(v) < gate).count())
}

/// [`load_map`] with the map's length unit, and what the reader saw. With
/// a `planarity_gate` above 0 (the mapper's `min_planarity`), a map that
/// came with normals but no planarity also gets each point's planarity
/// ([`planarity_of`]; its normals are kept), for the mapper's gate.
pub fn load_map_reporting(
    path: &Path,
    units: InputUnits,
    planarity_gate: f64,
) -> Result<(PointCloud, LoadReport)> {
    let read = ReadOptions {
        units,
        ..ReadOptions::default()
    };
    let (mut cloud, load) = read_point_cloud_with(path, &read)
        .with_context(|| format!("reading the LiDAR map {}", path.display()))?;
    if cloud.is_empty() {
        bail!("the LiDAR map {} holds no points", path.display());
    }
    let file_planarity = cloud.planarity.is_some();
    let estimate = !load.had_normals || load.normals_invalid > 0;
    let score = planarity_gate > 0.0 && load.had_normals && !file_planarity;
    if !(estimate || score) {
        return Ok((cloud, load));
    }
    // One radius for both: it follows the map's points, not its normals.
    let mut options = NormalOptions::default();
    let what = if estimate {
        "estimating normals of"
    } else {
        "scoring the planarity of"
    };
    let scales = widen_normal_radius(&mut options, &cloud)
        .with_context(|| format!("{what} {}", path.display()))?;
    if let Some(noise) = scales.noise_m {
        log::info!("map noise about {:.1} mm", noise * 1e3);
    }
    if estimate {
        let report = estimate_normals(&mut cloud, &options)
            .with_context(|| format!("estimating normals of {}", path.display()))?;
        log::info!(
            "map normals ({:.3} m radius): {} kept, {} estimated{}, {} failed",
            options.radius_m,
            report.kept,
            report.estimated,
            report.widened_note(),
            report.failed
        );
    }
    if score {
        let started = std::time::Instant::now();
        let report = planarity_of(&mut cloud, &options)
            .with_context(|| format!("scoring the planarity of {}", path.display()))?;
        let gated = points_below_planarity(&cloud, planarity_gate).unwrap_or(0);
        log::info!(
            "map planarity ({:.3} m radius, normals kept as given): {} scored, {} ({:.1} %) below {} give no plane, {:.1} s",
            options.radius_m,
            report.estimated + report.failed,
            gated,
            100.0 * gated as f64 / cloud.len() as f64,
            planarity_gate,
            started.elapsed().as_secs_f64()
        );
    }
    Ok((cloud, load))
}

pub fn run(args: &MapArgs) -> Result<()> {
    let config = args.config()?;
    check_output(&config.output)?;
    let output_before = crate::io::atomic::OutputSnapshot::take(&config.output);
    let mut files = vec![config.database.as_path(), config.lidar.as_path()];
    files.extend(config.pose_priors.as_deref());
    files.extend(args.options.as_deref());
    let mut folders = Vec::new();
    folders.extend(config.input_model.as_deref());
    folders.extend(config.image_path.as_deref());
    if let Some(why) = output_replaces_input(&config.output, true, &files, &folders) {
        bail!(why);
    }
    let db = read_database(&config.database)
        .with_context(|| format!("reading the database {}", config.database.display()))?;
    if let Some(dir) = &config.image_path {
        let expected = db
            .images
            .values()
            .map(|img| ExpectedImage::new(&img.name, &db.cameras[&img.camera_id]));
        let n = check_image_folder(dir, expected).with_context(|| {
            format!(
                "checking the image folder against the database {}",
                config.database.display()
            )
        })?;
        log::info!("{n} images found in {}", dir.display());
    }
    // The images for the keypoints' refinement on the map's planes (read
    // after mapping, the registered ones only).
    let image_dir = config.image_path.as_deref().filter(|_| {
        config.options.keypoints.refine
            && config.options.association.kind != AssociationKind::None
            && config.input_model.is_none()
    });
    // What may explain a failed run, from the inputs: given with its error.
    let mut hints = init_pose_hints(&config.init_poses);
    let known_poses = known_poses(&db, config.pose_priors.as_deref(), &mut hints)?;
    let gps = gps_positions(&db, config.map_crs.as_ref());
    // Where the run starts: the model to extend, or the initial image(s) at
    // their poses.
    let start = match &config.input_model {
        Some(dir) => {
            let model = read_model(dir)
                .with_context(|| format!("reading the input model {}", dir.display()))?;
            let existing =
                match_to_database(&model, &db, config.fix_existing_images).map_err(|e| {
                    anyhow::anyhow!(
                        "the input model {} does not match the database {}: {e}",
                        dir.display(),
                        config.database.display()
                    )
                })?;
            log::info!(
                "input model {}: {} images, {} points with two or more observations",
                dir.display(),
                existing.poses.len(),
                existing.points.len()
            );
            RunStart::Model(existing)
        }
        None => match positions_start(&db, &config, &known_poses, &gps)? {
            Some(image) => RunStart::Positions(image),
            None => RunStart::InitialPoses(group_starts(&db, &config, &known_poses)?),
        },
    };
    let association = &config.options.association;
    let gate = match association.kind {
        AssociationKind::None => 0.0,
        _ => association.min_planarity,
    };
    let (cloud, load) = load_map_reporting(&config.lidar, config.input_units, gate)?;
    if matches!(start, RunStart::Positions(_)) {
        check_positions_near_map(&gps, &cloud, &config)?;
    }
    let total = db.images.len();
    let bar = super::image_progress_bar(total, "images registered");
    let mut progress = |done: usize, _total: usize| {
        if let Some(bar) = &bar {
            bar.set_position(done as u64);
        }
    };
    let run_log = RunLog::default();
    let inputs = MapperInputs {
        db: &db,
        cloud: &cloud,
        known_poses: &known_poses,
        held_cameras: &BTreeSet::new(),
        run_log: Some(&run_log),
        image_dir,
    };
    let mapping = std::time::Instant::now();
    let out = match &start {
        RunStart::InitialPoses(starts) => map_groups(
            inputs,
            starts,
            config.init_search.as_ref(),
            &config.options,
            &mut progress,
        ),
        RunStart::Model(existing) => extend_model(inputs, existing, &config.options, &mut progress),
        RunStart::Positions(image) => run_mapper_from_positions(
            inputs,
            *image,
            &gps,
            config.init_search.as_ref(),
            &config.options,
            &mut progress,
        )
        .map(|mut out| {
            if let Some(record) = &mut out.report.positions {
                record.crs = config.map_crs.as_ref().map(|c| c.name.clone());
            }
            out
        }),
    };
    let mut out = out
        .with_context(|| {
            format!(
                "mapping {} into the LiDAR map {}",
                config.database.display(),
                config.lidar.display()
            )
        })
        .map_err(|e| {
            // Only a failed run looks at the map's extent.
            hints.extend(outside_the_map(&config.init_poses, &cloud));
            with_hints(e, &hints)
        })?;
    out.report.mapping_s = Some(mapping.elapsed().as_secs_f64());
    // Every run's record; the kept ones are the model's (one per group).
    let kept: BTreeSet<usize> = std::iter::once(out.report.run_index)
        .chain(
            out.report
                .groups
                .iter()
                .map(|g| g.report.as_ref().and_then(|r| r.run_index)),
        )
        .flatten()
        .collect();
    out.report.runs = run_log.records(&kept);
    out.report.map_file = Some(config.lidar.display().to_string());
    out.report.map_points = Some(cloud.len());
    out.report.map_points_below_planarity = points_below_planarity(&cloud, gate);
    out.report.map_units = load.units;
    if let Some(bar) = &bar {
        bar.finish_and_clear();
    }
    if let Some(dir) = &config.image_path {
        let t = std::time::Instant::now();
        let summary = colour_points(&mut out.reconstruction, dir)
            .context("colouring the points from the images")?;
        let time_s = t.elapsed().as_secs_f64();
        log::info!(
            "coloured {} points from {} observations in {} images ({time_s:.1} s)",
            summary.points_coloured,
            summary.observations_sampled,
            summary.images_read
        );
        if !summary.unread.is_empty() {
            log::warn!(
                "{} images could not be read for the colours (report.json: point_colours.unread); \
                 their points take their colour from the other images",
                summary.unread.len()
            );
        }
        out.report
            .stages
            .push(StageRecord::new("point colours", time_s));
        out.report.point_colours = Some(summary);
    }
    let report_json =
        serde_json::to_string_pretty(&out.report).context("serialising the report")?;
    output_before.check_unchanged(&config.output)?;
    crate::io::atomic::write_dir_atomically(&config.output, |tmp| -> Result<()> {
        write_model(tmp, &out.reconstruction, config.format)?;
        std::fs::write(tmp.join("report.json"), format!("{report_json}\n"))?;
        std::fs::write(
            tmp.join("pose.ply"),
            format_model_pose_ply(&out.reconstruction),
        )?;
        Ok(())
    })
    .with_context(|| format!("writing the model to {}", config.output.display()))?;
    println!(
        "registered {}/{} images, {} points, mean reprojection error {:.3} px, mapped in {:.1} s; model in {}",
        out.report.num_registered,
        out.report.num_images,
        out.report.num_points,
        out.report.mean_reprojection_error_px,
        out.report.mapping_s.unwrap_or(f64::NAN),
        config.output.display()
    );
    for g in &out.report.groups {
        if let Some(error) = &g.error {
            println!(
                "  group of {}: FAILED, its {} images left out of the model ({:.1} s): {error}",
                g.init_image, g.num_images, g.mapping_s
            );
            continue;
        }
        println!(
            "  group of {}: {}/{} images, {} points, {:.1} s{}",
            g.init_image,
            g.num_registered,
            g.num_images,
            g.num_points,
            g.mapping_s,
            if g.cameras_held.is_empty() {
                String::new()
            } else {
                format!(
                    ", intrinsics of cameras {:?} held as an earlier group's run gave them",
                    g.cameras_held
                )
            }
        );
    }
    if let Some(summary) = out.report.not_registered_summary() {
        log::warn!("{summary}");
    }
    for c in &out.report.intrinsics {
        if c.refined != "held" {
            println!(
                "camera {} ({}): intrinsics refined in {}, focal length {:+.3} %: {} -> {}",
                c.camera_id,
                c.model,
                c.refined,
                c.focal_change * 100.0,
                fmt_params(&c.database_params),
                fmt_params(&c.final_params)
            );
        }
    }
    if let Some(u) = &out.report.pose_uncertainty {
        println!(
            "pose uncertainty (1 sigma, from the final solve's information; report.json per image): \
             camera centre median {:.1} mm, max {:.1} mm along the least determined direction; \
             rotation median {:.3} deg",
            u.median_centre_sigma_major_m * 1e3,
            u.max_centre_sigma_major_m * 1e3,
            u.median_rotation_sigma_deg
        );
        if let (Some(c), Some(m), Some(r)) = (
            u.median_clustered_centre_sigma_major_m,
            u.max_clustered_centre_sigma_major_m,
            u.median_clustered_rotation_sigma_deg,
        ) {
            println!(
                "  cluster-robust (residuals that err together in a cube count once; \
                 closer to the true errors on the synthetic scenes): centre median {:.1} mm, \
                 max {:.1} mm; rotation median {:.3} deg",
                c * 1e3,
                m * 1e3,
                r
            );
        }
    }
    Ok(())
}

/// Camera parameters for a summary line (6 decimals, trailing zeros dropped).
fn fmt_params(params: &[f64]) -> String {
    params
        .iter()
        .map(|p| {
            format!("{p:.6}")
                .trim_end_matches('0')
                .trim_end_matches('.')
                .to_string()
        })
        .collect::<Vec<_>>()
        .join(",")
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    fn pose([x, y, z, roll, pitch, yaw]: [f64; 6]) -> BodyPose {
        BodyPose::from_degrees(Vector3::new(x, y, z), roll, pitch, yaw)
    }

    #[test]
    fn hints_name_radians_and_a_centre_outside_the_map() {
        // Radians where degrees are read: a hint with the degrees; a pose in
        // degrees, or a level one facing +x, none.
        let hints = init_pose_hints(&[
            pose([0.0, -1.6, 1.5, 0.0089, -0.0051, -1.3089]),
            pose([0.0, -1.6, 1.5, 0.5, -0.3, -75.0]),
            pose([0.0, -1.6, 1.5, 0.0, 0.0, 0.0]),
        ]);
        assert_eq!(hints.len(), 1, "{hints:?}");
        assert!(
            hints[0].contains("if they are radians, give 0.5099,-0.2922,-74.9944"),
            "{}",
            hints[0]
        );
        // A room from (0, 0, 0) to (4, 3, 2.5): a centre below the floor is
        // named with how far, one inside is not.
        let cloud = PointCloud {
            origin: Vector3::zeros(),
            points: vec![[0.0, 0.0, 0.0], [4.0, 3.0, 2.5]],
            normals: None,
            planarity: None,
        };
        let hints = outside_the_map(
            &[
                pose([2.0, 1.0, -1.5, 0.0, 0.0, 90.0]),
                pose([2.0, 1.0, 1.5, 0.0, 0.0, 90.0]),
            ],
            &cloud,
        );
        assert_eq!(hints.len(), 1, "{hints:?}");
        assert!(
            hints[0].contains("z 1.50 m below the map's least"),
            "{}",
            hints[0]
        );
        // The hints follow the error, one per line; none: the error as it was.
        let e = with_hints(anyhow::anyhow!("cause").context("mapping"), &hints);
        assert!(format!("{e:#}")
            .starts_with("mapping: cause\nwhat may explain it:\n  - --init-pose puts"));
        let e = with_hints(anyhow::anyhow!("cause").context("mapping"), &[]);
        assert_eq!(format!("{e:#}"), "mapping: cause");
    }
}
