//! COLMAP model files (cameras, images, points3D), text and binary.
//!
//! Layouts (COLMAP 3.8, checked against the real `colmap model_converter`):
//!
//! * `cameras.txt`: `CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]`.
//! * `images.txt`: two lines per image, `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`
//!   then `X Y POINT3D_ID ...` (`-1` for a keypoint without a 3D point; the line is
//!   empty when the image has no keypoints).
//! * `points3D.txt`: `POINT3D_ID X Y Z R G B ERROR TRACK[]`, the track as
//!   `IMAGE_ID POINT2D_IDX` pairs.
//! * `cameras.bin`: u64 count; per camera u32 id, i32 model id, u64 width, u64 height,
//!   f64 params.
//! * `images.bin`: u64 count; per image u32 id, f64 qw qx qy qz, f64 tx ty tz, u32
//!   camera id, the name NUL-terminated, u64 number of keypoints, per keypoint f64 x,
//!   f64 y, u64 3D point id (`u64::MAX` for none).
//! * `points3D.bin`: u64 count; per point u64 id, f64 x y z, u8 r g b, f64 error,
//!   u64 track length, per element u32 image id, u32 keypoint index.
//!
//! All integers and floats are little-endian. Text lines starting with `#` and empty
//! lines are comments (except the keypoint line of an image, which may be empty).
//!
//! Writing: only registered images (`cam_from_world.is_some()`) are written, all
//! records in increasing id order, floats in Rust's shortest round-trip notation, so
//! reading gives back bit-identical values and the same model gives the same bytes.
//! The output folder is written atomically and replaced as a whole (stale files of
//! the other format disappear); a folder holding anything but model files is refused.
//!
//! Reading checks the model for consistency (cameras of images exist, every keypoint's
//! 3D point exists and lists that keypoint in its track, every track element names an
//! image and a keypoint that exist and point back) and reports any problem with the
//! file and line (text) or record and byte offset (binary). Quaternions are kept as
//! written when their norm is within 1e-12 of one (so round trips are exact) and
//! normalised otherwise.
//!
//! Image names: text names are the rest of the line after `CAMERA_ID`, so names with
//! inner spaces round-trip through our reader, but COLMAP 3.8's own text reader
//! truncates them at the first space (its binary reader keeps them). Names must be
//! non-empty, without leading or trailing whitespace, and without line breaks or NUL.
mod binary;
mod text;

use std::collections::{BTreeMap, BTreeSet};
use std::fmt;
use std::io;
use std::path::{Path, PathBuf};

use nalgebra::{Quaternion, UnitQuaternion, Vector3};

use crate::scene::camera::bad_image_size;
use crate::scene::{Camera, Image, ImageId, Point3D, Point3DId, Reconstruction, Rigid3};

/// The two on-disk encodings of a COLMAP model.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ModelFormat {
    /// `cameras.txt`, `images.txt`, `points3D.txt`.
    Text,
    /// `cameras.bin`, `images.bin`, `points3D.bin`.
    Binary,
}

impl ModelFormat {
    /// File extension without the dot.
    pub fn extension(self) -> &'static str {
        match self {
            ModelFormat::Text => "txt",
            ModelFormat::Binary => "bin",
        }
    }

    /// Paths of the three files of a model in `dir`: cameras, images, points3D.
    pub fn paths(self, dir: &Path) -> [PathBuf; 3] {
        let ext = self.extension();
        [
            dir.join(format!("cameras.{ext}")),
            dir.join(format!("images.{ext}")),
            dir.join(format!("points3D.{ext}")),
        ]
    }
}

/// Errors reading or writing a model. Every variant names the file or folder.
#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: io::Error,
    },
    /// Malformed or inconsistent text file; `line` is 1-based.
    #[error("{}:{line}: {msg}", path.display())]
    Text {
        path: PathBuf,
        line: usize,
        msg: String,
    },
    /// Malformed or inconsistent binary file. `record` is the 0-based index of the
    /// camera, image or point (`None` for the count header); `offset` is the byte
    /// offset of the problem (of the record's start for consistency problems).
    #[error("{}: {}byte offset {offset}: {msg}", path.display(), RecordPrefix(*record))]
    Binary {
        path: PathBuf,
        record: Option<u64>,
        offset: u64,
        msg: String,
    },
    #[error("{}: no COLMAP model (cameras, images, points3D as .bin or .txt)", dir.display())]
    NotFound { dir: PathBuf },
    #[error("{}: incomplete model, {} is missing", dir.display(), missing.display())]
    Incomplete { dir: PathBuf, missing: PathBuf },
    /// The reconstruction cannot be written as a valid COLMAP model.
    #[error("cannot write a model to {}: {msg}", dir.display())]
    InvalidModel { dir: PathBuf, msg: String },
    /// The output path is not a folder, or holds files that are not part of a
    /// COLMAP model (it would be replaced as a whole).
    #[error("refusing to replace {}: {reason}", dir.display())]
    WouldClobber { dir: PathBuf, reason: String },
}

