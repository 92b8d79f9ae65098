//! The `colmap-lidar` binary: parse, run one command, print the error chain once.
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use colmap_lidar::commands;

/// mimalloc instead of glibc's allocator, for Rust and (its `override`
/// feature replaces `malloc` and `free` in the binary) for Ceres too: every
/// solve builds and frees a problem of many small blocks, and glibc spent
/// about a tenth of a mapping run's CPU time in `malloc`, `free` and their
/// arena locks. With it the runs are about 10 % faster, and byte-identical
/// (`docs/results.md`, session 48).
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// `mi_option_purge_delay`: its place in mimalloc's `mi_option_e` (the same
/// in mimalloc 2 and 3; `tests::freed_memory_is_kept` checks the version).
const MI_OPTION_PURGE_DELAY: libmimalloc_sys::mi_option_t = 15;

/// Tells mimalloc to keep the memory a run frees instead of handing it back
/// to the system (after about a second; unless `MIMALLOC_PURGE_DELAY` says
/// otherwise). Every solve frees its problem and the next one allocates it
/// again: on a machine with transparent huge pages each such page came back
/// as a fault that zeroes 2 MB (100-160 k faults and about 2.5 s of system
/// time on the 100-image corridor). Kept: about 1.4 k faults, peak memory
/// 4-7 % higher, the same model; the wall-time gain was within the test
/// machine's noise (`docs/results.md`, session 51).
fn keep_freed_memory() {
    if std::env::var_os("MIMALLOC_PURGE_DELAY").is_none() {
        // SAFETY: sets one of mimalloc's options; any value is valid for it.
        unsafe { libmimalloc_sys::mi_option_set(MI_OPTION_PURGE_DELAY, -1) }
    }
}

/// Puts photos into a LiDAR map: incremental structure-from-motion over a COLMAP
/// database, tied to the map's planes, output in the map's frame and metric scale.
#[derive(Parser, Debug)]
#[command(name = "colmap-lidar", version, about, long_about = None)]
struct Cli {
    /// More log output (-v: debug, -vv: trace). RUST_LOG overrides.
    #[arg(short, long, action = clap::ArgAction::Count, global = true)]
    verbose: u8,
    /// Only warnings and errors.
    #[arg(short, long, global = true, conflicts_with = "verbose")]
    quiet: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Summarise a COLMAP database: cameras, images, keypoints, verified pairs, tracks.
    Inspect(commands::inspect::InspectArgs),
    /// Structure-from-motion inside the LiDAR map: COLMAP database + map -> model in the map frame.
    Map(commands::map::MapArgs),
    /// Put models of the same LiDAR map (e.g. groups of photos mapped each from its own pose) into one model.
    Merge(commands::merge::MergeArgs),
    /// Prepare a raw point cloud (PLY, PCD, LAS/LAZ, E57) as a map: downsample, estimate normals.
    PrepareMap(commands::prepare_map::PrepareMapArgs),
    /// Render a synthetic scene with exact ground truth (images, LiDAR map, true cameras).
    Synth(commands::synth::SynthArgs),
    /// Compare a model's camera poses with a reference model (ground truth).
    Evaluate(commands::evaluate::EvaluateArgs),
    /// Render what the map looks like from a registered image: a colour-mapped depth PNG.
    Depth(commands::depth::DepthArgs),
    /// The map's depth at every pixel of every registered image of a model (16-bit PNG or .npy), for depth-supervised NeRF or Gaussian splatting.
    DepthMaps(commands::depth_maps::DepthMapsArgs),
    /// Colour the LiDAR map with the photos of a model (occlusion-aware): a PLY with red, green, blue.
    #[command(visible_alias = "colorize-map")]
    ColourMap(commands::colour_map::ColourMapArgs),
    /// Figures of a `map` run (SVG): plane terms, point-to-plane distances and
    /// reprojection errors per solve, and per image.
    Plot(commands::plot::PlotArgs),
    /// Benchmark helpers for the map (generate / load a large building-like cloud).
    #[command(hide = true)]
    BenchMap(commands::bench_map::BenchMapArgs),
}

fn main() -> ExitCode {
    keep_freed_memory();
    let cli = Cli::parse();
    let level = match (cli.quiet, cli.verbose) {
        (true, _) => "warn",
        (false, 0) => "info",
        (false, 1) => "debug",
        _ => "trace",
    };
    env_logger::Builder::from_env(env_logger::Env::default().default_filter_or(level))
        .format_timestamp_millis()
        .init();
    let result = match &cli.command {
        Command::Inspect(args) => commands::inspect::run(args),
        Command::Map(args) => commands::map::run(args),
        Command::Merge(args) => commands::merge::run(args),
        Command::PrepareMap(args) => commands::prepare_map::run(args),
        Command::Depth(args) => commands::depth::run(args),
        Command::DepthMaps(args) => commands::depth_maps::run(args),
        Command::ColourMap(args) => commands::colour_map::run(args),
        Command::Plot(args) => commands::plot::run(args),
        Command::Synth(args) => commands::synth::run(args),
        Command::Evaluate(args) => commands::evaluate::run(args),
        Command::BenchMap(args) => commands::bench_map::run(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("error: {}", error_chain(&err));
            ExitCode::FAILURE
        }
    }
}

/// The error and its causes on one line, skipping a cause whose text the
/// message before it already contains (typed errors often quote their source).
fn error_chain(err: &anyhow::Error) -> String {
    let mut text = err.to_string();
    let mut last = text.clone();
    for cause in err.chain().skip(1) {
        let cause = cause.to_string();
        if !last.contains(&cause) {
            text.push_str(": ");
            text.push_str(&cause);
        }
        last = cause;
    }
    text
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn freed_memory_is_kept() {
        // SAFETY: reads mimalloc's version and options.
        let version = unsafe { libmimalloc_sys::mi_version() };
        // major * 10000 + minor * 100 + patch
        assert!(
            (20_000..40_000).contains(&version),
            "mimalloc {version}: check MI_OPTION_PURGE_DELAY against its mi_option_e"
        );
        let before = unsafe { libmimalloc_sys::mi_option_get(MI_OPTION_PURGE_DELAY) };
        keep_freed_memory();
        let after = unsafe { libmimalloc_sys::mi_option_get(MI_OPTION_PURGE_DELAY) };
        match std::env::var("MIMALLOC_PURGE_DELAY") {
            // mimalloc's default purges (after 1 s in mimalloc 3.3).
            Err(_) => assert!(before >= 0 && after == -1, "{before} -> {after}"),
            Ok(_) => assert_eq!(after, before),
        }
    }
}
