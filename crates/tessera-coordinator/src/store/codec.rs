//! Binary encoding of tile checkpoints (format in the [module docs](super)) and their
//! validation against a job's plan. Pure functions, shared by every store implementation.

use tessera_api::FrameRange;
use tessera_farm::{AdaptivePixel, AdaptiveTileCheckpoint, BiasStats, FramePlan, PixelStats};

use super::{UnitDigest, CHECKPOINT_FORMAT_VERSION};

/// Bytes of the header of both blobs: version (u8) and count (u32).
const HEADER_BYTES: usize = 5;
/// Bytes per pixel in the statistics blob: `passes` (u32) and 8 f64.
pub(crate) const PIXEL_BYTES: usize = 4 + 8 * 8;
/// Bytes per pixel of the bias records after the statistics: `passes` (u32) and 2 f64.
pub(crate) const BIAS_BYTES: usize = 4 + 2 * 8;
/// Bytes per unit in the digest blob: `first_pass`, `pass_count` (u32) and `digest` (u64).
pub(crate) const UNIT_BYTES: usize = 4 + 4 + 8;

/// Bytes per pixel in the adaptive policy blob: the statistics record, then `stopped_at`,
/// `needed` and `traced` (u32).
pub(crate) const ADAPTIVE_PIXEL_BYTES: usize = PIXEL_BYTES + 3 * 4;

fn put_stats(out: &mut Vec<u8>, p: &PixelStats) {
    let mut record = [0u8; PIXEL_BYTES];
    write_stats(&mut record, p);
    out.extend_from_slice(&record);
}

/// One pixel's statistics record into `record` (`PIXEL_BYTES` long): written in place,
/// because the checkpoint of a tile is encoded again for every result merged into it and
/// a growing vector's per-value capacity checks were most of the cost.
#[inline]
fn write_stats(record: &mut [u8], p: &PixelStats) {
    record[..4].copy_from_slice(&p.passes.to_le_bytes());
    let values = [
        p.mean[0], p.mean[1], p.mean[2], p.m2[0], p.m2[1], p.m2[2], p.mean_lum, p.m2_lum,
    ];
    for (b, v) in record[4..].chunks_exact_mut(8).zip(values) {
        b.copy_from_slice(&v.to_bits().to_le_bytes());
    }
}

/// One pixel's bias record into `record` (`BIAS_BYTES` long).
fn write_bias(record: &mut [u8], b: &BiasStats) {
    record[..4].copy_from_slice(&b.passes.to_le_bytes());
    record[4..12].copy_from_slice(&b.mean.to_bits().to_le_bytes());
    record[12..20].copy_from_slice(&b.m2.to_bits().to_le_bytes());
}

fn get_bias(r: &[u8]) -> BiasStats {
    BiasStats {
        passes: u32_at(r, 0),
        mean: f64::from_bits(u64_at(r, 4)),
        m2: f64::from_bits(u64_at(r, 12)),
    }
}

/// The number of records a blob's header announces (0 if it is too short to have one).
fn announced(blob: &[u8]) -> usize {
    blob.get(1..HEADER_BYTES)
        .map_or(0, |c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]) as usize)
}

/// Whether a blob of `len` bytes holds, after `fixed` bytes, `count` records of `record`
/// bytes each followed by as many bias records (rather than the records alone).
fn has_bias_trailer(len: usize, fixed: usize, count: usize, record: usize) -> bool {
    let with_bias = (count as u64)
        .checked_mul((record + BIAS_BYTES) as u64)
        .and_then(|b| b.checked_add(fixed as u64));
    count > 0 && with_bias == Some(len as u64)
}

fn get_stats(r: &[u8]) -> PixelStats {
    let f = |i: usize| f64::from_bits(u64_at(r, 4 + 8 * i));
    PixelStats {
        passes: u32_at(r, 0),
        mean: [f(0), f(1), f(2)],
        m2: [f(3), f(4), f(5)],
        mean_lum: f(6),
        m2_lum: f(7),
    }
}

