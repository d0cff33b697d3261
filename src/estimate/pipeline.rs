//! An estimate from references to figures: the steps the `estimate` command and the sweep
//! share — references, geometry masks, noise floor, fit, re-render of the estimate,
//! representation limit and light recovery. Files are the caller's business.
//!
//! Seeds: references use the sidecar's seed; the noise floor, the transport, the re-render and
//! the oracle each offset it, so no two of them share random numbers.

use std::path::Path;
use std::time::Instant;

use glam::Vec3;

use super::recovery::{self, LightRecovery, SphereRecovery};
use super::select::held_out;
use super::spheres::{self, Observations, SphereFit, SphereSettings};
use super::{Fit, FitSettings, Solver};
use crate::envmap::{Envmap, RingGrid};
use crate::error::{Error, Result};
use crate::imageio::{self, Image};
use crate::metrics::{self, Metrics};
use crate::render::{Lights, RenderSettings, Renderer};
use crate::scene::sidecar::MAX_SPP;
use crate::scene::{Camera, SphereLight};

/// Reads each view's reference in `dir` ([`reference_path`]), checking size and finiteness,
/// with the pixels each can vouch for: not saturated, and inside `<view>.mask.png` where there
/// is one (non-black = kept).
pub fn load_references(
    dir: &Path,
    views: &[&Camera],
    decoding: imageio::Decoding,
) -> Result<(Vec<Image>, Vec<Vec<bool>>)> {
    check_reference_dir(dir)?;
    let mut images = Vec::new();
    let mut usable = Vec::new();
    for cam in views {
        let p = reference_path(dir, cam)?;
        let (img, mut ok) = imageio::read_photo(&p, decoding)?;
        let (width, height) = (cam.width, cam.height);
        if (img.width, img.height) != (width, height) {
            return Err(Error::file(
                &p,
                format!(
                    "is {}×{}, but view {:?} renders {width}×{height} (the sidecar's image, or --height)",
                    img.width, img.height, cam.name
                ),
            ));
        }
        imageio::check_radiance(&p, &img, true)?;
        imageio::check_negative_share(&p, &img)?;
        let mask_path = dir.join(format!("{}.mask.png", cam.name));
        if mask_path.exists() {
            let (mask, _) = imageio::read_photo(&mask_path, imageio::Decoding::default())?;
            if (mask.width, mask.height) != (width, height) {
                return Err(Error::file(
                    &mask_path,
                    format!(
                        "is {}×{}, but its reference is {width}×{height}",
                        mask.width, mask.height
                    ),
                ));
            }
            for (o, m) in ok.iter_mut().zip(&mask.rgb) {
                *o &= m.max_element() > 0.0;
            }
        }
        images.push(img);
        usable.push(ok);
    }
    Ok((images, usable))
}

/// Reads each view's twin in `dir` ([`twin_name`]), checked as its reference is, and leaves
/// out of `usable` the pixels the twin cannot vouch for (saturated). `cameras`: every camera
/// name of the scene, whose references are no twins. Empty when the folder holds no twin; an
/// error when it holds some but not all, or a twin equal to its reference (the same random
/// numbers: it measures no noise).
pub fn load_twins(
    dir: &Path,
    views: &[&Camera],
    cameras: &[String],
    references: &[Image],
    decoding: imageio::Decoding,
    usable: &mut [Vec<bool>],
) -> Result<Vec<Image>> {
    let taken = |cam: &Camera| twin_name_taken(cam, views, cameras);
    let paths: Vec<Option<std::path::PathBuf>> = views
        .iter()
        .map(|cam| {
            (!taken(cam))
                .then(|| photo_path(dir, &twin_name(cam)))
                .flatten()
        })
        .collect();
    let Some(given) = paths.iter().flatten().next() else {
        return Ok(Vec::new());
    };
    let mut twins = Vec::with_capacity(views.len());
    for (((cam, path), reference), ok) in views.iter().zip(&paths).zip(references).zip(usable) {
        let Some(p) = path else {
            let why = if taken(cam) {
                format!(
                    "view {:?} can have none: {:?}, its twin's name, is a camera of the scene (rename that camera)",
                    cam.name,
                    twin_name(cam)
                )
            } else {
                format!(
                    "none for view {:?}: give a `<view>_b` twin for every view or for none",
                    cam.name
                )
            };
            return Err(Error::file(
                dir,
                format!("holds a twin ({}) but {why}", given.display()),
            ));
        };
        let (img, twin_ok) = imageio::read_photo(p, decoding)?;
        if (img.width, img.height) != (cam.width, cam.height) {
            return Err(Error::file(
                p,
                format!(
                    "is {}×{}, but it is the twin of view {:?}'s {}×{} reference",
                    img.width, img.height, cam.name, cam.width, cam.height
                ),
            ));
        }
        imageio::check_radiance(p, &img, true)?;
        imageio::check_negative_share(p, &img)?;
        if img.rgb == reference.rgb {
            return Err(Error::file(
                p,
                format!(
                    "equals view {:?}'s reference pixel for pixel: a twin needs other random numbers (another seed) to measure the noise",
                    cam.name
                ),
            ));
        }
        for (o, t) in ok.iter_mut().zip(twin_ok) {
            *o &= t;
        }
        twins.push(img);
    }
    Ok(twins)
}

