//! Mappings (issue 47): a producer's names (a tracker's, Audio2Face's, visemes, a VRM avatar's
//! expressions) turned into a rig's target weights. Each entry takes one source to one target
//! with a gain and an offset (Audio2Face's per-shape multipliers and offsets:
//! `gain · value + offset`); a target several entries reach gets their sum (many-to-one), a
//! source several entries name reaches each (one-to-many), and a target's sum is then clamped
//! into every clamp its entries give. An entry counts only when its source was sent: a target
//! none of whose sources was sent is left to what is below it.
//!
//! Before the entries, a source may be binary (VRM's `isBinary`: above 0.5 is 1, else 0), and
//! VRM 1.0's procedural overrides apply (`expressions.md`, "Procedural override"): each source
//! that is not itself of a procedural group may block or blend that group (blink: `blink`,
//! `blinkLeft`, `blinkRight`; look-at: `lookUp`, `lookDown`, `lookLeft`, `lookRight`; mouth:
//! `aa`, `ih`, `ou`, `ee`, `oh`). Per group, `value = Σ (block: 1, blend: w)` over the sent
//! sources with `w > 0` that override it, and its sources are scaled by
//! `1 − saturate(value)`; a binary source of the group is 0 as soon as that factor is below 1
//! ("completely suppressed if the effect received is greater than 0"). A binary source that
//! overrides uses its binary value.
//!
//! This module is the arithmetic on indices and the built-in tables by name; the server
//! matches the names against a rig (`crates/server/src/mappings.rs`).

use serde::{Deserialize, Serialize};

use super::ARKIT_NAMES;

/// Most entries (and most sources) a mapping may have.
pub const MAX_MAP_ENTRIES: usize = 1024;

/// Largest gain, offset or clamp bound in absolute value (a mapped weight is a live weight,
/// bounded by [`super::MAX_LIVE_WEIGHT`] too).
pub const MAX_MAP_VALUE: f32 = super::MAX_LIVE_WEIGHT;

/// The names of the built-in mappings, which no `PUT` may take.
pub const BUILTIN_MAPPINGS: [&str; 4] = ["arkit", "a2f", "oculus-visemes", "vrm"];

/// What a source does to a procedural group (VRM 1.0's `overrideBlink`, `overrideLookAt`,
/// `overrideMouth`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Override {
    /// Nothing.
    #[default]
    None,
    /// The group's weights are 0 while this source is above 0.
    Block,
    /// The group's weights are scaled down by this source's weight.
    Blend,
}

/// VRM 1.0's procedural groups, in the order of [`MapSource::overrides`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Procedural {
    /// `blink`, `blinkLeft`, `blinkRight`.
    Blink = 0,
    /// `lookUp`, `lookDown`, `lookLeft`, `lookRight`.
    LookAt = 1,
    /// `aa`, `ih`, `ou`, `ee`, `oh`.
    Mouth = 2,
}

impl Procedural {
    /// The group a source of this name belongs to (VRM's preset names, exactly).
    pub fn of(name: &str) -> Option<Procedural> {
        match name {
            "blink" | "blinkLeft" | "blinkRight" => Some(Procedural::Blink),
            "lookUp" | "lookDown" | "lookLeft" | "lookRight" => Some(Procedural::LookAt),
            "aa" | "ih" | "ou" | "ee" | "oh" => Some(Procedural::Mouth),
            _ => None,
        }
    }
}

/// One entry of a mapping by name: `target += gain · source + offset`, then clamped.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NamedEntry {
    /// The producer's name.
    pub source: String,
    /// The rig's target (any loose spelling).
    pub target: String,
    /// Multiplier.
    pub gain: f32,
    /// Added after the gain.
    pub offset: f32,
    /// The target's range after the sum, if any.
    pub clamp: Option<[f32; 2]>,
}

/// What a source is beyond its entries: binary, and what it overrides.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct NamedSource {
    /// The producer's name.
    pub name: String,
    /// Above 0.5 is 1, else 0.
    pub binary: bool,
    /// Blink, look-at and mouth overrides, in [`Procedural`]'s order.
    pub overrides: [Override; 3],
}

