//! The paper's experiment: `scenarios`, `sweep` and `report`.

use std::io::IsTerminal;
use std::path::{Path, PathBuf};

use anyhow::bail;
use indicatif::{ProgressBar, ProgressStyle};
use serde_json::json;

use lightprobe::experiment::scenarios;
use lightprobe::imageio;
use lightprobe::scene::Scene;

use super::{ColourArg, FitAlbedoArg, SolverArg, flag_error, outln, prepare_out_dir, say};

#[derive(clap::Args)]
pub struct ScenariosArgs {
    /// The template sidecar: its glTF, views, image and settings are kept, its lights replaced.
    #[arg(long, default_value = "scenes/tabletop/tabletop.ron")]
    scene: PathBuf,
    /// How many scenarios.
    #[arg(long, default_value_t = 55)]
    count: usize,
    /// Random seed; the same seed gives the same scenarios.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Output folder for s00.ron, s01.ron, … and scenarios.json.
    #[arg(long, short)]
    out: PathBuf,
}

#[derive(clap::Args)]
pub struct SweepArgs {
    /// Scenario sidecars, or folders of them (every *.ron inside, sorted).
    #[arg(required = true)]
    scenarios: Vec<PathBuf>,
    /// Output folder: trials*.jsonl, and references/<scenario>/ rendered once and reused.
    #[arg(long, short)]
    out: PathBuf,
    /// Envmap resolutions (rings).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "3,5,7,9,11,13,15,17,19,21,23,25,27"
    )]
    rings: Vec<u32>,
    /// Solvers.
    #[arg(long, value_enum, value_delimiter = ',', default_value = "nnls")]
    solver: Vec<SolverArg>,
    /// Transport samples per pixel (over all rounds); references keep the sidecar's.
    #[arg(long, value_delimiter = ',', default_value = "512")]
    spp: Vec<u32>,
    /// Run one slice: the scenarios at positions ≡ i (mod n), 0 <= i < n, into
    /// trials.shard-i-of-n.jsonl (e.g. --shard $SLURM_ARRAY_TASK_ID/8).
    #[arg(long, default_value = "0/1")]
    shard: String,
    /// Smoothness weight (as for estimate).
    #[arg(long, default_value_t = 0.0)]
    smooth: f64,
    /// Ridge weight (as for estimate).
    #[arg(long, default_value_t = 1e-3)]
    ridge: f64,
    /// How NNLS treats a cell's three channels (as for estimate).
    #[arg(long, value_enum, default_value_t = ColourArg::PerChannel)]
    colour: ColourArg,
    /// Time budget per channel solve, seconds.
    #[arg(long, default_value_t = 60.0)]
    time_limit: f64,
    /// Also run a `--rings auto` trial per scenario, choosing among --rings.
    #[arg(long)]
    auto: bool,
    /// Also fit the sphere-light model (`estimate --model spheres`) per scenario, started from
    /// the envmap estimate with this many rings.
    #[arg(long, value_name = "RINGS")]
    spheres: Option<u32>,
    /// Fit with imperfect albedos: each value e (e.g. 0.05,0.1,0.2) scales every material's
    /// albedo per channel by a fixed random factor in [1 − e, 1 + e]; the estimate is judged
    /// in the true scene. 0 = the true albedos.
    #[arg(long, value_delimiter = ',', default_value = "0")]
    albedo_error: Vec<f32>,
    /// Beside every trial with a nonzero albedo error, one that fits the albedo (as `estimate
    /// --fit-albedo materials`); its records give the fitted albedo's error against the truth.
    #[arg(long, value_enum)]
    fit_albedo: Option<FitAlbedoArg>,
    /// Materials the albedo error leaves exact and the albedo fits trust (as `estimate
    /// --trust-albedo`).
    #[arg(long, value_delimiter = ',')]
    trust_albedo: Vec<String>,
    /// Exit 0 even when some trials failed (they are recorded either way).
    #[arg(long)]
    allow_failures: bool,
    /// No progress bar.
    #[arg(long, short)]
    quiet: bool,
}

