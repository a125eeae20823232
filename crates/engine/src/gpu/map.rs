//! Waiting for buffer mappings: the outcome of a piece of work's `map_async` requests, and a
//! wait that returns only once every one of them has reported.
//!
//! Why waiting for the submission is not enough: wgpu runs map callbacks on whichever thread's
//! `poll` or `queue.submit` first finds the work done, and only after that call has released
//! the device's locks. When another thread — a concurrent render's submit, the GPU engine's
//! compute thread on a shared device — finds this work done first, this thread's
//! `poll(Wait { submission })` returns at once (the fence has passed) while the callbacks are
//! still to run on the other thread. Reading the results then saw none, and a healthy frame was
//! reported as a failed mapping (a 503 `render_unavailable` for a render, a lost device for the
//! engine). So [`MapResults::wait`] polls for the submission and then waits for the callbacks
//! themselves.

use std::ops::RangeBounds;
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

/// How long a wait lets callbacks another thread has collected take to arrive after the
/// submission is done. They run as soon as that thread leaves the device's locks, so this bound
/// only turns a driver that never reports into an error instead of a hung request.
const CALLBACK_WAIT: Duration = Duration::from_secs(30);

/// How often a wait polls the device again while it waits for callbacks (a mapping that no
/// thread's poll has collected yet is collected by the next one).
const REPOLL: Duration = Duration::from_millis(20);

/// Each request's outcome, in the order the callbacks ran.
type Outcomes = Vec<Result<(), String>>;

/// The results of the `map_async` requests made through it; cheap to clone (callbacks hold a
/// clone).
#[derive(Clone, Default)]
pub struct MapResults {
    shared: Arc<(Mutex<Outcomes>, Condvar)>,
}

impl std::fmt::Debug for MapResults {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MapResults")
            .field("reported", &self.reported().len())
            .finish()
    }
}

impl MapResults {
    /// No requests yet.
    pub fn new() -> MapResults {
        MapResults::default()
    }

    /// Asks for `range` of `buffer` to be mapped for reading; its outcome is recorded here.
    pub fn request(&self, buffer: &wgpu::Buffer, range: impl RangeBounds<wgpu::BufferAddress>) {
        let shared = self.shared.clone();
        buffer.map_async(wgpu::MapMode::Read, range, move |r| {
            let (results, arrived) = &*shared;
            if let Ok(mut v) = results.lock() {
                v.push(r.map_err(|e| e.to_string()));
            }
            arrived.notify_all();
        });
    }

    /// The outcomes reported so far.
    pub fn reported(&self) -> Outcomes {
        self.shared.0.lock().map(|v| v.clone()).unwrap_or_default()
    }

    /// Waits until `submission` is done on `device` and `expected` mappings have reported, all
    /// of them successfully. `Err` says why not: the poll failed (device lost), a mapping
    /// failed, or callbacks never arrived.
    pub fn wait(
        &self,
        device: &wgpu::Device,
        submission: wgpu::SubmissionIndex,
        expected: usize,
    ) -> Result<(), String> {
        device
            .poll(wgpu::PollType::Wait {
                submission_index: Some(submission),
                timeout: None,
            })
            .map_err(|e| e.to_string())?;
        let deadline = Instant::now() + CALLBACK_WAIT;
        let (results, arrived) = &*self.shared;
        loop {
            {
                let guard = results
                    .lock()
                    .map_err(|_| "a mapping lock was poisoned".to_string())?;
                let (guard, _) = arrived
                    .wait_timeout_while(guard, REPOLL, |v| v.len() < expected)
                    .map_err(|_| "a mapping lock was poisoned".to_string())?;
                if guard.len() >= expected {
                    return if guard.iter().any(Result::is_err) {
                        Err(format!("buffer mapping failed: {:?}", *guard))
                    } else {
                        Ok(())
                    };
                }
                if Instant::now() >= deadline {
                    return Err(format!(
                        "{} of {expected} buffer mappings reported within {} s of the work \
                         finishing: {:?}",
                        guard.len(),
                        CALLBACK_WAIT.as_secs(),
                        *guard
                    ));
                }
            }
            // Outside the lock: callbacks this poll collects run on this thread and take it.
            device
                .poll(wgpu::PollType::Poll)
                .map_err(|e| e.to_string())?;
        }
    }
}
