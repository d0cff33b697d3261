//! Sphere lights as the light model. With the lights' centres and radii fixed,
//! every pixel is linear in their radiances, `I_α = Σ_k T_kα L_kα`, so the radiances come from
//! a small exact NNLS on the per-light transport T_k, and only the geometry (4 numbers per
//! light) is left to a non-linear search: variable projection, by Levenberg–Marquardt.
//!
//! The one path tracer estimates T_k: it renders the lights at unit radiance and accumulates,
//! per pixel, the weight each light receives (the transport's [`PerEmitterAccumulator`]).
//! Renders of two geometries with the same seed share their random numbers (common random
//! numbers), so their residuals differ by the geometry, not by noise.
//!
//! The fit compares *bins* of pixels (sums over `bin × bin` blocks), not single pixels: the
//! Monte Carlo variance of a low-sample transport adds to the squared residual and depends on
//! the geometry (a bigger, dimmer light is smoother), which on single pixels pulls the optimum
//! measurably toward wrong lights; summing 16 pixels cuts that term 16-fold while shading and
//! shadows, a few pixels wide or more, survive.

use std::time::Instant;

use glam::{DVec3, Vec3};
use serde::Serialize;

use super::is_held_out;
use super::nnls;
use super::transport::{EmitterKind, PerEmitterAccumulator};
use crate::envmap::{Envmap, RingGrid};
use crate::imageio::Image;
use crate::render::{Lights, Paths, RenderSettings, Renderer};
use crate::scene::{Camera, SphereLight};

/// The images a sphere model is fitted to.
#[derive(Clone, Copy)]
pub struct Observations<'a> {
    pub cameras: &'a [&'a Camera],
    /// The pixels the fit compares, per view ([`fit_masks`] of the views' masks).
    pub masks: &'a [Vec<bool>],
    /// The pixels the fitted models' re-renders are compared on: every pixel the views'
    /// masks hold.
    pub evaluated: &'a [Vec<bool>],
    pub references: &'a [Image],
    /// Pixels are summed over `bin × bin` blocks (see the module notes); 1 = single pixels.
    pub bin: u32,
    /// Leave out the held-out quarter of the pixels ([`is_held_out`]), for model selection.
    pub holdout: bool,
    /// Also fit an envmap on this grid behind the lights (light from afar, e.g. a sky): its
    /// cells become further linear unknowns after the lights' ([`SphereProblem::lights`]
    /// counts both). For [`refine`] and [`judge`]; the start searches take None.
    pub background: Option<&'a RingGrid>,
    /// Camera paths kept between renders (None: every render traces its own).
    pub paths: Option<&'a PathCache>,
    /// Told the pixel samples each of the fit's renders lit (compared pixels × spp), for a
    /// progress bar that moves while a fit runs.
    pub progress: Option<&'a (dyn Fn(u64) + Sync)>,
}

impl Observations<'_> {
    /// Whether the fit compares pixel `i` of view `v`: in its mask, and not held out.
    pub fn compares(&self, v: usize, i: u32) -> bool {
        self.masks[v][i as usize] && !(self.holdout && is_held_out((v, i)))
    }

    /// How many pixels the fit compares, over every view.
    pub fn compared_pixels(&self) -> u64 {
        let per_view = self.masks.iter().enumerate().map(|(v, mask)| {
            (0..mask.len() as u32)
                .filter(|&i| self.compares(v, i))
                .count() as u64
        });
        per_view.sum()
    }
}

/// Most pixels a sphere fit compares by default ([`fit_masks`], `--sphere-pixels`). Each
/// keeps its walked camera paths (about 11 KB at 2 bounces: 360 MB for this many) and is lit
/// again by each of the fit's hundreds of renders: past this, pixels cost memory and time in
/// proportion. The bundled scene's 10,600 seen pixels are all compared.
pub const FIT_PIXELS: usize = 1 << 15;

/// Fewest pixels a sphere fit may be asked to compare: 256 blocks of 4×4, more rows than
/// a 9-ring background has cells (`--model auto` fits one behind the lights).
pub const MIN_FIT_PIXELS: usize = 1 << 12;

/// The pixels of `masks` a sphere fit compares: all of them when they are at most `most`;
/// else whole `bin × bin` blocks (the fit sums pixels per block), those of smallest hash of
/// (view, block) while they fit in `most`: spread over every view, and the same in every run.
pub fn fit_masks(
    cameras: &[&Camera],
    masks: &[Vec<bool>],
    bin: u32,
    most: usize,
) -> Vec<Vec<bool>> {
    let seen: usize = masks.iter().map(|m| m.iter().filter(|&&k| k).count()).sum();
    if seen <= most {
        return masks.to_vec();
    }
    let bin = bin.max(1);
    let blocks_in = |cam: &Camera| (cam.width.div_ceil(bin) * cam.height.div_ceil(bin)) as usize;
    let block_of = |cam: &Camera, i: usize| {
        let (x, y) = (i as u32 % cam.width, i as u32 / cam.width);
        ((y / bin) * cam.width.div_ceil(bin) + x / bin) as usize
    };
    // (hash, view, block, pixels seen in it) of every block with a seen pixel.
    let mut blocks: Vec<(u64, usize, usize, usize)> = Vec::new();
    for (v, (cam, mask)) in cameras.iter().zip(masks).enumerate() {
        let mut count = vec![0usize; blocks_in(cam)];
        for (i, _) in mask.iter().enumerate().filter(|(_, k)| **k) {
            count[block_of(cam, i)] += 1;
        }
        blocks.extend(
            count
                .iter()
                .enumerate()
                .filter(|(_, n)| **n > 0)
                .map(|(b, &n)| {
                    let hash = crate::sampling::mix64(((v as u64) << 32 | b as u64) ^ 0x5EED_B10C);
                    (hash, v, b, n)
                }),
        );
    }
    blocks.sort_unstable();
    let mut chosen: Vec<Vec<bool>> = cameras.iter().map(|c| vec![false; blocks_in(c)]).collect();
    let mut total = 0;
    for &(_, v, b, n) in &blocks {
        if total + n > most {
            break;
        }
        total += n;
        chosen[v][b] = true;
    }
    cameras
        .iter()
        .zip(masks)
        .zip(&chosen)
        .map(|((cam, mask), chosen)| {
            mask.iter()
                .enumerate()
                .map(|(i, &k)| k && chosen[block_of(cam, i)])
                .collect()
        })
        .collect()
}

/// Camera paths walked once per (scene, view, seed, samples, bounces) and lit again by every
/// later transport render with those settings ([`Renderer::trace_paths`]): the sphere model's
/// hundreds of renders differ only in their lights, so only their shadow rays are traced again.
/// Renders above [`PathCache::MAX_SPP`] samples are not kept (memory: about 64 bytes per path
/// vertex, 150 MB for 2 views of 128×96 at 64 spp and 2 bounces).
#[derive(Default)]
pub struct PathCache {
    #[allow(clippy::type_complexity)]
    paths: std::sync::Mutex<
        std::collections::HashMap<(usize, u64, u64, u32, u32, bool), std::sync::Arc<Paths>>,
    >,
}

impl PathCache {
    pub const MAX_SPP: u32 = 64;

    /// The paths of view `view` (random stream `stream`) under `settings`, walked now if new,
    /// of the pixels `wanted` flags (the same flags whenever `holdout` is: the fit's pixels).
    fn get(
        &self,
        renderer: &Renderer,
        camera: &Camera,
        stream: u64,
        settings: &RenderSettings,
        (holdout, wanted): (bool, impl FnOnce() -> Vec<bool>),
    ) -> std::sync::Arc<Paths> {
        let key = (
            renderer.scene as *const _ as usize,
            stream,
            settings.seed,
            settings.spp,
            settings.max_bounces,
            holdout,
        );
        let mut map = self.paths.lock().unwrap_or_else(|e| e.into_inner());
        map.entry(key)
            .or_insert_with(|| {
                let paths = renderer.trace_paths(camera, stream, settings, Some(wanted()));
                std::sync::Arc::new(paths)
            })
            .clone()
    }

    /// Drops every path kept (e.g. the held-out fits' once the refit on all pixels begins).
    pub fn clear(&self) {
        self.paths.lock().unwrap_or_else(|e| e.into_inner()).clear();
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        let map = self.paths.lock().unwrap_or_else(|e| e.into_inner());
        map.values().map(|p| p.bytes()).sum()
    }
}

/// The fitting problem at one geometry: per-light transport and references, summed per bin
/// over the kept pixels. Per channel, T is `rows × lights`, row-major.
#[derive(Debug, Clone)]
pub struct SphereProblem {
    /// Columns of T: the sphere lights, then the background's cells if any.
    pub lights: usize,
    pub t: [Vec<f32>; 3],
    pub y: [Vec<f64>; 3],
    /// The same transport rendered again with independent random numbers ([`twin_problem`]),
    /// if any: products of the two are free of the renders' noise energy. Only
    /// [`uncertainty`] makes and reads twins.
    pub twin: Option<[Vec<f32>; 3]>,
}

impl SphereProblem {
    pub fn rows(&self) -> usize {
        self.y[0].len()
    }

    /// This problem with column `j` replaced by `column`'s only one (same rows).
    fn with_column(&self, j: usize, column: &SphereProblem) -> SphereProblem {
        debug_assert_eq!((column.lights, column.rows()), (1, self.rows()));
        let mut p = self.clone();
        for ch in 0..3 {
            for (row, &v) in p.t[ch].chunks_exact_mut(self.lights).zip(&column.t[ch]) {
                row[j] = v;
            }
        }
        p
    }
}

/// Estimates the per-light transport of `geometry` (centres and radii; radiances ignored) and
/// bins it with the references. The same `settings.seed` gives the same random numbers for
/// any geometry.
pub fn sphere_problem(
    renderer: &Renderer,
    obs: &Observations,
    geometry: &[SphereLight],
    settings: &RenderSettings,
) -> SphereProblem {
    transport(renderer, obs, geometry, None, settings)
}

