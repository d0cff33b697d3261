//! Charts and a markdown summary of a sweep's trials (`trials*.jsonl`, all shards merged):
//!
//! - `error_vs_rings.png` — the paper's Fig. 4: relMAE (mean ± std over scenarios) against
//!   rings, per solver × spp, with the mean noise floor;
//! - `speed_vs_accuracy.png` — stand-alone fit time against mean relMAE for every setting
//!   tried, the Pareto front joined;
//! - `error_vs_distance.png` — each scenario's best relMAE over rings against its nearest
//!   light's distance (in scene sizes): where the infinite-distance model breaks down;
//! - `report.md` and `summary.json`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use plotters::prelude::*;
use serde::Serialize;

use super::sweep::{Status, TrialRecord, read_records};
use crate::error::{Error, Result};
use crate::estimate::Solver;
use crate::output::figure::{self, Chart, Drawn};
use plotters::coord::Shift;
use plotters::coord::types::RangedCoordf64;
use plotters::style::text_anchor::{HPos, Pos, VPos};

/// A series of the charts: one solver at one transport spp and albedo error.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize)]
pub struct SeriesKey {
    pub solver: SolverName,
    pub spp: u32,
    /// The fit's albedo error, percent (0 = true albedos).
    pub albedo_error_percent: u32,
    /// The albedo was fitted beside the lighting.
    pub fit_albedo: bool,
}

/// Solver, ordered and printable.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum SolverName {
    Nnls,
    Gradient,
}

impl From<Solver> for SolverName {
    fn from(s: Solver) -> Self {
        match s {
            Solver::Nnls => SolverName::Nnls,
            Solver::Gradient => SolverName::Gradient,
        }
    }
}

impl SeriesKey {
    fn of(r: &TrialRecord) -> Self {
        SeriesKey {
            solver: r.solver.into(),
            spp: r.spp,
            albedo_error_percent: (r.albedo_error * 100.0).round() as u32,
            fit_albedo: r.fit_albedo,
        }
    }

    fn label(&self) -> String {
        if self.albedo_error_percent > 0 {
            return format!(
                "{} {} spp, albedo ±{}%{}",
                format!("{:?}", self.solver).to_lowercase(),
                self.spp,
                self.albedo_error_percent,
                if self.fit_albedo { ", fitted" } else { "" }
            );
        }
        format!(
            "{} {} spp",
            format!("{:?}", self.solver).to_lowercase(),
            self.spp
        )
    }
}

/// Mean and spread of one setting over scenarios.
#[derive(Debug, Clone, Serialize)]
pub struct Cell {
    pub series: SeriesKey,
    pub rings: u32,
    pub scenarios: usize,
    pub rel_mae_mean: f64,
    pub rel_mae_std: f64,
    pub noise_floor_mean: f64,
    /// Mean stand-alone fit time, seconds.
    pub fit_seconds_mean: f64,
    pub on_pareto_front: bool,
    /// Series that fit the albedo: the mean over trials of each trial's mean relative error
    /// of the fitted albedo, and the largest over trials and materials.
    pub albedo_error_mean: Option<f64>,
    pub albedo_error_max: Option<f64>,
}

/// What `report` found.
#[derive(Debug, Clone, Serialize)]
pub struct Summary {
    pub trials: usize,
    pub failed: usize,
    pub not_converged: usize,
    pub scenarios: usize,
    pub cells: Vec<Cell>,
    /// Sum of the trials' wall times, seconds (references not included).
    pub trial_seconds: f64,
    /// Wall time of the sweep runs recorded in runs*.jsonl (shards summed), seconds.
    pub sweep_wall_seconds: Option<f64>,
    /// `--rings auto` trials against the best fixed resolution of their scenario and series.
    pub auto: Vec<AutoFigures>,
    /// Fraction of scenarios where auto is within 10% of the best fixed resolution's error.
    pub auto_within_10_percent: Option<f64>,
    /// The sphere-light model's trials (`sweep --spheres`).
    pub spheres: Option<SphereSummary>,
    pub charts: Vec<PathBuf>,
}

/// The sphere model against its goal (every centre within 2% of its distance, every power within 5%), on the scenarios whose lights all sit 1.5–5 m from
/// the scene centre: relMAE within 2× the noise floor, every centre within 2% of its distance,
/// every power within 5%.
#[derive(Debug, Clone, Serialize)]
pub struct SphereSummary {
    pub scenarios: usize,
    pub in_range: usize,
    pub in_range_within_2x_noise_floor: usize,
    pub in_range_centres_within_2_percent: usize,
    pub in_range_power_within_5_percent: usize,
    pub in_range_all_three: usize,
    /// Means over all sphere trials: the sphere model's relMAE and its initialising envmap's.
    pub rel_mae_mean: f64,
    pub envmap_rel_mae_mean: f64,
    /// Mean stand-alone time: envmap fit + sphere fit, seconds.
    pub fit_seconds_mean: f64,
    pub rows: Vec<SphereRow>,
}

/// One scenario's sphere trial.
#[derive(Debug, Clone, Serialize)]
pub struct SphereRow {
    pub scenario: String,
    pub true_lights: usize,
    pub fitted_lights: usize,
    /// Distances of the true lights, metres.
    pub distances: Vec<f32>,
    pub rel_mae: f64,
    pub envmap_rel_mae: Option<f64>,
    pub noise_floor: Option<f64>,
    /// Largest centre error over the true lights, as a fraction of distance (None: a light
    /// was not recovered).
    pub worst_centre_fraction: Option<f32>,
    /// Largest |power ratio − 1| over the true lights.
    pub worst_power_error: Option<f32>,
    pub fit_seconds: f64,
}

