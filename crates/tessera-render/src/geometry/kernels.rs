//! The box-test kernels of the wide BVH and the choice among them at run time.
//!
//! Every kernel computes, for each child, the same IEEE operations in the same order:
//! `(plane - origin) * inv_dir` per slab, the entry distance as the running maximum
//! (starting at 0) and the exit distance as the running minimum (starting at the pruning
//! limit) of the three axes, each as `if a > b { a } else { b }` (so a NaN slab, a ray
//! lying in a box face, leaves the running value alone, and the compare is what
//! `maxps`/`minps` compute), then `entry <= exit * (1 + 2 γ(3))`. No fused multiply-add,
//! no approximate reciprocal: `inv_dir` is one correctly rounded division per ray. The
//! kernels differ only in how many children one instruction covers:
//!
//! - `scalar`: one child at a time, skipping unused slots (the reference);
//! - `sse2`: all `WIDTH` children as plain array code LLVM vectorises with the
//!   baseline x86-64 instruction set (4 lanes);
//! - `avx2`, `avx512`: the box test written out with 8-lane AVX intrinsics (one register
//!   per plane array; LLVM vectorised the array code only 4 lanes at a time), and the
//!   traversal and triangle tests compiled inside `#[target_feature]` functions for
//!   AVX2 or AVX-512 F.
//!
//! Traversal and triangle tests are the same code in every kernel (compiled per kernel
//! too, so they use its registers), and the hit does not depend on the box test beyond
//! its being conservative (see `wide`), so images are bit-identical across kernels. The
//! top level over instances and the motion segments go through the same kernels: a leaf
//! holding instances walks each one's prototype with the kernel's box test, inside the
//! kernel's `#[target_feature]` function.
//!
//! `TESSERA_ISA=scalar|sse2|avx2|avx512` forces a kernel; [`Isa::from_env`] refuses a
//! value this CPU cannot run, with a message naming what it lacks.

use super::wide::{
    self, far_scale, planes, BoxRay, BoxTest, Leaves, Nearest, WideBvh, WideNode, WIDTH,
};
use glam::Vec3;
use std::sync::OnceLock;

/// An instruction set the wide BVH's kernels can use.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Isa {
    /// One child at a time (the reference kernel).
    Scalar,
    /// SSE2 (baseline x86-64): 4 lanes.
    Sse2,
    /// AVX2: 8 lanes.
    Avx2,
    /// AVX-512 (F): 8 lanes with mask registers.
    Avx512,
}

impl Isa {
    /// Every kernel, slowest first.
    pub const ALL: [Isa; 4] = [Isa::Scalar, Isa::Sse2, Isa::Avx2, Isa::Avx512];

    /// The name `TESSERA_ISA` takes.
    pub fn name(self) -> &'static str {
        match self {
            Isa::Scalar => "scalar",
            Isa::Sse2 => "sse2",
            Isa::Avx2 => "avx2",
            Isa::Avx512 => "avx512",
        }
    }

    /// Whether this CPU runs the kernel.
    pub fn available(self) -> bool {
        #[cfg(target_arch = "x86_64")]
        {
            match self {
                Isa::Scalar | Isa::Sse2 => true,
                Isa::Avx2 => std::arch::is_x86_feature_detected!("avx2"),
                // The AVX-512 kernel's box test is the AVX2 one (8 children fill one
                // 256-bit register), so it needs both.
                Isa::Avx512 => {
                    std::arch::is_x86_feature_detected!("avx512f")
                        && std::arch::is_x86_feature_detected!("avx2")
                }
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            self == Isa::Scalar
        }
    }

    /// The widest kernel this CPU runs.
    pub fn best() -> Isa {
        Isa::ALL
            .into_iter()
            .rev()
            .find(|i| i.available())
            .unwrap_or(Isa::Scalar)
    }

    /// The kernel `TESSERA_ISA` names (the best one when it is unset or empty), or why
    /// it cannot be used.
    pub fn from_env() -> Result<Isa, String> {
        match std::env::var("TESSERA_ISA") {
            Err(_) => Ok(Isa::best()),
            Ok(v) if v.trim().is_empty() => Ok(Isa::best()),
            Ok(v) => Isa::parse(v.trim()),
        }
    }

    /// The kernel named `name`, if this CPU runs it.
    pub fn parse(name: &str) -> Result<Isa, String> {
        let isa = Isa::ALL
            .into_iter()
            .find(|i| i.name().eq_ignore_ascii_case(name))
            .ok_or_else(|| {
                format!("TESSERA_ISA={name}: unknown; expected scalar, sse2, avx2 or avx512")
            })?;
        if isa.available() {
            Ok(isa)
        } else {
            Err(format!(
                "TESSERA_ISA={name}: this CPU lacks {} (available: {})",
                isa.name(),
                Isa::ALL
                    .into_iter()
                    .filter(|i| i.available())
                    .map(Isa::name)
                    .collect::<Vec<_>>()
                    .join(", ")
            ))
        }
    }
}

