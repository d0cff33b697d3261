//! A sweep of estimates: every scenario × samples × rings × solver, as the `estimate` command
//! would run it (same seeds, same figures), one JSON line per trial.
//!
//! - **Shared work.** References and the noise floor are rendered once per scenario and kept
//!   under `OUT/references/<scenario>/`. Scenarios that differ only in their lights share the
//!   geometry and the BVH; a trial's fit is the stand-alone estimate's.
//! - **Resumable.** Finished trials are read back from `OUT/trials*.jsonl` and skipped; a line
//!   cut short by a crash is ignored (and the trial run again).
//! - **Shardable.** `Shard { index: i, count: n }` runs the scenarios whose position in the list
//!   is ≡ i (mod n), into `trials.shard-i-of-n.jsonl`, so a job array can spread the sweep and
//!   the report merges the files.

use std::collections::{HashMap, HashSet};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::estimate::Solver;
use crate::estimate::job::{
    self, EstimateReport, EstimateSettings, FitStatus, Job, LightModel, Rings,
};
use crate::estimate::pipeline::{self, SeenViews};
use crate::estimate::recovery::SphereRecovery;
use crate::estimate::select::Selection;
use crate::estimate::spheres::LightStatus;
use crate::imageio;
use crate::metrics::Metrics;
use crate::render::{Lights, RenderSettings, Renderer};
use crate::sampling::mix64;
use crate::scene::sidecar::{self, Sidecar};
use crate::scene::{Camera, Scene, SphereLight};

/// Which slice of the scenarios this process runs: those at positions ≡ `index` (mod `count`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Shard {
    pub index: u32,
    pub count: u32,
}

impl Shard {
    pub const ALL: Shard = Shard { index: 0, count: 1 };

    /// Parses `i/n` with 0 ≤ i < n.
    pub fn parse(s: &str) -> Result<Shard> {
        let bad = || Error::Setting {
            name: "shard",
            expected: "i/n with 0 <= i < n, e.g. 0/4".into(),
            got: format!("{s:?}"),
        };
        let (i, n) = s.split_once('/').ok_or_else(bad)?;
        let (index, count) = (
            i.trim().parse().map_err(|_| bad())?,
            n.trim().parse().map_err(|_| bad())?,
        );
        if count == 0 || index >= count {
            return Err(bad());
        }
        Ok(Shard { index, count })
    }

    /// The JSON-lines file this shard appends to.
    pub fn file_name(&self) -> String {
        if self.count == 1 {
            "trials.jsonl".to_string()
        } else {
            format!("trials.shard-{}-of-{}.jsonl", self.index, self.count)
        }
    }
}

/// What to sweep.
#[derive(Debug, Clone)]
pub struct SweepSettings {
    pub rings: Vec<u32>,
    pub solvers: Vec<Solver>,
    /// Transport samples per pixel (over all rounds); references keep the sidecar's spp.
    pub spp: Vec<u32>,
    pub shard: Shard,
    pub smooth: f64,
    pub ridge: f64,
    pub colour: crate::estimate::Colour,
    pub time_limit: Duration,
    /// Also run a `--rings auto` trial per scenario, choosing among `rings`.
    pub auto: bool,
    /// Albedo errors to fit with (0 = the true albedos): every material's albedo is scaled per
    /// channel by a fixed random factor in [1 − e, 1 + e]; the estimate is judged in the true
    /// scene.
    pub albedo_errors: Vec<f32>,
    /// Also run the sphere-light model per scenario (`estimate --model spheres`), started
    /// from an envmap estimate with this many rings.
    pub spheres: Option<u32>,
    /// Beside every trial with an albedo error, one that fits the albedo
    /// (`estimate --fit-albedo materials`).
    pub fit_albedo: bool,
    /// Materials whose albedo the perturbation leaves exact and the albedo fits trust
    /// (`--trust-albedo`).
    pub trust_albedo: Vec<String>,
}

/// How a trial ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Status {
    Ok,
    /// The solver stopped at its iteration or time limit before its optimality test passed.
    NotConverged,
    /// The estimate failed (the error says why); no figures.
    Failed,
}

/// A view's figures.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ViewFigures {
    pub view: String,
    /// None where the figure is not finite (e.g. a view whose reference is black).
    pub rel_mae: Option<f64>,
    pub rel_mse: Option<f64>,
    pub rmse: Option<f64>,
    pub psnr: Option<f64>,
    pub noise_floor_rel_mae: Option<f64>,
}

/// A figure for JSON: None unless finite (JSON has no NaN or Inf).
fn fin(x: f64) -> Option<f64> {
    x.is_finite().then_some(x)
}

/// A true light as seen from the scene centre.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct LightFigures {
    /// Centre distance from the scene centre, metres.
    pub distance: f32,
    /// Distance over the scene's size (its larger horizontal extent).
    pub distance_over_size: f32,
    pub elevation_degrees: f32,
    /// Estimated direction's error and power ratio, when a cluster matched it.
    pub angle_error_degrees: Option<f32>,
    pub power_ratio: Option<f32>,
}

/// Seconds per phase.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct Timings {
    /// What the fit costs on its own (`estimate --fit-only`'s fit): choosing the resolution
    /// (with `--rings auto`), fitting the albedo (with `--fit-albedo`), the transport and the
    /// solves.
    pub fit_seconds: f64,
    pub transport_seconds: f64,
    pub solve_seconds: f64,
    pub rerender_seconds: f64,
    /// This trial's wall time in the sweep (references not included).
    pub trial_seconds: f64,
    /// `--rings auto`: choosing the resolution (included in `fit_seconds`).
    #[serde(default)]
    pub selection_seconds: f64,
    /// `--fit-albedo`: the fits and passes before the last fit (included in `fit_seconds`).
    #[serde(default)]
    pub albedo_seconds: f64,
}

