//! The ring environment map: light from infinitely far away, piecewise constant over the cells
//! of a [`RingGrid`] — a true area light at infinity, with one linear RGB radiance per cell.
//!
//! Importance sampling follows pbrt's 2D piecewise-constant distribution adapted to rings: a
//! marginal over rings and a conditional over the cells of a ring, each cell weighted by
//! luminance × solid angle plus a small floor (so no cell has zero probability); the direction
//! is then uniform inside the cell, so the pdf per unit solid angle is `P(cell) / Ω(cell)`.
//!
//! File format (`envmap.ron`): `Envmap(rings: N, radiance: [(r, g, b), …])`, one triple per
//! cell, ring by ring from +Y, by increasing azimuth (see [`grid`]).
//!
//! ```
//! use glam::Vec3;
//! use lightprobe::envmap::Envmap;
//! let env = Envmap::constant(9, Vec3::splat(0.5));
//! assert_eq!(env.grid.cell_count(), 90);
//! assert_eq!(env.eval(Vec3::Y), (0, Vec3::splat(0.5)));
//! ```

pub mod grid;
pub mod latlong;

use std::fmt::Write as _;
use std::path::Path;

use glam::{Vec2, Vec3};
use serde::Deserialize;

pub use grid::RingGrid;

use crate::checked::checked;
use crate::error::{Error, Result};
use crate::imageio::{luminance, write_bytes};

/// Largest accepted ring count of the grid (1000 rings hold about 1.3 million cells).
pub const MAX_RINGS: u32 = 1000;

checked!(
    /// Ring count of the envmap grid, 1..=1000.
    Rings(u32), "u32", |v| (1..=MAX_RINGS).contains(&v),
    "rings must be between 1 and 1000, got {}"
);
checked!(
    /// Linear RGB radiance, each channel in [0, 1e15] ([`crate::imageio::MAX_RADIANCE`]:
    /// beyond it, a render's sums overflow): `(r, g, b)` or `[r, g, b]`.
    Rgb((f32, f32, f32)), "(f32, f32, f32)", |v| [v.0, v.1, v.2].iter().all(|c| (0.0..=crate::imageio::MAX_RADIANCE).contains(c)),
    "radiance must be between 0 and 1e15 in every channel, got {:?}"
);

/// Relative weight floor of the sampling distribution (× the mean luminance).
const FLOOR: f64 = 1e-3;

/// A ring envmap with its sampling distribution.
#[derive(Debug, Clone)]
pub struct Envmap {
    pub grid: RingGrid,
    /// Linear RGB radiance per cell.
    radiance: Vec<Vec3>,
    /// Solid angle per cell (sr).
    solid_angle: Vec<f32>,
    /// Cumulative ring probabilities, `rings + 1` entries from 0 to 1.
    ring_cdf: Vec<f64>,
    /// Per cell: cumulative probability within its ring (the last of each ring is 1).
    cell_cdf: Vec<f64>,
    /// Per cell: P(cell) / Ω(cell).
    pdf: Vec<f32>,
    /// Σ luminance × Ω over cells: the map's weight when lights are picked by power.
    luminance_integral: f32,
}

impl Envmap {
    /// An envmap from per-cell radiance (length must equal the grid's cell count; every
    /// channel finite and ≥ 0).
    pub fn new(rings: u32, radiance: Vec<Vec3>) -> std::result::Result<Envmap, String> {
        if !(1..=MAX_RINGS).contains(&rings) {
            return Err(format!(
                "rings must be between 1 and {MAX_RINGS}, got {rings}"
            ));
        }
        let grid = RingGrid::new(rings);
        if radiance.len() != grid.cell_count() {
            return Err(format!(
                "{rings} rings have {} cells, but {} radiance values were given",
                grid.cell_count(),
                radiance.len()
            ));
        }
        if let Some(i) = radiance.iter().position(|c| {
            !(c.is_finite()
                && c.min_element() >= 0.0
                && c.max_element() <= crate::imageio::MAX_RADIANCE)
        }) {
            return Err(format!(
                "cell {i} has radiance {:?}; every channel must be between 0 and 1e15",
                radiance[i].to_array()
            ));
        }
        let solid_angle: Vec<f32> = (0..grid.cell_count() as u32)
            .map(|c| grid.solid_angle(c) as f32)
            .collect();
        let mut env = Envmap {
            grid,
            radiance,
            solid_angle,
            ring_cdf: Vec::new(),
            cell_cdf: Vec::new(),
            pdf: Vec::new(),
            luminance_integral: 0.0,
        };
        env.build_distribution();
        env.luminance_integral = luminance(env.integral());
        Ok(env)
    }

