//! The render budgets: pixels and estimated work in flight, with the share session viewers may
//! hold, taken before any work and given back as the render finishes (pixels with the
//! response body, work once encoded). `crowdmorph_engine::render::cost` prices a render; this admits it.

use std::sync::Arc;
use std::time::Duration;

use axum::http::StatusCode;
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

use crate::http::ApiError;
use crate::metrics::Metrics;
use crowdmorph_engine::render::cost::RenderCost;

/// Who a render is for: session viewers' frames hold a capped share of the budgets.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Renderee {
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

    /// The whole pixel budget.
    pub fn pixels_limit(&self) -> u64 {
        self.pixels_limit
    }

    /// Seconds until the work held now has drained, as a Retry-After (1 to 60).
    fn retry_after(&self) -> u32 {
        let (held, _) = self.work_seconds();
        held.ceil().clamp(1.0, 60.0) as u32
    }
}

/// What an admitted render holds of the [`RenderBudget`]: the pixels go with the response
/// body, the work is given back once the image is encoded.
pub struct RenderPermits {
    /// The image's pixels: they go with the response body.
    pub pixels: OwnedSemaphorePermit,
    /// The render's estimated work: given back once it is encoded.
    pub work: OwnedSemaphorePermit,
    /// A viewer's frame also holds its share.
    _viewer: Option<(OwnedSemaphorePermit, OwnedSemaphorePermit)>,
}

/// Tries to take `n` permits of `s`: `None` when they are not free now.
fn take(s: &Arc<Semaphore>, n: u64) -> Option<OwnedSemaphorePermit> {
    s.clone()
        .try_acquire_many_owned(u32::try_from(n).ok()?)
        .ok()
}

/// 413 for a render estimated to take more than the whole work budget (or a viewer's share
/// of it, `limit_us`).
fn too_costly(estimate: Duration, cost: &RenderCost, viewer: bool, limit_us: u64) -> ApiError {
    let flag = if viewer {
        format!(
            "{} ms, the share session viewers may hold (--viewer-render-share) of the \
             render work budget (--render-work-ms)",
            limit_us / 1000
        )
    } else {
        format!(
            "the render work budget of {} ms (--render-work-ms)",
            limit_us / 1000
        )
    };
    ApiError::new(
        StatusCode::PAYLOAD_TOO_LARGE,
        "render_too_costly",
        format!(
            "drawing this crowd is estimated at {:.0} ms on this server's renderer \
             ({} blend work, {} vertices and {} triangles drawn, {} pixels, {} texture \
             fetches), more than {flag}; ask for fewer heads, a coarser lod or a smaller image",
            estimate.as_secs_f64() * 1e3,
            cost.blend,
            cost.vertices,
            cost.triangles,
            cost.pixels,
            cost.texture_fetches
        ),
    )
}

impl RenderBudget {
    /// Takes the render budgets for an image of `pixels` and an estimated duration of
    /// `estimate`: 413 when the render can never fit (larger than the whole budget, or than
    /// the share viewers may hold), 503 `render_busy` with a Retry-After when renders in flight
    /// hold too much now.
    pub fn reserve(
        &self,
        pixels: u64,
        estimate: Duration,
        cost: &RenderCost,
        who: Renderee,
        metrics: &Metrics,
    ) -> Result<RenderPermits, ApiError> {
        let b = self;
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
            metrics.reject("render_too_costly");
            return Err(too_costly(estimate, cost, viewer, work_limit_us));
        }
        let busy = |what: &str| {
            metrics.reject("render_busy");
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
    pub fn too_many_pixels(&self, pixels: u64, viewer: bool) -> ApiError {
        let b = self;
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
}

#[cfg(test)]
mod tests {
    use super::*;

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
}
