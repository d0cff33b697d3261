//! Ray queries over a triangle soup: a compressed wide BVH (obvhs' CWBVH) with closest-hit and
//! occlusion traversal. Knows nothing of materials or lights.
//!
//! Triangles are copied into BVH leaf order (as `RtTriangle`) so traversal reads them
//! contiguously; `order` maps a leaf slot back to the caller's triangle index.
//!
//! ```
//! use glam::Vec3;
//! use lightprobe::accel::Accel;
//! let tris = [[Vec3::new(-1.0, 0.0, -1.0), Vec3::new(1.0, 0.0, -1.0), Vec3::new(0.0, 0.0, 1.0)]];
//! let accel = Accel::build(&tris);
//! let hit = accel.intersect(Vec3::new(0.0, 1.0, 0.0), Vec3::NEG_Y, f32::INFINITY).unwrap();
//! assert_eq!(hit.triangle, 0);
//! assert!((hit.t - 1.0).abs() < 1e-6);
//! ```

use std::time::Duration;

use glam::{Vec3, Vec3A};
use obvhs::BvhBuildParams;
use obvhs::cwbvh::CwBvh;
use obvhs::cwbvh::builder::build_cwbvh_from_tris;
use obvhs::ray::{Ray, RayHit};
use obvhs::rt_triangle::RtTriangle;
use obvhs::triangle::Triangle;

/// The closest intersection along a ray.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hit {
    /// Distance along the (unit) ray direction, metres.
    pub t: f32,
    /// The caller's triangle index.
    pub triangle: u32,
    /// Barycentric weights of corners 1 and 2 (corner 0 gets `1 − b1 − b2`).
    pub b1: f32,
    pub b2: f32,
}

/// A BVH over triangles, ready for ray queries from many threads.
pub struct Accel {
    bvh: CwBvh,
    /// Triangles in BVH leaf order.
    tris: Vec<RtTriangle>,
    /// Leaf slot → caller's triangle index.
    order: Vec<u32>,
    /// The caller's triangles, for exact barycentrics of the final hit.
    corners: Vec<[Vec3; 3]>,
}

impl Accel {
    /// Builds the BVH (in parallel). Degenerate triangles are allowed; they are never hit.
    pub fn build(triangles: &[[Vec3; 3]]) -> Accel {
        let tris: Vec<Triangle> = triangles
            .iter()
            .map(|[a, b, c]| Triangle {
                v0: (*a).into(),
                v1: (*b).into(),
                v2: (*c).into(),
            })
            .collect();
        if tris.is_empty() {
            return Accel {
                bvh: CwBvh::default(),
                tris: Vec::new(),
                order: Vec::new(),
                corners: Vec::new(),
            };
        }
        let bvh = build_cwbvh_from_tris(
            &tris,
            BvhBuildParams::medium_build(),
            &mut Duration::default(),
        );
        let order = bvh.primitive_indices.clone();
        let leaf_tris = order
            .iter()
            .map(|&i| RtTriangle::from(&tris[i as usize]))
            .collect();
        Accel {
            bvh,
            tris: leaf_tris,
            order,
            corners: triangles.to_vec(),
        }
    }

    /// Number of triangles indexed.
    pub fn len(&self) -> usize {
        self.corners.len()
    }

    /// True when there are no triangles.
    pub fn is_empty(&self) -> bool {
        self.corners.is_empty()
    }

    /// The closest hit with `t` in (0, `t_max`], for a unit `dir`.
    #[inline]
    pub fn intersect(&self, origin: Vec3, dir: Vec3, t_max: f32) -> Option<Hit> {
        if self.tris.is_empty() {
            return None;
        }
        let ray = Ray::new(origin.into(), canonical(dir), 0.0, t_max);
        let mut hit = RayHit::none();
        if !self
            .bvh
            .ray_traverse(ray, &mut hit, |r, id| self.tris[id].intersect(r))
        {
            return None;
        }
        let triangle = self.order[hit.primitive_id as usize];
        let (b1, b2) = barycentrics(&self.corners[triangle as usize], origin, dir);
        Some(Hit {
            t: hit.t,
            triangle,
            b1,
            b2,
        })
    }

    /// True if anything lies on the segment from `origin` along unit `dir` up to `t_max`.
    #[inline]
    pub fn occluded(&self, origin: Vec3, dir: Vec3, t_max: f32) -> bool {
        if self.tris.is_empty() {
            return false;
        }
        let ray = Ray::new(origin.into(), canonical(dir), 0.0, t_max);
        !self
            .bvh
            .ray_traverse_miss(ray, |r, id| self.tris[id].intersect(r))
    }
}

/// The direction with −0.0 components turned into +0.0: obvhs takes the traversal octant from
/// `d < 0` but the inverse direction from the sign bit, and the two disagree on −0.0 (an exactly
/// axis-aligned ray like −Y then misses everything).
#[inline]
fn canonical(dir: Vec3) -> Vec3A {
    Vec3A::from(dir) + Vec3A::ZERO
}

