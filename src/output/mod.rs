//! Writing an estimate's files: every file of an output folder is written here, each whole
//! or not at all ([`imageio::write_atomic`]).
//!
//! ```text
//! OUT/report.json            the EstimateReport (schemas/report.schema.json)
//! OUT/index.html             the results page: views, error maps, the envmap and its lights,
//!                             key figures, model selection (figures/ holds its own pictures)
//! OUT/envmap.ron, .exr        the ring envmap, and its lat-long EXR (Mitsuba's convention)
//! OUT/reference/<view>.exr    references rendered from the scene's lights (none when given)
//! OUT/estimate/<view>.exr     the envmap's re-render, a PNG preview and an error heat map
//! OUT/scene.glb (or .gltf)   the scene's glTF with the envmap named in its scene's extras
//! OUT/spheres/lights.ron      the sphere-light model as a sidecar fragment, its re-renders,
//!                             and background.ron/.exr when an envmap is behind the lights
//! OUT/spheres/scene.glb       the scene's glTF with the sphere lights as KHR point lights
//! OUT/lights.usda, spheres/lights.usda
//!                             USD stages of the lights: a DomeLight of <envmap>_usd.exr
//!                             (OpenEXR's lat-long convention), SphereLights
//! OUT/mitsuba/scene.xml, spheres/mitsuba/scene.xml
//!                             Mitsuba 3 scenes of the estimate (meshes as PLY, textures,
//!                             envmap.exr): `mitsuba scene.xml` renders the views
//! OUT/blender.py, spheres/blender.py
//!                             Blender scripts that import scene.glb, set the World and
//!                             the lights and render the views with Cycles
//! ```

use std::path::{Path, PathBuf};

use crate::envmap::Envmap;
use crate::envmap::latlong::{self, Filter, Target};
use crate::error::{Error, Result};
use crate::estimate::job::{Estimate, EstimateReport};
use crate::estimate::pipeline::{SeenViews, SphereOutcome};
use crate::imageio::{self, Image};
use crate::scene::{Scene, export};

pub mod figure;
pub mod page;

/// Width of the lat-long EXR written beside each envmap: renderers interpolate between pixels,
/// which blurs a cell's edges by half a pixel (measured in Mitsuba: the worst cell of 9 rings
/// loses 0.7% of its power at 4096 pixels, 2.7% at 1024).
pub const LATLONG_WIDTH: u32 = 4096;

/// Writes every file of an estimate into `dir`, which must exist, the scene's glTF
/// (`gltf`, none for scenes built in code) among them; `rendered_references` when the
/// references were rendered here (not given). The report, written last, gets
/// `timings.total_seconds` from `started` (the whole command, its other files included).
/// Files are written when the estimate is complete: a run that fails or is stopped before
/// leaves none of them.
pub fn write_estimate(
    dir: &Path,
    scene: Option<&Scene>,
    estimate: &mut Estimate,
    seen: &SeenViews,
    rendered_references: bool,
    started: std::time::Instant,
) -> Result<Vec<String>> {
    if rendered_references {
        let refs = dir.join("reference");
        create_dir(&refs)?;
        let seen_views = seen.views.iter().map(|c| c.name.as_str());
        let names = seen_views.chain(seen.blind.iter().map(String::as_str));
        let images = seen.references.iter().chain(&seen.blind_references);
        for (img, name) in images.zip(names) {
            imageio::write_exr(&refs.join(format!("{name}.exr")), img)?;
        }
    }
    // Error images compare with what the lighting explains: each reference over its exposure.
    let scaled;
    let seen = match &estimate.report.exposure {
        Some(e) => {
            let exposures: Vec<f64> = e.relative.iter().map(|v| v.exposure).collect();
            scaled = seen.with_exposures(&exposures);
            &scaled
        }
        None => seen,
    };
    let names: Vec<&str> = seen
        .views
        .iter()
        .map(|c| c.name.as_str())
        .chain(seen.blind.iter().map(String::as_str))
        .collect();
    remove_stale(dir, &names, estimate.spheres.is_some(), rendered_references)?;
    let env = &estimate.envmap.fit.envmap;
    let render = estimate.report.settings;
    let mut notes = Vec::new();
    write_envmap(dir, "envmap", env)?;
    if let Some(scene) = scene {
        let note = envmap_note("envmap", env);
        notes.extend(write_scene(
            dir,
            scene,
            estimate.materials.as_deref(),
            &[],
            &[],
            Some(env),
            Some(&note),
            &render,
        )?);
    }
    write_usd(dir, &[], &[], Some(("envmap", env)))?;
    if !estimate.envmap.renders.is_empty() {
        write_renders(
            &dir.join("estimate"),
            "envmap",
            &estimate.envmap.renders,
            seen,
        )?;
    }
    if let Some(so) = &estimate.spheres {
        let spheres = dir.join("spheres");
        write_spheres(&spheres, so, seen)?;
        let (lights, doubts) = (so.fit.lights(), so.fit.radius_doubts());
        let background = so.fit.background.as_ref();
        if let Some(scene) = scene {
            let note = background.map(|bg| envmap_note("background", bg));
            notes.extend(write_scene(
                &spheres,
                scene,
                estimate.materials.as_deref(),
                &lights,
                &doubts,
                background,
                note.as_ref(),
                &render,
            )?);
        }
        write_usd(
            &spheres,
            &lights,
            &doubts,
            background.map(|bg| ("background", bg)),
        )?;
    }
    estimate.report.timings.total_seconds = started.elapsed().as_secs_f64();
    // The page reads report.json's own text, so that it shows the numbers as written there
    // (f32 figures at their shortest, not widened).
    let json = report_json(&estimate.report)
        .and_then(|t| serde_json::from_str(&t).map_err(|e| e.to_string()))
        .map_err(|e| Error::file(dir.join("report.json"), e))?;
    page::write(dir, &json, estimate, seen, scene, rendered_references)?;
    write_report(dir, &estimate.report)?;
    notes.dedup();
    Ok(notes)
}

