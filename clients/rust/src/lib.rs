//! A small async client of the crowdmorph server, speaking the v1 protocol of
//! [`crowdmorph_proto`] in JSON or bincode.
//!
//! It is what the server's tests and `crowdmorph bench http` use, and a worked example of the
//! protocol: every call is one HTTP/1.1 request on a pooled keep-alive connection (hyper), and
//! every non-2xx answer becomes [`ClientError::Api`] with the server's error code and message.

use bytes::Bytes;
use crowdmorph_proto::{
    CONTENT_TYPE_BINCODE, CONTENT_TYPE_JSON, ClipList, ClipUpload, CrowdFrameRequest,
    CrowdFrameResponse, ErrorBody, JointMapInfo, JointMapSpec, LodInfo, LodRequest, MeshResponse,
    RenderRequest, RigInfo, RigList, SessionInfo, SessionRequest,
};
use http_body_util::{BodyExt, Full};
use hyper::{Request, StatusCode};
use hyper_util::client::legacy::Client as HyperClient;
use hyper_util::client::legacy::connect::HttpConnector;
use hyper_util::rt::TokioExecutor;
use serde::Serialize;
use serde::de::DeserializeOwned;

pub use crowdmorph_proto as proto;
use crowdmorph_proto::percent_encode;
/// The routing hint of a crowd (`path?rig=RIG`), as the wire crate writes it.
pub use crowdmorph_proto::with_rig_hint;
pub use hyper::Method;

/// Encoding of request and response bodies.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Encoding {
    /// `application/json`.
    Json,
    /// `application/x-bincode`.
    Bincode,
}

impl Encoding {
    /// The Content-Type of a body in this encoding.
    pub fn content_type(self) -> &'static str {
        match self {
            Encoding::Json => CONTENT_TYPE_JSON,
            Encoding::Bincode => CONTENT_TYPE_BINCODE,
        }
    }
}

/// Why a call failed.
#[derive(Debug)]
pub enum ClientError {
    /// The request could not be sent or the response not read.
    Transport(String),
    /// The server answered with an error.
    Api {
        /// HTTP status.
        status: u16,
        /// The error code (`unknown_rig`, `queue_full`, ...).
        code: String,
        /// The server's message.
        message: String,
    },
    /// The response body could not be decoded.
    Decode(String),
}

impl std::fmt::Display for ClientError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ClientError::Transport(e) => write!(f, "transport: {e}"),
            ClientError::Api {
                status,
                code,
                message,
            } => write!(f, "{status} {code}: {message}"),
            ClientError::Decode(e) => write!(f, "decode: {e}"),
        }
    }
}

impl std::error::Error for ClientError {}

/// A raw response.
#[derive(Debug, Clone)]
pub struct Reply {
    /// Status code.
    pub status: u16,
    /// Content-Type header, if any.
    pub content_type: Option<String>,
    /// Retry-After header, if any.
    pub retry_after: Option<String>,
    /// x-request-id header, if any.
    pub request_id: Option<String>,
    /// Every header.
    pub headers: hyper::HeaderMap,
    /// The body (inflated, when it came with a `Content-Encoding`).
    pub body: Bytes,
    /// Bytes of the body as it came over the wire.
    pub wire_bytes: usize,
}

/// A `Content-Encoding` the client asks for (`Accept-Encoding`) and inflates.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Compression {
    /// zstd.
    Zstd,
    /// gzip.
    Gzip,
}

impl Compression {
    /// The `Accept-Encoding` token.
    pub fn token(self) -> &'static str {
        match self {
            Compression::Zstd => "zstd",
            Compression::Gzip => "gzip",
        }
    }
}

/// `body` inflated as its `Content-Encoding` says (none, zstd or gzip).
fn inflate(encoding: Option<&str>, body: Bytes) -> Result<Bytes, ClientError> {
    use std::io::Read;
    let bad = |e: std::io::Error| ClientError::Decode(format!("inflating the body: {e}"));
    match encoding.map(str::trim) {
        None | Some("identity") => Ok(body),
        Some("zstd") => Ok(zstd::stream::decode_all(&body[..]).map_err(bad)?.into()),
        Some("gzip") => {
            let mut out = Vec::new();
            flate2::read::GzDecoder::new(&body[..])
                .read_to_end(&mut out)
                .map_err(bad)?;
            Ok(out.into())
        }
        Some(other) => Err(ClientError::Decode(format!(
            "unknown Content-Encoding {other:?}"
        ))),
    }
}

