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
//! **Observability** ([`MaterialSums::observability`]). A material is constrained only if
//! light that lights it also lights other materials: a material (or a group of materials) lit
//! by cells no other material sees trades its albedo for those cells' radiance freely. From
//! the transport's TᵀT kept per material (G_m) and the fitted radiance λ, per channel: the
//! information on a material's multiplier once the lighting and the other free multipliers
//! are refitted, `1/(H⁻¹)_mm` with H the profile's Gauss–Newton matrix ([`observability_of`]),
//! relative to its value were the other materials lit exactly as this one. 0: unconstrained;
//! 1: the lighting cannot mimic any of it.
//!
//! **The envmap: a joint fit** ([`joint_channel`]); sphere models and per-view exposures
//! alternate ([`super::job::run`]).

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
    /// The materials' multipliers, then each fitted texture's texels corrected by a coarse
    /// grid of multipliers with a smoothness prior ([`super::texels`]): shading baked into a
    /// photographed texture taken out.
    Texels,
}

/// Fewest pixels that see a material alone for its albedo to be fitted: fewer are reported
/// [`MaterialStatus::Unseen`] and kept as given.
pub const MIN_MATERIAL_PIXELS: usize = 64;

/// Least observability of a fitted material ([`observability_of`]): below it, it is reported
/// [`MaterialStatus::Unconstrained`] and kept as given.
pub const MIN_OBSERVABILITY: f64 = 0.01;

/// Relative change of every multiplier below which the alternation stops: the lighting fit's
/// own noise moves a material's ratio by about 1.5% between fits (bundled scene).
pub const ALBEDO_TOLERANCE: f64 = 0.02;

/// Relative change of every multiplier below which the joint passes stop: what a pass at the
/// albedo found changes is the light between surfaces, which the one-bounce joint fit leaves
/// out, and the pass's own noise, which moved materials of 84–262 pixels by up to 1.8%
/// between passes of a quarter of 128 samples.
pub const JOINT_TOLERANCE: f64 = 0.02;

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
    /// How well the images pin its albedo, 0 (not at all: lit only by light no other material
    /// sees) to 1 (as well as beside a material lit exactly alike), the least over its lit
    /// channels ([`observability_of`]); null where not measured (unseen, or trusted).
    pub observability: Option<f64>,
    /// Mean albedo as given, linear RGB: over the pixels that see it alone as rendered there
    /// (texture, factor and vertex colours together); where none does, the material's own
    /// (a texture's mean texel × its factor).
    pub given: [f32; 3],
    /// Mean albedo fitted, linear RGB, over the same pixels as `given`: `given × multiplier`,
    /// and with `--fit-albedo texels` the corrected texture's too.
    pub fitted: [f32; 3],
    /// What multiplies the constant albedo or the texture's factor, per channel.
    pub multiplier: [f32; 3],
    /// A channel reached a bound: the mean albedo 1 (`given × multiplier` ≤ 1), or 1/100 of
    /// the given.
    pub at_bound: bool,
}

/// `report.json`'s `albedo`: the albedo fitted beside the lighting.
#[derive(Debug, Clone, Serialize, JsonSchema)]
pub struct AlbedoReport {
    pub fit: FitAlbedo,
    pub method: AlbedoMethod,
    /// Joint: rings of the envmap the albedo was fitted under (the fit's, or coarser where
    /// the per-material sums would pass their memory bound, [`material_grid`]).
    pub rings: Option<u32>,
    /// Joint: a fit's steps stopped on a singular system; the albedo is where they were, and
    /// not converged.
    pub stalled: bool,
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
    /// `--fit-albedo texels`: rounds made (a correction of every fitted texture, then a fit of
    /// the lighting at it); 0 otherwise.
    pub texel_rounds: usize,
    /// `--fit-albedo texels`: each corrected texture's correction.
    pub texels: Vec<super::texels::TexelFit>,
    /// `--fit-albedo texels`: the textures left as given, and why.
    pub texel_notes: Vec<String>,
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
    /// Per material, its mean albedo over those pixels at their centres, as rendered (texture,
    /// factor and vertex colours together); zero where no pixel sees it alone.
    pub seen_albedo: Vec<DVec3>,
    /// Per view, per pixel, the glTF texture coordinates at its centre (NaN where it sees
    /// no geometry): where a texel fit ([`super::texels`]) puts the pixel.
    pub uv: Vec<Vec<Vec2>>,
}