/// The kernel of this process: [`Isa::from_env`], read once. An unusable `TESSERA_ISA`
/// is reported on stderr once and the best kernel is used (images do not depend on the
/// kernel); front ends that must refuse it call [`Isa::from_env`] at start-up.
pub fn active() -> Isa {
    static ACTIVE: OnceLock<Isa> = OnceLock::new();
    *ACTIVE.get_or_init(|| {
        Isa::from_env().unwrap_or_else(|e| {
            eprintln!("tessera: {e}; using {}", Isa::best().name());
            Isa::best()
        })
    })
}

/// The reference kernel: one child at a time.
pub(super) struct Scalar;

impl BoxTest for Scalar {
    // Lanes are indexed by child on purpose: the same index walks six arrays.
    #[allow(clippy::needless_range_loop)]
    #[inline(always)]
    fn test(node: &WideNode, ray: &BoxRay, limit: f32) -> ([f32; WIDTH], u32) {
        let mut dist = [0.0f32; WIDTH];
        let mut mask = 0u32;
        for c in 0..WIDTH {
            // Unused slots are empty boxes; skipping them also keeps this loop scalar.
            if node.lo[0][c] > node.hi[0][c] {
                continue;
            }
            let mut entry = 0.0f32;
            let mut exit = limit;
            for axis in 0..3 {
                let (near, far) = planes(node, axis, ray.neg[axis]);
                let a = (near[c] - ray.origin[axis]) * ray.inv[axis];
                entry = if a > entry { a } else { entry };
                let b = (far[c] - ray.origin[axis]) * ray.inv[axis];
                exit = if b < exit { b } else { exit };
            }
            dist[c] = entry;
            if entry <= exit * far_scale() {
                mask |= 1 << c;
            }
        }
        (dist, mask)
    }
}

/// The array kernel: every child at once, vectorised by LLVM for the ISA of the function
/// it is compiled into.
pub(super) struct Lanes;

impl BoxTest for Lanes {
    // Lanes are indexed by child on purpose: the same index walks six arrays.
    #[allow(clippy::needless_range_loop)]
    #[inline(always)]
    fn test(node: &WideNode, ray: &BoxRay, limit: f32) -> ([f32; WIDTH], u32) {
        let mut entry = [0.0f32; WIDTH];
        let mut exit = [limit; WIDTH];
        for axis in 0..3 {
            let (near, far) = planes(node, axis, ray.neg[axis]);
            let (o, inv) = (ray.origin[axis], ray.inv[axis]);
            for c in 0..WIDTH {
                let a = (near[c] - o) * inv;
                entry[c] = if a > entry[c] { a } else { entry[c] };
                let b = (far[c] - o) * inv;
                exit[c] = if b < exit[c] { b } else { exit[c] };
            }
        }
        let scale = far_scale();
        let mut mask = 0u32;
        for c in 0..WIDTH {
            mask |= u32::from(entry[c] <= exit[c] * scale) << c;
        }
        (entry, mask)
    }
}

/// Kernel `isa`'s box test of `node` alone (for the tests that compare kernels lane by
/// lane); `isa` must be available.
#[cfg(test)]
pub(super) fn box_test(isa: Isa, node: &WideNode, ray: &BoxRay, limit: f32) -> ([f32; WIDTH], u32) {
    match isa {
        Isa::Scalar => Scalar::test(node, ray, limit),
        Isa::Sse2 => Lanes::test(node, ray, limit),
        #[cfg(target_arch = "x86_64")]
        Isa::Avx2 | Isa::Avx512 => x86::box_test(isa, node, ray, limit),
        #[cfg(not(target_arch = "x86_64"))]
        _ => Scalar::test(node, ray, limit),
    }
}

