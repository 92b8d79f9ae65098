//! Readers and writer: every PLY encoding and property type, PCD ascii /
//! binary / binary_compressed, LAS and LAZ; UTM-sized coordinates; NaN rows;
//! malformed and truncated files give errors that name the file.
use std::path::{Path, PathBuf};

use colmap_lidar::map::io::{
    read_point_cloud, read_point_cloud_with, write_ply, CloudFormat, InputUnits, MapIoError,
    ReadOptions,
};
use colmap_lidar::map::PointCloud;
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::{millimetre_las_header, ply_bytes, write_millimetre_las, Enc};

fn write(dir: &Path, name: &str, bytes: &[u8]) -> PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, bytes).unwrap();
    path
}

/// Reads a file that must fail; checks the message names the file.
fn read_err(path: &Path) -> MapIoError {
    let err = match read_point_cloud(path) {
        Ok((cloud, _)) => panic!(
            "{} read {} points, expected an error",
            path.display(),
            cloud.len()
        ),
        Err(e) => e,
    };
    let name = path.file_name().unwrap().to_string_lossy().to_string();
    assert!(
        err.to_string().contains(&name),
        "error `{err}` does not name {name}"
    );
    err
}

/// A value of PLY type `ty` for a random test row.
fn random_value(ty: &str, rng: &mut ChaCha8Rng) -> f64 {
    match ty {
        "uchar" | "uint8" => f64::from(rng.gen_range(0u8..=255)),
        "char" | "int8" => f64::from(rng.gen_range(-128i8..=127)),
        "short" | "int16" => f64::from(rng.gen_range(-30000i16..30000)),
        "ushort" | "uint16" => f64::from(rng.gen_range(0u16..60000)),
        "int" | "int32" => f64::from(rng.gen_range(-100_000i32..100_000)),
        "uint" | "uint32" => f64::from(rng.gen_range(0u32..200_000)),
        "float" | "float32" => f64::from(rng.gen_range(-300.0f32..300.0)),
        _ => rng.gen_range(-300.0..300.0),
    }
}

fn random_unit(rng: &mut ChaCha8Rng) -> [f64; 3] {
    loop {
        let v: [f64; 3] = [
            rng.gen_range(-1.0..1.0),
            rng.gen_range(-1.0..1.0),
            rng.gen_range(-1.0..1.0),
        ];
        let n: f64 = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        if n > 0.1 && n < 1.0 {
            return [v[0] / n, v[1] / n, v[2] / n];
        }
    }
}

#[test]
fn ply_every_encoding_and_property_type_reads_back_exactly() {
    let dir = tempfile::tempdir().unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let coord_types = [
        "float", "double", "int", "uint", "short", "ushort", "uchar", "char", "float32", "float64",
        "int16", "uint8",
    ];
    for enc in [Enc::Ascii, Enc::Le, Enc::Be] {
        for (t, ty) in coord_types.iter().enumerate() {
            // Normals: none, `nx`, `normal_x`, typed float or double.
            let normal_style = t % 3;
            let normal_ty = if t % 2 == 0 { "float" } else { "double" };
            let mut props: Vec<(&str, &str)> = vec![
                ("uchar", "red"),
                (ty, "x"),
                ("ushort", "intensity"),
                (ty, "y"),
                (ty, "z"),
            ];
            match normal_style {
                1 => props.extend([(normal_ty, "nx"), (normal_ty, "ny"), (normal_ty, "nz")]),
                2 => props.extend([
                    (normal_ty, "normal_x"),
                    (normal_ty, "normal_y"),
                    (normal_ty, "normal_z"),
                ]),
                _ => {}
            }
            props.push(("double", "gps_time"));
            let rows: Vec<Vec<f64>> = (0..57)
                .map(|_| {
                    let n = random_unit(&mut rng);
                    let mut row = vec![
                        random_value("uchar", &mut rng),
                        random_value(ty, &mut rng),
                        random_value("ushort", &mut rng),
                        random_value(ty, &mut rng),
                        random_value(ty, &mut rng),
                    ];
                    if normal_style != 0 {
                        row.extend(n);
                    }
                    row.push(rng.gen_range(0.0..1e6));
                    row
                })
                .collect();
            let name = format!("t_{enc:?}_{ty}.ply");
            let path = write(dir.path(), &name, &ply_bytes(enc, &props, &rows, None));
            let (cloud, report) = read_point_cloud(&path).unwrap_or_else(|e| panic!("{e}"));
            let format = match enc {
                Enc::Ascii => CloudFormat::PlyAscii,
                Enc::Le => CloudFormat::PlyBinaryLittleEndian,
                Enc::Be => CloudFormat::PlyBinaryBigEndian,
            };
            assert_eq!(report.format, format);
            assert_eq!(report.points_read, rows.len() as u64);
            assert_eq!(report.dropped_non_finite, 0);
            assert_eq!(report.had_normals, normal_style != 0, "{name}");
            assert_eq!(report.normals_invalid, 0);
            let is_float = ty.starts_with("float") || *ty == "double";
            if is_float {
                assert_eq!(cloud.origin, Vector3::zeros(), "{name}");
            }
            assert_eq!(cloud.len(), rows.len());
            for (i, row) in rows.iter().enumerate() {
                // Floating-point values (small here: the origin stays zero)
                // are stored as f32; integers are exact whatever the origin.
                let expect = |v: f64| if is_float { f64::from(v as f32) } else { v };
                let p = cloud.point_in_map(i);
                assert_eq!(
                    [p.x, p.y, p.z],
                    [expect(row[1]), expect(row[3]), expect(row[4])],
                    "{name} row {i}"
                );
                if normal_style != 0 {
                    let n = cloud.normals.as_ref().unwrap()[i];
                    for a in 0..3 {
                        assert!(
                            (f64::from(n[a]) - row[5 + a]).abs() < 1e-6,
                            "{name} row {i}"
                        );
                    }
                } else {
                    assert!(cloud.normals.is_none());
                }
            }
        }
    }
}

