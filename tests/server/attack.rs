//! Renders and sessions under attack, with no admin token (the default): the reproductions of
//! the hardening issue, one test each, run against in-process servers and the real binary.
//!
//! | reproduction | test |
//! |---|---|
//! | 10,000 clones at 64 × 48: a 504 at 10 s while the cores keep rendering | [`a_render_of_ten_thousand_clones_is_refused_before_any_work`], [`after_a_504_the_render_stops_and_the_process_goes_idle`] |
//! | eight 1,000-head renders make every render time out | [`big_renders_in_flight_make_others_wait_with_a_503_not_a_504`] |
//! | a client that hangs up leaves its render running | [`a_render_whose_client_hangs_up_stops`] |
//! | a `PUT .../lod` whose client hangs up (its build stopped, but counted running forever) | [`a_lod_put_whose_client_hangs_up_stops_and_is_counted`] |
//! | finite but absurd cameras and placements are 500 `internal` | [`absurd_cameras_and_placements_are_400s_naming_the_field`] |
//! | the same camera in a viewer's hello is accepted and never drawn | [`a_viewer_with_an_absurd_camera_is_closed_with_1008`] |
//! | a tiny session fps panics the tick task and leaves a zombie | [`tiny_fps_is_refused_and_slow_sessions_still_end_at_their_idle_timeout`], [`a_panicking_tick_ends_its_session`] |
//! | frames viewers hold the whole render budget | [`viewers_images_are_capped_and_http_renders_are_served_while_viewers_stream`] |
//! | none of it may reach an ERROR log line | [`hostile_renders_and_sessions_log_no_error`] |

use crate::util::gpu_test;
use std::path::Path;
use std::time::{Duration, Instant};

use bytes::Bytes;
use crowdmorph::server::ServerConfig;
use crowdmorph::server::sessions::SessionLimits;
use crowdmorph_client::{Client, Method, Reply};
use futures_util::SinkExt;
use serde_json::{Value, json};
use tokio::io::AsyncWriteExt;
use tokio_tungstenite::tungstenite::Message;

use super::persistence::{Proc, ready, spawn_with};
use super::sessions::{self, call, connect, create, next_close};
use super::{TestServer, temp_dir};

/// `n` clones of the embedded head (frame 0 of `talk`) at `width × height`, as the issue's
/// reproduction writes them.
fn clones(n: u64, width: u32, height: u32) -> Value {
    let heads: Vec<Value> = (0..n)
        .map(|i| json!({"head": i, "rig": "default-head", "clip": "talk", "frame": 0}))
        .collect();
    json!({"heads": heads, "image": {"width": width, "height": height}})
}

async fn post_json(client: &Client, path: &str, body: &Value) -> Reply {
    client
        .send(
            Method::POST,
            path,
            Some("application/json"),
            None,
            Bytes::from(body.to_string()),
        )
        .await
        .expect("request")
}

fn error_code(r: &Reply) -> String {
    r.error().map(|e| e.error.code).unwrap_or_default()
}

fn error_message(r: &Reply) -> String {
    r.error().map(|e| e.error.message).unwrap_or_default()
}

/// CPU seconds (user + system) the process has used, from `/proc/<pid>/stat`.
pub(super) fn cpu_seconds(pid: u32) -> f64 {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).expect("stat");
    // Fields after the command name (which is in parentheses and may hold spaces).
    let rest = &stat[stat.rfind(')').expect("comm") + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks = |i: usize| f[i].parse::<f64>().expect("a number");
    // utime and stime are fields 14 and 15 of the line, 12 and 13 after the command name.
    // SAFETY: sysconf reads a constant of the running system.
    let hz = unsafe { libc::sysconf(libc::_SC_CLK_TCK) } as f64;
    (ticks(11) + ticks(12)) / hz
}

/// The share of one core the process used over `window`.
pub(super) async fn cores_used(pid: u32, window: Duration) -> f64 {
    let before = cpu_seconds(pid);
    tokio::time::sleep(window).await;
    (cpu_seconds(pid) - before) / window.as_secs_f64()
}

