//! Photometric error between an image and a reference, and an error heat map.
//!
//! Over the masked-in pixels P and channels c, with x the image and r the reference:
//! `MAE = Σ|x−r| / 3|P|`, `RMSE = √(Σ(x−r)² / 3|P|)`, `relMAE = Σ|x−r| / Σ|r|` (the headline,
//! scale-free), `relMSE = Σ(x−r)² / Σr²`, `PSNR = 10·log10(peak² / MSE)` with peak the largest
//! reference value over P. The mask excludes pixels that see no scene geometry: lightprobe
//! writes, as each image's alpha, the fraction of camera samples that hit geometry, and a pixel
//! counts when the reference's alpha is > 0. A reference without alpha masks nothing.

use serde::Serialize;

use crate::error::{Error, Result};
use crate::imageio::Image;

/// Error figures of an image against a reference.
#[derive(Debug, Clone, Copy, Serialize, PartialEq, schemars::JsonSchema)]
pub struct Metrics {
    /// Pixels compared (in the mask).
    pub pixels: usize,
    /// Pixels left out by the mask (background).
    pub masked_out: usize,
    pub mae: f64,
    pub rmse: f64,
    /// Σ|x − r| / Σ|r| (null when the reference is black).
    #[schemars(with = "Option<f64>")]
    pub rel_mae: f64,
    /// Σ(x − r)² / Σr² (null when the reference is black).
    #[schemars(with = "Option<f64>")]
    pub rel_mse: f64,
    /// 10 log10(peak² / MSE), dB (null for identical images).
    #[schemars(with = "Option<f64>")]
    pub psnr: f64,
    /// Mean RGB of the image and of the reference over the mask.
    pub mean: [f64; 3],
    pub mean_reference: [f64; 3],
}

/// The mask of a reference: its alpha > 0, or every pixel if it has no alpha.
pub fn mask_of(reference: &Image) -> Vec<bool> {
    match &reference.alpha {
        Some(a) => a.iter().map(|&v| v > 0.0).collect(),
        None => vec![true; reference.rgb.len()],
    }
}

/// Compares `image` with `reference` over `mask` (see the module doc for definitions).
pub fn compare(image: &Image, reference: &Image, mask: &[bool]) -> Result<Metrics> {
    if (image.width, image.height) != (reference.width, reference.height) {
        return Err(Error::Invalid(format!(
            "images differ in size: {}×{} vs {}×{}",
            image.width, image.height, reference.width, reference.height
        )));
    }
    let (mut abs, mut sq, mut ref_abs, mut ref_sq, mut peak) = (0f64, 0f64, 0f64, 0f64, 0f64);
    let (mut sum_x, mut sum_r) = (glam::DVec3::ZERO, glam::DVec3::ZERO);
    let mut pixels = 0usize;
    for ((x, r), &m) in image.rgb.iter().zip(&reference.rgb).zip(mask) {
        if !m {
            continue;
        }
        pixels += 1;
        let (x, r) = (x.as_dvec3(), r.as_dvec3());
        let d = x - r;
        abs += d.abs().element_sum();
        sq += d.length_squared();
        ref_abs += r.abs().element_sum();
        ref_sq += r.length_squared();
        peak = peak.max(r.max_element());
        sum_x += x;
        sum_r += r;
    }
    if pixels == 0 {
        return Err(Error::Invalid(
            "no pixel to compare: the reference's mask is empty".into(),
        ));
    }
    let n = 3.0 * pixels as f64;
    let mse = sq / n;
    let ratio = |a: f64, b: f64| {
        if b > 0.0 {
            a / b
        } else if a == 0.0 {
            0.0
        } else {
            f64::INFINITY
        }
    };
    Ok(Metrics {
        pixels,
        masked_out: mask.len() - pixels,
        mae: abs / n,
        rmse: mse.sqrt(),
        rel_mae: ratio(abs, ref_abs),
        rel_mse: ratio(sq, ref_sq),
        psnr: if mse > 0.0 && peak > 0.0 {
            10.0 * (peak * peak / mse).log10()
        } else {
            f64::INFINITY
        },
        mean: (sum_x / pixels as f64).to_array(),
        mean_reference: (sum_r / pixels as f64).to_array(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn img(values: &[f32], alpha: Option<Vec<f32>>) -> Image {
        Image {
            width: values.len() as u32,
            height: 1,
            rgb: values.iter().map(|&v| glam::Vec3::splat(v)).collect(),
            alpha,
        }
    }

    #[test]
    fn metrics_match_hand_computation() {
        let r = img(&[1.0, 2.0, 3.0, 4.0], None);
        let x = img(&[1.5, 2.0, 2.0, 4.0], None);
        let m = compare(&x, &r, &mask_of(&r)).unwrap();
        assert_eq!(m.pixels, 4);
        assert!((m.mae - 1.5 / 4.0).abs() < 1e-12);
        assert!((m.rmse - (1.25f64 / 4.0).sqrt()).abs() < 1e-12);
        assert!((m.rel_mae - 1.5 / 10.0).abs() < 1e-12);
        assert!((m.rel_mse - 1.25 / 30.0).abs() < 1e-12);
        assert!((m.psnr - 10.0 * (16.0f64 / (1.25 / 4.0)).log10()).abs() < 1e-9);
    }

    #[test]
    fn identical_images_have_zero_error() {
        let r = img(&[0.3, 0.0, 7.0], None);
        let m = compare(&r, &r, &mask_of(&r)).unwrap();
        assert_eq!((m.mae, m.rel_mae, m.rel_mse), (0.0, 0.0, 0.0));
        assert!(m.psnr.is_infinite());
    }

    #[test]
    fn mask_excludes_background() {
        let r = img(&[1.0, 0.0], Some(vec![1.0, 0.0]));
        let x = img(&[1.0, 50.0], None);
        let m = compare(&x, &r, &mask_of(&r)).unwrap();
        assert_eq!((m.pixels, m.masked_out), (1, 1));
        assert_eq!(m.rel_mae, 0.0);
    }

    #[test]
    fn size_mismatch_is_an_error() {
        let e = compare(&img(&[1.0], None), &img(&[1.0, 2.0], None), &[true, true]).unwrap_err();
        assert!(e.to_string().contains("differ in size"));
    }
}