/// The name of view `cam`'s twin: `<view>_b` ([`load_twins`]), a second capture of the same
/// view under the same lighting with independent noise (two renders with other seeds, two
/// exposures of a still scene), which measures the references' noise ([`crate::noise`]).
pub fn twin_name(cam: &Camera) -> String {
    format!("{}_b", cam.name)
}

/// Whether view `cam`'s twin name is a view's or another camera's name (then its file would
/// be that camera's reference, not a twin).
pub fn twin_name_taken(cam: &Camera, views: &[&Camera], cameras: &[String]) -> bool {
    let name = twin_name(cam);
    views.iter().any(|v| v.name == name) || cameras.contains(&name)
}

/// The reference of view `cam` in `dir`: the first `<view>.<ext>` there in the order of
/// [`imageio::PHOTO_EXTENSIONS`] (EXR first: `render-reference` writes a PNG preview beside
/// each EXR).
pub fn reference_path(dir: &Path, cam: &Camera) -> Result<std::path::PathBuf> {
    photo_path(dir, &cam.name).ok_or_else(|| {
        Error::file(
            dir,
            format!(
                "has no reference for view {:?}: expected {0}.exr, .hdr, .png, .jpg or .jpeg",
                cam.name
            ),
        )
    })
}

/// The first `<name>.<ext>` in `dir`, in the order of [`imageio::PHOTO_EXTENSIONS`].
fn photo_path(dir: &Path, name: &str) -> Option<std::path::PathBuf> {
    // Each extension as written here and in capitals, as cameras write them (`.JPG`).
    imageio::PHOTO_EXTENSIONS
        .iter()
        .flat_map(|e| [e.to_string(), e.to_ascii_uppercase()])
        .map(|e| dir.join(format!("{name}.{e}")))
        .find(|p| p.is_file())
}

/// The image size of each view's reference in `dir`, read from the files' headers, and the
/// files.
pub fn reference_sizes(
    dir: &Path,
    views: &[Camera],
) -> Result<Vec<((u32, u32), std::path::PathBuf)>> {
    check_reference_dir(dir)?;
    views
        .iter()
        .map(|cam| {
            let p = reference_path(dir, cam)?;
            Ok((imageio::photo_size(&p)?, p))
        })
        .collect()
}

fn check_reference_dir(dir: &Path) -> Result<()> {
    if !dir.is_dir() {
        let what = if dir.exists() {
            "is not a folder (--reference names a folder of <view>.exr, .hdr, .png or .jpg)"
        } else {
            "no such folder"
        };
        return Err(Error::file(dir, what));
    }
    Ok(())
}

/// The pixels every error counts: the reference's coverage alpha where it has one, else the
/// pixel centres that hit geometry.
pub fn geometry_masks(
    renderer: &Renderer,
    views: &[&Camera],
    references: &[Image],
) -> Vec<Vec<bool>> {
    references
        .iter()
        .zip(views)
        .map(|(img, cam)| match &img.alpha {
            Some(_) => metrics::mask_of(img),
            None => renderer
                .aovs(cam)
                .depth
                .rgb
                .iter()
                .map(|d| d.x > 0.0)
                .collect(),
        })
        .collect()
}

