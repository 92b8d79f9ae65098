//! Metric depth maps of the LiDAR map as a model's images see it: at each
//! pixel the depth of the map's surface there, for depth-supervised NeRF and
//! Gaussian splatting, or to check a dense reconstruction against the scan.
//!
//! The map's points are drawn as square splats into a z-buffer
//! ([`nearest_splats`], as `depth` and `colour-map` do); at each pixel the
//! nearest splat's point stands for the surface, and the pixel's own ray is
//! crossed with that point's tangent plane (its normal), so that the depth
//! follows the surface across the splat. A splat's own depth, the same over
//! its whole square, is off by up to its half-width times the tangent of the
//! view's angle from the normal: centimetres on a floor seen at a glance.
//! Where the point has no normal, the view is more grazing than
//! `max_view_angle_deg` or the crossing lies beyond the splat's reach, the
//! point's own depth is kept.
use nalgebra::{Vector2, Vector3};
use rayon::prelude::*;

use super::cloud::PointCloud;
use super::depth_image::{nearest_splats, NO_SPLAT};
use super::grid::FrustumGrid;
use super::projection::{project_visible_points, ProjectionError, ProjectionOptions};
use crate::scene::camera::Camera;
use crate::scene::pose::Rigid3;

/// What a depth map's value measures.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum DepthKind {
    /// Along the optical axis (the camera frame's z): what NeRF and Gaussian
    /// splatting tools and COLMAP's depth maps hold.
    Z,
    /// Distance from the camera centre.
    Range,
}

/// Options of [`render_surface_depth`].
#[derive(Clone, Debug, PartialEq)]
pub struct SurfaceDepthOptions {
    /// Depth range and splats (see [`ProjectionOptions`]).
    pub projection: ProjectionOptions,
    /// On a map of spacing s, a map point's splat is at least this times s
    /// wide either side ([`Self::splats_for_spacing`]): wide enough
    /// that a surface in front has no gaps a surface behind shows through
    /// (as `colour-map`'s).
    pub splat_per_spacing: f64,
    /// Views farther than this from a point's normal keep the point's own
    /// depth rather than its tangent plane's, degrees.
    pub max_view_angle_deg: f64,
    /// The tangent plane is crossed at most this many splat half-widths from
    /// its point (measured on the plane); farther, the point's own depth.
    pub max_reach_half_widths: f64,
    /// No depth within the nearer splat's half-size of a step between
    /// surfaces (an occluding edge, a corner, the map's end), where the
    /// splats of the surface in front may reach past its edge. Default off.
    pub drop_edges: bool,
}

impl Default for SurfaceDepthOptions {
    fn default() -> Self {
        SurfaceDepthOptions {
            projection: ProjectionOptions::default(),
            splat_per_spacing: 0.8,
            max_view_angle_deg: 85.0,
            max_reach_half_widths: 4.0,
            drop_edges: false,
        }
    }
}

impl SurfaceDepthOptions {
    pub fn validate(&self) -> Result<(), ProjectionError> {
        self.projection.validate()?;
        let bad = |m: &str| Err(ProjectionError::InvalidOption(m.to_string()));
        if !(self.splat_per_spacing >= 0.0 && self.splat_per_spacing.is_finite()) {
            return bad("the splat width per map spacing must be finite and >= 0");
        }
        if !(self.max_view_angle_deg >= 0.0 && self.max_view_angle_deg < 90.0) {
            return bad("the largest view angle for tangent planes must be in [0, 90) degrees");
        }
        if !(self.max_reach_half_widths >= 0.0 && self.max_reach_half_widths.is_finite()) {
            return bad("the tangent planes' reach must be finite and >= 0 splat half-widths");
        }
        Ok(())
    }

