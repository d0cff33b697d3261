//! Estimating the environment map that best explains reference images.
//!
//! The one path tracer estimates the transport T ([`transport`]); a solver ([`nnls`]) fits the
//! per-cell radiance λ ≥ 0 to the references, per colour channel, over the masked pixels of
//! every view jointly: `min ‖T_α λ_α − I_α‖² (+ μ·smoothness)` subject to `λ_α ≥ 0`.
//!
//! - `nnls` (default): a pilot pass steers the cell sampling of one pass of independent parts,
//!   then exact NNLS on their unbiased normal equations.
//! - `gradient`: the paper's method — projected gradient descent with a backtracking line
//!   search, re-estimating T between rounds with importance sampling from the current estimate
//!   (sequential Monte Carlo).

pub mod albedo;
pub mod job;
pub mod nnls;
pub mod pipeline;
pub mod recovery;
pub mod select;
pub mod spheres;
pub mod texels;
pub mod transport;

use std::time::{Duration, Instant};

use glam::Vec3;
use serde::Serialize;

use crate::envmap::{Envmap, RingGrid};
use crate::imageio::Image;
use crate::render::{RenderSettings, Renderer};
use crate::scene::Camera;
use transport::{NormalEquations, Part, Targets, accumulate};

/// Which solver fits λ.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, serde::Deserialize, schemars::JsonSchema,
)]
#[serde(rename_all = "kebab-case")]
pub enum Solver {
    /// Exact non-negative least squares (active set) on the normal equations.
    Nnls,
    /// The paper's projected gradient descent with sequential Monte Carlo re-sampling.
    Gradient,
}

impl Solver {
    /// Transport parts or rounds by default: NNLS combines four independent parts
    /// ([`transport`]; it needs two or more for an unbiased TᵀT; measured with sequential
    /// rounds on the bundled scene at 9 rings, mean relMAE over 3 seeds, 2 → 4 at equal
    /// samples: 10.09% → 9.94% at 128 spp, 9.87% → 9.84% at 512). The gradient solver
    /// continues from its estimate over three rounds.
    pub fn default_rounds(self) -> u32 {
        match self {
            Solver::Nnls => 4,
            Solver::Gradient => 3,
        }
    }
}

/// How the NNLS solver treats a cell's three channels.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, serde::Deserialize, schemars::JsonSchema,
)]
#[serde(rename_all = "kebab-case")]
pub enum Colour {
    /// One grey radiance per cell first (NNLS on the three channels' systems summed: which
    /// cells are lit, and how brightly), then each channel as that grey map times a per-cell
    /// factor, every factor pulled weakly toward 1 ([`CHROMA_PRIOR`]): the lit cells are the
    /// same in every channel, and a cell the data barely tell apart stays near grey. Not the
    /// default: which cells the grey fit lights is all or nothing in every channel, so a
    /// cluster's direction scatters more between seeds (a known 5-ring sky: 2.2° over 8 seeds
    /// against 0.25° per channel), which its jackknife understated (0.66°): an estimate in
    /// this mode states no interval for its clusters.
    Together,
    /// Each channel fitted on its own (the paper's way): nearly collinear neighbouring cells
    /// let each channel pick its own, so a white light can come back as red, green and blue
    /// cells side by side.
    #[default]
    PerChannel,
}

/// Weight of the pull of every colour factor toward 1 (grey) under [`Colour::Together`],
/// relative to the mean diagonal of the factors' system. Measured at 9 rings, split power
/// (share in cells with a channel below a fifth of their brightest) and relMAE: the bundled
/// scene 27.7% and 9.360% per channel; 0 and 9.326% at 0.003; 0 and 9.336% at 0.01. A known
/// coloured sky (warm and blue cells) fitted at 0.01 needed 2.01% relMAE where 2% passed the
/// exposure test; smoothing the factors between neighbouring cells as well (weight 0.01 to 1)
/// biased that sky to 1.4–2.9× its noise floor, so no smoothing is applied.
pub const CHROMA_PRIOR: f64 = 3e-3;

