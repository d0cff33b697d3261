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

use crate::envmap::grid::azimuth;
use crate::envmap::{Envmap, RingGrid};
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
    /// Sphere light `j` alone, in the row's one column.
    Sphere(u32),
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
    fn add(&self, pixel: &mut Vec<Vec3>, emitter: Emitter, _: Vec3, weight: Vec3) {
        match (self.kind, emitter) {
            (EmitterKind::Spheres | EmitterKind::SpheresThenCells { .. }, Emitter::Sphere(i)) => {
                pixel[i as usize] += weight
            }
            (EmitterKind::SpheresThenCells { spheres }, Emitter::EnvCell(c)) => {
                pixel[(spheres + c) as usize] += weight
            }
            (EmitterKind::Sphere(j), Emitter::Sphere(i)) if i == j => pixel[0] += weight,
            _ => {}
        }
    }
    fn finish(&self, pixel: &mut Vec<Vec3>, spp: u32) {
        let inv = 1.0 / spp as f32;
        pixel.iter_mut().for_each(|v| *v *= inv);
    }
    /// No row: a render of a few pixels of a large view allocates nothing for the others
    /// (callers read only the pixels they asked for).
    fn left_out(&self) -> Vec<Vec3> {
        Vec::new()
    }
}

/// Accumulates a pixel's transport rows sparsely, one per target grid: the (cell, weight per
/// unit radiance) each path delivers, merged by cell when the pixel is done. A 16-sample part
/// at 25 rings reaches a few dozen of 738 cells; a dense row would be zeroed and scanned whole
/// for each pixel of each part.
///
/// A grid with the sampling grid's ring count takes the emitter's own cell (a direction
/// sampled in a cell looks up to that cell); any other grid bins the direction. Each grid's
/// row is an unbiased transport of that grid whatever grid sampled it: a path's weight is
/// its contribution over its pdf, and the integral over a cell is the same sum restricted to
/// the directions in it.
pub struct CellAccumulator<'a> {
    pub grids: &'a [RingGrid],
    /// Ring count of the grid whose cells the emitters are (the parts' sampling envmap).
    pub sampling_rings: u32,
    /// Deliveries a pixel is expected to make (room reserved once, not grown sample by
    /// sample).
    pub expected: usize,
}

/// A pixel's transport row: (cell, weight per unit radiance), by increasing cell.
pub type CellRow = Vec<(u32, Vec3)>;

/// A pixel being accumulated by [`CellAccumulator`]: what its paths delivered, then (once
/// finished) its row in each grid.
pub struct CellPixel {
    /// (the sampling grid's cell, unit direction, weight) per delivery.
    delivered: Vec<(u32, Vec3, Vec3)>,
    /// Per grid, the row.
    pub rows: Vec<CellRow>,
}

