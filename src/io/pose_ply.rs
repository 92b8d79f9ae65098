//! The reference implementation's `pose.ply` pose files: one body pose per COLMAP
//! image id. Read as per-image pose priors (`--pose-priors FILE`) and written next
//! to the output model.
//!
//! Layout: an ASCII PLY header with one `vertex` element of six properties
//! `x y z roll pitch yaw` (float or double), then data line k (k = 1, 2, ...)
//! holds the pose of the image with COLMAP image id k:
//!
//! ```text
//! ply
//! format ascii 1.0
//! comment any number of comment lines
//! element vertex 3
//! property double x
//! property double y
//! property double z
//! property double roll
//! property double pitch
//! property double yaw
//! end_header
//! 500000.25 4400000.5 12 0 0.1 1.5707963267948966
//! nan nan nan nan nan nan
//! 500001.25 4400000.5 12 0 0.1 1.6
//! ```
//!
//! `x y z` is the camera centre in the map frame (metres); `roll pitch yaw` are
//! the body-convention angles of [`BodyPose`] (method.md section 2) in RADIANS.
//! A line of six `nan` (any case, any sign) means "no pose for this id".
//!
//! Reading is tolerant about the header and line ends (comment and `obj_info`
//! lines, float or double properties, CRLF, a UTF-8 byte order mark, trailing
//! empty lines, a vertex count that disagrees with the data: a warning, and the
//! lines present are used) and strict about the data: every line must hold six
//! finite numbers or six nans, otherwise the error names the file, the line and
//! the image id.
use std::collections::BTreeMap;
use std::io::{self, Write};
use std::path::{Path, PathBuf};

use nalgebra::Vector3;

use crate::io::atomic::write_file_atomically;
use crate::scene::{BodyPose, ImageId};

/// The six vertex properties, in file order.
const PROPERTY_NAMES: [&str; 6] = ["x", "y", "z", "roll", "pitch", "yaw"];

/// Property types accepted in the header (the values are parsed as f64 anyway).
const PROPERTY_TYPES: [&str; 4] = ["float", "double", "float32", "float64"];

/// Why reading or writing a pose file failed. Every message names the file.
#[derive(Debug, thiserror::Error)]
pub enum PosePlyError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: io::Error },
    /// The header is missing or not the pose layout. `line` is 1-based.
    #[error("{path}: line {line}: {detail}")]
    Header {
        path: PathBuf,
        line: usize,
        detail: String,
    },
    /// The file ended before `end_header`.
    #[error("{path}: no `end_header` line: a pose file needs the PLY header (ply, format ascii 1.0, element vertex N, properties x y z roll pitch yaw, end_header)")]
    MissingEndHeader { path: PathBuf },
    /// A data line is malformed. `line` is the 1-based line number in the file.
    #[error("{path}: line {line} (image id {image_id}): {detail}")]
    Data {
        path: PathBuf,
        line: usize,
        image_id: u64,
        detail: String,
    },
    /// A pose that cannot be written (image id 0, non-finite values).
    #[error("{path}: cannot write the pose of image id {image_id}: {detail}")]
    Unwritable {
        path: PathBuf,
        image_id: ImageId,
        detail: String,
    },
}

