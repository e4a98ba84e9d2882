//! Step 2, accessors (spec "Buffers and Buffer Views", "Accessors"): buffer views checked
//! against their buffers, accessors packed (strides removed, sparse substitution applied)
//! and read as floats or as indices.

use super::{Importer, Res};
use gltf::json;
use json::accessor::{ComponentType, GenericComponentType, IndexComponentType, Type};
use json::validation::Checked;

impl Importer<'_> {
    /// The bytes of buffer view `vi`, checked against its buffer.
    pub(super) fn view_bytes(&self, vi: usize, what: &str) -> Res<&[u8]> {
        let Some(view) = self.root.buffer_views.get(vi) else {
            return self.err(format!(
                "{what} refers to bufferView {vi}, but there are only {}",
                self.root.buffer_views.len()
            ));
        };
        let bi = view.buffer.value();
        let Some(buffer) = self.buffers.get(bi) else {
            return self.err(format!(
                "bufferView {vi} ({what}) refers to buffer {bi}, but there are only {}",
                self.buffers.len()
            ));
        };
        let offset = view.byte_offset.map_or(0, |o| o.0);
        let len = view.byte_length.0;
        match offset.checked_add(len) {
            Some(end) if end <= buffer.len() as u64 => Ok(&buffer[offset as usize..end as usize]),
            _ => self.err(format!(
                "bufferView {vi} ({what}): bytes {offset}..{} are past the end of buffer {bi} \
                 ({} bytes)",
                offset as u128 + len as u128,
                buffer.len()
            )),
        }
    }

    /// The elements of accessor `ai`, tightly packed (strides removed, sparse substitution
    /// applied), with their component type and component count (spec "Accessors").
    fn packed_accessor(&self, ai: usize, what: &str) -> Res<(Vec<u8>, ComponentType, usize)> {
        let Some(acc) = self.root.accessors.get(ai) else {
            return self.err(format!(
                "{what} refers to accessor {ai}, but there are only {}",
                self.root.accessors.len()
            ));
        };
        let what = format!("accessor {ai} ({what})");
        let Checked::Valid(GenericComponentType(ct)) = acc.component_type else {
            return self.err(format!("{what} has an invalid componentType"));
        };
        let Checked::Valid(ty) = acc.type_ else {
            return self.err(format!("{what} has an invalid type"));
        };
        let ncomp = match ty {
            Type::Scalar => 1,
            Type::Vec2 => 2,
            Type::Vec3 => 3,
            Type::Vec4 => 4,
            // Inverse bind matrices (spec "Skins"); float columns need no padding.
            Type::Mat4 if ct == ComponentType::F32 => 16,
            _ => return self.err(format!("{what}: matrix accessors are not supported here")),
        };
        let elem = ncomp * ct.size();
        let count = acc.count.0;
        let total = match count.checked_mul(elem as u64) {
            Some(t) if t <= self.limit => t as usize,
            _ => return self.err(format!("{what}: count {count} is too large")),
        };
        let count = count as usize;
        let mut out = vec![0u8; total];
        if let Some(vi) = acc.buffer_view {
            let vi = vi.value();
            let bytes = self.view_bytes(vi, &what)?;
            let stride = match self.root.buffer_views[vi].byte_stride {
                Some(s) if s.0 < elem => {
                    return self.err(format!(
                        "{what}: bufferView {vi} byteStride {} is smaller than an element \
                         ({elem} bytes)",
                        s.0
                    ))
                }
                Some(s) => s.0,
                None => elem,
            };
            let offset = acc.byte_offset.map_or(0, |o| o.0);
            if count > 0 {
                let need = (count as u128 - 1) * stride as u128 + elem as u128 + offset as u128;
                if need > bytes.len() as u128 {
                    return self.err(format!(
                        "{what}: {count} elements of {elem} bytes at offset {offset} with \
                         stride {stride} need {need} bytes, but bufferView {vi} has only {}",
                        bytes.len()
                    ));
                }
                let offset = offset as usize;
                for (i, dst) in out.chunks_exact_mut(elem).enumerate() {
                    let start = offset + i * stride;
                    dst.copy_from_slice(&bytes[start..start + elem]);
                }
            }
        }
        if let Some(sparse) = &acc.sparse {
            self.apply_sparse(sparse, &what, count, elem, &mut out)?;
        }
        Ok((out, ct, ncomp))
    }

    /// Substitutes the sparse elements of an accessor of `count` elements of `elem` bytes
    /// into `out` (spec "Accessors > Sparse Accessors").
    fn apply_sparse(
        &self,
        sparse: &json::accessor::sparse::Sparse,
        what: &str,
        count: usize,
        elem: usize,
        out: &mut [u8],
    ) -> Res<()> {
        let n = sparse.count.0;
        if n > count as u64 {
            return self.err(format!(
                "{what}: sparse count {n} exceeds the accessor count {count}"
            ));
        }
        let n = n as usize;
        let Checked::Valid(IndexComponentType(ict)) = sparse.indices.component_type else {
            return self.err(format!("{what}: invalid sparse index componentType"));
        };
        if !matches!(
            ict,
            ComponentType::U8 | ComponentType::U16 | ComponentType::U32
        ) {
            return self.err(format!("{what}: sparse indices must be unsigned integers"));
        }
        let isz = ict.size();
        let ivi = sparse.indices.buffer_view.value();
        let ibytes = self.view_bytes(ivi, &format!("{what} sparse indices"))?;
        let ioff = sparse.indices.byte_offset.0;
        let vvi = sparse.values.buffer_view.value();
        let vbytes = self.view_bytes(vvi, &format!("{what} sparse values"))?;
        let voff = sparse.values.byte_offset.0;
        if ioff as u128 + (n * isz) as u128 > ibytes.len() as u128
            || voff as u128 + (n * elem) as u128 > vbytes.len() as u128
        {
            return self.err(format!(
                "{what}: sparse indices or values run past their bufferViews ({ivi}, {vvi})"
            ));
        }
        let (ioff, voff) = (ioff as usize, voff as usize);
        for k in 0..n {
            let idx = read_uint(ict, &ibytes[ioff + k * isz..]) as usize;
            if idx >= count {
                return self.err(format!(
                    "{what}: sparse index {k} = {idx} is past the accessor count {count}"
                ));
            }
            out[idx * elem..(idx + 1) * elem]
                .copy_from_slice(&vbytes[voff + k * elem..voff + (k + 1) * elem]);
        }
        Ok(())
    }

    /// Reads a float (or normalized/integer) accessor with `n` components per element.
    pub(super) fn read_floats<const N: usize>(&self, ai: usize, what: &str) -> Res<Vec<[f32; N]>> {
        let (bytes, ct, ncomp) = self.packed_accessor(ai, what)?;
        if ncomp != N {
            return self.err(format!(
                "accessor {ai} ({what}) has {ncomp} components per element, expected {N}"
            ));
        }
        let normalized = self.root.accessors[ai].normalized;
        let cs = ct.size();
        let out: Vec<[f32; N]> = bytes
            .chunks_exact(N * cs)
            .map(|e| std::array::from_fn(|j| read_float(ct, normalized, &e[j * cs..])))
            .collect();
        if let Some(i) = out.iter().position(|v| v.iter().any(|c| !c.is_finite())) {
            return self.err(format!(
                "accessor {ai} ({what}) element {i} is not finite: {:?}",
                out[i]
            ));
        }
        Ok(out)
    }

    /// Reads a `COLOR_0` accessor as linear RGBA (spec "Meshes > Overview": VEC3 or VEC4,
    /// float or normalized unsigned byte/short; a VEC3 colour has alpha 1).
    pub(super) fn read_colors(&self, ai: usize, what: &str) -> Res<Vec<glam::Vec4>> {
        let acc = self.root.accessors.get(ai);
        let ct = acc.and_then(|a| match a.component_type {
            Checked::Valid(GenericComponentType(ct)) => Some(ct),
            Checked::Invalid => None,
        });
        let normalized = acc.is_some_and(|a| a.normalized);
        match ct {
            Some(ComponentType::F32) => {}
            Some(ComponentType::U8 | ComponentType::U16) if normalized => {}
            Some(_) => {
                return self.err(format!(
                    "accessor {ai} ({what}) must be float or normalized unsigned byte/short \
                     colours"
                ))
            }
            // Missing or invalid accessors are reported by the read below.
            None => {}
        }
        let vec4 = acc.is_some_and(|a| a.type_ == Checked::Valid(Type::Vec4));
        let colors = if vec4 {
            self.read_floats::<4>(ai, what)?
                .into_iter()
                .map(glam::Vec4::from)
                .collect()
        } else {
            self.read_floats::<3>(ai, what)?
                .into_iter()
                .map(|c| glam::Vec3::from(c).extend(1.0))
                .collect()
        };
        Ok(colors)
    }

    /// Reads an index accessor (unsigned scalar integers, spec "Meshes > Overview").
    pub(super) fn read_indices(&self, ai: usize, what: &str) -> Res<Vec<u32>> {
        let (bytes, ct, ncomp) = self.packed_accessor(ai, what)?;
        if ncomp != 1
            || !matches!(
                ct,
                ComponentType::U8 | ComponentType::U16 | ComponentType::U32
            )
        {
            return self.err(format!(
                "accessor {ai} ({what}) must be SCALAR unsigned byte/short/int indices"
            ));
        }
        let cs = ct.size();
        Ok(bytes.chunks_exact(cs).map(|b| read_uint(ct, b)).collect())
    }
}