#[test]
fn utm_coordinates_round_trip_within_a_tenth_of_a_millimetre() {
    let dir = tempfile::tempdir().unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let base = [512_345.678_9, 5_412_345.432_1, 231.5];
    let rows: Vec<Vec<f64>> = (0..2000)
        .map(|_| {
            let n = random_unit(&mut rng);
            vec![
                base[0] + rng.gen_range(-600.0..600.0),
                base[1] + rng.gen_range(-600.0..600.0),
                base[2] + rng.gen_range(-30.0..30.0),
                n[0],
                n[1],
                n[2],
            ]
        })
        .collect();
    let props = [
        ("double", "x"),
        ("double", "y"),
        ("double", "z"),
        ("float", "nx"),
        ("float", "ny"),
        ("float", "nz"),
    ];
    for enc in [Enc::Ascii, Enc::Le, Enc::Be] {
        let path = write(
            dir.path(),
            &format!("utm_{enc:?}.ply"),
            &ply_bytes(enc, &props, &rows, None),
        );
        let (cloud, _) = read_point_cloud(&path).unwrap();
        assert!(cloud.origin.x.abs() > 1e5, "origin {:?}", cloud.origin);
        let check = |cloud: &PointCloud, what: &str| {
            for (i, row) in rows.iter().enumerate() {
                let p = cloud.point_in_map(i);
                for a in 0..3 {
                    assert!(
                        (p[a] - row[a]).abs() < 1e-4,
                        "{what} row {i} axis {a}: {} vs {}",
                        p[a],
                        row[a]
                    );
                }
            }
        };
        check(&cloud, "read");
        let out = dir.path().join(format!("utm_{enc:?}_out.ply"));
        write_ply(&out, &cloud).unwrap();
        let bytes = std::fs::read(&out).unwrap();
        let head = String::from_utf8_lossy(&bytes[..300]);
        assert!(head.contains("format binary_little_endian 1.0"));
        assert!(head.contains("property double x"));
        assert!(head.contains("property float nx"));
        let (again, report) = read_point_cloud(&out).unwrap();
        assert_eq!(report.points_read, rows.len() as u64);
        check(&again, "re-read");
        let (a, b) = (again.normals.unwrap(), cloud.normals.unwrap());
        for (x, y) in a.iter().zip(&b) {
            for k in 0..3 {
                assert!((x[k] - y[k]).abs() < 1e-6);
            }
        }
    }
}

#[test]
fn small_float_cloud_round_trips_bit_for_bit_with_planarity() {
    let dir = tempfile::tempdir().unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let cloud = PointCloud {
        origin: Vector3::zeros(),
        points: (0..500)
            .map(|_| {
                [
                    rng.gen_range(-50.0..50.0),
                    rng.gen_range(-50.0..50.0),
                    rng.gen_range(0.0..10.0),
                ]
            })
            .collect(),
        normals: Some(
            (0..500)
                .map(|_| {
                    let n = random_unit(&mut rng);
                    [n[0] as f32, n[1] as f32, n[2] as f32]
                })
                .collect(),
        ),
        planarity: Some((0..500).map(|_| rng.gen_range(0.0..1.0)).collect()),
    };
    let out = dir.path().join("small.ply");
    write_ply(&out, &cloud).unwrap();
    let head = String::from_utf8_lossy(&std::fs::read(&out).unwrap()[..250]).to_string();
    assert!(head.contains("property float x"), "{head}");
    let (again, _) = read_point_cloud(&out).unwrap();
    assert_eq!(again.points, cloud.points);
    assert_eq!(again.planarity, cloud.planarity);
    let (a, b) = (again.normals.unwrap(), cloud.normals.unwrap());
    for (x, y) in a.iter().zip(&b) {
        for k in 0..3 {
            assert!((x[k] - y[k]).abs() < 1e-6);
        }
    }
}

#[test]
fn non_finite_rows_are_dropped_and_counted() {
    let dir = tempfile::tempdir().unwrap();
    let props = [
        ("float", "x"),
        ("float", "y"),
        ("float", "z"),
        ("float", "nx"),
        ("float", "ny"),
        ("float", "nz"),
    ];
    let rows = vec![
        vec![1.0, 2.0, 3.0, 0.0, 0.0, 1.0],
        vec![f64::NAN, 2.0, 3.0, 0.0, 0.0, 1.0],
        vec![4.0, f64::INFINITY, 3.0, 0.0, 0.0, 1.0],
        vec![5.0, 6.0, 7.0, 0.0, 0.0, 0.0],
        vec![8.0, 9.0, f64::NEG_INFINITY, 0.0, 0.0, 1.0],
        vec![10.0, 11.0, 12.0, f64::NAN, 0.0, 1.0],
        vec![13.0, 14.0, 15.0, 0.0, 0.5, 0.0],
    ];
    for enc in [Enc::Ascii, Enc::Le, Enc::Be] {
        let mut bytes = ply_bytes(enc, &props, &rows, None);
        if enc == Enc::Ascii {
            // Spell the infinities as other writers do.
            let text = String::from_utf8(bytes)
                .unwrap()
                .replace("-inf", "-Infinity")
                .replace(" inf", " INF");
            bytes = text.into_bytes();
        }
        let path = write(dir.path(), &format!("nan_{enc:?}.ply"), &bytes);
        let (cloud, report) = read_point_cloud(&path).unwrap();
        assert_eq!(report.points_read, 7);
        assert_eq!(report.dropped_non_finite, 3);
        assert_eq!(
            report.normals_invalid, 3,
            "zero, NaN and half-length normals"
        );
        assert_eq!(
            cloud.points,
            vec![
                [1.0, 2.0, 3.0],
                [5.0, 6.0, 7.0],
                [10.0, 11.0, 12.0],
                [13.0, 14.0, 15.0]
            ]
        );
        assert_eq!(
            cloud.normals.unwrap(),
            vec![[0.0, 0.0, 1.0], [0.0; 3], [0.0; 3], [0.0; 3]]
        );
    }
}

/// A binary PLY with a `face` list element before the vertices and an `edge`
/// element after them.
fn ply_with_faces(enc: Enc) -> Vec<u8> {
    let format = match enc {
        Enc::Ascii => "ascii",
        Enc::Le => "binary_little_endian",
        Enc::Be => "binary_big_endian",
    };
    let mut out = format!(
        "ply\nformat {format} 1.0\nobj_info from a mesher\nelement face 2\nproperty list uchar int vertex_indices\n\
         property uchar flags\nelement vertex 3\nproperty short x\nproperty float y\nproperty double z\n\
         element edge 1\nproperty int a\nproperty int b\nend_header\n"
    )
    .into_bytes();
    if enc == Enc::Ascii {
        out.extend_from_slice(b"3 0 1 2 7\n4 0 1 2 0 9\n1 2 3\n-4 5.5 6.25\n7 8 9\n0 1\n");
        return out;
    }
    let put = |out: &mut Vec<u8>, ty: &str, v: f64| super::encode_value(ty, v, enc, out);
    put(&mut out, "uchar", 3.0);
    for v in [0.0, 1.0, 2.0] {
        put(&mut out, "int", v);
    }
    put(&mut out, "uchar", 7.0);
    put(&mut out, "uchar", 4.0);
    for v in [0.0, 1.0, 2.0, 0.0] {
        put(&mut out, "int", v);
    }
    put(&mut out, "uchar", 9.0);
    for row in [[1.0, 2.0, 3.0], [-4.0, 5.5, 6.25], [7.0, 8.0, 9.0]] {
        put(&mut out, "short", row[0]);
        put(&mut out, "float", row[1]);
        put(&mut out, "double", row[2]);
    }
    put(&mut out, "int", 0.0);
    put(&mut out, "int", 1.0);
    out
}

