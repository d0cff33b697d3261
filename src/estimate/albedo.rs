//! Albedo fitted beside the lighting (`--fit-albedo materials`): one RGB multiplier per
//! material, of its constant albedo or of its texture's factor.
//!
//! **Why a ratio step.** For fixed lighting a pixel's value is linear in the albedo of the
//! surface it sees at one bounce (and nearly so at more: light that came back to the surface
//! is the smaller part). So a material's multiplier is moved by the ratio of the references'
//! sum to the re-render's over the pixels that see it alone ([`MaterialPixels`]), per channel,
//! between fits of the lighting ([`super::job::run`]). A ratio of sums, not a slope: the
//! re-render's noise would bias a slope low.
//!
//! **The gauge.** Albedo × light is all the images know: scaling every albedo by k and the
//! light by 1/k changes nothing at one bounce. The scale is fixed per channel by the trusted
//! materials (`--trust-albedo`), kept as given, or else by keeping the pixel-weighted
//! geometric mean of the fitted materials' multipliers at 1: each step is taken relative to
//! the anchors' mean step, and the next lighting fit absorbs the rest.
//!
//! **Observability** ([`observability`]). A material is constrained only if light that lights
//! it also lights other materials: a material lit by cells no other material sees trades its
//! albedo for those cells' radiance freely. The measure is the share of a material's image
//! that no change of the lighting can produce, `F/E` with `E = λᵀG_mλ` (its pixels' energy)
//! and `F = E − (G_mλ)ᵀG⁻¹(G_mλ)` (the part of it left when the lighting is refitted over all
//! pixels: a Schur complement), G_m the transport's TᵀT over the material's pixels, G over
//! every material's, λ the fitted radiance. 0: unconstrained; 1: the lighting cannot mimic any
//! of it.

use faer::linalg::solvers::Solve;
use glam::{DVec3, Vec2, Vec3};
use schemars::JsonSchema;
use serde::Serialize;

use super::FitSettings;
use super::transport::{self, NormalEquations, Part, Targets};
use crate::envmap::{Envmap, RingGrid};
use crate::imageio::Image;
use crate::render::{NO_MATERIAL, Renderer};
use crate::scene::{Camera, Material};

/// What `--fit-albedo` fits.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum FitAlbedo {
    /// One RGB multiplier per material: of its constant albedo, or of its texture's factor
    /// (the texture's pattern and the vertex colours are kept).
    Materials,
}

/// Fewest pixels that see a material alone for its albedo to be fitted: fewer are reported
/// [`MaterialStatus::Unseen`] and kept as given.
pub const MIN_MATERIAL_PIXELS: usize = 64;

/// Least [`observability`] of a fitted material: below it, less than 1% of its image is what
/// only its albedo can explain, and it is reported [`MaterialStatus::Unconstrained`] and kept
/// as given.
pub const MIN_OBSERVABILITY: f64 = 0.01;

/// Relative change of every multiplier below which the alternation stops: the lighting fit's
/// own noise moves a material's ratio by about 1.5% between fits (bundled scene).
pub const ALBEDO_TOLERANCE: f64 = 0.02;

/// Relative change of every multiplier below which the joint passes stop: what a pass at the
/// albedo found changes is the light between surfaces, which the one-bounce joint fit leaves
/// out, and the transport's noise.
pub const JOINT_TOLERANCE: f64 = 0.005;

/// Ridge of the joint fit (relative to the mean diagonal of TᵀT), far below the envmap fit's:
/// a ridge shrinks the cells few pixels see, and with the albedo free the materials that see
/// them take up the shrinkage (at the fit's 0.001, a ball and a box lit from below came out
/// 2.5% bright; at 1e-5 and 0, 0.2%). Only numerical safety is wanted here.
pub const JOINT_RIDGE: f64 = 1e-6;

/// Most transport passes of the joint fit.
pub const MAX_JOINT_PASSES: usize = 4;

