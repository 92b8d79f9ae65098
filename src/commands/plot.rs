//! `colmap-lidar plot`: the paper's three figures from a `map` run's
//! `report.json`, as SVG files, plus one per image:
//!
//! * `planes.svg`: plane terms per solve by kind (projection, nearest,
//!   ground, all) against the number of registered images;
//! * `plane_distance.svg`: mean point-to-plane distance of the associated
//!   points before and after each solve (log scale, millimetres);
//! * `reprojection.svg`: mean reprojection error before and after each solve,
//!   with the spread (mean +- one standard deviation) after it;
//! * `images.svg`: per image in registration order, the plane terms its points
//!   carry by kind and their mean distance to the planes.
//!
//! Local solves (first, robust pass) are drawn as lines, as in the paper; the
//! sphere and final solves as markers at their own image counts. Solves that
//! the mapper discarded or that had no points are left out.
use std::fs;
use std::ops::Range;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use plotters::coord::ranged1d::{AsRangedCoord, ValueFormatter};
use plotters::coord::types::RangedCoordf64;
use plotters::coord::Shift;
use plotters::prelude::*;
use serde::Deserialize;

use crate::io::atomic::write_file_atomically;
use crate::sfm::associate::SolveKind;

#[derive(clap::Args, Debug, Clone)]
pub struct PlotArgs {
    /// A `map` run's report.json, or the model folder holding it.
    pub report: PathBuf,
    /// Output folder for the SVG files (created if missing; only the four
    /// figures' files in it are replaced, each atomically).
    #[arg(long)]
    pub output: PathBuf,
    /// Draw the run at this index of report.json's `runs` (0: the first run
    /// made) instead of the kept one: a run set aside (stopped at its look,
    /// failed, or mapped again from where it ended) kept only its solves, so
    /// its per-image figure is empty.
    #[arg(long, value_name = "INDEX")]
    pub run: Option<usize>,
}

/// The parts of `report.json` the figures use. Every field is optional (older
/// reports lack some) and a number may be `null` (JSON has no NaN: an
/// undetermined sigma is written so); such values are left out.
#[derive(Debug, Default, Deserialize)]
#[serde(default)]
pub struct ReportForPlots {
    pub solves: Vec<SolveForPlots>,
    pub images: Vec<ImageForPlots>,
    pub runs: Vec<RunForPlots>,
}

/// One run of `report.json` -> `runs`: the kept run's solves are the
/// report's own, a run set aside has its own.
#[derive(Debug, Default, Deserialize)]
#[serde(default)]
pub struct RunForPlots {
    pub index: usize,
    pub kept: bool,
    pub outcome: String,
    pub solves: Vec<SolveForPlots>,
}

impl ReportForPlots {
    /// What there is to draw of run `index` (`report.json` -> `runs`): the
    /// report itself for the kept run, the solves alone for a run set aside;
    /// an error naming the runs there are when there is no such run.
    pub fn of_run(self, index: usize) -> anyhow::Result<ReportForPlots> {
        let Some(pos) = self.runs.iter().position(|r| r.index == index) else {
            let runs: Vec<String> = self
                .runs
                .iter()
                .map(|r| {
                    // The outcome's first words: "failed: why..." -> "failed".
                    let outcome = r.outcome.split(':').next().unwrap_or_default();
                    let kept = if r.kept { ", kept" } else { "" };
                    format!("{} ({outcome}{kept})", r.index)
                })
                .collect();
            bail!(
                "the report has no run {index}; its runs: {}",
                if runs.is_empty() {
                    "none recorded (a report from an older colmap-lidar)".to_string()
                } else {
                    runs.join("; ")
                }
            );
        };
        let mut runs = self.runs;
        let run = runs.swap_remove(pos);
        Ok(if run.kept {
            ReportForPlots {
                runs: Vec::new(),
                ..self
            }
        } else {
            ReportForPlots {
                solves: run.solves,
                images: Vec::new(),
                runs: Vec::new(),
            }
        })
    }
}

/// One solve of `report.json` -> `solves`.
#[derive(Debug, Deserialize)]
pub struct SolveForPlots {
    pub kind: SolveKind,
    #[serde(default)]
    pub num_registered: usize,
    #[serde(default)]
    pub num_points: usize,
    #[serde(default)]
    pub num_planes: usize,
    #[serde(default)]
    pub num_projection_planes: usize,
    #[serde(default)]
    pub num_nearest_planes: usize,
    #[serde(default)]
    pub num_ground_planes: usize,
    #[serde(default)]
    pub plane_distance_before_m: MeanStd,
    #[serde(default)]
    pub plane_distance_after_m: MeanStd,
    #[serde(default)]
    pub reprojection_before_px: MeanStd,
    #[serde(default)]
    pub reprojection_after_px: MeanStd,
    #[serde(default)]
    pub discarded: bool,
}

