//! The transport (the paper's Eq. 4, generalised to any number of bounces): for every pixel and
//! colour channel α, the derivative of the pixel value with respect to each envmap cell's
//! radiance. Light transport is linear in emitted radiance, so `I_α = T_α λ_α` exactly; the
//! one path tracer estimates T by accumulating, per cell, the weight a path delivers.
//!
//! Cells are sampled by the envmap's importance distribution: with a constant map that is in
//! proportion to solid angle (so fine grids are not starved); with a current estimate it is
//! the paper's sequential Monte Carlo importance.

use glam::Vec3;

use crate::envmap::Envmap;
use crate::render::{Accumulator, Emitter, Lights, RenderSettings, Renderer};
use crate::scene::Camera;

/// Which emitters a [`PerEmitterAccumulator`] keeps apart.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EmitterKind {
    /// The envmap's cells (the envmap model's transport).
    EnvCells,
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
            (EmitterKind::EnvCells, Emitter::EnvCell(i))
            | (EmitterKind::Spheres | EmitterKind::SpheresThenCells { .. }, Emitter::Sphere(i)) => {
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

/// T for the masked pixels of some views: `rows` rows (pixels) × `cells` columns, one matrix
/// per channel, row-major, f32.
#[derive(Debug, Clone)]
pub struct Transport {
    pub rings: u32,
    pub cells: usize,
    pub rows: usize,
    /// Per channel (R, G, B): `rows × cells`, row-major.
    pub t: [Vec<f32>; 3],
    /// Per row: (view index, pixel index).
    pub pixel_of_row: Vec<(usize, u32)>,
}

impl Transport {
    /// Bytes held.
    pub fn memory_bytes(&self) -> usize {
        3 * self.rows * self.cells * 4 + self.pixel_of_row.len() * 16
    }

    /// Bytes a transport of this size would need (to refuse jobs that cannot fit).
    pub fn memory_needed(rows: usize, cells: usize) -> usize {
        3 * rows * cells * 4 + rows * 16
    }

    /// T·λ for channel `ch`: the predicted value of every row.
    pub fn apply(&self, ch: usize, lambda: &[f64]) -> Vec<f64> {
        self.t[ch]
            .chunks_exact(self.cells)
            .map(|row| row.iter().zip(lambda).map(|(&t, &l)| t as f64 * l).sum())
            .collect()
    }
}

/// Estimates T for the masked pixels of each camera. `sampling` is the envmap whose importance
/// distribution picks cells (its radiance only steers sampling; T does not depend on it).
pub fn estimate_transport(
    renderer: &Renderer,
    cameras: &[&Camera],
    masks: &[Vec<bool>],
    sampling: &Envmap,
    settings: &RenderSettings,
    stream_base: u64,
    progress: &(dyn Fn(u64) + Sync),
) -> Transport {
    let cells = sampling.grid.cell_count();
    let lights = Lights::env(sampling.clone());
    let renderer = renderer.with_lights(&lights);
    let acc = PerEmitterAccumulator {
        kind: EmitterKind::EnvCells,
        count: cells,
    };
    let rows_total: usize = masks.iter().map(|m| m.iter().filter(|&&b| b).count()).sum();
    let mut t: [Vec<f32>; 3] = std::array::from_fn(|_| Vec::with_capacity(rows_total * cells));
    let mut pixel_of_row = Vec::with_capacity(rows_total);
    for (v, (cam, mask)) in cameras.iter().zip(masks).enumerate() {
        let frame = renderer.render(cam, stream_base + v as u64, settings, &acc, progress);
        for (i, row) in frame.pixels.into_iter().enumerate() {
            if !mask[i] {
                continue;
            }
            for (ch, t_ch) in t.iter_mut().enumerate() {
                t_ch.extend(row.iter().map(|w| w[ch]));
            }
            pixel_of_row.push((v, i as u32));
        }
    }
    Transport {
        rings: sampling.grid.rings(),
        cells,
        rows: pixel_of_row.len(),
        t,
        pixel_of_row,
    }
}