/// Offers every hit of the ray `origin + t dir` in `bvh`'s leaves to `best` (see
/// [`wide::nearest`]), with kernel `isa`'s box test, for the walk and for any walk the
/// leaves start in turn (an instance's prototype).
#[inline(always)]
pub(super) fn nearest<L: Leaves>(
    isa: Isa,
    bvh: &WideBvh,
    origin: Vec3,
    dir: Vec3,
    leaves: &L,
    best: &mut Nearest,
) {
    let ray = BoxRay::new(origin, dir);
    match isa {
        Isa::Scalar => wide::nearest::<Scalar, L>(bvh, &ray, leaves, best),
        Isa::Sse2 => wide::nearest::<Lanes, L>(bvh, &ray, leaves, best),
        #[cfg(target_arch = "x86_64")]
        Isa::Avx2 => x86::nearest_avx2(bvh, &ray, leaves, best),
        #[cfg(target_arch = "x86_64")]
        Isa::Avx512 => x86::nearest_avx512(bvh, &ray, leaves, best),
        #[cfg(not(target_arch = "x86_64"))]
        _ => wide::nearest::<Scalar, L>(bvh, &ray, leaves, best),
    }
}

/// Whether any kept hit of the ray in `bvh`'s leaves has `t < t_max` (see
/// [`wide::any`]), with kernel `isa`.
#[inline(always)]
pub(super) fn any<L: Leaves>(
    isa: Isa,
    bvh: &WideBvh,
    origin: Vec3,
    dir: Vec3,
    leaves: &L,
    t_max: f32,
) -> bool {
    let ray = BoxRay::new(origin, dir);
    match isa {
        Isa::Scalar => wide::any::<Scalar, L>(bvh, &ray, leaves, t_max),
        Isa::Sse2 => wide::any::<Lanes, L>(bvh, &ray, leaves, t_max),
        #[cfg(target_arch = "x86_64")]
        Isa::Avx2 => x86::any_avx2(bvh, &ray, leaves, t_max),
        #[cfg(target_arch = "x86_64")]
        Isa::Avx512 => x86::any_avx512(bvh, &ray, leaves, t_max),
        #[cfg(not(target_arch = "x86_64"))]
        _ => wide::any::<Scalar, L>(bvh, &ray, leaves, t_max),
    }
}

/// The traversals compiled for AVX2 and AVX-512, and the one place the crate calls a
/// `#[target_feature]` function from code without those features (ARCHITECTURE.md §1).
#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
mod x86 {
    use super::super::wide::{
        self, far_scale, planes, BoxRay, BoxTest, Leaves, Nearest, WideBvh, WideNode, WIDTH,
    };
    use super::{Isa, Lanes};
    use std::arch::x86_64::{
        _mm256_cmp_ps, _mm256_loadu_ps, _mm256_max_ps, _mm256_min_ps, _mm256_movemask_ps,
        _mm256_mul_ps, _mm256_set1_ps, _mm256_setzero_ps, _mm256_storeu_ps, _mm256_sub_ps,
        _CMP_LE_OQ,
    };

    /// The box test of all [`WIDTH`] children in one 8-lane register per plane array:
    /// the operations of [`super::Lanes`] in the same order, written out because LLVM
    /// vectorises the array code only 4 lanes at a time. `_mm256_max_ps(a, e)` is
    /// `if a > e { a } else { e }` and `_mm256_min_ps(b, x)` is `if b < x { b } else
    /// { x }` exactly (the second operand on NaN), and `_CMP_LE_OQ` is `<=` (false on
    /// NaN), so every lane computes the bits the scalar kernel does.
    ///
    /// Used only inside the `#[target_feature]` functions below, which run only after
    /// `Isa::available` confirmed AVX2 (the AVX-512 kernel checks it too). `test` is not
    /// itself a `#[target_feature]` function (those cannot be `#[inline(always)]`, and
    /// LLVM left such a function uninlined in the walk); inlined into the kernels, its
    /// intrinsics are inlined there.
    struct Avx2Box;

