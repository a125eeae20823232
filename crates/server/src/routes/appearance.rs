//! What a rig looks like, for clients that draw it themselves: `GET /v1/rigs/{id}/materials`
//! (glTF-shaped JSON: materials, textures, samplers, and images as URIs) and
//! `GET /v1/rigs/{id}/textures/{i}` (an image's bytes as uploaded, or as downscaled to
//! `--max-texture-size`).
//!
//! `GET /v1/rigs/{id}/model.glb?lod=L` is the rig's mesh at one level as a GLB with its
//! materials and images and no morph targets, for engines that load a model once and write
//! each frame's positions into it.
//!
//! An image's `ETag` is a checksum of its bytes, so it is the same across generations,
//! restarts and replicas: the URIs `/materials` gives carry it as `?v=`, and a request with a
//! matching `v` is answered `Cache-Control: immutable` (a viewer fetches each image once per
//! rig, however many ticks and generations follow); without it, `no-cache` with the `ETag`
//! (and a 304 to `If-None-Match`).

use axum::body::Body;
use axum::extract::{Path, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::IntoResponse;

use crate::http::cache::Validator;
use crate::http::{self, ApiError, ApiResult, Query, Ready};
use crate::routes::rigs::MeshQuery;
use crate::services::Parts;
use crate::state::AppState;
use crowdmorph_core::rig::ImageData;

/// The `ETag` token of an image: CRC-32 and length of its bytes.
fn etag(image: &ImageData) -> String {
    format!(
        "{:08x}-{}",
        crc32fast::hash(&image.bytes),
        image.bytes.len()
    )
}

/// `GET /v1/rigs/{id}/materials`: glTF 2.0's `materials`, `textures`, `samplers` and `images`
/// of the rig (empty arrays when it has none), each image a `uri` to fetch with its size and
/// checksum, and the import's notes on what is not drawn.
pub async fn get_materials(
    State(state): State<AppState>,
    _ready: Ready,
    Path(id): Path<String>,
) -> ApiResult {
    let entry = state.rig(&id)?;
    let rig = entry.rig();
    // The JSON grows with the file's tables and names: charged to the queue memory (the
    // value and its text) until it is sent. An image's entry is its URI and numbers.
    let held = state
        .queue_memory
        .reserve(rig.appearance.as_deref().map_or(0, |a| {
            a.gltf_json_bytes(IMAGE_ENTRY_BYTES + 2 * id.len() as u64)
        }))?;
    let body = match rig.appearance.as_deref() {
        None => serde_json::json!({
            "rig": id, "materials": [], "textures": [], "samplers": [], "images": [],
            "extensionsUsed": [], "notes": [],
        }),
        Some(a) => {
            let mut tables = a.gltf_json(|i, image| {
                let tag = etag(image);
                let mut o = serde_json::json!({
                    "uri": format!("/v1/rigs/{id}/textures/{i}?v={tag}"),
                    "mimeType": image.mime.as_str(),
                    "width": image.width,
                    "height": image.height,
                    "etag": tag,
                });
                if let Some(d) = image.downscaled_from {
                    o["downscaledFrom"] = d.to_vec().into();
                }
                o
            });
            tables["rig"] = id.as_str().into();
            tables["extensionsUsed"] = a.extensions_used().into();
            tables["notes"] = a.notes.clone().into();
            tables
        }
    };
    Ok(http::body::json_held(&body, held))
}

/// Bytes of one image's entry in `/materials` besides its rig id (twice, in the URI and
/// `rig`): a URI, a MIME type, two sizes, a checksum, a downscale.
const IMAGE_ENTRY_BYTES: u64 = 512;

/// `?v=` of a texture request: the `ETag` token `/materials` gave.
#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TextureQuery {
    /// The `ETag` token, when the URI carries it.
    pub v: Option<String>,
}

/// `GET /v1/rigs/{id}/textures/{i}`: image `i`'s bytes with their content type.
pub async fn get_texture(
    State(state): State<AppState>,
    _ready: Ready,
    Path((id, index)): Path<(String, String)>,
    Query(query): Query<TextureQuery>,
    headers: HeaderMap,
) -> ApiResult {
    let entry = state.rig(&id)?;
    let rig = entry.rig();
    let images = rig.appearance.as_deref().map_or(&[][..], |a| &a.images[..]);
    let image = index
        .parse::<usize>()
        .ok()
        .and_then(|i| images.get(i))
        .ok_or_else(|| {
            ApiError::not_found(
                "unknown_texture",
                format!(
                    "rig {id:?} has no image {index:?} (it has {}; GET /v1/rigs/{id}/materials lists them)",
                    images.len()
                ),
            )
        })?;
    let validator = Validator::new(&etag(image), query.v.as_deref())?;
    if let Some(not_modified) = validator.not_modified(&headers) {
        return Ok(not_modified);
    }
    // The body shares the image's bytes (no copy); the response holds the rig's entry, so
    // they stay charged to the rig until sent.
    let bytes = bytes::Bytes::from_owner(ArcBytes(image.bytes.clone()));
    Ok(validator.respond(image.mime.as_str(), bytes, entry))
}

/// An image's shared bytes as a `Bytes` owner.
struct ArcBytes(std::sync::Arc<[u8]>);

impl AsRef<[u8]> for ArcBytes {
    fn as_ref(&self) -> &[u8] {
        &self.0
    }
}

/// `GET /v1/rigs/{id}/model.glb?lod=L`: level `L`'s mesh (default 0) as a self-contained GLB.
pub async fn get_model(
    State(state): State<AppState>,
    _ready: Ready,
    Path(id): Path<String>,
    Query(query): Query<MeshQuery>,
) -> ApiResult {
    let entry = state.rig(&id)?;
    let lod = query.level(&entry, &id)?;
    // The file copies the level's arrays and the images: charged to the queue memory (twice:
    // the JSON values and the bytes) until it is sent.
    let level = entry.prepared.at_level(lod).rig().clone();
    let held = state
        .queue_memory
        .reserve(2 * crowdmorph_engine::glb::model_glb_bytes(&level))?;
    let generation = entry.generation;
    let glb = http::blocking(move || {
        crowdmorph_engine::glb::model_glb(&level).map_err(ApiError::internal)
    })
    .await?;
    let etag =
        HeaderValue::from_str(&format!("\"g{generation}-l{lod}\"")).map_err(ApiError::internal)?;
    let response = (
        StatusCode::OK,
        [
            (
                header::CONTENT_TYPE,
                HeaderValue::from_static("model/gltf-binary"),
            ),
            (header::ETAG, etag),
            (header::CACHE_CONTROL, HeaderValue::from_static("no-cache")),
        ],
        Body::from(glb),
    )
        .into_response();
    Ok(http::body::hold(response, held))
}
