//! Scene geometry: textured rectangles ("quads") and solid boxes made of them,
//! with ray intersection and point-to-surface queries.
//!
//! Coordinates are the scene's local world frame (metres, z up); the optional
//! georeferencing offset is added only when outputs are written.
use nalgebra::Vector3;

use super::texture::{Material, Texture};

/// A textured rectangle: `origin + a * u_axis + b * v_axis`, `a` in
/// `[0, size_u_m]`, `b` in `[0, size_v_m]`. Its normal `u_axis x v_axis` points
/// to the side the surface is seen from (into free space).
#[derive(Clone, Debug)]
pub struct Quad {
    pub origin: Vector3<f64>,
    pub u_axis: Vector3<f64>,
    pub v_axis: Vector3<f64>,
    pub size_u_m: f64,
    pub size_v_m: f64,
    pub normal: Vector3<f64>,
    pub texture: Texture,
}

impl Quad {
    /// A quad from its origin corner and two orthogonal edge vectors; the
    /// normal is `edge_u x edge_v` normalised.
    pub fn new(
        origin: Vector3<f64>,
        edge_u: Vector3<f64>,
        edge_v: Vector3<f64>,
        texture: Texture,
    ) -> Self {
        let (size_u_m, size_v_m) = (edge_u.norm(), edge_v.norm());
        let u_axis = edge_u / size_u_m;
        let v_axis = edge_v / size_v_m;
        Self {
            origin,
            u_axis,
            v_axis,
            size_u_m,
            size_v_m,
            normal: u_axis.cross(&v_axis).normalize(),
            texture,
        }
    }

    pub fn area_m2(&self) -> f64 {
        self.size_u_m * self.size_v_m
    }

    /// The point at surface coordinates `(a, b)` metres.
    pub fn point_at(&self, a: f64, b: f64) -> Vector3<f64> {
        self.origin + self.u_axis * a + self.v_axis * b
    }

    /// Ray parameter `t > t_min` of the hit with `origin + t * dir`, and the
    /// surface coordinates there; `None` when the ray misses or is parallel.
    pub fn intersect(
        &self,
        origin: &Vector3<f64>,
        dir: &Vector3<f64>,
        t_min: f64,
        t_max: f64,
    ) -> Option<(f64, f64, f64)> {
        let denom = self.normal.dot(dir);
        if denom.abs() < 1e-12 {
            return None;
        }
        let t = self.normal.dot(&(self.origin - origin)) / denom;
        if t <= t_min || t >= t_max {
            return None;
        }
        let q = origin + dir * t - self.origin;
        let a = q.dot(&self.u_axis);
        let b = q.dot(&self.v_axis);
        if a < 0.0 || a > self.size_u_m || b < 0.0 || b > self.size_v_m {
            return None;
        }
        Some((t, a, b))
    }

    /// Euclidean distance from a point to the rectangle.
    pub fn distance_to(&self, p: &Vector3<f64>) -> f64 {
        let q = p - self.origin;
        let a = q.dot(&self.u_axis).clamp(0.0, self.size_u_m);
        let b = q.dot(&self.v_axis).clamp(0.0, self.size_v_m);
        (p - self.point_at(a, b)).norm()
    }
}

/// A solid box standing on `base_z_m`, rotated by `yaw_rad` about the vertical.
#[derive(Clone, Debug)]
pub struct SolidBox {
    pub center_xy_m: [f64; 2],
    pub base_z_m: f64,
    /// Full sizes along the box's own x, y and z.
    pub size_m: [f64; 3],
    pub yaw_rad: f64,
}

impl SolidBox {
    fn axes(&self) -> (Vector3<f64>, Vector3<f64>, Vector3<f64>) {
        let (s, c) = self.yaw_rad.sin_cos();
        (
            Vector3::new(c, s, 0.0),
            Vector3::new(-s, c, 0.0),
            Vector3::z(),
        )
    }

    /// True when `p` is strictly inside the box by more than `margin_m`.
    pub fn contains(&self, p: &Vector3<f64>, margin_m: f64) -> bool {
        let (ex, ey, _) = self.axes();
        let d = p - Vector3::new(self.center_xy_m[0], self.center_xy_m[1], self.base_z_m);
        let (x, y, z) = (d.dot(&ex), d.dot(&ey), d.z);
        x.abs() < self.size_m[0] / 2.0 - margin_m
            && y.abs() < self.size_m[1] / 2.0 - margin_m
            && z > margin_m
            && z < self.size_m[2] - margin_m
    }

    /// The outward faces: four sides and the top (the bottom rests on the
    /// ground and is never seen). Each face gets its own texture seed.
    pub fn faces(&self, material: Material, seed: u64) -> Vec<Quad> {
        let (ex, ey, ez) = self.axes();
        let [sx, sy, sz] = self.size_m;
        let c = Vector3::new(self.center_xy_m[0], self.center_xy_m[1], self.base_z_m);
        // Corner at (-x, -y, bottom).
        let o = c - ex * (sx / 2.0) - ey * (sy / 2.0);
        let (vx, vy, vz) = (ex * sx, ey * sy, ez * sz);
        let t = |k: u64| Texture::new(material, super::texture::hash64(seed.wrapping_add(k)));
        vec![
            // -y side, normal -y: u = +x, v = +z gives x cross z = -y.
            Quad::new(o, vx, vz, t(1)),
            // +x side, normal +x: u = +y, v = +z.
            Quad::new(o + vx, vy, vz, t(2)),
            // +y side, normal +y: u = -x, v = +z.
            Quad::new(o + vx + vy, -vx, vz, t(3)),
            // -x side, normal -x: u = -y, v = +z.
            Quad::new(o + vy, -vy, vz, t(4)),
            // top, normal +z: u = +x, v = +y.
            Quad::new(o + vz, vx, vy, t(5)),
        ]
    }
}