impl Reply {
    /// A header's value, when present and text.
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers.get(name).and_then(|v| v.to_str().ok())
    }

    /// The error body, when the status is 4xx/5xx and the body is the JSON error.
    pub fn error(&self) -> Option<ErrorBody> {
        serde_json::from_slice(&self.body).ok()
    }

    fn into_error(self) -> ClientError {
        match self.error() {
            Some(e) => ClientError::Api {
                status: self.status,
                code: e.error.code,
                message: e.error.message,
            },
            None => ClientError::Api {
                status: self.status,
                code: String::new(),
                message: String::from_utf8_lossy(&self.body).into_owned(),
            },
        }
    }
}

/// A client of one server.
#[derive(Clone, Debug)]
pub struct Client {
    http: HyperClient<HttpConnector, Full<Bytes>>,
    base: String,
    token: Option<String>,
    compression: Option<Compression>,
}

impl Client {
    /// A client of the server at `base` (e.g. `http://127.0.0.1:8080`).
    pub fn new(base: impl Into<String>) -> Client {
        let mut connector = HttpConnector::new();
        connector.set_nodelay(true);
        Client {
            http: HyperClient::builder(TokioExecutor::new())
                .pool_max_idle_per_host(1024)
                .build(connector),
            base: base.into().trim_end_matches('/').to_string(),
            token: None,
            compression: None,
        }
    }

    /// The server's base URL.
    pub fn base(&self) -> &str {
        &self.base
    }

    /// Asks for compressed responses (`Accept-Encoding`) and inflates them; `Reply::wire_bytes`
    /// says what came over the wire.
    pub fn with_compression(mut self, compression: Compression) -> Client {
        self.compression = Some(compression);
        self
    }

    /// Sends `Authorization: Bearer <token>` with every request.
    pub fn with_token(mut self, token: impl Into<String>) -> Client {
        self.token = Some(token.into());
        self
    }

    /// Sends one request and reads the whole response, whatever its status.
    pub async fn send(
        &self,
        method: Method,
        path: &str,
        content_type: Option<&str>,
        accept: Option<&str>,
        body: Bytes,
    ) -> Result<Reply, ClientError> {
        let mut headers = Vec::new();
        if let Some(ct) = content_type {
            headers.push(("content-type", ct));
        }
        if let Some(a) = accept {
            headers.push(("accept", a));
        }
        self.send_with(method, path, &headers, body).await
    }

    /// [`Client::send`] with any request headers (e.g. a `Content-Encoding` of the body).
    pub async fn send_with(
        &self,
        method: Method,
        path: &str,
        headers: &[(&str, &str)],
        body: Bytes,
    ) -> Result<Reply, ClientError> {
        let mut req = Request::builder()
            .method(method)
            .uri(format!("{}{path}", self.base));
        for (name, value) in headers {
            req = req.header(*name, *value);
        }
        if let Some(t) = &self.token {
            req = req.header("authorization", format!("Bearer {t}"));
        }
        if let Some(c) = self.compression {
            req = req.header("accept-encoding", c.token());
        }
        let req = req
            .body(Full::new(body))
            .map_err(|e| ClientError::Transport(e.to_string()))?;
        let resp = self
            .http
            .request(req)
            .await
            .map_err(|e| ClientError::Transport(e.to_string()))?;
        let status = resp.status().as_u16();
        let header = |name: &str| {
            resp.headers()
                .get(name)
                .and_then(|v| v.to_str().ok())
                .map(str::to_string)
        };
        let content_type = header("content-type");
        let retry_after = header("retry-after");
        let request_id = header("x-request-id");
        let encoding = header("content-encoding");
        let headers = resp.headers().clone();
        let body = resp
            .into_body()
            .collect()
            .await
            .map_err(|e| ClientError::Transport(e.to_string()))?
            .to_bytes();
        let wire_bytes = body.len();
        let body = inflate(encoding.as_deref(), body)?;
        Ok(Reply {
            status,
            content_type,
            retry_after,
            request_id,
            headers,
            body,
            wire_bytes,
        })
    }

