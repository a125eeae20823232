//! `POST /v1/crowd/render`: a picture of a crowd, for clients that cannot draw meshes. The
//! handler decodes the request (its heads and placements charged), looks up rigs this replica
//! lacks, and hands admission, drawing and encoding to [`crate::services::render`] on the
//! blocking pool within the request's deadline.

use std::time::{Duration, Instant};

use axum::extract::State;
use axum::http::StatusCode;
use crowdmorph_proto::RenderRequest;

use crate::admission::resolve::heads_held_bytes;
use crate::admission::{Decoded, Priced, Renderee};
use crate::http::timing::Arrived;
use crate::http::{Accept, ApiError, ApiResult, Ready, blocking};
use crate::services::render::Rendering;
use crate::services::replicas::{find_missing, missing};
use crate::state::AppState;
use crowdmorph_core::cancel::Cancel;
use crowdmorph_engine::render::scene;

/// `POST /v1/crowd/render`: decode (the heads and placements charged), admit (image, heads,
/// scene, budgets), draw and encode on the blocking pool within the deadline.
pub async fn crowd_render(
    State(state): State<AppState>,
    Arrived(arrived): Arrived,
    _ready: Ready,
    Decoded(req): Decoded<RenderRequest>,
) -> ApiResult {
    let deadline = state
        .config
        .request_timeout
        .saturating_sub(arrived.elapsed())
        .max(Duration::from_millis(1));
    // The guard lives in this future: a 504 below, or the client hanging up (the future is
    // dropped), raises the cancellation and the drawing stops at its next stage.
    let (cancel, _guard) = Cancel::new(Some(Instant::now() + deadline));
    find_missing(
        &state,
        missing(&state, req.heads.iter().map(|h| h.rig.as_str())),
    )
    .await?;
    let (req, held) = req.into_parts();
    let s = state.clone();
    // Admission too runs on the blocking pool: it resolves every head and reads each rig's
    // box, work that grows with the request and must not hold an async worker.
    let draw = move || {
        let job = s.admit_render(req, Some(held), Renderee::Http, cancel)?;
        s.run_render(job)
    };
    let rendered = tokio::time::timeout(deadline, blocking(draw))
        .await
        .map_err(|_| {
            state.metrics.reject("deadline");
            ApiError::new(
                StatusCode::GATEWAY_TIMEOUT,
                "deadline_exceeded",
                format!(
                    "the image was not ready within the request deadline of {} ms",
                    state.config.request_timeout.as_millis()
                ),
            )
        })??;
    Ok(rendered.into_response())
}

/// What a render request holds per head and placement from its decoding until its frame is
/// drawn: the decoded head and its names, its placement, what admission builds per head (its
/// box, 24 bytes; its face box when the camera frames faces, 24; id, 8; job index, 4;
/// transform, 64; the instance matrix its group keeps, 64; the instance record the renderer
/// uploads, 112; and the per-job instance count, 8: 384 bytes cover them), and the map the scene layout builds of the placements before it checks them
/// against the heads ([`crowdmorph_engine::render::scene::placement_bytes`]: up to seven times a decoded
/// placement).
impl Priced for RenderRequest {
    fn price(&self, _: Accept) -> u64 {
        let heads = heads_held_bytes(&self.heads, RENDER_BYTES_PER_HEAD);
        let placements = self.placements.as_ref().map_or(0, |p| {
            p.capacity() as u64 * size_of::<crowdmorph_proto::Placement>() as u64
                + scene::placement_bytes(p.len())
        });
        heads + placements
    }
}

/// What admission builds per head of a render beyond the decoded head (see
/// [`RenderRequest`]'s [`Priced`]).
pub const RENDER_BYTES_PER_HEAD: u64 = 384;
