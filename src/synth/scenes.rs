//! The built-in scenes and their camera trajectories.
//!
//! * `yard`: an outdoor courtyard, ground plus four building blocks and a few
//!   objects; the camera walks a circle around the middle at 1.6 m, looking out
//!   at the facades (a full loop at about 90 images).
//! * `room`: an indoor room (floor, ceiling, four walls) with pillars and
//!   furniture; the camera walks a circle looking at the walls past the pillars.
//! * `corridor`: a 40 m corridor walked forward, turned at the far point and
//!   walked back, looking ahead and slightly at one wall: the case where plain
//!   SfM drifts in scale.
//!
//! Trajectories are sampled so that consecutive images overlap strongly
//! (steps of tens of centimetres, a few degrees), with a little seeded
//! hand-held jitter.
use std::f64::consts::PI;

use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::geometry::{Lighting, Quad, Scene, SolidBox};
use super::texture::{hash64, Material, Texture};
use crate::scene::BodyPose;

/// The built-in scenes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum SceneKind {
    Yard,
    Room,
    Corridor,
    /// The yard seen from a drone: nadir photos along a lawnmower survey.
    Aerial,
    /// The yard seen from a drone circling it, the camera 45 deg down
    /// towards the middle (oblique photos).
    Orbit,
}

impl SceneKind {
    pub fn name(self) -> &'static str {
        match self {
            SceneKind::Yard => "yard",
            SceneKind::Room => "room",
            SceneKind::Corridor => "corridor",
            SceneKind::Aerial => "aerial",
            SceneKind::Orbit => "orbit",
        }
    }
}

/// Builds the geometry of a scene. The seed changes the textures only.
pub fn build_scene(kind: SceneKind, seed: u64) -> Scene {
    build_changed_scene(kind, seed, 0).0
}

/// The scene as photographed after it changed since the scan: `changes` of
/// its movable objects (the yard's objects, the room's furniture, the
/// corridor's cabinets) are gone and up to `changes` new boxes stand where
/// there was nothing (none on the cameras' paths). Both come from fixed
/// lists per scene, ordered so that the default 24-image walk sees the first
/// ones: in the room it sees the first three of each, in the yard the first
/// three added and two removed (only two of the yard's objects are in its
/// view); the corridor's are not ordered (cabinets by x, the new boxes
/// every 1.5 m on alternate walls). `changes` = 0 is [`build_scene`]. Also returns how many
/// objects were taken away and how many added.
pub fn build_changed_scene(kind: SceneKind, seed: u64, changes: usize) -> (Scene, usize, usize) {
    let mut edit = Edit {
        removed: removal_order(kind).take(changes).collect(),
        added: new_objects(kind, seed, changes),
        num_removed: 0,
    };
    let scene = edit.apply(kind, seed);
    (scene, edit.num_removed, edit.added.len())
}

/// Changes applied to a scene's movable objects.
struct Edit {
    /// Indices of the movable objects left out.
    removed: Vec<usize>,
    /// New boxes, added with their own textures.
    added: Vec<SolidBox>,
    /// Objects left out so far.
    num_removed: usize,
}

impl Edit {
    fn apply(&mut self, kind: SceneKind, seed: u64) -> Scene {
        match kind {
            SceneKind::Yard | SceneKind::Aerial | SceneKind::Orbit => yard(seed, self),
            SceneKind::Room => room(seed, self),
            SceneKind::Corridor => corridor(seed, self),
        }
    }

    /// Adds the movable objects (`k`-th of `objects` unless removed) and then
    /// the new ones, with seeds from `seed_base` upwards.
    fn place(&mut self, s: &mut Scene, objects: Vec<SolidBox>, seed: u64, seed_base: u64) {
        for (k, b) in objects.into_iter().enumerate() {
            if self.removed.contains(&k) {
                self.num_removed += 1;
                continue;
            }
            add_box(
                s,
                b,
                Material::Object,
                hash64(seed ^ (seed_base + k as u64)),
            );
        }
        for (k, b) in self.added.iter().enumerate() {
            add_box(
                s,
                b.clone(),
                Material::Object,
                hash64(seed ^ (900 + k as u64)),
            );
        }
    }
}

/// Which movable objects go first: those the 24-image walk sees (room:
/// furniture 1, 4 and 2 first seen from images 2, 10 and 16; yard: objects
/// 5 and 3, and no other).
fn removal_order(kind: SceneKind) -> Box<dyn Iterator<Item = usize>> {
    match kind {
        SceneKind::Yard | SceneKind::Aerial | SceneKind::Orbit => {
            Box::new([5, 3, 1, 6, 2, 4, 0].into_iter())
        }
        SceneKind::Room => Box::new([1, 4, 2, 0, 3].into_iter()),
        SceneKind::Corridor => Box::new(0..),
    }
}