/// One trial: a line of `trials*.jsonl`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct TrialRecord {
    pub id: String,
    pub scenario: String,
    pub file: PathBuf,
    pub rings: u32,
    pub cells: usize,
    pub solver: Solver,
    pub spp: u32,
    pub rounds: u32,
    pub status: Status,
    #[serde(default)]
    pub error: Option<String>,
    /// Mean over views of the estimate's relMAE.
    pub rel_mae: Option<f64>,
    pub noise_floor_rel_mae: Option<f64>,
    pub views: Vec<ViewFigures>,
    pub lights: Vec<LightFigures>,
    /// Solver iterations, summed over channels and rounds.
    pub iterations: usize,
    /// Largest KKT violation over channels.
    pub kkt_violation: f64,
    pub timings: Timings,
    pub transport_bytes: usize,
    /// Peak resident memory of the sweep process so far.
    pub peak_bytes: u64,
    pub threads: usize,
    /// The albedo error the fit lived with (0 = true albedos).
    #[serde(default)]
    pub albedo_error: f32,
    /// The trial fitted the albedo (`--fit-albedo materials`).
    #[serde(default)]
    pub fit_albedo: bool,
    /// With `fit_albedo`: the largest and the mean relative error, over the fitted materials
    /// and channels, of the fitted albedo against the true one.
    #[serde(default)]
    pub albedo_max_error: Option<f64>,
    #[serde(default)]
    pub albedo_mean_error: Option<f64>,
    /// The scenario and settings the trial ran with; resuming refuses a mismatch.
    #[serde(default)]
    pub fingerprint: String,
    /// The `--rings auto` trial: how the resolution was chosen.
    #[serde(default)]
    pub auto: Option<Selection>,
    /// The sphere-model trial: its lights and their recovery (the trial's errors are the
    /// sphere model's; `rings` is the initialising envmap's).
    #[serde(default)]
    pub spheres: Option<SphereTrial>,
    /// How the envmap's colour holds together, against the scenario's lights.
    #[serde(default)]
    pub colour: Option<crate::estimate::recovery::ColourFigures>,
}

/// A sphere-model trial's own figures.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SphereTrial {
    /// Lights fitted (the envmap's bright clusters, at most 3) and how each ended.
    pub statuses: Vec<LightStatus>,
    /// Per true light, brightest first.
    pub recovery: Vec<SphereRecovery>,
    /// relMAE of the initialising envmap estimate, for contrast.
    pub envmap_rel_mae: Option<f64>,
    /// The sphere fits alone (search + refinement, every candidate count), seconds; the
    /// envmap fit is `fit_seconds`.
    pub sphere_fit_seconds: f64,
    /// How the number of lights was chosen (held-out pixels, as `estimate --model spheres`).
    #[serde(default)]
    pub selection: Option<crate::estimate::select::ModelSelection>,
    pub renders: usize,
    pub iterations: usize,
}

/// Trial identity: what resuming matches on (`rings` None: the `--rings auto` trial; `spheres`:
/// the sphere model started from that resolution).
pub fn trial_id(
    scenario: &str,
    spp: u32,
    rings: Option<u32>,
    solver: Solver,
    albedo_error: f32,
    spheres: bool,
    fit_albedo: bool,
) -> String {
    let r = rings.map_or("auto".to_string(), |r| format!("rings{r}"));
    let r = if spheres {
        format!("spheres-from-{r}")
    } else {
        r
    };
    let a = if albedo_error > 0.0 {
        format!("/albedo{}", (albedo_error * 100.0).round())
    } else {
        String::new()
    };
    let f = if fit_albedo { "/fitalbedo" } else { "" };
    format!("{scenario}/spp{spp}/{r}/{solver:?}{a}{f}").to_lowercase()
}

/// Seed of the albedo perturbation (the same for every scenario).
const ALBEDO_SEED: u64 = 0x00A1_BED0;

/// Reads every `trials*.jsonl` in `dir` (all shards). Lines that do not parse (a write cut
/// short) are skipped; for a trial recorded twice, the last line wins.
pub fn read_records(dir: &Path) -> Result<Vec<TrialRecord>> {
    let mut files: Vec<PathBuf> = match std::fs::read_dir(dir) {
        Ok(rd) => rd
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| {
                p.file_name()
                    .and_then(|n| n.to_str())
                    .is_some_and(|n| n.starts_with("trials") && n.ends_with(".jsonl"))
            })
            .collect(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(Error::io(dir, e)),
    };
    files.sort();
    let mut by_id: HashMap<String, usize> = HashMap::new();
    let mut out: Vec<TrialRecord> = Vec::new();
    for f in files {
        let bytes = std::fs::read(&f).map_err(|e| Error::io(&f, e))?;
        let lines: Vec<&[u8]> = bytes.split(|&c| c == b'\n').collect();
        for (i, line) in lines.iter().enumerate() {
            if line.iter().all(u8::is_ascii_whitespace) {
                continue;
            }
            let parsed = std::str::from_utf8(line)
                .ok()
                .and_then(|l| serde_json::from_str::<TrialRecord>(l).ok());
            let Some(r) = parsed else {
                // Only the last line can be cut short by a crash (see `open_append`).
                if i + 1 == lines.len() {
                    continue;
                }
                return Err(Error::file_at(
                    &f,
                    i + 1,
                    1,
                    "is not a trial record (a JSON line written by `lightprobe sweep`)",
                ));
            };
            match by_id.get(&r.id) {
                Some(&k) => out[k] = r,
                None => {
                    by_id.insert(r.id.clone(), out.len());
                    out.push(r);
                }
            }
        }
    }
    Ok(out)
}

