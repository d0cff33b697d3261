//! `estimate`: the lighting that best explains reference images. Flags become
//! [`EstimateSettings`]; the library's one estimate job does the work; this prints a summary.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::Context;

use lightprobe::Error;
use lightprobe::estimate::job::{
    self, EstimateReport, EstimateSettings, Exposure, Job, LightModel, Progress, References, Rings,
};
use lightprobe::estimate::spheres::LightStatus;
use lightprobe::output;
use lightprobe::render::{Lights, RenderSettings, Renderer};
use lightprobe::scene::{Scene, sidecar};

use super::{
    Bars, ColourArg, FitAlbedoArg, SceneArgs, SolverArg, check_memory, outln, prepare_out_dir, say,
};
use lightprobe::estimate::albedo::{AlbedoMethod, AlbedoReport, MaterialStatus};

/// `--model`: the envmap, K sphere lights (None: 1 to 3, chosen on held-out pixels), or
/// chosen from the data.
fn parse_model(s: &str) -> Result<LightModel, String> {
    match s {
        "envmap" => Ok(LightModel::Envmap),
        "spheres" => Ok(LightModel::Spheres(None)),
        "auto" => Ok(LightModel::Auto),
        _ => match s.strip_prefix("spheres:").map(str::parse::<usize>) {
            Some(Ok(k)) if (1..=8).contains(&k) => Ok(LightModel::Spheres(Some(k))),
            _ => Err(format!(
                "expected envmap, spheres, spheres:K (K = 1..8) or auto, got {s:?}"
            )),
        },
    }
}

/// `--saturation`: a finite radiance > 0.
fn parse_saturation(s: &str) -> Result<f32, String> {
    match s.parse::<f32>() {
        Ok(x) if x.is_finite() && x > 0.0 => Ok(x),
        _ => Err(format!("expected a radiance > 0, got {s:?}")),
    }
}

