//! Texture images: header sniffing, decoding with memory charged first, downscaling, mips.
//!
//! A rig's images come inside a hostile file: a 100-byte PNG may declare 50,000 × 50,000
//! pixels (10 GB of RGBA), a JPEG may be cut short, a "PNG" may be a JPEG. This module reads
//! them so that nothing proportional to an image's size is allocated before it is charged to
//! the operation's [`Budget`]:
//!
//! 1. [`sniff`] reads the header only (PNG `IHDR`, the JPEG marker scan up to `SOFn`, WebP
//!    `VP8 `/`VP8L`/`VP8X`) and allocates nothing proportional to the image;
//! 2. [`decode_cost`] turns a header into the most bytes [`decode`] charges at once, which
//!    the importer reserves before decoding anything (a bomb is a 413 at that point);
//! 3. [`decode`] charges each buffer before it exists (the full-size RGBA8 image with the
//!    decoder's scratch, each halving, the mip chain, the re-encoded bytes), releases what it
//!    frees, and returns with only what the image keeps still charged ([`kept_bytes`]);
//! 4. [`decode_pixels`] rebuilds the pixels of an image already imported (store, replica).
//!
//! The decoders are the ones the `image` crate is built on, each called where it lets us
//! control its memory:
//!
//! - PNG: `png`, expanding and stripping to 8 bits, so grey, grey + alpha, palette (with
//!   `tRNS` alpha), 16-bit and Adam7-interlaced images all come out as 8-bit samples, written
//!   into the front of the RGBA buffer and widened in place (no second buffer). `image`'s
//!   own PNG adapter keeps 16 bits, which would need twice the buffer.
//! - JPEG: `zune-jpeg` (what `image` uses), called directly: `image`'s adapter first copies
//!   the whole file, a copy [`decode_cost`] could not know the size of. Baseline, progressive,
//!   grey, CMYK and YCCK (converted to RGB) are read. Lenient mode, as `image` and browsers
//!   are, except that a file without an end-of-image marker after its image data is refused
//!   as cut short instead of being drawn half grey.
//! - WebP: `image`'s WebP decoder (`image-webp`): lossy, lossless, extended (alpha) and
//!   animated files, of which the first frame is drawn.
//!
//! Scratch estimates follow what those decoders allocate (read from their sources):
//! `zune-jpeg` holds every DCT coefficient of a progressive (or non-interleaved) JPEG as
//! `i16`, `image-webp` holds YUV planes, alpha planes, a lossless temporary and an animation
//! canvas. Two things they allocate are bounded by the file's size instead, and so are not in
//! [`decode_cost`]: `image-webp` copies a lossy stream's compressed partitions (charged by
//! [`decode`] as twice the file's size), and builds lossless Huffman tables for as many groups
//! as the bitstream names (a few KB per group, each costing the file a few bytes). It also
//! sizes a lossy stream's partition buffers from lengths the stream declares (at most 16 MB
//! each); they are zeroed by the allocator and filled only as far as the file goes.
//!
//! What hostile images get: unknown magic, an empty slice, 0 × 0, a truncated or corrupt
//! file (any decoder error, a JPEG without its end marker, a still WebP whose canvas is not
//! its image) and a decoder panic are [`ImageError::Invalid`] naming the index; a header
//! declaring more pixels than the budget allows is [`ImageError::Budget`] before anything is
//! allocated; a declared MIME type the magic contradicts, an animated WebP or PNG (first frame
//! or default image drawn) and a downscale are decoded with a note.
//!
//! Above `--max-texture-size` an image is halved with the mip filter until both sides fit
//! (so a non-power-of-two side may end below the maximum), then re-encoded: PNG at zlib
//! level 1 for PNG and WebP sources, JPEG q92 for JPEG sources. Mips run down to 1 × 1 with
//! a box filter that averages the encoded values (`halve` says why not in linear light).
//!
//! Colour: pixels stay in the space they were encoded in (ICC profiles and EXIF orientation
//! are ignored, as glTF viewers do); sRGB or linear is the sampling slot's business.

use std::io::{Cursor, Write};
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::sync::Arc;

use crowdmorph_core::budget::{Budget, BudgetError};
use crowdmorph_core::rig::{ImageData, ImageMime, MipLevel, Mips};

/// What an image's header says, read without decoding it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ImageHeader {
    /// The encoding, from the magic bytes (not from any declared MIME type).
    pub mime: ImageMime,
    /// Width in pixels (nonzero).
    pub width: u32,
    /// Height in pixels (nonzero).
    pub height: u32,
}

/// Why an image could not be decoded.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    /// The image is not one the import reads: unknown magic, 0 × 0, cut short, corrupt, or a
    /// feature its decoder refuses. The index is the file's image index.
    #[error("image {index}: {problem}")]
    Invalid {
        /// The file's image index.
        index: usize,
        /// What is wrong.
        problem: String,
    },
    /// Decoding it would hold more memory than the budget allows (an image bomb, or just an
    /// image too big for the limits).
    #[error(transparent)]
    Budget(#[from] BudgetError),
}

/// JPEG quality of the re-encoded image when a JPEG is downscaled: high enough that the
/// second generation is not visibly worse than the first.
pub const REENCODE_JPEG_QUALITY: u8 = 92;

const PNG_SIGNATURE: [u8; 8] = [0x89, b'P', b'N', b'G', b'\r', b'\n', 0x1A, b'\n'];

/// What any decoder or encoder holds that does not grow with the image: Huffman and zlib
/// state, chunk tables, the metadata a decoder keeps.
const FIXED_SCRATCH: u64 = 1 << 20;

/// Most bytes of ancillary chunks (`PLTE`, `tRNS`, `eXIf`, ...) the PNG decoder may hold;
/// text and ICC chunks are skipped unread.
const PNG_METADATA_LIMIT: u64 = 1 << 20;

fn invalid(index: usize, problem: impl Into<String>) -> ImageError {
    ImageError::Invalid {
        index,
        problem: problem.into(),
    }
}

/// The format's name as messages write it.
fn format_name(mime: ImageMime) -> &'static str {
    match mime {
        ImageMime::Png => "PNG",
        ImageMime::Jpeg => "JPEG",
        ImageMime::Webp => "WebP",
    }
}

// ------------------------------------------------------------------------------------------
// Headers
// ------------------------------------------------------------------------------------------

/// What the decoder of a format will allocate depends on more than the size: this is what the
/// header says about it (private: [`ImageHeader`] is what callers see).
#[derive(Clone, Copy, Debug)]
enum Layout {
    Png,
    Jpeg(JpegLayout),
    Webp(WebpKind),
}