/// Reads an unsigned integer component (little endian, as all glTF binary data).
fn read_uint(ct: ComponentType, b: &[u8]) -> u32 {
    match ct {
        ComponentType::U8 | ComponentType::I8 => u32::from(b[0]),
        ComponentType::U16 | ComponentType::I16 => u32::from(u16::from_le_bytes([b[0], b[1]])),
        ComponentType::U32 | ComponentType::F32 => u32::from_le_bytes([b[0], b[1], b[2], b[3]]),
    }
}

/// Reads one component as f32; normalized integers map to [0, 1] or [-1, 1] as the spec's
/// "Accessors" section prescribes (e.g. `max(c / 127, -1)` for signed bytes).
fn read_float(ct: ComponentType, normalized: bool, b: &[u8]) -> f32 {
    match ct {
        ComponentType::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]),
        ComponentType::I8 => {
            let v = f32::from(b[0] as i8);
            if normalized {
                (v / 127.0).max(-1.0)
            } else {
                v
            }
        }
        ComponentType::U8 => {
            let v = f32::from(b[0]);
            if normalized {
                v / 255.0
            } else {
                v
            }
        }
        ComponentType::I16 => {
            let v = f32::from(i16::from_le_bytes([b[0], b[1]]));
            if normalized {
                (v / 32767.0).max(-1.0)
            } else {
                v
            }
        }
        ComponentType::U16 => {
            let v = f32::from(u16::from_le_bytes([b[0], b[1]]));
            if normalized {
                v / 65535.0
            } else {
                v
            }
        }
        ComponentType::U32 => {
            let v = u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64;
            (if normalized { v / u32::MAX as f64 } else { v }) as f32
        }
    }
}
