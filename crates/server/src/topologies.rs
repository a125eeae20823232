//! What rendering needs in the server state: the render device (or why there is none) and the
//! mesh topologies uploaded to it, kept per rig generation and mesh level in a small LRU
//! ([`TopologyCache`]) so that a frame uploads no indices. The cache keeps them only for reuse:
//! it is registered with the renderer's device, and a charge there that finds the GPU budget
//! full (a rig upload, a batch, a render) empties it first.

use std::sync::{Arc, Mutex};

use crowdmorph_engine::gpu::Reclaim;
use crowdmorph_engine::render::crowd::RenderDevice;
use crowdmorph_engine::render::gpu::MeshTopology;

/// Most topologies kept on the renderer's device.
const TOPOLOGY_ENTRIES: usize = 32;
/// Most bytes of index (and other topology) buffers kept on the renderer's device.
const TOPOLOGY_BYTES: u64 = 512 << 20;

/// Which mesh a topology is of: a rig's generation and mesh level (`None`: the full mesh).
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct TopologyKey {
    /// The rig's id.
    pub rig: String,
    /// Its generation.
    pub generation: u64,
    /// The mesh level (`None`: the full mesh).
    pub mesh: Option<usize>,
}

/// What a cache entry occupies.
pub trait Footprint {
    /// Bytes it holds (on the device, for a topology).
    fn bytes(&self) -> u64;
}

impl Footprint for MeshTopology {
    fn bytes(&self) -> u64 {
        MeshTopology::bytes(self)
    }
}

/// Topologies uploaded to the renderer, most recently used last, bounded by count and bytes
/// (`T` is a parameter so the eviction rules are tested without a device).
pub struct TopologyCache<T = MeshTopology> {
    entries: Vec<(TopologyKey, Arc<T>)>,
    bytes: u64,
}

impl<T> Default for TopologyCache<T> {
    fn default() -> Self {
        TopologyCache {
            entries: Vec::new(),
            bytes: 0,
        }
    }
}

impl<T> std::fmt::Debug for TopologyCache<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TopologyCache")
            .field("entries", &self.entries.len())
            .field("bytes", &self.bytes)
            .finish()
    }
}

impl<T: Footprint> TopologyCache<T> {
    /// The topology of `key`, made the most recently used.
    pub fn get(&mut self, key: &TopologyKey) -> Option<Arc<T>> {
        let i = self.entries.iter().position(|(k, _)| k == key)?;
        let e = self.entries.remove(i);
        let t = e.1.clone();
        self.entries.push(e);
        Some(t)
    }

    /// Keeps `t` for `key` unless `current` (the rig's registered generation now, `None` when
    /// it is gone) says `key`'s generation was deleted or replaced while `t` was uploaded: the
    /// delete's purge may already have run, and nothing but the LRU would drop it. Returns the
    /// topology to use.
    pub fn insert_if_current(
        &mut self,
        key: TopologyKey,
        t: Arc<T>,
        current: Option<u64>,
    ) -> Arc<T> {
        if current == Some(key.generation) {
            self.insert(key, t)
        } else {
            t
        }
    }

    fn insert(&mut self, key: TopologyKey, t: Arc<T>) -> Arc<T> {
        // Another render may have uploaded the same topology meanwhile: keep one.
        if let Some(existing) = self.get(&key) {
            return existing;
        }
        self.bytes += t.bytes();
        self.entries.push((key, t.clone()));
        while self.entries.len() > TOPOLOGY_ENTRIES
            || (self.bytes > TOPOLOGY_BYTES && self.entries.len() > 1)
        {
            let (_, old) = self.entries.remove(0);
            self.bytes -= old.bytes();
        }
        t
    }

    /// Forgets every topology, returning them so the caller can drop them outside its lock.
    fn take_all(&mut self) -> Vec<(TopologyKey, Arc<T>)> {
        self.bytes = 0;
        std::mem::take(&mut self.entries)
    }

    /// Forgets every topology of rig `id` (it was deleted): its device memory is freed once
    /// renders in flight drop their handles.
    pub fn purge(&mut self, id: &str) {
        let bytes = &mut self.bytes;
        self.entries.retain(|(k, t)| {
            let keep = k.rig != id;
            if !keep {
                *bytes -= t.bytes();
            }
            keep
        });
    }
}

/// A [`TopologyCache`] behind its lock, as the server state and the renderer's device share it
/// (a type of this crate, so that it may implement the engine's [`Reclaim`]).
#[derive(Debug)]
pub struct SharedTopologies<T = MeshTopology>(Mutex<TopologyCache<T>>);

impl<T> Default for SharedTopologies<T> {
    fn default() -> Self {
        SharedTopologies(Mutex::new(TopologyCache::default()))
    }
}

impl<T> std::ops::Deref for SharedTopologies<T> {
    type Target = Mutex<TopologyCache<T>>;
    fn deref(&self) -> &Self::Target {
        &self.0
    }
}