/// Up to `n` new boxes for `kind`: candidates in view of the trajectory,
/// those that would touch one of the scene's own solids skipped.
fn new_objects(kind: SceneKind, seed: u64, n: usize) -> Vec<SolidBox> {
    if n == 0 {
        return Vec::new();
    }
    let candidates: Vec<SolidBox> = match kind {
        SceneKind::Yard | SceneKind::Aerial | SceneKind::Orbit => vec![
            boxed(4.8, -8.6, 1.2, 0.8, 1.2, 20.0),
            boxed(10.0, -3.0, 1.0, 1.4, 1.0, 0.0),
            boxed(9.0, 3.0, 1.0, 1.8, 1.2, -15.0),
            boxed(-1.5, -8.6, 1.4, 0.9, 1.5, -10.0),
            boxed(-2.0, 8.5, 1.4, 1.0, 1.5, 20.0),
            boxed(-9.5, 3.0, 1.2, 1.2, 2.0, 0.0),
            boxed(4.5, -8.5, 1.6, 0.8, 1.0, 30.0),
            boxed(8.5, 7.5, 1.0, 1.0, 0.9, 10.0),
        ],
        SceneKind::Room => vec![
            boxed(5.2, -0.8, 0.8, 1.0, 0.7, 0.0),
            boxed(0.0, -3.8, 1.2, 0.7, 0.9, 0.0),
            boxed(3.6, 3.9, 0.8, 0.6, 1.0, 0.0),
            boxed(-4.8, -2.8, 0.8, 0.8, 1.4, 0.0),
            boxed(-4.0, 3.8, 1.4, 0.6, 1.1, 0.0),
            boxed(-5.3, -1.5, 0.8, 0.6, 1.0, 0.0),
        ],
        SceneKind::Corridor => (0..24)
            .map(|i| {
                let x = 3.0 + 1.5 * i as f64;
                let side = if i % 2 == 0 { 1.0 } else { -1.0 };
                boxed(x, side * (1.2 - 0.176), 0.7, 0.35, 1.3, 0.0)
            })
            .collect(),
    };
    let existing = build_scene_solids(kind, seed);
    let mut chosen: Vec<SolidBox> = Vec::new();
    for c in candidates {
        if chosen.len() == n {
            break;
        }
        let clear = existing
            .iter()
            .chain(&chosen)
            .all(|b| !boxes_touch(b, &c, 0.1));
        if clear {
            chosen.push(c);
        }
    }
    chosen
}

/// The solids of the unchanged scene.
fn build_scene_solids(kind: SceneKind, seed: u64) -> Vec<SolidBox> {
    let mut edit = Edit {
        removed: Vec::new(),
        added: Vec::new(),
        num_removed: 0,
    };
    edit.apply(kind, seed).solids
}

/// Whether two upright boxes standing on the ground come within `margin_m`
/// of each other: a point of one's footprint outline (every 5 cm) or centre
/// inside the other grown by the margin.
fn boxes_touch(a: &SolidBox, b: &SolidBox, margin_m: f64) -> bool {
    let outline = |x: &SolidBox| -> Vec<Vector3<f64>> {
        let (sin, cos) = x.yaw_rad.sin_cos();
        let (ex, ey) = (v(cos, sin, 0.0), v(-sin, cos, 0.0));
        let centre = v(x.center_xy_m[0], x.center_xy_m[1], x.base_z_m + 0.05);
        let (hx, hy) = (x.size_m[0] / 2.0, x.size_m[1] / 2.0);
        let corners = [(-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy)];
        let mut points = vec![centre];
        for k in 0..4 {
            let (p, q) = (corners[k], corners[(k + 1) % 4]);
            let steps = ((q.0 - p.0).hypot(q.1 - p.1) / 0.05).ceil().max(1.0) as usize;
            for i in 0..steps {
                let t = i as f64 / steps as f64;
                let (u, w) = (p.0 + t * (q.0 - p.0), p.1 + t * (q.1 - p.1));
                points.push(centre + ex * u + ey * w);
            }
        }
        points
    };
    outline(a).iter().any(|p| b.contains(p, -margin_m))
        || outline(b).iter().any(|p| a.contains(p, -margin_m))
}