#[test]
fn elements_around_the_vertices_are_skipped() {
    let dir = tempfile::tempdir().unwrap();
    for enc in [Enc::Ascii, Enc::Le, Enc::Be] {
        let path = write(
            dir.path(),
            &format!("faces_{enc:?}.ply"),
            &ply_with_faces(enc),
        );
        let (cloud, report) = read_point_cloud(&path).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(report.points_read, 3);
        assert_eq!(
            cloud.points,
            vec![[1.0, 2.0, 3.0], [-4.0, 5.5, 6.25], [7.0, 8.0, 9.0]]
        );
    }
}

#[test]
fn malformed_ply_files_give_errors_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let props = [("float", "x"), ("float", "y"), ("float", "z")];
    let rows: Vec<Vec<f64>> = (0..10).map(|i| vec![i as f64, 1.0, 2.0]).collect();
    for enc in [Enc::Le, Enc::Be] {
        // Truncated binary body.
        let mut bytes = ply_bytes(enc, &props, &rows, None);
        bytes.truncate(bytes.len() - 5);
        let err = read_err(&write(dir.path(), &format!("cut_{enc:?}.ply"), &bytes));
        assert!(
            matches!(
                err,
                MapIoError::Truncated {
                    declared: 10,
                    read: 9,
                    ..
                }
            ),
            "{err}"
        );
        // The header claims more points than the body holds.
        let bytes = ply_bytes(enc, &props, &rows, Some(12));
        let err = read_err(&write(dir.path(), &format!("more_{enc:?}.ply"), &bytes));
        assert!(
            matches!(
                err,
                MapIoError::Truncated {
                    declared: 12,
                    read: 10,
                    ..
                }
            ),
            "{err}"
        );
        // ... or fewer.
        let bytes = ply_bytes(enc, &props, &rows, Some(8));
        let err = read_err(&write(dir.path(), &format!("fewer_{enc:?}.ply"), &bytes));
        assert!(
            matches!(err, MapIoError::CountMismatch { declared: 8, .. }),
            "{err}"
        );
    }
    let bytes = ply_bytes(Enc::Ascii, &props, &rows, Some(12));
    let err = read_err(&write(dir.path(), "more_ascii.ply", &bytes));
    assert!(
        matches!(
            err,
            MapIoError::Truncated {
                declared: 12,
                read: 10,
                ..
            }
        ),
        "{err}"
    );
    let bytes = ply_bytes(Enc::Ascii, &props, &rows, Some(9));
    let err = read_err(&write(dir.path(), "fewer_ascii.ply", &bytes));
    assert!(matches!(err, MapIoError::CountMismatch { .. }), "{err}");
    // A short ascii row and a non-number.
    let text = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n4 5\n";
    let err = read_err(&write(dir.path(), "short_row.ply", text.as_bytes()));
    assert!(err.to_string().contains("line 2"), "{err}");
    let text = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 two 3\n";
    read_err(&write(dir.path(), "word.ply", text.as_bytes()));
    // Missing x.
    let bytes = ply_bytes(
        Enc::Le,
        &[("float", "u"), ("float", "y"), ("float", "z")],
        &rows,
        None,
    );
    let err = read_err(&write(dir.path(), "no_x.ply", &bytes));
    assert!(
        matches!(&err, MapIoError::MissingCoordinate { name, .. } if name == "x"),
        "{err}"
    );
    // Garbage after a `ply` line, an unknown format, an unknown type, no end_header.
    read_err(&write(
        dir.path(),
        "garbage.ply",
        b"ply\n\x00\x01\x02\xff\xfe garbage\n",
    ));
    read_err(&write(
        dir.path(),
        "fmt.ply",
        b"ply\nformat binary_middle_endian 1.0\nelement vertex 0\nend_header\n",
    ));
    read_err(&write(
        dir.path(),
        "type.ply",
        b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float128 x\nend_header\n",
    ));
    read_err(&write(
        dir.path(),
        "noend.ply",
        b"ply\nformat ascii 1.0\nelement vertex 1\n",
    ));
    read_err(&write(dir.path(), "notply.ply", b"PK\x03\x04 zip file"));
    read_err(&write(dir.path(), "empty.ply", b""));
    read_err(&dir.path().join("does_not_exist.ply"));
    // Unknown format, by extension and by content.
    let err = read_err(&write(dir.path(), "cloud.xyz", b"1 2 3\n4 5 6\n"));
    assert!(matches!(err, MapIoError::UnknownFormat { .. }), "{err}");
    // Format found from the signature when the extension says nothing.
    let path = write(
        dir.path(),
        "cloud.bin",
        &ply_bytes(Enc::Le, &props, &rows, None),
    );
    assert_eq!(read_point_cloud(&path).unwrap().0.len(), 10);
}

#[test]
fn every_truncation_and_header_corruption_is_an_error_not_a_panic() {
    let dir = tempfile::tempdir().unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    for enc in [Enc::Ascii, Enc::Le, Enc::Be] {
        let full = ply_with_faces(enc);
        let path = dir.path().join(format!("cut_{enc:?}.ply"));
        for len in 0..full.len() {
            std::fs::write(&path, &full[..len]).unwrap();
            let result = read_point_cloud(&path);
            // The `edge` element after the vertices is not read (5 bytes in
            // ascii, 8 in binary): only cuts before its end must fail.
            let tail = if enc == Enc::Ascii { 5 } else { 8 };
            if len < full.len() - tail {
                assert!(
                    result.is_err(),
                    "{enc:?} cut at {len} of {} read fine",
                    full.len()
                );
            }
        }
        for _ in 0..300 {
            let mut bytes = full.clone();
            let at = rng.gen_range(0..bytes.len());
            bytes[at] = rng.gen();
            std::fs::write(&path, &bytes).unwrap();
            let _ = read_point_cloud(&path);
        }
    }
}

/// A PCD file: header + body.
fn pcd_bytes(
    data: &str,
    fields: &[(&str, &str, usize, usize)],
    points: usize,
    body: &[u8],
) -> Vec<u8> {
    let names: Vec<&str> = fields.iter().map(|f| f.0).collect();
    let types: Vec<&str> = fields.iter().map(|f| f.1).collect();
    let sizes: Vec<String> = fields.iter().map(|f| f.2.to_string()).collect();
    let counts: Vec<String> = fields.iter().map(|f| f.3.to_string()).collect();
    let mut out = format!(
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS {}\nSIZE {}\nTYPE {}\nCOUNT {}\n\
         WIDTH {points}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {points}\nDATA {data}\n",
        names.join(" "),
        sizes.join(" "),
        types.join(" "),
        counts.join(" ")
    )
    .into_bytes();
    out.extend_from_slice(body);
    out
}

