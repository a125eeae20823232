//! The GPU renderer (`crowdmorph::render::gpu`) on a real device — lavapipe in CI and on
//! machines without a GPU. Each test opens its own device.
//!
//! Two kinds of checks: golden images (the embedded head from the front, a 3×3 crowd of
//! instances), compared with a tolerance (`util::image`) and rewritten by
//! `CROWDMORPH_BLESS=1 cargo test --locked render`; and behaviour checks that need no golden
//! (coverage where the head is and background where it is not, device and host vertex sources
//! agreeing, instances at their transforms, normals mattering, mesh levels close to the full
//! mesh, bad input refused, concurrent renders, the GPU budget and kept targets giving way).

use crate::util::gpu_test;
use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

use crowdmorph::engine::gpu::GpuOptions;
use crowdmorph::engine::{BlendJob, Engine, OutputSpec, Precision, PreparedRig};
use crowdmorph::lod::{LodSpec, OrderMethod, build_lod};
use crowdmorph::render::gpu::{
    Frame, MeshTopology, RenderError, RenderOutput, Renderer, SceneMesh, VertexSource, View,
};
use crowdmorph::rig::{Rig, mesh_level_rigs};
use glam::{Mat4, Vec3};

use crate::util::image::{Image, Tolerance, check_golden, compare};
use crate::util::open_gpu;

/// sRGB background of the tests: exact 8-bit values, so a cleared pixel reads back exactly.
const BG: [u8; 3] = [40, 48, 64];

fn frame(width: u32, height: u32) -> Frame {
    Frame {
        width,
        height,
        background: BG.map(|c| f32::from(c) / 255.0),
    }
}

fn renderer() -> Renderer {
    Renderer::new(Arc::new(open_gpu(GpuOptions::default()))).expect("renderer")
}

fn golden(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/golden/render")
        .join(name)
}

/// Goldens come from lavapipe and are compared on lavapipe, where they match exactly; the
/// tolerance absorbs a few MSAA edge samples and last-bit shading after a Mesa or LLVM update.
const GOLDEN: Tolerance = Tolerance {
    per_pixel: 8,
    max_fraction: 0.005,
};

fn image(out: &RenderOutput) -> Image {
    Image::new(out.width, out.height, out.rgba.clone())
}

/// The embedded head, prepared for the CPU engine, once per run.
fn head() -> &'static (Arc<Rig>, PreparedRig) {
    static HEAD: OnceLock<(Arc<Rig>, PreparedRig)> = OnceLock::new();
    HEAD.get_or_init(|| {
        let rig = Arc::new(crowdmorph::embedded::default_rig());
        let prepared = Engine::cpu().prepare(rig.clone()).expect("prepare");
        (rig, prepared)
    })
}

/// Positions and normals of one job of a prepared rig, from the CPU engine.
fn evaluate(prepared: &PreparedRig, clip: &str, frame: u32) -> (Vec<f32>, Vec<f32>) {
    let clip = prepared
        .rig()
        .clips
        .iter()
        .position(|c| c.name == clip)
        .expect("clip") as u32;
    let out = Engine::cpu()
        .evaluate(
            prepared,
            &[BlendJob::frame(clip, frame, 0)],
            OutputSpec {
                normals: true,
                precision: Precision::F32,
            },
        )
        .expect("evaluate")
        .output;
    (out.job_positions(0), out.job_normals(0).expect("normals"))
}

/// A front view (the face looks toward +Z) framing a box of `size` around `center`.
fn front_view(center: Vec3, size: f32) -> View {
    let fov = 30.0f32;
    let distance = size * 0.5 / (fov.to_radians() * 0.5).tan() * 1.1;
    View {
        eye: center + Vec3::Z * distance,
        target: center,
        up: Vec3::Y,
        fov_y_deg: fov,
        near: distance * 0.1,
        far: distance * 10.0,
    }
}

fn head_view(rig: &Rig) -> View {
    let b = rig.bbox();
    front_view(
        (b.min + b.max) * 0.5,
        (b.max - b.min).truncate().max_element(),
    )
}

fn host<'a>(
    topology: &'a MeshTopology,
    data: &'a (Vec<f32>, Vec<f32>),
    instances: &'a [Mat4],
) -> SceneMesh<'a> {
    SceneMesh {
        topology,
        positions: VertexSource::Host(&data.0),
        normals: VertexSource::Host(&data.1),
        instances,
        layers: &[],
    }
}

fn is_bg(p: [u8; 4]) -> bool {
    p == [BG[0], BG[1], BG[2], 255]
}

