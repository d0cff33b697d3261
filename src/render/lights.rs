//! The lights a path can reach: spherical area lights and the ring environment map. Each kind
//! keeps sampling, pdf and evaluation side by side.
//!
//! Sphere lights are sampled uniformly in the cone they subtend (pbrt's "sample by solid
//! angle"); the envmap by its cell distribution. A light is picked in proportion to how
//! strongly it lights the shading point (luminance × solid angle); pdfs are per unit solid
//! angle at the shading point and include the probability of picking the light.

use glam::{Vec2, Vec3};

use super::sampling::{ONE_MINUS_EPS, uniform_cone};
use crate::envmap::Envmap;
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
    /// Probability density per unit solid angle (including the choice of light).
    pub pdf: f32,
}

/// The set of lights of a render.
#[derive(Debug, Clone, Default)]
pub struct Lights {
    pub spheres: Vec<SphereLight>,
    /// Light from infinitely far away; rays that escape the scene see it.
    pub env: Option<Envmap>,
}

/// Up to this many lights are picked by how strongly they light the shading point; more are
/// picked uniformly (the weights would cost more than they save).
pub const MAX_WEIGHTED: usize = 16;

impl Lights {
    /// Sphere lights only.
    pub fn new(spheres: Vec<SphereLight>) -> Lights {
        Lights { spheres, env: None }
    }

    /// An environment map only.
    pub fn env(env: Envmap) -> Lights {
        Lights {
            spheres: Vec::new(),
            env: Some(env),
        }
    }

    /// Lights to sample: each sphere, and the envmap as one (index `len() - 1`).
    pub fn len(&self) -> usize {
        self.spheres.len() + self.env.is_some() as usize
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
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
            w[i] = Cone::of(s, p).map_or(0.0, |c| {
                crate::imageio::luminance(s.radiance).max(0.0)
                    * std::f32::consts::TAU
                    * c.omc
                    * c.max_cosine(n)
            });
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
    /// and a direction in it with `u`.
    #[inline]
    pub fn sample(&self, p: Vec3, n: Vec3, u_light: Vec2, u: Vec2) -> Option<LightSample> {
        let count = self.len();
        if count == 0 {
            return None;
        }
        // The pick and where `u_light.x` fell within the picked light's share, rescaled to
        // [0, 1).
        let (i, pick, within) = match self.pick_weights(p, n) {
            Some(w) => {
                let target = u_light.x * w[count];
                let mut acc = 0.0;
                let mut i = count - 1;
                for (k, &wk) in w[..count].iter().enumerate() {
                    acc += wk;
                    if target < acc && wk > 0.0 {
                        i = k;
                        break;
                    }
                }
                // Rounding can leave the last index with weight zero: take the last nonzero.
                while w[i] <= 0.0 && i > 0 {
                    i -= 1;
                }
                let below: f32 = w[..i].iter().sum();
                (i, w[i] / w[count], (target - below) / w[i])
            }
            None => {
                let x = u_light.x * count as f32;
                let i = (x as usize).min(count - 1);
                (i, 1.0 / count as f32, x - i as f32)
            }
        };
        // A sphere's direction comes from the pick's own pair, so the samples that pick it
        // keep that pair's stratification; the other pair's points would be a random subset.
        // Not for a light picked rarely: its share of the f32 `u_light.x` holds too few
        // distinct values.
        let u = if i < self.spheres.len() && pick >= 1.0 / 4096.0 {
            Vec2::new(within.clamp(0.0, ONE_MINUS_EPS), u_light.y)
        } else {
            u
        };
        let ls = self.sample_light(i, p, u_light.y, u)?;
        Some(LightSample {
            pdf: ls.pdf * pick,
            ..ls
        })
    }

    /// A direction toward light `i` alone (sphere `i`, or the envmap at `len() - 1`, its cell
    /// picked with `u_cell`), its pdf excluding any choice of light: next-event estimation
    /// that samples every light ([`super::RenderSettings::every_light`]).
    #[inline]
    pub fn sample_light(&self, i: usize, p: Vec3, u_cell: f32, u: Vec2) -> Option<LightSample> {
        if i < self.spheres.len() {
            let (wi, dist, pdf) = sample_sphere(&self.spheres[i], p, u)?;
            return Some(LightSample {
                emitter: Emitter::Sphere(i as u32),
                wi,
                dist,
                pdf,
            });
        }
        let env = self.env.as_ref()?;
        let (cell, wi, pdf) = env.sample(u_cell, u);
        Some(LightSample {
            emitter: Emitter::EnvCell(cell),
            wi,
            dist: f32::INFINITY,
            pdf,
        })
    }

    /// The pdf [`Lights::sample`] has for reaching `emitter` (in a direction that does reach
    /// it) from `p`.
    #[inline]
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
}

impl Cone {
    /// The cone of `s` from `p`, or `None` from inside it.
    #[inline]
    fn of(s: &SphereLight, p: Vec3) -> Option<Cone> {
        let to_c = s.center - p;
        let d2 = to_c.length_squared();
        let r2 = s.radius * s.radius;
        if d2 <= r2 * 1.0001 {
            return None;
        }
        let dist = d2.sqrt();
        let sin2 = r2 / d2;
        let cos_a = (1.0 - sin2).max(0.0).sqrt();
        Some(Cone {
            axis: to_c / dist,
            dist,
            omc: sin2 / (1.0 + cos_a),
            sin_a: s.radius / dist,
            cos_a,
        })
    }

    /// The largest cosine between unit `n` and a direction in the cone, clamped at zero:
    /// cos(max(θ − α, 0)) for the axis' angle θ from `n`.
    #[inline]
    fn max_cosine(&self, n: Vec3) -> f32 {
        let cos_t = n.dot(self.axis).clamp(-1.0, 1.0);
        if cos_t >= self.cos_a {
            return 1.0; // n points into the cone
        }
        let sin_t = (1.0 - cos_t * cos_t).max(0.0).sqrt();
        (cos_t * self.cos_a + sin_t * self.sin_a).max(0.0)
    }

    /// Pdf per unit solid angle of uniform cone sampling.
    #[inline]
    fn pdf(&self) -> f32 {
        1.0 / (std::f32::consts::TAU * self.omc)
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

/// The cone-sampling pdf of any direction that hits `s` from `p` (0 from inside).
#[inline]
pub fn cone_pdf(s: &SphereLight, p: Vec3) -> f32 {
    Cone::of(s, p).map_or(0.0, |c| c.pdf())
}

/// The first crossing of a unit ray with the sphere's surface beyond `t_min`.
#[inline]
pub fn intersect_sphere(s: &SphereLight, o: Vec3, d: Vec3, t_min: f32) -> Option<f32> {
    let oc = o - s.center;
    let b = oc.dot(d);
    // r² − |oc − b·d|² is the discriminant, computed without the cancellation of b² − c.
    let perp = oc - b * d;
    let disc = s.radius * s.radius - perp.length_squared();
    if disc < 0.0 {
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
    use crate::render::sampling::Rng;

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
                center: crate::render::sampling::uniform_sphere(r.next_2d()) * 2.0,
                radius: 0.1 + r.next_f32(),
                radiance: Vec3::ONE,
            };
            let p = Vec3::new(r.next_f32(), r.next_f32(), r.next_f32()) * 0.2;
            let n = crate::render::sampling::uniform_sphere(r.next_2d());
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
            let w = crate::render::sampling::uniform_sphere(r.next_2d());
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
