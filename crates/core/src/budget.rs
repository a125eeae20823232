//! Memory budgets: every allocation whose size an input decides is charged here first.
//!
//! Two levels, both counted in bytes of host memory:
//!
//! - A [`MemoryPool`] is what the whole server may hold for rigs (`--max-rig-memory`): the
//!   resident rigs, plus whatever uploads, clip imports and LOD builds in progress hold. When
//!   it is full, new work is refused with 503 (retry once something finishes or a rig is
//!   deleted).
//! - A [`Budget`] is one operation's share (`--max-upload-memory` for an upload): it reserves
//!   an estimate made from the file's headers *before* any work, then charges each allocation
//!   as it happens, growing the reservation if the estimate was short. Past its limit the
//!   operation is refused with 413; what it still holds goes back to the pool when it is
//!   dropped.
//!
//! What an operation leaves behind — a registered rig — keeps its bytes as a [`Charge`], which
//! returns them when the rig (all its versions) is gone. The numbers are upper bounds of
//! what the arrays occupy, not of the allocator's overhead; tests compare them with the
//! process's peak RSS.

use std::fmt;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

/// Why a charge was refused.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum BudgetError {
    /// The operation alone needs more than its limit allows: it can never succeed as is.
    #[error("{what} needs {needed} bytes of memory, more than the limit of {limit} bytes ({flag})")]
    TooLarge {
        /// What was being charged (e.g. "clip table \"talk\" (51 targets × 64 frames)").
        what: String,
        /// Bytes the operation would hold with this charge.
        needed: u64,
        /// The limit.
        limit: u64,
        /// The flag that sets the limit.
        flag: &'static str,
    },
    /// The server-wide pool is too full right now.
    #[error(
        "{what} needs {needed} more bytes of memory, but rigs and work in progress hold {used} of the \
         server's {limit} bytes ({flag}); retry later, delete a rig, or raise the limit"
    )]
    Full {
        /// What was being charged.
        what: String,
        /// Bytes asked for.
        needed: u64,
        /// Bytes the pool holds.
        used: u64,
        /// The pool's size.
        limit: u64,
        /// The flag that sets it.
        flag: &'static str,
    },
}

/// The server-wide pool of memory for rigs and the work that makes them.
#[derive(Debug)]
pub struct MemoryPool {
    limit: u64,
    used: AtomicU64,
    flag: &'static str,
}

impl MemoryPool {
    /// A pool of `limit` bytes; `flag` names the option that sets it, for error messages.
    pub fn new(limit: u64, flag: &'static str) -> Arc<MemoryPool> {
        Arc::new(MemoryPool {
            limit,
            used: AtomicU64::new(0),
            flag,
        })
    }

    /// Bytes held now.
    pub fn used(&self) -> u64 {
        self.used.load(Ordering::Acquire)
    }

    /// The pool's size.
    pub fn limit(&self) -> u64 {
        self.limit
    }

    /// Takes `bytes` for an object that keeps them until it is dropped (a buffer on the GPU,
    /// charged to the device's pool before it is created): refused as [`Budget::charge`]
    /// refuses, `TooLarge` when `bytes` alone exceed the pool, `Full` when what is held leaves
    /// no room now.
    pub fn charge(
        self: &Arc<Self>,
        bytes: u64,
        what: impl Fn() -> String,
    ) -> Result<Charge, BudgetError> {
        self.try_take(bytes, &what)?;
        Ok(Charge {
            pool: Some(self.clone()),
            bytes,
        })
    }

    /// Takes `bytes` if they fit.
    fn try_take(&self, bytes: u64, what: &dyn Fn() -> String) -> Result<(), BudgetError> {
        if bytes > self.limit {
            return Err(BudgetError::TooLarge {
                what: what(),
                needed: bytes,
                limit: self.limit,
                flag: self.flag,
            });
        }
        self.used
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |used| {
                used.checked_add(bytes).filter(|&u| u <= self.limit)
            })
            .map(|_| ())
            .map_err(|used| BudgetError::Full {
                what: what(),
                needed: bytes,
                used,
                limit: self.limit,
                flag: self.flag,
            })
    }

    /// Takes `bytes` whether or not they fit: for memory that is already allocated (the
    /// pool then reports more than its limit until something is freed).
    fn force_take(&self, bytes: u64) {
        self.used.fetch_add(bytes, Ordering::AcqRel);
    }

    fn give(&self, bytes: u64) {
        let _ = self
            .used
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |u| {
                Some(u.saturating_sub(bytes))
            });
    }
}

