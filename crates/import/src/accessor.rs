//! Accessor decoding with every size checked before anything is allocated.
//!
//! The `gltf` crate parses and cross-checks the document; reading accessor bytes is done here so
//! that all component types (including normalized integers, as in KHR_mesh_quantization files)
//! and sparse accessors decode the same way, and so that a declared count larger than the bytes
//! behind it is a typed error rather than a panic or a huge allocation.

use std::borrow::Cow;
use std::collections::HashMap;
use std::sync::{Arc, OnceLock};

use glam::{Vec2, Vec3, Vec4};
use gltf::accessor::sparse::IndexType;
use gltf::accessor::{DataType, Dimensions};

use super::{ImportError, meshopt};
use crowdmorph_core::budget::Budget;

/// The buffers of a document, its compressed buffer views (decoded when first read), and the
/// budget decoding is charged to.
pub(crate) struct Source<'a> {
    buffers: Vec<Cow<'a, [u8]>>,
    /// Buffer views stored compressed (`EXT_meshopt_compression`): view index → its checked
    /// header and, once an accessor has read it, its bytes.
    compressed: HashMap<usize, CompressedView>,
    budget: Arc<Budget>,
}

/// A compressed buffer view whose header passed [`meshopt::check_view`].
pub(crate) struct CompressedView {
    /// The extension's name (`EXT_` or `KHR_meshopt_compression`).
    pub(crate) name: &'static str,
    pub(crate) ext: meshopt::CompressedView,
    /// The view's declared (decoded) length.
    pub(crate) length: usize,
    /// The decoded bytes (4-byte aligned storage, at least `length` bytes), made by the first
    /// read.
    decoded: OnceLock<Vec<u32>>,
}

impl CompressedView {
    /// A view whose header was checked, not yet decoded.
    pub(crate) fn new(name: &'static str, ext: meshopt::CompressedView, length: usize) -> Self {
        CompressedView {
            name,
            ext,
            length,
            decoded: OnceLock::new(),
        }
    }

    /// Bytes decoding it will charge.
    fn decoded_bytes(&self) -> u64 {
        (self.length as u64).div_ceil(4) * 4
    }
}

fn component_size(t: DataType) -> usize {
    match t {
        DataType::I8 | DataType::U8 => 1,
        DataType::I16 | DataType::U16 => 2,
        DataType::U32 | DataType::F32 => 4,
    }
}

