//! `EXT_meshopt_compression` (and its ratified successor `KHR_meshopt_compression`): buffer
//! views stored compressed, as gltfpack and glTF Transform write them.
//!
//! A compressed view names a byte range of another buffer, the element count and stride, the
//! codec mode (attributes, triangle indices, other indices) and an optional filter applied
//! after decoding (octahedral unit vectors, quaternions, exponential floats; `KHR_` adds YCoCg
//! colours). Each view's header is checked when the document is parsed; a view is decoded
//! only when an accessor first reads it (views no accessor reads are never decoded), once, into
//! bytes laid out as the view declares, and accessors then read it as they read any view. The
//! header-only size checks read the declared length, and the import's estimate counts the
//! decoded bytes of the views its accessors read before any of them is decoded. The bitstream decoders are
//! meshoptimizer's (through the `meshopt` crate's bindings), which are written for untrusted
//! input: a malformed stream returns an error code, never reads or writes out of bounds. Every
//! precondition they only `assert` (stride limits, index sizes, counts) is checked here first,
//! and the decoded size — `count × byteStride`, which a tiny file can declare huge — is charged
//! to the import's budget before it is allocated.
//!
//! Fallback buffers (a placeholder with no data, marked `fallback: true`, that holds the
//! uncompressed layout for loaders without the extension) are never loaded.

use serde::Deserialize;

use super::ImportError;
use crowdmorph_core::budget::Budget;

/// The extension names this module decodes.
pub(crate) const EXTENSIONS: [&str; 2] = ["EXT_meshopt_compression", "KHR_meshopt_compression"];

/// Most bytes one element of an attribute stream may have (meshoptimizer's limit).
const MAX_ATTRIBUTE_STRIDE: u64 = 256;

/// The extension object of a compressed buffer view.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(rename_all = "camelCase")]
pub(crate) struct CompressedView {
    /// Buffer holding the compressed bytes.
    pub(crate) buffer: usize,
    /// Where they start in it.
    #[serde(default)]
    pub(crate) byte_offset: u64,
    /// How many compressed bytes there are.
    pub(crate) byte_length: u64,
    /// Bytes per decoded element.
    pub(crate) byte_stride: u64,
    /// Decoded elements.
    pub(crate) count: u64,
    /// `ATTRIBUTES`, `TRIANGLES` or `INDICES`.
    pub(crate) mode: String,
    /// `NONE`, `OCTAHEDRAL`, `QUATERNION`, `EXPONENTIAL` (or `COLOR`, `KHR_` only).
    #[serde(default)]
    pub(crate) filter: Option<String>,
}

/// The compressed-view extension of a buffer view, if it has one, with the extension's name.
pub(crate) fn view_extension(
    view: &gltf::buffer::View<'_>,
) -> Option<Result<(&'static str, CompressedView), ImportError>> {
    EXTENSIONS.iter().find_map(|&name| {
        view.extension_value(name).map(|v| {
            CompressedView::deserialize(v)
                .map(|ext| (name, ext))
                .map_err(|e| {
                    ImportError::Invalid(format!(
                        "bufferViews[{}].extensions.{name}: {e}",
                        view.index()
                    ))
                })
        })
    })
}

/// Whether a buffer is a fallback placeholder that compressed views stand in for.
pub(crate) fn is_fallback(buffer: &gltf::Buffer<'_>) -> bool {
    EXTENSIONS.iter().any(|&name| {
        buffer
            .extension_value(name)
            .and_then(|v| v.get("fallback"))
            .and_then(serde_json::Value::as_bool)
            .unwrap_or(false)
    })
}

