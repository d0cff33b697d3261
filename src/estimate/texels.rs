//! Texel corrections of albedo textures (`--fit-albedo texels`): the shading a photographed
//! texture carries baked in, taken out where the fitted lighting does not explain it.
//!
//! **The model.** With the lighting fixed, a pixel that sees one textured material is linear
//! in the albedo where it sees it. The correction `c` is a coarse grid of RGB multipliers over
//! the texture's domain (repeat-wrapped and looked up bilinearly, as the texture is), coarse
//! enough to vary slowly against a pixel, so a pixel's reference is `y ≈ c(uv)·x` with `x` its
//! re-render at the current texture and `uv` the texture coordinates at its centre. Light that
//! came back to the same texture is scaled too, which the model ignores (a plane or a convex
//! object does not light itself).
//!
//! **Least squares with a membrane prior.** Per channel, over the grid's cells `c_j`:
//!
//! ```text
//! Σ_p (y_p − x_p Σ_j w_pj c_j)²  +  μ Σ_{i~j} (c_i − c_j)²  +  ε Σ_j (c_j − 1)²
//! ```
//!
//! with `w_pj` the bilinear taps and `i~j` the four-neighbour pairs (wrapping). `x_p²` is taken
//! as `x¹_p·x²_p` of two independent re-renders and `x_p` as their mean, so the renders' noise
//! does not bias `c` low (`E[x¹x²] = x̄²`, where `E[x²] = x̄² + σ²`); the references' noise
//! does not bias a least-squares fit. `μ` is the smoothness times the mean diagonal of the
//! data term over the cells pixels see: at 1 a cell leans on its neighbours as much as on its
//! own pixels. `ε` ([`UNSEEN_PULL`] of that diagonal) keeps the system definite: a cell no
//! pixel sees follows its seen neighbours, and far from any, stays 1.
//!
//! **Bounds.** The corrected texel times the material's factor is clamped to [0, 1]
//! ([`Correction::apply`]).

use faer::linalg::solvers::Solve;
use faer::sparse::{SparseColMat, Triplet};
use glam::{DVec3, Vec2, Vec3};
use schemars::JsonSchema;
use serde::Serialize;

use crate::scene::Texture;

/// Cells along the longer side of a texture's correction grid by default.
pub const DEFAULT_TEXEL_GRID: u32 = 32;

/// Fewest cells along a side (the neighbour bookkeeping needs three; four keeps a wrap from
/// tying a cell to itself).
pub const MIN_TEXEL_GRID: u32 = 4;

/// Most cells along a side: a finer grid than this is more unknowns than any capture's pixels
/// pin down, and the sparse solve grows with it.
pub const MAX_TEXEL_GRID: u32 = 256;

/// Default weight of the membrane prior, relative to the mean diagonal of the data term.
pub const DEFAULT_TEXEL_SMOOTHNESS: f64 = 1.0;

/// Largest `--texel-smoothness`: beyond it the prior swamps any capture's pixels (and the
/// system's scale would overflow).
pub const MAX_TEXEL_SMOOTHNESS: f64 = 1e6;

/// Pull of every cell toward 1, relative to the mean diagonal of the data term: far below any
/// seen cell's data, it only decides cells no pixel sees.
pub const UNSEEN_PULL: f64 = 1e-3;

/// Most cells of a grid whose standard deviations [`TexelSums::sigma`] measures (a 64×64 grid).
pub const MAX_SIGMA_CELLS: usize = 4096;

/// Pixel-weighted RMS change of a correction below which the texel rounds stop.
pub const TEXEL_TOLERANCE: f64 = 0.02;

/// Most texel rounds (a correction, then a lighting fit at it).
pub const MAX_TEXEL_ROUNDS: usize = 3;

/// A texel's albedo as rendered: texel × factor, clamped to [0, 1].
fn albedo(texel: Vec3, factor: Vec3) -> Vec3 {
    (texel * factor).clamp(Vec3::ZERO, Vec3::ONE)
}

/// `a / b` per channel, 1 where `b` is 0 (a channel the texture does not have).
fn ratio(a: Vec3, b: Vec3) -> DVec3 {
    let (a, b) = (a.as_dvec3(), b.as_dvec3());
    DVec3::select(b.cmpgt(DVec3::ZERO), a / b, DVec3::ONE)
}