/// `--exposure`.
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum ExposureArg {
    Shared,
    PerView,
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

#[derive(clap::Args)]
pub struct Args {
    #[command(flatten)]
    scene: SceneArgs,
    /// Output folder (created if missing).
    #[arg(long, short)]
    out: PathBuf,
    /// Folder of references named <view>.exr (RGB or RGBA, half or float; alpha = coverage),
    /// <view>.hdr (Radiance), or <view>.png / .jpg / .jpeg (8 or 16 bit, sRGB unless --linear), the
    /// first of these that exists, with an optional <view>.mask.png (black = left out). They also set the views' image size
    /// when neither the sidecar nor --height does (default: render them from the scene's
    /// lights into OUT/reference/).
    #[arg(long)]
    reference: Option<PathBuf>,
    /// 8- and 16-bit references (PNG, JPEG) hold linear values (default: sRGB-encoded, as
    /// cameras write them).
    #[arg(long, requires = "reference")]
    linear: bool,
    /// Leave out reference pixels with any channel at or above this radiance (saturated);
    /// 8- and 16-bit references always lose the pixels at their format's maximum.
    #[arg(long, value_parser = parse_saturation, requires = "reference")]
    saturation: Option<f32>,
    /// `shared`: the references are radiance at one exposure. `per-view`: each view's
    /// reference has its own unknown exposure (photographs at different shutter, aperture or
    /// gain), fitted beside the lighting by alternating fits (2–8); report.json
    /// gives the views' exposures relative to their geometric mean, the unit the lighting is
    /// then in (photographs cannot tell the overall scale).
    #[arg(long, value_enum, default_value_t = ExposureArg::Shared)]
    exposure: ExposureArg,
    /// Fit the albedo beside the lighting: `materials` corrects each material's albedo by an
    /// RGB multiplier (of its constant, or of its texture's factor; vertex colours kept), from
    /// the pixels that see it alone; with --model envmap jointly with the envmap (1–4
    /// transport passes, then the fit), with other models by alternating fits (2–8). A
    /// material seen alone by fewer than 64 pixels, or whose albedo the images cannot tell
    /// from the light (lit only by light no other material sees), is kept as given and
    /// reported so; it takes two such materials sharing light, or one beside a trusted one.
    /// report.json's "albedo" lists every material's given and fitted albedo; the written
    /// glTF, Blender and Mitsuba scenes carry the fitted one. With --exposure per-view the
    /// exposures alternate around these fits (with the envmap, each a joint fit); not with
    /// --model auto. `texels` then corrects each fitted textured
    /// material's texture by a grid of multipliers (--texel-grid cells, smooth by
    /// --texel-smoothness) from the pixels that see it, and fits the lighting again, up to 3
    /// rounds: shading baked into a photographed texture is taken out where the lighting does
    /// not explain it. The corrected textures are written as albedo_textures/*.png beside the
    /// glTF export (and as EXRs in the Blender and Mitsuba exports).
    #[arg(long, value_enum)]
    fit_albedo: Option<FitAlbedoArg>,
    /// `--fit-albedo texels`: cells along each texture's longer side of its correction grid
    /// (4 to 256). Finer follows sharper baked shading; cells few pixels see lean on their
    /// neighbours (--texel-smoothness). [default: 32]
    #[arg(long)]
    texel_grid: Option<u32>,
    /// `--fit-albedo texels`: how strongly neighbouring cells of a correction are pulled
    /// together (relative to a cell's own pixels; 0 = not at all). [default: 1]
    #[arg(long)]
    texel_smoothness: Option<f64>,
    /// Sphere models: most pixels the fit compares (at least 4096). A capture that sees more
    /// is fitted on whole 4×4 blocks of its pixels spread over every view, and scored on all
    /// of them; each fitted pixel keeps about 11 KB of camera paths (at 2 bounces) and is lit
    /// by each of the fit's hundreds of renders. [default: 32768]
    #[arg(long)]
    sphere_pixels: Option<usize>,
    /// Materials whose albedo is known (comma-separated glTF material names): kept as given,
    /// they fix the scale between albedo and light that images cannot tell (default: the
    /// fitted materials' pixel-weighted geometric-mean multiplier is kept at 1, so the light's
    /// level is as right as the given albedo on average).
    #[arg(long, value_delimiter = ',', requires = "fit_albedo")]
    trust_albedo: Vec<String>,
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
    /// three quarters of the pixels, the fewest within one standard error of the best on the
    /// held-out quarter kept; `auto`: the same with two more candidates, the envmap, and the
    /// sphere model chosen so far with an envmap behind its lights (`envmap+spheres:K`, for
    /// light from afar beside near lights; written as spheres/lights.ron plus
    /// spheres/background.ron and .exr). Choosing stops at the first model that re-renders
    /// within 10% of the noise floor and is chosen over every smaller one: no larger one could
    /// change the choice.
    #[arg(long, default_value = "envmap", value_parser = parse_model)]
    model: LightModel,
    /// Resolutions `--rings auto` chooses from.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "3,5,7,9,11,13,15,17,19,21,23,25,27"
    )]
    rings_candidates: Vec<u32>,
    #[arg(long, value_enum, default_value_t = SolverArg::Nnls)]
    solver: SolverArg,
    /// Samples per pixel of the transport estimate, over all its parts or rounds (default: the
    /// sidecar's).
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
    /// How NNLS treats a cell's three channels. `together` removes the red, green and blue
    /// patchwork of near-white lights at equal error, but its clusters' directions scatter
    /// more between seeds than their intervals say: see docs/design.md.
    #[arg(long, value_enum, default_value_t = ColourArg::PerChannel)]
    colour: ColourArg,
    /// How the transport's --spp is split. nnls (default 4): into that many independent
    /// parts, whose cell sampling a pilot pass over a quarter of the pixels steers (the fit
    /// takes TᵀT from products of different parts: unbiased from 2 on). gradient (default 3):
    /// into sequential rounds, each sampling cells by the estimate so far.
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

