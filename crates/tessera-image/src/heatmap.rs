//! A heat-map PNG of a per-pixel count (e.g. samples per pixel), so users see where an
//! adaptive render spent its effort.

use crate::{encode_png_rgb8, ImageError};

/// Colour stops of the map, dark (few samples) to bright (many): black, purple, red,
/// orange, pale yellow — monotonic in lightness, so it also reads in greyscale.
const STOPS: [[f32; 3]; 5] = [
    [0.0, 0.0, 0.02],
    [0.34, 0.06, 0.43],
    [0.80, 0.20, 0.30],
    [0.98, 0.55, 0.04],
    [0.99, 0.99, 0.75],
];

/// The map's colour at `t` in [0, 1] (piecewise linear between the map's colour stops, `STOPS`).
pub fn heat_colour(t: f32) -> [u8; 3] {
    let t = if t.is_nan() { 0.0 } else { t.clamp(0.0, 1.0) };
    let x = t * (STOPS.len() - 1) as f32;
    let i = (x.floor() as usize).min(STOPS.len() - 2);
    let f = x - i as f32;
    let (a, b) = (STOPS[i], STOPS[i + 1]);
    [0, 1, 2].map(|c| ((a[c] + (b[c] - a[c]) * f) * 255.0 + 0.5) as u8)
}

/// Encodes `values` (row-major, `width * height`) as a heat-map PNG on a logarithmic
/// scale from the smallest to the largest value (sample counts of adaptive renders span
/// orders of magnitude). Zeros map to black; an image with one value everywhere is drawn
/// in the middle colour.
pub fn encode_heat_map_png(width: u32, height: u32, values: &[u32]) -> Result<Vec<u8>, ImageError> {
    let n = width as usize * height as usize;
    if values.len() != n {
        return Err(ImageError::Png(format!(
            "heat map has {} values for a {width}x{height} image",
            values.len()
        )));
    }
    let positive = values.iter().copied().filter(|&v| v > 0);
    let lo = positive.clone().min().unwrap_or(1) as f32;
    let hi = positive.max().unwrap_or(1) as f32;
    let (llo, lhi) = (lo.ln(), hi.ln());
    let mut rgb = Vec::with_capacity(3 * n);
    for &v in values {
        let t = if v == 0 {
            0.0
        } else if lhi > llo {
            0.1 + 0.9 * ((v as f32).ln() - llo) / (lhi - llo)
        } else {
            0.5
        };
        rgb.extend(heat_colour(t));
    }
    encode_png_rgb8(width, height, &rgb)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn colours_are_monotonic_in_lightness() {
        let lum = |c: [u8; 3]| 0.2126 * c[0] as f32 + 0.7152 * c[1] as f32 + 0.0722 * c[2] as f32;
        let mut last = -1.0;
        for k in 0..=100 {
            let l = lum(heat_colour(k as f32 / 100.0));
            assert!(l >= last - 0.5, "{k}");
            last = l;
        }
        assert_eq!(heat_colour(f32::NAN), heat_colour(0.0));
    }

    #[test]
    fn encodes_and_checks_size() {
        let png = encode_heat_map_png(3, 1, &[8, 64, 1024]).unwrap();
        assert_eq!(&png[1..4], b"PNG");
        assert!(encode_heat_map_png(3, 1, &[8, 64]).is_err());
        assert!(encode_heat_map_png(2, 1, &[0, 0]).is_ok());
    }
}
