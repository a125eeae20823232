//! Tests of the HTTP server: real sockets on port 0 (a child process where a crash must be
//! real), the Rust client from `clients/rust`, and the CPU engine or the f64 oracle as the
//! reference for every vertex that comes back.

mod alive;
mod animation;
mod api;
mod appearance;
mod attack;
mod avatar;
mod bad_input;
mod balancer;
mod concurrency;
mod connections;
mod deploy;
mod encoding;
mod golden;
mod graphs;
mod hostile;
mod joints;
mod layers;
mod live;
mod loadtest;
mod lod;
mod mappings;
mod metrics;
mod near_clones;
mod overload;
mod persistence;
mod poses;
mod python_peer;
mod render;
mod replicas;
mod sessions;
mod skin;
mod temporal;
mod threejs;
mod viewer;

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use bytes::Bytes;
use crowdmorph::server::{AppState, ServerConfig};
use crowdmorph_client::Client;
use crowdmorph_proto::{Blob, Format, FrameBuffer};

/// A server on 127.0.0.1:0 in this process.
pub struct TestServer {
    pub addr: SocketAddr,
    pub client: Client,
    pub state: AppState,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    handle: tokio::task::JoinHandle<Result<(), crowdmorph::server::ServerError>>,
}

impl TestServer {
    /// Starts a server and waits until it is ready. The background LOD job is off, so that
    /// frames compare against the rig exactly as uploaded; `tests/server/lod.rs` turns it on
    /// with [`TestServer::start_with_auto_lod`].
    pub async fn start(config: ServerConfig) -> TestServer {
        Self::start_with_auto_lod(ServerConfig {
            no_auto_lod: true,
            ..config
        })
        .await
    }

    /// Starts a server with `config` as given (the background LOD job as configured).
    pub async fn start_with_auto_lod(config: ServerConfig) -> TestServer {
        let state = AppState::new(config).expect("server state");
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
            .await
            .expect("bind");
        let addr = listener.local_addr().expect("addr");
        let (stop, rx) = tokio::sync::oneshot::channel::<()>();
        let handle = tokio::spawn(crowdmorph::server::serve(listener, state.clone(), async {
            let _ = rx.await;
        }));
        let client = Client::new(format!("http://{addr}"));
        for _ in 0..200 {
            if state.is_ready() {
                break;
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        assert!(state.is_ready(), "server ready");
        TestServer {
            addr,
            client,
            state,
            stop: Some(stop),
            handle,
        }
    }

    /// Asks for a graceful shutdown and waits for the server to return.
    pub async fn stop(mut self) {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        self.handle.await.expect("join").expect("serve");
    }

    /// Sends the shutdown signal without waiting.
    pub fn signal_stop(&mut self) {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
    }

    /// Waits for the server task after [`TestServer::signal_stop`].
    pub async fn join(self) {
        self.handle.await.expect("join").expect("serve");
    }
}

/// A fresh, empty directory under the system temp dir.
pub fn temp_dir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!(
        "crowdmorph-test-{tag}-{}-{}",
        std::process::id(),
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos())
            .unwrap_or(0)
    ));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("temp dir");
    d
}

/// The default configuration with a data directory, so that rigs persist across restarts.
pub fn stored_config(dir: &Path) -> ServerConfig {
    ServerConfig {
        data_dir: Some(dir.to_path_buf()),
        ..ServerConfig::default()
    }
}

