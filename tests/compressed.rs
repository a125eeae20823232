//! Compressed and quantized glTF: real rigs from `../shared/data` written back out twice from
//! the same arrays — once plain (f32, uncompressed) and once the way gltfpack ships them:
//! `KHR_mesh_quantization` (u16 positions and i16 morph deltas as plain integers, dequantized by
//! the node transform; octahedral i8 normals) inside `EXT_meshopt_compression` buffer views
//! (attribute streams with the octahedral and exponential filters, triangle-coded indices, a
//! fallback buffer with no data), encoded with the encode side of the `meshopt` crate. Both
//! import; every frame of a clip evaluates to the same vertices within the error the
//! quantization allows, computed per frame from the steps and the weights. Then the
//! compressed streams are truncated, bit-flipped and given absurd sizes: each is an import
//! error (the server's 4xx), never a panic, and never an allocation the budget did not allow.

use std::sync::Arc;

use crowdmorph::engine::{BlendJob, Engine, OutputSpec};
use crowdmorph::import::gltf::rig_from_slice;
use crowdmorph::import::{ImportError, ImportOptions, load_path};
use crowdmorph::rig::Rig;
use serde_json::{Value, json};

use crate::util::builder::{Builder, Component};
use crate::util::{Rng, data_dir};

/// Baking rate of the test clip.
const FPS: f32 = 10.0;

/// Mantissa bits of the exponential filter for key values and normal deltas.
const EXP_BITS: i32 = 20;

