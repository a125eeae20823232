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