impl MaterialPixels {
    /// The material maps of `views` in `renderer`'s scene, inside `masks`.
    pub fn new(renderer: &Renderer, views: &[&Camera], masks: &[Vec<bool>]) -> Self {
        let n = renderer.scene.materials.len();
        let (mut counts, mut seen_in) = (vec![0usize; n], vec![0usize; n]);
        let mut albedo = vec![DVec3::ZERO; n];
        let mut uv = Vec::with_capacity(views.len());
        let ids: Vec<Vec<u32>> = views
            .iter()
            .zip(masks)
            .map(|(cam, mask)| {
                let mut ids = renderer.material_ids(cam);
                let aovs = renderer.aovs(cam);
                let mut here = vec![false; n];
                for ((id, &m), a) in ids.iter_mut().zip(mask).zip(&aovs.albedo.rgb) {
                    if !m || *id as usize >= n {
                        *id = NO_MATERIAL;
                    } else {
                        counts[*id as usize] += 1;
                        albedo[*id as usize] += a.as_dvec3();
                        here[*id as usize] = true;
                    }
                }
                for (s, h) in seen_in.iter_mut().zip(here) {
                    *s += h as usize;
                }
                uv.push(aovs.uv);
                ids
            })
            .collect();
        let seen_albedo = albedo
            .iter()
            .zip(&counts)
            .map(|(a, &c)| *a / c.max(1) as f64)
            .collect();
        MaterialPixels {
            ids,
            counts,
            views: seen_in,
            seen_albedo,
            uv,
        }
    }

    /// Per material, its pixel count as a weight (of the gauge's mean).
    pub fn weights(&self) -> Vec<f64> {
        self.counts.iter().map(|&c| c as f64).collect()
    }

    /// The material pixel `i` of view `v` sees alone.
    pub fn of(&self, (v, i): (usize, u32)) -> Option<usize> {
        let id = self.ids[v][i as usize];
        (id != NO_MATERIAL).then_some(id as usize)
    }
}

/// Per material, `ln(Σ reference / Σ render)` per channel over the pixels that see it alone;
/// NaN in a channel whose sums are not both positive (nothing to scale there).
pub fn log_ratios(pixels: &MaterialPixels, references: &[Image], renders: &[Image]) -> Vec<DVec3> {
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
    let ln = |y: f64, x: f64| {
        if y > 0.0 && x > 0.0 {
            (y / x).ln()
        } else {
            f64::NAN
        }
    };
    y.iter()
        .zip(&x)
        .map(|(y, x)| DVec3::new(ln(y.x, x.x), ln(y.y, x.y), ln(y.z, x.z)))
        .collect()
}

/// The anchors' pixel-weighted mean log ratio per channel: the trusted materials lit in that
/// channel; without any, the free ones; 0 where none is lit. What every free material's step
/// is taken relative to ([`gauged_step`]).
pub fn anchor_mean(ratios: &[DVec3], free: &[bool], trusted: &[bool], counts: &[usize]) -> DVec3 {
    let mut mean = DVec3::ZERO;
    for c in 0..3 {
        let weighted = |anchor: &dyn Fn(usize) -> bool| {
            let (mut sum, mut weight) = (0.0, 0.0);
            for m in 0..ratios.len() {
                let r = ratios[m][c];
                if anchor(m) && r.is_finite() {
                    sum += r * counts[m] as f64;
                    weight += counts[m] as f64;
                }
            }
            (weight > 0.0).then(|| sum / weight)
        };
        mean[c] = weighted(&|m| trusted[m])
            .or_else(|| weighted(&|m| free[m]))
            .unwrap_or(0.0);
    }
    mean
}