pub fn scenarios(a: ScenariosArgs) -> anyhow::Result<()> {
    if !(1..=10_000).contains(&a.count) {
        bail!("--count must be between 1 and 10000");
    }
    let scene = Scene::load(&a.scene)?;
    let list = scenarios::generate(&scene, a.count, a.seed)?;
    // Written after the folder is prepared, but made before: a template that cannot be one
    // fails here and leaves no folder.
    let texts = list
        .iter()
        .map(|sc| scenarios::sidecar_text(&a.scene, sc, &a.out))
        .collect::<lightprobe::Result<Vec<_>>>()?;
    let _lock = prepare_out_dir(&a.out, lightprobe::output::LOCK_FILE)?;
    // A folder left with sNN.ron files of a larger set would mix two sets in a sweep.
    let ours: Vec<String> = list.iter().map(|s| format!("{}.ron", s.name)).collect();
    for e in std::fs::read_dir(&a.out)
        .map_err(|e| lightprobe::Error::io(&a.out, e))?
        .flatten()
    {
        let name = e.file_name().to_string_lossy().into_owned();
        let numbered = name.strip_prefix('s').and_then(|r| r.strip_suffix(".ron"));
        if numbered.is_some_and(|n| n.chars().all(|c| c.is_ascii_digit())) && !ours.contains(&name)
        {
            bail!(
                "{}: holds {name}, which is not one of these {} scenarios; use an empty folder",
                a.out.display(),
                list.len()
            );
        }
    }
    for (sc, text) in list.iter().zip(&texts) {
        imageio::write_bytes(&a.out.join(format!("{}.ron", sc.name)), text.as_bytes())?;
    }
    let manifest = json!({
        "lightprobe_version": lightprobe::VERSION,
        "template": a.scene,
        "seed": a.seed,
        "scenarios": list,
    });
    let text = serde_json::to_string_pretty(&manifest)? + "\n";
    imageio::write_bytes(&a.out.join("scenarios.json"), text.as_bytes())?;
    let two = list.iter().filter(|s| s.lights.len() == 2).count();
    outln!(
        "{} scenarios ({} with two lights) in {}",
        list.len(),
        two,
        a.out.display()
    )?;
    Ok(())
}

/// Sidecars named on the command line: files as given, folders as their *.ron files, sorted.
fn sidecar_files(args: &[PathBuf]) -> anyhow::Result<Vec<PathBuf>> {
    let mut files = Vec::new();
    for p in args {
        if p.is_dir() {
            let mut v: Vec<PathBuf> = std::fs::read_dir(p)
                .map_err(|e| lightprobe::Error::io(p, e))?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|f| f.extension().is_some_and(|x| x == "ron"))
                .collect();
            if v.is_empty() {
                bail!("{}: holds no .ron sidecars", p.display());
            }
            v.sort();
            files.extend(v);
        } else {
            files.push(p.clone());
        }
    }
    Ok(files)
}

