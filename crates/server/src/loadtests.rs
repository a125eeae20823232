//! The load tests of `POST /v1/loadtest`: the one running and the last few done, and what
//! their requests and answers are (the handlers are `routes::loadtest`).

use std::collections::VecDeque;
use std::sync::{Arc, Mutex};

use serde::{Deserialize, Serialize};

use crowdmorph_load::{CrowdShape, Live, LoadReport};

/// Finished loads kept for `GET /v1/loadtest/{id}`.
pub const KEEP_DONE: usize = 8;

/// The body of `POST /v1/loadtest`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LoadtestRequest {
    /// Requests per second.
    pub rate: f64,
    /// Seconds measured.
    pub duration_s: f64,
    /// Seconds sent before the measured window.
    #[serde(default)]
    pub warmup_s: f64,
    /// In-process lanes the requests are spread over (a lane sends one request at a time).
    #[serde(default = "default_concurrency")]
    pub concurrency: u32,
    /// The crowds.
    #[serde(default)]
    pub crowd: CrowdShape,
}

fn default_concurrency() -> u32 {
    16
}

/// What `POST /v1/loadtest` and `GET /v1/loadtest/{id}` answer.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LoadtestStatus {
    /// The load's id.
    pub id: String,
    /// `running`, `done`, or `cancelled` (the server shut down, or answers ran past the grace).
    pub status: String,
    /// Seconds since it started.
    pub elapsed_s: f64,
    /// What was asked for.
    pub request: LoadtestRequest,
    /// The report: so far while running, final when done.
    pub report: LoadReport,
}

/// One load, running or done.
#[derive(Debug)]
pub struct Run {
    /// Its id.
    pub id: String,
    /// What was asked for.
    pub request: LoadtestRequest,
    /// Its counters, read while it runs.
    pub live: Arc<Live>,
    /// Set when it has finished.
    pub done: tokio::sync::watch::Sender<bool>,
}

impl Run {
    /// What `GET /v1/loadtest/{id}` answers of it.
    pub fn status(&self) -> LoadtestStatus {
        let report = self.live.snapshot();
        let status = if !report.finished {
            "running"
        } else if report.cancelled {
            "cancelled"
        } else {
            "done"
        };
        LoadtestStatus {
            id: self.id.clone(),
            status: status.into(),
            elapsed_s: self.live.elapsed(),
            request: self.request.clone(),
            report,
        }
    }
}

#[derive(Debug, Default)]
struct Runs {
    next: u64,
    current: Option<Arc<Run>>,
    done: VecDeque<Arc<Run>>,
}

/// The server's loads: the one running and the last few done.
#[derive(Debug, Default)]
pub struct Loadtests(Mutex<Runs>);

impl Loadtests {
    /// Stops the running load (the server is shutting down).
    pub fn cancel_all(&self) {
        if let Ok(runs) = self.0.lock()
            && let Some(r) = &runs.current
        {
            r.live.cancel();
        }
    }

    /// The running load's id, if one runs (a check before work; [`Loadtests::start`] is the
    /// one that decides).
    pub fn running(&self) -> Option<String> {
        self.0.lock().ok()?.current.as_ref().map(|r| r.id.clone())
    }

    /// The running or finished load `id`.
    pub fn find(&self, id: &str) -> Option<Arc<Run>> {
        let runs = self.0.lock().ok()?;
        runs.current
            .iter()
            .chain(runs.done.iter())
            .find(|r| r.id == id)
            .cloned()
    }

    /// Registers a new load unless one is running (`Err`: the running one's id; `None` when
    /// the registry is unusable, a poisoned lock).
    pub fn start(
        &self,
        request: LoadtestRequest,
        live: Arc<Live>,
    ) -> Result<Arc<Run>, Option<String>> {
        let mut runs = self.0.lock().map_err(|_| None)?;
        if let Some(r) = &runs.current {
            return Err(Some(r.id.clone()));
        }
        runs.next += 1;
        let run = Arc::new(Run {
            id: runs.next.to_string(),
            request,
            live,
            done: tokio::sync::watch::Sender::new(false),
        });
        runs.current = Some(run.clone());
        Ok(run)
    }

    /// Moves `run` to the finished ones.
    pub fn finish(&self, run: &Arc<Run>) {
        if let Ok(mut runs) = self.0.lock() {
            if runs.current.as_ref().is_some_and(|r| Arc::ptr_eq(r, run)) {
                runs.current = None;
            }
            runs.done.push_back(run.clone());
            while runs.done.len() > KEEP_DONE {
                runs.done.pop_front();
            }
        }
        run.done.send_replace(true);
    }
}
