//! Point-cloud readers and writers: PLY (ascii, binary little and big endian),
//! PCD (ascii, binary, binary_compressed), LAS/LAZ and E57 (read only).
//!
//! Every reader streams the file once into a [`PointCloud`]. Coordinates are
//! read as f64; the local origin is chosen once from the first finite point
//! (see [`choose_origin`]) and subtracted before the f32 offsets are stored, so
//! UTM-sized coordinates (10^5..10^7 m) keep sub-millimetre resolution.
//!
//! Points whose position has a NaN or infinite coordinate are dropped and
//! counted in the [`LoadReport`]. Normals are kept when their length is within
//! [`NORMAL_UNIT_TOLERANCE`] of 1 (and then renormalised); other normals (zero,
//! NaN, infinite, far from unit length) are stored as `[0, 0, 0]` and counted
//! as invalid, so that preparation re-estimates them
//! ([`crate::map::prepare::estimate_normals`]).
//!
//! Errors ([`MapIoError`]) name the file and what is wrong.
use std::fmt;
use std::fs::File;
use std::io::{BufReader, Read};
use std::path::{Path, PathBuf};

use nalgebra::Vector3;

use crate::map::PointCloud;

pub mod e57;
pub mod las;
pub mod pcd;
pub mod ply;
pub mod units;

pub use ply::{write_ply, PlyEncoding};
pub use units::InputUnits;

/// A normal whose length differs from 1 by more than this is invalid.
pub const NORMAL_UNIT_TOLERANCE: f64 = 1e-2;

/// Coordinates at least this large (metres, any axis of the first finite
/// point) move the local origin away from zero.
pub const LARGE_COORDINATE_M: f64 = 1000.0;

/// Size of the read buffers (bytes).
pub(crate) const READ_BUFFER_BYTES: usize = 1 << 22;

/// What went wrong while reading or writing a point cloud. Every variant names
/// the file.
#[derive(Debug, thiserror::Error)]
pub enum MapIoError {
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "{}: unknown point-cloud format (expected a PLY, PCD, LAS, LAZ or E57 file: \
         extension .ply/.pcd/.las/.laz/.e57 or a ply/PCD/LASF/ASTM-E57 signature)",
        path.display()
    )]
    UnknownFormat { path: PathBuf },
    #[error(
        "{} is a folder: merge its point clouds into one map first, with \
         `colmap-lidar prepare-map --input {} --output MAP.ply` (MAP.ply outside the folder)",
        path.display(),
        path.display()
    )]
    Folder { path: PathBuf },
    #[error("{}: bad header: {message}", path.display())]
    Header { path: PathBuf, message: String },
    #[error("{}: the point records have no `{name}` coordinate", path.display())]
    MissingCoordinate { path: PathBuf, name: String },
    #[error(
        "{}: truncated body: the header declares {declared} points but the file ends after {read}",
        path.display()
    )]
    Truncated {
        path: PathBuf,
        declared: u64,
        read: u64,
    },
    #[error(
        "{}: the header declares {declared} points but the body holds more data ({detail})",
        path.display()
    )]
    CountMismatch {
        path: PathBuf,
        declared: u64,
        detail: String,
    },
    #[error("{}: line {line}: {message}", path.display())]
    Body {
        path: PathBuf,
        line: u64,
        message: String,
    },
    #[error("{}: unsupported: {message}", path.display())]
    Unsupported { path: PathBuf, message: String },
    #[error("{}: {message}", path.display())]
    Units { path: PathBuf, message: String },
    #[error("{}: LAS/LAZ: {source}", path.display())]
    Las {
        path: PathBuf,
        #[source]
        source: ::las::Error,
    },
    #[error("{}: E57: {source}", path.display())]
    E57 {
        path: PathBuf,
        #[source]
        source: ::e57::Error,
    },
}

impl MapIoError {
    pub(crate) fn io(path: &Path, source: std::io::Error) -> Self {
        MapIoError::Io {
            path: path.to_path_buf(),
            source,
        }
    }
    pub(crate) fn header(path: &Path, message: impl Into<String>) -> Self {
        MapIoError::Header {
            path: path.to_path_buf(),
            message: message.into(),
        }
    }
    pub(crate) fn unsupported(path: &Path, message: impl Into<String>) -> Self {
        MapIoError::Unsupported {
            path: path.to_path_buf(),
            message: message.into(),
        }
    }
}

