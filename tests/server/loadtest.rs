//! `POST /v1/loadtest`: the report of a synthetic load run through the real batcher, its
//! labels in the metrics, one load at a time, caps as 400, the admin token, and the priority
//! of client requests over the synthetic ones. Assertions are on counts and order, never on
//! how long anything took.

use std::time::Duration;

use bytes::Bytes;
use crowdmorph::load::{CrowdShape, RigClips};
use crowdmorph::server::ServerConfig;
use crowdmorph::server::loadtests::LoadtestStatus;
use crowdmorph_client::{Client, Encoding, Method, Reply, metric};
use crowdmorph_proto::{CrowdFrameRequest, Format, Head, OutputOptions};
use serde_json::json;

use super::TestServer;

async fn post(client: &Client, query: &str, body: serde_json::Value) -> Reply {
    client
        .send(
            Method::POST,
            &format!("/v1/loadtest{query}"),
            Some("application/json"),
            Some("application/json"),
            Bytes::from(body.to_string()),
        )
        .await
        .expect("POST /v1/loadtest")
}

async fn get(client: &Client, id: &str) -> Reply {
    client
        .send(
            Method::GET,
            &format!("/v1/loadtest/{id}"),
            None,
            None,
            Bytes::new(),
        )
        .await
        .expect("GET /v1/loadtest")
}

fn status_of(reply: &Reply) -> LoadtestStatus {
    assert!(
        reply.status == 200 || reply.status == 202,
        "{} {}",
        reply.status,
        String::from_utf8_lossy(&reply.body)
    );
    serde_json::from_slice(&reply.body).expect("a LoadtestStatus")
}

fn code_of(reply: &Reply) -> (u16, String) {
    (
        reply.status,
        reply.error().map(|e| e.error.code).unwrap_or_default(),
    )
}

