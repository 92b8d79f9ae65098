//! The reconstruction under construction: images with poses and a 3D point id
//! per keypoint, 3D points with tracks, and the bookkeeping that next-best-view
//! needs (per keypoint, how many of its correspondences already see a 3D
//! point; per image, how many keypoints do, and how well they spread over the
//! image: a multi-resolution visibility pyramid as in COLMAP).
//!
//! Every map is ordered and ids are handed out in sequence, so the same
//! sequence of calls gives the same state.
use std::collections::{BTreeMap, BTreeSet};

use nalgebra::{Vector2, Vector3};

use crate::io::database::DatabaseSnapshot;
use crate::scene::correspondence_graph::CorrespondenceGraph;
use crate::scene::{
    Camera, CameraId, Image, ImageId, Point2D, Point3D, Point3DId, Reconstruction, Rigid3,
    TrackElement,
};

/// Occupied cells of a grid over the image at several resolutions. Level `l`
/// splits the image into `2^(l+1) x 2^(l+1)` cells; a cell that becomes
/// occupied adds `2^l` to the score, so features spread over the image score
/// higher than the same number in a clump.
#[derive(Clone, Debug)]
pub struct VisibilityPyramid {
    width: f64,
    height: f64,
    /// Per level, the count of visible keypoints per cell.
    cells: Vec<Vec<u32>>,
    score: u64,
}

impl VisibilityPyramid {
    pub fn new(levels: usize, width: u32, height: u32) -> Self {
        let cells = (0..levels)
            .map(|l| vec![0u32; 1 << (2 * (l + 1))])
            .collect();
        Self {
            width: f64::from(width.max(1)),
            height: f64::from(height.max(1)),
            cells,
            score: 0,
        }
    }

    fn cell(&self, level: usize, xy: &Vector2<f64>) -> usize {
        let dim = 1usize << (level + 1);
        let cx = ((xy.x / self.width * dim as f64).floor().max(0.0) as usize).min(dim - 1);
        let cy = ((xy.y / self.height * dim as f64).floor().max(0.0) as usize).min(dim - 1);
        cy * dim + cx
    }

    pub fn add(&mut self, xy: &Vector2<f64>) {
        for level in 0..self.cells.len() {
            let c = self.cell(level, xy);
            self.cells[level][c] += 1;
            if self.cells[level][c] == 1 {
                self.score += 1 << level;
            }
        }
    }

    pub fn remove(&mut self, xy: &Vector2<f64>) {
        for level in 0..self.cells.len() {
            let c = self.cell(level, xy);
            debug_assert!(self.cells[level][c] > 0);
            self.cells[level][c] = self.cells[level][c].saturating_sub(1);
            if self.cells[level][c] == 0 {
                self.score -= 1 << level;
            }
        }
    }

    pub fn score(&self) -> u64 {
        self.score
    }

    /// The score with every cell occupied.
    pub fn max_score(&self) -> u64 {
        (0..self.cells.len())
            .map(|l| (1u64 << l) * self.cells[l].len() as u64)
            .sum()
    }
}

/// One image while mapping.
#[derive(Clone, Debug)]
pub struct ImageState {
    pub id: ImageId,
    pub name: String,
    pub camera_id: CameraId,
    /// Keypoints, pixels (COLMAP convention).
    pub keypoints: Vec<Vector2<f64>>,
    /// The 3D point each keypoint observes.
    pub point3d: Vec<Option<Point3DId>>,
    pub cam_from_world: Option<Rigid3>,
    /// Per keypoint: correspondences whose keypoint observes a 3D point.
    num_corrs_with_point: Vec<u32>,
    /// Keypoints with at least one such correspondence.
    pub num_visible: usize,
    pub pyramid: VisibilityPyramid,
}

impl ImageState {
    pub fn is_registered(&self) -> bool {
        self.cam_from_world.is_some()
    }

    pub fn num_points3d(&self) -> usize {
        self.point3d.iter().filter(|p| p.is_some()).count()
    }
}

/// A 3D point while mapping.
#[derive(Clone, Debug, PartialEq)]
pub struct MapPoint {
    pub xyz: Vector3<f64>,
    /// Sorted by (image, keypoint).
    pub track: Vec<TrackElement>,
    /// Global bundle adjustments this point took part in (shrinks its
    /// association radius).
    pub num_global_ba: u32,
    /// Tied to the map: created from it at initialisation, or associated
    /// with a LiDAR plane in the latest solve. Such points are not removed
    /// for a small triangulation angle (the map fixes their depth).
    pub anchored: bool,
    /// The LiDAR plane the point was tied to in the latest solve (world frame).
    pub plane: Option<PointPlane>,
}