impl SphereRow {
    fn in_range(&self) -> bool {
        self.distances.iter().all(|d| (1.5..=5.0).contains(d))
    }
    fn within_noise(&self) -> bool {
        self.noise_floor.is_some_and(|n| self.rel_mae <= 2.0 * n)
    }
    fn centres_ok(&self) -> bool {
        self.worst_centre_fraction.is_some_and(|f| f <= 0.02)
    }
    fn power_ok(&self) -> bool {
        self.worst_power_error.is_some_and(|p| p <= 0.05)
    }
}

fn sphere_summary(trials: &[&TrialRecord]) -> Option<SphereSummary> {
    let rows: Vec<SphereRow> = trials
        .iter()
        .filter_map(|r| {
            let s = r.spheres.as_ref()?;
            let worst = |f: &dyn Fn(&crate::estimate::recovery::SphereRecovery) -> Option<f32>| {
                s.recovery
                    .iter()
                    .map(f)
                    .try_fold(0.0f32, |m, x| x.map(|x| m.max(x)))
            };
            Some(SphereRow {
                scenario: r.scenario.clone(),
                true_lights: r.lights.len(),
                fitted_lights: s
                    .statuses
                    .iter()
                    .filter(|st| {
                        matches!(
                            st,
                            crate::estimate::spheres::LightStatus::Identified
                                | crate::estimate::spheres::LightStatus::DistanceUnidentified
                        )
                    })
                    .count(),
                distances: r.lights.iter().map(|l| l.distance).collect(),
                rel_mae: r.rel_mae?,
                envmap_rel_mae: s.envmap_rel_mae,
                noise_floor: r.noise_floor_rel_mae,
                worst_centre_fraction: worst(&|x| x.centre_error_fraction_of_distance),
                worst_power_error: worst(&|x| x.power_ratio.map(|p| (p - 1.0).abs())),
                fit_seconds: r.timings.fit_seconds + s.sphere_fit_seconds,
            })
        })
        .collect();
    if rows.is_empty() {
        return None;
    }
    let near: Vec<&SphereRow> = rows.iter().filter(|r| r.in_range()).collect();
    let count = |f: &dyn Fn(&SphereRow) -> bool| near.iter().filter(|r| f(r)).count();
    let mean = |v: Vec<f64>| v.iter().sum::<f64>() / v.len().max(1) as f64;
    Some(SphereSummary {
        scenarios: rows.len(),
        in_range: near.len(),
        in_range_within_2x_noise_floor: count(&|r| r.within_noise()),
        in_range_centres_within_2_percent: count(&|r| r.centres_ok()),
        in_range_power_within_5_percent: count(&|r| r.power_ok()),
        in_range_all_three: count(&|r| r.within_noise() && r.centres_ok() && r.power_ok()),
        rel_mae_mean: mean(rows.iter().map(|r| r.rel_mae).collect()),
        envmap_rel_mae_mean: mean(rows.iter().filter_map(|r| r.envmap_rel_mae).collect()),
        fit_seconds_mean: mean(rows.iter().map(|r| r.fit_seconds).collect()),
        rows,
    })
}

/// One scenario's `--rings auto` trial against its best fixed resolution.
#[derive(Debug, Clone, Serialize)]
pub struct AutoFigures {
    pub scenario: String,
    pub series: SeriesKey,
    pub auto_rings: u32,
    pub auto_rel_mae: f64,
    pub best_rings: u32,
    pub best_rel_mae: f64,
    /// Mean stand-alone time of `--rings auto` (selection + fit), seconds.
    pub auto_fit_seconds: f64,
}

fn auto_against_best(ok: &[&TrialRecord]) -> Vec<AutoFigures> {
    ok.iter()
        .filter(|r| r.auto.is_some())
        .filter_map(|a| {
            let series = SeriesKey::of(a);
            let best = ok
                .iter()
                .filter(|r| {
                    r.auto.is_none() && r.scenario == a.scenario && SeriesKey::of(r) == series
                })
                .min_by(|x, y| {
                    x.rel_mae
                        .unwrap_or(f64::INFINITY)
                        .total_cmp(&y.rel_mae.unwrap_or(f64::INFINITY))
                })?;
            Some(AutoFigures {
                scenario: a.scenario.clone(),
                series,
                auto_rings: a.rings,
                auto_rel_mae: a.rel_mae?,
                best_rings: best.rings,
                best_rel_mae: best.rel_mae?,
                auto_fit_seconds: a.timings.fit_seconds,
            })
        })
        .collect()
}

fn mean_std(v: &[f64]) -> (f64, f64) {
    let n = v.len().max(1) as f64;
    let m = v.iter().sum::<f64>() / n;
    let var = v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0).max(1.0);
    (m, var.sqrt())
}

/// Colour of series `s` among `series`: its samples per pixel, albedo error and whether it
/// fitted the albedo ranked along viridis (the solver is told by the marker, not the colour).
fn series_colour(series: &[SeriesKey], s: &SeriesKey) -> RGBColor {
    let key = |k: &SeriesKey| (k.spp, k.albedo_error_percent, k.fit_albedo);
    let mut keys: Vec<(u32, u32, bool)> = series.iter().map(key).collect();
    keys.sort_unstable();
    keys.dedup();
    let i = keys.iter().position(|k| *k == key(s)).unwrap_or(0);
    figure::series_colour(i, keys.len())
}