/// Encodes the adaptive policy state of a tile (format in the [module docs](super)): the
/// header, `consumed_passes` (u32), then one record per pixel, then for a tile with a bias
/// channel (vcm, ppm; [`AdaptiveTileCheckpoint::bias`]) one bias record per pixel, as
/// after the statistics blob's records.
pub(crate) fn encode_adaptive(cp: &AdaptiveTileCheckpoint) -> Vec<u8> {
    let extra = cp.bias.as_ref().map_or(0, |b| BIAS_BYTES * b.len());
    let mut out =
        Vec::with_capacity(HEADER_BYTES + 4 + ADAPTIVE_PIXEL_BYTES * cp.pixels.len() + extra);
    out.push(CHECKPOINT_FORMAT_VERSION);
    out.extend_from_slice(&(cp.pixels.len() as u32).to_le_bytes());
    out.extend_from_slice(&cp.consumed_passes.to_le_bytes());
    for p in &cp.pixels {
        put_stats(&mut out, &p.stats);
        for v in [p.stopped_at, p.needed, p.traced] {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    for b in cp.bias.iter().flatten() {
        let mut record = [0u8; BIAS_BYTES];
        write_bias(&mut record, b);
        out.extend_from_slice(&record);
    }
    out
}

/// Decodes the adaptive policy state of a tile, with its bias records when the blob has
/// them (its length says, as for [`decode_stats`]: a blob written before they existed has
/// none); the error says what is wrong. Only the layout is checked here: whether the state
/// is one the job's policy could have reached is [`tessera_farm::AdaptiveTile::restore`]'s
/// to say, with the settings at hand.
pub(crate) fn decode_adaptive(blob: &[u8]) -> Result<AdaptiveTileCheckpoint, String> {
    let count = announced(blob);
    let (blob, bias) =
        if has_bias_trailer(blob.len(), HEADER_BYTES + 4, count, ADAPTIVE_PIXEL_BYTES) {
            let (records, trailer) = blob.split_at(blob.len() - BIAS_BYTES * count);
            let bias = trailer.chunks_exact(BIAS_BYTES).map(get_bias).collect();
            (records, Some(bias))
        } else {
            (blob, None)
        };
    let Some((consumed, rest)) = blob
        .get(HEADER_BYTES..)
        .and_then(|b| b.split_first_chunk::<4>())
    else {
        return Err(format!(
            "adaptive policy blob is truncated: {} bytes, shorter than its {}-byte header",
            blob.len(),
            HEADER_BYTES + 4
        ));
    };
    // The version and count checks of the other blobs, over the header and the records.
    let mut framed = Vec::with_capacity(HEADER_BYTES + rest.len());
    framed.extend_from_slice(&blob[..HEADER_BYTES]);
    framed.extend_from_slice(rest);
    let body = records(&framed, "adaptive policy", ADAPTIVE_PIXEL_BYTES)?;
    Ok(AdaptiveTileCheckpoint {
        consumed_passes: u32::from_le_bytes(*consumed),
        pixels: body
            .chunks_exact(ADAPTIVE_PIXEL_BYTES)
            .map(|r| AdaptivePixel {
                stats: get_stats(r),
                stopped_at: u32_at(r, PIXEL_BYTES),
                needed: u32_at(r, PIXEL_BYTES + 4),
                traced: u32_at(r, PIXEL_BYTES + 8),
            })
            .collect(),
        bias,
    })
}

/// Checks an adaptive policy state against its tile: one record per pixel, no more
/// passes consumed than the plan has, bias records (if any) as [`check_bias`] wants them.
pub(crate) fn check_adaptive(
    plan: &FramePlan,
    tile: u32,
    cp: &AdaptiveTileCheckpoint,
) -> Result<(), String> {
    let pixels = plan.get_tile(tile).map_or(0, |r| r.pixel_count());
    if cp.pixels.len() != pixels {
        return Err(format!(
            "adaptive policy state has {} pixels, the tile {pixels}",
            cp.pixels.len()
        ));
    }
    if cp.consumed_passes > plan.passes {
        return Err(format!(
            "adaptive policy state consumed {} passes, the plan has {}",
            cp.consumed_passes, plan.passes
        ));
    }
    match &cp.bias {
        Some(bias) => check_bias_of(cp.pixels.iter().map(|p| p.stats.passes), bias),
        None => Ok(()),
    }
}

/// Encodes per-pixel statistics, followed by the bias records when the tile has a bias
/// channel (`bias`, one per pixel). The caller guarantees `pixels.len() <= u32::MAX` (a
/// tile has at most 256 x 256 pixels).
pub(crate) fn encode_stats(pixels: &[PixelStats], bias: Option<&[BiasStats]>) -> Vec<u8> {
    let body = PIXEL_BYTES * pixels.len();
    let extra = bias.map_or(0, |b| BIAS_BYTES * b.len());
    let mut out = vec![0u8; HEADER_BYTES + body + extra];
    out[0] = CHECKPOINT_FORMAT_VERSION;
    out[1..HEADER_BYTES].copy_from_slice(&(pixels.len() as u32).to_le_bytes());
    for (record, p) in out[HEADER_BYTES..HEADER_BYTES + body]
        .chunks_exact_mut(PIXEL_BYTES)
        .zip(pixels)
    {
        write_stats(record, p);
    }
    if let Some(bias) = bias {
        for (record, b) in out[HEADER_BYTES + body..]
            .chunks_exact_mut(BIAS_BYTES)
            .zip(bias)
        {
            write_bias(record, b);
        }
    }
    out
}

/// Encodes unit digests.
pub(crate) fn encode_units(units: &[UnitDigest]) -> Vec<u8> {
    let mut out = Vec::with_capacity(HEADER_BYTES + UNIT_BYTES * units.len());
    out.push(CHECKPOINT_FORMAT_VERSION);
    out.extend_from_slice(&(units.len() as u32).to_le_bytes());
    for u in units {
        out.extend_from_slice(&u.first_pass.to_le_bytes());
        out.extend_from_slice(&u.pass_count.to_le_bytes());
        out.extend_from_slice(&u.digest.to_le_bytes());
    }
    out
}

/// Checks the header of a blob and returns its records.
fn records<'a>(blob: &'a [u8], what: &str, record_bytes: usize) -> Result<&'a [u8], String> {
    let Some((&version, rest)) = blob.split_first() else {
        return Err(format!("{what} blob is empty"));
    };
    if version != CHECKPOINT_FORMAT_VERSION {
        return Err(format!(
            "{what} blob has format version {version}, this build reads version {CHECKPOINT_FORMAT_VERSION}"
        ));
    }
    let Some((count, body)) = rest.split_first_chunk::<4>() else {
        return Err(format!(
            "{what} blob is truncated: {} bytes, shorter than its {HEADER_BYTES}-byte header",
            blob.len()
        ));
    };
    let count = u32::from_le_bytes(*count) as usize;
    let expected = count as u64 * record_bytes as u64;
    if body.len() as u64 != expected {
        return Err(format!(
            "{what} blob holds {} bytes of records, its header announces {count} records of {record_bytes} bytes ({expected} bytes)",
            body.len()
        ));
    }
    Ok(body)
}