/// Camera trajectory of `num_images` poses (local frame).
pub fn trajectory(kind: SceneKind, num_images: usize, seed: u64) -> Vec<BodyPose> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x7A3C_0FFE);
    let mut poses = match kind {
        SceneKind::Yard => circle_outward(num_images, [0.0, -0.5], 5.0, 0.35, 1.6, -6.0, 80.0),
        SceneKind::Room => circle_outward(num_images, [0.0, 0.0], 1.6, 0.22, 1.5, 0.0, 75.0),
        SceneKind::Corridor => corridor_walk(num_images),
        SceneKind::Aerial => survey_flight(num_images),
        // A full circle 14 m about the yard's middle at 16 m, facing in.
        SceneKind::Orbit => {
            let step_m = 2.0 * PI * ORBIT_RADIUS_M / num_images as f64;
            circle_outward(
                num_images,
                [0.0, -0.5],
                ORBIT_RADIUS_M,
                step_m,
                16.0,
                45.0,
                -90.0,
            )
        }
    };
    // Hand-held jitter: +-2 cm, +-0.8 deg.
    for p in &mut poses {
        for k in 0..3 {
            p.position_m[k] += rng.gen_range(-0.02..0.02);
        }
        p.roll_rad += rng.gen_range(-0.8f64..0.8).to_radians();
        p.pitch_rad += rng.gen_range(-0.8f64..0.8).to_radians();
        p.yaw_rad += rng.gen_range(-0.8f64..0.8).to_radians();
    }
    poses
}

/// Walks a circle of `radius_m` counter-clockwise with `step_m` between
/// images, the camera turned `look_deg` from the walking direction towards the
/// outside (90 = straight out, -90 straight in) and pitched `pitch_deg` down.
fn circle_outward(
    n: usize,
    centre: [f64; 2],
    radius_m: f64,
    step_m: f64,
    height_m: f64,
    pitch_deg: f64,
    look_deg: f64,
) -> Vec<BodyPose> {
    let dtheta = step_m / radius_m;
    (0..n)
        .map(|i| {
            let theta = -PI / 2.0 + dtheta * i as f64;
            let pos = Vector3::new(
                centre[0] + radius_m * theta.cos(),
                centre[1] + radius_m * theta.sin(),
                height_m,
            );
            // Walking direction (counter-clockwise) is theta + 90 deg; outward is theta.
            let heading = theta + PI / 2.0;
            let yaw = heading - look_deg.to_radians();
            BodyPose {
                position_m: pos,
                roll_rad: 0.0,
                pitch_rad: pitch_deg.to_radians(),
                yaw_rad: yaw,
            }
        })
        .collect()
}

/// Radius of the drone's circle over the yard ([`SceneKind::Orbit`]), metres.
const ORBIT_RADIUS_M: f64 = 14.0;

/// Height of the survey flight over the yard's ground, metres.
const FLIGHT_HEIGHT_M: f64 = 24.0;

/// A drone's survey of the yard: the camera looking straight down, three
/// strips 5 m apart (y = -5, 0, 5) flown east, west and east again between
/// x = -9 and 9 m, the camera's top towards the flight direction; images
/// evenly along each strip (at 24 images 2.6 m apart, 89 % overlap along
/// the strip and 83 % across it at 24 m).
fn survey_flight(n: usize) -> Vec<BodyPose> {
    let strips = 3.min(n);
    let mut poses = Vec::with_capacity(n);
    for s in 0..strips {
        let count = n / strips + usize::from(s < n % strips);
        let y = 5.0 * (s as f64 - (strips as f64 - 1.0) / 2.0);
        let east = s % 2 == 0;
        for i in 0..count {
            let t = if count > 1 {
                i as f64 / (count - 1) as f64
            } else {
                0.5
            };
            let x = if east {
                -9.0 + 18.0 * t
            } else {
                9.0 - 18.0 * t
            };
            poses.push(BodyPose {
                position_m: Vector3::new(x, y, FLIGHT_HEIGHT_M),
                roll_rad: 0.0,
                pitch_rad: PI / 2.0,
                yaw_rad: if east { 0.0 } else { PI },
            });
        }
    }
    poses
}

/// Length of the corridor walk's forward leg at most (the corridor is 40 m
/// long; the walk starts at x = 2 m and turns within 0.35 m of its end).
const CORRIDOR_WALK_M: f64 = 36.0;