#[derive(Clone, Copy, Debug, Default)]
struct JpegLayout {
    /// `SOF2`, `SOF6`, `SOF10`, `SOF14`: every coefficient is held until the last scan.
    progressive: bool,
    /// Number of components (1 to 4).
    components: u8,
    /// (horizontal, vertical) sampling factors of each component.
    sampling: [(u8, u8); 4],
    /// Components of the first scan, when the header reaches one: fewer than the frame's
    /// means the scans are not interleaved and the decoder holds every coefficient.
    first_scan: Option<u8>,
    /// Where the first scan's entropy-coded data starts.
    data_start: usize,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum WebpKind {
    /// A bare `VP8 ` chunk.
    Lossy,
    /// A bare `VP8L` chunk.
    Lossless,
    /// `VP8X`: alpha, metadata, or animation.
    Extended { animated: bool },
}

fn bytes_at<const N: usize>(b: &[u8], at: usize) -> Option<[u8; N]> {
    b.get(at..at.checked_add(N)?)?.try_into().ok()
}

fn be16(b: &[u8], at: usize) -> Option<u16> {
    bytes_at(b, at).map(u16::from_be_bytes)
}

fn be32(b: &[u8], at: usize) -> Option<u32> {
    bytes_at(b, at).map(u32::from_be_bytes)
}

fn le16(b: &[u8], at: usize) -> Option<u16> {
    bytes_at(b, at).map(u16::from_le_bytes)
}

fn le24(b: &[u8], at: usize) -> Option<u32> {
    bytes_at::<3>(b, at).map(|[a, c, d]| u32::from_le_bytes([a, c, d, 0]))
}

fn le32(b: &[u8], at: usize) -> Option<u32> {
    bytes_at(b, at).map(u32::from_le_bytes)
}

/// Reads only the header (PNG IHDR, JPEG SOFn marker scan, WebP VP8/VP8L/VP8X): allocates
/// nothing proportional to the image. The format comes from the magic bytes; an image that
/// declares 0 × 0 pixels is refused here.
pub fn sniff(bytes: &[u8]) -> Result<ImageHeader, String> {
    sniff_layout(bytes).map(|(h, _)| h)
}

fn sniff_layout(b: &[u8]) -> Result<(ImageHeader, Layout), String> {
    let (mime, width, height, layout) = if b.starts_with(&PNG_SIGNATURE) {
        let (w, h) = sniff_png(b)?;
        (ImageMime::Png, w, h, Layout::Png)
    } else if b.starts_with(&[0xFF, 0xD8]) {
        let (w, h, l) = sniff_jpeg(b)?;
        (ImageMime::Jpeg, w, h, Layout::Jpeg(l))
    } else if b.starts_with(b"RIFF") && b.get(8..12) == Some(b"WEBP") {
        let (w, h, k) = sniff_webp(b)?;
        (ImageMime::Webp, w, h, Layout::Webp(k))
    } else if b.is_empty() {
        return Err("the image is empty".into());
    } else {
        let start: Vec<String> = b.iter().take(8).map(|x| format!("{x:02x}")).collect();
        return Err(format!(
            "not a PNG, JPEG or WebP image (it starts with {})",
            start.join(" ")
        ));
    };
    if width == 0 || height == 0 {
        return Err(format!(
            "the {} declares {width} × {height} pixels",
            format_name(mime)
        ));
    }
    Ok((
        ImageHeader {
            mime,
            width,
            height,
        },
        layout,
    ))
}

fn sniff_png(b: &[u8]) -> Result<(u32, u32), String> {
    let short = || format!("the PNG header is cut short ({} bytes)", b.len());
    let length = be32(b, 8).ok_or_else(short)?;
    let kind = b.get(12..16).ok_or_else(short)?;
    if kind != b"IHDR" || length != 13 {
        return Err("the PNG does not start with its IHDR chunk".into());
    }
    let (w, h) = (
        be32(b, 16).ok_or_else(short)?,
        be32(b, 20).ok_or_else(short)?,
    );
    // The PNG specification's limit; the decoder refuses more.
    if w > i32::MAX as u32 || h > i32::MAX as u32 {
        return Err(format!(
            "the PNG declares {w} × {h} pixels (at most 2^31 - 1 a side)"
        ));
    }
    Ok((w, h))
}

/// Whether a JPEG marker starts a frame (`SOF0`–`SOF15` less `DHT`, `JPG` and `DAC`).
fn is_sof(m: u8) -> bool {
    matches!(m, 0xC0..=0xCF) && !matches!(m, 0xC4 | 0xC8 | 0xCC)
}

/// Walks the markers up to the frame header (and on to the first scan, for the layout).
fn sniff_jpeg(b: &[u8]) -> Result<(u32, u32, JpegLayout), String> {
    let short = "the JPEG ends before its frame header";
    let mut at = 2usize;
    let mut layout = JpegLayout::default();
    let mut frame: Option<(u32, u32)> = None;
    // Decoders skip stray bytes between segments; so does this scan.
    while let Some(&byte) = b.get(at) {
        if byte != 0xFF {
            at += 1;
            continue;
        }
        while b.get(at) == Some(&0xFF) {
            at += 1;
        }
        let Some(&marker) = b.get(at) else { break };
        at += 1;
        match marker {
            // Standalone markers: no length.
            0x00 | 0x01 | 0xD0..=0xD8 => continue,
            0xD9 => break,
            _ => {}
        }
        let length = usize::from(be16(b, at).ok_or(short)?);
        if length < 2 {
            return Err(format!("the JPEG has a marker segment of length {length}"));
        }
        if marker == 0xDA {
            if frame.is_none() {
                return Err("the JPEG has image data before its frame header".into());
            }
            layout.first_scan = b.get(at + 2).copied();
            layout.data_start = at.saturating_add(length);
            break;
        }
        if is_sof(marker) {
            if frame.is_some() {
                return Err("the JPEG has two frame headers".into());
            }
            let h = be16(b, at + 3).ok_or(short)?;
            let w = be16(b, at + 5).ok_or(short)?;
            let n = *b.get(at + 7).ok_or(short)?;
            if !(1..=4).contains(&n) {
                return Err(format!("the JPEG has {n} components (1 to 4 are read)"));
            }
            for i in 0..usize::from(n) {
                let hv = *b.get(at + 9 + 3 * i).ok_or(short)?;
                let (sh, sv) = (hv >> 4, hv & 0x0F);
                if !(1..=4).contains(&sh) || !(1..=4).contains(&sv) {
                    return Err(format!("the JPEG has a sampling factor of {sh} × {sv}"));
                }
                layout.sampling[i] = (sh, sv);
            }
            layout.components = n;
            layout.progressive = matches!(marker, 0xC2 | 0xC6 | 0xCA | 0xCE);
            frame = Some((u32::from(w), u32::from(h)));
        }
        at = at.saturating_add(length);
    }
    let (w, h) = frame.ok_or(short)?;
    Ok((w, h, layout))
}

fn sniff_webp(b: &[u8]) -> Result<(u32, u32, WebpKind), String> {
    let short = || format!("the WebP header is cut short ({} bytes)", b.len());
    let chunk = b.get(12..16).ok_or_else(short)?;
    match chunk {
        b"VP8 " => {
            let (w, h) = vp8_size(b, 20)?.ok_or_else(short)?;
            Ok((w, h, WebpKind::Lossy))
        }
        b"VP8L" => {
            let (w, h) = vp8l_size(b, 20)?.ok_or_else(short)?;
            Ok((w, h, WebpKind::Lossless))
        }
        b"VP8X" => {
            let flags = *b.get(20).ok_or_else(short)?;
            let w = le24(b, 24).ok_or_else(short)? + 1;
            let h = le24(b, 27).ok_or_else(short)? + 1;
            let animated = flags & 0x02 != 0;
            // A still image's canvas is its image: a canvas larger than the image it holds
            // would be charged and allocated for nothing, so it is refused from the header.
            if !animated
                && let Some((iw, ih)) = extended_image_size(b)?
                && (iw, ih) != (w, h)
            {
                return Err(format!(
                    "the WebP's canvas is {w} × {h} but its image is {iw} × {ih}"
                ));
            }
            Ok((w, h, WebpKind::Extended { animated }))
        }
        other => Err(format!(
            "the WebP starts with an unknown chunk {:?}",
            String::from_utf8_lossy(other)
        )),
    }
}

/// The size in a `VP8 ` chunk's frame header at `at`; `None` when the slice ends first.
fn vp8_size(b: &[u8], at: usize) -> Result<Option<(u32, u32)>, String> {
    let (Some(tag), Some(code), Some(w), Some(h)) = (
        le24(b, at),
        bytes_at::<3>(b, at + 3),
        le16(b, at + 6),
        le16(b, at + 8),
    ) else {
        return Ok(None);
    };
    if tag & 1 != 0 {
        return Err("the WebP's VP8 frame is not a key frame".into());
    }
    if code != [0x9D, 0x01, 0x2A] {
        return Err("the WebP's VP8 frame has no start code".into());
    }
    Ok(Some((u32::from(w & 0x3FFF), u32::from(h & 0x3FFF))))
}

/// The size in a `VP8L` chunk's header at `at`; `None` when the slice ends first.
fn vp8l_size(b: &[u8], at: usize) -> Result<Option<(u32, u32)>, String> {
    let (Some(&signature), Some(bits)) = (b.get(at), le32(b, at + 1)) else {
        return Ok(None);
    };
    if signature != 0x2F {
        return Err("the WebP's VP8L stream has no signature".into());
    }
    Ok(Some(((bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1)))
}

/// The size of the image of an extended (`VP8X`) still WebP: its `VP8 ` or `VP8L` chunk, found
/// by walking the chunks after the header; `None` when the slice ends first.
fn extended_image_size(b: &[u8]) -> Result<Option<(u32, u32)>, String> {
    let mut at = 12usize;
    while let (Some(kind), Some(size)) = (
        bytes_at::<4>(b, at),
        at.checked_add(4).and_then(|p| le32(b, p)),
    ) {
        let data = at + 8;
        match &kind {
            b"VP8 " => return vp8_size(b, data),
            b"VP8L" => return vp8l_size(b, data),
            _ => {}
        }
        // Chunks are padded to an even size.
        let next = data as u64 + u64::from(size) + u64::from(size & 1);
        let Ok(next) = usize::try_from(next) else {
            break;
        };
        at = next;
    }
    Ok(None)
}

// ------------------------------------------------------------------------------------------
// Costs
// ------------------------------------------------------------------------------------------

fn pixels(w: u32, h: u32) -> u64 {
    u64::from(w) * u64::from(h)
}

fn rgba_bytes(w: u32, h: u32) -> u64 {
    pixels(w, h).saturating_mul(4)
}

/// [`Mips::chain_bytes`] without overflow for any `u32` size.
fn chain_bytes(w: u32, h: u32) -> u64 {
    let (mut w, mut h, mut total) = (w.max(1), h.max(1), 0u64);
    loop {
        total = total.saturating_add(rgba_bytes(w, h));
        if w == 1 && h == 1 {
            return total;
        }
        (w, h) = half(w, h);
    }
}

/// The next mip level's size: each side halved, rounded down, at least 1 (glTF and
/// `glGenerateMipmap`'s rule).
fn half(w: u32, h: u32) -> (u32, u32) {
    ((w / 2).max(1), (h / 2).max(1))
}

/// The size an image is stored at: halved until both sides are at most `max`.
fn fitted_size(w: u32, h: u32, max: u32) -> (u32, u32) {
    let max = max.max(1);
    let (mut w, mut h) = (w, h);
    while w > max || h > max {
        (w, h) = half(w, h);
    }
    (w, h)
}

/// Row accumulators and tap tables of one halving of a `w × h` level.
fn filter_scratch(w: u32, h: u32) -> u64 {
    64 * (u64::from(w) + u64::from(h)) + 4096
}

/// The decoder's scratch for any image of this header: the most over every file that could
/// have it (what [`decode_cost`] reserves).
fn worst_scratch(h: &ImageHeader) -> u64 {
    let (w, hh) = (u64::from(h.width), u64::from(h.height));
    match h.mime {
        // Rows being unfiltered (16-bit RGBA at worst) and the ancillary chunks.
        ImageMime::Png => png_scratch(h.width),
        // Four full-resolution components of `i16` coefficients, padded to 4 × 8 pixels.
        ImageMime::Jpeg => jpeg_row_scratch(h.width)
            .saturating_add((w + 31).saturating_mul(hh + 31).saturating_mul(8)),
        ImageMime::Webp => webp_scratch(h, WebpKind::Extended { animated: true }),
    }
}

fn png_scratch(w: u32) -> u64 {
    let row = u64::from(w) * 8 + 1;
    FIXED_SCRATCH + PNG_METADATA_LIMIT + 16 * row
}

/// `zune-jpeg`'s per-row buffers: a row of MCUs of up to 4 components with their upsampling
/// rows (at most a few hundred bytes per column).
fn jpeg_row_scratch(w: u32) -> u64 {
    FIXED_SCRATCH + 2048 * (u64::from(w) + 32)
}

fn jpeg_scratch(h: &ImageHeader, l: &JpegLayout) -> u64 {
    let rows = jpeg_row_scratch(h.width);
    let interleaved_in_one_scan = l.first_scan == Some(l.components);
    if !l.progressive && interleaved_in_one_scan {
        return rows;
    }
    // Every coefficient until the last scan: MCUs × blocks of each component × 64 × i16.
    let comps = &l.sampling[..usize::from(l.components)];
    let hmax = u64::from(comps.iter().map(|s| s.0).max().unwrap_or(1));
    let vmax = u64::from(comps.iter().map(|s| s.1).max().unwrap_or(1));
    let mcus_x = u64::from(h.width).div_ceil(8 * hmax);
    let mcus_y = u64::from(h.height).div_ceil(8 * vmax);
    let blocks: u64 = comps
        .iter()
        .map(|&(sh, sv)| u64::from(sh) * u64::from(sv))
        .sum();
    rows.saturating_add(
        mcus_x
            .saturating_mul(mcus_y)
            .saturating_mul(blocks)
            .saturating_mul(128),
    )
}

/// `image-webp`'s buffers besides ours, in units of the padded area (macroblocks of 16):
/// lossy YUV planes (1.5); a lossless file without alpha decodes into an RGBA temporary (4)
/// plus its transforms and entropy image (2); an extended still image adds an alpha plane,
/// possibly lossless-coded (6); an animation adds a canvas and a frame (4 + 4).
fn webp_scratch(h: &ImageHeader, kind: WebpKind) -> u64 {
    let padded = (u64::from(h.width) + 16).saturating_mul(u64::from(h.height) + 16);
    let units = match kind {
        WebpKind::Lossy => 2,
        WebpKind::Lossless => 6,
        WebpKind::Extended { animated: false } => 8,
        WebpKind::Extended { animated: true } => 12,
    };
    FIXED_SCRATCH.saturating_add(padded.saturating_mul(units))
}

/// The decoder's scratch for this file, from what its header says (at most [`worst_scratch`]).
fn scratch(h: &ImageHeader, layout: &Layout) -> u64 {
    match layout {
        Layout::Png => png_scratch(h.width),
        Layout::Jpeg(l) => jpeg_scratch(h, l),
        Layout::Webp(kind) => webp_scratch(h, *kind),
    }
}

/// Copies of the encoded bytes a decoder makes: `image-webp` reads a lossy stream's
/// partitions into buffers of their own (twice, for the last one).
fn copies(layout: &Layout, encoded: usize) -> u64 {
    match layout {
        Layout::Webp(WebpKind::Lossless) | Layout::Png | Layout::Jpeg(_) => 0,
        Layout::Webp(_) => 2 * encoded as u64,
    }
}

/// Most bytes the re-encoded image may take: a deflated PNG is at most its raw rows plus
/// the stored blocks' overhead; a q92 4:4:4 JPEG of adversarial content may spend ~10 bytes
/// a pixel with the default Huffman tables.
fn encoded_bound(mime: ImageMime, w: u32, h: u32) -> u64 {
    let raw = pixels(w, h).saturating_mul(4).saturating_add(u64::from(h));
    let bound = match mime {
        ImageMime::Jpeg => pixels(w, h).saturating_mul(10),
        ImageMime::Png | ImageMime::Webp => raw.saturating_add(raw / 64),
    };
    bound.saturating_add(64 << 10)
}

/// The output's growth (at most 1.5 × its final size), the shared copy made of it, and the
/// encoder's rows and tables.
fn encode_peak(mime: ImageMime, w: u32, h: u32) -> u64 {
    let bound = encoded_bound(mime, w, h);
    bound
        .saturating_mul(5)
        .div_ceil(2)
        .saturating_add(FIXED_SCRATCH + 128 * (u64::from(w) + 16))
}

/// The output format of a downscaled image: JPEG stays JPEG, the rest becomes PNG.
fn reencoded_mime(source: ImageMime) -> ImageMime {
    match source {
        ImageMime::Jpeg => ImageMime::Jpeg,
        ImageMime::Png | ImageMime::Webp => ImageMime::Png,
    }
}

/// The most `decode` charges at once for a decoder scratch of `scratch` bytes: the largest of
/// its phases (decoding; each halving; the chain; re-encoding beside the chain).
fn peak(h: &ImageHeader, scratch: u64, max_texture_size: u32) -> u64 {
    let (w, hh) = (h.width, h.height);
    let mut peak = rgba_bytes(w, hh).saturating_add(scratch);
    let target = fitted_size(w, hh, max_texture_size);
    let (mut cw, mut ch) = (w, hh);
    while (cw, ch) != target {
        let (nw, nh) = half(cw, ch);
        let step = rgba_bytes(cw, ch)
            .saturating_add(rgba_bytes(nw, nh))
            .saturating_add(filter_scratch(cw, ch));
        peak = peak.max(step);
        (cw, ch) = (nw, nh);
    }
    let (tw, th) = target;
    let chain = chain_bytes(tw, th);
    peak = peak.max(chain.saturating_add(filter_scratch(tw, th)));
    if target != (w, hh) {
        let out = reencoded_mime(h.mime);
        peak = peak.max(chain.saturating_add(encode_peak(out, tw, th)));
    }
    peak
}

/// The most bytes `decode` charges at once for an image with this header (full-size RGBA8,
/// decoder scratch, downscaled copy, final mip chain) — what the importer reserves up front so
/// a tiny PNG declaring 50,000 × 50,000 is refused (413) before any allocation.
///
/// It is the worst case over every file with this header (a progressive JPEG, an animated
/// WebP); [`decode`] charges what the file's own header needs, never more, except for the
/// copies a lossy WebP's decoder makes of its compressed bytes (up to twice the file's
/// size), which are not known from the header and which [`decode`] charges as well.
pub fn decode_cost(h: &ImageHeader, max_texture_size: u32) -> u64 {
    peak(h, worst_scratch(h), max_texture_size)
}

/// Bytes the budget still holds for `image` after [`decode`] returned it (or
/// [`decode_pixels`], whose image is never downscaled): its mip chain, and its re-encoded
/// bytes when it was downscaled (the original bytes are the caller's).
pub fn kept_bytes(image: &ImageData) -> u64 {
    let chain = image.pixels.as_ref().map_or(0, |p| p.bytes() as u64);
    let encoded = if image.downscaled_from.is_some() {
        image.bytes.len() as u64
    } else {
        0
    };
    chain + encoded
}

// ------------------------------------------------------------------------------------------
// Charges
// ------------------------------------------------------------------------------------------

/// Bytes charged to a budget and given back when dropped, so every early return (a corrupt
/// file half decoded) releases what it charged.
struct Held<'b> {
    budget: &'b Budget,
    bytes: u64,
}

impl<'b> Held<'b> {
    fn new(budget: &'b Budget) -> Self {
        Held { budget, bytes: 0 }
    }