/// How the albedo was fitted.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum AlbedoMethod {
    /// The envmap model: multipliers and envmap fitted jointly on the transport kept per
    /// material ([`MaterialSums::joint`]), a pass again at the albedo found until it holds.
    Joint,
    /// Sphere models or per-view exposures: alternating fits of the lighting and ratio steps
    /// of the albedo ([`super::job::run`]).
    Alternation,
}

/// What became of a material's albedo.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum MaterialStatus {
    /// Named in `--trust-albedo`: kept as given, it fixes the scale.
    Trusted,
    /// Fitted.
    Fitted,
    /// Fewer than [`MIN_MATERIAL_PIXELS`] pixels see it alone: kept as given.
    Unseen,
    /// Lit by light no other material's pixels see, so its albedo trades freely with that
    /// light ([`MIN_OBSERVABILITY`]): kept as given.
    Unconstrained,
}

/// One material's albedo, given and fitted.
#[derive(Debug, Clone, Serialize, JsonSchema)]
pub struct MaterialAlbedo {
    pub name: String,
    pub status: MaterialStatus,
    /// Pixels (over all views, inside the masks) that see this material alone.
    pub pixels: usize,
    /// Views with such pixels.
    pub views: usize,
    /// Share of its image only its albedo explains, 0–1 (the module doc); null where not
    /// measured (unseen, or trusted).
    pub observability: Option<f64>,
    /// Mean albedo as given (a texture's mean texel × its factor), linear RGB.
    pub given: [f32; 3],
    /// Mean albedo fitted, linear RGB.
    pub fitted: [f32; 3],
    /// `fitted / given` per channel: what multiplies the constant albedo or the texture's
    /// factor.
    pub multiplier: [f32; 3],
    /// A channel reached the bound albedo ≤ 1.
    pub at_bound: bool,
}

/// `report.json`'s `albedo`: the albedo fitted beside the lighting.
#[derive(Debug, Clone, Serialize, JsonSchema)]
pub struct AlbedoReport {
    pub fit: FitAlbedo,
    pub method: AlbedoMethod,
    /// What fixes the overall scale between albedo and light, in words.
    pub gauge: String,
    /// The materials `--trust-albedo` named.
    pub trusted: Vec<String>,
    /// Alternation: lighting fits made, the last with every sample. Joint: transport passes
    /// kept per material.
    pub fits: usize,
    /// The largest relative change of a multiplier at the last fit or pass.
    pub last_change: f64,
    /// Whether the last change was below [`ALBEDO_TOLERANCE`] (alternation) or
    /// [`JOINT_TOLERANCE`] (joint).
    pub converged: bool,
    pub materials: Vec<MaterialAlbedo>,
}

/// Where each material is seen alone: per view, per pixel, the material index the pixel's
/// centre and four inner points all hit inside the view's mask ([`Renderer::material_ids`]),
/// else [`NO_MATERIAL`].
pub struct MaterialPixels {
    pub ids: Vec<Vec<u32>>,
    /// Pixels per material.
    pub counts: Vec<usize>,
    /// Views with a pixel per material.
    pub views: Vec<usize>,
}

impl MaterialPixels {
    /// The material maps of `views` in `renderer`'s scene, inside `masks`.
    pub fn new(renderer: &Renderer, views: &[&Camera], masks: &[Vec<bool>]) -> Self {
        let n = renderer.scene.materials.len();
        let (mut counts, mut seen_in) = (vec![0usize; n], vec![0usize; n]);
        let ids: Vec<Vec<u32>> = views
            .iter()
            .zip(masks)
            .map(|(cam, mask)| {
                let mut ids = renderer.material_ids(cam);
                let mut here = vec![false; n];
                for (id, &m) in ids.iter_mut().zip(mask) {
                    if !m || *id as usize >= n {
                        *id = NO_MATERIAL;
                    } else {
                        counts[*id as usize] += 1;
                        here[*id as usize] = true;
                    }
                }
                for (s, h) in seen_in.iter_mut().zip(here) {
                    *s += h as usize;
                }
                ids
            })
            .collect();
        MaterialPixels {
            ids,
            counts,
            views: seen_in,
        }
    }