impl Args {
    /// The estimate's settings: these flags over the sidecar's defaults.
    fn settings(&self, scene: &Scene) -> EstimateSettings {
        let solver = self.solver.into();
        EstimateSettings {
            rings: match self.rings {
                Some(RingsArg::Fixed(r)) => Rings::Fixed(r),
                Some(RingsArg::Auto) => Rings::Auto(self.rings_candidates.clone()),
                None => Rings::Fixed(scene.settings.rings),
            },
            model: self.model,
            solver,
            spp: self.spp.unwrap_or(scene.settings.spp),
            rounds: self.rounds.unwrap_or(solver.default_rounds()),
            smooth: self.smooth,
            ridge: self.ridge,
            colour: self.colour.into(),
            // Checked by `EstimateSettings::check`; NaN and negatives become zero, which fails it.
            time_limit: Duration::try_from_secs_f64(self.time_limit).unwrap_or(Duration::ZERO),
            evaluate: !self.fit_only,
            noise_floor: true,
            oracle: self.oracle,
            exposure: match self.exposure {
                ExposureArg::Shared => Exposure::Shared,
                ExposureArg::PerView => Exposure::PerView,
            },
            diagnose: true,
            fit_albedo: self.fit_albedo.map(Into::into),
            trust_albedo: self.trust_albedo.clone(),
            texel_grid: self
                .texel_grid
                .unwrap_or(lightprobe::estimate::texels::DEFAULT_TEXEL_GRID),
            texel_smoothness: self
                .texel_smoothness
                .unwrap_or(lightprobe::estimate::texels::DEFAULT_TEXEL_SMOOTHNESS),
            sphere_pixels: self
                .sphere_pixels
                .unwrap_or(lightprobe::estimate::spheres::FIT_PIXELS),
        }
    }

    /// A settings error in the words of these flags.
    fn flag_error(&self, e: Error) -> anyhow::Error {
        let Error::Setting {
            name,
            expected,
            got,
        } = &e
        else {
            if self.fit_only && matches!(self.exposure, ExposureArg::PerView) {
                return anyhow::anyhow!(
                    "--exposure per-view compares each view's re-render with its reference; it cannot be used with --fit-only"
                );
            }
            if self.fit_only && self.fit_albedo.is_some() {
                return anyhow::anyhow!(
                    "--fit-albedo compares each material's re-rendered pixels with the references'; it cannot be used with --fit-only"
                );
            }
            if self.fit_only && self.model.chooses() {
                return anyhow::anyhow!(
                    "--model auto and --model spheres (without :K) compare the models' re-renders; they cannot be used with --fit-only"
                );
            }
            return e.into();
        };
        match *name {
            "rings" if matches!(self.rings, Some(RingsArg::Auto)) => {
                anyhow::anyhow!("--rings-candidates must be {expected}, got {got}")
            }
            "texel grid" => anyhow::anyhow!("--texel-grid must be {expected}, got {got}"),
            "sphere pixels" => anyhow::anyhow!("--sphere-pixels must be {expected}, got {got}"),
            "texel smoothness" => {
                anyhow::anyhow!("--texel-smoothness must be {expected}, got {got}")
            }
            "time limit" => anyhow::anyhow!(
                "--time-limit must be a positive number of seconds, at most 1e6, got {}",
                self.time_limit
            ),
            _ => super::flag_error(e),
        }
    }
}

