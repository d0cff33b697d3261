//! Photometric error between an image and a reference, and an error heat map.
//!
//! Over the masked-in pixels P and channels c, with x the image and r the reference:
//! `MAE = Σ|x−r| / 3|P|`, `RMSE = √(Σ(x−r)² / 3|P|)`, `relMAE = Σ|x−r| / Σ|r|` (the headline,
//! scale-free), `relMSE = Σ(x−r)² / Σr²`, `PSNR = 10·log10(peak² / MSE)` with peak the largest
//! reference value over P. The mask excludes pixels that see no scene geometry: lightprobe
//! writes, as each image's alpha, the fraction of camera samples that hit geometry, and a pixel
//! counts when the reference's alpha is > 0. A reference without alpha masks nothing.

use std::path::Path;

use glam::Vec3;
use serde::Serialize;

use crate::error::{Error, Result};
use crate::imageio::{Image, write_rgb8_png};

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

/// Per-pixel mean absolute error over the channels (0 outside the mask).
pub fn error_map(image: &Image, reference: &Image, mask: &[bool]) -> Vec<f32> {
    image
        .rgb
        .iter()
        .zip(&reference.rgb)
        .zip(mask)
        .map(|((x, r), &m)| {
            if m {
                (*x - *r).abs().element_sum() / 3.0
            } else {
                0.0
            }
        })
        .collect()
}

/// Writes the error heat map as a PNG: the per-pixel mean absolute error mapped through a
/// perceptual colour map from 0 to `scale` (default: the 99th percentile of the error), with a
/// colour bar labelled in the image's units. Masked-out pixels are grey. Returns the scale.
pub fn write_heatmap(
    path: &Path,
    image: &Image,
    reference: &Image,
    mask: &[bool],
    scale: Option<f32>,
) -> Result<f32> {
    let err = error_map(image, reference, mask);
    let scale = scale.unwrap_or_else(|| {
        let mut v: Vec<f32> = err
            .iter()
            .zip(mask)
            .filter(|(_, m)| **m)
            .map(|(e, _)| *e)
            .collect();
        if v.is_empty() {
            return 1.0;
        }
        let k = ((v.len() - 1) as f32 * 0.99) as usize;
        let (_, p, _) = v.select_nth_unstable_by(k, f32::total_cmp);
        if *p > 0.0 { *p } else { 1.0 }
    });
    let (w, h) = (image.width as usize, image.height as usize);
    let zoom = (512 / w.max(1)).clamp(1, 8);
    let (iw, ih) = (w * zoom, h * zoom);
    let bar_w = 90;
    let (cw, ch) = (iw + bar_w, ih.max(120));
    let mut canvas = vec![[255u8; 3]; cw * ch];
    for y in 0..ih {
        for x in 0..iw {
            let i = (y / zoom) * w + x / zoom;
            canvas[y * cw + x] = if mask[i] {
                colormap(err[i] / scale)
            } else {
                [96, 96, 96]
            };
        }
    }
    // Colour bar: top = scale, bottom = 0.
    let (bx, by0, by1) = (iw + 10, 12, ch - 12);
    for y in by0..by1 {
        let c = colormap(1.0 - (y - by0) as f32 / (by1 - by0 - 1) as f32);
        for x in bx..bx + 16 {
            canvas[y * cw + x] = c;
        }
    }
    draw_text(&mut canvas, cw, bx + 20, by0 - 2, &fmt_label(scale));
    draw_text(
        &mut canvas,
        cw,
        bx + 20,
        (by0 + by1) / 2 - 5,
        &fmt_label(scale / 2.0),
    );
    draw_text(&mut canvas, cw, bx + 20, by1 - 10, "0");
    let bytes = canvas.into_iter().flatten().collect();
    write_rgb8_png(path, cw as u32, ch as u32, bytes)?;
    Ok(scale)
}

fn fmt_label(v: f32) -> String {
    if (0.01..1000.0).contains(&v) {
        format!("{v:.3}")
    } else {
        format!("{v:.1e}")
    }
}

/// A perceptual dark-to-bright colour map (inferno-like control points), t in [0, 1].
pub fn colormap(t: f32) -> [u8; 3] {
    const STOPS: [Vec3; 7] = [
        Vec3::new(0.0, 0.0, 0.016),
        Vec3::new(0.16, 0.04, 0.34),
        Vec3::new(0.40, 0.08, 0.43),
        Vec3::new(0.64, 0.17, 0.36),
        Vec3::new(0.87, 0.32, 0.20),
        Vec3::new(0.98, 0.58, 0.04),
        Vec3::new(0.99, 1.0, 0.64),
    ];
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        1.0
    } * (STOPS.len() - 1) as f32;
    let i = (t as usize).min(STOPS.len() - 2);
    let c = STOPS[i].lerp(STOPS[i + 1], t - i as f32);
    (c * 255.0 + 0.5).to_array().map(|v| v as u8)
}

/// 3×5 glyphs (rows top to bottom, 3 bits each, MSB left) for the labels' characters.
fn glyph(c: char) -> [u8; 5] {
    match c {
        '0' => [7, 5, 5, 5, 7],
        '1' => [2, 6, 2, 2, 7],
        '2' => [7, 1, 7, 4, 7],
        '3' => [7, 1, 7, 1, 7],
        '4' => [5, 5, 7, 1, 1],
        '5' => [7, 4, 7, 1, 7],
        '6' => [7, 4, 7, 5, 7],
        '7' => [7, 1, 2, 2, 2],
        '8' => [7, 5, 7, 5, 7],
        '9' => [7, 5, 7, 1, 7],
        '.' => [0, 0, 0, 0, 2],
        '-' => [0, 0, 7, 0, 0],
        '+' => [0, 2, 7, 2, 0],
        'e' => [0, 7, 7, 4, 7],
        _ => [0; 5],
    }
}

/// Draws black text at (x, y), each glyph pixel 2×2.
fn draw_text(canvas: &mut [[u8; 3]], width: usize, x: usize, y: usize, text: &str) {
    for (k, c) in text.chars().enumerate() {
        for (row, bits) in glyph(c).iter().enumerate() {
            for col in 0..3 {
                if bits & (4 >> col) != 0 {
                    for (dy, dx) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
                        let (px, py) = (x + k * 8 + col * 2 + dx, y + row * 2 + dy);
                        if let Some(p) = canvas.get_mut(py * width + px).filter(|_| px < width) {
                            *p = [0, 0, 0];
                        }
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn img(values: &[f32], alpha: Option<Vec<f32>>) -> Image {
        Image {
            width: values.len() as u32,
            height: 1,
            rgb: values.iter().map(|&v| Vec3::splat(v)).collect(),
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

    #[test]
    fn colormap_is_monotone_in_brightness() {
        let lum = |c: [u8; 3]| 0.2126 * c[0] as f32 + 0.7152 * c[1] as f32 + 0.0722 * c[2] as f32;
        let mut last = -1.0;
        for i in 0..=100 {
            let l = lum(colormap(i as f32 / 100.0));
            assert!(l >= last - 0.5, "{i}");
            last = l;
        }
    }
}