    fn decode<T: DeserializeOwned>(reply: Reply, enc: Encoding) -> Result<T, ClientError> {
        if !(200..300).contains(&reply.status) {
            return Err(reply.into_error());
        }
        match enc {
            Encoding::Json => {
                serde_json::from_slice(&reply.body).map_err(|e| ClientError::Decode(e.to_string()))
            }
            Encoding::Bincode => crowdmorph_proto::wire::response_from_bincode(&reply.body)
                .map_err(|e| ClientError::Decode(e.to_string())),
        }
    }

    async fn get<T: DeserializeOwned>(&self, path: &str, enc: Encoding) -> Result<T, ClientError> {
        let reply = self
            .send(
                Method::GET,
                path,
                None,
                Some(enc.content_type()),
                Bytes::new(),
            )
            .await?;
        Self::decode(reply, enc)
    }

    /// `POST /v1/rigs?name=NAME` with GLB or self-contained glTF bytes.
    pub async fn upload_rig(&self, name: &str, bytes: Bytes) -> Result<RigInfo, ClientError> {
        let reply = self
            .send(
                Method::POST,
                &format!("/v1/rigs?name={name}"),
                Some("model/gltf-binary"),
                Some(CONTENT_TYPE_JSON),
                bytes,
            )
            .await?;
        Self::decode(reply, Encoding::Json)
    }

    /// `GET /v1/rigs`.
    pub async fn rigs(&self) -> Result<RigList, ClientError> {
        self.get("/v1/rigs", Encoding::Json).await
    }

    /// `GET /v1/rigs/{id}`.
    pub async fn rig(&self, id: &str) -> Result<RigInfo, ClientError> {
        self.get(&format!("/v1/rigs/{id}"), Encoding::Json).await
    }

    /// `DELETE /v1/rigs/{id}`.
    pub async fn delete_rig(&self, id: &str) -> Result<(), ClientError> {
        let reply = self
            .send(
                Method::DELETE,
                &format!("/v1/rigs/{id}"),
                None,
                None,
                Bytes::new(),
            )
            .await?;
        if reply.status == 204 {
            Ok(())
        } else {
            Err(reply.into_error())
        }
    }

    /// `GET /v1/rigs/{id}/mesh`.
    pub async fn mesh(&self, id: &str, enc: Encoding) -> Result<MeshResponse, ClientError> {
        self.get(&format!("/v1/rigs/{id}/mesh"), enc).await
    }

    /// `GET /v1/rigs/{id}/mesh?lod=L`: the (possibly simplified) mesh LOD level `lod` uses.
    pub async fn mesh_at(
        &self,
        id: &str,
        lod: u32,
        enc: Encoding,
    ) -> Result<MeshResponse, ClientError> {
        self.get(&format!("/v1/rigs/{id}/mesh?lod={lod}"), enc)
            .await
    }

    /// `GET /v1/rigs/{id}/materials`: the rig's glTF `materials`, `textures`, `samplers`
    /// and `images` (each with a `uri` to fetch with [`Client::texture_at`]), its
    /// `extensionsUsed` and the import's `notes` (glTF-shaped JSON, kept as a value).
    pub async fn materials(&self, id: &str) -> Result<serde_json::Value, ClientError> {
        self.get(&format!("/v1/rigs/{id}/materials"), Encoding::Json)
            .await
    }

    /// `GET /v1/rigs/{id}/textures/{i}`: image `i`'s bytes and their content type.
    pub async fn texture(&self, id: &str, image: usize) -> Result<(Bytes, String), ClientError> {
        self.texture_at(&format!("/v1/rigs/{id}/textures/{image}"))
            .await
    }

    /// `GET /v1/rigs/{id}/model.glb?lod=L`: the rig's mesh at level `lod` as a GLB with its
    /// materials and images, no morph targets (load it once; write each frame's positions).
    pub async fn model_glb(&self, id: &str, lod: u32) -> Result<Bytes, ClientError> {
        let reply = self
            .send(
                Method::GET,
                &format!("/v1/rigs/{id}/model.glb?lod={lod}"),
                None,
                None,
                Bytes::new(),
            )
            .await?;
        if reply.status != 200 {
            return Err(reply.into_error());
        }
        Ok(reply.body)
    }

