//! The noise an image carries, measured from the images themselves, and a test of whether a
//! model's residual is more than that noise.
//!
//! Monte Carlo noise and sensor noise are independent from pixel to pixel, while what a
//! lighting model gets wrong (a light misplaced, a bounce missing) changes smoothly across the
//! image. So in a residual `r = reference − render` the difference of two neighbouring pixels
//! holds the noise of both: `E[(r_i − r_j)²] / 2` is the noise variance there. Summed over the
//! image it is what the residual's `Σ r²` would be if the model explained everything but the
//! noise; the ratio of the two is the test statistic (1 within noise). Where twins are known
//! (lightprobe rendered the references, so it can render their lights again; or the user gives
//! a second capture of each view), their differences give the noise instead, exactly.
//!
//! Caveats of the neighbouring pixels, stated where the figures are reported. Misfit is not
//! smooth at 100-pixel scales: albedo texture modulates it and near lights' shadow edges are
//! sharp, so part of any misfit reads as noise. On the bundled scene's 9-ring envmap the
//! twin says the residual is 220–370× the noise, the neighbours 5–7×: a misfit found this way
//! is real, its size a lower bound, and the noise floor an upper bound. Noise correlated
//! between neighbours (a demosaiced photograph, a blue-noise sampler) reads as less noise than
//! there is, so as misfit.

use serde::Serialize;

use glam::Vec3;

use crate::imageio::Image;

/// Side of the square blocks of pixels whose sums make the test's samples: wide enough that
/// blocks are nearly independent (a pixel's variance estimate uses its neighbours), small
/// enough that an image holds hundreds.
const BLOCK: u32 = 16;

/// What one view's (or several views') residual holds, for the noise floor and the test.
#[derive(Debug, Clone, Default)]
pub struct ResidualNoise {
    /// Pixels counted: in the mask, with at least one neighbour in it.
    pub pixels: usize,
    /// `Σ r²` over those pixels and the three channels.
    pub residual_sq: f64,
    /// The noise's share of it: `Σ_i mean_j Σ_c (r_ic − r_jc)² / 2` over each pixel's
    /// neighbours j in the mask.
    pub noise_sq: f64,
    /// `Σ_i mean_j Σ_c |r_ic − r_jc| / √2`: the residual's absolute sum that the noise alone
    /// gives (exact for Gaussian noise), the numerator of the noise floor's relMAE.
    pub noise_abs: f64,
    /// `Σ |reference|` over the same pixels and channels.
    pub reference_abs: f64,
    /// Per block of [`BLOCK`]² pixels, `Σ r² − noise²`: zero in expectation where the model
    /// explains the images.
    blocks: Vec<f64>,
}

/// The fit test: is the residual more than the noise?
#[derive(Debug, Clone, Copy, PartialEq, Serialize, schemars::JsonSchema)]
pub struct FitTest {
    /// The residual's `Σ r²` over what the noise explains (1 = within noise). Its square
    /// root is the residual's RMS over the noise's.
    pub residual_over_noise: f64,
    /// The excess in standard errors: the blocks' sum over its standard error (from their
    /// spread), as the normal deviate of the same tail probability.
    pub z: f64,
    /// One-sided p-value of an excess at least this large if the model explained the images.
    pub p_value: f64,
    /// Pixels tested.
    pub pixels: usize,
    /// `(Σ r² − the noise's share) / pixels`: the misfit's own energy per pixel, comparable
    /// between runs whose noise differs.
    pub excess_per_pixel: f64,
}

