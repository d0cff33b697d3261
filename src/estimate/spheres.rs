//! Sphere lights as the light model (issue 9, its linear part). With the lights' centres and
//! radii fixed, every pixel is linear in their radiances, `I_α = Σ_k T_kα L_kα`, so the
//! radiances come from a small exact NNLS on the per-light transport T_k, and only the
//! geometry (4 numbers per light) is left to a non-linear search: variable projection.
//!
//! The one path tracer estimates T_k: it renders the lights at unit radiance and accumulates,
//! per pixel, the weight each light receives ([`SphereAccumulator`]). Renders of two
//! geometries with the same seed share their random numbers (common random numbers), so
//! their residuals differ by the geometry, not by noise.

use glam::Vec3;

use super::nnls;
use crate::imageio::Image;
use crate::render::{Accumulator, Emitter, Lights, RenderSettings, Renderer};
use crate::scene::{Camera, SphereLight};

/// Accumulates, per pixel, the weight each sphere light delivers (per unit radiance).
pub struct SphereAccumulator {
    pub lights: usize,
}

impl Accumulator for SphereAccumulator {
    type Pixel = Vec<Vec3>;
    fn new_pixel(&self) -> Vec<Vec3> {
        vec![Vec3::ZERO; self.lights]
    }
    #[inline]
    fn add(&self, pixel: &mut Vec<Vec3>, emitter: Emitter, weight: Vec3) {
        if let Emitter::Sphere(i) = emitter {
            pixel[i as usize] += weight;
        }
    }
    fn finish(&self, pixel: &mut Vec<Vec3>, spp: u32) {
        let inv = 1.0 / spp as f32;
        pixel.iter_mut().for_each(|v| *v *= inv);
    }
}

/// Per-light transport of the masked pixels: per channel, `rows × lights`, row-major.
#[derive(Debug, Clone)]
pub struct SphereTransport {
    pub lights: usize,
    pub rows: usize,
    pub t: [Vec<f32>; 3],
    /// Per row: (view index, pixel index).
    pub pixel_of_row: Vec<(usize, u32)>,
}

/// Estimates the per-light transport of `geometry` (centres and radii; radiances ignored) for
/// the masked pixels of each camera. The same `settings.seed` gives the same random numbers
/// for any geometry.
pub fn sphere_transport(
    renderer: &Renderer,
    cameras: &[&Camera],
    masks: &[Vec<bool>],
    geometry: &[SphereLight],
    settings: &RenderSettings,
    progress: &(dyn Fn(u64) + Sync),
) -> SphereTransport {
    let unit: Vec<SphereLight> = geometry
        .iter()
        .map(|l| SphereLight {
            radiance: Vec3::ONE,
            ..*l
        })
        .collect();
    let lights = Lights::new(unit);
    let renderer = renderer.with_lights(&lights);
    let acc = SphereAccumulator {
        lights: geometry.len(),
    };
    let mut t: [Vec<f32>; 3] = std::array::from_fn(|_| Vec::new());
    let mut pixel_of_row = Vec::new();
    for (v, (cam, mask)) in cameras.iter().zip(masks).enumerate() {
        let frame = renderer.render(cam, 2000 + v as u64, settings, &acc, progress);
        for (i, row) in frame
            .pixels
            .into_iter()
            .enumerate()
            .filter(|(i, _)| mask[*i])
        {
            for (ch, t_ch) in t.iter_mut().enumerate() {
                t_ch.extend(row.iter().map(|w| w[ch]));
            }
            pixel_of_row.push((v, i as u32));
        }
    }
    SphereTransport {
        lights: geometry.len(),
        rows: pixel_of_row.len(),
        t,
        pixel_of_row,
    }
}

/// Radiances of the lights that best explain `references` for this transport, and the
/// remaining error: `relMAE = Σ|T L − I| / Σ|I|` over the masked pixels and channels.
pub fn solve_radiance(tr: &SphereTransport, references: &[Image]) -> (Vec<Vec3>, f64) {
    let k = tr.lights;
    let mut radiance = vec![Vec3::ZERO; k];
    let (mut abs, mut ref_abs) = (0.0f64, 0.0f64);
    for ch in 0..3 {
        let y: Vec<f64> = tr
            .pixel_of_row
            .iter()
            .map(|&(v, i)| references[v].rgb[i as usize][ch] as f64)
            .collect();
        let t = &tr.t[ch];
        let mut g = vec![0.0f64; k * k];
        let mut b = vec![0.0f64; k];
        for (r, yr) in y.iter().enumerate() {
            let row = &t[r * k..(r + 1) * k];
            for a in 0..k {
                b[a] += row[a] as f64 * yr;
                for c in 0..k {
                    g[a * k + c] += row[a] as f64 * row[c] as f64;
                }
            }
        }
        let x = nnls::nnls(
            &g,
            &b,
            1e-12,
            100 * k + 100,
            std::time::Duration::from_secs(10),
        )
        .x;
        for (l, v) in radiance.iter_mut().zip(&x) {
            l[ch] = *v as f32;
        }
        for (r, yr) in y.iter().enumerate() {
            let row = &t[r * k..(r + 1) * k];
            let pred: f64 = row.iter().zip(&x).map(|(&a, &b)| a as f64 * b).sum();
            abs += (pred - yr).abs();
            ref_abs += yr.abs();
        }
    }
    (radiance, abs / ref_abs.max(f64::MIN_POSITIVE))
}