/// `report.json`'s `albedo.texels[]`: one texture's correction.
#[derive(Debug, Clone, Serialize, JsonSchema)]
pub struct TexelFit {
    pub material: String,
    /// The material's index in the scene's materials (0: glTF's default material).
    pub index: usize,
    /// Cells of its correction grid, across and down.
    pub grid: [u32; 2],
    /// Pixels that see the material alone and fed the last round's correction.
    pub pixels: usize,
    /// Cells those pixels see; the others follow their seen neighbours (the prior) and, far
    /// from any, stay 1.
    pub cells_seen: usize,
    /// The least and the largest ratio of a texel as fitted to as given (per channel, clamps
    /// included, the material's multiplier not), over the texels the pixels see.
    pub range: [f64; 2],
    /// The last round's RMS relative change of the texels the pixels see (worst channel),
    /// clamps included ([`TEXEL_TOLERANCE`]).
    pub last_change: f64,
    /// Texels the bound (texel × factor within [0, 1]) clamped in the last round.
    pub clamped_texels: usize,
    /// One standard deviation of the last round's correction relative to it, over the cells
    /// the pixels see (a cell's worst lit channel): the median and the largest. From the
    /// residuals ([`TexelSums::sigma`]): noise, and misfit as if it were noise. Null for
    /// grids of more than 4096 cells ([`MAX_SIGMA_CELLS`]: a square texture's `--texel-grid`
    /// above 64) and where the last round's system could not be solved.
    pub sigma: Option<[f64; 2]>,
    /// The corrected texture as the glTF exports refer to it, relative to each:
    /// `albedo_textures/…` (8-bit sRGB PNG of texel × factor, the factor then 1).
    pub file: String,
}

/// The cells of a correction grid for a `width` × `height` texture with `cells` along its
/// longer side: the other side in proportion, each at most the texture's own and at least
/// [`MIN_TEXEL_GRID`]; `None` for a texture narrower than that (a palette or a constant: its
/// material's multiplier is all it can take).
pub fn grid_size(width: u32, height: u32, cells: u32) -> Option<(u32, u32)> {
    if width.min(height) < MIN_TEXEL_GRID {
        return None;
    }
    let (long, short) = (width.max(height), width.min(height));
    let along = cells.clamp(MIN_TEXEL_GRID, MAX_TEXEL_GRID).min(long);
    let other = ((along as u64 * short as u64 + long as u64 / 2) / long as u64) as u32;
    let other = other.clamp(MIN_TEXEL_GRID, MAX_TEXEL_GRID).min(short);
    Some(if width >= height {
        (along, other)
    } else {
        (other, along)
    })
}

/// The four bilinear taps (cell index, weight) of glTF texture coordinates `uv` on a
/// `width` × `height` grid, repeat-wrapped: the weights [`Texture::sample`] gives its texels.
/// `None` for coordinates that are not finite.
pub fn taps(uv: Vec2, width: u32, height: u32) -> Option<[(usize, f64); 4]> {
    let x = uv.x as f64 * width as f64 - 0.5;
    let y = uv.y as f64 * height as f64 - 0.5;
    if !(x.is_finite() && y.is_finite()) {
        return None;
    }
    let (x0, y0) = (x.floor(), y.floor());
    let (fx, fy) = (x - x0, y - y0);
    let (w, h) = (width as i64, height as i64);
    let (i0, j0) = ((x0 as i64).rem_euclid(w), (y0 as i64).rem_euclid(h));
    let (i1, j1) = ((i0 + 1) % w, (j0 + 1) % h);
    let at = |i: i64, j: i64| (j * w + i) as usize;
    Some([
        (at(i0, j0), (1.0 - fx) * (1.0 - fy)),
        (at(i1, j0), fx * (1.0 - fy)),
        (at(i0, j1), (1.0 - fx) * fy),
        (at(i1, j1), fx * fy),
    ])
}