    fn charge(&mut self, bytes: u64, what: impl Fn() -> String) -> Result<(), BudgetError> {
        self.budget.charge(bytes, what)?;
        self.bytes += bytes;
        Ok(())
    }

    fn release(&mut self, bytes: u64) {
        let bytes = bytes.min(self.bytes);
        self.budget.release(bytes);
        self.bytes -= bytes;
    }

    /// Leaves what is held charged: it now belongs to the image returned.
    fn keep(mut self) {
        self.bytes = 0;
    }
}

impl Drop for Held<'_> {
    fn drop(&mut self) {
        if self.bytes > 0 {
            self.budget.release(self.bytes);
        }
    }
}

/// A zeroed buffer of `len` bytes, already charged.
fn zeroed(index: usize, len: u64) -> Result<Vec<u8>, ImageError> {
    let len = usize::try_from(len)
        .map_err(|_| invalid(index, "the image is too large for this machine's memory"))?;
    // Zeroed by the allocator: pages a decoder never writes (a file that declares more than
    // it holds) cost address space, not memory.
    Ok(vec![0; len])
}

/// Runs a third-party decoder or encoder: its errors become [`ImageError::Invalid`], and so
/// does a panic on hostile input (a decoder bug must not take the server down).
fn guarded<T>(
    index: usize,
    codec: &str,
    f: impl FnOnce() -> Result<T, ImageError>,
) -> Result<T, ImageError> {
    catch_unwind(AssertUnwindSafe(f)).unwrap_or_else(|_| {
        Err(invalid(
            index,
            format!("the {codec} decoder failed on this file (it panicked)"),
        ))
    })
}

// ------------------------------------------------------------------------------------------
// Decoding
// ------------------------------------------------------------------------------------------

/// Decodes image `index` (for messages: "image {index}: ...") of the file; `declared` is the
/// glTF mimeType if any.
///
/// The result is the [`ImageData`] to keep: its bytes are the original bytes when not
/// downscaled, else re-encoded (PNG for PNG and WebP sources, JPEG q92 for JPEG sources);
/// width and height are the final size; `downscaled_from` is the original size when
/// downscaled; `pixels` is the full RGBA8 chain. Then the notes: a declared MIME type the
/// bytes contradict (the bytes win), an animation of which the first frame is drawn, a
/// downscale.
///
/// Every buffer is charged to `budget` before it is allocated and released when freed; on
/// success the budget still holds [`kept_bytes`] for the image, on error nothing.
pub fn decode(
    index: usize,
    bytes: Arc<[u8]>,
    declared: Option<ImageMime>,
    max_texture_size: u32,
    budget: &Budget,
) -> Result<(ImageData, Vec<String>), ImageError> {
    let (header, layout) = sniff_layout(&bytes).map_err(|p| invalid(index, p))?;
    let (w, h) = (header.width, header.height);
    let name = format_name(header.mime);
    let mut notes = Vec::new();
    if let Some(declared) = declared
        && declared != header.mime
    {
        notes.push(format!(
            "image {index} is declared {} but is a {name}",
            declared.as_str()
        ));
    }

    let mut held = Held::new(budget);
    let scratch = scratch(&header, &layout).saturating_add(copies(&layout, bytes.len()));
    held.charge(rgba_bytes(w, h).saturating_add(scratch), || {
        format!("image {index} ({w} × {h} {name}): its RGBA8 pixels and the decoder's scratch")
    })?;
    let (mut level, animated) = decode_rgba(index, &bytes, &header, &layout)?;
    held.release(scratch);
    if animated {
        notes.push(format!(
            "image {index} is an animated {name}: its {} is drawn",
            if header.mime == ImageMime::Png {
                "default image"
            } else {
                "first frame"
            }
        ));
    }

    // Halve until it fits, charging the next level before making it and releasing the one
    // it was made from.
    let target = fitted_size(w, h, max_texture_size);
    let (mut cw, mut ch) = (w, h);
    while (cw, ch) != target {
        let (nw, nh) = half(cw, ch);
        let step = rgba_bytes(nw, nh) + filter_scratch(cw, ch);
        held.charge(step, || {
            format!("image {index}: its {nw} × {nh} downscaled copy")
        })?;
        let mut next = zeroed(index, rgba_bytes(nw, nh))?;
        halve(&level, cw, ch, &mut next);
        drop(level);
        held.release(rgba_bytes(cw, ch) + filter_scratch(cw, ch));
        (level, cw, ch) = (next, nw, nh);
    }

    let (tw, th) = target;
    let rest = chain_bytes(tw, th) - rgba_bytes(tw, th) + filter_scratch(tw, th);
    held.charge(rest, || {
        format!("image {index}: the mip chain of its {tw} × {th} pixels")
    })?;
    let mips = mip_chain(index, level, tw, th)?;
    held.release(filter_scratch(tw, th));

    let (mime, encoded, downscaled_from) = if target == (w, h) {
        (header.mime, bytes, None)
    } else {
        let out = reencoded_mime(header.mime);
        let encoded = encode(index, out, &mips, budget)?;
        notes.push(format!(
            "image {index} {w} × {h} → {tw} × {th} (--max-texture-size)"
        ));
        (out, encoded, Some([w, h]))
    };
    held.keep();
    Ok((
        ImageData {
            mime,
            bytes: encoded,
            width: tw,
            height: th,
            downscaled_from,
            pixels: Some(Arc::new(mips)),
        },
        notes,
    ))
}

