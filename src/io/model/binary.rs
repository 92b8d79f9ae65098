//! The binary encoding: `cameras.bin`, `images.bin`, `points3D.bin` (layout in the
//! parent module's doc). Counts read from a file are checked against the bytes left
//! before anything is allocated, so a corrupt count cannot exhaust memory.
use std::fs::File;
use std::io::{self, BufRead, BufReader, Read, Write};
use std::path::{Path, PathBuf};

use crate::scene::{
    Camera, CameraId, CameraModel, Image, ImageId, Point2D, Point3D, Point3DId, Reconstruction,
    TrackElement,
};

use super::text::write_file;
use super::{
    bad_camera, bad_coordinates, pose_from_file, Loc, ModelError, ModelFormat, ParsedImage,
    ParsedModel,
};

/// Smallest possible encoded sizes, for the count checks.
const MIN_CAMERA_BYTES: u64 = 4 + 4 + 8 + 8 + 3 * 8;
const MIN_IMAGE_BYTES: u64 = 4 + 7 * 8 + 4 + 1 + 8;
const MIN_POINT_BYTES: u64 = 8 + 3 * 8 + 3 + 8 + 8;
const KEYPOINT_BYTES: u64 = 8 + 8 + 8;
const TRACK_ELEMENT_BYTES: u64 = 4 + 4;

/// A little-endian reader that knows its byte offset and current record.
struct BinReader {
    path: PathBuf,
    reader: Box<dyn BufRead>,
    offset: u64,
    len: u64,
    record: Option<u64>,
}

impl BinReader {
    fn open(path: &Path) -> Result<Self, ModelError> {
        let io_err = |source| ModelError::Io {
            path: path.to_path_buf(),
            source,
        };
        let file = File::open(path).map_err(io_err)?;
        let len = file.metadata().map_err(io_err)?.len();
        Ok(Self::new(path, Box::new(BufReader::new(file)), len))
    }

    /// Reads `len` bytes from `reader`, naming `path` in errors.
    fn new(path: &Path, reader: Box<dyn BufRead>, len: u64) -> Self {
        Self {
            path: path.to_path_buf(),
            reader,
            offset: 0,
            len,
            record: None,
        }
    }

    fn error_at(&self, offset: u64, msg: impl Into<String>) -> ModelError {
        ModelError::Binary {
            path: self.path.clone(),
            record: self.record,
            offset,
            msg: msg.into(),
        }
    }

    fn loc(&self) -> Loc {
        Loc::Record {
            index: self.record.unwrap_or(0),
            offset: self.offset,
        }
    }

    fn bytes<const N: usize>(&mut self, what: &str) -> Result<[u8; N], ModelError> {
        let mut buf = [0u8; N];
        match self.reader.read_exact(&mut buf) {
            Ok(()) => {
                self.offset += N as u64;
                Ok(buf)
            }
            Err(e) if e.kind() == io::ErrorKind::UnexpectedEof => Err(self.error_at(
                self.offset,
                format!("file is truncated: it ends inside {what}"),
            )),
            Err(source) => Err(ModelError::Io {
                path: self.path.clone(),
                source,
            }),
        }
    }

    fn u8(&mut self, what: &str) -> Result<u8, ModelError> {
        Ok(self.bytes::<1>(what)?[0])
    }

    fn u32(&mut self, what: &str) -> Result<u32, ModelError> {
        Ok(u32::from_le_bytes(self.bytes(what)?))
    }

    fn i32(&mut self, what: &str) -> Result<i32, ModelError> {
        Ok(i32::from_le_bytes(self.bytes(what)?))
    }

    fn u64(&mut self, what: &str) -> Result<u64, ModelError> {
        Ok(u64::from_le_bytes(self.bytes(what)?))
    }

    fn f64(&mut self, what: &str) -> Result<f64, ModelError> {
        Ok(f64::from_le_bytes(self.bytes(what)?))
    }

    /// A u64 count of items of at least `min_bytes` each, checked against the rest
    /// of the file.
    fn count(&mut self, what: &str, min_bytes: u64) -> Result<u64, ModelError> {
        let start = self.offset;
        let n = self.u64(&format!("the number of {what}"))?;
        let remaining = self.len.saturating_sub(self.offset);
        match n.checked_mul(min_bytes) {
            Some(need) if need <= remaining => Ok(n),
            _ => Err(self.error_at(
                start,
                format!(
                    "{n} {what} need at least {min_bytes} bytes each, but only {remaining} \
                     bytes remain (truncated or corrupt file)"
                ),
            )),
        }
    }

