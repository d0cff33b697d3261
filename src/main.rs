//! The `lightprobe` command: a thin layer over the library. Parses flags, checks them, calls
//! the library, prints. Errors print once, as one line, with a non-zero exit code.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Context, bail};
use clap::{Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use serde_json::json;

use lightprobe::envmap::latlong::{self, Filter, Target};
use lightprobe::envmap::{Envmap, RingGrid};
use lightprobe::estimate::{self, FitSettings, Solver, pipeline};
use lightprobe::experiment::scenarios;
use lightprobe::imageio::{self, Image};
use lightprobe::metrics;
use lightprobe::render::{Lights, RenderSettings, Renderer, Strategy};
use lightprobe::scene::{Scene, sidecar};

/// Mirrors a library option enum as a clap value enum (the library does not depend on clap);
/// variant doc comments become the values' help.
macro_rules! cli_enum {
    ($cli:ident => $lib:ident { $($(#[$doc:meta])* $v:ident),+ $(,)? }) => {
        #[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
        enum $cli { $($(#[$doc])* $v),+ }
        impl From<$cli> for $lib {
            fn from(c: $cli) -> Self {
                match c { $($cli::$v => $lib::$v),+ }
            }
        }
    };
}

cli_enum!(StrategyArg => Strategy {
    /// Emitter sampling and BSDF sampling combined by the power heuristic.
    Mis,
    /// Emitter sampling only.
    LightOnly,
    /// BSDF sampling only.
    BsdfOnly,
});
cli_enum!(SolverArg => Solver {
    /// Exact non-negative least squares (active set) on the normal equations.
    Nnls,
    /// The paper's projected gradient descent with sequential Monte Carlo re-sampling.
    Gradient,
});
cli_enum!(TargetArg => Target {
    /// Mitsuba 3's envmap: +Y up, poles on the first and last rows.
    Mitsuba,
    /// Blender's World Environment Texture, for a scene imported from the glTF (Z up).
    Blender,
    /// pbrt-v3's lat-long infinite light (Z up, same axis change as Blender's importer).
    PbrtV3,
});
cli_enum!(FilterArg => Filter {
    /// The cell under each pixel centre.
    Box,
    /// Interpolated between grid points.
    Smooth,
});

/// `--model`: the envmap, K sphere lights (None: 1 to 3, chosen on held-out pixels), or
/// chosen from the data.
#[derive(Clone, Copy, Debug)]
enum ModelArg {
    Envmap,
    Spheres(Option<usize>),
    Auto,
}

fn parse_model(s: &str) -> Result<ModelArg, String> {
    match s {
        "envmap" => Ok(ModelArg::Envmap),
        "spheres" => Ok(ModelArg::Spheres(None)),
        "auto" => Ok(ModelArg::Auto),
        _ => match s.strip_prefix("spheres:").map(str::parse::<usize>) {
            Some(Ok(k)) if (1..=8).contains(&k) => Ok(ModelArg::Spheres(Some(k))),
            _ => Err(format!(
                "expected envmap, spheres, spheres:K (K = 1..8) or auto, got {s:?}"
            )),
        },
    }
}

/// `--rings`: a ring count or `auto`.
#[derive(Clone, Copy, Debug)]
enum RingsArg {
    Auto,
    Fixed(u32),
}

fn parse_rings(s: &str) -> Result<RingsArg, String> {
    if s == "auto" {
        return Ok(RingsArg::Auto);
    }
    s.parse()
        .map(RingsArg::Fixed)
        .map_err(|_| format!("expected a ring count or `auto`, got {s:?}"))
}

#[derive(Parser)]
#[command(name = "lightprobe", version, about = "Estimate the lighting of a 3D scene from images of it.", long_about = None)]
struct Cli {
    /// Worker threads (default: all cores; RAYON_NUM_THREADS also works). Results do not
    /// depend on it.
    #[arg(long, global = true)]
    threads: Option<usize>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Path-trace reference images of a scene under its sphere lights: one linear f32 EXR per
    /// view (alpha = fraction of samples that saw geometry), a PNG preview and render.json.
    RenderReference(RenderArgs),
    /// Photometric error of an image against a reference (relMAE, MAE, RMSE, relMSE, PSNR),
    /// over the pixels where the reference's alpha is > 0 (its geometry mask).
    Compare(CompareArgs),
    /// Estimate the ring environment map that best explains reference images (rendered from
    /// the sidecar's sphere lights, or given with --reference), re-render it with a fresh seed
    /// and report the photometric error against the Monte Carlo noise floor.
    Estimate(EstimateArgs),
    /// Write a ring envmap (envmap.ron) as a lat-long OpenEXR that another renderer loads the
    /// right way up (default: Mitsuba 3's `envmap`, +Y up, poles on the first and last rows).
    ExportEnvmap(ExportArgs),
    /// Average a lat-long OpenEXR environment over the cells of an N-ring grid (envmap.ron),
    /// e.g. to use any HDR environment as ground-truth lighting.
    ImportEnvmap(ImportArgs),
    /// Print what lightprobe loaded from a scene as JSON: triangle count, bounds, surface
    /// area, materials, cameras (pose, field of view), lights and settings.
    Info {
        /// The scene sidecar (.ron).
        scene: PathBuf,
    },
    /// Generate random illumination scenarios of a scene (the paper's experiment): one sidecar
    /// per scenario with one or two sphere lights, and scenarios.json describing them.
    Scenarios(ScenariosArgs),
    /// Run estimates over scenarios × samples × rings × solvers (the paper's experiment),
    /// appending one JSON line per trial to OUT/trials*.jsonl; resumable and shardable.
    Sweep(SweepArgs),
    /// Charts (PNG) and a markdown summary of a sweep's trials, all shards merged:
    /// error against rings (the paper's Fig. 4), speed against accuracy with the Pareto
    /// front, error against light distance.
    Report {
        /// The sweep's output folder.
        dir: PathBuf,
        /// Print summary.json to stdout.
        #[arg(long)]
        json: bool,
    },
    /// Print the JSON Schema of the scene sidecar (RON).
    Schema,
}

#[derive(clap::Args)]
struct RenderArgs {
    /// The scene sidecar (.ron), which names the glTF file.
    scene: PathBuf,
    /// Output folder (created if missing).
    #[arg(long, short)]
    out: PathBuf,
    /// Samples per pixel (default: the sidecar's).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=sidecar::MAX_SPP as i64))]
    spp: Option<u32>,
    /// Random seed (default: the sidecar's).
    #[arg(long)]
    seed: Option<u64>,
    /// Scattering events per path, 1 = direct light only (default: the sidecar's).
    #[arg(long)]
    max_bounces: Option<u32>,
    /// Light transport estimator.
    #[arg(long, value_enum, default_value_t = StrategyArg::Mis)]
    strategy: StrategyArg,
    /// Show emitters seen directly by the camera (default: black, like Mitsuba's hide_emitters).
    #[arg(long)]
    show_emitters: bool,
    /// Also light the scene with this ring envmap (envmap.ron); escaping rays see it.
    #[arg(long)]
    envmap: Option<PathBuf>,
    /// Leave out the sidecar's sphere lights (e.g. to light with --envmap alone).
    #[arg(long)]
    no_sphere_lights: bool,
    /// Only these views (comma-separated camera node names; default: the sidecar's).
    #[arg(long, value_delimiter = ',')]
    views: Vec<String>,
    /// Also write geometry buffers at pixel centres: depth (metres), normal (world), albedo.
    #[arg(long, value_delimiter = ',', value_parser = ["depth", "normal", "albedo"])]
    aov: Vec<String>,
    /// Print render.json to stdout instead of a summary.
    #[arg(long)]
    json: bool,
    /// No progress bar.
    #[arg(long, short)]
    quiet: bool,
}

#[derive(clap::Args)]
struct CompareArgs {
    /// The image to judge (EXR).
    image: PathBuf,
    /// The reference (EXR); its alpha, if any, masks out background pixels.
    reference: PathBuf,
    /// Write a per-pixel error heat map (PNG) with a colour bar.
    #[arg(long)]
    heatmap: Option<PathBuf>,
    /// Top of the heat map's colour scale (default: 99th percentile of the error).
    #[arg(long)]
    scale: Option<f32>,
    /// Compare every pixel, ignoring the reference's alpha mask.
    #[arg(long)]
    no_mask: bool,
    /// Print the metrics as JSON.
    #[arg(long)]
    json: bool,
}

#[derive(clap::Args)]
struct EstimateArgs {
    /// The scene sidecar (.ron).
    scene: PathBuf,
    /// Output folder (created if missing).
    #[arg(long, short)]
    out: PathBuf,
    /// Folder of reference EXRs named <view>.exr (default: render them from the sidecar's
    /// sphere lights into OUT/reference/).
    #[arg(long)]
    reference: Option<PathBuf>,
    /// Rings of the envmap (default: the sidecar's), or `auto`: fit each of
    /// --rings-candidates on three quarters of the pixels and take the smallest whose error
    /// on the held-out quarter is within one standard error of the best.
    #[arg(long, value_parser = parse_rings)]
    rings: Option<RingsArg>,
    /// Light model: `envmap` (the ring envmap); `spheres:K`: K sphere lights at finite
    /// distance, started from the best set of K candidate lights (the envmap's bright cells and
    /// an even scan of directions) and a distance search, refined by Levenberg–Marquardt
    /// (centres, radii; radiances exact), written as a sidecar fragment (spheres/lights.ron)
    /// with its own re-render and errors; `spheres`: 1, 2, … (at most 3) lights fitted on
    /// three quarters of the pixels, the fewest
    /// within one standard error of the best on the held-out quarter kept; `auto`: the same
    /// with two more candidates, the envmap, and the sphere model chosen so far with an envmap
    /// behind its lights (`envmap+spheres:K`, for light from afar beside near lights; written
    /// as spheres/lights.ron plus spheres/background.ron and .exr).
    #[arg(long, default_value = "envmap", value_parser = parse_model)]
    model: ModelArg,
    /// Resolutions `--rings auto` chooses from.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "3,5,7,9,11,13,15,17,19,21,23,25,27"
    )]
    rings_candidates: Vec<u32>,
    #[arg(long, value_enum, default_value_t = SolverArg::Nnls)]
    solver: SolverArg,
    /// Samples per pixel of the transport estimate, over all rounds (default: the sidecar's).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=sidecar::MAX_SPP as i64))]
    spp: Option<u32>,
    /// Smoothness weight between neighbouring cells (relative; 0 = none).
    #[arg(long, default_value_t = 0.0)]
    smooth: f64,
    /// Ridge weight pulling cells toward zero (relative to the mean diagonal of TᵀT): keeps
    /// cells the views barely see from taking wild values. 0.001 shrinks a cell of average
    /// visibility by about 0.1% (0.01, the default before the renderer's noise fell, cost a
    /// visible 1% of brightness on coarse grids).
    #[arg(long, default_value_t = 1e-3)]
    ridge: f64,
    /// Transport rounds (sequential Monte Carlo), sharing --spp: rounds after the first sample
    /// cells by the current estimate. Default 4 for nnls (which fits their mean transport,
    /// with TᵀT from products of different rounds: unbiased from 2 rounds on), 3 for gradient
    /// (which continues from its estimate each round).
    #[arg(long)]
    rounds: Option<u32>,
    /// Also compute the representation limit: the best envmap of this resolution, fitted to a
    /// transport with 8× the samples (slower).
    #[arg(long)]
    oracle: bool,
    /// Only fit and write the envmap: skip the noise floor and the re-render of the estimate
    /// (and their errors in report.json), for speed.
    #[arg(long, conflicts_with = "oracle")]
    fit_only: bool,
    /// Time budget per channel solve, seconds.
    #[arg(long, default_value_t = 60.0)]
    time_limit: f64,
    /// Exit 0 even when the solver stops at its iteration or time limit (the outputs are
    /// written either way; report.json says "status": "not-converged").
    #[arg(long)]
    allow_nonconvergence: bool,
    /// Print report.json to stdout instead of a summary.
    #[arg(long)]
    json: bool,
    /// No progress bars.
    #[arg(long, short)]
    quiet: bool,
}

#[derive(clap::Args)]
struct ExportArgs {
    /// The ring envmap (envmap.ron).
    envmap: PathBuf,
    /// Output lat-long EXR.
    #[arg(long, short)]
    out: PathBuf,
    /// Image width in pixels (height = width / 2), 8..=16384. Renderers interpolate between
    /// pixels, which blurs cell edges by half a pixel: measured in Mitsuba, the worst cell
    /// (a pole cap of 9 rings) loses 2.7% of its power at 1024 and 0.7% at 4096.
    #[arg(long, default_value_t = 4096)]
    width: u32,
    /// Whose lat-long convention to write.
    #[arg(long, value_enum, default_value_t = TargetArg::Mitsuba)]
    target: TargetArg,
    /// `box`: the cell under each pixel centre (import-envmap gives the cells back exactly);
    /// `smooth`: interpolated between grid points.
    #[arg(long, value_enum, default_value_t = FilterArg::Box)]
    filter: FilterArg,
}

#[derive(clap::Args)]
struct ScenariosArgs {
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
struct SweepArgs {
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
    /// Exit 0 even when some trials failed (they are recorded either way).
    #[arg(long)]
    allow_failures: bool,
    /// No progress bar.
    #[arg(long, short)]
    quiet: bool,
}

#[derive(clap::Args)]
struct ImportArgs {
    /// A lat-long RGB OpenEXR.
    image: PathBuf,
    /// Ring count of the grid to average onto (1..=1000).
    #[arg(long)]
    rings: u32,
    /// Output envmap.ron.
    #[arg(long, short)]
    out: PathBuf,
    /// Whose lat-long convention the image follows.
    #[arg(long, value_enum, default_value_t = TargetArg::Mitsuba)]
    target: TargetArg,
}

fn main() -> ExitCode {
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) => return usage_error(e),
    };
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("lightprobe: error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// A command-line error from clap as one line, like every other error (clap's own message
/// adds a usage block), with clap's exit code 2. Help and version requests print as clap
/// writes them.
fn usage_error(e: clap::Error) -> ExitCode {
    use clap::error::ErrorKind;
    if matches!(
        e.kind(),
        ErrorKind::DisplayHelp
            | ErrorKind::DisplayVersion
            | ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand
    ) {
        e.exit();
    }
    // The message runs to the first blank line; then come tips (kept) and usage (dropped).
    let text = e.render().to_string();
    let message: Vec<&str> = text
        .lines()
        .take_while(|l| !l.trim().is_empty())
        .map(str::trim)
        .collect();
    let tips = text
        .lines()
        .map(str::trim)
        .filter(|l| l.starts_with("tip:"));
    let message = std::iter::once(message.join(" ")).chain(tips.map(str::to_string));
    let message = message.collect::<Vec<_>>().join("; ");
    eprintln!(
        "lightprobe: error: {} (see --help)",
        message.trim_start_matches("error: ")
    );
    ExitCode::from(2)
}

fn run(cli: Cli) -> anyhow::Result<()> {
    if let Some(n) = cli.threads {
        if n == 0 {
            bail!("--threads must be at least 1");
        }
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build_global()
            .context("cannot start the thread pool")?;
    }
    match cli.command {
        Command::RenderReference(args) => render_reference(args),
        Command::Compare(args) => compare(args),
        Command::Estimate(args) => estimate(args),
        Command::ExportEnvmap(args) => export_envmap(args),
        Command::ImportEnvmap(args) => import_envmap(args),
        Command::Info { scene } => info(&scene),
        Command::Scenarios(a) => scenarios(a),
        Command::Sweep(a) => sweep(a),
        Command::Report { dir, json } => {
            let s = lightprobe::experiment::report::report(&dir)?;
            if json {
                println!("{}", serde_json::to_string_pretty(&s)?);
            } else {
                println!(
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
                );
            }
            Ok(())
        }
        Command::Schema => {
            print!("{}", sidecar::json_schema());
            Ok(())
        }
    }
}

/// Creates `dir` and proves it writable before any long work starts.
fn prepare_out_dir(dir: &Path) -> anyhow::Result<()> {
    if dir.exists() && !dir.is_dir() {
        return Err(lightprobe::Error::file(
            dir,
            "exists and is not a folder (--out names a folder)",
        )
        .into());
    }
    std::fs::create_dir_all(dir).map_err(|e| lightprobe::Error::io(dir, e))?;
    let probe = dir.join(format!(".lightprobe-write-test.{}", std::process::id()));
    std::fs::write(&probe, b"")
        .map_err(|e| lightprobe::Error::file(dir, format!("output folder is not writable: {e}")))?;
    let _ = std::fs::remove_file(&probe);
    Ok(())
}

fn progress_bar(total: u64, quiet: bool, what: &str) -> ProgressBar {
    if quiet {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::new(total);
    bar.set_style(
        ProgressStyle::with_template(
            "{msg:>12} [{bar:40}] {percent:>3}% {elapsed_precise} eta {eta}",
        )
        .expect("a valid template")
        .progress_chars("=> "),
    );
    bar.set_message(what.to_string());
    bar
}

fn render_reference(a: RenderArgs) -> anyhow::Result<()> {
    let t_load = Instant::now();
    let mut scene = Scene::load(&a.scene)?;
    let mut settings = RenderSettings::from_scene(&scene.settings);
    if let Some(spp) = a.spp {
        if !(1..=sidecar::MAX_SPP).contains(&spp) {
            bail!("--spp must be between 1 and {}", sidecar::MAX_SPP);
        }
        settings.spp = spp;
    }
    if let Some(b) = a.max_bounces {
        if !(1..=sidecar::MAX_BOUNCES).contains(&b) {
            bail!(
                "--max-bounces must be between 1 and {}",
                sidecar::MAX_BOUNCES
            );
        }
        settings.max_bounces = b;
    }
    if let Some(seed) = a.seed {
        settings.seed = seed;
    }
    settings.strategy = a.strategy.into();
    settings.hide_emitters = !a.show_emitters;
    if !a.views.is_empty() {
        let mut picked = Vec::new();
        for (i, v) in a.views.iter().enumerate() {
            if a.views[..i].contains(v) {
                bail!("--views: {v:?} is listed twice");
            }
            let cam = scene.cameras.iter().find(|c| &c.name == v);
            picked.push(
                cam.with_context(|| {
                    format!("--views: {v:?} is not a view of {}", a.scene.display())
                })?
                .clone(),
            );
        }
        scene.cameras = picked;
    }
    let mut lights = Lights::new(if a.no_sphere_lights {
        Vec::new()
    } else {
        scene.lights.clone()
    });
    if let Some(p) = &a.envmap {
        lights.env = Some(Envmap::load(p)?);
    }
    if lights.is_empty() {
        bail!(
            "{}: nothing lights the scene (no sphere lights and no --envmap)",
            a.scene.display()
        );
    }
    // One view at a time: its image (RGB + coverage), the per-tile results and the EXR encoder.
    let need = (scene.settings.width as u64 * scene.settings.height as u64) * 40;
    if let Some(avail) = lightprobe::memory::available_bytes()
        && need > avail / 10 * 9
    {
        bail!(
            "{}×{} images would need about {:.1} GiB each, but only {:.1} GiB is available",
            scene.settings.width,
            scene.settings.height,
            need as f64 / (1u64 << 30) as f64,
            avail as f64 / (1u64 << 30) as f64
        );
    }
    prepare_out_dir(&a.out)?;
    let load_s = t_load.elapsed().as_secs_f64();

    let t_bvh = Instant::now();
    let renderer = Renderer::new(&scene, &lights);
    let bvh_s = t_bvh.elapsed().as_secs_f64();

    let pixels_per_view = (scene.settings.width * scene.settings.height) as u64;
    let bar = progress_bar(
        pixels_per_view * scene.cameras.len() as u64,
        a.quiet,
        "rendering",
    );
    let mut views = Vec::new();
    let t_all = Instant::now();
    for cam in &scene.cameras {
        let t = Instant::now();
        let img =
            renderer.render_radiance(cam, lightprobe::render::view_stream(cam), &settings, &|n| {
                bar.inc(n)
            });
        let secs = t.elapsed().as_secs_f64();
        if img.rgb.iter().any(|c| !c.is_finite()) {
            bail!(
                "view {:?}: the render produced non-finite pixels (a bug; please report it)",
                cam.name
            );
        }
        let exr = a.out.join(format!("{}.exr", cam.name));
        imageio::write_exr(&exr, &img)?;
        let png = a.out.join(format!("{}.png", cam.name));
        imageio::write_png(&png, &img, imageio::auto_exposure(&img))?;
        let mut aov_files = serde_json::Map::new();
        if !a.aov.is_empty() {
            let aovs = renderer.aovs(cam);
            for name in &a.aov {
                let (image, file): (&Image, PathBuf) = match name.as_str() {
                    "depth" => (&aovs.depth, a.out.join(format!("{}.depth.exr", cam.name))),
                    "normal" => (&aovs.normal, a.out.join(format!("{}.normal.exr", cam.name))),
                    _ => (&aovs.albedo, a.out.join(format!("{}.albedo.exr", cam.name))),
                };
                imageio::write_exr(&file, image)?;
                aov_files.insert(name.clone(), json!(file));
            }
        }
        let samples = pixels_per_view as f64 * settings.spp as f64;
        let coverage = img.alpha.as_ref().map_or(1.0, |al| {
            al.iter().map(|&v| v as f64).sum::<f64>() / al.len() as f64
        });
        views.push(json!({
            "view": cam.name,
            "exr": exr,
            "png": png,
            "aov": aov_files,
            "mean_rgb": img.mean().to_array(),
            "coverage": coverage,
            "seconds": secs,
            "samples_per_second": samples / secs,
        }));
    }
    bar.finish_and_clear();
    let total_s = t_all.elapsed().as_secs_f64();
    let total_samples = pixels_per_view as f64 * settings.spp as f64 * scene.cameras.len() as f64;
    let report = json!({
        "lightprobe_version": lightprobe::VERSION,
        "scene": a.scene,
        "triangles": scene.mesh.triangle_count(),
        "image": { "width": scene.settings.width, "height": scene.settings.height },
        "lights": lights.spheres.iter().map(|l| json!({
            "center": l.center.to_array(), "radius": l.radius, "radiance": l.radiance.to_array() })).collect::<Vec<_>>(),
        "envmap": a.envmap.as_ref().map(|p| json!({ "file": p, "rings": lights.env.as_ref().map(|e| e.grid.rings()) })),
        "settings": settings,
        "threads": rayon::current_num_threads(),
        "timings": { "load_seconds": load_s, "bvh_seconds": bvh_s, "render_seconds": total_s },
        "samples_per_second": total_samples / total_s,
        "views": views,
    });
    let text = serde_json::to_string_pretty(&report)? + "\n";
    imageio::write_bytes(&a.out.join("render.json"), text.as_bytes())?;
    if a.json {
        print!("{text}");
    } else {
        for v in report["views"].as_array().into_iter().flatten() {
            println!(
                "{:<12} {}  mean {:.4?}  coverage {:.0}%  {:.2} s",
                v["view"].as_str().unwrap_or(""),
                v["exr"].as_str().unwrap_or(""),
                v["mean_rgb"]
                    .as_array()
                    .map(|m| m.iter().filter_map(|x| x.as_f64()).collect::<Vec<_>>())
                    .unwrap_or_default(),
                100.0 * v["coverage"].as_f64().unwrap_or(0.0),
                v["seconds"].as_f64().unwrap_or(0.0),
            );
        }
        println!(
            "{} triangles, {} spp, {} bounces: {:.2} s, {:.2} M samples/s on {} threads",
            scene.mesh.triangle_count(),
            settings.spp,
            settings.max_bounces,
            total_s,
            total_samples / total_s / 1e6,
            rayon::current_num_threads()
        );
    }
    Ok(())
}

fn compare(a: CompareArgs) -> anyhow::Result<()> {
    let image = imageio::read_exr(&a.image)?;
    let reference = imageio::read_exr(&a.reference)?;
    if (image.width, image.height) != (reference.width, reference.height) {
        bail!(
            "{}: image is {}×{} but the reference {} is {}×{}",
            a.image.display(),
            image.width,
            image.height,
            a.reference.display(),
            reference.width,
            reference.height
        );
    }
    for (img, path) in [(&image, &a.image), (&reference, &a.reference)] {
        if let Some(i) = img.rgb.iter().position(|c| !c.is_finite()) {
            bail!(
                "{}: pixel ({}, {}) is not finite",
                path.display(),
                i as u32 % img.width,
                i as u32 / img.width
            );
        }
    }
    if let Some(s) = a.scale
        && !(s.is_finite() && s > 0.0)
    {
        bail!("--scale must be a finite number > 0");
    }
    let mask = if a.no_mask {
        vec![true; reference.rgb.len()]
    } else {
        metrics::mask_of(&reference)
    };
    if !mask.contains(&true) {
        bail!(
            "{}: its alpha (coverage) is zero everywhere, so no pixel is compared; pass --no-mask to compare every pixel",
            a.reference.display()
        );
    }
    let m = metrics::compare(&image, &reference, &mask)?;
    let scale = match &a.heatmap {
        Some(p) => Some(metrics::write_heatmap(
            p, &image, &reference, &mask, a.scale,
        )?),
        None => None,
    };
    if a.json {
        let mut v = serde_json::to_value(m)?;
        v["image"] = json!(a.image);
        v["reference"] = json!(a.reference);
        if let (Some(p), Some(s)) = (&a.heatmap, scale) {
            v["heatmap"] = json!({ "path": p, "scale": s });
        }
        println!("{}", serde_json::to_string_pretty(&v)?);
    } else {
        println!("relMAE  {:.5}  ({:.2}%)", m.rel_mae, 100.0 * m.rel_mae);
        println!("MAE     {:.6}", m.mae);
        println!("RMSE    {:.6}", m.rmse);
        println!("relMSE  {:.6}", m.rel_mse);
        println!("PSNR    {:.2} dB", m.psnr);
        println!(
            "pixels  {} compared, {} masked out (background)",
            m.pixels, m.masked_out
        );
        if let (Some(p), Some(s)) = (&a.heatmap, scale) {
            println!("heatmap {} (scale 0..{s:.4})", p.display());
        }
    }
    Ok(())
}

fn info(path: &Path) -> anyhow::Result<()> {
    use lightprobe::scene::Albedo;
    let scene = Scene::load(path)?;
    let (lo, hi) = scene.mesh.bounds();
    let materials: Vec<_> = scene
        .materials
        .iter()
        .map(|m| match &m.albedo {
            Albedo::Constant(c) => json!({ "name": m.name, "albedo": c.to_array() }),
            Albedo::Texture { texture, factor } => json!({
                "name": m.name,
                "albedo_factor": factor.to_array(),
                "texture": { "width": texture.width, "height": texture.height, "mean_linear": texture.mean().to_array() },
            }),
        })
        .collect();
    let cameras: Vec<_> = scene
        .cameras
        .iter()
        .map(|c| {
            json!({
                "name": c.name,
                "origin": c.origin_world.to_array(),
                "right": c.world_from_camera.x_axis.to_array(),
                "up": c.world_from_camera.y_axis.to_array(),
                "forward": (-c.world_from_camera.z_axis).to_array(),
                "yfov": c.yfov,
                "width": c.width,
                "height": c.height,
            })
        })
        .collect();
    let out = json!({
        "scene": path,
        "triangles": scene.mesh.triangle_count(),
        "vertices": scene.mesh.positions.len(),
        "bounds": { "min": lo.to_array(), "max": hi.to_array() },
        "surface_area": scene.mesh.surface_area(),
        "materials": materials,
        "cameras": cameras,
        "lights": scene.lights.iter().map(|l| json!({
            "center": l.center.to_array(), "radius": l.radius, "radiance": l.radiance.to_array() })).collect::<Vec<_>>(),
        "settings": {
            "width": scene.settings.width, "height": scene.settings.height, "spp": scene.settings.spp,
            "max_bounces": scene.settings.max_bounces, "seed": scene.settings.seed, "rings": scene.settings.rings,
        },
    });
    println!("{}", serde_json::to_string_pretty(&out)?);
    Ok(())
}

fn export_envmap(a: ExportArgs) -> anyhow::Result<()> {
    let (target, filter): (Target, Filter) = (a.target.into(), a.filter.into());
    if !(8..=16384).contains(&a.width) {
        bail!(
            "--width must be between 8 and 16384 pixels, got {}",
            a.width
        );
    }
    let env = Envmap::load(&a.envmap)?;
    let img = latlong::export(&env, target, filter, a.width);
    imageio::write_latlong_exr(&a.out, &img)?;
    println!(
        "{}: {}×{} lat-long ({:?}, {:?} filter) of {} rings / {} cells",
        a.out.display(),
        img.width,
        img.height,
        target,
        filter,
        env.grid.rings(),
        env.grid.cell_count()
    );
    Ok(())
}

fn import_envmap(a: ImportArgs) -> anyhow::Result<()> {
    let target: Target = a.target.into();
    if !(1..=sidecar::MAX_RINGS).contains(&a.rings) {
        bail!(
            "--rings must be between 1 and {}, got {}",
            sidecar::MAX_RINGS,
            a.rings
        );
    }
    let img = imageio::read_exr(&a.image)?;
    if img.width != 2 * img.height {
        // Any size is read as lat-long, but one that is not 2:1 is probably something else.
        eprintln!(
            "lightprobe: warning: {} is {}×{}, not 2:1 like a lat-long map; reading it as one anyway",
            a.image.display(),
            img.width,
            img.height
        );
    }
    let env =
        latlong::import(&img, target, a.rings).map_err(|m| lightprobe::Error::file(&a.image, m))?;
    env.save(&a.out)?;
    println!(
        "{}: {} rings / {} cells from {}×{} {}",
        a.out.display(),
        a.rings,
        env.grid.cell_count(),
        img.width,
        img.height,
        a.image.display()
    );
    Ok(())
}

fn scenarios(a: ScenariosArgs) -> anyhow::Result<()> {
    if !(1..=10_000).contains(&a.count) {
        bail!("--count must be between 1 and 10000");
    }
    let scene = Scene::load(&a.scene)?;
    let list = scenarios::generate(&scene, a.count, a.seed)?;
    prepare_out_dir(&a.out)?;
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
    for sc in &list {
        let text = scenarios::sidecar_text(&a.scene, sc, &a.out)?;
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
    println!(
        "{} scenarios ({} with two lights) in {}",
        list.len(),
        two,
        a.out.display()
    );
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

fn sweep(a: SweepArgs) -> anyhow::Result<()> {
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
        shard: Shard::parse(&a.shard)?,
        smooth: a.smooth,
        ridge: a.ridge,
        time_limit: std::time::Duration::from_secs_f64(a.time_limit),
        auto: a.auto,
        albedo_errors: a.albedo_error.clone(),
        spheres: a.spheres,
    };

    let files = sidecar_files(&a.scenarios)?;
    prepare_out_dir(&a.out)?;
    let bar = if a.quiet {
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
        match p.record {
            Some(r) => bar.set_message(format!(
                "{} {} rings: relMAE {}",
                r.scenario,
                r.rings,
                r.rel_mae
                    .map_or("failed".to_string(), |e| format!("{:.2}%", 100.0 * e))
            )),
            None => bar.set_message(p.phase.to_string()),
        }
    })?;
    bar.finish_and_clear();
    println!(
        "{} trials planned, {} already done, {} run ({} failed, {} not converged) in {:.1} s: {}",
        summary.planned,
        summary.skipped,
        summary.ran,
        summary.failed,
        summary.not_converged,
        summary.wall_seconds,
        summary.trials_file.display()
    );
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

fn metrics_json(m: &metrics::Metrics) -> serde_json::Value {
    serde_json::to_value(m).unwrap_or_default()
}

/// Writes re-renders of an estimate into `dir`: per view the EXR, a PNG preview exposed like
/// its reference, and the error heat map against it.
fn write_renders(
    dir: &Path,
    renders: &[Image],
    views: &[&lightprobe::scene::Camera],
    references: &[Image],
    masks: &[Vec<bool>],
) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| lightprobe::Error::io(dir, e))?;
    for (i, (img, cam)) in renders.iter().zip(views).enumerate() {
        imageio::write_exr(&dir.join(format!("{}.exr", cam.name)), img)?;
        imageio::write_png(
            &dir.join(format!("{}.png", cam.name)),
            img,
            imageio::auto_exposure(&references[i]),
        )?;
        metrics::write_heatmap(
            &dir.join(format!("{}.error.png", cam.name)),
            img,
            &references[i],
            &masks[i],
            None,
        )?;
    }
    Ok(())
}

/// Writes `NAME.ron` and its lat-long `NAME.exr` (Mitsuba's convention) into `dir`.
fn write_envmap(dir: &Path, name: &str, env: &lightprobe::envmap::Envmap) -> anyhow::Result<()> {
    env.save(&dir.join(format!("{name}.ron")))?;
    imageio::write_latlong_exr(
        &dir.join(format!("{name}.exr")),
        &latlong::export(env, Target::Mitsuba, Filter::Box, 4096),
    )?;
    Ok(())
}

/// Writes a sphere-model estimate: the sidecar fragment and the re-renders.
fn write_spheres(
    dir: &Path,
    so: &pipeline::SphereOutcome,
    views: &[&lightprobe::scene::Camera],
    references: &[Image],
    masks: &[Vec<bool>],
) -> anyhow::Result<()> {
    write_renders(dir, &so.renders, views, references, masks)?;
    imageio::write_bytes(&dir.join("lights.ron"), so.fit.fragment().as_bytes())?;
    if let Some(bg) = &so.fit.background {
        write_envmap(dir, "background", bg)?;
    }
    Ok(())
}

/// report.json's view of a sphere-model estimate.
fn spheres_report(so: &pipeline::SphereOutcome) -> serde_json::Value {
    json!({
        "model": so.fit.model_name(),
        "background_rings": so.fit.background.as_ref().map(|b| b.grid.rings()),
        "lights": so.fit.fitted,
        "start": so.fit.start.iter().map(|l| json!({ "center": l.center.to_array(), "radius": l.radius })).collect::<Vec<_>>(),
        "requested": so.fit.requested,
        "rel_mae": so.rel_mae(),
        "views": so.errors.iter().map(metrics_json).collect::<Vec<_>>(),
        "fit_rel_mae_binned": so.fit.fit_rel_mae,
        "iterations": so.fit.iterations,
        "objective_trace": so.fit.history,
        "renders": so.fit.renders,
        "recovery": so.recovery,
        "fit_seconds": so.fit.seconds,
        "rerender_seconds": so.rerender_seconds,
    })
}

/// Lines printed for a sphere-model estimate, beside the envmap's `errors`.
fn spheres_summary(so: &pipeline::SphereOutcome, errors: &[metrics::Metrics]) -> Vec<String> {
    use estimate::spheres::LightStatus;
    let mut lines = Vec::new();
    if let Some(e) = so.rel_mae() {
        lines.push(format!(
            "spheres ({} lights): relMAE {:.2}% (envmap {:.2}%), fit {:.1} s, {} renders",
            so.fit.lights().len(),
            100.0 * e,
            100.0 * pipeline::mean_rel_mae(errors).unwrap_or(f64::NAN),
            so.fit.seconds,
            so.fit.renders,
        ));
    }
    for (j, f) in so.fit.fitted.iter().enumerate() {
        let sigma = |v: Option<f64>| v.map_or("?".into(), |v| format!("{v:.3}"));
        lines.push(match f.status {
            LightStatus::Identified => format!(
                "sphere {j}: centre ({:.3}, {:.3}, {:.3}) ± {} m along its direction, radius {:.3}",
                f.light.center.x, f.light.center.y, f.light.center.z,
                sigma(f.distance_sigma_m), f.light.radius
            ),
            LightStatus::DistanceUnidentified => format!(
                "sphere {j}: direction and power fit; its distance is not identifiable from these images (25% nearer or farther fits within {:.1} σ)",
                f.distance_profile_sigmas.unwrap_or(0.0)
            ),
            LightStatus::Merged { into } => format!(
                "sphere {j}: too close in direction to sphere {into} to tell apart; merged into it"
            ),
            LightStatus::NoContribution => format!(
                "sphere {j}: changes no pixel (e.g. hidden below the table); left out"
            ),
        });
    }
    for (k, r) in so.recovery.iter().enumerate() {
        lines.push(match (r.centre_error_m, r.radius, r.power_ratio) {
            (Some(off), Some(rad), Some(p)) => format!(
                "true light {k}: centre off {off:.3} m ({:.1}% of its {:.2} m distance), radius {rad:.3} (true {:.3}), power ×{p:.3}",
                100.0 * off / r.true_distance_m, r.true_distance_m, r.true_radius
            ),
            _ => format!("true light {k}: not recovered (the model has fewer lights)"),
        });
    }
    lines
}

fn estimate(a: EstimateArgs) -> anyhow::Result<()> {
    let solver: Solver = a.solver.into();
    let t_all = Instant::now();
    let scene = Scene::load(&a.scene)?;
    let auto = matches!(a.rings, Some(RingsArg::Auto));
    // The largest model the job may fit (for the memory check).
    let mut rings = match a.rings {
        Some(RingsArg::Fixed(r)) => r,
        Some(RingsArg::Auto) => a.rings_candidates.iter().copied().max().unwrap_or(0),
        None => scene.settings.rings,
    };
    let candidates = if auto {
        &a.rings_candidates[..]
    } else {
        &[rings][..]
    };
    if let Some(r) = candidates
        .iter()
        .find(|r| !(1..=sidecar::MAX_RINGS).contains(*r))
    {
        bail!(
            "{} must be between 1 and {}, got {r}",
            if auto {
                "--rings-candidates"
            } else {
                "--rings"
            },
            sidecar::MAX_RINGS
        );
    }
    if auto && a.rings_candidates.is_empty() {
        bail!("--rings auto needs at least one --rings-candidates value");
    }
    let spp = a.spp.unwrap_or(scene.settings.spp);
    if !(1..=sidecar::MAX_SPP).contains(&spp) {
        bail!("--spp must be between 1 and {}", sidecar::MAX_SPP);
    }
    if !(a.smooth.is_finite() && a.smooth >= 0.0) {
        bail!("--smooth must be a finite number >= 0");
    }
    if !(a.ridge.is_finite() && a.ridge >= 0.0) {
        bail!("--ridge must be a finite number >= 0");
    }
    if !(a.time_limit.is_finite() && a.time_limit > 0.0 && a.time_limit <= 1e6) {
        bail!("--time-limit must be a positive number of seconds, at most 1e6");
    }
    let model_auto = matches!(a.model, ModelArg::Auto);
    // The number of sphere lights chosen from the data (`spheres` without K, or `auto`).
    let choose_k = matches!(a.model, ModelArg::Auto | ModelArg::Spheres(None));
    if choose_k && a.fit_only {
        bail!(
            "--model auto and --model spheres (without :K) compare the models' re-renders; they cannot be used with --fit-only"
        );
    }
    let rounds = a.rounds.unwrap_or(solver.default_rounds());
    if rounds == 0 || rounds > 100 {
        bail!("--rounds must be between 1 and 100");
    }
    if a.reference.is_none() && scene.lights.is_empty() {
        bail!(
            "{}: has no sphere lights to render references from; pass --reference DIR",
            a.scene.display()
        );
    }
    let (w, h) = (scene.settings.width, scene.settings.height);
    let cells = estimate::transport::Transport::memory_needed(
        (w * h) as usize * scene.cameras.len(),
        RingGrid::new(rings).cell_count(),
    );
    // Transport rows, one channel's f64 copy for the Gram product, and the per-pixel
    // accumulators of one view while it renders.
    let n = RingGrid::new(rings).cell_count() as u64;
    let need = cells as u64
        + (w * h) as u64 * scene.cameras.len() as u64 * n * 8
        + (w * h) as u64 * n * 12
        + n * n * 16;
    if let Some(avail) = lightprobe::memory::available_bytes()
        && need > avail / 10 * 9
    {
        bail!(
            "{rings} rings ({n} cells) at {w}×{h} × {} views would need about {:.1} GiB, but only {:.1} GiB is available; use fewer rings",
            scene.cameras.len(),
            need as f64 / (1u64 << 30) as f64,
            avail as f64 / (1u64 << 30) as f64
        );
    }
    prepare_out_dir(&a.out)?;
    let settings = RenderSettings::from_scene(&scene.settings);
    let true_lights = Lights::new(scene.lights.clone());
    let renderer = Renderer::new(&scene, &true_lights);
    let all_views: Vec<&lightprobe::scene::Camera> = scene.cameras.iter().collect();

    // ---- References ----
    let t = Instant::now();
    let references = match &a.reference {
        Some(dir) => pipeline::load_references(dir, &all_views, w, h)?,
        None => {
            let pb = progress_bar(
                (w * h) as u64 * all_views.len() as u64,
                a.quiet,
                "references",
            );
            let refs = renderer.render_views(&all_views, &settings, &|k| pb.inc(k));
            pb.finish_and_clear();
            refs
        }
    };
    let masks = pipeline::geometry_masks(&renderer, &all_views, &references);
    // A view that sees no scene geometry has no pixel to fit or to measure: leave it out.
    // A given reference's mask is its alpha: say so, rather than blame the geometry.
    let why = match &a.reference {
        Some(dir) => format!(
            "its reference in {} has zero alpha (coverage) everywhere",
            dir.display()
        ),
        None => "it sees no scene geometry".to_string(),
    };
    if !masks.iter().any(|m| m.contains(&true)) {
        let names: Vec<&str> = all_views.iter().map(|c| c.name.as_str()).collect();
        bail!(
            "{}: no view has a pixel to fit ({}: {why}): there is nothing to fit",
            a.scene.display(),
            names.join(", ")
        );
    }
    if a.reference.is_none() {
        let dir = a.out.join("reference");
        std::fs::create_dir_all(&dir).map_err(|e| lightprobe::Error::io(&dir, e))?;
        for (img, cam) in references.iter().zip(&all_views) {
            imageio::write_exr(&dir.join(format!("{}.exr", cam.name)), img)?;
        }
    }
    let pipeline::SeenViews {
        views,
        references,
        masks,
        blind,
    } = pipeline::seen_views(&all_views, references, masks);
    for name in &blind {
        eprintln!(
            "lightprobe: warning: view {name:?} is left out of the fit and of the errors: {why}"
        );
    }
    let reference_seconds = t.elapsed().as_secs_f64();
    let bar = |what: &str, passes: u64| {
        progress_bar((w * h) as u64 * views.len() as u64 * passes, a.quiet, what)
    };

    // ---- Resolution from the data ----
    let template = FitSettings {
        smooth: a.smooth,
        ridge: a.ridge,
        time_limit: std::time::Duration::from_secs_f64(a.time_limit),
        holdout: model_auto,
        ..FitSettings::new(&settings, rings, solver, spp, rounds)
    };
    let mut selection = None;
    if auto {
        let pb = bar("choosing rings", candidates.len() as u64 * rounds as u64);
        let s = estimate::select::select_rings(
            &renderer,
            &views,
            &references,
            &masks,
            candidates,
            &template,
            &mut |_| None,
            &|k| pb.inc(k),
        )
        .context("--rings auto: no candidate")?;
        pb.finish_and_clear();
        rings = s.rings;
        selection = Some(s);
    }

    // ---- Fit, re-render, representation limit ----
    let options = pipeline::EstimateOptions {
        fit: FitSettings { rings, ..template },
        evaluate: !a.fit_only,
        // The reference lighting again from the re-render's paths (the seed the fit never saw).
        noise_floor: true,
        oracle: a.oracle,
    };
    let pb = bar("estimate", options.passes(0));
    let outcome = pipeline::run(
        &renderer,
        &renderer,
        &views,
        &references,
        &masks,
        &scene.lights,
        scene.center(),
        &options,
        &settings,
        None,
        &|k| pb.inc(k),
    )
    .with_context(|| a.scene.display().to_string())?;
    pb.finish_and_clear();
    let fit = &outcome.fit;
    let (errors, limit) = (&outcome.errors, &outcome.limit);
    let noise_floor = &outcome.noise_floor;
    for (ch, c) in fit.channels.iter().enumerate() {
        if !c.converged {
            eprintln!(
                "lightprobe: warning: the {:?} solver did not converge in channel {} within {} iterations / {} s (KKT violation {:.2e})",
                solver,
                ["R", "G", "B"][ch],
                c.iterations,
                a.time_limit,
                c.kkt_violation
            );
        }
    }
    let converged = fit.channels.iter().all(|c| c.converged);
    write_envmap(&a.out, "envmap", &fit.envmap)?;
    if !outcome.renders.is_empty() {
        write_renders(
            &a.out.join("estimate"),
            &outcome.renders,
            &views,
            &references,
            &masks,
        )?;
    }
    let rerender_seconds = outcome.rerender_seconds;

    // ---- Sphere lights (--model spheres[:K] | auto) ----
    let mut spheres_json = serde_json::Value::Null;
    let mut spheres_lines = Vec::new();
    let mut model_selection = None;
    let max_lights = match a.model {
        ModelArg::Envmap => 0,
        ModelArg::Spheres(Some(k)) => k,
        ModelArg::Spheres(None) | ModelArg::Auto => 3,
    };
    let (lo, hi) = scene.mesh.bounds();
    let size = (hi.x - lo.x).max(hi.z - lo.z).max(1e-3);
    let paths = estimate::spheres::PathCache::default();
    let obs = estimate::spheres::Observations {
        cameras: &views,
        masks: &masks,
        references: &references,
        bin: 4,
        holdout: choose_k,
        background: None,
        paths: Some(&paths),
    };
    let mut sphere_models = Vec::new();
    if max_lights > 0 {
        let pb = bar("sphere lights", max_lights as u64);
        sphere_models = pipeline::run_sphere_models(
            &renderer,
            &renderer,
            &obs,
            &fit.envmap,
            &scene.lights,
            (scene.center(), size),
            max_lights,
            choose_k,
            &settings,
            !a.fit_only,
            &|k| pb.inc(k),
        )
        .with_context(|| format!("{}: --model spheres", a.scene.display()))?;
        pb.finish_and_clear();
    }
    // --model auto: sphere models again, with an envmap behind their lights.
    let bases: Vec<_> = pipeline::background_bases(&sphere_models, &references, &masks)
        .into_iter()
        .filter(|_| model_auto)
        .map(|b| b.fit.clone())
        .collect();
    for base in &bases {
        let pb = bar(&format!("spheres:{} + envmap", base.requested), 1);
        let combined = pipeline::run_with_background(
            &renderer,
            &renderer,
            &obs,
            base,
            rings,
            &scene.lights,
            (scene.center(), size),
            &settings,
            true,
            &|k| pb.inc(k),
        )
        .with_context(|| format!("{}: --model auto (lights + envmap)", a.scene.display()))?;
        pb.finish_and_clear();
        sphere_models.push(combined);
    }
    let mut chosen = sphere_models.len().checked_sub(1);
    if choose_k {
        let sel = pipeline::select_model(
            model_auto.then_some(&outcome),
            &sphere_models,
            &references,
            &masks,
        )
        .context("--model: no candidate")?;
        chosen = sphere_models
            .iter()
            .position(|m| sel.chosen == m.fit.model_name());
        spheres_lines.push(format!(
            "model chosen: {} (held-out relMAE {}; lowest: {})",
            sel.chosen,
            sel.candidates
                .iter()
                .map(|c| format!("{} {:.2}%", c.model, 100.0 * c.validation_rel_mae))
                .collect::<Vec<_>>()
                .join(", "),
            sel.best
        ));
        model_selection = Some(sel);
    }
    // Chosen on held-out pixels: fitted again on all of them.
    if let Some(i) = chosen.filter(|_| choose_k) {
        let pb = bar("refit on all pixels", 1);
        sphere_models[i] = pipeline::refit_on_all_pixels(
            &renderer,
            &renderer,
            &obs,
            &sphere_models[i].fit,
            &scene.lights,
            scene.center(),
            &settings,
            true,
            &|k| pb.inc(k),
        )
        .with_context(|| format!("{}: --model (refit on all pixels)", a.scene.display()))?;
        pb.finish_and_clear();
    }
    if let Some(so) = chosen.map(|i| &sphere_models[i]) {
        write_spheres(&a.out.join("spheres"), so, &views, &references, &masks)?;
        spheres_lines.extend(spheres_summary(so, errors));
        spheres_json = spheres_report(so);
    }
    let oracle_seconds = outcome.oracle_seconds;

    let recovery = &outcome.recovery;
    let per_view: Vec<_> = views
        .iter()
        .enumerate()
        .map(|(i, cam)| {
            let e = errors.get(i);
            json!({
                "view": cam.name,
                "estimate": e.map(metrics_json),
                "noise_floor": noise_floor.get(i).map(metrics_json),
                "representation_limit": limit.get(i).map(metrics_json),
                "rel_mae_over_noise_floor": e.zip(noise_floor.get(i)).map(|(e, n)| e.rel_mae / n.rel_mae),
                "rel_mae_over_representation_limit": e.zip(limit.get(i)).map(|(e, l)| e.rel_mae / l.rel_mae),
            })
        })
        .collect();
    let mean = pipeline::mean_rel_mae;
    let report = json!({
        "lightprobe_version": lightprobe::VERSION,
        "scene": a.scene,
        "rings": rings,
        "rings_selection": selection,
        "cells": fit.envmap.grid.cell_count(),
        "solver": solver,
        "smooth": a.smooth,
        "ridge": a.ridge,
        "transport_spp": spp,
        "rounds": rounds,
        "settings": settings,
        "rel_mae": mean(errors),
        "noise_floor_rel_mae": mean(noise_floor),
        "representation_limit_rel_mae": mean(limit),
        "views": per_view,
        "views_without_geometry": blind,
        "channels": fit.channels,
        "light_recovery": recovery,
        "model": model_selection.as_ref().map_or(
            chosen.map_or("envmap".to_string(), |i| sphere_models[i].fit.model_name()),
            |m| m.chosen.clone(),
        ),
        "model_selection": model_selection,
        "spheres": spheres_json,
        "sphere_candidates": if choose_k { sphere_models.iter().map(spheres_report).collect::<Vec<_>>() } else { vec![] },
        "timings": {
            "references_seconds": reference_seconds,
            // The noise floor's render shares the re-render's camera paths: its cost is in
            // rerender_seconds.
            "noise_floor_seconds": 0.0,
            "transport_seconds": fit.transport_seconds,
            "solve_seconds": fit.solve_seconds,
            "rings_selection_seconds": selection.as_ref().map(|s| s.seconds),
            "fit_seconds": fit.transport_seconds + fit.solve_seconds,
            "rerender_seconds": rerender_seconds,
            "oracle_seconds": oracle_seconds,
            "total_seconds": t_all.elapsed().as_secs_f64(),
        },
        "memory": { "transport_bytes": fit.transport_bytes, "peak_bytes": lightprobe::memory::peak_bytes() },
        "threads": rayon::current_num_threads(),
        "status": if converged { "ok" } else { "not-converged" },
    });
    let text = serde_json::to_string_pretty(&report)? + "\n";
    imageio::write_bytes(&a.out.join("report.json"), text.as_bytes())?;
    // Outputs are complete and valid either way; the exit code tells scripts the fit stopped
    // at its limits.
    let not_converged = || {
        anyhow::anyhow!(
            "{}: the {:?} solver did not converge (\"status\": \"not-converged\"; the envmap is written); pass --allow-nonconvergence to exit 0 anyway",
            a.out.join("report.json").display(),
            solver
        )
    };
    if a.json {
        print!("{text}");
        if !converged && !a.allow_nonconvergence {
            return Err(not_converged());
        }
        return Ok(());
    }
    println!(
        "{rings} rings ({} cells), {:?} solver, transport {spp} spp",
        fit.envmap.grid.cell_count(),
        solver
    );
    if let Some(sel) = &selection {
        println!(
            "rings auto: {} (held-out relMAE {}; lowest at {} rings), {:.1} s",
            sel.rings,
            sel.candidates
                .iter()
                .map(|c| format!("{}: {:.2}%", c.rings, 100.0 * c.validation_rel_mae))
                .collect::<Vec<_>>()
                .join(", "),
            sel.best_rings,
            sel.seconds
        );
    }
    for (i, cam) in views.iter().enumerate().filter(|(i, _)| *i < errors.len()) {
        let mut line = format!("{:<12} relMAE {:.2}%", cam.name, 100.0 * errors[i].rel_mae);
        if let Some(nf) = noise_floor.get(i) {
            line += &format!(
                "  noise floor {:.2}% (×{:.2})",
                100.0 * nf.rel_mae,
                errors[i].rel_mae / nf.rel_mae
            );
        }
        if let Some(l) = limit.get(i) {
            line += &format!(
                "  representation limit {:.2}% (×{:.2})",
                100.0 * l.rel_mae,
                errors[i].rel_mae / l.rel_mae
            );
        }
        println!("{line}");
    }
    for line in &spheres_lines {
        println!("{line}");
    }
    for (k, r) in recovery.iter().enumerate() {
        if r.cluster_cells > 0 {
            println!(
                "light {k}: direction off by {:.1}°, power ratio {:.2}",
                r.angle_error_degrees, r.power_ratio
            );
        } else {
            // Every bright cluster went to a brighter light: none is left for this one.
            println!("light {k}: not recovered (no bright cluster left for it)");
        }
    }
    println!(
        "fit {:.2} s (transport {:.2} s, solve {:.2} s); total {:.1} s; peak memory {:.0} MiB; {}",
        fit.transport_seconds + fit.solve_seconds,
        fit.transport_seconds,
        fit.solve_seconds,
        t_all.elapsed().as_secs_f64(),
        lightprobe::memory::peak_bytes() as f64 / (1u64 << 20) as f64,
        a.out.join("report.json").display()
    );
    if !converged && !a.allow_nonconvergence {
        return Err(not_converged());
    }
    Ok(())
}
