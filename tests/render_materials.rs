//! Materials in rendered frames (`crowdmorph::render::gpu` on lavapipe): the glTF
//! metallic-roughness BRDF checked pixel by pixel against its CPU mirror
//! (`crowdmorph::render::brdf`), on flat quads built by hand with a material each, so every
//! pixel's normal and view direction are known exactly.

use crate::util::gpu_test;
use std::sync::Arc;

use crowdmorph::engine::gpu::GpuOptions;
use crowdmorph::render::brdf::{self, Surface};
use crowdmorph::render::gpu::{Frame, Renderer, SceneMesh, VertexSource, View};
use crowdmorph::rig::{Appearance, Lod, Material, Primitive, Rig, VertexLook};
use glam::{Mat4, Quat, Vec2, Vec3, Vec4};

use crate::util::open_gpu;

/// sRGB background: exact 8-bit values.
const BG: [u8; 3] = [40, 48, 64];

fn renderer() -> Renderer {
    Renderer::new(Arc::new(open_gpu(GpuOptions::default()))).expect("renderer")
}

fn frame(size: u32) -> Frame {
    Frame {
        width: size,
        height: size,
        background: BG.map(|c| f32::from(c) / 255.0),
    }
}

/// A camera on +Z looking at the origin, 4 units away.
fn view() -> View {
    View {
        eye: Vec3::new(0.0, 0.0, 4.0),
        target: Vec3::ZERO,
        up: Vec3::Y,
        fov_y_deg: 30.0,
        near: 0.5,
        far: 20.0,
    }
}

/// A `2·half`-wide square in the z = 0 plane facing +Z, texture coordinates (0, 0) at its top
/// left and (1, 1) at its bottom right (glTF's convention: v runs down the image).
fn quad(name: &str, half: f32, material: Option<u32>) -> Primitive {
    let positions = vec![
        Vec3::new(-half, half, 0.0),
        Vec3::new(half, half, 0.0),
        Vec3::new(half, -half, 0.0),
        Vec3::new(-half, -half, 0.0),
    ];
    Primitive {
        name: name.into(),
        normals: vec![Vec3::Z; 4],
        positions,
        normals_from_file: true,
        tangents: None,
        // Counter-clockwise seen from +Z.
        indices: vec![0, 3, 2, 0, 2, 1],
        targets: Vec::new(),
        base_color: [1.0; 4],
        skin: None,
        look: VertexLook {
            uv0: Some(vec![
                Vec2::new(0.0, 0.0),
                Vec2::new(1.0, 0.0),
                Vec2::new(1.0, 1.0),
                Vec2::new(0.0, 1.0),
            ]),
            material,
            ..VertexLook::default()
        },
    }
}

/// A rig of `primitives` and `appearance`, nothing else (no targets or clips).
fn rig(primitives: Vec<Primitive>, appearance: Option<Appearance>) -> Rig {
    let rig = Rig {
        name: "quads".into(),
        targets: Vec::new(),
        default_weights: Vec::new(),
        primitives: Arc::new(primitives),
        clips: Vec::new(),
        lod: Lod::file_order(0),
        skeleton: None,
        import_notes: Vec::new(),
        appearance: appearance.map(Arc::new),
    };
    rig.validate().expect("a valid rig");
    rig
}

/// The rig's neutral positions and normals, as a renderer's host vertex data.
fn neutral(rig: &Rig) -> (Vec<f32>, Vec<f32>) {
    let mut p = Vec::new();
    let mut n = Vec::new();
    for prim in rig.primitives.iter() {
        p.extend(prim.positions.iter().flat_map(|v| v.to_array()));
        n.extend(prim.normals.iter().flat_map(|v| v.to_array()));
    }
    (p, n)
}

/// Renders `rig` once per model matrix in `instances` (one mesh) at `size`², RGBA8 rows.
fn render(r: &Renderer, rig: &Rig, instances: &[Mat4], view: &View, size: u32) -> Vec<u8> {
    let topology = r.topology(rig).expect("topology");
    let data = neutral(rig);
    let mesh = SceneMesh {
        topology: &topology,
        positions: VertexSource::Host(&data.0),
        normals: VertexSource::Host(&data.1),
        instances,
        layers: &[],
    };
    r.render(&[mesh], view, &frame(size)).expect("render").rgba
}

fn pixel(rgba: &[u8], size: u32, x: u32, y: u32) -> [u8; 4] {
    let i = ((y * size + x) * 4) as usize;
    [rgba[i], rgba[i + 1], rgba[i + 2], rgba[i + 3]]
}

/// Where the ray through pixel (`x`, `y`)'s centre meets the plane through `point` with normal
/// `n`.
fn hit(view: &View, size: u32, x: u32, y: u32, point: Vec3, n: Vec3) -> Vec3 {
    let inv = view.clip_from_world(1.0).inverse();
    let ndc = Vec2::new(
        (x as f32 + 0.5) / size as f32 * 2.0 - 1.0,
        1.0 - (y as f32 + 0.5) / size as f32 * 2.0,
    );
    let a = inv.project_point3(ndc.extend(1.0));
    let b = inv.project_point3(ndc.extend(0.5));
    let dir = (b - a).normalize();
    let t = (point - a).dot(n) / dir.dot(n);
    a + dir * t
}

/// The CPU mirror's 8-bit sRGB colour of `surface` at world point `p` with unit normal `n`.
fn expected(view: &View, surface: &Surface, p: Vec3, n: Vec3) -> [u8; 3] {
    let lights = brdf::reference_lights(view).expect("lights");
    let c = brdf::shade(surface, n, (view.eye - p).normalize(), &lights);
    c.to_array().map(brdf::linear_to_srgb8)
}