/// Corridor: forward along +x, a turn over a short arc, back along -x.
/// Images are 0.45 m apart, closer when more than 200 would not fit in
/// the corridor.
fn corridor_walk(n: usize) -> Vec<BodyPose> {
    let n_turn = (n / 5).max(6).min(n);
    let n_fwd = (n - n_turn) / 2;
    let n_back = n - n_turn - n_fwd;
    let step_m = 0.45f64.min(CORRIDOR_WALK_M / n_fwd.max(1) as f64);
    let look = 22f64.to_radians();
    let start_x = 2.0;
    let mut poses = Vec::with_capacity(n);
    let height = 1.55;
    for i in 0..n_fwd {
        let x = start_x + step_m * i as f64;
        poses.push(BodyPose {
            position_m: Vector3::new(x, -0.35, height),
            roll_rad: 0.0,
            pitch_rad: 0.0,
            yaw_rad: look,
        });
    }
    // Turn from yaw = look to yaw = pi - look along a half circle of radius 0.35 m.
    let x_end = start_x + step_m * n_fwd.max(1) as f64;
    for j in 0..n_turn {
        let s = (j as f64 + 0.5) / n_turn as f64;
        let phi = -PI / 2.0 + PI * s;
        let pos = Vector3::new(x_end + 0.35 * phi.cos(), 0.35 * phi.sin(), height);
        let yaw = look + (PI - 2.0 * look) * s;
        poses.push(BodyPose {
            position_m: pos,
            roll_rad: 0.0,
            pitch_rad: 0.0,
            yaw_rad: yaw,
        });
    }
    for i in 0..n_back {
        let x = x_end - step_m * (i as f64 + 1.0);
        poses.push(BodyPose {
            position_m: Vector3::new(x, 0.35, height),
            roll_rad: 0.0,
            pitch_rad: 0.0,
            yaw_rad: PI - look,
        });
    }
    poses
}

fn tex(material: Material, seed: u64, k: u64) -> Texture {
    Texture::new(material, hash64(seed.wrapping_mul(1000).wrapping_add(k)))
}

fn v(x: f64, y: f64, z: f64) -> Vector3<f64> {
    Vector3::new(x, y, z)
}

fn add_box(scene: &mut Scene, b: SolidBox, material: Material, seed: u64) {
    scene.quads.extend(b.faces(material, seed));
    scene.solids.push(b);
}

fn boxed(cx: f64, cy: f64, sx: f64, sy: f64, sz: f64, yaw_deg: f64) -> SolidBox {
    SolidBox {
        center_xy_m: [cx, cy],
        base_z_m: 0.0,
        size_m: [sx, sy, sz],
        yaw_rad: yaw_deg.to_radians(),
    }
}

fn yard(seed: u64, edit: &mut Edit) -> Scene {
    let mut s = Scene {
        quads: vec![Quad::new(
            v(-22.0, -22.0, 0.0),
            v(44.0, 0.0, 0.0),
            v(0.0, 44.0, 0.0),
            tex(Material::Ground, seed, 0),
        )],
        solids: vec![],
        lighting: Lighting {
            to_light: v(0.45, -0.35, 0.82).normalize(),
            light: 0.85,
            ambient: 0.38,
            shadows: true,
            sky: true,
        },
    };
    let buildings = [
        boxed(0.0, 12.5, 28.0, 6.0, 9.0, 0.0),
        boxed(-1.0, -12.5, 24.0, 6.0, 7.0, 0.0),
        boxed(-14.5, 0.0, 6.0, 19.0, 8.0, 0.0),
        boxed(14.0, 0.5, 6.0, 16.0, 10.5, 4.0),
    ];
    for (k, b) in buildings.into_iter().enumerate() {
        add_box(&mut s, b, Material::Facade, hash64(seed ^ (100 + k as u64)));
    }
    let objects = vec![
        boxed(5.0, 5.5, 2.2, 1.6, 2.6, 15.0),
        boxed(-4.5, -5.5, 1.0, 1.0, 1.0, 30.0),
        boxed(-5.8, -4.8, 1.2, 0.8, 0.8, -10.0),
        boxed(8.0, -6.0, 4.0, 0.3, 1.2, 0.0),
        boxed(-8.5, 6.0, 0.6, 0.6, 2.8, 0.0),
        boxed(2.0, -8.0, 1.5, 1.5, 1.8, 45.0),
        boxed(-9.0, -1.0, 1.8, 0.9, 1.1, 80.0),
    ];
    edit.place(&mut s, objects, seed, 200);
    s
}