    /// The material pixel `i` of view `v` sees alone.
    pub fn of(&self, (v, i): (usize, u32)) -> Option<usize> {
        let id = self.ids[v][i as usize];
        (id != NO_MATERIAL).then_some(id as usize)
    }
}

/// Per material, `ln(Σ reference / Σ render)` per channel over the pixels that see it alone;
/// `None` where a sum of a channel is not positive (nothing to scale).
pub fn log_ratios(
    pixels: &MaterialPixels,
    references: &[Image],
    renders: &[Image],
) -> Vec<Option<DVec3>> {
    let n = pixels.counts.len();
    let (mut y, mut x) = (vec![DVec3::ZERO; n], vec![DVec3::ZERO; n]);
    for ((ids, r), q) in pixels.ids.iter().zip(references).zip(renders) {
        for ((&id, a), b) in ids.iter().zip(&r.rgb).zip(&q.rgb) {
            if id != NO_MATERIAL {
                y[id as usize] += a.as_dvec3();
                x[id as usize] += b.as_dvec3();
            }
        }
    }
    y.iter()
        .zip(&x)
        .map(|(y, x)| {
            let r = *y / *x;
            (r.min_element() > 0.0 && r.is_finite())
                .then(|| DVec3::new(r.x.ln(), r.y.ln(), r.z.ln()))
        })
        .collect()
}

/// The step of every material's log-multiplier: a free material's log ratio less the anchors'
/// pixel-weighted mean log ratio (per channel), zero for the others. The anchors are the
/// trusted materials, or without any the free ones (keeping their weighted mean at 0).
pub fn gauged_step(
    ratios: &[Option<DVec3>],
    free: &[bool],
    anchors: &[bool],
    counts: &[usize],
) -> Vec<DVec3> {
    let (mut sum, mut weight) = (DVec3::ZERO, 0.0);
    for ((r, &a), &c) in ratios.iter().zip(anchors).zip(counts) {
        if let (Some(r), true) = (r, a) {
            sum += *r * c as f64;
            weight += c as f64;
        }
    }
    let mean = if weight > 0.0 {
        sum / weight
    } else {
        DVec3::ZERO
    };
    ratios
        .iter()
        .zip(free)
        .map(|(r, &f)| match (r, f) {
            (Some(r), true) => *r - mean,
            _ => DVec3::ZERO,
        })
        .collect()
}

/// The largest log-multiplier per channel that keeps a material's mean albedo `given` at most
/// 1 (a channel given as 0 stays 0 whatever multiplies it).
pub fn upper_bound(given: Vec3) -> DVec3 {
    let g = given.as_dvec3();
    DVec3::new(bound(g.x), bound(g.y), bound(g.z))
}

fn bound(g: f64) -> f64 {
    if g > 0.0 { -g.ln() } else { f64::INFINITY }
}

/// `material` with its albedo multiplied per channel by `k` ([`Material::scaled`]).
pub fn scaled_materials(given: &[Material], k: &[DVec3]) -> Vec<Material> {
    given
        .iter()
        .zip(k)
        .map(|(m, k)| m.scaled(k.as_vec3()))
        .collect()
}

/// Bytes above which [`observability`] takes a coarser grid than the fit's: its sums are kept
/// per material.
const MATERIAL_SUMS_BYTES: usize = 256 << 20;

/// The grid [`observability`] measures on for a fit of `rings` rings and `sets` materials: the
/// fit's, or the finest coarser one whose per-material sums fit in [`MATERIAL_SUMS_BYTES`]
/// and whose cells are at most [`super::MAX_JACKKNIFE_CELLS`].
pub fn material_grid(rings: u32, sets: usize) -> RingGrid {
    (1..=rings)
        .rev()
        .map(RingGrid::new)
        .find(|g| {
            g.cell_count() <= super::MAX_JACKKNIFE_CELLS
                && sets.max(1) * NormalEquations::memory_needed(g.cell_count())
                    <= MATERIAL_SUMS_BYTES
        })
        .unwrap_or_else(|| RingGrid::new(1))
}