impl ResidualNoise {
    /// Measures the residual `reference − render` over `mask` (pixels in both images' order),
    /// its noise from `noise` where given (per pixel, a sample of the residual's noise from
    /// twins: its `Σ n²` is then the noise's share exactly), else from neighbouring pixels.
    /// Images of different sizes give an empty measure.
    pub fn of(
        reference: &Image,
        render: &Image,
        mask: &[bool],
        noise: Option<&[Vec3]>,
    ) -> ResidualNoise {
        let (w, h) = (reference.width as usize, reference.height as usize);
        let mut out = ResidualNoise::default();
        let same = |i: &Image| (i.width, i.height) == (reference.width, reference.height);
        if !same(render)
            || noise.is_some_and(|n| n.len() != w * h)
            || mask.len() != w * h
            || reference.rgb.len() != w * h
        {
            return out;
        }
        let r = |i: usize| (reference.rgb[i] - render.rgb[i]).as_dvec3();
        let (bw, bh) = (w.div_ceil(BLOCK as usize), h.div_ceil(BLOCK as usize));
        let mut blocks = vec![0.0f64; bw * bh];
        let mut used = vec![false; bw * bh];
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                if !mask[i] {
                    continue;
                }
                let ri = r(i);
                let (noise_sq, noise_abs) = match noise {
                    Some(n) => {
                        let d = n[i].as_dvec3();
                        (d.length_squared(), d.abs().element_sum())
                    }
                    None => {
                        let (mut n, mut sq, mut abs) = (0u32, 0.0f64, 0.0f64);
                        let neighbours = [
                            (x > 0).then(|| i - 1),
                            (x + 1 < w).then(|| i + 1),
                            (y > 0).then(|| i - w),
                            (y + 1 < h).then(|| i + w),
                        ];
                        for j in neighbours.into_iter().flatten().filter(|&j| mask[j]) {
                            let d = ri - r(j);
                            n += 1;
                            sq += d.length_squared() / 2.0;
                            abs += d.abs().element_sum() / std::f64::consts::SQRT_2;
                        }
                        if n == 0 {
                            continue;
                        }
                        (sq / n as f64, abs / n as f64)
                    }
                };
                let own = ri.length_squared();
                out.pixels += 1;
                out.residual_sq += own;
                out.noise_sq += noise_sq;
                out.noise_abs += noise_abs;
                out.reference_abs += reference.rgb[i].as_dvec3().abs().element_sum();
                let b = (y / BLOCK as usize) * bw + x / BLOCK as usize;
                blocks[b] += own - noise_sq;
                used[b] = true;
            }
        }
        out.blocks = blocks
            .into_iter()
            .zip(used)
            .filter(|(_, u)| *u)
            .map(|(b, _)| b)
            .collect();
        out
    }

    /// Several views' measures as one.
    pub fn pooled<'a>(parts: impl IntoIterator<Item = &'a ResidualNoise>) -> ResidualNoise {
        let mut out = ResidualNoise::default();
        for p in parts {
            out.pixels += p.pixels;
            out.residual_sq += p.residual_sq;
            out.noise_sq += p.noise_sq;
            out.noise_abs += p.noise_abs;
            out.reference_abs += p.reference_abs;
            out.blocks.extend_from_slice(&p.blocks);
        }
        out
    }

    /// The noise floor: the relMAE that the noise alone gives a perfect model's render
    /// (None without pixels or with a black reference).
    pub fn rel_mae(&self) -> Option<f64> {
        let v = self.noise_abs / self.reference_abs;
        v.is_finite().then_some(v)
    }

    /// The fit test (None without pixels, or where the images hold no noise to compare with).
    pub fn test(&self) -> Option<FitTest> {
        if self.pixels == 0 || self.noise_sq <= 0.0 {
            return None;
        }
        // A t statistic over the blocks: their sum over its standard error, estimated from
        // their spread about their mean (blocks differ in noise; the spread says by how much).
        let b = self.blocks.len() as f64;
        let sum: f64 = self.blocks.iter().sum();
        let mean = sum / b;
        let spread = (self.blocks.iter().map(|v| (v - mean).powi(2)).sum::<f64>() * b
            / (b - 1.0).max(1.0))
        .sqrt();
        let t = if spread > 0.0 {
            sum / spread
        } else if sum > 0.0 {
            f64::INFINITY
        } else {
            0.0
        };
        // The statistic is a Student t with ν = b − 1 degrees of freedom, mapped to the normal
        // deviate of the same tail, `z = √((ν − ½) ln(1 + t²/ν))` (Wallace's approximation:
        // within 2% of z for ν ≥ 3 at the 97.5% to 99.95% quantiles, checked against tables),
        // so that a small image's few blocks do not overstate significance.
        let nu = (b - 1.0).max(1.0);
        let z = if t.is_finite() {
            t.signum() * ((nu - 0.5) * (t * t / nu).ln_1p()).sqrt()
        } else {
            t
        };
        Some(FitTest {
            residual_over_noise: self.residual_sq / self.noise_sq,
            z,
            p_value: 0.5 * libm::erfc(z / std::f64::consts::SQRT_2),
            pixels: self.pixels,
            excess_per_pixel: (self.residual_sq - self.noise_sq) / self.pixels as f64,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    /// A reference of a smooth ramp plus Gaussian noise of standard deviation `sigma(x, y)`,
    /// and a render of the ramp (× `gain`) without noise.
    fn pair(gain: f32, sigma: impl Fn(u32, u32) -> f32, seed: u64) -> (Image, Image) {
        let (w, h) = (96u32, 64u32);
        let mut rng = seed;
        let mut uniform = || {
            rng = rng
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((rng >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        let mut gauss = || {
            let (a, b) = (uniform(), uniform());
            ((-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()) as f32
        };
        let signal = |x: u32, y: u32| {
            Vec3::splat(0.2 + 0.6 * (x as f32 / w as f32) + 0.1 * (y as f32 / h as f32))
        };
        let mut reference = Image::new(w, h);
        let mut render = Image::new(w, h);
        for y in 0..h {
            for x in 0..w {
                let i = (y * w + x) as usize;
                let s = sigma(x, y);
                reference.rgb[i] = signal(x, y) + Vec3::new(gauss(), gauss(), gauss()) * s;
                render.rgb[i] = signal(x, y) * gain;
            }
        }
        (reference, render)
    }

    #[test]
    fn noise_alone_measures_its_own_variance_and_passes_the_test() {
        let mask = vec![true; 96 * 64];
        let mut ratios = Vec::new();
        let mut small_p = 0;
        for seed in 0..40 {
            // Heteroscedastic: noise 4× stronger on the right half.
            let (reference, render) = pair(1.0, |x, _| if x < 48 { 0.01 } else { 0.04 }, seed);
            let m = ResidualNoise::of(&reference, &render, &mask, None);
            let t = m.test().unwrap();
            ratios.push(t.residual_over_noise);
            small_p += (t.p_value < 0.05) as usize;
            // The noise floor: E|n| = σ√(2/π) per channel.
            let expected = (0.01 + 0.04) / 2.0 * (2.0 / std::f64::consts::PI).sqrt() * 3.0;
            let floor = m.noise_abs / m.pixels as f64;
            assert!(
                (floor / expected - 1.0).abs() < 0.05,
                "{floor} vs {expected}"
            );
        }
        let mean = ratios.iter().sum::<f64>() / ratios.len() as f64;
        assert!((mean - 1.0).abs() < 0.01, "mean ratio {mean}");
        // About 5% of 40 trials fall below p = 0.05 by chance; far more would mean the test
        // is miscalibrated.
        assert!(
            small_p <= 6,
            "{small_p} of 40 pure-noise trials had p < 0.05"
        );
    }

    #[test]
    fn a_smooth_misfit_half_the_noise_is_found() {
        let mask = vec![true; 96 * 64];
        // The render 3% too bright: on a signal of ~0.55 that is ~0.017, against noise 0.03.
        let (reference, render) = pair(1.03, |_, _| 0.03, 7);
        let t = ResidualNoise::of(&reference, &render, &mask, None)
            .test()
            .unwrap();
        assert!(t.residual_over_noise > 1.2 && t.p_value < 1e-6, "{t:?}");
        // Pooling two views keeps the verdict; a view with no noise and no residual adds
        // nothing.
        let clean = ResidualNoise::of(&render, &render, &mask, None);
        assert_eq!(clean.test(), None);
        let both =
            ResidualNoise::pooled([&ResidualNoise::of(&reference, &render, &mask, None), &clean]);
        assert_eq!(
            both.test().unwrap().residual_over_noise,
            t.residual_over_noise
        );
    }

    #[test]
    fn masked_out_pixels_and_lone_pixels_are_not_counted() {
        let (reference, render) = pair(1.0, |_, _| 0.02, 3);
        // A checkerboard mask leaves every pixel without a neighbour.
        let mask: Vec<bool> = (0..96 * 64).map(|i| (i % 96 + i / 96) % 2 == 0).collect();
        let m = ResidualNoise::of(&reference, &render, &mask, None);
        assert_eq!((m.pixels, m.test()), (0, None));
        assert_eq!(m.rel_mae(), None);
    }
}