    /// An image by the `uri` [`Client::materials`] gives it (its `?v=` makes the answer
    /// cacheable forever): its bytes and content type.
    pub async fn texture_at(&self, uri: &str) -> Result<(Bytes, String), ClientError> {
        let reply = self
            .send(Method::GET, uri, None, None, Bytes::new())
            .await?;
        if reply.status != 200 {
            return Err(reply.into_error());
        }
        let ct = reply.content_type.clone().unwrap_or_default();
        Ok((reply.body, ct))
    }

    /// `GET /v1/rigs/{id}/lod`.
    pub async fn lod(&self, id: &str) -> Result<LodInfo, ClientError> {
        self.get(&format!("/v1/rigs/{id}/lod"), Encoding::Json)
            .await
    }

    /// `PUT /v1/rigs/{id}/lod`: rebuilds the rig's order, table and mesh levels.
    pub async fn set_lod(&self, id: &str, request: &LodRequest) -> Result<RigInfo, ClientError> {
        let body = Self::encode(request, Encoding::Json)?;
        let reply = self
            .send(
                Method::PUT,
                &format!("/v1/rigs/{id}/lod"),
                Some(CONTENT_TYPE_JSON),
                Some(CONTENT_TYPE_JSON),
                body,
            )
            .await?;
        Self::decode(reply, Encoding::Json)
    }

    /// `GET /v1/rigs/{id}/joint-map`: the clip columns that turn the rig's joints.
    pub async fn joint_map(&self, id: &str) -> Result<JointMapInfo, ClientError> {
        self.get(&format!("/v1/rigs/{id}/joint-map"), Encoding::Json)
            .await
    }

    /// `PUT /v1/rigs/{id}/joint-map`: gives the rig its own map of columns to joints.
    pub async fn set_joint_map(
        &self,
        id: &str,
        map: &JointMapSpec,
    ) -> Result<JointMapInfo, ClientError> {
        let body = Self::encode(map, Encoding::Json)?;
        let reply = self
            .send(
                Method::PUT,
                &format!("/v1/rigs/{id}/joint-map"),
                Some(CONTENT_TYPE_JSON),
                Some(CONTENT_TYPE_JSON),
                body,
            )
            .await?;
        Self::decode(reply, Encoding::Json)
    }

    /// `DELETE /v1/rigs/{id}/joint-map`: back to the default map.
    pub async fn reset_joint_map(&self, id: &str) -> Result<JointMapInfo, ClientError> {
        let reply = self
            .send(
                Method::DELETE,
                &format!("/v1/rigs/{id}/joint-map"),
                None,
                Some(CONTENT_TYPE_JSON),
                Bytes::new(),
            )
            .await?;
        Self::decode(reply, Encoding::Json)
    }

    /// `POST /v1/rigs/{id}/clips?name=NAME` with a CSV, JSON or glTF body of `content_type`.
    pub async fn upload_clip(
        &self,
        rig: &str,
        query: &str,
        content_type: &str,
        bytes: Bytes,
    ) -> Result<ClipUpload, ClientError> {
        let reply = self
            .send(
                Method::POST,
                &format!("/v1/rigs/{rig}/clips?{query}"),
                Some(content_type),
                Some(CONTENT_TYPE_JSON),
                bytes,
            )
            .await?;
        Self::decode(reply, Encoding::Json)
    }

    /// `GET /v1/rigs/{id}/clips`.
    pub async fn clips(&self, rig: &str) -> Result<ClipList, ClientError> {
        self.get(&format!("/v1/rigs/{rig}/clips"), Encoding::Json)
            .await
    }

    /// Encodes a request body.
    pub fn encode<T: Serialize>(value: &T, enc: Encoding) -> Result<Bytes, ClientError> {
        match enc {
            Encoding::Json => serde_json::to_vec(value)
                .map(Bytes::from)
                .map_err(|e| ClientError::Decode(e.to_string())),
            Encoding::Bincode => crowdmorph_proto::wire::to_bincode(value)
                .map(Bytes::from)
                .map_err(|e| ClientError::Decode(e.to_string())),
        }
    }