/// The real binary with `env`, on the CPU engine and without the background LOD job.
pub(super) async fn binary(tag: &str, env: &[(&str, &str)]) -> (Proc, Client) {
    let dir = temp_dir(tag);
    let mut all = vec![
        ("CROWDMORPH_BACKEND", "cpu"),
        ("CROWDMORPH_NO_AUTO_LOD", "true"),
    ];
    all.extend_from_slice(env);
    let proc = spawn_with(Path::new(&dir), &all);
    let client = Client::new(proc.base.clone());
    ready(&client).await;
    (proc, client)
}

/// A sample's value; NaN when the page lacks it, so that no comparison passes on a series that
/// is not exported.
pub(super) fn metric(page: &str, name: &str) -> f64 {
    crowdmorph_client::metric(page, name).unwrap_or(f64::NAN)
}

gpu_test!(
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_render_of_ten_thousand_clones_is_refused_before_any_work() {
        let server = TestServer::start(ServerConfig::default()).await;
        // The body: 6.8 MB, under --max-heads and --max-request-bytes.
        let started = Instant::now();
        let r = post_json(&server.client, "/v1/crowd/render", &clones(10_000, 64, 48)).await;
        assert_eq!(r.status, 413, "{}", String::from_utf8_lossy(&r.body));
        assert_eq!(error_code(&r), "render_too_costly");
        let m = error_message(&r);
        assert!(
            m.contains("--render-work-ms") && m.contains("triangles"),
            "the message names the limit and what was priced: {m}"
        );
        // Refused at admission: nothing was blended or drawn, so nothing holds the budgets.
        let page = server.client.metrics().await.expect("metrics");
        assert_eq!(metric(&page, "crowdmorph_render_work_seconds"), 0.0);
        assert_eq!(metric(&page, "crowdmorph_render_pixels"), 0.0);
        assert_eq!(
            metric(
                &page,
                "crowdmorph_rejected_total{reason=\"render_too_costly\"}"
            ),
            1.0
        );
        eprintln!(
            "10,000 clones refused in {:.0} ms",
            started.elapsed().as_secs_f64() * 1e3
        );
        // A normal render is served as before.
        let r = post_json(&server.client, "/v1/crowd/render", &clones(3, 64, 48)).await;
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
        server.stop().await;
    }
);

gpu_test!(
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn big_renders_in_flight_make_others_wait_with_a_503_not_a_504() {
        let server = TestServer::start(ServerConfig::default()).await;
        // Eight big renders and a normal one at once: what fits the work budget is drawn, the rest
        // is told to come back (503 with Retry-After) at once; nothing runs past its deadline. (The
        // issue's 1,000-head renders are estimated past the whole default budget on lavapipe, a
        // 413; 300 heads, about 1.5 s each there, fit one at a time.)
        let big = clones(300, 64, 48);
        let mut tasks = Vec::new();
        for _ in 0..8 {
            let c = server.client.clone();
            let body = big.clone();
            tasks.push(tokio::spawn(async move {
                post_json(&c, "/v1/crowd/render", &body).await
            }));
        }
        let normal = {
            let c = server.client.clone();
            tokio::spawn(async move { post_json(&c, "/v1/crowd/render", &clones(2, 64, 48)).await })
        };
        let (mut served, mut busy) = (0, 0);
        for t in tasks.into_iter().chain([normal]) {
            let r = t.await.expect("join");
            match r.status {
                200 => served += 1,
                503 => {
                    busy += 1;
                    assert_eq!(error_code(&r), "render_busy");
                    assert!(
                        r.header("retry-after")
                            .and_then(|v| v.parse::<u32>().ok())
                            .is_some_and(|s| (1..=60).contains(&s)),
                        "a 503 says when to retry"
                    );
                }
                s => panic!("{s}: {}", String::from_utf8_lossy(&r.body)),
            }
        }
        assert!(served >= 1, "what fits is drawn");
        assert!(
            busy >= 1,
            "renders that do not fit beside those in flight are refused with 503"
        );
        // Once they are done, the normal render is served.
        let r = post_json(&server.client, "/v1/crowd/render", &clones(2, 64, 48)).await;
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
        server.stop().await;
    }
);

