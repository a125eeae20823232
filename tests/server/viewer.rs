//! The browser viewer (`clients/web`, `GET /viewer`): its files are served from the binary with
//! their content types and nothing else is; and, end to end in real headless Chromium driven
//! over the DevTools protocol, the page creates a session, streams q16 ticks over the WebSocket
//! and draws a lit crowd, with no console error, while its controls change the session. The page
//! asks for temporal residuals packed with deflate (`TickDelta` inside `PackedMessage`), and what
//! it decodes is checked bit for bit against a plain q16 viewer of the same session (Rust, over
//! its own WebSocket) at the same tick; so is the page's `?temporal=0` plain mode.
//!
//! The end-to-end test runs in real time (the page streams while the server ticks), bounded by
//! generous deadlines that only decide when to give up, never what passes. Its screenshot is
//! kept at `$CROWDMORPH_VIEWER_SCREENSHOT`, else `target/viewer-screenshot.png`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use bytes::Bytes;
use crowdmorph::server::ServerConfig;
use crowdmorph_client::{Encoding, Method};
use crowdmorph_proto::{CameraSpec, MeshResponse, Received, SessionInfo, StreamState};
use futures_util::{SinkExt, StreamExt};
use serde_json::{Value, json};
use tokio_tungstenite::tungstenite::Message;

use super::TestServer;
use crate::util::browser::{Browser, Cdp, Request, base64_decode};
use crate::util::image::{Image, ssim_masked};

/// The files the page loads, with the types browsers insist on for them.
const FILES: &[(&str, &str)] = &[
    ("/viewer", "text/html"),
    ("/viewer/index.html", "text/html"),
    ("/viewer/viewer.css", "text/css"),
    ("/viewer/main.js", "text/javascript"),
    ("/viewer/api.js", "text/javascript"),
    ("/viewer/bincode.js", "text/javascript"),
    ("/viewer/camera.js", "text/javascript"),
    ("/viewer/render.js", "text/javascript"),
];

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn viewer_files_are_served_with_their_types_and_nothing_else_is() {
    let server = TestServer::start(ServerConfig {
        // The page itself needs no token, whatever the server's.
        admin_token: Some("secret".into()),
        ..ServerConfig::default()
    })
    .await;
    let get = |path: String| {
        let client = server.client.clone();
        async move {
            client
                .send(Method::GET, &path, None, None, Bytes::new())
                .await
                .unwrap()
        }
    };
    let mut referenced = Vec::new();
    for (path, kind) in FILES {
        let reply = get(path.to_string()).await;
        assert_eq!(reply.status, 200, "{path}");
        let ct = reply.content_type.clone().unwrap_or_default();
        assert!(ct.starts_with(kind), "{path}: content-type {ct}");
        assert!(
            reply.header("content-security-policy").is_some(),
            "{path}: no CSP"
        );
        assert_eq!(reply.header("x-content-type-options"), Some("nosniff"));
        // Every file the page names must be one the server serves: collect the references.
        let text = String::from_utf8(reply.body.to_vec()).expect("utf-8");
        for quote in ['"', '\''] {
            for (i, _) in text.match_indices(&format!("{quote}/viewer/")) {
                let rest = &text[i + 1..];
                referenced.push(rest[..rest.find(quote).unwrap()].to_string());
            }
            for (i, _) in text.match_indices(&format!("from {quote}./")) {
                let rest = &text[i + 8..];
                referenced.push(format!("/viewer/{}", &rest[..rest.find(quote).unwrap()]));
            }
        }
    }
    assert!(referenced.len() >= 6, "references found: {referenced:?}");
    for path in referenced {
        assert!(
            FILES.iter().any(|(p, _)| *p == path),
            "the page loads {path}, which this test does not check"
        );
        assert_eq!(get(path.clone()).await.status, 200, "{path}");
    }
    for bad in [
        "/viewer/secret.js",
        "/viewer/..%2FCargo.toml",
        "/viewer/../Cargo.toml",
        "/viewer/README.md",
        "/viewer/main.js.map",
        "/viewer/",
    ] {
        let reply = get(bad.to_string()).await;
        assert_eq!(reply.status, 404, "{bad}");
        let err = reply.error().expect("a JSON error body");
        assert!(
            ["no_route", "not_found"].contains(&err.error.code.as_str()),
            "{bad}: {err:?}"
        );
    }
    server.stop().await;
}

/// The page's error box, empty while hidden (or while the page is still loading).
const ERROR_TEXT: &str =
    "(e => e && !e.hidden ? e.textContent : '')(document.getElementById('error'))";

/// Where a test's screenshot is kept: `$CROWDMORPH_VIEWER_SCREENSHOT`, else
/// `target/viewer-screenshot.png`, with `suffix` added to the file's stem.
fn screenshot_path(suffix: &str) -> PathBuf {
    let path = std::env::var_os("CROWDMORPH_VIEWER_SCREENSHOT")
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            Path::new(env!("CARGO_MANIFEST_DIR")).join("target/viewer-screenshot.png")
        });
    let stem = path.file_stem().unwrap_or_default().to_string_lossy();
    path.with_file_name(format!("{stem}{suffix}.png"))
}

/// A screenshot of the page, written to `path` first (for whoever looks into a failure).
/// Waits 30 more ticks of the page's clock (`tick`, an expression) and checks the page made
/// no HTTP request past the first `before` meanwhile: what it fetches, it fetches once.
async fn no_requests_for_30_ticks(cdp: &mut Cdp, tick: &str, before: usize) {
    let now = cdp.eval(tick).await.as_u64().unwrap();
    cdp.wait_for("30 more ticks", tick, Duration::from_secs(90), |v| {
        v.as_u64().unwrap_or(0) >= now + 30
    })
    .await;
    let _ = cdp.eval("0").await; // Reads the events that came meanwhile.
    let later = cdp.requests();
    assert_eq!(
        later.len(),
        before,
        "HTTP requests while the stream ticked: {:#?}",
        &later[before..]
    );
}

/// A screenshot of the page (written to `screenshot_path(suffix)`) with the view it shows and
/// the panel's rectangle, checked not to have moved while it was taken.
async fn still_screenshot(cdp: &mut Cdp, suffix: &str) -> (Value, PathBuf, Image, Value) {
    let view = cdp.eval("window.crowdmorphViewer.view").await;
    let path = screenshot_path(suffix);
    let image = screenshot(cdp, &path).await;
    assert_eq!(
        cdp.eval("window.crowdmorphViewer.view").await,
        view,
        "the view changed while the screenshot was taken"
    );
    let panel = cdp
        .eval(
            "JSON.parse(JSON.stringify(document.getElementById('panel').getBoundingClientRect()))",
        )
        .await;
    (view, path, image, panel)
}

async fn screenshot(cdp: &mut Cdp, path: &Path) -> Image {
    let shot = cdp
        .call("Page.captureScreenshot", json!({"format": "png"}))
        .await;
    let png = base64_decode(shot["data"].as_str().unwrap());
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).unwrap();
    }
    std::fs::write(path, &png).unwrap();
    println!("viewer screenshot: {}", path.display());
    Image::decode_png(&png).unwrap()
}

/// Chromium with one blank page attached over the DevTools protocol, its console, log and page
/// events on, and the `extra` domains (`Network.enable`, ...).
async fn open_page(extra: &[&str]) -> (Browser, Cdp) {
    let mut browser = Browser::launch();
    let mut cdp = browser.page_with(extra).await;
    cdp.shown_error = Some(ERROR_TEXT);
    (browser, cdp)
}

