//! The API end to end: every real rig uploaded, framed in every format and encoding, and
//! compared with the f64 oracle; meshes; clips; the admin token; CORS.
//!
//! Tolerances (relative to the rig's bounding-box diagonal `d`): f32 positions 1e-5·d; f16
//! positions 1e-5·d plus `max |coordinate| × 2^-11`; q16 positions 1e-5·d plus the response's
//! stated `max_error` per axis. Normals are unit vectors: 2e-3 in f32 (recomputed normals
//! come from blended f32 positions), plus 2^-11 in f16 and 1/65534 in q16.

use crate::util::gpu_test;
use std::collections::HashMap;

use bytes::Bytes;
use crowdmorph::import::{ImportOptions, clip_from_json, load_path};
use crowdmorph::rig::Rig;
use crowdmorph::server::ServerConfig;
use crowdmorph_client::Method;
use crowdmorph_client::{ClientError, Encoding};
use crowdmorph_proto::{CrowdFrameRequest, Format, Head, OutputOptions};
use glam::DVec3;

use super::{TestServer, normals_f32, positions_f32, random_clip_json, upload_bytes};
use crate::util::{effective_weights, rig_files, rig_oracle};

/// A crowd over every clip of `rig`: first, second, last and a wrapped frame, LOD 0 and the
/// last level, and clones of the first heads.
fn crowd(rig_id: &str, rig: &Rig, format: Format, normals: bool) -> CrowdFrameRequest {
    let mut heads = Vec::new();
    let last_lod = rig.lod.levels.len() as u32 - 1;
    for c in &rig.clips {
        let n = i64::from(c.frames);
        for frame in [0, 1.min(n - 1), n - 1, n + 3] {
            for lod in [0, last_lod] {
                heads.push(Head {
                    head: heads.len() as u64 * 10 + 3,
                    rig: rig_id.to_string(),
                    clip: c.name.clone(),
                    frame,
                    lod,
                    ..Default::default()
                });
            }
        }
    }
    let clones: Vec<Head> = heads.iter().take(5).cloned().collect();
    for mut h in clones {
        h.head += 1_000_000;
        heads.push(h);
    }
    CrowdFrameRequest {
        heads,
        output: OutputOptions { normals, format },
        wrap: true,
    }
}

fn max_diff(got: &[f32], want: &[DVec3]) -> [f64; 3] {
    assert_eq!(got.len(), want.len() * 3, "buffer length");
    let mut m = [0f64; 3];
    for (g, w) in got.chunks_exact(3).zip(want) {
        for a in 0..3 {
            m[a] = m[a].max((f64::from(g[a]) - w[a]).abs());
        }
    }
    m
}

