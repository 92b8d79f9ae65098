//! Triangulation of new tracks (multi-view DLT inside a RANSAC over view
//! pairs, minimum triangulation angle, cheirality, reprojection error), track
//! continuation (a keypoint joins a point its correspondences observe when it
//! reprojects well) and merging (two points linked by a correspondence become
//! one when every observation of both fits the merged position).
use std::collections::BTreeSet;

use nalgebra::{Vector2, Vector3};

use super::geometry::reprojection_error_sq;
use crate::estimators::triangulation::{triangulate_dlt, triangulation_angle_deg};

/// Angle (radians) at `point` between the rays to two camera centres.
fn triangulation_angle_rad(c1: &Vector3<f64>, c2: &Vector3<f64>, point: &Vector3<f64>) -> f64 {
    triangulation_angle_deg(c1, c2, point).to_radians()
}
use super::options::TriangulateOptions;
use super::state::MapState;
use crate::scene::{ImageId, Point3DId, Rigid3, TrackElement};

/// Counts of one triangulation pass.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct TriangulationStats {
    pub created: usize,
    pub continued: usize,
    pub merged: usize,
}

impl std::ops::AddAssign for TriangulationStats {
    fn add_assign(&mut self, o: Self) {
        self.created += o.created;
        self.continued += o.continued;
        self.merged += o.merged;
    }
}

/// Whether `xyz` reprojects within `max_error_px` (and in front) at `e`.
fn fits(state: &MapState, e: TrackElement, xyz: &Vector3<f64>, max_error_px: f64) -> bool {
    let Some(pose) = state.pose(e.image_id) else {
        return false;
    };
    reprojection_error_sq(state.camera_of(e.image_id), &pose, xyz, &state.keypoint(e))
        .is_some_and(|e2| e2 <= max_error_px * max_error_px)
}

/// Largest triangulation angle over pairs of the given camera centres.
fn max_angle_rad(centres: &[Vector3<f64>], xyz: &Vector3<f64>) -> f64 {
    let mut best: f64 = 0.0;
    for i in 0..centres.len() {
        for j in i + 1..centres.len() {
            best = best.max(triangulation_angle_rad(&centres[i], &centres[j], xyz));
        }
    }
    best
}

/// Robust triangulation of keypoints in distinct registered images: DLT of
/// every pair of views (the first 12 views), keeping the pair with the most
/// views that fit; then DLT of those views. Returns the point and the views
/// that fit it, or `None` when fewer than two views fit or the angle is too
/// small.
pub fn triangulate_views(
    state: &MapState,
    views: &[TrackElement],
    options: &TriangulateOptions,
) -> Option<(Vector3<f64>, Vec<TrackElement>)> {
    let data: Vec<(TrackElement, Rigid3, Vector2<f64>, Vector3<f64>)> = views
        .iter()
        .filter_map(|e| {
            let pose = state.pose(e.image_id)?;
            let ray = state.camera_of(e.image_id).unproject(&state.keypoint(*e))?;
            Some((*e, pose, Vector2::new(ray.x, ray.y), pose.camera_center()))
        })
        .collect();
    if data.len() < 2 {
        return None;
    }
    let min_angle = options.min_angle_deg.to_radians();
    let inliers_of = |xyz: &Vector3<f64>| -> Vec<usize> {
        (0..data.len())
            .filter(|&i| fits(state, data[i].0, xyz, options.max_error_px))
            .collect()
    };
    let m = data.len().min(12);
    let mut best: Option<Vec<usize>> = None;
    for i in 0..m {
        for j in i + 1..m {
            let Some(xyz) = triangulate_dlt(&[
                (data[i].1, data[i].2.push(1.0)),
                (data[j].1, data[j].2.push(1.0)),
            ]) else {
                continue;
            };
            if triangulation_angle_rad(&data[i].3, &data[j].3, &xyz) < min_angle {
                continue;
            }
            let inl = inliers_of(&xyz);
            if inl.len() >= 2 && best.as_ref().is_none_or(|b| inl.len() > b.len()) {
                let all = inl.len() == data.len();
                best = Some(inl);
                if all {
                    break;
                }
            }
        }
    }
    let inl = best?;
    let sub: Vec<(Rigid3, Vector3<f64>)> = inl
        .iter()
        .map(|&i| (data[i].1, data[i].2.push(1.0)))
        .collect();
    let xyz = triangulate_dlt(&sub)?;
    let inl: Vec<usize> = inl
        .into_iter()
        .filter(|&i| fits(state, data[i].0, &xyz, options.max_error_px))
        .collect();
    if inl.len() < 2 {
        return None;
    }
    let centres: Vec<Vector3<f64>> = inl.iter().map(|&i| data[i].3).collect();
    if max_angle_rad(&centres, &xyz) < min_angle {
        return None;
    }
    Some((xyz, inl.into_iter().map(|i| data[i].0).collect()))
}

