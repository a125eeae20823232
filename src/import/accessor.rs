//! Accessor decoding with every size checked before anything is allocated.
//!
//! The `gltf` crate parses and cross-checks the document; reading accessor bytes is done here so
//! that all component types (including normalized integers, as in KHR_mesh_quantization files)
//! and sparse accessors decode the same way, and so that a declared count larger than the bytes
//! behind it is a typed error rather than a panic or a huge allocation.

use std::borrow::Cow;
use std::cell::Cell;

use gltf::accessor::sparse::IndexType;
use gltf::accessor::{DataType, Dimensions};

use super::ImportError;

/// The buffers of a document and what is left of the decoding budget.
pub(crate) struct Source<'a> {
    buffers: Vec<Cow<'a, [u8]>>,
    budget: Cell<usize>,
    limit: usize,
}

fn component_size(t: DataType) -> usize {
    match t {
        DataType::I8 | DataType::U8 => 1,
        DataType::I16 | DataType::U16 => 2,
        DataType::U32 | DataType::F32 => 4,
    }
}

fn dims_len(d: Dimensions) -> usize {
    d.multiplicity()
}

/// Decodes one component at `bytes[0..size]` as glTF defines it.
#[inline]
fn decode(bytes: &[u8], t: DataType, normalized: bool) -> f32 {
    match t {
        DataType::F32 => f32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]),
        DataType::U32 => u32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]) as f32,
        DataType::I8 => {
            let v = bytes[0] as i8 as f32;
            if normalized { (v / 127.0).max(-1.0) } else { v }
        }
        DataType::U8 => {
            let v = f32::from(bytes[0]);
            if normalized { v / 255.0 } else { v }
        }
        DataType::I16 => {
            let v = f32::from(i16::from_le_bytes([bytes[0], bytes[1]]));
            if normalized {
                (v / 32767.0).max(-1.0)
            } else {
                v
            }
        }
        DataType::U16 => {
            let v = f32::from(u16::from_le_bytes([bytes[0], bytes[1]]));
            if normalized { v / 65535.0 } else { v }
        }
    }
}

impl<'a> Source<'a> {
    pub(crate) fn new(buffers: Vec<Cow<'a, [u8]>>, limit: usize) -> Self {
        Source {
            buffers,
            budget: Cell::new(limit),
            limit,
        }
    }

    /// Reserves `bytes` of the decoding budget.
    pub(crate) fn reserve(&self, bytes: usize) -> Result<(), ImportError> {
        let left = self.budget.get();
        if bytes > left {
            return Err(ImportError::TooLarge {
                declared: self.limit - left + bytes,
                limit: self.limit,
            });
        }
        self.budget.set(left - bytes);
        Ok(())
    }

    /// The bytes `[offset, offset + len)` of the buffer a view lives in, checked.
    fn view_bytes(
        &self,
        index: usize,
        view: &gltf::buffer::View<'_>,
        offset: usize,
        len: u64,
    ) -> Result<&[u8], ImportError> {
        let bad = |problem: String| ImportError::Accessor { index, problem };
        let buffer = self
            .buffers
            .get(view.buffer().index())
            .ok_or_else(|| bad(format!("buffer {} is not loaded", view.buffer().index())))?;
        let view_end = view.offset() as u64 + view.length() as u64;
        if view_end > buffer.len() as u64 {
            return Err(bad(format!(
                "buffer view {} ends at byte {view_end}, past the {} bytes of buffer {}",
                view.index(),
                buffer.len(),
                view.buffer().index()
            )));
        }
        let start = view.offset() as u64 + offset as u64;
        let end = start.saturating_add(len);
        if end > view_end {
            return Err(bad(format!(
                "needs bytes {start}..{end} but buffer view {} ends at {view_end}",
                view.index()
            )));
        }
        Ok(&buffer[start as usize..end as usize])
    }