/// The file formats the readers understand.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CloudFormat {
    PlyAscii,
    PlyBinaryLittleEndian,
    PlyBinaryBigEndian,
    PcdAscii,
    PcdBinary,
    PcdBinaryCompressed,
    Las,
    Laz,
    E57,
}

impl fmt::Display for CloudFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let name = match self {
            CloudFormat::PlyAscii => "PLY ascii",
            CloudFormat::PlyBinaryLittleEndian => "PLY binary little endian",
            CloudFormat::PlyBinaryBigEndian => "PLY binary big endian",
            CloudFormat::PcdAscii => "PCD ascii",
            CloudFormat::PcdBinary => "PCD binary",
            CloudFormat::PcdBinaryCompressed => "PCD binary_compressed",
            CloudFormat::Las => "LAS",
            CloudFormat::Laz => "LAZ",
            CloudFormat::E57 => "E57",
        };
        f.write_str(name)
    }
}

/// What a reader saw, returned beside the cloud.
#[derive(Clone, Debug, PartialEq)]
pub struct LoadReport {
    pub format: CloudFormat,
    /// Point records in the file (kept + dropped).
    pub points_read: u64,
    /// Records dropped because a coordinate was NaN or infinite (E57: also
    /// records flagged invalid or holding only a direction).
    pub dropped_non_finite: u64,
    /// True when the records carry normals (`nx ny nz` or `normal_x ...`).
    pub had_normals: bool,
    /// Kept points whose normal was zero, NaN, infinite or not unit length
    /// (stored as `[0, 0, 0]`).
    pub normals_invalid: u64,
    /// LAS/LAZ records dropped for their class ([`ReadOptions::drop_las_classes`],
    /// by default the ASPRS noise classes).
    pub dropped_by_class: u64,
    /// LAS/LAZ records flagged withheld (to be treated as deleted, says the
    /// format's specification), always dropped.
    pub dropped_withheld: u64,
    /// Largest coordinate of a kept point relative to the chosen origin
    /// (metres, any axis). Above [`PRECISION_WARNING_OFFSET_M`] the f32
    /// offsets lose millimetres (a far-away first point chose the origin);
    /// readers then log a warning.
    pub max_offset_m: f64,
    /// Metres per coordinate unit, horizontal (x, y) and vertical (z), as
    /// applied while reading: `[1, 1]` for metres.
    pub metres_per_unit: [f64; 2],
    /// The units converted from and where they were read (`None`: metres).
    pub units: Option<String>,
}

/// Offsets beyond this (metres) are stored with a resolution coarser than
/// 1 mm in f32.
pub const PRECISION_WARNING_OFFSET_M: f64 = 8192.0;

impl LoadReport {
    pub(crate) fn new(format: CloudFormat) -> Self {
        LoadReport {
            format,
            points_read: 0,
            dropped_non_finite: 0,
            had_normals: false,
            normals_invalid: 0,
            dropped_by_class: 0,
            dropped_withheld: 0,
            max_offset_m: 0.0,
            metres_per_unit: [1.0, 1.0],
            units: None,
        }
    }
}

/// The local origin for a cloud whose first finite point is `first_m` (map
/// frame, metres): zero when every coordinate is below
/// [`LARGE_COORDINATE_M`] in magnitude (small clouds keep their f32 values
/// bit for bit), else the point rounded to whole metres.
pub fn choose_origin(first_m: [f64; 3]) -> Vector3<f64> {
    if first_m.iter().all(|c| c.abs() < LARGE_COORDINATE_M) {
        Vector3::zeros()
    } else {
        Vector3::new(first_m[0].round(), first_m[1].round(), first_m[2].round())
    }
}

/// Accumulates decoded records into a [`PointCloud`]: chooses the origin,
/// drops non-finite points, validates normals. Shared by all readers.
pub(crate) struct CloudSink {
    origin: Option<Vector3<f64>>,
    points: Vec<[f32; 3]>,
    normals: Option<Vec<[f32; 3]>>,
    planarity: Option<Vec<f32>>,
    pub(crate) report: LoadReport,
}

