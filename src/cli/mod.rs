//! The commands of the `lightprobe` binary, one module each: flags (clap), their checks in
//! command-line terms, a call into the library, and what is printed. Work and files belong to
//! the library.

pub mod alloc;
pub mod compare;
pub mod envmap;
pub mod estimate;
pub mod experiment;
pub mod info;
pub mod render;

use std::io::{IsTerminal, Write};
use std::path::Path;
use std::sync::Mutex;

use indicatif::{ProgressBar, ProgressStyle};

use lightprobe::envmap::latlong::{Filter, Target};
use lightprobe::estimate::albedo::FitAlbedo;
use lightprobe::estimate::job::Progress;
use lightprobe::estimate::{Colour, Solver};
use lightprobe::render::Strategy;

/// Mirrors a library option enum as a clap value enum (the library does not depend on clap);
/// variant doc comments become the values' help.
macro_rules! cli_enum {
    ($cli:ident => $lib:ident { $($(#[$doc:meta])* $v:ident),+ $(,)? }) => {
        #[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
        pub enum $cli { $($(#[$doc])* $v),+ }
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
cli_enum!(ColourArg => Colour {
    /// A grey map first (which cells are lit, how brightly), then each channel as that map
    /// times a per-cell factor pulled weakly toward grey: a light's colour stays together.
    Together,
    /// Each channel fitted on its own (the paper's way); can split a white light into red,
    /// green and blue cells.
    PerChannel,
});
cli_enum!(FitAlbedoArg => FitAlbedo {
    /// One RGB multiplier per material, of its constant albedo or its texture's factor.
    Materials,
    /// The materials' multipliers, then each fitted texture corrected by a coarse grid of
    /// multipliers with a smoothness prior (shading baked into a photographed texture).
    Texels,
});
cli_enum!(TargetArg => Target {
    /// Mitsuba 3's envmap: +Y up, poles on the first and last rows.
    Mitsuba,
    /// Blender's World Environment Texture, for a scene imported from the glTF (Z up).
    Blender,
    /// pbrt-v3's lat-long infinite light (Z up, same axis change as Blender's importer).
    PbrtV3,
    /// USD's DomeLight (texture format latlong, stage +Y up): OpenEXR's lat-long map.
    Usd,
});
cli_enum!(FilterArg => Filter {
    /// The cell under each pixel centre.
    Box,
    /// Interpolated between grid points.
    Smooth,
});

/// A library error in command-line terms: a setting becomes its flag (`spp` → `--spp`).
pub fn flag_error(e: lightprobe::Error) -> anyhow::Error {
    match e {
        lightprobe::Error::Setting {
            name,
            expected,
            got,
        } => anyhow::anyhow!("--{} must be {expected}, got {got}", name.replace(' ', "-")),
        e => e.into(),
    }
}

/// Standard output could not be written (a closed pipe, a full disk).
#[derive(Debug, thiserror::Error)]
#[error("cannot write to standard output")]
pub struct StdoutError(#[source] std::io::Error);

/// Writes `text` to standard output; failing to is an error ([`StdoutError`]), never a panic.
pub fn print(text: &str) -> anyhow::Result<()> {
    let mut out = std::io::stdout().lock();
    out.write_all(text.as_bytes())
        .and_then(|()| out.flush())
        .map_err(|e| StdoutError(e).into())
}

/// [`print`] with a newline, formatted like `println!`.
macro_rules! outln {
    ($($arg:tt)*) => {
        $crate::cli::print(&format!("{}\n", format_args!($($arg)*)))
    };
}
pub(crate) use outln;

/// Whether `e` is standard output's reader having gone away.
pub fn is_broken_pipe(e: &anyhow::Error) -> bool {
    e.downcast_ref::<StdoutError>()
        .is_some_and(|StdoutError(io)| io.kind() == std::io::ErrorKind::BrokenPipe)
}

/// Writes a line to standard error, ignoring failure (there is nowhere left to report it).
pub fn say(line: &str) {
    let _ = writeln!(std::io::stderr(), "{line}");
}

/// On SIGINT, SIGTERM or SIGHUP: removes this process's temporary files, says so, and exits
/// with status 130. (Outputs are renamed into place only when complete, so an interrupted
/// run leaves its output folder as it was, plus whatever finished before.)
pub fn on_interrupt() {
    // Failing to install the handler only loses the clean-up; the run itself is unaffected.
    let _ = ctrlc::set_handler(|| {
        lightprobe::cleanup::remove_all();
        say("lightprobe: interrupted");
        std::process::exit(130);
    });
}

/// A byte count with an optional unit: `4G`, `4GiB`, `512M`, `1.5g`, `1000000` (bytes). K, M,
/// G and T are powers of 1024.
pub fn parse_size(text: &str) -> Result<u64, String> {
    let t = text.trim();
    let digits = t
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .unwrap_or(t.len());
    let (number, unit) = t.split_at(digits);
    let shift = match unit.trim().to_ascii_lowercase().as_str() {
        "" | "b" => 0,
        "k" | "kb" | "kib" => 10,
        "m" | "mb" | "mib" => 20,
        "g" | "gb" | "gib" => 30,
        "t" | "tb" | "tib" => 40,
        _ => {
            return Err(format!(
                "{text:?}: expected a size such as 4G, 512M or 2.5GiB"
            ));
        }
    };
    let value: f64 = number
        .parse()
        .map_err(|_| format!("{text:?}: expected a size such as 4G, 512M or 2.5GiB"))?;
    let bytes = value * (1u64 << shift) as f64;
    if !(bytes >= 1.0 && bytes < 2f64.powi(62)) {
        return Err(format!("{text:?}: must be at least 1 byte and below 4 EiB"));
    }
    Ok(bytes as u64)
}

/// Creates the `--out` folder, proves it writable and locks it for this run (the lock file
/// `lock_name`; see `lightprobe::output::DirLock`) before any long work starts. Keep the lock
/// until the run ends.
pub fn prepare_out_dir(dir: &Path, lock_name: &str) -> anyhow::Result<lightprobe::output::DirLock> {
    if dir.exists() && !dir.is_dir() {
        anyhow::bail!(
            "{}: exists and is not a folder (--out names a folder)",
            dir.display()
        );
    }
    Ok(lightprobe::output::prepare_dir(dir, lock_name)?)
}

/// The scene a command works on, and how large its views are.
#[derive(clap::Args)]
pub struct SceneArgs {
    /// The scene: a glTF 2.0 file (.gltf/.glb: its cameras are the views, its point lights
    /// the lights), or a RON sidecar that names one and sets views, image size, albedo, lights
    /// and render settings.
    pub scene: std::path::PathBuf,
    /// Image height of every view in pixels, the width following the sidecar's image or the
    /// camera's glTF aspectRatio (4:3 where it has none). Default: the sidecar's image; else
    /// the references' size (estimate --reference); else 480.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=lightprobe::scene::sidecar::MAX_IMAGE_SIDE as i64))]
    pub height: Option<u32>,
    /// Only these views, in this order (comma-separated camera node names; default: the
    /// sidecar's `views`, else every camera).
    #[arg(long, value_delimiter = ',')]
    pub views: Vec<String>,
}

impl SceneArgs {
    /// Loads the scene and says once, on stderr, what its files hold that the model leaves
    /// out.
    pub fn load(&self) -> anyhow::Result<lightprobe::scene::Scene> {
        let scene = lightprobe::scene::Scene::load_with(
            &self.scene,
            lightprobe::scene::LoadOptions {
                height: self.height,
                views: self.views.clone(),
            },
        )?;
        for i in &scene.ignored {
            say(&format!(
                "lightprobe: note: {}: {}: left out of lightprobe's Lambertian model: {}",
                self.scene.display(),
                i.what,
                i.properties.join("; ")
            ));
        }
        Ok(scene)
    }
}

/// Refuses a job that needs more than the memory budget allows (`lightprobe::memory`);
/// `hint` ends the message (what to do instead).
pub fn check_memory(need: u64, what: impl FnOnce() -> String, hint: &str) -> anyhow::Result<()> {
    lightprobe::memory::reserve(need, what).map_err(|e| anyhow::anyhow!("{e}{hint}"))
}

/// Progress on stderr: a bar per phase on a terminal; elsewhere (logs of batch jobs and CI)
/// a line when a phase starts and at every tenth of it.
pub struct Bars {
    quiet: bool,
    terminal: bool,
    state: Mutex<Phase>,
}

#[derive(Default)]
struct Phase {
    name: String,
    bar: Option<ProgressBar>,
    total: u64,
    done: u64,
    /// Tenths logged so far (non-terminal).
    tenths: u64,
    start: Option<std::time::Instant>,
}

impl Bars {
    pub fn new(quiet: bool) -> Bars {
        Bars {
            quiet,
            terminal: std::io::stderr().is_terminal(),
            state: Mutex::new(Phase::default()),
        }
    }

    /// A bar of `total` units outside any job (one command, one phase).
    pub fn single(quiet: bool, name: &str, total: u64) -> Bars {
        let bars = Bars::new(quiet);
        bars.phase(name, total);
        bars
    }

    /// Clears the bar of the last phase.
    pub fn finish(&self) {
        let mut s = self.state.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(bar) = s.bar.take() {
            bar.finish_and_clear();
        }
    }
}

/// A command that fails part way clears its bar before its error is printed.
impl Drop for Bars {
    fn drop(&mut self) {
        self.finish();
    }
}

impl Progress for Bars {
    fn phase(&self, name: &str, units: u64) {
        if self.quiet {
            return;
        }
        self.finish();
        let mut s = self.state.lock().unwrap_or_else(|e| e.into_inner());
        *s = Phase {
            name: name.to_string(),
            total: units.max(1),
            start: Some(std::time::Instant::now()),
            ..Phase::default()
        };
        if self.terminal {
            let bar = ProgressBar::new(units.max(1));
            bar.set_style(
                ProgressStyle::with_template(
                    "{msg:>20} [{bar:40}] {percent:>3}% {elapsed_precise} eta {eta}",
                )
                .expect("a valid template")
                .progress_chars("=> "),
            );
            bar.set_message(name.to_string());
            s.bar = Some(bar);
        } else {
            say(&format!("lightprobe: {name}: started"));
        }
    }

    fn advance(&self, units: u64) {
        if self.quiet {
            return;
        }
        let mut s = self.state.lock().unwrap_or_else(|e| e.into_inner());
        s.done = (s.done + units).min(s.total);
        if let Some(bar) = &s.bar {
            bar.set_position(s.done);
            return;
        }
        let tenths = s.done * 10 / s.total;
        if tenths > s.tenths {
            s.tenths = tenths;
            let secs = s.start.map_or(0.0, |t| t.elapsed().as_secs_f64());
            say(&format!(
                "lightprobe: {}: {}% after {secs:.1} s",
                s.name,
                tenths * 10
            ));
        }
    }
}
