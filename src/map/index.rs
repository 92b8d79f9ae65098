//! Nearest-neighbour index of the LiDAR map, behind a small API of our own.
//!
//! A sparse two-level voxel grid, built for the queries the mapper makes
//! (nearest map point within a radius of 0.1-1.5 m of points near surfaces)
//! on maps of tens of millions of points:
//!
//! * **cells** (default 0.2 m, [`IndexOptions::cell_size_m`]) hold the points,
//!   stored contiguously per cell (compressed sparse rows) as 16-bit
//!   coordinates relative to the cell's corner (cell / 65535: 3 µm for 0.2 m
//!   cells), x, y and z runs one after the other per cell, plus the point's
//!   index in the cloud;
//! * **blocks** of 8 x 8 x 8 cells, found through a small open-addressing hash
//!   table, each with a 512-bit occupancy mask and the index of its first cell
//!   per z-layer, so a cell's position is a popcount away and empty space is
//!   skipped a block or a mask word at a time.
//!
//! A query scans the query's own cell first (near a surface it holds the
//! nearest point), then only the cells whose box lies within the best distance
//! so far: a handful of cache lines, whatever the map's size. Queries far from
//! the map cost at most the blocks within the radius; unbounded queries
//! ([`MapIndex::nearest`], [`MapIndex::k_nearest`]) widen the radius
//! geometrically (cubes of cells growing by half around the query).
//!
//! The index costs 10 bytes a point plus 4 bytes an occupied cell and ~100
//! bytes an occupied block; the build sorts 16 bytes a point (parallel) and
//! frees them.
//!
//! Results are exact for the stored coordinates and deterministic: the nearest
//! by (squared distance, point index), whatever the visiting order. Accuracy:
//! stored coordinates are within half a quantisation step per axis (1.5 µm
//! for 0.2 m cells) of the cloud's f32 coordinates, and squared distances are
//! computed in f32 relative to the cell, so returned distances carry an error
//! below 1.4e-5 of the cell size (2.7 µm for 0.2 m cells), independent of the
//! map's extent. Use [`PointCloud::point_in_map`] for the exact point.
//!
//! A second backend, a kiddo 6 immutable kd-tree of the same (dequantised)
//! points rotated by a fixed generic rotation, is built lazily on first use
//! when enabled with [`MapIndex::set_tree_min_radius_cells`] (off by
//! default: slower than the grid in every measured case, see
//! [`DEFAULT_TREE_MIN_RADIUS_CELLS`]). Its candidates are re-ranked with the
//! grid's own distances, so both backends return identical results.
use std::collections::BinaryHeap;
use std::num::NonZeroUsize;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::OnceLock;

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use nalgebra::{Matrix3, Rotation3, Vector3};
use rayon::prelude::*;

use super::cloud::PointCloud;

/// Errors building a [`MapIndex`].
#[derive(Debug, thiserror::Error)]
pub enum IndexError {
    #[error("the map has {0} points; the index holds at most 2^32 - 1")]
    TooManyPoints(usize),
    #[error("map point {index} has a non-finite coordinate")]
    NonFinitePoint { index: usize },
    #[error("building the index failed: {0}")]
    Construction(String),
    #[error("index cell size must be finite and positive, got {0} m")]
    BadCellSize(f64),
    #[error(
        "the map spans {cells} index cells of {cell_size_m} m along one axis; at most {max} are \
         supported (use larger cells)"
    )]
    TooLarge {
        cells: i64,
        cell_size_m: f64,
        max: i64,
    },
}

/// One neighbour found by a query.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Neighbour {
    /// Index of the point in the [`PointCloud`] the index was built from.
    pub point_idx: u32,
    /// Squared Euclidean distance to the query point (m²).
    pub dist_sq: f64,
}

/// Map points sampled for [`MapIndex::surface_spacing_m`] by the mapper and
/// `depth` (an even stride; about 0.1 s on 1.5 million points).
pub const SPACING_SAMPLES: usize = 20_000;

/// Options of [`MapIndex::build_with_options`].
#[derive(Clone, Debug, Default, PartialEq)]
pub struct IndexOptions {
    /// Edge of a grid cell (m). Default `None`: automatic, 0.2 m (about
    /// 40-60 points a cell on a surface sampled every 2.5-3 cm; the mapper's
    /// query radii, 0.1-1.5 m, span a few cells), rebuilt once with a cell
    /// size scaled to give about 32 points an occupied cell when the mean
    /// is below 8 or above 256 (sparser or denser maps).
    pub cell_size_m: Option<f64>,
}

/// Automatic cell size: the first try, and the bounds of the mean number of
/// points an occupied cell outside which the index is rebuilt once.
const AUTO_CELL_M: f64 = 0.2;
const AUTO_MIN_MEAN: f64 = 8.0;
const AUTO_MAX_MEAN: f64 = 256.0;
const AUTO_TARGET_MEAN: f64 = 32.0;

/// Cells per block edge is `1 << BLOCK_SHIFT` (8: 512 cells, one `u64` mask
/// word per z-layer).
const BLOCK_SHIFT: i64 = 3;
const BLOCK_EDGE: i64 = 1 << BLOCK_SHIFT;
/// Bits per axis of a packed block key.
const KEY_AXIS_BITS: u32 = 18;
/// Cells per axis the grid can span.
const MAX_CELLS_PER_AXIS: i64 = 1 << (KEY_AXIS_BITS as i64 + BLOCK_SHIFT);
/// Quantisation steps across a cell.
const STEPS: f64 = 65535.0;
/// Neighbour cells within this distance (cells) of a query are prefetched
/// before its own cell is scanned.
const NEIGHBOUR_PREFETCH_CELLS: f64 = 0.25;
/// Empty slot of the block hash table (no valid key has all bits set).
const EMPTY_KEY: u64 = u64::MAX;
/// No answer, in a batch's heap keys (a NaN distance: no real key).
const NO_ANSWER: u64 = u64::MAX;
/// A batch query's point and cell are prefetched this many queries ahead.
const BATCH_PREFETCH_AHEAD: usize = 8;

fn pack_block(b: [i64; 3]) -> u64 {
    ((b[0] as u64) << (2 * KEY_AXIS_BITS)) | ((b[1] as u64) << KEY_AXIS_BITS) | (b[2] as u64)
}

fn unpack_block(key: u64) -> [i64; 3] {
    let m = (1u64 << KEY_AXIS_BITS) - 1;
    [
        (key >> (2 * KEY_AXIS_BITS)) as i64,
        ((key >> KEY_AXIS_BITS) & m) as i64,
        (key & m) as i64,
    ]
}

/// 8 x 8 x 8 cells: bit `x | y << 3` of word `z` is set when cell (x, y, z)
/// of the block holds points; the cells of word `z` are numbered from
/// `first_cell[z]` in bit order. For an empty word, `first_cell[z]` is the
/// id of the next occupied cell in memory order (in a later z-layer or
/// block; the number of cells after the last), so [`Block::cell_id`] of any
/// cell, occupied or not, is that of the first occupied cell at or after it
/// in memory order.
#[derive(Clone, Copy, Debug)]
struct Block {
    occupied: [u64; 8],
    first_cell: [u32; 8],
}

impl Block {
    #[inline]
    fn cell_id(&self, z: usize, bit: u32) -> u32 {
        self.first_cell[z] + (self.occupied[z] & ((1u64 << bit) - 1)).count_ones()
    }
}

/// Open-addressing hash table (linear probing) from block keys to block ids.
#[derive(Clone, Debug)]
struct BlockTable {
    keys: Vec<u64>,
    ids: Vec<u32>,
    shift: u32,
}

impl BlockTable {
    fn new(block_keys: &[u64]) -> Self {
        let capacity = (2 * block_keys.len()).next_power_of_two().max(2);
        let shift = 64 - capacity.trailing_zeros();
        let mut table = Self {
            keys: vec![EMPTY_KEY; capacity],
            ids: vec![0; capacity],
            shift,
        };
        let mask = capacity - 1;
        for (id, &key) in block_keys.iter().enumerate() {
            let mut s = table.slot(key);
            while table.keys[s] != EMPTY_KEY {
                s = (s + 1) & mask;
            }
            table.keys[s] = key;
            table.ids[s] = id as u32;
        }
        table
    }

    #[inline]
    fn slot(&self, key: u64) -> usize {
        (key.wrapping_mul(0x9E37_79B9_7F4A_7C15) >> self.shift) as usize
    }

    #[inline]
    fn get(&self, key: u64) -> Option<u32> {
        let mask = self.keys.len() - 1;
        let mut s = self.slot(key);
        loop {
            let k = self.keys[s];
            if k == key {
                return Some(self.ids[s]);
            }
            if k == EMPTY_KEY {
                return None;
            }
            s = (s + 1) & mask;
        }
    }
}

/// `floor(x)` as an integer, saturating (`as`); without the libm call that
/// `f64::floor` is on baseline x86-64.
#[inline]
fn floor_i64(x: f64) -> i64 {
    let t = x as i64;
    if (t as f64) > x {
        t.saturating_sub(1)
    } else {
        t
    }
}

/// The grid cell holding the point `g` (continuous grid-cell coordinates).
#[inline]
fn grid_cell(g: &[f64; 3]) -> [i64; 3] {
    [floor_i64(g[0]), floor_i64(g[1]), floor_i64(g[2])]
}

/// Hints the processor to fetch the cache line holding `value` (no effect
/// on results).
#[inline]
fn prefetch<T>(value: &T) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        // SAFETY: SSE is part of the x86-64 baseline, and a prefetch of a
        // valid address has no effect but on caches.
        unsafe { _mm_prefetch::<_MM_HINT_T0>((value as *const T).cast::<i8>()) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = value;
}

/// Nearest-neighbour index of a [`PointCloud`] (see the module doc). Holds no
/// reference to the cloud; results are point indices into it.
pub struct MapIndex {
    /// The cloud's local origin (map frame, metres).
    origin: Vector3<f64>,
    cell_size_m: f64,
    /// Integer coordinates (cells from the cloud's origin) of grid cell 0.
    min_cell: [i64; 3],
    /// Cells spanned per axis (grid cells are `0..extent`).
    extent: [i64; 3],
    table: BlockTable,
    /// Packed keys of the blocks, increasing; `blocks[i]` is block `block_keys[i]`.
    block_keys: Vec<u64>,
    blocks: Vec<Block>,
    /// `cell_start[c]..cell_start[c + 1]` is cell `c`'s range in the point arrays.
    cell_start: Vec<u32>,
    /// One contiguous run per cell: for the cell's `n` points at positions
    /// `start..start + n`, `data[5 * start..5 * (start + n)]` holds their x
    /// coordinates, then the y, then the z (relative to the cell's corner, in
    /// steps of `cell_size_m / 65535`), then the low and the high 16 bits of
    /// their indices in the cloud (increasing within a cell). A query touches
    /// one run of memory a cell; the coordinate runs vectorise.
    data: Vec<u16>,
    num_points: usize,
    /// The kd-tree backend, built on first use (`None` inside when the map
    /// is empty or kiddo failed to build: the grid answers then).
    kd: OnceLock<Option<KdBackend>>,
    /// Bounded queries with a radius above this many cells use the kd-tree.
    tree_min_radius_cells: f64,
}