impl CloudSink {
    /// `capacity_hint` is only a hint (a lying header must not allocate huge
    /// buffers: callers bound it by the file size).
    pub(crate) fn new(
        format: CloudFormat,
        capacity_hint: usize,
        with_normals: bool,
        with_planarity: bool,
    ) -> Self {
        let mut report = LoadReport::new(format);
        report.had_normals = with_normals;
        CloudSink {
            origin: None,
            points: Vec::with_capacity(capacity_hint),
            normals: with_normals.then(|| Vec::with_capacity(capacity_hint)),
            planarity: with_planarity.then(|| Vec::with_capacity(capacity_hint)),
            report,
        }
    }

    /// Adds one record. `normal` and `planarity` are read only when the sink
    /// was created with them.
    #[inline]
    pub(crate) fn push(&mut self, p_m: [f64; 3], normal: [f64; 3], planarity: f64) {
        self.report.points_read += 1;
        if !(p_m[0].is_finite() && p_m[1].is_finite() && p_m[2].is_finite()) {
            self.report.dropped_non_finite += 1;
            return;
        }
        let origin = *self.origin.get_or_insert_with(|| choose_origin(p_m));
        let offset = [p_m[0] - origin.x, p_m[1] - origin.y, p_m[2] - origin.z];
        let largest = offset[0].abs().max(offset[1].abs()).max(offset[2].abs());
        if largest > self.report.max_offset_m {
            self.report.max_offset_m = largest;
        }
        self.points
            .push([offset[0] as f32, offset[1] as f32, offset[2] as f32]);
        if let Some(normals) = &mut self.normals {
            let len =
                (normal[0] * normal[0] + normal[1] * normal[1] + normal[2] * normal[2]).sqrt();
            if len.is_finite() && (len - 1.0).abs() <= NORMAL_UNIT_TOLERANCE {
                normals.push([
                    (normal[0] / len) as f32,
                    (normal[1] / len) as f32,
                    (normal[2] / len) as f32,
                ]);
            } else {
                self.report.normals_invalid += 1;
                normals.push([0.0; 3]);
            }
        }
        if let Some(values) = &mut self.planarity {
            values.push(if planarity.is_finite() {
                planarity.clamp(0.0, 1.0) as f32
            } else {
                0.0
            });
        }
    }

    /// Fixes the origin before the first point (e.g. from a header's bounds).
    pub(crate) fn set_origin(&mut self, origin: Vector3<f64>) {
        self.origin = Some(origin);
    }

    pub(crate) fn finish(self) -> (PointCloud, LoadReport) {
        let mut cloud = PointCloud {
            origin: self.origin.unwrap_or_else(Vector3::zeros),
            points: self.points,
            normals: self.normals,
            planarity: self.planarity,
        };
        cloud.points.shrink_to_fit();
        (cloud, self.report)
    }
}

/// Reads a point cloud, choosing the reader from the extension (`.ply`,
/// `.pcd`, `.las`, `.laz`, `.e57`, any case) or, failing that, from the file's first
/// bytes.
pub fn read_point_cloud(path: &Path) -> Result<(PointCloud, LoadReport), MapIoError> {
    read_point_cloud_with(path, &ReadOptions::default())
}

/// ASPRS LAS classes of noise: 7 (low point), 18 (high noise).
pub const LAS_NOISE_CLASSES: [u8; 2] = [7, 18];

/// What the readers leave out, and the unit of the coordinates.
#[derive(Clone, Debug, PartialEq)]
pub struct ReadOptions {
    /// LAS/LAZ classification values whose points are dropped (default
    /// [`LAS_NOISE_CLASSES`]; empty keeps every class).
    pub drop_las_classes: Vec<u8>,
    /// The coordinates' length unit (default: as the file says, see
    /// [`units`]); coordinates are converted to metres as they are read.
    pub units: InputUnits,
}

impl Default for ReadOptions {
    fn default() -> Self {
        ReadOptions {
            drop_las_classes: LAS_NOISE_CLASSES.to_vec(),
            units: InputUnits::Auto,
        }
    }
}

