//! PLY reader (ascii, binary little and big endian; any numeric property type;
//! `x y z` plus optional `nx ny nz` / `normal_x normal_y normal_z` and our own
//! `planarity`; other properties and elements ignored) and a binary
//! little-endian writer that CloudCompare and the mapper both read.
//!
//! Binary bodies are decoded record by record from precomputed byte offsets,
//! in large blocks, without per-property allocation.
use std::io::{BufRead, Read, Write};
use std::path::Path;

use super::{open_buffered, read_full, CloudFormat, CloudSink, LoadReport, MapIoError, ScalarType};
use crate::map::PointCloud;

/// Longest header accepted (bytes): a garbage file fails fast.
const MAX_HEADER_BYTES: u64 = 1 << 20;

/// Body encodings of a PLY file.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PlyEncoding {
    Ascii,
    BinaryLittleEndian,
    BinaryBigEndian,
}

#[derive(Clone, Debug)]
enum PropertyKind {
    Scalar(ScalarType),
    List { count: ScalarType, item: ScalarType },
}

#[derive(Clone, Debug)]
struct Property {
    name: String,
    kind: PropertyKind,
}

#[derive(Clone, Debug)]
struct Element {
    name: String,
    count: u64,
    properties: Vec<Property>,
}

impl Element {
    /// Bytes per record when every property is a scalar.
    fn fixed_size(&self) -> Option<usize> {
        self.properties
            .iter()
            .map(|p| match p.kind {
                PropertyKind::Scalar(t) => Some(t.size()),
                PropertyKind::List { .. } => None,
            })
            .sum()
    }
}

#[derive(Debug)]
struct Header {
    encoding: PlyEncoding,
    elements: Vec<Element>,
}

fn parse_type(name: &str) -> Option<ScalarType> {
    Some(match name {
        "char" | "int8" => ScalarType::I8,
        "uchar" | "uint8" => ScalarType::U8,
        "short" | "int16" => ScalarType::I16,
        "ushort" | "uint16" => ScalarType::U16,
        "int" | "int32" => ScalarType::I32,
        "uint" | "uint32" => ScalarType::U32,
        "float" | "float32" => ScalarType::F32,
        "double" | "float64" => ScalarType::F64,
        _ => return None,
    })
}

fn read_header(read: &mut impl BufRead, path: &Path) -> Result<Header, MapIoError> {
    let mut limited = read.take(MAX_HEADER_BYTES);
    let mut line = Vec::new();
    let mut line_no = 0u64;
    let mut encoding = None;
    let mut elements: Vec<Element> = Vec::new();
    loop {
        line.clear();
        let n = limited
            .read_until(b'\n', &mut line)
            .map_err(|e| MapIoError::io(path, e))?;
        line_no += 1;
        if n == 0 {
            return Err(MapIoError::header(
                path,
                "the file ends before `end_header` (or the header is longer than 1 MiB)",
            ));
        }
        let text = std::str::from_utf8(&line)
            .map_err(|_| MapIoError::header(path, format!("header line {line_no} is not text")))?;
        let text = text.trim_end_matches(['\n', '\r']);
        let mut words = text.split_ascii_whitespace();
        let keyword = words.next().unwrap_or("");
        if line_no == 1 {
            if text.trim() != "ply" {
                return Err(MapIoError::header(path, "the first line is not `ply`"));
            }
            continue;
        }
        let words: Vec<&str> = words.collect();
        match keyword {
            "" | "comment" | "obj_info" => {}
            "format" => {
                encoding = Some(match words.first().copied() {
                    Some("ascii") => PlyEncoding::Ascii,
                    Some("binary_little_endian") => PlyEncoding::BinaryLittleEndian,
                    Some("binary_big_endian") => PlyEncoding::BinaryBigEndian,
                    other => {
                        return Err(MapIoError::header(
                            path,
                            format!("unknown format `{}`", other.unwrap_or("")),
                        ))
                    }
                });
            }
            "element" => {
                if words.len() != 2 {
                    return Err(MapIoError::header(
                        path,
                        format!("line {line_no}: expected `element <name> <count>`"),
                    ));
                }
                let count = words[1].parse::<u64>().map_err(|_| {
                    MapIoError::header(
                        path,
                        format!("line {line_no}: bad element count `{}`", words[1]),
                    )
                })?;
                elements.push(Element {
                    name: words[0].to_string(),
                    count,
                    properties: Vec::new(),
                });
            }
            "property" => {
                let element = elements.last_mut().ok_or_else(|| {
                    MapIoError::header(path, format!("line {line_no}: property before any element"))
                })?;
                let bad_type = |t: &str| {
                    MapIoError::header(path, format!("line {line_no}: unknown property type `{t}`"))
                };
                let property = match words.as_slice() {
                    ["list", count, item, name] => Property {
                        name: name.to_string(),
                        kind: PropertyKind::List {
                            count: parse_type(count).ok_or_else(|| bad_type(count))?,
                            item: parse_type(item).ok_or_else(|| bad_type(item))?,
                        },
                    },
                    [t, name] => Property {
                        name: name.to_string(),
                        kind: PropertyKind::Scalar(parse_type(t).ok_or_else(|| bad_type(t))?),
                    },
                    _ => {
                        return Err(MapIoError::header(
                            path,
                            format!("line {line_no}: malformed property line `{text}`"),
                        ))
                    }
                };
                if let PropertyKind::List { count, .. } = property.kind {
                    if matches!(count, ScalarType::F32 | ScalarType::F64) {
                        return Err(MapIoError::header(
                            path,
                            format!("line {line_no}: list length type must be an integer"),
                        ));
                    }
                }
                element.properties.push(property);
            }
            "end_header" => break,
            other => {
                return Err(MapIoError::header(
                    path,
                    format!("line {line_no}: unknown keyword `{other}`"),
                ))
            }
        }
    }
    let encoding = encoding.ok_or_else(|| MapIoError::header(path, "no `format` line"))?;
    Ok(Header { encoding, elements })
}

