//! Lat-long (equirectangular) images of an envmap, in the conventions other renderers load.
//!
//! | target | up | pixel (column j, row i) → direction (glTF frame) |
//! | --- | --- | --- |
//! | `mitsuba` (default) | +Y | `u = (j+½)/W`, φ = 2πu = atan2(x, −z); row i at θ = iπ/(H−1): the first and last rows are the poles |
//! | `blender` | +Z (after the glTF importer's (x, y, z) → (x, −z, y)) | `u = (j+½)/W = ½ + atan2(z, x)/2π`, θ = (i+½)π/H from +Y |
//! | `pbrt-v3` | +Z (same axis change) | `u = (j+½)/W`, φ_pbrt = 2πu = atan2(−z, x), θ = (i+½)π/H from +Y |
//!
//! The Mitsuba and Blender mappings were measured in those renderers (docs/design.md);
//! the Mitsuba one is checked by a cross-render in `scripts/`. `box` export point-samples the
//! cell under each pixel centre (so export → import of the same grid is exact); `smooth`
//! interpolates between the grid points (bilinear in θ and φ along the rings).

use std::f64::consts::{PI, TAU};

use glam::{DVec3, Vec3};

use super::Envmap;
use rayon::prelude::*;

use super::grid::direction;
use crate::imageio::Image;

/// Which renderer's lat-long convention to write.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Target {
    Mitsuba,
    Blender,
    PbrtV3,
    /// OpenEXR's lat-long map, which USD's DomeLight (texture format `latlong`, stage +Y up)
    /// adopts: the first and last rows are the poles, the first and last columns both
    /// longitude ±π (−Z), longitude 0 is +Z and π/2 is +X.
    Usd,
}

/// How pixels sample the piecewise-constant map.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Filter {
    /// The cell under the pixel centre (exact round trip).
    Box,
    /// Interpolated between grid points (no visible cell edges).
    Smooth,
}

/// The grid angles of a pixel centre: θ from +Y and φ = atan2(x, −z) in [0, 2π) (see
/// [`super::grid`]). Blender's azimuth a = atan2(z, x) is φ − π/2, pbrt-v3's atan2(−z, x) is
/// π/2 − φ, OpenEXR's longitude atan2(x, z) is π − φ (column j at π − 2πj/(W−1)). Export and
/// import look cells up from these directly: no inverse trigonometry.
pub fn pixel_angles(target: Target, width: u32, height: u32, col: u32, row: u32) -> (f64, f64) {
    let u = (col as f64 + 0.5) / width as f64;
    let centred = (row as f64 + 0.5) * PI / height as f64;
    let pole_to_pole = if height > 1 {
        row as f64 * PI / (height - 1) as f64
    } else {
        PI / 2.0
    };
    match target {
        Target::Mitsuba => (pole_to_pole, TAU * u),
        Target::Usd => (
            pole_to_pole,
            (TAU * col as f64 / (width - 1).max(1) as f64).rem_euclid(TAU),
        ),
        Target::Blender => (centred, (PI / 2.0 + TAU * (u - 0.5)).rem_euclid(TAU)),
        Target::PbrtV3 => (centred, (PI / 2.0 - TAU * u).rem_euclid(TAU)),
    }
}

/// The glTF-frame direction of a pixel centre.
pub fn pixel_direction(target: Target, width: u32, height: u32, col: u32, row: u32) -> DVec3 {
    let (theta, phi) = pixel_angles(target, width, height, col, row);
    direction(theta, phi)
}

/// The solid angle a pixel row stands for (per pixel), for area-weighted averages.
fn pixel_solid_angle(target: Target, width: u32, height: u32, row: u32) -> f64 {
    let (lo, hi) = match target {
        Target::Mitsuba | Target::Usd => {
            let d = PI / (height - 1).max(1) as f64;
            let t = row as f64 * d;
            ((t - 0.5 * d).max(0.0), (t + 0.5 * d).min(PI))
        }
        _ => (
            row as f64 * PI / height as f64,
            (row + 1) as f64 * PI / height as f64,
        ),
    };
    (lo.cos() - hi.cos()) * TAU / width as f64
}

/// Renders the envmap as a `width × width/2` lat-long image (rows in parallel).
pub fn export(env: &Envmap, target: Target, filter: Filter, width: u32) -> Image {
    let height = (width / 2).max(2);
    let mut img = Image::new(width, height);
    img.rgb
        .par_chunks_mut(width as usize)
        .enumerate()
        .for_each(|(row, pixels)| {
            for (col, px) in pixels.iter_mut().enumerate() {
                let (theta, phi) = pixel_angles(target, width, height, col as u32, row as u32);
                *px = match filter {
                    Filter::Box => env.radiance()[env.grid.lookup_angles(theta, phi) as usize],
                    Filter::Smooth => smooth(env, theta, phi),
                };
            }
        });
    img
}