impl Accumulator for CellAccumulator<'_> {
    type Pixel = CellPixel;
    fn new_pixel(&self) -> Self::Pixel {
        CellPixel {
            delivered: Vec::with_capacity(self.expected),
            rows: Vec::new(),
        }
    }
    /// Nothing reserved, no rows: [`accumulate`] reads only the pixels it asked for.
    fn left_out(&self) -> Self::Pixel {
        CellPixel {
            delivered: Vec::new(),
            rows: Vec::new(),
        }
    }
    #[inline]
    fn add(&self, pixel: &mut Self::Pixel, emitter: Emitter, dir: Vec3, weight: Vec3) {
        if let Emitter::EnvCell(c) = emitter {
            pixel.delivered.push((c, dir, weight));
        }
    }
    fn finish(&self, pixel: &mut Self::Pixel, spp: u32) {
        let inv = 1.0 / spp as f32;
        let delivered = std::mem::take(&mut pixel.delivered);
        // One inverse cosine and one arctangent per delivery, shared by the grids that bin.
        let polar: Vec<(f64, f64, f64)> =
            if self.grids.iter().any(|g| g.rings() != self.sampling_rings) {
                delivered
                    .iter()
                    .map(|&(_, d, _)| {
                        let y = d.y as f64;
                        (y, y.clamp(-1.0, 1.0).acos(), azimuth(d))
                    })
                    .collect()
            } else {
                Vec::new()
            };
        pixel.rows = self
            .grids
            .iter()
            .map(|g| {
                if g.rings() == self.sampling_rings {
                    merge_by_cell_dense(delivered.iter().map(|&(c, _, w)| (c, w)), g, inv)
                } else {
                    let binned = delivered
                        .iter()
                        .zip(&polar)
                        .map(|(&(_, _, w), &(y, t, p))| (g.lookup_polar(y, t, p), w));
                    merge_by_cell_dense(binned, g, inv)
                }
            })
            .collect();
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
    /// `Σ_{a≠b} T_aᵀT_b` over ordered pairs of different parts (with one part, its own
    /// `T_aᵀT_a`): packed lower triangle (entry (i, j ≤ i) at [`tri`]`(i) + j`), the three
    /// channels of an entry together (the sparse updates touch one place for all three).
    cross: Vec<DVec3>,
    /// `Sᵀy` per cell, `S = Σ_a T_a`.
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
            cross: vec![DVec3::ZERO; tri(cells)],
            sty: vec![DVec3::ZERO; cells],
            yy: DVec3::ZERO,
        }
    }

    /// TᵀT of channel `ch`, dense row-major: with two or more parts the unbiased
    /// `Σ_{a≠b} T_aᵀT_b / (P(P−1))`, projected onto the positive semi-definite cone
    /// ([`nearest_psd`]); with one part its own Gram (biased upward by the part's noise).
    pub fn gram(&self, ch: usize) -> Vec<f64> {
        let (n, p) = (self.cells, self.parts as f64);
        let scale = if self.parts < 2 {
            1.0
        } else {
            1.0 / (p * (p - 1.0))
        };
        let entry = |k: usize| self.cross[k][ch] * scale;
        let mut g = vec![0.0; n * n];
        for i in 0..n {
            for j in 0..=i {
                let v = entry(tri(i) + j);
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

    /// Bytes the sums of `cells` cells hold (a packed triangle and a vector, three channels
    /// each).
    pub fn memory_needed(cells: usize) -> usize {
        (tri(cells) + cells) * 24
    }

    /// Adds the sums of `other`, rendered by the same parts over other pixels.
    pub fn add(&mut self, other: &NormalEquations) {
        assert_eq!((self.cells, self.parts), (other.cells, other.parts));
        self.rows += other.rows;
        for (a, b) in self.cross.iter_mut().zip(&other.cross) {
            *a += *b;
        }
        for (a, b) in self.sty.iter_mut().zip(&other.sty) {
            *a += *b;
        }
        self.yy += other.yy;
    }

    /// These sums without `part` (sums of the same parts over some of these pixels).
    pub fn without(&self, part: &NormalEquations) -> NormalEquations {
        assert_eq!((self.cells, self.parts), (part.cells, part.parts));
        let mut out = self.clone();
        out.rows -= part.rows;
        for (a, b) in out.cross.iter_mut().zip(&part.cross) {
            *a -= *b;
        }
        for (a, b) in out.sty.iter_mut().zip(&part.sty) {
            *a -= *b;
        }
        out.yy -= part.yy;
        out
    }

    /// Adds a chunk of rendered rows: `row(r, a)` is row r's transport in part a, `y[r]` its
    /// value. By dense products or sparse updates, whichever visits fewer entries.
    fn add_rows<'r>(&mut self, y: &[DVec3], row: impl Fn(usize, usize) -> &'r CellRow + Sync) {
        let (m, cells, parts) = (y.len(), self.cells, self.parts);
        self.rows += m;
        // Pairs a sparse update visits (three channels each), against the dense products'
        // multiply-adds (per channel, lower triangles of each part's and of their sum's
        // Gram): a scattered update costs about SPARSE_COST of a dense one's. Bundled scene,
        // 320×240, 64 spp: at 9 rings the dense products are faster (2.4 s against 2.9 s of
        // transport), at 25 rings the sparse updates (3.5 s against 17 s).
        const SPARSE_COST: usize = 16;
        let pairs: usize = (0..m)
            .into_par_iter()
            .map(|r| {
                let nnz: Vec<usize> = (0..parts).map(|a| row(r, a).len()).collect();
                let sum = nnz.iter().sum::<usize>().min(cells);
                SparseRow::cost(&nnz, sum).0
            })
            .sum();
        let dense = 3 * m * cells * (cells + 1) / 2 * (parts + 1);
        if pairs * SPARSE_COST < dense {
            let lists: Vec<SparseRow> = (0..m)
                .into_par_iter()
                .map(|r| SparseRow::new((0..parts).map(|a| row(r, a)), cells))
                .collect();
            self.add_sparse(&lists, y);
            return;
        }
        for ch in 0..3 {
            // Row-major copies (each pixel's row is contiguous where it was rendered).
            let mut mats: Vec<Vec<f64>> = vec![vec![0.0; m * cells]; parts];
            for r in 0..m {
                for (a, mat) in mats.iter_mut().enumerate() {
                    for &(c, w) in row(r, a) {
                        mat[r * cells + c as usize] = w[ch] as f64;
                    }
                }
            }
            let mats: Vec<MatRef<f64>> = mats
                .iter()
                .map(|d| MatRef::from_row_major_slice(d, m, cells))
                .collect();
            let ych: Vec<f64> = y.iter().map(|v| v[ch]).collect();
            self.add_dense(ch, &mats, &ych);
        }
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
                self.cross[tri(i) + j][ch] += if parts.len() > 1 {
                    sum[(i, j)] - own[(i, j)]
                } else {
                    own[(i, j)]
                };
            }
        }
        let yv = MatRef::from_column_major_slice(y, y.len(), 1);
        let sty = s.transpose() * yv;
        for (j, v) in self.sty.iter_mut().enumerate() {
            v[ch] += sty[(j, 0)];
        }
        self.yy[ch] += y.iter().map(|v| v * v).sum::<f64>();
    }

    /// Adds a chunk of rows by sparse products, all three channels at once ([`SparseRow`]);
    /// `y[r]` is row r's value. The lower triangle is cut into fixed blocks of Gram rows,
    /// updated in parallel, each row's entries in row order: the sums do not depend on the
    /// thread count.
    fn add_sparse(&mut self, rows: &[SparseRow], y: &[DVec3]) {
        let edges = block_edges(self.cells);
        let mut blocks: Vec<&mut [DVec3]> = Vec::with_capacity(BLOCKS);
        let mut rest = &mut self.cross[..];
        for w in edges.windows(2) {
            let (a, b) = rest.split_at_mut(tri(w[1]) - tri(w[0]));
            blocks.push(a);
            rest = b;
        }
        let one_part = self.parts < 2;
        blocks.into_par_iter().enumerate().for_each(|(block, dst)| {
            let base = tri(edges[block]);
            // Adds sign × la ⊗ lb to the block's rows (entries at or left of the diagonal).
            let mut outer = |(la, sa): Blocked, (lb, sb): Blocked, sign: f64| {
                // lb[..end]: the entries at or left of the diagonal of row i.
                let mut end = sb[block] as usize;
                for &(i, wi) in &la[sa[block] as usize..sa[block + 1] as usize] {
                    while end < lb.len() && lb[end].0 <= i {
                        end += 1;
                    }
                    let row = &mut dst[tri(i as usize) - base..];
                    let wi = wi * sign;
                    for &(j, wj) in &lb[..end] {
                        row[j as usize] += wi * wj;
                    }
                }
            };
            for r in rows {
                match r.sum() {
                    // SᵀS − Σ_a T_aᵀT_a.
                    Some(sum) => {
                        outer(sum, sum, 1.0);
                        for a in 0..r.parts.len() {
                            outer(r.part(a), r.part(a), -1.0);
                        }
                    }
                    None if one_part => outer(r.part(0), r.part(0), 1.0),
                    None => {
                        for a in 0..r.parts.len() {
                            for b in 0..r.parts.len() {
                                if a != b {
                                    outer(r.part(a), r.part(b), 1.0);
                                }
                            }
                        }
                    }
                }
            }
        });
        for (r, y) in rows.iter().zip(y) {
            for &(i, w) in r.parts.iter().flatten() {
                self.sty[i as usize] += w * *y;
            }
            self.yy += *y * *y;
        }
    }
}