    /// Splats exactly `splat_per_spacing` times `spacing_m` wide either side
    /// at every depth (no angular margin, no saturation: the reference's
    /// splat, sized for looking up features, is 8-10 px wide either side at
    /// 2-3 m at 640 x 480 and put a near surface's depth on the 2-4 % of a
    /// room's pixels that lie beside its edges). Unchanged for a spacing
    /// that is not a positive number (the projection's default splats).
    pub fn splats_for_spacing(&mut self, spacing_m: f64) {
        if spacing_m.is_finite() && spacing_m > 0.0 {
            let splat = &mut self.projection.splat;
            let half = self.splat_per_spacing * spacing_m;
            splat.patch_half_width_m = half;
            splat.near_half_width_m = half;
            splat.angular_margin_rad = 0.0;
            splat.saturation_depth_m = 0.0;
        }
    }
}

/// The ray of every pixel centre of a camera, on the normalised image plane
/// (the ray is `(x, y, 1)` in the camera frame), row-major; NaN where the
/// pixel has no ray (beyond a fisheye's 90°, or where the distortion folds
/// back). Computed once per camera: undoing a lens's distortion takes a few
/// Newton steps per pixel.
#[derive(Clone, Debug)]
pub struct PixelRays {
    pub width: u32,
    pub height: u32,
    rays: Vec<[f32; 2]>,
}

impl PixelRays {
    pub fn new(camera: &Camera) -> Self {
        let w = camera.width as usize;
        let mut rays = vec![[f32::NAN; 2]; w * camera.height as usize];
        if w > 0 {
            rays.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
                for (x, ray) in row.iter_mut().enumerate() {
                    let pixel = Vector2::new(x as f64 + 0.5, y as f64 + 0.5);
                    if let Some(r) = camera.unproject(&pixel) {
                        *ray = [r.x as f32, r.y as f32];
                    }
                }
            });
        }
        PixelRays {
            width: camera.width,
            height: camera.height,
            rays,
        }
    }

    /// The ray `(x, y, 1)` of pixel `i` (row-major), when it has one.
    fn ray(&self, i: usize) -> Option<Vector3<f64>> {
        let [x, y] = self.rays[i];
        (x.is_finite() && y.is_finite()).then(|| Vector3::new(f64::from(x), f64::from(y), 1.0))
    }
}

/// A depth map: metres, row-major, 0 where the image sees no map surface.
#[derive(Clone, Debug, PartialEq)]
pub struct DepthMap {
    pub width: u32,
    pub height: u32,
    pub depth_m: Vec<f32>,
    /// Pixels whose depth is the crossing with a tangent plane (the others
    /// with a depth have their point's own).
    pub num_on_tangent_planes: usize,
}

impl DepthMap {
    /// Pixels with a depth.
    pub fn num_filled(&self) -> usize {
        self.depth_m.iter().filter(|&&d| d > 0.0).count()
    }

    /// Median of the depths there are (`None` when there is none).
    pub fn median_m(&self) -> Option<f64> {
        let mut d: Vec<f32> = self.depth_m.iter().copied().filter(|&d| d > 0.0).collect();
        if d.is_empty() {
            return None;
        }
        let mid = d.len() / 2;
        let (_, m, _) = d.select_nth_unstable_by(mid, f32::total_cmp);
        Some(f64::from(*m))
    }
}

/// What the map holds around one of its points.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum MapSurface {
    /// A surface: the offset `d` of its plane `n . x = d` (world frame, `n`
    /// the point's normal), e.g. the mean over the point's neighbours
    /// ([`crate::sfm::associate::NearestNeighbourAssociator::plane_offset_at`]).
    Plane(f64),
    /// Other points but no plane (a pole thinner than the plane radius,
    /// foliage): a pixel where it is the nearest has no depth.
    NoPlane,
    /// No other point near it (dust, a bird, a scan's stray return): it is
    /// not drawn, and the surface behind shows.
    Stray,
}

/// [`MapSurface`] of map point `i`.
pub type SurfaceAt<'a> = &'a (dyn Fn(usize) -> MapSurface + Sync);

