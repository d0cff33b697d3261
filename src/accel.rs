//! Ray queries over a triangle soup: an 8-wide BVH with closest-hit and occlusion traversal.
//! Knows nothing of materials or lights.
//!
//! obvhs builds a binary BVH (PLOC with reinsertion); [`Accel::build`] collapses it into 8-wide
//! nodes whose child boxes are plain `f32` in structure-of-arrays form, so one node test is a
//! few 8-lane vector operations (fixed-size loops the compiler vectorises). obvhs' own
//! compressed wide BVH decodes quantised boxes at every node test, which was most of our
//! render time. Closest-hit traversal visits hit children nearest first and skips any whose
//! entry distance lies beyond the closest hit so far.
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

use glam::Vec3;
use obvhs::BvhBuildParams;
use obvhs::bvh2::Bvh2;
use obvhs::bvh2::builder::build_bvh2_from_tris;
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

/// Children per node.
const WIDTH: usize = 8;
/// A child reference with this bit set is a leaf, `LEAF | packet index`; otherwise it is a
/// node index.
const LEAF: u32 = 1 << 31;
/// Entries of the stack of [`Accel::bundle`]'s traversal (deeper trees give up the bundle).
const STACK: usize = 128;

thread_local! {
    /// Each thread's traversal stacks (closest hit, any hit), grown to the deepest tree it
    /// has traversed: a stack on the machine stack would be zeroed at every ray, which cost
    /// an eighth of a closest-hit query.
    static STACKS: std::cell::RefCell<Stacks> =
        const { std::cell::RefCell::new((Vec::new(), Vec::new())) };
}

/// Traversal stacks: closest hit (child reference, entry distance), any hit (child reference).
type Stacks = (Vec<(u32, f32)>, Vec<u32>);

/// One 8-wide node: the boxes of its children, world space, metres.
#[derive(Clone, Copy)]
#[repr(C, align(64))]
struct Node {
    /// `[min x, max x, min y, max y, min z, max z]`, one lane per child.
    bounds: [[f32; WIDTH]; 6],
    /// One child reference per lane (see [`LEAF`]).
    child: [u32; WIDTH],
    /// Bit i set if lane i holds a child.
    lanes: u32,
}

/// The triangles of one leaf, ready for Möller–Trumbore on all lanes at once: per lane,
/// corner 0 and the edges to corners 1 and 2 (`[axis][lane]`).
#[derive(Clone, Copy)]
#[repr(C, align(32))]
struct Packet {
    v0: [[f32; WIDTH]; 3],
    e1: [[f32; WIDTH]; 3],
    e2: [[f32; WIDTH]; 3],
    /// Bit i set if lane i holds a triangle.
    lanes: u32,
}

/// What every node test of one ray needs.
struct RayData {
    origin: Vec3,
    dir: Vec3,
    /// 1 / direction, with zero components replaced by a tiny signed value (no 0 × ∞).
    inv: [f32; 3],
    /// Per axis, the `bounds` row of the near slab (the far one is `near ^ 1`).
    near: [usize; 3],
}

impl RayData {
    #[inline(always)]
    fn new(origin: Vec3, dir: Vec3) -> RayData {
        let inv = dir.to_array().map(|c| {
            let c = if c.abs() < 1e-20 {
                1e-20f32.copysign(c)
            } else {
                c
            };
            1.0 / c
        });
        RayData {
            origin,
            dir,
            near: [0, 1, 2].map(|a| 2 * a + (inv[a] < 0.0) as usize),
            inv,
        }
    }
}

/// The leaves that rays from one origin within a thin pyramid can hit (e.g. the camera rays
/// of one pixel), nearest box first: [`Accel::intersect_bundle`] tests a ray against these
/// alone, with no traversal, and a pyramid that meets no geometry costs its rays nothing.
/// `Bundle::default()` is scratch space for [`Accel::bundle`] to fill, not a bundle yet.
#[derive(Debug, Default, Clone)]
pub struct Bundle {
    /// The rays' common origin, world space (metres).
    origin: Vec3,
    /// Per leaf: the distance from `origin` to its box (no ray meets the leaf sooner) and its
    /// packet, by increasing distance.
    leaves: Vec<(f32, u32)>,
    /// Per leaf, in the same order: its triangles prepared for rays from `origin`.
    prepared: Vec<Prepared>,
    /// False when the pyramid met too many leaves for a flat list to pay off (rays then fall
    /// back to the full traversal).
    usable: bool,
}

impl Bundle {
    /// The rays' common origin, world space (metres).
    pub fn origin(&self) -> Vec3 {
        self.origin
    }

    /// Leaves the pyramid meets.
    pub fn len(&self) -> usize {
        self.leaves.len()
    }

    pub fn is_empty(&self) -> bool {
        self.leaves.is_empty()
    }

    /// Whether rays use the list ([`Accel::intersect_bundle`]) or fall back to traversal.
    pub fn usable(&self) -> bool {
        self.usable
    }

    /// True when no ray inside the pyramid can meet a triangle.
    pub fn meets_nothing(&self) -> bool {
        self.usable && self.leaves.is_empty()
    }
}

/// A bundle of more leaves than this is not worth a flat list (a ray may test them all).
const BUNDLE_MAX: usize = 64;

/// A BVH over triangles, ready for ray queries from many threads.
pub struct Accel {
    nodes: Vec<Node>,
    /// One packet per leaf.
    packets: Vec<Packet>,
    /// Leaf slot (packet × WIDTH + lane) → caller's triangle index.
    order: Vec<u32>,
    /// Traversal stack entries the deepest path can need.
    stack_len: usize,
    /// Number of the caller's triangles.
    len: usize,
    /// Whether traversal runs its AVX kernels ([`Isa::detect`]).
    isa: Isa,
}

