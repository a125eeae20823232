//! A minimal deterministic CPU software rasterizer: the reference renderer of LOD's image
//! metrics and feature detection (not the renderer clients see, which is `crate::render`).
//!
//! The image metrics of Costigan et al. 2016 §4.1 (image MSE, SSIM, Yee's perceptual
//! difference) compare renders of an expression and of the neutral face made "with the same
//! camera and lighting". They need a renderer that gives the same pixels on every machine and
//! every run, needs no GPU, and is mirror-exact (a left target and its mirrored right twin must
//! render as mirror images, or the metrics would tell them apart for no reason). This is that
//! renderer: orthographic front view framing the rig's bounding box, a z-buffer, per-pixel
//! interpolated vertex normals, Lambert + ambient shading from a light in the x = 0 plane, one
//! grayscale f32 channel. Triangles are drawn in order on one thread; ties in depth keep the first
//! triangle drawn, so the output depends only on the input. The GPU renderer in [`crate::render::gpu`] draws
//! the pictures clients see (perspective, colour, MSAA, instanced crowds); this one stays the
//! reference for the metrics.
//!
//! Besides shading, a [`Frame`] keeps the depth and the nearest vertex of every covered pixel,
//! which `crate::lod::mesh` uses to find facial feature points on the visible surface.

use glam::{Vec2, Vec3};

use crowdmorph_core::rig::{Aabb, Rig, vertex_normals};

/// Marks a pixel that no triangle covers in [`Frame::vertex`].
pub const NO_VERTEX: u32 = u32::MAX;

/// An orthographic camera looking down −Z (the glTF face looks toward +Z), and the lighting.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// Rig-space point at the centre of the image.
    pub center: Vec2,
    /// Rig units per pixel.
    pub units_per_pixel: f32,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Unit direction toward the light (from the surface).
    pub light: Vec3,
    /// Ambient term added to every lit pixel.
    pub ambient: f32,
    /// Weight of the Lambert term.
    pub diffuse: f32,
}

impl Camera {
    /// A square front view of `size` pixels framing `bbox` (x and y) with a 4 % margin; the
    /// light comes from the front and a little above, in the x = 0 plane so that the lighting is
    /// left/right symmetric.
    pub fn front(bbox: Aabb, size: u32) -> Camera {
        let size = size.max(1);
        let extent = (bbox.max - bbox.min).truncate().max_element().max(1e-6);
        Camera {
            center: ((bbox.min + bbox.max) * 0.5).truncate(),
            units_per_pixel: extent * 1.04 / size as f32,
            width: size,
            height: size,
            light: Vec3::new(0.0, 0.35, 1.0).normalize(),
            ambient: 0.1,
            diffuse: 0.9,
        }
    }

    /// The front view of a rig's neutral bounding box.
    pub fn for_rig(rig: &Rig, size: u32) -> Camera {
        Camera::front(rig.bbox(), size)
    }

    /// Screen position (pixels, x right, y down; pixel centres at +0.5) of a rig-space point.
    #[inline]
    pub fn project(&self, p: Vec3) -> Vec2 {
        Vec2::new(
            (p.x - self.center.x) / self.units_per_pixel + self.width as f32 * 0.5,
            (self.center.y - p.y) / self.units_per_pixel + self.height as f32 * 0.5,
        )
    }
}

/// A grayscale image, row-major, top row first.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// `width × height` intensities; 0 is black, lit surfaces are in (0, 1].
    pub pixels: Vec<f32>,
}

impl Image {
    /// A black image.
    pub fn new(width: u32, height: u32) -> Image {
        Image {
            width,
            height,
            pixels: vec![0.0; width as usize * height as usize],
        }
    }

    /// Intensity at (`x`, `y`).
    #[inline]
    pub fn at(&self, x: u32, y: u32) -> f32 {
        self.pixels[y as usize * self.width as usize + x as usize]
    }

