//! Level of detail over HTTP: the background job that gives every rig a metric-based order and
//! mesh levels, `PUT /v1/rigs/{id}/lod`, frames and meshes at simplified levels (checked
//! against the CPU engine on the server's own rig), persistence of a computed LOD, and bad
//! LOD requests.
//!
//! Tolerance: positions within 1e-5 × the bounding-box diagonal of the CPU engine's output
//! for the same rig version (bitwise equal on a CPU backend).

use std::sync::Arc;
use std::time::{Duration, Instant};

use crowdmorph::engine::{BlendJob, Engine, OutputSpec};
use crowdmorph::server::ServerConfig;
use crowdmorph_client::{ClientError, Encoding};
use crowdmorph_proto::{
    CrowdFrameRequest, Format, Head, LodInfo, LodLevelRequest, LodRequest, OutputOptions,
};

use super::{TestServer, positions_f32, stored_config, temp_dir, upload_bytes};
use crate::util::rig_files;

/// Polls a rig's LOD until the background job has finished.
async fn wait_ready(server: &TestServer, id: &str) -> LodInfo {
    let start = Instant::now();
    loop {
        let lod = server.client.lod(id).await.expect("GET lod");
        match lod.status.as_str() {
            "ready" => return lod,
            "failed" => panic!("LOD of {id} failed: {:?}", lod.error),
            s => assert!(s == "computing" || s == "imported", "unexpected status {s}"),
        }
        assert!(
            start.elapsed() < Duration::from_secs(300),
            "LOD of {id} not ready: {lod:?}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// Frames one head per LOD level and checks each buffer against the CPU engine evaluating
/// the server's current version of the rig, and against that level's mesh.
async fn check_levels(server: &TestServer, id: &str, clip: &str, frame: u32) {
    let entry = server.state.registry.get(id).expect("registered");
    let rig = entry.rig().clone();
    let info = server.client.rig(id).await.expect("rig info");
    let levels = info.lod.levels.len() as u32;
    let req = CrowdFrameRequest {
        heads: (0..levels)
            .map(|lod| Head {
                head: u64::from(lod),
                rig: id.to_string(),
                clip: clip.to_string(),
                frame: i64::from(frame),
                lod,
                ..Default::default()
            })
            .collect(),
        output: OutputOptions {
            normals: false,
            format: Format::F32,
        },
        wrap: true,
    };
    let (resp, _) = server
        .client
        .crowd_frame(&req, Encoding::Bincode)
        .await
        .expect("frame");
    let engine = Engine::cpu();
    let prepared = engine.prepare(Arc::new(rig.clone())).expect("prepare");
    let ci = rig.clip_index(clip).expect("clip") as u32;
    let diag = rig.bbox().diagonal();
    for (lod, h) in resp.heads.iter().enumerate() {
        let buffer = &resp.buffers[h.buffer as usize];
        let level = &info.lod.levels[lod];
        assert_eq!(
            buffer.vertices, level.vertices,
            "level {lod}: buffer size is the level's mesh"
        );
        let want = engine
            .evaluate(
                &prepared,
                &[BlendJob::frame(ci, frame, lod as u32)],
                OutputSpec::default(),
            )
            .expect("evaluate");
        let got = positions_f32(Format::F32, buffer);
        let expected = want.output.job_positions(0);
        assert_eq!(got.len(), expected.len());
        let d = got
            .iter()
            .zip(&expected)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f32::max);
        assert!(d <= 1e-5 * diag, "level {lod}: differs by {d}");
        let mesh = server
            .client
            .mesh_at(id, lod as u32, Encoding::Bincode)
            .await
            .expect("mesh");
        assert_eq!(mesh.vertices, level.vertices, "level {lod}: mesh vertices");
        assert_eq!(
            mesh.indices.0.len() / 4,
            level.triangles as usize * 3,
            "level {lod}: mesh triangles"
        );
        assert!(
            mesh.indices
                .0
                .chunks_exact(4)
                .all(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) < level.vertices),
            "level {lod}: indices within the level's vertices"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rigs_get_a_metric_order_and_mesh_levels_in_the_background() {
    let server = TestServer::start_with_auto_lod(ServerConfig::default()).await;
    // The embedded rig starts with the import's quick order and gets the combined one.
    let lod = wait_ready(&server, "default-head").await;
    assert_eq!(lod.method, "combined");
    assert_eq!(lod.levels.len(), 5);
    assert_eq!(lod.levels[0].mesh, None, "level 0 is the full mesh");
    let full = lod.levels[0].vertices;
    for l in 1..4 {
        assert_eq!(
            lod.levels[l].mesh,
            Some(l as u32 - 1),
            "levels 1-3 use the 50/25/10 % meshes"
        );
        assert!(
            lod.levels[l].vertices < lod.levels[l - 1].vertices
                || l == 1 && lod.levels[1].vertices < full
        );
    }
    assert!(
        lod.levels[3].triangles * 8 < lod.levels[0].triangles,
        "10 % mesh: {lod:?}"
    );
    check_levels(&server, "default-head", "talk", 17).await;
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
async fn an_uploaded_rig_gets_a_metric_order_and_mesh_levels_in_the_background() {
    let server = TestServer::start_with_auto_lod(ServerConfig::default()).await;
    let files = rig_files();
    let stress = files
        .iter()
        .find(|f| f.ends_with("MorphStressTest.gltf"))
        .expect("file");
    server
        .client
        .upload_rig("stress", upload_bytes(stress))
        .await
        .expect("upload");
    let lod = wait_ready(&server, "stress").await;
    assert_eq!(lod.method, "combined");
    check_levels(&server, "stress", "TheWave", 20).await;
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn put_lod_sets_order_pins_and_table() {
    let server = TestServer::start(ServerConfig {
        admin_token: Some("secret".into()),
        ..ServerConfig::default()
    })
    .await;
    let admin = server.client.clone().with_token("secret");
    let before = server.client.lod("default-head").await.expect("lod");
    assert_eq!(before.status, "imported");

    let request = LodRequest {
        method: Some("file-order".into()),
        pinned: vec!["eyeBlink_L".into(), "eyeBlink_R".into()],
        levels: Some(vec![
            LodLevelRequest {
                shapes: 51,
                mesh: None,
            },
            LodLevelRequest {
                shapes: 10,
                mesh: None,
            },
            LodLevelRequest {
                shapes: 4,
                mesh: Some(0),
            },
        ]),
        mesh_fractions: vec![0.3],
        ..LodRequest::default()
    };
    // Uploads and deletes need the token; so does changing the LOD.
    let denied = server
        .client
        .set_lod("default-head", &request)
        .await
        .expect_err("no token");
    assert!(
        matches!(denied, ClientError::Api { status: 401, .. }),
        "{denied}"
    );

    let info = admin
        .set_lod("default-head", &request)
        .await
        .expect("PUT lod");
    assert_eq!(info.lod.method, "file-order+pinned");
    assert_eq!(info.lod.status, "ready");
    assert_eq!(
        &info.lod.order[..2],
        ["eyeBlink_L", "eyeBlink_R"],
        "pins lead the order"
    );
    assert_eq!(info.lod.pinned, vec!["eyeBlink_L", "eyeBlink_R"]);
    let shapes: Vec<u32> = info.lod.levels.iter().map(|l| l.shapes).collect();
    assert_eq!(shapes, vec![51, 10, 4]);
    assert_eq!(info.lod.levels[2].mesh, Some(0));
    assert!(info.lod.levels[2].vertices < info.lod.levels[0].vertices);
    // The rest of file order follows the pins.
    let rig = server
        .state
        .registry
        .get("default-head")
        .expect("rig")
        .rig()
        .clone();
    let rest: Vec<&String> = rig
        .targets
        .iter()
        .filter(|t| !t.starts_with("eyeBlink"))
        .collect();
    assert_eq!(info.lod.order[2..].iter().collect::<Vec<_>>(), rest);
    check_levels(&server, "default-head", "idle", 40).await;

    // Bad requests name the problem and change nothing.
    for (bad, needle) in [
        (
            LodRequest {
                method: Some("loudness".into()),
                ..LodRequest::default()
            },
            "unknown method",
        ),
        (
            LodRequest {
                pinned: vec!["noSuchShape".into()],
                ..LodRequest::default()
            },
            "noSuchShape",
        ),
        (
            LodRequest {
                mesh_fractions: vec![2.0],
                ..LodRequest::default()
            },
            "mesh fraction",
        ),
        (
            // Each mesh level is a copy of the rig at a fraction of its size: capped.
            LodRequest {
                mesh_fractions: vec![0.5; 9],
                ..LodRequest::default()
            },
            "at most 8",
        ),
        (
            LodRequest {
                levels: Some(vec![LodLevelRequest {
                    shapes: 10,
                    mesh: None,
                }]),
                ..LodRequest::default()
            },
            "level 0",
        ),
        (
            LodRequest {
                levels: Some(vec![
                    LodLevelRequest {
                        shapes: 51,
                        mesh: None,
                    },
                    LodLevelRequest {
                        shapes: 5,
                        mesh: Some(3),
                    },
                ]),
                ..LodRequest::default()
            },
            "mesh",
        ),
    ] {
        assert_invalid_lod(admin.set_lod("default-head", &bad).await, needle);
    }
    let after = server.client.lod("default-head").await.expect("lod");
    assert_eq!(
        after, info.lod,
        "a refused request leaves the LOD as it was"
    );
    match server
        .client
        .mesh_at("default-head", 9, Encoding::Json)
        .await
    {
        Err(ClientError::Api {
            status: 400, code, ..
        }) => assert_eq!(code, "lod_out_of_range"),
        other => panic!("expected lod_out_of_range, got {other:?}"),
    }
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
async fn a_computed_lod_survives_a_restart() {
    let files = rig_files();
    let dir = temp_dir("lod-restart");
    let config = stored_config(&dir);
    let stress = files
        .iter()
        .find(|f| f.ends_with("MorphStressTest.gltf"))
        .expect("file");
    let s1 = TestServer::start_with_auto_lod(config.clone()).await;
    s1.client
        .upload_rig("stress", upload_bytes(stress))
        .await
        .expect("upload");
    let computed = wait_ready(&s1, "stress").await;
    s1.stop().await;

    // Back with the background job off: the stored rig already has its computed LOD.
    let s2 = TestServer::start(config).await;
    let reloaded = s2.client.lod("stress").await.expect("lod");
    assert_eq!(
        reloaded, computed,
        "order, table and mesh levels persisted with the rig"
    );
    check_levels(&s2, "stress", "Pulse", 33).await;
    s2.stop().await;
    let _ = std::fs::remove_dir_all(dir);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
async fn deleting_a_rig_cancels_its_lod_job() {
    let files = rig_files();
    let server = TestServer::start_with_auto_lod(ServerConfig::default()).await;
    let ict = files
        .iter()
        .find(|f| f.ends_with("ict_facekit_53.glb"))
        .expect("ICT");
    server
        .client
        .upload_rig("ict", upload_bytes(ict))
        .await
        .expect("upload");
    // Wait until a background build is computing, then delete the rig.
    let m = &server.state.metrics;
    let t0 = Instant::now();
    while m.lod_builds_running.get() == 0 {
        assert!(
            t0.elapsed() < Duration::from_secs(30),
            "no LOD build started"
        );
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    server.client.delete_rig("ict").await.expect("delete");
    // Every build ends (the built-in rig's, if it runs, normally); ICT's must end as
    // cancelled. A cancellation that did nothing would let it run to completion, uncounted.
    while m.lod_builds_running.get() > 0 {
        assert!(
            t0.elapsed() < Duration::from_secs(120),
            "a LOD build never ended"
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    assert_eq!(
        m.lod_builds_cancelled.get(),
        1,
        "the deleted rig's LOD build was not cancelled"
    );
    assert!(server.state.registry.get("ict").is_none());
    assert!(matches!(
        server.client.lod("ict").await,
        Err(ClientError::Api { status: 404, .. })
    ));
    // The server still serves.
    wait_ready(&server, "default-head").await;
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
async fn a_put_lod_wins_over_the_background_job() {
    let files = rig_files();
    let stress = files
        .iter()
        .find(|f| f.ends_with("MorphStressTest.gltf"))
        .expect("file");
    let server = TestServer::start_with_auto_lod(ServerConfig::default()).await;
    server
        .client
        .upload_rig("stress", upload_bytes(stress))
        .await
        .expect("upload");
    // The background job has only just started scoring; the PUT replaces it.
    let put = server
        .client
        .set_lod(
            "stress",
            &LodRequest {
                method: Some("file-order".into()),
                ..LodRequest::default()
            },
        )
        .await
        .expect("PUT lod");
    assert_eq!(put.lod.method, "file-order");
    // Give a job that ignored its cancellation ample time to finish and overwrite (the
    // whole job takes well under this on this rig); the PUT must still be what is served.
    let t0 = Instant::now();
    while t0.elapsed() < Duration::from_secs(3) {
        let lod = server.client.lod("stress").await.expect("lod");
        assert_eq!(
            lod.method, "file-order",
            "the background job overwrote a PUT"
        );
        assert_eq!(lod.status, "ready");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    server.stop().await;
}

/// A rig of points only (no triangles): blends, but has no mesh to simplify.
fn points_rig() -> Vec<u8> {
    let mut b = crate::util::builder::Builder::new();
    let positions: Vec<[f32; 3]> = (0..64)
        .map(|i| [(i % 8) as f32, (i / 8) as f32, 0.0])
        .collect();
    let targets: Vec<Vec<[f32; 3]>> = (0..3)
        .map(|t| {
            positions
                .iter()
                .enumerate()
                .map(|(i, _)| {
                    if i % 3 == t {
                        [0.0, 0.0, 0.5]
                    } else {
                        [0.0; 3]
                    }
                })
                .collect()
        })
        .collect();
    let mut prim = b.primitive(&positions, None, &targets);
    prim["mode"] = serde_json::json!(0);
    let mesh = b.mesh(vec![prim], Some(&["a", "b", "c"]));
    let node = b.node(Some(mesh));
    b.scene(&[node]);
    b.to_glb()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_rig_without_triangles_gets_an_order_and_no_unloadable_mesh_levels() {
    let dir = temp_dir("lod-points");
    let config = stored_config(&dir);
    let s1 = TestServer::start_with_auto_lod(config.clone()).await;
    s1.client
        .upload_rig("dots", points_rig().into())
        .await
        .expect("upload");
    let lod = wait_ready(&s1, "dots").await;
    assert!(
        lod.levels.iter().all(|l| l.mesh.is_none()),
        "no mesh levels for a rig without triangles: {lod:?}"
    );
    // Asking for mesh levels explicitly is a named 400, and nothing is stored.
    assert_invalid_lod(
        s1.client
            .set_lod(
                "dots",
                &LodRequest {
                    mesh_fractions: vec![0.5],
                    ..LodRequest::default()
                },
            )
            .await,
        "no vertices",
    );
    assert_eq!(s1.client.lod("dots").await.expect("lod"), lod);
    s1.stop().await;
    // What was stored loads again.
    let s2 = TestServer::start(config).await;
    assert_eq!(s2.client.lod("dots").await.expect("lod"), lod);
    assert!(
        s2.state.skipped().is_empty(),
        "nothing skipped: {:?}",
        s2.state.skipped()
    );
    s2.stop().await;
    let _ = std::fs::remove_dir_all(dir);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_built_in_rigs_lod_survives_a_restart() {
    let dir = temp_dir("lod-builtin");
    let config = stored_config(&dir);
    let s1 = TestServer::start(config.clone()).await;
    let set = s1
        .client
        .set_lod(
            "default-head",
            &LodRequest {
                method: Some("file-order".into()),
                pinned: vec!["jawOpen".into()],
                mesh_fractions: vec![0.4],
                ..LodRequest::default()
            },
        )
        .await
        .expect("PUT lod");
    s1.stop().await;
    let s2 = TestServer::start(config).await;
    let reloaded = s2.client.lod("default-head").await.expect("lod");
    assert_eq!(reloaded, set.lod, "the built-in rig's LOD was stored");
    assert_eq!(reloaded.method, "file-order+pinned");
    check_levels(&s2, "default-head", "talk", 17).await;
    s2.stop().await;
    let _ = std::fs::remove_dir_all(dir);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_cli_sets_a_lod_on_a_running_server() {
    let server = TestServer::start(ServerConfig {
        admin_token: Some("secret".into()),
        ..ServerConfig::default()
    })
    .await;
    let url = format!("http://{}", server.addr);
    // The binary, off this test's async threads.
    let lod_set = |args: Vec<String>| {
        tokio::task::spawn_blocking(move || {
            std::process::Command::new(env!("CARGO_BIN_EXE_crowdmorph"))
                .args(args)
                .env_remove("CROWDMORPH_ADMIN_TOKEN")
                .env("NO_COLOR", "1")
                .output()
                .expect("run crowdmorph")
        })
    };
    let args = |extra: &[&str], token: bool| -> Vec<String> {
        let mut a: Vec<String> = ["lod", "set", "default-head", "--server", &url]
            .iter()
            .map(|s| s.to_string())
            .collect();
        if token {
            a.extend(["--token".to_string(), "secret".to_string()]);
        }
        a.extend(extra.iter().map(|s| s.to_string()));
        a
    };
    // Levels it cannot parse are refused before anything is sent.
    for bad in ["twelve", "12:x"] {
        let out = lod_set(args(&["--level", bad], true)).await.expect("join");
        assert_eq!(out.status.code(), Some(2), "--level {bad}");
    }
    // `crowdmorph lod set default-head --method file-order --pin jawOpen --level 51
    //  --level 12:0 --level 0:0 --mesh-fractions 0.3`.
    let request = [
        "--method",
        "file-order",
        "--pin",
        "jawOpen",
        "--level",
        "51",
        "--level",
        "12:0",
        "--level",
        "0:0",
        "--mesh-fractions",
        "0.3",
    ];
    let mut json = request.to_vec();
    json.push("--json");
    let out = lod_set(args(&json, true)).await.expect("join");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let info: crowdmorph_proto::RigInfo = serde_json::from_slice(&out.stdout).expect("RigInfo");
    assert_eq!(info.lod.method, "file-order+pinned");
    assert_eq!(info.lod.order[0], "jawOpen");
    let shapes: Vec<u32> = info.lod.levels.iter().map(|l| l.shapes).collect();
    assert_eq!(shapes, vec![51, 12, 0]);
    assert_eq!(info.lod.levels[1].mesh, Some(0));
    let out = lod_set(args(&request, true)).await.expect("join");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("level 1:  12 shapes"), "{text}");
    assert_eq!(
        server.client.lod("default-head").await.expect("lod"),
        info.lod,
        "what the tool set is what the server serves"
    );
    // Without the token the server refuses, and the tool says so.
    let out = lod_set(args(&request, false)).await.expect("join");
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("401"), "{err}");
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn dropping_the_server_state_cancels_its_lod_builds() {
    // The built-in rig gets its metric order in the background once stored rigs are loaded.
    let state = crowdmorph::server::AppState::new(ServerConfig::default()).expect("state");
    state.load_stored().await;
    let metrics = state.metrics.clone();
    let t0 = Instant::now();
    while metrics.lod_builds_running.get() == 0 {
        assert!(
            t0.elapsed() < Duration::from_secs(30),
            "no LOD build started"
        );
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    // The owner lets go: the build is cancelled, not left to run to its end.
    drop(state);
    while metrics.lod_builds_running.get() > 0 {
        assert!(
            t0.elapsed() < Duration::from_secs(120),
            "the LOD build never ended"
        );
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    assert_eq!(
        metrics.lod_builds_cancelled.get(),
        1,
        "the build of a dropped state ran to completion"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bad_table_is_refused_before_a_build_is_started() {
    // An upload memory budget too small for scoring the built-in rig: any PUT that reaches
    // the build is refused with 413 when it reserves the build's memory, so a 400 for a bad
    // table shows the table was checked before a build was started.
    let server = TestServer::start(ServerConfig {
        admin_token: Some("secret".into()),
        max_upload_memory: 2 << 20,
        ..ServerConfig::default()
    })
    .await;
    let admin = server.client.clone().with_token("secret");
    let before = server.client.lod("default-head").await.expect("lod");
    let n = server
        .state
        .registry
        .get("default-head")
        .expect("built-in rig")
        .rig()
        .targets
        .len() as u32;
    let level = |shapes| LodLevelRequest { shapes, mesh: None };
    let build = |levels| LodRequest {
        levels: Some(levels),
        ..LodRequest::default()
    };
    match admin
        .set_lod("default-head", &build(vec![level(n), level(3)]))
        .await
    {
        Err(ClientError::Api {
            status: 413, code, ..
        }) => assert_eq!(code, "lod_too_large"),
        other => panic!("a good table reaches the build and its budget: {other:?}"),
    }
    for (levels, needle) in [
        (vec![level(n); 65], "more than 64 levels"),
        (
            vec![level(n), level(n + 1)],
            &format!("{} shapes of {n}", n + 1),
        ),
    ] {
        assert_invalid_lod(admin.set_lod("default-head", &build(levels)).await, needle);
    }
    let after = server.client.lod("default-head").await.expect("lod");
    assert_eq!(after, before, "refused requests leave the LOD as it was");
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_lod_body_is_charged_while_decoded_and_its_lists_are_capped() {
    let server = TestServer::start(ServerConfig {
        admin_token: Some("secret".into()),
        queue_memory_bytes: 8 << 20,
        ..ServerConfig::default()
    })
    .await;
    let admin = server.client.clone().with_token("secret");
    let before = server.client.lod("default-head").await.expect("lod");
    let n = before.order.len();
    // 1 MB of empty names decodes to 350,000 strings (8 MB and more): more than this
    // server's whole queue memory, so the decode is refused before it is made, as too large
    // (it could never fit), not as busy.
    let many = LodRequest {
        order: Some(vec![String::new(); 350_000]),
        ..LodRequest::default()
    };
    match admin.set_lod("default-head", &many).await {
        Err(ClientError::Api {
            status: 413, code, ..
        }) => assert_eq!(code, "queue_memory_exceeded"),
        other => panic!("expected the decode to be refused with 413, got {other:?}"),
    }
    // A list longer than the rig's targets names the limit.
    let mut order = before.order.clone();
    order.push(order[0].clone());
    for bad in [
        LodRequest {
            order: Some(order.clone()),
            ..LodRequest::default()
        },
        LodRequest {
            pinned: order,
            ..LodRequest::default()
        },
    ] {
        assert_invalid_lod(
            admin.set_lod("default-head", &bad).await,
            &format!("at most {n}"),
        );
    }
    // The charge is given back: a request of the rig's size goes through.
    let ok = LodRequest {
        method: Some("file-order".into()),
        order: Some(before.order.clone()),
        ..LodRequest::default()
    };
    admin
        .set_lod("default-head", &ok)
        .await
        .expect("a good PUT");
    server.stop().await;
}

/// Asserts that a LOD request was refused with 400 `invalid_lod` and a message containing
/// `needle`.
fn assert_invalid_lod<T: std::fmt::Debug>(result: Result<T, ClientError>, needle: &str) {
    match result {
        Err(ClientError::Api {
            status: 400,
            code,
            message,
        }) => {
            assert_eq!(code, "invalid_lod", "{message}");
            assert!(
                message.contains(needle),
                "{message:?} should mention {needle:?}"
            );
        }
        other => panic!("expected a 400 invalid_lod mentioning {needle:?}, got {other:?}"),
    }
}