/// A sidecar of the sweep.
struct ScenarioFile {
    name: String,
    path: PathBuf,
    lights: Vec<SphereLight>,
    /// Index of its scene group (same sidecar apart from the lights).
    group: usize,
    /// [`scenario_fingerprint`]: what its references depend on.
    fingerprint: String,
}

/// The sidecar with its lights removed and its paths made absolute: equal keys, equal scenes.
fn scene_key(sc: &Sidecar, path: &Path) -> Result<String> {
    let base = Sidecar::base_dir(path);
    let abs = |p: &Path| std::path::absolute(base.join(p)).map_err(|e| Error::io(p, e));
    let mut k = sc.clone();
    k.lights.clear();
    k.gltf = abs(&sc.gltf)?;
    for source in k.albedo.values_mut() {
        if let sidecar::AlbedoSource::Map(p) = source {
            *p = abs(p)?;
        }
    }
    ron::to_string(&k).map_err(|e| Error::file(path, format!("cannot fingerprint: {e}")))
}

/// A scenario's references, geometry masks and noise floor.
struct Observed<'a> {
    /// Every view, with its reference and mask.
    seen: SeenViews<'a>,
    /// relMAE of the noise floor, per view.
    noise_floor: Vec<f64>,
}

/// Progress of a sweep, reported after each trial.
pub struct Progress<'a> {
    pub done: usize,
    pub total: usize,
    /// Trials found finished in the output folder and skipped.
    pub skipped: usize,
    pub record: Option<&'a TrialRecord>,
    /// What is being worked on, for a progress bar's message.
    pub phase: &'a str,
}

/// What a sweep did.
#[derive(Debug, Clone, Serialize)]
pub struct Summary {
    pub planned: usize,
    pub skipped: usize,
    pub ran: usize,
    /// Failed trials of the plan, this run's and those found recorded.
    pub failed: usize,
    /// Trials of the plan whose solver stopped at its limits, this run's and recorded ones.
    pub not_converged: usize,
    pub wall_seconds: f64,
    pub trials_file: PathBuf,
}

/// Runs the trials of `settings.shard` that `out` does not hold yet.
pub fn run(
    files: &[PathBuf],
    settings: &SweepSettings,
    out: &Path,
    progress: &mut dyn FnMut(Progress),
) -> Result<Summary> {
    let t_all = Instant::now();
    let (scenarios, group_files) = load_scenarios(files)?;
    let axes = Axes::of(settings)?;
    let plan = plan(&scenarios, &axes, settings);
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    let fingerprint = |s: usize, solver: Solver| {
        // The colour mode changes NNLS fits only.
        let colour = match (solver, settings.colour) {
            (Solver::Nnls, crate::estimate::Colour::Together) => " colour=together",
            _ => "",
        };
        // The materials left exact change every perturbed trial's scene.
        let colour = if settings.trust_albedo.is_empty() {
            colour.to_string()
        } else {
            format!("{colour} exact_albedo={}", settings.trust_albedo.join(","))
        };
        format!(
            // The transport method: a sweep started by another cannot be resumed into this one.
            "{} smooth={} ridge={}{colour} time_limit={}s rounds={} transport=streamed-pilot-parts",
            scenarios[s].fingerprint,
            settings.smooth,
            settings.ridge,
            settings.time_limit.as_secs_f64(),
            solver.default_rounds()
        )
    };
    let id = |t: &Trial| {
        trial_id(
            &scenarios[t.scenario].name,
            t.spp,
            t.rings,
            t.solver,
            axes.albedo_errors[t.albedo],
            t.spheres,
            t.fit_albedo,
        )
    };
    let (todo, failed_before, not_converged_before) = pending(&plan, out, &id, &fingerprint)?;
    let skipped = plan.len() - todo.len();
    let trials_file = out.join(settings.shard.file_name());
    let mut summary = Summary {
        planned: plan.len(),
        skipped,
        ran: 0,
        failed: failed_before,
        not_converged: not_converged_before,
        wall_seconds: 0.0,
        trials_file: trials_file.clone(),
    };
    progress(Progress {
        done: skipped,
        total: plan.len(),
        skipped,
        record: None,
        phase: "loading",
    });
    if todo.is_empty() {
        summary.wall_seconds = t_all.elapsed().as_secs_f64();
        return Ok(summary);
    }

    // ---- Scenes: loaded and BVH-built once per group ----
    let needed: HashSet<usize> = todo.iter().map(|t| scenarios[t.scenario].group).collect();
    let scenes: Vec<Option<Scene>> = (0..group_files.len())
        .map(|g| {
            needed
                .contains(&g)
                .then(|| Scene::load(&group_files[g]))
                .transpose()
        })
        .collect::<Result<_>>()?;
    check_memory(&todo, &scenarios, &scenes, &axes, settings, &id)?;
    // A trusted name the scene lacks would leave every material perturbed and fail every
    // fitting trial: refused before the first.
    for (g, scene) in scenes.iter().enumerate() {
        let Some(scene) = scene else { continue };
        if let Some(name) = settings
            .trust_albedo
            .iter()
            .find(|n| !scene.materials.iter().any(|m| &m.name == *n))
        {
            return Err(Error::file(
                &group_files[g],
                format!("trusted albedo names material {name:?}, which this scene does not have"),
            ));
        }
    }
    let mut sink = open_append(&trials_file)?;
    let no_lights = Lights::new(Vec::new());
    let renderers: Vec<Option<Renderer>> = scenes
        .iter()
        .map(|s| s.as_ref().map(|s| Renderer::new(s, &no_lights)))
        .collect();
    // The scenes the fits see: per group and albedo error (index 0 of a zero error: the scene).
    let perturbed: Vec<Vec<Option<Scene>>> = scenes
        .iter()
        .map(|s| {
            axes.albedo_errors
                .iter()
                .map(|&e| {
                    s.as_ref().filter(|_| e > 0.0).map(|s| {
                        super::with_albedo_error(s, e, ALBEDO_SEED, &settings.trust_albedo)
                    })
                })
                .collect()
        })
        .collect();
    let ctx = Context {
        scenarios: &scenarios,
        scenes: &scenes,
        renderers: &renderers,
        perturbed: &perturbed,
        no_lights: &no_lights,
        axes: &axes,
        settings,
        out,
    };
    let mut caches = Caches::default();
    for (k, &trial) in todo.iter().enumerate() {
        let t_trial = Instant::now();
        let mut phase = |phase: &str| {
            progress(Progress {
                done: skipped + k,
                total: plan.len(),
                skipped,
                record: None,
                phase,
            })
        };
        let mut record = run_trial(&ctx, &mut caches, trial, &mut phase)?;
        record.fingerprint = fingerprint(trial.scenario, trial.solver);
        summary.failed += (record.status == Status::Failed) as usize;
        summary.not_converged += (record.status == Status::NotConverged) as usize;
        record.timings.trial_seconds = t_trial.elapsed().as_secs_f64();
        record.peak_bytes = crate::memory::peak_bytes();
        let line =
            serde_json::to_string(&record).map_err(|e| Error::Invalid(e.to_string()))? + "\n";
        sink.write_all(line.as_bytes())
            .and_then(|_| sink.flush())
            .map_err(|e| Error::io(&trials_file, e))?;
        summary.ran += 1;
        progress(Progress {
            done: skipped + k + 1,
            total: plan.len(),
            skipped,
            record: Some(&record),
            phase: "",
        });
    }
    summary.wall_seconds = t_all.elapsed().as_secs_f64();
    // The run's wall time (references included), for the report's total.
    let run = serde_json::json!({
        "shard": settings.shard.file_name(),
        "ran": summary.ran,
        "wall_seconds": summary.wall_seconds,
        "threads": rayon::current_num_threads(),
    });
    let log_path = out.join(settings.shard.file_name().replacen("trials", "runs", 1));
    let mut log = open_append(&log_path)?;
    writeln!(log, "{run}").map_err(|e| Error::io(&log_path, e))?;
    Ok(summary)
}

