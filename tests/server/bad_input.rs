//! Bad input over HTTP: every case is a 4xx whose JSON body names the problem, and the server
//! keeps serving correct frames afterwards.

use bytes::Bytes;
use crowdmorph::server::ServerConfig;
use crowdmorph_client::{Encoding, Method, Reply};
use crowdmorph_proto::{CONTENT_TYPE_BINCODE, CrowdFrameRequest, Head, OutputOptions};
use serde_json::json;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

use super::TestServer;

fn head(rig: &str, clip: &str, frame: i64, lod: u32) -> Head {
    Head {
        head: 1,
        rig: rig.into(),
        clip: clip.into(),
        frame,
        lod,
        ..Default::default()
    }
}

fn frame_req(heads: Vec<Head>, wrap: bool) -> CrowdFrameRequest {
    CrowdFrameRequest {
        heads,
        output: OutputOptions::default(),
        wrap,
    }
}

/// Asserts the reply is `status` with error `code` and a message containing `needle`, then
/// that the server still answers a good frame.
async fn expect(server: &TestServer, reply: Reply, status: u16, code: &str, needle: &str) {
    assert_eq!(
        reply.status,
        status,
        "{code}: {}",
        String::from_utf8_lossy(&reply.body)
    );
    assert_eq!(reply.content_type.as_deref(), Some("application/json"));
    let e = reply.error().expect("a JSON error body");
    assert_eq!(e.error.code, code, "{}", e.error.message);
    assert!(
        e.error.message.contains(needle),
        "message {:?} should name {needle:?}",
        e.error.message
    );
    still_serving(server).await;
}

async fn still_serving(server: &TestServer) {
    let req = frame_req(vec![head("default-head", "talk", 3, 0)], true);
    let (resp, _) = server
        .client
        .crowd_frame(&req, Encoding::Bincode)
        .await
        .expect("the server still serves frames");
    assert_eq!(resp.buffers.len(), 1);
    assert_eq!(resp.buffers[0].positions.0.len(), 7262 * 12);
}

/// A request with no body and no content type.
async fn bare(server: &TestServer, method: Method, path: &str) -> Reply {
    server
        .client
        .send(method, path, None, None, Bytes::new())
        .await
        .expect("transport")
}

async fn post(server: &TestServer, path: &str, ct: &str, body: impl Into<Bytes>) -> Reply {
    server
        .client
        .send(Method::POST, path, Some(ct), None, body.into())
        .await
        .expect("transport")
}

