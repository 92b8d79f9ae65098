//! Where the model's tracks lie relative to the map's surfaces when they are
//! triangulated at the reference poses: how well the images themselves agree
//! with the map, apart from any error of the solve.
//!
//! Every 3D point of the model with at least two observations in reference
//! images is triangulated again at the reference poses (the model's
//! intrinsics; DLT, then Gauss-Newton on the reprojection error). Its plane
//! in the map is the one the mapper would use at the smallest search radius
//! ([`NearestNeighbourAssociator::plane_near`]: a map point's normal, the
//! offset averaged over the map around it), the normal turned toward the
//! point's cameras. The signed distance is positive toward the cameras. The
//! model's own points are measured the same way. Both are summarised by the
//! mean |cos| of the angle between the normal and the viewing rays (1 seen
//! head-on, 0 edge-on), since a feature's position depends on how obliquely
//! its surface was seen.
//!
//! With exact ground truth this shows what the poses cannot beat: on the
//! synthetic corridor (seed 0, clean map) the features of the floor and the
//! ceiling, seen at |cos| 0.3-0.5, triangulate 0.4 mm inside the corridor
//! at the true poses, and at |cos| 0.2-0.3 0.6 mm, while walls seen at
//! |cos| above 0.5 lie on the map within 0.05 mm.
use std::collections::BTreeMap;

use nalgebra::{Matrix3, Vector2, Vector3};
use serde::Serialize;

use super::Stats;
use crate::estimators::triangulation::triangulate_dlt;
use crate::scene::{Camera, Reconstruction, Rigid3};
use crate::sfm::associate::NearestNeighbourAssociator;

/// Upper bounds of the |cos| classes (the first starts at 0).
pub const COS_BOUNDS: [f64; 5] = [0.2, 0.3, 0.5, 0.7, 1.0];

/// Points whose plane lies farther than this are not counted (not on a
/// mapped surface, or a wrong plane), metres.
pub const MAX_DISTANCE_M: f64 = 0.02;

/// Signed distances of the points of one |cos| class.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CosClass {
    pub min_cos: f64,
    pub max_cos: f64,
    /// Points triangulated at the reference poses.
    pub reference_count: usize,
    /// Median and mean signed distance to the map's plane (positive toward
    /// the cameras), metres.
    pub reference_median_m: Option<f64>,
    pub reference_mean_m: Option<f64>,
    /// The model's own points.
    pub model_count: usize,
    pub model_median_m: Option<f64>,
    pub model_mean_m: Option<f64>,
}

/// Result of [`map_agreement`].
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct MapAgreement {
    /// Model points with two or more observations in reference images.
    pub num_points: usize,
    /// ... of which triangulated at the reference poses, in front of them.
    pub num_triangulated: usize,
    pub classes: Vec<CosClass>,
}

/// One point's plane and distances.
struct Measured {
    cos: f64,
    reference_signed_m: Option<f64>,
    model_signed_m: Option<f64>,
}

