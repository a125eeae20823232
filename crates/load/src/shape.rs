//! The crowds a load sends: how many heads, how many of them unique, which rigs, clips, LOD
//! levels, format and encoding; and the deterministic request bodies made from them.

use std::collections::BTreeMap;
use std::sync::Arc;

use bytes::Bytes;
use crowdmorph_proto::{CrowdFrameRequest, Format, Head, OutputOptions};
use serde::{Deserialize, Serialize};

use super::LoadError;
use crowdmorph_core::rng::SplitMix64;

/// Encoding of requests and responses.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum WireEncoding {
    /// `application/x-bincode` both ways.
    #[default]
    Bincode,
    /// `application/json` both ways (vertex data base64).
    Json,
}

impl WireEncoding {
    /// The Content-Type (and Accept) of this encoding.
    pub fn content_type(self) -> &'static str {
        match self {
            WireEncoding::Bincode => crowdmorph_proto::CONTENT_TYPE_BINCODE,
            WireEncoding::Json => crowdmorph_proto::CONTENT_TYPE_JSON,
        }
    }
}

/// The shape of every crowd request of a load.
///
/// Request `i` has `heads` heads over `unique_jobs()` distinct jobs (head `h` uses job
/// `h mod unique_jobs()`). Each job picks a rig uniformly from `rigs`, a clip from the `clips`
/// mix (by weight, among the mix's clips that rig has; every clip of the rig equally when the
/// mix is empty) and a LOD level from the `lods` mix, with a generator seeded by `seed`; job
/// `j` of request `i` plays frame `i × unique + j` (wrapping), so consecutive requests rarely
/// share jobs and the server gets little help from cross-request coalescing.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CrowdShape {
    /// Heads per request.
    pub heads: u32,
    /// Share of the heads that are unique jobs, in (0, 1]; the rest are clones.
    pub unique: f64,
    /// Rig ids, picked uniformly per job.
    pub rigs: Vec<String>,
    /// Clip name → weight; empty: every clip of the picked rig, equally.
    pub clips: BTreeMap<String, f64>,
    /// LOD level → weight.
    pub lods: BTreeMap<u32, f64>,
    /// Vertex format.
    pub format: Format,
    /// Ask for normals too.
    pub normals: bool,
    /// JSON or bincode.
    pub encoding: WireEncoding,
    /// Seed of the picks.
    pub seed: u64,
}

impl Default for CrowdShape {
    fn default() -> Self {
        CrowdShape {
            heads: 100,
            unique: 1.0,
            // The embedded rig every server has.
            rigs: vec!["default-head".to_string()],
            clips: BTreeMap::new(),
            lods: BTreeMap::from([(0, 1.0)]),
            format: Format::F32,
            normals: false,
            encoding: WireEncoding::Bincode,
            seed: 1,
        }
    }
}

/// Most entries in each of a shape's lists: its rigs, its clip mix, its LOD mix.
pub const MAX_MIX: usize = 64;

/// What the generator needs to know about a rig on the server.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RigClips {
    /// Its id.
    pub id: String,
    /// Its clip names.
    pub clips: Vec<String>,
    /// Its LOD levels.
    pub lod_levels: u32,
}

/// A rig id with the clip mix it plays (shared by every entry that lists the rig).
type RigMix = (String, Arc<Mix<String>>);

/// A weighted pick from a list.
struct Mix<T> {
    items: Vec<(T, f64)>,
    total: f64,
}

impl<T: Clone> Mix<T> {
    fn new(items: Vec<(T, f64)>) -> Option<Mix<T>> {
        let total: f64 = items.iter().map(|(_, w)| w).sum();
        (total > 0.0 && total.is_finite()).then_some(Mix { items, total })
    }

    fn pick(&self, rng: &mut SplitMix64) -> T {
        let mut x = rng.f64() * self.total;
        for (item, w) in &self.items {
            if x < *w {
                return item.clone();
            }
            x -= w;
        }
        // Rounding left x at the very top: the last item with any weight.
        self.items
            .iter()
            .rev()
            .find(|(_, w)| *w > 0.0)
            .map_or_else(|| self.items[0].0.clone(), |(i, _)| i.clone())
    }
}

