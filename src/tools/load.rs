//! `crowdmorph load`: the open-loop load generator of [`crate::load`] against a running server
//! over HTTP, at a fixed rate or ramping to the highest rate whose p99 meets a target, with a
//! live progress line on standard error (only when it is a terminal).

use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, Result};
use serde::Serialize;

use crate::load::http::{HttpLane, HttpTarget};
use crate::load::{
    self, CrowdShape, Live, LoadReport, RampOptions, RampReport, RigClips, RunOptions,
};

/// Request bodies generated; request `i` sends body `i mod RING`.
const RING: usize = 64;

/// What `crowdmorph load` was asked to do.
#[derive(Clone, Debug)]
pub struct LoadCommand {
    /// `http://host:port` of the server.
    pub url: String,
    /// Requests per second (the first rate of a ramp).
    pub rate: f64,
    /// Seconds measured (per step of a ramp).
    pub duration: f64,
    /// Seconds sent before each measured window.
    pub warmup: f64,
    /// Seconds unanswered requests may take after the window before they count as unfinished.
    pub grace: f64,
    /// Connections.
    pub connections: usize,
    /// The crowds.
    pub crowd: CrowdShape,
    /// Ramp instead of one fixed rate.
    pub ramp: Option<RampOptions>,
    /// Draw the progress line (it is drawn only when standard error is a terminal).
    pub progress: bool,
}

/// The result: one report, or a ramp's.
#[derive(Debug, Serialize)]
#[serde(untagged)]
pub enum LoadOutcome {
    /// A fixed rate.
    Fixed(LoadReport),
    /// `--ramp`.
    Ramp(RampReport),
}

impl LoadOutcome {
    /// The human-readable table.
    pub fn text(&self) -> String {
        match self {
            LoadOutcome::Fixed(r) => r.text(),
            LoadOutcome::Ramp(r) => r.text(),
        }
    }
}

/// Runs the command to the end.
pub fn load(cmd: &LoadCommand) -> Result<LoadOutcome> {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the tokio runtime")?;
    runtime.block_on(run(cmd))
}

/// What the server says about the rigs of the shape.
async fn describe_rigs(url: &str, crowd: &CrowdShape) -> Result<Vec<RigClips>> {
    let client = crowdmorph_client::Client::new(url.trim_end_matches('/'));
    let mut rigs = Vec::new();
    for id in &crowd.rigs {
        let info = client
            .rig(id)
            .await
            .map_err(|e| anyhow::anyhow!("{e}"))
            .with_context(|| format!("asking {url} about rig {id:?}"))?;
        rigs.push(RigClips {
            id: id.clone(),
            clips: info.clips.iter().map(|c| c.name.clone()).collect(),
            lod_levels: info.lod.levels.len() as u32,
        });
    }
    Ok(rigs)
}

async fn run(cmd: &LoadCommand) -> Result<LoadOutcome> {
    load::http::authority_of(&cmd.url)?;
    let rigs = describe_rigs(&cmd.url, &cmd.crowd).await?;
    let bodies = cmd.crowd.bodies(&rigs, RING)?;
    let target = HttpTarget::new(&cmd.url, bodies, cmd.crowd.encoding)?;
    let opts = |rate: f64| RunOptions {
        rate,
        duration: Duration::from_secs_f64(cmd.duration.max(0.0)),
        warmup: Duration::from_secs_f64(cmd.warmup.max(0.0)),
        grace: Duration::from_secs_f64(cmd.grace.max(0.0)),
        heads_per_request: u64::from(cmd.crowd.heads),
    };
    opts(cmd.rate).check()?;
    match &cmd.ramp {
        None => Ok(LoadOutcome::Fixed(
            run_at(&target, cmd.connections, opts(cmd.rate), cmd.progress).await?,
        )),
        Some(ramp) => {
            let ramp = RampOptions {
                start_rate: cmd.rate,
                ..ramp.clone()
            };
            let report = load::ramp(&ramp, |rate| {
                let target = target.clone();
                let opts = opts(rate);
                async move {
                    run_at(&target, cmd.connections, opts, cmd.progress)
                        .await
                        .map_err(|e| load::LoadError::Invalid(format!("{e:#}")))
                }
            })
            .await?;
            Ok(LoadOutcome::Ramp(report))
        }
    }
}

