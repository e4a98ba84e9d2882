//! The EXR encoded a block of rows at a time, from any source of a frame's pixel layers
//! ([`FrameRows`]), in bounded memory: the bytes are those of [`crate::encode_exr`] of the
//! same [`FrameImage`], but no layer of the whole frame is ever built.
//!
//! Why two passes for large files: an EXR starts with a table of every chunk's byte
//! offset, and a ZIP-compressed chunk's size is known only once it is compressed. The
//! first pass compresses every block and keeps the file only while it is smaller than a
//! limit (it is then returned whole, [`Exr::Whole`]); past that it keeps the header and
//! the offset table alone. The second pass ([`ExrStream::write_to`]) compresses the blocks
//! again, in the same order with the same code, and writes them after that prefix. The
//! encoder is deterministic (single-threaded, a pure function of the pixels), so the
//! second pass's chunks are the first pass's, byte for byte; the source must return the
//! same pixels both times (a snapshot, or a frame that no longer changes).
//!
//! Working memory: [`exr_working_bytes`], a few blocks of 16 rows, whatever the frame's
//! size, plus the kept file up to the caller's limit.

use std::io::{Seek, SeekFrom, Write};

use exr::block::writer::ChunksWriter;
use exr::block::BlockIndex;
use exr::meta::attribute::{AttributeValue, Text};
use exr::meta::Headers;
use exr::prelude::{
    AnyChannel, AnyChannels, Encoding, FlatSamples, Image, Layer, LayerAttributes, WritableImage,
};
use tessera_farm::FrameImage;

use crate::{ImageError, METADATA_ATTRIBUTE};

/// The layers of one pixel as [`FrameImage`] holds them (44 bytes).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Pixel {
    /// Mean radiance.
    pub mean: [f32; 3],
    /// Estimated variance of the mean (0 with fewer than 2 passes).
    pub variance_of_mean: [f32; 3],
    /// Merged passes.
    pub passes: u32,
    /// Samples per pixel traced.
    pub samples: u32,
    /// Relative error (0 with fewer than 2 passes).
    pub relative_error: f32,
    /// The bias layers ([`FrameImage::bias`]): the mean bias estimate and its variance of
    /// the mean; zero when the frame has none ([`FrameRows::has_bias`]).
    pub bias: [f32; 2],
}

/// A frame's pixel layers, read a row or a pixel at a time: a [`FrameImage`], or a
/// frame's merge state read in place (the coordinator), so that encoding never copies
/// the whole frame.
pub trait FrameRows {
    /// Width in pixels.
    fn width(&self) -> u32;
    /// Height in pixels.
    fn height(&self) -> u32;
    /// Pixel (`x`, `y`), inside the frame.
    fn pixel(&self, x: u32, y: u32) -> Pixel;
    /// Whether the frame has bias layers (a biased render, [`FrameImage::bias`]): the EXR
    /// then has the channels `bias.Y` and `bias.variance.Y`, and the error estimate adds
    /// the bias. False by default.
    fn has_bias(&self) -> bool {
        false
    }
    /// Row `y` into `out` (cleared first); the default reads it pixel by pixel.
    fn row(&self, y: u32, out: &mut Vec<Pixel>) {
        out.clear();
        out.extend((0..self.width()).map(|x| self.pixel(x, y)));
    }
}

impl FrameRows for FrameImage {
    fn width(&self) -> u32 {
        self.width
    }
    fn height(&self) -> u32 {
        self.height
    }
    fn pixel(&self, x: u32, y: u32) -> Pixel {
        let p = y as usize * self.width as usize + x as usize;
        Pixel {
            mean: self.mean[p],
            variance_of_mean: self.variance_of_mean[p],
            passes: self.passes[p],
            samples: self.samples[p],
            relative_error: self.relative_error[p],
            bias: self.bias.as_ref().map_or([0.0; 2], |b| b[p]),
        }
    }
    fn has_bias(&self) -> bool {
        self.bias.is_some()
    }
}

