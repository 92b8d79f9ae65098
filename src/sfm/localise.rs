//! Where in the map a model lies when the initial pose is known only roughly
//! (`map --init-search METRES,DEGREES`).
//!
//! The mapper's own placement has a basin of about 0.5 m and 5 deg around
//! the given initial pose: the initial image's features take their depths
//! from the map seen at that pose, and the early solves tie the model to the
//! surfaces near where it starts. Farther off, the model is built around
//! the wrong surfaces. The search instead takes a model mapped without the
//! map's planes (plain SfM: the initial image at the rough pose and a second
//! image from their essential matrix, at the scale the map's depths at the
//! rough pose suggest, so the rough pose need not see the map; its shape is
//! right up to a similarity) and finds the similarity that puts most of its
//! points on the map:
//!
//! 1. a grid over the heading (a turn about the map's z axis, which is
//!    gravity), the scale and the position of the initial camera within the
//!    region, every placement scored on a few hundred of the points by a
//!    soft count of those near a map plane;
//! 2. the best distinct placements refined by point-to-plane ICP over all
//!    seven parameters ([`super::align`], radii 1 m down to 0.1 m), each
//!    scored by the points within [`super::align::INLIER_M`] of the map;
//! 3. the best one, and up to two others that put at least 90 % as many
//!    points on the map; the mapper maps the database from each and keeps
//!    the finished model that fits the map best (a uniform corridor, a
//!    symmetric room or a repeated facade make two placements fit alike:
//!    that is an error, not a guess).
//!
//! Roll and pitch are left to the ICP: the search assumes the rough pose
//! has them within about 10 deg.
use nalgebra::{Rotation3, UnitQuaternion, Vector3};
use rayon::prelude::*;

use super::align::TRIAL_POINTS;
use super::align::{
    count_points_on_map, every_kth, fit_similarity, mean, nearest_tangent_planes, within_bounds,
    AlignOptions,
};
use super::associate::NearestNeighbourAssociator;
use crate::estimators::similarity::Sim3;

/// Where to search: around the rough initial camera centre and heading.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct SearchRegion {
    /// Horizontal distance from the rough camera centre, metres.
    pub radius_m: f64,
    /// Heading either way from the rough one, degrees (180: any heading).
    pub yaw_deg: f64,
    /// Height either way from the rough camera centre, metres (by default
    /// the radius, at most [`DEFAULT_VERTICAL_M`]).
    pub vertical_m: f64,
}

impl SearchRegion {
    /// Within `radius_m` horizontally and `yaw_deg` of heading, vertically
    /// the default: the radius, at most [`DEFAULT_VERTICAL_M`].
    pub fn around(radius_m: f64, yaw_deg: f64) -> Self {
        Self {
            radius_m,
            yaw_deg,
            vertical_m: radius_m.min(DEFAULT_VERTICAL_M),
        }
    }

    /// Parses `METRES,DEGREES[,VERTICAL_METRES]`.
    pub fn parse(s: &str) -> Result<Self, String> {
        let parts: Vec<&str> = s.split(',').map(str::trim).collect();
        let (m, d, v) = match parts.as_slice() {
            [m, d] => (*m, *d, None),
            [m, d, v] => (*m, *d, Some(*v)),
            _ => {
                return Err(format!(
                    "expected METRES,DEGREES or METRES,DEGREES,VERTICAL_METRES (e.g. 2,30 or 2,30,1.5), got `{s}` ({} values)",
                    parts.len()
                ))
            }
        };
        let parse = |v: &str, what: &str| -> Result<f64, String> {
            v.parse::<f64>()
                .ok()
                .filter(|x| x.is_finite() && *x >= 0.0)
                .ok_or_else(|| format!("{what} must be a number >= 0, got `{v}`"))
        };
        let mut region = Self::around(
            parse(m, "the radius (metres)")?,
            parse(d, "the heading range (degrees)")?.min(180.0),
        );
        if let Some(v) = v {
            region.vertical_m = parse(v, "the vertical range (metres)")?;
        }
        for (what, metres) in [
            ("radius", region.radius_m),
            ("vertical range", region.vertical_m),
        ] {
            if metres > MAX_RADIUS_M {
                return Err(format!(
                    "a {what} of {metres} m is more than this search covers ({MAX_RADIUS_M} m): give a rough pose within that of the true one"
                ));
            }
        }
        Ok(region)
    }
}

/// The largest radius (and vertical range) [`SearchRegion::parse`]
/// accepts: the grid grows with the radius' square.
pub const MAX_RADIUS_M: f64 = 10.0;

