//! 200 concurrent clients with overlapping crowds: every response is exactly the CPU engine's
//! output for its own heads, and the metrics show jobs shared across requests.

use std::sync::Arc;
use std::time::Duration;

use crowdmorph::engine::cpu::CpuRig;
use crowdmorph::engine::{BlendJob, OutputSpec, WeightBatch};
use crowdmorph::server::ServerConfig;
use crowdmorph_client::{Encoding, metric};
use crowdmorph_proto::{CrowdFrameRequest, Format, Head, OutputOptions};

use super::TestServer;
use crate::util::Rng;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_hundred_clients_get_their_own_correct_frames_and_jobs_coalesce() {
    // A long batch delay, held even while the engine is idle, makes the requests meet in the
    // queue, so that identical jobs of different requests are waiting together (correctness
    // does not depend on it).
    let server = TestServer::start(ServerConfig {
        batch_delay: Duration::from_millis(150),
        batch_hold_when_idle: true,
        ..ServerConfig::default()
    })
    .await;
    let rig = crowdmorph::embedded::default_rig();
    // The pool of jobs: 12 (clip, frame, lod) triples over every clip.
    let mut rng = Rng(42);
    let pool: Vec<(usize, u32, u32)> = (0..12)
        .map(|_| {
            let c = rng.below(rig.clips.len());
            let f = rng.below(rig.clips[c].frames as usize) as u32;
            let l = rng.below(rig.lod.levels.len()) as u32;
            (c, f, l)
        })
        .collect();
    let cpu = CpuRig::new(&rig);
    let jobs: Vec<BlendJob> = pool
        .iter()
        .map(|&(c, f, l)| BlendJob::frame(c as u32, f, l))
        .collect();
    let out = cpu
        .evaluate(
            &WeightBatch::gather(&rig, &jobs).unwrap(),
            OutputSpec::default(),
        )
        .unwrap();
    let expected: Arc<Vec<Vec<u8>>> = Arc::new(
        (0..pool.len())
            .map(|j| {
                out.job_positions(j)
                    .iter()
                    .flat_map(|x| x.to_le_bytes())
                    .collect()
            })
            .collect(),
    );
    let clip_names: Arc<Vec<String>> = Arc::new(rig.clips.iter().map(|c| c.name.clone()).collect());
    let clip_frames: Arc<Vec<i64>> =
        Arc::new(rig.clips.iter().map(|c| i64::from(c.frames)).collect());

    let clients = 200;
    let heads_each = 10;
    let barrier = Arc::new(tokio::sync::Barrier::new(clients));
    let mut tasks = Vec::new();
    for i in 0..clients {
        let client = server.client.clone();
        let barrier = barrier.clone();
        let expected = expected.clone();
        let pool = pool.clone();
        let clip_names = clip_names.clone();
        let clip_frames = clip_frames.clone();
        tasks.push(tokio::spawn(async move {
            let mut rng = Rng(1000 + i as u64);
            let picks: Vec<usize> = (0..heads_each).map(|_| rng.below(pool.len())).collect();
            let req = CrowdFrameRequest {
                heads: picks
                    .iter()
                    .enumerate()
                    .map(|(h, &p)| Head {
                        head: (i * 1000 + h) as u64,
                        rig: "default-head".into(),
                        clip: clip_names[pool[p].0].clone(),
                        // Some heads name the frame past the end: it wraps to the same job.
                        frame: i64::from(pool[p].1)
                            + if h % 3 == 1 {
                                clip_frames[pool[p].0]
                            } else {
                                0
                            },
                        lod: pool[p].2,
                        ..Default::default()
                    })
                    .collect(),
                output: OutputOptions {
                    normals: false,
                    format: Format::F32,
                },
                wrap: true,
            };
            barrier.wait().await;
            let enc = if i % 4 == 0 {
                Encoding::Json
            } else {
                Encoding::Bincode
            };
            let (resp, _) = client.crowd_frame(&req, enc).await.unwrap();
            assert_eq!(resp.heads.len(), heads_each);
            for (h, (hb, &p)) in resp.heads.iter().zip(&picks).enumerate() {
                assert_eq!(hb.head, (i * 1000 + h) as u64, "client {i}: head order");
                let b = &resp.buffers[hb.buffer as usize];
                assert_eq!(b.clip, clip_names[pool[p].0]);
                assert_eq!((b.frame, b.lod), (pool[p].1, pool[p].2));
                assert!(
                    b.positions.0 == expected[p],
                    "client {i} head {h}: vertices differ from the engine's"
                );
            }
        }));
    }
    for t in tasks {
        t.await.unwrap();
    }
    let page = server.client.metrics().await.unwrap();
    let requested = metric(&page, "crowdmorph_jobs_requested_total").unwrap();
    let computed = metric(&page, "crowdmorph_jobs_computed_total").unwrap();
    let coalesced = metric(&page, "crowdmorph_jobs_coalesced_total").unwrap();
    // The client's series: the family's series come in no fixed order.
    let heads = metric(&page, "crowdmorph_heads_total{source=\"api\"}").unwrap();
    assert_eq!(heads, (clients * heads_each) as f64);
    assert!(
        coalesced > 0.0,
        "no job was shared across requests:\n{page}"
    );
    assert!(computed < requested, "computed {computed} of {requested}");
    assert!(metric(&page, "crowdmorph_unique_job_ratio").unwrap() < 1.0);
    // One rig, one output kind, no simplified meshes: one engine call per batch.
    let batches = metric(&page, "crowdmorph_batches_total").unwrap();
    let dispatches = metric(&page, "crowdmorph_engine_dispatches_total").unwrap();
    assert!(batches >= 1.0);
    assert_eq!(dispatches, batches, "one dispatch per rig per batch");
    assert!(
        metric(
            &page,
            "crowdmorph_http_requests_total{route=\"/v1/crowd/frame\",status=\"200\"}"
        )
        .unwrap()
            >= clients as f64
    );
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_f32_and_a_q16_request_for_one_frame_share_a_batch_and_each_gets_its_format() {
    // Both requests wait in one batch; the engine writes each wire format in its kernel's
    // output stage (no second pass over an f32 buffer), so the batch has one engine call per
    // format, and both answers are the same blend.
    let server = TestServer::start(ServerConfig {
        batch_delay: Duration::from_millis(300),
        batch_hold_when_idle: true,
        ..ServerConfig::default()
    })
    .await;
    let request = |format: Format| CrowdFrameRequest {
        heads: vec![Head {
            head: 1,
            rig: "default-head".into(),
            clip: "talk".into(),
            frame: 17,
            lod: 0,
            ..Default::default()
        }],
        output: OutputOptions {
            normals: false,
            format,
        },
        wrap: true,
    };
    let (f32_req, q16_req) = (request(Format::F32), request(Format::Q16));
    let (a, b) = tokio::join!(
        server.client.crowd_frame(&f32_req, Encoding::Bincode),
        server.client.crowd_frame(&q16_req, Encoding::Bincode),
    );
    let (a, _) = a.expect("f32 frame");
    let (b, _) = b.expect("q16 frame");
    let page = server.client.metrics().await.expect("metrics");
    assert_eq!(
        metric(&page, "crowdmorph_batches_total"),
        Some(1.0),
        "one batch"
    );
    assert_eq!(
        metric(&page, "crowdmorph_engine_dispatches_total"),
        Some(2.0),
        "one engine call per wire format"
    );
    assert_eq!(
        metric(&page, "crowdmorph_jobs_computed_total"),
        Some(2.0),
        "the frame once in each format"
    );
    // And both answers are that blend: q16 within its stated error of the f32 one.
    let f = super::positions_f32(Format::F32, &a.buffers[0]);
    let q = super::positions_f32(Format::Q16, &b.buffers[0]);
    let err = b.buffers[0].quantization.expect("box").max_error;
    for (i, (x, y)) in f.iter().zip(&q).enumerate() {
        assert!(
            (x - y).abs() <= err[i % 3] * 1.0001,
            "component {i}: {x} vs {y}"
        );
    }
    server.stop().await;
}
