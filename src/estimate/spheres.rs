//! Sphere lights as the light model (issue 9, its linear part). With the lights' centres and
//! radii fixed, every pixel is linear in their radiances, `I_α = Σ_k T_kα L_kα`, so the
//! radiances come from a small exact NNLS on the per-light transport T_k, and only the
//! geometry (4 numbers per light) is left to a non-linear search: variable projection.
//!
//! The one path tracer estimates T_k: it renders the lights at unit radiance and accumulates,
//! per pixel, the weight each light receives (the transport's [`PerEmitterAccumulator`]). Renders of two
//! geometries with the same seed share their random numbers (common random numbers), so
//! their residuals differ by the geometry, not by noise.

use glam::Vec3;

use super::nnls;
use super::transport::{EmitterKind, PerEmitterAccumulator};
use crate::imageio::Image;
use crate::render::{Lights, RenderSettings, Renderer};
use crate::scene::{Camera, SphereLight};

/// Per-light transport of the masked pixels: per channel, `rows × lights`, row-major.
#[derive(Debug, Clone)]
pub struct SphereTransport {
    pub lights: usize,
    pub rows: usize,
    pub t: [Vec<f32>; 3],
    /// Per row: (view index, pixel index).
    pub pixel_of_row: Vec<(usize, u32)>,
}

/// Estimates the per-light transport of `geometry` (centres and radii; radiances ignored) for
/// the masked pixels of each camera. The same `settings.seed` gives the same random numbers
/// for any geometry.
pub fn sphere_transport(
    renderer: &Renderer,
    cameras: &[&Camera],
    masks: &[Vec<bool>],
    geometry: &[SphereLight],
    settings: &RenderSettings,
    progress: &(dyn Fn(u64) + Sync),
) -> SphereTransport {
    let unit: Vec<SphereLight> = geometry
        .iter()
        .map(|l| SphereLight {
            radiance: Vec3::ONE,
            ..*l
        })
        .collect();
    let lights = Lights::new(unit);
    let renderer = renderer.with_lights(&lights);
    let acc = PerEmitterAccumulator {
        kind: EmitterKind::Spheres,
        count: geometry.len(),
    };
    let mut t: [Vec<f32>; 3] = std::array::from_fn(|_| Vec::new());
    let mut pixel_of_row = Vec::new();
    for (v, (cam, mask)) in cameras.iter().zip(masks).enumerate() {
        let frame = renderer.render(cam, 2000 + v as u64, settings, &acc, progress);
        for (i, row) in frame
            .pixels
            .into_iter()
            .enumerate()
            .filter(|(i, _)| mask[*i])
        {
            for (ch, t_ch) in t.iter_mut().enumerate() {
                t_ch.extend(row.iter().map(|w| w[ch]));
            }
            pixel_of_row.push((v, i as u32));
        }
    }
    SphereTransport {
        lights: geometry.len(),
        rows: pixel_of_row.len(),
        t,
        pixel_of_row,
    }
}