/// How to fit.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct FitSettings {
    pub rings: u32,
    /// Samples, bounces and seed of the transport estimate.
    pub transport: RenderSettings,
    pub solver: Solver,
    /// Weight of the smoothness term between neighbouring cells, relative to the data term's
    /// scale (mean diagonal of TᵀT); 0 = none.
    pub smooth: f64,
    /// Weight of a ridge pulling every cell toward zero, relative to the mean diagonal of TᵀT:
    /// cells the views barely see stay dark instead of taking wild values; 0 = none.
    pub ridge: f64,
    /// How the transport's samples are split. NNLS: into this many independent parts of one
    /// pass, sampled by a pilot's estimate ([`fit`]; their mean, and cross products for TᵀT).
    /// Gradient: into sequential rounds (sequential Monte Carlo), each sampling cells by the
    /// current estimate (plus a defensive floor) and continuing from it.
    pub rounds: u32,
    /// Wall-clock budget of each channel's solve.
    pub time_limit: Duration,
    /// Fit on three quarters of the pixels only, leaving the quarter [`is_held_out`] picks for
    /// judging candidates on re-renders ([`select`]).
    pub holdout: bool,
    /// With NNLS and at most [`MAX_JACKKNIFE_CELLS`] cells, also fit this many delete-a-group
    /// jackknife replicates ([`Fit::replicates`]); below 2, none.
    pub jackknife: u32,
    /// How NNLS treats the channels (the gradient solver fits each on its own).
    pub colour: Colour,
}

/// Most cells [`FitSettings::jackknife`] fits replicates for (17 rings): the sums are kept per
/// group (groups × 1.3 MB at 330 cells) and each replicate is a solve of its own.
pub const MAX_JACKKNIFE_CELLS: usize = 330;

/// The jackknife group of pixel `(view, pixel)` among `groups`: a hash, so each group is
/// scattered over every view (the pixels' noise is independent, so any split samples it).
fn jackknife_group((view, pixel): (usize, u32), groups: usize) -> usize {
    (crate::sampling::mix64(((view as u64) << 32 | pixel as u64) ^ 0x0000_1ACC_0A1F)
        % groups as u64) as usize
}

/// The fixed quarter of the pixels a hold-out fit leaves out, by (view, pixel index): a hash,
/// so held-out pixels are scattered over every view.
pub fn is_held_out((view, pixel): (usize, u32)) -> bool {
    crate::sampling::mix64(((view as u64) << 32 | pixel as u64) ^ 0x401D).is_multiple_of(4)
}

/// Error of a hold-out fit on the held-out pixels.
#[derive(Debug, Clone, Default)]
pub struct Validation {
    /// Per held-out pixel: Σ over channels of |T·λ − reference|.
    pub abs_error: Vec<f64>,
    /// Σ over held-out pixels and channels of |reference|.
    pub reference_abs: f64,
}

impl Validation {
    /// relMAE over the held-out pixels.
    pub fn rel_mae(&self) -> f64 {
        self.abs_error.iter().sum::<f64>() / self.reference_abs.max(f64::MIN_POSITIVE)
    }
}

impl FitSettings {
    /// What [`fit`] reports to its progress on `masks`: each pixel it renders, once per part
    /// or round, the pilot's too (each unit a pixel at one part's samples).
    pub fn progress_units(&self, masks: &[Vec<bool>]) -> u64 {
        let rounds = self.rounds.max(1) as usize;
        let fit_pixel = |p| self.fits(p);
        let main = transport::progress_units(masks, &fit_pixel, rounds);
        match self.solver {
            Solver::Nnls if rounds >= 2 => {
                main + transport::progress_units(masks, &|p| fit_pixel(p) && in_pilot(p), 1)
            }
            _ => main,
        }
    }

    /// Whether `fit` fits pixel `p` (all pixels, or with `holdout` those [`is_held_out`]
    /// leaves in).
    fn fits(&self, p: (usize, u32)) -> bool {
        !self.holdout || !is_held_out(p)
    }

    /// What [`fit_candidates`] reports to its progress on `masks`: as [`fit`] with `holdout`.
    pub fn candidates_progress_units(&self, masks: &[Vec<bool>]) -> u64 {
        FitSettings {
            holdout: true,
            solver: Solver::Nnls,
            ..*self
        }
        .progress_units(masks)
    }

    /// What [`Candidates::refit`] reports to its progress: each held-out pixel once per part.
    pub fn refit_progress_units(&self, masks: &[Vec<bool>]) -> u64 {
        transport::progress_units(masks, &|p| is_held_out(p), self.rounds.max(1) as usize)
    }

    /// Settings for `spp` transport samples per pixel in all, split over `rounds`, with the
    /// transport's own seed (the references' + 1); no smoothing, ridge 0.001, 60 s per solve.
    pub fn new(render: &RenderSettings, rings: u32, solver: Solver, spp: u32, rounds: u32) -> Self {
        let rounds = rounds.max(1);
        FitSettings {
            rings,
            transport: RenderSettings {
                spp: (spp / rounds).max(1),
                seed: render.seed.wrapping_add(1),
                ..*render
            },
            solver,
            smooth: 0.0,
            ridge: 1e-3,
            rounds,
            time_limit: Duration::from_secs(60),
            holdout: false,
            jackknife: 0,
            colour: Colour::PerChannel,
        }
    }
}