/// The vertical range when none is given: photos taken by hand or from a
/// vehicle are at about the height a rough pose says, within a metre.
pub const DEFAULT_VERTICAL_M: f64 = 1.0;

/// Options of [`search_placement`].
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct SearchOptions {
    /// Grid step of the position, metres (about half the ICP's basin at its
    /// first radius, 1 m).
    pub step_m: f64,
    /// Grid step of the heading, degrees.
    pub step_deg: f64,
    /// Scales from 1/`max_scale` to `max_scale`, in steps of the factor
    /// `scale_step`: the plain model's scale comes from the map's depths at
    /// the rough pose (measured 0.69 of the true one from 1.5 m / 20 deg
    /// off on the seed-0 yard, 1/2.71 on the CI yard from 1.3 m / 15 deg).
    pub max_scale: f64,
    pub scale_step: f64,
    /// Points each grid placement is scored on.
    pub grid_points: usize,
    /// Best distinct grid placements refined by ICP, and at least as many
    /// of every tilt and scale.
    pub candidates: usize,
    pub candidates_per_scale: usize,
    /// Distinct placements that put more than this share of the best one's
    /// count of points on the map are mapped too, at most `max_contenders`
    /// in all (the shared CI yard: the right placement 2808 of 3373 points,
    /// a wrong one 0.96 m away 2577; a uniform corridor: wrong ones up to
    /// 1.04 times the right one's count).
    pub max_runner_up_share: f64,
    pub max_contenders: usize,
    /// The kept placement must put at least this share of the points on the
    /// map (within [`super::align::INLIER_M`]).
    pub min_on_map_share: f64,
    /// The ICP's radii and the radius at which the refined placements'
    /// points are counted on the map are at least this, metres: on a sparse
    /// map [`SPARSE_MAP_RADIUS_PER_SPACING`] times its spacing (a point on a
    /// surface sampled every 20 cm is often farther than the ICP's finest
    /// 0.1 m from every sample of it). Default 0 (the ICP's own radii).
    pub min_radius_m: f64,
}

/// [`SearchOptions::min_radius_m`] per unit of the map's spacing: a point
/// on a jittered grid of spacing `s` is within about `0.8 s` of a sample.
/// A map of 6.6 cm spacing or finer keeps the ICP's radii.
pub const SPARSE_MAP_RADIUS_PER_SPACING: f64 = 1.5;

impl Default for SearchOptions {
    fn default() -> Self {
        Self {
            step_m: 0.5,
            step_deg: 5.0,
            max_scale: 4.0,
            scale_step: 1.15,
            grid_points: 256,
            candidates: 16,
            candidates_per_scale: 2,
            max_runner_up_share: 0.9,
            max_contenders: 3,
            min_on_map_share: 0.3,
            min_radius_m: 0.0,
        }
    }
}

/// What [`search_placement`] found (in `report.json` as `init_search`).
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct SearchRecord {
    pub region: SearchRegion,
    /// Grid placements scored.
    pub placements: usize,
    /// Points of the plain model, and how many the refined placements were
    /// counted on.
    pub num_points: usize,
    pub num_checked: usize,
    /// Of those, on the map at the kept placement and at the best other one.
    pub on_map: usize,
    pub runner_up_on_map: Option<usize>,
    /// The placements mapped (the best and those close to it): the points
    /// on the map at each, and the mapped model's fit (`fit_share`; `None`
    /// when that run failed; a model refused as too loosely held by the
    /// map keeps its fit). The first is the one kept.
    pub contenders_on_map: Vec<usize>,
    pub contender_fits: Vec<Option<f64>>,
    /// How far the cameras' right-hand axes levelled the model (degrees;
    /// searched besides the rough pose's roll and pitch), if at all.
    pub levelling_deg: Option<f64>,
    /// Where the kept placement puts the initial camera's centre (map frame).
    pub found_centre: [f64; 3],
    /// How the kept placement moved the initial camera from its rough pose:
    /// centre, metres; rotation, degrees; and the plain model's scale.
    pub moved_m: f64,
    pub turned_deg: f64,
    pub scale: f64,
    /// The plain run's start: its second image, paired with the initial one
    /// by their essential matrix, and the metres per unit of their baseline
    /// that the map's depths at the rough pose gave.
    pub plain_second_image: u32,
    pub plain_pair_scale: Option<f64>,
    /// The pair's baseline in the finished plain model (its units; `scale`
    /// times this is the pair's baseline in the map). The plain run's
    /// solves hold it only softly, so it may differ from
    /// `plain_pair_scale`: the seed-0 yard from 1.3 m / 15 deg off moved
    /// it by 8 % on one database and not on another.
    pub plain_pair_baseline: Option<f64>,
    /// Wall time of the plain run and of the search, seconds.
    pub plain_run_s: f64,
    pub search_s: f64,
    /// When the search was not asked for but followed a run from the given
    /// pose that failed (`bundle.fallback_search_m`): that run's error and
    /// wall time, seconds (its held retry included).
    pub after_failure: Option<String>,
    pub first_run_s: Option<f64>,
    /// The kept model is one the map holds only loosely (it would have been
    /// refused) and the photos' GPS positions placed it (GPS placements).
    pub kept_by_positions: bool,
}