/// The mean radiance of `envmap` over each cell of `grid` (8 × 8 stratified directions per
/// cell, uniform in solid angle).
fn resampled(envmap: &Envmap, grid: &RingGrid) -> Vec<DVec3> {
    if grid.rings() == envmap.grid.rings() {
        return envmap.radiance().iter().map(|r| r.as_dvec3()).collect();
    }
    (0..grid.cell_count() as u32)
        .map(|c| {
            let mut sum = DVec3::ZERO;
            for a in 0..8 {
                for b in 0..8 {
                    let u = Vec2::new((a as f32 + 0.5) / 8.0, (b as f32 + 0.5) / 8.0);
                    sum += envmap.eval(grid.sample_in_cell(c, u)).1.as_dvec3();
                }
            }
            sum / 64.0
        })
        .collect()
}

/// The transport's normal equations kept per material ([`material_sums`]).
pub struct MaterialSums {
    pub grid: RingGrid,
    /// The material of each set.
    pub materials: Vec<usize>,
    /// Per set.
    pub sums: Vec<NormalEquations>,
}

/// One transport pass whose normal equations are kept per material, for the materials `wanted`
/// marks: `settings.rounds` parts (at least 2, for unbiased Grams) of the fit's samples per
/// part, their cells sampled by `envmap`, over [`material_grid`]. `progress` gets
/// [`transport::progress_units`] of the wanted materials' pixels and the parts.
#[allow(clippy::too_many_arguments)]
pub fn material_sums(
    renderer: &Renderer,
    views: &[&Camera],
    references: &[Image],
    masks: &[Vec<bool>],
    pixels: &MaterialPixels,
    wanted: &[bool],
    envmap: &Envmap,
    settings: &FitSettings,
    progress: &(dyn Fn(u64) + Sync),
) -> MaterialSums {
    let materials: Vec<usize> = (0..wanted.len()).filter(|&m| wanted[m]).collect();
    let mut set_of_material = vec![None; wanted.len()];
    for (s, &m) in materials.iter().enumerate() {
        set_of_material[m] = Some(s);
    }
    let grid = material_grid(envmap.grid.rings(), materials.len());
    if materials.is_empty() {
        return MaterialSums {
            grid,
            materials,
            sums: Vec::new(),
        };
    }
    let set_of = |p: (usize, u32)| pixels.of(p).and_then(|m| set_of_material[m]);
    let targets = Targets {
        grids: std::slice::from_ref(&grid),
        sets: materials.len(),
        set_of: &set_of,
        max_set_cells: usize::MAX,
    };
    let sampling = super::steering(envmap.grid.rings(), envmap.radiance());
    let parts: Vec<Part> = (0..settings.rounds.max(2))
        .map(|k| Part {
            sampling: sampling.clone(),
            settings: super::part_seed(settings, MATERIAL_PARTS + k),
        })
        .collect();
    let mut sums = transport::accumulate(
        renderer,
        views,
        masks,
        &targets,
        references,
        &parts,
        super::TRANSPORT_STREAMS,
        progress,
    );
    MaterialSums {
        grid,
        materials,
        sums: sums.swap_remove(0),
    }
}

/// The parts [`material_sums`] renders.
pub fn material_parts(settings: &FitSettings) -> usize {
    settings.rounds.max(2) as usize
}

impl MaterialSums {
    /// Each material's observability (the module doc) under `envmap`, per material of the
    /// scene (`None` for those not in a set, or unlit): the least of its channels'.
    pub fn observability(&self, envmap: &Envmap, materials: usize) -> Vec<Option<f64>> {
        let mut out = vec![None; materials];
        if self.sums.is_empty() {
            return out;
        }
        let lambda = resampled(envmap, &self.grid);
        let per_channel: Vec<Vec<Option<f64>>> = (0..3)
            .map(|ch| {
                let grams: Vec<Vec<f64>> = self.sums.iter().map(|s| s.gram(ch)).collect();
                let l: Vec<f64> = lambda.iter().map(|v| v[ch]).collect();
                observability_of(&grams, &l)
            })
            .collect();
        for (s, &m) in self.materials.iter().enumerate() {
            // A channel with no light says nothing.
            out[m] = per_channel
                .iter()
                .filter_map(|c| c[s])
                .fold(None, |a: Option<f64>, r| Some(a.map_or(r, |a| a.min(r))));
        }
        out
    }