/// The normal equations of one texture's correction ([`TexelSums::add`] per pixel).
#[derive(Debug, Clone)]
pub struct TexelSums {
    pub width: u32,
    pub height: u32,
    /// Per cell, per neighbour offset (`3·(dy+1) + (dx+1)`, wrapping), per channel:
    /// `Σ_p w_pi w_pj x¹_p x²_p`.
    gram: Vec<[DVec3; 9]>,
    /// Per cell, per channel: `Σ_p w_pi x̄_p y_p`.
    rhs: Vec<DVec3>,
    /// Per cell, per channel: `Σ_p w_pi x̄_p`, the re-render the cell carries.
    carried: Vec<DVec3>,
    /// Per cell: `Σ_p w_pi`, how much the pixels see it.
    pub seen: Vec<f64>,
    /// Pixels added.
    pub pixels: usize,
    /// As `gram`, of `Σ_p w_pi w_pj s_p²` with `s_p = x̄_p y_p − x¹_p x²_p c(uv_p)` a pixel's
    /// score under a fitted correction c ([`TexelSums::add_residual`]): the spread of the
    /// estimating equation, for [`TexelSums::sigma`].
    spread: Vec<[DVec3; 9]>,
}

impl TexelSums {
    pub fn new((width, height): (u32, u32)) -> TexelSums {
        let n = (width * height) as usize;
        TexelSums {
            width,
            height,
            gram: vec![[DVec3::ZERO; 9]; n],
            rhs: vec![DVec3::ZERO; n],
            carried: vec![DVec3::ZERO; n],
            seen: vec![0.0; n],
            pixels: 0,
            spread: vec![[DVec3::ZERO; 9]; n],
        }
    }

    /// The offset slot of cell `b` seen from cell `a` (they are at most one cell apart per
    /// axis, wrapping).
    fn slot(&self, a: usize, b: usize) -> usize {
        let (w, h) = (self.width as usize, self.height as usize);
        let step = |from: usize, to: usize, n: usize| {
            if to == from {
                1
            } else if to == (from + 1) % n {
                2
            } else {
                0
            }
        };
        3 * step(a / w, b / w, h) + step(a % w, b % w, w)
    }

    /// The cell at offset slot `k` from cell `a`.
    fn neighbour(&self, a: usize, k: usize) -> usize {
        let (w, h) = (self.width as i64, self.height as i64);
        let (dx, dy) = ((k % 3) as i64 - 1, (k / 3) as i64 - 1);
        let (i, j) = (a as i64 % w, a as i64 / w);
        ((j + dy).rem_euclid(h) * w + (i + dx).rem_euclid(w)) as usize
    }

    /// Adds a pixel at texture coordinates `uv` with reference `y` and two independent
    /// re-renders `x1`, `x2` at the current texture. A pixel whose coordinates are not finite
    /// is skipped.
    pub fn add(&mut self, uv: Vec2, y: Vec3, x1: Vec3, x2: Vec3) {
        let Some(taps) = taps(uv, self.width, self.height) else {
            return;
        };
        let (x1, x2) = (x1.as_dvec3(), x2.as_dvec3());
        let (cross, mean) = (x1 * x2, (x1 + x2) * 0.5);
        let y = y.as_dvec3();
        for &(a, wa) in &taps {
            self.rhs[a] += wa * mean * y;
            self.carried[a] += wa * mean;
            self.seen[a] += wa;
            for &(b, wb) in &taps {
                let k = self.slot(a, b);
                self.gram[a][k] += wa * wb * cross;
            }
        }
        self.pixels += 1;
    }

    /// Adds the residual of a pixel [`TexelSums::add`] took, under the correction `c` solved
    /// from these sums: what the references and the re-renders left unexplained, noise and
    /// misfit both.
    pub fn add_residual(&mut self, uv: Vec2, y: Vec3, x1: Vec3, x2: Vec3, c: &Correction) {
        let Some(taps) = taps(uv, self.width, self.height) else {
            return;
        };
        // The pixel's term of the estimating equation the solve zeroes, `Σ w (x̄y − x¹x²c)`:
        // its spread is the sandwich's meat.
        let (x1, x2) = (x1.as_dvec3(), x2.as_dvec3());
        let score = (x1 + x2) * 0.5 * y.as_dvec3() - x1 * x2 * c.at(uv);
        let meat = score * score;
        for &(a, wa) in &taps {
            for &(b, wb) in &taps {
                let k = self.slot(a, b);
                self.spread[a][k] += wa * wb * meat;
            }
        }
    }

