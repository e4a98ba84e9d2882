//! Texture lookup: wrap modes and bilinear filtering as OpenGL defines them (which glTF
//! adopts, spec "Samplers"): the wrap mode applies to the integer texel index, so a
//! bilinear footprint straddling an edge reads the wrapped texel, and `CLAMP_TO_EDGE` never
//! blends with anything outside the image.

use glam::{Vec2, Vec4};
use tessera_scene::{Image, Texture, Wrap};

/// Texel index `i` (any integer) wrapped into `0..n` by `mode`.
#[inline]
pub fn wrap_index(i: i64, n: u32, mode: Wrap) -> u32 {
    let n = i64::from(n);
    let w = match mode {
        Wrap::Repeat => i.rem_euclid(n),
        Wrap::MirroredRepeat => {
            // Period 2n: 0, 1, .., n-1, n-1, .., 1, 0.
            let m = i.rem_euclid(2 * n);
            if m < n {
                m
            } else {
                2 * n - 1 - m
            }
        }
        Wrap::ClampToEdge => i.clamp(0, n - 1),
    };
    w as u32
}

/// The integer texel index of a coordinate, saturating far outside (huge or non-finite
/// coordinates must not overflow; NaN reads texel 0).
#[inline]
fn texel_floor(x: f32) -> i64 {
    // ±2^40 texels is far beyond any image, yet exact in f32 steps that matter here.
    x.floor().clamp(-1.0e12, 1.0e12) as i64
}

/// The texture's value at `uv` (glTF convention: (0, 0) is the top-left corner of the
/// image, texel centres at half-integers), RGBA with RGB linearised when `srgb`.
/// Bilinear unless the sampler asks for nearest.
#[inline]
pub fn sample(image: &Image, tex: &Texture, uv: Vec2, srgb: bool) -> Vec4 {
    let (w, h) = (image.width, image.height);
    let x = uv.x * w as f32;
    let y = uv.y * h as f32;
    if tex.nearest {
        let ix = wrap_index(texel_floor(x), w, tex.wrap_s);
        let iy = wrap_index(texel_floor(y), h, tex.wrap_t);
        return image.texel(ix, iy, srgb);
    }
    let (x, y) = (x - 0.5, y - 0.5);
    let (x0, y0) = (texel_floor(x), texel_floor(y));
    let fx = if x.is_finite() { x - x0 as f32 } else { 0.0 };
    let fy = if y.is_finite() { y - y0 as f32 } else { 0.0 };
    let (fx, fy) = (fx.clamp(0.0, 1.0), fy.clamp(0.0, 1.0));
    let xa = wrap_index(x0, w, tex.wrap_s);
    let xb = wrap_index(x0 + 1, w, tex.wrap_s);
    let ya = wrap_index(y0, h, tex.wrap_t);
    let yb = wrap_index(y0 + 1, h, tex.wrap_t);
    let top = image
        .texel(xa, ya, srgb)
        .lerp(image.texel(xb, ya, srgb), fx);
    let bottom = image
        .texel(xa, yb, srgb)
        .lerp(image.texel(xb, yb, srgb), fx);
    top.lerp(bottom, fy)
}

#[cfg(test)]
mod tests {
    use super::*;
    use tessera_scene::Texels;

    fn image(values: &[u8], width: u32) -> Image {
        Image {
            width,
            height: values.len() as u32 / width,
            texels: Texels::Rgba8(values.iter().map(|&v| [v, v, v, 255]).collect()),
        }
    }

    fn tex(wrap: Wrap) -> Texture {
        Texture {
            image: 0,
            wrap_s: wrap,
            wrap_t: wrap,
            nearest: false,
        }
    }

    #[test]
    fn wrap_modes_follow_the_opengl_definitions() {
        let repeat: Vec<u32> = (-5..7).map(|i| wrap_index(i, 3, Wrap::Repeat)).collect();
        assert_eq!(repeat, [1, 2, 0, 1, 2, 0, 1, 2, 0, 1, 2, 0]);
        let mirror: Vec<u32> = (-5..7)
            .map(|i| wrap_index(i, 3, Wrap::MirroredRepeat))
            .collect();
        assert_eq!(mirror, [1, 2, 2, 1, 0, 0, 1, 2, 2, 1, 0, 0]);
        let clamp: Vec<u32> = (-5..7)
            .map(|i| wrap_index(i, 3, Wrap::ClampToEdge))
            .collect();
        assert_eq!(clamp, [0, 0, 0, 0, 0, 0, 1, 2, 2, 2, 2, 2]);
    }

    #[test]
    fn bilinear_filtering_interpolates_between_texel_centres() {
        // One row 0, 255: linear values 0 and 1 (not sRGB).
        let im = image(&[0, 255], 2);
        let at = |u: f32, wrap| sample(&im, &tex(wrap), Vec2::new(u, 0.5), false).x;
        // Texel centres at u = 0.25 and 0.75; halfway between them is 0.5.
        assert!((at(0.25, Wrap::Repeat) - 0.0).abs() < 1e-6);
        assert!((at(0.75, Wrap::Repeat) - 1.0).abs() < 1e-6);
        assert!((at(0.5, Wrap::Repeat) - 0.5).abs() < 1e-6);
        // At u = 0 (the left edge) repeat blends the last texel in, clamp does not, and
        // mirroring reads the first texel twice.
        assert!((at(0.0, Wrap::Repeat) - 0.5).abs() < 1e-6);
        assert!((at(0.0, Wrap::ClampToEdge) - 0.0).abs() < 1e-6);
        assert!((at(0.0, Wrap::MirroredRepeat) - 0.0).abs() < 1e-6);
        // Far outside: clamp is the edge texel exactly; repeat has period 1; mirrored
        // repeat has period 2 and is mirrored in [1, 2).
        assert_eq!(at(-7.3, Wrap::ClampToEdge), 0.0);
        assert_eq!(at(9.9, Wrap::ClampToEdge), 1.0);
        assert!((at(3.75, Wrap::Repeat) - 1.0).abs() < 1e-5);
        assert!((at(1.25, Wrap::MirroredRepeat) - 1.0).abs() < 1e-5);
        assert!((at(1.75, Wrap::MirroredRepeat) - 0.0).abs() < 1e-5);
        // Non-finite coordinates read something finite.
        assert!(at(f32::NAN, Wrap::Repeat).is_finite());
        assert!(at(f32::INFINITY, Wrap::MirroredRepeat).is_finite());
    }

    #[test]
    fn srgb_texels_are_linearised_before_filtering() {
        let im = image(&[0, 255], 2);
        let mid = sample(&im, &tex(Wrap::ClampToEdge), Vec2::new(0.5, 0.5), true).x;
        // Filtering in linear space: halfway between 0 and 1 is 0.5 (filtering the codes
        // would give the sRGB EOTF of 127.5 / 255, about 0.21).
        assert!((mid - 0.5).abs() < 1e-6, "{mid}");
        let alpha = sample(&im, &tex(Wrap::ClampToEdge), Vec2::new(0.5, 0.5), true).w;
        assert_eq!(alpha, 1.0);
    }
}