/// Lighting of a scene: a directional light plus ambient.
#[derive(Clone, Copy, Debug)]
pub struct Lighting {
    /// Unit vector pointing towards the light.
    pub to_light: Vector3<f64>,
    pub light: f32,
    pub ambient: f32,
    /// Cast shadows from the directional light (outdoors).
    pub shadows: bool,
    /// Rays that hit nothing see a sky gradient (outdoors); black otherwise.
    pub sky: bool,
}

/// A whole synthetic scene.
#[derive(Clone, Debug)]
pub struct Scene {
    pub quads: Vec<Quad>,
    /// Solids, used to drop LiDAR samples hidden inside them.
    pub solids: Vec<SolidBox>,
    pub lighting: Lighting,
}

/// The nearest hit of a ray.
#[derive(Clone, Copy, Debug)]
pub struct Hit {
    pub t: f64,
    pub quad: usize,
    pub a_m: f64,
    pub b_m: f64,
}

impl Scene {
    /// Nearest surface hit by `origin + t * dir`, `t` in `(t_min, t_max)`.
    pub fn cast(
        &self,
        origin: &Vector3<f64>,
        dir: &Vector3<f64>,
        t_min: f64,
        t_max: f64,
    ) -> Option<Hit> {
        let mut best: Option<Hit> = None;
        let mut t_best = t_max;
        for (i, q) in self.quads.iter().enumerate() {
            if let Some((t, a, b)) = q.intersect(origin, dir, t_min, t_best) {
                t_best = t;
                best = Some(Hit {
                    t,
                    quad: i,
                    a_m: a,
                    b_m: b,
                });
            }
        }
        best
    }

    /// True when anything blocks the segment `origin + t * dir`, `t` in `(t_min, t_max)`.
    pub fn occluded(
        &self,
        origin: &Vector3<f64>,
        dir: &Vector3<f64>,
        t_min: f64,
        t_max: f64,
    ) -> bool {
        self.quads
            .iter()
            .any(|q| q.intersect(origin, dir, t_min, t_max).is_some())
    }

    /// Distance from a point to the nearest surface.
    pub fn distance_to_surfaces(&self, p: &Vector3<f64>) -> f64 {
        self.quads
            .iter()
            .map(|q| q.distance_to(p))
            .fold(f64::INFINITY, f64::min)
    }

    pub fn bounding_box(&self) -> (Vector3<f64>, Vector3<f64>) {
        let mut lo = Vector3::repeat(f64::INFINITY);
        let mut hi = Vector3::repeat(f64::NEG_INFINITY);
        for q in &self.quads {
            for (a, b) in [
                (0.0, 0.0),
                (q.size_u_m, 0.0),
                (0.0, q.size_v_m),
                (q.size_u_m, q.size_v_m),
            ] {
                let p = q.point_at(a, b);
                lo = lo.inf(&p);
                hi = hi.sup(&p);
            }
        }
        (lo, hi)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn box_faces_point_outwards_and_ray_hits_nearest() {
        let b = SolidBox {
            center_xy_m: [0.0, 0.0],
            base_z_m: 0.0,
            size_m: [2.0, 4.0, 3.0],
            yaw_rad: 0.3,
        };
        let centre = Vector3::new(0.0, 0.0, 1.5);
        for f in b.faces(Material::Object, 1) {
            let mid = f.point_at(f.size_u_m / 2.0, f.size_v_m / 2.0);
            assert!(f.normal.dot(&(mid - centre)) > 0.0);
            assert!(!b.contains(&mid, 1e-6));
        }
        assert!(b.contains(&centre, 0.1));
        let scene = Scene {
            quads: b.faces(Material::Object, 1),
            solids: vec![b.clone()],
            lighting: Lighting {
                to_light: Vector3::z(),
                light: 1.0,
                ambient: 0.2,
                shadows: false,
                sky: false,
            },
        };
        // From x = 10 towards the origin: first hit on the +x face of the rotated box.
        let hit = scene
            .cast(
                &Vector3::new(10.0, 0.0, 1.0),
                &Vector3::new(-1.0, 0.0, 0.0),
                0.0,
                100.0,
            )
            .unwrap();
        // Distance from the centre to the +x face along -x of a box rotated by 0.3 rad:
        // half-size 1 along its own x, so 1 / cos(0.3) along the world x axis.
        assert!(
            (hit.t - (10.0 - 1.0 / 0.3f64.cos())).abs() < 1e-9,
            "{}",
            hit.t
        );
        assert!(scene.occluded(
            &Vector3::new(10.0, 0.0, 1.0),
            &Vector3::new(-1.0, 0.0, 0.0),
            0.0,
            20.0
        ));
        assert!(!scene.occluded(
            &Vector3::new(10.0, 0.0, 1.0),
            &Vector3::new(1.0, 0.0, 0.0),
            0.0,
            20.0
        ));
    }
}
