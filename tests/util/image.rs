//! RGBA8 images for rendered-frame tests: PNG read and write, a tolerant comparison in the
//! manner of wgpu's own screenshot tests, and golden files.
//!
//! A comparison counts a pixel as different when any channel differs by more than a per-pixel
//! threshold, and passes when at most a set fraction of the pixels differ: rasterizers may
//! disagree in the last bit of shading or on which side of an edge a sample falls (a driver or
//! LLVM update moves a few MSAA edge pixels), while a real regression — wrong lighting, a
//! missing instance, a flipped camera — changes many pixels by a lot.
//!
//! Golden files are generated on lavapipe by an explicit step:
//!
//!     CROWDMORPH_BLESS=1 cargo test --locked render
//!
//! rewrites every golden image a test checks (review the new PNGs before committing them);
//! without it a test compares against the committed file, and on a mismatch writes what it
//! rendered and a difference image under the target folder (`golden-failures/`) and names them.

use std::path::{Path, PathBuf};

/// An RGBA8 image, rows top-down, `width * 4` bytes each.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    pub rgba: Vec<u8>,
}

impl Image {
    /// Wraps tightly packed RGBA8 rows; panics if the length does not match the size.
    pub fn new(width: u32, height: u32, rgba: Vec<u8>) -> Image {
        assert_eq!(
            rgba.len(),
            width as usize * height as usize * 4,
            "{width}×{height} RGBA8 needs width × height × 4 bytes"
        );
        Image {
            width,
            height,
            rgba,
        }
    }

    /// The pixel at (`x`, `y`), (0, 0) top left.
    pub fn pixel(&self, x: u32, y: u32) -> [u8; 4] {
        let i = (y as usize * self.width as usize + x as usize) * 4;
        [
            self.rgba[i],
            self.rgba[i + 1],
            self.rgba[i + 2],
            self.rgba[i + 3],
        ]
    }

    /// Decodes a PNG of any colour type and bit depth into RGBA8 (grey and RGB are expanded,
    /// 16-bit channels keep their high byte).
    pub fn decode_png(bytes: &[u8]) -> Result<Image, String> {
        let mut decoder = png::Decoder::new(std::io::Cursor::new(bytes));
        decoder.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
        let mut reader = decoder.read_info().map_err(|e| e.to_string())?;
        let size = reader
            .output_buffer_size()
            .ok_or("PNG too large to decode")?;
        let mut buf = vec![0u8; size];
        let info = reader.next_frame(&mut buf).map_err(|e| e.to_string())?;
        buf.truncate(info.buffer_size());
        let pixels = info.width as usize * info.height as usize;
        let rgba = match info.color_type {
            png::ColorType::Rgba => buf,
            png::ColorType::Rgb => buf
                .chunks_exact(3)
                .flat_map(|p| [p[0], p[1], p[2], 255])
                .collect(),
            png::ColorType::GrayscaleAlpha => buf
                .chunks_exact(2)
                .flat_map(|p| [p[0], p[0], p[0], p[1]])
                .collect(),
            png::ColorType::Grayscale => buf.iter().flat_map(|&g| [g, g, g, 255]).collect(),
            other => {
                return Err(format!(
                    "unexpected PNG colour type {other:?} after expansion"
                ));
            }
        };
        if rgba.len() != pixels * 4 {
            return Err(format!(
                "PNG {}×{} decoded to {} bytes",
                info.width,
                info.height,
                rgba.len()
            ));
        }
        Ok(Image::new(info.width, info.height, rgba))
    }

    /// Encodes as an 8-bit RGBA PNG.
    pub fn encode_png(&self) -> Vec<u8> {
        let mut out = Vec::new();
        {
            let mut enc = png::Encoder::new(&mut out, self.width, self.height);
            enc.set_color(png::ColorType::Rgba);
            enc.set_depth(png::BitDepth::Eight);
            let mut w = enc.write_header().expect("PNG header");
            w.write_image_data(&self.rgba).expect("PNG data");
        }
        out
    }

    pub fn read_png(path: &Path) -> Result<Image, String> {
        let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
        Image::decode_png(&bytes).map_err(|e| format!("{}: {e}", path.display()))
    }

    /// Writes a PNG, creating the folder.
    pub fn write_png(&self, path: &Path) -> Result<(), String> {
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
        }
        std::fs::write(path, self.encode_png()).map_err(|e| format!("{}: {e}", path.display()))
    }
}

/// When two images count as equal.
#[derive(Clone, Copy, Debug)]
pub struct Tolerance {
    /// Largest difference in any channel (0..=255) a pixel may have and still count as equal.
    pub per_pixel: u8,
    /// Largest fraction of pixels (0..=1) that may differ by more.
    pub max_fraction: f64,
}

impl Tolerance {
    pub const EXACT: Tolerance = Tolerance {
        per_pixel: 0,
        max_fraction: 0.0,
    };
}

/// The outcome of comparing two images of the same size.
#[derive(Clone, Debug)]
pub struct Comparison {
    /// Pixels differing by more than the per-pixel threshold.
    pub differing: usize,
    pub pixels: usize,
    /// Largest difference in any channel of any pixel.
    pub max_delta: u8,
    /// A picture of the differences: differing pixels red, the rest the expected image dimmed.
    pub diff: Image,
}

