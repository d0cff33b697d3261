//! The one pixel loop. A render is cut into fixed tiles ([`tiles`]); [`drive`] visits a
//! tile's pixels row by row, hands each pixel's camera samples to a [`Kernel`] in chunks of
//! [`LANES`], and applies the one rule for skipping a pixel: when none of its camera rays can
//! meet geometry and what they would see instead is hidden, its samples cannot deliver
//! anything. Three kernels run in it: [`Trace`] walks and lights paths in one go (a fresh
//! render), [`Walk`] keeps walked paths to light later, [`Light`] lights kept paths.
//!
//! Every camera sample draws from streams keyed by (render key, pixel index, sample index),
//! so what a kernel computes for a pixel does not depend on the tile or the thread.

use glam::{Vec2, Vec3};

use super::integrator::{self, PathSampler, Scratch, Tracer, Vertex, Walked};
use super::lights::LANES;
use super::{Accumulator, Lights, RenderSettings};
use crate::accel::{Bundle, Isa};
use crate::sampling::{Rng, mix64};
use crate::scene::Camera;

/// Side of the square tiles work is split into. Small enough that the threads finish a view
/// together: the bundled scene's 16-pixel tiles (48 per view, some ten times the work of
/// others) left a thread idle at the end of each view, 4–5% of a 2-thread render. Images do
/// not depend on it (pixels are seeded by their index).
pub const TILE: u32 = 8;

/// A tile: pixels `x0..x1` × `y0..y1`.
pub type Tile = (u32, u32, u32, u32);

/// Fixed tiles covering a w × h image, row by row.
pub fn tiles(w: u32, h: u32) -> Vec<Tile> {
    let mut out = Vec::new();
    for y0 in (0..h).step_by(TILE as usize) {
        for x0 in (0..w).step_by(TILE as usize) {
            out.push((x0, y0, (x0 + TILE).min(w), (y0 + TILE).min(h)));
        }
    }
    out
}

/// A pixel being visited.
pub struct Pixel {
    pub x: u32,
    pub y: u32,
    /// `y · width + x`.
    pub index: u32,
    /// The unit directions through its corners, in order around it (its samples' jitter lies
    /// in [0, 1)², so every camera ray lies inside their pyramid).
    pub corners: [Vec3; 4],
}

/// What the pixel loop runs at each pixel.
pub trait Kernel {
    /// Prepares `p`; true when none of its camera rays can meet scene geometry.
    fn blind(&mut self, p: &Pixel) -> bool;
    /// Whether emitters seen directly are hidden: then a blind pixel delivers nothing.
    fn hides_emitters(&self) -> bool;
    /// Records a pixel whose samples are skipped by the one rule.
    fn skip(&mut self, p: &Pixel);
    /// Records a pixel the caller did not ask for ([`View::wanted`]): nothing is walked for
    /// it, and a lighting kernel gives it the accumulator's [`Accumulator::left_out`] pixel.
    fn leave_out(&mut self, p: &Pixel);
    /// A pixel whose samples follow.
    fn start(&mut self, p: &Pixel);
    /// The next (at most [`LANES`]) camera samples of the pixel: unit directions and samplers.
    fn chunk(&mut self, dirs: &[Vec3], samplers: &mut [PathSampler]);
    /// The pixel's samples are done.
    fn end(&mut self, p: &Pixel);
}

/// What every tile of one render shares.
pub struct View<'a, R: Fn(f32, f32) -> Vec3> {
    pub camera: &'a Camera,
    /// The key every random stream of the render derives from ([`render_key`]).
    pub key: u64,
    /// The camera's ray direction through an image point.
    pub ray_dir: &'a R,
    pub settings: &'a RenderSettings,
    /// The instruction set the BVH runs ([`crate::accel::Accel::isa`]); the pixel loop
    /// follows it.
    pub isa: Isa,
    /// The pixels (by index) the caller asks for; the others are skipped. None: all.
    pub wanted: Option<&'a (dyn Fn(u32) -> bool + Sync)>,
}

