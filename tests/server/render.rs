//! `POST /v1/crowd/render` over real sockets: golden pictures of a head, a 3×3 crowd and placed
//! clones on lavapipe (rewritten by `CROWDMORPH_BLESS=1 cargo test --locked render`, see
//! `tests/util/image.rs`), behaviour that needs no golden (the background is exact, a LOD level
//! changes little, the mouth moves in `talk`, formats agree), the pixel budget and the GPU
//! budget (cached topologies give way to uploads), a render racing a rig delete, and bad input — which is checked before anything is drawn, so those tests run
//! without a GPU too.

use crate::util::gpu_test;
use std::path::{Path, PathBuf};
use std::time::Duration;

use bytes::Bytes;
use crowdmorph::render::scene;
use crowdmorph::server::{RenderBackend, ServerConfig};
use crowdmorph_client::{Encoding, Method, Reply};
use crowdmorph_proto::{
    CameraSpec, Head, ImageFormat, ImageOptions, LodLevelRequest, LodRequest, Placement,
    RenderRequest,
};
use glam::Vec3;
use serde_json::json;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

use super::TestServer;
use crate::util::image::{Image, Tolerance, check_golden, compare};

/// Goldens are rendered on lavapipe and compared on lavapipe, where they match exactly; the
/// tolerance absorbs MSAA edge samples and last-bit shading after a Mesa or LLVM update.
const GOLDEN: Tolerance = Tolerance {
    per_pixel: 8,
    max_fraction: 0.005,
};

fn golden(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/golden/render")
        .join(name)
}

fn head(id: u64, clip: &str, frame: i64, lod: u32) -> Head {
    Head {
        head: id,
        rig: "default-head".into(),
        clip: clip.into(),
        frame,
        lod,
        ..Default::default()
    }
}

fn request(heads: Vec<Head>, width: u32, height: u32) -> RenderRequest {
    RenderRequest {
        heads,
        wrap: true,
        placements: None,
        camera: None,
        image: Some(ImageOptions {
            width,
            height,
            ..ImageOptions::default()
        }),
    }
}

fn with_format(mut r: RenderRequest, format: ImageFormat) -> RenderRequest {
    if let Some(i) = r.image.as_mut() {
        i.format = format;
    }
    r
}

/// Renders and decodes a PNG reply, checking its type and size headers.
async fn png(server: &TestServer, req: &RenderRequest) -> Image {
    let reply = server
        .client
        .render(req, Encoding::Json)
        .await
        .expect("render");
    decode_png(&reply, req)
}

fn decode_png(reply: &Reply, req: &RenderRequest) -> Image {
    let size = req.image.map_or((640, 480), |i| (i.width, i.height));
    assert_eq!(reply.content_type.as_deref(), Some("image/png"));
    assert_eq!(size_headers(reply), size);
    let img = Image::decode_png(&reply.body).expect("a PNG");
    assert_eq!((img.width, img.height), size);
    img
}

fn size_headers(reply: &Reply) -> (u32, u32) {
    let get = |name| {
        reply
            .header(name)
            .unwrap_or_else(|| panic!("no {name} header"))
            .parse::<u32>()
            .expect("a number")
    };
    (get("x-image-width"), get("x-image-height"))
}

/// The stages of the Server-Timing header and their durations.
fn server_timing(reply: &Reply) -> Vec<(String, f64)> {
    reply
        .header("server-timing")
        .expect("Server-Timing")
        .split(',')
        .map(|entry| {
            let (name, dur) = entry
                .trim()
                .split_once(";dur=")
                .unwrap_or_else(|| panic!("malformed entry {entry:?}"));
            (name.to_string(), dur.parse().expect("milliseconds"))
        })
        .collect()
}

fn is_colour(p: [u8; 4], rgb: [u8; 3]) -> bool {
    p == [rgb[0], rgb[1], rgb[2], 255]
}

/// Fraction of the pixels of `a` and `b` inside `[x0, x1) × [y0, y1)` (or outside it) whose
/// largest channel difference is over `threshold`.
fn differing(a: &Image, b: &Image, rect: (u32, u32, u32, u32), inside: bool, threshold: u8) -> f64 {
    let (x0, x1, y0, y1) = rect;
    let (mut n, mut d) = (0usize, 0usize);
    for y in 0..a.height {
        for x in 0..a.width {
            if (x >= x0 && x < x1 && y >= y0 && y < y1) != inside {
                continue;
            }
            n += 1;
            let (p, q) = (a.pixel(x, y), b.pixel(x, y));
            if p.iter().zip(q).any(|(u, v)| u.abs_diff(v) > threshold) {
                d += 1;
            }
        }
    }
    d as f64 / n.max(1) as f64
}

gpu_test!(
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_head_a_crowd_and_placed_clones_match_their_golden_images() {
        let server = TestServer::start(ServerConfig::default()).await;
        let s = &server;
        // /readyz names the adapter that renders.
        let ready = s
            .client
            .send(Method::GET, "/readyz", None, None, Bytes::new())
            .await
            .expect("readyz");
        let r: crowdmorph_proto::Readiness = serde_json::from_slice(&ready.body).expect("JSON");
        let adapter = r.renderer.expect("a renderer");
        eprintln!("rendering on {adapter}");

        let one = request(vec![head(1, "talk", 12, 0)], 320, 240);
        let reply = s.client.render(&one, Encoding::Json).await.expect("render");
        let img = decode_png(&reply, &one);
        check_golden(&golden("http_head.png"), &img, GOLDEN);
        let stages: Vec<String> = server_timing(&reply).into_iter().map(|s| s.0).collect();
        assert_eq!(stages, ["compute", "render", "readback", "encode"]);
        // The same request in bincode draws the same picture.
        let bin = s
            .client
            .render(&one, Encoding::Bincode)
            .await
            .expect("render");
        assert_eq!(decode_png(&bin, &one), img);

        let crowd: Vec<Head> = (0..9)
            .map(|i| {
                let clip = ["talk", "smile", "surprise"][i % 3];
                head(i as u64, clip, 10 * i as i64, 0)
            })
            .collect();
        let img = png(s, &request(crowd, 320, 240)).await;
        check_golden(&golden("http_crowd_3x3.png"), &img, GOLDEN);

        // Three clones of one job, placed, turned and scaled, seen from a raised camera.
        let mut clones = request(
            vec![
                head(1, "smile", 30, 0),
                head(2, "smile", 30, 0),
                head(3, "smile", 30, 0),
            ],
            320,
            240,
        );
        clones.placements = Some(vec![
            Placement {
                head: 1,
                position: [-20.0, 0.0, 0.0],
                yaw: 30.0,
                scale: 1.0,
            },
            Placement {
                head: 2,
                position: [0.0, 0.0, -10.0],
                yaw: 0.0,
                scale: 1.4,
            },
            Placement {
                head: 3,
                position: [20.0, 0.0, 0.0],
                yaw: -30.0,
                scale: 1.0,
            },
        ]);
        clones.camera = Some(CameraSpec {
            fov_y: 40.0,
            ..CameraSpec::looking([0.0, 15.0, 80.0], [0.0, 0.0, 0.0])
        });
        let img = png(s, &clones).await;
        check_golden(&golden("http_clones.png"), &img, GOLDEN);
        server.stop().await;
    }
);

