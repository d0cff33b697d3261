//! The transport (the paper's Eq. 4, generalised to any number of bounces): for every pixel and
//! colour channel α, the derivative of the pixel value with respect to each envmap cell's
//! radiance. Light transport is linear in emitted radiance, so `I_α = T_α λ_α` exactly; the
//! one path tracer estimates T by accumulating, per cell, the weight a path delivers.
//!
//! **Streamed.** The solvers need only T's normal equations — TᵀT (cells × cells), Tᵀy and
//! yᵀy per channel — so T is rendered a chunk of tiles at a time and each chunk is reduced to
//! those sums at once; no pixel's row outlives its chunk. Memory depends on the cell count, not
//! on the pixels or views, and the solve never touches a pixel.
//!
//! **Unbiased TᵀT.** A pass renders P independent estimates T_a of the same T ([`Part`]: each
//! its own seed, and its own cell sampling fixed before the pass). T is estimated by their
//! mean. TᵀT is not estimated by the mean's own Gram: a Monte Carlo `T̂ = T + E` has
//! `E[T̂ᵀT̂] = TᵀT + E[EᵀE]`, a positive bias that shrinks the least-squares fit toward zero
//! (errors in variables). Products of different parts carry no such term:
//! `Σ_{a≠b} T_aᵀT_b / (P(P−1))` is unbiased, summed per chunk as `SᵀS − Σ_a T_aᵀT_a` with
//! `S = Σ_a T_a`.
//!
//! Cells are sampled by a part's envmap importance distribution: with a constant map that is
//! in proportion to solid angle (so fine grids are not starved); with an estimate, the paper's
//! sequential Monte Carlo importance.

use faer::linalg::matmul::triangular::{BlockStructure, matmul};
use faer::{Accum, Mat, MatRef};
use glam::{DVec3, Vec3};
use rayon::prelude::*;

use crate::envmap::Envmap;
use crate::imageio::Image;
use crate::render::{Accumulator, Done, Emitter, Lights, RenderSettings, Renderer, Tile, tiles};
use crate::scene::Camera;

/// Which emitters a [`PerEmitterAccumulator`] keeps apart (the envmap's own transport
/// accumulates sparsely, [`CellAccumulator`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EmitterKind {
    /// The sphere lights (the sphere model's transport, [`super::spheres`]).
    Spheres,
    /// The sphere lights, then the envmap's cells (the sphere model with a background).
    SpheresThenCells { spheres: u32 },
}

/// Accumulates one row of a transport per pixel: the weight (per unit radiance) each emitter
/// of one kind delivers; other emitters are ignored.
pub struct PerEmitterAccumulator {
    pub kind: EmitterKind,
    pub count: usize,
}

impl Accumulator for PerEmitterAccumulator {
    type Pixel = Vec<Vec3>;
    fn new_pixel(&self) -> Vec<Vec3> {
        vec![Vec3::ZERO; self.count]
    }
    #[inline]
    fn add(&self, pixel: &mut Vec<Vec3>, emitter: Emitter, weight: Vec3) {
        match (self.kind, emitter) {
            (EmitterKind::Spheres | EmitterKind::SpheresThenCells { .. }, Emitter::Sphere(i)) => {
                pixel[i as usize] += weight
            }
            (EmitterKind::SpheresThenCells { spheres }, Emitter::EnvCell(c)) => {
                pixel[(spheres + c) as usize] += weight
            }
            _ => {}
        }
    }
    fn finish(&self, pixel: &mut Vec<Vec3>, spp: u32) {
        let inv = 1.0 / spp as f32;
        pixel.iter_mut().for_each(|v| *v *= inv);
    }
}

/// Accumulates a pixel's row of the envmap's transport sparsely: the (cell, weight per unit
/// radiance) each path delivers, merged by cell when the pixel is done. A 16-sample part at
/// 25 rings reaches a few dozen of 738 cells; a dense row would be zeroed and scanned whole
/// for each pixel of each part.
pub struct CellAccumulator;