/// A mean (and spread) as report.json has them.
#[derive(Debug, Default, Deserialize)]
#[serde(default)]
pub struct MeanStd {
    pub mean: Option<f64>,
    pub std: Option<f64>,
    pub count: Option<usize>,
}

impl MeanStd {
    /// The mean when it is a finite number (and, with a count, over at least one value).
    fn mean(&self) -> Option<f64> {
        self.mean.filter(|m| m.is_finite() && self.count != Some(0))
    }
}

/// One image of `report.json` -> `images`.
#[derive(Debug, Default, Deserialize)]
#[serde(default)]
pub struct ImageForPlots {
    pub registered: bool,
    pub registration_index: Option<usize>,
    pub num_projection_planes: usize,
    pub num_nearest_planes: usize,
    pub num_ground_planes: usize,
    pub mean_plane_distance_m: Option<f64>,
}

/// A series of (x, y) points.
pub type Series = Vec<(f64, f64)>;

/// What one kind of solve contributes to the figures, one entry per solve, x
/// = registered images when it ran.
#[derive(Debug, Default, PartialEq)]
pub struct SolveSeries {
    pub projection: Series,
    pub nearest: Series,
    pub ground: Series,
    pub planes: Series,
    /// Mean point-to-plane distance, millimetres, solves with planes only.
    pub distance_before_mm: Series,
    pub distance_after_mm: Series,
    /// Reprojection error, pixels: mean before, mean after, and after's spread.
    pub reprojection_before_px: Series,
    pub reprojection_after_px: Series,
    pub reprojection_after_std_px: Series,
}

impl SolveSeries {
    fn push(&mut self, s: &SolveForPlots) {
        let x = s.num_registered as f64;
        self.projection.push((x, s.num_projection_planes as f64));
        self.nearest.push((x, s.num_nearest_planes as f64));
        self.ground.push((x, s.num_ground_planes as f64));
        self.planes.push((x, s.num_planes as f64));
        if s.num_planes > 0 {
            let mm = |d: &MeanStd| d.mean().map(|m| (x, 1e3 * m));
            self.distance_before_mm
                .extend(mm(&s.plane_distance_before_m));
            self.distance_after_mm.extend(mm(&s.plane_distance_after_m));
        }
        let px = |e: &MeanStd| e.mean().map(|m| (x, m));
        self.reprojection_before_px
            .extend(px(&s.reprojection_before_px));
        let after = &s.reprojection_after_px;
        if let (Some(m), Some(sd)) = (after.mean(), after.std.filter(|v| v.is_finite())) {
            self.reprojection_after_px.push((x, m));
            self.reprojection_after_std_px.push((x, sd));
        }
    }
}

/// Per registered image, x = registration index.
#[derive(Debug, Default, PartialEq)]
pub struct ImageSeries {
    pub projection: Series,
    pub nearest: Series,
    pub ground: Series,
    /// Mean distance of its points to their planes, millimetres.
    pub distance_mm: Series,
}

/// Everything the figures draw.
#[derive(Debug, Default, PartialEq)]
pub struct PlotData {
    /// First (robust) pass of each local solve.
    pub local: SolveSeries,
    /// Sphere (global) solves.
    pub global: SolveSeries,
    /// Final rounds.
    pub final_rounds: SolveSeries,
    pub images: ImageSeries,
}

impl PlotData {
    /// The series of `report`, in its order. Errors if it holds no solve to draw.
    pub fn from_report(report: &ReportForPlots) -> anyhow::Result<Self> {
        let mut data = PlotData::default();
        for s in &report.solves {
            if s.discarded || s.num_points == 0 {
                continue;
            }
            match s.kind {
                SolveKind::Local => data.local.push(s),
                SolveKind::LocalRefine => {}
                SolveKind::Global => data.global.push(s),
                SolveKind::FinalFirst | SolveKind::FinalMoving | SolveKind::Final => {
                    data.final_rounds.push(s)
                }
            }
        }
        if data.local.planes.is_empty()
            && data.global.planes.is_empty()
            && data.final_rounds.planes.is_empty()
        {
            bail!("the report holds no solve to plot");
        }
        let mut registered: Vec<&ImageForPlots> = report
            .images
            .iter()
            .filter(|r| r.registered && r.registration_index.is_some())
            .collect();
        registered.sort_by_key(|r| r.registration_index);
        for r in registered {
            let x = r.registration_index.unwrap_or_default() as f64;
            data.images
                .projection
                .push((x, r.num_projection_planes as f64));
            data.images.nearest.push((x, r.num_nearest_planes as f64));
            data.images.ground.push((x, r.num_ground_planes as f64));
            if let Some(d) = r.mean_plane_distance_m.filter(|d| d.is_finite()) {
                data.images.distance_mm.push((x, 1e3 * d));
            }
        }
        Ok(data)
    }
}

