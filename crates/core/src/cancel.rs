//! Cancellation of one request's work: a flag and a deadline that long-running work checks at
//! its stage boundaries.
//!
//! Work that runs off the async runtime (a render on the blocking pool, its engine calls and
//! draw submissions) outlives the request future that started it: a 504 or a client that hangs
//! up drops the future, but not the thread doing the work. So the work carries a [`Cancel`] and
//! asks [`Cancel::check`] between stages (each group's blend, each draw submission, the
//! readback, the encoding); the request holds the [`CancelOnDrop`] guard, whose drop — the
//! handler finished, timed out, or was dropped because the connection closed — raises the
//! flag. The deadline is checked as well, so work whose request has passed it stops even if
//! the guard is still alive (a session viewer's frame, which no HTTP request owns).

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

/// Why work stopped early.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum Cancelled {
    /// The request's owner went away (its future was dropped: the client hung up, or the
    /// handler answered already).
    #[error("the request was cancelled")]
    Dropped,
    /// The request's deadline passed.
    #[error("the request's deadline passed")]
    Deadline,
}

/// A cancellation token: cheap to clone, checked by the work.
#[derive(Clone, Debug)]
pub struct Cancel {
    flag: Arc<AtomicBool>,
    deadline: Option<Instant>,
}

impl Cancel {
    /// A token that nothing cancels (command-line tools, benchmarks).
    pub fn never() -> Cancel {
        Cancel::manual()
    }

    /// A token without a deadline, cancelled by [`Cancel::cancel`] (an owner that lives
    /// longer than one request: a session viewer).
    pub fn manual() -> Cancel {
        Cancel {
            flag: Arc::new(AtomicBool::new(false)),
            deadline: None,
        }
    }

    /// The same flag with a deadline of its own (one frame of a viewer).
    pub fn with_deadline(&self, deadline: Instant) -> Cancel {
        Cancel {
            flag: self.flag.clone(),
            deadline: Some(deadline),
        }
    }

    /// A token cancelled when the returned guard is dropped or at `deadline`.
    pub fn new(deadline: Option<Instant>) -> (Cancel, CancelOnDrop) {
        let c = Cancel {
            flag: Arc::new(AtomicBool::new(false)),
            deadline,
        };
        (c.clone(), CancelOnDrop(c))
    }

    /// Why the work should stop now, if it should.
    pub fn reason(&self) -> Option<Cancelled> {
        // The deadline first: a request answered 504 drops its guard too, and is late.
        if self.deadline.is_some_and(|d| Instant::now() >= d) {
            Some(Cancelled::Deadline)
        } else if self.flag.load(Ordering::Acquire) {
            Some(Cancelled::Dropped)
        } else {
            None
        }
    }

    /// `Err` when the work should stop: call it at every stage boundary.
    pub fn check(&self) -> Result<(), Cancelled> {
        self.reason().map_or(Ok(()), Err)
    }

    /// Raises the flag.
    pub fn cancel(&self) {
        self.flag.store(true, Ordering::Release);
    }
}

/// Cancels its token when dropped: what a request future holds while its work runs elsewhere.
#[derive(Debug)]
pub struct CancelOnDrop(Cancel);

impl Drop for CancelOnDrop {
    fn drop(&mut self) {
        self.0.cancel();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn a_token_stops_when_its_guard_is_dropped_or_its_deadline_passes() {
        let (c, guard) = Cancel::new(None);
        assert_eq!(c.check(), Ok(()));
        let clone = c.clone();
        drop(guard);
        assert_eq!(clone.check(), Err(Cancelled::Dropped));
        let (late, _guard) = Cancel::new(Some(Instant::now() - Duration::from_millis(1)));
        assert_eq!(late.check(), Err(Cancelled::Deadline));
        let (soon, _guard) = Cancel::new(Some(Instant::now() + Duration::from_secs(60)));
        assert_eq!(soon.check(), Ok(()));
        assert_eq!(Cancel::never().check(), Ok(()));
        let viewer = Cancel::manual();
        let frame = viewer.with_deadline(Instant::now() + Duration::from_secs(60));
        assert_eq!(frame.check(), Ok(()));
        viewer.cancel();
        assert_eq!(frame.check(), Err(Cancelled::Dropped));
    }
}
