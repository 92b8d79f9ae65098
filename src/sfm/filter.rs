//! Outlier filters run after each bundle adjustment. Free functions; each
//! returns how many observations or points it removed.
use std::collections::BTreeSet;

use nalgebra::Vector3;

use super::geometry::reprojection_error_sq;
use super::state::MapState;
use crate::estimators::triangulation::triangulation_angle_deg;
use crate::scene::{ImageId, Point3DId, TrackElement};

/// Removes observations whose reprojection error exceeds `max_error_px` or
/// whose point lies behind the camera, for the points observed by `images`
/// (all points when `None`). Points left with fewer than two observations are
/// deleted. Returns the number of observations removed.
pub fn filter_observations(
    state: &mut MapState,
    images: Option<&BTreeSet<ImageId>>,
    max_error_px: f64,
) -> usize {
    let points: Vec<Point3DId> = match images {
        None => state.points.keys().copied().collect(),
        Some(set) => {
            let mut ids: Vec<Point3DId> = set
                .iter()
                .filter_map(|i| state.images.get(i))
                .flat_map(|img| img.point3d.iter().flatten().copied())
                .collect();
            ids.sort();
            ids.dedup();
            ids
        }
    };
    let max_sq = max_error_px * max_error_px;
    let mut removed = 0;
    for pid in points {
        let Some(p) = state.points.get(&pid) else {
            continue;
        };
        let bad: Vec<TrackElement> = p
            .track
            .iter()
            .copied()
            .filter(|e| {
                let Some(pose) = state.pose(e.image_id) else {
                    return true;
                };
                reprojection_error_sq(
                    state.camera_of(e.image_id),
                    &pose,
                    &p.xyz,
                    &state.keypoint(*e),
                )
                .is_none_or(|e2| e2 > max_sq)
            })
            .collect();
        for e in bad {
            removed += 1;
            if state.remove_observation(pid, e) {
                // The point is gone with its remaining observation.
                removed += 1;
                break;
            }
        }
    }
    removed
}

/// Deletes points whose largest triangulation angle is below `min_angle_deg`,
/// except those anchored to the map. Returns the number of points deleted.
pub fn filter_small_angle_points(state: &mut MapState, min_angle_deg: f64) -> usize {
    let min_rad = min_angle_deg.to_radians();
    let doomed: Vec<Point3DId> = state
        .points
        .iter()
        .filter(|(_, p)| !p.anchored)
        .filter(|(_, p)| {
            let centres: Vec<Vector3<f64>> = p
                .track
                .iter()
                .filter_map(|e| state.pose(e.image_id).map(|q| q.camera_center()))
                .collect();
            let mut best: f64 = 0.0;
            for i in 0..centres.len() {
                for j in i + 1..centres.len() {
                    best = best.max(
                        triangulation_angle_deg(&centres[i], &centres[j], &p.xyz).to_radians(),
                    );
                }
            }
            best < min_rad
        })
        .map(|(id, _)| *id)
        .collect();
    for id in &doomed {
        state.delete_point(*id);
    }
    doomed.len()
}
