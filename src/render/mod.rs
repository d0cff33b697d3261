//! Rendering: the tile loop, written once, over the one path tracer ([`integrator`]), generic
//! over what it accumulates ([`Accumulator`]): radiance for images, or later derivatives with
//! respect to each emitter.
//!
//! Determinism: every camera sample draws from a stream keyed by (seed, stream, pixel, sample
//! index), and tiles are fixed, so an image is bit-identical whatever the thread count.
//!
//! ```no_run
//! use lightprobe::{render::{Renderer, RenderSettings, Lights}, scene::Scene};
//! let scene = Scene::load(std::path::Path::new("scenes/tabletop/tabletop.ron"))?;
//! let lights = Lights::new(scene.lights.clone());
//! let renderer = Renderer::new(&scene, &lights);
//! let image = renderer.render_radiance(&scene.cameras[0], 0, &RenderSettings::from_scene(&scene.settings), &|_| {});
//! # Ok::<(), lightprobe::Error>(())
//! ```

mod integrator;
pub mod lights;
mod pixels;
pub mod report;

use glam::{Vec2, Vec3};
use rayon::prelude::*;
use serde::Serialize;

pub use lights::{Emitter, LightSample, Lights};

use crate::accel::Accel;
use crate::imageio::Image;
use crate::sampling::mix64;
use crate::scene::{Camera, Scene, SceneSettings};
use integrator::{FirstHit, Tracer};
use pixels::{Light, TilePaths, Trace, View, Walk, drive, render_key};

pub use pixels::{Done, TILE, Tile, tiles};

/// Which light-transport estimator to use at each surface vertex.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, schemars::JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum Strategy {
    /// Emitter sampling and BSDF sampling combined by the power heuristic (default).
    Mis,
    /// Emitter sampling only (emitters hit by BSDF rays count nothing).
    LightOnly,
    /// BSDF sampling only (no shadow rays).
    BsdfOnly,
}

/// Monte Carlo settings of one render.
#[derive(Debug, Clone, Copy, Serialize, schemars::JsonSchema)]
pub struct RenderSettings {
    /// Camera samples per pixel.
    pub spp: u32,
    /// Scattering events per path: 1 = direct light only.
    pub max_bounces: u32,
    /// Seed of every random stream.
    pub seed: u64,
    pub strategy: Strategy,
    /// Emitters seen directly by the camera render black (they still occlude), like
    /// Mitsuba's `hide_emitters`.
    pub hide_emitters: bool,
    /// Camera rays meet sphere lights (seen, or black with `hide_emitters`, hiding what is
    /// behind them). Off in the sphere fit's renders: a trial light crossing a view would
    /// black out what the view sees there, a wall between a start and the light's true place
    /// (a scan's lamp beside a camera: the error rose fivefold on the way to it). What a fit
    /// gives up is small: a rendered reference leaves out the pixels a light covers whole
    /// (alpha 0), a photograph's lamp is mostly saturated (left out).
    pub camera_sees_lights: bool,
    /// Next-event estimation samples every light at every vertex (a shadow ray each) instead
    /// of picking one. Picking costs little when one light dominates, but tosses a coin
    /// between lights of similar weight, and its variance is of the order of the signal: the
    /// sphere model's per-light transports, rendered at unit radiance, need every light.
    pub every_light: bool,
}

impl RenderSettings {
    /// The sidecar's settings, with MIS and hidden emitters.
    pub fn from_scene(s: &SceneSettings) -> Self {
        RenderSettings {
            spp: s.spp,
            max_bounces: s.max_bounces,
            seed: s.seed,
            strategy: Strategy::Mis,
            hide_emitters: true,
            camera_sees_lights: true,
            every_light: false,
        }
    }

    /// A quick, noisy preset for looking at a scene.
    pub fn preview() -> Self {
        RenderSettings {
            spp: 16,
            max_bounces: 2,
            seed: 1,
            strategy: Strategy::Mis,
            hide_emitters: true,
            camera_sees_lights: true,
            every_light: false,
        }
    }
}

