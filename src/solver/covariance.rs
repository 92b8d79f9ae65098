//! Pose uncertainty at a bundle-adjustment solution: the covariance of each
//! variable pose with every point (and any free intrinsics) marginalised,
//! and of each camera's free intrinsics with the points marginalised.
//!
//! The bridge returns the Jacobian `J` (robust losses applied as the solver
//! applies them). With the points first, the normal matrix
//! `H = J^T J = [[Hpp, Hpc], [Hcp, Hcc]]` has a 3x3 block per point in `Hpp`,
//! so the reduced camera matrix `S = Hcc - Hcp Hpp^-1 Hpc` is built point by
//! point and inverted densely; `S^-1`'s diagonal blocks are the poses'
//! covariances in units of the residuals' variance. A point whose own block
//! is singular (one view, no plane) uses the pseudo-inverse: the directions
//! it cannot fix carry no information to the cameras, as they should.
//!
//! The result is the usual first-order (Gauss-Newton) covariance with the
//! associations held fixed, scaled by the residual variance the fit itself
//! estimates (`sum r^2 / (rows - columns)`). It says how well the data fix
//! each pose under the solve's own noise model; a systematic error of the
//! map or the features is not in it.
//!
//! [`clustered_pose_covariances`] gives beside it the cluster-robust
//! ("sandwich") estimate `S^-1 M S^-1`: `M` sums the outer products of each
//! cluster's gradient `J^T r` with its points eliminated, so residuals that
//! err together within a cluster count by their joint pull, as the data
//! show it, not by their number.
use nalgebra::{DMatrix, Matrix3, Matrix6, Vector3};

use super::bridge;
use super::options::SolverOptions;
use super::problem::BundleAdjustmentProblem;
use super::SolverError;

/// Column block kinds, as the bridge numbers them.
const BLOCK_POINT: u32 = 0;
const BLOCK_POSE_ROTATION: u32 = 1;
const BLOCK_POSE_TRANSLATION: u32 = 2;
const BLOCK_CAMERA: u32 = 3;

/// Covariances of the variable poses and intrinsics of a problem.
#[derive(Clone, Debug)]
pub struct PoseCovariances {
    /// Per pose of the problem (same index): the 6x6 covariance of
    /// `[rotation, centre]`, where the rotation is the world-frame rotation
    /// vector of `world_from_cam` (radians) and the centre is in the
    /// problem's frame (metres); already scaled by `residual_variance`.
    /// `None` for constant poses and poses without residuals.
    pub poses: Vec<Option<Matrix6<f64>>>,
    /// The same from [`clustered_pose_covariances`] (the cluster-robust
    /// estimate, not scaled by `residual_variance`); empty otherwise.
    pub clustered_poses: Vec<Option<Matrix6<f64>>>,
    /// Per camera of the problem (same index): the covariance of its
    /// variable intrinsics, in the model's parameter order with the
    /// constant ones left out (pixels squared for focal lengths), scaled by
    /// `residual_variance`. `None` for a camera whose intrinsics are all
    /// constant or that no residual touches.
    pub cameras: Vec<Option<DMatrix<f64>>>,
    /// The same from [`clustered_pose_covariances`]; empty otherwise.
    pub clustered_cameras: Vec<Option<DMatrix<f64>>>,
    /// Variance of a unit-weight residual, estimated from the fit
    /// (pixels squared for reprojections).
    pub residual_variance: f64,
    /// Residual rows minus the parameter directions the data fix (a point's
    /// unfixed directions do not count).
    pub redundancy: usize,
    /// Points whose own 3x3 information was rank deficient.
    pub num_degenerate_points: usize,
}

impl PoseCovariances {
    /// Standard deviations of the camera centre along the frame's axes, metres.
    pub fn centre_sigma_m(&self, pose: usize) -> Option<Vector3<f64>> {
        let c = self.poses.get(pose)?.as_ref()?;
        Some(Vector3::new(c[(3, 3)], c[(4, 4)], c[(5, 5)]).map(sigma_of_variance))
    }

