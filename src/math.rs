//! Fast f32 arithmetic for the tracer's inner loops: trigonometry inline and branch-free
//! (loops over lanes vectorise), within a few 10⁻⁷ of libm, where a libm call per sample cost
//! percents of a render; and rounding without library calls, exact.

/// (sin 2πu, cos 2πu) for `u` in [0, 1], within 2·10⁻⁷: the octant's centre, then short
/// Taylor series over ±π/8. A libm `sincosf` call per BSDF and light sample was 2.8% of a
/// render. No table and no branches, so loops over lanes vectorise.
#[inline]
pub fn sin_cos_2pi(u: f32) -> (f32, f32) {
    // (sin, cos) of π/8 and 3π/8: the centres of the first quadrant's two octants.
    const S: f32 = 0.382_683_43;
    const C: f32 = 0.923_879_5;
    let x = 8.0 * u;
    let k = (x as u32).min(7);
    let t = (x - k as f32 - 0.5) * std::f32::consts::FRAC_PI_4;
    let t2 = t * t;
    let sin_t = t * (1.0 - t2 * (1.0 / 6.0 - t2 * (1.0 / 120.0 - t2 * (1.0 / 5040.0))));
    let cos_t = 1.0 - t2 * (0.5 - t2 * (1.0 / 24.0 - t2 * (1.0 / 720.0)));
    // Octant k's centre (k + ½)·π/4: the quadrant's octant, turned by k / 2 quarter turns.
    let (s, c) = if k & 1 != 0 { (C, S) } else { (S, C) };
    let (s, c) = if k & 2 != 0 { (c, -s) } else { (s, c) };
    let (s, c) = if k & 4 != 0 { (-s, -c) } else { (s, c) };
    (s * cos_t + c * sin_t, c * cos_t - s * sin_t)
}

/// `y.atan2(x)` in [−π, π], within 3·10⁻⁷ rad, inline: the ratio of the smaller to the larger
/// magnitude reduced to [0, tan π/8] and Cephes' `atanf` polynomial, then the octant restored
/// by selects. (The libm call was ~4% of an envmap render, for the sector of every escaping
/// ray.) `atan2(0, 0)` is 0.
#[inline]
pub fn atan2(y: f32, x: f32) -> f32 {
    use std::f32::consts::{FRAC_PI_2, FRAC_PI_4, PI};
    let (ax, ay) = (x.abs(), y.abs());
    let (lo, hi) = (ax.min(ay), ax.max(ay));
    let t = if hi > 0.0 { lo / hi } else { 0.0 };
    let big = t > 0.414_213_57; // tan π/8
    let z = if big { (t - 1.0) / (t + 1.0) } else { t };
    let z2 = z * z;
    let p = (((8.053_744_5e-2 * z2 - 1.387_768_6e-1) * z2 + 1.997_771_1e-1) * z2 - 3.333_295e-1)
        * z2
        * z
        + z;
    let a = if big { FRAC_PI_4 + p } else { p };
    let a = if ay > ax { FRAC_PI_2 - a } else { a };
    let a = if x < 0.0 { PI - a } else { a };
    if y < 0.0 { -a } else { a }
}

/// `x.floor()`, exactly (sign of zero and NaN included), without a library call: the
/// baseline x86-64 target has no rounding instruction (SSE4.1's `roundss`), so `f32::floor`
/// is a call to libm's `floorf` there.
#[inline]
pub fn floor(x: f32) -> f32 {
    // Every f32 of magnitude 2²³ or more is an integer, and NaN stays NaN.
    if x.is_nan() || x.abs() >= 8_388_608.0 {
        return x;
    }
    let t = x as i32 as f32;
    let t = if t > x { t - 1.0 } else { t };
    if t == 0.0 { t.copysign(x) } else { t }
}

/// `x.fract()` for `x` ≥ 0 below 2⁶⁴, exactly, without a library call (see [`floor`]).
#[inline]
pub fn fract_nonnegative(x: f64) -> f64 {
    debug_assert!((0.0..1.8e19).contains(&x));
    x - (x as u64) as f64
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sampling::{Rng, uniform_sphere};

    #[test]
    fn floor_and_fract_are_the_library_ones_bit_for_bit() {
        let mut r = Rng::new(5);
        let specials = [
            0.0,
            -0.0,
            0.5,
            -0.5,
            1.0,
            -1.0,
            -1e-30,
            8_388_607.5,
            -8_388_607.5,
            8_388_608.0,
            3e9,
            -3e9,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
        ];
        let random = (0..100_000).map(|i| {
            let scale = [1.0, 100.0, 1e6, 1e9][i % 4];
            (r.next_f32() - 0.5) * scale
        });
        for x in specials.into_iter().chain(random) {
            assert_eq!(floor(x).to_bits(), x.floor().to_bits(), "floor({x})");
        }
        for i in 0..100_000u32 {
            let x = r.next_f32() as f64 + i as f64 * 0.754_877_666_246_692_8;
            assert_eq!(
                fract_nonnegative(x).to_bits(),
                x.fract().to_bits(),
                "fract({x})"
            );
        }
    }

    #[test]
    fn sin_cos_2pi_matches_the_library_everywhere() {
        let mut worst = 0f64;
        for i in 0..=1_000_000u32 {
            let u = i as f32 / 1_000_000.0;
            let (s, c) = sin_cos_2pi(u);
            let (s64, c64) = (std::f64::consts::TAU * u as f64).sin_cos();
            worst = worst
                .max((s as f64 - s64).abs())
                .max((c as f64 - c64).abs());
        }
        assert!(worst < 2e-7, "worst error {worst:e}");
    }

    #[test]
    fn inline_arctangent_matches_libm() {
        let mut r = Rng::new(17);
        for i in 0..200_000 {
            let (y, x) = match i {
                0 => (0.0, 0.0),
                1 => (0.0, -1.0),
                2 => (-1.0, 0.0),
                3 => (1.0, 1.0),
                _ => {
                    let d = uniform_sphere(r.next_2d());
                    (d.x, d.z * [1.0, 1e-3, 1e3][i % 3])
                }
            };
            let err = (atan2(y, x) as f64 - (y as f64).atan2(x as f64)).abs();
            assert!(err < 3e-7, "atan2({y}, {x}) off by {err}");
        }
    }
}
