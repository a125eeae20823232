//! A small line-plot writer for the LOD report's PNG.
//!
//! Hand-drawn on an RGB buffer and encoded with `png`: plotting crates draw text through system
//! fonts or a font file, which a fresh machine or CI may not have, while a report needs axis
//! labels and a legend. A 5 × 7 bitmap font (upper case, digits, a few symbols) keeps the PNG
//! self-contained and byte-for-byte deterministic.

/// One line of a panel.
#[derive(Clone, Debug)]
pub struct Series {
    /// Legend label.
    pub label: String,
    /// (x, y) points, drawn in order.
    pub points: Vec<(f64, f64)>,
}

/// Panels side by side, each with a title and its series.
#[derive(Clone, Debug)]
pub struct Plot {
    /// Title above the panels.
    pub title: String,
    /// (panel title, series).
    pub panels: Vec<(String, Vec<Series>)>,
}

const PANEL_W: usize = 560;
const PANEL_H: usize = 420;
const TITLE_H: usize = 30;
const SCALE: usize = 2;
const PALETTE: [[u8; 3]; 8] = [
    [0, 0, 0],
    [31, 119, 180],
    [44, 160, 44],
    [148, 103, 189],
    [255, 127, 14],
    [23, 190, 207],
    [214, 39, 40],
    [140, 86, 75],
];

/// 5 × 7 glyphs, one row per byte (bit 4 = leftmost column).
fn glyph(c: char) -> [u8; 7] {
    match c.to_ascii_uppercase() {
        '0' => [0x0E, 0x11, 0x13, 0x15, 0x19, 0x11, 0x0E],
        '1' => [0x04, 0x0C, 0x04, 0x04, 0x04, 0x04, 0x0E],
        '2' => [0x0E, 0x11, 0x01, 0x02, 0x04, 0x08, 0x1F],
        '3' => [0x1F, 0x02, 0x04, 0x02, 0x01, 0x11, 0x0E],
        '4' => [0x02, 0x06, 0x0A, 0x12, 0x1F, 0x02, 0x02],
        '5' => [0x1F, 0x10, 0x1E, 0x01, 0x01, 0x11, 0x0E],
        '6' => [0x06, 0x08, 0x10, 0x1E, 0x11, 0x11, 0x0E],
        '7' => [0x1F, 0x01, 0x02, 0x04, 0x08, 0x08, 0x08],
        '8' => [0x0E, 0x11, 0x11, 0x0E, 0x11, 0x11, 0x0E],
        '9' => [0x0E, 0x11, 0x11, 0x0F, 0x01, 0x02, 0x0C],
        'A' => [0x0E, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11],
        'B' => [0x1E, 0x11, 0x11, 0x1E, 0x11, 0x11, 0x1E],
        'C' => [0x0E, 0x11, 0x10, 0x10, 0x10, 0x11, 0x0E],
        'D' => [0x1C, 0x12, 0x11, 0x11, 0x11, 0x12, 0x1C],
        'E' => [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x1F],
        'F' => [0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x10],
        'G' => [0x0E, 0x11, 0x10, 0x17, 0x11, 0x11, 0x0F],
        'H' => [0x11, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11],
        'I' => [0x0E, 0x04, 0x04, 0x04, 0x04, 0x04, 0x0E],
        'J' => [0x07, 0x02, 0x02, 0x02, 0x02, 0x12, 0x0C],
        'K' => [0x11, 0x12, 0x14, 0x18, 0x14, 0x12, 0x11],
        'L' => [0x10, 0x10, 0x10, 0x10, 0x10, 0x10, 0x1F],
        'M' => [0x11, 0x1B, 0x15, 0x15, 0x11, 0x11, 0x11],
        'N' => [0x11, 0x11, 0x19, 0x15, 0x13, 0x11, 0x11],
        'O' => [0x0E, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E],
        'P' => [0x1E, 0x11, 0x11, 0x1E, 0x10, 0x10, 0x10],
        'Q' => [0x0E, 0x11, 0x11, 0x11, 0x15, 0x12, 0x0D],
        'R' => [0x1E, 0x11, 0x11, 0x1E, 0x14, 0x12, 0x11],
        'S' => [0x0F, 0x10, 0x10, 0x0E, 0x01, 0x01, 0x1E],
        'T' => [0x1F, 0x04, 0x04, 0x04, 0x04, 0x04, 0x04],
        'U' => [0x11, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E],
        'V' => [0x11, 0x11, 0x11, 0x11, 0x11, 0x0A, 0x04],
        'W' => [0x11, 0x11, 0x11, 0x15, 0x15, 0x15, 0x0A],
        'X' => [0x11, 0x11, 0x0A, 0x04, 0x0A, 0x11, 0x11],
        'Y' => [0x11, 0x11, 0x11, 0x0A, 0x04, 0x04, 0x04],
        'Z' => [0x1F, 0x01, 0x02, 0x04, 0x08, 0x10, 0x1F],
        '.' => [0x00, 0x00, 0x00, 0x00, 0x00, 0x0C, 0x0C],
        ',' => [0x00, 0x00, 0x00, 0x00, 0x0C, 0x04, 0x08],
        '-' => [0x00, 0x00, 0x00, 0x1F, 0x00, 0x00, 0x00],
        '%' => [0x18, 0x19, 0x02, 0x04, 0x08, 0x13, 0x03],
        '/' => [0x00, 0x01, 0x02, 0x04, 0x08, 0x10, 0x00],
        '_' => [0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x1F],
        '+' => [0x00, 0x04, 0x04, 0x1F, 0x04, 0x04, 0x00],
        ':' => [0x00, 0x0C, 0x0C, 0x00, 0x0C, 0x0C, 0x00],
        '(' => [0x02, 0x04, 0x08, 0x08, 0x08, 0x04, 0x02],
        ')' => [0x08, 0x04, 0x02, 0x02, 0x02, 0x04, 0x08],
        '=' => [0x00, 0x00, 0x1F, 0x00, 0x1F, 0x00, 0x00],
        '@' => [0x0E, 0x11, 0x01, 0x0D, 0x15, 0x15, 0x0E],
        ' ' => [0; 7],
        _ => [0x1F, 0x11, 0x11, 0x11, 0x11, 0x11, 0x1F],
    }
}