/// A pixel's transport row: (cell, weight per unit radiance), by increasing cell.
pub type CellRow = Vec<(u32, Vec3)>;

impl Accumulator for CellAccumulator {
    type Pixel = CellRow;
    fn new_pixel(&self) -> Self::Pixel {
        Vec::new()
    }
    #[inline]
    fn add(&self, pixel: &mut Self::Pixel, emitter: Emitter, weight: Vec3) {
        if let Emitter::EnvCell(c) = emitter {
            pixel.push((c, weight));
        }
    }
    fn finish(&self, pixel: &mut Self::Pixel, spp: u32) {
        let mut merged = merge_by_cell(std::mem::take(pixel));
        merged.retain(|e| e.1 != Vec3::ZERO);
        let inv = 1.0 / spp as f32;
        merged.iter_mut().for_each(|e| e.1 *= inv);
        *pixel = merged;
    }
}

/// One independent estimate of T within a pass: the envmap whose importance distribution
/// picks cells (its radiance only steers sampling; T does not depend on it) and the render
/// settings (samples, bounces, seed).
#[derive(Clone)]
pub struct Part {
    pub sampling: Envmap,
    pub settings: RenderSettings,
}

/// A transport pass reduced to what the solvers need, per channel, summed over the rows
/// (masked, kept pixels) of every view.
#[derive(Debug, Clone)]
pub struct NormalEquations {
    pub cells: usize,
    /// Pixels summed over.
    pub rows: usize,
    /// Independent estimates of T in the pass.
    pub parts: usize,
    /// `Σ_a T_aᵀT_a`, lower triangle (entry (i, j ≤ i) at `i·cells + j`), the three
    /// channels of an entry together (the sparse updates touch one place for all three).
    own: Vec<DVec3>,
    /// `SᵀS` with `S = Σ_a T_a`, laid out as `own`.
    sum: Vec<DVec3>,
    /// `Sᵀy` per cell.
    sty: Vec<DVec3>,
    /// `yᵀy`.
    yy: DVec3,
}

impl NormalEquations {
    fn new(cells: usize, parts: usize) -> Self {
        NormalEquations {
            cells,
            rows: 0,
            parts,
            own: vec![DVec3::ZERO; cells * cells],
            sum: vec![DVec3::ZERO; cells * cells],
            sty: vec![DVec3::ZERO; cells],
            yy: DVec3::ZERO,
        }
    }

    /// TᵀT of channel `ch`, dense row-major: with two or more parts the unbiased
    /// `Σ_{a≠b} T_aᵀT_b / (P(P−1))`, projected onto the positive semi-definite cone
    /// ([`nearest_psd`]); with one part its own Gram (biased upward by the part's noise).
    pub fn gram(&self, ch: usize) -> Vec<f64> {
        let (n, p) = (self.cells, self.parts as f64);
        let entry = |k: usize| {
            if self.parts < 2 {
                self.own[k][ch]
            } else {
                (self.sum[k][ch] - self.own[k][ch]) / (p * (p - 1.0))
            }
        };
        let mut g = vec![0.0; n * n];
        for i in 0..n {
            for j in 0..=i {
                let v = entry(i * n + j);
                g[i * n + j] = v;
                g[j * n + i] = v;
            }
        }
        if self.parts < 2 { g } else { nearest_psd(g) }
    }

    /// `T̄ᵀy` of channel `ch`, T̄ the mean of the parts.
    pub fn tb(&self, ch: usize) -> Vec<f64> {
        let inv = 1.0 / self.parts as f64;
        self.sty.iter().map(|v| v[ch] * inv).collect()
    }

    /// `yᵀy` of channel `ch`.
    pub fn yy(&self, ch: usize) -> f64 {
        self.yy[ch]
    }

    /// Bytes held.
    pub fn memory_bytes(&self) -> usize {
        Self::memory_needed(self.cells)
    }

    /// Bytes the sums of `cells` cells hold (two Grams and a vector, three channels each).
    pub fn memory_needed(cells: usize) -> usize {
        (2 * cells * cells + cells) * 24
    }

