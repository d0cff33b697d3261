//! One estimate, written once: references → geometry masks → (resolution from the data) → the
//! envmap fit → its re-render, noise floor and representation limit → sphere-light models and
//! model selection → a typed [`EstimateReport`]. The `estimate` command and every sweep trial
//! run this job, so a trial is a stand-alone estimate by construction.
//!
//! The job writes no files ([`crate::output`] does) and prints nothing; it reports its phases
//! to a [`Progress`].
//!
//! ```no_run
//! use lightprobe::estimate::job::{self, EstimateSettings, References};
//! use lightprobe::render::{Lights, RenderSettings, Renderer};
//! use lightprobe::scene::Scene;
//! let scene = Scene::load(std::path::Path::new("scenes/tabletop/tabletop.ron"))?;
//! let lights = Lights::new(scene.lights.clone());
//! let renderer = Renderer::new(&scene, &lights);
//! let render = RenderSettings::from_scene(&scene.settings);
//! let settings = EstimateSettings::new(&scene.settings);
//! let seen = job::observe(&renderer, &render, References::Render, &())?;
//! let estimate = job::run(&job::Job::new(&renderer, &seen, &render, &settings), &())?;
//! println!("relMAE {:?}", estimate.report.rel_mae);
//! # Ok::<(), lightprobe::Error>(())
//! ```

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use glam::Vec3;
use schemars::JsonSchema;
use serde::Serialize;

use super::albedo::{
    self, AlbedoReport, FitAlbedo, MaterialAlbedo, MaterialPixels, MaterialStatus,
};
use super::pipeline::{self, EstimateOptions, Outcome, SeenViews, SphereOutcome};
use super::recovery::{self, ClusterEstimate, LightRecovery, SphereRecovery};
use super::select::{self, ModelSelection, Selection};
use super::spheres::{FittedLight, Observations, PathCache};
use super::texels::{self, TexelFit};
use super::{ChannelFit, Colour, FitSettings, Solver, Validation};
use crate::envmap::MAX_RINGS;
use crate::error::{Error, Result};
use crate::imageio::Image;
use crate::metrics::Metrics;
use crate::noise::{FitTest, ResidualNoise};
use crate::render::{Lights, RenderSettings, Renderer};
use crate::scene::{Camera, SceneSettings};

/// Most samples per pixel a transport may take.
pub const MAX_SPP: u32 = crate::scene::sidecar::MAX_SPP;

/// The envmap's resolution: given, or chosen from the data among candidates.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Rings {
    Fixed(u32),
    /// Each candidate fitted on three quarters of the pixels; the smallest within one
    /// standard error of the best on the held-out quarter is kept ([`select::select_rings`]).
    Auto(Vec<u32>),
}

/// The light model.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LightModel {
    /// The ring envmap alone.
    Envmap,
    /// K sphere lights at finite distance; `None`: 1 to 3, chosen on held-out pixels.
    Spheres(Option<usize>),
    /// Chosen on held-out pixels among the envmap, 1 to 3 sphere lights and sphere lights with
    /// an envmap behind them.
    Auto,
}

impl LightModel {
    /// Whether the number of lights (or the model) is chosen from the data, which compares
    /// re-renders.
    pub fn chooses(self) -> bool {
        matches!(self, LightModel::Auto | LightModel::Spheres(None))
    }

    /// The most sphere lights the model fits.
    pub fn max_lights(self) -> usize {
        match self {
            LightModel::Envmap => 0,
            LightModel::Spheres(Some(k)) => k,
            LightModel::Spheres(None) | LightModel::Auto => 3,
        }
    }
}

/// What an estimate fits and measures. [`EstimateSettings::check`] says whether it is valid.
#[derive(Debug, Clone)]
pub struct EstimateSettings {
    pub rings: Rings,
    pub model: LightModel,
    pub solver: Solver,
    /// Transport samples per pixel, over all parts (NNLS) or rounds (gradient).
    pub spp: u32,
    /// NNLS: independent parts of the transport pass; gradient: sequential rounds.
    pub rounds: u32,
    /// Smoothness weight between neighbouring cells (relative; 0 = none).
    pub smooth: f64,
    /// Ridge weight toward zero (relative to the mean diagonal of TᵀT).
    pub ridge: f64,
    /// How NNLS treats a cell's channels.
    pub colour: Colour,
    /// Wall-clock budget of each channel's solve.
    pub time_limit: Duration,
    /// Re-render the estimate with a seed the fit never saw and measure its error.
    pub evaluate: bool,
    /// With `evaluate`, also measure the noise floor: the true lights (if known) rendered
    /// from the re-render's camera paths against the references.
    pub noise_floor: bool,
    /// Also fit the best envmap of this resolution (8× the samples): the representation limit.
    pub oracle: bool,
    /// Whether the references share one exposure or each has its own.
    pub exposure: Exposure,
    /// Measure the envmap clusters' intervals ([`JACKKNIFE_GROUPS`]), make the fit test
    /// against given twins (which needs the final model rendered again for its render
    /// noise), and when the envmap model misfits, re-fit it with one more bounce at a
    /// quarter of the samples to tell whether the bounce count is the cause
    /// ([`bounce_probe`]).
    pub diagnose: bool,
    /// Fit the albedo beside the lighting ([`super::albedo`]); `None`: the scene's albedo is
    /// taken as known.
    pub fit_albedo: Option<FitAlbedo>,
    /// Materials whose albedo is known: kept as given, they fix the scale between albedo and
    /// light. Empty: the fitted materials' mean multiplier is kept at 1.
    pub trust_albedo: Vec<String>,
    /// [`FitAlbedo::Texels`]: cells along the longer side of each texture's correction grid
    /// ([`texels::grid_size`]).
    pub texel_grid: u32,
    /// [`FitAlbedo::Texels`]: weight of the correction's membrane prior ([`texels`]).
    pub texel_smoothness: f64,
    /// Most pixels a sphere fit compares ([`super::spheres::fit_masks`]).
    pub sphere_pixels: usize,
}

/// How the references' exposures relate.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum Exposure {
    /// One exposure: the references are radiance in one unit.
    #[default]
    Shared,
    /// One unknown scale per view (photographs at different shutter, aperture or gain): fitted
    /// beside the lighting by alternation ([`run`]). Only ratios between views can be known:
    /// the lighting comes out in units of the views' geometric-mean exposure.
    PerView,
}

/// `report.json`'s `exposure` with `--exposure per-view`.
#[derive(Debug, Clone, Serialize, JsonSchema)]
pub struct ExposureReport {
    /// Each fitted view's exposure relative to the geometric mean over views (its reference
    /// divided by it is what the lighting explains). The overall scale is not identifiable
    /// from the references: the lighting is in units of the geometric-mean exposure.
    pub relative: Vec<ViewExposure>,
    /// Fits made, alternating lighting and exposures (with `--fit-albedo texels`, over every
    /// texel round's alternation).
    pub fits: usize,
    /// Whether the exposures converged: the last fit asks for less than
    /// [`EXPOSURE_TOLERANCE`]'s change (with texels: the last round's last fit). When not,
    /// the exposures (and the lighting) are still moving: the views may not share a scene
    /// (swapped photographs?), or the model fits them too poorly to tell exposure from
    /// lighting.
    pub converged: bool,
    /// Largest relative change of an exposure the last fit (the one with every sample) asks
    /// for: how far the exposures reported are from converged. An alternation stops below
    /// [`EXPOSURE_TOLERANCE`] or after [`MAX_ALTERNATION_FITS`] fits (with texels, each
    /// round's; the next round starts from where it ended).
    pub last_change: f64,
}

/// One view's relative exposure.
#[derive(Debug, Clone, Serialize, JsonSchema)]
pub struct ViewExposure {
    pub view: String,
    pub exposure: f64,
}

/// Relative change of every exposure below which the alternation stops.
pub const EXPOSURE_TOLERANCE: f64 = 1e-3;
/// Most fits the alternation ([`run`]) makes, the last one with every sample included.
pub const MAX_ALTERNATION_FITS: usize = 8;

impl EstimateSettings {
    /// The sidecar's rings and samples, the NNLS solver with its default rounds, the envmap
    /// model, evaluation and noise floor on.
    pub fn new(scene: &SceneSettings) -> Self {
        EstimateSettings {
            rings: Rings::Fixed(scene.rings),
            model: LightModel::Envmap,
            solver: Solver::Nnls,
            spp: scene.spp,
            rounds: Solver::Nnls.default_rounds(),
            smooth: 0.0,
            ridge: 1e-3,
            colour: Colour::PerChannel,
            time_limit: Duration::from_secs(60),
            evaluate: true,
            noise_floor: true,
            oracle: false,
            exposure: Exposure::Shared,
            diagnose: true,
            fit_albedo: None,
            trust_albedo: Vec::new(),
            texel_grid: texels::DEFAULT_TEXEL_GRID,
            texel_smoothness: texels::DEFAULT_TEXEL_SMOOTHNESS,
            sphere_pixels: super::spheres::FIT_PIXELS,
        }
    }

    /// The ring counts the job may fit (for memory estimates): the one, or the candidates.
    pub fn ring_counts(&self) -> &[u32] {
        match &self.rings {
            Rings::Fixed(r) => std::slice::from_ref(r),
            Rings::Auto(c) => c,
        }
    }