/// Ticks, labels and grid lines of an x axis that holds log10 of its values (from `lo` to
/// `hi`), at 1-2-5 steps ([`figure::log_ticks`]): plotters' own log axis labels nothing over
/// less than a decade, and repeats labels over a few.
fn log_x_axis<DB>(
    root: &DrawingArea<DB, Shift>,
    ch: &mut ChartContext<'_, DB, Cartesian2d<RangedCoordf64, RangedCoordf64>>,
    (lo, hi): (f64, f64),
    y_max: f64,
) -> Drawn
where
    DB: DrawingBackend,
    DB::ErrorType: 'static,
{
    let (_, ys) = ch.plotting_area().get_pixel_range();
    for t in figure::log_ticks(lo, hi) {
        let x = t.log10();
        ch.draw_series([PathElement::new([(x, 0.0), (x, y_max)], BLACK.mix(0.15))])?;
        let (px, _) = ch.backend_coord(&(x, 0.0));
        root.draw(&PathElement::new([(px, ys.end), (px, ys.end + 5)], BLACK))?;
        root.draw(&Text::new(
            figure::tick_label(t),
            (px, ys.end + 8),
            figure::text(15).pos(Pos::new(HPos::Center, VPos::Top)),
        ))?;
    }
    Ok(())
}

/// Draws a chart's legend, the same way on every chart.
fn legend<'a, DB, CT>(ch: &mut ChartContext<'a, DB, CT>, position: SeriesLabelPosition) -> Drawn
where
    DB: DrawingBackend + 'a,
    DB::ErrorType: 'static,
    CT: plotters::coord::CoordTranslate,
{
    ch.configure_series_labels()
        .position(position)
        .label_font(figure::text(15))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()?;
    Ok(())
}

/// Reads the trials in `dir` and writes the charts, report.md and summary.json there.
pub fn report(dir: &Path) -> Result<Summary> {
    if !dir.is_dir() {
        return Err(Error::file(
            dir,
            "no such folder (a `lightprobe sweep --out` folder)",
        ));
    }
    let records = read_records(dir)?;
    if records.is_empty() {
        return Err(Error::file(
            dir,
            "holds no trials (trials*.jsonl); run `lightprobe sweep` first",
        ));
    }
    let ok: Vec<&TrialRecord> = records
        .iter()
        .filter(|r| r.status != Status::Failed && r.rel_mae.is_some_and(f64::is_finite))
        .collect();
    // The sphere model's trials have their own section; the envmap figures leave them out.
    let (sphere_trials, ok): (Vec<&TrialRecord>, Vec<&TrialRecord>) =
        ok.into_iter().partition(|r| r.spheres.is_some());
    let failed = records
        .iter()
        .filter(|r| r.status == Status::Failed)
        .count();
    if ok.is_empty() {
        return Err(Error::file(
            dir,
            format!(
                "all {} trials failed: nothing to chart (see \"error\" in trials*.jsonl)",
                records.len()
            ),
        ));
    }
    let not_converged = records
        .iter()
        .filter(|r| r.status == Status::NotConverged)
        .count();

    let cells = aggregate(&ok);
    let series: Vec<SeriesKey> = {
        let mut v: Vec<SeriesKey> = cells.iter().map(|c| c.series).collect();
        v.dedup();
        v
    };
    let best = best_per_scenario(&ok, series.first());
    let auto = auto_against_best(&ok);
    // A chart of one point says nothing: drawn only when its axis has two values or more
    // (else an earlier report's copy is removed).
    let mut rings: Vec<u32> = cells.iter().map(|c| c.rings).collect();
    rings.sort_unstable();
    rings.dedup();
    let mut charts = Vec::new();
    for (name, wanted) in [
        ("error_vs_rings", rings.len() > 1),
        ("speed_vs_accuracy", cells.len() > 1),
        ("auto_vs_best", !auto.is_empty()),
    ] {
        if !wanted {
            for ext in ["png", "svg"] {
                let stale = dir.join(format!("{name}.{ext}"));
                match std::fs::remove_file(&stale) {
                    Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                        return Err(Error::io(&stale, e));
                    }
                    _ => {}
                }
            }
            continue;
        }
        charts.push(match name {
            "error_vs_rings" => chart_error_vs_rings(dir, &cells, &series)?,
            "speed_vs_accuracy" => chart_speed_vs_accuracy(dir, &cells, &series)?,
            _ => chart_auto_vs_best(dir, &auto)?,
        });
    }
    charts.push(chart_error_vs_distance(
        dir,
        &best,
        &sphere_trials,
        series.first(),
    )?);

    // ---- Markdown and JSON ----
    let sweep_wall_seconds = read_run_seconds(dir);
    let summary = Summary {
        trials: records.len(),
        failed,
        not_converged,
        scenarios: records
            .iter()
            .map(|r| r.scenario.as_str())
            .collect::<std::collections::BTreeSet<_>>()
            .len(),
        cells,
        trial_seconds: records.iter().map(|r| r.timings.trial_seconds).sum(),
        sweep_wall_seconds,
        auto_within_10_percent: (!auto.is_empty()).then(|| {
            auto.iter()
                .filter(|a| a.auto_rel_mae <= 1.1 * a.best_rel_mae)
                .count() as f64
                / auto.len() as f64
        }),
        auto,
        spheres: sphere_summary(&sphere_trials),
        charts,
    };
    let md = markdown(&summary, &best);
    crate::imageio::write_bytes(&dir.join("report.md"), md.as_bytes())?;
    let html = html_page(&summary, &best);
    crate::imageio::write_bytes(&dir.join("index.html"), html.as_bytes())?;
    let json =
        serde_json::to_string_pretty(&summary).map_err(|e| Error::Invalid(e.to_string()))? + "\n";
    crate::imageio::write_bytes(&dir.join("summary.json"), json.as_bytes())?;
    Ok(summary)
}