struct Canvas {
    w: usize,
    h: usize,
    rgb: Vec<u8>,
}

impl Canvas {
    fn new(w: usize, h: usize) -> Canvas {
        Canvas {
            w,
            h,
            rgb: vec![255; w * h * 3],
        }
    }

    fn set(&mut self, x: i64, y: i64, c: [u8; 3]) {
        if x >= 0 && y >= 0 && (x as usize) < self.w && (y as usize) < self.h {
            let i = (y as usize * self.w + x as usize) * 3;
            self.rgb[i..i + 3].copy_from_slice(&c);
        }
    }

    fn rect(&mut self, x: i64, y: i64, w: i64, h: i64, c: [u8; 3]) {
        for yy in y..y + h {
            for xx in x..x + w {
                self.set(xx, yy, c);
            }
        }
    }

    /// A line `thick` pixels wide (Bresenham with a square pen).
    fn line(&mut self, (x0, y0): (i64, i64), (x1, y1): (i64, i64), thick: i64, c: [u8; 3]) {
        let (dx, dy) = ((x1 - x0).abs(), -(y1 - y0).abs());
        let (sx, sy) = (if x0 < x1 { 1 } else { -1 }, if y0 < y1 { 1 } else { -1 });
        let (mut x, mut y, mut err) = (x0, y0, dx + dy);
        loop {
            self.rect(x - thick / 2, y - thick / 2, thick, thick, c);
            if x == x1 && y == y1 {
                break;
            }
            let e2 = 2 * err;
            if e2 >= dy {
                err += dy;
                x += sx;
            }
            if e2 <= dx {
                err += dx;
                y += sy;
            }
        }
    }

    /// Draws `text` with its top-left corner at (x, y), [`SCALE`] pixels per font pixel.
    fn text(&mut self, x: i64, y: i64, text: &str, c: [u8; 3]) {
        let k = SCALE as i64;
        for (n, ch) in text.chars().enumerate() {
            let g = glyph(ch);
            let ox = x + n as i64 * 6 * k;
            for (row, bits) in g.iter().enumerate() {
                for col in 0..5 {
                    if bits & (0x10 >> col) != 0 {
                        self.rect(ox + col * k, y + row as i64 * k, k, k, c);
                    }
                }
            }
        }
    }
}

/// Width in pixels of `text` drawn by [`Canvas::text`].
fn text_width(text: &str) -> i64 {
    (text.chars().count() * 6 * SCALE) as i64
}

/// A short label for an axis value: up to three significant digits.
fn tick_label(v: f64) -> String {
    if v == 0.0 {
        return "0".into();
    }
    let a = v.abs();
    if (0.01..1000.0).contains(&a) {
        let digits = (2 - a.log10().floor() as i32).clamp(0, 3) as usize;
        let s = format!("{v:.digits$}");
        if s.contains('.') {
            s.trim_end_matches('0').trim_end_matches('.').to_string()
        } else {
            s
        }
    } else {
        format!("{v:.1e}").to_uppercase()
    }
}

