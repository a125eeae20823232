//! What the server benchmarks share: a server started in this process on a loopback port with
//! the rig to measure, the process's CPU time, and rig files made uploadable.

use std::time::Duration;

use anyhow::{Context, Result};
use bytes::Bytes;
use crowdmorph_client::Client;

use crowdmorph_server::{AppState, ServerConfig};

/// The bytes to upload for a rig file: a `.glb` as it is, a `.gltf` with its external buffers
/// and images inlined as base64 data URIs (the server accepts only self-contained files).
pub fn self_contained_bytes(path: &std::path::Path) -> Result<Vec<u8>> {
    use base64::Engine as _;
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    if bytes.starts_with(b"glTF") {
        return Ok(bytes);
    }
    let mut doc: serde_json::Value =
        serde_json::from_slice(&bytes).with_context(|| format!("parsing {}", path.display()))?;
    let dir = path.parent().unwrap_or(std::path::Path::new("."));
    if let Some(buffers) = doc.get_mut("buffers").and_then(|b| b.as_array_mut()) {
        for b in buffers {
            let Some(uri) = b.get("uri").and_then(|u| u.as_str()).map(str::to_string) else {
                continue;
            };
            if uri.starts_with("data:") {
                continue;
            }
            let data = std::fs::read(dir.join(&uri))
                .with_context(|| format!("reading buffer {uri} of {}", path.display()))?;
            b["uri"] = serde_json::Value::String(format!(
                "data:application/octet-stream;base64,{}",
                base64::engine::general_purpose::STANDARD.encode(data)
            ));
        }
    }
    // Images too, so the server draws the rig's textures.
    if let Some(images) = doc.get_mut("images").and_then(|b| b.as_array_mut()) {
        for im in images {
            let Some(uri) = im.get("uri").and_then(|u| u.as_str()).map(str::to_string) else {
                continue;
            };
            if uri.starts_with("data:") {
                continue;
            }
            let data = std::fs::read(dir.join(&uri))
                .with_context(|| format!("reading image {uri} of {}", path.display()))?;
            let mime = im
                .get("mimeType")
                .and_then(|m| m.as_str())
                .unwrap_or(if uri.ends_with(".png") {
                    "image/png"
                } else {
                    "image/jpeg"
                })
                .to_string();
            im["uri"] = serde_json::Value::String(format!(
                "data:{mime};base64,{}",
                base64::engine::general_purpose::STANDARD.encode(data)
            ));
        }
    }
    Ok(serde_json::to_vec(&doc)?)
}

/// A server started in this process on a loopback port for a benchmark, with its rig.
pub struct BenchServer {
    /// The server's state.
    pub state: AppState,
    /// Where it listens.
    pub addr: std::net::SocketAddr,
    /// A client of it.
    pub client: Client,
    /// The rig to measure: the uploaded one, else the embedded head.
    pub rig_id: String,
    /// Stops the server.
    pub stop_tx: tokio::sync::oneshot::Sender<()>,
    /// The serving task.
    pub server: tokio::task::JoinHandle<Result<(), crowdmorph_server::ServerError>>,
}

impl BenchServer {
    /// Starts a server with `config` and uploads `rig_bytes` as rig `bench` when given.
    pub async fn start(config: ServerConfig, rig_bytes: Option<Vec<u8>>) -> Result<BenchServer> {
        let state = AppState::new(config)?;
        state.load_stored().await;
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?;
        let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
        let server = tokio::spawn(crowdmorph_server::serve(listener, state.clone(), async {
            let _ = stop_rx.await;
        }));
        let client = Client::new(format!("http://{addr}"));
        let rig_id = match rig_bytes {
            Some(b) => {
                client
                    .upload_rig("bench", Bytes::from(b))
                    .await
                    .context("uploading the rig")?
                    .id
            }
            None => crowdmorph_server::registry::BUILTIN_ID.to_string(),
        };
        Ok(BenchServer {
            state,
            addr,
            client,
            rig_id,
            stop_tx,
            server,
        })
    }
}

/// Uploads every `.csv` and `.json` clip in `dir` to rig `rig`, each named by its file stem
/// (in name order), with `ignore_unknown=true` (the embedded head's clips name 51 ARKit
/// targets; ICT FaceKit spells two of them differently); returns the names.
pub async fn upload_clips(
    client: &Client,
    rig: &str,
    dir: &std::path::Path,
) -> Result<Vec<String>> {
    let mut names = Vec::new();
    for (path, name, csv) in clip_files(dir)? {
        let content_type = if csv { "text/csv" } else { "application/json" };
        let bytes = std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
        client
            .upload_clip(
                rig,
                &format!("name={name}&ignore_unknown=true"),
                content_type,
                Bytes::from(bytes),
            )
            .await
            .with_context(|| format!("uploading clip {}", path.display()))?;
        names.push(name);
    }
    Ok(names)
}

/// The `.csv` and `.json` clips in `dir`, in name order: each path, its name (the file stem)
/// and whether it is CSV. An empty folder is an error.
pub fn clip_files(dir: &std::path::Path) -> Result<Vec<(std::path::PathBuf, String, bool)>> {
    let mut files: Vec<std::path::PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("reading {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| matches!(p.extension().and_then(|e| e.to_str()), Some("csv" | "json")))
        .collect();
    files.sort();
    if files.is_empty() {
        anyhow::bail!("{} has no .csv or .json clips", dir.display());
    }
    files
        .into_iter()
        .map(|path| {
            let name = path
                .file_stem()
                .and_then(|s| s.to_str())
                .context("a clip file name that is not UTF-8")?
                .to_string();
            let csv = path.extension().and_then(|e| e.to_str()) == Some("csv");
            Ok((path, name, csv))
        })
        .collect()
}

/// CPU time of this process (user + system); zero where `getrusage` is unavailable.
pub fn process_cpu() -> Duration {
    #[cfg(unix)]
    {
        // SAFETY: getrusage writes one rusage through a pointer to a live, zeroed local.
        let mut u: libc::rusage = unsafe { std::mem::zeroed() };
        if unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) } == 0 {
            let tv = |t: libc::timeval| {
                Duration::from_secs(t.tv_sec as u64) + Duration::from_micros(t.tv_usec as u64)
            };
            return tv(u.ru_utime) + tv(u.ru_stime);
        }
    }
    Duration::ZERO
}