pub fn run(a: Args) -> anyhow::Result<()> {
    let t_all = Instant::now();
    let mut scene = a.scene.load()?;
    let path = &a.scene.scene;
    if let Some(dir) = a.reference.as_ref().filter(|_| !scene.size_given) {
        let found = lightprobe::estimate::pipeline::reference_sizes(dir, &scene.cameras)?;
        let sizes: Vec<_> = found.iter().map(|f| f.0).collect();
        scene.size_views(&sizes, |i| found[i].1.clone())?;
    }
    let texels = matches!(a.fit_albedo, Some(FitAlbedoArg::Texels));
    if !texels && (a.texel_grid.is_some() || a.texel_smoothness.is_some()) {
        anyhow::bail!(
            "--texel-grid and --texel-smoothness shape the texel corrections of --fit-albedo texels; without it they do nothing"
        );
    }
    if a.sphere_pixels.is_some() && a.model.max_lights() == 0 {
        anyhow::bail!(
            "--sphere-pixels limits the pixels a sphere-light fit compares; with --model envmap there is none (use --model spheres, spheres:K or auto)"
        );
    }
    let settings = a.settings(&scene);
    settings.check().map_err(|e| a.flag_error(e))?;
    if let Some(name) = a
        .trust_albedo
        .iter()
        .find(|n| scene.materials.iter().filter(|m| &m.name == *n).count() > 1)
    {
        anyhow::bail!(
            "{}: --trust-albedo names material {name:?}, which names several of the scene's materials",
            path.display()
        );
    }
    if let Some(name) = a
        .trust_albedo
        .iter()
        .find(|n| !n.is_empty() && !scene.materials.iter().any(|m| &m.name == *n))
    {
        anyhow::bail!(
            "{}: --trust-albedo names material {name:?}, which the scene does not have (it has {})",
            path.display(),
            lightprobe::estimate::albedo::material_names(&scene.materials)
        );
    }
    anyhow::ensure!(
        a.reference.is_some() || !scene.lights.is_empty(),
        "{}: has no sphere or point lights to render references from; pass --reference DIR",
        path.display()
    );
    let views = scene.cameras.len() as u64;
    let pixels = scene.pixel_count();
    let size = match scene.common_size() {
        Some((w, h)) => format!("{w}×{h} × {views} views"),
        None => format!("{pixels} pixels in {views} views"),
    };
    let rings = settings.ring_counts().iter().copied().max().unwrap_or(1);
    let spheres = settings.model.max_lights() > 0;
    check_memory(
        settings.memory_needed(pixels, scene.settings.max_bounces, &scene.materials),
        || match spheres {
            true => format!("sphere lights and {rings} rings at {size}"),
            false => format!("{rings} rings at {size}"),
        },
        match spheres {
            // The sphere model keeps its camera paths: they grow with the pixels.
            true => {
                "; the sphere model keeps its camera paths per pixel: use fewer or smaller views (--views)"
            }
            false => "; use fewer rings",
        },
    )?;
    // The glTF written back must not land on the scene it came from.
    let written = lightprobe::scene::export::written_name(&scene.gltf);
    for dir in [a.out.clone(), a.out.join("spheres")] {
        let target = dir.join(written);
        if same_file(&target, &scene.gltf) {
            anyhow::bail!(
                "{}: --out {} would write {} over it; pick another --out",
                scene.gltf.display(),
                a.out.display(),
                target.display()
            );
        }
    }
    let _lock = prepare_out_dir(&a.out, lightprobe::output::LOCK_FILE)?;
    let render = RenderSettings::from_scene(&scene.settings);
    let true_lights = Lights::new(scene.lights.clone());
    let renderer = Renderer::new(&scene, &true_lights);
    let bars = Bars::new(a.quiet);
    let references = match &a.reference {
        Some(dir) => References::Folder(
            dir,
            lightprobe::imageio::Decoding {
                linear: a.linear,
                saturation: a.saturation,
            },
        ),
        None => References::Render,
    };
    let in_scene = || path.display().to_string();
    let seen = job::observe(&renderer, &render, references, &bars).with_context(in_scene)?;
    bars.finish();
    for name in &seen.blind {
        say(&format!(
            "lightprobe: warning: view {name:?} is left out of the fit and of the errors: {}",
            seen.blind_reason
        ));
    }
    let job = Job::new(&renderer, &seen, &render, &settings);
    let mut estimate = job::run(&job, &bars).with_context(in_scene)?;
    bars.finish();
    let report = &mut estimate.report;
    report.scene = path.clone();
    for (ch, c) in report.channels.iter().enumerate() {
        if !c.converged {
            say(&format!(
                "lightprobe: warning: the {:?} solver stopped after {} iterations in channel {} without converging (KKT violation {:.2e}; it stops at its iteration limit or after --time-limit {} s)",
                report.solver,
                c.iterations,
                ["R", "G", "B"][ch],
                c.kkt_violation,
                a.time_limit
            ));
        }
    }
    if let Some(a) = report.albedo.as_ref() {
        let what = match a.method {
            AlbedoMethod::Joint => "joint passes",
            AlbedoMethod::Alternation => "fits",
        };
        if a.stalled {
            say(&format!(
                "lightprobe: warning: the albedo's joint fit stopped on a singular system after {} {what}: the albedo is where it stopped; trust more materials (--trust-albedo) or fit a sphere model",
                a.fits
            ));
        } else if !a.converged {
            say(&format!(
                "lightprobe: warning: the albedo did not converge in {} {what} (the last still moved one by {:.2}%): the model may fit the images too poorly to tell albedo from lighting; check the fit test, or try a sphere model",
                a.fits,
                100.0 * a.last_change
            ));
        }
        if !a
            .materials
            .iter()
            .any(|m| m.status == MaterialStatus::Fitted)
        {
            say(
                "lightprobe: warning: no material's albedo was fitted (report.json \"albedo\" says why for each): at least two materials must be seen alone by 64 pixels and share light, or one besides a trusted one",
            );
        }
    }
    if let Some(e) = report.exposure.as_ref().filter(|e| !e.converged) {
        say(&format!(
            "lightprobe: warning: the exposures did not converge in {} fits (the last still moved one by {:.2}%): the views may not show one scene under one lighting (swapped photographs?), or the model fits them too poorly to tell exposure from lighting",
            e.fits,
            100.0 * e.last_change
        ));
    }
    // The images, maps, exports, figures and page: seconds on a large capture.
    bars.phase("writing outputs", 1);
    let notes = output::write_estimate(
        &a.out,
        Some(&scene),
        &mut estimate,
        &seen,
        a.reference.is_none(),
        t_all,
    )?;
    bars.advance(1);
    bars.finish();
    for note in notes {
        say(&format!("lightprobe: note: {note}"));
    }
    let report = &estimate.report;
    // Said once the outputs are written: a run that fails says only why it failed.
    if let Some(t) = report.fit_test.as_ref().filter(|t| t.misfit) {
        say(&misfit_warning(t));
        if report.albedo.is_some() {
            say(
                "lightprobe: warning: the albedo was fitted beside a light model that does not explain the images, so it has taken up part of the misfit: trust the fitted albedo only once the fit test passes (try --model auto)",
            );
        }
    }
    if a.json {
        super::print(&output::report_json(report).map_err(anyhow::Error::msg)?)?;
    } else {
        for line in summary(report) {
            outln!("{line}")?;
        }
        outln!(
            "total {:.1} s; peak memory {:.0} MiB; {}",
            report.timings.total_seconds,
            report.memory.peak_bytes as f64 / (1u64 << 20) as f64,
            a.out.join("report.json").display()
        )?;
    }
    // The outputs are complete and valid either way; the exit code tells scripts the fit
    // stopped at its limits.
    if report.status != job::FitStatus::Ok && !a.allow_nonconvergence {
        anyhow::bail!(
            "{}: the {:?} solver did not converge (\"status\": \"not-converged\"; the envmap is written); pass --allow-nonconvergence to exit 0 anyway",
            a.out.join("report.json").display(),
            report.solver
        );
    }
    Ok(())
}

