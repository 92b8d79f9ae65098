//! Evaluation of a reconstruction against reference (ground-truth) poses.
//!
//! Images are matched by name. Errors per image: camera-centre distance
//! (metres) and rotation angle of `R_est * R_ref^T` (degrees), after an
//! optional alignment of the model to the reference:
//! * `none`: the model is compared as is (the honest comparison for a tool
//!   that outputs poses in the map frame);
//! * `sim3`: the best similarity (Umeyama, least squares over camera centres)
//!   is applied first (the best case for scale-free SfM).
//!
//! The best Sim3 scale is always reported (with >= 3 registered images), as is
//! the scale drift: the ratio of Sim3 scales fitted to the last and the first
//! third of the registered images (reference name order).
use std::collections::BTreeMap;
use std::path::PathBuf;

use nalgebra::{Matrix3, Vector3};
use serde::Serialize;

use crate::scene::Rigid3;

pub mod intrinsics;
pub mod map_agreement;
pub mod model_poses;

pub use model_poses::load_poses;

#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    #[error("{path}: {message}")]
    Model { path: PathBuf, message: String },
    #[error("Sim3 alignment needs at least 3 registered images with distinct centres, got {0}")]
    TooFewForSim3(usize),
}

/// How the model is aligned to the reference before errors are measured.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Alignment {
    None,
    Sim3,
}

/// A similarity `x_b = scale * R * x_a + t`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sim3 {
    pub scale: f64,
    pub rotation: Matrix3<f64>,
    pub translation: Vector3<f64>,
}

impl Sim3 {
    pub fn identity() -> Self {
        Self {
            scale: 1.0,
            rotation: Matrix3::identity(),
            translation: Vector3::zeros(),
        }
    }

    pub fn transform_point(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.scale * (self.rotation * p) + self.translation
    }

    /// A `cam_from_a` pose expressed as `cam_from_b` (b = this transform's target frame).
    pub fn transform_pose(&self, cam_from_a: &Rigid3) -> Rigid3 {
        let r = cam_from_a.rotation_matrix() * self.rotation.transpose();
        let centre = self.transform_point(&cam_from_a.camera_center());
        Rigid3::from_rotation_matrix(&r, -(r * centre))
    }
}

/// Least-squares similarity mapping `src[i]` onto `dst[i]` (Umeyama 1991).
/// `None` with fewer than 3 pairs or degenerate (collinear or coincident) input.
pub fn umeyama(src: &[Vector3<f64>], dst: &[Vector3<f64>]) -> Option<Sim3> {
    let n = src.len();
    if n < 3 || dst.len() != n {
        return None;
    }
    let mean = |v: &[Vector3<f64>]| v.iter().sum::<Vector3<f64>>() / n as f64;
    let (ms, md) = (mean(src), mean(dst));
    let mut cov = Matrix3::zeros();
    let mut var_src = 0.0;
    for (s, d) in src.iter().zip(dst) {
        let (a, b) = (s - ms, d - md);
        cov += b * a.transpose();
        var_src += a.norm_squared();
    }
    cov /= n as f64;
    var_src /= n as f64;
    if var_src < 1e-18 {
        return None;
    }
    let svd = cov.svd(true, true);
    let (u, v_t) = (svd.u?, svd.v_t?);
    let sv = svd.singular_values;
    // Rank check: collinear points leave the rotation about the line free.
    let mut order = [0usize, 1, 2];
    order.sort_by(|&i, &j| sv[j].total_cmp(&sv[i]));
    if sv[order[1]] < 1e-12 * sv[order[0]].max(1e-300) {
        return None;
    }
    let mut d = Matrix3::identity();
    if (u * v_t).determinant() < 0.0 {
        // Flip the axis of the smallest singular value.
        d[(order[2], order[2])] = -1.0;
    }
    let rotation = u * d * v_t;
    let trace_ds: f64 = (0..3).map(|i| d[(i, i)] * sv[i]).sum();
    let scale = trace_ds / var_src;
    let translation = md - scale * (rotation * ms);
    Some(Sim3 {
        scale,
        rotation,
        translation,
    })
}