/// What the tracer accumulates per pixel. A path hands over each emitter it reaches, the unit
/// direction (world space) in which it reached it, and a weight per unit of that emitter's
/// radiance (throughput × MIS weight / pdf).
pub trait Accumulator: Sync {
    type Pixel: Send;
    fn new_pixel(&self) -> Self::Pixel;
    fn add(&self, pixel: &mut Self::Pixel, emitter: Emitter, dir: Vec3, weight: Vec3);
    /// Turns the sum over `spp` samples into the pixel's estimate.
    fn finish(&self, pixel: &mut Self::Pixel, spp: u32);
    /// What a render gives a pixel it was not asked for (its `wanted` filter): by default the
    /// empty estimate.
    fn left_out(&self) -> Self::Pixel {
        let mut px = self.new_pixel();
        self.finish(&mut px, 1);
        px
    }
}

/// Accumulates radiance: weight × the emitter's radiance, averaged over samples.
pub struct RadianceAccumulator<'a>(pub &'a Lights);

impl Accumulator for RadianceAccumulator<'_> {
    type Pixel = Vec3;
    fn new_pixel(&self) -> Vec3 {
        Vec3::ZERO
    }
    #[inline]
    fn add(&self, pixel: &mut Vec3, emitter: Emitter, _: Vec3, weight: Vec3) {
        *pixel += weight * self.0.radiance(emitter);
    }
    fn finish(&self, pixel: &mut Vec3, spp: u32) {
        *pixel /= spp as f32;
    }
}

/// One accumulated image: a pixel per position, row-major, row 0 at the top, and the fraction
/// of camera samples that saw scene geometry (the mask of every error metric).
pub struct Frame<P> {
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<P>,
    pub coverage: Vec<f32>,
}

impl Frame<Vec3> {
    /// A radiance frame as an image; the coverage becomes its alpha.
    pub fn into_image(self) -> Image {
        Image {
            width: self.width,
            height: self.height,
            rgb: self.pixels,
            alpha: Some(self.coverage),
        }
    }
}

/// Geometry buffers at pixel centres, for checking against other tools.
pub struct Aovs {
    /// Distance from the camera to the first hit, metres (0 where the ray sees no geometry).
    pub depth: Image,
    /// Shading normal facing the camera, world space (0 where none).
    pub normal: Image,
    /// Albedo, linear RGB (0 where none).
    pub albedo: Image,
    /// glTF texture coordinates, row-major (NaN where none).
    pub uv: Vec<Vec2>,
}

/// Builds the ray-query structure over a scene's triangles.
pub fn build_accel(scene: &Scene) -> Accel {
    let tris: Vec<[Vec3; 3]> = (0..scene.mesh.triangle_count())
        .map(|t| scene.mesh.corners(t))
        .collect();
    Accel::build(&tris)
}

/// A scene, its BVH and a set of lights, ready to render from any camera.
pub struct Renderer<'a> {
    pub scene: &'a Scene,
    pub lights: &'a Lights,
    /// Shared, so the same scene can be rendered under other lights without a rebuild.
    pub accel: std::sync::Arc<Accel>,
}

impl<'a> Renderer<'a> {
    /// Builds the BVH.
    pub fn new(scene: &'a Scene, lights: &'a Lights) -> Self {
        Renderer {
            scene,
            lights,
            accel: std::sync::Arc::new(build_accel(scene)),
        }
    }