/// Visits the pixels of `tile` with `kernel`: compiled twice, for the baseline target and for
/// AVX2 (the tracer's eight-lane loops run 8 wide, not 4, and rounding is an instruction, not
/// a library call); the AVX2 copy runs where the CPU has it and the BVH runs its AVX kernels
/// ([`Isa`]). Rust contracts no floating-point operations, so both compute the same bits.
#[inline]
pub fn drive<R: Fn(f32, f32) -> Vec3, K: Kernel>(view: &View<R>, tile: Tile, kernel: &mut K) {
    #[cfg(target_arch = "x86_64")]
    if view.isa == Isa::Avx2 {
        // SAFETY: `Isa::Avx2` is chosen only where the CPU has every feature `drive_avx2` is
        // compiled with (`Isa::detect`).
        unsafe { drive_avx2(view, tile, kernel) };
        return;
    }
    drive_on(view, tile, kernel)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
fn drive_avx2<R: Fn(f32, f32) -> Vec3, K: Kernel>(view: &View<R>, tile: Tile, kernel: &mut K) {
    drive_on(view, tile, kernel)
}

/// [`drive`]'s loop, inlined into each of its copies.
#[inline(always)]
fn drive_on<R: Fn(f32, f32) -> Vec3, K: Kernel>(view: &View<R>, tile: Tile, kernel: &mut K) {
    let (x0, y0, x1, y1) = tile;
    let (mut dirs, mut samplers) = (Vec::with_capacity(LANES), Vec::with_capacity(LANES));
    for y in y0..y1 {
        for x in x0..x1 {
            let p = Pixel {
                x,
                y,
                index: y * view.camera.width + x,
                corners: pixel_corners(view.ray_dir, x, y),
            };
            if view.wanted.is_some_and(|w| !w(p.index)) {
                kernel.leave_out(&p);
                continue;
            }
            if kernel.blind(&p) && kernel.hides_emitters() {
                kernel.skip(&p);
                continue;
            }
            kernel.start(&p);
            let mut samples = camera_samples(view, &p);
            while next_chunk(&mut samples, &mut dirs, &mut samplers) {
                kernel.chunk(&dirs, &mut samplers);
            }
            kernel.end(&p);
        }
    }
}

/// The key every random stream of a render derives from.
pub fn render_key(settings: &RenderSettings, stream: u64) -> u64 {
    mix64(settings.seed ^ mix64(stream.wrapping_add(0xC0FFEE)))
}

/// The unit directions through pixel (`x`, `y`)'s corners, in order around it.
#[inline(always)]
fn pixel_corners(ray_dir: &impl Fn(f32, f32) -> Vec3, x: u32, y: u32) -> [Vec3; 4] {
    let (x, y) = (x as f32, y as f32);
    [
        ray_dir(x, y),
        ray_dir(x + 1.0, y),
        ray_dir(x + 1.0, y + 1.0),
        ray_dir(x, y + 1.0),
    ]
}

/// Whether a ray from `origin` inside the pyramid spanned by unit `corners` can meet one of
/// the sphere lights. Conservative: the cone around the pyramid against the cone each sphere
/// subtends (they meet when the angle between their axes is at most the sum of their
/// half-angles), with a margin for rounding.
pub fn pyramid_meets_lights(lights: &Lights, origin: Vec3, corners: &[Vec3; 4]) -> bool {
    const MARGIN: f32 = 1e-3; // radians
    let axis = corners.iter().copied().sum::<Vec3>().normalize();
    let angle = |a: Vec3, b: Vec3| a.dot(b).clamp(-1.0, 1.0).acos();
    let half = corners.iter().map(|&c| angle(c, axis)).fold(0.0, f32::max);
    lights.spheres.iter().any(|s| {
        let to_c = s.center - origin;
        let d = to_c.length();
        d <= s.radius * 1.001 || angle(to_c / d, axis) <= half + (s.radius / d).asin() + MARGIN
    })
}

/// Fills `bundle` with the BVH leaves pixel `p`'s pyramid reaches; true when it reaches none
/// (no camera ray of the pixel can meet geometry).
#[inline(always)]
fn pyramid_is_blind(tracer: &Tracer, camera: &Camera, p: &Pixel, bundle: &mut Bundle) -> bool {
    tracer.accel.bundle(camera.origin_world, p.corners, bundle);
    bundle.meets_nothing()
}

/// The camera samples of a pixel: each one's ray direction and random streams.
#[inline(always)]
fn camera_samples<'a, R: Fn(f32, f32) -> Vec3>(
    view: &View<'a, R>,
    p: &Pixel,
) -> CameraSamples<'a, R> {
    let pixel_key = mix64(view.key ^ p.index as u64);
    let mut keys = Rng::new(pixel_key);
    let pixel_offset = keys.next_2d();
    CameraSamples {
        ray_dir: view.ray_dir,
        pixel_key,
        pixel_offset,
        sobol_keys: [(); integrator::KEYS].map(|_| keys.next_u32()),
        spp: view.settings.spp,
        max_bounces: view.settings.max_bounces,
        x: p.x as f32,
        y: p.y as f32,
        next: 0,
    }
}

