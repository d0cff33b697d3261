//! The lights a path can reach: spherical area lights and the ring environment map. Each kind
//! keeps sampling, pdf and evaluation side by side.
//!
//! Sphere lights are sampled uniformly in the cone they subtend (pbrt's "sample by solid
//! angle"), point lights (radius 0) in their one direction; the envmap by its cell
//! distribution. A light is picked in proportion to how
//! strongly it lights the shading point (luminance × solid angle); pdfs are per unit solid
//! angle at the shading point and include the probability of picking the light.

use glam::{Vec2, Vec3};

use crate::envmap::Envmap;
use crate::sampling::{ONE_MINUS_EPS, uniform_cone};
use crate::scene::SphereLight;

/// Which emitter a path reached. Transport is linear in each emitter's radiance, so
/// accumulators receive this plus a weight per unit of emitted radiance.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Emitter {
    /// Sphere light `i` of [`Lights::spheres`].
    Sphere(u32),
    /// Cell `c` of the environment map.
    EnvCell(u32),
}

/// A sampled direction toward a light.
#[derive(Debug, Clone, Copy)]
pub struct LightSample {
    pub emitter: Emitter,
    /// Unit direction from the shading point, world space.
    pub wi: Vec3,
    /// Distance to the emitting surface, metres (infinite for the envmap).
    pub dist: f32,
    /// Probability density per unit solid angle (including the choice of light). For a point
    /// light, which has no density, d² times the choice's probability: so that the intensity
    /// over `pdf` is the irradiance factor I/d² of that choice.
    pub pdf: f32,
    /// A point light: no other strategy can reach it, so multiple importance sampling gives
    /// this sample the whole weight.
    pub delta: bool,
}

/// The set of lights of a render.
#[derive(Debug, Clone, Default)]
pub struct Lights {
    pub spheres: Vec<SphereLight>,
    /// Light from infinitely far away; rays that escape the scene see it.
    pub env: Option<Envmap>,
    /// Sphere `i` alone emits: the other spheres still block light, but are neither sampled
    /// nor delivered, and the envmap delivers nothing. One light's share of a render (its
    /// column of a transport) at the cost of one light, with the random numbers it gets
    /// among all of them under [`super::RenderSettings::every_light`].
    pub alone: Option<u32>,
}

/// Shading points whose light samples are drawn together ([`Lights::sample_lanes`]): eight
/// f32 lanes fill a 256-bit vector register.
pub const LANES: usize = 8;

/// Up to [`LANES`] shading points and their sample numbers, structure of arrays (lane `l` of
/// each field belongs to point `l`).
#[derive(Debug, Clone, Copy, Default)]
pub struct LightQuery {
    /// Lanes in use, `0..len`.
    pub len: usize,
    /// Position, world space (metres), per axis.
    pub p: [[f32; LANES]; 3],
    /// Unit shading normal, world space, per axis.
    pub n: [[f32; LANES]; 3],
    /// The pick's numbers and the direction's ([`Lights::sample`]).
    pub u_light: [[f32; LANES]; 2],
    pub u: [[f32; LANES]; 2],
}

impl LightQuery {
    /// Adds a point in the next lane (at most [`LANES`]).
    #[inline]
    pub fn push(&mut self, p: Vec3, n: Vec3, u_light: Vec2, u: Vec2) {
        let l = self.len;
        (self.p[0][l], self.p[1][l], self.p[2][l]) = (p.x, p.y, p.z);
        (self.n[0][l], self.n[1][l], self.n[2][l]) = (n.x, n.y, n.z);
        (self.u_light[0][l], self.u_light[1][l]) = (u_light.x, u_light.y);
        (self.u[0][l], self.u[1][l]) = (u.x, u.y);
        self.len += 1;
    }

    #[inline(always)]
    fn p(&self, l: usize) -> Vec3 {
        Vec3::new(self.p[0][l], self.p[1][l], self.p[2][l])
    }

    #[inline(always)]
    fn n(&self, l: usize) -> Vec3 {
        Vec3::new(self.n[0][l], self.n[1][l], self.n[2][l])
    }
}

/// Up to this many lights are picked by how strongly they light the shading point; more are
/// picked uniformly (the weights would cost more than they save).
pub const MAX_WEIGHTED: usize = 16;

impl Lights {
    /// Sphere lights only.
    pub fn new(spheres: Vec<SphereLight>) -> Lights {
        Lights {
            spheres,
            env: None,
            alone: None,
        }
    }

    /// An environment map only.
    pub fn env(env: Envmap) -> Lights {
        Lights {
            spheres: Vec::new(),
            env: Some(env),
            alone: None,
        }
    }