fn u32_at(b: &[u8], at: usize) -> u32 {
    let mut a = [0u8; 4];
    a.copy_from_slice(&b[at..at + 4]);
    u32::from_le_bytes(a)
}

fn u64_at(b: &[u8], at: usize) -> u64 {
    let mut a = [0u8; 8];
    a.copy_from_slice(&b[at..at + 8]);
    u64::from_le_bytes(a)
}

/// Statistics decoded from a blob: the pixels' and, for a tile with a bias channel, the
/// bias records.
pub(crate) type DecodedStats = (Vec<PixelStats>, Option<Vec<BiasStats>>);

/// Decodes per-pixel statistics and the bias records when the blob has them (its length
/// says: `PIXEL_BYTES` per pixel, or `PIXEL_BYTES + BIAS_BYTES`); the error says what is
/// wrong.
pub(crate) fn decode_stats(blob: &[u8]) -> Result<DecodedStats, String> {
    let count = announced(blob);
    if has_bias_trailer(blob.len(), HEADER_BYTES, count, PIXEL_BYTES) {
        let body = &blob[HEADER_BYTES..];
        let split = PIXEL_BYTES * count;
        let pixels = records(&blob[..HEADER_BYTES + split], "statistics", PIXEL_BYTES)?
            .chunks_exact(PIXEL_BYTES)
            .map(get_stats)
            .collect();
        let bias = body[split..]
            .chunks_exact(BIAS_BYTES)
            .map(get_bias)
            .collect();
        return Ok((pixels, Some(bias)));
    }
    let body = records(blob, "statistics", PIXEL_BYTES)?;
    Ok((
        body.chunks_exact(PIXEL_BYTES).map(get_stats).collect(),
        None,
    ))
}