/// The trials of `plan` that `out` does not hold yet, and how many of those it holds failed
/// or did not converge. A trial recorded with another fingerprint (other settings or another
/// scenario file) is an error: resuming must not mix two sweeps.
fn pending(
    plan: &[Trial],
    out: &Path,
    id: &dyn Fn(&Trial) -> String,
    fingerprint: &dyn Fn(usize, Solver) -> String,
) -> Result<(Vec<Trial>, usize, usize)> {
    let done: HashMap<String, TrialRecord> = read_records(out)?
        .into_iter()
        .map(|r| (r.id.clone(), r))
        .collect();
    let mut todo = Vec::new();
    let (mut failed_before, mut not_converged_before) = (0, 0);
    for &trial in plan {
        let id = id(&trial);
        let want = fingerprint(trial.scenario, trial.solver);
        match done.get(&id) {
            None => todo.push(trial),
            // Records from before fingerprints ("") are taken as they are.
            Some(r) if !r.fingerprint.is_empty() && r.fingerprint != want => {
                return Err(Error::file(
                    out,
                    format!(
                        "holds trial {id} run with other settings or another scenario file \
                         ({} ≠ {want}); use another output folder, or remove its lines to rerun it",
                        r.fingerprint
                    ),
                ));
            }
            Some(r) => {
                failed_before += (r.status == Status::Failed) as usize;
                not_converged_before += (r.status == Status::NotConverged) as usize;
            }
        }
    }
    Ok((todo, failed_before, not_converged_before))
}

/// The scenario sidecars, each with its scene group (same sidecar apart from the lights),
/// and one sidecar file per group.
fn load_scenarios(files: &[PathBuf]) -> Result<(Vec<ScenarioFile>, Vec<PathBuf>)> {
    let mut keys: Vec<String> = Vec::new();
    let mut group_files: Vec<PathBuf> = Vec::new();
    let mut scenarios: Vec<ScenarioFile> = Vec::new();
    let mut names = HashSet::new();
    for f in files {
        let sc = Sidecar::load(f)?;
        let name = f
            .file_stem()
            .and_then(|s| s.to_str())
            .ok_or_else(|| Error::file(f, "has no file name"))?
            .to_string();
        if !names.insert(name.clone()) {
            return Err(Error::file(
                f,
                format!("another scenario is also named {name:?}"),
            ));
        }
        if sc.lights.is_empty() {
            return Err(Error::file(
                f,
                "has no sphere lights to render references from",
            ));
        }
        let key = scene_key(&sc, f)?;
        let group = match keys.iter().position(|k| *k == key) {
            Some(g) => g,
            None => {
                keys.push(key);
                group_files.push(f.clone());
                keys.len() - 1
            }
        };
        let lights = sc.sphere_lights();
        scenarios.push(ScenarioFile {
            name,
            path: f.clone(),
            fingerprint: scenario_fingerprint(&keys[group], &lights),
            lights,
            group,
        });
    }
    Ok((scenarios, group_files))
}