/// A point's plane: `normal . X = offset_m` in the world frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PointPlane {
    pub family: crate::solver::PlaneFamily,
    pub normal: Vector3<f64>,
    pub offset_m: f64,
}

impl PointPlane {
    /// Unsigned distance of `x` (world frame) to the plane, metres.
    pub fn distance_m(&self, x: &Vector3<f64>) -> f64 {
        (self.normal.dot(x) - self.offset_m).abs()
    }
}

/// The reconstruction under construction.
#[derive(Clone, Debug)]
pub struct MapState {
    pub cameras: BTreeMap<CameraId, Camera>,
    pub images: BTreeMap<ImageId, ImageState>,
    pub points: BTreeMap<Point3DId, MapPoint>,
    pub graph: CorrespondenceGraph,
    /// Images in the order they were registered.
    pub registration_order: Vec<ImageId>,
    /// Cameras whose intrinsics are another's (see
    /// [`MapState::share_identical_intrinsics`]); a camera not in here has
    /// its own.
    shared_intrinsics: BTreeMap<CameraId, CameraId>,
    /// Per intrinsics owner, the solves whose refinement took its intrinsics
    /// out of COLMAP's bounds (each then solved again with them held); at
    /// [`MAX_IMPLAUSIBLE_REFINEMENTS`] they are held for the rest of the run.
    pub implausible_refinements: BTreeMap<CameraId, u32>,
    /// Cameras (intrinsics owners) whose principal point is refined with
    /// their focal length and distortion
    /// ([`crate::sfm::options::BundleOptions::refine_principal_point`]);
    /// the others' stays.
    pub principal_point_refined: BTreeSet<CameraId>,
    next_point_id: u64,
}

/// Solves with implausible refined intrinsics after which a camera's
/// intrinsics are no longer refined: each such solve runs twice, and a
/// camera whose points keep pulling it out of bounds would double the cost
/// of every later solve.
pub const MAX_IMPLAUSIBLE_REFINEMENTS: u32 = 2;

impl MapState {
    /// The empty state of a database: no image registered, no point.
    pub fn new(db: &DatabaseSnapshot, pyramid_levels: usize) -> Self {
        let graph = db.correspondence_graph();
        let mut images = BTreeMap::new();
        for (id, img) in &db.images {
            let keypoints = db.keypoints.get(id).cloned().unwrap_or_default();
            let (w, h) = db
                .cameras
                .get(&img.camera_id)
                .map_or((1, 1), |c| (c.width, c.height));
            images.insert(
                *id,
                ImageState {
                    id: *id,
                    name: img.name.clone(),
                    camera_id: img.camera_id,
                    point3d: vec![None; keypoints.len()],
                    num_corrs_with_point: vec![0; keypoints.len()],
                    keypoints,
                    cam_from_world: None,
                    num_visible: 0,
                    pyramid: VisibilityPyramid::new(pyramid_levels, w, h),
                },
            );
        }
        Self {
            cameras: db.cameras.clone(),
            images,
            points: BTreeMap::new(),
            graph,
            registration_order: Vec::new(),
            shared_intrinsics: BTreeMap::new(),
            implausible_refinements: BTreeMap::new(),
            principal_point_refined: BTreeSet::new(),
            next_point_id: 1,
        }
    }

    /// Whether `owner`'s intrinsics are still refined when a solve asks for
    /// it (see [`MAX_IMPLAUSIBLE_REFINEMENTS`]).
    pub fn intrinsics_refinable(&self, owner: CameraId) -> bool {
        self.implausible_refinements
            .get(&owner)
            .is_none_or(|&n| n < MAX_IMPLAUSIBLE_REFINEMENTS)
    }

    /// The camera whose intrinsics `camera` uses in bundle adjustment (itself
    /// unless shared).
    pub fn intrinsics_of(&self, camera: CameraId) -> CameraId {
        self.shared_intrinsics
            .get(&camera)
            .copied()
            .unwrap_or(camera)
    }