/// `index.html` of a sweep: each chart (its SVG) beside the table of what it plots.
fn html_page(s: &Summary, best: &BTreeMap<&str, &TrialRecord>) -> String {
    use crate::output::page::escape;
    let mut h = format!(
        "<!doctype html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>lightprobe \
         sweep</title><style>body{{font-family:'DejaVu Sans',sans-serif;margin:24px;color:#222}}\
         .pair{{display:flex;gap:24px;align-items:flex-start;flex-wrap:wrap;margin-bottom:32px}}\
         .pair img{{width:720px}}table{{border-collapse:collapse;font-size:13px}}td,th{{padding:\
         2px 8px;border-bottom:1px solid #eee;text-align:right}}</style></head><body>\n\
         <h1>Sweep report</h1><p>{} trials over {} scenarios; {} failed, {} did not converge. \
         Every chart is an SVG (and a PNG) beside this page; summary.json holds every \
         figure.</p>\n",
        s.trials, s.scenarios, s.failed, s.not_converged
    );
    let cells_table = |with_time: bool| {
        let mut t = String::from(
            "<table><tr><th>series</th><th>rings</th><th>relMAE mean</th><th>std</th>\
             <th>noise floor</th>",
        );
        t += if with_time {
            "<th>fit (s)</th><th>Pareto front</th></tr>\n"
        } else {
            "</tr>\n"
        };
        for c in &s.cells {
            t += &format!(
                "<tr><td>{}</td><td>{}</td><td>{:.2}%</td><td>{:.2}%</td><td>{:.2}%</td>",
                escape(&c.series.label()),
                c.rings,
                100.0 * c.rel_mae_mean,
                100.0 * c.rel_mae_std,
                100.0 * c.noise_floor_mean
            );
            if with_time {
                t += &format!(
                    "<td>{:.2}</td><td>{}</td>",
                    c.fit_seconds_mean,
                    if c.on_pareto_front { "●" } else { "" }
                );
            }
            t += "</tr>\n";
        }
        t + "</table>"
    };
    for chart in &s.charts {
        let name = chart
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let table = match name.as_str() {
            "error_vs_rings.png" => cells_table(false),
            "speed_vs_accuracy.png" => cells_table(true),
            "auto_vs_best.png" => {
                let mut t = String::from(
                    "<table><tr><th>scenario</th><th>auto rings</th><th>auto relMAE</th>\
                     <th>best rings</th><th>best relMAE</th></tr>\n",
                );
                for a in &s.auto {
                    t += &format!(
                        "<tr><td>{}</td><td>{}</td><td>{:.2}%</td><td>{}</td><td>{:.2}%</td></tr>\n",
                        escape(&a.scenario),
                        a.auto_rings,
                        100.0 * a.auto_rel_mae,
                        a.best_rings,
                        100.0 * a.best_rel_mae
                    );
                }
                t + "</table>"
            }
            _ => {
                let mut t = String::from(
                    "<table><tr><th>scenario</th><th>nearest light / scene size</th>\
                     <th>best relMAE</th><th>rings</th><th>noise floor</th></tr>\n",
                );
                for (scenario, r) in best {
                    let nearest = r
                        .lights
                        .iter()
                        .map(|l| l.distance_over_size)
                        .fold(f32::INFINITY, f32::min);
                    t += &format!(
                        "<tr><td>{}</td><td>{nearest:.2}</td><td>{:.2}%</td><td>{}</td>\
                         <td>{:.2}%</td></tr>\n",
                        escape(scenario),
                        100.0 * r.rel_mae.unwrap_or(f64::NAN),
                        r.rings,
                        100.0 * r.noise_floor_rel_mae.unwrap_or(f64::NAN)
                    );
                }
                t + "</table>"
            }
        };
        let svg = name.replace(".png", ".svg");
        h += &format!(
            "<div class=\"pair\"><img src=\"{svg}\" alt=\"{}\">{table}</div>\n",
            escape(&name)
        );
    }
    h + "</body></html>\n"
}

/// Per (series, rings): the mean and spread of the error over scenarios, and whether the
/// setting is on the Pareto front of fit time against error.
fn aggregate(ok: &[&TrialRecord]) -> Vec<Cell> {
    let mut groups: BTreeMap<(SeriesKey, u32), Vec<&TrialRecord>> = BTreeMap::new();
    for r in ok.iter().filter(|r| r.auto.is_none()) {
        let key = SeriesKey::of(r);
        groups.entry((key, r.rings)).or_default().push(r);
    }
    let mut cells: Vec<Cell> = groups
        .iter()
        .map(|((series, rings), rs)| {
            let errs: Vec<f64> = rs.iter().filter_map(|r| r.rel_mae).collect();
            let (m, s) = mean_std(&errs);
            let nf: Vec<f64> = rs.iter().filter_map(|r| r.noise_floor_rel_mae).collect();
            let fit: Vec<f64> = rs.iter().map(|r| r.timings.fit_seconds).collect();
            let albedo: Vec<f64> = rs.iter().filter_map(|r| r.albedo_mean_error).collect();
            Cell {
                albedo_error_mean: (!albedo.is_empty()).then(|| mean_std(&albedo).0),
                albedo_error_max: rs
                    .iter()
                    .filter_map(|r| r.albedo_max_error)
                    .reduce(f64::max),
                series: *series,
                rings: *rings,
                scenarios: rs.len(),
                rel_mae_mean: m,
                rel_mae_std: s,
                noise_floor_mean: mean_std(&nf).0,
                fit_seconds_mean: mean_std(&fit).0,
                on_pareto_front: false,
            }
        })
        .collect();
    // Pareto front: no other setting (fitting with the same albedo error) is both faster and
    // at least as accurate.
    let snapshot: Vec<(f64, f64, u32)> = cells
        .iter()
        .map(|c| {
            (
                c.fit_seconds_mean,
                c.rel_mae_mean,
                c.series.albedo_error_percent,
            )
        })
        .collect();
    for (i, c) in cells.iter_mut().enumerate() {
        let (ti, ei, ai) = snapshot[i];
        c.on_pareto_front = !snapshot
            .iter()
            .enumerate()
            .any(|(j, &(t, e, a))| j != i && a == ai && t <= ti && e <= ei && (t < ti || e < ei));
    }
    cells
}

