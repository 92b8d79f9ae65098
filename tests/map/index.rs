//! Integration tests: map index (kd-tree) against brute-force oracles, on
//! uniform random clouds and on axis-aligned "building" clouds (floors, walls,
//! boxes sampled on a regular lattice: many exact ties, the kd-tree's worst
//! case). Also the benchmark of the index (`#[ignore]`, see
//! `scripts/bench_projection.sh`).
use colmap_lidar::map::index::{IndexOptions, MapIndex};
use colmap_lidar::map::PointCloud;
use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A georeferenced-looking origin: large coordinates must not lose precision.
pub fn utm_origin() -> Vector3<f64> {
    Vector3::new(512_345.25, 5_401_234.5, 231.0)
}

pub fn cloud_from(points: Vec<[f32; 3]>) -> PointCloud {
    PointCloud {
        origin: utm_origin(),
        points,
        normals: None,
        planarity: None,
    }
}

pub fn uniform_cloud(n: usize, half_extent_m: f32, seed: u64) -> PointCloud {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let points = (0..n)
        .map(|_| {
            [
                rng.gen_range(-half_extent_m..half_extent_m),
                rng.gen_range(-half_extent_m..half_extent_m),
                rng.gen_range(-half_extent_m..half_extent_m),
            ]
        })
        .collect();
    cloud_from(points)
}

/// A building-like map of about `n` points: storeys of floors, outer and inner
/// walls and boxes, all axis-aligned and sampled on a regular lattice (spacing
/// chosen to give about `n` points), with unit normals. `jitter_m` adds
/// uniform noise (0 keeps exact lattice coordinates and ties).
pub fn building_cloud(n: usize, jitter_m: f32, seed: u64) -> PointCloud {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    // Footprint 60 x 40 m, 3 storeys of 3 m; total surface area (approx):
    let (lx, ly, storey, storeys) = (60.0f32, 40.0f32, 3.0f32, 3);
    // Rectangles: (origin, edge u, edge v, normal).
    type Rect = ([f32; 3], [f32; 3], [f32; 3], [f32; 3]);
    let mut rects: Vec<Rect> = Vec::new();
    for s in 0..=storeys {
        let z = s as f32 * storey;
        rects.push((
            [0.0, 0.0, z],
            [lx, 0.0, 0.0],
            [0.0, ly, 0.0],
            [0.0, 0.0, 1.0],
        ));
    }
    let h = storey * storeys as f32;
    rects.push((
        [0.0, 0.0, 0.0],
        [lx, 0.0, 0.0],
        [0.0, 0.0, h],
        [0.0, 1.0, 0.0],
    ));
    rects.push((
        [0.0, ly, 0.0],
        [lx, 0.0, 0.0],
        [0.0, 0.0, h],
        [0.0, -1.0, 0.0],
    ));
    rects.push((
        [0.0, 0.0, 0.0],
        [0.0, ly, 0.0],
        [0.0, 0.0, h],
        [1.0, 0.0, 0.0],
    ));
    rects.push((
        [lx, 0.0, 0.0],
        [0.0, ly, 0.0],
        [0.0, 0.0, h],
        [-1.0, 0.0, 0.0],
    ));
    // Inner walls every 10 m along x.
    for k in 1..6 {
        let x = k as f32 * 10.0;
        rects.push((
            [x, 0.0, 0.0],
            [0.0, ly * 0.8, 0.0],
            [0.0, 0.0, h],
            [1.0, 0.0, 0.0],
        ));
    }
    // Boxes (tops and two sides) on the ground floor.
    for k in 0..12 {
        let (bx, by) = (3.0 + 4.7 * k as f32, 5.0 + 2.5 * (k % 5) as f32);
        let (sx, sy, sz) = (1.2f32, 0.8f32, 1.0f32);
        rects.push((
            [bx, by, sz],
            [sx, 0.0, 0.0],
            [0.0, sy, 0.0],
            [0.0, 0.0, 1.0],
        ));
        rects.push((
            [bx, by, 0.0],
            [sx, 0.0, 0.0],
            [0.0, 0.0, sz],
            [0.0, -1.0, 0.0],
        ));
        rects.push((
            [bx, by, 0.0],
            [0.0, sy, 0.0],
            [0.0, 0.0, sz],
            [-1.0, 0.0, 0.0],
        ));
    }
    let area: f32 = rects
        .iter()
        .map(|(_, u, v, _)| Vector3::from(*u).norm() * Vector3::from(*v).norm())
        .sum();
    let spacing = (area / n as f32).sqrt();
    let mut points = Vec::with_capacity(n + n / 8);
    let mut normals = Vec::with_capacity(n + n / 8);
    for (o, u, v, nrm) in &rects {
        let (lu, lv) = (Vector3::from(*u).norm(), Vector3::from(*v).norm());
        let (nu, nv) = ((lu / spacing) as usize, (lv / spacing) as usize);
        for i in 0..nu {
            for j in 0..nv {
                let a = (i as f32 + 0.5) / nu as f32;
                let b = (j as f32 + 0.5) / nv as f32;
                let mut p = [0f32; 3];
                for c in 0..3 {
                    p[c] = o[c] + a * u[c] + b * v[c];
                    if jitter_m > 0.0 {
                        p[c] += rng.gen_range(-jitter_m..jitter_m);
                    }
                }
                points.push(p);
                normals.push(*nrm);
            }
        }
    }
    let mut cloud = cloud_from(points);
    cloud.normals = Some(normals);
    cloud
}

