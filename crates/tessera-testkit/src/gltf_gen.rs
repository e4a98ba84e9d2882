//! Builds small glTF 2.0 documents programmatically for the import and rendering tests:
//! JSON with one binary buffer, written either as `.gltf` with an embedded base64 `data:`
//! URI, as `.gltf` plus an external `.bin`, or as `.glb` ([`glb`] packs any JSON and
//! binary chunk into a GLB container).

use serde_json::{json, Value};
use std::path::Path;

/// A glTF document under construction: the JSON and the bytes of buffer 0.
pub struct Gen {
    /// The document JSON (without `buffers`, which the writers add).
    pub doc: Value,
    /// Contents of buffer 0.
    pub bin: Vec<u8>,
}

impl Default for Gen {
    fn default() -> Self {
        Self::new()
    }
}

impl Gen {
    /// An empty document with one default scene.
    pub fn new() -> Self {
        Gen {
            doc: json!({
                "asset": {"version": "2.0", "generator": "tessera-scene tests"},
                "scene": 0,
                "scenes": [{"nodes": []}],
            }),
            bin: Vec::new(),
        }
    }

    /// Appends `value` to the top-level array `key` and returns its index.
    pub fn push(&mut self, key: &str, value: Value) -> usize {
        let array = self.doc[key].as_array_mut();
        match array {
            Some(a) => {
                a.push(value);
                a.len() - 1
            }
            None => {
                self.doc[key] = json!([value]);
                0
            }
        }
    }

    /// Declares an extension in `extensionsUsed`.
    pub fn uses(&mut self, extension: &str) {
        let used = self.doc["extensionsUsed"]
            .as_array()
            .cloned()
            .unwrap_or_default();
        if !used.iter().any(|e| e == extension) {
            self.push("extensionsUsed", json!(extension));
        }
    }

    /// Appends bytes (4-byte aligned) to buffer 0 and returns a new bufferView on them.
    pub fn view(&mut self, bytes: &[u8]) -> usize {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        let offset = self.bin.len();
        self.bin.extend_from_slice(bytes);
        self.push(
            "bufferViews",
            json!({"buffer": 0, "byteOffset": offset, "byteLength": bytes.len()}),
        )
    }

    /// A VEC3 FLOAT accessor with `min`/`max` (as POSITION requires).
    pub fn positions(&mut self, p: &[[f32; 3]]) -> usize {
        let bytes: Vec<u8> = p.iter().flatten().flat_map(|v| v.to_le_bytes()).collect();
        let view = self.view(&bytes);
        let min: Vec<f32> = (0..3)
            .map(|j| p.iter().map(|v| v[j]).fold(f32::INFINITY, f32::min))
            .collect();
        let max: Vec<f32> = (0..3)
            .map(|j| p.iter().map(|v| v[j]).fold(f32::NEG_INFINITY, f32::max))
            .collect();
        self.push(
            "accessors",
            json!({"bufferView": view, "componentType": 5126, "count": p.len(), "type": "VEC3",
                   "min": min, "max": max}),
        )
    }

    /// A VEC3 FLOAT accessor (normals).
    pub fn vec3(&mut self, p: &[[f32; 3]]) -> usize {
        let bytes: Vec<u8> = p.iter().flatten().flat_map(|v| v.to_le_bytes()).collect();
        let view = self.view(&bytes);
        self.push(
            "accessors",
            json!({"bufferView": view, "componentType": 5126, "count": p.len(), "type": "VEC3"}),
        )
    }

    /// A VEC2 FLOAT accessor (texture coordinates).
    pub fn vec2(&mut self, p: &[[f32; 2]]) -> usize {
        let bytes: Vec<u8> = p.iter().flatten().flat_map(|v| v.to_le_bytes()).collect();
        let view = self.view(&bytes);
        self.push(
            "accessors",
            json!({"bufferView": view, "componentType": 5126, "count": p.len(), "type": "VEC2"}),
        )
    }

    /// A SCALAR UNSIGNED_SHORT index accessor.
    pub fn indices_u16(&mut self, i: &[u16]) -> usize {
        let bytes: Vec<u8> = i.iter().flat_map(|v| v.to_le_bytes()).collect();
        let view = self.view(&bytes);
        self.push(
            "accessors",
            json!({"bufferView": view, "componentType": 5123, "count": i.len(), "type": "SCALAR"}),
        )
    }

    /// A SCALAR UNSIGNED_INT index accessor.
    pub fn indices_u32(&mut self, i: &[u32]) -> usize {
        let bytes: Vec<u8> = i.iter().flat_map(|v| v.to_le_bytes()).collect();
        let view = self.view(&bytes);
        self.push(
            "accessors",
            json!({"bufferView": view, "componentType": 5125, "count": i.len(), "type": "SCALAR"}),
        )
    }