/// The depth map of the map's surfaces seen by `camera` at `cam_from_world`
/// (`rays` from [`PixelRays::new`] for this camera): see the module's doc.
/// With `surface_at`, each point's plane is the one it gives (a plane
/// through the mean of its neighbours is less noisy than one through the
/// point), stray points are not drawn, and where a point with no plane is
/// the nearest the pixel has no depth (rather than a square of the point's
/// depth, or the surface behind it); without, each point's own tangent
/// plane.
#[allow(clippy::too_many_arguments)]
pub fn render_surface_depth(
    cloud: &PointCloud,
    grid: &FrustumGrid,
    camera: &Camera,
    rays: &PixelRays,
    cam_from_world: &Rigid3,
    options: &SurfaceDepthOptions,
    kind: DepthKind,
    surface_at: Option<SurfaceAt>,
) -> Result<DepthMap, ProjectionError> {
    options.validate()?;
    if (rays.width, rays.height) != (camera.width, camera.height) {
        return Err(ProjectionError::InvalidOption(format!(
            "pixel rays for a {} x {} image, the camera is {} x {}",
            rays.width, rays.height, camera.width, camera.height
        )));
    }
    let focal = camera.mean_focal_length();
    let mut projection = options.projection.clone();
    // Splats as wide as the map's spacing down to the nearest depth drawn,
    // whatever the focal length (a 5 cm map at 3200 px needs 80 px at 1 m).
    let splat = &mut projection.splat;
    let nearest_half_size = focal * splat.near_half_width_m / projection.min_depth_m;
    if nearest_half_size.is_finite() {
        splat.max_half_size_px = splat.max_half_size_px.max(nearest_half_size);
    }
    let mut splats = project_visible_points(cloud, grid, camera, cam_from_world, &projection)?;
    // Each splat's plane offset (`None`: no depth where it is the nearest).
    let mut offsets: Vec<Option<f64>> = Vec::new();
    if let Some(surface_at) = surface_at {
        let surfaces: Vec<MapSurface> = splats
            .par_iter()
            .map(|s| surface_at(s.point_idx as usize))
            .collect();
        let mut k = 0;
        splats.retain(|_| {
            k += 1;
            surfaces[k - 1] != MapSurface::Stray
        });
        offsets = surfaces
            .into_iter()
            .filter_map(|s| match s {
                MapSurface::Plane(d) => Some(Some(d)),
                MapSurface::NoPlane => Some(None),
                MapSurface::Stray => None,
            })
            .collect();
    }
    let nearest = nearest_splats(&splats, camera.width, camera.height);
    let min_cos = options.max_view_angle_deg.to_radians().cos();
    let (min_depth, max_depth) = (projection.min_depth_m, projection.max_depth_m);
    let fisheye = camera.model.is_fisheye();
    let rotation = cam_from_world.rotation.to_rotation_matrix();
    // The depth (of `kind`) of the surface of splat `k`'s point along `ray`
    // and whether it is its plane's crossing (else the point's own depth);
    // `None` for a point without a surface.
    let surface = |k: u32, ray: &Vector3<f64>, bounded: bool| -> Option<(f64, bool)> {
        let offset = match offsets.get(k as usize) {
            Some(None) => return None,
            Some(&Some(d)) => Some(d),
            None => None,
        };
        let splat = &splats[k as usize];
        let i = splat.point_idx as usize;
        let crossing = cloud.normals.as_ref().and_then(|normals| {
            let n_world = Vector3::from(normals[i].map(f64::from)).try_normalize(1e-9)?;
            let p_world = cloud.point_in_map(i);
            // The plane's offset from the point, along the normal.
            let shift = offset
                .map(|d| d - n_world.dot(&p_world))
                .filter(|s| s.is_finite())
                .unwrap_or(0.0);
            let n = rotation * n_world;
            let p = cam_from_world.transform_point(&p_world) + n * shift;
            let n_dot_ray = n.dot(ray);
            let cos = n_dot_ray.abs() / ray.norm();
            // (Unbounded, as for comparing two pixels' surfaces, at any
            // slant: one plane still agrees with itself.)
            if !(cos > 0.0 && (cos >= min_cos || !bounded)) {
                return None;
            }
            // The crossing t * ray; its z is t.
            let t = n.dot(&p) / n_dot_ray;
            // The splat's footprint on the plane: its square seen at a
            // slant, moved with the plane's shift.
            let tan = (1.0 - cos * cos).max(0.0).sqrt() / cos;
            let reach =
                options.max_reach_half_widths * splat.half_size_px * splat.range_m / focal / cos
                    + shift.abs() * tan;
            let on_plane = t * ray - p;
            let depth = match kind {
                DepthKind::Z => t,
                DepthKind::Range => t * ray.norm(),
            };
            // Within the depth range, as the points drawn are: not nearer
            // than its start along the axis (a fisheye: from the camera),
            // neither deeper nor farther than its end.
            let range = t * ray.norm();
            let near = if fisheye { range } else { t };
            let in_range = near >= min_depth && t <= max_depth && range <= max_depth;
            (!bounded || on_plane.norm() <= reach && in_range).then_some(depth)
        });
        Some(match (crossing, kind) {
            (Some(depth), _) => (depth, true),
            (None, DepthKind::Z) => (splat.depth_m, false),
            (None, DepthKind::Range) => (splat.range_m, false),
        })
    };
    let (w, h) = (camera.width as usize, camera.height as usize);
    // The nearest splat's surface at each pixel, then the gaps closed.
    let mut depth: Vec<(f32, bool)> = (0..w * h)
        .into_par_iter()
        .map(|px| {
            let (_, k) = nearest[px];
            match rays.ray(px) {
                Some(ray) if k != NO_SPLAT => surface(k, &ray, true)
                    .map_or((0.0, false), |(d, on_plane)| (d as f32, on_plane)),
                _ => (0.0, false),
            }
        })
        .collect();
    let mut winner: Vec<u32> = nearest.iter().map(|n| n.1).collect();
    close_gaps(w, &mut depth, &mut winner, |px, k| {
        surface(k, &rays.ray(px)?, true)
            .filter(|s| s.1)
            .map(|s| s.0)
    });
    if options.drop_edges {
        drop_edges(
            w,
            &mut depth,
            &winner,
            |px, k| {
                surface(k, &rays.ray(px)?, false)
                    .filter(|s| s.1)
                    .map(|s| s.0)
            },
            |k| splats[k as usize].half_size_px,
        );
    }
    Ok(DepthMap {
        width: camera.width,
        height: camera.height,
        num_on_tangent_planes: depth.iter().filter(|d| d.1).count(),
        depth_m: depth.into_iter().map(|d| d.0).collect(),
    })
}

