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

/// Side of the windows of [`ssim_masked`], in pixels.
pub const SSIM_WINDOW: u32 = 8;

/// How far (0..=255, in any channel) a pixel must be from the background to count as drawn in
/// [`ssim_masked`]: a renderer's clear colour goes through its own sRGB round trip, and may land
/// a step away from the requested one.
pub const DRAWN_THRESHOLD: u8 = 2;

/// The outcome of [`ssim_masked`].
#[derive(Clone, Debug)]
pub struct MaskedSsim {
    /// Mean SSIM over the drawn pixels whose window fits in the image (1: identical).
    pub mean: f64,
    /// How many pixels the mean is over.
    pub pixels: usize,
    /// The SSIM map: each pixel of the mean in grey (black ≤ 0, white 1), the rest dark blue.
    pub map: Image,
}

/// Structural similarity (Wang et al. 2004) of the luminance of two pictures of one scene,
/// over the pixels either of them draws: those further than [`DRAWN_THRESHOLD`] from
/// `background` in `a` or in `b`.
///
/// Why this form: two renderers' pictures of one file are compared where something is drawn —
/// a picture that is mostly background would score near 1 whatever the model looked like, and
/// a pixel that only one of them draws (a silhouette that disagrees) must count. Luminance
/// (Rec. 709 weights of the sRGB-encoded values, the values a viewer sees) carries the
/// structure SSIM measures; colour differences show in it too, as a shift of the mean.
///
/// Each counted pixel `(x, y)` contributes the SSIM of the [`SSIM_WINDOW`]² window
/// `[x − 4, x + 4) × [y − 4, y + 4)` (uniform weights, K1 = 0.01, K2 = 0.03, dynamic range 1);
/// pixels whose window leaves the image are not counted. `Err` when the sizes differ or
/// nothing is drawn.
pub fn ssim_masked(a: &Image, b: &Image, background: [u8; 3]) -> Result<MaskedSsim, String> {
    if (a.width, a.height) != (b.width, b.height) {
        return Err(format!(
            "sizes differ: {}×{} and {}×{}",
            a.width, a.height, b.width, b.height
        ));
    }
    let (w, h) = (a.width as usize, a.height as usize);
    let luma = |img: &Image| -> Vec<f64> {
        img.rgba
            .chunks_exact(4)
            .map(|p| {
                (0.2126 * f64::from(p[0]) + 0.7152 * f64::from(p[1]) + 0.0722 * f64::from(p[2]))
                    / 255.0
            })
            .collect()
    };
    let drawn = |img: &Image, i: usize| {
        (0..3).any(|c| img.rgba[i * 4 + c].abs_diff(background[c]) > DRAWN_THRESHOLD)
    };
    let (la, lb) = (luma(a), luma(b));
    let c1 = 0.01f64.powi(2);
    let c2 = 0.03f64.powi(2);
    let half = SSIM_WINDOW as usize / 2;
    let n = (SSIM_WINDOW * SSIM_WINDOW) as f64;
    let mut map = Vec::with_capacity(w * h * 4);
    let (mut total, mut pixels) = (0f64, 0usize);
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let fits = x >= half && y >= half && x + half <= w && y + half <= h;
            if !fits || !(drawn(a, i) || drawn(b, i)) {
                map.extend_from_slice(&[0, 0, 64, 255]);
                continue;
            }
            let mut m = [0f64; 5];
            for wy in y - half..y + half {
                for wx in x - half..x + half {
                    let (p, q) = (la[wy * w + wx], lb[wy * w + wx]);
                    m[0] += p;
                    m[1] += q;
                    m[2] += p * p;
                    m[3] += q * q;
                    m[4] += p * q;
                }
            }
            let (mu_a, mu_b) = (m[0] / n, m[1] / n);
            let var_a = m[2] / n - mu_a * mu_a;
            let var_b = m[3] / n - mu_b * mu_b;
            let cov = m[4] / n - mu_a * mu_b;
            let s = ((2.0 * mu_a * mu_b + c1) * (2.0 * cov + c2))
                / ((mu_a * mu_a + mu_b * mu_b + c1) * (var_a + var_b + c2));
            total += s;
            pixels += 1;
            let g = (s.clamp(0.0, 1.0) * 255.0).round() as u8;
            map.extend_from_slice(&[g, g, g, 255]);
        }
    }
    if pixels == 0 {
        return Err("nothing is drawn in either image".into());
    }
    Ok(MaskedSsim {
        mean: total / pixels as f64,
        pixels,
        map: Image::new(a.width, a.height, map),
    })
}

#[test]
fn masked_ssim_is_one_for_equal_pictures_and_lower_for_shifted_or_noisy_ones() {
    const BG: [u8; 3] = [30, 40, 50];
    // A textured disc on a plain background, optionally moved right by `dx` pixels.
    let picture = |dx: i32| {
        let mut rgba = Vec::new();
        for y in 0..64i32 {
            for x in 0..64i32 {
                let (u, v) = (x - dx - 32, y - 32);
                if u * u + v * v < 24 * 24 {
                    let checker = ((u + 64) / 4 + (v + 64) / 4) % 2 == 0;
                    let g = if checker { 220 } else { 90 } as u8;
                    rgba.extend_from_slice(&[g, g / 2, 255 - g, 255]);
                } else {
                    rgba.extend_from_slice(&[BG[0], BG[1], BG[2], 255]);
                }
            }
        }
        Image::new(64, 64, rgba)
    };
    let base = picture(0);
    let same = ssim_masked(&base, &base, BG).expect("same size");
    assert_eq!(same.mean, 1.0);
    assert!(same.pixels > 1500, "{} pixels", same.pixels);
    assert_eq!(same.map.pixel(32, 32), [255, 255, 255, 255]);
    assert_eq!(same.map.pixel(1, 1), [0, 0, 64, 255]);

    let shifted = ssim_masked(&picture(3), &base, BG).expect("same size");
    assert!(shifted.mean < 0.6, "shifted by 3 pixels: {}", shifted.mean);
    // The pixels either picture draws: more than one alone.
    assert!(shifted.pixels > same.pixels);

    let mut rng = crate::util::Rng(7);
    let mut noisy = base.clone();
    for (i, c) in noisy.rgba.iter_mut().enumerate() {
        if i % 4 != 3 && base.rgba[i - i % 4..i - i % 4 + 3] != BG {
            let d = (rng.next_u64() % 61) as i32 - 30;
            *c = (i32::from(*c) + d).clamp(0, 255) as u8;
        }
    }
    let noised = ssim_masked(&noisy, &base, BG).expect("same size");
    assert!(
        noised.mean < 0.99 && noised.mean > shifted.mean,
        "noise ±30: {} (shifted: {})",
        noised.mean,
        shifted.mean
    );
    assert!(ssim_masked(&Image::new(1, 1, vec![0; 4]), &base, BG).is_err());
    let blank = picture(1000);
    assert!(ssim_masked(&blank, &blank, BG).is_err());
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