/// Where the fields we read sit in a vertex record.
struct VertexLayout {
    /// Property index of x, y, z, nx, ny, nz, planarity.
    index: [Option<usize>; 7],
    types: [ScalarType; 7],
    /// Byte offsets (binary, all-scalar records).
    offsets: [usize; 7],
    with_normals: bool,
    with_planarity: bool,
}

fn vertex_layout(element: &Element, path: &Path) -> Result<VertexLayout, MapIoError> {
    let find = |names: &[&str]| {
        element
            .properties
            .iter()
            .position(|p| names.contains(&p.name.as_str()))
    };
    let mut index = [None; 7];
    for (k, name) in ["x", "y", "z"].iter().enumerate() {
        index[k] = Some(find(&[name]).ok_or_else(|| MapIoError::MissingCoordinate {
            path: path.to_path_buf(),
            name: name.to_string(),
        })?);
    }
    let normals = [
        find(&["nx", "normal_x"]),
        find(&["ny", "normal_y"]),
        find(&["nz", "normal_z"]),
    ];
    let with_normals = normals.iter().all(Option::is_some);
    if with_normals {
        index[3..6].copy_from_slice(&normals);
    }
    index[6] = find(&["planarity"]);
    let with_planarity = index[6].is_some();
    let mut types = [ScalarType::F32; 7];
    let mut offsets = [0usize; 7];
    let mut offset_of = Vec::with_capacity(element.properties.len());
    let mut offset = 0usize;
    for p in &element.properties {
        offset_of.push(offset);
        if let PropertyKind::Scalar(t) = p.kind {
            offset += t.size();
        }
    }
    for k in 0..7 {
        if let Some(i) = index[k] {
            match element.properties[i].kind {
                PropertyKind::Scalar(t) => {
                    types[k] = t;
                    offsets[k] = offset_of[i];
                }
                PropertyKind::List { .. } => {
                    return Err(MapIoError::header(
                        path,
                        format!(
                            "vertex property `{}` is a list, not a number",
                            element.properties[i].name
                        ),
                    ))
                }
            }
        }
    }
    Ok(VertexLayout {
        index,
        types,
        offsets,
        with_normals,
        with_planarity,
    })
}