/// LZF "compression" into literal runs only (valid LZF), plus one back
/// reference when the data starts with 8 identical bytes... kept simple: the
/// decoder's back references are covered by its unit test.
fn lzf_literals(data: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    for chunk in data.chunks(32) {
        out.push((chunk.len() - 1) as u8);
        out.extend_from_slice(chunk);
    }
    out
}

#[test]
fn pcd_ascii_binary_and_compressed_read_back() {
    let dir = tempfile::tempdir().unwrap();
    let fields = [
        ("x", "F", 4, 1),
        ("y", "F", 4, 1),
        ("z", "F", 8, 1),
        ("rgb", "U", 4, 1),
        ("normal_x", "F", 4, 1),
        ("normal_y", "F", 4, 1),
        ("normal_z", "F", 4, 1),
        ("fpfh", "F", 4, 3),
        ("label", "I", 2, 1),
    ];
    let pts: Vec<[f64; 6]> = vec![
        [1.5, -2.25, 512_345.125, 0.0, 0.0, 1.0],
        [f64::NAN, f64::NAN, f64::NAN, 0.0, 0.0, 1.0],
        [3.0, 4.0, 512_346.5, 0.6, 0.8, 0.0],
    ];
    // ascii
    let mut body = String::new();
    for p in &pts {
        body.push_str(&format!(
            "{} {} {} 4278190080 {} {} {} 0.1 0.2 0.3 -7\n",
            if p[0].is_nan() {
                "nan".to_string()
            } else {
                p[0].to_string()
            },
            if p[1].is_nan() {
                "nan".to_string()
            } else {
                p[1].to_string()
            },
            if p[2].is_nan() {
                "nan".to_string()
            } else {
                p[2].to_string()
            },
            p[3],
            p[4],
            p[5]
        ));
    }
    // binary records
    let mut records = Vec::new();
    for p in &pts {
        records.extend_from_slice(&(p[0] as f32).to_le_bytes());
        records.extend_from_slice(&(p[1] as f32).to_le_bytes());
        records.extend_from_slice(&p[2].to_le_bytes());
        records.extend_from_slice(&7u32.to_le_bytes());
        for v in &p[3..6] {
            records.extend_from_slice(&(*v as f32).to_le_bytes());
        }
        for v in [0.1f32, 0.2, 0.3] {
            records.extend_from_slice(&v.to_le_bytes());
        }
        records.extend_from_slice(&(-7i16).to_le_bytes());
    }
    // binary_compressed: columns
    let mut columns = Vec::new();
    for p in &pts {
        columns.extend_from_slice(&(p[0] as f32).to_le_bytes());
    }
    for p in &pts {
        columns.extend_from_slice(&(p[1] as f32).to_le_bytes());
    }
    for p in &pts {
        columns.extend_from_slice(&p[2].to_le_bytes());
    }
    for _ in &pts {
        columns.extend_from_slice(&7u32.to_le_bytes());
    }
    for k in 3..6 {
        for p in &pts {
            columns.extend_from_slice(&(p[k] as f32).to_le_bytes());
        }
    }
    for _ in &pts {
        for v in [0.1f32, 0.2, 0.3] {
            columns.extend_from_slice(&v.to_le_bytes());
        }
    }
    for _ in &pts {
        columns.extend_from_slice(&(-7i16).to_le_bytes());
    }
    let packed = lzf_literals(&columns);
    let mut compressed = Vec::new();
    compressed.extend_from_slice(&(packed.len() as u32).to_le_bytes());
    compressed.extend_from_slice(&(columns.len() as u32).to_le_bytes());
    compressed.extend_from_slice(&packed);
    let cases = [
        ("ascii", body.into_bytes(), CloudFormat::PcdAscii),
        ("binary", records.clone(), CloudFormat::PcdBinary),
        (
            "binary_compressed",
            compressed,
            CloudFormat::PcdBinaryCompressed,
        ),
    ];
    for (data, body, format) in cases {
        let path = write(
            dir.path(),
            &format!("{data}.pcd"),
            &pcd_bytes(data, &fields, 3, &body),
        );
        let (cloud, report) = read_point_cloud(&path).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(report.format, format);
        assert_eq!(report.points_read, 3);
        assert_eq!(report.dropped_non_finite, 1);
        assert!(report.had_normals);
        assert_eq!(cloud.len(), 2);
        for (i, p) in [pts[0], pts[2]].iter().enumerate() {
            let q = cloud.point_in_map(i);
            for a in 0..3 {
                assert!((q[a] - p[a]).abs() < 1e-4, "{data}: {q:?} vs {p:?}");
            }
            let n = cloud.normals.as_ref().unwrap()[i];
            for a in 0..3 {
                assert!((f64::from(n[a]) - p[3 + a]).abs() < 1e-6);
            }
        }
    }
    // Errors: truncated binary, POINTS vs WIDTH, missing x, unknown DATA,
    // corrupt compressed block.
    let mut cut = pcd_bytes("binary", &fields, 3, &records);
    cut.truncate(cut.len() - 3);
    let err = read_err(&write(dir.path(), "cut.pcd", &cut));
    assert!(
        matches!(
            err,
            MapIoError::Truncated {
                declared: 3,
                read: 2,
                ..
            }
        ),
        "{err}"
    );
    let lying = String::from_utf8(pcd_bytes("ascii", &fields, 3, b""))
        .unwrap()
        .replace("POINTS 3", "POINTS 4");
    read_err(&write(dir.path(), "lying.pcd", lying.as_bytes()));
    let no_x = [("u", "F", 4, 1), ("y", "F", 4, 1), ("z", "F", 4, 1)];
    let err = read_err(&write(
        dir.path(),
        "no_x.pcd",
        &pcd_bytes("ascii", &no_x, 1, b"1 2 3\n"),
    ));
    assert!(matches!(err, MapIoError::MissingCoordinate { .. }), "{err}");
    read_err(&write(
        dir.path(),
        "data.pcd",
        &pcd_bytes("zipped", &no_x, 1, b""),
    ));
    let mut bad = Vec::new();
    bad.extend_from_slice(&4u32.to_le_bytes());
    bad.extend_from_slice(&((3 * 4 * 3) as u32).to_le_bytes());
    bad.extend_from_slice(&[40, 9, 9, 9]);
    let xyz = [("x", "F", 4, 1), ("y", "F", 4, 1), ("z", "F", 4, 1)];
    read_err(&write(
        dir.path(),
        "bad_lzf.pcd",
        &pcd_bytes("binary_compressed", &xyz, 3, &bad),
    ));
    // COUNTs whose record size is beyond any real layout or overflows:
    // header errors, not an allocation, a division by zero or a slice
    // out of range.
    let huge = |size, count| {
        [
            ("x", "F", 4, 1),
            ("y", "F", 4, 1),
            ("z", "F", 4, 1),
            ("a", "U", size, count),
        ]
    };
    for (name, data, fields, body) in [
        (
            "count_ascii.pcd",
            "ascii",
            huge(4, 1 << 60),
            &b"1 2 3 4\n"[..],
        ),
        (
            "count_wraps.pcd",
            "binary",
            huge(1, usize::MAX - 11),
            &[0u8; 16][..],
        ),
        (
            "count_first.pcd",
            "binary",
            {
                let mut f = huge(1, 1);
                f.rotate_right(1);
                f[0].3 = usize::MAX - 7;
                f
            },
            &[0u8; 16][..],
        ),
        (
            "count_lzf.pcd",
            "binary_compressed",
            huge(1, usize::MAX - 11),
            &[0u8; 8][..],
        ),
    ] {
        let err = read_err(&write(dir.path(), name, &pcd_bytes(data, &fields, 1, body)));
        assert!(
            err.to_string()
                .contains("point record of more than 1048576 bytes"),
            "{name}: {err}"
        );
    }
    // A compressed block that says it expands more than LZF can.
    let mut sizes = 4u32.to_le_bytes().to_vec();
    sizes.extend_from_slice(&12_000u32.to_le_bytes());
    sizes.extend_from_slice(&[0, 9, 9, 9]);
    let err = read_err(&write(
        dir.path(),
        "lzf_ratio.pcd",
        &pcd_bytes("binary_compressed", &xyz, 1000, &sizes),
    ));
    assert!(err.to_string().contains("more than LZF can"), "{err}");
    // Every truncation of the binary file fails cleanly.
    let full = pcd_bytes("binary", &fields, 3, &records);
    let path = dir.path().join("cuts.pcd");
    for len in 0..full.len() {
        std::fs::write(&path, &full[..len]).unwrap();
        assert!(read_point_cloud(&path).is_err(), "cut at {len}");
    }
}

