//! Shared helpers for the integration tests.
#![allow(dead_code)]
use std::ffi::OsStr;
use std::path::PathBuf;

use colmap_lidar::scene::{Image, Reconstruction};

/// Path of the built `colmap-lidar` binary.
pub fn bin() -> PathBuf {
    PathBuf::from(env!("CARGO_BIN_EXE_colmap-lidar"))
}

/// Runs `colmap` (headless) with `args`, asserting success; returns stdout + stderr.
pub fn run_colmap<I, S>(args: I) -> String
where
    I: IntoIterator<Item = S>,
    S: AsRef<OsStr>,
{
    let args: Vec<S> = args.into_iter().collect();
    let out = std::process::Command::new("colmap")
        .args(&args)
        .env("QT_QPA_PLATFORM", "offscreen")
        .output()
        .expect("colmap runs");
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let shown: Vec<_> = args.iter().map(|a| a.as_ref().to_string_lossy()).collect();
    assert!(out.status.success(), "colmap {shown:?} failed:\n{text}");
    text
}

/// True when Debian's `colmap` binary is on PATH. Tests that need it print a
/// loud message and return early when it is absent; CI installs it.
pub fn have_colmap() -> bool {
    let found = std::process::Command::new("colmap")
        .arg("help")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .status()
        .is_ok();
    if !found {
        eprintln!(
            "\n!!!!! SKIPPED: the `colmap` binary is not installed (run scripts/setup.sh) !!!!!\n"
        );
    }
    found
}

/// A synthetic scene with its real COLMAP database, made once per test run and
/// shared by every test that needs one (rendering and COLMAP cost tens of seconds).
pub struct SceneDb {
    /// Keeps the folder alive for the whole run.
    _dir: tempfile::TempDir,
    /// The scene folder (`images/`, `lidar.ply`, `gt/`, `init_pose.txt`).
    pub scene: PathBuf,
    /// The COLMAP database made by `feature_extractor` + `exhaustive_matcher`.
    pub database: PathBuf,
}

/// Images in the shared yard scene: "a few dozen", as a user's first run.
pub const YARD_IMAGES: usize = 24;

/// The shared CI-sized yard scene (`YARD_IMAGES` images, 640x480, seed 7) and its database,
/// or `None` (with a loud message) when `colmap` is not installed.
pub fn yard_db() -> Option<&'static SceneDb> {
    use colmap_lidar::synth::{
        generate_scene, make_database, HarnessOptions, SceneKind, SynthOptions,
    };
    static YARD: std::sync::OnceLock<Option<SceneDb>> = std::sync::OnceLock::new();
    YARD.get_or_init(|| {
        if !have_colmap() {
            return None;
        }
        let dir = tempfile::tempdir().expect("temporary folder");
        let scene = dir.path().join("yard");
        let options = SynthOptions {
            scene: SceneKind::Yard,
            num_images: YARD_IMAGES,
            width: 640,
            height: 480,
            seed: 7,
            ..SynthOptions::default()
        };
        generate_scene(&options, &scene).expect("yard scene renders");
        let database =
            make_database(&scene, &HarnessOptions::default()).expect("COLMAP makes the database");
        Some(SceneDb {
            _dir: dir,
            scene,
            database,
        })
    })
    .as_ref()
}

/// The header of a PLY file's bytes (through `end_header`) and where the
/// body starts.
pub fn ply_header(bytes: &[u8]) -> (&str, usize) {
    let end = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .expect("a PLY header")
        + 11;
    (std::str::from_utf8(&bytes[..end]).unwrap(), end)
}

/// `rec` with only the images `keep` takes: their observations, and the
/// points two or more of them still see.
pub fn part_of_model(rec: &Reconstruction, keep: impl Fn(&Image) -> bool) -> Reconstruction {
    let mut part = rec.clone();
    part.images.retain(|_, img| keep(img));
    part.points3d.retain(|_, p| {
        p.track.retain(|e| part.images.contains_key(&e.image_id));
        p.track.len() >= 2
    });
    for img in part.images.values_mut() {
        for p in &mut img.points2d {
            if p.point3d_id
                .is_some_and(|id| !part.points3d.contains_key(&id))
            {
                p.point3d_id = None;
            }
        }
    }
    part
}
