//! The server's render of a textured, morphed rig against what three.js draws of the same file:
//! three from npm (the version `.ci/run` pins) in headless Chromium, the page of
//! `tests/threejs/`, with the same camera, the same lights (the renderer's key and fill
//! directional lights and hemisphere ambient, from `brdf::reference_lights`), the same weights,
//! background and size, sRGB output and no tone mapping. The two pictures must agree to a
//! luminance SSIM of at least [`MIN_SSIM`] over the pixels either draws
//! (`util::image::ssim_masked`).
//!
//! Why three.js: it is the renderer most users compare a glTF file's picture with, so a
//! difference here (a flipped texture, a wrong sRGB decode, a light from the wrong side, a
//! culled face) is one they would see. The server uploads the rig as a self-contained GLB
//! (`util::pack`), three loads the original `.gltf` with its external buffers and images,
//! served from the shared rigs by a loopback file server of this test.
//!
//! SSIM forgives two things, so the test checks them beside it: an even shift of brightness (a
//! light too strong or weak: the mean luminance difference must stay within
//! [`MAX_LUMA_DIFFERENCE`]), and nothing (a control: three's picture with every texture read
//! upside down must score below [`MIN_SSIM`], or the comparison could not see a flipped texture
//! coordinate; on lavapipe against SwiftShader it scores 0.36 and −0.15).
//!
//! The second test draws what a three.js client of the server draws: `model.glb` (the rig's
//! mesh, materials and textures, no morph targets) loaded once, then one crowd frame's vertex
//! buffers (f32 positions and normals, cut per primitive as the mesh endpoint lists them)
//! written into its meshes. It must match the server's render of the same head as closely.
//!
//! The server's light set is fixed (no request field changes it), so the issue's "one
//! directional + ambient" is met by giving three exactly the server's lights instead.
//!
//! On a failure both pictures and the SSIM map are left in `util::image::failure_dir()` as
//! `threejs-<rig>-{server,three,ssim}.png`.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use axum::extract::State;
use axum::http::{StatusCode, Uri, header};
use axum::response::{IntoResponse, Response};
use crowdmorph::render::{brdf, scene};
use crowdmorph::server::ServerConfig;
use crowdmorph_client::Encoding;
use crowdmorph_proto::{CameraSpec, CrowdFrameRequest, Format, Head, LiveWeights, OutputOptions};
use serde_json::{Value, json};

use super::TestServer;
use crate::util::browser::{Browser, Cdp, base64_decode};
use crate::util::gpu_test;
use crate::util::image::{Image, failure_dir, ssim_masked};

/// The least luminance SSIM, over the drawn pixels, of the server's picture and three's.
const MIN_SSIM: f64 = 0.9;

/// The largest mean luminance difference (0..=255) of the two pictures where both draw. The
/// renderers differ by design by about 2: the server's direct diffuse is glTF's
/// `(1 − F)·c_diff/π` (Appendix B), three's `c_diff/π`, and three adds a little roughness
/// where normals curve (`geometryRoughness`). A wrong light intensity or sRGB step is tens.
const MAX_LUMA_DIFFERENCE: f64 = 6.0;

/// The background of both pictures, sRGB: a colour neither rig draws, so the drawn pixels are
/// told apart from it.
const BACKGROUND: [u8; 3] = [40, 44, 52];

/// One comparison: a shared rig, the weights its head gets, and the camera.
struct Case {
    /// The rig's name on the server and in the failure files.
    name: &'static str,
    /// The `.gltf`, under the shared rigs' `khronos/` folder.
    file: &'static str,
    /// Named live weights; a target the file leaves unnamed is `target_<i>` (the importer's
    /// name; the page maps it to index `i`).
    weights: &'static [(&'static str, f32)],
    position: [f32; 3],
    target: [f32; 3],
    fov_y: f32,
    near: f32,
    far: f32,
    size: (u32, u32),
}