/// Checks a compressed view's header without decoding anything: the decoded size
/// (`count × byteStride`) equals `view_length`, the view's declared length; the mode, stride
/// and filter are ones the decoders take; the compressed bytes lie within the
/// `compressed_len` bytes of the buffer the extension names.
pub(crate) fn check_view(
    index: usize,
    name: &str,
    ext: &CompressedView,
    view_length: usize,
    compressed_len: usize,
) -> Result<(), ImportError> {
    let bad = |problem: String| {
        ImportError::Invalid(format!("bufferViews[{index}].extensions.{name}: {problem}"))
    };
    let (stride, count) = (ext.byte_stride, ext.count);
    let decoded = stride
        .checked_mul(count)
        .ok_or_else(|| bad(format!("{count} elements of {stride} bytes overflow")))?;
    if decoded != view_length as u64 {
        return Err(bad(format!(
            "{count} elements of {stride} bytes make {decoded} bytes, but the view declares {view_length}"
        )));
    }
    let filter = ext.filter.as_deref().unwrap_or("NONE");
    match ext.mode.as_str() {
        "ATTRIBUTES" => {
            if stride == 0 || stride % 4 != 0 || stride > MAX_ATTRIBUTE_STRIDE {
                return Err(bad(format!(
                    "ATTRIBUTES need a byteStride that is a multiple of 4 up to {MAX_ATTRIBUTE_STRIDE}, not {stride}"
                )));
            }
            let ok = match filter {
                "NONE" | "EXPONENTIAL" => true,
                "OCTAHEDRAL" => stride == 4 || stride == 8,
                "QUATERNION" => stride == 8,
                "COLOR" => name.starts_with("KHR_") && (stride == 4 || stride == 8),
                _ => false,
            };
            if !ok {
                return Err(bad(format!(
                    "filter {filter:?} is unknown or does not allow byteStride {stride}"
                )));
            }
        }
        "TRIANGLES" | "INDICES" => {
            if stride != 2 && stride != 4 {
                return Err(bad(format!(
                    "{} need a byteStride of 2 or 4, not {stride}",
                    ext.mode
                )));
            }
            if ext.mode == "TRIANGLES" && count % 3 != 0 {
                return Err(bad(format!(
                    "TRIANGLES count {count} is not a multiple of 3"
                )));
            }
            if filter != "NONE" {
                return Err(bad(format!("{} take no filter, not {filter:?}", ext.mode)));
            }
        }
        other => return Err(bad(format!("unknown mode {other:?}"))),
    }
    ext.byte_offset
        .checked_add(ext.byte_length)
        .filter(|&e| e <= compressed_len as u64)
        .ok_or_else(|| {
            bad(format!(
                "compressed bytes {}..{} lie past the {compressed_len} bytes of buffer {}",
                ext.byte_offset,
                ext.byte_offset.saturating_add(ext.byte_length),
                ext.buffer
            ))
        })?;
    Ok(())
}