/// Whether two paths name one existing file.
fn same_file(a: &std::path::Path, b: &std::path::Path) -> bool {
    match (a.canonicalize(), b.canonicalize()) {
        (Ok(x), Ok(y)) => x == y,
        _ => false,
    }
}

/// The summary lines of a report, each saying which model its figures belong to.
fn summary(r: &EstimateReport) -> Vec<String> {
    let mut lines = vec![format!(
        "envmap: {} rings ({} cells), {:?} solver, transport {} spp",
        r.rings, r.cells, r.solver, r.transport_spp
    )];
    if let Some(sel) = &r.rings_selection {
        lines.push(format!(
            "rings auto: {} (held-out relMAE {}; lowest at {} rings), {:.1} s",
            sel.rings,
            sel.candidates
                .iter()
                .map(|c| format!("{}: {:.2}%", c.rings, 100.0 * c.validation_rel_mae))
                .collect::<Vec<_>>()
                .join(", "),
            sel.best_rings,
            sel.seconds
        ));
    }
    for v in &r.views {
        let Some(e) = v.estimate else { continue };
        let mut line = format!("envmap, {:<12} relMAE {:.2}%", v.view, 100.0 * e.rel_mae);
        if let Some(nf) = v.noise_floor_rel_mae {
            line += &format!("  noise floor {:.2}% (×{:.2})", 100.0 * nf, e.rel_mae / nf);
        }
        if let Some(t) = v.true_lights {
            line += &format!("  scene's lights {:.2}%", 100.0 * t.rel_mae);
        }
        if let Some(l) = v.representation_limit {
            line += &format!(
                "  representation limit {:.2}% (×{:.2})",
                100.0 * l.rel_mae,
                e.rel_mae / l.rel_mae
            );
        }
        lines.push(line);
    }
    // The brightest clusters, with 95% intervals where the jackknife measured them: a cone of
    // 2.448 σ per axis, ± 1.96 σ on the power (the scatter of the fit; a coarse grid's or a
    // near light's bias is not in it).
    for (k, c) in r.clusters.iter().take(3).enumerate() {
        let d = c.direction;
        let intervals = match (c.direction_sigma_degrees, c.power_sigma_relative) {
            (Some(a), Some(p)) => format!(
                " ± {:.2}°, power {:.4} ± {:.1}% (95% intervals of its scatter; bias not included)",
                2.448 * a,
                c.power,
                100.0 * 1.96 * p
            ),
            _ => format!(", power {:.4}", c.power),
        };
        let [r_, g_, b_] = c.chromaticity;
        lines.push(format!(
            "envmap cluster {k} ({} cells): direction ({:.3}, {:.3}, {:.3}){intervals}; colour R:G:B {r_:.2}:{g_:.2}:{b_:.2}",
            c.cells.len(),
            d[0],
            d[1],
            d[2]
        ));
    }
    if r.clusters
        .first()
        .is_some_and(|c| c.direction_sigma_degrees.is_none())
    {
        lines.push(
            "envmap clusters: no intervals (measured only with the NNLS solver, --colour \
             per-channel and at most 17 rings, and when every jackknife replicate converged)"
                .into(),
        );
    }
    for (k, rec) in r.light_recovery.iter().enumerate() {
        lines.push(if rec.cluster_cells > 0 {
            format!(
                "envmap, light {k}: direction off by {:.1}°, power ratio {:.2}",
                rec.angle_error_degrees, rec.power_ratio
            )
        } else {
            // Every bright cluster went to a brighter light: none is left for this one.
            format!("envmap, light {k}: not recovered (no bright cluster left for it)")
        });
    }
    if let Some(sel) = &r.model_selection {
        lines.push(format!(
            "model chosen: {} (held-out relMAE {}; lowest: {})",
            sel.chosen,
            sel.candidates
                .iter()
                .map(|c| format!("{} {:.2}%", c.model, 100.0 * c.validation_rel_mae))
                .collect::<Vec<_>>()
                .join(", "),
            sel.best
        ));
        if let (Some(m), Some(x)) = (&sel.at_noise_floor, sel.over_noise_floor) {
            lines.push(format!(
                "{m} re-renders at {x:.3}× the noise floor on the held-out pixels (within {:.0}%) and is chosen over every smaller model: no larger model was fitted",
                100.0 * lightprobe::estimate::select::MODEL_TOLERANCE
            ));
        }
    }
    if let Some(s) = &r.spheres {
        lines.extend(spheres_summary(s, r.rel_mae));
    }
    if let (Some(source), Some(floor)) = (r.noise_floor_source, r.noise_floor_rel_mae) {
        lines.push(format!(
            "noise floor {:.2}% ({})",
            100.0 * floor,
            match source {
                job::NoiseSource::RenderedTwin => "a second render of the true lights",
                job::NoiseSource::NeighbouringPixels => "from the residual's neighbouring pixels",
                job::NoiseSource::GivenTwins => "from the references' twins",
            }
        ));
    }
    if let Some(t) = &r.fit_test {
        lines.push(format!(
            "fit test, {}: residual {:.2}× what the noise explains (Σr²), p = {}: {}",
            t.model,
            t.test.residual_over_noise,
            p_value(t.test.p_value),
            if t.misfit {
                "does not explain the images (see the warning)"
            } else if t.test.p_value < job::MISFIT_P_VALUE {
                "a small excess, below the 1.2× that counts as a misfit"
            } else {
                "within noise"
            }
        ));
    }
    if let Some(e) = &r.exposure {
        lines.push(format!(
            "exposures relative to their geometric mean (the lighting's unit), {} fits, last change {:.2}%: {}",
            e.fits,
            100.0 * e.last_change,
            e.relative
                .iter()
                .map(|v| format!("{} ×{:.4}", v.view, v.exposure))
                .collect::<Vec<_>>()
                .join(", ")
        ));
    }
    if let Some(a) = &r.albedo {
        lines.extend(albedo_summary(a, r.timings.alternation_seconds));
    }
    lines.push(format!(
        "envmap fit {:.2} s (transport {:.2} s, solve {:.2} s)",
        r.timings.fit_seconds, r.timings.transport_seconds, r.timings.solve_seconds
    ));
    lines
}