/// The sweep's axes, checked, repeats removed.
struct Axes {
    rings: Vec<u32>,
    spp: Vec<u32>,
    solvers: Vec<Solver>,
    /// At least one (0: the true albedos).
    albedo_errors: Vec<f32>,
}

impl Axes {
    fn of(settings: &SweepSettings) -> Result<Axes> {
        let named = |name| move |&r: &u32| (name, r);
        let rings = settings.rings.iter().map(named("rings"));
        for (name, r) in rings.chain(settings.spheres.iter().map(named("spheres"))) {
            if !(1..=crate::envmap::MAX_RINGS).contains(&r) {
                return Err(Error::Setting {
                    name,
                    expected: format!("between 1 and {}", crate::envmap::MAX_RINGS),
                    got: r.to_string(),
                });
            }
        }
        for &s in &settings.spp {
            if !(1..=sidecar::MAX_SPP).contains(&s) {
                return Err(Error::Setting {
                    name: "spp",
                    expected: format!("between 1 and {}", sidecar::MAX_SPP),
                    got: s.to_string(),
                });
            }
        }
        let albedo_errors = if settings.albedo_errors.is_empty() {
            vec![0.0]
        } else {
            dedup(&settings.albedo_errors)
        };
        if let Some(e) = albedo_errors.iter().find(|e| {
            !(e.is_finite()
                && (0.0..1.0).contains(*e)
                && (**e * 100.0 - (**e * 100.0).round()).abs() < 1e-3)
        }) {
            return Err(Error::Setting {
                name: "albedo error",
                expected: "a whole percentage in [0, 1) (e.g. 0.05)".into(),
                got: e.to_string(),
            });
        }
        if settings.fit_albedo && !albedo_errors.iter().any(|&e| e > 0.0) {
            return Err(Error::Invalid(
                "fitting the albedo adds trials beside the nonzero albedo errors, and none is \
                 given (--albedo-error 0.2, say)"
                    .into(),
            ));
        }
        // What every trial's estimate checks, once for the sweep (a bad value would otherwise
        // fail every trial, and the failures would count as done).
        for &solver in &settings.solvers {
            let spp = settings.spp.first().copied().unwrap_or(1);
            let rings = Rings::Auto(settings.rings.clone());
            trial_settings(settings, solver, spp, rings, false, settings.fit_albedo).check()?;
        }
        Ok(Axes {
            rings: dedup(&settings.rings),
            spp: dedup(&settings.spp),
            solvers: dedup(&settings.solvers),
            albedo_errors,
        })
    }
}

/// This shard's trials: per spp and albedo error, the fixed resolutions, then the `--rings
/// auto` trial, then the sphere model; within each, every solver over every scenario.
fn plan(scenarios: &[ScenarioFile], axes: &Axes, settings: &SweepSettings) -> Vec<Trial> {
    let mine: Vec<usize> = (0..scenarios.len())
        .filter(|i| *i as u32 % settings.shard.count == settings.shard.index)
        .collect();
    let mut plan = Vec::new();
    for &spp in &axes.spp {
        for a in 0..axes.albedo_errors.len() {
            let fixed = axes.rings.iter().map(|&r| (Some(r), false));
            let auto = settings.auto.then_some((None, false));
            let spheres = settings.spheres.map(|r| (Some(r), true));
            let fits: &[bool] = if settings.fit_albedo && axes.albedo_errors[a] > 0.0 {
                &[false, true]
            } else {
                &[false]
            };
            for (rings, spheres) in fixed.chain(auto).chain(spheres) {
                for &fit_albedo in fits {
                    for &solver in &axes.solvers {
                        for &s in &mine {
                            plan.push(Trial {
                                scenario: s,
                                spp,
                                rings,
                                solver,
                                albedo: a,
                                spheres,
                                fit_albedo,
                            });
                        }
                    }
                }
            }
        }
    }
    plan
}

/// What every trial of a run shares.
struct Context<'a> {
    scenarios: &'a [ScenarioFile],
    /// Per scene group: loaded where a pending trial needs it.
    scenes: &'a [Option<Scene>],
    /// Per scene group: its BVH (no lights).
    renderers: &'a [Option<Renderer<'a>>],
    /// Per scene group and albedo error: the scene the fits see, if perturbed.
    perturbed: &'a [Vec<Option<Scene>>],
    no_lights: &'a Lights,
    axes: &'a Axes,
    settings: &'a SweepSettings,
    out: &'a Path,
}

/// What trials hand on to later ones: each scenario's references.
#[derive(Default)]
struct Caches<'a> {
    observed: HashMap<usize, Arc<Observed<'a>>>,
}