/// Why the search found no placement.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum SearchError {
    #[error("the model mapped without the map's planes has only {0} 3D points")]
    TooFewPoints(usize),
    #[error(
        "no placement within {:.1} m and {:.0} deg of the rough initial pose puts more than {:.0} % of the model's points on the map (best {on_map} of {checked}): is the rough pose in the map's frame, and does the map cover what the photos show?",
        region.radius_m, region.yaw_deg, min_share * 100.0
    )]
    NoFit {
        region: SearchRegion,
        on_map: usize,
        checked: usize,
        min_share: f64,
    },
    #[error(
        "placements {:.1} m apart fit the map about equally even mapped from each ({:.1} % and {:.1} % of the points on the map; the initial camera at {} and at {}): the map cannot tell them apart (a uniform corridor, a symmetric room); give a closer rough pose or a smaller --init-search",
        distance(best_centre, other_centre), best_fit * 100.0, other_fit * 100.0,
        fmt_xyz(best_centre), fmt_xyz(other_centre)
    )]
    Ambiguous {
        best_fit: f64,
        other_fit: f64,
        best_centre: [f64; 3],
        other_centre: [f64; 3],
    },
}

fn distance(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f64>().sqrt()
}

fn fmt_xyz(x: &[f64; 3]) -> String {
    format!("({:.2}, {:.2}, {:.2})", x[0], x[1], x[2])
}

/// A placement of the grid: the model turned by `yaw` about the map's z
/// axis and scaled by `scale`, both about the pivot, and moved by `shift`.
#[derive(Clone, Copy, Debug)]
struct Placement {
    /// Applied first: the identity or the levelling ([`levelling`]).
    tilt: UnitQuaternion<f64>,
    yaw_rad: f64,
    scale: f64,
    shift: Vector3<f64>,
    /// Its tilt and scale (an index).
    group: usize,
}

impl Placement {
    fn sim3(&self, pivot: &Vector3<f64>) -> Sim3 {
        // x' = pivot + shift + s R (x - pivot).
        let rotation =
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), self.yaw_rad) * self.tilt;
        Sim3 {
            scale: self.scale,
            rotation,
            translation: pivot + self.shift - self.scale * (rotation * pivot),
        }
    }
}

/// The turn that levels a model whose cameras were held level: their
/// right-hand axes (`right_axes`, in the model's frame) are horizontal, so
/// the model's up is the direction most nearly orthogonal to all of them
/// (the least eigenvector of their scatter; when they all point one way,
/// only the tilt about that way is found and the rest kept). `None` when
/// that up is within 1 deg of the model's z axis (nothing to level) or more
/// than [`MAX_LEVELLING_DEG`] from it (portrait photos, or cameras held
/// askew: the rough pose's roll and pitch are kept then).
fn levelling(right_axes: &[Vector3<f64>]) -> Option<UnitQuaternion<f64>> {
    if right_axes.len() < 2 {
        return None;
    }
    let scatter: nalgebra::Matrix3<f64> = right_axes.iter().map(|x| x * x.transpose()).sum();
    let eigen = scatter.symmetric_eigen();
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eigen.eigenvalues[a].total_cmp(&eigen.eigenvalues[b]));
    let z = Vector3::z();
    let [least, _, most] = order.map(|i| eigen.eigenvectors.column(i).into_owned());
    let spread = eigen.eigenvalues[order[1]] / eigen.eigenvalues[order[2]].max(1e-12);
    let up = if spread >= MIN_HEADING_SPREAD {
        least
    } else {
        // One heading: the up is orthogonal to it, nearest the model's z.
        z - most * most.dot(&z)
    };
    let up = up.try_normalize(1e-9)?;
    let up = if up.dot(&z) < 0.0 { -up } else { up };
    let angle = up.dot(&z).clamp(-1.0, 1.0).acos().to_degrees();
    (1.0..=MAX_LEVELLING_DEG)
        .contains(&angle)
        .then(|| UnitQuaternion::rotation_between(&up, &z))
        .flatten()
}