/// Radiances of the lights that best explain `references` for this transport, and the
/// remaining error: `relMAE = Σ|T L − I| / Σ|I|` over the masked pixels and channels.
pub fn solve_radiance(tr: &SphereTransport, references: &[Image]) -> (Vec<Vec3>, f64) {
    let k = tr.lights;
    let mut radiance = vec![Vec3::ZERO; k];
    let (mut abs, mut ref_abs) = (0.0f64, 0.0f64);
    for ch in 0..3 {
        let y: Vec<f64> = tr
            .pixel_of_row
            .iter()
            .map(|&(v, i)| references[v].rgb[i as usize][ch] as f64)
            .collect();
        let t = &tr.t[ch];
        let mut g = vec![0.0f64; k * k];
        let mut b = vec![0.0f64; k];
        for (r, yr) in y.iter().enumerate() {
            let row = &t[r * k..(r + 1) * k];
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
        for (r, yr) in y.iter().enumerate() {
            let row = &t[r * k..(r + 1) * k];
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
    /// Samples and seed of every transport render (one seed: common random numbers).
    pub transport: RenderSettings,
    pub max_iterations: usize,
}

/// Refined geometry and radiances.
#[derive(Debug, Clone)]
pub struct Refined {
    pub lights: Vec<SphereLight>,
    /// relMAE of the fit over the masked pixels (against the transport's own prediction).
    pub rel_mae: f64,
    pub iterations: usize,
    /// Transport renders made.
    pub evaluations: usize,
    /// Sum of squared residuals after each accepted step.
    pub history: Vec<f64>,
}

/// Parameters of one light: centre x, y, z (metres) and ln(radius).
fn params(lights: &[SphereLight]) -> Vec<f64> {
    lights
        .iter()
        .flat_map(|l| {
            [
                l.center.x as f64,
                l.center.y as f64,
                l.center.z as f64,
                (l.radius as f64).ln(),
            ]
        })
        .collect()
}

fn lights_of(p: &[f64]) -> Vec<SphereLight> {
    p.chunks_exact(4)
        .map(|q| SphereLight {
            center: Vec3::new(q[0] as f32, q[1] as f32, q[2] as f32),
            radius: (q[3].exp() as f32).max(1e-3),
            radiance: Vec3::ONE,
        })
        .collect()
}

/// Residuals `T L − I` (all rows, channels) with L solved exactly, and the radiances.
fn residuals(tr: &SphereTransport, references: &[Image]) -> (Vec<f64>, Vec<Vec3>, f64) {
    let (radiance, rel) = solve_radiance(tr, references);
    let k = tr.lights;
    let mut r = Vec::with_capacity(3 * tr.rows);
    for ch in 0..3 {
        for (row, &(v, i)) in tr.t[ch].chunks_exact(k).zip(&tr.pixel_of_row) {
            let pred: f64 = row
                .iter()
                .zip(&radiance)
                .map(|(&t, l)| t as f64 * l[ch] as f64)
                .sum();
            r.push(pred - references[v].rgb[i as usize][ch] as f64);
        }
    }
    (r, radiance, rel)
}

/// Solves the small dense system `a x = b` (Gaussian elimination with partial pivoting);
/// None when singular.
fn solve_dense(mut a: Vec<f64>, mut b: Vec<f64>) -> Option<Vec<f64>> {
    let n = b.len();
    for c in 0..n {
        let p = (c..n).max_by(|&i, &j| a[i * n + c].abs().total_cmp(&a[j * n + c].abs()))?;
        if a[p * n + c].abs() < 1e-300 {
            return None;
        }
        for k in 0..n {
            a.swap(c * n + k, p * n + k);
        }
        b.swap(c, p);
        for r in c + 1..n {
            let f = a[r * n + c] / a[c * n + c];
            for k in c..n {
                a[r * n + k] -= f * a[c * n + k];
            }
            b[r] -= f * b[c];
        }
    }
    let mut x = vec![0.0; n];
    for c in (0..n).rev() {
        let s: f64 = (c + 1..n).map(|k| a[c * n + k] * x[k]).sum();
        x[c] = (b[c] - s) / a[c * n + c];
    }
    x.iter().all(|v| v.is_finite()).then_some(x)
}

/// Refines the lights' centres and radii from `start` by Levenberg–Marquardt on the
/// variable-projection residual (radiances re-solved exactly at every evaluation), with
/// forward-difference derivatives over renders that share their random numbers.
pub fn refine(
    renderer: &Renderer,
    cameras: &[&Camera],
    masks: &[Vec<bool>],
    references: &[Image],
    start: &[SphereLight],
    settings: &RefineSettings,
) -> Refined {
    let mut evaluations = 0;
    let mut eval = |p: &[f64]| {
        evaluations += 1;
        let tr = sphere_transport(
            renderer,
            cameras,
            masks,
            &lights_of(p),
            &settings.transport,
            &|_| {},
        );
        residuals(&tr, references)
    };
    let mut p = params(start);
    let (mut r, mut radiance, mut rel) = eval(&p);
    let sse = |r: &[f64]| r.iter().map(|v| v * v).sum::<f64>();
    let mut f = sse(&r);
    let mut history = vec![f];
    let mut mu = 1e-3;
    let mut iterations = 0;
    let n = p.len();
    while iterations < settings.max_iterations {
        iterations += 1;
        // Forward differences: 1 cm in position, 2% in radius.
        let mut jac: Vec<Vec<f64>> = Vec::with_capacity(n);
        for j in 0..n {
            let h = if j % 4 == 3 { 0.02 } else { 0.01 };
            let mut q = p.clone();
            q[j] += h;
            let (rj, _, _) = eval(&q);
            jac.push(rj.iter().zip(&r).map(|(a, b)| (a - b) / h).collect());
        }
        let mut a = vec![0.0; n * n];
        let mut g = vec![0.0; n];
        for i in 0..n {
            g[i] = jac[i].iter().zip(&r).map(|(x, y)| x * y).sum();
            for j in 0..n {
                a[i * n + j] = jac[i].iter().zip(&jac[j]).map(|(x, y)| x * y).sum();
            }
        }
        let mut improved = false;
        for _ in 0..8 {
            let mut damped = a.clone();
            for i in 0..n {
                damped[i * n + i] += mu * a[i * n + i].max(1e-12);
            }
            let Some(step) = solve_dense(damped, g.iter().map(|v| -v).collect()) else {
                mu *= 10.0;
                continue;
            };
            let q: Vec<f64> = p.iter().zip(&step).map(|(a, b)| a + b).collect();
            let (rq, lq, relq) = eval(&q);
            let fq = sse(&rq);
            if fq < f {
                improved = (f - fq) > 1e-4 * f;
                (p, r, radiance, rel, f) = (q, rq, lq, relq, fq);
                history.push(f);
                mu = (mu / 3.0).max(1e-9);
                break;
            }
            mu *= 4.0;
        }
        if !improved {
            break;
        }
    }
    let lights = lights_of(&p)
        .into_iter()
        .zip(&radiance)
        .map(|(l, &radiance)| SphereLight { radiance, ..l })
        .collect();
    Refined {
        lights,
        rel_mae: rel,
        iterations,
        evaluations,
        history,
    }
}

/// Starting lights from an envmap estimate, with no hand-given guess: the `k` brightest
/// clusters give directions from `center`; each light in turn is placed at the distance (from
/// 1 to 10 scene sizes, radius subtending 3°) whose exactly-fitted radiances explain the images
/// best, the others held at their current place.
#[allow(clippy::too_many_arguments)]
pub fn initialise(
    renderer: &Renderer,
    cameras: &[&Camera],
    masks: &[Vec<bool>],
    references: &[Image],
    envmap: &crate::envmap::Envmap,
    k: usize,
    center: Vec3,
    size: f32,
    settings: &RenderSettings,
) -> Vec<SphereLight> {
    let dirs: Vec<Vec3> = super::recovery::clusters(envmap)
        .into_iter()
        .take(k)
        .map(|c| c.direction)
        .collect();
    let place = |dir: Vec3, d: f32| SphereLight {
        center: center + dir * d,
        radius: d * 3f32.to_radians().tan(),
        radiance: Vec3::ONE,
    };
    let distances: Vec<f32> = (0..8).map(|i| size * 10f32.powf(i as f32 / 7.0)).collect();
    let mut lights: Vec<SphereLight> = dirs.iter().map(|&d| place(d, 3.0 * size)).collect();
    for i in 0..lights.len() {
        let mut best = (f64::INFINITY, lights[i]);
        for &d in &distances {
            let mut trial = lights.clone();
            trial[i] = place(dirs[i], d);
            let tr = sphere_transport(renderer, cameras, masks, &trial, settings, &|_| {});
            let (r, _, _) = residuals(&tr, references);
            let sse: f64 = r.iter().map(|v| v * v).sum();
            if sse < best.0 {
                best = (sse, trial[i]);
            }
        }
        lights[i] = best.1;
    }
    lights
}