/// Median, 90th percentile (nearest rank) and maximum.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Stats {
    pub median: f64,
    pub p90: f64,
    pub max: f64,
}

impl Stats {
    pub fn of(values: &[f64]) -> Option<Self> {
        if values.is_empty() {
            return None;
        }
        let mut v = values.to_vec();
        v.sort_by(f64::total_cmp);
        let n = v.len();
        let median = if n % 2 == 1 {
            v[n / 2]
        } else {
            0.5 * (v[n / 2 - 1] + v[n / 2])
        };
        let rank = ((0.9 * n as f64).ceil() as usize).clamp(1, n);
        Some(Self {
            median,
            p90: v[rank - 1],
            max: v[n - 1],
        })
    }
}

/// Errors of one registered image.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ImageError {
    pub name: String,
    pub centre_error_m: f64,
    pub rotation_error_deg: f64,
}

/// Share of all reference images within a centre and a rotation threshold.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ThresholdShare {
    pub centre_m: f64,
    pub rotation_deg: f64,
    pub count: usize,
    pub share: f64,
}

/// The thresholds reported, (metres, degrees).
pub const THRESHOLDS: [(f64, f64); 3] = [(0.02, 0.1), (0.05, 0.5), (0.10, 1.0)];

/// Result of [`evaluate`].
#[derive(Clone, Debug, Serialize)]
pub struct EvaluationReport {
    pub alignment: Alignment,
    pub num_reference: usize,
    pub num_registered: usize,
    pub registered_share: f64,
    /// Model images absent from the reference (ignored).
    pub num_unknown: usize,
    /// Scale of the best Sim3 from the model to the reference.
    pub sim3_scale: Option<f64>,
    /// That similarity itself.
    #[serde(skip)]
    pub sim3: Option<Sim3>,
    /// Sim3 scale on the last third over the first third (1 = no drift).
    pub scale_drift: Option<f64>,
    pub centre_error_m: Option<Stats>,
    pub rotation_error_deg: Option<Stats>,
    pub within: Vec<ThresholdShare>,
    pub images: Vec<ImageError>,
    /// Errors over the uncertainties the model reported for itself (see
    /// [`EvaluationReport::errors_over`]).
    pub error_over_sigma: Option<ErrorOverSigma>,
    /// The same over the model's cluster-robust sigmas.
    pub error_over_clustered_sigma: Option<ErrorOverSigma>,
    /// The model's error split into where it is placed as a whole and its
    /// shape (with at least 3 registered images with distinct centres).
    pub placement: Option<Placement>,
    /// Per model camera, its focal length against the reference's (filled
    /// by the caller from the two models' cameras; see
    /// [`intrinsics::focal_errors`]).
    pub focal_lengths: Vec<intrinsics::FocalError>,
}

/// A model's error as a whole: the best similarity from the model to the
/// reference (least squares over camera centres) read as the model's
/// placement error, and what remains after it (the shape error). For a tool
/// whose model is placed by a map, the first is what the map fixed, the
/// second what the images did.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Placement {
    /// Where the model's mean camera centre lies relative to where the
    /// reference puts that point, metres, the reference's axes.
    pub shift_m: [f64; 3],
    /// The model's rotation relative to the reference as a rotation vector,
    /// degrees (its length is the angle).
    pub rotation_deg: [f64; 3],
    /// The model's size over the reference's (1: right).
    pub scale: f64,
    /// Camera-centre errors after the best similarity, metres.
    pub shape_error_m: Stats,
}