    /// Adds a chunk of rows of channel `ch` by dense products: per part, a `rows × cells`
    /// matrix; `y` the rows' values.
    fn add_dense(&mut self, ch: usize, parts: &[MatRef<f64>], y: &[f64]) {
        let n = self.cells;
        let par = faer::get_global_parallelism();
        let lower = |dst: &mut Mat<f64>, accum: Accum, a: MatRef<f64>| {
            matmul(
                dst.as_mut(),
                BlockStructure::TriangularLower,
                accum,
                a.transpose(),
                BlockStructure::Rectangular,
                a,
                BlockStructure::Rectangular,
                1.0,
                par,
            )
        };
        let mut own = Mat::<f64>::zeros(n, n);
        for a in parts {
            lower(&mut own, Accum::Add, *a);
        }
        let mut s = parts[0].to_owned();
        for a in &parts[1..] {
            s += a;
        }
        let mut sum = Mat::<f64>::zeros(n, n);
        if parts.len() > 1 {
            lower(&mut sum, Accum::Replace, s.as_ref());
        }
        for i in 0..n {
            for j in 0..=i {
                self.own[i * n + j][ch] += own[(i, j)];
                self.sum[i * n + j][ch] += sum[(i, j)];
            }
        }
        let yv = MatRef::from_column_major_slice(y, y.len(), 1);
        let sty = s.transpose() * yv;
        for (j, v) in self.sty.iter_mut().enumerate() {
            v[ch] += sty[(j, 0)];
        }
        self.yy[ch] += y.iter().map(|v| v * v).sum::<f64>();
    }

    /// Adds a chunk of rows by sparse products, all three channels at once: `rows[r]` is row
    /// r's non-zero entries `(cell, weight)` per part (by increasing cell) and, last, of their
    /// sum; `y[r]` its values. The lower triangles are cut into fixed blocks of Gram rows,
    /// updated in parallel, each row's entries in row order: the sums do not depend on the
    /// thread count.
    fn add_sparse(&mut self, rows: &[Vec<Sparse>], y: &[DVec3]) {
        let n = self.cells;
        // Block boundaries at equal shares of the triangle's area.
        const BLOCKS: usize = 16;
        let edges: Vec<usize> = (0..=BLOCKS)
            .map(|b| ((n as f64) * (b as f64 / BLOCKS as f64).sqrt()).round() as usize)
            .collect();
        let mut own_blocks: Vec<&mut [DVec3]> = Vec::with_capacity(BLOCKS);
        let mut sum_blocks: Vec<&mut [DVec3]> = Vec::with_capacity(BLOCKS);
        let (mut own_rest, mut sum_rest) = (&mut self.own[..], &mut self.sum[..]);
        for w in edges.windows(2) {
            let len = (w[1] - w[0]) * n;
            let (a, b) = own_rest.split_at_mut(len);
            own_blocks.push(a);
            own_rest = b;
            let (a, b) = sum_rest.split_at_mut(len);
            sum_blocks.push(a);
            sum_rest = b;
        }
        let parts = self.parts;
        own_blocks
            .into_par_iter()
            .zip(sum_blocks)
            .zip(edges.par_windows(2))
            .for_each(|((own, sum), w)| {
                let (lo, hi) = (w[0] as u32, w[1] as u32);
                for lists in rows {
                    for (k, list) in lists.iter().enumerate() {
                        // The parts' own products, then the sum's (one part: no sum).
                        let dst: &mut [DVec3] = if k < parts {
                            &mut *own
                        } else if parts > 1 {
                            &mut *sum
                        } else {
                            continue;
                        };
                        for (a, &(i, wi)) in list.iter().enumerate() {
                            if i < lo {
                                continue;
                            }
                            if i >= hi {
                                break;
                            }
                            let row = &mut dst[(i - lo) as usize * n..];
                            for &(j, wj) in &list[..=a] {
                                row[j as usize] += wi * wj;
                            }
                        }
                    }
                }
            });
        for (lists, y) in rows.iter().zip(y) {
            for &(i, w) in lists.last().expect("the sum's list") {
                self.sty[i as usize] += w * *y;
            }
            self.yy += *y * *y;
        }
    }
}