    /// Whether [`TexelSums::sigma`] measures this grid (at most [`MAX_SIGMA_CELLS`] cells).
    pub fn measures_sigma(&self) -> bool {
        self.gram.len() <= MAX_SIGMA_CELLS
    }

    /// The factor by which `c` changes the pixels' summed re-render, per channel (1 where
    /// nothing is lit): a correction divided by it keeps the material's level and changes its
    /// pattern only.
    pub fn level(&self, c: &Correction) -> DVec3 {
        let (mut moved, mut total) = (DVec3::ZERO, DVec3::ZERO);
        for (x, k) in self.carried.iter().zip(&c.cells) {
            moved += *x * *k;
            total += *x;
        }
        DVec3::select(total.cmpgt(DVec3::ZERO), moved / total, DVec3::ONE)
    }

    /// Channel `ch`'s system `H = G + μ·(membrane) + ε·I` (lower triangle and upper alike)
    /// and ε, for membrane weight `smoothness`; `None` when nothing is lit in the channel.
    fn system(&self, ch: usize, smoothness: f64) -> Option<(SparseColMat<usize, f64>, f64)> {
        let n = self.gram.len();
        let seen_cells: Vec<usize> = (0..n).filter(|&a| self.seen[a] > 0.0).collect();
        let diag = seen_cells.iter().map(|&a| self.gram[a][4][ch]).sum::<f64>()
            / seen_cells.len().max(1) as f64;
        if diag <= 0.0 || diag.is_nan() {
            return None;
        }
        let (mu, eps) = (smoothness.max(0.0) * diag, UNSEEN_PULL * diag);
        let mut triplets = Vec::with_capacity(n * 9);
        for a in 0..n {
            let mut row = [0.0f64; 9];
            for (k, g) in self.gram[a].iter().enumerate() {
                row[k] = g[ch];
            }
            row[4] += eps;
            for k in [1, 3, 5, 7] {
                row[4] += mu;
                row[k] -= mu;
            }
            for (k, &v) in row.iter().enumerate() {
                if v != 0.0 {
                    triplets.push(Triplet::new(self.neighbour(a, k), a, v));
                }
            }
        }
        let h = SparseColMat::<usize, f64>::try_new_from_triplets(n, n, &triplets).ok()?;
        Some((h, eps))
    }

    /// The correction minimising the module's objective with membrane weight `smoothness`;
    /// `None` when no pixel was added or a channel's system is not positive definite.
    pub fn solve(&self, smoothness: f64) -> Option<Correction> {
        let n = self.gram.len();
        if !self.seen.iter().any(|&s| s > 0.0) {
            return None;
        }
        let mut cells = vec![DVec3::ONE; n];
        for ch in 0..3 {
            // Nothing lit in this channel: nothing to correct.
            let Some((h, eps)) = self.system(ch, smoothness) else {
                continue;
            };
            let llt = h.sp_cholesky(faer::Side::Lower).ok()?;
            let b = faer::Mat::<f64>::from_fn(n, 1, |a, _| self.rhs[a][ch] + eps);
            let c = llt.solve(b);
            for (a, cell) in cells.iter_mut().enumerate() {
                let v = c[(a, 0)];
                if !v.is_finite() {
                    return None;
                }
                cell[ch] = v.max(0.0);
            }
        }
        Some(Correction {
            width: self.width,
            height: self.height,
            cells,
            seen: self.seen.clone(),
        })
    }