const CASES: [Case; 2] = [
    // Two primitives, both double-sided: a base with TinyGrid.png and an occlusion map on
    // texture coordinate set 1, and a strip with ColorSwatches.png whose eight targets raise
    // its parts; seen from the front and above, two of them set.
    Case {
        name: "MorphStressTest",
        file: "MorphStressTest/glTF/MorphStressTest.gltf",
        weights: &[("Key 1", 1.0), ("Key 5", 0.5)],
        position: [0.0, 2.0, 3.6],
        target: [0.0, 0.15, 0.0],
        fov_y: 40.0,
        near: 0.5,
        far: 20.0,
        size: (480, 320),
    },
    // A plane in red and a square in green, each the base colour factor times uv_texture.jpg
    // (wrapped), single-sided; its one target (unnamed in the file) at 0.7.
    Case {
        name: "MorphPrimitivesTest",
        file: "MorphPrimitivesTest/glTF/MorphPrimitivesTest.gltf",
        weights: &[("target_0", 0.7)],
        position: [0.0, 1.2, 1.3],
        target: [0.0, 0.1, 0.0],
        fov_y: 45.0,
        near: 0.1,
        far: 10.0,
        size: (400, 300),
    },
];

/// three's npm package folder, as `build.rs` found it.
fn three_dir() -> PathBuf {
    PathBuf::from(option_env!("CROWDMORPH_THREEJS_DIR").unwrap_or_else(|| {
        panic!(
            "three.js is not installed (npm install --prefix target/threejs three@0.170.0, then \
             touch build.rs)"
        )
    }))
}