    /// The same radiance everywhere.
    pub fn constant(rings: u32, radiance: Vec3) -> Envmap {
        let n = RingGrid::new(rings).cell_count();
        Envmap::new(rings, vec![radiance; n]).expect("a valid constant envmap")
    }

    fn build_distribution(&mut self) {
        let g = &self.grid;
        let n = g.cell_count();
        let lum: Vec<f64> = self
            .radiance
            .iter()
            .map(|c| luminance(*c).max(0.0) as f64)
            .collect();
        let total_sa: f64 = self.solid_angle.iter().map(|&s| s as f64).sum();
        let mean_lum = lum
            .iter()
            .zip(&self.solid_angle)
            .map(|(l, s)| l * *s as f64)
            .sum::<f64>()
            / total_sa;
        let floor = if mean_lum > 0.0 {
            FLOOR * mean_lum
        } else {
            1.0
        };
        let weight: Vec<f64> = (0..n)
            .map(|c| (lum[c] + floor) * self.solid_angle[c] as f64)
            .collect();
        let total: f64 = weight.iter().sum();

        self.ring_cdf = Vec::with_capacity(g.rings() as usize + 1);
        self.cell_cdf = vec![0.0; n];
        self.pdf = vec![0.0; n];
        let mut acc = 0.0;
        self.ring_cdf.push(0.0);
        for ring in 0..g.rings() {
            let (start, len) = (g.ring_start(ring) as usize, g.ring_len(ring) as usize);
            let ring_w: f64 = weight[start..start + len].iter().sum();
            let mut in_ring = 0.0;
            let cells = start..start + len;
            for (((w, cdf), pdf), sa) in weight[cells.clone()]
                .iter()
                .zip(&mut self.cell_cdf[cells.clone()])
                .zip(&mut self.pdf[cells.clone()])
                .zip(&self.solid_angle[cells])
            {
                in_ring += w;
                *cdf = in_ring / ring_w;
                *pdf = (w / total / *sa as f64) as f32;
            }
            self.cell_cdf[start + len - 1] = 1.0;
            acc += ring_w / total;
            self.ring_cdf.push(acc);
        }
        *self.ring_cdf.last_mut().expect("at least one ring") = 1.0;
    }

    /// Radiance of every cell.
    pub fn radiance(&self) -> &[Vec3] {
        &self.radiance
    }

    /// Solid angle of a cell, steradians.
    pub fn solid_angle(&self, cell: u32) -> f32 {
        self.solid_angle[cell as usize]
    }

    /// The cell seen in unit direction `d` and its radiance.
    #[inline]
    pub fn eval(&self, d: Vec3) -> (u32, Vec3) {
        let c = self.grid.lookup(d);
        (c, self.radiance[c as usize])
    }

    /// Probability density per unit solid angle of sampling any direction in `cell`.
    #[inline]
    pub fn pdf(&self, cell: u32) -> f32 {
        self.pdf[cell as usize]
    }