/// The most [`levelling`] may turn the model's up.
pub const MAX_LEVELLING_DEG: f64 = 20.0;
/// The share of the right-hand axes' scatter across their main direction
/// from which they fix the up in both tilts (cameras facing at least two
/// ways about 25 deg apart).
const MIN_HEADING_SPREAD: f64 = 0.05;

/// Values from `-half` to `half` in steps of at most `step`, 0 among them.
fn symmetric_grid(half: f64, step: f64) -> Vec<f64> {
    let n = (half / step).ceil() as i64;
    if n <= 0 {
        return vec![0.0];
    }
    let step = half / n as f64;
    (-n..=n).map(|k| k as f64 * step).collect()
}

/// The heading grid: a full turn without its repeated end for 180 deg.
fn yaw_grid(half_deg: f64, step_deg: f64) -> Vec<f64> {
    if half_deg >= 180.0 {
        let n = (360.0 / step_deg).ceil() as i64;
        let step = 360.0 / n as f64;
        return (0..n)
            .map(|k| (k as f64 * step - 180.0).to_radians())
            .collect();
    }
    symmetric_grid(half_deg, step_deg)
        .into_iter()
        .map(f64::to_radians)
        .collect()
}

/// How well `points` (already placed) lie on the map, given the tangent
/// plane nearest each within `2 tol` (`planes`, [`nearest_tangent_planes`]):
/// each point near a map plane counts `1 - (e / tol)^2` at a distance `e`
/// below `tol`.
fn soft_score(points: &[Vector3<f64>], planes: &[Option<(Vector3<f64>, f64)>], tol: f64) -> f64 {
    points
        .iter()
        .zip(planes)
        .filter_map(|(y, plane)| {
            let (n, d) = (*plane)?;
            let e = (n.dot(y) - d) / tol;
            (e.abs() < 1.0).then_some(1.0 - e * e)
        })
        .sum()
}