/// A mapping by name, as stored and sent: entries, and the sources with properties (a source
/// that only entries name is a plain one).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct NamedMapping {
    /// Source to target, in order.
    pub entries: Vec<NamedEntry>,
    /// Sources that are binary or override a group.
    pub sources: Vec<NamedSource>,
}

impl NamedMapping {
    /// Heap bytes it holds (names by length).
    pub fn heap_bytes(&self) -> u64 {
        let entries: u64 = self
            .entries
            .iter()
            .map(|e| (size_of::<NamedEntry>() + e.source.len() + e.target.len()) as u64)
            .sum();
        let sources: u64 = self
            .sources
            .iter()
            .map(|s| (size_of::<NamedSource>() + s.name.len()) as u64)
            .sum();
        entries + sources
    }
}

/// A mapping that cannot be used.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MappingError {
    /// More entries or sources than [`MAX_MAP_ENTRIES`].
    #[error("{0} entries or sources; a mapping has at most {MAX_MAP_ENTRIES}")]
    TooLarge(usize),
    /// A gain, offset or clamp that is not finite or past ±[`MAX_MAP_VALUE`].
    #[error("entries[{index}].{field} is {value}; it must be finite, within ±{MAX_MAP_VALUE}")]
    Value {
        /// Entry.
        index: usize,
        /// `gain`, `offset` or `clamp`.
        field: &'static str,
        /// What it was.
        value: f32,
    },
    /// A clamp with `lo > hi`, or a target whose entries' clamps do not overlap.
    #[error(
        "entries[{0}].clamp leaves its target no value (lo > hi, or no overlap with another entry's clamp of the same target)"
    )]
    EmptyClamp(usize),
}

/// One entry resolved to indices: a source slot and a target (a rig channel for the server).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MapTerm {
    /// Index into the input.
    pub source: u32,
    /// Output index.
    pub target: u32,
    /// Multiplier.
    pub gain: f32,
    /// Added after the gain.
    pub offset: f32,
    /// The target's range, if this entry gives one.
    pub clamp: Option<[f32; 2]>,
}

/// Per source slot: binary, its group, and its overrides.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SourceRule {
    /// Above 0.5 is 1, else 0.
    pub binary: bool,
    /// The procedural group it belongs to.
    pub group: Option<Procedural>,
    /// Blink, look-at and mouth overrides.
    pub overrides: [Override; 3],
}

/// A mapping resolved to indices and checked: what [`MapTable::apply`] evaluates.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MapTable {
    /// One per source slot.
    rules: Vec<SourceRule>,
    /// Sorted by target (stable: a target's entries keep their order).
    terms: Vec<MapTerm>,
    /// Per run of one target's terms: the target's clamp (the intersection of its entries').
    clamps: Vec<(u32, [f32; 2])>,
    /// Whether any source overrides a group (else that step is skipped).
    overriding: bool,
}

fn check(index: usize, field: &'static str, value: f32) -> Result<(), MappingError> {
    if value.is_finite() && value.abs() <= MAX_MAP_VALUE {
        Ok(())
    } else {
        Err(MappingError::Value {
            index,
            field,
            value,
        })
    }
}

impl MapTable {
    /// Checks and sorts `terms` (each `source` below `rules.len()`, which the caller ensures).
    pub fn new(rules: Vec<SourceRule>, mut terms: Vec<MapTerm>) -> Result<MapTable, MappingError> {
        let most = terms.len().max(rules.len());
        if most > MAX_MAP_ENTRIES {
            return Err(MappingError::TooLarge(most));
        }
        for (i, t) in terms.iter().enumerate() {
            check(i, "gain", t.gain)?;
            check(i, "offset", t.offset)?;
            if let Some([lo, hi]) = t.clamp {
                check(i, "clamp", lo)?;
                check(i, "clamp", hi)?;
                if lo > hi {
                    return Err(MappingError::EmptyClamp(i));
                }
            }
        }
        // Remember each term's entry for errors, then sort by target.
        let mut order: Vec<usize> = (0..terms.len()).collect();
        order.sort_by_key(|&i| terms[i].target);
        let sorted: Vec<MapTerm> = order.iter().map(|&i| terms[i]).collect();
        let mut clamps: Vec<(u32, [f32; 2])> = Vec::new();
        for (k, t) in sorted.iter().enumerate() {
            let Some([lo, hi]) = t.clamp else { continue };
            match clamps.last_mut() {
                Some((target, c)) if *target == t.target => {
                    c[0] = c[0].max(lo);
                    c[1] = c[1].min(hi);
                    if c[0] > c[1] {
                        return Err(MappingError::EmptyClamp(order[k]));
                    }
                }
                _ => clamps.push((t.target, [lo, hi])),
            }
        }
        terms = sorted;
        let overriding = rules
            .iter()
            .any(|r| r.overrides.iter().any(|o| *o != Override::None));
        Ok(MapTable {
            rules,
            terms,
            clamps,
            overriding,
        })
    }