/// Runs one trial: its scenario's references (once, kept on disk), then one estimate job; a
/// failed estimate is a failed record, not an error. The
/// record's `fingerprint` is the caller's to fill.
fn run_trial<'a>(
    ctx: &Context<'a>,
    caches: &mut Caches<'a>,
    trial: Trial,
    phase: &mut dyn FnMut(&str),
) -> Result<TrialRecord> {
    let Trial {
        scenario: s,
        spp,
        rings: rings_plan,
        solver,
        albedo: a,
        spheres,
        fit_albedo,
    } = trial;
    let (settings, out) = (ctx.settings, ctx.out);
    let sf = &ctx.scenarios[s];
    let scene = ctx.scenes[sf.group].as_ref().expect("loaded above");
    let base = ctx.renderers[sf.group].as_ref().expect("built above");
    let views: Vec<&Camera> = scene.cameras.iter().collect();
    let render = RenderSettings::from_scene(&scene.settings);
    let lights = Lights::new(sf.lights.clone());
    let renderer = base.with_lights(&lights);
    // What the fit sees: the scene, or its albedo-perturbed twin (same BVH).
    let fit_renderer = match &ctx.perturbed[sf.group][a] {
        Some(p) => base.with_scene(p, ctx.no_lights),
        None => base.with_lights(ctx.no_lights),
    };
    // References, masks and noise floor: once per scenario, kept on disk.
    let obs = match caches.observed.get(&s) {
        Some(o) => o.clone(),
        None => {
            phase(&format!("{} references", sf.name));
            let o = Arc::new(observe(
                &renderer,
                &views,
                &render,
                &out.join("references").join(&sf.name),
                &sf.fingerprint,
            )?);
            caches.observed.insert(s, o.clone());
            o
        }
    };

    let rings = match rings_plan {
        Some(r) => Rings::Fixed(r),
        None => Rings::Auto(ctx.axes.rings.clone()),
    };
    let estimate = trial_settings(settings, solver, spp, rings, spheres, fit_albedo);
    let id = trial_id(
        &sf.name,
        spp,
        rings_plan,
        solver,
        ctx.axes.albedo_errors[a],
        spheres,
        fit_albedo,
    );
    phase(&id);
    let (lo, hi) = scene.mesh.bounds();
    let job = Job {
        fit: &fit_renderer,
        truth: &renderer,
        seen: &obs.seen,
        render: &render,
        settings: &estimate,
        center: scene.center(),
        size: (hi.x - lo.x).max(hi.z - lo.z).max(1e-3),
    };
    let result = job::run(&job, &());
    let mut record = blank_record(
        id,
        sf,
        trial,
        &estimate,
        pipeline_mean(&obs.noise_floor),
        light_figures(&sf.lights, job.center, job.size),
        ctx.axes.albedo_errors[a],
    );
    match result {
        Err(e) => {
            record.status = Status::Failed;
            record.error = Some(e.to_string());
        }
        Ok(est) => {
            if let Some(a) = &est.report.albedo {
                (record.albedo_max_error, record.albedo_mean_error) =
                    albedo_errors(a, &fit_renderer.scene.materials, &scene.materials);
            }
            fill_record(
                &mut record,
                est.report,
                &obs.noise_floor,
                (&sf.lights, job.center),
            )
        }
    }
    Ok(record)
}

/// The largest and the mean relative error, over the fitted materials and their channels, of
/// the fitted albedo (the `given` materials' times their multipliers) against the `truth`'s
/// (`None` without a fitted material).
fn albedo_errors(
    report: &crate::estimate::albedo::AlbedoReport,
    given: &[crate::scene::Material],
    truth: &[crate::scene::Material],
) -> (Option<f64>, Option<f64>) {
    use crate::estimate::albedo::MaterialStatus;
    let errors: Vec<f64> = report
        .materials
        .iter()
        .zip(given.iter().zip(truth))
        .filter(|(m, _)| m.status == MaterialStatus::Fitted)
        .flat_map(|(m, (g, t))| {
            let fitted = g.scaled(glam::Vec3::from_array(m.multiplier)).mean_albedo();
            let truth = t.mean_albedo();
            (0..3)
                .filter(move |&c| truth[c] > 0.0)
                .map(move |c| (fitted[c] as f64 / truth[c] as f64 - 1.0).abs())
        })
        .collect();
    let max = errors.iter().copied().reduce(f64::max);
    let mean = (!errors.is_empty()).then(|| errors.iter().sum::<f64>() / errors.len() as f64);
    (max, mean)
}

/// A trial's record before its estimate: what it is, its scenario's figures, no results yet.
fn blank_record(
    id: String,
    sf: &ScenarioFile,
    trial: Trial,
    estimate: &EstimateSettings,
    noise_floor_rel_mae: Option<f64>,
    lights: Vec<LightFigures>,
    albedo_error: f32,
) -> TrialRecord {
    TrialRecord {
        id,
        scenario: sf.name.clone(),
        file: sf.path.clone(),
        rings: trial.rings.unwrap_or(0),
        cells: trial
            .rings
            .map_or(0, |r| crate::envmap::RingGrid::new(r).cell_count()),
        solver: trial.solver,
        spp: trial.spp,
        rounds: estimate.rounds,
        status: Status::Ok,
        error: None,
        rel_mae: None,
        noise_floor_rel_mae,
        views: Vec::new(),
        lights,
        iterations: 0,
        kkt_violation: 0.0,
        timings: Timings::default(),
        auto: None,
        spheres: None,
        colour: None,
        albedo_error,
        fit_albedo: trial.fit_albedo,
        albedo_max_error: None,
        albedo_mean_error: None,
        fingerprint: String::new(),
        transport_bytes: 0,
        peak_bytes: 0,
        threads: rayon::current_num_threads(),
    }
}

/// The estimate a trial runs: as `estimate` would with these settings, evaluated, with the
/// sphere model (1 to 3 lights, chosen on held-out pixels) or the envmap alone. The noise
/// floor is measured once per scenario (`observe`), not per trial.
/// Refuses the sweep, before its first trial, if any trial's peak (the transport dominates
/// it; `--auto` trials at their largest candidate) exceeds the memory budget.
fn check_memory(
    todo: &[Trial],
    scenarios: &[ScenarioFile],
    scenes: &[Option<Scene>],
    axes: &Axes,
    settings: &SweepSettings,
    id: &dyn Fn(&Trial) -> String,
) -> Result<()> {
    for t in todo {
        let Some(scene) = &scenes[scenarios[t.scenario].group] else {
            continue;
        };
        let pixels = scene.pixel_count();
        let rings = match t.rings {
            Some(r) => Rings::Fixed(r),
            None => Rings::Auto(axes.rings.clone()),
        };
        let need = trial_settings(settings, t.solver, t.spp, rings, t.spheres, t.fit_albedo)
            .memory_needed(pixels, scene.settings.max_bounces, &scene.materials);
        crate::memory::reserve(need, || format!("trial {}", id(t)))?;
    }
    Ok(())
}