    /// The camera centre's covariance, square metres.
    pub fn centre_covariance(&self, pose: usize) -> Option<Matrix3<f64>> {
        block(&self.poses, pose, 3)
    }

    /// The rotation's covariance (world-frame rotation vector), square radians.
    pub fn rotation_covariance(&self, pose: usize) -> Option<Matrix3<f64>> {
        block(&self.poses, pose, 0)
    }

    /// The cluster-robust camera centre covariance, square metres.
    pub fn clustered_centre_covariance(&self, pose: usize) -> Option<Matrix3<f64>> {
        block(&self.clustered_poses, pose, 3)
    }

    /// The cluster-robust rotation covariance, square radians.
    pub fn clustered_rotation_covariance(&self, pose: usize) -> Option<Matrix3<f64>> {
        block(&self.clustered_poses, pose, 0)
    }
}

/// The 3x3 diagonal block from row and column `at` of pose `pose`'s covariance.
fn block(poses: &[Option<Matrix6<f64>>], pose: usize, at: usize) -> Option<Matrix3<f64>> {
    let c = poses.get(pose)?.as_ref()?;
    Some(c.fixed_view::<3, 3>(at, at).into_owned())
}

/// Square root of a variance; NaN (not 0) for a negative or NaN one.
pub fn sigma_of_variance(v: f64) -> f64 {
    if v >= 0.0 {
        v.sqrt()
    } else {
        f64::NAN
    }
}