    impl BoxTest for Avx2Box {
        #[inline(always)]
        fn test(node: &WideNode, ray: &BoxRay, limit: f32) -> ([f32; WIDTH], u32) {
            const _: () = assert!(WIDTH == 8, "the AVX2 box test covers exactly 8 children");
            let mut dist = [0.0f32; WIDTH];
            // SAFETY: this type is private to this module and its test is reached only
            // from the kernels below (and `box_test`), which run only on a CPU with AVX2
            // (see above). The plane arrays and `dist` are arrays of exactly 8 `f32`s:
            // one unaligned 256-bit load or store each.
            let mask = unsafe {
                let mut entry = _mm256_setzero_ps();
                let mut exit = _mm256_set1_ps(limit);
                for axis in 0..3 {
                    let (near, far) = planes(node, axis, ray.neg[axis]);
                    let o = _mm256_set1_ps(ray.origin[axis]);
                    let inv = _mm256_set1_ps(ray.inv[axis]);
                    let a = _mm256_mul_ps(_mm256_sub_ps(_mm256_loadu_ps(near.as_ptr()), o), inv);
                    entry = _mm256_max_ps(a, entry);
                    let b = _mm256_mul_ps(_mm256_sub_ps(_mm256_loadu_ps(far.as_ptr()), o), inv);
                    exit = _mm256_min_ps(b, exit);
                }
                let inside = _mm256_cmp_ps::<_CMP_LE_OQ>(
                    entry,
                    _mm256_mul_ps(exit, _mm256_set1_ps(far_scale())),
                );
                _mm256_storeu_ps(dist.as_mut_ptr(), entry);
                _mm256_movemask_ps(inside) as u32
            };
            (dist, mask)
        }
    }

    /// The AVX2 box test compiled for AVX2 (for the tests).
    #[cfg(test)]
    #[target_feature(enable = "avx2")]
    fn box_test_avx2(node: &WideNode, ray: &BoxRay, limit: f32) -> ([f32; WIDTH], u32) {
        Avx2Box::test(node, ray, limit)
    }

    /// The AVX2 box test for the tests, on a CPU that has `isa`.
    #[cfg(test)]
    pub(in super::super) fn box_test(
        isa: Isa,
        node: &WideNode,
        ray: &BoxRay,
        limit: f32,
    ) -> ([f32; WIDTH], u32) {
        assert!(isa.available(), "this CPU lacks {}", isa.name());
        // SAFETY: every kernel that reaches here (AVX2, AVX-512) was just confirmed
        // available, and each needs AVX2 (see `Isa::available`).
        unsafe { box_test_avx2(node, ray, limit) }
    }

    macro_rules! kernel {
        ($nearest:ident, $nearest_tf:ident, $any:ident, $any_tf:ident, $feature:literal, $isa:expr) => {
            #[target_feature(enable = $feature)]
            fn $nearest_tf<L: Leaves>(bvh: &WideBvh, ray: &BoxRay, leaves: &L, best: &mut Nearest) {
                wide::nearest::<Avx2Box, L>(bvh, ray, leaves, best)
            }

            #[target_feature(enable = $feature)]
            fn $any_tf<L: Leaves>(bvh: &WideBvh, ray: &BoxRay, leaves: &L, t_max: f32) -> bool {
                wide::any::<Avx2Box, L>(bvh, ray, leaves, t_max)
            }

            #[inline(always)]
            pub(in super::super) fn $nearest<L: Leaves>(
                bvh: &WideBvh,
                ray: &BoxRay,
                leaves: &L,
                best: &mut Nearest,
            ) {
                if !$isa.available() {
                    return wide::nearest::<Lanes, L>(bvh, ray, leaves, best);
                }
                // SAFETY: `Isa::available` just confirmed with `is_x86_feature_detected!`
                // that this CPU has the feature the function is compiled for.
                unsafe { $nearest_tf(bvh, ray, leaves, best) }
            }

            #[inline(always)]
            pub(in super::super) fn $any<L: Leaves>(
                bvh: &WideBvh,
                ray: &BoxRay,
                leaves: &L,
                t_max: f32,
            ) -> bool {
                if !$isa.available() {
                    return wide::any::<Lanes, L>(bvh, ray, leaves, t_max);
                }
                // SAFETY: `Isa::available` just confirmed with `is_x86_feature_detected!`
                // that this CPU has the feature the function is compiled for.
                unsafe { $any_tf(bvh, ray, leaves, t_max) }
            }
        };
    }

    kernel!(
        nearest_avx2,
        nearest_avx2_tf,
        any_avx2,
        any_avx2_tf,
        "avx2",
        Isa::Avx2
    );
    kernel!(
        nearest_avx512,
        nearest_avx512_tf,
        any_avx512,
        any_avx512_tf,
        "avx512f",
        Isa::Avx512
    );
}
