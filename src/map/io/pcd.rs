//! PCD reader (Point Cloud Library format, v0.7 and older headers): `DATA
//! ascii`, `binary` (little-endian records) and `binary_compressed` (LZF
//! compressed, one column per field). Fields `x y z`, optional `normal_x
//! normal_y normal_z` (or `nx ny nz`); other fields are ignored.
use std::io::{BufRead, Read};
use std::path::Path;

use super::{open_buffered, CloudFormat, CloudSink, LoadReport, MapIoError, ScalarType};
use crate::map::PointCloud;

const MAX_HEADER_LINES: usize = 1000;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum DataKind {
    Ascii,
    Binary,
    BinaryCompressed,
}

#[derive(Debug)]
struct Field {
    name: String,
    ty: ScalarType,
    count: usize,
}

#[derive(Debug)]
struct Header {
    fields: Vec<Field>,
    /// Bytes of one point's record (at most [`MAX_RECORD_BYTES`]).
    record: usize,
    points: u64,
    data: DataKind,
}

/// Largest point record a PCD header may declare, bytes: far beyond the
/// widest real layouts (a VFH descriptor is 308 floats), and small enough
/// that no offset computed from it overflows.
const MAX_RECORD_BYTES: usize = 1 << 20;

/// Most bytes LZF can expand one compressed byte into: a back reference of
/// at most 264 bytes takes 3 (rounded up).
const LZF_MAX_EXPANSION: u64 = 100;

fn pcd_type(kind: &str, size: usize) -> Option<ScalarType> {
    Some(match (kind, size) {
        ("I", 1) => ScalarType::I8,
        ("I", 2) => ScalarType::I16,
        ("I", 4) => ScalarType::I32,
        ("I", 8) => ScalarType::I64,
        ("U", 1) => ScalarType::U8,
        ("U", 2) => ScalarType::U16,
        ("U", 4) => ScalarType::U32,
        ("U", 8) => ScalarType::U64,
        ("F", 4) => ScalarType::F32,
        ("F", 8) => ScalarType::F64,
        _ => return None,
    })
}