/// Bytes `count` elements of `elem` bytes span at `stride` (the last one needs no padding).
fn span(count: usize, stride: usize, elem: usize) -> u64 {
    if count == 0 {
        0
    } else {
        (count as u64 - 1)
            .saturating_mul(stride as u64)
            .saturating_add(elem as u64)
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
    pub(crate) fn new(
        buffers: Vec<Cow<'a, [u8]>>,
        compressed: HashMap<usize, CompressedView>,
        budget: Arc<Budget>,
    ) -> Self {
        Source {
            buffers,
            compressed,
            budget,
        }
    }

    /// Bytes that decoding the compressed views among `views` (view indices, each counted
    /// once) not decoded yet will charge: what reading their accessors will add.
    pub(crate) fn pending_decode_bytes(&self, views: impl IntoIterator<Item = usize>) -> u64 {
        views
            .into_iter()
            .filter_map(|v| self.compressed.get(&v))
            .filter(|c| c.decoded.get().is_none())
            .map(CompressedView::decoded_bytes)
            .sum()
    }

    /// The decoded bytes of compressed view `view`, decoding it (charged first) on the first
    /// read.
    fn decompressed<'s>(
        &'s self,
        view: usize,
        c: &'s CompressedView,
    ) -> Result<&'s [u8], ImportError> {
        if let Some(words) = c.decoded.get() {
            return Ok(bytemuck::cast_slice::<u32, u8>(words));
        }
        let compressed = self.buffers.get(c.ext.buffer).ok_or_else(|| {
            ImportError::Invalid(format!(
                "bufferViews[{view}].extensions.{} refers to buffer {} of {}",
                c.name,
                c.ext.buffer,
                self.buffers.len()
            ))
        })?;
        let words = meshopt::decode_view(view, c.name, &c.ext, c.length, compressed, &self.budget)?;
        // Only this thread decodes (a `Source` is read by one import), so the cell is empty.
        let words = c.decoded.get_or_init(|| words);
        Ok(bytemuck::cast_slice::<u32, u8>(words))
    }

    /// The budget allocations are charged to.
    pub(crate) fn budget(&self) -> &Arc<Budget> {
        &self.budget
    }

    /// Charges `bytes` about to be allocated for accessor `index`.
    fn charge(&self, index: usize, bytes: u64) -> Result<(), ImportError> {
        self.budget
            .charge(bytes, || format!("decoding accessor {index}"))
            .map_err(ImportError::from)
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
        if let Some(c) = self.compressed.get(&view.index()) {
            // A compressed view: offsets count from its start once decoded, which it is only
            // after the range is known to lie within its declared length.
            let end = (offset as u64).saturating_add(len);
            if end > c.length as u64 {
                return Err(bad(format!(
                    "needs bytes {offset}..{end} of buffer view {}, which has {} once decompressed",
                    view.index(),
                    c.length
                )));
            }
            let data = self.decompressed(view.index(), c)?;
            let data = data.get(..c.length).unwrap_or(data);
            let end = (offset as u64).saturating_add(len);
            if end > data.len() as u64 {
                return Err(bad(format!(
                    "needs bytes {offset}..{end} of buffer view {}, which has {} once decompressed",
                    view.index(),
                    data.len()
                )));
            }
            return Ok(&data[offset..end as usize]);
        }
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

    /// The bytes of buffer view `view`, which image `image` is stored in. A compressed view
    /// is refused: meshopt compression is for vertex and index data.
    pub(crate) fn image_view(
        &self,
        image: usize,
        view: &gltf::buffer::View<'_>,
    ) -> Result<&[u8], ImportError> {
        let bad = |problem: String| ImportError::Image {
            index: image,
            problem,
        };
        if self.compressed.contains_key(&view.index()) {
            return Err(bad(format!(
                "is stored in the meshopt-compressed buffer view {}",
                view.index()
            )));
        }
        let buffer = self.buffers.get(view.buffer().index()).ok_or_else(|| {
            bad(format!(
                "buffer {} of its view is not loaded",
                view.buffer().index()
            ))
        })?;
        let start = view.offset() as u64;
        let end = start + view.length() as u64;
        if end > buffer.len() as u64 {
            return Err(bad(format!(
                "buffer view {} ends at byte {end}, past the {} bytes of buffer {}",
                view.index(),
                buffer.len(),
                view.buffer().index()
            )));
        }
        Ok(&buffer[start as usize..end as usize])
    }

    /// Checks that `[offset, offset + len)` lies within a view and its buffer, without
    /// decoding a compressed view (its declared length is what it will have).
    fn check_range(
        &self,
        index: usize,
        view: &gltf::buffer::View<'_>,
        offset: usize,
        len: u64,
    ) -> Result<(), ImportError> {
        match self.compressed.get(&view.index()) {
            Some(c) => {
                let end = (offset as u64).saturating_add(len);
                if end > c.length as u64 {
                    return Err(ImportError::Accessor {
                        index,
                        problem: format!(
                            "needs bytes {offset}..{end} of buffer view {}, which has {} once decompressed",
                            view.index(),
                            c.length
                        ),
                    });
                }
                Ok(())
            }
            None => self.view_bytes(index, view, offset, len).map(|_| ()),
        }
    }

    /// Checks that an accessor's declared elements (and sparse blocks) lie within the bytes
    /// present, without decoding anything (compressed views included): a count larger than
    /// the data behind it is a malformed file (400), found before any size estimate (413) is
    /// made from that count. Returns the views the accessor reads.
    pub(crate) fn check_bounds(
        &self,
        acc: &gltf::Accessor<'_>,
    ) -> Result<[Option<usize>; 3], ImportError> {
        let index = acc.index();
        let csize = component_size(acc.data_type());
        let elem = dims_len(acc.dimensions()) * csize;
        let count = acc.count();
        let mut views = [None; 3];
        if let Some(view) = acc.view() {
            let stride = view.stride().unwrap_or(elem).max(elem);
            let span = span(count, stride, elem);
            self.check_range(index, &view, acc.offset(), span)?;
            views[0] = Some(view.index());
        }
        if let Some(sparse) = acc.sparse() {
            let n = sparse.count() as u64;
            let isize = match sparse.indices().index_type() {
                IndexType::U8 => 1,
                IndexType::U16 => 2,
                IndexType::U32 => 4,
            };
            self.check_range(
                index,
                &sparse.indices().view(),
                sparse.indices().offset(),
                n.saturating_mul(isize),
            )?;
            self.check_range(
                index,
                &sparse.values().view(),
                sparse.values().offset(),
                n.saturating_mul(elem as u64),
            )?;
            views[1] = Some(sparse.indices().view().index());
            views[2] = Some(sparse.values().view().index());
        }
        Ok(views)
    }

    /// Decodes an accessor to `count × components` f32, applying sparse substitution.
    pub(crate) fn read_f32(&self, acc: &gltf::Accessor<'_>) -> Result<Vec<f32>, ImportError> {
        let comps = dims_len(acc.dimensions());
        let mut out = Vec::new();
        self.read_elements(acc, comps, comps, &mut out, |e, out: &mut Vec<f32>| {
            out.extend_from_slice(e)
        })?;
        Ok(out)
    }

    /// Decodes a VEC3 accessor straight into vectors (no intermediate f32 array).
    pub(crate) fn read_vec3s(&self, acc: &gltf::Accessor<'_>) -> Result<Vec<Vec3>, ImportError> {
        let mut out = Vec::new();
        self.read_elements(acc, 3, 1, &mut out, |e, out: &mut Vec<Vec3>| {
            out.push(Vec3::new(e[0], e[1], e[2]))
        })?;
        Ok(out)
    }

    /// Decodes a VEC2 accessor straight into vectors (texture coordinates).
    pub(crate) fn read_vec2s(&self, acc: &gltf::Accessor<'_>) -> Result<Vec<Vec2>, ImportError> {
        let mut out = Vec::new();
        self.read_elements(acc, 2, 1, &mut out, |e, out: &mut Vec<Vec2>| {
            out.push(Vec2::new(e[0], e[1]))
        })?;
        Ok(out)
    }

    /// Decodes a VEC4 accessor straight into vectors.
    pub(crate) fn read_vec4s(&self, acc: &gltf::Accessor<'_>) -> Result<Vec<Vec4>, ImportError> {
        let mut out = Vec::new();
        self.read_elements(acc, 4, 1, &mut out, |e, out: &mut Vec<Vec4>| {
            out.push(Vec4::new(e[0], e[1], e[2], e[3]))
        })?;
        Ok(out)
    }

    /// Decodes a MAT4 float accessor (a skin's inverse bind matrices), column-major as glTF
    /// stores them. Sparse matrices are refused: no exporter writes them.
    pub(crate) fn read_mat4s(
        &self,
        acc: &gltf::Accessor<'_>,
    ) -> Result<Vec<glam::Mat4>, ImportError> {
        let index = acc.index();
        let bad = |problem: String| ImportError::Accessor { index, problem };
        if acc.dimensions() != Dimensions::Mat4 || acc.data_type() != DataType::F32 {
            return Err(bad("inverse bind matrices must be MAT4 of FLOAT".into()));
        }
        if acc.sparse().is_some() {
            return Err(bad("sparse inverse bind matrices are not supported".into()));
        }
        let view = acc
            .view()
            .ok_or_else(|| bad("inverse bind matrices have no buffer view".into()))?;
        let count = acc.count();
        let stride = view.stride().unwrap_or(64);
        if stride < 64 {
            return Err(bad(format!(
                "byte stride {stride} is smaller than a MAT4 (64)"
            )));
        }
        let bytes = self.view_bytes(index, &view, acc.offset(), span(count, stride, 64))?;
        self.charge(index, (count as u64).saturating_mul(64))?;
        let mut out = Vec::with_capacity(count);
        for i in 0..count {
            let b = &bytes[i * stride..i * stride + 64];
            let mut m = [0f32; 16];
            for (c, v) in m.iter_mut().enumerate() {
                *v = decode(&b[c * 4..], DataType::F32, false);
            }
            out.push(glam::Mat4::from_cols_array(&m));
        }
        Ok(out)
    }

    /// Decodes every element of `acc` (which must have `comps` components) into `out`, as
    /// `push` makes them (`per_element` items each), then applies the accessor's sparse
    /// substitution. `out` is charged to the budget before it is allocated.
    fn read_elements<T: Copy + Default>(
        &self,
        acc: &gltf::Accessor<'_>,
        comps: usize,
        per_element: usize,
        out: &mut Vec<T>,
        push: impl Fn(&[f32], &mut Vec<T>),
    ) -> Result<(), ImportError> {
        let index = acc.index();
        let bad = |problem: String| ImportError::Accessor { index, problem };
        if matches!(
            acc.dimensions(),
            Dimensions::Mat2 | Dimensions::Mat3 | Dimensions::Mat4
        ) {
            return Err(bad("matrix accessors are not used by rigs".into()));
        }
        if dims_len(acc.dimensions()) != comps {
            return Err(bad(format!(
                "has {:?} elements, {comps} components were expected",
                acc.dimensions()
            )));
        }
        let t = acc.data_type();
        let csize = component_size(t);
        let elem = comps * csize;
        let count = acc.count();
        // Bytes of the decoded output: what `out` will hold.
        let items = (count as u64).saturating_mul(per_element as u64);
        let decoded = items
            .checked_mul(size_of::<T>() as u64)
            .filter(|&b| b < (1u64 << 48))
            .ok_or_else(|| bad(format!("declared count {count} is absurd")))?;
        let normalized = acc.normalized();
        let mut e = [0f32; 4];
        if let Some(view) = acc.view() {
            let stride = view.stride().unwrap_or(elem);
            if stride < elem {
                return Err(bad(format!(
                    "byte stride {stride} is smaller than an element ({elem})"
                )));
            }
            let span = span(count, stride, elem);
            let bytes = self.view_bytes(index, &view, acc.offset(), span)?;
            self.charge(index, decoded)?;
            out.reserve_exact(items as usize);
            for i in 0..count {
                let b = &bytes[i * stride..i * stride + elem];
                for (c, v) in e.iter_mut().enumerate().take(comps) {
                    *v = decode(&b[c * csize..], t, normalized);
                }
                push(&e[..comps], out);
            }
        } else {
            // No buffer view: the accessor is all zeros (then sparse values, if any). The budget
            // check is what stops a tiny file from declaring a billion zeros.
            self.charge(index, decoded)?;
            let zeros = [0f32; 4];
            out.reserve_exact(items as usize);
            for _ in 0..count {
                push(&zeros[..comps], out);
            }
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
            let per_elem = per_element;
            let mut one = Vec::with_capacity(per_elem);
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
                let b = &vbytes[k * elem..(k + 1) * elem];
                for (c, v) in e.iter_mut().enumerate().take(comps) {
                    *v = decode(&b[c * csize..], t, normalized);
                }
                one.clear();
                push(&e[..comps], &mut one);
                out[i * per_elem..(i + 1) * per_elem].copy_from_slice(&one);
            }
        }
        Ok(())
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
        let span = span(count, stride, csize);
        let bytes = self.view_bytes(index, &view, acc.offset(), span)?;
        self.charge(index, count as u64 * 4)?;
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