/// The views with a pixel in their mask, with their references and masks, and the names of
/// the others ([`seen_views`]).
pub struct SeenViews<'a> {
    pub views: Vec<&'a Camera>,
    pub references: Vec<Image>,
    pub masks: Vec<Vec<bool>>,
    /// Views whose mask is empty: nothing to fit or to measure there.
    pub blind: Vec<String>,
    /// Their references, in the same order (written out with the others).
    pub blind_references: Vec<Image>,
    /// Why a view's mask is empty, for a person ("it sees no scene geometry").
    pub blind_reason: String,
    /// Seconds spent rendering or reading the references.
    pub seconds: f64,
    /// The references were rendered from the truth renderer's lights, so a second render of
    /// those lights is their exact twin: same lighting, independent noise.
    pub rendered: bool,
    /// The references' given twins ([`load_twins`]), one per view in the same order, or none.
    pub twins: Vec<Image>,
}

impl SeenViews<'_> {
    /// The same views with each reference divided by its view's exposure (blind views keep
    /// theirs: they have none fitted).
    pub fn with_exposures(&self, exposures: &[f64]) -> Self {
        let scaled = |images: &[Image]| -> Vec<Image> {
            images
                .iter()
                .zip(exposures)
                .map(|(r, &e)| {
                    let inv = (1.0 / e) as f32;
                    Image {
                        width: r.width,
                        height: r.height,
                        rgb: r.rgb.iter().map(|p| *p * inv).collect(),
                        alpha: r.alpha.clone(),
                    }
                })
                .collect()
        };
        SeenViews {
            views: self.views.clone(),
            references: scaled(&self.references),
            twins: scaled(&self.twins),
            masks: self.masks.clone(),
            blind: self.blind.clone(),
            blind_references: self.blind_references.clone(),
            blind_reason: self.blind_reason.clone(),
            seconds: self.seconds,
            rendered: self.rendered,
        }
    }
}

/// Splits the views (in order, with their references and masks) into those with at least one
/// masked pixel and the rest.
pub fn seen_views<'a>(
    views: &[&'a Camera],
    references: Vec<Image>,
    twins: Vec<Image>,
    masks: Vec<Vec<bool>>,
) -> SeenViews<'a> {
    let mut twins = twins.into_iter();
    let mut out = SeenViews {
        views: Vec::new(),
        references: Vec::new(),
        masks: Vec::new(),
        blind: Vec::new(),
        blind_references: Vec::new(),
        blind_reason: String::new(),
        seconds: 0.0,
        rendered: false,
        twins: Vec::new(),
    };
    for ((cam, r), m) in views.iter().zip(references).zip(masks) {
        let twin = twins.next();
        if m.contains(&true) {
            out.views.push(*cam);
            out.references.push(r);
            out.twins.extend(twin);
            out.masks.push(m);
        } else {
            out.blind.push(cam.name.clone());
            out.blind_references.push(r);
        }
    }
    out
}

/// Error of each image against its reference.
pub fn compare_views(
    images: &[Image],
    references: &[Image],
    masks: &[Vec<bool>],
) -> Result<Vec<Metrics>> {
    images
        .iter()
        .zip(references)
        .zip(masks)
        .map(|((x, r), m)| metrics::compare(x, r, m))
        .collect()
}

/// Settings of the re-render of an estimate and of the noise floor's second render of the
/// reference lighting: a seed the fit never saw.
pub fn evaluation_settings(settings: &RenderSettings) -> RenderSettings {
    RenderSettings {
        seed: settings.seed.wrapping_add(104_729),
        ..*settings
    }
}

/// The noise floor: error of a second, independent render of the reference lighting.
pub fn noise_floor(
    renderer: &Renderer,
    views: &[&Camera],
    references: &[Image],
    masks: &[Vec<bool>],
    settings: &RenderSettings,
    progress: &(dyn Fn(u64) + Sync),
) -> Result<Vec<Metrics>> {
    let again = renderer.render_views(views, &evaluation_settings(settings), progress);
    compare_views(&again, references, masks)
}

/// What to do after the fit.
#[derive(Debug, Clone, Copy)]
pub struct EstimateOptions {
    pub fit: FitSettings,
    /// The fit is made already and handed to [`run`] (choosing the resolution made it): no
    /// transport of its own.
    pub fitted: bool,
    /// Re-render the estimate and measure its error.
    pub evaluate: bool,
    /// With `evaluate`, also measure the noise floor: the truth renderer's own lights lit
    /// from the re-render's camera paths (one walk for both).
    pub noise_floor: bool,
    /// Also fit with 8× the samples (NNLS) and measure that: the representation limit.
    pub oracle: bool,
}

