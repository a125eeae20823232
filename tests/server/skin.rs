//! Skinned rigs over HTTP: the upload's answer describes the skeleton, frames are posed
//! meshes (morph targets, then skinning) equal to the independent evaluator, hostile skins
//! are 400s naming the problem, and a skinned rig survives a restart.

use bytes::Bytes;
use crowdmorph::server::ServerConfig;
use crowdmorph_client::Encoding;
use crowdmorph_proto::{CrowdFrameRequest, Format, Head, OutputOptions};
use glam::DVec3;
use serde_json::json;

use super::{
    TestServer, api_error, max_distance, normals_f32, positions_f32, stored_config, temp_dir,
};
use crate::util::RefDoc;
use crate::util::builder::skinned_triangle_rig;

fn heads(rig: &str, frames: &[(&str, i64)]) -> CrowdFrameRequest {
    CrowdFrameRequest {
        heads: frames
            .iter()
            .enumerate()
            .map(|(i, &(clip, frame))| Head {
                head: i as u64,
                rig: rig.into(),
                clip: clip.into(),
                frame,
                lod: 0,
                ..Default::default()
            })
            .collect(),
        output: OutputOptions {
            normals: true,
            format: Format::F32,
        },
        wrap: false,
    }
}

/// The frames of `req` as f32 positions and normals, per head.
async fn frames(server: &TestServer, req: &CrowdFrameRequest) -> Vec<(Vec<f32>, Vec<f32>)> {
    let (resp, _) = server
        .client
        .crowd_frame(req, Encoding::Bincode)
        .await
        .expect("frame");
    resp.heads
        .iter()
        .map(|h| {
            let b = &resp.buffers[h.buffer as usize];
            (
                positions_f32(Format::F32, b),
                normals_f32(Format::F32, b).expect("normals"),
            )
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_skinned_upload_is_described_and_its_frames_are_posed() {
    let server = TestServer::start(ServerConfig::default()).await;
    let (b, _) = skinned_triangle_rig();
    let glb = b.to_glb();
    let info = server
        .client
        .upload_rig("jaw", Bytes::from(glb.clone()))
        .await
        .expect("upload");
    let sk = info
        .skeleton
        .as_ref()
        .expect("the answer describes the skeleton");
    assert_eq!((sk.nodes, sk.bones), (2, 2), "{sk:?}");
    assert_eq!((sk.skinned_vertices, sk.rigid_vertices), (3, 0));
    assert_eq!(sk.animated_nodes, ["Root", "Jaw"]);
    assert_eq!(sk.clips_with_joints, ["open", "wag"]);
    assert!(info.import_notes.is_empty(), "{:?}", info.import_notes);

    let doc = RefDoc::from_bytes(&glb, std::path::Path::new("."));
    let asked = [
        ("open", 0),
        ("open", 12),
        ("open", 30),
        ("wag", 7),
        ("wag", 21),
    ];
    let got = frames(&server, &heads("jaw", &asked)).await;
    let rest = doc.pose(&doc.rest_locals());
    let mut moved = 0f64;
    for ((clip, f), (p, n)) in asked.iter().zip(&got) {
        let want = doc.pose(&doc.locals_at(clip, *f as f64 / 30.0));
        let d = max_distance(p, &want[0].positions);
        // The triangle's diagonal is √2.
        assert!(d <= 1e-5 * 2f64.sqrt(), "{clip} {f}: position off by {d:e}");
        // The file has no normals: they are recomputed from the posed positions.
        assert!(want[0].normals.is_none());
        let want_n = crate::util::ref_vertex_normals(&want[0].positions, &[0, 1, 2]);
        let dn = max_distance(n, &want_n);
        assert!(dn <= 1e-4, "{clip} {f}: normal off by {dn:e}");
        moved = moved.max(max_distance(p, &rest[0].positions));
    }
    assert!(moved > 0.2, "the joints move the triangle ({moved})");
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hostile_skins_are_refused_naming_the_problem() {
    let server = TestServer::start(ServerConfig::default()).await;
    type Edit = fn(&mut crate::util::builder::Builder, &crate::util::builder::SkinnedTriangle);
    let cases: [(&str, Edit, &str); 6] = [
        (
            "joint out of range",
            |b, ids| {
                // Vertex 1 names joint 7 of a two-joint skin.
                let view = b.accessor_mut(ids.joints)["bufferView"].as_u64().unwrap() as usize;
                let at = b.buffer_view_mut(view)["byteOffset"].as_u64().unwrap_or(0) as usize;
                b.bin_mut()[at + 4] = 7;
            },
            "joint",
        ),
        (
            "weights that do not sum to one",
            |b, ids| {
                let view = b.accessor_mut(ids.weights)["bufferView"].as_u64().unwrap() as usize;
                let at = b.buffer_view_mut(view)["byteOffset"].as_u64().unwrap_or(0) as usize;
                b.bin_mut()[at..at + 4].copy_from_slice(&0.5f32.to_le_bytes());
            },
            "sum",
        ),
        (
            "10⁵ joints in a small file",
            |b, ids| {
                b.json_mut()["skins"][0]["joints"] = json!(vec![ids.jaw; 100_000]);
                b.json_mut()["skins"][0]
                    .as_object_mut()
                    .unwrap()
                    .remove("inverseBindMatrices");
            },
            "joints",
        ),
        (
            "a cyclic node graph",
            |b, ids| {
                b.json_mut()["nodes"][ids.jaw]["children"] = json!([ids.root]);
            },
            "cycle",
        ),
        (
            "a NaN inverse bind matrix",
            |b, ids| {
                let view = b.accessor_mut(ids.ibm)["bufferView"].as_u64().unwrap() as usize;
                let at = b.buffer_view_mut(view)["byteOffset"].as_u64().unwrap_or(0) as usize;
                b.bin_mut()[at + 64..at + 68].copy_from_slice(&f32::NAN.to_le_bytes());
            },
            "finite",
        ),
        (
            "a NaN joint rotation",
            |b, ids| {
                let _ = ids;
                let sampler = &b.json_mut()["animations"][0]["samplers"][0];
                let out = sampler["output"].as_u64().unwrap() as usize;
                let view = b.accessor_mut(out)["bufferView"].as_u64().unwrap() as usize;
                let at = b.buffer_view_mut(view)["byteOffset"].as_u64().unwrap_or(0) as usize;
                b.bin_mut()[at + 16..at + 20].copy_from_slice(&f32::NAN.to_le_bytes());
            },
            "finite",
        ),
    ];
    for (what, edit, needle) in cases {
        let (mut b, ids) = skinned_triangle_rig();
        edit(&mut b, &ids);
        let result = server
            .client
            .upload_rig("bad", Bytes::from(b.to_glb()))
            .await;
        let message = api_error(result, 400, "invalid_rig");
        eprintln!("{what}: {message}");
        assert!(
            message.to_lowercase().contains(needle),
            "{what}: {message:?} should name {needle:?}"
        );
    }
    // Nothing half-registered, and the server still serves.
    let rigs = server.client.rigs().await.expect("rigs");
    assert_eq!(rigs.rigs.len(), 1, "only the built-in rig");
    let ok = frames(&server, &heads("default-head", &[("talk", 3)])).await;
    assert_eq!(ok.len(), 1);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_skinned_rig_survives_a_restart() {
    let dir = temp_dir("skin-restart");
    let (b, _) = skinned_triangle_rig();
    let req = heads("jaw", &[("open", 20), ("wag", 11)]);
    let s1 = TestServer::start(stored_config(&dir)).await;
    let before_info = s1
        .client
        .upload_rig("jaw", Bytes::from(b.to_glb()))
        .await
        .expect("upload");
    let before = frames(&s1, &req).await;
    s1.stop().await;
    let s2 = TestServer::start(stored_config(&dir)).await;
    let after_info = s2.client.rig("jaw").await.expect("the rig is back");
    assert_eq!(after_info.skeleton, before_info.skeleton);
    assert_eq!(after_info.import_notes, before_info.import_notes);
    let after = frames(&s2, &req).await;
    assert_eq!(after, before, "the same posed frames after a restart");
    s2.stop().await;
    let _ = std::fs::remove_dir_all(&dir);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (the shared test rigs; set CROWDMORPH_TEST_DATA)"
)]
async fn robot_expressive_waves_over_http() {
    let path = crate::util::data_dir().join("robot-expressive/RobotExpressive.glb");
    let server = TestServer::start(ServerConfig::default()).await;
    let info = server
        .client
        .upload_rig("robot", super::upload_bytes(&path))
        .await
        .expect("upload");
    let sk = info.skeleton.expect("skeleton");
    assert_eq!(sk.clips_with_joints.len(), 14);
    let doc = RefDoc::load(&path);
    let got = frames(&server, &heads("robot", &[("Wave", 20), ("Running", 9)])).await;
    let diag = {
        let (lo, hi) = (info.bbox.min, info.bbox.max);
        DVec3::from(hi.map(f64::from)).distance(DVec3::from(lo.map(f64::from)))
    };
    for ((clip, f), (p, _)) in [("Wave", 20), ("Running", 9)].iter().zip(&got) {
        let want: Vec<DVec3> = doc
            .pose(&doc.locals_at(clip, f64::from(*f) / 30.0))
            .into_iter()
            .flat_map(|p| p.positions)
            .collect();
        let d = max_distance(p, &want);
        assert!(d <= 1e-5 * diag, "{clip} {f}: off by {d:e}");
    }
    // q16 frames quantize in a box that holds the pose.
    let mut req = heads("robot", &[("Wave", 20)]);
    req.output.format = Format::Q16;
    let (resp, _) = server
        .client
        .crowd_frame(&req, Encoding::Bincode)
        .await
        .expect("q16 frame");
    let b = &resp.buffers[0];
    let q = b.quantization.expect("box");
    let back = positions_f32(Format::Q16, b);
    for (i, (a, w)) in back.iter().zip(&got[0].0).enumerate() {
        assert!(
            (a - w).abs() <= q.max_error[i % 3],
            "component {i}: {a} vs {w}"
        );
    }
    server.stop().await;
}