gpu_test!(
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn no_heads_render_the_background_exactly_and_formats_agree() {
        let server = TestServer::start(ServerConfig::default()).await;
        let s = &server;
        let bg = [12u8, 200, 99];
        let mut empty = with_format(request(Vec::new(), 70, 33), ImageFormat::Rgba);
        if let Some(i) = empty.image.as_mut() {
            i.background = bg;
        }
        let reply = s
            .client
            .render(&empty, Encoding::Json)
            .await
            .expect("render");
        assert_eq!(
            reply.content_type.as_deref(),
            Some("application/octet-stream")
        );
        assert_eq!(size_headers(&reply), (70, 33));
        assert_eq!(reply.body.len(), 70 * 33 * 4);
        assert!(
            reply
                .body
                .chunks_exact(4)
                .all(|p| is_colour([p[0], p[1], p[2], p[3]], bg)),
            "every pixel is the background {bg:?}"
        );

        // One head as PNG, raw RGBA and JPEG: the same picture.
        let one = request(vec![head(1, "talk", 20, 0)], 160, 120);
        let png_img = png(s, &one).await;
        let raw = s
            .client
            .render(&with_format(one.clone(), ImageFormat::Rgba), Encoding::Json)
            .await
            .expect("render");
        assert_eq!(size_headers(&raw), (160, 120));
        assert_eq!(Image::new(160, 120, raw.body.to_vec()), png_img);
        let jpeg = s
            .client
            .render(&with_format(one, ImageFormat::Jpeg), Encoding::Json)
            .await
            .expect("render");
        assert_eq!(jpeg.content_type.as_deref(), Some("image/jpeg"));
        assert_eq!(size_headers(&jpeg), (160, 120));
        let j = &jpeg.body;
        assert_eq!(&j[..2], &[0xFF, 0xD8], "JPEG start of image");
        assert_eq!(&j[j.len() - 2..], &[0xFF, 0xD9], "JPEG end of image");
        assert_eq!(crowdmorph::render::encode::jpeg_size(j), Some((160, 120)));
        // The head is drawn: not every pixel is the default background.
        let bg = crowdmorph_proto::DEFAULT_BACKGROUND;
        let drawn = png_img
            .rgba
            .chunks_exact(4)
            .filter(|p| !is_colour([p[0], p[1], p[2], p[3]], bg))
            .count();
        assert!(drawn > 160 * 120 / 10, "{drawn} pixels drawn");
        server.stop().await;
    }
);

gpu_test!(
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_lod_level_on_a_simplified_mesh_changes_the_picture_little() {
        let server = TestServer::start(ServerConfig::default()).await;
        let s = &server;
        // Level 1 keeps every shape but draws the half-resolution mesh with its own triangles.
        let info = s
            .client
            .set_lod(
                "default-head",
                &LodRequest {
                    method: Some("file-order".into()),
                    levels: Some(vec![
                        LodLevelRequest {
                            shapes: 51,
                            mesh: None,
                        },
                        LodLevelRequest {
                            shapes: 51,
                            mesh: Some(0),
                        },
                    ]),
                    mesh_fractions: vec![0.5],
                    ..LodRequest::default()
                },
            )
            .await
            .expect("set the LOD");
        let levels = &info.lod.levels;
        assert_eq!(levels[1].mesh, Some(0));
        assert!(levels[1].triangles < levels[0].triangles / 3 * 2);
        let full = png(s, &request(vec![head(1, "talk", 40, 0)], 320, 240)).await;
        let coarse = png(s, &request(vec![head(1, "talk", 40, 1)], 320, 240)).await;
        let c = compare(&coarse, &full, 32).expect("same size");
        let any = compare(&coarse, &full, 0).expect("same size");
        eprintln!(
            "LOD 1 against LOD 0: {c}; {} pixels differ at all",
            any.differing
        );
        assert!(
            any.differing > 100,
            "the simplified mesh draws its own triangles: {any}"
        );
        assert!(
            c.fraction() < 0.03,
            "half the triangles should change the picture little: {c}"
        );
        server.stop().await;
    }
);

/// Frames of `talk` where `jawOpen` is smallest and largest.
fn jaw_extremes(rig: &crowdmorph::rig::Rig) -> (u32, u32) {
    let talk = &rig.clips[rig.clip_index("talk").expect("talk")];
    let jaw = rig.target_id("jawOpen").expect("jawOpen") as usize;
    let w: Vec<f32> = (0..talk.frames).map(|f| talk.weight(jaw, f)).collect();
    let arg = |better: fn(f32, f32) -> bool| {
        (0..w.len()).fold(0, |b, i| if better(w[i], w[b]) { i } else { b }) as u32
    };
    (arg(|a, b| a < b), arg(|a, b| a > b))
}

/// The pixel rectangle around the vertices `jawOpen` moves most, for a lone head seen by the
/// default camera.
fn mouth_rect(rig: &crowdmorph::rig::Rig, width: u32, height: u32) -> (u32, u32, u32, u32) {
    let aspect = width as f32 / height as f32;
    let layout = scene::layout(&[rig.bbox()], None, &[1], None, None, aspect).expect("layout");
    let vp = layout.view.view_projection(aspect);
    let jaw = rig.target_id("jawOpen").expect("jawOpen");
    // (neutral position, length of the jawOpen delta) of every vertex the target moves.
    let deltas: Vec<(Vec3, f32)> = rig
        .primitives
        .iter()
        .flat_map(|p| {
            p.targets
                .iter()
                .filter(|t| t.target == jaw)
                .flat_map(move |t| {
                    t.vertices
                        .iter()
                        .zip(&t.positions)
                        .map(move |(&v, d)| (p.positions[v as usize], d.length()))
                })
        })
        .collect();
    let max = deltas.iter().map(|d| d.1).fold(0.0f32, f32::max);
    let moved: Vec<Vec3> = deltas
        .iter()
        .filter(|d| d.1 > 0.5 * max)
        .map(|d| layout.transforms[0].transform_point3(d.0))
        .collect();
    assert!(!moved.is_empty(), "jawOpen moves vertices");
    let (mut x0, mut x1, mut y0, mut y1) = (f32::MAX, f32::MIN, f32::MAX, f32::MIN);
    for p in moved {
        let n = vp.project_point3(p);
        let (x, y) = (
            (n.x + 1.0) * 0.5 * width as f32,
            (1.0 - n.y) * 0.5 * height as f32,
        );
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(y);
        y1 = y1.max(y);
    }
    let clamp = |v: f32, hi: u32| v.clamp(0.0, hi as f32) as u32;
    (
        clamp(x0, width),
        clamp(x1.ceil(), width),
        clamp(y0, height),
        clamp(y1.ceil(), height),
    )
}

