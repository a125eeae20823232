//! A rig's named masks and mappings as stored (`PUT /v1/rigs/{id}/masks/{name}`,
//! `PUT /v1/rigs/{id}/mappings/{name}`, and the `vrm` mapping read from an uploaded VRM
//! file), by rig. They are persisted with the rig's motion graphs
//! (`crate::services::persist::persist_graphs`, one file or store object per rig) and
//! looked up by name where layers and heads are resolved: each lookup takes a snapshot (an
//! `Arc` of the rig's maps), so a request or a tick resolves against one version of them.

use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Mutex};

use crowdmorph_proto::{Mapping, Mask};

/// Most masks one rig may have.
pub const MAX_MASKS_PER_RIG: usize = 64;

/// Most mappings one rig may have (its `vrm` one included).
pub const MAX_MAPPINGS_PER_RIG: usize = 64;

/// One rig's masks and mappings.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct NamedMaps {
    /// Masks by name.
    pub masks: Arc<BTreeMap<String, Mask>>,
    /// Mappings by name (the rig's `vrm` among them when its file had expressions).
    pub mappings: Arc<BTreeMap<String, Mapping>>,
}

impl NamedMaps {
    /// Whether there is nothing to store.
    pub fn is_empty(&self) -> bool {
        self.masks.is_empty() && self.mappings.is_empty()
    }
}

/// Every rig's masks and mappings.
#[derive(Debug, Default)]
pub struct RigMaps {
    by_rig: Mutex<HashMap<String, NamedMaps>>,
}

impl RigMaps {
    fn with<T>(&self, f: impl FnOnce(&mut HashMap<String, NamedMaps>) -> T) -> T {
        let mut m = self
            .by_rig
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        f(&mut m)
    }

    /// Rig `rig`'s masks and mappings (a snapshot: `Arc`s, not copies).
    pub fn of(&self, rig: &str) -> NamedMaps {
        self.with(|m| m.get(rig).cloned().unwrap_or_default())
    }

    /// Rig `rig`'s masks (a snapshot).
    pub fn masks(&self, rig: &str) -> Arc<BTreeMap<String, Mask>> {
        self.of(rig).masks
    }

    /// Rig `rig`'s mapping `name`, if it has one of its own (or a `vrm` one).
    pub fn mapping(&self, rig: &str, name: &str) -> Option<Mapping> {
        self.with(|m| m.get(rig).and_then(|r| r.mappings.get(name).cloned()))
    }

    /// Replaces rig `rig`'s masks and mappings (after they were persisted).
    pub fn set(&self, rig: &str, maps: NamedMaps) {
        self.with(|m| {
            if maps.is_empty() {
                m.remove(rig);
            } else {
                m.insert(rig.to_string(), maps);
            }
        });
    }

    /// Forgets a deleted rig's masks and mappings.
    pub fn drop_rig(&self, rig: &str) {
        self.with(|m| m.remove(rig));
    }
}
