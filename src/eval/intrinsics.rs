//! A model's focal lengths against the reference's, camera by camera: the
//! reference's cameras are found through the images both models have (by
//! name), so the two may number their cameras differently.
use std::collections::BTreeMap;

use serde::Serialize;

use crate::scene::Reconstruction;

/// One model camera's focal length against the reference's for the same
/// images.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct FocalError {
    pub camera_id: u32,
    /// The model's registered images with this camera that the reference
    /// has (by name).
    pub num_images: usize,
    /// Mean focal length (fx and fy averaged where the model has both), px.
    pub focal_px: f64,
    /// The reference's for the same images (its cameras' mean focal
    /// lengths averaged over them), px.
    pub reference_focal_px: f64,
    /// `focal_px / reference_focal_px - 1`.
    pub relative_error: f64,
    /// The one-sigma uncertainty the model reported for it (`map`'s
    /// `report.json` → `intrinsics` → `focal_sigma_px`, where that
    /// record's final focal length is this one), px.
    pub sigma_px: Option<f64>,
    /// The same, cluster-robust (`clustered_focal_sigma_px`).
    pub clustered_sigma_px: Option<f64>,
}

/// Per camera of `model` used by a registered image that `reference` has
/// registered too, its focal length against the reference's.
pub fn focal_errors(model: &Reconstruction, reference: &Reconstruction) -> Vec<FocalError> {
    let reference_focal: BTreeMap<&str, f64> = reference
        .registered_images()
        .filter_map(|img| {
            let camera = reference.cameras.get(&img.camera_id)?;
            Some((img.name.as_str(), camera.mean_focal_length()))
        })
        .collect();
    // Per model camera: the reference's focal lengths of its images.
    let mut matched: BTreeMap<u32, Vec<f64>> = BTreeMap::new();
    for img in model.registered_images() {
        if let Some(&f) = reference_focal.get(img.name.as_str()) {
            matched.entry(img.camera_id.0).or_default().push(f);
        }
    }
    matched
        .into_iter()
        .filter_map(|(id, refs)| {
            let camera = model.cameras.get(&crate::scene::CameraId(id))?;
            let focal_px = camera.mean_focal_length();
            let reference_focal_px = refs.iter().sum::<f64>() / refs.len() as f64;
            Some(FocalError {
                camera_id: id,
                num_images: refs.len(),
                focal_px,
                reference_focal_px,
                relative_error: focal_px / reference_focal_px - 1.0,
                sigma_px: None,
                clustered_sigma_px: None,
            })
        })
        .collect()
}

/// The table's lines for `errors`: the focal length against the
/// reference's, and over the model's own sigmas where it gave them.
pub fn focal_table(errors: &[FocalError]) -> String {
    let mut s = String::new();
    for e in errors {
        let over = |sigma: Option<f64>, what: &str| {
            sigma
                .filter(|v| v.is_finite() && *v > 0.0)
                .map(|v| format!(", {:.2} {what}", (e.focal_px - e.reference_focal_px) / v))
                .unwrap_or_default()
        };
        s += &format!(
            "focal length (px)    {:.3} against {:.3} ({:+.4} %{}{}; camera {}, {} image{})\n",
            e.focal_px,
            e.reference_focal_px,
            100.0 * e.relative_error,
            over(e.sigma_px, "own sigmas"),
            over(e.clustered_sigma_px, "clustered sigmas"),
            e.camera_id,
            e.num_images,
            if e.num_images == 1 { "" } else { "s" }
        );
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{Camera, CameraId, CameraModel, Image, ImageId, Rigid3};

    fn camera(id: u32, model: CameraModel, params: Vec<f64>) -> (CameraId, Camera) {
        let id = CameraId(id);
        let camera = Camera {
            id,
            model,
            width: 640,
            height: 480,
            params,
        };
        (id, camera)
    }

    fn image(id: u32, name: &str, camera: u32, registered: bool) -> (ImageId, Image) {
        let id = ImageId(id);
        let image = Image {
            id,
            name: name.into(),
            camera_id: CameraId(camera),
            cam_from_world: registered.then(Rigid3::identity),
            points2d: vec![],
        };
        (id, image)
    }

    /// Two model cameras (one with fx and fy) against a reference that
    /// numbers its cameras otherwise; images the reference lacks, or that
    /// either side did not register, do not count.
    #[test]
    fn focal_lengths_are_compared_through_the_images() {
        let model = Reconstruction {
            cameras: [
                camera(1, CameraModel::SimpleRadial, vec![515.0, 320.0, 240.0, 0.0]),
                camera(2, CameraModel::Pinhole, vec![600.0, 604.0, 320.0, 240.0]),
                camera(3, CameraModel::SimplePinhole, vec![700.0, 320.0, 240.0]),
            ]
            .into(),
            images: [
                image(1, "a.jpg", 1, true),
                image(2, "b.jpg", 1, true),
                image(3, "c.jpg", 2, true),
                image(4, "d.jpg", 1, false),
                image(5, "new.jpg", 3, true),
                image(6, "e.jpg", 1, true),
            ]
            .into(),
            points3d: BTreeMap::new(),
        };
        let reference = Reconstruction {
            cameras: [
                camera(7, CameraModel::SimplePinhole, vec![512.0, 320.0, 240.0]),
                camera(8, CameraModel::SimplePinhole, vec![600.0, 320.0, 240.0]),
            ]
            .into(),
            images: [
                image(1, "a.jpg", 7, true),
                image(2, "b.jpg", 7, true),
                image(3, "c.jpg", 8, true),
                image(4, "d.jpg", 7, true),
                image(5, "e.jpg", 7, false),
            ]
            .into(),
            points3d: BTreeMap::new(),
        };
        let mut errors = focal_errors(&model, &reference);
        assert_eq!(errors.len(), 2);
        assert_eq!(
            (
                errors[0].camera_id,
                errors[0].num_images,
                errors[0].focal_px
            ),
            (1, 2, 515.0)
        );
        assert_eq!(errors[0].reference_focal_px, 512.0);
        assert!((errors[0].relative_error - 3.0 / 512.0).abs() < 1e-15);
        assert_eq!(
            (
                errors[1].camera_id,
                errors[1].num_images,
                errors[1].focal_px
            ),
            (2, 1, 602.0)
        );
        assert!((errors[1].relative_error - 2.0 / 600.0).abs() < 1e-15);
        errors[0].clustered_sigma_px = Some(1.5);
        let table = focal_table(&errors);
        assert!(
            table.contains(
                "focal length (px)    515.000 against 512.000 (+0.5859 %, 2.00 clustered sigmas; camera 1, 2 images)"
            ),
            "{table}"
        );
        assert!(
            table.contains("602.000 against 600.000 (+0.3333 %; camera 2, 1 image)"),
            "{table}"
        );
    }
}
