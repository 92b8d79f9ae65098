//! Synthetic LiDAR maps: points sampled on the scene's surfaces with range
//! noise along the normal, missing patches and a few outliers; and a small
//! binary PLY writer (x y z as double so georeferenced offsets survive, normals
//! as float).
use std::io::{self, Write};

use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal, StandardNormal};

use super::geometry::Scene;

/// How the map is sampled.
#[derive(Clone, Debug)]
pub struct LidarOptions {
    /// Sample spacing on the surfaces in metres; `None` picks the smallest
    /// spacing >= 2 cm that keeps the map under `max_points`. Default `None`.
    pub spacing_m: Option<f64>,
    /// Upper bound on the number of surface samples. Default 1_500_000.
    pub max_points: usize,
    /// Standard deviation of the noise along the normal, metres. Default 0.015.
    pub noise_sigma_m: f64,
    /// Number of circular holes (missing patches). Default 12.
    pub num_holes: usize,
    /// Fraction of outliers added uniformly in the scene's bounding box. Default 0.001.
    pub outlier_fraction: f64,
    /// Where the scanner was. Default [`LidarPlatform::Terrestrial`].
    pub platform: LidarPlatform,
    pub seed: u64,
}

/// Where the scan was taken from, which sets how densely each surface is sampled.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum LidarPlatform {
    /// Every surface at the same density (scans from the ground all around, as
    /// a mobile or tripod scanner gives).
    #[default]
    Terrestrial,
    /// From an aircraft or drone flying over it, the scan lines near nadir:
    /// a surface is sampled in proportion to how much it faces up, walls
    /// (and surfaces facing down by less than 30 deg) at
    /// [`AIRBORNE_WALL_SHARE`] of the ground's density, surfaces facing
    /// further down not at all.
    Airborne,
}

/// The density of a vertical wall relative to flat ground in an airborne scan:
/// the sine of a typical 10-20 deg scan angle, halved as only the strips on a
/// wall's side see it.
pub const AIRBORNE_WALL_SHARE: f64 = 0.15;

impl LidarPlatform {
    /// The share of a surface's grid samples this platform keeps, by the
    /// surface's unit normal.
    pub fn density(self, normal: &Vector3<f64>) -> f64 {
        match self {
            Self::Terrestrial => 1.0,
            Self::Airborne if normal.z < -0.5 => 0.0,
            Self::Airborne => normal.z.clamp(AIRBORNE_WALL_SHARE, 1.0),
        }
    }
}

impl Default for LidarOptions {
    fn default() -> Self {
        Self {
            spacing_m: None,
            max_points: 1_500_000,
            noise_sigma_m: 0.015,
            num_holes: 12,
            outlier_fraction: 0.001,
            platform: LidarPlatform::Terrestrial,
            seed: 0,
        }
    }
}

/// A sampled map in the scene-local frame.
#[derive(Clone, Debug, Default)]
pub struct LidarMap {
    pub points: Vec<Vector3<f64>>,
    /// Unit normals (exact surface normals; random for outliers).
    pub normals: Vec<Vector3<f32>>,
    /// True for the outliers (not written to the PLY; for tests).
    pub is_outlier: Vec<bool>,
    pub spacing_m: f64,
}