fn max_delta(a: [u8; 4], b: [u8; 3]) -> u8 {
    (0..3).map(|i| a[i].abs_diff(b[i])).max().unwrap_or(0)
}

/// Materials that cover the BRDF's corners: dielectric and metal, rough and smooth, coloured,
/// emissive.
fn materials() -> Vec<Material> {
    let m = |base: [f32; 3], metallic: f32, roughness: f32| Material {
        base_color_factor: [base[0], base[1], base[2], 1.0],
        metallic_factor: metallic,
        roughness_factor: roughness,
        ..Material::default()
    };
    vec![
        m([0.745, 0.412, 0.305], 0.0, 0.5),
        m([0.9, 0.9, 0.9], 1.0, 0.3),
        m([0.2, 0.5, 0.8], 0.0, 0.9),
        m([1.0, 0.8, 0.4], 1.0, 0.08),
        m([0.5, 0.5, 0.5], 0.5, 0.0),
        Material {
            emissive_factor: [0.3, 0.1, 0.0],
            emissive_strength: 1.5,
            ..m([0.1, 0.6, 0.2], 0.0, 0.6)
        },
    ]
}

fn surface(m: &Material) -> Surface {
    Surface {
        base: Vec4::from_array(m.base_color_factor).truncate(),
        metallic: m.metallic_factor,
        roughness: m.roughness_factor,
        occlusion: 1.0,
        emissive: Vec3::from_array(m.emissive_factor) * m.emissive_strength,
    }
}

gpu_test!(
    #[test]
    fn the_brdf_matches_its_cpu_mirror_on_flat_quads() {
        let r = renderer();
        let view = view();
        let lights = brdf::reference_lights(&view).expect("lights");
        let size = 65;
        // Facing the camera; facing the key light's half vector (the highlight's peak); and
        // turned well away, toward the fill.
        let key_half = (lights.key.direction + Vec3::Z).normalize();
        let turns = [
            Quat::IDENTITY,
            Quat::from_rotation_arc(Vec3::Z, key_half),
            Quat::from_rotation_arc(Vec3::Z, Vec3::new(0.6, -0.3, 0.74).normalize()),
        ];
        let mut worst = 0u8;
        for (k, material) in materials().into_iter().enumerate() {
            let s = surface(&material);
            let appearance = Appearance {
                materials: vec![material],
                ..Appearance::default()
            };
            let rig = rig(vec![quad("quad", 1.0, Some(0))], Some(appearance));
            for turn in turns {
                let model = Mat4::from_quat(turn);
                let n = turn * Vec3::Z;
                let rgba = render(&r, &rig, &[model], &view, size);
                // The centre and four points around it, all well inside the quad.
                for (x, y) in [(32, 32), (24, 26), (40, 27), (27, 39), (38, 38)] {
                    let p = hit(&view, size, x, y, Vec3::ZERO, n);
                    let want = expected(&view, &s, p, n);
                    let got = pixel(&rgba, size, x, y);
                    let d = max_delta(got, want);
                    worst = worst.max(d);
                    assert!(
                        d <= 3 && got[3] == 255,
                        "material {k}, normal {n}, pixel ({x}, {y}): GPU {got:?}, CPU {want:?}"
                    );
                }
            }
        }
        eprintln!("largest difference from the CPU BRDF: {worst}/255");
    }
);

gpu_test!(
    #[test]
    fn an_unlit_material_draws_its_base_colour() {
        let r = renderer();
        let view = view();
        let material = Material {
            base_color_factor: [0.2, 0.5, 0.8, 1.0],
            unlit: true,
            ..Material::default()
        };
        let appearance = Appearance {
            materials: vec![material],
            ..Appearance::default()
        };
        let rig = rig(vec![quad("quad", 1.0, Some(0))], Some(appearance));
        // Turned away from every light: lit, it would be dark.
        let model = Mat4::from_rotation_y(1.2);
        let rgba = render(&r, &rig, &[model], &view, 33);
        let want = [0.2f32, 0.5, 0.8].map(brdf::linear_to_srgb8);
        assert!(max_delta(pixel(&rgba, 33, 16, 16), want) <= 1);
    }
);

gpu_test!(
    #[test]
    fn a_primitive_without_a_material_is_a_half_rough_dielectric_of_its_base_colour() {
        let r = renderer();
        let view = view();
        let mut q = quad("quad", 1.0, None);
        q.base_color = [0.745, 0.412, 0.305, 1.0];
        let rig = rig(vec![q], None);
        let rgba = render(&r, &rig, &[Mat4::IDENTITY], &view, 33);
        let s = surface(&Material::untextured([0.745, 0.412, 0.305, 1.0]));
        let want = expected(&view, &s, Vec3::ZERO, Vec3::Z);
        let got = pixel(&rgba, 33, 16, 16);
        assert!(max_delta(got, want) <= 3, "{got:?} vs {want:?}");
    }
);

// ---------------------------------------------------------------------------------------------
// Textures
// ---------------------------------------------------------------------------------------------

use crowdmorph::rig::{
    AlphaMode, Filter, ImageData, ImageMime, MipLevel, Mips, Sampler, TexRef, Texture, UvTransform,
    Wrap,
};