fn read_header(read: &mut impl BufRead, path: &Path) -> Result<Header, MapIoError> {
    let mut names: Option<Vec<String>> = None;
    let mut sizes: Option<Vec<usize>> = None;
    let mut types: Option<Vec<String>> = None;
    let mut counts: Option<Vec<usize>> = None;
    let mut width: Option<u64> = None;
    let mut height: Option<u64> = None;
    let mut points: Option<u64> = None;
    let mut line = Vec::new();
    for line_no in 1..=MAX_HEADER_LINES {
        line.clear();
        let n = (&mut *read)
            .take(1 << 16)
            .read_until(b'\n', &mut line)
            .map_err(|e| MapIoError::io(path, e))?;
        if n == 0 {
            return Err(MapIoError::header(
                path,
                "the file ends before the `DATA` line",
            ));
        }
        let text = std::str::from_utf8(&line)
            .map_err(|_| MapIoError::header(path, format!("header line {line_no} is not text")))?;
        let text = text.trim();
        if text.is_empty() || text.starts_with('#') {
            continue;
        }
        let mut words = text.split_ascii_whitespace();
        // Not empty (checked above).
        let key = words.next().unwrap_or("");
        let rest: Vec<&str> = words.collect();
        let numbers = |what: &str| -> Result<Vec<usize>, MapIoError> {
            rest.iter()
                .map(|w| {
                    w.parse::<usize>()
                        .map_err(|_| MapIoError::header(path, format!("bad {what} value `{w}`")))
                })
                .collect()
        };
        let one = |what: &str| -> Result<u64, MapIoError> {
            match rest.as_slice() {
                [w] => w
                    .parse::<u64>()
                    .map_err(|_| MapIoError::header(path, format!("bad {what} value `{w}`"))),
                _ => Err(MapIoError::header(path, format!("{what} needs one value"))),
            }
        };
        match key.to_ascii_uppercase().as_str() {
            "VERSION" | "VIEWPOINT" => {}
            "FIELDS" => names = Some(rest.iter().map(|s| s.to_string()).collect()),
            "SIZE" => sizes = Some(numbers("SIZE")?),
            "TYPE" => types = Some(rest.iter().map(|s| s.to_ascii_uppercase()).collect()),
            "COUNT" => counts = Some(numbers("COUNT")?),
            "WIDTH" => width = Some(one("WIDTH")?),
            "HEIGHT" => height = Some(one("HEIGHT")?),
            "POINTS" => points = Some(one("POINTS")?),
            "DATA" => {
                let data = match rest.first().map(|s| s.to_ascii_lowercase()).as_deref() {
                    Some("ascii") => DataKind::Ascii,
                    Some("binary") => DataKind::Binary,
                    Some("binary_compressed") => DataKind::BinaryCompressed,
                    other => {
                        return Err(MapIoError::header(
                            path,
                            format!("unknown DATA kind `{}`", other.unwrap_or("")),
                        ))
                    }
                };
                let names = names.ok_or_else(|| MapIoError::header(path, "no FIELDS line"))?;
                let sizes = sizes.ok_or_else(|| MapIoError::header(path, "no SIZE line"))?;
                let types = types.ok_or_else(|| MapIoError::header(path, "no TYPE line"))?;
                let counts = counts.unwrap_or_else(|| vec![1; names.len()]);
                if sizes.len() != names.len()
                    || types.len() != names.len()
                    || counts.len() != names.len()
                {
                    return Err(MapIoError::header(
                        path,
                        "FIELDS, SIZE, TYPE and COUNT have different lengths",
                    ));
                }
                let mut fields = Vec::with_capacity(names.len());
                for i in 0..names.len() {
                    let ty = pcd_type(&types[i], sizes[i]).ok_or_else(|| {
                        MapIoError::header(
                            path,
                            format!(
                                "field `{}`: unsupported TYPE {} with SIZE {}",
                                names[i], types[i], sizes[i]
                            ),
                        )
                    })?;
                    if counts[i] == 0 {
                        return Err(MapIoError::header(
                            path,
                            format!("field `{}` has COUNT 0", names[i]),
                        ));
                    }
                    fields.push(Field {
                        name: names[i].clone(),
                        ty,
                        count: counts[i],
                    });
                }
                // Checked here, so that the readers' offsets cannot overflow.
                let record = fields.iter().try_fold(0usize, |sum, f| {
                    f.ty.size()
                        .checked_mul(f.count)
                        .and_then(|b| sum.checked_add(b))
                });
                let Some(record) = record.filter(|&r| r <= MAX_RECORD_BYTES) else {
                    return Err(MapIoError::header(
                        path,
                        format!(
                            "SIZE x COUNT make a point record of more than {MAX_RECORD_BYTES} bytes"
                        ),
                    ));
                };
                let wh = match (width, height) {
                    (Some(w), Some(h)) => Some(w.saturating_mul(h)),
                    (Some(w), None) => Some(w),
                    _ => None,
                };
                let points = match (points, wh) {
                    (Some(p), Some(wh)) if p != wh => {
                        return Err(MapIoError::header(
                            path,
                            format!("POINTS {p} disagrees with WIDTH x HEIGHT = {wh}"),
                        ))
                    }
                    (Some(p), _) => p,
                    (None, Some(wh)) => wh,
                    (None, None) => {
                        return Err(MapIoError::header(path, "neither POINTS nor WIDTH given"))
                    }
                };
                return Ok(Header {
                    fields,
                    record,
                    points,
                    data,
                });
            }
            other => {
                return Err(MapIoError::header(
                    path,
                    format!("line {line_no}: unknown keyword `{other}`"),
                ))
            }
        }
    }
    Err(MapIoError::header(
        path,
        "no `DATA` line in the first 1000 lines",
    ))
}

/// For each of x y z nx ny nz: (field index); plus whether normals exist.
fn locate(header: &Header, path: &Path) -> Result<([usize; 6], bool), MapIoError> {
    let find = |names: &[&str]| {
        header
            .fields
            .iter()
            .position(|f| names.contains(&f.name.as_str()))
    };
    let mut idx = [0usize; 6];
    for (k, name) in ["x", "y", "z"].iter().enumerate() {
        idx[k] = find(&[name]).ok_or_else(|| MapIoError::MissingCoordinate {
            path: path.to_path_buf(),
            name: name.to_string(),
        })?;
    }
    let normals = [
        find(&["normal_x", "nx"]),
        find(&["normal_y", "ny"]),
        find(&["normal_z", "nz"]),
    ];
    let with_normals = normals.iter().all(Option::is_some);
    if with_normals {
        for k in 0..3 {
            // Checked by `with_normals`.
            idx[3 + k] = normals[k].unwrap_or(0);
        }
    }
    Ok((idx, with_normals))
}

