//! Atomic outputs: everything is written into a temporary sibling, then renamed
//! into place, so a failed run never leaves a partial output behind.
use std::fs;
use std::io;
use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};

fn parent_of(path: &Path) -> PathBuf {
    match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

/// Whether `path`'s last component, as written, is `.` or `..` (or it is
/// empty): `Path` would read `out/.` as `out`, whose parent is then the
/// wrong folder.
fn names_nothing(path: &Path) -> bool {
    use std::os::unix::ffi::OsStrExt;
    let bytes = path.as_os_str().as_bytes();
    let trimmed = match bytes.iter().rposition(|&b| b != b'/') {
        Some(end) => &bytes[..=end],
        None => return true,
    };
    let last = trimmed.rsplit(|&b| b == b'/').next().unwrap_or(trimmed);
    last == b"." || last == b".." || path.file_name().is_none()
}

/// An error when `path` names no file or folder ([`names_nothing`]).
fn refuse_nameless(path: &Path) -> io::Result<()> {
    if !names_nothing(path) {
        return Ok(());
    }
    Err(io::Error::new(
        io::ErrorKind::InvalidInput,
        format!(
            "the output `{}` names no file or folder (it ends in `.` or `..`): give its name",
            path.display()
        ),
    ))
}

fn file_in_the_way(folder: &Path, file: &Path) -> io::Error {
    io::Error::new(
        io::ErrorKind::NotADirectory,
        format!(
            "cannot make the folder {} for the output: {} is a file, not a folder",
            folder.display(),
            file.display()
        ),
    )
}

fn not_a_folder(path: &Path) -> io::Error {
    io::Error::new(
        io::ErrorKind::AlreadyExists,
        format!(
            "the output {} exists and is not a folder: refusing to replace it",
            path.display()
        ),
    )
}

/// The output's folder, created when missing; an output that names no file
/// or folder (ending in `.` or `..`) or whose folder cannot be made (a file
/// in its way) is an error that says so.
fn prepare_parent(path: &Path) -> io::Result<PathBuf> {
    refuse_nameless(path)?;
    let parent = parent_of(path);
    if let Err(e) = fs::create_dir_all(&parent) {
        // A file where a folder should be: name it.
        let in_the_way = parent.ancestors().find(|a| a.exists() && !a.is_dir());
        return Err(match in_the_way {
            Some(file) => file_in_the_way(&parent, file),
            None => io::Error::new(
                e.kind(),
                format!("cannot make the folder {}: {e}", parent.display()),
            ),
        });
    }
    Ok(parent)
}

/// Checks, before any work, that an output can be written where asked: it
/// names a file or folder, what exists there is of the kind the command
/// writes (a folder when `is_dir`, else a file), no file stands where a
/// folder of its path should be, and the nearest existing folder on its path
/// takes new entries (a read-only folder or file system is found now, not
/// after a long run). The probe is a temporary folder, removed at once; the
/// output's missing folders are not made.
pub fn check_output_location(path: &Path, is_dir: bool) -> io::Result<()> {
    refuse_nameless(path)?;
    if let Ok(meta) = fs::metadata(path) {
        if is_dir && !meta.is_dir() {
            return Err(not_a_folder(path));
        }
        if !is_dir && meta.is_dir() {
            return Err(io::Error::new(
                io::ErrorKind::AlreadyExists,
                format!(
                    "the output {} is a folder: give a file name",
                    path.display()
                ),
            ));
        }
    }
    let parent = parent_of(path);
    // The nearest existing folder on the path (a relative path's last
    // ancestor is empty: the current folder).
    let Some(existing) = parent
        .ancestors()
        .map(|a| {
            if a.as_os_str().is_empty() {
                Path::new(".")
            } else {
                a
            }
        })
        .find(|a| a.exists())
    else {
        return Ok(());
    };
    if !existing.is_dir() {
        return Err(file_in_the_way(&parent, existing));
    }
    probe(existing, path)
}

/// [`check_output_location`] for a folder whose files are written into it
/// one by one (not replaced as a whole): an existing one must take new
/// entries itself, whatever its parent does.
pub fn check_output_folder_to_fill(dir: &Path) -> io::Result<()> {
    if dir.is_dir() && !names_nothing(dir) {
        return probe(dir, dir);
    }
    check_output_location(dir, true)
}

/// Whether `folder` takes a new entry (a temporary folder, removed at once),
/// for the output `path`.
fn probe(folder: &Path, path: &Path) -> io::Result<()> {
    tempfile::Builder::new()
        .prefix(".colmap-lidar-probe-")
        .tempdir_in(folder)
        .map(drop)
        .map_err(|e| {
            // The system's reason, without the probe's own name.
            let why = e.raw_os_error().map_or_else(
                || e.to_string(),
                |code| io::Error::from_raw_os_error(code).to_string(),
            );
            io::Error::new(
                e.kind(),
                format!(
                    "cannot write the output {}: the folder {} takes no new entries ({why})",
                    path.display(),
                    folder.display()
                ),
            )
        })
}

/// What stood at an output's path when a command started (device, inode,
/// modification time; nothing), so that before replacing it the command can
/// tell whether another process wrote there meanwhile: two runs into one
/// output folder would otherwise each replace it, and the first result be
/// lost without a word.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OutputSnapshot(Option<(u64, u64, i64, i64)>);

impl OutputSnapshot {
    pub fn take(path: &Path) -> Self {
        use std::os::unix::fs::MetadataExt;
        Self(
            fs::symlink_metadata(path)
                .ok()
                .map(|m| (m.dev(), m.ino(), m.mtime(), m.mtime_nsec())),
        )
    }

    /// An error when `path` no longer is what it was at [`Self::take`].
    pub fn check_unchanged(&self, path: &Path) -> io::Result<()> {
        if Self::take(path) == *self {
            return Ok(());
        }
        Err(io::Error::other(format!(
            "the output {} was {} while this run worked (another run writing there?): \
             refusing to replace it; nothing written",
            path.display(),
            if self.0.is_none() { "made" } else { "changed" }
        )))
    }
}

/// `path` as a write to it would find it: resolved through symbolic links,
/// `.` and `..` (its folder only, when it does not exist yet). `None` when
/// neither it nor its folder exists.
fn resolved(path: &Path) -> Option<PathBuf> {
    if let Ok(p) = path.canonicalize() {
        return Some(p);
    }
    let name = path.file_name()?;
    Some(parent_of(path).canonicalize().ok()?.join(name))
}

/// Why writing `output` (a folder when `output_is_dir`, replaced as a whole,
/// else a file) would destroy an input: it is one of the input `files`, is
/// or lies inside one of the input `folders`, or (a folder) holds one of
/// the inputs. `None` when it would not.
pub fn output_replaces_input(
    output: &Path,
    output_is_dir: bool,
    files: &[&Path],
    folders: &[&Path],
) -> Option<String> {
    let out = resolved(output)?;
    for file in files {
        let Some(input) = resolved(file) else {
            continue;
        };
        if input == out {
            return Some(format!(
                "the output {} is the input {}: write it elsewhere",
                output.display(),
                file.display()
            ));
        }
        if output_is_dir && input.starts_with(&out) {
            return Some(format!(
                "the output folder {} holds the input {}, and is replaced as a whole: write it elsewhere",
                output.display(),
                file.display()
            ));
        }
    }
    for folder in folders {
        let Some(input) = resolved(folder) else {
            continue;
        };
        let (o, f) = (output.display(), folder.display());
        if out == input {
            return Some(format!(
                "the output {o} is the input folder {f}: write it elsewhere"
            ));
        }
        if out.starts_with(&input) {
            return Some(format!(
                "the output {o} is inside the input folder {f}: write it elsewhere"
            ));
        }
        if output_is_dir && input.starts_with(&out) {
            return Some(format!(
                "the output folder {o} holds the input folder {f}, and is replaced as a whole: write it elsewhere"
            ));
        }
    }
    None
}

/// Writes a folder atomically: `fill` populates a fresh temporary folder next
/// to `dir`, which then replaces `dir` (an existing `dir` is removed only after
/// `fill` succeeded).
pub fn write_dir_atomically<E>(
    dir: &Path,
    fill: impl FnOnce(&Path) -> Result<(), E>,
) -> Result<(), E>
where
    E: From<io::Error>,
{
    let parent = prepare_parent(dir)?;
    // Before the work of filling it.
    if dir.exists() && !dir.is_dir() {
        return Err(not_a_folder(dir).into());
    }
    let tmp = tempfile::Builder::new()
        .prefix(".colmap-lidar-tmp-")
        .tempdir_in(&parent)?;
    fill(tmp.path())?;
    // Temporary folders are created 0700; outputs get the usual 0755.
    fs::set_permissions(tmp.path(), fs::Permissions::from_mode(0o755))?;
    let staged = tmp.keep();
    if dir.exists() {
        let old = tempfile::Builder::new()
            .prefix(".colmap-lidar-old-")
            .tempdir_in(&parent)
            .map(tempfile::TempDir::keep)
            .and_then(|old| fs::remove_dir(&old).map(|()| old))
            .and_then(|old| fs::rename(dir, &old).map(|()| old));
        let old = match old {
            Ok(old) => old,
            Err(e) => {
                let _ = fs::remove_dir_all(&staged);
                return Err(e.into());
            }
        };
        if let Err(e) = fs::rename(&staged, dir) {
            // Put the previous output back before reporting.
            let _ = fs::rename(&old, dir);
            let _ = fs::remove_dir_all(&staged);
            return Err(e.into());
        }
        fs::remove_dir_all(&old)?;
    } else if let Err(e) = fs::rename(&staged, dir) {
        let _ = fs::remove_dir_all(&staged);
        return Err(e.into());
    }
    Ok(())
}

/// Writes a file atomically: `fill` writes a temporary file next to `path`,
/// which is then renamed over `path`.
pub fn write_file_atomically<E>(
    path: &Path,
    fill: impl FnOnce(&mut io::BufWriter<fs::File>) -> Result<(), E>,
) -> Result<(), E>
where
    E: From<io::Error>,
{
    let parent = prepare_parent(path)?;
    let tmp = tempfile::Builder::new()
        .prefix(".colmap-lidar-tmp-")
        .tempfile_in(&parent)?;
    let (file, tmp_path) = tmp.into_parts();
    let mut writer = io::BufWriter::new(file);
    fill(&mut writer)?;
    let file = writer.into_inner().map_err(|e| e.into_error())?;
    // Temporary files are created 0600; outputs get the usual 0644.
    file.set_permissions(fs::Permissions::from_mode(0o644))?;
    file.sync_all()?;
    tmp_path.persist(path).map_err(|e| e.error)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    #[test]
    fn outputs_that_would_replace_an_input_are_named() {
        let root = tempfile::tempdir().unwrap();
        let r = root.path();
        fs::create_dir_all(r.join("model")).unwrap();
        fs::create_dir_all(r.join("images")).unwrap();
        fs::write(r.join("lidar.ply"), "ply").unwrap();
        fs::write(r.join("model/cameras.txt"), "#").unwrap();
        std::os::unix::fs::symlink(r.join("lidar.ply"), r.join("link.ply")).unwrap();
        let (lidar, model, images) = (r.join("lidar.ply"), r.join("model"), r.join("images"));
        let files = [lidar.as_path()];
        let folders = [model.as_path(), images.as_path()];
        let says = |output: PathBuf, is_dir: bool| {
            output_replaces_input(&output, is_dir, &files, &folders)
        };
        // A file output: the map itself, through `..` or a link; a model
        // file; a file inside the image folder; one not there yet inside it.
        for out in [
            r.join("lidar.ply"),
            r.join("images/../lidar.ply"),
            r.join("link.ply"),
            r.join("model/cameras.txt"),
            r.join("model/new.png"),
            r.join("images/a.jpg"),
        ] {
            assert!(says(out.clone(), false).is_some(), "{}", out.display());
        }
        let msg = says(r.join("link.ply"), false).unwrap();
        assert!(
            msg.contains("is the input") && msg.contains("lidar.ply"),
            "{msg}"
        );
        // A folder output: an input folder, one holding the map, one
        // holding an input folder.
        assert!(says(r.join("model"), true)
            .unwrap()
            .contains("is the input folder"));
        assert!(says(r.join("model/sub"), true)
            .unwrap()
            .contains("is inside the input folder"));
        assert!(says(r.to_path_buf(), true)
            .unwrap()
            .contains("holds the input"));
        // Elsewhere, existing or not: fine.
        assert_eq!(says(r.join("depth.png"), false), None);
        assert_eq!(says(r.join("sparse/0"), true), None);
        assert_eq!(says(r.join("nowhere/at/all.png"), false), None);
    }

    #[test]
    fn outputs_that_name_nothing_or_sit_under_a_file_say_so() {
        let root = tempfile::tempdir().unwrap();
        let file = root.path().join("afile");
        fs::write(&file, "x").unwrap();
        let err = write_dir_atomically::<io::Error>(&file.join("out"), |_| Ok(())).unwrap_err();
        assert!(
            err.to_string().contains("afile is a file, not a folder"),
            "{err}"
        );
        let err =
            write_file_atomically::<io::Error>(&file.join("sub/out.png"), |_| Ok(())).unwrap_err();
        assert!(
            err.to_string().contains("afile is a file, not a folder"),
            "{err}"
        );
        assert!(names_nothing(Path::new(".")) && names_nothing(Path::new("a/./")));
        assert!(names_nothing(Path::new("/")) && names_nothing(Path::new("")));
        assert!(!names_nothing(Path::new("./out")) && !names_nothing(Path::new("a/.b/")));
        for name in [".", "deep/a/.."] {
            let err =
                write_dir_atomically::<io::Error>(&root.path().join(name), |_| Ok(())).unwrap_err();
            assert!(
                err.to_string().contains("names no file or folder"),
                "{name}: {err}"
            );
        }
        // A folder output where a file is: refused, the file kept, nothing
        // left behind.
        let err = write_dir_atomically::<io::Error>(&file, |tmp| fs::write(tmp.join("a"), "a"))
            .unwrap_err();
        assert!(err.to_string().contains("is not a folder"), "{err}");
        assert_eq!(fs::read_to_string(&file).unwrap(), "x");
        let left: Vec<_> = fs::read_dir(root.path())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(left, vec![std::ffi::OsString::from("afile")]);
    }

    #[test]
    fn outputs_that_cannot_be_written_are_found_before_any_work() {
        let root = tempfile::tempdir().unwrap();
        let r = root.path();
        let file = r.join("afile");
        fs::write(&file, "x").unwrap();
        fs::create_dir(r.join("adir")).unwrap();
        let says = |path: PathBuf, is_dir: bool| {
            check_output_location(&path, is_dir)
                .map_err(|e| e.to_string())
                .err()
        };
        // Writable places, existing or not, and their folders not made.
        assert_eq!(says(r.join("out"), true), None);
        assert_eq!(says(r.join("deep/er/out"), true), None);
        assert_eq!(says(r.join("adir"), true), None);
        assert_eq!(says(r.join("afile"), false), None);
        assert_eq!(says(r.join("adir/x.png"), false), None);
        assert!(!r.join("deep").exists());
        // Each problem named.
        let wrong = [
            (file.join("out"), true, "afile is a file, not a folder"),
            (file.join("a/b.png"), false, "afile is a file, not a folder"),
            (file.clone(), true, "exists and is not a folder"),
            (r.join("adir"), false, "is a folder: give a file name"),
            (r.join("adir/.."), true, "names no file or folder"),
            // No new entries in /proc, even for root.
            (
                PathBuf::from("/proc/colmap-lidar/out"),
                true,
                "takes no new entries",
            ),
        ];
        for (path, is_dir, what) in wrong {
            let msg = says(path.clone(), is_dir).unwrap_or_default();
            assert!(msg.contains(what), "{}: {msg}", path.display());
        }
        // Nothing left behind by the probes.
        let mut left: Vec<_> = fs::read_dir(r)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        left.sort();
        assert_eq!(left, ["adir", "afile"]);
        // A folder without write permission (only without root's override):
        // refused as a place for outputs, and as a folder to fill, but a
        // writable folder inside it may be filled.
        let locked = r.join("locked");
        fs::create_dir_all(locked.join("open")).unwrap();
        fs::set_permissions(&locked, fs::Permissions::from_mode(0o555)).unwrap();
        let root_writes = tempfile::tempdir_in(&locked).is_ok();
        let msg = says(locked.join("out"), true);
        assert_eq!(msg.is_some(), !root_writes, "{msg:?}");
        assert_eq!(check_output_folder_to_fill(&locked).is_err(), !root_writes);
        assert!(check_output_folder_to_fill(&locked.join("open")).is_ok());
        assert!(check_output_folder_to_fill(&r.join("new/figures")).is_ok());
        assert!(check_output_folder_to_fill(&file).is_err());
        fs::set_permissions(&locked, fs::Permissions::from_mode(0o755)).unwrap();
    }

    #[test]
    fn an_output_written_by_another_run_meanwhile_is_found() {
        let root = tempfile::tempdir().unwrap();
        let out = root.path().join("model");
        // Made meanwhile.
        let before = OutputSnapshot::take(&out);
        assert!(before.check_unchanged(&out).is_ok());
        write_dir_atomically::<io::Error>(&out, |tmp| fs::write(tmp.join("a"), "a")).unwrap();
        let err = before.check_unchanged(&out).unwrap_err().to_string();
        assert!(err.contains("was made while this run worked"), "{err}");
        // Replaced meanwhile (a new folder renamed into place), or a file
        // added to it.
        let before = OutputSnapshot::take(&out);
        write_dir_atomically::<io::Error>(&out, |tmp| fs::write(tmp.join("b"), "b")).unwrap();
        assert!(before.check_unchanged(&out).is_err());
        let before = OutputSnapshot::take(&out);
        std::thread::sleep(std::time::Duration::from_millis(20));
        fs::write(out.join("c"), "c").unwrap();
        let err = before.check_unchanged(&out).unwrap_err().to_string();
        assert!(err.contains("was changed while this run worked"), "{err}");
        // Left alone: unchanged.
        let before = OutputSnapshot::take(&out);
        assert!(before.check_unchanged(&out).is_ok());
    }

    #[test]
    fn failed_fill_leaves_nothing() {
        let root = tempfile::tempdir().unwrap();
        let out = root.path().join("model");
        let r: Result<(), io::Error> = write_dir_atomically(&out, |tmp| {
            fs::write(tmp.join("a.txt"), "x")?;
            Err(io::Error::other("boom"))
        });
        assert!(r.is_err());
        assert!(!out.exists());
        assert_eq!(
            fs::read_dir(root.path()).unwrap().count(),
            0,
            "temporary folder left behind"
        );
    }

    #[test]
    fn replaces_existing_dir_and_file() {
        let root = tempfile::tempdir().unwrap();
        let out = root.path().join("model");
        fs::create_dir(&out).unwrap();
        fs::write(out.join("old.txt"), "old").unwrap();
        write_dir_atomically::<io::Error>(&out, |tmp| fs::write(tmp.join("new.txt"), "new"))
            .unwrap();
        assert!(!out.join("old.txt").exists());
        assert_eq!(
            fs::metadata(&out).unwrap().permissions().mode() & 0o777,
            0o755
        );
        assert_eq!(fs::read_to_string(out.join("new.txt")).unwrap(), "new");

        let file = root.path().join("f.txt");
        write_file_atomically::<io::Error>(&file, |w| w.write_all(b"one")).unwrap();
        write_file_atomically::<io::Error>(&file, |w| w.write_all(b"two")).unwrap();
        assert_eq!(fs::read_to_string(&file).unwrap(), "two");
        assert_eq!(
            fs::metadata(&file).unwrap().permissions().mode() & 0o777,
            0o644
        );
        assert_eq!(fs::read_dir(root.path()).unwrap().count(), 2);
    }
}