impl Placement {
    /// The placement of a model whose best similarity onto the reference
    /// is `to_reference`; `model_centres` are its registered camera centres,
    /// `shape_errors` their errors after that similarity.
    fn of(
        to_reference: &Sim3,
        model_centres: &[Vector3<f64>],
        shape_errors: &[f64],
    ) -> Option<Self> {
        let shape_error_m = Stats::of(shape_errors)?;
        let centroid = model_centres.iter().sum::<Vector3<f64>>() / model_centres.len() as f64;
        let shift = centroid - to_reference.transform_point(&centroid);
        // The model is turned by R^T and scaled by 1 / s against the reference.
        let turn = nalgebra::Rotation3::from_matrix_unchecked(to_reference.rotation.transpose())
            .scaled_axis()
            .map(f64::to_degrees);
        Some(Self {
            shift_m: shift.into(),
            rotation_deg: turn.into(),
            scale: 1.0 / to_reference.scale,
            shape_error_m,
        })
    }
}

/// One image's reported uncertainty (one sigma): the camera centre along its
/// least determined direction, metres, and the rotation about its least
/// determined axis, degrees.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ReportedSigma {
    pub centre_m: f64,
    pub rotation_deg: f64,
}

/// Errors divided by the reported sigmas over the images that have both.
/// The centre ratio is the error vector's length over the sigma of the least
/// determined direction: with calibrated sigmas its median lies between 0.67
/// (one direction dominates) and 1.54 (three equal ones).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct ErrorOverSigma {
    pub count: usize,
    pub centre: Stats,
    pub rotation: Stats,
}

/// Compares `model` to `reference` (both name -> `cam_from_world`).
pub fn evaluate(
    model: &BTreeMap<String, Rigid3>,
    reference: &BTreeMap<String, Rigid3>,
    alignment: Alignment,
) -> Result<EvaluationReport, EvalError> {
    let common: Vec<(&String, &Rigid3, &Rigid3)> = reference
        .iter()
        .filter_map(|(name, r)| model.get(name).map(|m| (name, m, r)))
        .collect();
    let src: Vec<Vector3<f64>> = common.iter().map(|(_, m, _)| m.camera_center()).collect();
    let dst: Vec<Vector3<f64>> = common.iter().map(|(_, _, r)| r.camera_center()).collect();
    let best = umeyama(&src, &dst);
    let third = common.len() / 3;
    let scale_drift = if third >= 3 {
        let n = common.len();
        match (
            umeyama(&src[..third], &dst[..third]),
            umeyama(&src[n - third..], &dst[n - third..]),
        ) {
            (Some(a), Some(b)) => Some(b.scale / a.scale),
            _ => None,
        }
    } else {
        None
    };
    let align = match alignment {
        Alignment::None => Sim3::identity(),
        Alignment::Sim3 => best.ok_or(EvalError::TooFewForSim3(common.len()))?,
    };
    let images: Vec<ImageError> = common
        .iter()
        .map(|(name, m, r)| {
            let aligned = align.transform_pose(m);
            let centre_error_m = (aligned.camera_center() - r.camera_center()).norm();
            let rotation_error_deg = aligned.rotation.angle_to(&r.rotation).to_degrees();
            ImageError {
                name: (*name).clone(),
                centre_error_m,
                rotation_error_deg,
            }
        })
        .collect();
    let n_ref = reference.len();
    let share = |k: usize| {
        if n_ref == 0 {
            0.0
        } else {
            k as f64 / n_ref as f64
        }
    };
    let within = THRESHOLDS
        .iter()
        .map(|&(c, r)| {
            let count = images
                .iter()
                .filter(|e| e.centre_error_m <= c && e.rotation_error_deg <= r)
                .count();
            ThresholdShare {
                centre_m: c,
                rotation_deg: r,
                count,
                share: share(count),
            }
        })
        .collect();
    let centres: Vec<f64> = images.iter().map(|e| e.centre_error_m).collect();
    let rotations: Vec<f64> = images.iter().map(|e| e.rotation_error_deg).collect();
    let placement = best.and_then(|sim| {
        let shape: Vec<f64> = src
            .iter()
            .zip(&dst)
            .map(|(m, r)| (sim.transform_point(m) - r).norm())
            .collect();
        Placement::of(&sim, &src, &shape)
    });
    Ok(EvaluationReport {
        alignment,
        num_reference: n_ref,
        num_registered: common.len(),
        registered_share: share(common.len()),
        num_unknown: model.keys().filter(|k| !reference.contains_key(*k)).count(),
        sim3_scale: best.map(|s| s.scale),
        sim3: best,
        scale_drift,
        centre_error_m: Stats::of(&centres),
        rotation_error_deg: Stats::of(&rotations),
        within,
        images,
        error_over_sigma: None,
        error_over_clustered_sigma: None,
        placement,
        focal_lengths: Vec::new(),
    })
}

