//! LAS and LAZ reader, through the `las` crate (with `laz` for compressed
//! files). LAS stores scaled integer coordinates; they are converted to f64 by
//! the header's scale and offset, to metres when the file's coordinate
//! reference system says feet ([`super::units`]), then to the cloud's local
//! origin. LAS has no normals.
use std::path::Path;

use super::units::{las_units, CrsUnits, LengthUnit};
use super::{CloudFormat, CloudSink, LoadReport, MapIoError, ReadOptions};
use crate::map::PointCloud;

/// Points decoded per batch ...
const BATCH_POINTS: u64 = 1 << 16;
/// ... and at most this many bytes of them.
const BATCH_BYTES: u64 = 1 << 24;

/// Reads a LAS or LAZ file, leaving out the points of the classes
/// `options.drop_las_classes` and those flagged withheld (counted in the
/// report), in metres: the unit `options.units` gives, else the one the
/// file's coordinate reference system gives (longitude and latitude are an
/// error).
pub fn read_las(
    path: &Path,
    options: &ReadOptions,
) -> Result<(PointCloud, LoadReport), MapIoError> {
    let las_err = |source| MapIoError::Las {
        path: path.to_path_buf(),
        source,
    };
    // Open ourselves first so a missing file reads as an I/O error.
    let file = std::fs::File::open(path).map_err(|e| MapIoError::io(path, e))?;
    let file_len = file.metadata().map_err(|e| MapIoError::io(path, e))?.len();
    let read = std::io::BufReader::with_capacity(super::READ_BUFFER_BYTES, file);
    let mut reader = ::las::Reader::new(read).map_err(las_err)?;
    let header = reader.header().clone();
    let format = if header.point_format().is_compressed {
        CloudFormat::Laz
    } else {
        CloudFormat::Las
    };
    let declared = header.number_of_points();
    let record = u64::from(header.point_format().len()).max(1);
    let hint = declared.min(file_len / record + 1) as usize;
    let mut sink = CloudSink::new(format, hint, false, false);
    let units_err = |message: String| MapIoError::Units {
        path: path.to_path_buf(),
        message,
    };
    let (horizontal, vertical, source) = match options.units.unit() {
        Some(unit) => (unit.clone(), unit, "as given".to_string()),
        None => match las_units(&header, path).map_err(|e| {
            units_err(format!("{e}; give the unit with `--input-units` (map, prepare-map)"))
        })? {
            CrsUnits::Unstated => (LengthUnit::metre(), LengthUnit::metre(), String::new()),
            CrsUnits::Linear {
                horizontal,
                vertical,
                source,
            } => (horizontal, vertical, format!("from {source}")),
            CrsUnits::Geographic { name, source } => {
                return Err(units_err(format!(
                    "the coordinate reference system of {source} is geographic ({name}): longitude \
                     and latitude in degrees, not metres; reproject the cloud to a projected CRS in \
                     metres (UTM, say) first, or give `--input-units m` (map, prepare-map) if the record is wrong"
                )))
            }
        },
    };
    let to_metres = [horizontal.metres, horizontal.metres, vertical.metres];
    if !horizontal.is_metre() || !vertical.is_metre() {
        sink.report.metres_per_unit = [horizontal.metres, vertical.metres];
        sink.report.units = Some(if horizontal == vertical {
            format!("{} ({source})", horizontal.name)
        } else {
            format!(
                "{} horizontally and {} vertically ({source})",
                horizontal.name, vertical.name
            )
        });
    }
    // The header's bounds give an origin near the middle of the cloud,
    // unless they span more than f32 offsets from their middle keep to a
    // millimetre (an outlier, often a noise point left out below, stretched
    // them) or they put the origin at zero (small coordinates, or bounds a
    // writer left unset): then the first point kept sets the origin.
    let bounds = header.bounds();
    let centre = [
        0.5 * (bounds.min.x + bounds.max.x) * to_metres[0],
        0.5 * (bounds.min.y + bounds.max.y) * to_metres[1],
        0.5 * (bounds.min.z + bounds.max.z) * to_metres[2],
    ];
    let spans = [
        (bounds.max.x - bounds.min.x) * to_metres[0],
        (bounds.max.y - bounds.min.y) * to_metres[1],
        (bounds.max.z - bounds.min.z) * to_metres[2],
    ];
    let tight = spans
        .iter()
        .all(|s| s.is_finite() && *s <= 2.0 * super::PRECISION_WARNING_OFFSET_M);
    if declared > 0 && tight && centre.iter().all(|c| c.is_finite()) {
        let origin = super::choose_origin(centre);
        if origin != nalgebra::Vector3::zeros() {
            sink.set_origin(origin);
        }
    }
    let mut drop_class = [false; 256];
    for &class in &options.drop_las_classes {
        drop_class[usize::from(class)] = true;
    }
    // The withheld flag: bit 7 of byte 15 in the legacy formats (0-5), bit 2
    // of byte 15 in the extended ones (6-10).
    let withheld_bit = if header.point_format().is_extended {
        0b0000_0100u8
    } else {
        0b1000_0000u8
    };
    let mut batch = ::las::PointDataBuilder::new().for_header(&header).build();
    // At most BATCH_BYTES of records at a time: a header may declare long
    // records (up to 64 KiB), and the batch is allocated before any is read.
    let batch_points = BATCH_POINTS.min((BATCH_BYTES / batch.record_len().max(1) as u64).max(1));
    let mut done = 0u64;
    while done < declared {
        let want = (declared - done).min(batch_points);
        let got = reader.fill_points(want, &mut batch).map_err(las_err)?;
        if got == 0 {
            break;
        }
        let records = batch.raw_bytes().chunks_exact(batch.record_len());
        let coordinates = batch.x().zip(batch.y()).zip(batch.z());
        for ((((x, y), z), class), record) in coordinates.zip(batch.classification()).zip(records) {
            if record[15] & withheld_bit != 0 {
                sink.report.points_read += 1;
                sink.report.dropped_withheld += 1;
            } else if drop_class[usize::from(class)] {
                sink.report.points_read += 1;
                sink.report.dropped_by_class += 1;
            } else {
                let p = [x * to_metres[0], y * to_metres[1], z * to_metres[2]];
                sink.push(p, [0.0; 3], 0.0);
            }
        }
        done += got;
    }
    if done < declared {
        return Err(MapIoError::Truncated {
            path: path.to_path_buf(),
            declared,
            read: done,
        });
    }
    Ok(sink.finish())
}