    /// Checks every value's range.
    pub fn check(&self) -> Result<()> {
        let setting = |name: &'static str, expected: String, got: String| {
            Err(Error::Setting {
                name,
                expected,
                got,
            })
        };
        if self.ring_counts().is_empty() {
            return Err(Error::Invalid("no ring count to choose from".into()));
        }
        if let Some(r) = self
            .ring_counts()
            .iter()
            .find(|r| !(1..=MAX_RINGS).contains(*r))
        {
            return setting("rings", format!("between 1 and {MAX_RINGS}"), r.to_string());
        }
        if !(1..=MAX_SPP).contains(&self.spp) {
            return setting(
                "spp",
                format!("between 1 and {MAX_SPP}"),
                self.spp.to_string(),
            );
        }
        if !(1..=100).contains(&self.rounds) {
            return setting(
                "rounds",
                "between 1 and 100".into(),
                self.rounds.to_string(),
            );
        }
        if self.solver == Solver::Gradient && self.colour == Colour::Together {
            return setting(
                "colour",
                "per-channel with the gradient solver (it fits each channel on its own)".into(),
                "together".into(),
            );
        }
        for (name, v) in [
            ("smooth", self.smooth),
            ("ridge", self.ridge),
            ("texel smoothness", self.texel_smoothness),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return setting(name, "a finite number >= 0".into(), v.to_string());
            }
        }
        let t = self.time_limit.as_secs_f64();
        if t <= 0.0 || t > 1e6 {
            return setting(
                "time limit",
                "a positive number of seconds, at most 1e6".into(),
                t.to_string(),
            );
        }
        if let LightModel::Spheres(Some(k)) = self.model
            && !(1..=8).contains(&k)
        {
            return setting("sphere light count", "1 to 8".into(), k.to_string());
        }
        if self.model.chooses() && !self.evaluate {
            return Err(Error::Invalid(
                "choosing the light model compares the models' re-renders, so it needs the \
                 evaluation (it cannot be fit-only)"
                    .into(),
            ));
        }
        if self.fit_albedo.is_some() && !self.evaluate {
            return Err(Error::Invalid(
                "fitting the albedo compares each material's re-rendered pixels with the \
                 references', so it needs the evaluation (it cannot be fit-only)"
                    .into(),
            ));
        }
        if self.fit_albedo.is_some()
            && self.exposure == Exposure::PerView
            && self.model == LightModel::Auto
        {
            return Err(Error::Invalid(
                "fitting the albedo and per-view exposures together needs one light model \
                 (--model envmap, spheres or spheres:K), not --model auto: each of the \
                 alternation's fits would choose a model again"
                    .into(),
            ));
        }
        if self.sphere_pixels < super::spheres::MIN_FIT_PIXELS {
            return setting(
                "sphere pixels",
                format!("at least {}", super::spheres::MIN_FIT_PIXELS),
                self.sphere_pixels.to_string(),
            );
        }
        if self.texel_smoothness > texels::MAX_TEXEL_SMOOTHNESS {
            return setting(
                "texel smoothness",
                format!("at most {:e}", texels::MAX_TEXEL_SMOOTHNESS),
                self.texel_smoothness.to_string(),
            );
        }
        if !(texels::MIN_TEXEL_GRID..=texels::MAX_TEXEL_GRID).contains(&self.texel_grid) {
            return setting(
                "texel grid",
                format!("{} to {}", texels::MIN_TEXEL_GRID, texels::MAX_TEXEL_GRID),
                self.texel_grid.to_string(),
            );
        }
        if self.trust_albedo.iter().any(String::is_empty) {
            return Err(Error::Invalid(
                "trusted albedo: an empty material name (a trailing comma?)".into(),
            ));
        }
        if self.fit_albedo.is_none() && !self.trust_albedo.is_empty() {
            return Err(Error::Invalid(
                "trusted albedo names the materials that fix the scale of a fitted albedo; \
                 without fitting the albedo every material is trusted"
                    .into(),
            ));
        }
        if self.exposure == Exposure::PerView && !self.evaluate {
            return Err(Error::Invalid(
                "fitting an exposure per view compares each view's re-render with its \
                 reference, so it needs the evaluation (it cannot be fit-only)"
                    .into(),
            ));
        }
        Ok(())
    }

    /// The bytes the envmap fit needs at `pixels` pixels over all views: the streamed
    /// transport's sums (every candidate's, each grid of at most
    /// [`super::MAX_JACKKNIFE_CELLS`] once per jackknife group) and chunk, independent of the
    /// pixels ([`super::transport::memory_needed`]), and per pixel the references and the images the
    /// job renders beside them (estimate, noise floor, representation limit, a candidate's
    /// validation), 16 bytes each; with sphere lights, the walked camera paths they keep
    /// ([`super::spheres::PathCache`]: up to `max_bounces` vertices of 64 bytes for each of
    /// 80 samples per pixel), for at most `sphere_pixels` pixels; with `--fit-albedo`, the sums kept
    /// per material of the scene's `materials` ([`albedo::material_grid`]) with one channel's
    /// dense copies, and a material index per pixel; with texels, their renders and sums and
    /// the corrected textures.
    pub fn memory_needed(
        &self,
        pixels: u64,
        max_bounces: u32,
        materials: &[crate::scene::Material],
    ) -> u64 {
        let texture_texels: u64 = materials
            .iter()
            .map(|m| match &m.albedo {
                crate::scene::Albedo::Texture { texture, .. } => texture.texels.len() as u64,
                crate::scene::Albedo::Constant(_) => 0,
            })
            .sum();
        let texture_count = materials
            .iter()
            .filter(|m| matches!(m.albedo, crate::scene::Albedo::Texture { .. }))
            .count();
        let materials = materials.len();
        let groups = if self.diagnose && self.colour == Colour::PerChannel {
            JACKKNIFE_GROUPS as usize
        } else {
            1
        };
        let grids: Vec<(usize, usize)> = self
            .ring_counts()
            .iter()
            .map(|&r| {
                let cells = crate::envmap::RingGrid::new(r).cell_count();
                let kept = if cells <= super::MAX_JACKKNIFE_CELLS {
                    groups
                } else {
                    1
                };
                (cells, kept)
            })
            .collect();
        let parts = self.rounds.max(1) as usize;
        let paths = if self.model.max_lights() > 0 {
            pixels.min(self.sphere_pixels as u64) * 80 * (max_bounces as u64 * 64 + 8)
        } else {
            0
        };
        let albedo = match self.fit_albedo {
            Some(_) => {
                let rings = self.ring_counts().iter().copied().max().unwrap_or(1);
                let cells = albedo::material_grid(rings, materials).cell_count();
                let sums = super::transport::NormalEquations::memory_needed(cells);
                (materials * (sums + 8 * cells * cells) + 7 * 8 * cells * cells) as u64
                    + pixels * (4 + 16)
            }
            None => 0,
        };
        // Texels: two re-renders and the coordinates per pixel; one texture's sums (488 bytes
        // a cell) and its sparse factor (a grid's Cholesky fills in to about 100 entries a
        // row); every texture's sums and correction kept for the deviations when the grid is
        // small enough to measure them, and one measurement's blocks of columns; a corrected
        // copy of every texture and an export's copy of one.
        let texel = match self.fit_albedo {
            Some(FitAlbedo::Texels) => {
                // At most: a non-square texture's grid is narrower than `texel_grid` along
                // its short side, and may be measured where a square one would not be.
                let cells = (self.texel_grid as u64).pow(2);
                let measured = cells.min(texels::MAX_SIGMA_CELLS as u64);
                let textures = texture_count as u64;
                let (kept, sigma) = (textures * measured * (488 + 32), measured * 2 * 256 * 8);
                pixels * (2 * 16 + 8)
                    + cells * (488 + 100 * 16)
                    + kept
                    + sigma
                    + 2 * 12 * texture_texels
            }
            _ => 0,
        };
        super::transport::memory_needed(&grids, parts) as u64
            + pixels * 16 * 5
            + paths
            + albedo
            + texel
    }
}

/// Where the references come from.
pub enum References<'p> {
    /// Rendered from the truth renderer's lights with the scene's settings.
    Render,
    /// `<view>.exr` (or `.hdr`, `.png`, `.jpg`) in this folder, each the size of its view's
    /// image, decoded so; `<view>.mask.png` and saturated pixels leave pixels out, and
    /// `<view>_b.exr` twins, where given, measure their noise ([`pipeline::load_twins`]).
    Folder(&'p Path, crate::imageio::Decoding),
    /// Given, one per view of the scene in order.
    Images(Vec<Image>),
}

/// The phases of a long job, for progress bars and logs.
pub trait Progress: Sync {
    /// A phase starts: its name and how many units of work it holds.
    fn phase(&self, _name: &str, _units: u64) {}
    /// `units` more of the current phase are done.
    fn advance(&self, _units: u64) {}
}

/// No progress reporting.
impl Progress for () {}

/// The references of every view of the truth renderer's scene, their geometry masks (the
/// references' alpha, or the pixel centres that see geometry), and the views left out
/// because their mask is empty. Errors when no view has a pixel.
pub fn observe<'a>(
    truth: &Renderer<'a>,
    render: &RenderSettings,
    references: References,
    progress: &dyn Progress,
) -> Result<SeenViews<'a>> {
    let scene: &'a crate::scene::Scene = truth.scene;
    let views: Vec<&'a Camera> = scene.cameras.iter().collect();
    let why = match &references {
        References::Render => "it sees no scene geometry".to_string(),
        References::Folder(dir, _) => format!(
            "its reference in {} leaves no pixel to fit (zero alpha, saturated or masked out everywhere)",
            dir.display()
        ),
        References::Images(_) => "its reference has zero alpha (coverage) everywhere".into(),
    };
    let t = Instant::now();
    let mut usable = None;
    let mut twins = Vec::new();
    let rendered = matches!(references, References::Render);
    let images = match references {
        References::Folder(dir, decoding) => {
            let (images, mut ok) = pipeline::load_references(dir, &views, decoding)?;
            let cameras = &scene.camera_names;
            twins = pipeline::load_twins(dir, &views, cameras, &images, decoding, &mut ok)?;
            usable = Some(ok);
            images
        }
        References::Images(images) => {
            let size = |i: &Image| (i.width, i.height);
            let want: Vec<_> = views.iter().map(|c| (c.width, c.height)).collect();
            if images.iter().map(size).collect::<Vec<_>>() != want {
                return Err(Error::Invalid(format!(
                    "references of {:?} for views of {want:?}",
                    images.iter().map(size).collect::<Vec<_>>(),
                )));
            }
            images
        }
        References::Render => {
            if truth.lights.is_empty() {
                return Err(Error::Invalid(
                    "the scene has no lights to render references from; give references".into(),
                ));
            }
            progress.phase("references", scene.pixel_count());
            truth.render_views(&views, render, &|k| progress.advance(k))
        }
    };
    let mut masks = pipeline::geometry_masks(truth, &views, &images);
    for (mask, ok) in masks.iter_mut().zip(usable.iter().flatten()) {
        for (m, &o) in mask.iter_mut().zip(ok) {
            *m &= o;
        }
    }
    let mut seen = pipeline::seen_views(&views, images, twins, masks);
    seen.seconds = t.elapsed().as_secs_f64();
    seen.rendered = rendered;
    if seen.views.is_empty() {
        return Err(Error::Invalid(format!(
            "no view has a pixel to fit ({}: {why}): there is nothing to fit",
            seen.blind.join(", ")
        )));
    }
    seen.blind_reason = why;
    Ok(seen)
}

/// What one estimate works on.
pub struct Job<'a> {
    /// Renders what the fit sees: the scene, or a twin with other albedos (same geometry).
    /// Its lights play no part.
    pub fit: &'a Renderer<'a>,
    /// Judges: re-renders are made in its scene, and its lights are the true ones (empty
    /// when unknown): the noise floor and the light recovery need them.
    pub truth: &'a Renderer<'a>,
    pub seen: &'a SeenViews<'a>,
    /// The references' render settings (samples, bounces, seed).
    pub render: &'a RenderSettings,
    pub settings: &'a EstimateSettings,
    /// The scene's centre and size (its larger horizontal extent), metres.
    pub center: Vec3,
    pub size: f32,
}

impl<'a> Job<'a> {
    /// A job that fits and judges in `renderer`'s scene.
    pub fn new(
        renderer: &'a Renderer<'a>,
        seen: &'a SeenViews<'a>,
        render: &'a RenderSettings,
        settings: &'a EstimateSettings,
    ) -> Self {
        let (lo, hi) = renderer.scene.mesh.bounds();
        Job {
            fit: renderer,
            truth: renderer,
            seen,
            render,
            settings,
            center: renderer.scene.center(),
            size: (hi.x - lo.x).max(hi.z - lo.z).max(1e-3),
        }
    }
}

/// An estimate: what was fitted, its images, and the report.
pub struct Estimate {
    pub envmap: Outcome,
    /// The chosen sphere-light model, if any.
    pub spheres: Option<SphereOutcome>,
    pub report: EstimateReport,
    /// The scene's materials with the fitted albedo (`--fit-albedo`), in the scene's order.
    pub materials: Option<Vec<crate::scene::Material>>,
}

/// `report.json`: everything an estimate measured. Figures that are not finite (a view whose
/// reference is black) are `null`.
#[derive(Debug, Clone, Serialize, JsonSchema)]
pub struct EstimateReport {
    pub lightprobe_version: String,
    /// The scene file, as given.
    pub scene: PathBuf,
    /// What the scene's files hold that the model leaves out (specular, emission, …): the
    /// fit explains the images without it.
    pub ignored: Vec<crate::scene::Ignored>,
    /// Rings of the envmap (the chosen ones with `--rings auto`).
    pub rings: u32,
    pub rings_selection: Option<Selection>,
    pub cells: usize,
    pub solver: Solver,
    pub smooth: f64,
    pub ridge: f64,
    /// How NNLS treated a cell's channels (the gradient solver fits each on its own).
    pub colour: Colour,
    /// Transport samples per pixel, over all parts (NNLS) or rounds (gradient).
    pub transport_spp: u32,
    pub rounds: u32,
    /// The references' render settings.
    pub settings: RenderSettings,
    /// Mean relMAE over views of the envmap estimate's re-render.
    pub rel_mae: Option<f64>,
    /// The noise floor: mean over views of the relMAE that the images' noise alone gives a
    /// perfect model's re-render, measured as `noise_floor_source` says.
    pub noise_floor_rel_mae: Option<f64>,
    pub noise_floor_source: Option<NoiseSource>,
    /// With given references and lights in the scene: mean relMAE over views of those lights
    /// re-rendered against the references. How well the scene's lights describe the images;
    /// not a noise figure.
    pub true_lights_rel_mae: Option<f64>,
    /// Whether the model the estimate ends with explains the images within their noise.
    pub fit_test: Option<ModelFitTest>,
    /// Mean relMAE over views of the best envmap of this resolution (`--oracle`).
    pub representation_limit_rel_mae: Option<f64>,
    pub views: Vec<ViewReport>,
    /// Views left out: nothing of their mask to fit or to measure.
    pub views_without_geometry: Vec<String>,
    /// The envmap's solve per colour channel.
    pub channels: Vec<ChannelFit>,
    /// The envmap's bright clusters (brightest first, at most 8, each at least 5% of the
    /// power) with their 95% intervals' standard deviations ([`recovery::cluster_estimates`]).
    pub clusters: Vec<ClusterEstimate>,
    /// How the envmap's colour holds together ([`recovery::colour_figures`]; against the
    /// scene's sphere lights where it has any).
    pub envmap_colour: recovery::ColourFigures,
    /// The envmap's bright clusters matched to the true sphere lights, brightest first.
    pub light_recovery: Vec<LightRecovery>,
    /// The model the estimate ends with: `envmap`, `spheres:K` or `envmap+spheres:K`.
    pub model: String,
    pub model_selection: Option<ModelSelection>,
    /// The fitted relative exposures (`--exposure per-view`); null when the references share
    /// one exposure.
    pub exposure: Option<ExposureReport>,
    /// The albedo fitted beside the lighting (`--fit-albedo`); null when taken as known.
    pub albedo: Option<AlbedoReport>,
    /// The sphere-light model's estimate (with `--model spheres` or `auto`).
    pub spheres: Option<SpheresReport>,
    /// Every sphere model compared, when the model was chosen from the data.
    pub sphere_candidates: Vec<SpheresReport>,
    pub timings: Timings,
    pub memory: Memory,
    pub threads: usize,
    pub status: FitStatus,
}