/// Barycentrics of the ray's crossing of the triangle's plane (Möller–Trumbore), clamped
/// into the triangle so a grazing hit never extrapolates attributes.
fn barycentrics([a, b, c]: &[Vec3; 3], origin: Vec3, dir: Vec3) -> (f32, f32) {
    let (e1, e2) = (Vec3A::from(*b - *a), Vec3A::from(*c - *a));
    let (o, d) = (Vec3A::from(origin), Vec3A::from(dir));
    let p = d.cross(e2);
    let det = e1.dot(p);
    if det == 0.0 {
        return (1.0 / 3.0, 1.0 / 3.0);
    }
    let s = o - Vec3A::from(*a);
    let q = s.cross(e1);
    let (b1, b2) = (s.dot(p) / det, d.dot(q) / det);
    let (b1, b2) = (b1.clamp(0.0, 1.0), b2.clamp(0.0, 1.0));
    let sum = b1 + b2;
    if sum > 1.0 {
        (b1 / sum, b2 / sum)
    } else {
        (b1, b2)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A deterministic pseudo-random generator for test geometry.
    fn lcg(state: &mut u64) -> f32 {
        *state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (*state >> 40) as f32 / (1u64 << 24) as f32
    }

    /// Independent of obvhs: a plain f64 Möller–Trumbore over every triangle.
    fn brute_force(tris: &[[Vec3; 3]], o: Vec3, d: Vec3, t_max: f32) -> Option<(f32, u32)> {
        let mut best: Option<(f32, u32)> = None;
        let (o, d) = (o.as_dvec3(), d.as_dvec3());
        for (i, t) in tris.iter().enumerate() {
            let [a, b, c] = t.map(|v| v.as_dvec3());
            let (e1, e2) = (b - a, c - a);
            let p = d.cross(e2);
            let det = e1.dot(p);
            if det.abs() < 1e-12 {
                continue;
            }
            let s = o - a;
            let u = s.dot(p) / det;
            let q = s.cross(e1);
            let v = d.dot(q) / det;
            let h = e2.dot(q) / det;
            if u >= 0.0
                && v >= 0.0
                && u + v <= 1.0
                && h > 0.0
                && h <= t_max as f64
                && best.is_none_or(|b| (h as f32) < b.0)
            {
                best = Some((h as f32, i as u32));
            }
        }
        best
    }

    #[test]
    fn agrees_with_brute_force() {
        let mut s = 7u64;
        let mut tris = Vec::new();
        for _ in 0..500 {
            let c = Vec3::new(lcg(&mut s), lcg(&mut s), lcg(&mut s)) * 4.0 - 2.0;
            let r = |s: &mut u64| Vec3::new(lcg(s), lcg(s), lcg(s)) * 0.6 - 0.3;
            tris.push([c + r(&mut s), c + r(&mut s), c + r(&mut s)]);
        }
        // Degenerate triangles must not break anything.
        tris.push([Vec3::ZERO, Vec3::ZERO, Vec3::ZERO]);
        tris.push([Vec3::ZERO, Vec3::X, Vec3::X * 2.0]);
        let accel = Accel::build(&tris);
        let mut hits = 0;
        for _ in 0..2000 {
            let o = Vec3::new(lcg(&mut s), lcg(&mut s), lcg(&mut s)) * 6.0 - 3.0;
            let d = (Vec3::new(lcg(&mut s), lcg(&mut s), lcg(&mut s)) * 2.0 - 1.0).normalize();
            let t_max = if lcg(&mut s) < 0.3 {
                1.5
            } else {
                f32::INFINITY
            };
            let got = accel.intersect(o, d, t_max);
            let want = brute_force(&tris, o, d, t_max);
            assert_eq!(got.is_some(), want.is_some(), "o={o} d={d}");
            assert_eq!(accel.occluded(o, d, t_max), want.is_some());
            if let (Some(g), Some(w)) = (got, want) {
                hits += 1;
                assert!((g.t - w.0).abs() < 1e-5, "t {} vs {}", g.t, w.0);
                // The hit point rebuilt from barycentrics lies on the ray.
                let [a, b, c] = tris[g.triangle as usize];
                let p = a * (1.0 - g.b1 - g.b2) + b * g.b1 + c * g.b2;
                assert!((p - (o + d * g.t)).length() < 1e-4);
            }
        }
        assert!(hits > 200, "too few hits to mean anything: {hits}");
    }

    #[test]
    fn axis_aligned_rays_hit_flat_geometry_from_both_sides() {
        // A flat quad in each axis plane; rays along ±X, ±Y, ±Z (with −0.0 components).
        for axis in 0..3 {
            let q = |a: f32, b: f32| {
                let mut v = [0.0; 3];
                v[(axis + 1) % 3] = a;
                v[(axis + 2) % 3] = b;
                Vec3::from(v)
            };
            let tris = [
                [q(-5.0, -5.0), q(5.0, 5.0), q(5.0, -5.0)],
                [q(-5.0, -5.0), q(-5.0, 5.0), q(5.0, 5.0)],
            ];
            let accel = Accel::build(&tris);
            for sign in [1.0f32, -1.0] {
                let mut d = Vec3::ZERO;
                d[axis] = sign;
                let d = -(-d); // keeps the −0.0 components a negation produces
                let o = q(0.2, 0.1) - d * 2.0;
                let hit = accel.intersect(o, d, f32::INFINITY);
                assert!(
                    hit.is_some_and(|h| (h.t - 2.0).abs() < 1e-5),
                    "axis {axis} sign {sign}: {hit:?}"
                );
                assert!(accel.occluded(o, d, 3.0));
                assert!(!accel.occluded(o, d, 1.9));
            }
        }
    }

    #[test]
    fn empty_scene_never_hits() {
        let accel = Accel::build(&[]);
        assert!(
            accel
                .intersect(Vec3::ZERO, Vec3::X, f32::INFINITY)
                .is_none()
        );
        assert!(!accel.occluded(Vec3::ZERO, Vec3::X, f32::INFINITY));
    }
}