/// Reads `path` (a report.json, or a folder holding one).
pub fn read_report(path: &Path) -> anyhow::Result<(PathBuf, ReportForPlots)> {
    let file = if path.is_dir() {
        path.join("report.json")
    } else {
        path.to_path_buf()
    };
    let bytes =
        fs::read(&file).with_context(|| format!("reading the report {}", file.display()))?;
    let Ok(text) = String::from_utf8(bytes) else {
        anyhow::bail!(
            "{} is not a colmap-lidar map report.json (not text)",
            file.display()
        );
    };
    let report: ReportForPlots = serde_json::from_str(&text)
        .with_context(|| format!("{} is not a colmap-lidar map report.json", file.display()))?;
    Ok((file, report))
}

pub fn run(args: &PlotArgs) -> anyhow::Result<()> {
    crate::io::atomic::check_output_folder_to_fill(&args.output)?;
    let (file, report) = read_report(&args.report)?;
    let report = match args.run {
        Some(index) => report
            .of_run(index)
            .with_context(|| format!("{}", file.display()))?,
        None => report,
    };
    let data = PlotData::from_report(&report).with_context(|| format!("{}", file.display()))?;
    // Everything is drawn before anything is written.
    let figures = render(&data)?;
    fs::create_dir_all(&args.output)
        .with_context(|| format!("creating the folder {}", args.output.display()))?;
    for (name, svg) in &figures {
        let path = args.output.join(name);
        write_file_atomically(&path, |w| std::io::Write::write_all(w, svg.as_bytes()))
            .with_context(|| format!("writing {}", path.display()))?;
    }
    log::info!(
        "wrote {} figures of {} solves to {}",
        figures.len(),
        report.solves.len(),
        args.output.display()
    );
    Ok(())
}

const SIZE: (u32, u32) = (900, 520);
const PROJECTION: RGBColor = RGBColor(128, 0, 160);
const NEAREST: RGBColor = RGBColor(0, 114, 178);
const GROUND: RGBColor = RGBColor(0, 158, 115);
const TOTAL: RGBColor = RGBColor(230, 159, 0);
const BEFORE: RGBColor = RGBColor(213, 94, 0);
const AFTER: RGBColor = RGBColor(0, 114, 178);

/// The files `plot` writes, in the order of [`render`].
pub const FIGURES: [&str; 4] = [
    "planes.svg",
    "plane_distance.svg",
    "reprojection.svg",
    "images.svg",
];

/// The figures as (file name, SVG text).
pub fn render(data: &PlotData) -> anyhow::Result<Vec<(&'static str, String)>> {
    let svgs = [
        planes_figure(data)?,
        distance_figure(data)?,
        reprojection_figure(data)?,
        images_figure(data)?,
    ];
    Ok(FIGURES.into_iter().zip(svgs).collect())
}

/// Span of the x values of `series`, padded so single points are visible.
fn x_range<'a>(series: impl IntoIterator<Item = &'a Series>) -> Range<f64> {
    let (lo, hi) = bounds(series.into_iter().flatten().map(|p| p.0));
    if lo > hi {
        return 0.0..1.0;
    }
    (lo - 0.5)..(hi + 0.5)
}

/// 0 up to the largest y of `series` (plus headroom for the legend).
fn y_range_from_zero<'a>(series: impl IntoIterator<Item = &'a Series>) -> Range<f64> {
    let (_, hi) = bounds(series.into_iter().flatten().map(|p| p.1));
    // Empty or all-zero series still get a drawable axis.
    0.0..(if hi > 0.0 { hi * 1.5 } else { 1.0 })
}

/// Positive span of the y values of `series` for a log axis (decade-padded).
fn y_log_range<'a>(series: impl IntoIterator<Item = &'a Series>) -> Range<f64> {
    let (lo, hi) = bounds(
        series
            .into_iter()
            .flatten()
            .map(|p| p.1)
            .filter(|&y| y > 0.0 && y.is_finite()),
    );
    if lo > hi {
        return 1e-3..1.0;
    }
    (lo / 2.0)..(hi * 40.0)
}

/// Values beyond this (only in a corrupt report) are left out of the axes'
/// ranges, which stay finite.
const MAX_AXIS_VALUE: f64 = 1e12;

fn bounds(values: impl Iterator<Item = f64>) -> (f64, f64) {
    values
        .filter(|v| v.is_finite() && v.abs() <= MAX_AXIS_VALUE)
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(v), hi.max(v))
        })
}

/// A chart with an f64 x axis and the y axis `Y` (linear or log).
type Chart<'a, 'b, Y> = ChartContext<'a, SVGBackend<'b>, Cartesian2d<RangedCoordf64, Y>>;