/// One view's figures.
#[derive(Debug, Clone, Serialize, JsonSchema)]
pub struct ViewReport {
    pub view: String,
    /// The envmap estimate's re-render against the reference.
    pub estimate: Option<Metrics>,
    /// relMAE that the noise alone gives ([`EstimateReport::noise_floor_source`]).
    pub noise_floor_rel_mae: Option<f64>,
    /// With given references: the scene's own lights re-rendered against them.
    pub true_lights: Option<Metrics>,
    pub representation_limit: Option<Metrics>,
    pub rel_mae_over_noise_floor: Option<f64>,
    pub rel_mae_over_representation_limit: Option<f64>,
    /// The fit test of the model the estimate ends with, in this view.
    pub fit_test: Option<FitTest>,
}

/// How the noise floor was measured.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum NoiseSource {
    /// lightprobe rendered the references: a second render of the same lights with other
    /// random numbers is their exact twin, and the floor is its relMAE against them.
    RenderedTwin,
    /// From the residual's differences between neighbouring pixels ([`crate::noise`]):
    /// assumes noise independent from pixel to pixel (true of lightprobe's and most
    /// renderers' samplers and of 8-bit quantisation; a demosaiced photograph's correlated
    /// noise reads as less noise than there is).
    NeighbouringPixels,
    /// From the references' given twins (`<view>_b`, [`pipeline::load_twins`]) and a second
    /// render of the model: exact, whatever the noise's correlation or distribution.
    GivenTwins,
}

/// The fit test of the model an estimate ends with: its residual against the images' noise.
#[derive(Debug, Clone, Serialize, JsonSchema)]
pub struct ModelFitTest {
    /// `envmap`, `spheres:K` or `envmap+spheres:K`.
    pub model: String,
    #[serde(flatten)]
    pub test: FitTest,
    /// The residual is significantly (p < [`MISFIT_P_VALUE`]) and materially (×
    /// [`MISFIT_RATIO`] the noise's `Σ r²` or more) above the noise: the model does not
    /// explain these images.
    pub misfit: bool,
    /// With a misfit: what to check, most likely first.
    pub causes: Vec<String>,
}

/// Groups of pixels of the envmap fit's jackknife ([`FitSettings::jackknife`]): its intervals'
/// variances have G − 1 degrees of freedom, so 16 groups leave the 95% interval's half-width
/// uncertain by about ±18%, at 16 extra solves (milliseconds each at 9 rings).
pub const JACKKNIFE_GROUPS: u32 = 16;

/// A residual more likely than this under a model that explains the images is not a misfit.
pub const MISFIT_P_VALUE: f64 = 1e-3;
/// A residual's `Σ r²` within this factor of the noise's is not called a misfit however
/// significant: with 10⁵–10⁶ pixels a test detects misfits far below what matters.
pub const MISFIT_RATIO: f64 = 1.2;

/// A sphere-light model's estimate.
#[derive(Debug, Clone, Serialize, JsonSchema)]
pub struct SpheresReport {
    /// `spheres:K` or `envmap+spheres:K`.
    pub model: String,
    /// Rings of the envmap behind the lights, if any.
    pub background_rings: Option<u32>,
    pub lights: Vec<FittedLight>,
    /// Where the refinement started (centre, radius).
    pub start: Vec<LightStart>,
    /// Lights asked for.
    pub requested: usize,
    /// Mean relMAE over views of its re-render.
    pub rel_mae: Option<f64>,
    pub views: Vec<Metrics>,
    /// relMAE over the binned rows the fit saw.
    pub fit_rel_mae_binned: f64,
    pub iterations: usize,
    /// Binned sum of squared residuals after each accepted step.
    pub objective_trace: Vec<f64>,
    /// Renders (of unit-radiance lights) the fit made.
    pub renders: usize,
    /// The true lights matched, brightest first.
    pub recovery: Vec<SphereRecovery>,
    /// Pixels the fit compared: every seen pixel up to a limit, else whole 4×4 blocks of them
    /// spread over every view, as many as the limit holds.
    pub fit_pixels: usize,
    /// Pixels the views see (the masks'), where the re-render is compared.
    pub seen_pixels: usize,
    pub fit_seconds: f64,
    pub rerender_seconds: f64,
}

/// A sphere light where a refinement started.
#[derive(Debug, Clone, Serialize, JsonSchema)]
pub struct LightStart {
    /// World space, metres.
    pub center: [f32; 3],
    /// Metres.
    pub radius: f32,
}

/// Seconds per phase.
#[derive(Debug, Clone, Default, Serialize, JsonSchema)]
pub struct Timings {
    pub references_seconds: f64,
    /// The noise floor shares the re-render's camera paths: its cost is in `rerender_seconds`.
    pub noise_floor_seconds: f64,
    pub transport_seconds: f64,
    pub solve_seconds: f64,
    /// `--rings auto`: choosing the resolution.
    pub rings_selection_seconds: Option<f64>,
    /// Transport and solve of the envmap.
    pub fit_seconds: f64,
    pub rerender_seconds: f64,
    /// The representation limit's fit.
    pub oracle_seconds: f64,
    /// The sphere models' fits (every candidate count, and the refit of the chosen one).
    pub sphere_fit_seconds: f64,
    /// Diagnosing a misfit of the envmap to given references (the bounce probe: a re-fit
    /// with one more bounce); 0 when nothing was diagnosed.
    pub diagnosis_seconds: f64,
    /// `--exposure per-view` and `--fit-albedo`: the fits and passes before the last fit
    /// (the last is counted as any estimate's).
    pub alternation_seconds: f64,
    /// The job's wall time; `estimate` writes its whole command's (loading, references and
    /// the output files included).
    pub total_seconds: f64,
}

/// Bytes.
#[derive(Debug, Clone, Serialize, JsonSchema)]
pub struct Memory {
    /// The envmap fit's streamed transport at most: its normal equations and one chunk of
    /// rendered rows (independent of the pixels and views).
    pub transport_bytes: usize,
    /// Peak resident memory of the process so far.
    pub peak_bytes: u64,
}

/// Whether every solve met its optimality test.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum FitStatus {
    Ok,
    /// A channel's solver stopped at its iteration or time limit first.
    NotConverged,
}

/// Runs the job. With [`Exposure::PerView`] or [`EstimateSettings::fit_albedo`] it
/// alternates: fit the lighting to the references divided by the current exposures, in the
/// scene with the current albedo; render that lighting there; set each view's exposure to the
/// ratio of its reference's sum to the render's (over the view's mask, all channels),
/// normalised to a geometric mean of 1, and move each material's albedo by the ratio over its
/// pixels ([`albedo`]), relative to the anchors'; accelerated ([`anderson_step`], over the
/// logarithms); until no exposure moves by [`EXPOSURE_TOLERANCE`] and no albedo by
/// [`albedo::ALBEDO_TOLERANCE`]. These fits take a quarter of the samples (a sum over many
/// pixels hardly sees the noise; the transport's products stay unbiased) and keep the ring
/// count the first chose; then fits with every sample go on until one's own step is within
/// the tolerances (the fit's noise moves a material's ratio by about 1.5% between a quarter
/// and all of the samples on the bundled scene), and that fit ends the job, its step
/// reported as the last change; at most [`MAX_ALTERNATION_FITS`] fits in all. Ratios of sums,
/// not least-squares slopes: the render's noise would bias a slope low.
///
/// The envmap's albedo is fitted jointly with it ([`run_joint`]), not by ratios: with
/// per-view exposures, each of the alternation's fits is a joint fit and only the exposures
/// alternate.
///
/// A fitted albedo is judged in its own scene too when the job judges in the scene it fits
/// in (`fit` and `truth` share a scene: a user's estimate); a sweep trial's truth keeps its
/// true albedo, so its errors measure the lighting alone.
///
/// With [`FitAlbedo::Texels`], texel rounds follow ([`run_texels`]).
pub fn run(job: &Job, progress: &dyn Progress) -> Result<Estimate> {
    let estimate = run_materials(job, None, progress)?;
    match job.settings.fit_albedo {
        Some(FitAlbedo::Texels) => run_texels(job, estimate, progress),
        _ => Ok(estimate),
    }
}

/// [`run`] up to the materials' albedo; with `--exposure per-view` the alternation starts from
/// `exposures` (per seen view, relative to their geometric mean) where given, else from 1.
fn run_materials(
    job: &Job,
    exposures: Option<&[f64]>,
    progress: &dyn Progress,
) -> Result<Estimate> {
    let per_view = job.settings.exposure == Exposure::PerView;
    if !per_view && job.settings.fit_albedo.is_none() {
        return run_once(job, progress);
    }
    // The envmap's albedo is fitted jointly with it; with per-view exposures, each of the
    // alternation's fits is such a joint fit.
    let joint = job.settings.fit_albedo.is_some() && job.settings.model == LightModel::Envmap;
    if !per_view && joint {
        return run_joint(job, progress);
    }
    job.settings.check()?;
    let t_all = Instant::now();
    let original = job.seen;
    let (mut settings, mut render) = first_fits(job);
    let mut fitting = match job.settings.fit_albedo {
        Some(_) if !joint => Some(AlbedoFit::new(job, progress)?),
        _ => None,
    };
    // The scene the lighting is fitted in, its materials set to the current albedo each fit.
    let mut scene = fitting.as_ref().map(|_| job.fit.scene.clone());
    let n_views = if per_view { original.views.len() } else { 0 };
    let materials = job.fit.scene.materials.len();
    // Fitting with every sample (once the quarter-sample fits converged), and the fit that
    // must end the loop.
    let (mut full, mut last) = (false, false);
    // `--rings auto`: the first fit's choice, which the later ones keep.
    let mut selection: Option<Selection> = None;
    // Natural logarithms of the exposures, then of each material's multiplier per channel:
    // the alternation's map is close to linear in them.
    let mut x = vec![0.0f64; n_views + 3 * materials * fitting.is_some() as usize];
    for (x, e) in x[..n_views].iter_mut().zip(exposures.into_iter().flatten()) {
        *x = e.ln();
    }
    let mut history: Vec<(Vec<f64>, Vec<f64>)> = Vec::new();
    let pixels: u64 = original
        .views
        .iter()
        .map(|c| (c.width * c.height) as u64)
        .sum();
    for fits in 1.. {
        let t_fit = Instant::now();
        let exposures: Vec<f64> = x[..n_views].iter().map(|l| l.exp()).collect();
        let multipliers: Vec<glam::DVec3> = x[n_views..]
            .chunks_exact(3)
            .map(|k| glam::DVec3::new(k[0].exp(), k[1].exp(), k[2].exp()))
            .collect();
        let scaled;
        let seen = if per_view {
            scaled = original.with_exposures(&exposures);
            &scaled
        } else {
            original
        };
        if let Some(scene) = scene.as_mut() {
            scene.materials = albedo::scaled_materials(&job.fit.scene.materials, &multipliers);
        }
        let in_scene = scene.as_ref().map(|s| renderers_in(job, s));
        let (fit, truth) = match &in_scene {
            Some((f, t)) => (f, t),
            None => (job.fit, job.truth),
        };
        let this = Job {
            fit,
            truth,
            seen,
            settings: &settings,
            render: &render,
            ..*job
        };
        let mut estimate = if joint {
            run_joint(&this, progress)?
        } else {
            run_once(&this, progress)?
        };
        // The lighting rendered in the scene it was fitted in: what the steps compare. Seeds
        // apart from the references' (rendered references share `render`'s).
        let albedo_render = |r: Renderer| {
            progress.phase("albedo render", pixels);
            let first = pipeline::evaluation_settings(&render);
            let settings = RenderSettings {
                seed: first.seed.wrapping_add(ALBEDO_RENDER_SEED),
                ..first
            };
            r.render_views(&original.views, &settings, &|k| progress.advance(k))
        };
        let (fitted_renders, fitted_scene);
        let renders = match &fitting {
            Some(f) => {
                if f.observability.is_none() {
                    let envmap = &estimate.envmap.fit.envmap;
                    let f = fitting.as_mut().expect("fitting");
                    f.pass(fit, seen, envmap, &settings, &render, progress);
                }
                let lights = final_lights(&estimate.envmap, estimate.spheres.as_ref());
                fitted_renders = albedo_render(fit.with_lights(&lights));
                &fitted_renders
            }
            // A joint fit's renders are the judge's, which keeps its own albedo where it
            // judges in another scene (a trial's truth): rendered again at the fitted albedo.
            None if joint && !std::ptr::eq(job.fit.scene, job.truth.scene) => {
                let mut scene = job.fit.scene.clone();
                scene.materials = estimate
                    .materials
                    .clone()
                    .expect("the joint fit sets the materials");
                fitted_scene = scene;
                let lights = final_lights(&estimate.envmap, None);
                fitted_renders = albedo_render(job.fit.with_scene(&fitted_scene, &lights));
                &fitted_renders
            }
            None => match &estimate.spheres {
                Some(so) => &so.renders,
                None => &estimate.envmap.renders,
            },
        };
        let mut step: Vec<f64> = Vec::with_capacity(x.len());
        if per_view {
            step.extend(
                fitted_exposures(original, renders)?
                    .iter()
                    .zip(&x)
                    .map(|(n, l)| n.ln() - l),
            );
        }
        let change_of = |s: &[f64]| s.iter().fold(0.0f64, |m, d| m.max(d.abs().exp_m1().abs()));
        let exposure_change = change_of(&step);
        let mut albedo_change = 0.0;
        if let Some(f) = &fitting {
            let a = f.step(&seen.references, renders);
            step.extend(a.iter().flat_map(|v| v.to_array()));
            albedo_change = change_of(&step[n_views..]);
        }
        let converged =
            exposure_change < EXPOSURE_TOLERANCE && albedo_change < albedo::ALBEDO_TOLERANCE;
        if last {
            let report = &mut estimate.report;
            report.exposure = per_view.then(|| ExposureReport {
                relative: original
                    .views
                    .iter()
                    .zip(&exposures)
                    .map(|(c, &e)| ViewExposure {
                        view: c.name.clone(),
                        exposure: e,
                    })
                    .collect(),
                fits,
                last_change: exposure_change,
                converged: exposure_change < EXPOSURE_TOLERANCE,
            });
            if let Some(f) = &fitting {
                report.albedo = Some(f.report(
                    job,
                    &multipliers,
                    (albedo::AlbedoMethod::Alternation, fits),
                    albedo_change,
                ));
                estimate.materials = scene.take().map(|s| s.materials);
            }
            if report.rings_selection.is_none() {
                report.timings.rings_selection_seconds = selection.as_ref().map(|s| s.seconds);
                report.rings_selection = selection;
            }
            report.timings.alternation_seconds = (t_fit - t_all).as_secs_f64();
            report.timings.total_seconds = original.seconds + t_all.elapsed().as_secs_f64();
            return Ok(estimate);
        }
        let mut next = anderson_step(&x, &step, &history);
        history.push((x, step));
        if history.len() > ANDERSON_MEMORY {
            history.remove(0);
        }
        if let Some(f) = &fitting {
            f.bound(&mut next[n_views..]);
        }
        x = next;
        if selection.is_none() {
            selection = estimate.report.rings_selection.take();
        }
        let rings = Rings::Fixed(estimate.report.rings);
        let to_full = !full && (converged || fits + 3 >= MAX_ALTERNATION_FITS);
        if to_full {
            full = true;
            render = *job.render;
        }
        // The exposures alone: one fit with every sample ends. With the albedo, fits with
        // every sample until one converges, then the last.
        last = fits + 1 == MAX_ALTERNATION_FITS
            || (to_full && fitting.is_none())
            || (full && !to_full && converged);
        settings = if last {
            EstimateSettings {
                rings,
                ..job.settings.clone()
            }
        } else if full {
            EstimateSettings {
                rings,
                noise_floor: false,
                oracle: false,
                diagnose: false,
                ..job.settings.clone()
            }
        } else {
            EstimateSettings { rings, ..settings }
        };
    }
    unreachable!("the loop returns by its last fit")
}