/// [`read_point_cloud`] with other [`ReadOptions`].
pub fn read_point_cloud_with(
    path: &Path,
    options: &ReadOptions,
) -> Result<(PointCloud, LoadReport), MapIoError> {
    if path.is_dir() {
        return Err(MapIoError::Folder {
            path: path.to_path_buf(),
        });
    }
    let (mut cloud, mut report) = read_any(path, options)?;
    let is_las = matches!(report.format, CloudFormat::Las | CloudFormat::Laz);
    if let (false, Some(unit)) = (is_las, options.units.unit()) {
        if !unit.is_metre() {
            cloud.scale_coordinates(unit.metres);
            report.max_offset_m *= unit.metres;
            report.metres_per_unit = [unit.metres; 2];
            report.units = Some(format!("{} (as given)", unit.name));
        }
    }
    if let Some(units) = &report.units {
        log::warn!(
            "{}: coordinates in {units}, converted to metres (x {:.10}, z {:.10}): the map, the \
             model, --init-pose, --pose-priors and --crop are in metres",
            path.display(),
            report.metres_per_unit[0],
            report.metres_per_unit[1]
        );
    }
    if report.dropped_by_class > 0 || report.dropped_withheld > 0 {
        log::info!(
            "{}: {} points of the classes {:?} and {} flagged withheld left out",
            path.display(),
            report.dropped_by_class,
            options.drop_las_classes,
            report.dropped_withheld
        );
    }
    if report.max_offset_m > PRECISION_WARNING_OFFSET_M {
        log::warn!(
            "{}: points lie up to {:.0} m from the local origin {:?} chosen from the first point; \
             coordinates that far keep only {:.1} mm resolution",
            path.display(),
            report.max_offset_m,
            cloud.origin.as_slice(),
            1000.0 * report.max_offset_m / f64::from(1u32 << 24)
        );
    }
    Ok((cloud, report))
}

fn read_any(path: &Path, options: &ReadOptions) -> Result<(PointCloud, LoadReport), MapIoError> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase());
    match ext.as_deref() {
        Some("ply") => return ply::read_ply(path),
        Some("pcd") => return pcd::read_pcd(path),
        Some("las") | Some("laz") => return las::read_las(path, options),
        Some("e57") => return e57::read_e57(path),
        _ => {}
    }
    let mut magic = [0u8; 16];
    let mut file = File::open(path).map_err(|e| MapIoError::io(path, e))?;
    let mut got = 0;
    while got < magic.len() {
        let n = file
            .read(&mut magic[got..])
            .map_err(|e| MapIoError::io(path, e))?;
        if n == 0 {
            break;
        }
        got += n;
    }
    let magic = &magic[..got];
    if magic.starts_with(b"ply\n") || magic.starts_with(b"ply\r\n") {
        ply::read_ply(path)
    } else if magic.starts_with(b"LASF") {
        las::read_las(path, options)
    } else if magic.starts_with(b"ASTM-E57") {
        e57::read_e57(path)
    } else if magic.starts_with(b"# .PCD") || magic.starts_with(b"VERSION") {
        pcd::read_pcd(path)
    } else {
        Err(MapIoError::UnknownFormat {
            path: path.to_path_buf(),
        })
    }
}

/// Opens `path` with a large read buffer.
pub(crate) fn open_buffered(path: &Path) -> Result<(BufReader<File>, u64), MapIoError> {
    let file = File::open(path).map_err(|e| MapIoError::io(path, e))?;
    let len = file.metadata().map_err(|e| MapIoError::io(path, e))?.len();
    Ok((BufReader::with_capacity(READ_BUFFER_BYTES, file), len))
}