/// One head of rig `rig` with the named live `weights` (the rest 0, or the file's defaults
/// for names not given), at `placement` (position, yaw in degrees, scale), rendered by the
/// server as a `width × height` PNG with `camera` on `background`: the picture tests compare
/// with another renderer's.
pub async fn render_one(
    server: &TestServer,
    rig: &str,
    weights: &[(String, f32)],
    placement: ([f32; 3], f32, f32),
    camera: crowdmorph_proto::CameraSpec,
    (width, height): (u32, u32),
    background: [u8; 3],
) -> crate::util::image::Image {
    use crowdmorph_proto::{Head, ImageOptions, LiveWeights, Placement, RenderRequest};
    let (position, yaw, scale) = placement;
    let req = RenderRequest {
        heads: vec![Head::live(1, rig, LiveWeights::Named(weights.to_vec()))],
        wrap: true,
        placements: Some(vec![Placement {
            head: 1,
            position,
            yaw,
            scale,
        }]),
        camera: Some(camera),
        image: Some(ImageOptions {
            width,
            height,
            background,
            ..ImageOptions::default()
        }),
    };
    let reply = server
        .client
        .render(&req, crowdmorph_client::Encoding::Json)
        .await
        .expect("render");
    assert_eq!(reply.status, 200, "{:?}", reply.error());
    let img = crate::util::image::Image::decode_png(&reply.body).expect("a PNG");
    assert_eq!((img.width, img.height), (width, height));
    img
}

/// The upload bytes of a rig file (external glTF buffers inlined).
pub fn upload_bytes(path: &Path) -> Bytes {
    Bytes::from(crowdmorph::bench::server::self_contained_bytes(path).expect("rig bytes"))
}

/// Positions of a buffer as f32, whatever the format.
/// Largest distance between the vertices `got` (x, y, z f32 each) and `want`.
pub fn max_distance(got: &[f32], want: &[glam::DVec3]) -> f64 {
    assert_eq!(got.len(), want.len() * 3);
    got.chunks_exact(3)
        .zip(want)
        .map(|(g, w)| {
            (glam::DVec3::new(f64::from(g[0]), f64::from(g[1]), f64::from(g[2])) - *w).length()
        })
        .fold(0.0, f64::max)
}

pub fn positions_f32(format: Format, b: &FrameBuffer) -> Vec<f32> {
    decode(format, &b.positions, b.quantization.as_ref(), false)
}

/// Normals of a buffer as f32, when present.
pub fn normals_f32(format: Format, b: &FrameBuffer) -> Option<Vec<f32>> {
    b.normals.as_ref().map(|n| decode(format, n, None, true))
}

fn decode(
    format: Format,
    blob: &Blob,
    q: Option<&crowdmorph_proto::Quantization>,
    normals: bool,
) -> Vec<f32> {
    match format {
        Format::F32 => blob.to_f32(),
        Format::F16 => blob
            .to_u16()
            .into_iter()
            .map(|h| half::f16::from_bits(h).to_f32())
            .collect(),
        Format::Q16 | Format::Q16R if normals => blob
            .to_i16()
            .into_iter()
            .map(|v| f32::from(v) / 32767.0)
            .collect(),
        Format::Q16 => q
            .expect("q16 buffers carry their box")
            .dequantize(&blob.to_i16()),
        Format::Q16R => panic!("q16r positions need their reference: decode with q16r_decode"),
        Format::Weights => panic!("a weights answer has no vertex buffers"),
    }
}

/// A deterministic JSON clip over every target of a rig.
pub fn random_clip_json(targets: &[String], frames: usize, seed: u64) -> String {
    let mut rng = crate::util::Rng(seed);
    let rows: Vec<Vec<f64>> = (0..frames)
        .map(|_| {
            targets
                .iter()
                .map(|_| {
                    if rng.below(4) == 0 {
                        0.0
                    } else {
                        (rng.f64() * 1.2 - 0.1) * 1e4
                    }
                    .round()
                        / 1e4
                })
                .collect()
        })
        .collect();
    serde_json::json!({"fps": 30, "targets": targets, "frames": rows}).to_string()
}

/// Asserts that `result` is the JSON error `status` `code`, and returns its message.
pub fn api_error<T: std::fmt::Debug>(
    result: Result<T, crowdmorph_client::ClientError>,
    status: u16,
    code: &str,
) -> String {
    match result {
        Err(crowdmorph_client::ClientError::Api {
            status: got,
            code: got_code,
            message,
        }) => {
            assert_eq!((got, got_code.as_str()), (status, code), "{message}");
            message
        }
        other => panic!("expected {status} {code}, got {other:?}"),
    }
}