fn dist(cloud: &PointCloud, i: usize, q: &Vector3<f64>) -> f64 {
    (cloud.point_in_map(i) - q).norm()
}

/// All distances from `q`, sorted, with indices.
fn oracle(cloud: &PointCloud, q: &Vector3<f64>) -> Vec<(f64, usize)> {
    let mut d: Vec<(f64, usize)> = (0..cloud.len()).map(|i| (dist(cloud, i, q), i)).collect();
    d.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    d
}

/// Tolerance on distances (m): f32 storage of offsets up to ~100 m.
const TOL_M: f64 = 1e-4;

pub fn random_queries(cloud: &PointCloud, n: usize, seed: u64) -> Vec<Vector3<f64>> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (lo, hi) = cloud.bounds().expect("a non-empty cloud");
    (0..n)
        .map(|k| {
            if k % 2 == 0 {
                // Near a map point.
                let i = rng.gen_range(0..cloud.len());
                cloud.point_in_map(i)
                    + Vector3::new(
                        rng.gen_range(-0.3..0.3),
                        rng.gen_range(-0.3..0.3),
                        rng.gen_range(-0.3..0.3),
                    )
            } else {
                // Anywhere in (and a bit beyond) the bounding box.
                let t = Vector3::new(
                    rng.gen_range(-0.1..1.1),
                    rng.gen_range(-0.1..1.1),
                    rng.gen_range(-0.1..1.1),
                );
                lo + (hi - lo).component_mul(&t)
            }
        })
        .collect()
}

fn check_against_oracle(cloud: &PointCloud, seed: u64) {
    check_against_oracle_with(cloud, seed, &IndexOptions::default());
}

fn check_against_oracle_with(cloud: &PointCloud, seed: u64, options: &IndexOptions) {
    // Default crossover, then each backend forced.
    for tree_cells in [None, Some(0.0), Some(f64::INFINITY)] {
        check_against_oracle_backend(cloud, seed, options, tree_cells);
    }
}