/// [`camera_samples`]: an iterator of its own rather than `map` over a range, so that its
/// `next` is compiled into each copy of the pixel loop (`Map::next` was left out of line,
/// without AVX2: 6% of a render).
struct CameraSamples<'a, R> {
    ray_dir: &'a R,
    pixel_key: u64,
    pixel_offset: Vec2,
    sobol_keys: [u32; integrator::KEYS],
    spp: u32,
    max_bounces: u32,
    /// The pixel's top-left corner, image coordinates.
    x: f32,
    y: f32,
    /// Index of the next sample.
    next: u32,
}

impl<R: Fn(f32, f32) -> Vec3> Iterator for CameraSamples<'_, R> {
    type Item = (Vec3, PathSampler);

    #[inline(always)]
    fn next(&mut self) -> Option<(Vec3, PathSampler)> {
        if self.next >= self.spp {
            return None;
        }
        let s = PathSampler::new(
            self.pixel_key,
            self.pixel_offset,
            self.sobol_keys,
            self.next,
            self.spp,
            self.max_bounces,
        );
        self.next += 1;
        let j: Vec2 = s.pixel_jitter();
        Some(((self.ray_dir)(self.x + j.x, self.y + j.y), s))
    }
}

/// Refills `dirs` and `samplers` with the next (at most [`LANES`]) camera samples of a pixel,
/// the chunk a kernel takes at once. False when there are none left.
#[inline(always)]
fn next_chunk(
    samples: &mut impl Iterator<Item = (Vec3, PathSampler)>,
    dirs: &mut Vec<Vec3>,
    samplers: &mut Vec<PathSampler>,
) -> bool {
    dirs.clear();
    samplers.clear();
    for (dir, s) in samples.by_ref().take(LANES) {
        dirs.push(dir);
        samplers.push(s);
    }
    !dirs.is_empty()
}

/// A finished pixel: (index, estimate, coverage = the fraction of its camera rays that saw
/// geometry).
pub type Done<P> = (u32, P, f32);

/// A pixel being accumulated.
struct Open<P> {
    px: P,
    /// Camera rays that saw geometry.
    hits: u32,
}

/// The accumulation the two lighting kernels share: pixels opened, summed into and finished
/// in `acc`, in visiting order.
struct Pixels<'a, A: Accumulator> {
    acc: &'a A,
    spp: u32,
    /// The lights and the camera origin, for [`pyramid_meets_lights`].
    lights: &'a Lights,
    origin: Vec3,
    /// Whether the camera rays of the open pixel test sphere lights: they can meet one
    /// ([`pyramid_meets_lights`]) and are to ([`super::RenderSettings::camera_sees_lights`]).
    lights_ahead: bool,
    /// [`super::RenderSettings::camera_sees_lights`].
    sees_lights: bool,
    open: Option<Open<A::Pixel>>,
    out: Vec<Done<A::Pixel>>,
}

impl<'a, A: Accumulator> Pixels<'a, A> {
    fn new(acc: &'a A, tracer: &'a Tracer<'a>, camera: &Camera, tile: Tile) -> Self {
        Pixels {
            acc,
            spp: tracer.settings.spp,
            lights: tracer.lights,
            origin: camera.origin_world,
            lights_ahead: false,
            sees_lights: tracer.settings.camera_sees_lights,
            open: None,
            out: Vec::with_capacity(tile_pixels(tile)),
        }
    }

    /// A pixel none of whose samples can deliver anything.
    #[inline(always)]
    fn skip(&mut self, p: &Pixel) {
        let mut px = self.acc.new_pixel();
        self.acc.finish(&mut px, self.spp);
        self.out.push((p.index, px, 0.0));
    }

    /// A pixel not asked for: the accumulator's [`Accumulator::left_out`] pixel.
    #[inline(always)]
    fn leave_out(&mut self, p: &Pixel) {
        self.out.push((p.index, self.acc.left_out(), 0.0));
    }

    #[inline(always)]
    fn start(&mut self, p: &Pixel) {
        self.lights_ahead =
            self.sees_lights && pyramid_meets_lights(self.lights, self.origin, &p.corners);
        self.open = Some(Open {
            px: self.acc.new_pixel(),
            hits: 0,
        });
    }

    #[inline(always)]
    fn open(&mut self) -> &mut Open<A::Pixel> {
        self.open.as_mut().expect("a started pixel")
    }