/// [`run`] fitting the albedo with the envmap model: a first fit at the given albedo (a
/// quarter of the samples) chooses the rings and steers the passes; each pass renders the
/// transport kept per material in the scene at the albedo so far, and the multipliers and
/// the envmap are fitted jointly on it ([`albedo::MaterialSums::joint`]); passes go on until
/// one changes no multiplier by [`albedo::JOINT_TOLERANCE`] (what it still changes is light
/// between surfaces, which the joint fit takes as fixed); then one fit with every sample at
/// the albedo found.
fn run_joint(job: &Job, progress: &dyn Progress) -> Result<Estimate> {
    job.settings.check()?;
    let t_all = Instant::now();
    let mut fitting = AlbedoFit::new(job, progress)?;
    let (mut settings, render) = first_fits(job);
    let given = &job.fit.scene.materials;
    let mut scene = job.fit.scene.clone();
    let mut multipliers = vec![glam::DVec3::ONE; given.len()];
    // The job in `scene` with `settings` and `render`.
    let fit_in = |scene: &crate::scene::Scene,
                  settings: &EstimateSettings,
                  render: &RenderSettings|
     -> Result<Estimate> {
        let (fit, truth) = renderers_in(job, scene);
        run_once(
            &Job {
                fit: &fit,
                truth: &truth,
                settings,
                render,
                ..*job
            },
            progress,
        )
    };
    let first = fit_in(&scene, &settings, &render)?;
    settings.rings = Rings::Fixed(first.report.rings);
    let selection = first.report.rings_selection.clone();
    let mut steer = first.envmap.fit.envmap.clone();
    let (mut passes, mut change, mut stalled, mut grid_rings) = (0, f64::INFINITY, false, None);
    while passes < albedo::MAX_JOINT_PASSES && change >= albedo::JOINT_TOLERANCE && !stalled {
        passes += 1;
        scene.materials = albedo::scaled_materials(given, &multipliers);
        let fit = job.fit.with_scene(&scene, job.fit.lights);
        let sums = fitting.pass(&fit, job.seen, &steer, &settings, &render, progress);
        grid_rings = Some(sums.grid.rings());
        let fitted = fitting.fitted();
        // Bounds relative to the multipliers so far: at least MIN_MULTIPLIER_LOG in all, at
        // most the albedo 1.
        let log = |k: &glam::DVec3| glam::DVec3::new(k.x.ln(), k.y.ln(), k.z.ln());
        let exp = |v: glam::DVec3| glam::DVec3::new(v.x.exp(), v.y.exp(), v.z.exp());
        let bounds: Vec<(glam::DVec3, glam::DVec3)> = fitting
            .upper
            .iter()
            .zip(&multipliers)
            .map(|(u, k)| {
                let upper = u.max(glam::DVec3::splat(MIN_MULTIPLIER_LOG));
                (
                    exp(glam::DVec3::splat(MIN_MULTIPLIER_LOG) - log(k)),
                    exp(upper - log(k)),
                )
            })
            .collect();
        let weights = fitting.pixels.weights();
        let (k, envmap, stuck) = sums.joint(
            (&fitted, &fitting.trusted),
            &weights,
            &bounds,
            albedo::JOINT_RIDGE,
            settings.time_limit,
        );
        stalled = stuck;
        change = k
            .iter()
            .flat_map(|v| v.to_array())
            .fold(0.0f64, |m, v| m.max(v.ln().abs().exp_m1()));
        for (m, k) in multipliers.iter_mut().zip(&k) {
            *m *= *k;
        }
        if envmap.grid.rings() == steer.grid.rings() {
            steer = envmap;
        }
    }
    scene.materials = albedo::scaled_materials(given, &multipliers);
    let settings = EstimateSettings {
        rings: settings.rings,
        ..job.settings.clone()
    };
    let alternation_seconds = t_all.elapsed().as_secs_f64();
    let mut estimate = fit_in(&scene, &settings, job.render)?;
    let report = &mut estimate.report;
    report.timings.alternation_seconds = alternation_seconds;
    if report.rings_selection.is_none() {
        report.timings.rings_selection_seconds = selection.as_ref().map(|s| s.seconds);
        report.rings_selection = selection;
    }
    let mut albedo_report = fitting.report(
        job,
        &multipliers,
        (albedo::AlbedoMethod::Joint, passes),
        change,
    );
    albedo_report.rings = grid_rings;
    albedo_report.stalled = stalled;
    albedo_report.converged &= !stalled;
    report.albedo = Some(albedo_report);
    report.timings.total_seconds = job.seen.seconds + t_all.elapsed().as_secs_f64();
    estimate.materials = Some(scene.materials);
    Ok(estimate)
}