/// A loopback file server for the page: each `(prefix, folder)` serves the folder's files
/// under the prefix, with the content types module scripts and images need. Paths with
/// empty, `.` or `..` segments, or escapes, are 404: only files below the folders are served.
async fn file_server(
    roots: Vec<(&'static str, PathBuf)>,
) -> (SocketAddr, tokio::task::JoinHandle<()>) {
    async fn serve(State(roots): State<Arc<Vec<(&'static str, PathBuf)>>>, uri: Uri) -> Response {
        let path = uri.path();
        let Some((rest, dir)) = roots
            .iter()
            .find_map(|(prefix, dir)| Some((path.strip_prefix(prefix)?, dir)))
        else {
            return StatusCode::NOT_FOUND.into_response();
        };
        let plain = |s: &str| !s.is_empty() && s != "." && s != ".." && !s.contains(['%', '\\']);
        if !rest.split('/').all(plain) {
            return StatusCode::NOT_FOUND.into_response();
        }
        let kind = match rest.rsplit_once('.').map(|(_, ext)| ext) {
            Some("html") => "text/html; charset=utf-8",
            Some("js") => "text/javascript; charset=utf-8",
            Some("gltf") => "model/gltf+json",
            Some("png") => "image/png",
            Some("jpg" | "jpeg") => "image/jpeg",
            Some("glb") => "model/gltf-binary",
            _ => "application/octet-stream",
        };
        match tokio::fs::read(dir.join(rest)).await {
            Ok(bytes) => (
                [
                    (header::CONTENT_TYPE, kind),
                    (header::CACHE_CONTROL, "no-store"),
                ],
                bytes,
            )
                .into_response(),
            Err(_) => StatusCode::NOT_FOUND.into_response(),
        }
    }
    let app = axum::Router::new()
        .fallback(serve)
        .with_state(Arc::new(roots));
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind the file server");
    let addr = listener.local_addr().expect("addr");
    let task = tokio::spawn(async move {
        axum::serve(listener, app).await.expect("the file server");
    });
    (addr, task)
}

/// The server's picture of `case`: one head at the origin (a placement, so the rig is not
/// moved to a grid cell), with the case's weights and camera.
async fn server_picture(server: &TestServer, case: &Case) -> Image {
    let weights: Vec<(String, f32)> = case
        .weights
        .iter()
        .map(|&(n, w)| (n.to_string(), w))
        .collect();
    let origin = ([0.0; 3], 0.0, 1.0);
    super::render_one(
        server,
        case.name,
        &weights,
        origin,
        camera_spec(case),
        case.size,
        BACKGROUND,
    )
    .await
}

/// The image of a PNG data URL (a canvas's `toDataURL`).
fn data_url_image(url: &Value) -> Image {
    let png = url
        .as_str()
        .and_then(|u| u.strip_prefix("data:image/png;base64,"))
        .unwrap_or_else(|| panic!("not a PNG data URL: {:.80}", url.to_string()));
    Image::decode_png(&base64_decode(png)).expect("three's PNG")
}

fn camera_spec(case: &Case) -> CameraSpec {
    CameraSpec {
        fov_y: case.fov_y,
        near: Some(case.near),
        far: Some(case.far),
        ..CameraSpec::looking(case.position, case.target)
    }
}

/// What the page needs to draw `case` as the server does: the server's own view of the camera
/// (its up vector included) and its lights for that view.
fn page_config(case: &Case) -> Value {
    let view = scene::camera_view(&camera_spec(case), None).expect("a valid camera");
    let lights = brdf::reference_lights(&view).expect("a view with a direction");
    let light = |l: brdf::DirectionalLight| json!({"direction": l.direction.to_array(), "intensity": l.intensity});
    json!({
        "model": format!("/data/{}", case.file),
        "width": case.size.0,
        "height": case.size.1,
        "background": BACKGROUND,
        "camera": {
            "position": view.eye.to_array(),
            "target": view.target.to_array(),
            "up": view.up.to_array(),
            "fovY": view.fov_y_deg,
            "near": view.near,
            "far": view.far,
        },
        "lights": {
            "key": light(lights.key),
            "fill": light(lights.fill),
            "up": lights.up.to_array(),
            "sky": lights.sky.to_array(),
            "ground": lights.ground.to_array(),
        },
        "weights": case.weights.iter().map(|&(n, w)| (n.to_string(), json!(w))).collect::<serde_json::Map<_, _>>(),
    })
}

/// How much brighter `a` is than `b` on average (Rec. 709 luma of the sRGB values, 0..=255)
/// over the pixels both draw. SSIM's luminance term forgives an even shift of brightness (a
/// light too strong or too weak), which this number shows.
fn mean_luma_difference(a: &Image, b: &Image) -> f64 {
    let luma =
        |p: &[u8]| 0.2126 * f64::from(p[0]) + 0.7152 * f64::from(p[1]) + 0.0722 * f64::from(p[2]);
    let drawn = |p: &[u8]| (0..3).any(|c| p[c].abs_diff(BACKGROUND[c]) > 2);
    let (mut sum, mut n) = (0f64, 0usize);
    for (p, q) in a.rgba.chunks_exact(4).zip(b.rgba.chunks_exact(4)) {
        if drawn(p) && drawn(q) {
            sum += luma(p) - luma(q);
            n += 1;
        }
    }
    sum / n.max(1) as f64
}

/// Fraction of an image's pixels further than 2 from the background in some channel.
fn drawn_fraction(img: &Image) -> f64 {
    let drawn = img
        .rgba
        .chunks_exact(4)
        .filter(|p| (0..3).any(|c| p[c].abs_diff(BACKGROUND[c]) > 2))
        .count();
    drawn as f64 / (img.width * img.height) as f64
}

/// One comparison's outcome, asserted once the browser and servers are down.
struct Outcome {
    name: String,
    ssim: f64,
    luma: f64,
    drawn: (f64, f64),
    pass: bool,
}

impl Outcome {
    fn assert(&self) {
        let Outcome {
            name, ssim, luma, ..
        } = self;
        assert!(
            self.pass,
            "{name}: SSIM {ssim:.4} (at least {MIN_SSIM}), luminance difference \
             {luma:+.2}/255 (at most ±{MAX_LUMA_DIFFERENCE}), drawn {:.1} % by the server \
             and {:.1} % by three.js (at least 10 % each); pictures in {}",
            self.drawn.0 * 100.0,
            self.drawn.1 * 100.0,
            failure_dir().display()
        );
    }
}

/// Draws `config` with three.js on the page `cdp` shows and compares it with `server_img`
/// (`name` names the failure files); also draws the flipped-texture control, which must fail.
async fn compare(cdp: &mut Cdp, name: &str, server_img: &Image, config: &Value) -> Outcome {
    let drawn = cdp.eval(&format!("window.renderReference({config})")).await;
    println!("{name}: three.js {}", drawn["info"]);
    let three_img = data_url_image(&drawn["png"]);
    assert_eq!(
        (three_img.width, three_img.height),
        (server_img.width, server_img.height)
    );
    let ssim = ssim_masked(server_img, &three_img, BACKGROUND).expect("drawn pixels");
    let (fs, ft) = (drawn_fraction(server_img), drawn_fraction(&three_img));
    let luma = mean_luma_difference(server_img, &three_img);
    // The control: three's picture with every texture upside down must fail, or the
    // comparison could not tell a flipped texture coordinate from a right one.
    let mut flipped = config.clone();
    flipped["flipV"] = json!(true);
    let flipped = cdp
        .eval(&format!("window.renderReference({flipped})"))
        .await;
    let control = ssim_masked(server_img, &data_url_image(&flipped["png"]), BACKGROUND)
        .expect("drawn pixels")
        .mean;
    println!(
        "{name}: SSIM {:.4} over {} pixels (drawn: server {:.1} %, three.js {:.1} %), \
         server − three.js luminance {luma:+.2}/255; with three's textures flipped: \
         SSIM {control:.4}",
        ssim.mean,
        ssim.pixels,
        fs * 100.0,
        ft * 100.0
    );
    assert!(
        control < MIN_SSIM,
        "{name}: three's picture with flipped textures still scores {control:.4}"
    );
    // Not a trivial comparison: the rig fills a good part of both pictures.
    let enough = fs > 0.1 && ft > 0.1;
    let pass = enough && ssim.mean >= MIN_SSIM && luma.abs() <= MAX_LUMA_DIFFERENCE;
    if !pass {
        let dir = failure_dir();
        for (what, img) in [
            ("server", server_img),
            ("three", &three_img),
            ("ssim", &ssim.map),
        ] {
            img.write_png(&dir.join(format!("threejs-{name}-{what}.png")))
                .expect("write a failure image");
        }
        println!("{name}: pictures in {}", dir.display());
    }
    Outcome {
        name: name.to_string(),
        ssim: ssim.mean,
        luma,
        drawn: (fs, ft),
        pass,
    }
}

/// A server with every case's rig uploaded (as a self-contained GLB), and the page loaded
/// from a loopback file server that also serves `extra` (a prefix and a folder).
async fn start(
    extra: Option<(&'static str, PathBuf)>,
) -> (TestServer, Browser, Cdp, tokio::task::JoinHandle<()>) {
    let server = TestServer::start(ServerConfig::default()).await;
    let khronos = crate::util::data_dir().join("khronos");
    for case in &CASES {
        let glb = crate::util::pack::self_contained_glb(&khronos.join(case.file));
        server
            .client
            .upload_rig(case.name, glb.into())
            .await
            .expect("upload");
    }
    let page_dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/threejs");
    let mut roots = vec![
        ("/page/", page_dir),
        ("/three/", three_dir()),
        ("/data/", khronos),
    ];
    roots.extend(extra);
    let (addr, files) = file_server(roots).await;

    let mut browser = Browser::launch();
    let mut cdp = browser.page().await;
    cdp.call(
        "Page.navigate",
        json!({"url": format!("http://{addr}/page/page.html")}),
    )
    .await;
    cdp.wait_for(
        "the page's module",
        "typeof window.renderReference",
        Duration::from_secs(60),
        |v| v == "function",
    )
    .await;
    (server, browser, cdp, files)
}

/// Checks the page logged no error, stops everything, then asserts each outcome (so a failure
/// leaves no browser or server behind).
async fn finish(
    server: TestServer,
    browser: Browser,
    cdp: Cdp,
    files: tokio::task::JoinHandle<()>,
    results: &[Outcome],
) {
    let errors = cdp.errors();
    drop(cdp);
    drop(browser);
    files.abort();
    server.stop().await;
    assert!(errors.is_empty(), "the page logged errors: {errors:#?}");
    results.iter().for_each(Outcome::assert);
}

/// A test of this file: it needs a Vulkan adapter, the shared rigs, Chromium and three.js,
/// and says which is missing when skipped.
macro_rules! threejs_test {
    ($($item:tt)*) => {
        gpu_test!(
            #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
            #[cfg_attr(
                not(crowdmorph_test_data),
                ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
            )]
            #[cfg_attr(
                not(crowdmorph_chromium),
                ignore = "no Chromium (apt-get install chromium, or set CROWDMORPH_CHROMIUM and touch build.rs)"
            )]
            #[cfg_attr(
                not(crowdmorph_threejs),
                ignore = "needs three.js: npm install --prefix target/threejs three@0.170.0, then touch build.rs"
            )]
            $($item)*
        );
    };
}