/// Bilinear interpolation between grid points at grid angles (θ, φ): along each of the two
/// nearest rings in φ, then between the rings in θ.
fn smooth(env: &Envmap, theta: f64, phi: f64) -> Vec3 {
    let g = &env.grid;
    if g.rings() == 1 {
        return env.radiance()[0];
    }
    let delta = PI / (g.rings() - 1) as f64;
    let x = theta / delta;
    let r0 = (x.floor() as u32).min(g.rings() - 2);
    let t = (x - r0 as f64).clamp(0.0, 1.0) as f32;
    let along = |ring: u32| {
        let n = g.ring_len(ring);
        let start = g.ring_start(ring);
        let y = phi * n as f64 / TAU;
        let j0 = y.floor() as u32 % n;
        let s = (y - y.floor()) as f32;
        let a = env.radiance()[(start + j0) as usize];
        let b = env.radiance()[(start + (j0 + 1) % n) as usize];
        a * (1.0 - s) + b * s
    };
    along(r0) * (1.0 - t) + along(r0 + 1) * t
}

/// Averages a lat-long image over each cell of an `rings`-ring grid (weighted by pixel solid
/// angle). Errors if the image is too coarse for some cell to contain a pixel centre, or if
/// a pixel is not finite. Small negative values, which captured HDRs carry from their
/// processing (Blender's bundled Poly Haven worlds hold pixels at −5e-5), are averaged in as
/// the noise they are, a cell whose average is negative taken as 0; an image whose negative
/// light exceeds [`crate::imageio::MAX_NEGATIVE_SHARE`] of its positive light (weighted by solid
/// angle) is refused as not radiance.
pub fn import(img: &Image, target: Target, rings: u32) -> std::result::Result<Envmap, String> {
    let grid = super::RingGrid::new(rings);
    let n = grid.cell_count();
    let mut sum = vec![DVec3::ZERO; n];
    let mut weight = vec![0f64; n];
    let (mut positive, mut negative) = (DVec3::ZERO, DVec3::ZERO);
    for row in 0..img.height {
        let w = pixel_solid_angle(target, img.width, img.height, row);
        for col in 0..img.width {
            let c = img.rgb[(row * img.width + col) as usize];
            if !c.is_finite() {
                return Err(format!(
                    "pixel ({col}, {row}) is {:?}; radiance must be finite",
                    c.to_array()
                ));
            }
            let (theta, phi) = pixel_angles(target, img.width, img.height, col, row);
            let cell = grid.lookup_angles(theta, phi) as usize;
            let c = c.as_dvec3() * w;
            sum[cell] += c;
            weight[cell] += w;
            positive += c.max(DVec3::ZERO);
            negative -= c.min(DVec3::ZERO);
        }
    }
    if let Some(why) =
        crate::imageio::negative_share_error(positive.to_array(), negative.to_array())
    {
        return Err(why);
    }
    if let Some(cell) = weight.iter().position(|&w| w == 0.0) {
        return Err(format!(
            "a {}×{} image is too coarse for {rings} rings (cell {cell} contains no pixel centre); use fewer rings or a larger image",
            img.width, img.height
        ));
    }
    let radiance = sum
        .iter()
        .zip(&weight)
        .map(|(s, w)| (*s / *w).max(DVec3::ZERO).as_vec3())
        .collect();
    Envmap::new(rings, radiance)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn varied(rings: u32) -> Envmap {
        let g = super::super::RingGrid::new(rings);
        let radiance = (0..g.cell_count() as u32)
            .map(|c| Vec3::new(c as f32, 1.0 + (c % 5) as f32, 0.5 * g.center(c).y + 0.5))
            .collect();
        Envmap::new(rings, radiance).unwrap()
    }

    #[test]
    fn export_then_import_gives_back_the_cells() {
        for target in [
            Target::Mitsuba,
            Target::Blender,
            Target::PbrtV3,
            Target::Usd,
        ] {
            for rings in [1, 2, 5, 9, 21] {
                let env = varied(rings);
                let img = export(&env, target, Filter::Box, 512);
                let back = import(&img, target, rings).unwrap();
                assert_eq!(back.radiance(), env.radiance(), "{target:?} {rings}");
            }
        }
    }

    #[test]
    fn processing_noise_below_zero_averages_in_and_a_negative_image_is_refused() {
        // A uniform sky of 1 with one pixel in 61 at −0.05 (a captured HDR's processing
        // noise): it imports, each cell the solid-angle mean of its pixels, never below 0.
        let (w, h) = (128, 64);
        let noisy = |v: f32| Image {
            width: w,
            height: h,
            rgb: (0..w * h)
                .map(|i| Vec3::splat(if i % 61 == 7 { v } else { 1.0 }))
                .collect(),
            alpha: None,
        };
        let env = import(&noisy(-0.05), Target::Blender, 5).unwrap();
        for c in env.radiance() {
            assert!((c.x - 1.0).abs() < 0.03 && c.min_element() >= 0.0, "{c}");
        }
        // Half the light negative is no noise: refused, naming the channel.
        let e = import(&noisy(-40.0), Target::Blender, 5).unwrap_err();
        assert!(e.contains("negative") && e.contains("channel 0"), "{e}");
        let e = import(&noisy(f32::NAN), Target::Blender, 5).unwrap_err();
        assert!(e.contains("finite"), "{e}");
    }

    #[test]
    fn pixel_angles_are_the_angles_of_the_pixel_direction() {
        use super::super::grid::angles;
        for target in [Target::Mitsuba, Target::Blender, Target::PbrtV3] {
            let (w, h) = (24, 12);
            for row in 1..h - 1 {
                for col in 0..w {
                    let (t, p) = pixel_angles(target, w, h, col, row);
                    let d = pixel_direction(target, w, h, col, row);
                    let (t2, p2) = angles(d.as_vec3());
                    let dp = (p - p2).abs();
                    assert!((t - t2).abs() < 1e-6, "{target:?} ({col}, {row})");
                    assert!(
                        dp.min(TAU - dp) < 1e-6,
                        "{target:?} ({col}, {row}): {p} vs {p2}"
                    );
                }
            }
        }
    }

    #[test]
    fn mitsuba_rows_are_poles_and_columns_follow_u() {
        let (w, h) = (64, 32);
        // OpenEXR / USD: longitude atan2(x, z) = π − 2πj/(W−1), latitude from +π/2 at row 0.
        for (col, row) in [(0, 3), (7, 2), (11, 5), (23, 6)] {
            let d = pixel_direction(Target::Usd, 24, 12, col, row);
            let lon = d.x.atan2(d.z);
            let want = PI - TAU * col as f64 / 23.0;
            let dl = (lon - want).rem_euclid(TAU);
            assert!(dl.min(TAU - dl) < 1e-9, "column {col}: {lon} vs {want}");
            let lat = d.y.asin();
            assert!((lat - (PI / 2.0 - PI * row as f64 / 11.0)).abs() < 1e-9);
        }
        assert!((pixel_direction(Target::Mitsuba, w, h, 5, 0) - DVec3::Y).length() < 1e-12);
        assert!((pixel_direction(Target::Mitsuba, w, h, 5, h - 1) + DVec3::Y).length() < 1e-12);
        // u = atan2(x, −z) / 2π: the column at u = 0.25 (+X) on the horizon row.
        let hd = Target::Mitsuba;
        let d = pixel_direction(hd, 4, 3, 1, 1); // u = 0.375, θ = π/2
        let u = d.x.atan2(-d.z) / TAU;
        assert!((u - 0.375).abs() < 1e-12 && d.y.abs() < 1e-12);
    }

    #[test]
    fn blender_convention_matches_measurement() {
        // Measured in Blender: u = ½ + atan2(g.z, g.x)/2π, v = acos(g.y)/π, both pixel-centred.
        let (w, h) = (16, 8);
        for (col, row) in [(0, 0), (3, 5), (15, 7)] {
            let d = pixel_direction(Target::Blender, w, h, col, row);
            let u = 0.5 + d.z.atan2(d.x) / TAU;
            let v = d.y.acos() / PI;
            assert!((u - (col as f64 + 0.5) / w as f64).abs() < 1e-12);
            assert!((v - (row as f64 + 0.5) / h as f64).abs() < 1e-12);
        }
    }

    #[test]
    fn smooth_filter_keeps_constants_and_stays_in_range() {
        let env = Envmap::constant(9, Vec3::splat(2.0));
        let img = export(&env, Target::Mitsuba, Filter::Smooth, 64);
        assert!(
            img.rgb
                .iter()
                .all(|c| (*c - Vec3::splat(2.0)).abs().max_element() < 1e-5)
        );
        let env = varied(9);
        let img = export(&env, Target::Mitsuba, Filter::Smooth, 64);
        let hi = env.radiance().iter().fold(Vec3::ZERO, |a, b| a.max(*b));
        assert!(img.rgb.iter().all(|c| c.cmple(hi + 1e-4).all()));
    }

    #[test]
    fn too_coarse_import_is_an_error() {
        let img = export(&varied(3), Target::Mitsuba, Filter::Box, 8);
        assert!(
            import(&img, Target::Mitsuba, 40)
                .unwrap_err()
                .contains("too coarse")
        );
    }
}
