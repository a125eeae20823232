//! A pool of reusable buffers bounded in count and in total bytes, shared by the engine's
//! output buffers (scheduler) and the JSON response buffers.
//!
//! Why bounded in bytes: a buffer is charged to the queue memory while its response is in
//! flight; once sent it is no longer charged, so what a pool keeps is memory beside the
//! budgets, and a rare huge response must not pin its memory for good.

use std::sync::Mutex;

/// A buffer a [`Pool`] can keep: its size in bytes.
pub(crate) trait Reusable {
    /// Bytes the buffer holds (its capacity, where that differs from its length).
    fn kept_bytes(&self) -> usize;
}

impl Reusable for Vec<u8> {
    fn kept_bytes(&self) -> usize {
        self.capacity()
    }
}

/// Up to `max_buffers` buffers holding at most `max_bytes` together.
#[derive(Debug)]
pub(crate) struct Pool<T> {
    free: Mutex<Vec<T>>,
    max_buffers: usize,
    max_bytes: usize,
}

impl<T: Reusable> Pool<T> {
    /// An empty pool with these bounds.
    pub(crate) fn new(max_buffers: usize, max_bytes: usize) -> Pool<T> {
        Pool {
            free: Mutex::new(Vec::new()),
            max_buffers,
            max_bytes,
        }
    }

    /// Takes the kept buffer with the greatest `rank` among those it ranks (`None`: not
    /// usable), if any.
    pub(crate) fn take_best<K: Ord>(&self, rank: impl Fn(&T) -> Option<K>) -> Option<T> {
        let mut free = self.free.lock().ok()?;
        let best = free
            .iter()
            .enumerate()
            .filter_map(|(i, b)| rank(b).map(|k| (k, i)))
            .max_by(|a, b| a.0.cmp(&b.0))
            .map(|(_, i)| i)?;
        Some(free.swap_remove(best))
    }

    /// Keeps `buffer` for reuse if the bounds allow, else frees it.
    pub(crate) fn put(&self, buffer: T) {
        if let Ok(mut free) = self.free.lock() {
            let kept: usize = free.iter().map(Reusable::kept_bytes).sum();
            if free.len() < self.max_buffers && kept + buffer.kept_bytes() <= self.max_bytes {
                free.push(buffer);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pool_keeps_buffers_within_its_count_and_byte_bounds() {
        let pool: Pool<Vec<u8>> = Pool::new(2, 100);
        pool.put(Vec::with_capacity(60));
        // Over the byte bound together with the first: freed.
        pool.put(Vec::with_capacity(50));
        pool.put(Vec::with_capacity(30));
        // Over the count bound: freed.
        pool.put(Vec::with_capacity(1));
        let caps = |p: &Pool<Vec<u8>>| {
            let mut c: Vec<usize> = p
                .free
                .lock()
                .expect("pool lock")
                .iter()
                .map(Vec::capacity)
                .collect();
            c.sort_unstable();
            c
        };
        let kept = caps(&pool);
        assert_eq!(kept.len(), 2);
        assert!(kept[0] >= 30 && kept[0] < 50 && kept[1] >= 60, "{kept:?}");
        // The best ranked usable buffer comes out; unranked ones stay.
        let small = pool.take_best(|b| (b.capacity() < 50).then_some(b.capacity()));
        assert!(small.is_some_and(|b| b.capacity() < 50));
        assert!(
            pool.take_best(|b| (b.capacity() < 50).then_some(0))
                .is_none()
        );
        assert_eq!(caps(&pool).len(), 1);
    }
}