    /// The joint fit ([`joint_channel`] per channel) over the sets of the `free` materials
    /// and the `held` ones (kept as they are: they fix the scale): per material of the scene,
    /// the multiplier of its albedo relative to the albedo the sums were rendered at (1 for
    /// materials not free), and the envmap fitted with them. `weights` (per material) fix the
    /// scale when none is held; `upper` bounds each material's multiplier.
    pub fn joint(
        &self,
        free: &[bool],
        held: &[bool],
        weights: &[f64],
        upper: &[DVec3],
        ridge: f64,
        time_limit: std::time::Duration,
    ) -> (Vec<DVec3>, Envmap) {
        // The sets the fit uses: the free materials' and the held ones'.
        let used: Vec<usize> = (0..self.materials.len())
            .filter(|&s| free[self.materials[s]] || held[self.materials[s]])
            .collect();
        let n_sets = used.len();
        let material = |s: usize| self.materials[used[s]];
        let set_free: Vec<bool> = (0..n_sets).map(|s| free[material(s)]).collect();
        let set_weights: Vec<f64> = (0..n_sets).map(|s| weights[material(s)]).collect();
        let mut k = vec![DVec3::ONE; free.len()];
        let mut radiance = vec![Vec3::ZERO; self.grid.cell_count()];
        for ch in 0..3 {
            let grams: Vec<Vec<f64>> = used.iter().map(|&s| self.sums[s].gram(ch)).collect();
            let tb: Vec<Vec<f64>> = used.iter().map(|&s| self.sums[s].tb(ch)).collect();
            let set_upper: Vec<f64> = (0..n_sets).map(|s| upper[material(s)][ch]).collect();
            let fit = joint_channel(
                &grams,
                &tb,
                &set_free,
                &set_weights,
                &set_upper,
                ridge,
                time_limit,
            );
            for s in 0..n_sets {
                k[material(s)][ch] = fit.k[s];
            }
            for (r, l) in radiance.iter_mut().zip(&fit.lambda) {
                r[ch] = (*l as f32).clamp(0.0, crate::imageio::MAX_RADIANCE);
            }
        }
        let envmap = Envmap::new(self.grid.rings(), radiance).expect("finite and non-negative");
        (k, envmap)
    }
}

/// One channel's joint fit of the albedo multipliers and the lighting.
#[derive(Debug, Clone)]
pub struct JointChannel {
    /// Per set.
    pub k: Vec<f64>,
    /// Per cell, ≥ 0.
    pub lambda: Vec<f64>,
    /// Gauss–Newton steps taken.
    pub iterations: usize,
}

/// Most Gauss–Newton steps of [`joint_channel`].
const MAX_JOINT_STEPS: usize = 40;