/// Tries to merge `b` into `a`: the position is the track-length weighted
/// mean; every observation of both must fit within `max_merge_error_px`.
pub fn try_merge(
    state: &mut MapState,
    a: Point3DId,
    b: Point3DId,
    options: &TriangulateOptions,
) -> bool {
    if a == b {
        return false;
    }
    let (Some(pa), Some(pb)) = (state.points.get(&a), state.points.get(&b)) else {
        return false;
    };
    let (na, nb) = (pa.track.len() as f64, pb.track.len() as f64);
    let xyz = (pa.xyz * na + pb.xyz * nb) / (na + nb);
    let ok = pa
        .track
        .iter()
        .chain(&pb.track)
        .all(|e| fits(state, *e, &xyz, options.max_merge_error_px));
    ok && {
        let anchored = pa.anchored || pb.anchored;
        let merged = state.merge_points(a, b, xyz);
        if merged {
            if let Some(p) = state.points.get_mut(&a) {
                p.anchored = anchored;
            }
        }
        merged
    }
}

/// Continues and merges tracks of `point` through the correspondence graph:
/// free keypoints of registered images that fit join it; points linked to it
/// are merged when they fit.
pub fn complete_and_merge_point(
    state: &mut MapState,
    point: Point3DId,
    options: &TriangulateOptions,
) -> TriangulationStats {
    let mut stats = TriangulationStats::default();
    let mut queue: Vec<TrackElement> = match state.points.get(&point) {
        Some(p) => p.track.clone(),
        None => return stats,
    };
    let mut seen: BTreeSet<TrackElement> = queue.iter().copied().collect();
    while let Some(e) = queue.pop() {
        let corrs: Vec<TrackElement> = state
            .graph
            .correspondences(e.image_id, e.point2d_idx)
            .to_vec();
        for c in corrs {
            if !seen.insert(c) || state.pose(c.image_id).is_none() {
                continue;
            }
            let Some(p) = state.points.get(&point) else {
                return stats;
            };
            match state.point_of(c) {
                None => {
                    let xyz = p.xyz;
                    if fits(state, c, &xyz, options.max_merge_error_px)
                        && state.add_observation(point, c)
                    {
                        stats.continued += 1;
                        queue.push(c);
                    }
                }
                Some(other) if other != point => {
                    let other_track = state.points[&other].track.clone();
                    if try_merge(state, point, other, options) {
                        stats.merged += 1;
                        for t in other_track {
                            if seen.insert(t) {
                                queue.push(t);
                            }
                        }
                    }
                }
                Some(_) => {}
            }
        }
    }
    stats
}

/// Triangulates the tracks of a newly registered image: a keypoint with a
/// point grows and merges it; a keypoint whose correspondences see points
/// joins the first that fits; otherwise a new point is triangulated from the
/// keypoint and its free correspondences in registered images.
pub fn triangulate_image(
    state: &mut MapState,
    image: ImageId,
    options: &TriangulateOptions,
) -> TriangulationStats {
    let mut stats = TriangulationStats::default();
    if state.pose(image).is_none() {
        return stats;
    }
    let n = state.images[&image].keypoints.len() as u32;
    for k in 0..n {
        let e = TrackElement {
            image_id: image,
            point2d_idx: k,
        };
        if state.point_of(e).is_none() {
            let corrs: Vec<TrackElement> = state
                .graph
                .correspondences(image, k)
                .iter()
                .copied()
                .filter(|c| state.pose(c.image_id).is_some())
                .collect();
            let mut candidates: Vec<Point3DId> =
                corrs.iter().filter_map(|c| state.point_of(*c)).collect();
            candidates.sort();
            candidates.dedup();
            for p in candidates {
                let xyz = state.points[&p].xyz;
                if fits(state, e, &xyz, options.max_merge_error_px) && state.add_observation(p, e) {
                    stats.continued += 1;
                    break;
                }
            }
            if state.point_of(e).is_none() {
                // One free keypoint per other image, in correspondence order.
                let mut views = vec![e];
                let mut used: BTreeSet<ImageId> = BTreeSet::from([image]);
                for c in &corrs {
                    if state.point_of(*c).is_none() && used.insert(c.image_id) {
                        views.push(*c);
                    }
                }
                if views.len() >= 2 {
                    if let Some((xyz, inliers)) = triangulate_views(state, &views, options) {
                        state.add_point(xyz, inliers);
                        stats.created += 1;
                    }
                }
            }
        }
        if let Some(p) = state.point_of(e) {
            stats += complete_and_merge_point(state, p, options);
        }
    }
    stats
}

/// Triangulates every registered image again (when registration stalls).
pub fn retriangulate_all(state: &mut MapState, options: &TriangulateOptions) -> TriangulationStats {
    let mut stats = TriangulationStats::default();
    let images: Vec<ImageId> = state.registration_order.clone();
    for image in images {
        stats += triangulate_image(state, image, options);
    }
    stats
}
