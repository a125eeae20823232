//! Render admission and drawing, for `POST /v1/crowd/render` and for session viewers that
//! want images: a request is resolved and planned exactly as a crowd frame (same snapshot rule,
//! same errors), laid out by [`crowdmorph_engine::render::scene`], drawn by
//! [`crowdmorph_engine::render::crowd::draw`] and encoded by [`crowdmorph_engine::render::encode`]
//! on the blocking pool. It sees the server through [`Rendering`].
//!
//! Three budgets bound what renders in
//! flight hold, all taken before any work ([`RenderBudget`]): the pixel budget
//! (`--render-pixels`; the image, from drawing until its bytes are sent), the render work budget
//! (`--render-work-ms`; the render's estimated duration, [`crowdmorph_engine::render::cost`], until it is
//! encoded) and the queue memory crowd frames also use (the unique jobs' blended vertices and
//! the request's heads). Session viewers' frames draw from the same pixel and work budgets but
//! together hold at most `--viewer-render-share` of each, so HTTP renders are served while
//! viewers stream. A render whose client hangs up or whose deadline passes stops at its next
//! stage boundary ([`crowdmorph_core::cancel`]): between engine calls, between render passes, before the
//! readback and before the encoding.
//! Mesh topologies are uploaded to the renderer once per rig generation and mesh level and kept
//! in a small LRU ([`crate::topologies::TopologyCache`]), so a frame uploads no indices. The cache keeps them only
//! for reuse: it is registered with the renderer's device, and a charge there that finds the
//! GPU budget full (a rig upload, a batch, a render) empties it first.