gpu_test!(
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn after_a_504_the_render_stops_and_the_process_goes_idle() {
        // A work budget large enough to admit 10,000 clones (estimated at tens of seconds on
        // lavapipe) and a one-second deadline: the client gets its 504, and the work stops at
        // its next stage boundary instead of running on for minutes.
        let (mut proc, client) = binary(
            "render-504",
            &[
                ("CROWDMORPH_REQUEST_TIMEOUT_MS", "1000"),
                ("CROWDMORPH_RENDER_WORK_MS", "600000"),
            ],
        )
        .await;
        let pid = proc.child.id();
        let before = cpu_seconds(pid);
        let r = post_json(&client, "/v1/crowd/render", &clones(10_000, 64, 48)).await;
        assert_eq!(r.status, 504, "{}", String::from_utf8_lossy(&r.body));
        assert!(
            cpu_seconds(pid) - before > 0.5,
            "the render was drawing until its 504"
        );
        // Within a second or two the process is idle: measured over the second after that.
        tokio::time::sleep(Duration::from_millis(1500)).await;
        let used = cores_used(pid, Duration::from_secs(1)).await;
        assert!(
            used < 0.25,
            "the process still uses {used:.2} cores after the 504"
        );
        let page = client.metrics().await.expect("metrics");
        assert_eq!(
            metric(
                &page,
                "crowdmorph_cancelled_total{work=\"render\",reason=\"deadline\"}"
            ),
            1.0,
            "the render stopped by its deadline is counted"
        );
        assert_eq!(metric(&page, "crowdmorph_render_work_seconds"), 0.0);
        let _ = proc.child.kill();
        let _ = proc.child.wait();
    }
);