/// The texel rounds of [`FitAlbedo::Texels`] after `first` (the materials' fit): each renders
/// the estimate's lighting twice (independent seeds) in the scene at the albedo so far,
/// corrects the pattern of every seen textured material's texture, fitted or trusted
/// ([`texels`]; its level kept: the material's re-rendered pixels keep their sum), and fits the
/// materials' albedo and the lighting again at it ([`run_materials`], same rings; a round
/// that will not be the last as the alternation's first fits): the level of an albedo trades
/// with the lighting, which the joint fit settles and an alternation would only approach
/// (3.5% short after three rounds on a test scene), while a shadow's shape does not. Until a
/// round changes no texture by [`texels::TEXEL_TOLERANCE`], at most
/// [`texels::MAX_TEXEL_ROUNDS`].
fn run_texels(job: &Job, first: Estimate, progress: &dyn Progress) -> Result<Estimate> {
    use crate::scene::Albedo;
    let t_texels = Instant::now();
    let Some(first_report) = first.report.albedo.clone() else {
        return Ok(first);
    };
    let Some(materials) = first.materials.clone() else {
        return Ok(first);
    };
    let mut scene = job.fit.scene.clone();
    scene.materials = materials;
    let mut notes = Vec::new();
    let mut targets: Vec<(usize, (u32, u32))> = Vec::new();
    for (m, a) in first_report.materials.iter().enumerate() {
        let Albedo::Texture { texture, .. } = &scene.materials[m].albedo else {
            continue;
        };
        if !matches!(a.status, MaterialStatus::Fitted | MaterialStatus::Trusted) {
            notes.push(format!(
                "material {:?}: its texture is kept as given (the material is {})",
                a.name,
                match a.status {
                    MaterialStatus::Unseen => "seen alone by too few pixels",
                    _ => "not constrained by the images",
                }
            ));
            continue;
        }
        match texels::grid_size(texture.width, texture.height, job.settings.texel_grid) {
            Some(size) => targets.push((m, size)),
            None => notes.push(format!(
                "material {:?}: its {}×{} texture is narrower than {} texels, too small for a \
                 correction grid; its multiplier is all it takes",
                a.name,
                texture.width,
                texture.height,
                texels::MIN_TEXEL_GRID
            )),
        }
    }
    // What the first fit took (the references' time apart).
    let first_seconds = first.report.timings.total_seconds - job.seen.seconds;
    if targets.is_empty() {
        let mut estimate = first;
        if let Some(a) = estimate.report.albedo.as_mut() {
            a.texel_notes = notes;
        }
        return Ok(estimate);
    }
    let given: Vec<Option<std::sync::Arc<crate::scene::Texture>>> = scene
        .materials
        .iter()
        .map(|m| match &m.albedo {
            Albedo::Texture { texture, .. } => Some(texture.clone()),
            Albedo::Constant(_) => None,
        })
        .collect();
    let seen = job.seen;
    // `--exposure per-view`: each view's exposure so far (relative to their geometric mean).
    // The texels are fitted to the references over them, and each round's alternation starts
    // from them.
    let mut exposures: Option<Vec<f64>> = first
        .report
        .exposure
        .as_ref()
        .map(|e| e.relative.iter().map(|v| v.exposure).collect());
    let units: u64 = seen.views.iter().map(|c| (c.width * c.height) as u64).sum();
    progress.phase("material maps", units);
    let pixels = MaterialPixels::new(job.fit, &seen.views, &seen.masks);
    progress.advance(units);
    let settings = EstimateSettings {
        rings: Rings::Fixed(first.report.rings),
        ..job.settings.clone()
    };
    // Per material, the product of the rounds' multipliers.
    let mut multipliers: Vec<Vec3> = first_report
        .materials
        .iter()
        .map(|a| Vec3::from_array(a.multiplier))
        .collect();
    // Per target, its last correction and its report.
    let mut fits: Vec<Option<(texels::Correction, TexelFit)>> = vec![None; targets.len()];
    // Per target, the round its system last failed in, unless a later round solved it: said
    // once the rounds are over (a later round's success makes an earlier failure moot).
    let mut failed: Vec<Option<usize>> = vec![None; targets.len()];
    let failure_notes = |failed: &[Option<usize>],
                         fits: &[Option<(texels::Correction, TexelFit)>],
                         scene: &crate::scene::Scene|
     -> Vec<String> {
        failed
            .iter()
            .enumerate()
            .filter_map(|(t, r)| Some((t, (*r)?)))
            .map(|(t, round)| {
                let name = &scene.materials[targets[t].0].name;
                match &fits[t] {
                    Some(_) => format!(
                        "material {name:?}: round {round}'s correction system could not be \
                         solved (non-finite values); its texture and figures are an earlier \
                         round's, without σ"
                    ),
                    None => format!(
                        "material {name:?}: its correction's system could not be solved \
                         (nothing lit, or non-finite values); its texture is kept as given"
                    ),
                }
            })
            .collect()
    };
    let mut albedo_fits = first_report.fits;
    let mut estimate = first;
    let mut rounds = 0;
    let mut texel_seconds;
    loop {
        rounds += 1;
        let lights = final_lights(&estimate.envmap, estimate.spheres.as_ref());
        let fit = job.fit.with_scene(&scene, &lights);
        progress.phase("texel renders", 2 * units);
        let base = pipeline::evaluation_settings(job.render);
        let [x1, x2] = [0, 1].map(|k| {
            let settings = RenderSettings {
                seed: base
                    .seed
                    .wrapping_add(TEXEL_RENDER_SEED + 2 * rounds as u64 + k),
                ..base
            };
            fit.render_views(&seen.views, &settings, &|n| progress.advance(n))
        });
        let over_exposure = |v: usize| exposures.as_ref().map_or(1.0, |e| (1.0 / e[v]) as f32);
        // Material m's pixels: texture coordinates, reference, the two re-renders.
        let (uvs, x1, x2) = (&pixels.uv, &x1, &x2);
        let material_pixels = |m: usize| {
            pixels.ids.iter().enumerate().flat_map(move |(v, ids)| {
                ids.iter()
                    .enumerate()
                    .filter(move |&(_, &id)| id as usize == m)
                    .map(move |(i, _)| {
                        let at = |img: &[Image]| img[v].rgb[i];
                        let y = at(&seen.references) * over_exposure(v);
                        (uvs[v][i], y, at(x1), at(x2))
                    })
            })
        };
        let mut change = 0.0f64;
        // Per target whose deviations can be measured: its sums and its correction as solved,
        // kept until the round is known to be the last (only the last round's are reported).
        let mut unmeasured: Vec<(usize, texels::TexelSums, texels::Correction)> = Vec::new();
        for (t, &(m, size)) in targets.iter().enumerate() {
            let Albedo::Texture { texture, factor } = &scene.materials[m].albedo else {
                continue;
            };
            let mut sums = texels::TexelSums::new(size);
            for (uv, y, a, b) in material_pixels(m) {
                sums.add(uv, y, a, b);
            }
            let Some(c) = sums.solve(settings.texel_smoothness) else {
                failed[t] = Some(rounds);
                continue;
            };
            failed[t] = None;
            let level = sums.level(&c);
            let solved = sums.measures_sigma().then(|| c.clone());
            let c = c.divided(level);
            let (corrected, clamped, moved) = c.apply(texture, *factor);
            // A NaN change is no convergence.
            change = if moved.is_nan() {
                f64::INFINITY
            } else {
                change.max(moved)
            };
            let material = &scene.materials[m];
            let fit = TexelFit {
                material: material.name.clone(),
                index: m,
                grid: [size.0, size.1],
                pixels: sums.pixels,
                cells_seen: c.cells_seen(),
                range: [1.0, 1.0],
                last_change: moved,
                clamped_texels: clamped,
                sigma: None,
                file: crate::scene::export::albedo_texture_file(m, &material.name),
            };
            fits[t] = Some((c, fit));
            if let Some(solved) = solved {
                unmeasured.push((t, sums, solved));
            }
            scene.materials[m].albedo = Albedo::Texture {
                texture: std::sync::Arc::new(corrected),
                factor: *factor,
            };
        }
        if fits.iter().all(Option::is_none) {
            // Nothing corrected: the materials' fit stands.
            notes.extend(failure_notes(&failed, &fits, &scene));
            if let Some(a) = estimate.report.albedo.as_mut() {
                a.texel_notes = notes;
            }
            return Ok(estimate);
        }
        texel_seconds = t_texels.elapsed().as_secs_f64();
        // A round that will not be the last fits as the alternation's first fits do: what it
        // must give is the next round's lighting, not the report's figures.
        let last = change < texels::TEXEL_TOLERANCE || rounds == texels::MAX_TEXEL_ROUNDS;
        if last && !unmeasured.is_empty() {
            // A phase of its own: a 64×64 grid's columns take seconds.
            let columns: u64 = unmeasured
                .iter()
                .map(|(_, _, c)| 3 * c.cells.len() as u64)
                .sum();
            progress.phase("texel deviations", columns);
            for (t, mut sums, c) in unmeasured {
                let (m, _) = targets[t];
                for (uv, y, a, b) in material_pixels(m) {
                    sums.add_residual(uv, y, a, b, &c);
                }
                // A system that fails part way reports the rest of its columns at its end.
                let done = AtomicU64::new(0);
                let sigma = sums.sigma(settings.texel_smoothness, &|k| {
                    done.fetch_add(k, Ordering::Relaxed);
                    progress.advance(k);
                });
                progress.advance((3 * c.cells.len() as u64).saturating_sub(done.into_inner()));
                if let Some((_, fit)) = fits[t].as_mut() {
                    fit.sigma = sigma.and_then(|s| c.relative_sigma(&s));
                }
            }
        }
        let (round, render) = if last {
            (settings.clone(), *job.render)
        } else {
            let (round, render) = first_fits(job);
            let rings = settings.rings.clone();
            (EstimateSettings { rings, ..round }, render)
        };
        let (fit, truth) = renderers_in(job, &scene);
        let mut next = run_materials(
            &Job {
                fit: &fit,
                truth: &truth,
                settings: &round,
                render: &render,
                ..*job
            },
            exposures.as_deref(),
            progress,
        )?;
        if let Some(report) = next.report.exposure.as_mut() {
            exposures = Some(report.relative.iter().map(|v| v.exposure).collect());
            report.fits += estimate.report.exposure.as_ref().map_or(0, |p| p.fits);
        }
        let report = next
            .report
            .albedo
            .as_ref()
            .expect("the materials' fit reports");
        albedo_fits += report.fits;
        for (k, a) in multipliers.iter_mut().zip(&report.materials) {
            *k *= Vec3::from_array(a.multiplier);
        }
        scene.materials = next
            .materials
            .clone()
            .expect("the materials' fit sets them");
        estimate = carry_over(estimate, next);
        if last {
            break;
        }
    }
    // The last round's albedo report, against the albedo as given at the start: the fitted
    // mean over the same pixels as the given, as rendered now.
    let now = MaterialPixels::new(
        &job.fit.with_scene(&scene, job.fit.lights),
        &seen.views,
        &seen.masks,
    );
    let mut albedo_report = estimate
        .report
        .albedo
        .take()
        .expect("the materials' fit reports");
    for (m, ((a, given), k)) in albedo_report
        .materials
        .iter_mut()
        .zip(&first_report.materials)
        .zip(&multipliers)
        .enumerate()
    {
        a.given = given.given;
        a.multiplier = k.to_array();
        if now.counts[m] > 0 {
            a.fitted = now.seen_albedo[m].as_vec3().to_array();
        }
    }
    albedo_report.fits = albedo_fits;
    albedo_report.texel_rounds = rounds;
    notes.extend(failure_notes(&failed, &fits, &scene));
    albedo_report.texel_notes = notes;
    albedo_report.texels = fits
        .into_iter()
        .flatten()
        .map(|(c, mut fit)| {
            let m = fit.index;
            if let (Some(was), Albedo::Texture { texture, factor }) =
                (&given[m], &scene.materials[m].albedo)
            {
                let (lo, hi) = c.ratio_range(was, texture, *factor);
                fit.range = [lo, hi];
            }
            fit
        })
        .collect();
    let report = &mut estimate.report;
    report.albedo = Some(albedo_report);
    // Before the last fit: the first fit whole, the texel rounds (their fits but the last),
    // and the last round's fits before its last.
    report.timings.alternation_seconds += first_seconds + texel_seconds;
    report.timings.total_seconds =
        job.seen.seconds + first_seconds + t_texels.elapsed().as_secs_f64();
    estimate.materials = Some(scene.materials);
    Ok(estimate)
}

/// `next`, a fit of [`run_texels`], with what only the fits before it reported: the
/// selection of rings, and the exposures where `next` fitted none.
fn carry_over(before: Estimate, mut next: Estimate) -> Estimate {
    let (from, to) = (before.report, &mut next.report);
    to.rings_selection = from.rings_selection;
    to.timings.rings_selection_seconds = from.timings.rings_selection_seconds;
    if to.exposure.is_none() {
        to.exposure = from.exposure;
    }
    next
}

/// The settings of the alternation's fits before the last: a quarter of the samples (at least
/// a sample per part, and 16 per pixel for renders), no noise floor, oracle or diagnosis.
fn first_fits(job: &Job) -> (EstimateSettings, RenderSettings) {
    let quarter = |n: u32, least: u32| (n / 4).max(least).min(n);
    let settings = EstimateSettings {
        spp: quarter(job.settings.spp, job.settings.rounds),
        noise_floor: false,
        oracle: false,
        diagnose: false,
        ..job.settings.clone()
    };
    let render = RenderSettings {
        spp: quarter(job.render.spp, 16),
        ..*job.render
    };
    (settings, render)
}

/// The job's renderers over `scene` (its geometry, other albedo): the fit's, and the judge's,
/// which takes the albedo too when the job judges in the scene it fits in (`fit` and `truth`
/// share a scene: a user's estimate), else keeps its own (a sweep trial's true albedo).
fn renderers_in<'s>(job: &'s Job, scene: &'s crate::scene::Scene) -> (Renderer<'s>, Renderer<'s>) {
    let fit = job.fit.with_scene(scene, job.fit.lights);
    let truth = if std::ptr::eq(job.fit.scene, job.truth.scene) {
        job.truth.with_scene(scene, job.truth.lights)
    } else {
        job.truth.with_lights(job.truth.lights)
    };
    (fit, truth)
}

/// The lights an estimate ends with: its chosen sphere model (with any envmap behind it),
/// else its envmap.
fn final_lights(envmap: &Outcome, spheres: Option<&SphereOutcome>) -> Lights {
    match spheres {
        Some(so) => Lights {
            spheres: so.fit.lights(),
            env: so.fit.background.clone(),
            alone: None,
        },
        None => Lights::env(envmap.fit.envmap.clone()),
    }
}

/// The albedo the alternation fits ([`run`]): which materials, where they are seen, and
/// what fixes the scale.
struct AlbedoFit {
    pixels: MaterialPixels,
    trusted: Vec<bool>,
    /// Materials seen by enough pixels and not trusted (those found unconstrained after the
    /// first fit are taken out).
    free: Vec<bool>,
    /// Measured after the first fit, on its lighting ([`albedo::observability`]).
    observability: Option<Vec<Option<f64>>>,
    /// Per material, the largest log-multiplier that keeps its mean albedo at most 1.
    upper: Vec<glam::DVec3>,
}

/// Material `m`'s mean albedo as given: over the pixels that see it alone, else its own.
fn given_albedo(pixels: &MaterialPixels, material: &crate::scene::Material, m: usize) -> Vec3 {
    if pixels.counts[m] > 0 {
        pixels.seen_albedo[m].as_vec3()
    } else {
        material.mean_albedo()
    }
}

/// Smallest multiplier the alternation may set (a material 100× darker than given is not a
/// correction of its albedo but a sign of the wrong model).
const MIN_MULTIPLIER_LOG: f64 = -4.605_170_185_988_091; // ln 0.01

impl AlbedoFit {
    fn new(job: &Job, progress: &dyn Progress) -> Result<Self> {
        let materials = &job.fit.scene.materials;
        let mut trusted = vec![false; materials.len()];
        for name in &job.settings.trust_albedo {
            match materials.iter().position(|m| &m.name == name) {
                Some(i) => trusted[i] = true,
                None => {
                    return Err(Error::Invalid(format!(
                        "trusted albedo names material {name:?}, which the scene does not \
                         have (it has {})",
                        albedo::material_names(materials)
                    )));
                }
            }
        }
        let seen = job.seen;
        let units: u64 = seen.views.iter().map(|c| (c.width * c.height) as u64).sum();
        progress.phase("material maps", units);
        let pixels = MaterialPixels::new(job.fit, &seen.views, &seen.masks);
        progress.advance(units);
        let enough = |m: usize| pixels.counts[m] >= albedo::MIN_MATERIAL_PIXELS;
        if let Some(m) = (0..materials.len()).find(|&m| trusted[m] && !enough(m)) {
            return Err(Error::Invalid(format!(
                "trusted albedo: material {:?} is seen alone by {} pixels (at least {} are \
                 needed for it to fix the scale)",
                materials[m].name,
                pixels.counts[m],
                albedo::MIN_MATERIAL_PIXELS
            )));
        }
        let free: Vec<bool> = (0..materials.len())
            .map(|m| !trusted[m] && enough(m))
            .collect();
        if !free.contains(&true) {
            return Err(Error::Invalid(format!(
                "fitting the albedo: no material is both untrusted and seen alone by at least \
                 {} pixels",
                albedo::MIN_MATERIAL_PIXELS
            )));
        }
        // The bound albedo ≤ 1 applies to what the pixels show (vertex colours included: a
        // scan's white material under dark vertex colours may brighten).
        let upper = (0..materials.len())
            .map(|m| albedo::upper_bound(given_albedo(&pixels, &materials[m], m)))
            .collect();
        Ok(AlbedoFit {
            upper,
            pixels,
            trusted,
            free,
            observability: None,
        })
    }

    /// The materials a pass keeps sums for: the free (until found unconstrained) and the
    /// trusted.
    fn wanted(&self) -> Vec<bool> {
        let fitted = self.fitted();
        (0..self.free.len())
            .map(|m| fitted[m] || self.trusted[m])
            .collect()
    }