/// Polls `GET /v1/loadtest/{id}` every 50 ms (at most 60 s) until `until` holds.
async fn wait_for(
    client: &Client,
    id: &str,
    until: impl Fn(&LoadtestStatus) -> bool,
) -> LoadtestStatus {
    for _ in 0..1200 {
        let s = status_of(&get(client, id).await);
        if until(&s) {
            return s;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    panic!("load test {id} never reached the state waited for");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_load_test_reports_what_it_sent_and_its_traffic_is_labelled() {
    let server = TestServer::start(ServerConfig::default()).await;
    // 0.5 s at 80 requests/s: requests 0..40, 5 heads over 2 unique jobs each.
    let body = json!({
        "rate": 80, "duration_s": 0.5, "concurrency": 4,
        "crowd": {"heads": 5, "unique": 0.4, "clips": {"talk": 1, "smile": 2},
                  "lods": {"0": 1, "1": 1}, "format": "f16"}
    });
    let done = status_of(&post(&server.client, "", body).await);
    assert_eq!(done.status, "done");
    let r = &done.report;
    assert!(r.finished && !r.cancelled);
    assert_eq!(
        (r.sent, r.ok, r.errors, r.unfinished),
        (40, 40, 0, 0),
        "{r:?}"
    );
    assert_eq!((r.lanes, r.heads_per_request), (4, 5));
    assert_eq!(r.latency_ms.count, 40);
    assert!((r.heads_per_s - 40.0 * 5.0 / 0.5).abs() < 1e-9, "{r:?}");
    // Two f16 jobs of the embedded head per response, at least.
    assert!(r.bytes_per_s >= 2.0 * (7_262 * 3 * 2) as f64 * 40.0 / 0.5);
    let t = r.server_ms.expect("the handler's Server-Timing was read");
    assert_eq!(
        (t.queue_ms.count, t.compute_ms.count, t.encode_ms.count),
        (40, 40, 40)
    );
    assert_eq!(done.request.crowd.heads, 5);

    // The same final report later.
    let again = status_of(&get(&server.client, &done.id).await);
    assert_eq!(again.report, done.report);

    // Synthetic traffic is labelled, and none of it counts as a client's.
    let page = server.client.metrics().await.expect("metrics");
    let m = |name: &str| metric(&page, name);
    assert_eq!(
        m("crowdmorph_heads_total{source=\"loadtest\"}"),
        Some(200.0),
        "{page}"
    );
    assert_eq!(m("crowdmorph_heads_total{source=\"api\"}"), Some(0.0));
    assert_eq!(
        m("crowdmorph_crowd_frames_total{source=\"loadtest\",status=\"200\"}"),
        Some(40.0)
    );
    assert_eq!(
        m("crowdmorph_crowd_frames_total{source=\"api\",status=\"200\"}"),
        None
    );
    assert_eq!(
        m("crowdmorph_http_requests_total{route=\"/v1/crowd/frame\",status=\"200\"}"),
        None,
        "no crowd frame came over HTTP"
    );
    assert!(m("crowdmorph_jobs_computed_total").unwrap() > 0.0);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_load_test_at_a_time_and_its_caps_are_400() {
    let server = TestServer::start(ServerConfig {
        loadtest_max_duration: Duration::from_secs(10),
        loadtest_max_rate: 500.0,
        loadtest_max_concurrency: 8,
        ..ServerConfig::default()
    })
    .await;
    let c = &server.client;
    let crowd = json!({"heads": 1});
    let started = post(
        c,
        "?wait=false",
        json!({"rate": 20, "duration_s": 2, "concurrency": 2, "crowd": crowd}),
    )
    .await;
    assert_eq!(started.status, 202);
    let running = status_of(&started);
    assert_eq!(running.status, "running");

    let second = post(
        c,
        "",
        json!({"rate": 20, "duration_s": 1, "concurrency": 1}),
    )
    .await;
    assert_eq!(code_of(&second), (409, "loadtest_running".into()));
    assert!(second.error().unwrap().error.message.contains(&running.id));
    // The second is refused before it is planned: its rigs are not even looked up.
    let unplanned = post(
        c,
        "",
        json!({"rate": 20, "duration_s": 1, "concurrency": 1, "crowd": {"rigs": ["nope"]}}),
    )
    .await;
    assert_eq!(code_of(&unplanned), (409, "loadtest_running".into()));

    // The first one finishes and its report is there; then the caps are checked, and
    // another may start.
    let done = wait_for(c, &running.id, |s| s.status != "running").await;
    assert_eq!(done.status, "done");
    assert_eq!(
        (done.report.sent, done.report.ok),
        (40, 40),
        "{:?}",
        done.report
    );
    let rigs = vec!["default-head"; 65];
    let clips: serde_json::Map<String, serde_json::Value> =
        (0..65).map(|i| (format!("c{i}"), json!(1))).collect();
    let lods: serde_json::Map<String, serde_json::Value> =
        (0..65).map(|i| (i.to_string(), json!(1))).collect();
    let refused = [
        (
            json!({"rate": 20, "duration_s": 9, "warmup_s": 2}),
            400,
            "loadtest_too_long",
        ),
        (
            json!({"rate": 501, "duration_s": 1}),
            400,
            "loadtest_rate_too_high",
        ),
        (json!({"rate": 0, "duration_s": 1}), 400, "invalid_loadtest"),
        (
            json!({"rate": 10, "duration_s": 1, "concurrency": 9}),
            400,
            "invalid_loadtest",
        ),
        (
            json!({"rate": 10, "duration_s": 1, "concurrency": 0}),
            400,
            "invalid_loadtest",
        ),
        (
            json!({"rate": 10, "duration_s": 1, "concurrency": 1, "crowd": {"unique": 2}}),
            400,
            "invalid_loadtest",
        ),
        (
            json!({"rate": 10, "duration_s": 1, "concurrency": 1, "crowd": {"clips": {"dance": 1}}}),
            400,
            "invalid_loadtest",
        ),
        (
            json!({"rate": 10, "duration_s": 1, "concurrency": 1, "crowd": {"rigs": ["nope"]}}),
            404,
            "unknown_rig",
        ),
        (
            json!({"rate": 10, "duration_s": 1, "speed": 3}),
            400,
            "malformed_json",
        ),
        (
            json!({"rate": 10, "duration_s": 1, "concurrency": 1, "crowd": {"heads": 100000000}}),
            400,
            "too_many_heads",
        ),
        // 8 lanes of 100,000 unique f32 heads would hold far more than half the queue memory.
        (
            json!({"rate": 10, "duration_s": 1, "concurrency": 8, "crowd": {"heads": 100000}}),
            400,
            "loadtest_too_large",
        ),
    ];
    for (body, status, code) in refused {
        let r = post(c, "", body.clone()).await;
        assert_eq!(code_of(&r), (status, code.to_string()), "{body}");
    }
    // Each list of the crowd is capped at 64 entries, and the refusal names the list and the
    // limit (a rig listed 65 times was planned, and its clip names copied, 65 times).
    for (list, value) in [
        ("rigs", json!(rigs)),
        ("clips", json!(clips)),
        ("lods", json!(lods)),
    ] {
        let mut crowd = serde_json::Map::new();
        crowd.insert(list.to_string(), value);
        let r = post(
            c,
            "",
            json!({"rate": 10, "duration_s": 1, "concurrency": 1, "crowd": crowd}),
        )
        .await;
        assert_eq!(code_of(&r), (400, "invalid_loadtest".into()), "{list}");
        let message = r.error().unwrap().error.message;
        assert!(
            message.contains(&format!("crowd.{list}")) && message.contains("at most 64"),
            "{message}"
        );
    }
    assert_eq!(
        code_of(&get(c, "999").await),
        (404, "unknown_loadtest".into())
    );
    let next = status_of(
        &post(
            c,
            "",
            json!({"rate": 20, "duration_s": 0.2, "concurrency": 2}),
        )
        .await,
    );
    assert_ne!(next.id, running.id);
    assert_eq!(next.report.ok, 4);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_load_test_needs_the_admin_token_when_there_is_one() {
    let server = TestServer::start(ServerConfig {
        admin_token: Some("secret".into()),
        ..ServerConfig::default()
    })
    .await;
    let body = json!({"rate": 20, "duration_s": 0.1, "crowd": {"heads": 1}});
    assert_eq!(
        code_of(&post(&server.client, "", body.clone()).await),
        (401, "token_required".into())
    );
    let wrong = server.client.clone().with_token("guess");
    assert_eq!(
        code_of(&post(&wrong, "", body.clone()).await),
        (401, "bad_token".into())
    );
    let admin = server.client.clone().with_token("secret");
    let done = status_of(&post(&admin, "", body).await);
    assert_eq!(done.report.ok, 2);
    assert_eq!(
        code_of(&get(&server.client, &done.id).await),
        (401, "token_required".into())
    );
    assert_eq!(status_of(&get(&admin, &done.id).await).id, done.id);
    server.stop().await;
}

/// A load test saturates the engine; client requests sent meanwhile are all answered, and each
/// goes ahead of the synthetic work queued before it: while a client request is answered, at
/// most the synthetic request computing when it arrived completes (plus what completes while
/// it travels to the batcher). Without the priority, every lane's queued request (15 here,
/// 3,000 batches) would complete first.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn client_requests_go_ahead_of_a_saturating_load_test() {
    let server = TestServer::start(ServerConfig {
        // One job per batch: a synthetic request of 200 unique heads takes 200 batches, and a
        // client's job goes in the first batch after it arrives.
        batch_cost: Some(1),
        ..ServerConfig::default()
    })
    .await;
    let lanes = 16;
    let started = post(
        &server.client,
        "?wait=false",
        json!({"rate": 5000, "duration_s": 30, "concurrency": lanes,
               "crowd": {"heads": 200, "clips": {"talk": 1}}}),
    )
    .await;
    let id = status_of(&started).id;
    let completed = || {
        let s = server.state.loadtest(&id).expect("the load test");
        s.report.ok + s.report.errors
    };
    // Saturated: every lane has had requests answered.
    wait_for(&server.client, &id, |s| s.report.ok >= 2 * lanes).await;
    let mut during = Vec::new();
    for k in 0..5 {
        let req = CrowdFrameRequest {
            heads: vec![Head {
                head: 1,
                rig: "default-head".into(),
                clip: "smile".into(),
                frame: k,
                lod: 0,
                ..Default::default()
            }],
            output: OutputOptions {
                normals: false,
                format: Format::F32,
            },
            wrap: true,
        };
        let before = completed();
        let (resp, _) = server
            .client
            .crowd_frame(&req, Encoding::Bincode)
            .await
            .expect("a client request is answered during the load test");
        during.push(completed() - before);
        assert_eq!(resp.buffers.len(), 1);
    }
    eprintln!("synthetic requests completed during each client request: {during:?}");
    let total: u64 = during.iter().sum();
    assert!(
        total <= 20,
        "synthetic requests completed while client requests were answered: {during:?}"
    );
    let s = server.state.loadtest(&id).expect("the load test");
    assert_eq!(s.status, "running", "the load was still saturating");
    let page = server.client.metrics().await.expect("metrics");
    assert_eq!(
        metric(
            &page,
            "crowdmorph_crowd_frames_total{source=\"api\",status=\"200\"}"
        ),
        Some(5.0)
    );
    assert_eq!(
        metric(&page, "crowdmorph_heads_total{source=\"api\"}"),
        Some(5.0)
    );
    // Shutdown stops the load test.
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_disabled_endpoint_is_403_and_an_oversized_body_413() {
    let server = TestServer::start(ServerConfig {
        loadtest_max_duration: Duration::ZERO,
        max_request_bytes: 4096,
        ..ServerConfig::default()
    })
    .await;
    let c = &server.client;
    let r = post(c, "", json!({"rate": 10, "duration_s": 1})).await;
    assert_eq!(code_of(&r), (403, "loadtest_disabled".into()));
    // The body is refused before it is parsed, whatever it asks for.
    let pad = "x".repeat(8192);
    let r = post(c, "", json!({"rate": 10, "duration_s": 1, "pad": pad})).await;
    assert_eq!(code_of(&r), (413, "body_too_large".into()));
    server.stop().await;
}

/// The shape of `crowd` as the server reads it from JSON, and the embedded rig as the load
/// generator sees it, so that a test can build the same bodies as the server.
fn bodies_of(crowd: &serde_json::Value) -> u64 {
    let shape: CrowdShape = serde_json::from_value(crowd.clone()).expect("a crowd shape");
    let rigs = [RigClips {
        id: "default-head".into(),
        clips: vec!["talk".into()],
        lod_levels: 1,
    }];
    shape
        .bodies(&rigs, 64)
        .expect("bodies")
        .iter()
        .map(|b| b.len() as u64)
        .sum()
}

/// The 64 synthetic request bodies are charged to the queue memory before they are built and
/// for as long as the load runs, and given back when it ends.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_load_test_holds_its_bodies_in_the_queue_memory_while_it_runs() {
    let server = TestServer::start(ServerConfig::default()).await;
    let crowd = json!({"heads": 2000, "unique": 0.0005, "clips": {"talk": 1}});
    let bodies = bodies_of(&crowd);
    assert!(bodies > 64 * 2000 * 20, "{bodies} bytes of bodies");
    // One request a second: between them, only the bodies are held.
    let started = post(
        &server.client,
        "?wait=false",
        json!({"rate": 1, "duration_s": 2, "concurrency": 1, "crowd": crowd}),
    )
    .await;
    let id = status_of(&started).id;
    let held = server.state.gauges().queue_memory_bytes;
    assert!(
        held >= bodies,
        "the running load holds {held} bytes of queue memory, less than its {bodies} bytes of \
         request bodies"
    );
    let done = wait_for(&server.client, &id, |s| s.status != "running").await;
    assert_eq!((done.report.ok, done.report.errors), (2, 0), "{done:?}");
    assert_eq!(
        server.state.gauges().queue_memory_bytes,
        0,
        "the bodies' memory is given back when the load ends"
    );
    server.stop().await;
}

/// What the lanes hold at once — each one's output and the decode reservation a request of its
/// body makes (the crowd-frame handler's own), plus the 64 bodies — must fit in half the queue
/// memory; counting only the outputs let a load of big bodies take what clients need.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_load_test_counts_its_bodies_and_decode_reservations_against_the_queue_memory() {
    // One unique f32 job of the embedded head: 87 KB of output per lane. The 2,000-head bincode
    // bodies are about 46 KB each (2.9 MB for 64), and a request of one reserves 16 × its body
    // (0.74 MB) while it is decoded.
    let crowd = json!({"heads": 2000, "unique": 0.0005, "clips": {"talk": 1}});
    let bodies = bodies_of(&crowd);
    assert!(bodies > (5 << 20) / 2 && bodies < 4 << 20, "{bodies}");
    // 8 lanes in 16 MB (half: 8 MB): outputs 0.7 MB and bodies 2.9 MB fit, the decode
    // reservations (5.9 MB) do not. 1 lane in 5 MB (half: 2.5 MB): the bodies alone do not.
    for (queue_memory_bytes, concurrency) in [(16 << 20, 8), (5 << 20, 1)] {
        let server = TestServer::start(ServerConfig {
            queue_memory_bytes,
            ..ServerConfig::default()
        })
        .await;
        let c = &server.client;
        let r = post(
            c,
            "",
            json!({"rate": 20, "duration_s": 0.1, "concurrency": concurrency, "crowd": crowd}),
        )
        .await;
        assert_eq!(
            code_of(&r),
            (400, "loadtest_too_large".into()),
            "{concurrency} lanes in {queue_memory_bytes} bytes"
        );
        let message = r.error().expect("an error body").error.message;
        assert!(
            message.contains("decod") && message.contains("bodies"),
            "{message}"
        );
        // A small load still runs on the same server, and gives its memory back.
        let done = status_of(
            &post(
                c,
                "",
                json!({"rate": 20, "duration_s": 0.1, "concurrency": concurrency,
                       "crowd": {"heads": 100, "unique": 0.05, "clips": {"talk": 1}}}),
            )
            .await,
        );
        assert_eq!((done.report.ok, done.report.errors), (2, 0), "{done:?}");
        assert_eq!(server.state.gauges().queue_memory_bytes, 0);
        server.stop().await;
    }
}

/// Synthetic bodies longer than `--max-request-bytes` would each be refused with 413: the load
/// is refused up front with 400 naming the limit, and nothing runs.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_load_whose_bodies_exceed_the_request_limit_is_400() {
    let server = TestServer::start(ServerConfig {
        max_request_bytes: 4096,
        ..ServerConfig::default()
    })
    .await;
    let c = &server.client;
    let crowd = json!({"heads": 1000, "clips": {"talk": 1}});
    assert!(bodies_of(&crowd) > 64 * 4096);
    let r = post(
        c,
        "",
        json!({"rate": 20, "duration_s": 0.1, "concurrency": 1, "crowd": crowd}),
    )
    .await;
    assert_eq!(code_of(&r), (400, "loadtest_too_large".into()));
    let message = r.error().expect("an error body").error.message;
    assert!(
        message.contains("--max-request-bytes") && message.contains("4096"),
        "{message}"
    );
    assert_eq!(server.state.gauges().queue_memory_bytes, 0);
    assert_eq!(
        code_of(&get(c, "1").await),
        (404, "unknown_loadtest".into()),
        "no load ran"
    );
    // Bodies within the limit run.
    let done = status_of(
        &post(
            c,
            "",
            json!({"rate": 20, "duration_s": 0.1, "concurrency": 1,
                   "crowd": {"heads": 10, "clips": {"talk": 1}}}),
        )
        .await,
    );
    assert_eq!((done.report.ok, done.report.errors), (2, 0), "{done:?}");
    server.stop().await;
}

/// `wait=true` (the default) for a load longer than the server lets a request run: the answer
/// comes before the timeout would cut the request with a 504, as 202 with the running status,
/// and the load goes on to finish (readable with GET).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn waiting_for_a_load_longer_than_the_timeout_answers_202_running() {
    let server = TestServer::start(ServerConfig {
        admin_timeout: Duration::from_secs(1),
        request_timeout: Duration::from_secs(1),
        ..ServerConfig::default()
    })
    .await;
    let c = &server.client;
    let r = post(
        c,
        "",
        json!({"rate": 4, "duration_s": 2.5, "concurrency": 1, "crowd": {"heads": 1}}),
    )
    .await;
    assert_eq!(r.status, 202, "{}", String::from_utf8_lossy(&r.body));
    let running = status_of(&r);
    assert_eq!(running.status, "running");
    let done = wait_for(c, &running.id, |s| s.status != "running").await;
    assert_eq!(done.status, "done");
    // Every request was sent and answered; with a 1 s request deadline on a busy machine an
    // answer may be a 504, which is not what this test is about.
    let r = &done.report;
    assert_eq!(
        (r.sent, r.ok + r.errors, r.unfinished),
        (10, 10, 0),
        "{done:?}"
    );
    assert!(r.ok > 0, "{done:?}");
    server.stop().await;
}