async fn post_json(server: &TestServer, v: serde_json::Value) -> Reply {
    post(server, "/v1/crowd/frame", "application/json", v.to_string()).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_unknown_and_out_of_range_requests_are_named_4xx() {
    let server = TestServer::start(ServerConfig {
        max_heads: 1000,
        ..ServerConfig::default()
    })
    .await;
    let s = &server;
    // Errors axum answers by itself get the same JSON body as every other error.
    let r = bare(s, Method::DELETE, "/v1/crowd/frame").await;
    expect(s, r, 405, "method_not_allowed", "Method Not Allowed").await;
    let r = bare(s, Method::GET, "/v1/rigs/%FF%FE").await;
    expect(s, r, 400, "bad_request", "UTF-8").await;
    let r = post(s, "/v1/crowd/frame", "application/json", "{\"heads\": [").await;
    expect(s, r, 400, "malformed_json", "JSON").await;
    let r = post(s, "/v1/crowd/frame", CONTENT_TYPE_BINCODE, vec![0xFFu8; 37]).await;
    expect(s, r, 400, "malformed_bincode", "bincode").await;
    // A bincode message that declares 10^7 heads but carries one: refused, not allocated.
    let one = crowdmorph_proto::wire::to_bincode(&frame_req(
        vec![head("default-head", "talk", 0, 0)],
        true,
    ))
    .unwrap();
    let mut lying = Vec::new();
    crowdmorph_proto::wire::put_varint(&mut lying, 10_000_000);
    lying.extend_from_slice(&one[1..]);
    let r = post(s, "/v1/crowd/frame", CONTENT_TYPE_BINCODE, lying).await;
    expect(s, r, 400, "malformed_bincode", "bincode").await;
    // A string that declares a terabyte.
    let mut huge = vec![1u8, 7];
    crowdmorph_proto::wire::put_varint(&mut huge, 1 << 40);
    let r = post(s, "/v1/crowd/frame", CONTENT_TYPE_BINCODE, huge).await;
    expect(s, r, 400, "malformed_bincode", "bincode").await;
    let r = post(s, "/v1/crowd/frame", "application/xml", "<heads/>").await;
    expect(s, r, 415, "unsupported_media_type", "application/xml").await;

    let frame = |rig: &str, clip: &str, frame: serde_json::Value, lod: u32, wrap: bool| json!({"heads":[{"head":5,"rig":rig,"clip":clip,"frame":frame,"lod":lod}],"wrap":wrap});
    let r = post_json(s, frame("nobody", "talk", json!(1), 0, true)).await;
    expect(s, r, 404, "unknown_rig", "nobody").await;
    let r = post_json(s, frame("default-head", "moonwalk", json!(1), 0, true)).await;
    expect(s, r, 404, "unknown_clip", "moonwalk").await;
    let frames = crowdmorph::embedded::default_rig().clips[1].frames;
    let r = post_json(s, frame("default-head", "talk", json!(frames), 0, false)).await;
    expect(s, r, 400, "frame_out_of_range", "past the end").await;
    let r = post_json(s, frame("default-head", "talk", json!(-1), 0, false)).await;
    expect(s, r, 400, "frame_out_of_range", "talk").await;
    let r = post_json(s, frame("default-head", "talk", json!(1), 99, true)).await;
    expect(s, r, 400, "lod_out_of_range", "99").await;
    // NaN is not JSON, and a fractional frame is not a frame.
    let r = post(
        s,
        "/v1/crowd/frame",
        "application/json",
        r#"{"heads":[{"head":1,"rig":"default-head","clip":"talk","frame":NaN}]}"#,
    )
    .await;
    expect(s, r, 400, "malformed_json", "JSON").await;
    let r = post_json(s, frame("default-head", "talk", json!(1.5), 0, true)).await;
    expect(s, r, 400, "malformed_json", "frame").await;
    let r = post_json(s, json!({"heads":[], "extra": 1})).await;
    expect(s, r, 400, "malformed_json", "extra").await;
    let r = post_json(
        s,
        json!({"heads":[{"head":1,"rig":"default-head","clip":"talk","frame":1}],"output":{"format":"f64"}}),
    )
    .await;
    expect(s, r, 400, "malformed_json", "f64").await;
    // More heads than the limit.
    let many: Vec<Head> = (0..1001)
        .map(|_| head("default-head", "talk", 0, 0))
        .collect();
    let r = post(
        s,
        "/v1/crowd/frame",
        "application/json",
        serde_json::to_vec(&frame_req(many, true)).unwrap(),
    )
    .await;
    expect(s, r, 400, "too_many_heads", "1001").await;
    // NaN weights in a clip.
    let r = post(
        s,
        "/v1/rigs/default-head/clips?name=bad",
        "text/csv",
        "jawOpen,eyeBlink_L\n0.1,NaN\n",
    )
    .await;
    expect(s, r, 400, "invalid_clip", "not finite").await;
    let r = post(s, "/v1/nothing", "application/json", "{}").await;
    expect(s, r, 404, "no_route", "endpoint").await;
    let r = post(s, "/v1/rigs?name=../../etc", "model/gltf-binary", "glTF").await;
    expect(s, r, 400, "invalid_name", "../../etc").await;
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn ten_million_heads_and_oversized_bodies_are_413() {
    let server = TestServer::start(ServerConfig {
        max_upload_bytes: 4096,
        ..ServerConfig::default()
    })
    .await;
    let s = &server;
    // Declared: a 10^7-head JSON body is about 700 MB; refused from its Content-Length.
    let mut sock = tokio::net::TcpStream::connect(s.addr).await.unwrap();
    sock.write_all(
        b"POST /v1/crowd/frame HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n\
          Content-Length: 700000000\r\nConnection: close\r\n\r\n{\"heads\":[",
    )
    .await
    .unwrap();
    let mut out = String::new();
    let _ = sock.read_to_string(&mut out).await;
    assert!(out.starts_with("HTTP/1.1 413"), "{out}");
    assert!(out.contains("body_too_large"), "{out}");
    // Streamed without a length: cut at the limit (16 MiB) while it arrives.
    let mut sock = tokio::net::TcpStream::connect(s.addr).await.unwrap();
    let (mut rd, mut wr) = sock.split();
    let writer = async {
        wr.write_all(
            b"POST /v1/crowd/frame HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n\
              Transfer-Encoding: chunked\r\nConnection: close\r\n\r\n",
        )
        .await?;
        let head = r#"{"head":1,"rig":"default-head","clip":"talk","frame":1},"#.repeat(10_000);
        let chunk = format!("{:x}\r\n{head}\r\n", head.len());
        wr.write_all(b"b\r\n{\"heads\":[ \r\n").await?;
        for _ in 0..(10_000_000 / 10_000) {
            wr.write_all(chunk.as_bytes()).await?;
        }
        std::io::Result::Ok(())
    };
    let reader = async {
        let mut out = Vec::new();
        let _ = rd.read_to_end(&mut out).await;
        String::from_utf8_lossy(&out).into_owned()
    };
    let (_, out) = tokio::join!(writer, reader);
    assert!(out.starts_with("HTTP/1.1 413"), "{out}");
    drop(sock);
    still_serving(s).await;
    // An upload over the upload limit.
    let glb = crate::util::builder::triangle_rig().to_glb();
    let mut big = glb.clone();
    big.resize(8192, 0);
    let r = post(s, "/v1/rigs?name=big", "model/gltf-binary", big).await;
    expect(s, r, 413, "body_too_large", "4096").await;
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn gltf_bombs_and_garbage_rigs_are_refused() {
    let server = TestServer::start(ServerConfig {
        max_upload_memory: 8 << 20,
        ..ServerConfig::default()
    })
    .await;
    let s = &server;
    // Huge declared counts in a tiny file.
    let mut b = crate::util::builder::triangle_rig();
    b.accessor_mut(0)["count"] = json!(2_000_000_000u64);
    let r = post(s, "/v1/rigs?name=bomb", "model/gltf-binary", b.to_glb()).await;
    assert!(r.status == 400 || r.status == 413, "{}", r.status);
    let e = r.error().unwrap();
    assert!(
        e.error.message.contains("accessor") || e.error.message.contains("limit"),
        "{}",
        e.error.message
    );
    still_serving(s).await;
    // Counts that fit the bytes present but exceed the decode budget.
    // 128 Ki vertices: a 4.7 MB body (under the 8 MiB budget), a rig of 7 MB more.
    let n = 1 << 17;
    let positions: Vec<[f32; 3]> = (0..n).map(|i| [i as f32, 0.0, 0.0]).collect();
    let targets = vec![positions.clone(); 2];
    let mut big = crate::util::builder::Builder::new();
    let mesh = big.mesh_with_targets(&positions, None, &targets, None);
    let node = big.node(Some(mesh));
    big.scene(&[node]);
    let r = post(s, "/v1/rigs?name=big", "model/gltf-binary", big.to_glb()).await;
    expect(s, r, 413, "rig_too_large", "limit").await;
    // A GLB whose chunk claims more bytes than the file has.
    let mut glb = crate::util::builder::triangle_rig().to_glb();
    glb[12..16].copy_from_slice(&u32::MAX.to_le_bytes());
    let r = post(s, "/v1/rigs?name=trunc", "model/gltf-binary", glb).await;
    expect(s, r, 400, "invalid_rig", "GLB").await;
    let r = post(s, "/v1/rigs?name=junk", "application/octet-stream", "hello").await;
    expect(s, r, 400, "invalid_rig", "glTF").await;
    // NaN positions.
    let mut nan = crate::util::builder::Builder::new();
    let mesh = nan.mesh_with_targets(
        &[[0.0, 0.0, 0.0], [f32::NAN, 0.0, 0.0], [0.0, 1.0, 0.0]],
        Some(&[0, 1, 2]),
        &crate::util::builder::triangle_targets(),
        None,
    );
    let node = nan.node(Some(mesh));
    nan.scene(&[node]);
    let r = post(s, "/v1/rigs?name=nan", "model/gltf-binary", nan.to_glb()).await;
    expect(s, r, 400, "invalid_rig", "finite").await;
    // Nothing half-registered.
    let rigs = s.client.rigs().await.unwrap();
    assert_eq!(rigs.rigs.len(), 1);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bodies_a_web_page_could_send_cross_origin_are_refused() {
    let server = TestServer::start(ServerConfig {
        admin_token: Some("s3cret".into()),
        ..ServerConfig::default()
    })
    .await;
    let s = &server;
    let frame = serde_json::to_vec(&frame_req(vec![head("default-head", "talk", 3, 0)], true))
        .expect("json");
    // The three CORS-safelisted types and no type at all: a page on any origin can send
    // these without a preflight, so none of them is read as JSON.
    for ct in [
        "text/plain",
        "application/x-www-form-urlencoded",
        "multipart/form-data",
    ] {
        let r = post(s, "/v1/crowd/frame", ct, frame.clone()).await;
        expect(s, r, 415, "unsupported_media_type", ct).await;
    }
    let r = s
        .client
        .send(
            Method::POST,
            "/v1/crowd/frame",
            None,
            None,
            Bytes::from(frame.clone()),
        )
        .await
        .expect("transport");
    expect(s, r, 415, "unsupported_media_type", "no Content-Type").await;
    // The same JSON as application/json is a frame.
    let r = post(s, "/v1/crowd/frame", "application/json", frame).await;
    assert_eq!(r.status, 200);

    // A rig upload as text/plain is refused too.
    let glb = crate::util::builder::triangle_rig().to_glb();
    let upload = |ct: &'static str, scheme: &'static str| {
        raw_post(
            s,
            "/v1/rigs?name=t",
            ct,
            format!("{scheme} s3cret"),
            glb.clone(),
        )
    };
    let (status, text) = upload("text/plain", "Bearer").await;
    assert_eq!(status, 415, "{text}");
    // RFC 7235: the scheme is case-insensitive (the token is not).
    let (status, text) = upload("model/gltf-binary", "bearer").await;
    assert_eq!(status, 201, "{text}");
    let (status, text) = upload("model/gltf-binary", "BEARER").await;
    assert_eq!(
        status, 409,
        "the same name again, past the token check: {text}"
    );
    server.stop().await;
}

/// A raw HTTP/1.1 POST with a content type and an Authorization header: (status, response).
async fn raw_post(
    server: &TestServer,
    path: &str,
    ct: &str,
    authorization: String,
    body: Vec<u8>,
) -> (u16, String) {
    let mut sock = tokio::net::TcpStream::connect(server.addr)
        .await
        .expect("connect");
    let head = format!(
        "POST {path} HTTP/1.1\r\nhost: {}\r\nconnection: close\r\ncontent-type: {ct}\r\n\
         authorization: {authorization}\r\ncontent-length: {}\r\n\r\n",
        server.addr,
        body.len()
    );
    sock.write_all(head.as_bytes()).await.expect("write");
    sock.write_all(&body).await.expect("write");
    let mut out = Vec::new();
    sock.read_to_end(&mut out).await.expect("read");
    let text = String::from_utf8_lossy(&out).into_owned();
    let status = text
        .split(' ')
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(0);
    (status, text)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn f16_output_of_positions_past_its_range_is_refused() {
    let server = TestServer::start(ServerConfig::default()).await;
    let s = &server;
    // A triangle 100 km out (in metres): fine in f32 and q16, past the largest f16 (65,504).
    let mut b = crate::util::builder::Builder::new();
    let far = [[1e5, 0.0, 0.0], [1e5 + 1.0, 0.0, 0.0], [1e5, 1.0, 0.0]];
    let mesh = b.mesh_with_targets(&far, None, &[vec![[0.0, 0.0, 1.0]; 3]], None);
    let node = b.node(Some(mesh));
    b.animation_weights("wave", node, &[0.0, 1.0], &[0.0, 1.0], "LINEAR");
    b.scene(&[node]);
    let r = post(s, "/v1/rigs?name=far", "model/gltf-binary", b.to_glb()).await;
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let mut req = frame_req(vec![head("far", "wave", 3, 0)], true);
    req.output.format = crowdmorph_proto::Format::F16;
    let r = post(
        s,
        "/v1/crowd/frame",
        "application/json",
        serde_json::to_vec(&req).unwrap(),
    )
    .await;
    expect(s, r, 400, "format_overflow", "65504").await;
    for format in [crowdmorph_proto::Format::F32, crowdmorph_proto::Format::Q16] {
        req.output.format = format;
        let (resp, _) = s
            .client
            .crowd_frame(&req, Encoding::Json)
            .await
            .expect("frame");
        let p = super::positions_f32(format, &resp.buffers[0]);
        assert!((p[0] - 1e5).abs() < 1.0, "{format:?}: {}", p[0]);
    }
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn clip_weights_that_would_overflow_the_output_are_refused() {
    let server = TestServer::start(ServerConfig::default()).await;
    let s = &server;
    let tri = crate::util::builder::triangle_rig().to_glb();
    let r = post(s, "/v1/rigs?name=tri", "model/gltf-binary", tri).await;
    assert_eq!(r.status, 201);
    // Weights of 1e30 on a unit delta: positions would reach 1e30, past what f32 blending,
    // normals and q16 boxes can carry.
    let clip = r#"{"fps":30,"targets":["a","b"],"frames":[[0,0],[1e30,0]]}"#;
    let r = post(s, "/v1/rigs/tri/clips?name=huge", "application/json", clip).await;
    expect(s, r, 400, "invalid_clip", "overflow").await;
    let clips = s.client.clips("tri").await.expect("clips");
    assert!(clips.clips.is_empty(), "nothing was added");
    server.stop().await;
}

/// A CSV clip naming a million unknown columns (the hostile run's: its error body was 8.9 MB)
/// is answered with a short error that quotes a few and counts the rest.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_million_unknown_clip_columns_get_a_short_error() {
    let server = TestServer::start(ServerConfig::default()).await;
    let s = &server;
    let n = 1_000_000;
    let mut csv = String::with_capacity(12 * n);
    for i in 0..n {
        csv.push_str(&format!("u{i},"));
    }
    csv.push_str("jawOpen\n");
    for _ in 0..n {
        csv.push_str("0,");
    }
    csv.push_str("0.5\n");
    let r = post(s, "/v1/rigs/default-head/clips?name=wide", "text/csv", csv).await;
    assert!(r.body.len() < 4096, "a {}-byte error body", r.body.len());
    expect(
        s,
        r,
        400,
        "unknown_targets",
        &format!(
            "not in the rig: {} and {} more",
            (0..16)
                .map(|i| format!("\"u{i}\""))
                .collect::<Vec<_>>()
                .join(", "),
            n - 16
        ),
    )
    .await;
    server.stop().await;
}

/// Two CSV columns that write one target, loose spellings included, are refused naming both
/// (one of them was dropped silently), and nothing is added.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn clip_columns_that_write_one_target_twice_are_refused_naming_both() {
    let server = TestServer::start(ServerConfig::default()).await;
    let s = &server;
    for (body, named) in [
        ("jawOpen,JawOpen\n0.5,0.5\n", "\"jawOpen\" and \"JawOpen\""),
        (
            "Timecode,eyeBlink_L,EyeBlinkLeft\n0,0.5,0.5\n",
            "\"eyeBlink_L\" and \"EyeBlinkLeft\"",
        ),
    ] {
        let r = post(
            s,
            "/v1/rigs/default-head/clips?name=twice",
            "text/csv",
            body,
        )
        .await;
        expect(s, r, 400, "invalid_clip", named).await;
    }
    let list = s.client.clips("default-head").await.expect("clips");
    assert!(
        list.clips.iter().all(|c| c.name != "twice"),
        "nothing added"
    );
    server.stop().await;
}

/// A live weight whose name has a NUL (which the loose spelling would drop, matching
/// `jawOpen`) is refused, not matched.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_weight_name_with_a_nul_is_refused_not_matched_loosely() {
    let server = TestServer::start(ServerConfig::default()).await;
    let s = &server;
    let weights =
        |name: &str| json!({"heads": [{"head": 0, "rig": "default-head", "weights": {name: 1.0}}]});
    let r = post_json(s, weights("jawOpen")).await;
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    for name in ["jaw\u{0}Open", "jaw\nOpen", "\u{1b}jawOpen"] {
        let r = post_json(s, weights(name)).await;
        expect(s, r, 400, "invalid_weights", "control character").await;
    }
    server.stop().await;
}