/// LAS/LAZ points of the ASPRS noise classes (7, 18) and points flagged
/// withheld are left out by default and counted (the other flags, set on a
/// third of the points, change nothing); `--drop-classes` chooses the
/// classes (`none` keeps them all), in the legacy point formats and the
/// extended ones (LAS 1.4, format 6), whose flags sit elsewhere.
#[test]
fn las_noise_classes_and_withheld_points_are_left_out() {
    let dir = tempfile::tempdir().unwrap();
    let classes = [2u8, 7, 18, 6];
    let withheld = |i: usize| i % 10 == 3;
    for (version, format, ext) in [((1, 2), 1u8, "las"), ((1, 4), 6, "laz"), ((1, 4), 6, "las")] {
        let path = dir.path().join(format!("classes_{format}.{ext}"));
        let mut builder = las::Builder::from(version);
        builder.point_format = las::point::Format::new(format).unwrap();
        builder.point_format.is_compressed = ext == "laz";
        let mut writer = las::Writer::from_path(&path, builder.into_header().unwrap()).unwrap();
        for i in 0..40 {
            writer
                .write_point(las::Point {
                    x: i as f64,
                    y: 2.0,
                    z: 3.0,
                    classification: las::point::Classification::new(classes[i % 4]).unwrap(),
                    is_withheld: withheld(i),
                    // The flags beside withheld, which must not count as it.
                    is_synthetic: i % 3 == 0,
                    is_key_point: i % 3 == 0,
                    is_edge_of_flight_line: i % 3 == 0,
                    is_overlap: format >= 6 && i % 3 == 0,
                    scanner_channel: if format >= 6 { (i % 4) as u8 } else { 0 },
                    gps_time: Some(1.0),
                    ..Default::default()
                })
                .unwrap();
        }
        writer.close().unwrap();
        drop(writer);
        let xs = |cloud: &PointCloud| -> Vec<usize> {
            (0..cloud.len())
                .map(|i| cloud.point_in_map(i).x as usize)
                .collect()
        };
        let (cloud, report) = read_point_cloud(&path).unwrap();
        let kept: Vec<usize> = (0..40)
            .filter(|&i| !withheld(i) && ![7, 18].contains(&classes[i % 4]))
            .collect();
        assert_eq!(xs(&cloud), kept, "format {format}");
        // 40 records: 4 withheld (3, 13, 23, 33: classes 6, 7, 6, 7), and
        // 18 of the other 36 of a noise class.
        assert_eq!(report.points_read, 40);
        assert_eq!(report.dropped_withheld, 4);
        assert_eq!(report.dropped_by_class, 18);
        let every_class = ReadOptions {
            drop_las_classes: Vec::new(),
            ..Default::default()
        };
        let (cloud, report) = read_point_cloud_with(&path, &every_class).unwrap();
        let kept: Vec<usize> = (0..40).filter(|&i| !withheld(i)).collect();
        assert_eq!(xs(&cloud), kept, "format {format}");
        assert_eq!((report.dropped_by_class, report.dropped_withheld), (0, 4));
    }
    // A noise point far below the survey stretches the header's bounds
    // (here 100 km): the origin then comes from the points kept, which
    // keep their coordinates to the micrometre.
    let path = dir.path().join("outlier.las");
    let utm = [512_000.0, 5_412_000.0, 0.0];
    let mut writer = las::Writer::from_path(&path, millimetre_las_header(utm)).unwrap();
    let survey = |i: usize| [512_100.0 + i as f64 * 0.25, 5_412_200.5, 230.125];
    for i in 0..20 {
        let [x, y, z] = survey(i);
        let (z, class) = if i == 0 { (-99_770.0, 7) } else { (z, 2) };
        writer
            .write_point(las::Point {
                x,
                y,
                z,
                classification: las::point::Classification::new(class).unwrap(),
                gps_time: Some(1.0),
                ..Default::default()
            })
            .unwrap();
    }
    writer.close().unwrap();
    drop(writer);
    // The same file with the header's bounds zeroed (a writer that left
    // them unset; LAS 1.2 keeps them at bytes 179-226): no origin at zero.
    let unset = dir.path().join("unset_bounds.las");
    let mut bytes = std::fs::read(&path).unwrap();
    bytes[179..227].fill(0);
    std::fs::write(&unset, bytes).unwrap();
    for path in [&path, &unset] {
        let (cloud, report) = read_point_cloud(path).unwrap();
        assert_eq!((cloud.len(), report.dropped_by_class), (19, 1));
        assert!(report.max_offset_m < 10.0, "{report:?}");
        for i in 0..19 {
            let p = cloud.point_in_map(i);
            let q = survey(i + 1);
            assert!((0..3).all(|a| (p[a] - q[a]).abs() < 1e-6), "{p:?} {q:?}");
        }
    }

    // On the command line.
    let path = dir.path().join("classes_1.las");
    let out = dir.path().join("map.ply");
    let prepare = |classes: &str| {
        std::process::Command::new(crate::common::bin())
            .args([
                "prepare-map",
                "--voxel",
                "0",
                "--keep-without-normal",
                "--input",
            ])
            .arg(&path)
            .arg("--output")
            .arg(&out)
            .args(["--drop-classes", classes])
            .output()
            .unwrap()
    };
    let output = prepare("6,18");
    assert!(output.status.success(), "{output:?}");
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        stdout.contains(
            "40 points read (0 dropped as NaN/inf, 18 of the classes 6,18, 4 flagged withheld)"
        ),
        "{stdout}"
    );
    assert_eq!(read_point_cloud(&out).unwrap().0.len(), 18);
    let output = prepare("7,x");
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stderr.contains("--drop-classes") && stderr.contains("`7,x`"),
        "{stderr}"
    );
}