struct RecordPrefix(Option<u64>);

impl fmt::Display for RecordPrefix {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.0 {
            Some(r) => write!(f, "record {r}, "),
            None => write!(f, "header, "),
        }
    }
}

/// Where a record came from, to name it in errors found after parsing.
#[derive(Clone, Copy, Debug)]
enum Loc {
    /// 1-based line number.
    Line(usize),
    /// 0-based record index and byte offset of its start.
    Record { index: u64, offset: u64 },
}

impl Loc {
    fn error(self, path: &Path, msg: impl Into<String>) -> ModelError {
        match self {
            Loc::Line(line) => ModelError::Text {
                path: path.to_path_buf(),
                line,
                msg: msg.into(),
            },
            Loc::Record { index, offset } => ModelError::Binary {
                path: path.to_path_buf(),
                record: Some(index),
                offset,
                msg: msg.into(),
            },
        }
    }
}

/// An image as parsed, before consistency checks. `pose_loc` is the image's first
/// line (text) or record; `points_loc` its keypoint line (same as `pose_loc` in binary).
struct ParsedImage {
    image: Image,
    pose_loc: Loc,
    points_loc: Loc,
}

/// The three files as parsed, in file order, before consistency checks.
struct ParsedModel {
    paths: [PathBuf; 3],
    cameras: Vec<(Camera, Loc)>,
    images: Vec<ParsedImage>,
    points: Vec<(Point3DId, Point3D, Loc)>,
}

/// A quaternion as read from a file: kept bit-exact when (numerically) unit, else
/// normalised. `None` when it is zero or not finite.
fn rotation_from_file(q_wxyz: [f64; 4]) -> Option<UnitQuaternion<f64>> {
    let q = Quaternion::new(q_wxyz[0], q_wxyz[1], q_wxyz[2], q_wxyz[3]);
    let norm = q.norm();
    if !norm.is_finite() || norm == 0.0 {
        return None;
    }
    if (norm - 1.0).abs() <= 1e-12 {
        Some(UnitQuaternion::new_unchecked(q))
    } else {
        Some(UnitQuaternion::from_quaternion(q))
    }
}

/// An image's pose as read from a file, or why it is not one.
fn pose_from_file(q_wxyz: [f64; 4], t: [f64; 3]) -> Result<Rigid3, String> {
    let rotation = rotation_from_file(q_wxyz)
        .ok_or_else(|| format!("QW QX QY QZ = {q_wxyz:?} is not a valid rotation"))?;
    if !t.iter().all(|v| v.is_finite()) {
        return Err(format!("TX TY TZ = {t:?} is not finite"));
    }
    Ok(Rigid3::new(rotation, Vector3::from(t)))
}

/// Why a camera read from a file cannot be used: an image size no camera
/// has ([`bad_image_size`]) or a parameter that is not finite.
fn bad_camera(camera: &Camera) -> Option<String> {
    if let Some(why) = bad_image_size(u64::from(camera.width), u64::from(camera.height)) {
        return Some(why);
    }
    let names = camera.model.param_names();
    let (i, p) = camera
        .params
        .iter()
        .enumerate()
        .find(|(_, p)| !p.is_finite())?;
    let name = names
        .get(i)
        .map_or_else(|| format!("{}", i + 1), |n| n.to_string());
    Some(format!("parameter {name} is {p}"))
}

/// Why a 3D point's or keypoint's coordinates read from a file cannot be
/// used: one is not finite.
fn bad_coordinates(what: &str, xyz: &[f64]) -> Option<String> {
    (!xyz.iter().all(|v| v.is_finite())).then(|| format!("{what} {xyz:?} is not finite"))
}

