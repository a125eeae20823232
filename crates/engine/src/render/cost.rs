//! What a rendered frame costs, estimated before any of it is done.
//!
//! A render's pixels bound its memory, but not its time: 10,000 clones of a 14,000-triangle head
//! at 64 × 48 pixels are 140 million triangles, minutes on a software rasterizer. So every
//! render is priced by everything it does — the unique jobs blended (vertices × active shapes,
//! the batcher's cost), the vertices and triangles drawn (instances × the mesh's), the samples
//! shaded and the pixels encoded — and the price is turned into an estimated duration by the
//! [`Rates`] of the device that will draw it. The server charges that duration to its render
//! work budget before anything runs (`--render-work-ms`): a render that can never fit is a
//! 413, one that does not fit now a 503.
//!
//! The rates are deliberately plain constants, measured once per device class (see
//! [`Rates::SOFTWARE`] and [`Rates::HARDWARE`]), not a live calibration: an estimate that
//! changed with load would make the same request a 200 one minute and a 413 the next.

use std::time::Duration;

/// The work of one render, in the units the [`Rates`] divide.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RenderCost {
    /// Blend work of the unique jobs: Σ vertices × (active shapes + 1).
    pub blend: u64,
    /// Vertices shaded: Σ over instances of the mesh's vertices.
    pub vertices: u64,
    /// Triangles set up and rasterized: Σ over instances of the mesh's triangles.
    pub triangles: u64,
    /// Pixels of the image (each shaded at 4× MSAA, resolved, read back and encoded).
    pub pixels: u64,
    /// Texture fetches: the pixels times the most texture slots a drawn primitive samples
    /// (`render::appearance::texture_slots`). Like `pixels`, an upper bound that ignores how
    /// much of the frame the heads cover.
    pub texture_fetches: u64,
}

impl RenderCost {
    /// Adds one unique job of `blend` work drawn `instances` times with a mesh of `vertices`
    /// and `triangles`.
    pub fn add_job(&mut self, blend: u64, instances: u64, vertices: u64, triangles: u64) {
        self.blend = self.blend.saturating_add(blend);
        self.vertices = self
            .vertices
            .saturating_add(instances.saturating_mul(vertices));
        self.triangles = self
            .triangles
            .saturating_add(instances.saturating_mul(triangles));
    }

    /// The estimated time of the whole render at `rates`.
    pub fn estimate(&self, rates: &Rates) -> Duration {
        let secs = rates.per_render
            + self.blend as f64 / rates.blend
            + self.vertices as f64 / rates.vertices
            + self.triangles as f64 / rates.triangles
            + self.pixels as f64
                * (f64::from(super::gpu::SAMPLES) / rates.samples + 1.0 / rates.encode)
            + self.texture_fetches as f64 / rates.texture_fetches;
        Duration::from_secs_f64(secs.min(1e9))
    }
}

/// How fast a device does each part of a render, per second.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Rates {
    /// Blend work (vertices × active shapes) of the engine that blends for the renderer.
    pub blend: f64,
    /// Vertices shaded (the vertex shader: two matrix products).
    pub vertices: f64,
    /// Triangles set up and rasterized.
    pub triangles: f64,
    /// MSAA samples shaded and written.
    pub samples: f64,
    /// Pixels encoded (PNG or JPEG on the host).
    pub encode: f64,
    /// Texture fetches of textured pixels (a filtered sample of one slot, and its share of
    /// the normal-map and material arithmetic).
    pub texture_fetches: f64,
    /// Seconds every render costs whatever it draws (submissions, targets, the readback).
    pub per_render: f64,
}