impl EvaluationReport {
    /// The errors over the model's own sigmas (by image name; images
    /// without a positive, finite sigma are skipped); `None` without any.
    pub fn errors_over(&self, sigmas: &BTreeMap<String, ReportedSigma>) -> Option<ErrorOverSigma> {
        let mut centre = Vec::new();
        let mut rotation = Vec::new();
        for e in &self.images {
            let Some(s) = sigmas.get(&e.name) else {
                continue;
            };
            let ok = |v: f64| v.is_finite() && v > 0.0;
            if ok(s.centre_m) && ok(s.rotation_deg) {
                centre.push(e.centre_error_m / s.centre_m);
                rotation.push(e.rotation_error_deg / s.rotation_deg);
            }
        }
        match (Stats::of(&centre), Stats::of(&rotation)) {
            (Some(c), Some(r)) => Some(ErrorOverSigma {
                count: centre.len(),
                centre: c,
                rotation: r,
            }),
            _ => None,
        }
    }

    /// A human-readable table.
    pub fn table(&self) -> String {
        let mut s = String::new();
        let opt =
            |v: Option<f64>, p: usize| v.map(|x| format!("{x:.p$}")).unwrap_or_else(|| "-".into());
        s += &format!("alignment            {:?}\n", self.alignment).to_lowercase();
        s += &format!(
            "registered           {} / {} ({:.1} %)\n",
            self.num_registered,
            self.num_reference,
            100.0 * self.registered_share
        );
        if self.num_unknown > 0 {
            s += &format!("not in reference     {}\n", self.num_unknown);
        }
        s += &format!("sim3 scale           {}\n", opt(self.sim3_scale, 6));
        s += &format!("scale drift          {}\n", opt(self.scale_drift, 4));
        s += "                     median       p90          max\n";
        if let (Some(c), Some(r)) = (self.centre_error_m, self.rotation_error_deg) {
            s += &format!(
                "centre error (m)     {:<12.4} {:<12.4} {:.4}\n",
                c.median, c.p90, c.max
            );
            s += &format!(
                "rotation error (deg) {:<12.4} {:<12.4} {:.4}\n",
                r.median, r.p90, r.max
            );
        }
        for (label, ratio) in [
            ("error / own sigma   ", &self.error_over_sigma),
            ("error / clustered s.", &self.error_over_clustered_sigma),
        ] {
            if let Some(e) = ratio {
                s += &format!(
                    "{label} {:<12.2} {:<12.2} {:.2}   (centre; {} images)\n",
                    e.centre.median, e.centre.p90, e.centre.max, e.count
                );
                s += &format!(
                    "                     {:<12.2} {:<12.2} {:.2}   (rotation)\n",
                    e.rotation.median, e.rotation.p90, e.rotation.max
                );
            }
        }
        if let (Some(p), Alignment::None) = (&self.placement, self.alignment) {
            let [x, y, z] = p.shift_m.map(|v| 1e3 * v);
            let angle = Vector3::from(p.rotation_deg).norm();
            s += &format!(
                "placement error      {:.2} mm (x {x:.2} y {y:.2} z {z:.2}) at the cameras' centroid, {angle:.4} deg, scale {:.6}\n",
                Vector3::new(x, y, z).norm(),
                p.scale
            );
            s += &format!(
                "shape error (m)      {:<12.4} {:<12.4} {:.4}   (centres after the best sim3)\n",
                p.shape_error_m.median, p.shape_error_m.p90, p.shape_error_m.max
            );
        }
        s += &intrinsics::focal_table(&self.focal_lengths);
        for t in &self.within {
            s += &format!(
                "within {:>3.0} cm {:>4.1} deg  {} / {} ({:.1} %)\n",
                t.centre_m * 100.0,
                t.rotation_deg,
                t.count,
                self.num_reference,
                100.0 * t.share
            );
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, UnitQuaternion};

    fn reference() -> BTreeMap<String, Rigid3> {
        (0..10)
            .map(|i| {
                let f = i as f64;
                let r = UnitQuaternion::from_euler_angles(0.1 * f, -0.05 * f, 0.3 + 0.2 * f);
                let centre = Vector3::new(f, 0.3 * f * f, 1.0 + (f * 0.7).sin());
                (
                    format!("im{i:02}.jpg"),
                    Rigid3::from_rotation_and_center(r, &centre),
                )
            })
            .collect()
    }

    /// Moves image `name`'s camera centre by `delta`, keeping its rotation.
    fn move_centre(model: &mut BTreeMap<String, Rigid3>, name: &str, delta: Vector3<f64>) {
        let pose = model[name];
        let centre = pose.camera_center() + delta;
        model.insert(
            name.into(),
            Rigid3::from_rotation_and_center(pose.rotation, &centre),
        );
    }

    #[test]
    fn errors_over_reported_sigmas() {
        let reference = reference();
        let mut model = reference.clone();
        // im01 moved 3 mm along x; im02 turned 0.02 deg.
        move_centre(&mut model, "im01.jpg", Vector3::new(0.003, 0.0, 0.0));
        let r2 = reference["im02.jpg"];
        let turned =
            r2.rotation * UnitQuaternion::from_euler_angles(0.02f64.to_radians(), 0.0, 0.0);
        let c2 = r2.camera_center();
        model.insert(
            "im02.jpg".into(),
            Rigid3::from_rotation_and_center(turned, &c2),
        );
        let mut report = evaluate(&model, &reference, Alignment::None).unwrap();
        assert!(report.error_over_sigma.is_none());
        assert!(report.errors_over(&BTreeMap::new()).is_none());
        let sigma = |c: f64, r: f64| ReportedSigma {
            centre_m: c,
            rotation_deg: r,
        };
        let sigmas: BTreeMap<String, ReportedSigma> = [
            ("im01.jpg".to_string(), sigma(0.001, 0.01)),
            ("im02.jpg".to_string(), sigma(0.002, 0.01)),
            ("im03.jpg".to_string(), sigma(f64::NAN, 0.01)),
            ("not_there.jpg".to_string(), sigma(0.001, 0.01)),
        ]
        .into();
        report.error_over_sigma = report.errors_over(&sigmas);
        let e = report.error_over_sigma.expect("two images");
        assert_eq!(e.count, 2);
        // Centres: 3 mm / 1 mm and 0 / 2 mm; rotations: 0 and 0.02 / 0.01 deg.
        assert!((e.centre.max - 3.0).abs() < 1e-6, "{e:?}");
        assert!((e.centre.median - 1.5).abs() < 1e-6, "{e:?}");
        assert!((e.rotation.max - 2.0).abs() < 1e-6, "{e:?}");
        assert!((e.rotation.median - 1.0).abs() < 1e-6, "{e:?}");
        assert!(report.table().contains("error / own sigma"));
    }

    /// The model is the reference moved by `(scale, rotation about the
    /// reference's mean centre, shift)`.
    fn moved(
        reference: &BTreeMap<String, Rigid3>,
        scale: f64,
        rotation: Rotation3<f64>,
        shift: Vector3<f64>,
    ) -> BTreeMap<String, Rigid3> {
        let n = reference.len() as f64;
        let c = reference
            .values()
            .map(|r| r.camera_center())
            .sum::<Vector3<f64>>()
            / n;
        let t = Sim3 {
            scale,
            rotation: *rotation.matrix(),
            translation: c - scale * (rotation * c) + shift,
        };
        reference
            .iter()
            .map(|(k, r)| (k.clone(), t.transform_pose(r)))
            .collect()
    }

    #[test]
    fn placement_of_a_moved_model() {
        let reference = reference();
        let placement = |model: &BTreeMap<String, Rigid3>| {
            evaluate(model, &reference, Alignment::None)
                .unwrap()
                .placement
                .expect("10 images")
        };
        // Shifted by (1, -2, 0.5) mm: the shift, nothing else.
        let shift = Vector3::new(0.001, -0.002, 0.0005);
        let p = placement(&moved(&reference, 1.0, Rotation3::identity(), shift));
        assert!((Vector3::from(p.shift_m) - shift).norm() < 1e-12, "{p:?}");
        assert!(Vector3::from(p.rotation_deg).norm() < 1e-9, "{p:?}");
        assert!(
            (p.scale - 1.0).abs() < 1e-12 && p.shape_error_m.max < 1e-12,
            "{p:?}"
        );
        // Turned 0.01 deg about z through the mean centre and 2e-4 too large:
        // no shift at the centroid.
        let turn = Rotation3::from_axis_angle(&Vector3::z_axis(), 0.01f64.to_radians());
        let p = placement(&moved(&reference, 1.0002, turn, Vector3::zeros()));
        assert!(Vector3::from(p.shift_m).norm() < 1e-12, "{p:?}");
        let r = Vector3::from(p.rotation_deg);
        assert!((r - Vector3::new(0.0, 0.0, 0.01)).norm() < 1e-9, "{r}");
        assert!(
            (p.scale - 1.0002).abs() < 1e-12 && p.shape_error_m.max < 1e-12,
            "{p:?}"
        );
        // One camera of ten moved 3 cm: that is shape, mostly.
        let mut model = reference.clone();
        move_centre(&mut model, "im04.jpg", Vector3::new(0.0, 0.0, 0.03));
        let rep = evaluate(&model, &reference, Alignment::None).unwrap();
        let p = rep.placement.unwrap();
        assert!(
            p.shape_error_m.max > 0.02 && p.shape_error_m.max < 0.03,
            "{p:?}"
        );
        assert!(rep.table().contains("placement error") && rep.table().contains("shape error"));
        // Not printed after a sim3 alignment (it is the alignment itself).
        let rep = evaluate(&model, &reference, Alignment::Sim3).unwrap();
        assert!(!rep.table().contains("placement error"));
    }

    #[test]
    fn umeyama_recovers_known_similarity() {
        let truth = Sim3 {
            scale: 2.5,
            rotation: *Rotation3::from_euler_angles(0.3, -1.0, 2.0).matrix(),
            translation: Vector3::new(5e5, 4.4e6, 200.0),
        };
        let src: Vec<Vector3<f64>> = (0..7)
            .map(|i| Vector3::new(i as f64, (i * i) as f64 * 0.1, (i as f64).cos()))
            .collect();
        let dst: Vec<Vector3<f64>> = src.iter().map(|p| truth.transform_point(p)).collect();
        let est = umeyama(&src, &dst).unwrap();
        assert!((est.scale - 2.5).abs() < 1e-9);
        assert!((est.rotation - truth.rotation).norm() < 1e-9);
        assert!((est.translation - truth.translation).norm() < 1e-6);
        // Collinear points: undetermined rotation.
        let line: Vec<Vector3<f64>> = (0..5).map(|i| Vector3::new(i as f64, 0.0, 0.0)).collect();
        assert!(umeyama(&line, &line).is_none());
        assert!(umeyama(&src[..2], &dst[..2]).is_none());
    }

    #[test]
    fn stats_by_hand() {
        let s = Stats::of(&[5.0, 1.0, 3.0, 2.0, 4.0, 6.0, 7.0, 8.0, 9.0, 10.0]).unwrap();
        assert_eq!(
            s,
            Stats {
                median: 5.5,
                p90: 9.0,
                max: 10.0
            }
        );
        let s = Stats::of(&[3.0]).unwrap();
        assert_eq!(
            s,
            Stats {
                median: 3.0,
                p90: 3.0,
                max: 3.0
            }
        );
        assert!(Stats::of(&[]).is_none());
    }

    #[test]
    fn known_errors_without_alignment() {
        let reference = reference();
        let mut model = reference.clone();
        // Shift one camera centre by 3 cm.
        move_centre(&mut model, "im02.jpg", Vector3::new(0.0, 0.03, 0.0));
        // Rotate another by 0.2 deg about its own optical axis, keeping its centre.
        let p = model["im05.jpg"];
        let c = p.camera_center();
        let r =
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.2f64.to_radians()) * p.rotation;
        model.insert("im05.jpg".into(), Rigid3::from_rotation_and_center(r, &c));
        // Drop one and add one the reference does not know.
        model.remove("im09.jpg");
        model.insert("extra.jpg".into(), Rigid3::identity());
        let rep = evaluate(&model, &reference, Alignment::None).unwrap();
        assert_eq!(
            (rep.num_reference, rep.num_registered, rep.num_unknown),
            (10, 9, 1)
        );
        assert!((rep.registered_share - 0.9).abs() < 1e-12);
        let e2 = rep.images.iter().find(|e| e.name == "im02.jpg").unwrap();
        assert!((e2.centre_error_m - 0.03).abs() < 1e-9 && e2.rotation_error_deg < 1e-6);
        let e5 = rep.images.iter().find(|e| e.name == "im05.jpg").unwrap();
        assert!(e5.centre_error_m < 1e-9 && (e5.rotation_error_deg - 0.2).abs() < 1e-6);
        // 7 exact images; im02 fails (2 cm, 0.1 deg) but passes (5 cm, 0.5 deg); im05 fails only 0.1 deg.
        let counts: Vec<usize> = rep.within.iter().map(|t| t.count).collect();
        assert_eq!(counts, vec![7, 9, 9]);
        assert!((rep.within[0].share - 0.7).abs() < 1e-12);
        let c = rep.centre_error_m.unwrap();
        assert!(c.median < 1e-9 && (c.max - 0.03).abs() < 1e-9);
    }