/// Removes what an earlier estimate wrote into `dir` that this one (of `views`, with or
/// without a sphere model) will not write again, so that the folder never mixes two runs:
/// the images of views not in this run, the exports' folders (rewritten whole), and the
/// sphere model's files when this run has none. Only lightprobe's own names are touched:
/// anything else there (a user's renders) stays; `reference/` only when this run renders its
/// references into it (otherwise it may be the references given).
fn remove_stale(dir: &Path, views: &[&str], spheres: bool, references: bool) -> Result<()> {
    let remove_file = |p: &Path| match std::fs::remove_file(p) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(Error::io(p, e)),
        _ => Ok(()),
    };
    let remove_dir = |p: &Path| match std::fs::remove_dir_all(p) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(Error::io(p, e)),
        _ => Ok(()),
    };
    // A view's images: <view>.exr, .png, .error.png.
    let view_of = |file: &str| {
        file.strip_suffix(".error.png")
            .or_else(|| file.strip_suffix(".png"))
            .or_else(|| file.strip_suffix(".exr"))
            .map(str::to_string)
    };
    let stale_views = |folder: &Path, keep: &[&str]| -> Result<()> {
        let Ok(entries) = std::fs::read_dir(folder) else {
            return Ok(());
        };
        for entry in entries.flatten() {
            let name = entry.file_name().to_string_lossy().into_owned();
            if entry.path().is_file()
                && let Some(view) = view_of(&name)
                && !keep.contains(&view.as_str())
            {
                remove_file(&entry.path())?;
            }
        }
        Ok(())
    };
    stale_views(&dir.join("estimate"), views)?;
    if references {
        stale_views(&dir.join("reference"), views)?;
    }
    let spheres_dir = dir.join("spheres");
    remove_dir(&dir.join("figures"))?;
    for d in [dir, spheres_dir.as_path()] {
        remove_dir(&d.join("mitsuba"))?;
        remove_dir(&d.join("blender_textures"))?;
        remove_dir(&d.join("albedo_textures"))?;
    }
    if spheres {
        stale_views(&spheres_dir, views)?;
    } else if spheres_dir.is_dir() {
        stale_views(&spheres_dir, &[])?;
        for f in [
            "lights.ron",
            "background.ron",
            "background.exr",
            "background_usd.exr",
            "lights.usda",
            "scene.glb",
            "scene.gltf",
            "blender.py",
            "envmap_blender.exr",
        ] {
            remove_file(&spheres_dir.join(f))?;
        }
        // Gone if nothing of the user's is left in it.
        let _ = std::fs::remove_dir(&spheres_dir);
    }
    Ok(())
}

