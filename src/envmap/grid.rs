//! The ring grid of the authors' code (`EnvironmentLight::UpdateOffsets`): `N` rings of
//! constant polar angle θ (from +Y), poles included, `Δ = π/(N−1)`, `θ_i = iΔ`. The pole rings
//! hold one point each; ring i in between holds `4·round(((N−1)/2)·sin θ_i)` points at
//! azimuths `φ_ij = 2πj/n_i`. `N = 1` is one cell covering the sphere (constant ambient light).
//!
//! Each point owns a cell: its band `[θ_i − Δ/2, θ_i + Δ/2] ∩ [0, π]` times its sector
//! `[φ_ij − π/n_i, φ_ij + π/n_i)`. Lookup rounds θ to the nearest ring, then φ to the nearest
//! point of that ring — O(1), and the cells tile the sphere exactly.
//!
//! Azimuth: `φ = atan2(d.x, −d.z)` wrapped to [0, 2π): φ = 0 is −Z, φ = π/2 is +X. This is
//! Mitsuba 3's lat-long `u = φ/2π`, so the default export is a plain resampling.
//! Cells are numbered ring by ring from +Y (ring 0, the north pole), by increasing φ.

use std::f64::consts::{PI, TAU};

use glam::{DVec3, Vec2, Vec3};

use crate::math::{atan2, sin_cos_2pi};

/// The cell layout of an `N`-ring envmap.
#[derive(Debug, Clone, PartialEq)]
pub struct RingGrid {
    rings: u32,
    /// Points (cells) per ring.
    counts: Vec<u32>,
    /// Index of each ring's first cell; `first[rings]` is the cell count.
    first: Vec<u32>,
    /// cos θ of the band edges between rings, `cos((k + ½)Δ)` for k = 0..N−2 (decreasing):
    /// lookup and sampling compare against these same numbers, so a sampled direction finds
    /// its own cell, and neither needs an inverse cosine.
    edges_cos: Vec<f64>,
    /// The ring of each cell.
    ring_of_cell: Vec<u32>,
}

/// Where a cell lies: its polar band and azimuth sector, radians.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CellBounds {
    pub theta_min: f64,
    pub theta_max: f64,
    /// Sector start (may be negative: the sector of φ = 0 straddles the seam).
    pub phi_min: f64,
    pub phi_max: f64,
}

impl CellBounds {
    /// Solid angle, steradians.
    pub fn solid_angle(&self) -> f64 {
        (self.theta_min.cos() - self.theta_max.cos()) * (self.phi_max - self.phi_min)
    }
}

/// Unit direction from polar angle θ (from +Y) and azimuth φ (see the module doc).
#[inline]
pub fn direction(theta: f64, phi: f64) -> DVec3 {
    let (st, ct) = theta.sin_cos();
    DVec3::new(st * phi.sin(), ct, -st * phi.cos())
}

/// (θ, φ) of a unit direction, θ in [0, π], φ in [0, 2π).
#[inline]
pub fn angles(d: Vec3) -> (f64, f64) {
    let d = d.as_dvec3();
    let theta = d.y.clamp(-1.0, 1.0).acos();
    let mut phi = d.x.atan2(-d.z);
    if phi < 0.0 {
        phi += TAU;
    }
    if phi >= TAU {
        phi = 0.0;
    }
    (theta, phi)
}

impl RingGrid {
    /// The grid of `rings` rings (≥ 1).
    pub fn new(rings: u32) -> RingGrid {
        assert!(rings >= 1, "a ring grid has at least one ring");
        let counts: Vec<u32> = if rings == 1 {
            vec![1]
        } else {
            let delta = PI / (rings - 1) as f64;
            (0..rings)
                .map(|i| {
                    if i == 0 || i == rings - 1 {
                        1
                    } else {
                        let x = 0.5 * (rings - 1) as f64 * (i as f64 * delta).sin();
                        // Round ties up, identically on both hemispheres (see docs/design.md).
                        4 * (x + 0.5 + 1e-9).floor() as u32
                    }
                })
                .collect()
        };
        let mut first = Vec::with_capacity(counts.len() + 1);
        let mut acc = 0;
        for &c in &counts {
            first.push(acc);
            acc += c;
        }
        first.push(acc);
        let delta = PI / (rings.max(2) - 1) as f64;
        let edges_cos = (0..rings.saturating_sub(1))
            .map(|k| ((k as f64 + 0.5) * delta).cos())
            .collect();
        let ring_of_cell = (0..rings)
            .flat_map(|r| std::iter::repeat_n(r, counts[r as usize] as usize))
            .collect();
        RingGrid {
            rings,
            counts,
            first,
            edges_cos,
            ring_of_cell,
        }
    }