/// Rebuilds the pixels of an already-imported image (store or replica load: its bytes are
/// already ≤ max size): charges Mips::chain_bytes + scratch first. On success the budget
/// still holds the chain's bytes ([`kept_bytes`] of the image with its pixels); bytes that
/// are not the image the record describes (format or size) are refused.
pub fn decode_pixels(
    index: usize,
    image: &ImageData,
    budget: &Budget,
) -> Result<Arc<Mips>, ImageError> {
    let (header, layout) = sniff_layout(&image.bytes).map_err(|p| invalid(index, p))?;
    let (w, h) = (header.width, header.height);
    if header.mime != image.mime || (w, h) != (image.width, image.height) {
        return Err(invalid(
            index,
            format!(
                "its bytes are a {w} × {h} {}, but it is recorded as a {} × {} {}",
                format_name(header.mime),
                image.width,
                image.height,
                format_name(image.mime)
            ),
        ));
    }
    let chain = chain_bytes(w, h);
    let scratch = scratch(&header, &layout)
        .saturating_add(copies(&layout, image.bytes.len()))
        .max(filter_scratch(w, h));
    let mut held = Held::new(budget);
    held.charge(chain.saturating_add(scratch), || {
        format!(
            "image {index} ({w} × {h} {}): its mip chain and the decoder's scratch",
            format_name(header.mime)
        )
    })?;
    let (level, _) = decode_rgba(index, &image.bytes, &header, &layout)?;
    let mips = mip_chain(index, level, w, h)?;
    held.release(scratch);
    held.keep();
    Ok(Arc::new(mips))
}

/// Decodes the full-size image into a new RGBA8 buffer (charged by the caller with the
/// decoder's scratch); also says whether the file is animated.
fn decode_rgba(
    index: usize,
    bytes: &[u8],
    header: &ImageHeader,
    layout: &Layout,
) -> Result<(Vec<u8>, bool), ImageError> {
    let (w, h) = (header.width, header.height);
    let mut rgba = zeroed(index, rgba_bytes(w, h))?;
    let name = format_name(header.mime);
    let (channels, animated) = guarded(index, name, || match layout {
        Layout::Png => png_into(bytes, w, h, &mut rgba),
        Layout::Jpeg(l) => jpeg_into(bytes, w, h, l, &mut rgba),
        Layout::Webp(kind) => webp_into(bytes, w, h, *kind, &mut rgba),
    })
    .map_err(|e| match e {
        ImageError::Invalid { problem, .. } => invalid(index, problem),
        e => e,
    })?;
    widen_to_rgba(&mut rgba, channels);
    Ok((rgba, animated))
}

/// The first `w × h × channels` bytes of `rgba`, as decoders want their output.
fn front(rgba: &mut [u8], w: u32, h: u32, channels: usize) -> Result<&mut [u8], ImageError> {
    let n = usize::try_from(pixels(w, h))
        .ok()
        .and_then(|p| p.checked_mul(channels))
        .filter(|&n| n <= rgba.len())
        .ok_or_else(|| invalid(0, format!("{channels} channels do not fit RGBA")))?;
    Ok(&mut rgba[..n])
}

fn png_into(bytes: &[u8], w: u32, h: u32, rgba: &mut [u8]) -> Result<(usize, bool), ImageError> {
    let fail = |e: png::DecodingError| invalid(0, format!("the PNG cannot be decoded: {e}"));
    let limit = PNG_METADATA_LIMIT + 2 * (u64::from(w) * 8 + 1);
    let mut decoder = png::Decoder::new_with_limits(
        Cursor::new(bytes),
        png::Limits {
            bytes: usize::try_from(limit).unwrap_or(usize::MAX),
        },
    );
    // Palette, tRNS and low bit depths expand to 8-bit grey/RGB(A); 16 bits keep their high
    // byte, which is what a display of the 16-bit image shows.
    decoder.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
    decoder.set_ignore_text_chunk(true);
    decoder.set_ignore_iccp_chunk(true);
    let mut reader = decoder.read_info().map_err(fail)?;
    let info = reader.info();
    if (info.width, info.height) != (w, h) {
        return Err(invalid(0, "the PNG's header changed between two reads"));
    }
    let animated = info.animation_control().is_some();
    let (color, depth) = reader.output_color_type();
    if depth != png::BitDepth::Eight {
        return Err(invalid(0, format!("the PNG decodes to {depth:?} bits")));
    }
    let channels = color.samples();
    let out = front(rgba, w, h, channels)?;
    if reader.output_buffer_size() != Some(out.len()) {
        return Err(invalid(
            0,
            "the PNG's rows are not the size its header says",
        ));
    }
    reader.next_frame(out).map_err(fail)?;
    Ok((channels, animated))
}

fn jpeg_into(
    bytes: &[u8],
    w: u32,
    h: u32,
    layout: &JpegLayout,
    rgba: &mut [u8],
) -> Result<(usize, bool), ImageError> {
    use zune_core::bytestream::ZCursor;
    use zune_core::colorspace::ColorSpace;
    use zune_core::options::DecoderOptions;

    let fail =
        |e: zune_jpeg::errors::DecodeErrors| invalid(0, format!("the JPEG cannot be decoded: {e}"));
    // Lenient decoders draw a cut-short JPEG with grey where its data is missing; refuse it
    // instead: entropy-coded data cannot hold FF D9 (an FF there is followed by 00 or a
    // restart marker), so without one after the first scan the file is cut short.
    let data = bytes.get(layout.data_start..).unwrap_or_default();
    if !data.windows(2).any(|m| m == [0xFF, 0xD9]) {
        return Err(invalid(
            0,
            "the JPEG is cut short (no end-of-image marker after its image data)",
        ));
    }
    let options = DecoderOptions::default()
        .set_strict_mode(false)
        .set_max_width(w as usize)
        .set_max_height(h as usize);
    let mut probe = zune_jpeg::JpegDecoder::new_with_options(ZCursor::new(bytes), options);
    probe.decode_headers().map_err(fail)?;
    if probe.dimensions() != Some((w as usize, h as usize)) {
        return Err(invalid(
            0,
            "the JPEG's frame header is not the one it decodes",
        ));
    }
    let input = probe
        .input_colorspace()
        .ok_or_else(|| invalid(0, "the JPEG has no colour space"))?;
    if input.num_components() != usize::from(layout.components) {
        return Err(invalid(
            0,
            "the JPEG's components are not the ones it decodes",
        ));
    }
    // Grey stays one channel until widened; everything else (YCbCr, RGB, CMYK, YCCK) is
    // converted to RGB by the decoder. (Its CMYK → RGBA path writes 3-byte pixels into a
    // 4-byte stride, so RGBA is not asked for.)
    let (out, channels) = if input.num_components() == 1 {
        (ColorSpace::Luma, 1)
    } else {
        (ColorSpace::RGB, 3)
    };
    let mut decoder = zune_jpeg::JpegDecoder::new_with_options(
        ZCursor::new(bytes),
        options.jpeg_set_out_colorspace(out),
    );
    decoder.decode_headers().map_err(fail)?;
    let dest = front(rgba, w, h, channels)?;
    if decoder.output_buffer_size() != Some(dest.len()) {
        return Err(invalid(
            0,
            "the JPEG decodes to a size its header does not say",
        ));
    }
    decoder.decode_into(dest).map_err(fail)?;
    Ok((channels, false))
}

fn webp_into(
    bytes: &[u8],
    w: u32,
    h: u32,
    kind: WebpKind,
    rgba: &mut [u8],
) -> Result<(usize, bool), ImageError> {
    use ::image::ImageDecoder;
    use ::image::codecs::webp::WebPDecoder;

    let fail = |e: ::image::ImageError| invalid(0, format!("the WebP cannot be decoded: {e}"));
    // `image-webp` sizes an animation's canvas in `u32` arithmetic.
    if kind == (WebpKind::Extended { animated: true }) && rgba_bytes(w, h) > u64::from(u32::MAX) {
        return Err(invalid(
            0,
            format!("the animated WebP's {w} × {h} canvas is larger than its decoder reads"),
        ));
    }
    let decoder = WebPDecoder::new(Cursor::new(bytes)).map_err(fail)?;
    if decoder.dimensions() != (w, h) {
        return Err(invalid(0, "the WebP's header is not the one it decodes"));
    }
    let animated = decoder.has_animation();
    let channels = usize::from(decoder.color_type().channel_count());
    let out = front(rgba, w, h, channels)?;
    if decoder.total_bytes() != out.len() as u64 {
        return Err(invalid(
            0,
            "the WebP decodes to a size its header does not say",
        ));
    }
    decoder.read_image(out).map_err(fail)?;
    Ok((channels, animated))
}

/// Widens `channels`-sample pixels packed at the front of `rgba` to RGBA8 in place, from the
/// last pixel back so no sample is overwritten before it is read.
fn widen_to_rgba(rgba: &mut [u8], channels: usize) {
    let n = rgba.len() / 4;
    match channels {
        1 => {
            for i in (0..n).rev() {
                let g = rgba[i];
                rgba[4 * i..4 * i + 4].copy_from_slice(&[g, g, g, 255]);
            }
        }
        2 => {
            for i in (0..n).rev() {
                let (g, a) = (rgba[2 * i], rgba[2 * i + 1]);
                rgba[4 * i..4 * i + 4].copy_from_slice(&[g, g, g, a]);
            }
        }
        3 => {
            for i in (0..n).rev() {
                let (r, g, b) = (rgba[3 * i], rgba[3 * i + 1], rgba[3 * i + 2]);
                rgba[4 * i..4 * i + 4].copy_from_slice(&[r, g, b, 255]);
            }
        }
        _ => {}
    }
}

// ------------------------------------------------------------------------------------------
// Filtering
// ------------------------------------------------------------------------------------------

/// Source pixels one destination pixel averages along an axis, with weights in 1/256 that
/// sum to 256.
#[derive(Clone, Copy, Debug)]
struct Taps {
    first: usize,
    count: usize,
    weights: [u32; 4],
}

/// The taps of halving an axis of `n` pixels to `max(1, n / 2)`: a box filter, i.e. each
/// destination pixel is the area average of the source pixels it covers. Even sizes average
/// pairs; an odd size `2m + 1` spreads over `m` pixels of `2 + 1/m` source pixels each (a
/// middle pixel split between two neighbours), so no source pixel is dropped and a constant
/// image stays constant; a single pixel stays itself.
fn axis_taps(n: u32) -> Vec<Taps> {
    let n = n.max(1) as usize;
    let m = (n / 2).max(1);
    (0..m)
        .map(|i| {
            if n == 1 {
                return Taps {
                    first: 0,
                    count: 1,
                    weights: [256, 0, 0, 0],
                };
            }
            if n.is_multiple_of(2) {
                return Taps {
                    first: 2 * i,
                    count: 2,
                    weights: [128, 128, 0, 0],
                };
            }
            // In units of 1/m source pixel: destination i spans [i·n, (i+1)·n), source j
            // spans [j·m, (j+1)·m).
            let (lo, hi) = (i * n, (i + 1) * n);
            let first = lo / m;
            let last = (hi - 1) / m;
            let mut weights = [0u32; 4];
            let count = (last - first + 1).min(4);
            for (k, wk) in weights.iter_mut().enumerate().take(count) {
                let j = first + k;
                let overlap = hi.min((j + 1) * m) - lo.max(j * m);
                *wk = ((overlap * 256 + n / 2) / n) as u32;
            }
            // Rounding may leave the sum off by one or two: the largest weight absorbs it.
            let sum: u32 = weights.iter().sum();
            if let Some(big) = weights.iter_mut().max_by_key(|w| **w) {
                *big = (*big + 256).saturating_sub(sum);
            }
            Taps {
                first,
                count,
                weights,
            }
        })
        .collect()
}

