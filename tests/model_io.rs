//! Integration tests: COLMAP model I/O. Exact round trips between our text and
//! binary encodings, the real `colmap model_analyzer` / `model_converter` reading
//! what we write, and typed errors (never panics) on malformed or truncated files.
use std::fs;
use std::path::{Path, PathBuf};

use colmap_lidar::io::model::{
    detect_format, read_binary_model, read_model, read_text_model, write_model, ModelError,
    ModelFormat,
};
use colmap_lidar::scene::{
    Camera, CameraId, CameraModel, Image, ImageId, Point2D, Point3D, Point3DId, Reconstruction,
    Rigid3, TrackElement,
};
use nalgebra::{UnitQuaternion, Vector2, Vector3};
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::common;

/// A float of random sign and magnitude (1e-12 .. 1e6), sometimes exactly 0 or 1.
fn wild_f64(rng: &mut ChaCha8Rng) -> f64 {
    match rng.gen_range(0..10) {
        0 => 0.0,
        1 => 1.0,
        _ => {
            let mag = 10f64.powf(rng.gen_range(-12.0..6.0));
            if rng.gen_bool(0.5) {
                mag
            } else {
                -mag
            }
        }
    }
}

/// A random, consistent reconstruction: every camera model, sparse ids, some
/// unregistered images, images without keypoints, keypoints without points, points
/// with tracks over 1-4 registered images. Image names have no spaces so that COLMAP
/// 3.8's text reader keeps them whole.
fn random_reconstruction(seed: u64) -> Reconstruction {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut rec = Reconstruction::default();
    let mut camera_id = 0u32;
    for model in CameraModel::ALL {
        camera_id += rng.gen_range(1..1000);
        let params = (0..model.num_params())
            .map(|i| {
                if i < 4 {
                    rng.gen_range(1.0..5000.0)
                } else {
                    wild_f64(&mut rng)
                }
            })
            .collect();
        rec.cameras.insert(
            CameraId(camera_id),
            Camera {
                id: CameraId(camera_id),
                model,
                width: rng.gen_range(1..10_000),
                height: rng.gen_range(1..10_000),
                params,
            },
        );
    }
    let camera_ids: Vec<CameraId> = rec.cameras.keys().copied().collect();

    let mut image_id = 0u32;
    for i in 0..rng.gen_range(8..20) {
        image_id += rng.gen_range(1..50);
        let registered = rng.gen_bool(0.8);
        let pose = Rigid3::new(
            UnitQuaternion::from_euler_angles(
                rng.gen_range(-3.0..3.0),
                rng.gen_range(-1.5..1.5),
                rng.gen_range(-3.0..3.0),
            ),
            Vector3::new(wild_f64(&mut rng), wild_f64(&mut rng), wild_f64(&mut rng)),
        );
        let num_points = if rng.gen_bool(0.15) {
            0
        } else {
            rng.gen_range(1..60)
        };
        let points2d = (0..num_points)
            .map(|_| Point2D {
                xy: Vector2::new(rng.gen_range(0.0..4000.0), rng.gen_range(0.0..3000.0)),
                point3d_id: None,
            })
            .collect();
        rec.images.insert(
            ImageId(image_id),
            Image {
                id: ImageId(image_id),
                name: format!("seq_{seed}/frame-{i:04}.jpg"),
                camera_id: *camera_ids.choose(&mut rng).expect("cameras exist"),
                cam_from_world: registered.then_some(pose),
                points2d,
            },
        );
    }

    // Points observe free keypoints of registered images.
    let mut free: Vec<(ImageId, u32)> = rec
        .registered_images()
        .flat_map(|im| (0..im.points2d.len() as u32).map(move |k| (im.id, k)))
        .collect();
    free.shuffle(&mut rng);
    let mut point_id = rng.gen_range(0..3u64);
    for _ in 0..rng.gen_range(20..80) {
        point_id += if rng.gen_bool(0.1) {
            1 << 40
        } else {
            rng.gen_range(1..20)
        };
        let want = rng.gen_range(0..=4usize);
        let mut track = Vec::new();
        let mut i = 0;
        while track.len() < want && i < free.len() {
            let (image_id, idx) = free[i];
            if track.iter().all(|e: &TrackElement| e.image_id != image_id) {
                track.push(TrackElement {
                    image_id,
                    point2d_idx: idx,
                });
                free.swap_remove(i);
            } else {
                i += 1;
            }
        }
        for el in &track {
            let image = rec
                .images
                .get_mut(&el.image_id)
                .expect("track image exists");
            image.points2d[el.point2d_idx as usize].point3d_id = Some(Point3DId(point_id));
        }
        rec.points3d.insert(
            Point3DId(point_id),
            Point3D {
                xyz: Vector3::new(wild_f64(&mut rng), wild_f64(&mut rng), wild_f64(&mut rng)),
                color: [rng.gen(), rng.gen(), rng.gen()],
                error: rng.gen_range(0.0..3.0),
                track,
            },
        );
    }
    rec
}

/// What a written model reads back as: the registered images only.
fn registered_only(rec: &Reconstruction) -> Reconstruction {
    let mut out = rec.clone();
    out.images.retain(|_, im| im.is_registered());
    out
}