impl EstimateOptions {
    /// Units of work [`run`] reports to its progress on `masks` (`pixels` in all views): the
    /// fit's ([`FitSettings::progress_units`]; the oracle's count 8 each), and every pixel of
    /// each re-rendered image.
    pub fn progress_units(&self, masks: &[Vec<bool>], pixels: u64) -> u64 {
        let lightings = self.evaluate as u64 * (1 + self.noise_floor as u64) + self.oracle as u64;
        // The oracle is an NNLS fit whatever the solver.
        let oracle = FitSettings {
            solver: Solver::Nnls,
            ..self.fit
        };
        let oracle = if self.oracle {
            8 * oracle.progress_units(masks)
        } else {
            0
        };
        let fit = if self.fitted {
            0
        } else {
            self.fit.progress_units(masks)
        };
        fit + oracle + pixels * lightings
    }
}

/// An estimate and its figures.
pub struct Outcome {
    pub fit: Fit,
    /// The estimate re-rendered, per view (empty without `evaluate`).
    pub renders: Vec<Image>,
    pub errors: Vec<Metrics>,
    /// Error of the truth's second render, per view (empty without `noise_floor`).
    pub noise_floor: Vec<Metrics>,
    /// That second render, per view: the references' twin where they were rendered from the
    /// same lights.
    pub twins: Vec<Image>,
    /// Error of the best envmap of this resolution, per view (empty without `oracle`).
    pub limit: Vec<Metrics>,
    pub recovery: Vec<LightRecovery>,
    /// The evaluation render: every image lit from its one walk (estimate, noise floor,
    /// representation limit).
    pub rerender_seconds: f64,
    /// The representation limit's fit.
    pub oracle_seconds: f64,
}

impl Outcome {
    /// Mean relMAE over views of the estimate (None without evaluation).
    pub fn rel_mae(&self) -> Option<f64> {
        mean_rel_mae(&self.errors)
    }
}

/// Mean relMAE over views.
pub fn mean_rel_mae(v: &[Metrics]) -> Option<f64> {
    (!v.is_empty()).then(|| v.iter().map(|m| m.rel_mae).sum::<f64>() / v.len() as f64)
}

/// Fits in the scene of `renderer`, then optionally re-renders and measures in the scene of
/// `truth_renderer` (the same one, or e.g. the true scene when the fit had perturbed albedos;
/// same geometry and views), then matches bright clusters to `truth` (the sphere lights that
/// made the references, if known) seen from `center`. `render` holds the references' render
/// settings. `fitted`: the fit, if already made (`options.fitted`).
#[allow(clippy::too_many_arguments)]
pub fn run(
    renderer: &Renderer,
    truth_renderer: &Renderer,
    views: &[&Camera],
    references: &[Image],
    masks: &[Vec<bool>],
    truth: &[SphereLight],
    center: Vec3,
    options: &EstimateOptions,
    fitted: Option<Fit>,
    render: &RenderSettings,
    progress: &(dyn Fn(u64) + Sync),
) -> Result<Outcome> {
    let seen: f64 = references
        .iter()
        .zip(masks)
        .flat_map(|(r, m)| r.rgb.iter().zip(m).filter(|(_, m)| **m))
        .map(|(c, _)| c.abs().element_sum() as f64)
        .sum();
    if seen <= 0.0 {
        return Err(Error::Invalid(
            "the references are black wherever they see geometry: no light reaches what the views see, so the lighting is unobservable".into(),
        ));
    }
    let fit = match fitted {
        Some(f) => f,
        None => super::fit(renderer, views, references, masks, &options.fit, progress),
    };
    if fit.non_finite {
        return Err(Error::Invalid(format!(
            "the {:?} solver produced a non-finite envmap",
            options.fit.solver
        )));
    }

    let t = Instant::now();
    let best = options.oracle.then(|| {
        let mut o = options.fit;
        o.solver = Solver::Nnls;
        o.transport.spp = options
            .fit
            .transport
            .spp
            .saturating_mul(8)
            .clamp(1, MAX_SPP);
        o.transport.seed = render.seed.wrapping_add(31_337);
        // 8× the samples per pixel: each pixel counts 8 for progress.
        let progress = |k| progress(8 * k);
        Lights::env(super::fit(renderer, views, references, masks, &o, &progress).envmap)
    });
    let oracle_seconds = t.elapsed().as_secs_f64();

    // One walk of camera paths, lit by each: the estimate, the truth, the best envmap.
    let t = Instant::now();
    let estimate = Lights::env(fit.envmap.clone());
    let with_truth = options.noise_floor && !truth_renderer.lights.is_empty();
    let mut sets: Vec<&Lights> = Vec::new();
    if options.evaluate {
        sets.push(&estimate);
        if with_truth {
            sets.push(truth_renderer.lights);
        }
    }
    sets.extend(&best);
    let mut images = truth_renderer
        .render_views_under(views, &evaluation_settings(render), &sets, None, progress)
        .into_iter();
    let (mut renders, mut errors) = (Vec::new(), Vec::new());
    let (mut noise_floor, mut twins) = (Vec::new(), Vec::new());
    if options.evaluate {
        renders = images.next().expect("a set per image");
        errors = compare_views(&renders, references, masks)?;
        if with_truth {
            twins = images.next().expect("a set per image");
            noise_floor = compare_views(&twins, references, masks)?;
        }
    }
    let limit = match images.next() {
        Some(imgs) => compare_views(&imgs, references, masks)?,
        None => Vec::new(),
    };
    let rerender_seconds = t.elapsed().as_secs_f64();

    let recovery = recovery::recover(&fit.envmap, truth, center);
    Ok(Outcome {
        fit,
        renders,
        errors,
        noise_floor,
        twins,
        limit,
        recovery,
        rerender_seconds,
        oracle_seconds,
    })
}