/// Closes the gaps between a surface's splats in a depth map `width` pixels
/// wide (`depth`: depth and whether on a plane, 0 where none; `winner`: the
/// splat each pixel's depth comes from): a pixel that sees past a surface
/// (at least 3/4 of the others in its 5 x 5 window see a surface nearer by
/// 10 % or more, or any surface where it sees none; beside a straight edge
/// of a surface in front 10 of 24 do, in a corner of one 15) takes the
/// nearest of those neighbours' surfaces that reaches it (`crossing(pixel,
/// splat)`: the depth of the splat's plane there, `None` where it does not
/// reach), twice (the second pass closes what the first narrowed). Closes
/// one-pixel slits and holes up to about 2 x 2 pixels; wider ones are left
/// (a slit 2 pixels wide: 15 of 24).
fn close_gaps(
    width: usize,
    depth: &mut [(f32, bool)],
    winner: &mut [u32],
    crossing: impl Fn(usize, u32) -> Option<f64> + Sync,
) {
    if width == 0 {
        return;
    }
    let height = depth.len() / width;
    for _ in 0..GAP_PASSES {
        let fill_gap = |px: usize| -> Option<(f32, u32)> {
            let (x, y) = (px % width, px / width);
            let d = depth[px].0;
            let mut front = [0u32; (2 * GAP_WINDOW + 1) * (2 * GAP_WINDOW + 1)];
            let (mut num_front, mut around) = (0usize, 0usize);
            for ny in y.saturating_sub(GAP_WINDOW)..(y + GAP_WINDOW + 1).min(height) {
                for nx in x.saturating_sub(GAP_WINDOW)..(x + GAP_WINDOW + 1).min(width) {
                    let nb = ny * width + nx;
                    if nb == px {
                        continue;
                    }
                    around += 1;
                    let nd = depth[nb].0;
                    if nd > 0.0 && (d == 0.0 || nd < GAP_RATIO * d) {
                        front[num_front] = winner[nb];
                        num_front += 1;
                    }
                }
            }
            if num_front == 0 || (num_front as f64) < MIN_FRONT_SHARE * around as f64 {
                return None;
            }
            let front = &mut front[..num_front];
            front.sort_unstable();
            let mut best: Option<(f64, u32)> = None;
            for (j, &k) in front.iter().enumerate() {
                if j > 0 && front[j - 1] == k {
                    continue;
                }
                let Some(t) = crossing(px, k) else {
                    continue;
                };
                if (d == 0.0 || t < f64::from(d)) && best.is_none_or(|b| t < b.0) {
                    best = Some((t, k));
                }
            }
            best.map(|(t, k)| (t as f32, k))
        };
        let filled: Vec<Option<(f32, u32)>> =
            (0..depth.len()).into_par_iter().map(fill_gap).collect();
        if filled.iter().all(Option::is_none) {
            break;
        }
        for (px, f) in filled.into_iter().enumerate() {
            if let Some((d, k)) = f {
                depth[px] = (d, true);
                winner[px] = k;
            }
        }
    }
}

