//! Hostile and broken input: every importer must answer with the specific typed error, with a
//! message that names the problem, without panicking and without trying to allocate what a
//! tiny file merely declares.
//!
//! Covered: truncated and malformed GLB containers, accessors and buffer views out of bounds,
//! absurd declared counts (with and without a buffer view, the latter stopped by the decode
//! budget), meshes whose primitives disagree on their target count, NaN and infinity in
//! positions, target deltas and animations, empty meshes, dangling references, unsupported
//! required extensions, external buffers, malformed JSON, broken CSV and JSON clip sources, and
//! property-based fuzzing (random bytes, single-byte corruptions and truncations of a valid
//! file) that must never panic.

use std::panic::{AssertUnwindSafe, catch_unwind};
use std::time::{Duration, Instant};

use crowdmorph::budget::BudgetError;
use crowdmorph::embedded::default_rig;
use crowdmorph::import::clips::ClipOptions;
use crowdmorph::import::gltf::rig_from_slice;
use crowdmorph::import::{ImportError, ImportOptions, clip_from_csv, clip_from_json};
use crowdmorph::rig::{Rig, RigError};
use proptest::prelude::*;
use proptest::test_runner::{Config as ProptestConfig, RngSeed};
use serde_json::json;

use crate::util::builder::{
    Builder, Component, TRIANGLE, glb_from_parts, triangle_rig, triangle_targets,
};

/// Longest any single import below may take; far more than a correct import of these tiny
/// files needs, far less than allocating or filling gigabytes would take.
const QUICK: Duration = Duration::from_secs(5);

/// Imports `bytes` with `options`, failing the test (rather than crashing it) on a panic or a
/// slow answer.
fn load_with(bytes: &[u8], options: &ImportOptions) -> Result<Rig, ImportError> {
    let start = Instant::now();
    let result = catch_unwind(AssertUnwindSafe(|| rig_from_slice(bytes, options)));
    let elapsed = start.elapsed();
    let result = result.unwrap_or_else(|_| panic!("rig_from_slice panicked"));
    assert!(elapsed < QUICK, "import took {elapsed:?}");
    result
}

/// Imports `bytes` with default options (no base dir, 2 GiB decode budget).
fn load(bytes: &[u8]) -> Result<Rig, ImportError> {
    load_with(bytes, &ImportOptions::default())
}

/// The error of an import that must fail.
fn error(result: Result<Rig, ImportError>) -> ImportError {
    match result {
        Ok(rig) => panic!(
            "import succeeded ({} vertices, {} targets) but must fail",
            rig.vertex_count(),
            rig.targets.len()
        ),
        Err(e) => e,
    }
}

/// Asserts that the error's message contains `needle` (case-insensitive).
fn assert_mentions(e: &ImportError, needle: &str) {
    let message = e.to_string();
    assert!(
        message.to_lowercase().contains(&needle.to_lowercase()),
        "message {message:?} does not mention {needle:?}"
    );
}

/// A small but feature-rich valid document: two primitives sharing two targets (one of them a
/// sparse accessor), u16 indices, mesh default weights, and LINEAR, CUBICSPLINE and normalized
/// u8 STEP weight animations. It is the seed of the corruption tests.
fn rich_builder() -> Builder {
    let mut b = Builder::new();
    let p0 = b.primitive(&TRIANGLE, Some(&[0, 1, 2]), &triangle_targets());
    let quad = [
        [2.0, 0.0, 0.0],
        [3.0, 0.0, 0.0],
        [3.0, 1.0, 0.0],
        [2.0, 1.0, 0.0],
    ];
    let pos = b.accessor_vec3(&quad);
    let idx = b.indices_u16(&[0, 1, 2, 0, 2, 3]);
    let t0 = b.accessor_sparse_vec3(4, &[1, 3], &[[0.0, 0.0, 1.0], [0.0, 0.5, 0.0]]);
    let t1 = b.accessor_vec3(&[[0.0, 0.0, 0.25]; 4]);
    let p1 = json!({
        "attributes": { "POSITION": pos },
        "indices": idx,
        "targets": [{ "POSITION": t0 }, { "POSITION": t1 }],
    });
    let mesh = b.mesh(vec![p0, p1], Some(&["jawOpen", "eyeBlink_L"]));
    b.set_mesh_weights(mesh, &[0.0, 0.1]);
    let node = b.node(Some(mesh));
    b.scene(&[node]);
    b.animation_weights(
        "lin",
        node,
        &[0.0, 0.5, 1.0],
        &[0.0, 1.0, 1.0, 0.0, 0.5, 0.5],
        "LINEAR",
    );
    #[rustfmt::skip]
    let cubic = [
        0.0, 0.0,  0.0, 1.0,  1.0, -1.0,
        -1.0, 0.5, 1.0, 0.0,  0.0, 0.0,
    ];
    b.animation_weights("cubic", node, &[0.25, 1.0], &cubic, "CUBICSPLINE");
    b.animation_weights_normalized(
        "quantized",
        node,
        &[0.0, 1.0],
        Component::U8,
        &[0, 255, 128, 64],
        "STEP",
    );
    b
}