/// Asserts `a == b`, reporting only the first differing camera, image or point.
fn assert_same(a: &Reconstruction, b: &Reconstruction, context: &str) {
    fn first_diff<K: Ord + std::fmt::Debug, V: PartialEq + std::fmt::Debug>(
        what: &str,
        a: &std::collections::BTreeMap<K, V>,
        b: &std::collections::BTreeMap<K, V>,
    ) -> Option<String> {
        let keys_a: Vec<&K> = a.keys().collect();
        let keys_b: Vec<&K> = b.keys().collect();
        if keys_a != keys_b {
            return Some(format!("{what} ids differ: {keys_a:?} vs {keys_b:?}"));
        }
        a.iter()
            .zip(b.values())
            .find(|((_, va), vb)| va != vb)
            .map(|((k, va), vb)| format!("{what} {k:?} differs:\n{va:?}\nvs\n{vb:?}"))
    }
    let diff = first_diff("camera", &a.cameras, &b.cameras)
        .or_else(|| first_diff("image", &a.images, &b.images))
        .or_else(|| first_diff("point", &a.points3d, &b.points3d));
    if let Some(diff) = diff {
        panic!("{context}: {diff}");
    }
    assert_eq!(a, b, "{context}");
}

fn model_bytes(dir: &Path, format: ModelFormat) -> Vec<Vec<u8>> {
    format
        .paths(dir)
        .iter()
        .map(|p| fs::read(p).unwrap_or_else(|e| panic!("{}: {e}", p.display())))
        .collect()
}

#[test]
fn text_binary_text_round_trip_is_exact() {
    for seed in 0..6 {
        let rec = random_reconstruction(seed);
        let expected = registered_only(&rec);
        assert!(expected.images.len() < rec.images.len() || seed > 0);
        let root = tempfile::tempdir().unwrap();
        let (t1, b1, t2, b2) = (
            root.path().join("t1"),
            root.path().join("b1"),
            root.path().join("t2"),
            root.path().join("b2"),
        );

        write_model(&t1, &rec, ModelFormat::Text).unwrap();
        let from_t1 = read_text_model(&t1).unwrap();
        assert_same(&from_t1, &expected, &format!("seed {seed}: text read-back"));

        write_model(&b1, &from_t1, ModelFormat::Binary).unwrap();
        let from_b1 = read_binary_model(&b1).unwrap();
        assert_same(
            &from_b1,
            &expected,
            &format!("seed {seed}: binary read-back"),
        );

        write_model(&t2, &from_b1, ModelFormat::Text).unwrap();
        assert_eq!(
            model_bytes(&t1, ModelFormat::Text),
            model_bytes(&t2, ModelFormat::Text),
            "seed {seed}: text -> binary -> text changed bytes"
        );

        write_model(&b2, &read_text_model(&t2).unwrap(), ModelFormat::Binary).unwrap();
        assert_eq!(
            model_bytes(&b1, ModelFormat::Binary),
            model_bytes(&b2, ModelFormat::Binary),
            "seed {seed}: binary -> text -> binary changed bytes"
        );

        // Writing from the original (with unregistered images) gives the same bytes.
        let b3 = root.path().join("b3");
        write_model(&b3, &rec, ModelFormat::Binary).unwrap();
        assert_eq!(
            model_bytes(&b1, ModelFormat::Binary),
            model_bytes(&b3, ModelFormat::Binary)
        );
    }
}

