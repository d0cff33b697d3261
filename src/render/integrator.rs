//! The path tracer — the only one in lightprobe. Lambertian two-sided surfaces; next-event
//! estimation of the lights combined with cosine-weighted BSDF sampling by multiple importance
//! sampling (power heuristic). What a path delivers goes to an [`Accumulator`] as
//! (emitter, weight per unit emitted radiance), so the same tracer renders radiance or
//! accumulates derivatives with respect to each emitter.

use glam::{Vec2, Vec3};

use super::lights::{LightSample, Lights};
use super::sampling::{INV_PI, Rng, cosine_hemisphere, power_heuristic, r2};
use super::{Accumulator, RenderSettings, Strategy};
use crate::accel::{Accel, Hit};
use crate::scene::Scene;

/// The random numbers of one camera sample. The pixel jitter comes from a per-pixel-rotated
/// R2 sequence (stratified across the pixel's samples); everything else from PCG. (Drawing
/// further dimensions from the same R2 sequence would tie them to the pixel position: each
/// pixel's estimate would then converge to a shifted, wrong integral.)
pub(super) struct PathSampler {
    pub rng: Rng,
    pub index: u32,
    pub pixel_offset: Vec2,
}

impl PathSampler {
    #[inline]
    pub fn pixel_jitter(&self) -> Vec2 {
        r2(self.index, self.pixel_offset)
    }
}

/// Local geometry at a surface hit, with both normals facing the incoming ray.
struct SurfacePoint {
    p: Vec3,
    /// Geometric normal, facing the side the ray came from.
    ng: Vec3,
    /// Shading normal (interpolated), on the same side as `ng`.
    ns: Vec3,
    albedo: Vec3,
}

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
    let albedo = scene.materials[mesh.triangle_material[t] as usize].albedo_at(uv);
    SurfacePoint { p, ng, ns, albedo }
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
    /// Traces one camera path from `origin` along unit `dir`, handing every emitter it reaches
    /// to `acc`. Returns whether the camera ray hit scene geometry (for the coverage mask).
    pub fn trace<A: Accumulator>(
        &self,
        origin: Vec3,
        dir: Vec3,
        s: &mut PathSampler,
        acc: &A,
        px: &mut A::Pixel,
    ) -> bool {
        let (lights, st) = (self.lights, self.settings);
        let (use_light, use_bsdf) = match st.strategy {
            Strategy::Mis => (true, true),
            Strategy::LightOnly => (true, false),
            Strategy::BsdfOnly => (false, true),
        };
        let mis = use_light && use_bsdf;

        let (mut o, mut d) = (origin, dir);
        let mut throughput = Vec3::ONE;
        let mut depth = 0u32; // scattering events so far
        let (mut prev_p, mut prev_pdf_bsdf) = (origin, 0.0f32);
        let mut hit_geometry = false;
        loop {
            let light_hit = lights.intersect(o, d, 0.0, f32::INFINITY);
            let t_max = light_hit.map_or(f32::INFINITY, |h| h.0);
            let hit = if depth > 0 && depth == st.max_bounces {
                // The path's last segment only counts if it reaches an emitter: an occlusion
                // test toward that emitter replaces the closest-hit query, and most such
                // segments (those toward no sphere light, with no envmap) need no ray at all.
                let reaches = use_bsdf
                    && (light_hit.is_some() || lights.env.is_some())
                    && !self.accel.occluded(o, d, t_max);
                if !reaches {
                    break;
                }
                None
            } else {
                self.accel.intersect(o, d, t_max)
            };
            let Some(hit) = hit else {
                // ---- An emitter seen directly, or through BSDF sampling ----
                if let Some(e) = light_hit.map(|h| h.1).or_else(|| lights.escape(d)) {
                    if depth == 0 {
                        if !st.hide_emitters {
                            acc.add(px, e, throughput);
                        }
                    } else if use_bsdf {
                        let w = if mis {
                            let light_pdf = if st.every_light {
                                lights.pdf_light(e, prev_p)
                            } else {
                                lights.pdf(e, prev_p)
                            };
                            power_heuristic(prev_pdf_bsdf, light_pdf)
                        } else {
                            1.0
                        };
                        acc.add(px, e, throughput * w);
                    }
                }
                break;
            };
            if depth == 0 {
                hit_geometry = true;
            }
            if depth == st.max_bounces {
                break;
            }
            depth += 1;
            let sp = surface_point(self.scene, &hit, d);
            let f = sp.albedo * INV_PI;

            // ---- Emitter sampling ----
            if use_light && st.every_light {
                for i in 0..lights.len() {
                    let (u_cell, u) = (s.rng.next_f32(), s.rng.next_2d());
                    if let Some(ls) = lights.sample_light(i, sp.p, u_cell, u) {
                        self.shadow_ray(&sp, &ls, mis, throughput * f, acc, px);
                    }
                }
            } else if use_light {
                let (u_light, u) = (s.rng.next_2d(), s.rng.next_2d());
                if let Some(ls) = lights.sample(sp.p, u_light, u) {
                    self.shadow_ray(&sp, &ls, mis, throughput * f, acc, px);
                }
            }

            // ---- BSDF sampling ----
            let wi = cosine_hemisphere(sp.ns, s.rng.next_2d());
            let pdf = wi.dot(sp.ns) * INV_PI;
            if wi.dot(sp.ng) <= 0.0 || pdf <= 0.0 {
                break;
            }
            throughput *= sp.albedo; // f · cos / pdf for a Lambertian
            if throughput == Vec3::ZERO {
                break;
            }
            prev_p = sp.p;
            prev_pdf_bsdf = pdf;
            o = offset(sp.p, sp.ng);
            d = wi;
        }
        hit_geometry
    }

    /// Next-event estimation of one light sample: a shadow ray, and if the light is visible
    /// its contribution, `throughput_f` being the path throughput times the BSDF.
    #[inline]
    fn shadow_ray<A: Accumulator>(
        &self,
        sp: &SurfacePoint,
        ls: &LightSample,
        mis: bool,
        throughput_f: Vec3,
        acc: &A,
        px: &mut A::Pixel,
    ) {
        let cos_s = ls.wi.dot(sp.ns);
        if cos_s <= 0.0 || ls.wi.dot(sp.ng) <= 0.0 {
            return;
        }
        // Aim from the offset origin at the sampled point on the emitter; the emitter itself
        // cannot block its own near side.
        let o_shadow = offset(sp.p, sp.ng);
        let (d_shadow, t_shadow) = if ls.dist.is_finite() {
            let to_light = sp.p + ls.wi * ls.dist - o_shadow;
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
        let w = if mis {
            power_heuristic(ls.pdf, cos_s * INV_PI)
        } else {
            1.0
        };
        acc.add(px, ls.emitter, throughput_f * (cos_s * w / ls.pdf));
    }

    /// Per-pixel-centre geometry for checking: (distance to the first hit in metres, shading
    /// normal facing the camera, albedo), or `None` if the ray sees no scene geometry.
    pub fn first_hit(&self, origin: Vec3, dir: Vec3) -> Option<(f32, Vec3, Vec3)> {
        let t_light = self
            .lights
            .intersect(origin, dir, 0.0, f32::INFINITY)
            .map_or(f32::INFINITY, |h| h.0);
        let hit = self.accel.intersect(origin, dir, t_light)?;
        let sp = surface_point(self.scene, &hit, dir);
        Some((hit.t, sp.ns, sp.albedo))
    }
}