/// One channel's solve. With [`Colour::Together`]: the iterations of the grey fit (counted in
/// every channel) and of this channel's factors, the KKT violation and convergence of the
/// problems solved (grey and factors; the channel's own problem is not solved, its unlit cells
/// are held dark), and each of those solves has the whole time budget.
#[derive(Debug, Clone, Serialize, schemars::JsonSchema)]
pub struct ChannelFit {
    pub iterations: usize,
    pub kkt_violation: f64,
    pub converged: bool,
    /// Objective ‖Tλ − I‖² after each iteration.
    pub objective: Vec<f64>,
}

/// A fitted envmap and how it was found.
pub struct Fit {
    pub envmap: Envmap,
    pub channels: Vec<ChannelFit>,
    pub transport_seconds: f64,
    pub solve_seconds: f64,
    pub transport_bytes: usize,
    /// The solver produced values that are not finite (replaced by 0): the fit failed.
    pub non_finite: bool,
    /// Delete-a-group jackknife replicates ([`FitSettings::jackknife`]): the same fit without
    /// one group of pixels each. With G of them, the variance of any function θ of the envmap
    /// is `(G−1)/G Σ_k (θ_k − θ̄)²`: the references' noise, the transport's and their
    /// dependence on the pixel are all in it, with no noise model assumed.
    pub replicates: Vec<Envmap>,
}

/// Pairs of neighbouring cells: adjacent in a ring, or overlapping in azimuth across rings.
pub fn neighbours(grid: &RingGrid) -> Vec<(u32, u32)> {
    let mut pairs = std::collections::BTreeSet::new();
    for ring in 0..grid.rings() {
        let (start, n) = (grid.ring_start(ring), grid.ring_len(ring));
        if n > 1 {
            for j in 0..n {
                let (a, b) = (start + j, start + (j + 1) % n);
                pairs.insert((a.min(b), a.max(b)));
            }
        }
        if ring + 1 < grid.rings() {
            let (next_start, m) = (grid.ring_start(ring + 1), grid.ring_len(ring + 1));
            let k = 4 * n.max(m);
            for s in 0..k {
                let phi = std::f64::consts::TAU * (s as f64 + 0.5) / k as f64;
                let a = start + ((phi * n as f64 / std::f64::consts::TAU).round() as u32 % n);
                let b = next_start + ((phi * m as f64 / std::f64::consts::TAU).round() as u32 % m);
                pairs.insert((a.min(b), a.max(b)));
            }
        }
    }
    pairs.into_iter().collect()
}

/// Normal equations of one channel, regularised: (TᵀT + ridge + smoothness, TᵀI, ‖I‖²), dense
/// row-major f64.
fn normal_equations(
    ne: &NormalEquations,
    ch: usize,
    smooth_pairs: &[(u32, u32)],
    smooth: f64,
    ridge: f64,
) -> (Vec<f64>, Vec<f64>, f64) {
    let n = ne.cells;
    let mut g = ne.gram(ch);
    let mean_diag = (0..n).map(|i| g[i * n + i]).sum::<f64>() / n as f64;
    if ridge > 0.0 {
        for i in 0..n {
            g[i * n + i] += ridge * mean_diag;
        }
    }
    if smooth > 0.0 {
        let scale = smooth * mean_diag;
        for &(a, b) in smooth_pairs {
            let (a, b) = (a as usize, b as usize);
            g[a * n + a] += scale;
            g[b * n + b] += scale;
            g[a * n + b] -= scale;
            g[b * n + a] -= scale;
        }
    }
    (g, ne.tb(ch), ne.yy(ch))
}