/// A frame of `width` x `height` pixels that are all `pixel` (a frame nothing was merged
/// into yet, or the render plan's black frame), held in no memory.
#[derive(Clone, Copy, Debug)]
pub struct UniformRows {
    /// Width.
    pub width: u32,
    /// Height.
    pub height: u32,
    /// Every pixel.
    pub pixel: Pixel,
}

impl FrameRows for UniformRows {
    fn width(&self) -> u32 {
        self.width
    }
    fn height(&self) -> u32 {
        self.height
    }
    fn pixel(&self, _: u32, _: u32) -> Pixel {
        self.pixel
    }
}

/// [`FrameImage::error_estimate`] of the frame `rows` holds, without building it: the
/// same pixel values, so the same number (the stop verdict an EXR header states).
pub fn error_estimate(
    rows: &dyn FrameRows,
    estimator: tessera_farm::ErrorEstimator,
) -> Option<f64> {
    let (w, h) = (rows.width(), rows.height());
    if w == 0 || h == 0 {
        return None;
    }
    let mut line = Vec::new();
    for y in 0..h {
        rows.row(y, &mut line);
        if line.iter().any(|p| p.passes < 2) {
            return None;
        }
    }
    let pixel = |x: usize, y: usize| {
        let p = rows.pixel(x as u32, y as u32);
        let m = tessera_farm::luminance(p.mean.map(f64::from));
        let se = f64::from(p.relative_error) * (m.max(0.0) + tessera_farm::REL_EPS);
        Some((m, se * se, p.passes))
    };
    // As `FrameImage::error_estimate`: the estimator's own biased form, so an unbiased
    // adaptive render of vcm or ppm pools its spread here as it does there.
    let e = if rows.has_bias() {
        estimator.image_error_biased(w as usize, h as usize, |x, y| {
            let (m, v, k) = pixel(x, y)?;
            let [b, vb] = rows.pixel(x as u32, y as u32).bias;
            Some((m, v, k, f64::from(b), f64::from(vb)))
        })
    } else {
        estimator.image_error(w as usize, h as usize, pixel)
    };
    e.is_finite().then_some(e)
}

/// The EXR channels, each a function of a pixel and its pooled variance; the last
/// [`BIAS_CHANNELS`] only in the files of frames with bias layers ([`FrameRows::has_bias`]).
const CHANNELS: [&str; 14] = [
    "R",
    "G",
    "B",
    "variance.R",
    "variance.G",
    "variance.B",
    "pooled_variance.R",
    "pooled_variance.G",
    "pooled_variance.B",
    "relerr.Y",
    "passes.Y",
    "samples.Y",
    "bias.Y",
    "bias.variance.Y",
];

/// The bias channels at the end of [`CHANNELS`].
const BIAS_CHANNELS: usize = 2;

/// Channel `c` (an index into [`CHANNELS`]) of a pixel with pooled variance `pooled`.
fn channel_value(c: usize, p: &Pixel, pooled: &[f32; 3]) -> f32 {
    match c {
        0..=2 => p.mean[c],
        3..=5 => p.variance_of_mean[c - 3],
        6..=8 => pooled[c - 6],
        9 => p.relative_error,
        10 => p.passes as f32,
        11 => p.samples as f32,
        12 => p.bias[0],
        _ => p.bias[1],
    }
}

/// The headers [`crate::encode_exr`] writes for a `width` x `height` frame: inferred by
/// the exr crate from the same layer description, with no pixel data.
fn headers(
    width: usize,
    height: usize,
    metadata: Option<&str>,
    bias: bool,
) -> Result<Headers, ImageError> {
    let used = if bias {
        CHANNELS.len()
    } else {
        CHANNELS.len() - BIAS_CHANNELS
    };
    let channels: Vec<AnyChannel<FlatSamples>> = CHANNELS[..used]
        .iter()
        .map(|name| AnyChannel::new(*name, FlatSamples::F32(Vec::new())))
        .collect();
    let mut attributes = LayerAttributes::named("tessera");
    if let Some(m) = metadata {
        let text = Text::new_or_none(m)
            .ok_or_else(|| ImageError::Exr("metadata is not Latin-1 text".into()))?;
        attributes
            .other
            .insert(Text::from(METADATA_ATTRIBUTE), AttributeValue::Text(text));
    }
    let layer = Layer::new(
        (width, height),
        attributes,
        Encoding::SMALL_LOSSLESS,
        AnyChannels::sort(channels.into()),
    );
    Ok(Image::from_layer(layer)
        .write()
        .non_parallel()
        .infer_meta_data())
}

