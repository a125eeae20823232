//! Mappings resolved against a rig (`crowdmorph_core::rig::mapping`): a built-in one (`arkit`,
//! `a2f`, `oculus-visemes`) or one of the rig's own (`PUT /v1/rigs/{id}/mappings/{name}`, and
//! `vrm` from its VRM file) by name, its targets matched as live weights match them (an ARKit
//! name the rig lacks is skipped), its sources by exact name, else by their one loose
//! spelling; then a producer's named values mapped to channel weights. Crowd heads
//! (`Head::mapping`), CSV clips (`?mapping=`) and live input use it. Errors are the 4xx a
//! request gets.

use std::collections::HashMap;

use crowdmorph_core::rig::{
    BUILTIN_MAPPINGS, MAX_LIVE_WEIGHT, MAX_MAP_ENTRIES, MapTable, MapTerm, NamedEntry,
    NamedMapping, NamedSource, Override, Procedural, Rig, SourceRule, builtin_mapping, quoted_name,
};
use crowdmorph_import::clips::{checked_name, is_live_link_angle, loose};
use crowdmorph_proto::{MapEntry, MapOverride, MapSource, Mapping};

use crate::admission::names::{LiveNames, is_arkit_name};
use crate::http::ApiError;
use crate::registry::RigEntry;
use crate::rig_maps::RigMaps;

/// Longest source, target or mask name (in bytes): names are matched, not stored for long.
pub const MAX_MAP_NAME: usize = 256;

fn invalid(message: String) -> ApiError {
    ApiError::bad_request("invalid_mapping", message)
}

fn over(o: MapOverride) -> Override {
    match o {
        MapOverride::None => Override::None,
        MapOverride::Block => Override::Block,
        MapOverride::Blend => Override::Blend,
    }
}

fn over_wire(o: Override) -> MapOverride {
    match o {
        Override::None => MapOverride::None,
        Override::Block => MapOverride::Block,
        Override::Blend => MapOverride::Blend,
    }
}

/// A wire mapping as the core's.
pub fn to_core(m: &Mapping) -> NamedMapping {
    NamedMapping {
        entries: m
            .entries
            .iter()
            .map(|e| NamedEntry {
                source: e.source.clone(),
                target: e.target.clone(),
                gain: e.gain,
                offset: e.offset,
                clamp: e.clamp,
            })
            .collect(),
        sources: m
            .sources
            .iter()
            .map(|s| NamedSource {
                name: s.name.clone(),
                binary: s.binary,
                overrides: [
                    over(s.override_blink),
                    over(s.override_look_at),
                    over(s.override_mouth),
                ],
            })
            .collect(),
    }
}

/// The core's mapping as the wire's.
pub fn to_wire(m: &NamedMapping) -> Mapping {
    Mapping {
        entries: m
            .entries
            .iter()
            .map(|e| MapEntry {
                source: e.source.clone(),
                target: e.target.clone(),
                gain: e.gain,
                offset: e.offset,
                clamp: e.clamp,
            })
            .collect(),
        sources: m
            .sources
            .iter()
            .map(|s| MapSource {
                name: s.name.clone(),
                binary: s.binary,
                override_blink: over_wire(s.overrides[0]),
                override_look_at: over_wire(s.overrides[1]),
                override_mouth: over_wire(s.overrides[2]),
            })
            .collect(),
    }
}

/// Bytes a decoded wire mapping holds (by capacity, with its names).
pub fn mapping_bytes(m: &Mapping) -> u64 {
    let entries = m.entries.capacity() * size_of::<MapEntry>()
        + m.entries
            .iter()
            .map(|e| e.source.capacity() + e.target.capacity())
            .sum::<usize>();
    let sources = m.sources.capacity() * size_of::<MapSource>()
        + m.sources.iter().map(|s| s.name.capacity()).sum::<usize>();
    (entries + sources) as u64
}