/// Reads a pose file. See the module doc for the layout.
pub fn read_pose_ply(path: &Path) -> Result<BTreeMap<ImageId, BodyPose>, PosePlyError> {
    let bytes = std::fs::read(path).map_err(|source| PosePlyError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let text = String::from_utf8(bytes).map_err(|e| PosePlyError::Header {
        path: path.to_path_buf(),
        line: 1 + e.as_bytes()[..e.utf8_error().valid_up_to()]
            .iter()
            .filter(|&&b| b == b'\n')
            .count(),
        detail: "not UTF-8 text (a pose file is ASCII PLY; binary PLY is not supported)"
            .to_string(),
    })?;
    parse_pose_ply(&text, path)
}

/// What the header says, as far as the data lines need it.
struct Header {
    /// Number of lines up to and including `end_header`.
    line_count: usize,
    /// `element vertex N`, if present.
    vertex_count: Option<usize>,
}

fn parse_header(text: &str, path: &Path) -> Result<Header, PosePlyError> {
    let header_error = |line: usize, detail: String| PosePlyError::Header {
        path: path.to_path_buf(),
        line,
        detail,
    };
    let mut lines = text.lines().enumerate().map(|(i, l)| (i + 1, l.trim()));
    match lines.next() {
        Some((_, "ply")) => {}
        _ => {
            return Err(header_error(
                1,
                "missing the `ply` magic line: a pose file needs the PLY header \
                 (ply, format ascii 1.0, element vertex N, properties x y z roll pitch yaw, \
                 end_header) before the data lines"
                    .to_string(),
            ))
        }
    }
    let mut vertex_count = None;
    // The element whose properties are being declared: None before the first
    // element, Some(true) for `vertex`.
    let mut in_vertex: Option<bool> = None;
    let mut properties: Vec<String> = Vec::new();
    for (number, line) in lines {
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            [] => {}
            ["comment", ..] | ["obj_info", ..] => {}
            ["format", "ascii", ..] => {}
            ["format", other, ..] => {
                return Err(header_error(
                    number,
                    format!("format `{other}` is not supported: pose files are `ascii`"),
                ))
            }
            ["element", name, count] => {
                let count: usize = count.parse().map_err(|_| {
                    header_error(number, format!("element count `{count}` is not a number"))
                })?;
                if *name == "vertex" {
                    if vertex_count.is_some() {
                        return Err(header_error(number, "a second `vertex` element".into()));
                    }
                    vertex_count = Some(count);
                    in_vertex = Some(true);
                } else if count == 0 {
                    in_vertex = Some(false);
                } else {
                    return Err(header_error(
                        number,
                        format!(
                            "element `{name}` with {count} rows: a pose file holds only \
                             the `vertex` element"
                        ),
                    ));
                }
            }
            ["property", "list", ..] if in_vertex == Some(true) => {
                return Err(header_error(
                    number,
                    "list properties are not part of the pose layout".into(),
                ))
            }
            ["property", kind, name] if in_vertex == Some(true) => {
                if !PROPERTY_TYPES.contains(kind) {
                    return Err(header_error(
                        number,
                        format!("property `{name}` has type `{kind}`; expected float or double"),
                    ));
                }
                properties.push(name.to_string());
            }
            ["property", ..] if in_vertex.is_none() => {
                return Err(header_error(
                    number,
                    "a property before any `element` line".into(),
                ))
            }
            // Properties of an empty element other than `vertex`.
            ["property", ..] => {}
            ["end_header"] => {
                if vertex_count.is_none() {
                    log::warn!(
                        "{}: the header has no `element vertex N` line; reading the data lines present",
                        path.display()
                    );
                }
                if properties.is_empty() {
                    log::warn!(
                        "{}: the header declares no vertex properties; assuming x y z roll pitch yaw",
                        path.display()
                    );
                } else if properties != PROPERTY_NAMES {
                    return Err(header_error(
                        number,
                        format!(
                            "vertex properties are `{}`; a pose file has `{}` in that order",
                            properties.join(" "),
                            PROPERTY_NAMES.join(" ")
                        ),
                    ));
                }
                return Ok(Header {
                    line_count: number,
                    vertex_count,
                });
            }
            _ => {
                return Err(header_error(
                    number,
                    format!("unexpected header line `{line}`"),
                ))
            }
        }
    }
    Err(PosePlyError::MissingEndHeader {
        path: path.to_path_buf(),
    })
}

/// One value of a data line.
enum Value {
    Nan,
    Number(f64),
}

/// Parses one field. Accepts every spelling of nan that C and Rust print
/// (`nan`, `NaN`, `-nan`, `nan(ind)`, ...); rejects infinities.
fn parse_value(token: &str) -> Result<Value, String> {
    let lower = token.to_ascii_lowercase();
    let unsigned = lower.strip_prefix(['+', '-']).unwrap_or(lower.as_str());
    if let Some(rest) = unsigned.strip_prefix("nan") {
        if rest.is_empty() || (rest.starts_with('(') && rest.ends_with(')')) {
            return Ok(Value::Nan);
        }
    }
    match token.parse::<f64>() {
        Ok(v) if v.is_nan() => Ok(Value::Nan),
        Ok(v) if v.is_infinite() => Err(format!("`{token}` is not finite")),
        Ok(v) => Ok(Value::Number(v)),
        Err(_) => Err(format!("`{token}` is not a number")),
    }
}