/// Pixels in the rectangle `[x0, x1) × [y0, y1)` that are not background.
fn covered(img: &Image, x0: u32, x1: u32, y0: u32, y1: u32) -> usize {
    (y0..y1)
        .flat_map(|y| (x0..x1).map(move |x| (x, y)))
        .filter(|&(x, y)| !is_bg(img.pixel(x, y)))
        .count()
}

#[test]
fn renderer_is_send_and_sync() {
    fn shared<T: Send + Sync>() {}
    shared::<Renderer>();
    shared::<MeshTopology>();
}

gpu_test!(
    #[test]
    fn no_meshes_render_the_background_exactly() {
        let r = renderer();
        let (rig, _) = head();
        let out = r
            .render(&[], &head_view(rig), &frame(70, 33))
            .expect("render");
        // 70 × 4 bytes is not a multiple of 256: the padding of the copy is stripped.
        assert_eq!((out.width, out.height), (70, 33));
        assert_eq!(out.rgba.len(), 70 * 33 * 4);
        assert!(
            out.rgba
                .chunks_exact(4)
                .all(|p| p == [BG[0], BG[1], BG[2], 255]),
            "background is exactly {BG:?}"
        );
        // A mesh with no instances draws nothing either.
        let topology = r.topology(rig).expect("topology");
        let data = evaluate(&head().1, "talk", 0);
        let out = r
            .render(
                &[host(&topology, &data, &[])],
                &head_view(rig),
                &frame(70, 33),
            )
            .expect("render");
        assert!(
            out.rgba
                .chunks_exact(4)
                .all(|p| is_bg([p[0], p[1], p[2], p[3]]))
        );
    }
);

gpu_test!(
    #[test]
    fn topology_counts_the_rig() {
        let r = renderer();
        let (rig, _) = head();
        let t = r.topology(rig).expect("topology");
        assert_eq!(t.vertices() as usize, rig.vertex_count());
        assert_eq!(t.triangles() as usize, rig.triangle_count());
        assert!(t.bytes() >= u64::from(t.triangles()) * 12);
    }
);

gpu_test!(
    #[test]
    fn the_embedded_head_from_the_front_matches_its_golden_image() {
        let r = renderer();
        let (rig, prepared) = head();
        let topology = r.topology(rig).expect("topology");
        let data = evaluate(prepared, "talk", 12);
        let out = r
            .render(
                &[host(&topology, &data, &[Mat4::IDENTITY])],
                &head_view(rig),
                &frame(256, 256),
            )
            .expect("render");
        eprintln!(
            "256×256 head on {}: render {} µs, readback {} µs",
            r.adapter().name,
            out.render_ns / 1000,
            out.readback_ns / 1000
        );
        check_golden(&golden("head_front.png"), &image(&out), GOLDEN);
    }
);

gpu_test!(
    #[test]
    fn a_crowd_of_instances_matches_its_golden_image() {
        let r = renderer();
        let (rig, prepared) = head();
        let topology = r.topology(rig).expect("topology");
        // Three unique buffers, each drawn by three heads: nine instances, one per grid cell,
        // each clip's heads on a diagonal-ish pattern so neighbours differ.
        let jobs = [("talk", 12), ("smile", 40), ("surprise", 20)];
        let data: Vec<_> = jobs
            .iter()
            .map(|&(clip, f)| evaluate(prepared, clip, f))
            .collect();
        let b = rig.bbox();
        let center = (b.min + b.max) * 0.5;
        let spacing = (b.max - b.min).truncate().max_element() * 1.1;
        let mut instances: Vec<Vec<Mat4>> = vec![Vec::new(); 3];
        for row in 0..3 {
            for col in 0..3 {
                let offset = Vec3::new(
                    (col as f32 - 1.0) * spacing,
                    (1.0 - row as f32) * spacing,
                    0.0,
                );
                // Turn each head a little toward the middle, so the model matrices are not only
                // translations.
                let turn = Mat4::from_rotation_y(-(col as f32 - 1.0) * 0.25);
                let model = Mat4::from_translation(offset + center)
                    * turn
                    * Mat4::from_translation(-center);
                instances[(row + col) % 3].push(model);
            }
        }
        let meshes: Vec<SceneMesh<'_>> = data
            .iter()
            .zip(&instances)
            .map(|(d, inst)| host(&topology, d, inst))
            .collect();
        let view = front_view(center, spacing * 3.0);
        let out = r.render(&meshes, &view, &frame(256, 256)).expect("render");
        let img = image(&out);
        check_golden(&golden("crowd_3x3.png"), &img, GOLDEN);
        // The same crowd cut into render passes (a pass per instance, then passes that split a
        // mesh's instances) is the same picture: samples and depth carry over between passes.
        let default_pass = r.pass_triangles();
        for per_pass in [
            u64::from(topology.triangles()),
            u64::from(topology.triangles()) * 2 + 1,
        ] {
            r.set_pass_triangles(per_pass);
            let passes = r
                .render(&meshes, &view, &frame(256, 256))
                .expect("render in passes");
            assert!(
                image(&passes) == img,
                "{per_pass} triangles a pass draws the single pass's picture"
            );
        }
        r.set_pass_triangles(default_pass);
        // Every cell has a head in its middle.
        for row in 0..3u32 {
            for col in 0..3u32 {
                let (cx, cy) = (col * 256 / 3 + 256 / 6, row * 256 / 3 + 256 / 6);
                assert!(
                    covered(&img, cx - 5, cx + 5, cy - 5, cy + 5) == 100,
                    "cell {row},{col} is covered in the middle"
                );
            }
        }
    }
);