/// The similarities (`map_from_model`) that put most of `points` (a model
/// mapped without the map's planes, its initial camera at `pivot` where the
/// rough pose put it; `right_axes` its cameras' x axes) on the map, searched
/// within `region`, from the rough pose's roll and pitch and from the
/// model [`levelling`]; and the search's record (its times left at 0 for the
/// caller).
pub fn search_placement(
    points: &[Vector3<f64>],
    right_axes: &[Vector3<f64>],
    pivot: &Vector3<f64>,
    nearest: &NearestNeighbourAssociator,
    region: &SearchRegion,
    options: &SearchOptions,
) -> Result<Search, SearchError> {
    if points.len() < 50 {
        return Err(SearchError::TooFewPoints(points.len()));
    }
    // 1. The grid.
    let grid_points = every_kth(points, options.grid_points);
    let offsets: Vec<Vector3<f64>> = grid_points.iter().map(|x| x - pivot).collect();
    let yaws = yaw_grid(region.yaw_deg, options.step_deg);
    let n_scale = (options.max_scale.ln() / options.scale_step.ln()).ceil() as i64;
    let scales: Vec<f64> = (-n_scale..=n_scale)
        .map(|k| options.scale_step.powi(k as i32))
        .collect();
    let horizontal = symmetric_grid(region.radius_m, options.step_m);
    let vertical = symmetric_grid(region.vertical_m, options.step_m);
    let shifts: Vec<Vector3<f64>> = horizontal
        .iter()
        .flat_map(|&x| horizontal.iter().map(move |&y| (x, y)))
        .filter(|(x, y)| x.hypot(*y) <= region.radius_m + 1e-9)
        .flat_map(|(x, y)| vertical.iter().map(move |&z| Vector3::new(x, y, z)))
        .collect();
    let tol = options.step_m / 2.0;
    let level = levelling(right_axes);
    let tilts: Vec<UnitQuaternion<f64>> = std::iter::once(UnitQuaternion::identity())
        .chain(level)
        .collect();
    let mut turns: Vec<(UnitQuaternion<f64>, f64, f64, usize)> = Vec::new();
    for (t, &tilt) in tilts.iter().enumerate() {
        for &yaw in &yaws {
            turns.extend(
                scales
                    .iter()
                    .enumerate()
                    .map(|(k, &s)| (tilt, yaw, s, t * scales.len() + k)),
            );
        }
    }
    // Scores in a fixed order (the output does not depend on the threads).
    let scored: Vec<(f64, Placement)> = turns
        .par_iter()
        .flat_map_iter(|&(tilt, yaw_rad, scale, group)| {
            let r = Rotation3::from_axis_angle(&Vector3::z_axis(), yaw_rad) * tilt;
            let turned: Vec<Vector3<f64>> = offsets.iter().map(|o| scale * (r * o)).collect();
            // Every shift of this turn in one batch of map lookups.
            let placed: Vec<Vector3<f64>> = shifts
                .iter()
                .flat_map(|shift| turned.iter().map(move |o| pivot + shift + o))
                .collect();
            let planes = nearest_tangent_planes(nearest, &placed, 2.0 * tol);
            let n = turned.len();
            shifts
                .iter()
                .enumerate()
                .map(|(k, shift)| {
                    let at = k * n..(k + 1) * n;
                    (
                        soft_score(&placed[at.clone()], &planes[at], tol),
                        Placement {
                            tilt,
                            yaw_rad,
                            scale,
                            shift: *shift,
                            group,
                        },
                    )
                })
                .collect::<Vec<_>>()
        })
        .collect();
    let placements = scored.len();
    log::debug!(
        "levelling {:?} deg; {placements} placements",
        level.map(|q| q.angle().to_degrees())
    );

    // 2. The best distinct placements, refined.
    let mut order: Vec<usize> = (0..scored.len()).collect();
    order.sort_by(|&a, &b| scored[b].0.total_cmp(&scored[a].0).then(a.cmp(&b)));
    let near = |a: &Placement, b: &Placement| {
        a.tilt == b.tilt
            && (a.shift - b.shift).abs().max() <= options.step_m + 1e-9
            && angle_between(a.yaw_rad, b.yaw_rad) <= options.step_deg.to_radians() + 1e-9
            && (a.scale / b.scale).ln().abs() <= options.scale_step.ln() + 1e-9
    };
    // The best over all, and the best of every tilt and scale: the soft
    // count favours a model shrunk onto one surface (a 24-image yard from a
    // pose 14 deg off in tilt: all 16 best at scales 0.38-0.57 against the
    // true 1.1), so each scale has its own candidates and the ICP's count at
    // 2 cm decides.
    let mut picked: Vec<Placement> = Vec::new();
    let mut per_group = vec![0usize; tilts.len() * scales.len()];
    for i in order {
        let p = scored[i].1;
        let group = &mut per_group[p.group];
        let wanted = picked.len() < options.candidates || *group < options.candidates_per_scale;
        if wanted && !picked.iter().any(|q| near(q, &p)) {
            picked.push(p);
            *group += 1;
        }
    }
    let checked = every_kth(points, TRIAL_POINTS);
    let mut align = AlignOptions::default();
    for r in &mut align.radii_m {
        *r = r.max(options.min_radius_m);
    }
    align.radii_m.dedup();
    let finest = align.finest_radius_m();
    // A refinement that moves far from its start has collapsed the model
    // onto a plane or a corner (every point on the ground at a scale near
    // 0, measured on the yard): it is no placement (the alignment's bounds,
    // [`within_bounds`]).
    let refined: Vec<(usize, Sim3)> = picked
        .par_iter()
        .filter_map(|p| {
            let start = p.sim3(pivot);
            let sim3 = fit_similarity(&checked, nearest, &align, start);
            let placed: Vec<Vector3<f64>> =
                checked.iter().map(|x| sim3.transform_point(x)).collect();
            let started: Vec<Vector3<f64>> =
                checked.iter().map(|x| start.transform_point(x)).collect();
            let step = sim3.compose(&start.inverse());
            let shift = (mean(&placed) - mean(&started)).norm();
            log::debug!(
                "candidate tilt {:.0} yaw {:.0} deg, scale {:.3}, shift {:?}: refined by scale {:.3}, {:.1} deg, {shift:.2} m",
                p.tilt.angle().to_degrees(),
                p.yaw_rad.to_degrees(),
                p.scale,
                p.shift.as_slice(),
                step.scale,
                step.rotation.angle().to_degrees()
            );
            within_bounds(&step, shift, 1.0)
                .then(|| (count_points_on_map(nearest, &placed, finest), sim3))
        })
        .collect();
    for (i, (n, sim3)) in refined.iter().enumerate() {
        log::debug!(
            "placement {i}: {n} of {} points on the map; camera at {:?}, scale {:.3}",
            checked.len(),
            sim3.transform_point(pivot).as_slice(),
            sim3.scale
        );
    }

    // 3. The best, and the others that come close to it.
    let (best_i, &(on_map, best)) = refined
        .iter()
        .enumerate()
        .max_by(|(i, a), (j, b)| a.0.cmp(&b.0).then(j.cmp(i)))
        .unwrap_or((0, &(0, Sim3::identity())));
    let min_points = (options.min_on_map_share * checked.len() as f64).ceil() as usize;
    if on_map < min_points.max(7) {
        return Err(SearchError::NoFit {
            region: *region,
            on_map,
            checked: checked.len(),
            min_share: options.min_on_map_share,
        });
    }
    let best_centre = best.transform_point(pivot);
    let differs = |s: &Sim3| !same_placement(s, &best, pivot);
    let runner_up = refined
        .iter()
        .enumerate()
        .filter(|(i, (_, s))| *i != best_i && differs(s))
        .max_by(|(i, a), (j, b)| a.0.cmp(&b.0).then(j.cmp(i)))
        .map(|(_, r)| *r);
    // Others that come close: mapped too, and the map's fit decides
    // ([`crate::sfm::run_mapper_searching`]).
    let mut others: Vec<(usize, Sim3)> = refined
        .iter()
        .enumerate()
        .filter(|(i, (n, s))| {
            *i != best_i && differs(s) && *n as f64 > options.max_runner_up_share * on_map as f64
        })
        .map(|(_, r)| *r)
        .collect();
    others.sort_by_key(|o| std::cmp::Reverse(o.0));
    let mut contenders = vec![(on_map, best)];
    for (n, s) in others {
        if contenders.len() < options.max_contenders
            && contenders.iter().all(|c| !same_placement(&s, &c.1, pivot))
        {
            contenders.push((n, s));
        }
    }
    let record = SearchRecord {
        region: *region,
        placements,
        num_points: points.len(),
        num_checked: checked.len(),
        on_map,
        runner_up_on_map: runner_up.map(|r| r.0),
        contenders_on_map: contenders.iter().map(|c| c.0).collect(),
        contender_fits: Vec::new(),
        levelling_deg: level.map(|q| q.angle().to_degrees()),
        found_centre: [best_centre.x, best_centre.y, best_centre.z],
        moved_m: (best_centre - pivot).norm(),
        turned_deg: best.rotation.angle().to_degrees(),
        scale: best.scale,
        plain_second_image: 0,
        plain_pair_scale: None,
        plain_pair_baseline: None,
        plain_run_s: 0.0,
        search_s: 0.0,
        after_failure: None,
        first_run_s: None,
        kept_by_positions: false,
    };
    Ok(Search { contenders, record })
}

