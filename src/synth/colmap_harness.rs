//! Runs the real COLMAP (Debian's `colmap`, CPU, headless) on a synthetic
//! scene: `feature_extractor` with the true camera, then
//! `exhaustive_matcher` (or `sequential_matcher`, as for a video). Returns
//! the database path. Tests use it; the shell twin is
//! `scripts/make_database.sh`.
use std::fs;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

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
    /// Which pairs are matched. Default [`Matcher::Exhaustive`].
    pub matcher: Matcher,
}

/// COLMAP's matcher to run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Matcher {
    /// Every pair (`exhaustive_matcher`).
    Exhaustive,
    /// `sequential_matcher` with `overlap`: image i with i + 1..=overlap in
    /// name order and (COLMAP's default quadratic overlap) i + 2^k for
    /// k < overlap; loop detection off (it needs a vocabulary tree).
    Sequential { overlap: usize },
}

impl Default for HarnessOptions {
    fn default() -> Self {
        Self {
            colmap: PathBuf::from("colmap"),
            database: None,
            max_num_features: 8192,
            num_threads: 2,
            use_true_camera: true,
            matcher: Matcher::Exhaustive,
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

/// How long a COLMAP step may linger after printing its final "Elapsed time"
/// line before it is taken as hung at shutdown and killed.
const SHUTDOWN_GRACE: Duration = Duration::from_secs(20);

/// Runs one COLMAP step. COLMAP 3.8's matchers can deadlock in their
/// destructor after all work is written (seen: `exhaustive_matcher` joining a
/// geometry-verifier thread that waits on an already-stopped job queue, all
/// 276 pairs in the database): once the step has printed its final
/// "Elapsed time" line and still runs `SHUTDOWN_GRACE` later, it is killed
/// and the step counts as done.
fn run(colmap: &Path, step: &str, args: &[String]) -> Result<(), SynthError> {
    run_with_grace(colmap, step, args, SHUTDOWN_GRACE)
}

fn run_with_grace(
    colmap: &Path,
    step: &str,
    args: &[String],
    grace: Duration,
) -> Result<(), SynthError> {
    log::info!("running colmap {step}");
    let log_file = tempfile::NamedTempFile::new().map_err(|e| SynthError::io(Path::new("."), e))?;
    let log_path = log_file.path().to_path_buf();
    let out_handle = log_file
        .reopen()
        .map_err(|e| SynthError::io(&log_path, e))?;
    let err_handle = log_file
        .reopen()
        .map_err(|e| SynthError::io(&log_path, e))?;
    let mut child = Command::new(colmap)
        .arg(step)
        .args(args)
        .env("QT_QPA_PLATFORM", "offscreen")
        .stdout(Stdio::from(out_handle))
        .stderr(Stdio::from(err_handle))
        .spawn()
        .map_err(|e| SynthError::ColmapNotFound(format!("{}: {e}", colmap.display())))?;
    let mut finished_at: Option<Instant> = None;
    let status = loop {
        if let Some(status) = child.try_wait().map_err(|e| SynthError::io(colmap, e))? {
            break Some(status);
        }
        if finished_at.is_none()
            && fs::read_to_string(&log_path).is_ok_and(|t| t.contains("Elapsed time"))
        {
            finished_at = Some(Instant::now());
        }
        if finished_at.is_some_and(|t| t.elapsed() > grace) {
            log::warn!(
                "colmap {step} finished its work but did not exit within {:.0} s (a known shutdown hang of COLMAP 3.8); killed it",
                grace.as_secs_f64()
            );
            let _ = child.kill();
            let _ = child.wait();
            break None;
        }
        std::thread::sleep(Duration::from_millis(250));
    };
    if let Some(status) = status.filter(|s| !s.success()) {
        let text = fs::read_to_string(&log_path).unwrap_or_default();
        let lines: Vec<&str> = text.lines().collect();
        let tail = lines[lines.len().saturating_sub(25)..].join("\n");
        return Err(SynthError::ColmapFailed {
            step: step.to_string(),
            status: status.to_string(),
            output_tail: tail,
        });
    }
    Ok(())
}

/// Removes the SQLite database `db` and its journal files, where present.
fn remove_database(db: &Path) -> Result<(), SynthError> {
    for suffix in ["", "-wal", "-shm"] {
        let p = PathBuf::from(format!("{}{suffix}", db.display()));
        if p.exists() {
            fs::remove_file(&p).map_err(|e| SynthError::io(&p, e))?;
        }
    }
    Ok(())
}

/// `feature_extractor`'s arguments: the images of `images` into `db`, one
/// camera for all, on the CPU with `opts.num_threads`, at most
/// `max_num_features` per image.
fn extractor_args(
    db: &Path,
    images: &Path,
    max_num_features: usize,
    opts: &HarnessOptions,
) -> Vec<String> {
    [
        "--database_path",
        &db.display().to_string(),
        "--image_path",
        &images.display().to_string(),
        "--ImageReader.single_camera",
        "1",
        "--SiftExtraction.use_gpu",
        "0",
        "--SiftExtraction.num_threads",
        &opts.num_threads.max(1).to_string(),
        "--SiftExtraction.max_num_features",
        &max_num_features.to_string(),
    ]
    .map(str::to_string)
    .to_vec()
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
    remove_database(&db)?;
    let s = |v: &str| v.to_string();
    let mut args = extractor_args(&db, &images, opts.max_num_features, opts);
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
    run_matcher(&db, opts)?;
    Ok(db)
}

/// A copy of `database` at `copy` with the camera COLMAP's extractor guesses
/// when it is given none (1.2 x the larger side, the image centre, no
/// distortion, `prior_focal_length = 0`: `feature_extractor` run on `image`
/// alone into a scratch database), every pair verified again under that
/// camera by `opts.matcher`. Features and raw matches are kept: neither
/// depends on the camera, and COLMAP's matchers only verify a pair whose
/// matches are already in the database. So this is the database an
/// extraction without the camera would give, for a few seconds instead of
/// the matching's minute. `database` must hold one camera of `image`'s size.
pub fn copy_with_guessed_camera(
    database: &Path,
    image: &Path,
    copy: &Path,
    opts: &HarnessOptions,
) -> Result<PathBuf, SynthError> {
    let sql = |path: &Path| {
        let path = path.to_path_buf();
        move |e: rusqlite::Error| SynthError::Parse {
            path: path.clone(),
            message: e.to_string(),
        }
    };
    let scratch = tempfile::tempdir()?;
    let images = scratch.path().join("images");
    fs::create_dir(&images).map_err(|e| SynthError::io(&images, e))?;
    let name = image.file_name().ok_or_else(|| {
        SynthError::InvalidOption(format!("{}: not an image file", image.display()))
    })?;
    fs::copy(image, images.join(name)).map_err(|e| SynthError::io(image, e))?;
    let guess_db = scratch.path().join("guess.db");
    // (Only the camera row is wanted: few features.)
    let args = extractor_args(&guess_db, &images, 64, opts);
    run(&opts.colmap, "feature_extractor", &args)?;
    type CameraRow = (i64, i64, i64, Vec<u8>, i64);
    let guess: CameraRow = rusqlite::Connection::open(&guess_db)
        .and_then(|c| {
            c.query_row(
                "SELECT model, width, height, params, prior_focal_length FROM cameras",
                [],
                |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?, r.get(4)?)),
            )
        })
        .map_err(sql(&guess_db))?;
    remove_database(copy)?;
    fs::copy(database, copy).map_err(|e| SynthError::io(database, e))?;
    // No copy left behind when it cannot be made right.
    let made = (|| {
        let conn = rusqlite::Connection::open(copy).map_err(sql(copy))?;
        let sizes: Vec<(i64, i64)> = conn
            .prepare("SELECT width, height FROM cameras")
            .and_then(|mut st| {
                st.query_map([], |r| Ok((r.get(0)?, r.get(1)?)))?
                    .collect::<Result<_, _>>()
            })
            .map_err(sql(copy))?;
        if sizes != [(guess.1, guess.2)] {
            return Err(SynthError::InvalidOption(format!(
                "{}: cameras {sizes:?}, expected one of {}x{} px",
                database.display(),
                guess.1,
                guess.2
            )));
        }
        conn.execute(
            "UPDATE cameras SET model = ?1, params = ?2, prior_focal_length = ?3",
            rusqlite::params![guess.0, guess.3, guess.4],
        )
        .and_then(|_| conn.execute("DELETE FROM two_view_geometries", []))
        .map_err(sql(copy))?;
        drop(conn);
        run_matcher(copy, opts)
    })();
    match made {
        Ok(()) => Ok(copy.to_path_buf()),
        Err(e) => {
            let _ = remove_database(copy);
            Err(e)
        }
    }
}

/// Runs `opts.matcher` on the database `db` (its features extracted).
pub fn run_matcher(db: &Path, opts: &HarnessOptions) -> Result<(), SynthError> {
    let s = |v: &str| v.to_string();
    let mut args = vec![
        s("--database_path"),
        db.display().to_string(),
        s("--SiftMatching.use_gpu"),
        s("0"),
        s("--SiftMatching.num_threads"),
        opts.num_threads.max(1).to_string(),
    ];
    match opts.matcher {
        Matcher::Exhaustive => run(&opts.colmap, "exhaustive_matcher", &args),
        Matcher::Sequential { overlap } => {
            args.extend([
                s("--SequentialMatching.overlap"),
                overlap.to_string(),
                s("--SequentialMatching.loop_detection"),
                s("0"),
            ]);
            run(&opts.colmap, "sequential_matcher", &args)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::fs::PermissionsExt;

    /// A stand-in for `colmap` running `body` (a shell script).
    fn fake_colmap(dir: &Path, body: &str) -> PathBuf {
        let path = dir.join("colmap");
        fs::write(&path, format!("#!/bin/sh\n{body}\n")).unwrap();
        fs::set_permissions(&path, fs::Permissions::from_mode(0o755)).unwrap();
        path
    }

    #[test]
    fn a_step_hung_after_its_final_line_is_killed_and_counts_as_done() {
        let dir = tempfile::tempdir().unwrap();
        let hung = fake_colmap(
            dir.path(),
            "echo 'Elapsed time: 0.1 [minutes]'; exec sleep 600",
        );
        let start = Instant::now();
        run_with_grace(&hung, "exhaustive_matcher", &[], Duration::from_millis(500)).unwrap();
        assert!(start.elapsed() < Duration::from_secs(30));
    }

    #[test]
    fn a_failing_step_reports_its_output() {
        let dir = tempfile::tempdir().unwrap();
        let failing = fake_colmap(dir.path(), "echo 'no such database' >&2; exit 3");
        let err = run_with_grace(
            &failing,
            "feature_extractor",
            &[],
            Duration::from_millis(500),
        )
        .unwrap_err()
        .to_string();
        assert!(
            err.contains("feature_extractor") && err.contains("no such database"),
            "{err}"
        );
        let ok = fake_colmap(dir.path(), "echo 'Elapsed time: 0 [minutes]'");
        run_with_grace(&ok, "feature_extractor", &[], Duration::from_millis(500)).unwrap();
    }
}
