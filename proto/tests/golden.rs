//! Golden files pin the encodings of the v1 messages, byte for byte, in both JSON and bincode:
//! `tests/golden/<name>.json` and `tests/golden/<name>.bincode`. A change here is a protocol
//! change. Set `CROWDMORPH_BLESS=1` to rewrite the files after an intended change.
//!
//! The same examples are written out field by field in `proto/README.md`.

// A test that meets an unexpected error should fail loudly, which is what unwrap does.
#![allow(clippy::unwrap_used)]

use std::path::PathBuf;

use crowdmorph_proto::wire::{request_from_bincode, response_from_bincode, to_bincode};
use crowdmorph_proto::*;

fn golden(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/golden")
        .join(name)
}

fn check(name: &str, bytes: &[u8]) {
    let path = golden(name);
    if std::env::var_os("CROWDMORPH_BLESS").is_some() {
        std::fs::write(&path, bytes).expect("write golden file");
    }
    let want = std::fs::read(&path).expect("golden file (CROWDMORPH_BLESS=1 writes it)");
    assert_eq!(bytes, &want[..], "{name}: the encoding changed");
}

fn request() -> CrowdFrameRequest {
    CrowdFrameRequest {
        heads: vec![
            Head {
                head: 7,
                rig: "default-head".into(),
                clip: "talk".into(),
                frame: 12,
                lod: 0,
                ..Default::default()
            },
            Head {
                head: 300,
                rig: "default-head".into(),
                clip: "talk".into(),
                frame: -1,
                lod: 2,
                ..Default::default()
            },
        ],
        output: OutputOptions {
            normals: false,
            format: Format::F16,
        },
        wrap: true,
    }
}

fn response() -> CrowdFrameResponse {
    let floats = [0.0f32, 1.0, -2.5, 0.5, 0.25, 3.0];
    CrowdFrameResponse {
        format: Format::F32,
        normals: false,
        buffers: vec![FrameBuffer {
            rig: "tri".into(),
            clip: "wave".into(),
            frame: 1,
            lod: 0,
            vertices: 2,
            quantization: None,
            positions: Blob(floats.iter().flat_map(|f| f.to_le_bytes()).collect()),
            normals: None,
        }],
        heads: vec![
            HeadBuffer { head: 1, buffer: 0 },
            HeadBuffer { head: 2, buffer: 0 },
        ],
        timings: FrameTimings {
            queue_us: 250,
            compute_us: 70000,
            total_us: 71000,
            gpu_us: Some(5),
        },
    }
}

/// Heads with a blend layer, live weights by name and dense live weights.
fn animated_request() -> CrowdFrameRequest {
    CrowdFrameRequest {
        heads: vec![
            Head {
                blend: vec![BlendLayer {
                    clip: "smile".into(),
                    frame: 3,
                    t: 0.25,
                }],
                joints: JointOverrides(vec![(
                    "LeftEye".into(),
                    JointTransform {
                        rotation: Some([0.0, 0.5, 0.0, 1.0]),
                        ..JointTransform::default()
                    },
                )]),
                ..Head::playing(8, "default-head", "talk", 40)
            },
            Head::live(
                9,
                "default-head",
                LiveWeights::Named(vec![("jawOpen".into(), 0.5), ("eyeBlinkLeft".into(), 1.0)]),
            ),
            Head::live(10, "default-head", LiveWeights::Dense(vec![0.0, 0.5])),
        ],
        output: OutputOptions::default(),
        wrap: true,
    }
}

#[test]
fn animated_crowd_frame_request() {
    let r = animated_request();
    let bin = to_bincode(&r).unwrap();
    check("crowd_frame_request_animated.bincode", &bin);
    assert_eq!(request_from_bincode::<CrowdFrameRequest>(&bin).unwrap(), r);
    let json = serde_json::to_vec(&r).unwrap();
    check("crowd_frame_request_animated.json", &json);
    assert_eq!(
        serde_json::from_slice::<CrowdFrameRequest>(&json).unwrap(),
        r
    );
    // Humans leave out what a head does not use.
    let short: CrowdFrameRequest = serde_json::from_str(
        r#"{"heads":[{"head":8,"rig":"default-head","clip":"talk","frame":40,
            "blend":[{"clip":"smile","frame":3,"t":0.25}],
            "joints":{"LeftEye":{"rotation":[0,0.5,0,1]}}},
            {"head":9,"rig":"default-head","weights":{"jawOpen":0.5,"eyeBlinkLeft":1}},
            {"head":10,"rig":"default-head","weights":[0,0.5]}]}"#,
    )
    .unwrap();
    assert_eq!(short, r);
}

fn layered_request() -> CrowdFrameRequest {
    CrowdFrameRequest {
        heads: vec![Head {
            layers: vec![
                Layer {
                    mask: Some(Mask::Named("lower_face".into())),
                    ..Layer::over("smile", 5, 0.5)
                },
                Layer {
                    mode: LayerMode::Additive,
                    reference: Some(0),
                    mask: Some(Mask::Weights(vec![("eyeBlinkLeft".into(), 0.75)])),
                    ..Layer::over("surprise", 20, 1.0)
                },
                Layer {
                    mask: Some(Mask::Names(vec!["jawOpen".into()])),
                    joint_mask: Some(vec!["Head".into()]),
                    ..Layer::over("talk", -1, 0.25)
                },
            ],
            weights: Some(Box::new(LiveWeights::Named(vec![("jawOpen".into(), 0.5)]))),
            weights_mode: LayerMode::Additive,
            clamp: Some([0.0, 1.0]),
            mapping: Some("arkit".into()),
            tolerance: Some(0.002),
            ..Head::playing(11, "default-head", "talk", 3)
        }],
        output: OutputOptions::default(),
        wrap: true,
    }
}