/// Reads a PCD file.
pub fn read_pcd(path: &Path) -> Result<(PointCloud, LoadReport), MapIoError> {
    let (mut read, file_len) = open_buffered(path)?;
    let header = read_header(&mut read, path)?;
    let (idx, with_normals) = locate(&header, path)?;
    let format = match header.data {
        DataKind::Ascii => CloudFormat::PcdAscii,
        DataKind::Binary => CloudFormat::PcdBinary,
        DataKind::BinaryCompressed => CloudFormat::PcdBinaryCompressed,
    };
    let record = header.record;
    let hint = header.points.min(file_len / record.max(1) as u64 + 1) as usize;
    let mut sink = CloudSink::new(format, hint, with_normals, false);
    let nfields = if with_normals { 6 } else { 3 };
    match header.data {
        DataKind::Ascii => {
            // Token position of each field's first value.
            let mut token_of_field = Vec::with_capacity(header.fields.len());
            let mut t = 0;
            for f in &header.fields {
                token_of_field.push(t);
                t += f.count;
            }
            let ntokens = t;
            let mut wanted = vec![usize::MAX; ntokens];
            for k in 0..nfields {
                wanted[token_of_field[idx[k]]] = k;
            }
            let mut line = Vec::new();
            let mut line_no = 0u64;
            let mut values = [0.0f64; 6];
            let mut done = 0u64;
            while done < header.points {
                line.clear();
                let n = read
                    .read_until(b'\n', &mut line)
                    .map_err(|e| MapIoError::io(path, e))?;
                if n == 0 {
                    return Err(MapIoError::Truncated {
                        path: path.to_path_buf(),
                        declared: header.points,
                        read: done,
                    });
                }
                line_no += 1;
                let text = std::str::from_utf8(&line).map_err(|_| MapIoError::Body {
                    path: path.to_path_buf(),
                    line: line_no,
                    message: "not text".to_string(),
                })?;
                if text.trim().is_empty() {
                    continue;
                }
                let mut count = 0;
                for (i, token) in text.split_ascii_whitespace().enumerate() {
                    count += 1;
                    if i < ntokens && wanted[i] != usize::MAX {
                        values[wanted[i]] = token.parse::<f64>().map_err(|_| MapIoError::Body {
                            path: path.to_path_buf(),
                            line: line_no,
                            message: format!("`{token}` is not a number"),
                        })?;
                    }
                }
                if count != ntokens {
                    return Err(MapIoError::Body {
                        path: path.to_path_buf(),
                        line: line_no,
                        message: format!("expected {ntokens} values, found {count}"),
                    });
                }
                sink.push(
                    [values[0], values[1], values[2]],
                    [values[3], values[4], values[5]],
                    0.0,
                );
                done += 1;
            }
            loop {
                line.clear();
                let n = read
                    .read_until(b'\n', &mut line)
                    .map_err(|e| MapIoError::io(path, e))?;
                if n == 0 {
                    break;
                }
                line_no += 1;
                if line.iter().any(|b| !b.is_ascii_whitespace()) {
                    return Err(MapIoError::CountMismatch {
                        path: path.to_path_buf(),
                        declared: header.points,
                        detail: format!("data line {line_no} follows the last declared point"),
                    });
                }
            }
        }
        DataKind::Binary => {
            let mut offset_of = Vec::with_capacity(header.fields.len());
            let mut o = 0;
            for f in &header.fields {
                offset_of.push(o);
                o += f.ty.size() * f.count;
            }
            let types: Vec<ScalarType> = (0..6).map(|k| header.fields[idx[k]].ty).collect();
            let offsets: Vec<usize> = (0..6).map(|k| offset_of[idx[k]]).collect();
            let per_block = (super::READ_BUFFER_BYTES / record).max(1);
            let mut block = vec![0u8; per_block * record];
            let mut done = 0u64;
            while done < header.points {
                let want = ((header.points - done).min(per_block as u64) as usize) * record;
                let got = super::read_full(&mut read, &mut block[..want])
                    .map_err(|e| MapIoError::io(path, e))?;
                let whole = got / record;
                for rec in block[..whole * record].chunks_exact(record) {
                    let mut v = [0.0f64; 6];
                    for k in 0..nfields {
                        v[k] = types[k].decode(&rec[offsets[k]..], false);
                    }
                    sink.push([v[0], v[1], v[2]], [v[3], v[4], v[5]], 0.0);
                }
                done += whole as u64;
                if got < want {
                    return Err(MapIoError::Truncated {
                        path: path.to_path_buf(),
                        declared: header.points,
                        read: done,
                    });
                }
            }
            let got = super::read_full(&mut read, &mut block[..record])
                .map_err(|e| MapIoError::io(path, e))?;
            if got >= record {
                return Err(MapIoError::CountMismatch {
                    path: path.to_path_buf(),
                    declared: header.points,
                    detail: "at least one more whole record follows".to_string(),
                });
            }
        }
        DataKind::BinaryCompressed => {
            let mut sizes = [0u8; 8];
            read.read_exact(&mut sizes)
                .map_err(|_| MapIoError::Truncated {
                    path: path.to_path_buf(),
                    declared: header.points,
                    read: 0,
                })?;
            let compressed = u32::from_le_bytes([sizes[0], sizes[1], sizes[2], sizes[3]]) as usize;
            let uncompressed = u32::from_le_bytes([sizes[4], sizes[5], sizes[6], sizes[7]]) as u64;
            let expected = header.points.saturating_mul(record as u64);
            if uncompressed != expected {
                return Err(MapIoError::header(
                    path,
                    format!(
                        "binary_compressed block holds {uncompressed} bytes but {} points of {record} bytes need {expected}",
                        header.points
                    ),
                ));
            }
            if uncompressed > (compressed as u64).saturating_mul(LZF_MAX_EXPANSION) {
                return Err(MapIoError::header(
                    path,
                    format!(
                        "binary_compressed block says {compressed} bytes expand to {uncompressed}, more than LZF can"
                    ),
                ));
            }
            if compressed as u64 > file_len {
                return Err(MapIoError::Truncated {
                    path: path.to_path_buf(),
                    declared: header.points,
                    read: 0,
                });
            }
            let mut packed = vec![0u8; compressed];
            let got =
                super::read_full(&mut read, &mut packed).map_err(|e| MapIoError::io(path, e))?;
            if got < compressed {
                return Err(MapIoError::Truncated {
                    path: path.to_path_buf(),
                    declared: header.points,
                    read: 0,
                });
            }
            let data = lzf_decompress(&packed, uncompressed as usize).map_err(|message| {
                MapIoError::Body {
                    path: path.to_path_buf(),
                    line: 0,
                    message: format!("corrupt LZF data: {message}"),
                }
            })?;
            // Column layout: field after field, each `points x size x count`.
            let n = header.points as usize;
            let mut column_of_field = Vec::with_capacity(header.fields.len());
            let mut o = 0;
            for f in &header.fields {
                column_of_field.push(o);
                o += f.ty.size() * f.count * n;
            }
            let stride: Vec<usize> = (0..6)
                .map(|k| header.fields[idx[k]].ty.size() * header.fields[idx[k]].count)
                .collect();
            for i in 0..n {
                let mut v = [0.0f64; 6];
                for k in 0..nfields {
                    let f = &header.fields[idx[k]];
                    let at = column_of_field[idx[k]] + i * stride[k];
                    v[k] = f.ty.decode(&data[at..], false);
                }
                sink.push([v[0], v[1], v[2]], [v[3], v[4], v[5]], 0.0);
            }
        }
    }
    Ok(sink.finish())
}