/// 404 `unknown_mapping`, listing the built-in mappings and the rig's own.
pub fn unknown_mapping(entry: &RigEntry, maps: &RigMaps, name: &str) -> ApiError {
    let own = maps.of(&entry.id).mappings;
    let mut have: Vec<&str> = BUILTIN_MAPPINGS
        .iter()
        .copied()
        .filter(|b| *b != "vrm" || own.contains_key("vrm"))
        .collect();
    have.extend(
        own.keys()
            .map(String::as_str)
            .filter(|n| *n != "vrm")
            .take(20),
    );
    ApiError::not_found(
        "unknown_mapping",
        format!(
            "rig {:?} has no mapping {} (mappings: {})",
            entry.id,
            quoted_name(name),
            have.join(", ")
        ),
    )
}

/// Mapping `name` of `entry`'s rig as specified: a built-in one, else the rig's own (its
/// `vrm` among them); 404 `unknown_mapping` otherwise.
pub fn mapping_spec(
    entry: &RigEntry,
    maps: &RigMaps,
    name: &str,
) -> Result<NamedMapping, ApiError> {
    if let Some(m) = builtin_mapping(name) {
        return Ok(m);
    }
    maps.mapping(&entry.id, name)
        .map(|m| to_core(&m))
        .ok_or_else(|| unknown_mapping(entry, maps, name))
}

/// Channels one target name can reach on `rig`, at most: one, plus every channel beyond the
/// first that shares a name (nodes with one name that behave differently).
fn channels_per_name(rig: &Rig) -> u64 {
    let names = rig.target_names().len();
    (rig.targets.len() - names.min(rig.targets.len())) as u64 + 1
}

/// Bytes [`resolve_mapping`] builds for `spec` on `rig`, at most: a term per entry and
/// channel its target reaches, a rule and two index entries (with the name twice) per source.
pub fn resolved_bytes(spec: &NamedMapping, rig: &Rig) -> u64 {
    let names: u64 = spec
        .entries
        .iter()
        .map(|e| e.source.len() as u64)
        .chain(spec.sources.iter().map(|s| s.name.len() as u64))
        .map(|n| 2 * n + 2 * 48 + size_of::<SourceRule>() as u64)
        .sum();
    let terms = spec.entries.len() as u64 * channels_per_name(rig) * size_of::<MapTerm>() as u64;
    names + 2 * terms + 64
}

/// A mapping resolved against one rig generation.
#[derive(Debug)]
pub(crate) struct ResolvedMapping {
    /// Its name, for errors.
    name: String,
    table: MapTable,
    exact: HashMap<String, u32>,
    loose: HashMap<String, Option<u32>>,
}

/// Checks one name of a mapping: not too long, no control characters.
fn check_name(what: &str, name: &str) -> Result<(), ApiError> {
    if name.len() > MAX_MAP_NAME {
        return Err(invalid(format!(
            "{what} is {} bytes long; a name has at most {MAX_MAP_NAME}",
            name.len()
        )));
    }
    checked_name(name).map_err(|why| invalid(format!("{what} {}: {why}", quoted_name(name))))
}