    /// Source slots.
    pub fn sources(&self) -> usize {
        self.rules.len()
    }

    /// The targets some entry reaches, ascending, each once.
    pub fn targets(&self) -> Vec<u32> {
        let mut t: Vec<u32> = self.terms.iter().map(|t| t.target).collect();
        t.dedup();
        t
    }

    /// Heap bytes it holds.
    pub fn heap_bytes(&self) -> u64 {
        (self.rules.len() * size_of::<SourceRule>()
            + self.terms.len() * size_of::<MapTerm>()
            + self.clamps.len() * size_of::<(u32, [f32; 2])>()) as u64
    }

    /// Bytes [`MapTable::apply`] writes to `out`, at most (one pair per term).
    pub fn output_bytes(&self) -> u64 {
        (self.terms.len() * size_of::<(u32, f32)>()) as u64
    }

    /// Maps `input` (one value per source slot, NaN: not sent; binary and overridden sources
    /// are rewritten in place) to `(target, weight)` pairs, targets ascending, into `out`.
    pub fn apply(&self, input: &mut [f32], out: &mut Vec<(u32, f32)>) {
        out.clear();
        for (x, r) in input.iter_mut().zip(&self.rules) {
            if r.binary && !x.is_nan() {
                *x = if *x > 0.5 { 1.0 } else { 0.0 };
            }
        }
        if self.overriding {
            self.override_groups(input);
        }
        let mut clamps = self.clamps.iter().peekable();
        let mut k = 0;
        while k < self.terms.len() {
            let target = self.terms[k].target;
            let (mut sum, mut sent) = (0f32, false);
            while k < self.terms.len() && self.terms[k].target == target {
                let t = &self.terms[k];
                if let Some(&x) = input.get(t.source as usize)
                    && !x.is_nan()
                {
                    sum += t.gain * x + t.offset;
                    sent = true;
                }
                k += 1;
            }
            while clamps.peek().is_some_and(|c| c.0 < target) {
                clamps.next();
            }
            if let Some(&&(t, [lo, hi])) = clamps.peek()
                && t == target
            {
                sum = sum.clamp(lo, hi);
            }
            if sent {
                out.push((target, sum));
            }
        }
    }

    /// VRM 1.0's procedural overrides, in place.
    fn override_groups(&self, input: &mut [f32]) {
        let mut value = [0f32; 3];
        for (x, r) in input.iter().zip(&self.rules) {
            if x.is_nan() || *x <= 0.0 {
                continue;
            }
            for (g, o) in r.overrides.iter().enumerate() {
                // An override of the source's own group is not one.
                if r.group.is_some_and(|own| own as usize == g) {
                    continue;
                }
                value[g] += match o {
                    Override::None => 0.0,
                    Override::Block => 1.0,
                    Override::Blend => *x,
                };
            }
        }
        let factor = value.map(|v| 1.0 - v.clamp(0.0, 1.0));
        for (x, r) in input.iter_mut().zip(&self.rules) {
            let Some(g) = r.group else { continue };
            if x.is_nan() {
                continue;
            }
            let f = factor[g as usize];
            *x = if r.binary && f < 1.0 { 0.0 } else { *x * f };
        }
    }
}

/// ARKit's name in Live Link Face's capitalised spelling (`eyeBlinkLeft` → `EyeBlinkLeft`).
pub fn capitalised(name: &str) -> String {
    let mut c = name.chars();
    c.next()
        .map(|f| f.to_uppercase().chain(c).collect())
        .unwrap_or_default()
}

