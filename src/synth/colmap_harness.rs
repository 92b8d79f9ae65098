//! Runs the real COLMAP (Debian's `colmap`, CPU, headless) on a synthetic
//! scene: `feature_extractor` with the true camera, then
//! `exhaustive_matcher`. Returns the database path. Tests use it; the shell
//! twin is `scripts/make_database.sh`.
use std::fs;
use std::path::{Path, PathBuf};
use std::process::Command;

use super::SynthError;

/// Options of [`make_database`].
#[derive(Clone, Debug)]
pub struct HarnessOptions {
    /// The `colmap` executable. Default `colmap` (from PATH).
    pub colmap: PathBuf,
    /// Database to create. Default `<scene_dir>/database.db`.
    pub database: Option<PathBuf>,
    /// `--SiftExtraction.max_num_features`. Default 8192 (COLMAP's default).
    pub max_num_features: usize,
    /// Threads for extraction and matching. Default 2.
    pub num_threads: usize,
    /// Pass the true camera of `gt/cameras.txt` to the extractor (single
    /// camera). Default true.
    pub use_true_camera: bool,
}

impl Default for HarnessOptions {
    fn default() -> Self {
        Self {
            colmap: PathBuf::from("colmap"),
            database: None,
            max_num_features: 8192,
            num_threads: 2,
            use_true_camera: true,
        }
    }
}

/// The single camera line of a COLMAP `cameras.txt`: (model name, params joined by commas).
fn read_true_camera(cameras_txt: &Path) -> Result<(String, String), SynthError> {
    let text = fs::read_to_string(cameras_txt).map_err(|e| SynthError::io(cameras_txt, e))?;
    let line = text
        .lines()
        .map(str::trim)
        .find(|l| !l.is_empty() && !l.starts_with('#'))
        .ok_or_else(|| SynthError::Parse {
            path: cameras_txt.into(),
            message: "no camera line".into(),
        })?;
    let fields: Vec<&str> = line.split_whitespace().collect();
    if fields.len() < 5 {
        return Err(SynthError::Parse {
            path: cameras_txt.into(),
            message: format!("camera line too short: {line:?}"),
        });
    }
    Ok((fields[1].to_string(), fields[4..].join(",")))
}

fn run(colmap: &Path, step: &str, args: &[String]) -> Result<(), SynthError> {
    log::info!("running colmap {step}");
    let out = Command::new(colmap)
        .arg(step)
        .args(args)
        .env("QT_QPA_PLATFORM", "offscreen")
        .output()
        .map_err(|e| SynthError::ColmapNotFound(format!("{}: {e}", colmap.display())))?;
    if !out.status.success() {
        let mut text = String::from_utf8_lossy(&out.stdout).into_owned();
        text.push_str(&String::from_utf8_lossy(&out.stderr));
        let lines: Vec<&str> = text.lines().collect();
        let tail = lines[lines.len().saturating_sub(25)..].join("\n");
        return Err(SynthError::ColmapFailed {
            step: step.to_string(),
            status: out.status.to_string(),
            output_tail: tail,
        });
    }
    Ok(())
}

/// Creates a fresh COLMAP database for the scene in `scene_dir` (with
/// `images/` and `gt/cameras.txt`) and returns its path. An existing database
/// at that path is replaced.
pub fn make_database(scene_dir: &Path, opts: &HarnessOptions) -> Result<PathBuf, SynthError> {
    let images = scene_dir.join("images");
    if !images.is_dir() {
        return Err(SynthError::io(
            &images,
            std::io::Error::new(std::io::ErrorKind::NotFound, "no images folder"),
        ));
    }
    let db = opts
        .database
        .clone()
        .unwrap_or_else(|| scene_dir.join("database.db"));
    for suffix in ["", "-wal", "-shm"] {
        let p = PathBuf::from(format!("{}{suffix}", db.display()));
        if p.exists() {
            fs::remove_file(&p).map_err(|e| SynthError::io(&p, e))?;
        }
    }
    let s = |v: &str| v.to_string();
    let threads = opts.num_threads.max(1).to_string();
    let mut args = vec![
        s("--database_path"),
        db.display().to_string(),
        s("--image_path"),
        images.display().to_string(),
        s("--ImageReader.single_camera"),
        s("1"),
        s("--SiftExtraction.use_gpu"),
        s("0"),
        s("--SiftExtraction.num_threads"),
        threads.clone(),
        s("--SiftExtraction.max_num_features"),
        opts.max_num_features.to_string(),
    ];
    if opts.use_true_camera {
        let (model, params) = read_true_camera(&scene_dir.join("gt").join("cameras.txt"))?;
        args.extend([
            s("--ImageReader.camera_model"),
            model,
            s("--ImageReader.camera_params"),
            params,
        ]);
    }
    run(&opts.colmap, "feature_extractor", &args)?;
    let args = vec![
        s("--database_path"),
        db.display().to_string(),
        s("--SiftMatching.use_gpu"),
        s("0"),
        s("--SiftMatching.num_threads"),
        threads,
    ];
    run(&opts.colmap, "exhaustive_matcher", &args)?;
    Ok(db)
}
