//! Deterministic procedural textures for synthetic surfaces.
//!
//! A texture is a function of the surface coordinates `(u, v)` in metres and of a
//! per-surface seed, so no two surfaces (and no two places on one surface) look
//! alike: SIFT finds many distinctive, non-repeating features. It layers
//! multi-octave value noise (stains, grain) with random blobs and rotated
//! rectangles drawn on jittered grids of several cell sizes (4 cm to 1.2 m).
//!
//! Anti-aliasing: every layer is band-limited by the pixel footprint (the size of
//! one pixel on the surface, in metres). Detail much smaller than the footprint
//! fades to its mean, and blob edges are smoothed over one footprint, the
//! equivalent of mip-mapping for a procedural texture. Oblique footprints are
//! the renderer's job (`render::footprint_albedo` averages along the long axis).

/// Linear RGB colour, components in [0, 1].
pub type Rgb = [f32; 3];

/// The look of a surface.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Material {
    /// Pavement / gravel: grey-brown, dense small stones, large stains.
    Ground,
    /// Plastered or brick facade: one base colour per building, paint patches.
    Facade,
    /// Indoor wall or pillar: light colours, posters and marks.
    Wall,
    /// Indoor floor: wood/linoleum-like tones.
    Floor,
    /// Ceiling: bright, with lower contrast.
    Ceiling,
    /// Crates and other objects: saturated colours.
    Object,
}

/// A textured surface: material, seed and the base colour drawn from both.
#[derive(Clone, Copy, Debug)]
pub struct Texture {
    pub material: Material,
    pub seed: u64,
    base: Rgb,
}