/// The viewer's background, sRGB (`BACKGROUND` in clients/web/render.js).
const BACKGROUND: [u8; 3] = [46, 50, 56];

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_chromium),
    ignore = "no Chromium (apt-get install chromium, or set CROWDMORPH_CHROMIUM and touch build.rs)"
)]
async fn the_viewer_streams_and_draws_a_lit_crowd_in_headless_chromium() {
    let server = TestServer::start(ServerConfig::default()).await;
    let (browser, mut cdp) = open_page(&[]).await;
    cdp.call(
        "Page.navigate",
        json!({"url": format!("http://{}/viewer", server.addr)}),
    )
    .await;

    // The tick counter advances: the page created a session and the stream runs.
    let tick = "Number(document.getElementById('tick')?.textContent || 0)";
    let first = cdp
        .wait_for("the first tick", tick, Duration::from_secs(120), |v| {
            v.as_u64().unwrap_or(0) > 0
        })
        .await
        .as_u64()
        .unwrap();
    cdp.wait_for("ten more ticks", tick, Duration::from_secs(90), |v| {
        v.as_u64().unwrap_or(0) >= first + 10
    })
    .await;
    // Every head of the default scene is drawn (topology fetched, buffers uploaded).
    let drawn = "Number(document.getElementById('view').dataset.drawn || 0)";
    cdp.wait_for("25 heads drawn", drawn, Duration::from_secs(90), |v| {
        v.as_u64() == Some(25)
    })
    .await;
    // The counters report what arrives.
    cdp.wait_for(
        "the bytes/s counter",
        "document.getElementById('bps').textContent",
        Duration::from_secs(10),
        |v| v.as_str().is_some_and(|s| s != "0 B"),
    )
    .await;

    // The server's view of it: one session of 25 heads, with this page as its viewer.
    let id = cdp
        .eval("new URL(location.href).searchParams.get('session')")
        .await;
    let id = id.as_str().expect("the page names its session").to_string();
    let session = session_info(&server, &id).await;
    assert_eq!(session.heads.len(), 25);
    assert_eq!(session.viewers, 1);
    assert!(session.stats.messages_sent > 0);

    // The canvas is not blank: outside the control panel, a meaningful share of it is lit
    // crowd, shaded over a range of brightness (a flat colour would be an unlit or failed draw).
    let layout = cdp
        .eval(
            "JSON.stringify({w: innerWidth, h: innerHeight, \
             panel: document.getElementById('panel').getBoundingClientRect()})",
        )
        .await;
    let layout: Value = serde_json::from_str(layout.as_str().unwrap()).unwrap();
    let path = screenshot_path("");
    let image = screenshot(&mut cdp, &path).await;
    let scale = f64::from(image.width) / layout["w"].as_f64().unwrap();
    let panel = &layout["panel"];
    let px = |k: &str| (panel[k].as_f64().unwrap() * scale) as u32;
    let (pl, pt, pr, pb) = (px("left"), px("top"), px("right"), px("bottom"));
    let (mut region, mut crowd) = (0u64, 0u64);
    let (mut darkest, mut brightest) = (255u8, 0u8);
    for y in 0..image.height {
        for x in 0..image.width {
            if (pl..=pr).contains(&x) && (pt..=pb).contains(&y) {
                continue;
            }
            region += 1;
            let p = image.pixel(x, y);
            if (0..3).any(|c| p[c].abs_diff(BACKGROUND[c]) > 12) {
                crowd += 1;
                let luma =
                    ((u32::from(p[0]) * 3 + u32::from(p[1]) * 6 + u32::from(p[2])) / 10) as u8;
                darkest = darkest.min(luma);
                brightest = brightest.max(luma);
            }
        }
    }
    let share = crowd as f64 / region as f64;
    assert!(
        share > 0.05,
        "only {:.2} % of the canvas differs from the background (see {})",
        share * 100.0,
        path.display()
    );
    assert!(
        brightest - darkest > 40,
        "the crowd is flat: brightness {darkest}..{brightest} (see {})",
        path.display()
    );

    // Crowd size: the slider adds heads with a PATCH; the next layout has them, and all are drawn.
    cdp.eval(
        "(() => { const r = document.getElementById('heads'); r.value = '36'; \
         r.dispatchEvent(new Event('input')); })()",
    )
    .await;
    cdp.wait_for("36 heads drawn", drawn, Duration::from_secs(90), |v| {
        v.as_u64() == Some(36)
    })
    .await;
    assert_eq!(session_info(&server, &id).await.heads.len(), 36);

    // Clip mix: without `idle`, no head plays it.
    cdp.eval(
        "(() => { for (const c of document.querySelectorAll('#clips input')) \
         if (c.parentElement.textContent.trim() === 'idle') c.click(); })()",
    )
    .await;
    let deadline = Instant::now() + Duration::from_secs(90);
    loop {
        let info = session_info(&server, &id).await;
        if info.heads.iter().all(|h| h.clip != "idle") {
            let clips: std::collections::BTreeSet<_> = info.heads.iter().map(|h| &h.clip).collect();
            assert_eq!(clips.len(), 3, "the other clips share the crowd: {clips:?}");
            break;
        }
        assert!(Instant::now() < deadline, "heads still play idle");
        tokio::time::sleep(Duration::from_millis(250)).await;
    }

    // LOD: a fixed level for every head is this viewer's choice, sent as a ViewerUpdate; the
    // buffers that come back are at that level.
    cdp.eval(
        "(() => { const m = document.getElementById('lod-mode'); m.value = '2'; \
         m.dispatchEvent(new Event('change')); })()",
    )
    .await;
    cdp.wait_for(
        "every head at LOD 2",
        "document.getElementById('view').dataset.lods",
        Duration::from_secs(90),
        |v| v.as_str() == Some("2"),
    )
    .await;

    // What the page decoded from temporal residuals, inflated by the browser, is bit for bit
    // what a plain q16 viewer of the same session gets, at the same ticks (every head is at
    // LOD 2 now, so the camera does not matter).
    let mode = cdp.eval("window.crowdmorphViewer.mode").await;
    assert_eq!(
        mode,
        json!({"format": "q16", "temporal": true, "compression": "deflate", "layers": true}),
        "the page's hello"
    );
    let plain = PlainViewer::start(
        &server,
        &id,
        json!({"format": "q16", "normals": true, "lod": 2}),
    )
    .await;
    let compared = compare_with_plain(&mut cdp, &plain, "window.crowdmorphViewer.snapshot()").await;
    let received = cdp.eval("window.crowdmorphViewer.received").await;
    println!("temporal page: compared ticks {compared:?}, received {received}");
    let variants: Vec<u64> = received["variants"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_u64().unwrap())
        .collect();
    assert_eq!(
        variants[0], 0,
        "plain TickVertices to a temporal viewer: {received}"
    );
    assert!(variants[2] > 0, "no TickDelta: {received}");
    assert_eq!(
        variants[3], variants[2],
        "every message packed, each holding a TickDelta: {received}"
    );
    assert!(
        received["fromResiduals"].as_u64().unwrap() > 0,
        "no head was decoded from residuals: {received}"
    );
    assert!(
        received["bytes"].as_u64().unwrap() > received["wireBytes"].as_u64().unwrap(),
        "deflate made nothing smaller: {received}"
    );

    // Orbiting the camera sends camera updates; the stream goes on.
    cdp.call(
        "Input.dispatchMouseEvent",
        json!({"type": "mousePressed", "x": 600, "y": 400, "button": "left", "clickCount": 1}),
    )
    .await;
    cdp.call(
        "Input.dispatchMouseEvent",
        json!({"type": "mouseMoved", "x": 680, "y": 380, "button": "left", "buttons": 1}),
    )
    .await;
    cdp.call(
        "Input.dispatchMouseEvent",
        json!({"type": "mouseReleased", "x": 680, "y": 380, "button": "left", "clickCount": 1}),
    )
    .await;
    let now = cdp.eval(tick).await.as_u64().unwrap();
    cdp.wait_for("ticks after orbiting", tick, Duration::from_secs(90), |v| {
        v.as_u64().unwrap_or(0) >= now + 10
    })
    .await;

    let errors = cdp.errors();
    assert!(errors.is_empty(), "the page logged errors: {errors:#?}");
    assert_eq!(cdp.eval(ERROR_TEXT).await, json!(""));

    // `?temporal=0` switches the page back to plain q16 messages, decoded the same.
    cdp.call(
        "Page.navigate",
        json!({"url": format!("http://{}/viewer?session={id}&temporal=0", server.addr)}),
    )
    .await;
    cdp.wait_for(
        "the plain page's first tick",
        "window.crowdmorphViewer?.tick ?? 0",
        Duration::from_secs(120),
        |v| v.as_u64().unwrap_or(0) > 0,
    )
    .await;
    let mode = cdp.eval("window.crowdmorphViewer.mode").await;
    assert_eq!(
        mode,
        json!({"format": "q16", "temporal": false, "compression": null, "layers": true}),
        "the page's hello with ?temporal=0"
    );
    // A page that joins chooses LOD by distance: make it LOD 2 for every head, as the plain
    // Rust viewer has.
    cdp.wait_for(
        "the plain page's LOD control",
        "document.getElementById('lod-mode').options.length",
        Duration::from_secs(60),
        |v| v.as_u64().unwrap_or(0) > 2,
    )
    .await;
    cdp.eval(
        "(() => { const m = document.getElementById('lod-mode'); m.value = '2'; \
         m.dispatchEvent(new Event('change')); })()",
    )
    .await;
    cdp.wait_for(
        "every head at LOD 2 on the plain page",
        "document.getElementById('view').dataset.lods",
        Duration::from_secs(90),
        |v| v.as_str() == Some("2"),
    )
    .await;
    let compared = compare_with_plain(&mut cdp, &plain, "window.crowdmorphViewer.snapshot()").await;
    let received = cdp.eval("window.crowdmorphViewer.received").await;
    println!("plain page: compared ticks {compared:?}, received {received}");
    let variants = &received["variants"];
    assert!(variants[0].as_u64().unwrap() > 0, "{received}");
    assert_eq!(variants[2], json!(0), "{received}");
    assert_eq!(variants[3], json!(0), "{received}");
    assert_eq!(received["fromResiduals"], json!(0), "{received}");

    let errors = cdp.errors();
    assert!(errors.is_empty(), "the page logged errors: {errors:#?}");
    assert_eq!(cdp.eval(ERROR_TEXT).await, json!(""));
    plain.stop();
    drop(cdp);
    drop(browser);
    server.stop().await;
}

