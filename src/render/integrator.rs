//! The path tracer — the only one in lightprobe. Lambertian two-sided surfaces; next-event
//! estimation of the lights combined with cosine-weighted BSDF sampling by multiple importance
//! sampling (power heuristic). What a path delivers goes to an [`Accumulator`] as
//! (emitter, weight per unit emitted radiance), so the same tracer renders radiance or
//! accumulates derivatives with respect to each emitter.
//!
//! A path is traced in two steps: [`Tracer::walk`] finds its scattering vertices (camera ray,
//! BSDF samples, closest hits: the scene's geometry only), then [`Tracer::light`] lights them
//! (emitter samples, shadow rays, and the emitters the BSDF segments reach). Nothing in the
//! walk depends on the lights, and the two draw from separate random streams, so a walked path
//! can be kept and lit again under other lights ([`super::Paths`]): the sphere model's many
//! renders differ only in their lights.

use glam::{Vec2, Vec3};

use super::lights::{Emitter, LANES, LightQuery, LightSample, Lights};
use super::{Accumulator, RenderSettings, Strategy};
use crate::accel::{Accel, Bundle, Hit};
use crate::sampling::{INV_PI, Rng, cosine_hemisphere, permute, power_heuristic, r2, sobol2};
use crate::scene::Scene;

/// The random numbers of one camera sample. The pixel jitter comes from a per-pixel-rotated
/// R2 sequence (stratified across the pixel's samples); the light and BSDF samples of the
/// first [`STRATIFIED`] vertices from padded Sobol pairs; later vertices' BSDF samples from a
/// PCG stream, and their light samples from the same stream further on. (Drawing further
/// dimensions from the same R2 sequence would tie them to the pixel position: each pixel's
/// estimate would then converge to a shifted, wrong integral.)
pub(super) struct PathSampler {
    /// The PCG streams (BSDF, light), made when a vertex beyond [`STRATIFIED`] first needs
    /// them: most paths never do, and seeding costs a few hashes per sample.
    streams: Option<(Rng, Rng)>,
    /// What seeds the streams.
    stream_key: u64,
    max_bounces: u32,
    pub index: u32,
    pub pixel_offset: Vec2,
    /// Per pixel: the permutation keys and digital shifts of the Sobol pairs of the first
    /// [`STRATIFIED`] vertices, three pairs each ([`PathSampler::light_sample`],
    /// [`PathSampler::bsdf_sample`]).
    pub keys: [u32; KEYS],
    /// Samples per pixel (the permutations' range).
    pub spp: u32,
}

/// Vertices whose light and BSDF samples are stratified over a pixel's samples; later ones
/// draw from the PCG streams.
pub(super) const STRATIFIED: usize = 2;
/// Keys per pixel: per stratified vertex three Sobol pairs, each a permutation key and two
/// digital shifts.
pub(super) const KEYS: usize = 9 * STRATIFIED;

impl PathSampler {
    /// The sampler of camera sample `index` of the pixel keyed `pixel_key`.
    #[inline]
    pub fn new(
        pixel_key: u64,
        pixel_offset: Vec2,
        keys: [u32; KEYS],
        index: u32,
        spp: u32,
        max_bounces: u32,
    ) -> PathSampler {
        PathSampler {
            streams: None,
            stream_key: pixel_key.wrapping_add(crate::sampling::mix64(index as u64 + 1)),
            max_bounces,
            index,
            pixel_offset,
            keys,
            spp,
        }
    }

    /// The (BSDF, light) PCG streams.
    #[inline]
    fn streams(&mut self) -> &mut (Rng, Rng) {
        let (key, max_bounces) = (self.stream_key, self.max_bounces);
        self.streams.get_or_insert_with(|| {
            let rng = Rng::new(key);
            (rng.clone(), rng.ahead(2 * max_bounces))
        })
    }

    /// The light stream (for vertices beyond [`STRATIFIED`]).
    #[inline]
    pub fn light_rng(&mut self) -> &mut Rng {
        &mut self.streams().1
    }

    #[inline]
    pub fn pixel_jitter(&self) -> Vec2 {
        r2(self.index, self.pixel_offset)
    }