fn entry(source: &str, target: &str, gain: f32) -> NamedEntry {
    NamedEntry {
        source: source.to_string(),
        target: target.to_string(),
        gain,
        offset: 0.0,
        clamp: None,
    }
}

/// Audio2Face's blendshape output as sources: ARKit's names in the capitalised spelling its
/// exports (`facsNames`) and its `blendshape_params` lists use (NVIDIA's ACE Audio2Face-3D
/// parameter guide and migration guide; the Maya ACE guide defines the per-shape
/// multipliers and offsets as `output = value × multiplier + offset`, which the entries'
/// gain and offset are). Audio2Face solves 46 of ARKit's 52 shapes; the pages this was
/// written from name the parameters but do not list which 46, so the table accepts every
/// ARKit name Audio2Face may send, each onto the ARKit target of the same name (identity
/// gains), less `TongueOut`: Audio2Face-3D drives the tongue with its own tongue shapes
/// (`TongueTipUp`, ...; its 2.0 migration guide), which no ARKit rig has. A name the rig
/// lacks is skipped as live weights skip ARKit names.
pub fn a2f_names() -> impl Iterator<Item = &'static str> {
    ARKIT_NAMES.iter().copied().filter(|n| *n != "tongueOut")
}

/// The 15 Oculus (Meta) OVRLipSync visemes onto ARKit mouth and jaw targets. Our own table
/// (Meta publishes reference images per viseme, not ARKit weights): each viseme's mouth
/// shape as the ARKit shapes that make it, jaw opening by how open the viseme's vowel or
/// consonant is.
pub const OCULUS_VISEMES: [(&str, &[(&str, f32)]); 15] = [
    ("sil", &[]),
    (
        "PP",
        &[
            ("mouthPressLeft", 0.6),
            ("mouthPressRight", 0.6),
            ("mouthClose", 0.4),
        ],
    ),
    (
        "FF",
        &[
            ("mouthRollLower", 0.6),
            ("mouthUpperUpLeft", 0.3),
            ("mouthUpperUpRight", 0.3),
            ("jawOpen", 0.1),
        ],
    ),
    ("TH", &[("jawOpen", 0.15), ("tongueOut", 0.3)]),
    (
        "DD",
        &[
            ("jawOpen", 0.2),
            ("mouthStretchLeft", 0.2),
            ("mouthStretchRight", 0.2),
        ],
    ),
    (
        "kk",
        &[
            ("jawOpen", 0.25),
            ("mouthStretchLeft", 0.3),
            ("mouthStretchRight", 0.3),
        ],
    ),
    ("CH", &[("mouthFunnel", 0.5), ("jawOpen", 0.2)]),
    (
        "SS",
        &[
            ("mouthStretchLeft", 0.4),
            ("mouthStretchRight", 0.4),
            ("jawOpen", 0.05),
        ],
    ),
    (
        "nn",
        &[
            ("jawOpen", 0.2),
            ("mouthStretchLeft", 0.15),
            ("mouthStretchRight", 0.15),
        ],
    ),
    (
        "RR",
        &[
            ("mouthFunnel", 0.3),
            ("mouthPucker", 0.3),
            ("jawOpen", 0.15),
        ],
    ),
    (
        "aa",
        &[
            ("jawOpen", 0.7),
            ("mouthLowerDownLeft", 0.3),
            ("mouthLowerDownRight", 0.3),
        ],
    ),
    (
        "E",
        &[
            ("jawOpen", 0.35),
            ("mouthStretchLeft", 0.4),
            ("mouthStretchRight", 0.4),
        ],
    ),
    (
        "I",
        &[
            ("jawOpen", 0.2),
            ("mouthSmileLeft", 0.4),
            ("mouthSmileRight", 0.4),
        ],
    ),
    ("O", &[("jawOpen", 0.45), ("mouthFunnel", 0.6)]),
    ("U", &[("jawOpen", 0.15), ("mouthPucker", 0.8)]),
];