#[test]
fn the_seed_documents_are_valid() {
    // The corruption tests below only mean something if the uncorrupted file imports.
    let b = rich_builder();
    for bytes in [b.to_glb(), b.to_gltf_data_uri()] {
        let rig = load(&bytes).expect("the seed document imports");
        assert_eq!(rig.vertex_count(), 7);
        assert_eq!(rig.targets, ["jawOpen", "eyeBlink_L"]);
        assert_eq!(rig.clips.len(), 3);
    }
    load(&triangle_rig().to_glb()).expect("the triangle imports");
}

#[test]
fn truncated_glb_is_a_glb_error() {
    let glb = rich_builder().to_glb();
    let n = glb.len();
    // An empty file is not a GLB at all.
    let e = error(load(&[]));
    assert!(matches!(e, ImportError::Glb(_)), "{e:?}");
    assert_mentions(&e, "magic");
    // Cuts after the header: the header's total length no longer matches.
    for cut in [12, 20, n / 2, n - 1] {
        let e = error(load(&glb[..cut]));
        assert!(matches!(e, ImportError::Glb(_)), "cut at {cut}: {e:?}");
        assert_mentions(&e, "truncated");
    }
}

#[test]
fn glb_cut_inside_its_header_is_reported_as_truncated() {
    // These files start with the right magic, so the problem is their length, not the magic.
    let glb = rich_builder().to_glb();
    for cut in [4, 5, 8, 11] {
        let e = error(load(&glb[..cut]));
        assert!(matches!(e, ImportError::Glb(_)), "cut at {cut}: {e:?}");
        let message = e.to_string();
        assert!(
            message.contains("truncated") || message.contains("too short"),
            "cut at {cut}: {message:?} does not say the file is too short"
        );
    }
}

#[test]
fn wrong_magic_and_unsupported_glb_version() {
    let glb = rich_builder().to_glb();
    let mut bad = glb.clone();
    bad[3] = b'X';
    let e = error(load(&bad));
    assert!(matches!(e, ImportError::Glb(_)), "{e:?}");
    assert_mentions(&e, "magic");

    for version in [1u32, 3] {
        let mut bad = glb.clone();
        bad[4..8].copy_from_slice(&version.to_le_bytes());
        let e = error(load(&bad));
        assert!(matches!(e, ImportError::Glb(_)), "{e:?}");
        assert_mentions(&e, &format!("version {version}"));
    }
}

#[test]
fn glb_chunk_problems() {
    let b = triangle_rig();
    let glb = b.to_glb();
    // A JSON chunk that claims more bytes than the file has.
    let mut bad = glb.clone();
    bad[12..16].copy_from_slice(&(glb.len() as u32).to_le_bytes());
    let e = error(load(&bad));
    assert!(matches!(e, ImportError::Glb(_)), "{e:?}");
    assert_mentions(&e, "chunk");

    // A first chunk that is not JSON.
    let mut bad = glb.clone();
    bad[16..20].copy_from_slice(b"BIN\0");
    let e = error(load(&bad));
    assert!(matches!(e, ImportError::Glb(_)), "{e:?}");
    assert_mentions(&e, "out of order");

    // A buffer without uri refers to the BIN chunk, which is missing.
    let json = serde_json::to_vec(&b.document(None)).expect("serialise");
    let e = error(load(&glb_from_parts(&json, None)));
    assert!(matches!(e, ImportError::Buffer { index: 0, .. }), "{e:?}");
    assert_mentions(&e, "BIN chunk");
}

#[test]
fn buffer_view_past_the_end_of_its_buffer() {
    let mut b = triangle_rig();
    // Accessor 0 is the triangle's POSITION, on view 0.
    let end = b.bin().len();
    b.buffer_view_mut(0)["byteOffset"] = json!(end);
    let e = error(load(&b.to_glb()));
    assert!(matches!(e, ImportError::Accessor { index: 0, .. }), "{e:?}");
    assert_mentions(&e, "past the");

    let mut b = triangle_rig();
    b.buffer_view_mut(0)["byteLength"] = json!(u32::MAX);
    let e = error(load(&b.to_glb()));
    assert!(matches!(e, ImportError::Accessor { index: 0, .. }), "{e:?}");
    assert_mentions(&e, "past the");
}

#[test]
fn accessor_offset_past_its_view() {
    let mut b = triangle_rig();
    b.accessor_mut(0)["byteOffset"] = json!(64);
    let e = error(load(&b.to_glb()));
    assert!(matches!(e, ImportError::Accessor { index: 0, .. }), "{e:?}");
    assert_mentions(&e, "ends at");
}

