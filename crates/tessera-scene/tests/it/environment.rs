//! Environment images: Radiance RGBE and OpenEXR decode to the same linear radiance, sizes
//! are checked from the header before decoding, anything else is refused by name.

use glam::Vec3;
use tessera_scene::environment::decode_environment;
use tessera_testkit::gltf_gen::scratch_dir;

/// A flat (uncompressed) Radiance file of `w` x `h` texels, exact RGBE of `f(x, y)`
/// (values of the form m · 2^e with an 8-bit mantissa are represented exactly).
fn rgbe_file(w: u32, h: u32, f: impl Fn(u32, u32) -> [u8; 4]) -> Vec<u8> {
    let mut out = format!("#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y {h} +X {w}\n").into_bytes();
    for y in 0..h {
        for x in 0..w {
            out.extend_from_slice(&f(x, y));
        }
    }
    out
}

#[test]
fn radiance_hdr_and_openexr_decode_to_linear_radiance() {
    // RGBE (128, 64, 32, 129): mantissas / 256 × 2^(129 - 128) = (1, 0.5, 0.25).
    let hdr = rgbe_file(4, 2, |x, y| {
        if (x, y) == (3, 1) {
            [128, 64, 32, 129 + 3]
        } else {
            [128, 64, 32, 129]
        }
    });
    let map = decode_environment(&hdr, "sky.hdr").unwrap();
    assert_eq!((map.width, map.height), (4, 2));
    assert_eq!(map.texels[0], Vec3::new(1.0, 0.5, 0.25));
    assert_eq!(map.texels[7], Vec3::new(8.0, 4.0, 2.0));
    // The same image as OpenEXR.
    let dir = scratch_dir("environment-exr");
    let path = dir.join("sky.exr");
    let texel = |x: usize, y: usize| if (x, y) == (3, 1) { 8.0f32 } else { 1.0 };
    exr::prelude::write_rgb_file(&path, 4, 2, |x, y| {
        let v = texel(x, y);
        (v, 0.5 * v, 0.25 * v)
    })
    .unwrap();
    let exr = std::fs::read(&path).unwrap();
    let from_exr = decode_environment(&exr, "sky.exr").unwrap();
    assert_eq!(from_exr.texels, map.texels);
    assert_eq!((from_exr.width, from_exr.height), (4, 2));
    // Through the file loader too.
    let loaded = tessera_scene::environment::load_environment(&path).unwrap();
    assert_eq!(loaded.texels, map.texels);
}

#[test]
fn environment_images_are_bounded_and_checked() {
    // A header claiming 10000 x 10000 texels is refused before any pixel is read.
    let bomb = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 10000 +X 10000\n".to_vec();
    let e = decode_environment(&bomb, "bomb.hdr")
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("MAX_IMAGE_TEXELS") && e.contains("bomb.hdr"),
        "{e}"
    );
    // Not an HDR image at all.
    let e = decode_environment(b"\x89PNG\r\n\x1a\n", "sky.png")
        .unwrap_err()
        .to_string();
    assert!(e.contains("Radiance") && e.contains("OpenEXR"), "{e}");
    // Truncated pixel data.
    let mut cut = rgbe_file(4, 2, |_, _| [128, 128, 128, 129]);
    cut.truncate(cut.len() - 5);
    assert!(decode_environment(&cut, "cut.hdr").is_err());
    // A missing file names itself.
    let e = tessera_scene::environment::load_environment(std::path::Path::new("/nonexistent.hdr"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("/nonexistent.hdr"), "{e}");
}