/// The instruction set the hot loops (BVH traversal, the pixel loop) are compiled for,
/// chosen at run time: the binary is built for the baseline x86-64 (or any other target), and
/// the x86-64-v3 copies run where the CPU has that level. Both compute the same arithmetic in
/// the same order, so they give the same answers bit for bit (tests compare them).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Isa {
    /// Plain Rust, for any target.
    Portable,
    /// x86-64-v3 (AVX2, FMA, BMI1/2, LZCNT, POPCNT; x86-64 only): 256-bit node tests, and
    /// bit scans and rounding as single instructions. Functions compiled for it carry
    /// `#[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]`.
    Avx2,
}

impl Isa {
    /// x86-64-v3 where this CPU has it, unless the environment variable `LIGHTPROBE_ISA` is
    /// `portable` (to test or compare the portable kernels on such a machine).
    pub fn detect() -> Isa {
        if std::env::var_os("LIGHTPROBE_ISA").is_some_and(|v| v == "portable") {
            return Isa::Portable;
        }
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2")
            && std::arch::is_x86_feature_detected!("fma")
            && std::arch::is_x86_feature_detected!("bmi1")
            && std::arch::is_x86_feature_detected!("bmi2")
            && std::arch::is_x86_feature_detected!("lzcnt")
            && std::arch::is_x86_feature_detected!("popcnt")
        {
            return Isa::Avx2;
        }
        Isa::Portable
    }
}

impl Accel {
    /// Builds the BVH (in parallel). Degenerate triangles are allowed; they are never hit.
    pub fn build(triangles: &[[Vec3; 3]]) -> Accel {
        let mut accel = Accel {
            nodes: Vec::new(),
            packets: Vec::new(),
            order: Vec::new(),
            stack_len: 1,
            len: triangles.len(),
            isa: Isa::detect(),
        };
        if triangles.is_empty() {
            return accel;
        }
        let input: Vec<Triangle> = triangles
            .iter()
            .map(|[a, b, c]| Triangle {
                v0: (*a).into(),
                v1: (*b).into(),
                v2: (*c).into(),
            })
            .collect();
        let bvh2 = build_bvh2_from_tris(
            &input,
            // At most WIDTH triangles per leaf: one packet. A leaf tests its 8 lanes at the
            // cost of one node test, so full leaves pay: a collapse cost of 6 (obvhs' default
            // 3) and the slower, better build took 3.5% off the bundled render for 2 ms more
            // build.
            BvhBuildParams {
                collapse_traversal_cost: 6.0,
                pre_split: false,
                ..BvhBuildParams::slow_build()
            },
            &mut Duration::default(),
        );
        let depth = accel.collapse(&bvh2, triangles, 0);
        // Each level pops one entry and pushes at most WIDTH; closest-hit traversal writes
        // WIDTH entries at once (a fixed-size copy, no memmove call), hence the slack.
        accel.stack_len = depth * (WIDTH - 1) + 1 + WIDTH;
        accel
    }

    /// Appends the 8-wide node for binary node `b` (and, first, its subtree). Returns the depth
    /// of the wide subtree.
    fn collapse(&mut self, bvh2: &Bvh2, triangles: &[[Vec3; 3]], b: usize) -> usize {
        // Open the largest inner child until there are WIDTH children or only leaves: large
        // boxes are the ones rays hit most, so they are the ones worth flattening.
        let mut kids: Vec<usize> = if bvh2.nodes[b].is_leaf() {
            vec![b]
        } else {
            let first = bvh2.nodes[b].first_index as usize;
            vec![first, first + 1]
        };
        while kids.len() < WIDTH {
            let widest = kids
                .iter()
                .enumerate()
                .filter(|(_, k)| !bvh2.nodes[**k].is_leaf())
                .max_by(|a, b| {
                    let area = |k: usize| bvh2.nodes[k].aabb().half_area();
                    area(*a.1).total_cmp(&area(*b.1))
                })
                .map(|(i, _)| i);
            let Some(i) = widest else { break };
            let first = bvh2.nodes[kids[i]].first_index as usize;
            kids[i] = first;
            kids.push(first + 1);
        }
        let index = self.nodes.len();
        self.nodes.push(Node {
            bounds: [[0.0; WIDTH]; 6],
            child: [0; WIDTH],
            lanes: (1 << kids.len()) - 1,
        });
        let mut depth = 0;
        for (lane, &k) in kids.iter().enumerate() {
            let node2 = &bvh2.nodes[k];
            let child = if node2.is_leaf() {
                let (first, count) = (node2.first_index as usize, node2.prim_count as usize);
                assert!(count <= WIDTH, "BVH leaf of {count} triangles");
                let mut packet = Packet {
                    v0: [[0.0; WIDTH]; 3],
                    e1: [[0.0; WIDTH]; 3],
                    e2: [[0.0; WIDTH]; 3],
                    lanes: (1 << count) - 1,
                };
                self.order
                    .extend(&bvh2.primitive_indices[first..first + count]);
                self.order
                    .resize(self.order.len() + WIDTH - count, u32::MAX);
                for (lane, &i) in bvh2.primitive_indices[first..first + count]
                    .iter()
                    .enumerate()
                {
                    let [a, b, c] = triangles[i as usize];
                    let (e1, e2) = (b - a, c - a);
                    for axis in 0..3 {
                        packet.v0[axis][lane] = a[axis];
                        packet.e1[axis][lane] = e1[axis];
                        packet.e2[axis][lane] = e2[axis];
                    }
                }
                self.packets.push(packet);
                LEAF | (self.packets.len() - 1) as u32
            } else {
                let below = self.nodes.len() as u32;
                depth = depth.max(self.collapse(bvh2, triangles, k));
                below
            };
            let aabb = node2.aabb();
            let node = &mut self.nodes[index];
            node.child[lane] = child;
            for axis in 0..3 {
                node.bounds[2 * axis][lane] = aabb.min[axis];
                node.bounds[2 * axis + 1][lane] = aabb.max[axis];
            }
        }
        depth + 1
    }