/// Default of [`MapIndex::set_tree_min_radius_cells`]: the kd-tree is off.
/// Measured on a 2 M point building-like map (one core, `bench_index`), the
/// grid beat the tree (with its exact re-ranking) for every query type:
/// unbounded nearest 1.60 vs 0.48 M/s near surfaces, 0.41 vs 0.18 M/s mixed;
/// k_nearest(10) 0.66 vs 0.37 and 0.20 vs 0.14 M/s; nearest_within at 1-8
/// cells 0.6-2.5 vs 0.2-0.55 M/s. Re-measure on 20 M point maps before
/// lowering it.
pub const DEFAULT_TREE_MIN_RADIUS_CELLS: f64 = f64::INFINITY;

/// Relative and absolute (times the coordinates' magnitude) error bound used
/// to widen kd-tree searches before the exact re-ranking: f32 rotated
/// coordinates and f32 squared distances are accurate to a few 2^-24; this is
/// about 8 times that.
const TREE_REL_ERR: f64 = 1e-6;
/// Extra neighbours asked of the kd-tree beyond `k`, so the exact re-ranking
/// usually needs no second query.
const TREE_EXTRA: usize = 4;

/// The lazily built kd-tree: kiddo's immutable tree of the grid's points
/// (dequantised, relative to the grid's centre, rotated by
/// [`tree_rotation`]), items = positions in the grid's point arrays.
struct KdBackend {
    tree: ImmutableKdTree<f32, 3>,
    /// Cell id of each position in the point arrays.
    cell_of_pos: Vec<u32>,
    /// Grid coordinates of each cell.
    cell_coord: Vec<[i32; 3]>,
    /// Centre of the tree's frame (grid-cell coordinates).
    centre_g: [f64; 3],
    /// Rotation applied to grid offsets (metres) before they enter the tree.
    rotation: Matrix3<f64>,
    /// Largest norm of a point in the tree's frame (m).
    max_norm_m: f64,
}

/// The fixed rotation applied inside the kd-tree: generic angles, so no
/// axis-aligned wall or floor of the map stays aligned with a tree axis
/// (kiddo is 17-35x slower on axis-aligned planar clouds otherwise);
/// distances do not change.
fn tree_rotation() -> Matrix3<f64> {
    Rotation3::from_euler_angles(0.371_4, 0.517_3, 0.834_2).into_inner()
}

impl std::fmt::Debug for MapIndex {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MapIndex")
            .field("origin", &self.origin)
            .field("num_points", &self.num_points)
            .field("cell_size_m", &self.cell_size_m)
            .field("num_cells", &(self.cell_start.len().saturating_sub(1)))
            .field("num_blocks", &self.blocks.len())
            .finish()
    }
}

/// The best candidate so far of a single-nearest query: squared distance in
/// squared quantisation steps, its cell and position in the index.
#[derive(Clone, Copy)]
struct Best {
    d: f32,
    cell: u32,
    pos: u32,
}

/// Heap key of a k-nearest query: `(squared distance bits, point index)`;
/// distances are non-negative, so their bit patterns order like their values.
#[inline]
fn heap_key(d: f32, idx: u32) -> u64 {
    (u64::from(d.to_bits()) << 32) | u64::from(idx)
}

#[inline]
fn key_dist(key: u64) -> f32 {
    f32::from_bits((key >> 32) as u32)
}

/// Squared distance (squared steps) from `q` to the stored point
/// `(x, y, z)`, both cell-local: the one formula of every query (the kd-tree's
/// re-ranking included), so all agree to the bit.
#[inline(always)]
fn dist_sq(q: [f32; 3], x: u16, y: u16, z: u16) -> f32 {
    let dx = q[0] - f32::from(x);
    let dy = q[1] - f32::from(y);
    let dz = q[2] - f32::from(z);
    dx * dx + dy * dy + dz * dz
}

/// How far (cells) from a query a search for points within `limit`
/// (squared steps, inclusive; may be infinite) reaches: the one formula of
/// [`MapIndex::within_radius`] and the growing searches, so they bound the
/// same ball by the same cells.
#[inline]
fn reach_cells(limit: f32) -> f64 {
    if limit.is_finite() {
        f64::from(limit).sqrt() * (1.0 / STEPS)
    } else {
        f64::INFINITY
    }
}

/// Lanes of the scan kernels: chunks of this many points are computed
/// together (one AVX2 register, two SSE ones).
const LANES: usize = 8;

/// [`dist_sq`] of `LANES` points (vectorised).
#[inline(always)]
fn chunk_dist_sq(q: [f32; 3], x: &[u16], y: &[u16], z: &[u16]) -> [f32; LANES] {
    let (x, y, z) = (&x[..LANES], &y[..LANES], &z[..LANES]);
    let mut d = [0.0; LANES];
    for l in 0..LANES {
        d[l] = dist_sq(q, x[l], y[l], z[l]);
    }
    d
}

/// Smallest [`dist_sq`] from `q` to the points of the runs `xs`, `ys`, `zs`
/// (infinite for none). Lane-wise minima over whole chunks, and over the
/// last `LANES` points for the rest (the minimum does not mind points seen
/// twice); short runs one by one.
#[inline(always)]
fn runs_min_impl(xs: &[u16], ys: &[u16], zs: &[u16], q: [f32; 3]) -> f32 {
    // Not `f32::min`: no NaN occurs, and this is one `minps`.
    let min = |a: f32, b: f32| if b < a { b } else { a };
    let n = xs.len();
    if n < LANES {
        return (0..n).fold(f32::INFINITY, |m, k| {
            min(m, dist_sq(q, xs[k], ys[k], zs[k]))
        });
    }
    let mut acc = [f32::INFINITY; LANES];
    let mut add = |d: [f32; LANES]| {
        for l in 0..LANES {
            acc[l] = min(acc[l], d[l]);
        }
    };
    let (cx, cy, cz) = (
        xs.chunks_exact(LANES),
        ys.chunks_exact(LANES),
        zs.chunks_exact(LANES),
    );
    let rest = cx.remainder().len();
    for ((x, y), z) in cx.zip(cy).zip(cz) {
        add(chunk_dist_sq(q, x, y, z));
    }
    if rest > 0 {
        let t = n - LANES;
        add(chunk_dist_sq(q, &xs[t..], &ys[t..], &zs[t..]));
    }
    acc.into_iter().fold(f32::INFINITY, min)
}

/// The smallest [`dist_sq`] from `q` to the points of the runs `xs`, `ys`,
/// `zs` and the first position where it occurs (`(infinity, 0)` for no
/// point): lane-wise minima and their first positions, then the lanes'
/// minimum at its smallest position (positions increase along a lane, the
/// last overlapping chunk included).
#[inline(always)]
fn runs_argmin_impl(xs: &[u16], ys: &[u16], zs: &[u16], q: [f32; 3]) -> (f32, usize) {
    let n = xs.len();
    let mut acc = [f32::INFINITY; LANES];
    let mut at = [0usize; LANES];
    let mut add = |k: usize| {
        let d = chunk_dist_sq(q, &xs[k..], &ys[k..], &zs[k..]);
        for l in 0..LANES {
            if d[l] < acc[l] {
                acc[l] = d[l];
                at[l] = k + l;
            }
        }
    };
    if n < LANES {
        let mut best = (f32::INFINITY, 0);
        for k in 0..n {
            let d = dist_sq(q, xs[k], ys[k], zs[k]);
            if d < best.0 {
                best = (d, k);
            }
        }
        return best;
    }
    for k in (0..n - LANES + 1).step_by(LANES) {
        add(k);
    }
    if !n.is_multiple_of(LANES) {
        add(n - LANES);
    }
    lanes_argmin(&acc, &at)
}

/// The smallest of the lanes' minima `acc`, at the smallest of the
/// positions `at` that reach it.
#[inline(always)]
fn lanes_argmin(acc: &[f32; LANES], at: &[usize; LANES]) -> (f32, usize) {
    let mut best = (acc[0], at[0]);
    for l in 1..LANES {
        if acc[l] < best.0 || (acc[l] == best.0 && at[l] < best.1) {
            best = (acc[l], at[l]);
        }
    }
    best
}

/// [`runs_argmin_impl`] with AVX2 intrinsics (a compare and two blends a
/// chunk; the compiler does not vectorise the positions by itself). Code
/// compiled without AVX2 calls it in `unsafe`, after checking that the
/// processor has AVX2 ([`runs_argmin`]).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn runs_argmin_avx2(xs: &[u16], ys: &[u16], zs: &[u16], q: [f32; 3]) -> (f32, usize) {
    use std::arch::x86_64::*;
    let n = xs.len();
    if n < LANES {
        return runs_argmin_impl(xs, ys, zs, q);
    }
    let (qx, qy, qz) = (
        _mm256_set1_ps(q[0]),
        _mm256_set1_ps(q[1]),
        _mm256_set1_ps(q[2]),
    );
    let lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    let mut acc = _mm256_set1_ps(f32::INFINITY);
    let mut at = _mm256_setzero_si256();
    let mut add = |k: usize| {
        let load = |v: &[u16]| {
            let chunk = &v[k..k + LANES];
            // SAFETY: `chunk` holds 8 u16, the 16 bytes read; the load
            // needs no alignment.
            let w = unsafe { _mm_loadu_si128(chunk.as_ptr().cast()) };
            _mm256_cvtepi32_ps(_mm256_cvtepu16_epi32(w))
        };
        // dist_sq's operations in its order: (dx dx + dy dy) + dz dz.
        let dx = _mm256_sub_ps(qx, load(xs));
        let dy = _mm256_sub_ps(qy, load(ys));
        let dz = _mm256_sub_ps(qz, load(zs));
        let d = _mm256_add_ps(
            _mm256_add_ps(_mm256_mul_ps(dx, dx), _mm256_mul_ps(dy, dy)),
            _mm256_mul_ps(dz, dz),
        );
        let better = _mm256_cmp_ps::<_CMP_LT_OQ>(d, acc);
        acc = _mm256_blendv_ps(acc, d, better);
        // k < 2^32 - 1: its bits as u32, in an i32 lane (read back below).
        let pos = _mm256_add_epi32(_mm256_set1_epi32(k as u32 as i32), lane);
        at = _mm256_castps_si256(_mm256_blendv_ps(
            _mm256_castsi256_ps(at),
            _mm256_castsi256_ps(pos),
            better,
        ));
    };
    for k in (0..n - LANES + 1).step_by(LANES) {
        add(k);
    }
    if !n.is_multiple_of(LANES) {
        add(n - LANES);
    }
    let (mut acc_l, mut at_l) = ([0f32; LANES], [0i32; LANES]);
    // SAFETY: both arrays hold 32 bytes, the bytes written; the stores
    // need no alignment.
    unsafe {
        _mm256_storeu_ps(acc_l.as_mut_ptr(), acc);
        _mm256_storeu_si256(at_l.as_mut_ptr().cast(), at);
    }
    // Positions are below the run's length, itself below 2^32 - 1 (the
    // index holds fewer points), and the lanes hold them modulo 2^32 (the
    // i32 additions wrap): read them as unsigned, also at 2^31 and above.
    lanes_argmin(&acc_l, &at_l.map(|p| p as u32 as usize))
}