/// What a written file looks like: its bytes and the quantization step of its positions.
struct Written {
    glb: Vec<u8>,
    /// Position (and delta) step in rig units; 0 for the plain file.
    step: f32,
    /// Compressed streams: (buffer view index, mode) for the fuzzing below.
    streams: Vec<(usize, &'static str)>,
}

/// Key times and key-major weights (one per target) of a deterministic clip.
fn clip_keys(targets: usize) -> (Vec<f32>, Vec<f32>) {
    let mut rng = Rng(0xC0FFEE);
    let times: Vec<f32> = (0..6).map(|k| k as f32 * 0.4).collect();
    let values = (0..times.len() * targets)
        .map(|_| {
            if rng.below(3) == 0 {
                0.0
            } else {
                rng.f64() as f32
            }
        })
        .collect();
    (times, values)
}

/// Appends `encoded` to the BIN buffer and adds a view that decompresses to `count × stride`
/// bytes, laid out in the fallback buffer (buffer 1) at `*fallback`.
#[allow(clippy::too_many_arguments)]
fn compressed_view(
    b: &mut Builder,
    fallback: &mut usize,
    encoded: &[u8],
    stride: usize,
    count: usize,
    mode: &str,
    filter: Option<&str>,
    vertex_stride: bool,
) -> usize {
    let at = b.add_buffer_data(encoded);
    let len = stride * count;
    let mut ext = json!({
        "buffer": 0, "byteOffset": at, "byteLength": encoded.len(),
        "byteStride": stride, "count": count, "mode": mode,
    });
    if let Some(f) = filter {
        ext["filter"] = json!(f);
    }
    let mut view = json!({
        "buffer": 1, "byteOffset": *fallback, "byteLength": len,
        "extensions": { "EXT_meshopt_compression": ext },
    });
    if vertex_stride {
        view["byteStride"] = json!(stride);
    }
    *fallback += len.div_ceil(4) * 4;
    let views = b.json_mut()["bufferViews"].as_array_mut().unwrap();
    views.push(view);
    views.len() - 1
}

/// Writes `rig` (its primitives in rig space, its target names, one clip from
/// [`clip_keys`]) as a GLB: plain f32 when `compress` is false, else quantized and compressed.
fn write(rig: &Rig, compress: bool) -> Written {
    let mut b = Builder::new();
    let bbox = rig.bbox();
    let extent = (bbox.max - bbox.min).max_element();
    let step = if compress { extent / 65535.0 } else { 0.0 };
    let names: Vec<&str> = rig.target_names();
    assert_eq!(
        names.len(),
        rig.targets.len(),
        "test rigs have one channel per name"
    );
    let mut fallback = 0usize;
    let mut streams = Vec::new();
    let mut nodes = Vec::new();
    for p in rig.primitives.iter() {
        let n = p.positions.len();
        // Dense deltas per target, in target order (zeros where the rig stores none).
        let dense = |t: usize, normals: bool| -> Option<Vec<[f32; 3]>> {
            let mut d = vec![[0.0f32; 3]; n];
            let st = p.targets.iter().find(|s| s.target as usize == t);
            let any_normals = p.targets.iter().any(|s| s.normals.is_some());
            if normals && !any_normals {
                return None;
            }
            if let Some(st) = st {
                let src = if normals {
                    st.normals.as_ref().map(|v| &v[..])
                } else {
                    Some(&st.positions[..])
                };
                if let Some(src) = src {
                    for (&v, x) in st.vertices.iter().zip(src) {
                        d[v as usize] = x.to_array();
                    }
                }
            }
            Some(d)
        };
        let mut prim = json!({ "attributes": {} });
        let mut targets = Vec::new();
        if !compress {
            let pos: Vec<[f32; 3]> = p.positions.iter().map(|v| v.to_array()).collect();
            prim["attributes"]["POSITION"] = json!(b.accessor_vec3(&pos));
            let nrm: Vec<[f32; 3]> = p.normals.iter().map(|v| v.to_array()).collect();
            prim["attributes"]["NORMAL"] = json!(b.accessor_vec3(&nrm));
            prim["indices"] = json!(b.indices_u32(&p.indices));
            for t in 0..names.len() {
                let mut tj = json!({ "POSITION": b.accessor_vec3(&dense(t, false).unwrap()) });
                if let Some(dn) = dense(t, true) {
                    tj["NORMAL"] = json!(b.accessor_vec3(&dn));
                }
                targets.push(tj);
            }
        } else {
            // Positions: u16 steps from the box corner (the node transform dequantizes).
            let q: Vec<[u16; 4]> = p
                .positions
                .iter()
                .map(|v| {
                    let s = (*v - bbox.min) / step;
                    [
                        s.x.round() as u16,
                        s.y.round() as u16,
                        s.z.round() as u16,
                        0,
                    ]
                })
                .collect();
            let enc = meshopt::encode_vertex_buffer(&q).unwrap();
            let view = compressed_view(&mut b, &mut fallback, &enc, 8, n, "ATTRIBUTES", None, true);
            streams.push((view, "ATTRIBUTES"));
            let (mut lo, mut hi) = ([u16::MAX; 3], [0u16; 3]);
            for e in &q {
                for c in 0..3 {
                    lo[c] = lo[c].min(e[c]);
                    hi[c] = hi[c].max(e[c]);
                }
            }
            prim["attributes"]["POSITION"] = json!(b.accessor_json(json!({
                "bufferView": view, "componentType": Component::U16.code(), "count": n,
                "type": "VEC3", "min": lo, "max": hi,
            })));
            // Normals: octahedral, 8-bit normalized.
            let normals: Vec<[f32; 4]> = p.normals.iter().map(|v| [v.x, v.y, v.z, 0.0]).collect();
            let oct = meshopt::encode_filter_oct::<i8>(&normals, 8);
            let enc = meshopt::encode_vertex_buffer(&oct).unwrap();
            let view = compressed_view(
                &mut b,
                &mut fallback,
                &enc,
                4,
                n,
                "ATTRIBUTES",
                Some("OCTAHEDRAL"),
                true,
            );
            streams.push((view, "ATTRIBUTES"));
            prim["attributes"]["NORMAL"] = json!(b.accessor_json(json!({
                "bufferView": view, "componentType": Component::I8.code(), "count": n,
                "type": "VEC3", "normalized": true,
            })));
            // Indices: the triangle codec.
            let enc = meshopt::encode_index_buffer(&p.indices, n).unwrap();
            let view = compressed_view(
                &mut b,
                &mut fallback,
                &enc,
                4,
                p.indices.len(),
                "TRIANGLES",
                None,
                false,
            );
            streams.push((view, "TRIANGLES"));
            prim["indices"] = json!(b.accessor_json(json!({
                "bufferView": view, "componentType": Component::U32.code(),
                "count": p.indices.len(), "type": "SCALAR",
            })));
            for t in 0..names.len() {
                // Position deltas: i16 steps, the same scale as the positions.
                let d: Vec<[i16; 4]> = dense(t, false)
                    .unwrap()
                    .iter()
                    .map(|x| {
                        let q = x.map(|c| (c / step).round());
                        assert!(q.iter().all(|c| c.abs() < 32767.0), "delta fits in i16");
                        [q[0] as i16, q[1] as i16, q[2] as i16, 0]
                    })
                    .collect();
                let enc = meshopt::encode_vertex_buffer(&d).unwrap();
                let view =
                    compressed_view(&mut b, &mut fallback, &enc, 8, n, "ATTRIBUTES", None, true);
                streams.push((view, "ATTRIBUTES"));
                let mut tj = json!({ "POSITION": b.accessor_json(json!({
                    "bufferView": view, "componentType": Component::I16.code(), "count": n,
                    "type": "VEC3",
                })) });
                // Normal deltas: floats through the exponential filter.
                if let Some(dn) = dense(t, true) {
                    let e =
                        meshopt::encode_filter_exp(&dn, EXP_BITS, meshopt::EncodeExpMode::Separate);
                    let enc = meshopt::encode_vertex_buffer(&e).unwrap();
                    let view = compressed_view(
                        &mut b,
                        &mut fallback,
                        &enc,
                        12,
                        n,
                        "ATTRIBUTES",
                        Some("EXPONENTIAL"),
                        true,
                    );
                    streams.push((view, "ATTRIBUTES"));
                    tj["NORMAL"] = json!(b.accessor_json(json!({
                        "bufferView": view, "componentType": Component::F32.code(),
                        "count": n, "type": "VEC3",
                    })));
                }
                targets.push(tj);
            }
        }
        prim["targets"] = json!(targets);
        let mesh = b.mesh(vec![prim], Some(&names));
        let node = b.node(Some(mesh));
        if compress {
            b.json_mut()["nodes"][node]["translation"] = json!(bbox.min.to_array());
            b.json_mut()["nodes"][node]["scale"] = json!([step, step, step]);
        }
        nodes.push(node);
    }
    b.scene(&nodes);
    // One clip on every node: times exact, values through the exponential filter.
    let (times, values) = clip_keys(names.len());
    let (input, output) = if compress {
        let t: Vec<[f32; 1]> = times.iter().map(|&x| [x]).collect();
        let enc = meshopt::encode_vertex_buffer(&t).unwrap();
        let tv = compressed_view(
            &mut b,
            &mut fallback,
            &enc,
            4,
            t.len(),
            "ATTRIBUTES",
            None,
            false,
        );
        let v: Vec<[f32; 1]> = values.iter().map(|&x| [x]).collect();
        let e = meshopt::encode_filter_exp(&v, EXP_BITS, meshopt::EncodeExpMode::Separate);
        let enc = meshopt::encode_vertex_buffer(&e).unwrap();
        let vv = compressed_view(
            &mut b,
            &mut fallback,
            &enc,
            4,
            v.len(),
            "ATTRIBUTES",
            Some("EXPONENTIAL"),
            false,
        );
        streams.push((tv, "ATTRIBUTES"));
        streams.push((vv, "ATTRIBUTES"));
        let last = times.last().copied().unwrap_or(0.0);
        (
            b.accessor_json(
                json!({ "bufferView": tv, "componentType": 5126, "count": t.len(),
                "type": "SCALAR", "min": [0.0], "max": [last] }),
            ),
            b.accessor_json(
                json!({ "bufferView": vv, "componentType": 5126, "count": v.len(),
                "type": "SCALAR" }),
            ),
        )
    } else {
        (b.accessor_scalar(&times), b.accessor_scalar(&values))
    };
    let samplers: Vec<Value> = vec![json!({ "input": input, "output": output })];
    let channels: Vec<Value> = nodes
        .iter()
        .map(|&n| json!({ "sampler": 0, "target": { "node": n, "path": "weights" } }))
        .collect();
    b.json_mut()["animations"]
        .as_array_mut()
        .unwrap()
        .push(json!({ "name": "play", "samplers": samplers, "channels": channels }));
    if compress {
        let bin_len = b.bin().len();
        b.json_mut()["buffers"] = json!([
            { "byteLength": bin_len },
            { "byteLength": fallback,
              "extensions": { "EXT_meshopt_compression": { "fallback": true } } },
        ]);
        b.json_mut()["extensionsUsed"] =
            json!(["EXT_meshopt_compression", "KHR_mesh_quantization"]);
        b.json_mut()["extensionsRequired"] =
            json!(["EXT_meshopt_compression", "KHR_mesh_quantization"]);
    }
    Written {
        glb: b.to_glb(),
        step,
        streams,
    }
}

fn import(bytes: &[u8]) -> Result<Rig, ImportError> {
    rig_from_slice(
        bytes,
        &ImportOptions {
            fps: FPS,
            max_decoded_bytes: 2 << 30,
            ..ImportOptions::default()
        },
    )
}

/// Every frame of the rig's only clip on the CPU engine.
fn frames(rig: &Rig) -> Vec<Vec<f32>> {
    let engine = Engine::cpu();
    let prepared = engine.prepare(Arc::new(rig.clone())).unwrap();
    let jobs: Vec<BlendJob> = (0..rig.clips[0].frames)
        .map(|f| BlendJob::frame(0, f, 0))
        .collect();
    let out = engine
        .evaluate(&prepared, &jobs, OutputSpec::default())
        .unwrap()
        .output;
    (0..jobs.len()).map(|j| out.job_positions(j)).collect()
}

/// Imports both files of a real rig and compares every frame of the clip.
fn check_rig(path: &std::path::Path) {
    let original = load_path(path, &ImportOptions::default()).unwrap();
    let plain = write(&original, false);
    let packed = write(&original, true);
    assert!(
        packed.glb.len() * 3 < plain.glb.len(),
        "{}: compressed {} bytes vs plain {}",
        original.name,
        packed.glb.len(),
        plain.glb.len()
    );
    let a = import(&plain.glb).unwrap();
    let b = import(&packed.glb).unwrap();
    assert_eq!(a.targets, b.targets);
    assert_eq!(a.vertex_count(), b.vertex_count());
    assert_eq!(a.clips[0].frames, b.clips[0].frames);
    let step = f64::from(packed.step);
    let diag = f64::from(a.bbox().diagonal());
    // Largest delta component of each target: what a weight error costs.
    let mut max_delta = vec![0f64; a.targets.len()];
    for p in a.primitives.iter() {
        for t in &p.targets {
            for d in &t.positions {
                let m = f64::from(d.abs().max_element());
                max_delta[t.target as usize] = max_delta[t.target as usize].max(m);
            }
        }
    }
    let weight_rel = 2f64.powi(-(EXP_BITS - 1));
    let (fa, fb) = (frames(&a), frames(&b));
    let mut worst = 0f64;
    for (f, (x, y)) in fa.iter().zip(&fb).enumerate() {
        let w: Vec<f64> = (0..a.targets.len())
            .map(|t| f64::from(a.clips[0].weight(t, f as u32)))
            .collect();
        // Rounding to the step: half a step for the position and for each weighted delta;
        // the weights' exponential encoding; f32 blending.
        let tol = 0.5 * step * (1.0 + w.iter().map(|x| x.abs()).sum::<f64>()) * 1.0001
            + w.iter()
                .zip(&max_delta)
                .map(|(w, d)| w.abs() * weight_rel * d)
                .sum::<f64>()
            + 1e-5 * diag;
        let d = x
            .iter()
            .zip(y)
            .map(|(p, q)| (f64::from(*p) - f64::from(*q)).abs())
            .fold(0.0, f64::max);
        assert!(
            d <= tol,
            "{} frame {f}: compressed differs by {d:e} > {tol:e} (step {step:e})",
            a.name
        );
        worst = worst.max(d / step);
    }
    eprintln!(
        "{}: {} → {} bytes, worst difference {worst:.2} steps",
        original.name,
        plain.glb.len(),
        packed.glb.len()
    );
}

#[test]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (or CROWDMORPH_TEST_DATA)"
)]
fn quantized_meshopt_ict_facekit_evaluates_like_the_plain_file() {
    check_rig(&data_dir().join("ict-facekit/ict_facekit_53.glb"));
}