/// [`sphere_problem`], or column `alone` of it (that light rendered alone, the others still
/// blocking it).
fn transport(
    renderer: &Renderer,
    obs: &Observations,
    geometry: &[SphereLight],
    alone: Option<usize>,
    settings: &RenderSettings,
) -> SphereProblem {
    let unit: Vec<SphereLight> = geometry
        .iter()
        .map(|l| SphereLight {
            radiance: Vec3::ONE,
            ..*l
        })
        .collect();
    let mut lights = Lights::new(unit);
    let mut acc = PerEmitterAccumulator {
        kind: EmitterKind::Spheres,
        count: geometry.len(),
    };
    if let Some(j) = alone {
        lights.alone = Some(j as u32);
        acc = PerEmitterAccumulator {
            kind: EmitterKind::Sphere(j as u32),
            count: 1,
        };
    } else if let Some(grid) = obs.background {
        let cells = grid.cell_count();
        lights.env = Some(
            Envmap::new(grid.rings(), vec![Vec3::ONE; cells]).expect("a unit envmap is valid"),
        );
        acc = PerEmitterAccumulator {
            kind: EmitterKind::SpheresThenCells {
                spheres: geometry.len() as u32,
            },
            count: geometry.len() + cells,
        };
    }
    let k = acc.count;
    let renderer = renderer.with_lights(&lights);
    let bin = obs.bin.max(1);
    let mut t: [Vec<f32>; 3] = std::array::from_fn(|_| Vec::new());
    let mut y: [Vec<f64>; 3] = std::array::from_fn(|_| Vec::new());
    for (v, (cam, mask)) in obs.cameras.iter().zip(obs.masks).enumerate() {
        let stream = 2000 + v as u64;
        // Only the pixels the fit compares are rendered.
        let fitted = |i: u32| obs.compares(v, i);
        let frame = match obs.paths.filter(|_| settings.spp <= PathCache::MAX_SPP) {
            Some(cache) => {
                let wanted = || (0..mask.len() as u32).map(fitted).collect();
                let paths = cache.get(&renderer, cam, stream, settings, (obs.holdout, wanted));
                renderer.render_paths(&paths, cam, settings, &acc)
            }
            None => renderer.render_some(cam, stream, settings, &acc, Some(&fitted), &|_| {}),
        };
        let (w, h) = (frame.width, frame.height);
        let bw = w.div_ceil(bin) as usize;
        let bins = bw * h.div_ceil(bin) as usize;
        let mut tb: [Vec<f32>; 3] = std::array::from_fn(|_| vec![0.0; bins * k]);
        let mut yb: [Vec<f64>; 3] = std::array::from_fn(|_| vec![0.0; bins]);
        let mut used = vec![false; bins];
        let mut lit = 0u64;
        for (i, row) in frame.pixels.iter().enumerate() {
            if !fitted(i as u32) {
                continue;
            }
            lit += 1;
            let (x, yy) = (i as u32 % w, i as u32 / w);
            let b = (yy / bin) as usize * bw + (x / bin) as usize;
            used[b] = true;
            let reference = obs.references[v].rgb[i];
            for ch in 0..3 {
                for (a, w) in row.iter().enumerate() {
                    tb[ch][b * k + a] += w[ch];
                }
                yb[ch][b] += reference[ch] as f64;
            }
        }
        for b in (0..bins).filter(|&b| used[b]) {
            for ch in 0..3 {
                t[ch].extend_from_slice(&tb[ch][b * k..(b + 1) * k]);
                y[ch].push(yb[ch][b]);
            }
        }
        if let Some(progress) = obs.progress {
            progress(lit * settings.spp as u64);
        }
    }
    SphereProblem {
        lights: k,
        t,
        y,
        twin: None,
    }
}

/// Seed offset of a twin transport's second half.
const TWIN_SEED: u64 = 0x9e37_79b9_7f4a_7c15;

/// [`transport`] rendered twice with independent random numbers at half the samples each
/// (the same cost), the second as the problem's twin: products of one half's residuals or
/// derivatives with the other's are free of the renders' noise energy ([`uncertainty`]).
fn twin_problem(
    renderer: &Renderer,
    obs: &Observations,
    geometry: &[SphereLight],
    alone: Option<usize>,
    settings: &RenderSettings,
) -> SphereProblem {
    let half = RenderSettings {
        spp: (settings.spp / 2).max(1),
        ..*settings
    };
    let other = RenderSettings {
        seed: half.seed ^ TWIN_SEED,
        ..half
    };
    let mut p = transport(renderer, obs, geometry, alone, &half);
    p.twin = Some(transport(renderer, obs, geometry, alone, &other).t);
    p
}

/// Radiances of the lights that best explain the references for this transport, and the
/// remaining error: `relMAE = Σ|T L − y| / Σ|y|` over the problem's rows and channels.
pub fn solve_radiance(p: &SphereProblem) -> (Vec<Vec3>, f64) {
    let k = p.lights;
    let mut radiance = vec![Vec3::ZERO; k];
    let (mut abs, mut ref_abs) = (0.0f64, 0.0f64);
    for ch in 0..3 {
        let (t, y) = (&p.t[ch], &p.y[ch]);
        let mut g = vec![0.0f64; k * k];
        let mut b = vec![0.0f64; k];
        for (row, yr) in t.chunks_exact(k).zip(y) {
            for a in 0..k {
                b[a] += row[a] as f64 * yr;
                for c in 0..k {
                    g[a * k + c] += row[a] as f64 * row[c] as f64;
                }
            }
        }
        let x = nnls::nnls(
            &g,
            &b,
            1e-12,
            100 * k + 100,
            std::time::Duration::from_secs(10),
        )
        .x;
        for (l, v) in radiance.iter_mut().zip(&x) {
            l[ch] = *v as f32;
        }
        for (row, yr) in t.chunks_exact(k).zip(y) {
            let pred: f64 = row.iter().zip(&x).map(|(&a, &b)| a as f64 * b).sum();
            abs += (pred - yr).abs();
            ref_abs += yr.abs();
        }
    }
    (radiance, abs / ref_abs.max(f64::MIN_POSITIVE))
}

/// Settings of [`refine`].
#[derive(Debug, Clone, Copy)]
pub struct RefineSettings {
    /// Samples and seed of the renders that measure the residual (one seed: common random
    /// numbers, so two geometries differ by the geometry, not by noise).
    pub residual: RenderSettings,
    /// Samples and seed of the finite-difference renders of the Jacobian: fewer samples (the
    /// step direction need not be exact, only downhill) and another seed, so their noise is
    /// independent of the residual's and does not bias where the search stops.
    pub jacobian: RenderSettings,
    pub max_iterations: usize,
    /// The first `fixed` lights keep their geometry (their radiances are still solved).
    pub fixed: usize,
    /// End with a direct search on each free light's apparent size.
    pub polish_radii: bool,
    /// Samples of the render the final radiances are solved on (none if not above the
    /// residual's).
    pub radiance_spp: u32,
}

/// Refined geometry and radiances.
#[derive(Debug, Clone)]
pub struct Refined {
    pub lights: Vec<SphereLight>,
    /// Radiance of each background cell ([`Observations::background`]; empty without).
    pub background: Vec<Vec3>,
    /// relMAE of the fit over the problem's rows (against the transport's own prediction).
    pub rel_mae: f64,
    pub iterations: usize,
    /// Transport renders made.
    pub evaluations: usize,
    /// Sum of squared residuals after each accepted step.
    pub history: Vec<f64>,
}

/// A light's geometry in coordinates where the fit is well conditioned: its direction from
/// the scene centre, ln of its distance and ln of the sine of its angular radius. Moving a
/// light farther while it keeps its apparent size (the images' weakest direction, with the
/// radiance refitted) is then one coordinate, not a diagonal of four.
#[derive(Debug, Clone, Copy)]
struct Polar {
    dir: DVec3,
    ln_distance: f64,
    ln_sin_radius: f64,
}

impl Polar {
    fn of(l: &SphereLight, center: Vec3) -> Polar {
        let v = (l.center - center).as_dvec3();
        let d = v.length().max(1e-6);
        Polar {
            dir: v / d,
            ln_distance: d.ln(),
            ln_sin_radius: (l.radius as f64 / d).clamp(1e-6, 0.99).ln(),
        }
    }

    /// This geometry moved by `q` = (tangent angle 1, tangent angle 2, Δ ln distance,
    /// Δ ln sin radius), as a unit-radiance light.
    fn moved(&self, q: &[f64], center: Vec3) -> (Polar, SphereLight) {
        let (t1, t2) = self.dir.any_orthonormal_pair();
        let dir = (self.dir + q[0] * t1 + q[1] * t2).normalize();
        let p = Polar {
            dir,
            ln_distance: self.ln_distance + q[2],
            ln_sin_radius: (self.ln_sin_radius + q[3]).min(0.99f64.ln()),
        };
        let d = p.ln_distance.exp();
        let light = SphereLight {
            center: center + (dir * d).as_vec3(),
            radius: ((d * p.ln_sin_radius.exp()) as f32).max(1e-4),
            radiance: Vec3::ONE,
        };
        (p, light)
    }
}

/// The lights at `base` moved by `q` (4 numbers per light, see [`Polar::moved`]).
fn lights_of(base: &[Polar], q: &[f64], center: Vec3) -> Vec<SphereLight> {
    base.iter()
        .zip(q.chunks_exact(4))
        .map(|(b, q)| b.moved(q, center).1)
        .collect()
}

fn dot(x: &[f64], y: &[f64]) -> f64 {
    x.iter().zip(y).map(|(p, q)| p * q).sum()
}

/// Residuals `T L − y` (all rows, channels) with L solved exactly, the radiances and relMAE.
fn residuals(p: &SphereProblem) -> (Vec<f64>, Vec<Vec3>, f64) {
    let (radiance, rel) = solve_radiance(p);
    let k = p.lights;
    let mut r = Vec::with_capacity(3 * p.rows());
    for ch in 0..3 {
        for (row, y) in p.t[ch].chunks_exact(k).zip(&p.y[ch]) {
            let pred: f64 = row
                .iter()
                .zip(&radiance)
                .map(|(&t, l)| t as f64 * l[ch] as f64)
                .sum();
            r.push(pred - y);
        }
    }
    (r, radiance, rel)
}

/// Solves the small dense system `a x = b` (row-major; LU with partial pivoting); None when
/// singular.
fn solve_dense(a: Vec<f64>, b: Vec<f64>) -> Option<Vec<f64>> {
    use faer::linalg::solvers::Solve;
    let n = b.len();
    let m = faer::Mat::<f64>::from_fn(n, n, |i, j| a[i * n + j]);
    let rhs = faer::Mat::<f64>::from_fn(n, 1, |i, _| b[i]);
    let x = m.partial_piv_lu().solve(&rhs);
    let x: Vec<f64> = (0..n).map(|i| x[(i, 0)]).collect();
    x.iter().all(|v| v.is_finite()).then_some(x)
}