/// The scene with `lights` and `envmap` written into `dir` for other tools: its glTF, a
/// Mitsuba scene (`mitsuba/`) and a Blender script, with the fitted `albedo` (the scene's
/// materials) where given. Returns what the exports leave out.
#[allow(clippy::too_many_arguments)]
fn write_scene(
    dir: &Path,
    scene: &Scene,
    albedo: Option<&[crate::scene::Material]>,
    lights: &[crate::scene::SphereLight],
    doubts: export::RadiusDoubts,
    envmap: Option<&Envmap>,
    note: Option<&export::EnvmapNote>,
    render: &crate::render::RenderSettings,
) -> Result<Vec<String>> {
    let given = &scene.materials;
    let fitted = albedo.map(|m| Scene {
        materials: m.to_vec(),
        ..scene.clone()
    });
    let (gltf, mut notes) = export::write_with_lights(
        &scene.gltf,
        dir,
        lights,
        doubts,
        note,
        albedo.map(|m| (&given[..], m)),
    )?;
    let scene = fitted.as_ref().unwrap_or(scene);
    let name = gltf
        .file_name()
        .and_then(|n| n.to_str())
        .unwrap_or("scene.glb");
    export::blender::write(dir, name, scene, envmap, render.spp, render.max_bounces)?;
    notes.extend(export::mitsuba::write(
        &dir.join("mitsuba"),
        scene,
        lights,
        doubts,
        envmap,
        export::mitsuba::Render {
            spp: render.spp,
            max_bounces: render.max_bounces,
        },
    )?);
    Ok(notes)
}

/// `lights.usda` in `dir`: the lights, and a dome of the envmap `(name, env)` written beside it
/// as `<name>_usd.exr` in OpenEXR's lat-long convention, which USD's DomeLight adopts.
fn write_usd(
    dir: &Path,
    lights: &[crate::scene::SphereLight],
    doubts: export::RadiusDoubts,
    dome: Option<(&str, &Envmap)>,
) -> Result<()> {
    let file = dome.map(|(name, _)| format!("{name}_usd.exr"));
    if let (Some((_, env)), Some(file)) = (dome, &file) {
        imageio::write_latlong_exr(
            &dir.join(file),
            &latlong::export(env, Target::Usd, Filter::Box, LATLONG_WIDTH),
        )?;
    }
    let text = export::usda(lights, doubts, file.as_deref());
    imageio::write_bytes(&dir.join("lights.usda"), text.as_bytes())
}

/// How an export names the envmap written as `<name>.ron` and `.exr` beside it.
fn envmap_note(name: &str, env: &Envmap) -> export::EnvmapNote {
    export::EnvmapNote {
        exr: format!("{name}.exr"),
        ron: format!("{name}.ron"),
        rings: env.grid.rings(),
    }
}

/// `report.json`, pretty-printed; returns its text.
pub fn write_report(dir: &Path, report: &EstimateReport) -> Result<String> {
    let text = report_json(report).map_err(|e| Error::file(dir.join("report.json"), e))?;
    imageio::write_bytes(&dir.join("report.json"), text.as_bytes())?;
    Ok(text)
}

/// The report as pretty-printed JSON with a final newline (an error for a path that is not
/// UTF-8, which JSON cannot hold).
pub fn report_json(report: &EstimateReport) -> std::result::Result<String, String> {
    serde_json::to_string_pretty(report)
        .map(|t| t + "\n")
        .map_err(|e| format!("cannot write the report: {e}"))
}

/// Writes `NAME.ron` and its lat-long `NAME.exr` (Mitsuba's convention) into `dir`.
pub fn write_envmap(dir: &Path, name: &str, env: &Envmap) -> Result<()> {
    env.save(&dir.join(format!("{name}.ron")))?;
    imageio::write_latlong_exr(
        &dir.join(format!("{name}.exr")),
        &latlong::export(env, Target::Mitsuba, Filter::Box, LATLONG_WIDTH),
    )
}

/// Writes the re-renders of `model` into `dir`: per view the EXR, a PNG preview exposed like
/// its reference, and the signed-error heat map against it ([`figure::write_error_map`]), all
/// views on one colour scale.
pub fn write_renders(dir: &Path, model: &str, renders: &[Image], seen: &SeenViews) -> Result<()> {
    create_dir(dir)?;
    let views = || {
        renders
            .iter()
            .zip(&seen.views)
            .zip(&seen.references)
            .zip(&seen.masks)
    };
    // One view's error map at a time: first for the shared scale, then drawn.
    let scale = figure::shared_scale(
        views().map(|(((img, _), reference), mask)| figure::signed_error(img, reference, mask)),
    );
    for (((img, cam), reference), mask) in views() {
        imageio::write_exr(&dir.join(format!("{}.exr", cam.name)), img)?;
        imageio::write_png(
            &dir.join(format!("{}.png", cam.name)),
            img,
            imageio::auto_exposure(reference),
        )?;
        figure::write_error_map(
            &dir.join(format!("{}.error.png", cam.name)),
            &format!("{model}, {}: estimate − reference", cam.name),
            (img.width, img.height),
            &figure::signed_error(img, reference, mask),
            scale,
        )?;
    }
    Ok(())
}

