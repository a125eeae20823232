//! Names a request matches against a rig: its targets for live weights and masks (exactly,
//! else by the one loose spelling, as CSV clips' columns are matched), its named masks,
//! ARKit's names, and the 404s that list what a rig has.

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;

use crowdmorph_proto::Mask;

use crowdmorph_core::rig::{ARKIT_NAMES, Rig, TargetId, quoted_name};
use crowdmorph_import::clips::loose;

use crate::http::ApiError;
use crate::registry::{Registry, RigEntry};

/// 404 for a rig id the registry does not have, listing (at most 20 of) the ones it has.
pub fn unknown_rig(registry: &Registry, id: &str) -> ApiError {
    let mut ids: Vec<String> = registry.all().iter().map(|e| e.id.clone()).collect();
    ids.truncate(20);
    ApiError::not_found(
        "unknown_rig",
        format!("no rig {} (rigs: {})", quoted_name(id), ids.join(", ")),
    )
}

/// 404 for a clip the rig does not have, listing at most 20 of its clips.
pub fn unknown_clip(entry: &RigEntry, clip: &str) -> ApiError {
    let names: Vec<&str> = entry
        .rig()
        .clips
        .iter()
        .take(20)
        .map(|c| c.name.as_str())
        .collect();
    ApiError::not_found(
        "unknown_clip",
        format!(
            "rig {:?} has no clip {} (clips: {})",
            entry.id,
            quoted_name(clip),
            names.join(", ")
        ),
    )
}

/// A rig's names for live weights, owned (a request's lookups outlive no rig snapshot but
/// borrow none): channels by exact name, else by the one name with that loose spelling, as
/// `import::clips::Matcher` matches a clip's columns; and, for dense weights, by position in
/// `RigInfo::targets`.
pub(crate) struct LiveNames {
    /// Per name, in `RigInfo::targets` order, its channels.
    pub(crate) by_position: Vec<Vec<TargetId>>,
    /// Exact name → index into `by_position`.
    exact: HashMap<String, u32>,
    /// Loose spelling → the one name with it (`None` when several share it).
    loose: HashMap<String, Option<u32>>,
    /// The rig's named masks, which a layer's `"mask": "name"` finds before the built-in ones
    /// (a snapshot shared with the registry, not a copy).
    masks: Arc<BTreeMap<String, Mask>>,
}

impl LiveNames {
    /// Bytes [`LiveNames::new`] holds for `rig`, at most: per channel an id, per name a list,
    /// two spellings of its text and two map entries.
    pub(crate) fn bytes(rig: &Rig) -> u64 {
        let n = rig.targets.len() as u64;
        let text: u64 = rig.targets.iter().map(|t| t.len() as u64).sum();
        n * (size_of::<Vec<TargetId>>() as u64 + 4 + 2 * 64) + 2 * text
    }

    pub(crate) fn new(rig: &Rig) -> LiveNames {
        let names = rig.target_names();
        let index = rig.target_index();
        let mut exact = HashMap::with_capacity(names.len());
        let mut loose_names: HashMap<String, Option<u32>> = HashMap::with_capacity(names.len());
        let by_position = names.iter().map(|n| index.ids(n).to_vec()).collect();
        for (i, name) in names.iter().enumerate() {
            exact.insert((*name).to_string(), i as u32);
            loose_names
                .entry(loose(name))
                .and_modify(|m| *m = None)
                .or_insert(Some(i as u32));
        }
        LiveNames {
            by_position,
            exact,
            loose: loose_names,
            masks: Arc::default(),
        }
    }

    /// The same names with the rig's named masks (`RigMaps::masks`).
    pub(crate) fn with_masks(self, masks: Arc<BTreeMap<String, Mask>>) -> LiveNames {
        LiveNames { masks, ..self }
    }

    /// The rig's mask `name`, if it has one.
    pub(crate) fn rig_mask(&self, name: &str) -> Option<&Mask> {
        self.masks.get(name)
    }

    /// The channels the name refers to (empty: none, or several names loosely).
    pub(crate) fn ids(&self, name: &str) -> &[TargetId] {
        let found = match self.exact.get(name) {
            Some(&i) => Some(i),
            None => self.loose.get(&loose(name)).copied().flatten(),
        };
        found.map_or(&[], |i| &self.by_position[i as usize])
    }
}

/// `entry`'s rig's names with its named masks (the registry's current ones): what layers and
/// live weights are matched against.
pub(crate) fn live_names(registry: &Registry, entry: &RigEntry) -> LiveNames {
    LiveNames::new(entry.rig()).with_masks(registry.maps.masks(&entry.id))
}

/// Whether `name` is one of ARKit's 52 blendshape names, in any loose spelling.
pub(crate) fn is_arkit_name(name: &str) -> bool {
    static LOOSE: std::sync::LazyLock<std::collections::HashSet<String>> =
        std::sync::LazyLock::new(|| ARKIT_NAMES.iter().map(|n| loose(n)).collect());
    LOOSE.contains(&loose(name))
}