/// `spec` (mapping `name`) resolved against `entry`'s rig through its `names`: every name
/// checked (400 `invalid_mapping`), every target matched (400 `unknown_targets` for a name
/// that is neither the rig's nor ARKit's), gains, offsets and clamps checked. The caller
/// charges [`resolved_bytes`] first.
pub(crate) fn resolve_mapping(
    entry: &RigEntry,
    names: &LiveNames,
    name: &str,
    spec: &NamedMapping,
) -> Result<ResolvedMapping, ApiError> {
    let at = |e: ApiError| ApiError {
        message: format!("mapping {}: {}", quoted_name(name), e.message),
        ..e
    };
    let most = spec.entries.len().max(spec.sources.len());
    if most > MAX_MAP_ENTRIES {
        return Err(at(invalid(format!(
            "{} entries and {} sources; a mapping has at most {MAX_MAP_ENTRIES} of each",
            spec.entries.len(),
            spec.sources.len()
        ))));
    }
    let mut exact: HashMap<String, u32> = HashMap::new();
    let mut rules: Vec<SourceRule> = Vec::new();
    let mut slot = |source: &str, rules: &mut Vec<SourceRule>| -> u32 {
        *exact.entry(source.to_string()).or_insert_with(|| {
            rules.push(SourceRule {
                group: Procedural::of(source),
                ..SourceRule::default()
            });
            (rules.len() - 1) as u32
        })
    };
    for (i, s) in spec.sources.iter().enumerate() {
        check_name(&format!("sources[{i}].name"), &s.name).map_err(at)?;
        let k = slot(&s.name, &mut rules) as usize;
        if rules[k].binary || rules[k].overrides != [Override::None; 3] {
            return Err(at(invalid(format!(
                "sources name {} twice",
                quoted_name(&s.name)
            ))));
        }
        rules[k].binary = s.binary;
        rules[k].overrides = s.overrides;
    }
    let mut terms = Vec::with_capacity(spec.entries.len());
    for (i, e) in spec.entries.iter().enumerate() {
        check_name(&format!("entries[{i}].source"), &e.source).map_err(at)?;
        check_name(&format!("entries[{i}].target"), &e.target).map_err(at)?;
        let source = slot(&e.source, &mut rules);
        let ids = names.ids(&e.target);
        if ids.is_empty() && !is_arkit_name(&e.target) {
            return Err(at(ApiError::bad_request(
                "unknown_targets",
                format!(
                    "entries[{i}].target is {}, which rig {:?} does not have (GET /v1/rigs/{} lists its targets)",
                    quoted_name(&e.target),
                    entry.id,
                    entry.id
                ),
            )));
        }
        // An ARKit name the rig lacks: the rig cannot show it, as with live weights.
        for &target in ids {
            terms.push(MapTerm {
                source,
                target,
                gain: e.gain,
                offset: e.offset,
                clamp: e.clamp,
            });
        }
        if ids.is_empty() {
            // Still a source: a producer sends it, and its value must be checked.
            continue;
        }
    }
    let table = MapTable::new(rules, terms).map_err(|e| at(invalid(e.to_string())))?;
    let mut loose_names: HashMap<String, Option<u32>> = HashMap::with_capacity(exact.len());
    for (n, &k) in &exact {
        loose_names
            .entry(loose(n))
            .and_modify(|m| *m = None)
            .or_insert(Some(k));
    }
    Ok(ResolvedMapping {
        name: name.to_string(),
        table,
        exact,
        loose: loose_names,
    })
}

impl ResolvedMapping {
    /// The source slot of `name`: exactly, else by its one loose spelling.
    fn source(&self, name: &str) -> Option<u32> {
        self.exact
            .get(name)
            .copied()
            .or_else(|| self.loose.get(&loose(name)).copied().flatten())
    }

    /// Whether `name` is one of its sources (exactly, else by its one loose spelling).
    pub(crate) fn is_source(&self, name: &str) -> bool {
        self.source(name).is_some()
    }

    /// The channels it can set, ascending, each once.
    pub(crate) fn channels(&self) -> Vec<u32> {
        self.table.targets()
    }

    /// Bytes [`ResolvedMapping::map`] holds for `inputs` values: a value per source slot and
    /// a pair per term.
    pub(crate) fn map_bytes(&self) -> u64 {
        16 + 4 * self.table.sources() as u64 + self.table.output_bytes()
    }