fn trial_settings(
    settings: &SweepSettings,
    solver: Solver,
    spp: u32,
    rings: Rings,
    spheres: bool,
    fit_albedo: bool,
) -> EstimateSettings {
    EstimateSettings {
        rings,
        model: if spheres {
            LightModel::Spheres(None)
        } else {
            LightModel::Envmap
        },
        solver,
        spp,
        rounds: solver.default_rounds(),
        smooth: settings.smooth,
        ridge: settings.ridge,
        // The gradient solver fits each channel on its own, whatever the sweep's colour.
        colour: match solver {
            Solver::Nnls => settings.colour,
            Solver::Gradient => crate::estimate::Colour::PerChannel,
        },
        time_limit: settings.time_limit,
        evaluate: true,
        noise_floor: false,
        oracle: false,
        exposure: crate::estimate::job::Exposure::Shared,
        // A trial's record has no place for the diagnosis; it would cost a fit per misfit.
        diagnose: false,
        fit_albedo: fit_albedo.then_some(crate::estimate::albedo::FitAlbedo::Materials),
        trust_albedo: if fit_albedo {
            settings.trust_albedo.clone()
        } else {
            Vec::new()
        },
        texel_grid: crate::estimate::texels::DEFAULT_TEXEL_GRID,
        texel_smoothness: crate::estimate::texels::DEFAULT_TEXEL_SMOOTHNESS,
        sphere_pixels: crate::estimate::spheres::FIT_PIXELS,
    }
}

/// One planned trial.
#[derive(Debug, Clone, Copy)]
struct Trial {
    /// Index into the scenarios.
    scenario: usize,
    spp: u32,
    /// None: the `--rings auto` trial.
    rings: Option<u32>,
    solver: Solver,
    /// Index into the albedo errors.
    albedo: usize,
    /// The sphere-light model, started from an envmap of `rings`.
    spheres: bool,
    /// Fits the albedo beside the lighting.
    fit_albedo: bool,
}

/// The true lights as seen from the scene's `center` (`size`: its larger horizontal extent),
/// to be matched with the estimate's.
fn light_figures(lights: &[SphereLight], center: Vec3, size: f32) -> Vec<LightFigures> {
    lights
        .iter()
        .map(|l| {
            let d = l.center - center;
            LightFigures {
                distance: d.length(),
                distance_over_size: d.length() / size,
                elevation_degrees: if d.length() > 0.0 {
                    (d.y / d.length()).clamp(-1.0, 1.0).asin().to_degrees()
                } else {
                    0.0
                },
                angle_error_degrees: None,
                power_ratio: None,
            }
        })
        .collect()
}

/// A trial's figures from its estimate's report.
fn fill_record(
    record: &mut TrialRecord,
    report: EstimateReport,
    noise_floor: &[f64],
    (truth, center): (&[SphereLight], Vec3),
) {
    record.rings = report.rings;
    record.cells = report.cells;
    record.rel_mae = report.rel_mae;
    record.colour = Some(report.envmap_colour);
    let fig = |m: &Metrics, nf: f64, view: &str| ViewFigures {
        view: view.to_string(),
        rel_mae: fin(m.rel_mae),
        rel_mse: fin(m.rel_mse),
        rmse: fin(m.rmse),
        psnr: fin(m.psnr),
        noise_floor_rel_mae: fin(nf),
    };
    record.views = report
        .views
        .iter()
        .zip(noise_floor)
        .filter_map(|(v, &nf)| v.estimate.as_ref().map(|m| fig(m, nf, &v.view)))
        .collect();
    // Recovery lists lights by decreasing power; match them back by direction.
    for r in &report.light_recovery {
        let dir = Vec3::from(r.true_direction);
        if let Some((lf, _)) = record.lights.iter_mut().zip(truth).find(|(lf, l)| {
            lf.angle_error_degrees.is_none() && (l.center - center).normalize().dot(dir) > 0.99999
        }) {
            lf.angle_error_degrees = Some(r.angle_error_degrees);
            lf.power_ratio = Some(r.power_ratio);
        }
    }
    record.iterations = report.channels.iter().map(|c| c.iterations).sum();
    record.kkt_violation = report
        .channels
        .iter()
        .map(|c| c.kkt_violation)
        .fold(0.0, f64::max);
    if report.status != FitStatus::Ok {
        record.status = Status::NotConverged;
    }
    if record.rel_mae.is_some_and(|e| !e.is_finite()) {
        record.status = Status::Failed;
        record.error = Some("the estimate's error is not finite".into());
        record.rel_mae = None;
    }
    let t = &report.timings;
    let selection_seconds = report.rings_selection.as_ref().map_or(0.0, |s| s.seconds);
    record.timings = Timings {
        fit_seconds: selection_seconds
            + t.alternation_seconds
            + t.transport_seconds
            + t.solve_seconds,
        transport_seconds: t.transport_seconds,
        solve_seconds: t.solve_seconds,
        rerender_seconds: t.rerender_seconds,
        trial_seconds: 0.0,
        selection_seconds,
        albedo_seconds: t.alternation_seconds,
    };
    record.transport_bytes = report.memory.transport_bytes;
    record.auto = report.rings_selection;
    // The sphere model's figures replace the envmap's.
    if let Some(so) = report.spheres {
        let envmap_rel_mae = record.rel_mae;
        record.rel_mae = so.rel_mae.filter(|e| e.is_finite());
        for (v, e) in record.views.iter_mut().zip(&so.views) {
            (v.rel_mae, v.rel_mse, v.rmse, v.psnr) =
                (fin(e.rel_mae), fin(e.rel_mse), fin(e.rmse), fin(e.psnr));
        }
        record.timings.rerender_seconds = so.rerender_seconds;
        record.spheres = Some(SphereTrial {
            statuses: so.lights.iter().map(|f| f.status).collect(),
            recovery: so.recovery,
            envmap_rel_mae,
            sphere_fit_seconds: t.sphere_fit_seconds,
            selection: report.model_selection,
            renders: so.renders,
            iterations: so.iterations,
        });
    }
}