    /// One standard deviation of each cell of the correction [`TexelSums::solve`] gives with
    /// `smoothness`, per channel:
    /// the sandwich `H⁻¹ S H⁻¹` with S the residuals' spread ([`TexelSums::add_residual`],
    /// which must have seen every pixel), so it holds whatever noise the references and the
    /// re-renders carry, and misfit as if it were noise; the prior's bias is not in it. `None`
    /// beyond [`MAX_SIGMA_CELLS`] cells (the columns of `H⁻¹` are solved for one by one) or
    /// where a system is not positive definite. 0 in channels with no light. `solved(k)`
    /// is told of every `k` columns done, `3 × cells` in all when it measures.
    pub fn sigma(&self, smoothness: f64, solved: &dyn Fn(u64)) -> Option<Vec<DVec3>> {
        if !self.measures_sigma() {
            return None;
        }
        let n = self.gram.len();
        let mut out = vec![DVec3::ZERO; n];
        for ch in 0..3 {
            let Some((h, _)) = self.system(ch, smoothness) else {
                solved(n as u64);
                continue;
            };
            let llt = h.sp_cholesky(faer::Side::Lower).ok()?;
            // Columns of H⁻¹ in blocks; the variance of cell i is xᵢᵀ S xᵢ, x = H⁻¹eᵢ.
            const BLOCK: usize = 256;
            for start in (0..n).step_by(BLOCK) {
                let k = BLOCK.min(n - start);
                let x = llt.solve(faer::Mat::<f64>::from_fn(n, k, |a, j| {
                    f64::from(a == start + j)
                }));
                for j in 0..k {
                    let mut v = 0.0;
                    for a in 0..n {
                        let xa = x[(a, j)];
                        if xa == 0.0 {
                            continue;
                        }
                        for (slot, s) in self.spread[a].iter().enumerate() {
                            v += xa * s[ch] * x[(self.neighbour(a, slot), j)];
                        }
                    }
                    if !v.is_finite() {
                        return None;
                    }
                    out[start + j][ch] = v.max(0.0).sqrt();
                }
                solved(k as u64);
            }
        }
        Some(out)
    }
}

/// A texture's correction: a multiplier per cell and channel.
#[derive(Debug, Clone)]
pub struct Correction {
    pub width: u32,
    pub height: u32,
    /// Row-major, row 0 at the texture's top (glTF's v = 0).
    pub cells: Vec<DVec3>,
    /// Per cell, how much the pixels saw it ([`TexelSums::seen`]).
    pub seen: Vec<f64>,
}

impl Correction {
    /// The correction's value at texture coordinates `uv` (bilinear, wrapping).
    pub fn at(&self, uv: Vec2) -> DVec3 {
        taps(uv, self.width, self.height)
            .map(|t| t.iter().map(|&(a, w)| self.cells[a] * w).sum())
            .unwrap_or(DVec3::ONE)
    }

    /// Whether a pixel saw any cell under texture coordinates `uv`.
    fn seen_at(&self, uv: Vec2) -> bool {
        taps(uv, self.width, self.height)
            .is_some_and(|t| t.iter().any(|&(a, w)| w > 0.0 && self.seen[a] > 0.0))
    }

    /// The texture coordinates of texel `i`'s centre in a `w` × `h` texture.
    fn texel_uv(i: usize, w: u32, h: u32) -> Vec2 {
        Vec2::new(
            ((i as u32 % w) as f32 + 0.5) / w as f32,
            ((i as u32 / w) as f32 + 0.5) / h as f32,
        )
    }

    /// `texture` with every texel multiplied by the correction at its centre, each channel
    /// clamped so that texel × `factor` stays within [0, 1]; how many texels a clamp changed;
    /// and the RMS relative change (worst channel) of the albedo the texels pixels saw render,
    /// clamps included.
    pub fn apply(&self, texture: &Texture, factor: Vec3) -> (Texture, usize, f64) {
        let (w, h) = (texture.width, texture.height);
        let ceiling = Vec3::select(factor.cmpgt(Vec3::ZERO), 1.0 / factor, Vec3::INFINITY);
        let (mut clamped, mut sq, mut n) = (0, DVec3::ZERO, 0usize);
        let texels = texture
            .texels
            .iter()
            .enumerate()
            .map(|(i, t)| {
                let uv = Self::texel_uv(i, w, h);
                let v = *t * self.at(uv).as_vec3();
                let c = v.clamp(Vec3::ZERO, ceiling);
                clamped += (c != v) as usize;
                if self.seen_at(uv) {
                    let d = ratio(albedo(c, factor), albedo(*t, factor)) - 1.0;
                    sq += d * d;
                    n += 1;
                }
                c
            })
            .collect();
        let texture = Texture {
            width: w,
            height: h,
            texels,
        };
        let change = if n > 0 {
            (sq / n as f64).max_element().sqrt()
        } else {
            0.0
        };
        (texture, clamped, change)
    }