    #[inline(always)]
    fn end(&mut self, p: &Pixel) {
        let mut open = self.open.take().expect("a started pixel");
        self.acc.finish(&mut open.px, self.spp);
        let coverage = open.hits as f32 / self.spp as f32;
        self.out.push((p.index, open.px, coverage));
    }
}

/// Traces and lights each camera path in one go: a fresh render with `acc`.
pub struct Trace<'a, A: Accumulator> {
    tracer: &'a Tracer<'a>,
    camera: &'a Camera,
    bundle: Bundle,
    scratch: Scratch,
    pixels: Pixels<'a, A>,
}

impl<'a, A: Accumulator> Trace<'a, A> {
    pub fn new(tracer: &'a Tracer<'a>, camera: &'a Camera, acc: &'a A, tile: Tile) -> Self {
        Trace {
            tracer,
            camera,
            bundle: Bundle::default(),
            scratch: Scratch::default(),
            pixels: Pixels::new(acc, tracer, camera, tile),
        }
    }

    /// Each visited pixel: (index, estimate, coverage).
    pub fn into_pixels(self) -> Vec<Done<A::Pixel>> {
        self.pixels.out
    }
}

impl<A: Accumulator> Kernel for Trace<'_, A> {
    #[inline(always)]
    fn blind(&mut self, p: &Pixel) -> bool {
        pyramid_is_blind(self.tracer, self.camera, p, &mut self.bundle)
    }
    #[inline(always)]
    fn hides_emitters(&self) -> bool {
        self.tracer.settings.hide_emitters
    }
    #[inline(always)]
    fn skip(&mut self, p: &Pixel) {
        self.pixels.skip(p);
    }
    #[inline(always)]
    fn leave_out(&mut self, p: &Pixel) {
        self.pixels.leave_out(p);
    }
    #[inline(always)]
    fn start(&mut self, p: &Pixel) {
        self.pixels.start(p);
    }
    #[inline(always)]
    fn chunk(&mut self, dirs: &[Vec3], samplers: &mut [PathSampler]) {
        let lights_ahead = self.pixels.lights_ahead;
        let acc = self.pixels.acc;
        let open = self.pixels.open();
        open.hits += self.tracer.trace(
            &self.bundle,
            lights_ahead,
            dirs,
            samplers,
            &mut self.scratch,
            acc,
            &mut open.px,
        );
    }
    #[inline(always)]
    fn end(&mut self, p: &Pixel) {
        self.pixels.end(p);
    }
}

/// The camera paths of one tile: per camera sample (pixels row by row, samples in order), the
/// distance to its first surface and how many vertices it has, which follow in `vertices`;
/// and per pixel whether it is blind (its camera rays meet no geometry; its samples are
/// recorded as escaping without a walk).
pub struct TilePaths {
    samples: Vec<(f32, u8)>,
    vertices: Vec<Vertex>,
    blind: Vec<bool>,
}

impl TilePaths {
    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.samples.len() * std::mem::size_of::<(f32, u8)>()
            + self.vertices.len() * std::mem::size_of::<Vertex>()
            + self.blind.len()
    }
}

/// Walks camera paths and keeps their vertices (the last segment's geometry traced too, as
/// the paths are lit more than once), to be lit by [`Light`].
pub struct Walk<'a> {
    tracer: &'a Tracer<'a>,
    camera: &'a Camera,
    bundle: Bundle,
    verts: Vec<Vertex>,
    out: TilePaths,
}

impl<'a> Walk<'a> {
    pub fn new(tracer: &'a Tracer<'a>, camera: &'a Camera, tile: Tile) -> Self {
        let pixels = tile_pixels(tile);
        Walk {
            tracer,
            camera,
            bundle: Bundle::default(),
            verts: Vec::new(),
            out: TilePaths {
                samples: Vec::new(),
                vertices: Vec::new(),
                blind: Vec::with_capacity(pixels),
            },
        }
    }

    /// The tile's walked paths, in as little memory as they need (they are kept, and a
    /// tile may hold few of the pixels asked for).
    pub fn into_paths(mut self) -> TilePaths {
        self.out.samples.shrink_to_fit();
        self.out.vertices.shrink_to_fit();
        self.out.blind.shrink_to_fit();
        self.out
    }
}