/// A full RGBA8 mip chain of a `w × h` image whose texel (x, y) is `texel(x, y)` (sRGB colour,
/// linear alpha), each level the 2×2 box mean of the one above in linear light, as an import
/// makes it.
fn mips(w: u32, h: u32, texel: impl Fn(u32, u32) -> [u8; 4]) -> Mips {
    let mut levels = vec![MipLevel {
        width: w,
        height: h,
        rgba: (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .flat_map(|(x, y)| texel(x, y))
            .collect(),
    }];
    while let Some(l) = levels.last().filter(|l| l.width > 1 || l.height > 1) {
        let (nw, nh) = ((l.width / 2).max(1), (l.height / 2).max(1));
        let at = |x: u32, y: u32, c: usize| {
            let (x, y) = (x.min(l.width - 1), y.min(l.height - 1));
            l.rgba[((y * l.width + x) * 4) as usize + c]
        };
        let mut rgba = Vec::with_capacity((nw * nh * 4) as usize);
        for y in 0..nh {
            for x in 0..nw {
                for c in 0..4 {
                    let mut sum = 0.0;
                    for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                        let v = at(2 * x + dx, 2 * y + dy, c);
                        sum += if c < 3 {
                            brdf::srgb8_to_linear(v)
                        } else {
                            f32::from(v) / 255.0
                        };
                    }
                    let mean = sum / 4.0;
                    rgba.push(if c < 3 {
                        brdf::linear_to_srgb8(mean)
                    } else {
                        (mean * 255.0).round() as u8
                    });
                }
            }
        }
        levels.push(MipLevel {
            width: nw,
            height: nh,
            rgba,
        });
    }
    Mips { levels }
}

/// An appearance of `materials` that all sample one image (`pixels`) through texture 0 with
/// `sampler`.
fn with_image(materials: Vec<Material>, pixels: Mips, sampler: Sampler) -> Appearance {
    let (w, h) = (pixels.levels[0].width, pixels.levels[0].height);
    Appearance {
        materials,
        textures: vec![Texture {
            sampler: Some(0),
            image: Some(0),
        }],
        samplers: vec![sampler],
        images: vec![ImageData {
            mime: ImageMime::Png,
            bytes: Arc::from(&[][..]),
            width: w,
            height: h,
            downscaled_from: None,
            pixels: Some(Arc::new(pixels)),
        }],
        notes: Vec::new(),
        target_textures: Vec::new(),
        clip_textures: Vec::new(),
    }
}

fn tex(tex_coord: u8, transform: Option<UvTransform>) -> Option<TexRef> {
    Some(TexRef {
        texture: 0,
        tex_coord,
        transform,
    })
}

/// Two colours far from grey and from each other, where a missing sRGB decode or a neighbour
/// bleeding in shows.
const WARM: [u8; 4] = [200, 60, 30, 255];
const COOL: [u8; 4] = [20, 120, 230, 255];

/// A 16 × 16 checker of 4 × 4-texel cells: bilinear filtering at a cell's centre reads four
/// texels of the cell's own colour, so the pixel there is the texel exactly.
fn checker(x: u32, y: u32) -> [u8; 4] {
    if (x / 4 + y / 4).is_multiple_of(2) {
        WARM
    } else {
        COOL
    }
}

/// The pixel whose centre is nearest the quad point at texture coordinates `uv` (a quad of
/// half-width 1 at the origin, unturned, seen by [`view`]).
fn pixel_at_uv(size: u32, uv: Vec2) -> (u32, u32) {
    let world = Vec3::new(uv.x * 2.0 - 1.0, 1.0 - uv.y * 2.0, 0.0);
    let clip = view().clip_from_world(1.0).project_point3(world);
    (
        ((clip.x + 1.0) * 0.5 * size as f32) as u32,
        ((1.0 - clip.y) * 0.5 * size as f32) as u32,
    )
}

gpu_test!(
    #[test]
    fn a_checker_textures_cell_centres_are_its_texels_in_srgb() {
        let r = renderer();
        let view = view();
        let size = 129;
        let unlit = Material {
            base_color_texture: tex(0, None),
            unlit: true,
            ..Material::default()
        };
        // Lit, and reading set 1, which runs the other way along u.
        let lit = Material {
            base_color_texture: tex(1, None),
            ..Material::untextured([1.0; 4])
        };
        // Shifted by one cell along u.
        let shifted = Material {
            base_color_texture: tex(
                0,
                Some(UvTransform {
                    offset: [0.25, 0.0],
                    ..UvTransform::default()
                }),
            ),
            unlit: true,
            ..Material::default()
        };
        let appearance = with_image(
            vec![unlit, lit, shifted],
            mips(16, 16, checker),
            Sampler::default(),
        );
        // Cell centres: texel 2, 6, 10, 14 along each axis, so uv (2k + 1)/8.
        let centres: Vec<(u32, u32)> = (0..4).flat_map(|i| (0..4).map(move |j| (i, j))).collect();
        let uv_of =
            |(i, j): (u32, u32)| Vec2::new((4 * i + 2) as f32 / 16.0, (4 * j + 2) as f32 / 16.0);
        let colour_of = |(i, j): (u32, u32)| checker(4 * i, 4 * j);
        for (m, what) in [(0, "unlit"), (1, "lit, set 1"), (2, "transformed")] {
            let mut q = quad("quad", 1.0, Some(m));
            q.look.uv1 = q
                .look
                .uv0
                .as_ref()
                .map(|uv| uv.iter().map(|t| Vec2::new(1.0 - t.x, t.y)).collect());
            let rig = rig(vec![q], Some(appearance.clone()));
            let rgba = render(&r, &rig, &[Mat4::IDENTITY], &view, size);
            for &cell in &centres {
                let uv = uv_of(cell);
                let (x, y) = pixel_at_uv(size, uv);
                let got = pixel(&rgba, size, x, y);
                let want: [u8; 3] = match m {
                    0 => {
                        let c = colour_of(cell);
                        [c[0], c[1], c[2]]
                    }
                    1 => {
                        let c = colour_of((3 - cell.0, cell.1));
                        let s = Surface {
                            base: Vec3::from_array([c[0], c[1], c[2]].map(brdf::srgb8_to_linear)),
                            ..surface(&Material::untextured([1.0; 4]))
                        };
                        expected(
                            &view,
                            &s,
                            hit(&view, size, x, y, Vec3::ZERO, Vec3::Z),
                            Vec3::Z,
                        )
                    }
                    _ => {
                        let c = colour_of(((cell.0 + 1) % 4, cell.1));
                        [c[0], c[1], c[2]]
                    }
                };
                let tolerance = if m == 1 { 3 } else { 2 };
                assert!(
                    max_delta(got, want) <= tolerance,
                    "{what}: cell {cell:?} at pixel ({x}, {y}): {got:?}, want {want:?}"
                );
            }
        }
    }
);

