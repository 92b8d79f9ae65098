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
    let parent = parent_of(dir);
    fs::create_dir_all(&parent)?;
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
            .tempdir_in(&parent)?
            .keep();
        fs::remove_dir(&old)?;
        fs::rename(dir, &old)?;
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
    let parent = parent_of(path);
    fs::create_dir_all(&parent)?;
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