    /// Number of triangles indexed.
    pub fn len(&self) -> usize {
        self.len
    }

    /// True when there are no triangles.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The closest hit with `t` in (0, `t_max`], for a unit `dir`.
    #[inline]
    pub fn intersect(&self, origin: Vec3, dir: Vec3, t_max: f32) -> Option<Hit> {
        #[cfg(target_arch = "x86_64")]
        if self.isa == Isa::Avx2 {
            // SAFETY: `isa` is `Avx2` only where the CPU has x86-64-v3 (`Isa::detect`).
            return unsafe { self.intersect_avx2(origin, dir, t_max) };
        }
        self.intersect_on::<false>(origin, dir, t_max)
    }

    /// True if anything lies on the segment from `origin` along unit `dir` up to `t_max`.
    #[inline]
    pub fn occluded(&self, origin: Vec3, dir: Vec3, t_max: f32) -> bool {
        #[cfg(target_arch = "x86_64")]
        if self.isa == Isa::Avx2 {
            // SAFETY: as in `intersect`.
            return unsafe { self.occluded_avx2(origin, dir, t_max) };
        }
        self.occluded_on::<false>(origin, dir, t_max)
    }

    // The whole query, ray set-up and stack included, is compiled in each kernel: a
    // baseline-compiled wrapper around the vector kernel costs a few percent of a render.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    fn intersect_avx2(&self, origin: Vec3, dir: Vec3, t_max: f32) -> Option<Hit> {
        self.intersect_on::<true>(origin, dir, t_max)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    fn occluded_avx2(&self, origin: Vec3, dir: Vec3, t_max: f32) -> bool {
        self.occluded_on::<true>(origin, dir, t_max)
    }

    /// [`Accel::intersect`] with the kernels of `AVX`.
    #[inline(always)]
    fn intersect_on<const AVX: bool>(&self, origin: Vec3, dir: Vec3, t_max: f32) -> Option<Hit> {
        if self.nodes.is_empty() {
            return None;
        }
        let ray = RayData::new(origin, dir);
        // The stack is taken out of the thread-local and put back, so that the traversal is
        // compiled in this kernel: run inside `LocalKey::with`'s closure, it may be left out
        // of line without the kernel's instruction set (measured: a quarter of a render).
        let mut stack = STACKS.with_borrow_mut(|(s, _)| std::mem::take(s));
        if stack.len() < self.stack_len {
            stack.resize(self.stack_len, (0, 0.0));
        }
        let hit = self.closest::<AVX>(&ray, t_max, &mut stack);
        STACKS.with_borrow_mut(|(s, _)| *s = stack);
        hit
    }

    /// [`Accel::occluded`] with the kernels of `AVX`.
    #[inline(always)]
    fn occluded_on<const AVX: bool>(&self, origin: Vec3, dir: Vec3, t_max: f32) -> bool {
        if self.nodes.is_empty() {
            return false;
        }
        let ray = RayData::new(origin, dir);
        // As in `intersect_on`.
        let mut stack = STACKS.with_borrow_mut(|(_, s)| std::mem::take(s));
        if stack.len() < self.stack_len {
            stack.resize(self.stack_len, 0);
        }
        let hit = self.any::<AVX>(&ray, t_max, &mut stack);
        STACKS.with_borrow_mut(|(_, s)| *s = stack);
        hit
    }

    /// The instruction set traversal uses.
    pub fn isa(&self) -> Isa {
        self.isa
    }

    /// The same BVH with traversal on `isa` (which this CPU must support; tests compare the
    /// kernels with it).
    pub fn with_isa(mut self, isa: Isa) -> Accel {
        if isa == Isa::Avx2 {
            assert_eq!(Isa::detect(), Isa::Avx2, "this CPU lacks x86-64-v3");
        }
        self.isa = isa;
        self
    }