    /// A NUL-terminated UTF-8 string.
    fn name(&mut self) -> Result<String, ModelError> {
        let start = self.offset;
        let mut buf = Vec::new();
        let n = self
            .reader
            .read_until(0, &mut buf)
            .map_err(|source| ModelError::Io {
                path: self.path.clone(),
                source,
            })?;
        self.offset += n as u64;
        if buf.pop() != Some(0) {
            return Err(self.error_at(start, "file is truncated: it ends inside NAME"));
        }
        String::from_utf8(buf).map_err(|_| self.error_at(start, "NAME is not valid UTF-8"))
    }

    /// Errors unless the whole file was consumed.
    fn finish(self) -> Result<(), ModelError> {
        if self.offset != self.len {
            return Err(ModelError::Binary {
                path: self.path.clone(),
                record: None,
                offset: self.offset,
                msg: format!(
                    "{} unexpected bytes after the last record",
                    self.len - self.offset
                ),
            });
        }
        Ok(())
    }
}

pub(super) fn read(dir: &Path) -> Result<ParsedModel, ModelError> {
    let paths = ModelFormat::Binary.paths(dir);
    let cameras = read_cameras(BinReader::open(&paths[0])?)?;
    let images = read_images(BinReader::open(&paths[1])?)?;
    let points = read_points(BinReader::open(&paths[2])?)?;
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
    let paths = ModelFormat::Binary.paths(dir);
    let reader = |i: usize| {
        BinReader::new(
            &paths[i],
            Box::new(io::Cursor::new(bytes[i].to_vec())),
            bytes[i].len() as u64,
        )
    };
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

fn read_cameras(mut r: BinReader) -> Result<Vec<(Camera, Loc)>, ModelError> {
    let n = r.count("cameras", MIN_CAMERA_BYTES)?;
    let mut cameras = Vec::with_capacity(n as usize);
    for index in 0..n {
        r.record = Some(index);
        let loc = r.loc();
        let id = CameraId(r.u32("CAMERA_ID")?);
        let model_offset = r.offset;
        let model_id = r.i32("MODEL_ID")?;
        let model = CameraModel::from_id(i64::from(model_id)).ok_or_else(|| {
            r.error_at(model_offset, format!("unknown camera MODEL_ID {model_id}"))
        })?;
        let mut size = [0u32; 2];
        for (value, what) in size.iter_mut().zip(["WIDTH", "HEIGHT"]) {
            let offset = r.offset;
            let v = r.u64(what)?;
            *value = u32::try_from(v)
                .map_err(|_| r.error_at(offset, format!("{what} {v} does not fit in 32 bits")))?;
        }
        let mut params = Vec::with_capacity(model.num_params());
        for name in model.param_names() {
            params.push(r.f64(&format!("parameter {name}"))?);
        }
        let camera = Camera {
            id,
            model,
            width: size[0],
            height: size[1],
            params,
        };
        if let Some(why) = bad_camera(&camera) {
            return Err(r.error_at(model_offset, why));
        }
        cameras.push((camera, loc));
    }
    r.finish()?;
    Ok(cameras)
}

fn read_images(mut r: BinReader) -> Result<Vec<ParsedImage>, ModelError> {
    let n = r.count("images", MIN_IMAGE_BYTES)?;
    let mut images = Vec::with_capacity(n as usize);
    for index in 0..n {
        r.record = Some(index);
        let loc = r.loc();
        let id = ImageId(r.u32("IMAGE_ID")?);
        let q_offset = r.offset;
        let q = [r.f64("QW")?, r.f64("QX")?, r.f64("QY")?, r.f64("QZ")?];
        let t = [r.f64("TX")?, r.f64("TY")?, r.f64("TZ")?];
        let pose = pose_from_file(q, t).map_err(|why| r.error_at(q_offset, why))?;
        let camera_id = CameraId(r.u32("CAMERA_ID")?);
        let name = r.name()?;
        let num_points = r.count("keypoints", KEYPOINT_BYTES)?;
        if u32::try_from(num_points).is_err() {
            return Err(r.error_at(r.offset - 8, format!("{num_points} keypoints are too many")));
        }
        let mut points2d = Vec::with_capacity(num_points as usize);
        for _ in 0..num_points {
            let xy_offset = r.offset;
            let x = r.f64("X")?;
            let y = r.f64("Y")?;
            if let Some(why) = bad_coordinates(&format!("keypoint {}", points2d.len()), &[x, y]) {
                return Err(r.error_at(xy_offset, why));
            }
            let id = r.u64("POINT3D_ID")?;
            points2d.push(Point2D {
                xy: [x, y].into(),
                point3d_id: (id != u64::MAX).then_some(Point3DId(id)),
            });
        }
        images.push(ParsedImage {
            image: Image {
                id,
                name,
                camera_id,
                cam_from_world: Some(pose),
                points2d,
            },
            pose_loc: loc,
            points_loc: loc,
        });
    }
    r.finish()?;
    Ok(images)
}

fn read_points(mut r: BinReader) -> Result<Vec<(Point3DId, Point3D, Loc)>, ModelError> {
    let n = r.count("points", MIN_POINT_BYTES)?;
    let mut points = Vec::with_capacity(n as usize);
    for index in 0..n {
        r.record = Some(index);
        let loc = r.loc();
        let id = r.u64("POINT3D_ID")?;
        if id == u64::MAX {
            return Err(r.error_at(
                r.offset - 8,
                "POINT3D_ID 2^64-1 is reserved for \"no point\"",
            ));
        }
        let xyz_offset = r.offset;
        let xyz = [r.f64("X")?, r.f64("Y")?, r.f64("Z")?];
        if let Some(why) = bad_coordinates("X Y Z", &xyz) {
            return Err(r.error_at(xyz_offset, why));
        }
        let color = [r.u8("R")?, r.u8("G")?, r.u8("B")?];
        let error = r.f64("ERROR")?;
        let len = r.count("track elements", TRACK_ELEMENT_BYTES)?;
        let mut track = Vec::with_capacity(len as usize);
        for _ in 0..len {
            let image_id = ImageId(r.u32("IMAGE_ID of a track element")?);
            let point2d_idx = r.u32("POINT2D_IDX of a track element")?;
            track.push(TrackElement {
                image_id,
                point2d_idx,
            });
        }
        points.push((
            Point3DId(id),
            Point3D {
                xyz: xyz.into(),
                color,
                error,
                track,
            },
            loc,
        ));
    }
    r.finish()?;
    Ok(points)
}

/// Writes the three binary files into `dir` (an existing, empty folder).
pub(super) fn write(dir: &Path, rec: &Reconstruction) -> Result<(), ModelError> {
    let [cam_path, img_path, pts_path] = ModelFormat::Binary.paths(dir);
    write_file(&cam_path, |w| write_cameras(w, rec))?;
    write_file(&img_path, |w| write_images(w, rec))?;
    write_file(&pts_path, |w| write_points(w, rec))?;
    Ok(())
}

fn put_f64s(w: &mut impl Write, values: &[f64]) -> io::Result<()> {
    values
        .iter()
        .try_for_each(|v| w.write_all(&v.to_le_bytes()))
}

pub(super) fn write_cameras(w: &mut impl Write, rec: &Reconstruction) -> io::Result<()> {
    w.write_all(&(rec.cameras.len() as u64).to_le_bytes())?;
    for camera in rec.cameras.values() {
        w.write_all(&camera.id.0.to_le_bytes())?;
        w.write_all(&camera.model.id().to_le_bytes())?;
        w.write_all(&u64::from(camera.width).to_le_bytes())?;
        w.write_all(&u64::from(camera.height).to_le_bytes())?;
        put_f64s(w, &camera.params)?;
    }
    Ok(())
}

pub(super) fn write_images(w: &mut impl Write, rec: &Reconstruction) -> io::Result<()> {
    w.write_all(&(rec.num_registered_images() as u64).to_le_bytes())?;
    for image in rec.registered_images() {
        let Some(pose) = image.cam_from_world else {
            continue; // registered_images() yields only images with a pose
        };
        w.write_all(&image.id.0.to_le_bytes())?;
        put_f64s(w, &pose.quaternion_wxyz())?;
        put_f64s(w, pose.translation.as_slice())?;
        w.write_all(&image.camera_id.0.to_le_bytes())?;
        w.write_all(image.name.as_bytes())?;
        w.write_all(&[0])?;
        w.write_all(&(image.points2d.len() as u64).to_le_bytes())?;
        for p in &image.points2d {
            put_f64s(w, &[p.xy.x, p.xy.y])?;
            let id = p.point3d_id.map_or(u64::MAX, |id| id.0);
            w.write_all(&id.to_le_bytes())?;
        }
    }
    Ok(())
}

pub(super) fn write_points(w: &mut impl Write, rec: &Reconstruction) -> io::Result<()> {
    w.write_all(&(rec.points3d.len() as u64).to_le_bytes())?;
    for (id, p) in &rec.points3d {
        w.write_all(&id.0.to_le_bytes())?;
        put_f64s(w, p.xyz.as_slice())?;
        w.write_all(&p.color)?;
        w.write_all(&p.error.to_le_bytes())?;
        w.write_all(&(p.track.len() as u64).to_le_bytes())?;
        for el in &p.track {
            w.write_all(&el.image_id.0.to_le_bytes())?;
            w.write_all(&el.point2d_idx.to_le_bytes())?;
        }
    }
    Ok(())
}