/// Checks a response against the oracle of `rig` (the same rig the server holds).
fn check(rig: &Rig, req: &CrowdFrameRequest, resp: &crowdmorph_proto::CrowdFrameResponse) {
    let format = req.output.format;
    assert_eq!(resp.format, format);
    assert_eq!(resp.heads.len(), req.heads.len());
    let diag = f64::from(rig.bbox().diagonal()).max(1e-9);
    let max_coord = rig
        .primitives
        .iter()
        .flat_map(|p| p.positions.iter())
        .map(|v| f64::from(v.abs().max_element()))
        .fold(0.0, f64::max);
    // Every head points at a buffer with its clip, resolved frame and LOD.
    for (h, hb) in req.heads.iter().zip(&resp.heads) {
        assert_eq!(hb.head, h.head, "head ids echoed in request order");
        let b = &resp.buffers[hb.buffer as usize];
        let clip = &rig.clips[rig.clip_index(&h.clip).unwrap()];
        assert_eq!(b.clip, h.clip);
        assert_eq!(
            i64::from(b.frame),
            h.frame.rem_euclid(i64::from(clip.frames))
        );
        assert_eq!(b.lod, h.lod);
    }
    // Clones share: no two buffers have the same job.
    let mut seen = HashMap::new();
    for (i, b) in resp.buffers.iter().enumerate() {
        assert!(
            seen.insert((b.clip.clone(), b.frame, b.lod), i).is_none(),
            "buffer {i} duplicates another"
        );
    }
    for b in &resp.buffers {
        let clip = &rig.clips[rig.clip_index(&b.clip).unwrap()];
        let w: Vec<f64> = (0..rig.targets.len())
            .map(|t| f64::from(clip.weight(t, b.frame)))
            .collect();
        let (pos, nrm) = rig_oracle(rig, &effective_weights(rig, &w, b.lod));
        let got = positions_f32(format, b);
        let d = max_diff(&got, &pos);
        for (a, &off) in d.iter().enumerate() {
            let tol = 1e-5 * diag
                + match format {
                    Format::F32 => 0.0,
                    Format::F16 => max_coord / 2048.0,
                    Format::Q16 | Format::Q16R => f64::from(b.quantization.unwrap().max_error[a]),
                    Format::Weights => unreachable!("asked for vertices"),
                };
            assert!(
                off <= tol,
                "{} {} frame {} lod {} {format:?}: axis {a} off by {off} > {tol}",
                rig.name,
                b.clip,
                b.frame,
                b.lod,
            );
        }
        assert_eq!(b.quantization.is_some(), format == Format::Q16);
        match normals_f32(format, b) {
            Some(n) => {
                assert!(req.output.normals);
                let tol = 2e-3
                    + match format {
                        Format::F32 => 0.0,
                        Format::F16 => 1.0 / 2048.0,
                        Format::Q16 | Format::Q16R => {
                            f64::from(crowdmorph_proto::Q16_NORMAL_MAX_ERROR)
                        }
                        Format::Weights => unreachable!("asked for vertices"),
                    };
                let dn = max_diff(&n, &nrm);
                assert!(
                    dn.iter().all(|&x| x <= tol),
                    "{} {} normals off by {dn:?}",
                    rig.name,
                    b.clip
                );
            }
            None => assert!(!req.output.normals),
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
async fn every_real_rig_uploads_and_frames_match_the_oracle() {
    let files = rig_files();
    let server = TestServer::start(ServerConfig::default()).await;
    let client = &server.client;
    for path in files {
        let stem = path.file_stem().unwrap().to_string_lossy().into_owned();
        let mut rig = load_path(&path, &ImportOptions::default()).unwrap();
        let info = client.upload_rig(&stem, upload_bytes(&path)).await.unwrap();
        assert_eq!(info.id, stem);
        assert_eq!(info.vertices as usize, rig.vertex_count());
        assert_eq!(info.targets, rig.targets);
        assert_eq!(info.clips.len(), rig.clips.len());
        assert!(info.memory.host_bytes > 0);
        if rig.clips.is_empty() {
            // Rigs without animation get a clip, uploaded and applied locally alike.
            let json = random_clip_json(&rig.targets, 6, 7);
            let up = client
                .upload_clip(
                    &stem,
                    "name=rnd",
                    "application/json",
                    Bytes::from(json.clone()),
                )
                .await
                .unwrap();
            assert_eq!(up.added.len(), 1);
            assert!(up.ignored.is_empty());
            let local = clip_from_json(&rig, "rnd", json.as_bytes(), &Default::default()).unwrap();
            rig.clips.push(local.clip);
        }
        for (format, normals, enc) in [
            (Format::F32, true, Encoding::Bincode),
            (Format::F16, false, Encoding::Bincode),
            (Format::Q16, true, Encoding::Bincode),
            (Format::F32, false, Encoding::Json),
            (Format::Q16, false, Encoding::Json),
        ] {
            let req = crowd(&stem, &rig, format, normals);
            let (resp, _) = client.crowd_frame(&req, enc).await.unwrap();
            check(&rig, &req, &resp);
        }
    }
    // Every rig is listed once, the built-in one included.
    let list = client.rigs().await.unwrap();
    assert_eq!(list.rigs.len(), 7);
    assert!(
        list.rigs
            .iter()
            .any(|r| r.id == "default-head" && r.builtin)
    );
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_builtin_rig_frames_match_the_oracle_without_any_files() {
    let server = TestServer::start(ServerConfig::default()).await;
    let rig = crowdmorph::embedded::default_rig();
    for (format, normals) in [
        (Format::F32, true),
        (Format::Q16, false),
        (Format::F16, true),
    ] {
        let req = crowd("default-head", &rig, format, normals);
        let (resp, _) = server
            .client
            .crowd_frame(&req, Encoding::Bincode)
            .await
            .unwrap();
        check(&rig, &req, &resp);
        assert!(resp.timings.total_us >= resp.timings.queue_us);
    }
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mesh_is_the_neutral_rig_in_both_encodings() {
    let server = TestServer::start(ServerConfig::default()).await;
    let rig = crowdmorph::embedded::default_rig();
    for enc in [Encoding::Json, Encoding::Bincode] {
        let mesh = server.client.mesh("default-head", enc).await.unwrap();
        assert_eq!(mesh.vertices as usize, rig.vertex_count());
        let pos = mesh.positions.to_f32();
        let want: Vec<f32> = rig
            .primitives
            .iter()
            .flat_map(|p| p.positions.iter().flat_map(|v| v.to_array()))
            .collect();
        assert_eq!(pos, want);
        assert_eq!(mesh.normals.to_f32().len(), want.len());
        let idx = mesh.indices.to_u32();
        assert_eq!(idx.len(), rig.triangle_count() * 3);
        // Indices address the concatenated vertex space, per primitive range.
        for (p, mp) in rig.primitives.iter().zip(&mesh.primitives) {
            let s = mp.first_index as usize;
            for (k, &i) in p.indices.iter().enumerate() {
                assert_eq!(idx[s + k], i + mp.first_vertex);
            }
        }
        let bbox = rig.bbox();
        assert_eq!(mesh.bbox.min, bbox.min.to_array());
        for a in 0..3 {
            assert!(mesh.quantization.min[a] <= bbox.min[a]);
        }
    }
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn clips_upload_list_get_delete_and_report_unknown_targets() {
    let server = TestServer::start(ServerConfig::default()).await;
    let c = &server.client;
    let csv = "Timecode,BlendShapeCount,JawOpen,EyeBlinkLeft,HeadYaw,Wrinkle\n\
               00:00:00:00,3,0.1,0.2,0.5,1\n00:00:00:01,3,0.4,0.9,0.1,1\n";
    // Unknown names are an error that names them (Live Link's head angle is not one: a rig
    // without a head joint cannot show it, and every Live Link file has it)...
    let err = c
        .upload_clip("default-head", "name=capture", "text/csv", Bytes::from(csv))
        .await
        .unwrap_err();
    match err {
        ClientError::Api {
            status,
            code,
            message,
        } => {
            assert_eq!(status, 400);
            assert_eq!(code, "unknown_targets");
            assert!(message.contains("Wrinkle"), "{message}");
            assert!(!message.contains("HeadYaw"), "{message}");
        }
        other => panic!("unexpected {other}"),
    }
    // ...or, when allowed, reported.
    let up = c
        .upload_clip(
            "default-head",
            "name=capture&ignore_unknown=true&fps=60",
            "text/csv",
            Bytes::from(csv),
        )
        .await
        .unwrap();
    assert_eq!(up.ignored, ["Wrinkle", "HeadYaw"]);
    assert_eq!(up.added[0].frames, 2);
    assert_eq!(up.added[0].fps, 60.0);
    let list = c.clips("default-head").await.unwrap();
    assert!(list.clips.iter().any(|k| k.name == "capture"));
    // The clip plays: frame 1 has jawOpen 0.4 and the blink at 0.9.
    let req = CrowdFrameRequest {
        heads: vec![Head {
            head: 1,
            rig: "default-head".into(),
            clip: "capture".into(),
            frame: 1,
            lod: 0,
            ..Default::default()
        }],
        output: OutputOptions::default(),
        wrap: false,
    };
    let (resp, _) = c.crowd_frame(&req, Encoding::Bincode).await.unwrap();
    let rig = crowdmorph::embedded::default_rig();
    let mut w = vec![0.0; rig.targets.len()];
    w[rig.target_id("jawOpen").unwrap() as usize] = 0.4;
    w[rig.target_id("eyeBlink_L").unwrap() as usize] = 0.9;
    let (pos, _) = rig_oracle(&rig, &w);
    let d = max_diff(&positions_f32(Format::F32, &resp.buffers[0]), &pos);
    assert!(
        d.iter()
            .all(|&x| x < 1e-5 * f64::from(rig.bbox().diagonal()))
    );
    // A duplicate name conflicts; built-in clips stay; uploaded ones go.
    let dup = c
        .upload_clip(
            "default-head",
            "name=capture&ignore_unknown=true",
            "text/csv",
            Bytes::from(csv),
        )
        .await
        .unwrap_err();
    assert!(matches!(dup, ClientError::Api { status: 409, .. }), "{dup}");
    let r = c
        .send(
            Method::DELETE,
            "/v1/rigs/default-head/clips/talk",
            None,
            None,
            Bytes::new(),
        )
        .await
        .unwrap();
    assert_eq!(r.status, 403);
    let r = c
        .send(
            Method::GET,
            "/v1/rigs/default-head/clips/capture",
            None,
            None,
            Bytes::new(),
        )
        .await
        .unwrap();
    assert_eq!(r.status, 200);
    let r = c
        .send(
            Method::DELETE,
            "/v1/rigs/default-head/clips/capture",
            None,
            None,
            Bytes::new(),
        )
        .await
        .unwrap();
    assert_eq!(r.status, 204);
    let r = c
        .send(
            Method::GET,
            "/v1/rigs/default-head/clips/capture",
            None,
            None,
            Bytes::new(),
        )
        .await
        .unwrap();
    assert_eq!(r.status, 404);
    assert_eq!(r.error().unwrap().error.code, "unknown_clip");
    // The built-in rig itself cannot be deleted.
    let r = c
        .send(
            Method::DELETE,
            "/v1/rigs/default-head",
            None,
            None,
            Bytes::new(),
        )
        .await
        .unwrap();
    assert_eq!(r.status, 403);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn uploads_and_deletes_need_the_admin_token_when_set() {
    let server = TestServer::start(ServerConfig {
        admin_token: Some("s3cret".into()),
        cors_origins: vec!["https://viewer.example".into()],
        ..ServerConfig::default()
    })
    .await;
    let glb = Bytes::from(crate::util::builder::triangle_rig().to_glb());
    for client in [
        server.client.clone(),
        server.client.clone().with_token("wrong"),
    ] {
        let e = client.upload_rig("tri", glb.clone()).await.unwrap_err();
        assert!(matches!(e, ClientError::Api { status: 401, .. }), "{e}");
    }
    let admin = server.client.clone().with_token("s3cret");
    let info = admin.upload_rig("tri", glb.clone()).await.unwrap();
    assert_eq!(info.vertices, 3);
    // Reading needs no token; deleting does.
    assert_eq!(server.client.rig("tri").await.unwrap().id, "tri");
    assert!(server.client.delete_rig("tri").await.is_err());
    admin.delete_rig("tri").await.unwrap();
    assert!(server.client.rig("tri").await.is_err());
    // CORS preflight for the viewer's origin; every response carries a request id.
    let r = reqwest_like_preflight(&server).await;
    assert_eq!(
        r.get("access-control-allow-origin").map(String::as_str),
        Some("https://viewer.example")
    );
    let reply = server
        .client
        .send(Method::GET, "/healthz", None, None, Bytes::new())
        .await
        .unwrap();
    assert!(reply.request_id.is_some());
    server.stop().await;
}

/// Sends a CORS preflight with a raw socket and returns the response headers (lowercased).
async fn reqwest_like_preflight(server: &TestServer) -> HashMap<String, String> {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut s = tokio::net::TcpStream::connect(server.addr).await.unwrap();
    let req = "OPTIONS /v1/crowd/frame HTTP/1.1\r\nHost: x\r\nOrigin: https://viewer.example\r\n\
               Access-Control-Request-Method: POST\r\nConnection: close\r\n\r\n";
    s.write_all(req.as_bytes()).await.unwrap();
    let mut out = String::new();
    s.read_to_string(&mut out).await.unwrap();
    out.lines()
        .skip(1)
        .take_while(|l| !l.is_empty())
        .filter_map(|l| l.split_once(':'))
        .map(|(k, v)| (k.trim().to_ascii_lowercase(), v.trim().to_string()))
        .collect()
}

/// Asks for the same crowd in q16 and in q16r and decodes the residuals against the reference
/// the client fetches: the q16 values, bit for bit, head by head.
async fn q16r_decodes_to_q16(client: &crowdmorph_client::Client, rig: &Rig) {
    let (plain, _) = client
        .crowd_frame(
            &crowd("default-head", rig, Format::Q16, true),
            Encoding::Bincode,
        )
        .await
        .expect("q16");
    let (coded, _) = client
        .crowd_frame(
            &crowd("default-head", rig, Format::Q16R, true),
            Encoding::Bincode,
        )
        .await
        .expect("q16r");
    assert_eq!(coded.format, Format::Q16R);
    let mut refs = HashMap::new();
    for (a, b) in plain.buffers.iter().zip(&coded.buffers) {
        assert_eq!(
            (a.clip.as_str(), a.frame, a.lod),
            (b.clip.as_str(), b.frame, b.lod)
        );
        if let std::collections::hash_map::Entry::Vacant(e) = refs.entry(b.lod) {
            let (r, q) = client
                .q16_reference("default-head", b.lod)
                .await
                .expect("reference");
            assert_eq!(Some(q), a.quantization, "the reference's box");
            e.insert(r);
        }
        let decoded =
            crowdmorph_proto::q16r_decode(&b.positions.0, &refs[&b.lod]).expect("decodes");
        let q16: Vec<i16> = a
            .positions
            .0
            .chunks_exact(2)
            .map(|c| i16::from_le_bytes([c[0], c[1]]))
            .collect();
        assert_eq!(decoded, q16, "{} frame {} lod {}", b.clip, b.frame, b.lod);
        assert_eq!(a.normals, b.normals, "normals travel as q16");
    }
}

gpu_test!(
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn frames_on_the_gpu_backend_match_the_cpu_engine() {
        // `--backend gpu` takes software adapters too; in CI that is lavapipe. Without an adapter
        // the server does not start, and the test fails (it runs only where a driver is installed).
        let server = TestServer::start(ServerConfig {
            backend: crowdmorph::engine::BackendChoice::Gpu,
            ..ServerConfig::default()
        })
        .await;
        assert_eq!(
            server.state.engine.info().kind,
            crowdmorph::engine::BackendKind::Gpu
        );
        let rig = server
            .state
            .registry
            .get("default-head")
            .expect("rig")
            .rig()
            .clone();
        let cpu = crowdmorph::engine::Engine::cpu();
        let prepared = cpu
            .prepare(std::sync::Arc::new(rig.clone()))
            .expect("prepare");
        let diag = rig.bbox().diagonal();
        for (format, normals) in [
            (Format::F32, true),
            (Format::F16, false),
            (Format::Q16, true),
        ] {
            let req = crowd("default-head", &rig, format, normals);
            let (resp, _) = server
                .client
                .crowd_frame(&req, Encoding::Bincode)
                .await
                .expect("frame");
            assert!(
                !server.state.engine.info().degraded,
                "{:?}",
                server.state.engine.info().degraded_reason
            );
            for (h, head) in req.heads.iter().zip(&resp.heads) {
                let b = &resp.buffers[head.buffer as usize];
                let ci = rig.clip_index(&h.clip).expect("clip") as u32;
                let job = crowdmorph::engine::BlendJob::frame(ci, b.frame, h.lod);
                let want = cpu
                    .evaluate(
                        &prepared,
                        &[job],
                        crowdmorph::engine::OutputSpec {
                            normals,
                            ..Default::default()
                        },
                    )
                    .expect("cpu");
                let got = positions_f32(format, b);
                let exp = want.output.job_positions(0);
                let max_coord = exp.iter().map(|x| x.abs()).fold(0.0, f32::max);
                let q = b
                    .quantization
                    .map_or(0.0, |q| q.max_error.iter().copied().fold(0.0, f32::max));
                let tol = 1e-5 * diag
                    + q
                    + if format == Format::F16 {
                        max_coord / 1024.0
                    } else {
                        0.0
                    };
                let d = got
                    .iter()
                    .zip(&exp)
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0, f32::max);
                assert!(d <= tol, "{format:?} head {}: {d} > {tol}", h.head);
                if normals {
                    let n = normals_f32(format, b).expect("normals");
                    let en = want.output.job_normals(0).expect("normals");
                    let d = n
                        .iter()
                        .zip(&en)
                        .map(|(a, b)| (a - b).abs())
                        .fold(0.0, f32::max);
                    assert!(d <= 2e-3, "{format:?} head {} normals: {d}", h.head);
                }
            }
        }
        // q16r, coded on the device, is the q16 answer once decoded against the reference.
        q16r_decodes_to_q16(&server.client, &rig).await;
        assert!(!server.state.engine.info().degraded);
        let metrics = server.client.metrics().await.expect("metrics");
        assert!(
            crowdmorph_client::metric(&metrics, "crowdmorph_gpu_seconds_total")
                .is_some_and(|v| v > 0.0),
            "GPU time is reported in metrics"
        );
        // The device goes away: frames keep coming (from the CPU engine) and /readyz says degraded.
        server.state.engine.gpu().expect("gpu").device().destroy();
        // The CPU engine codes q16r on the host now; a client decodes it as before.
        q16r_decodes_to_q16(&server.client, &rig).await;
        let req = crowd("default-head", &rig, Format::F32, false);
        let (resp, _) = server
            .client
            .crowd_frame(&req, Encoding::Bincode)
            .await
            .expect("frames after the device loss");
        assert_eq!(resp.heads.len(), req.heads.len());
        let ready = server
            .client
            .send(Method::GET, "/readyz", None, None, Bytes::new())
            .await
            .expect("readyz");
        assert_eq!(ready.status, 200);
        let r: crowdmorph_proto::Readiness = serde_json::from_slice(&ready.body).expect("JSON");
        assert_eq!(r.status, "degraded");
        assert_eq!(r.backend, "cpu");
        assert!(r.degraded_reason.is_some());
        server.stop().await;
    }
);

gpu_test!(
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn gpu_batches_overlap_under_load_and_every_response_is_right() {
        // One job per batch, so 32 concurrent requests make a stream of batches: the compute
        // thread submits each next batch before it waits for the one computing.
        let server = TestServer::start(ServerConfig {
            backend: crowdmorph::engine::BackendChoice::Gpu,
            batch_cost: Some(1),
            ..ServerConfig::default()
        })
        .await;
        let rig = server
            .state
            .registry
            .get("default-head")
            .expect("rig")
            .rig()
            .clone();
        let cpu = crowdmorph::engine::Engine::cpu();
        let prepared = cpu
            .prepare(std::sync::Arc::new(rig.clone()))
            .expect("prepare");
        let talk = rig.clip_index("talk").expect("talk") as u32;
        let frames = i64::from(rig.clips[talk as usize].frames);
        let tasks: Vec<_> = (0..32i64)
            .map(|r| {
                let client = server.client.clone();
                let heads: Vec<Head> = (0..4)
                    .map(|k| Head {
                        head: (r * 4 + k) as u64,
                        rig: "default-head".into(),
                        clip: "talk".into(),
                        frame: (r * 3 + k) % frames,
                        lod: (k % 2) as u32,
                        ..Default::default()
                    })
                    .collect();
                tokio::spawn(async move {
                    let req = CrowdFrameRequest {
                        heads,
                        output: OutputOptions {
                            normals: false,
                            format: Format::F32,
                        },
                        wrap: true,
                    };
                    let (resp, _) = client
                        .crowd_frame(&req, Encoding::Bincode)
                        .await
                        .expect("frame");
                    (req, resp)
                })
            })
            .collect();
        let diag = rig.bbox().diagonal();
        for t in tasks {
            let (req, resp) = t.await.expect("join");
            for (h, head) in req.heads.iter().zip(&resp.heads) {
                let b = &resp.buffers[head.buffer as usize];
                let want = cpu
                    .evaluate(
                        &prepared,
                        &[crowdmorph::engine::BlendJob::frame(talk, b.frame, h.lod)],
                        crowdmorph::engine::OutputSpec::default(),
                    )
                    .expect("cpu");
                assert_eq!(b.frame as i64, h.frame, "head {} got another frame", h.head);
                let d = positions_f32(Format::F32, b)
                    .iter()
                    .zip(want.output.job_positions(0))
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0, f32::max);
                assert!(d <= 1e-5 * diag, "head {}: {d}", h.head);
            }
        }
        assert!(!server.state.engine.info().degraded);
        let metrics = server.client.metrics().await.expect("metrics");
        let pipelined = crowdmorph_client::metric(&metrics, "crowdmorph_batches_pipelined_total");
        let batches = crowdmorph_client::metric(&metrics, "crowdmorph_batches_total");
        eprintln!("{batches:?} batches, {pipelined:?} begun while another computed");
        assert!(
            pipelined.is_some_and(|v| v >= 1.0),
            "consecutive batches overlapped on the GPU: {pipelined:?} of {batches:?}"
        );
        server.stop().await;
    }
);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn readyz_says_loading_until_stored_rigs_are_loaded() {
    use http_body_util::BodyExt;
    use tower::ServiceExt;
    // The router alone, through `oneshot`: a state whose stored rigs are not loaded yet.
    let state = crowdmorph::server::AppState::new(ServerConfig::default()).expect("state");
    let get = |path: &str| {
        axum::http::Request::builder()
            .uri(path)
            .body(axum::body::Body::empty())
            .expect("request")
    };
    let resp = crowdmorph::server::app(state.clone())
        .oneshot(get("/readyz"))
        .await
        .expect("response");
    assert_eq!(resp.status(), 503);
    let body = resp.into_body().collect().await.expect("body").to_bytes();
    let r: crowdmorph_proto::Readiness = serde_json::from_slice(&body).expect("JSON");
    assert_eq!(r.status, "loading");
    // Liveness does not wait for loading.
    let live = crowdmorph::server::app(state.clone())
        .oneshot(get("/healthz"))
        .await
        .expect("response");
    assert_eq!(live.status(), 200);
    state.load_stored().await;
    let resp = crowdmorph::server::app(state)
        .oneshot(get("/readyz"))
        .await
        .expect("response");
    assert_eq!(resp.status(), 200);
    let body = resp.into_body().collect().await.expect("body").to_bytes();
    let r: crowdmorph_proto::Readiness = serde_json::from_slice(&body).expect("JSON");
    assert_eq!(r.status, "ready");
    assert_eq!(r.rigs, 1, "the embedded rig");
}