/// A "nice" axis: a tick step of 1, 2 or 5 × 10^k giving at most six intervals, and the
/// smallest multiple of it at or above `v`.
fn nice_max(v: f64) -> (f64, f64) {
    if v <= 0.0 || !v.is_finite() {
        return (1.0, 0.2);
    }
    let raw = v / 6.0;
    let p = 10f64.powf(raw.log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0]
        .iter()
        .map(|m| m * p)
        .find(|&s| s >= raw * (1.0 - 1e-12))
        .unwrap_or(10.0 * p);
    ((v / step - 1e-9).ceil().max(1.0) * step, step)
}

impl Plot {
    /// Renders the plot as PNG bytes.
    pub fn to_png(&self) -> Result<Vec<u8>, png::EncodingError> {
        let panels = self.panels.len().max(1);
        let mut cv = Canvas::new(PANEL_W * panels, PANEL_H + TITLE_H);
        let black = [0, 0, 0];
        let grey = [200, 200, 200];
        cv.text(12, 8, &self.title, black);
        for (pi, (title, series)) in self.panels.iter().enumerate() {
            let ox = (pi * PANEL_W) as i64;
            let oy = TITLE_H as i64;
            // Plot area inside the panel.
            let (left, right, top, bottom) = (ox + 70, ox + PANEL_W as i64 - 20, oy + 30, oy + 260);
            cv.text(left, oy + 6, title, black);
            let xmax = series
                .iter()
                .flat_map(|s| s.points.iter().map(|p| p.0))
                .fold(0.0f64, f64::max)
                .max(1.0);
            let ymax_raw = series
                .iter()
                .flat_map(|s| s.points.iter().map(|p| p.1))
                .fold(0.0f64, f64::max);
            let (ymax, ystep) = nice_max(ymax_raw);
            let (xnice, xstep) = nice_max(xmax);
            let px = |x: f64| left + ((x / xnice) * (right - left) as f64).round() as i64;
            let py = |y: f64| bottom - ((y / ymax) * (bottom - top) as f64).round() as i64;
            let mut t = 0.0;
            while t <= ymax * (1.0 + 1e-9) {
                let y = py(t);
                cv.line((left, y), (right, y), 1, grey);
                let label = tick_label(t);
                cv.text(left - 8 - text_width(&label), y - 7, &label, black);
                t += ystep;
            }
            let mut t = 0.0;
            while t <= xnice * (1.0 + 1e-9) {
                let x = px(t);
                cv.line((x, bottom), (x, bottom + 5), 1, black);
                let label = tick_label(t);
                cv.text(x - text_width(&label) / 2, bottom + 9, &label, black);
                t += xstep;
            }
            cv.line((left, top), (left, bottom), 2, black);
            cv.line((left, bottom), (right, bottom), 2, black);
            for (si, s) in series.iter().enumerate() {
                let c = PALETTE[si % PALETTE.len()];
                let pts: Vec<(i64, i64)> = s.points.iter().map(|&(x, y)| (px(x), py(y))).collect();
                for w in pts.windows(2) {
                    cv.line(w[0], w[1], 3, c);
                }
                for &p in &pts {
                    cv.rect(p.0 - 4, p.1 - 4, 9, 9, c);
                }
                // Legend: two columns under the axes.
                let lx = left + (si % 2) as i64 * 240;
                let ly = bottom + 36 + (si / 2) as i64 * 22;
                cv.rect(lx, ly + 3, 24, 8, c);
                cv.text(lx + 32, ly, &s.label, black);
            }
        }
        let mut out = Vec::new();
        {
            let mut enc = png::Encoder::new(&mut out, cv.w as u32, cv.h as u32);
            enc.set_color(png::ColorType::Rgb);
            enc.set_depth(png::BitDepth::Eight);
            let mut wr = enc.write_header()?;
            wr.write_image_data(&cv.rgb)?;
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ticks_and_nice_maxima() {
        let close =
            |a: (f64, f64), b: (f64, f64)| (a.0 - b.0).abs() < 1e-9 && (a.1 - b.1).abs() < 1e-9;
        assert!(close(nice_max(0.37), (0.4, 0.1)), "{:?}", nice_max(0.37));
        assert!(close(nice_max(1.0), (1.0, 0.2)), "{:?}", nice_max(1.0));
        assert!(close(nice_max(53.0), (60.0, 10.0)), "{:?}", nice_max(53.0));
        assert_eq!(tick_label(0.25), "0.25");
        assert_eq!(tick_label(12.0), "12");
        assert_eq!(tick_label(0.0), "0");
    }

    #[test]
    fn a_plot_encodes_deterministically() {
        let plot = Plot {
            title: "T".into(),
            panels: vec![(
                "P".into(),
                vec![Series {
                    label: "a".into(),
                    points: vec![(0.0, 1.0), (5.0, 0.0)],
                }],
            )],
        };
        let a = plot.to_png().expect("png");
        assert_eq!(a, plot.to_png().expect("png"));
        assert!(a.starts_with(b"\x89PNG"));
    }
}