    /// Sobol pair `pair` (0..3) of vertex `vertex` (< [`STRATIFIED`]), padded: its own
    /// per-pixel permutation of the sample index and digital shift, so pairs are independent
    /// of each other and of the pixel jitter, and every point is uniform (each pixel's
    /// estimate stays unbiased).
    #[inline(always)]
    fn pair(&self, vertex: usize, pair: usize) -> Vec2 {
        let k = &self.keys[9 * vertex + 3 * pair..];
        sobol2(permute(self.index, self.spp, k[0]), [k[1], k[2]])
    }

    /// Vertex `k`'s light sample: (light and cell pick, direction), stratified over the
    /// pixel's samples for the first [`STRATIFIED`] vertices (the light samples of the first
    /// bounces are most of a diffuse image's noise), from the light stream after them.
    #[inline(always)]
    pub fn light_sample(&mut self, k: usize) -> (Vec2, Vec2) {
        if k < STRATIFIED {
            (self.pair(k, 0), self.pair(k, 1))
        } else {
            let rng = self.light_rng();
            (rng.next_2d(), rng.next_2d())
        }
    }

    /// Vertex `k`'s BSDF sample, stratified like [`PathSampler::light_sample`].
    #[inline]
    pub fn bsdf_sample(&mut self, k: usize) -> Vec2 {
        if k < STRATIFIED {
            self.pair(k, 2)
        } else {
            self.streams().0.next_2d()
        }
    }
}

/// A scattering vertex of a camera path: what lighting it needs, none of it dependent on the
/// lights.
#[derive(Debug, Clone, Copy)]
pub struct Vertex {
    /// Position, world space (metres).
    p: Vec3,
    /// Geometric normal facing the incoming ray; shading normal on the same side.
    ng: Vec3,
    ns: Vec3,
    /// Path throughput up to this vertex times its BSDF (albedo / π).
    throughput_f: Vec3,
    /// The BSDF-sampled direction leaving the vertex; zero where the path ends here.
    wi: Vec3,
    /// Distance to scene geometry along `wi` from the offset origin: ∞ if the ray escapes,
    /// NaN if not traced (a path's last segment, which matters only if it reaches an emitter).
    t_next: f32,
}

impl Vertex {
    /// A placeholder (scratch space), overwritten before it is read.
    const NONE: Vertex = Vertex {
        p: Vec3::ZERO,
        ng: Vec3::ZERO,
        ns: Vec3::ZERO,
        throughput_f: Vec3::ZERO,
        wi: Vec3::ZERO,
        t_next: f32::NAN,
    };
}

/// The set bits of `mask` (lanes), in increasing order.
#[inline]
fn set_bits(mut mask: u32) -> impl Iterator<Item = usize> {
    std::iter::from_fn(move || {
        (mask != 0).then(|| {
            let l = mask.trailing_zeros() as usize;
            mask &= mask - 1;
            l
        })
    })
}

/// What each of [`LANES`] paths delivers, (emitter, weight per unit emitted radiance), in
/// order: [`Tracer::light`]'s scratch space.
/// Per lane, what its path delivers: (emitter, unit direction toward it, weight).
pub(super) type Added = [Vec<(Emitter, Vec3, Vec3)>; LANES];

/// Lane `l`'s `len` vertices in the scratch space [`Tracer::walk`] filled with
/// `max_bounces`-long stretches (empty for a lane past the last).
#[inline]
pub(super) fn lane_vertices(
    verts: &[Vertex],
    max_bounces: usize,
    l: usize,
    len: usize,
) -> &[Vertex] {
    verts.get(l * max_bounces..).map_or(&[], |v| &v[..len])
}

/// Scratch space of [`Tracer::trace`]: the walked vertices, and what the paths deliver
/// before it is handed to the accumulator ([`Tracer::light`]).
#[derive(Default)]
pub(super) struct Scratch {
    pub verts: Vec<Vertex>,
    pub added: Added,
}

/// A walked camera path, ready to be lit ([`Tracer::light`]).
#[derive(Debug, Clone, Copy)]
pub struct Walked<'v> {
    /// The camera ray's unit direction, world space.
    pub dir: Vec3,
    /// Distance to the first surface, metres (∞ if the camera ray sees none).
    pub t_first: f32,
    pub verts: &'v [Vertex],
}

/// Local geometry at a surface hit, with both normals facing the incoming ray.
struct SurfacePoint {
    p: Vec3,
    /// Geometric normal, facing the side the ray came from.
    ng: Vec3,
    /// Shading normal (interpolated), on the same side as `ng`.
    ns: Vec3,
    albedo: Vec3,
    /// glTF texture coordinates.
    uv: Vec2,
}