    /// Fills `out` with the leaves the pyramid with apex `origin` spanned by the four edge
    /// directions `corners` (in order around it, each unit length, the pyramid narrower than a
    /// half-space) can reach. Conservative: a ray from `origin` inside the pyramid crosses no
    /// triangle outside the list.
    pub fn bundle(&self, origin: Vec3, corners: [Vec3; 4], out: &mut Bundle) {
        out.origin = origin;
        out.leaves.clear();
        out.prepared.clear();
        out.usable = true;
        if self.nodes.is_empty() {
            return;
        }
        // Unit inward normals of the four side planes, all through the apex. In f64: the
        // corners of a small pixel are nearly parallel, and their f32 cross product would
        // carry an error of ~1e-7 against a length of the pixel's angle (its direction, even
        // its sign, unreliable for pixels of ~1e-4 rad).
        let corners = corners.map(|c| c.as_dvec3());
        let centre: glam::DVec3 = corners.iter().copied().sum();
        let planes = [0, 1, 2, 3].map(|i| {
            let n = corners[i].cross(corners[(i + 1) % 4]).normalize_or_zero();
            (if n.dot(centre) < 0.0 { -n } else { n }).as_vec3()
        });
        let o = origin.to_array();
        let mut stack = [0u32; STACK];
        let mut top = 1;
        stack[0] = 0;
        while top > 0 {
            if top - 1 + WIDTH > STACK {
                out.usable = false;
                out.leaves.clear();
                return;
            }
            top -= 1;
            let node = &self.nodes[stack[top] as usize];
            let b = &node.bounds;
            let mut mask = node.lanes as u8;
            for n in &planes {
                // Per child box, the signed distance of its corner farthest along n: the box
                // lies wholly outside when even that corner is behind the plane by more than
                // MARGIN radians at its distance from the apex (`reach` bounds that distance).
                // The margin covers the f32 rounding of the rays' and the corners' directions
                // (a few 1e-7 rad) and of this sum.
                const MARGIN: f32 = 1e-5;
                let (mut far, mut reach) = ([0.0f32; WIDTH], [0.0f32; WIDTH]);
                for (a, n) in n.to_array().into_iter().enumerate() {
                    let rows = b[2 * a].iter().zip(&b[2 * a + 1]);
                    for ((f, r), (lo, hi)) in far.iter_mut().zip(&mut reach).zip(rows) {
                        let (lo, hi) = (lo - o[a], hi - o[a]);
                        *f += (n * lo).max(n * hi);
                        *r += lo.abs().max(hi.abs());
                    }
                }
                for (i, (f, r)) in far.iter().zip(&reach).enumerate() {
                    if *f < -MARGIN * r {
                        mask &= !(1 << i);
                    }
                }
            }
            let mut mask = mask as u32;
            while mask != 0 {
                let lane = mask.trailing_zeros() as usize;
                mask &= mask - 1;
                let child = node.child[lane];
                if child & LEAF == 0 {
                    stack[top] = child;
                    top += 1;
                    continue;
                }
                if out.leaves.len() == BUNDLE_MAX {
                    out.usable = false;
                    out.leaves.clear();
                    return;
                }
                // Distance from the apex to the box: a lower bound on where any ray enters it.
                let gap = Vec3::from([0, 1, 2].map(|a| {
                    (b[2 * a][lane] - o[a]).max(0.0) + (o[a] - b[2 * a + 1][lane]).max(0.0)
                }));
                out.leaves
                    .push((gap.length() * (1.0 - 1e-5), child & !LEAF));
            }
        }
        out.leaves.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
        out.prepared.extend(
            out.leaves
                .iter()
                .map(|&(_, k)| Prepared::new(&self.packets[k as usize], origin)),
        );
    }