    pub fn rings(&self) -> u32 {
        self.rings
    }

    pub fn cell_count(&self) -> usize {
        self.first[self.rings as usize] as usize
    }

    /// Points in ring `i`.
    pub fn ring_len(&self, ring: u32) -> u32 {
        self.counts[ring as usize]
    }

    /// Index of ring `i`'s first cell.
    pub fn ring_start(&self, ring: u32) -> u32 {
        self.first[ring as usize]
    }

    /// The ring of a cell and its index within the ring.
    #[inline]
    pub fn ring_of(&self, cell: u32) -> (u32, u32) {
        let ring = self.ring_of_cell[cell as usize];
        (ring, cell - self.first[ring as usize])
    }

    fn delta(&self) -> f64 {
        if self.rings == 1 {
            PI
        } else {
            PI / (self.rings - 1) as f64
        }
    }

    /// The cell containing direction (θ, φ).
    #[inline]
    pub fn lookup_angles(&self, theta: f64, phi: f64) -> u32 {
        if self.rings == 1 {
            return 0;
        }
        let ring = ((theta / self.delta()).round() as u32).min(self.rings - 1);
        let n = self.counts[ring as usize];
        let j = (phi * n as f64 / TAU).round() as u32 % n;
        self.first[ring as usize] + j
    }

    /// The cell containing unit direction `d`: the same cell as [`Self::lookup_angles`] (up to
    /// rounding at cell edges), without an inverse cosine and with an inline f32 arctangent
    /// (this is on the tracer's path for every ray that escapes).
    #[inline(always)]
    pub fn lookup(&self, d: Vec3) -> u32 {
        let y = d.y as f64;
        self.cell_in_ring(count_while(&self.edges_cos, |e| y <= e), || azimuth(d))
    }

    /// [`Self::lookup`] of a direction with up-component `y`, polar angle `theta` (≈ acos y)
    /// and azimuth `phi` ([`azimuth`]): the same cell, found in O(1) whatever the ring count,
    /// so that many grids can share one inverse cosine and one arctangent.
    #[inline(always)]
    pub fn lookup_polar(&self, y: f64, theta: f64, phi: f64) -> u32 {
        // The ring is the number of band edges at or above the direction; θ/Δ rounded
        // counts them up to rounding, which the comparisons with the edges settle.
        let last = self.edges_cos.len();
        let mut ring = ((theta / self.delta() + 0.5) as usize).min(last);
        while ring > 0 && y > self.edges_cos[ring - 1] {
            ring -= 1;
        }
        while ring < last && y <= self.edges_cos[ring] {
            ring += 1;
        }
        self.cell_in_ring(ring, || phi)
    }

    /// The cell of ring `ring` whose sector holds azimuth `phi` (asked for only if the ring
    /// has more than one cell).
    #[inline(always)]
    fn cell_in_ring(&self, ring: usize, phi: impl FnOnce() -> f64) -> u32 {
        let n = self.counts[ring];
        if n == 1 {
            return self.first[ring];
        }
        // Nearest sector centre; φ ≥ 0, so rounding is the truncation of x + ½ (f64::round
        // and, on the baseline x86-64 target, f64::floor are library calls) and the wrap past
        // the last sector a comparison (not a division).
        let j = (phi() * n as f64 / TAU + 0.5) as u32;
        self.first[ring] + if j >= n { j - n } else { j }
    }

    /// cos θ at the top and bottom of ring `ring`'s band (the top is the larger).
    #[inline]
    fn band_cos(&self, ring: u32) -> (f64, f64) {
        let r = ring as usize;
        let top = if r == 0 { 1.0 } else { self.edges_cos[r - 1] };
        let bottom = self.edges_cos.get(r).copied().unwrap_or(-1.0);
        (top, bottom)
    }

