//! Overload and shutdown: a full queue answers 503 with Retry-After, memory held by admitted
//! requests stays under its limit, late requests get 504, the server recovers, and a graceful
//! shutdown lets requests in flight complete.
//!
//! Long batch delays, held even while the engine is idle (`batch_hold_when_idle`), make
//! requests wait in the queue deterministically enough: the assertions are about what happens
//! when the queue is full, never about how long anything took.

use std::sync::Arc;
use std::time::Duration;

use crowdmorph::server::ServerConfig;
use crowdmorph_client::{Client, ClientError, Encoding, metric};
use crowdmorph_proto::{CrowdFrameRequest, Format, Head, OutputOptions};

use super::TestServer;

fn req(frames: &[i64]) -> CrowdFrameRequest {
    CrowdFrameRequest {
        heads: frames
            .iter()
            .enumerate()
            .map(|(h, &f)| Head {
                head: h as u64,
                rig: "default-head".into(),
                clip: "talk".into(),
                frame: f,
                lod: 0,
                ..Default::default()
            })
            .collect(),
        output: OutputOptions {
            normals: false,
            format: Format::F32,
        },
        wrap: true,
    }
}

/// Polls `f` every 20 ms for up to 20 s.
async fn eventually(mut f: impl FnMut() -> bool) -> bool {
    for _ in 0..1000 {
        if f() {
            return true;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    false
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_queue_answers_503_then_recovers() {
    let server = TestServer::start(ServerConfig {
        queue_requests: 4,
        batch_delay: Duration::from_secs(2),
        batch_hold_when_idle: true,
        batch_cost: Some(u64::MAX),
        ..ServerConfig::default()
    })
    .await;
    let mut tasks = Vec::new();
    for i in 0..40 {
        let c = server.client.clone();
        tasks.push(tokio::spawn(async move {
            c.crowd_frame_raw(
                Client::encode(&req(&[i]), Encoding::Bincode).unwrap(),
                Encoding::Bincode,
            )
            .await
            .unwrap()
        }));
    }
    // While they wait: never more than 4 requests in the batcher.
    let depth = &server.state.metrics.queue_depth;
    assert!(eventually(|| depth.get() == 4).await);
    let page = server.client.metrics().await.unwrap();
    assert!(metric(&page, "crowdmorph_queue_depth").unwrap() <= 4.0);
    let (mut ok, mut full) = (0, 0);
    for t in tasks {
        let r = t.await.unwrap();
        match r.status {
            200 => ok += 1,
            503 => {
                full += 1;
                assert_eq!(r.retry_after.as_deref(), Some("1"));
                assert_eq!(r.error().unwrap().error.code, "queue_full");
            }
            s => panic!("unexpected status {s}"),
        }
    }
    assert!(ok >= 4 && full > 0, "{ok} ok, {full} refused");
    assert_eq!(ok + full, 40);
    // Recovery: the queue is empty again and requests succeed.
    assert!(eventually(|| depth.get() == 0).await);
    let (resp, _) = server
        .client
        .crowd_frame(&req(&[1, 2]), Encoding::Bincode)
        .await
        .unwrap();
    assert_eq!(resp.buffers.len(), 2);
    let page = server.client.metrics().await.unwrap();
    assert!(metric(&page, "crowdmorph_rejected_total{reason=\"queue_full\"}").unwrap() > 0.0);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn output_memory_is_bounded_and_oversized_responses_are_413() {
    // One default-head f32 job is 7262 × 12 = 87,144 bytes: two fit in 200 KiB, three do not.
    let server = TestServer::start(ServerConfig {
        queue_memory_bytes: 200 << 10,
        batch_delay: Duration::from_secs(1),
        batch_hold_when_idle: true,
        batch_cost: Some(u64::MAX),
        ..ServerConfig::default()
    })
    .await;
    let e = server
        .client
        .crowd_frame(&req(&[1, 2, 3]), Encoding::Bincode)
        .await
        .unwrap_err();
    match e {
        ClientError::Api { status, code, .. } => {
            assert_eq!((status, code.as_str()), (413, "response_too_large"));
        }
        other => panic!("{other}"),
    }
    let mut tasks = Vec::new();
    for i in 0..6 {
        let c = server.client.clone();
        tasks.push(tokio::spawn(async move {
            c.crowd_frame(&req(&[i]), Encoding::Bincode).await
        }));
    }
    let limit = 200u64 << 10;
    let state = server.state.clone();
    assert!(eventually(|| state.gauges().queue_memory_bytes > 0).await);
    assert!(state.gauges().queue_memory_bytes <= limit);
    let mut refused = 0;
    for t in tasks {
        match t.await.unwrap() {
            Ok((r, _)) => assert_eq!(r.buffers.len(), 1),
            Err(ClientError::Api {
                status: 503, code, ..
            }) => {
                assert_eq!(code, "queue_full");
                refused += 1;
            }
            Err(e) => panic!("{e}"),
        }
    }
    assert!(refused > 0);
    // Everything sent: the memory is released.
    assert!(eventually(|| state.gauges().queue_memory_bytes == 0).await);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn past_the_deadline_is_504_and_abandoned_jobs_are_not_computed() {
    let server = TestServer::start(ServerConfig {
        request_timeout: Duration::from_millis(100),
        batch_delay: Duration::from_millis(600),
        batch_hold_when_idle: true,
        batch_cost: Some(u64::MAX),
        ..ServerConfig::default()
    })
    .await;
    let e = server
        .client
        .crowd_frame(&req(&[5]), Encoding::Json)
        .await
        .unwrap_err();
    match e {
        ClientError::Api { status, code, .. } => {
            assert_eq!((status, code.as_str()), (504, "deadline_exceeded"));
        }
        other => panic!("{other}"),
    }
    let m = server.state.metrics.clone();
    assert!(eventually(|| m.jobs_cancelled.get() == 1).await);
    assert_eq!(m.jobs_computed.get(), 0);
    assert!(eventually(|| m.queue_depth.get() == 0).await);
    let page = server.client.metrics().await.unwrap();
    assert_eq!(
        metric(
            &page,
            "crowdmorph_cancelled_total{work=\"frame\",reason=\"deadline\"}"
        ),
        Some(1.0),
        "the request stopped by its deadline is counted"
    );
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn too_many_requests_at_once_are_shed_with_503() {
    let server = TestServer::start(ServerConfig {
        max_concurrency: 2,
        // Long enough for all eight to arrive on a loaded machine while two are held.
        batch_delay: Duration::from_secs(3),
        batch_hold_when_idle: true,
        batch_cost: Some(u64::MAX),
        ..ServerConfig::default()
    })
    .await;
    let mut tasks = Vec::new();
    for i in 0..8 {
        let c = server.client.clone();
        tasks.push(tokio::spawn(async move {
            c.crowd_frame_raw(
                Client::encode(&req(&[i]), Encoding::Json).unwrap(),
                Encoding::Json,
            )
            .await
            .unwrap()
        }));
    }
    let mut shed = 0;
    for t in tasks {
        let r = t.await.unwrap();
        if r.status == 503 {
            assert_eq!(r.error().unwrap().error.code, "overloaded");
            assert!(r.retry_after.is_some());
            shed += 1;
        } else {
            assert_eq!(r.status, 200);
        }
    }
    assert!(shed > 0);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_lets_requests_in_flight_complete() {
    let mut server = TestServer::start(ServerConfig {
        // All ten must be queued before the batch closes, on a loaded machine too.
        batch_delay: Duration::from_secs(3),
        batch_hold_when_idle: true,
        batch_cost: Some(u64::MAX),
        ..ServerConfig::default()
    })
    .await;
    let rig = crowdmorph::embedded::default_rig();
    let expected = Arc::new(rig);
    let mut tasks = Vec::new();
    for i in 0..10 {
        let c = server.client.clone();
        tasks.push(tokio::spawn(async move {
            c.crowd_frame(&req(&[i, i + 1]), Encoding::Bincode).await
        }));
    }
    let m = server.state.metrics.clone();
    assert!(eventually(|| m.queue_depth.get() == 10).await);
    server.signal_stop();
    for t in tasks {
        let (resp, _) = t.await.unwrap().expect("in-flight request completes");
        assert_eq!(resp.buffers.len(), 2);
        assert_eq!(
            resp.buffers[0].positions.0.len(),
            expected.vertex_count() * 12
        );
    }
    let addr = server.addr;
    server.join().await;
    // Stopped: new connections are refused.
    assert!(tokio::net::TcpStream::connect(addr).await.is_err());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_that_disconnects_does_not_cancel_shared_work() {
    use tokio::io::AsyncWriteExt;
    let server = TestServer::start(ServerConfig {
        // A queues, B joins it and A hangs up, all before the batch closes.
        batch_delay: Duration::from_secs(3),
        batch_hold_when_idle: true,
        batch_cost: Some(u64::MAX),
        ..ServerConfig::default()
    })
    .await;
    let m = server.state.metrics.clone();
    // A asks for frame 5 over a raw connection, so that the test decides when it goes away.
    let body = serde_json::to_vec(&req(&[5])).unwrap();
    let mut a = tokio::net::TcpStream::connect(server.addr).await.unwrap();
    let head = format!(
        "POST /v1/crowd/frame HTTP/1.1\r\nhost: test\r\ncontent-type: application/json\r\n\
         content-length: {}\r\n\r\n",
        body.len()
    );
    a.write_all(head.as_bytes()).await.unwrap();
    a.write_all(&body).await.unwrap();
    assert!(eventually(|| m.queue_depth.get() == 1).await);
    // B asks for frames 5 and 6: frame 5 joins A's queued job.
    let c = server.client.clone();
    let b = tokio::spawn(async move { c.crowd_frame(&req(&[5, 6]), Encoding::Bincode).await });
    assert!(eventually(|| m.jobs_coalesced.get() == 1).await);
    // A hangs up before the batch closes.
    drop(a);
    let (resp, _) = b.await.unwrap().expect("B is answered");
    let frames: Vec<u32> = resp.buffers.iter().map(|b| b.frame).collect();
    assert_eq!(frames, vec![5, 6]);
    assert_eq!(m.jobs_cancelled.get(), 0, "shared work kept");
    assert_eq!(m.jobs_computed.get(), 2);
    // A was really gone: only B's request was answered, and A's counted as cancelled.
    let text = server.client.metrics().await.unwrap();
    assert_eq!(
        metric(
            &text,
            "crowdmorph_cancelled_total{work=\"frame\",reason=\"dropped\"}"
        ),
        Some(1.0)
    );
    let answered: f64 = text
        .lines()
        .filter(|l| l.starts_with("crowdmorph_http_requests_total{route=\"/v1/crowd/frame\""))
        .filter_map(|l| l.rsplit(' ').next()?.parse::<f64>().ok())
        .sum();
    assert_eq!(answered, 1.0, "{text}");
    server.stop().await;
}

/// Serves `fits` and refuses `refused` with 413 `response_too_large`: the queue memory holds
/// the first request's output but not the second's.
async fn serves_then_refuses_as_too_large(
    server: &TestServer,
    fits: CrowdFrameRequest,
    refused: CrowdFrameRequest,
) {
    let (resp, _) = server
        .client
        .crowd_frame(&fits, Encoding::Bincode)
        .await
        .expect("the first request fits");
    let unique: std::collections::HashSet<_> = fits
        .heads
        .iter()
        .map(|h| (&h.rig, &h.clip, h.frame, h.lod))
        .collect();
    assert_eq!(resp.buffers.len(), unique.len());
    super::api_error(
        server.client.crowd_frame(&refused, Encoding::Bincode).await,
        413,
        "response_too_large",
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sixteen_bit_normals_that_are_recomputed_are_charged_for_the_f32_blend_before_them() {
    // The default head's normals are recomputed from the blended positions, which the CPU
    // engine blends in f32 before it encodes f16: one job with normals holds 7262 × 3 × 2 × 2
    // = 87,144 bytes of f16 and 174,288 bytes of f32 on the way. 128 KiB holds the first only.
    let rig = crowdmorph::embedded::default_rig();
    assert!(
        rig.recomputes_normals(),
        "the test needs a rig whose normals are recomputed"
    );
    let server = TestServer::start(ServerConfig {
        queue_memory_bytes: 128 << 10,
        ..ServerConfig::default()
    })
    .await;
    let mut positions = req(&[1]);
    positions.output.format = Format::F16;
    let mut with_normals = positions.clone();
    with_normals.output.normals = true;
    serves_then_refuses_as_too_large(&server, positions, with_normals).await;
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn q16_on_the_gpu_engine_is_charged_for_the_f32_it_reads_back() {
    // The GPU engine reads q16 jobs back as f32 and quantizes them on the host: one default-head
    // job holds 7262 × 3 × 2 = 43,572 bytes of q16 and 87,144 of f32 beside it. 100 KiB holds
    // the first only; f16, which the GPU packs itself, still fits.
    let server = TestServer::start(ServerConfig {
        queue_memory_bytes: 100 << 10,
        backend: crowdmorph::engine::BackendChoice::Gpu,
        ..ServerConfig::default()
    })
    .await;
    assert!(
        server.state.engine.gpu_memory().is_some(),
        "the GPU engine (lavapipe)"
    );
    let mut f16 = req(&[1]);
    f16.output.format = Format::F16;
    let mut q16 = f16.clone();
    q16.output.format = Format::Q16;
    serves_then_refuses_as_too_large(&server, f16, q16).await;
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_rig_of_many_targets_and_few_vertices_is_charged_for_its_jobs_weights() {
    // A triangle with 1,024 targets: a job's f32 output is 36 bytes, but the batch gathers
    // 1,024 weights per job (and the CPU kernel regroups them): about 9 KiB. 64 unique jobs
    // fit in 1 MiB of queue memory, 256 do not, though their outputs are 9 KiB in all.
    use crate::util::builder::{Builder, TRIANGLE};
    const TARGETS: usize = 1024;
    let targets: Vec<Vec<[f32; 3]>> = (0..TARGETS)
        .map(|t| vec![[0.0; 3], [0.0, 0.0, 1e-3 * (t + 1) as f32], [0.0; 3]])
        .collect();
    let mut b = Builder::new();
    let mesh = b.mesh_with_targets(&TRIANGLE, Some(&[0, 1, 2]), &targets, None);
    let node = b.node(Some(mesh));
    b.scene(&[node]);
    // Two keys ten seconds apart: 301 frames at 30 fps, every weight moving.
    let values: Vec<f32> = (0..2 * TARGETS).map(|i| (i % 7) as f32 / 7.0).collect();
    b.animation_weights("sweep", node, &[0.0, 10.0], &values, "LINEAR");
    let server = TestServer::start(ServerConfig {
        queue_memory_bytes: 1 << 20,
        ..ServerConfig::default()
    })
    .await;
    server
        .client
        .upload_rig("many", b.to_glb().into())
        .await
        .expect("upload");
    let crowd = |n: i64| CrowdFrameRequest {
        heads: (0..n)
            .map(|f| Head {
                head: f as u64,
                rig: "many".into(),
                clip: "sweep".into(),
                frame: f,
                lod: 0,
                ..Default::default()
            })
            .collect(),
        ..req(&[])
    };
    serves_then_refuses_as_too_large(&server, crowd(64), crowd(256)).await;
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_mesh_larger_than_the_whole_queue_memory_is_413_not_all_of_it() {
    // The default head's mesh response copies 7,262 positions and normals and 14,512
    // triangles (≈ 349 KB, twice that while it is encoded): more than 256 KiB of queue memory
    // can ever hold. It used to take the whole queue and allocate past it.
    let server = TestServer::start(ServerConfig {
        queue_memory_bytes: 256 << 10,
        ..ServerConfig::default()
    })
    .await;
    let message = super::api_error(
        server.client.mesh("default-head", Encoding::Bincode).await,
        413,
        "queue_memory_exceeded",
    );
    assert!(message.contains("--queue-memory-bytes"), "{message}");
    // The server answers what fits afterwards: nothing stayed reserved.
    let (resp, _) = server
        .client
        .crowd_frame(&req(&[1]), Encoding::Bincode)
        .await
        .expect("a crowd frame fits");
    assert_eq!(resp.buffers.len(), 1);
    // The response's charge is given back once its body has gone out, which may be a moment
    // after the client has read it.
    assert!(
        eventually(|| server.state.gauges().queue_memory_bytes == 0).await,
        "everything given back"
    );
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_crowds_heads_are_charged_until_its_response_is_sent() {
    // 1,000 clones of one head need one 87 KB blend, but their decoded heads, names, plan
    // and response entries (≈ 240 bytes each) stay alive until the response is sent: with
    // the blend they are more than 256 KiB of queue memory (the heads alone are not: 1,100
    // were, once `Head` gained its `mapping`). They used to be charged only while the body was
    // decoded. 100 clones fit.
    let server = TestServer::start(ServerConfig {
        queue_memory_bytes: 256 << 10,
        ..ServerConfig::default()
    })
    .await;
    let clones = |n: usize| req(&vec![3; n]);
    serves_then_refuses_as_too_large(&server, clones(100), clones(1_000)).await;
    assert!(
        eventually(|| server.state.gauges().queue_memory_bytes == 0).await,
        "everything given back"
    );
    server.stop().await;
}