#[test]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (or CROWDMORPH_TEST_DATA)"
)]
fn quantized_meshopt_morph_stress_test_with_normal_deltas_evaluates_like_the_plain_file() {
    check_rig(&data_dir().join("khronos/MorphStressTest/glTF/MorphStressTest.gltf"));
}

/// The compressed file of a small real rig, for the fuzzing below.
fn small_packed() -> (Written, Value, Vec<u8>) {
    let original = load_path(
        &data_dir().join("khronos/MorphStressTest/glTF/MorphStressTest.gltf"),
        &ImportOptions::default(),
    )
    .unwrap();
    let w = write(&original, true);
    let (json, bin) = split(&w.glb);
    (w, json, bin)
}

/// The JSON and BIN chunks of a GLB the tests wrote.
fn split(glb: &[u8]) -> (Value, Vec<u8>) {
    let jl = u32::from_le_bytes(glb[12..16].try_into().unwrap()) as usize;
    let json = serde_json::from_slice(&glb[20..20 + jl]).unwrap();
    let at = 20 + jl;
    let bl = u32::from_le_bytes(glb[at..at + 4].try_into().unwrap()) as usize;
    (json, glb[at + 8..at + 8 + bl].to_vec())
}

fn glb(json: &Value, bin: &[u8]) -> Vec<u8> {
    crate::util::builder::glb_from_parts(&serde_json::to_vec(json).unwrap(), Some(bin))
}