/// What [`search_placement`] found: the best placement first, then those
/// that came within [`SearchOptions::max_runner_up_share`] of it (the
/// points on the map and `map_from_model` of each).
#[derive(Clone, Debug)]
pub struct Search {
    pub contenders: Vec<(usize, Sim3)>,
    pub record: SearchRecord,
}

/// Whether two placements (`map_from_model`) are one: the initial camera
/// (at `pivot` in the model) within [`SAME_PLACE_M`], the turns within
/// [`SAME_TURN_DEG`] and the scales within [`SAME_SCALE`] (refined starts
/// that met).
fn same_placement(a: &Sim3, b: &Sim3, pivot: &Vector3<f64>) -> bool {
    (a.transform_point(pivot) - b.transform_point(pivot)).norm() <= SAME_PLACE_M
        && (a.rotation.inverse() * b.rotation).angle().to_degrees() <= SAME_TURN_DEG
        && (a.scale / b.scale).ln().abs() <= SAME_SCALE
}

/// Refined placements closer than these are one: initial camera centre,
/// metres; turn, degrees; log of the scale ratio. The mapper also counts two
/// mapped models' initial cameras within `SAME_PLACE_M` as one place.
pub(crate) const SAME_PLACE_M: f64 = 0.1;
const SAME_TURN_DEG: f64 = 1.0;
const SAME_SCALE: f64 = 0.01;