/// [`runs_min_impl`] compiled for AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn runs_min_avx2(xs: &[u16], ys: &[u16], zs: &[u16], q: [f32; 3]) -> f32 {
    runs_min_impl(xs, ys, zs, q)
}

/// Whether the AVX2 builds of the scan kernels can run (checked once, then
/// a cached flag). Both builds compute the same IEEE operations in the same
/// order (Rust does not fuse multiply-adds) and pick the same position, so
/// answers do not depend on it. Other targets use the scalar builds only.
#[cfg(target_arch = "x86_64")]
#[inline]
fn has_avx2() -> bool {
    std::arch::is_x86_feature_detected!("avx2")
}

/// [`runs_min_impl`], with AVX2 when available.
#[inline]
fn runs_min(xs: &[u16], ys: &[u16], zs: &[u16], q: [f32; 3]) -> f32 {
    #[cfg(target_arch = "x86_64")]
    if has_avx2() {
        // SAFETY: the processor has AVX2 (checked above).
        return unsafe { runs_min_avx2(xs, ys, zs, q) };
    }
    runs_min_impl(xs, ys, zs, q)
}

/// [`runs_argmin_impl`], with AVX2 when available.
#[inline]
fn runs_argmin(xs: &[u16], ys: &[u16], zs: &[u16], q: [f32; 3]) -> (f32, usize) {
    #[cfg(target_arch = "x86_64")]
    if has_avx2() {
        // SAFETY: the processor has AVX2 (checked above).
        return unsafe { runs_argmin_avx2(xs, ys, zs, q) };
    }
    runs_argmin_impl(xs, ys, zs, q)
}

/// A query run by [`MapIndex::search_growing`].
trait Search {
    /// Current bound on the squared distance of a useful point (squared
    /// steps, inclusive).
    fn limit(&self) -> f32;
    /// Scans cell `id` (grid cell `c`) for the query `g`.
    fn scan(&mut self, index: &MapIndex, id: u32, c: [i64; 3], g: &[f64; 3]);
}

/// Single nearest point within `bound` (its cloud index is read on ties and
/// once at the end).
struct NearestSearch {
    bound: f32,
    best: Option<Best>,
}

impl Search for NearestSearch {
    #[inline]
    fn limit(&self) -> f32 {
        self.best.map_or(self.bound, |b| b.d)
    }

    /// The first cell scanned gives the minimum and its position in one
    /// pass; the next ones their minimum only (a cheaper pass), and their
    /// position only when they can win: most lose.
    #[inline]
    fn scan(&mut self, index: &MapIndex, id: u32, c: [i64; 3], g: &[f64; 3]) {
        let q = MapIndex::local_query(g, c);
        let (xs, ys, zs, start) = index.cell_coords(id);
        let (d, k) = if self.best.is_none() {
            runs_argmin(xs, ys, zs, q)
        } else {
            let d = runs_min(xs, ys, zs, q);
            if d > self.limit() {
                return;
            }
            runs_argmin(xs, ys, zs, q)
        };
        // `limit` is the best distance so far (<= bound) or the bound; no
        // NaN occurs (finite query, bound checked).
        if d > self.limit() {
            return;
        }
        let pos = start + k;
        let better = match self.best {
            None => true,
            Some(b) => {
                d < b.d || index.point_index(id, pos) < index.point_index(b.cell, b.pos as usize)
            }
        };
        if better {
            self.best = Some(Best {
                d,
                cell: id,
                pos: pos as u32,
            });
        }
    }
}

/// The `k` nearest points within `bound`, in a max-heap of [`heap_key`]s.
struct KSearch {
    k: usize,
    bound: f32,
    heap: BinaryHeap<u64>,
}

impl Search for KSearch {
    #[inline]
    fn limit(&self) -> f32 {
        match self.heap.peek() {
            Some(&worst) if self.heap.len() >= self.k => key_dist(worst),
            _ => self.bound,
        }
    }

    fn scan(&mut self, index: &MapIndex, id: u32, c: [i64; 3], g: &[f64; 3]) {
        let q = MapIndex::local_query(g, c);
        let mut lim = self.limit();
        let (xs, ys, zs, start) = index.cell_coords(id);
        for (k, ((&x, &y), &z)) in xs.iter().zip(ys).zip(zs).enumerate() {
            let d = dist_sq(q, x, y, z);
            if !(d <= lim) {
                continue;
            }
            let key = heap_key(d, index.point_index(id, start + k));
            if self.heap.len() < self.k {
                self.heap.push(key);
            } else if self.heap.peek().is_some_and(|&worst| key < worst) {
                self.heap.pop();
                self.heap.push(key);
            } else {
                continue;
            }
            lim = self.limit();
        }
    }
}

impl MapIndex {
    /// Builds the index of every point of `cloud` with the default options.
    /// Parallel (rayon); the index does not depend on the number of threads.
    pub fn build(cloud: &PointCloud) -> Result<Self, IndexError> {
        Self::build_with_options(cloud, &IndexOptions::default())
    }

    /// Builds the index of every point of `cloud`.
    pub fn build_with_options(
        cloud: &PointCloud,
        options: &IndexOptions,
    ) -> Result<Self, IndexError> {
        if let Some(s) = options.cell_size_m {
            return Self::build_with_cell_size(cloud, s);
        }
        let first = Self::build_with_cell_size(cloud, AUTO_CELL_M)?;
        let mean = first.len() as f64 / first.num_cells().max(1) as f64;
        if first.is_empty() || (AUTO_MIN_MEAN..=AUTO_MAX_MEAN).contains(&mean) {
            return Ok(first);
        }
        // Points a cell scale with the cell's area on surfaces.
        let s = (AUTO_CELL_M * (AUTO_TARGET_MEAN / mean).sqrt()).clamp(0.01, 10.0);
        drop(first);
        match Self::build_with_cell_size(cloud, s) {
            Err(IndexError::TooLarge { .. }) => Self::build_with_cell_size(cloud, AUTO_CELL_M),
            other => other,
        }
    }

    fn build_with_cell_size(cloud: &PointCloud, s: f64) -> Result<Self, IndexError> {
        if !(s.is_finite() && s > 0.0) {
            return Err(IndexError::BadCellSize(s));
        }
        let n = cloud.len();
        if n >= u32::MAX as usize {
            return Err(IndexError::TooManyPoints(n));
        }
        if let Some(index) = cloud.first_non_finite_point() {
            return Err(IndexError::NonFinitePoint { index });
        }
        let inv = 1.0 / s;
        let cell_of = |p: &[f32; 3]| -> [i64; 3] {
            [
                floor_i64(f64::from(p[0]) * inv),
                floor_i64(f64::from(p[1]) * inv),
                floor_i64(f64::from(p[2]) * inv),
            ]
        };
        let (min_cell, max_cell) = super::cloud::cell_bounds(&cloud.points, cell_of);
        let (min_cell, extent) = if n == 0 {
            ([0; 3], [0; 3])
        } else {
            let extent = [
                max_cell[0] - min_cell[0] + 1,
                max_cell[1] - min_cell[1] + 1,
                max_cell[2] - min_cell[2] + 1,
            ];
            if let Some(&cells) = extent.iter().find(|&&e| e > MAX_CELLS_PER_AXIS) {
                return Err(IndexError::TooLarge {
                    cells,
                    cell_size_m: s,
                    max: MAX_CELLS_PER_AXIS,
                });
            }
            (min_cell, extent)
        };
        // (block key << 9 | cell bit in block, point index), sorted: blocks in
        // key order, cells by (z, y, x) in a block, points by index in a cell.
        let mut pairs: Vec<(u64, u32)> = cloud
            .points
            .par_iter()
            .enumerate()
            .map(|(i, p)| {
                let c = cell_of(p);
                let g = [c[0] - min_cell[0], c[1] - min_cell[1], c[2] - min_cell[2]];
                let block = pack_block([
                    g[0] >> BLOCK_SHIFT,
                    g[1] >> BLOCK_SHIFT,
                    g[2] >> BLOCK_SHIFT,
                ]);
                let m = BLOCK_EDGE - 1;
                let bit = ((g[2] & m) << 6) | ((g[1] & m) << 3) | (g[0] & m);
                ((block << 9) | bit as u64, i as u32)
            })
            .collect();
        pairs.par_sort_unstable();
        let mut block_keys: Vec<u64> = Vec::new();
        let mut blocks: Vec<Block> = Vec::new();
        let mut cell_start: Vec<u32> = Vec::new();
        let mut last_key = u64::MAX;
        for (k, &(key, _)) in pairs.iter().enumerate() {
            if key == last_key {
                continue;
            }
            last_key = key;
            let block_key = key >> 9;
            if block_keys.last() != Some(&block_key) {
                block_keys.push(block_key);
                blocks.push(Block {
                    occupied: [0; 8],
                    first_cell: [0; 8],
                });
            }
            let cell_id = cell_start.len() as u32;
            cell_start.push(k as u32);
            // A block was pushed above: `last` cannot fail.
            let block = blocks.last_mut().expect("a block exists");
            let (z, bit) = (((key >> 6) & 7) as usize, key & 63);
            if block.occupied[z] == 0 {
                block.first_cell[z] = cell_id;
            }
            block.occupied[z] |= 1u64 << bit;
        }
        cell_start.push(n as u32);
        // Empty z-layers: the next occupied cell's id, walking backwards
        // from the end (see `Block`).
        let mut next = (cell_start.len() - 1) as u32;
        for block in blocks.iter_mut().rev() {
            for z in (0..8).rev() {
                if block.occupied[z] == 0 {
                    block.first_cell[z] = next;
                } else {
                    next = block.first_cell[z];
                }
            }
        }
        let table = BlockTable::new(&block_keys);

        // Groups of whole cells of about 32k points, quantised in parallel.
        let mut groups = Vec::new();
        let mut group_start = 0usize;
        for c in 0..cell_start.len() - 1 {
            let end = cell_start[c + 1] as usize;
            if end - cell_start[group_start] as usize >= 1 << 15 || c + 2 == cell_start.len() {
                groups.push((group_start, c + 1));
                group_start = c + 1;
            }
        }
        let step = s / STEPS;
        // The groups' runs, cut out of the final array (no copy).
        let mut data = vec![0u16; 5 * n];
        advise_huge_pages(&mut data);
        let mut runs: Vec<&mut [u16]> = Vec::with_capacity(groups.len());
        let mut rest: &mut [u16] = &mut data;
        for &(c0, c1) in &groups {
            let len = 5 * (cell_start[c1] - cell_start[c0]) as usize;
            let (run, tail) = rest.split_at_mut(len);
            runs.push(run);
            rest = tail;
        }
        groups
            .par_iter()
            .zip(runs.into_par_iter())
            .for_each(|(&(c0, c1), out)| {
                let first = cell_start[c0] as usize;
                for c in c0..c1 {
                    let (start, end) = (cell_start[c] as usize, cell_start[c + 1] as usize);
                    let count = end - start;
                    let base = 5 * (start - first);
                    for (k, &(key, i)) in pairs[start..end].iter().enumerate() {
                        let b = unpack_block(key >> 9);
                        let local = [
                            (key & 7) as i64,
                            ((key >> 3) & 7) as i64,
                            ((key >> 6) & 7) as i64,
                        ];
                        let p = cloud.points[i as usize];
                        for a in 0..3 {
                            let cell = (b[a] << BLOCK_SHIFT) + local[a] + min_cell[a];
                            let steps = (f64::from(p[a]) - cell as f64 * s) / step;
                            // Within [0, 65535] up to rounding: `as`
                            // saturates, +0.5 rounds.
                            out[base + a * count + k] = (steps + 0.5).clamp(0.0, STEPS) as u16;
                        }
                        out[base + 3 * count + k] = i as u16;
                        out[base + 4 * count + k] = (i >> 16) as u16;
                    }
                }
            });
        drop(pairs);
        Ok(Self {
            origin: cloud.origin,
            cell_size_m: s,
            min_cell,
            extent,
            table,
            block_keys,
            blocks,
            cell_start,
            data,
            num_points: n,
            kd: OnceLock::new(),
            tree_min_radius_cells: DEFAULT_TREE_MIN_RADIUS_CELLS,
        })
    }

