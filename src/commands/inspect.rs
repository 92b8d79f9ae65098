//! `colmap-lidar inspect`: a readable summary of a COLMAP database.
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::PathBuf;

use anyhow::Result;

use crate::io::database::{read_database, DatabaseSnapshot};
use crate::scene::correspondence_graph::CorrespondenceGraph;
use crate::scene::ImageId;

#[derive(clap::Args, Debug)]
pub struct InspectArgs {
    /// COLMAP database (opened read-only).
    #[arg(long, visible_alias = "database_path", value_name = "DB")]
    pub database: PathBuf,
    /// Also list every image with its keypoint and correspondence counts.
    #[arg(long)]
    pub images: bool,
}

pub fn run(args: &InspectArgs) -> Result<()> {
    let db = read_database(&args.database)?;
    print!("{}", summary(&db, args.images));
    Ok(())
}

/// Minimum, median and maximum of a list (0s when empty).
fn min_median_max(mut v: Vec<usize>) -> (usize, usize, usize) {
    if v.is_empty() {
        return (0, 0, 0);
    }
    v.sort_unstable();
    (v[0], v[v.len() / 2], v[v.len() - 1])
}

fn config_name(config: i64) -> &'static str {
    match config {
        0 => "undefined",
        1 => "degenerate",
        2 => "calibrated",
        3 => "uncalibrated",
        4 => "planar",
        5 => "panoramic",
        6 => "planar or panoramic",
        7 => "watermark",
        8 => "multiple",
        _ => "unknown",
    }
}