    /// The least and largest ratio (per channel) of `fitted` to `given`, two versions of one
    /// texture, as rendered with `factor` (clamped to 1), over the texels pixels saw; (1, 1)
    /// when they saw none.
    pub fn ratio_range(&self, given: &Texture, fitted: &Texture, factor: Vec3) -> (f64, f64) {
        let (w, h) = (given.width, given.height);
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for (i, (g, f)) in given.texels.iter().zip(&fitted.texels).enumerate() {
            if self.seen_at(Self::texel_uv(i, w, h)) {
                let r = ratio(albedo(*f, factor), albedo(*g, factor));
                lo = lo.min(r.min_element());
                hi = hi.max(r.max_element());
            }
        }
        if lo <= hi { (lo, hi) } else { (1.0, 1.0) }
    }

    /// The correction divided by `k` per channel.
    pub fn divided(mut self, k: DVec3) -> Correction {
        for c in &mut self.cells {
            *c /= k;
        }
        self
    }

    /// The median and the largest of `sigma` (per cell, as [`TexelSums::sigma`] gives)
    /// relative to the cells, over the cells the pixels see (each cell's worst channel among
    /// those with a correction above 0); `None` when no cell is seen.
    pub fn relative_sigma(&self, sigma: &[DVec3]) -> Option<[f64; 2]> {
        let mut rel: Vec<f64> = (0..self.cells.len())
            .filter(|&a| self.seen[a] > 0.0)
            .map(|a| {
                (0..3)
                    .filter(|&ch| self.cells[a][ch] > 0.0)
                    .map(|ch| sigma[a][ch] / self.cells[a][ch])
                    .fold(0.0f64, f64::max)
            })
            .collect();
        if rel.is_empty() {
            return None;
        }
        rel.sort_by(f64::total_cmp);
        Some([rel[rel.len() / 2], rel[rel.len() - 1]])
    }