    pub fn len(&self) -> usize {
        self.num_points
    }

    /// The map's typical sample spacing on its surfaces (m): the side of the
    /// square of surface one point stands for, `sqrt(pi / k) * r_k` with
    /// `r_k` the median distance from a point to its `k = 8`th nearest
    /// neighbour (for points on a surface, `k` neighbours fill a disc of
    /// radius `r_k`; a square grid of spacing `s`, whose 8th neighbour lies at
    /// `sqrt(2) s`, gives `sqrt(pi / 4) s = 0.89 s`). Over at most
    /// `max_samples` points taken at an even stride (deterministic); points
    /// without 8 neighbours within 2 m (outliers, stray returns) are skipped.
    /// `None` when no sampled point has them. `cloud` is the cloud the index
    /// was built from.
    /// ([`SPACING_SAMPLES`] is the count the mapper, `depth` and the normal
    /// estimation use.)
    pub fn surface_spacing_m(&self, cloud: &PointCloud, max_samples: usize) -> Option<f64> {
        let n = cloud.len();
        if max_samples == 0 {
            return None;
        }
        let stride = n.div_ceil(max_samples).max(1);
        self.spacing_among_m(cloud, (0..n).step_by(stride))
    }

    /// [`Self::surface_spacing_m`] over the steep points of `cloud` only:
    /// those whose normal is within 30 deg of horizontal (walls; map z is
    /// up). An airborne scan samples them a few times more sparsely than
    /// its ground and roofs. `None` without normals or such points.
    pub fn steep_spacing_m(&self, cloud: &PointCloud, max_samples: usize) -> Option<f64> {
        let normals = cloud.normals.as_ref()?;
        let steep = |n: &&[f32; 3]| {
            let norm_sq = n[0] * n[0] + n[1] * n[1] + n[2] * n[2];
            norm_sq > 0.0 && n[2] * n[2] < 0.25 * norm_sq
        };
        let count = normals.iter().filter(steep).count();
        if max_samples == 0 {
            return None;
        }
        let stride = count.div_ceil(max_samples).max(1);
        let sample = normals
            .iter()
            .enumerate()
            .filter(|(_, n)| steep(n))
            .map(|(i, _)| i)
            .step_by(stride);
        self.spacing_among_m(cloud, sample)
    }

    /// [`Self::surface_spacing_m`] over the points `sample`.
    fn spacing_among_m(
        &self,
        cloud: &PointCloud,
        sample: impl Iterator<Item = usize>,
    ) -> Option<f64> {
        const K: usize = 8;
        const MAX_RADIUS_M: f64 = 2.0;
        let mut radii: Vec<f64> = sample
            .filter_map(|i| {
                // The point itself comes first, at distance 0.
                let found = self.k_nearest_within(&cloud.point_in_map(i), K + 1, MAX_RADIUS_M);
                (found.len() == K + 1).then(|| found[K].dist_sq.sqrt())
            })
            .collect();
        if radii.is_empty() {
            return None;
        }
        radii.sort_by(f64::total_cmp);
        let median = radii[radii.len() / 2];
        Some((std::f64::consts::PI / K as f64).sqrt() * median)
    }

    /// [`Self::surface_spacing_m`] of a cloud without an index yet (one is
    /// built for it, over [`SPACING_SAMPLES`] samples); `None` when the
    /// index cannot be built or no spacing estimated.
    pub fn spacing_of(cloud: &PointCloud) -> Option<f64> {
        Self::build(cloud)
            .ok()?
            .surface_spacing_m(cloud, SPACING_SAMPLES)
    }

    pub fn is_empty(&self) -> bool {
        self.num_points == 0
    }

    /// Edge of a grid cell (m).
    pub fn cell_size_m(&self) -> f64 {
        self.cell_size_m
    }

    /// Number of occupied cells.
    pub fn num_cells(&self) -> usize {
        self.cell_start.len().saturating_sub(1)
    }

    /// Heap bytes held by the index.
    pub fn memory_bytes(&self) -> usize {
        self.table.keys.capacity() * 8
            + self.table.ids.capacity() * 4
            + self.block_keys.capacity() * 8
            + self.blocks.capacity() * std::mem::size_of::<Block>()
            + self.cell_start.capacity() * 4
            + self.data.capacity() * 2
            + self.kd.get().and_then(|kd| kd.as_ref()).map_or(0, |kd| {
                // kiddo does not report its heap size: points (3 x f32) and
                // items (u32), plus a stem (f32) and slack a leaf of <= 32.
                kd.tree.size() * 16
                    + kd.tree.leaf_count() * 16
                    + kd.cell_of_pos.capacity() * 4
                    + kd.cell_coord.capacity() * 12
            })
    }

    /// Whether the kd-tree backend has been built (it is built on the first
    /// query that needs it).
    pub fn has_tree(&self) -> bool {
        self.kd.get().is_some_and(|kd| kd.is_some())
    }

    /// Sets the crossover between the two backends: radius-bounded queries
    /// ([`nearest_within`](Self::nearest_within),
    /// [`within_radius`](Self::within_radius),
    /// [`k_nearest_within`](Self::k_nearest_within)) with a radius above
    /// `cells` grid cells use the kd-tree, the others the grid. Default
    /// [`DEFAULT_TREE_MIN_RADIUS_CELLS`]. `0` sends every bounded query with a
    /// positive radius to the tree; `f64::INFINITY` never uses the tree, not
    /// even for the unbounded queries ([`nearest`](Self::nearest),
    /// [`k_nearest`](Self::k_nearest)), which use it otherwise. Results are
    /// the same either way (exact re-ranking, see [`MapIndex::nearest`]).
    pub fn set_tree_min_radius_cells(&mut self, cells: f64) {
        self.tree_min_radius_cells = if cells.is_nan() {
            DEFAULT_TREE_MIN_RADIUS_CELLS
        } else {
            cells
        };
    }

    /// Whether a query of radius `radius_m` (infinite: unbounded) goes to
    /// the kd-tree.
    fn use_tree(&self, radius_m: f64) -> bool {
        self.tree_min_radius_cells.is_finite()
            && radius_m > self.tree_min_radius_cells * self.cell_size_m
    }

    /// The kd-tree backend, built on first use.
    fn kd(&self) -> Option<&KdBackend> {
        self.kd.get_or_init(|| self.build_kd()).as_ref()
    }

    fn build_kd(&self) -> Option<KdBackend> {
        let n = self.num_points;
        if n == 0 {
            return None;
        }
        let mut cell_coord = vec![[0i32; 3]; self.num_cells()];
        self.for_each_cell_in_box([0; 3], self.extent, |id, c| {
            // Grid coordinates are below 2^21 (MAX_CELLS_PER_AXIS).
            cell_coord[id as usize] = [c[0] as i32, c[1] as i32, c[2] as i32];
        });
        let mut cell_of_pos = vec![0u32; n];
        for id in 0..self.num_cells() {
            let range = self.cell_range(id as u32);
            cell_of_pos[range].fill(id as u32);
        }
        let centre_g = [
            self.extent[0] as f64 / 2.0,
            self.extent[1] as f64 / 2.0,
            self.extent[2] as f64 / 2.0,
        ];
        let rotation = tree_rotation();
        let s = self.cell_size_m;
        const CHUNK: usize = 1 << 16;
        let mut points = vec![[0f32; 3]; n];
        let max_norm_m = points
            .par_chunks_mut(CHUNK)
            .enumerate()
            .map(|(chunk, out)| {
                let mut max_norm = 0f64;
                for (j, p) in out.iter_mut().enumerate() {
                    let pos = chunk * CHUNK + j;
                    let id = cell_of_pos[pos];
                    let c = cell_coord[id as usize];
                    let (xyz, _) = self.point_at(id, pos);
                    let local = Vector3::new(
                        (f64::from(c[0]) + f64::from(xyz[0]) / STEPS - centre_g[0]) * s,
                        (f64::from(c[1]) + f64::from(xyz[1]) / STEPS - centre_g[1]) * s,
                        (f64::from(c[2]) + f64::from(xyz[2]) / STEPS - centre_g[2]) * s,
                    );
                    let r = rotation * local;
                    max_norm = max_norm.max(r.norm());
                    *p = [r.x as f32, r.y as f32, r.z as f32];
                }
                max_norm
            })
            .reduce(|| 0.0, f64::max);
        let tree = match ImmutableKdTree::<f32, 3>::new_from_slice_parallel(&points) {
            Ok(tree) => tree,
            Err(e) => {
                log::warn!("kd-tree of the map index not built ({e}); the grid answers");
                return None;
            }
        };
        Some(KdBackend {
            tree,
            cell_of_pos,
            cell_coord,
            centre_g,
            rotation,
            max_norm_m,
        })
    }

    /// The stored coordinates (cell-local steps) and cloud index of the
    /// point at position `pos` of cell `id`.
    #[inline]
    fn point_at(&self, id: u32, pos: usize) -> ([u16; 3], u32) {
        let range = self.cell_range(id);
        let (n, k) = (range.len(), pos - range.start);
        let base = 5 * range.start + k;
        (
            [
                self.data[base],
                self.data[base + n],
                self.data[base + 2 * n],
            ],
            u32::from(self.data[base + 3 * n]) | (u32::from(self.data[base + 4 * n]) << 16),
        )
    }

    /// Heap key ([`heap_key`]) of the point at position `pos` for the query
    /// `g`: the squared distance computed exactly as the grid's scans do.
    #[inline]
    fn exact_key(&self, kd: &KdBackend, g: &[f64; 3], pos: u32) -> u64 {
        let id = kd.cell_of_pos[pos as usize];
        let c = kd.cell_coord[id as usize];
        let q = Self::local_query(g, [i64::from(c[0]), i64::from(c[1]), i64::from(c[2])]);
        let (xyz, idx) = self.point_at(id, pos as usize);
        heap_key(dist_sq(q, xyz[0], xyz[1], xyz[2]), idx)
    }

