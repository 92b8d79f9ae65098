//! Reads the image poses (name -> `cam_from_world`) of a COLMAP model folder,
//! text or binary.
use std::collections::BTreeMap;
use std::path::Path;

use super::EvalError;
use crate::scene::{Reconstruction, Rigid3};

/// Poses by image name, read with [`crate::io::model::read_model`] (text or
/// binary). Unregistered images are left out.
pub fn load_poses(dir: &Path) -> Result<BTreeMap<String, Rigid3>, EvalError> {
    poses_of(&load_model(dir)?, dir)
}

/// The model in `dir` (text or binary), its errors naming the folder.
pub fn load_model(dir: &Path) -> Result<Reconstruction, EvalError> {
    crate::io::model::read_model(dir).map_err(|e| EvalError::Model {
        path: dir.to_path_buf(),
        message: e.to_string(),
    })
}

/// The registered images' poses of `rec` (read from `dir`) by name; an
/// error when a name appears twice.
pub fn poses_of(rec: &Reconstruction, dir: &Path) -> Result<BTreeMap<String, Rigid3>, EvalError> {
    let mut out = BTreeMap::new();
    for image in rec.images.values() {
        if let Some(pose) = image.cam_from_world {
            insert(&mut out, dir, image.name.clone(), pose)?;
        }
    }
    Ok(out)
}

fn bad(path: &Path, message: String) -> EvalError {
    EvalError::Model {
        path: path.to_path_buf(),
        message,
    }
}

fn insert(
    out: &mut BTreeMap<String, Rigid3>,
    path: &Path,
    name: String,
    pose: Rigid3,
) -> Result<(), EvalError> {
    if out.insert(name.clone(), pose).is_some() {
        return Err(bad(path, format!("image name {name:?} appears twice")));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::model::{write_model, ModelFormat};
    use crate::scene::{Camera, CameraId, CameraModel, Image, ImageId};

    #[test]
    fn poses_of_text_and_binary_models() {
        let mut rec = Reconstruction::default();
        rec.cameras.insert(
            CameraId(1),
            Camera {
                id: CameraId(1),
                model: CameraModel::SimplePinhole,
                width: 64,
                height: 48,
                params: vec![50.0, 32.0, 24.0],
            },
        );
        let poses = [
            (
                "a.jpg",
                Some(Rigid3::from_colmap([0.9, 0.1, -0.2, 0.3], [1.0, 2.0, 3.0])),
            ),
            (
                "c.jpg",
                Some(Rigid3::from_colmap(
                    [1.0, 0.0, 0.0, 0.0],
                    [-4.0, 5.5, 4.4e6],
                )),
            ),
            ("unregistered.jpg", None),
        ];
        for (i, (name, pose)) in poses.iter().enumerate() {
            let id = ImageId(i as u32 + 1);
            rec.images.insert(
                id,
                Image {
                    id,
                    name: name.to_string(),
                    camera_id: CameraId(1),
                    cam_from_world: *pose,
                    points2d: vec![],
                },
            );
        }
        let dir = tempfile::tempdir().unwrap();
        for format in [ModelFormat::Text, ModelFormat::Binary] {
            let model = dir.path().join(format!("{format:?}"));
            write_model(&model, &rec, format).unwrap();
            let got = load_poses(&model).unwrap();
            assert_eq!(got.len(), 2, "{format:?}");
            for (name, pose) in &poses[..2] {
                let (p, g) = (pose.unwrap(), got[*name]);
                assert!((g.translation - p.translation).norm() < 1e-9);
                assert!(g.rotation.angle_to(&p.rotation) < 1e-12);
            }
        }
        assert!(load_poses(&dir.path().join("missing")).is_err());
    }
}