#[test]
fn layered_crowd_frame_request() {
    let r = layered_request();
    let bin = to_bincode(&r).unwrap();
    check("crowd_frame_request_layered.bincode", &bin);
    assert_eq!(request_from_bincode::<CrowdFrameRequest>(&bin).unwrap(), r);
    let json = serde_json::to_vec(&r).unwrap();
    check("crowd_frame_request_layered.json", &json);
    assert_eq!(
        serde_json::from_slice::<CrowdFrameRequest>(&json).unwrap(),
        r
    );
    // Humans leave out the defaults (weight 1, override) and spell masks three ways.
    let short: CrowdFrameRequest = serde_json::from_str(
        r#"{"heads":[{"head":11,"rig":"default-head","clip":"talk","frame":3,
            "layers":[
                {"clip":"smile","frame":5,"weight":0.5,"mask":"lower_face"},
                {"clip":"surprise","frame":20,"mode":"additive","reference":0,
                 "mask":{"eyeBlinkLeft":0.75}},
                {"clip":"talk","frame":-1,"weight":0.25,"mask":["jawOpen"],
                 "joint_mask":["Head"]}],
            "weights":{"jawOpen":0.5},"weights_mode":"additive","clamp":[0,1],
            "mapping":"arkit","tolerance":0.002}]}"#,
    )
    .unwrap();
    assert_eq!(short, r);
}

#[test]
fn crowd_frame_request() {
    let r = request();
    let bin = to_bincode(&r).unwrap();
    check("crowd_frame_request.bincode", &bin);
    assert_eq!(request_from_bincode::<CrowdFrameRequest>(&bin).unwrap(), r);
    let json = serde_json::to_vec(&r).unwrap();
    check("crowd_frame_request.json", &json);
    assert_eq!(
        serde_json::from_slice::<CrowdFrameRequest>(&json).unwrap(),
        r
    );
    // Defaults for humans: output and wrap may be left out, lod too.
    let short: CrowdFrameRequest = serde_json::from_str(
        r#"{"heads":[{"head":7,"rig":"default-head","clip":"talk","frame":12}]}"#,
    )
    .unwrap();
    assert_eq!(short.output, OutputOptions::default());
    assert!(short.wrap);
    assert_eq!(short.heads[0].lod, 0);
}

#[test]
fn crowd_frame_response() {
    let r = response();
    let bin = to_bincode(&r).unwrap();
    check("crowd_frame_response.bincode", &bin);
    assert_eq!(
        response_from_bincode::<CrowdFrameResponse>(&bin).unwrap(),
        r
    );
    let json = serde_json::to_vec(&r).unwrap();
    check("crowd_frame_response.json", &json);
    assert_eq!(
        serde_json::from_slice::<CrowdFrameResponse>(&json).unwrap(),
        r
    );
}

#[test]
fn error_body() {
    let e = ErrorBody {
        error: ErrorDetail {
            code: "unknown_rig".into(),
            message: "no rig \"x\" (rigs: default-head)".into(),
        },
    };
    check("error.json", &serde_json::to_vec(&e).unwrap());
}

#[test]
fn trailing_bytes_and_truncation_are_errors() {
    let mut bin = to_bincode(&request()).unwrap();
    assert!(request_from_bincode::<CrowdFrameRequest>(&bin[..bin.len() - 1]).is_err());
    bin.push(0);
    assert!(matches!(
        request_from_bincode::<CrowdFrameRequest>(&bin),
        Err(wire::WireError::Trailing(1))
    ));
}

/// Pins `value` as `<name>.bincode` and `<name>.json` and checks both decode back to it.
fn pin<T>(name: &str, value: &T)
where
    T: serde::Serialize + serde::de::DeserializeOwned + PartialEq + std::fmt::Debug,
{
    let bin = to_bincode(value).unwrap();
    check(&format!("{name}.bincode"), &bin);
    assert_eq!(&response_from_bincode::<T>(&bin).unwrap(), value, "{name}");
    let json = serde_json::to_vec(value).unwrap();
    check(&format!("{name}.json"), &json);
    assert_eq!(
        &serde_json::from_slice::<T>(&json).unwrap(),
        value,
        "{name}"
    );
}

fn clip_info(name: &str, frames: u32) -> ClipInfo {
    ClipInfo {
        name: name.into(),
        frames,
        fps: 30.0,
    }
}

fn rig_info() -> RigInfo {
    RigInfo {
        id: "tri".into(),
        name: "triangle".into(),
        builtin: false,
        vertices: 3,
        triangles: 1,
        primitives: vec![PrimitiveInfo {
            name: "Mesh/0".into(),
            vertices: 3,
            triangles: 1,
        }],
        targets: vec!["up".into(), "out".into()],
        clips: vec![clip_info("wave", 31)],
        lod: LodInfo {
            method: "combined+pinned".into(),
            status: "ready".into(),
            progress: 1.0,
            error: None,
            order: vec!["out".into(), "up".into()],
            pinned: vec!["out".into()],
            levels: vec![
                LodLevelInfo {
                    shapes: 2,
                    mesh: None,
                    vertices: 3,
                    triangles: 1,
                },
                LodLevelInfo {
                    shapes: 1,
                    mesh: Some(0),
                    vertices: 3,
                    triangles: 1,
                },
            ],
        },
        bbox: Aabb {
            min: [0.0, 0.0, 0.0],
            max: [1.0, 1.0, 0.0],
        },
        memory: Memory {
            host_bytes: 4096,
            device_bytes: 0,
        },
        split_targets: vec![SplitTarget {
            name: "up".into(),
            channels: 2,
        }],
        graphs: vec!["moods".into()],
        skeleton: Some(SkeletonInfo {
            nodes: 3,
            bones: 2,
            skinned_vertices: 2,
            rigid_vertices: 1,
            animated_nodes: vec!["Jaw".into()],
            clips_with_joints: vec!["wave".into()],
            node_names: Vec::new(),
        }),
        import_notes: vec!["2 translation/rotation/scale animation channels target nodes that move no mesh (no skin uses them and no mesh hangs from them): left out".into()],
    }
}