fn check_against_oracle_backend(
    cloud: &PointCloud,
    seed: u64,
    options: &IndexOptions,
    tree_min_radius_cells: Option<f64>,
) {
    let mut index = MapIndex::build_with_options(cloud, options).unwrap();
    if let Some(cells) = tree_min_radius_cells {
        index.set_tree_min_radius_cells(cells);
    }
    assert_eq!(index.len(), cloud.len());
    let mut found_some = 0;
    let mut found_none = 0;
    for q in random_queries(cloud, 150, seed) {
        let all = oracle(cloud, &q);
        let (d_min, _) = all[0];
        for radius in [0.05, 0.3, 2.0] {
            // nearest_within
            match index.nearest_within(&q, radius) {
                None => {
                    assert!(
                        d_min > radius - TOL_M,
                        "missed a point at {d_min} < {radius}"
                    );
                    found_none += 1;
                }
                Some(n) => {
                    let d = dist(cloud, n.point_idx as usize, &q);
                    assert!((d - d_min).abs() < TOL_M, "nearest {d} vs oracle {d_min}");
                    assert!((n.dist_sq.sqrt() - d).abs() < TOL_M);
                    assert!(d <= radius + TOL_M);
                    found_some += 1;
                }
            }
            // within_radius
            let w = index.within_radius(&q, radius);
            let mut seen = std::collections::BTreeSet::new();
            for n in &w {
                assert!(seen.insert(n.point_idx), "duplicate result");
                let d = dist(cloud, n.point_idx as usize, &q);
                assert!(d <= radius + TOL_M, "result at {d} beyond {radius}");
                assert!((n.dist_sq.sqrt() - d).abs() < TOL_M);
            }
            for &(d, i) in all.iter().take_while(|(d, _)| *d < radius - TOL_M) {
                assert!(
                    seen.contains(&(i as u32)),
                    "point {i} at {d} < {radius} missing"
                );
            }
            assert!(w.windows(2).all(|p| p[0].dist_sq <= p[1].dist_sq));
            // k_nearest_within
            let kw = index.k_nearest_within(&q, 4, radius);
            let expect = all
                .iter()
                .filter(|(d, _)| *d <= radius - TOL_M)
                .count()
                .min(4);
            assert!(kw.len() >= expect && kw.len() <= 4);
            for (n, (d_or, _)) in kw.iter().zip(&all) {
                assert!((dist(cloud, n.point_idx as usize, &q) - d_or).abs() < TOL_M);
            }
        }
        // k_nearest
        for k in [1, 7, 30] {
            let kn = index.k_nearest(&q, k);
            assert_eq!(kn.len(), k.min(cloud.len()));
            let mut seen = std::collections::BTreeSet::new();
            for (n, (d_or, _)) in kn.iter().zip(&all) {
                assert!(seen.insert(n.point_idx));
                let d = dist(cloud, n.point_idx as usize, &q);
                assert!(
                    (d - d_or).abs() < TOL_M,
                    "k-th distance {d} vs oracle {d_or}"
                );
            }
        }
    }
    // The radii were chosen so that both outcomes occur.
    assert!(
        found_some > 50 && found_none > 50,
        "{found_some} / {found_none}"
    );
}

#[test]
fn index_matches_brute_force_on_uniform_cloud() {
    check_against_oracle(&uniform_cloud(20_000, 10.0, 1), 11);
}

#[test]
fn index_matches_brute_force_on_building_cloud() {
    // Exact lattice coordinates: axis-aligned planes, many ties.
    check_against_oracle(&building_cloud(20_000, 0.0, 2), 12);
    check_against_oracle(&building_cloud(20_000, 0.005, 3), 13);
}

#[test]
fn index_matches_brute_force_with_small_and_large_cells() {
    // Cells much smaller than the radii (many cells and blocks visited) and
    // larger than them (many points a cell).
    let cloud = building_cloud(20_000, 0.005, 4);
    for cell_size_m in [0.03, 0.7, 3.0] {
        check_against_oracle_with(
            &cloud,
            14,
            &IndexOptions {
                cell_size_m: Some(cell_size_m),
            },
        );
    }
    assert!(MapIndex::build_with_options(
        &cloud,
        &IndexOptions {
            cell_size_m: Some(0.0)
        }
    )
    .is_err());
    // 2^21 cells along an axis at most.
    let wide = cloud_from(vec![[0.0, 0.0, 0.0], [5000.0, 0.0, 0.0]]);
    assert!(MapIndex::build_with_options(
        &wide,
        &IndexOptions {
            cell_size_m: Some(0.001)
        }
    )
    .is_err());
    assert!(MapIndex::build_with_options(
        &wide,
        &IndexOptions {
            cell_size_m: Some(0.01)
        }
    )
    .is_ok());
}