/// Solves all three channels of `ne`, starting the gradient solver from `start`; records
/// iterations and objectives into `channels` when given.
fn solve_all(
    ne: &NormalEquations,
    grid: &RingGrid,
    settings: &FitSettings,
    start: &[Vec<f64>],
    mut channels: Option<&mut Vec<ChannelFit>>,
) -> Vec<Vec<f64>> {
    let n = ne.cells;
    let rounds = settings.rounds.max(1);
    let pairs = if settings.smooth > 0.0 {
        neighbours(grid)
    } else {
        Vec::new()
    };
    let systems: Vec<_> = (0..3)
        .map(|ch| normal_equations(ne, ch, &pairs, settings.smooth, settings.ridge))
        .collect();
    let together = (settings.solver == Solver::Nnls && settings.colour == Colour::Together)
        .then(|| colour_together(&systems, settings.time_limit));
    systems
        .into_iter()
        .enumerate()
        .map(|(ch, (g, b, yy))| {
            let s = match settings.solver {
                Solver::Nnls => match &together {
                    Some(sols) => sols[ch].clone(),
                    None => nnls::nnls(&g, &b, 1e-9, 20 * n + 100, settings.time_limit),
                },
                Solver::Gradient => nnls::projected_gradient(
                    &g,
                    &b,
                    &start[ch],
                    1e-6,
                    100_000,
                    settings.time_limit / rounds,
                ),
            };
            if let Some(chs) = channels.as_deref_mut() {
                let c = &mut chs[ch];
                c.iterations += s.iterations;
                c.kkt_violation = s.kkt_violation;
                c.converged = s.converged;
                // ‖Tλ − y‖² = 2·(½λᵀGλ − bᵀλ) + ‖y‖² (exact without regularisation).
                c.objective
                    .extend(s.objective.iter().map(|f| (2.0 * f + yy).max(0.0)));
            }
            s.x
        })
        .collect()
}

/// The three channels' solutions with their colour kept together ([`Colour::Together`]), from
/// their regularised systems `(G, b, ‖y‖²)`: the grey map `s`, then per channel the factors
/// `f ≥ 0` minimising `‖T diag(s) f − y‖² + p Σ (f − 1)²` on the cells `s` lights, with
/// `p` [`CHROMA_PRIOR`] times the mean diagonal of `diag(s) G diag(s)`; `λ = s · f`.
fn colour_together(
    systems: &[(Vec<f64>, Vec<f64>, f64)],
    time_limit: Duration,
) -> Vec<nnls::Solution> {
    let n = systems[0].1.len();
    let mut g = vec![0.0; n * n];
    let mut b = vec![0.0; n];
    for (gc, bc, _) in systems {
        g.iter_mut().zip(gc).for_each(|(a, v)| *a += v);
        b.iter_mut().zip(bc).for_each(|(a, v)| *a += v);
    }
    let grey = nnls::nnls(&g, &b, 1e-9, 20 * n + 100, time_limit);
    let s = &grey.x;
    let cells: Vec<usize> = (0..n).filter(|&i| s[i] > 0.0).collect();
    let k = cells.len();
    systems
        .iter()
        .map(|(gc, bc, _)| {
            let mut sg: Vec<f64> = cells
                .iter()
                .flat_map(|&i| cells.iter().map(move |&j| s[i] * gc[i * n + j] * s[j]))
                .collect();
            let mut sb: Vec<f64> = cells.iter().map(|&i| s[i] * bc[i]).collect();
            let p = CHROMA_PRIOR * (0..k).map(|j| sg[j * k + j]).sum::<f64>() / k.max(1) as f64;
            for j in 0..k {
                sg[j * k + j] += p;
                sb[j] += p;
            }
            let f = nnls::nnls(&sg, &sb, 1e-9, 20 * k + 100, time_limit);
            let mut x = vec![0.0; n];
            for (&i, v) in cells.iter().zip(&f.x) {
                x[i] = s[i] * v;
            }
            let objective = vec![nnls::objective(gc, bc, &x)];
            nnls::Solution {
                x,
                iterations: grey.iterations + f.iterations,
                converged: grey.converged && f.converged,
                kkt_violation: grey.kkt_violation.max(f.kkt_violation),
                objective,
            }
        })
        .collect()
}

/// Random streams of the transport renders (`1000 + view index`; the images' streams are
/// [`crate::render::view_stream`], hashes of the views' names).
const TRANSPORT_STREAMS: u64 = 1000;

/// The pixels the NNLS fit's pilot pass renders: a fixed quarter, by a hash of (view, pixel),
/// scattered over every view. The pilot only steers the cell sampling of the main pass, which
/// a quarter of the pixels does about as well as all of them (bundled scene, 64 spp, 3 seeds:
/// 9 rings 9.54% against 9.53% relMAE, 25 rings 9.56% against 9.39%; single seeds spread by
/// ±0.15%), for 1/(4P) of the main pass's samples with P parts (a sixteenth at the default 4).
fn in_pilot((view, pixel): (usize, u32)) -> bool {
    crate::sampling::mix64(((view as u64) << 32 | pixel as u64) ^ 0x005E_ED0F_9170)
        .is_multiple_of(4)
}

