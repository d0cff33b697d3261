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

/// Relative change of every multiplier below which the alternation stops.
pub const ALBEDO_TOLERANCE: f64 = 0.02;

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
    /// What fixes the overall scale between albedo and light, in words.
    pub gauge: String,
    /// The materials `--trust-albedo` named.
    pub trusted: Vec<String>,
    /// Lighting fits the alternation made, the last with every sample.
    pub fits: usize,
    /// The largest relative change of a multiplier at the last step.
    pub last_change: f64,
    /// Whether the last change was below [`ALBEDO_TOLERANCE`].
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
const OBSERVABILITY_BYTES: usize = 256 << 20;

/// The grid [`observability`] measures on for a fit of `rings` rings and `sets` materials: the
/// fit's, or the finest coarser one whose per-material sums fit in [`OBSERVABILITY_BYTES`]
/// and whose cells are at most [`super::MAX_JACKKNIFE_CELLS`].
pub fn observability_grid(rings: u32, sets: usize) -> RingGrid {
    (1..=rings)
        .rev()
        .map(RingGrid::new)
        .find(|g| {
            g.cell_count() <= super::MAX_JACKKNIFE_CELLS
                && sets.max(1) * NormalEquations::memory_needed(g.cell_count())
                    <= OBSERVABILITY_BYTES
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

/// Each material's observability (the module doc) under the fitted `envmap`, for the materials
/// `wanted` marks (the others get `None`): one transport pass of two parts at the fit's
/// samples, its sums kept per material, over [`observability_grid`]. `progress` gets
/// [`transport::progress_units`] of the wanted materials' pixels and two parts.
#[allow(clippy::too_many_arguments)]
pub fn observability(
    renderer: &Renderer,
    views: &[&Camera],
    references: &[Image],
    masks: &[Vec<bool>],
    pixels: &MaterialPixels,
    wanted: &[bool],
    envmap: &Envmap,
    settings: &FitSettings,
    progress: &(dyn Fn(u64) + Sync),
) -> Vec<Option<f64>> {
    let sets: Vec<usize> = (0..wanted.len()).filter(|&m| wanted[m]).collect();
    let mut out = vec![None; wanted.len()];
    if sets.is_empty() {
        return out;
    }
    let mut set_of_material = vec![None; wanted.len()];
    for (s, &m) in sets.iter().enumerate() {
        set_of_material[m] = Some(s);
    }
    let grid = observability_grid(envmap.grid.rings(), sets.len());
    let set_of = |p: (usize, u32)| pixels.of(p).and_then(|m| set_of_material[m]);
    let targets = Targets {
        grids: std::slice::from_ref(&grid),
        sets: sets.len(),
        set_of: &set_of,
        max_set_cells: usize::MAX,
    };
    let sampling = super::steering(envmap.grid.rings(), envmap.radiance());
    let parts: Vec<Part> = (0..2)
        .map(|k| Part {
            sampling: sampling.clone(),
            settings: super::part_seed(settings, OBSERVABILITY_PARTS + k),
        })
        .collect();
    let sums = transport::accumulate(
        renderer,
        views,
        masks,
        &targets,
        references,
        &parts,
        super::TRANSPORT_STREAMS,
        progress,
    );
    let lambda = resampled(envmap, &grid);
    let per_channel: Vec<Vec<Option<f64>>> = (0..3)
        .map(|ch| {
            let grams: Vec<Vec<f64>> = sums[0].iter().map(|s| s.gram(ch)).collect();
            let l: Vec<f64> = lambda.iter().map(|v| v[ch]).collect();
            observability_of(&grams, &l)
        })
        .collect();
    for (s, &m) in sets.iter().enumerate() {
        // The least observable channel (a channel with no light says nothing).
        out[m] = per_channel
            .iter()
            .filter_map(|c| c[s])
            .fold(None, |a: Option<f64>, r| Some(a.map_or(r, |a| a.min(r))));
    }
    out
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

/// Part seeds of [`observability`]'s pass, apart from the fit's.
const OBSERVABILITY_PARTS: u32 = 7_919;

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
    fn the_observability_grid_bounds_the_sums() {
        assert_eq!(observability_grid(9, 8).rings(), 9);
        let g = observability_grid(27, 8);
        assert!(g.cell_count() <= super::super::MAX_JACKKNIFE_CELLS);
        let many = observability_grid(17, 2000);
        assert!(2000 * NormalEquations::memory_needed(many.cell_count()) <= OBSERVABILITY_BYTES);
    }
}