    /// `POST /v1/crowd/frame` with a pre-encoded body; returns the raw reply.
    pub async fn crowd_frame_raw(&self, body: Bytes, enc: Encoding) -> Result<Reply, ClientError> {
        self.send(
            Method::POST,
            "/v1/crowd/frame",
            Some(enc.content_type()),
            Some(enc.content_type()),
            body,
        )
        .await
    }

    /// `POST /v1/crowd/frame` with a pre-encoded body, reading the response without keeping
    /// it: returns the status and the body length as it came over the wire (compressed, and
    /// not inflated, when [`Client::with_compression`] asked for it). For load generators,
    /// which should spend as little CPU as possible.
    pub async fn crowd_frame_drain(
        &self,
        body: Bytes,
        enc: Encoding,
    ) -> Result<(u16, usize), ClientError> {
        let mut req = Request::builder()
            .method(Method::POST)
            .uri(format!("{}/v1/crowd/frame", self.base))
            .header("content-type", enc.content_type())
            .header("accept", enc.content_type());
        if let Some(t) = &self.token {
            req = req.header("authorization", format!("Bearer {t}"));
        }
        if let Some(c) = self.compression {
            req = req.header("accept-encoding", c.token());
        }
        let req = req
            .body(Full::new(body))
            .map_err(|e| ClientError::Transport(e.to_string()))?;
        let resp = self
            .http
            .request(req)
            .await
            .map_err(|e| ClientError::Transport(e.to_string()))?;
        let status = resp.status().as_u16();
        let mut body = resp.into_body();
        let mut len = 0;
        while let Some(frame) = body.frame().await {
            let frame = frame.map_err(|e| ClientError::Transport(e.to_string()))?;
            if let Some(d) = frame.data_ref() {
                len += d.len();
            }
        }
        Ok((status, len))
    }

    /// `POST /v1/crowd/frame?rig=...`: the response and its body size in bytes. The query
    /// is the routing hint (the first head's rig), which load balancers hash on.
    pub async fn crowd_frame(
        &self,
        req: &CrowdFrameRequest,
        enc: Encoding,
    ) -> Result<(CrowdFrameResponse, usize), ClientError> {
        let path = with_rig_hint("/v1/crowd/frame", req.heads.first().map(|h| h.rig.as_str()));
        let reply = self
            .send(
                Method::POST,
                &path,
                Some(enc.content_type()),
                Some(enc.content_type()),
                Self::encode(req, enc)?,
            )
            .await?;
        let len = reply.body.len();
        Ok((Self::decode(reply, enc)?, len))
    }

    /// `POST /v1/crowd/frame` with `"format": "weights"` (whatever `req.output.format` says):
    /// each head's final weights and moved joints, for a client that blends itself; the
    /// numbers are named by [`Client::rig_channels`].
    pub async fn crowd_poses(
        &self,
        req: &CrowdFrameRequest,
        enc: Encoding,
    ) -> Result<(crowdmorph_proto::CrowdPoseResponse, usize), ClientError> {
        let mut req = req.clone();
        req.output.format = crowdmorph_proto::Format::Weights;
        let path = with_rig_hint("/v1/crowd/frame", req.heads.first().map(|h| h.rig.as_str()));
        let reply = self
            .send(
                Method::POST,
                &path,
                Some(enc.content_type()),
                Some(enc.content_type()),
                Self::encode(&req, enc)?,
            )
            .await?;
        let len = reply.body.len();
        Ok((Self::decode(reply, enc)?, len))
    }

    /// `GET /v1/rigs/{id}/channels`: the rig's weight channels and skeleton nodes, in the
    /// order a pose ([`Client::crowd_poses`], a weights viewer's ticks) numbers them.
    pub async fn rig_channels(
        &self,
        id: &str,
    ) -> Result<crowdmorph_proto::RigChannels, ClientError> {
        self.get(&format!("/v1/rigs/{id}/channels"), Encoding::Json)
            .await
    }