fn weights_ok(what: &str, weights: impl Iterator<Item = f64>) -> Result<(), LoadError> {
    let mut sum = 0.0;
    for w in weights {
        if !(w.is_finite() && w >= 0.0) {
            return Err(LoadError::Invalid(format!(
                "{what} weights must be finite and >= 0, not {w}"
            )));
        }
        sum += w;
    }
    if sum > 0.0 {
        Ok(())
    } else {
        Err(LoadError::Invalid(format!(
            "{what} weights must add up to more than 0"
        )))
    }
}

impl CrowdShape {
    /// Unique jobs per request: `heads × unique`, rounded, at least 1.
    pub fn unique_jobs(&self) -> u32 {
        ((f64::from(self.heads) * self.unique).round() as u32).clamp(1, self.heads.max(1))
    }

    /// Checks what does not depend on the server.
    pub fn check(&self) -> Result<(), LoadError> {
        if self.heads == 0 {
            return Err(LoadError::Invalid(
                "a request needs at least one head".into(),
            ));
        }
        if !(self.unique > 0.0 && self.unique <= 1.0) {
            return Err(LoadError::Invalid(format!(
                "the unique share must be in (0, 1], not {}",
                self.unique
            )));
        }
        if self.rigs.is_empty() {
            return Err(LoadError::Invalid("name at least one rig".into()));
        }
        if !self.format.is_vertices() {
            return Err(LoadError::Invalid(format!(
                "format {} has no vertex buffers to load the engine with; ask for f32, f16, q16 \
                 or q16r",
                self.format.name()
            )));
        }
        // Every entry costs a lookup and its rig's clip list while the load is planned, before
        // any body is charged: the lists are capped, not left to the request size.
        for (what, len) in [
            ("rigs", self.rigs.len()),
            ("clips", self.clips.len()),
            ("lods", self.lods.len()),
        ] {
            if len > MAX_MIX {
                return Err(LoadError::Invalid(format!(
                    "crowd.{what} has {len} entries; at most {MAX_MIX}"
                )));
            }
        }
        if !self.clips.is_empty() {
            weights_ok("clip", self.clips.values().copied())?;
        }
        weights_ok("LOD", self.lods.values().copied())?;
        Ok(())
    }

    /// Each rig of the shape with the clip mix it plays; errors name a rig the server did not
    /// describe, a clip of the mix that no rig has, a rig that has none of the mix's clips, or
    /// a LOD level a rig does not have.
    /// A rig listed several times (to weight it) shares one mix.
    fn mixes(&self, rigs: &[RigClips]) -> Result<Vec<RigMix>, LoadError> {
        self.check()?;
        for name in self.clips.keys() {
            let has = |r: &&RigClips| r.clips.iter().any(|c| c == name);
            if !rigs
                .iter()
                .filter(|r| self.rigs.contains(&r.id))
                .any(|r| has(&r))
            {
                return Err(LoadError::Invalid(format!(
                    "no rig of the load has a clip {name:?}"
                )));
            }
        }
        let mut made: BTreeMap<&str, Arc<Mix<String>>> = BTreeMap::new();
        self.rigs
            .iter()
            .map(|id| {
                if let Some(mix) = made.get(id.as_str()) {
                    return Ok((id.clone(), mix.clone()));
                }
                let rig = rigs
                    .iter()
                    .find(|r| &r.id == id)
                    .ok_or_else(|| LoadError::Invalid(format!("the server has no rig {id:?}")))?;
                if let Some((&lod, _)) = self.lods.iter().find(|(l, _)| **l >= rig.lod_levels) {
                    return Err(LoadError::Invalid(format!(
                        "rig {id:?} has LOD levels 0..{}, not {lod}",
                        rig.lod_levels.saturating_sub(1)
                    )));
                }
                let items: Vec<(String, f64)> = if self.clips.is_empty() {
                    rig.clips.iter().map(|c| (c.clone(), 1.0)).collect()
                } else {
                    self.clips
                        .iter()
                        .filter(|(name, _)| rig.clips.contains(name))
                        .map(|(n, w)| (n.clone(), *w))
                        .collect()
                };
                let mix = Mix::new(items).ok_or_else(|| {
                    LoadError::Invalid(if self.clips.is_empty() {
                        format!("rig {id:?} has no clips to play")
                    } else {
                        format!(
                            "rig {id:?} has none of the clips of the mix (or only weights of 0)"
                        )
                    })
                })?;
                let mix = Arc::new(mix);
                made.insert(id.as_str(), mix.clone());
                Ok((id.clone(), mix))
            })
            .collect()
    }