    /// The query in the tree's frame, with the absolute error margin (m) of
    /// distances computed there; `None` when too far for f32 coordinates.
    fn tree_query(&self, kd: &KdBackend, g: &[f64; 3]) -> Option<([f32; 3], f64)> {
        let local = Vector3::new(
            (g[0] - kd.centre_g[0]) * self.cell_size_m,
            (g[1] - kd.centre_g[1]) * self.cell_size_m,
            (g[2] - kd.centre_g[2]) * self.cell_size_m,
        );
        let r = kd.rotation * local;
        let norm = r.norm();
        if !(norm < 1e15) {
            return None;
        }
        let margin = TREE_REL_ERR * (kd.max_norm_m + norm + self.cell_size_m) + 1e-9;
        Some(([r.x as f32, r.y as f32, r.z as f32], margin))
    }

    /// The `k` nearest points within `bound` (squared steps, inclusive; may
    /// be infinite) of `g` through the kd-tree, as sorted heap keys; `None`
    /// when the tree cannot answer (the caller asks the grid).
    ///
    /// kiddo's f32 distances are within `TREE_REL_ERR` (relative) plus
    /// `margin` of the exact ones, so kiddo is asked for `k + TREE_EXTRA`
    /// neighbours; when the last of them is farther (beyond the error) than
    /// the k-th, no other point can be among the exact `k` nearest; else a
    /// radius query of the k-th distance plus the error collects every
    /// candidate. The candidates are re-ranked by the grid's own distances.
    fn tree_k_nearest(&self, g: &[f64; 3], k: usize, bound: f32) -> Option<Vec<u64>> {
        let kd = self.kd()?;
        let (q, margin) = self.tree_query(kd, g)?;
        let inflate = |d: f64| d * (1.0 + TREE_REL_ERR) + margin;
        let deflate = |d: f64| d * (1.0 - TREE_REL_ERR) - margin;
        let bound_m = (f64::from(bound) * self.step_sq()).sqrt();
        let m = k.saturating_add(TREE_EXTRA);
        // m >= TREE_EXTRA > 0.
        let m_nz = NonZeroUsize::new(m).expect("k + extra is positive");
        let found = if bound_m.is_finite() {
            let r = inflate(bound_m);
            kd.tree
                .query(&q)
                .nearest_n::<SquaredEuclidean<f32>>(m_nz)
                .within((r * r) as f32)
                .execute()
        } else {
            kd.tree
                .query(&q)
                .nearest_n::<SquaredEuclidean<f32>>(m_nz)
                .execute()
        };
        let mut kd_dist: Vec<f64> = found.iter().map(|r| f64::from(r.distance).sqrt()).collect();
        kd_dist.sort_unstable_by(f64::total_cmp);
        let complete = found.len() < m || deflate(kd_dist[m - 1]) > inflate(kd_dist[k - 1]);
        let mut keys: Vec<u64> = if complete {
            found
                .iter()
                .map(|r| self.exact_key(kd, g, r.item))
                .collect()
        } else {
            let r = inflate(inflate(kd_dist[k - 1]));
            let r = if bound_m.is_finite() {
                r.min(inflate(bound_m))
            } else {
                r
            };
            kd.tree
                .query(&q)
                .within::<SquaredEuclidean<f32>>((r * r) as f32)
                .unsorted()
                .execute()
                .iter()
                .map(|r| self.exact_key(kd, g, r.item))
                .collect()
        };
        keys.retain(|&key| key_dist(key) <= bound);
        keys.sort_unstable();
        keys.truncate(k);
        Some(keys)
    }

    /// Every point within `bound` (squared steps) of `g` through the
    /// kd-tree, as sorted heap keys (see [`tree_k_nearest`](Self::tree_k_nearest)).
    fn tree_within(&self, g: &[f64; 3], bound: f32) -> Option<Vec<u64>> {
        let kd = self.kd()?;
        let (q, margin) = self.tree_query(kd, g)?;
        let bound_m = (f64::from(bound) * self.step_sq()).sqrt();
        let r = bound_m * (1.0 + TREE_REL_ERR) + margin;
        let mut keys: Vec<u64> = kd
            .tree
            .query(&q)
            .within::<SquaredEuclidean<f32>>((r * r) as f32)
            .unsorted()
            .execute()
            .iter()
            .map(|r| self.exact_key(kd, g, r.item))
            .filter(|&key| key_dist(key) <= bound)
            .collect();
        keys.sort_unstable();
        Some(keys)
    }

    /// Squared length of a quantisation step (m²).
    fn step_sq(&self) -> f64 {
        let step = self.cell_size_m / STEPS;
        step * step
    }

    /// The query point in continuous grid-cell coordinates (`None` when not
    /// finite).
    fn to_grid(&self, point_in_map: &Vector3<f64>) -> Option<[f64; 3]> {
        let l = point_in_map - self.origin;
        let inv = 1.0 / self.cell_size_m;
        let g = [
            l.x * inv - self.min_cell[0] as f64,
            l.y * inv - self.min_cell[1] as f64,
            l.z * inv - self.min_cell[2] as f64,
        ];
        g.iter().all(|c| c.is_finite()).then_some(g)
    }

    /// A radius (m) as a squared distance in squared steps (inclusive bound);
    /// `None` for a negative or NaN radius.
    fn radius_steps_sq(&self, radius_m: f64) -> Option<f32> {
        if !(radius_m >= 0.0) {
            return None;
        }
        Some((radius_m * radius_m / self.step_sq()) as f32)
    }

    /// The block holding grid cell `c` and the cell's z-layer and bit in
    /// it, if the block is occupied.
    #[inline]
    fn block_of(&self, c: [i64; 3]) -> Option<(&Block, usize, u32)> {
        if (0..3).any(|a| c[a] < 0 || c[a] >= self.extent[a]) {
            return None;
        }
        let b = [
            c[0] >> BLOCK_SHIFT,
            c[1] >> BLOCK_SHIFT,
            c[2] >> BLOCK_SHIFT,
        ];
        let block = &self.blocks[self.table.get(pack_block(b))? as usize];
        let m = BLOCK_EDGE - 1;
        let (z, bit) = ((c[2] & m) as usize, ((c[1] & m) << 3 | (c[0] & m)) as u32);
        Some((block, z, bit))
    }

    /// The id of the grid cell `c`, if occupied.
    #[inline]
    fn cell_id(&self, c: [i64; 3]) -> Option<u32> {
        let (block, z, bit) = self.block_of(c)?;
        (block.occupied[z] >> bit & 1 == 1).then(|| block.cell_id(z, bit))
    }

    /// Squared distance (squared steps) from `g` to the box of cell `c`.
    #[inline]
    fn box_dist_steps_sq(g: &[f64; 3], c: [i64; 3]) -> f32 {
        let mut d = 0.0;
        for a in 0..3 {
            let lo = c[a] as f64;
            let v = if g[a] < lo {
                lo - g[a]
            } else if g[a] > lo + 1.0 {
                g[a] - lo - 1.0
            } else {
                0.0
            };
            d += v * v;
        }
        (d * (STEPS * STEPS)) as f32
    }

    /// Calls `f(cell id, cell)` for every occupied cell in the inclusive cell
    /// box `[lo, hi]` (clamped to the grid), block by block.
    #[inline]
    fn for_each_cell_in_box(&self, lo: [i64; 3], hi: [i64; 3], mut f: impl FnMut(u32, [i64; 3])) {
        let lo = [lo[0].max(0), lo[1].max(0), lo[2].max(0)];
        let hi = [
            hi[0].min(self.extent[0] - 1),
            hi[1].min(self.extent[1] - 1),
            hi[2].min(self.extent[2] - 1),
        ];
        if (0..3).any(|a| lo[a] > hi[a]) {
            return;
        }
        let blo = [
            lo[0] >> BLOCK_SHIFT,
            lo[1] >> BLOCK_SHIFT,
            lo[2] >> BLOCK_SHIFT,
        ];
        let bhi = [
            hi[0] >> BLOCK_SHIFT,
            hi[1] >> BLOCK_SHIFT,
            hi[2] >> BLOCK_SHIFT,
        ];
        let span = (bhi[0] - blo[0] + 1) * (bhi[1] - blo[1] + 1) * (bhi[2] - blo[2] + 1);
        let mut visit = |b: [i64; 3], block: &Block| {
            let base = [
                b[0] << BLOCK_SHIFT,
                b[1] << BLOCK_SHIFT,
                b[2] << BLOCK_SHIFT,
            ];
            let r = |a: usize| -> (i64, i64) {
                (
                    (lo[a] - base[a]).max(0),
                    (hi[a] - base[a]).min(BLOCK_EDGE - 1),
                )
            };
            let ((x0, x1), (y0, y1), (z0, z1)) = (r(0), r(1), r(2));
            if x0 > x1 || y0 > y1 || z0 > z1 {
                return;
            }
            let row = ((1u64 << (x1 - x0 + 1)) - 1) << x0;
            let mut rect = 0u64;
            for y in y0..=y1 {
                rect |= row << (8 * y);
            }
            for z in z0..=z1 {
                let occupied = block.occupied[z as usize];
                let mut m = occupied & rect;
                while m != 0 {
                    let bit = m.trailing_zeros();
                    m &= m - 1;
                    let id = block.cell_id(z as usize, bit);
                    f(
                        id,
                        [
                            base[0] + i64::from(bit & 7),
                            base[1] + i64::from(bit >> 3),
                            base[2] + z,
                        ],
                    );
                }
            }
        };
        if span as usize > self.blocks.len() {
            // Wider than the map's blocks: walk the blocks instead.
            for (key, block) in self.block_keys.iter().zip(&self.blocks) {
                let b = unpack_block(*key);
                if (0..3).all(|a| b[a] >= blo[a] && b[a] <= bhi[a]) {
                    visit(b, block);
                }
            }
        } else {
            for bx in blo[0]..=bhi[0] {
                for by in blo[1]..=bhi[1] {
                    for bz in blo[2]..=bhi[2] {
                        if let Some(id) = self.table.get(pack_block([bx, by, bz])) {
                            visit([bx, by, bz], &self.blocks[id as usize]);
                        }
                    }
                }
            }
        }
    }

    /// The query relative to cell `c`'s corner, in steps.
    #[inline]
    fn local_query(g: &[f64; 3], c: [i64; 3]) -> [f32; 3] {
        [
            ((g[0] - c[0] as f64) * STEPS) as f32,
            ((g[1] - c[1] as f64) * STEPS) as f32,
            ((g[2] - c[2] as f64) * STEPS) as f32,
        ]
    }

    /// Range of cell `id` in the point arrays.
    #[inline]
    fn cell_range(&self, id: u32) -> std::ops::Range<usize> {
        self.cell_start[id as usize] as usize..self.cell_start[id as usize + 1] as usize
    }

    /// The x, y and z runs of cell `id` and its first position.
    #[inline]
    fn cell_coords(&self, id: u32) -> (&[u16], &[u16], &[u16], usize) {
        let range = self.cell_range(id);
        let n = range.len();
        let run = &self.data[5 * range.start..5 * range.start + 3 * n];
        let (xs, rest) = run.split_at(n);
        let (ys, zs) = rest.split_at(n);
        (xs, ys, zs, range.start)
    }

    /// Index in the cloud of the point at position `pos` of cell `id`.
    #[inline]
    fn point_index(&self, id: u32, pos: usize) -> u32 {
        let range = self.cell_range(id);
        let (n, k) = (range.len(), pos - range.start);
        let base = 5 * range.start;
        u32::from(self.data[base + 3 * n + k]) | (u32::from(self.data[base + 4 * n + k]) << 16)
    }