#[test]
fn text_header_and_layout_match_colmap() {
    let mut rec = Reconstruction::default();
    rec.cameras.insert(
        CameraId(1),
        Camera {
            id: CameraId(1),
            model: CameraModel::SimpleRadial,
            width: 640,
            height: 480,
            params: vec![500.5, 320.0, 240.0, -0.01],
        },
    );
    for (id, points) in [
        (2u32, vec![]),
        (1, vec![(10.5, 20.25, Some(7)), (1.0, 2.0, None)]),
    ] {
        rec.images.insert(
            ImageId(id),
            Image {
                id: ImageId(id),
                name: format!("im{id}.png"),
                camera_id: CameraId(1),
                cam_from_world: Some(Rigid3::new(
                    UnitQuaternion::identity(),
                    Vector3::new(0.1, 1e-7, -3.0),
                )),
                points2d: points
                    .into_iter()
                    .map(|(x, y, p)| Point2D {
                        xy: Vector2::new(x, y),
                        point3d_id: p.map(Point3DId),
                    })
                    .collect(),
            },
        );
    }
    rec.points3d.insert(
        Point3DId(7),
        Point3D {
            xyz: Vector3::new(1.0, -2.5, 3.0),
            color: [255, 0, 10],
            error: 0.5,
            track: vec![TrackElement {
                image_id: ImageId(1),
                point2d_idx: 0,
            }],
        },
    );
    let root = tempfile::tempdir().unwrap();
    let dir = root.path().join("m");
    write_model(&dir, &rec, ModelFormat::Text).unwrap();
    let images = fs::read_to_string(dir.join("images.txt")).unwrap();
    assert_eq!(
        images,
        "# Image list with two lines of data per image:\n\
         #   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n\
         #   POINTS2D[] as (X, Y, POINT3D_ID)\n\
         # Number of images: 2, mean observations per image: 0.5\n\
         1 1 0 0 0 0.1 1e-7 -3 1 im1.png\n\
         10.5 20.25 7 1 2 -1\n\
         2 1 0 0 0 0.1 1e-7 -3 1 im2.png\n\
         \n"
    );
    let cameras = fs::read_to_string(dir.join("cameras.txt")).unwrap();
    assert!(
        cameras.ends_with("# Number of cameras: 1\n1 SIMPLE_RADIAL 640 480 500.5 320 240 -0.01\n")
    );
    let points = fs::read_to_string(dir.join("points3D.txt")).unwrap();
    assert!(points
        .ends_with("# Number of points: 1, mean track length: 1\n7 1 -2.5 3 255 0 10 0.5 1 0\n"));
    assert_eq!(read_model(&dir).unwrap(), rec);

    // Binary sizes by hand: header 8 + camera (4+4+8+8+4*8) = 64 bytes.
    write_model(&dir, &rec, ModelFormat::Binary).unwrap();
    assert_eq!(fs::read(dir.join("cameras.bin")).unwrap().len(), 64);
    // 8 + image 1 (4+56+4+8 name "im1.png\0"+8+2*24) + image 2 (4+56+4+8+8).
    assert_eq!(
        fs::read(dir.join("images.bin")).unwrap().len(),
        8 + 128 + 80
    );
    // 8 + point (8+24+3+8+8+8).
    assert_eq!(fs::read(dir.join("points3D.bin")).unwrap().len(), 8 + 59);
    assert!(
        !dir.join("images.txt").exists(),
        "old text files left behind"
    );
    assert_eq!(read_model(&dir).unwrap(), rec);
}

#[test]
fn names_with_inner_spaces_round_trip_and_bad_names_are_refused() {
    let mut rec = random_reconstruction(11);
    let id = rec.registered_images().next().unwrap().id;
    rec.images.get_mut(&id).unwrap().name = "my holiday/IMG 0001.JPG".to_string();
    let root = tempfile::tempdir().unwrap();
    for format in [ModelFormat::Text, ModelFormat::Binary] {
        let dir = root.path().join(format.extension());
        write_model(&dir, &rec, format).unwrap();
        assert_eq!(read_model(&dir).unwrap(), registered_only(&rec));
    }
    for bad in ["a\nb.jpg", " lead.jpg", "", "nul\0.jpg"] {
        rec.images.get_mut(&id).unwrap().name = bad.to_string();
        let dir = root.path().join("bad");
        let err = write_model(&dir, &rec, ModelFormat::Text).unwrap_err();
        assert!(matches!(err, ModelError::InvalidModel { .. }), "{err}");
        assert!(!dir.exists());
    }
}

