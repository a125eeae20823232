//! A rig's named masks and mappings (`proto/README.md`, "Masks" and "Mappings"): masks that
//! layers name (`PUT /v1/rigs/{id}/masks/{name}`), and mappings from a producer's names
//! (a tracker's, Audio2Face's, visemes, a VRM avatar's expressions) to the rig's targets
//! (`PUT /v1/rigs/{id}/mappings/{name}`), which crowd heads, CSV clips and live input name.

use serde::{Deserialize, Serialize};

use crate::Mask;

/// `GET /v1/rigs/{id}/masks/{name}` response (also the answer to `PUT`, whose body is a
/// [`Mask`]: a list of target names or an object of names to weights).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MaskInfo {
    /// The rig.
    pub rig: String,
    /// The mask's name.
    pub name: String,
    /// The mask as stored.
    pub mask: Mask,
}

/// `GET /v1/rigs/{id}/masks` response: the rig's masks by name (the built-in ones are not
/// listed).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MaskList {
    /// By name.
    pub masks: Vec<MaskInfo>,
}

/// What a source does to one of VRM 1.0's procedural groups (blink, look-at, mouth) while it
/// is above 0: nothing, block it (its weights 0), or blend it (its weights times
/// `1 − weight`). In JSON `"none"`, `"block"`, `"blend"`; in bincode variants 0, 1, 2.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MapOverride {
    /// Nothing.
    #[default]
    None,
    /// The group's weights are 0.
    Block,
    /// The group's weights are scaled by `1 − weight`.
    Blend,
}

/// One entry of a [`Mapping`]: `target += gain · source + offset`, the target's sum then
/// clamped into every `clamp` its entries give.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MapEntry {
    /// The producer's name (matched exactly, else by its loose spelling).
    pub source: String,
    /// The rig's target (any loose spelling; an ARKit name the rig lacks is skipped).
    pub target: String,
    /// Multiplier (Audio2Face's per-shape multiplier), 1 when absent.
    #[serde(default = "crate::one")]
    pub gain: f32,
    /// Added after the gain (Audio2Face's per-shape offset), 0 when absent.
    #[serde(default)]
    pub offset: f32,
    /// The target's `[lo, hi]` after the sum.
    #[serde(default)]
    pub clamp: Option<[f32; 2]>,
}

/// A source with more than entries: binary (VRM's `isBinary`: above 0.5 is 1, else 0) or
/// overriding VRM's procedural groups.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MapSource {
    /// The source's name.
    pub name: String,
    /// Above 0.5 is 1, else 0.
    #[serde(default)]
    pub binary: bool,
    /// What it does to `blink`, `blinkLeft`, `blinkRight`.
    #[serde(default)]
    pub override_blink: MapOverride,
    /// What it does to `lookUp`, `lookDown`, `lookLeft`, `lookRight`.
    #[serde(default)]
    pub override_look_at: MapOverride,
    /// What it does to `aa`, `ih`, `ou`, `ee`, `oh`.
    #[serde(default)]
    pub override_mouth: MapOverride,
}

/// `PUT /v1/rigs/{id}/mappings/{name}` request: source names to the rig's targets.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Mapping {
    /// The entries.
    #[serde(default)]
    pub entries: Vec<MapEntry>,
    /// Sources that are binary or override a group (others need not be listed).
    #[serde(default)]
    pub sources: Vec<MapSource>,
}

/// `GET /v1/rigs/{id}/mappings/{name}` response (also the answer to `PUT`).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MappingInfo {
    /// The rig.
    pub rig: String,
    /// The mapping's name.
    pub name: String,
    /// Whether it is built in (`arkit`, `a2f`, `oculus-visemes`, `vrm`).
    pub builtin: bool,
    /// The mapping.
    pub mapping: Mapping,
}

/// `GET /v1/rigs/{id}/mappings` response: the built-in mappings the rig has, then its own.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MappingList {
    /// Built in first, then by name.
    pub mappings: Vec<MappingInfo>,
}