/// A sphere-model estimate and its figures.
#[derive(Clone)]
pub struct SphereOutcome {
    pub fit: SphereFit,
    /// The model re-rendered, per view (empty without `evaluate`).
    pub renders: Vec<Image>,
    pub errors: Vec<Metrics>,
    /// Against the true lights, when known.
    pub recovery: Vec<SphereRecovery>,
    pub rerender_seconds: f64,
    /// Pixels the fit compared ([`spheres::fit_masks`]), and pixels the views see.
    pub fit_pixels: usize,
    pub seen_pixels: usize,
}

impl SphereOutcome {
    pub fn rel_mae(&self) -> Option<f64> {
        mean_rel_mae(&self.errors)
    }
}

/// Fits sphere models of 1, 2, … up to `max_lights` lights (greedy and nested, see
/// [`spheres::fit_sphere_models`]; directions from `envmap`, an envmap estimate of the same
/// images), or with `all` false the `max_lights` one alone; each re-rendered as it is made
/// (with `evaluate`) with a seed the fit never saw, in the scene of `truth_renderer`, and
/// matched to `truth`. `enough` ends the nested sequence at the first model it accepts (from
/// its outcome). `scene` is the scene's centre and size (metres).
#[allow(clippy::too_many_arguments)]
pub fn run_sphere_models(
    renderer: &Renderer,
    truth_renderer: &Renderer,
    obs: &Observations,
    envmap: &Envmap,
    truth: &[SphereLight],
    (center, size): (Vec3, f32),
    max_lights: usize,
    all: bool,
    render: &RenderSettings,
    evaluate: bool,
    enough: &dyn Fn(&SphereOutcome) -> bool,
    progress: &(dyn Fn(u64) + Sync),
) -> Result<Vec<SphereOutcome>> {
    let settings = SphereSettings {
        at_once: !all,
        ..SphereSettings::new(max_lights, render)
    };
    let mut out = Vec::new();
    let mut failed = None;
    spheres::fit_sphere_models(renderer, obs, envmap, center, size, &settings, &mut |fit| {
        if fit.lights().is_empty() {
            return true;
        }
        let outcome = outcome_of(
            fit.clone(),
            truth_renderer,
            obs,
            truth,
            center,
            render,
            evaluate,
            progress,
        );
        match outcome {
            Ok(o) => {
                let go_on = !enough(&o);
                out.push(o);
                go_on
            }
            Err(e) => {
                failed = Some(e);
                false
            }
        }
    });
    if let Some(e) = failed {
        return Err(e);
    }
    // Models the sequence did not need to fit: their re-renders' share of the progress.
    if evaluate && all {
        let pixels: u64 = obs
            .cameras
            .iter()
            .map(|c| (c.width * c.height) as u64)
            .sum();
        progress(pixels * max_lights.saturating_sub(out.len()) as u64);
    }
    if out.is_empty() {
        return Err(Error::Invalid(
            "no sphere light explains the images (every fitted light contributes nothing)".into(),
        ));
    }
    Ok(out)
}

