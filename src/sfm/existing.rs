//! A model to extend: an earlier model of the same database in the map's
//! frame (`map --input-model`), matched to the database by image name, as
//! COLMAP's mapper does with `--input_path`. New photos added to the database
//! since (feature extraction and matching add them to the same file) are then
//! registered into it instead of mapping everything again.
use std::collections::{BTreeMap, BTreeSet};

use nalgebra::Vector3;
use thiserror::Error;

use crate::io::database::DatabaseSnapshot;
use crate::scene::{CameraId, ImageId, Reconstruction, Rigid3, TrackElement};

/// How far a model's 2D point may be from the database's keypoint of the
/// same index, pixels: COLMAP stores keypoints as 32-bit floats and writes
/// them with at least six significant digits; a model of another database
/// (other features) is off by pixels.
pub const KEYPOINT_TOLERANCE_PX: f64 = 0.05;

/// An earlier model in database ids.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ExistingModel {
    /// The model's intrinsics, by database camera id.
    pub camera_params: BTreeMap<CameraId, Vec<f64>>,
    /// Registered images and their poses, by database image id.
    pub poses: BTreeMap<ImageId, Rigid3>,
    /// 3D points with their tracks in database ids (two observations or more).
    pub points: Vec<(Vector3<f64>, Vec<TrackElement>)>,
    /// Whether the model's images stay at their poses in every solve
    /// (`--fix-existing-images`); otherwise the map holds the model and they
    /// are refined with the new ones.
    pub hold: bool,
}

impl ExistingModel {
    pub fn image_ids(&self) -> BTreeSet<ImageId> {
        self.poses.keys().copied().collect()
    }
}

#[derive(Debug, Error, PartialEq)]
pub enum ExistingModelError {
    #[error("it has no registered image")]
    Empty,
    #[error("its image {0:?} is not in the database")]
    UnknownImage(String),
    #[error("its image {0:?} is in the database twice")]
    DuplicateName(String),
    #[error("it holds image {0:?} twice")]
    DuplicateImage(String),
    #[error("its image {name:?} has camera {camera} which it does not define")]
    MissingCamera { name: String, camera: u32 },
    #[error(
        "its image {name:?} has a {model} camera of {width}x{height} where the database has a {db_model} camera of {db_width}x{db_height}"
    )]
    CameraMismatch {
        name: String,
        model: String,
        width: u32,
        height: u32,
        db_model: String,
        db_width: u32,
        db_height: u32,
    },
    #[error(
        "two of its cameras, for images sharing database camera {0}, have different parameters"
    )]
    CameraConflict(u32),
    #[error("its image {name:?} has {model} 2D points where the database has {db} keypoints: the model was made from other features")]
    KeypointCount {
        name: String,
        model: usize,
        db: usize,
    },
    #[error("2D point {index} of its image {name:?} is at ({x:.2}, {y:.2}) where the database's keypoint is at ({db_x:.2}, {db_y:.2}): the model was made from other features")]
    KeypointMoved {
        name: String,
        index: usize,
        x: f64,
        y: f64,
        db_x: f64,
        db_y: f64,
    },
    #[error("its 3D point {point} is observed by 2D point {index} of image id {image}, which the model does not have")]
    BadTrack { point: u64, image: u32, index: u32 },
}