#[derive(Debug, Default)]
struct BudgetState {
    /// Bytes taken from the pool for this operation.
    reserved: u64,
    /// Bytes charged and not yet released.
    used: u64,
    /// Most bytes charged at once.
    peak: u64,
}

/// One operation's memory: a limit, a reservation in the pool, and what is charged now.
pub struct Budget {
    limit: u64,
    flag: &'static str,
    pool: Option<Arc<MemoryPool>>,
    state: Mutex<BudgetState>,
}

impl fmt::Debug for Budget {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let s = self.snapshot();
        f.debug_struct("Budget")
            .field("limit", &self.limit)
            .field("flag", &self.flag)
            .field("reserved", &s.reserved)
            .field("used", &s.used)
            .field("peak", &s.peak)
            .finish()
    }
}

impl Budget {
    /// A budget of `limit` bytes drawing from `pool` (none: only the limit applies, as for
    /// command-line tools); `flag` names the option that sets the limit.
    pub fn new(limit: u64, flag: &'static str, pool: Option<Arc<MemoryPool>>) -> Budget {
        Budget {
            limit,
            flag,
            pool,
            state: Mutex::new(BudgetState::default()),
        }
    }

    fn snapshot(&self) -> BudgetState {
        self.state
            .lock()
            .map(|s| BudgetState {
                reserved: s.reserved,
                used: s.used,
                peak: s.peak,
            })
            .unwrap_or_default()
    }

    /// The limit.
    pub fn limit(&self) -> u64 {
        self.limit
    }

    /// Bytes taken from the pool for this operation.
    pub fn reserved(&self) -> u64 {
        self.snapshot().reserved
    }

    /// Bytes charged now.
    pub fn used(&self) -> u64 {
        self.snapshot().used
    }

    /// Most bytes charged at once so far.
    pub fn peak(&self) -> u64 {
        self.snapshot().peak
    }

    /// Grows the reservation to at least `total` bytes.
    fn grow_to(
        &self,
        s: &mut BudgetState,
        total: u64,
        what: &dyn Fn() -> String,
    ) -> Result<(), BudgetError> {
        if total <= s.reserved {
            return Ok(());
        }
        if total > self.limit {
            return Err(BudgetError::TooLarge {
                what: what(),
                needed: total,
                limit: self.limit,
                flag: self.flag,
            });
        }
        if let Some(pool) = &self.pool {
            pool.try_take(total - s.reserved, what)?;
        }
        s.reserved = total;
        Ok(())
    }

    /// Reserves an estimate of everything the operation will hold at once, before any work:
    /// refused at once when it is over the limit or the pool cannot give it.
    pub fn reserve(&self, total: u64, what: impl Fn() -> String) -> Result<(), BudgetError> {
        let mut s = self.state.lock().map_err(|_| poisoned(&what))?;
        self.grow_to(&mut s, total, &what)
    }

    /// Charges `bytes` about to be allocated; `what` describes them if refused.
    pub fn charge(&self, bytes: u64, what: impl Fn() -> String) -> Result<(), BudgetError> {
        let mut s = self.state.lock().map_err(|_| poisoned(&what))?;
        let used = s.used.saturating_add(bytes);
        self.grow_to(&mut s, used, &what)?;
        s.used = used;
        s.peak = s.peak.max(used);
        Ok(())
    }

    /// Releases `bytes` charged earlier and now freed (the reservation stays: the operation
    /// may need it again).
    pub fn release(&self, bytes: u64) {
        if let Ok(mut s) = self.state.lock() {
            s.used = s.used.saturating_sub(bytes);
        }
    }

    /// Turns `bytes` of this operation's reservation into a lasting [`Charge`] (what a
    /// registered rig keeps). Bytes beyond the reservation are already allocated, so they are
    /// taken from the pool even if it is over its limit.
    pub fn keep(&self, bytes: u64) -> Charge {
        if let Ok(mut s) = self.state.lock() {
            let from_reservation = bytes.min(s.reserved);
            s.reserved -= from_reservation;
            s.used = s.used.saturating_sub(bytes);
            if let Some(pool) = &self.pool {
                pool.force_take(bytes - from_reservation);
            }
        }
        Charge {
            pool: self.pool.clone(),
            bytes,
        }
    }
}