/// See the module documentation. `reference` maps image names to
/// `cam_from_world`; `planes` gives the map's planes.
pub fn map_agreement(
    model: &Reconstruction,
    reference: &BTreeMap<String, Rigid3>,
    planes: &NearestNeighbourAssociator,
) -> MapAgreement {
    let radius_m = planes.options.min_radius_m;
    let mut num_points = 0;
    let mut num_triangulated = 0;
    let mut measured = Vec::new();
    for point in model.points3d.values() {
        // (camera, reference pose, keypoint) of the observations in reference images.
        let views: Vec<(&Camera, Rigid3, Vector2<f64>)> = point
            .track
            .iter()
            .filter_map(|e| {
                let image = model.images.get(&e.image_id)?;
                let pose = *reference.get(&image.name)?;
                let camera = model.cameras.get(&image.camera_id)?;
                let xy = image.points2d.get(e.point2d_idx as usize)?.xy;
                Some((camera, pose, xy))
            })
            .collect();
        if views.len() < 2 {
            continue;
        }
        num_points += 1;
        let triangulated = triangulate_at(&views);
        num_triangulated += usize::from(triangulated.is_some());
        // The plane: found from the reference point when there is one (the
        // model's own point may sit off by the model's error).
        let at = triangulated.unwrap_or(point.xyz);
        let Some((normal, offset_m)) = planes.plane_near(&at, radius_m) else {
            continue;
        };
        let centres: Vector3<f64> = views.iter().map(|(_, p, _)| p.camera_center()).sum();
        let centre = centres / views.len() as f64;
        let (normal, offset_m) = if normal.dot(&(centre - at)) < 0.0 {
            (-normal, -offset_m)
        } else {
            (normal, offset_m)
        };
        let cosines: Vec<f64> = views
            .iter()
            .filter_map(|(_, p, _)| (at - p.camera_center()).try_normalize(1e-12))
            .map(|ray| ray.dot(&normal).abs())
            .collect();
        if cosines.is_empty() {
            continue;
        }
        let cos = cosines.iter().sum::<f64>() / cosines.len() as f64;
        let signed = |x: &Vector3<f64>| {
            let d = normal.dot(x) - offset_m;
            (d.abs() <= MAX_DISTANCE_M).then_some(d)
        };
        measured.push(Measured {
            cos,
            reference_signed_m: triangulated.as_ref().and_then(signed),
            model_signed_m: signed(&point.xyz),
        });
    }
    let mut lower = 0.0;
    let classes = COS_BOUNDS
        .iter()
        .map(|&upper| {
            let inside: Vec<&Measured> = measured
                .iter()
                .filter(|m| m.cos >= lower && (m.cos < upper || upper >= 1.0))
                .collect();
            let reference: Vec<f64> = inside.iter().filter_map(|m| m.reference_signed_m).collect();
            let own: Vec<f64> = inside.iter().filter_map(|m| m.model_signed_m).collect();
            let class = CosClass {
                min_cos: lower,
                max_cos: upper,
                reference_count: reference.len(),
                reference_median_m: Stats::of(&reference).map(|s| s.median),
                reference_mean_m: mean(&reference),
                model_count: own.len(),
                model_median_m: Stats::of(&own).map(|s| s.median),
                model_mean_m: mean(&own),
            };
            lower = upper;
            class
        })
        .collect();
    MapAgreement {
        num_points,
        num_triangulated,
        classes,
    }
}

fn mean(values: &[f64]) -> Option<f64> {
    (!values.is_empty()).then(|| values.iter().sum::<f64>() / values.len() as f64)
}

/// The point seen at `views` (two or more): DLT from the viewing rays, then
/// Gauss-Newton on the reprojection error (numerical derivatives). `None`
/// when a ray is missing, the rays are parallel, or the point falls behind a
/// camera.
pub fn triangulate_at(views: &[(&Camera, Rigid3, Vector2<f64>)]) -> Option<Vector3<f64>> {
    let rays: Vec<(Rigid3, Vector3<f64>)> = views
        .iter()
        .map(|(camera, pose, xy)| Some((*pose, camera.unproject(xy)?)))
        .collect::<Option<_>>()?;
    let mut x = triangulate_dlt(&rays)?;
    let residuals = |x: &Vector3<f64>| -> Option<Vec<f64>> {
        let mut r = Vec::with_capacity(2 * views.len());
        for (camera, pose, xy) in views {
            let in_cam = pose.transform_point(x);
            if in_cam.z <= 0.0 {
                return None;
            }
            let d = camera.project(&in_cam)? - xy;
            r.extend([d.x, d.y]);
        }
        Some(r)
    };
    let norm_sq = |r: &[f64]| r.iter().map(|v| v * v).sum::<f64>();
    let mut r = residuals(&x)?;
    let h = (views[0].1.camera_center() - x).norm() * 1e-7;
    for _ in 0..10 {
        let columns: Vec<Vec<f64>> = (0..3)
            .map(|axis| {
                let mut step = Vector3::zeros();
                step[axis] = h;
                let (plus, minus) = (residuals(&(x + step))?, residuals(&(x - step))?);
                Some(
                    plus.iter()
                        .zip(&minus)
                        .map(|(p, m)| (p - m) / (2.0 * h))
                        .collect(),
                )
            })
            .collect::<Option<_>>()?;
        let mut jtj = Matrix3::zeros();
        let mut jtr = Vector3::zeros();
        for i in 0..r.len() {
            let j = Vector3::new(columns[0][i], columns[1][i], columns[2][i]);
            jtj += j * j.transpose();
            jtr += j * r[i];
        }
        let Some(step) = jtj.try_inverse().map(|inv| -(inv * jtr)) else {
            break;
        };
        let Some(next) = residuals(&(x + step)) else {
            break;
        };
        if norm_sq(&next) >= norm_sq(&r) {
            break;
        }
        x += step;
        r = next;
        if step.norm() < 1e-10 * (1.0 + x.norm()) {
            break;
        }
    }
    Some(x)
}

