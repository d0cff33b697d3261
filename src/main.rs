//! The `lightprobe` command: parse, dispatch, exit code. Each command lives in [`cli`]; the
//! work is the library's. Errors print once, as one line, with a non-zero exit code.

mod cli;

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

#[global_allocator]
static ALLOCATOR: cli::alloc::Guarded = cli::alloc::Guarded;

#[derive(Parser)]
#[command(name = "lightprobe", version, about = "Estimate the lighting of a 3D scene from images of it.", long_about = None)]
struct Cli {
    /// Worker threads (default: all cores; RAYON_NUM_THREADS also works). Results do not
    /// depend on it.
    #[arg(long, global = true)]
    threads: Option<usize>,
    /// Most memory this run may use, e.g. 4G, 512M or 2.5GiB (default: no limit of its own).
    /// Whatever the setting, the process's own limits (ulimit -v, a container's or batch
    /// job's cgroup) and the machine's free memory also bound it; work that would exceed
    /// the tightest is refused before it starts.
    #[arg(long, global = true, value_name = "SIZE", value_parser = cli::parse_size)]
    memory_limit: Option<u64>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Path-trace reference images of a scene under its lights: one linear f32 EXR per view
    /// (alpha = fraction of samples that saw geometry), a PNG preview and render.json.
    RenderReference(cli::render::Args),
    /// Photometric error of an image against a reference (relMAE, MAE, RMSE, relMSE, PSNR),
    /// over the pixels where the reference's alpha is > 0 (its geometry mask).
    Compare(cli::compare::Args),
    /// Estimate the ring environment map (or sphere lights) that best explains reference
    /// images (rendered from the scene's lights, or given with --reference), re-render it with
    /// a fresh seed and report the photometric error against the Monte Carlo noise floor.
    Estimate(cli::estimate::Args),
    /// Write a ring envmap (envmap.ron) as a lat-long OpenEXR that another renderer loads the
    /// right way up (default: Mitsuba 3's `envmap`, +Y up, poles on the first and last rows).
    ExportEnvmap(cli::envmap::ExportArgs),
    /// Average a lat-long OpenEXR environment over the cells of an N-ring grid (envmap.ron),
    /// e.g. to use any HDR environment as ground-truth lighting.
    ImportEnvmap(cli::envmap::ImportArgs),
    /// Print what lightprobe loaded from a scene as JSON: triangle count, bounds, surface
    /// area, materials, cameras (pose, field of view), lights and settings.
    Info(cli::info::Args),
    /// Generate random illumination scenarios of a scene (the paper's experiment): one sidecar
    /// per scenario with one or two sphere lights, and scenarios.json describing them.
    Scenarios(cli::experiment::ScenariosArgs),
    /// Run estimates over scenarios × samples × rings × solvers (the paper's experiment),
    /// appending one JSON line per trial to OUT/trials*.jsonl; resumable and shardable.
    Sweep(cli::experiment::SweepArgs),
    /// Charts (PNG and SVG), a results page (index.html) and a markdown summary of a sweep's
    /// trials, all shards merged: error against rings (the paper's Fig. 4), speed against
    /// accuracy with the Pareto front, error against light distance.
    Report {
        /// The sweep's output folder.
        dir: PathBuf,
        /// Print summary.json to stdout.
        #[arg(long)]
        json: bool,
    },
    /// Print a JSON Schema: of the scene sidecar (RON), or with --report of report.json.
    Schema {
        /// The schema of `estimate`'s report.json instead.
        #[arg(long)]
        report: bool,
    },
}

fn main() -> ExitCode {
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) => return usage_error(e),
    };
    cli::on_interrupt();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        // A reader that stopped reading (`| head`) is no error, as for other Unix tools.
        Err(e) if cli::is_broken_pipe(&e) => ExitCode::SUCCESS,
        Err(e) => {
            cli::say(&format!("lightprobe: error: {}", one_line(&e)));
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> anyhow::Result<()> {
    if let Some(v) = std::env::var_os("LIGHTPROBE_ISA")
        && v != "portable"
    {
        anyhow::bail!(
            "LIGHTPROBE_ISA={v:?}: the one value is `portable` (unset it to use the CPU's vector units)"
        );
    }
    lightprobe::memory::set_limit(cli.memory_limit);
    if let Some(n) = cli.threads {
        // Beyond a few threads per core there is nothing to gain, and each costs a stack.
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        anyhow::ensure!(
            (1..=4 * cores).contains(&n),
            "--threads must be between 1 and {} (4 × this machine's {cores} cores), got {n}",
            4 * cores
        );
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build_global()
            .map_err(|e| anyhow::anyhow!("cannot start the thread pool: {e}"))?;
    }
    match cli.command {
        Command::RenderReference(a) => cli::render::run(a),
        Command::Compare(a) => cli::compare::run(a),
        Command::Estimate(a) => cli::estimate::run(a),
        Command::ExportEnvmap(a) => cli::envmap::export(a),
        Command::ImportEnvmap(a) => cli::envmap::import(a),
        Command::Info(a) => cli::info::run(a),
        Command::Scenarios(a) => cli::experiment::scenarios(a),
        Command::Sweep(a) => cli::experiment::sweep(a),
        Command::Report { dir, json } => cli::experiment::report(&dir, json),
        Command::Schema { report } => cli::print(&if report {
            lightprobe::estimate::job::report_schema()
        } else {
            lightprobe::scene::sidecar::json_schema()
        }),
    }
}

/// An error and its causes as one line. An I/O error under the library's own `Io` error is
/// already worded there.
fn one_line(e: &anyhow::Error) -> String {
    let mut parts: Vec<String> = Vec::new();
    let mut under_io = false;
    for cause in e.chain() {
        if under_io && cause.downcast_ref::<std::io::Error>().is_some() {
            continue;
        }
        under_io = matches!(
            cause.downcast_ref::<lightprobe::Error>(),
            Some(lightprobe::Error::Io { .. })
        );
        parts.push(cause.to_string());
    }
    parts.join(": ")
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
    cli::say(&format!(
        "lightprobe: error: {} (see --help)",
        message.trim_start_matches("error: ")
    ));
    ExitCode::from(2)
}
