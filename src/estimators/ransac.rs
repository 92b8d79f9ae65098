//! Generic LO-RANSAC.
//!
//! An [`Estimator`] turns a minimal sample into 0..n candidate models, measures a
//! datum's squared residual against a model and, optionally, re-estimates a model
//! from many inliers (the local optimisation step of LO-RANSAC, Chum et al. 2003).
//! [`run`] samples minimal sets with an injected seeded RNG, scores every
//! candidate by its inlier count (ties broken by the sum of inlier squared
//! residuals), and each time a sampled model becomes the best it repeatedly
//! re-estimates from the current inliers while that improves the score.
//!
//! The number of iterations adapts to the best inlier ratio `w` seen so far:
//! `N = log(1 - confidence) / log(1 - w^MIN_SAMPLES)`, clamped to
//! `[min_iterations, max_iterations]`.
use rand::Rng;
use rand_chacha::ChaCha8Rng;

use super::InvalidOptions;

/// A model family for [`run`].
pub trait Estimator {
    /// One observation (e.g. a 2D-3D correspondence). Copied into minimal samples.
    type Datum: Clone;
    type Model: Clone;
    /// Size of a minimal sample.
    const MIN_SAMPLES: usize;

    /// Candidate models from exactly `MIN_SAMPLES` data; empty when the sample is
    /// degenerate.
    fn estimate(&self, sample: &[Self::Datum]) -> Vec<Self::Model>;

    /// Squared residual of `datum` under `model`, in the squared units of
    /// [`RansacOptions::max_error`]. `f64::INFINITY` (or NaN) marks an outlier.
    fn residual_sq(&self, model: &Self::Model, datum: &Self::Datum) -> f64;

    /// Local optimisation: a model re-estimated from `inliers` (at least
    /// `MIN_SAMPLES` of them), starting from `model`. `None` when the estimator
    /// has no such step or it failed. Default: `None`.
    fn refine(&self, _model: &Self::Model, _inliers: &[Self::Datum]) -> Option<Self::Model> {
        None
    }
}

/// Options of [`run`].
#[derive(Clone, Debug, PartialEq)]
pub struct RansacOptions {
    /// A datum is an inlier when its residual is at most this (same units as the
    /// estimator's residual, e.g. pixels). Default: 4.0.
    pub max_error: f64,
    /// Probability of having drawn at least one outlier-free sample when the
    /// adaptive loop stops, in (0, 1). Default: 0.9999.
    pub confidence: f64,
    /// Iterations (minimal samples drawn) at least. Default: 0.
    pub min_iterations: usize,
    /// Iterations at most. Default: 10000.
    pub max_iterations: usize,
    /// Run the local optimisation step ([`Estimator::refine`]) on each new best
    /// sampled model. Default: true.
    pub local_optimization: bool,
    /// Re-estimations per local optimisation at most (each from the inliers of
    /// the previous one, while the score improves). Default: 10.
    pub max_local_iterations: usize,
}

impl Default for RansacOptions {
    fn default() -> Self {
        Self {
            max_error: 4.0,
            confidence: 0.9999,
            min_iterations: 0,
            max_iterations: 10000,
            local_optimization: true,
            max_local_iterations: 10,
        }
    }
}

impl RansacOptions {
    pub fn validate(&self) -> Result<(), InvalidOptions> {
        if !(self.max_error.is_finite() && self.max_error > 0.0) {
            return Err(InvalidOptions::new(
                "max_error",
                format!("must be finite and > 0, got {}", self.max_error),
            ));
        }
        if !(self.confidence > 0.0 && self.confidence < 1.0) {
            return Err(InvalidOptions::new(
                "confidence",
                format!("must be in (0, 1), got {}", self.confidence),
            ));
        }
        if self.max_iterations == 0 || self.min_iterations > self.max_iterations {
            return Err(InvalidOptions::new(
                "max_iterations",
                format!(
                    "must be >= 1 and >= min_iterations ({}), got {}",
                    self.min_iterations, self.max_iterations
                ),
            ));
        }
        Ok(())
    }
}

