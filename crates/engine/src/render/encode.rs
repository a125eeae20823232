//! Encoding of rendered frames: PNG, JPEG or raw RGBA8, and the checks on a requested image.
//!
//! Input is what the renderer reads back: RGBA8, rows top-down, `width × 4` bytes per row. PNG
//! goes through the `png` crate (already used for plots) at its `Fast` level (a DEFLATE tuned
//! for images: encoding time counts in every response); JPEG through `jpeg-encoder` (pure Rust,
//! no dependencies; alpha is dropped); raw RGBA is the buffer itself, not copied. Encoding is
//! CPU work of milliseconds, so the server calls it on the blocking pool.

use crowdmorph_proto::{ImageFormat, ImageOptions, MAX_IMAGE_SIDE};

/// Why an image could not be encoded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum EncodeError {
    /// The pixel buffer does not match the stated size.
    #[error("{got} bytes of pixels for a {width} × {height} RGBA image (want {want})")]
    Size {
        /// Width in pixels.
        width: u32,
        /// Height in pixels.
        height: u32,
        /// Bytes given.
        got: usize,
        /// Bytes a `width × height` RGBA8 image has.
        want: usize,
    },
    /// The PNG encoder failed.
    #[error("PNG encoding: {0}")]
    Png(String),
    /// The JPEG encoder failed.
    #[error("JPEG encoding: {0}")]
    Jpeg(String),
}

/// Why a requested image is not acceptable.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ImageError {
    /// A malformed option (a side of 0, a quality outside 1–100): the client's mistake.
    #[error("{0}")]
    Invalid(String),
    /// Larger than this server draws.
    #[error("{0}")]
    TooLarge(String),
}

/// Checks a requested image: sides 1..=`max_side` (at most [`MAX_IMAGE_SIDE`]), quality
/// 1..=100.
pub fn check_image(image: &ImageOptions, max_side: u32) -> Result<(), ImageError> {
    let cap = max_side.min(MAX_IMAGE_SIDE);
    for (name, v) in [("width", image.width), ("height", image.height)] {
        if v == 0 {
            return Err(ImageError::Invalid(format!(
                "image {name} is 0; it must be 1 to {cap} pixels"
            )));
        }
        if v > cap {
            return Err(ImageError::TooLarge(format!(
                "image {name} {v} is more than the largest side this server renders, {cap} pixels"
            )));
        }
    }
    if !(1..=100).contains(&image.quality) {
        return Err(ImageError::Invalid(format!(
            "image quality {} must be 1 to 100",
            image.quality
        )));
    }
    Ok(())
}

/// Encodes RGBA8 pixels (rows top-down) as `format`; `quality` is JPEG's (1–100).
pub fn encode(
    rgba: Vec<u8>,
    width: u32,
    height: u32,
    format: ImageFormat,
    quality: u8,
) -> Result<Vec<u8>, EncodeError> {
    let want = width as usize * height as usize * 4;
    if rgba.len() != want {
        return Err(EncodeError::Size {
            width,
            height,
            got: rgba.len(),
            want,
        });
    }
    match format {
        ImageFormat::Png => png_bytes(&rgba, width, height),
        ImageFormat::Jpeg => jpeg_bytes(&rgba, width, height, quality),
        ImageFormat::Rgba => Ok(rgba),
    }
}

fn png_bytes(rgba: &[u8], width: u32, height: u32) -> Result<Vec<u8>, EncodeError> {
    let err = |e: png::EncodingError| EncodeError::Png(e.to_string());
    // Flat-shaded renders compress well; a tenth of the raw size is typical.
    let mut out = Vec::with_capacity(rgba.len() / 8 + 1024);
    let mut enc = png::Encoder::new(&mut out, width, height);
    enc.set_color(png::ColorType::Rgba);
    enc.set_depth(png::BitDepth::Eight);
    enc.set_compression(png::Compression::Fast);
    let mut writer = enc.write_header().map_err(err)?;
    writer.write_image_data(rgba).map_err(err)?;
    writer.finish().map_err(err)?;
    Ok(out)
}

fn jpeg_bytes(rgba: &[u8], width: u32, height: u32, quality: u8) -> Result<Vec<u8>, EncodeError> {
    let side =
        |v: u32| u16::try_from(v).map_err(|_| EncodeError::Jpeg(format!("a side of {v} pixels")));
    let mut out = Vec::with_capacity(rgba.len() / 10 + 1024);
    jpeg_encoder::Encoder::new(&mut out, quality.clamp(1, 100))
        .encode(
            rgba,
            side(width)?,
            side(height)?,
            jpeg_encoder::ColorType::Rgba,
        )
        .map_err(|e| EncodeError::Jpeg(e.to_string()))?;
    Ok(out)
}