/// Parses the text of a pose file; `path_for_errors` only names the file in
/// errors and warnings. Returns the poses by image id (line k after the header
/// is image id k); `nan` lines give no entry.
pub fn parse_pose_ply(
    text: &str,
    path_for_errors: &Path,
) -> Result<BTreeMap<ImageId, BodyPose>, PosePlyError> {
    let path = path_for_errors;
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    let header = parse_header(text, path)?;
    let mut data: Vec<&str> = text.lines().skip(header.line_count).collect();
    while data.last().is_some_and(|l| l.trim().is_empty()) {
        data.pop();
    }
    if let Some(expected) = header.vertex_count {
        if expected != data.len() {
            log::warn!(
                "{}: the header says {expected} vertices but there are {} data lines; \
                 reading the {} lines present (line k = image id k)",
                path.display(),
                data.len(),
                data.len()
            );
        }
    }

    let mut poses = BTreeMap::new();
    for (index, line) in data.iter().enumerate() {
        let line_number = header.line_count + index + 1;
        let id = index as u64 + 1;
        let data_error = |detail: String| PosePlyError::Data {
            path: path.to_path_buf(),
            line: line_number,
            image_id: id,
            detail,
        };
        let image_id = u32::try_from(id)
            .map(ImageId)
            .map_err(|_| data_error("image id beyond the u32 range of COLMAP ids".into()))?;
        let fields: Vec<&str> = line.split_whitespace().collect();
        if fields.len() != PROPERTY_NAMES.len() {
            return Err(data_error(format!(
                "expected 6 values `x y z roll pitch yaw` (or 6 nan), found {}",
                fields.len()
            )));
        }
        let mut values = [0.0; 6];
        let mut nan_fields = Vec::new();
        for (k, field) in fields.iter().enumerate() {
            match parse_value(field) {
                Ok(Value::Nan) => nan_fields.push(PROPERTY_NAMES[k]),
                Ok(Value::Number(v)) => values[k] = v,
                Err(what) => return Err(data_error(format!("{}: {what}", PROPERTY_NAMES[k]))),
            }
        }
        if nan_fields.len() == PROPERTY_NAMES.len() {
            continue;
        }
        if !nan_fields.is_empty() {
            return Err(data_error(format!(
                "a mix of nan and numbers (nan in {}): a line is either six numbers or six nan",
                nan_fields.join(", ")
            )));
        }
        let [x, y, z, roll_rad, pitch_rad, yaw_rad] = values;
        poses.insert(
            image_id,
            BodyPose {
                position_m: Vector3::new(x, y, z),
                roll_rad,
                pitch_rad,
                yaw_rad,
            },
        );
    }
    if let Some(why) = degrees_suspected(path, &poses) {
        log::warn!("{why}");
    }
    Ok(poses)
}

/// What to say of the `poses` read from `path` when their angles reach
/// beyond 2π: they look like degrees, as the file should hold radians. Not
/// an error: an unwrapped yaw (odometry after a few turns) is radians
/// beyond 2π.
pub fn degrees_suspected(path: &Path, poses: &BTreeMap<ImageId, BodyPose>) -> Option<String> {
    let max_abs_angle_rad = poses
        .values()
        .flat_map(|p| [p.roll_rad, p.pitch_rad, p.yaw_rad])
        .fold(0.0f64, |m, a| m.max(a.abs()));
    (max_abs_angle_rad > std::f64::consts::TAU).then(|| {
        format!(
            "{}: angles up to {max_abs_angle_rad} in absolute value; pose files store radians \
             (were degrees written?)",
            path.display()
        )
    })
}

/// [`format_pose_ply`] of a model's registered images.
pub fn format_model_pose_ply(rec: &crate::scene::Reconstruction) -> String {
    let poses: BTreeMap<ImageId, BodyPose> = rec
        .images
        .iter()
        .filter_map(|(&id, img)| Some((id, BodyPose::from_cam_from_world(&img.cam_from_world?))))
        .collect();
    format_pose_ply(&poses)
}