impl Rates {
    /// Mesa's lavapipe on two cores, with the CPU engine blending. Measured through the
    /// server's Server-Timing on the release build (2026-12-01, 2-core Xeon, the embedded
    /// head: 7,262 vertices and 14,500 triangles an instance): 100 clones at 64 × 48 draw in
    /// 578–611 ms and 1,000 in 4.97–5.19 s (about 5 ms an instance), one head at 1920 × 1080
    /// in 77 ms warm (142 ms when the targets are new) against 11 ms at 64 × 48, 100 unique
    /// jobs blend in 12–24 ms, a 1080p PNG encodes in 7–9 ms. Set about 35 % slower than that,
    /// so that estimates err long: 6.9 ms an instance, 35 ms a full-HD frame. Texture fetches:
    /// `bench render --textures both` (2026-12-07, same machine under a load of 6–8 from other
    /// builds, 100 unique embedded heads at 1280 × 720, four slots: 3.7 M fetches) drew
    /// 120–1,120 ms slower textured, 4–28 % of a frame; at the unloaded frame time above that
    /// is at least 19 M fetches/s, set at 15 M.
    pub const SOFTWARE: Rates = Rates {
        blend: 500.0e6,
        vertices: 3.5e6,
        triangles: 3.0e6,
        samples: 60.0e6,
        encode: 30.0e6,
        texture_fetches: 15.0e6,
        per_render: 0.02,
    };

    /// A hardware GPU: conservative for any discrete GPU of the last decade (a current one is
    /// 10–100× faster at each), with the host encoding the image.
    pub const HARDWARE: Rates = Rates {
        blend: 20.0e9,
        vertices: 1.0e9,
        triangles: 500.0e6,
        samples: 5.0e9,
        encode: 30.0e6,
        texture_fetches: 5.0e9,
        per_render: 0.002,
    };

    /// The rates of a render whose jobs are blended by the GPU engine (`engine_gpu`) or the
    /// CPU engine, and drawn by a software adapter (lavapipe, SwiftShader) or a hardware one.
    pub fn new(engine_gpu: bool, software: bool) -> Rates {
        let draw = if software {
            Rates::SOFTWARE
        } else {
            Rates::HARDWARE
        };
        let blend = if engine_gpu {
            Rates::HARDWARE.blend
        } else {
            Rates::SOFTWARE.blend
        };
        Rates { blend, ..draw }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clones_cost_drawing_but_not_blending() {
        let mut one = RenderCost {
            pixels: 64 * 48,
            ..RenderCost::default()
        };
        one.add_job(7_000 * 52, 1, 7_000, 14_000);
        let mut crowd = RenderCost {
            pixels: 64 * 48,
            ..RenderCost::default()
        };
        crowd.add_job(7_000 * 52, 10_000, 7_000, 14_000);
        assert_eq!(crowd.blend, one.blend, "clones are instances");
        assert_eq!(crowd.triangles, 10_000 * one.triangles);
        let (a, b) = (
            one.estimate(&Rates::SOFTWARE),
            crowd.estimate(&Rates::SOFTWARE),
        );
        assert!(b > a * 1000, "{a:?} vs {b:?}");
        // 140 million triangles are many seconds on a software rasterizer, a fraction of one
        // on a GPU.
        assert!(b > Duration::from_secs(10), "{b:?}");
        assert!(crowd.estimate(&Rates::HARDWARE) < Duration::from_secs(1));
        // Saturating, never overflowing.
        let mut huge = RenderCost::default();
        huge.add_job(u64::MAX, u64::MAX, u64::MAX, u64::MAX);
        assert_eq!(huge.triangles, u64::MAX);
        assert!(huge.estimate(&Rates::SOFTWARE) > Duration::from_secs(1_000_000));
    }

    #[test]
    fn textures_cost_per_pixel_and_slot() {
        let plain = RenderCost {
            pixels: 1280 * 720,
            ..RenderCost::default()
        };
        let textured = RenderCost {
            texture_fetches: 1280 * 720 * 4,
            ..plain
        };
        let (a, b) = (
            plain.estimate(&Rates::SOFTWARE),
            textured.estimate(&Rates::SOFTWARE),
        );
        assert!(b > a, "{a:?} vs {b:?}");
        let fetches = b - a;
        let expected = 1280.0 * 720.0 * 4.0 / Rates::SOFTWARE.texture_fetches;
        assert!((fetches.as_secs_f64() - expected).abs() < 1e-6);
    }
}
