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