/// Halves a `w × h` RGBA8 level into `dst` (`half(w, h)`), averaging each channel in the
/// space it is encoded in. Averaging sRGB colours in linear light would be more faithful,
/// but an image does not know which slot samples it (a base colour is sRGB, a normal map is
/// not); straight averages of the stored values are what `glGenerateMipmap` does. Alpha is
/// straight, not premultiplied, likewise.
fn halve(src: &[u8], w: u32, h: u32, dst: &mut [u8]) {
    let (xs, ys) = (axis_taps(w), axis_taps(h));
    let row = w as usize * 4;
    let dst_row = xs.len() * 4;
    let mut acc = vec![0u32; row];
    for (out, ty) in dst.chunks_exact_mut(dst_row).zip(&ys) {
        acc.iter_mut().for_each(|a| *a = 0);
        for k in 0..ty.count {
            let wy = ty.weights[k];
            let Some(line) = src.get((ty.first + k) * row..(ty.first + k + 1) * row) else {
                continue;
            };
            for (a, &s) in acc.iter_mut().zip(line) {
                *a += wy * u32::from(s);
            }
        }
        for (px, tx) in out.chunks_exact_mut(4).zip(&xs) {
            for (c, v) in px.iter_mut().enumerate() {
                let mut sum = 0u32;
                for k in 0..tx.count {
                    sum += tx.weights[k] * acc[(tx.first + k) * 4 + c];
                }
                // Weights sum to 256 × 256: round to nearest.
                *v = ((sum + 32768) >> 16) as u8;
            }
        }
    }
}

/// The full chain from `level0` down to 1 × 1 (its bytes charged by the caller).
fn mip_chain(index: usize, level0: Vec<u8>, w: u32, h: u32) -> Result<Mips, ImageError> {
    let mut levels = vec![MipLevel {
        width: w,
        height: h,
        rgba: level0,
    }];
    let (mut cw, mut ch) = (w, h);
    while (cw, ch) != (1, 1) {
        let (nw, nh) = half(cw, ch);
        let mut next = zeroed(index, rgba_bytes(nw, nh))?;
        if let Some(prev) = levels.last() {
            halve(&prev.rgba, cw, ch, &mut next);
        }
        levels.push(MipLevel {
            width: nw,
            height: nh,
            rgba: next,
        });
        (cw, ch) = (nw, nh);
    }
    Ok(Mips { levels })
}

// ------------------------------------------------------------------------------------------
// Re-encoding
// ------------------------------------------------------------------------------------------

/// An encoder's output, each growth charged before it is allocated (to at most 1.5 × what
/// is written, so [`encode_peak`] bounds it).
struct ChargedOutput<'b> {
    buf: Vec<u8>,
    held: Held<'b>,
    index: usize,
    refused: Option<BudgetError>,
}