    /// Cameras of the same model, size and parameters share one set of
    /// intrinsics (the one with the smallest id) in every later solve:
    /// COLMAP's extractor gives every image its own camera unless told
    /// otherwise, all with the same guessed or EXIF focal length, and one
    /// image's focal length cannot be refined from its own few hundred
    /// points. A camera in `guessed` (no focal length prior) never shares
    /// with one outside it (with `auto` the two are refined differently), nor
    /// does a camera in `apart` (an input model's, which keep their own
    /// intrinsics) with one outside it. Returns the number of cameras that now
    /// share another's.
    pub fn share_identical_intrinsics(
        &mut self,
        guessed: &BTreeSet<CameraId>,
        apart: &BTreeSet<CameraId>,
    ) -> usize {
        let mut first: BTreeMap<(IntrinsicsKey, bool), CameraId> = BTreeMap::new();
        self.shared_intrinsics.clear();
        for (id, c) in &self.cameras {
            let key = (intrinsics_key(c, guessed.contains(id)), apart.contains(id));
            let owner = *first.entry(key).or_insert(*id);
            if owner != *id {
                self.shared_intrinsics.insert(*id, owner);
            }
        }
        self.shared_intrinsics.len()
    }

    /// The cameras whose intrinsics are those of `owner` (itself included).
    pub fn cameras_sharing(&self, owner: CameraId) -> Vec<CameraId> {
        self.cameras
            .keys()
            .copied()
            .filter(|&id| self.intrinsics_of(id) == owner)
            .collect()
    }

    /// Sets the focal length of `owner`'s intrinsics (every focal parameter)
    /// on every camera sharing them; returns those cameras.
    pub fn set_focal_length(&mut self, owner: CameraId, focal_px: f64) -> Vec<CameraId> {
        let members = self.cameras_sharing(owner);
        for id in &members {
            if let Some(c) = self.cameras.get_mut(id) {
                *c = super::focal::with_focal(c, focal_px);
            }
        }
        members
    }

    pub fn camera_of(&self, image: ImageId) -> &Camera {
        // Every image's camera exists: the database reader checks the foreign key.
        &self.cameras[&self.images[&image].camera_id]
    }

    pub fn pose(&self, image: ImageId) -> Option<Rigid3> {
        self.images.get(&image).and_then(|i| i.cam_from_world)
    }

    pub fn num_registered(&self) -> usize {
        self.registration_order.len()
    }

    pub fn register(&mut self, image: ImageId, cam_from_world: Rigid3) {
        let img = self
            .images
            .get_mut(&image)
            .expect("registering a known image");
        if img.cam_from_world.is_none() {
            self.registration_order.push(image);
        }
        img.cam_from_world = Some(cam_from_world);
    }

    pub fn keypoint(&self, e: TrackElement) -> Vector2<f64> {
        self.images[&e.image_id].keypoints[e.point2d_idx as usize]
    }

    pub fn point_of(&self, e: TrackElement) -> Option<Point3DId> {
        self.images
            .get(&e.image_id)
            .and_then(|i| i.point3d.get(e.point2d_idx as usize).copied().flatten())
    }

    /// Book-keeping of the correspondences of `e` when it gains (+1) or loses
    /// (-1) a 3D point.
    fn update_corr_counts(&mut self, e: TrackElement, gained: bool) {
        let corrs: Vec<TrackElement> = self
            .graph
            .correspondences(e.image_id, e.point2d_idx)
            .to_vec();
        for c in corrs {
            let Some(img) = self.images.get_mut(&c.image_id) else {
                continue;
            };
            let k = c.point2d_idx as usize;
            if k >= img.keypoints.len() {
                continue;
            }
            let xy = img.keypoints[k];
            if gained {
                img.num_corrs_with_point[k] += 1;
                if img.num_corrs_with_point[k] == 1 {
                    img.num_visible += 1;
                    img.pyramid.add(&xy);
                }
            } else {
                img.num_corrs_with_point[k] = img.num_corrs_with_point[k].saturating_sub(1);
                if img.num_corrs_with_point[k] == 0 {
                    img.num_visible -= 1;
                    img.pyramid.remove(&xy);
                }
            }
        }
    }

    /// A new 3D point observed by `track` (keypoints must be free).
    pub fn add_point(&mut self, xyz: Vector3<f64>, track: Vec<TrackElement>) -> Point3DId {
        let id = Point3DId(self.next_point_id);
        self.next_point_id += 1;
        self.points.insert(
            id,
            MapPoint {
                xyz,
                track: Vec::new(),
                num_global_ba: 0,
                anchored: false,
                plane: None,
            },
        );
        for e in track {
            self.add_observation(id, e);
        }
        id
    }