/// The angle between two headings, radians, in [0, pi].
fn angle_between(a: f64, b: f64) -> f64 {
    let d = (a - b).rem_euclid(std::f64::consts::TAU);
    d.min(std::f64::consts::TAU - d)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::map::index::MapIndex;
    use crate::sfm::align::tests::{box_room, room_map};
    use crate::sfm::options::AssociationOptions;

    #[test]
    fn region_parsing() {
        assert_eq!(
            SearchRegion::parse("2,30"),
            Ok(SearchRegion {
                radius_m: 2.0,
                yaw_deg: 30.0,
                vertical_m: 1.0,
            })
        );
        assert_eq!(SearchRegion::parse("0.5,10").unwrap().vertical_m, 0.5);
        assert_eq!(SearchRegion::parse("3,10, 2.5").unwrap().vertical_m, 2.5);
        assert_eq!(SearchRegion::parse("3,10,0").unwrap().vertical_m, 0.0);
        assert_eq!(SearchRegion::parse(" 1.5 , 400 ").unwrap().yaw_deg, 180.0);
        for bad in [
            "2", "2,30,1,1", "-1,30", "x,30", "nan,30", "2,inf", "11,30", "2,30,-1", "2,30,11",
            "2,30,",
        ] {
            assert!(SearchRegion::parse(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn grids() {
        assert_eq!(symmetric_grid(1.0, 0.5), vec![-1.0, -0.5, 0.0, 0.5, 1.0]);
        assert_eq!(symmetric_grid(0.0, 0.5), vec![0.0]);
        // 0.7 in steps of at most 0.5: two steps of 0.35.
        assert_eq!(symmetric_grid(0.7, 0.5).len(), 5);
        assert_eq!(yaw_grid(180.0, 5.0).len(), 72);
        assert_eq!(yaw_grid(30.0, 5.0).len(), 13);
        assert!((angle_between(3.1, -3.1) - (std::f64::consts::TAU - 6.2)).abs() < 1e-12);
    }

    /// The room's points turned 25 deg, scaled by 0.7 about a pivot and
    /// moved 1.3 m: the search finds the inverse exactly (no ambiguity in a
    /// 6 x 4 m room within +-40 deg).
    #[test]
    fn a_model_far_off_is_found_in_the_room() {
        let region = SearchRegion::parse("2,40").unwrap();
        find_in_room(&Vector3::new(1.0, -0.8, 0.2), &region);
    }

    /// Moved 1.7 m down and 0.4 m sideways: found with a vertical range of
    /// 2 m, whose grid has 9 heights (in steps of 0.5 m) at each of the 13
    /// positions within 1 m, for each of 17 headings (+-40 deg in 5 deg
    /// steps) and 21 scales (1.15^-10 to 1.15^10).
    #[test]
    fn a_model_far_below_is_found_with_a_vertical_range() {
        let region = SearchRegion::parse("1,40,2").unwrap();
        assert_eq!(region.vertical_m, 2.0);
        let record = find_in_room(&Vector3::new(0.3, 0.25, -1.7), &region);
        assert_eq!(record.placements, 13 * 9 * 17 * 21);
    }

    /// The room's points turned 25 deg, scaled by 0.7 about a pivot and
    /// moved by `shift`, searched for within `region`: the inverse, exactly.
    fn find_in_room(shift: &Vector3<f64>, region: &SearchRegion) -> SearchRecord {
        let (cloud, on_map) = room_map();
        let index = MapIndex::build(&cloud).unwrap();
        let nearest =
            NearestNeighbourAssociator::new(&cloud, &index, AssociationOptions::default());
        let pivot_true = Vector3::new(1.5, 2.0, 1.4);
        let truth = Placement {
            tilt: UnitQuaternion::identity(),
            yaw_rad: 25f64.to_radians(),
            scale: 0.7,
            shift: *shift,
            group: 0,
        }
        .sim3(&pivot_true);
        let model: Vec<Vector3<f64>> = on_map.iter().map(|x| truth.transform_point(x)).collect();
        let pivot = truth.transform_point(&pivot_true);
        let Search { contenders, record } = search_placement(
            &model,
            &[],
            &pivot,
            &nearest,
            region,
            &SearchOptions::default(),
        )
        .expect("found");
        assert_eq!(contenders.len(), 1);
        let found = contenders[0].1;
        let back = found.compose(&truth);
        assert!((back.scale - 1.0).abs() < 1e-6, "scale {}", back.scale);
        assert!(back.rotation.angle() < 1e-6, "{}", back.rotation.angle());
        assert!((back.transform_point(&pivot_true) - pivot_true).norm() < 1e-5);
        assert_eq!(record.on_map, record.num_checked);
        assert!((record.scale - 1.0 / 0.7).abs() < 1e-5);
        assert!(
            (record.turned_deg - 25.0).abs() < 1e-4,
            "{}",
            record.turned_deg
        );
        assert!((record.moved_m - (pivot_true - pivot).norm()).abs() < 1e-5);
        record
    }

    /// A square room turned by a quarter turn is the same room: with any
    /// heading allowed the search cannot choose and says so.
    #[test]
    fn a_symmetric_room_has_contenders_with_any_heading() {
        let (cloud, on_map) = square_room();
        let index = MapIndex::build(&cloud).unwrap();
        let nearest =
            NearestNeighbourAssociator::new(&cloud, &index, AssociationOptions::default());
        let pivot = Vector3::new(2.0, 2.0, 1.5);
        let within = |yaw_deg: f64| {
            let region = SearchRegion {
                radius_m: 0.5,
                yaw_deg,
                vertical_m: 0.5,
            };
            search_placement(
                &on_map,
                &[],
                &pivot,
                &nearest,
                &region,
                &SearchOptions::default(),
            )
            .expect("found")
        };
        let search = within(180.0);
        // The quarter turns about the room's centre fit as well: at most
        // three are mapped, each a distinct turn of the same count.
        assert_eq!(search.contenders.len(), 3);
        let turns: Vec<UnitQuaternion<f64>> = search
            .contenders
            .iter()
            .map(|(n, s)| {
                assert_eq!(*n, on_map.len());
                assert!((s.transform_point(&pivot) - pivot).norm() < 1e-5);
                assert!((s.scale - 1.0).abs() < 1e-6);
                s.rotation
            })
            .collect();
        for (i, a) in turns.iter().enumerate() {
            let deg = a.angle().to_degrees();
            assert!(
                [0.0, 90.0, 180.0].iter().any(|t| (deg - t).abs() < 1e-4),
                "{deg}"
            );
            assert!((a.inverse() * Vector3::z() - Vector3::z()).norm() < 1e-6);
            for b in &turns[..i] {
                assert!((a.inverse() * b).angle().to_degrees() > 1.0);
            }
        }
        assert_eq!(search.record.contenders_on_map, vec![on_map.len(); 3]);
        // Within +-30 deg the quarter turns are out of reach.
        let search = within(30.0);
        assert_eq!(search.contenders.len(), 1);
        assert!((search.contenders[0].1.transform_point(&pivot) - pivot).norm() < 1e-5);
    }

    /// Level cameras at several headings, seen in a frame tilted 12 deg:
    /// the levelling undoes the tilt; facing one way, it undoes only the
    /// part about that way; beyond 20 deg (portrait photos) nothing.
    #[test]
    fn levelling_from_the_cameras_right_hand_axes() {
        let tilt = UnitQuaternion::from_euler_angles(0.15, -0.14, 0.3);
        let rights = |yaws: &[f64]| -> Vec<Vector3<f64>> {
            yaws.iter()
                .map(|y: &f64| tilt * Vector3::new(y.cos(), y.sin(), 0.0))
                .collect()
        };
        let level = levelling(&rights(&[0.0, 0.7, 1.9, 3.0])).expect("levelled");
        assert!((level * tilt * Vector3::z() - Vector3::z()).norm() < 1e-9);
        // One heading: the up found is orthogonal to it.
        let one = rights(&[0.4, 0.4]);
        let level = levelling(&one).expect("levelled");
        assert!((level * one[0]).z.abs() < 1e-9);
        // Already level, or too far from it.
        let flat: Vec<Vector3<f64>> = [0.0f64, 1.0, 2.0]
            .iter()
            .map(|y| Vector3::new(y.cos(), y.sin(), 0.0))
            .collect();
        assert_eq!(levelling(&flat), None);
        let portrait: Vec<Vector3<f64>> = [0.0f64, 1.0, 2.0]
            .iter()
            .map(|y| Vector3::new(0.1 * y.cos(), 0.1 * y.sin(), 1.0).normalize())
            .collect();
        assert_eq!(levelling(&portrait), None);
    }

    /// Points nowhere near the map: no placement fits.
    #[test]
    fn a_model_off_the_map_is_refused() {
        let (cloud, on_map) = room_map();
        let index = MapIndex::build(&cloud).unwrap();
        let nearest =
            NearestNeighbourAssociator::new(&cloud, &index, AssociationOptions::default());
        let far: Vec<Vector3<f64>> = on_map
            .iter()
            .map(|x| x + Vector3::new(40.0, 0.0, 0.0))
            .collect();
        let region = SearchRegion::parse("1,10").unwrap();
        let err = search_placement(
            &far,
            &[],
            &Vector3::new(43.0, 2.0, 1.5),
            &nearest,
            &region,
            &SearchOptions::default(),
        )
        .unwrap_err();
        assert!(matches!(err, SearchError::NoFit { on_map: 0, .. }), "{err}");
        assert_eq!(
            search_placement(
                &on_map[..10],
                &[],
                &Vector3::zeros(),
                &nearest,
                &region,
                &SearchOptions::default()
            )
            .unwrap_err(),
            SearchError::TooFewPoints(10)
        );
    }

    /// A 4 x 4 x 3 m room (floor and ceiling, four walls, 4 cm spacing)
    /// and a sparse set of points on it.
    fn square_room() -> (crate::map::PointCloud, Vec<Vector3<f64>>) {
        box_room([4.0, 4.0, 3.0], 0.04, |i, j| i % 11 == 3 && j % 7 == 2)
    }
}