/// The step of every material's log-multiplier: per channel, a free material's log ratio less
/// the anchors' mean ([`anchor_mean`]), zero for the others and where its ratio is NaN.
pub fn gauged_step(
    ratios: &[DVec3],
    free: &[bool],
    trusted: &[bool],
    counts: &[usize],
) -> Vec<DVec3> {
    let mean = anchor_mean(ratios, free, trusted, counts);
    ratios
        .iter()
        .zip(free)
        .map(|(r, &f)| {
            let d = *r - mean;
            let keep = |v: f64| if f && v.is_finite() { v } else { 0.0 };
            DVec3::new(keep(d.x), keep(d.y), keep(d.z))
        })
        .collect()
}

/// The named materials, comma-separated (glTF's unnamed default left out): for messages that
/// name one the scene lacks.
pub fn material_names(materials: &[Material]) -> String {
    let names: Vec<&str> = materials
        .iter()
        .map(|m| m.name.as_str())
        .filter(|n| !n.is_empty())
        .collect();
    names.join(", ")
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

/// Bytes of per-material sums above which [`material_sums`] takes a coarser grid than the
/// fit's.
pub const MATERIAL_SUMS_BYTES: usize = 256 << 20;

/// The grid of [`material_sums`] for a fit of `rings` rings and `sets` materials: the fit's,
/// or the finest coarser one whose per-material sums fit in [`MATERIAL_SUMS_BYTES`] (the
/// albedo is then fitted under a coarser envmap than the final fit's, and takes up its
/// coarser error; `albedo.rings` in the report).
pub fn material_grid(rings: u32, sets: usize) -> RingGrid {
    (1..=rings)
        .rev()
        .map(RingGrid::new)
        .find(|g| {
            sets.max(1) * NormalEquations::memory_needed(g.cell_count()) <= MATERIAL_SUMS_BYTES
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
    /// scene: `None` for those not `free` or not in a set, or unlit; else the least of its
    /// lit channels'. The sets of materials not free hold the scale; without any, `weights`
    /// (per material) pin it.
    pub fn observability(
        &self,
        envmap: &Envmap,
        free: &[bool],
        weights: &[f64],
    ) -> Vec<Option<f64>> {
        let mut out = vec![None; free.len()];
        if self.sums.is_empty() {
            return out;
        }
        let lambda = resampled(envmap, &self.grid);
        let set_free: Vec<bool> = self.materials.iter().map(|&m| free[m]).collect();
        let set_weights: Vec<f64> = self.materials.iter().map(|&m| weights[m]).collect();
        let per_channel: Vec<Vec<Option<f64>>> = (0..3)
            .map(|ch| {
                let grams: Vec<Vec<f64>> = self.sums.iter().map(|s| s.gram(ch)).collect();
                let l: Vec<f64> = lambda.iter().map(|v| v[ch]).collect();
                observability_of(&grams, &l, &set_free, &set_weights)
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
    /// materials not free), the envmap fitted with them, and whether a channel's steps
    /// stalled. `weights` (per material) fix the scale when none is held; `bounds` (per
    /// material, lower and upper) bound each material's multiplier.
    pub fn joint(
        &self,
        (free, held): (&[bool], &[bool]),
        weights: &[f64],
        bounds: &[(DVec3, DVec3)],
        ridge: f64,
        time_limit: std::time::Duration,
    ) -> (Vec<DVec3>, Envmap, bool) {
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
        let mut stalled = false;
        for ch in 0..3 {
            let grams: Vec<Vec<f64>> = used.iter().map(|&s| self.sums[s].gram(ch)).collect();
            let tb: Vec<Vec<f64>> = used.iter().map(|&s| self.sums[s].tb(ch)).collect();
            let lower: Vec<f64> = (0..n_sets).map(|s| bounds[material(s)].0[ch]).collect();
            let upper: Vec<f64> = (0..n_sets).map(|s| bounds[material(s)].1[ch]).collect();
            let fit = joint_channel(
                &grams,
                &tb,
                &set_free,
                &set_weights,
                (&lower, &upper),
                ridge,
                time_limit,
            );
            stalled |= fit.stalled;
            for s in 0..n_sets {
                k[material(s)][ch] = fit.k[s];
            }
            for (r, l) in radiance.iter_mut().zip(&fit.lambda) {
                r[ch] = (*l as f32).clamp(0.0, crate::imageio::MAX_RADIANCE);
            }
        }
        let envmap = Envmap::new(self.grid.rings(), radiance).expect("finite and non-negative");
        (k, envmap, stalled)
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
    /// The steps stopped on a singular system before converging: `k` is where they were.
    pub stalled: bool,
}

/// Most Gauss–Newton steps of [`joint_channel`].
const MAX_JOINT_STEPS: usize = 40;

/// Per set: `G_s λ` and its energy `λᵀG_sλ`.
fn lit(grams: &[Vec<f64>], lambda: &[f64]) -> (Vec<Vec<f64>>, Vec<f64>) {
    let n = lambda.len();
    let gl: Vec<Vec<f64>> = grams
        .iter()
        .map(|g| g.chunks_exact(n).map(|row| dot(row, lambda)).collect())
        .collect();
    let energy = gl.iter().map(|v| dot(v, lambda)).collect();
    (gl, energy)
}

/// The Gauss–Newton matrix of the profile over the multipliers of the sets `free`, the
/// radiance of `cells` eliminated: `H = diag(E) − Cᵀ A⁻¹ C`, with `C_s = k_s G_s λ` and
/// `A = Σ_s k_s² G_s + r I` over those cells (every set's). With `pin` (per set weights) the
/// common scale of the free multipliers (in log k) is pinned: no set is held to fix it.
#[allow(clippy::too_many_arguments)]
fn profile_matrix(
    grams: &[Vec<f64>],
    gl: &[Vec<f64>],
    energy: &[f64],
    k: &[f64],
    cells: &[usize],
    r: f64,
    free: &[usize],
    pin: Option<&[f64]>,
) -> Option<faer::Mat<f64>> {
    let n = gl.first().map_or(0, Vec::len);
    let (na, m) = (cells.len(), free.len());
    let a = faer::Mat::<f64>::from_fn(na, na, |i, j| {
        let (p, q) = (cells[i], cells[j]);
        let v: f64 = (0..grams.len())
            .map(|s| k[s] * k[s] * grams[s][p * n + q])
            .sum();
        v + if i == j { r } else { 0.0 }
    });
    let c = faer::Mat::<f64>::from_fn(na, m, |i, j| k[free[j]] * gl[free[j]][cells[i]]);
    let llt = a.llt(faer::Side::Lower).ok()?;
    let ainv_c = llt.solve(&c);
    let mut h = faer::Mat::<f64>::from_fn(m, m, |p, q| {
        let d = if p == q { energy[free[p]] } else { 0.0 };
        d - (0..na).map(|i| c[(i, p)] * ainv_c[(i, q)]).sum::<f64>()
    });
    let scale = (0..m).map(|p| h[(p, p)].abs()).fold(0.0, f64::max);
    if scale.is_nan() || scale <= 0.0 {
        return None;
    }
    if let Some(w) = pin {
        let v: Vec<f64> = free.iter().map(|&s| w[s] / k[s]).collect();
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
    Some(h)
}

/// One channel of the joint fit, from the transport of each set of pixels rendered at the
/// current albedo (its Gram `grams[s]`, cells × cells, and `tb[s]`): multipliers `k` (1 for
/// sets not `free`) and radiance `λ ≥ 0` minimising `Σ_s ‖k_s T_s λ − y_s‖² + r‖λ‖²` (r
/// `ridge` times the mean diagonal of Σ G_s), by Gauss–Newton on k over the profile λ(k)
/// (variable projection: each k's λ is the exact NNLS, so the steps follow the valley an
/// alternation crawls along), with a backtracking line search. The scale is held by the sets
/// not free that this channel lights; with none, the pixel-weighted (`weights`) geometric
/// mean of the free sets' k is kept at 1. Each k_s stays within `[lower_s, upper_s]`.
#[allow(clippy::too_many_arguments)]
pub fn joint_channel(
    grams: &[Vec<f64>],
    tb: &[Vec<f64>],
    free: &[bool],
    weights: &[f64],
    (lower, upper): (&[f64], &[f64]),
    ridge: f64,
    time_limit: std::time::Duration,
) -> JointChannel {
    let sets = grams.len();
    let n = tb.first().map_or(0, Vec::len);
    let mut k = vec![1.0f64; sets];
    let mean_diag = (0..n)
        .map(|i| grams.iter().map(|g| g[i * n + i]).sum::<f64>())
        .sum::<f64>()
        / n.max(1) as f64;
    let r = ridge * mean_diag;
    let idx: Vec<usize> = (0..sets).filter(|&s| free[s]).collect();
    if n == 0 || mean_diag.is_nan() || mean_diag <= 0.0 || idx.is_empty() {
        return JointChannel {
            k,
            lambda: vec![0.0; n],
            iterations: 0,
            stalled: false,
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
    let (mut lambda, mut f) = profile(&k);
    // Held: a set not free that this channel lights (a trusted red material holds nothing
    // in green).
    let held = {
        let (_, energy) = lit(grams, &lambda);
        (0..sets).any(|s| !free[s] && energy[s] > 0.0)
    };
    let bounded = |k: &mut [f64]| {
        for &s in &idx {
            k[s] = k[s].clamp(lower[s], upper[s].max(lower[s]));
        }
    };
    let gauge = |k: &mut [f64]| {
        if held {
            return;
        }
        let (mut sum, mut w) = (0.0, 0.0);
        for &s in &idx {
            sum += weights[s] * k[s].ln();
            w += weights[s];
        }
        if w > 0.0 {
            let c = (-sum / w).exp();
            idx.iter().for_each(|&s| k[s] *= c);
        }
    };
    let (mut iterations, mut stalled) = (0, false);
    while iterations < MAX_JOINT_STEPS {
        iterations += 1;
        let (gl, energy) = lit(grams, &lambda);
        let beta: Vec<f64> = tb.iter().map(|b| dot(b, &lambda)).collect();
        let active: Vec<usize> = (0..n).filter(|&i| lambda[i] > 0.0).collect();
        let pin = (!held).then_some(weights);
        let Some(h) = profile_matrix(grams, &gl, &energy, &k, &active, r, &idx, pin) else {
            stalled = true;
            break;
        };
        let grad = faer::Mat::<f64>::from_fn(idx.len(), 1, |p, _| {
            let s = idx[p];
            beta[s] - k[s] * energy[s]
        });
        let Ok(hl) = h.llt(faer::Side::Lower) else {
            stalled = true;
            break;
        };
        let dk = hl.solve(&grad);
        let mut alpha = 1.0;
        let mut moved = None;
        for _ in 0..10 {
            let mut next = k.clone();
            for (p, &s) in idx.iter().enumerate() {
                next[s] = k[s] + alpha * dk[(p, 0)];
            }
            // Bounds, the gauge, and the bounds again (the gauge may push one past).
            bounded(&mut next);
            gauge(&mut next);
            bounded(&mut next);
            let (l2, f2) = profile(&next);
            if f2 <= f {
                let largest = (0..sets).fold(0.0f64, |a, s| a.max((next[s] / k[s]).ln().abs()));
                (k, lambda, f) = (next, l2, f2);
                moved = Some(largest);
                break;
            }
            alpha *= 0.5;
        }
        // No step lowers the objective: at its minimum (up to the line search's reach).
        if moved.is_none_or(|m| m < 1e-6) {
            break;
        }
    }
    JointChannel {
        k,
        lambda,
        iterations,
        stalled,
    }
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// The observability (the module doc) of each set of pixels from one channel's Gram matrices
/// `grams` (dense, cells × cells, one per set) and radiance `lambda`: per free set,
/// `1 / (S · (H⁻¹)_ss)`, H the profile's Gauss–Newton matrix over every free set's multiplier
/// with the radiance of every cell free ([`profile_matrix`]; the lighting and the other free
/// materials refitted: a group of materials lit only by light no held one sees is
/// unobservable together), and `S = E(Ê − E)/Ê` what `1/(H⁻¹)_ss` is for one free set beside
/// others lit exactly as it is (the harmonic combination of its energy E and theirs, Ê all
/// sets'): a set that dominates the pixels is not unconstrained for it. Without a lit set
/// held, the free sets' pixel-weighted (`weights`) mean is pinned, and a lone free set is 0.
/// `None` for sets not free or not lit in this channel.
pub fn observability_of(
    grams: &[Vec<f64>],
    lambda: &[f64],
    free: &[bool],
    weights: &[f64],
) -> Vec<Option<f64>> {
    let sets = grams.len();
    let n = lambda.len();
    let mut out = vec![None; sets];
    let (gl, energy) = lit(grams, lambda);
    let total: f64 = energy.iter().sum();
    let trace: f64 = (0..n)
        .map(|i| grams.iter().map(|g| g[i * n + i]).sum::<f64>())
        .sum();
    if total.is_nan() || total <= 0.0 || trace.is_nan() || trace <= 0.0 {
        return out;
    }
    let idx: Vec<usize> = (0..sets).filter(|&s| free[s] && energy[s] > 0.0).collect();
    let held = (0..sets).any(|s| !free[s] && energy[s] > 0.0);
    if idx.is_empty() {
        return out;
    }
    if !held && idx.len() == 1 {
        // Alone, it is the scale itself: nothing to compare its albedo with.
        out[idx[0]] = Some(0.0);
        return out;
    }
    let cells: Vec<usize> = (0..n).collect();
    // A ridge far below the data's scale: cells no pixel sees leave A singular.
    let r = 1e-9 * trace / n as f64;
    let k = vec![1.0; sets];
    let pin = (!held).then_some(weights);
    let inverse_diagonal =
        profile_matrix(grams, &gl, &energy, &k, &cells, r, &idx, pin).and_then(|h| {
            let m = idx.len();
            let llt = h.llt(faer::Side::Lower).ok()?;
            let inv = llt.solve(faer::Mat::<f64>::identity(m, m));
            Some((0..m).map(|p| inv[(p, p)]).collect::<Vec<f64>>())
        });
    let Some(var) = inverse_diagonal else {
        return out;
    };
    for (p, &s) in idx.iter().enumerate() {
        let e = energy[s];
        let shared = e * (total - e) / total;
        out[s] = Some(if shared > 0.0 && var[p] > 0.0 {
            (1.0 / (shared * var[p])).clamp(0.0, 1.0)
        } else {
            0.0
        });
    }
    out
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
        let nan = DVec3::splat(f64::NAN);
        let ratios = [light, light + own, nan];
        let trusted = [true, false, false];
        let step = gauged_step(&ratios, &[false, true, true], &trusted, &[10, 5, 3]);
        assert!((step[0]).length() == 0.0);
        assert!((step[1] - own).length() < 1e-12);
        assert_eq!(step[2], DVec3::ZERO);
        // Without trusted materials, the free ones' weighted mean step is 0.
        let step = gauged_step(&ratios, &[true, true, false], &[false; 3], &[10, 5, 3]);
        let mean = (step[0] * 10.0 + step[1] * 5.0) / 15.0;
        assert!(mean.length() < 1e-12);
        assert!((step[1] - step[0] - own).length() < 1e-12);
        // A trusted pure red material holds red only: green and blue fall back to the free
        // materials' mean.
        let red = DVec3::new(light.x, f64::NAN, f64::NAN);
        let ratios = [red, light + own, light];
        let step = gauged_step(&ratios, &[false, true, true], &trusted, &[10, 5, 5]);
        assert!((step[1].x - own.x).abs() < 1e-12);
        assert!((step[1].y + step[2].y).abs() < 1e-12 && (step[1].z + step[2].z).abs() < 1e-12);
        assert!(step.iter().all(|v| v.is_finite()));
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
        // Four cells; A is held (trusted). A sees cells 0 and 1, B cells 1 and 2, C only 3.
        let a = gram(&[vec![1.0, 0.5, 0.0, 0.0], vec![0.8, 0.9, 0.0, 0.0]]);
        let b = gram(&[vec![0.0, 0.7, 0.4, 0.0], vec![0.0, 0.2, 1.0, 0.0]]);
        let c = gram(&[vec![0.0, 0.0, 0.0, 1.0], vec![0.0, 0.0, 0.0, 0.6]]);
        let lambda = [1.0, 2.0, 0.5, 3.0];
        let w = [1.0; 3];
        let free = [false, true, true];
        let o = observability_of(&[a.clone(), b.clone(), c.clone()], &lambda, &free, &w);
        assert_eq!(o[0], None);
        assert!(o[2].unwrap() < 1e-6, "{o:?}");
        // B shares cell 1 with A: a change of B's albedo cannot all go into its own cell 2
        // (its two pixels mix cells 1 and 2 differently) without changing A.
        assert!(o[1].unwrap() > 0.05, "{o:?}");
        // A group: B and C lit only by cells 2 and 3, which A does not see. Each alone is
        // pinned by the other, but together they trade with those cells: both unobservable.
        let b2 = gram(&[vec![0.0, 0.0, 0.7, 0.4], vec![0.0, 0.0, 0.2, 1.0]]);
        let c2 = gram(&[vec![0.0, 0.0, 1.0, 0.1], vec![0.0, 0.0, 0.3, 0.6]]);
        let group = observability_of(&[a.clone(), b2, c2], &lambda, &free, &w);
        assert!(
            group[1].unwrap() < 1e-6 && group[2].unwrap() < 1e-6,
            "{group:?}"
        );
        // Lit exactly alike, a free material beside a held one is fully observable: 1.
        let same = observability_of(&[a.clone(), a.clone()], &lambda, &[false, true], &w);
        assert!((same[1].unwrap() - 1.0).abs() < 1e-6, "{same:?}");
        // Nothing held: two alike pin each other; one alone is the scale itself; an unlit
        // one says nothing.
        let pair = observability_of(&[a.clone(), a.clone()], &lambda, &[true, true], &w);
        assert!(pair.iter().all(|v| v.unwrap() > 0.5), "{pair:?}");
        let dark = observability_of(&[a, vec![0.0; 16]], &lambda, &[true, true], &w);
        assert_eq!(dark, vec![Some(0.0), None]);
    }

    #[test]
    fn the_material_grid_bounds_the_sums() {
        assert_eq!(material_grid(9, 8).rings(), 9);
        assert_eq!(material_grid(27, 8).rings(), 27);
        let many = material_grid(17, 2000);
        assert!(2000 * NormalEquations::memory_needed(many.cell_count()) <= MATERIAL_SUMS_BYTES);
    }
}