/// splitmix64: a small, good integer hash.
pub fn hash64(mut x: u64) -> u64 {
    x = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    x = (x ^ (x >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    x ^ (x >> 31)
}

fn hash3(seed: u64, a: i64, b: i64) -> u64 {
    hash64(
        seed.wrapping_add((a as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15))
            .wrapping_add((b as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)),
    )
}

/// Uniform in [0, 1) from the `k`-th 16-bit slice of a hash (and rehashing beyond).
fn unit(h: u64, k: u32) -> f32 {
    let h = if k < 4 { h } else { hash64(h ^ u64::from(k)) };
    ((h >> ((k % 4) * 16)) & 0xFFFF) as f32 / 65536.0
}

fn smoothstep(e0: f32, e1: f32, x: f32) -> f32 {
    let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

fn lerp3(a: Rgb, b: Rgb, t: f32) -> Rgb {
    [
        a[0] + (b[0] - a[0]) * t,
        a[1] + (b[1] - a[1]) * t,
        a[2] + (b[2] - a[2]) * t,
    ]
}

fn scale3(a: Rgb, s: f32) -> Rgb {
    [a[0] * s, a[1] * s, a[2] * s]
}

/// Colour from hue (0..1), saturation and value.
fn hsv(h: f32, s: f32, v: f32) -> Rgb {
    let h6 = (h.fract() * 6.0).max(0.0);
    let i = h6.floor() as i32;
    let f = h6 - i as f32;
    let (p, q, t) = (v * (1.0 - s), v * (1.0 - s * f), v * (1.0 - s * (1.0 - f)));
    match i {
        0 => [v, t, p],
        1 => [q, v, p],
        2 => [p, v, t],
        3 => [p, q, v],
        4 => [t, p, v],
        _ => [v, p, q],
    }
}

/// Value noise in [-1, 1] on a unit grid, smooth (quintic) interpolation.
fn value_noise(seed: u64, x: f32, y: f32) -> f32 {
    let (xf, yf) = (x.floor(), y.floor());
    let (ix, iy) = (xf as i64, yf as i64);
    let (fx, fy) = (x - xf, y - yf);
    let q = |t: f32| t * t * t * (t * (t * 6.0 - 15.0) + 10.0);
    let (sx, sy) = (q(fx), q(fy));
    let v = |dx: i64, dy: i64| unit(hash3(seed, ix + dx, iy + dy), 0) * 2.0 - 1.0;
    let a = v(0, 0) + (v(1, 0) - v(0, 0)) * sx;
    let b = v(0, 1) + (v(1, 1) - v(0, 1)) * sx;
    a + (b - a) * sy
}

/// Weight of a detail of size `size_m` seen with pixel footprint `footprint_m`:
/// 1 when the detail spans several pixels, 0 when it is below about one pixel.
fn band_weight(size_m: f32, footprint_m: f32) -> f32 {
    smoothstep(0.8, 2.5, size_m / footprint_m.max(1e-6))
}

/// Cell sizes (metres) of the blob layers, coarse to fine.
const BLOB_CELLS_M: [f32; 5] = [1.0, 0.42, 0.18, 0.08, 0.035];

impl Texture {
    pub fn new(material: Material, seed: u64) -> Self {
        let h = hash64(seed ^ 0xA5A5);
        let (r1, r2, r3) = (unit(h, 0), unit(h, 1), unit(h, 2));
        let base = match material {
            Material::Ground => hsv(0.08 + 0.05 * r1, 0.12 + 0.15 * r2, 0.35 + 0.15 * r3),
            Material::Facade => hsv(r1, 0.15 + 0.35 * r2, 0.45 + 0.35 * r3),
            Material::Wall => hsv(r1, 0.05 + 0.25 * r2, 0.6 + 0.25 * r3),
            Material::Floor => hsv(0.05 + 0.06 * r1, 0.3 + 0.3 * r2, 0.35 + 0.25 * r3),
            Material::Ceiling => hsv(r1, 0.03 + 0.06 * r2, 0.75 + 0.15 * r3),
            Material::Object => hsv(r1, 0.45 + 0.4 * r2, 0.4 + 0.4 * r3),
        };
        Self {
            material,
            seed,
            base,
        }
    }

    /// Contrast of the blob layers for this material (0..1).
    fn blob_contrast(&self) -> f32 {
        match self.material {
            Material::Ceiling => 0.45,
            Material::Ground => 0.8,
            Material::Facade => 0.65,
            _ => 0.85,
        }
    }

    /// Probability that a blob-grid cell holds a blob.
    fn blob_density(&self) -> f32 {
        match self.material {
            Material::Facade => 0.45,
            Material::Ground => 0.55,
            Material::Floor => 0.4,
            Material::Ceiling => 0.35,
            Material::Wall => 0.5,
            Material::Object => 0.6,
        }
    }

    /// Man-made structure of the material: paving slabs, windows, planks,
    /// ceiling tiles, skirting boards. `v` is the vertical coordinate on
    /// walls (metres above the surface's lower edge).
    fn structure(&self, colour: Rgb, u: f32, v: f32, fp: f32) -> Rgb {
        let h = hash64(self.seed ^ 0x5157);
        match self.material {
            Material::Ground => {
                let row_h = 0.5;
                let row = (v / row_h).floor();
                let offset = unit(hash3(h, row as i64, 7), 0) * 0.6;
                let width = 0.6;
                let col = ((u + offset) / width).floor();
                let hs = hash3(h, col as i64, row as i64);
                let tone = 0.75 + 0.5 * unit(hs, 0);
                let tint = hsv(0.05 + 0.1 * unit(hs, 1), 0.15 * unit(hs, 2), 1.0);
                let c = [
                    colour[0] * tone * tint[0],
                    colour[1] * tone * tint[1],
                    colour[2] * tone * tint[2],
                ];
                let du = ((u + offset) - col * width).min((col + 1.0) * width - (u + offset));
                let dv = (v - row * row_h).min((row + 1.0) * row_h - v);
                self.joint(c, du.min(dv), 0.012, 0.45, fp)
            }
            Material::Floor => {
                let row_h = 0.19;
                let row = (v / row_h).floor();
                let offset = unit(hash3(h, row as i64, 3), 0) * 1.3;
                let len = 1.3;
                let col = ((u + offset) / len).floor();
                let hs = hash3(h, col as i64, row as i64);
                let tone = 0.7 + 0.6 * unit(hs, 0);
                // Wood grain: noise stretched along the plank.
                let grain = if band_weight(0.01, fp) > 0.0 {
                    0.12 * band_weight(0.01, fp) * value_noise(hs, u / 0.25, v / 0.008)
                } else {
                    0.0
                };
                let c = scale3(colour, tone * (1.0 + grain));
                let du = ((u + offset) - col * len).min((col + 1.0) * len - (u + offset));
                let dv = (v - row * row_h).min((row + 1.0) * row_h - v);
                self.joint(c, du.min(dv), 0.004, 0.5, fp)
            }
            Material::Ceiling => {
                let tile = 0.6;
                let (cu, cv) = ((u / tile).floor(), (v / tile).floor());
                let hs = hash3(h, cu as i64, cv as i64);
                let c = scale3(colour, 0.9 + 0.2 * unit(hs, 0));
                let du = (u - cu * tile).min((cu + 1.0) * tile - u);
                let dv = (v - cv * tile).min((cv + 1.0) * tile - v);
                self.joint(c, du.min(dv), 0.015, 0.6, fp)
            }
            Material::Wall => {
                if v < 0.1 {
                    // Skirting board.
                    return scale3(colour, 0.45);
                }
                colour
            }
            Material::Facade => self.windows(colour, u, v, fp, h),
            Material::Object => colour,
        }
    }

    /// Darkens `colour` to `dark` times within `half_width_m` of a joint at
    /// distance `dist_m`, anti-aliased over the footprint.
    fn joint(&self, colour: Rgb, dist_m: f32, half_width_m: f32, dark: f32, fp: f32) -> Rgb {
        let visible = band_weight(2.0 * half_width_m, fp);
        let inside = 1.0 - smoothstep(half_width_m - 0.5 * fp, half_width_m + 0.5 * fp, dist_m);
        scale3(colour, 1.0 - (1.0 - dark) * inside * visible)
    }

    /// Facade windows: one grid per building face, every window different
    /// (blinds, curtains, reflections), some bricked up.
    fn windows(&self, colour: Rgb, u: f32, v: f32, fp: f32, h: u64) -> Rgb {
        let spacing = 2.4 + 1.2 * unit(h, 0);
        let floor_h = 3.0 + 0.4 * unit(h, 1);
        let (win_w, win_h, sill) = (spacing * (0.38 + 0.2 * unit(h, 2)), 1.5, 0.9);
        let (col, floor) = ((u / spacing).floor(), (v / floor_h).floor());
        let hw = hash3(h, col as i64, floor as i64);
        if unit(hw, 0) < 0.12 {
            return colour;
        }
        let x = u - col * spacing - (spacing - win_w) / 2.0;
        let y = v - floor * floor_h - sill;
        let frame = 0.07;
        let d_out = (-x).max(x - win_w).max(-y).max(y - win_h);
        if d_out > 0.5 * fp {
            return colour;
        }
        let cover = 1.0 - smoothstep(-0.5 * fp, 0.5 * fp, d_out);
        let frame_colour = scale3(
            hsv(unit(hw, 1), 0.1 * unit(hw, 2), 1.0),
            0.55 + 0.3 * unit(hw, 3),
        );
        let d_in = (frame - x)
            .max(x - (win_w - frame))
            .max(frame - y)
            .max(y - (win_h - frame));
        let glass_cover = 1.0 - smoothstep(-0.5 * fp, 0.5 * fp, d_in);
        // Glass: dark, with a reflection gradient and a blind from the top.
        let hg = hash64(hw);
        let mut glass = lerp3(
            [0.05, 0.07, 0.1],
            [0.25, 0.3, 0.38],
            (y / win_h).clamp(0.0, 1.0) * unit(hg, 0),
        );
        let blind = win_h * (1.0 - unit(hg, 1));
        if y > blind {
            let slat = 0.5
                + 0.5 * ((y - blind) / 0.03 * std::f32::consts::PI).sin() * band_weight(0.03, fp);
            glass = scale3(
                hsv(unit(hg, 2), 0.3 * unit(hg, 3), 0.5 + 0.3 * unit(hg, 4)),
                0.8 + 0.2 * slat,
            );
        }
        // A curtain on one side.
        let curtain = win_w * 0.45 * unit(hg, 5);
        if (unit(hg, 6) < 0.5 && x < curtain) || (unit(hg, 6) >= 0.5 && x > win_w - curtain) {
            let fold =
                0.85 + 0.15 * (x / 0.06 * std::f32::consts::PI).sin() * band_weight(0.06, fp);
            glass = scale3(hsv(unit(hg, 7), 0.5, 0.6), fold);
        }
        let inner = lerp3(frame_colour, glass, glass_cover);
        lerp3(colour, inner, cover)
    }

    /// Colour of one blob: a variation of the base colour, sometimes a free colour.
    fn blob_colour(&self, h: u64) -> Rgb {
        let pick = unit(h, 4);
        if pick < 0.1 {
            hsv(unit(h, 5), 0.4 + 0.5 * unit(h, 6), 0.2 + 0.7 * unit(h, 7))
        } else {
            let light = 0.35 + 1.3 * unit(h, 5);
            let tint = hsv(unit(h, 6), 0.25 * unit(h, 7), 1.0);
            let c = scale3(self.base, light);
            [c[0] * tint[0], c[1] * tint[1], c[2] * tint[2]]
        }
    }

    /// Albedo (linear RGB) at surface coordinates `(u_m, v_m)` for a pixel
    /// footprint of `footprint_m` metres.
    pub fn albedo(&self, u_m: f64, v_m: f64, footprint_m: f64) -> Rgb {
        // Surfaces are at most a few hundred metres: f32 keeps sub-millimetre detail.
        let (u, v, fp) = (u_m as f32, v_m as f32, footprint_m as f32);
        let mut colour = self.base;

        // Large stains and fine grain: fBm, octaves from 2.5 m down to 1 cm.
        let mut amp = 0.3;
        let mut size = 2.5f32;
        let mut grain = 0.0f32;
        for octave in 0..8u64 {
            let w = band_weight(size, fp);
            if w <= 0.0 {
                break;
            }
            grain += amp * w * value_noise(self.seed ^ (octave * 7919 + 11), u / size, v / size);
            amp *= 0.9;
            size *= 0.45;
        }
        colour = scale3(colour, (1.0 + grain).max(0.05));
        colour = self.structure(colour, u, v, fp);

        // Blob layers, coarse to fine; each is painted over the result so far.
        let contrast = self.blob_contrast();
        let density = self.blob_density();
        for (layer, &cell) in BLOB_CELLS_M.iter().enumerate() {
            let w_band = band_weight(cell * 0.25, fp);
            if w_band <= 0.0 {
                break;
            }
            let layer_seed = hash64(self.seed ^ ((layer as u64 + 1) << 40));
            // A blob stays within half a cell of its centre, so only the 2 x 2
            // cells whose centres are nearest can reach (u, v).
            let (cu, cv) = (
                (u / cell - 0.5).floor() as i64,
                (v / cell - 0.5).floor() as i64,
            );
            for dy in 0..=1 {
                for dx in 0..=1 {
                    let (ix, iy) = (cu + dx, cv + dy);
                    let h = hash3(layer_seed, ix, iy);
                    if unit(h, 0) > density {
                        continue;
                    }
                    let cx = (ix as f32 + unit(h, 1)) * cell;
                    let cy = (iy as f32 + unit(h, 2)) * cell;
                    // Reach: with aspect in [0.5, 1.6] every shape stays within
                    // 1.6 radius (rectangle corner: sqrt(0.5 + 2) = 1.58), so
                    // radius <= 0.28 cell keeps it within 0.45 cell (plus the edge blur).
                    let radius = cell * (0.1 + 0.18 * unit(h, 3));
                    let (px, py) = (u - cx, v - cy);
                    let reach = radius * 1.6 + 0.5 * fp;
                    if px.abs() > reach || py.abs() > reach {
                        continue;
                    }
                    let h2 = hash64(h);
                    // A random rotation from two uniforms (cheaper than sin_cos);
                    // the degenerate (0, 0) case falls back to no rotation.
                    let (rc, rs) = (unit(h2, 0) * 2.0 - 1.0, unit(h2, 3) * 2.0 - 1.0);
                    let norm = (rc * rc + rs * rs).sqrt();
                    let (c, s) = if norm > 1e-3 {
                        (rc / norm, rs / norm)
                    } else {
                        (1.0, 0.0)
                    };
                    let (qx, qy) = (c * px + s * py, -s * px + c * py);
                    let aspect = 0.5 + 1.1 * unit(h2, 1);
                    let shape = unit(h2, 2);
                    // Signed distance (approximate), negative inside.
                    let sd = if shape < 0.45 {
                        // Ellipse.
                        let (ax, ay) = (radius * aspect.sqrt(), radius / aspect.sqrt());
                        let k = ((qx / ax).powi(2) + (qy / ay).powi(2)).sqrt();
                        (k - 1.0) * ax.min(ay)
                    } else if shape < 0.85 {
                        // Rotated rectangle: corners for the detector.
                        let (ax, ay) = (radius * aspect.sqrt(), radius / aspect.sqrt());
                        (qx.abs() - ax).max(qy.abs() - ay)
                    } else {
                        // Ring.
                        let k = (qx * qx + qy * qy).sqrt();
                        (k - radius * 0.75).abs() - radius * 0.22
                    };
                    let cover = 1.0 - smoothstep(-0.5 * fp, 0.5 * fp, sd);
                    if cover <= 0.0 {
                        continue;
                    }
                    let blob = self.blob_colour(h2);
                    colour = lerp3(colour, blob, cover * contrast * w_band);
                }
            }
        }
        [
            colour[0].clamp(0.0, 1.0),
            colour[1].clamp(0.0, 1.0),
            colour[2].clamp(0.0, 1.0),
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn deterministic_and_varied() {
        let t = Texture::new(Material::Facade, 42);
        let a = t.albedo(1.234, 5.678, 0.005);
        assert_eq!(a, t.albedo(1.234, 5.678, 0.005));
        // Values differ across the surface (not a flat colour) and between seeds.
        let other = Texture::new(Material::Facade, 43).albedo(1.234, 5.678, 0.005);
        let mut distinct = 0;
        for i in 0..50 {
            let b = t.albedo(1.234 + 0.05 * i as f64, 5.678, 0.005);
            if (b[0] - a[0]).abs() + (b[1] - a[1]).abs() > 0.02 {
                distinct += 1;
            }
        }
        assert!(distinct > 25, "{distinct}");
        assert_ne!(a, other);
    }

    #[test]
    fn large_footprint_is_smooth() {
        // With a 1 m footprint fine detail is gone: neighbours 1 cm apart are nearly equal.
        let t = Texture::new(Material::Ground, 7);
        for i in 0..20 {
            let u = 0.37 * i as f64;
            let a = t.albedo(u, 1.0, 1.0);
            let b = t.albedo(u + 0.01, 1.0, 1.0);
            let d: f32 = (0..3).map(|k| (a[k] - b[k]).abs()).sum();
            assert!(d < 0.05, "{d}");
        }
    }
}