impl MapAgreement {
    /// Text table: per |cos| class, count and median / mean signed distance (mm).
    pub fn table(&self) -> String {
        let mut out = format!(
            "points vs the map ({} points, {} triangulated at the reference poses;\n\
             signed distance to the map's plane in mm, positive toward the cameras):\n\
             {:<12} {:>8} {:>10} {:>10} {:>8} {:>10} {:>10}\n",
            self.num_points,
            self.num_triangulated,
            "mean |cos|",
            "ref. n",
            "median",
            "mean",
            "model n",
            "median",
            "mean",
        );
        let mm = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{:.3}", v * 1000.0));
        for c in &self.classes {
            out += &format!(
                "{:<12} {:>8} {:>10} {:>10} {:>8} {:>10} {:>10}\n",
                format!("{:.1}-{:.1}", c.min_cos, c.max_cos),
                c.reference_count,
                mm(c.reference_median_m),
                mm(c.reference_mean_m),
                c.model_count,
                mm(c.model_median_m),
                mm(c.model_mean_m),
            );
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::index::MapIndex;
    use crate::map::PointCloud;
    use crate::scene::{CameraId, CameraModel, Image, ImageId, Point2D, Point3D, Point3DId};
    use crate::sfm::options::AssociationOptions;

    fn camera() -> Camera {
        Camera {
            id: CameraId(1),
            model: CameraModel::SimpleRadial,
            width: 640,
            height: 480,
            params: vec![500.0, 320.0, 240.0, -0.05],
        }
    }

    /// A camera at `centre` looking straight down (x right, y toward -y world).
    fn looking_down(centre: Vector3<f64>) -> Rigid3 {
        let down = Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, -1.0));
        Rigid3::from_rotation_matrix(&down, -(down * centre))
    }

    #[test]
    fn triangulation_at_known_poses_is_exact() {
        let cam = camera();
        let x = Vector3::new(0.3, -0.2, 0.05);
        let views: Vec<(&Camera, Rigid3, Vector2<f64>)> = [-0.4, 0.1, 0.5]
            .iter()
            .map(|&cx| {
                let pose = looking_down(Vector3::new(cx, 0.2, 3.0));
                let px = cam.project(&pose.transform_point(&x)).unwrap();
                (&cam, pose, px)
            })
            .collect();
        let got = triangulate_at(&views).unwrap();
        assert!((got - x).norm() < 1e-9, "{got}");
        // One view cannot place a point.
        assert!(triangulate_at(&views[..1]).is_none());
        // Rays whose lines meet 1 m above the cameras (each pixel is that of
        // the point mirrored through the camera's centre): refused.
        let above = Vector3::new(0.3, -0.2, 4.0);
        let behind: Vec<_> = views
            .iter()
            .map(|(c, p, _)| {
                let mirrored = 2.0 * p.camera_center() - above;
                (*c, *p, c.project(&p.transform_point(&mirrored)).unwrap())
            })
            .collect();
        assert!(triangulate_dlt(
            &behind
                .iter()
                .map(|(c, p, xy)| (*p, c.unproject(xy).unwrap()))
                .collect::<Vec<_>>()
        )
        .is_some_and(|x| (x - above).norm() < 1e-6));
        assert!(triangulate_at(&behind).is_none());
    }