/// A row's non-zero entries `(cell, RGB weight)`, by increasing cell.
type Sparse = Vec<(u32, DVec3)>;

/// A tile of a view: (view index, tile).
type ViewTile = (usize, Tile);

/// Bytes a chunk of rendered rows may take (every part's f32 rows, one channel's f64 copies):
/// big enough for efficient matrix products, small beside any image.
const CHUNK_BYTES: usize = 16 << 20;

/// Tiles rendered and reduced together: a function of the cell and part counts only, so the
/// sums (and the fit) do not depend on the thread count.
fn tiles_per_chunk(cells: usize, parts: usize) -> usize {
    let px = (crate::render::TILE * crate::render::TILE) as usize;
    let per_tile = px * cells * (12 * parts + 8 * (parts + 1));
    (CHUNK_BYTES / per_tile.max(1)).clamp(16, 4096)
}

/// Bytes [`accumulate`] and the solve after it need at most for `cells` cells and `parts`
/// parts: the sums, one chunk (rendered rows, sparse at up to 16 bytes an entry or dense, and
/// their f64 copies), the products' scratch, and the solve's dense Gram, its regularised copy
/// and the positive semi-definite projection's eigenvectors (about 5 cells² f64).
pub fn memory_needed(cells: usize, parts: usize) -> usize {
    let px = (crate::render::TILE * crate::render::TILE) as usize;
    let chunk = tiles_per_chunk(cells, parts) * px * cells * (16 * parts + 8 * (parts + 1));
    NormalEquations::memory_needed(cells) + chunk + 2 * cells * cells * 8 + 5 * cells * cells * 8
}