fn poisoned(what: &dyn Fn() -> String) -> BudgetError {
    BudgetError::Full {
        what: what(),
        needed: 0,
        used: 0,
        limit: 0,
        flag: "internal: a budget lock was poisoned",
    }
}

impl Drop for Budget {
    fn drop(&mut self) {
        if let (Some(pool), Ok(s)) = (&self.pool, self.state.lock()) {
            pool.give(s.reserved);
        }
    }
}

/// Bytes a lasting object (a registered rig) holds in the pool; given back on drop.
#[derive(Debug, Default)]
pub struct Charge {
    pool: Option<Arc<MemoryPool>>,
    bytes: u64,
}

impl Charge {
    /// Bytes held.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    /// Moves the bytes out, leaving this charge empty (a new version of a rig takes over the
    /// charge of the version it replaces).
    pub fn take(&mut self) -> Charge {
        std::mem::take(self)
    }

    /// Adds `other`'s bytes to this charge.
    pub fn absorb(&mut self, mut other: Charge) {
        if self.pool.is_none() {
            self.pool = other.pool.clone();
        }
        self.bytes += std::mem::take(&mut other.bytes);
    }

    /// Sets the charge to `bytes`, the memory now actually held: growth is taken from the
    /// pool even past its limit (it is allocated already), shrinking gives back.
    pub fn set(&mut self, bytes: u64) {
        if let Some(pool) = &self.pool {
            if bytes > self.bytes {
                pool.force_take(bytes - self.bytes);
            } else {
                pool.give(self.bytes - bytes);
            }
        }
        self.bytes = bytes;
    }
}

impl Drop for Charge {
    fn drop(&mut self) {
        if let Some(pool) = &self.pool {
            pool.give(self.bytes);
        }
    }
}

/// Hands memory that was freed back to the operating system, so that deleting a large rig
/// lowers the process's resident size. glibc keeps freed heap memory in its arenas (and raises
/// its mmap threshold after large frees, so later large blocks land there too); `malloc_trim`
/// returns the free pages. Elsewhere this does nothing.
pub fn return_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        // SAFETY: malloc_trim only walks the allocator's own free lists; it has no
        // preconditions and is safe to call from any thread at any time.
        unsafe {
            libc::malloc_trim(0);
        }
    }
}

/// Freed memory worth handing back to the operating system after a request ends: a request
/// that held this much (a refused upload bomb read to its limit, a drained overload) leaves
/// the process that much larger until the allocator is trimmed.
pub const TRIM_AFTER_BYTES: u64 = 64 << 20;

/// Least time between two trims that [`return_freed_memory_soon`] asks for: a server under
/// steady heavy load asks often, and a trim is cheap but not free (it walks the arenas, and
/// what it hands back is faulted in again when reused).
const TRIM_INTERVAL: std::time::Duration = std::time::Duration::from_secs(2);

/// How long a trim waits after it is asked for, so that what is being freed as it is asked
/// is freed before the allocator is walked.
const TRIM_SETTLE: std::time::Duration = std::time::Duration::from_millis(50);