impl Write for ChargedOutput<'_> {
    fn write(&mut self, data: &[u8]) -> std::io::Result<usize> {
        let need = self.buf.len() + data.len();
        if need > self.buf.capacity() {
            let cap = self.buf.capacity();
            let grown = need.max(cap + cap / 2).max(64 << 10);
            let index = self.index;
            if let Err(e) = self.held.charge((grown - cap) as u64, || {
                format!("image {index}: its re-encoded bytes")
            }) {
                self.refused = Some(e);
                return Err(std::io::Error::other("over the memory budget"));
            }
            self.buf
                .try_reserve_exact(grown - self.buf.len())
                .map_err(std::io::Error::other)?;
        }
        self.buf.extend_from_slice(data);
        Ok(data.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

/// Encodes level 0 of `mips` as `mime`; the bytes returned stay charged.
fn encode(
    index: usize,
    mime: ImageMime,
    mips: &Mips,
    budget: &Budget,
) -> Result<Arc<[u8]>, ImageError> {
    let level = mips
        .levels
        .first()
        .ok_or_else(|| invalid(index, "no pixels to encode"))?;
    let (w, h) = (level.width, level.height);
    let mut scratch = Held::new(budget);
    scratch.charge(FIXED_SCRATCH + 128 * (u64::from(w) + 16), || {
        format!("image {index}: the encoder of its {w} × {h} copy")
    })?;
    let mut out = ChargedOutput {
        buf: Vec::new(),
        held: Held::new(budget),
        index,
        refused: None,
    };
    let result = guarded(index, format_name(mime), || {
        let problem = match mime {
            ImageMime::Jpeg => {
                let (w16, h16) = (
                    u16::try_from(w).map_err(|_| invalid(index, "too wide for a JPEG"))?,
                    u16::try_from(h).map_err(|_| invalid(index, "too tall for a JPEG"))?,
                );
                jpeg_encoder::Encoder::new(&mut out, REENCODE_JPEG_QUALITY)
                    .encode(&level.rgba, w16, h16, jpeg_encoder::ColorType::Rgba)
                    .err()
                    .map(|e| e.to_string())
            }
            ImageMime::Png | ImageMime::Webp => {
                let mut encoder = png::Encoder::new(&mut out, w, h);
                encoder.set_color(png::ColorType::Rgba);
                encoder.set_depth(png::BitDepth::Eight);
                // zlib level 1: on a grainy 1024² texture about 25% larger than level 6 but
                // some 30 times faster (level 6 took a second on the import's path).
                encoder.set_deflate_compression(png::DeflateCompression::Level(1));
                encoder
                    .write_header()
                    .and_then(|mut writer| {
                        writer.write_image_data(&level.rgba)?;
                        writer.finish()
                    })
                    .err()
                    .map(|e| e.to_string())
            }
        };
        match problem {
            None => Ok(()),
            Some(p) => Err(invalid(
                index,
                format!("cannot re-encode it as a {}: {p}", format_name(mime)),
            )),
        }
    });
    if let Some(refused) = out.refused.take() {
        return Err(refused.into());
    }
    result?;
    let mut kept = Held::new(budget);
    kept.charge(out.buf.len() as u64, || {
        format!("image {index}: its re-encoded bytes")
    })?;
    let bytes: Arc<[u8]> = Arc::from(out.buf.as_slice());
    drop(out);
    drop(scratch);
    kept.keep();
    Ok(bytes)
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use crowdmorph_core::budget::{Budget, BudgetError};
    use crowdmorph_core::rig::{ImageData, ImageMime, Mips};

    use super::{
        ImageError, ImageHeader, axis_taps, decode, decode_cost, decode_pixels, kept_bytes, sniff,
    };

    const LOSSY_WEBP: &[u8] = include_bytes!("../testdata/images/lossy.webp");
    const LOSSY_ALPHA_WEBP: &[u8] = include_bytes!("../testdata/images/lossy_alpha.webp");
    const ANIMATED_WEBP: &[u8] = include_bytes!("../testdata/images/animated.webp");

    fn budget() -> Budget {
        Budget::new(1 << 30, "--max-upload-memory", None)
    }

    /// The pixels testdata/images/gen.py draws (24 × 16), which the WebP fixtures encode.
    fn fixture(x: u32, y: u32) -> [u8; 4] {
        [
            (x * 255 / 23) as u8,
            (y * 255 / 15) as u8,
            (255 - (x * 5 + y * 6)) as u8,
            (255 - y * 8) as u8,
        ]
    }

    /// A smooth pattern with alpha, for any size (JPEG tolerances need smooth content).
    fn smooth(x: u32, y: u32) -> [u8; 4] {
        [
            (x * 7 % 256) as u8,
            (y * 5 % 256) as u8,
            ((x + y) * 3 % 256) as u8,
            (255 - (x * 3 + y) % 200) as u8,
        ]
    }

    fn rgba_of(w: u32, h: u32, f: impl Fn(u32, u32) -> [u8; 4]) -> Vec<u8> {
        (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .flat_map(|(x, y)| f(x, y))
            .collect()
    }

    /// Keeps `keep` of every RGBA pixel's channels (e.g. `[0, 1, 2]` for RGB).
    fn channels(rgba: &[u8], keep: &[usize]) -> Vec<u8> {
        rgba.chunks_exact(4)
            .flat_map(|p| keep.iter().map(move |&c| p[c]))
            .collect()
    }

    fn png_of(w: u32, h: u32, color: png::ColorType, depth: png::BitDepth, data: &[u8]) -> Vec<u8> {
        png_with(w, h, color, depth, data, |_| {})
    }

    fn png_with(
        w: u32,
        h: u32,
        color: png::ColorType,
        depth: png::BitDepth,
        data: &[u8],
        setup: impl FnOnce(&mut png::Encoder<'_, &mut Vec<u8>>),
    ) -> Vec<u8> {
        let mut out = Vec::new();
        let mut encoder = png::Encoder::new(&mut out, w, h);
        encoder.set_color(color);
        encoder.set_depth(depth);
        setup(&mut encoder);
        let mut writer = encoder.write_header().expect("PNG header");
        writer.write_image_data(data).expect("PNG data");
        writer.finish().expect("PNG end");
        out
    }

    fn jpeg_of(
        w: u32,
        h: u32,
        data: &[u8],
        color: jpeg_encoder::ColorType,
        progressive: bool,
    ) -> Vec<u8> {
        let mut out = Vec::new();
        let mut encoder = jpeg_encoder::Encoder::new(&mut out, 95);
        encoder.set_progressive(progressive);
        encoder
            .encode(data, w as u16, h as u16, color)
            .expect("JPEG encoding");
        out
    }

    fn lossless_webp_of(w: u32, h: u32, data: &[u8], color: ::image::ExtendedColorType) -> Vec<u8> {
        let mut out = Vec::new();
        ::image::codecs::webp::WebPEncoder::new_lossless(&mut out)
            .encode(data, w, h, color)
            .expect("WebP encoding");
        out
    }

    fn zlib(data: &[u8]) -> Vec<u8> {
        use std::io::Write;
        let mut z = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::fast());
        z.write_all(data).expect("zlib");
        z.finish().expect("zlib")
    }

    fn chunk(kind: &[u8; 4], data: &[u8]) -> Vec<u8> {
        let mut out = (data.len() as u32).to_be_bytes().to_vec();
        out.extend_from_slice(kind);
        out.extend_from_slice(data);
        let mut crc = crc32fast::Hasher::new();
        crc.update(kind);
        crc.update(data);
        out.extend_from_slice(&crc.finalize().to_be_bytes());
        out
    }

    /// A PNG written by hand: signature, IHDR, one IDAT of `idat` (already zlib), IEND.
    fn raw_png(w: u32, h: u32, depth: u8, color: u8, interlace: u8, idat: &[u8]) -> Vec<u8> {
        let mut ihdr = w.to_be_bytes().to_vec();
        ihdr.extend_from_slice(&h.to_be_bytes());
        ihdr.extend_from_slice(&[depth, color, 0, 0, interlace]);
        let mut out = super::PNG_SIGNATURE.to_vec();
        out.extend(chunk(b"IHDR", &ihdr));
        out.extend(chunk(b"IDAT", idat));
        out.extend(chunk(b"IEND", &[]));
        out
    }

    /// An Adam7-interlaced RGBA8 PNG (the `png` encoder writes none): each pass's rows, each
    /// row with filter byte 0.
    fn interlaced_png(w: u32, h: u32, rgba: &[u8]) -> Vec<u8> {
        const PASSES: [(u32, u32, u32, u32); 7] = [
            (0, 0, 8, 8),
            (4, 0, 8, 8),
            (0, 4, 4, 8),
            (2, 0, 4, 4),
            (0, 2, 2, 4),
            (1, 0, 2, 2),
            (0, 1, 1, 2),
        ];
        let mut raw = Vec::new();
        for (x0, y0, dx, dy) in PASSES {
            if x0 >= w || y0 >= h {
                continue;
            }
            for y in (y0..h).step_by(dy as usize) {
                raw.push(0);
                for x in (x0..w).step_by(dx as usize) {
                    let at = ((y * w + x) * 4) as usize;
                    raw.extend_from_slice(&rgba[at..at + 4]);
                }
            }
        }
        raw_png(w, h, 8, 6, 1, &zlib(&raw))
    }

    fn decoded(
        bytes: &[u8],
        declared: Option<ImageMime>,
        max: u32,
    ) -> (ImageData, Vec<String>, Budget) {
        let budget = budget();
        let (image, notes) =
            decode(3, Arc::from(bytes), declared, max, &budget).expect("a valid image decodes");
        (image, notes, budget)
    }

    fn level0(image: &ImageData) -> &[u8] {
        &image.pixels.as_ref().expect("decoded pixels").levels[0].rgba
    }

    fn refusal(bytes: &[u8]) -> String {
        let budget = budget();
        match decode(7, Arc::from(bytes), None, 4096, &budget) {
            Err(e @ ImageError::Invalid { index: 7, .. }) => {
                assert_eq!(budget.used(), 0, "a refused image holds nothing");
                e.to_string()
            }
            other => panic!("expected an invalid image 7, got {other:?}"),
        }
    }

    fn max_difference(a: &[u8], b: &[u8]) -> u8 {
        assert_eq!(a.len(), b.len());
        a.iter()
            .zip(b)
            .map(|(x, y)| x.abs_diff(*y))
            .max()
            .unwrap_or(0)
    }

    /// Pseudo-random bytes (xorshift), the same on every run.
    fn noise(seed: u64, len: usize) -> Vec<u8> {
        let mut s = seed | 1;
        (0..len)
            .map(|_| {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                (s >> 24) as u8
            })
            .collect()
    }

    #[test]
    fn sniff_reads_each_format_from_its_header() {
        let rgba = rgba_of(24, 16, fixture);
        let png = png_of(24, 16, png::ColorType::Rgba, png::BitDepth::Eight, &rgba);
        let jpeg = jpeg_of(24, 16, &rgba, jpeg_encoder::ColorType::Rgba, false);
        let lossless = lossless_webp_of(24, 16, &rgba, ::image::ExtendedColorType::Rgba8);
        for (bytes, mime) in [
            (&png[..], ImageMime::Png),
            (&jpeg[..], ImageMime::Jpeg),
            (&lossless[..], ImageMime::Webp),
            (LOSSY_WEBP, ImageMime::Webp),
            (LOSSY_ALPHA_WEBP, ImageMime::Webp),
            (ANIMATED_WEBP, ImageMime::Webp),
        ] {
            let header = sniff(bytes).expect("a valid header");
            assert_eq!(
                header,
                ImageHeader {
                    mime,
                    width: 24,
                    height: 16
                }
            );
        }
    }

    #[test]
    fn sniffing_and_decoding_never_read_past_the_slice() {
        let rgba = rgba_of(24, 16, fixture);
        let images = [
            png_of(24, 16, png::ColorType::Rgba, png::BitDepth::Eight, &rgba),
            interlaced_png(24, 16, &rgba),
            jpeg_of(24, 16, &rgba, jpeg_encoder::ColorType::Rgba, false),
            jpeg_of(24, 16, &rgba, jpeg_encoder::ColorType::Rgba, true),
            lossless_webp_of(24, 16, &rgba, ::image::ExtendedColorType::Rgba8),
            LOSSY_WEBP.to_vec(),
            LOSSY_ALPHA_WEBP.to_vec(),
            ANIMATED_WEBP.to_vec(),
        ];
        for image in &images {
            for end in 0..image.len() {
                let prefix = &image[..end];
                let _ = sniff(prefix);
                let budget = budget();
                match decode(0, Arc::from(prefix), None, 8, &budget) {
                    // A PNG cut after its image data (before IEND) is still whole.
                    Ok((image, _)) => assert_eq!(budget.used(), kept_bytes(&image)),
                    Err(ImageError::Invalid { problem, .. }) => {
                        assert!(!problem.contains("panicked"), "{problem}");
                        assert_eq!(budget.used(), 0);
                    }
                    Err(e) => panic!("{e}"),
                }
            }
        }
        // Random tails behind each magic, so the header walks go deep.
        let magics: [&[u8]; 4] = [
            &super::PNG_SIGNATURE,
            &[0xFF, 0xD8],
            b"RIFF\0\0\0\0WEBPVP8X",
            b"RIFF\0\0\0\0WEBPVP8L",
        ];
        for seed in 0..2000u64 {
            let magic = magics[(seed % 4) as usize];
            let mut bytes = magic.to_vec();
            bytes.extend(noise(seed, (seed % 97) as usize));
            let _ = sniff(&bytes);
            let _ = sniff(&noise(seed, (seed % 61) as usize));
        }
    }

    #[test]
    fn png_variants_decode_to_their_source_pixels() {
        let (w, h) = (13, 7);
        let rgba = rgba_of(w, h, smooth);
        let grey: Vec<u8> = rgba.chunks_exact(4).map(|p| p[0]).collect();
        let widen_grey = |alpha: Option<&[u8]>| -> Vec<u8> {
            grey.iter()
                .enumerate()
                .flat_map(|(i, &g)| [g, g, g, alpha.map_or(255, |a| a[i])])
                .collect()
        };
        let alpha: Vec<u8> = rgba.chunks_exact(4).map(|p| p[3]).collect();
        let opaque: Vec<u8> = rgba
            .chunks_exact(4)
            .flat_map(|p| [p[0], p[1], p[2], 255])
            .collect();

        let cases: Vec<(&str, Vec<u8>, Vec<u8>)> = vec![
            (
                "RGBA8",
                png_of(w, h, png::ColorType::Rgba, png::BitDepth::Eight, &rgba),
                rgba.clone(),
            ),
            (
                "RGB8",
                png_of(
                    w,
                    h,
                    png::ColorType::Rgb,
                    png::BitDepth::Eight,
                    &channels(&rgba, &[0, 1, 2]),
                ),
                opaque.clone(),
            ),
            (
                "grey",
                png_of(w, h, png::ColorType::Grayscale, png::BitDepth::Eight, &grey),
                widen_grey(None),
            ),
            (
                "grey + alpha",
                png_of(
                    w,
                    h,
                    png::ColorType::GrayscaleAlpha,
                    png::BitDepth::Eight,
                    &channels(&rgba, &[0, 3]),
                ),
                widen_grey(Some(&alpha)),
            ),
            (
                "16-bit RGBA",
                // Low bytes that are not the high ones: stripping keeps the high byte.
                png_of(
                    w,
                    h,
                    png::ColorType::Rgba,
                    png::BitDepth::Sixteen,
                    &rgba
                        .iter()
                        .flat_map(|&v| [v, v ^ 0x5A])
                        .collect::<Vec<u8>>(),
                ),
                rgba.clone(),
            ),
            ("interlaced", interlaced_png(w, h, &rgba), rgba.clone()),
        ];
        for (what, bytes, expected) in cases {
            let (image, notes, _) = decoded(&bytes, Some(ImageMime::Png), 4096);
            assert_eq!((image.width, image.height), (w, h), "{what}");
            assert!(notes.is_empty(), "{what}: {notes:?}");
            assert_eq!(level0(&image), &expected[..], "{what}");
            assert_eq!(
                &image.bytes[..],
                &bytes[..],
                "{what}: the original bytes are kept"
            );
        }
        // Not downscaled, the image keeps the caller's bytes themselves, not a copy.
        let bytes: Arc<[u8]> = Arc::from(interlaced_png(w, h, &rgba));
        let (image, _) = decode(0, bytes.clone(), None, 4096, &budget()).expect("decodes");
        assert!(Arc::ptr_eq(&image.bytes, &bytes));

        // Palette with tRNS alpha (entries past tRNS are opaque), at 4 bits per index.
        let palette: Vec<u8> = (0..16u8)
            .flat_map(|i| [i * 16, 255 - i * 16, i * 8])
            .collect();
        let trns: Vec<u8> = (0..10u8).map(|i| i * 25).collect();
        let indices: Vec<u8> = (0..w * h).map(|i| (i * 7 % 16) as u8).collect();
        let packed: Vec<u8> = indices
            .chunks(w as usize)
            .flat_map(|row| {
                row.chunks(2)
                    .map(|p| (p[0] << 4) | p.get(1).copied().unwrap_or(0))
            })
            .collect();
        let bytes = png_with(
            w,
            h,
            png::ColorType::Indexed,
            png::BitDepth::Four,
            &packed,
            |e| {
                e.set_palette(palette.clone());
                e.set_trns(trns.clone());
            },
        );
        let expected: Vec<u8> = indices
            .iter()
            .flat_map(|&i| {
                let i = usize::from(i);
                let a = trns.get(i).copied().unwrap_or(255);
                [palette[3 * i], palette[3 * i + 1], palette[3 * i + 2], a]
            })
            .collect();
        let (image, _, _) = decoded(&bytes, None, 4096);
        assert_eq!(level0(&image), &expected[..], "palette + tRNS");
    }

    #[test]
    fn jpeg_variants_decode_within_tolerance() {
        let (w, h) = (40, 24);
        let rgba = rgba_of(w, h, smooth);
        let opaque: Vec<u8> = rgba
            .chunks_exact(4)
            .flat_map(|p| [p[0], p[1], p[2], 255])
            .collect();
        let grey: Vec<u8> = rgba.chunks_exact(4).map(|p| p[1]).collect();
        let grey_rgba: Vec<u8> = grey.iter().flat_map(|&g| [g, g, g, 255]).collect();
        // CMYK made from the colour: K the darkest part, C M Y the rest; back to RGB as
        // (255 - C)(255 - K) / 255, as decoders read Adobe CMYK.
        let cmyk: Vec<u8> = rgba
            .chunks_exact(4)
            .flat_map(|p| {
                let k = 255 - p[0].max(p[1]).max(p[2]);
                let ink = |v: u8| {
                    let rest = 255 - u32::from(k);
                    (u32::from(v) * 255)
                        .checked_div(rest)
                        .map_or(0, |q| (255 - q) as u8)
                };
                [ink(p[0]), ink(p[1]), ink(p[2]), k]
            })
            .collect();
        let cmyk_rgba: Vec<u8> = cmyk
            .chunks_exact(4)
            .flat_map(|p| {
                let rgb = |c: u8| ((255 - u32::from(c)) * (255 - u32::from(p[3])) / 255) as u8;
                [rgb(p[0]), rgb(p[1]), rgb(p[2]), 255]
            })
            .collect();
        assert!(
            max_difference(&cmyk_rgba, &opaque) <= 3,
            "the CMYK oracle round-trips"
        );

        for (what, bytes, expected, tolerance) in [
            (
                "baseline",
                jpeg_of(w, h, &rgba, jpeg_encoder::ColorType::Rgba, false),
                &opaque,
                12,
            ),
            (
                "progressive",
                jpeg_of(w, h, &rgba, jpeg_encoder::ColorType::Rgba, true),
                &opaque,
                12,
            ),
            (
                "grey",
                jpeg_of(w, h, &grey, jpeg_encoder::ColorType::Luma, false),
                &grey_rgba,
                4,
            ),
            (
                "CMYK",
                jpeg_of(w, h, &cmyk, jpeg_encoder::ColorType::Cmyk, false),
                &cmyk_rgba,
                16,
            ),
        ] {
            let (image, notes, _) = decoded(&bytes, Some(ImageMime::Jpeg), 4096);
            assert!(notes.is_empty(), "{what}: {notes:?}");
            assert_eq!(
                (image.mime, image.width, image.height),
                (ImageMime::Jpeg, w, h)
            );
            let d = max_difference(level0(&image), expected);
            assert!(d <= tolerance, "{what}: off by {d}");
        }
    }

    #[test]
    fn webp_variants_decode_to_their_source_pixels() {
        let (w, h) = (24, 16);
        let rgba = rgba_of(w, h, fixture);
        let opaque: Vec<u8> = rgba
            .chunks_exact(4)
            .flat_map(|p| [p[0], p[1], p[2], 255])
            .collect();

        let lossless = lossless_webp_of(w, h, &rgba, ::image::ExtendedColorType::Rgba8);
        let (image, notes, _) = decoded(&lossless, Some(ImageMime::Webp), 4096);
        assert!(notes.is_empty(), "{notes:?}");
        assert_eq!(level0(&image), &rgba[..], "lossless RGBA");
        let rgb = channels(&rgba, &[0, 1, 2]);
        let lossless = lossless_webp_of(w, h, &rgb, ::image::ExtendedColorType::Rgb8);
        let (image, _, _) = decoded(&lossless, None, 4096);
        assert_eq!(level0(&image), &opaque[..], "lossless RGB");

        let (image, _, _) = decoded(LOSSY_WEBP, None, 4096);
        let d = max_difference(level0(&image), &opaque);
        assert!(d <= 16, "lossy: off by {d}");

        // cwebp -alpha_q 100 keeps alpha lossless.
        let (image, _, _) = decoded(LOSSY_ALPHA_WEBP, None, 4096);
        let got = level0(&image);
        assert_eq!(
            channels(got, &[3]),
            channels(&rgba, &[3]),
            "lossy + alpha: alpha"
        );
        let d = max_difference(&channels(got, &[0, 1, 2]), &channels(&rgba, &[0, 1, 2]));
        assert!(d <= 16, "lossy + alpha: off by {d}");

        // Two lossless frames: the pattern, then its inverse; the first is drawn.
        let (image, notes, _) = decoded(ANIMATED_WEBP, Some(ImageMime::Webp), 4096);
        assert_eq!(
            notes,
            ["image 3 is an animated WebP: its first frame is drawn"]
        );
        assert_eq!(level0(&image), &rgba[..], "animated: first frame");
    }

    #[test]
    fn an_animated_png_draws_its_default_image_with_a_note() {
        let first = rgba_of(8, 4, smooth);
        let second = rgba_of(8, 4, |_, _| [1, 2, 3, 4]);
        let mut out = Vec::new();
        let mut encoder = png::Encoder::new(&mut out, 8, 4);
        encoder.set_color(png::ColorType::Rgba);
        encoder.set_animated(2, 0).expect("APNG");
        let mut writer = encoder.write_header().expect("PNG header");
        writer.write_image_data(&first).expect("frame 1");
        writer.write_image_data(&second).expect("frame 2");
        writer.finish().expect("PNG end");
        let (image, notes, _) = decoded(&out, None, 4096);
        assert_eq!(
            notes,
            ["image 3 is an animated PNG: its default image is drawn"]
        );
        assert_eq!(level0(&image), &first[..]);
    }

    #[test]
    fn a_mismatched_declared_type_is_decoded_by_its_magic_with_a_note() {
        let rgba = rgba_of(16, 8, smooth);
        let jpeg = jpeg_of(16, 8, &rgba, jpeg_encoder::ColorType::Rgba, false);
        let (image, notes, _) = decoded(&jpeg, Some(ImageMime::Png), 4096);
        assert_eq!(image.mime, ImageMime::Jpeg);
        assert_eq!(notes, ["image 3 is declared image/png but is a JPEG"]);
        let png = png_of(16, 8, png::ColorType::Rgba, png::BitDepth::Eight, &rgba);
        let (image, notes, _) = decoded(&png, Some(ImageMime::Webp), 4096);
        assert_eq!(image.mime, ImageMime::Png);
        assert_eq!(notes, ["image 3 is declared image/webp but is a PNG"]);
    }

    #[test]
    fn hostile_images_are_refused_naming_their_index() {
        let rgba = rgba_of(32, 16, smooth);
        let png = png_of(32, 16, png::ColorType::Rgba, png::BitDepth::Eight, &rgba);
        let jpeg = jpeg_of(32, 16, &rgba, jpeg_encoder::ColorType::Rgba, false);
        let webp = lossless_webp_of(32, 16, &rgba, ::image::ExtendedColorType::Rgba8);

        assert_eq!(refusal(b""), "image 7: the image is empty");
        assert_eq!(
            refusal(b"GIF89a\x01\0\x01\0"),
            "image 7: not a PNG, JPEG or WebP image (it starts with 47 49 46 38 39 61 01 00)"
        );
        assert_eq!(
            refusal(&raw_png(0, 0, 8, 6, 0, &zlib(&[]))),
            "image 7: the PNG declares 0 × 0 pixels"
        );
        let mut zero_high = jpeg.clone();
        let sof = zero_high
            .windows(2)
            .position(|m| m == [0xFF, 0xC0])
            .expect("a baseline frame header");
        zero_high[sof + 5..sof + 7].copy_from_slice(&[0, 0]);
        assert_eq!(
            refusal(&zero_high),
            "image 7: the JPEG declares 32 × 0 pixels"
        );

        // An extended WebP whose canvas is not the size of the image it holds.
        let mut canvas = LOSSY_ALPHA_WEBP.to_vec();
        canvas[24..27].copy_from_slice(&9999u32.to_le_bytes()[..3]);
        assert_eq!(
            refusal(&canvas),
            "image 7: the WebP's canvas is 10000 × 16 but its image is 24 × 16"
        );

        // Cut short: a PNG inside its image data, a JPEG half way, a WebP before its end.
        let idat = png.windows(4).position(|c| c == b"IDAT").expect("an IDAT");
        let message = refusal(&png[..idat + 20]);
        assert!(
            message.starts_with("image 7: the PNG cannot be decoded"),
            "{message}"
        );
        let message = refusal(&jpeg[..jpeg.len() / 2]);
        assert!(message.contains("JPEG is cut short"), "{message}");
        let message = refusal(&webp[..webp.len() - 10]);
        assert!(
            message.starts_with("image 7: the WebP cannot be decoded"),
            "{message}"
        );

        // Corrupt: a flipped bit inside the PNG's compressed data (its CRC no longer holds).
        let mut corrupt = png.clone();
        corrupt[idat + 10] ^= 0x10;
        let message = refusal(&corrupt);
        assert!(
            message.starts_with("image 7: the PNG cannot be decoded"),
            "{message}"
        );
    }

    #[test]
    fn a_tiny_png_declaring_50000_squared_is_refused_before_allocating() {
        // 50,000 × 50,000 RGBA8 (10 GB decoded) in about 100 bytes: one compressed zero row.
        let bomb = raw_png(50_000, 50_000, 8, 6, 0, &zlib(&[0; 64]));
        assert!(bomb.len() < 128, "{} bytes", bomb.len());
        let header = sniff(&bomb).expect("its header reads");
        let cost = decode_cost(&header, 4096);
        assert!(cost > 10_000_000_000, "{cost}");

        let budget = budget();
        match decode(5, Arc::from(&bomb[..]), Some(ImageMime::Png), 4096, &budget) {
            Err(ImageError::Budget(BudgetError::TooLarge { what, needed, .. })) => {
                assert!(what.starts_with("image 5 (50000 × 50000 PNG)"), "{what}");
                assert!(needed >= 10_000_000_000, "{needed}");
            }
            other => panic!("expected the budget's refusal, got {other:?}"),
        }
        assert!(budget.peak() < 1 << 20, "peak {}", budget.peak());
        assert_eq!(budget.used(), 0);
        // What the importer reserves up front is refused the same way.
        assert!(budget.reserve(cost, || "image 5".into()).is_err());
    }

    #[test]
    fn images_above_the_maximum_are_halved_until_they_fit_and_reencoded() {
        let rgba = rgba_of(45, 27, smooth);
        let png = png_of(45, 27, png::ColorType::Rgba, png::BitDepth::Eight, &rgba);
        let (image, notes, budget) = decoded(&png, None, 16);
        // 45 × 27 → 22 × 13 → 11 × 6.
        assert_eq!((image.width, image.height), (11, 6));
        assert_eq!(image.downscaled_from, Some([45, 27]));
        assert_eq!(image.mime, ImageMime::Png);
        assert_eq!(notes, ["image 3 45 × 27 → 11 × 6 (--max-texture-size)"]);
        assert_eq!(budget.used(), kept_bytes(&image));
        // The stored bytes are the downscaled pixels, losslessly.
        let again = decode_pixels(3, &image, &super::tests::budget()).expect("re-decodes");
        assert_eq!(again.levels, image.pixels.as_ref().expect("pixels").levels);

        // A JPEG stays a JPEG; a WebP becomes a PNG.
        let jpeg = jpeg_of(
            64,
            48,
            &rgba_of(64, 48, smooth),
            jpeg_encoder::ColorType::Rgba,
            false,
        );
        let (image, notes, _) = decoded(&jpeg, None, 32);
        assert_eq!(
            (image.mime, image.width, image.height),
            (ImageMime::Jpeg, 32, 24)
        );
        assert_eq!(notes, ["image 3 64 × 48 → 32 × 24 (--max-texture-size)"]);
        assert_eq!(sniff(&image.bytes).expect("a JPEG").width, 32);
        let webp = lossless_webp_of(
            24,
            16,
            &rgba_of(24, 16, fixture),
            ::image::ExtendedColorType::Rgba8,
        );
        let (image, _, _) = decoded(&webp, None, 8);
        assert_eq!(
            (image.mime, image.width, image.height),
            (ImageMime::Png, 6, 4)
        );
    }

    #[test]
    fn mips_are_box_filtered_down_to_one_pixel() {
        // 2 × 2 → the rounded average.
        let png = png_of(
            2,
            2,
            png::ColorType::Rgba,
            png::BitDepth::Eight,
            &[0, 10, 255, 255, 1, 20, 255, 0, 2, 30, 0, 255, 4, 41, 0, 0],
        );
        let (image, _, _) = decoded(&png, None, 4096);
        let mips = image.pixels.as_ref().expect("pixels");
        assert_eq!(mips.levels[1].rgba, [2, 25, 128, 128]);

        // An odd size spreads its middle pixel: 3 × 1 of 0, 90, 180 → 90.
        let png = png_of(
            3,
            1,
            png::ColorType::Grayscale,
            png::BitDepth::Eight,
            &[0, 90, 180],
        );
        let (image, _, _) = decoded(&png, None, 4096);
        assert_eq!(
            image.pixels.as_ref().expect("pixels").levels[1].rgba,
            [90, 90, 90, 255]
        );
        for n in 1..40 {
            let taps = axis_taps(n);
            assert_eq!(taps.len(), (n as usize / 2).max(1));
            for t in &taps {
                assert_eq!(t.weights.iter().sum::<u32>(), 256, "{n}: {t:?}");
            }
        }

        // A constant image stays constant at every level, whatever the sizes; the chain goes
        // down to 1 × 1 by halving (rounded down) and holds chain_bytes.
        let rgba = rgba_of(37, 11, |_, _| [200, 100, 50, 25]);
        let png = png_of(37, 11, png::ColorType::Rgba, png::BitDepth::Eight, &rgba);
        let (image, _, _) = decoded(&png, None, 4096);
        let mips = image.pixels.as_ref().expect("pixels");
        let sizes: Vec<(u32, u32)> = mips.levels.iter().map(|l| (l.width, l.height)).collect();
        assert_eq!(sizes, [(37, 11), (18, 5), (9, 2), (4, 1), (2, 1), (1, 1)]);
        for level in &mips.levels {
            assert!(level.rgba.chunks_exact(4).all(|p| p == [200, 100, 50, 25]));
        }
        assert_eq!(mips.bytes() as u64, Mips::chain_bytes(37, 11));
        assert_eq!(super::chain_bytes(37, 11), Mips::chain_bytes(37, 11));
    }

    #[test]
    fn decode_never_charges_more_than_decode_cost_and_keeps_only_the_image() {
        let rgba = rgba_of(64, 40, smooth);
        let images: Vec<(&str, Vec<u8>)> = vec![
            (
                "PNG",
                png_of(64, 40, png::ColorType::Rgba, png::BitDepth::Eight, &rgba),
            ),
            ("interlaced PNG", interlaced_png(64, 40, &rgba)),
            (
                "JPEG",
                jpeg_of(64, 40, &rgba, jpeg_encoder::ColorType::Rgba, false),
            ),
            (
                "progressive JPEG",
                jpeg_of(64, 40, &rgba, jpeg_encoder::ColorType::Rgba, true),
            ),
            (
                "WebP",
                lossless_webp_of(64, 40, &rgba, ::image::ExtendedColorType::Rgba8),
            ),
            ("lossy WebP", LOSSY_WEBP.to_vec()),
            ("animated WebP", ANIMATED_WEBP.to_vec()),
        ];
        for (what, bytes) in &images {
            let header = sniff(bytes).expect("a header");
            for max in [4096, 32, 8, 1] {
                let (image, _, budget) = decoded(bytes, None, max);
                let copies = if header.mime == ImageMime::Webp {
                    2 * bytes.len() as u64
                } else {
                    0
                };
                let cost = decode_cost(&header, max);
                assert!(
                    budget.peak() <= cost + copies,
                    "{what} at {max}: peak {} > cost {cost}",
                    budget.peak()
                );
                assert_eq!(budget.used(), kept_bytes(&image), "{what} at {max}");
                drop(image);
            }
        }
    }

    #[test]
    fn a_refused_charge_releases_everything() {
        let rgba = rgba_of(64, 40, smooth);
        for bytes in [
            png_of(64, 40, png::ColorType::Rgba, png::BitDepth::Eight, &rgba),
            jpeg_of(64, 40, &rgba, jpeg_encoder::ColorType::Rgba, false),
        ] {
            let (image, _, full) = decoded(&bytes, None, 8);
            for limit in (0..full.peak()).step_by(9973) {
                let budget = Budget::new(limit, "--max-upload-memory", None);
                match decode(1, Arc::from(&bytes[..]), None, 8, &budget) {
                    Err(ImageError::Budget(BudgetError::TooLarge { .. })) => {}
                    other => panic!("limit {limit}: expected the budget's refusal, got {other:?}"),
                }
                assert_eq!(budget.used(), 0, "limit {limit}");
            }
            // Re-encoding comes after the larger decoding charge: refused on its own, by its
            // scratch or by its output's growth.
            let mips = image.pixels.as_ref().expect("pixels");
            let scratch = super::FIXED_SCRATCH + 128 * (8 + 16);
            for limit in [0, scratch - 1, scratch + 1000] {
                let budget = Budget::new(limit, "--max-upload-memory", None);
                match super::encode(1, image.mime, mips, &budget) {
                    Err(ImageError::Budget(BudgetError::TooLarge { what, .. })) => {
                        assert!(what.starts_with("image 1: "), "{what}")
                    }
                    other => panic!("limit {limit}: expected the budget's refusal, got {other:?}"),
                }
                assert_eq!(budget.used(), 0, "limit {limit}");
            }
        }
    }

    #[test]
    fn decode_pixels_rebuilds_the_chain_and_checks_the_record() {
        let rgba = rgba_of(20, 12, smooth);
        let png = png_of(20, 12, png::ColorType::Rgba, png::BitDepth::Eight, &rgba);
        let (image, _, _) = decoded(&png, None, 4096);
        let stored = ImageData {
            pixels: None,
            ..image.clone()
        };
        let budget = budget();
        let mips = decode_pixels(2, &stored, &budget).expect("rebuilds");
        assert_eq!(Some(&mips), image.pixels.as_ref());
        assert_eq!(budget.used(), Mips::chain_bytes(20, 12));
        assert!(budget.peak() >= Mips::chain_bytes(20, 12));

        let wrong = ImageData {
            width: 21,
            ..stored.clone()
        };
        let budget = super::tests::budget();
        match decode_pixels(2, &wrong, &budget) {
            Err(ImageError::Invalid { index: 2, problem }) => assert_eq!(
                problem,
                "its bytes are a 20 × 12 PNG, but it is recorded as a 21 × 12 PNG"
            ),
            other => panic!("expected a refusal, got {other:?}"),
        }
        assert_eq!(budget.used(), 0);
    }

    /// 2048² images of each format decode within the cost charged from their header (the
    /// peak of the budget never passes `decode_cost`), at the default and a smaller
    /// `--max-texture-size`. It prints decode times and charges too, for commit messages and
    /// docs/perf (the fastest of 5 runs in a release build, of 1 otherwise; printed, never
    /// asserted): `cargo test --release -p crowdmorph-import --lib
    /// image::tests::large_images -- --nocapture`.
    #[test]
    fn large_images_peak_within_the_cost_charged_from_their_header() {
        let (w, h) = (2048, 2048);
        // Smooth content with a little grain, as photographed textures have.
        let grain = noise(7, (w * h) as usize);
        let rgba = rgba_of(w, h, |x, y| {
            let g = grain[(y * w + x) as usize] / 32;
            let s = smooth(x, y);
            [s[0].wrapping_add(g), s[1].wrapping_add(g), s[2], 255]
        });
        let images = [
            ("JPEG q92", {
                let mut out = Vec::new();
                jpeg_encoder::Encoder::new(&mut out, 92)
                    .encode(&rgba, w as u16, h as u16, jpeg_encoder::ColorType::Rgba)
                    .expect("JPEG");
                out
            }),
            ("progressive JPEG q92", {
                let mut out = Vec::new();
                let mut encoder = jpeg_encoder::Encoder::new(&mut out, 92);
                encoder.set_progressive(true);
                encoder
                    .encode(&rgba, w as u16, h as u16, jpeg_encoder::ColorType::Rgba)
                    .expect("JPEG");
                out
            }),
            (
                "PNG RGBA",
                png_of(w, h, png::ColorType::Rgba, png::BitDepth::Eight, &rgba),
            ),
            (
                "WebP lossless",
                lossless_webp_of(w, h, &rgba, ::image::ExtendedColorType::Rgba8),
            ),
        ];
        let runs = if cfg!(debug_assertions) { 1 } else { 5 };
        let fastest = |f: &mut dyn FnMut()| {
            (0..runs)
                .map(|_| {
                    let start = std::time::Instant::now();
                    f();
                    start.elapsed().as_secs_f64() * 1e3
                })
                .fold(f64::INFINITY, f64::min)
        };
        for (what, bytes) in &images {
            let (header, layout) = super::sniff_layout(bytes).expect("a header");
            let pixels_ms = fastest(&mut || {
                let _ = super::decode_rgba(0, bytes, &header, &layout).expect("decodes");
            });
            for max in [4096, 1024] {
                let mut peak = 0;
                let mut kept = 0;
                let ms = fastest(&mut || {
                    let budget = budget();
                    let (image, _) =
                        decode(0, Arc::from(&bytes[..]), None, max, &budget).expect("decodes");
                    (peak, kept) = (budget.peak(), kept_bytes(&image));
                });
                let cost = decode_cost(&header, max);
                println!(
                    "{what} {w}² ({} KB) max {max}: pixels {pixels_ms:.1} ms, decode {ms:.1} ms, \
                     peak {:.1} MB (decode_cost {:.1} MB), kept {:.1} MB",
                    bytes.len() / 1024,
                    peak as f64 / 1e6,
                    cost as f64 / 1e6,
                    kept as f64 / 1e6,
                );
                assert!(
                    peak <= cost,
                    "{what} max {max}: peak {peak} over the charge {cost}"
                );
                assert!(
                    kept > 0 && kept <= peak,
                    "{what} max {max}: kept {kept}, peak {peak}"
                );
            }
        }
    }
}