    /// `count` requests, request `i` as the type's documentation says.
    pub fn requests(
        &self,
        rigs: &[RigClips],
        count: usize,
    ) -> Result<Vec<CrowdFrameRequest>, LoadError> {
        let mut out = Vec::with_capacity(count);
        self.each_request(rigs, count, |r| {
            out.push(r);
            Ok(())
        })?;
        Ok(out)
    }

    /// Makes the `count` requests one at a time and hands each to `each`, so that a caller
    /// that keeps only their encodings never holds more than one request's heads.
    fn each_request(
        &self,
        rigs: &[RigClips],
        count: usize,
        mut each: impl FnMut(CrowdFrameRequest) -> Result<(), LoadError>,
    ) -> Result<(), LoadError> {
        let mixes = self.mixes(rigs)?;
        let lods = Mix::new(self.lods.iter().map(|(&l, &w)| (l, w)).collect())
            .ok_or_else(|| LoadError::Invalid("the LOD mix is empty".into()))?;
        let mut rng = SplitMix64(self.seed);
        let unique = self.unique_jobs() as usize;
        for i in 0..count {
            let jobs: Vec<(String, String, u32)> = (0..unique)
                .map(|_| {
                    let (rig, clips) = &mixes[rng.below(mixes.len())];
                    (rig.clone(), clips.pick(&mut rng), lods.pick(&mut rng))
                })
                .collect();
            each(CrowdFrameRequest {
                heads: (0..self.heads as usize)
                    .map(|h| {
                        let j = h % unique;
                        let (rig, clip, lod) = &jobs[j];
                        Head {
                            head: h as u64,
                            rig: rig.clone(),
                            clip: clip.clone(),
                            frame: (i * unique + j) as i64,
                            lod: *lod,
                            ..Default::default()
                        }
                    })
                    .collect(),
                output: OutputOptions {
                    normals: self.normals,
                    format: self.format,
                },
                wrap: true,
            })?;
        }
        Ok(())
    }

    /// A request in the shape's encoding.
    fn encode(&self, r: &CrowdFrameRequest) -> Result<Vec<u8>, LoadError> {
        match self.encoding {
            WireEncoding::Bincode => {
                crowdmorph_proto::wire::to_bincode(r).map_err(|e| LoadError::Encode(e.to_string()))
            }
            WireEncoding::Json => {
                serde_json::to_vec(r).map_err(|e| LoadError::Encode(e.to_string()))
            }
        }
    }

    /// `count` request bodies in the shape's encoding, made one request at a time.
    pub fn bodies(&self, rigs: &[RigClips], count: usize) -> Result<Vec<Bytes>, LoadError> {
        Ok(self
            .bodies_with_rigs(rigs, count)?
            .into_iter()
            .map(|(b, _)| b)
            .collect())
    }

    /// [`CrowdShape::bodies`], each with the rig of its first head: the `?rig=` routing hint
    /// a balancer in front of several replicas hashes on (the clients send the same).
    pub fn bodies_with_rigs(
        &self,
        rigs: &[RigClips],
        count: usize,
    ) -> Result<Vec<(Bytes, String)>, LoadError> {
        let mut out = Vec::with_capacity(count);
        self.each_request(rigs, count, |r| {
            let rig = r.heads.first().map(|h| h.rig.clone()).unwrap_or_default();
            out.push((Bytes::from(self.encode(&r)?), rig));
            Ok(())
        })?;
        Ok(out)
    }