/// Writes a sphere-model estimate into `dir`: the sidecar fragment, the re-renders, and the
/// envmap behind the lights if any.
pub fn write_spheres(dir: &Path, so: &SphereOutcome, seen: &SeenViews) -> Result<()> {
    write_renders(dir, &so.fit.model_name(), &so.renders, seen)?;
    imageio::write_bytes(&dir.join("lights.ron"), so.fit.fragment().as_bytes())?;
    if let Some(bg) = &so.fit.background {
        write_envmap(dir, "background", bg)?;
    }
    Ok(())
}

/// The name of the lock file [`prepare_dir`] holds in an output folder.
pub const LOCK_FILE: &str = ".lightprobe.lock";

/// An output folder held by this process: an advisory lock (`flock`) on a file in it that
/// holds the process id, so that a second run can say who holds the folder. The operating
/// system releases the lock when the process ends, however it ends; the file is removed when
/// the run ends normally or is interrupted.
#[derive(Debug)]
pub struct DirLock {
    path: PathBuf,
    file: std::fs::File,
    /// The folder, if this run created it: removed again if the run leaves it empty.
    created: Option<PathBuf>,
}

impl Drop for DirLock {
    fn drop(&mut self) {
        // Removed while still locked: a run that opened the file meanwhile finds, once it
        // gets the lock, that the name no longer leads to it, and starts over.
        let _ = std::fs::remove_file(&self.path);
        crate::cleanup::unregister(&self.path);
        if let Some(dir) = &self.created {
            let _ = std::fs::remove_dir(dir);
            crate::cleanup::unregister(dir);
        }
    }
}

/// Creates the output folder `dir`, proves it writable, locks it for this run (`lock_name`,
/// a file in it; see [`DirLock`]) and removes the temporaries that runs which died left in it.
/// A folder another live run holds is refused, naming that run's process.
pub fn prepare_dir(dir: &Path, lock_name: &str) -> Result<DirLock> {
    if dir.exists() && !dir.is_dir() {
        return Err(Error::file(dir, "exists and is not a folder"));
    }
    let created = (!dir.exists()).then(|| dir.to_path_buf());
    create_dir(dir)?;
    if let Some(dir) = &created {
        crate::cleanup::register(dir);
    }
    let path = dir.join(lock_name);
    if let Ok(meta) = std::fs::symlink_metadata(&path)
        && !meta.is_file()
    {
        return Err(Error::file(
            &path,
            "is not a regular file (a link or a folder); remove it to use this output folder",
        ));
    }
    let not_writable =
        |e: std::io::Error| Error::file(dir, format!("output folder is not writable: {e}"));
    let file = loop {
        let mut file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .map_err(not_writable)?;
        match file.try_lock() {
            Ok(()) => {}
            Err(std::fs::TryLockError::WouldBlock) => {
                let mut holder = String::new();
                let _ = std::io::Read::read_to_string(&mut file, &mut holder);
                let who = match holder.trim() {
                    "" => "another lightprobe run".to_string(),
                    pid => format!("another lightprobe run (process {pid})"),
                };
                return Err(Error::file(
                    dir,
                    format!("is in use by {who}; wait for it to end or write elsewhere"),
                ));
            }
            // Filesystems without locks (some network mounts): run unlocked.
            Err(std::fs::TryLockError::Error(e)) if e.kind() == std::io::ErrorKind::Unsupported => {
                break file;
            }
            Err(std::fs::TryLockError::Error(e)) => return Err(Error::io(&path, e)),
        }
        if same_file(&file, &path) {
            break file;
        }
        // The holder removed the file as we opened it: lock the new one.
    };
    crate::cleanup::register(&path);
    // From here on, dropping the lock removes the file, also on the error below.
    let mut lock = DirLock {
        path,
        file,
        created,
    };
    lock.file
        .set_len(0)
        .and_then(|()| {
            std::io::Write::write_all(
                &mut lock.file,
                format!("{}\n", std::process::id()).as_bytes(),
            )
        })
        .map_err(not_writable)?;
    crate::cleanup::remove_stale(dir, 2);
    Ok(lock)
}

/// Whether `path` still names the open `file` (not a file created after it was removed).
fn same_file(file: &std::fs::File, path: &Path) -> bool {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        match (file.metadata(), std::fs::metadata(path)) {
            (Ok(a), Ok(b)) => a.dev() == b.dev() && a.ino() == b.ino(),
            _ => false,
        }
    }
    #[cfg(not(unix))]
    {
        let _ = (file, path);
        true
    }
}

fn create_dir(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))
}