/// The shared MorphPrimitivesTest rig: a flat 1 m × 1 m grid in two primitives, one with a red
/// and one with a green material, both multiplying `uv_texture.jpg` by their factor. The image
/// is a checker of 16 × 16 grey and white labelled cells: upside down, grey and white swap (15
/// is odd), so a flipped texture is as wrong as a missing one.
fn textured_rig() -> PathBuf {
    crate::util::data_dir().join("khronos/MorphPrimitivesTest/glTF/MorphPrimitivesTest.gltf")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(all(crowdmorph_chromium, crowdmorph_test_data)),
    ignore = "needs Chromium and ../shared/data (see the lit crowd test and util::data_dir)"
)]
async fn the_viewer_draws_textures_fetched_once_in_headless_chromium() {
    let server = TestServer::start(ServerConfig::default()).await;
    let glb = crate::util::pack::self_contained_glb(&textured_rig());
    let info = server
        .client
        .upload_rig("prims", Bytes::from(glb.clone()))
        .await
        .expect("upload");
    // One clip that holds the target at 0: the grid stays flat, where the mesh endpoint's
    // neutral positions have it, so this test knows which texel lands on each pixel.
    let csv = format!("{}\n0\n0\n", info.targets[0]);
    server
        .client
        .upload_clip("prims", "name=still", "text/csv", Bytes::from(csv))
        .await
        .expect("clip");
    let mesh = server
        .client
        .mesh("prims", Encoding::Json)
        .await
        .expect("mesh");
    let materials = server.client.materials("prims").await.expect("materials");
    let images = materials["images"].as_array().expect("images").len();
    assert_eq!(images, 1, "{materials}");
    // The texture as the importer decodes it on the CPU (not the browser's decoder).
    let rig = crowdmorph::import::gltf::rig_from_slice(
        &glb,
        &crowdmorph::import::ImportOptions::default(),
    )
    .expect("the GLB imports");
    let appearance = rig.appearance.as_deref().expect("materials");
    let mips = appearance.images[0].pixels.as_deref().expect("pixels");
    let texture = &mips.levels[0];

    let (browser, mut cdp) = open_page(&["Network.enable"]).await;
    cdp.call(
        "Page.navigate",
        json!({"url": format!("http://{}/viewer?rig=prims&heads=1", server.addr)}),
    )
    .await;
    let tick = "window.crowdmorphViewer?.tick ?? 0";
    cdp.wait_for("the first tick", tick, Duration::from_secs(120), |v| {
        v.as_u64().unwrap_or(0) > 0
    })
    .await;
    cdp.wait_for(
        "the texture on the GPU",
        "window.crowdmorphViewer.appearance.imagesReady",
        Duration::from_secs(60),
        |v| v.as_u64() == Some(1),
    )
    .await;
    let drawn = "Number(document.getElementById('view').dataset.drawn || 0)";
    cdp.wait_for("the head drawn", drawn, Duration::from_secs(60), |v| {
        v.as_u64() == Some(1)
    })
    .await;
    // The page frames the grid from 20° above it, edge on; a drag 120 px down turns the camera
    // to 56°, where the checker's cells are tens of pixels.
    for (kind, y, buttons) in [
        ("mousePressed", 250, 1),
        ("mouseMoved", 310, 1),
        ("mouseMoved", 370, 1),
        ("mouseReleased", 370, 0),
    ] {
        cdp.call(
            "Input.dispatchMouseEvent",
            json!({"type": kind, "x": 640, "y": y, "button": "left", "buttons": buttons,
                   "clickCount": 1}),
        )
        .await;
    }
    let now = cdp.eval(tick).await.as_u64().unwrap();
    cdp.wait_for("ticks after turning", tick, Duration::from_secs(90), |v| {
        v.as_u64().unwrap_or(0) >= now + 10
    })
    .await;

    // The picture against the CPU's expectation.
    let (view, path, image, panel) = still_screenshot(&mut cdp, "-textured").await;
    let scene = Scene::new(&view, &mesh, &materials, &panel, f64::from(image.width));
    let fit = scene.fit(&image, texture, false);
    println!("textured page: {fit:?}");
    fit.check(&path);
    // The server's render of the same camera: the page shades with the renderer's BRDF and
    // lights, so the two pictures agree wherever the page's panel leaves the canvas free.
    let zeros: Vec<(String, f32)> = info.targets.iter().map(|t| (t.clone(), 0.0)).collect();
    compare_with_the_servers_render(&server, &view, &zeros, &image, &scene.frame(), &path).await;
    // The samples tell an upside-down texture apart: read with v flipped, the same picture
    // fits nothing (a self-check of the test rather than of the page).
    let flipped = scene.fit(&image, texture, true);
    println!("read upside down: {flipped:?}");
    assert!(
        flipped.problem().is_some(),
        "the samples cannot tell a flipped texture from the right one: {flipped:?}"
    );

    // Appearance was fetched once: the materials, and each image by its versioned URI; then,
    // while the stream ticks, the page asks for nothing more (0 bytes of appearance per tick).
    let requests = cdp.requests();
    let matching = |part: &str| -> Vec<Request> {
        requests
            .iter()
            .filter(|r| r.url.contains(part))
            .cloned()
            .collect()
    };
    let textures = matching("/v1/rigs/prims/textures/");
    let material_requests = matching("/v1/rigs/prims/materials");
    let meshes = matching("/v1/rigs/prims/mesh");
    assert_eq!(textures.len(), images, "{requests:#?}");
    assert_eq!(material_requests.len(), 1, "{requests:#?}");
    assert_eq!(meshes.len(), 1, "{requests:#?}");
    for r in textures.iter().chain(&material_requests) {
        assert_eq!(r.status, Some(200), "{r:?}");
    }
    let uri = materials["images"][0]["uri"].as_str().unwrap();
    assert!(textures[0].url.ends_with(uri), "{textures:?} vs {uri}");
    no_requests_for_30_ticks(&mut cdp, tick, requests.len()).await;
    let stats = cdp.eval("window.crowdmorphViewer.appearance").await;
    assert_eq!(stats["materialFetches"], json!(1), "{stats}");
    assert_eq!(stats["imageFetches"], json!(images), "{stats}");
    assert_eq!(stats["imageFailures"], json!(0), "{stats}");
    let bytes = |rs: &[Request]| -> u64 { rs.iter().map(|r| r.body_bytes.unwrap_or(0)).sum() };
    let wire = |rs: &[Request]| -> u64 { rs.iter().map(|r| r.wire_bytes.unwrap_or(0)).sum() };
    let received = cdp.eval("window.crowdmorphViewer.received").await;
    // A packed message counts once as itself and once as the message it holds.
    let variants: Vec<u64> = received["variants"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_u64().unwrap())
        .collect();
    let messages = variants.iter().sum::<u64>() - variants[3];
    println!(
        "appearance, fetched once per rig: materials {} B ({} B on the wire), textures {} B ({} \
         B on the wire), texture coordinates {} B in the mesh ({} B on the wire with its \
         positions, normals and indices); per tick 0 B (the stream's messages average {} B on \
         the wire, vertices only)",
        bytes(&material_requests),
        wire(&material_requests),
        bytes(&textures),
        wire(&textures),
        mesh.uvs.0.len(),
        wire(&meshes),
        received["wireBytes"].as_u64().unwrap() / messages.max(1),
    );
    let errors = cdp.errors();
    assert!(errors.is_empty(), "the page logged errors: {errors:#?}");
    assert_eq!(cdp.eval(ERROR_TEXT).await, json!(""));
    drop(cdp);
    drop(browser);
    server.stop().await;
}

/// The least luminance SSIM of the page's screenshot and the server's render of its camera,
/// over the pixels either draws. They are two rasterizers (WebGL2 on SwiftShader with the
/// browser's multisampling and anisotropic filtering, wgpu on lavapipe with 4× MSAA and
/// trilinear) of the same BRDF, lights and texture.
const MIN_VIEWER_SSIM: f64 = 0.9;

/// The largest mean luminance difference (0..=255) of those two pictures where both draw: a
/// light of another strength or a missed sRGB step is tens.
const MAX_VIEWER_LUMA_DIFFERENCE: f64 = 6.0;

/// Where the page draws: the panel's box in drawing-buffer pixels (the page draws under it)
/// and screenshot pixels per drawing-buffer pixel.
struct PageFrame {
    panel: [f64; 4],
    scale: f64,
}

impl PageFrame {
    /// From the page's panel (`getBoundingClientRect()`, CSS pixels) and its drawing buffer's
    /// width: the canvas fills the window.
    fn new(view: &Value, panel: &Value, shot_width: f64) -> PageFrame {
        let scale = shot_width / view["width"].as_f64().expect("width");
        let css = |k: &str| panel[k].as_f64().expect("a number") / scale;
        PageFrame {
            panel: [css("left"), css("top"), css("right"), css("bottom")],
            scale,
        }
    }
}