/// Why an image name cannot be written, if it cannot.
fn bad_name_reason(name: &str) -> Option<&'static str> {
    if name.is_empty() {
        Some("empty")
    } else if name.contains(['\n', '\r', '\0']) {
        Some("contains a line break or NUL")
    } else if name.trim() != name {
        Some("has leading or trailing whitespace")
    } else {
        None
    }
}

impl ParsedModel {
    /// Builds the reconstruction, checking ids and cross-references.
    fn assemble(self) -> Result<Reconstruction, ModelError> {
        let [cam_path, img_path, pts_path] = &self.paths;
        let mut rec = Reconstruction::default();

        for (camera, loc) in self.cameras {
            if camera.params.len() != camera.model.num_params() {
                return Err(loc.error(
                    cam_path,
                    format!(
                        "camera {}: model {} takes {} parameters, found {}",
                        camera.id,
                        camera.model.name(),
                        camera.model.num_params(),
                        camera.params.len()
                    ),
                ));
            }
            if rec.cameras.contains_key(&camera.id) {
                return Err(loc.error(cam_path, format!("duplicate CAMERA_ID {}", camera.id)));
            }
            rec.cameras.insert(camera.id, camera);
        }

        let mut image_locs: BTreeMap<ImageId, Loc> = BTreeMap::new();
        for parsed in self.images {
            let image = parsed.image;
            if rec.images.contains_key(&image.id) {
                return Err(parsed
                    .pose_loc
                    .error(img_path, format!("duplicate IMAGE_ID {}", image.id)));
            }
            if !rec.cameras.contains_key(&image.camera_id) {
                return Err(parsed.pose_loc.error(
                    img_path,
                    format!(
                        "image {}: CAMERA_ID {} is not in {}",
                        image.id,
                        image.camera_id,
                        cam_path.display()
                    ),
                ));
            }
            image_locs.insert(image.id, parsed.points_loc);
            rec.images.insert(image.id, image);
        }

        // Every (point, image, keypoint) listed in some track.
        let mut observed: BTreeSet<(Point3DId, ImageId, u32)> = BTreeSet::new();
        for (id, point, loc) in self.points {
            if rec.points3d.contains_key(&id) {
                return Err(loc.error(pts_path, format!("duplicate POINT3D_ID {id}")));
            }
            for el in &point.track {
                let Some(image) = rec.images.get(&el.image_id) else {
                    return Err(loc.error(
                        pts_path,
                        format!(
                            "point {id}: track refers to IMAGE_ID {}, which is not in {}",
                            el.image_id,
                            img_path.display()
                        ),
                    ));
                };
                let back = image
                    .points2d
                    .get(el.point2d_idx as usize)
                    .map(|p| p.point3d_id);
                match back {
                    None => {
                        return Err(loc.error(
                            pts_path,
                            format!(
                                "point {id}: track refers to POINT2D_IDX {} of image {}, \
                                 which has {} keypoints",
                                el.point2d_idx,
                                el.image_id,
                                image.points2d.len()
                            ),
                        ))
                    }
                    Some(back) if back != Some(id) => {
                        return Err(loc.error(
                            pts_path,
                            format!(
                                "point {id}: track element (image {}, keypoint {}) \
                                 observes {} in {}",
                                el.image_id,
                                el.point2d_idx,
                                back.map_or("no point".to_string(), |b| format!("point {b}")),
                                img_path.display()
                            ),
                        ))
                    }
                    Some(_) => {}
                }
                if !observed.insert((id, el.image_id, el.point2d_idx)) {
                    return Err(loc.error(
                        pts_path,
                        format!(
                            "point {id}: track lists (image {}, keypoint {}) twice",
                            el.image_id, el.point2d_idx
                        ),
                    ));
                }
            }
            rec.points3d.insert(id, point);
        }

        for image in rec.images.values() {
            for (idx, p) in image.points2d.iter().enumerate() {
                let Some(pid) = p.point3d_id else { continue };
                // Indexing cannot panic: every image was inserted with its location.
                let loc = image_locs[&image.id];
                if !rec.points3d.contains_key(&pid) {
                    return Err(loc.error(
                        img_path,
                        format!(
                            "image {}: keypoint {idx} refers to POINT3D_ID {pid}, which is not in {}",
                            image.id,
                            pts_path.display()
                        ),
                    ));
                }
                if !observed.contains(&(pid, image.id, idx as u32)) {
                    return Err(loc.error(
                        img_path,
                        format!(
                            "image {}: keypoint {idx} refers to POINT3D_ID {pid}, whose track \
                             does not list it",
                            image.id
                        ),
                    ));
                }
            }
        }
        Ok(rec)
    }
}