    /// The same scene and BVH under other lights.
    pub fn with_lights<'b>(&self, lights: &'b Lights) -> Renderer<'b>
    where
        'a: 'b,
    {
        Renderer {
            scene: self.scene,
            lights,
            accel: self.accel.clone(),
        }
    }

    /// The same BVH over `scene`, which must have this renderer's geometry (e.g. the scene with
    /// other albedos), lit by `lights`.
    pub fn with_scene<'b>(&self, scene: &'b Scene, lights: &'b Lights) -> Renderer<'b>
    where
        'a: 'b,
    {
        debug_assert_eq!(
            scene.mesh.triangle_count(),
            self.scene.mesh.triangle_count()
        );
        Renderer {
            scene,
            lights,
            accel: self.accel.clone(),
        }
    }

    /// What every tile of a render of `camera` shares.
    fn view<'v, R: Fn(f32, f32) -> Vec3>(
        &self,
        camera: &'v Camera,
        settings: &'v RenderSettings,
        stream: u64,
        ray_dir: &'v R,
    ) -> View<'v, R> {
        View {
            camera,
            key: render_key(settings, stream),
            ray_dir,
            settings,
            isa: self.accel.isa(),
            wanted: None,
        }
    }

    fn tracer<'s>(&'s self, settings: &'s RenderSettings) -> Tracer<'s> {
        Tracer {
            scene: self.scene,
            accel: &self.accel,
            lights: self.lights,
            settings,
        }
    }

    /// Renders `camera` with `acc`. `stream` separates the random streams of renders that
    /// share a seed (e.g. [`view_stream`]). `progress` is called with the pixels of each
    /// finished tile.
    pub fn render<A: Accumulator>(
        &self,
        camera: &Camera,
        stream: u64,
        settings: &RenderSettings,
        acc: &A,
        progress: &(dyn Fn(u64) + Sync),
    ) -> Frame<A::Pixel> {
        self.render_some(camera, stream, settings, acc, None, progress)
    }

    /// [`Renderer::render`], of only the pixels `wanted` flags (by index) if given: the others
    /// get the accumulator's `left_out` pixel and coverage 0, the flagged ones what `render` gives
    /// them. `progress` counts every pixel of a finished tile, flagged or not.
    pub fn render_some<A: Accumulator>(
        &self,
        camera: &Camera,
        stream: u64,
        settings: &RenderSettings,
        acc: &A,
        wanted: Option<&(dyn Fn(u32) -> bool + Sync)>,
        progress: &(dyn Fn(u64) + Sync),
    ) -> Frame<A::Pixel> {
        let done: Vec<Vec<Done<A::Pixel>>> = tiles(camera.width, camera.height)
            .par_iter()
            .map(|&tile| {
                let pixels = self.render_tile(camera, stream, settings, acc, tile, wanted);
                progress(pixels.len() as u64);
                pixels
            })
            .collect();
        assemble(camera.width, camera.height, done)
    }

    /// Renders one tile of `camera` (one of [`tiles`]) on this thread: its pixels in visiting
    /// order, each as [`Renderer::render`] computes it (a pixel's random streams depend on its
    /// index, not on its tile), except that pixels `wanted` refuses are skipped (no sample,
    /// the accumulator's `left_out` pixel, coverage 0). For reductions that never hold a whole
    /// frame.
    #[allow(clippy::too_many_arguments)]
    pub fn render_tile<A: Accumulator>(
        &self,
        camera: &Camera,
        stream: u64,
        settings: &RenderSettings,
        acc: &A,
        tile: Tile,
        wanted: Option<&(dyn Fn(u32) -> bool + Sync)>,
    ) -> Vec<Done<A::Pixel>> {
        let tracer = self.tracer(settings);
        let ray_dir = camera.ray_dirs();
        let view = View {
            wanted,
            ..self.view(camera, settings, stream, &ray_dir)
        };
        let mut k = Trace::new(&tracer, camera, acc, tile);
        drive(&view, tile, &mut k);
        k.into_pixels()
    }

    /// Walks every camera path of a render of `camera` (as [`Renderer::render`] would with
    /// these settings and `stream`), keeping their vertices to be lit later by
    /// [`Renderer::render_paths`], under any lights. With `wanted` (one flag per pixel, row by
    /// row), only the pixels it flags: the others are neither walked nor lit later (a pixel's
    /// paths do not depend on which others are walked). Memory: about 64 bytes per vertex, up
    /// to `max_bounces` vertices per sample.
    pub fn trace_paths(
        &self,
        camera: &Camera,
        stream: u64,
        settings: &RenderSettings,
        wanted: Option<Vec<bool>>,
    ) -> Paths {
        let tracer = self.tracer(settings);
        let ray_dir = camera.ray_dirs();
        let filter = wanted.as_ref().map(|w| move |i: u32| w[i as usize]);
        let view = View {
            wanted: filter.as_ref().map(|f| f as _),
            ..self.view(camera, settings, stream, &ray_dir)
        };
        let tiles = tiles(camera.width, camera.height)
            .par_iter()
            .map(|&tile| walk_tile(&view, &tracer, tile))
            .collect();
        Paths {
            width: camera.width,
            height: camera.height,
            settings: *settings,
            stream,
            wanted,
            tiles,
        }
    }

    /// Lights `paths` (walked by [`Renderer::trace_paths`] from `camera`) with this renderer's
    /// lights: the image [`Renderer::render`] makes with the paths' seed, samples and bounces
    /// and `settings`' strategy and emitter options, without tracing a camera path again.
    /// Pixels the walk left out get the accumulator's `left_out` pixel and coverage 0.
    pub fn render_paths<A: Accumulator>(
        &self,
        paths: &Paths,
        camera: &Camera,
        settings: &RenderSettings,
        acc: &A,
    ) -> Frame<A::Pixel> {
        let (w, h) = (paths.width, paths.height);
        let settings = RenderSettings {
            spp: paths.settings.spp,
            seed: paths.settings.seed,
            max_bounces: paths.settings.max_bounces,
            ..*settings
        };
        let tracer = self.tracer(&settings);
        let ray_dir = camera.ray_dirs();
        let filter = paths.wanted.as_ref().map(|w| move |i: u32| w[i as usize]);
        let view = View {
            wanted: filter.as_ref().map(|f| f as _),
            ..self.view(camera, &settings, paths.stream, &ray_dir)
        };
        let done: Vec<Vec<Done<A::Pixel>>> = tiles(w, h)
            .par_iter()
            .zip(&paths.tiles)
            .map(|(&tile, walked)| light_tile(&view, &tracer, acc, walked, tile))
            .collect();
        assemble(w, h, done)
    }

    /// Radiance images of `camera` under each of `lights` (this renderer's geometry; its own
    /// lights play no part), from one set of camera paths: each tile's paths are walked once
    /// and lit by every light set in turn, so k images cost one walk and k lightings. Each
    /// image is an unbiased render with `settings`' seed and `stream`; their noise is
    /// correlated, since they share paths.
    pub fn render_radiance_under(
        &self,
        camera: &Camera,
        stream: u64,
        settings: &RenderSettings,
        lights: &[&Lights],
        progress: &(dyn Fn(u64) + Sync),
    ) -> Vec<Image> {
        self.radiance_under(camera, stream, settings, lights, None, progress)
    }

    /// [`Renderer::render_radiance_under`] of the pixels `wanted` accepts (by index; the others
    /// are black with coverage 0); `progress` counts rendered pixels once per light set.
    fn radiance_under(
        &self,
        camera: &Camera,
        stream: u64,
        settings: &RenderSettings,
        lights: &[&Lights],
        wanted: Option<&(dyn Fn(u32) -> bool + Sync)>,
        progress: &(dyn Fn(u64) + Sync),
    ) -> Vec<Image> {
        if lights.is_empty() {
            return Vec::new();
        }
        let (w, h) = (camera.width, camera.height);
        let tracers: Vec<Tracer> = lights
            .iter()
            .map(|l| Tracer {
                lights: l,
                ..self.tracer(settings)
            })
            .collect();
        let ray_dir = camera.ray_dirs();
        let view = View {
            wanted,
            ..self.view(camera, settings, stream, &ray_dir)
        };
        let walker = self.tracer(settings);
        let done: Vec<Vec<Vec<Done<Vec3>>>> = tiles(w, h)
            .par_iter()
            .map(|&tile| {
                let walked = walk_tile(&view, &walker, tile);
                let lit: Vec<_> = tracers
                    .iter()
                    .map(|t| light_tile(&view, t, &RadianceAccumulator(t.lights), &walked, tile))
                    .collect();
                let pixels = match wanted {
                    Some(f) => lit[0].iter().filter(|d| f(d.0)).count(),
                    None => lit[0].len(),
                };
                progress((pixels * lit.len()) as u64);
                lit
            })
            .collect();
        transpose(done, lights.len())
            .into_iter()
            .map(|done| assemble(w, h, done).into_image())
            .collect()
    }

    /// [`Renderer::render_radiance_under`] for each view (random stream [`view_stream`]): per
    /// light set, one image per view. With `wanted`, only the (view index, pixel index) pairs
    /// it accepts are rendered, the rest left black.
    pub fn render_views_under(
        &self,
        views: &[&Camera],
        settings: &RenderSettings,
        lights: &[&Lights],
        wanted: Option<&(dyn Fn((usize, u32)) -> bool + Sync)>,
        progress: &(dyn Fn(u64) + Sync),
    ) -> Vec<Vec<Image>> {
        let per_view = views
            .iter()
            .enumerate()
            .map(|(v, cam)| {
                let in_view = move |i: u32| wanted.is_none_or(|f| f((v, i)));
                let filter: Option<&(dyn Fn(u32) -> bool + Sync)> =
                    wanted.is_some().then_some(&in_view);
                self.radiance_under(cam, view_stream(cam), settings, lights, filter, progress)
            })
            .collect();
        transpose(per_view, lights.len())
    }

    /// Renders radiance for each view (random stream [`view_stream`]).
    pub fn render_views(
        &self,
        views: &[&Camera],
        settings: &RenderSettings,
        progress: &(dyn Fn(u64) + Sync),
    ) -> Vec<Image> {
        views
            .iter()
            .map(|cam| self.render_radiance(cam, view_stream(cam), settings, progress))
            .collect()
    }

    /// Renders radiance; the coverage becomes the image's alpha.
    pub fn render_radiance(
        &self,
        camera: &Camera,
        stream: u64,
        settings: &RenderSettings,
        progress: &(dyn Fn(u64) + Sync),
    ) -> Image {
        let frame = self.render(
            camera,
            stream,
            settings,
            &RadianceAccumulator(self.lights),
            progress,
        );
        frame.into_image()
    }

    /// Depth, normal, albedo and texture coordinates at pixel centres (one ray per pixel, no
    /// randomness).
    pub fn aovs(&self, camera: &Camera) -> Aovs {
        let settings = RenderSettings::preview();
        let tracer = self.tracer(&settings);
        let (w, h) = (camera.width, camera.height);
        let hits: Vec<Option<FirstHit>> = (0..w * h)
            .into_par_iter()
            .map(|i| {
                let c = Vec2::new((i % w) as f32 + 0.5, (i / w) as f32 + 0.5);
                tracer.first_hit(camera.origin_world, camera.ray_dir_world(c.x, c.y))
            })
            .collect();
        let make = |f: &dyn Fn(&FirstHit) -> Vec3| Image {
            width: w,
            height: h,
            rgb: hits
                .iter()
                .map(|hit| hit.as_ref().map_or(Vec3::ZERO, f))
                .collect(),
            alpha: None,
        };
        Aovs {
            depth: make(&|h| Vec3::splat(h.distance)),
            normal: make(&|h| h.normal),
            albedo: make(&|h| h.albedo),
            uv: hits
                .iter()
                .map(|hit| hit.as_ref().map_or(Vec2::NAN, |h| h.uv))
                .collect(),
        }
    }

    /// Each pixel's material (row-major, an index into the scene's materials): the one its
    /// centre and four points half-way to its corners all see, else [`NO_MATERIAL`]. A pixel
    /// on an edge between materials averages both, so it is left out rather than given to
    /// either.
    pub fn material_ids(&self, camera: &Camera) -> Vec<u32> {
        let settings = RenderSettings::preview();
        let tracer = self.tracer(&settings);
        let w = camera.width;
        const POINTS: [(f32, f32); 5] = [
            (0.5, 0.5),
            (0.25, 0.25),
            (0.75, 0.25),
            (0.25, 0.75),
            (0.75, 0.75),
        ];
        (0..w * camera.height)
            .into_par_iter()
            .map(|i| {
                let (x, y) = ((i % w) as f32, (i / w) as f32);
                let mut seen = POINTS.iter().map(|(dx, dy)| {
                    tracer.first_material(camera.origin_world, camera.ray_dir_world(x + dx, y + dy))
                });
                let first = seen.next().flatten();
                match first {
                    Some(m) if seen.all(|s| s == Some(m)) => m,
                    _ => NO_MATERIAL,
                }
            })
            .collect()
    }
}