/// The paper's Fig. 4: error against rings, mean ± std over scenarios, per series.
fn chart_error_vs_rings(dir: &Path, cells: &[Cell], series: &[SeriesKey]) -> Result<PathBuf> {
    let path = dir.join("error_vs_rings.png");
    figure::write_chart(&path, &ErrorVsRings { cells, series })?;
    Ok(path)
}

struct ErrorVsRings<'a> {
    cells: &'a [Cell],
    series: &'a [SeriesKey],
}

impl Chart for ErrorVsRings<'_> {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Drawn
    where
        DB::ErrorType: 'static,
    {
        let &ErrorVsRings { cells, series } = self;
        let max_rings = cells.iter().map(|c| c.rings).max().unwrap_or(1);
        let y_max = cells
            .iter()
            .map(|c| 100.0 * (c.rel_mae_mean + c.rel_mae_std))
            .fold(1.0, f64::max)
            * 1.1;
        let mut ch = ChartBuilder::on(root)
            .caption(
                "Photometric error against envmap resolution (mean ± std over scenarios)",
                figure::text(20),
            )
            .margin(15)
            .x_label_area_size(45)
            .y_label_area_size(60)
            .build_cartesian_2d(0f64..(max_rings + 2) as f64, 0f64..y_max)?;
        ch.configure_mesh()
            .x_desc("rings")
            .y_desc("relMAE (%)")
            .label_style(figure::text(15))
            .draw()?;
        for (i, s) in series.iter().enumerate() {
            let col = series_colour(series, s);
            // Series side by side at each ring count, so that their error bars stay apart.
            let x = |c: &Cell| c.rings as f64 + 0.12 * (i as f64 - 0.5 * (series.len() - 1) as f64);
            let pts: Vec<&Cell> = cells.iter().filter(|c| c.series == *s).collect();
            let line = pts.iter().map(|c| (x(c), 100.0 * c.rel_mae_mean));
            ch.draw_series(pts.iter().map(|c| {
                PathElement::new(
                    vec![
                        (x(c), 100.0 * (c.rel_mae_mean - c.rel_mae_std).max(0.0)),
                        (x(c), 100.0 * (c.rel_mae_mean + c.rel_mae_std)),
                    ],
                    col.stroke_width(1),
                )
            }))?;
            // NNLS: solid line and circles; the gradient solver: dashed line and triangles.
            if s.solver == SolverName::Gradient {
                ch.draw_series(DashedLineSeries::new(line, 8, 5, col.stroke_width(2)))?;
                ch.draw_series(pts.iter().map(|c| {
                    TriangleMarker::new((x(c), 100.0 * c.rel_mae_mean), 5, col.filled())
                }))?
                .label(s.label())
                .legend(move |(x, y)| TriangleMarker::new((x + 10, y), 5, col.filled()));
            } else {
                ch.draw_series(LineSeries::new(line, col.stroke_width(2)))?;
                ch.draw_series(
                    pts.iter()
                        .map(|c| Circle::new((x(c), 100.0 * c.rel_mae_mean), 4, col.filled())),
                )?
                .label(s.label())
                .legend(move |(x, y)| Circle::new((x + 10, y), 4, col.filled()));
            }
        }
        let nf: Vec<&Cell> = cells
            .iter()
            .filter(|c| Some(&c.series) == series.first())
            .collect();
        ch.draw_series(LineSeries::new(
            nf.iter()
                .map(|c| (c.rings as f64, 100.0 * c.noise_floor_mean)),
            BLACK.stroke_width(1),
        ))?
        .label("noise floor (two reference renders)")
        .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK.stroke_width(1)));
        legend(&mut ch, SeriesLabelPosition::UpperRight)?;
        Ok(())
    }
}

/// Fit time against error for every setting, with the Pareto front.
fn chart_speed_vs_accuracy(dir: &Path, cells: &[Cell], series: &[SeriesKey]) -> Result<PathBuf> {
    let path = dir.join("speed_vs_accuracy.png");
    figure::write_chart(&path, &SpeedVsAccuracy { cells, series })?;
    Ok(path)
}

struct SpeedVsAccuracy<'a> {
    cells: &'a [Cell],
    series: &'a [SeriesKey],
}

