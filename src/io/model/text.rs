//! The text encoding: `cameras.txt`, `images.txt`, `points3D.txt` (layout in the
//! parent module's doc).
use std::fmt;
use std::fs::File;
use std::io::{self, BufRead, BufReader, BufWriter, Write};
use std::path::{Path, PathBuf};
use std::str::FromStr;

use crate::scene::{
    Camera, CameraId, CameraModel, Image, ImageId, Point2D, Point3D, Point3DId, Reconstruction,
    TrackElement,
};

use super::{
    bad_camera, bad_coordinates, mean_observations_per_image, mean_track_length, pose_from_file,
    Loc, ModelError, ModelFormat, ParsedImage, ParsedModel,
};

/// Shortest round-trip decimal form of an f64 (reads back bit-identical). Plain
/// notation for magnitudes in [1e-5, 1e16) and zero, scientific otherwise, so no
/// number is hundreds of characters long.
pub(super) struct F(pub f64);

impl fmt::Display for F {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let a = self.0.abs();
        if a == 0.0 || !a.is_finite() || (1e-5..1e16).contains(&a) {
            write!(f, "{}", self.0)
        } else {
            write!(f, "{:e}", self.0)
        }
    }
}

/// Reads lines one at a time, counting them (1-based).
struct LineReader {
    path: PathBuf,
    reader: Box<dyn BufRead>,
    line_no: usize,
    bytes: Vec<u8>,
    line: String,
}

impl LineReader {
    fn open(path: &Path) -> Result<Self, ModelError> {
        let file = File::open(path).map_err(|source| ModelError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Ok(Self::new(path, Box::new(BufReader::new(file))))
    }

    /// Reads lines from `reader`, naming `path` in errors.
    fn new(path: &Path, reader: Box<dyn BufRead>) -> Self {
        Self {
            path: path.to_path_buf(),
            reader,
            line_no: 0,
            bytes: Vec::new(),
            line: String::new(),
        }
    }

    fn error(&self, msg: impl Into<String>) -> ModelError {
        Loc::Line(self.line_no).error(&self.path, msg)
    }

    /// Reads the next line into `self.line` (without its line break); false at the end.
    fn next_line(&mut self) -> Result<bool, ModelError> {
        self.bytes.clear();
        let n = self
            .reader
            .read_until(b'\n', &mut self.bytes)
            .map_err(|source| ModelError::Io {
                path: self.path.clone(),
                source,
            })?;
        if n == 0 {
            return Ok(false);
        }
        self.line_no += 1;
        if self.bytes.last() == Some(&b'\n') {
            self.bytes.pop();
        }
        if self.bytes.last() == Some(&b'\r') {
            self.bytes.pop();
        }
        self.line.clear();
        match std::str::from_utf8(&self.bytes) {
            Ok(s) => self.line.push_str(s),
            Err(_) => return Err(self.error("not valid UTF-8")),
        }
        Ok(true)
    }

    /// Skips comments (`#`) and blank lines; false at the end.
    fn next_record(&mut self) -> Result<bool, ModelError> {
        while self.next_line()? {
            let t = self.line.trim_start();
            if !t.is_empty() && !t.starts_with('#') {
                return Ok(true);
            }
        }
        Ok(false)
    }
}

/// Whitespace-separated fields of one line, parsed with errors naming the field.
struct Fields<'a> {
    rest: &'a str,
}

impl<'a> Fields<'a> {
    fn new(line: &'a str) -> Self {
        Self { rest: line }
    }