#[test]
fn buffer_shorter_than_declared() {
    let mut b = triangle_rig();
    let declared = b.bin().len() + 100;
    b.json_mut()["buffers"] = json!([{ "byteLength": declared }]);
    let e = error(load(&b.to_glb()));
    assert!(matches!(e, ImportError::Buffer { index: 0, .. }), "{e:?}");
    assert_mentions(&e, &format!("declares {declared} bytes"));
}

#[test]
fn huge_count_on_a_position_accessor_with_a_view_is_an_accessor_error() {
    let mut b = triangle_rig();
    b.accessor_mut(0)["count"] = json!(1u64 << 31);
    let e = error(load(&b.to_glb()));
    assert!(matches!(e, ImportError::Accessor { index: 0, .. }), "{e:?}");
    assert_mentions(&e, "buffer view 0 ends at");
}

#[test]
fn huge_sparse_only_accessor_is_stopped_by_the_decode_budget() {
    // A sparse accessor without a buffer view is all zeros but one element: nothing in the file
    // bounds its count, only the decode budget does.
    let mut b = Builder::new();
    let pos = b.accessor_sparse_vec3(60_000_000, &[0], &[[1.0, 0.0, 0.0]]);
    let mesh = b.mesh(vec![json!({ "attributes": { "POSITION": pos } })], None);
    let node = b.node(Some(mesh));
    b.scene(&[node]);
    let options = ImportOptions::default();
    let e = error(load_with(&b.to_glb(), &options));
    match e {
        ImportError::Budget(BudgetError::TooLarge {
            needed,
            limit,
            flag,
            ..
        }) => {
            assert_eq!(limit, options.max_decoded_bytes as u64);
            assert_eq!(limit, 1 << 30);
            assert_eq!(flag, "--max-upload-memory");
            // Positions and normals of 60 M vertices, at least.
            assert!(needed >= 60_000_000 * 24, "needed {needed}");
        }
        other => panic!("expected a budget refusal, got {other:?}"),
    }
    // Past the engines' vertex limit, the count alone refuses it.
    let mut b = Builder::new();
    let pos = b.accessor_sparse_vec3(1 << 31, &[0], &[[1.0, 0.0, 0.0]]);
    let mesh = b.mesh(vec![json!({ "attributes": { "POSITION": pos } })], None);
    let node = b.node(Some(mesh));
    b.scene(&[node]);
    let e = error(load_with(&b.to_glb(), &options));
    assert!(
        matches!(e, ImportError::Rig(RigError::TooLarge(_))),
        "{e:?}"
    );
    assert_mentions(&e, "vertices");

    // The budget is the caller's: a tiny one refuses even a triangle.
    let options = ImportOptions {
        max_decoded_bytes: 16,
        ..Default::default()
    };
    let e = error(load_with(&triangle_rig().to_glb(), &options));
    assert!(
        matches!(
            e,
            ImportError::Budget(BudgetError::TooLarge { limit: 16, .. })
        ),
        "{e:?}"
    );
    assert_mentions(&e, "limit of 16 bytes");
}

#[test]
fn primitives_of_one_mesh_disagree_on_their_target_count() {
    let mut b = Builder::new();
    let p0 = b.primitive(&TRIANGLE, None, &triangle_targets());
    let p1 = b.primitive(&TRIANGLE, None, &triangle_targets()[..1]);
    let mesh = b.mesh(vec![p0, p1], None);
    b.mesh_mut(mesh)["name"] = json!("face");
    let node = b.node(Some(mesh));
    b.scene(&[node]);
    let e = error(load(&b.to_glb()));
    match &e {
        ImportError::Mesh { mesh, problem } => {
            assert_eq!(mesh, "face");
            assert!(
                problem.contains("different target counts (2 and 1)"),
                "{problem}"
            );
        }
        other => panic!("expected a Mesh error, got {other:?}"),
    }
}

/// A one-triangle rig (mesh 0 on node 0) with the given positions and target deltas.
fn triangle_with(positions: &[[f32; 3]], targets: &[Vec<[f32; 3]>]) -> Builder {
    let mut b = Builder::new();
    let mesh = b.mesh_with_targets(positions, Some(&[0, 1, 2]), targets, None);
    let node = b.node(Some(mesh));
    b.scene(&[node]);
    b
}

/// Asserts a `RigError::NonFinite` about an array whose description contains `what`.
fn assert_non_finite(e: &ImportError, what: &str) {
    match e {
        ImportError::Rig(RigError::NonFinite { what: w }) => {
            assert!(w.contains(what), "{w:?} should name {what:?}");
        }
        other => panic!("expected RigError::NonFinite, got {other:?}"),
    }
    assert_mentions(e, "non-finite");
}

#[test]
fn non_finite_positions_are_rejected() {
    for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        let mut p = TRIANGLE;
        p[1][0] = bad;
        let e = error(load(&triangle_with(&p, &triangle_targets()).to_glb()));
        assert_non_finite(&e, "positions");
    }
}