impl Chart for SpeedVsAccuracy<'_> {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Drawn
    where
        DB::ErrorType: 'static,
    {
        let &SpeedVsAccuracy { cells, series } = self;
        // x is log10(seconds) on a linear axis, labelled in seconds: plotters' log axis shows no
        // labels over less than a decade.
        let lt = |c: &Cell| c.fit_seconds_mean.max(1e-4).log10();
        let t_min = cells.iter().map(lt).fold(f64::INFINITY, f64::min) - 0.1;
        let t_max = cells
            .iter()
            .map(lt)
            .fold(f64::NEG_INFINITY, f64::max)
            .max(t_min + 0.3)
            + 0.1;
        let y_max = cells
            .iter()
            .map(|c| 100.0 * c.rel_mae_mean)
            .fold(1.0, f64::max)
            * 1.15;
        let mut ch = ChartBuilder::on(root)
            .caption(
                "Speed against accuracy: every setting tried (mean over scenarios)",
                figure::text(20),
            )
            .margin(15)
            .x_label_area_size(45)
            .y_label_area_size(60)
            .build_cartesian_2d(t_min..t_max, 0f64..y_max)?;
        ch.configure_mesh()
            .x_labels(0)
            .x_desc("stand-alone fit time per estimate (s, log scale, 2 cores)")
            .y_desc("relMAE (%)")
            .label_style(figure::text(15))
            .draw()?;
        log_x_axis(root, &mut ch, (t_min, t_max), y_max)?;
        // One front per albedo error: settings fitting different albedos are not rivals, and
        // one line through all of them would zig-zag.
        let mut albedos: Vec<u32> = cells
            .iter()
            .map(|c| c.series.albedo_error_percent)
            .collect();
        albedos.sort_unstable();
        albedos.dedup();
        for (k, albedo) in albedos.iter().enumerate() {
            let mut front: Vec<&Cell> = cells
                .iter()
                .filter(|c| c.on_pareto_front && c.series.albedo_error_percent == *albedo)
                .collect();
            front.sort_by(|a, b| a.fit_seconds_mean.total_cmp(&b.fit_seconds_mean));
            let line = ch.draw_series(LineSeries::new(
                front.iter().map(|c| (lt(c), 100.0 * c.rel_mae_mean)),
                BLACK.stroke_width(1),
            ))?;
            if k == 0 {
                line.label(if albedos.len() > 1 {
                    "Pareto front (one per albedo error)"
                } else {
                    "Pareto front"
                })
                .legend(|(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], BLACK.stroke_width(1))
                });
            }
        }
        for s in series {
            let col = series_colour(series, s);
            let pts: Vec<&Cell> = cells.iter().filter(|c| c.series == *s).collect();
            let size = |c: &Cell| if c.on_pareto_front { 6 } else { 4 };
            let at = |c: &Cell| (lt(c), 100.0 * c.rel_mae_mean);
            let label = format!("{} (labels: rings)", s.label());
            if s.solver == SolverName::Gradient {
                ch.draw_series(
                    pts.iter()
                        .map(|c| TriangleMarker::new(at(c), size(c) + 1, col.filled())),
                )?
                .label(label)
                .legend(move |(x, y)| TriangleMarker::new((x + 10, y), 5, col.filled()));
            } else {
                ch.draw_series(
                    pts.iter()
                        .map(|c| Circle::new(at(c), size(c), col.filled())),
                )?
                .label(label)
                .legend(move |(x, y)| Circle::new((x + 10, y), 4, col.filled()));
            }
        }
        // Ring labels beside their points, each where it covers no point and no other label.
        let at: Vec<(i32, i32)> = cells
            .iter()
            .map(|c| ch.backend_coord(&(lt(c), 100.0 * c.rel_mae_mean)))
            .collect();
        let mut placed: Vec<(i32, i32, i32, i32)> = at
            .iter()
            .map(|&(x, y)| (x - 6, y - 6, x + 7, y + 7))
            .collect();
        let area = ch.plotting_area().get_pixel_range();
        for (c, &p) in cells.iter().zip(&at) {
            let label = c.rings.to_string();
            let (w, h) = root.estimate_text_size(&label, &figure::text(12))?;
            let b = figure::label_spot(p, (w as i32 + 2, h as i32), &placed, area.clone());
            placed.push(b);
            root.draw(&Text::new(label, (b.0 + 1, b.1), figure::text(12)))?;
        }
        legend(&mut ch, SeriesLabelPosition::LowerLeft)?;
        Ok(())
    }
}

/// Per scenario, its best trial over rings in `series` (fixed resolutions only).
fn best_per_scenario<'a>(
    ok: &[&'a TrialRecord],
    series: Option<&SeriesKey>,
) -> BTreeMap<&'a str, &'a TrialRecord> {
    let mut best: BTreeMap<&str, &TrialRecord> = BTreeMap::new();
    if let Some(s0) = series {
        for r in ok
            .iter()
            .filter(|r| r.auto.is_none() && SeriesKey::of(r) == *s0)
        {
            let e = best.entry(r.scenario.as_str()).or_insert(r);
            if r.rel_mae < e.rel_mae {
                *e = r;
            }
        }
    }
    best
}

/// Best error over rings (first series) and the sphere model's error against the nearest
/// light's distance.
fn chart_error_vs_distance(
    dir: &Path,
    best: &BTreeMap<&str, &TrialRecord>,
    sphere_trials: &[&TrialRecord],
    first_series: Option<&SeriesKey>,
) -> Result<PathBuf> {
    let path = dir.join("error_vs_distance.png");
    figure::write_chart(
        &path,
        &ErrorVsDistance {
            best,
            sphere_trials,
            first_series,
        },
    )?;
    Ok(path)
}

struct ErrorVsDistance<'a> {
    best: &'a BTreeMap<&'a str, &'a TrialRecord>,
    sphere_trials: &'a [&'a TrialRecord],
    first_series: Option<&'a SeriesKey>,
}