/// `v` without repeats, in first-seen order (a value given twice runs once).
fn dedup<T: PartialEq + Copy>(v: &[T]) -> Vec<T> {
    let mut out: Vec<T> = Vec::new();
    for &x in v {
        if !out.contains(&x) {
            out.push(x);
        }
    }
    out
}

/// Mean over views; None when empty or any value is not finite.
fn pipeline_mean(v: &[f64]) -> Option<f64> {
    (!v.is_empty() && v.iter().all(|x| x.is_finite()))
        .then(|| v.iter().sum::<f64>() / v.len() as f64)
}

/// Opens a JSON-lines file for appending. A last line cut short by a crash is cut off first,
/// so only ever the last line of a file can be incomplete.
fn open_append(path: &Path) -> Result<std::fs::File> {
    let keep = match std::fs::read(path) {
        Ok(b) if !b.is_empty() && !b.ends_with(b"\n") => {
            Some(b.iter().rposition(|&c| c == b'\n').map_or(0, |i| i + 1))
        }
        _ => None,
    };
    let f = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .map_err(|e| Error::io(path, e))?;
    if let Some(len) = keep {
        f.set_len(len as u64).map_err(|e| Error::io(path, e))?;
    }
    Ok(f)
}

/// What a scenario's references depend on: the scene (sidecar minus lights) and the lights.
fn scenario_fingerprint(key: &str, lights: &[SphereLight]) -> String {
    // `streams=name`: references are rendered with each view's stream from its name
    // (`render::view_stream`); folders from before render with other noise.
    let text = format!("{key}|{lights:?}|streams=name");
    let h = text
        .bytes()
        .fold(0x5CE9_A410u64, |h, b| mix64(h ^ b as u64));
    format!("{h:016x}")
}

#[derive(Serialize, Deserialize)]
struct NoiseFile {
    views: Vec<String>,
    /// None where not finite (a view whose reference is black).
    noise_floor_rel_mae: Vec<Option<f64>>,
    /// The scenario this was rendered for ([`scenario_fingerprint`]).
    #[serde(default)]
    scenario: String,
}

/// A scenario's references and noise floor, from `dir` when a previous run left them there.
fn observe<'a>(
    renderer: &Renderer,
    views: &[&'a Camera],
    render: &RenderSettings,
    dir: &Path,
    fingerprint: &str,
) -> Result<Observed<'a>> {
    let names: Vec<String> = views.iter().map(|c| c.name.clone()).collect();
    let noise_path = dir.join("noise.json");
    // Reused only for the same views and scenario (files from before fingerprints: "").
    let cached = std::fs::read_to_string(&noise_path)
        .ok()
        .and_then(|t| serde_json::from_str::<NoiseFile>(&t).ok())
        .filter(|n| n.views == names && (n.scenario.is_empty() || n.scenario == fingerprint));
    let (references, noise_floor): (Vec<_>, Vec<f64>) = match cached {
        Some(n) => (
            pipeline::load_references(dir, views, Default::default())?.0,
            n.noise_floor_rel_mae
                .iter()
                .map(|x| x.unwrap_or(f64::INFINITY))
                .collect(),
        ),
        None => {
            let refs = renderer.render_views(views, render, &|_| {});
            let masks = pipeline::geometry_masks(renderer, views, &refs);
            let nf = pipeline::noise_floor(renderer, views, &refs, &masks, render, &|_| {})?;
            std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
            for (img, cam) in refs.iter().zip(views) {
                imageio::write_exr(&dir.join(format!("{}.exr", cam.name)), img)?;
            }
            let n = NoiseFile {
                views: names,
                noise_floor_rel_mae: nf.iter().map(|m| fin(m.rel_mae)).collect(),
                scenario: fingerprint.to_string(),
            };
            let text =
                serde_json::to_string_pretty(&n).map_err(|e| Error::Invalid(e.to_string()))?;
            imageio::write_bytes(&noise_path, text.as_bytes())?;
            (refs, nf.iter().map(|m| m.rel_mae).collect())
        }
    };
    // The masks, and the views kept, exactly as a stand-alone estimate makes them.
    let seen = job::observe(renderer, render, job::References::Images(references), &())?;
    // The views kept, in order, as this scene's cameras (`renderer` lives for one trial).
    let kept: Vec<usize> = views
        .iter()
        .enumerate()
        .filter(|(_, c)| seen.views.iter().any(|v| v.name == c.name))
        .map(|(i, _)| i)
        .collect();
    let noise_floor: Vec<f64> = kept.iter().map(|&i| noise_floor[i]).collect();
    let seen = SeenViews {
        views: kept.iter().map(|&i| views[i]).collect(),
        references: seen.references,
        masks: seen.masks,
        blind: seen.blind,
        blind_references: seen.blind_references,
        blind_reason: seen.blind_reason,
        seconds: seen.seconds,
        rendered: true,
        twins: Vec::new(),
    };
    Ok(Observed { seen, noise_floor })
}