    /// Picks a cell with `u_cell` (by luminance × solid angle) and a direction uniformly in it
    /// with `u`: (cell, unit direction, pdf per solid angle).
    #[inline(always)]
    pub fn sample(&self, u_cell: f32, u: Vec2) -> (u32, Vec3, f32) {
        let u_cell = u_cell as f64;
        let ring = (grid::count_while(&self.ring_cdf, |c| c <= u_cell)
            .clamp(1, self.grid.rings() as usize)
            - 1) as u32;
        let (lo, hi) = (
            self.ring_cdf[ring as usize],
            self.ring_cdf[ring as usize + 1],
        );
        let v = if hi > lo {
            ((u_cell - lo) / (hi - lo)).clamp(0.0, 1.0)
        } else {
            0.5
        };
        let (start, len) = (
            self.grid.ring_start(ring) as usize,
            self.grid.ring_len(ring) as usize,
        );
        let j = grid::count_while(&self.cell_cdf[start..start + len], |c| c <= v).min(len - 1);
        let cell = (start + j) as u32;
        (cell, self.grid.sample_in_cell(cell, u), self.pdf[start + j])
    }

    /// Σ luminance × Ω over cells (cached): how strongly the map lights a receiver.
    pub fn luminance_integral(&self) -> f32 {
        self.luminance_integral
    }

    /// Total emitted power per unit area of a receiver facing everything, Σ λ·Ω (W/m² per
    /// channel): the irradiance-like scale of the map.
    pub fn integral(&self) -> Vec3 {
        self.radiance
            .iter()
            .zip(&self.solid_angle)
            .map(|(l, &s)| *l * s)
            .sum()
    }

    /// Reads an `envmap.ron`. Errors name the file (and line:column for syntax errors).
    pub fn load(path: &Path) -> Result<Envmap> {
        #[derive(Deserialize)]
        #[serde(rename = "Envmap", deny_unknown_fields)]
        struct File {
            rings: Rings,
            radiance: Vec<Rgb>,
        }
        let text = crate::memory::read_input_text(path)?;
        let f: File = ron::Options::default().from_str(&text).map_err(|e| {
            Error::file_at(
                path,
                e.span.start.line,
                e.span.start.col,
                e.code.to_string(),
            )
        })?;
        let radiance = f
            .radiance
            .iter()
            .map(|&Rgb((r, g, b))| Vec3::new(r, g, b))
            .collect();
        Envmap::new(f.rings.0, radiance).map_err(|m| Error::file(path, m))
    }

    /// The `envmap.ron` text: exact f32 values, one cell per line.
    pub fn to_ron(&self) -> String {
        let g = &self.grid;
        let mut s = format!(
            "// lightprobe ring envmap: {} rings, {} cells; linear RGB radiance per cell, ring by ring\n\
             // from +Y (theta = 0), by increasing azimuth phi = atan2(x, -z) (phi = 0 is -Z).\nEnvmap(\n    rings: {},\n    radiance: [\n",
            g.rings(),
            g.cell_count(),
            g.rings()
        );
        for (c, l) in self.radiance.iter().enumerate() {
            let (ring, j) = g.ring_of(c as u32);
            let _ = writeln!(
                s,
                "        ({:?}, {:?}, {:?}), // ring {ring} cell {j}",
                l.x, l.y, l.z
            );
        }
        s.push_str("    ],\n)\n");
        s
    }

