//! Dense depth image of the map seen from a camera, and its colour-mapped PNG
//! with query pixels (features) drawn on top: the paper's depth figure, to see
//! whether a pose and the map agree.
//!
//! Same projection and splats as [`super::projection`], into a full-resolution
//! z-buffer of ranges. Parallel over bands of rows: each band is written by one
//! task that visits the splats in a fixed order, so the image does not depend
//! on the number of threads (ties keep the first splat, i.e. the smaller cell
//! then point index).
use std::path::Path;

use image::{ImageFormat, Rgb, RgbImage};
use nalgebra::Vector2;
use rayon::prelude::*;

use super::cloud::PointCloud;
use super::grid::FrustumGrid;
use super::projection::{
    project_visible_points, ProjectedPoint, ProjectionError, ProjectionOptions,
};
use crate::io::atomic::write_file_atomically;
use crate::scene::camera::Camera;
use crate::scene::pose::Rigid3;

/// Errors writing a depth image.
#[derive(Debug, thiserror::Error)]
pub enum DepthImageError {
    #[error(transparent)]
    Projection(#[from] ProjectionError),
    #[error("writing {path}: {source}")]
    Write {
        path: String,
        source: std::io::Error,
    },
    #[error("encoding {path} as PNG: {source}")]
    Encode {
        path: String,
        source: image::ImageError,
    },
    #[error("the depth image is empty (0 x 0 pixels)")]
    Empty,
}

/// Range (m) of the nearest splat at each pixel, row-major; `f32::INFINITY`
/// where no map point is seen.
#[derive(Clone, Debug, PartialEq)]
pub struct DepthImage {
    pub width: u32,
    pub height: u32,
    pub range_m: Vec<f32>,
}

impl DepthImage {
    pub fn range_at(&self, x: u32, y: u32) -> f32 {
        self.range_m[y as usize * self.width as usize + x as usize]
    }

    /// Number of pixels where a map point is seen.
    pub fn num_filled(&self) -> usize {
        self.range_m.iter().filter(|r| r.is_finite()).count()
    }
}

/// Rows per parallel band.
const BAND_ROWS: usize = 32;

/// Renders the dense range image of the map seen by `camera` at
/// `cam_from_world`. Pixel (i, j) has centre (i + 0.5, j + 0.5) and is covered
/// by a splat when the centre lies inside its square.
pub fn render_depth_image(
    cloud: &PointCloud,
    grid: &FrustumGrid,
    camera: &Camera,
    cam_from_world: &Rigid3,
    options: &ProjectionOptions,
) -> Result<DepthImage, ProjectionError> {
    let splats = project_visible_points(cloud, grid, camera, cam_from_world, options)?;
    Ok(depth_image_from_splats(
        &splats,
        camera.width,
        camera.height,
    ))
}

/// The z-buffer of `splats` (from [`project_visible_points`]) in a
/// `width` x `height` image: at each pixel the smallest range of the splats
/// covering its centre.
pub fn depth_image_from_splats(splats: &[ProjectedPoint], width: u32, height: u32) -> DepthImage {
    DepthImage {
        width,
        height,
        range_m: nearest_splats(splats, width, height)
            .into_iter()
            .map(|(range, _)| range)
            .collect(),
    }
}

/// Marks a pixel no splat covers in [`nearest_splats`].
pub const NO_SPLAT: u32 = u32::MAX;

/// The z-buffer of `splats` in a `width` x `height` image, row-major: at each
/// pixel the smallest range of the splats covering its centre and that
/// splat's index in `splats` (`f32::INFINITY` and [`NO_SPLAT`] where none
/// does; ties keep the first splat).
pub fn nearest_splats(splats: &[ProjectedPoint], width: u32, height: u32) -> Vec<(f32, u32)> {
    let (w, h) = (width as usize, height as usize);
    let mut nearest = vec![(f32::INFINITY, NO_SPLAT); w * h];
    if w == 0 || h == 0 {
        return nearest;
    }
    // Splats bucketed by the bands their rows reach (CSR, splat order
    // kept within a band), so that a band visits only its own splats.
    let bands = h.div_ceil(BAND_ROWS);
    let band_range = |y: f64, hs: f64| -> Option<(usize, usize)> {
        let (y0, y1) = (y - hs - 0.5, y + hs - 0.5);
        if !(y1 >= 0.0 && y0 <= (h - 1) as f64) {
            return None;
        }
        let b0 = (y0.max(0.0) as usize / BAND_ROWS).min(bands - 1);
        let b1 = ((y1.max(0.0) as usize).min(h - 1) / BAND_ROWS).min(bands - 1);
        Some((b0, b1))
    };
    let mut band_starts = vec![0usize; bands + 1];
    for sp in splats {
        if let Some((b0, b1)) = band_range(sp.pixel.y, sp.half_size_px) {
            for b in b0..=b1 {
                band_starts[b + 1] += 1;
            }
        }
    }
    for b in 0..bands {
        band_starts[b + 1] += band_starts[b];
    }
    let mut fill = band_starts.clone();
    let mut band_splats = vec![0u32; band_starts[bands]];
    for (k, sp) in splats.iter().enumerate() {
        if let Some((b0, b1)) = band_range(sp.pixel.y, sp.half_size_px) {
            for b in b0..=b1 {
                band_splats[fill[b]] = k as u32;
                fill[b] += 1;
            }
        }
    }
    nearest
        .par_chunks_mut(BAND_ROWS * w)
        .enumerate()
        .for_each(|(band, rows)| {
            let row0 = band * BAND_ROWS;
            let nrows = rows.len() / w;
            // Pixel centres of this band span [row0 + 0.5, row0 + nrows - 0.5].
            let (band_y0, band_y1) = (row0 as f64 + 0.5, (row0 + nrows) as f64 - 0.5);
            let mine = &band_splats[band_starts[band]..band_starts[band + 1]];
            for &k in mine {
                let s = &splats[k as usize];
                let (y0, y1) = (s.pixel.y - s.half_size_px, s.pixel.y + s.half_size_px);
                if y1 < band_y0 || y0 > band_y1 {
                    continue;
                }
                let (x0, x1) = (s.pixel.x - s.half_size_px, s.pixel.x + s.half_size_px);
                // Pixel k is covered when x0 <= k + 0.5 <= x1.
                let kx0 = (x0 - 0.5).ceil().max(0.0) as usize;
                let kx1 = (x1 - 0.5).floor();
                if kx1 < 0.0 {
                    continue;
                }
                let kx1 = (kx1 as usize).min(w - 1);
                let ky0 = ((y0 - 0.5).ceil().max(row0 as f64) as usize).max(row0);
                let ky1 = ((y1 - 0.5).floor() as i64).min((row0 + nrows) as i64 - 1);
                if ky1 < ky0 as i64 || kx0 > kx1 {
                    continue;
                }
                let r = s.range_m as f32;
                for ky in ky0..=ky1 as usize {
                    let row = &mut rows[(ky - row0) * w..(ky - row0 + 1) * w];
                    for px in &mut row[kx0..=kx1] {
                        if r < px.0 {
                            *px = (r, k);
                        }
                    }
                }
            }
        });
    nearest
}

/// Colour of a normalised range `t` in [0, 1]: near = dark violet, through
/// blue, cyan, green, yellow, to far = light red.
pub fn range_colour(t: f64) -> [u8; 3] {
    const STOPS: [[f64; 3]; 6] = [
        [48.0, 18.0, 59.0],
        [50.0, 100.0, 230.0],
        [30.0, 200.0, 210.0],
        [90.0, 220.0, 80.0],
        [240.0, 210.0, 40.0],
        [250.0, 110.0, 80.0],
    ];
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        1.0
    };
    let x = t * (STOPS.len() - 1) as f64;
    let k = (x.floor() as usize).min(STOPS.len() - 2);
    let f = x - k as f64;
    let mut c = [0u8; 3];
    for a in 0..3 {
        c[a] = (STOPS[k][a] * (1.0 - f) + STOPS[k + 1][a] * f).round() as u8;
    }
    c
}