/// Refines the lights' geometry from `start` by Levenberg–Marquardt on the
/// variable-projection residual (radiances re-solved exactly at every evaluation), with
/// forward-difference derivatives over renders that share their random numbers. The
/// coordinates are [`Polar`] about `center`, re-based on the current directions every step.
///
/// One function of about 180 lines on purpose: it is one Levenberg–Marquardt loop (Jacobian,
/// damped step, acceptance, damping update, stopping tests) whose state every part reads and
/// writes; cut into pieces it would pass that state around instead of reading as the
/// algorithm does.
pub fn refine(
    renderer: &Renderer,
    obs: &Observations,
    start: &[SphereLight],
    center: Vec3,
    settings: &RefineSettings,
) -> Refined {
    // A light rendered alone is always sampled as under `every_light` (a pick would draw its
    // direction from other numbers), so the whole fit is: every trial then compares the same
    // estimator. Camera rays pass through the trial lights ([`SphereSettings::new`]).
    let every = |at: RenderSettings| RenderSettings {
        every_light: true,
        camera_sees_lights: false,
        ..at
    };
    let settings = &RefineSettings {
        residual: every(settings.residual),
        jacobian: every(settings.jacobian),
        ..*settings
    };
    // Renders made; a trial that moves one light renders that light alone
    // ([`sphere_column`]) into the problem it moves from.
    let evaluations = std::cell::Cell::new(0);
    let problem = |base: &[Polar], q: &[f64], at: &RenderSettings| {
        evaluations.set(evaluations.get() + 1);
        sphere_problem(renderer, obs, &lights_of(base, q, center), at)
    };
    let moved_one = |from: &SphereProblem, base: &[Polar], q: &[f64], j, at: &RenderSettings| {
        evaluations.set(evaluations.get() + 1);
        let column = transport(renderer, obs, &lights_of(base, q, center), Some(j), at);
        from.with_column(j, &column)
    };
    let mut base: Vec<Polar> = start.iter().map(|l| Polar::of(l, center)).collect();
    let n = 4 * base.len();
    let zero = vec![0.0; n];
    // The problem at the current geometry, at the residual's settings.
    let mut at_base = problem(&base, &zero, &settings.residual);
    let (mut r, mut radiance, mut rel) = residuals(&at_base);
    let sse = |r: &[f64]| r.iter().map(|v| v * v).sum::<f64>();
    let mut f = sse(&r);
    let mut history = vec![f];
    let mut mu = 1e-3;
    let mut iterations = 0;
    // The free parameters: those of the lights after the fixed ones.
    let first = 4 * settings.fixed.min(base.len());
    let m = n - first;
    let mut normal = vec![0.0; m * m];
    // Forward-difference steps: 0.3° of direction, 2% of distance, 3% of angular radius —
    // large enough that a step moves many samples' shadows, not a few.
    let steps = [0.005, 0.005, 0.02, 0.03];
    // Levenberg–Marquardt, then the direct search on sizes; while that search still gains,
    // LM again from there (positions and radiances shift with the sizes), at most twice.
    let mut budget = settings.max_iterations;
    for pass in 0..3 {
        while iterations < budget {
            iterations += 1;
            let p0 = problem(&base, &zero, &settings.jacobian);
            let (r0, _, _) = residuals(&p0);
            let mut jac: Vec<Vec<f64>> = Vec::with_capacity(m);
            for j in first..n {
                let h = steps[j % 4];
                let mut q = zero.clone();
                q[j] = h;
                let (rj, _, _) = residuals(&moved_one(&p0, &base, &q, j / 4, &settings.jacobian));
                jac.push(rj.iter().zip(&r0).map(|(a, b)| (a - b) / h).collect());
            }
            let mut g = vec![0.0; m];
            for i in 0..m {
                g[i] = jac[i].iter().zip(&r).map(|(x, y)| x * y).sum();
                for j in 0..m {
                    normal[i * m + j] = jac[i].iter().zip(&jac[j]).map(|(x, y)| x * y).sum();
                }
            }
            let mut improved = false;
            for attempt in 0..6 {
                // Every second try holds the radii: a dim light's apparent size can be so
                // weakly seen that its noisy derivative alone steers the step (s13: a 0.12 m
                // light's size took every step while the centres waited); the other tries
                // still move sizes, as does the line search where it runs.
                let hold_radii = attempt % 2 == 1;
                let mut damped = normal.clone();
                let mut rhs: Vec<f64> = g.iter().map(|v| -v).collect();
                for i in 0..m {
                    damped[i * m + i] += mu * normal[i * m + i].max(1e-12);
                    if hold_radii && (first + i) % 4 == 3 {
                        for k in 0..m {
                            (damped[i * m + k], damped[k * m + i]) = (0.0, 0.0);
                        }
                        (damped[i * m + i], rhs[i]) = (1.0, 0.0);
                    }
                }
                let Some(free_step) = solve_dense(damped, rhs) else {
                    mu *= 10.0;
                    continue;
                };
                let mut step = zero.clone();
                step[first..].copy_from_slice(&free_step);
                // A trust region in plain terms: at most 10° and a factor 1.5 per step.
                for (j, s) in step.iter_mut().enumerate() {
                    let cap = if j % 4 < 2 { 0.17 } else { 0.4 };
                    *s = s.clamp(-cap, cap);
                }
                let pq = problem(&base, &step, &settings.residual);
                let (rq, lq, relq) = residuals(&pq);
                let fq = sse(&rq);
                if fq < f {
                    let f_before = f;
                    // A step the linear model got right but too short (the noisy Jacobian
                    // underrates how far a penumbra can move) is taken again while it gains,
                    // at most twice, for one residual render each instead of a Jacobian's
                    // 4K + 1.
                    let mut accepted = (pq, rq, lq, relq, fq);
                    for again in 0..3 {
                        let (pq, rq, lq, relq, fq) = accepted;
                        at_base = pq;
                        base = base
                            .iter()
                            .zip(step.chunks_exact(4))
                            .map(|(b, q)| b.moved(q, center).0)
                            .collect();
                        (r, radiance, rel, f) = (rq, lq, relq, fq);
                        history.push(f);
                        if again == 2 {
                            break;
                        }
                        let pq = problem(&base, &step, &settings.residual);
                        let (rq, lq, relq) = residuals(&pq);
                        let fq = sse(&rq);
                        if fq >= f - 5e-4 * f {
                            break;
                        }
                        accepted = (pq, rq, lq, relq, fq);
                    }
                    mu = (mu / 3.0).max(1e-9);
                    // Gains below 0.05% are below the noise: with 10³–10⁴ binned residuals that
                    // is a step of about one standard deviation of the parameters.
                    improved = (f_before - f) > 5e-4 * f_before;
                    break;
                }
                // Damping as small as the accepted steps left it barely changes the step:
                // the next try must be a different one, not the same render again.
                if hold_radii {
                    mu = (mu * 4.0).max(1e-2);
                }
            }
            if !improved {
                break;
            }
        }
        // The apparent size is the slowest coordinate (a penumbra's width, traded against
        // radiance): where the noisy Jacobian stalls, a line search along it on the residual
        // renders themselves still goes downhill ([`line_search`]). Its steps double while
        // they gain, since a light that starts far too small barely moves its penumbrae under
        // the Jacobian's 3% step (s50: a 0.42 m light stalled at 0.07 m, and a third light grew
        // beside it to widen them).
        let before_polish = f;
        if settings.polish_radii {
            for j in settings.fixed.min(base.len())..base.len() {
                let at = |t: f64| {
                    let mut q = zero.clone();
                    q[4 * j + 3] = t;
                    let pq = moved_one(&at_base, &base, &q, j, &settings.residual);
                    let (rq, lq, relq) = residuals(&pq);
                    (sse(&rq), (q, pq, rq, lq, relq))
                };
                if let Some((fq, (q, pq, rq, lq, relq))) = line_search(f, 0.35, at) {
                    at_base = pq;
                    base[j] = base[j].moved(&q[4 * j..4 * j + 4], center).0;
                    (r, radiance, rel, f) = (rq, lq, relq, fq);
                    history.push(f);
                }
            }
            // The line search may grow or shrink a light several-fold, beyond what a
            // one-light trial may leave out (how it blocks the others): where it moved any,
            // the problem is rendered whole again, so what follows starts from the truth.
            if f < before_polish {
                at_base = problem(&base, &zero, &settings.residual);
                (r, radiance, rel) = residuals(&at_base);
                f = sse(&r);
                history.push(f);
            }
        }
        if !settings.polish_radii || pass == 2 || f >= before_polish * (1.0 - 5e-4) {
            break;
        }
        budget = iterations + settings.max_iterations / 2;
    }
    // The lights written out get their radiances from a render with more samples at the
    // final geometry (less transport noise than the 64-spp residuals'). Measured: dim lights'
    // power moved by at most 0.3% (s13, s35), so their remaining 4–9% error comes from
    // their geometry, not from noise in the transport (errors in the variables).
    if settings.radiance_spp > settings.residual.spp {
        let at = RenderSettings {
            spp: settings.radiance_spp,
            ..settings.residual
        };
        (_, radiance, rel) = residuals(&problem(&base, &zero, &at));
    }
    let lights = lights_of(&base, &zero, center)
        .into_iter()
        .zip(&radiance)
        .map(|(l, &radiance)| SphereLight { radiance, ..l })
        .collect();
    Refined {
        lights,
        background: radiance.split_off(base.len()),
        rel_mae: rel,
        iterations,
        evaluations: evaluations.get(),
        history,
    }
}

