//! `POST /v1/crowd/render`: a picture of a crowd, for clients that cannot draw meshes.
//!
//! The request is resolved and planned exactly as a crowd frame (same snapshot rule, same
//! errors), laid out by [`crate::render::scene`], drawn by [`crate::render::crowd::draw`] and
//! encoded by [`crate::render::encode`] on the blocking pool. Three budgets bound what renders in
//! flight hold, all taken before any work ([`RenderBudget`]): the pixel budget
//! (`--render-pixels`; the image, from drawing until its bytes are sent), the render work budget
//! (`--render-work-ms`; the render's estimated duration, [`crate::render::cost`], until it is
//! encoded) and the queue memory crowd frames also use (the unique jobs' blended vertices and
//! the request's heads). Session viewers' frames draw from the same pixel and work budgets but
//! together hold at most `--viewer-render-share` of each, so HTTP renders are served while
//! viewers stream. A render whose client hangs up or whose deadline passes stops at its next
//! stage boundary ([`crate::cancel`]): between engine calls, between render passes, before the
//! readback and before the encoding.
//! Mesh topologies are uploaded to the renderer once per rig generation and mesh level and kept
//! in a small LRU ([`TopologyCache`]), so a frame uploads no indices. The cache keeps them only
//! for reuse: it is registered with the renderer's device, and a charge there that finds the
//! GPU budget full (a rig upload, a batch, a render) empties it first.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use axum::body::Body;
use axum::extract::State;
use axum::http::{HeaderMap, HeaderName, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use bytes::Bytes;
use crowdmorph_proto::{ImageFormat, ImageOptions, MAX_IMAGE_SIDE, RenderRequest};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

use super::api::{ApiResult, ResolvedHeads, blocking, chunked_body, job_request};
use super::registry::RigEntry;
use super::{ApiError, AppState};
use crate::cancel::{Cancel, Cancelled};
use crate::engine::EngineError;
use crate::engine::gpu::Reclaim;
use crate::render::cost::{Rates, RenderCost};
use crate::render::crowd::{self, CrowdError, CrowdGroup, PlannedGroup, RenderDevice};
use crate::render::encode::{self, ImageError};
use crate::render::gpu::{Frame, MeshTopology, RenderError, Renderer, View};
use crate::render::scene::{self, SceneError};
use crate::rig::{Aabb, FrameMode};

/// Header with the image's width in pixels.
pub const IMAGE_WIDTH: HeaderName = HeaderName::from_static("x-image-width");
/// Header with the image's height in pixels.
pub const IMAGE_HEIGHT: HeaderName = HeaderName::from_static("x-image-height");
/// The Server-Timing header (RFC: W3C Server Timing).
pub const SERVER_TIMING: HeaderName = HeaderName::from_static("server-timing");

/// Most topologies kept on the renderer's device.
const TOPOLOGY_ENTRIES: usize = 32;
/// Most bytes of index (and other topology) buffers kept on the renderer's device.
const TOPOLOGY_BYTES: u64 = 512 << 20;

/// Which mesh a topology is of: a rig's generation and mesh level (`None`: the full mesh).
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
struct TopologyKey {
    rig: String,
    generation: u64,
    mesh: Option<usize>,
}

/// What a cache entry occupies.
pub trait Footprint {
    /// Bytes it holds (on the device, for a topology).
    fn bytes(&self) -> u64;
}

impl Footprint for MeshTopology {
    fn bytes(&self) -> u64 {
        MeshTopology::bytes(self)
    }
}

/// Topologies uploaded to the renderer, most recently used last, bounded by count and bytes
/// (`T` is a parameter so the eviction rules are tested without a device).
pub struct TopologyCache<T = MeshTopology> {
    entries: Vec<(TopologyKey, Arc<T>)>,
    bytes: u64,
}

impl<T> Default for TopologyCache<T> {
    fn default() -> Self {
        TopologyCache {
            entries: Vec::new(),
            bytes: 0,
        }
    }
}

impl<T> std::fmt::Debug for TopologyCache<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TopologyCache")
            .field("entries", &self.entries.len())
            .field("bytes", &self.bytes)
            .finish()
    }
}

impl<T: Footprint> TopologyCache<T> {
    fn get(&mut self, key: &TopologyKey) -> Option<Arc<T>> {
        let i = self.entries.iter().position(|(k, _)| k == key)?;
        let e = self.entries.remove(i);
        let t = e.1.clone();
        self.entries.push(e);
        Some(t)
    }