#[test]
fn las_and_laz_written_by_the_las_crate_read_back() {
    let dir = tempfile::tempdir().unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let pts: Vec<[f64; 3]> = (0..3000)
        .map(|_| {
            [
                512_000.0 + (rng.gen_range(0.0..800.0f64) * 1000.0).round() / 1000.0,
                5_412_000.0 + (rng.gen_range(0.0..800.0f64) * 1000.0).round() / 1000.0,
                200.0 + (rng.gen_range(0.0..50.0f64) * 1000.0).round() / 1000.0,
            ]
        })
        .collect();
    for ext in ["las", "laz"] {
        let path = dir.path().join(format!("cloud.{ext}"));
        write_millimetre_las(&path, [512_000.0, 5_412_000.0, 0.0], &pts);
        let (cloud, report) = read_point_cloud(&path).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            report.format,
            if ext == "las" {
                CloudFormat::Las
            } else {
                CloudFormat::Laz
            }
        );
        assert_eq!(report.points_read, pts.len() as u64);
        assert!(!report.had_normals);
        assert_eq!(cloud.len(), pts.len());
        for (i, p) in pts.iter().enumerate() {
            let q = cloud.point_in_map(i);
            for a in 0..3 {
                assert!(
                    (q[a] - p[a]).abs() < 1e-4,
                    "{ext} point {i}: {q:?} vs {p:?}"
                );
            }
        }
        // Truncated files are errors, not panics.
        let bytes = std::fs::read(&path).unwrap();
        for keep in [10, 200, bytes.len() / 2, bytes.len() - 7] {
            let cut = write(dir.path(), &format!("cut_{keep}.{ext}"), &bytes[..keep]);
            read_err(&cut);
        }
    }
}

#[test]
fn a_far_first_point_is_reported_through_the_largest_offset() {
    let dir = tempfile::tempdir().unwrap();
    let props = [("double", "x"), ("double", "y"), ("double", "z")];
    // A junk first point at zero picks a zero origin for a UTM cloud.
    let rows = vec![vec![0.0, 0.0, 0.0], vec![512_345.5, 5_412_345.25, 200.0]];
    let path = write(
        dir.path(),
        "junk_first.ply",
        &ply_bytes(Enc::Le, &props, &rows, None),
    );
    let (cloud, report) = read_point_cloud(&path).unwrap();
    assert_eq!(cloud.origin, Vector3::zeros());
    assert_eq!(report.max_offset_m, 5_412_345.25);
    assert!(report.max_offset_m > colmap_lidar::map::io::PRECISION_WARNING_OFFSET_M);
    // The usual case stays well below it.
    let rows = vec![
        vec![512_345.5, 5_412_345.25, 200.0],
        vec![512_845.5, 5_411_345.25, 210.0],
    ];
    let path = write(
        dir.path(),
        "utm.ply",
        &ply_bytes(Enc::Le, &props, &rows, None),
    );
    let (cloud, report) = read_point_cloud(&path).unwrap();
    assert_eq!(cloud.origin, Vector3::new(512_346.0, 5_412_345.0, 200.0));
    assert_eq!(report.max_offset_m, 999.75);
}

/// The points of `tests/data/two_scans.e57` in the map frame, in file order
/// (see `scripts/make_e57_fixture.py`): the ground and the wall x = 5 from
/// scan 0, the wall y = 8 from scan 1, all 500000, 4400000, 200 off.
fn two_scans_points() -> Vec<[f64; 3]> {
    let mut pts = Vec::new();
    for x in 0..10 {
        for y in 0..10 {
            pts.push([f64::from(x), f64::from(y), 0.0]);
        }
    }
    for y in 0..10 {
        for z in 1..5 {
            pts.push([5.0, f64::from(y), f64::from(z)]);
        }
    }
    for x in 0..10 {
        for z in 1..5 {
            pts.push([f64::from(x), 8.0, f64::from(z)]);
        }
    }
    for p in &mut pts {
        p[0] += 500000.0;
        p[1] += 4400000.0;
        p[2] += 200.0;
    }
    pts
}

#[test]
fn an_e57_file_libe57format_wrote_is_read_at_its_scans_poses() {
    // Written by libE57Format (pye57), each scan in its scanner's frame.
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/two_scans.e57");
    let (cloud, report) = read_point_cloud(&path).unwrap();
    assert_eq!(report.format, CloudFormat::E57);
    let truth = two_scans_points();
    // The invalid record of scan 1 is dropped and counted.
    assert_eq!(report.points_read, truth.len() as u64 + 1);
    assert_eq!(report.dropped_non_finite, 1);
    assert!(!report.had_normals);
    assert_eq!(cloud.len(), truth.len());
    assert_eq!(cloud.origin, Vector3::new(500000.0, 4400000.0, 200.0));
    for (i, p) in truth.iter().enumerate() {
        let q = cloud.point_in_map(i);
        for a in 0..3 {
            assert!((q[a] - p[a]).abs() < 1e-4, "point {i}: {q:?} vs {p:?}");
        }
    }
    // The extension does not matter: the signature tells.
    let dir = tempfile::tempdir().unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let renamed = write(dir.path(), "scan.bin", &bytes);
    assert_eq!(read_point_cloud(&renamed).unwrap().0.len(), truth.len());
    // Cut short or corrupted: an error naming the file, no panic.
    for keep in [10, 100, 1024, bytes.len() / 2, bytes.len() - 7] {
        let cut = write(dir.path(), &format!("cut_{keep}.e57"), &bytes[..keep]);
        read_err(&cut);
    }
    let mut flipped = bytes.clone();
    flipped[bytes.len() / 3] ^= 0xff;
    read_err(&write(dir.path(), "flipped.e57", &flipped));
}

