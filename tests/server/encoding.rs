//! `Content-Encoding` both ways: responses compressed with zstd or gzip when asked and
//! inflating to the plain bytes, nothing changed for a client that asks for nothing, images and
//! small responses left alone; request bodies inflated within the body limit (a bomb is 413
//! without being inflated), other encodings 415.

use std::io::Write;

use bytes::Bytes;
use crowdmorph_client::{Client, Compression, Encoding, Method};
use crowdmorph_proto::{CrowdFrameRequest, Format, Head, OutputOptions};

use super::TestServer;

fn crowd(format: Format) -> CrowdFrameRequest {
    CrowdFrameRequest {
        heads: (0..12)
            .map(|i| Head {
                head: i,
                rig: "default-head".into(),
                clip: "talk".into(),
                frame: i as i64 * 7,
                lod: 0,
                ..Default::default()
            })
            .collect(),
        output: OutputOptions {
            normals: true,
            format,
        },
        wrap: true,
    }
}

fn zstd_bytes(b: &[u8]) -> Bytes {
    Bytes::from(zstd::bulk::compress(b, 3).expect("zstd"))
}

fn gzip_bytes(b: &[u8]) -> Bytes {
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    e.write_all(b).expect("gzip");
    Bytes::from(e.finish().expect("gzip"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn responses_compress_when_asked_and_inflate_to_the_same_bytes() {
    let s = TestServer::start(crowdmorph::server::ServerConfig::default()).await;
    let base = format!("http://{}", s.addr);
    let plain = Client::new(&base);
    for format in [Format::F32, Format::Q16] {
        let body = Client::encode(&crowd(format), Encoding::Bincode).unwrap();
        let want = plain
            .crowd_frame_raw(body.clone(), Encoding::Bincode)
            .await
            .unwrap();
        assert_eq!(want.status, 200);
        assert!(
            want.header("content-encoding").is_none(),
            "nothing asked, nothing changed"
        );
        assert_eq!(want.wire_bytes, want.body.len());
        for c in [Compression::Zstd, Compression::Gzip] {
            let client = Client::new(&base).with_compression(c);
            let got = client
                .crowd_frame_raw(body.clone(), Encoding::Bincode)
                .await
                .unwrap();
            assert_eq!(got.status, 200);
            let token = if c == Compression::Zstd {
                "zstd"
            } else {
                "gzip"
            };
            assert_eq!(got.header("content-encoding"), Some(token));
            // The frames of one clip are the same bytes after inflating; the timings differ.
            let (a, b) =
                (
                    crowdmorph_proto::wire::response_from_bincode::<
                        crowdmorph_proto::CrowdFrameResponse,
                    >(&got.body)
                    .unwrap(),
                    crowdmorph_proto::wire::response_from_bincode::<
                        crowdmorph_proto::CrowdFrameResponse,
                    >(&want.body)
                    .unwrap(),
                );
            assert_eq!(a.buffers, b.buffers, "{format:?} {c:?}");
            assert_eq!(a.heads, b.heads);
            assert!(
                got.wire_bytes < got.body.len(),
                "{format:?} {c:?}: {} ≥ {}",
                got.wire_bytes,
                got.body.len()
            );
        }
    }
    // Small answers and images stay plain even when compression is asked for.
    let zc = Client::new(&base).with_compression(Compression::Zstd);
    let health = zc
        .send(Method::GET, "/healthz", None, None, Bytes::new())
        .await
        .unwrap();
    assert!(health.header("content-encoding").is_none());
    let render = serde_json::json!({
        "heads": [{"head": 0, "rig": "default-head", "clip": "talk", "frame": 3}],
        "width": 64, "height": 64, "format": "png"
    });
    let r = zc
        .send(
            Method::POST,
            "/v1/crowd/render",
            Some("application/json"),
            Some("image/png"),
            Bytes::from(render.to_string()),
        )
        .await
        .unwrap();
    if r.status == 200 {
        assert!(
            r.header("content-encoding").is_none(),
            "a PNG is not compressed again"
        );
    }
    s.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn compressed_requests_inflate_within_the_limit_and_other_encodings_are_415() {
    let s = TestServer::start(crowdmorph::server::ServerConfig {
        max_request_bytes: 1 << 20,
        ..crowdmorph::server::ServerConfig::default()
    })
    .await;
    let base = format!("http://{}", s.addr);
    let json = serde_json::to_vec(&crowd(Format::Q16)).unwrap();
    let plain = Client::new(&base)
        .crowd_frame_raw(Bytes::from(json.clone()), Encoding::Json)
        .await
        .unwrap();
    assert_eq!(plain.status, 200);
    let url = base.clone();
    let http = post_encoded;
    for (name, body) in [("zstd", zstd_bytes(&json)), ("gzip", gzip_bytes(&json))] {
        let (status, reply) = http(&url, name, body).await;
        assert_eq!(status, 200, "{name}: {}", String::from_utf8_lossy(&reply));
        let (a, b): (serde_json::Value, serde_json::Value) = (
            serde_json::from_slice(&reply).unwrap(),
            serde_json::from_slice(&plain.body).unwrap(),
        );
        assert_eq!(a["buffers"], b["buffers"], "{name}");
    }
    // 256 MiB of zeros in a 8 KiB zstd frame: refused at the 1 MiB limit, not inflated.
    let bomb = zstd_bytes(&vec![0u8; 256 << 20]);
    assert!(bomb.len() < 64 << 10);
    let (status, reply) = http(&url, "zstd", bomb).await;
    assert_eq!(status, 413, "{}", String::from_utf8_lossy(&reply));
    let e: serde_json::Value = serde_json::from_slice(&reply).unwrap();
    assert!(e["error"]["code"].is_string(), "{e}");
    let (status, reply) = http(&url, "br", Bytes::from(json.clone())).await;
    assert_eq!(status, 415, "{}", String::from_utf8_lossy(&reply));
    let e: serde_json::Value = serde_json::from_slice(&reply).unwrap();
    assert!(e["error"]["code"].is_string(), "{e}");
    s.stop().await;
}

/// POSTs `body` as JSON with `Content-Encoding: encoding`.
async fn post_encoded(base: &str, encoding: &str, body: Bytes) -> (u16, Bytes) {
    let r = Client::new(base)
        .send_with(
            Method::POST,
            "/v1/crowd/frame",
            &[
                ("content-type", "application/json"),
                ("accept", "application/json"),
                ("content-encoding", encoding),
            ],
            body,
        )
        .await
        .unwrap();
    (r.status, r.body)
}

/// The int16 values of a q16 blob.
fn i16s(b: &[u8]) -> Vec<i16> {
    b.chunks_exact(2)
        .map(|c| i16::from_le_bytes([c[0], c[1]]))
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn q16_residuals_decode_bit_for_bit_to_q16_and_compress_better() {
    let s = TestServer::start(crowdmorph::server::ServerConfig::default()).await;
    let base = format!("http://{}", s.addr);
    let client = Client::new(&base);
    // Real clip frames at every LOD level the rig has, a blend and live weights among them.
    let rig = client.rig("default-head").await.unwrap();
    let levels = rig.lod.levels.len() as u32;
    let mut heads: Vec<Head> = Vec::new();
    for (i, clip) in ["talk", "smile", "surprise", "idle"].iter().enumerate() {
        for lod in 0..levels {
            heads.push(Head {
                head: heads.len() as u64,
                rig: "default-head".into(),
                clip: (*clip).into(),
                frame: 11 * i as i64 + lod as i64,
                lod,
                ..Default::default()
            });
        }
    }
    let req = |format| CrowdFrameRequest {
        heads: heads.clone(),
        output: OutputOptions {
            normals: true,
            format,
        },
        wrap: true,
    };
    let (plain, plain_bytes) = client
        .crowd_frame(&req(Format::Q16), Encoding::Bincode)
        .await
        .unwrap();
    let (resid, _) = client
        .crowd_frame(&req(Format::Q16R), Encoding::Bincode)
        .await
        .unwrap();
    assert_eq!(resid.format, Format::Q16R);
    assert_eq!(plain.heads, resid.heads);
    let mut refs = std::collections::HashMap::new();
    for (a, b) in plain.buffers.iter().zip(&resid.buffers) {
        assert_eq!(
            (a.rig.as_str(), a.lod, a.vertices),
            (b.rig.as_str(), b.lod, b.vertices)
        );
        assert_eq!(a.quantization, b.quantization, "the same box");
        if let std::collections::hash_map::Entry::Vacant(e) = refs.entry(b.lod) {
            let (r, q) = client.q16_reference("default-head", b.lod).await.unwrap();
            assert_eq!(Some(q), b.quantization);
            e.insert(r);
        }
        let decoded = crowdmorph_proto::q16r_decode(&b.positions.0, &refs[&b.lod]).unwrap();
        assert_eq!(decoded, i16s(&a.positions.0), "lod {}: bit for bit", b.lod);
        assert_eq!(a.normals, b.normals, "normals travel as q16");
        assert_ne!(b.positions, a.positions);
    }
    // The JSON answer carries the same bytes.
    let (json, _) = client
        .crowd_frame(&req(Format::Q16R), Encoding::Json)
        .await
        .unwrap();
    assert_eq!(json.buffers, resid.buffers);
    // Compressed, the residuals are smaller than compressed q16 (they are mostly zero bytes).
    let zc = Client::new(&base).with_compression(Compression::Zstd);
    let size = |f| {
        let zc = zc.clone();
        let body = Client::encode(&req(f), Encoding::Bincode).unwrap();
        async move {
            zc.crowd_frame_raw(body, Encoding::Bincode)
                .await
                .unwrap()
                .wire_bytes
        }
    };
    let (zq, zr) = (size(Format::Q16).await, size(Format::Q16R).await);
    assert!(
        zr < zq,
        "zstd: q16r {zr} bytes, q16 {zq} (plain {plain_bytes})"
    );
    s.stop().await;
}

/// GETs `path` with `Accept-Encoding: accept_encoding` and JSON.
async fn get_with(base: &str, path: &str, accept_encoding: &str) -> crowdmorph_client::Reply {
    Client::new(base)
        .send_with(
            Method::GET,
            path,
            &[
                ("accept", "application/json"),
                ("accept-encoding", accept_encoding),
            ],
            Bytes::new(),
        )
        .await
        .unwrap()
}

/// A client that accepts no encoding the server has (`identity;q=0`, `*;q=0`, `br` alone) gets
/// the identity encoding, with the status and body it would get otherwise (not a 406 around
/// the success body); `*` accepts zstd, and is charged as zstd is.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn accept_encodings_the_server_cannot_meet_get_the_plain_answer() {
    let s = TestServer::start(crowdmorph::server::ServerConfig::default()).await;
    let base = format!("http://{}", s.addr);
    let plain = get_with(&base, "/v1/rigs/default-head", "identity").await;
    assert_eq!(plain.status, 200);
    assert!(plain.body.len() > 1400, "large enough to be compressed");
    let want: serde_json::Value = serde_json::from_slice(&plain.body).unwrap();
    for refused in [
        "identity;q=0",
        "*;q=0",
        "*;q=0, identity;q=0",
        "br",
        "br, identity;q=0",
        "zstd;q=0, gzip;q=0, identity;q=0",
    ] {
        let r = get_with(&base, "/v1/rigs/default-head", refused).await;
        assert_eq!(
            r.status,
            200,
            "{refused}: {}",
            String::from_utf8_lossy(&r.body)
        );
        assert_eq!(r.header("content-encoding"), None, "{refused}");
        let got: serde_json::Value = serde_json::from_slice(&r.body).unwrap();
        assert_eq!(got, want, "{refused}");
        // An error is the error, as JSON.
        let r = get_with(&base, "/v1/rigs/nope", refused).await;
        assert_eq!(r.status, 404, "{refused}");
        assert_eq!(r.error().expect("JSON error").error.code, "unknown_rig");
    }
    for (accepted, token) in [("*", "zstd"), ("*, zstd;q=0", "gzip"), ("GZIP", "gzip")] {
        let r = get_with(&base, "/v1/rigs/default-head", accepted).await;
        assert_eq!(r.status, 200, "{accepted}");
        assert_eq!(r.header("content-encoding"), Some(token), "{accepted}");
        let got: serde_json::Value = serde_json::from_slice(&r.body).unwrap();
        assert_eq!(got, want, "{accepted}");
    }
    s.stop().await;
}

/// Gzip with one member per part (`cat a.gz b.gz`, which RFC 1952 allows).
fn gzip_members(parts: &[&[u8]]) -> Bytes {
    let mut out = Vec::new();
    for p in parts {
        out.extend_from_slice(&gzip_bytes(p));
    }
    Bytes::from(out)
}

/// A request body in several gzip members or zstd frames is read whole (every member, every
/// frame), `GZIP` and `x-gzip` are gzip (codings are case-insensitive), a cut-off stream is a
/// 400, and an encoding the server does not take is a 415 that names it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_member_of_a_compressed_request_is_read_and_refusals_name_the_encoding() {
    let s = TestServer::start(crowdmorph::server::ServerConfig::default()).await;
    let base = format!("http://{}", s.addr);
    let json = serde_json::to_vec(&crowd(Format::Q16)).unwrap();
    let (status, plain) = post_encoded(&base, "identity", Bytes::from(json.clone())).await;
    assert_eq!(status, 200);
    let plain: serde_json::Value = serde_json::from_slice(&plain).unwrap();
    // Cut inside a string and inside a number: a reader of the first member alone sees
    // malformed JSON.
    let (a, rest) = json.split_at(json.len() / 3);
    let (b, c) = rest.split_at(rest.len() / 2);
    let mut zstd_frames = zstd_bytes(a).to_vec();
    zstd_frames.extend_from_slice(&zstd_bytes(b));
    zstd_frames.extend_from_slice(&zstd_bytes(c));
    let cases = [
        ("gzip", gzip_members(&[a, b, c])),
        ("x-gzip", gzip_members(&[a, b, c])),
        ("GZIP", gzip_bytes(&json)),
        ("Zstd", zstd_bytes(&json)),
        ("zstd", Bytes::from(zstd_frames)),
        // An empty member between two others.
        ("gzip", gzip_members(&[a, b"", rest])),
    ];
    for (coding, body) in cases {
        let (status, reply) = post_encoded(&base, coding, body).await;
        assert_eq!(status, 200, "{coding}: {}", String::from_utf8_lossy(&reply));
        let got: serde_json::Value = serde_json::from_slice(&reply).unwrap();
        assert_eq!(got["buffers"], plain["buffers"], "{coding}");
        assert_eq!(got["heads"], plain["heads"], "{coding}");
    }
    // Cut short: the body cannot be read.
    for (coding, whole) in [("gzip", gzip_bytes(&json)), ("zstd", zstd_bytes(&json))] {
        let cut = whole.slice(..whole.len() - 5);
        let (status, reply) = post_encoded(&base, coding, cut).await;
        assert_eq!(status, 400, "{coding}: {}", String::from_utf8_lossy(&reply));
        let e: serde_json::Value = serde_json::from_slice(&reply).unwrap();
        assert_eq!(e["error"]["code"], "body_unreadable", "{e}");
    }
    for refused in ["br", "deflate", "gzip, zstd", "compress"] {
        let (status, reply) = post_encoded(&base, refused, Bytes::from(json.clone())).await;
        assert_eq!(status, 415, "{refused}");
        let e: serde_json::Value = serde_json::from_slice(&reply).unwrap();
        assert_eq!(e["error"]["code"], "unsupported_media_type", "{e}");
        let message = e["error"]["message"].as_str().unwrap();
        assert!(message.contains(&format!("{refused:?}")), "{message}");
    }
    s.stop().await;
}

/// A zstd frame's header says how large a window its decoder must hold: up to 128 MiB by
/// libzstd's default, from a body of a few bytes. The server takes at most RFC 9659's 8 MiB
/// (a frame that asks for more is a 400 before anything is allocated for it), and charges its
/// decoder to the queue memory before it reads the body: a decoder larger than the whole queue
/// memory is a 413 naming the flag.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_zstd_body_cannot_ask_for_a_large_window_and_its_decoder_is_charged() {
    let s = TestServer::start(crowdmorph::server::ServerConfig::default()).await;
    let base = format!("http://{}", s.addr);
    let json = serde_json::to_vec(&crowd(Format::Q16)).unwrap();
    // The same body with a 128 MiB window (long-distance matching keeps the frame from
    // shrinking it to the content's size).
    let mut e = zstd::stream::Encoder::new(Vec::new(), 1).unwrap();
    e.window_log(27).unwrap();
    e.long_distance_matching(true).unwrap();
    e.include_contentsize(false).unwrap();
    e.write_all(&json).unwrap();
    let wide = Bytes::from(e.finish().unwrap());
    let (status, reply) = post_encoded(&base, "zstd", wide).await;
    assert_eq!(status, 400, "{}", String::from_utf8_lossy(&reply));
    let err: serde_json::Value = serde_json::from_slice(&reply).unwrap();
    assert_eq!(err["error"]["code"], "body_unreadable", "{err}");
    let (status, _) = post_encoded(&base, "zstd", zstd_bytes(&json)).await;
    assert_eq!(status, 200, "an ordinary zstd body");
    s.stop().await;

    // 8 MiB of queue memory: never room for zstd's decoder, which is refused as larger than
    // the whole budget before the body is read (413), while the same body sent plain only
    // waits for room (the body's own reservation takes what is free: 503).
    let s = TestServer::start(crowdmorph::server::ServerConfig {
        queue_memory_bytes: 8 << 20,
        ..crowdmorph::server::ServerConfig::default()
    })
    .await;
    let base = format!("http://{}", s.addr);
    let (status, reply) = post_encoded(&base, "zstd", zstd_bytes(&json)).await;
    assert_eq!(status, 413, "{}", String::from_utf8_lossy(&reply));
    let err: serde_json::Value = serde_json::from_slice(&reply).unwrap();
    assert_eq!(err["error"]["code"], "queue_memory_exceeded", "{err}");
    let message = err["error"]["message"].as_str().unwrap();
    assert!(message.contains("--queue-memory-bytes"), "{message}");
    let (status, reply) = post_encoded(&base, "identity", Bytes::from(json.clone())).await;
    assert_ne!(status, 413, "{}", String::from_utf8_lossy(&reply));
    s.stop().await;
}