    /// Writes `envmap.ron` atomically.
    pub fn save(&self, path: &Path) -> Result<()> {
        write_bytes(path, self.to_ron().as_bytes())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampling::Rng;

    fn varied(rings: u32) -> Envmap {
        let g = RingGrid::new(rings);
        let radiance = (0..g.cell_count() as u32)
            .map(|c| {
                let d = g.center(c);
                Vec3::new(
                    0.1 + d.y.max(0.0) * 5.0,
                    0.2 + (c % 3) as f32,
                    if c == 7 { 100.0 } else { 0.05 },
                )
            })
            .collect();
        Envmap::new(rings, radiance).unwrap()
    }

    #[test]
    fn pdf_integrates_to_one() {
        for rings in [1, 2, 5, 9, 21] {
            let e = varied(rings);
            let total: f64 = (0..e.grid.cell_count() as u32)
                .map(|c| e.pdf(c) as f64 * e.solid_angle(c) as f64)
                .sum();
            assert!((total - 1.0).abs() < 1e-5, "{rings}: {total}");
        }
    }

    #[test]
    fn sampling_matches_the_pdf_chi_square() {
        let e = varied(9);
        let n = e.grid.cell_count();
        let draws = 400_000;
        let mut counts = vec![0u32; n];
        let mut r = Rng::new(17);
        for _ in 0..draws {
            let (cell, d, pdf) = e.sample(r.next_f32(), r.next_2d());
            assert_eq!(e.grid.lookup(d), cell);
            assert_eq!(pdf, e.pdf(cell));
            counts[cell as usize] += 1;
        }
        // χ² over cells (expected counts ≥ 5 pooled); dof ≈ n − 1 ≤ 89. The 0.001 critical
        // value for 89 dof is ~137.
        let (mut chi2, mut dof, mut pool_o, mut pool_e) = (0.0f64, 0usize, 0.0f64, 0.0f64);
        for (c, &count) in counts.iter().enumerate() {
            let expected = e.pdf(c as u32) as f64 * e.solid_angle(c as u32) as f64 * draws as f64;
            if expected < 5.0 {
                pool_o += count as f64;
                pool_e += expected;
                continue;
            }
            chi2 += (count as f64 - expected).powi(2) / expected;
            dof += 1;
        }
        if pool_e > 0.0 {
            chi2 += (pool_o - pool_e).powi(2) / pool_e.max(1.0);
            dof += 1;
        }
        assert!(dof > 50, "too few bins: {dof}");
        assert!(chi2 < 137.0, "χ² = {chi2} with {dof} bins");
    }

    #[test]
    fn bright_cells_are_sampled_more_but_none_is_starved() {
        // pdf per solid angle ∝ luminance + floor, in every cell.
        let e = varied(9);
        let n = e.grid.cell_count() as u32;
        let lum = |c: u32| luminance(e.radiance()[c as usize]) as f64;
        let mean = (0..n)
            .map(|c| lum(c) * e.solid_angle(c) as f64)
            .sum::<f64>()
            / (4.0 * std::f64::consts::PI);
        let ratio = |c: u32| e.pdf(c) as f64 / (lum(c) + FLOOR * mean);
        assert!((0..n).all(|c| (ratio(c) / ratio(0) - 1.0).abs() < 1e-4));
        assert!(e.pdf(7) > e.pdf(8));
        assert!((0..n).all(|c| e.pdf(c) > 0.0));
        let black = Envmap::constant(5, Vec3::ZERO);
        assert!(
            (0..black.grid.cell_count() as u32)
                .all(|c| (black.pdf(c) - 1.0 / (4.0 * std::f32::consts::PI)).abs() < 1e-5)
        );
    }

    #[test]
    fn ron_round_trip_is_exact() {
        let e = varied(7);
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("env.ron");
        e.save(&p).unwrap();
        assert_eq!(Envmap::load(&p).unwrap().radiance(), e.radiance());
    }

    #[test]
    fn bad_files_are_clear_errors() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("env.ron");
        for (text, needle) in [
            (
                "Envmap(rings: 2, radiance: [(1, 1, 1)])",
                "2 rings have 2 cells",
            ),
            ("Envmap(rings: 0, radiance: [])", "rings"),
            ("Envmap(rings: 2000, radiance: [])", "rings"),
            ("Envmap(rings: 1, radiance: [(1, NaN, 1)])", "radiance"),
            ("Envmap(rings: 1, radiance: [(1, -1, 1)])", "radiance"),
            ("Envmap(rings: 1, radiance: [(1, 1, 1)], extra: 2)", "extra"),
        ] {
            std::fs::write(&p, text).unwrap();
            let e = Envmap::load(&p).unwrap_err().to_string();
            assert!(e.contains("env.ron") && e.contains(needle), "{text} -> {e}");
        }
    }
}