/// Imports a triangle whose target `target` has `delta` at vertex `vertex`, and asserts that
/// the import fails with a `NonFinite` error about position deltas.
fn assert_delta_rejected(target: usize, vertex: usize, delta: [f32; 3]) {
    let mut t = triangle_targets();
    t[target][vertex] = delta;
    match load(&triangle_with(&TRIANGLE, &t).to_glb()) {
        Ok(rig) => {
            let stored: Vec<_> = rig.primitives[0]
                .targets
                .iter()
                .map(|t| (t.target, t.vertices.clone(), t.positions.clone()))
                .collect();
            panic!(
                "a delta of {delta:?} at vertex {vertex} of target {target} was accepted; \
                 stored (target, vertices, deltas): {stored:?}"
            );
        }
        Err(e) => assert_non_finite(&e, "position deltas"),
    }
}

#[test]
fn infinite_target_deltas_are_rejected() {
    for bad in [f32::INFINITY, f32::NEG_INFINITY] {
        assert_delta_rejected(1, 2, [0.0, bad, 2.0]);
        assert_delta_rejected(0, 0, [bad, 0.0, 0.0]);
    }
}

#[test]
fn nan_target_deltas_are_rejected() {
    // NaN next to a large component, NaN next to zeros, and all NaN: a NaN delta is as broken
    // as an infinite one, whatever the other components hold.
    for delta in [
        [f32::NAN, 1.0, 0.0],
        [f32::NAN, 0.0, 0.0],
        [f32::NAN, f32::NAN, f32::NAN],
    ] {
        assert_delta_rejected(0, 0, delta);
    }
}

/// Asserts an `ImportError::Animation` about the animation `name` whose problem mentions
/// non-finite values.
fn assert_animation_non_finite(e: &ImportError, name: &str) {
    match e {
        ImportError::Animation { animation, problem } => {
            assert_eq!(animation, name);
            assert!(problem.contains("non-finite"), "{problem}");
        }
        other => panic!("expected an Animation error, got {other:?}"),
    }
}

#[test]
fn non_finite_animation_values_and_times_are_rejected() {
    for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        let mut b = triangle_rig();
        b.animation_weights("out", 0, &[0.0, 1.0], &[0.0, 1.0, bad, 0.0], "LINEAR");
        assert_animation_non_finite(&error(load(&b.to_glb())), "out");

        let mut b = triangle_rig();
        b.animation_weights("times", 0, &[0.0, bad], &[0.0, 1.0, 1.0, 0.0], "LINEAR");
        assert_animation_non_finite(&error(load(&b.to_glb())), "times");

        // Cubic tangents are outputs too.
        let mut cubic = [0.0; 12];
        cubic[4] = bad;
        let mut b = triangle_rig();
        b.animation_weights("tangent", 0, &[0.0, 1.0], &cubic, "CUBICSPLINE");
        assert_animation_non_finite(&error(load(&b.to_glb())), "tangent");
    }
}

#[test]
fn a_mesh_without_vertices_is_no_rig() {
    let mut b = Builder::new();
    // Something must be in the buffer for its one buffer to exist.
    b.add_buffer_data(&[0; 4]);
    let mesh = b.mesh_with_targets(&[], None, &[], None);
    let node = b.node(Some(mesh));
    b.scene(&[node]);
    let e = error(load(&b.to_glb()));
    assert!(matches!(e, ImportError::Rig(RigError::NoVertices)), "{e:?}");
    assert_mentions(&e, "no vertices");

    // A file without any mesh is no rig either.
    let mut b = Builder::new();
    let node = b.node(None);
    b.scene(&[node]);
    let e = error(load(&b.to_gltf_data_uri()));
    assert!(matches!(e, ImportError::Rig(RigError::NoVertices)), "{e:?}");
}

#[test]
fn index_out_of_range() {
    let mut b = Builder::new();
    let mesh = b.mesh_with_targets(&TRIANGLE, Some(&[0, 1, 5]), &triangle_targets(), None);
    let node = b.node(Some(mesh));
    b.scene(&[node]);
    let e = error(load(&b.to_glb()));
    // Accessor 0 is POSITION, 1 the indices.
    assert!(matches!(e, ImportError::Accessor { index: 1, .. }), "{e:?}");
    assert_mentions(&e, "index 5 out of range for 3 vertices");
}