gpu_test!(
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_render_whose_client_hangs_up_stops() {
        let (mut proc, client) =
            binary("render-gone", &[("CROWDMORPH_RENDER_WORK_MS", "600000")]).await;
        let pid = proc.child.id();
        // The request by hand, and the socket closed while the server draws.
        let body = clones(10_000, 64, 48).to_string();
        let addr = proc.base.trim_start_matches("http://").to_string();
        let mut tcp = tokio::net::TcpStream::connect(&addr)
            .await
            .expect("connect");
        let head = format!(
            "POST /v1/crowd/render HTTP/1.1\r\nhost: {addr}\r\ncontent-type: application/json\r\n\
             content-length: {}\r\n\r\n",
            body.len()
        );
        tcp.write_all(head.as_bytes()).await.expect("write");
        tcp.write_all(body.as_bytes()).await.expect("write");
        tokio::time::sleep(Duration::from_millis(1000)).await;
        let busy = cores_used(pid, Duration::from_millis(500)).await;
        assert!(busy > 0.5, "the render was drawing: {busy:.2} cores");
        drop(tcp);
        tokio::time::sleep(Duration::from_millis(1500)).await;
        let used = cores_used(pid, Duration::from_secs(1)).await;
        assert!(
            used < 0.25,
            "drawing for a client that left: {used:.2} cores (while it was there: {busy:.2})"
        );
        let page = client.metrics().await.expect("metrics");
        assert_eq!(
            metric(
                &page,
                "crowdmorph_cancelled_total{work=\"render\",reason=\"dropped\"}"
            ),
            1.0,
            "{page}"
        );
        let _ = proc.child.kill();
        let _ = proc.child.wait();
    }
);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_lod_put_whose_client_hangs_up_stops_and_is_counted() {
    let server = TestServer::start(ServerConfig::default()).await;
    let m = server.state.metrics.clone();
    // The metric order of the embedded head: seconds of scoring, by hand so the test hangs up.
    let body = json!({"method": "combined", "mesh_fractions": [0.5, 0.25]}).to_string();
    let mut tcp = tokio::net::TcpStream::connect(server.addr)
        .await
        .expect("connect");
    let head = format!(
        "PUT /v1/rigs/default-head/lod HTTP/1.1\r\nhost: test\r\ncontent-type: application/json\r\n\
         content-length: {}\r\n\r\n",
        body.len()
    );
    tcp.write_all(head.as_bytes()).await.expect("write");
    tcp.write_all(body.as_bytes()).await.expect("write");
    let t0 = Instant::now();
    while m.lod_builds_running.get() == 0 {
        assert!(
            t0.elapsed() < Duration::from_secs(30),
            "no LOD build started"
        );
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    drop(tcp);
    // The build stops at its next stage, and is neither counted running forever nor lost.
    while m.lod_builds_running.get() > 0 {
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "the LOD build of a client that left is still counted running"
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let page = server.client.metrics().await.expect("metrics");
    assert_eq!(
        metric(
            &page,
            "crowdmorph_cancelled_total{work=\"lod\",reason=\"dropped\"}"
        ),
        1.0
    );
    assert_eq!(metric(&page, "crowdmorph_lod_builds_cancelled_total"), 1.0);
    // The rig kept its LOD: the cancelled build changed nothing.
    let lod = server.client.lod("default-head").await.expect("lod");
    assert_eq!(lod.status, "imported", "{lod:?}");
    server.stop().await;
}

/// The absurd cameras and placements of the issue, each with the code and the field it must
/// be named by.
fn absurd_scenes() -> Vec<(Value, &'static str, &'static str)> {
    let cam = |c: Value| json!({"camera": c});
    let placed = |p: Value| json!({"placements": [p]});
    vec![
        (
            cam(json!({"position": [3e38, 0, 5], "target": [0, 0, 0]})),
            "invalid_camera",
            "position",
        ),
        (
            cam(json!({"position": [0, 0, 5], "target": [0, 0, 0], "fov_y": 1e-40})),
            "invalid_camera",
            "fov_y",
        ),
        (
            cam(json!({"position": [0, 0, 5], "target": [0, 0, 0], "near": 1e-45, "far": 1e-44})),
            "invalid_camera",
            "near",
        ),
        (
            cam(json!({"position": [0, 0, 5], "target": [0, 0, 0], "near": 1e-3, "far": 1e30})),
            "invalid_camera",
            "far",
        ),
        (
            cam(json!({"position": [1e-30, 0, 0], "target": [0, 0, 0]})),
            "invalid_camera",
            "target",
        ),
        (
            placed(json!({"head": 1, "position": [1e20, 0, 0]})),
            "invalid_placement",
            "position",
        ),
        (
            placed(json!({"head": 1, "position": [0, -1e20, 0]})),
            "invalid_placement",
            "position",
        ),
        (
            placed(json!({"head": 1, "position": [0, 0, 0], "scale": 1e-30})),
            "invalid_placement",
            "scale",
        ),
        (
            placed(json!({"head": 1, "position": [0, 0, 0], "scale": 1e30})),
            "invalid_placement",
            "scale",
        ),
    ]
}

fn with_heads(extra: &Value) -> Value {
    let mut v = json!({
        "heads": [{"head": 1, "rig": "default-head", "clip": "talk", "frame": 3},
                  {"head": 2, "rig": "default-head", "clip": "talk", "frame": 9}],
        "image": {"width": 64, "height": 48}
    });
    if let (Some(o), Some(e)) = (v.as_object_mut(), extra.as_object()) {
        o.extend(e.clone());
    }
    v
}

gpu_test!(
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn absurd_cameras_and_placements_are_400s_naming_the_field() {
        let server = TestServer::start(ServerConfig::default()).await;
        for (extra, code, field) in absurd_scenes() {
            let r = post_json(&server.client, "/v1/crowd/render", &with_heads(&extra)).await;
            assert_eq!(
                r.status,
                400,
                "{extra}: {}",
                String::from_utf8_lossy(&r.body)
            );
            assert_eq!(error_code(&r), code, "{extra}");
            let m = error_message(&r);
            assert!(m.contains(field), "{extra}: {m:?} names {field:?}");
        }
        // Huge but meaningful numbers are drawn: a yaw of 1e30 degrees is an angle, a camera a
        // million units away with a narrow lens sees the crowd.
        for extra in [
            json!({"placements": [{"head": 1, "position": [0, 0, 0], "yaw": 1e30}]}),
            json!({"camera": {"position": [0, 0, 1e6], "target": [0, 0, 0], "fov_y": 0.1}}),
            json!({"placements": [{"head": 2, "position": [1e6, -1e6, 1e6], "scale": 1e4}]}),
        ] {
            let r = post_json(&server.client, "/v1/crowd/render", &with_heads(&extra)).await;
            assert_eq!(
                r.status,
                200,
                "{extra}: {}",
                String::from_utf8_lossy(&r.body)
            );
        }
        // The same placements in a session are refused when the session is made.
        let (status, v) = call(
            &server,
            Method::POST,
            "/v1/sessions",
            json!({"heads": [{"head": 1, "rig": "default-head", "clip": "talk", "position": [1e20, 0, 0]}]}),
        )
        .await;
        assert_eq!(status, 400, "{v}");
        assert!(v.to_string().contains("position"), "{v}");
        server.stop().await;
    }
);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_viewer_with_an_absurd_camera_is_closed_with_1008() {
    let server = TestServer::start(ServerConfig::default()).await;
    let s = create(
        &server,
        json!({"fps": 120, "heads": [sessions::head(1, "talk", 0, [0.0, 0.0, 0.0])]}),
    )
    .await;
    for camera in [
        json!({"position": [3e38, 0, 5], "target": [0, 0, 0]}),
        json!({"position": [0, 0, 5], "target": [0, 0, 0], "fov_y": 1e-40}),
        json!({"position": [0, 0, 5], "target": [0, 0, 0], "near": 1e-45, "far": 1e-44}),
    ] {
        let mut ws = connect(
            &server,
            &s.id,
            json!({"output": "frames", "camera": camera}),
        )
        .await;
        let (code, reason) = next_close(&mut ws).await;
        assert_eq!(code, 1008, "{camera}: {reason}");
        assert!(reason.contains("camera"), "{reason}");
    }
    // An update to such a camera closes a viewer that was fine.
    let mut ws = connect(
        &server,
        &s.id,
        json!({"camera": {"position": [0, 0, 2], "target": [0, 0, 0]}}),
    )
    .await;
    ws.send(Message::text(
        json!({"camera": {"position": [0, 0, 5], "target": [0, 0, 0], "fov_y": 1e-40}}).to_string(),
    ))
    .await
    .expect("update");
    let (code, reason) = next_close(&mut ws).await;
    assert_eq!(code, 1008, "{reason}");
    assert!(reason.contains("fov_y"), "{reason}");
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tiny_fps_is_refused_and_slow_sessions_still_end_at_their_idle_timeout() {
    let server = TestServer::start(ServerConfig {
        sessions: SessionLimits {
            max_sessions: 3,
            ..SessionLimits::default()
        },
        ..ServerConfig::default()
    })
    .await;
    for fps in [1e-30, 1e-10, 0.05] {
        let (status, v) = call(
            &server,
            Method::POST,
            "/v1/sessions",
            json!({"fps": fps, "idle_timeout_s": 1, "heads": []}),
        )
        .await;
        assert_eq!(status, 400, "fps {fps}: {v}");
        assert!(
            v.to_string().contains("fps") && v.to_string().contains("0.1"),
            "{v}"
        );
    }
    // Three sessions at the lowest rate, a tick every ten seconds, fill --max-sessions; each
    // still ends one second after it was left idle, so new sessions can be made.
    let started = Instant::now();
    let mut ids = Vec::new();
    for _ in 0..3 {
        ids.push(
            create(
                &server,
                json!({"fps": 0.1, "idle_timeout_s": 1, "heads": []}),
            )
            .await
            .id,
        );
    }
    let (status, _) = call(
        &server,
        Method::POST,
        "/v1/sessions",
        json!({"fps": 0.1, "heads": []}),
    )
    .await;
    assert_eq!(status, 503, "the sessions are full");
    for id in &ids {
        let mut gone = false;
        for _ in 0..100 {
            let (status, _) = call(
                &server,
                Method::GET,
                &format!("/v1/sessions/{id}"),
                Value::Null,
            )
            .await;
            if status == 404 {
                gone = true;
                break;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        assert!(gone, "session {id} ended");
    }
    assert!(
        started.elapsed() < Duration::from_secs(8),
        "the sessions ended at their idle timeout, not at their next tick ({:?})",
        started.elapsed()
    );
    create(&server, json!({"fps": 0.1, "heads": []})).await;
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_panicking_tick_ends_its_session() {
    let server = TestServer::start(ServerConfig {
        sessions: SessionLimits {
            max_sessions: 1,
            ..SessionLimits::default()
        },
        ..ServerConfig::default()
    })
    .await;
    let s = create(
        &server,
        json!({"fps": 20, "heads": [sessions::head(1, "talk", 0, [0.0, 0.0, 0.0])]}),
    )
    .await;
    let mut ws = connect(&server, &s.id, json!({})).await;
    assert!(server.state.sessions.panic_next_tick(&s.id));
    let (code, reason) = next_close(&mut ws).await;
    assert_eq!(code, 1011, "{reason}");
    let (status, _) = call(
        &server,
        Method::GET,
        &format!("/v1/sessions/{}", s.id),
        Value::Null,
    )
    .await;
    assert_eq!(status, 404, "the session is gone");
    let page = server.client.metrics().await.expect("metrics");
    assert_eq!(metric(&page, "crowdmorph_session_panics_total"), 1.0);
    assert_eq!(metric(&page, "crowdmorph_sessions"), 0.0);
    // It no longer counts toward --max-sessions.
    create(&server, json!({"heads": []})).await;
    server.stop().await;
}

gpu_test!(
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn viewers_images_are_capped_and_http_renders_are_served_while_viewers_stream() {
        // The 16 viewers of 4096² are refused at their hello by --max-viewer-pixels.
        let server = TestServer::start(ServerConfig::default()).await;
        let s = create(
            &server,
            json!({"fps": 30, "heads": [sessions::head(1, "talk", 0, [0.0, 0.0, 0.0])]}),
        )
        .await;
        for _ in 0..16 {
            let mut ws = connect(
                &server,
                &s.id,
                json!({"output": "frames", "image": {"width": 4096, "height": 4096}}),
            )
            .await;
            let (code, reason) = next_close(&mut ws).await;
            assert_eq!(code, 1008, "{reason}");
            assert!(reason.contains("--max-viewer-pixels"), "{reason}");
        }
        server.stop().await;

        // Within the cap, viewers that would fill the pixel budget hold at most their share: a
        // budget of four 256² images, eight viewers of 256² each at 30 fps (together at most two
        // images), and HTTP renders of 256² keep being served (one, and the previous one's
        // pixels until its body is sent).
        let side = 256u32;
        let server = TestServer::start(ServerConfig {
            render_pixels: 4 * u64::from(side * side),
            sessions: SessionLimits {
                max_viewer_pixels: u64::from(side * side),
                ..SessionLimits::default()
            },
            ..ServerConfig::default()
        })
        .await;
        let s = create(
            &server,
            json!({"fps": 30, "heads": [sessions::head(1, "talk", 0, [0.0, 0.0, 0.0]),
                                        sessions::head(2, "smile", 0, [0.3, 0.0, 0.0])]}),
        )
        .await;
        let mut viewers = Vec::new();
        for _ in 0..8 {
            viewers.push(
                connect(
                    &server,
                    &s.id,
                    json!({"output": "frames", "image": {"width": side, "height": side, "format": "png"}}),
                )
                .await,
            );
        }
        // Let them stream.
        tokio::time::sleep(Duration::from_millis(500)).await;
        let mut statuses = Vec::new();
        for _ in 0..10 {
            let r = post_json(&server.client, "/v1/crowd/render", &clones(2, side, side)).await;
            statuses.push((r.status, error_code(&r)));
        }
        assert!(
            statuses.iter().all(|(s, _)| *s == 200),
            "HTTP renders while 8 viewers stream: {statuses:?}"
        );
        let page = server.client.metrics().await.expect("metrics");
        assert!(
            metric(&page, "crowdmorph_session_messages_total{result=\"sent\"}") > 0.0,
            "the viewers were served too"
        );
        drop(viewers);
        server.stop().await;
    }
);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hostile_renders_and_sessions_log_no_error() {
    // The inputs against the real binary, and its log read back: a client's mistakes
    // are answered (4xx, 1008) and logged at WARN at most.
    let (mut proc, client) = binary("no-error", &[]).await;
    for (extra, _, _) in absurd_scenes() {
        let r = post_json(&client, "/v1/crowd/render", &with_heads(&extra)).await;
        assert_eq!(r.status, 400, "{extra}");
    }
    let r = post_json(&client, "/v1/crowd/render", &clones(10_000, 64, 48)).await;
    assert!(
        r.status == 413 || r.status == 503,
        "{}",
        String::from_utf8_lossy(&r.body)
    );
    for fps in [1e-30, 1e-10] {
        let r = post_json(
            &client,
            "/v1/sessions",
            &json!({"fps": fps, "idle_timeout_s": 1, "heads": []}),
        )
        .await;
        assert_eq!(r.status, 400);
    }
    let s = post_json(
        &client,
        "/v1/sessions",
        &json!({"fps": 120, "heads": [{"head": 1, "rig": "default-head", "clip": "talk"}]}),
    )
    .await;
    assert_eq!(s.status, 201);
    let id = serde_json::from_slice::<Value>(&s.body).expect("JSON")["id"]
        .as_str()
        .expect("id")
        .to_string();
    let url = format!(
        "{}/v1/sessions/{id}/stream",
        proc.base.replace("http://", "ws://")
    );
    for _ in 0..4 {
        let (mut ws, _) = tokio_tungstenite::connect_async(&url)
            .await
            .expect("connect");
        ws.send(Message::text(
            json!({"output": "frames", "camera": {"position": [3e38, 0, 5], "target": [0, 0, 0]}})
                .to_string(),
        ))
        .await
        .expect("hello");
        let (code, _) = next_close(&mut ws).await;
        assert_eq!(code, 1008);
    }
    let name = "x".repeat(1 << 20);
    let r = client
        .send(
            Method::PUT,
            "/v1/rigs/default-head/lod",
            Some("application/json"),
            None,
            Bytes::from(json!({"pinned": [name]}).to_string()),
        )
        .await
        .expect("request");
    assert_eq!(r.status, 400);
    assert!(
        r.body.len() < 4096,
        "a 1 MB bad name is not echoed back whole: {} bytes",
        r.body.len()
    );
    // A moment for anything logged late (a session tick, a viewer's frame).
    tokio::time::sleep(Duration::from_millis(500)).await;
    let log = proc.log.lock().unwrap().clone();
    let errors: Vec<&String> = log.iter().filter(|l| l.contains("ERROR")).collect();
    assert!(errors.is_empty(), "client-caused ERROR lines: {errors:#?}");
    let _ = proc.child.kill();
    let _ = proc.child.wait();
}

#[test]
fn a_log_written_to_a_pipe_has_no_colour_codes() {
    use std::io::BufRead;
    // Without NO_COLOR (which `spawn_with` sets): a pipe is not a terminal.
    let dir = temp_dir("no-colour");
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_crowdmorph"))
        .args([
            "serve",
            "--addr",
            "127.0.0.1:0",
            "--backend",
            "cpu",
            "--no-auto-lod",
            "--data-dir",
        ])
        .arg(&dir)
        .env_remove("NO_COLOR")
        .env("RUST_LOG", "info")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("spawn");
    let stderr = child.stderr.take().expect("stderr");
    let mut text = String::new();
    for line in std::io::BufReader::new(stderr)
        .lines()
        .map_while(Result::ok)
    {
        text.push_str(&line);
        text.push('\n');
        if line.contains("listening") {
            break;
        }
    }
    let _ = child.kill();
    let _ = child.wait();
    assert!(text.contains("listening"), "{text}");
    assert!(
        !text.contains('\u{1b}'),
        "escape codes in a piped log: {text:?}"
    );
}