/// Every query's nearest point equals the brute-force nearest up to the
/// quantisation of the stored coordinates (cell / 65535 per axis): its
/// distance is within sqrt(3)/2 step (plus f32 rounding) of the true nearest
/// distance.
#[test]
fn nearest_within_agrees_with_brute_force_far_and_near() {
    let cloud = building_cloud(30_000, 0.0, 5);
    let index = MapIndex::build(&cloud).unwrap();
    let tol = 1e-6 + 0.9 * 3f64.sqrt() * index.cell_size_m() / 65535.0;
    let mut rng = ChaCha8Rng::seed_from_u64(15);
    let mut checked = 0;
    for k in 0..400 {
        let q = if k % 4 == 0 {
            // Well outside the map.
            cloud.origin
                + Vector3::new(
                    rng.gen_range(-30.0..90.0),
                    rng.gen_range(-30.0..70.0),
                    rng.gen_range(-10.0..20.0),
                )
        } else {
            cloud.point_in_map(rng.gen_range(0..cloud.len()))
                + Vector3::new(
                    rng.gen_range(-0.05..0.05),
                    rng.gen_range(-0.05..0.05),
                    rng.gen_range(-0.05..0.05),
                )
        };
        let all = oracle(&cloud, &q);
        let n = index.nearest(&q).unwrap();
        assert!((dist(&cloud, n.point_idx as usize, &q) - all[0].0).abs() < tol);
        assert!((n.dist_sq.sqrt() - all[0].0).abs() < tol);
        for radius in [0.1, 0.5, 1.5] {
            let got = index.nearest_within(&q, radius);
            if all[0].0 < radius - tol {
                let g = got.expect("a point within the radius");
                assert!((dist(&cloud, g.point_idx as usize, &q) - all[0].0).abs() < tol);
                checked += 1;
            } else if all[0].0 > radius + tol {
                assert!(got.is_none());
            }
        }
    }
    assert!(checked > 300, "{checked}");
}

#[test]
fn ties_and_empty_results() {
    // Integer lattice 6 x 6 x 6: the centre of a unit cube has 8 neighbours
    // at exactly the same distance, the next ones much farther.
    let mut points = Vec::new();
    for x in 0..6 {
        for y in 0..6 {
            for z in 0..6 {
                points.push([x as f32, y as f32, z as f32]);
            }
        }
    }
    let cloud = cloud_from(points);
    let index = MapIndex::build(&cloud).unwrap();
    let q = cloud.origin + Vector3::new(2.5, 2.5, 2.5);
    let cube: std::collections::BTreeSet<u32> = (0..cloud.len() as u32)
        .filter(|&i| (dist(&cloud, i as usize, &q) - 0.75f64.sqrt()).abs() < 1e-9)
        .collect();
    assert_eq!(cube.len(), 8);
    let k8: std::collections::BTreeSet<u32> =
        index.k_nearest(&q, 8).iter().map(|n| n.point_idx).collect();
    assert_eq!(k8, cube);
    let w: Vec<u32> = index
        .within_radius(&q, 1.0)
        .iter()
        .map(|n| n.point_idx)
        .collect();
    assert_eq!(
        w.iter().copied().collect::<std::collections::BTreeSet<_>>(),
        cube
    );
    let n = index.nearest_within(&q, 1.0).unwrap();
    // Exact ties go to the smaller index.
    assert_eq!(Some(&n.point_idx), cube.iter().next());
    assert_eq!(index.nearest(&q).unwrap(), n);
    // Deterministic: the same answer every time.
    for _ in 0..3 {
        assert_eq!(index.nearest_within(&q, 1.0).unwrap(), n);
        assert_eq!(
            index
                .within_radius(&q, 1.0)
                .iter()
                .map(|n| n.point_idx)
                .collect::<Vec<_>>(),
            w
        );
    }
    // Radius below the tie distance: nothing.
    assert!(index.nearest_within(&q, 0.8).is_none());
    assert!(index.within_radius(&q, 0.8).is_empty());
    assert!(index.k_nearest_within(&q, 3, 0.8).is_empty());
    // Far from the map: nothing within 10 m, but the unbounded query answers.
    let far = cloud.origin + Vector3::new(100.0, -50.0, 20.0);
    assert!(index.nearest_within(&far, 10.0).is_none());
    let nn = index.nearest(&far).unwrap();
    assert!((nn.dist_sq.sqrt() - oracle(&cloud, &far)[0].0).abs() < TOL_M);
    // Query exactly on a point: distance 0.
    let on = cloud.point_in_map(17);
    let n = index.nearest_within(&on, 0.01).unwrap();
    assert_eq!(n.point_idx, 17);
    assert!(n.dist_sq < 1e-9);
    // Negative or NaN radius: nothing, no panic.
    assert!(index.nearest_within(&on, -1.0).is_none());
    assert!(index.within_radius(&on, f64::NAN).is_empty());
}