/// The lowest point found of a smooth (if noisy) `f` along one coordinate from 0, where it is
/// `f0`: steps of `h` either way, doubling downhill until a step loses, then one parabola
/// through the last three points (or through −h, 0, h when neither first step gains). Returns
/// the best value and what `f` returned with it, if any point beat `f0`; at most 11
/// evaluations, typically 3–5 (a fixed-step pattern search took 8–14).
fn line_search<T>(f0: f64, h: f64, mut f: impl FnMut(f64) -> (f64, T)) -> Option<(f64, T)> {
    let mut best: Option<(f64, T)> = None;
    let keep = |v: f64, payload: T, best: &mut Option<(f64, T)>| {
        if v < best.as_ref().map_or(f0, |b| b.0) {
            *best = Some((v, payload));
        }
    };
    // Parabola vertex through three points (None if they are collinear or open downward).
    let vertex = |(a, fa): (f64, f64), (b, fb): (f64, f64), (c, fc): (f64, f64)| {
        let den = (b - a) * (fb - fc) - (b - c) * (fb - fa);
        let num = (b - a).powi(2) * (fb - fc) - (b - c).powi(2) * (fb - fa);
        let curvature = ((fc - fb) / (c - b) - (fb - fa) / (b - a)) / (c - a);
        (den.abs() > 0.0 && curvature > 0.0)
            .then(|| b - 0.5 * num / den)
            .filter(|t| t.is_finite())
    };
    let (fp, payload) = f(h);
    let (dir, f1) = if fp < f0 {
        keep(fp, payload, &mut best);
        (1.0, fp)
    } else {
        let (fm, payload) = f(-h);
        if fm >= f0 {
            // Bracketed about 0: one parabola step, if it lands away from 0.
            if let Some(t) = vertex((-h, fm), (0.0, f0), (h, fp)).filter(|t| t.abs() > 0.1 * h) {
                let (v, payload) = f(t.clamp(-h, h));
                keep(v, payload, &mut best);
            }
            return best;
        }
        keep(fm, payload, &mut best);
        (-1.0, fm)
    };
    // Downhill from (0, f0) to (dir·h, f1): double the step while it gains.
    let (mut a, mut b) = ((0.0, f0), (dir * h, f1));
    let mut step = h;
    for _ in 0..8 {
        step *= 2.0;
        let t = b.0 + dir * step;
        let (v, payload) = f(t);
        if v < b.1 {
            keep(v, payload, &mut best);
            (a, b) = (b, (t, v));
            continue;
        }
        if let Some(t) = vertex(a, b, (t, v)).filter(|x| (x - b.0).abs() > 0.1 * h) {
            let (lo, hi) = (a.0.min(b.0 + dir * step), a.0.max(b.0 + dir * step));
            let (v, payload) = f(t.clamp(lo, hi));
            keep(v, payload, &mut best);
        }
        break;
    }
    best
}

/// `base`'s lights and `extra`'s as one problem (same rows: the same observations).
fn joined(base: Option<&SphereProblem>, extra: &SphereProblem) -> SphereProblem {
    let Some(base) = base else {
        return extra.clone();
    };
    let (kb, ke) = (base.lights, extra.lights);
    let t = std::array::from_fn(|ch| {
        base.t[ch]
            .chunks_exact(kb)
            .zip(extra.t[ch].chunks_exact(ke))
            .flat_map(|(a, b)| a.iter().chain(b).copied())
            .collect()
    });
    SphereProblem {
        lights: kb + ke,
        t,
        y: extra.y.clone(),
        twin: None,
    }
}

/// Adds to `dirs` the centres of the `count` brightest cells of `envmap` (by power) that lie
/// at least 10° from each other, from `taken` and from those already in `dirs`.
fn add_bright_directions(
    envmap: &crate::envmap::Envmap,
    count: usize,
    taken: &[Vec3],
    dirs: &mut Vec<Vec3>,
) {
    let g = &envmap.grid;
    let mut cells: Vec<(f32, Vec3)> = (0..g.cell_count() as u32)
        .map(|c| {
            let p =
                crate::imageio::luminance(envmap.radiance()[c as usize]) * envmap.solid_angle(c);
            (p, g.center(c))
        })
        .filter(|(p, _)| *p > 0.0)
        .collect();
    cells.sort_by(|a, b| b.0.total_cmp(&a.0));
    let mut added = 0;
    for (_, d) in cells {
        if added == count {
            break;
        }
        let far = |o: &Vec3| d.angle_between(*o) > 10f32.to_radians();
        if taken.iter().all(far) && dirs.iter().all(far) {
            dirs.push(d);
            added += 1;
        }
    }
}

/// A trial light of the start searches: unit radiance, `distance` metres from `center` along
/// unit `dir`, its radius subtending 3° from there.
fn trial_light(center: Vec3, dir: Vec3, distance: f32) -> SphereLight {
    SphereLight {
        center: center + dir * distance,
        radius: distance * 3f32.to_radians().tan(),
        radiance: Vec3::ONE,
    }
}

/// `n` directions spread evenly over the unit sphere (a Fibonacci lattice).
fn even_directions(n: usize) -> Vec<Vec3> {
    let golden = std::f32::consts::PI * (3.0 - 5f32.sqrt());
    (0..n)
        .map(|i| {
            let y = 1.0 - 2.0 * (i as f32 + 0.5) / n as f32;
            let r = (1.0 - y * y).max(0.0).sqrt();
            let phi = golden * i as f32;
            Vec3::new(r * phi.cos(), y, r * phi.sin())
        })
        .collect()
}

/// Candidate lights for a joint start: a small light (radius subtending 3°) in each of many
/// directions from the scene centre at one distance, each one's binned transport rendered
/// alone. With the Gram products of all pairs at hand, any set of candidates is scored with
/// its radiances solved exactly and no further render, so the best *set* is found by
/// exhaustive search — where adding one light at a time would keep a compromise between two
/// lights that the first light found (measured on s35: a 0.9 m light between two true ones,
/// and every single extra light, with the first held, scoring best below the table).
pub struct Dictionary {
    pub directions: Vec<Vec3>,
    /// Per channel, `n × n`: Σ over rows of T_i T_j.
    gram: [Vec<f64>; 3],
    /// Per channel: Σ over rows of T_i y.
    b: [Vec<f64>; 3],
    /// Per channel: Σ over rows of y².
    yy: [f64; 3],
}

/// Candidate directions of the [`Dictionary`] besides the envmap's (about 25° apart).
const DICTIONARY_DIRECTIONS: usize = 64;

impl Dictionary {
    /// The envmap estimate's 12 brightest directions and an even scan of the sphere, at twice
    /// the scene size from `center`, rendered with `settings`. Returns it and the renders made.
    pub fn new(
        renderer: &Renderer,
        obs: &Observations,
        envmap: &crate::envmap::Envmap,
        (center, size): (Vec3, f32),
        settings: &RenderSettings,
    ) -> (Dictionary, usize) {
        let mut directions = Vec::new();
        add_bright_directions(envmap, 12, &[], &mut directions);
        for d in even_directions(DICTIONARY_DIRECTIONS) {
            if directions
                .iter()
                .all(|o| d.angle_between(*o) > 10f32.to_radians())
            {
                directions.push(d);
            }
        }
        let distance = 2.0 * size;
        let columns: Vec<SphereProblem> = directions
            .iter()
            .map(|&d| sphere_problem(renderer, obs, &[trial_light(center, d, distance)], settings))
            .collect();
        let n = columns.len();
        let dot = |a: &[f32], b: &[f32]| -> f64 {
            a.iter().zip(b).map(|(&x, &y)| x as f64 * y as f64).sum()
        };
        let gram = std::array::from_fn(|ch| {
            let mut g = vec![0.0; n * n];
            for i in 0..n {
                for j in i..n {
                    let v = dot(&columns[i].t[ch], &columns[j].t[ch]);
                    (g[i * n + j], g[j * n + i]) = (v, v);
                }
            }
            g
        });
        let y = columns.first().map(|c| c.y.clone()).unwrap_or_default();
        let b = std::array::from_fn(|ch| {
            columns
                .iter()
                .map(|c| {
                    c.t[ch]
                        .iter()
                        .zip(&y[ch])
                        .map(|(&t, &y)| t as f64 * y)
                        .sum()
                })
                .collect()
        });
        let yy = std::array::from_fn(|ch| y[ch].iter().map(|v| v * v).sum());
        (
            Dictionary {
                directions,
                gram,
                b,
                yy,
            },
            n,
        )
    }

    /// Sum of squared residuals of the candidates `set` with their best non-negative
    /// radiances: exact, over every passive subset (the optimum is the unconstrained one on
    /// its passive set, and feasible; every feasible such point bounds it from above).
    pub fn sse(&self, set: &[usize]) -> f64 {
        let n = self.directions.len();
        (0..3)
            .map(|ch| {
                let (g, b) = (&self.gram[ch], &self.b[ch]);
                let mut best = self.yy[ch];
                for mask in 1u32..(1 << set.len()) {
                    let p: Vec<usize> = (0..set.len())
                        .filter(|i| mask >> i & 1 == 1)
                        .map(|i| set[i])
                        .collect();
                    let gp = p
                        .iter()
                        .flat_map(|&i| p.iter().map(move |&j| g[i * n + j]))
                        .collect();
                    let bp: Vec<f64> = p.iter().map(|&i| b[i]).collect();
                    if let Some(x) = solve_dense(gp, bp.clone())
                        && x.iter().all(|&v| v >= 0.0)
                    {
                        best = best
                            .min(self.yy[ch] - x.iter().zip(&bp).map(|(a, b)| a * b).sum::<f64>());
                    }
                }
                best.max(0.0)
            })
            .sum()
    }

    /// The `k` candidates that together explain the images best: by exhaustive search over
    /// sets whose directions are at least 15° apart up to three, then adding one at a time.
    pub fn best(&self, k: usize) -> Vec<Vec3> {
        let n = self.directions.len();
        let apart = |i: usize, j: usize| {
            self.directions[i].angle_between(self.directions[j]) > 15f32.to_radians()
        };
        let mut best = (f64::INFINITY, Vec::new());
        let mut consider = |set: &[usize]| {
            let e = self.sse(set);
            if e < best.0 {
                best = (e, set.to_vec());
            }
        };
        match k {
            0 => {}
            1 => (0..n).for_each(|i| consider(&[i])),
            2 => {
                for i in 0..n {
                    for j in (i + 1..n).filter(|&j| apart(i, j)) {
                        consider(&[i, j]);
                    }
                }
            }
            _ => {
                for i in 0..n {
                    for j in (i + 1..n).filter(|&j| apart(i, j)) {
                        for l in (j + 1..n).filter(|&l| apart(i, l) && apart(j, l)) {
                            consider(&[i, j, l]);
                        }
                    }
                }
            }
        }
        let mut set = best.1;
        while set.len() < k.min(n) {
            let Some(next) =
                (0..n)
                    .filter(|&i| set.iter().all(|&j| apart(i, j)))
                    .min_by(|&a, &b| {
                        let with = |i: usize| self.sse(&[set.as_slice(), &[i]].concat());
                        with(a).total_cmp(&with(b))
                    })
            else {
                break;
            };
            set.push(next);
        }
        set.iter().map(|&i| self.directions[i]).collect()
    }
}