/// Seed of transport part or round `k`.
fn part_seed(settings: &FitSettings, k: u32) -> RenderSettings {
    let mut st = settings.transport;
    st.seed = st.seed.wrapping_add(k as u64 * 0x9E37_79B9);
    st
}

/// Fits an envmap of `settings.rings` rings to `references` (masked by `masks`), seen by
/// `cameras` in the scene of `renderer`.
///
/// - NNLS: [`nnls_pass`] into the one grid, then exact NNLS on its unbiased normal equations.
/// - Gradient: the paper's rounds, each a pass of one part sampled by the current estimate,
///   the solver continuing from it.
pub fn fit(
    renderer: &Renderer,
    cameras: &[&Camera],
    references: &[Image],
    masks: &[Vec<bool>],
    settings: &FitSettings,
    progress: &(dyn Fn(u64) + Sync),
) -> Fit {
    if settings.solver == Solver::Gradient {
        return fit_gradient(renderer, cameras, references, masks, settings, progress);
    }
    let grid = RingGrid::new(settings.rings);
    let groups = settings.jackknife as usize;
    if groups >= 2 && grid.cell_count() <= MAX_JACKKNIFE_CELLS {
        return fit_jackknife(
            renderer, cameras, references, masks, settings, groups, progress,
        );
    }
    let fit_pixel = |p| settings.fits(p).then_some(0);
    let targets = Targets::one(&grid, &fit_pixel);
    let pass = nnls_pass(
        renderer, cameras, references, masks, settings, &grid, &targets, progress,
    );
    solved(
        &pass.sums[0][0],
        &grid,
        settings,
        (pass.seconds, pass.bytes),
    )
}

/// [`fit`] with its jackknife replicates: one pass whose sums are kept per group of pixels
/// (the same pilot, parts and rendered rows as without groups, so the fit differs only by
/// the order of its sums), each replicate solved on the sums of the other groups.
fn fit_jackknife(
    renderer: &Renderer,
    cameras: &[&Camera],
    references: &[Image],
    masks: &[Vec<bool>],
    settings: &FitSettings,
    groups: usize,
    progress: &(dyn Fn(u64) + Sync),
) -> Fit {
    let grid = RingGrid::new(settings.rings);
    let group_of = |p| settings.fits(p).then(|| jackknife_group(p, groups));
    let targets = Targets {
        grids: std::slice::from_ref(&grid),
        sets: groups,
        set_of: &group_of,
        max_set_cells: MAX_JACKKNIFE_CELLS,
    };
    let pass = nnls_pass(
        renderer, cameras, references, masks, settings, &grid, &targets, progress,
    );
    let all = pass.total(0);
    let mut fit = solved(&all, &grid, settings, (pass.seconds, pass.bytes));
    add_replicates(&mut fit, &pass.sums[0], &all, &grid, settings);
    fit
}

/// Adds to `fit` (of `grid`, on `all`, the sums of every group in `per_group`) its
/// delete-a-group jackknife replicates, each solved on the sums of the other groups. With
/// fewer than two groups, none; a replicate that fails or stops short leaves none rather than
/// a wrong interval.
fn add_replicates(
    fit: &mut Fit,
    per_group: &[NormalEquations],
    all: &NormalEquations,
    grid: &RingGrid,
    settings: &FitSettings,
) {
    let groups = per_group.len();
    if groups < 2 {
        return;
    }
    let t = Instant::now();
    let zero = vec![vec![0.0f64; all.cells]; 3];
    // All replicates together within the fit's own time budget.
    let quick = FitSettings {
        time_limit: settings.time_limit / groups as u32,
        ..*settings
    };
    fit.replicates = per_group
        .iter()
        .filter_map(|group| {
            let ne = all.without(group);
            let mut channels = new_channels();
            let x = solve_all(&ne, grid, &quick, &zero, Some(&mut channels));
            let (radiance, non_finite) = radiance_of(&x);
            let converged = channels.iter().all(|c| c.converged);
            (converged && !non_finite)
                .then(|| Envmap::new(grid.rings(), radiance).ok())
                .flatten()
        })
        .collect();
    if fit.replicates.len() != groups {
        fit.replicates.clear();
    }
    fit.solve_seconds += t.elapsed().as_secs_f64();
}