/// Checks a tile's bias records against its pixels: one per pixel, the same passes, finite
/// values.
pub(crate) fn check_bias(pixels: &[PixelStats], bias: &[BiasStats]) -> Result<(), String> {
    check_bias_of(pixels.iter().map(|p| p.passes), bias)
}

/// [`check_bias`] against the pixels' pass counts `passes` (one per pixel).
fn check_bias_of(
    passes: impl ExactSizeIterator<Item = u32>,
    bias: &[BiasStats],
) -> Result<(), String> {
    if bias.len() != passes.len() {
        return Err(format!(
            "{} bias records for {} pixels",
            bias.len(),
            passes.len()
        ));
    }
    for (i, (b, p)) in bias.iter().zip(passes).enumerate() {
        if b.passes != p {
            return Err(format!(
                "pixel {i}'s bias record has {} passes, its statistics {p}",
                b.passes
            ));
        }
        if !(b.mean.is_finite() && b.m2.is_finite()) {
            return Err(format!("pixel {i}'s bias record is not finite"));
        }
    }
    Ok(())
}

/// Decodes unit digests; the error says what is wrong.
pub(crate) fn decode_units(blob: &[u8]) -> Result<Vec<UnitDigest>, String> {
    let body = records(blob, "unit digest", UNIT_BYTES)?;
    Ok(body
        .chunks_exact(UNIT_BYTES)
        .map(|r| UnitDigest {
            first_pass: u32_at(r, 0),
            pass_count: u32_at(r, 4),
            digest: u64_at(r, 8),
        })
        .collect())
}