    /// `POST /v1/crowd/frame` for faces driven by live weights (a face tracker's, an
    /// Audio2Face-style service's): head `i` is `faces[i]`, by name or dense in the order of
    /// `RigInfo::targets`, at LOD `lod`. Faces whose weights agree to 1/4096 share a buffer.
    pub async fn live_frame(
        &self,
        rig: &str,
        faces: Vec<crowdmorph_proto::LiveWeights>,
        lod: u32,
        output: crowdmorph_proto::OutputOptions,
        enc: Encoding,
    ) -> Result<(CrowdFrameResponse, usize), ClientError> {
        let heads = faces
            .into_iter()
            .enumerate()
            .map(|(i, w)| crowdmorph_proto::Head {
                lod,
                ..crowdmorph_proto::Head::live(i as u64, rig, w)
            })
            .collect();
        let req = CrowdFrameRequest {
            heads,
            output,
            wrap: true,
        };
        self.crowd_frame(&req, enc).await
    }

    /// The reference of [`crowdmorph_proto::Format::Q16R`] buffers of rig `rig` at LOD `lod`:
    /// the q16 positions of the frame with every weight 0 (an empty set of live weights), with
    /// the box they are in. Fetch it once per rig, LOD and box (a buffer's `quantization`).
    pub async fn q16_reference(
        &self,
        rig: &str,
        lod: u32,
    ) -> Result<(Vec<i16>, crowdmorph_proto::Quantization), ClientError> {
        let output = crowdmorph_proto::OutputOptions {
            normals: false,
            format: crowdmorph_proto::Format::Q16,
        };
        let (resp, _) = self
            .live_frame(
                rig,
                vec![crowdmorph_proto::LiveWeights::Named(Vec::new())],
                lod,
                output,
                Encoding::Bincode,
            )
            .await?;
        let b = resp
            .buffers
            .into_iter()
            .next()
            .ok_or_else(|| ClientError::Decode("no buffer in the reference frame".into()))?;
        let q = b
            .quantization
            .ok_or_else(|| ClientError::Decode("the reference frame is not q16".into()))?;
        let values = b
            .positions
            .0
            .chunks_exact(2)
            .map(|c| i16::from_le_bytes([c[0], c[1]]))
            .collect();
        Ok((values, q))
    }

    /// `POST /v1/crowd/render` with an encoded body: the reply whatever its status (an image
    /// with `x-image-width`, `x-image-height` and `Server-Timing`, or a JSON error).
    pub async fn render_raw(&self, body: Bytes, enc: Encoding) -> Result<Reply, ClientError> {
        self.send(
            Method::POST,
            "/v1/crowd/render",
            Some(enc.content_type()),
            None,
            body,
        )
        .await
    }

    /// `POST /v1/crowd/render?rig=...`: the image (PNG, JPEG or raw RGBA8 as the request
    /// asks) and its headers; an error status is [`ClientError::Api`]. The query is the
    /// routing hint, as for [`Client::crowd_frame`]. A framing camera
    /// ([`CameraSpec::frame`](crowdmorph_proto::CameraSpec::frame)) has no bincode form (that
    /// layout is pinned), so a request with one goes as JSON whatever `enc` says.
    pub async fn render(&self, req: &RenderRequest, enc: Encoding) -> Result<Reply, ClientError> {
        let enc = if req.camera.is_some_and(|c| c.frame.is_some()) {
            Encoding::Json
        } else {
            enc
        };
        let path = with_rig_hint(
            "/v1/crowd/render",
            req.heads.first().map(|h| h.rig.as_str()),
        );
        let reply = self
            .send(
                Method::POST,
                &path,
                Some(enc.content_type()),
                None,
                Self::encode(req, enc)?,
            )
            .await?;
        if !(200..300).contains(&reply.status) {
            return Err(reply.into_error());
        }
        Ok(reply)
    }

    /// Creates a session: `POST /v1/sessions` (the server names it), or with `id`
    /// `PUT /v1/sessions/{id}` (a balancer hashing on the id then sends every viewer of it to
    /// the same replica; a taken id is a 409 `session_exists`).
    pub async fn create_session(
        &self,
        req: &SessionRequest,
        id: Option<&str>,
        enc: Encoding,
    ) -> Result<SessionInfo, ClientError> {
        let (method, path) = match id {
            None => (Method::POST, "/v1/sessions".to_string()),
            Some(id) => (Method::PUT, format!("/v1/sessions/{}", percent_encode(id))),
        };
        let reply = self
            .send(
                method,
                &path,
                Some(enc.content_type()),
                Some(enc.content_type()),
                Self::encode(req, enc)?,
            )
            .await?;
        Self::decode(reply, enc)
    }