    /// Keeps `t` for `key` unless `current` (the rig's registered generation now, `None` when
    /// it is gone) says `key`'s generation was deleted or replaced while `t` was uploaded: the
    /// delete's purge may already have run, and nothing but the LRU would drop it. Returns the
    /// topology to use.
    fn insert_if_current(&mut self, key: TopologyKey, t: Arc<T>, current: Option<u64>) -> Arc<T> {
        if current == Some(key.generation) {
            self.insert(key, t)
        } else {
            t
        }
    }

    fn insert(&mut self, key: TopologyKey, t: Arc<T>) -> Arc<T> {
        // Another render may have uploaded the same topology meanwhile: keep one.
        if let Some(existing) = self.get(&key) {
            return existing;
        }
        self.bytes += t.bytes();
        self.entries.push((key, t.clone()));
        while self.entries.len() > TOPOLOGY_ENTRIES
            || (self.bytes > TOPOLOGY_BYTES && self.entries.len() > 1)
        {
            let (_, old) = self.entries.remove(0);
            self.bytes -= old.bytes();
        }
        t
    }

    /// Forgets every topology, returning them so the caller can drop them outside its lock.
    fn take_all(&mut self) -> Vec<(TopologyKey, Arc<T>)> {
        self.bytes = 0;
        std::mem::take(&mut self.entries)
    }

    /// Forgets every topology of rig `id` (it was deleted): its device memory is freed once
    /// renders in flight drop their handles.
    pub fn purge(&mut self, id: &str) {
        let bytes = &mut self.bytes;
        self.entries.retain(|(k, t)| {
            let keep = k.rig != id;
            if !keep {
                *bytes -= t.bytes();
            }
            keep
        });
    }
}

/// The cache gives its topologies up when the device's budget is full: a render in flight that
/// uses one holds its own `Arc`, so its index buffer lives (and stays charged) until that render
/// ends; the others are freed at once, and a later render uploads them again.
impl<T: Footprint + Send + Sync> Reclaim for Mutex<TopologyCache<T>> {
    fn reclaim(&self) -> bool {
        // Not waited for: a holder is looking a topology up or inserting one right now.
        let dropped = match self.try_lock() {
            Ok(mut cache) => cache.take_all(),
            Err(_) => return false,
        };
        !dropped.is_empty()
    }
}

/// What rendering needs in the server state: the device, or why there is none, and the
/// topologies uploaded to it.
#[derive(Debug)]
pub struct RenderState {
    /// The renderer, or why there is none.
    pub device: Result<RenderDevice, String>,
    /// Topologies on its device (registered with the device as memory kept for reuse).
    pub topologies: Arc<Mutex<TopologyCache>>,
}

impl RenderState {
    /// The state of `device`, with an empty topology cache registered with the renderer's
    /// device, so a full GPU budget empties it.
    pub fn new(device: Result<RenderDevice, String>) -> RenderState {
        let topologies = Arc::new(Mutex::new(TopologyCache::default()));
        if let Ok(d) = &device {
            d.renderer
                .register_reclaim(Arc::downgrade(&topologies) as std::sync::Weak<dyn Reclaim>);
        }
        RenderState { device, topologies }
    }

    /// The adapter that renders, for `/readyz`.
    pub fn adapter_name(&self) -> Option<String> {
        self.device.as_ref().ok().map(RenderDevice::name)
    }
}

/// Who a render is for: session viewers' frames hold a capped share of the budgets.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Renderee {
    /// `POST /v1/crowd/render`.
    Http,
    /// A session viewer that asked for frames.
    Viewer,
}

/// The render budgets: pixels in flight (memory: targets, read-back pixels, the encoded image)
/// and estimated work in flight (time: blending, drawing, encoding, in microseconds of the
/// drawing device's [`Rates`]), each with the share that session viewers may hold together.
#[derive(Debug)]
pub struct RenderBudget {
    pixels: Arc<Semaphore>,
    pixels_limit: u64,
    work: Arc<Semaphore>,
    work_limit_us: u64,
    viewer_pixels: Arc<Semaphore>,
    viewer_pixels_limit: u64,
    viewer_work: Arc<Semaphore>,
    viewer_work_limit_us: u64,
}