/// Reads a model from `dir`, binary if `cameras.bin`, `images.bin` and `points3D.bin`
/// are all there (as COLMAP does), otherwise text.
pub fn read_model(dir: &Path) -> Result<Reconstruction, ModelError> {
    match detect_format(dir)? {
        ModelFormat::Binary => read_binary_model(dir),
        ModelFormat::Text => read_text_model(dir),
    }
}

/// Which format the model in `dir` is stored in. Errors when neither a complete
/// binary nor a complete text model is there, naming the first missing file.
pub fn detect_format(dir: &Path) -> Result<ModelFormat, ModelError> {
    let mut first_missing = None;
    for format in [ModelFormat::Binary, ModelFormat::Text] {
        let paths = format.paths(dir);
        let present: Vec<bool> = paths.iter().map(|p| p.is_file()).collect();
        if present.iter().all(|&p| p) {
            return Ok(format);
        }
        if first_missing.is_none() && present.iter().any(|&p| p) {
            // Not all three are present (checked above), so one is missing.
            let missing = present.iter().position(|&p| !p).unwrap_or(0);
            first_missing = Some(paths[missing].clone());
        }
    }
    Err(match first_missing {
        Some(missing) => ModelError::Incomplete {
            dir: dir.to_path_buf(),
            missing,
        },
        None => ModelError::NotFound {
            dir: dir.to_path_buf(),
        },
    })
}

/// Reads `cameras.txt`, `images.txt` and `points3D.txt` from `dir`.
pub fn read_text_model(dir: &Path) -> Result<Reconstruction, ModelError> {
    text::read(dir)?.assemble()
}

/// Reads `cameras.bin`, `images.bin` and `points3D.bin` from `dir`.
pub fn read_binary_model(dir: &Path) -> Result<Reconstruction, ModelError> {
    binary::read(dir)?.assemble()
}

/// Checks that `rec` can be written as a COLMAP model that reads back identically:
/// parameter counts, image names, references between the registered images and the
/// points (a track may only name registered images), reserved ids.
pub fn check_writable(rec: &Reconstruction) -> Result<(), String> {
    for (id, camera) in &rec.cameras {
        if *id != camera.id {
            return Err(format!("camera stored under id {id} has id {}", camera.id));
        }
        if camera.params.len() != camera.model.num_params() {
            return Err(format!(
                "camera {id}: model {} takes {} parameters, has {}",
                camera.model.name(),
                camera.model.num_params(),
                camera.params.len()
            ));
        }
    }
    for (id, image) in &rec.images {
        if *id != image.id {
            return Err(format!("image stored under id {id} has id {}", image.id));
        }
        if !image.is_registered() {
            continue;
        }
        if !rec.cameras.contains_key(&image.camera_id) {
            return Err(format!(
                "image {id}: camera {} does not exist",
                image.camera_id
            ));
        }
        if let Some(reason) = bad_name_reason(&image.name) {
            return Err(format!("image {id}: name {:?} is {reason}", image.name));
        }
        if u32::try_from(image.points2d.len()).is_err() {
            return Err(format!("image {id}: too many keypoints"));
        }
        for (idx, p) in image.points2d.iter().enumerate() {
            let Some(pid) = p.point3d_id else { continue };
            let listed = rec.points3d.get(&pid).is_some_and(|pt| {
                pt.track
                    .iter()
                    .any(|el| el.image_id == *id && el.point2d_idx as usize == idx)
            });
            if !listed {
                return Err(format!(
                    "image {id}: keypoint {idx} refers to point {pid}, which does not exist \
                     or whose track does not list it"
                ));
            }
        }
    }
    for (id, point) in &rec.points3d {
        if id.0 == u64::MAX {
            return Err(format!("point id {id} is reserved for \"no point\""));
        }
        let mut seen = BTreeSet::new();
        for el in &point.track {
            let back = rec
                .images
                .get(&el.image_id)
                .filter(|im| im.is_registered())
                .and_then(|im| im.points2d.get(el.point2d_idx as usize))
                .map(|p| p.point3d_id);
            if back != Some(Some(*id)) {
                return Err(format!(
                    "point {id}: track element (image {}, keypoint {}) does not exist, is not \
                     registered or does not observe this point",
                    el.image_id, el.point2d_idx
                ));
            }
            if !seen.insert(*el) {
                return Err(format!(
                    "point {id}: track lists (image {}, keypoint {}) twice",
                    el.image_id, el.point2d_idx
                ));
            }
        }
    }
    Ok(())
}