/// [`return_freed_memory`] on a thread of its own, soon: for the end of a request that held a
/// lot (at least [`TRIM_AFTER_BYTES`]) and freed it. A trim walks every allocator arena under
/// its lock and can take milliseconds on a large heap, so it never runs on the caller's (an
/// async worker's) thread, and asks coalesce: one trim runs at a time, at most one waits, and
/// trims are at least [`TRIM_INTERVAL`] apart, so a flood of refused requests costs one trim
/// every two seconds at most. The last ask is always followed by two trims: one at once, one
/// [`TRIM_INTERVAL`] later for what is freed after it.
pub fn return_freed_memory_soon() {
    static ASKS: std::sync::OnceLock<Option<std::sync::mpsc::SyncSender<()>>> =
        std::sync::OnceLock::new();
    let asks = ASKS.get_or_init(|| {
        let (tx, rx) = std::sync::mpsc::sync_channel::<()>(1);
        std::thread::Builder::new()
            .name("crowdmorph-trim".into())
            .spawn(move || {
                while rx.recv().is_ok() {
                    // The ask comes as a charge is dropped, often just before the memory it
                    // paid for is freed (a value drops its fields in order): let that finish.
                    std::thread::sleep(TRIM_SETTLE);
                    return_freed_memory();
                    // What the last requests free after their ask (a response sent after its
                    // charge went back, connection buffers) is trimmed by one more pass after
                    // the interval; asks that came meanwhile are served by it too.
                    loop {
                        std::thread::sleep(TRIM_INTERVAL);
                        let asked = rx.try_recv().is_ok();
                        return_freed_memory();
                        if !asked {
                            break;
                        }
                    }
                }
            })
            .ok()
            .map(|_| tx)
    });
    if let Some(tx) = asks {
        // Full: a trim is already waiting, and it runs after what was freed so far.
        let _ = tx.try_send(());
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn budget_reserves_charges_and_gives_back() {
        let pool = MemoryPool::new(1000, "--pool");
        let b = Budget::new(600, "--op", Some(pool.clone()));
        b.reserve(300, || "estimate".into()).expect("fits");
        assert_eq!(pool.used(), 300);
        // Charges within the reservation take nothing more from the pool.
        b.charge(200, || "a".into()).expect("fits");
        assert_eq!(pool.used(), 300);
        // Past it, the reservation grows.
        b.charge(200, || "b".into()).expect("fits");
        assert_eq!((b.reserved(), b.used(), pool.used()), (400, 400, 400));
        b.release(300);
        assert_eq!(b.used(), 100);
        assert_eq!(b.peak(), 400);
        // Over the operation's limit: 413-like, naming the flag.
        let e = b.charge(550, || "big".into()).expect_err("over the limit");
        assert!(matches!(
            e,
            BudgetError::TooLarge {
                needed: 650,
                limit: 600,
                flag: "--op",
                ..
            }
        ));
        // Another operation finds the pool too full: 503-like.
        let other = Budget::new(1000, "--op", Some(pool.clone()));
        let e = other
            .reserve(700, || "other".into())
            .expect_err("pool full");
        assert!(matches!(
            e,
            BudgetError::Full {
                used: 400,
                limit: 1000,
                ..
            }
        ));
        let kept = b.keep(250);
        assert_eq!(pool.used(), 400, "kept bytes stay taken");
        drop(b);
        assert_eq!(pool.used(), 250, "the rest of the reservation goes back");
        drop(kept);
        assert_eq!(pool.used(), 0);
    }

    #[test]
    fn a_pool_charges_objects_directly_until_they_are_dropped() {
        let pool = MemoryPool::new(100, "--gpu");
        let a = pool.charge(60, || "a".into()).expect("fits");
        assert_eq!((a.bytes(), pool.used()), (60, 60));
        let e = pool.charge(50, || "b".into()).expect_err("full");
        assert!(matches!(
            e,
            BudgetError::Full {
                used: 60,
                limit: 100,
                flag: "--gpu",
                ..
            }
        ));
        let e = pool.charge(101, || "huge".into()).expect_err("too large");
        assert!(matches!(e, BudgetError::TooLarge { needed: 101, .. }));
        assert!(e.to_string().contains("huge") && e.to_string().contains("--gpu"));
        drop(a);
        assert_eq!(pool.used(), 0);
        let b = pool.charge(50, || "b".into()).expect("fits once a is gone");
        assert_eq!(pool.used(), 50);
        drop(b);
    }

    #[test]
    fn charges_move_between_versions_and_resize() {
        let pool = MemoryPool::new(100, "--pool");
        let b = Budget::new(100, "--op", Some(pool.clone()));
        b.reserve(60, || "rig".into()).expect("fits");
        let mut v1 = b.keep(60);
        drop(b);
        let mut v2 = v1.take();
        assert_eq!((v1.bytes(), v2.bytes(), pool.used()), (0, 60, 60));
        v2.set(80);
        assert_eq!(pool.used(), 80);
        v2.set(20);
        assert_eq!(pool.used(), 20);
        drop(v1);
        assert_eq!(pool.used(), 20);
        drop(v2);
        assert_eq!(pool.used(), 0);
    }
}