/// The result of a successful [`run`].
#[derive(Clone, Debug, PartialEq)]
pub struct RansacReport<M> {
    pub model: M,
    /// `inlier_mask[i]`: datum `i` has a residual <= `max_error` under `model`.
    pub inlier_mask: Vec<bool>,
    pub num_inliers: usize,
    /// Minimal samples drawn.
    pub num_iterations: usize,
    /// Local optimisation re-estimations that improved the best model.
    pub num_local_improvements: usize,
}

/// Why [`run`] found no model.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum RansacError {
    #[error(transparent)]
    InvalidOptions(#[from] InvalidOptions),
    #[error("RANSAC needs at least {needed} data, got {got}")]
    NotEnoughData { needed: usize, got: usize },
    #[error("RANSAC found no model with at least {needed} inliers in {iterations} iterations")]
    NoModel { needed: usize, iterations: usize },
}

/// Score of a model: more inliers is better; for equal counts, a smaller sum of
/// inlier squared residuals.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Score {
    num_inliers: usize,
    residual_sum_sq: f64,
}

impl Score {
    const WORST: Score = Score {
        num_inliers: 0,
        residual_sum_sq: f64::INFINITY,
    };

    fn is_better_than(&self, other: &Score) -> bool {
        self.num_inliers > other.num_inliers
            || (self.num_inliers == other.num_inliers
                && self.residual_sum_sq < other.residual_sum_sq)
    }
}

/// Scores `model`; stops early (returning [`Score::WORST`]) once it has more
/// outliers than `max_outliers`, i.e. once it can no longer reach the best
/// model's inlier count.
fn score<E: Estimator>(
    estimator: &E,
    model: &E::Model,
    data: &[E::Datum],
    max_sq: f64,
    max_outliers: usize,
) -> Score {
    let mut s = Score {
        num_inliers: 0,
        residual_sum_sq: 0.0,
    };
    let mut num_outliers = 0;
    for datum in data {
        let r_sq = estimator.residual_sq(model, datum);
        // NaN compares false: an outlier.
        if r_sq <= max_sq {
            s.num_inliers += 1;
            s.residual_sum_sq += r_sq;
        } else {
            num_outliers += 1;
            if num_outliers > max_outliers {
                return Score::WORST;
            }
        }
    }
    s
}

fn collect_inliers<E: Estimator>(
    estimator: &E,
    model: &E::Model,
    data: &[E::Datum],
    max_sq: f64,
    out: &mut Vec<E::Datum>,
) {
    out.clear();
    out.extend(
        data.iter()
            .filter(|d| estimator.residual_sq(model, d) <= max_sq)
            .cloned(),
    );
}

/// Iterations needed so that an all-inlier sample was drawn with probability
/// `confidence`, for an inlier ratio `inlier_ratio` and samples of `sample_size`.
pub fn required_iterations(
    inlier_ratio: f64,
    sample_size: usize,
    confidence: f64,
    max_iterations: usize,
) -> usize {
    let p_good_sample = inlier_ratio.clamp(0.0, 1.0).powi(sample_size as i32);
    if p_good_sample >= 1.0 {
        return 1;
    }
    if p_good_sample <= 0.0 {
        return max_iterations;
    }
    let n = (1.0 - confidence).ln() / (1.0 - p_good_sample).ln();
    if n.is_finite() && n < max_iterations as f64 {
        (n.ceil() as usize).max(1)
    } else {
        max_iterations
    }
}

/// Draws `k` distinct indices in `0..n` (k <= n, k small) into `out`.
fn sample_indices(rng: &mut ChaCha8Rng, n: usize, k: usize, out: &mut Vec<usize>) {
    out.clear();
    while out.len() < k {
        let i = rng.gen_range(0..n);
        if !out.contains(&i) {
            out.push(i);
        }
    }
}