/// One channel of the joint fit, from the transport of each set of pixels rendered at the
/// current albedo (its Gram `grams[s]`, cells × cells, and `tb[s]`): multipliers `k` (1 for
/// sets not `free`) and radiance `λ ≥ 0` minimising `Σ_s ‖k_s T_s λ − y_s‖² + r‖λ‖²` (r
/// `ridge` times the mean diagonal of Σ G_s), by Gauss–Newton on k over the profile λ(k)
/// (variable projection: each k's λ is the exact NNLS, so the steps follow the valley the
/// alternation of [`super::job::run`] crawls along). With no set held, the pixel-weighted
/// geometric mean of the free sets' k is kept at 1. Each k_s stays within
/// `[0.01, upper_s]`.
pub fn joint_channel(
    grams: &[Vec<f64>],
    tb: &[Vec<f64>],
    free: &[bool],
    weights: &[f64],
    upper: &[f64],
    ridge: f64,
    time_limit: std::time::Duration,
) -> JointChannel {
    let sets = grams.len();
    let n = tb.first().map_or(0, Vec::len);
    let mut k = vec![1.0f64; sets];
    let held = free.iter().any(|f| !f);
    let mean_diag = (0..n)
        .map(|i| grams.iter().map(|g| g[i * n + i]).sum::<f64>())
        .sum::<f64>()
        / n.max(1) as f64;
    let r = ridge * mean_diag;
    if n == 0 || mean_diag.is_nan() || mean_diag <= 0.0 {
        return JointChannel {
            k,
            lambda: vec![0.0; n],
            iterations: 0,
        };
    }
    // λ(k) by NNLS and the objective ½λᵀAλ − cᵀλ there.
    let profile = |k: &[f64]| -> (Vec<f64>, f64) {
        let mut a = vec![0.0; n * n];
        let mut c = vec![0.0; n];
        for s in 0..sets {
            let k2 = k[s] * k[s];
            a.iter_mut().zip(&grams[s]).for_each(|(a, g)| *a += k2 * g);
            c.iter_mut().zip(&tb[s]).for_each(|(c, b)| *c += k[s] * b);
        }
        for i in 0..n {
            a[i * n + i] += r;
        }
        let sol = super::nnls::nnls(&a, &c, 1e-9, 20 * n + 100, time_limit);
        let f = super::nnls::objective(&a, &c, &sol.x);
        (sol.x, f)
    };
    let gauge = |k: &mut [f64]| {
        if held {
            return;
        }
        let (mut sum, mut w) = (0.0, 0.0);
        for s in 0..sets {
            if free[s] {
                sum += weights[s] * k[s].ln();
                w += weights[s];
            }
        }
        if w > 0.0 {
            let c = (-sum / w).exp();
            k.iter_mut()
                .zip(free)
                .filter(|(_, f)| **f)
                .for_each(|(k, _)| *k *= c);
        }
    };
    let (mut lambda, mut f) = profile(&k);
    let mut iterations = 0;
    let idx: Vec<usize> = (0..sets).filter(|&s| free[s]).collect();
    let m = idx.len();
    while iterations < MAX_JOINT_STEPS && m > 0 {
        iterations += 1;
        // Per set: G_s λ, its energy λᵀG_sλ and λᵀb_s.
        let gl: Vec<Vec<f64>> = grams
            .iter()
            .map(|g| g.chunks_exact(n).map(|row| dot(row, &lambda)).collect())
            .collect();
        let energy: Vec<f64> = gl.iter().map(|v| dot(v, &lambda)).collect();
        let beta: Vec<f64> = tb.iter().map(|b| dot(b, &lambda)).collect();
        // Gauss–Newton on (k, λ_active), λ eliminated: H = D − Cᵀ A⁻¹ C, D = diag(energy),
        // C_s = k_s G_s λ on the lit cells, A = Σ k² G + r I there.
        let active: Vec<usize> = (0..n).filter(|&i| lambda[i] > 0.0).collect();
        let na = active.len();
        let a = faer::Mat::<f64>::from_fn(na, na, |i, j| {
            let (p, q) = (active[i], active[j]);
            let v: f64 = (0..sets).map(|s| k[s] * k[s] * grams[s][p * n + q]).sum();
            v + if i == j { r } else { 0.0 }
        });
        let cmat = faer::Mat::<f64>::from_fn(na, m, |i, j| k[idx[j]] * gl[idx[j]][active[i]]);
        let Ok(llt) = a.llt(faer::Side::Lower) else {
            break;
        };
        let ainv_c = llt.solve(&cmat);
        let mut h = faer::Mat::<f64>::from_fn(m, m, |p, q| {
            let d = if p == q { energy[idx[p]] } else { 0.0 };
            d - (0..na).map(|i| cmat[(i, p)] * ainv_c[(i, q)]).sum::<f64>()
        });
        let scale = (0..m).map(|p| h[(p, p)].abs()).fold(0.0, f64::max);
        if scale.is_nan() || scale <= 0.0 {
            break;
        }
        // No set held: the common scale of k is the lighting's; pin it (in log k).
        if !held {
            let v: Vec<f64> = idx.iter().map(|&s| weights[s] / k[s]).collect();
            let vv: f64 = v.iter().map(|x| x * x).sum();
            for p in 0..m {
                for q in 0..m {
                    h[(p, q)] += scale * v[p] * v[q] / vv;
                }
            }
        }
        for p in 0..m {
            h[(p, p)] += 1e-12 * scale;
        }
        let grad = faer::Mat::<f64>::from_fn(m, 1, |p, _| {
            let s = idx[p];
            beta[s] - k[s] * energy[s]
        });
        let Ok(hl) = h.llt(faer::Side::Lower) else {
            break;
        };
        let dk = hl.solve(&grad);
        let mut alpha = 1.0;
        let mut accepted = false;
        let mut largest = 0.0f64;
        for _ in 0..10 {
            let mut next = k.clone();
            for p in 0..m {
                let s = idx[p];
                next[s] = (k[s] + alpha * dk[(p, 0)]).clamp(0.01, upper[s].max(0.01));
            }
            gauge(&mut next);
            let (l2, f2) = profile(&next);
            if f2 <= f {
                largest = (0..sets).fold(0.0f64, |a, s| a.max((next[s] / k[s]).ln().abs()));
                k = next;
                lambda = l2;
                f = f2;
                accepted = true;
                break;
            }
            alpha *= 0.5;
        }
        if !accepted || largest < 1e-6 {
            break;
        }
    }
    JointChannel {
        k,
        lambda,
        iterations,
    }
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// The observability (the module doc) of each set of pixels from one channel's Gram matrices
/// `grams` (dense, cells × cells, one per set) and radiance `lambda`: `F / S`, F the Schur
/// complement of the set's multiplier against the lighting fitted over every set, and
/// `S = E(Ê − E)/Ê` the value F takes when the other sets are lit exactly as this one (the
/// harmonic combination of its energy E and theirs, Ê all sets'): a set that dominates the
/// pixels is not unconstrained for it. `None` where the set has no energy in this channel.
pub fn observability_of(grams: &[Vec<f64>], lambda: &[f64]) -> Vec<Option<f64>> {
    let n = lambda.len();
    let mut all = vec![0.0; n * n];
    for g in grams {
        all.iter_mut().zip(g).for_each(|(a, b)| *a += b);
    }
    let gl: Vec<Vec<f64>> = grams
        .iter()
        .map(|gm| {
            (0..n)
                .map(|i| (0..n).map(|j| gm[i * n + j] * lambda[j]).sum())
                .collect()
        })
        .collect();
    let energy: Vec<f64> = gl
        .iter()
        .map(|sm| sm.iter().zip(lambda).map(|(a, b)| a * b).sum())
        .collect();
    let total: f64 = energy.iter().sum();
    let trace: f64 = (0..n).map(|i| all[i * n + i]).sum();
    if total.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) || trace <= 0.0 {
        return vec![None; grams.len()];
    }
    // A ridge far below the data's scale: cells no pixel sees leave G singular.
    let ridge = 1e-9 * trace / n as f64;
    let g = faer::Mat::<f64>::from_fn(n, n, |i, j| {
        all[i * n + j] + if i == j { ridge } else { 0.0 }
    });
    let Ok(llt) = g.llt(faer::Side::Lower) else {
        return vec![None; grams.len()];
    };
    gl.iter()
        .zip(&energy)
        .map(|(sm, &e)| {
            if e.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
                return None;
            }
            let shared = e * (total - e) / total;
            if shared <= 0.0 {
                // The only lit set: nothing to compare its albedo with.
                return Some(0.0);
            }
            let x = llt.solve(faer::Mat::<f64>::from_fn(n, 1, |i, _| sm[i]));
            let explained: f64 = (0..n).map(|i| sm[i] * x[(i, 0)]).sum();
            Some(((e - explained) / shared).clamp(0.0, 1.0))
        })
        .collect()
}

