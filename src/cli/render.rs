//! `render-reference`: path-traced reference images of a scene under its lights.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;

use lightprobe::envmap::Envmap;
use lightprobe::estimate::job::Progress;
use lightprobe::estimate::pipeline::{twin_name, twin_name_taken};
use lightprobe::imageio::{self, Image};
use lightprobe::render::report::{
    EnvmapReport, ImageSize, LightReport, RenderReport, RenderTimings, ViewRender,
};
use lightprobe::render::{Lights, RenderSettings, Renderer, view_stream};
use lightprobe::scene::{Camera, sidecar};

use super::{Bars, SceneArgs, StrategyArg, check_memory, outln, prepare_out_dir};

/// A ring envmap file, or a lat-long image averaged into `rings` rings.
fn load_envmap(
    path: &std::path::Path,
    target: lightprobe::envmap::latlong::Target,
    rings: u32,
) -> anyhow::Result<Envmap> {
    let ext = lightprobe::imageio::extension(path);
    if ["png", "jpg", "jpeg", "tif", "tiff", "bmp"].contains(&ext.as_str()) {
        // 8- and 16-bit images clip the sky's bright parts: no radiance to light with.
        anyhow::bail!(
            "{}: is not an environment map lightprobe reads: give a ring envmap (.ron) or a lat-long OpenEXR (.exr) or Radiance (.hdr) image",
            path.display()
        );
    }
    if ext != "exr" && ext != "hdr" {
        return Ok(Envmap::load(path)?);
    }
    anyhow::ensure!(
        (1..=lightprobe::envmap::MAX_RINGS).contains(&rings),
        "--envmap-rings must be between 1 and {}, got {rings}",
        lightprobe::envmap::MAX_RINGS
    );
    let img = lightprobe::imageio::read_latlong(path)?;
    Ok(lightprobe::envmap::latlong::import(&img, target, rings)
        .map_err(|m| lightprobe::Error::file(path, m))?)
}

