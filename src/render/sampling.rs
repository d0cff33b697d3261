//! Random numbers and warps. Every stream is seeded from (seed, stream, pixel, sample), so an
//! image is the same whatever the thread count or tile order.

use std::f32::consts::{PI, TAU};

use glam::{Vec2, Vec3};

/// SplitMix64's finaliser: a fast, well-mixed 64-bit hash.
#[inline]
pub fn mix64(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// PCG32 (O'Neill): small state, good statistics, cheap to seed per sample.
#[derive(Debug, Clone)]
pub struct Rng {
    state: u64,
    inc: u64,
}

impl Rng {
    /// A stream determined by `key` (hash several counters into it with [`mix64`]).
    #[inline]
    pub fn new(key: u64) -> Rng {
        let mut r = Rng {
            state: 0,
            inc: (mix64(key ^ 0x5851_F42D_4C95_7F2D) << 1) | 1,
        };
        r.next_u32();
        r.state = r.state.wrapping_add(mix64(key));
        r.next_u32();
        r
    }

    #[inline]
    pub fn next_u32(&mut self) -> u32 {
        let old = self.state;
        self.state = old
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(self.inc);
        let xorshifted = (((old >> 18) ^ old) >> 27) as u32;
        let rot = (old >> 59) as u32;
        xorshifted.rotate_right(rot)
    }

    /// The stream `n` draws ahead of this one (a cheap second stream: a consumer that never
    /// draws more than `n` numbers from this one never overlaps it).
    #[inline]
    pub fn ahead(&self, n: u32) -> Rng {
        let mut r = self.clone();
        for _ in 0..n {
            r.state = r
                .state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(r.inc);
        }
        r
    }

    /// Uniform in [0, 1).
    #[inline]
    pub fn next_f32(&mut self) -> f32 {
        (self.next_u32() >> 8) as f32 * (1.0 / (1u32 << 24) as f32)
    }

    #[inline]
    pub fn next_2d(&mut self) -> Vec2 {
        Vec2::new(self.next_f32(), self.next_f32())
    }
}

/// The R2 low-discrepancy sequence (Roberts' generalised golden ratio), point `i` shifted by
/// `offset` (Cranley–Patterson rotation). With a random offset each point is uniform, and the
/// points of one pixel are well stratified.
#[inline]
pub fn r2(i: u32, offset: Vec2) -> Vec2 {
    const A1: f64 = 0.754_877_666_246_692_8;
    const A2: f64 = 0.569_840_290_998_053_3;
    let x = (offset.x as f64 + i as f64 * A1).fract();
    let y = (offset.y as f64 + i as f64 * A2).fract();
    Vec2::new((x as f32).min(ONE_MINUS_EPS), (y as f32).min(ONE_MINUS_EPS))
}

const ONE_MINUS_EPS: f32 = 1.0 - f32::EPSILON / 2.0;

/// An orthonormal basis (t, b, n) around unit `n` (Duff et al. 2017, branchless).
#[inline]
pub fn frame(n: Vec3) -> (Vec3, Vec3) {
    let sign = 1.0f32.copysign(n.z);
    let a = -1.0 / (sign + n.z);
    let b = n.x * n.y * a;
    (
        Vec3::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x),
        Vec3::new(b, sign + n.y * n.y * a, -n.y),
    )
}

/// Local (x, y, z) around unit `n` to world.
#[inline]
pub fn to_world(n: Vec3, local: Vec3) -> Vec3 {
    let (t, b) = frame(n);
    t * local.x + b * local.y + n * local.z
}

/// Cosine-weighted direction about unit `n`; pdf per solid angle = cos θ / π.
#[inline]
pub fn cosine_hemisphere(n: Vec3, u: Vec2) -> Vec3 {
    let r = u.x.sqrt();
    let phi = TAU * u.y;
    let z = (1.0 - u.x).max(0.0).sqrt();
    to_world(n, Vec3::new(r * phi.cos(), r * phi.sin(), z))
}

/// Uniform direction inside the cone about unit `axis` with `1 − cos θmax = one_minus_cos_max`
/// (passed as such to keep precision for tiny cones); pdf = 1 / (2π · one_minus_cos_max).
#[inline]
pub fn uniform_cone(axis: Vec3, one_minus_cos_max: f32, u: Vec2) -> Vec3 {
    let one_minus_cos = u.x * one_minus_cos_max;
    let cos_t = 1.0 - one_minus_cos;
    let sin_t = (one_minus_cos * (2.0 - one_minus_cos)).max(0.0).sqrt();
    let phi = TAU * u.y;
    to_world(axis, Vec3::new(sin_t * phi.cos(), sin_t * phi.sin(), cos_t))
}