    /// A cell's band and sector.
    pub fn bounds(&self, cell: u32) -> CellBounds {
        let (ring, j) = self.ring_of(cell);
        let n = self.counts[ring as usize] as f64;
        if self.rings == 1 {
            return CellBounds {
                theta_min: 0.0,
                theta_max: PI,
                phi_min: 0.0,
                phi_max: TAU,
            };
        }
        let (d, theta) = (self.delta(), ring as f64 * self.delta());
        let half = PI / n;
        let phi = TAU * j as f64 / n;
        CellBounds {
            theta_min: (theta - 0.5 * d).max(0.0),
            theta_max: (theta + 0.5 * d).min(PI),
            phi_min: phi - half,
            phi_max: phi + half,
        }
    }

    /// The direction of a cell's grid point (its ring's θ, its φ). Inverse of [`Self::lookup`]:
    /// `lookup(center(c)) == c`.
    pub fn center(&self, cell: u32) -> Vec3 {
        if self.rings == 1 {
            return Vec3::Y;
        }
        let (ring, j) = self.ring_of(cell);
        let n = self.counts[ring as usize] as f64;
        direction(ring as f64 * self.delta(), TAU * j as f64 / n).as_vec3()
    }

    /// Solid angle of a cell, steradians.
    pub fn solid_angle(&self, cell: u32) -> f64 {
        self.bounds(cell).solid_angle()
    }

    /// A direction uniformly distributed (per solid angle) over the cell, from `u` ∈ [0,1)²:
    /// cos θ uniform over the band, φ uniform over the sector.
    #[inline]
    pub fn sample_in_cell(&self, cell: u32, u: Vec2) -> Vec3 {
        let (ring, j) = self.ring_of(cell);
        let (c0, c1) = self.band_cos(ring);
        let cos_t = c0 + (c1 - c0) * u.x as f64;
        let sin_t = (1.0 - cos_t * cos_t).max(0.0).sqrt();
        let n = self.counts[ring as usize] as f64;
        // φ / 2π in f32 (a sector is ≥ 0.5° wide, f32 rounds φ to ~1e-7 rad), wrapped into
        // [0, 1), and its sine and cosine inline: this is on the tracer's path.
        let turns = ((j as f64 - 0.5 + u.y as f64) / n) as f32;
        let (sp, cp) = sin_cos_2pi(if turns < 0.0 { turns + 1.0 } else { turns });
        Vec3::new(
            (sin_t * sp as f64) as f32,
            cos_t as f32,
            (-sin_t * cp as f64) as f32,
        )
    }
}

/// The azimuth φ ∈ [0, 2π) of unit direction `d` (see the module doc), by the inline f32
/// arctangent of [`RingGrid::lookup`].
#[inline(always)]
pub fn azimuth(d: Vec3) -> f64 {
    let phi = atan2(d.x, -d.z) as f64;
    if phi < 0.0 { phi + TAU } else { phi }
}

