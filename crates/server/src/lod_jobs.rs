//! The LOD jobs of the server by rig id: a rig's background job or a `PUT` being served, at
//! most one per rig (the handlers and the build are `routes::lod`).

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use crowdmorph_engine::lod::Progress;

/// A running or failed LOD computation: the background job of a newly registered rig, or a
/// `PUT` being served.
#[derive(Debug, Default)]
pub struct LodJob {
    /// Its progress, through which it is cancelled.
    pub progress: Arc<Progress>,
    /// Why it failed, once it has.
    pub failed: Mutex<Option<String>>,
    /// Started by registration rather than by a request.
    pub background: bool,
}

/// The jobs by rig id. At most one per rig: a new one cancels the old.
#[derive(Debug, Default)]
pub struct LodJobs(Mutex<HashMap<String, Arc<LodJob>>>);

impl LodJobs {
    /// The job of rig `id`.
    pub fn get(&self, id: &str) -> Option<Arc<LodJob>> {
        self.0.lock().ok().and_then(|m| m.get(id).cloned())
    }

    /// Cancels and forgets the job of a rig (on delete, or before a `PUT` replaces it).
    pub fn cancel(&self, id: &str) {
        if let Some(job) = self.0.lock().ok().and_then(|mut m| m.remove(id)) {
            job.progress.cancel();
        }
    }

    /// Cancels every background job (on shutdown: they are not requests in flight, and a
    /// half-scored rig keeps its import order until the next start computes it again).
    pub fn cancel_background(&self) {
        if let Ok(mut m) = self.0.lock() {
            m.retain(|_, job| {
                if job.background {
                    job.progress.cancel();
                }
                !job.background
            });
        }
    }

    /// Cancels every job (the state is being dropped).
    pub fn cancel_all(&self) {
        if let Ok(mut m) = self.0.lock() {
            for job in m.values() {
                job.progress.cancel();
            }
            m.clear();
        }
    }

    /// Starts a job for rig `id`, cancelling the one it had.
    pub fn start(&self, id: &str, background: bool) -> Arc<LodJob> {
        let job = Arc::new(LodJob {
            background,
            ..LodJob::default()
        });
        // Replaced and cancelled under one lock: two starts at once cannot both miss the
        // other and leave a build running that nothing can cancel.
        if let Ok(mut m) = self.0.lock()
            && let Some(old) = m.insert(id.to_string(), job.clone())
        {
            old.progress.cancel();
        }
        job
    }

    /// Forgets `job`, if it is still rig `id`'s.
    pub fn finish(&self, id: &str, job: &Arc<LodJob>) {
        if let Ok(mut m) = self.0.lock()
            && m.get(id).is_some_and(|j| Arc::ptr_eq(j, job))
        {
            m.remove(id);
        }
    }
}