#[test]
fn dangling_references_are_errors_not_panics() {
    // POSITION attribute.
    let mut b = triangle_rig();
    b.mesh_mut(0)["primitives"][0]["attributes"]["POSITION"] = json!(99);
    let e = error(load(&b.to_glb()));
    assert!(matches!(e, ImportError::Invalid(_)), "{e:?}");
    assert_mentions(&e, "accessor 99");

    // Morph target attribute.
    let mut b = triangle_rig();
    b.mesh_mut(0)["primitives"][0]["targets"][1]["POSITION"] = json!(99);
    let e = error(load(&b.to_glb()));
    assert!(matches!(e, ImportError::Invalid(_)), "{e:?}");
    assert_mentions(&e, "accessor 99");

    // Indices.
    let mut b = triangle_rig();
    b.mesh_mut(0)["primitives"][0]["indices"] = json!(99);
    let e = error(load(&b.to_glb()));
    assert!(matches!(e, ImportError::Invalid(_)), "{e:?}");
    assert_mentions(&e, "indices");

    // A node's mesh.
    let mut b = triangle_rig();
    b.json_mut()["nodes"][0]["mesh"] = json!(7);
    let e = error(load(&b.to_glb()));
    assert!(matches!(e, ImportError::Invalid(_)), "{e:?}");
    assert_mentions(&e, "mesh");

    // An animation sampler's input.
    let mut b = triangle_rig();
    b.animation_weights("a", 0, &[0.0, 1.0], &[0.0, 1.0, 1.0, 0.0], "LINEAR");
    b.json_mut()["animations"][0]["samplers"][0]["input"] = json!(99);
    let e = error(load(&b.to_glb()));
    assert!(matches!(e, ImportError::Invalid(_)), "{e:?}");
    assert_mentions(&e, "input");
}

#[test]
fn dangling_animation_target_node_is_an_error_not_a_panic() {
    let mut b = triangle_rig();
    b.animation_weights("a", 0, &[0.0, 1.0], &[0.0, 1.0, 1.0, 0.0], "LINEAR");
    b.json_mut()["animations"][0]["channels"][0]["target"]["node"] = json!(5);
    let e = error(load(&b.to_glb()));
    assert!(matches!(e, ImportError::Invalid(_)), "{e:?}");
    assert_mentions(&e, "node");
}

#[test]
fn unknown_animation_channel_path_is_not_a_panic() {
    // An animated property outside the glTF enum (e.g. from an extension this reader does not
    // know). Refusing the document and ignoring the channel are both acceptable; panicking is
    // not, and a channel that is not `weights` must not become a clip.
    let mut b = triangle_rig();
    b.animation_weights("a", 0, &[0.0, 1.0], &[0.0, 1.0, 1.0, 0.0], "LINEAR");
    b.json_mut()["animations"][0]["channels"][0]["target"]["path"] = json!("colour");
    match load(&b.to_glb()) {
        Ok(rig) => assert!(rig.clips.is_empty(), "clips {:?}", rig.clip_index("a")),
        Err(e) => assert!(
            matches!(e, ImportError::Invalid(_) | ImportError::Animation { .. }),
            "{e:?}"
        ),
    }
}

#[test]
fn unsupported_required_extension() {
    let mut b = triangle_rig();
    b.json_mut()["extensionsUsed"] = json!(["KHR_draco_mesh_compression"]);
    b.json_mut()["extensionsRequired"] = json!(["KHR_draco_mesh_compression"]);
    let e = error(load(&b.to_glb()));
    match &e {
        ImportError::UnsupportedExtension(name) => {
            assert_eq!(name, "KHR_draco_mesh_compression");
        }
        other => panic!("expected UnsupportedExtension, got {other:?}"),
    }
    assert_mentions(&e, "KHR_draco_mesh_compression");

    // Quantized meshes are read, so requiring that extension is fine.
    let mut b = triangle_rig();
    b.json_mut()["extensionsUsed"] = json!(["KHR_mesh_quantization"]);
    b.json_mut()["extensionsRequired"] = json!(["KHR_mesh_quantization"]);
    load(&b.to_glb()).expect("KHR_mesh_quantization is supported");
}

#[test]
fn external_buffer_needs_a_base_dir_and_stays_inside_it() {
    let b = triangle_rig();
    let gltf = b.to_gltf_external("triangle.bin");
    let e = error(load(&gltf));
    assert!(matches!(e, ImportError::Buffer { index: 0, .. }), "{e:?}");
    assert_mentions(&e, "external file \"triangle.bin\"");

    // With a base dir holding the file, the same document imports.
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos());
    let dir = std::env::temp_dir().join(format!(
        "crowdmorph-test-external-{}-{nanos}",
        std::process::id()
    ));
    std::fs::create_dir_all(&dir).expect("create temp dir");
    std::fs::write(dir.join("triangle.bin"), b.bin()).expect("write buffer");
    let options = ImportOptions {
        base_dir: Some(dir.clone()),
        ..Default::default()
    };
    let loaded = load_with(&gltf, &options);
    // Paths that leave the base dir are refused even when the file exists.
    let escape = load_with(&b.to_gltf_external("../triangle.bin"), &options);
    let _ = std::fs::remove_dir_all(&dir);
    let rig = loaded.expect("imports with a base dir");
    assert_eq!(rig.vertex_count(), 3);
    let e = error(escape);
    assert!(matches!(e, ImportError::Buffer { index: 0, .. }), "{e:?}");
    assert_mentions(&e, "must be relative");
}