/// Where the next light starts, with no hand-given guess: the brightest cells of the `guides`
/// (envmap estimates, by power, at least 10° from each other and from the lights already
/// `placed`; 12 in all, shared among the guides) are candidate directions from `center`; each is tried at 3 scene sizes (radius subtending 3°)
/// beside the placed lights (radiances solved exactly), and along the best two a distance
/// search (1 to 10 scene sizes) picks the start. Returns the light and the renders made; None
/// when no candidate direction is left.
pub fn next_light(
    renderer: &Renderer,
    obs: &Observations,
    guides: &[&crate::envmap::Envmap],
    placed: &[SphereLight],
    (center, size): (Vec3, f32),
    settings: &RenderSettings,
) -> (Option<SphereLight>, usize) {
    let taken: Vec<Vec3> = placed
        .iter()
        .map(|l| (l.center - center).normalize())
        .collect();
    let mut dirs: Vec<Vec3> = Vec::new();
    let per_guide = 12 / guides.len().max(1);
    for envmap in guides {
        add_bright_directions(envmap, per_guide, &taken, &mut dirs);
    }
    let mut renders = 0;
    let base = (!placed.is_empty()).then(|| {
        renders += 1;
        sphere_problem(renderer, obs, placed, settings)
    });
    let place = |dir: Vec3, d: f32| trial_light(center, dir, d);
    let mut sse = |l: SphereLight| {
        renders += 1;
        let (r, _, _) = residuals(&joined(
            base.as_ref(),
            &sphere_problem(renderer, obs, &[l], settings),
        ));
        r.iter().map(|v| v * v).sum::<f64>()
    };
    let mut by_direction: Vec<(f64, Vec3)> = dirs
        .iter()
        .map(|&d| {
            let best = [1.5f32, 3.0, 6.0]
                .iter()
                .map(|&m| sse(place(d, m * size)))
                .fold(f64::INFINITY, f64::min);
            (best, d)
        })
        .collect();
    by_direction.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut best: Option<(f64, SphereLight)> = None;
    for &(_, d) in by_direction.iter().take(2) {
        for i in 0..8 {
            let l = place(d, size * 10f32.powf(i as f32 / 7.0));
            let e = sse(l);
            if best.is_none_or(|(b, _)| e < b) {
                best = Some((e, l));
            }
        }
    }
    (best.map(|b| b.1), renders)
}

/// Starting lights all at once: `directions` from `center` (the [`Dictionary`]'s best set);
/// each light in turn is placed at the distance (1 to 10 scene
/// sizes, radius subtending 3°) whose exactly-fitted radiances explain the images best, the
/// others held at their current place. Returns the lights and the renders made.
pub fn initialise(
    renderer: &Renderer,
    obs: &Observations,
    directions: &[Vec3],
    (center, size): (Vec3, f32),
    settings: &RenderSettings,
) -> (Vec<SphereLight>, usize) {
    let place = |dir: Vec3, d: f32| trial_light(center, dir, d);
    let mut lights: Vec<SphereLight> = directions.iter().map(|&d| place(d, 3.0 * size)).collect();
    let mut renders = 0;
    for i in 0..lights.len() {
        let mut best = (f64::INFINITY, lights[i]);
        for j in 0..8 {
            let mut trial = lights.clone();
            trial[i] = place(directions[i], size * 10f32.powf(j as f32 / 7.0));
            let (r, _, _) = residuals(&sphere_problem(renderer, obs, &trial, settings));
            renders += 1;
            let sse: f64 = r.iter().map(|v| v * v).sum();
            if sse < best.0 {
                best = (sse, trial[i]);
            }
        }
        lights[i] = best.1;
    }
    (lights, renders)
}

/// Settings of [`fit_sphere_models`].
#[derive(Debug, Clone, Copy)]
pub struct SphereSettings {
    /// Most lights to fit.
    pub k: usize,
    /// Fit only the K-light model, from the [`Dictionary`]'s best set of K (the fast path of
    /// `--model spheres:K`); else the nested sequence.
    pub at_once: bool,
    /// Samples and seed of the start search's renders ([`next_light`]).
    pub search: RenderSettings,
    pub refine: RefineSettings,
}

impl SphereSettings {
    /// The defaults (with 4×4 bins, [`Observations::bin`]): a 32-sample distance search,
    /// 64-sample residuals and 16-sample Jacobians, at most 20 Levenberg–Marquardt steps.
    /// Measured on the bundled scene: centres within 1.4% of their distance, power within
    /// 3.2%, in 9 s (128-sample residuals: 1.1%, 1.8%, 13 s).
    pub fn new(k: usize, render: &RenderSettings) -> Self {
        // Every light sampled at every vertex: the transports are rendered at unit radiance,
        // where picking one light would toss a coin between a bright and a dim one.
        let at = |spp, offset| RenderSettings {
            spp,
            seed: render.seed.wrapping_add(offset),
            every_light: true,
            // A trial light crossing a view must not black out what the view sees there.
            camera_sees_lights: false,
            ..*render
        };
        SphereSettings {
            k,
            at_once: false,
            search: at(32, 3),
            refine: RefineSettings {
                residual: at(64, 5),
                jacobian: at(16, 6),
                max_iterations: 20,
                fixed: 0,
                polish_radii: true,
                radiance_spp: 256,
            },
        }
    }
}

/// How well the images pin a recovered light down.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, serde::Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "snake_case", tag = "status")]
pub enum LightStatus {
    /// A light 25% nearer or farther explains the images worse by more than two standard
    /// deviations of the residual noise.
    Identified,
    /// Direction and power fit, but the images cannot tell this light from one 25% nearer
    /// or farther (same apparent size, radiance refitted) at two standard deviations: no
    /// shadow or parallax measures its distance.
    DistanceUnidentified,
    /// Within a few degrees of a brighter light (seen from the scene centre): the images
    /// cannot separate the two, so it was merged into that one.
    Merged { into: usize },
    /// Less than 0.1% of the light in the images: the light changes no pixel (e.g. below the
    /// table).
    NoContribution,
}

/// One recovered light and how well it is determined.
#[derive(Debug, Clone, Serialize, schemars::JsonSchema)]
pub struct FittedLight {
    #[serde(with = "light_json")]
    #[schemars(with = "light_json::Light")]
    pub light: SphereLight,
    #[serde(flatten)]
    pub status: LightStatus,
    /// How many standard deviations of the residual noise worse the fit gets with the light
    /// 25% nearer or farther (the smaller of the two, `√(Δ SSE / σ²)`): the distance test.
    pub distance_profile_sigmas: Option<f64>,
    /// One standard deviation of the centre along its direction from the scene centre, and
    /// across it (metres, per axis), from [`uncertainty`]'s sandwich covariance (None where the
    /// images hold no measure of it). Over 20 seeds of the bundled scene the 95% intervals
    /// held the truth for direction 95%, distance 98%, radius 87% and power 98% of the
    /// lights; over the 15-scenario study (2 seeds) 98%, 98%, 92%, 95% (docs/results.md).
    pub distance_sigma_m: Option<f64>,
    pub lateral_sigma_m: Option<f64>,
    /// One standard deviation of the direction from the scene centre, per axis, degrees.
    pub direction_sigma_degrees: Option<f64>,
    pub radius_sigma_relative: Option<f64>,
    /// One standard deviation of the power (luminance × radius²), relative.
    pub power_sigma_relative: Option<f64>,
    /// One standard deviation of the colour: each channel of the radiance divided by its
    /// luminance (linear RGB, so a white light is (1, 1, 1); absolute, as a channel may be 0).
    pub colour_sigma: Option<[f64; 3]>,
    /// The radius's 95% interval lies within a factor [`IDENTIFIED_FACTOR`] of it either way
    /// (None where not measured: the intervals are measured for the model an estimate ends
    /// with, not for every candidate).
    pub radius_identified: Option<bool>,
    /// The same of the power.
    pub power_identified: Option<bool>,
}

/// A radius or power is identified when its 95% interval lies within this factor of it
/// either way (`1.96 σ_ln < ln 1.5`).
pub const IDENTIFIED_FACTOR: f64 = 1.5;

/// Whether a relative standard deviation (of a logarithm) makes an identified value.
fn identified(sigma_ln: Option<f64>) -> bool {
    sigma_ln.is_some_and(|s| 1.96 * s < IDENTIFIED_FACTOR.ln())
}

impl FittedLight {
    /// Whether the model keeps the light: it contributes and was not merged away.
    pub fn kept(&self) -> bool {
        matches!(
            self.status,
            LightStatus::Identified | LightStatus::DistanceUnidentified
        )
    }

    /// The factor (×/÷) of the radius's 95% interval, where the images measure it.
    fn radius_factor(&self) -> Option<f64> {
        self.radius_sigma_relative.map(|s| (1.96 * s).exp())
    }

    /// The radius's 95% interval in words: "95% interval ×/÷ 1.63", or that there is none.
    pub fn radius_interval(&self) -> String {
        match self.radius_factor() {
            Some(f) => format!("95% interval ×/÷ {f:.2}"),
            None => "the images hold no measure of it".to_string(),
        }
    }
}

mod light_json {
    use crate::scene::SphereLight;
    use serde::Serializer;
    use serde::ser::SerializeStruct;

    /// What the light is written as: centre (world, metres), radius (metres), linear RGB
    /// radiance.
    #[derive(schemars::JsonSchema)]
    #[allow(dead_code)]
    pub struct Light {
        center: [f32; 3],
        radius: f32,
        radiance: [f32; 3],
    }

    pub fn serialize<S: Serializer>(l: &SphereLight, s: S) -> Result<S::Ok, S::Error> {
        let mut st = s.serialize_struct("SphereLight", 3)?;
        st.serialize_field("center", &l.center.to_array())?;
        st.serialize_field("radius", &l.radius)?;
        st.serialize_field("radiance", &l.radiance.to_array())?;
        st.end()
    }
}

/// A sphere-model fit: every light with its status, and the lights kept (identified or with
/// loose distance), which is the model.
#[derive(Debug, Clone, Serialize)]
pub struct SphereFit {
    pub requested: usize,
    pub fitted: Vec<FittedLight>,
    #[serde(skip)]
    pub start: Vec<SphereLight>,
    /// relMAE over the binned rows (transport samples against the references).
    pub fit_rel_mae: f64,
    pub iterations: usize,
    pub renders: usize,
    /// Sum of squared binned residuals after each accepted step (of the last refinement).
    pub history: Vec<f64>,
    pub seconds: f64,
    /// The envmap fitted behind the lights ([`Observations::background`]), if any.
    #[serde(skip)]
    pub background: Option<Envmap>,
}

impl SphereFit {
    /// The objective (binned sum of squared residuals) at the end of the refinement.
    fn history_last(&self) -> f64 {
        self.history.last().copied().unwrap_or(f64::INFINITY)
    }

    /// The model's name in a selection: `spheres:K`, or `envmap+spheres:K` with a background.
    pub fn model_name(&self) -> String {
        let bg = if self.background.is_some() {
            "envmap+"
        } else {
            ""
        };
        format!("{bg}spheres:{}", self.requested)
    }