/// Renders the transport of `parts` over the pixels of each camera that its mask holds and
/// `keep((view, pixel))` accepts, and reduces it to its [`NormalEquations`] against the
/// references' values, chunk by chunk. Tiles without such a pixel are not rendered.
/// `progress` is called with the rendered pixels of each tile and part: [`progress_units`]
/// in all.
#[allow(clippy::too_many_arguments)]
pub fn accumulate(
    renderer: &Renderer,
    cameras: &[&Camera],
    masks: &[Vec<bool>],
    keep: &(dyn Fn((usize, u32)) -> bool + Sync),
    references: &[Image],
    parts: &[Part],
    stream_base: u64,
    progress: &(dyn Fn(u64) + Sync),
) -> NormalEquations {
    let cells = parts[0].sampling.grid.cell_count();
    let mut out = NormalEquations::new(cells, parts.len());
    let lights: Vec<Lights> = parts
        .iter()
        .map(|p| Lights::env(p.sampling.clone()))
        .collect();
    let renderers: Vec<Renderer> = lights.iter().map(|l| renderer.with_lights(l)).collect();
    let acc = CellAccumulator;
    let counts = |(v, i): (usize, u32)| masks[v][i as usize] && keep((v, i));
    // (view, tile) pairs with a pixel to render, and how many.
    let work: Vec<(ViewTile, u64)> = cameras
        .iter()
        .enumerate()
        .flat_map(|(v, cam)| {
            tiles(cam.width, cam.height)
                .into_iter()
                .map(move |t| (v, t))
        })
        .map(|(v, (x0, y0, x1, y1))| {
            let w = cameras[v].width;
            let n = (y0..y1)
                .flat_map(|y| (x0..x1).map(move |x| y * w + x))
                .filter(|&i| counts((v, i)))
                .count();
            ((v, (x0, y0, x1, y1)), n as u64)
        })
        .filter(|&(_, n)| n > 0)
        .collect();
    for chunk in work.chunks(tiles_per_chunk(cells, parts.len())) {
        // Per tile, per part: the tile's pixels.
        let rendered: Vec<Vec<Vec<Done<CellRow>>>> = chunk
            .par_iter()
            .map(|&((v, tile), wanted)| {
                let wanted_pixel = |i| counts((v, i));
                renderers
                    .iter()
                    .zip(parts)
                    .map(|(r, part)| {
                        let px = r.render_tile(
                            cameras[v],
                            stream_base + v as u64,
                            &part.settings,
                            &acc,
                            tile,
                            Some(&wanted_pixel),
                        );
                        progress(wanted);
                        px
                    })
                    .collect()
            })
            .collect();
        // The kept rows, in tile order: (view, index within the tile).
        let rows: Vec<(usize, usize, usize)> = chunk
            .iter()
            .zip(&rendered)
            .enumerate()
            .flat_map(|(t, (&((v, _), _), per_part))| {
                per_part[0]
                    .iter()
                    .enumerate()
                    .filter(move |(_, (index, _, _))| counts((v, *index)))
                    .map(move |(k, _)| (t, v, k))
            })
            .collect();
        out.rows += rows.len();
        let y: Vec<DVec3> = rows
            .iter()
            .map(|&(t, v, k)| {
                let index = rendered[t][0][k].0 as usize;
                references[v].rgb[index].as_dvec3()
            })
            .collect();
        // Pairs a sparse update would visit (three channels each; the sum's non-zeros taken
        // as the parts' together), against the dense products' multiply-adds (per channel,
        // lower triangles): a scattered update costs about SPARSE_COST of a dense one's.
        // Bundled scene, 320×240, 64 spp: at 9 rings the dense products are faster (2.4 s
        // against 2.9 s of transport), at 25 rings the sparse updates (3.5 s against 17 s).
        const SPARSE_COST: usize = 16;
        let pairs: usize = rows
            .par_iter()
            .map(|&(t, _, k)| {
                let nnz: Vec<usize> = rendered[t].iter().map(|part| part[k].1.len()).collect();
                let all = nnz.iter().sum::<usize>().min(cells);
                nnz.iter()
                    .chain([&all])
                    .map(|k| k * (k + 1) / 2)
                    .sum::<usize>()
            })
            .sum();
        let dense = 3 * rows.len() * cells * (cells + 1) / 2 * (parts.len() + 1);
        if pairs * SPARSE_COST < dense {
            // Each row's non-zero entries per part and of their sum, by increasing cell.
            let lists: Vec<Vec<Sparse>> = rows
                .par_iter()
                .map(|&(t, _, k)| {
                    let mut lists: Vec<Sparse> = rendered[t]
                        .iter()
                        .map(|part| part[k].1.iter().map(|&(c, w)| (c, w.as_dvec3())).collect())
                        .collect();
                    lists.push(sum_of(&lists));
                    lists
                })
                .collect();
            out.add_sparse(&lists, &y);
            continue;
        }
        let m = rows.len();
        for ch in 0..3 {
            // Row-major copies (each pixel's row is contiguous where it was rendered).
            let mut mats: Vec<Vec<f64>> = vec![vec![0.0; m * cells]; parts.len()];
            for (r, &(t, _, k)) in rows.iter().enumerate() {
                for (a, mat) in mats.iter_mut().enumerate() {
                    for &(c, w) in &rendered[t][a][k].1 {
                        mat[r * cells + c as usize] = w[ch] as f64;
                    }
                }
            }
            let mats: Vec<MatRef<f64>> = mats
                .iter()
                .map(|d| MatRef::from_row_major_slice(d, m, cells))
                .collect();
            let ych: Vec<f64> = y.iter().map(|v| v[ch]).collect();
            out.add_dense(ch, &mats, &ych);
        }
    }
    out
}

/// What [`accumulate`] reports to its progress: the pixels it renders, once per part.
pub fn progress_units(
    masks: &[Vec<bool>],
    keep: &dyn Fn((usize, u32)) -> bool,
    parts: usize,
) -> u64 {
    let kept: usize = masks
        .iter()
        .enumerate()
        .map(|(v, m)| {
            m.iter()
                .enumerate()
                .filter(|&(i, &b)| b && keep((v, i as u32)))
                .count()
        })
        .sum();
    kept as u64 * parts as u64
}

