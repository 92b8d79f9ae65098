//! `colmap-lidar bench-map` (hidden): benchmarks of the map readers and
//! preparation on a synthetic building-like cloud. `generate` writes the
//! cloud; `load` times reading it (the peak memory is measured from outside,
//! e.g. `/usr/bin/time -v`). Preparation is timed through `prepare-map`.
//! Used by `scripts/bench_map.sh`.
use std::path::PathBuf;
use std::time::Instant;

use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use rayon::prelude::*;

use crate::map::io::{read_point_cloud, write_ply};
use crate::map::PointCloud;

#[derive(clap::Args, Debug, Clone)]
pub struct BenchMapArgs {
    #[command(subcommand)]
    pub action: BenchMapAction,
}

#[derive(clap::Subcommand, Debug, Clone)]
pub enum BenchMapAction {
    /// Writes a building-like cloud (binary PLY without normals).
    Generate {
        #[arg(long)]
        output: PathBuf,
        /// Number of points.
        #[arg(long, default_value_t = 20_000_000)]
        points: usize,
        /// Store coordinates relative to zero instead of at UTM-like
        /// coordinates (float instead of double x/y/z).
        #[arg(long)]
        local: bool,
        /// Surface noise (standard deviation, metres).
        #[arg(long, default_value_t = 0.005)]
        noise: f64,
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
    /// Nearest-neighbour queries a second on one core, on a generated
    /// building-like cloud: map points moved by Gaussian noise, in random
    /// order, in a coherent (cell-sorted) order, and through the batch API.
    Nn {
        /// Number of map points.
        #[arg(long, default_value_t = 20_000_000)]
        points: usize,
        /// Number of queries.
        #[arg(long, default_value_t = 2_000_000)]
        queries: usize,
        /// Standard deviation of the queries' offsets from map points (m).
        #[arg(long, default_value_t = 0.05)]
        noise: f64,
        /// Query radii (m).
        #[arg(long, value_delimiter = ',', default_value = "0.2,0.5,1.5")]
        radius: Vec<f64>,
        /// Index cell size (m); automatic when not given.
        #[arg(long)]
        cell: Option<f64>,
    },
    /// Reads a cloud (and builds the map index) and reports the times.
    Load {
        #[arg(long)]
        input: PathBuf,
        /// Also build the nearest-neighbour index ([`crate::map::index::MapIndex`])
        /// and the frustum grid ([`crate::map::grid::FrustumGrid`]).
        #[arg(long)]
        index: bool,
    },
}

/// A rectangle `corner + a u + b v`, a, b in [0, 1].
struct Patch {
    corner: Vector3<f64>,
    u: Vector3<f64>,
    v: Vector3<f64>,
}

/// Surfaces of a three-storey building, 40 m x 25 m, 3 m storeys, rooms on
/// a 5 m grid (walls with 1 m door gaps), floors and ceilings.
fn building() -> Vec<Patch> {
    let (len_x, len_y, storey, storeys) = (40.0, 25.0, 3.0, 3);
    let mut patches = Vec::new();
    for s in 0..storeys {
        let z0 = s as f64 * storey;
        // Floor slab top and ceiling underside.
        for z in [z0, z0 + storey - 0.05] {
            patches.push(Patch {
                corner: Vector3::new(0.0, 0.0, z),
                u: Vector3::new(len_x, 0.0, 0.0),
                v: Vector3::new(0.0, len_y, 0.0),
            });
        }
        // Walls across x (constant x), with a door gap at each room.
        let mut x = 0.0;
        while x <= len_x {
            let mut y = 0.0;
            while y < len_y {
                patches.push(Patch {
                    corner: Vector3::new(x, y + 1.0, z0),
                    u: Vector3::new(0.0, 4.0, 0.0),
                    v: Vector3::new(0.0, 0.0, storey - 0.05),
                });
                y += 5.0;
            }
            x += 5.0;
        }
        let mut y = 0.0;
        while y <= len_y {
            let mut x = 0.0;
            while x < len_x {
                patches.push(Patch {
                    corner: Vector3::new(x + 1.0, y, z0),
                    u: Vector3::new(4.0, 0.0, 0.0),
                    v: Vector3::new(0.0, 0.0, storey - 0.05),
                });
                x += 5.0;
            }
            y += 5.0;
        }
    }
    patches
}

/// A deterministic building-like cloud of `count` points (map frame: a UTM-like
/// offset unless `local`).
pub fn generate_building(count: usize, local: bool, noise_m: f64, seed: u64) -> PointCloud {
    let patches = building();
    let areas: Vec<f64> = patches.iter().map(|p| p.u.cross(&p.v).norm()).collect();
    let total: f64 = areas.iter().sum();
    let mut cumulative = Vec::with_capacity(areas.len());
    let mut acc = 0.0;
    for a in &areas {
        acc += a / total;
        cumulative.push(acc);
    }
    let origin = if local {
        Vector3::zeros()
    } else {
        Vector3::new(512_000.0, 5_412_000.0, 200.0)
    };
    // Noise is a valid standard deviation (clamped to >= 0).
    let noise = Normal::new(0.0, noise_m.max(0.0)).expect("non-negative std dev");
    const CHUNK: usize = 1 << 16;
    let points: Vec<[f32; 3]> = (0..count.div_ceil(CHUNK))
        .into_par_iter()
        .flat_map_iter(|chunk| {
            let mut rng = ChaCha8Rng::seed_from_u64(seed.wrapping_mul(1_000_003) + chunk as u64);
            let n = CHUNK.min(count - chunk * CHUNK);
            let patches = &patches;
            let cumulative = &cumulative;
            (0..n)
                .map(move |_| {
                    let r: f64 = rng.gen();
                    let k = cumulative
                        .partition_point(|c| *c < r)
                        .min(patches.len() - 1);
                    let p = &patches[k];
                    let normal = p.u.cross(&p.v).normalize();
                    let q = p.corner
                        + p.u * rng.gen::<f64>()
                        + p.v * rng.gen::<f64>()
                        + normal * noise.sample(&mut rng);
                    [q.x as f32, q.y as f32, q.z as f32]
                })
                .collect::<Vec<_>>()
        })
        .collect();
    PointCloud {
        origin,
        points,
        normals: None,
        planarity: None,
    }
}

/// The generator's and the benchmark's own arguments: at least one point,
/// a finite non-negative noise.
fn check_cloud_args(points: usize, noise: f64) -> anyhow::Result<()> {
    anyhow::ensure!(points >= 1, "--points must be at least 1");
    anyhow::ensure!(
        noise.is_finite() && noise >= 0.0,
        "--noise must be finite and >= 0 metres, got {noise}"
    );
    Ok(())
}

pub fn run(args: &BenchMapArgs) -> anyhow::Result<()> {
    match &args.action {
        BenchMapAction::Generate { points, noise, .. }
        | BenchMapAction::Nn { points, noise, .. } => check_cloud_args(*points, *noise)?,
        BenchMapAction::Load { .. } => {}
    }
    match &args.action {
        BenchMapAction::Generate {
            output,
            points,
            local,
            noise,
            seed,
        } => {
            crate::io::atomic::check_output_location(output, false)?;
            let start = Instant::now();
            let cloud = generate_building(*points, *local, *noise, *seed);
            let generated = start.elapsed().as_secs_f64();
            write_ply(output, &cloud)?;
            println!(
                "generated {} points in {generated:.2} s, wrote {} in {:.2} s",
                cloud.len(),
                output.display(),
                start.elapsed().as_secs_f64() - generated
            );
        }
        BenchMapAction::Nn {
            points,
            queries,
            noise,
            radius,
            cell,
        } => bench_nn(*points, *queries, *noise, radius, *cell)?,
        BenchMapAction::Load { input, index } => {
            let start = Instant::now();
            let (cloud, report) = read_point_cloud(input)?;
            let loaded = start.elapsed().as_secs_f64();
            println!(
                "loaded {} points ({}, {} dropped) from {} in {loaded:.2} s",
                cloud.len(),
                report.format,
                report.dropped_non_finite,
                input.display(),
            );
            if *index {
                let start = Instant::now();
                let map_index = crate::map::index::MapIndex::build(&cloud)?;
                let built = start.elapsed().as_secs_f64();
                // A few queries, checked against the cloud, so the index is used.
                let mut found = 0;
                for i in (0..cloud.len()).step_by((cloud.len() / 1000).max(1)) {
                    let p = cloud.point_in_map(i);
                    if let Some(n) = map_index.nearest_within(&p, 0.01) {
                        found += usize::from(n.dist_sq < 1e-6);
                    }
                }
                println!(
                    "built the index of {} points in {built:.2} s ({:.0} MB, {} cells of {} m; \
                     {found} self-queries found)",
                    map_index.len(),
                    map_index.memory_bytes() as f64 / 1e6,
                    map_index.num_cells(),
                    map_index.cell_size_m(),
                );
                let start = Instant::now();
                let grid = crate::map::grid::FrustumGrid::build(
                    &cloud,
                    &crate::map::grid::GridOptions::default(),
                )?;
                let gridded = start.elapsed().as_secs_f64();
                println!(
                    "built the frustum grid in {gridded:.2} s ({:.0} MB, {} cells); \
                     load + index + grid {:.2} s",
                    grid.memory_bytes() as f64 / 1e6,
                    grid.num_cells(),
                    loaded + built + gridded
                );
            }
        }
    }
    Ok(())
}

/// See [`BenchMapAction::Nn`].
fn bench_nn(
    points: usize,
    queries: usize,
    noise_m: f64,
    radii: &[f64],
    cell_size_m: Option<f64>,
) -> anyhow::Result<()> {
    let cloud = generate_building(points, true, 0.005, 1);
    let start = Instant::now();
    let options = crate::map::index::IndexOptions { cell_size_m };
    let index = crate::map::index::MapIndex::build_with_options(&cloud, &options)?;
    println!(
        "index of {} points: {:.2} s, {:.0} MB, {} cells of {} m",
        index.len(),
        start.elapsed().as_secs_f64(),
        index.memory_bytes() as f64 / 1e6,
        index.num_cells(),
        index.cell_size_m()
    );
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let noise = Normal::new(0.0, noise_m.max(0.0))?;
    let random: Vec<Vector3<f64>> = (0..queries)
        .map(|_| {
            let i = rng.gen_range(0..cloud.len().max(1));
            cloud.point_in_map(i)
                + Vector3::new(
                    noise.sample(&mut rng),
                    noise.sample(&mut rng),
                    noise.sample(&mut rng),
                )
        })
        .collect();
    let mut coherent = random.clone();
    coherent.sort_by_key(|q| {
        let c = |v: f64| ((v / 0.5).floor() as i64 + (1 << 20)) as u64;
        (c(q.x), c(q.y), c(q.z))
    });
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
    pool.install(|| {
        for &r in radii {
            for (name, qs) in [("random order", &random), ("coherent order", &coherent)] {
                // The answers are used (found count and index checksum), as
                // the batch's are, so no part of a query is optimised away.
                let start = Instant::now();
                let (found, checksum) = qs
                    .iter()
                    .filter_map(|q| index.nearest_within(q, r))
                    .fold((0usize, 0u64), |(n, c), nb| (n + 1, c ^ u64::from(nb.point_idx)));
                let s = start.elapsed().as_secs_f64();
                println!(
                    "nearest_within r = {r} m, {name}: {:.2} M queries/s on one core ({found} found, \
                     checksum {checksum:x})",
                    qs.len() as f64 / s / 1e6
                );
            }
            let start = Instant::now();
            let (found, checksum) = index
                .nearest_within_batch(&random, r)
                .iter()
                .flatten()
                .fold((0usize, 0u64), |(n, c), nb| (n + 1, c ^ u64::from(nb.point_idx)));
            let s = start.elapsed().as_secs_f64();
            println!(
                "nearest_within_batch r = {r} m (random order in): {:.2} M queries/s on one core \
                 ({found} found, checksum {checksum:x})",
                random.len() as f64 / s / 1e6
            );
        }
    });
    Ok(())
}