    /// Adds `e` to the track of `point`; false when `e` already has a point
    /// or the track already holds a keypoint of that image.
    pub fn add_observation(&mut self, point: Point3DId, e: TrackElement) -> bool {
        if self.point_of(e).is_some() {
            return false;
        }
        let Some(p) = self.points.get(&point) else {
            return false;
        };
        if p.track.iter().any(|t| t.image_id == e.image_id) {
            return false;
        }
        let p = self.points.get_mut(&point).expect("checked above");
        let pos = p.track.binary_search(&e).unwrap_or_else(|i| i);
        p.track.insert(pos, e);
        self.images
            .get_mut(&e.image_id)
            .expect("known image")
            .point3d[e.point2d_idx as usize] = Some(point);
        self.update_corr_counts(e, true);
        true
    }

    /// Removes one observation; deletes the point when fewer than two remain.
    /// Returns whether the point was deleted.
    pub fn remove_observation(&mut self, point: Point3DId, e: TrackElement) -> bool {
        let Some(p) = self.points.get_mut(&point) else {
            return false;
        };
        if let Ok(pos) = p.track.binary_search(&e) {
            p.track.remove(pos);
            self.images
                .get_mut(&e.image_id)
                .expect("known image")
                .point3d[e.point2d_idx as usize] = None;
            self.update_corr_counts(e, false);
        }
        if self.points[&point].track.len() < 2 {
            self.delete_point(point);
            true
        } else {
            false
        }
    }

    pub fn delete_point(&mut self, point: Point3DId) {
        let Some(p) = self.points.remove(&point) else {
            return;
        };
        for e in p.track {
            self.images
                .get_mut(&e.image_id)
                .expect("known image")
                .point3d[e.point2d_idx as usize] = None;
            self.update_corr_counts(e, false);
        }
    }

    /// Merges point `b` into `a` at position `xyz` when their tracks share no
    /// image. Returns false (and changes nothing) otherwise.
    pub fn merge_points(&mut self, a: Point3DId, b: Point3DId, xyz: Vector3<f64>) -> bool {
        if a == b {
            return false;
        }
        let (Some(pa), Some(pb)) = (self.points.get(&a), self.points.get(&b)) else {
            return false;
        };
        if pb
            .track
            .iter()
            .any(|e| pa.track.iter().any(|f| f.image_id == e.image_id))
        {
            return false;
        }
        let track_b = pb.track.clone();
        let global_ba = pa.num_global_ba.min(pb.num_global_ba);
        self.delete_point(b);
        for e in track_b {
            self.add_observation(a, e);
        }
        let p = self.points.get_mut(&a).expect("a exists");
        p.xyz = xyz;
        p.num_global_ba = global_ba;
        true
    }

    /// Mean reprojection error of a point over its track, pixels (`None` if
    /// any observation is behind its camera).
    pub fn point_error_px(&self, point: Point3DId) -> Option<f64> {
        let p = self.points.get(&point)?;
        let mut sum = 0.0;
        for e in &p.track {
            let pose = self.pose(e.image_id)?;
            let e2 = super::geometry::reprojection_error_sq(
                self.camera_of(e.image_id),
                &pose,
                &p.xyz,
                &self.keypoint(*e),
            )?;
            sum += e2.sqrt();
        }
        Some(sum / p.track.len().max(1) as f64)
    }

    /// Number of 3D points two registered images share.
    pub fn num_shared_points(&self, a: ImageId, b: ImageId) -> usize {
        let img = &self.images[&a];
        img.point3d
            .iter()
            .flatten()
            .filter(|pid| self.points[pid].track.iter().any(|e| e.image_id == b))
            .count()
    }

    /// The COLMAP model of the current state (registered images only carry a
    /// pose; every image keeps its keypoints).
    pub fn to_reconstruction(&self) -> Reconstruction {
        let mut rec = Reconstruction {
            cameras: self.cameras.clone(),
            ..Default::default()
        };
        for (id, img) in &self.images {
            if !img.is_registered() {
                continue;
            }
            rec.images.insert(
                *id,
                Image {
                    id: *id,
                    name: img.name.clone(),
                    camera_id: img.camera_id,
                    cam_from_world: img.cam_from_world,
                    points2d: img
                        .keypoints
                        .iter()
                        .zip(&img.point3d)
                        .map(|(xy, p)| Point2D {
                            xy: *xy,
                            point3d_id: *p,
                        })
                        .collect(),
                },
            );
        }
        for (id, p) in &self.points {
            rec.points3d.insert(
                *id,
                Point3D {
                    xyz: p.xyz,
                    color: [128, 128, 128],
                    error: self.point_error_px(*id).unwrap_or(0.0),
                    track: p.track.clone(),
                },
            );
        }
        rec
    }
}