/// Where a pixel's material is not known: it sees no geometry, or more than one material.
pub const NO_MATERIAL: u32 = u32::MAX;

/// Camera paths of one view, walked once ([`Renderer::trace_paths`]) to be lit many times.
pub struct Paths {
    pub width: u32,
    pub height: u32,
    /// The settings they were walked with (seed, samples, bounces).
    pub settings: RenderSettings,
    pub stream: u64,
    /// The pixels walked, if not all (one flag per pixel, row by row).
    wanted: Option<Vec<bool>>,
    /// Per tile, in [`tiles`] order.
    tiles: Vec<TilePaths>,
}

impl Paths {
    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.tiles.iter().map(TilePaths::bytes).sum::<usize>()
            + self.wanted.as_ref().map_or(0, Vec::len)
    }
}

/// Walks the camera paths of one tile ([`Walk`]).
fn walk_tile<R: Fn(f32, f32) -> Vec3>(view: &View<R>, tracer: &Tracer, tile: Tile) -> TilePaths {
    let mut k = Walk::new(tracer, view.camera, tile);
    drive(view, tile, &mut k);
    k.into_paths()
}

/// Lights one tile's walked paths with the tracer's lights ([`Light`]).
fn light_tile<R: Fn(f32, f32) -> Vec3, A: Accumulator>(
    view: &View<R>,
    tracer: &Tracer,
    acc: &A,
    walked: &TilePaths,
    tile: Tile,
) -> Vec<Done<A::Pixel>> {
    let mut k = Light::new(tracer, view.camera, acc, walked, tile);
    drive(view, tile, &mut k);
    k.into_pixels()
}