/// The text `inspect` prints.
pub fn summary(db: &DatabaseSnapshot, per_image: bool) -> String {
    let mut out = String::new();
    let w = &mut out;
    // Writing to a String cannot fail.
    let _ = writeln!(w, "Database  {}", db.path.display());
    let _ = writeln!(
        w,
        "Schema    user_version {} ({} tables)",
        db.schema.user_version,
        db.schema.tables.len()
    );
    let _ = writeln!(w, "\nCameras   {}", db.cameras.len());
    for cam in db.cameras.values() {
        let params: Vec<String> = cam
            .model
            .param_names()
            .iter()
            .zip(&cam.params)
            .map(|(n, v)| format!("{n}={v:.6}"))
            .collect();
        let _ = writeln!(
            w,
            "  camera {:>4}  {:<22} {}x{}  {}  {}",
            cam.id,
            cam.model.name(),
            cam.width,
            cam.height,
            params.join(" "),
            if db.cameras_without_focal_prior.contains(&cam.id) {
                "(focal length guessed: `map` self-calibrates it)"
            } else {
                "(focal length given)"
            }
        );
    }
    let counts: Vec<usize> = db.images.keys().map(|&id| db.num_keypoints(id)).collect();
    let total_kp: usize = counts.iter().sum();
    let (kmin, kmed, kmax) = min_median_max(counts);
    let _ = writeln!(w, "\nImages    {}", db.images.len());
    let _ = writeln!(
        w,
        "Keypoints {total_kp} in all; per image min {kmin}, median {kmed}, max {kmax}"
    );
    let without: usize = db
        .images
        .keys()
        .filter(|&&id| db.num_keypoints(id) == 0)
        .count();
    if without > 0 {
        let _ = writeln!(w, "          {without} images have no keypoints");
    }

    let verified: Vec<_> = db
        .two_view_geometries
        .iter()
        .filter(|g| !g.inlier_matches.is_empty())
        .collect();
    let per_pair: Vec<usize> = verified.iter().map(|g| g.inlier_matches.len()).collect();
    let total_matches: usize = per_pair.iter().sum();
    let (mmin, mmed, mmax) = min_median_max(per_pair);
    let _ = writeln!(w, "\nVerified pairs  {} (inlier matches {total_matches} in all; per pair min {mmin}, median {mmed}, max {mmax})", verified.len());
    let mut configs: BTreeMap<i64, usize> = BTreeMap::new();
    for g in &verified {
        *configs.entry(g.config).or_insert(0) += 1;
    }
    for (config, n) in &configs {
        let _ = writeln!(w, "  config {config} ({}): {n}", config_name(*config));
    }

    let graph = db.correspondence_graph();
    let stats = graph.track_stats();
    let observed: usize = graph.image_ids().map(|id| graph.num_observations(id)).sum();
    let _ = writeln!(w, "\nCorrespondence graph");
    let _ = writeln!(w, "  keypoints with a correspondence  {observed}");
    let _ = writeln!(w, "  tracks                           {}", stats.num_tracks);
    if stats.num_inconsistent > 0 {
        let _ = writeln!(
            w,
            "  tracks with 2+ keypoints in one image (ambiguous)  {}",
            stats.num_inconsistent
        );
    }
    let _ = writeln!(w, "  track length (images)  tracks");
    let max_count = stats.histogram.values().copied().max().unwrap_or(1).max(1);
    for (len, n) in &stats.histogram {
        let bar = "#".repeat((40 * n).div_ceil(max_count));
        let _ = writeln!(w, "  {len:>21}  {n:>6}  {bar}");
    }
    let isolated = db
        .images
        .keys()
        .filter(|&&id| graph.num_observations(id) == 0)
        .count();
    if isolated > 0 {
        let _ = writeln!(w, "  {isolated} images have no verified match at all");
    }
    let _ = writeln!(w, "\nImage groups  {}", image_groups_line(&graph, db));

    if per_image {
        let _ = writeln!(w, "\n  image_id  keypoints  matched  name");
        for img in db.images.values() {
            let _ = writeln!(
                w,
                "  {:>8}  {:>9}  {:>7}  {}",
                img.id,
                db.num_keypoints(img.id),
                graph.num_observations(img.id),
                img.name
            );
        }
    }
    let gps: Vec<[f64; 3]> = db
        .pose_priors
        .values()
        .filter(|p| p.is_gps())
        .filter_map(|p| p.position)
        .collect();
    if gps.len() < db.pose_priors.len() {
        let _ = writeln!(
            w,
            "\nPose priors  {} images",
            db.pose_priors.len() - gps.len()
        );
    }
    if !gps.is_empty() {
        let range = |k: usize| {
            gps.iter()
                .map(|p| p[k])
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
                    (lo.min(v), hi.max(v))
                })
        };
        let ((lat0, lat1), (lon0, lon1)) = (range(0), range(1));
        let _ = writeln!(
            w,
            "\nGPS          {} images, latitude {lat0:.6} to {lat1:.6}, longitude {lon0:.6} to {lon1:.6}\n             \
             (map places the model from them without an initial pose, given the map's CRS: --map-crs)",
            gps.len()
        );
    }
    if !db.schema.notes.is_empty() {
        let _ = writeln!(w, "\nNotes");
        for note in &db.schema.notes {
            let _ = writeln!(w, "  {note}");
        }
    }
    out
}

/// The image graph's groups (images linked by verified pairs, see
/// [`CorrespondenceGraph::image_groups`]): a `map` run registers the groups
/// of its initial images, so more than one is worth saying how to map them.
fn image_groups_line(graph: &CorrespondenceGraph, db: &DatabaseSnapshot) -> String {
    let sizes = CorrespondenceGraph::group_sizes(&graph.image_groups(db.images.keys().copied()));
    let linked: Vec<(ImageId, usize)> = sizes
        .iter()
        .filter(|(_, &n)| n > 1)
        .map(|(&g, &n)| (g, n))
        .collect();
    let alone = sizes.values().filter(|&&n| n == 1).count();
    let mut line = match linked.len() {
        0 => "none: no two images share verified matches".to_string(),
        1 => format!("1 ({} images linked by verified pairs)", linked[0].1),
        k => {
            let list: Vec<String> = linked
                .iter()
                .map(|(g, n)| {
                    let name = db.images.get(g).map_or("?", |img| img.name.as_str());
                    format!("{n} images from id {} ({name})", g.0)
                })
                .collect();
            format!(
                "{k} ({}): no verified pair links one to another: a `map` run registers the groups of its initial images (give one --init-image with its --init-pose per group) or of its input model",
                list.join(", ")
            )
        }
    };
    if alone > 0 {
        let images = if alone == 1 { "image" } else { "images" };
        line.push_str(&format!("; {alone} {images} in none (no verified pair)"));
    }
    line
}