/// The sums of an NNLS transport pass, and what the pass cost.
pub struct Pass {
    /// Normal equations by `[grid][set]` of the pass's [`Targets`].
    pub sums: Vec<Vec<NormalEquations>>,
    /// The parts of its main pass (their seeds and cell sampling), to add more pixels to
    /// the same sums.
    pub parts: Vec<Part>,
    pub seconds: f64,
    /// Bytes the pass and a solve after it need at most ([`transport::pass_memory`]).
    pub bytes: usize,
}

impl Pass {
    /// Grid `g`'s sums over every set of pixels.
    fn total(&self, g: usize) -> NormalEquations {
        sum_of(&self.sums[g])
    }
}

/// The sums of several sets of pixels (at least one) rendered by the same parts, added.
fn sum_of(sets: &[NormalEquations]) -> NormalEquations {
    let mut all = sets[0].clone();
    for set in &sets[1..] {
        all.add(set);
    }
    all
}

/// The NNLS estimator's transport. A pilot pass ([`in_pilot`] pixels of any set, one part, the
/// cells of `pilot` sampled by solid angle) is solved on its own Gram to steer the cell
/// sampling of the main pass: `rounds` independent parts of `spp / rounds` samples each,
/// sampled by the pilot's estimate plus a defensive floor, accumulated into `targets` (whose
/// grids need not be the pilot's). With one round, no pilot: one part cannot give an unbiased
/// TᵀT, so there is nothing to steer for.
#[allow(clippy::too_many_arguments)]
fn nnls_pass(
    renderer: &Renderer,
    cameras: &[&Camera],
    references: &[Image],
    masks: &[Vec<bool>],
    settings: &FitSettings,
    pilot: &RingGrid,
    targets: &Targets,
    progress: &(dyn Fn(u64) + Sync),
) -> Pass {
    let t0 = Instant::now();
    let rounds = settings.rounds.max(1);
    let constant = Envmap::constant(pilot.rings(), Vec3::ONE);
    let sampling = if rounds >= 2 {
        let part = Part {
            sampling: constant,
            settings: part_seed(settings, rounds),
        };
        let in_a_set = |p| ((targets.set_of)(p).is_some() && in_pilot(p)).then_some(0);
        let pilot_targets = Targets::one(pilot, &in_a_set);
        let ne = &accumulate(
            renderer,
            cameras,
            masks,
            &pilot_targets,
            references,
            &[part],
            TRANSPORT_STREAMS,
            progress,
        )[0][0];
        let zero = vec![vec![0.0f64; ne.cells]; 3];
        let x = solve_all(ne, pilot, settings, &zero, None);
        // The pilot only steers: a value out of range there fails nothing.
        steering(pilot.rings(), &radiance_of(&x).0)
    } else {
        constant
    };
    let parts: Vec<Part> = (0..rounds)
        .map(|k| Part {
            sampling: sampling.clone(),
            settings: part_seed(settings, k),
        })
        .collect();
    let sums = accumulate(
        renderer,
        cameras,
        masks,
        targets,
        references,
        &parts,
        TRANSPORT_STREAMS,
        progress,
    );
    Pass {
        sums,
        bytes: transport::pass_memory(targets, parts.len()),
        parts,
        seconds: t0.elapsed().as_secs_f64(),
    }
}

fn new_channels() -> Vec<ChannelFit> {
    (0..3)
        .map(|_| ChannelFit {
            iterations: 0,
            kkt_violation: 0.0,
            converged: false,
            objective: Vec::new(),
        })
        .collect()
}

/// The NNLS fit of `grid` on the sums `ne` of a pass that took `transport_seconds` and needs
/// `transport_bytes`.
fn solved(
    ne: &NormalEquations,
    grid: &RingGrid,
    settings: &FitSettings,
    (transport_seconds, transport_bytes): (f64, usize),
) -> Fit {
    let t = Instant::now();
    let mut channels = new_channels();
    let zero = vec![vec![0.0f64; ne.cells]; 3];
    let x = solve_all(ne, grid, settings, &zero, Some(&mut channels));
    let (radiance, non_finite) = radiance_of(&x);
    Fit {
        envmap: Envmap::new(grid.rings(), radiance)
            .expect("solver output is finite and non-negative"),
        channels,
        transport_seconds,
        solve_seconds: t.elapsed().as_secs_f64(),
        transport_bytes,
        non_finite,
        replicates: Vec::new(),
    }
}

/// Hold-out fits of several resolutions from one NNLS pass ([`fit_candidates`]), and what it
/// takes to refit any of them on every pixel.
pub struct Candidates {
    pub grids: Vec<RingGrid>,
    /// Per grid, its fit on the pixels [`is_held_out`] leaves in.
    pub fits: Vec<Fit>,
    pass: Pass,
}