/// How many leading elements of `sorted` satisfy `pred` (which must hold for a prefix, as for
/// [`slice::partition_point`], whose answer this is). Short slices are counted whole, without
/// the unpredictable branches of a binary search: the grid's and the envmap's searches run
/// for every envmap sample and every escaping ray.
#[inline]
pub(crate) fn count_while(sorted: &[f64], pred: impl Fn(f64) -> bool) -> usize {
    if sorted.len() <= 64 {
        sorted.iter().map(|&e| pred(e) as usize).sum()
    } else {
        sorted.partition_point(|&e| pred(e))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampling::{Rng, uniform_sphere};

    #[test]
    fn counts_match_the_authors_table() {
        let want = [
            1, 2, 6, 10, 18, 26, 54, 66, 90, 106, 134, 154, 186, 210, 246, 282, 330, 370, 422, 466,
            522, 562, 622, 666, 738,
        ];
        for (n, &w) in (1..=25).zip(&want) {
            assert_eq!(RingGrid::new(n).cell_count(), w, "N = {n}");
        }
    }

    #[test]
    fn hemispheres_are_symmetric_even_at_ties() {
        for n in 2..=60 {
            let g = RingGrid::new(n);
            for i in 0..n {
                assert_eq!(g.ring_len(i), g.ring_len(n - 1 - i), "N = {n}, ring {i}");
            }
        }
    }

    #[test]
    fn solid_angles_sum_to_four_pi() {
        for n in [1, 2, 3, 7, 9, 19, 21, 25, 100] {
            let g = RingGrid::new(n);
            let total: f64 = (0..g.cell_count() as u32).map(|c| g.solid_angle(c)).sum();
            assert!((total - 4.0 * PI).abs() < 1e-9, "N = {n}: {total}");
        }
    }

    #[test]
    fn every_centre_looks_up_to_itself() {
        for n in [1, 2, 3, 5, 9, 19, 21, 40] {
            let g = RingGrid::new(n);
            for c in 0..g.cell_count() as u32 {
                assert_eq!(g.lookup(g.center(c)), c, "N = {n}");
            }
        }
    }

    #[test]
    fn fast_lookup_agrees_with_the_angles() {
        // `lookup` (band edges by cosine, f32 arctangent) against `lookup_angles` (f64 θ, φ):
        // equal except within rounding of an edge.
        let mut r = Rng::new(5);
        for n in [1, 2, 3, 9, 21, 25] {
            let g = RingGrid::new(n);
            let mut differ = 0;
            for _ in 0..100_000 {
                let d = uniform_sphere(r.next_2d());
                let (t, p) = angles(d);
                differ += (g.lookup(d) != g.lookup_angles(t, p)) as u32;
            }
            assert!(differ <= 2, "N = {n}: {differ} of 100000 differ");
        }
    }

    #[test]
    fn polar_lookup_is_exactly_the_fast_lookup() {
        // Many grids share one θ and φ per direction: the cell must be the one `lookup` (and
        // so the tracer) finds, bit for bit, also at band edges and the poles.
        let mut r = Rng::new(9);
        for n in [1, 2, 3, 4, 9, 21, 27, 61] {
            let g = RingGrid::new(n);
            let edge_dirs = g.edges_cos.iter().flat_map(|&c| {
                let s = (1.0 - c * c).sqrt() as f32;
                [Vec3::new(s, c as f32, 0.0), Vec3::new(0.0, c as f32, -s)]
            });
            let random = (0..50_000).map(|_| uniform_sphere(r.next_2d()));
            let poles = [Vec3::Y, Vec3::NEG_Y, Vec3::NEG_Z];
            for d in random.chain(edge_dirs.collect::<Vec<_>>()).chain(poles) {
                let y = d.y as f64;
                let theta = y.clamp(-1.0, 1.0).acos();
                assert_eq!(
                    g.lookup_polar(y, theta, azimuth(d)),
                    g.lookup(d),
                    "N={n} {d}"
                );
            }
        }
    }

    #[test]
    fn random_directions_fall_inside_their_cell() {
        let mut r = Rng::new(11);
        for n in [2, 3, 9, 21] {
            let g = RingGrid::new(n);
            for _ in 0..20_000 {
                let d = uniform_sphere(r.next_2d());
                let (t, mut p) = angles(d);
                let b = g.bounds(g.lookup(d));
                assert!(t >= b.theta_min - 1e-9 && t <= b.theta_max + 1e-9);
                if p >= b.phi_max {
                    p -= TAU; // the seam sector [−π/n, π/n)
                }
                assert!(
                    p >= b.phi_min - 1e-9 && p < b.phi_max + 1e-9,
                    "N={n} φ={p} {b:?}"
                );
            }
        }
    }

    #[test]
    fn cell_samples_stay_in_their_cell() {
        let g = RingGrid::new(9);
        let mut r = Rng::new(3);
        for c in 0..g.cell_count() as u32 {
            for _ in 0..200 {
                assert_eq!(g.lookup(g.sample_in_cell(c, r.next_2d())), c);
            }
        }
    }

    #[test]
    fn azimuth_convention_is_pinned() {
        // φ = 0 is −Z, φ = π/2 is +X; poles are rings 0 (+Y) and N−1 (−Y).
        let (_, p) = angles(Vec3::NEG_Z);
        assert!(p.abs() < 1e-12);
        let (_, p) = angles(Vec3::X);
        assert!((p - PI / 2.0).abs() < 1e-12);
        let g = RingGrid::new(5);
        assert_eq!(g.lookup(Vec3::Y), 0);
        assert_eq!(g.lookup(-Vec3::Y) as usize, g.cell_count() - 1);
        // Just either side of the seam (φ ≈ 0 from above and from below 2π) is the same cell.
        let a = g.lookup(direction(PI / 2.0, 1e-6).as_vec3());
        let b = g.lookup(direction(PI / 2.0, TAU - 1e-6).as_vec3());
        assert_eq!(a, b);
        assert_eq!(g.ring_of(a), (2, 0));
    }
}