/// The random stream of a view's renders, from its name alone: a view renders the same image
/// whichever other views are selected, and in whatever order.
pub fn view_stream(camera: &Camera) -> u64 {
    // FNV-1a over the name's bytes, then mixed.
    let fnv = camera.name.bytes().fold(0xCBF2_9CE4_8422_2325u64, |h, b| {
        (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01B3)
    });
    mix64(fnv)
}

/// Puts tiles' pixels (index, pixel, coverage) in their places.
fn assemble<P>(w: u32, h: u32, done: Vec<Vec<Done<P>>>) -> Frame<P> {
    let n = (w * h) as usize;
    let mut slots: Vec<Option<P>> = (0..n).map(|_| None).collect();
    let mut coverage = vec![0.0; n];
    for (index, px, cov) in done.into_iter().flatten() {
        slots[index as usize] = Some(px);
        coverage[index as usize] = cov;
    }
    let pixels = slots
        .into_iter()
        .map(|p| p.expect("every pixel belongs to one tile"))
        .collect();
    Frame {
        width: w,
        height: h,
        pixels,
        coverage,
    }
}

/// Rows of `n` items as `n` columns: `[a][b]` → `[b][a]`.
fn transpose<T>(rows: Vec<Vec<T>>, n: usize) -> Vec<Vec<T>> {
    let mut columns: Vec<Vec<T>> = (0..n).map(|_| Vec::with_capacity(rows.len())).collect();
    for row in rows {
        for (column, item) in columns.iter_mut().zip(row) {
            column.push(item);
        }
    }
    columns
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampling::{self, Rng};
    use crate::scene::SphereLight;

    #[test]
    fn pyramids_that_reach_a_light_are_never_said_to_miss_it() {
        // Random pixel-like pyramids and spheres: whenever a ray inside a pyramid hits a
        // sphere, the pyramid must be said to meet the lights; and far from every sphere,
        // it must not (or the test would prove nothing).
        let mut r = Rng::new(3);
        let (mut met, mut missed) = (0, 0);
        for _ in 0..4000 {
            let o = Vec3::new(r.next_f32(), r.next_f32(), r.next_f32()) * 4.0 - Vec3::splat(2.0);
            let ahead = sampling::uniform_sphere(r.next_2d());
            let (right, up) = sampling::frame(ahead);
            let size = [0.002, 0.01, 0.1][r.next_u32() as usize % 3];
            let corner = |u: f32, v: f32| (ahead + (right * u + up * v) * size).normalize();
            let corners = [
                corner(0.0, 0.0),
                corner(1.0, 0.0),
                corner(1.0, 1.0),
                corner(0.0, 1.0),
            ];
            // A sphere near the pyramid's axis, sometimes off it.
            let along = o + ahead * (0.5 + 3.0 * r.next_f32());
            let off = sampling::uniform_sphere(r.next_2d()) * (0.2 * r.next_f32());
            let lights = Lights::new(vec![SphereLight {
                center: along + off,
                radius: 0.005 + 0.05 * r.next_f32(),
                radiance: Vec3::ONE,
            }]);
            let says = pixels::pyramid_meets_lights(&lights, o, &corners);
            let hit = (0..200).any(|_| {
                let u = r.next_2d();
                let d = corner(u.x, u.y);
                lights.intersect(o, d, 0.0, f32::INFINITY).is_some()
            });
            assert!(
                says || !hit,
                "a ray hits the sphere, the pyramid is said to miss it"
            );
            met += hit as usize;
            missed += !says as usize;
        }
        assert!(met > 200 && missed > 1000, "met {met}, missed {missed}");
    }
}