/// The fitted albedo, a line per material.
fn albedo_summary(a: &AlbedoReport, seconds: f64) -> Vec<String> {
    let rgb = |v: [f32; 3]| format!("{:.3} {:.3} {:.3}", v[0], v[1], v[2]);
    let mut lines = vec![format!(
        "albedo fitted per material in {seconds:.1} s, {} {}, last change {:.2}%; scale: {}",
        a.fits,
        match a.method {
            AlbedoMethod::Joint => "joint passes",
            AlbedoMethod::Alternation => "fits",
        },
        100.0 * a.last_change,
        if a.trusted.is_empty() {
            "the fitted materials' mean multiplier kept at 1".to_string()
        } else {
            format!("trusted {}", a.trusted.join(", "))
        }
    )];
    for m in a
        .materials
        .iter()
        .filter(|m| m.pixels > 0 || m.status == MaterialStatus::Trusted)
    {
        let status = match m.status {
            MaterialStatus::Fitted if m.at_bound => "fitted (at albedo 1)",
            MaterialStatus::Fitted => "fitted",
            MaterialStatus::Trusted => "trusted",
            MaterialStatus::Unseen => "kept: fewer than 64 pixels see it alone",
            MaterialStatus::Unconstrained => {
                "kept: the images cannot tell its albedo from the light (trust it, or add views)"
            }
        };
        let obs = m
            .observability
            .map(|o| format!(", observability {o:.2}"))
            .unwrap_or_default();
        lines.push(format!(
            "  {:<14} given {}  fitted {}  ({}; {} px{obs})",
            m.name,
            rgb(m.given),
            rgb(m.fitted),
            status,
            m.pixels
        ));
    }
    if a.texel_rounds > 0 {
        lines.push(format!(
            "texels corrected in {} round(s) (a texture's level stays with its material):",
            a.texel_rounds
        ));
    }
    for t in &a.texels {
        lines.push(format!(
            "  {:<14} grid {}×{}, {} of its cells seen by {} px; multipliers {:.2} to {:.2}{}, last change {:.2}%{}; {}",
            t.material,
            t.grid[0],
            t.grid[1],
            t.cells_seen,
            t.pixels,
            t.range[0],
            t.range[1],
            t.sigma.map_or(
                if (t.grid[0] as usize) * (t.grid[1] as usize)
                    > lightprobe::estimate::texels::MAX_SIGMA_CELLS
                {
                    format!(
                        " (no σ: measured on grids of at most {} cells)",
                        lightprobe::estimate::texels::MAX_SIGMA_CELLS
                    )
                } else {
                    " (no σ: its system could not be solved)".to_string()
                },
                |[median, largest]| format!(
                    " (σ {:.1}% median, {:.1}% largest)",
                    100.0 * median,
                    100.0 * largest
                )
            ),
            100.0 * t.last_change,
            if t.clamped_texels > 0 {
                format!(", {} texels clamped to albedo 1", t.clamped_texels)
            } else {
                String::new()
            },
            t.file
        ));
    }
    if a.fit == lightprobe::estimate::albedo::FitAlbedo::Texels && a.texel_rounds == 0 {
        lines.push(
            "texels: no texture was corrected (why, per material, below; none listed: no fitted \
             or trusted material has a texture); only the materials' albedo was fitted"
                .into(),
        );
    }
    lines.extend(a.texel_notes.iter().map(|n| format!("  {n}")));
    lines
}