gpu_test!(
    #[test]
    fn a_head_fills_the_middle_of_the_frame_and_not_the_corners() {
        let r = renderer();
        let (rig, prepared) = head();
        let topology = r.topology(rig).expect("topology");
        let data = evaluate(prepared, "idle", 0);
        let (w, h) = (160, 120);
        let out = r
            .render(
                &[host(&topology, &data, &[Mat4::IDENTITY])],
                &head_view(rig),
                &frame(w, h),
            )
            .expect("render");
        let img = image(&out);
        // The middle fifth is all head; 8-pixel corners are all background.
        let (mx, my) = (w / 5, h / 5);
        let middle = covered(
            &img,
            w / 2 - mx / 2,
            w / 2 + mx / 2,
            h / 2 - my / 2,
            h / 2 + my / 2,
        );
        assert_eq!(
            middle,
            (mx / 2 * 2 * (my / 2 * 2)) as usize,
            "middle covered"
        );
        for (x0, y0) in [(0, 0), (w - 8, 0), (0, h - 8), (w - 8, h - 8)] {
            assert_eq!(covered(&img, x0, x0 + 8, y0, y0 + 8), 0, "corner {x0},{y0}");
        }
        // The skin tone shows: red above green above blue in the middle, opaque.
        let p = img.pixel(w / 2, h / 2 + h / 10);
        assert!(
            p[0] > p[1] && p[1] > p[2] && p[3] == 255,
            "skin tone: {p:?}"
        );
    }
);