/// Writes `rec` to `dir` in `format`, atomically: the files are written into a
/// temporary sibling folder which then replaces `dir` as a whole. Refuses (before
/// writing anything) when `dir` exists and holds anything but COLMAP model files,
/// or when `rec` fails [`check_writable`].
pub fn write_model(
    dir: &Path,
    rec: &Reconstruction,
    format: ModelFormat,
) -> Result<(), ModelError> {
    check_writable(rec).map_err(|msg| ModelError::InvalidModel {
        dir: dir.to_path_buf(),
        msg,
    })?;
    check_replaceable(dir)?;
    if format == ModelFormat::Text {
        let spaced = rec
            .registered_images()
            .filter(|im| im.name.contains(char::is_whitespace))
            .count();
        if spaced > 0 {
            log::warn!(
                "{}: {spaced} image names contain spaces; COLMAP 3.8's text reader cuts \
                 them at the first space (its binary reader and ours keep them)",
                dir.display()
            );
        }
    }
    crate::io::atomic::write_dir_atomically(dir, |tmp| {
        let result = match format {
            ModelFormat::Text => text::write(tmp, rec),
            ModelFormat::Binary => binary::write(tmp, rec),
        };
        result.map_err(WriteError::Model)
    })
    .map_err(|e| match e {
        WriteError::Model(e) => e,
        WriteError::Io(source) => ModelError::Io {
            path: dir.to_path_buf(),
            source,
        },
    })
}

/// Files that may be in a model folder we replace.
const MODEL_FILE_NAMES: [&str; 11] = [
    "cameras.txt",
    "images.txt",
    "points3D.txt",
    "cameras.bin",
    "images.bin",
    "points3D.bin",
    "project.ini",
    "rigs.txt",
    "rigs.bin",
    "frames.txt",
    "frames.bin",
];

fn check_replaceable(dir: &Path) -> Result<(), ModelError> {
    let io_err = |source| ModelError::Io {
        path: dir.to_path_buf(),
        source,
    };
    let meta = match std::fs::symlink_metadata(dir) {
        Ok(meta) => meta,
        Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(()),
        Err(e) => return Err(io_err(e)),
    };
    if !meta.is_dir() {
        return Err(ModelError::WouldClobber {
            dir: dir.to_path_buf(),
            reason: "it is not a folder (or is a symbolic link)".to_string(),
        });
    }
    let mut names = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(io_err)? {
        names.push(entry.map_err(io_err)?.file_name());
    }
    names.sort();
    for name in names {
        let name = name.to_string_lossy().into_owned();
        if !MODEL_FILE_NAMES.contains(&name.as_str()) {
            return Err(ModelError::WouldClobber {
                dir: dir.to_path_buf(),
                reason: format!("it contains {name:?}, which is not a COLMAP model file"),
            });
        }
    }
    Ok(())
}

/// Errors inside the atomic writer: ours, or its own renames.
enum WriteError {
    Model(ModelError),
    Io(io::Error),
}

impl From<io::Error> for WriteError {
    fn from(e: io::Error) -> Self {
        WriteError::Io(e)
    }
}

/// Mean number of keypoints with a 3D point per registered image (0 without images).
fn mean_observations_per_image(rec: &Reconstruction) -> f64 {
    let (n, obs) = rec
        .registered_images()
        .fold((0usize, 0usize), |(n, obs), im| {
            (n + 1, obs + im.num_points3d())
        });
    if n == 0 {
        0.0
    } else {
        obs as f64 / n as f64
    }
}