/// `FrameImage::interval_variance` of row `y` from rows `y - 1`, `y`, `y + 1` (`None`
/// outside the frame): the same sums in the same order, so the same bits.
fn pooled_row(prev: Option<&[Pixel]>, cur: &[Pixel], next: Option<&[Pixel]>, out: &mut [[f32; 3]]) {
    let w = cur.len();
    let rows = [prev, Some(cur), next];
    for (x, (o, p)) in out.iter_mut().zip(cur).enumerate() {
        *o = [0.0; 3];
        if p.passes < 2 {
            continue;
        }
        let (mut sum, mut dof) = ([0.0f64; 3], 0.0f64);
        for row in rows.iter().flatten() {
            for q in &row[x.saturating_sub(1)..(x + 2).min(w)] {
                let n = f64::from(q.passes);
                if n < 2.0 {
                    continue;
                }
                for (c, s) in sum.iter_mut().enumerate() {
                    *s += (n - 1.0) * n * f64::from(q.variance_of_mean[c]);
                }
                dof += n - 1.0;
            }
        }
        let own = f64::from(p.passes);
        *o = tessera_farm::pooled_interval_variance(sum, dof, own);
    }
}

/// The uncompressed bytes of one scan-line block, as the exr crate lays them out: for
/// each row, each channel's samples in the header's (sorted) channel order, native-endian.
struct BlockMaker<'a> {
    rows: &'a dyn FrameRows,
    /// Index into [`CHANNELS`] of each header channel, in header order.
    order: Vec<usize>,
    window: Vec<Vec<Pixel>>,
    pooled: Vec<[f32; 3]>,
}

impl BlockMaker<'_> {
    fn block(&mut self, index: BlockIndex) -> Vec<u8> {
        let (w, h) = (self.rows.width() as usize, self.rows.height() as usize);
        let y0 = index.pixel_position.y();
        let lines = index.pixel_size.y();
        // Rows y0 - 1 ..= y0 + lines, clipped to the frame: the 3x3 pooling's neighbours.
        let first = y0.saturating_sub(1);
        let end = (y0 + lines + 1).min(h);
        self.window.resize_with(end - first, Vec::new);
        for (i, y) in (first..end).enumerate() {
            self.rows.row(y as u32, &mut self.window[i]);
        }
        self.pooled.resize(w, [0.0; 3]);
        let mut data = Vec::with_capacity(lines * w * CHANNELS.len() * 4);
        for y in y0..y0 + lines {
            let i = y - first;
            let prev = (y > 0).then(|| self.window[i - 1].as_slice());
            let next = (y + 1 < h).then(|| self.window[i + 1].as_slice());
            pooled_row(prev, &self.window[i], next, &mut self.pooled);
            for &c in &self.order {
                for (p, pooled) in self.window[i].iter().zip(&self.pooled) {
                    data.extend_from_slice(&channel_value(c, p, pooled).to_ne_bytes());
                }
            }
        }
        data
    }
}