impl SurfacePoint {
    /// A placeholder for an idle lane: a normal (+Z) that BSDF sampling accepts.
    const NONE: SurfacePoint = SurfacePoint {
        p: Vec3::ZERO,
        ng: Vec3::Z,
        ns: Vec3::Z,
        albedo: Vec3::ZERO,
        uv: Vec2::ZERO,
    };
}

#[inline(always)]
fn surface_point(scene: &Scene, hit: &Hit, d: Vec3) -> SurfacePoint {
    let mesh = &scene.mesh;
    let t = hit.triangle as usize;
    let [ia, ib, ic] = mesh.triangles[t].map(|i| i as usize);
    let b0 = 1.0 - hit.b1 - hit.b2;
    let [a, b, c] = [mesh.positions[ia], mesh.positions[ib], mesh.positions[ic]];
    let p = a * b0 + b * hit.b1 + c * hit.b2;
    let mut ng = (b - a).cross(c - a).normalize_or_zero();
    if ng.dot(d) > 0.0 {
        ng = -ng;
    }
    let n = mesh.normals[ia] * b0 + mesh.normals[ib] * hit.b1 + mesh.normals[ic] * hit.b2;
    let mut ns = n.normalize_or(ng);
    if ns.dot(ng) < 0.0 {
        ns = -ns;
    }
    let uv = mesh.uvs[ia] * b0 + mesh.uvs[ib] * hit.b1 + mesh.uvs[ic] * hit.b2;
    let color = mesh.colors[ia] * b0 + mesh.colors[ib] * hit.b1 + mesh.colors[ic] * hit.b2;
    let albedo = scene.materials[mesh.triangle_material[t] as usize].albedo_at(uv) * color;
    SurfacePoint {
        p,
        ng,
        ns,
        albedo,
        uv,
    }
}

/// What a ray sees first ([`Tracer::first_hit`]).
pub struct FirstHit {
    /// Distance from the ray's origin, metres.
    pub distance: f32,
    /// Shading normal facing the ray, world space.
    pub normal: Vec3,
    /// Albedo, linear RGB (texture, factor and vertex colour together).
    pub albedo: Vec3,
    /// glTF texture coordinates (not wrapped).
    pub uv: Vec2,
}

/// A ray origin just off the surface on the side of `n`, scaled to the coordinates' magnitude.
#[inline]
fn offset(p: Vec3, n: Vec3) -> Vec3 {
    p + n * (1e-4 * (1.0 + p.abs().max_element()))
}

/// Geometry, lights and settings of one render.
pub(super) struct Tracer<'a> {
    pub scene: &'a Scene,
    pub accel: &'a Accel,
    pub lights: &'a Lights,
    pub settings: &'a RenderSettings,
}