/// Colour-maps `depth` (ranges 0..`max_range_m`, black where empty) and draws
/// each query pixel as a ring of radius 3 px: green when `hit[i]`, red
/// otherwise.
pub fn colourise(
    depth: &DepthImage,
    max_range_m: f64,
    query_pixels: &[Vector2<f64>],
    hit: &[bool],
) -> RgbImage {
    let mut img = RgbImage::new(depth.width, depth.height);
    for (i, px) in img.pixels_mut().enumerate() {
        let r = depth.range_m[i];
        *px = if r.is_finite() {
            Rgb(range_colour(f64::from(r) / max_range_m))
        } else {
            Rgb([0, 0, 0])
        };
    }
    let (w, h) = (i64::from(depth.width), i64::from(depth.height));
    for (i, q) in query_pixels.iter().enumerate() {
        let colour = if hit.get(i).copied().unwrap_or(false) {
            Rgb([0, 255, 0])
        } else {
            Rgb([255, 0, 0])
        };
        // Pixel holding the query point.
        let (cx, cy) = (q.x.floor() as i64, q.y.floor() as i64);
        for dy in -3i64..=3 {
            for dx in -3i64..=3 {
                let d_sq = dx * dx + dy * dy;
                if !(5..=12).contains(&d_sq) {
                    continue;
                }
                let (x, y) = (cx + dx, cy + dy);
                if x >= 0 && y >= 0 && x < w && y < h {
                    img.put_pixel(x as u32, y as u32, colour);
                }
            }
        }
    }
    img
}

/// Writes `img` as a PNG, atomically (temporary sibling, then rename).
pub fn write_png(img: &RgbImage, path: &Path) -> Result<(), DepthImageError> {
    if img.width() == 0 || img.height() == 0 {
        return Err(DepthImageError::Empty);
    }
    let name = path.display().to_string();
    let mut bytes = std::io::Cursor::new(Vec::new());
    img.write_to(&mut bytes, ImageFormat::Png)
        .map_err(|source| DepthImageError::Encode {
            path: name.clone(),
            source,
        })?;
    write_file_atomically::<std::io::Error>(path, |w| std::io::Write::write_all(w, bytes.get_ref()))
        .map_err(|source| DepthImageError::Write { path: name, source })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn colour_map_ends() {
        assert_eq!(range_colour(0.0), [48, 18, 59]);
        assert_eq!(range_colour(1.0), [250, 110, 80]);
        assert_eq!(range_colour(2.0), [250, 110, 80]);
        assert_eq!(range_colour(f64::NAN), [250, 110, 80]);
    }
}