/// Why no covariance could be computed.
#[derive(Debug, thiserror::Error)]
pub enum CovarianceError {
    #[error(transparent)]
    Solver(#[from] SolverError),
    /// The reduced camera matrix is singular: some pose direction is not
    /// fixed at all (a free gauge).
    #[error("the poses are not fully determined (free gauge): no covariance")]
    Singular,
    /// As many parameters as residuals: the residual variance is unknown.
    #[error("no redundancy ({rows} residuals for {cols} parameters)")]
    NoRedundancy { rows: usize, cols: usize },
    /// The cluster-robust estimate needs at least two clusters.
    #[error("{0} cluster(s) of residuals: the cluster-robust covariance needs at least 2")]
    TooFewClusters(usize),
    /// The bridge returned a layout this code does not expect.
    #[error("unexpected Jacobian layout: {0}")]
    Layout(String),
}

/// Pose covariances of `problem` at its current parameters (normally a
/// solution), with `options`' robust losses. Dense in the camera side: the
/// caller bounds its size.
pub fn pose_covariances(
    problem: &BundleAdjustmentProblem,
    options: &SolverOptions,
) -> Result<PoseCovariances, CovarianceError> {
    covariances(problem, options, None)
}

/// Cluster-robust ("sandwich") pose covariances: `S^-1 M S^-1`, where `M`
/// sums, over clusters of points, the outer product of each cluster's
/// gradient with its points eliminated (`point_cluster[i]`: the cluster of
/// point `i`; rows without a point are clusters of one row each), times
/// `G / (G - 1)` for `G` clusters. Where the residuals of a cluster's points
/// err together (the map's noise shared by neighbouring points, a feature
/// bias common to a surface), this is what the data's own scatter says;
/// with independent residuals it agrees with [`pose_covariances`] on
/// average. The result holds both: `poses` as [`pose_covariances`] gives
/// them, `clustered_poses` the sandwich.
pub fn clustered_pose_covariances(
    problem: &BundleAdjustmentProblem,
    options: &SolverOptions,
    point_cluster: &[u32],
) -> Result<PoseCovariances, CovarianceError> {
    if point_cluster.len() != problem.points.len() {
        return Err(CovarianceError::Layout(format!(
            "{} clusters for {} points",
            point_cluster.len(),
            problem.points.len()
        )));
    }
    covariances(problem, options, Some(point_cluster))
}

fn covariances(
    problem: &BundleAdjustmentProblem,
    options: &SolverOptions,
    point_cluster: Option<&[u32]>,
) -> Result<PoseCovariances, CovarianceError> {
    let jac = bridge::jacobian(problem, options)?;
    let rows = jac.num_rows as usize;
    let cols = jac.num_cols as usize;
    let layout = |what: String| CovarianceError::Layout(what);
    if jac.row_starts.len() != rows + 1 || jac.residuals.len() != rows {
        return Err(layout(format!(
            "{} row starts, {} residuals for {rows} rows",
            jac.row_starts.len(),
            jac.residuals.len()
        )));
    }
    // Column ranges of the blocks; points must come first, 3 columns each.
    let mut start = 0usize;
    let mut num_point_cols = 0usize;
    let mut pose_cols: Vec<[Option<usize>; 2]> = vec![[None, None]; problem.poses.len()];
    // Per camera: its first column (after the points) and its size.
    let mut camera_cols: Vec<Option<(usize, usize)>> = vec![None; problem.cameras.len()];
    for ((&kind, &index), &size) in jac
        .block_kind
        .iter()
        .zip(&jac.block_index)
        .zip(&jac.block_size)
    {
        let index = index as usize;
        match kind {
            BLOCK_POINT => {
                if size != 3 || start != num_point_cols {
                    return Err(layout("point blocks must lead, 3 columns each".into()));
                }
                num_point_cols += 3;
            }
            BLOCK_POSE_ROTATION | BLOCK_POSE_TRANSLATION => {
                if size != 3 || index >= pose_cols.len() {
                    return Err(layout(format!("pose block {index} of size {size}")));
                }
                pose_cols[index][(kind - BLOCK_POSE_ROTATION) as usize] =
                    Some(start - num_point_cols);
            }
            BLOCK_CAMERA => {
                if index >= camera_cols.len() {
                    return Err(layout(format!(
                        "camera block {index} of {}",
                        camera_cols.len()
                    )));
                }
                camera_cols[index] = Some((start - num_point_cols, size as usize));
            }
            _ => {}
        }
        start += size as usize;
    }
    if start != cols {
        return Err(layout(format!("blocks cover {start} of {cols} columns")));
    }
    let num_points = num_point_cols / 3;
    let nc = cols - num_point_cols;

    // Accumulate Hcc (dense), Hpp (3x3 per point) and Hpc (sparse per point).
    let mut hcc = DMatrix::<f64>::zeros(nc, nc);
    let mut hpp = vec![Matrix3::<f64>::zeros(); num_points];
    // Per point and camera column: Hpc's 3 entries and the camera side of
    // the gradient J^T r (only used for the clustered covariance).
    let mut hpc: Vec<Vec<(usize, Vector3<f64>, f64)>> = vec![Vec::new(); num_points];
    // The point side of the gradient, and the gradient of each row without
    // a point; only for the clustered covariance.
    let clustered = point_cluster.is_some();
    let mut grad_point = vec![Vector3::<f64>::zeros(); if clustered { num_points } else { 0 }];
    let mut grad_lone: Vec<Vec<(usize, f64)>> = Vec::new();
    let mut cam: Vec<(usize, f64)> = Vec::new();
    for r in 0..rows {
        let (begin, end) = (jac.row_starts[r] as usize, jac.row_starts[r + 1] as usize);
        let mut jp = Vector3::zeros();
        let mut point = None;
        cam.clear();
        for k in begin..end {
            let c = jac.cols[k] as usize;
            let v = jac.values[k];
            if c < num_point_cols {
                if point.is_some_and(|p| p != c / 3) {
                    return Err(layout(format!("row {r} touches two points")));
                }
                point = Some(c / 3);
                jp[c % 3] = v;
            } else {
                cam.push((c - num_point_cols, v));
            }
        }
        for &(a, va) in &cam {
            for &(b, vb) in &cam {
                hcc[(a, b)] += va * vb;
            }
        }
        let res = jac.residuals[r];
        if let Some(p) = point {
            hpp[p] += jp * jp.transpose();
            if clustered {
                grad_point[p] += jp * res;
            }
            for &(a, va) in &cam {
                let entry = &mut hpc[p];
                match entry.iter_mut().find(|(col, _, _)| *col == a) {
                    Some((_, acc, grad)) => {
                        *acc += jp * va;
                        *grad += va * res;
                    }
                    None => entry.push((a, jp * va, va * res)),
                }
            }
        } else if clustered {
            grad_lone.push(cam.iter().map(|&(a, va)| (a, va * res)).collect());
        }
    }
    // Eliminate the points: S = Hcc - sum_p Hcp Hpp^+ Hpc.
    let mut num_degenerate_points = 0;
    let mut rank_deficit = 0;
    // Each cluster's reduced gradient z = g_c - Hcp Hpp^+ g_p, sparse.
    let mut cluster_grad: std::collections::BTreeMap<u32, Vec<(usize, f64)>> =
        std::collections::BTreeMap::new();
    for (p, (h, b)) in hpp.iter().zip(&hpc).enumerate() {
        let (inv, rank) = pseudo_inverse(h);
        if rank < 3 {
            num_degenerate_points += 1;
            rank_deficit += 3 - rank;
        }
        if let Some(clusters) = point_cluster {
            // Entries pushed as they come; merged per column below.
            let moved = inv * grad_point[p];
            let z = cluster_grad.entry(clusters[p]).or_default();
            z.extend(b.iter().map(|(a, va, grad)| (*a, grad - va.dot(&moved))));
        }
        if b.is_empty() {
            continue;
        }
        let w: Vec<Vector3<f64>> = b.iter().map(|(_, v, _)| inv * v).collect();
        for (a, va, _) in b {
            for ((c, _, _), wc) in b.iter().zip(&w) {
                hcc[(*a, *c)] -= va.dot(wc);
            }
        }
    }
    // Directions of points the data do not fix are not fitted parameters.
    let fitted = cols - rank_deficit;
    if rows <= fitted {
        return Err(CovarianceError::NoRedundancy { rows, cols: fitted });
    }
    let residual_variance =
        jac.residuals.iter().map(|r| r * r).sum::<f64>() / (rows - fitted) as f64;
    // A pivot far below its diagonal entry is a direction nothing fixes
    // (rounding keeps an exactly singular S from failing the factorisation).
    let diagonal = hcc.diagonal();
    let cholesky = hcc.cholesky().ok_or(CovarianceError::Singular)?;
    let pivots = cholesky.l_dirty().diagonal();
    if !pivots
        .iter()
        .zip(diagonal.iter())
        .all(|(l, d)| l * l > 1e-12 * d)
    {
        return Err(CovarianceError::Singular);
    }
    let inverse = cholesky.inverse();
    // Clustered: S^-1 M S^-1 with M = G / (G - 1) sum_c z_c z_c^T, already
    // in the residuals' units (no residual variance).
    let sandwich = match point_cluster {
        None => None,
        Some(_) => {
            for z in cluster_grad.values_mut() {
                merge_columns(z);
            }
            let groups: Vec<&Vec<(usize, f64)>> =
                cluster_grad.values().chain(grad_lone.iter()).collect();
            if groups.len() < 2 {
                return Err(CovarianceError::TooFewClusters(groups.len()));
            }
            let g = groups.len() as f64;
            let mut m = DMatrix::<f64>::zeros(nc, nc);
            for z in groups {
                for &(a, va) in z {
                    for &(b, vb) in z {
                        m[(a, b)] += va * vb;
                    }
                }
            }
            m *= g / (g - 1.0);
            Some(&inverse * m * &inverse)
        }
    };
    let world_blocks = |tangent_cov: &DMatrix<f64>, scale: f64| -> Vec<Option<Matrix6<f64>>> {
        let mut out = vec![None; problem.poses.len()];
        for (pose, cols) in pose_cols.iter().enumerate() {
            let [Some(rc), Some(tc)] = *cols else {
                continue;
            };
            // Tangent covariance, order [d (rotation tangent), dt].
            let idx = [rc, rc + 1, rc + 2, tc, tc + 1, tc + 2];
            let tangent = Matrix6::from_fn(|i, j| tangent_cov[(idx[i], idx[j])]) * scale;
            let rigid = problem.poses[pose].rigid();
            let r = rigid.rotation.to_rotation_matrix().into_inner();
            let t = rigid.translation;
            // Ceres' quaternion tangent d turns q into exp(2 d) q (left), so
            // world_from_cam = R^T turns by the world-frame vector -2 R^T d; the
            // centre C = -R^T t moves by -2 R^T [t]x d - R^T dt.
            let mut jacobian = Matrix6::zeros();
            jacobian
                .fixed_view_mut::<3, 3>(0, 0)
                .copy_from(&(-2.0 * r.transpose()));
            jacobian
                .fixed_view_mut::<3, 3>(3, 0)
                .copy_from(&(-2.0 * r.transpose() * t.cross_matrix()));
            jacobian
                .fixed_view_mut::<3, 3>(3, 3)
                .copy_from(&(-r.transpose()));
            let c = jacobian * tangent * jacobian.transpose();
            out[pose] = Some((c + c.transpose()) * 0.5);
        }
        out
    };
    // Intrinsics: the tangent of a camera block is its variable parameters
    // in order (Ceres' subset manifold), so the block is the covariance.
    let camera_blocks = |cov: &DMatrix<f64>, scale: f64| -> Vec<Option<DMatrix<f64>>> {
        camera_cols
            .iter()
            .map(|cols| cols.map(|(at, size)| cov.view((at, at), (size, size)) * scale))
            .collect()
    };
    Ok(PoseCovariances {
        poses: world_blocks(&inverse, residual_variance),
        cameras: camera_blocks(&inverse, residual_variance),
        clustered_cameras: sandwich
            .as_ref()
            .map_or_else(Vec::new, |m| camera_blocks(m, 1.0)),
        clustered_poses: sandwich.map_or_else(Vec::new, |m| world_blocks(&m, 1.0)),
        residual_variance,
        redundancy: rows - fitted,
        num_degenerate_points,
    })
}

/// Sorts sparse `(column, value)` entries by column and sums those of the
/// same column (in a fixed order: the sums do not depend on anything else).
fn merge_columns(entries: &mut Vec<(usize, f64)>) {
    entries.sort_by_key(|&(col, _)| col);
    let mut merged: Vec<(usize, f64)> = Vec::with_capacity(entries.len());
    for &(col, v) in entries.iter() {
        match merged.last_mut() {
            Some((last, acc)) if *last == col => *acc += v,
            _ => merged.push((col, v)),
        }
    }
    *entries = merged;
}

/// Pseudo-inverse of a symmetric positive semi-definite 3x3 matrix; eigen
/// directions below 1e-10 of the largest carry no information. Also the
/// number of directions kept.
fn pseudo_inverse(h: &Matrix3<f64>) -> (Matrix3<f64>, usize) {
    let eig = h.symmetric_eigen();
    let max = eig.eigenvalues.max();
    if max <= 0.0 || !max.is_finite() {
        return (Matrix3::zeros(), 0);
    }
    let mut inv = Matrix3::zeros();
    let mut rank = 0;
    for k in 0..3 {
        let l = eig.eigenvalues[k];
        if l > 1e-10 * max {
            let v = eig.eigenvectors.column(k);
            inv += v * v.transpose() / l;
            rank += 1;
        }
    }
    (inv, rank)
}