gpu_test!(
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn the_mouth_visibly_moves_between_two_frames_of_talk() {
        let server = TestServer::start(ServerConfig::default()).await;
        let rig = crowdmorph::embedded::default_rig();
        let (closed, open) = jaw_extremes(&rig);
        let (w, h) = (320, 240);
        let rect = mouth_rect(&rig, w, h);
        let a = png(
            &server,
            &request(vec![head(1, "talk", closed.into(), 0)], w, h),
        )
        .await;
        let b = png(
            &server,
            &request(vec![head(1, "talk", open.into(), 0)], w, h),
        )
        .await;
        let mouth = differing(&a, &b, rect, true, 24);
        let rest = differing(&a, &b, rect, false, 24);
        eprintln!(
            "frames {closed} and {open}: mouth {rect:?} differs {mouth:.3}, the rest {rest:.4}"
        );
        assert!(mouth > 0.15, "the mouth region barely changed: {mouth}");
        assert!(
            mouth > 5.0 * rest,
            "the change is not concentrated at the mouth: mouth {mouth}, elsewhere {rest}"
        );
        server.stop().await;
    }
);

/// Pixel rectangle `(x0, x1, y0, y1)` (unclamped; `x1`, `y1` past the last pixel) of the
/// corners of `b`, placed by `m` and seen by `view`, in a `width` × `height` image.
fn projected(
    view: &scene::View,
    m: glam::Mat4,
    b: &crowdmorph::rig::Aabb,
    width: u32,
    height: u32,
) -> (f32, f32, f32, f32) {
    let vp = view.view_projection(width as f32 / height as f32);
    let (mut x0, mut x1, mut y0, mut y1) = (f32::MAX, f32::MIN, f32::MAX, f32::MIN);
    for i in 0..8 {
        let c = Vec3::new(
            if i & 1 == 0 { b.min.x } else { b.max.x },
            if i & 2 == 0 { b.min.y } else { b.max.y },
            if i & 4 == 0 { b.min.z } else { b.max.z },
        );
        let n = vp.project_point3(m.transform_point3(c));
        let (x, y) = (
            (n.x + 1.0) * 0.5 * width as f32,
            (1.0 - n.y) * 0.5 * height as f32,
        );
        (x0, x1, y0, y1) = (x0.min(x), x1.max(x), y0.min(y), y1.max(y));
    }
    (x0, x1, y0, y1)
}

/// Rectangle `(x0, x1, y0, y1)` (`x1`, `y1` exclusive) of the pixels that are not `bg`, and
/// how many there are.
fn drawn(img: &Image, bg: [u8; 3]) -> ((u32, u32, u32, u32), usize) {
    let (mut x0, mut x1, mut y0, mut y1, mut n) = (u32::MAX, 0, u32::MAX, 0, 0);
    for y in 0..img.height {
        for x in 0..img.width {
            if !is_colour(img.pixel(x, y), bg) {
                (x0, x1, y0, y1) = (x0.min(x), x1.max(x + 1), y0.min(y), y1.max(y + 1));
                n += 1;
            }
        }
    }
    ((x0, x1, y0, y1), n)
}

/// A rig at rest (live weights, none given) alone in a 320 × 240 PNG on `bg`, seen by `camera`.
async fn alone(server: &TestServer, rig: &str, camera: Option<CameraSpec>, bg: [u8; 3]) -> Image {
    alone_as(server, rig, camera, bg, Encoding::Json).await
}

/// [`alone`], asked for in the encoding `enc`.
async fn alone_as(
    server: &TestServer,
    rig: &str,
    camera: Option<CameraSpec>,
    bg: [u8; 3],
    enc: Encoding,
) -> Image {
    let mut req = request(
        vec![Head {
            head: 1,
            rig: rig.into(),
            weights: Some(Box::new(crowdmorph_proto::LiveWeights::Named(Vec::new()))),
            ..Default::default()
        }],
        320,
        240,
    );
    req.camera = camera;
    if let Some(i) = req.image.as_mut() {
        i.background = bg;
    }
    let reply = server.client.render(&req, enc).await.expect("render");
    decode_png(&reply, &req)
}