/// Reads a PLY file (any encoding).
pub fn read_ply(path: &Path) -> Result<(PointCloud, LoadReport), MapIoError> {
    let (mut read, file_len) = open_buffered(path)?;
    let header = read_header(&mut read, path)?;
    let vertex_pos = header
        .elements
        .iter()
        .position(|e| e.name == "vertex")
        .ok_or_else(|| MapIoError::header(path, "no `vertex` element"))?;
    let vertex = &header.elements[vertex_pos];
    let layout = vertex_layout(vertex, path)?;
    let format = match header.encoding {
        PlyEncoding::Ascii => CloudFormat::PlyAscii,
        PlyEncoding::BinaryLittleEndian => CloudFormat::PlyBinaryLittleEndian,
        PlyEncoding::BinaryBigEndian => CloudFormat::PlyBinaryBigEndian,
    };
    // A lying count must not allocate more than the file can hold.
    let min_record = vertex.fixed_size().unwrap_or(1).max(1) as u64;
    let hint = vertex.count.min(file_len / min_record + 1) as usize;
    let mut sink = CloudSink::new(format, hint, layout.with_normals, layout.with_planarity);
    let is_last = vertex_pos + 1 == header.elements.len();
    match header.encoding {
        PlyEncoding::Ascii => read_ascii_body(
            &mut read, path, &header, vertex_pos, &layout, is_last, &mut sink,
        )?,
        PlyEncoding::BinaryLittleEndian | PlyEncoding::BinaryBigEndian => {
            let big = header.encoding == PlyEncoding::BinaryBigEndian;
            for element in &header.elements[..vertex_pos] {
                skip_binary_element(&mut read, path, element, big)?;
            }
            read_binary_vertices(&mut read, path, vertex, &layout, big, is_last, &mut sink)?
        }
    }
    Ok(sink.finish())
}

fn skip_binary_element(
    read: &mut impl Read,
    path: &Path,
    element: &Element,
    big: bool,
) -> Result<(), MapIoError> {
    let truncated = |_: ()| {
        MapIoError::header(
            path,
            format!(
                "truncated body in element `{}` (before the vertices)",
                element.name
            ),
        )
    };
    if let Some(size) = element.fixed_size() {
        let bytes = element.count.saturating_mul(size as u64);
        let copied = std::io::copy(&mut read.take(bytes), &mut std::io::sink())
            .map_err(|e| MapIoError::io(path, e))?;
        if copied != bytes {
            return Err(truncated(()));
        }
        return Ok(());
    }
    let mut buf = [0u8; 8];
    for _ in 0..element.count {
        for p in &element.properties {
            match p.kind {
                PropertyKind::Scalar(t) => {
                    read.read_exact(&mut buf[..t.size()])
                        .map_err(|_| truncated(()))?;
                }
                PropertyKind::List { count, item } => {
                    read.read_exact(&mut buf[..count.size()])
                        .map_err(|_| truncated(()))?;
                    // Checked at header parsing: an integer type.
                    let n = count.decode_count(&buf, big).unwrap_or(0);
                    let bytes = n * item.size() as u64;
                    let copied = std::io::copy(&mut read.take(bytes), &mut std::io::sink())
                        .map_err(|e| MapIoError::io(path, e))?;
                    if copied != bytes {
                        return Err(truncated(()));
                    }
                }
            }
        }
    }
    Ok(())
}

fn read_binary_vertices(
    read: &mut impl Read,
    path: &Path,
    vertex: &Element,
    layout: &VertexLayout,
    big: bool,
    is_last: bool,
    sink: &mut CloudSink,
) -> Result<(), MapIoError> {
    let record = vertex.fixed_size().ok_or_else(|| {
        MapIoError::unsupported(
            path,
            "list properties in the vertex element of a binary PLY",
        )
    })?;
    if record == 0 {
        return Err(MapIoError::header(
            path,
            "the vertex element has no properties",
        ));
    }
    let records_per_block = (super::READ_BUFFER_BYTES / record).max(1);
    let mut block = vec![0u8; records_per_block * record];
    let mut remaining = vertex.count;
    let mut read_so_far = 0u64;
    let t = layout.types;
    let o = layout.offsets;
    while remaining > 0 {
        let want = (remaining.min(records_per_block as u64) as usize) * record;
        let got = read_full(read, &mut block[..want]).map_err(|e| MapIoError::io(path, e))?;
        let whole = got / record;
        for rec in block[..whole * record].chunks_exact(record) {
            let p = [
                t[0].decode(&rec[o[0]..], big),
                t[1].decode(&rec[o[1]..], big),
                t[2].decode(&rec[o[2]..], big),
            ];
            let n = if layout.with_normals {
                [
                    t[3].decode(&rec[o[3]..], big),
                    t[4].decode(&rec[o[4]..], big),
                    t[5].decode(&rec[o[5]..], big),
                ]
            } else {
                [0.0; 3]
            };
            let planarity = if layout.with_planarity {
                t[6].decode(&rec[o[6]..], big)
            } else {
                0.0
            };
            sink.push(p, n, planarity);
        }
        read_so_far += whole as u64;
        if got < want {
            return Err(MapIoError::Truncated {
                path: path.to_path_buf(),
                declared: vertex.count,
                read: read_so_far,
            });
        }
        remaining -= whole as u64;
    }
    if is_last {
        // More than a stray byte or two after the last element means the
        // header's count is wrong.
        let got = read_full(read, &mut block[..record]).map_err(|e| MapIoError::io(path, e))?;
        if got >= record {
            return Err(MapIoError::CountMismatch {
                path: path.to_path_buf(),
                declared: vertex.count,
                detail: "at least one more whole vertex record follows".to_string(),
            });
        }
    }
    Ok(())
}

