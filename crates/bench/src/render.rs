//! `crowdmorph bench render`: the offline crowd of [`crowdmorph_engine::render::offline`] drawn repeatedly,
//! the median time of each stage reported: compute (the engine), render, readback, encode.
//! `--textures both` draws the same crowd without and with textures
//! ([`RenderOptions::textures`]; generated ones when the rig has none) and reports both and
//! their ratio: what texture sampling costs a frame on this renderer.

use std::time::Instant;

use serde::Serialize;

use super::sample::Samples;
use crowdmorph_core::rig::Rig;
use crowdmorph_engine::Engine;
use crowdmorph_engine::render::offline::{
    OfflineError, RANDOM_CLIP, RenderOptions, RenderReport, StageTimes, build, draw_once,
    open_device, report,
};

type Result<T> = std::result::Result<T, OfflineError>;

/// Which textures `bench render` draws with (`--textures`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum TextureChoice {
    /// The rig as it is.
    #[default]
    Rig,
    /// With textures: the rig's, or generated ones when it has none.
    On,
    /// Its materials' factors without their textures.
    Off,
    /// Off, then on, on the same crowd.
    Both,
}

impl std::str::FromStr for TextureChoice {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s.to_ascii_lowercase().as_str() {
            "rig" => Ok(TextureChoice::Rig),
            "on" => Ok(TextureChoice::On),
            "off" => Ok(TextureChoice::Off),
            "both" => Ok(TextureChoice::Both),
            other => Err(format!(
                "unknown texture choice {other:?} (rig, on, off or both)"
            )),
        }
    }
}

/// The same crowd drawn without and with textures.
#[derive(Clone, Debug, Serialize)]
pub struct TextureComparison {
    /// Without textures.
    pub untextured: RenderReport,
    /// With textures.
    pub textured: RenderReport,
    /// Textured over untextured render (drawing) time.
    pub render_ratio: f64,
    /// Textured over untextured total time per frame.
    pub total_ratio: f64,
}

impl std::fmt::Display for TextureComparison {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "untextured: {}", self.untextured)?;
        write!(f, "textured: {}", self.textured)?;
        writeln!(
            f,
            "textured / untextured: render {:.2}×, total {:.2}× ({:.2} vs {:.2} ms render per frame)",
            self.render_ratio,
            self.total_ratio,
            self.textured.times.render_ms,
            self.untextured.times.render_ms
        )
    }
}

/// `crowdmorph bench render --textures both`: [`bench_render`] of the crowd without, then
/// with, textures.
pub fn bench_render_textures(
    engine: &Engine,
    rig: &Rig,
    opt: &RenderOptions,
    seconds: f64,
    min_runs: usize,
) -> Result<TextureComparison> {
    let with = |textures| RenderOptions {
        textures: Some(textures),
        ..opt.clone()
    };
    let untextured = bench_render(engine, rig, &with(false), seconds, min_runs)?;
    let textured = bench_render(engine, rig, &with(true), seconds, min_runs)?;
    let ratio = |a: f64, b: f64| if b > 0.0 { a / b } else { 0.0 };
    Ok(TextureComparison {
        render_ratio: ratio(textured.times.render_ms, untextured.times.render_ms),
        total_ratio: ratio(textured.times.total_ms, untextured.times.total_ms),
        untextured,
        textured,
    })
}

/// `crowdmorph bench render`: draws the crowd repeatedly for about `seconds` (at least
/// `min_runs` times, after one warm-up frame) and reports the median of each stage. A rig
/// without clips plays a synthetic `random` clip, so its heads differ.
pub fn bench_render(
    engine: &Engine,
    rig: &Rig,
    opt: &RenderOptions,
    seconds: f64,
    min_runs: usize,
) -> Result<RenderReport> {
    let mut opt = opt.clone();
    if opt.clip.is_none() && rig.clips.is_empty() {
        opt.clip = Some(RANDOM_CLIP.into());
    }
    let opt = &opt;
    let device = open_device(engine, opt)?;
    let c = build(engine, &device, rig, opt)?;
    // The first frame pays for pipeline and buffer creation.
    let (bytes, _) = draw_once(engine, &device, &c, &opt.image)?;
    let start = Instant::now();
    let mut runs: Vec<StageTimes> = Vec::new();
    while runs.len() < min_runs.max(1) || start.elapsed().as_secs_f64() < seconds {
        runs.push(draw_once(engine, &device, &c, &opt.image)?.1);
    }
    let median = |f: fn(&StageTimes) -> f64| Samples::new(runs.iter().map(f).collect()).median();
    let times = StageTimes {
        compute_ms: median(|t| t.compute_ms),
        render_ms: median(|t| t.render_ms),
        readback_ms: median(|t| t.readback_ms),
        encode_ms: median(|t| t.encode_ms),
        total_ms: median(|t| t.total_ms),
    };
    Ok(report(
        engine,
        &device,
        &c,
        opt,
        bytes.len(),
        times,
        runs.len(),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn texture_choices_parse() {
        assert_eq!("both".parse(), Ok(TextureChoice::Both));
        assert_eq!("ON".parse(), Ok(TextureChoice::On));
        assert_eq!("off".parse(), Ok(TextureChoice::Off));
        assert_eq!("rig".parse(), Ok(TextureChoice::Rig));
        assert!("maybe".parse::<TextureChoice>().is_err());
    }
}