/// Peak resident memory of this process (MB), from /proc (Linux).
pub fn peak_rss_mb() -> f64 {
    proc_status_kb("VmHWM:") / 1024.0
}

pub fn rss_mb() -> f64 {
    proc_status_kb("VmRSS:") / 1024.0
}

fn proc_status_kb(key: &str) -> f64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    status
        .lines()
        .find(|l| l.starts_with(key))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|v| v.parse::<f64>().ok())
        .unwrap_or(f64::NAN)
}

/// Resets the peak resident memory counter (Linux >= 4.0).
pub fn reset_peak_rss() {
    let _ = std::fs::write("/proc/self/clear_refs", "5");
}

/// Benchmark (not a timed test): nearest-neighbour queries a second on one
/// core on a building-like map, load + index time and peak memory. Size from
/// `COLMAP_LIDAR_BENCH_POINTS` (default 20 million). Run it in release mode
/// through `scripts/bench_projection.sh`.
#[test]
#[ignore]
fn bench_index() {
    use colmap_lidar::map::grid::{FrustumGrid, GridOptions};
    use colmap_lidar::map::io::{read_point_cloud, write_ply};
    use std::time::Instant;

    let n: usize = std::env::var("COLMAP_LIDAR_BENCH_POINTS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(20_000_000);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("building.ply");
    {
        let cloud = building_cloud(n, 0.005, 7);
        write_ply(&path, &cloud).unwrap();
    }
    let size_mb = std::fs::metadata(&path).unwrap().len() as f64 / 1e6;
    reset_peak_rss();
    let rss0 = rss_mb();
    let t = Instant::now();
    let (cloud, _) = read_point_cloud(&path).unwrap();
    let load_s = t.elapsed().as_secs_f64();
    let rss_cloud = rss_mb();
    let t = Instant::now();
    let mut index = MapIndex::build(&cloud).unwrap();
    let index_s = t.elapsed().as_secs_f64();
    let rss_index = rss_mb();
    let t = Instant::now();
    let grid = FrustumGrid::build(&cloud, &GridOptions::default()).unwrap();
    let grid_s = t.elapsed().as_secs_f64();
    let peak = peak_rss_mb();
    println!(
        "BENCH map: {} points (building-like, binary PLY with normals, {size_mb:.0} MB)",
        cloud.len()
    );
    println!(
        "BENCH load {load_s:.2} s + index {index_s:.2} s + grid {grid_s:.2} s = {:.2} s \
         ({} threads)",
        load_s + index_s + grid_s,
        rayon::current_num_threads()
    );
    println!(
        "BENCH memory: cloud {:.0} MB, index {:.0} MB (RSS +{:.0} MB, {} cells of {} m), \
         grid {:.0} MB ({} cells); peak RSS during load + index {:.0} MB (process baseline \
         {rss0:.0} MB)",
        rss_cloud - rss0,
        index.memory_bytes() as f64 / 1e6,
        rss_index - rss_cloud,
        index.num_cells(),
        index.cell_size_m(),
        grid.memory_bytes() as f64 / 1e6,
        grid.num_cells(),
        peak
    );

    // Query sets (2 M each), timed on one core:
    // * "near surface": map points moved by 5 cm (Gaussian, per axis), as the
    //   mapper's triangulated points, in random order and in a coherent order
    //   (sorted along a space-filling curve, as a sweep over the map would be);
    // * "mixed": half within 0.3 m of a map point, half anywhere in the box.
    let near = noisy_map_points(&cloud, 2_000_000, 0.05, 9);
    let mixed = random_queries(&cloud, 2_000_000, 8);
    let coherent = {
        let mut keyed: Vec<(u64, Vector3<f64>)> = near
            .iter()
            .map(|q| {
                let l = q - cloud.origin;
                let c = |v: f64| ((v / 0.5).floor() as i64 + 4096) as u64;
                (c(l.x) << 26 | c(l.y) << 13 | c(l.z), *q)
            })
            .collect();
        keyed.sort_by_key(|k| k.0);
        keyed.into_iter().map(|k| k.1).collect::<Vec<_>>()
    };
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    pool.install(|| {
        for (name, queries) in [
            ("near surface, random order", &near),
            ("near surface, coherent order", &coherent),
            ("mixed, random order", &mixed),
        ] {
            for radius in [0.2, 0.5, 1.0, 1.5] {
                let t = Instant::now();
                let found = queries
                    .iter()
                    .filter(|q| index.nearest_within(q, radius).is_some())
                    .count();
                let s = t.elapsed().as_secs_f64();
                println!(
                    "BENCH nearest_within(r = {radius} m), {name}: {:.2} M queries/s on one core \
                     ({found} of {} found)",
                    queries.len() as f64 / s / 1e6,
                    queries.len()
                );
            }
        }
        for (name, queries) in [("near surface", &near), ("mixed", &mixed)] {
            for radius in [0.2, 1.0] {
                let t = Instant::now();
                let found = index
                    .nearest_within_batch(queries, radius)
                    .iter()
                    .filter(|n| n.is_some())
                    .count();
                let s = t.elapsed().as_secs_f64();
                println!(
                    "BENCH nearest_within_batch(r = {radius} m), {name}: {:.2} M queries/s on \
                     one core ({found} found; queries sorted in z-order inside)",
                    queries.len() as f64 / s / 1e6
                );
            }
        }
        for (name, queries) in [("near surface", &near), ("mixed", &mixed)] {
            let t = Instant::now();
            let sum: f64 = queries[..500_000]
                .iter()
                .map(|q| index.nearest(q).map_or(0.0, |n| n.dist_sq))
                .sum();
            let s = t.elapsed().as_secs_f64();
            println!(
                "BENCH nearest (unbounded), {name}: {:.2} M queries/s on one core \
                 (checksum {sum:.1})",
                0.5 / s
            );
            let t = Instant::now();
            let total: usize = queries[..200_000]
                .iter()
                .map(|q| index.k_nearest(q, 10).len())
                .sum();
            let s = t.elapsed().as_secs_f64();
            println!(
                "BENCH k_nearest(10), {name}: {:.2} M queries/s on one core ({total} results)",
                0.2 / s
            );
            let t = Instant::now();
            let total: usize = queries[..200_000]
                .iter()
                .map(|q| index.within_radius(q, 0.1).len())
                .sum();
            let s = t.elapsed().as_secs_f64();
            println!(
                "BENCH within_radius(0.1 m), {name}: {:.2} M queries/s on one core \
                 ({total} results)",
                0.2 / s
            );
        }
    });
    println!(
        "BENCH index memory with the kd-tree built: {:.0} MB",
        index.memory_bytes() as f64 / 1e6
    );
    // The crossover: bounded queries through each backend.
    for (backend, cells) in [("grid", f64::INFINITY), ("kd-tree", 0.0)] {
        index.set_tree_min_radius_cells(cells);
        pool.install(|| {
            for (name, queries) in [("near surface", &near), ("mixed", &mixed)] {
                for radius_cells in [1.0, 2.0, 4.0, 8.0] {
                    let radius = radius_cells * index.cell_size_m();
                    let t = Instant::now();
                    let found = queries[..500_000]
                        .iter()
                        .filter(|q| index.nearest_within(q, radius).is_some())
                        .count();
                    let s = t.elapsed().as_secs_f64();
                    println!(
                        "BENCH {backend}: nearest_within({radius_cells} cells), {name}: {:.2} M \
                         queries/s on one core ({found} found)",
                        0.5 / s
                    );
                }
            }
        });
    }
}

/// `n` map points (chosen at random) moved by Gaussian noise of `sigma_m` per axis.
pub fn noisy_map_points(
    cloud: &PointCloud,
    n: usize,
    sigma_m: f64,
    seed: u64,
) -> Vec<Vector3<f64>> {
    use rand_distr::{Distribution, Normal};
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    // sigma_m is a valid standard deviation.
    let noise = Normal::new(0.0, sigma_m).unwrap();
    (0..n)
        .map(|_| {
            let i = rng.gen_range(0..cloud.len());
            cloud.point_in_map(i)
                + Vector3::new(
                    noise.sample(&mut rng),
                    noise.sample(&mut rng),
                    noise.sample(&mut rng),
                )
        })
        .collect()
}

/// Every query answered by the grid alone and by the kd-tree alone (both
/// forced) gives exactly the same neighbours, in the same order, with the
/// same distances; on axis-aligned lattice clouds (exact ties, kiddo's worst
/// case without the rotation), jittered ones and uniform ones.
#[test]
fn tree_and_grid_backends_agree_exactly() {
    for (name, cloud) in [
        ("lattice building", building_cloud(20_000, 0.0, 21)),
        ("jittered building", building_cloud(20_000, 0.005, 22)),
        ("uniform", uniform_cloud(20_000, 10.0, 23)),
    ] {
        let mut grid = MapIndex::build(&cloud).unwrap();
        grid.set_tree_min_radius_cells(f64::INFINITY);
        let mut tree = MapIndex::build(&cloud).unwrap();
        tree.set_tree_min_radius_cells(0.0);
        let mem_before = tree.memory_bytes();
        assert!(!tree.has_tree(), "{name}: the tree is built lazily");
        let queries = random_queries(&cloud, 300, 24);
        for q in &queries {
            assert_eq!(grid.nearest(q), tree.nearest(q), "{name}: nearest at {q:?}");
            for k in [1, 5, 30] {
                assert_eq!(
                    grid.k_nearest(q, k),
                    tree.k_nearest(q, k),
                    "{name}: k = {k}"
                );
            }
            for radius in [0.05, 0.3, 2.0] {
                assert_eq!(
                    grid.nearest_within(q, radius),
                    tree.nearest_within(q, radius),
                    "{name}: r = {radius}"
                );
                assert_eq!(
                    grid.within_radius(q, radius),
                    tree.within_radius(q, radius),
                    "{name}: within r = {radius}"
                );
                assert_eq!(
                    grid.k_nearest_within(q, 6, radius),
                    tree.k_nearest_within(q, 6, radius),
                    "{name}: k within r = {radius}"
                );
            }
        }
        assert!(tree.has_tree() && !grid.has_tree(), "{name}");
        // The tree's points and items: at least 16 bytes a point.
        assert!(
            tree.memory_bytes() >= mem_before + 16 * cloud.len(),
            "{name}: {} vs {mem_before}",
            tree.memory_bytes()
        );
        assert_eq!(grid.memory_bytes(), mem_before);
    }
}

/// On the 6 x 6 x 6 integer lattice (8 equidistant neighbours around a
/// cube's centre: ties up to the grid's quantisation) the tree path returns
/// the grid's answer, and the right set.
#[test]
fn tree_backend_on_lattice_ties() {
    let mut points = Vec::new();
    for x in 0..6 {
        for y in 0..6 {
            for z in 0..6 {
                points.push([x as f32, y as f32, z as f32]);
            }
        }
    }
    let cloud = cloud_from(points);
    let mut index = MapIndex::build(&cloud).unwrap();
    index.set_tree_min_radius_cells(0.0);
    let mut grid = MapIndex::build(&cloud).unwrap();
    grid.set_tree_min_radius_cells(f64::INFINITY);
    let q = cloud.origin + Vector3::new(2.5, 2.5, 2.5);
    let cube: std::collections::BTreeSet<u32> = (0..cloud.len() as u32)
        .filter(|&i| (dist(&cloud, i as usize, &q) - 0.75f64.sqrt()).abs() < 1e-9)
        .collect();
    assert_eq!(cube.len(), 8);
    let k3 = index.k_nearest(&q, 3);
    assert_eq!(k3, grid.k_nearest(&q, 3));
    assert!(k3.iter().all(|n| cube.contains(&n.point_idx)));
    assert_eq!(index.nearest(&q), grid.nearest(&q));
    assert_eq!(index.nearest_within(&q, 1.0), grid.nearest_within(&q, 1.0));
    let w = index.within_radius(&q, 1.0);
    assert_eq!(w, grid.within_radius(&q, 1.0));
    assert_eq!(
        w.iter()
            .map(|n| n.point_idx)
            .collect::<std::collections::BTreeSet<_>>(),
        cube
    );
    assert!(index.within_radius(&q, 0.8).is_empty());
    assert!(index.k_nearest_within(&q, 2, 0.8).is_empty());
    assert!(index.nearest_within(&q, 0.8).is_none());
    // Far from the map: the unbounded query still answers.
    let far = cloud.origin + Vector3::new(100.0, -50.0, 20.0);
    assert_eq!(index.nearest(&far), grid.nearest(&far));
    assert!(
        (index.nearest(&far).unwrap().dist_sq.sqrt() - oracle(&cloud, &far)[0].0).abs() < TOL_M
    );
}