    /// Decodes an accessor to `count × components` f32, applying sparse substitution.
    pub(crate) fn read_f32(&self, acc: &gltf::Accessor<'_>) -> Result<Vec<f32>, ImportError> {
        let index = acc.index();
        let bad = |problem: String| ImportError::Accessor { index, problem };
        if matches!(
            acc.dimensions(),
            Dimensions::Mat2 | Dimensions::Mat3 | Dimensions::Mat4
        ) {
            return Err(bad("matrix accessors are not used by rigs".into()));
        }
        let t = acc.data_type();
        let comps = dims_len(acc.dimensions());
        let csize = component_size(t);
        let elem = comps * csize;
        let count = acc.count();
        let total = (count as u64) * comps as u64;
        if total > (usize::MAX / 8) as u64 {
            return Err(bad(format!("declared count {count} is absurd")));
        }
        let normalized = acc.normalized();
        let mut out: Vec<f32>;
        if let Some(view) = acc.view() {
            let stride = view.stride().unwrap_or(elem);
            if stride < elem {
                return Err(bad(format!(
                    "byte stride {stride} is smaller than an element ({elem})"
                )));
            }
            let span = if count == 0 {
                0
            } else {
                (count as u64 - 1)
                    .saturating_mul(stride as u64)
                    .saturating_add(elem as u64)
            };
            let bytes = self.view_bytes(index, &view, acc.offset(), span)?;
            self.reserve(total as usize * 4)?;
            out = Vec::with_capacity(total as usize);
            for i in 0..count {
                let e = &bytes[i * stride..i * stride + elem];
                for c in 0..comps {
                    out.push(decode(&e[c * csize..], t, normalized));
                }
            }
        } else {
            // No buffer view: the accessor is all zeros (then sparse values, if any). The budget
            // check is what stops a tiny file from declaring a billion zeros.
            self.reserve(total as usize * 4)?;
            out = vec![0.0; total as usize];
        }
        if let Some(sparse) = acc.sparse() {
            let n = sparse.count();
            if n > count {
                return Err(bad(format!(
                    "sparse count {n} exceeds accessor count {count}"
                )));
            }
            let isize = match sparse.indices().index_type() {
                IndexType::U8 => 1,
                IndexType::U16 => 2,
                IndexType::U32 => 4,
            };
            let iview = sparse.indices().view();
            let ibytes =
                self.view_bytes(index, &iview, sparse.indices().offset(), (n * isize) as u64)?;
            let vview = sparse.values().view();
            let vbytes =
                self.view_bytes(index, &vview, sparse.values().offset(), (n * elem) as u64)?;
            for k in 0..n {
                let ib = &ibytes[k * isize..];
                let i = match isize {
                    1 => ib[0] as usize,
                    2 => u16::from_le_bytes([ib[0], ib[1]]) as usize,
                    _ => u32::from_le_bytes([ib[0], ib[1], ib[2], ib[3]]) as usize,
                };
                if i >= count {
                    return Err(bad(format!(
                        "sparse index {i} out of range (count {count})"
                    )));
                }
                let e = &vbytes[k * elem..(k + 1) * elem];
                for c in 0..comps {
                    out[i * comps + c] = decode(&e[c * csize..], t, normalized);
                }
            }
        }
        Ok(out)
    }

    /// Decodes an index accessor (unsigned integer scalars) exactly.
    pub(crate) fn read_indices(&self, acc: &gltf::Accessor<'_>) -> Result<Vec<u32>, ImportError> {
        let index = acc.index();
        let bad = |problem: String| ImportError::Accessor { index, problem };
        if acc.dimensions() != Dimensions::Scalar || acc.sparse().is_some() {
            return Err(bad("indices must be a dense scalar accessor".into()));
        }
        let t = acc.data_type();
        if !matches!(t, DataType::U8 | DataType::U16 | DataType::U32) {
            return Err(bad(format!("indices must be unsigned integers, not {t:?}")));
        }
        let view = acc
            .view()
            .ok_or_else(|| bad("indices have no buffer view".into()))?;
        let csize = component_size(t);
        let count = acc.count();
        let stride = view.stride().unwrap_or(csize).max(csize);
        let span = if count == 0 {
            0
        } else {
            (count as u64 - 1)
                .saturating_mul(stride as u64)
                .saturating_add(csize as u64)
        };
        let bytes = self.view_bytes(index, &view, acc.offset(), span)?;
        self.reserve(count * 4)?;
        Ok((0..count)
            .map(|i| {
                let e = &bytes[i * stride..];
                match t {
                    DataType::U8 => u32::from(e[0]),
                    DataType::U16 => u32::from(u16::from_le_bytes([e[0], e[1]])),
                    _ => u32::from_le_bytes([e[0], e[1], e[2], e[3]]),
                }
            })
            .collect())
    }
}
