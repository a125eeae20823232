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
use crowdmorph_client::Method;
use crowdmorph_proto::{Received, SessionInfo, StreamState};
use futures_util::{SinkExt, StreamExt};
use serde_json::{Value, json};
use tokio_tungstenite::tungstenite::Message;

use super::TestServer;
use crate::util::browser::{Browser, Cdp, base64_decode};
use crate::util::image::Image;

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

fn screenshot_path() -> PathBuf {
    std::env::var_os("CROWDMORPH_VIEWER_SCREENSHOT")
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            Path::new(env!("CARGO_MANIFEST_DIR")).join("target/viewer-screenshot.png")
        })
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
    let mut browser = Browser::launch();
    let mut cdp = browser.page().await;
    cdp.shown_error = Some(ERROR_TEXT);
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
    let shot = cdp
        .call("Page.captureScreenshot", json!({"format": "png"}))
        .await;
    let png = base64_decode(shot["data"].as_str().unwrap());
    let path = screenshot_path();
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).unwrap();
    }
    std::fs::write(&path, &png).unwrap();
    println!("viewer screenshot: {}", path.display());
    let image = Image::decode_png(&png).unwrap();
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
        json!({"format": "q16", "temporal": true, "compression": "deflate"}),
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
        json!({"format": "q16", "temporal": false, "compression": null}),
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