/// A chart on a white SVG canvas with labelled axes.
fn chart<'a, 'b, Y>(
    root: &'a DrawingArea<SVGBackend<'b>, Shift>,
    caption: &str,
    x: Range<f64>,
    y: Y,
    x_desc: &str,
    y_desc: &str,
    y_counts: bool,
) -> anyhow::Result<Chart<'a, 'b, Y::CoordDescType>>
where
    Y: AsRangedCoord<Value = f64>,
    Y::CoordDescType: ValueFormatter<f64>,
{
    root.fill(&WHITE).map_err(plot_error)?;
    let mut chart = ChartBuilder::on(root)
        .caption(caption, ("sans-serif", 20))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(x, y)
        .map_err(plot_error)?;
    // Whole numbers only: padded or short axes get fractional ticks.
    let whole = |v: &f64| {
        if (v - v.round()).abs() < 1e-9 {
            format!("{v:.0}")
        } else {
            String::new()
        }
    };
    let mut mesh = chart.configure_mesh();
    // The x axes count images; counts on y are whole numbers too.
    mesh.x_desc(x_desc).y_desc(y_desc).x_label_formatter(&whole);
    if y_counts {
        mesh.y_label_formatter(&whole);
    }
    mesh.draw().map_err(plot_error)?;
    Ok(chart)
}

fn plot_error<E: std::fmt::Display>(e: E) -> anyhow::Error {
    anyhow::anyhow!("drawing a figure: {e}")
}

/// A line with a legend entry.
fn line<'a, 'b: 'a, Y>(
    chart: &mut Chart<'a, 'b, Y>,
    series: &Series,
    colour: RGBColor,
    label: &str,
) -> anyhow::Result<()>
where
    Y: Ranged<ValueType = f64>,
{
    if series.is_empty() {
        return Ok(());
    }
    chart
        .draw_series(LineSeries::new(
            series.iter().copied(),
            colour.stroke_width(2),
        ))
        .map_err(plot_error)?
        .label(label)
        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(2)));
    Ok(())
}

/// Markers (circles for sphere solves, triangles for final rounds) with a legend entry.
fn markers<'a, 'b: 'a, Y>(
    chart: &mut Chart<'a, 'b, Y>,
    series: &Series,
    colour: RGBColor,
    triangle: bool,
    label: &str,
) -> anyhow::Result<()>
where
    Y: Ranged<ValueType = f64>,
{
    if series.is_empty() {
        return Ok(());
    }
    let style = colour.stroke_width(2);
    let annotation = if triangle {
        chart
            .draw_series(series.iter().map(|&p| TriangleMarker::new(p, 6, style)))
            .map_err(plot_error)?
    } else {
        chart
            .draw_series(series.iter().map(|&p| Circle::new(p, 5, style)))
            .map_err(plot_error)?
    };
    annotation.label(label).legend(move |(x, y)| {
        if triangle {
            TriangleMarker::new((x + 10, y), 6, style).into_dyn()
        } else {
            Circle::new((x + 10, y), 5, style).into_dyn()
        }
    });
    Ok(())
}

/// The sphere solves' (circles) and final rounds' (triangles) values of one series.
fn sphere_and_final<'a, 'b: 'a, Y>(
    chart: &mut Chart<'a, 'b, Y>,
    sphere: &Series,
    finals: &Series,
    colour: RGBColor,
    what: &str,
) -> anyhow::Result<()>
where
    Y: Ranged<ValueType = f64>,
{
    markers(chart, sphere, colour, false, &format!("{what} (sphere)"))?;
    markers(chart, finals, colour, true, &format!("{what} (final)"))
}

fn legend<'a, 'b: 'a, Y>(chart: &mut Chart<'a, 'b, Y>) -> anyhow::Result<()>
where
    Y: Ranged<ValueType = f64>,
{
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(plot_error)
}

fn svg(
    draw: impl FnOnce(&DrawingArea<SVGBackend, Shift>) -> anyhow::Result<()>,
) -> anyhow::Result<String> {
    let mut text = String::new();
    {
        let root = SVGBackend::with_string(&mut text, SIZE).into_drawing_area();
        draw(&root)?;
        root.present().map_err(plot_error)?;
    }
    Ok(text)
}

fn planes_figure(data: &PlotData) -> anyhow::Result<String> {
    let all = [
        &data.local.planes,
        &data.global.planes,
        &data.final_rounds.planes,
    ];
    svg(|root| {
        let mut c = chart(
            root,
            "Plane terms per solve",
            x_range(all),
            y_range_from_zero(all),
            "registered images",
            "plane terms",
            true,
        )?;
        line(
            &mut c,
            &data.local.projection,
            PROJECTION,
            "projection (local)",
        )?;
        line(&mut c, &data.local.nearest, NEAREST, "nearest (local)")?;
        line(&mut c, &data.local.ground, GROUND, "ground (local)")?;
        line(&mut c, &data.local.planes, TOTAL, "all (local)")?;
        sphere_and_final(
            &mut c,
            &data.global.planes,
            &data.final_rounds.planes,
            TOTAL,
            "all",
        )?;
        legend(&mut c)
    })
}