    /// A mesh with one triangle primitive; returns the mesh index.
    pub fn triangle_mesh(
        &mut self,
        name: &str,
        positions: &[[f32; 3]],
        indices: Option<&[u16]>,
        material: Option<usize>,
    ) -> usize {
        let pos = self.positions(positions);
        let mut prim = json!({"attributes": {"POSITION": pos}});
        if let Some(i) = indices {
            prim["indices"] = json!(self.indices_u16(i));
        }
        if let Some(m) = material {
            prim["material"] = json!(m);
        }
        self.push("meshes", json!({"name": name, "primitives": [prim]}))
    }

    /// Adds a node and returns its index (not yet in the scene).
    pub fn node(&mut self, node: Value) -> usize {
        self.push("nodes", node)
    }

    /// Adds a node as a root of scene 0 and returns its index.
    pub fn root(&mut self, node: Value) -> usize {
        let i = self.node(node);
        self.doc["scenes"][0]["nodes"]
            .as_array_mut()
            .unwrap()
            .push(json!(i));
        i
    }

    /// Adds a `KHR_lights_punctual` light and returns its index.
    pub fn light(&mut self, light: Value) -> usize {
        self.uses("KHR_lights_punctual");
        let lights = &mut self.doc["extensions"]["KHR_lights_punctual"]["lights"];
        if lights.is_null() {
            *lights = json!([]);
        }
        let a = lights.as_array_mut().unwrap();
        a.push(light);
        a.len() - 1
    }

    /// The document with buffer 0 set to `uri` (or to the GLB chunk when `None`).
    pub fn json_with_buffer(&self, uri: Option<String>) -> Value {
        let mut doc = self.doc.clone();
        if !self.bin.is_empty() {
            let mut buffer = json!({"byteLength": self.bin.len()});
            if let Some(uri) = uri {
                buffer["uri"] = json!(uri);
            }
            doc["buffers"] = json!([buffer]);
        }
        doc
    }

    /// `.gltf` JSON with the buffer embedded as a base64 data URI.
    pub fn gltf(&self) -> Vec<u8> {
        let uri = format!("data:application/octet-stream;base64,{}", base64(&self.bin));
        serde_json::to_vec_pretty(&self.json_with_buffer(Some(uri))).unwrap()
    }

    /// `.glb` with the buffer in the BIN chunk.
    pub fn glb(&self) -> Vec<u8> {
        glb(
            &serde_json::to_vec(&self.json_with_buffer(None)).unwrap(),
            &self.bin,
        )
    }

    /// Writes `name.gltf` referring to the external `bin_uri` and writes the buffer to
    /// `bin_file` (both in `dir`); returns the .gltf path.
    pub fn write_external(
        &self,
        dir: &Path,
        name: &str,
        bin_uri: &str,
        bin_file: Option<&str>,
    ) -> std::path::PathBuf {
        std::fs::create_dir_all(dir).unwrap();
        if let Some(f) = bin_file {
            std::fs::write(dir.join(f), &self.bin).unwrap();
        }
        let path = dir.join(name);
        let json = serde_json::to_vec_pretty(&self.json_with_buffer(Some(bin_uri.into()))).unwrap();
        std::fs::write(&path, json).unwrap();
        path
    }
}

/// Assembles a GLB container from JSON and binary chunk contents (spec "GLB File Format
/// Specification"): 12-byte header, JSON chunk padded with spaces, BIN chunk padded with
/// zeros.
pub fn glb(json: &[u8], bin: &[u8]) -> Vec<u8> {
    let mut json = json.to_vec();
    while !json.len().is_multiple_of(4) {
        json.push(b' ');
    }
    let mut bin = bin.to_vec();
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    let total = 12 + 8 + json.len() + if bin.is_empty() { 0 } else { 8 + bin.len() };
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(json.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&json);
    if !bin.is_empty() {
        out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
        out.extend_from_slice(b"BIN\0");
        out.extend_from_slice(&bin);
    }
    out
}