/// Part seeds of [`material_sums`]'s pass, apart from the fit's.
const MATERIAL_PARTS: u32 = 7_919;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_gauged_step_keeps_the_anchors_fixed() {
        // Two materials: the trusted one's ratio is the light's error alone; the other's is
        // its own error times the light's. The step removes the light's share.
        let light = DVec3::new(0.1, -0.2, 0.05);
        let own = DVec3::new(0.3, 0.0, -0.1);
        let ratios = [Some(light), Some(light + own), None];
        let step = gauged_step(
            &ratios,
            &[false, true, true],
            &[true, false, false],
            &[10, 5, 3],
        );
        assert!((step[0]).length() == 0.0);
        assert!((step[1] - own).length() < 1e-12);
        assert_eq!(step[2], DVec3::ZERO);
        // Without trusted materials, the free ones' weighted mean step is 0.
        let step = gauged_step(
            &ratios,
            &[true, true, false],
            &[true, true, false],
            &[10, 5, 3],
        );
        let mean = (step[0] * 10.0 + step[1] * 5.0) / 15.0;
        assert!(mean.length() < 1e-12);
        assert!((step[1] - step[0] - own).length() < 1e-12);
    }

    #[test]
    fn the_bound_keeps_the_albedo_at_most_one() {
        let b = upper_bound(Vec3::new(0.5, 1.0, 0.0));
        assert!((b.x - 2f64.ln()).abs() < 1e-12);
        assert_eq!(b.y, 0.0);
        assert_eq!(b.z, f64::INFINITY);
    }

    /// A set's Gram from its pixels' transport rows (cells × cells).
    fn gram(rows: &[Vec<f64>]) -> Vec<f64> {
        let n = rows[0].len();
        let mut g = vec![0.0; n * n];
        for r in rows {
            for i in 0..n {
                for j in 0..n {
                    g[i * n + j] += r[i] * r[j];
                }
            }
        }
        g
    }

    #[test]
    fn a_material_lit_by_light_no_other_sees_is_unobservable() {
        // Four cells. A sees cells 0 and 1, B cells 1 and 2, C only cell 3.
        let a = gram(&[vec![1.0, 0.5, 0.0, 0.0], vec![0.8, 0.9, 0.0, 0.0]]);
        let b = gram(&[vec![0.0, 0.7, 0.4, 0.0], vec![0.0, 0.2, 1.0, 0.0]]);
        let c = gram(&[vec![0.0, 0.0, 0.0, 1.0], vec![0.0, 0.0, 0.0, 0.6]]);
        let lambda = [1.0, 2.0, 0.5, 3.0];
        let o = observability_of(&[a.clone(), b.clone(), c], &lambda);
        assert!(o[2].unwrap() < 1e-6, "{o:?}");
        // A and B share cell 1: a change of A's albedo cannot all go into its own cell 0
        // (its two pixels mix cells 0 and 1 differently) without changing B.
        assert!(o[0].unwrap() > 0.05 && o[1].unwrap() > 0.05, "{o:?}");
        // Lit exactly alike (the same rows), two materials are fully observable: 1.
        let same = observability_of(&[a.clone(), a.clone()], &lambda);
        assert!(
            same.iter().all(|v| (v.unwrap() - 1.0).abs() < 1e-6),
            "{same:?}"
        );
        // One lit set alone has nothing to compare with; an unlit one says nothing.
        let dark = observability_of(&[a, vec![0.0; 16]], &lambda);
        assert_eq!(dark, vec![Some(0.0), None]);
    }

    #[test]
    fn the_material_grid_bounds_the_sums() {
        assert_eq!(material_grid(9, 8).rings(), 9);
        let g = material_grid(27, 8);
        assert!(g.cell_count() <= super::super::MAX_JACKKNIFE_CELLS);
        let many = material_grid(17, 2000);
        assert!(2000 * NormalEquations::memory_needed(many.cell_count()) <= MATERIAL_SUMS_BYTES);
    }
}