impl Candidates {
    /// Candidate `i` fitted on every pixel: its sums, plus the held-out pixels rendered by
    /// the same parts into its grid alone (a pixel's paths depend on its index and the
    /// part's seed only, so these are the rows the pass would have added), with its
    /// jackknife replicates if the pass kept its sums per group. `progress` as for
    /// [`accumulate`]: [`FitSettings::refit_progress_units`].
    #[allow(clippy::too_many_arguments)]
    pub fn refit(
        &self,
        i: usize,
        settings: &FitSettings,
        renderer: &Renderer,
        cameras: &[&Camera],
        references: &[Image],
        masks: &[Vec<bool>],
        progress: &(dyn Fn(u64) + Sync),
    ) -> Fit {
        let t0 = Instant::now();
        let grid = &self.grids[i];
        let groups = self.pass.sums[i].len();
        let held_out = |p| is_held_out(p).then(|| jackknife_group(p, groups));
        let targets = Targets {
            sets: groups,
            ..Targets::one(grid, &held_out)
        };
        let mut per_group = accumulate(
            renderer,
            cameras,
            masks,
            &targets,
            references,
            &self.pass.parts,
            TRANSPORT_STREAMS,
            progress,
        )
        .swap_remove(0);
        for (sums, held_in) in per_group.iter_mut().zip(&self.pass.sums[i]) {
            sums.add(held_in);
        }
        let all = sum_of(&per_group);
        let seconds = self.pass.seconds + t0.elapsed().as_secs_f64();
        // Beside the pass: the held-out pixels' sums per group, their total and a replicate's.
        let bytes = self.pass.bytes
            + (per_group.len() + 2) * NormalEquations::memory_needed(grid.cell_count());
        let mut fit = solved(&all, grid, settings, (seconds, bytes));
        add_replicates(&mut fit, &per_group, &all, grid, settings);
        fit
    }

    /// Candidate `i`'s hold-out fit, with its jackknife replicates if the pass kept its sums
    /// per group.
    pub fn held_in_fit(mut self, i: usize, settings: &FitSettings) -> Fit {
        let all = self.pass.total(i);
        let mut fit = self.fits.swap_remove(i);
        add_replicates(&mut fit, &self.pass.sums[i], &all, &self.grids[i], settings);
        fit
    }
}

/// Fits every resolution of `rings` on the pixels [`is_held_out`] leaves in, with the NNLS
/// estimator, from one transport pass: each path's directions are binned into every
/// candidate's grid ([`transport::CellAccumulator`]), the pilot steering from the finest
/// grid: fine grids fit noticeably worse when sampled by a coarser estimate (scenario s30 at
/// 27 rings: 8.85% steered by 15 rings, 8.35% by 27, 8.26% for its own fixed fit), coarse
/// ones do not mind. One walk then serves all candidates, where fitting each on its own would walk the
/// scene once per candidate. With `template.jackknife`, grids of at most
/// [`MAX_JACKKNIFE_CELLS`] keep their sums per jackknife group, for the chosen one's
/// intervals. `template` gives everything but the ring count.
pub fn fit_candidates(
    renderer: &Renderer,
    cameras: &[&Camera],
    references: &[Image],
    masks: &[Vec<bool>],
    template: &FitSettings,
    rings: &[u32],
    progress: &(dyn Fn(u64) + Sync),
) -> Candidates {
    let grids: Vec<RingGrid> = rings.iter().map(|&r| RingGrid::new(r)).collect();
    let finest = grids
        .iter()
        .max_by_key(|g| g.cell_count())
        .expect("at least one candidate");
    let groups = if template.jackknife >= 2 {
        template.jackknife as usize
    } else {
        1
    };
    let held_in = |p| (!is_held_out(p)).then(|| jackknife_group(p, groups));
    let targets = Targets {
        grids: &grids,
        sets: groups,
        set_of: &held_in,
        max_set_cells: MAX_JACKKNIFE_CELLS,
    };
    let pass = nnls_pass(
        renderer, cameras, references, masks, template, finest, &targets, progress,
    );
    let fits = grids
        .iter()
        .enumerate()
        .map(|(i, g)| {
            let settings = FitSettings {
                rings: g.rings(),
                ..*template
            };
            solved(&pass.total(i), g, &settings, (pass.seconds, pass.bytes))
        })
        .collect();
    Candidates { grids, fits, pass }
}