    /// A transport pass kept per material ([`albedo::material_sums`]) in `fit`'s scene,
    /// sampled by `envmap`; the first measures the observability.
    fn pass(
        &mut self,
        fit: &Renderer,
        seen: &SeenViews,
        envmap: &crate::envmap::Envmap,
        settings: &EstimateSettings,
        render: &RenderSettings,
        progress: &dyn Progress,
    ) -> albedo::MaterialSums {
        let wanted = self.wanted();
        let fit_settings = super::FitSettings::new(
            render,
            envmap.grid.rings(),
            settings.solver,
            settings.spp,
            settings.rounds,
        );
        let keep = |p| self.pixels.of(p).is_some_and(|m| wanted[m]);
        progress.phase(
            "albedo transport",
            super::transport::progress_units(
                &seen.masks,
                &keep,
                albedo::material_parts(&fit_settings),
            ),
        );
        let sums = albedo::material_sums(
            fit,
            &seen.views,
            &seen.references,
            &seen.masks,
            &self.pixels,
            &wanted,
            envmap,
            &fit_settings,
            &|k| progress.advance(k),
        );
        if self.observability.is_none() {
            let weights = self.pixels.weights();
            let free: Vec<bool> = (0..self.free.len())
                .map(|m| self.free[m] && !self.trusted[m])
                .collect();
            self.observability = Some(sums.observability(envmap, &free, &weights));
        }
        sums
    }

    /// The materials fitted: free and, once measured, observable.
    fn fitted(&self) -> Vec<bool> {
        (0..self.free.len())
            .map(|m| {
                self.free[m]
                    && self
                        .observability
                        .as_ref()
                        .is_none_or(|o| o[m].is_some_and(|v| v >= albedo::MIN_OBSERVABILITY))
            })
            .collect()
    }

    /// The step of every material's log-multiplier from the references and the renders.
    fn step(&self, references: &[Image], renders: &[Image]) -> Vec<glam::DVec3> {
        let ratios = albedo::log_ratios(&self.pixels, references, renders);
        albedo::gauged_step(&ratios, &self.fitted(), &self.trusted, &self.pixels.counts)
    }

    /// Keeps log-multipliers within their bounds, and those not fitted at 0.
    fn bound(&self, x: &mut [f64]) {
        let fitted = self.fitted();
        for (m, k) in x.chunks_exact_mut(3).enumerate() {
            for (c, v) in k.iter_mut().enumerate() {
                *v = if fitted[m] {
                    v.clamp(MIN_MULTIPLIER_LOG, self.upper[m][c].max(MIN_MULTIPLIER_LOG))
                } else {
                    0.0
                };
            }
        }
    }

    fn report(
        &self,
        job: &Job,
        multipliers: &[glam::DVec3],
        (method, fits): (albedo::AlbedoMethod, usize),
        last_change: f64,
    ) -> AlbedoReport {
        let fitted = self.fitted();
        let materials = &job.fit.scene.materials;
        let trusted: Vec<String> = job.settings.trust_albedo.clone();
        AlbedoReport {
            fit: job.settings.fit_albedo.unwrap_or(FitAlbedo::Materials),
            gauge: if trusted.is_empty() {
                "no material is trusted: the fitted materials' mean multiplier (geometric, \
                 weighted by their pixels) is kept at 1 per channel, and the lighting takes \
                 the rest of the scale"
                    .into()
            } else {
                format!(
                    "the trusted materials ({}) keep their albedo as given; the lighting and \
                     the other materials take the scale from them",
                    trusted.join(", ")
                )
            },
            trusted,
            method,
            rings: None,
            stalled: false,
            fits,
            last_change,
            converged: last_change
                < match method {
                    albedo::AlbedoMethod::Joint => albedo::JOINT_TOLERANCE,
                    albedo::AlbedoMethod::Alternation => albedo::ALBEDO_TOLERANCE,
                },
            texel_rounds: 0,
            texels: Vec::new(),
            texel_notes: Vec::new(),
            materials: materials
                .iter()
                .enumerate()
                .map(|(m, mat)| {
                    let given = given_albedo(&self.pixels, mat, m);
                    let k = multipliers[m];
                    let status = if self.trusted[m] {
                        MaterialStatus::Trusted
                    } else if !self.free[m] {
                        MaterialStatus::Unseen
                    } else if fitted[m] {
                        MaterialStatus::Fitted
                    } else {
                        MaterialStatus::Unconstrained
                    };
                    let log_k = glam::DVec3::new(k.x.ln(), k.y.ln(), k.z.ln());
                    MaterialAlbedo {
                        name: mat.name.clone(),
                        status,
                        pixels: self.pixels.counts[m],
                        views: self.pixels.views[m],
                        observability: self
                            .observability
                            .as_ref()
                            .and_then(|o| o[m])
                            .filter(|_| self.free[m]),
                        given: given.to_array(),
                        fitted: (given * k.as_vec3()).to_array(),
                        multiplier: k.as_vec3().to_array(),
                        at_bound: fitted[m]
                            && (0..3).any(|c| {
                                log_k[c] >= self.upper[m][c] - 1e-9
                                    || log_k[c] <= MIN_MULTIPLIER_LOG + 1e-9
                            }),
                    }
                })
                .collect(),
        }
    }
}

/// Iterates kept by [`anderson_step`]: with n views the exposures have n − 1 free directions,
/// and a memory of a few past steps covers those that converge slowest.
const ANDERSON_MEMORY: usize = 3;

/// The next iterate of a fixed-point iteration `x ← x + step(x)` by Anderson acceleration
/// (type II) over `history`, the past iterates and their steps, oldest first: the plain step
/// corrected by the combination of past changes that best cancels the current step in least
/// squares. Plain alternation converges linearly (each fit removed ~75% of the exposures'
/// error); where the map is linear in the directions the history spans, this lands on its
/// fixed point.
fn anderson_step(x: &[f64], step: &[f64], history: &[(Vec<f64>, Vec<f64>)]) -> Vec<f64> {
    use faer::linalg::solvers::Solve;
    let plain: Vec<f64> = x.iter().zip(step).map(|(x, s)| x + s).collect();
    let m = history.len();
    if m == 0 {
        return plain;
    }
    // Column j: the change of steps (and of iterates) from history j to the next iterate.
    let next = |j: usize| -> (&[f64], &[f64]) {
        match history.get(j + 1) {
            Some((x1, s1)) => (x1, s1),
            None => (x, step),
        }
    };
    let dg = |i: usize, j: usize| next(j).1[i] - history[j].1[i];
    let dx = |i: usize, j: usize| next(j).0[i] - history[j].0[i];
    let n = x.len();
    let gram = faer::Mat::<f64>::from_fn(m, m, |a, b| (0..n).map(|i| dg(i, a) * dg(i, b)).sum());
    let scale = (0..m).map(|a| gram[(a, a)]).fold(0.0, f64::max);
    if scale.is_nan() || scale <= 1e-300 {
        return plain;
    }
    let ridged = faer::Mat::<f64>::from_fn(m, m, |a, b| {
        gram[(a, b)] + if a == b { 1e-10 * scale } else { 0.0 }
    });
    let rhs = faer::Mat::<f64>::from_fn(m, 1, |a, _| (0..n).map(|i| dg(i, a) * step[i]).sum());
    let Ok(llt) = ridged.llt(faer::Side::Lower) else {
        return plain;
    };
    let gamma = llt.solve(&rhs);
    let out: Vec<f64> = (0..n)
        .map(|i| {
            plain[i]
                - (0..m)
                    .map(|j| gamma[(j, 0)] * (dx(i, j) + dg(i, j)))
                    .sum::<f64>()
        })
        .collect();
    if out.iter().all(|v| v.is_finite()) {
        out
    } else {
        plain
    }
}

/// Each view's exposure that makes its re-render's sum over its mask match its reference's,
/// normalised to a geometric mean of 1 over views. Errors when a view's re-render or
/// reference sums to nothing there: its exposure is then unknowable.
fn fitted_exposures(seen: &SeenViews, renders: &[Image]) -> Result<Vec<f64>> {
    let sum = |img: &Image, mask: &[bool]| -> f64 {
        img.rgb
            .iter()
            .zip(mask)
            .filter(|(_, m)| **m)
            .map(|(p, _)| p.as_dvec3().element_sum())
            .sum()
    };
    let mut ratios = Vec::with_capacity(renders.len());
    for (((cam, reference), render), mask) in seen
        .views
        .iter()
        .zip(&seen.references)
        .zip(renders)
        .zip(&seen.masks)
    {
        let (y, r) = (sum(reference, mask), sum(render, mask));
        let ratio = y / r;
        if !(ratio.is_finite() && ratio > 0.0) {
            return Err(Error::Invalid(format!(
                "view {:?}: its reference sums to {y:.3e} and the estimate's re-render to \
                 {r:.3e} over its pixels, so its exposure cannot be fitted (--exposure per-view)",
                cam.name
            )));
        }
        ratios.push(ratio);
    }
    let log_mean = ratios.iter().map(|r| r.ln()).sum::<f64>() / ratios.len() as f64;
    Ok(ratios.iter().map(|r| r / log_mean.exp()).collect())
}