/// Formats poses as a pose file: data lines 1..=max id; ids without a pose get a
/// `nan` line. Values use Rust's shortest round-trip formatting, so reading the
/// text back gives bit-identical f64s. A pose with a non-finite value is written
/// as a `nan` line and image id 0 (which COLMAP never uses) is left out:
/// [`write_pose_ply`] rejects both instead.
pub fn format_pose_ply(poses: &BTreeMap<ImageId, BodyPose>) -> String {
    let line_count = poses.keys().next_back().map_or(0, |id| id.0 as usize);
    let mut out = String::new();
    out.push_str("ply\nformat ascii 1.0\n");
    out.push_str(
        "comment colmap-lidar pose file: data line k = COLMAP image id k; nan = no pose\n",
    );
    out.push_str(
        "comment x y z = camera centre in the map frame (m); roll pitch yaw in radians, \
         R_world_from_body = Rz(yaw) Ry(pitch) Rx(roll), body x forward y left z up\n",
    );
    out.push_str(&format!("element vertex {line_count}\n"));
    for name in PROPERTY_NAMES {
        out.push_str(&format!("property double {name}\n"));
    }
    out.push_str("end_header\n");
    let mut next_id = 1usize;
    for (id, pose) in poses.range(ImageId(1)..) {
        let id = id.0 as usize;
        for _ in next_id..id {
            out.push_str("nan nan nan nan nan nan\n");
        }
        next_id = id + 1;
        let values = pose_values(pose);
        if values.iter().all(|v| v.is_finite()) {
            let [x, y, z, roll, pitch, yaw] = values;
            out.push_str(&format!("{x} {y} {z} {roll} {pitch} {yaw}\n"));
        } else {
            out.push_str("nan nan nan nan nan nan\n");
        }
    }
    out
}

fn pose_values(pose: &BodyPose) -> [f64; 6] {
    [
        pose.position_m.x,
        pose.position_m.y,
        pose.position_m.z,
        pose.roll_rad,
        pose.pitch_rad,
        pose.yaw_rad,
    ]
}