    /// 8-bit grayscale PNG bytes (intensities clamped to [0, 1]), for looking at renders.
    pub fn to_png(&self) -> Result<Vec<u8>, png::EncodingError> {
        let mut out = Vec::new();
        {
            let mut enc = png::Encoder::new(&mut out, self.width, self.height);
            enc.set_color(png::ColorType::Grayscale);
            enc.set_depth(png::BitDepth::Eight);
            let mut w = enc.write_header()?;
            let bytes: Vec<u8> = self
                .pixels
                .iter()
                .map(|&v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
                .collect();
            w.write_image_data(&bytes)?;
        }
        Ok(out)
    }
}

/// A rendered frame: the shaded image plus, per pixel, depth and the nearest vertex.
#[derive(Clone, Debug, PartialEq)]
pub struct Frame {
    /// Shaded intensities.
    pub image: Image,
    /// Rig-space z of the visible surface (larger is nearer); `-inf` where nothing is drawn.
    pub depth: Vec<f32>,
    /// Global vertex index (evaluation order) of the visible triangle's corner with the largest
    /// barycentric weight; [`NO_VERTEX`] where nothing is drawn.
    pub vertex: Vec<u32>,
}

/// One triangle mesh to draw: positions and unit normals in rig space.
#[derive(Clone, Copy, Debug)]
pub struct MeshView<'a> {
    /// Vertex positions.
    pub positions: &'a [Vec3],
    /// Unit vertex normals, parallel to `positions`.
    pub normals: &'a [Vec3],
    /// Triangle list into `positions`.
    pub indices: &'a [u32],
    /// Global index of this mesh's vertex 0, for [`Frame::vertex`].
    pub first_vertex: u32,
}

/// Draws meshes into one frame with a z-buffer.
pub fn render(camera: &Camera, meshes: &[MeshView<'_>]) -> Frame {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let mut frame = Frame {
        image: Image::new(camera.width, camera.height),
        depth: vec![f32::NEG_INFINITY; w * h],
        vertex: vec![NO_VERTEX; w * h],
    };
    for m in meshes {
        let screen: Vec<Vec2> = m.positions.iter().map(|&p| camera.project(p)).collect();
        for tri in m.indices.chunks_exact(3) {
            let [a, b, c] = [tri[0] as usize, tri[1] as usize, tri[2] as usize];
            let (Some(&sa), Some(&sb), Some(&sc)) = (screen.get(a), screen.get(b), screen.get(c))
            else {
                continue;
            };
            draw_triangle(camera, &mut frame, m, [a, b, c], [sa, sb, sc]);
        }
    }
    frame
}

/// Signed doubled area of (a, b, p): positive when p is left of a→b in screen space.
#[inline]
fn edge(a: Vec2, b: Vec2, p: Vec2) -> f32 {
    (b.x - a.x) * (p.y - a.y) - (b.y - a.y) * (p.x - a.x)
}

fn draw_triangle(
    camera: &Camera,
    frame: &mut Frame,
    m: &MeshView<'_>,
    v: [usize; 3],
    s: [Vec2; 3],
) {
    let area = edge(s[0], s[1], s[2]);
    if area == 0.0 || !area.is_finite() {
        return;
    }
    let (w, h) = (camera.width as i64, camera.height as i64);
    let min = s[0].min(s[1]).min(s[2]);
    let max = s[0].max(s[1]).max(s[2]);
    // Pixels whose centre (x + 0.5) can fall inside the triangle.
    let x0 = ((min.x - 0.5).ceil() as i64).max(0);
    let x1 = ((max.x - 0.5).floor() as i64).min(w - 1);
    let y0 = ((min.y - 0.5).ceil() as i64).max(0);
    let y1 = ((max.y - 0.5).floor() as i64).min(h - 1);
    if x0 > x1 || y0 > y1 {
        return;
    }
    let z = [
        m.positions[v[0]].z,
        m.positions[v[1]].z,
        m.positions[v[2]].z,
    ];
    let n = [m.normals[v[0]], m.normals[v[1]], m.normals[v[2]]];
    let inv = 1.0 / area;
    for py in y0..=y1 {
        for px in x0..=x1 {
            let p = Vec2::new(px as f32 + 0.5, py as f32 + 0.5);
            // Barycentrics by signed area, so both windings draw (no culling) and a mirrored
            // triangle covers exactly the mirrored pixels.
            let l0 = edge(s[1], s[2], p) * inv;
            let l1 = edge(s[2], s[0], p) * inv;
            let l2 = edge(s[0], s[1], p) * inv;
            if l0 < 0.0 || l1 < 0.0 || l2 < 0.0 {
                continue;
            }
            let depth = l0 * z[0] + l1 * z[1] + l2 * z[2];
            let i = py as usize * camera.width as usize + px as usize;
            if depth <= frame.depth[i] {
                continue;
            }
            frame.depth[i] = depth;
            let normal = (n[0] * l0 + n[1] * l1 + n[2] * l2).normalize_or_zero();
            frame.image.pixels[i] =
                camera.ambient + camera.diffuse * normal.dot(camera.light).max(0.0);
            let k = if l0 >= l1 && l0 >= l2 {
                0
            } else if l1 >= l2 {
                1
            } else {
                2
            };
            frame.vertex[i] = m.first_vertex + v[k] as u32;
        }
    }
}