/// The sum of sparse rows, by increasing cell.
fn sum_of(lists: &[Sparse]) -> Sparse {
    merge_by_cell(lists.iter().flatten().copied().collect())
}

/// (cell, weight) entries summed by cell, by increasing cell; a cell's weights are summed in
/// the order given (the sort is stable), so sums do not depend on how they were gathered.
fn merge_by_cell<T: Copy + std::ops::AddAssign>(mut entries: Vec<(u32, T)>) -> Vec<(u32, T)> {
    entries.sort_by_key(|e| e.0);
    let mut out: Vec<(u32, T)> = Vec::with_capacity(entries.len());
    for (c, w) in entries {
        match out.last_mut() {
            Some(last) if last.0 == c => last.1 += w,
            _ => out.push((c, w)),
        }
    }
    out
}

/// The nearest (Frobenius) positive semi-definite matrix to the symmetric `g`: negative
/// eigenvalues clipped to zero; returned unchanged when already positive semi-definite. A
/// cross-product Gram can lose definiteness where the views barely see a cell, and NNLS on an
/// indefinite G would be neither convex nor exact.
pub fn nearest_psd(mut g: Vec<f64>) -> Vec<f64> {
    let n = (g.len() as f64).sqrt() as usize;
    let m = Mat::<f64>::from_fn(n, n, |i, j| 0.5 * (g[i * n + j] + g[j * n + i]));
    let Ok(eig) = m.self_adjoint_eigen(faer::Side::Lower) else {
        return g;
    };
    let s = eig.S().column_vector();
    if (0..n).all(|i| s[i] >= 0.0) {
        return g;
    }
    let u = eig.U();
    let clipped = Mat::<f64>::from_fn(n, n, |i, j| u[(i, j)] * s[j].max(0.0));
    let psd = &clipped * u.transpose();
    for (k, v) in g.iter_mut().enumerate() {
        *v = psd[(k / n, k % n)];
    }
    g
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimate::nnls;
    use crate::sampling::Rng;
    use std::time::Duration;

    /// Normal equations of `parts` (each rows × cells, one channel copied to all three) and
    /// `y`, added in chunks of `chunk` rows.
    fn sums(parts: &[Vec<f64>], cells: usize, y: &[f64], chunk: usize) -> NormalEquations {
        let rows = y.len();
        let mut ne = NormalEquations::new(cells, parts.len());
        for start in (0..rows).step_by(chunk) {
            let end = (start + chunk).min(rows);
            let mats: Vec<MatRef<f64>> = parts
                .iter()
                .map(|t| {
                    MatRef::from_row_major_slice(&t[start * cells..end * cells], end - start, cells)
                })
                .collect();
            for ch in 0..3 {
                ne.add_dense(ch, &mats, &y[start..end]);
            }
            ne.rows += end - start;
        }
        ne
    }

    /// `Σ_{a≠b} T_aᵀT_b / (P(P−1))` of channel `ch` before the PSD projection, full.
    fn raw_cross(ne: &NormalEquations, ch: usize) -> Vec<f64> {
        let (n, p) = (ne.cells, ne.parts as f64);
        (0..n * n)
            .map(|k| {
                let (i, j) = (k / n, k % n);
                let e = i.max(j) * n + i.min(j);
                (ne.sum[e][ch] - ne.own[e][ch]) / (p * (p - 1.0))
            })
            .collect()
    }

    #[test]
    fn sparse_and_dense_updates_give_the_same_sums() {
        // Three parts of mostly-zero rows, channels scaled differently; the same rows in
        // two chunks by each path.
        let (rows, cells, parts) = (50, 12, 3);
        let mut rng = Rng::new(11);
        let t: Vec<Vec<f64>> = (0..parts)
            .map(|_| {
                (0..rows * cells)
                    .map(|_| {
                        let v = rng.next_f32() as f64;
                        if v < 0.7 { 0.0 } else { v }
                    })
                    .collect()
            })
            .collect();
        let y: Vec<DVec3> = (0..rows)
            .map(|_| DVec3::new(rng.next_f32() as f64, 2.0, -(rng.next_f32() as f64)))
            .collect();
        let scale = [1.0, 0.5, 3.0];
        let mut dense = NormalEquations::new(cells, parts);
        let mut sparse = NormalEquations::new(cells, parts);
        for (start, end) in [(0, 20), (20, rows)] {
            for ch in 0..3 {
                let scaled: Vec<Vec<f64>> = t
                    .iter()
                    .map(|p| {
                        p[start * cells..end * cells]
                            .iter()
                            .map(|v| v * scale[ch])
                            .collect()
                    })
                    .collect();
                let mats: Vec<MatRef<f64>> = scaled
                    .iter()
                    .map(|d| MatRef::from_row_major_slice(d, end - start, cells))
                    .collect();
                let ych: Vec<f64> = y[start..end].iter().map(|v| v[ch]).collect();
                dense.add_dense(ch, &mats, &ych);
            }
            let lists: Vec<Vec<Sparse>> = (start..end)
                .map(|r| {
                    let mut l: Vec<Sparse> = t
                        .iter()
                        .map(|p| {
                            (0..cells)
                                .filter(|&c| p[r * cells + c] != 0.0)
                                .map(|c| {
                                    let v = p[r * cells + c];
                                    (c as u32, DVec3::from_array(scale) * v)
                                })
                                .collect()
                        })
                        .collect();
                    l.push(sum_of(&l));
                    l
                })
                .collect();
            sparse.add_sparse(&lists, &y[start..end]);
        }
        let close = |a: &[f64], b: &[f64]| {
            a.iter()
                .zip(b)
                .all(|(x, y)| (x - y).abs() <= 1e-12 * (1.0 + x.abs()))
        };
        for ch in 0..3 {
            assert!(
                close(&raw_cross(&dense, ch), &raw_cross(&sparse, ch)),
                "channel {ch}"
            );
            assert!(close(&dense.tb(ch), &sparse.tb(ch)), "channel {ch}");
            assert!((dense.yy(ch) - sparse.yy(ch)).abs() < 1e-9, "channel {ch}");
            let own = |ne: &NormalEquations| -> Vec<f64> { ne.own.iter().map(|e| e[ch]).collect() };
            assert!(close(&own(&dense), &own(&sparse)), "channel {ch}");
        }
        // Not all zero, or the comparison proves nothing.
        assert!(raw_cross(&dense, 0).iter().any(|v| *v > 0.1));
    }

    #[test]
    fn cross_products_of_parts_remove_the_shrinkage_of_noisy_transports() {
        // y = Tλ exactly; three parts estimate T with independent zero-mean noise, part 2
        // with a quarter of part 1's variance on the last two cells (as if it sampled them 4×
        // more). Least squares on the mean transport's own Gram shrinks λ
        // (E[T̂ᵀT̂] = TᵀT + E[EᵀE]); on the parts' cross Gram it does not.
        let (m, n) = (4000, 4);
        let truth = [1.0, 2.0, 3.0, 4.0];
        let mut rng = Rng::new(7);
        let t: Vec<f64> = (0..m * n).map(|_| rng.next_f32() as f64).collect();
        let y: Vec<f64> = t
            .chunks_exact(n)
            .map(|row| row.iter().zip(&truth).map(|(a, b)| a * b).sum())
            .collect();
        let trials = 40;
        let (mut plain, mut cross) = (vec![0.0; n], vec![0.0; n]);
        for _ in 0..trials {
            let mut noisy = |scale: [f64; 4]| -> Vec<f64> {
                t.iter()
                    .enumerate()
                    .map(|(k, &x)| x + scale[k % n] * 0.8 * (rng.next_f32() as f64 - 0.5))
                    .collect()
            };
            let parts = [
                noisy([1.0; 4]),
                noisy([1.0, 1.0, 0.5, 0.5]),
                noisy([1.0; 4]),
            ];
            let ne = sums(&parts, n, &y, 1000);
            // The mean transport as one part: its own Gram.
            let mean: Vec<f64> = (0..m * n)
                .map(|k| parts.iter().map(|p| p[k]).sum::<f64>() / 3.0)
                .collect();
            let single = sums(std::slice::from_ref(&mean), n, &y, 1000);
            for (g, sum) in [(single.gram(0), &mut plain), (ne.gram(0), &mut cross)] {
                let x = nnls::nnls(&g, &ne.tb(0), 1e-12, 1000, Duration::from_secs(10)).x;
                sum.iter_mut()
                    .zip(&x)
                    .for_each(|(s, x)| *s += x / trials as f64);
            }
        }
        // The noise acts as a ridge on TᵀT, whose small eigenvalues (the differences between
        // these correlated columns) it shrinks most: the extreme cells are pulled together.
        let worst = |x: &[f64]| -> f64 {
            x.iter()
                .zip(&truth)
                .map(|(x, t)| (x / t - 1.0).abs())
                .fold(0.0, f64::max)
        };
        // Measured: plain 8.2% off at worst, cross 1.0% (what is left is the second-order
        // bias of a ratio of noisy sums, which falls with the number of rows).
        assert!(worst(&plain) > 0.05, "plain {plain:?}");
        assert!(worst(&cross) < 0.025, "cross {cross:?}");
    }

    #[test]
    fn the_sums_are_the_mean_transport_and_the_mean_cross_product_in_any_chunking() {
        // Two rows, two cells, three parts: by hand.
        let parts = [
            vec![1.0, 2.0, 0.5, 0.0],
            vec![3.0, 2.0, 1.0, 4.0],
            vec![5.0, 8.0, 0.0, 2.0],
        ];
        let y = [2.0, -1.0];
        let want_cross: Vec<f64> = (0..4)
            .map(|k| {
                let (i, j) = (k / 2, k % 2);
                let mut s = 0.0;
                for a in 0..3 {
                    for b in (0..3).filter(|&b| b != a) {
                        for r in 0..2 {
                            s += parts[a][r * 2 + i] * parts[b][r * 2 + j];
                        }
                    }
                }
                s / 6.0
            })
            .collect();
        let want_tb: Vec<f64> = (0..2)
            .map(|j| {
                (0..2)
                    .map(|r| parts.iter().map(|p| p[r * 2 + j]).sum::<f64>() / 3.0 * y[r])
                    .sum()
            })
            .collect();
        for chunk in [1, 2] {
            let ne = sums(&parts, 2, &y, chunk);
            assert_eq!(ne.rows, 2);
            let raw = raw_cross(&ne, 0);
            for (a, b) in raw.iter().zip(&want_cross) {
                assert!(
                    (a - b).abs() < 1e-12,
                    "chunk {chunk}: {raw:?} vs {want_cross:?}"
                );
            }
            for (a, b) in ne.tb(0).iter().zip(&want_tb) {
                assert!((a - b).abs() < 1e-12, "{a} vs {b}");
            }
            assert_eq!(ne.yy(0), 5.0);
            for (a, b) in ne.gram(0).iter().zip(nearest_psd(raw.clone())) {
                assert!((a - b).abs() < 1e-12, "{a} vs {b}");
            }
        }
        // One part: its own Gram.
        let one = sums(&parts[..1], 2, &y, 2);
        let own = [1.0 + 0.25, 2.0, 2.0, 4.0];
        assert_eq!(one.gram(0), own);
    }

    #[test]
    fn nearest_psd_clips_negative_eigenvalues_and_keeps_psd_matrices() {
        // Eigenvalues 3 and −1 (eigenvectors (1, 1)/√2, (1, −1)/√2) → 3 only: 1.5·[[1, 1], [1, 1]].
        let g = nearest_psd(vec![1.0, 2.0, 2.0, 1.0]);
        for (a, b) in g.iter().zip([1.5, 1.5, 1.5, 1.5]) {
            assert!((a - b).abs() < 1e-12, "{g:?}");
        }
        let spd = vec![2.0, 0.5, 0.5, 1.0];
        assert_eq!(nearest_psd(spd.clone()), spd);
    }
}