pub fn sweep(a: SweepArgs) -> anyhow::Result<()> {
    use lightprobe::experiment::sweep::{self, Shard, SweepSettings};
    if !(a.smooth.is_finite() && a.smooth >= 0.0) {
        bail!("--smooth must be a finite number >= 0");
    }
    if !(a.ridge.is_finite() && a.ridge >= 0.0) {
        bail!("--ridge must be a finite number >= 0");
    }
    if !(a.time_limit.is_finite() && a.time_limit > 0.0 && a.time_limit <= 1e6) {
        bail!("--time-limit must be a positive number of seconds, at most 1e6");
    }
    let settings = SweepSettings {
        rings: a.rings.clone(),
        solvers: a.solver.iter().map(|&s| s.into()).collect(),
        spp: a.spp.clone(),
        shard: Shard::parse(&a.shard).map_err(flag_error)?,
        smooth: a.smooth,
        ridge: a.ridge,
        colour: a.colour.into(),
        time_limit: std::time::Duration::from_secs_f64(a.time_limit),
        auto: a.auto,
        albedo_errors: a.albedo_error.clone(),
        spheres: a.spheres,
        fit_albedo: match a.fit_albedo {
            None => false,
            Some(FitAlbedoArg::Materials) => true,
            Some(FitAlbedoArg::Texels) => anyhow::bail!(
                "sweep --fit-albedo takes `materials`: the scenarios' albedo errors are per material, with no texture's shading to correct"
            ),
        },
        trust_albedo: a.trust_albedo.clone(),
    };

    let files = sidecar_files(&a.scenarios)?;
    // Shards of one sweep may share the folder; each locks its own trials file.
    let _lock = prepare_out_dir(&a.out, &format!(".{}.lock", settings.shard.file_name()))?;
    // On a terminal a bar; elsewhere (batch and CI logs, where a bar shows nothing) a line
    // when the sweep starts, at every tenth of its trials and for every failed trial.
    let terminal = std::io::stderr().is_terminal();
    let log = !a.quiet && !terminal;
    let started = std::time::Instant::now();
    let mut logged_tenths = None;
    let bar = if a.quiet || !terminal {
        ProgressBar::hidden()
    } else {
        let b = ProgressBar::new(0);
        b.set_style(
            ProgressStyle::with_template(
                "{pos}/{len} trials [{bar:30}] {elapsed_precise} eta {eta}  {msg}",
            )
            .expect("a valid template")
            .progress_chars("=> "),
        );
        b
    };
    let summary = sweep::run(&files, &settings, &a.out, &mut |p| {
        bar.set_length(p.total as u64);
        bar.set_position(p.done as u64);
        if p.skipped > 0 && p.done == p.skipped {
            bar.reset_eta();
        }
        let last = p.record.map(|r| {
            format!(
                "{} {} rings: relMAE {}",
                r.scenario,
                r.rings,
                r.rel_mae
                    .map_or("failed".to_string(), |e| format!("{:.2}%", 100.0 * e))
            )
        });
        match &last {
            Some(text) => bar.set_message(text.clone()),
            None => bar.set_message(p.phase.to_string()),
        }
        if log {
            let tenths = (p.done * 10).checked_div(p.total).unwrap_or(10);
            let failed = p.record.is_some_and(|r| r.rel_mae.is_none());
            if logged_tenths.is_none_or(|t| tenths > t) || failed {
                logged_tenths = Some(tenths);
                say(&format!(
                    "lightprobe: sweep: {}/{} trials ({} done before) after {:.0} s{}",
                    p.done,
                    p.total,
                    p.skipped,
                    started.elapsed().as_secs_f64(),
                    last.map_or(String::new(), |t| format!("; last {t}"))
                ));
            }
        }
    })
    .map_err(flag_error)?;
    bar.finish_and_clear();
    outln!(
        "{} trials planned, {} already done, {} run ({} failed, {} not converged) in {:.1} s: {}",
        summary.planned,
        summary.skipped,
        summary.ran,
        summary.failed,
        summary.not_converged,
        summary.wall_seconds,
        summary.trials_file.display()
    )?;
    if summary.failed + summary.not_converged > 0 && !a.allow_failures {
        bail!(
            "{} trials failed and {} did not converge (see \"status\" and \"error\" in {}); pass --allow-failures to exit 0 anyway",
            summary.failed,
            summary.not_converged,
            summary.trials_file.display()
        );
    }
    Ok(())
}

/// `report`: charts and a summary of a sweep's trials.
pub fn report(dir: &Path, json: bool) -> anyhow::Result<()> {
    let s = lightprobe::experiment::report::report(dir)?;
    if json {
        outln!("{}", serde_json::to_string_pretty(&s)?)?;
    } else {
        outln!(
            "{} trials ({} failed) over {} scenarios: {} in {}",
            s.trials,
            s.failed,
            s.scenarios,
            s.charts
                .iter()
                .map(|c| c.file_name().unwrap_or_default().to_string_lossy())
                .collect::<Vec<_>>()
                .join(", "),
            dir.display()
        )?;
    }
    Ok(())
}