gpu_test!(
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    #[cfg_attr(
        not(crowdmorph_test_data),
        ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
    )]
    async fn a_camera_framing_faces_fills_the_picture_with_the_head_and_leaves_the_feet_out() {
        use crowdmorph::rig::RegionSource;
        use crowdmorph_proto::CameraFrame;
        let server = TestServer::start(ServerConfig::default()).await;
        let s = &server;
        let data = crate::util::data_dir();
        for (id, file) in [
            ("robot", "robot-expressive/RobotExpressive.glb"),
            ("ict", "ict-facekit/ict_facekit_53.glb"),
        ] {
            s.client
                .upload_rig(id, super::upload_bytes(&data.join(file)))
                .await
                .expect("upload");
        }
        let (w, h) = (320u32, 240u32);
        let (wf, hf) = (w as f32, h as f32);
        let aspect = wf / hf;
        let bg = [255u8, 0, 255];
        let faces = CameraSpec::framing(CameraFrame::Faces);
        let bodies = CameraSpec::framing(CameraFrame::Bodies);

        // RobotExpressive: skinned, its face region is what its `Head` joint carries.
        let entry = s.state.registry.get("robot").expect("robot");
        let rig = entry.rig();
        let region = rig.face_region();
        let sk = rig.skeleton.as_ref().expect("skinned");
        let RegionSource::HeadJoint { node } = region.source else {
            panic!("the robot's face region should come from its head joint: {region:?}");
        };
        assert_eq!(sk.nodes[node as usize].name, "Head");
        assert_eq!(
            entry.face_region(),
            region.bbox,
            "the registry keeps the same box"
        );
        let whole = rig.bbox();
        eprintln!("robot: whole {whole:?}, head {region:?}");
        // Where the server's layout puts the head box and the feet, and what it draws.
        let laid = scene::layout(
            &[whole],
            Some(&[region.bbox]),
            &[1],
            None,
            Some(&faces),
            aspect,
        )
        .expect("layout");
        let head_px = projected(&laid.view, laid.transforms[0], &region.bbox, w, h);
        let body_px = projected(&laid.view, laid.transforms[0], &whole, w, h);
        eprintln!("robot, faces: head at {head_px:?}, body at {body_px:?}");
        let (x0, x1, y0, y1) = head_px;
        assert!(
            x0 >= -0.5 && y0 >= -0.5 && x1 <= wf + 0.5 && y1 <= hf + 0.5,
            "the head box is in the picture: {head_px:?}"
        );
        assert!(
            ((x1 - x0) / wf).max((y1 - y0) / hf) >= 0.85,
            "the head box fills the picture: {head_px:?}"
        );
        assert!(
            body_px.3 > hf * 1.5,
            "the feet are well below it: {body_px:?}"
        );
        let face_img = alone(s, "robot", Some(faces), bg).await;
        // The Rust client sends a framing camera as JSON whatever it is asked to use.
        assert!(
            alone_as(s, "robot", Some(faces), bg, Encoding::Bincode).await == face_img,
            "the same picture asked for in bincode"
        );
        let ((dx0, dx1, dy0, dy1), n) = drawn(&face_img, bg);
        eprintln!("robot, faces: drawn {:?}", (dx0, dx1, dy0, dy1));
        assert!(n > 0, "the robot is drawn");
        // The top of the figure is the top of its head, drawn inside the box's projection: a
        // little below its top, as the box's front face is what fits the picture and the
        // round head is widest further back. The body goes on out of the picture.
        assert!(
            dy0 as f32 >= y0 - 2.0 && (dy0 as f32) <= y0 + 0.15 * hf,
            "the head's top is drawn at {dy0}, its box's at {y0}"
        );
        assert_eq!(dy1, h, "the body leaves the picture at the bottom");
        // Most of the head box is head.
        let (hx0, hx1, hy0, hy1) = (
            x0.max(0.0) as u32,
            x1.min(wf) as u32,
            y0.max(0.0) as u32,
            y1.min(hf) as u32,
        );
        let inside = (hy0..hy1)
            .flat_map(|y| (hx0..hx1).map(move |x| (x, y)))
            .filter(|&(x, y)| !is_colour(face_img.pixel(x, y), bg))
            .count();
        let area = ((hx1 - hx0) * (hy1 - hy0)) as usize;
        assert!(
            inside * 2 > area,
            "only {inside} of the head box's {area} pixels are drawn"
        );
        // Framing bodies is the view without a camera, pixel for pixel, and it holds the whole
        // robot, feet too, inside the margins.
        let body_img = alone(s, "robot", Some(bodies), bg).await;
        assert!(
            body_img == alone(s, "robot", None, bg).await,
            "bodies is the default view"
        );
        assert!(body_img != face_img);
        let ((bx0, bx1, by0, by1), _) = drawn(&body_img, bg);
        eprintln!("robot, bodies: drawn {:?}", (bx0, bx1, by0, by1));
        assert!(
            bx0 > 0 && by0 > 0 && bx1 < w && by1 < h,
            "the whole robot is in the picture: {:?}",
            (bx0, bx1, by0, by1)
        );
        // The head is drawn more than twice as large framed alone.
        let default_head = projected(
            &scene::layout(&[whole], None, &[1], None, None, aspect)
                .expect("layout")
                .view,
            laid.transforms[0],
            &region.bbox,
            w,
            h,
        );
        assert!(
            (y1 - y0) > 2.0 * (default_head.3 - default_head.2),
            "faces {head_px:?} against bodies {default_head:?}"
        );

        // ICT FaceKit: no skeleton, so the region is what its expressions move, which leaves
        // out the top of the scalp and the back of the head; faces frames that box, bodies the
        // whole head.
        let entry = s.state.registry.get("ict").expect("ict");
        let rig = entry.rig();
        let region = rig.face_region();
        let whole = rig.bbox();
        eprintln!("ict: whole {whole:?}, targets {region:?}");
        assert_eq!(region.source, RegionSource::Targets);
        assert_eq!(entry.face_region(), region.bbox);
        assert!(
            region.bbox.max.y < whole.max.y - 0.02 * (whole.max.y - whole.min.y)
                && region.bbox.min.z > whole.min.z,
            "the scalp and the back of the head are still: {region:?} in {whole:?}"
        );
        let laid = scene::layout(
            &[whole],
            Some(&[region.bbox]),
            &[1],
            None,
            Some(&faces),
            aspect,
        )
        .expect("layout");
        let (x0, x1, y0, y1) = projected(&laid.view, laid.transforms[0], &region.bbox, w, h);
        assert!(
            ((x1 - x0) / wf).max((y1 - y0) / hf) >= 0.85,
            "the region fills the picture: {:?}",
            (x0, x1, y0, y1)
        );
        let face_img = alone(s, "ict", Some(faces), bg).await;
        let body_img = alone(s, "ict", Some(bodies), bg).await;
        assert!(
            body_img == alone(s, "ict", None, bg).await,
            "bodies is the default view"
        );
        let ((fx0, fx1, fy0, fy1), _) = drawn(&face_img, bg);
        let ((bx0, bx1, by0, by1), _) = drawn(&body_img, bg);
        eprintln!(
            "ict: region at {:?}, drawn framing faces {:?}, bodies {:?}",
            (x0, x1, y0, y1),
            (fx0, fx1, fy0, fy1),
            (bx0, bx1, by0, by1)
        );
        // Its expressions move the neck too, so the region is most of the head: framed, the
        // head is drawn a little larger (5 % here), its neck still at the picture's bottom.
        assert!(face_img != body_img);
        assert!(
            fy1 - fy0 >= by1 - by0 + 4 && fx1 - fx0 >= bx1 - bx0 + 4,
            "faces draws the head larger: {:?} against {:?}",
            (fx0, fx1, fy0, fy1),
            (bx0, bx1, by0, by1)
        );
        assert!(fy1 >= by1 && fy1 < h, "the neck ends at {fy1}, not {by1}");
        server.stop().await;
    }
);