fn read_ascii_body(
    read: &mut impl BufRead,
    path: &Path,
    header: &Header,
    vertex_pos: usize,
    layout: &VertexLayout,
    is_last: bool,
    sink: &mut CloudSink,
) -> Result<(), MapIoError> {
    let vertex = &header.elements[vertex_pos];
    if vertex
        .properties
        .iter()
        .any(|p| matches!(p.kind, PropertyKind::List { .. }))
    {
        return Err(MapIoError::unsupported(
            path,
            "list properties in the vertex element of an ascii PLY",
        ));
    }
    let mut line = Vec::with_capacity(256);
    // Line numbers count body lines after the header.
    let mut line_no = 0u64;
    let mut next_line = |line: &mut Vec<u8>, line_no: &mut u64| -> Result<bool, MapIoError> {
        loop {
            line.clear();
            let n = read
                .read_until(b'\n', line)
                .map_err(|e| MapIoError::io(path, e))?;
            if n == 0 {
                return Ok(false);
            }
            *line_no += 1;
            if line.iter().any(|b| !b.is_ascii_whitespace()) {
                return Ok(true);
            }
        }
    };
    for element in &header.elements[..vertex_pos] {
        for _ in 0..element.count {
            if !next_line(&mut line, &mut line_no)? {
                return Err(MapIoError::header(
                    path,
                    format!(
                        "truncated body in element `{}` (before the vertices)",
                        element.name
                    ),
                ));
            }
        }
    }
    let nprops = vertex.properties.len();
    // Which token goes to which field (x y z nx ny nz planarity).
    let mut field_of_token = vec![usize::MAX; nprops];
    for (k, idx) in layout.index.iter().enumerate() {
        if let Some(i) = idx {
            field_of_token[*i] = k;
        }
    }
    let mut values = [0.0f64; 7];
    for done in 0..vertex.count {
        if !next_line(&mut line, &mut line_no)? {
            return Err(MapIoError::Truncated {
                path: path.to_path_buf(),
                declared: vertex.count,
                read: done,
            });
        }
        let text = std::str::from_utf8(&line).map_err(|_| MapIoError::Body {
            path: path.to_path_buf(),
            line: line_no,
            message: "not text".to_string(),
        })?;
        let mut ntokens = 0;
        for (i, token) in text.split_ascii_whitespace().enumerate() {
            ntokens += 1;
            if i >= nprops {
                continue;
            }
            let field = field_of_token[i];
            if field != usize::MAX {
                values[field] = token.parse::<f64>().map_err(|_| MapIoError::Body {
                    path: path.to_path_buf(),
                    line: line_no,
                    message: format!(
                        "`{token}` is not a number (property `{}`)",
                        vertex.properties[i].name
                    ),
                })?;
            }
        }
        if ntokens != nprops {
            return Err(MapIoError::Body {
                path: path.to_path_buf(),
                line: line_no,
                message: format!("expected {nprops} values, found {ntokens}"),
            });
        }
        sink.push(
            [values[0], values[1], values[2]],
            [values[3], values[4], values[5]],
            values[6],
        );
    }
    if is_last && next_line(&mut line, &mut line_no)? {
        return Err(MapIoError::CountMismatch {
            path: path.to_path_buf(),
            declared: vertex.count,
            detail: format!("line {line_no} follows the last declared vertex"),
        });
    }
    Ok(())
}

/// Writes `cloud` as a binary little-endian PLY: `x y z` as `double` when the
/// origin is not zero (georeferenced coordinates are kept exactly), else as
/// `float`; `nx ny nz` as `float` when the cloud has normals; `planarity` as
/// `float` when present. Written atomically (temporary file, then rename).
pub fn write_ply(path: &Path, cloud: &PointCloud) -> Result<(), MapIoError> {
    write_ply_with_colours(path, cloud, None)
}

/// Per-point colours for [`write_ply_with_colours`].
#[derive(Clone, Copy, Debug)]
pub struct PlyColours<'a> {
    /// `red green blue`, one per point.
    pub rgb: &'a [[u8; 3]],
    /// How many images gave the colour, one per point (`views`, `ushort`).
    pub views: &'a [u16],
}