/// The page's screenshot and the server's render of its camera, side by side in drawing-buffer
/// pixels (see [`compare_with_the_servers_render`]).
struct Pictures {
    /// The server's, moved as the page's projection is.
    server: Image,
    page: Image,
}

/// Asks the server to render the head the page shows (`view`: its camera, clip planes, head
/// placement and drawing-buffer size) with `weights` (as the page's clip has them, not the
/// file's default weights), and lays that beside the page's screenshot `shot`, leaving out
/// what the panel covers. The page moves its picture right of the panel by `ndcShiftX` (an
/// off-centre projection no `CameraSpec` gives), so the server's picture is moved by as much.
async fn the_servers_render_of_the_page(
    server: &TestServer,
    view: &Value,
    weights: &[(String, f32)],
    shot: &Image,
    frame: &PageFrame,
) -> Pictures {
    let num = |v: &Value| v.as_f64().expect("a number");
    let (width, height) = (num(&view["width"]) as u32, num(&view["height"]) as u32);
    let cam = &view["camera"];
    let head = &view["heads"][0];
    let model: Vec<f64> = head["model"]
        .as_array()
        .expect("model")
        .iter()
        .map(num)
        .collect();
    // The page's placement is translate · rotate_y(yaw) · scale, as the server's.
    let scale = (model[0] * model[0] + model[1] * model[1] + model[2] * model[2]).sqrt();
    let yaw = (-model[2]).atan2(model[0]).to_degrees();
    let v3 = |v: &Value| -> [f32; 3] { [0, 1, 2].map(|i| num(&v[i]) as f32) };
    let placement = (
        [model[12] as f32, model[13] as f32, model[14] as f32],
        yaw as f32,
        scale as f32,
    );
    let camera = CameraSpec {
        fov_y: num(&cam["fov_y"]) as f32,
        near: Some(num(&cam["near"]) as f32),
        far: Some(num(&cam["far"]) as f32),
        ..CameraSpec::looking(v3(&cam["position"]), v3(&cam["target"]))
    };
    let rig = head["rig"].as_str().expect("rig");
    let server_img = super::render_one(
        server,
        rig,
        weights,
        placement,
        camera,
        (width, height),
        BACKGROUND,
    )
    .await;
    // Both in drawing-buffer pixels, the server's moved as the page's projection moves, the
    // panel and what the move uncovers painted background in both.
    let shift = (num(&view["ndcShiftX"]) * f64::from(width) / 2.0).round() as i64;
    let mut page = Image::new(width, height, vec![0; (width * height * 4) as usize]);
    let mut moved = Image::new(width, height, vec![0; (width * height * 4) as usize]);
    let [pl, pt, pr, pb] = frame.panel;
    for y in 0..height {
        for x in 0..width {
            let at = ((y * width + x) * 4) as usize;
            let sx = i64::from(x) - shift;
            let (fx, fy) = (f64::from(x), f64::from(y));
            let covered = fx >= pl - 2.0 && fx <= pr + 2.0 && fy >= pt - 2.0 && fy <= pb + 2.0;
            if covered || sx < 0 || sx >= i64::from(width) {
                for img in [&mut page, &mut moved] {
                    img.rgba[at..at + 4].copy_from_slice(&[
                        BACKGROUND[0],
                        BACKGROUND[1],
                        BACKGROUND[2],
                        255,
                    ]);
                }
                continue;
            }
            let from = ((y * width + sx as u32) * 4) as usize;
            moved.rgba[at..at + 4].copy_from_slice(&server_img.rgba[from..from + 4]);
            let (qx, qy) = ((fx * frame.scale) as u32, (fy * frame.scale) as u32);
            let q = ((qy.min(shot.height - 1) * shot.width + qx.min(shot.width - 1)) * 4) as usize;
            page.rgba[at..at + 4].copy_from_slice(&shot.rgba[q..q + 4]);
        }
    }
    Pictures {
        server: moved,
        page,
    }
}

/// Whether a pixel is drawn (not the background).
fn is_drawn(p: &[u8]) -> bool {
    (0..3).any(|c| p[c].abs_diff(BACKGROUND[c]) > 2)
}

/// Compares the page's screenshot `shot` with the server's render of its camera
/// ([`the_servers_render_of_the_page`]): the least SSIM and the largest luminance difference
/// allowed, over the pixels either draws. Returns the two pictures.
async fn compare_with_the_servers_render(
    server: &TestServer,
    view: &Value,
    weights: &[(String, f32)],
    shot: &Image,
    frame: &PageFrame,
    path: &Path,
) -> Pictures {
    let pictures = the_servers_render_of_the_page(server, view, weights, shot, frame).await;
    let (moved, page) = (&pictures.server, &pictures.page);
    let ssim = ssim_masked(moved, page, BACKGROUND).expect("drawn pixels");
    let luma =
        |p: &[u8]| 0.2126 * f64::from(p[0]) + 0.7152 * f64::from(p[1]) + 0.0722 * f64::from(p[2]);
    let (mut sum, mut n) = (0.0, 0usize);
    for (a, b) in moved.rgba.chunks_exact(4).zip(page.rgba.chunks_exact(4)) {
        if is_drawn(a) && is_drawn(b) {
            sum += luma(a) - luma(b);
            n += 1;
        }
    }
    let difference = sum / n.max(1) as f64;
    println!(
        "the page against the server's render of its camera: SSIM {:.4} over {} pixels, \
         server − page luminance {difference:+.2}/255",
        ssim.mean, ssim.pixels
    );
    let pass = ssim.mean >= MIN_VIEWER_SSIM && difference.abs() <= MAX_VIEWER_LUMA_DIFFERENCE;
    if !pass {
        for (what, img) in [("server", moved), ("page", page), ("ssim", &ssim.map)] {
            let file = path.with_file_name(format!("viewer-vs-server-{what}.png"));
            img.write_png(&file).expect("write");
            println!("{what}: {}", file.display());
        }
    }
    assert!(
        pass,
        "the page's picture against the server's render: SSIM {:.4} (at least \
         {MIN_VIEWER_SSIM}), luminance {difference:+.2}/255 (at most \
         ±{MAX_VIEWER_LUMA_DIFFERENCE})",
        ssim.mean
    );
    pictures
}

/// One drawn head of a textured rig as the page drew it (its `crowdmorphViewer.view`): each
/// mesh triangle on screen, for finding which primitive and texture coordinate a pixel shows.
struct Scene {
    /// Per vertex: screen x, y (drawing-buffer pixels, y down) and clip w.
    screen: Vec<[f64; 3]>,
    uvs: Vec<[f64; 2]>,
    /// Per triangle: its vertices and its primitive's base colour factor.
    triangles: Vec<([usize; 3], [f64; 4])>,
    /// The panel's box in drawing-buffer pixels (the page draws under it).
    panel: [f64; 4],
    width: f64,
    height: f64,
    /// Screenshot pixels per drawing-buffer pixel.
    scale: f64,
}

/// How well a screenshot fits `factor × texel × D`: per sample, the channel the factor keeps
/// minus the one it removes (which cancels the grey specular) is the texel's, times one
/// diffuse light `D` for the whole flat grid, fitted as the median over the samples.
#[derive(Debug)]
struct Fit {
    samples: usize,
    /// Samples on white (≥ 0.6 linear) and on grey (≤ 0.3) texels, per material factor.
    light: [usize; 2],
    dark: [usize; 2],
    diffuse: f64,
    /// The share of samples within tolerance of the fitted picture.
    within: f64,
    /// The largest |green − blue| where the factor is red (both are the grey specular alone).
    grey_specular: f64,
}