/// A row's non-zero entries per part, and, where that is the cheaper way to the cross
/// products, of their sum S. The cross products `Σ_{a≠b} T_aᵀT_b` are summed directly where
/// the parts reach different cells (as at fine grids, sampled by solid angle), and as
/// `SᵀS − Σ_a T_aᵀT_a` where they share most (as where all parts' sampling favours the
/// same bright cells): whichever visits fewer pairs.
struct SparseRow {
    parts: Vec<Sparse>,
    sum: Option<Sparse>,
    /// Per part, then of the sum: where each Gram block's cells ([`block_edges`]) begin
    /// among its entries (the last, its length). Found once per row, not once per block.
    starts: Vec<BlockStarts>,
}

/// Index of the first entry of each of the [`BLOCKS`] Gram blocks, then the entry count.
type BlockStarts = [u32; BLOCKS + 1];

/// A sparse list and its [`BlockStarts`].
type Blocked<'a> = (&'a [(u32, DVec3)], &'a BlockStarts);

impl SparseRow {
    fn new<'r>(rows: impl Iterator<Item = &'r CellRow>, cells: usize) -> Self {
        let parts: Vec<Sparse> = rows
            .map(|row| row.iter().map(|&(c, w)| (c, w.as_dvec3())).collect())
            .collect();
        let nnz: Vec<usize> = parts.iter().map(|p| p.len()).collect();
        // The sum has at least the largest part's non-zeros: merge only if that leaves the
        // sum's way cheaper, and keep it if it is.
        let least = nnz.iter().copied().max().unwrap_or(0).min(cells);
        let sum = (parts.len() > 1 && Self::cost(&nnz, least).1)
            .then(|| merge_sorted(&parts))
            .filter(|sum| Self::cost(&nnz, sum.len()).1);
        Self::with_sum(parts, sum, cells)
    }

    /// The row of these parts, summed by way of `sum` where given, for `cells` cells.
    fn with_sum(parts: Vec<Sparse>, sum: Option<Sparse>, cells: usize) -> Self {
        debug_assert!(
            parts
                .iter()
                .chain(&sum)
                .flatten()
                .all(|e| (e.0 as usize) < cells),
            "a cell outside the grid"
        );
        let edges = block_edges(cells);
        let starts = parts
            .iter()
            .chain(&sum)
            .map(|list| {
                let mut at = [0u32; BLOCKS + 1];
                let mut k = 0;
                for (b, &edge) in edges.iter().enumerate() {
                    while k < list.len() && (list[k].0 as usize) < edge {
                        k += 1;
                    }
                    at[b] = k as u32;
                }
                at[BLOCKS] = list.len() as u32;
                at
            })
            .collect();
        SparseRow { parts, sum, starts }
    }

    fn part(&self, a: usize) -> Blocked<'_> {
        (&self.parts[a], &self.starts[a])
    }

    fn sum(&self) -> Option<Blocked<'_>> {
        let starts = self.starts.get(self.parts.len())?;
        self.sum.as_deref().map(|s| (s, starts))
    }

    /// Pairs visited for parts of `nnz` non-zeros whose sum has `sum` (at most), and whether
    /// the sum's way is the cheaper.
    fn cost(nnz: &[usize], sum: usize) -> (usize, bool) {
        let half = |k: usize| k * (k + 1) / 2;
        let own: usize = nnz.iter().map(|&k| half(k)).sum();
        if nnz.len() < 2 {
            return (own, false);
        }
        let total: usize = nnz.iter().sum();
        let direct = (total * total - nnz.iter().map(|k| k * k).sum::<usize>()) / 2;
        let via_sum = half(sum) + own;
        (direct.min(via_sum), via_sum < direct)
    }
}