fn distance_figure(data: &PlotData) -> anyhow::Result<String> {
    let sets = [&data.local, &data.global, &data.final_rounds];
    let all: Vec<&Series> = sets
        .iter()
        .flat_map(|s| [&s.distance_before_mm, &s.distance_after_mm])
        .collect();
    svg(|root| {
        let mut c = chart(
            root,
            "Mean point-to-plane distance before and after each solve",
            x_range(all.iter().copied()),
            y_log_range(all.iter().copied()).log_scale(),
            "registered images",
            "distance (mm)",
            false,
        )?;
        let positive = |s: &Series| -> Series { s.iter().copied().filter(|p| p.1 > 0.0).collect() };
        line(
            &mut c,
            &positive(&data.local.distance_before_mm),
            BEFORE,
            "before (local)",
        )?;
        line(
            &mut c,
            &positive(&data.local.distance_after_mm),
            AFTER,
            "after (local)",
        )?;
        sphere_and_final(
            &mut c,
            &positive(&data.global.distance_before_mm),
            &positive(&data.final_rounds.distance_before_mm),
            BEFORE,
            "before",
        )?;
        sphere_and_final(
            &mut c,
            &positive(&data.global.distance_after_mm),
            &positive(&data.final_rounds.distance_after_mm),
            AFTER,
            "after",
        )?;
        legend(&mut c)
    })
}

fn reprojection_figure(data: &PlotData) -> anyhow::Result<String> {
    let local = &data.local;
    // mean + sign * std, not below zero.
    let offset = |sign: f64| -> Series {
        local
            .reprojection_after_px
            .iter()
            .zip(&local.reprojection_after_std_px)
            .map(|(m, s)| (m.0, (m.1 + sign * s.1).max(0.0)))
            .collect()
    };
    let (upper, lower) = (offset(1.0), offset(-1.0));
    let all = [
        &upper,
        &local.reprojection_before_px,
        &data.global.reprojection_after_px,
        &data.final_rounds.reprojection_after_px,
    ];
    svg(|root| {
        let mut c = chart(
            root,
            "Reprojection error before and after each solve",
            x_range(all),
            y_range_from_zero(all),
            "registered images",
            "reprojection error (px)",
            false,
        )?;
        if !upper.is_empty() {
            let band: Vec<(f64, f64)> = upper
                .iter()
                .copied()
                .chain(lower.iter().rev().copied())
                .collect();
            c.draw_series(std::iter::once(Polygon::new(band, AFTER.mix(0.2).filled())))
                .map_err(plot_error)?
                .label("after: mean +- std (local)")
                .legend(|(x, y)| {
                    Rectangle::new([(x, y - 5), (x + 20, y + 5)], AFTER.mix(0.2).filled())
                });
        }
        line(
            &mut c,
            &local.reprojection_before_px,
            BEFORE,
            "mean before (local)",
        )?;
        line(
            &mut c,
            &local.reprojection_after_px,
            AFTER,
            "mean after (local)",
        )?;
        sphere_and_final(
            &mut c,
            &data.global.reprojection_after_px,
            &data.final_rounds.reprojection_after_px,
            AFTER,
            "mean after",
        )?;
        legend(&mut c)
    })
}