gpu_test!(
    #[test]
    fn vertex_colours_multiply_the_base_colour() {
        let r = renderer();
        let view = view();
        let material = Material {
            base_color_factor: [1.0, 0.8, 1.0, 1.0],
            base_color_texture: tex(0, None),
            unlit: true,
            ..Material::default()
        };
        let appearance = with_image(vec![material], mips(16, 16, checker), Sampler::default());
        let mut q = quad("quad", 1.0, Some(0));
        q.look.colors = Some(vec![Vec4::new(0.5, 1.0, 0.25, 1.0); 4]);
        let rig = rig(vec![q], Some(appearance));
        let size = 129;
        let rgba = render(&r, &rig, &[Mat4::IDENTITY], &view, size);
        let (x, y) = pixel_at_uv(size, Vec2::new(2.0 / 16.0, 2.0 / 16.0));
        let want = [0.5f32, 0.8, 0.25]
            .iter()
            .zip(&WARM)
            .map(|(k, &c)| brdf::linear_to_srgb8(k * brdf::srgb8_to_linear(c)))
            .collect::<Vec<_>>();
        let got = pixel(&rgba, size, x, y);
        assert!(
            max_delta(got, [want[0], want[1], want[2]]) <= 2,
            "{got:?} vs {want:?}"
        );
    }
);

gpu_test!(
    #[test]
    fn a_minified_checker_shows_its_mip_means() {
        let r = renderer();
        let view = view();
        // One-texel cells: any level but the base one is their mean, and a pixel spanning
        // many texels without mips would alias to one colour or the other.
        let chain = mips(64, 64, |x, y| if (x + y) % 2 == 0 { WARM } else { COOL });
        let mean = chain.levels[1].rgba[..3].to_vec();
        let sampler = Sampler {
            mag: Filter::Linear,
            min: Filter::Linear,
            mipmap: Some(Filter::Linear),
            wrap_s: Wrap::Repeat,
            wrap_t: Wrap::Repeat,
        };
        let material = Material {
            base_color_texture: tex(0, None),
            unlit: true,
            ..Material::default()
        };
        let rig = rig(
            vec![quad("quad", 1.0, Some(0))],
            Some(with_image(vec![material], chain, sampler)),
        );
        // 20 pixels across for 64 texels: about level 1.7.
        let size = 65;
        let far = View {
            eye: Vec3::new(0.0, 0.0, 12.0),
            ..view
        };
        let rgba = render(&r, &rig, &[Mat4::IDENTITY], &far, size);
        let mut checked = 0;
        for y in 28..37 {
            for x in 28..37 {
                let got = pixel(&rgba, size, x, y);
                assert!(
                    max_delta(got, [mean[0], mean[1], mean[2]]) <= 3,
                    "pixel ({x}, {y}): {got:?}, the mip mean is {mean:?}"
                );
                checked += 1;
            }
        }
        assert_eq!(checked, 81);
    }
);

gpu_test!(
    #[test]
    fn a_masked_material_has_holes_below_its_cutoff() {
        let r = renderer();
        let view = view();
        // Alpha 0 and 255 in 4 × 4 cells.
        let chain = mips(16, 16, |x, y| {
            let [r, g, b, _] = WARM;
            [r, g, b, if (x / 4 + y / 4) % 2 == 0 { 255 } else { 0 }]
        });
        let mask = Material {
            base_color_texture: tex(0, None),
            alpha_mode: AlphaMode::Mask,
            alpha_cutoff: 0.5,
            unlit: true,
            ..Material::default()
        };
        let opaque = Material {
            alpha_mode: AlphaMode::Opaque,
            ..mask.clone()
        };
        let appearance = with_image(vec![mask, opaque], chain, Sampler::default());
        let size = 129;
        for (m, holes) in [(0, true), (1, false)] {
            let rig = rig(vec![quad("quad", 1.0, Some(m))], Some(appearance.clone()));
            let rgba = render(&r, &rig, &[Mat4::IDENTITY], &view, size);
            for (i, j) in [(0u32, 0u32), (1, 0), (2, 1), (3, 3), (0, 3)] {
                let (x, y) = pixel_at_uv(
                    size,
                    Vec2::new((4 * i + 2) as f32 / 16.0, (4 * j + 2) as f32 / 16.0),
                );
                let got = pixel(&rgba, size, x, y);
                let solid = (i + j) % 2 == 0;
                let want = if solid || !holes {
                    [WARM[0], WARM[1], WARM[2]]
                } else {
                    BG
                };
                assert!(
                    max_delta(got, want) <= 2,
                    "material {m}, cell ({i}, {j}): {got:?}, want {want:?}"
                );
            }
        }
    }
);