impl Chart for ErrorVsDistance<'_> {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Drawn
    where
        DB::ErrorType: 'static,
    {
        let &ErrorVsDistance {
            best,
            sphere_trials,
            first_series,
        } = self;
        // x is log10 of the distance on a linear axis ([`log_x_axis`]).
        let nearest = |r: &TrialRecord| {
            (r.lights
                .iter()
                .map(|l| l.distance_over_size)
                .fold(f32::INFINITY, f32::min) as f64)
                .log10()
        };
        let x_max = best
            .values()
            .chain(sphere_trials)
            .map(|r| nearest(r))
            .fold(0.0, f64::max)
            + 0.08;
        let x_min = 0.8f64.log10();
        let y_max = best
            .values()
            .chain(sphere_trials)
            .filter_map(|r| r.rel_mae)
            .fold(0.01, f64::max)
            * 110.0;
        let mut ch = ChartBuilder::on(root)
            .caption(
                format!(
                    "Best error over rings against the nearest light's distance ({})",
                    first_series.map(|s| s.label()).unwrap_or_default()
                ),
                figure::text(20),
            )
            .margin(15)
            .x_label_area_size(45)
            .y_label_area_size(60)
            .build_cartesian_2d(x_min..x_max, 0f64..y_max)?;
        ch.configure_mesh()
            .x_labels(0)
            .x_desc("nearest light's distance from the scene centre / scene size (log scale)")
            .y_desc("relMAE (%)")
            .label_style(figure::text(15))
            .draw()?;
        log_x_axis(root, &mut ch, (x_min, x_max), y_max)?;
        for (lights, col, label) in [
            (1, figure::series_colour(0, 3), "one light"),
            (2, figure::series_colour(1, 3), "two lights"),
        ] {
            ch.draw_series(best.values().filter(|r| r.lights.len() == lights).map(|r| {
                Circle::new(
                    (nearest(r), 100.0 * r.rel_mae.unwrap_or(0.0)),
                    4,
                    col.filled(),
                )
            }))?
            .label(label)
            .legend(move |(x, y)| Circle::new((x + 10, y), 4, col.filled()));
        }
        if !sphere_trials.is_empty() {
            let col = figure::series_colour(2, 3);
            ch.draw_series(sphere_trials.iter().map(|r| {
                TriangleMarker::new(
                    (nearest(r), 100.0 * r.rel_mae.unwrap_or(0.0)),
                    5,
                    col.filled(),
                )
            }))?
            .label("sphere model")
            .legend(move |(x, y)| TriangleMarker::new((x + 10, y), 5, col.filled()));
        }
        ch.draw_series(best.values().chain(sphere_trials).map(|r| {
            Cross::new(
                (nearest(r), 100.0 * r.noise_floor_rel_mae.unwrap_or(0.0)),
                3,
                BLACK.stroke_width(1),
            )
        }))?
        .label("noise floor")
        .legend(|(x, y)| Cross::new((x + 10, y), 3, BLACK.stroke_width(1)));
        legend(&mut ch, SeriesLabelPosition::UpperRight)?;
        Ok(())
    }
}

/// `--rings auto` against each scenario's best fixed resolution.
fn chart_auto_vs_best(dir: &Path, auto: &[AutoFigures]) -> Result<PathBuf> {
    let path = dir.join("auto_vs_best.png");
    figure::write_chart(&path, &AutoVsBest { auto })?;
    Ok(path)
}

struct AutoVsBest<'a> {
    auto: &'a [AutoFigures],
}

impl Chart for AutoVsBest<'_> {
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Drawn
    where
        DB::ErrorType: 'static,
    {
        let &AutoVsBest { auto } = self;
        let top = auto
            .iter()
            .map(|a| a.auto_rel_mae.max(a.best_rel_mae))
            .fold(0.01, f64::max)
            * 110.0;
        let mut ch = ChartBuilder::on(root)
            .caption(
                "--rings auto against the best fixed resolution, per scenario",
                figure::text(20),
            )
            .margin(15)
            .x_label_area_size(45)
            .y_label_area_size(60)
            .build_cartesian_2d(0f64..top, 0f64..top)?;
        ch.configure_mesh()
            .x_desc("best relMAE over the fixed resolutions (%)")
            .y_desc("relMAE with --rings auto (%)")
            .label_style(figure::text(15))
            .draw()?;
        for (k, style, label) in [
            (1.0, BLACK.stroke_width(1), "equal"),
            (1.1, RED.stroke_width(1), "10% worse"),
        ] {
            ch.draw_series(LineSeries::new([(0.0, 0.0), (top / k, top)], style))?
                .label(label)
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], style));
        }
        let col = figure::series_colour(0, 1);
        ch.draw_series(auto.iter().map(|a| {
            Circle::new(
                (100.0 * a.best_rel_mae, 100.0 * a.auto_rel_mae),
                4,
                col.filled(),
            )
        }))?
        .label("scenario")
        .legend(move |(x, y)| Circle::new((x + 10, y), 4, col.filled()));
        legend(&mut ch, SeriesLabelPosition::UpperLeft)?;
        Ok(())
    }
}

/// Total wall time of the sweep runs logged in `runs*.jsonl` (all shards, summed).
fn read_run_seconds(dir: &Path) -> Option<f64> {
    let mut total = 0.0;
    for entry in std::fs::read_dir(dir).ok()?.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        if !(name.starts_with("runs") && name.ends_with(".jsonl")) {
            continue;
        }
        let text = std::fs::read_to_string(entry.path()).ok()?;
        total += text
            .lines()
            .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
            .filter_map(|v| v["wall_seconds"].as_f64())
            .sum::<f64>();
    }
    (total > 0.0).then_some(total)
}