/// Decodes one compressed view: `compressed` is the whole buffer the extension names,
/// `view_length` the view's declared (decoded) length. Returns the decoded bytes in
/// 4-byte-aligned storage (filters read 16- and 32-bit components), `view_length` bytes long
/// once cast. The header is checked first ([`check_view`]) and the decoded size is charged to
/// `budget` before it is allocated.
pub(crate) fn decode_view(
    index: usize,
    name: &str,
    ext: &CompressedView,
    view_length: usize,
    compressed: &[u8],
    budget: &Budget,
) -> Result<Vec<u32>, ImportError> {
    check_view(index, name, ext, view_length, compressed.len())?;
    let bad = |problem: String| {
        ImportError::Invalid(format!("bufferViews[{index}].extensions.{name}: {problem}"))
    };
    let (stride, count) = (ext.byte_stride, ext.count);
    let decoded = stride * count;
    let filter = ext.filter.as_deref().unwrap_or("NONE");
    let input = &compressed[ext.byte_offset as usize..(ext.byte_offset + ext.byte_length) as usize];

    let words = decoded.div_ceil(4);
    budget.charge(words * 4, || {
        format!("decompressing buffer view {index} ({decoded} bytes)")
    })?;
    let mut out = vec![0u32; words as usize];
    let (count, stride) = (count as usize, stride as usize);
    let dst = out.as_mut_ptr().cast::<std::ffi::c_void>();
    // SAFETY: `out` holds at least `count × stride` bytes (`words × 4 ≥ decoded`), 4-byte
    // aligned; the input slice is valid for its length. meshoptimizer's decoders read only
    // `input` (bounds-checked against its length, returning an error code on a malformed or
    // short stream) and write only `count × stride` bytes of the destination. Their asserted
    // preconditions were checked above: attribute strides are multiples of 4 up to 256, index
    // strides 2 or 4, triangle counts multiples of 3, and each filter's stride is one it
    // takes.
    let rc = unsafe {
        match ext.mode.as_str() {
            "ATTRIBUTES" => meshopt::ffi::meshopt_decodeVertexBuffer(
                dst,
                count,
                stride,
                input.as_ptr(),
                input.len(),
            ),
            "TRIANGLES" => meshopt::ffi::meshopt_decodeIndexBuffer(
                dst,
                count,
                stride,
                input.as_ptr(),
                input.len(),
            ),
            _ => meshopt::ffi::meshopt_decodeIndexSequence(
                dst,
                count,
                stride,
                input.as_ptr(),
                input.len(),
            ),
        }
    };
    if rc != 0 {
        budget.release(words * 4);
        return Err(bad(format!(
            "the {} stream does not decode (meshoptimizer error {rc}: {})",
            ext.mode,
            match rc {
                -1 => "bad header or unsupported version",
                -2 => "truncated",
                _ => "length does not match the data",
            }
        )));
    }
    // SAFETY: as above, `out` holds `count × stride` bytes, 4-byte aligned, and each filter is
    // called only with a stride it accepts (checked above).
    unsafe {
        match filter {
            "OCTAHEDRAL" => meshopt::ffi::meshopt_decodeFilterOct(dst, count, stride),
            "QUATERNION" => meshopt::ffi::meshopt_decodeFilterQuat(dst, count, stride),
            "EXPONENTIAL" => meshopt::ffi::meshopt_decodeFilterExp(dst, count, stride),
            "COLOR" => meshopt::ffi::meshopt_decodeFilterColor(dst, count, stride),
            _ => {}
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ext(mode: &str, filter: Option<&str>, stride: u64, count: u64, len: u64) -> CompressedView {
        CompressedView {
            buffer: 0,
            byte_offset: 0,
            byte_length: len,
            byte_stride: stride,
            count,
            mode: mode.into(),
            filter: filter.map(str::to_string),
        }
    }

    fn budget() -> Budget {
        Budget::new(1 << 30, "--max-upload-memory", None)
    }

    fn bytes(words: &[u32], len: usize) -> Vec<u8> {
        bytemuck::cast_slice::<u32, u8>(words)[..len].to_vec()
    }

    #[test]
    fn attributes_and_every_filter_round_trip() {
        // Exponential: f32 xyz at 16 mantissa bits (sign included) decode within 2^-15 relative.
        let data: Vec<[f32; 3]> = (0..100)
            .map(|i| {
                let x = i as f32 * 0.173;
                [x.sin() * 3.0, x.cos() * 0.01, x * 1e-3 - 0.05]
            })
            .collect();
        let enc = meshopt::encode_filter_exp(&data, 16, meshopt::EncodeExpMode::Separate);
        let stream = meshopt::encode_vertex_buffer(&enc).expect("encodes");
        let e = ext(
            "ATTRIBUTES",
            Some("EXPONENTIAL"),
            12,
            100,
            stream.len() as u64,
        );
        let out = decode_view(0, EXTENSIONS[0], &e, 1200, &stream, &budget()).expect("decodes");
        let got: &[f32] = bytemuck::cast_slice(&out[..300]);
        for (g, w) in got.chunks_exact(3).zip(&data) {
            for c in 0..3 {
                let tol = w[c].abs() * 2f32.powi(-15) * 1.01;
                assert!((g[c] - w[c]).abs() <= tol, "{g:?} vs {w:?}");
            }
        }

        // Octahedral: unit normals in 8-bit (stride 4) and 16-bit (stride 8) components.
        let normals: Vec<[f32; 4]> = (0..64)
            .map(|i| {
                let a = i as f32 * 0.41;
                let v = glam::Vec3::new(a.cos(), a.sin(), (a * 0.7).cos()).normalize();
                [v.x, v.y, v.z, 0.0]
            })
            .collect();
        let e8 = meshopt::encode_filter_oct::<i8>(&normals, 8);
        let s8 = meshopt::encode_vertex_buffer(&e8).expect("encodes");
        let d8 = decode_view(
            1,
            EXTENSIONS[0],
            &ext("ATTRIBUTES", Some("OCTAHEDRAL"), 4, 64, s8.len() as u64),
            256,
            &s8,
            &budget(),
        )
        .expect("decodes");
        let d8: &[i8] = bytemuck::cast_slice(&d8);
        let e16 = meshopt::encode_filter_oct::<i16>(&normals, 16);
        let s16 = meshopt::encode_vertex_buffer(&e16).expect("encodes");
        let d16 = decode_view(
            2,
            EXTENSIONS[0],
            &ext("ATTRIBUTES", Some("OCTAHEDRAL"), 8, 64, s16.len() as u64),
            512,
            &s16,
            &budget(),
        )
        .expect("decodes");
        let d16: &[i16] = bytemuck::cast_slice(&d16);
        for (i, n) in normals.iter().enumerate() {
            for c in 0..3 {
                let a = f32::from(d8[i * 4 + c]) / 127.0;
                let b = f32::from(d16[i * 4 + c]) / 32767.0;
                assert!((a - n[c]).abs() < 0.02, "8-bit {a} vs {}", n[c]);
                assert!((b - n[c]).abs() < 1e-3, "16-bit {b} vs {}", n[c]);
            }
        }

        // Quaternion: unit rotations in 16-bit components.
        let quats: Vec<[f32; 4]> = (0..40)
            .map(|i| {
                let q = glam::Quat::from_euler(
                    glam::EulerRot::XYZ,
                    i as f32 * 0.1,
                    0.3,
                    -(i as f32) * 0.05,
                );
                q.to_array()
            })
            .collect();
        let eq = meshopt::encode_filter_quat(&quats, 12);
        let sq = meshopt::encode_vertex_buffer(&eq).expect("encodes");
        let dq = decode_view(
            3,
            EXTENSIONS[0],
            &ext("ATTRIBUTES", Some("QUATERNION"), 8, 40, sq.len() as u64),
            320,
            &sq,
            &budget(),
        )
        .expect("decodes");
        let dq: &[i16] = bytemuck::cast_slice(&dq);
        for (i, q) in quats.iter().enumerate() {
            let got = glam::Quat::from_xyzw(
                f32::from(dq[i * 4]) / 32767.0,
                f32::from(dq[i * 4 + 1]) / 32767.0,
                f32::from(dq[i * 4 + 2]) / 32767.0,
                f32::from(dq[i * 4 + 3]) / 32767.0,
            );
            let want = glam::Quat::from_array(*q);
            assert!(got.dot(want).abs() > 0.999, "{got:?} vs {want:?}");
        }

        // Plain attributes decode exactly.
        let raw: Vec<[u16; 4]> = (0..33).map(|i| [i, i * 7, 65535 - i, 3]).collect();
        let sr = meshopt::encode_vertex_buffer(&raw).expect("encodes");
        let dr = decode_view(
            4,
            EXTENSIONS[0],
            &ext("ATTRIBUTES", None, 8, 33, sr.len() as u64),
            264,
            &sr,
            &budget(),
        )
        .expect("decodes");
        assert_eq!(bytes(&dr, 264), bytemuck::cast_slice::<[u16; 4], u8>(&raw));
    }

    #[test]
    fn index_streams_round_trip() {
        let tris: Vec<u32> = vec![0, 1, 2, 2, 1, 3, 3, 1, 4, 4, 5, 3];
        let st = meshopt::encode_index_buffer(&tris, 6).expect("encodes");
        // The triangle codec may rotate a triangle's corners (its winding is kept).
        let canonical = |t: &[u32]| -> Vec<[u32; 3]> {
            t.chunks_exact(3)
                .map(|c| {
                    let r = (0..3).min_by_key(|&i| c[i]).unwrap_or(0);
                    [c[r], c[(r + 1) % 3], c[(r + 2) % 3]]
                })
                .collect()
        };
        let d = decode_view(
            0,
            EXTENSIONS[0],
            &ext("TRIANGLES", None, 4, 12, st.len() as u64),
            48,
            &st,
            &budget(),
        )
        .expect("decodes");
        assert_eq!(canonical(&d[..12]), canonical(&tris));
        let d16 = decode_view(
            0,
            EXTENSIONS[0],
            &ext("TRIANGLES", None, 2, 12, st.len() as u64),
            24,
            &st,
            &budget(),
        )
        .expect("decodes");
        let d16: Vec<u32> = bytemuck::cast_slice::<u32, u16>(&d16)[..12]
            .iter()
            .map(|&i| u32::from(i))
            .collect();
        assert_eq!(canonical(&d16), canonical(&tris));
        let seq: Vec<u32> = vec![5, 9, 9, 1, 0, 700];
        let ss = meshopt::encode_index_sequence(&seq, 701).expect("encodes");
        let d = decode_view(
            0,
            EXTENSIONS[0],
            &ext("INDICES", None, 4, 6, ss.len() as u64),
            24,
            &ss,
            &budget(),
        )
        .expect("decodes");
        assert_eq!(&d[..6], &seq[..]);
    }

    #[test]
    fn bad_parameters_and_streams_are_errors() {
        let raw: Vec<[f32; 3]> = (0..50).map(|i| [i as f32, 0.5, -1.0]).collect();
        let s = meshopt::encode_vertex_buffer(&raw).expect("encodes");
        let b = budget();
        let ok = ext("ATTRIBUTES", None, 12, 50, s.len() as u64);
        assert!(decode_view(0, "EXT_meshopt_compression", &ok, 600, &s, &b).is_ok());
        for (e, len) in [
            (ext("ATTRIBUTES", None, 6, 100, s.len() as u64), 600),
            (ext("ATTRIBUTES", None, 260, 1, s.len() as u64), 260),
            (
                ext("ATTRIBUTES", Some("OCTAHEDRAL"), 12, 50, s.len() as u64),
                600,
            ),
            (
                ext("ATTRIBUTES", Some("QUATERNION"), 4, 150, s.len() as u64),
                600,
            ),
            (
                ext("ATTRIBUTES", Some("COLOR"), 4, 150, s.len() as u64),
                600,
            ),
            (
                ext("ATTRIBUTES", Some("SHINY"), 12, 50, s.len() as u64),
                600,
            ),
            (ext("TRIANGLES", None, 4, 10, s.len() as u64), 40),
            (ext("TRIANGLES", None, 3, 12, s.len() as u64), 36),
            (
                ext("INDICES", Some("EXPONENTIAL"), 4, 10, s.len() as u64),
                40,
            ),
            (ext("POINTS", None, 4, 10, s.len() as u64), 40),
            (ext("ATTRIBUTES", None, 12, 50, s.len() as u64), 599),
            (ext("ATTRIBUTES", None, 12, 50, s.len() as u64 + 1), 600),
            (
                ext("ATTRIBUTES", None, 4, u64::MAX / 2, s.len() as u64),
                600,
            ),
        ] {
            assert!(
                decode_view(0, "EXT_meshopt_compression", &e, len, &s, &b).is_err(),
                "{e:?}"
            );
        }
        // Truncated and corrupted streams are errors or (for bit flips) some decoded bytes,
        // never a crash.
        for cut in [0, 1, 2, s.len() / 2, s.len() - 1] {
            let e = ext("ATTRIBUTES", None, 12, 50, cut as u64);
            assert!(decode_view(0, "EXT_meshopt_compression", &e, 600, &s[..cut], &b).is_err());
        }
        let mut flipped = s.clone();
        for i in 0..flipped.len() {
            flipped[i] ^= 0x5a;
            let _ = decode_view(0, "EXT_meshopt_compression", &ok, 600, &flipped, &b);
            flipped[i] ^= 0x5a;
        }
        // A huge declared count is refused by the budget before anything is allocated.
        let small = Budget::new(1 << 20, "--max-upload-memory", None);
        let huge = ext("ATTRIBUTES", None, 256, 1 << 30, s.len() as u64);
        assert!(matches!(
            decode_view(0, "EXT_meshopt_compression", &huge, 256 << 30, &s, &small),
            Err(ImportError::Budget(_))
        ));
    }
}