impl Tracer<'_> {
    /// Traces camera paths from `pixel`'s origin, one per unit direction of `dirs` (inside
    /// the pixel's bundle, [`crate::accel::Accel::bundle`]) with the sampler of the same index in `s`
    /// (at most [`LANES`]), and hands every emitter they reach to `acc`. Returns how many
    /// camera rays saw scene geometry (for the coverage mask). `lights_ahead` as for
    /// [`Tracer::light`].
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    pub fn trace<A: Accumulator>(
        &self,
        pixel: &Bundle,
        lights_ahead: bool,
        dirs: &[Vec3],
        s: &mut [PathSampler],
        scratch: &mut Scratch,
        acc: &A,
        px: &mut A::Pixel,
    ) -> u32 {
        let Scratch { verts, added } = scratch;
        let (t_first, len) = self.walk(pixel, dirs, s, false, verts);
        let mb = self.settings.max_bounces as usize;
        let paths: [Walked; LANES] = std::array::from_fn(|l| Walked {
            dir: dirs.get(l).copied().unwrap_or(Vec3::Z),
            t_first: t_first[l],
            verts: lane_vertices(verts, mb, l, len[l]),
        });
        self.light(
            pixel.origin(),
            lights_ahead,
            &paths[..dirs.len()],
            s,
            added,
            acc,
            px,
        )
    }

    /// The scattering vertices of camera paths from `pixel`'s origin, one per unit direction
    /// of `dirs` (at most [`LANES`], inside the pixel's bundle), BSDF directions from the
    /// sampler of the same index in `s`: lane `l`'s (at most `max_bounces`) at
    /// `out[l · max_bounces..][..len[l]]` (`out` is scratch space, grown as needed; the rest
    /// of each lane's stretch holds nothing of this call). With `trace_last` the last segment's geometry is
    /// found too (worth it for a path lit many times). Returns per lane the distance to the
    /// first surface (∞ if the camera ray sees none) and the number of vertices.
    ///
    /// The lanes advance together, a segment at a time: the surface lookups of their hits
    /// (triangle, then its corners' attributes: cache misses, mostly) then do not wait on
    /// each other, where one path after another would wait on every one in turn.
    #[inline(always)]
    pub fn walk(
        &self,
        pixel: &Bundle,
        dirs: &[Vec3],
        s: &mut [PathSampler],
        trace_last: bool,
        out: &mut Vec<Vertex>,
    ) -> ([f32; LANES], [usize; LANES]) {
        let mb = self.settings.max_bounces as usize;
        debug_assert!(dirs.len() <= LANES && s.len() >= dirs.len());
        let n = dirs.len().min(LANES);
        if out.len() < n * mb {
            out.resize(n * mb, Vertex::NONE);
        }
        let mut t_first = [f32::INFINITY; LANES];
        let mut len = [0usize; LANES];
        let mut throughput = [Vec3::ONE; LANES];
        // Per lane, the segment being traced: its direction and what it hit.
        let mut d = [Vec3::ZERO; LANES];
        let mut hits: [Option<Hit>; LANES] = [None; LANES];
        // One closest-hit query per segment; the camera rays' from the pixel's leaves.
        for l in 0..n {
            d[l] = dirs[l];
            hits[l] = self.accel.intersect_bundle(pixel, d[l], f32::INFINITY);
        }
        let mut going = (1u32 << n) - 1;
        for depth in 0..=mb {
            // The surface points of this depth's hits, and their BSDF samples' numbers.
            let mut shade = 0u32;
            let mut sp = [SurfacePoint::NONE; LANES];
            let mut u = [Vec2::ZERO; LANES];
            for l in set_bits(going) {
                let t = hits[l].map_or(f32::INFINITY, |h| h.t);
                if depth == 0 {
                    t_first[l] = t;
                } else {
                    out[l * mb + depth - 1].t_next = t;
                }
                let Some(hit) = hits[l] else { continue };
                if depth == mb {
                    continue;
                }
                sp[l] = surface_point(self.scene, &hit, d[l]);
                u[l] = s[l].bsdf_sample(depth);
                shade |= 1 << l;
            }
            // The BSDF directions of all lanes at once (a loop the compiler vectorises; idle
            // lanes compute and drop a direction about +Z).
            let wi: [Vec3; LANES] = std::array::from_fn(|l| cosine_hemisphere(sp[l].ns, u[l]));
            let mut next = 0u32;
            for l in set_bits(shade) {
                let (sp, wi) = (&sp[l], wi[l]);
                let mut v = Vertex {
                    p: sp.p,
                    ng: sp.ng,
                    ns: sp.ns,
                    throughput_f: throughput[l] * sp.albedo * INV_PI,
                    wi: Vec3::ZERO,
                    t_next: f32::NAN,
                };
                let pdf = wi.dot(sp.ns) * INV_PI;
                throughput[l] *= sp.albedo; // f · cos / pdf for a Lambertian
                let ends = wi.dot(sp.ng) <= 0.0 || pdf <= 0.0 || throughput[l] == Vec3::ZERO;
                if !ends {
                    v.wi = wi;
                }
                out[l * mb + depth] = v;
                len[l] += 1;
                let last = depth + 1 == mb;
                if ends || (last && !trace_last) {
                    continue;
                }
                d[l] = wi;
                next |= 1 << l;
            }
            going = next;
            if going == 0 {
                break;
            }
            for l in set_bits(going) {
                let v = &out[l * mb + depth];
                hits[l] = self.accel.intersect(offset(v.p, v.ng), d[l], f32::INFINITY);
            }
        }
        (t_first, len)
    }

    /// Lights walked camera paths from `origin` (at most [`LANES`], each with the sampler of
    /// the same index in `s`): next-event estimation at each vertex and the emitters its
    /// segments reach, handed to `acc`. An emitter in front of a vertex ends the path there.
    /// The paths advance together, a vertex at a time, so that the light samples of their
    /// vertices at one depth are drawn together ([`Lights::sample_lanes`]). Returns how many
    /// camera rays saw scene geometry before any emitter they test. `lights_ahead` false
    /// skips the camera rays' sphere tests: no camera ray meets a sphere light (the pixel's
    /// pyramid misses them all, [`super::pixels::pyramid_meets_lights`]), or they are to pass
    /// through lights ([`super::RenderSettings::camera_sees_lights`]). `added` is scratch
    /// space.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    pub fn light<A: Accumulator>(
        &self,
        origin: Vec3,
        lights_ahead: bool,
        paths: &[Walked],
        s: &mut [PathSampler],
        added: &mut Added,
        acc: &A,
        px: &mut A::Pixel,
    ) -> u32 {
        let (lights, st) = (self.lights, self.settings);
        // What each path delivers, kept by lane and handed to `acc` path by path at the end:
        // the pixel's sums then run in sample order, as if each path were lit alone.
        added.iter_mut().for_each(Vec::clear);
        let (use_light, use_bsdf) = match st.strategy {
            Strategy::Mis => (true, true),
            Strategy::LightOnly => (true, false),
            Strategy::BsdfOnly => (false, true),
        };
        let mis = use_light && use_bsdf;
        // One light alone is sampled as every light is: its pdf has no choice of light in it.
        let every_light = st.every_light || lights.alone.is_some();

        // ---- The camera rays: emitters seen directly ----
        let mut alive = [false; LANES];
        for (l, path) in paths.iter().enumerate() {
            let light_hit = lights_ahead
                .then(|| lights.intersect(origin, path.dir, 0.0, path.t_first))
                .flatten();
            let seen = match light_hit {
                Some((_, e)) => Some(e),
                None if path.t_first.is_infinite() => lights.escape(path.dir),
                None => None,
            };
            if let Some(e) = seen {
                if !st.hide_emitters {
                    added[l].push((e, path.dir, Vec3::ONE));
                }
                continue;
            }
            alive[l] = path.t_first.is_finite();
        }
        let hits = alive.iter().filter(|&&a| a).count() as u32;

        for k in 0..st.max_bounces as usize {
            // The paths still going at vertex k.
            let mut lanes = [0usize; LANES];
            let mut n = 0;
            for (l, path) in paths.iter().enumerate() {
                if alive[l] && k < path.verts.len() {
                    (lanes[n], n) = (l, n + 1);
                }
            }
            let lanes = &lanes[..n];
            if lanes.is_empty() {
                break;
            }

            // ---- Emitter sampling ----
            if use_light && every_light {
                // Every light gets the vertex's one sample (each light's estimate is
                // unbiased; their correlation biases nothing), so a light's share does not
                // depend on which others are sampled beside it ([`Lights::alone`]).
                let shared: [(Vec2, Vec2); LANES] = std::array::from_fn(|j| {
                    if j < n {
                        s[lanes[j]].light_sample(k)
                    } else {
                        Default::default()
                    }
                });
                let sampled = match lights.alone {
                    Some(i) => i as usize..i as usize + 1,
                    None => 0..lights.len(),
                };
                for i in sampled {
                    let mut q = LightQuery::default();
                    for (j, &l) in lanes.iter().enumerate() {
                        let (pick, u) = shared[j];
                        let v = &paths[l].verts[k];
                        q.push(v.p, v.ns, Vec2::new(0.0, pick.y), u);
                    }
                    let samples = lights.sample_lanes(&q, Some(i));
                    for (j, &l) in lanes.iter().enumerate() {
                        if let Some(ls) = &samples[j] {
                            self.shadow_ray(l, &paths[l].verts[k], ls, mis, added);
                        }
                    }
                }
            } else if use_light {
                let mut q = LightQuery::default();
                for &l in lanes {
                    let (u_light, u) = s[l].light_sample(k);
                    let v = &paths[l].verts[k];
                    q.push(v.p, v.ns, u_light, u);
                }
                let samples = lights.sample_lanes(&q, None);
                for (j, &l) in lanes.iter().enumerate() {
                    if let Some(ls) = &samples[j] {
                        self.shadow_ray(l, &paths[l].verts[k], ls, mis, added);
                    }
                }
            }

            // ---- BSDF sampling: the emitter each next segment reaches, if any ----
            for &l in lanes {
                let v = &paths[l].verts[k];
                if v.wi == Vec3::ZERO {
                    alive[l] = false;
                    continue;
                }
                let o = offset(v.p, v.ng);
                let light_hit = lights.intersect(o, v.wi, 0.0, f32::INFINITY);
                let reached = if v.t_next.is_nan() {
                    // Not traced: one occlusion test toward the emitter it would reach (no
                    // ray at all toward none, or without `use_bsdf`).
                    let target =
                        light_hit.or_else(|| lights.escape(v.wi).map(|e| (f32::INFINITY, e)));
                    target
                        .filter(|&(t, _)| use_bsdf && !self.accel.occluded(o, v.wi, t))
                        .map(|(_, e)| e)
                } else {
                    match light_hit {
                        Some((t, e)) if t < v.t_next => Some(e),
                        _ if v.t_next.is_infinite() => lights.escape(v.wi),
                        _ => None,
                    }
                };
                let Some(e) = reached else {
                    continue;
                };
                if use_bsdf {
                    let w = if mis {
                        let light_pdf = if every_light {
                            lights.pdf_light(e, v.p)
                        } else {
                            lights.pdf(e, v.p, v.ns)
                        };
                        power_heuristic(v.wi.dot(v.ns) * INV_PI, light_pdf)
                    } else {
                        1.0
                    };
                    // Throughput after the bounce: f · cos / pdf = albedo, i.e. π · f.
                    added[l].push((e, v.wi, v.throughput_f * std::f32::consts::PI * w));
                }
                alive[l] = false;
            }
        }
        for added in &added[..paths.len()] {
            for &(e, d, w) in added.iter().filter(|a| lights.delivers(a.0)) {
                acc.add(px, e, d, w);
            }
        }
        hits
    }

    /// Next-event estimation of one light sample at vertex `v` of path `lane`: a shadow ray,
    /// and if the light is visible its contribution, into `added`.
    #[inline(always)]
    fn shadow_ray(&self, lane: usize, v: &Vertex, ls: &LightSample, mis: bool, added: &mut Added) {
        let cos_s = ls.wi.dot(v.ns);
        if cos_s <= 0.0 || ls.wi.dot(v.ng) <= 0.0 {
            return;
        }
        // Aim from the offset origin at the sampled point on the emitter; the emitter itself
        // cannot block its own near side.
        let o_shadow = offset(v.p, v.ng);
        let (d_shadow, t_shadow) = if ls.dist.is_finite() {
            let to_light = v.p + ls.wi * ls.dist - o_shadow;
            let len = to_light.length();
            (to_light / len, len * (1.0 - 1e-4))
        } else {
            (ls.wi, f32::INFINITY)
        };
        if self.accel.occluded(o_shadow, d_shadow, t_shadow)
            || self
                .lights
                .occludes(o_shadow, d_shadow, t_shadow, ls.emitter)
        {
            return;
        }
        let w = if mis && !ls.delta {
            power_heuristic(ls.pdf, cos_s * INV_PI)
        } else {
            1.0
        };
        added[lane].push((ls.emitter, ls.wi, v.throughput_f * (cos_s * w / ls.pdf)));
    }

    /// The first surface the ray meets, or `None` if it sees no scene geometry.
    pub fn first_hit(&self, origin: Vec3, dir: Vec3) -> Option<FirstHit> {
        let t_light = self
            .lights
            .intersect(origin, dir, 0.0, f32::INFINITY)
            .map_or(f32::INFINITY, |h| h.0);
        let hit = self.accel.intersect(origin, dir, t_light)?;
        let sp = surface_point(self.scene, &hit, dir);
        Some(FirstHit {
            distance: hit.t,
            normal: sp.ns,
            albedo: sp.albedo,
            uv: sp.uv,
        })
    }

    /// The material of the first surface the ray meets (as [`Tracer::first_hit`] finds it),
    /// or `None` if it sees no scene geometry.
    pub fn first_material(&self, origin: Vec3, dir: Vec3) -> Option<u32> {
        let t_light = self
            .lights
            .intersect(origin, dir, 0.0, f32::INFINITY)
            .map_or(f32::INFINITY, |h| h.0);
        let hit = self.accel.intersect(origin, dir, t_light)?;
        Some(self.scene.mesh.triangle_material[hit.triangle as usize])
    }
}