/// Clears the depth (`depth`, `winner` as for [`close_gaps`]) within the
/// nearer splat's half-size (`half_size(splat)`, pixels) of every step
/// between two neighbouring pixels: one has a depth and the other none, or
/// neither's plane (`plane(pixel, splat)`: the depth of the splat's plane
/// along the pixel's ray, unbounded) passes within [`EDGE_STEP_M`] plus
/// [`EDGE_STEP_SHARE`] of the depth of the other's surface (one surface
/// seen through two splats agrees both ways; across an occluding edge or a
/// corner neither does).
fn drop_edges(
    width: usize,
    depth: &mut [(f32, bool)],
    winner: &[u32],
    plane: impl Fn(usize, u32) -> Option<f64> + Sync,
    half_size: impl Fn(u32) -> f64 + Sync,
) {
    if width == 0 {
        return;
    }
    let height = depth.len() / width;
    let differs = |p: usize, q: usize| -> bool {
        let (dp, dq) = (depth[p].0, depth[q].0);
        if (dp > 0.0) != (dq > 0.0) {
            return true;
        }
        if dp == 0.0 || winner[p] == winner[q] {
            return false;
        }
        let (dp, dq) = (f64::from(dp), f64::from(dq));
        let tolerance = EDGE_STEP_M + EDGE_STEP_SHARE * dp.min(dq);
        let apart = |from: usize, to: usize, d_to: f64| {
            plane(to, winner[from]).is_none_or(|d| (d - d_to).abs() > tolerance)
        };
        apart(p, q, dq) && apart(q, p, dp)
    };
    // Each step: the nearer pixel and how far around it to clear.
    let near = |a: usize| {
        if depth[a].0 > 0.0 {
            depth[a].0
        } else {
            f32::INFINITY
        }
    };
    let steps: Vec<(usize, usize)> = (0..depth.len())
        .into_par_iter()
        .flat_map_iter(|p| {
            let (x, y) = (p % width, p / width);
            let mut found = Vec::new();
            for q in [
                (x + 1 < width).then_some(p + 1),
                (y + 1 < height).then_some(p + width),
            ]
            .into_iter()
            .flatten()
            {
                if differs(p, q) {
                    let nearer = if near(p) <= near(q) { p } else { q };
                    found.push((nearer, half_size(winner[nearer]).ceil().max(1.0) as usize));
                }
            }
            found
        })
        .collect();
    for (p, r) in steps {
        let (x, y) = (p % width, p / width);
        for ny in y.saturating_sub(r)..(y + r + 1).min(height) {
            for nx in x.saturating_sub(r)..(x + r + 1).min(width) {
                depth[ny * width + nx] = (0.0, false);
            }
        }
    }
}