/// The gradient solver's fit: sequential rounds, each one part sampled by the estimate so far.
fn fit_gradient(
    renderer: &Renderer,
    cameras: &[&Camera],
    references: &[Image],
    masks: &[Vec<bool>],
    settings: &FitSettings,
    progress: &(dyn Fn(u64) + Sync),
) -> Fit {
    let grid = RingGrid::new(settings.rings);
    let n = grid.cell_count();
    let mut channels = new_channels();
    let (mut transport_seconds, mut solve_seconds) = (0.0, 0.0);
    let mut non_finite = false;
    let fit_pixel = |p| settings.fits(p).then_some(0);
    let targets = Targets::one(&grid, &fit_pixel);
    let (mut sampling, mut lambda) = (
        Envmap::constant(settings.rings, Vec3::ONE),
        vec![vec![0.0f64; n]; 3],
    );
    let mut radiance = Vec::new();
    for round in 0..settings.rounds.max(1) {
        let part = Part {
            sampling: sampling.clone(),
            settings: part_seed(settings, round),
        };
        let t0 = Instant::now();
        let ne = &accumulate(
            renderer,
            cameras,
            masks,
            &targets,
            references,
            &[part],
            TRANSPORT_STREAMS,
            progress,
        )[0][0];
        transport_seconds += t0.elapsed().as_secs_f64();
        let t1 = Instant::now();
        let x = solve_all(ne, &grid, settings, &lambda, Some(&mut channels));
        solve_seconds += t1.elapsed().as_secs_f64();
        let bad;
        (radiance, bad) = radiance_of(&x);
        non_finite |= bad;
        lambda = (0..3)
            .map(|ch| radiance.iter().map(|r| r[ch] as f64).collect())
            .collect();
        sampling = steering(settings.rings, &radiance);
    }
    Fit {
        envmap: Envmap::new(settings.rings, radiance)
            .expect("solver output is finite and non-negative"),
        channels,
        transport_seconds,
        solve_seconds,
        transport_bytes: transport::memory_needed(&[(n, 1)], 1),
        non_finite,
        replicates: Vec::new(),
    }
}

/// A solver's per-channel cells as radiance, and whether any was out of range: a value
/// outside [0, MAX_RADIANCE] (a solver blown up, or beyond any radiance) becomes 0, and
/// callers report the fit as failed.
fn radiance_of(x: &[Vec<f64>]) -> (Vec<Vec3>, bool) {
    let mut bad = false;
    let mut cell = |v: f64| {
        let v = v as f32;
        if (0.0..=crate::imageio::MAX_RADIANCE).contains(&v) {
            v
        } else {
            bad = true;
            0.0
        }
    };
    let radiance = (0..x[0].len())
        .map(|c| Vec3::new(cell(x[0][c]), cell(x[1][c]), cell(x[2][c])))
        .collect();
    (radiance, bad)
}

/// The envmap that samples cells by an estimate, with a defensive floor so that no cell is
/// starved.
fn steering(rings: u32, radiance: &[Vec3]) -> Envmap {
    let mean = radiance.iter().copied().sum::<Vec3>() / radiance.len() as f32;
    let steer = radiance
        .iter()
        .map(|r| {
            (*r + 0.25 * mean + Vec3::splat(1e-6)).min(Vec3::splat(crate::imageio::MAX_RADIANCE))
        })
        .collect();
    Envmap::new(rings, steer).expect("finite and non-negative")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn neighbours_are_symmetric_local_and_connect_the_grid() {
        for rings in [2, 3, 9, 21] {
            let g = RingGrid::new(rings);
            let pairs = neighbours(&g);
            let n = g.cell_count();
            // Connected: a union-find over the pairs ends in one set.
            let mut parent: Vec<usize> = (0..n).collect();
            fn find(p: &mut Vec<usize>, i: usize) -> usize {
                if p[i] != i {
                    let r = find(p, p[i]);
                    p[i] = r;
                }
                p[i]
            }
            for &(a, b) in &pairs {
                assert!(a < b);
                let d = g.center(a).angle_between(g.center(b));
                assert!(
                    d < 2.5 * std::f32::consts::PI / (rings - 1) as f32,
                    "rings {rings}: {a}-{b} {d}"
                );
                let (ra, rb) = (find(&mut parent, a as usize), find(&mut parent, b as usize));
                parent[ra] = rb;
            }
            let root = find(&mut parent, 0);
            assert!(
                (0..n).all(|i| find(&mut parent, i) == root),
                "rings {rings}"
            );
        }
    }
}