    #[test]
    fn scaled_model_sim3_gives_zero_error_and_scale() {
        let reference = reference();
        // The model is the reference in another frame, scaled by 2.
        let model_from_ref = Sim3 {
            scale: 2.0,
            rotation: *Rotation3::from_euler_angles(0.2, 0.1, -0.7).matrix(),
            translation: Vector3::new(3.0, -1.0, 0.5),
        };
        let model: BTreeMap<String, Rigid3> = reference
            .iter()
            .map(|(k, p)| (k.clone(), model_from_ref.transform_pose(p)))
            .collect();
        let rep = evaluate(&model, &reference, Alignment::Sim3).unwrap();
        assert!((rep.sim3_scale.unwrap() - 0.5).abs() < 1e-9);
        assert!((rep.scale_drift.unwrap() - 1.0).abs() < 1e-9);
        assert!(rep.centre_error_m.unwrap().max < 1e-9);
        assert!(rep.rotation_error_deg.unwrap().max < 1e-6);
        assert_eq!(rep.within[0].count, 10);
        // Without alignment the same model is far off.
        let rep = evaluate(&model, &reference, Alignment::None).unwrap();
        assert!(rep.centre_error_m.unwrap().median > 0.5);
        assert_eq!(rep.within[2].count, 0);
        assert!((rep.sim3_scale.unwrap() - 0.5).abs() < 1e-9);
    }

    #[test]
    fn sim3_needs_three_images() {
        let reference = reference();
        let model: BTreeMap<String, Rigid3> = reference
            .iter()
            .take(2)
            .map(|(k, v)| (k.clone(), *v))
            .collect();
        assert!(matches!(
            evaluate(&model, &reference, Alignment::Sim3),
            Err(EvalError::TooFewForSim3(2))
        ));
        let rep = evaluate(&model, &reference, Alignment::None).unwrap();
        assert_eq!(rep.num_registered, 2);
        assert!(rep.sim3_scale.is_none());
    }
}