/// A step between surfaces is at least this deep, metres ...
const EDGE_STEP_M: f64 = 0.05;

/// ... plus this share of the nearer depth.
const EDGE_STEP_SHARE: f64 = 0.02;

/// Passes that close gaps between a surface's splats.
const GAP_PASSES: usize = 2;

/// The window a gap is judged in reaches this many pixels either side.
const GAP_WINDOW: usize = 2;

/// Share of the window's other pixels in front that makes a pixel a gap in
/// a surface.
const MIN_FRONT_SHARE: f64 = 0.75;

/// A neighbour is in front when its depth is below this share of the
/// pixel's.
const GAP_RATIO: f32 = 0.9;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::grid::GridOptions;
    use crate::scene::camera::CameraModel;
    use nalgebra::{UnitQuaternion, Vector3};

    /// A wall of points 1 cm apart at z = 4 m in front of the camera, tilted
    /// 60° about the y axis: every pixel that sees it holds the plane's
    /// exact depth (its tangent planes), where the points' own depths are up
    /// to half a splat times tan 60° off.
    #[test]
    fn depth_follows_a_tilted_plane() {
        let camera = Camera {
            id: crate::scene::CameraId(1),
            model: CameraModel::Pinhole,
            width: 200,
            height: 150,
            params: vec![180.0, 180.0, 100.0, 75.0],
        };
        let tilt = 60f64.to_radians();
        let normal = Vector3::new(tilt.sin(), 0.0, -tilt.cos());
        // The plane through (0, 0, 4): n . X = n . (0, 0, 4).
        let offset = normal.dot(&Vector3::new(0.0, 0.0, 4.0));
        let (u, v) = (Vector3::new(tilt.cos(), 0.0, tilt.sin()), Vector3::y());
        let mut points = Vec::new();
        for i in -150..=150 {
            for j in -150..=150 {
                let p = Vector3::new(0.0, 0.0, 4.0) + u * (i as f64 * 0.01) + v * (j as f64 * 0.01);
                points.push(p.map(|c| c as f32).into());
            }
        }
        let cloud = PointCloud {
            origin: Vector3::zeros(),
            normals: Some(vec![normal.map(|c| c as f32).into(); points.len()]),
            points,
            planarity: None,
        };
        let grid = FrustumGrid::build(&cloud, &GridOptions::default()).unwrap();
        let rays = PixelRays::new(&camera);
        let mut options = SurfaceDepthOptions::default();
        options.splats_for_spacing(0.01);
        let pose = Rigid3::new(UnitQuaternion::identity(), Vector3::zeros());
        let render = |options: &SurfaceDepthOptions, kind| {
            render_surface_depth(&cloud, &grid, &camera, &rays, &pose, options, kind, None).unwrap()
        };
        let depth = render(&options, DepthKind::Z);
        let mut own_options = options.clone();
        own_options.max_reach_half_widths = 0.0;
        let own = render(&own_options, DepthKind::Z);
        let range = render(&options, DepthKind::Range);
        let (mut worst, mut worst_own, mut filled, mut inside) = (0f64, 0f64, 0, 0);
        for y in 0..150 {
            for x in 0..200 {
                let i = y * 200 + x;
                let ray = rays.ray(i).unwrap();
                let truth = offset / normal.dot(&ray);
                // Where the ray meets the plane, on the patch's axes.
                let on = truth * ray - Vector3::new(0.0, 0.0, 4.0);
                if on.dot(&u).abs() < 1.45 && on.dot(&v).abs() < 1.45 {
                    inside += 1;
                }
                if depth.depth_m[i] == 0.0 {
                    continue;
                }
                filled += 1;
                worst = worst.max((f64::from(depth.depth_m[i]) - truth).abs());
                worst_own = worst_own.max((f64::from(own.depth_m[i]) - truth).abs());
                let r = f64::from(range.depth_m[i]);
                assert!((r - truth * ray.norm()).abs() < 1e-5 * r, "{r}");
            }
        }
        assert!(inside > 5000 && filled >= inside, "{filled} {inside}");
        assert_eq!(depth.num_on_tangent_planes, filled);
        assert_eq!(own.num_on_tangent_planes, 0);
        assert!(worst < 1e-5, "{worst}");
        // Half a splat (0.8 x 1 cm) times tan 60° is 14 mm; projected on the
        // optical axis about half of that.
        assert!(worst_own > 3e-3, "{worst_own}");
    }

    /// The gap rule on a 12 x 12 map of a surface in front (depth 2, splat
    /// 0) with the one behind (depth 5, splat 1) showing through a 1-pixel
    /// hole, a 2 x 2 hole, an empty pixel, a 3 x 3 hole and beside an edge
    /// (a block 3 wide reaching to the corner): the first three close onto
    /// the front plane, the rest stay.
    #[test]
    fn gaps_close_and_edges_stay() {
        let w = 12;
        let mut depth = vec![(2.0f32, true); w * w];
        let mut winner = vec![0u32; w * w];
        let mut behind = |x: usize, y: usize| {
            depth[y * w + x] = (5.0, true);
            winner[y * w + x] = 1;
        };
        behind(2, 2);
        for (x, y) in [(6, 2), (7, 2), (6, 3), (7, 3)] {
            behind(x, y);
        }
        for x in 2..5 {
            for y in 7..10 {
                behind(x, y);
            }
        }
        for x in 9..12 {
            for y in 6..12 {
                behind(x, y);
            }
        }
        depth[2 * w + 10] = (0.0, false);
        let before = depth.clone();
        close_gaps(w, &mut depth, &mut winner, |_, k| {
            Some(if k == 0 { 2.0 } else { 5.0 })
        });
        for y in 0..w {
            for x in 0..w {
                let closed = (x, y) == (2, 2)
                    || (6..8).contains(&x) && (2..4).contains(&y)
                    || (x, y) == (10, 2);
                let expected = if closed {
                    (2.0, true)
                } else {
                    before[y * w + x]
                };
                assert_eq!(depth[y * w + x], expected, "{x} {y}");
                assert_eq!(winner[y * w + x] == 0, expected.0 == 2.0, "{x} {y}");
            }
        }
        // A neighbour whose plane does not reach closes nothing.
        let mut depth = before.clone();
        let mut winner: Vec<u32> = before.iter().map(|d| u32::from(d.0 != 2.0)).collect();
        close_gaps(w, &mut depth, &mut winner, |_, k| (k == 1).then_some(5.0));
        assert_eq!(depth, before);
    }

    /// A map point in front of a wall with no plane around it leaves its
    /// pixels without a depth, rather than its own or the wall's; a stray
    /// one (nothing near it) is not drawn.
    #[test]
    fn points_without_a_plane_leave_no_depth() {
        let camera = Camera {
            id: crate::scene::CameraId(1),
            model: CameraModel::Pinhole,
            width: 100,
            height: 80,
            params: vec![90.0, 90.0, 50.0, 40.0],
        };
        let mut points: Vec<[f32; 3]> = Vec::new();
        for i in -100..=100 {
            for j in -100..=100 {
                points.push([i as f32 * 0.02, j as f32 * 0.02, 3.0]);
            }
        }
        let stray = points.len();
        points.push([0.0, 0.0, 0.7]);
        let cloud = PointCloud {
            origin: Vector3::zeros(),
            normals: Some(vec![[0.0, 0.0, -1.0]; points.len()]),
            points,
            planarity: None,
        };
        let grid = FrustumGrid::build(&cloud, &GridOptions::default()).unwrap();
        let rays = PixelRays::new(&camera);
        let mut options = SurfaceDepthOptions::default();
        options.splats_for_spacing(0.02);
        let pose = Rigid3::new(UnitQuaternion::identity(), Vector3::zeros());
        let planes = |i: usize| {
            if i == stray {
                MapSurface::NoPlane
            } else {
                MapSurface::Plane(-3.0)
            }
        };
        let render = |planes: Option<SurfaceAt>| {
            render_surface_depth(
                &cloud,
                &grid,
                &camera,
                &rays,
                &pose,
                &options,
                DepthKind::Z,
                planes,
            )
            .unwrap()
        };
        let (with, without) = (render(Some(&planes)), render(None));
        let centre = 40 * 100 + 50;
        assert!((without.depth_m[centre] - 0.7).abs() < 1e-6);
        assert_eq!(with.depth_m[centre], 0.0);
        // The stray point's splat: 0.8 x 2 cm at 0.7 m, 2.06 px either side
        // (4 x 4 pixels: too large a hole to close; one of 2 x 2 would take
        // the wall's depth).
        let empty = with.depth_m.iter().filter(|&&d| d == 0.0).count();
        assert_eq!(empty, 16);
        for (a, b) in with.depth_m.iter().zip(&without.depth_m) {
            let on_wall = |d: f32| (d - 3.0).abs() < 1e-5;
            assert!(*a == 0.0 && (b - 0.7).abs() < 1e-6 || on_wall(*a) && on_wall(*b));
        }
        // A stray point (nothing near it) is not drawn: the wall shows.
        let strays = |i: usize| {
            if i == stray {
                MapSurface::Stray
            } else {
                MapSurface::Plane(-3.0)
            }
        };
        let without_stray = render(Some(&strays));
        assert!(without_stray
            .depth_m
            .iter()
            .all(|&d| (d - 3.0).abs() < 1e-5));
    }

    /// `drop_edges` on a 12 x 6 map: a surface in front (depth 2, splats 0
    /// and 2 alternating, half-size 1.5 px) left of x = 6, one behind (5,
    /// splat 1) right of it, one pixel without a depth: the pixels within
    /// 2 px of the nearer side of each step are cleared (the front's beside
    /// the surface behind, and around the empty pixel), the rest kept; the
    /// two front splats agree and make no step.
    #[test]
    fn edges_are_dropped_beside_steps_only() {
        let (w, h) = (12, 6);
        let mut depth: Vec<(f32, bool)> = (0..w * h)
            .map(|p| if p % w < 6 { (2.0, true) } else { (5.0, true) })
            .collect();
        let winner: Vec<u32> = (0..w * h)
            .map(|p| if p % w < 6 { 2 * (p as u32 % 2) } else { 1 })
            .collect();
        depth[w + 1] = (0.0, false);
        let plane = |_, k: u32| Some(if k == 1 { 5.0 } else { 2.0 });
        drop_edges(w, &mut depth, &winner, plane, |_| 1.5);
        for y in 0..h {
            for x in 0..w {
                // Around the empty pixel's four neighbours, which have a
                // depth (the nearer side of each step).
                let beside_empty = [(2, 1), (1, 2), (0, 1), (1, 0)]
                    .iter()
                    .any(|&(cx, cy): &(usize, usize)| x.abs_diff(cx) <= 2 && y.abs_diff(cy) <= 2);
                let cleared = (3..8).contains(&x) || beside_empty;
                assert_eq!(depth[y * w + x].0 == 0.0, cleared, "{x} {y}");
            }
        }
    }
}