/// A built-in mapping that needs no rig data (`arkit`, `a2f`, `oculus-visemes`); `None` for
/// another name (`vrm` is read from the rig's file).
pub fn builtin_mapping(name: &str) -> Option<NamedMapping> {
    let identity = |names: &mut dyn Iterator<Item = &'static str>| NamedMapping {
        entries: names.map(|n| entry(&capitalised(n), n, 1.0)).collect(),
        sources: Vec::new(),
    };
    match name {
        "arkit" => Some(identity(&mut ARKIT_NAMES.iter().copied())),
        "a2f" => Some(identity(&mut a2f_names())),
        "oculus-visemes" => Some(NamedMapping {
            entries: OCULUS_VISEMES
                .iter()
                .flat_map(|(v, to)| to.iter().map(move |(t, g)| entry(v, t, *g)))
                .collect(),
            // `sil` moves nothing but is a source: a producer sends it.
            sources: OCULUS_VISEMES
                .iter()
                .map(|(v, _)| NamedSource {
                    name: v.to_string(),
                    ..NamedSource::default()
                })
                .collect(),
        }),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn term(source: u32, target: u32, gain: f32, offset: f32) -> MapTerm {
        MapTerm {
            source,
            target,
            gain,
            offset,
            clamp: None,
        }
    }

    fn run(t: &MapTable, input: &[f32]) -> Vec<(u32, f32)> {
        let mut input = input.to_vec();
        let mut out = Vec::new();
        t.apply(&mut input, &mut out);
        out
    }

    #[test]
    fn gain_offset_and_clamp() {
        let mut clamped = term(1, 3, 4.0, 0.0);
        clamped.clamp = Some([0.0, 1.0]);
        let t = MapTable::new(
            vec![SourceRule::default(); 2],
            vec![term(0, 5, 2.0, 0.25), clamped],
        )
        .expect("valid");
        // 2·0.5 + 0.25 = 1.25; 4·0.5 = 2 clamped to 1; targets ascending.
        assert_eq!(run(&t, &[0.5, 0.5]), vec![(3, 1.0), (5, 1.25)]);
        // A source not sent sets nothing, its offset included.
        assert_eq!(run(&t, &[f32::NAN, 0.1]), vec![(3, 0.4)]);
    }

    #[test]
    fn many_to_one_sums_then_clamps_and_one_to_many_reaches_each() {
        let mut a = term(0, 7, 1.0, 0.0);
        a.clamp = Some([-1.0, 0.8]);
        let mut b = term(1, 7, 1.0, 0.1);
        b.clamp = Some([0.0, 2.0]);
        let c = term(1, 2, -0.5, 0.0);
        let t = MapTable::new(vec![SourceRule::default(); 2], vec![a, b, c]).expect("valid");
        // Target 7: 0.3 + (0.3 + 0.1) = 0.7 within [0, 0.8]; source 1 also reaches 2.
        let out = run(&t, &[0.3, 0.3]);
        assert_eq!(out.len(), 2);
        assert_eq!(out[0], (2, -0.15));
        assert!((out[1].1 - 0.7).abs() < 1e-6 && out[1].0 == 7);
        // 0.6 + 0.7 = 1.3, clamped to the intersection's 0.8; one source alone still counts.
        assert_eq!(run(&t, &[0.6, 0.6])[1], (7, 0.8));
        assert_eq!(run(&t, &[0.5, f32::NAN]), vec![(7, 0.5)]);
    }

    #[test]
    fn bad_tables_are_refused() {
        let rules = vec![SourceRule::default(); 2];
        let nan = term(0, 0, f32::NAN, 0.0);
        assert!(matches!(
            MapTable::new(rules.clone(), vec![nan]),
            Err(MappingError::Value { field: "gain", .. })
        ));
        let huge = term(0, 0, 1.0, 1e9);
        assert!(matches!(
            MapTable::new(rules.clone(), vec![huge]),
            Err(MappingError::Value {
                field: "offset",
                ..
            })
        ));
        let (mut a, mut b) = (term(0, 1, 1.0, 0.0), term(1, 1, 1.0, 0.0));
        a.clamp = Some([0.0, 0.2]);
        b.clamp = Some([0.5, 1.0]);
        assert_eq!(
            MapTable::new(rules.clone(), vec![a, b]),
            Err(MappingError::EmptyClamp(1))
        );
        let many = vec![term(0, 0, 1.0, 0.0); MAX_MAP_ENTRIES + 1];
        assert_eq!(
            MapTable::new(rules, many),
            Err(MappingError::TooLarge(MAX_MAP_ENTRIES + 1))
        );
    }

    /// Sources: 0 happy (overrides), 1 blink, 2 aa; each onto its own target.
    fn vrm(happy: SourceRule, blink_binary: bool) -> MapTable {
        let rules = vec![
            happy,
            SourceRule {
                binary: blink_binary,
                group: Some(Procedural::Blink),
                // Its own group only, which is no override.
                overrides: [Override::Block, Override::None, Override::None],
            },
            SourceRule {
                group: Some(Procedural::Mouth),
                ..SourceRule::default()
            },
        ];
        let terms = (0..3).map(|s| term(s, s, 1.0, 0.0)).collect();
        MapTable::new(rules, terms).expect("valid")
    }

    fn overriding(o: Override, binary: bool) -> SourceRule {
        SourceRule {
            binary,
            group: None,
            overrides: [o, Override::None, o],
        }
    }

    #[test]
    fn vrm_overrides_block_and_blend() {
        let block = vrm(overriding(Override::Block, false), false);
        // Any happy at all zeroes blink and mouth; none leaves them.
        assert_eq!(
            run(&block, &[0.1, 0.8, 0.6]),
            vec![(0, 0.1), (1, 0.0), (2, 0.0)]
        );
        assert_eq!(
            run(&block, &[0.0, 0.8, 0.6]),
            vec![(0, 0.0), (1, 0.8), (2, 0.6)]
        );
        let blend = vrm(overriding(Override::Blend, false), false);
        let out = run(&blend, &[0.25, 0.8, 0.4]);
        assert!((out[1].1 - 0.6).abs() < 1e-6, "0.8 × (1 − 0.25): {out:?}");
        assert!((out[2].1 - 0.3).abs() < 1e-6, "0.4 × (1 − 0.25): {out:?}");
        // A blink source's own blink override is not one: blink does not block itself.
        assert_eq!(run(&blend, &[f32::NAN, 0.8, f32::NAN]), vec![(1, 0.8)]);
    }

    #[test]
    fn vrm_binary_sources_and_overrides() {
        // A binary overrider acts by its binary value: 0.4 is 0 and blocks nothing; 0.6 is 1.
        let t = vrm(overriding(Override::Blend, true), false);
        assert_eq!(run(&t, &[0.4, 0.8, f32::NAN]), vec![(0, 0.0), (1, 0.8)]);
        assert_eq!(run(&t, &[0.6, 0.8, f32::NAN]), vec![(0, 1.0), (1, 0.0)]);
        // A binary overridden source is 0 once any effect reaches it, else 0 or 1.
        let t = vrm(overriding(Override::Blend, false), true);
        assert_eq!(run(&t, &[0.1, 0.8, f32::NAN]), vec![(0, 0.1), (1, 0.0)]);
        assert_eq!(run(&t, &[0.0, 0.8, f32::NAN]), vec![(0, 0.0), (1, 1.0)]);
        assert_eq!(run(&t, &[0.0, 0.3, f32::NAN]), vec![(0, 0.0), (1, 0.0)]);
    }

    #[test]
    fn builtin_tables() {
        let arkit = builtin_mapping("arkit").expect("arkit");
        assert_eq!(arkit.entries.len(), 52);
        assert!(
            arkit
                .entries
                .iter()
                .any(|e| e.source == "EyeBlinkLeft" && e.target == "eyeBlinkLeft")
        );
        assert!(arkit.entries.iter().all(|e| e.gain == 1.0
            && e.offset == 0.0
            && e.source.to_lowercase() == e.target.to_lowercase()));
        let a2f = builtin_mapping("a2f").expect("a2f");
        assert!(
            a2f.entries
                .iter()
                .all(|e| ARKIT_NAMES.contains(&e.target.as_str()))
        );
        let visemes = builtin_mapping("oculus-visemes").expect("visemes");
        assert_eq!(visemes.sources.len(), 15);
        assert!(
            visemes
                .entries
                .iter()
                .all(|e| ARKIT_NAMES.contains(&e.target.as_str()) && e.gain > 0.0 && e.gain <= 1.0)
        );
        assert!(builtin_mapping("vrm").is_none() && builtin_mapping("x").is_none());
        assert_eq!(capitalised("jawOpen"), "JawOpen");
    }
}