#[test]
fn e57_spherical_scans_are_converted_and_posed() {
    use e57::{E57Writer, Quaternion, Record, RecordValue, Transform, Translation};
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("spherical.e57");
    // Range, azimuth, elevation (the scanner's frame) of a few points.
    let rae: Vec<[f64; 3]> = (0..40)
        .map(|i| {
            let i = f64::from(i);
            [2.0 + 0.25 * i, -3.0 + 0.15 * i, -0.6 + 0.03 * i]
        })
        .collect();
    let half = 0.5 * 40f64.to_radians();
    let axis = Vector3::new(1.0, -2.0, 0.5).normalize();
    let (w, v) = (half.cos(), axis * half.sin());
    let t = Vector3::new(-12.0, 7.5, 1.25);
    {
        let mut writer = E57Writer::from_file(&path, "test-guid").unwrap();
        let mut pc = writer
            .add_pointcloud(
                "scan-guid",
                vec![
                    Record::SPHERICAL_RANGE_F64,
                    Record::SPHERICAL_AZIMUTH_F64,
                    Record::SPHERICAL_ELEVATION_F64,
                ],
            )
            .unwrap();
        pc.set_transform(Some(Transform {
            rotation: Quaternion {
                w,
                x: v.x,
                y: v.y,
                z: v.z,
            },
            translation: Translation {
                x: t.x,
                y: t.y,
                z: t.z,
            },
        }));
        for p in &rae {
            pc.add_point(p.iter().map(|&x| RecordValue::Double(x)).collect())
                .unwrap();
        }
        pc.finalize().unwrap();
        writer.finalize().unwrap();
    }
    let (cloud, report) = read_point_cloud(&path).unwrap();
    assert_eq!(report.points_read, rae.len() as u64);
    let rotation =
        nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(w, v.x, v.y, v.z));
    for (i, [r, az, el]) in rae.iter().enumerate() {
        // E57: x = r cos(el) cos(az), y = r cos(el) sin(az), z = r sin(el).
        let local = Vector3::new(
            r * el.cos() * az.cos(),
            r * el.cos() * az.sin(),
            r * el.sin(),
        );
        let expect = rotation * local + t;
        let q = cloud.point_in_map(i);
        assert!((q - expect).norm() < 1e-5, "point {i}: {q} vs {expect}");
    }
}