    /// Visits the occupied cells around `g` nearest first, roughly: the own
    /// cell, then cubes of half-width 1, 2, 3, 4, 6, 9, ... cells around it
    /// (growing by half; each cell once), until the cube holds the ball of
    /// radius `sqrt(search.limit())` (the limit may shrink while visiting).
    /// Cells whose box lies beyond the limit are not scanned.
    fn search_growing<S: Search>(&self, g: &[f64; 3], search: &mut S) {
        let own = grid_cell(g);
        self.search_around(g, own, self.cell_id(own), search);
    }

    /// [`search_growing`](Self::search_growing) with the query's own cell
    /// `own` (`grid_cell(g)`) and its id (`None` when empty) known.
    #[inline]
    fn search_around<S: Search>(
        &self,
        g: &[f64; 3],
        own: [i64; 3],
        own_id: Option<u32>,
        search: &mut S,
    ) {
        if let Some(id) = own_id {
            self.prefetch_cell(id);
        }
        self.prefetch_near_neighbours(g, own, NEIGHBOUR_PREFETCH_CELLS);
        if let Some(id) = own_id {
            search.scan(self, id, own, g);
        }
        let mut done: i64 = 0;
        loop {
            let reach = reach_cells(search.limit());
            // `as` saturates for infinite reaches; clamped to the grid.
            let lo = [
                (floor_i64(g[0] - reach)).max(0),
                (floor_i64(g[1] - reach)).max(0),
                (floor_i64(g[2] - reach)).max(0),
            ];
            let hi = [
                (floor_i64(g[0] + reach)).min(self.extent[0] - 1),
                (floor_i64(g[1] + reach)).min(self.extent[1] - 1),
                (floor_i64(g[2] + reach)).min(self.extent[2] - 1),
            ];
            if (0..3).any(|a| lo[a] > hi[a]) {
                return;
            }
            let needed = (0..3)
                .map(|a| (own[a] - lo[a]).max(hi[a] - own[a]))
                .max()
                .unwrap_or(0);
            if needed <= done {
                return;
            }
            let next = needed.min(done + (done / 2).max(1));
            let box_lo = [
                (own[0] - next).max(lo[0]),
                (own[1] - next).max(lo[1]),
                (own[2] - next).max(lo[2]),
            ];
            let box_hi = [
                (own[0] + next).min(hi[0]),
                (own[1] + next).min(hi[1]),
                (own[2] + next).min(hi[2]),
            ];
            self.for_each_cell_in_box(box_lo, box_hi, |id, c| {
                let cheb = (0..3).map(|a| (c[a] - own[a]).abs()).max().unwrap_or(0);
                if cheb <= done {
                    // Visited by an earlier cube.
                    return;
                }
                if Self::box_dist_steps_sq(g, c) > search.limit() {
                    return;
                }
                search.scan(self, id, c, g);
            });
            done = next;
        }
    }

    /// The nearest map point within `radius_m` (inclusive) of `point_in_map`,
    /// or `None` when there is none. Ties go to the smaller point index.
    pub fn nearest_within(&self, point_in_map: &Vector3<f64>, radius_m: f64) -> Option<Neighbour> {
        if self.is_empty() {
            return None;
        }
        let bound = self.radius_steps_sq(radius_m)?;
        let g = self.to_grid(point_in_map)?;
        if self.use_tree(radius_m) {
            if let Some(keys) = self.tree_k_nearest(&g, 1, bound) {
                return self.keys_to_neighbours(keys).into_iter().next();
            }
        }
        let own = grid_cell(&g);
        self.nearest_around(&g, own, self.cell_id(own), bound)
            .map(|key| self.key_to_neighbour(key))
    }

    /// The grid's nearest point within `bound` (squared steps, inclusive)
    /// of `g`, whose own cell `own` has the id `own_id`, as a heap key.
    #[inline]
    fn nearest_around(
        &self,
        g: &[f64; 3],
        own: [i64; 3],
        own_id: Option<u32>,
        bound: f32,
    ) -> Option<u64> {
        let mut search = NearestSearch { bound, best: None };
        self.search_around(g, own, own_id, &mut search);
        search
            .best
            .map(|b| heap_key(b.d, self.point_index(b.cell, b.pos as usize)))
    }

    /// [`nearest_within`](Self::nearest_within) for many query points at
    /// once: the answer for `points_in_map[i]` is at `i`. Queries run in the
    /// index's own memory order (sorted by cell, a radix sort), so
    /// consecutive queries scan the same cells and mostly hit the caches, in
    /// parallel over chunks (rayon); the result does not depend on the order
    /// or the thread count.
    pub fn nearest_within_batch(
        &self,
        points_in_map: &[Vector3<f64>],
        radius_m: f64,
    ) -> Vec<Option<Neighbour>> {
        let n = points_in_map.len();
        let Some(bound) = self.radius_steps_sq(radius_m) else {
            return vec![None; n];
        };
        if self.is_empty() || self.use_tree(radius_m) {
            return points_in_map
                .par_iter()
                .map(|p| self.nearest_within(p, radius_m))
                .collect();
        }
        let order = self.memory_order(points_in_map);
        let outside = self.outside_key();
        // Heap keys of the answers (NO_ANSWER for none), written in place:
        // each slot once, `order` being a permutation.
        let answers: Vec<AtomicU64> = (0..n).map(|_| AtomicU64::new(NO_ANSWER)).collect();
        order.par_chunks(4096).for_each(|chunk| {
            for (j, &v) in chunk.iter().enumerate() {
                if let Some(&ahead) = chunk.get(j + BATCH_PREFETCH_AHEAD) {
                    // The query point and its answer's slot are random
                    // accesses; its cell usually the next run of memory.
                    prefetch(&points_in_map[ahead as u32 as usize]);
                    prefetch(&answers[ahead as u32 as usize]);
                    let key = (ahead >> 32) as u32;
                    if key != outside && key & 1 == 1 {
                        self.prefetch_cell(key >> 1);
                    }
                }
                let i = v as u32 as usize;
                let key = (v >> 32) as u32;
                let Some(g) = self.to_grid(&points_in_map[i]) else {
                    continue;
                };
                let own = grid_cell(&g);
                let own_id = if key == outside {
                    self.cell_id(own)
                } else {
                    (key & 1 == 1).then_some(key >> 1)
                };
                if let Some(found) = self.nearest_around(&g, own, own_id, bound) {
                    answers[i].store(found, Ordering::Relaxed);
                }
            }
        });
        answers
            .into_iter()
            .map(|a| {
                let key = a.into_inner();
                (key != NO_ANSWER).then(|| self.key_to_neighbour(key))
            })
            .collect()
    }

    /// The batch sort key ([`memory_order`](Self::memory_order)) of queries
    /// outside the grid, in an empty block or not finite: the largest.
    fn outside_key(&self) -> u32 {
        (2 * self.num_cells() as u64 + 1).min(u64::from(u32::MAX)) as u32
    }

    /// The queries' indices (low 32 bits) sorted by a key (high 32 bits)
    /// that follows the index's memory order: `2 id + 1` for a query in the
    /// occupied cell `id`; `2 id` for one in an empty cell of an occupied
    /// block, `id` being that of the first occupied cell after it in memory
    /// order (in its z-layer, a later one or a later block; the number of
    /// cells after the last: order only, see [`Block`]), so it sorts just
    /// before that cell's queries; [`outside_key`](Self::outside_key) for
    /// the rest (and for cell ids too large for the key), last. Ties by
    /// index. The sort uses only the key's significant bits.
    fn memory_order(&self, points_in_map: &[Vector3<f64>]) -> Vec<u64> {
        let outside = self.outside_key();
        let mut keyed: Vec<u64> = points_in_map
            .par_iter()
            .enumerate()
            .map(|(i, p)| {
                let key = self
                    .to_grid(p)
                    .and_then(|g| self.block_of(grid_cell(&g)))
                    .map(|(block, z, bit)| {
                        let occupied = block.occupied[z] >> bit & 1;
                        2 * u64::from(block.cell_id(z, bit)) + occupied
                    })
                    .filter(|&key| key < u64::from(outside))
                    .unwrap_or(u64::from(outside));
                (key << 32) | i as u64
            })
            .collect();
        radix_sort_high_u32(&mut keyed, u32::BITS - outside.leading_zeros());
        keyed
    }

    /// Hints the processor to fetch the starts of the x, y and z runs of
    /// cell `id` (no effect on results).
    #[inline]
    fn prefetch_cell(&self, id: u32) {
        let range = self.cell_range(id);
        let (start, n) = (5 * range.start, range.len());
        for offset in [0, n, 2 * n] {
            if let Some(first) = self.data.get(start + offset) {
                prefetch(first);
            }
        }
    }

    /// Prefetches the occupied neighbours of cell `own` whose box lies within
    /// `margin` cells of `g` (likely scanned next: their memory latency then
    /// overlaps the own cell's).
    #[inline]
    fn prefetch_near_neighbours(&self, g: &[f64; 3], own: [i64; 3], margin: f64) {
        let mut dir = [0i64; 3];
        for a in 0..3 {
            let f = g[a] - own[a] as f64;
            dir[a] = if f < margin {
                -1
            } else if f > 1.0 - margin {
                1
            } else {
                0
            };
        }
        if dir == [0; 3] {
            return;
        }
        for mask in 1..8u32 {
            let mut c = own;
            let mut valid = true;
            for a in 0..3 {
                if mask >> a & 1 == 1 {
                    if dir[a] == 0 {
                        valid = false;
                    }
                    c[a] += dir[a];
                }
            }
            if valid {
                if let Some(id) = self.cell_id(c) {
                    self.prefetch_cell(id);
                }
            }
        }
    }

    /// The `k` nearest points within `bound` (squared steps, inclusive; may
    /// be infinite) of `g`, as heap keys (unsorted).
    fn k_nearest_bounded(&self, g: &[f64; 3], k: usize, bound: f32) -> BinaryHeap<u64> {
        let mut search = KSearch {
            k,
            bound,
            heap: BinaryHeap::with_capacity(k.min(4096) + 1),
        };
        if k > 0 {
            self.search_growing(g, &mut search);
        }
        search.heap
    }

    /// Heap keys to neighbours, nearest first (ties by point index).
    fn sorted_neighbours(&self, heap: BinaryHeap<u64>) -> Vec<Neighbour> {
        self.keys_to_neighbours(heap.into_sorted_vec())
    }

    /// Sorted heap keys to neighbours.
    fn keys_to_neighbours(&self, keys: Vec<u64>) -> Vec<Neighbour> {
        keys.into_iter()
            .map(|key| self.key_to_neighbour(key))
            .collect()
    }

    /// A heap key to the neighbour.
    #[inline]
    fn key_to_neighbour(&self, key: u64) -> Neighbour {
        Neighbour {
            point_idx: key as u32,
            dist_sq: f64::from(key_dist(key)) * self.step_sq(),
        }
    }