    /// Lights to sample: each sphere, and the envmap as one (index `len() - 1`).
    pub fn len(&self) -> usize {
        self.spheres.len() + self.env.is_some() as usize
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Whether `emitter` delivers light in this render ([`Lights::alone`]).
    #[inline]
    pub fn delivers(&self, emitter: Emitter) -> bool {
        self.alone.is_none_or(|i| emitter == Emitter::Sphere(i))
    }

    /// Emitted radiance of `emitter` (linear RGB).
    #[inline]
    pub fn radiance(&self, emitter: Emitter) -> Vec3 {
        match emitter {
            Emitter::Sphere(i) => self.spheres[i as usize].radiance,
            Emitter::EnvCell(c) => self
                .env
                .as_ref()
                .map_or(Vec3::ZERO, |e| e.radiance()[c as usize]),
        }
    }

    /// How likely each light is to be picked at `p` with shading normal `n`: in proportion to
    /// how strongly it can light `p` — luminance × the solid angle a sphere subtends there ×
    /// the largest cosine to `n` over that cone (zero for a sphere wholly below the horizon,
    /// which lights nothing there), and the envmap's Σ luminance × Ω — so a dim or
    /// grazing light beside a bright one costs the bright one few samples. Uniform when every
    /// weight is zero, or beyond [`MAX_WEIGHTED`] lights. Index `len()` holds the total.
    #[inline]
    fn pick_weights(&self, p: Vec3, n: Vec3) -> Option<[f32; MAX_WEIGHTED + 1]> {
        let count = self.len();
        if count > MAX_WEIGHTED {
            return None;
        }
        let mut w = [0.0f32; MAX_WEIGHTED + 1];
        for (i, s) in self.spheres.iter().enumerate() {
            w[i] = pick_weight(s, p, n);
        }
        if let Some(env) = &self.env {
            w[count - 1] = env.luminance_integral().max(0.0);
        }
        let total: f32 = w[..count].iter().sum();
        (total > 0.0 && total.is_finite()).then(|| {
            w[count] = total;
            w
        })
    }

    /// The probability of picking light `i` at `p` with shading normal `n`.
    #[inline]
    fn pick_pdf(&self, i: usize, p: Vec3, n: Vec3) -> f32 {
        match self.pick_weights(p, n) {
            Some(w) => w[i] / w[self.len()],
            None => 1.0 / self.len() as f32,
        }
    }

    /// Picks a light for the point `p` with shading normal `n` with `u_light.x`
    /// ([`Lights::pick_weights`]), then a direction to it: to a sphere with where `u_light.x`
    /// fell in its share (rescaled) and `u_light.y`; into the envmap, a cell with `u_light.y`
    /// and a direction in it with `u`. One lane of [`Lights::sample_lanes`].
    #[inline]
    pub fn sample(&self, p: Vec3, n: Vec3, u_light: Vec2, u: Vec2) -> Option<LightSample> {
        let mut q = LightQuery::default();
        q.push(p, n, u_light, u);
        self.sample_lanes(&q, None)[0]
    }

    /// A direction toward light `i` alone (sphere `i`, or the envmap at `len() - 1`, its cell
    /// picked with `u_cell`), its pdf excluding any choice of light: next-event estimation
    /// that samples every light ([`super::RenderSettings::every_light`]). One lane of
    /// [`Lights::sample_lanes`].
    #[inline]
    pub fn sample_light(&self, i: usize, p: Vec3, u_cell: f32, u: Vec2) -> Option<LightSample> {
        let mut q = LightQuery::default();
        q.push(p, Vec3::Z, Vec2::new(0.0, u_cell), u);
        self.sample_lanes(&q, Some(i))[0]
    }

    /// [`Lights::sample`] at each point of `q` (`only: None`), or [`Lights::sample_light`] of
    /// light `i` (`only: Some(i)`, `u_light.y` picking the envmap cell). Lanes past `q.len`
    /// get `None`. The arithmetic runs on all lanes at once, in loops over lanes the compiler
    /// vectorises; only the envmap's cell search is done lane by lane.
    #[inline(always)]
    pub fn sample_lanes(
        &self,
        q: &LightQuery,
        only: Option<usize>,
    ) -> [Option<LightSample>; LANES] {
        let mut out = [None; LANES];
        let count = self.len();
        if count == 0 || q.len == 0 {
            return out;
        }
        // Per lane: the light, the probability it was picked, the direction's numbers.
        let (mut pick, mut prob, mut u) = ([0usize; LANES], [1.0f32; LANES], q.u);
        match only {
            Some(i) => pick = [i.min(count - 1); LANES],
            None => self.pick_lanes(q, &mut pick, &mut prob, &mut u),
        }

        let spheres = self.spheres.len();
        if spheres > 0 {
            // The picked sphere of each lane (the first where the envmap was picked: that
            // lane's cone is computed and thrown away).
            let (mut center, mut radius) = ([[0.0f32; LANES]; 3], [0.0f32; LANES]);
            for l in 0..LANES {
                let s = &self.spheres[pick[l].min(spheres - 1)];
                (center[0][l], center[1][l], center[2][l]) = (s.center.x, s.center.y, s.center.z);
                radius[l] = s.radius;
            }
            let mut wi = [[0.0f32; LANES]; 3];
            let (mut dist, mut pdf, mut inside) = ([0.0f32; LANES], [0.0f32; LANES], [true; LANES]);
            for l in 0..LANES {
                let c = Vec3::new(center[0][l], center[1][l], center[2][l]);
                let cone = Cone::at(c, radius[l], q.p(l));
                let (w, d, f) = cone.sample(radius[l], Vec2::new(u[0][l], u[1][l]));
                (wi[0][l], wi[1][l], wi[2][l]) = (w.x, w.y, w.z);
                (dist[l], pdf[l], inside[l]) = (d, f * prob[l], cone.inside);
            }
            for l in 0..q.len {
                if pick[l] < spheres && !inside[l] {
                    out[l] = Some(LightSample {
                        emitter: Emitter::Sphere(pick[l] as u32),
                        wi: Vec3::new(wi[0][l], wi[1][l], wi[2][l]),
                        dist: dist[l],
                        pdf: pdf[l],
                        delta: radius[l] == 0.0,
                    });
                }
            }
        }
        if let Some(env) = &self.env {
            for l in (0..q.len).filter(|&l| pick[l] == count - 1) {
                let (cell, wi, pdf) = env.sample(q.u_light[1][l], Vec2::new(u[0][l], u[1][l]));
                out[l] = Some(LightSample {
                    emitter: Emitter::EnvCell(cell),
                    wi,
                    dist: f32::INFINITY,
                    pdf: pdf * prob[l],
                    delta: false,
                });
            }
        }
        out
    }

    /// The light each lane of `q` picks with `u_light.x` ([`Lights::pick_weights`]), the
    /// probability of that pick, and for a sphere picked often enough, its direction numbers:
    /// where `u_light.x` fell within the sphere's share (rescaled to [0, 1)) and `u_light.y`.
    /// So the samples that pick a sphere keep that pair's stratification; the other pair's
    /// points would be a random subset. Not for a light picked rarely: its share of the f32
    /// `u_light.x` holds too few distinct values.
    #[inline(always)]
    fn pick_lanes(
        &self,
        q: &LightQuery,
        pick: &mut [usize; LANES],
        prob: &mut [f32; LANES],
        u: &mut [[f32; LANES]; 2],
    ) {
        let count = self.len();
        let mut within = [0.0f32; LANES];
        // Uniform picks (too many lights to weigh, or weights all zero) where needed.
        let uniform = |l: usize,
                       pick: &mut [usize; LANES],
                       prob: &mut [f32; LANES],
                       within: &mut [f32; LANES]| {
            let x = q.u_light[0][l] * count as f32;
            pick[l] = (x as usize).min(count - 1);
            prob[l] = 1.0 / count as f32;
            within[l] = x - pick[l] as f32;
        };
        if count > MAX_WEIGHTED {
            (0..LANES).for_each(|l| uniform(l, pick, prob, &mut within));
        } else {
            let mut w = [[0.0f32; LANES]; MAX_WEIGHTED];
            for (wi, s) in w.iter_mut().zip(&self.spheres) {
                *wi = std::array::from_fn(|l| pick_weight(s, q.p(l), q.n(l)));
            }
            if let Some(env) = &self.env {
                w[count - 1] = [env.luminance_integral().max(0.0); LANES];
            }
            let mut total = [0.0f32; LANES];
            for wi in &w[..count] {
                (0..LANES).for_each(|l| total[l] += wi[l]);
            }
            // The first light whose running sum passes the target, with the sum before it;
            // rounding can leave none, then the last light of nonzero weight.
            let target: [f32; LANES] = std::array::from_fn(|l| q.u_light[0][l] * total[l]);
            let (mut sum, mut found) = ([0.0f32; LANES], [false; LANES]);
            let (mut below, mut last, mut below_last) =
                ([0.0f32; LANES], [0usize; LANES], [0.0f32; LANES]);
            for (i, wi) in w[..count].iter().enumerate() {
                for l in 0..LANES {
                    let before = sum[l];
                    sum[l] += wi[l];
                    let take = !found[l] && target[l] < sum[l] && wi[l] > 0.0;
                    if take {
                        (pick[l], below[l], found[l]) = (i, before, true);
                    }
                    if wi[l] > 0.0 {
                        (last[l], below_last[l]) = (i, before);
                    }
                }
            }
            for l in 0..LANES {
                if !(total[l] > 0.0 && total[l].is_finite()) {
                    uniform(l, pick, prob, &mut within);
                    continue;
                }
                if !found[l] {
                    (pick[l], below[l]) = (last[l], below_last[l]);
                }
                let wp = w[pick[l]][l];
                prob[l] = wp / total[l];
                within[l] = (target[l] - below[l]) / wp;
            }
        }
        for l in 0..LANES {
            if pick[l] < self.spheres.len() && prob[l] >= 1.0 / 4096.0 {
                u[0][l] = within[l].clamp(0.0, ONE_MINUS_EPS);
                u[1][l] = q.u_light[1][l];
            }
        }
    }

    /// The pdf [`Lights::sample`] has for reaching `emitter` (in a direction that does reach
    /// it) from `p`.
    #[inline(always)]
    pub fn pdf(&self, emitter: Emitter, p: Vec3, n: Vec3) -> f32 {
        let i = match emitter {
            Emitter::Sphere(i) => i as usize,
            Emitter::EnvCell(_) => self.len() - 1,
        };
        self.pdf_light(emitter, p) * self.pick_pdf(i, p, n)
    }

    /// The pdf [`Lights::sample_light`] has for reaching `emitter` from `p`.
    #[inline]
    pub fn pdf_light(&self, emitter: Emitter, p: Vec3) -> f32 {
        match emitter {
            Emitter::Sphere(i) => cone_pdf(&self.spheres[i as usize], p),
            Emitter::EnvCell(c) => self.env.as_ref().map_or(0.0, |e| e.pdf(c)),
        }
    }

    /// The envmap cell a ray escaping in unit direction `d` sees, if there is an envmap.
    #[inline]
    pub fn escape(&self, d: Vec3) -> Option<Emitter> {
        self.env
            .as_ref()
            .map(|e| Emitter::EnvCell(e.grid.lookup(d)))
    }

    /// The closest sphere light along a unit ray within (t_min, t_max).
    #[inline]
    pub fn intersect(&self, o: Vec3, d: Vec3, t_min: f32, t_max: f32) -> Option<(f32, Emitter)> {
        let mut best: Option<(f32, Emitter)> = None;
        for (i, s) in self.spheres.iter().enumerate() {
            if let Some(t) = intersect_sphere(s, o, d, t_min)
                && t < best.map_or(t_max, |b| b.0)
            {
                best = Some((t, Emitter::Sphere(i as u32)));
            }
        }
        best
    }
}

impl Lights {
    /// True if an emitter other than `except` lies on the unit ray within (0, t_max).
    #[inline]
    pub fn occludes(&self, o: Vec3, d: Vec3, t_max: f32, except: Emitter) -> bool {
        self.spheres.iter().enumerate().any(|(i, s)| {
            Emitter::Sphere(i as u32) != except
                && intersect_sphere(s, o, d, 0.0).is_some_and(|t| t < t_max)
        })
    }
}

/// The cone a sphere light subtends from a point outside it, with what sampling, pdfs and
/// pick weights need (computed once per point and light).
#[derive(Debug, Clone, Copy)]
struct Cone {
    /// Unit direction from the point to the centre (world space).
    axis: Vec3,
    /// Distance to the centre, metres.
    dist: f32,
    /// `1 − cos α` of the half-angle α, kept as such for tiny cones; and sin α, cos α.
    omc: f32,
    sin_a: f32,
    cos_a: f32,
    /// The point is inside the sphere (or on it): there is no cone, and the other fields are
    /// meaningless.
    inside: bool,
    /// The light is a point (radius 0): the cone is its axis alone.
    point: bool,
}

impl Cone {
    /// The cone of `s` from `p`, or `None` from inside it.
    #[inline]
    fn of(s: &SphereLight, p: Vec3) -> Option<Cone> {
        let c = Cone::at(s.center, s.radius, p);
        (!c.inside).then_some(c)
    }