    /// The fitted lights that contribute and were not merged away.
    fn kept(&self) -> impl Iterator<Item = &FittedLight> {
        self.fitted.iter().filter(|f| f.kept())
    }

    /// The model's lights: those that contribute and were not merged away.
    pub fn lights(&self) -> Vec<SphereLight> {
        self.kept().map(|f| f.light).collect()
    }

    /// Per light of [`Self::lights`], what the exports say of a radius the images do not
    /// identify: its 95% interval factor (×/÷; infinite where they hold no measure of it).
    pub fn radius_doubts(&self) -> Vec<Option<f64>> {
        self.kept()
            .map(|f| {
                (f.radius_identified == Some(false))
                    .then(|| f.radius_factor().unwrap_or(f64::INFINITY))
            })
            .collect()
    }

    /// The model as a sidecar fragment that `render-reference` accepts as is. A light whose
    /// radius the images do not pin down says so in a comment above it.
    pub fn fragment(&self) -> String {
        let mut s = String::from(
            "// Sphere lights recovered by `lightprobe estimate --model spheres`: paste into a\n// sidecar's `lights` to render with them.\nlights: [\n",
        );
        for (f, doubt) in self.kept().zip(self.radius_doubts()) {
            let l = f.light;
            if let Some(factor) = doubt {
                let words = crate::scene::export::radius_doubt_words(l.radius, factor);
                s += &format!("    // {}{}.\n", words[..1].to_uppercase(), &words[1..]);
            }
            s += &format!(
                "    Sphere(center: ({}, {}, {}), radius: {}, radiance: ({}, {}, {})),\n",
                l.center.x,
                l.center.y,
                l.center.z,
                l.radius,
                l.radiance.x,
                l.radiance.y,
                l.radiance.z
            );
        }
        s + "],\n"
    }
}

/// Power of a light as seen from afar: luminance × radius² (× π, dropped).
pub fn power(l: &SphereLight) -> f32 {
    crate::imageio::luminance(l.radiance) * l.radius * l.radius
}

/// Angular radius of a light seen from `center`, radians.
fn angular_radius(l: &SphereLight, center: Vec3) -> f32 {
    (l.radius / (l.center - center).length().max(l.radius)).asin()
}

/// Fits 1, 2, … up to `settings.k` sphere lights, greedily: each model is the previous one's
/// lights plus the [`next_light`] start, all refined together by [`refine`]; then each light
/// is judged. A new light that lands within 2° plus their angular radii of another (the images
/// cannot separate the pair) is marked merged, one that gets no radiance as contributing
/// nothing; either ends the sequence, as does running out of candidate directions or a light
/// that lowers the objective by less than 5% (the data need no more), as does `go_on`
/// returning false for the fit just made (the caller's judgement, e.g. a model already at the
/// images' noise). Returns the fits in order of light count (nested, so `seconds` and
/// `renders` are cumulative). `center` and `size` are the scene's centre and size (metres).
pub fn fit_sphere_models(
    renderer: &Renderer,
    obs: &Observations,
    envmap: &crate::envmap::Envmap,
    center: Vec3,
    size: f32,
    settings: &SphereSettings,
    go_on: &mut dyn FnMut(&SphereFit) -> bool,
) -> Vec<SphereFit> {
    let t0 = Instant::now();
    let mut renders = 0;
    let mut iterations = 0;
    let mut lights: Vec<SphereLight> = Vec::new();
    let mut fits = Vec::new();
    // The joint start's candidates, rendered once for every light count.
    let coarse = RenderSettings {
        spp: (settings.search.spp / 4).max(1),
        ..settings.search
    };
    let mut dictionary: Option<Dictionary> = None;
    let mut joint_start = |k: usize, renders: &mut usize| {
        let d = dictionary.get_or_insert_with(|| {
            let (d, r) = Dictionary::new(renderer, obs, envmap, (center, size), &coarse);
            *renders += r;
            d
        });
        let (start, r) = initialise(renderer, obs, &d.best(k), (center, size), &settings.search);
        *renders += r;
        start
    };
    if settings.at_once {
        let mut r = 0;
        let start = joint_start(settings.k, &mut r);
        let refined = refine(renderer, obs, &start, center, &settings.refine);
        let (fitted, j) = judge(renderer, obs, &refined, center, &settings.refine.residual);
        let fit = SphereFit {
            requested: settings.k,
            fitted,
            start,
            fit_rel_mae: refined.rel_mae,
            iterations: refined.iterations,
            renders: r + refined.evaluations + j,
            history: refined.history,
            seconds: t0.elapsed().as_secs_f64(),
            background: None,
        };
        go_on(&fit);
        return vec![fit];
    }
    let mut fitted_lights: Vec<SphereLight> = Vec::new();
    for k in 1..=settings.k {
        // Where the lights found so far leave light unexplained: an envmap fitted to the
        // residual images (the first light looks at the envmap estimate itself).
        let residual_env;
        let guides = if fitted_lights.is_empty() {
            vec![envmap]
        } else {
            renders += 1;
            residual_env = residual_envmap(
                renderer,
                obs,
                &fitted_lights,
                envmap.grid.rings(),
                &settings.search,
            );
            vec![&residual_env, envmap]
        };
        let (next, r) = next_light(
            renderer,
            obs,
            &guides,
            &lights,
            (center, size),
            &settings.search,
        );
        renders += r;
        let Some(next) = next else { break };
        let mut start = lights.clone();
        start.push(next);
        let start_greedy = start.clone();
        // The new light alone first (the others are at their optimum), then all together.
        let mut begin = start_greedy;
        if k > 1 {
            let alone = RefineSettings {
                fixed: k - 1,
                max_iterations: 8,
                polish_radii: false,
                radiance_spp: 0,
                ..settings.refine
            };
            let r = refine(renderer, obs, &start, center, &alone);
            renders += r.evaluations;
            iterations += r.iterations;
            begin = r.lights;
        }
        // A greedy start can stay in the compromise the smaller model found between two
        // lights; the best set of k candidates, chosen together, competes. Both take a few
        // steps, and the one lower then is refined to the end (refining both to the end cost
        // twice as much; the sphere study's lights came out as accurate with the race).
        if k > 1 {
            let together = joint_start(k, &mut renders);
            let race = RefineSettings {
                max_iterations: 4,
                polish_radii: false,
                radiance_spp: 0,
                ..settings.refine
            };
            let greedy = refine(renderer, obs, &begin, center, &race);
            let joint = refine(renderer, obs, &together, center, &race);
            renders += greedy.evaluations + joint.evaluations;
            iterations += greedy.iterations + joint.iterations;
            begin = if joint.history.last() < greedy.history.last() {
                start = together;
                joint.lights
            } else {
                greedy.lights
            };
        }
        let refined = refine(renderer, obs, &begin, center, &settings.refine);
        renders += refined.evaluations;
        iterations += refined.iterations;
        let (fitted, r) = judge(renderer, obs, &refined, center, &settings.refine.residual);
        renders += r;
        let done = fitted.iter().any(|f| {
            f.status != LightStatus::Identified && f.status != LightStatus::DistanceUnidentified
        });
        fitted_lights = refined.lights.clone();
        lights = refined
            .lights
            .iter()
            .map(|l| SphereLight {
                radiance: Vec3::ONE,
                ..*l
            })
            .collect();
        fits.push(SphereFit {
            requested: k,
            fitted,
            start,
            fit_rel_mae: refined.rel_mae,
            iterations,
            renders,
            history: refined.history,
            seconds: t0.elapsed().as_secs_f64(),
            background: None,
        });
        let gain = match fits.as_slice() {
            [.., before, after] => 1.0 - after.history_last() / before.history_last(),
            _ => 1.0,
        };
        let wanted = fits.last().is_some_and(&mut *go_on);
        if done || gain < 0.05 || !wanted {
            break;
        }
    }
    fits
}

/// An envmap (of `rings`) fitted to what `lights` leave unexplained in the references (the
/// residual images, rendered with `settings`): where the next light should go.
fn residual_envmap(
    renderer: &Renderer,
    obs: &Observations,
    lights: &[SphereLight],
    rings: u32,
    settings: &RenderSettings,
) -> crate::envmap::Envmap {
    let l = Lights::new(lights.to_vec());
    let with = renderer.with_lights(&l);
    let residual: Vec<Image> = obs
        .cameras
        .iter()
        .zip(obs.references)
        .enumerate()
        .map(|(v, (cam, reference))| {
            // Only the pixels the fit compares (a large capture's others would cost a render
            // of every view per light added).
            let mask = &obs.masks[v];
            let fitted = |i: u32| mask[i as usize];
            let acc = crate::render::RadianceAccumulator(&l);
            let frame =
                with.render_some(cam, 3000 + v as u64, settings, &acc, Some(&fitted), &|_| {});
            if let Some(progress) = obs.progress {
                let lit = mask.iter().filter(|&&m| m).count() as u64;
                progress(lit * settings.spp as u64);
            }
            let pred = frame.into_image();
            Image {
                rgb: reference
                    .rgb
                    .iter()
                    .zip(&pred.rgb)
                    .map(|(r, p)| *r - *p)
                    .collect(),
                ..reference.clone()
            }
        })
        .collect();
    let fit = super::FitSettings {
        holdout: obs.holdout,
        ..super::FitSettings::new(settings, rings, super::Solver::Nnls, 2 * settings.spp, 1)
    };
    // Its transport reports pixels, each lit at the fit's samples.
    let spp = fit.transport.spp as u64;
    let progress = |pixels: u64| {
        if let Some(progress) = obs.progress {
            progress(pixels * spp);
        }
    };
    super::fit(renderer, obs.cameras, &residual, obs.masks, &fit, &progress).envmap
}