    /// The nearest map point, whatever its distance (`None` for an empty map).
    ///
    /// When enabled with
    /// [`set_tree_min_radius_cells`](Self::set_tree_min_radius_cells) (off
    /// by default), unbounded queries ([`nearest`](Self::nearest),
    /// [`k_nearest`](Self::k_nearest)) and bounded ones with a large radius
    /// are answered by a kiddo kd-tree built on first use (about 17 bytes a
    /// point more; [`memory_bytes`](Self::memory_bytes) counts it once
    /// built). Its candidates are re-ranked with the grid's own distances, so
    /// the results are those of the grid: sorted by (distance, point index).
    pub fn nearest(&self, point_in_map: &Vector3<f64>) -> Option<Neighbour> {
        let g = self.to_grid(point_in_map)?;
        if self.is_empty() {
            return None;
        }
        if self.use_tree(f64::INFINITY) {
            if let Some(keys) = self.tree_k_nearest(&g, 1, f32::INFINITY) {
                return self.keys_to_neighbours(keys).into_iter().next();
            }
        }
        self.sorted_neighbours(self.k_nearest_bounded(&g, 1, f32::INFINITY))
            .into_iter()
            .next()
    }

    /// The `k` nearest map points, nearest first (ties by point index). Fewer
    /// than `k` when the map is smaller.
    pub fn k_nearest(&self, point_in_map: &Vector3<f64>, k: usize) -> Vec<Neighbour> {
        let Some(g) = self.to_grid(point_in_map) else {
            return Vec::new();
        };
        if self.is_empty() || k == 0 {
            return Vec::new();
        }
        if self.use_tree(f64::INFINITY) {
            if let Some(keys) = self.tree_k_nearest(&g, k, f32::INFINITY) {
                return self.keys_to_neighbours(keys);
            }
        }
        self.sorted_neighbours(self.k_nearest_bounded(&g, k, f32::INFINITY))
    }

    /// The `k` nearest map points within `radius_m` (inclusive), nearest first
    /// (ties by point index).
    pub fn k_nearest_within(
        &self,
        point_in_map: &Vector3<f64>,
        k: usize,
        radius_m: f64,
    ) -> Vec<Neighbour> {
        let (Some(g), Some(bound)) = (self.to_grid(point_in_map), self.radius_steps_sq(radius_m))
        else {
            return Vec::new();
        };
        if self.is_empty() || k == 0 {
            return Vec::new();
        }
        if self.use_tree(radius_m) {
            if let Some(keys) = self.tree_k_nearest(&g, k, bound) {
                return self.keys_to_neighbours(keys);
            }
        }
        self.sorted_neighbours(self.k_nearest_bounded(&g, k, bound))
    }

    /// Every map point within `radius_m` (inclusive) of `point_in_map`,
    /// nearest first (ties by point index).
    pub fn within_radius(&self, point_in_map: &Vector3<f64>, radius_m: f64) -> Vec<Neighbour> {
        let (Some(g), Some(bound)) = (self.to_grid(point_in_map), self.radius_steps_sq(radius_m))
        else {
            return Vec::new();
        };
        let reach = reach_cells(bound);
        let lo = [
            floor_i64(g[0] - reach),
            floor_i64(g[1] - reach),
            floor_i64(g[2] - reach),
        ];
        let hi = [
            floor_i64(g[0] + reach),
            floor_i64(g[1] + reach),
            floor_i64(g[2] + reach),
        ];
        let mut found: Vec<u64> = Vec::new();
        if self.is_empty() {
            return Vec::new();
        }
        if self.use_tree(radius_m) {
            if let Some(keys) = self.tree_within(&g, bound) {
                return self.keys_to_neighbours(keys);
            }
        }
        self.for_each_cell_in_box(lo, hi, |id, c| {
            if Self::box_dist_steps_sq(&g, c) > bound {
                return;
            }
            let q = Self::local_query(&g, c);
            let (xs, ys, zs, start) = self.cell_coords(id);
            for (k, ((&x, &y), &z)) in xs.iter().zip(ys).zip(zs).enumerate() {
                let d = dist_sq(q, x, y, z);
                if d <= bound {
                    found.push(heap_key(d, self.point_index(id, start + k)));
                }
            }
        });
        found.sort_unstable();
        self.keys_to_neighbours(found)
    }
}