/// Writes a pose file atomically (see [`format_pose_ply`]). Fails without
/// touching `path` on image id 0 or a pose with a non-finite value.
pub fn write_pose_ply(
    path: &Path,
    poses: &BTreeMap<ImageId, BodyPose>,
) -> Result<(), PosePlyError> {
    for (id, pose) in poses {
        let unwritable = |detail: &str| PosePlyError::Unwritable {
            path: path.to_path_buf(),
            image_id: *id,
            detail: detail.to_string(),
        };
        if id.0 == 0 {
            return Err(unwritable("COLMAP image ids start at 1 (line 1 is id 1)"));
        }
        if !pose_values(pose).iter().all(|v| v.is_finite()) {
            return Err(unwritable(&format!(
                "non-finite value in {:?} (x y z roll pitch yaw)",
                pose_values(pose)
            )));
        }
    }
    let text = format_pose_ply(poses);
    write_file_atomically::<io::Error>(path, |w| w.write_all(text.as_bytes())).map_err(|source| {
        PosePlyError::Io {
            path: path.to_path_buf(),
            source,
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use std::f64::consts::{FRAC_PI_2, PI};

    fn p() -> &'static Path {
        Path::new("/data/poses/pose.ply")
    }

    const HEADER: &str = "ply\nformat ascii 1.0\nelement vertex 3\nproperty double x\n\
        property double y\nproperty double z\nproperty double roll\nproperty double pitch\n\
        property double yaw\nend_header\n";

    fn bits(pose: &BodyPose) -> [u64; 6] {
        pose_values(pose).map(f64::to_bits)
    }

    #[test]
    fn round_trip_is_bit_exact_with_gaps() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let mut poses = BTreeMap::new();
        for id in [1u32, 2, 5, 6, 9, 40] {
            let pose = BodyPose {
                position_m: Vector3::new(
                    500000.0 + rng.gen_range(-1000.0..1000.0),
                    4400000.0 + rng.gen_range(-1000.0..1000.0),
                    rng.gen_range(-50.0..300.0),
                ),
                roll_rad: rng.gen_range(-PI..PI),
                pitch_rad: rng.gen_range(-FRAC_PI_2..FRAC_PI_2),
                yaw_rad: rng.gen_range(-PI..PI),
            };
            poses.insert(ImageId(id), pose);
        }
        // Edge values: exactly +-pi, the next f64 below pi, -0, tiny and huge.
        poses.insert(
            ImageId(12),
            BodyPose {
                position_m: Vector3::new(-0.0, 1e-300, 6.02e23),
                roll_rad: PI,
                pitch_rad: -PI,
                yaw_rad: f64::from_bits(PI.to_bits() - 1),
            },
        );
        let text = format_pose_ply(&poses);
        let data_lines: Vec<&str> = text
            .lines()
            .skip_while(|l| *l != "end_header")
            .skip(1)
            .collect();
        assert_eq!(data_lines.len(), 40);
        assert!(text.contains("element vertex 40\n"));
        for gap in [3usize, 4, 7, 8, 10, 11, 13, 39] {
            assert_eq!(data_lines[gap - 1], "nan nan nan nan nan nan", "id {gap}");
        }
        let back = parse_pose_ply(&text, p()).unwrap();
        assert_eq!(
            back.keys().collect::<Vec<_>>(),
            poses.keys().collect::<Vec<_>>()
        );
        for (id, pose) in &poses {
            assert_eq!(bits(&back[id]), bits(pose), "image id {id}");
        }

        // Through the file system as well.
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("out/pose.ply");
        write_pose_ply(&file, &poses).unwrap();
        let read = read_pose_ply(&file).unwrap();
        for (id, pose) in &poses {
            assert_eq!(bits(&read[id]), bits(pose), "image id {id}");
        }
        assert_eq!(std::fs::read_to_string(&file).unwrap(), text);
    }

    #[test]
    fn angles_beyond_two_pi_are_suspected_degrees() {
        let path = Path::new("poses.ply");
        let reaching = |yaw_rad: f64| -> BTreeMap<ImageId, BodyPose> {
            let level = BodyPose {
                position_m: Vector3::zeros(),
                roll_rad: 0.0,
                pitch_rad: 0.0,
                yaw_rad: 0.0,
            };
            BTreeMap::from([
                (ImageId(1), level),
                (ImageId(2), BodyPose { yaw_rad, ..level }),
            ])
        };
        let says = degrees_suspected(path, &reaching(-106.0)).unwrap();
        assert!(
            says.starts_with("poses.ply: angles up to 106")
                && says.contains("were degrees written?"),
            "{says}"
        );
        assert!(degrees_suspected(path, &reaching(6.3)).is_some());
        assert!(degrees_suspected(path, &reaching(6.2)).is_none());
    }

    #[test]
    fn empty_map_round_trips() {
        let text = format_pose_ply(&BTreeMap::new());
        assert!(text.contains("element vertex 0\n"));
        assert!(text.ends_with("end_header\n"));
        assert!(parse_pose_ply(&text, p()).unwrap().is_empty());
    }

    #[test]
    fn hand_written_example() {
        let text = format!(
            "{HEADER}500000.25 4400000.5 12 0 0.1 1.5707963267948966\n\
             nan nan nan nan nan nan\n\
             -1.5 2e1 -0.125 -3.25 -0.5 0.25\n"
        );
        let poses = parse_pose_ply(&text, p()).unwrap();
        assert_eq!(poses.len(), 2);
        let one = &poses[&ImageId(1)];
        assert_eq!(one.position_m, Vector3::new(500000.25, 4400000.5, 12.0));
        assert_eq!(
            (one.roll_rad, one.pitch_rad, one.yaw_rad),
            (0.0, 0.1, FRAC_PI_2)
        );
        assert!(!poses.contains_key(&ImageId(2)));
        let three = &poses[&ImageId(3)];
        assert_eq!(three.position_m, Vector3::new(-1.5, 20.0, -0.125));
        assert_eq!(
            (three.roll_rad, three.pitch_rad, three.yaw_rad),
            (-3.25, -0.5, 0.25)
        );
    }

    #[test]
    fn nan_spellings_are_skipped() {
        let text = format!(
            "{HEADER}nan nan nan nan nan nan\nNaN NAN -nan +nan -nan(ind) nan(0x1)\n1 2 3 0.1 0.2 0.3\n"
        );
        let poses = parse_pose_ply(&text, p()).unwrap();
        assert_eq!(poses.keys().copied().collect::<Vec<_>>(), vec![ImageId(3)]);
        assert_eq!(poses[&ImageId(3)].position_m, Vector3::new(1.0, 2.0, 3.0));
    }

    #[test]
    fn header_variants_are_accepted() {
        // float properties, comments and obj_info, CRLF, BOM, blank header line,
        // trailing empty lines, vertex count smaller and larger than the data.
        let text = "\u{feff}ply\r\nformat ascii 1.0\r\ncomment written by hand\r\n\
            obj_info reference layout\r\nelement vertex 2\r\n\r\nproperty float x\r\n\
            property float y\r\nproperty float z\r\ncomment angles in radians\r\n\
            property float roll\r\nproperty float32 pitch\r\nproperty float64 yaw\r\n\
            end_header\r\n1 2 3 0 0 0\r\nnan nan nan nan nan nan\r\n7 8 9 0.5 0.25 -1\r\n\r\n  \r\n";
        let poses = parse_pose_ply(text, p()).unwrap();
        assert_eq!(
            poses.keys().copied().collect::<Vec<_>>(),
            vec![ImageId(1), ImageId(3)]
        );
        assert_eq!(poses[&ImageId(3)].position_m, Vector3::new(7.0, 8.0, 9.0));
        assert_eq!(poses[&ImageId(3)].yaw_rad, -1.0);

        let larger = HEADER.replace("element vertex 3", "element vertex 100") + "1 2 3 0 0 0\n";
        assert_eq!(parse_pose_ply(&larger, p()).unwrap().len(), 1);
        // A minimal header (no element, no properties) and no final newline.
        let minimal = "ply\nformat ascii 1.0\nend_header\nnan nan nan nan nan nan\n1 2 3 0 0 0";
        let poses = parse_pose_ply(minimal, p()).unwrap();
        assert_eq!(poses.keys().copied().collect::<Vec<_>>(), vec![ImageId(2)]);
        // Properties of an empty element before the vertex element are ignored.
        let face_first = HEADER.replace(
            "element vertex 3",
            "element face 0\nproperty list uchar int vertex_indices\nelement vertex 3",
        ) + "1 2 3 0 0 0\n";
        assert_eq!(parse_pose_ply(&face_first, p()).unwrap().len(), 1);
    }

    /// The error message of parsing `text`, checked to name the file and `line`.
    fn error_at(text: &str, line: usize) -> String {
        let err = parse_pose_ply(text, p()).unwrap_err();
        let message = err.to_string();
        assert!(message.contains("/data/poses/pose.ply"), "{message}");
        assert!(message.contains(&format!("line {line}")), "{message}");
        message
    }

    #[test]
    fn malformed_data_lines_are_errors_naming_file_line_and_id() {
        // The header has 10 lines: image id k is on line 10 + k.
        let good = "1 2 3 0 0 0\n";
        let cases = [
            ("1 2 3 0 0\n", "found 5"),
            ("1 2 3 0 0 0 7\n", "found 7"),
            ("1 2 3 0 zero 0\n", "pitch: `zero` is not a number"),
            ("1 2 3 0 0 0,5\n", "yaw: `0,5` is not a number"),
            ("1 nan 3 0 0 0\n", "a mix of nan and numbers (nan in y)"),
            ("nan nan nan nan nan 0\n", "nan in x, y, z, roll, pitch"),
            ("1 2 inf 0 0 0\n", "z: `inf` is not finite"),
            ("1 2 3 -Infinity 0 0\n", "roll: `-Infinity` is not finite"),
            ("1 2 1e999 0 0 0\n", "z: `1e999` is not finite"),
            ("\n", "found 0"),
        ];
        for (bad, what) in cases {
            let text = format!("{HEADER}{good}{good}{bad}{good}");
            let message = error_at(&text, 13);
            assert!(message.contains("image id 3"), "{message}");
            assert!(message.contains(what), "{bad:?}: {message}");
        }
        // CRLF files count lines the same way.
        let text = format!("{HEADER}{good}1 2\n").replace('\n', "\r\n");
        let message = error_at(&text, 12);
        assert!(message.contains("image id 2"), "{message}");
    }

    #[test]
    fn header_problems_are_errors() {
        let data = "1 2 3 0 0 0\n";
        // No header at all.
        let message = error_at(data, 1);
        assert!(message.contains("`ply`"), "{message}");
        // No end_header.
        let text = HEADER.replace("end_header\n", "");
        let err = parse_pose_ply(&text, p()).unwrap_err();
        assert!(matches!(err, PosePlyError::MissingEndHeader { .. }));
        assert!(err.to_string().contains("/data/poses/pose.ply"));
        assert!(err.to_string().contains("end_header"));
        // Data lines instead of end_header: the first one is an unexpected header line.
        let message = error_at(&format!("{text}{data}"), 10);
        assert!(message.contains("unexpected header line"), "{message}");
        // Binary format.
        let text = HEADER.replace("format ascii 1.0", "format binary_little_endian 1.0");
        let message = error_at(&text, 2);
        assert!(message.contains("binary_little_endian"), "{message}");
        // Wrong property order, wrong type, extra property.
        let text = HEADER.replace(
            "property double roll\nproperty double pitch",
            "property double pitch\nproperty double roll",
        );
        let message = error_at(&text, 10);
        assert!(message.contains("x y z pitch roll"), "{message}");
        let text = HEADER.replace("property double z", "property uchar z");
        assert!(error_at(&text, 6).contains("`uchar`"));
        let text = HEADER.replace("end_header", "property double qw\nend_header");
        assert!(error_at(&text, 11).contains("x y z roll pitch yaw qw"));
        // A second element with rows.
        let text = HEADER.replace("end_header", "element face 2\nend_header");
        assert!(error_at(&text, 10).contains("element `face`"));
        // A bad vertex count.
        let text = HEADER.replace("element vertex 3", "element vertex three");
        assert!(error_at(&text, 3).contains("`three`"));
    }

    #[test]
    fn unreadable_and_unwritable_files() {
        let dir = tempfile::tempdir().unwrap();
        let missing = dir.path().join("nothing.ply");
        let err = read_pose_ply(&missing).unwrap_err();
        assert!(matches!(err, PosePlyError::Io { .. }));
        assert!(err.to_string().contains("nothing.ply"), "{err}");

        let binary = dir.path().join("binary.ply");
        std::fs::write(&binary, b"ply\nformat binary_little_endian 1.0\n\xff\xfe").unwrap();
        let err = read_pose_ply(&binary).unwrap_err();
        assert!(err.to_string().contains("binary.ply"), "{err}");
        assert!(err.to_string().contains("line 3"), "{err}");

        let out = dir.path().join("pose.ply");
        let zero = BodyPose::from_degrees(Vector3::zeros(), 0.0, 0.0, 0.0);
        let err = write_pose_ply(&out, &BTreeMap::from([(ImageId(0), zero)])).unwrap_err();
        assert!(err.to_string().contains("pose.ply") && err.to_string().contains("id 0"));
        let mut bad = zero;
        bad.yaw_rad = f64::NAN;
        let err = write_pose_ply(&out, &BTreeMap::from([(ImageId(4), bad)])).unwrap_err();
        assert!(err.to_string().contains("image id 4"), "{err}");
        assert!(!out.exists());
        // format_pose_ply (infallible) writes the non-finite pose as "no pose".
        let text = format_pose_ply(&BTreeMap::from([(ImageId(2), bad)]));
        assert!(text.ends_with("end_header\nnan nan nan nan nan nan\nnan nan nan nan nan nan\n"));
    }

    #[test]
    fn line_pose_gives_the_hand_computed_cam_from_world() {
        // yaw = pi/2 at c = (10, 20, 5): body x (forward) = +y_world, body y (left)
        // = -x_world, body z = +z_world. So x_cam = -y_body = +x_world,
        // y_cam = -z_body = -z_world, z_cam = x_body = +y_world: the rows of
        // R_cam_from_world are [1 0 0], [0 0 -1], [0 1 0], and t = -R c = (-10, 5, -20).
        let text = format!("{HEADER}10 20 5 0 0 1.5707963267948966\n");
        let poses = parse_pose_ply(&text, p()).unwrap();
        let cam_from_world = poses[&ImageId(1)].to_cam_from_world();
        let r = cam_from_world.rotation_matrix();
        let expected_r = nalgebra::Matrix3::new(1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0);
        assert!((r - expected_r).norm() < 1e-12, "{r}");
        let t = cam_from_world.transform_point(&Vector3::zeros());
        assert!((t - Vector3::new(-10.0, 5.0, -20.0)).norm() < 1e-12, "{t}");
        // A point 3 m ahead along +y is on the optical axis at depth 3.
        let ahead = cam_from_world.transform_point(&Vector3::new(10.0, 23.0, 5.0));
        assert!(
            (ahead - Vector3::new(0.0, 0.0, 3.0)).norm() < 1e-12,
            "{ahead}"
        );
    }
}
