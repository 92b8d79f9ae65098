//! Models of the same LiDAR map in one model: `map` outputs share the map's
//! frame and scale, so images that no verified match links (groups of
//! photos mapped each from its own initial pose) go into one model as they
//! are, with no alignment and nothing moved. Used by `colmap-lidar merge`
//! and by `map` with one initial image per group.
use std::collections::{BTreeMap, BTreeSet};

use super::{CameraId, ImageId, Point3DId, Reconstruction, TrackElement};

/// Why models could not be merged.
#[derive(Debug, thiserror::Error)]
pub enum MergeError {
    #[error("{0} has no registered image: nothing to merge")]
    Empty(String),
    #[error("{model}: image {image} is in it twice (a model has one pose per image)")]
    ImageTwice { model: String, image: String },
    #[error("image {image} is in both {first} and {second}: merge models of different images (one pose per image)")]
    ImageInTwo {
        image: String,
        first: String,
        second: String,
    },
    #[error("{model}: camera {camera} of its images is missing")]
    MissingCamera { model: String, camera: u32 },
    #[error("no {0} id left to give")]
    NoIdLeft(&'static str),
}

/// What [`merge_models`] did besides the union.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct MergeSummary {
    /// Cameras of a later model given a new id because the same id held
    /// other intrinsics (model index, old id, new id).
    pub cameras_renumbered: Vec<(usize, CameraId, CameraId)>,
    /// Images of a later model given a new id because the id was taken
    /// (model index, old id, new id).
    pub images_renumbered: Vec<(usize, ImageId, ImageId)>,
}

/// The registered images of `models` (and the points they see) in one
/// model. Images are matched by name: one name in two models is an error
/// (which pose would it keep?). Ids are kept where they are free: a camera
/// id that a later model uses for other intrinsics, or an image id taken by
/// another image, gets the next free id. 3D points are numbered from 1 in
/// the models' order.
///
/// Each model comes with a label for the errors (its folder, or the run
/// that made it).
pub fn merge_models(
    models: &[(String, Reconstruction)],
) -> Result<(Reconstruction, MergeSummary), MergeError> {
    let mut out = Reconstruction::default();
    let mut summary = MergeSummary::default();
    let mut names: BTreeMap<String, &str> = BTreeMap::new();
    let mut next_point = 1u64;
    for (k, (label, model)) in models.iter().enumerate() {
        if model.num_registered_images() == 0 {
            return Err(MergeError::Empty(label.clone()));
        }
        let mut own: BTreeSet<&str> = BTreeSet::new();
        for img in model.registered_images() {
            if !own.insert(img.name.as_str()) {
                return Err(MergeError::ImageTwice {
                    model: label.clone(),
                    image: img.name.clone(),
                });
            }
            if let Some(first) = names.insert(img.name.clone(), label) {
                return Err(MergeError::ImageInTwo {
                    image: img.name.clone(),
                    first: first.to_owned(),
                    second: label.clone(),
                });
            }
        }
        let mut camera_ids: BTreeMap<CameraId, CameraId> = BTreeMap::new();
        let used: BTreeSet<CameraId> = model.registered_images().map(|img| img.camera_id).collect();
        // A new id is free in the merged model and not one of this model's
        // own, which keep theirs where they can.
        let mut cameras_taken: BTreeSet<u32> =
            out.cameras.keys().chain(&used).map(|c| c.0).collect();
        for id in used {
            let camera = model.cameras.get(&id).ok_or(MergeError::MissingCamera {
                model: label.clone(),
                camera: id.0,
            })?;
            let new_id = match out.cameras.get(&id) {
                None => id,
                Some(c) if c == camera => id,
                Some(_) => {
                    let free = CameraId(
                        next_free(&mut cameras_taken).ok_or(MergeError::NoIdLeft("camera"))?,
                    );
                    summary.cameras_renumbered.push((k, id, free));
                    free
                }
            };
            let mut camera = camera.clone();
            camera.id = new_id;
            out.cameras.insert(new_id, camera);
            camera_ids.insert(id, new_id);
        }
        let mut image_ids: BTreeMap<ImageId, ImageId> = BTreeMap::new();
        let mut images_taken: BTreeSet<u32> = out
            .images
            .keys()
            .copied()
            .chain(model.registered_images().map(|img| img.id))
            .map(|i| i.0)
            .collect();
        for img in model.registered_images() {
            let new_id = if out.images.contains_key(&img.id) {
                let free =
                    ImageId(next_free(&mut images_taken).ok_or(MergeError::NoIdLeft("image"))?);
                summary.images_renumbered.push((k, img.id, free));
                free
            } else {
                img.id
            };
            image_ids.insert(img.id, new_id);
        }
        let mut point_ids: BTreeMap<Point3DId, Point3DId> = BTreeMap::new();
        for (&id, point) in &model.points3d {
            let track: Vec<TrackElement> = point
                .track
                .iter()
                .filter_map(|e| {
                    Some(TrackElement {
                        image_id: *image_ids.get(&e.image_id)?,
                        point2d_idx: e.point2d_idx,
                    })
                })
                .collect();
            if track.is_empty() {
                continue;
            }
            let new_id = Point3DId(next_point);
            next_point += 1;
            let mut point = point.clone();
            point.track = track;
            out.points3d.insert(new_id, point);
            point_ids.insert(id, new_id);
        }
        for img in model.registered_images() {
            let mut img = img.clone();
            img.id = image_ids[&img.id];
            img.camera_id = camera_ids[&img.camera_id];
            for p in &mut img.points2d {
                p.point3d_id = p.point3d_id.and_then(|id| point_ids.get(&id).copied());
            }
            out.images.insert(img.id, img);
        }
    }
    Ok((out, summary))
}

/// The smallest id above every id in `taken`, which it joins (`None` past
/// `u32::MAX`).
fn next_free(taken: &mut BTreeSet<u32>) -> Option<u32> {
    let id = taken.last().map_or(Some(1), |&max| max.checked_add(1))?;
    taken.insert(id);
    Some(id)
}
