//! LAS and LAZ reader, through the `las` crate (with `laz` for compressed
//! files). LAS stores scaled integer coordinates; they are converted to f64 by
//! the header's scale and offset, then to the cloud's local origin. LAS has
//! no normals.
use std::path::Path;

use super::{CloudFormat, CloudSink, LoadReport, MapIoError};
use crate::map::PointCloud;

/// Points decoded per batch.
const BATCH_POINTS: u64 = 1 << 16;

/// Reads a LAS or LAZ file.
pub fn read_las(path: &Path) -> Result<(PointCloud, LoadReport), MapIoError> {
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
    // The header's bounds give an origin near the middle of the cloud.
    let bounds = header.bounds();
    let centre = [
        0.5 * (bounds.min.x + bounds.max.x),
        0.5 * (bounds.min.y + bounds.max.y),
        0.5 * (bounds.min.z + bounds.max.z),
    ];
    if declared > 0 && centre.iter().all(|c| c.is_finite()) {
        sink.set_origin(super::choose_origin(centre));
    }
    let mut batch = ::las::PointDataBuilder::new().for_header(&header).build();
    let mut done = 0u64;
    while done < declared {
        let want = (declared - done).min(BATCH_POINTS);
        let got = reader.fill_points(want, &mut batch).map_err(las_err)?;
        if got == 0 {
            break;
        }
        for ((x, y), z) in batch.x().zip(batch.y()).zip(batch.z()) {
            sink.push([x, y, z], [0.0; 3], 0.0);
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