/// A p-value as people read it: tiny ones as a bound.
fn p_value(p: f64) -> String {
    if p < 1e-12 {
        "< 1e-12".into()
    } else if p < 1e-3 {
        format!("{p:.1e}")
    } else {
        format!("{p:.3}")
    }
}

/// The warning of a model that does not explain the images, with what to check.
fn misfit_warning(t: &job::ModelFitTest) -> String {
    format!(
        "lightprobe: warning: the {} model does not explain the images: its residual is {:.2}× what their noise explains (Σr², p = {}). Check, most likely first: {}.",
        t.model,
        t.test.residual_over_noise,
        p_value(t.test.p_value),
        t.causes.join("; ")
    )
}

/// Lines for a sphere-model estimate, beside the envmap's relMAE.
fn spheres_summary(s: &job::SpheresReport, envmap_rel_mae: Option<f64>) -> Vec<String> {
    let mut lines = Vec::new();
    let kept = s.lights.iter().filter(|f| f.kept()).count();
    if let Some(e) = s.rel_mae {
        lines.push(format!(
            "{} ({kept} lights): relMAE {:.2}% (envmap {:.2}%), fit {:.1} s, {} renders",
            s.model,
            100.0 * e,
            100.0 * envmap_rel_mae.unwrap_or(f64::NAN),
            s.fit_seconds,
            s.renders,
        ));
    }
    if s.fit_pixels < s.seen_pixels {
        lines.push(format!(
            "{} fitted on {} of the {} seen pixels (whole 4×4 blocks spread over every view; its relMAE is over all of them)",
            s.model, s.fit_pixels, s.seen_pixels
        ));
    }
    for (j, f) in s.lights.iter().enumerate() {
        // 95% intervals: ±1.96 σ, ×/÷ e^(1.96 σ) for the logarithmic ones, and for the
        // direction a cone of 2.448 σ (σ per axis: the 95% radius of a 2-D normal).
        let pm = |v: Option<f64>, k: f64, unit: &str| {
            v.map_or("(no interval)".into(), |v| format!("± {:.3}{unit}", k * v))
        };
        let power = match (f.power_identified, f.power_sigma_relative) {
            (Some(true), Some(p)) => format!(", power ×/÷ {:.3}", (1.96 * p).exp()),
            (Some(_), _) => ", power not identified".into(),
            (None, _) => String::new(),
        };
        let radius = match f.radius_identified {
            Some(true) => format!("radius {:.3} ({})", f.light.radius, f.radius_interval()),
            Some(false) => format!(
                "radius {:.3} not identified ({})",
                f.light.radius,
                f.radius_interval()
            ),
            None => format!("radius {:.3}", f.light.radius),
        };
        lines.push(match f.status {
            LightStatus::Identified => format!(
                "{} sphere {j}: centre ({:.3}, {:.3}, {:.3}), direction {}, distance {}, {radius}{power} (95% intervals)",
                s.model,
                f.light.center.x, f.light.center.y, f.light.center.z,
                pm(f.direction_sigma_degrees, 2.448, "°"),
                pm(f.distance_sigma_m, 1.96, " m"),
            ),
            LightStatus::DistanceUnidentified => format!(
                "{} sphere {j}: direction {}{power}; its distance is not identifiable from these images (25% nearer or farther fits within {:.1} σ)",
                s.model,
                pm(f.direction_sigma_degrees, 2.448, "°"),
                f.distance_profile_sigmas.unwrap_or(0.0)
            ),
            LightStatus::Merged { into } => format!(
                "{} sphere {j}: too close in direction to sphere {into} to tell apart; merged into it",
                s.model
            ),
            LightStatus::NoContribution => format!(
                "{} sphere {j}: changes no pixel (e.g. hidden below the table); left out",
                s.model
            ),
        });
    }
    for (k, r) in s.recovery.iter().enumerate() {
        lines.push(match (r.centre_error_m, r.radius, r.power_ratio) {
            (Some(off), Some(rad), Some(p)) => format!(
                "{} vs true light {k}: centre off {off:.3} m ({:.1}% of its {:.2} m distance), radius {rad:.3} (true {:.3}), power ×{p:.3}",
                s.model, 100.0 * off / r.true_distance_m, r.true_distance_m, r.true_radius
            ),
            _ => format!(
                "{} vs true light {k}: not recovered (the model has fewer lights)",
                s.model
            ),
        });
    }
    lines
}