/// Asks the kernel to back `v` with 2 MB pages where it can (Linux
/// transparent huge pages, `madvise` mode): random queries into a map of
/// hundreds of megabytes then miss the TLB far less often. Only a hint: call
/// it before the memory is first written (fresh pages), no effect on
/// contents or elsewhere.
fn advise_huge_pages<T>(v: &mut [T]) {
    #[cfg(target_os = "linux")]
    {
        const HUGE: usize = 2 << 20;
        let start = v.as_mut_ptr() as usize;
        let end = start + std::mem::size_of_val(v);
        let (lo, hi) = (start.next_multiple_of(HUGE), end / HUGE * HUGE);
        if lo < hi {
            // SAFETY: [lo, hi) lies inside `v`'s allocation; MADV_HUGEPAGE
            // changes no contents. A failure (e.g. THP disabled) is harmless.
            unsafe { libc::madvise(lo as *mut libc::c_void, hi - lo, libc::MADV_HUGEPAGE) };
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = v;
}

/// Sorts `values` by their high 32 bits, of which only the low `key_bits`
/// may be set, stably (values with equal high bits keep their order): a
/// least-significant-digit radix sort in as few passes of at most 11 bits
/// as cover `key_bits`, skipping passes in which every value has the same
/// digit.
fn radix_sort_high_u32(values: &mut Vec<u64>, key_bits: u32) {
    const MAX_DIGIT_BITS: u32 = 11;
    let key_bits = key_bits.min(32);
    if key_bits == 0 {
        return;
    }
    let bits = key_bits.div_ceil(key_bits.div_ceil(MAX_DIGIT_BITS));
    let buckets = 1usize << bits;
    let mut scratch = vec![0u64; values.len()];
    let mut shift = 32;
    while shift < 32 + key_bits {
        let digit = |v: u64| ((v >> shift) as usize) & (buckets - 1);
        let mut counts = vec![0usize; buckets];
        for &v in values.iter() {
            counts[digit(v)] += 1;
        }
        if !counts.contains(&values.len()) {
            let mut next = 0;
            for c in counts.iter_mut() {
                let k = *c;
                *c = next;
                next += k;
            }
            for &v in values.iter() {
                let d = digit(v);
                scratch[counts[d]] = v;
                counts[d] += 1;
            }
            std::mem::swap(values, &mut scratch);
        }
        shift += bits;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cloud(points: Vec<[f32; 3]>) -> PointCloud {
        PointCloud {
            origin: Vector3::new(500_000.0, 4_000_000.0, 100.0),
            points,
            normals: None,
            planarity: None,
        }
    }

    /// Square grids of 2, 5 and 10 cm on a plane (tilted, far from the
    /// origin), with a few far outliers: the estimate is the grid's spacing
    /// to 15 % (a grid's 8th neighbour ring is not a disc).
    #[test]
    fn surface_spacing_of_square_grids() {
        for spacing in [0.02f32, 0.05, 0.1] {
            let mut points = Vec::new();
            for i in 0..120 {
                for j in 0..120 {
                    let (u, v) = (i as f32 * spacing, j as f32 * spacing);
                    points.push([u, 0.6 * v, 0.8 * v]);
                }
            }
            for k in 0..30 {
                points.push([-50.0 - 10.0 * k as f32, 40.0, 7.0 * k as f32]);
            }
            let c = cloud(points);
            let index = MapIndex::build(&c).unwrap();
            let estimate = index.surface_spacing_m(&c, 2000).unwrap();
            let ratio = estimate / f64::from(spacing);
            assert!(
                (0.85..1.15).contains(&ratio),
                "spacing {spacing}: {estimate}"
            );
            // Same answer every time.
            assert_eq!(index.surface_spacing_m(&c, 2000), Some(estimate));
        }
        // Only isolated points: no estimate.
        let lonely = cloud(vec![[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]]);
        let index = MapIndex::build(&lonely).unwrap();
        assert_eq!(index.surface_spacing_m(&lonely, 100), None);
    }

    /// A floor every 10 cm and a wall every 30 cm (an airborne scan's
    /// walls): the whole map reads the floor's spacing, its steep points the
    /// wall's; without normals there is no steep spacing.
    #[test]
    fn steep_spacing_reads_the_walls() {
        let mut points = Vec::new();
        let mut normals = Vec::new();
        for i in 0..100 {
            for j in 0..100 {
                points.push([i as f32 * 0.1, j as f32 * 0.1, 0.0]);
                normals.push([0.0, 0.0, 1.0]);
            }
        }
        for j in 0..34 {
            for k in 1..20 {
                points.push([10.0, j as f32 * 0.3, k as f32 * 0.3]);
                normals.push([-1.0, 0.0, 0.0]);
            }
        }
        let mut c = cloud(points);
        let index = MapIndex::build(&c).unwrap();
        assert_eq!(index.steep_spacing_m(&c, 2000), None);
        c.normals = Some(normals);
        let whole = index.surface_spacing_m(&c, 2000).unwrap();
        let walls = index.steep_spacing_m(&c, 2000).unwrap();
        assert!((0.085..0.115).contains(&whole), "{whole}");
        assert!((0.255..0.345).contains(&walls), "{walls}");
    }

    #[test]
    fn hand_computed_queries() {
        let c = cloud(vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]]);
        let index = MapIndex::build(&c).unwrap();
        let q = c.origin + Vector3::new(0.9, 0.0, 0.0);
        let n = index.nearest_within(&q, 0.5).unwrap();
        assert_eq!(n.point_idx, 1);
        assert!((n.dist_sq - 0.01).abs() < 1e-5);
        assert!(index.nearest_within(&q, 0.05).is_none());
        let k = index.k_nearest(&q, 5);
        assert_eq!(
            k.iter().map(|n| n.point_idx).collect::<Vec<_>>(),
            vec![1, 0, 2]
        );
        let w = index.within_radius(&q, 1.0);
        assert_eq!(
            w.iter().map(|n| n.point_idx).collect::<Vec<_>>(),
            vec![1, 0]
        );
        assert_eq!(index.k_nearest_within(&q, 5, 1.0).len(), 2);
    }

    #[test]
    fn batch_equals_single_queries() {
        let mut points = Vec::new();
        for i in 0..2000u32 {
            let t = i as f32 * 0.01;
            points.push([t.sin() * 5.0, t.cos() * 3.0, t * 0.1]);
        }
        let c = cloud(points);
        let index = MapIndex::build(&c).unwrap();
        let mut queries: Vec<Vector3<f64>> = (0..500)
            .map(|i| {
                let t = i as f64 * 0.37;
                c.origin + Vector3::new(t.sin() * 6.0, t.cos() * 2.0, (t * 0.05) % 2.0)
            })
            .collect();
        // Outside the grid, non-finite, and twice the same point: sorted
        // last or next to each other, answered like single queries.
        queries.insert(17, c.origin + Vector3::new(1e4, -1e4, 3.0));
        queries.insert(3, Vector3::new(f64::NAN, 0.0, 0.0));
        let found = (0..queries.len())
            .find(|&i| index.nearest_within(&queries[i], 0.5).is_some())
            .expect("a query near the cloud");
        queries.push(queries[found]);
        let batch = index.nearest_within_batch(&queries, 0.5);
        assert_eq!(batch[3], None);
        assert_eq!(batch[18], None);
        assert!(batch[found].is_some());
        assert_eq!(batch[found], batch[queries.len() - 1]);
        assert_eq!(batch.len(), queries.len());
        let mut some = 0;
        for (q, b) in queries.iter().zip(&batch) {
            assert_eq!(*b, index.nearest_within(q, 0.5));
            some += usize::from(b.is_some());
        }
        assert!(some > 50 && some < 500, "{some}");
    }

    #[test]
    fn batch_keys_of_empty_cells_follow_memory_order() {
        // 1 m cells: block (0, 0, 0) holds cells (0, 0, 0), (1, 0, 0) and
        // (0, 0, 3) (ids 0, 1, 2), block (0, 0, 1) cell (0, 0, 12) (id 3),
        // block (1, 0, 1) cell (8, 0, 8) (id 4). A query in an empty cell
        // gets twice the id of the first occupied cell after it in memory
        // order, also in an empty z-layer (never 0 but before cell 0).
        let c = cloud(vec![
            [0.5, 0.5, 0.5],
            [1.5, 0.5, 0.5],
            [0.5, 0.5, 3.5],
            [0.5, 0.5, 12.5],
            [8.5, 0.5, 8.5],
        ]);
        let options = IndexOptions {
            cell_size_m: Some(1.0),
        };
        let index = MapIndex::build_with_options(&c, &options).unwrap();
        assert_eq!(index.num_cells(), 5);
        let outside = index.outside_key();
        assert_eq!(outside, 11);
        let cases: [([f64; 3], u32); 11] = [
            ([0.5, 0.5, 0.5], 1),
            ([0.2, 0.7, 3.1], 5),
            ([0.5, 0.5, 1.5], 4),
            ([2.5, 0.5, 0.5], 4),
            ([0.5, 0.5, 5.5], 6),
            ([0.5, 0.5, 8.5], 6),
            ([0.5, 0.5, 12.5], 7),
            ([8.5, 0.5, 10.5], 10),
            ([8.5, 0.5, 8.5], 9),
            ([8.5, 0.5, 0.5], outside),
            ([-3.0, 0.5, 0.5], outside),
        ];
        let queries: Vec<Vector3<f64>> = cases
            .iter()
            .map(|(p, _)| c.origin + Vector3::new(p[0], p[1], p[2]))
            .collect();
        let order = index.memory_order(&queries);
        assert_eq!(order.len(), cases.len());
        for pair in order.windows(2) {
            assert!(pair[0] < pair[1]);
        }
        for &v in &order {
            let i = v as u32 as usize;
            assert_eq!((v >> 32) as u32, cases[i].1, "query {:?}", cases[i].0);
        }
        let batch = index.nearest_within_batch(&queries, 2.0);
        for (q, b) in queries.iter().zip(&batch) {
            assert_eq!(*b, index.nearest_within(q, 2.0));
        }
    }

    /// xorshift64: the kernel tests' deterministic random numbers.
    struct Xorshift(u64);

    impl Xorshift {
        fn next(&mut self) -> u64 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            self.0
        }

        /// Any u16, the full range.
        fn u16(&mut self) -> u16 {
            (self.next() >> 48) as u16
        }

        fn point(&mut self) -> [u16; 3] {
            [self.u16(), self.u16(), self.u16()]
        }
    }

    /// The runs of `points` (x, y and z).
    fn runs(points: &[[u16; 3]]) -> [Vec<u16>; 3] {
        [0, 1, 2].map(|a| points.iter().map(|p| p[a]).collect())
    }

    /// The scan kernels' answer for `points` and `q`, checked to be the same
    /// in a plain loop (the first position of the smallest distance,
    /// `(infinity, 0)` when no distance is below infinity), the scalar
    /// builds, the dispatching ones and, when the processor has AVX2, the
    /// AVX2 builds.
    fn kernels_answer(points: &[[u16; 3]], q: [f32; 3], what: &str) -> (f32, usize) {
        let [xs, ys, zs] = runs(points);
        let mut plain = (f32::INFINITY, 0);
        for (k, p) in points.iter().enumerate() {
            let d = dist_sq(q, p[0], p[1], p[2]);
            if d < plain.0 {
                plain = (d, k);
            }
        }
        let what = format!("{what}, n = {}, q = {q:?}", points.len());
        assert_eq!(
            runs_min_impl(&xs, &ys, &zs, q),
            plain.0,
            "scalar min, {what}"
        );
        assert_eq!(
            runs_argmin_impl(&xs, &ys, &zs, q),
            plain,
            "scalar argmin, {what}"
        );
        assert_eq!(runs_min(&xs, &ys, &zs, q), plain.0, "min, {what}");
        assert_eq!(runs_argmin(&xs, &ys, &zs, q), plain, "argmin, {what}");
        #[cfg(target_arch = "x86_64")]
        if has_avx2() {
            // SAFETY: the processor has AVX2 (checked above).
            let (min, argmin) = unsafe {
                (
                    runs_min_avx2(&xs, &ys, &zs, q),
                    runs_argmin_avx2(&xs, &ys, &zs, q),
                )
            };
            assert_eq!(min, plain.0, "AVX2 min, {what}");
            assert_eq!(argmin, plain, "AVX2 argmin, {what}");
        }
        plain
    }

    /// The stored coordinate nearest to the query coordinate `v`.
    fn nearest_step(v: f32) -> u16 {
        v.round().clamp(0.0, STEPS as f32) as u16
    }

    #[test]
    fn scan_kernels_match_a_plain_loop() {
        // Runs of every length up to 17 (short runs, one chunk and a tail)
        // and a few longer (whole chunks, tails); full-range coordinates;
        // queries with fractional parts, negative and above 65535.
        let lengths: Vec<usize> = (0..=17).chain([23, 31, 40]).collect();
        let queries: [[f32; 3]; 6] = [
            [1500.25, 999.5, 2000.0],
            [31_337.5, 12.5, 65_000.5],
            [-1234.75, 40_000.125, -0.5],
            [65_535.5, 70_000.375, 131_071.9],
            [-70_000.3, 65_600.8, 3.7],
            [0.5, 65_534.5, 32_767.5],
        ];
        let mut rng = Xorshift(0x9e37_79b9_7f4a_7c15);
        // Redraws the points not in `keep` until they are farther than
        // `d` (they then cannot tie with the expected minimum).
        let farther = |rng: &mut Xorshift, points: &mut [[u16; 3]], keep: &[usize], q, d| {
            for (k, p) in points.iter_mut().enumerate() {
                while !keep.contains(&k) && dist_sq(q, p[0], p[1], p[2]) <= d {
                    *p = rng.point();
                }
            }
        };
        for &q in &queries {
            let near = q.map(nearest_step);
            for &n in &lengths {
                // Random runs; and from a few values (ties by chance).
                let points: Vec<[u16; 3]> = (0..n).map(|_| rng.point()).collect();
                kernels_answer(&points, q, "random");
                let points: Vec<[u16; 3]> =
                    (0..n).map(|_| rng.point().map(|v| v % 4 * 1000)).collect();
                kernels_answer(&points, q, "few values");

                // Every position the unique minimum (at or next to the
                // query's nearest stored point).
                for p in 0..n {
                    let mut points: Vec<[u16; 3]> = (0..n).map(|_| rng.point()).collect();
                    points[p] = near.map(|v| v.saturating_add(rng.u16() % 3));
                    let d = dist_sq(q, points[p][0], points[p][1], points[p][2]);
                    farther(&mut rng, &mut points, &[p], q, d);
                    assert_eq!(kernels_answer(&points, q, "unique"), (d, p), "p = {p}");
                }

                // Every pair tied at the minimum: the lower position wins.
                // Mirrored around a query at half a step when it lies in
                // the range (different points), else the same point twice.
                for j in 0..n {
                    for i in 0..j {
                        let mut points: Vec<[u16; 3]> = (0..n).map(|_| rng.point()).collect();
                        points[i] = near;
                        points[j] = near;
                        if q[0].fract() == 0.5 && (0.5..=65_534.5).contains(&q[0]) {
                            points[i][0] = (q[0] - 0.5) as u16;
                            points[j][0] = (q[0] + 0.5) as u16;
                            if (i + j) % 2 == 1 {
                                points.swap(i, j);
                            }
                        }
                        let d = dist_sq(q, points[i][0], points[i][1], points[i][2]);
                        assert_eq!(d, dist_sq(q, points[j][0], points[j][1], points[j][2]));
                        farther(&mut rng, &mut points, &[i, j], q, d);
                        assert_eq!(kernels_answer(&points, q, "tie"), (d, i), "{i}, {j}");
                    }
                }

                // All points the same: position 0.
                let same = rng.point();
                let d = dist_sq(q, same[0], same[1], same[2]);
                let answer = kernels_answer(&vec![same; n], q, "all equal");
                assert_eq!(answer, if n == 0 { (f32::INFINITY, 0) } else { (d, 0) });
            }
        }
        // Queries so far that every distance is infinite: (infinity, 0),
        // the kernels' answer for no point too.
        let far: [[f32; 3]; 4] = [
            [1e20, -1e20, 3e19],
            [f32::MAX, 0.5, 0.5],
            [f32::INFINITY, 100.25, -7.5],
            [-3.5, f32::NEG_INFINITY, 65_536.5],
        ];
        for &q in &far {
            for &n in &lengths {
                let points: Vec<[u16; 3]> = (0..n).map(|_| rng.point()).collect();
                assert_eq!(
                    kernels_answer(&points, q, "far"),
                    (f32::INFINITY, 0),
                    "n = {n}, q = {q:?}"
                );
            }
        }
    }

    #[test]
    fn radix_sort_is_a_stable_sort_by_the_high_bits() {
        // Keys over all 32 high bits, and keys in a narrow range (passes
        // skipped); low bits in decreasing order to see the stability.
        let mut state = 0x1234_5678_9abc_def0u64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        for (mask, key_bits) in [(u64::MAX, 32), (0xffu64 << 32, 8), (0x3ffu64 << 32, 10)] {
            let mut values: Vec<u64> = (0..20_000u64)
                .map(|i| (next() & mask & !0xffff_ffff) | (20_000 - i))
                .collect();
            let mut expected = values.clone();
            expected.sort_by_key(|v| v >> 32);
            radix_sort_high_u32(&mut values, key_bits);
            assert_eq!(values, expected);
        }
    }

    #[test]
    fn empty_map() {
        let index = MapIndex::build(&cloud(Vec::new())).unwrap();
        assert!(index.is_empty());
        let q = Vector3::zeros();
        assert!(index.nearest_within(&q, 10.0).is_none());
        assert!(index.nearest(&q).is_none());
        assert!(index.k_nearest(&q, 3).is_empty());
        assert!(index.within_radius(&q, 3.0).is_empty());
    }

    #[test]
    fn rejects_nan() {
        let c = cloud(vec![[0.0, 0.0, 0.0], [f32::NAN, 0.0, 0.0]]);
        assert!(matches!(
            MapIndex::build(&c),
            Err(IndexError::NonFinitePoint { index: 1 })
        ));
    }
}