/// Samples the surfaces of `scene` on a jittered grid.
pub fn sample_lidar(scene: &Scene, opts: &LidarOptions) -> LidarMap {
    let mut rng = ChaCha8Rng::seed_from_u64(opts.seed ^ 0x11DA_2000);
    let area: f64 = scene.quads.iter().map(|q| q.area_m2()).sum();
    let spacing = opts
        .spacing_m
        .unwrap_or_else(|| (area / opts.max_points.max(1) as f64).sqrt().max(0.02));
    // Holes: (quad, centre a, centre b, radius), quads drawn by area.
    let mut holes = Vec::new();
    for _ in 0..opts.num_holes {
        let mut pick = rng.gen_range(0.0..area);
        let mut qi = 0;
        for (i, q) in scene.quads.iter().enumerate() {
            qi = i;
            if pick < q.area_m2() {
                break;
            }
            pick -= q.area_m2();
        }
        let q = &scene.quads[qi];
        holes.push((
            qi,
            rng.gen_range(0.0..q.size_u_m),
            rng.gen_range(0.0..q.size_v_m),
            rng.gen_range(0.25..1.0),
        ));
    }
    // Normal::new fails only for a negative or NaN sigma, clamped here.
    let noise = Normal::new(0.0, opts.noise_sigma_m.max(0.0)).unwrap();
    let mut map = LidarMap {
        spacing_m: spacing,
        ..Default::default()
    };
    for (qi, q) in scene.quads.iter().enumerate() {
        let nu = (q.size_u_m / spacing).ceil().max(1.0) as usize;
        let nv = (q.size_v_m / spacing).ceil().max(1.0) as usize;
        let (du, dv) = (q.size_u_m / nu as f64, q.size_v_m / nv as f64);
        let n32 = Vector3::new(q.normal.x as f32, q.normal.y as f32, q.normal.z as f32);
        let keep = opts.platform.density(&q.normal);
        for j in 0..nv {
            for i in 0..nu {
                let a = (i as f64 + rng.gen::<f64>()) * du;
                let b = (j as f64 + rng.gen::<f64>()) * dv;
                let in_hole = holes.iter().any(|&(hq, ha, hb, r)| {
                    hq == qi && (a - ha).powi(2) + (b - hb).powi(2) < r * r
                });
                let p = q.point_at(a, b);
                let n: f64 = noise.sample(&mut rng);
                // Drawn only when thinning, so a terrestrial map is as before.
                let thinned = keep < 1.0 && rng.gen::<f64>() >= keep;
                if thinned || in_hole || scene.solids.iter().any(|s| s.contains(&p, 0.005)) {
                    continue;
                }
                map.points.push(p + q.normal * n);
                map.normals.push(n32);
                map.is_outlier.push(false);
            }
        }
    }
    let (lo, hi) = scene.bounding_box();
    let num_outliers = (map.points.len() as f64 * opts.outlier_fraction).round() as usize;
    for _ in 0..num_outliers {
        let p = Vector3::new(
            rng.gen_range(lo.x..=hi.x),
            rng.gen_range(lo.y..=hi.y),
            rng.gen_range(lo.z..=hi.z),
        );
        let d: Vector3<f64> = Vector3::from_fn(|_, _| StandardNormal.sample(&mut rng));
        let d = d.normalize();
        map.points.push(p);
        map.normals
            .push(Vector3::new(d.x as f32, d.y as f32, d.z as f32));
        map.is_outlier.push(true);
    }
    map
}

/// Writes a binary little-endian PLY: `x y z` double (plus `offset`), and
/// `nx ny nz` float when `with_normals`.
pub fn write_ply(
    out: &mut impl Write,
    map: &LidarMap,
    offset: &Vector3<f64>,
    with_normals: bool,
) -> io::Result<()> {
    writeln!(out, "ply")?;
    writeln!(out, "format binary_little_endian 1.0")?;
    writeln!(
        out,
        "comment synthetic LiDAR map written by colmap-lidar synth"
    )?;
    writeln!(out, "element vertex {}", map.points.len())?;
    for c in ["x", "y", "z"] {
        writeln!(out, "property double {c}")?;
    }
    if with_normals {
        for c in ["nx", "ny", "nz"] {
            writeln!(out, "property float {c}")?;
        }
    }
    writeln!(out, "end_header")?;
    let mut buf = Vec::with_capacity(36);
    for (p, n) in map.points.iter().zip(&map.normals) {
        buf.clear();
        let q = p + offset;
        for k in 0..3 {
            buf.extend_from_slice(&q[k].to_le_bytes());
        }
        if with_normals {
            for k in 0..3 {
                buf.extend_from_slice(&n[k].to_le_bytes());
            }
        }
        out.write_all(&buf)?;
    }
    Ok(())
}