gpu_test!(
    #[test]
    fn blended_quads_composite_far_to_near_whatever_the_request_order() {
        let r = renderer();
        let view = view();
        let blend = |c: [f32; 3]| Material {
            base_color_factor: [c[0], c[1], c[2], 0.5],
            alpha_mode: AlphaMode::Blend,
            unlit: true,
            ..Material::default()
        };
        let appearance = Appearance {
            materials: vec![
                blend([1.0, 0.0, 0.0]),
                blend([0.0, 0.0, 1.0]),
                Material {
                    base_color_factor: [0.0, 0.5, 0.0, 1.0],
                    unlit: true,
                    ..Material::default()
                },
            ],
            ..Appearance::default()
        };
        // Red nearest, blue in the middle, an opaque green quad behind both, each its own rig
        // and mesh; the near ones smaller so each shows alone somewhere.
        let red = rig(vec![quad("red", 0.5, Some(0))], Some(appearance.clone()));
        let blue = rig(vec![quad("blue", 0.8, Some(1))], Some(appearance.clone()));
        let green = rig(vec![quad("green", 1.0, Some(2))], Some(appearance));
        let at = |z: f32| [Mat4::from_translation(Vec3::new(0.0, 0.0, z))];
        let placed = [(&red, at(0.6)), (&blue, at(0.3)), (&green, at(0.0))];
        let topologies: Vec<_> = placed
            .iter()
            .map(|(rig, _)| r.topology(rig).expect("topology"))
            .collect();
        let data: Vec<_> = placed.iter().map(|(rig, _)| neutral(rig)).collect();
        let size = 65;
        let draw = |order: [usize; 3]| {
            let meshes: Vec<SceneMesh<'_>> = order
                .iter()
                .map(|&k| SceneMesh {
                    topology: &topologies[k],
                    positions: VertexSource::Host(&data[k].0),
                    normals: VertexSource::Host(&data[k].1),
                    instances: &placed[k].1,
                    layers: &[],
                })
                .collect();
            r.render(&meshes, &view, &frame(size)).expect("render").rgba
        };
        let first = draw([0, 1, 2]);
        for order in [[2, 1, 0], [1, 0, 2], [0, 2, 1]] {
            assert!(
                draw(order) == first,
                "order {order:?} draws another picture"
            );
        }
        // Straight alpha in linear light: blue over green, then red over that.
        let over = |src: [f32; 3], dst: [f32; 3]| [0, 1, 2].map(|i| src[i] * 0.5 + dst[i] * 0.5);
        let green_lin = [0.0, 0.5, 0.0];
        let centre = over([1.0, 0.0, 0.0], over([0.0, 0.0, 1.0], green_lin));
        let want = centre.map(brdf::linear_to_srgb8);
        let got = pixel(&first, size, 32, 32);
        assert!(max_delta(got, want) <= 2, "centre {got:?}, want {want:?}");
        assert_eq!(got[3], 255, "the frame stays opaque");
    }
);

gpu_test!(
    #[test]
    fn single_sided_back_faces_are_culled_and_double_sided_ones_lit_from_their_side() {
        let r = renderer();
        let view = view();
        let m = |double_sided: bool| Material {
            double_sided,
            ..Material::untextured([0.745, 0.412, 0.305, 1.0])
        };
        let appearance = Appearance {
            materials: vec![m(false), m(true)],
            ..Appearance::default()
        };
        // Turned to show its back, a little toward the key light.
        let turn = Quat::from_rotation_y(std::f32::consts::PI - 0.4);
        let size = 65;
        for (k, culled) in [(0, true), (1, false)] {
            let rig = rig(vec![quad("quad", 1.0, Some(k))], Some(appearance.clone()));
            let rgba = render(&r, &rig, &[Mat4::from_quat(turn)], &view, size);
            let got = pixel(&rgba, size, 32, 32);
            if culled {
                assert_eq!(got, [BG[0], BG[1], BG[2], 255], "a culled back face");
            } else {
                // The surface's other side: the normal turned round.
                let n = -(turn * Vec3::Z);
                let want = expected(&view, &surface(&m(true)), Vec3::ZERO, n);
                assert!(max_delta(got, want) <= 3, "{got:?} vs {want:?}");
            }
        }
        // A mirroring instance is never culled: its triangles' winding is turned round.
        let rig = rig(vec![quad("quad", 1.0, Some(0))], Some(appearance));
        let mirror = Mat4::from_scale(Vec3::new(-1.0, 1.0, 1.0));
        let rgba = render(&r, &rig, &[mirror], &view, size);
        let want = expected(&view, &surface(&m(false)), Vec3::ZERO, Vec3::Z);
        let got = pixel(&rgba, size, 32, 32);
        assert!(
            max_delta(got, want) <= 3,
            "mirrored front: {got:?} vs {want:?}"
        );
    }
);

gpu_test!(
    #[test]
    fn textures_are_charged_to_the_gpu_budget_once_per_rig_and_given_back() {
        let r = renderer();
        let material = Material {
            base_color_texture: tex(0, None),
            ..Material::default()
        };
        let chain = mips(64, 32, checker);
        let texture_bytes = chain.bytes() as u64;
        let textured = rig(
            vec![quad("quad", 1.0, Some(0))],
            Some(with_image(vec![material], chain, Sampler::default())),
        );
        let before = r.memory().used();
        let t = r.topology(&textured).expect("topology");
        assert_eq!(t.texture_bytes(), texture_bytes);
        assert_eq!(r.memory().used() - before, t.bytes());
        // A second topology of the rig (another mesh level would be the same) shares them.
        let again = r.topology(&textured).expect("topology");
        assert_eq!(
            r.memory().used() - before,
            t.bytes() + again.bytes() - texture_bytes
        );
        drop(t);
        assert_eq!(r.memory().used() - before, again.bytes());
        drop(again);
        assert_eq!(r.memory().used(), before, "everything is given back");
        // An image without pixels draws white and costs nothing.
        let mut appearance = textured.appearance.as_deref().cloned().expect("appearance");
        appearance.images[0].pixels = None;
        let plain = rig(vec![quad("quad", 1.0, Some(0))], Some(appearance));
        let t = r.topology(&plain).expect("topology");
        assert_eq!(t.texture_bytes(), 0);
        assert_eq!(t.texture_slots(), 0);
    }
);