/// An inward-facing axis-aligned shell: floor, ceiling and four walls.
fn shell(s: &mut Scene, lo: [f64; 3], hi: [f64; 3], seed: u64) {
    let (x0, y0, z0) = (lo[0], lo[1], lo[2]);
    let (dx, dy, dz) = (hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]);
    let q = &mut s.quads;
    // Floor, normal +z.
    q.push(Quad::new(
        v(x0, y0, z0),
        v(dx, 0.0, 0.0),
        v(0.0, dy, 0.0),
        tex(Material::Floor, seed, 1),
    ));
    // Ceiling, normal -z.
    q.push(Quad::new(
        v(x0, y0, z0 + dz),
        v(0.0, dy, 0.0),
        v(dx, 0.0, 0.0),
        tex(Material::Ceiling, seed, 2),
    ));
    // Wall at y0, normal +y: u = -x... use u = +z, v = +x: z cross x = +y.
    q.push(Quad::new(
        v(x0, y0, z0),
        v(0.0, 0.0, dz),
        v(dx, 0.0, 0.0),
        tex(Material::Wall, seed, 3),
    ));
    // Wall at y1, normal -y: u = +x, v = +z: x cross z = -y.
    q.push(Quad::new(
        v(x0, y0 + dy, z0),
        v(dx, 0.0, 0.0),
        v(0.0, 0.0, dz),
        tex(Material::Wall, seed, 4),
    ));
    // Wall at x0, normal +x: u = +y, v = +z.
    q.push(Quad::new(
        v(x0, y0, z0),
        v(0.0, dy, 0.0),
        v(0.0, 0.0, dz),
        tex(Material::Wall, seed, 5),
    ));
    // Wall at x1, normal -x: u = +z, v = +y: z cross y = -x.
    q.push(Quad::new(
        v(x0 + dx, y0, z0),
        v(0.0, 0.0, dz),
        v(0.0, dy, 0.0),
        tex(Material::Wall, seed, 6),
    ));
}

fn indoor_lighting() -> Lighting {
    Lighting {
        to_light: v(0.3, 0.5, 0.81).normalize(),
        light: 0.45,
        ambient: 0.62,
        shadows: false,
        sky: false,
    }
}

fn room(seed: u64, edit: &mut Edit) -> Scene {
    let mut s = Scene {
        quads: vec![],
        solids: vec![],
        lighting: indoor_lighting(),
    };
    shell(&mut s, [-6.0, -4.5, 0.0], [6.0, 4.5, 3.2], seed);
    let pillars = [
        (-3.0, -2.4),
        (3.0, -2.4),
        (-3.0, 2.4),
        (3.0, 2.4),
        (0.0, 3.3),
    ];
    for (k, (x, y)) in pillars.into_iter().enumerate() {
        add_box(
            &mut s,
            boxed(x, y, 0.5, 0.5, 3.2, 0.0),
            Material::Wall,
            hash64(seed ^ (300 + k as u64)),
        );
    }
    let furniture = vec![
        boxed(-5.2, 0.5, 1.2, 2.0, 0.8, 0.0),
        boxed(4.8, -3.5, 1.6, 0.8, 1.9, 0.0),
        boxed(1.5, 3.8, 2.0, 0.6, 1.0, 0.0),
        boxed(-1.8, -3.9, 1.0, 0.9, 0.75, 10.0),
        boxed(5.3, 2.0, 0.8, 1.4, 1.2, 0.0),
    ];
    edit.place(&mut s, furniture, seed, 400);
    s
}

fn corridor(seed: u64, edit: &mut Edit) -> Scene {
    let mut s = Scene {
        quads: vec![],
        solids: vec![],
        lighting: indoor_lighting(),
    };
    shell(&mut s, [0.0, -1.2, 0.0], [40.0, 1.2, 2.8], seed);
    // Cabinets, benches and pilasters along both walls, from a seeded layout.
    let mut rng = ChaCha8Rng::seed_from_u64(hash64(seed ^ 0xC0DE));
    let mut x = 1.5;
    let mut cabinets = Vec::new();
    while x < 38.0 {
        let len = rng.gen_range(0.4..1.6);
        let depth = rng.gen_range(0.15..0.45);
        let height = rng.gen_range(0.5..2.2);
        let side = if rng.gen_bool(0.5) { 1.0 } else { -1.0 };
        let y = side * (1.2 - depth / 2.0 - 0.001);
        cabinets.push(boxed(x + len / 2.0, y, len, depth, height, 0.0));
        x += len + rng.gen_range(1.0..3.0);
    }
    edit.place(&mut s, cabinets, seed, 500);
    s
}