    fn next_token(&mut self) -> Option<&'a str> {
        let s = self.rest.trim_start();
        if s.is_empty() {
            self.rest = s;
            return None;
        }
        let end = s.find(char::is_whitespace).unwrap_or(s.len());
        self.rest = &s[end..];
        Some(&s[..end])
    }

    /// The next field parsed as `T`; `kind` says what was expected ("an integer").
    fn parse<T: FromStr>(&mut self, field: &str, kind: &str) -> Result<T, String> {
        let token = self
            .next_token()
            .ok_or_else(|| format!("line ends before {field}"))?;
        token
            .parse()
            .map_err(|_| format!("{field}: {token:?} is not {kind}"))
    }

    fn f64(&mut self, field: &str) -> Result<f64, String> {
        self.parse(field, "a number")
    }

    fn u32(&mut self, field: &str) -> Result<u32, String> {
        self.parse(field, "an integer in 0..=4294967295")
    }

    fn point3d_id(&mut self, field: &str) -> Result<Point3DId, String> {
        let id: u64 = self.parse(field, "an integer in 0..2^64-1")?;
        if id == u64::MAX {
            return Err(format!("{field}: {id} is reserved for \"no point\""));
        }
        Ok(Point3DId(id))
    }

    /// The remaining fields, all numbers.
    fn rest_f64(&mut self, field: &str) -> Result<Vec<f64>, String> {
        let mut values = Vec::new();
        while let Some(token) = self.next_token() {
            values.push(
                token
                    .parse()
                    .map_err(|_| format!("{field}: {token:?} is not a number"))?,
            );
        }
        Ok(values)
    }

    fn rest_trimmed(&self) -> &'a str {
        self.rest.trim()
    }
}

pub(super) fn read(dir: &Path) -> Result<ParsedModel, ModelError> {
    let paths = ModelFormat::Text.paths(dir);
    let cameras = read_cameras(LineReader::open(&paths[0])?)?;
    let images = read_images(LineReader::open(&paths[1])?)?;
    let points = read_points(LineReader::open(&paths[2])?)?;
    Ok(ParsedModel {
        paths,
        cameras,
        images,
        points,
    })
}

/// Parses the three files from memory (for tests), naming them as if in `dir`.
#[cfg(test)]
pub(super) fn read_bytes(dir: &Path, bytes: [&[u8]; 3]) -> Result<ParsedModel, ModelError> {
    let paths = ModelFormat::Text.paths(dir);
    let reader =
        |i: usize| LineReader::new(&paths[i], Box::new(io::Cursor::new(bytes[i].to_vec())));
    let cameras = read_cameras(reader(0))?;
    let images = read_images(reader(1))?;
    let points = read_points(reader(2))?;
    Ok(ParsedModel {
        paths,
        cameras,
        images,
        points,
    })
}

fn read_cameras(mut lines: LineReader) -> Result<Vec<(Camera, Loc)>, ModelError> {
    let mut cameras = Vec::new();
    while lines.next_record()? {
        let parse = |line: &str| -> Result<Camera, String> {
            let mut f = Fields::new(line);
            let id = CameraId(f.u32("CAMERA_ID")?);
            let name = f.next_token().ok_or("line ends before MODEL")?;
            let model = CameraModel::from_name(name)
                .ok_or_else(|| format!("MODEL: unknown camera model {name:?}"))?;
            let width = f.u32("WIDTH")?;
            let height = f.u32("HEIGHT")?;
            let params = f.rest_f64("PARAMS")?;
            let camera = Camera {
                id,
                model,
                width,
                height,
                params,
            };
            match bad_camera(&camera) {
                Some(why) => Err(why),
                None => Ok(camera),
            }
        };
        let camera = parse(&lines.line).map_err(|msg| lines.error(msg))?;
        cameras.push((camera, Loc::Line(lines.line_no)));
    }
    Ok(cameras)
}