fn srgb_to_linear(c: u8) -> f64 {
    let c = f64::from(c) / 255.0;
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// `m · p` for a column-major 4 × 4 matrix.
fn transform(m: &[f64], p: [f64; 4]) -> [f64; 4] {
    let mut out = [0.0; 4];
    for (r, o) in out.iter_mut().enumerate() {
        *o = (0..4).map(|c| m[c * 4 + r] * p[c]).sum();
    }
    out
}

impl Scene {
    fn new(
        view: &Value,
        mesh: &MeshResponse,
        materials: &Value,
        panel: &Value,
        shot_width: f64,
    ) -> Scene {
        let nums = |v: &Value| -> Vec<f64> {
            v.as_array()
                .expect("an array")
                .iter()
                .map(|x| x.as_f64().expect("a number"))
                .collect()
        };
        let view_proj = nums(&view["viewProj"]);
        let heads = view["heads"].as_array().expect("heads");
        assert_eq!(heads.len(), 1, "{view}");
        let model = nums(&heads[0]["model"]);
        let width = view["width"].as_f64().unwrap();
        let height = view["height"].as_f64().unwrap();
        let f32s = |b: &[u8]| -> Vec<f64> {
            b.chunks_exact(4)
                .map(|c| f64::from(f32::from_le_bytes([c[0], c[1], c[2], c[3]])))
                .collect()
        };
        let positions = f32s(&mesh.positions.0);
        let screen = positions
            .chunks_exact(3)
            .map(|p| {
                let world = transform(&model, [p[0], p[1], p[2], 1.0]);
                let clip = transform(&view_proj, world);
                [
                    (clip[0] / clip[3] + 1.0) / 2.0 * width,
                    (1.0 - clip[1] / clip[3]) / 2.0 * height,
                    clip[3],
                ]
            })
            .collect();
        let uvs = f32s(&mesh.uvs.0)
            .chunks_exact(2)
            .map(|c| [c[0], c[1]])
            .collect();
        let indices: Vec<usize> = mesh
            .indices
            .0
            .chunks_exact(4)
            .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]) as usize)
            .collect();
        let mut triangles = Vec::new();
        for p in &mesh.primitives {
            let m = p.material.expect("every primitive has a material") as usize;
            let factor: Vec<f64> =
                nums(&materials["materials"][m]["pbrMetallicRoughness"]["baseColorFactor"]);
            let first = p.first_index as usize;
            for t in indices[first..first + p.indices as usize].chunks_exact(3) {
                triangles.push((
                    [t[0], t[1], t[2]],
                    [factor[0], factor[1], factor[2], factor[3]],
                ));
            }
        }
        // CSS pixels to drawing-buffer pixels (the canvas fills the window).
        let scale = shot_width / width;
        let css = |k: &str| panel[k].as_f64().unwrap() / scale;
        Scene {
            screen,
            uvs,
            triangles,
            panel: [css("left"), css("top"), css("right"), css("bottom")],
            width,
            height,
            scale,
        }
    }

    /// Where the page draws, for [`compare_with_the_servers_render`].
    fn frame(&self) -> PageFrame {
        PageFrame {
            panel: self.panel,
            scale: self.scale,
        }
    }

    /// The triangle under a point of the drawing buffer and the texture coordinate there
    /// (perspective-correct, as the GPU interpolates it).
    fn locate(&self, x: f64, y: f64) -> Option<(usize, [f64; 2])> {
        for (i, (t, _)) in self.triangles.iter().enumerate() {
            let [a, b, c] = t.map(|k| self.screen[k]);
            let det = (b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1]);
            if det.abs() < 1e-9 {
                continue;
            }
            let l1 = ((x - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (y - a[1])) / det;
            let l2 = ((b[0] - a[0]) * (y - a[1]) - (x - a[0]) * (b[1] - a[1])) / det;
            let l = [1.0 - l1 - l2, l1, l2];
            if l.iter().any(|&w| w < 0.0) {
                continue;
            }
            let q: Vec<f64> = (0..3).map(|k| l[k] / self.screen[t[k]][2]).collect();
            let sum: f64 = q.iter().sum();
            let mut uv = [0.0; 2];
            for k in 0..3 {
                for (d, u) in uv.iter_mut().enumerate() {
                    *u += q[k] * self.uvs[t[k]][d] / sum;
                }
            }
            return Some((i, uv));
        }
        None
    }

    /// Samples pixels whose neighbourhood shows one primitive and one texel colour (away from
    /// cell borders, labels and triangle-crossing primitive borders), compares each with
    /// `factor × texel × D`, and fits D. With `flip`, the texture is read upside down.
    fn fit(&self, shot: &Image, texture: &crowdmorph::rig::MipLevel, flip: bool) -> Fit {
        let texel = |uv: [f64; 2]| -> [u8; 4] {
            let v = if flip { 1.0 - uv[1] } else { uv[1] };
            // glTF: v = 0 is the image's top row; the sampler repeats.
            let x = (uv[0].rem_euclid(1.0) * f64::from(texture.width)) as u32;
            let y = (v.rem_euclid(1.0) * f64::from(texture.height)) as u32;
            let (x, y) = (x.min(texture.width - 1), y.min(texture.height - 1));
            let at = (y * texture.width + x) as usize * 4;
            let p = &texture.rgba[at..at + 4];
            [p[0], p[1], p[2], p[3]]
        };
        const STEPS: [f64; 5] = [-3.0, -1.5, 0.0, 1.5, 3.0];
        let mut rows = Vec::new(); // (observed, expected, which factor, texel value)
        let mut grey_specular: f64 = 0.0;
        let mut y = 0.5;
        while y < self.height {
            let mut x = 0.5;
            while x < self.width {
                let p = self.panel;
                let under_panel =
                    x > p[0] - 6.0 && x < p[2] + 6.0 && y > p[1] - 6.0 && y < p[3] + 6.0;
                let here = if under_panel { None } else { self.locate(x, y) };
                if let Some((tri, uv)) = here {
                    let factor = self.triangles[tri].1;
                    let centre = texel(uv);
                    let uniform = STEPS.iter().all(|&dy| {
                        STEPS.iter().all(|&dx| {
                            self.locate(x + dx, y + dy).is_some_and(|(t, uv)| {
                                self.triangles[t].1 == factor
                                    && (0..3).all(|c| texel(uv)[c].abs_diff(centre[c]) <= 8)
                            })
                        })
                    });
                    let px = shot.pixel(
                        ((x - 0.5) * self.scale) as u32,
                        ((y - 0.5) * self.scale) as u32,
                    );
                    // A clipped channel says nothing about D.
                    if uniform && px[..3].iter().all(|&c| c < 250) {
                        let keep = (0..3)
                            .max_by(|&a, &b| factor[a].total_cmp(&factor[b]))
                            .unwrap();
                        let drop = (0..3)
                            .min_by(|&a, &b| factor[a].total_cmp(&factor[b]))
                            .unwrap();
                        let lin = |c: usize| srgb_to_linear(px[c]);
                        let observed = lin(keep) - lin(drop);
                        let t = |c: usize| factor[c] * srgb_to_linear(centre[c]);
                        let expected = t(keep) - t(drop);
                        if factor[0] > factor[1] {
                            grey_specular = grey_specular.max((lin(1) - lin(2)).abs());
                        }
                        rows.push((observed, expected, keep, srgb_to_linear(centre[keep])));
                    }
                }
                x += 4.0;
            }
            y += 4.0;
        }
        let mut ratios: Vec<f64> = rows
            .iter()
            .filter(|r| r.1 > 0.05)
            .map(|r| r.0 / r.1)
            .collect();
        ratios.sort_by(f64::total_cmp);
        let diffuse = ratios.get(ratios.len() / 2).copied().unwrap_or(0.0);
        let within = rows
            .iter()
            .filter(|r| (r.0 - diffuse * r.1).abs() <= 0.02 + 0.08 * diffuse * r.1)
            .count();
        let count = |keep: usize, test: &dyn Fn(f64) -> bool| {
            rows.iter().filter(|r| r.2 == keep && test(r.3)).count()
        };
        Fit {
            samples: rows.len(),
            light: [count(0, &|t| t >= 0.6), count(1, &|t| t >= 0.6)],
            dark: [count(0, &|t| t <= 0.3), count(1, &|t| t <= 0.3)],
            diffuse,
            within: within as f64 / rows.len().max(1) as f64,
            grey_specular,
        }
    }
}

impl Fit {
    /// What makes the fit fail, if anything.
    fn problem(&self) -> Option<&'static str> {
        if self.samples < 200 {
            return Some("too few pixels to judge");
        }
        // Both materials show their grey texels, and white texels show somewhere, enough to
        // judge. (Under the renderer's lights, the green factor's white texels clip at this
        // angle, and a clipped channel says nothing about D.)
        if !(self.dark.iter().all(|&d| d >= 20) && self.light.iter().sum::<usize>() >= 20) {
            return Some("too few samples on white and grey texels");
        }
        if !(0.3..1.5).contains(&self.diffuse) {
            return Some("the lighting is implausible");
        }
        if self.within < 0.95 {
            return Some("the canvas does not show factor × texture");
        }
        if self.grey_specular > 0.03 {
            return Some("a red material shows green or blue beyond its grey highlight");
        }
        None
    }

    fn check(&self, path: &Path) {
        if let Some(problem) = self.problem() {
            panic!("{problem}: {self:?} (see {})", path.display());
        }
    }
}

/// FNV-1a 32 over what a viewer's heads hold, as `q16Checksum` in clients/web/main.js: for each
/// layout head with a buffer, in layout order, its id (u64 little-endian), its q16 positions'
/// bytes, then its normals' bytes.
fn q16_checksum(state: &StreamState) -> u32 {
    let mut h: u32 = 0x811c_9dc5;
    let mut feed = |bytes: &[u8]| {
        for &b in bytes {
            h = (h ^ u32::from(b)).wrapping_mul(0x0100_0193);
        }
    };
    for head in state.layout() {
        let Some(b) = state.buffer(head.head) else {
            continue;
        };
        feed(&head.head.to_le_bytes());
        feed(&b.positions.0);
        if let Some(n) = &b.normals {
            feed(&n.0);
        }
    }
    h
}

/// A plain q16 viewer of a session over its own WebSocket, decoded with the proto crate's
/// `StreamState`: the checksum of what it holds after each tick it received.
struct PlainViewer {
    checksums: Arc<Mutex<BTreeMap<u64, u32>>>,
    task: tokio::task::JoinHandle<()>,
}