    /// `GET /metrics` as text.
    pub async fn metrics(&self) -> Result<String, ClientError> {
        let reply = self
            .send(Method::GET, "/metrics", None, None, Bytes::new())
            .await?;
        if reply.status != StatusCode::OK.as_u16() {
            return Err(reply.into_error());
        }
        Ok(String::from_utf8_lossy(&reply.body).into_owned())
    }
}

/// The value of a sample (first line starting with `name` followed by a space or `{`) in a
/// Prometheus or OpenMetrics text page (what `/metrics` answers). Comment lines (`# HELP`,
/// `# TYPE`, `# EOF`) are skipped; `name` may include the labels, as written on the page
/// (`crowdmorph_heads_total{source="api"}`), else the first series of the family is read.
pub fn metric(page: &str, name: &str) -> Option<f64> {
    page.lines()
        .filter(|l| !l.starts_with('#'))
        .find(|l| {
            l.strip_prefix(name)
                .is_some_and(|r| r.starts_with(' ') || r.starts_with('{'))
        })
        .and_then(|l| l.rsplit(' ').next())
        .and_then(|v| v.parse().ok())
}

#[cfg(test)]
mod tests {
    use super::{metric, with_rig_hint};

    #[test]
    fn the_rig_hint_is_a_percent_encoded_query_only_when_there_is_a_rig() {
        assert_eq!(with_rig_hint("/v1/crowd/frame", None), "/v1/crowd/frame");
        assert_eq!(
            with_rig_hint("/v1/crowd/frame", Some("")),
            "/v1/crowd/frame"
        );
        assert_eq!(
            with_rig_hint("/v1/crowd/frame", Some("default-head")),
            "/v1/crowd/frame?rig=default-head"
        );
        assert_eq!(
            with_rig_hint("/v1/crowd/render", Some("a b&c/é")),
            "/v1/crowd/render?rig=a%20b%26c%2F%C3%A9"
        );
    }

    /// What `prometheus-client` writes: counters with `_total` on their samples only, labels
    /// in declaration order, real numbers with a decimal point, `# EOF` last.
    const PAGE: &str = "# HELP crowdmorph_heads Heads served.\n\
        # TYPE crowdmorph_heads counter\n\
        crowdmorph_heads_total{source=\"api\"} 3\n\
        crowdmorph_heads_total{source=\"loadtest\"} 0\n\
        # HELP crowdmorph_heads_per_second Heads served during the last complete second.\n\
        # TYPE crowdmorph_heads_per_second gauge\n\
        crowdmorph_heads_per_second 2.5\n\
        # HELP crowdmorph_queue_seconds Queue time.\n\
        # TYPE crowdmorph_queue_seconds histogram\n\
        crowdmorph_queue_seconds_sum 0.5\n\
        crowdmorph_queue_seconds_count 2\n\
        crowdmorph_queue_seconds_bucket{le=\"5.0e-5\"} 1\n\
        crowdmorph_queue_seconds_bucket{le=\"+Inf\"} 2\n\
        # EOF\n";

    #[test]
    fn reads_openmetrics_samples() {
        assert_eq!(
            metric(PAGE, "crowdmorph_heads_total{source=\"api\"}"),
            Some(3.0)
        );
        assert_eq!(
            metric(PAGE, "crowdmorph_heads_total{source=\"loadtest\"}"),
            Some(0.0)
        );
        assert_eq!(metric(PAGE, "crowdmorph_heads_per_second"), Some(2.5));
        assert_eq!(metric(PAGE, "crowdmorph_queue_seconds_sum"), Some(0.5));
        assert_eq!(metric(PAGE, "crowdmorph_queue_seconds_count"), Some(2.0));
        assert_eq!(
            metric(PAGE, "crowdmorph_queue_seconds_bucket{le=\"+Inf\"}"),
            Some(2.0)
        );
        // Family names (of `# TYPE` lines) and `# EOF` are no samples.
        assert_eq!(metric(PAGE, "crowdmorph_heads"), None);
        assert_eq!(metric(PAGE, "EOF"), None);
        assert_eq!(metric(PAGE, "crowdmorph_queue"), None);
    }
}