/// The cache gives its topologies up when the device's budget is full: a render in flight that
/// uses one holds its own `Arc`, so its index buffer lives (and stays charged) until that render
/// ends; the others are freed at once, and a later render uploads them again.
impl<T: Footprint + Send + Sync> Reclaim for SharedTopologies<T> {
    fn reclaim(&self) -> bool {
        // Not waited for: a holder is looking a topology up or inserting one right now.
        let dropped = match self.try_lock() {
            Ok(mut cache) => cache.take_all(),
            Err(_) => return false,
        };
        !dropped.is_empty()
    }
}

/// What rendering needs in the server state: the device, or why there is none, and the
/// topologies uploaded to it.
#[derive(Debug)]
pub struct RenderState {
    /// The renderer, or why there is none.
    pub device: Result<RenderDevice, String>,
    /// Topologies on its device (registered with the device as memory kept for reuse).
    pub topologies: Arc<SharedTopologies>,
}

impl RenderState {
    /// The state of `device`, with an empty topology cache registered with the renderer's
    /// device, so a full GPU budget empties it.
    pub fn new(device: Result<RenderDevice, String>) -> RenderState {
        let topologies = Arc::new(SharedTopologies::default());
        if let Ok(d) = &device {
            d.renderer
                .register_reclaim(Arc::downgrade(&topologies) as std::sync::Weak<dyn Reclaim>);
        }
        RenderState { device, topologies }
    }

    /// The adapter that renders, for `/readyz`.
    pub fn adapter_name(&self) -> Option<String> {
        self.device.as_ref().ok().map(RenderDevice::name)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    struct Sized(u64);

    impl Footprint for Sized {
        fn bytes(&self) -> u64 {
            self.0
        }
    }

    fn key(rig: &str, generation: u64) -> TopologyKey {
        TopologyKey {
            rig: rig.into(),
            generation,
            mesh: None,
        }
    }

    #[test]
    fn the_topology_cache_keeps_the_most_recently_used_within_its_bounds() {
        let mut c = TopologyCache::default();
        for g in 0..TOPOLOGY_ENTRIES as u64 {
            c.insert(key("a", g), Arc::new(Sized(1)));
        }
        // Using generation 0 makes generation 1 the oldest, which the next insert evicts.
        assert!(c.get(&key("a", 0)).is_some());
        c.insert(key("b", 0), Arc::new(Sized(1)));
        assert_eq!(c.entries.len(), TOPOLOGY_ENTRIES);
        assert!(c.get(&key("a", 1)).is_none() && c.get(&key("a", 0)).is_some());
        // A second upload of the same key keeps the first.
        let first = c.get(&key("b", 0)).expect("cached");
        let kept = c.insert(key("b", 0), Arc::new(Sized(1)));
        assert!(Arc::ptr_eq(&first, &kept));
        assert_eq!(c.bytes, TOPOLOGY_ENTRIES as u64);
        // Past the byte bound, the oldest go, but the newest always stays.
        c.insert(key("huge", 0), Arc::new(Sized(TOPOLOGY_BYTES + 1)));
        assert_eq!(c.entries.len(), 1);
        assert_eq!(c.bytes, TOPOLOGY_BYTES + 1);
        c.insert(key("a", 7), Arc::new(Sized(3)));
        assert_eq!((c.entries.len(), c.bytes), (1, 3), "the huge one made room");
        // A deleted rig's topologies go, whatever their generation and mesh.
        c.insert(key("a", 8), Arc::new(Sized(4)));
        c.insert(key("c", 0), Arc::new(Sized(5)));
        c.purge("a");
        assert_eq!((c.entries.len(), c.bytes), (1, 5));
        assert!(c.get(&key("c", 0)).is_some());
        // An upload that a delete or a replacement overtook is used but not kept.
        let late = c.insert_if_current(key("d", 1), Arc::new(Sized(6)), None);
        assert_eq!(late.0, 6);
        c.insert_if_current(key("d", 1), Arc::new(Sized(6)), Some(2));
        assert!(c.get(&key("d", 1)).is_none());
        assert_eq!((c.entries.len(), c.bytes), (1, 5));
        c.insert_if_current(key("d", 2), Arc::new(Sized(6)), Some(2));
        assert!(c.get(&key("d", 2)).is_some());
    }

    #[test]
    fn a_reclaim_empties_the_cache_but_topologies_in_use_stay_alive() {
        let cache = SharedTopologies::default();
        assert!(!cache.reclaim(), "nothing to give back");
        let in_use = Arc::new(Sized(10));
        if let Ok(mut c) = cache.lock() {
            c.insert(key("a", 0), in_use.clone());
            c.insert(key("b", 0), Arc::new(Sized(20)));
        }
        let idle = Arc::downgrade(&cache.lock().expect("lock").get(&key("b", 0)).expect("b"));
        // A holder of the lock is not waited for.
        {
            let _held = cache.lock().expect("lock");
            assert!(!cache.reclaim());
        }
        assert!(cache.reclaim());
        let c = cache.lock().expect("lock");
        assert_eq!((c.entries.len(), c.bytes), (0, 0));
        assert!(idle.upgrade().is_none(), "an idle topology is freed");
        // One a render holds lives on, now held by that render alone.
        assert_eq!(Arc::strong_count(&in_use), 1);
    }
}