#[test]
fn rig_messages() {
    pin("rig_info", &rig_info());
    pin(
        "rig_list",
        &RigList {
            rigs: vec![rig_info()],
        },
    );
    pin("lod_info", &rig_info().lod);
    pin(
        "clip_upload",
        &ClipUpload {
            rig: "tri".into(),
            added: vec![clip_info("chat", 3)],
            ignored: vec!["tongueOut".into()],
        },
    );
    pin(
        "clip_list",
        &ClipList {
            rig: "tri".into(),
            clips: vec![clip_info("wave", 31), clip_info("chat", 3)],
        },
    );
}

/// The skeleton's node names, added after the layout was pinned, travel in JSON only: a
/// `RigInfo` that has them is, in bincode, byte for byte the pinned message (which reads back
/// without them), and in JSON the pinned message (which has none) reads back as empty.
#[test]
fn skeleton_node_names_travel_in_json_only() {
    let mut named = rig_info();
    if let Some(k) = named.skeleton.as_mut() {
        k.node_names = vec!["Root".into(), "Jaw".into(), "Head".into()];
    }
    let pinned = std::fs::read(golden("rig_info.bincode")).unwrap();
    assert_eq!(to_bincode(&named).unwrap(), pinned);
    assert_eq!(
        response_from_bincode::<RigInfo>(&pinned).unwrap(),
        rig_info()
    );
    let list = RigList {
        rigs: vec![named.clone(), rig_info()],
    };
    let bin = to_bincode(&list).unwrap();
    assert_eq!(
        response_from_bincode::<RigList>(&bin).unwrap().rigs,
        vec![rig_info(), rig_info()]
    );
    let json = serde_json::to_value(&named).unwrap();
    assert_eq!(
        json["skeleton"]["node_names"],
        serde_json::json!(["Root", "Jaw", "Head"])
    );
    assert_eq!(serde_json::from_value::<RigInfo>(json).unwrap(), named);
    let pinned = std::fs::read(golden("rig_info.json")).unwrap();
    assert_eq!(
        serde_json::from_slice::<RigInfo>(&pinned).unwrap(),
        rig_info()
    );
}

#[test]
fn lod_request() {
    let r = LodRequest {
        method: Some("file-order".into()),
        order: None,
        pinned: vec!["eyeBlink_L".into()],
        levels: Some(vec![
            LodLevelRequest {
                shapes: 51,
                mesh: None,
            },
            LodLevelRequest {
                shapes: 12,
                mesh: Some(0),
            },
        ]),
        mesh_fractions: vec![0.25],
    };
    let bin = to_bincode(&r).unwrap();
    check("lod_request.bincode", &bin);
    assert_eq!(request_from_bincode::<LodRequest>(&bin).unwrap(), r);
    let json = serde_json::to_vec(&r).unwrap();
    check("lod_request.json", &json);
    assert_eq!(serde_json::from_slice::<LodRequest>(&json).unwrap(), r);
    // Every field may be left out in JSON.
    assert_eq!(
        serde_json::from_str::<LodRequest>("{}").unwrap(),
        LodRequest::default()
    );
}

#[test]
fn mesh_response() {
    let f32s = |v: &[f32]| Blob(v.iter().flat_map(|f| f.to_le_bytes()).collect());
    pin(
        "mesh_response",
        &MeshResponse {
            rig: "tri".into(),
            lod: 0,
            vertices: 3,
            primitives: vec![MeshPrimitive {
                name: "Mesh/0".into(),
                first_vertex: 0,
                vertices: 3,
                first_index: 0,
                indices: 3,
                material: Some(0),
            }],
            bbox: Aabb {
                min: [0.0, 0.0, 0.0],
                max: [1.0, 1.0, 0.0],
            },
            quantization: Quantization {
                min: [0.0, 0.0, 0.0],
                step: [1.0 / 65535.0, 1.0 / 65535.0, 0.0],
                max_error: [0.5 / 65535.0, 0.5 / 65535.0, 0.0],
            },
            indices: Blob([0u32, 1, 2].iter().flat_map(|i| i.to_le_bytes()).collect()),
            positions: f32s(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]),
            normals: f32s(&[0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0]),
            uvs: f32s(&[0.0, 1.0, 1.0, 1.0, 0.0, 0.0]),
            uvs1: f32s(&[0.5, 0.5, 1.0, 0.5, 0.5, 0.0]),
            colors: f32s(&[1.0, 0.0, 0.0, 1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.5]),
        },
    );
}

#[test]
fn readiness() {
    // Always JSON.
    let r = Readiness {
        status: "degraded".into(),
        backend: "cpu".into(),
        cpu_isa: "avx2".into(),
        degraded_reason: Some("GPU device lost: test".into()),
        rigs: 2,
        skipped_files: vec!["rigs/broken.cmrig: checksum mismatch".into()],
        renderer: Some("llvmpipe (LLVM 15.0.6, 256 bits) (Vulkan)".into()),
    };
    let json = serde_json::to_vec(&r).unwrap();
    check("readiness.json", &json);
    assert_eq!(serde_json::from_slice::<Readiness>(&json).unwrap(), r);
}