/// Checks that a checkpoint fits its job: frame in range, tile in the plan, one statistic
/// per pixel, `merged_passes` within the plan, finite values, no pixel beyond
/// `merged_passes`, units tiling `0..merged_passes` in order.
pub(crate) fn check_checkpoint(
    plan: &FramePlan,
    frames: FrameRange,
    frame: u32,
    tile: u32,
    merged_passes: u32,
    pixels: &[PixelStats],
    units: &[UnitDigest],
) -> Result<(), String> {
    if !(frames.start..=frames.end).contains(&frame) {
        return Err(format!(
            "frame {frame} is outside the job's frames {}..={}",
            frames.start, frames.end
        ));
    }
    let Some(rect) = plan.get_tile(tile) else {
        return Err(format!(
            "tile {tile} does not exist (the plan has {} tiles)",
            plan.tile_count()
        ));
    };
    if pixels.len() != rect.pixel_count() {
        return Err(format!(
            "{} pixel statistics for a {}x{} tile ({} pixels)",
            pixels.len(),
            rect.width,
            rect.height,
            rect.pixel_count()
        ));
    }
    if merged_passes > plan.passes {
        return Err(format!(
            "merged_passes {merged_passes} exceeds the plan's {} passes",
            plan.passes
        ));
    }
    for (i, p) in pixels.iter().enumerate() {
        if p.passes > merged_passes {
            return Err(format!(
                "pixel {i} has {} passes, more than the tile's merged_passes {merged_passes}",
                p.passes
            ));
        }
        let finite = p
            .mean
            .iter()
            .chain(&p.m2)
            .chain([&p.mean_lum, &p.m2_lum])
            .all(|v| v.is_finite());
        if !finite {
            return Err(format!("pixel {i} has a non-finite statistic: {p:?}"));
        }
    }
    let mut next = 0u64;
    for (i, u) in units.iter().enumerate() {
        if u.pass_count == 0 || u64::from(u.first_pass) != next {
            return Err(format!(
                "unit {i} (passes {}..{}) does not continue the merged passes at {next}",
                u.first_pass,
                u64::from(u.first_pass) + u64::from(u.pass_count)
            ));
        }
        next += u64::from(u.pass_count);
    }
    if next != u64::from(merged_passes) {
        return Err(format!(
            "the units cover passes 0..{next}, merged_passes is {merged_passes}"
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn stats(n: usize) -> Vec<PixelStats> {
        (0..n)
            .map(|i| {
                let mut s = PixelStats::default();
                for k in 0..3 {
                    s.push([0.1 * i as f32, 0.3 + k as f32, 1.0 / 3.0 + i as f32]);
                }
                s
            })
            .collect()
    }

    #[test]
    fn stats_round_trip_bit_exact() {
        let mut px = stats(17);
        px[3].mean[1] = f64::from_bits(0x3ff0_0000_0000_0001);
        px[4].m2_lum = -0.0;
        px[5].mean_lum = f64::MIN_POSITIVE / 4.0; // subnormal
        let blob = encode_stats(&px, None);
        assert_eq!(blob.len(), HEADER_BYTES + 17 * PIXEL_BYTES);
        assert_eq!(blob[0], 1);
        let back = decode_stats(&blob).unwrap().0;
        assert_eq!(back.len(), px.len());
        for (a, b) in px.iter().zip(&back) {
            assert_eq!(a.passes, b.passes);
            let bits = |s: &PixelStats| {
                let mut v = vec![];
                v.extend(s.mean.map(f64::to_bits));
                v.extend(s.m2.map(f64::to_bits));
                v.push(s.mean_lum.to_bits());
                v.push(s.m2_lum.to_bits());
                v
            };
            assert_eq!(bits(a), bits(b));
        }
        assert_eq!(decode_stats(&encode_stats(&[], None)).unwrap().0, vec![]);
    }

    #[test]
    fn adaptive_state_round_trips_and_refuses_bad_blobs() {
        let cp = AdaptiveTileCheckpoint {
            consumed_passes: 12,
            pixels: stats(5)
                .into_iter()
                .enumerate()
                .map(|(i, stats)| AdaptivePixel {
                    stats,
                    stopped_at: if i == 2 { 8 } else { 0 },
                    needed: i as u32,
                    traced: 12 - i as u32,
                })
                .collect(),
            bias: None,
        };
        let blob = encode_adaptive(&cp);
        assert_eq!(blob.len(), HEADER_BYTES + 4 + 5 * ADAPTIVE_PIXEL_BYTES);
        assert_eq!(decode_adaptive(&blob).unwrap(), cp);
        let empty = AdaptiveTileCheckpoint {
            consumed_passes: 0,
            pixels: vec![],
            bias: None,
        };
        assert_eq!(decode_adaptive(&encode_adaptive(&empty)).unwrap(), empty);
        // Truncated, padded, another version.
        for (bad, says) in [
            (blob[..7].to_vec(), "truncated"),
            (blob[..blob.len() - 1].to_vec(), "announces 5 records"),
            ([blob.as_slice(), &[0]].concat(), "announces 5 records"),
            ([&[2u8], &blob[1..]].concat(), "format version 2"),
        ] {
            let e = decode_adaptive(&bad).unwrap_err();
            assert!(e.contains(says), "{e}");
            assert!(e.contains("adaptive policy"), "{e}");
        }
        let plan = FramePlan::new(16, 16, 16, 4, 8).unwrap();
        let e = check_adaptive(&plan, 0, &cp).unwrap_err();
        assert!(e.contains("5 pixels, the tile 256"), "{e}");
    }

    #[test]
    fn layout_is_little_endian() {
        let p = PixelStats {
            passes: 0x0102_0304,
            mean: [1.0, 0.0, 0.0],
            ..Default::default()
        };
        let blob = encode_stats(&[p], None);
        assert_eq!(&blob[..9], &[1, 1, 0, 0, 0, 4, 3, 2, 1]);
        assert_eq!(&blob[9..17], &1.0f64.to_bits().to_le_bytes());
        let u = encode_units(&[UnitDigest {
            first_pass: 2,
            pass_count: 3,
            digest: 0x0102_0304_0506_0708,
        }]);
        assert_eq!(
            u,
            [1, 1, 0, 0, 0, 2, 0, 0, 0, 3, 0, 0, 0, 8, 7, 6, 5, 4, 3, 2, 1]
        );
    }

    #[test]
    fn malformed_blobs_are_errors() {
        let blob = encode_stats(&stats(4), None);
        for cut in [0, 1, 4, 5, 6, blob.len() - 1] {
            let e = decode_stats(&blob[..cut]).unwrap_err();
            assert!(!e.is_empty());
        }
        let mut longer = blob.clone();
        longer.push(0);
        assert!(decode_stats(&longer).unwrap_err().contains("announces 4"));
        let mut v2 = blob.clone();
        v2[0] = 2;
        assert!(decode_stats(&v2).unwrap_err().contains("format version 2"));
        let mut huge = blob.clone();
        huge[1..5].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(decode_stats(&huge).is_err());
        let units = encode_units(&[UnitDigest {
            first_pass: 0,
            pass_count: 1,
            digest: 7,
        }]);
        assert!(decode_units(&units[..units.len() - 3]).is_err());
        assert!(decode_units(&[]).unwrap_err().contains("empty"));
    }

    #[test]
    fn checkpoints_are_checked_against_the_plan() {
        let plan = FramePlan::new(10, 6, 4, 2, 8).unwrap(); // tiles 4x4, 4x4, 2x4, 4x2, ...
        let frames = FrameRange { start: 2, end: 3 };
        let u = |first_pass, pass_count| UnitDigest {
            first_pass,
            pass_count,
            digest: 1,
        };
        let px = stats(16);
        let ok = |frame, tile, merged, px: &[PixelStats], units: &[UnitDigest]| {
            check_checkpoint(&plan, frames, frame, tile, merged, px, units)
        };
        ok(2, 0, 3, &px, &[u(0, 2), u(2, 1)]).unwrap();
        ok(3, 2, 3, &stats(8), &[u(0, 3)]).unwrap();
        ok(3, 2, 0, &[PixelStats::default(); 8], &[]).unwrap();
        assert!(ok(1, 0, 3, &px, &[u(0, 3)])
            .unwrap_err()
            .contains("frame 1"));
        assert!(ok(2, 6, 3, &px, &[u(0, 3)]).unwrap_err().contains("tile 6"));
        assert!(ok(2, 2, 3, &px, &[u(0, 3)])
            .unwrap_err()
            .contains("16 pixel"));
        assert!(ok(2, 0, 9, &px, &[u(0, 9)]).unwrap_err().contains("9"));
        assert!(ok(2, 0, 2, &px, &[u(0, 2)])
            .unwrap_err()
            .contains("3 passes"));
        assert!(ok(2, 0, 3, &px, &[u(0, 2)]).unwrap_err().contains("0..2"));
        assert!(ok(2, 0, 3, &px, &[u(0, 2), u(3, 1)])
            .unwrap_err()
            .contains("unit 1"));
        assert!(ok(2, 0, 3, &px, &[u(0, 0), u(0, 3)])
            .unwrap_err()
            .contains("unit 0"));
        let mut nan = px.clone();
        nan[5].m2[2] = f64::NAN;
        assert!(ok(2, 0, 3, &nan, &[u(0, 3)])
            .unwrap_err()
            .contains("pixel 5"));
    }

    /// A tile with a bias channel: its records follow the pixels' and round-trip bit for
    /// bit; the blob of a tile without one is unchanged; records that disagree with the
    /// pixels are refused.
    #[test]
    fn bias_records_round_trip_after_the_statistics() {
        let px = stats(5);
        let bias: Vec<BiasStats> = px
            .iter()
            .enumerate()
            .map(|(i, p)| BiasStats {
                passes: p.passes,
                mean: -0.25 * i as f64,
                m2: 0.5 + i as f64,
            })
            .collect();
        let plain = encode_stats(&px, None);
        let blob = encode_stats(&px, Some(&bias));
        assert_eq!(&blob[..plain.len()], &plain[..]);
        assert_eq!(blob.len(), plain.len() + BIAS_BYTES * px.len());
        let (back, back_bias) = decode_stats(&blob).unwrap();
        assert_eq!(back, px);
        assert_eq!(back_bias.as_deref(), Some(&bias[..]));
        assert_eq!(decode_stats(&plain).unwrap().1, None);
        check_bias(&px, &bias).unwrap();
        let mut wrong = bias.clone();
        wrong[2].passes += 1;
        assert!(check_bias(&px, &wrong).unwrap_err().contains("pixel 2"));
        assert!(check_bias(&px, &bias[1..]).is_err());
    }

    /// An adaptive policy state with bias records (vcm, ppm): they follow the pixels'
    /// records and round-trip bit for bit; the blob without them is unchanged (a blob
    /// stored before they existed decodes as before, without bias); records that disagree
    /// with the pixels are refused; a damaged length is still an error.
    #[test]
    fn adaptive_bias_records_round_trip_after_the_pixels() {
        let pixels: Vec<AdaptivePixel> = stats(5)
            .into_iter()
            .map(|stats| AdaptivePixel {
                stats,
                stopped_at: 0,
                needed: 2,
                traced: 11,
            })
            .collect();
        let bias: Vec<BiasStats> = pixels
            .iter()
            .enumerate()
            .map(|(i, p)| BiasStats {
                passes: p.stats.passes,
                mean: -0.125 * i as f64 + f64::from_bits(0x3ff0_0000_0000_0001),
                m2: 0.75 + i as f64,
            })
            .collect();
        let plain = AdaptiveTileCheckpoint {
            consumed_passes: 11,
            pixels,
            bias: None,
        };
        let cp = AdaptiveTileCheckpoint {
            bias: Some(bias.clone()),
            ..plain.clone()
        };
        let plain_blob = encode_adaptive(&plain);
        let blob = encode_adaptive(&cp);
        assert_eq!(&blob[..plain_blob.len()], &plain_blob[..]);
        assert_eq!(blob.len(), plain_blob.len() + 5 * BIAS_BYTES);
        // The trailer's records are the statistics blob's.
        let px: Vec<PixelStats> = cp.pixels.iter().map(|p| p.stats).collect();
        let stats_blob = encode_stats(&px, Some(&bias));
        assert_eq!(
            &blob[plain_blob.len()..],
            &stats_blob[stats_blob.len() - 5 * BIAS_BYTES..]
        );
        let back = decode_adaptive(&blob).unwrap();
        assert_eq!(back, cp);
        let bits = |b: &[BiasStats]| -> Vec<(u32, u64, u64)> {
            b.iter()
                .map(|b| (b.passes, b.mean.to_bits(), b.m2.to_bits()))
                .collect()
        };
        assert_eq!(bits(back.bias.as_deref().unwrap()), bits(&bias));
        assert_eq!(decode_adaptive(&plain_blob).unwrap(), plain);
        let plan = FramePlan::new(5, 1, 8, 1, 16).unwrap();
        check_adaptive(&plan, 0, &cp).unwrap();
        let mut wrong = cp.clone();
        if let Some(b) = wrong.bias.as_mut() {
            b[1].passes += 1;
        }
        let e = check_adaptive(&plan, 0, &wrong).unwrap_err();
        assert!(e.contains("pixel 1's bias record"), "{e}");
        let mut short = cp.clone();
        if let Some(b) = short.bias.as_mut() {
            b.pop();
        }
        let e = check_adaptive(&plan, 0, &short).unwrap_err();
        assert!(e.contains("4 bias records for 5 pixels"), "{e}");
        let mut nan = cp;
        if let Some(b) = nan.bias.as_mut() {
            b[4].m2 = f64::INFINITY;
        }
        let e = check_adaptive(&plan, 0, &nan).unwrap_err();
        assert!(e.contains("not finite"), "{e}");
        // Neither a whole record nor a whole trailer: refused.
        for bad in [&blob[..blob.len() - 1], &blob[..blob.len() - BIAS_BYTES]] {
            let e = decode_adaptive(bad).unwrap_err();
            assert!(e.contains("announces 5 records"), "{e}");
        }
    }
}
