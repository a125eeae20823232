//! `crowdmorph bench render`: the offline crowd of [`crowdmorph_engine::render::offline`] drawn repeatedly,
//! the median time of each stage reported: compute (the engine), render, readback, encode.

use std::time::Instant;

use super::sample::Samples;
use crowdmorph_core::rig::Rig;
use crowdmorph_engine::Engine;
use crowdmorph_engine::render::offline::{
    OfflineError, RANDOM_CLIP, RenderOptions, RenderReport, StageTimes, build, draw_once,
    open_device, report,
};

type Result<T> = std::result::Result<T, OfflineError>;

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
