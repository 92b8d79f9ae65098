//! One module per command of the `colmap-lidar` binary.
pub mod bench_map;
pub mod colour_map;
pub mod depth;
pub mod depth_maps;
pub mod evaluate;
pub mod inspect;
pub mod map;
pub mod merge;
pub mod plot;
pub mod prepare_map;
pub mod synth;

use std::io::IsTerminal;
use std::path::Path;

use crate::scene::{Camera, Image, Reconstruction};

/// Three comma-separated numbers `X,Y,Z` (`synth --offset`, `map
/// --map-origin`).
pub(crate) fn parse_xyz(s: &str) -> Result<[f64; 3], String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|p| p.trim().parse::<f64>().map_err(|e| format!("{p:?}: {e}")))
        .collect::<Result<_, _>>()?;
    v.try_into()
        .map_err(|_| format!("expected X,Y,Z, got {s:?}"))
}

/// A progress bar over `len` images, `what` after the count (e.g. "images
/// registered"); `None` when stderr is not a terminal (logs and pipes get
/// no bar).
pub(crate) fn image_progress_bar(len: usize, what: &str) -> Option<indicatif::ProgressBar> {
    std::io::stderr().is_terminal().then(|| {
        let bar = indicatif::ProgressBar::new(len as u64);
        bar.set_style(
            indicatif::ProgressStyle::with_template(&format!(
                "{{elapsed_precise}} [{{bar:40}}] {{pos}}/{{len}} {what}"
            ))
            .expect("the template is valid"),
        );
        bar
    })
}

/// The registered images of `model` (read from `path`) with their cameras,
/// in id order; an error for an image whose camera is missing.
pub(crate) fn registered_with_cameras<'a>(
    model: &'a Reconstruction,
    path: &Path,
) -> anyhow::Result<Vec<(&'a Image, &'a Camera)>> {
    use anyhow::Context;
    model
        .registered_images()
        .map(|image| {
            let camera = model.cameras.get(&image.camera_id).with_context(|| {
                format!(
                    "image `{}` refers to camera {}, missing from {}",
                    image.name,
                    image.camera_id,
                    path.display()
                )
            })?;
            Ok((image, camera))
        })
        .collect()
}

/// Refuses an output file whose name does not end in `.{extension}` (any
/// case): the command writes `what` (e.g. "a binary PLY"), and a name that
/// promises another format (`map.pcd`, `depth.jpg`) would mislead every
/// reader of it. Checked after where it goes and whether it would replace
/// an input, whose errors say more.
pub(crate) fn check_output_extension(
    path: &Path,
    extension: &str,
    what: &str,
) -> anyhow::Result<()> {
    let matches = path
        .extension()
        .is_some_and(|e| e.to_string_lossy().eq_ignore_ascii_case(extension));
    if !matches {
        anyhow::bail!(
            "the output {} would hold {what}: give it a name ending in .{extension}",
            path.display()
        );
    }
    Ok(())
}

/// Refuses an output folder, replaced as a whole, that cannot be written
/// there ([`crate::io::atomic::check_output_location`]: also a file in its
/// place) or that holds an entry not in `replaceable` (what the command
/// itself writes there; `what` names it in the error, e.g. "a model file").
pub(crate) fn check_replaceable_output(
    dir: &Path,
    replaceable: &[&str],
    what: &str,
) -> anyhow::Result<()> {
    use anyhow::{bail, Context};
    crate::io::atomic::check_output_location(dir, true)?;
    if !dir.exists() {
        return Ok(());
    }
    let listing = || format!("reading {}", dir.display());
    for entry in std::fs::read_dir(dir).with_context(listing)? {
        let name = entry.with_context(listing)?.file_name();
        let name = name.to_string_lossy();
        if !replaceable.contains(&name.as_ref()) {
            bail!(
                "the output folder {} holds `{name}`, which is not {what}: refusing to replace it",
                dir.display()
            );
        }
    }
    Ok(())
}