gpu_test!(
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_full_pixel_budget_is_503_render_busy_with_retry_after() {
        // The budget holds one 2048 × 2048 image. Its permit goes with the response body, so a
        // client that does not read a 16 MiB raw image keeps the budget full for as long as it
        // likes: no timing involved.
        let side = 2048u32;
        let server = TestServer::start(ServerConfig {
            render_pixels: u64::from(side * side),
            ..ServerConfig::default()
        })
        .await;
        let big = with_format(request(Vec::new(), side, side), ImageFormat::Rgba);
        let body = serde_json::to_vec(&big).expect("JSON");
        let socket = tokio::net::TcpSocket::new_v4().expect("socket");
        // A small receive window, so that the server's writes block after a few MiB.
        socket.set_recv_buffer_size(4096).expect("SO_RCVBUF");
        let mut stream = socket.connect(server.addr).await.expect("connect");
        let head = format!(
            "POST /v1/crowd/render HTTP/1.1\r\nhost: x\r\ncontent-type: application/json\r\n\
             content-length: {}\r\n\r\n",
            body.len()
        );
        stream.write_all(head.as_bytes()).await.expect("send");
        stream.write_all(&body).await.expect("send");
        let mut first = [0u8; 12];
        stream.read_exact(&mut first).await.expect("status line");
        assert_eq!(&first, b"HTTP/1.1 200", "the big render is served");

        let small = request(Vec::new(), 8, 8);
        let r = s_render_raw(&server, &small).await;
        assert_eq!(r.status, 503, "{}", String::from_utf8_lossy(&r.body));
        assert_eq!(r.error().expect("JSON error").error.code, "render_busy");
        assert_eq!(r.retry_after.as_deref(), Some("1"));
        let page = server.client.metrics().await.expect("metrics");
        assert_eq!(
            crowdmorph_client::metric(&page, "crowdmorph_render_pixels"),
            Some(f64::from(side * side))
        );

        // Reading the image (or dropping the connection) gives the budget back.
        drop(stream);
        let mut ok = false;
        for _ in 0..500 {
            let r = s_render_raw(&server, &small).await;
            if r.status == 200 {
                ok = true;
                break;
            }
            assert_eq!(r.status, 503);
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        assert!(
            ok,
            "the budget came back after the big response's connection closed"
        );
        // An image larger than the whole budget can never be served: 413, not 503.
        let too_big = request(Vec::new(), side, side + 1);
        let r = s_render_raw(&server, &too_big).await;
        assert_eq!(r.status, 413);
        assert_eq!(r.error().expect("JSON").error.code, "image_too_large");
        server.stop().await;
    }
);

async fn s_render_raw(server: &TestServer, req: &RenderRequest) -> Reply {
    server
        .client
        .render_raw(
            Bytes::from(serde_json::to_vec(req).expect("JSON")),
            Encoding::Json,
        )
        .await
        .expect("transport")
}

/// A triangle rig with a two-key clip `wave`.
fn triangle_glb() -> Bytes {
    let mut b = crate::util::builder::Builder::new();
    let tri = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
    let mesh = b.mesh_with_targets(&tri, Some(&[0, 1, 2]), &[vec![[0.0, 0.0, 0.5]; 3]], None);
    let node = b.node(Some(mesh));
    b.animation_weights("wave", node, &[0.0, 1.0], &[0.0, 1.0], "LINEAR");
    b.scene(&[node]);
    Bytes::from(b.to_glb())
}

gpu_test!(
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn renders_racing_a_rig_delete_get_the_old_generation_or_404_never_500() {
        let server = TestServer::start(ServerConfig::default()).await;
        let glb = triangle_glb();
        // First the race made to happen every time, then the races left to chance.
        a_delete_and_another_poll_inside_the_race_window(&server, glb.clone()).await;
        let mut seen = (0, 0);
        for round in 0..6 {
            server
                .client
                .upload_rig("tri", glb.clone())
                .await
                .expect("upload");
            let renders: Vec<_> = (0..6)
                .map(|i| {
                    let client = server.client.clone();
                    let req = request(
                        vec![
                            Head {
                                head: 1,
                                rig: "tri".into(),
                                clip: "wave".into(),
                                frame: i,
                                lod: 0,
                                ..Default::default()
                            },
                            head(2, "talk", i, 0),
                        ],
                        96,
                        64,
                    );
                    tokio::spawn(async move {
                        let body = Bytes::from(serde_json::to_vec(&req).expect("JSON"));
                        client.render_raw(body, Encoding::Json).await
                    })
                })
                .collect();
            // Delete while the renders are in flight (some resolved the rig, some not yet).
            if round % 2 == 1 {
                tokio::task::yield_now().await;
            }
            server.client.delete_rig("tri").await.expect("delete");
            for r in renders {
                let r = r.await.expect("join").expect("transport");
                match r.status {
                    200 => {
                        assert_eq!(r.content_type.as_deref(), Some("image/png"));
                        Image::decode_png(&r.body).expect("a PNG");
                        seen.0 += 1;
                    }
                    404 => {
                        assert_eq!(r.error().expect("JSON").error.code, "unknown_rig");
                        seen.1 += 1;
                    }
                    other => panic!(
                        "a render racing a delete got {other}: {}",
                        String::from_utf8_lossy(&r.body)
                    ),
                }
            }
        }
        eprintln!("served {} old-generation renders, {} 404s", seen.0, seen.1);
        server.stop().await;
    }
);

/// One render whose race window (its work submitted, its frame's mapping requested, not yet
/// waited for) holds both a delete of its rig and another thread taking the frame's mapping
/// callbacks, as a concurrent render's submit did under load (the 503 "mapping the rendered
/// frame failed" this test once got): the render gets the old generation's picture, the same
/// as before the delete, and the next one a 404.
async fn a_delete_and_another_poll_inside_the_race_window(server: &TestServer, glb: Bytes) {
    use std::sync::{Arc, Mutex};
    server.client.upload_rig("tri", glb).await.expect("upload");
    let req = request(
        vec![
            Head {
                head: 1,
                rig: "tri".into(),
                clip: "wave".into(),
                frame: 1,
                lod: 0,
                ..Default::default()
            },
            head(2, "talk", 1, 0),
        ],
        // Large enough that the frame's copy still runs when the render submits it.
        1024,
        768,
    );
    let before = png(server, &req).await;
    let renderer = server.state.renderer().expect("a renderer");
    let (entered, in_window) = tokio::sync::oneshot::channel::<()>();
    let entered = Mutex::new(Some(entered));
    let (resume, resumed) = std::sync::mpsc::channel::<()>();
    let resumed = Mutex::new(resumed);
    let others = Arc::new(Mutex::new(Vec::new()));
    let o = others.clone();
    renderer.set_after_submit(Some(Arc::new(move |ctx| {
        // Only the first render waits in its window.
        let Some(entered) = entered.lock().expect("lock").take() else {
            return;
        };
        o.lock()
            .expect("lock")
            .push(crate::render::collect_mappings_elsewhere(ctx));
        let _ = entered.send(());
        let _ = resumed
            .lock()
            .expect("lock")
            .recv_timeout(Duration::from_secs(60));
    })));
    let client = server.client.clone();
    let body = Bytes::from(serde_json::to_vec(&req).expect("JSON"));
    let raced = tokio::spawn(async move { client.render_raw(body, Encoding::Json).await });
    in_window.await.expect("the render reached its race window");
    server.client.delete_rig("tri").await.expect("delete");
    resume.send(()).expect("the render waits");
    let raced = raced.await.expect("join").expect("transport");
    renderer.set_after_submit(None);
    for t in std::mem::take(&mut *others.lock().expect("lock")) {
        t.join().expect("the other thread");
    }
    assert_eq!(
        raced.status,
        200,
        "a render racing a delete: {}",
        String::from_utf8_lossy(&raced.body)
    );
    let raced = decode_png(&raced, &req);
    assert!(raced == before, "the raced render drew something else");
    let after = server
        .client
        .render_raw(
            Bytes::from(serde_json::to_vec(&req).expect("JSON")),
            Encoding::Json,
        )
        .await
        .expect("transport");
    assert_eq!(after.status, 404);
    assert_eq!(after.error().expect("JSON").error.code, "unknown_rig");
}

/// Posts a JSON value to the render endpoint.
async fn post_json(server: &TestServer, v: serde_json::Value) -> Reply {
    server
        .client
        .render_raw(Bytes::from(v.to_string()), Encoding::Json)
        .await
        .expect("transport")
}

async fn expect_error(
    server: &TestServer,
    v: serde_json::Value,
    status: u16,
    code: &str,
    needle: &str,
) {
    let r = post_json(server, v.clone()).await;
    assert_eq!(
        r.status,
        status,
        "{v}: {}",
        String::from_utf8_lossy(&r.body)
    );
    assert_eq!(r.content_type.as_deref(), Some("application/json"));
    let e = r.error().expect("a JSON error body");
    assert_eq!(e.error.code, code, "{v}: {}", e.error.message);
    assert!(
        e.error.message.contains(needle),
        "{v}: message {:?} should name {needle:?}",
        e.error.message
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_render_requests_are_named_4xx_and_without_a_renderer_503() {
    // Rendering off: requests are checked before anything would be drawn, so every 4xx is
    // the same with or without a GPU, and a valid request is a 503 that says why.
    let server = TestServer::start(ServerConfig {
        render_backend: RenderBackend::Off,
        render_pixels: 1_000_000,
        max_heads: 50,
        ..ServerConfig::default()
    })
    .await;
    let s = &server;
    let one = json!([{"head": 1, "rig": "default-head", "clip": "talk", "frame": 3}]);
    let with = |extra: serde_json::Value| {
        let mut v = json!({"heads": one});
        if let (Some(o), Some(e)) = (v.as_object_mut(), extra.as_object()) {
            o.extend(e.clone());
        }
        v
    };
    // The camera.
    let cam = |c| with(json!({"camera": c}));
    expect_error(
        s,
        cam(json!({"position": [1, 2, 3], "target": [1, 2, 3]})),
        400,
        "invalid_camera",
        "target",
    )
    .await;
    for fov in [0, 180, -1, 400] {
        expect_error(
            s,
            cam(json!({"position": [0, 0, 5], "target": [0, 0, 0], "fov_y": fov})),
            400,
            "invalid_camera",
            "fov_y",
        )
        .await;
    }
    expect_error(
        s,
        cam(json!({"position": [0, 0, 5], "target": [0, 0, 0], "near": 2, "far": 1})),
        400,
        "invalid_camera",
        "near",
    )
    .await;
    // A framing camera places itself: a position or target beside its frame is refused, and
    // without a frame both are required. Its field of view is checked as any camera's.
    for (c, needle) in [
        (
            json!({"frame": "faces", "position": [0, 0, 5]}),
            "position [0.0, 0.0, 5.0]",
        ),
        (
            json!({"frame": "bodies", "target": [0, 0, 0]}),
            "target [0.0, 0.0, 0.0]",
        ),
        (
            json!({"frame": "faces", "position": [0, 0, 5], "target": [0, 0, 0]}),
            "must be absent",
        ),
        (
            json!({"position": [0, 0, 5]}),
            "position and target are required",
        ),
        (json!({"fov_y": 40}), "position and target are required"),
        (json!({"frame": "faces", "fov_y": 0}), "fov_y"),
    ] {
        expect_error(s, cam(c), 400, "invalid_camera", needle).await;
    }
    expect_error(
        s,
        cam(json!({"frame": "face"})),
        400,
        "malformed_json",
        "frame",
    )
    .await;
    // The image.
    let img = |i| with(json!({"image": i}));
    expect_error(s, img(json!({"width": 0})), 400, "invalid_image", "width").await;
    expect_error(s, img(json!({"height": 0})), 400, "invalid_image", "height").await;
    expect_error(
        s,
        img(json!({"quality": 0})),
        400,
        "invalid_image",
        "quality",
    )
    .await;
    expect_error(
        s,
        img(json!({"quality": 101})),
        400,
        "invalid_image",
        "quality",
    )
    .await;
    expect_error(
        s,
        img(json!({"format": "gif"})),
        400,
        "malformed_json",
        "format",
    )
    .await;
    expect_error(
        s,
        img(json!({"width": 4097})),
        413,
        "image_too_large",
        "4096",
    )
    .await;
    // Under 4096 a side but more pixels than the whole budget.
    expect_error(
        s,
        img(json!({"width": 2000, "height": 1000})),
        413,
        "image_too_large",
        "--render-pixels",
    )
    .await;
    // Placements.
    let placed = |p| with(json!({"placements": p}));
    expect_error(
        s,
        placed(json!([{"head": 9, "position": [0, 0, 0]}])),
        400,
        "invalid_placement",
        "9",
    )
    .await;
    expect_error(
        s,
        placed(json!([{"head": 1, "position": [0, 0, 0], "scale": 0}])),
        400,
        "invalid_placement",
        "scale",
    )
    .await;
    expect_error(
        s,
        placed(json!([{"head": 1, "position": [0, 0, 0]}, {"head": 1, "position": [1, 0, 0]}])),
        400,
        "invalid_placement",
        "twice",
    )
    .await;
    expect_error(
        s,
        placed(json!([{"head": 1}])),
        400,
        "malformed_json",
        "position",
    )
    .await;
    // Heads: the frame endpoint's checks and messages.
    let heads = |h| json!({"heads": h, "wrap": false});
    expect_error(
        s,
        heads(json!([{"head": 4, "rig": "nobody", "clip": "talk", "frame": 0}])),
        404,
        "unknown_rig",
        "nobody",
    )
    .await;
    expect_error(
        s,
        heads(json!([{"head": 4, "rig": "default-head", "clip": "sing", "frame": 0}])),
        404,
        "unknown_clip",
        "sing",
    )
    .await;
    expect_error(
        s,
        heads(json!([{"head": 4, "rig": "default-head", "clip": "talk", "frame": 100000}])),
        400,
        "frame_out_of_range",
        "head 0 (id 4)",
    )
    .await;
    expect_error(
        s,
        heads(json!([{"head": 4, "rig": "default-head", "clip": "talk", "frame": 0, "lod": 99}])),
        400,
        "lod_out_of_range",
        "LOD 99",
    )
    .await;
    let many: Vec<_> = (0..51)
        .map(|i| json!({"head": i, "rig": "default-head", "clip": "talk", "frame": 0}))
        .collect();
    expect_error(s, json!({"heads": many}), 400, "too_many_heads", "51").await;
    expect_error(
        s,
        json!({"heads": [], "output": {"format": "f16"}}),
        400,
        "malformed_json",
        "output",
    )
    .await;
    // Bodies as for every crowd request.
    let r = s
        .client
        .send(
            Method::POST,
            "/v1/crowd/render",
            Some("text/plain"),
            None,
            Bytes::from(with(json!({})).to_string()),
        )
        .await
        .expect("transport");
    assert_eq!(r.status, 415);
    let r = s
        .client
        .render_raw(Bytes::from_static(&[0xFF; 9]), Encoding::Bincode)
        .await
        .expect("transport");
    assert_eq!(r.status, 400);
    assert_eq!(r.error().expect("JSON").error.code, "malformed_bincode");

    // A valid request: 503 render_unavailable, no Retry-After (waiting does not help), and the
    // message says why; /readyz says nothing renders; frames still work. Framing cameras are
    // valid too.
    for c in [
        json!({"frame": "faces"}),
        json!({"frame": "bodies", "fov_y": 20}),
    ] {
        let r = post_json(s, cam(c.clone())).await;
        assert_eq!(r.status, 503, "{c}: {}", String::from_utf8_lossy(&r.body));
    }
    let r = post_json(s, with(json!({}))).await;
    assert_eq!(r.status, 503);
    let e = r.error().expect("JSON");
    assert_eq!(e.error.code, "render_unavailable");
    assert!(
        e.error.message.contains("--render-backend off"),
        "{}",
        e.error.message
    );
    assert_eq!(r.retry_after, None);
    let ready = s
        .client
        .send(Method::GET, "/readyz", None, None, Bytes::new())
        .await
        .expect("readyz");
    let ready: crowdmorph_proto::Readiness = serde_json::from_slice(&ready.body).expect("JSON");
    assert_eq!(ready.renderer, None);
    let frame = crowdmorph_proto::CrowdFrameRequest {
        heads: vec![head(1, "talk", 3, 0)],
        output: crowdmorph_proto::OutputOptions::default(),
        wrap: true,
    };
    let (resp, _) = s
        .client
        .crowd_frame(&frame, Encoding::Bincode)
        .await
        .expect("frames still work");
    assert_eq!(resp.buffers.len(), 1);
    server.stop().await;
}

gpu_test!(
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn the_gpu_engine_draws_its_outputs_where_they_are() {
        // With the GPU engine the renderer shares its device and draws the blended buffers
        // without a readback: the picture is the CPU engine's golden, within its tolerance.
        let server = TestServer::start(ServerConfig {
            backend: crowdmorph::engine::BackendChoice::Gpu,
            ..ServerConfig::default()
        })
        .await;
        let ready = server
            .client
            .send(Method::GET, "/readyz", None, None, Bytes::new())
            .await
            .expect("readyz");
        let r: crowdmorph_proto::Readiness = serde_json::from_slice(&ready.body).expect("JSON");
        assert_eq!(r.backend, "gpu");
        let info = server.state.engine.info();
        assert_eq!(
            r.renderer, info.adapter,
            "the renderer is the engine's adapter"
        );
        let device = crowdmorph::render::crowd::RenderDevice::open(
            &server.state.engine,
            RenderBackend::Auto,
        )
        .expect("a renderer");
        assert!(
            device.shared,
            "on the engine's own device, not a second one"
        );
        let one = request(vec![head(1, "talk", 12, 0)], 320, 240);
        let img = png(&server, &one).await;
        let expected = Image::read_png(&golden("http_head.png")).expect("golden");
        let c = compare(&img, &expected, GOLDEN.per_pixel).expect("same size");
        assert!(
            c.fraction() <= GOLDEN.max_fraction,
            "GPU engine against the CPU golden: {c}"
        );
        assert!(
            !server.state.engine.info().degraded,
            "no device fault on the way"
        );
        server.stop().await;
    }
);

gpu_test!(
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    #[cfg_attr(
        not(crowdmorph_test_data),
        ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
    )]
    async fn the_gpu_memory_budget_refuses_rigs_and_renders_over_it_and_a_delete_gives_it_back() {
        use crowdmorph::engine::BackendChoice;
        use crowdmorph_client::ClientError;
        let glb = Bytes::from(
            std::fs::read(crate::util::data_dir().join("ict-facekit/ict_facekit_53.glb"))
                .expect("ICT FaceKit"),
        );
        // The GPU engine (lavapipe here) with the renderer on its device.
        let gpu = || ServerConfig {
            backend: BackendChoice::Gpu,
            ..ServerConfig::default()
        };
        // Under the default budget: what the built-in head and ICT FaceKit hold on the device, and
        // a delete gives the rig's share back.
        let server = TestServer::start(gpu()).await;
        let memory = gpu_pool(&server);
        let builtin = memory.used();
        let ict = upload_charged(&server, &memory, "ict", glb.clone()).await;
        assert!(ict > 0, "the rig is charged to the GPU budget");
        // /metrics reports the budget once: the renderer shares the engine's device and pool.
        let page = server.client.metrics().await.expect("metrics");
        let gauge = |name: &str| crowdmorph_client::metric(&page, name);
        assert_eq!(
            gauge("crowdmorph_gpu_memory_bytes"),
            Some(memory.used() as f64)
        );
        assert_eq!(
            gauge("crowdmorph_gpu_memory_limit_bytes"),
            Some(memory.limit() as f64)
        );
        server.client.delete_rig("ict").await.expect("delete");
        assert_eq!(
            memory.used(),
            builtin,
            "a delete gives the rig's GPU memory back"
        );
        server.stop().await;

        // A budget with room for the built-in head and half of ICT FaceKit: the upload is refused
        // with the JSON error naming the flag, as the host budget refuses (413 when the rig alone
        // is over it, 503 when it does not fit next to what is there), and leaves nothing charged.
        let cap = builtin + ict / 2;
        let server = TestServer::start(ServerConfig {
            gpu_memory: Some(cap),
            ..gpu()
        })
        .await;
        let memory = gpu_pool(&server);
        let at_start = memory.used();
        let e = server
            .client
            .upload_rig("ict", glb)
            .await
            .expect_err("over the GPU budget");
        let ClientError::Api {
            status,
            code,
            message,
        } = e
        else {
            panic!("not a JSON error: {e}");
        };
        assert!(
            (status, code.as_str()) == (413, "rig_too_large")
                || (status, code.as_str()) == (503, "memory_full"),
            "{status} {code}: {message}"
        );
        assert!(message.contains("--max-gpu-memory"), "{message}");
        assert_eq!(memory.used(), at_start, "a refused upload holds nothing");

        // A render whose targets alone (4× MSAA colour and depth: 32 bytes a pixel) exceed the
        // budget: 413 naming the flag. A small one still renders.
        let side = ((cap / 32) as f64).sqrt().ceil() as u32 + 16;
        let r = s_render_raw(&server, &request(vec![head(1, "talk", 0, 0)], side, side)).await;
        assert_eq!(r.status, 413, "{}", String::from_utf8_lossy(&r.body));
        let err = r.error().expect("JSON").error;
        assert_eq!(err.code, "image_too_large");
        assert!(err.message.contains("--max-gpu-memory"), "{}", err.message);
        png(&server, &request(vec![head(1, "talk", 0, 0)], 96, 64)).await;
        server.stop().await;
    }
);

/// A flat grid rig of `side` × `side` vertices (two triangles a cell) with `targets` targets
/// that each move every vertex, and a two-key clip `wave` driving them all: many triangles, so
/// its index buffer on the renderer's device is large. Returns the GLB and its triangle count.
fn grid_glb(side: u32, targets: usize) -> (Bytes, u64) {
    let positions: Vec<[f32; 3]> = (0..side * side)
        .map(|i| [(i % side) as f32, (i / side) as f32, 0.0])
        .collect();
    let mut indices = Vec::new();
    for y in 0..side - 1 {
        for x in 0..side - 1 {
            let i = y * side + x;
            indices.extend_from_slice(&[i, i + 1, i + side, i + 1, i + side + 1, i + side]);
        }
    }
    let deltas: Vec<Vec<[f32; 3]>> = (0..targets)
        .map(|t| {
            (0..side * side)
                .map(|i| [0.0, 0.0, 0.01 * ((i as usize + t) % 7) as f32 + 0.01])
                .collect()
        })
        .collect();
    let mut b = crate::util::builder::Builder::new();
    let mesh = b.mesh_with_targets(&positions, Some(&indices), &deltas, None);
    let node = b.node(Some(mesh));
    let values: Vec<f32> = (0..2 * targets).map(|i| (i / targets) as f32).collect();
    b.animation_weights("wave", node, &[0.0, 1.0], &values, "LINEAR");
    b.scene(&[node]);
    (Bytes::from(b.to_glb()), indices.len() as u64 / 3)
}

gpu_test!(
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_cached_topology_gives_way_to_a_rig_upload_and_the_next_render_uploads_it_again() {
        // The server keeps each rendered rig's index buffer for the next render, on the engine's
        // device. With a GPU budget that has room for two copies of a rig and half that index
        // buffer, a second upload after a render frees it (with the render's kept targets and the
        // engine's idle batch buffers) instead of being refused with 503 forever.
        use crowdmorph::engine::BackendChoice;
        let (glb, triangles) = grid_glb(96, 32);
        let topology = triangles * 12;
        let gpu = || ServerConfig {
            backend: BackendChoice::Gpu,
            ..ServerConfig::default()
        };
        let grid = |rig: &str| {
            request(
                vec![Head {
                    head: 1,
                    rig: rig.into(),
                    clip: "wave".into(),
                    frame: 0,
                    lod: 0,
                    ..Default::default()
                }],
                96,
                64,
            )
        };

        // Under the default budget: what the rig holds, and what a render of it leaves kept.
        let server = TestServer::start(gpu()).await;
        let memory = gpu_pool(&server);
        let base = memory.used();
        let rig = upload_charged(&server, &memory, "a", glb.clone()).await;
        let want = png(&server, &grid("a")).await;
        let kept = memory.used() - base - rig;
        // Less than the rig: the render fits next to one copy under the budget below.
        assert!(
            kept > topology && kept < rig,
            "a render keeps {kept} bytes: more than the index buffer ({topology}), less than the \
             rig ({rig})"
        );
        server.stop().await;

        let server = TestServer::start(ServerConfig {
            gpu_memory: Some(base + 2 * rig + topology / 2),
            ..gpu()
        })
        .await;
        let memory = gpu_pool(&server);
        assert_eq!(memory.used(), base);
        server
            .client
            .upload_rig("a", glb.clone())
            .await
            .expect("upload");
        png(&server, &grid("a")).await;
        assert_eq!(
            memory.used(),
            base + rig + kept,
            "the render's memory is kept"
        );
        server
            .client
            .upload_rig("b", glb)
            .await
            .expect("what is kept for reuse makes room for a second copy");
        assert_eq!(
            memory.used(),
            base + 2 * rig,
            "the cached topology, kept targets and idle batch buffers were given back"
        );

        // Renders still work: with the first copy deleted, the second draws the same picture,
        // uploading its topology and making new targets.
        server.client.delete_rig("a").await.expect("delete");
        let again = png(&server, &grid("b")).await;
        assert!(again == want, "the picture after the reclaim differs");
        assert_eq!(
            memory.used(),
            base + rig + kept,
            "kept again for the next render"
        );
        server.stop().await;
    }
);

/// The GPU memory budget of a server running the GPU engine.
fn gpu_pool(server: &TestServer) -> std::sync::Arc<crowdmorph::budget::MemoryPool> {
    server
        .state
        .engine
        .gpu_memory()
        .expect("GPU engine")
        .clone()
}

/// Uploads `glb` as rig `id`; the bytes of `pool` the rig took.
async fn upload_charged(
    server: &TestServer,
    pool: &crowdmorph::budget::MemoryPool,
    id: &str,
    glb: Bytes,
) -> u64 {
    let before = pool.used();
    server.client.upload_rig(id, glb).await.expect("upload");
    pool.used() - before
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_renders_placements_are_charged_for_the_map_its_layout_builds() {
    // The layout maps each placement's id to its matrix (up to ≈ 220 bytes a placement)
    // before it checks them against the heads. 5,000 placements naming no head of a one-head
    // render are 160 KB decoded but ≈ 1 MB with their map: under 512 KiB of queue memory they
    // are refused before the map is built (413); charged at their decoded size they were
    // mapped uncharged and then refused as naming no head (400).
    let server = TestServer::start(ServerConfig {
        queue_memory_bytes: 512 << 10,
        ..ServerConfig::default()
    })
    .await;
    let render = |placements: Vec<Placement>| RenderRequest {
        heads: vec![Head {
            head: 0,
            rig: "default-head".into(),
            clip: "talk".into(),
            frame: 3,
            lod: 0,
            ..Default::default()
        }],
        image: Some(ImageOptions {
            width: 64,
            height: 48,
            ..ImageOptions::default()
        }),
        wrap: true,
        placements: Some(placements),
        camera: None,
    };
    let place = |head: u64| Placement {
        head,
        position: [0.0; 3],
        yaw: 0.0,
        scale: 1.0,
    };
    // The head's own placement draws under this budget.
    let one = render(vec![place(0)]);
    let reply = server
        .client
        .render(&one, Encoding::Bincode)
        .await
        .expect("render");
    decode_png(&reply, &one);
    let strays = render((1..=5_000).map(place).collect());
    super::api_error(
        server.client.render(&strays, Encoding::Bincode).await,
        413,
        "queue_memory_exceeded",
    );
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_renders_heads_are_charged_until_its_frame_is_drawn() {
    // Each head of a render holds its decoded form, names and what admission builds for it
    // (box, transform, instance: ≈ 350 bytes) until its frame is drawn. 100 clones of the
    // default head fit 512 KiB of queue memory beside their one 174 KB blend; 2,000 clones'
    // heads alone are more than all of it, which used to be drawn uncharged.
    let server = TestServer::start(ServerConfig {
        queue_memory_bytes: 512 << 10,
        ..ServerConfig::default()
    })
    .await;
    let crowd = |n: u64| RenderRequest {
        heads: (0..n)
            .map(|h| Head {
                head: h,
                rig: "default-head".into(),
                clip: "talk".into(),
                frame: 3,
                lod: 0,
                ..Default::default()
            })
            .collect(),
        image: Some(ImageOptions {
            width: 64,
            height: 48,
            ..ImageOptions::default()
        }),
        wrap: true,
        placements: None,
        camera: None,
    };
    png(&server, &crowd(100)).await;
    super::api_error(
        server.client.render(&crowd(2_000), Encoding::Json).await,
        413,
        "queue_memory_exceeded",
    );
    server.stop().await;
}

gpu_test!(
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_textured_rigs_textures_are_charged_to_the_gpu_budget_and_freed_by_its_delete() {
        use crowdmorph::budget::Budget;
        use crowdmorph::engine::BackendChoice;
        use crowdmorph::rig::Mips;
        use crowdmorph::server::registry::{ClipLayout, NewEntry, RigEntry, quantization_box};
        use std::sync::Arc;
        // The GPU engine (lavapipe) with the renderer on its device, so one pool holds both.
        let server = TestServer::start(ServerConfig {
            backend: BackendChoice::Gpu,
            ..ServerConfig::default()
        })
        .await;
        let memory = gpu_pool(&server);
        // A frame of the built-in head first: the renderer's kept targets are then in `before`.
        let req = |rig: &str| {
            let mut h = head(1, "talk", 3, 0);
            h.rig = rig.into();
            request(vec![h], 96, 64)
        };
        png(&server, &req("default-head")).await;
        let before = memory.used();
        // No import fills textures yet: the embedded head with generated ones (three 64²
        // images, full chains), registered as an upload would register it.
        let rig = Arc::new(crowdmorph::render::offline::with_generated_textures(
            &crowdmorph::embedded::default_rig(),
            64,
        ));
        let texture_bytes = 3 * Mips::chain_bytes(64, 64);
        let prepared = server.state.engine.prepare(rig.clone()).expect("prepare");
        server
            .state
            .registry
            .insert(Arc::new(RigEntry::new(NewEntry {
                id: "textured".into(),
                builtin: None,
                prepared,
                generation: server.state.registry.generation(),
                layout: ClipLayout::default(),
                charge: Budget::new(u64::MAX, "", None).keep(0),
                qbox: quantization_box(&rig),
            })));
        let registered = memory.used();
        let img = png(&server, &req("textured")).await;
        let drawn = memory.used();
        assert!(
            drawn - registered >= texture_bytes,
            "the first frame uploads the textures: {} bytes more, {texture_bytes} of textures",
            drawn - registered
        );
        // Drawn with them: not the untextured head.
        let plain = png(&server, &req("default-head")).await;
        let diff = compare(&img, &plain, 8).expect("same size");
        assert!(diff.differing > 100, "{} pixels differ", diff.differing);
        // A second frame reuses the cached topology and its textures.
        png(&server, &req("textured")).await;
        assert_eq!(memory.used(), drawn);
        server.client.delete_rig("textured").await.expect("delete");
        assert_eq!(
            memory.used(),
            before,
            "the delete frees the rig, its topology and its textures"
        );
        server.stop().await;
    }
);