#[test]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (or CROWDMORPH_TEST_DATA)"
)]
fn truncated_and_corrupted_compressed_streams_are_errors_not_panics() {
    let (w, json, bin) = small_packed();
    import(&glb(&json, &bin)).expect("the untouched file imports");
    // Every stream cut short: nothing to decode from (the tail block is missing).
    for &(view, mode) in &w.streams {
        for keep in [0.0, 0.5, 0.9] {
            let mut j = json.clone();
            let ext = &mut j["bufferViews"][view]["extensions"]["EXT_meshopt_compression"];
            let len = ext["byteLength"].as_u64().unwrap();
            let cut = ((len as f64 * keep) as u64).min(len - 1);
            ext["byteLength"] = json!(cut);
            let e = import(&glb(&j, &bin)).expect_err("a truncated stream is refused");
            assert!(
                matches!(e, ImportError::Invalid(_)),
                "view {view} ({mode}) cut to {cut}: {e}"
            );
            assert!(e.to_string().contains("does not decode"), "{e}");
        }
    }
    // Bit flips anywhere in the compressed bytes: an error or a rig that passes every check,
    // never a panic. (The decoders tolerate garbage; what they make is validated after.)
    let mut rng = Rng(7);
    let mut refused = 0;
    for _ in 0..300 {
        let mut b = bin.clone();
        let at = rng.below(b.len());
        b[at] ^= 1 << rng.below(8);
        match import(&glb(&json, &b)) {
            Ok(rig) => rig.validate().expect("an accepted rig is valid"),
            Err(_) => refused += 1,
        }
    }
    eprintln!("{refused} of 300 bit-flipped files refused");
    // Streams past the end of their buffer, an unknown filter, a stride the filter cannot
    // take, a view length that does not match count × stride: each a 400-class error.
    let (view, _) = w.streams[0];
    for (field, value) in [
        ("byteOffset", json!(bin.len())),
        ("byteLength", json!(bin.len() + 1)),
        ("filter", json!("WAVELET")),
        ("byteStride", json!(6)),
        ("count", json!(3)),
        ("mode", json!("POINTS")),
        ("buffer", json!(9)),
    ] {
        let mut j = json.clone();
        j["bufferViews"][view]["extensions"]["EXT_meshopt_compression"][field] = value.clone();
        let e = import(&glb(&j, &bin)).expect_err("refused");
        assert!(
            matches!(e, ImportError::Invalid(_)),
            "{field} = {value}: {e:?}"
        );
    }
    // A tiny file that declares a gigabyte of decompressed data that an accessor reads is
    // refused by the budget before anything is allocated (by the import's estimate, which
    // counts the views its accessors read, or by the decode's own charge).
    let mut j = json.clone();
    let ext = &mut j["bufferViews"][view]["extensions"]["EXT_meshopt_compression"];
    ext["count"] = json!(1u64 << 27);
    j["bufferViews"][view]["byteLength"] = json!(8u64 << 27);
    let small = ImportOptions {
        max_decoded_bytes: 64 << 20,
        ..ImportOptions::default()
    };
    match rig_from_slice(&glb(&j, &bin), &small) {
        Err(ImportError::Budget(_)) => {}
        other => panic!("expected a budget refusal, got {other:?}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (or CROWDMORPH_TEST_DATA)"
)]
async fn the_server_takes_compressed_rigs_and_answers_bad_streams_with_4xx() {
    use crowdmorph::server::ServerConfig;
    use crowdmorph_client::ClientError;
    let (_, json, bin) = small_packed();
    let server = crate::server::TestServer::start(ServerConfig {
        max_upload_memory: 256 << 20,
        ..ServerConfig::default()
    })
    .await;
    let c = &server.client;
    let info = c
        .upload_rig("packed", bytes::Bytes::from(glb(&json, &bin)))
        .await
        .unwrap();
    assert!(info.vertices > 0);
    let mut j = json.clone();
    let view = j["bufferViews"]
        .as_array()
        .unwrap()
        .iter()
        .position(|v| v.get("extensions").is_some())
        .unwrap();
    j["bufferViews"][view]["extensions"]["EXT_meshopt_compression"]["byteLength"] = json!(5);
    match c.upload_rig("cut", bytes::Bytes::from(glb(&j, &bin))).await {
        Err(ClientError::Api { status, code, .. }) => {
            assert_eq!((status, code.as_str()), (400, "invalid_rig"));
        }
        other => panic!("expected 400, got {other:?}"),
    }
    let ext = &mut j["bufferViews"][view]["extensions"]["EXT_meshopt_compression"];
    ext["count"] = json!(1u64 << 28);
    ext["byteStride"] = json!(8);
    j["bufferViews"][view]["byteLength"] = json!(8u64 << 28);
    match c
        .upload_rig("huge", bytes::Bytes::from(glb(&j, &bin)))
        .await
    {
        Err(ClientError::Api { status, .. }) => assert_eq!(status, 413),
        other => panic!("expected 413, got {other:?}"),
    }
    server.stop().await;
}

#[test]
fn texture_only_required_extensions_load_and_draco_says_how_to_convert() {
    // A rig whose only texture is KTX2 (KHR_texture_basisu, required): it loads.
    let mut b = crate::util::builder::triangle_rig();
    let j = b.json_mut();
    j["images"] = json!([{ "uri": "data:image/ktx2;base64,AAAA", "mimeType": "image/ktx2" }]);
    j["textures"] = json!([{ "extensions": { "KHR_texture_basisu": { "source": 0 } } }]);
    j["materials"] = json!([{ "pbrMetallicRoughness": {
        "baseColorTexture": { "index": 0 }, "baseColorFactor": [1.0, 0.5, 0.5, 1.0] } }]);
    j["meshes"][0]["primitives"][0]["material"] = json!(0);
    j["extensionsUsed"] = json!(["KHR_texture_basisu"]);
    j["extensionsRequired"] = json!(["KHR_texture_basisu"]);
    let rig = import(&b.to_glb()).expect("a required texture extension does not stop a rig");
    assert_eq!(rig.primitives[0].base_color, [1.0, 0.5, 0.5, 1.0]);
    // Drawn with its factors, and the answer says why the texture is not.
    let a = rig.appearance.as_deref().expect("the material is kept");
    assert_eq!(a.materials[0].base_color_factor, [1.0, 0.5, 0.5, 1.0]);
    assert_eq!(a.textures[0].image, None);
    assert!(a.images.is_empty());
    assert!(
        rig.import_notes
            .iter()
            .any(|n| n.contains("texture 0") && n.contains("KTX2")),
        "{:?}",
        rig.import_notes
    );
    let report = crowdmorph::import::gltf::extension_report(&b.to_glb()).unwrap();
    assert_eq!(report.len(), 1);
    assert_eq!(
        (
            report[0].name.as_str(),
            report[0].handling,
            report[0].required
        ),
        ("KHR_texture_basisu", "ignored", true)
    );
    // Several required texture extensions (one listed twice), checked in one walk: it loads,
    // and one of them also on a node is refused by name.
    let mut several = crate::util::builder::triangle_rig();
    *several.json_mut() = b.json_mut().clone();
    let j = several.json_mut();
    // (On a texture no material draws: the KTX2 bytes are not a WebP image, and a drawn one
    // would be a 400 naming the image.)
    if let Some(t) = j["textures"].as_array_mut() {
        t.push(json!({ "extensions": { "EXT_texture_webp": { "source": 0 } } }));
    }
    j["extensionsUsed"] = json!(["KHR_texture_basisu", "EXT_texture_webp"]);
    j["extensionsRequired"] = json!(["EXT_texture_webp", "KHR_texture_basisu", "EXT_texture_webp"]);
    import(&several.to_glb()).expect("required texture-only extensions do not stop a rig");
    several.json_mut()["nodes"][0]["extensions"] = json!({ "EXT_texture_webp": {} });
    match import(&several.to_glb()) {
        Err(ImportError::UnsupportedExtension(e)) => assert_eq!(e, "EXT_texture_webp"),
        other => panic!("expected the node's extension refused, got {other:?}"),
    }
    // The same name on a mesh primitive is not texture-only: refused.
    b.json_mut()["meshes"][0]["primitives"][0]["extensions"] = json!({ "KHR_texture_basisu": {} });
    assert!(matches!(
        import(&b.to_glb()),
        Err(ImportError::UnsupportedExtension(_))
    ));
    // Draco: refused, and the message says how to convert the file.
    let mut b = crate::util::builder::triangle_rig();
    b.json_mut()["extensionsUsed"] = json!(["KHR_draco_mesh_compression"]);
    b.json_mut()["extensionsRequired"] = json!(["KHR_draco_mesh_compression"]);
    let e = import(&b.to_glb()).unwrap_err().to_string();
    assert!(
        e.contains("KHR_draco_mesh_compression")
            && e.contains("gltf-transform")
            && e.contains("gltfpack"),
        "{e}"
    );
}

#[test]
fn inspect_lists_the_extensions_and_the_names_with_several_channels() {
    // The per-node test file with a required KTX2 texture, run through the real binary.
    let (json, bin) = split(&crate::channels::file(crate::channels::Case::HeadOnly(
        "LINEAR",
    )));
    let mut j = json;
    j["images"] = json!([{ "uri": "data:image/ktx2;base64,AAAA", "mimeType": "image/ktx2" }]);
    j["textures"] = json!([{ "extensions": { "KHR_texture_basisu": { "source": 0 } } }]);
    j["extensionsUsed"] = json!(["KHR_texture_basisu"]);
    j["extensionsRequired"] = json!(["KHR_texture_basisu"]);
    let dir = std::env::temp_dir().join(format!("crowdmorph-inspect-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("split.glb");
    std::fs::write(&path, glb(&j, &bin)).unwrap();
    let run = |json: bool| {
        let mut c = std::process::Command::new(env!("CARGO_BIN_EXE_crowdmorph"));
        c.arg("inspect").arg(&path).args(["--backend", "cpu"]);
        if json {
            c.arg("--json");
        }
        let out = c.env("RUST_LOG", "warn").output().unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8(out.stdout).unwrap()
    };
    let text = run(false);
    assert!(text.contains("jaw ×3, blink ×3"), "{text}");
    assert!(text.contains("KHR_texture_basisu"), "{text}");
    assert!(text.contains("ignored (required)"), "{text}");
    assert!(text.contains("jaw#3"), "{text}");
    let s: Value = serde_json::from_str(&run(true)).unwrap();
    assert_eq!(s["extensions"][0]["name"], "KHR_texture_basisu");
    assert_eq!(s["extensions"][0]["handling"], "ignored");
    assert_eq!(s["split_targets"], json!([["jaw", 3], ["blink", 3]]));
    let _ = std::fs::remove_dir_all(&dir);
}

/// Adds to `json` a compressed buffer view that no accessor reads and that declares a
/// gigabyte once decompressed (its stream: `stream_at..stream_at + stream_len` of buffer 0),
/// laid out in a fallback buffer of its own.
fn add_unread_huge_view(json: &mut Value, stream_at: u64, stream_len: u64) {
    let huge = 1u64 << 30;
    let buffers = json["buffers"].as_array_mut().unwrap();
    buffers.push(json!({ "byteLength": huge,
        "extensions": { "EXT_meshopt_compression": { "fallback": true } } }));
    let fallback = buffers.len() - 1;
    json["bufferViews"].as_array_mut().unwrap().push(json!({
        "buffer": fallback, "byteOffset": 0, "byteLength": huge,
        "extensions": { "EXT_meshopt_compression": {
            "buffer": 0, "byteOffset": stream_at, "byteLength": stream_len,
            "byteStride": 16, "count": huge / 16, "mode": "ATTRIBUTES" } },
    }));
    json["extensionsUsed"] = json!(["EXT_meshopt_compression"]);
}

#[test]
fn import_never_decodes_a_compressed_view_no_accessor_reads() {
    // The triangle rig, plain, with an extra compressed view nothing reads: a gigabyte on its
    // header, garbage as a stream. A 64 MiB budget imports it, the same rig as without it.
    let b = crate::util::builder::triangle_rig();
    let plain = import(&b.to_glb()).unwrap();
    let (mut j, bin) = split(&b.to_glb());
    j["buffers"] = json!([{ "byteLength": bin.len() }]);
    add_unread_huge_view(&mut j, 0, 8);
    let small = ImportOptions {
        fps: FPS,
        max_decoded_bytes: 64 << 20,
        ..ImportOptions::default()
    };
    let rig = rig_from_slice(&glb(&j, &bin), &small).expect("an unread view is not decoded");
    assert_eq!(rig, plain);
    // Its header is still checked: a stream past the end of its buffer is refused.
    j["bufferViews"].as_array_mut().unwrap().last_mut().unwrap()["extensions"]["EXT_meshopt_compression"]
        ["byteOffset"] = json!(bin.len());
    assert!(matches!(
        rig_from_slice(&glb(&j, &bin), &small),
        Err(ImportError::Invalid(_))
    ));
}

#[test]
#[cfg_attr(
    not(crowdmorph_test_data),
    ignore = "needs ../shared/data (or CROWDMORPH_TEST_DATA)"
)]
fn import_of_a_real_compressed_rig_decodes_only_the_views_it_reads() {
    // MorphStressTest written the way gltfpack ships it, plus a gigabyte view nothing reads
    // (over a real stream): the same rig as the untouched file, within a 64 MiB budget.
    let (w, json, bin) = small_packed();
    let untouched = import(&glb(&json, &bin)).unwrap();
    let (view, _) = w.streams[0];
    let ext = &json["bufferViews"][view]["extensions"]["EXT_meshopt_compression"];
    let (at, len) = (
        ext["byteOffset"].as_u64().unwrap(),
        ext["byteLength"].as_u64().unwrap(),
    );
    let mut j = json.clone();
    add_unread_huge_view(&mut j, at, len);
    j["extensionsUsed"] = json!(["EXT_meshopt_compression", "KHR_mesh_quantization"]);
    let small = ImportOptions {
        fps: FPS,
        max_decoded_bytes: 64 << 20,
        ..ImportOptions::default()
    };
    let rig = rig_from_slice(&glb(&j, &bin), &small).expect("imports within the budget");
    assert_eq!(rig, untouched);
}