/// A LAS file in feet (its coordinate reference system in a WKT record or in
/// GeoTIFF keys, or the unit given) is read in metres: x and y by the
/// horizontal unit, z by the vertical one; a geographic CRS (longitude and
/// latitude) is an error that names the file, unless a unit is given; a PLY
/// given in feet is scaled too.
#[test]
fn las_coordinates_in_feet_are_read_as_metres() {
    const US_FT: f64 = 1200.0 / 3937.0;
    let dir = tempfile::tempdir().unwrap();
    // State-plane-sized coordinates on a millimetre grid.
    let survey: Vec<[f64; 3]> = (0..30)
        .map(|i| {
            let i = i as f64;
            [1_012_345.5 + 0.5 * i, 201_234.25 + i, 35.5 + 0.125 * i]
        })
        .collect();
    let write = |name: &str, version: (u8, u8), vlrs: Vec<las::Vlr>, wkt: Option<&str>| {
        let path = dir.path().join(name);
        let mut builder = las::Builder::from(version);
        builder.point_format = las::point::Format::new(if version.1 >= 4 { 6 } else { 1 }).unwrap();
        let millimetres = |offset| las::Transform {
            scale: 0.001,
            offset,
        };
        builder.transforms = las::Vector {
            x: millimetres(1_000_000.0),
            y: millimetres(200_000.0),
            z: millimetres(0.0),
        };
        builder.vlrs = vlrs;
        let mut header = builder.into_header().unwrap();
        if let Some(wkt) = wkt {
            header.set_wkt_crs(wkt.as_bytes().to_vec()).unwrap();
        }
        let mut writer = las::Writer::from_path(&path, header).unwrap();
        for &[x, y, z] in &survey {
            writer
                .write_point(las::Point {
                    x,
                    y,
                    z,
                    gps_time: Some(1.0),
                    ..Default::default()
                })
                .unwrap();
        }
        writer.close().unwrap();
        path
    };
    let projection_vlr = |record_id: u16, data: Vec<u8>| las::Vlr {
        user_id: "LASF_Projection".to_string(),
        record_id,
        description: String::new(),
        data,
    };
    // A GeoTIFF key directory of (id, location, count, value) entries.
    let geotiff_entries = |entries: &[[u16; 4]]| {
        let mut data = Vec::new();
        for v in [1u16, 1, 0, entries.len() as u16] {
            data.extend_from_slice(&v.to_le_bytes());
        }
        for entry in entries {
            for v in entry {
                data.extend_from_slice(&v.to_le_bytes());
            }
        }
        projection_vlr(34735, data)
    };
    let geotiff = |keys: &[(u16, u16)]| {
        let entries: Vec<[u16; 4]> = keys.iter().map(|&(id, v)| [id, 0, 1, v]).collect();
        vec![geotiff_entries(&entries)]
    };
    let check = |path: &Path, options: &ReadOptions, xy: f64, z: f64| {
        let (cloud, report) = read_point_cloud_with(path, options).unwrap();
        assert_eq!(cloud.len(), survey.len());
        for (i, q) in survey.iter().enumerate() {
            let p = cloud.point_in_map(i);
            let want = [q[0] * xy, q[1] * xy, q[2] * z];
            assert!(
                (0..3).all(|a| (p[a] - want[a]).abs() < 1e-6),
                "{}: {p:?} {want:?}",
                path.display()
            );
        }
        assert_eq!(report.metres_per_unit, [xy, z], "{}", path.display());
        assert_eq!(report.units.is_some(), xy != 1.0 || z != 1.0);
        report
    };
    let auto = ReadOptions::default();
    let geogcs = r#"GEOGCS["NAD83",DATUM["North_American_Datum_1983",SPHEROID["GRS 1980",6378137,298.257222101]],PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]]"#;
    let projcs = format!(
        r#"PROJCS["NAD83 / New York Long Island (ftUS)",{geogcs},PROJECTION["Lambert_Conformal_Conic_2SP"],PARAMETER["false_easting",984250],UNIT["US survey foot",0.3048006096012192,AUTHORITY["EPSG","9003"]],AUTHORITY["EPSG","2263"]]"#
    );
    // WKT (LAS 1.4): feet throughout, then feet with heights in metres.
    let path = write("wkt.las", (1, 4), Vec::new(), Some(&projcs));
    let report = check(&path, &auto, 0.3048006096012192, 0.3048006096012192);
    assert!(
        report
            .units
            .as_deref()
            .unwrap()
            .contains("US survey foot (from its WKT record)"),
        "{report:?}"
    );
    // `map` loads it so too, and its report names the unit.
    let (cloud, load) =
        colmap_lidar::commands::map::load_map_reporting(&path, Default::default(), 0.0).unwrap();
    assert_eq!(cloud.len(), survey.len());
    assert_eq!(load.units, report.units);
    assert!((cloud.point_in_map(0).x - survey[0][0] * 0.3048006096012192).abs() < 1e-6);
    // `map --input-units m` overrides the record: the raw numbers.
    let (cloud, load) =
        colmap_lidar::commands::map::load_map_reporting(&path, InputUnits::Metre, 0.0).unwrap();
    assert_eq!(load.units, None);
    assert!((cloud.point_in_map(0).x - survey[0][0]).abs() < 1e-6);
    let compound = format!(
        r#"COMPD_CS["NY + NAVD88",{projcs},VERT_CS["NAVD88 height",VERT_DATUM["NAVD88",2005],UNIT["metre",1]]]"#
    );
    let path = write("compound.laz", (1, 4), Vec::new(), Some(&compound));
    check(&path, &auto, 0.3048006096012192, 1.0);
    // GeoTIFF keys (LAS 1.2): only the projected CRS's EPSG code (2263, in
    // US survey feet), or a unit key, or a CRS in metres.
    let path = write(
        "epsg2263.las",
        (1, 2),
        geotiff(&[(1024, 1), (3072, 2263)]),
        None,
    );
    check(&path, &auto, US_FT, US_FT);
    let path = write(
        "unitkey.las",
        (1, 2),
        geotiff(&[(1024, 1), (3076, 9002), (4099, 9001)]),
        None,
    );
    check(&path, &auto, 0.3048, 1.0);
    let path = write(
        "utm.las",
        (1, 2),
        geotiff(&[(1024, 1), (3072, 32618)]),
        None,
    );
    check(&path, &auto, 1.0, 1.0);
    // No CRS record: metres, unless a unit is given.
    let path = write("plain.las", (1, 2), Vec::new(), None);
    check(&path, &auto, 1.0, 1.0);
    let given = ReadOptions {
        units: InputUnits::UsSurveyFoot,
        ..Default::default()
    };
    let report = check(&path, &given, US_FT, US_FT);
    assert_eq!(report.units.as_deref(), Some("US survey foot (as given)"));
    // Longitude and latitude: an error naming the file and the CRS, in
    // either record; a unit given overrides the record.
    for path in [
        write(
            "lonlat.las",
            (1, 2),
            geotiff(&[(1024, 2), (2048, 4269)]),
            None,
        ),
        write("lonlat_wkt.las", (1, 4), Vec::new(), Some(geogcs)),
    ] {
        let err = read_err(&path).to_string();
        assert!(
            err.contains("is geographic") && err.contains("--input-units m"),
            "{err}"
        );
        let metres = ReadOptions {
            units: InputUnits::Metre,
            ..Default::default()
        };
        check(&path, &metres, 1.0, 1.0);
    }
    // LAS 1.2 with a WKT record: read when there are no GeoTIFF keys, or
    // when they give no unit; GeoTIFF keys that give one come first (the
    // header does not say WKT).
    let wkt_vlr = || projection_vlr(2112, projcs.clone().into_bytes());
    let path = write("wkt12.las", (1, 2), vec![wkt_vlr()], None);
    check(&path, &auto, US_FT, US_FT);
    let mut both = geotiff(&[(1024, 1)]);
    both.push(wkt_vlr());
    let path = write("wkt_after_keys.las", (1, 2), both, None);
    check(&path, &auto, US_FT, US_FT);
    let mut both = geotiff(&[(1024, 1), (3072, 32618)]);
    both.push(wkt_vlr());
    let path = write("keys_before_wkt.las", (1, 2), both, None);
    check(&path, &auto, 1.0, 1.0);
    // A citation key pointing past its (missing) text record does not
    // hide the other keys.
    let keys = geotiff_entries(&[[1024, 0, 1, 1], [1026, 34737, 50, 0], [3072, 0, 1, 2263]]);
    let path = write("citation.las", (1, 2), vec![keys], None);
    check(&path, &auto, US_FT, US_FT);
    // A record that cannot be read, with nothing else saying the unit: an
    // error naming the file, not metres.
    for (name, version, vlrs, wkt) in [
        (
            "short_keys.las",
            (1, 2),
            vec![projection_vlr(34735, vec![1, 0, 1])],
            None,
        ),
        (
            "bad_wkt.las",
            (1, 4),
            Vec::new(),
            Some(r#"PROJCS["NY",UNIT["US survey foot",0.3048"#),
        ),
    ] {
        let path = write(name, version, vlrs, wkt);
        let err = read_err(&path).to_string();
        assert!(
            err.contains("cannot be read") && err.contains("--input-units"),
            "{err}"
        );
    }
    // A unit code this reader does not size: an error naming it.
    let path = write(
        "fathoms.las",
        (1, 2),
        geotiff(&[(1024, 1), (3076, 9014)]),
        None,
    );
    let err = read_err(&path).to_string();
    assert!(
        err.contains("EPSG:9014") && err.contains("--input-units"),
        "{err}"
    );
    // A PLY given in feet: scaled, the local origin with it, normals kept.
    let cloud = PointCloud {
        origin: Vector3::new(3_000_000.0, 700_000.0, 300.0),
        points: vec![[10.0, -20.0, 3.0], [1.0, 2.0, 4.0]],
        normals: Some(vec![[0.0, 0.0, 1.0], [0.6, 0.8, 0.0]]),
        planarity: None,
    };
    let ply = dir.path().join("feet.ply");
    write_ply(&ply, &cloud).unwrap();
    let feet = ReadOptions {
        units: InputUnits::Foot,
        ..Default::default()
    };
    let (read, report) = read_point_cloud_with(&ply, &feet).unwrap();
    assert_eq!(report.metres_per_unit, [0.3048, 0.3048]);
    assert_eq!(report.units.as_deref(), Some("foot (as given)"));
    for i in 0..2 {
        let want = cloud.point_in_map(i) * 0.3048;
        assert!((read.point_in_map(i) - want).norm() < 1e-5, "{i}");
    }
    assert_eq!(read.normals, cloud.normals);
}