/// The frame size a JPEG's start-of-frame marker states (`None` when the markers before it are
/// not well formed): what a client would read from the file, used to check encoded frames.
pub fn jpeg_size(bytes: &[u8]) -> Option<(u32, u32)> {
    let mut i = 2;
    while i + 9 < bytes.len() {
        if bytes[i] != 0xFF {
            return None;
        }
        let marker = bytes[i + 1];
        let len = u16::from_be_bytes([bytes[i + 2], bytes[i + 3]]) as usize;
        // SOF0..SOF15 except DHT (C4), JPG (C8) and DAC (CC).
        if (0xC0..=0xCF).contains(&marker) && ![0xC4, 0xC8, 0xCC].contains(&marker) {
            let h = u16::from_be_bytes([bytes[i + 5], bytes[i + 6]]);
            let w = u16::from_be_bytes([bytes[i + 7], bytes[i + 8]]);
            return Some((u32::from(w), u32::from(h)));
        }
        i += 2 + len;
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A test card: a gradient, a red square and a white bar, so that rows and columns are
    /// told apart (a transposed or flipped image decodes differently).
    fn card(w: u32, h: u32) -> Vec<u8> {
        let mut px = Vec::with_capacity((w * h * 4) as usize);
        for y in 0..h {
            for x in 0..w {
                let rgb = if x < w / 4 && y < h / 4 {
                    [220, 30, 30]
                } else if y > h * 3 / 4 {
                    [250, 250, 250]
                } else {
                    [(x * 255 / w) as u8, (y * 255 / h) as u8, 90]
                };
                px.extend_from_slice(&[rgb[0], rgb[1], rgb[2], 255]);
            }
        }
        px
    }

    #[test]
    fn png_round_trips_exactly() {
        let (w, h) = (37, 21);
        let px = card(w, h);
        let bytes = encode(px.clone(), w, h, ImageFormat::Png, 90).expect("encodes");
        let decoder = png::Decoder::new(std::io::Cursor::new(bytes));
        let mut reader = decoder.read_info().expect("encodes");
        let mut buf = vec![0; reader.output_buffer_size().expect("encodes")];
        let info = reader.next_frame(&mut buf).expect("encodes");
        assert_eq!((info.width, info.height), (w, h));
        assert_eq!(info.color_type, png::ColorType::Rgba);
        assert_eq!(&buf[..info.buffer_size()], &px[..]);
    }

    #[test]
    fn jpeg_is_a_whole_file_of_the_right_size_and_quality_matters() {
        let (w, h) = (64, 48);
        let px = card(w, h);
        let hi = encode(px.clone(), w, h, ImageFormat::Jpeg, 95).expect("encodes");
        let lo = encode(px, w, h, ImageFormat::Jpeg, 10).expect("encodes");
        for j in [&hi, &lo] {
            assert_eq!(&j[..2], &[0xFF, 0xD8], "SOI");
            assert_eq!(&j[j.len() - 2..], &[0xFF, 0xD9], "EOI");
            assert_eq!(jpeg_size(j), Some((w, h)));
        }
        assert!(
            lo.len() < hi.len(),
            "quality 10: {} bytes, 95: {}",
            lo.len(),
            hi.len()
        );
    }

    #[test]
    fn rgba_is_the_pixels_themselves() {
        let px = card(5, 3);
        assert_eq!(
            encode(px.clone(), 5, 3, ImageFormat::Rgba, 90).expect("encodes"),
            px
        );
    }

    #[test]
    fn a_buffer_of_the_wrong_size_is_refused() {
        let e = encode(vec![0; 10], 2, 2, ImageFormat::Png, 90).expect_err("refused");
        assert_eq!(
            e,
            EncodeError::Size {
                width: 2,
                height: 2,
                got: 10,
                want: 16
            }
        );
    }

    #[test]
    fn image_options_are_checked_naming_the_field() {
        let ok = ImageOptions::default();
        assert_eq!(check_image(&ok, 4096), Ok(()));
        let with = |f: fn(&mut ImageOptions)| {
            let mut o = ImageOptions::default();
            f(&mut o);
            o
        };
        let e = check_image(&with(|o| o.width = 0), 4096).expect_err("refused");
        assert!(
            matches!(&e, ImageError::Invalid(m) if m.contains("width is 0")),
            "{e}"
        );
        let e = check_image(&with(|o| o.height = 4097), 4096).expect_err("refused");
        assert!(
            matches!(&e, ImageError::TooLarge(m) if m.contains("height 4097")),
            "{e}"
        );
        // The adapter's own limit is the cap when it is lower.
        let e = check_image(&with(|o| o.width = 3000), 2048).expect_err("refused");
        assert!(
            matches!(&e, ImageError::TooLarge(m) if m.contains("2048")),
            "{e}"
        );
        assert_eq!(check_image(&with(|o| o.width = 4096), 16384), Ok(()));
        let e = check_image(&with(|o| o.quality = 0), 4096).expect_err("refused");
        assert!(
            matches!(&e, ImageError::Invalid(m) if m.contains("quality 0")),
            "{e}"
        );
        let e = check_image(&with(|o| o.quality = 101), 4096).expect_err("refused");
        assert!(
            matches!(&e, ImageError::Invalid(m) if m.contains("quality 101")),
            "{e}"
        );
    }
}