/// Matches `model` to `db` by image name: its poses, intrinsics and tracks in
/// the database's ids. Every registered image must be in the database with a
/// camera of the same model and size and the same keypoints (those of its 2D
/// points with a 3D point, to [`KEYPOINT_TOLERANCE_PX`]). Points observed by
/// fewer than two images are left out.
pub fn match_to_database(
    model: &Reconstruction,
    db: &DatabaseSnapshot,
    hold: bool,
) -> Result<ExistingModel, ExistingModelError> {
    let mut by_name: BTreeMap<&str, ImageId> = BTreeMap::new();
    for img in db.images.values() {
        if by_name.insert(img.name.as_str(), img.id).is_some() {
            return Err(ExistingModelError::DuplicateName(img.name.clone()));
        }
    }
    let mut out = ExistingModel {
        hold,
        ..Default::default()
    };
    // The model's image id -> the database's.
    let mut ids: BTreeMap<ImageId, ImageId> = BTreeMap::new();
    for img in model.registered_images() {
        let Some(&db_id) = by_name.get(img.name.as_str()) else {
            return Err(ExistingModelError::UnknownImage(img.name.clone()));
        };
        if out.poses.contains_key(&db_id) {
            return Err(ExistingModelError::DuplicateImage(img.name.clone()));
        }
        let db_image = &db.images[&db_id];
        let camera =
            model
                .cameras
                .get(&img.camera_id)
                .ok_or_else(|| ExistingModelError::MissingCamera {
                    name: img.name.clone(),
                    camera: img.camera_id.0,
                })?;
        // The database reader checks every image's camera exists.
        let db_camera = &db.cameras[&db_image.camera_id];
        if camera.model != db_camera.model
            || camera.width != db_camera.width
            || camera.height != db_camera.height
        {
            return Err(ExistingModelError::CameraMismatch {
                name: img.name.clone(),
                model: camera.model.name().to_owned(),
                width: camera.width,
                height: camera.height,
                db_model: db_camera.model.name().to_owned(),
                db_width: db_camera.width,
                db_height: db_camera.height,
            });
        }
        match out.camera_params.get(&db_camera.id) {
            Some(params) if *params != camera.params => {
                return Err(ExistingModelError::CameraConflict(db_camera.id.0));
            }
            _ => {
                out.camera_params
                    .insert(db_camera.id, camera.params.clone());
            }
        }
        let keypoints = db.keypoints.get(&db_id).map_or(&[][..], Vec::as_slice);
        if img.points2d.len() != keypoints.len() {
            return Err(ExistingModelError::KeypointCount {
                name: img.name.clone(),
                model: img.points2d.len(),
                db: keypoints.len(),
            });
        }
        for (index, (p, k)) in img.points2d.iter().zip(keypoints).enumerate() {
            if p.point3d_id.is_some() && !((p.xy - k).norm() <= KEYPOINT_TOLERANCE_PX) {
                return Err(ExistingModelError::KeypointMoved {
                    name: img.name.clone(),
                    index,
                    x: p.xy.x,
                    y: p.xy.y,
                    db_x: k.x,
                    db_y: k.y,
                });
            }
        }
        let pose = img.cam_from_world.expect("a registered image has a pose");
        out.poses.insert(db_id, pose);
        ids.insert(img.id, db_id);
    }
    if out.poses.is_empty() {
        return Err(ExistingModelError::Empty);
    }
    for (point_id, point) in &model.points3d {
        let mut track = Vec::with_capacity(point.track.len());
        for e in &point.track {
            let in_range = model
                .images
                .get(&e.image_id)
                .is_some_and(|i| (e.point2d_idx as usize) < i.points2d.len());
            let Some(&db_id) = ids.get(&e.image_id).filter(|_| in_range) else {
                return Err(ExistingModelError::BadTrack {
                    point: point_id.0,
                    image: e.image_id.0,
                    index: e.point2d_idx,
                });
            };
            track.push(TrackElement {
                image_id: db_id,
                point2d_idx: e.point2d_idx,
            });
        }
        // One observation per image, as the mapper keeps them.
        track.sort();
        track.dedup_by_key(|e| e.image_id);
        if track.len() >= 2 {
            out.points.push((point.xyz, track));
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::database::DbImage;
    use crate::scene::{Camera, CameraModel, Image, Point2D, Point3D, Point3DId};
    use nalgebra::{UnitQuaternion, Vector2};

    fn camera(id: u32, f: f64) -> Camera {
        Camera {
            id: CameraId(id),
            model: CameraModel::SimpleRadial,
            width: 640,
            height: 480,
            params: vec![f, 320.0, 240.0, 0.0],
        }
    }

    /// A database of three images (ids 1, 2, 3; camera 1) with four keypoints each.
    fn database() -> DatabaseSnapshot {
        let mut db = DatabaseSnapshot::default();
        db.cameras.insert(CameraId(1), camera(1, 500.0));
        for (id, name) in [(1, "a.jpg"), (2, "b.jpg"), (3, "c.jpg")] {
            db.images.insert(
                ImageId(id),
                DbImage {
                    id: ImageId(id),
                    name: name.to_owned(),
                    camera_id: CameraId(1),
                },
            );
            let k = (0..4)
                .map(|i| Vector2::new(10.0 * i as f64 + id as f64, 5.0))
                .collect();
            db.keypoints.insert(ImageId(id), k);
        }
        db
    }

    /// A model of images b and c under other ids (7, 9) and camera 4, with
    /// point 1 seen by both (keypoints 0 and 2), point 2 by b only.
    fn model(db: &DatabaseSnapshot) -> Reconstruction {
        let mut rec = Reconstruction::default();
        rec.cameras.insert(CameraId(4), camera(4, 510.0));
        for (model_id, db_id, name) in [(7, 2, "b.jpg"), (9, 3, "c.jpg")] {
            let points2d = db.keypoints[&ImageId(db_id)]
                .iter()
                .enumerate()
                .map(|(i, xy)| Point2D {
                    xy: xy + Vector2::new(0.01, 0.0),
                    point3d_id: match (model_id, i) {
                        (7, 0) | (9, 2) => Some(Point3DId(1)),
                        (7, 3) => Some(Point3DId(2)),
                        _ => None,
                    },
                })
                .collect();
            rec.images.insert(
                ImageId(model_id),
                Image {
                    id: ImageId(model_id),
                    name: name.to_owned(),
                    camera_id: CameraId(4),
                    cam_from_world: Some(Rigid3::new(
                        UnitQuaternion::identity(),
                        Vector3::new(model_id as f64, 0.0, 0.0),
                    )),
                    points2d,
                },
            );
        }
        let point = |xyz: [f64; 3], track: &[(u32, u32)]| Point3D {
            xyz: Vector3::from(xyz),
            color: [0, 0, 0],
            error: 0.0,
            track: track
                .iter()
                .map(|&(i, k)| TrackElement {
                    image_id: ImageId(i),
                    point2d_idx: k,
                })
                .collect(),
        };
        rec.points3d
            .insert(Point3DId(1), point([1.0, 2.0, 3.0], &[(7, 0), (9, 2)]));
        rec.points3d
            .insert(Point3DId(2), point([4.0, 5.0, 6.0], &[(7, 3)]));
        rec
    }

    #[test]
    fn a_model_is_matched_to_the_database_by_name() {
        let db = database();
        let out = match_to_database(&model(&db), &db, true).unwrap();
        assert!(out.hold);
        assert_eq!(out.image_ids(), BTreeSet::from([ImageId(2), ImageId(3)]));
        assert_eq!(out.poses[&ImageId(2)].translation.x, 7.0);
        assert_eq!(out.poses[&ImageId(3)].translation.x, 9.0);
        // The model's intrinsics, under the database's camera id.
        assert_eq!(
            out.camera_params,
            BTreeMap::from([(CameraId(1), vec![510.0, 320.0, 240.0, 0.0])])
        );
        // Point 2 has one observation: left out.
        let e = |i, k| TrackElement {
            image_id: ImageId(i),
            point2d_idx: k,
        };
        assert_eq!(
            out.points,
            vec![(Vector3::new(1.0, 2.0, 3.0), vec![e(2, 0), e(3, 2)])]
        );
    }

    #[test]
    fn a_model_of_other_images_or_features_is_refused() {
        let db = database();
        let mut m = model(&db);
        m.images.get_mut(&ImageId(9)).unwrap().name = "z.jpg".into();
        assert_eq!(
            match_to_database(&m, &db, false),
            Err(ExistingModelError::UnknownImage("z.jpg".into()))
        );

        let mut m = model(&db);
        m.images.get_mut(&ImageId(7)).unwrap().points2d.pop();
        assert_eq!(
            match_to_database(&m, &db, false),
            Err(ExistingModelError::KeypointCount {
                name: "b.jpg".into(),
                model: 3,
                db: 4
            })
        );

        // A moved keypoint counts only where it observes a 3D point.
        let mut m = model(&db);
        m.images.get_mut(&ImageId(9)).unwrap().points2d[1].xy.x += 3.0;
        assert!(match_to_database(&m, &db, false).is_ok());
        m.images.get_mut(&ImageId(9)).unwrap().points2d[2].xy.x += 0.1;
        let err = match_to_database(&m, &db, false).unwrap_err();
        assert!(
            matches!(err, ExistingModelError::KeypointMoved { index: 2, .. }),
            "{err}"
        );

        let mut m = model(&db);
        m.cameras.get_mut(&CameraId(4)).unwrap().width = 641;
        let err = match_to_database(&m, &db, false).unwrap_err();
        assert!(err.to_string().contains("641x480"), "{err}");
        assert!(err.to_string().contains("640x480"), "{err}");

        // Two model cameras for one database camera must agree.
        let mut m = model(&db);
        m.cameras.insert(CameraId(5), camera(5, 520.0));
        m.images.get_mut(&ImageId(9)).unwrap().camera_id = CameraId(5);
        assert_eq!(
            match_to_database(&m, &db, false),
            Err(ExistingModelError::CameraConflict(1))
        );

        let mut m = model(&db);
        m.points3d.get_mut(&Point3DId(1)).unwrap().track[1].point2d_idx = 4;
        assert_eq!(
            match_to_database(&m, &db, false),
            Err(ExistingModelError::BadTrack {
                point: 1,
                image: 9,
                index: 4
            })
        );

        let mut m = model(&db);
        m.images.get_mut(&ImageId(9)).unwrap().name = "b.jpg".into();
        assert_eq!(
            match_to_database(&m, &db, false),
            Err(ExistingModelError::DuplicateImage("b.jpg".into()))
        );

        let mut m = model(&db);
        for img in m.images.values_mut() {
            img.cam_from_world = None;
        }
        assert_eq!(
            match_to_database(&m, &db, false),
            Err(ExistingModelError::Empty)
        );
    }
}