fn render_request() -> RenderRequest {
    RenderRequest {
        heads: vec![
            Head {
                head: 1,
                rig: "default-head".into(),
                clip: "talk".into(),
                frame: 12,
                lod: 0,
                ..Default::default()
            },
            Head {
                head: 2,
                rig: "default-head".into(),
                clip: "smile".into(),
                frame: 40,
                lod: 2,
                ..Default::default()
            },
        ],
        wrap: true,
        placements: Some(vec![Placement {
            head: 2,
            position: [0.25, 0.0, -0.5],
            yaw: 30.0,
            scale: 1.5,
        }]),
        camera: Some(CameraSpec {
            fov_y: 35.0,
            far: Some(10.0),
            ..CameraSpec::looking([0.0, 0.1, 1.0], [0.0, 0.0, 0.0])
        }),
        image: Some(ImageOptions {
            width: 320,
            height: 240,
            format: ImageFormat::Jpeg,
            quality: 85,
            background: [255, 128, 0],
        }),
    }
}

#[test]
fn render_request_encodings() {
    let r = render_request();
    let bin = to_bincode(&r).unwrap();
    check("render_request.bincode", &bin);
    assert_eq!(request_from_bincode::<RenderRequest>(&bin).unwrap(), r);
    let json = serde_json::to_vec(&r).unwrap();
    check("render_request.json", &json);
    assert_eq!(serde_json::from_slice::<RenderRequest>(&json).unwrap(), r);
    // A request that lists heads only gets a grid, a front camera and a 640 × 480 PNG.
    let short: RenderRequest = serde_json::from_str(
        r#"{"heads":[{"head":7,"rig":"default-head","clip":"talk","frame":12}]}"#,
    )
    .unwrap();
    assert!(short.wrap);
    assert_eq!(
        (short.placements, short.camera, short.image),
        (None, None, None)
    );
    // Inside the optional objects, everything but positions may be left out too.
    let parts: RenderRequest = serde_json::from_str(
        r#"{"heads":[],"placements":[{"head":1,"position":[1,2,3]}],
            "camera":{"position":[0,0,5],"target":[0,0,0]},"image":{"format":"rgba"}}"#,
    )
    .unwrap();
    let p = parts.placements.unwrap()[0];
    assert_eq!((p.yaw, p.scale), (0.0, 1.0));
    let c = parts.camera.unwrap();
    assert_eq!((c.fov_y, c.near, c.far), (DEFAULT_FOV_Y, None, None));
    let i = parts.image.unwrap();
    assert_eq!(
        i,
        ImageOptions {
            format: ImageFormat::Rgba,
            ..ImageOptions::default()
        }
    );
    // Unknown fields are errors, as in every request.
    assert!(serde_json::from_str::<RenderRequest>(r#"{"heads":[],"image":{"widht":10}}"#).is_err());
}

#[test]
fn a_framing_camera_is_json_only_and_leaves_the_pinned_bincode_alone() {
    // In JSON a frame replaces position and target, which may then be left out.
    let framed: CameraSpec = serde_json::from_str(r#"{"frame":"faces"}"#).unwrap();
    assert_eq!(framed, CameraSpec::framing(CameraFrame::Faces));
    let json = serde_json::to_string(&framed).unwrap();
    assert_eq!(
        json,
        r#"{"position":null,"target":null,"fov_y":30.0,"near":null,"far":null,"frame":"faces"}"#
    );
    assert_eq!(serde_json::from_str::<CameraSpec>(&json).unwrap(), framed);
    let bodies: CameraSpec = serde_json::from_str(r#"{"frame":"bodies","fov_y":20}"#).unwrap();
    assert_eq!(
        (bodies.frame, bodies.fov_y),
        (Some(CameraFrame::Bodies), 20.0)
    );
    assert!(serde_json::from_str::<CameraSpec>(r#"{"frame":"Faces"}"#).is_err());
    assert!(serde_json::from_str::<CameraSpec>(r#"{"frame":"heads"}"#).is_err());
    // Reading keeps what was given; whether a frame and a position go together is the
    // server's check (a 400 invalid_camera), and so is a camera with neither.
    let both: CameraSpec = serde_json::from_str(r#"{"frame":"faces","position":[0,0,5]}"#).unwrap();
    assert_eq!(
        (both.frame, both.position, both.target),
        (Some(CameraFrame::Faces), Some([0.0, 0.0, 5.0]), None)
    );
    let neither: CameraSpec = serde_json::from_str(r#"{"fov_y":40}"#).unwrap();
    assert_eq!(
        (neither.position, neither.target, neither.frame),
        (None, None, None)
    );
    // A camera without a frame writes the JSON it always has.
    let looking = CameraSpec::looking([0.0, 0.0, 5.0], [0.0; 3]);
    assert_eq!(
        serde_json::to_string(&looking).unwrap(),
        r#"{"position":[0.0,0.0,5.0],"target":[0.0,0.0,0.0],"fov_y":30.0,"near":null,"far":null}"#
    );
    // Bincode: the frame takes no bytes and reads as none (the golden render request pins
    // the rest), and a camera without a position cannot be written.
    let bin = to_bincode(&looking).unwrap();
    assert_eq!(
        bin.len(),
        4 * 7 + 2,
        "three floats, three floats, fov, two Nones"
    );
    let with_frame = CameraSpec {
        frame: Some(CameraFrame::Bodies),
        ..looking
    };
    assert_eq!(to_bincode(&with_frame).unwrap(), bin);
    assert_eq!(request_from_bincode::<CameraSpec>(&bin).unwrap(), looking);
    assert!(to_bincode(&framed).is_err());
}

#[test]
fn image_format_names_and_content_types() {
    for (f, name, ct) in [
        (ImageFormat::Png, "png", "image/png"),
        (ImageFormat::Jpeg, "jpeg", "image/jpeg"),
        (ImageFormat::Rgba, "rgba", "application/octet-stream"),
    ] {
        assert_eq!(f.name(), name);
        assert_eq!(f.content_type(), ct);
        assert_eq!(name.parse::<ImageFormat>().unwrap(), f);
        assert_eq!(serde_json::to_string(&f).unwrap(), format!("\"{name}\""));
    }
    assert_eq!("JPG".parse::<ImageFormat>().unwrap(), ImageFormat::Jpeg);
    assert!("gif".parse::<ImageFormat>().is_err());
}

fn session_head(head: u64, clip: &str, offset: i64, x: f32) -> SessionHead {
    SessionHead {
        head,
        rig: "default-head".into(),
        clip: clip.into(),
        offset,
        position: [x, 0.0, -1.5],
        yaw: 15.0,
        scale: 1.0,
        graph: None,
        joints: JointOverrides::default(),
        layers: Vec::new(),
        clamp: None,
        live: None,
        alive: None,
    }
}

#[test]
fn session_messages() {
    let heads = vec![
        session_head(1, "talk", 0, 0.0),
        session_head(2, "talk", 0, 0.5),
        SessionHead {
            layers: vec![Layer {
                mask: Some(Mask::Named("lower_face".into())),
                ..Layer::over("talk", 2, 0.5)
            }],
            clamp: Some([0.0, 1.0]),
            live: Some(LiveSpec {
                hold_ms: 750,
                smoothing: Some(OneEuro {
                    min_cutoff: 1.0,
                    beta: 0.5,
                    d_cutoff: 1.0,
                }),
                mapping: Some("a2f".into()),
                ..LiveSpec::default()
            }),
            ..session_head(3, "smile", -4, 1.0)
        },
        SessionHead {
            graph: Some(GraphPlay {
                name: "moods".into(),
                start: "talk".into(),
                seed: 7,
                script: vec!["smile".into()],
            }),
            joints: JointOverrides(vec![(
                "LeftEye".into(),
                JointTransform {
                    translation: Some([0.0, 0.0, 0.25]),
                    rotation: Some([0.0, 0.5, 0.0, 1.0]),
                    scale: None,
                },
            )]),
            ..session_head(4, "", 0, 1.5)
        },
        // A clip-less head (the neutral), alive: blinks, saccades, a look-at point, a seed.
        SessionHead {
            alive: Some(Alive {
                blink: true,
                saccades: true,
                look_at: Some([0.5, 1.5, 2.0]),
                breathing: false,
                seed: Some(42),
            }),
            ..session_head(5, "", 0, 2.0)
        },
    ];
    pin(
        "session_request",
        &SessionRequest {
            fps: 30.0,
            wrap: true,
            idle_timeout_s: 60,
            heads: heads.clone(),
            alive: Some(Alive {
                blink: true,
                breathing: true,
                ..Alive::default()
            }),
        },
    );
    pin(
        "session_patch",
        &SessionPatch {
            remove: vec![2],
            change: vec![
                HeadChange {
                    head: 3,
                    clip: Some("talk".into()),
                    offset: None,
                    position: None,
                    yaw: Some(-30.0),
                    scale: None,
                    node: None,
                    joints: Some(JointOverrides::rotation("Head", [0.0, 0.5, 0.0, 1.0])),
                    layers: Some(Vec::new()),
                    clamp: Some([-1.0, 2.0]),
                    live: Some(LiveSpec::default()),
                    alive: Some(Alive::default()),
                },
                HeadChange {
                    head: 4,
                    clip: None,
                    offset: None,
                    position: None,
                    yaw: None,
                    scale: None,
                    node: Some("surprise".into()),
                    joints: None,
                    layers: None,
                    clamp: None,
                    live: None,
                    alive: None,
                },
            ],
            add: vec![session_head(9, "idle", 7, 2.0)],
            alive: Some(Alive {
                look_at: Some([3.0, 1.5, -4.0]),
                ..Alive::default()
            }),
        },
    );
    pin(
        "session_info",
        &SessionInfo {
            id: "s1".into(),
            fps: 30.0,
            wrap: true,
            idle_timeout_s: 60,
            tick: 451,
            heads: heads.clone(),
            viewers: 2,
            stats: SessionStats {
                ticks: 450,
                ticks_late: 3,
                ticks_skipped: 1,
                jobs: 900,
                messages_sent: 899,
                messages_dropped: 1,
                bytes_sent: 123_456,
            },
            alive: Some(Alive {
                saccades: true,
                ..Alive::default()
            }),
        },
    );
    // A viewer's second tick: head 3 changed (one buffer), heads 1 and 2 did not.
    let frame = response();
    pin(
        "stream_vertices",
        &StreamMessage::Vertices(TickVertices {
            tick: 452,
            format: frame.format,
            normals: false,
            layout: None,
            buffers: frame.buffers,
            heads: vec![
                HeadBuffer {
                    head: 1,
                    buffer: HEAD_UNCHANGED,
                },
                HeadBuffer {
                    head: 2,
                    buffer: HEAD_UNCHANGED,
                },
                HeadBuffer { head: 3, buffer: 0 },
            ],
            timings: frame.timings,
        }),
    );
    // A layers viewer's tick: head 3's wrinkle weight and clip texture coefficients changed.
    pin(
        "stream_layers",
        &StreamMessage::Layers(TickLayers {
            tick: 452,
            heads: vec![HeadLayers {
                head: 3,
                inputs: vec![0.5, 1.0, -0.25],
            }],
        }),
    );
    // A weights viewer's tick: head 1 unchanged, head 2 a new pose (three weights and one
    // moved node), head 3's rig gone.
    pin("stream_poses", &StreamMessage::Poses(poses_tick()));
    pin(
        "stream_frame",
        &StreamMessage::Frame(TickFrame {
            tick: 9,
            format: ImageFormat::Jpeg,
            width: 2,
            height: 1,
            image: Blob(vec![0xFF, 0xD8, 0xFF, 0xD9]),
        }),
    );
    // The viewer's hello is JSON only (its `lod` is a number or an object).
    let hello: ViewerHello = serde_json::from_str(
        r#"{"output":"vertices","format":"q16","normals":true,
            "camera":{"position":[0,1.6,6],"target":[0,1.6,0],"fov_y":40},
            "lod":{"by_distance":[[0,0],[8,1],[16,3]]}}"#,
    )
    .unwrap();
    assert_eq!(hello.format, Format::Q16);
    assert_eq!(
        hello.lod,
        LodChoice::ByDistance {
            by_distance: vec![[0.0, 0.0], [8.0, 1.0], [16.0, 3.0]]
        }
    );
    let fixed: ViewerUpdate = serde_json::from_str(r#"{"lod":2}"#).unwrap();
    assert_eq!(fixed.lod, Some(LodChoice::Fixed(2)));
    assert!(serde_json::from_str::<ViewerHello>(r#"{"zoom":1}"#).is_err());
    assert_eq!(
        serde_json::from_str::<ViewerHello>("{}").unwrap(),
        ViewerHello::default()
    );
}

/// One pose: weights 0.5, 1, −0.25 (binary16 `00 38`, `00 3c`, `00 b4`) and node 2 turned
/// (rotation 0, 0.6, 0, 0.8) and moved (translation 0, 0.25, 0), at its rest scale.
fn head_pose() -> HeadPose {
    HeadPose {
        weights: Blob(weights_f16_le(&[0.5, 1.0, -0.25])),
        joints: vec![NodePose {
            node: 2,
            rotation: [0.0, 0.6, 0.0, 0.8],
            translation: Some([0.0, 0.25, 0.0]),
            scale: None,
        }],
    }
}

fn poses_tick() -> TickPoses {
    TickPoses {
        tick: 452,
        layout: None,
        poses: vec![head_pose()],
        heads: vec![
            HeadBuffer {
                head: 1,
                buffer: HEAD_UNCHANGED,
            },
            HeadBuffer { head: 2, buffer: 0 },
            HeadBuffer {
                head: 3,
                buffer: HEAD_MISSING,
            },
        ],
        timings: FrameTimings {
            queue_us: 0,
            compute_us: 0,
            total_us: 180,
            gpu_us: None,
        },
    }
}

/// Poses for clients that blend themselves: a crowd frame's answer to `"format": "weights"`,
/// the rig's channels, and the viewer hello that asks for them.
#[test]
fn pose_messages() {
    assert_eq!(
        head_pose().weights.0,
        [0x00, 0x38, 0x00, 0x3c, 0x00, 0xb4],
        "binary16, little-endian"
    );
    assert_eq!(head_pose().weights_f32(), [0.5, 1.0, -0.25]);
    pin(
        "crowd_pose_response",
        &CrowdPoseResponse {
            format: Format::Weights,
            poses: vec![
                head_pose(),
                HeadPose {
                    weights: Blob(weights_f16_le(&[0.0, 0.0, 0.125])),
                    joints: Vec::new(),
                },
            ],
            heads: vec![
                HeadBuffer { head: 7, buffer: 0 },
                HeadBuffer { head: 8, buffer: 1 },
                HeadBuffer { head: 9, buffer: 0 },
            ],
            timings: FrameTimings {
                queue_us: 0,
                compute_us: 0,
                total_us: 95,
                gpu_us: None,
            },
        },
    );
    pin(
        "rig_channels",
        &RigChannels {
            rig: "avatar".into(),
            targets: vec![
                "jawOpen".into(),
                "mouthSmile#1".into(),
                "mouthSmile#2".into(),
            ],
            nodes: vec!["Hips".into(), "Neck".into(), "Head".into()],
        },
    );
    // A request for weights is an ordinary crowd frame request whose format is 4.
    let mut req = request();
    req.output.format = Format::Weights;
    let bin = to_bincode(&req).unwrap();
    assert_eq!(&bin[bin.len() - 3..], [0x00, 0x04, 0x01]);
    assert_eq!(
        serde_json::to_value(req.output).unwrap(),
        serde_json::json!({"normals": false, "format": "weights"})
    );
    let hello: ViewerHello = serde_json::from_str(r#"{"output":"weights"}"#).unwrap();
    assert_eq!(hello.output, ViewerOutput::Weights);
}

#[test]
fn live_messages() {
    let input = LiveInput {
        heads: vec![
            LiveSample {
                head: 3,
                weights: Some(LiveWeights::Named(vec![
                    ("jawOpen".into(), 0.5),
                    ("HeadYaw".into(), -0.25),
                ])),
                joints: JointOverrides::rotation("LeftEye", [0.0, 0.1, 0.0, 1.0]),
                t: Some(12.5),
            },
            LiveSample {
                head: 4,
                weights: Some(LiveWeights::Dense(vec![0.0, 1.0])),
                joints: JointOverrides::default(),
                t: None,
            },
        ],
    };
    pin("live_input", &input);
    pin("live_ack", &LiveAck { accepted: 2 });
    let json: LiveInput = serde_json::from_str(
        r#"{"heads":[{"head":3,"weights":{"jawOpen":0.5,"HeadYaw":-0.25},"joints":{"LeftEye":{"rotation":[0,0.1,0,1]}},"t":12.5},{"head":4,"weights":[0,1]}]}"#,
    )
    .unwrap();
    assert_eq!(json, input);
    let spec: LiveSpec = serde_json::from_str("{}").unwrap();
    assert_eq!(spec, LiveSpec::default());
    assert!(serde_json::from_str::<LiveSpec>(r#"{"hold":1}"#).is_err());
}

#[test]
fn graph_messages() {
    let graph = MotionGraph {
        nodes: vec![
            GraphNode {
                name: "talk".into(),
                clip: "talk".into(),
                frames: None,
            },
            GraphNode {
                name: "smile".into(),
                clip: "smile".into(),
                frames: Some([0, 59]),
            },
        ],
        edges: vec![
            GraphEdge {
                from: "talk".into(),
                to: "smile".into(),
                fade: 10,
                window: None,
            },
            GraphEdge {
                from: "smile".into(),
                to: "talk".into(),
                fade: 8,
                window: Some([20, 40]),
            },
        ],
    };
    pin("motion_graph", &graph);
    pin(
        "graph_list",
        &GraphList {
            graphs: vec![GraphInfo {
                rig: "default-head".into(),
                name: "moods".into(),
                graph,
            }],
        },
    );
}

/// A zlib stream (RFC 1950) of one stored deflate block: what any inflater reads, with bytes
/// that do not depend on a compressor's version.
fn zlib_stored(data: &[u8]) -> Vec<u8> {
    assert!(data.len() < 65_536);
    let mut out = vec![0x78, 0x01, 0x01];
    let n = data.len() as u16;
    out.extend_from_slice(&n.to_le_bytes());
    out.extend_from_slice(&(!n).to_le_bytes());
    out.extend_from_slice(data);
    let (mut a, mut b) = (1u32, 0u32);
    for &x in data {
        a = (a + u32::from(x)) % 65_521;
        b = (b + a) % 65_521;
    }
    out.extend_from_slice(&((b << 16) | a).to_be_bytes());
    out
}

fn q16_bytes(q: &[i16]) -> Blob {
    Blob(q.iter().flat_map(|v| v.to_le_bytes()).collect())
}

#[test]
fn temporal_stream_messages_and_q16r() {
    let box_ = Quantization {
        min: [-1.0, -1.0, -1.0],
        step: [2.0 / 65_535.0; 3],
        max_error: [1.0 / 65_535.0; 3],
    };
    let buffer = |q: &[i16], frame: u32| FrameBuffer {
        rig: "tri".into(),
        clip: "wave".into(),
        frame,
        lod: 0,
        vertices: 2,
        quantization: Some(box_),
        positions: q16_bytes(q),
        normals: None,
    };
    let layout = vec![
        SessionHead {
            head: 1,
            rig: "tri".into(),
            clip: "wave".into(),
            offset: 0,
            position: [0.0; 3],
            yaw: 0.0,
            scale: 1.0,
            graph: None,
            joints: JointOverrides::default(),
            layers: Vec::new(),
            clamp: None,
            live: None,
            alive: None,
        },
        SessionHead {
            head: 2,
            rig: "tri".into(),
            clip: "wave".into(),
            offset: 5,
            position: [1.0, 0.0, 0.0],
            yaw: 0.0,
            scale: 1.0,
            graph: None,
            joints: JointOverrides::default(),
            layers: Vec::new(),
            clamp: None,
            live: None,
            alive: None,
        },
    ];
    let timings = FrameTimings {
        queue_us: 1,
        compute_us: 2,
        total_us: 3,
        gpu_us: None,
    };
    let first_q: [i16; 6] = [0, 100, -100, 32_767, -32_768, 7];
    let other_q: [i16; 6] = [5, 5, 5, 5, 5, 5];
    let next_q: [i16; 6] = [2, 98, -97, -32_768, 32_767, 7];
    // Tick 10: both heads keyframes, in q16.
    let first = StreamMessage::Delta(TickDelta {
        tick: 10,
        format: Format::Q16,
        normals: false,
        layout: Some(layout.clone()),
        residual: vec![false, false],
        buffers: vec![buffer(&first_q, 0), buffer(&other_q, 5)],
        heads: vec![
            HeadBuffer { head: 1, buffer: 0 },
            HeadBuffer { head: 2, buffer: 1 },
        ],
        timings,
    });
    // Tick 11: head 1 as residuals against what it had (wrapping at the ends), head 2 unchanged.
    let mut planes = vec![0u8; 12];
    q16r_encode(&next_q, &first_q, &mut planes);
    assert_eq!(
        planes,
        [4, 3, 6, 2, 1, 0, 0, 0, 0, 0, 0, 0],
        "differences 2, −2, 3, 1 and −1 (both wrapping), 0; zigzag; low bytes then high"
    );
    // The same coding on the little-endian bytes a session's buffers travel as.
    assert_eq!(
        q16r_encode_le(&q16_bytes(&next_q).0, &q16_bytes(&first_q).0),
        planes
    );
    let second = StreamMessage::Delta(TickDelta {
        tick: 11,
        format: Format::Q16,
        normals: false,
        layout: None,
        residual: vec![true],
        buffers: vec![FrameBuffer {
            positions: Blob(planes),
            ..buffer(&[], 1)
        }],
        heads: vec![
            HeadBuffer { head: 1, buffer: 0 },
            HeadBuffer {
                head: 2,
                buffer: HEAD_UNCHANGED,
            },
        ],
        timings,
    });
    pin("stream_delta_keyframes", &first);
    pin("stream_delta_residuals", &second);
    // The second tick packed: a zlib stream of its bincode.
    let inner = to_bincode(&second).unwrap();
    let packed = StreamMessage::Packed(PackedMessage {
        encoding: MessageEncoding::Deflate,
        length: inner.len() as u64,
        data: Blob(zlib_stored(&inner)),
    });
    pin("stream_packed_deflate", &packed);

    let mut state = StreamState::new();
    state.receive(&to_bincode(&first).unwrap()).unwrap();
    let got = state.receive(&to_bincode(&packed).unwrap()).unwrap();
    assert_eq!(
        got,
        Received::Vertices(Applied {
            tick: 11,
            changed: 1,
            from_residuals: 1,
            buffers: 1
        })
    );
    assert_eq!(state.buffer(1).unwrap().positions.to_i16(), next_q);
    assert_eq!(state.buffer(1).unwrap().frame, 1);
    assert_eq!(state.buffer(2).unwrap().positions.to_i16(), other_q);
    // Residuals for a head that never had a buffer, or a packed message that lies about its
    // length, are errors that leave the state as it was.
    let mut fresh = StreamState::new();
    let lost = StreamMessage::Delta(TickDelta {
        layout: Some(layout),
        heads: vec![
            HeadBuffer { head: 1, buffer: 0 },
            HeadBuffer {
                head: 2,
                buffer: HEAD_MISSING,
            },
        ],
        ..match &second {
            StreamMessage::Delta(d) => d.clone(),
            _ => unreachable!(),
        }
    });
    assert!(fresh.apply(lost).is_err());
    assert_eq!(fresh.tick(), 0);
    let liar = StreamMessage::Packed(PackedMessage {
        encoding: MessageEncoding::Deflate,
        length: inner.len() as u64 - 1,
        data: Blob(zlib_stored(&inner)),
    });
    assert!(state.receive(&to_bincode(&liar).unwrap()).is_err());
    assert_eq!(state.tick(), 11);

    // A q16r crowd frame: one head's positions as residual planes against its reference.
    let q16r = CrowdFrameResponse {
        format: Format::Q16R,
        normals: false,
        buffers: vec![FrameBuffer {
            positions: match &second {
                StreamMessage::Delta(d) => d.buffers[0].positions.clone(),
                _ => unreachable!(),
            },
            ..buffer(&[], 1)
        }],
        heads: vec![HeadBuffer { head: 1, buffer: 0 }],
        timings,
    };
    pin("crowd_frame_response_q16r", &q16r);
    assert_eq!(
        q16r_decode(&q16r.buffers[0].positions.0, &first_q).unwrap(),
        next_q
    );
}

/// Every stream message pinned above, skimmed (`crowdmorph_proto::skim`, what load generators
/// and benchmarks read of a stream) as it decodes: tick, heads, changed heads, buffers,
/// timings; a packed one is skimmed through its unpacked bytes.
#[cfg(feature = "unpack")]
#[test]
fn every_golden_stream_message_skims_as_it_decodes() {
    use crowdmorph_proto::skim::{TickSummary, skim};
    fn summary(m: &StreamMessage) -> TickSummary {
        let count = |heads: &[HeadBuffer]| {
            heads
                .iter()
                .filter(|h| h.buffer != HEAD_MISSING && h.buffer != HEAD_UNCHANGED)
                .count() as u64
        };
        match m {
            StreamMessage::Vertices(v) => TickSummary {
                tick: v.tick,
                heads: v.heads.len() as u64,
                changed: count(&v.heads),
                buffers: v.buffers.len() as u64,
                timings: Some(v.timings),
            },
            StreamMessage::Delta(d) => TickSummary {
                tick: d.tick,
                heads: d.heads.len() as u64,
                changed: count(&d.heads),
                buffers: d.buffers.len() as u64,
                timings: Some(d.timings),
            },
            StreamMessage::Frame(f) => TickSummary {
                tick: f.tick,
                ..TickSummary::default()
            },
            StreamMessage::Layers(l) => TickSummary {
                tick: l.tick,
                ..TickSummary::default()
            },
            StreamMessage::Poses(p) => TickSummary {
                tick: p.tick,
                heads: p.heads.len() as u64,
                changed: count(&p.heads),
                buffers: p.poses.len() as u64,
                timings: Some(p.timings),
            },
            StreamMessage::Packed(p) => {
                summary(&response_from_bincode::<StreamMessage>(&p.unpack().unwrap()).unwrap())
            }
        }
    }
    let mut skimmed = 0;
    for name in [
        "stream_vertices",
        "stream_frame",
        "stream_layers",
        "stream_poses",
        "stream_delta_keyframes",
        "stream_delta_residuals",
        "stream_packed_deflate",
    ] {
        let bytes = std::fs::read(golden(&format!("{name}.bincode"))).unwrap();
        let message: StreamMessage = response_from_bincode(&bytes).unwrap();
        assert_eq!(skim(&bytes).unwrap(), summary(&message), "{name}");
        // A message cut short is refused, not misread.
        assert!(skim(&bytes[..bytes.len() - 1]).is_err(), "{name}");
        skimmed += 1;
    }
    assert_eq!(skimmed, 7);
}

#[test]
fn mapping_request() {
    let m = Mapping {
        entries: vec![
            MapEntry {
                source: "JawOpen".into(),
                target: "jawOpen".into(),
                gain: 1.0,
                offset: 0.0,
                clamp: None,
            },
            MapEntry {
                source: "happy".into(),
                target: "mouthSmileLeft".into(),
                gain: 0.8,
                offset: 0.05,
                clamp: Some([0.0, 1.0]),
            },
        ],
        sources: vec![MapSource {
            name: "happy".into(),
            binary: true,
            override_blink: MapOverride::Block,
            override_look_at: MapOverride::None,
            override_mouth: MapOverride::Blend,
        }],
    };
    let bin = to_bincode(&m).unwrap();
    check("mapping.bincode", &bin);
    assert_eq!(request_from_bincode::<Mapping>(&bin).unwrap(), m);
    let json = serde_json::to_vec(&m).unwrap();
    check("mapping.json", &json);
    // Humans leave out gain 1, offset 0, no clamp and "none".
    let short: Mapping = serde_json::from_str(
        r#"{"entries":[{"source":"JawOpen","target":"jawOpen"},
            {"source":"happy","target":"mouthSmileLeft","gain":0.8,"offset":0.05,"clamp":[0,1]}],
            "sources":[{"name":"happy","binary":true,"override_blink":"block",
                        "override_mouth":"blend"}]}"#,
    )
    .unwrap();
    assert_eq!(short, m);
}
