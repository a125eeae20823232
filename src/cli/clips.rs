//! `crowdmorph clips graph`: a motion graph built from a rig file's clips (Kovar et al. 2002),
//! its edges' costs, and the graph as JSON to `PUT /v1/rigs/{id}/graphs/{name}`.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Subcommand;
use serde::Serialize;

use crowdmorph::graph::{BuildOptions, Built, Graph, build};

#[derive(Subcommand)]
/// `crowdmorph clips ...`.
pub enum Command {
    /// Find transitions between the rig's clips (frame distances in vertex space over a window,
    /// local minima under a threshold), cut the clips into nodes there, prune to the largest
    /// strongly connected component, and report each edge's cost.
    Graph {
        /// glTF/GLB rig with clips (default: the embedded head).
        rig: Option<PathBuf>,
        /// Frames compared per transition, and its cross-fade.
        #[arg(long, default_value_t = 5)]
        window: u32,
        /// Largest mean RMS vertex distance of a transition, as a fraction of the rig's
        /// bounding-box diagonal.
        #[arg(long, default_value_t = 0.02)]
        threshold: f32,
        /// Most transitions per (source clip, target clip).
        #[arg(long, default_value_t = 8)]
        per_pair: usize,
        /// Write the graph here as JSON (the body of `PUT /v1/rigs/{id}/graphs/{name}`).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Print JSON instead of text.
        #[arg(long)]
        json: bool,
    },
}

/// What `clips graph` reports.
#[derive(Serialize)]
pub struct GraphReport {
    /// The rig's name.
    pub rig: String,
    /// What was found.
    #[serde(flatten)]
    pub built: Built,
}

impl super::Report for GraphReport {}

impl std::fmt::Display for GraphReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let g = &self.built.graph;
        writeln!(
            f,
            "rig {:?}: {} candidate transitions; graph of {} nodes and {} edges ({} nodes outside \
             the largest strongly connected component dropped)",
            self.rig,
            self.built.candidates,
            g.nodes.len(),
            g.edges.len(),
            self.built.dropped_nodes
        )?;
        for (e, cost) in g.edges.iter().zip(&self.built.costs) {
            let kind = if *cost == 0.0 && e.fade == 1 {
                "plays on".to_string()
            } else {
                format!("cost {cost:.2e} × diagonal")
            };
            writeln!(
                f,
                "  {:>24} → {:<24} fade {:>2}, from frame {:>4}: {kind}",
                e.from,
                e.to,
                e.fade,
                e.window.map_or(0, |w| w[0])
            )?;
        }
        Ok(())
    }
}

/// Runs `crowdmorph clips ...`.
pub fn run(which: Command) -> Result<()> {
    match which {
        Command::Graph {
            rig,
            window,
            threshold,
            per_pair,
            out,
            json,
        } => {
            let rig = super::load_rig(rig.as_deref())?;
            let built = build(
                &rig,
                BuildOptions {
                    window,
                    threshold,
                    per_pair,
                },
            )
            .with_context(|| {
                format!(
                    "rig {:?}: no cycle of transitions under the threshold {threshold} (raise \
                     --threshold or lower --window)",
                    rig.name
                )
            })?;
            // What the server would say of it.
            Graph::resolve(&built.graph, &rig, |n| rig.clip_index(n))
                .context("the built graph does not check")?;
            if let Some(path) = out {
                std::fs::write(&path, serde_json::to_vec_pretty(&built.graph)?)
                    .with_context(|| format!("writing {}", path.display()))?;
            }
            super::emit(
                &GraphReport {
                    rig: rig.name.clone(),
                    built,
                },
                json,
            )
        }
    }
}
