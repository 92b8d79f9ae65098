//! Integration tests: the LiDAR map (readers, preparation, index, projection),
//! plus hand-written encoders used to build test files byte by byte.
mod colour;
mod depth_maps;
mod index;
mod io;
mod prepare;
mod projection;

/// The synthetic scan of `scene` with `noise_m` along the normals, without
/// its holes (0.25-1 m wide, which leave out parts of surfaces in front: an
/// image would see those, the map cannot) and its outliers, with the true
/// normals; and its sample spacing.
pub fn scan_without_holes(
    scene: &colmap_lidar::synth::geometry::Scene,
    noise_m: f64,
) -> (colmap_lidar::map::PointCloud, f64) {
    use colmap_lidar::synth::lidar::{sample_lidar, LidarOptions};
    let lidar = LidarOptions {
        num_holes: 0,
        noise_sigma_m: noise_m,
        ..Default::default()
    };
    let map = sample_lidar(scene, &lidar);
    let keep: Vec<usize> = (0..map.points.len())
        .filter(|&i| !map.is_outlier[i])
        .collect();
    let cloud = colmap_lidar::map::PointCloud {
        origin: nalgebra::Vector3::zeros(),
        points: keep
            .iter()
            .map(|&i| map.points[i].map(|c| c as f32).into())
            .collect(),
        normals: Some(keep.iter().map(|&i| map.normals[i].into()).collect()),
        planarity: None,
    };
    (cloud, map.spacing_m)
}

/// Body encodings of the hand-written PLY files.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Enc {
    Ascii,
    Le,
    Be,
}

/// Encodes one value of a PLY type (`float`, `uchar`, ...).
pub fn encode_value(ty: &str, v: f64, enc: Enc, out: &mut Vec<u8>) {
    macro_rules! put {
        ($t:ty) => {{
            let x = v as $t;
            out.extend_from_slice(&match enc {
                Enc::Be => x.to_be_bytes(),
                _ => x.to_le_bytes(),
            });
        }};
    }
    match ty {
        "char" | "int8" => put!(i8),
        "uchar" | "uint8" => put!(u8),
        "short" | "int16" => put!(i16),
        "ushort" | "uint16" => put!(u16),
        "int" | "int32" => put!(i32),
        "uint" | "uint32" => put!(u32),
        "float" | "float32" => put!(f32),
        "double" | "float64" => put!(f64),
        other => panic!("test helper: unknown type {other}"),
    }
}

/// A PLY file with one `vertex` element: `props` are (type, name), `rows`
/// the values (cast to each type). `count` overrides the declared count.
pub fn ply_bytes(
    enc: Enc,
    props: &[(&str, &str)],
    rows: &[Vec<f64>],
    count: Option<usize>,
) -> Vec<u8> {
    let mut out = Vec::new();
    let format = match enc {
        Enc::Ascii => "ascii",
        Enc::Le => "binary_little_endian",
        Enc::Be => "binary_big_endian",
    };
    out.extend_from_slice(
        format!(
            "ply\nformat {format} 1.0\ncomment test\nelement vertex {}\n",
            count.unwrap_or(rows.len())
        )
        .as_bytes(),
    );
    for (ty, name) in props {
        out.extend_from_slice(format!("property {ty} {name}\n").as_bytes());
    }
    out.extend_from_slice(b"end_header\n");
    for row in rows {
        assert_eq!(row.len(), props.len());
        if enc == Enc::Ascii {
            let words: Vec<String> = row
                .iter()
                .zip(props)
                .map(|(v, (ty, _))| {
                    if ty.contains("float") || ty.contains("double") {
                        if v.is_nan() {
                            "nan".to_string()
                        } else if ty.starts_with("float") && *ty != "float64" {
                            format!("{}", *v as f32)
                        } else {
                            format!("{v}")
                        }
                    } else {
                        format!("{}", *v as i64)
                    }
                })
                .collect();
            out.extend_from_slice(words.join(" ").as_bytes());
            out.push(b'\n');
        } else {
            for (v, (ty, _)) in row.iter().zip(props) {
                encode_value(ty, *v, enc, &mut out);
            }
        }
    }
    out
}

/// Angle between two directions in degrees, sign ignored when `unsigned`.
pub fn angle_deg(a: [f64; 3], b: [f64; 3], unsigned: bool) -> f64 {
    let na = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
    let nb = (b[0] * b[0] + b[1] * b[1] + b[2] * b[2]).sqrt();
    let mut c = (a[0] * b[0] + a[1] * b[1] + a[2] * b[2]) / (na * nb);
    if unsigned {
        c = c.abs();
    }
    c.clamp(-1.0, 1.0).acos().to_degrees()
}

/// A LAS 1.2 header, point format 1 (with GPS time), millimetre coordinates
/// from `offsets` (x, y, z).
pub fn millimetre_las_header(offsets: [f64; 3]) -> las::Header {
    let mut builder = las::Builder::from((1, 2));
    builder.point_format = las::point::Format::new(1).unwrap();
    let millimetres = |offset| las::Transform {
        scale: 0.001,
        offset,
    };
    builder.transforms = las::Vector {
        x: millimetres(offsets[0]),
        y: millimetres(offsets[1]),
        z: millimetres(offsets[2]),
    };
    builder.into_header().unwrap()
}

/// Writes `points` as a LAS or LAZ file (by the extension) with
/// [`millimetre_las_header`].
pub fn write_millimetre_las(path: &std::path::Path, offsets: [f64; 3], points: &[[f64; 3]]) {
    let mut writer = las::Writer::from_path(path, millimetre_las_header(offsets)).unwrap();
    for p in points {
        writer
            .write_point(las::Point {
                x: p[0],
                y: p[1],
                z: p[2],
                gps_time: Some(1.0),
                ..Default::default()
            })
            .unwrap();
    }
    writer.close().unwrap();
}