/// A semaphore of `n` permits (at most the most tokio allows).
fn semaphore(n: u64) -> Arc<Semaphore> {
    Arc::new(Semaphore::new(
        usize::try_from(n)
            .unwrap_or(usize::MAX)
            .min(Semaphore::MAX_PERMITS),
    ))
}

impl RenderBudget {
    /// Budgets of `pixels` and `work`, of which viewers may hold `viewer_share` (0 to 1).
    pub fn new(pixels: u64, work: Duration, viewer_share: f64) -> RenderBudget {
        let share = if viewer_share.is_finite() {
            viewer_share.clamp(0.0, 1.0)
        } else {
            0.0
        };
        let work_us = u64::try_from(work.as_micros()).unwrap_or(u64::MAX).max(1);
        let viewer_pixels = (pixels as f64 * share) as u64;
        let viewer_work = (work_us as f64 * share) as u64;
        RenderBudget {
            pixels: semaphore(pixels),
            pixels_limit: pixels,
            work: semaphore(work_us),
            work_limit_us: work_us,
            viewer_pixels: semaphore(viewer_pixels),
            viewer_pixels_limit: viewer_pixels,
            viewer_work: semaphore(viewer_work),
            viewer_work_limit_us: viewer_work,
        }
    }

    /// Pixels held now, and the limit.
    pub fn pixels(&self) -> (u64, u64) {
        let free = self.pixels.available_permits() as u64;
        (self.pixels_limit.saturating_sub(free), self.pixels_limit)
    }

    /// Estimated work held now, and the limit, in seconds.
    pub fn work_seconds(&self) -> (f64, f64) {
        let free = self.work.available_permits() as u64;
        (
            self.work_limit_us.saturating_sub(free) as f64 * 1e-6,
            self.work_limit_us as f64 * 1e-6,
        )
    }

    /// Seconds until the work held now has drained, as a Retry-After (1 to 60).
    fn retry_after(&self) -> u32 {
        let (held, _) = self.work_seconds();
        held.ceil().clamp(1.0, 60.0) as u32
    }
}

/// What an admitted render holds of the [`RenderBudget`]: the pixels go with the response
/// body, the work is given back once the image is encoded.
struct RenderPermits {
    pixels: OwnedSemaphorePermit,
    work: OwnedSemaphorePermit,
    /// A viewer's frame also holds its share.
    _viewer: Option<(OwnedSemaphorePermit, OwnedSemaphorePermit)>,
}

/// Tries to take `n` permits of `s`: `None` when they are not free now.
fn take(s: &Arc<Semaphore>, n: u64) -> Option<OwnedSemaphorePermit> {
    s.clone()
        .try_acquire_many_owned(u32::try_from(n).ok()?)
        .ok()
}

impl AppState {
    /// The renderer, when the server has one (tests reach its race-window hook,
    /// [`Renderer::set_after_submit`], through it).
    #[doc(hidden)]
    pub fn renderer(&self) -> Option<&Renderer> {
        self.render.device.as_ref().ok().map(|d| &d.renderer)
    }

    /// The renderer; 503 `render_unavailable` naming why (and what to install) without one.
    fn render_device(&self) -> Result<&RenderDevice, ApiError> {
        self.render.device.as_ref().map_err(|why| {
            ApiError::new(
                StatusCode::SERVICE_UNAVAILABLE,
                "render_unavailable",
                format!("this server cannot render: {why}"),
            )
        })
    }