impl Comparison {
    /// Fraction of pixels differing by more than the threshold.
    pub fn fraction(&self) -> f64 {
        self.differing as f64 / self.pixels.max(1) as f64
    }
}

impl std::fmt::Display for Comparison {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} of {} pixels differ ({:.3} %), largest channel difference {}",
            self.differing,
            self.pixels,
            self.fraction() * 100.0,
            self.max_delta
        )
    }
}

/// Compares `actual` with `expected` pixel by pixel; `Err` when the sizes differ.
pub fn compare(actual: &Image, expected: &Image, per_pixel: u8) -> Result<Comparison, String> {
    if (actual.width, actual.height) != (expected.width, expected.height) {
        return Err(format!(
            "size {}×{}, expected {}×{}",
            actual.width, actual.height, expected.width, expected.height
        ));
    }
    let mut differing = 0;
    let mut max_delta = 0u8;
    let mut diff = Vec::with_capacity(expected.rgba.len());
    for (a, e) in actual
        .rgba
        .chunks_exact(4)
        .zip(expected.rgba.chunks_exact(4))
    {
        let delta = a
            .iter()
            .zip(e)
            .map(|(x, y)| x.abs_diff(*y))
            .max()
            .unwrap_or(0);
        max_delta = max_delta.max(delta);
        if delta > per_pixel {
            differing += 1;
            diff.extend_from_slice(&[255, 0, 0, 255]);
        } else {
            diff.extend(e[..3].iter().map(|&c| c / 3));
            diff.push(255);
        }
    }
    Ok(Comparison {
        differing,
        pixels: expected.rgba.len() / 4,
        max_delta,
        diff: Image::new(expected.width, expected.height, diff),
    })
}

/// Whether this run rewrites golden files (`CROWDMORPH_BLESS` set to anything but `0` or empty).
pub fn blessing() -> bool {
    std::env::var("CROWDMORPH_BLESS").is_ok_and(|v| !v.is_empty() && v != "0")
}

/// Where a failed comparison leaves what it rendered.
pub fn failure_dir() -> PathBuf {
    Path::new(env!("CARGO_TARGET_TMPDIR")).join("golden-failures")
}

/// Checks `actual` against the golden PNG at `path` within `tolerance`, or rewrites the golden
/// file when [`blessing`]. On a mismatch, writes `<name>-actual.png` and `<name>-diff.png` to
/// [`failure_dir`] and panics naming them.
pub fn check_golden(path: &Path, actual: &Image, tolerance: Tolerance) {
    let name = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "image".into());
    if blessing() {
        actual.write_png(path).expect("write golden image");
        eprintln!("blessed {}", path.display());
        return;
    }
    let expected = Image::read_png(path).unwrap_or_else(|e| {
        panic!(
            "golden image missing or unreadable ({e}); generate it on lavapipe with \
             `CROWDMORPH_BLESS=1 cargo test --locked render` and review it before committing"
        )
    });
    let result = compare(actual, &expected, tolerance.per_pixel)
        .map(|c| (c.fraction() <= tolerance.max_fraction, c));
    let report = match result {
        Ok((true, _)) => return,
        Ok((false, c)) => {
            let diff_path = failure_dir().join(format!("{name}-diff.png"));
            c.diff.write_png(&diff_path).expect("write diff image");
            format!("{c}; difference image {}", diff_path.display())
        }
        Err(e) => e,
    };
    let actual_path = failure_dir().join(format!("{name}-actual.png"));
    actual.write_png(&actual_path).expect("write actual image");
    panic!(
        "{} does not match the golden image within {tolerance:?}: {report}; rendered image \
         {}. If the change is intended, re-bless with `CROWDMORPH_BLESS=1 cargo test --locked \
         render`",
        name,
        actual_path.display()
    );
}

#[test]
fn png_round_trip_and_comparison() {
    let mut rgba = Vec::new();
    for i in 0..12u8 {
        rgba.extend_from_slice(&[i * 20, 255 - i * 20, i, 255 - i]);
    }
    let img = Image::new(4, 3, rgba);
    let back = Image::decode_png(&img.encode_png()).expect("decode");
    assert_eq!(back, img);

    let mut other = img.clone();
    other.rgba[0] += 3; // pixel (0, 0): 3 off
    other.rgba[4 * 5 + 1] -= 40; // pixel (1, 1): 40 off
    let c = compare(&other, &img, 3).expect("same size");
    assert_eq!((c.differing, c.pixels, c.max_delta), (1, 12, 40));
    assert_eq!(c.diff.pixel(1, 1), [255, 0, 0, 255]);
    assert_eq!(compare(&other, &img, 40).expect("same size").differing, 0);
    assert!(compare(&Image::new(1, 1, vec![0; 4]), &img, 0).is_err());

    // Grey and RGB PNGs are expanded to RGBA.
    let mut grey = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut grey, 2, 1);
        enc.set_color(png::ColorType::Grayscale);
        enc.set_depth(png::BitDepth::Eight);
        let mut w = enc.write_header().expect("header");
        w.write_image_data(&[7, 200]).expect("data");
    }
    let g = Image::decode_png(&grey).expect("decode grey");
    assert_eq!(g.rgba, vec![7, 7, 7, 255, 200, 200, 200, 255]);
}