// ---------------------------------------------------------------------------------------------
// Normal maps
// ---------------------------------------------------------------------------------------------

gpu_test!(
    #[test]
    fn a_normal_mapped_flat_quad_shades_as_its_perturbed_normal() {
        let r = renderer();
        let view = view();
        let size = 65;
        // One tangent-space normal everywhere, (0.65, −0.53, 0.57) before normalization:
        // linear data (sampled through the linear view).
        let texel = [210u8, 60, 200, 255];
        let decode = |c: u8| f32::from(c) / 255.0 * 2.0 - 1.0;
        let tn = Vec3::new(decode(texel[0]), decode(texel[1]), decode(texel[2]));
        let material = Material {
            base_color_factor: [0.6, 0.6, 0.6, 1.0],
            metallic_factor: 0.0,
            roughness_factor: 0.4,
            normal_texture: tex(0, None),
            normal_scale: 0.8,
            ..Material::default()
        };
        let s = surface(&material);
        let appearance = with_image(vec![material], mips(4, 4, |_, _| texel), Sampler::default());
        // glTF tangent space: t along u, bitangent up the image (against v), n out of the
        // surface; the map's xy are scaled by normal_scale.
        let scaled = Vec3::new(tn.x * 0.8, tn.y * 0.8, tn.z);
        // (layout, tangents from the file?, world t, world b): u to the right (generated, and
        // from the file), and u up the quad with v to the right (generated).
        let rotated_uv = vec![
            Vec2::new(1.0, 0.0),
            Vec2::new(1.0, 1.0),
            Vec2::new(0.0, 1.0),
            Vec2::new(0.0, 0.0),
        ];
        let cases: [(Option<Vec<Vec2>>, bool, Vec3, Vec3); 3] = [
            (None, false, Vec3::X, Vec3::Y),
            (None, true, Vec3::X, Vec3::Y),
            (Some(rotated_uv), false, Vec3::Y, -Vec3::X),
        ];
        for (k, (uv, file_tangents, t, b)) in cases.into_iter().enumerate() {
            let mut q = quad("quad", 1.0, Some(0));
            if let Some(uv) = uv {
                q.look.uv0 = Some(uv);
            }
            if file_tangents {
                q.tangents = Some(vec![Vec4::new(1.0, 0.0, 0.0, 1.0); 4]);
            }
            let rig = rig(vec![q], Some(appearance.clone()));
            let rgba = render(&r, &rig, &[Mat4::IDENTITY], &view, size);
            let n = (t * scaled.x + b * scaled.y + Vec3::Z * scaled.z).normalize();
            for (x, y) in [(32, 32), (26, 28), (38, 37)] {
                let p = hit(&view, size, x, y, Vec3::ZERO, Vec3::Z);
                let want = expected(&view, &s, p, n);
                let got = pixel(&rgba, size, x, y);
                assert!(
                    max_delta(got, want) <= 3,
                    "case {k}, pixel ({x}, {y}): {got:?}, the perturbed normal's {want:?}"
                );
                // And it is not the flat quad's colour.
                let flat = expected(&view, &s, p, Vec3::Z);
                let apart = (0..3).map(|i| want[i].abs_diff(flat[i])).max();
                assert!(apart > Some(8), "the map must change the picture");
            }
        }
    }
);

gpu_test!(
    #[test]
    fn occlusion_and_emissive_textures_scale_by_their_strengths() {
        let r = renderer();
        let view = view();
        let size = 65;
        // R = 0.4 occlusion, and an sRGB emissive colour, from one image (channels apart).
        let texel = [102u8, 200, 60, 255];
        let material = Material {
            base_color_factor: [0.5, 0.5, 0.5, 1.0],
            metallic_factor: 0.0,
            roughness_factor: 0.7,
            occlusion_texture: tex(0, None),
            occlusion_strength: 0.5,
            emissive_texture: tex(0, None),
            emissive_factor: [0.5, 0.25, 1.0],
            emissive_strength: 2.0,
            ..Material::default()
        };
        let ao = 1.0 + 0.5 * (f32::from(texel[0]) / 255.0 - 1.0);
        let emissive = Vec3::new(0.5, 0.25, 1.0)
            * 2.0
            * Vec3::from_array([texel[0], texel[1], texel[2]].map(brdf::srgb8_to_linear));
        let s = Surface {
            occlusion: ao,
            emissive,
            ..surface(&material)
        };
        let appearance = with_image(vec![material], mips(4, 4, |_, _| texel), Sampler::default());
        let rig = rig(vec![quad("quad", 1.0, Some(0))], Some(appearance));
        let rgba = render(&r, &rig, &[Mat4::IDENTITY], &view, size);
        let want = expected(&view, &s, Vec3::ZERO, Vec3::Z);
        let got = pixel(&rgba, size, 32, 32);
        assert!(max_delta(got, want) <= 3, "{got:?} vs {want:?}");
    }
);