use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::http::{HeaderName, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use bytes::Bytes;
use crowdmorph_proto::{CameraFrame, ImageFormat, ImageOptions, MAX_IMAGE_SIDE, RenderRequest};
use tokio::sync::OwnedSemaphorePermit;

use super::Parts;
use crate::admission::resolve::job_request;
use crate::admission::{
    Charge, Priced, RenderBudget, RenderPermits, Renderee, ResolvedHeads, resolve_heads,
};
use crate::http::timing::ServerTiming;
use crate::http::{Accept, ApiError, SERVER_TIMING, blocking, chunked_body};
use crate::registry::RigEntry;
use crate::topologies::{RenderState, TopologyKey};
use crowdmorph_core::cancel::{Cancel, Cancelled};
use crowdmorph_core::rig::{Aabb, FrameMode};
use crowdmorph_engine::EngineError;
use crowdmorph_engine::render::appearance::texture_slots;
use crowdmorph_engine::render::cost::{Rates, RenderCost};
use crowdmorph_engine::render::crowd::{self, CrowdError, CrowdGroup, PlannedGroup, RenderDevice};
use crowdmorph_engine::render::encode::{self, ImageError};
use crowdmorph_engine::render::gpu::{Frame, MeshTopology, RenderError, View};
use crowdmorph_engine::render::scene::{self, SceneError};

/// Header with the image's width in pixels.
pub const IMAGE_WIDTH: HeaderName = HeaderName::from_static("x-image-width");
/// Header with the image's height in pixels.
pub const IMAGE_HEIGHT: HeaderName = HeaderName::from_static("x-image-height");

fn image_error(e: ImageError) -> ApiError {
    match e {
        ImageError::Invalid(m) => ApiError::bad_request("invalid_image", m),
        ImageError::TooLarge(m) => {
            ApiError::new(StatusCode::PAYLOAD_TOO_LARGE, "image_too_large", m)
        }
    }
}

fn scene_error(e: SceneError) -> ApiError {
    match e {
        SceneError::Placement(m) => ApiError::bad_request("invalid_placement", m),
        SceneError::Camera(m) => ApiError::bad_request("invalid_camera", m),
    }
}

fn crowd_error(e: CrowdError) -> ApiError {
    match e {
        CrowdError::Render(RenderError::TooLarge(m)) => {
            ApiError::new(StatusCode::PAYLOAD_TOO_LARGE, "image_too_large", m)
        }
        CrowdError::Render(RenderError::Memory(b)) => ApiError::budget(b, "image_too_large"),
        CrowdError::Engine(EngineError::GpuMemory(b)) => ApiError::budget(b, "response_too_large"),
        CrowdError::Render(RenderError::Device(m)) => ApiError::new(
            StatusCode::SERVICE_UNAVAILABLE,
            "render_unavailable",
            format!("the rendering device failed: {m}"),
        ),
        CrowdError::Engine(e @ (EngineError::DoesNotFit(_) | EngineError::TooLarge(_))) => {
            ApiError::new(
                StatusCode::PAYLOAD_TOO_LARGE,
                "response_too_large",
                e.to_string(),
            )
        }
        other => ApiError::internal(other),
    }
}

/// A render request checked, resolved, laid out and admitted: what the blocking pool draws.
pub struct RenderJob {
    image: ImageOptions,
    rigs: Vec<Arc<RigEntry>>,
    groups: Vec<PlannedGroup>,
    view: View,
    frame: Frame,
    /// Its share of the render budgets.
    permits: RenderPermits,
    /// The blended vertices and the request's heads; released once the crowd is drawn.
    vertices: Charge,
    /// Raised when the request is gone or late: the work stops at its next stage.
    cancel: Cancel,
    /// Whose render it is, for the cancellation metrics.
    who: Renderee,
}

/// An encoded image with what its response headers say.
pub struct Rendered {
    bytes: Vec<u8>,
    width: u32,
    height: u32,
    format: ImageFormat,
    timing: Option<HeaderValue>,
    pixels: OwnedSemaphorePermit,
}

impl Rendered {
    /// The response: the image, its type and size, the timing; its pixels held until sent.
    pub fn into_response(self) -> Response {
        let mut resp = (
            StatusCode::OK,
            [(
                header::CONTENT_TYPE,
                HeaderValue::from_static(self.format.content_type()),
            )],
            // The pixel permit goes with the body: the image's bytes count until they are sent.
            chunked_body(vec![Bytes::from(self.bytes)], self.pixels),
        )
            .into_response();
        let headers = resp.headers_mut();
        headers.insert(IMAGE_WIDTH, HeaderValue::from(self.width));
        headers.insert(IMAGE_HEIGHT, HeaderValue::from(self.height));
        if let Some(v) = self.timing {
            headers.insert(SERVER_TIMING, v);
        }
        resp
    }
}

/// The answer to a render stopped by its cancellation (its client is gone, or has its 504).
fn cancelled(c: Cancelled) -> ApiError {
    match c {
        Cancelled::Deadline => ApiError::new(
            StatusCode::GATEWAY_TIMEOUT,
            "deadline_exceeded",
            "the image was not ready within the request deadline",
        ),
        Cancelled::Dropped => ApiError::unavailable("cancelled", "the request was cancelled", 1),
    }
}

/// The scene of a render: each head's box placed (by the request's placements or the grid)
/// and the camera (the request's, checked, or one that frames the crowd). A camera framing
/// faces also gets each head's face region (its rig's, found once per rig generation).
fn lay_out(
    req: &RenderRequest,
    image: &ImageOptions,
    rigs: &[Arc<RigEntry>],
    plan: &crowdmorph_core::plan::Plan,
) -> Result<scene::Scene, ApiError> {
    let rig_boxes: Vec<Aabb> = rigs.iter().map(|e| e.rig().bbox()).collect();
    let boxes: Vec<Aabb> = plan
        .head_job
        .iter()
        .map(|&j| rig_boxes[plan.jobs[j as usize].rig as usize])
        .collect();
    let faces: Option<Vec<Aabb>> = req
        .camera
        .as_ref()
        .is_some_and(|c| c.frame == Some(CameraFrame::Faces))
        .then(|| {
            let rig_faces: Vec<Aabb> = rigs.iter().map(|e| e.face_region()).collect();
            plan.head_job
                .iter()
                .map(|&j| rig_faces[plan.jobs[j as usize].rig as usize])
                .collect()
        });
    let ids: Vec<u64> = req.heads.iter().map(|h| h.head).collect();
    scene::layout(
        &boxes,
        faces.as_deref(),
        &ids,
        req.placements.as_deref(),
        req.camera.as_ref(),
        image.width as f32 / image.height as f32,
    )
    .map_err(scene_error)
}

/// What rendering needs of the server: the renderer and its topologies, the render budgets,
/// (beside [`Parts`]). The provided methods are the
/// service.
pub trait Rendering: Parts {
    /// The renderer (or why there is none) and its topologies.
    fn render_state(&self) -> &RenderState;
    /// The pixels and work renders in flight hold.
    fn render_budget(&self) -> &RenderBudget;

    /// The renderer; 503 `render_unavailable` naming why (and what to install) without one.
    fn render_device(&self) -> Result<&RenderDevice, ApiError> {
        self.render_state().device.as_ref().map_err(|why| {
            ApiError::new(
                StatusCode::SERVICE_UNAVAILABLE,
                "render_unavailable",
                format!("this server cannot render: {why}"),
            )
        })
    }

    /// What rendering `plan` at `pixels` costs, and how long the renderer is estimated to take.
    fn render_cost(
        &self,
        device: &RenderDevice,
        rigs: &[Arc<RigEntry>],
        plan: &crowdmorph_core::plan::Plan,
        pixels: u64,
    ) -> (RenderCost, Duration) {
        let mut instances = vec![0u64; plan.jobs.len()];
        for &j in &plan.head_job {
            instances[j as usize] += 1;
        }
        // (vertices, triangles, texture slots) of each rig level, looked up once.
        let mut sizes: std::collections::HashMap<(u32, u32), (u64, u64, u32)> =
            std::collections::HashMap::new();
        let mut cost = RenderCost {
            pixels,
            ..RenderCost::default()
        };
        let mut slots = 0u32;
        for (k, &n) in plan.jobs.iter().zip(&instances) {
            let entry = &rigs[k.rig as usize];
            let (v, t, s) = *sizes.entry((k.rig, k.lod)).or_insert_with(|| {
                let rig = entry.prepared.at_level(k.lod).rig();
                (
                    rig.vertex_count() as u64,
                    rig.triangle_count() as u64,
                    texture_slots(rig),
                )
            });
            let blend = job_request(entry, &k.pose, k.lod, &k.joints).cost;
            cost.add_job(blend, n, v, t);
            slots = slots.max(s);
        }
        // Every pixel priced as if the most textured head covered it, as `pixels` is.
        cost.texture_fetches = pixels.saturating_mul(u64::from(slots));
        let rates = Rates::new(
            self.on_gpu() && device.shared,
            device.renderer.is_software(),
        );
        let estimate = cost.estimate(&rates);
        (cost, estimate)
    }

    /// The topology of `entry`'s mesh level `mesh` on the renderer, uploaded on first use.
    fn topology(
        &self,
        device: &RenderDevice,
        entry: &RigEntry,
        mesh: Option<usize>,
    ) -> Result<Arc<MeshTopology>, RenderError> {
        let key = TopologyKey {
            rig: entry.id.clone(),
            generation: entry.generation,
            mesh,
        };
        if let Some(t) = self
            .render_state()
            .topologies
            .lock()
            .ok()
            .and_then(|mut c| c.get(&key))
        {
            return Ok(t);
        }
        let rig = match mesh {
            Some(m) => entry
                .prepared
                .mesh_levels()
                .get(m)
                .map_or(entry.rig(), |l| l.rig()),
            None => entry.rig(),
        };
        let t = Arc::new(device.renderer.topology(rig)?);
        Ok(match self.render_state().topologies.lock() {
            // Read under the cache's lock: a delete removes the rig from the registry before
            // it purges the cache, so either this sees it gone or the purge comes after.
            Ok(mut c) => {
                let current = self.registry().get(&entry.id).map(|e| e.generation);
                c.insert_if_current(key, t, current)
            }
            Err(_) => t,
        })
    }

    /// Checks the image, resolves the heads (as a crowd frame does), lays out the scene,
    /// prices the render and takes its budgets; every refusal is the JSON error that names it.
    fn admit_render(
        &self,
        req: RenderRequest,
        held: Option<Charge>,
        who: Renderee,
        cancel: Cancel,
    ) -> Result<RenderJob, ApiError> {
        let max_side = self.max_side();
        let image = req.image.unwrap_or_default();
        encode::check_image(&image, max_side).map_err(image_error)?;
        let pixels = u64::from(image.width) * u64::from(image.height);
        if pixels > self.render_budget().pixels_limit() {
            // Checked before the heads, so the answer does not depend on them.
            return Err(self.render_budget().too_many_pixels(pixels, false));
        }
        let mode = if req.wrap {
            FrameMode::Wrap
        } else {
            FrameMode::Strict
        };
        let ResolvedHeads {
            rigs,
            plan,
            charge: poses,
        } = resolve_heads(
            self.registry(),
            self.queue_memory(),
            self.config().max_heads,
            &req.heads,
            mode,
            false,
        )?;
        let layout = lay_out(&req, &image, &rigs, &plan)?;
        // Checked after the request itself, so a client learns its own mistakes first.
        let device = self.render_device()?;
        let (cost, estimate) = self.render_cost(device, &rigs, &plan, pixels);
        let vertex_bytes: u64 = plan
            .jobs
            .iter()
            .map(|k| {
                let level = rigs[k.rig as usize].prepared.at_level(k.lod);
                crowd::job_bytes(level.rig().vertex_count())
            })
            .sum();
        self.check_render_memory(vertex_bytes, held.as_ref())?;
        let permits = self
            .render_budget()
            .reserve(pixels, estimate, &cost, who, self.metrics())?;
        let mut vertex_permit = self.queue_memory().reserve(vertex_bytes)?;
        if let Some(held) = held {
            vertex_permit.merge(held);
        }
        if let Some(poses) = poses {
            vertex_permit.merge(poses);
        }
        let groups = crowd::plan_groups(&plan, &layout.transforms, |k| {
            rigs[k.rig as usize].prepared.mesh_of(k.lod)
        });
        Ok(RenderJob {
            view: layout.view,
            frame: crowd::to_frame(image.width, image.height, image.background),
            image,
            rigs,
            groups,
            permits,
            vertices: vertex_permit,
            cancel,
            who,
        })
    }

    /// The request's own share (`held`, taken while it was decoded) and its blended
    /// vertices must fit the whole queue memory together: 413 when they never can.
    fn check_render_memory(
        &self,
        vertex_bytes: u64,
        held: Option<&Charge>,
    ) -> Result<(), ApiError> {
        let limit = self.queue_memory().limit();
        let held_bytes = held.map_or(0, Charge::bytes);
        if vertex_bytes.saturating_add(held_bytes) <= limit {
            return Ok(());
        }
        Err(ApiError::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            "response_too_large",
            format!(
                "drawing this crowd would hold {} bytes ({vertex_bytes} of blended \
                 vertices, {held_bytes} of its heads and placements), more than the \
                 server's queue memory of {limit} bytes (--queue-memory-bytes); ask for \
                 fewer unique heads, heads or placements",
                vertex_bytes.saturating_add(held_bytes)
            ),
        ))
    }

    /// Counts a render stopped by its cancellation and answers for it.
    fn render_cancelled(&self, who: Renderee, c: Cancelled) -> ApiError {
        let work = match who {
            Renderee::Http => "render",
            Renderee::Viewer => "session_frame",
        };
        self.metrics().cancelled(work, c);
        cancelled(c)
    }

    /// Draws and encodes an admitted render (blocking: engine, renderer and encoder), stopping
    /// at the next stage once the job's cancellation is raised.
    fn run_render(&self, job: RenderJob) -> Result<Rendered, ApiError> {
        let who = job.who;
        let stop = |c| self.render_cancelled(who, c);
        job.cancel.check().map_err(stop)?;
        let device = self.render_device()?;
        let mut groups = Vec::with_capacity(job.groups.len());
        for g in job.groups {
            let entry = &job.rigs[g.rig as usize];
            let topology = self
                .topology(device, entry, g.mesh)
                .map_err(|e| crowd_error(e.into()))?;
            groups.push(CrowdGroup {
                prepared: &entry.prepared,
                topology,
                jobs: g.jobs,
                instances: g.instances,
            });
        }
        let drawn = match crowd::draw_until(
            self.engine(),
            device,
            &groups,
            &job.view,
            &job.frame,
            &job.cancel,
        ) {
            Ok(d) => d,
            Err(CrowdError::Cancelled(c) | CrowdError::Render(RenderError::Cancelled(c))) => {
                return Err(stop(c));
            }
            Err(e) => return Err(crowd_error(e)),
        };
        drop(groups);
        drop(job.vertices);
        job.cancel.check().map_err(stop)?;
        let encoding = Instant::now();
        let out = drawn.output;
        let (width, height) = (out.width, out.height);
        let bytes = encode::encode(out.rgba, width, height, job.image.format, job.image.quality)
            .map_err(ApiError::internal)?;
        let timing = ServerTiming::default()
            .with("compute", Duration::from_nanos(drawn.compute_ns))
            .with("render", Duration::from_nanos(out.render_ns))
            .with("readback", Duration::from_nanos(out.readback_ns))
            .with("encode", encoding.elapsed())
            .header();
        // The work is done; the pixels stay held until the image is sent.
        drop(job.permits.work);
        Ok(Rendered {
            bytes,
            width,
            height,
            format: job.image.format,
            timing,
            pixels: job.permits.pixels,
        })
    }

    /// The largest image side the renderer draws.
    fn max_side(&self) -> u32 {
        self.render_state()
            .device
            .as_ref()
            .map_or(MAX_IMAGE_SIDE, |d| d.renderer.max_size())
    }

    /// Draws one tick for a session viewer that wants images: the same checks and drawing as
    /// `POST /v1/crowd/render`, within the viewers' share of the render budgets, stopped by
    /// `cancel` (the viewer leaving, or the deadline). Returns the encoded image, its size and
    /// encoding.
    fn render_for_session(
        &self,
        req: RenderRequest,
        cancel: Cancel,
    ) -> impl Future<Output = Result<(Vec<u8>, u32, u32, ImageFormat), ApiError>> + Send {
        // The heads and placements built for the viewer, and what admission builds from them,
        // are charged as an HTTP render's are (503 when the queue memory is full now: the
        // viewer's frame is dropped, not queued).
        let held = self
            .queue_memory()
            .reserve(req.price(Accept { bincode: true }));
        let s = self.clone();
        async move {
            let held = held?;
            let r = blocking(move || {
                let job = s.admit_render(req, Some(held), Renderee::Viewer, cancel)?;
                s.run_render(job)
            })
            .await?;
            Ok((r.bytes, r.width, r.height, r.format))
        }
    }
}