impl PlainViewer {
    async fn start(server: &TestServer, id: &str, hello: Value) -> PlainViewer {
        let url = format!("ws://{}/v1/sessions/{id}/stream", server.addr);
        let (mut ws, _) = tokio_tungstenite::connect_async(url)
            .await
            .expect("connect the plain viewer");
        ws.send(Message::text(hello.to_string()))
            .await
            .expect("hello");
        let checksums = Arc::new(Mutex::new(BTreeMap::new()));
        let out = checksums.clone();
        let task = tokio::spawn(async move {
            let mut state = StreamState::new();
            while let Some(msg) = ws.next().await {
                match msg.expect("the plain viewer's stream") {
                    Message::Binary(b) => match state.receive(&b) {
                        Ok(Received::Vertices(applied)) => {
                            let sum = q16_checksum(&state);
                            let mut map = out.lock().unwrap();
                            map.insert(applied.tick, sum);
                            // The ticks the page may still report, not the whole run.
                            while map.len() > 4096 {
                                map.pop_first();
                            }
                        }
                        Ok(Received::Frame(_)) => panic!("the plain viewer got a frame"),
                        Ok(Received::Layers(_)) => panic!("the plain viewer got layers"),
                        Ok(Received::Poses(_)) => panic!("the plain viewer got poses"),
                        Err(e) => panic!("the plain viewer: {e}"),
                    },
                    Message::Close(c) => panic!("the plain viewer was closed: {c:?}"),
                    _ => {}
                }
            }
        });
        PlainViewer { checksums, task }
    }

    fn checksum_at(&self, tick: u64) -> Option<u32> {
        if self.task.is_finished() {
            panic!("the plain viewer stopped reading");
        }
        self.checksums.lock().unwrap().get(&tick).copied()
    }

    fn stop(self) {
        self.task.abort();
    }
}

