//! LAS and LAZ reader, through the `las` crate (with `laz` for compressed
//! files). LAS stores scaled integer coordinates; they are converted to f64 by
//! the header's scale and offset, then to the cloud's local origin. LAS has
//! no normals.
use std::path::Path;

use super::{CloudFormat, CloudSink, LoadReport, MapIoError};
use crate::map::PointCloud;

/// Points decoded per batch.
const BATCH_POINTS: u64 = 1 << 16;

/// Reads a LAS or LAZ file, leaving out the points of the classes
/// `drop_classes` and those flagged withheld (counted in the report).
pub fn read_las(path: &Path, drop_classes: &[u8]) -> Result<(PointCloud, LoadReport), MapIoError> {
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
    // The header's bounds give an origin near the middle of the cloud,
    // unless they span more than f32 offsets from their middle keep to a
    // millimetre (an outlier, often a noise point left out below, stretched
    // them) or they put the origin at zero (small coordinates, or bounds a
    // writer left unset): then the first point kept sets the origin.
    let bounds = header.bounds();
    let centre = [
        0.5 * (bounds.min.x + bounds.max.x),
        0.5 * (bounds.min.y + bounds.max.y),
        0.5 * (bounds.min.z + bounds.max.z),
    ];
    let spans = [
        bounds.max.x - bounds.min.x,
        bounds.max.y - bounds.min.y,
        bounds.max.z - bounds.min.z,
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
    for &class in drop_classes {
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
    let mut done = 0u64;
    while done < declared {
        let want = (declared - done).min(BATCH_POINTS);
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
                sink.push([x, y, z], [0.0; 3], 0.0);
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