/// The joint covariance of a sphere model's parameters: per light its [`Polar`] coordinates
/// (two tangent angles in radians, Δ ln distance, Δ ln sin angular radius), then per column
/// of the problem its linear unknown in R, G, B: for a light its radiance × sin² of its
/// angular radius (what it delivers from afar: a light's size then only widens penumbrae, so
/// an unseen size is one coordinate, not a trade with its radiance), for a background cell its
/// radiance.
///
/// The sandwich `N⁻¹ (Σ_i g_i g_iᵀ) N⁻¹`, with `N = ½ (J_aᵀ J_b + J_bᵀ J_a)` and
/// `g_i = ½ (J_a,i r_b,i + J_b,i r_a,i)` each bin's share of the gradient (its three channels
/// summed: they share their paths' noise), from a twin
/// render at the final lights ([`twin_problem`]: another seed, half the residual's samples
/// per half). It holds the references' noise and the renders' alike, whatever their
/// distribution, with no noise level assumed. (Minimising `r_aᵀ r_b` in the refinement
/// itself, which this sandwich describes exactly, was tried: intervals as calibrated, but
/// centres 25–60% less accurate with half the samples per render, and one radius collapsed.) `N` pairs two independent halves, so a
/// parameter the images barely see (a light's radius) does not get a large `JᵀJ` from noise
/// alone, as the single render's `JᵀJ` did: the LM loop's own `σ² (JᵀJ)⁻¹` understated the
/// radius's error 39-fold on the bundled scene. Directions where `N` is not clearly positive
/// (noise exceeds signal) are floored at their curvature's noise: the data bound them only
/// that far.
pub struct Uncertainty {
    /// Parameters: 4 per light, then 3 per column.
    pub n: usize,
    /// Row-major `n × n`; infinite on the diagonal of unidentified parameters.
    pub covariance: Vec<f64>,
}

impl Uncertainty {
    pub fn var(&self, a: usize, b: usize) -> f64 {
        self.covariance[a * self.n + b]
    }

    /// Variance of `gᵀ θ` (infinite where `g` leans on an unidentified parameter).
    pub fn var_of(&self, g: &[(usize, f64)]) -> f64 {
        g.iter()
            .flat_map(|&(a, ga)| g.iter().map(move |&(b, gb)| ga * gb * self.var(a, b)))
            .sum()
    }
}

/// Most unknowns [`uncertainty`] measures intervals over (8 lights with a 9-ring background:
/// 326; a second or two).
pub const MAX_INTERVAL_UNKNOWNS: usize = 330;

/// Whether [`uncertainty`] measures intervals for `lights` sphere lights in front of
/// `background`: the products it forms cost unknowns² × rows, so a fine background (25 rings:
/// 2,214 radiance unknowns, hours) goes without, past [`MAX_INTERVAL_UNKNOWNS`].
pub fn intervals_measured(lights: usize, background: Option<&RingGrid>) -> bool {
    let unknowns = 4 * lights + 3 * (lights + background.map_or(0, |g| g.cell_count()));
    unknowns <= MAX_INTERVAL_UNKNOWNS
}

/// [`Uncertainty`] of `lights` (with `radiance` per column) at the residual's settings; None
/// where not [`intervals_measured`].
pub fn uncertainty(
    renderer: &Renderer,
    obs: &Observations,
    lights: &[SphereLight],
    radiance: &[Vec3],
    center: Vec3,
    residual: &RenderSettings,
) -> Option<Uncertainty> {
    // Kept camera paths would be two more sets per view: these renders walk their own.
    let obs = &Observations {
        paths: None,
        ..*obs
    };
    let at = RenderSettings {
        seed: residual.seed.wrapping_add(7_919),
        every_light: true,
        camera_sees_lights: false,
        ..*residual
    };
    if !intervals_measured(lights.len(), obs.background) {
        return None;
    }
    let polar: Vec<Polar> = lights.iter().map(|l| Polar::of(l, center)).collect();
    let sin2: Vec<f64> = polar
        .iter()
        .map(|p| (2.0 * p.ln_sin_radius).exp())
        .collect();
    let base = twin_problem(renderer, obs, lights, None, &at);
    let (rows, cols) = (base.rows(), base.lights);
    // `twin_problem` always sets the twin; borrowed, not copied (one copy per parameter).
    fn twin_of(p: &SphereProblem) -> &[Vec<f32>; 3] {
        p.twin.as_ref().expect("twin_problem sets the twin")
    }
    let (base_a, base_b) = (&base.t, twin_of(&base));
    // Columns of the Jacobian of `T(θ) L − y` at fixed L, per half, channel-major rows.
    let (mut ja, mut jb): (Vec<Vec<f64>>, Vec<Vec<f64>>) = (Vec::new(), Vec::new());
    let steps = [0.005, 0.005, 0.02, 0.03];
    for j in 0..4 * lights.len() {
        let (l, h) = (j / 4, steps[j % 4]);
        let mut q = [0.0; 4];
        q[j % 4] = h;
        let mut moved = lights.to_vec();
        moved[l] = polar[l].moved(&q, center).1;
        let column = twin_problem(renderer, obs, &moved, Some(l), &at);
        // At fixed radiance × sin²: the moved light's radiance is scaled by the step's
        // 1/sin² (exactly, not to first order: a 3% step's second-order term would leave a
        // copy of the light's own column in the derivative).
        let own = if j % 4 == 3 { (-2.0 * h).exp() } else { 1.0 };
        let derivative = |from: &[Vec<f32>; 3], to: &[Vec<f32>; 3]| {
            let mut d = Vec::with_capacity(3 * rows);
            for ch in 0..3 {
                let l_ch = radiance[l][ch] as f64;
                for (row, &v) in from[ch].chunks_exact(cols).zip(&to[ch]) {
                    d.push((v as f64 * own - row[l] as f64) / h * l_ch);
                }
            }
            d
        };
        ja.push(derivative(base_a, &column.t));
        jb.push(derivative(base_b, twin_of(&column)));
    }
    for c in 0..cols {
        let per = 1.0 / sin2.get(c).copied().unwrap_or(1.0);
        for want in 0..3 {
            let linear = |t: &[Vec<f32>; 3]| {
                let mut d = vec![0.0; 3 * rows];
                for (i, row) in t[want].chunks_exact(cols).enumerate() {
                    d[want * rows + i] = row[c] as f64 * per;
                }
                d
            };
            ja.push(linear(base_a));
            jb.push(linear(base_b));
        }
    }
    let residual_of = |t: &[Vec<f32>; 3]| -> Vec<f64> {
        (0..3)
            .flat_map(|ch| {
                t[ch]
                    .chunks_exact(cols)
                    .zip(&base.y[ch])
                    .map(move |(row, y)| {
                        row.iter()
                            .zip(radiance)
                            .map(|(&t, l)| t as f64 * l[ch] as f64)
                            .sum::<f64>()
                            - y
                    })
            })
            .collect()
    };
    let (ra, rb) = (residual_of(base_a), residual_of(base_b));
    let n = ja.len();
    if n == 0 {
        return None;
    }
    let normal = faer::Mat::<f64>::from_fn(n, n, |i, j| {
        0.5 * (dot(&ja[i], &jb[j]) + dot(&ja[j], &jb[i]))
    });
    // One bin's share of the gradient, over its three channels together: a bin's R, G and B
    // come from the same paths, so their noise is shared.
    let per_bin = |row: usize, p: usize| -> f64 {
        (0..3)
            .map(|ch| {
                let r = ch * rows + row;
                0.5 * (ja[p][r] * rb[r] + jb[p][r] * ra[r])
            })
            .sum()
    };
    let mut meat = faer::Mat::<f64>::zeros(n, n);
    let mut gi = vec![0.0; n];
    for row in 0..rows {
        for (p, g) in gi.iter_mut().enumerate() {
            *g = per_bin(row, p);
        }
        for p in 0..n {
            if gi[p] != 0.0 {
                for q in 0..n {
                    meat[(p, q)] += gi[p] * gi[q];
                }
            }
        }
    }
    // The parameters the images bear on at all (positive curvature of their own); the others
    // (a background cell nothing sees, a size whose cross-curvature is noise) are unknown and
    // kept out of the decomposition, where rounding alone would decide their sign.
    let live: Vec<usize> = (0..n).filter(|&i| normal[(i, i)] > 0.0).collect();
    let m = live.len();
    // Scaled to a unit diagonal so that the floor below compares parameters of different
    // units alike.
    let scale: Vec<f64> = live.iter().map(|&i| 1.0 / normal[(i, i)].sqrt()).collect();
    let scaled = faer::Mat::<f64>::from_fn(m, m, |a, b| {
        normal[(live[a], live[b])] * scale[a] * scale[b]
    });
    let eigen = scaled.self_adjoint_eigen(faer::Side::Lower).ok()?;
    let (values, vectors) = (eigen.S(), eigen.U());
    // Each direction's curvature is itself a sum over bins of products of the two halves:
    // its standard error comes from the bins' spread. Where the curvature is not three of
    // those above zero, the images do not pin that direction down better than noise does:
    // it is floored there, so its parameters get the wide variance the data allow instead of
    // a number made of noise (or a negative one).
    let mut inverse = faer::Mat::<f64>::zeros(n, n);
    for k in 0..m {
        let v: Vec<f64> = (0..m).map(|a| vectors[(a, k)] * scale[a]).collect();
        let along = |j: &[Vec<f64>], r: usize| (0..m).map(|a| v[a] * j[live[a]][r]).sum::<f64>();
        let spread = (0..rows)
            .map(|row| {
                (0..3)
                    .map(|ch| along(&ja, ch * rows + row) * along(&jb, ch * rows + row))
                    .sum::<f64>()
                    .powi(2)
            })
            .sum::<f64>()
            .sqrt();
        let lambda = values[k].max(3.0 * spread);
        if lambda.is_nan() || lambda <= 0.0 {
            return None;
        }
        for a in 0..m {
            for b in 0..m {
                // Back to the parameters' units: N⁻¹ = S (scaled N)⁻¹ S.
                inverse[(live[a], live[b])] +=
                    vectors[(a, k)] * vectors[(b, k)] / lambda * scale[a] * scale[b];
            }
        }
    }
    let sandwich = &inverse * &meat * &inverse;
    let mut covariance: Vec<f64> = (0..n * n).map(|ij| sandwich[(ij / n, ij % n)]).collect();
    for i in (0..n).filter(|i| !live.contains(i)) {
        covariance[i * n + i] = f64::INFINITY;
    }
    covariance
        .iter()
        .all(|v| !v.is_nan())
        .then_some(Uncertainty { n, covariance })
}