    /// Takes the render budgets for an image of `pixels` and an estimated duration of
    /// `estimate`: 413 when the render can never fit (larger than the whole budget, or than
    /// the share viewers may hold), 503 `render_busy` with a Retry-After when renders in flight
    /// hold too much now.
    fn reserve_render(
        &self,
        pixels: u64,
        estimate: Duration,
        cost: &RenderCost,
        who: Renderee,
    ) -> Result<RenderPermits, ApiError> {
        let b = &self.render_budget;
        let viewer = who == Renderee::Viewer;
        let (pixel_limit, work_limit_us) = if viewer {
            (b.viewer_pixels_limit, b.viewer_work_limit_us)
        } else {
            (b.pixels_limit, b.work_limit_us)
        };
        if pixels > pixel_limit {
            return Err(self.too_many_pixels(pixels, viewer));
        }
        let work_us = u64::try_from(estimate.as_micros())
            .unwrap_or(u64::MAX)
            .max(1);
        if work_us > work_limit_us {
            self.metrics.reject("render_too_costly");
            let flag = if viewer {
                format!(
                    "{} ms, the share session viewers may hold (--viewer-render-share) of the \
                     render work budget (--render-work-ms)",
                    work_limit_us / 1000
                )
            } else {
                format!(
                    "the render work budget of {} ms (--render-work-ms)",
                    work_limit_us / 1000
                )
            };
            return Err(ApiError::new(
                StatusCode::PAYLOAD_TOO_LARGE,
                "render_too_costly",
                format!(
                    "drawing this crowd is estimated at {:.0} ms on this server's renderer \
                     ({} blend work, {} vertices and {} triangles drawn, {} pixels), more than \
                     {flag}; ask for fewer heads, a coarser lod or a smaller image",
                    estimate.as_secs_f64() * 1e3,
                    cost.blend,
                    cost.vertices,
                    cost.triangles,
                    cost.pixels
                ),
            ));
        }
        let busy = |what: &str| {
            self.metrics.reject("render_busy");
            ApiError::unavailable(
                "render_busy",
                format!("renders in flight hold the server's {what}; retry shortly"),
                b.retry_after(),
            )
        };
        let share = if viewer {
            let p = take(&b.viewer_pixels, pixels).ok_or_else(|| {
                busy("share of the render budget that session viewers may hold (--viewer-render-share)")
            })?;
            let w = take(&b.viewer_work, work_us).ok_or_else(|| {
                busy("share of the render budget that session viewers may hold (--viewer-render-share)")
            })?;
            Some((p, w))
        } else {
            None
        };
        let pixel_permit = take(&b.pixels, pixels).ok_or_else(|| {
            busy(&format!(
                "render budget of {} pixels (--render-pixels)",
                b.pixels_limit
            ))
        })?;
        let work = take(&b.work, work_us).ok_or_else(|| {
            busy(&format!(
                "render work budget of {} ms (--render-work-ms)",
                b.work_limit_us / 1000
            ))
        })?;
        Ok(RenderPermits {
            pixels: pixel_permit,
            work,
            _viewer: share,
        })
    }

    /// 413 for an image larger than the whole pixel budget (or a viewer's share of it).
    fn too_many_pixels(&self, pixels: u64, viewer: bool) -> ApiError {
        let b = &self.render_budget;
        let (limit, flag) = if viewer {
            (
                b.viewer_pixels_limit,
                "the share session viewers may hold (--viewer-render-share) of --render-pixels",
            )
        } else {
            (b.pixels_limit, "--render-pixels")
        };
        ApiError::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            "image_too_large",
            format!(
                "an image of {pixels} pixels is larger than the server's render budget of \
                 {limit} pixels ({flag})"
            ),
        )
    }

    /// What rendering `plan` at `pixels` costs, and how long the renderer is estimated to take.
    fn render_cost(
        &self,
        device: &RenderDevice,
        rigs: &[Arc<RigEntry>],
        plan: &crate::plan::Plan,
        pixels: u64,
    ) -> (RenderCost, Duration) {
        let mut instances = vec![0u64; plan.jobs.len()];
        for &j in &plan.head_job {
            instances[j as usize] += 1;
        }
        // (vertices, triangles) of each rig level, looked up once.
        let mut sizes: std::collections::HashMap<(u32, u32), (u64, u64)> =
            std::collections::HashMap::new();
        let mut cost = RenderCost {
            pixels,
            ..RenderCost::default()
        };
        for (k, &n) in plan.jobs.iter().zip(&instances) {
            let entry = &rigs[k.rig as usize];
            let (v, t) = *sizes.entry((k.rig, k.lod)).or_insert_with(|| {
                let rig = entry.prepared.at_level(k.lod).rig();
                (rig.vertex_count() as u64, rig.triangle_count() as u64)
            });
            let blend = job_request(entry, k.clip, k.frame, k.lod).cost;
            cost.add_job(blend, n, v, t);
        }
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
            .render
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
        Ok(match self.render.topologies.lock() {
            // Read under the cache's lock: a delete removes the rig from the registry before
            // it purges the cache, so either this sees it gone or the purge comes after.
            Ok(mut c) => {
                let current = self.registry.get(&entry.id).map(|e| e.generation);
                c.insert_if_current(key, t, current)
            }
            Err(_) => t,
        })
    }
}

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
        CrowdError::Render(RenderError::Memory(b)) => {
            super::api::budget_error(b, "image_too_large")
        }
        CrowdError::Engine(EngineError::GpuMemory(b)) => {
            super::api::budget_error(b, "response_too_large")
        }
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