    /// The cone of the sphere (`center`, `radius`) from `p`, without branches (so that loops
    /// over lanes vectorise): check `inside`.
    #[inline(always)]
    fn at(center: Vec3, radius: f32, p: Vec3) -> Cone {
        let to_c = center - p;
        let d2 = to_c.length_squared();
        let r2 = radius * radius;
        let inside = d2 <= r2 * 1.0001;
        let d2 = d2.max(f32::MIN_POSITIVE);
        let dist = d2.sqrt();
        let sin2 = (r2 / d2).min(1.0);
        let cos_a = (1.0 - sin2).sqrt();
        Cone {
            axis: to_c / dist,
            dist,
            omc: sin2 / (1.0 + cos_a),
            sin_a: radius / dist,
            cos_a,
            inside,
            point: radius == 0.0,
        }
    }

    /// The largest cosine between unit `n` and a direction in the cone, clamped at zero:
    /// cos(max(θ − α, 0)) for the axis' angle θ from `n`.
    #[inline]
    fn max_cosine(&self, n: Vec3) -> f32 {
        let cos_t = n.dot(self.axis).clamp(-1.0, 1.0);
        let sin_t = (1.0 - cos_t * cos_t).max(0.0).sqrt();
        let rim = (cos_t * self.cos_a + sin_t * self.sin_a).max(0.0);
        // 1 where n points into the cone.
        if cos_t >= self.cos_a { 1.0 } else { rim }
    }