/// Judges each refined light: merged (inseparable from a brighter one), contributing nothing,
/// or identified or not in distance by the profile test (the objective with the light 25%
/// nearer or farther at the same apparent size, radiances refitted, same random numbers, in
/// units of the residual variance). Returns the verdicts and the renders made.
pub fn judge(
    renderer: &Renderer,
    obs: &Observations,
    refined: &Refined,
    center: Vec3,
    residual: &RenderSettings,
) -> (Vec<FittedLight>, usize) {
    let l = &refined.lights;
    let p0 = sphere_problem(renderer, obs, l, residual);
    let (r0, radiance0, _) = residuals(&p0);
    let mut renders = 1;
    let mut sse_at = |lights: &[SphereLight]| {
        renders += 1;
        let (r, _, _) = residuals(&sphere_problem(renderer, obs, lights, residual));
        r.iter().map(|v| v * v).sum::<f64>()
    };
    let (f0, rows) = (r0.iter().map(|v| v * v).sum::<f64>(), r0.len());
    // Parameters: 4 per light's geometry, 3 per column's radiance (lights and background).
    let sigma2 = f0 / (rows as f64 - (4 * l.len() + 3 * p0.lights) as f64).max(1.0);
    // Each light's share of the light in the images: its predicted pixels over the
    // references'. (Not its power: a light below the table can pick up a huge radiance from
    // the few samples that slip through mesh edges, and still light nothing.)
    let total: f64 = p0.y.iter().flatten().map(|v| v.abs()).sum();
    let share: Vec<f64> = (0..l.len())
        .map(|j| {
            let lit: f64 = (0..3)
                .map(|ch| {
                    p0.t[ch]
                        .chunks_exact(p0.lights)
                        .map(|row| row[j] as f64 * radiance0[j][ch] as f64)
                        .sum::<f64>()
                })
                .sum();
            lit / total.max(f64::MIN_POSITIVE)
        })
        .collect();
    let merged_into = |j: usize| {
        (0..l.len()).find(|&i| {
            i != j
                && share[i] >= share[j]
                && (l[i].center - center).angle_between(l[j].center - center)
                    < angular_radius(&l[i], center)
                        + angular_radius(&l[j], center)
                        + 2f32.to_radians()
        })
    };
    let mut fitted = Vec::new();
    for (j, light) in l.iter().enumerate() {
        // At least 0.1% of the light in the images.
        let contributes = share[j] > 1e-3;
        let merged = merged_into(j).filter(|_| contributes);
        let profile = (contributes && merged.is_none()).then(|| {
            let worst = [0.8f32, 1.25]
                .iter()
                .map(|&scale| {
                    let mut moved = l.clone();
                    moved[j].center = center + (light.center - center) * scale;
                    moved[j].radius *= scale;
                    (sse_at(&moved) - f0).max(0.0)
                })
                .fold(f64::INFINITY, f64::min);
            (worst / sigma2.max(f64::MIN_POSITIVE)).sqrt()
        });
        let status = match (merged, profile) {
            (Some(into), _) => LightStatus::Merged { into },
            (None, None) => LightStatus::NoContribution,
            (None, Some(z)) if z < 2.0 => LightStatus::DistanceUnidentified,
            (None, Some(_)) => LightStatus::Identified,
        };
        fitted.push(FittedLight {
            light: *light,
            status,
            distance_profile_sigmas: profile,
            distance_sigma_m: None,
            lateral_sigma_m: None,
            direction_sigma_degrees: None,
            radius_sigma_relative: None,
            power_sigma_relative: None,
            colour_sigma: None,
            radius_identified: None,
            power_identified: None,
        });
    }
    (fitted, renders)
}

/// Measures the 95% intervals of `fitted`'s lights ([`uncertainty`]) at the residual's
/// settings, in place: the model an estimate ends with gets them (2 + 8 renders per light at
/// half the residual's samples, about 1 s for two lights on the bundled scene).
pub fn measure_intervals(
    renderer: &Renderer,
    obs: &Observations,
    fitted: &mut [FittedLight],
    center: Vec3,
    residual: &RenderSettings,
) {
    if !intervals_measured(fitted.len(), obs.background) {
        // Not measured: the flags stay None rather than read as "not identified".
        return;
    }
    let l: Vec<SphereLight> = fitted.iter().map(|f| f.light).collect();
    let n = 4 * l.len();
    let (radiance, _) = solve_radiance(&sphere_problem(renderer, obs, &l, residual));
    let Some(unc) = uncertainty(renderer, obs, &l, &radiance, center, residual) else {
        return;
    };
    for (j, f) in fitted.iter_mut().enumerate() {
        let distance = (f.light.center - center).length() as f64;
        if distance <= 0.0 {
            continue;
        }
        // The standard deviation of gᵀθ, None where the images hold no measure of it.
        let sd = |g: &[(usize, f64)]| {
            let v = unc.var_of(g);
            v.is_finite().then(|| v.max(0.0).sqrt())
        };
        let at = |k: usize| 4 * j + k;
        // Two tangent angles: their mean variance, per axis.
        let angle = sd(&[(at(0), 1.0)])
            .zip(sd(&[(at(1), 1.0)]))
            .map(|(a, b)| ((a * a + b * b) / 2.0).sqrt());
        // ln r = ln d + ln sin α.
        let radius = sd(&[(at(2), 1.0), (at(3), 1.0)]);
        // Power = luminance(L) r² = luminance(Φ) d², with Φ = L sin²α the unknown
        // [`uncertainty`] solves for: ln P = ln luminance(Φ) + 2 ln d.
        let sin2 = (f.light.radius as f64 / distance).powi(2);
        let lum = crate::imageio::luminance(radiance[j]).max(f32::MIN_POSITIVE) as f64 * sin2;
        let w = crate::imageio::LUMINANCE;
        let mut g = vec![(at(2), 2.0)];
        g.extend((0..3).map(|ch| (n + 3 * j + ch, w[ch] as f64 / lum)));
        let power = sd(&g);
        // Colour c = Φ / luminance(Φ) (the size cancels): ∂c_k/∂Φ_m = (δ_km − c_k w_m) / lum.
        let phi: Vec<f64> = (0..3).map(|ch| radiance[j][ch] as f64 * sin2).collect();
        let colour: Option<Vec<f64>> = (0..3)
            .map(|k| {
                let c_k = phi[k] / lum;
                let g: Vec<(usize, f64)> = (0..3)
                    .map(|m| {
                        let own = if m == k { 1.0 } else { 0.0 };
                        (n + 3 * j + m, (own - c_k * w[m] as f64) / lum)
                    })
                    .collect();
                sd(&g)
            })
            .collect();
        f.colour_sigma = colour.map(|c| [c[0], c[1], c[2]]);
        f.distance_sigma_m = sd(&[(at(2), 1.0)]).map(|v| distance * v);
        f.lateral_sigma_m = angle.map(|v| distance * v);
        f.direction_sigma_degrees = angle.map(f64::to_degrees);
        f.radius_sigma_relative = radius;
        f.power_sigma_relative = power;
        f.radius_identified = Some(identified(radius));
        f.power_identified = Some(identified(power));
    }
}

#[cfg(test)]
mod tests {
    use super::{FIT_PIXELS, fit_masks, intervals_measured, line_search};
    use crate::envmap::RingGrid;
    use crate::scene::Camera;
    use glam::Vec3;

    #[test]
    fn a_large_capture_is_fitted_on_whole_blocks_spread_over_every_view() {
        let cams: Vec<Camera> = (0..6)
            .map(|v| Camera::look_at(&format!("v{v}"), Vec3::Z * 3.0, Vec3::ZERO, 0.8, 250, 190))
            .collect();
        let cams: Vec<&Camera> = cams.iter().collect();
        // Each view sees a different half-disc or so: masks with ragged edges.
        let masks: Vec<Vec<bool>> = (0..6)
            .map(|v| {
                (0..250 * 190)
                    .map(|i| {
                        let (x, y) = ((i % 250) as f32, (i / 250) as f32);
                        (x - 100.0 - 5.0 * v as f32).hypot(y - 90.0) < 80.0 + 3.0 * v as f32
                    })
                    .collect()
            })
            .collect();
        let count = |m: &[Vec<bool>]| m.iter().flatten().filter(|&&k| k).count();
        assert!(count(&masks) > 2 * FIT_PIXELS);
        let fit = fit_masks(&cams, &masks, 4, FIT_PIXELS);
        let kept = count(&fit);
        assert!(kept <= FIT_PIXELS && kept > FIT_PIXELS - 16, "{kept}");
        for (v, (f, m)) in fit.iter().zip(&masks).enumerate() {
            // A subset of the mask, in every view, and whole blocks: a kept pixel's block
            // keeps every pixel the mask holds in it.
            assert!(f.iter().zip(m).all(|(&f, &m)| !f || m));
            let share = f.iter().filter(|&&k| k).count() as f64 / kept as f64;
            assert!(share > 0.1, "view {v}: {share}");
            for i in (0..f.len()).filter(|&i| f[i]) {
                let (bx, by) = (i % 250 / 4 * 4, i / 250 / 4 * 4);
                for y in by..(by + 4).min(190) {
                    for x in bx..(bx + 4).min(250) {
                        assert_eq!(f[y * 250 + x], m[y * 250 + x], "view {v} pixel {x},{y}");
                    }
                }
            }
        }
        // The same every time; a small capture is kept whole.
        assert_eq!(fit_masks(&cams, &masks, 4, FIT_PIXELS), fit);
        let small: Vec<Vec<bool>> = masks[..1].to_vec();
        assert_eq!(fit_masks(&cams[..1], &small, 4, FIT_PIXELS), small);
    }

    #[test]
    fn intervals_are_measured_up_to_eight_lights_before_a_nine_ring_background() {
        // The most `--model` allows (8 lights) before a 9-ring background: measured; one more
        // light, or one more ring pair behind a single light: not.
        let nine = RingGrid::new(9);
        assert!(intervals_measured(8, Some(&nine)));
        assert!(!intervals_measured(9, Some(&nine)));
        assert!(!intervals_measured(1, Some(&RingGrid::new(11))));
        assert!(intervals_measured(8, None));
    }

    #[test]
    fn line_search_walks_down_to_a_far_minimum_and_refines_a_near_one() {
        let mut calls = 0;
        // Far downhill: the steps double (0.35, 1.05, 2.45) past 1.3, then the parabola
        // through the last three points lands on the quadratic's minimum exactly.
        let (v, t) = line_search(1.69, 0.35, |t| {
            calls += 1;
            ((t - 1.3) * (t - 1.3), t)
        })
        .unwrap();
        assert!((t - 1.3).abs() < 1e-9 && v < 1e-12, "{t} {v}");
        assert_eq!(calls, 4);
        // Bracketed about 0 (the minimum at −0.1, within the first steps): one parabola.
        let (_, t) = line_search(0.01, 0.35, |t| ((t + 0.1) * (t + 0.1), t)).unwrap();
        assert!((t + 0.1).abs() < 1e-9, "{t}");
        // Already at the minimum, or flat: nothing beats f0.
        assert!(line_search(0.0, 0.35, |t| (t * t, t)).is_none());
        assert!(line_search(1.0, 0.35, |t| (1.0, t)).is_none());
    }
}
