//! Floating-point helpers for robust ray tracing: error bounds and ray-origin offsets.
//!
//! A hit point computed in floating point lies within a small box around the true surface
//! point. Spawning the next ray from the computed point can re-hit the same surface
//! ("self-intersection", "shadow acne"). Following pbrt (Pharr, Jakob & Humphreys, 3rd ed.,
//! §3.9), every intersection carries a conservative bound `p_error` on the absolute error of
//! each coordinate, and a new ray's origin is pushed along the geometric normal just past
//! that box, then rounded away from the surface. This scales with the scene: it works the
//! same at 1e-4 and at 1e4 scene units, unlike a fixed epsilon.

use glam::Vec3;

/// Machine epsilon as pbrt uses it: half the distance from 1 to the next float (the unit
/// roundoff of round-to-nearest).
pub const MACHINE_EPSILON: f32 = f32::EPSILON * 0.5;

/// The classic bound on the relative error accumulated by `n` floating-point operations:
/// `gamma(n) = n u / (1 - n u)` (Higham; pbrt §3.9.1).
#[inline]
pub fn gamma(n: i32) -> f32 {
    let nu = n as f32 * MACHINE_EPSILON;
    nu / (1.0 - nu)
}

/// The next representable float above `v` (toward +inf).
#[inline]
pub fn next_float_up(v: f32) -> f32 {
    if v.is_infinite() && v > 0.0 {
        return v;
    }
    let v = if v == -0.0 { 0.0 } else { v };
    let bits = v.to_bits();
    let bits = if v >= 0.0 { bits + 1 } else { bits - 1 };
    f32::from_bits(bits)
}

/// The next representable float below `v` (toward -inf).
#[inline]
pub fn next_float_down(v: f32) -> f32 {
    if v.is_infinite() && v < 0.0 {
        return v;
    }
    let v = if v == 0.0 { -0.0 } else { v };
    let bits = v.to_bits();
    let bits = if v > 0.0 { bits - 1 } else { bits + 1 };
    f32::from_bits(bits)
}

/// Offsets a ray origin `p` (with per-coordinate error bound `p_error`) along the
/// geometric normal `n` to the side that `w` points to, far enough that the new ray cannot
/// re-intersect the surface the point lies on (pbrt 3rd ed. §3.9.5, `OffsetRayOrigin`).
#[inline]
pub fn offset_ray_origin(p: Vec3, p_error: Vec3, n: Vec3, w: Vec3) -> Vec3 {
    let d = n.abs().dot(p_error);
    let mut offset = n * d;
    if w.dot(n) < 0.0 {
        offset = -offset;
    }
    let po = p + offset;
    // Round away from p so the offset is not lost to rounding: one ulp in the direction of
    // the offset, per coordinate (written without a loop so it stays branch-light).
    Vec3::new(
        round_away(po.x, offset.x),
        round_away(po.y, offset.y),
        round_away(po.z, offset.z),
    )
}

/// Moves `v` one ulp in the direction of the sign of `o` (not at all for `o == 0`).
#[inline(always)]
fn round_away(v: f32, o: f32) -> f32 {
    if o > 0.0 {
        next_float_up(v)
    } else if o < 0.0 {
        next_float_down(v)
    } else {
        v
    }
}

/// Luminance of linear Rec. 709 RGB.
#[inline]
pub fn luminance(c: Vec3) -> f32 {
    0.2126 * c.x + 0.7152 * c.y + 0.0722 * c.z
}

/// Reflects `w` about the normal `n` (both pointing away from the surface).
#[inline]
pub fn reflect(w: Vec3, n: Vec3) -> Vec3 {
    2.0 * w.dot(n) * n - w
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn next_float_steps_one_ulp() {
        for v in [0.0f32, -0.0, 1.0, -1.0, 1e-30, -1e30, 3.5] {
            assert!(next_float_up(v) > v);
            assert!(next_float_down(v) < v);
        }
        assert_eq!(next_float_up(1.0), 1.0 + f32::EPSILON);
    }

    #[test]
    fn offset_moves_past_error_box() {
        let p = Vec3::new(1e4, 2e4, 3e4);
        let err = Vec3::splat(1e-2);
        let n = Vec3::Y;
        let o = offset_ray_origin(p, err, n, Vec3::Y);
        assert!(o.y - p.y >= 1e-2);
        let o = offset_ray_origin(p, err, n, -Vec3::Y);
        assert!(p.y - o.y >= 1e-2);
    }
}