#[derive(clap::Args)]
pub struct Args {
    #[command(flatten)]
    scene: SceneArgs,
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
    /// Also light the scene with this environment map (escaping rays see it): a ring envmap
    /// (envmap.ron), or a lat-long OpenEXR or Radiance .hdr in --envmap-target's convention,
    /// averaged into --envmap-rings rings (as import-envmap does).
    #[arg(long)]
    envmap: Option<PathBuf>,
    /// Whose lat-long convention an --envmap image follows (Blender's for a map Blender uses
    /// as its World).
    #[arg(long, value_enum, default_value_t = super::TargetArg::Mitsuba, requires = "envmap")]
    envmap_target: super::TargetArg,
    /// Rings an --envmap image is averaged into (1..=1000; 64 rings are cells of about 3°).
    #[arg(long, default_value_t = 64, requires = "envmap")]
    envmap_rings: u32,
    /// Leave out the scene's sphere and point lights (e.g. to light with --envmap alone).
    #[arg(long)]
    no_sphere_lights: bool,
    /// Also write `<view>_b.exr`, a twin: the same render with other random numbers. Beside
    /// the references, twins let `estimate --reference` measure their noise exactly.
    #[arg(long)]
    twin: bool,
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

pub fn run(a: Args) -> anyhow::Result<()> {
    let t_load = Instant::now();
    let scene = a.scene.load()?;
    let mut settings = RenderSettings::from_scene(&scene.settings);
    if let Some(spp) = a.spp {
        settings.spp = spp;
    }
    if let Some(b) = a.max_bounces {
        anyhow::ensure!(
            (1..=sidecar::MAX_BOUNCES).contains(&b),
            "--max-bounces must be between 1 and {}",
            sidecar::MAX_BOUNCES
        );
        settings.max_bounces = b;
    }
    if let Some(seed) = a.seed {
        settings.seed = seed;
    }
    settings.strategy = a.strategy.into();
    settings.hide_emitters = !a.show_emitters;
    let mut lights = Lights::new(if a.no_sphere_lights {
        Vec::new()
    } else {
        scene.lights.clone()
    });
    if let Some(p) = &a.envmap {
        lights.env = Some(load_envmap(p, a.envmap_target.into(), a.envmap_rings)?);
    }
    anyhow::ensure!(
        !(settings.strategy == lightprobe::render::Strategy::BsdfOnly
            && lights.spheres.iter().any(|l| l.is_point())),
        "{}: has point lights, which only light sampling reaches: use --strategy mis or light-only",
        a.scene.scene.display()
    );
    anyhow::ensure!(
        !lights.is_empty(),
        "{}: nothing lights the scene (no sphere or point lights and no --envmap)",
        a.scene.scene.display()
    );
    // One view at a time: its image (RGB + coverage), the per-tile results and the encoder.
    let (w, h) = scene
        .cameras
        .iter()
        .map(|c| (c.width, c.height))
        .max_by_key(|&(w, h)| w as u64 * h as u64)
        .unwrap_or((1, 1));
    check_memory(w as u64 * h as u64 * 40, || format!("{w}×{h} images"), "")?;
    let views: Vec<&Camera> = scene.cameras.iter().collect();
    let taken = |cam: &Camera| twin_name_taken(cam, &views, &scene.camera_names);
    if a.twin
        && let Some(cam) = views.iter().find(|c| taken(c))
    {
        anyhow::bail!(
            "{}: --twin would write view {:?}'s twin as {}.exr, but {:?} is a camera of the scene (rename that camera)",
            a.scene.scene.display(),
            cam.name,
            twin_name(cam),
            twin_name(cam)
        );
    }
    let _lock = prepare_out_dir(&a.out, lightprobe::output::LOCK_FILE)?;
    // A twin left by an earlier run with --twin would pair with these references although
    // it shows other lighting or noise: removed (never another camera's reference).
    if !a.twin {
        for cam in views.iter().filter(|c| !taken(c)) {
            let stale = a.out.join(format!("{}.exr", twin_name(cam)));
            if stale.is_file() {
                std::fs::remove_file(&stale).map_err(|e| lightprobe::Error::io(&stale, e))?;
            }
        }
    }
    let load_seconds = t_load.elapsed().as_secs_f64();

    let t_bvh = Instant::now();
    let renderer = Renderer::new(&scene, &lights);
    let bvh_seconds = t_bvh.elapsed().as_secs_f64();

    let renders = if a.twin { 2 } else { 1 };
    let bars = Bars::single(a.quiet, "rendering", renders * scene.pixel_count());
    let mut views = Vec::new();
    let t_all = Instant::now();
    for cam in &scene.cameras {
        views.push(render_view(&renderer, cam, &settings, &a, &bars)?);
    }
    bars.finish();
    let render_seconds = t_all.elapsed().as_secs_f64();
    // Every render counted, the twins too: the rate is of the time they all took.
    let total_samples = (renders * scene.pixel_count()) as f64 * settings.spp as f64;
    let report = RenderReport {
        lightprobe_version: lightprobe::VERSION.to_string(),
        scene: a.scene.scene.clone(),
        triangles: scene.mesh.triangle_count(),
        image: scene
            .common_size()
            .map(|(width, height)| ImageSize { width, height }),
        lights: lights
            .spheres
            .iter()
            .map(|l| LightReport {
                center: l.center.to_array(),
                radius: l.radius,
                radiance: l.radiance.to_array(),
            })
            .collect(),
        envmap: a
            .envmap
            .as_ref()
            .zip(lights.env.as_ref())
            .map(|(p, e)| EnvmapReport {
                file: p.clone(),
                rings: e.grid.rings(),
            }),
        settings,
        threads: rayon::current_num_threads(),
        kernels: renderer.accel.isa(),
        timings: RenderTimings {
            load_seconds,
            bvh_seconds,
            render_seconds,
        },
        samples_per_second: total_samples / render_seconds,
        views,
    };
    let text = serde_json::to_string_pretty(&report).context("render.json")? + "\n";
    imageio::write_bytes(&a.out.join("render.json"), text.as_bytes())?;
    if a.json {
        super::print(&text)?;
        return Ok(());
    }
    for v in &report.views {
        outln!(
            "{:<12} {}  mean {:.4?}  coverage {:.0}%  {:.2} s",
            v.view,
            v.exr.display(),
            v.mean_rgb,
            100.0 * v.coverage,
            v.seconds,
        )?;
    }
    outln!(
        "{} triangles, {} spp, {} bounces: {:.2} s, {:.2} M samples/s on {} threads",
        report.triangles,
        settings.spp,
        settings.max_bounces,
        render_seconds,
        report.samples_per_second / 1e6,
        report.threads
    )?;
    Ok(())
}

/// A twin's seed: the references' seed with these bits flipped, far from the small offsets an
/// estimate gives its own renders.
const TWIN_SEED: u64 = 0x7477_696e_5f62_0000;

/// Renders one view and writes its EXR, PNG preview and geometry buffers into `--out`.
fn render_view(
    renderer: &Renderer,
    cam: &Camera,
    settings: &RenderSettings,
    a: &Args,
    bars: &Bars,
) -> anyhow::Result<ViewRender> {
    let t = Instant::now();
    let img = renderer.render_radiance(cam, view_stream(cam), settings, &|n| bars.advance(n));
    let seconds = t.elapsed().as_secs_f64();
    anyhow::ensure!(
        img.rgb.iter().all(|c| c.is_finite()),
        "view {:?}: the render produced non-finite pixels from {} (its lights or materials \
         overflow; a bug if every value in it is moderate)",
        cam.name,
        a.scene.scene.display()
    );
    let file = |suffix: &str| a.out.join(format!("{}.{suffix}", cam.name));
    let (exr, png) = (file("exr"), file("png"));
    imageio::write_exr(&exr, &img)?;
    imageio::write_png(&png, &img, imageio::auto_exposure(&img))?;
    let twin = if a.twin {
        let other = RenderSettings {
            seed: settings.seed ^ TWIN_SEED,
            ..*settings
        };
        let img = renderer.render_radiance(cam, view_stream(cam), &other, &|n| bars.advance(n));
        anyhow::ensure!(
            img.rgb.iter().all(|c| c.is_finite()),
            "view {:?}: its twin render produced non-finite pixels from {}",
            cam.name,
            a.scene.scene.display()
        );
        let path = a.out.join(format!("{}.exr", twin_name(cam)));
        imageio::write_exr(&path, &img)?;
        Some(path)
    } else {
        None
    };
    let mut aov = BTreeMap::new();
    if !a.aov.is_empty() {
        let aovs = renderer.aovs(cam);
        for name in &a.aov {
            let image: &Image = match name.as_str() {
                "depth" => &aovs.depth,
                "normal" => &aovs.normal,
                _ => &aovs.albedo,
            };
            let path = file(&format!("{name}.exr"));
            imageio::write_exr(&path, image)?;
            aov.insert(name.clone(), path);
        }
    }
    let coverage = img.alpha.as_ref().map_or(1.0, |al| {
        al.iter().map(|&v| v as f64).sum::<f64>() / al.len() as f64
    });
    Ok(ViewRender {
        view: cam.name.clone(),
        width: cam.width,
        height: cam.height,
        exr,
        png,
        twin,
        aov,
        mean_rgb: img.mean().to_array(),
        coverage,
        seconds,
        samples_per_second: (cam.width * cam.height) as f64 * settings.spp as f64 / seconds,
    })
}