    /// A 2 x 2 m floor (z = 0, 2 cm grid, normal up, at a world offset)
    /// under cameras 3 m above it; images 1 and 2 are in the reference,
    /// image 3 is not. Point 1 (images 1, 2) has the keypoints of a point
    /// 1 mm above the floor and the model holds it 0.5 mm below: +1 mm at
    /// the reference poses (toward the cameras), -0.5 mm in the model, seen
    /// head-on. Point 2 (images 1, 3) has one reference view: not counted.
    /// Point 3 (images 1, 2), 5 cm above the floor, is farther than
    /// `MAX_DISTANCE_M`.
    #[test]
    fn distances_to_the_map_by_incidence() {
        let mut points = Vec::new();
        for i in -50..=50 {
            for j in -50..=50 {
                points.push([i as f32 * 0.02, j as f32 * 0.02, 0.0]);
            }
        }
        let floor = Vector3::new(1000.0, 2000.0, 5.0);
        let cloud = PointCloud {
            origin: floor,
            normals: Some(vec![[0.0, 0.0, 1.0]; points.len()]),
            points,
            planarity: None,
        };
        let index = MapIndex::build(&cloud).unwrap();
        let planes = NearestNeighbourAssociator::new(&cloud, &index, AssociationOptions::default());
        // The same floor with its normals pointing down: turned toward the cameras.
        let mut down = cloud.clone();
        down.normals = Some(vec![[0.0, 0.0, -1.0]; down.points.len()]);
        let down_index = MapIndex::build(&down).unwrap();
        let down_planes =
            NearestNeighbourAssociator::new(&down, &down_index, AssociationOptions::default());
        let cam = camera();
        let seen = [
            floor + Vector3::new(0.1, 0.05, 0.001),
            floor + Vector3::new(-0.2, 0.3, 0.0),
            floor + Vector3::new(0.2, -0.1, 0.05),
        ];
        let held = [floor + Vector3::new(0.1, 0.05, -0.0005), seen[1], seen[2]];
        let tracks: [&[u32]; 3] = [&[1, 2], &[1, 3], &[1, 2]];
        let mut model = Reconstruction::default();
        model.cameras.insert(CameraId(1), cam.clone());
        let mut reference = BTreeMap::new();
        for (k, cx) in [0.0, 0.6, 0.3].into_iter().enumerate() {
            let id = ImageId(k as u32 + 1);
            let pose = looking_down(floor + Vector3::new(cx, 0.0, 3.0));
            let name = format!("{}.png", id.0);
            let points2d = seen
                .iter()
                .enumerate()
                .map(|(p, x)| Point2D {
                    xy: cam.project(&pose.transform_point(x)).unwrap(),
                    point3d_id: tracks[p].contains(&id.0).then_some(Point3DId(p as u64 + 1)),
                })
                .collect();
            model.images.insert(
                id,
                Image {
                    id,
                    name: name.clone(),
                    camera_id: CameraId(1),
                    // The model's own poses do not enter the measure.
                    cam_from_world: Some(looking_down(floor + Vector3::new(cx, 0.0, 2.0))),
                    points2d,
                },
            );
            if id.0 != 3 {
                reference.insert(name, pose);
            }
        }
        for (p, x) in held.iter().enumerate() {
            let track = tracks[p]
                .iter()
                .map(|&i| crate::scene::TrackElement {
                    image_id: ImageId(i),
                    point2d_idx: p as u32,
                })
                .collect();
            model.points3d.insert(
                Point3DId(p as u64 + 1),
                Point3D {
                    xyz: *x,
                    color: [0; 3],
                    error: 0.0,
                    track,
                },
            );
        }
        let a = map_agreement(&model, &reference, &planes);
        assert_eq!((a.num_points, a.num_triangulated), (2, 2), "{a:?}");
        let head_on = a.classes.last().unwrap();
        assert_eq!((head_on.min_cos, head_on.max_cos), (0.7, 1.0));
        assert_eq!((head_on.reference_count, head_on.model_count), (1, 1));
        let reference_m = head_on.reference_median_m.unwrap();
        assert!((reference_m - 0.001).abs() < 1e-7, "{reference_m}");
        let model_m = head_on.model_mean_m.unwrap();
        assert!((model_m + 0.0005).abs() < 1e-7, "{model_m}");
        let counted: usize = a
            .classes
            .iter()
            .map(|c| c.reference_count + c.model_count)
            .sum();
        assert_eq!(counted, 2);
        assert_eq!(map_agreement(&model, &reference, &down_planes), a);
        assert_eq!(a.classes.len(), COS_BOUNDS.len());
        let table = a.table();
        assert!(
            table.contains("0.7-1.0") && table.contains("1.000"),
            "{table}"
        );
    }
}