#[test]
fn malformed_json() {
    let e = error(load(br#"{"asset": {"version": "2.0"}, "nodes": [}"#));
    assert!(matches!(e, ImportError::Json(_)), "{e:?}");

    // Well-formed JSON of the wrong shape.
    let e = error(load(br#"{"asset": 5}"#));
    assert!(matches!(e, ImportError::Json(_)), "{e:?}");

    // Malformed JSON inside a GLB.
    let e = error(load(&glb_from_parts(br#"{"asset": {"#, None)));
    assert!(matches!(e, ImportError::Json(_)), "{e:?}");

    // Neither GLB nor JSON.
    let e = error(load(b"ply\nformat ascii 1.0\n"));
    assert!(matches!(e, ImportError::Glb(_)), "{e:?}");
    assert_mentions(&e, "not a glTF file");
}

/// Reads a CSV clip onto the embedded rig.
fn csv(
    text: &str,
    options: &ClipOptions,
) -> Result<crowdmorph::import::clips::ClipImport, ImportError> {
    clip_from_csv(&default_rig(), "c", text.as_bytes(), options)
}

/// Asserts a `ClipSource` error whose message contains `needle`.
fn assert_clip_source(e: &ImportError, needle: &str) {
    assert!(matches!(e, ImportError::ClipSource(_)), "{e:?}");
    assert_mentions(e, needle);
}

#[test]
fn csv_ragged_row() {
    let e = csv(
        "jawOpen,eyeBlink_L\n0.1,0.2\n0.3\n",
        &ClipOptions::default(),
    )
    .expect_err("ragged row");
    assert_clip_source(&e, "row 3 has 1 fields, the header has 2");
    let e =
        csv("jawOpen,eyeBlink_L\n0.1,0.2,0.3\n", &ClipOptions::default()).expect_err("long row");
    assert_clip_source(&e, "row 2 has 3 fields");
}

#[test]
fn csv_bad_cells() {
    let e = csv(
        "jawOpen,eyeBlink_L\n0.1,0.2\n0.3,abc\n",
        &ClipOptions::default(),
    )
    .expect_err("non-numeric cell");
    assert_clip_source(&e, "row 3, column \"eyeBlink_L\": \"abc\" is not a number");
    for bad in ["NaN", "inf", "-inf", "1e39"] {
        let e = csv(&format!("jawOpen\n{bad}\n"), &ClipOptions::default())
            .expect_err("non-finite cell");
        assert_clip_source(&e, "is not finite");
    }
    let e = csv("jawOpen,eyeBlink_L\n", &ClipOptions::default()).expect_err("no rows");
    assert_clip_source(&e, "no frames");
}

#[test]
fn csv_unknown_targets() {
    let text = "Timecode,jawOpen,fooBar,tongueOut\n0,0.5,1,1\n1,0.25,1,1\n";
    let e = csv(text, &ClipOptions::default()).expect_err("unknown targets");
    match &e {
        ImportError::UnknownTargets(names) => assert_eq!(names, &["fooBar", "tongueOut"]),
        other => panic!("expected UnknownTargets, got {other:?}"),
    }
    assert_mentions(&e, "\"fooBar\", \"tongueOut\"");

    let options = ClipOptions {
        ignore_unknown: true,
        ..Default::default()
    };
    let rig = default_rig();
    let imported =
        clip_from_csv(&rig, "c", text.as_bytes(), &options).expect("unknown names ignored");
    assert_eq!(*imported.ignored, ["fooBar", "tongueOut"]);
    let jaw = rig.target_id("jawOpen").expect("jawOpen") as usize;
    assert_eq!(imported.clip.weight(jaw, 0), 0.5);
    assert_eq!(imported.clip.weight(jaw, 1), 0.25);
}

/// A header of many unknown names is named in a bounded message: the first few, quoted (each
/// cut to 64 characters, as live weights quote a name), and how many more there are.
#[test]
fn csv_unknown_targets_are_listed_within_a_bounded_message() {
    let n = 20_000;
    let mut header: Vec<String> = (0..n).map(|i| format!("noSuchShape{i:05}")).collect();
    header.push("x".repeat(10_000));
    header.push("jawOpen".into());
    let row = vec!["0"; header.len()].join(",");
    let text = format!("{}\n{row}\n", header.join(","));
    let e = csv(&text, &ClipOptions::default()).expect_err("unknown targets");
    match &e {
        ImportError::UnknownTargets(names) => assert_eq!(names.len(), n + 1),
        other => panic!("expected UnknownTargets, got {other:?}"),
    }
    let message = e.to_string();
    assert!(message.len() < 2_000, "{} bytes", message.len());
    assert!(
        message.contains("\"noSuchShape00000\", \"noSuchShape00001\""),
        "{message}"
    );
    assert!(!message.contains("noSuchShape00016"), "{message}");
    assert!(
        message.ends_with(&format!("and {} more", n + 1 - 16)),
        "{message}"
    );
    // Fewer than the cap: every one, and no count.
    let e = csv(
        &format!(
            "{},jawOpen\n{}\n",
            header[..3].join(","),
            ["0"; 4].join(",")
        ),
        &ClipOptions::default(),
    )
    .expect_err("unknown targets");
    assert!(e.to_string().ends_with("\"noSuchShape00002\""), "{e}");
}

/// Two columns that write one target — the same name twice, or two spellings that match it
/// loosely — are refused naming both, in CSV and JSON alike: one of them would be dropped.
#[test]
fn clip_columns_that_write_one_target_twice_are_refused() {
    let rig = default_rig();
    for (header, a, b) in [
        ("jawOpen,JawOpen", "\"jawOpen\"", "\"JawOpen\""),
        (
            "eyeBlink_L,jawOpen,EyeBlinkLeft",
            "\"eyeBlink_L\"",
            "\"EyeBlinkLeft\"",
        ),
        (
            "Timecode,jawOpen,jawOpen",
            "\"jawOpen\" and \"jawOpen\"",
            "jawOpen",
        ),
    ] {
        let cols = header.split(',').count();
        let text = format!("{header}\n{}\n", vec!["0.5"; cols].join(","));
        let e = csv(&text, &ClipOptions::default()).expect_err(header);
        assert_clip_source(&e, a);
        assert_mentions(&e, b);
        assert_mentions(&e, "both write target");
        // Ignoring unknown names does not let a duplicate through.
        let options = ClipOptions {
            ignore_unknown: true,
            ..Default::default()
        };
        let e = csv(&text, &options).expect_err(header);
        assert_clip_source(&e, b);
        let names: Vec<&str> = header.split(',').filter(|n| *n != "Timecode").collect();
        let json = json!({ "targets": names, "frames": [vec![0.5; names.len()]] });
        let e = clip_from_json(&rig, "j", json.to_string().as_bytes(), &options).expect_err(header);
        assert_clip_source(&e, b);
    }
    // Distinct targets, and an unknown name twice (it writes nothing): accepted.
    let options = ClipOptions {
        ignore_unknown: true,
        ..Default::default()
    };
    let imported = csv("jawOpen,eyeBlink_L,fooBar,fooBar\n0.5,0.25,1,1\n", &options)
        .expect("distinct targets");
    assert_eq!(*imported.ignored, ["fooBar", "fooBar"]);
}

/// A column name with a control character is refused: its loose spelling drops the character,
/// so `jaw\0Open` would otherwise write `jawOpen`.
#[test]
fn clip_column_names_with_control_characters_are_refused() {
    let rig = default_rig();
    for name in ["jaw\u{0}Open", "jaw\u{1}Open", "eye\u{7f}Blink_L"] {
        let text = format!("{name}\n0.5\n");
        let e = csv(&text, &ClipOptions::default()).expect_err(name);
        assert_clip_source(&e, "control character");
        let json = json!({ "targets": [name], "frames": [[0.5]] });
        let e = clip_from_json(
            &rig,
            "j",
            json.to_string().as_bytes(),
            &ClipOptions::default(),
        )
        .expect_err(name);
        assert_clip_source(&e, "control character");
    }
}

#[test]
fn json_clip_problems() {
    let rig = default_rig();
    let e = clip_from_json(
        &rig,
        "j",
        br#"{"targets": ["jawOpen", "eyeBlink_L"], "frames": [[0.1, 0.2], [0.3]]}"#,
        &ClipOptions::default(),
    )
    .expect_err("ragged frame");
    assert_clip_source(&e, "frame 1 has 1 weights, there are 2 targets");

    let text = br#"{"targets": ["jawOpen", "noSuchShape"], "frames": [[0.1, 0.2]]}"#;
    let e = clip_from_json(&rig, "j", text, &ClipOptions::default()).expect_err("unknown");
    match &e {
        ImportError::UnknownTargets(names) => assert_eq!(names, &["noSuchShape"]),
        other => panic!("expected UnknownTargets, got {other:?}"),
    }
    let options = ClipOptions {
        ignore_unknown: true,
        ..Default::default()
    };
    let imported = clip_from_json(&rig, "j", text, &options).expect("unknown names ignored");
    assert_eq!(*imported.ignored, ["noSuchShape"]);

    let e = clip_from_json(
        &rig,
        "j",
        br#"{"targets": ["jawOpen"], "frames": [[nan]]}"#,
        &options,
    )
    .expect_err("not JSON");
    assert_clip_source(&e, "JSON");
}

/// Fuzzing configuration: a fixed seed (deterministic runs), a modest number of cases, and no
/// regression files written into the source tree.
fn fuzz_config() -> ProptestConfig {
    ProptestConfig {
        cases: 256,
        failure_persistence: None,
        rng_seed: RngSeed::Fixed(0x00C0_FFEE),
        ..ProptestConfig::default()
    }
}

/// Imports without letting a panic escape: `Err` carries the fact that it panicked.
fn no_panic(bytes: &[u8]) -> Result<Result<Rig, ImportError>, String> {
    catch_unwind(AssertUnwindSafe(|| {
        rig_from_slice(bytes, &ImportOptions::default())
    }))
    .map_err(|_| format!("panicked on {} bytes", bytes.len()))
}

proptest! {
    #![proptest_config(fuzz_config())]

    #[test]
    fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..512)) {
        prop_assert!(no_panic(&bytes).is_ok());
    }

    #[test]
    fn arbitrary_chunks_after_a_glb_header_never_panic(
        body in proptest::collection::vec(any::<u8>(), 0..256),
        declared in proptest::option::of(any::<u32>()),
    ) {
        let total = declared.unwrap_or(12 + body.len() as u32);
        let mut bytes = b"glTF".to_vec();
        bytes.extend_from_slice(&2u32.to_le_bytes());
        bytes.extend_from_slice(&total.to_le_bytes());
        bytes.extend_from_slice(&body);
        prop_assert!(no_panic(&bytes).is_ok());
    }

    #[test]
    fn single_byte_corruptions_of_a_glb_never_panic(at in any::<prop::sample::Index>(), byte in any::<u8>()) {
        let mut glb = rich_builder().to_glb();
        let i = at.index(glb.len());
        glb[i] = byte;
        prop_assert!(no_panic(&glb).is_ok(), "byte {} set to {:#04x}", i, byte);
    }

    #[test]
    fn single_byte_corruptions_of_a_gltf_never_panic(at in any::<prop::sample::Index>(), byte in any::<u8>()) {
        let mut gltf = rich_builder().to_gltf_data_uri();
        let i = at.index(gltf.len());
        gltf[i] = byte;
        prop_assert!(no_panic(&gltf).is_ok(), "byte {} set to {:#04x}", i, byte);
    }

    #[test]
    fn truncated_glbs_fail_without_panicking(at in any::<prop::sample::Index>()) {
        let glb = rich_builder().to_glb();
        let cut = at.index(glb.len());
        let result = no_panic(&glb[..cut]);
        prop_assert!(result.is_ok(), "cut at {}", cut);
        prop_assert!(matches!(result, Ok(Err(ImportError::Glb(_)))), "cut at {}: {:?}", cut, result.map(|r| r.err()));
    }
}

/// A mesh whose two target names are 512 KiB each, instanced by 100 nodes: a few hundred
/// bytes of JSON per node that once made the importer rebuild (and hold) a megabyte of names
/// per node, uncharged.
fn long_names_many_nodes() -> (Builder, Vec<String>) {
    let names: Vec<String> = ["a", "b"].iter().map(|c| c.repeat(512 << 10)).collect();
    let refs: Vec<&str> = names.iter().map(String::as_str).collect();
    let mut b = Builder::new();
    let mesh = b.mesh_with_targets(
        &TRIANGLE,
        Some(&[0, 1, 2]),
        &triangle_targets(),
        Some(&refs),
    );
    let nodes: Vec<usize> = (0..100).map(|_| b.node(Some(mesh))).collect();
    b.scene(&nodes);
    (b, names)
}

#[test]
fn import_charges_target_names_once_per_mesh_not_per_node() {
    use crowdmorph::budget::Budget;
    use std::sync::Arc;
    let (b, names) = long_names_many_nodes();
    let glb = b.to_glb();
    let text: usize = names.iter().map(String::len).sum();
    let budget = Arc::new(Budget::new(1 << 30, "--max-upload-memory", None));
    let options = ImportOptions {
        budget: Some(budget.clone()),
        ..ImportOptions::default()
    };
    let rig = load_with(&glb, &options).expect("imports");
    assert_eq!(rig.targets, names);
    assert_eq!(rig.primitives.len(), 100);
    // The names are charged (the document's text alone is not what holds them)...
    let peak = budget.peak() as usize;
    assert!(
        peak >= glb.len() + text,
        "peak {peak} < file {} + names {text}",
        glb.len()
    );
    // ... once for the mesh (and once for the rig's channels), not once per node.
    assert!(
        peak < glb.len() + 8 * text,
        "peak {peak}: names charged per node?"
    );
    // A budget that holds the document but not its names twice refuses the import.
    let e = error(load_with(
        &glb,
        &ImportOptions {
            max_decoded_bytes: peak - text,
            ..ImportOptions::default()
        },
    ));
    assert!(matches!(e, ImportError::Budget(_)), "{e:?}");
}