/// Renders `rig` once at `size`² with the layer inputs of `pose` at LOD 0 (what the crowd
/// path gives each job's draw).
fn render_posed(r: &Renderer, rig: &Rig, pose: &crowdmorph::rig::Pose, size: u32) -> Vec<u8> {
    let topology = r.topology(rig).expect("topology");
    let data = neutral(rig);
    let layers = crowdmorph::rig::layer_inputs(rig, pose, 0);
    let mesh = SceneMesh {
        topology: &topology,
        positions: VertexSource::Host(&data.0),
        normals: VertexSource::Host(&data.1),
        instances: &[Mat4::IDENTITY],
        layers: &layers,
    };
    r.render(&[mesh], &view(), &frame(size))
        .expect("render")
        .rgba
}

/// The quad rig of [`rig`] with weight channels `targets` and clips `clips`.
fn layered_rig(appearance: Appearance, targets: &[&str], clips: Vec<crowdmorph::rig::Clip>) -> Rig {
    let mut r = rig(vec![quad("quad", 1.0, Some(0))], Some(appearance));
    r.targets = targets.iter().map(|t| t.to_string()).collect();
    r.default_weights = vec![0.0; targets.len()];
    r.lod = Lod::file_order(targets.len());
    r.clips = clips;
    r.validate().expect("a valid layered rig");
    r
}

/// The wrinkle texture's colours: unlike the checker's, so a layer that is not summed shows.
fn wrinkle_checker(x: u32, y: u32) -> [u8; 4] {
    if (x / 4 + y / 4).is_multiple_of(2) {
        [90, 200, 120, 255]
    } else {
        [240, 230, 40, 255]
    }
}

gpu_test!(
    #[test]
    fn a_wrinkle_map_fades_in_with_its_targets_weight() {
        use crowdmorph::rig::{Pose, TargetTexture};
        let r = renderer();
        let size = 129;
        let mut appearance = with_image(
            vec![Material {
                base_color_texture: tex(0, None),
                unlit: true,
                ..Material::default()
            }],
            mips(16, 16, checker),
            Sampler::default(),
        );
        appearance.textures.push(Texture {
            sampler: Some(0),
            image: Some(1),
        });
        let mut wrinkle = appearance.images[0].clone();
        wrinkle.pixels = Some(Arc::new(mips(16, 16, wrinkle_checker)));
        appearance.images.push(wrinkle);
        appearance.target_textures.push(TargetTexture {
            material: 0,
            target: "browInnerUp".into(),
            texture: TexRef {
                texture: 1,
                tex_coord: 0,
                transform: None,
            },
        });
        let rig = layered_rig(appearance, &["jawOpen", "browInnerUp"], Vec::new());
        for w in [0.0f32, 0.5, 1.0] {
            // The other channel's weight must not move the layer.
            let rgba = render_posed(&r, &rig, &Pose::live(&[0.7, w]), size);
            for (i, j) in (0..4).flat_map(|i| (0..4).map(move |j| (i, j))) {
                let uv = Vec2::new((4 * i + 2) as f32 / 16.0, (4 * j + 2) as f32 / 16.0);
                let (x, y) = pixel_at_uv(size, uv);
                let (b, k) = (checker(4 * i, 4 * j), wrinkle_checker(4 * i, 4 * j));
                // The reference: linear interpolation of the two textures' linear colours,
                // which is what base + w·(wrinkle − base) is.
                let want = [0, 1, 2].map(|c| {
                    let (b, k) = (brdf::srgb8_to_linear(b[c]), brdf::srgb8_to_linear(k[c]));
                    brdf::linear_to_srgb8(b + w * (k - b))
                });
                let got = pixel(&rgba, size, x, y);
                // The layer is stored in binary16 (within 2^-11 of its value) and the target
                // rounds once: 2 units of 8 bits covers both at any brightness here.
                assert!(
                    max_delta(got, want) <= 2,
                    "weight {w}, cell ({i}, {j}): {got:?}, want {want:?}"
                );
            }
        }
    }
);

/// An image sequence that is constant over each 4 × 4 cell of a 16 × 16 texture (so a
/// pixel at a cell's centre samples one value whatever the filter): a static colour per cell,
/// the top row of cells blinking and the third changing with a second rhythm.
fn cell_frames(frames: u32) -> Vec<Vec<f32>> {
    (0..frames)
        .map(|f| {
            let blink = ((f as f32) * 0.9).sin().abs();
            let talk = 0.5 + 0.5 * ((f as f32) * 0.37).cos();
            let mut out = Vec::with_capacity(16 * 16 * 3);
            for y in 0..16u32 {
                for x in 0..16u32 {
                    let (i, j) = (x / 4, y / 4);
                    for c in 0..3u32 {
                        let base = 0.1 + 0.05 * (i + 2 * j + c) as f32;
                        let v = match j {
                            0 => base + 0.5 * blink * ((i + c) % 2) as f32,
                            2 => base + 0.4 * talk * ((i * 3 + c) % 3) as f32 / 2.0,
                            _ => base,
                        };
                        out.push(v);
                    }
                }
            }
            out
        })
        .collect()
}