    /// Upper bounds of what [`CrowdShape::bodies`] makes, known before it runs (so that the
    /// memory can be charged first): the longest body, and what making one holds besides the
    /// bodies (one request's heads and its encoding). Every field of a head encodes to at
    /// most the length of its largest value (head id, frame, LOD level) or its longest name,
    /// so a head made of those, encoded by the shape's own encoder, bounds every head.
    pub fn body_sizes(&self, rigs: &[RigClips], count: usize) -> Result<BodySizes, LoadError> {
        let mixes = self.mixes(rigs)?;
        let longest = |names: &mut dyn Iterator<Item = &String>| -> Result<String, LoadError> {
            let mut best = (0, String::new());
            for n in names {
                let len = self.encode_str(n)?;
                if len > best.0 || best.1.is_empty() {
                    best = (len, n.clone());
                }
            }
            Ok(best.1)
        };
        let rig = longest(&mut mixes.iter().map(|(id, _)| id))?;
        let clip = longest(
            &mut mixes
                .iter()
                .flat_map(|(_, m)| m.items.iter().map(|(c, _)| c)),
        )?;
        let unique = u64::from(self.unique_jobs());
        let heads = u64::from(self.heads);
        let worst = Head {
            head: heads.saturating_sub(1),
            frame: i64::try_from((count as u64).saturating_mul(unique)).unwrap_or(i64::MAX),
            lod: self.lods.keys().copied().max().unwrap_or(0),
            rig,
            clip,
            ..Default::default()
        };
        let empty = CrowdFrameRequest {
            heads: Vec::new(),
            output: OutputOptions {
                normals: self.normals,
                format: self.format,
            },
            wrap: true,
        };
        let one = CrowdFrameRequest {
            heads: vec![worst.clone()],
            ..empty.clone()
        };
        let (empty_len, one_len) = (
            self.encode(&empty)?.len() as u64,
            self.encode(&one)?.len() as u64,
        );
        // JSON adds a comma between heads; bincode's head count grows to at most 9 bytes.
        let per_head = one_len - empty_len + 1;
        let body = empty_len + 8 + heads.saturating_mul(per_head);
        let names = (worst.rig.len() + worst.clip.len()) as u64;
        let request = heads.saturating_mul(size_of::<Head>() as u64 + names);
        Ok(BodySizes {
            body,
            // The request's heads, and its encoding while the vector it grows in doubles.
            building: request.saturating_add(body.saturating_mul(2)),
        })
    }

    /// Length of a name in the shape's encoding.
    fn encode_str(&self, s: &str) -> Result<usize, LoadError> {
        Ok(match self.encoding {
            WireEncoding::Bincode => crowdmorph_proto::wire::to_bincode(&s)
                .map_err(|e| LoadError::Encode(e.to_string()))?
                .len(),
            WireEncoding::Json => serde_json::to_vec(s)
                .map_err(|e| LoadError::Encode(e.to_string()))?
                .len(),
        })
    }
}

/// Sizes of a load's request bodies, bounded before they are made ([`CrowdShape::body_sizes`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BodySizes {
    /// Bytes of the longest body.
    pub body: u64,
    /// Bytes making one body holds besides the bodies already made.
    pub building: u64,
}

#[cfg(test)]
mod tests {
    // A test that meets an unexpected error should fail loudly.
    #![allow(clippy::unwrap_used)]

    use super::*;

    fn rigs() -> Vec<RigClips> {
        vec![
            RigClips {
                id: "a".into(),
                clips: vec!["talk".into(), "smile".into()],
                lod_levels: 3,
            },
            RigClips {
                id: "b".into(),
                clips: vec!["talk".into()],
                lod_levels: 1,
            },
        ]
    }