/// Renders a rig posed at `positions` (evaluation order: all primitives concatenated), with
/// normals recomputed from the posed triangles (area-weighted), as every pose is shaded alike.
/// `positions` shorter than the rig draws only the primitives it covers.
pub fn render_pose(rig: &Rig, positions: &[Vec3], camera: &Camera) -> Frame {
    let offsets = rig.vertex_offsets();
    let mut normals = Vec::with_capacity(rig.primitives.len());
    for (i, p) in rig.primitives.iter().enumerate() {
        let r = offsets[i]..offsets[i + 1];
        let pos = positions.get(r).unwrap_or(&[]);
        normals.push(vertex_normals(pos, &p.indices));
    }
    let views: Vec<MeshView<'_>> = rig
        .primitives
        .iter()
        .enumerate()
        .filter_map(|(i, p)| {
            let pos = positions.get(offsets[i]..offsets[i + 1])?;
            Some(MeshView {
                positions: pos,
                normals: &normals[i],
                indices: &p.indices,
                first_vertex: offsets[i] as u32,
            })
        })
        .collect();
    render(camera, &views)
}

/// The rig's neutral positions in evaluation order.
pub fn neutral_positions(rig: &Rig) -> Vec<Vec3> {
    rig.primitives
        .iter()
        .flat_map(|p| p.positions.iter().copied())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn quad() -> (Vec<Vec3>, Vec<u32>) {
        let p = vec![
            Vec3::new(-1.0, -1.0, 0.0),
            Vec3::new(1.0, -1.0, 0.0),
            Vec3::new(1.0, 1.0, 0.0),
            Vec3::new(-1.0, 1.0, 0.0),
        ];
        (p, vec![0, 1, 2, 0, 2, 3])
    }

    #[test]
    fn a_front_facing_quad_fills_the_frame_with_the_lit_value() {
        let (p, i) = quad();
        let n = vec![Vec3::Z; 4];
        let bbox = Aabb {
            min: Vec3::new(-1.0, -1.0, 0.0),
            max: Vec3::new(1.0, 1.0, 0.0),
        };
        let cam = Camera::front(bbox, 64);
        let f = render(
            &cam,
            &[MeshView {
                positions: &p,
                normals: &n,
                indices: &i,
                first_vertex: 10,
            }],
        );
        let lit = cam.ambient + cam.diffuse * cam.light.z;
        // The 4 % margin leaves a border of one pixel or so; the centre is covered and lit.
        assert!((f.image.at(32, 32) - lit).abs() < 1e-6);
        assert_eq!(f.image.at(0, 0), 0.0);
        let covered = f.vertex.iter().filter(|&&v| v != NO_VERTEX).count();
        assert!(covered > 58 * 58, "{covered}");
        assert!(
            f.vertex
                .iter()
                .all(|&v| v == NO_VERTEX || (10..14).contains(&v))
        );
    }

    #[test]
    fn mirrored_meshes_render_as_mirrored_images() {
        // A slanted triangle and its mirror image render as mirror images, pixel for pixel.
        let p = vec![
            Vec3::new(-1.0, -1.0, 0.0),
            Vec3::new(0.3, -0.2, 0.5),
            Vec3::new(-0.2, 1.0, 0.1),
        ];
        let q: Vec<Vec3> = p.iter().map(|v| Vec3::new(-v.x, v.y, v.z)).collect();
        let bbox = Aabb {
            min: Vec3::new(-1.0, -1.0, 0.0),
            max: Vec3::new(1.0, 1.0, 0.5),
        };
        let cam = Camera::front(bbox, 50);
        let img = |pos: &[Vec3], i: &[u32]| {
            let n = vertex_normals(pos, i);
            render(
                &cam,
                &[MeshView {
                    positions: pos,
                    normals: &n,
                    indices: i,
                    first_vertex: 0,
                }],
            )
        };
        // A mirror image reverses the winding, so the mirrored mesh lists its corners reversed.
        let (a, b) = (img(&p, &[0, 1, 2]), img(&q, &[0, 2, 1]));
        let lit = a.image.pixels.iter().filter(|&&v| v > 0.0).count();
        assert!(lit > 100);
        // Pixel centres lie exactly mirrored; only a centre that falls on an edge can go either
        // way, and shading may differ in the last bits, as rounding differs between a triangle
        // and its mirror image.
        let mut differ = 0;
        for y in 0..50 {
            for x in 0..50 {
                let (p, q) = (a.image.at(x, y), b.image.at(49 - x, y));
                if (p == 0.0) != (q == 0.0) {
                    differ += 1;
                } else {
                    assert!((p - q).abs() < 1e-5, "pixel {x},{y}: {p} vs {q}");
                }
            }
        }
        assert!(differ <= 2, "{differ} pixels differ");
    }
}