/// Standard base64 with padding (RFC 4648).
pub fn base64(bytes: &[u8]) -> String {
    const ALPHABET: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for chunk in bytes.chunks(3) {
        let b = [
            chunk[0],
            *chunk.get(1).unwrap_or(&0),
            *chunk.get(2).unwrap_or(&0),
        ];
        let n = (u32::from(b[0]) << 16) | (u32::from(b[1]) << 8) | u32::from(b[2]);
        for k in 0..4 {
            if k <= chunk.len() {
                out.push(ALPHABET[((n >> (18 - 6 * k)) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

/// Encodes a Radiance `.hdr` (RGBE) image of `width` x `height` texels, row by row from
/// the top, each texel `radiance(x, y)` (linear RGB, non-negative), in flat scanlines
/// (no run-length encoding): the environment images of the lighting tests. Keep the
/// channels of a texel within a factor of about 100 of each other, so no texel encodes
/// as the old format's run marker (1, 1, 1, e).
pub fn radiance_hdr(width: u32, height: u32, radiance: impl Fn(u32, u32) -> [f32; 3]) -> Vec<u8> {
    let mut out =
        format!("#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y {height} +X {width}\n").into_bytes();
    for y in 0..height {
        for x in 0..width {
            let c = radiance(x, y);
            let m = c[0].max(c[1]).max(c[2]);
            if m < 1e-32 {
                out.extend_from_slice(&[0, 0, 0, 0]);
                continue;
            }
            // m = mantissa * 2^e with the mantissa in [0.5, 1) (C's frexp).
            let mut e = m.log2().floor() as i32 + 1;
            let mut mantissa = m / 2f32.powi(e);
            while mantissa >= 1.0 {
                mantissa /= 2.0;
                e += 1;
            }
            while mantissa < 0.5 {
                mantissa *= 2.0;
                e -= 1;
            }
            let scale = mantissa * 256.0 / m;
            let byte = |v: f32| (v * scale).clamp(0.0, 255.0) as u8;
            out.extend_from_slice(&[byte(c[0]), byte(c[1]), byte(c[2]), (e + 128) as u8]);
        }
    }
    out
}

/// Encodes an 8-bit RGB PNG.
pub fn png_rgb8(width: u32, height: u32, rgb: &[u8]) -> Vec<u8> {
    png8(width, height, rgb, png::ColorType::Rgb)
}

/// Encodes an 8-bit RGBA PNG.
pub fn png_rgba8(width: u32, height: u32, rgba: &[u8]) -> Vec<u8> {
    png8(width, height, rgba, png::ColorType::Rgba)
}

/// Encodes an 8-bit PNG of the given colour type.
fn png8(width: u32, height: u32, rgb: &[u8], color: png::ColorType) -> Vec<u8> {
    let mut out = Vec::new();
    {
        let mut encoder = png::Encoder::new(&mut out, width, height);
        encoder.set_color(color);
        encoder.set_depth(png::BitDepth::Eight);
        let mut writer = encoder.write_header().unwrap();
        writer.write_image_data(rgb).unwrap();
        writer.finish().unwrap();
    }
    out
}

/// An 8-bit greyscale PNG of `width` x `height` zeros, streamed row by row at high
/// compression: a decompression bomb (16384 x 16384 is 256 MiB of texels in about
/// 0.26 MB), built without holding the decoded image.
pub fn png_zeros(width: u32, height: u32) -> Vec<u8> {
    let mut out = Vec::new();
    {
        let mut encoder = png::Encoder::new(&mut out, width, height);
        encoder.set_color(png::ColorType::Grayscale);
        encoder.set_depth(png::BitDepth::Eight);
        encoder.set_compression(png::Compression::High);
        let mut writer = encoder.write_header().unwrap();
        let mut stream = writer.stream_writer().unwrap();
        let row = vec![0u8; width as usize];
        for _ in 0..height {
            std::io::Write::write_all(&mut stream, &row).unwrap();
        }
        stream.finish().unwrap();
    }
    out
}

/// Encodes a 16-bit greyscale PNG (samples are big-endian in PNG).
pub fn png_grey16(width: u32, height: u32, grey: &[u16]) -> Vec<u8> {
    let mut out = Vec::new();
    {
        let mut encoder = png::Encoder::new(&mut out, width, height);
        encoder.set_color(png::ColorType::Grayscale);
        encoder.set_depth(png::BitDepth::Sixteen);
        let mut writer = encoder.write_header().unwrap();
        let bytes: Vec<u8> = grey.iter().flat_map(|v| v.to_be_bytes()).collect();
        writer.write_image_data(&bytes).unwrap();
        writer.finish().unwrap();
    }
    out
}

/// A unique, empty scratch directory for one test, removed again when dropped.
pub struct Scratch(std::path::PathBuf);

impl std::ops::Deref for Scratch {
    type Target = Path;
    fn deref(&self) -> &Path {
        &self.0
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Creates the scratch directory for `test` (unique per process).
pub fn scratch_dir(test: &str) -> Scratch {
    let dir = std::env::temp_dir().join(format!("tessera-scene-{}-{test}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    Scratch(dir)
}