gpu_test!(
    #[test]
    fn a_clips_animated_texture_draws_its_pca_decode_at_each_frame() {
        use crowdmorph::rig::{Clip, Pose, TextureRegion};
        let r = renderer();
        let size = 129;
        let frames = 12;
        let seq = cell_frames(frames);
        let regions = vec![
            TextureRegion {
                name: "eyes".into(),
                rect: [0, 0, 16, 4],
                components: 3,
            },
            TextureRegion {
                name: "rest".into(),
                rect: [0, 0, 16, 16],
                components: 2,
            },
        ];
        let t = crowdmorph::texture::compress("talk", 0, 16, 16, &seq, &regions).expect("compress");
        // The base colour texture the mean replaces: the checker, so the mean's layer is a
        // real difference.
        let mut appearance = with_image(
            vec![Material {
                base_color_texture: tex(0, None),
                unlit: true,
                ..Material::default()
            }],
            mips(16, 16, checker),
            Sampler::default(),
        );
        appearance.clip_textures.push(Arc::new(t.clone()));
        let clip = Clip {
            name: "talk".into(),
            fps: 30.0,
            frames,
            targets: 1,
            weights: Arc::new(vec![0.0; frames as usize]),
            joints: None,
        };
        let rig = layered_rig(appearance, &["jawOpen"], vec![clip]);
        for f in [0, 5, 11] {
            let rgba = render_posed(&r, &rig, &Pose::Frame { clip: 0, frame: f }, size);
            let decoded = t.decode(f);
            for (i, j) in (0..4).flat_map(|i| (0..4).map(move |j| (i, j))) {
                let uv = Vec2::new((4 * i + 2) as f32 / 16.0, (4 * j + 2) as f32 / 16.0);
                let (x, y) = pixel_at_uv(size, uv);
                let texel = ((4 * j + 2) * 16 + 4 * i + 2) as usize;
                let want = [0, 1, 2].map(|c| brdf::linear_to_srgb8(decoded[3 * texel + c] as f32));
                let got = pixel(&rgba, size, x, y);
                // Mean − base and each component are binary16 (2^-11 relative); the
                // coefficients are f32: a few thousandths in linear at most, 2 units of 8 bits.
                assert!(
                    max_delta(got, want) <= 2,
                    "frame {f}, cell ({i}, {j}): {got:?}, want {want:?}"
                );
            }
        }
        // A blend of two frames draws the blend of their decodes (the same fractions as the
        // weights).
        let pose = Pose::blend((0, 2), &[(0, 9, 0.25)]);
        let rgba = render_posed(&r, &rig, &pose, size);
        let (a, b) = (t.decode(2), t.decode(9));
        let (x, y) = pixel_at_uv(size, Vec2::new(2.0 / 16.0, 2.0 / 16.0));
        let texel = (2 * 16 + 2) as usize;
        let want = [0, 1, 2].map(|c| {
            brdf::linear_to_srgb8((0.75 * a[3 * texel + c] + 0.25 * b[3 * texel + c]) as f32)
        });
        assert!(max_delta(pixel(&rgba, size, x, y), want) <= 2);
    }
);

gpu_test!(
    #[test]
    fn a_wrinkle_map_from_gltf_extras_is_imported_and_drawn_end_to_end() {
        use crate::util::wrinkle::{png, wrinkle_glb};
        use crowdmorph::import::ImportOptions;
        use crowdmorph::import::gltf::rig_from_slice;
        use crowdmorph::rig::Pose;
        use serde_json::json;
        let (base, wrinkle) = ([200u8, 60, 30], [20u8, 120, 230]);
        // A quad with TEXCOORD_0 and a target `brow` that barely moves it (toward the
        // camera).
        let glb = wrinkle_glb(&png(4, 4, |_, _| base), &png(4, 4, |_, _| wrinkle), 0.01);
        let rig = rig_from_slice(&glb, &ImportOptions::default()).expect("import");
        let a = rig.appearance.as_deref().expect("an appearance");
        assert_eq!(a.target_textures.len(), 2);
        assert_eq!(a.target_textures[0].target, "brow");
        assert!(
            rig.import_notes
                .iter()
                .any(|n| n.contains("noSuchTarget") && n.contains("not drawn")),
            "{:?}",
            rig.import_notes
        );
        assert!(a.images.iter().all(|i| i.pixels.is_some()), "both decoded");
        // The convention goes back out in the materials' JSON.
        let j = a.gltf_json(|_, _| json!({}));
        assert_eq!(
            j["materials"][0]["extras"]["crowdmorph"]["targetTextures"][0]["target"],
            "brow"
        );
        let r = renderer();
        let size = 65;
        for w in [0.0f32, 0.5, 1.0] {
            let rgba = render_posed(&r, &rig, &Pose::live(&[w]), size);
            let got = pixel(&rgba, size, size / 2, size / 2);
            for c in 0..3 {
                let (b, k) = (
                    brdf::srgb8_to_linear(base[c]),
                    brdf::srgb8_to_linear(wrinkle[c]),
                );
                let want = b + w * (k - b);
                // The base is decoded by the sampler's sRGB view, the layer (wrinkle − base)
                // on the host, so the sum carries any difference between the two decodes of
                // the base, plus the layer's binary16 rounding (≤ 2.4e-4 at 0.57): measured on
                // lavapipe, red went 200 → 20 as 17, 1.4e-3 in linear, which at a dark result
                // (the curve is steep there) is 3 units of 8 bits. Allowed: 2 units, or what
                // ±1.5e-3 linear spans around the value.
                let span = brdf::linear_to_srgb8(want + 1.5e-3)
                    .abs_diff(brdf::linear_to_srgb8((want - 1.5e-3).max(0.0)));
                let tolerance = 2.max(span / 2 + 1);
                let diff = got[c].abs_diff(brdf::linear_to_srgb8(want));
                assert!(
                    diff <= tolerance,
                    "weight {w}, channel {c}: {got:?}, want {} ± {tolerance}",
                    brdf::linear_to_srgb8(want)
                );
            }
        }
    }
);