    /// The closest hit with `t` in (0, `t_max`] of a ray from the bundle's origin along unit
    /// `dir`, which must lie inside the bundle's pyramid: [`Accel::intersect`], answered from
    /// the bundle's leaves.
    #[inline]
    pub fn intersect_bundle(&self, bundle: &Bundle, dir: Vec3, t_max: f32) -> Option<Hit> {
        if !bundle.usable {
            return self.intersect(bundle.origin, dir, t_max);
        }
        #[cfg(target_arch = "x86_64")]
        if self.isa == Isa::Avx2 {
            // SAFETY: as in `intersect`.
            return unsafe { self.bundle_hit_avx2(bundle, dir, t_max) };
        }
        self.bundle_hit::<false>(bundle, dir, t_max)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    fn bundle_hit_avx2(&self, bundle: &Bundle, dir: Vec3, t_max: f32) -> Option<Hit> {
        self.bundle_hit::<true>(bundle, dir, t_max)
    }

    /// [`Accel::intersect_bundle`] on a usable bundle, with the kernels of `AVX`.
    #[inline(always)]
    fn bundle_hit<const AVX: bool>(&self, bundle: &Bundle, dir: Vec3, t_max: f32) -> Option<Hit> {
        let mut t_max = t_max;
        let mut best = None;
        for (&(near, packet), prepared) in bundle.leaves.iter().zip(&bundle.prepared) {
            if near > t_max {
                break;
            }
            let packet = packet as usize;
            if let Some((lane, t, b1, b2)) = hit_prepared::<AVX>(prepared, dir, t_max) {
                t_max = t;
                best = Some(((packet * WIDTH + lane) as u32, b1, b2));
            }
        }
        best.map(|(slot, b1, b2)| Hit {
            t: t_max,
            triangle: self.order[slot as usize],
            b1,
            b2,
        })
    }

    /// Closest-hit traversal with a stack of (child reference, entry distance), with the
    /// kernels of `AVX` (true only inside functions compiled with AVX enabled).
    #[inline(always)]
    fn closest<const AVX: bool>(
        &self,
        ray: &RayData,
        mut t_max: f32,
        stack: &mut [(u32, f32)],
    ) -> Option<Hit> {
        let mut best: Option<(u32, f32, f32)> = None;
        let mut top = 0;
        let mut child = 0u32;
        loop {
            if child & LEAF != 0 {
                let packet = (child & !LEAF) as usize;
                if let Some((lane, t, b1, b2)) =
                    hit_packet::<AVX>(&self.packets[packet], ray.origin, ray.dir, t_max)
                {
                    t_max = t;
                    best = Some(((packet * WIDTH + lane) as u32, b1, b2));
                }
            } else {
                let node = &self.nodes[child as usize];
                let (t_near, mut mask) = node_test::<AVX>(node, ray, t_max);
                if mask.is_power_of_two() {
                    // One child hit (the common case): nothing to order or push.
                    child = node.child[mask.trailing_zeros() as usize];
                    continue;
                } else if mask != 0 {
                    // Visit the nearest hit child next and push the others farthest first.
                    // Keys order by entry distance (non-negative, so its bits order like
                    // the value), ties by lane, later lanes first.
                    let mut keys = [0u64; WIDTH];
                    let mut n = 0;
                    while mask != 0 {
                        let lane = mask.trailing_zeros() as usize;
                        mask &= mask - 1;
                        let key =
                            ((t_near[lane].to_bits() as u64) << 32) | (WIDTH - 1 - lane) as u64;
                        let mut j = n;
                        while j > 0 && keys[j - 1] < key {
                            keys[j] = keys[j - 1];
                            j -= 1;
                        }
                        keys[j] = key;
                        n += 1;
                    }
                    for (slot, &key) in stack[top..top + WIDTH].iter_mut().zip(&keys) {
                        let lane = WIDTH - 1 - (key as u32 as usize);
                        *slot = (node.child[lane], f32::from_bits((key >> 32) as u32));
                    }
                    top += n - 1;
                    child = stack[top].0;
                    continue;
                }
            }
            // Pop the nearest child not beyond the closest hit so far.
            loop {
                if top == 0 {
                    return best.map(|(slot, b1, b2)| Hit {
                        t: t_max,
                        triangle: self.order[slot as usize],
                        b1,
                        b2,
                    });
                }
                top -= 1;
                let (c, t_enter) = stack[top];
                if t_enter <= t_max {
                    child = c;
                    break;
                }
            }
        }
    }

    /// Any-hit traversal: stops at the first triangle within (0, `t_max`], with the kernels
    /// of `AVX` as in [`Accel::closest`].
    #[inline(always)]
    fn any<const AVX: bool>(&self, ray: &RayData, t_max: f32, stack: &mut [u32]) -> bool {
        stack[0] = 0;
        let mut top = 1;
        while top > 0 {
            top -= 1;
            let child = stack[top];
            if child & LEAF != 0 {
                if hit_packet::<AVX>(
                    &self.packets[(child & !LEAF) as usize],
                    ray.origin,
                    ray.dir,
                    t_max,
                )
                .is_some()
                {
                    return true;
                }
                continue;
            }
            let node = &self.nodes[child as usize];
            let (_, mut mask) = node_test::<AVX>(node, ray, t_max);
            while mask != 0 {
                let lane = mask.trailing_zeros() as usize;
                mask &= mask - 1;
                stack[top] = node.child[lane];
                top += 1;
            }
        }
        false
    }
}

/// `a.max(b)` without NaN handling, so it compiles to one vector instruction.
#[inline(always)]
fn fmax(a: f32, b: f32) -> f32 {
    if a > b { a } else { b }
}

#[inline(always)]
fn fmin(a: f32, b: f32) -> f32 {
    if a < b { a } else { b }
}

/// (box − origin) · (1/d) rounds twice; widening a slab's exit distance by 1 + 2γ₃ (pbrt-v4's
/// bound) keeps rays that graze a box from missing it.
const WIDEN: f32 = 1.0 + 2.0 * 3.0 * f32::EPSILON * 0.5 / (1.0 - 3.0 * f32::EPSILON * 0.5);

// The AVX code below reads and writes rows of exactly eight f32.
const _: () = assert!(WIDTH == 8);

/// Slab test of the ray against all children of `node` over (0, `t_max`]: the entry
/// distances, and a bit mask of the children hit. With `AVX`, spelled out in AVX intrinsics:
/// the compiler's own vectorisation of the portable loop ([`node_test_portable`]) split it
/// into scalar and 4-wide pieces with shuffles (three times the instructions); this is the
/// same arithmetic, so the same answers (`maxps`/`minps` pick as `fmax`/`fmin` do; a test
/// compares the two).
#[inline(always)]
fn node_test<const AVX: bool>(node: &Node, ray: &RayData, t_max: f32) -> ([f32; WIDTH], u32) {
    #[cfg(target_arch = "x86_64")]
    if AVX {
        // SAFETY: `AVX` is true only in kernels compiled with AVX enabled, which run only
        // where the CPU has it (`Isa::detect`).
        return unsafe { node_test_avx(node, ray, t_max) };
    }
    node_test_portable(node, ray, t_max)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
#[inline]
fn node_test_avx(node: &Node, ray: &RayData, t_max: f32) -> ([f32; WIDTH], u32) {
    use std::arch::x86_64::*;
    let b = &node.bounds;
    let [nx, ny, nz] = ray.near;
    // SAFETY: each row is 8 contiguous f32 (an unaligned load asks no more), and so is
    // `t_near`.
    unsafe {
        let slab = |r: usize, a: usize| {
            let o = _mm256_set1_ps(ray.origin[a]);
            let inv = _mm256_set1_ps(ray.inv[a]);
            _mm256_mul_ps(_mm256_sub_ps(_mm256_loadu_ps(b[r].as_ptr()), o), inv)
        };
        let (tx0, tx1) = (slab(nx, 0), slab(nx ^ 1, 0));
        let (ty0, ty1) = (slab(ny, 1), slab(ny ^ 1, 1));
        let (tz0, tz1) = (slab(nz, 2), slab(nz ^ 1, 2));
        let t0 = _mm256_max_ps(
            _mm256_max_ps(tx0, ty0),
            _mm256_max_ps(tz0, _mm256_setzero_ps()),
        );
        let t1 = _mm256_mul_ps(
            _mm256_min_ps(
                _mm256_min_ps(tx1, ty1),
                _mm256_min_ps(tz1, _mm256_set1_ps(t_max)),
            ),
            _mm256_set1_ps(WIDEN),
        );
        let mask = _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(t0, t1)) as u32;
        let mut t_near = [0.0; WIDTH];
        _mm256_storeu_ps(t_near.as_mut_ptr(), t0);
        (t_near, mask & node.lanes)
    }
}

/// [`node_test`] in plain Rust, for any target.
#[inline(always)]
fn node_test_portable(node: &Node, ray: &RayData, t_max: f32) -> ([f32; WIDTH], u32) {
    let b = &node.bounds;
    let o = ray.origin.to_array();
    let [nx, ny, nz] = ray.near;
    let mut t_near = [0.0; WIDTH];
    let mut t_far = [0.0; WIDTH];
    for i in 0..WIDTH {
        let tx0 = (b[nx][i] - o[0]) * ray.inv[0];
        let tx1 = (b[nx ^ 1][i] - o[0]) * ray.inv[0];
        let ty0 = (b[ny][i] - o[1]) * ray.inv[1];
        let ty1 = (b[ny ^ 1][i] - o[1]) * ray.inv[1];
        let tz0 = (b[nz][i] - o[2]) * ray.inv[2];
        let tz1 = (b[nz ^ 1][i] - o[2]) * ray.inv[2];
        let t0 = fmax(fmax(tx0, ty0), fmax(tz0, 0.0));
        let t1 = fmin(fmin(tx1, ty1), fmin(tz1, t_max)) * WIDEN;
        t_near[i] = t0;
        t_far[i] = t1;
    }
    let mut mask = 0u8;
    for i in 0..WIDTH {
        mask |= ((t_near[i] <= t_far[i]) as u8) << i;
    }
    (t_near, mask as u32 & node.lanes)
}

/// A leaf's triangles as seen from one ray origin: what Möller–Trumbore computes from the
/// origin alone (per lane `s` = origin − corner 0, `q` = s × e1, and e2 · q), so that the rays
/// of a bundle, which share their origin, skip it.
#[derive(Debug, Clone, Copy)]
#[repr(C, align(32))]
struct Prepared {
    e1: [[f32; WIDTH]; 3],
    e2: [[f32; WIDTH]; 3],
    s: [[f32; WIDTH]; 3],
    q: [[f32; WIDTH]; 3],
    e2q: [f32; WIDTH],
    lanes: u32,
}

impl Prepared {
    #[inline(always)]
    fn new(k: &Packet, origin: Vec3) -> Prepared {
        let o = origin.to_array();
        let s: [[f32; WIDTH]; 3] = std::array::from_fn(|a| k.v0[a].map(|v| o[a] - v));
        let (e1, e2) = (&k.e1, &k.e2);
        let mut q = [[0.0; WIDTH]; 3];
        let mut e2q = [0.0; WIDTH];
        for i in 0..WIDTH {
            let (sx, sy, sz) = (s[0][i], s[1][i], s[2][i]);
            let (e1x, e1y, e1z) = (e1[0][i], e1[1][i], e1[2][i]);
            q[0][i] = sy * e1z - sz * e1y;
            q[1][i] = sz * e1x - sx * e1z;
            q[2][i] = sx * e1y - sy * e1x;
            e2q[i] = e2[0][i] * q[0][i] + e2[1][i] * q[1][i] + e2[2][i] * q[2][i];
        }
        Prepared {
            e1: k.e1,
            e2: k.e2,
            s,
            q,
            e2q,
            lanes: k.lanes,
        }
    }
}

/// Möller–Trumbore on every lane of a leaf: the closest crossing with `t` in (0, `t_max`] as
/// `(lane, t, b1, b2)`.
#[inline(always)]
fn hit_packet<const AVX: bool>(
    k: &Packet,
    origin: Vec3,
    dir: Vec3,
    t_max: f32,
) -> Option<(usize, f32, f32, f32)> {
    hit_prepared::<AVX>(&Prepared::new(k, origin), dir, t_max)
}

/// [`hit_packet`] from the origin the leaf was prepared for (the same arithmetic, so the same
/// answers).
#[inline(always)]
fn hit_prepared<const AVX: bool>(
    k: &Prepared,
    dir: Vec3,
    t_max: f32,
) -> Option<(usize, f32, f32, f32)> {
    let [dx, dy, dz] = dir.to_array();
    let (mut t, mut b1, mut b2) = ([f32::INFINITY; WIDTH], [0.0; WIDTH], [0.0; WIDTH]);
    for i in 0..WIDTH {
        let (e1x, e1y, e1z) = (k.e1[0][i], k.e1[1][i], k.e1[2][i]);
        let (e2x, e2y, e2z) = (k.e2[0][i], k.e2[1][i], k.e2[2][i]);
        let (px, py, pz) = (
            dy * e2z - dz * e2y,
            dz * e2x - dx * e2z,
            dx * e2y - dy * e2x,
        );
        let det = e1x * px + e1y * py + e1z * pz;
        let inv_det = 1.0 / det;
        let (sx, sy, sz) = (k.s[0][i], k.s[1][i], k.s[2][i]);
        let u = (sx * px + sy * py + sz * pz) * inv_det;
        let (qx, qy, qz) = (k.q[0][i], k.q[1][i], k.q[2][i]);
        let v = (dx * qx + dy * qy + dz * qz) * inv_det;
        let h = k.e2q[i] * inv_det;
        // Each comparison fails on NaN, so degenerate lanes (det = 0) never hit.
        let inside = det != 0.0 && u >= 0.0 && v >= 0.0 && u + v <= 1.0;
        t[i] = if inside && h > 0.0 && h <= t_max {
            h
        } else {
            f32::INFINITY
        };
        b1[i] = u;
        b2[i] = v;
    }
    // Most leaves are crossed nowhere or once: only several crossings need a search (the
    // first lane of the nearest, as a scan in lane order keeps).
    let hits = finite_lanes::<AVX>(&t) & k.lanes;
    if hits == 0 {
        return None;
    }
    let mut best = hits.trailing_zeros() as usize;
    let mut rest = hits & (hits - 1);
    while rest != 0 {
        let i = rest.trailing_zeros() as usize;
        rest &= rest - 1;
        if t[i] < t[best] {
            best = i;
        }
    }
    Some((best, t[best], b1[best], b2[best]))
}

/// Bit i set where `t[i]` is below +∞ (a crossing; ∞ marks none).
#[inline(always)]
fn finite_lanes<const AVX: bool>(t: &[f32; WIDTH]) -> u32 {
    #[cfg(target_arch = "x86_64")]
    if AVX {
        // SAFETY: as in `node_test`.
        return unsafe { finite_lanes_avx(t) };
    }
    finite_lanes_portable(t)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
#[inline]
fn finite_lanes_avx(t: &[f32; WIDTH]) -> u32 {
    use std::arch::x86_64::*;
    // SAFETY: `t` holds 8 f32.
    unsafe {
        let t = _mm256_loadu_ps(t.as_ptr());
        _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LT_OQ>(
            t,
            _mm256_set1_ps(f32::INFINITY),
        )) as u32
    }
}

/// [`finite_lanes`] in plain Rust, for any target.
#[inline(always)]
fn finite_lanes_portable(t: &[f32; WIDTH]) -> u32 {
    (0..WIDTH).fold(0, |m, i| m | ((t[i] < f32::INFINITY) as u32) << i)
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

    /// Independent of the BVH: a plain f64 Möller–Trumbore over every triangle.
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

    /// `n` random triangles in the 4-m cube about the origin, corners within `size` of a
    /// random centre.
    fn soup(s: &mut u64, n: usize, size: f32) -> Vec<[Vec3; 3]> {
        (0..n)
            .map(|_| {
                let c = Vec3::new(lcg(s), lcg(s), lcg(s)) * 4.0 - 2.0;
                let r = |s: &mut u64| (Vec3::new(lcg(s), lcg(s), lcg(s)) - 0.5) * size;
                [c + r(s), c + r(s), c + r(s)]
            })
            .collect()
    }

    /// Two triangles per cell of an `n` × `n` grid of points `at(i, j)`, i, j in 0..=n.
    fn grid(n: usize, at: impl Fn(usize, usize) -> Vec3, tris: &mut Vec<[Vec3; 3]>) {
        for i in 0..n {
            for j in 0..n {
                tris.push([at(i, j), at(i + 1, j), at(i + 1, j + 1)]);
                tris.push([at(i, j), at(i + 1, j + 1), at(i, j + 1)]);
            }
        }
    }

    #[test]
    fn agrees_with_brute_force() {
        let mut s = 7u64;
        let mut tris = soup(&mut s, 500, 0.6);
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
    fn bundles_answer_as_traversal_does() {
        // Rays through pixel-like pyramids (image-plane corners, jitter in [0, 1]² including
        // the edges) into a soup of triangles: the bundle's leaves give the traversal's hit.
        let mut s = 11u64;
        let mut tris = soup(&mut s, 3000, 0.3);
        // A finely tessellated bumpy floor (cells smaller than a pyramid's footprint), so
        // rays along a pyramid's edges hit triangles whose boxes barely reach into it.
        let n = 120;
        let height: Vec<f32> = (0..(n + 1) * (n + 1)).map(|_| lcg(&mut s) * 0.01).collect();
        let at = |i: usize, j: usize| {
            Vec3::new(
                i as f32 / n as f32 * 4.0 - 2.0,
                -2.5 + height[i * (n + 1) + j],
                j as f32 / n as f32 * 4.0 - 2.0,
            )
        };
        grid(n, at, &mut tris);
        // And a 2-cm patch of 0.13-mm cells above it, for the tiniest pyramids.
        let (m, centre) = (150, Vec3::new(0.5, -2.4, 0.5));
        let bumps: Vec<f32> = (0..(m + 1) * (m + 1)).map(|_| lcg(&mut s) * 3e-5).collect();
        let at = |i: usize, j: usize| {
            centre
                + Vec3::new(
                    (i as f32 / m as f32 - 0.5) * 0.02,
                    bumps[i * (m + 1) + j],
                    (j as f32 / m as f32 - 0.5) * 0.02,
                )
        };
        grid(m, at, &mut tris);
        let accel = Accel::build(&tris);
        let mut bundle = Bundle::default();
        let (mut hits, mut used, mut fell_back, mut empty) = (0, 0, 0, 0);
        for k in 0..600 {
            // Pixel-sized pyramids (0.01 rad: 128 rows; 1e-3, 1e-4, 3e-5: 1000 to 30 000
            // rows, where f32 cross products of the corners lose the planes), some wide
            // enough to meet too many leaves.
            let size = match k % 10 {
                1 => 0.5,
                2 | 3 => 1e-4,
                4 | 5 => 1e-3,
                6 => 3e-5,
                _ => 0.01,
            };
            let mut o = Vec3::new(lcg(&mut s), lcg(&mut s), lcg(&mut s)) * 8.0 - 4.0;
            // Every other pyramid looks at the floor, the tiniest at the patch.
            let target = if size < 1e-3 {
                let t = centre + Vec3::new(lcg(&mut s) - 0.5, 0.0, lcg(&mut s) - 0.5) * 0.02;
                let up = Vec3::new(lcg(&mut s) - 0.5, 0.6 + lcg(&mut s), lcg(&mut s) - 0.5);
                o = t + up.normalize() * (0.3 + 1.7 * lcg(&mut s));
                t
            } else if k % 2 == 0 {
                Vec3::new(lcg(&mut s) * 3.0 - 1.5, -2.5, lcg(&mut s) * 3.0 - 1.5)
            } else if k % 4 == 1 {
                Vec3::new(lcg(&mut s), lcg(&mut s), lcg(&mut s)) - 0.5
            } else {
                // Up and away: often nothing there at all.
                o + Vec3::new(lcg(&mut s) - 0.5, 1.0, lcg(&mut s) - 0.5)
            };
            let ahead = (target - o).normalize();
            let right = ahead.any_orthonormal_vector();
            let up = ahead.cross(right);
            let plane = |u: f32, v: f32| ahead + (right * u + up * v) * size;
            let corners = [
                plane(0.0, 0.0),
                plane(1.0, 0.0),
                plane(1.0, 1.0),
                plane(0.0, 1.0),
            ]
            .map(Vec3::normalize);
            accel.bundle(o, corners, &mut bundle);
            match (bundle.usable(), bundle.is_empty()) {
                (false, _) => fell_back += 1,
                (true, true) => empty += 1,
                (true, false) => used += 1,
            }
            for j in 0..40 {
                let (u, v) = match j {
                    0 => (0.0, 0.0),
                    1 => (1.0, 1.0),
                    2 => (1.0, 0.0),
                    3 => (0.0, 1.0),
                    _ => (lcg(&mut s), lcg(&mut s)),
                };
                let d = plane(u, v).normalize();
                let t_max = if j % 4 == 1 {
                    lcg(&mut s) * 8.0
                } else {
                    f32::INFINITY
                };
                let want = accel.intersect(o, d, t_max);
                let got = accel.intersect_bundle(&bundle, d, t_max);
                assert_eq!(got.is_some(), want.is_some(), "o={o} d={d} size {size}");
                if let (Some(g), Some(w)) = (got, want) {
                    hits += 1;
                    assert_eq!((g.t, g.triangle), (w.t, w.triangle), "o={o} d={d}");
                }
            }
        }
        assert!(hits > 2000, "too few hits to mean anything: {hits}");
        assert!(
            used > 100 && fell_back > 10 && empty > 50,
            "{used} {fell_back} {empty}"
        );
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
    #[cfg(target_arch = "x86_64")]
    fn vector_tests_answer_as_the_portable_ones() {
        if Isa::detect() != Isa::Avx2 {
            eprintln!("skipped: this CPU runs no AVX kernel, so there is nothing to compare");
            return;
        }
        // Random boxes and rays, with the awkward cases mixed in: origins on a slab plane,
        // axis-parallel rays (±0 direction components), empty and infinite boxes, t_max = ∞.
        let mut s = 9u64;
        let specials = [0.0, -0.0, 1.0, f32::INFINITY, f32::NEG_INFINITY];
        for i in 0..20_000 {
            let mut node = Node {
                bounds: [[0.0; WIDTH]; 6],
                child: [0; WIDTH],
                lanes: (lcg(&mut s) * 256.0) as u32,
            };
            for lane in 0..WIDTH {
                for axis in 0..3 {
                    let (a, b) = (lcg(&mut s) * 4.0 - 2.0, lcg(&mut s) * 4.0 - 2.0);
                    node.bounds[2 * axis][lane] = a.min(b);
                    node.bounds[2 * axis + 1][lane] = a.max(b);
                    if i % 7 == 0 {
                        node.bounds[2 * axis + (i / 7) % 2][lane] = specials[(i / 14) % 5];
                    }
                }
            }
            let mut o = Vec3::new(lcg(&mut s), lcg(&mut s), lcg(&mut s)) * 6.0 - Vec3::splat(3.0);
            let mut d = Vec3::new(lcg(&mut s), lcg(&mut s), lcg(&mut s)) - Vec3::splat(0.5);
            if i % 5 == 0 {
                o.x = node.bounds[0][i % WIDTH]; // on a slab plane
            }
            if i % 3 == 0 {
                d[i % 3] = if i % 2 == 0 { 0.0 } else { -0.0 };
            }
            let d = d.normalize();
            let t_max = if i % 4 == 0 {
                f32::INFINITY
            } else {
                lcg(&mut s) * 5.0
            };
            let ray = RayData::new(o, d);
            // SAFETY: the CPU has AVX (checked above).
            let (near_v, mask_v) = unsafe { node_test_avx(&node, &ray, t_max) };
            let (near_p, mask_p) = node_test_portable(&node, &ray, t_max);
            assert_eq!(mask_v, mask_p, "ray {i}");
            for lane in 0..WIDTH {
                assert_eq!(near_v[lane].to_bits(), near_p[lane].to_bits(), "ray {i}");
            }
            let t: [f32; WIDTH] = std::array::from_fn(|lane| near_p[lane] - 1.0);
            let t = t.map(|x| if x > 1.0 { f32::INFINITY } else { x });
            // SAFETY: as above.
            assert_eq!(unsafe { finite_lanes_avx(&t) }, finite_lanes_portable(&t));
        }
    }

    #[test]
    fn portable_and_detected_kernels_give_the_same_hits() {
        // Whole traversals (closest hit, occlusion, bundles) on both instruction sets: the
        // same bits, so images do not depend on the CPU.
        let mut s = 13u64;
        let tris = soup(&mut s, 2000, 0.4);
        let fast = Accel::build(&tris);
        let portable = Accel::build(&tris).with_isa(Isa::Portable);
        let (mut b_fast, mut b_port) = (Bundle::default(), Bundle::default());
        for i in 0..4000 {
            let o = Vec3::new(lcg(&mut s), lcg(&mut s), lcg(&mut s)) * 6.0 - 3.0;
            let d = (Vec3::new(lcg(&mut s), lcg(&mut s), lcg(&mut s)) * 2.0 - 1.0).normalize();
            let t_max = if i % 3 == 0 { 2.0 } else { f32::INFINITY };
            assert_eq!(fast.intersect(o, d, t_max), portable.intersect(o, d, t_max));
            assert_eq!(fast.occluded(o, d, t_max), portable.occluded(o, d, t_max));
            // A thin pyramid around d.
            let (u, v) = (
                d.any_orthonormal_vector() * 0.01,
                d.cross(d.any_orthonormal_vector()) * 0.01,
            );
            let corners = [d - u - v, d + u - v, d + u + v, d - u + v].map(|c| c.normalize());
            fast.bundle(o, corners, &mut b_fast);
            portable.bundle(o, corners, &mut b_port);
            assert_eq!(
                fast.intersect_bundle(&b_fast, d, t_max),
                portable.intersect_bundle(&b_port, d, t_max)
            );
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