/// LO-RANSAC. `initial_models` (e.g. a prior pose) are scored (and locally
/// optimised) before any sample is drawn. Deterministic for a given RNG state.
pub fn run<E: Estimator>(
    estimator: &E,
    data: &[E::Datum],
    initial_models: &[E::Model],
    options: &RansacOptions,
    rng: &mut ChaCha8Rng,
) -> Result<RansacReport<E::Model>, RansacError> {
    options.validate()?;
    let n = data.len();
    if n < E::MIN_SAMPLES || E::MIN_SAMPLES == 0 {
        return Err(RansacError::NotEnoughData {
            needed: E::MIN_SAMPLES.max(1),
            got: n,
        });
    }
    let max_sq = options.max_error * options.max_error;
    let mut best: Option<(E::Model, Score)> = None;
    let mut num_local_improvements = 0;
    let mut required = options.max_iterations;
    let mut sample_idx = Vec::with_capacity(E::MIN_SAMPLES);
    let mut sample = Vec::with_capacity(E::MIN_SAMPLES);
    let mut inliers = Vec::new();

    // Scores `model`; when it becomes the best, locally optimises it and updates
    // the required number of iterations.
    let mut consider = |model: E::Model,
                        best: &mut Option<(E::Model, Score)>,
                        required: &mut usize,
                        inliers: &mut Vec<E::Datum>| {
        let best_score = best.as_ref().map_or(Score::WORST, |b| b.1);
        let s = score(estimator, &model, data, max_sq, n - best_score.num_inliers);
        if !s.is_better_than(&best_score) {
            return;
        }
        let (mut current, mut current_score) = (model, s);
        if options.local_optimization {
            for _ in 0..options.max_local_iterations {
                collect_inliers(estimator, &current, data, max_sq, inliers);
                if inliers.len() < E::MIN_SAMPLES {
                    break;
                }
                let Some(refined) = estimator.refine(&current, inliers) else {
                    break;
                };
                let refined_score = score(
                    estimator,
                    &refined,
                    data,
                    max_sq,
                    n - current_score.num_inliers,
                );
                if !refined_score.is_better_than(&current_score) {
                    break;
                }
                current = refined;
                current_score = refined_score;
                num_local_improvements += 1;
            }
        }
        *required = required_iterations(
            current_score.num_inliers as f64 / n as f64,
            E::MIN_SAMPLES,
            options.confidence,
            options.max_iterations,
        );
        *best = Some((current, current_score));
    };

    for model in initial_models {
        consider(model.clone(), &mut best, &mut required, &mut inliers);
    }
    let mut iterations = 0;
    while iterations < options.max_iterations
        && (iterations < options.min_iterations || iterations < required)
    {
        iterations += 1;
        sample_indices(rng, n, E::MIN_SAMPLES, &mut sample_idx);
        sample.clear();
        sample.extend(sample_idx.iter().map(|&i| data[i].clone()));
        for model in estimator.estimate(&sample) {
            consider(model, &mut best, &mut required, &mut inliers);
        }
    }

    match best {
        Some((model, s)) if s.num_inliers >= E::MIN_SAMPLES => {
            let inlier_mask: Vec<bool> = data
                .iter()
                .map(|d| estimator.residual_sq(&model, d) <= max_sq)
                .collect();
            Ok(RansacReport {
                model,
                num_inliers: s.num_inliers,
                inlier_mask,
                num_iterations: iterations,
                num_local_improvements,
            })
        }
        _ => Err(RansacError::NoModel {
            needed: E::MIN_SAMPLES,
            iterations,
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    /// A 2D line `y = a x + b` from two points; residual = vertical distance.
    struct LineEstimator;

    impl Estimator for LineEstimator {
        type Datum = [f64; 2];
        type Model = [f64; 2];
        const MIN_SAMPLES: usize = 2;

        fn estimate(&self, s: &[[f64; 2]]) -> Vec<[f64; 2]> {
            let dx = s[1][0] - s[0][0];
            if dx.abs() < 1e-12 {
                return vec![];
            }
            let a = (s[1][1] - s[0][1]) / dx;
            vec![[a, s[0][1] - a * s[0][0]]]
        }

        fn residual_sq(&self, m: &[f64; 2], d: &[f64; 2]) -> f64 {
            let r = d[1] - (m[0] * d[0] + m[1]);
            r * r
        }

        /// Least-squares line through the inliers.
        fn refine(&self, _m: &[f64; 2], inl: &[[f64; 2]]) -> Option<[f64; 2]> {
            let n = inl.len() as f64;
            let (sx, sy) = inl.iter().fold((0.0, 0.0), |a, d| (a.0 + d[0], a.1 + d[1]));
            let (mx, my) = (sx / n, sy / n);
            let sxx: f64 = inl.iter().map(|d| (d[0] - mx).powi(2)).sum();
            let sxy: f64 = inl.iter().map(|d| (d[0] - mx) * (d[1] - my)).sum();
            (sxx > 0.0).then(|| [sxy / sxx, my - sxy / sxx * mx])
        }
    }

    fn line_data(rng: &mut ChaCha8Rng) -> (Vec<[f64; 2]>, Vec<bool>) {
        let mut data = Vec::new();
        let mut truth = Vec::new();
        for i in 0..200 {
            let x = i as f64 * 0.1;
            if i % 5 < 2 {
                // 40 % outliers, far from the line.
                data.push([x, rng.gen_range(20.0..100.0)]);
                truth.push(false);
            } else {
                data.push([x, 2.0 * x - 1.0 + rng.gen_range(-0.05..0.05)]);
                truth.push(true);
            }
        }
        (data, truth)
    }

    #[test]
    fn finds_line_with_outliers_and_is_deterministic() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let (data, truth) = line_data(&mut rng);
        let options = RansacOptions {
            max_error: 0.1,
            ..Default::default()
        };
        let report = run(
            &LineEstimator,
            &data,
            &[],
            &options,
            &mut ChaCha8Rng::seed_from_u64(7),
        )
        .unwrap();
        assert_eq!(report.inlier_mask, truth);
        assert_eq!(report.num_inliers, 120);
        assert!((report.model[0] - 2.0).abs() < 0.01, "{:?}", report.model);
        assert!((report.model[1] + 1.0).abs() < 0.1, "{:?}", report.model);
        // Adaptive: w = 0.6, s = 2 -> 21 iterations for 0.9999.
        assert!(report.num_iterations <= 21, "{}", report.num_iterations);
        let again = run(
            &LineEstimator,
            &data,
            &[],
            &options,
            &mut ChaCha8Rng::seed_from_u64(7),
        )
        .unwrap();
        assert_eq!(report, again);
        assert_eq!(report.model[0].to_bits(), again.model[0].to_bits());
    }

    #[test]
    fn initial_model_is_used() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let (data, _) = line_data(&mut rng);
        let options = RansacOptions {
            max_error: 0.1,
            local_optimization: false,
            ..Default::default()
        };
        // A perfect initial model: 120/200 inliers -> adaptive count from the start.
        let report = run(
            &LineEstimator,
            &data,
            &[[2.0, -1.0]],
            &options,
            &mut ChaCha8Rng::seed_from_u64(3),
        )
        .unwrap();
        assert_eq!(report.num_inliers, 120);
        assert_eq!(
            report.num_iterations,
            required_iterations(0.6, 2, 0.9999, 10000)
        );
    }

    #[test]
    fn errors_not_panics() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let opts = RansacOptions::default();
        assert_eq!(
            run(&LineEstimator, &[[0.0, 0.0]], &[], &opts, &mut rng),
            Err(RansacError::NotEnoughData { needed: 2, got: 1 })
        );
        // All x equal: every sample is degenerate.
        let data = vec![[1.0, 0.0]; 10];
        assert!(matches!(
            run(&LineEstimator, &data, &[], &opts, &mut rng),
            Err(RansacError::NoModel { .. })
        ));
        // NaN data: never inliers.
        let data = vec![[f64::NAN, f64::NAN]; 10];
        assert!(matches!(
            run(&LineEstimator, &data, &[], &opts, &mut rng),
            Err(RansacError::NoModel { .. })
        ));
        let bad = RansacOptions {
            confidence: 1.0,
            ..Default::default()
        };
        assert!(matches!(
            run(&LineEstimator, &[[0.0, 0.0]; 3], &[], &bad, &mut rng),
            Err(RansacError::InvalidOptions(_))
        ));
    }

    #[test]
    fn required_iterations_formula() {
        // w = 0.5, s = 3, p = 0.99: log(0.01) / log(0.875) = 34.5 -> 35.
        assert_eq!(required_iterations(0.5, 3, 0.99, 1000), 35);
        assert_eq!(required_iterations(1.0, 3, 0.99, 1000), 1);
        assert_eq!(required_iterations(0.0, 3, 0.99, 1000), 1000);
        assert_eq!(required_iterations(1e-6, 3, 0.99, 1000), 1000);
    }
}