fn read_images(mut lines: LineReader) -> Result<Vec<ParsedImage>, ModelError> {
    let mut images = Vec::new();
    while lines.next_record()? {
        let pose_loc = Loc::Line(lines.line_no);
        let parse_header = |line: &str| -> Result<Image, String> {
            let mut f = Fields::new(line);
            let id = ImageId(f.u32("IMAGE_ID")?);
            let q = [f.f64("QW")?, f.f64("QX")?, f.f64("QY")?, f.f64("QZ")?];
            let t = [f.f64("TX")?, f.f64("TY")?, f.f64("TZ")?];
            let camera_id = CameraId(f.u32("CAMERA_ID")?);
            let name = f.rest_trimmed();
            if name.is_empty() {
                return Err("line ends before NAME".to_string());
            }
            let pose = pose_from_file(q, t)?;
            Ok(Image {
                id,
                name: name.to_string(),
                camera_id,
                cam_from_world: Some(pose),
                points2d: Vec::new(),
            })
        };
        let mut image = parse_header(&lines.line).map_err(|msg| lines.error(msg))?;
        if !lines.next_line()? {
            return Err(lines.error(format!(
                "file ends before the POINTS2D line of image {}",
                image.id
            )));
        }
        let parse_points = |line: &str| -> Result<Vec<Point2D>, String> {
            let mut f = Fields::new(line);
            let mut points = Vec::new();
            while let Some(x) = f.next_token() {
                let x: f64 = x.parse().map_err(|_| {
                    format!("X of keypoint {}: {x:?} is not a number", points.len())
                })?;
                let y = f.f64(&format!("Y of keypoint {}", points.len()))?;
                if let Some(why) = bad_coordinates(&format!("keypoint {}", points.len()), &[x, y]) {
                    return Err(why);
                }
                let field = format!("POINT3D_ID of keypoint {}", points.len());
                let id = f
                    .next_token()
                    .ok_or_else(|| format!("line ends before {field}"))?;
                let point3d_id = if id == "-1" {
                    None
                } else {
                    Some(Fields::new(id).point3d_id(&field)?)
                };
                points.push(Point2D {
                    xy: [x, y].into(),
                    point3d_id,
                });
            }
            if u32::try_from(points.len()).is_err() {
                return Err("too many keypoints".to_string());
            }
            Ok(points)
        };
        image.points2d = parse_points(&lines.line).map_err(|msg| lines.error(msg))?;
        images.push(ParsedImage {
            image,
            pose_loc,
            points_loc: Loc::Line(lines.line_no),
        });
    }
    Ok(images)
}

fn read_points(mut lines: LineReader) -> Result<Vec<(Point3DId, Point3D, Loc)>, ModelError> {
    let mut points = Vec::new();
    while lines.next_record()? {
        let parse = |line: &str| -> Result<(Point3DId, Point3D), String> {
            let mut f = Fields::new(line);
            let id = f.point3d_id("POINT3D_ID")?;
            let xyz = [f.f64("X")?, f.f64("Y")?, f.f64("Z")?];
            if let Some(why) = bad_coordinates("X Y Z", &xyz) {
                return Err(why);
            }
            let rgb_kind = "an integer in 0..=255";
            let color = [
                f.parse("R", rgb_kind)?,
                f.parse("G", rgb_kind)?,
                f.parse("B", rgb_kind)?,
            ];
            let error = f.f64("ERROR")?;
            let mut track = Vec::new();
            while let Some(image) = f.next_token() {
                let image_id = Fields::new(image).u32("IMAGE_ID of a track element")?;
                let point2d_idx = f.u32("POINT2D_IDX of a track element")?;
                track.push(TrackElement {
                    image_id: ImageId(image_id),
                    point2d_idx,
                });
            }
            Ok((
                id,
                Point3D {
                    xyz: xyz.into(),
                    color,
                    error,
                    track,
                },
            ))
        };
        let (id, point) = parse(&lines.line).map_err(|msg| lines.error(msg))?;
        points.push((id, point, Loc::Line(lines.line_no)));
    }
    Ok(points)
}

/// Writes the three text files into `dir` (an existing, empty folder).
pub(super) fn write(dir: &Path, rec: &Reconstruction) -> Result<(), ModelError> {
    let [cam_path, img_path, pts_path] = ModelFormat::Text.paths(dir);
    write_file(&cam_path, |w| write_cameras(w, rec))?;
    write_file(&img_path, |w| write_images(w, rec))?;
    write_file(&pts_path, |w| write_points(w, rec))?;
    Ok(())
}

pub(super) fn write_file(
    path: &Path,
    fill: impl FnOnce(&mut BufWriter<File>) -> io::Result<()>,
) -> Result<(), ModelError> {
    let io_err = |source| ModelError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut w = BufWriter::new(File::create(path).map_err(io_err)?);
    fill(&mut w).map_err(io_err)?;
    let file = w.into_inner().map_err(|e| io_err(e.into_error()))?;
    file.sync_all().map_err(io_err)
}