/// Mean track length (0 without points).
fn mean_track_length(rec: &Reconstruction) -> f64 {
    if rec.points3d.is_empty() {
        return 0.0;
    }
    let total: usize = rec.points3d.values().map(|p| p.track.len()).sum();
    total as f64 / rec.points3d.len() as f64
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::CameraId;
    use rand::{Rng, SeedableRng};

    const CAMERAS_TXT: &str =
        "# c\n1 PINHOLE 100 80 50 51 50 40\n7 OPENCV 9 9 5 5 4 4 0.1 -0.2 1e-3 2e-4\n";
    const IMAGES_TXT: &str = "# i\n\
        3 1 0 0 0 0 0 0 1 a b.jpg\n1 2 7 -1 5 -1 4.5 6 8\n\
        4 0 1 0 0 1 2 3 7 c.jpg\n9 9 7 3 3 8\n\
        5 0 0 1 0 -1 -2 -3 7 d.jpg\n\n";
    const POINTS_TXT: &str =
        "# p\n7 1 2 3 255 0 10 0.5 3 0 4 0\n8 -1 -2 -3 1 2 3 0.25 3 2 4 1\n9 0 0 0 0 0 0 0\n";

    fn encode(rec: &Reconstruction, format: ModelFormat) -> [Vec<u8>; 3] {
        let mut files = [Vec::new(), Vec::new(), Vec::new()];
        let result = match format {
            ModelFormat::Text => text::write_cameras(&mut files[0], rec)
                .and_then(|_| text::write_images(&mut files[1], rec))
                .and_then(|_| text::write_points(&mut files[2], rec)),
            ModelFormat::Binary => binary::write_cameras(&mut files[0], rec)
                .and_then(|_| binary::write_images(&mut files[1], rec))
                .and_then(|_| binary::write_points(&mut files[2], rec)),
        };
        result.expect("writing to memory cannot fail");
        files
    }

    fn decode(files: [&[u8]; 3], format: ModelFormat) -> Result<Reconstruction, ModelError> {
        let dir = Path::new("model");
        match format {
            ModelFormat::Text => text::read_bytes(dir, files)?.assemble(),
            ModelFormat::Binary => binary::read_bytes(dir, files)?.assemble(),
        }
    }

    /// Every truncation and thousands of random corruptions of every file, in both
    /// formats: errors name a model file, nothing panics, and a truncated binary file
    /// is always an error naming that file.
    #[test]
    fn fuzzed_files_give_errors_not_panics() {
        let text_files = [CAMERAS_TXT, IMAGES_TXT, POINTS_TXT].map(str::as_bytes);
        let rec = decode(text_files, ModelFormat::Text).unwrap();
        assert_eq!(
            (rec.cameras.len(), rec.images.len(), rec.points3d.len()),
            (2, 3, 3)
        );
        assert_eq!(rec.images[&ImageId(3)].name, "a b.jpg");
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        for format in [ModelFormat::Text, ModelFormat::Binary] {
            let files = encode(&rec, format);
            let names = ModelFormat::paths(format, Path::new("model"))
                .map(|p| p.file_name().unwrap().to_string_lossy().into_owned());
            assert_eq!(
                decode([&files[0], &files[1], &files[2]], format).unwrap(),
                rec
            );
            let check = |which: usize, bytes: &[u8]| -> bool {
                let mut inputs: [&[u8]; 3] = [&files[0], &files[1], &files[2]];
                inputs[which] = bytes;
                match decode(inputs, format) {
                    Ok(_) => false,
                    Err(e) => {
                        let msg = e.to_string();
                        let named = match format {
                            ModelFormat::Binary => msg.contains(&names[which]),
                            ModelFormat::Text => names.iter().any(|n| msg.contains(n)),
                        };
                        assert!(named, "{msg}");
                        true
                    }
                }
            };
            for which in 0..3 {
                let full = &files[which];
                let mut errors = 0;
                for len in 0..full.len() {
                    errors += usize::from(check(which, &full[..len]));
                }
                if format == ModelFormat::Binary {
                    assert_eq!(errors, full.len(), "{}", names[which]);
                } else {
                    assert!(errors > full.len() / 2, "{}", names[which]);
                }
                for _ in 0..3000 {
                    let mut bytes = full.clone();
                    for _ in 0..rng.gen_range(1..4) {
                        let i = rng.gen_range(0..bytes.len());
                        bytes[i] = if format == ModelFormat::Text && rng.gen_bool(0.7) {
                            b" -#\n0123456789e.x"[rng.gen_range(0..17)]
                        } else {
                            rng.gen()
                        };
                    }
                    check(which, &bytes);
                }
                for _ in 0..200 {
                    let garbage: Vec<u8> = (0..rng.gen_range(0..300)).map(|_| rng.gen()).collect();
                    check(which, &garbage);
                }
            }
        }
    }

    /// Values no model can hold, written by our own writers in both
    /// formats: each read is an error naming the file and the value.
    #[test]
    fn sizes_and_values_no_model_holds_are_errors() {
        let text_files = [CAMERAS_TXT, IMAGES_TXT, POINTS_TXT].map(str::as_bytes);
        let good = decode(text_files, ModelFormat::Text).unwrap();
        let (camera, image, point) = (CameraId(1), ImageId(3), Point3DId(7));
        type Spoil = fn(&mut Reconstruction, CameraId, ImageId, Point3DId);
        let cases: [(Spoil, usize, &str); 8] = [
            (
                |r, c, _, _| r.cameras.get_mut(&c).unwrap().width = u32::MAX,
                0,
                "side over 100000",
            ),
            (
                |r, c, _, _| r.cameras.get_mut(&c).unwrap().height = 0,
                0,
                "is empty",
            ),
            (
                |r, c, _, _| {
                    let cam = r.cameras.get_mut(&c).unwrap();
                    (cam.width, cam.height) = (40_000, 40_000);
                },
                0,
                "over 1073741824 pixels",
            ),
            (
                |r, c, _, _| r.cameras.get_mut(&c).unwrap().params[1] = f64::NAN,
                0,
                "parameter fy is NaN",
            ),
            (
                |r, _, i, _| {
                    let pose = r
                        .images
                        .get_mut(&i)
                        .unwrap()
                        .cam_from_world
                        .as_mut()
                        .unwrap();
                    pose.translation.y = f64::INFINITY;
                },
                1,
                "TX TY TZ = [",
            ),
            (
                |r, _, i, _| r.images.get_mut(&i).unwrap().points2d[0].xy.x = f64::NAN,
                1,
                "keypoint 0 [NaN",
            ),
            (
                |r, _, _, p| r.points3d.get_mut(&p).unwrap().xyz.z = f64::NAN,
                2,
                "X Y Z [1.0, 2.0, NaN]",
            ),
            (
                |r, _, _, p| r.points3d.get_mut(&p).unwrap().xyz.x = -f64::INFINITY,
                2,
                "is not finite",
            ),
        ];
        for format in [ModelFormat::Text, ModelFormat::Binary] {
            let names = ModelFormat::paths(format, Path::new("model"))
                .map(|p| p.file_name().unwrap().to_string_lossy().into_owned());
            for (spoil, file, says) in cases {
                let mut bad = good.clone();
                spoil(&mut bad, camera, image, point);
                let files = encode(&bad, format);
                let err = decode([&files[0], &files[1], &files[2]], format)
                    .expect_err(says)
                    .to_string();
                assert!(
                    err.contains(says) && err.contains(&names[file]),
                    "{format:?}: {err}"
                );
            }
        }
    }

    #[test]
    fn unit_quaternion_is_kept_bit_exact_and_others_normalised() {
        let q = UnitQuaternion::from_euler_angles(0.3, -1.2, 2.0);
        let wxyz = [q.w, q.i, q.j, q.k];
        let back = rotation_from_file(wxyz).unwrap();
        assert_eq!([back.w, back.i, back.j, back.k], wxyz);
        let scaled = rotation_from_file([2.0, 0.0, 0.0, 0.0]).unwrap();
        assert_eq!(
            [scaled.w, scaled.i, scaled.j, scaled.k],
            [1.0, 0.0, 0.0, 0.0]
        );
        assert!(rotation_from_file([0.0; 4]).is_none());
        assert!(rotation_from_file([f64::NAN, 0.0, 0.0, 1.0]).is_none());
    }

    #[test]
    fn names() {
        assert_eq!(bad_name_reason("a b/c.jpg"), None);
        assert!(bad_name_reason("").is_some());
        assert!(bad_name_reason(" a.jpg").is_some());
        assert!(bad_name_reason("a\nb.jpg").is_some());
        assert!(bad_name_reason("a\0b.jpg").is_some());
    }
}