/// Decompresses an LZF stream into exactly `out_len` bytes.
///
/// LZF: a control byte `c`; `c < 32` starts a literal run of `c + 1` bytes;
/// otherwise a back reference of length `(c >> 5) + 2` (an extra length byte
/// is added when `c >> 5 == 7`) at distance `((c & 31) << 8) + next + 1`.
pub(crate) fn lzf_decompress(input: &[u8], out_len: usize) -> Result<Vec<u8>, String> {
    let mut out = Vec::with_capacity(out_len);
    let mut i = 0;
    while i < input.len() {
        let ctrl = input[i] as usize;
        i += 1;
        if ctrl < 32 {
            let len = ctrl + 1;
            if i + len > input.len() {
                return Err("literal run past the end of the input".into());
            }
            if out.len() + len > out_len {
                return Err("output longer than declared".into());
            }
            out.extend_from_slice(&input[i..i + len]);
            i += len;
        } else {
            let mut len = ctrl >> 5;
            if len == 7 {
                let extra = *input
                    .get(i)
                    .ok_or("back reference past the end of the input")?;
                len += extra as usize;
                i += 1;
            }
            len += 2;
            let low = *input
                .get(i)
                .ok_or("back reference past the end of the input")? as usize;
            i += 1;
            let distance = ((ctrl & 0x1f) << 8) + low + 1;
            if distance > out.len() {
                return Err("back reference before the start of the output".into());
            }
            if out.len() + len > out_len {
                return Err("output longer than declared".into());
            }
            let start = out.len() - distance;
            // Overlapping copies repeat bytes: copy one at a time.
            for j in 0..len {
                let b = out[start + j];
                out.push(b);
            }
        }
    }
    if out.len() != out_len {
        return Err(format!(
            "decompressed {} bytes, expected {out_len}",
            out.len()
        ));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lzf_literal_and_overlapping_back_reference() {
        // "abc" literal, then a back reference of length 6 at distance 3:
        // ctrl = (4 << 5) | 0, low = 2 -> len 4 + 2 = 6, distance 3.
        let input = [2, b'a', b'b', b'c', (4 << 5), 2];
        assert_eq!(lzf_decompress(&input, 9).unwrap(), b"abcabcabc");
        // Long back reference with the extra length byte: len = 7 + 1 + 2 = 10.
        let input = [0, b'z', (7 << 5), 1, 0];
        assert_eq!(lzf_decompress(&input, 11).unwrap(), vec![b'z'; 11]);
        assert!(lzf_decompress(&[5, 1, 2], 6).is_err());
        assert!(lzf_decompress(&[(1 << 5), 0], 3).is_err());
        assert!(lzf_decompress(&[0, 1], 2).is_err());
    }
}