/// Reads until `buf` is full or the input ends; returns the bytes read.
pub(crate) fn read_full(read: &mut impl Read, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut got = 0;
    while got < buf.len() {
        match read.read(&mut buf[got..]) {
            Ok(0) => break,
            Ok(n) => got += n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(got)
}

/// Numeric types of PLY and PCD properties.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum ScalarType {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    I64,
    U64,
    F32,
    F64,
}

impl ScalarType {
    pub(crate) fn size(self) -> usize {
        match self {
            ScalarType::I8 | ScalarType::U8 => 1,
            ScalarType::I16 | ScalarType::U16 => 2,
            ScalarType::I32 | ScalarType::U32 | ScalarType::F32 => 4,
            ScalarType::I64 | ScalarType::U64 | ScalarType::F64 => 8,
        }
    }

    /// Decodes one value from the start of `b` (at least `size()` bytes).
    #[inline(always)]
    pub(crate) fn decode(self, b: &[u8], big_endian: bool) -> f64 {
        macro_rules! get {
            ($t:ty, $n:expr) => {{
                let mut a = [0u8; $n];
                a.copy_from_slice(&b[..$n]);
                if big_endian {
                    <$t>::from_be_bytes(a)
                } else {
                    <$t>::from_le_bytes(a)
                }
            }};
        }
        match self {
            ScalarType::I8 => f64::from(b[0] as i8),
            ScalarType::U8 => f64::from(b[0]),
            ScalarType::I16 => f64::from(get!(i16, 2)),
            ScalarType::U16 => f64::from(get!(u16, 2)),
            ScalarType::I32 => f64::from(get!(i32, 4)),
            ScalarType::U32 => f64::from(get!(u32, 4)),
            ScalarType::I64 => get!(i64, 8) as f64,
            ScalarType::U64 => get!(u64, 8) as f64,
            ScalarType::F32 => f64::from(get!(f32, 4)),
            ScalarType::F64 => get!(f64, 8),
        }
    }

    /// Decodes an integer (list lengths); `None` for float types or negative
    /// values.
    pub(crate) fn decode_count(self, b: &[u8], big_endian: bool) -> Option<u64> {
        match self {
            ScalarType::F32 | ScalarType::F64 => None,
            _ => {
                let v = self.decode(b, big_endian);
                (v >= 0.0).then_some(v as u64)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn origin_is_zero_for_small_and_rounded_for_large_coordinates() {
        assert_eq!(choose_origin([1.5, -2.0, 999.0]), Vector3::zeros());
        assert_eq!(
            choose_origin([512_345.678, 5_412_345.4, 52.6]),
            Vector3::new(512_346.0, 5_412_345.0, 53.0)
        );
    }

    #[test]
    fn sink_drops_non_finite_points_and_flags_bad_normals() {
        let mut sink = CloudSink::new(CloudFormat::PlyAscii, 4, true, false);
        sink.push([1.0, 2.0, 3.0], [0.0, 0.0, 2.0], 0.0);
        sink.push([f64::NAN, 2.0, 3.0], [0.0, 0.0, 1.0], 0.0);
        sink.push([1.0, f64::INFINITY, 3.0], [0.0, 0.0, 1.0], 0.0);
        sink.push([4.0, 5.0, 6.0], [0.0, 0.6, 0.8], 0.0);
        sink.push([7.0, 8.0, 9.0], [f64::NAN, 0.0, 1.0], 0.0);
        let (cloud, report) = sink.finish();
        assert_eq!(report.points_read, 5);
        assert_eq!(report.dropped_non_finite, 2);
        assert_eq!(report.normals_invalid, 2);
        assert_eq!(
            cloud.points,
            vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]]
        );
        assert_eq!(
            cloud.normals.unwrap(),
            vec![[0.0; 3], [0.0, 0.6, 0.8], [0.0; 3]]
        );
    }

    #[test]
    fn scalar_decoding_both_endians() {
        assert_eq!(ScalarType::I16.decode(&[0xff, 0xfe], true), -2.0);
        assert_eq!(ScalarType::I16.decode(&[0xfe, 0xff], false), -2.0);
        assert_eq!(ScalarType::U8.decode(&[200], false), 200.0);
        assert_eq!(ScalarType::I8.decode(&[200], false), -56.0);
        let b = 1.25f64.to_be_bytes();
        assert_eq!(ScalarType::F64.decode(&b, true), 1.25);
        let b = (-7.5f32).to_le_bytes();
        assert_eq!(ScalarType::F32.decode(&b, false), -7.5);
        assert_eq!(ScalarType::U32.decode_count(&[3, 0, 0, 0], false), Some(3));
        assert_eq!(ScalarType::F32.decode_count(&[0, 0, 0, 0], false), None);
    }
}