/// Blocks of Gram rows the sparse updates split the packed triangle into, updated in
/// parallel (each by one thread, its rows' entries in row order: the sums do not depend on
/// the thread count).
const BLOCKS: usize = 16;

/// The first Gram row of each block and the cell count: blocks of equal shares of the
/// triangle's area.
fn block_edges(cells: usize) -> [usize; BLOCKS + 1] {
    std::array::from_fn(|b| ((cells as f64) * (b as f64 / BLOCKS as f64).sqrt()).round() as usize)
}

/// Entries in the packed lower triangle of an `n × n` matrix before row `n`: row i starts
/// at `tri(i)`.
#[inline]
fn tri(n: usize) -> usize {
    n * (n + 1) / 2
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

/// Bytes a pass into `targets` with `parts` parts needs at most, with a solve after it.
pub fn pass_memory(targets: &Targets, parts: usize) -> usize {
    let sums: Vec<(usize, usize)> = (0..targets.grids.len())
        .map(|g| (targets.grids[g].cell_count(), targets.sets_of_grid(g)))
        .collect();
    memory_needed(&sums, parts)
}

/// Bytes [`accumulate`] and the solve after it need at most for grids of `(cells, sums kept)`
/// and `parts` parts ([`pass_memory`]): the sums, one chunk (rendered rows,
/// sparse at up to 16 bytes an entry per grid, and the largest grid's dense f64 copies), and
/// one solve's dense Gram, its regularised copy and the positive semi-definite projection's
/// eigenvectors (about 7 cells² f64 of the largest grid).
pub fn memory_needed(grids: &[(usize, usize)], parts: usize) -> usize {
    let px = (crate::render::TILE * crate::render::TILE) as usize;
    let total: usize = grids.iter().map(|g| g.0).sum();
    let largest = grids.iter().map(|g| g.0).max().unwrap_or(0);
    let chunk =
        tiles_per_chunk(total, parts) * px * (16 * parts * total + 8 * (parts + 1) * largest);
    let sums: usize = grids
        .iter()
        .map(|&(cells, kept)| kept * NormalEquations::memory_needed(cells))
        .sum();
    sums + chunk + 7 * largest * largest * 8
}

/// What one transport pass accumulates: for each grid, the normal equations of each set of
/// pixels (or of all of them, for a grid too large to keep sets apart).
pub struct Targets<'a> {
    /// The grids directions are binned into (any ring counts: the parts' sampling grid need
    /// not be among them).
    pub grids: &'a [RingGrid],
    /// How many sets of pixels.
    pub sets: usize,
    /// The set a (view, pixel) belongs to, or `None` if the pass leaves it out. Only pixels
    /// the masks hold are asked about.
    pub set_of: &'a (dyn Fn((usize, u32)) -> Option<usize> + Sync),
    /// Grids of more cells keep one sum for the pixels of every set: a sum per set costs
    /// cells² each, and only grids this small are wanted per set.
    pub max_set_cells: usize,
}