/// Milliseconds with three decimals, as Server-Timing wants them.
/// A duration as a `Server-Timing` `dur` value: milliseconds with three decimals.
pub(super) fn ms(d: Duration) -> String {
    format!("{:.3}", d.as_secs_f64() * 1e3)
}

/// A render request checked, resolved, laid out and admitted: what the blocking pool draws.
struct RenderJob {
    image: ImageOptions,
    rigs: Vec<Arc<RigEntry>>,
    groups: Vec<PlannedGroup>,
    view: View,
    frame: Frame,
    /// Its share of the render budgets.
    permits: RenderPermits,
    /// The blended vertices and the request's heads; released once the crowd is drawn.
    vertices: OwnedSemaphorePermit,
    /// Raised when the request is gone or late: the work stops at its next stage.
    cancel: Cancel,
    /// Whose render it is, for the cancellation metrics.
    who: Renderee,
}

/// An encoded image with what its response headers say.
struct Rendered {
    bytes: Vec<u8>,
    width: u32,
    height: u32,
    format: ImageFormat,
    timing: String,
    pixels: OwnedSemaphorePermit,
}

impl Rendered {
    fn into_response(self) -> Response {
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
        if let Ok(v) = HeaderValue::from_str(&self.timing) {
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

impl AppState {
    /// Checks the image, resolves the heads (as a crowd frame does), lays out the scene,
    /// prices the render and takes its budgets; every refusal is the JSON error that names it.
    fn admit_render(
        &self,
        req: RenderRequest,
        max_side: u32,
        held: Option<OwnedSemaphorePermit>,
        who: Renderee,
        cancel: Cancel,
    ) -> Result<RenderJob, ApiError> {
        let image = req.image.unwrap_or_default();
        encode::check_image(&image, max_side).map_err(image_error)?;
        let pixels = u64::from(image.width) * u64::from(image.height);
        if pixels > self.render_budget.pixels_limit {
            // Checked before the heads, so the answer does not depend on them.
            return Err(self.too_many_pixels(pixels, false));
        }
        let mode = if req.wrap {
            FrameMode::Wrap
        } else {
            FrameMode::Strict
        };
        let ResolvedHeads { rigs, plan } = self.resolve_heads(&req.heads, mode, false)?;
        let rig_boxes: Vec<Aabb> = rigs.iter().map(|e| e.rig().bbox()).collect();
        let boxes: Vec<Aabb> = plan
            .head_job
            .iter()
            .map(|&j| rig_boxes[plan.jobs[j as usize].rig as usize])
            .collect();
        let ids: Vec<u64> = req.heads.iter().map(|h| h.head).collect();
        let layout = scene::layout(
            &boxes,
            &ids,
            req.placements.as_deref(),
            req.camera.as_ref(),
            image.width as f32 / image.height as f32,
        )
        .map_err(scene_error)?;
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
        let limit = u64::from(self.memory_units) * 1024;
        // The request's own share (`held`, taken while it was decoded) and the vertices must
        // fit the whole queue together.
        let held_bytes = held.as_ref().map_or(0, |p| p.num_permits() as u64 * 1024);
        if vertex_bytes.saturating_add(held_bytes) > limit {
            return Err(ApiError::new(
                StatusCode::PAYLOAD_TOO_LARGE,
                "response_too_large",
                format!(
                    "drawing this crowd would hold {} bytes ({vertex_bytes} of blended \
                     vertices, {held_bytes} of its heads and placements), more than the \
                     server's queue memory of {limit} bytes (--queue-memory-bytes); ask for \
                     fewer unique heads, heads or placements",
                    vertex_bytes.saturating_add(held_bytes)
                ),
            ));
        }
        let permits = self.reserve_render(pixels, estimate, &cost, who)?;
        let mut vertex_permit = self.reserve_queue_memory(vertex_bytes)?;
        if let Some(held) = held {
            vertex_permit.merge(held);
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

    /// Counts a render stopped by its cancellation and answers for it.
    fn render_cancelled(&self, who: Renderee, c: Cancelled) -> ApiError {
        let work = match who {
            Renderee::Http => "render",
            Renderee::Viewer => "session_frame",
        };
        self.metrics.cancelled(work, c);
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
            &self.engine,
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
        let timing = format!(
            "compute;dur={}, render;dur={}, readback;dur={}, encode;dur={}",
            ms(Duration::from_nanos(drawn.compute_ns)),
            ms(Duration::from_nanos(out.render_ns)),
            ms(Duration::from_nanos(out.readback_ns)),
            ms(encoding.elapsed())
        );
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
        self.render
            .device
            .as_ref()
            .map_or(MAX_IMAGE_SIDE, |d| d.renderer.max_size())
    }
}

impl AppState {
    /// Draws one tick for a session viewer that wants images: the same checks and drawing as
    /// `POST /v1/crowd/render`, within the viewers' share of the render budgets, stopped by
    /// `cancel` (the viewer leaving, or the deadline). Returns the encoded image, its size and
    /// encoding.
    pub(super) async fn render_for_session(
        &self,
        req: RenderRequest,
        cancel: Cancel,
    ) -> Result<(Vec<u8>, u32, u32, ImageFormat), ApiError> {
        let job = self.admit_render(req, self.max_side(), None, Renderee::Viewer, cancel)?;
        let s = self.clone();
        let r = blocking(move || s.run_render(job)).await?;
        Ok((r.bytes, r.width, r.height, r.format))
    }
}

pub(super) async fn crowd_render(
    State(state): State<AppState>,
    headers: HeaderMap,
    body: Body,
) -> ApiResult {
    let arrived = Instant::now();
    state.check_ready()?;
    let max_side = state.max_side();
    let (req, held): (RenderRequest, _) = state
        .crowd_request_held(&headers, body, render_held_bytes)
        .await?;
    let deadline = state
        .config
        .request_timeout
        .saturating_sub(arrived.elapsed())
        .max(Duration::from_millis(1));
    // The guard lives in this future: a 504 below, or the client hanging up (the future is
    // dropped), raises the cancellation and the drawing stops at its next stage.
    let (cancel, _guard) = Cancel::new(Some(Instant::now() + deadline));
    let job = state.admit_render(req, max_side, Some(held), Renderee::Http, cancel)?;
    let s = state.clone();
    let rendered = tokio::time::timeout(deadline, blocking(move || s.run_render(job)))
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
/// box, 24 bytes; id, 8; job index, 4; transform, 64; the instance matrix its group keeps, 64;
/// the instance record the renderer uploads, 112; and the per-job instance count, 8: 384 bytes
/// cover them), and the map the scene layout builds of the placements before it checks them
/// against the heads ([`crate::render::scene::placement_bytes`]: up to seven times a decoded
/// placement).
fn render_held_bytes(req: &RenderRequest) -> u64 {
    let heads = super::api::heads_held_bytes(&req.heads, 384);
    let placements = req.placements.as_ref().map_or(0, |p| {
        p.capacity() as u64 * size_of::<crowdmorph_proto::Placement>() as u64
            + scene::placement_bytes(p.len())
    });
    heads + placements
}

#[cfg(test)]
mod tests {
    use super::*;

    struct Sized(u64);

    impl Footprint for Sized {
        fn bytes(&self) -> u64 {
            self.0
        }
    }

    fn key(rig: &str, generation: u64) -> TopologyKey {
        TopologyKey {
            rig: rig.into(),
            generation,
            mesh: None,
        }
    }

    #[test]
    fn the_topology_cache_keeps_the_most_recently_used_within_its_bounds() {
        let mut c = TopologyCache::default();
        for g in 0..TOPOLOGY_ENTRIES as u64 {
            c.insert(key("a", g), Arc::new(Sized(1)));
        }
        // Using generation 0 makes generation 1 the oldest, which the next insert evicts.
        assert!(c.get(&key("a", 0)).is_some());
        c.insert(key("b", 0), Arc::new(Sized(1)));
        assert_eq!(c.entries.len(), TOPOLOGY_ENTRIES);
        assert!(c.get(&key("a", 1)).is_none() && c.get(&key("a", 0)).is_some());
        // A second upload of the same key keeps the first.
        let first = c.get(&key("b", 0)).expect("cached");
        let kept = c.insert(key("b", 0), Arc::new(Sized(1)));
        assert!(Arc::ptr_eq(&first, &kept));
        assert_eq!(c.bytes, TOPOLOGY_ENTRIES as u64);
        // Past the byte bound, the oldest go, but the newest always stays.
        c.insert(key("huge", 0), Arc::new(Sized(TOPOLOGY_BYTES + 1)));
        assert_eq!(c.entries.len(), 1);
        assert_eq!(c.bytes, TOPOLOGY_BYTES + 1);
        c.insert(key("a", 7), Arc::new(Sized(3)));
        assert_eq!((c.entries.len(), c.bytes), (1, 3), "the huge one made room");
        // A deleted rig's topologies go, whatever their generation and mesh.
        c.insert(key("a", 8), Arc::new(Sized(4)));
        c.insert(key("c", 0), Arc::new(Sized(5)));
        c.purge("a");
        assert_eq!((c.entries.len(), c.bytes), (1, 5));
        assert!(c.get(&key("c", 0)).is_some());
        // An upload that a delete or a replacement overtook is used but not kept.
        let late = c.insert_if_current(key("d", 1), Arc::new(Sized(6)), None);
        assert_eq!(late.0, 6);
        c.insert_if_current(key("d", 1), Arc::new(Sized(6)), Some(2));
        assert!(c.get(&key("d", 1)).is_none());
        assert_eq!((c.entries.len(), c.bytes), (1, 5));
        c.insert_if_current(key("d", 2), Arc::new(Sized(6)), Some(2));
        assert!(c.get(&key("d", 2)).is_some());
    }

    #[test]
    fn a_reclaim_empties_the_cache_but_topologies_in_use_stay_alive() {
        let cache = Mutex::new(TopologyCache::default());
        assert!(!cache.reclaim(), "nothing to give back");
        let in_use = Arc::new(Sized(10));
        if let Ok(mut c) = cache.lock() {
            c.insert(key("a", 0), in_use.clone());
            c.insert(key("b", 0), Arc::new(Sized(20)));
        }
        let idle = Arc::downgrade(&cache.lock().expect("lock").get(&key("b", 0)).expect("b"));
        // A holder of the lock is not waited for.
        {
            let _held = cache.lock().expect("lock");
            assert!(!cache.reclaim());
        }
        assert!(cache.reclaim());
        let c = cache.lock().expect("lock");
        assert_eq!((c.entries.len(), c.bytes), (0, 0));
        assert!(idle.upgrade().is_none(), "an idle topology is freed");
        // One a render holds lives on, now held by that render alone.
        assert_eq!(Arc::strong_count(&in_use), 1);
    }

    #[test]
    fn viewers_hold_at_most_their_share_and_http_renders_keep_the_rest() {
        let b = RenderBudget::new(1_000, Duration::from_millis(100), 0.5);
        assert_eq!(
            (b.viewer_pixels_limit, b.viewer_work_limit_us),
            (500, 50_000)
        );
        // Viewers take their whole share...
        let v1 = (take(&b.viewer_pixels, 300), take(&b.pixels, 300));
        let v2 = (take(&b.viewer_pixels, 200), take(&b.pixels, 200));
        assert!(v1.0.is_some() && v1.1.is_some() && v2.0.is_some() && v2.1.is_some());
        // ...and no more, while half of the budget stays for HTTP renders.
        assert!(take(&b.viewer_pixels, 1).is_none());
        assert_eq!(b.pixels(), (500, 1_000));
        let http = take(&b.pixels, 500);
        assert!(http.is_some());
        assert!(take(&b.pixels, 1).is_none());
        drop((v1, v2, http));
        assert_eq!(b.pixels(), (0, 1_000));
        // Retry-After follows the work held: 1 s at least, a minute at most.
        assert_eq!(b.retry_after(), 1);
        let big = RenderBudget::new(1, Duration::from_secs(600), 0.0);
        let _w = take(&big.work, 120_000_000);
        assert_eq!(big.retry_after(), 60);
        assert_eq!(big.viewer_pixels_limit, 0, "a share of 0 keeps viewers out");
    }

    #[test]
    fn server_timing_durations_are_milliseconds_with_three_decimals() {
        assert_eq!(ms(Duration::from_nanos(1_234_567)), "1.235");
        assert_eq!(ms(Duration::ZERO), "0.000");
    }
}
