//! What `/readyz` reports as skipped: stored files and generations that were not used, each
//! with why, until what it is about is superseded (a later generation of its rig is held, or
//! the rig is gone).

use std::sync::Mutex;

/// Most entries kept (the oldest go first): a bound on what a flood of damage could add.
const MAX_SKIPPED: usize = 256;

/// A stored file or generation that was not used, and why.
#[derive(Debug, PartialEq, Eq)]
struct Report {
    /// The rig it is about, when known: cleared once a later generation of it is held.
    rig: Option<String>,
    /// The generation it is about (0 in the data dir: any later write supersedes it).
    generation: u64,
    /// The report.
    why: String,
}

/// The reports, in the order they came.
#[derive(Debug, Default)]
pub struct Skipped(Mutex<Vec<Report>>);

impl Skipped {
    /// Reports `why` for as long as the server runs.
    pub fn skip(&self, why: String) {
        self.push(Report {
            rig: None,
            generation: 0,
            why,
        });
    }

    /// Reports `why`, about generation `generation` of rig `id` (0 in the data dir), until a
    /// later generation of the rig is held or the rig is deleted ([`Skipped::clear`]).
    pub fn skip_rig(&self, id: &str, generation: u64, why: String) {
        self.push(Report {
            rig: Some(id.to_string()),
            generation,
            why,
        });
    }

    fn push(&self, entry: Report) {
        if let Ok(mut s) = self.0.lock()
            && !s.contains(&entry)
        {
            if s.len() >= MAX_SKIPPED {
                s.remove(0);
            }
            s.push(entry);
        }
    }

    /// Forgets what was reported about generations of rig `id` before `below`: a newer one
    /// is held now, or the rig is gone.
    pub fn clear(&self, id: &str, below: u64) {
        if let Ok(mut s) = self.0.lock() {
            s.retain(|e| e.rig.as_deref() != Some(id) || e.generation >= below);
        }
    }

    /// What is reported now.
    pub fn list(&self) -> Vec<String> {
        self.0
            .lock()
            .map(|s| s.iter().map(|e| e.why.clone()).collect())
            .unwrap_or_default()
    }
}