/// Samples the page's `{tick, checksum}` (`snapshot`, evaluated in one go between two
/// messages) until five of its ticks are ones the plain viewer also received, and asserts that
/// the page's checksum equals the plain viewer's at each. Returns the ticks compared.
async fn compare_with_plain(cdp: &mut Cdp, plain: &PlainViewer, snapshot: &str) -> Vec<u64> {
    let mut pending: BTreeMap<u64, u64> = BTreeMap::new(); // page tick → page checksum
    let mut compared = Vec::new();
    let deadline = Instant::now() + Duration::from_secs(120);
    while compared.len() < 5 {
        let s = cdp.eval(snapshot).await;
        let tick = s["tick"].as_u64().expect("the page's tick");
        let sum = s["checksum"].as_u64().expect("the page's q16 checksum");
        pending.entry(tick).or_insert(sum);
        // Page ticks the plain viewer has received are compared; others wait (the plain viewer
        // may not have read that far yet, or may have skipped them).
        let settled: Vec<u64> = pending.keys().copied().collect();
        for t in settled {
            if let Some(want) = plain.checksum_at(t) {
                let got = pending.remove(&t).unwrap();
                assert_eq!(
                    got,
                    u64::from(want),
                    "tick {t}: the page's decoded q16 values differ from a plain q16 viewer's"
                );
                compared.push(t);
            }
        }
        let errors = cdp.errors();
        let shown = cdp.eval(ERROR_TEXT).await;
        assert!(
            shown.as_str().unwrap_or("").is_empty() && errors.is_empty(),
            "comparing with a plain viewer: the page shows {shown} and logged {errors:#?}"
        );
        assert!(
            Instant::now() < deadline,
            "no five ticks in common with a plain viewer in 120 s: page ticks {:?} pending, \
             compared {compared:?}",
            pending.keys().collect::<Vec<_>>()
        );
        // Never more than a few hundred page ticks kept waiting.
        while pending.len() > 256 {
            pending.pop_first();
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    compared
}

async fn session_info(server: &TestServer, id: &str) -> SessionInfo {
    let reply = server
        .client
        .send(
            Method::GET,
            &format!("/v1/sessions/{id}"),
            None,
            Some("application/json"),
            Bytes::new(),
        )
        .await
        .unwrap();
    assert_eq!(reply.status, 200, "{:?}", reply.error());
    serde_json::from_slice(&reply.body).unwrap()
}

// ---------------------------------------------------------------------------------------------
// Expression layers: the wrinkle map rig of `util::wrinkle`, its layers served as the renderer
// uploads them, each head's inputs streamed when they change, and the page's sum.

/// The wrinkle rig's base colour: a checker of 4-pixel cells, 32 × 32.
fn wrinkle_base(x: u32, y: u32) -> [u8; 3] {
    if (x / 4 + y / 4).is_multiple_of(2) {
        [200, 170, 140]
    } else {
        [70, 60, 50]
    }
}

/// Its wrinkle texture: bands 8 pixels tall, blue and red, unlike the checker everywhere.
fn wrinkle_texture(_x: u32, y: u32) -> [u8; 3] {
    if (y / 8).is_multiple_of(2) {
        [30, 60, 210]
    } else {
        [230, 50, 40]
    }
}

/// The wrinkle rig's GLB: `brow` moves the quad 1 mm, so what changes with it is the colour.
fn wrinkle_rig() -> Vec<u8> {
    use crate::util::wrinkle::{png, wrinkle_glb};
    wrinkle_glb(
        &png(32, 32, wrinkle_base),
        &png(32, 32, wrinkle_texture),
        0.001,
    )
}

/// Uploads the wrinkle rig as `id` with clip `clip` holding `brow` at `weights`, frame by frame.
async fn upload_wrinkle_rig(server: &TestServer, id: &str, clip: &str, weights: &[f32]) -> Vec<u8> {
    let glb = wrinkle_rig();
    server
        .client
        .upload_rig(id, Bytes::from(glb.clone()))
        .await
        .expect("upload");
    let csv: String = std::iter::once("brow".to_string())
        .chain(weights.iter().map(|w| w.to_string()))
        .collect::<Vec<_>>()
        .join("\n");
    server
        .client
        .upload_clip(id, &format!("name={clip}"), "text/csv", Bytes::from(csv))
        .await
        .expect("clip");
    glb
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn layers_are_served_as_the_renderer_uploads_them_once_per_generation() {
    let server = TestServer::start(ServerConfig::default()).await;
    let glb = upload_wrinkle_rig(&server, "wrinkled", "still", &[0.8, 0.8]).await;
    let get = |path: String, headers: Vec<(&'static str, String)>| {
        let client = server.client.clone();
        async move {
            let h: Vec<(&str, &str)> = headers.iter().map(|(k, v)| (*k, v.as_str())).collect();
            client
                .send_with(Method::GET, &path, &h, Bytes::new())
                .await
                .unwrap()
        }
    };
    let reply = get("/v1/rigs/wrinkled/layers".into(), vec![]).await;
    assert_eq!(reply.status, 200);
    let doc: Value = serde_json::from_slice(&reply.body).expect("JSON");
    // The engine's plan of the same file, imported here.
    let rig = crowdmorph::import::gltf::rig_from_slice(
        &glb,
        &crowdmorph::import::ImportOptions::default(),
    )
    .expect("the GLB imports");
    use crowdmorph::engine::render::appearance::{layer_plan, layer_texels};
    let plan = layer_plan(&rig, 0, 4096)
        .expect("plan")
        .expect("material 0 has layers");
    assert_eq!(doc["inputs"], json!(1), "{doc}");
    let materials = doc["materials"].as_array().expect("materials");
    assert_eq!(materials.len(), 1, "{doc}");
    let m = &materials[0];
    assert_eq!(m["material"], json!(0));
    assert_eq!(
        (m["width"].as_u64(), m["height"].as_u64()),
        (Some(32), Some(32))
    );
    let levels: Vec<(u32, u32)> = plan.levels.clone();
    assert_eq!(
        m["levels"],
        json!(levels.iter().map(|&(w, h)| [w, h]).collect::<Vec<_>>())
    );
    // `brow`'s wrinkle reads input 0, clamped; the one for a target the rig lacks reads none.
    assert_eq!(
        m["layers"],
        json!([
            {"kind": "target", "input": 0, "clamp": true},
            {"kind": "target", "input": null, "clamp": false},
        ])
    );
    assert_eq!(m["bytes"].as_u64(), Some(plan.bytes()));
    let mut want = Vec::new();
    layer_texels(&rig, 0, 4096, |l| {
        for t in l.texels {
            want.extend_from_slice(&t.to_le_bytes());
        }
    })
    .expect("texels");
    assert_eq!(want.len() as u64, plan.bytes());
    // The texels, by the URI /layers gives: immutable, and exactly the engine's.
    let uri = m["texels"].as_str().expect("texels URI").to_string();
    let texels = get(uri.clone(), vec![]).await;
    assert_eq!(texels.status, 200);
    assert_eq!(
        texels.content_type.as_deref(),
        Some("application/octet-stream")
    );
    assert!(
        texels
            .header("cache-control")
            .is_some_and(|c| c.contains("immutable")),
        "{:?}",
        texels.header("cache-control")
    );
    assert!(
        texels.body == want[..],
        "the served texels are not the engine's"
    );
    // A layer is the wrinkle minus the base in linear RGBA: at texel (0, 0) of level 0, the
    // checker's light cell and the blue band.
    let texel0: Vec<f32> = want[..8]
        .chunks_exact(2)
        .map(|c| half::f16::from_le_bytes([c[0], c[1]]).to_f32())
        .collect();
    let lin = crowdmorph::engine::render::brdf::srgb8_to_linear;
    for c in 0..3 {
        let d = lin(wrinkle_texture(0, 0)[c]) - lin(wrinkle_base(0, 0)[c]);
        assert!(
            (texel0[c] - d).abs() < 2e-3,
            "{texel0:?}: channel {c} should be {d}"
        );
    }
    // Without the version: revalidated, 304 to its ETag, no body.
    let plain = get("/v1/rigs/wrinkled/layers/0".into(), vec![]).await;
    assert_eq!(plain.status, 200);
    assert_eq!(plain.header("cache-control"), Some("no-cache"));
    let etag = plain.header("etag").expect("an ETag").to_string();
    assert_eq!(Some(etag.as_str()), texels.header("etag"));
    let again = get(
        "/v1/rigs/wrinkled/layers/0".into(),
        vec![("if-none-match", etag.clone())],
    )
    .await;
    assert_eq!(again.status, 304);
    assert!(again.body.is_empty());
    // A new generation of the rig (a clip added): a new ETag, so a viewer fetches the texels
    // of the new generation once.
    server
        .client
        .upload_clip(
            "wrinkled",
            "name=other",
            "text/csv",
            Bytes::from(
                "brow
0
1",
            ),
        )
        .await
        .expect("clip");
    let after = get(
        "/v1/rigs/wrinkled/layers/0".into(),
        vec![("if-none-match", etag.clone())],
    )
    .await;
    assert_eq!(after.status, 200);
    assert_ne!(after.header("etag"), Some(etag.as_str()));
    // Unknown material, rig, or a material without layers: 404 with a JSON error.
    for (path, code) in [
        ("/v1/rigs/wrinkled/layers/1", "unknown_layers"),
        ("/v1/rigs/wrinkled/layers/x", "unknown_layers"),
        ("/v1/rigs/nope/layers/0", "unknown_rig"),
        ("/v1/rigs/nope/layers", "unknown_rig"),
        ("/v1/rigs/default-head/layers/0", "unknown_layers"),
    ] {
        let r = get(path.into(), vec![]).await;
        assert_eq!(r.status, 404, "{path}");
        assert_eq!(r.error().expect("a JSON error").error.code, code, "{path}");
    }
    // A rig without layers.
    let none = get("/v1/rigs/default-head/layers".into(), vec![]).await;
    let none: Value = serde_json::from_slice(&none.body).expect("JSON");
    assert_eq!(none, json!({"materials": [], "inputs": 0}));
    server.stop().await;
}

/// What a layers viewer received: per tick, its layer message's heads and bytes, and whether
/// that came just before the tick's vertices.
#[derive(Default)]
struct LayerLog {
    /// Per tick with a layer message: (heads listed, bytes on the wire).
    messages: BTreeMap<u64, (Vec<u64>, usize)>,
    /// Vertex messages received.
    ticks: u64,
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_layers_viewer_is_sent_each_heads_inputs_when_they_change_before_its_vertices() {
    let server = TestServer::start(ServerConfig::default()).await;
    let ramp: Vec<f32> = (0..8).map(|f| f as f32 / 7.0 * 1.4 - 0.2).collect();
    upload_wrinkle_rig(&server, "wrinkled", "ramp", &ramp).await;
    let still = [0.6f32; 8];
    let csv: String = std::iter::once("brow".to_string())
        .chain(still.iter().map(|w| w.to_string()))
        .collect::<Vec<_>>()
        .join("\n");
    server
        .client
        .upload_clip("wrinkled", "name=still", "text/csv", Bytes::from(csv))
        .await
        .expect("clip");
    // Heads 0..8 play the ramp at different offsets, head 8 holds still, head 9 is a rig
    // without layers.
    let ramps = 8u64;
    let mut heads: Vec<Value> = (0..ramps)
        .map(|h| json!({"head": h, "rig": "wrinkled", "clip": "ramp", "offset": h, "position": [h as f32 * 3.0, 0, 0]}))
        .collect();
    heads.push(
        json!({"head": 8, "rig": "wrinkled", "clip": "still", "offset": 0, "position": [0, 0, 3]}),
    );
    heads.push(json!({"head": 9, "rig": "default-head", "clip": "talk", "offset": 0, "position": [0, 0, 6]}));
    let req: crowdmorph_proto::SessionRequest =
        serde_json::from_value(json!({"fps": 20, "wrap": true, "heads": heads})).expect("request");
    let session = server
        .client
        .create_session(&req, None, Encoding::Json)
        .await
        .expect("session");
    let url = format!("ws://{}/v1/sessions/{}/stream", server.addr, session.id);
    // A layers viewer, the same packed, and one that did not ask.
    let mut viewers = Vec::new();
    for hello in [
        json!({"format": "q16", "layers": true}),
        json!({"format": "q16", "layers": true, "temporal": true, "compression": "deflate"}),
        json!({"format": "q16"}),
    ] {
        let (mut ws, _) = tokio_tungstenite::connect_async(&url)
            .await
            .expect("connect");
        ws.send(Message::text(hello.to_string()))
            .await
            .expect("hello");
        viewers.push(ws);
    }
    let mut logs = Vec::new();
    for (v, ws) in viewers.iter_mut().enumerate() {
        let mut state = StreamState::new();
        let mut log = LayerLog::default();
        let mut pending: Option<u64> = None;
        let deadline = Instant::now() + Duration::from_secs(60);
        while log.ticks < 30 {
            let msg = tokio::time::timeout_at(tokio::time::Instant::from_std(deadline), ws.next())
                .await
                .expect("30 ticks in time")
                .expect("open")
                .expect("a message");
            let Message::Binary(b) = msg else { continue };
            match state.receive(&b).expect("decodes") {
                Received::Layers(n) => {
                    assert!(pending.is_none(), "two layer messages in a row");
                    let tick = crowdmorph_proto::skim::skim(&b).expect("skims").tick;
                    let m: crowdmorph_proto::StreamMessage = if b[0] == 3 {
                        let crowdmorph_proto::StreamMessage::Packed(p) =
                            crowdmorph_proto::wire::response_from_bincode(&b).unwrap()
                        else {
                            unreachable!()
                        };
                        crowdmorph_proto::wire::response_from_bincode(&p.unpack().unwrap()).unwrap()
                    } else {
                        crowdmorph_proto::wire::response_from_bincode(&b).unwrap()
                    };
                    let crowdmorph_proto::StreamMessage::Layers(l) = m else {
                        panic!("not a layer message")
                    };
                    assert_eq!(l.heads.len(), n);
                    let ids = l.heads.iter().map(|h| h.head).collect();
                    log.messages.insert(tick, (ids, b.len()));
                    pending = Some(tick);
                }
                Received::Vertices(a) => {
                    if let Some(t) = pending.take() {
                        assert_eq!(t, a.tick, "the layers come just before their tick");
                    }
                    log.ticks += 1;
                    // Every wrinkled head that has a buffer draws its frame's weight.
                    for h in 0..=8u64 {
                        let Some(buffer) = state.buffer(h) else {
                            continue;
                        };
                        let clip: &[f32] = if h == 8 { &still } else { &ramp };
                        let inputs = state.layer_inputs(h);
                        if v == 2 {
                            assert_eq!(inputs, None, "viewer {v} did not ask for layers");
                            continue;
                        }
                        let want = clip[buffer.frame as usize];
                        let got = inputs.expect("a wrinkled head has inputs");
                        assert_eq!(got.len(), 1);
                        assert!(
                            (got[0] - want).abs() < 1e-6,
                            "viewer {v}, head {h} at frame {}: {got:?}, want {want}",
                            buffer.frame
                        );
                    }
                    assert_eq!(state.layer_inputs(9), None, "a rig without layers");
                }
                Received::Frame(_) => panic!("a frame"),
                Received::Poses(_) => panic!("poses for a vertex viewer"),
            }
        }
        logs.push(log);
    }
    for (v, log) in logs.iter().enumerate().take(2) {
        // The still head is sent its inputs once; ramp heads when their frame's weight changed.
        let sent_still = log
            .messages
            .values()
            .filter(|(ids, _)| ids.contains(&8))
            .count();
        assert_eq!(sent_still, 1, "viewer {v}: {:?}", log.messages);
        assert!(log.messages.values().all(|(ids, _)| !ids.contains(&9)));
        let per_tick =
            log.messages.values().map(|(_, b)| b).sum::<usize>() as f64 / log.ticks as f64;
        let listed = log
            .messages
            .values()
            .map(|(ids, _)| ids.len())
            .sum::<usize>() as f64
            / log.ticks as f64;
        println!(
            "viewer {v}: variant 4 averages {per_tick:.1} B per tick for {} heads with layers \
             ({listed:.1} listed per tick, {} ticks)",
            ramps + 1,
            log.ticks
        );
    }
    assert!(logs[2].messages.is_empty());
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_chromium),
    ignore = "no Chromium (apt-get install chromium, or set CROWDMORPH_CHROMIUM and touch build.rs)"
)]
async fn the_viewer_draws_expression_layers_as_the_server_does_in_headless_chromium() {
    let server = TestServer::start(ServerConfig::default()).await;
    // The head holds `brow` at 0.8: the quad shows 80 % of the way from the checker to the
    // bands.
    let brow = 0.8f32;
    upload_wrinkle_rig(&server, "wrinkled", "still", &[brow, brow]).await;
    let (browser, mut cdp) = open_page(&["Network.enable"]).await;
    cdp.call(
        "Page.navigate",
        json!({"url": format!("http://{}/viewer?rig=wrinkled&heads=1", server.addr)}),
    )
    .await;
    let tick = "window.crowdmorphViewer?.tick ?? 0";
    cdp.wait_for("the first tick", tick, Duration::from_secs(120), |v| {
        v.as_u64().unwrap_or(0) > 0
    })
    .await;
    let appearance = "window.crowdmorphViewer.appearance";
    cdp.wait_for(
        "the base texture and the layers on the GPU",
        appearance,
        Duration::from_secs(60),
        |v| v["imagesReady"].as_u64() == Some(1) && v["layersReady"].as_u64() == Some(1),
    )
    .await;
    cdp.wait_for(
        "head 0's layer inputs",
        "window.crowdmorphViewer.layerInputs",
        Duration::from_secs(60),
        |v| v["0"].is_array(),
    )
    .await;
    let drawn = "Number(document.getElementById('view').dataset.drawn || 0)";
    cdp.wait_for("the head drawn", drawn, Duration::from_secs(60), |v| {
        v.as_u64() == Some(1)
    })
    .await;
    let now = cdp.eval(tick).await.as_u64().unwrap();
    cdp.wait_for("ten more ticks", tick, Duration::from_secs(90), |v| {
        v.as_u64().unwrap_or(0) >= now + 10
    })
    .await;
    let inputs = cdp.eval("window.crowdmorphViewer.layerInputs").await;
    assert_eq!(inputs, json!({"0": [brow]}), "the page's inputs");

    let (view, path, image, panel) = still_screenshot(&mut cdp, "-layers").await;
    let frame = PageFrame::new(&view, &panel, f64::from(image.width));
    let with = compare_with_the_servers_render(
        &server,
        &view,
        &[("brow".to_string(), brow)],
        &image,
        &frame,
        &path,
    )
    .await;
    // The control: the server's render without the wrinkle (`brow` at 0). Where the wrinkle
    // shows (the two renders differ), the page is the render with it, and far from the one
    // without: a page that drew base colours alone would fail here.
    let without = the_servers_render_of_the_page(
        &server,
        &view,
        &[("brow".to_string(), 0.0)],
        &image,
        &frame,
    )
    .await;
    let channel_diff =
        |a: &[u8], b: &[u8]| (0..3).map(|c| a[c].abs_diff(b[c])).max().unwrap_or(0) as f64;
    let (mut shown, mut to_with, mut to_without) = (0usize, 0.0, 0.0);
    for ((w, o), p) in with
        .server
        .rgba
        .chunks_exact(4)
        .zip(without.server.rgba.chunks_exact(4))
        .zip(with.page.rgba.chunks_exact(4))
    {
        if is_drawn(w) && is_drawn(o) && is_drawn(p) && channel_diff(w, o) > 40.0 {
            shown += 1;
            to_with += channel_diff(p, w);
            to_without += channel_diff(p, o);
        }
    }
    let (to_with, to_without) = (
        to_with / shown.max(1) as f64,
        to_without / shown.max(1) as f64,
    );
    println!(
        "where the wrinkle shows ({shown} pixels), the page is {to_with:.1}/255 from the \
         server's render with it and {to_without:.1}/255 from the one without"
    );
    assert!(shown > 2000, "the wrinkle shows on {shown} pixels only");
    assert!(
        to_without > 60.0 && to_with < to_without / 4.0,
        "the page does not show the wrinkle as the server does: {to_with:.1} from the render \
         with it, {to_without:.1} from the one without"
    );

    // Layers fetched once, the texels by their versioned URI; nothing more while ticking.
    let requests = cdp.requests();
    let matching = |part: &str| -> Vec<Request> {
        requests
            .iter()
            .filter(|r| r.url.contains(part))
            .cloned()
            .collect()
    };
    let docs: Vec<Request> = matching("/v1/rigs/wrinkled/layers")
        .into_iter()
        .filter(|r| r.url.ends_with("/layers"))
        .collect();
    let texels = matching("/v1/rigs/wrinkled/layers/0?v=");
    assert_eq!(docs.len(), 1, "{requests:#?}");
    assert_eq!(texels.len(), 1, "{requests:#?}");
    no_requests_for_30_ticks(&mut cdp, tick, requests.len()).await;
    let stats = cdp.eval(appearance).await;
    assert_eq!(stats["layerFetches"], json!(1), "{stats}");
    assert_eq!(stats["texelFetches"], json!(1), "{stats}");
    assert_eq!(stats["layerFailures"], json!(0), "{stats}");
    let received = cdp.eval("window.crowdmorphViewer.received").await;
    let variants = received["variants"].as_array().unwrap();
    let bytes = |rs: &[Request]| -> u64 { rs.iter().map(|r| r.body_bytes.unwrap_or(0)).sum() };
    let wire = |rs: &[Request]| -> u64 { rs.iter().map(|r| r.wire_bytes.unwrap_or(0)).sum() };
    println!(
        "layers, fetched once per rig: /layers {} B ({} B on the wire), texels {} B ({} B on \
         the wire); variant 4: {} messages, {} B inflated in all (a still head is sent its \
         inputs once)",
        bytes(&docs),
        wire(&docs),
        bytes(&texels),
        wire(&texels),
        variants[4],
        received["layerBytes"],
    );
    assert_eq!(
        variants[4],
        json!(1),
        "a still head's inputs are sent once: {received}"
    );
    let errors = cdp.errors();
    assert!(errors.is_empty(), "the page logged errors: {errors:#?}");
    assert_eq!(cdp.eval(ERROR_TEXT).await, json!(""));
    drop(cdp);
    drop(browser);
    server.stop().await;
}

/// An avatar with no clips at all (VALID's, as uploaded): `/viewer?rig=ID` gets a session of
/// its neutral, alive (each head blinking, darting its eyes and breathing), instead of an error;
/// the stream ticks and every head is drawn.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_chromium),
    ignore = "no Chromium (apt-get install chromium, or set CROWDMORPH_CHROMIUM and touch build.rs)"
)]
async fn the_viewer_shows_a_rig_without_clips_alive_in_headless_chromium() {
    let server = TestServer::start(ServerConfig::default()).await;
    let glb = std::fs::read(
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/data/avatars/valid-white-f-1/White_F_1_Casual.glb"),
    )
    .expect("avatar");
    let info = server
        .client
        .upload_rig("avatar", Bytes::from(glb))
        .await
        .expect("upload");
    assert!(info.clips.is_empty(), "the avatar has no clips");
    let (browser, mut cdp) = open_page(&[]).await;
    cdp.call(
        "Page.navigate",
        json!({"url": format!("http://{}/viewer?rig=avatar&heads=4", server.addr)}),
    )
    .await;
    let tick = "window.crowdmorphViewer?.tick ?? 0";
    let first = cdp
        .wait_for("the first tick", tick, Duration::from_secs(120), |v| {
            v.as_u64().unwrap_or(0) > 0
        })
        .await
        .as_u64()
        .unwrap();
    cdp.wait_for("ten more ticks", tick, Duration::from_secs(90), |v| {
        v.as_u64().unwrap_or(0) >= first + 10
    })
    .await;
    let drawn = "Number(document.getElementById('view').dataset.drawn || 0)";
    cdp.wait_for("4 heads drawn", drawn, Duration::from_secs(90), |v| {
        v.as_u64() == Some(4)
    })
    .await;
    let id = cdp
        .eval("new URL(location.href).searchParams.get('session')")
        .await;
    let id = id.as_str().expect("the page names its session").to_string();
    let session = session_info(&server, &id).await;
    assert_eq!(session.heads.len(), 4);
    for h in &session.heads {
        assert!(h.clip.is_empty() && h.graph.is_none(), "{h:?}");
        let alive = h.alive.as_ref().expect("alive");
        assert!(alive.blink && alive.saccades && alive.breathing, "{h:?}");
    }
    let errors = cdp.errors();
    assert!(errors.is_empty(), "the page logged errors: {errors:#?}");
    assert_eq!(cdp.eval(ERROR_TEXT).await, json!(""));
    drop(cdp);
    drop(browser);
    server.stop().await;
}