pub(super) fn write_cameras(w: &mut impl Write, rec: &Reconstruction) -> io::Result<()> {
    writeln!(w, "# Camera list with one line of data per camera:")?;
    writeln!(w, "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]")?;
    writeln!(w, "# Number of cameras: {}", rec.cameras.len())?;
    for camera in rec.cameras.values() {
        write!(
            w,
            "{} {} {} {}",
            camera.id,
            camera.model.name(),
            camera.width,
            camera.height
        )?;
        for &p in &camera.params {
            write!(w, " {}", F(p))?;
        }
        writeln!(w)?;
    }
    Ok(())
}

pub(super) fn write_images(w: &mut impl Write, rec: &Reconstruction) -> io::Result<()> {
    writeln!(w, "# Image list with two lines of data per image:")?;
    writeln!(
        w,
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME"
    )?;
    writeln!(w, "#   POINTS2D[] as (X, Y, POINT3D_ID)")?;
    writeln!(
        w,
        "# Number of images: {}, mean observations per image: {}",
        rec.num_registered_images(),
        mean_observations_per_image(rec)
    )?;
    for image in rec.registered_images() {
        let Some(pose) = image.cam_from_world else {
            continue; // registered_images() yields only images with a pose
        };
        let [qw, qx, qy, qz] = pose.quaternion_wxyz();
        let t = pose.translation;
        writeln!(
            w,
            "{} {} {} {} {} {} {} {} {} {}",
            image.id,
            F(qw),
            F(qx),
            F(qy),
            F(qz),
            F(t.x),
            F(t.y),
            F(t.z),
            image.camera_id,
            image.name
        )?;
        for (i, p) in image.points2d.iter().enumerate() {
            if i > 0 {
                write!(w, " ")?;
            }
            write!(w, "{} {} ", F(p.xy.x), F(p.xy.y))?;
            match p.point3d_id {
                Some(id) => write!(w, "{id}")?,
                None => write!(w, "-1")?,
            }
        }
        writeln!(w)?;
    }
    Ok(())
}

pub(super) fn write_points(w: &mut impl Write, rec: &Reconstruction) -> io::Result<()> {
    writeln!(w, "# 3D point list with one line of data per point:")?;
    writeln!(
        w,
        "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)"
    )?;
    writeln!(
        w,
        "# Number of points: {}, mean track length: {}",
        rec.points3d.len(),
        mean_track_length(rec)
    )?;
    for (id, p) in &rec.points3d {
        write!(
            w,
            "{} {} {} {} {} {} {} {}",
            id,
            F(p.xyz.x),
            F(p.xyz.y),
            F(p.xyz.z),
            p.color[0],
            p.color[1],
            p.color[2],
            F(p.error)
        )?;
        for el in &p.track {
            write!(w, " {} {}", el.image_id, el.point2d_idx)?;
        }
        writeln!(w)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn floats_are_shortest_and_round_trip() {
        assert_eq!(F(1.0).to_string(), "1");
        assert_eq!(F(-0.0).to_string(), "-0");
        assert_eq!(F(0.1).to_string(), "0.1");
        assert_eq!(F(1e-7).to_string(), "1e-7");
        assert_eq!(F(-2.5e20).to_string(), "-2.5e20");
        assert_eq!(F(123456.789).to_string(), "123456.789");
        let mut x = 0.3f64;
        for _ in 0..2000 {
            x = x * 1.37 + 1e-3 * x.sin();
            for v in [
                x,
                -x,
                1.0 / x,
                x.to_bits() as f64 * 1e-300,
                f64::MIN_POSITIVE * x,
            ] {
                let back: f64 = F(v).to_string().parse().unwrap();
                assert_eq!(back.to_bits(), v.to_bits(), "{v:e}");
            }
            if !x.is_finite() {
                x = 0.7;
            }
        }
    }

    #[test]
    fn fields_name_the_problem() {
        let mut f = Fields::new("  12 abc");
        assert_eq!(f.u32("A"), Ok(12));
        assert_eq!(f.f64("B"), Err("B: \"abc\" is not a number".to_string()));
        assert_eq!(f.f64("C"), Err("line ends before C".to_string()));
        let mut f = Fields::new("18446744073709551615");
        assert!(f.point3d_id("ID").unwrap_err().contains("reserved"));
    }
}