fn images_figure(data: &PlotData) -> anyhow::Result<String> {
    let im = &data.images;
    let total: Series = im
        .projection
        .iter()
        .zip(&im.nearest)
        .zip(&im.ground)
        .map(|((p, n), g)| (p.0, p.1 + n.1 + g.1))
        .collect();
    let counts = [&total];
    svg(|root| {
        let (top, bottom) = root.split_vertically(SIZE.1 / 2);
        {
            let mut c = chart(
                &top,
                if total.is_empty() {
                    "Per image: none recorded (a run set aside keeps only its solves)"
                } else {
                    "Per image (registration order): plane terms of its points"
                },
                x_range([&total, &im.distance_mm]),
                y_range_from_zero(counts),
                "",
                "plane terms",
                true,
            )?;
            line(&mut c, &im.projection, PROJECTION, "projection")?;
            line(&mut c, &im.nearest, NEAREST, "nearest")?;
            line(&mut c, &im.ground, GROUND, "ground")?;
            line(&mut c, &total, TOTAL, "all")?;
            legend(&mut c)?;
        }
        let mut c = chart(
            &bottom,
            "Mean point-to-plane distance of its points",
            x_range([&total, &im.distance_mm]),
            y_range_from_zero([&im.distance_mm]),
            "registration index",
            "distance (mm)",
            false,
        )?;
        line(&mut c, &im.distance_mm, AFTER, "mean distance")?;
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A solve record as report.json has it.
    fn solve(
        kind: &str,
        registered: usize,
        planes: [usize; 3],
        before_mm: f64,
        after_mm: f64,
    ) -> serde_json::Value {
        let n = planes.iter().sum::<usize>();
        serde_json::json!({
            "kind": kind, "num_registered": registered, "num_variable_poses": 2,
            "num_constant_poses": 0, "num_points": 10 * registered,
            "num_observations": 30 * registered, "num_planes": n,
            "num_projection_planes": planes[0], "num_nearest_planes": planes[1],
            "num_ground_planes": planes[2],
            "plane_distance_before_m": {"mean": before_mm * 1e-3, "median": 0.0},
            "plane_distance_after_m": {"mean": after_mm * 1e-3, "median": 0.0},
            "reprojection_before_px": {"mean": 0.5, "std": 0.2, "count": 30},
            "reprojection_after_px": {"mean": 0.25, "std": 0.1, "count": 30},
            "initial_cost": 1.0, "final_cost": 0.5, "iterations": 3, "usable": true,
            "discarded": false, "intrinsics_held": [], "time_s": 0.1,
            "association_time_s": 0.01
        })
    }

    fn image(
        id: u32,
        index: Option<usize>,
        planes: [usize; 3],
        distance_mm: Option<f64>,
    ) -> serde_json::Value {
        serde_json::json!({
            "image_id": id, "name": format!("{id}.jpg"), "registered": index.is_some(),
            "registration_index": index, "attempts": 1, "num_correspondences": 50,
            "pnp_inliers": 40, "placed_by_prior": false, "num_observations": 100,
            "mean_reprojection_error_px": 0.3, "num_projection_planes": planes[0],
            "num_nearest_planes": planes[1], "num_ground_planes": planes[2],
            "mean_plane_distance_m": distance_mm.map(|d| d * 1e-3), "pose_uncertainty": null
        })
    }

    fn sample_report() -> ReportForPlots {
        serde_json::from_value(sample_json()).unwrap()
    }

    fn sample_json() -> serde_json::Value {
        let mut discarded = solve("final", 4, [0, 50, 0], 3.0, 2.0);
        discarded["discarded"] = serde_json::json!(true);
        let mut empty = solve("local", 4, [0, 0, 0], 0.0, 0.0);
        empty["num_points"] = serde_json::json!(0);
        let json = serde_json::json!({
            "seed": 0,
            "solves": [
                solve("local", 2, [10, 60, 30], 4.0, 0.01),
                solve("local_refine", 2, [10, 60, 30], 0.01, 0.005),
                solve("local", 3, [20, 100, 40], 2.0, 0.02),
                solve("global", 3, [25, 120, 45], 1.0, 0.03),
                empty,
                solve("local", 4, [0, 150, 50], 8.0, 0.04),
                solve("final_first", 4, [5, 200, 60], 0.5, 3.0),
                discarded,
                solve("final", 4, [5, 210, 65], 3.0, 2.5),
            ],
            "images": [
                image(7, Some(1), [1, 20, 5], Some(2.0)),
                image(8, None, [0, 0, 0], None),
                image(9, Some(0), [2, 30, 0], Some(4.0)),
                image(10, Some(2), [0, 0, 0], None),
            ],
        });
        json
    }

    #[test]
    fn series_follow_the_report() {
        let data = PlotData::from_report(&sample_report()).unwrap();
        // Local: first passes with points only; the refine pass and the empty solve left out.
        assert_eq!(
            data.local.planes,
            vec![(2.0, 100.0), (3.0, 160.0), (4.0, 200.0)]
        );
        assert_eq!(
            data.local.projection,
            vec![(2.0, 10.0), (3.0, 20.0), (4.0, 0.0)]
        );
        assert_eq!(
            data.local.ground,
            vec![(2.0, 30.0), (3.0, 40.0), (4.0, 50.0)]
        );
        let mm = |s: &Series| {
            s.iter()
                .map(|p| (p.0, (p.1 * 1e6).round() / 1e6))
                .collect::<Series>()
        };
        assert_eq!(
            mm(&data.local.distance_before_mm),
            vec![(2.0, 4.0), (3.0, 2.0), (4.0, 8.0)]
        );
        assert_eq!(
            mm(&data.local.distance_after_mm),
            vec![(2.0, 0.01), (3.0, 0.02), (4.0, 0.04)]
        );
        assert_eq!(data.global.planes, vec![(3.0, 190.0)]);
        // Both final rounds; the discarded one left out.
        assert_eq!(data.final_rounds.planes, vec![(4.0, 265.0), (4.0, 280.0)]);
        assert_eq!(
            data.local.reprojection_after_std_px,
            vec![(2.0, 0.1), (3.0, 0.1), (4.0, 0.1)]
        );
        // Images in registration order; the unregistered one left out, the
        // one without planes has no distance.
        assert_eq!(
            data.images.nearest,
            vec![(0.0, 30.0), (1.0, 20.0), (2.0, 0.0)]
        );
        assert_eq!(data.images.distance_mm.len(), 2);
        assert_eq!(mm(&data.images.distance_mm), vec![(0.0, 4.0), (1.0, 2.0)]);
    }

    /// The data polylines (more than the legend's two points) of one colour.
    fn polylines(svg: &str, colour: RGBColor) -> Vec<Vec<(f64, f64)>> {
        let stroke = format!(
            "stroke=\"#{:02X}{:02X}{:02X}\"",
            colour.0, colour.1, colour.2
        );
        svg.split("<polyline")
            .skip(1)
            .filter(|e| e.split('>').next().is_some_and(|tag| tag.contains(&stroke)))
            .filter_map(|e| {
                let points = e.split("points=\"").nth(1)?.split('"').next()?;
                let parsed: Vec<(f64, f64)> = points
                    .split_whitespace()
                    .map(|p| {
                        let (x, y) = p.split_once(',').unwrap();
                        (x.parse().unwrap(), y.parse().unwrap())
                    })
                    .collect();
                (parsed.len() > 2).then_some(parsed)
            })
            .collect()
    }

    #[test]
    fn figures_draw_the_series() {
        let data = PlotData::from_report(&sample_report()).unwrap();
        let figures = render(&data).unwrap();
        let names: Vec<&str> = figures.iter().map(|f| f.0).collect();
        assert_eq!(
            names,
            [
                "planes.svg",
                "plane_distance.svg",
                "reprojection.svg",
                "images.svg"
            ]
        );
        // planes.svg: the total over local solves, 100, 160, 200 at x = 2, 3, 4:
        // evenly spaced in x, rising on screen (y grows downwards) in proportion.
        let lines = polylines(&figures[0].1, TOTAL);
        assert_eq!(lines.len(), 1, "{lines:?}");
        let p = &lines[0];
        assert_eq!(p.len(), 3);
        assert!(
            ((p[1].0 - p[0].0) - (p[2].0 - p[1].0)).abs() <= 1.0,
            "{p:?}"
        );
        let rise = |a: (f64, f64), b: (f64, f64)| a.1 - b.1;
        assert!(rise(p[0], p[1]) > 0.0 && rise(p[1], p[2]) > 0.0);
        assert!(
            (rise(p[0], p[1]) / rise(p[1], p[2]) - 60.0 / 40.0).abs() < 0.1,
            "{p:?}"
        );
        // plane_distance.svg (log scale): after lies below before everywhere,
        // and 4 mm -> 2 mm -> 8 mm rise as log ratios (-1 : 2).
        let before = &polylines(&figures[1].1, BEFORE)[0];
        let after = &polylines(&figures[1].1, AFTER)[0];
        for (b, a) in before.iter().zip(after) {
            assert!(a.1 > b.1, "{before:?} {after:?}");
        }
        let r = rise(before[1], before[2]) / rise(before[0], before[1]);
        assert!((r + 2.0).abs() < 0.1, "{before:?}");
        // images.svg: three registered images on the per-image lines.
        assert_eq!(polylines(&figures[3].1, NEAREST)[0].len(), 3);
    }

    #[test]
    fn runs_without_lidar_terms_are_drawn() {
        // `--no-lidar-constraints`: solves without planes, images without distances.
        let json = serde_json::json!({
            "solves": [solve("local", 2, [0, 0, 0], 0.0, 0.0), solve("final", 3, [0, 0, 0], 0.0, 0.0)],
            "images": [image(1, Some(0), [0, 0, 0], None)],
        });
        let data = PlotData::from_report(&serde_json::from_value(json).unwrap()).unwrap();
        assert!(data.local.distance_after_mm.is_empty() && data.images.distance_mm.is_empty());
        assert_eq!(data.local.reprojection_after_px, vec![(2.0, 0.25)]);
        let figures = render(&data).unwrap();
        assert!(figures
            .iter()
            .all(|(_, svg)| svg.trim_end().ends_with("</svg>")));
    }

    #[test]
    fn nulls_missing_fields_and_absurd_values_are_left_out() {
        // An undetermined sigma is written as null, older reports lack
        // fields, a corrupt one may hold absurd numbers.
        let mut image_with_null = image(3, Some(0), [0, 5, 0], Some(1.0));
        image_with_null["pose_uncertainty"] = serde_json::json!(
            {"centre_sigma_m": [null, 0.001, 0.001], "rotation_sigma_deg": null}
        );
        let mut old = solve("local", 2, [0, 50, 0], 3.0, 0.01);
        old.as_object_mut().unwrap().remove("discarded");
        old.as_object_mut().unwrap().remove("intrinsics_held");
        let mut nulls = solve("local", 3, [0, 60, 0], 2.0, 0.02);
        nulls["plane_distance_after_m"]["mean"] = serde_json::Value::Null;
        nulls["reprojection_after_px"]["std"] = serde_json::Value::Null;
        let huge = solve("global", 4, [0, 70, 0], 1e300, 0.03);
        let json = serde_json::json!({"solves": [old, nulls, huge], "images": [image_with_null]});
        let report: ReportForPlots = serde_json::from_value(json).unwrap();
        let data = PlotData::from_report(&report).unwrap();
        assert_eq!(data.local.planes, vec![(2.0, 50.0), (3.0, 60.0)]);
        assert_eq!(data.local.distance_after_mm.len(), 1);
        assert_eq!(data.local.reprojection_after_px, vec![(2.0, 0.25)]);
        assert_eq!(data.images.nearest, vec![(0.0, 5.0)]);
        // The 1e303 mm value is left off the axis, which stays finite.
        let figures = render(&data).unwrap();
        assert!(figures[1].1.trim_end().ends_with("</svg>"));
    }

    /// `--run`: the kept run is the report's own solves and images; a run set
    /// aside has its own solves and no images, and is drawn with an empty
    /// per-image figure; an index not there names the runs there are.
    #[test]
    fn a_run_set_aside_is_drawn_from_its_own_solves() {
        let mut json = sample_json();
        json["runs"] = serde_json::json!([
            {"index": 0, "kept": false, "outcome": "stopped at its look", "time_s": 3.0,
             "solves": [solve("local", 2, [0, 40, 10], 9.0, 0.5),
                        solve("global", 3, [0, 70, 20], 5.0, 0.4)]},
            {"index": 1, "kept": true, "outcome": "finished", "time_s": 9.0},
            {"index": 2, "kept": false, "outcome": "failed: the model does not fit the map",
             "time_s": 1.0, "solves": []},
        ]);
        let report = || serde_json::from_value::<ReportForPlots>(json.clone()).unwrap();
        let kept = report().of_run(1).unwrap();
        assert_eq!((kept.solves.len(), kept.images.len()), (9, 4));
        let aside = report().of_run(0).unwrap();
        assert_eq!((aside.solves.len(), aside.images.len()), (2, 0));
        let data = PlotData::from_report(&aside).unwrap();
        assert_eq!(data.local.nearest, vec![(2.0, 40.0)]);
        assert_eq!(data.global.ground, vec![(3.0, 20.0)]);
        assert!(data.images.projection.is_empty());
        let figures = render(&data).unwrap();
        let (name, images) = &figures[3];
        assert_eq!(*name, "images.svg");
        assert!(images.contains("none recorded"), "{images}");
        let err = report().of_run(5).unwrap_err().to_string();
        assert!(
            err.contains("no run 5") && err.contains("0 (stopped at its look)"),
            "{err}"
        );
        assert!(err.contains("1 (finished, kept); 2 (failed)"), "{err}");
        // A run that failed before its first solve has nothing to draw.
        let failed = report().of_run(2).unwrap();
        assert!(PlotData::from_report(&failed).is_err());
        let old = serde_json::from_value::<ReportForPlots>(sample_json()).unwrap();
        let err = old.of_run(0).unwrap_err().to_string();
        assert!(err.contains("none recorded"), "{err}");
        // Through the command: the run set aside's figures, written.
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("report.json");
        fs::write(&file, json.to_string()).unwrap();
        let out = dir.path().join("plots");
        run(&PlotArgs {
            report: dir.path().to_path_buf(),
            output: out.clone(),
            run: Some(0),
        })
        .unwrap();
        let written = fs::read_to_string(out.join("images.svg")).unwrap();
        assert!(written.contains("none recorded"));
    }

    #[test]
    fn reports_without_solves_and_bad_files_are_errors() {
        let empty: ReportForPlots =
            serde_json::from_str(r#"{"solves": [], "images": []}"#).unwrap();
        let err = PlotData::from_report(&empty).unwrap_err();
        assert!(err.to_string().contains("no solve"), "{err}");
        let dir = tempfile::tempdir().unwrap();
        let bad = dir.path().join("report.json");
        fs::write(&bad, "{\"solves\": [{\"kind\": \"local\"").unwrap();
        let err = format!("{:#}", read_report(dir.path()).unwrap_err());
        assert!(err.contains(&bad.display().to_string()), "{err}");
        let err = format!(
            "{:#}",
            read_report(&dir.path().join("missing.json")).unwrap_err()
        );
        assert!(err.contains("missing.json"), "{err}");
        // Nothing written on error: a report that parses but has nothing to draw.
        fs::write(&bad, r#"{"seed": 0, "solves": []}"#).unwrap();
        let out = dir.path().join("plots");
        let args = PlotArgs {
            report: bad.clone(),
            output: out.clone(),
            run: None,
        };
        let err = format!("{:#}", run(&args).unwrap_err());
        assert!(
            err.contains("no solve") && err.contains("report.json"),
            "{err}"
        );
        assert!(!out.exists());
        // Into the model's own folder: the figures join its files, which stay.
        fs::write(&bad, sample_json().to_string()).unwrap();
        let model_file = dir.path().join("cameras.txt");
        fs::write(&model_file, "# camera").unwrap();
        run(&PlotArgs {
            report: dir.path().to_path_buf(),
            output: dir.path().to_path_buf(),
            run: None,
        })
        .unwrap();
        assert!(model_file.exists() && dir.path().join("planes.svg").exists());
    }
}