/// Runs the job once, with the references as they are.
fn run_once(job: &Job, progress: &dyn Progress) -> Result<Estimate> {
    let t_all = Instant::now();
    let s = job.settings;
    s.check()?;
    let seen = job.seen;
    let (views, references, masks) = (&seen.views[..], &seen.references[..], &seen.masks[..]);
    let pixels: u64 = views.iter().map(|c| (c.width * c.height) as u64).sum();
    let truth_lights = &job.truth.lights.spheres;
    let model_auto = s.model == LightModel::Auto;

    // ---- Resolution from the data ----
    let template = FitSettings {
        smooth: s.smooth,
        ridge: s.ridge,
        colour: s.colour,
        time_limit: s.time_limit,
        holdout: model_auto,
        // Together, a cell is lit in every channel or none, and which cells a replicate lights
        // flips as a whole: the replicates' spread understated the clusters' scatter over seeds
        // (0.6° against 1.2°, and whole cells changing cluster), so no interval is stated.
        jackknife: if s.diagnose && s.colour == Colour::PerChannel {
            JACKKNIFE_GROUPS
        } else {
            0
        },
        ..FitSettings::new(job.render, 1, s.solver, s.spp, s.rounds)
    };
    let (rings, selection, fitted) = match &s.rings {
        Rings::Fixed(r) => (*r, None, None),
        Rings::Auto(candidates) => {
            progress.phase(
                "choosing rings",
                select::progress_units(&template, candidates, masks),
            );
            let choice = select::select_rings(
                job.fit,
                views,
                references,
                masks,
                candidates,
                &template,
                &|k| progress.advance(k),
            )
            .ok_or_else(|| Error::Invalid("no ring count to choose from".into()))?;
            (choice.selection.rings, Some(choice.selection), choice.fit)
        }
    };

    // ---- The envmap: fit (unless choosing the rings made it), re-render, noise floor,
    // representation limit ----
    let options = EstimateOptions {
        fit: FitSettings { rings, ..template },
        fitted: fitted.is_some(),
        evaluate: s.evaluate,
        noise_floor: s.noise_floor,
        oracle: s.oracle,
    };
    progress.phase("estimate", options.progress_units(masks, pixels));
    let envmap = pipeline::run(
        job.fit,
        job.truth,
        views,
        references,
        masks,
        truth_lights,
        job.center,
        &options,
        fitted,
        job.render,
        &|k| progress.advance(k),
    )?;

    // ---- Sphere lights, and the model chosen from the data ----
    let SphereModels {
        chosen: spheres,
        candidates,
        selection: model_selection,
        seconds: sphere_fit_seconds,
    } = fit_spheres(job, &envmap, rings, progress)?;
    let sphere_reports: Vec<SpheresReport> = candidates.iter().map(spheres_report).collect();
    let model = match (&model_selection, &spheres) {
        (Some(m), _) => m.chosen.clone(),
        (None, Some(so)) => so.fit.model_name(),
        (None, None) => "envmap".to_string(),
    };

    // ---- The noise floor, and the fit test of the model the estimate ends with ----
    let finals = match &spheres {
        Some(so) => &so.renders,
        None => &envmap.renders,
    };
    // Twins of the references (same lighting, independent noise): the truth's second render
    // where lightprobe rendered them (same settings, another seed), else the given `<view>_b`.
    let twins: &[Image] = if seen.rendered {
        &envmap.twins
    } else {
        &seen.twins
    };
    let twins = (!twins.is_empty() && twins.len() == references.len()).then_some(twins);
    // The noise of `reference − render` pixel by pixel. lightprobe's references: `A − B`,
    // exact where the model's render is as noisy as the true lights' (a sphere model; an
    // envmap's render is noisier, and then the ratio is an upper bound). Given twins:
    // `(A − B + X − X′)/√2`, X′ the model rendered again with other random numbers, holds the
    // reference's noise and the render's own.
    let samples: Vec<Vec<Vec3>> = match twins {
        Some(b) if seen.rendered => references
            .iter()
            .zip(b)
            .map(|(a, b)| a.rgb.iter().zip(&b.rgb).map(|(a, b)| *a - *b).collect())
            .collect(),
        Some(b) if s.diagnose && !finals.is_empty() => {
            progress.phase("render noise", pixels);
            let again = render_again(job, &envmap, spheres.as_ref(), &|k| progress.advance(k));
            let k = std::f32::consts::FRAC_1_SQRT_2;
            references
                .iter()
                .zip(b)
                .zip(finals.iter().zip(&again))
                .map(|((a, b), (x, x2))| {
                    let both = a.rgb.iter().zip(&b.rgb).zip(x.rgb.iter().zip(&x2.rgb));
                    both.map(|((a, b), (x, x2))| (*a - *b + *x - *x2) * k)
                        .collect()
                })
                .collect()
        }
        _ => Vec::new(),
    };
    let measured: Vec<ResidualNoise> = references
        .iter()
        .zip(finals)
        .zip(masks)
        .enumerate()
        .map(|(i, ((r, x), m))| ResidualNoise::of(r, x, m, samples.get(i).map(Vec::as_slice)))
        .collect();
    // The floor: the references against their twins where known, else the residual's
    // neighbouring pixels.
    let (floors, source): (Vec<Option<f64>>, _) = match twins {
        Some(_) if seen.rendered => {
            let floors = envmap.noise_floor.iter().map(|m| Some(m.rel_mae)).collect();
            (floors, Some(NoiseSource::RenderedTwin))
        }
        Some(b) => {
            let floors = pipeline::compare_views(b, references, masks)?;
            let floors = floors.iter().map(|m| Some(m.rel_mae)).collect();
            (floors, Some(NoiseSource::GivenTwins))
        }
        None if !measured.is_empty() => {
            let floors = measured.iter().map(ResidualNoise::rel_mae).collect();
            (floors, Some(NoiseSource::NeighbouringPixels))
        }
        None => (Vec::new(), None),
    };
    let true_lights = if seen.rendered {
        Vec::new()
    } else {
        envmap.noise_floor.clone()
    };
    // (Given twins without a second render of the model, as in the bounce probe's re-fit,
    // leave the test to the neighbouring pixels.)
    let mut fit_test = ResidualNoise::pooled(&measured).test().map(|test| {
        let misfit = test.p_value < MISFIT_P_VALUE && test.residual_over_noise >= MISFIT_RATIO;
        ModelFitTest {
            causes: if misfit {
                misfit_causes(job, &model)
            } else {
                Vec::new()
            },
            model: model.clone(),
            test,
            misfit,
        }
    });

    // References lightprobe rendered share the model's bounces, albedo and geometry: only
    // the light model can be wrong there, so there is nothing to probe.
    let mut diagnosis_seconds = 0.0;
    if let Some(t) = fit_test
        .as_mut()
        .filter(|t| t.misfit && t.model == "envmap" && s.diagnose && !seen.rendered)
    {
        // The probe's re-fit is tested on neighbouring pixels: so is this model here, for
        // a like-for-like comparison of the misfit's energy.
        let neighbours: Vec<ResidualNoise> = references
            .iter()
            .zip(finals)
            .zip(masks)
            .map(|((r, x), m)| ResidualNoise::of(r, x, m, None))
            .collect();
        if let Some(before) = ResidualNoise::pooled(&neighbours).test() {
            let t0 = Instant::now();
            bounce_probe(job, rings, t, before.excess_per_pixel);
            diagnosis_seconds = t0.elapsed().as_secs_f64();
        }
    }

    // ---- The report ----
    let fit = &envmap.fit;
    let mean = pipeline::mean_rel_mae;
    let converged = fit.channels.iter().all(|c| c.converged);
    let known = floors.iter().flatten().copied().collect::<Vec<f64>>();
    let report = EstimateReport {
        lightprobe_version: crate::VERSION.to_string(),
        scene: job.truth.scene.source.clone(),
        ignored: job.truth.scene.ignored.clone(),
        rings,
        cells: fit.envmap.grid.cell_count(),
        solver: s.solver,
        smooth: s.smooth,
        ridge: s.ridge,
        colour: s.colour,
        transport_spp: s.spp,
        rounds: s.rounds,
        settings: *job.render,
        rel_mae: mean(&envmap.errors),
        noise_floor_rel_mae: (known.len() == floors.len() && !known.is_empty())
            .then(|| known.iter().sum::<f64>() / known.len() as f64),
        noise_floor_source: source,
        true_lights_rel_mae: mean(&true_lights),
        fit_test,
        representation_limit_rel_mae: mean(&envmap.limit),
        views: views
            .iter()
            .enumerate()
            .map(|(i, cam)| ViewReport {
                view: cam.name.clone(),
                estimate: envmap.errors.get(i).copied(),
                noise_floor_rel_mae: floors.get(i).copied().flatten(),
                true_lights: true_lights.get(i).copied(),
                representation_limit: envmap.limit.get(i).copied(),
                rel_mae_over_noise_floor: envmap
                    .errors
                    .get(i)
                    .zip(floors.get(i).copied().flatten().filter(|n| *n > 0.0))
                    .map(|(e, n)| e.rel_mae / n),
                rel_mae_over_representation_limit: envmap
                    .errors
                    .get(i)
                    .zip(envmap.limit.get(i))
                    .map(|(e, l)| e.rel_mae / l.rel_mae),
                fit_test: measured.get(i).and_then(ResidualNoise::test),
            })
            .collect(),
        views_without_geometry: seen.blind.clone(),
        channels: fit.channels.clone(),
        clusters: recovery::cluster_estimates(&envmap.fit.envmap, &envmap.fit.replicates),
        envmap_colour: recovery::colour_figures(&envmap.fit.envmap, truth_lights, job.center),
        light_recovery: envmap.recovery.clone(),
        model,
        model_selection,
        exposure: None,
        albedo: None,
        spheres: spheres.as_ref().map(spheres_report),
        sphere_candidates: sphere_reports,
        timings: Timings {
            references_seconds: seen.seconds,
            noise_floor_seconds: 0.0,
            transport_seconds: fit.transport_seconds,
            solve_seconds: fit.solve_seconds,
            rings_selection_seconds: selection.as_ref().map(|s| s.seconds),
            fit_seconds: fit.transport_seconds + fit.solve_seconds,
            rerender_seconds: envmap.rerender_seconds,
            oracle_seconds: envmap.oracle_seconds,
            sphere_fit_seconds,
            diagnosis_seconds,
            alternation_seconds: 0.0,
            total_seconds: seen.seconds + t_all.elapsed().as_secs_f64(),
        },
        rings_selection: selection,
        memory: Memory {
            transport_bytes: fit.transport_bytes,
            peak_bytes: crate::memory::peak_bytes(),
        },
        threads: rayon::current_num_threads(),
        status: if converged {
            FitStatus::Ok
        } else {
            FitStatus::NotConverged
        },
    };
    Ok(Estimate {
        envmap,
        spheres,
        report,
        materials: None,
    })
}

/// The sphere-light models of an estimate.
#[derive(Default)]
struct SphereModels {
    /// The model the estimate ends with, if a sphere model.
    chosen: Option<SphereOutcome>,
    /// Every model compared on held-out pixels.
    candidates: Vec<SphereOutcome>,
    selection: Option<ModelSelection>,
    /// Seconds of the sphere fits.
    seconds: f64,
}

/// The model the estimate ends with (the chosen sphere model, else the envmap), rendered again
/// as its final render was but with other random numbers: its difference from that render
/// measures the render's own noise. (Fewer samples and a variance scaled by the count would
/// be cheaper, but the pixel sampler is stratified, so its variance falls faster than 1/N:
/// at a quarter of the samples the test read 0.92 for a model within noise.)
fn render_again(
    job: &Job,
    envmap: &Outcome,
    spheres: Option<&SphereOutcome>,
    progress: &(dyn Fn(u64) + Sync),
) -> Vec<Image> {
    let lights = final_lights(envmap, spheres);
    let first = pipeline::evaluation_settings(job.render);
    let settings = RenderSettings {
        seed: first.seed.wrapping_add(RENDER_AGAIN_SEED),
        ..first
    };
    job.truth
        .with_lights(&lights)
        .render_views(&job.seen.views, &settings, progress)
}

/// Seed offset of [`render_again`] from the final render's.
const RENDER_AGAIN_SEED: u64 = 65_537;

/// Seed offset of the alternation's renders of the albedo steps from the evaluation's.
const ALBEDO_RENDER_SEED: u64 = 131_071;

/// Seed offset of the texel rounds' renders from the evaluation's.
const TEXEL_RENDER_SEED: u64 = 262_147;

/// Side in pixels of the blocks the sphere fit sums ([`Observations::bin`]).
const SPHERE_BIN: u32 = 4;

/// Pixel samples a sphere fit lights per light and compared pixel, about: the measured fits
/// made 84–135 renders per light (the scan's `spheres:2` and the bundled scene's), at 8–64
/// samples a pixel.
const FIT_SAMPLES_PER_LIGHT: u64 = 4_000;

/// The same for a refinement from fitted lights (no start search; on all pixels, or with a
/// background).
const REFIT_SAMPLES_PER_LIGHT: u64 = 1_000;

/// A progress phase of sphere models: per model, its fit (counted by the pixel samples its
/// renders light, up to an estimate of the whole fit) and its re-render of `pixels` at
/// `spp`. The bar then moves while a fit runs instead of waiting for the re-render.
struct FitProgress<'a> {
    progress: &'a dyn Progress,
    spp: u64,
    /// Units the phase declared, and those reported so far.
    total: u64,
    reported: AtomicU64,
    /// Fit samples the phase counts at most, and those lit so far.
    budget: u64,
    lit: AtomicU64,
}

impl<'a> FitProgress<'a> {
    /// Starts phase `name` of models of `lights` lights each, a light's fit lighting about
    /// `per_light` pixel samples, each model re-rendered on `pixels` at `spp` (0: not).
    fn start(
        progress: &'a dyn Progress,
        name: &str,
        lights: &[usize],
        (pixels, spp): (u64, u64),
        per_light: u64,
    ) -> Self {
        let budget = lights.iter().sum::<usize>() as u64 * per_light;
        let total = lights.len() as u64 * pixels * spp + budget;
        progress.phase(name, total);
        FitProgress {
            progress,
            spp,
            total,
            reported: AtomicU64::new(0),
            budget,
            lit: AtomicU64::new(0),
        }
    }

    fn report(&self, units: u64) {
        self.reported.fetch_add(units, Ordering::Relaxed);
        self.progress.advance(units);
    }

    /// A fit's render lit `samples` pixel samples.
    fn fitted(&self, samples: u64) {
        let before = self.lit.fetch_add(samples, Ordering::Relaxed);
        let counted = self.budget.saturating_sub(before).min(samples);
        if counted > 0 {
            self.report(counted);
        }
    }

    /// A re-render finished `pixels` more pixels.
    fn rendered(&self, pixels: u64) {
        self.report(pixels * self.spp);
    }

    /// The phase's work is done: what it did not report (fits shorter than their estimate,
    /// models the choice did not need, re-renders not asked for) is reported now.
    fn finish(&self) {
        let left = self
            .total
            .saturating_sub(self.reported.load(Ordering::Relaxed));
        if left > 0 {
            self.report(left);
        }
    }
}