impl<'a> Targets<'a> {
    /// One grid, one set of pixels: those `set_of` places in set 0.
    pub fn one(
        grid: &'a RingGrid,
        set_of: &'a (dyn Fn((usize, u32)) -> Option<usize> + Sync),
    ) -> Self {
        Targets {
            grids: std::slice::from_ref(grid),
            sets: 1,
            set_of,
            max_set_cells: usize::MAX,
        }
    }

    /// The sums grid `g` keeps: one per set, or one for all sets.
    pub fn sets_of_grid(&self, g: usize) -> usize {
        if self.grids[g].cell_count() <= self.max_set_cells {
            self.sets
        } else {
            1
        }
    }
}

/// Renders the transport of `parts` over the pixels of each camera that its mask holds and
/// `targets` places in a set, and reduces it, per set and grid, to its [`NormalEquations`]
/// against the references' values, chunk by chunk: `[grid][set]`, with
/// [`Targets::sets_of_grid`] sets per grid. Tiles without such a pixel
/// are not rendered. `progress` is called with the rendered pixels of each tile and part:
/// [`progress_units`] in all.
#[allow(clippy::too_many_arguments)]
pub fn accumulate(
    renderer: &Renderer,
    cameras: &[&Camera],
    masks: &[Vec<bool>],
    targets: &Targets,
    references: &[Image],
    parts: &[Part],
    stream_base: u64,
    progress: &(dyn Fn(u64) + Sync),
) -> Vec<Vec<NormalEquations>> {
    let grids = targets.grids;
    let mut out: Vec<Vec<NormalEquations>> = grids
        .iter()
        .enumerate()
        .map(|(g, grid)| {
            (0..targets.sets_of_grid(g))
                .map(|_| NormalEquations::new(grid.cell_count(), parts.len()))
                .collect()
        })
        .collect();
    let lights: Vec<Lights> = parts
        .iter()
        .map(|p| Lights::env(p.sampling.clone()))
        .collect();
    let renderers: Vec<Renderer> = lights.iter().map(|l| renderer.with_lights(l)).collect();
    // A sample's camera ray can escape, and each vertex delivers a light sample and a
    // scattered ray that escapes.
    let part = &parts[0].settings;
    let acc = CellAccumulator {
        grids,
        sampling_rings: parts[0].sampling.grid.rings(),
        expected: (part.spp * (2 * part.max_bounces + 1)) as usize,
    };
    let set_of = |(v, i): (usize, u32)| {
        if masks[v][i as usize] {
            (targets.set_of)((v, i))
        } else {
            None
        }
    };
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
                .filter(|&i| set_of((v, i)).is_some())
                .count();
            ((v, (x0, y0, x1, y1)), n as u64)
        })
        .filter(|&(_, n)| n > 0)
        .collect();
    let total_cells = grids.iter().map(|g| g.cell_count()).sum();
    for chunk in work.chunks(tiles_per_chunk(total_cells, parts.len())) {
        // Per tile, per part: the tile's pixels.
        let rendered: Vec<Vec<Vec<Done<CellPixel>>>> = chunk
            .par_iter()
            .map(|&((v, tile), wanted)| {
                let wanted_pixel = |i| set_of((v, i)).is_some();
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
        // Sets apart for the grids that keep them (all grids when there is one set), then
        // every set at once for the others.
        let apart = |g: usize| targets.sets_of_grid(g) == targets.sets;
        let batches = (0..targets.sets)
            .map(|set| (Some(set), (0..grids.len()).filter(|&g| apart(g)).collect()))
            .chain(std::iter::once((
                None,
                (0..grids.len()).filter(|&g| !apart(g)).collect(),
            )));
        for (set, batch_grids) in batches {
            let batch_grids: Vec<usize> = batch_grids;
            if batch_grids.is_empty() {
                continue;
            }
            // The batch's rows, in tile order: (tile in the chunk, index within the tile).
            let rows: Vec<(usize, usize)> = chunk
                .iter()
                .zip(&rendered)
                .enumerate()
                .flat_map(|(t, (&((v, _), _), per_part))| {
                    per_part[0]
                        .iter()
                        .enumerate()
                        .filter(move |(_, (index, _, _))| {
                            let s = set_of((v, *index));
                            s.is_some() && (set.is_none() || s == set)
                        })
                        .map(move |(k, _)| (t, k))
                })
                .collect();
            if rows.is_empty() {
                continue;
            }
            let y: Vec<DVec3> = rows
                .iter()
                .map(|&(t, k)| {
                    let v = chunk[t].0.0;
                    let index = rendered[t][0][k].0 as usize;
                    references[v].rgb[index].as_dvec3()
                })
                .collect();
            for g in batch_grids {
                out[g][set.unwrap_or(0)].add_rows(&y, |r, a| {
                    let (t, k) = rows[r];
                    &rendered[t][a][k].1.rows[g]
                });
            }
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

/// Entries in `grid`'s cells summed by cell (in the order given), times `scale`, by
/// increasing cell, without the cells whose sum is zero. By a dense scratch row per thread
/// rather than a sort of the entries: a pixel's deliveries are many times its distinct cells.
fn merge_by_cell_dense(
    entries: impl Iterator<Item = (u32, Vec3)>,
    grid: &RingGrid,
    scale: f32,
) -> CellRow {
    thread_local! {
        static SCRATCH: std::cell::RefCell<(Vec<Vec3>, Vec<bool>, Vec<u32>)> = Default::default();
    }
    let cells = grid.cell_count();
    SCRATCH.with_borrow_mut(|(sum, seen, touched)| {
        if sum.len() < cells {
            sum.resize(cells, Vec3::ZERO);
            seen.resize(cells, false);
        }
        touched.clear();
        for (c, w) in entries {
            let i = c as usize;
            if !seen[i] {
                seen[i] = true;
                touched.push(c);
                sum[i] = w;
            } else {
                sum[i] += w;
            }
        }
        touched.sort_unstable();
        let mut row = Vec::with_capacity(touched.len());
        for &c in touched.iter() {
            let i = c as usize;
            seen[i] = false;
            let w = std::mem::replace(&mut sum[i], Vec3::ZERO);
            if w != Vec3::ZERO {
                row.push((c, w * scale));
            }
        }
        row
    })
}

/// The rows `rows` (each by increasing cell) summed by cell, a cell's weights in the rows'
/// order, by increasing cell.
fn merge_sorted(rows: &[Sparse]) -> Sparse {
    let mut out: Sparse = rows.first().cloned().unwrap_or_default();
    let mut next = Vec::new();
    for row in rows.iter().skip(1) {
        next.clear();
        next.reserve(out.len() + row.len());
        let (mut a, mut b) = (out.iter().peekable(), row.iter().peekable());
        loop {
            match (a.peek(), b.peek()) {
                (Some(&&(ca, wa)), Some(&&(cb, wb))) => {
                    if ca < cb {
                        next.push((ca, wa));
                        a.next();
                    } else if cb < ca {
                        next.push((cb, wb));
                        b.next();
                    } else {
                        next.push((ca, wa + wb));
                        a.next();
                        b.next();
                    }
                }
                (Some(&&e), None) => {
                    next.push(e);
                    a.next();
                }
                (None, Some(&&e)) => {
                    next.push(e);
                    b.next();
                }
                (None, None) => break,
            }
        }
        std::mem::swap(&mut out, &mut next);
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

    /// `Σ_{a≠b} T_aᵀT_b / (P(P−1))` of channel `ch` before the PSD projection, full (one
    /// part: its own Gram).
    fn raw_cross(ne: &NormalEquations, ch: usize) -> Vec<f64> {
        let (n, p) = (ne.cells, ne.parts as f64);
        let scale = if ne.parts < 2 { 1.0 } else { p * (p - 1.0) };
        (0..n * n)
            .map(|k| {
                let (i, j) = (k / n, k % n);
                let e = tri(i.max(j)) + i.min(j);
                ne.cross[e][ch] / scale
            })
            .collect()
    }

    #[test]
    fn sparse_and_dense_updates_give_the_same_sums() {
        // Three parts (and one) of mostly-zero rows, channels scaled differently; the same
        // rows in two chunks by each path.
        // 12 cells leave most of the 16 Gram blocks empty; 100 fill every one.
        for (parts, cells) in [(3, 12), (1, 12), (3, 100)] {
            same_sums_by_both_paths(parts, cells);
        }
    }

    fn same_sums_by_both_paths(parts: usize, cells: usize) {
        let rows = 50;
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
        let mut summed = NormalEquations::new(cells, parts);
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
                    t.iter()
                        .map(|p| {
                            (0..cells)
                                .filter(|&c| p[r * cells + c] != 0.0)
                                .map(|c| {
                                    let v = p[r * cells + c];
                                    (c as u32, DVec3::from_array(scale) * v)
                                })
                                .collect()
                        })
                        .collect()
                })
                .collect();
            // Directly, and by way of the sum.
            let direct: Vec<SparseRow> = lists
                .iter()
                .map(|l| SparseRow::with_sum(l.clone(), None, cells))
                .collect();
            let via_sum: Vec<SparseRow> = lists
                .iter()
                .map(|l| {
                    SparseRow::with_sum(l.clone(), (parts > 1).then(|| merge_sorted(l)), cells)
                })
                .collect();
            sparse.add_sparse(&direct, &y[start..end]);
            summed.add_sparse(&via_sum, &y[start..end]);
        }
        let close = |a: &[f64], b: &[f64]| {
            a.iter()
                .zip(b)
                .all(|(x, y)| (x - y).abs() <= 1e-12 * (1.0 + x.abs()))
        };
        for ch in 0..3 {
            for sparse in [&sparse, &summed] {
                assert!(
                    close(&raw_cross(&dense, ch), &raw_cross(sparse, ch)),
                    "{parts} parts, channel {ch}"
                );
                assert!(close(&dense.tb(ch), &sparse.tb(ch)), "channel {ch}");
                assert!((dense.yy(ch) - sparse.yy(ch)).abs() < 1e-9, "channel {ch}");
            }
        }
        // Not all zero, or the comparison proves nothing.
        assert!(raw_cross(&dense, 0).iter().any(|v| *v > 0.1));
    }

    /// (cell, weight) entries summed by cell in the order given (the sort is stable), by
    /// increasing cell: what the merges compute, the obvious way.
    fn merge_by_cell<T: Copy + std::ops::AddAssign>(mut entries: Vec<(u32, T)>) -> Vec<(u32, T)> {
        entries.sort_by_key(|e| e.0);
        let mut out: Vec<(u32, T)> = Vec::new();
        for (c, w) in entries {
            match out.last_mut() {
                Some(last) if last.0 == c => last.1 += w,
                _ => out.push((c, w)),
            }
        }
        out
    }

    #[test]
    fn merges_give_the_sorted_sums_bit_for_bit() {
        let grid = RingGrid::new(9);
        let mut rng = Rng::new(3);
        for _ in 0..50 {
            let len = (rng.next_f32() * 200.0) as usize;
            let entries: Vec<(u32, Vec3)> = (0..len)
                .map(|_| {
                    let c = (rng.next_f32() * 20.0) as u32 * 4;
                    let w = Vec3::new(rng.next_f32(), rng.next_f32(), 0.0) - 0.3;
                    (c, w)
                })
                .collect();
            let mut expected = merge_by_cell(entries.clone());
            expected.retain(|e| e.1 != Vec3::ZERO);
            expected.iter_mut().for_each(|e| e.1 *= 0.25);
            assert_eq!(
                merge_by_cell_dense(entries.iter().copied(), &grid, 0.25),
                expected
            );
            let rows: Vec<Sparse> = entries
                .chunks(len / 3 + 1)
                .map(|c| merge_by_cell(c.iter().map(|&(c, w)| (c, w.as_dvec3())).collect()))
                .collect();
            let flat: Vec<(u32, DVec3)> = rows.iter().flatten().copied().collect();
            assert_eq!(merge_sorted(&rows), merge_by_cell(flat));
        }
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