threejs_test!(
    async fn textured_morphed_rigs_render_as_three_js_draws_them() {
        let (server, browser, mut cdp, files) = start(None).await;
        let mut results = Vec::new();
        for case in &CASES {
            let server_img = server_picture(&server, case).await;
            results.push(compare(&mut cdp, case.name, &server_img, &page_config(case)).await);
        }
        finish(server, browser, cdp, files, &results).await;
    }
);

/// The vertex buffers of one crowd frame of `case` (f32 with normals, the case's weights),
/// cut per primitive as `GET /v1/rigs/{id}/mesh` lists them: what a three.js client writes
/// into the meshes of `model.glb`.
async fn frame_buffers(server: &TestServer, case: &Case) -> Value {
    let req = CrowdFrameRequest {
        heads: vec![Head::live(
            1,
            case.name,
            LiveWeights::Named(
                case.weights
                    .iter()
                    .map(|&(n, w)| (n.to_string(), w))
                    .collect(),
            ),
        )],
        output: OutputOptions {
            normals: true,
            format: Format::F32,
        },
        wrap: true,
    };
    let (frame, _) = server
        .client
        .crowd_frame(&req, Encoding::Bincode)
        .await
        .expect("a crowd frame");
    let buffer = &frame.buffers[frame.heads[0].buffer as usize];
    let positions = buffer.positions.to_f32();
    let normals = buffer.normals.as_ref().expect("normals asked for").to_f32();
    let mesh = server
        .client
        .mesh(case.name, Encoding::Bincode)
        .await
        .expect("the mesh");
    let cut = |all: &[f32]| -> Vec<Value> {
        mesh.primitives
            .iter()
            .map(|p| {
                let (a, n) = (p.first_vertex as usize * 3, p.vertices as usize * 3);
                json!(all[a..a + n])
            })
            .collect()
    };
    json!({"positions": cut(&positions), "normals": cut(&normals)})
}

threejs_test!(
    async fn three_js_draws_the_servers_vertex_buffers_textured_from_model_glb() {
        // What a three.js client does: load `model.glb` once (no morph targets), then write
        // each crowd frame's positions and normals into its meshes. Drawn so, it must look as
        // the server's own render of the same head.
        let models = crate::server::temp_dir("threejs-models");
        let (server, browser, mut cdp, files) = start(Some(("/model/", models.clone()))).await;
        let mut results = Vec::new();
        for case in &CASES {
            let glb = server
                .client
                .model_glb(case.name, 0)
                .await
                .expect("model.glb");
            std::fs::write(models.join(format!("{}.glb", case.name)), &glb).expect("write");
            let mut config = page_config(case);
            config["model"] = json!(format!("/model/{}.glb", case.name));
            config["weights"] = json!({});
            config["frame"] = frame_buffers(&server, case).await;
            let server_img = server_picture(&server, case).await;
            let name = format!("{}-model-glb", case.name);
            results.push(compare(&mut cdp, &name, &server_img, &config).await);
        }
        finish(server, browser, cdp, files, &results).await;
    }
);