/// Uniform direction on the unit sphere; pdf = 1 / 4π.
#[inline]
pub fn uniform_sphere(u: Vec2) -> Vec3 {
    let z = 1.0 - 2.0 * u.x;
    let r = (1.0 - z * z).max(0.0).sqrt();
    let phi = TAU * u.y;
    Vec3::new(r * phi.cos(), r * phi.sin(), z)
}

/// The power heuristic (β = 2) weight of strategy `a` against `b`.
#[inline]
pub fn power_heuristic(pdf_a: f32, pdf_b: f32) -> f32 {
    let (a2, b2) = (pdf_a * pdf_a, pdf_b * pdf_b);
    if a2 + b2 > 0.0 && (a2 + b2).is_finite() {
        a2 / (a2 + b2)
    } else if pdf_a > pdf_b {
        1.0
    } else {
        0.0
    }
}

/// 1 / π.
pub const INV_PI: f32 = 1.0 / PI;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rng_is_uniform_and_keyed() {
        let mut r = Rng::new(42);
        let n = 200_000;
        let mut bins = [0u32; 10];
        let mut sum = 0.0f64;
        for _ in 0..n {
            let x = r.next_f32();
            assert!((0.0..1.0).contains(&x));
            bins[(x * 10.0) as usize] += 1;
            sum += x as f64;
        }
        assert!((sum / n as f64 - 0.5).abs() < 0.005);
        for b in bins {
            assert!((b as f64 / n as f64 - 0.1).abs() < 0.005);
        }
        assert_ne!(Rng::new(1).next_u32(), Rng::new(2).next_u32());
        assert_eq!(Rng::new(9).next_u32(), Rng::new(9).next_u32());
    }

    #[test]
    fn frame_is_orthonormal_everywhere() {
        for n in [
            Vec3::X,
            Vec3::Y,
            Vec3::Z,
            -Vec3::Z,
            Vec3::new(0.3, -0.9, 0.1).normalize(),
            Vec3::new(0.0, 0.0, -0.999_999_9).normalize(),
        ] {
            let (t, b) = frame(n);
            assert!((t.length() - 1.0).abs() < 1e-5 && (b.length() - 1.0).abs() < 1e-5);
            assert!(t.dot(b).abs() < 1e-5 && t.dot(n).abs() < 1e-5 && b.dot(n).abs() < 1e-5);
            assert!((t.cross(b) - n).length() < 1e-4, "right-handed");
        }
    }

    #[test]
    fn cosine_hemisphere_mean_cosine_is_two_thirds() {
        let n = Vec3::new(1.0, 2.0, -0.5).normalize();
        let mut r = Rng::new(3);
        let m = 100_000;
        let mean: f64 = (0..m)
            .map(|_| cosine_hemisphere(n, r.next_2d()).dot(n) as f64)
            .sum::<f64>()
            / m as f64;
        assert!((mean - 2.0 / 3.0).abs() < 0.003, "{mean}");
    }

    #[test]
    fn cone_stays_inside_and_is_uniform_in_cos() {
        let axis = Vec3::new(0.2, 0.9, 0.3).normalize();
        let omc = 0.1f32;
        let mut r = Rng::new(5);
        let m = 100_000;
        let mut sum = 0.0f64;
        for _ in 0..m {
            let d = uniform_cone(axis, omc, r.next_2d());
            assert!((d.length() - 1.0).abs() < 1e-4);
            assert!(d.dot(axis) >= 1.0 - omc - 1e-5);
            sum += (1.0 - d.dot(axis)) as f64;
        }
        assert!((sum / m as f64 - omc as f64 / 2.0).abs() < 0.001);
    }

    #[test]
    fn r2_points_are_in_unit_square_and_stratified() {
        let off = Vec2::new(0.3, 0.7);
        let mut cells = [0u32; 16];
        for i in 0..256 {
            let p = r2(i, off);
            assert!((0.0..1.0).contains(&p.x) && (0.0..1.0).contains(&p.y));
            cells[(p.x * 4.0) as usize * 4 + (p.y * 4.0) as usize] += 1;
        }
        // 256 points in 16 cells: a low-discrepancy set puts close to 16 in each.
        assert!(cells.iter().all(|&c| (12..=20).contains(&c)), "{cells:?}");
    }
}