/// What makes cameras share intrinsics in
/// [`MapState::share_identical_intrinsics`]: model, size, parameter bits, and
/// whether the focal length is a guess that is refined apart.
pub(crate) type IntrinsicsKey = (&'static str, u32, u32, Vec<u64>, bool);

/// The [`IntrinsicsKey`] of camera `c`.
pub(crate) fn intrinsics_key(c: &Camera, guessed: bool) -> IntrinsicsKey {
    (
        c.model.name(),
        c.width,
        c.height,
        c.params.iter().map(|p| p.to_bits()).collect(),
        guessed,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::CameraModel;

    #[test]
    fn pyramid_prefers_spread() {
        let mut clumped = VisibilityPyramid::new(3, 100, 100);
        let mut spread = VisibilityPyramid::new(3, 100, 100);
        for i in 0..4 {
            clumped.add(&Vector2::new(10.0 + 0.5 * i as f64, 10.0));
        }
        for (x, y) in [(10.0, 10.0), (90.0, 10.0), (10.0, 90.0), (90.0, 90.0)] {
            spread.add(&Vector2::new(x, y));
        }
        // Clump: one cell per level: 1 + 2 + 4.
        assert_eq!(clumped.score(), 7);
        // Spread: four cells per level: 4 * (1 + 2 + 4).
        assert_eq!(spread.score(), 28);
        assert_eq!(spread.max_score(), 4 + 16 * 2 + 64 * 4);
        for (x, y) in [(10.0, 10.0), (90.0, 10.0), (10.0, 90.0), (90.0, 90.0)] {
            spread.remove(&Vector2::new(x, y));
        }
        assert_eq!(spread.score(), 0);
    }

    #[test]
    fn identical_cameras_share_the_smallest_ids_intrinsics() {
        let radial = |id: u32, f: f64, w: u32| Camera {
            id: CameraId(id),
            model: CameraModel::SimpleRadial,
            width: w,
            height: 480,
            params: vec![f, 320.0, 240.0, 0.0],
        };
        let mut db = DatabaseSnapshot::default();
        for c in [
            radial(1, 768.0, 640),
            radial(2, 768.0, 640),
            radial(3, 700.0, 640),
            radial(4, 768.0, 640),
            radial(5, 768.0, 641),
            radial(6, 700.0, 640),
        ] {
            db.cameras.insert(c.id, c);
        }
        let mut pinhole = radial(7, 768.0, 640);
        pinhole.model = CameraModel::Pinhole;
        pinhole.params = vec![768.0, 768.0, 320.0, 240.0];
        db.cameras.insert(CameraId(7), pinhole);
        db.cameras.insert(CameraId(8), radial(8, 768.0, 640));
        let mut state = MapState::new(&db, 1);
        assert_eq!(state.intrinsics_of(CameraId(2)), CameraId(2));
        // 8 has 1's parameters but no focal length prior (1 has one).
        let guessed = BTreeSet::from([CameraId(8)]);
        assert_eq!(
            state.share_identical_intrinsics(&guessed, &BTreeSet::new()),
            3
        );
        let of: Vec<u32> = (1..=8)
            .map(|i| state.intrinsics_of(CameraId(i)).0)
            .collect();
        // 2 and 4 are 1's twins, 6 is 3's; 5 (another width), 7 (another
        // model) and 8 (guessed) are their own.
        assert_eq!(of, [1, 1, 3, 1, 5, 3, 7, 8]);
        // 4 kept apart (an input model's camera): it shares with none, the
        // others as before.
        let apart = BTreeSet::from([CameraId(4)]);
        assert_eq!(state.share_identical_intrinsics(&guessed, &apart), 2);
        let of: Vec<u32> = (1..=8)
            .map(|i| state.intrinsics_of(CameraId(i)).0)
            .collect();
        assert_eq!(of, [1, 1, 3, 4, 5, 3, 7, 8]);
    }
}