/// [`write_ply`], with `red green blue` (`uchar`) and `views` (`ushort`)
/// after the other properties when `colours` is given.
pub fn write_ply_with_colours(
    path: &Path,
    cloud: &PointCloud,
    colours: Option<PlyColours>,
) -> Result<(), MapIoError> {
    if let Some(c) = &colours {
        if c.rgb.len() != cloud.len() || c.views.len() != cloud.len() {
            return Err(MapIoError::unsupported(
                path,
                format!(
                    "cloud has {} points but {} colours and {} view counts",
                    cloud.len(),
                    c.rgb.len(),
                    c.views.len()
                ),
            ));
        }
    }
    if let Some(n) = &cloud.normals {
        if n.len() != cloud.len() {
            return Err(MapIoError::unsupported(
                path,
                format!("cloud has {} points but {} normals", cloud.len(), n.len()),
            ));
        }
    }
    if let Some(p) = &cloud.planarity {
        if p.len() != cloud.len() {
            return Err(MapIoError::unsupported(
                path,
                format!(
                    "cloud has {} points but {} planarity values",
                    cloud.len(),
                    p.len()
                ),
            ));
        }
    }
    let use_double = cloud.origin != nalgebra::Vector3::zeros();
    crate::io::atomic::write_file_atomically(path, |w| -> std::io::Result<()> {
        let coord = if use_double { "double" } else { "float" };
        let mut header = String::new();
        header.push_str("ply\nformat binary_little_endian 1.0\n");
        header.push_str("comment written by colmap-lidar\n");
        header.push_str(&format!("element vertex {}\n", cloud.len()));
        for axis in ["x", "y", "z"] {
            header.push_str(&format!("property {coord} {axis}\n"));
        }
        if cloud.normals.is_some() {
            header.push_str("property float nx\nproperty float ny\nproperty float nz\n");
        }
        if cloud.planarity.is_some() {
            header.push_str("property float planarity\n");
        }
        if colours.is_some() {
            header.push_str("property uchar red\nproperty uchar green\nproperty uchar blue\n");
            header.push_str("property ushort views\n");
        }
        header.push_str("end_header\n");
        w.write_all(header.as_bytes())?;
        let mut buf: Vec<u8> = Vec::with_capacity(1 << 20);
        let o = cloud.origin;
        for (i, p) in cloud.points.iter().enumerate() {
            if use_double {
                buf.extend_from_slice(&(o.x + f64::from(p[0])).to_le_bytes());
                buf.extend_from_slice(&(o.y + f64::from(p[1])).to_le_bytes());
                buf.extend_from_slice(&(o.z + f64::from(p[2])).to_le_bytes());
            } else {
                for c in p {
                    buf.extend_from_slice(&c.to_le_bytes());
                }
            }
            if let Some(normals) = &cloud.normals {
                for c in &normals[i] {
                    buf.extend_from_slice(&c.to_le_bytes());
                }
            }
            if let Some(planarity) = &cloud.planarity {
                buf.extend_from_slice(&planarity[i].to_le_bytes());
            }
            if let Some(c) = &colours {
                buf.extend_from_slice(&c.rgb[i]);
                buf.extend_from_slice(&c.views[i].to_le_bytes());
            }
            if buf.len() >= (1 << 20) - 64 {
                w.write_all(&buf)?;
                buf.clear();
            }
        }
        w.write_all(&buf)?;
        Ok(())
    })
    .map_err(|e| MapIoError::io(path, e))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_parsing_finds_fields_after_a_face_element() {
        let text = b"ply\r\nformat ascii 1.0\r\ncomment hi\r\nelement face 1\r\n\
            property list uchar int vertex_indices\r\nelement vertex 2\r\nproperty uchar red\r\n\
            property double x\r\nproperty float y\r\nproperty float z\r\nproperty float normal_x\r\n\
            property float normal_y\r\nproperty float normal_z\r\nend_header\r\n";
        let mut read = &text[..];
        let header = read_header(&mut read, Path::new("t.ply")).unwrap();
        assert_eq!(header.encoding, PlyEncoding::Ascii);
        assert_eq!(header.elements.len(), 2);
        let layout = vertex_layout(&header.elements[1], Path::new("t.ply")).unwrap();
        assert!(layout.with_normals);
        assert_eq!(layout.offsets[..6], [1, 9, 13, 17, 21, 25]);
        assert_eq!(layout.types[0], ScalarType::F64);
    }
}