fn markdown(s: &Summary, best: &BTreeMap<&str, &TrialRecord>) -> String {
    let mut md = String::from("# Sweep report\n\n");
    md += &format!(
        "{} trials over {} scenarios; {} failed, {} did not converge. Trial time {:.0} s",
        s.trials, s.scenarios, s.failed, s.not_converged, s.trial_seconds
    );
    if let Some(w) = s.sweep_wall_seconds {
        md += &format!(
            "; sweep wall time {:.1} min (runs*.jsonl, shards summed, references included)",
            w / 60.0
        );
    }
    md += ".\n\n";
    let drawn = |name: &str| s.charts.iter().any(|c| c.ends_with(name));
    if drawn("error_vs_rings.png") {
        md += "![error against rings](error_vs_rings.png)\n\n";
    }
    let albedo = s.cells.iter().any(|c| c.albedo_error_mean.is_some());
    md += "| series | rings | scenarios | relMAE mean | std | noise floor | fit (s) | Pareto |";
    md += if albedo {
        " fitted albedo error, mean / max |\n|---|---:|---:|---:|---:|---:|---:|:-:|---:|\n"
    } else {
        "\n|---|---:|---:|---:|---:|---:|---:|:-:|\n"
    };
    for c in &s.cells {
        md += &format!(
            "| {} | {} | {} | {:.2}% | {:.2}% | {:.2}% | {:.2} | {} |",
            c.series.label(),
            c.rings,
            c.scenarios,
            100.0 * c.rel_mae_mean,
            100.0 * c.rel_mae_std,
            100.0 * c.noise_floor_mean,
            c.fit_seconds_mean,
            if c.on_pareto_front { "●" } else { "" }
        );
        if albedo {
            md += &match (c.albedo_error_mean, c.albedo_error_max) {
                (Some(m), Some(x)) => format!(" {:.2}% / {:.2}% |", 100.0 * m, 100.0 * x),
                _ => " |".to_string(),
            };
        }
        md += "\n";
    }
    md += "\n";
    if drawn("speed_vs_accuracy.png") {
        md += "![speed against accuracy](speed_vs_accuracy.png)\n\n";
    }
    md += "![error against distance](error_vs_distance.png)\n\n";
    if let Some(f) = s.auto_within_10_percent {
        let n = s.auto.len();
        let mean_t = s.auto.iter().map(|a| a.auto_fit_seconds).sum::<f64>() / n.max(1) as f64;
        md += &format!(
            "## `--rings auto`\n\nWithin 10% of the best fixed resolution's error on {:.0}% of {} scenarios \
             (goal: 80%); worst ratio to the best {:.3}; mean chosen rings {:.1} against {:.1} for the best \
             fixed resolution; mean stand-alone time (selection + fit) {:.1} s.\n\n\
             ![auto against best](auto_vs_best.png)\n\n",
            100.0 * f,
            n,
            s.auto
                .iter()
                .map(|a| a.auto_rel_mae / a.best_rel_mae)
                .fold(0.0, f64::max),
            s.auto.iter().map(|a| a.auto_rings as f64).sum::<f64>() / n.max(1) as f64,
            s.auto.iter().map(|a| a.best_rings as f64).sum::<f64>() / n.max(1) as f64,
            mean_t
        );
    }
    if let Some(sp) = &s.spheres {
        md += &format!(
            "## Sphere-light model\n\n{} scenarios; mean relMAE {:.2}% against {:.2}% for the envmap it \
             starts from; mean stand-alone time (envmap fit + sphere fit) {:.1} s. On the {} scenarios \
             whose lights all sit 1.5–5 m from the scene centre: relMAE within 2× the noise floor on {}, \
             every centre within 2% of its distance on {}, every power within 5% on {}; all three on \
             {} ({:.0}%; goal 90%).\n\n\
             | scenario | lights (true/fitted) | distances (m) | relMAE | envmap | noise floor | worst centre / distance | worst power error | time (s) |\n\
             |---|---:|---|---:|---:|---:|---:|---:|---:|\n",
            sp.scenarios,
            100.0 * sp.rel_mae_mean,
            100.0 * sp.envmap_rel_mae_mean,
            sp.fit_seconds_mean,
            sp.in_range,
            sp.in_range_within_2x_noise_floor,
            sp.in_range_centres_within_2_percent,
            sp.in_range_power_within_5_percent,
            sp.in_range_all_three,
            100.0 * sp.in_range_all_three as f64 / sp.in_range.max(1) as f64,
        );
        let pct = |x: Option<f64>| x.map_or("–".into(), |x| format!("{:.2}%", 100.0 * x));
        for r in &sp.rows {
            md += &format!(
                "| {}{} | {}/{} | {} | {:.2}% | {} | {} | {} | {} | {:.1} |\n",
                r.scenario,
                if r.in_range() { "" } else { " (out of range)" },
                r.true_lights,
                r.fitted_lights,
                r.distances
                    .iter()
                    .map(|d| format!("{d:.2}"))
                    .collect::<Vec<_>>()
                    .join(", "),
                100.0 * r.rel_mae,
                pct(r.envmap_rel_mae),
                pct(r.noise_floor),
                pct(r.worst_centre_fraction.map(f64::from)),
                pct(r.worst_power_error.map(f64::from)),
                r.fit_seconds
            );
        }
        md += "\n";
    }
    let mut worst: Vec<&&TrialRecord> = best.values().collect();
    worst.sort_by(|a, b| {
        b.rel_mae
            .unwrap_or(0.0)
            .total_cmp(&a.rel_mae.unwrap_or(0.0))
    });
    md += "Hardest scenarios (best relMAE over rings, first series):\n\n| scenario | lights | nearest distance / size | best rings | relMAE | noise floor |\n|---|---:|---:|---:|---:|---:|\n";
    for r in worst.iter().take(8) {
        md += &format!(
            "| {} | {} | {:.2} | {} | {:.2}% | {:.2}% |\n",
            r.scenario,
            r.lights.len(),
            r.lights
                .iter()
                .map(|l| l.distance_over_size)
                .fold(f32::INFINITY, f32::min),
            r.rings,
            100.0 * r.rel_mae.unwrap_or(0.0),
            100.0 * r.noise_floor_rel_mae.unwrap_or(0.0)
        );
    }
    md
}