    /// Cells pixels see.
    pub fn cells_seen(&self) -> usize {
        self.seen.iter().filter(|&&w| w > 0.0).count()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rng(seed: &mut u64) -> f64 {
        *seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (*seed >> 11) as f64 / (1u64 << 53) as f64
    }

    #[test]
    fn taps_weigh_as_the_texture_samples() {
        let (w, h) = (7u32, 5u32);
        let texels: Vec<Vec3> = (0..w * h)
            .map(|i| Vec3::new(i as f32, (i * i % 11) as f32, 1.0 + (i % 3) as f32))
            .collect();
        let texture = Texture {
            width: w,
            height: h,
            texels: texels.clone(),
        };
        let mut seed = 3;
        for _ in 0..200 {
            let uv = Vec2::new(
                (rng(&mut seed) * 3.0 - 1.0) as f32,
                (rng(&mut seed) * 3.0 - 1.0) as f32,
            );
            let t = taps(uv, w, h).expect("finite");
            let sum: f64 = t.iter().map(|&(_, w)| w).sum();
            assert!((sum - 1.0).abs() < 1e-12);
            let mine: Vec3 = t.iter().map(|&(a, wt)| texels[a] * wt as f32).sum();
            let theirs = texture.sample(uv);
            assert!(
                (mine - theirs).abs().max_element() < 1e-3,
                "{uv}: {mine} against {theirs}"
            );
        }
        assert!(taps(Vec2::new(f32::NAN, 0.0), w, h).is_none());
    }

    #[test]
    fn grid_follows_the_aspect_within_bounds() {
        assert_eq!(grid_size(256, 256, 32), Some((32, 32)));
        assert_eq!(grid_size(512, 256, 32), Some((32, 16)));
        assert_eq!(grid_size(100, 400, 32), Some((8, 32)));
        assert_eq!(grid_size(4096, 16, 32), Some((32, MIN_TEXEL_GRID)));
        assert_eq!(
            grid_size(4096, 4096, 1000),
            Some((MAX_TEXEL_GRID, MAX_TEXEL_GRID))
        );
        // Never finer than the texture; none for a texture narrower than the least grid.
        assert_eq!(grid_size(8, 8, 32), Some((8, 8)));
        assert_eq!(grid_size(1, 1, 32), None);
        assert_eq!(grid_size(64, 2, 32), None);
    }

    /// A known correction on the grid (a darkened blob, one multiplier per cell and channel,
    /// looked up bilinearly), seen by noiseless pixels everywhere but one cell: recovered to
    /// 0.1% with a faint prior, and the cell no pixel sees follows its neighbours.
    #[test]
    fn recovers_a_known_correction() {
        let (w, h) = (16u32, 12u32);
        let blob = |i: u32, j: u32| {
            let d = (i as f64 - 6.0).powi(2) + (j as f64 - 6.5).powi(2);
            let e = (-d / 8.0).exp();
            DVec3::new(1.0 - 0.5 * e, 1.0 - 0.4 * e, 1.0 - 0.3 * e)
        };
        let truth = Correction {
            width: w,
            height: h,
            cells: (0..w * h).map(|a| blob(a % w, a / w)).collect(),
            seen: vec![1.0; (w * h) as usize],
        };
        let mut sums = TexelSums::new((w, h));
        let mut seed = 11;
        for _ in 0..40_000 {
            let uv = Vec2::new(rng(&mut seed) as f32, rng(&mut seed) as f32);
            // No pixel near cell (3, 3)'s centre: none of its taps is taken.
            let cell = Vec2::new(uv.x * w as f32 - 0.5, uv.y * h as f32 - 0.5);
            if (cell - Vec2::new(3.0, 3.0)).abs().max_element() < 1.0 {
                continue;
            }
            let x = Vec3::new(0.2, 0.3, 0.25) * (0.5 + rng(&mut seed) as f32);
            let y = (x.as_dvec3() * truth.at(uv)).as_vec3();
            sums.add(uv, y, x, x);
        }
        let c = sums.solve(1e-4).expect("solved");
        let hole = (3 * w + 3) as usize;
        let worst = (0..(w * h) as usize)
            .filter(|&a| a != hole)
            .map(|a| (c.cells[a] - truth.cells[a]).abs().max_element())
            .fold(0.0f64, f64::max);
        assert!(worst < 1e-3, "worst cell off by {worst}");
        assert_eq!(c.cells_seen(), (w * h) as usize - 1);
        let next = c.cells[hole + 1];
        assert!(
            (c.cells[hole] - next).abs().max_element() < 0.1,
            "{} beside {next}",
            c.cells[hole]
        );
    }

    /// References and both re-renders with noise (its deviation growing with the pixel's
    /// brightness), 200 draws: the stated standard deviation of each cell matches the cells'
    /// scatter over the draws.
    /// With a faint prior every cell does; with a firm one (0.3) the prior bends the blob,
    /// and that misfit in the residuals overstates a few cells.
    #[test]
    fn stated_deviations_match_the_scatter_over_noisy_references() {
        let (w, h) = (6u32, 5u32);
        let n = (w * h) as usize;
        let truth =
            |uv: Vec2| 1.0 - 0.4 * (-(uv - Vec2::new(0.4, 0.5)).length_squared() / 0.05).exp();
        let gauss = |seed: &mut u64| {
            let (u1, u2) = (rng(seed).max(1e-300), rng(seed));
            (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
        };
        let draws = 200;
        for (smoothness, lowest) in [(0.01, 0.7), (0.3, 0.5)] {
            let (mut sum, mut sum2, mut stated) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
            let mut seed = 17;
            for _ in 0..draws {
                // The same pixels every draw (a capture's geometry), new noise.
                let mut at = 99;
                let pixels: Vec<(Vec2, Vec3, Vec3, Vec3)> = (0..3000)
                    .map(|_| {
                        let uv = Vec2::new(rng(&mut at) as f32, rng(&mut at) as f32);
                        let x = 0.2 + 0.6 * rng(&mut at);
                        let y = x * truth(uv) as f64 * (1.0 + 0.1 * gauss(&mut seed));
                        let mut render =
                            || Vec3::splat((x * (1.0 + 0.05 * gauss(&mut seed))) as f32);
                        let (x1, x2) = (render(), render());
                        (uv, Vec3::splat(y as f32), x1, x2)
                    })
                    .collect();
                let mut sums = TexelSums::new((w, h));
                for &(uv, y, x1, x2) in &pixels {
                    sums.add(uv, y, x1, x2);
                }
                let c = sums.solve(smoothness).expect("solved");
                for &(uv, y, x1, x2) in &pixels {
                    sums.add_residual(uv, y, x1, x2, &c);
                }
                let columns = std::cell::Cell::new(0);
                let sigma = sums
                    .sigma(smoothness, &|k| columns.set(columns.get() + k))
                    .expect("measured");
                assert_eq!(columns.get(), 3 * n as u64);
                for a in 0..n {
                    sum[a] += c.cells[a].x;
                    sum2[a] += c.cells[a].x * c.cells[a].x;
                    stated[a] += sigma[a].x / draws as f64;
                }
            }
            let mut ratios: Vec<f64> = (0..n)
                .map(|a| {
                    let mean = sum[a] / draws as f64;
                    let scatter = (sum2[a] / draws as f64 - mean * mean).max(0.0).sqrt();
                    scatter / stated[a]
                })
                .collect();
            ratios.sort_by(f64::total_cmp);
            // 200 draws: a deviation's own scatter is about 5%.
            assert!(
                (0.85..1.15).contains(&ratios[n / 2]) && ratios[0] > lowest && ratios[n - 1] < 1.4,
                "smoothness {smoothness}: scatter over stated, sorted: {ratios:?}"
            );
        }
        // Without a residual seen, the spread is nil: no deviation is claimed from nothing.
        let mut empty = TexelSums::new((w, h));
        empty.add(Vec2::new(0.5, 0.5), Vec3::ONE, Vec3::ONE, Vec3::ONE);
        assert!(
            empty
                .sigma(0.3, &|_| ())
                .unwrap()
                .iter()
                .all(|s| *s == DVec3::ZERO)
        );
    }

    /// Noisy re-renders: the cross product keeps the fit unbiased where the square of one
    /// render would pull it low by x̄²/(x̄²+σ²).
    #[test]
    fn render_noise_does_not_bias_the_correction() {
        let (w, h) = (4u32, 4u32);
        let mut sums = TexelSums::new((w, h));
        let mut squared = TexelSums::new((w, h));
        let mut seed = 5;
        let noisy = |seed: &mut u64| 0.5 * (1.0 + 0.8 * (rng(seed) - 0.5) * 3.4641) as f32;
        for _ in 0..200_000 {
            let uv = Vec2::new(rng(&mut seed) as f32, rng(&mut seed) as f32);
            let (x1, x2) = (Vec3::splat(noisy(&mut seed)), Vec3::splat(noisy(&mut seed)));
            let y = Vec3::splat(0.7 * 0.5);
            sums.add(uv, y, x1, x2);
            squared.add(uv, y, x1, x1);
        }
        let c = sums.solve(0.1).expect("solved");
        let mean = c.cells.iter().map(|c| c.x).sum::<f64>() / c.cells.len() as f64;
        assert!((mean - 0.7).abs() < 0.01, "cross: {mean}");
        let biased = squared.solve(0.1).expect("solved");
        let low = biased.cells.iter().map(|c| c.x).sum::<f64>() / c.cells.len() as f64;
        // x̄ = 0.5, σ = 0.2: the square's fit lands near 0.7·0.25/0.29 = 0.60, not 0.7.
        assert!(low < 0.65, "square: {low}");
    }

    #[test]
    fn apply_clamps_to_the_albedo_bound() {
        let texture = Texture {
            width: 2,
            height: 1,
            texels: vec![Vec3::splat(0.5), Vec3::splat(0.9)],
        };
        let c = Correction {
            width: 4,
            height: 4,
            cells: vec![DVec3::splat(1.5); 16],
            seen: vec![1.0; 16],
        };
        let factor = Vec3::new(1.0, 1.0, 2.0);
        let (t, clamped, change) = c.apply(&texture, factor);
        assert_eq!(clamped, 2);
        assert!(
            (t.texels[0] - Vec3::new(0.75, 0.75, 0.5))
                .abs()
                .max_element()
                < 1e-6
        );
        assert!((t.texels[1] - Vec3::new(1.0, 1.0, 0.5)).abs().max_element() < 1e-6);
        // What the rendered albedo moved, clamps included: red and green ×1.5 and ×1/0.9,
        // blue (at albedo 1 before and after) not at all.
        let want = ((0.5f64.powi(2) + (1.0 / 0.9 - 1.0f64).powi(2)) / 2.0).sqrt();
        assert!((change - want).abs() < 1e-6, "{change}");
        let (lo, hi) = c.ratio_range(&texture, &t, factor);
        assert!(
            (lo - 1.0).abs() < 1e-6 && (hi - 1.5).abs() < 1e-6,
            "{lo} {hi}"
        );
    }
}