/// One run at a fixed rate over fresh connections.
async fn run_at(
    target: &Arc<HttpTarget>,
    connections: usize,
    opts: RunOptions,
    progress: bool,
) -> Result<LoadReport> {
    let mut lanes: Vec<HttpLane> = Vec::with_capacity(connections.max(1));
    for _ in 0..connections.max(1) {
        lanes.push(target.lane().await?);
    }
    let rate = opts.rate;
    let live = Live::new(opts);
    // indicatif hides the line when standard error is not a terminal; then nothing is drawn
    // and no snapshot is taken.
    let bar = progress
        .then(indicatif::ProgressBar::new_spinner)
        .filter(|b| !b.is_hidden());
    if let Some(b) = &bar {
        b.enable_steady_tick(Duration::from_millis(120));
    }
    let ticker = bar.clone().map(|bar| {
        let live = live.clone();
        tokio::spawn(async move {
            loop {
                tokio::time::sleep(Duration::from_millis(250)).await;
                let r = live.snapshot();
                let (sent, done) = live.counts();
                bar.set_message(format!(
                    "{rate:.0} req/s: {:.1} s, {sent} sent, {} in flight, {} ok, {} errors; \
                     p50 {:.2} ms, p99 {:.2} ms; {:.0} heads/s",
                    live.elapsed(),
                    sent.saturating_sub(done),
                    r.ok,
                    r.errors,
                    r.latency_ms.p50,
                    r.latency_ms.p99,
                    r.heads_per_s
                ));
            }
        })
    });
    let result = load::run(lanes, &live).await;
    if let Some(t) = ticker {
        t.abort();
    }
    if let Some(b) = bar {
        b.finish_and_clear();
    }
    Ok(result?)
}

/// Parses a mix entry `NAME[:WEIGHT]` (`--clip talk:3`); without a weight, 1.
pub fn parse_weighted(s: &str) -> Result<(String, f64)> {
    let (name, weight) = match s.rsplit_once(':') {
        Some((n, w)) if !n.is_empty() && w.trim().parse::<f64>().is_ok() => {
            (n, w.trim().parse::<f64>()?)
        }
        _ => (s, 1.0),
    };
    anyhow::ensure!(!name.is_empty(), "{s:?}: name a clip");
    anyhow::ensure!(
        weight.is_finite() && weight >= 0.0,
        "{s:?}: the weight must be a finite number >= 0"
    );
    Ok((name.to_string(), weight))
}

/// Parses a LOD mix entry `LEVEL[:WEIGHT]` (`--lod 2:0.25`); without a weight, 1.
pub fn parse_weighted_lod(s: &str) -> Result<(u32, f64)> {
    let (level, weight) = parse_weighted(s)?;
    let level = level
        .trim()
        .parse()
        .with_context(|| format!("{s:?}: the LOD level must be a whole number"))?;
    Ok((level, weight))
}

#[cfg(test)]
mod tests {
    // A test that meets an unexpected error should fail loudly.
    #![allow(clippy::unwrap_used)]

    use super::*;

    #[test]
    fn mix_entries_parse() {
        assert_eq!(parse_weighted("talk:3").unwrap(), ("talk".into(), 3.0));
        assert_eq!(parse_weighted("talk").unwrap(), ("talk".into(), 1.0));
        // A colon that does not start a weight is part of the name.
        assert_eq!(parse_weighted("a:b").unwrap(), ("a:b".into(), 1.0));
        assert!(parse_weighted("talk:-1").is_err());
        assert_eq!(parse_weighted_lod("2:0.25").unwrap(), (2, 0.25));
        assert!(parse_weighted_lod("x:1").is_err());
    }
}