impl Kernel for Walk<'_> {
    #[inline(always)]
    fn blind(&mut self, p: &Pixel) -> bool {
        let blind = pyramid_is_blind(self.tracer, self.camera, p, &mut self.bundle);
        self.out.blind.push(blind);
        blind
    }
    /// A walk sees no emitter: a blind pixel's walks would each end at the camera ray.
    #[inline(always)]
    fn hides_emitters(&self) -> bool {
        true
    }
    #[inline(always)]
    fn skip(&mut self, _: &Pixel) {
        let n = self.out.samples.len() + self.tracer.settings.spp as usize;
        self.out.samples.resize(n, (f32::INFINITY, 0));
    }
    #[inline(always)]
    fn leave_out(&mut self, _: &Pixel) {}
    #[inline(always)]
    fn start(&mut self, _: &Pixel) {}
    #[inline(always)]
    fn chunk(&mut self, dirs: &[Vec3], samplers: &mut [PathSampler]) {
        let mb = self.tracer.settings.max_bounces as usize;
        let (t, len) = self
            .tracer
            .walk(&self.bundle, dirs, samplers, true, &mut self.verts);
        for l in 0..dirs.len() {
            self.out
                .vertices
                .extend_from_slice(integrator::lane_vertices(&self.verts, mb, l, len[l]));
            self.out.samples.push((t[l], len[l] as u8));
        }
    }
    #[inline(always)]
    fn end(&mut self, _: &Pixel) {}
}

/// Lights a tile's walked paths with the tracer's lights into `acc`.
pub struct Light<'a, A: Accumulator> {
    tracer: &'a Tracer<'a>,
    camera: &'a Camera,
    walked: &'a TilePaths,
    /// Cursors into `walked`: the next pixel, sample and vertex.
    pixel: usize,
    sample: usize,
    vertex: usize,
    added: integrator::Added,
    pixels: Pixels<'a, A>,
}

impl<'a, A: Accumulator> Light<'a, A> {
    pub fn new(
        tracer: &'a Tracer<'a>,
        camera: &'a Camera,
        acc: &'a A,
        walked: &'a TilePaths,
        tile: Tile,
    ) -> Self {
        Light {
            tracer,
            camera,
            walked,
            pixel: 0,
            sample: 0,
            vertex: 0,
            added: integrator::Added::default(),
            pixels: Pixels::new(acc, tracer, camera, tile),
        }
    }

    /// Each visited pixel: (index, estimate, coverage).
    pub fn into_pixels(self) -> Vec<Done<A::Pixel>> {
        self.pixels.out
    }
}

impl<A: Accumulator> Kernel for Light<'_, A> {
    #[inline(always)]
    fn blind(&mut self, _: &Pixel) -> bool {
        self.pixel += 1;
        self.walked.blind[self.pixel - 1]
    }
    #[inline(always)]
    fn hides_emitters(&self) -> bool {
        self.tracer.settings.hide_emitters
    }
    #[inline(always)]
    fn skip(&mut self, p: &Pixel) {
        // Its walks were recorded as escapes, with no vertices.
        self.sample += self.tracer.settings.spp as usize;
        self.pixels.skip(p);
    }
    #[inline(always)]
    fn leave_out(&mut self, p: &Pixel) {
        // Nothing was walked for it.
        self.pixels.leave_out(p);
    }
    #[inline(always)]
    fn start(&mut self, p: &Pixel) {
        self.pixels.start(p);
    }
    #[inline(always)]
    fn chunk(&mut self, dirs: &[Vec3], samplers: &mut [PathSampler]) {
        let mut paths = [Walked {
            dir: Vec3::Z,
            t_first: f32::INFINITY,
            verts: &[],
        }; LANES];
        for (path, &dir) in paths.iter_mut().zip(dirs) {
            let (t_first, n) = self.walked.samples[self.sample];
            let verts = &self.walked.vertices[self.vertex..self.vertex + n as usize];
            (self.sample, self.vertex) = (self.sample + 1, self.vertex + n as usize);
            *path = Walked {
                dir,
                t_first,
                verts,
            };
        }
        let lights_ahead = self.pixels.lights_ahead;
        let acc = self.pixels.acc;
        let open = self.pixels.open();
        open.hits += self.tracer.light(
            self.camera.origin_world,
            lights_ahead,
            &paths[..dirs.len()],
            samplers,
            &mut self.added,
            acc,
            &mut open.px,
        );
    }
    #[inline(always)]
    fn end(&mut self, p: &Pixel) {
        self.pixels.end(p);
    }
}

fn tile_pixels((x0, y0, x1, y1): Tile) -> usize {
    ((x1 - x0) * (y1 - y0)) as usize
}