    /// `input` (a producer's names and values) mapped to `(channel, weight)`, channels
    /// ascending, into `out`. A name that is no source of the mapping is a 400
    /// `invalid_weights` (Live Link's head and eye angles are skipped: a mapping maps
    /// blendshapes); so is a value or a mapped weight that is not finite within
    /// ±[`MAX_LIVE_WEIGHT`], and a source sent twice. The caller charges
    /// [`ResolvedMapping::map_bytes`] first.
    pub(crate) fn map(
        &self,
        input: &[(String, f32)],
        out: &mut Vec<(u32, f32)>,
    ) -> Result<(), ApiError> {
        let bad = |m: String| ApiError::bad_request("invalid_weights", m);
        let mut values = vec![f32::NAN; self.table.sources()];
        for (name, v) in input {
            if !(v.is_finite() && v.abs() <= MAX_LIVE_WEIGHT) {
                return Err(bad(format!(
                    "weights[{}] is {v}; a weight must be finite, within ±{MAX_LIVE_WEIGHT}",
                    quoted_name(name)
                )));
            }
            checked_name(name)
                .map_err(|why| bad(format!("weights[{}]: {why}", quoted_name(name))))?;
            match self.source(name) {
                Some(s) => {
                    let slot = &mut values[s as usize];
                    if !slot.is_nan() {
                        return Err(bad(format!(
                            "weights name the source of {} twice",
                            quoted_name(name)
                        )));
                    }
                    *slot = *v;
                }
                None if is_live_link_angle(name) => {}
                None => {
                    return Err(bad(format!(
                        "weights name {}, which mapping {} has no source for (GET .../mappings/{} lists them)",
                        quoted_name(name),
                        quoted_name(&self.name),
                        self.name
                    )));
                }
            }
        }
        self.table.apply(&mut values, out);
        if let Some((k, v)) = out
            .iter()
            .find(|(_, v)| !(v.is_finite() && v.abs() <= MAX_LIVE_WEIGHT))
        {
            return Err(bad(format!(
                "mapping {} gives channel {k} a weight of {v}; a weight must be finite, within ±{MAX_LIVE_WEIGHT}",
                quoted_name(&self.name)
            )));
        }
        Ok(())
    }
}

/// Bytes [`map_named`] holds for mapping `name` on `entry`'s rig (its spec as the server
/// keeps it, the rig's names, the resolved mapping and one mapping of `inputs` values), at
/// most; 0 for an unknown mapping (which [`map_named`] refuses before it builds anything).
pub fn map_named_bytes(entry: &RigEntry, maps: &RigMaps, name: &str, inputs: usize) -> u64 {
    let Ok(spec) = mapping_spec(entry, maps, name) else {
        return 0;
    };
    let rig = entry.rig();
    let sources = (spec.entries.len() + spec.sources.len()) as u64;
    2 * spec.heap_bytes()
        + LiveNames::bytes(rig)
        + resolved_bytes(&spec, rig)
        + 16
        + 4 * sources
        + 8 * spec.entries.len() as u64 * channels_per_name(rig)
        + 8 * inputs as u64
}

/// Live input through mapping `name` of `entry`'s rig: `(channel, weight)` pairs, channels
/// ascending (a channel is an index into the rig's `targets`). 404 `unknown_mapping`, 400
/// `invalid_mapping` / `unknown_targets` for a mapping that no longer fits the rig, 400
/// `invalid_weights` for bad input. The caller charges [`map_named_bytes`] first. It resolves
/// the mapping on every call; a caller that maps many inputs of one mapping resolves it once
/// ([`resolve_mapping`]) and calls [`ResolvedMapping::map`].
// The live input of session heads (`/v1/sessions/{id}/live`, issue 47) calls it.
pub(crate) fn map_named(
    entry: &RigEntry,
    maps: &RigMaps,
    name: &str,
    input: &[(String, f32)],
) -> Result<Vec<(u32, f32)>, ApiError> {
    let spec = mapping_spec(entry, maps, name)?;
    let names = LiveNames::new(entry.rig());
    let resolved = resolve_mapping(entry, &names, name, &spec)?;
    let mut out = Vec::new();
    resolved.map(input, &mut out)?;
    Ok(out)
}