/// The sphere-light models the settings ask for, started from the envmap estimate.
fn fit_spheres(
    job: &Job,
    envmap: &Outcome,
    rings: u32,
    progress: &dyn Progress,
) -> Result<SphereModels> {
    let s = job.settings;
    let max_lights = s.model.max_lights();
    if max_lights == 0 {
        return Ok(SphereModels::default());
    }
    let (choose, model_auto) = (s.model.chooses(), s.model == LightModel::Auto);
    let seen = job.seen;
    let pixels: u64 = seen.views.iter().map(|c| (c.width * c.height) as u64).sum();
    let truth = &job.truth.lights.spheres;
    let scene = (job.center, job.size);
    let paths = PathCache::default();
    let fitted = super::spheres::fit_masks(&seen.views, &seen.masks, SPHERE_BIN, s.sphere_pixels);
    let obs = Observations {
        cameras: &seen.views,
        masks: &fitted,
        evaluated: &seen.masks,
        references: &seen.references,
        bin: SPHERE_BIN,
        holdout: choose,
        background: None,
        paths: Some(&paths),
        progress: None,
    };
    let in_spheres = |e: Error| Error::Stage {
        stage: "sphere-light model",
        inner: Box::new(e),
    };
    // Choosing: the nested sequence ends at the first model no larger one could be chosen
    // over ([`select::larger_models_needed`]), and then no sphere model is fitted again with
    // an envmap behind it; nor when the envmap is such a model.
    let floor = choose.then(|| held_out_noise_floor(job, envmap)).flatten();
    let candidates = std::cell::RefCell::new(Vec::new());
    let sufficient = std::cell::RefCell::new(None);
    let enough = |renders: &[Image], name: String| {
        if !choose || renders.is_empty() {
            return false;
        }
        let mut seen_so_far = candidates.borrow_mut();
        seen_so_far.push(select::held_out(renders, &seen.references, &seen.masks));
        let Some(f) = floor.or_else(|| neighbour_noise_floor(job, renders)) else {
            return false;
        };
        let all: Vec<&Validation> = seen_so_far.iter().collect();
        if select::larger_models_needed(&all, f) {
            return false;
        }
        *sufficient.borrow_mut() = Some((name, all[all.len() - 1].rel_mae() / f));
        true
    };
    // The bar's units: pixel samples of the fits' renders and of the re-renders.
    let eval_spp = if s.evaluate {
        pipeline::evaluation_settings(job.render).spp as u64
    } else {
        0
    };
    let held_in = obs.compared_pixels();
    let all_fitted = Observations {
        holdout: false,
        ..obs
    }
    .compared_pixels();
    let sizes: Vec<usize> = if choose {
        (1..=max_lights).collect()
    } else {
        vec![max_lights]
    };
    let bar = FitProgress::start(
        progress,
        "sphere lights",
        &sizes,
        (pixels, eval_spp),
        FIT_SAMPLES_PER_LIGHT * held_in,
    );
    let mut models = pipeline::run_sphere_models(
        job.fit,
        job.truth,
        &Observations {
            progress: Some(&|k| bar.fitted(k)),
            ..obs
        },
        &envmap.fit.envmap,
        truth,
        scene,
        max_lights,
        choose,
        job.render,
        s.evaluate,
        // A model whose lights merged is no candidate of the selection ([`select_model`]).
        &|so| so.fit.lights().len() == so.fit.requested && enough(&so.renders, so.fit.model_name()),
        &|k| bar.rendered(k),
    )
    .map_err(in_spheres)?;
    bar.finish();
    // Nested fits: the last one's time includes the others'.
    let mut seconds = models.last().map_or(0.0, |m| m.fit.seconds);
    // The envmap comes after the sphere models in parameter count.
    if model_auto && sufficient.borrow().is_none() {
        enough(&envmap.renders, "envmap".to_string());
    }
    let sufficient = sufficient.into_inner();
    // --model auto: sphere models again, with an envmap behind their lights.
    let bases: Vec<_> = if model_auto && sufficient.is_none() {
        pipeline::background_bases(&models, &seen.references, &seen.masks)
            .into_iter()
            .map(|b| b.fit.clone())
            .collect()
    } else {
        Vec::new()
    };
    for base in &bases {
        let bar = FitProgress::start(
            progress,
            &format!("spheres:{} + envmap", base.requested),
            &[base.requested],
            (pixels, eval_spp),
            REFIT_SAMPLES_PER_LIGHT * held_in,
        );
        let combined = pipeline::run_with_background(
            job.fit,
            job.truth,
            &Observations {
                progress: Some(&|k| bar.fitted(k)),
                ..obs
            },
            base,
            rings,
            truth,
            scene,
            job.render,
            true,
            &|k| bar.rendered(k),
        )
        .map_err(in_spheres)?;
        bar.finish();
        seconds += combined.fit.seconds;
        models.push(combined);
    }
    // The 95% intervals, for the model the estimate ends with (on every pixel the fit
    // compares, held-out ones included).
    let intervals = |so: &mut SphereOutcome| {
        let grid = so.fit.background.as_ref().map(|b| b.grid.clone());
        // No phase for intervals that will not be measured: its bar would jump to its end.
        if !super::spheres::intervals_measured(so.fit.fitted.len(), grid.as_ref()) {
            return 0.0;
        }
        let all = Observations {
            holdout: false,
            background: grid.as_ref(),
            ..obs
        };
        let residual = super::spheres::SphereSettings::new(so.fit.requested, job.render)
            .refine
            .residual;
        let t = std::time::Instant::now();
        // The radiance solve's render, then two half-sample renders at the lights and at
        // each of their four parameters moved ([`super::spheres::uncertainty`]).
        let renders = 2 + 4 * so.fit.fitted.len() as u64;
        let bar = FitProgress::start(
            progress,
            "sphere intervals",
            &[1],
            (0, 0),
            renders * residual.spp as u64 * all_fitted,
        );
        let all = Observations {
            progress: Some(&|k| bar.fitted(k)),
            ..all
        };
        super::spheres::measure_intervals(job.fit, &all, &mut so.fit.fitted, job.center, &residual);
        bar.finish();
        t.elapsed().as_secs_f64()
    };
    if !choose {
        let mut chosen = models.pop();
        if let Some(so) = chosen.as_mut() {
            seconds += intervals(so);
        }
        return Ok(SphereModels {
            chosen,
            seconds,
            ..SphereModels::default()
        });
    }
    let mut sel = pipeline::select_model(
        model_auto.then_some(envmap),
        &models,
        &seen.references,
        &seen.masks,
    )
    .ok_or_else(|| in_spheres(Error::Invalid("no candidate model to choose from".into())))?;
    (sel.at_noise_floor, sel.over_noise_floor) = sufficient.unzip();
    let Some(i) = models.iter().position(|m| sel.chosen == m.fit.model_name()) else {
        // The envmap was chosen.
        return Ok(SphereModels {
            chosen: None,
            candidates: models,
            selection: Some(sel),
            seconds,
        });
    };
    // Chosen on held-out pixels: fitted again on all of them, whose paths are walked anew.
    paths.clear();
    let bar = FitProgress::start(
        progress,
        "refit on all pixels",
        &[models[i].fit.requested],
        (pixels, eval_spp),
        REFIT_SAMPLES_PER_LIGHT * all_fitted,
    );
    let mut refit = pipeline::refit_on_all_pixels(
        job.fit,
        job.truth,
        &Observations {
            progress: Some(&|k| bar.fitted(k)),
            ..obs
        },
        &models[i].fit,
        truth,
        job.center,
        job.render,
        true,
        &|k| bar.rendered(k),
    )
    .map_err(in_spheres)?;
    bar.finish();
    seconds += refit.fit.seconds - models[i].fit.seconds + intervals(&mut refit);
    // The candidates are reported as the estimate ends them: the chosen one refitted.
    models[i] = refit.clone();
    Ok(SphereModels {
        chosen: Some(refit),
        candidates: models,
        selection: Some(sel),
        seconds,
    })
}

/// The held-out relMAE the true lights would score (the noise alone), where it is known
/// without a model: the true lights' second render where lightprobe rendered the references
/// (it lights the candidates' camera paths, so it is their floor exactly); the given twins'
/// over √2 otherwise (their difference holds two captures' noise, a render of the true lights
/// one capture's and its own: √2 takes the render's as nil, the floor's lowest, so choosing
/// stops no earlier than it should). None: neither ([`neighbour_noise_floor`]).
fn held_out_noise_floor(job: &Job, envmap: &Outcome) -> Option<f64> {
    let seen = job.seen;
    let v = if seen.rendered && envmap.twins.len() == seen.references.len() {
        select::held_out(&envmap.twins, &seen.references, &seen.masks).rel_mae()
    } else if !seen.rendered && seen.twins.len() == seen.references.len() {
        select::held_out(&seen.twins, &seen.references, &seen.masks).rel_mae()
            / std::f64::consts::SQRT_2
    } else {
        return None;
    };
    (v.is_finite() && v > 0.0).then_some(v)
}

/// The relMAE the noise alone gives in a candidate's residual (`renders` against the
/// references), from neighbouring pixels over the masks ([`ResidualNoise`]), mean over views.
/// Lenient where a misfit is sharp-edged (part of it reads as noise): used only where no twin
/// gives the floor.
fn neighbour_noise_floor(job: &Job, renders: &[Image]) -> Option<f64> {
    let seen = job.seen;
    let each: Vec<f64> = seen
        .references
        .iter()
        .zip(renders)
        .zip(&seen.masks)
        .filter_map(|((r, x), m)| ResidualNoise::of(r, x, m, None).rel_mae())
        .collect();
    (each.len() == renders.len() && !each.is_empty())
        .then(|| each.iter().sum::<f64>() / each.len() as f64)
}

/// Re-fits the envmap with one more bounce, at a quarter of the samples, and says in `test`'s
/// causes how much of the misfit's energy that removes: more than half puts the bounce count
/// first. The misfit's energy per pixel (the residual's less the noise's) is compared, not the
/// ratio, since the probe's fewer samples raise its noise; `before` is the model's, measured
/// as the probe's is (on neighbouring pixels, whatever the main test used).
/// A probe that fails leaves the causes as they were: it is a diagnosis, not the estimate.
fn bounce_probe(job: &Job, rings: u32, test: &mut ModelFitTest, before: f64) {
    let bounces = job.render.max_bounces + 1;
    if bounces > crate::scene::sidecar::MAX_BOUNCES {
        return;
    }
    let render = RenderSettings {
        max_bounces: bounces,
        spp: (job.render.spp / 4).max(16),
        ..*job.render
    };
    let s = job.settings;
    let settings = EstimateSettings {
        rings: Rings::Fixed(rings),
        model: LightModel::Envmap,
        spp: (s.spp / 4).max(s.rounds),
        oracle: false,
        diagnose: false,
        ..s.clone()
    };
    let Ok(probe) = run_once(
        &Job {
            render: &render,
            settings: &settings,
            ..*job
        },
        &(),
    ) else {
        return;
    };
    let Some(after) = probe.report.fit_test.map(|t| t.test.excess_per_pixel) else {
        return;
    };
    let removed = 1.0 - after.max(0.0) / before.max(f64::MIN_POSITIVE);
    let Some(i) = test
        .causes
        .iter()
        .position(|c| c.starts_with("the bounce count"))
    else {
        return;
    };
    let mut cause = test.causes.remove(i);
    cause += &format!(
        " (a quick re-fit with {bounces} bounces removed {:.0}% of the misfit)",
        100.0 * removed.clamp(0.0, 1.0)
    );
    test.causes.insert(if removed > 0.5 { 0 } else { i }, cause);
}

/// What to check when `model` does not explain the images, most likely first: what the
/// job knows of its own settings and scene picks the words.
fn misfit_causes(job: &Job, model: &str) -> Vec<String> {
    let mut causes = Vec::new();
    if job.seen.rendered {
        // Rendered by this scene with these settings: only the light model can differ.
        causes.push(if model == "envmap" {
            "the light model: an envmap cannot place the scene's lights near it (try --model \
             auto) or resolve small ones (more --rings)"
                .to_string()
        } else {
            "the light model: more or fewer lights (try --model auto), or a fit that stopped \
             short"
                .to_string()
        });
        return causes;
    }
    if model == "envmap" {
        causes.push(
            "the light model: an envmap cannot place lights near the scene (try --model auto) \
             or resolve small ones (more --rings)"
                .to_string(),
        );
    }
    causes.push(format!(
        "the bounce count: max_bounces is {} in the render settings; light that bounces more \
         is missing",
        job.render.max_bounces
    ));
    causes.push(match job.settings.fit_albedo {
        None => "the albedo (the glTF's baseColor, or the sidecar's albedo): try --fit-albedo \
                 materials"
            .to_string(),
        Some(FitAlbedo::Materials) => "the albedo within a material (--fit-albedo materials \
                                       fits one colour per material; texels also corrects \
                                       textures)"
            .to_string(),
        Some(FitAlbedo::Texels) => "the albedo within a material: finer than the texel grid \
                                    (--texel-grid), or vertex colours and constant albedos, \
                                    which texels leaves to one colour per material"
            .to_string(),
    });
    let ignored = &job.truth.scene.ignored;
    if !ignored.is_empty() {
        causes.push(format!(
            "what the diffuse model leaves out: {}",
            ignored
                .iter()
                .map(|i| format!("{} ({})", i.what, i.properties.join(", ")))
                .collect::<Vec<_>>()
                .join("; ")
        ));
    }
    if job.settings.exposure == Exposure::Shared && job.seen.views.len() > 1 {
        causes.push(
            "the exposure: views at different exposures need --exposure per-view".to_string(),
        );
    }
    causes.push("the geometry and the camera poses".to_string());
    causes
}

fn spheres_report(so: &SphereOutcome) -> SpheresReport {
    SpheresReport {
        model: so.fit.model_name(),
        background_rings: so.fit.background.as_ref().map(|b| b.grid.rings()),
        lights: so.fit.fitted.clone(),
        start: so
            .fit
            .start
            .iter()
            .map(|l| LightStart {
                center: l.center.to_array(),
                radius: l.radius,
            })
            .collect(),
        requested: so.fit.requested,
        rel_mae: so.rel_mae(),
        views: so.errors.clone(),
        fit_rel_mae_binned: so.fit.fit_rel_mae,
        iterations: so.fit.iterations,
        objective_trace: so.fit.history.clone(),
        renders: so.fit.renders,
        recovery: so.recovery.clone(),
        fit_pixels: so.fit_pixels,
        seen_pixels: so.seen_pixels,
        fit_seconds: so.fit.seconds,
        rerender_seconds: so.rerender_seconds,
    }
}

/// The JSON Schema of `report.json`.
pub fn report_schema() -> String {
    let schema = schemars::schema_for!(EstimateReport);
    serde_json::to_string_pretty(&schema).expect("a schema serialises") + "\n"
}