/// The bases for [`run_with_background`]: the sphere models (all their lights kept) with no
/// more lights than the one held-out selection takes among `spheres` alone (see
/// [`select_model`]). Not that one alone: a lamp under a sky can take a second light to patch
/// the sky, which the background then makes needless.
pub fn background_bases<'a>(
    spheres: &'a [SphereOutcome],
    references: &[Image],
    masks: &[Vec<bool>],
) -> Vec<&'a SphereOutcome> {
    let Some(sel) = select_model(None, spheres, references, masks) else {
        return Vec::new();
    };
    let Some(chosen) = spheres.iter().find(|s| s.fit.model_name() == sel.chosen) else {
        return Vec::new();
    };
    spheres
        .iter()
        .filter(|s| {
            s.fit.background.is_none()
                && s.fit.requested <= chosen.fit.requested
                && s.fit.lights().len() == s.fit.requested
        })
        .collect()
}

/// The sphere model `base` with an envmap of `rings` fitted behind its lights, for light
/// from afar beside the near lights (a sky through a window and a lamp): Levenberg–Marquardt
/// from `base`'s lights with the background's cells as further linear unknowns, then judged
/// and, with `evaluate`, re-rendered (lights and background) like [`run_sphere_models`].
#[allow(clippy::too_many_arguments)]
pub fn run_with_background(
    renderer: &Renderer,
    truth_renderer: &Renderer,
    obs: &Observations,
    base: &SphereFit,
    rings: u32,
    truth: &[SphereLight],
    (center, size): (Vec3, f32),
    render: &RenderSettings,
    evaluate: bool,
    progress: &(dyn Fn(u64) + Sync),
) -> Result<SphereOutcome> {
    let t0 = Instant::now();
    let grid = RingGrid::new(rings);
    let obs = Observations {
        background: Some(&grid),
        ..*obs
    };
    // Only the directions are kept: without a background, the lights had grown to take in
    // the light from afar. The distance search places small lights again, background fitted.
    let directions: Vec<Vec3> = base
        .lights()
        .iter()
        .map(|l| (l.center - center).normalize())
        .collect();
    let settings = SphereSettings::new(directions.len(), render);
    let (start, searched) = spheres::initialise(
        renderer,
        &obs,
        &directions,
        (center, size),
        &settings.search,
    );
    let mut fit = refine_and_judge(renderer, &obs, &start, center, render)?;
    fit.renders += searched;
    fit.seconds = t0.elapsed().as_secs_f64();
    outcome_of(
        fit,
        truth_renderer,
        &obs,
        truth,
        center,
        render,
        evaluate,
        progress,
    )
}

/// The model held-out selection chose (fitted on three quarters of the pixels), fitted again
/// on all of them: the selection needs pixels the fits never saw, the estimate does not.
/// Levenberg–Marquardt from the chosen lights (and background), then judged and scored like
/// [`run_sphere_models`].
#[allow(clippy::too_many_arguments)]
pub fn refit_on_all_pixels(
    renderer: &Renderer,
    truth_renderer: &Renderer,
    obs: &Observations,
    chosen: &SphereFit,
    truth: &[SphereLight],
    center: Vec3,
    render: &RenderSettings,
    evaluate: bool,
    progress: &(dyn Fn(u64) + Sync),
) -> Result<SphereOutcome> {
    let t0 = Instant::now();
    let grid = chosen
        .background
        .as_ref()
        .map(|b| RingGrid::new(b.grid.rings()));
    let obs = Observations {
        holdout: false,
        background: grid.as_ref(),
        ..*obs
    };
    let fit = refine_and_judge(renderer, &obs, &chosen.lights(), center, render)?;
    let fit = SphereFit {
        requested: chosen.requested,
        start: chosen.start.clone(),
        iterations: chosen.iterations + fit.iterations,
        renders: chosen.renders + fit.renders,
        seconds: chosen.seconds + t0.elapsed().as_secs_f64(),
        ..fit
    };
    outcome_of(
        fit,
        truth_renderer,
        &obs,
        truth,
        center,
        render,
        evaluate,
        progress,
    )
}