#[test]
fn write_refuses_inconsistent_models_and_foreign_folders() {
    let root = tempfile::tempdir().unwrap();
    let dir = root.path().join("model");
    let rec = random_reconstruction(3);
    write_model(&dir, &rec, ModelFormat::Binary).unwrap();
    let before = model_bytes(&dir, ModelFormat::Binary);

    // A track element naming an unregistered image.
    let mut bad = rec.clone();
    let (pid, point) = bad
        .points3d
        .iter()
        .find(|(_, p)| !p.track.is_empty())
        .map(|(id, p)| (*id, p.clone()))
        .unwrap();
    let el = point.track[0];
    bad.images.get_mut(&el.image_id).unwrap().cam_from_world = None;
    let err = write_model(&dir, &bad, ModelFormat::Text).unwrap_err();
    assert!(err.to_string().contains(&format!("point {pid}")), "{err}");
    assert_eq!(model_bytes(&dir, ModelFormat::Binary), before);
    assert!(!dir.join("cameras.txt").exists());

    // A keypoint naming a point that does not exist.
    let mut bad = rec.clone();
    bad.points3d.remove(&pid);
    assert!(write_model(&dir, &bad, ModelFormat::Binary).is_err());
    // Wrong parameter count.
    let mut bad = rec.clone();
    bad.cameras.values_mut().next().unwrap().params.pop();
    assert!(write_model(&dir, &bad, ModelFormat::Binary).is_err());
    assert_eq!(model_bytes(&dir, ModelFormat::Binary), before);

    // A folder with something else in it is not replaced.
    fs::write(dir.join("notes.md"), "mine").unwrap();
    let err = write_model(&dir, &rec, ModelFormat::Text).unwrap_err();
    assert!(matches!(err, ModelError::WouldClobber { .. }), "{err}");
    assert!(err.to_string().contains("notes.md"));
    assert_eq!(fs::read_to_string(dir.join("notes.md")).unwrap(), "mine");
    let file = root.path().join("file");
    fs::write(&file, "x").unwrap();
    assert!(write_model(&file, &rec, ModelFormat::Text).is_err());
    assert_eq!(fs::read_to_string(&file).unwrap(), "x");
    // Nothing temporary left next to the outputs.
    let mut names: Vec<String> = fs::read_dir(root.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(names, ["file", "model"]);
}

#[test]
fn format_detection() {
    let root = tempfile::tempdir().unwrap();
    let dir = root.path().join("m");
    assert!(matches!(
        read_model(&dir).unwrap_err(),
        ModelError::NotFound { .. }
    ));
    let rec = random_reconstruction(5);
    write_model(&dir, &rec, ModelFormat::Text).unwrap();
    assert_eq!(detect_format(&dir).unwrap(), ModelFormat::Text);
    fs::remove_file(dir.join("points3D.txt")).unwrap();
    let err = read_model(&dir).unwrap_err();
    assert!(matches!(err, ModelError::Incomplete { .. }));
    assert!(err.to_string().contains("points3D.txt"), "{err}");
    write_model(&dir, &rec, ModelFormat::Binary).unwrap();
    assert_eq!(detect_format(&dir).unwrap(), ModelFormat::Binary);
    assert_eq!(read_model(&dir).unwrap(), registered_only(&rec));
}

// ---------------------------------------------------------------- malformed input

/// A small consistent text model, written by hand.
const CAMERAS_TXT: &str = "# cams\n1 PINHOLE 100 80 50 51 50 40\n2 SIMPLE_RADIAL 10 10 5 5 5 0.1\n";
const IMAGES_TXT: &str = "# imgs\n\
    3 1 0 0 0 0 0 0 1 a.jpg\n\
    1 2 7 -1 5 -1\n\
    \n\
    4 0 1 0 0 1 2 3 2 b.jpg\n\
    9 9 7\n";
const POINTS_TXT: &str = "# pts\n7 1 2 3 255 0 10 0.5 3 0 4 0\n";

fn write_text_files(dir: &Path, cameras: &str, images: &str, points: &str) {
    fs::create_dir_all(dir).unwrap();
    fs::write(dir.join("cameras.txt"), cameras).unwrap();
    fs::write(dir.join("images.txt"), images).unwrap();
    fs::write(dir.join("points3D.txt"), points).unwrap();
}

/// Reads a text model made of the given files and returns the error message.
fn text_error(cameras: &str, images: &str, points: &str) -> String {
    let root = tempfile::tempdir().unwrap();
    write_text_files(root.path(), cameras, images, points);
    match read_model(root.path()) {
        Ok(_) => panic!("malformed model accepted:\n{cameras}\n{images}\n{points}"),
        Err(e) => e.to_string(),
    }
}

#[test]
fn hand_written_text_model_reads() {
    let root = tempfile::tempdir().unwrap();
    write_text_files(root.path(), CAMERAS_TXT, IMAGES_TXT, POINTS_TXT);
    let rec = read_model(root.path()).unwrap();
    assert_eq!(rec.cameras.len(), 2);
    assert_eq!(rec.images.len(), 2);
    let a = &rec.images[&ImageId(3)];
    assert_eq!(a.name, "a.jpg");
    assert_eq!(a.points2d.len(), 2);
    assert_eq!(a.points2d[0].point3d_id, Some(Point3DId(7)));
    assert_eq!(a.points2d[1].point3d_id, None);
    assert_eq!(a.points2d[1].xy, Vector2::new(-1.0, 5.0));
    let b = &rec.images[&ImageId(4)];
    let pose = b.cam_from_world.unwrap();
    assert_eq!(pose.quaternion_wxyz(), [0.0, 1.0, 0.0, 0.0]);
    assert_eq!(pose.translation, Vector3::new(1.0, 2.0, 3.0));
    let p = &rec.points3d[&Point3DId(7)];
    assert_eq!(p.color, [255, 0, 10]);
    assert_eq!(
        p.track,
        vec![
            TrackElement {
                image_id: ImageId(3),
                point2d_idx: 0
            },
            TrackElement {
                image_id: ImageId(4),
                point2d_idx: 0
            }
        ]
    );
}

#[test]
fn malformed_text_gives_errors_naming_file_and_line() {
    let cases: Vec<(&str, String, String, String)> = vec![
        // (expected "file:line" and words, cameras, images, points)
        (
            "cameras.txt:2: PARAMS",
            CAMERAS_TXT.replace("50 40", "50 4x0"),
            IMAGES_TXT.into(),
            POINTS_TXT.into(),
        ),
        (
            "cameras.txt:2: camera 1: model PINHOLE takes 4 parameters, found 3",
            CAMERAS_TXT.replace("50 40", "50"),
            IMAGES_TXT.into(),
            POINTS_TXT.into(),
        ),
        (
            "cameras.txt:3: MODEL: unknown camera model \"SIMPLE_RADIALX\"",
            CAMERAS_TXT.replace("SIMPLE_RADIAL", "SIMPLE_RADIALX"),
            IMAGES_TXT.into(),
            POINTS_TXT.into(),
        ),
        (
            "cameras.txt:2: WIDTH",
            CAMERAS_TXT.replace("100", "-100"),
            IMAGES_TXT.into(),
            POINTS_TXT.into(),
        ),
        (
            "cameras.txt:3: duplicate CAMERA_ID 1",
            CAMERAS_TXT.replace("2 SIMPLE", "1 SIMPLE"),
            IMAGES_TXT.into(),
            POINTS_TXT.into(),
        ),
        (
            "images.txt:2: line ends before NAME",
            CAMERAS_TXT.into(),
            IMAGES_TXT.replace(" a.jpg", ""),
            POINTS_TXT.into(),
        ),
        (
            "images.txt:2: TZ",
            CAMERAS_TXT.into(),
            IMAGES_TXT.replace("0 0 0 1 a.jpg", "0 0 zero 1 a.jpg"),
            POINTS_TXT.into(),
        ),
        (
            "images.txt:2: QW QX QY QZ",
            CAMERAS_TXT.into(),
            IMAGES_TXT.replace("3 1 0 0 0", "3 0 0 0 0"),
            POINTS_TXT.into(),
        ),
        (
            "images.txt:2: image 3: CAMERA_ID 9 is not in",
            CAMERAS_TXT.into(),
            IMAGES_TXT.replace("0 0 0 1 a.jpg", "0 0 0 9 a.jpg"),
            POINTS_TXT.into(),
        ),
        (
            "images.txt:3: line ends before POINT3D_ID of keypoint 2",
            CAMERAS_TXT.into(),
            IMAGES_TXT.replace("1 2 7 -1 5 -1", "1 2 7 -1 5 -1 8 9"),
            POINTS_TXT.into(),
        ),
        (
            "images.txt:5: file ends before the POINTS2D line of image 4",
            CAMERAS_TXT.into(),
            IMAGES_TXT.replace("b.jpg\n9 9 7\n", "b.jpg\n"),
            POINTS_TXT.into(),
        ),
        (
            "images.txt:3: image 3: keypoint 1 refers to POINT3D_ID 8, which is not in",
            CAMERAS_TXT.into(),
            IMAGES_TXT.replace("5 -1", "5 8"),
            POINTS_TXT.into(),
        ),
        (
            "images.txt:3: POINT3D_ID of keypoint 1: \"-2\"",
            CAMERAS_TXT.into(),
            IMAGES_TXT.replace("5 -1", "5 -2"),
            POINTS_TXT.into(),
        ),
        (
            "points3D.txt:2: point 7: track refers to IMAGE_ID 5, which is not in",
            CAMERAS_TXT.into(),
            IMAGES_TXT.into(),
            POINTS_TXT.replace("3 0 4 0", "3 0 5 0"),
        ),
        (
            "points3D.txt:2: point 7: track refers to POINT2D_IDX 3 of image 4, which has 1",
            CAMERAS_TXT.into(),
            IMAGES_TXT.into(),
            POINTS_TXT.replace("3 0 4 0", "3 0 4 3"),
        ),
        (
            "points3D.txt:2: point 7: track element (image 3, keypoint 1) observes no point",
            CAMERAS_TXT.into(),
            IMAGES_TXT.into(),
            POINTS_TXT.replace("3 0 4 0", "3 0 4 0 3 1"),
        ),
        (
            "points3D.txt:2: line ends before POINT2D_IDX",
            CAMERAS_TXT.into(),
            IMAGES_TXT.into(),
            POINTS_TXT.replace("3 0 4 0", "3 0 4"),
        ),
        (
            "points3D.txt:2: R: \"256\" is not an integer in 0..=255",
            CAMERAS_TXT.into(),
            IMAGES_TXT.into(),
            POINTS_TXT.replace("255 0 10", "256 0 10"),
        ),
        (
            // Point 7 misses (image 3, keypoint 0) in its track.
            "images.txt:3: image 3: keypoint 0 refers to POINT3D_ID 7, whose track does not",
            CAMERAS_TXT.into(),
            IMAGES_TXT.into(),
            POINTS_TXT.replace("0.5 3 0 4 0", "0.5 4 0"),
        ),
    ];
    for (expected, cameras, images, points) in cases {
        let msg = text_error(&cameras, &images, &points);
        assert!(
            msg.contains(expected),
            "expected {expected:?} in the error, got {msg:?}"
        );
    }
    // A typo fixed gives back a valid model (the cases above differ only in the typo).
    let root = tempfile::tempdir().unwrap();
    write_text_files(root.path(), CAMERAS_TXT, IMAGES_TXT, POINTS_TXT);
    assert!(read_model(root.path()).is_ok());
}

/// The three files of a model as written by us, in `format`, for `rec`.
fn files_of(rec: &Reconstruction, format: ModelFormat) -> Vec<(String, Vec<u8>)> {
    let root = tempfile::tempdir().unwrap();
    let dir = root.path().join("m");
    write_model(&dir, rec, format).unwrap();
    format
        .paths(&dir)
        .iter()
        .map(|p| {
            (
                p.file_name().unwrap().to_string_lossy().into_owned(),
                fs::read(p).unwrap(),
            )
        })
        .collect()
}

/// Reads the model in `dir` (holding `files`) with file `which` replaced by `bytes`,
/// then restores that file. Returns the error message, if any, after checking that
/// it names a model file: the replaced one for binary models (whose files are parsed
/// to the last byte before any cross-check), any of the three for text ones (a
/// truncated text file may parse and fail a consistency check in another file).
fn read_with_replaced(
    dir: &Path,
    files: &[(String, Vec<u8>)],
    which: usize,
    bytes: &[u8],
    format: ModelFormat,
) -> Option<String> {
    let path = dir.join(&files[which].0);
    fs::write(&path, bytes).unwrap();
    let result = match format {
        ModelFormat::Text => read_text_model(dir),
        ModelFormat::Binary => read_binary_model(dir),
    };
    fs::write(&path, &files[which].1).unwrap();
    let msg = result.err()?.to_string();
    let named = match format {
        ModelFormat::Binary => msg.contains(&files[which].0),
        ModelFormat::Text => files.iter().any(|(name, _)| msg.contains(name)),
    };
    assert!(named, "error does not name the file: {msg}");
    Some(msg)
}

/// Truncation lengths to try: every one near both ends, a sample in between (the
/// unit tests in `src/io/model` try every length and many more corruptions in memory).
fn truncation_lengths(len: usize) -> Vec<usize> {
    let mut lens: Vec<usize> = (0..len.min(48)).collect();
    lens.extend(len.saturating_sub(16)..len);
    lens.extend((0..40).map(|i| i * len / 40));
    lens.sort();
    lens.dedup();
    lens
}

#[test]
fn truncated_and_garbage_files_give_errors_not_panics() {
    let rec = random_reconstruction(7);
    let root = tempfile::tempdir().unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(99);
    for format in [ModelFormat::Binary, ModelFormat::Text] {
        let dir = root.path().join(format.extension());
        fs::create_dir_all(&dir).unwrap();
        let files = files_of(&rec, format);
        for (name, content) in &files {
            fs::write(dir.join(name), content).unwrap();
        }
        for which in 0..3 {
            let full = &files[which].1;
            let lens = truncation_lengths(full.len());
            let mut errors = 0;
            for &len in &lens {
                if read_with_replaced(&dir, &files, which, &full[..len], format).is_some() {
                    errors += 1;
                }
            }
            if format == ModelFormat::Binary {
                // A truncated binary file is always an error.
                assert_eq!(errors, lens.len(), "{}", files[which].0);
                let msg = read_with_replaced(&dir, &files, which, &full[..full.len() - 3], format)
                    .unwrap();
                assert!(msg.contains("truncated"), "{msg}");
                let mut longer = full.clone();
                longer.push(0);
                let msg = read_with_replaced(&dir, &files, which, &longer, format).unwrap();
                assert!(msg.contains("unexpected bytes"), "{msg}");
            } else {
                assert!(errors > 0);
            }
            // Random byte flips and garbage.
            for _ in 0..40 {
                let mut bytes = full.clone();
                for _ in 0..rng.gen_range(1..4) {
                    let i = rng.gen_range(0..bytes.len());
                    bytes[i] = rng.gen();
                }
                read_with_replaced(&dir, &files, which, &bytes, format);
            }
            let garbage: Vec<u8> = (0..rng.gen_range(0..2000)).map(|_| rng.gen()).collect();
            read_with_replaced(&dir, &files, which, &garbage, format);
        }
        // A huge count fails fast, without allocating.
        if format == ModelFormat::Binary {
            let mut bytes = files[2].1.clone();
            bytes[..8].copy_from_slice(&(u64::MAX / 2).to_le_bytes());
            let msg = read_with_replaced(&dir, &files, 2, &bytes, format).unwrap();
            assert!(msg.contains("header, byte offset 0"), "{msg}");
        }
    }
}

#[test]
fn binary_errors_name_record_and_offset() {
    let rec = random_reconstruction(8);
    let files = files_of(&rec, ModelFormat::Binary);
    let root = tempfile::tempdir().unwrap();
    for (name, content) in &files {
        fs::write(root.path().join(name), content).unwrap();
    }
    // cameras.bin: the first camera's MODEL_ID (offset 8 + 4) set to 99.
    let mut cams = files[0].1.clone();
    cams[12..16].copy_from_slice(&99i32.to_le_bytes());
    let msg = read_with_replaced(root.path(), &files, 0, &cams, ModelFormat::Binary).unwrap();
    assert!(
        msg.contains("cameras.bin: record 0, byte offset 12: unknown camera MODEL_ID 99"),
        "{msg}"
    );
    // images.bin: a keypoint without a 3D point gets the id of a missing point.
    let mut record_offset = 8u64;
    let mut target = None;
    for (index, image) in rec.registered_images().enumerate() {
        let name_bytes = image.name.len() as u64 + 1;
        if let Some(idx) = image.points2d.iter().position(|p| p.point3d_id.is_none()) {
            target = Some((index, record_offset, image.id, idx, name_bytes));
            break;
        }
        record_offset += 4 + 56 + 4 + name_bytes + 8 + 24 * image.points2d.len() as u64;
    }
    let (index, record_offset, image_id, idx, name_bytes) =
        target.expect("seed 8 has a keypoint without a 3D point");
    let at = (record_offset + 4 + 56 + 4 + name_bytes + 8 + 24 * idx as u64 + 16) as usize;
    let mut imgs = files[1].1.clone();
    imgs[at..at + 8].copy_from_slice(&(u64::MAX - 1).to_le_bytes());
    let msg = read_with_replaced(root.path(), &files, 1, &imgs, ModelFormat::Binary).unwrap();
    assert!(
        msg.contains(&format!(
            "images.bin: record {index}, byte offset {record_offset}: image {image_id}: \
             keypoint {idx} refers to POINT3D_ID {}, which is not in",
            u64::MAX - 1
        )),
        "{msg}"
    );
}

// ---------------------------------------------------------------- the real COLMAP

/// The integer after `label` in `model_analyzer`'s output (`Points: 123`).
fn analyzer_count(output: &str, label: &str) -> usize {
    output
        .lines()
        .find_map(|l| l.trim().strip_prefix(label)?.trim().parse().ok())
        .unwrap_or_else(|| panic!("no {label:?} line in model_analyzer output:\n{output}"))
}

fn path_str(p: &Path) -> &str {
    p.to_str().expect("temporary paths are UTF-8")
}

#[test]
fn colmap_reads_every_model_we_write() {
    if !common::have_colmap() {
        return;
    }
    for seed in [21, 22] {
        let rec = random_reconstruction(seed);
        let expected = registered_only(&rec);
        let observations: usize = expected.images.values().map(|im| im.num_points3d()).sum();
        let root = tempfile::tempdir().unwrap();
        for format in [ModelFormat::Text, ModelFormat::Binary] {
            let ours: PathBuf = root.path().join(format!("ours_{}", format.extension()));
            write_model(&ours, &rec, format).unwrap();

            let out = common::run_colmap(["model_analyzer", "--path", path_str(&ours)]);
            assert_eq!(analyzer_count(&out, "Cameras:"), expected.cameras.len());
            assert_eq!(analyzer_count(&out, "Images:"), expected.images.len());
            assert_eq!(
                analyzer_count(&out, "Registered images:"),
                expected.images.len()
            );
            assert_eq!(analyzer_count(&out, "Points:"), expected.points3d.len());
            assert_eq!(analyzer_count(&out, "Observations:"), observations);

            // COLMAP converts ours to text (it prints 17 significant digits, enough
            // for exact doubles) and to binary; both read back exactly.
            for (out_type, out_format) in [("TXT", ModelFormat::Text), ("BIN", ModelFormat::Binary)]
            {
                let converted = root
                    .path()
                    .join(format!("colmap_{}_{out_type}", format.extension()));
                fs::create_dir_all(&converted).unwrap();
                common::run_colmap([
                    "model_converter",
                    "--input_path",
                    path_str(&ours),
                    "--output_path",
                    path_str(&converted),
                    "--output_type",
                    out_type,
                ]);
                assert_eq!(detect_format(&converted).unwrap(), out_format);
                let mut back = read_model(&converted).unwrap();
                // COLMAP re-normalises quaternions on reading (last-bit changes);
                // check those to 1e-15 and everything else exactly.
                for (id, image) in back.images.iter_mut() {
                    let Some(ours) = expected.images.get(id) else {
                        continue;
                    };
                    let (Some(pose), Some(ours_pose)) =
                        (&mut image.cam_from_world, ours.cam_from_world)
                    else {
                        continue;
                    };
                    let (q, q_ours) = (pose.quaternion_wxyz(), ours_pose.quaternion_wxyz());
                    for k in 0..4 {
                        assert!(
                            (q[k] - q_ours[k]).abs() <= 1e-15,
                            "image {id}: {q:?} vs {q_ours:?}"
                        );
                    }
                    pose.rotation = ours_pose.rotation;
                }
                assert_same(
                    &back,
                    &expected,
                    &format!("seed {seed}: {format:?} -> colmap {out_type}"),
                );
            }
        }
    }
}

/// Timing on a large model (500 images x 4000 keypoints, 600k points, 1.8M
/// observations). Run with `cargo test --release --test tests model_io::large -- --ignored
/// --nocapture`.
#[test]
#[ignore = "benchmark"]
fn large_model_timing() {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let mut rec = Reconstruction::default();
    rec.cameras.insert(
        CameraId(1),
        Camera {
            id: CameraId(1),
            model: CameraModel::OpenCv,
            width: 4000,
            height: 3000,
            params: vec![3000.1, 3000.2, 2000.3, 1500.4, 0.01, -0.02, 0.001, 0.0002],
        },
    );
    let (num_images, keypoints) = (500u32, 4000usize);
    for i in 1..=num_images {
        rec.images.insert(
            ImageId(i),
            Image {
                id: ImageId(i),
                name: format!("images/{i:06}.jpg"),
                camera_id: CameraId(1),
                cam_from_world: Some(Rigid3::new(
                    UnitQuaternion::from_euler_angles(rng.gen(), rng.gen(), rng.gen()),
                    Vector3::new(rng.gen(), rng.gen(), rng.gen()),
                )),
                points2d: (0..keypoints)
                    .map(|_| Point2D {
                        xy: Vector2::new(rng.gen_range(0.0..4000.0), rng.gen_range(0.0..3000.0)),
                        point3d_id: None,
                    })
                    .collect(),
            },
        );
    }
    // Point k observes keypoint k % (keypoints * 0.9) of three consecutive images.
    let per_image = keypoints * 9 / 10;
    let mut next = 1u64;
    for start in 0..(num_images - 2) {
        for k in 0..per_image / 3 {
            let idx = (3 * k + start as usize % 3) as u32;
            let track: Vec<TrackElement> = (0..3)
                .map(|d| TrackElement {
                    image_id: ImageId(start + 1 + d),
                    point2d_idx: idx,
                })
                .filter(|el| {
                    rec.images[&el.image_id].points2d[idx as usize]
                        .point3d_id
                        .is_none()
                })
                .collect();
            for el in &track {
                rec.images.get_mut(&el.image_id).unwrap().points2d[idx as usize].point3d_id =
                    Some(Point3DId(next));
            }
            rec.points3d.insert(
                Point3DId(next),
                Point3D {
                    xyz: Vector3::new(rng.gen(), rng.gen(), rng.gen()),
                    color: [rng.gen(), rng.gen(), rng.gen()],
                    error: rng.gen(),
                    track,
                },
            );
            next += 1;
        }
    }
    let observations: usize = rec.points3d.values().map(|p| p.track.len()).sum();
    println!(
        "{} images, {} keypoints, {} points, {observations} observations",
        rec.images.len(),
        rec.images.len() * keypoints,
        rec.points3d.len()
    );
    let root = tempfile::tempdir().unwrap();
    for format in [ModelFormat::Text, ModelFormat::Binary] {
        let dir = root.path().join(format.extension());
        let t = std::time::Instant::now();
        write_model(&dir, &rec, format).unwrap();
        let write_s = t.elapsed().as_secs_f64();
        let t = std::time::Instant::now();
        let back = read_model(&dir).unwrap();
        let read_s = t.elapsed().as_secs_f64();
        let bytes: usize = model_bytes(&dir, format).iter().map(Vec::len).sum();
        println!(
            "{format:?}: write {write_s:.2} s, read {read_s:.2} s, {:.1} MB",
            bytes as f64 / 1e6
        );
        assert_eq!(back.points3d.len(), rec.points3d.len());
    }
}

/// Every command that writes checks where before reading its inputs: an
/// output under a file, or in a folder that takes no new entries (`/proc`,
/// even for root), is an error naming it, with a non-zero exit, although the
/// inputs do not exist either (their errors would come first otherwise).
#[test]
fn every_command_refuses_an_unwritable_output_before_its_inputs() {
    let root = tempfile::tempdir().unwrap();
    let file = root.path().join("afile");
    fs::write(&file, "x").unwrap();
    let missing = root.path().join("missing");
    let m = missing.to_str().unwrap();
    let refused = |args: &[&str], out: &Path, says: &str| {
        let out = std::process::Command::new(common::bin())
            .args(args)
            .arg(out)
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?}");
        assert!(stderr.contains(says), "{args:?}: {stderr}");
    };
    // Each command's arguments but the output, which comes last.
    let depth = [
        "depth", "--lidar", m, "--model", m, "--image", "a", "--output",
    ];
    let colour = [
        "colour-map",
        "--lidar",
        m,
        "--model",
        m,
        "--image-path",
        m,
        "--output",
    ];
    let prepare = ["prepare-map", "--input", m, "--output"];
    for place in [file.clone(), PathBuf::from("/proc/colmap-lidar-test")] {
        let (dir, png, ply) = (
            place.join("out"),
            place.join("out.png"),
            place.join("out.ply"),
        );
        let expected = if place == file {
            "afile is a file, not a folder"
        } else {
            "takes no new entries"
        };
        for (args, out) in [
            (
                &["map", "--database", m, "--lidar", m, "--output"][..],
                &dir,
            ),
            (&["merge", "--input", m, "--input", m, "--output"], &dir),
            (&["synth", "--scene", "room", "--output"], &dir),
            (&prepare, &ply),
            (&depth, &png),
            (&colour, &ply),
            (&["plot", m, "--output"], &dir),
            (
                &["depth-maps", "--lidar", m, "--model", m, "--output"],
                &dir,
            ),
            (
                &["evaluate", "--model", m, "--reference", m, "--json"],
                &png,
            ),
            (&["bench-map", "generate", "--output"], &ply),
        ] {
            refused(args, out, expected);
        }
    }
    // A file named for another format than the one written: refused too.
    let r = root.path();
    refused(
        &prepare,
        &r.join("map.pcd"),
        "give it a name ending in .ply",
    );
    refused(
        &depth,
        &r.join("depth.jpg"),
        "give it a name ending in .png",
    );
    refused(&colour, &r.join("map.txt"), "give it a name ending in .ply");
    assert_eq!(fs::read_to_string(&file).unwrap(), "x");
    assert_eq!(fs::read_dir(root.path()).unwrap().count(), 1);
}
