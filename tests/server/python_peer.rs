//! The dense Python peer of `bench http --python-peer` (`clients/python/bench/dense_server.py`)
//! answers the same bincode request with the same vertices as crowdmorph: the benchmark's
//! comparison is between two servers doing the same work. Runs where `/usr/bin/python3` has
//! numpy and aiohttp (`build.rs` sets `crowdmorph_python_peer`); ignored with the reason
//! otherwise.

use bytes::Bytes;
use crowdmorph::bench::peers::{self as pypeer, PythonPeer};
use crowdmorph::server::ServerConfig;
use crowdmorph_client::{Client, Encoding};
use crowdmorph_proto::{CrowdFrameRequest, Format, Head, OutputOptions};

use super::{TestServer, random_clip_json, upload_bytes};

/// Exports `rig_id` from `server`, starts the peer on it and checks `heads` in f32 and f16
/// against crowdmorph's response, within 1e-5 of the rig's bounding-box diagonal.
async fn same_vertices(server: &TestServer, rig_id: &str, heads: Vec<Head>) {
    let entry = server.state.registry.get(rig_id).expect("rig registered");
    let rig = entry.rig().clone();
    let dir = pypeer::temp_dir("crowdmorph-test-pypeer-").unwrap();
    let scripts = pypeer::write_scripts(&dir.path().join("py")).unwrap();
    pypeer::export_rig(&rig, rig_id, &dir.path().join("rig")).unwrap();
    let peer = PythonPeer::start(
        std::path::Path::new(pypeer::DEFAULT_PYTHON),
        &scripts,
        &dir.path().join("rig"),
        "thread",
    )
    .unwrap();
    assert!(!peer.numpy.is_empty(), "the peer names its numpy");
    let client = Client::new(peer.url());
    let tolerance = 1e-5 * rig.bbox().diagonal();
    for format in [Format::F32, Format::F16] {
        let req = CrowdFrameRequest {
            heads: heads.clone(),
            output: OutputOptions {
                normals: false,
                format,
            },
            wrap: true,
        };
        let (ours, _) = server
            .client
            .crowd_frame(&req, Encoding::Bincode)
            .await
            .unwrap();
        let (theirs, _) = client.crowd_frame(&req, Encoding::Bincode).await.unwrap();
        assert!(ours.buffers.len() < heads.len(), "the crowd has duplicates");
        let worst = pypeer::compare_responses(&ours, &theirs, tolerance)
            .unwrap_or_else(|e| panic!("{rig_id} {format:?}: {e:#}"));
        if format == Format::F32 {
            assert!(worst <= tolerance, "{worst} > {tolerance}");
        }
        // Not a comparison of two neutral meshes: the crowd's heads moved.
        if format == Format::F32 {
            let neutral = pypeer::neutral(&rig);
            let moved = ours
                .buffers
                .iter()
                .filter(|b| {
                    b.positions
                        .to_f32()
                        .iter()
                        .zip(&neutral)
                        .any(|(x, n)| (x - n).abs() > 100.0 * tolerance)
                })
                .count();
            assert!(moved > ours.buffers.len() / 2, "{moved} heads moved");
        }
    }
    // What the peer does not serve is a 400 with crowdmorph's error body, not a wrong answer.
    let req = CrowdFrameRequest {
        heads: heads[..1].to_vec(),
        output: OutputOptions {
            normals: true,
            format: Format::F32,
        },
        wrap: true,
    };
    let reply = client
        .crowd_frame_raw(
            Client::encode(&req, Encoding::Bincode).unwrap(),
            Encoding::Bincode,
        )
        .await
        .unwrap();
    assert_eq!(reply.status, 400);
    assert_eq!(reply.error().unwrap().error.code, "unsupported");
    drop(peer);
}

fn head(head: u64, rig: &str, clip: &str, frame: i64, lod: u32) -> Head {
    Head {
        head,
        rig: rig.to_string(),
        clip: clip.to_string(),
        frame,
        lod,
        ..Default::default()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_python_peer),
    ignore = "needs /usr/bin/python3 with numpy and aiohttp: apt-get install python3-numpy python3-aiohttp"
)]
async fn the_python_peer_serves_the_embedded_heads_vertices() {
    let server = TestServer::start(ServerConfig::default()).await;
    let id = crowdmorph::server::registry::BUILTIN_ID;
    let levels = server
        .state
        .registry
        .get(id)
        .unwrap()
        .rig()
        .lod
        .levels
        .len() as u32;
    assert!(levels > 1, "the embedded head has LOD levels to check");
    // Several clips, repeated heads, wrapped and negative frames, every LOD level.
    let mut heads = Vec::new();
    for (i, clip) in ["idle", "talk", "smile", "surprise"].iter().enumerate() {
        for k in 0..6i64 {
            let n = heads.len() as u64;
            heads.push(head(n, id, clip, k * 7 - 3, (k as u32 + i as u32) % levels));
        }
        let n = heads.len() as u64;
        heads.push(head(n, id, clip, 11, 0));
        heads.push(head(n + 1, id, clip, 11, 0));
    }
    heads.push(head(1000, id, "talk", 1_000_000, 0));
    same_vertices(&server, id, heads).await;
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(all(crowdmorph_python_peer, crowdmorph_test_data)),
    ignore = "needs /usr/bin/python3 with numpy and aiohttp, and the shared rigs"
)]
async fn the_python_peer_serves_ict_facekits_vertices() {
    let server = TestServer::start(ServerConfig::default()).await;
    let path = crate::util::data_dir().join("ict-facekit/ict_facekit_53.glb");
    let info = server
        .client
        .upload_rig("ict", upload_bytes(&path))
        .await
        .unwrap();
    let clip = random_clip_json(&info.targets, 40, 0x1C7);
    server
        .client
        .upload_clip("ict", "name=random", "application/json", Bytes::from(clip))
        .await
        .unwrap();
    let heads: Vec<Head> = (0..24)
        .map(|h| head(h, "ict", "random", (h as i64 * 5) % 17 - 2, 0))
        .collect();
    same_vertices(&server, "ict", heads).await;
    server.stop().await;
}

// Moved from `crates/bench/src/peers.rs` with the split into crates: it needs the
// `crowdmorph_python_peer` cfg that the root package's build.rs sets.
#[test]
#[cfg_attr(
    not(crowdmorph_python_peer),
    ignore = "needs /usr/bin/python3 with numpy and aiohttp"
)]
fn a_missing_package_is_named_in_the_error() {
    for missing in ["numpy", "aiohttp"] {
        let dir = pypeer::temp_dir("crowdmorph-missing-").unwrap();
        let scripts = pypeer::write_scripts(dir.path()).unwrap();
        // The script's own folder comes first on sys.path: this module shadows the real one.
        std::fs::write(
            scripts.join(format!("bench/{missing}.py")),
            format!("raise ImportError('No module named {missing}')\n"),
        )
        .unwrap();
        let err = PythonPeer::start(
            std::path::Path::new(pypeer::DEFAULT_PYTHON),
            &scripts,
            dir.path(),
            "thread",
        )
        .err()
        .expect("the peer cannot start");
        let text = format!("{err:#}");
        assert!(
            text.contains(&format!("needs {missing}")) && text.contains("apt-get install"),
            "{text}"
        );
    }
}