    #[test]
    fn requests_follow_the_shape() {
        let shape = CrowdShape {
            heads: 10,
            unique: 0.3,
            rigs: vec!["a".into(), "b".into()],
            clips: BTreeMap::from([("talk".into(), 1.0), ("smile".into(), 3.0)]),
            lods: BTreeMap::from([(0, 1.0)]),
            ..CrowdShape::default()
        };
        let reqs = shape.requests(&rigs(), 4).unwrap();
        assert_eq!(reqs.len(), 4);
        for (i, r) in reqs.iter().enumerate() {
            assert_eq!(r.heads.len(), 10);
            // 3 unique jobs: head h is a clone of head h mod 3.
            for (h, head) in r.heads.iter().enumerate() {
                let first = &r.heads[h % 3];
                assert_eq!(
                    (&head.rig, &head.clip, head.frame),
                    (&first.rig, &first.clip, first.frame)
                );
                assert_eq!(head.frame, (i * 3 + h % 3) as i64);
                // Rig b has only talk.
                if head.rig == "b" {
                    assert_eq!(head.clip, "talk");
                }
            }
        }
        // Deterministic.
        assert_eq!(reqs, shape.requests(&rigs(), 4).unwrap());
        assert_eq!(shape.bodies(&rigs(), 2).unwrap().len(), 2);
    }

    #[test]
    fn body_sizes_bound_every_body_in_both_encodings() {
        for encoding in [WireEncoding::Bincode, WireEncoding::Json] {
            for heads in [1, 10, 300, 5_000] {
                let shape = CrowdShape {
                    heads,
                    unique: 0.3,
                    rigs: vec!["a".into(), "b".into()],
                    clips: BTreeMap::from([("talk".into(), 1.0), ("smile".into(), 3.0)]),
                    encoding,
                    ..CrowdShape::default()
                };
                let sizes = shape.body_sizes(&rigs(), 64).unwrap();
                let bodies = shape.bodies(&rigs(), 64).unwrap();
                let longest = bodies.iter().map(Bytes::len).max().unwrap() as u64;
                assert!(
                    longest <= sizes.body,
                    "{encoding:?} {heads}: {longest} > {sizes:?}"
                );
                // A bound, not a guess: within a third of the real length.
                assert!(
                    sizes.body <= longest + longest / 3 + 16,
                    "{encoding:?} {heads}: {longest} vs {sizes:?}"
                );
            }
        }
    }

    #[test]
    fn the_mix_weights_are_followed() {
        let shape = CrowdShape {
            heads: 1000,
            rigs: vec!["a".into()],
            clips: BTreeMap::from([("talk".into(), 1.0), ("smile".into(), 3.0)]),
            lods: BTreeMap::from([(0, 1.0), (2, 1.0)]),
            ..CrowdShape::default()
        };
        let r = &shape.requests(&rigs(), 1).unwrap()[0];
        let smiles = r.heads.iter().filter(|h| h.clip == "smile").count();
        let lod2 = r.heads.iter().filter(|h| h.lod == 2).count();
        assert!((650..850).contains(&smiles), "{smiles} of 1000");
        assert!((400..600).contains(&lod2), "{lod2} of 1000");
    }

    #[test]
    fn impossible_shapes_are_named() {
        let bad = |shape: CrowdShape| shape.requests(&rigs(), 1).unwrap_err().to_string();
        let base = CrowdShape {
            rigs: vec!["a".into()],
            ..CrowdShape::default()
        };
        assert!(
            bad(CrowdShape {
                rigs: vec!["zzz".into()],
                ..base.clone()
            })
            .contains("no rig \"zzz\"")
        );
        assert!(
            bad(CrowdShape {
                clips: BTreeMap::from([("dance".into(), 1.0)]),
                ..base.clone()
            })
            .contains("\"dance\"")
        );
        assert!(
            bad(CrowdShape {
                rigs: vec!["b".into()],
                lods: BTreeMap::from([(2, 1.0)]),
                ..base.clone()
            })
            .contains("LOD levels 0..0, not 2")
        );
        assert!(
            bad(CrowdShape {
                unique: 0.0,
                ..base.clone()
            })
            .contains("unique share")
        );
        assert!(
            bad(CrowdShape {
                heads: 0,
                ..base.clone()
            })
            .contains("at least one head")
        );
        assert!(
            bad(CrowdShape {
                lods: BTreeMap::from([(0, -1.0)]),
                ..base
            })
            .contains("LOD weights")
        );
    }
}