/// Levenberg–Marquardt from `start` on `obs` (with its background's cells, if any), then each
/// light judged: the fit, with the iterations and renders of these two steps.
fn refine_and_judge(
    renderer: &Renderer,
    obs: &Observations,
    start: &[SphereLight],
    center: Vec3,
    render: &RenderSettings,
) -> Result<SphereFit> {
    let t0 = Instant::now();
    let settings = SphereSettings::new(start.len(), render);
    let refined = spheres::refine(renderer, obs, start, center, &settings.refine);
    let (fitted, judged) =
        spheres::judge(renderer, obs, &refined, center, &settings.refine.residual);
    let background = match obs.background {
        Some(g) => {
            Some(Envmap::new(g.rings(), refined.background.clone()).map_err(Error::Invalid)?)
        }
        None => None,
    };
    Ok(SphereFit {
        requested: start.len(),
        fitted,
        start: start.to_vec(),
        fit_rel_mae: refined.rel_mae,
        iterations: refined.iterations,
        renders: refined.evaluations + judged,
        history: refined.history,
        seconds: t0.elapsed().as_secs_f64(),
        background,
    })
}

/// A sphere-model fit with its figures: with `evaluate`, its lights (and background)
/// re-rendered with a seed the fit never saw, in the scene of `truth_renderer`, and its
/// errors; its recovery of `truth`.
#[allow(clippy::too_many_arguments)]
fn outcome_of(
    fit: SphereFit,
    truth_renderer: &Renderer,
    obs: &Observations,
    truth: &[SphereLight],
    center: Vec3,
    render: &RenderSettings,
    evaluate: bool,
    progress: &(dyn Fn(u64) + Sync),
) -> Result<SphereOutcome> {
    let lights = fit.lights();
    let t = Instant::now();
    let (mut renders, mut errors) = (Vec::new(), Vec::new());
    if evaluate {
        let l = Lights {
            spheres: lights.clone(),
            env: fit.background.clone(),
            alone: None,
        };
        renders = truth_renderer.with_lights(&l).render_views(
            obs.cameras,
            &evaluation_settings(render),
            progress,
        );
        errors = compare_views(&renders, obs.references, obs.evaluated)?;
    }
    let count = |masks: &[Vec<bool>]| masks.iter().flatten().filter(|&&k| k).count();
    Ok(SphereOutcome {
        fit_pixels: count(obs.masks),
        seen_pixels: count(obs.evaluated),
        recovery: recovery::recover_spheres(&lights, truth, center),
        fit,
        renders,
        errors,
        rerender_seconds: t.elapsed().as_secs_f64(),
    })
}

/// Chooses among light models fitted without the held-out pixels (the envmap with
/// [`FitSettings::holdout`], sphere models with [`Observations::holdout`]), by their
/// re-renders' error on the held-out pixels: the fewest parameters within one standard error
/// of the best. Sphere models are named `spheres:K` for the K lights asked of them
/// (`envmap+spheres:K` with a background, counting its cells too). None when nothing was
/// re-rendered.
pub fn select_model(
    envmap: Option<&Outcome>,
    spheres: &[SphereOutcome],
    references: &[Image],
    masks: &[Vec<bool>],
) -> Option<super::select::ModelSelection> {
    let mut candidates: Vec<_> = spheres
        .iter()
        .map(|so| (so, so.fit.requested))
        .filter(|(so, _)| !so.renders.is_empty())
        // K lights asked, fewer kept (merged, or contributing nothing): a smaller model's
        // duplicate, or worse.
        .filter(|(so, k)| so.fit.lights().len() == *k)
        .map(|(so, k)| {
            (
                so.fit.model_name(),
                7 * k
                    + so.fit
                        .background
                        .as_ref()
                        .map_or(0, |b| 3 * b.grid.cell_count()),
                held_out(&so.renders, references, masks),
                so.fit.seconds + so.rerender_seconds,
            )
        })
        .collect();
    if let Some(env) = envmap.filter(|e| !e.renders.is_empty()) {
        candidates.push((
            "envmap".into(),
            3 * env.fit.envmap.grid.cell_count(),
            held_out(&env.renders, references, masks),
            env.fit.transport_seconds + env.fit.solve_seconds + env.rerender_seconds,
        ));
    }
    super::select::choose_model(candidates)
}