gpu_test!(
    #[test]
    fn a_device_vertex_buffer_renders_like_the_same_data_from_the_host() {
        let ctx = Arc::new(open_gpu(GpuOptions::default()));
        let r = Renderer::new(ctx.clone()).expect("renderer");
        let (rig, prepared) = head();
        let topology = r.topology(rig).expect("topology");
        let data = evaluate(prepared, "smile", 30);
        // Positions from byte 256 and normals right after them, as the GPU engine lays out jobs in
        // one output buffer.
        let bytes = (data.0.len() * 4) as u64;
        let buffer = ctx.device().create_buffer(&wgpu::BufferDescriptor {
            label: Some("test vertices"),
            size: 256 + 2 * bytes,
            usage: wgpu::BufferUsages::VERTEX | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        ctx.queue()
            .write_buffer(&buffer, 256, bytemuck::cast_slice(&data.0));
        ctx.queue()
            .write_buffer(&buffer, 256 + bytes, bytemuck::cast_slice(&data.1));
        let instances = [Mat4::IDENTITY, Mat4::from_translation(Vec3::X * 30.0)];
        let b = rig.bbox();
        let view = front_view((b.min + b.max) * 0.5 + Vec3::X * 15.0, 60.0);
        let from_host = r
            .render(
                &[host(&topology, &data, &instances)],
                &view,
                &frame(200, 100),
            )
            .expect("host render");
        let from_device = r
            .render(
                &[SceneMesh {
                    topology: &topology,
                    positions: VertexSource::Device {
                        buffer: &buffer,
                        offset: 256,
                    },
                    normals: VertexSource::Device {
                        buffer: &buffer,
                        offset: 256 + bytes,
                    },
                    instances: &instances,
                    layers: &[],
                }],
                &view,
                &frame(200, 100),
            )
            .expect("device render");
        assert!(covered(&image(&from_host), 0, 200, 0, 100) > 800);
        assert!(
            from_host.rgba == from_device.rgba,
            "device and host sources differ: {}",
            compare(&image(&from_device), &image(&from_host), 0).expect("same size")
        );
        // Mixed: positions on the device, normals from the host.
        let mixed = r
            .render(
                &[SceneMesh {
                    topology: &topology,
                    positions: VertexSource::Device {
                        buffer: &buffer,
                        offset: 256,
                    },
                    normals: VertexSource::Host(&data.1),
                    instances: &instances,
                    layers: &[],
                }],
                &view,
                &frame(200, 100),
            )
            .expect("mixed render");
        assert!(mixed.rgba == from_host.rgba);
    }
);

gpu_test!(
    #[test]
    fn two_instances_appear_at_both_places() {
        let r = renderer();
        let (rig, prepared) = head();
        let topology = r.topology(rig).expect("topology");
        let data = evaluate(prepared, "talk", 5);
        let b = rig.bbox();
        let center = (b.min + b.max) * 0.5;
        let size = (b.max - b.min).truncate().max_element();
        // The frame is 4.5 head sizes wide: thirds of 1.5 sizes, a head in the middle of each.
        let view = front_view(center, size * 1.5);
        let (w, h) = (300, 100);
        let render = |instances: &[Mat4]| {
            image(
                &r.render(&[host(&topology, &data, instances)], &view, &frame(w, h))
                    .expect("render"),
            )
        };
        let left = Mat4::from_translation(Vec3::X * -1.5 * size);
        let right = Mat4::from_translation(Vec3::X * 1.5 * size);
        let one = render(&[Mat4::IDENTITY]);
        let two = render(&[left, right]);
        let third = |img: &Image, k: u32| covered(img, k * w / 3, (k + 1) * w / 3, 0, h);
        // One head at the identity: the middle third only.
        assert!(third(&one, 1) > 1000 && third(&one, 0) == 0 && third(&one, 2) == 0);
        // Two heads, 1.5 head sizes to each side: the outer thirds, and nothing in the middle
        // column between them.
        assert!(third(&two, 0) > 1000 && third(&two, 2) > 1000);
        assert_eq!(covered(&two, w / 2 - 2, w / 2 + 2, 0, h), 0);
        // Each instance looks like the head moved, not like a different picture: the left head's
        // coverage mirrors the right one's in pixel count (the rig is left/right symmetric and the
        // view is centred).
        let (l, rr) = (third(&two, 0) as f64, third(&two, 2) as f64);
        assert!((l - rr).abs() / l < 0.05, "left {l} vs right {rr}");
    }
);

gpu_test!(
    #[test]
    fn flipped_normals_change_the_shading_but_not_the_coverage() {
        let r = renderer();
        let (rig, prepared) = head();
        let topology = r.topology(rig).expect("topology");
        let data = evaluate(prepared, "idle", 0);
        let flipped = (
            data.0.clone(),
            data.1.iter().map(|n| -n).collect::<Vec<f32>>(),
        );
        let view = head_view(rig);
        let render = |d: &(Vec<f32>, Vec<f32>)| {
            image(
                &r.render(
                    &[host(&topology, d, &[Mat4::IDENTITY])],
                    &view,
                    &frame(128, 128),
                )
                .expect("render"),
            )
        };
        let (a, b) = (render(&data), render(&flipped));
        let mask = |img: &Image| -> Vec<bool> {
            img.rgba
                .chunks_exact(4)
                .map(|p| !is_bg([p[0], p[1], p[2], p[3]]))
                .collect()
        };
        assert_eq!(mask(&a), mask(&b), "normals do not move geometry");
        let brightness = |img: &Image| -> f64 {
            let m = mask(img);
            let (sum, n) = img.rgba.chunks_exact(4).zip(&m).filter(|(_, c)| **c).fold(
                (0u64, 0u64),
                |(s, n), (p, _)| {
                    (
                        s + u64::from(p[0]) + u64::from(p[1]) + u64::from(p[2]),
                        n + 1,
                    )
                },
            );
            sum as f64 / n.max(1) as f64
        };
        let (lit, dark) = (brightness(&a), brightness(&b));
        // Facing away from both lights leaves the ambient term alone.
        assert!(dark < lit * 0.7, "flipped {dark} vs {lit}");
    }
);

gpu_test!(
    #[test]
    fn a_mesh_level_renders_close_to_the_full_mesh() {
        let mut rig = crowdmorph::embedded::default_rig();
        let spec = LodSpec {
            method: OrderMethod::FileOrder,
            mesh_fractions: vec![0.5],
            ..LodSpec::default()
        };
        rig.lod = build_lod(&rig, &spec, None, None).expect("lod");
        let level = Arc::new(mesh_level_rigs(&rig).expect("mesh levels").remove(0));
        let rig = Arc::new(rig);
        let engine = Engine::cpu();
        let full = evaluate(&engine.prepare(rig.clone()).expect("prepare"), "talk", 12);
        let reduced = evaluate(&engine.prepare(level.clone()).expect("prepare"), "talk", 12);

        let r = renderer();
        let full_topology = r.topology(&rig).expect("topology");
        let level_topology = r.topology(&level).expect("level topology");
        assert!(level_topology.vertices() < full_topology.vertices());
        assert!(level_topology.triangles() * 3 < full_topology.triangles() * 2);
        let view = head_view(&rig);
        let render = |t: &MeshTopology, d: &(Vec<f32>, Vec<f32>)| {
            image(
                &r.render(&[host(t, d, &[Mat4::IDENTITY])], &view, &frame(256, 256))
                    .expect("render"),
            )
        };
        let a = render(&full_topology, &full);
        let b = render(&level_topology, &reduced);
        // The full mesh's vertex data does not fit the level's topology.
        assert!(matches!(
            r.render(
                &[host(&level_topology, &full, &[Mat4::IDENTITY])],
                &view,
                &frame(8, 8)
            ),
            Err(RenderError::Invalid(_))
        ));
        let c = compare(&b, &a, 24).expect("same size");
        eprintln!("mesh level at 50 % vs full mesh: {c}");
        assert!(c.fraction() < 0.02, "{c}");
        assert!(covered(&b, 0, 256, 0, 256) > 20_000);
    }
);

gpu_test!(
    #[test]
    fn bad_input_is_an_error_not_a_panic() {
        let ctx = Arc::new(open_gpu(GpuOptions::default()));
        let r = Renderer::new(ctx.clone()).expect("renderer");
        let (rig, prepared) = head();
        let topology = r.topology(rig).expect("topology");
        let data = evaluate(prepared, "talk", 0);
        let view = head_view(rig);
        let one = [Mat4::IDENTITY];
        let good = host(&topology, &data, &one);
        let invalid = |result: Result<RenderOutput, RenderError>, what: &str| match result {
            Err(RenderError::Invalid(msg)) => eprintln!("{what}: {msg}"),
            other => panic!("{what}: expected Invalid, got {:?}", other.map(|o| o.width)),
        };
        let too_large = |result: Result<RenderOutput, RenderError>, what: &str| match result {
            Err(RenderError::TooLarge(msg)) => eprintln!("{what}: {msg}"),
            other => panic!(
                "{what}: expected TooLarge, got {:?}",
                other.map(|o| o.width)
            ),
        };

        let short = &data.0[..data.0.len() - 3];
        let mut m = good;
        m.positions = VertexSource::Host(short);
        invalid(r.render(&[m], &view, &frame(8, 8)), "short host positions");
        let mut m = good;
        m.normals = VertexSource::Host(&data.1[..6]);
        invalid(r.render(&[m], &view, &frame(8, 8)), "short host normals");
        invalid(r.render(&[good], &view, &frame(0, 8)), "width 0");
        invalid(r.render(&[good], &view, &frame(8, 0)), "height 0");
        let max = r.max_size();
        too_large(
            r.render(&[good], &view, &frame(max + 1, 8)),
            "width past max_size",
        );
        too_large(
            r.render(&[], &view, &frame(8, max + 1)),
            "height past max_size",
        );
        let mut f = frame(8, 8);
        f.background[1] = f32::NAN;
        invalid(r.render(&[], &view, &f), "NaN background");
        let bad_view = View {
            target: view.eye,
            ..view
        };
        invalid(
            r.render(&[good], &bad_view, &frame(8, 8)),
            "eye at the target",
        );
        let nan = [Mat4::from_translation(Vec3::new(f32::NAN, 0.0, 0.0))];
        invalid(
            r.render(&[host(&topology, &data, &nan)], &view, &frame(8, 8)),
            "NaN model matrix",
        );

        // Device buffers: too short from the offset, misaligned, without VERTEX usage.
        let bytes = (data.0.len() * 4) as u64;
        let make = |size: u64, usage: wgpu::BufferUsages| {
            ctx.device().create_buffer(&wgpu::BufferDescriptor {
                label: Some("test"),
                size,
                usage,
                mapped_at_creation: false,
            })
        };
        let vertex = make(bytes + 16, wgpu::BufferUsages::VERTEX);
        let storage = make(bytes, wgpu::BufferUsages::STORAGE);
        for (buffer, offset, what) in [
            (
                &vertex,
                32,
                "device buffer shorter than the topology from the offset",
            ),
            (&vertex, 2, "misaligned offset"),
            (&vertex, u64::MAX - 3, "offset overflowing"),
            (&storage, 0, "buffer without VERTEX usage"),
        ] {
            let mut m = good;
            m.positions = VertexSource::Device { buffer, offset };
            invalid(r.render(&[m], &view, &frame(8, 8)), what);
        }

        // A topology from another device.
        let other = Renderer::new(Arc::new(open_gpu(GpuOptions::default()))).expect("renderer");
        let foreign = other.topology(rig).expect("topology");
        invalid(
            r.render(&[host(&foreign, &data, &one)], &view, &frame(8, 8)),
            "topology from another device",
        );

        // None of that hurt the renderer or the device the GPU engine shares.
        ctx.health().expect("device healthy");
        let out = r.render(&[good], &view, &frame(32, 32)).expect("render");
        assert!(covered(&image(&out), 0, 32, 0, 32) > 100);
    }
);

gpu_test!(
    #[test]
    fn renders_from_two_threads_at_once_match_renders_from_one() {
        let r = renderer();
        let (rig, prepared) = head();
        let topology = r.topology(rig).expect("topology");
        let poses = [
            evaluate(prepared, "talk", 3),
            evaluate(prepared, "smile", 20),
        ];
        let view = head_view(rig);
        // Different sizes per thread, so the pooled targets are contended and replaced.
        let sizes = [(96, 64), (64, 96)];
        let render = |k: usize| {
            let (w, h) = sizes[k];
            r.render(
                &[host(&topology, &poses[k], &[Mat4::IDENTITY])],
                &view,
                &frame(w, h),
            )
            .expect("render")
            .rgba
        };
        let alone = [render(0), render(1)];
        std::thread::scope(|s| {
            let threads: Vec<_> = (0..2)
                .map(|k| {
                    let render = &render;
                    let want = &alone[k];
                    s.spawn(move || {
                        for _ in 0..6 {
                            assert!(render(k) == *want, "thread {k} rendered something else");
                        }
                    })
                })
                .collect();
            for t in threads {
                t.join().expect("render thread");
            }
        });
    }
);

gpu_test!(
    #[test]
    fn the_gpu_engine_outputs_are_drawn_where_they_are() {
        // The GPU engine and the renderer share one device: the blended buffers of
        // `evaluate_for_render` go straight into the draw, never through the host. The picture
        // equals the one drawn from the CPU engine's host arrays.
        use crowdmorph::engine::{BackendChoice, RenderBuffers};
        let engine = Engine::with_gpu(open_gpu(GpuOptions::default()), BackendChoice::Gpu);
        let renderer = Renderer::new(engine.gpu_shared().expect("gpu")).expect("renderer");
        let (rig, cpu_prepared) = head();
        let prepared = engine.prepare(rig.clone()).expect("upload");
        let talk = rig.clip_index("talk").expect("talk") as u32;
        let jobs: Vec<BlendJob> = [3u32, 17, 29]
            .iter()
            .map(|&frame| BlendJob::frame(talk, frame, 0))
            .collect();
        let (buffers, _) = engine
            .evaluate_for_render(&prepared, &jobs)
            .expect("evaluate");
        let RenderBuffers::Device(out) = buffers else {
            panic!("a healthy GPU engine leaves render outputs on the device");
        };
        let topology = renderer.topology(rig).expect("topology");
        let normals = out.normals.as_ref().expect("normals");
        let spacing = (rig.bbox().max - rig.bbox().min).x * 1.2;
        let instances: Vec<[Mat4; 1]> = (0..3)
            .map(|i| [Mat4::from_translation(Vec3::X * spacing * (i as f32 - 1.0))])
            .collect();
        let device: Vec<SceneMesh<'_>> = (0..3)
            .map(|j| SceneMesh {
                topology: &topology,
                positions: VertexSource::Device {
                    buffer: &out.positions,
                    offset: out.offset(j),
                },
                normals: VertexSource::Device {
                    buffer: normals,
                    offset: out.offset(j),
                },
                instances: &instances[j],
                layers: &[],
            })
            .collect();
        let b = rig.bbox();
        // A 3:1 frame: the view spans one spacing vertically, three across.
        let view = front_view((b.min + b.max) * 0.5, spacing * 1.1);
        let drawn = renderer
            .render(&device, &view, &frame(384, 128))
            .expect("render");
        assert!(
            !engine.info().degraded,
            "{:?}",
            engine.info().degraded_reason
        );

        let host_data: Vec<(Vec<f32>, Vec<f32>)> = [3u32, 17, 29]
            .iter()
            .map(|&f| evaluate(cpu_prepared, "talk", f))
            .collect();
        let from_host: Vec<SceneMesh<'_>> = (0..3)
            .map(|j| host(&topology, &host_data[j], &instances[j]))
            .collect();
        let reference = renderer
            .render(&from_host, &view, &frame(384, 128))
            .expect("render");
        let c = compare(&image(&drawn), &image(&reference), 8).expect("same size");
        assert!(c.fraction() <= 0.002, "{} of pixels differ", c.fraction());
        assert!(covered(&image(&drawn), 0, 384, 0, 128) > 384 * 128 / 10);
    }
);

/// How long [`collect_mappings_elsewhere`]'s other thread holds back the mapping callbacks it
/// collected: long enough that the waiting thread looks while they have not run (it looks
/// within microseconds), not a measured duration.
const HOLD: std::time::Duration = std::time::Duration::from_millis(300);

/// Makes another thread collect the mappings this thread's work has requested on `ctx` and
/// hold their callbacks back, as a concurrent render's submit or the GPU engine's compute
/// thread on a shared device does under load: a blocker buffer's mapping is requested now,
/// ahead of the work's (which wgpu queues once the submission is done), so the other thread's
/// poll reports the blocker first, and the blocker's callback sleeps before returning. Returns
/// once the other thread is inside that callback, i.e. has taken the work's mappings off the
/// device; the work's own poll then finds nothing left to report. Join the handle at the end.
pub(crate) fn collect_mappings_elsewhere(
    ctx: &crowdmorph::engine::gpu::GpuContext,
) -> std::thread::JoinHandle<()> {
    let device = ctx.device().clone();
    let blocker = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("test blocker"),
        size: 4,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let (inside, entered) = std::sync::mpsc::channel();
    blocker.map_async(wgpu::MapMode::Read, .., move |r| {
        r.expect("the blocker maps");
        let _ = inside.send(());
        std::thread::sleep(HOLD);
    });
    let other = std::thread::spawn(move || {
        device
            .poll(wgpu::PollType::wait_indefinitely())
            .expect("the other thread's poll");
        drop(blocker);
    });
    entered
        .recv_timeout(std::time::Duration::from_secs(60))
        .expect("the other thread collected the mappings");
    other
}

gpu_test!(
    #[test]
    fn a_frame_whose_mapping_another_thread_collects_is_still_read_back() {
        // The cause of a 503 "mapping the rendered frame failed" under load: another thread's
        // poll or submit found the render's copy done and took its mapping callbacks, and the
        // render read its results before that thread had run them. The frame must come back, and
        // be the same picture as without the race.
        let r = renderer();
        let (rig, prepared) = head();
        let topology = r.topology(rig).expect("topology");
        let data = evaluate(prepared, "talk", 12);
        let view = head_view(rig);
        // Large enough that the copy is still running when the render submits it, so its mapping
        // waits behind the blocker (see `collect_mappings_elsewhere`).
        let size = frame(1024, 768);
        let meshes = [host(&topology, &data, &[Mat4::IDENTITY])];
        let alone = r.render(&meshes, &view, &size).expect("render alone");
        let others = Arc::new(std::sync::Mutex::new(Vec::new()));
        let o = others.clone();
        r.set_after_submit(Some(Arc::new(move |ctx| {
            let t = collect_mappings_elsewhere(ctx);
            o.lock().expect("lock").push(t);
        })));
        let raced = r.render(&meshes, &view, &size);
        r.set_after_submit(None);
        for t in std::mem::take(&mut *others.lock().expect("lock")) {
            t.join().expect("the other thread");
        }
        let raced = raced.expect("a render whose mapping another thread collected");
        assert!(
            raced.rgba == alone.rgba,
            "the raced render drew something else"
        );
    }
);

gpu_test!(
    #[test]
    fn a_batch_whose_mapping_another_thread_collects_is_read_back_and_the_engine_stays_healthy() {
        // The same race in the GPU engine, where a missing callback was taken for a lost device
        // and sent every later batch to the CPU engine: a render on the shared device (or another
        // batch) collects a batch's mappings between its submit and its wait.
        use crowdmorph::engine::{BackendChoice, BackendKind};
        let engine = Engine::with_gpu(open_gpu(GpuOptions::default()), BackendChoice::Gpu);
        let ctx = engine.gpu_shared().expect("gpu");
        let (rig, cpu_prepared) = head();
        let prepared = engine.prepare(rig.clone()).expect("upload");
        let talk = rig.clip_index("talk").expect("talk");
        let frames = rig.clips[talk].frames;
        // Enough jobs that the batch is still running when `submit` returns.
        let jobs: Vec<BlendJob> = (0..64)
            .map(|j| BlendJob::frame(talk as u32, j % frames, 0))
            .collect();
        let spec = OutputSpec {
            normals: true,
            precision: Precision::F32,
        };
        let pending = engine.submit(&prepared, &jobs, spec, true).expect("submit");
        let other = collect_mappings_elsewhere(&ctx);
        let got = pending.wait();
        other.join().expect("the other thread");
        let got = got.expect("a batch whose mapping another thread collected");
        assert_eq!(got.kind, Some(BackendKind::Gpu));
        assert!(
            !engine.info().degraded,
            "{:?}",
            engine.info().degraded_reason
        );
        let want = Engine::cpu()
            .evaluate(cpu_prepared, &jobs, spec)
            .expect("cpu")
            .output;
        let diag = rig.bbox().diagonal();
        for j in [0, 31, 63] {
            let worst = got
                .output
                .job_positions(j)
                .iter()
                .zip(want.job_positions(j))
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max);
            assert!(worst <= 1e-5 * diag, "job {j}: {worst}");
        }
    }
);

gpu_test!(
    #[test]
    fn a_frame_over_the_gpu_memory_budget_is_refused_and_smaller_ones_still_render() {
        use crowdmorph::budget::BudgetError;
        // 8 MiB beyond what the renderer itself holds (a software rasterizer's bins).
        let probe = open_gpu(GpuOptions::default());
        let budget = (8u64 << 20) + crowdmorph::render::gpu::fixed_bytes(probe.adapter());
        drop(probe);
        let r = Renderer::new(Arc::new(open_gpu(GpuOptions {
            memory: Some(budget),
            ..GpuOptions::default()
        })))
        .expect("renderer");
        let (rig, prepared) = head();
        let topology = r.topology(rig).expect("topology");
        let data = evaluate(prepared, "talk", 12);
        let meshes = [host(&topology, &data, &[Mat4::IDENTITY])];
        let view = head_view(rig);
        // 2048 × 2048 with 4× MSAA colour and depth alone is 128 MiB: more than the whole budget.
        let e = r
            .render(&meshes, &view, &frame(2048, 2048))
            .expect_err("over the budget");
        assert!(
            matches!(e, RenderError::Memory(BudgetError::TooLarge { limit, .. }) if limit == budget),
            "{e:?}"
        );
        assert!(e.to_string().contains("--max-gpu-memory"), "{e}");
        let out = r
            .render(&meshes, &view, &frame(128, 128))
            .expect("a small frame fits");
        assert!(covered(&image(&out), 32, 96, 32, 96) > 1000);
    }
);

gpu_test!(
    #[test]
    fn a_renderers_kept_targets_give_way_to_a_rig_upload_and_renders_make_new_ones() {
        // The renderer keeps its last targets and buffers for the next render. On the engine's
        // device, with a budget that has room for them or for a second copy of the rig but not
        // both, the upload frees them instead of being refused; the next render makes new ones and
        // draws the same picture.
        use crowdmorph::engine::BackendChoice;
        let (rig, cpu_prepared) = head();
        let data = evaluate(cpu_prepared, "talk", 12);
        let view = head_view(rig);
        let size = frame(96, 96);
        let on_gpu = |memory: Option<u64>| {
            let engine = Engine::with_gpu(
                open_gpu(GpuOptions {
                    memory,
                    ..GpuOptions::default()
                }),
                BackendChoice::Gpu,
            );
            let renderer = Renderer::new(engine.gpu_shared().expect("gpu")).expect("renderer");
            (engine, renderer)
        };

        // What the rig, its topology and a render's kept targets and buffers hold, by default.
        let (engine, renderer) = on_gpu(None);
        let memory = renderer.memory().clone();
        let start = memory.used();
        let prepared = engine.prepare(rig.clone()).expect("upload");
        let rig_bytes = memory.used() - start;
        let topology = renderer.topology(rig).expect("topology");
        let before = memory.used();
        let want = renderer
            .render(&[host(&topology, &data, &[Mat4::IDENTITY])], &view, &size)
            .expect("render");
        let kept = memory.used() - before;
        assert!(
            kept > 0 && kept / 2 < rig_bytes,
            "kept {kept} bytes: between 0 and twice the rig's {rig_bytes}"
        );
        drop((topology, prepared, renderer, engine));

        // Room for two copies of the rig, the topology and half of what a render keeps.
        let (engine, renderer) = on_gpu(Some(before + rig_bytes + kept / 2));
        let memory = renderer.memory().clone();
        let first = engine.prepare(rig.clone()).expect("the first copy fits");
        let topology = renderer.topology(rig).expect("topology");
        let meshes = [host(&topology, &data, &[Mat4::IDENTITY])];
        renderer
            .render(&meshes, &view, &size)
            .expect("a render fits next to one copy");
        assert_eq!(memory.used(), before + kept, "the render keeps its targets");
        let second = engine
            .prepare(rig.clone())
            .expect("the kept targets make room for a second copy");
        assert_eq!(
            memory.used(),
            before + rig_bytes,
            "the kept targets and buffers were given back"
        );

        // With one copy gone, a render fits again: new targets, the same picture.
        drop(first);
        let again = renderer
            .render(&meshes, &view, &size)
            .expect("renders work after the reclaim");
        assert_eq!(memory.used(), before + kept, "new targets are kept");
        assert!(
            again.rgba == want.rgba,
            "the picture after the reclaim differs from the one before"
        );
        assert!(covered(&image(&again), 24, 72, 24, 72) > 500);
        assert!(
            !engine.info().degraded,
            "{:?}",
            engine.info().degraded_reason
        );
        drop((second, topology));
    }
);