    /// The solid angle of the cone, 2π(1 − cos α), sr; for a point light 1/d², m⁻² (what
    /// turns its intensity into irradiance, as the solid angle turns a sphere's radiance).
    #[inline]
    fn solid_angle(&self) -> f32 {
        // Both computed, one chosen: a select, so that loops over lanes stay vectorised.
        let (sphere, point) = (
            std::f32::consts::TAU * self.omc,
            1.0 / (self.dist * self.dist),
        );
        if self.point { point } else { sphere }
    }

    /// Pdf per unit solid angle of uniform cone sampling; for a point light d²
    /// ([`LightSample::pdf`]).
    #[inline]
    fn pdf(&self) -> f32 {
        1.0 / self.solid_angle()
    }

    /// A uniform direction in the cone from `u`: (direction, distance to the surface of the
    /// sphere of `radius`, pdf).
    #[inline]
    fn sample(&self, radius: f32, u: Vec2) -> (Vec3, f32, f32) {
        let wi = uniform_cone(self.axis, self.omc, u);
        // Distance to the near surface along wi (clamped for directions grazing the rim).
        let (d, cos_t) = (self.dist, wi.dot(self.axis));
        let perp2 = (d * d * (1.0 - cos_t * cos_t)).max(0.0);
        let dist = d * cos_t - (radius * radius - perp2).max(0.0).sqrt();
        (wi, dist.max(0.0), self.pdf())
    }
}

/// How strongly sphere `s` can light the point `p` with shading normal `n`, the weight of
/// its pick ([`Lights::pick_weights`]): luminance × solid angle × the largest cosine over
/// the cone, zero from inside.
#[inline(always)]
fn pick_weight(s: &SphereLight, p: Vec3, n: Vec3) -> f32 {
    let c = Cone::at(s.center, s.radius, p);
    let lum = crate::imageio::luminance(s.radiance).max(0.0);
    // Each kind in its own order of operations (a shared factor would reorder the sphere's
    // product, and with it the rounding of every sphere-lit image).
    let cos = c.max_cosine(n);
    let (sphere, point) = (
        lum * std::f32::consts::TAU * c.omc * cos,
        lum / (c.dist * c.dist) * cos,
    );
    let w = if c.point { point } else { sphere };
    if c.inside { 0.0 } else { w }
}

/// `1 − cos θmax` of the cone a sphere subtends from `p`, or `None` from inside it.
#[cfg(test)]
fn one_minus_cos_max(s: &SphereLight, p: Vec3) -> Option<f32> {
    Cone::of(s, p).map(|c| c.omc)
}

/// The largest cosine between unit `n` and a direction from `p` to a point of `s`, clamped
/// at zero (`p` outside `s`).
#[cfg(test)]
fn max_cosine(s: &SphereLight, p: Vec3, n: Vec3) -> f32 {
    Cone::of(s, p).map_or(0.0, |c| c.max_cosine(n))
}

/// Samples the cone subtended by `s` from `p`: (direction, distance to the surface, pdf).
#[inline]
pub fn sample_sphere(s: &SphereLight, p: Vec3, u: Vec2) -> Option<(Vec3, f32, f32)> {
    Cone::of(s, p).map(|c| c.sample(s.radius, u))
}

/// The cone-sampling pdf of any direction that hits `s` from `p` (0 from inside, and for a
/// point light, which no direction hits).
#[inline]
pub fn cone_pdf(s: &SphereLight, p: Vec3) -> f32 {
    Cone::of(s, p).filter(|c| !c.point).map_or(0.0, |c| c.pdf())
}

/// The first crossing of a unit ray with the sphere's surface beyond `t_min` (none for a point
/// light: it has no surface).
#[inline]
pub fn intersect_sphere(s: &SphereLight, o: Vec3, d: Vec3, t_min: f32) -> Option<f32> {
    let oc = o - s.center;
    let b = oc.dot(d);
    // r² − |oc − b·d|² is the discriminant, computed without the cancellation of b² − c. A
    // point light's is never positive; a sphere's is zero only for rays that graze it.
    let perp = oc - b * d;
    let disc = s.radius * s.radius - perp.length_squared();
    if disc <= 0.0 {
        return None;
    }
    let q = disc.sqrt();
    let (t0, t1) = (-b - q, -b + q);
    if t0 > t_min {
        Some(t0)
    } else if t1 > t_min {
        Some(t1)
    } else {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::envmap::RingGrid;
    use crate::sampling::Rng;

    fn light() -> SphereLight {
        SphereLight {
            center: Vec3::new(0.3, 2.0, -0.5),
            radius: 0.4,
            radiance: Vec3::ONE,
        }
    }

    /// `n` light samples at the origin with normal +Y, each checked against [`Lights::pdf`],
    /// with the index of the sphere picked.
    fn draws(lights: &Lights, n: usize, seed: u64) -> Vec<(usize, LightSample)> {
        let mut rng = Rng::new(seed);
        (0..n)
            .map(|_| {
                let s = lights
                    .sample(Vec3::ZERO, Vec3::Y, rng.next_2d(), rng.next_2d())
                    .expect("a sample");
                let back = lights.pdf(s.emitter, Vec3::ZERO, Vec3::Y);
                assert!((back - s.pdf).abs() <= 1e-4 * s.pdf, "{back} vs {}", s.pdf);
                let Emitter::Sphere(i) = s.emitter else {
                    panic!("no envmap here")
                };
                (i as usize, s)
            })
            .collect()
    }

    /// How often each of three lights was picked.
    fn counts(draws: &[(usize, LightSample)]) -> [usize; 3] {
        let mut counts = [0; 3];
        draws.iter().for_each(|&(i, _)| counts[i] += 1);
        counts
    }

    #[test]
    fn lights_are_picked_by_how_strongly_they_light_the_point() {
        // Same size and distance, one 9× brighter in luminance: picked 9× as often, and the
        // pdf a sample reports is the one `pdf` gives for it (at the origin).
        let bright = SphereLight {
            center: Vec3::new(1.0, 2.0, 0.0),
            radius: 0.3,
            radiance: Vec3::splat(9.0),
        };
        let dim = SphereLight {
            center: Vec3::new(-1.0, 2.0, 0.0),
            radiance: Vec3::ONE,
            ..bright
        };
        let zero = SphereLight {
            center: Vec3::new(0.0, 2.0, 1.0),
            radiance: Vec3::ZERO,
            ..bright
        };
        let lights = Lights::new(vec![bright, dim, zero]);
        let counts = counts(&draws(&lights, 20_000, 34));
        assert_eq!(counts[2], 0, "a black light is never picked: {counts:?}");
        let ratio = counts[0] as f64 / counts[1] as f64;
        assert!((ratio - 9.0).abs() < 0.6, "{counts:?}");
    }

    #[test]
    fn a_light_below_the_horizon_is_never_picked_and_grazing_ones_seldom() {
        // Three equal lights seen from a point with normal +Y: one overhead, one just above
        // the horizon, one below it. The pick follows the largest cosine over each cone.
        let p = Vec3::ZERO;
        let at = |c: Vec3| SphereLight {
            center: c,
            radius: 0.2,
            radiance: Vec3::ONE,
        };
        let lights = Lights::new(vec![
            at(Vec3::new(0.0, 2.0, 0.0)),
            at(Vec3::new(2.0, 0.5, 0.0)),
            at(Vec3::new(0.0, -0.5, 2.0)),
        ]);
        let counts = counts(&draws(&lights, 40_000, 5));
        assert_eq!(counts[2], 0, "{counts:?}");
        // The grazing light's best cosine is sin(14.0° + 5.6°) = 0.336 (the overhead one's
        // is 1), times the ratio of their solid angles (0.94).
        let d = Vec3::new(2.0, 0.5, 0.0).length();
        let best = ((0.5 / d).asin() + (0.2 / d).asin()).sin();
        let omc = |i: usize| one_minus_cos_max(&lights.spheres[i], p).unwrap();
        let want = (best * omc(1) / omc(0)) as f64;
        let ratio = counts[1] as f64 / counts[0] as f64;
        assert!((ratio / want - 1.0).abs() < 0.05, "{counts:?} {want}");
    }

    #[test]
    fn each_picked_light_gets_uniform_directions_in_its_cone() {
        // The direction reuses the pick's number rescaled to the light's share: for every
        // light, 1 − cos θ from the cone's axis must stay uniform on [0, 1 − cos α] (mean 1/2,
        // mean square 1/3 in units of 1 − cos α), whatever its share.
        let p = Vec3::ZERO;
        let at = |c: Vec3, l: f32| SphereLight {
            center: c,
            radius: 0.3,
            radiance: Vec3::splat(l),
        };
        let lights = Lights::new(vec![
            at(Vec3::new(0.0, 2.0, 0.0), 1.0),
            at(Vec3::new(1.5, 1.5, 0.0), 5.0),
            at(Vec3::new(-1.0, 0.4, 1.0), 2.0),
        ]);
        let mut moments = [(0.0f64, 0.0f64, 0usize); 3];
        for (i, ls) in draws(&lights, 60_000, 21) {
            let cone = Cone::of(&lights.spheres[i], p).unwrap();
            let x = ((1.0 - ls.wi.dot(cone.axis) as f64) / cone.omc as f64).clamp(0.0, 1.0);
            let m = &mut moments[i];
            *m = (m.0 + x, m.1 + x * x, m.2 + 1);
        }
        for (i, (s1, s2, n)) in moments.into_iter().enumerate() {
            assert!(n > 5000, "light {i} picked {n} times");
            let (mean, square) = (s1 / n as f64, s2 / n as f64);
            assert!((mean - 0.5).abs() < 0.02, "light {i}: mean {mean}");
            assert!(
                (square - 1.0 / 3.0).abs() < 0.02,
                "light {i}: mean square {square}"
            );
        }
    }

    #[test]
    fn max_cosine_bounds_every_direction_to_the_sphere() {
        let mut r = Rng::new(9);
        for _ in 0..200 {
            let s = SphereLight {
                center: crate::sampling::uniform_sphere(r.next_2d()) * 2.0,
                radius: 0.1 + r.next_f32(),
                radiance: Vec3::ONE,
            };
            let p = Vec3::new(r.next_f32(), r.next_f32(), r.next_f32()) * 0.2;
            let n = crate::sampling::uniform_sphere(r.next_2d());
            let bound = max_cosine(&s, p, n);
            let mut seen = 0.0f32;
            for _ in 0..2000 {
                let (wi, _, _) = sample_sphere(&s, p, r.next_2d()).unwrap();
                seen = seen.max(wi.dot(n));
            }
            assert!(
                seen <= bound + 1e-5,
                "a direction beats the bound: {seen} > {bound}"
            );
            assert!(
                bound - seen.max(0.0) < 0.02,
                "loose bound: {bound} vs {seen}"
            );
        }
    }

    #[test]
    fn samples_land_on_the_sphere() {
        let s = light();
        let p = Vec3::new(0.1, 0.0, 0.2);
        let mut r = Rng::new(1);
        for _ in 0..10_000 {
            let (wi, dist, pdf) = sample_sphere(&s, p, r.next_2d()).unwrap();
            let q = p + wi * dist;
            assert!(((q - s.center).length() - s.radius).abs() < 1e-4);
            let t = intersect_sphere(&s, p, wi, 0.0).unwrap();
            assert!((t - dist).abs() < 1e-3, "{t} {dist}");
            assert!((pdf - cone_pdf(&s, p)).abs() < 1e-3 * pdf);
        }
    }

    #[test]
    fn cone_pdf_integrates_to_one_over_the_sphere_silhouette() {
        // Monte Carlo over uniform directions: ∫ pdf · 1[hits] dω = 1. A large sphere, so that
        // ~6% of directions hit it and the 2% bound is about 3σ.
        let s = SphereLight {
            radius: 1.0,
            ..light()
        };
        let p = Vec3::new(0.1, 0.0, 0.2);
        let mut r = Rng::new(2);
        let n = 400_000;
        let mut acc = 0.0f64;
        for _ in 0..n {
            let w = crate::sampling::uniform_sphere(r.next_2d());
            if intersect_sphere(&s, p, w, 0.0).is_some() {
                acc += cone_pdf(&s, p) as f64 * 4.0 * std::f64::consts::PI;
            }
        }
        assert!((acc / n as f64 - 1.0).abs() < 0.02, "{}", acc / n as f64);
    }

    #[test]
    fn inside_has_no_sample_and_zero_pdf() {
        let s = light();
        assert!(sample_sphere(&s, s.center, Vec2::splat(0.5)).is_none());
        assert_eq!(cone_pdf(&s, s.center + Vec3::X * 0.1), 0.0);
    }

    #[test]
    fn lanes_sample_as_each_point_alone() {
        // Eight points at once give each point the sample it gets alone, whichever light
        // (or none, from inside a sphere) each lane picks: the lanes do not leak into each
        // other. Three spheres and an envmap, all picks and `sample_light` of each light.
        let mut r = Rng::new(17);
        let spheres = vec![
            light(),
            SphereLight {
                center: Vec3::new(-1.0, 1.0, 0.5),
                radius: 0.2,
                radiance: Vec3::new(5.0, 1.0, 0.5),
            },
            SphereLight {
                center: Vec3::new(0.5, 0.3, 1.5),
                radius: 0.6,
                radiance: Vec3::splat(0.3),
            },
        ];
        let radiance = (0..RingGrid::new(4).cell_count())
            .map(|c| Vec3::splat(0.1 + (c % 5) as f32))
            .collect();
        let mut lights = Lights::new(spheres);
        lights.env = Some(Envmap::new(4, radiance).unwrap());
        let mut same = 0;
        for round in 0..500 {
            let mut q = LightQuery::default();
            let len = 1 + round % LANES;
            for l in 0..len {
                // One lane in four inside the first sphere.
                let p = if l % 4 == 3 {
                    lights.spheres[0].center + Vec3::X * 0.1
                } else {
                    Vec3::new(r.next_f32(), r.next_f32(), r.next_f32()) * 2.0 - Vec3::ONE
                };
                let n = crate::sampling::uniform_sphere(r.next_2d());
                q.push(p, n, r.next_2d(), r.next_2d());
            }
            let together = lights.sample_lanes(&q, None);
            for (l, together) in together.iter().enumerate() {
                let alone = (l < len).then(|| {
                    let (p, n) = (q.p(l), q.n(l));
                    let u_light = Vec2::new(q.u_light[0][l], q.u_light[1][l]);
                    lights.sample(p, n, u_light, Vec2::new(q.u[0][l], q.u[1][l]))
                });
                let alone = alone.flatten();
                assert_eq!(format!("{together:?}"), format!("{alone:?}"));
                same += alone.is_some() as usize;
            }
            for i in 0..lights.len() {
                let together = lights.sample_lanes(&q, Some(i));
                for (l, together) in together.iter().enumerate().take(len) {
                    let u = Vec2::new(q.u[0][l], q.u[1][l]);
                    let alone = lights.sample_light(i, q.p(l), q.u_light[1][l], u);
                    assert_eq!(format!("{together:?}"), format!("{alone:?}"));
                }
            }
        }
        assert!(same > 1000, "too few samples compared: {same}");
    }

    #[test]
    fn a_point_light_is_sampled_in_its_one_direction_and_never_hit() {
        let s = SphereLight::point(Vec3::new(0.3, 2.0, -0.5), Vec3::splat(4.0));
        let p = Vec3::new(0.1, 0.0, 0.2);
        let lights = Lights::new(vec![s]);
        let ls = lights
            .sample_light(0, p, 0.5, Vec2::new(0.37, 0.81))
            .unwrap();
        let to = s.center - p;
        assert!((ls.wi - to.normalize()).length() < 1e-6, "{:?}", ls.wi);
        assert!((ls.dist - to.length()).abs() < 1e-5);
        assert!(ls.delta);
        // Intensity over "pdf" is the irradiance factor I / d².
        assert!((ls.pdf - to.length_squared()).abs() < 1e-5 * to.length_squared());
        assert_eq!(intersect_sphere(&s, p, to.normalize(), 0.0), None);
        assert!(!lights.occludes(p, to.normalize(), 10.0, Emitter::EnvCell(0)));
        assert_eq!(cone_pdf(&s, p), 0.0);
        assert!((s.solid_angle_from(p) - 1.0 / to.length_squared()).abs() < 1e-6);
        assert_eq!(s.intensity(), Vec3::splat(4.0));
        // Picked by how strongly it lights the point: luminance × 1/d² × cosine, as a tiny
        // sphere of the same intensity at the same place is (its cone widens the cosine by
        // about r/d).
        let sphere = SphereLight {
            radius: 1e-3,
            radiance: Vec3::splat(4.0 / (std::f32::consts::PI * 1e-6)),
            ..s
        };
        let (a, b) = (
            pick_weight(&s, p, Vec3::Y),
            pick_weight(&sphere, p, Vec3::Y),
        );
        assert!((a / b - 1.0).abs() < 1e-3, "{a} vs {b}");
    }

    #[test]
    fn tiny_far_sphere_keeps_precision() {
        let s = SphereLight {
            center: Vec3::new(0.0, 1000.0, 0.0),
            radius: 0.01,
            radiance: Vec3::ONE,
        };
        let omc = one_minus_cos_max(&s, Vec3::ZERO).unwrap();
        // 1 − cos θ ≈ θ²/2 with θ = 1e-5.
        assert!((omc / 5e-11 - 1.0).abs() < 1e-3, "{omc}");
    }
}