/// Runs the exr crate's writer over `sink`, with blocks made from `rows`.
fn write_blocks<W: Write + Seek>(
    rows: &dyn FrameRows,
    headers: Headers,
    sink: W,
) -> Result<(), ImageError> {
    let order = headers[0]
        .channels
        .list
        .iter()
        .map(|c| {
            let name = c.name.to_string();
            CHANNELS
                .iter()
                .position(|n| *n == name)
                .ok_or(ImageError::MissingChannel(name))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let mut maker = BlockMaker {
        rows,
        order,
        window: Vec::new(),
        pooled: Vec::new(),
    };
    exr::block::write(sink, headers, true, |meta, writer| {
        let blocks = meta.collect_ordered_block_data(|index| maker.block(index));
        writer
            .on_progress(|_| ())
            .compress_all_blocks_sequential(&meta, blocks)
    })
    .map_err(|e| ImageError::Exr(e.to_string()))
}

/// Bytes the encoder holds besides the kept file, for a frame `width` pixels wide: the
/// row window (18 rows of 44 B pixels), the uncompressed block (16 rows of at most 56 B:
/// 14 channels with the bias layers) and the ZIP compressor's copies of it (at most three
/// more), with 64 KiB of slack.
pub fn exr_working_bytes(width: u32) -> u64 {
    let w = u64::from(width);
    18 * w * 44 + 4 * 16 * w * 56 + (64 << 10)
}

/// An encoded EXR: whole, or its header and offset table with the rest still to write.
pub enum Exr {
    /// The whole file (it fit the limit).
    Whole(Vec<u8>),
    /// A file larger than the limit.
    Stream(ExrStream),
}

/// The start of an EXR larger than the limit it was encoded with: the header and offset
/// table; [`ExrStream::write_to`] writes the whole file.
pub struct ExrStream {
    prefix: Vec<u8>,
    len: u64,
    metadata: Option<String>,
}

impl ExrStream {
    /// The file's length in bytes.
    pub fn len(&self) -> u64 {
        self.len
    }

    /// Whether the file is empty (never: it has a header).
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Writes the whole file to `out`, compressing the blocks of `rows` again; `rows` must
    /// hold the pixels it held when this was encoded.
    pub fn write_to(&self, rows: &dyn FrameRows, out: &mut dyn Write) -> Result<(), ImageError> {
        let io = |e: std::io::Error| ImageError::Exr(e.to_string());
        out.write_all(&self.prefix).map_err(io)?;
        let headers = headers(
            rows.width() as usize,
            rows.height() as usize,
            self.metadata.as_deref(),
            rows.has_bias(),
        )?;
        let mut sink = StreamSink {
            out: &mut *out,
            skip: self.prefix.len() as u64,
            pos: 0,
            written: self.prefix.len() as u64,
        };
        write_blocks(rows, headers, &mut sink)?;
        if sink.written != self.len {
            return Err(ImageError::Exr(format!(
                "the second pass wrote {} bytes, the first {}: the frame changed while it \
                 was encoded",
                sink.written, self.len
            )));
        }
        out.flush().map_err(io)
    }
}

/// Encodes the EXR of `rows` (the bytes of [`crate::encode_exr`] of the same image),
/// whole if it is at most `keep` bytes long, else as an [`ExrStream`].
pub fn encode_exr_rows(
    rows: &dyn FrameRows,
    metadata: Option<&str>,
    keep: usize,
) -> Result<Exr, ImageError> {
    let headers = headers(
        rows.width() as usize,
        rows.height() as usize,
        metadata,
        rows.has_bias(),
    )?;
    let chunks: usize = headers.iter().map(|h| h.chunk_count).sum();
    // The header and offset table are always kept: a few KiB of text and 8 B per 16 rows.
    let minimum = 8 * chunks + metadata.map_or(0, str::len) + (64 << 10);
    let mut sink = CaptureSink {
        buf: Vec::new(),
        keep: keep.max(minimum),
        pos: 0,
        len: 0,
        table: None,
    };
    write_blocks(rows, headers, &mut sink)?;
    if sink.len <= keep as u64 {
        sink.buf.truncate(sink.len as usize);
        return Ok(Exr::Whole(sink.buf));
    }
    let start = sink
        .table
        .ok_or_else(|| ImageError::Exr("the writer did not write an offset table".into()))?;
    let prefix_len = start as usize + 8 * chunks;
    if prefix_len > sink.buf.len() {
        return Err(ImageError::Exr("the EXR header is too large".into()));
    }
    sink.buf.truncate(prefix_len);
    Ok(Exr::Stream(ExrStream {
        prefix: sink.buf,
        len: sink.len,
        metadata: metadata.map(str::to_string),
    }))
}

/// A writer target that keeps the bytes at positions below `keep` and counts the rest;
/// `table` is where the writer seeked back to (the offset table, written last).
struct CaptureSink {
    buf: Vec<u8>,
    keep: usize,
    pos: u64,
    len: u64,
    table: Option<u64>,
}

impl Write for CaptureSink {
    fn write(&mut self, data: &[u8]) -> std::io::Result<usize> {
        let start = self.pos as usize;
        if start < self.keep {
            let end = (start + data.len()).min(self.keep);
            if self.buf.len() < end {
                self.buf.resize(end, 0);
            }
            self.buf[start..end].copy_from_slice(&data[..end - start]);
        }
        self.pos += data.len() as u64;
        self.len = self.len.max(self.pos);
        Ok(data.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

impl Seek for CaptureSink {
    fn seek(&mut self, to: SeekFrom) -> std::io::Result<u64> {
        self.pos = seek_target(to)?;
        self.table.get_or_insert(self.pos);
        Ok(self.pos)
    }
}

/// A writer target that forwards the bytes at positions from `skip` on (written in order:
/// the chunks) and drops the rest (the header, and the offset table the writer fills in
/// last, both already written from the first pass).
struct StreamSink<W> {
    out: W,
    skip: u64,
    pos: u64,
    written: u64,
}

impl<W: Write> Write for StreamSink<W> {
    fn write(&mut self, data: &[u8]) -> std::io::Result<usize> {
        let end = self.pos + data.len() as u64;
        if end > self.skip {
            let from = self.skip.saturating_sub(self.pos) as usize;
            if self.pos.max(self.skip) != self.written {
                return Err(std::io::Error::other("EXR chunks out of order"));
            }
            self.out.write_all(&data[from..])?;
            self.written = end;
        }
        self.pos = end;
        Ok(data.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.out.flush()
    }
}

impl<W> Seek for StreamSink<W> {
    fn seek(&mut self, to: SeekFrom) -> std::io::Result<u64> {
        self.pos = seek_target(to)?;
        Ok(self.pos)
    }
}

/// The exr writer seeks only to absolute positions.
fn seek_target(to: SeekFrom) -> std::io::Result<u64> {
    match to {
        SeekFrom::Start(p) => Ok(p),
        _ => Err(std::io::Error::other("only absolute seeks are supported")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// splitmix64.
    struct Rng(u64);
    impl Rng {
        fn next(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            z ^ (z >> 31)
        }
        fn f(&mut self) -> f32 {
            (self.next() >> 40) as f32 / (1u64 << 24) as f32
        }
    }

    /// An irregular image: some pixels with fewer than 2 passes, varying layers.
    fn image(w: u32, h: u32, seed: u64) -> FrameImage {
        let mut r = Rng(seed);
        let n = (w * h) as usize;
        let mut img = FrameImage {
            width: w,
            height: h,
            mean: Vec::new(),
            variance_of_mean: Vec::new(),
            passes: Vec::new(),
            samples: Vec::new(),
            relative_error: Vec::new(),
            bias: None,
        };
        for _ in 0..n {
            let passes = (r.next() % 6) as u32;
            img.mean.push([r.f() * 3.0, r.f(), r.f() * 0.1]);
            let var = if passes >= 2 {
                [r.f() * 0.01; 3]
            } else {
                [0.0; 3]
            };
            img.variance_of_mean.push(var);
            img.passes.push(passes);
            img.samples.push(passes * 16);
            img.relative_error
                .push(if passes >= 2 { r.f() } else { 0.0 });
        }
        img
    }

    /// Today's encoder: the exr crate's high-level writer over whole-frame channels, as
    /// `encode_exr` was written before it went through [`encode_exr_rows`]. The contract
    /// the row encoder must keep, byte for byte.
    fn reference(img: &FrameImage, metadata: Option<&str>) -> Vec<u8> {
        use exr::prelude::*;
        let n = (img.width as usize) * (img.height as usize);
        let pooled = img.interval_variance();
        let chan = |name: &str, f: &dyn Fn(usize) -> f32| -> AnyChannel<FlatSamples> {
            AnyChannel::new(name, FlatSamples::F32((0..n).map(f).collect()))
        };
        let channels = vec![
            chan("R", &|i| img.mean[i][0]),
            chan("G", &|i| img.mean[i][1]),
            chan("B", &|i| img.mean[i][2]),
            chan("variance.R", &|i| img.variance_of_mean[i][0]),
            chan("variance.G", &|i| img.variance_of_mean[i][1]),
            chan("variance.B", &|i| img.variance_of_mean[i][2]),
            chan("pooled_variance.R", &|i| pooled[i][0]),
            chan("pooled_variance.G", &|i| pooled[i][1]),
            chan("pooled_variance.B", &|i| pooled[i][2]),
            chan("relerr.Y", &|i| img.relative_error[i]),
            chan("passes.Y", &|i| img.passes[i] as f32),
            chan("samples.Y", &|i| img.samples[i] as f32),
        ];
        let mut channels = channels;
        if let Some(b) = &img.bias {
            channels.push(chan("bias.Y", &|i| b[i][0]));
            channels.push(chan("bias.variance.Y", &|i| b[i][1]));
        }
        let mut attributes = LayerAttributes::named("tessera");
        if let Some(m) = metadata {
            attributes.other.insert(
                Text::from(METADATA_ATTRIBUTE),
                AttributeValue::Text(Text::new_or_none(m).unwrap()),
            );
        }
        let layer = Layer::new(
            (img.width as usize, img.height as usize),
            attributes,
            Encoding::SMALL_LOSSLESS,
            AnyChannels::sort(channels.into()),
        );
        let mut out = std::io::Cursor::new(Vec::new());
        Image::from_layer(layer)
            .write()
            .non_parallel()
            .to_buffered(&mut out)
            .unwrap();
        out.into_inner()
    }

    fn streamed(rows: &dyn FrameRows, metadata: Option<&str>, keep: usize) -> (Vec<u8>, bool) {
        match encode_exr_rows(rows, metadata, keep).unwrap() {
            Exr::Whole(b) => (b, false),
            Exr::Stream(s) => {
                let mut out = Vec::new();
                s.write_to(rows, &mut out).unwrap();
                assert_eq!(out.len() as u64, s.len());
                (out, true)
            }
        }
    }

    #[test]
    fn row_encoder_is_byte_identical_to_the_whole_frame_encoder() {
        let meta = r#"{"settings":{"seed":3}}"#;
        // Heights around the 16-row block, widths of one pixel and odd ones.
        for (i, (w, h)) in [(1, 1), (7, 5), (33, 16), (33, 17), (64, 47), (130, 90)]
            .into_iter()
            .enumerate()
        {
            let img = image(w, h, 11 + i as u64);
            for metadata in [None, Some(meta)] {
                let want = reference(&img, metadata);
                assert_eq!(crate::encode_exr(&img, metadata).unwrap(), want, "{w}x{h}");
                // Whole, and streamed in two passes with only the header kept.
                let (whole, s) = streamed(&img, metadata, usize::MAX);
                assert!(!s);
                assert_eq!(whole, want, "{w}x{h} whole");
                let (stream, s) = streamed(&img, metadata, 0);
                assert!(s, "{w}x{h} was not streamed");
                assert_eq!(stream, want, "{w}x{h} streamed");
            }
        }
    }

    #[test]
    fn uniform_rows_are_the_black_and_empty_images() {
        use tessera_farm::FramePlan;
        let plan = FramePlan::new(70, 40, 16, 4, 8).unwrap();
        let black = FrameImage::black(&plan);
        let rows = UniformRows {
            width: 70,
            height: 40,
            pixel: Pixel {
                passes: plan.passes,
                samples: plan.spp(),
                ..Pixel::default()
            },
        };
        assert_eq!(streamed(&rows, None, 0).0, reference(&black, None));
    }

    #[test]
    fn error_estimate_matches_the_frame_image() {
        let mut img = image(40, 30, 5);
        // Every pixel estimated, else both say None.
        assert_eq!(
            error_estimate(&img, tessera_farm::ErrorEstimator::Robust),
            None
        );
        img.passes.iter_mut().for_each(|p| *p = (*p).max(2));
        for e in [
            tessera_farm::ErrorEstimator::Robust,
            tessera_farm::ErrorEstimator::PooledPerPass,
        ] {
            let want = img.error_estimate(e);
            assert!(want.is_some());
            assert_eq!(error_estimate(&img, e), want);
        }
    }

    /// A biased render's bias layers: the channels `bias.Y` and `bias.variance.Y`, whole
    /// and streamed, read back as written; the estimate from the rows is the image's,
    /// and larger than the same image's without them.
    #[test]
    fn bias_layers_are_written_and_estimated() {
        let mut img = image(40, 30, 9);
        img.passes.iter_mut().for_each(|p| *p = (*p).max(2));
        let plain = img.error_estimate(tessera_farm::ErrorEstimator::Robust);
        img.bias = Some(
            (0..img.mean.len())
                .map(|i| [0.3 * (i % 7) as f32 - 0.9, 1e-3 * (i % 3) as f32])
                .collect(),
        );
        let want = reference(&img, Some("{}"));
        assert_eq!(streamed(&img, Some("{}"), usize::MAX).0, want);
        assert_eq!(streamed(&img, Some("{}"), 0).0, want);
        let back = crate::read_exr(&want).unwrap();
        let layer = back.get("bias.Y").unwrap();
        let bias = img.bias.as_ref().unwrap();
        assert!(layer.iter().zip(bias).all(|(a, b)| *a == b[0]));
        assert!(back.get("bias.variance.Y").is_ok());
        let with = img.error_estimate(tessera_farm::ErrorEstimator::Robust);
        assert_eq!(
            error_estimate(&img, tessera_farm::ErrorEstimator::Robust),
            with
        );
        assert!(with.unwrap() > plain.unwrap());
        // The pooled estimator (unbiased adaptive renders of vcm and ppm) adds the term to
        // its pooled spread, from the rows as from the image.
        let pooled = img.error_estimate(tessera_farm::ErrorEstimator::PooledPerPass);
        assert_eq!(
            error_estimate(&img, tessera_farm::ErrorEstimator::PooledPerPass),
            pooled
        );
        assert_ne!(pooled, with);
        // Without bias layers the file has no such channels.
        img.bias = None;
        let back = crate::read_exr(&reference(&img, None)).unwrap();
        assert!(back.get("bias.Y").is_err());
    }

    #[test]
    fn a_source_that_changes_between_passes_is_an_error_not_a_corrupt_file() {
        struct Changing(std::cell::Cell<bool>, FrameImage);
        impl FrameRows for Changing {
            fn width(&self) -> u32 {
                self.1.width
            }
            fn height(&self) -> u32 {
                self.1.height
            }
            fn pixel(&self, x: u32, y: u32) -> Pixel {
                let mut p = self.1.pixel(x, y);
                if self.0.get() {
                    // Incompressible where the first pass saw constants.
                    p.mean[0] = (x.wrapping_mul(2_654_435_761) ^ y.wrapping_mul(40_503)) as f32;
                }
                p
            }
        }
        let img = FrameImage {
            mean: vec![[0.5; 3]; 64 * 64],
            ..image(64, 64, 1)
        };
        let src = Changing(std::cell::Cell::new(false), img);
        let Exr::Stream(s) = encode_exr_rows(&src, None, 0).unwrap() else {
            panic!("not streamed");
        };
        src.0.set(true);
        let mut out = Vec::new();
        assert!(s.write_to(&src, &mut out).is_err());
    }
}
