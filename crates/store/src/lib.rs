//! crowdmorph-store: persistence. [`codec`] is the one module of the workspace that touches
//! bincode (wire messages and stored records); the crate root keeps rigs in the data dir;
//! [`objects`] is the shared store of several replicas (a directory, or S3 with feature `s3`).
//!
//! | module | what it is |
//! |---|---|
//! | [`codec`] | the one bincode user: wire messages, stored records, `FrameResponseEncoder` |
//! | the crate root | the data dir: one checksummed, atomically replaced record per rig, plus clip files |
//! | [`objects`] | the shared store of `serve --store`: immutable objects and a manifest per generation, repairs, LOD claims |
//! | `sections` | the payload of records since kind 12: tagged sections (`tag, length, bytes`), checked before anything is decoded |
//!
//! # The data dir
//!
//! Persistence of registered rigs and clips: one checksummed record per rig under the data
//! dir, and one per batch of clips added to it later.
//!
//! A rig's record holds its geometry, LOD and the clips it was stored with; clips uploaded
//! afterwards go to their own files (`<id>@<seq>.cmclips`, in upload order), so adding a clip
//! writes that clip, not the whole rig again. A rig's clips are its record's, then its clip
//! files' in sequence order. Deleting a clip rewrites only the file that holds it.
//!
//! Nothing is ever half-written where a reader looks: a record is written to a temporary file in
//! the same directory, flushed to disk (`fsync`), renamed over its final name (atomic on POSIX
//! file systems), and the directory is flushed so that the rename itself survives a power cut.
//! A process killed at any point leaves either the old file, the new file, or a stray temporary
//! file that the next start deletes — never a partial rig.
//!
//! File layout (all integers little-endian):
//!
//! | bytes | what |
//! |---|---|
//! | 8 | magic `CMSTORE1` |
//! | 4 | record kind: 12 = a rig, 13 = the extra clips and LOD of a built-in rig, 14 = clips added to a rig, each a payload of sections (below); read but no longer written (the legacy kinds, one whole value each): 6 = a rig, 9 = a rig with a skeleton, 10 = the same with its own joint map, 7 = a built-in rig's clips and LOD, 8 = clips added to a rig, 11 = the same with joint tables, and, with their clips as plain tables, 5 and 1 (a rig with and without base colours), 3 and 2 (a built-in rig's clips with and without its LOD), 4 (clips added to a rig) |
//! | 8 | payload length `n` |
//! | 4 | CRC-32 (IEEE) of the payload |
//! | n | payload: kinds 12–14, sections; legacy kinds, the record encoded by [`crate::codec`] |
//!
//! **Sections** (kinds 12–14). Each kind of record was once a new kind per feature (a rig,
//! then a rig with a skeleton, then with its own joint map...); the payload is now a sequence
//! of sections, `tag: u32, length: u64, bytes` (little-endian), each section's bytes one value
//! encoded by [`crate::codec`], in any order, each tag at most once. A record holds the
//! required sections of its kind and the others its rig has; the next feature is a new
//! section, not a new kind. The kind still says what the record is (a rig, a built-in rig's
//! clips, a clip file), as in the legacy kinds. Bit 31 of a tag marks a section that a reader
//! which does not know it may skip (a later build's addition that an older build can do
//! without); an unknown tag without it makes the record unreadable, and so does a missing
//! required section, a tag seen twice, a known tag of another kind of record, or a length
//! past the payload's end (checked before anything is decoded or allocated). Every tag
//! below has bit 31 clear, as this build knows them all. Builds from before kind 12 read none
//! of kinds 12–14 (unknown record kind): replicas sharing a store run this build or a later
//! one before any of them writes; an older replica finds such a generation unusable (a record
//! it cannot decode, which is not damage to repair) rather than rewriting it.
//!
//! | tag | section | in kinds | present |
//! |---|---|---|---|
//! | 1 | the registry id | 12, 13, 14 | always (required) |
//! | 2 | the clip file's sequence number | 14 | always (required) |
//! | 3 | the rig: name, targets, default weights, primitives, their base colours, LOD table (JSON) | 12 | always (required) |
//! | 4 | the record's clips, each its plain table or compressed (below) | 12, 13, 14 | always (required; may be empty) |
//! | 5 | the joint tables of the record's clips, by clip name | 12, 13, 14 | when one of its clips has a table |
//! | 6 | the skin: skeleton, each primitive's influences, the import's notes | 12 | when the rig has a skeleton |
//! | 7 | the rig's own joint map | 12 | when its skeleton has one (never without 6) |
//! | 8 | a built-in rig's LOD (JSON) and the [`geometry_fingerprint`] it was built for | 13 | always written; a record without it has no LOD (as kind 2) |
//! | 9 | each primitive's texture coordinates of set 0 ([`crowdmorph_core::rig::VertexLook::uv0`]) | 12 | when a primitive has some |
//! | 10 | the rest of each primitive's [`crowdmorph_core::rig::VertexLook`] (set 1, colours, material) and the rig's [`crowdmorph_core::rig::Appearance`]: materials, textures, samplers, notes and wrinkle maps (`target_textures`) as JSON, images as their encoded bytes | 12 | when the rig has materials or one of those arrays |
//! | 11 | the clips' animated textures, by clip name, each in its byte form (`AnimatedTexture::to_bytes`) | 12 | when a clip has one |
//!
//! A file whose magic, length, checksum or payload is wrong is reported and skipped by
//! [`Store::load_all`]; nothing of it is loaded. Loaded rigs are re-validated with
//! [`Rig::validate`] so that a record from an older build that no longer satisfies the
//! invariants is skipped too.
//!
//! **Compressed clips** (`serve --compress-clips E`, [`Store::compress_clips`]). Kinds 6–11
//! and section 4 hold each clip either as its plain table, curve-coded by [`crowdmorph_anim::compress`], or
//! transform-coded by [`crowdmorph_anim::transform`] (clip record variant 2, versioned inside;
//! records written before it never hold it and read as before) within `E ×` the
//! rig's diagonal. The server puts a clip into that form as it arrives
//! ([`crowdmorph_anim::compress::stored_form`]), so the clip it plays is the one the record decodes to,
//! before and after a restart; the writer compresses only a clip that is already in that form
//! (it checks by decoding), and stores any other plainly. A compressed clip is decoded and
//! checked on its own when its file is read: one that does not decode (a record a faulty
//! build wrote, a segment damaged before the checksum was taken) is skipped and reported,
//! and the rest of its file loads.

pub mod codec;
pub mod objects;
mod sections;

use std::fs::{self, File};
use std::io::{Seek, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use serde::{Deserialize, Serialize};

use crowdmorph_core::rig::{
    Appearance, Clip, ImageData, ImageMime, Influences, JointMap, JointTable, Lod, Material, Rig,
    Sampler, Skeleton, TargetTexture, Texture, VertexLook,
};

use sections::{Known, Sections};

const MAGIC: &[u8; 8] = b"CMSTORE1";
const HEADER: usize = 8 + 4 + 8 + 4;
const KIND_RIG: u32 = 1;
/// A whole rig with its primitives' base colours (written since they were added).
const KIND_RIG_COLORS: u32 = 5;
const KIND_BUILTIN_CLIPS: u32 = 2;
const KIND_BUILTIN: u32 = 3;
const KIND_CLIPS: u32 = 4;
/// Kind 5 with each clip as a [`ClipRecord`].
const KIND_RIG_V6: u32 = 6;
/// Kind 3 with each clip as a [`ClipRecord`].
const KIND_BUILTIN_V7: u32 = 7;
/// Kind 4 with each clip as a [`ClipRecord`].
const KIND_CLIPS_V8: u32 = 8;
/// Kind 6 followed by a [`SkinRecord`]: a rig with a skeleton (others are still kind 6).
const KIND_RIG_SKINNED_V9: u32 = 9;
/// Kind 9 followed by the rig's own [`JointMap`] (rigs with the default map are still kind 9).
const KIND_RIG_SKINNED_MAP_V10: u32 = 10;
/// Kind 8 followed by the clips' joint tables by name (clips without any are still kind 8).
const KIND_CLIPS_JOINTS_V11: u32 = 11;
/// A rig as sections: [`RIG_SECTIONS`] (written for every rig since; replaces 6, 9 and 10).
const KIND_RIG_SECTIONS: u32 = 12;
/// A built-in rig's clips and LOD as sections: [`BUILTIN_SECTIONS`] (replaces 7).
const KIND_BUILTIN_SECTIONS: u32 = 13;
/// Clips added to a rig as sections: [`CLIPS_SECTIONS`] (replaces 8 and 11).
const KIND_CLIPS_SECTIONS: u32 = 14;

/// The registry id (`String`).
const S_ID: Known = Known {
    tag: 1,
    name: "id",
    required: true,
};
/// A clip file's sequence number (`u64`).
const S_SEQ: Known = Known {
    tag: 2,
    name: "sequence number",
    required: true,
};
/// The rig without its clips and skeleton: [`RigSectionRef`].
const S_RIG: Known = Known {
    tag: 3,
    name: "rig",
    required: true,
};
/// The record's clips, each a [`ClipRecord`] (an empty list when it holds none).
const S_CLIPS: Known = Known {
    tag: 4,
    name: "clips",
    required: true,
};
/// The joint tables of the record's clips by clip name, when one has a table.
const S_CLIP_JOINTS: Known = Known {
    tag: 5,
    name: "joint tables",
    required: false,
};
/// The skeleton of a rig that has one: [`SkinSectionRef`].
const S_SKIN: Known = Known {
    tag: 6,
    name: "skin",
    required: false,
};
/// The rig's own [`JointMap`], when its skeleton has one (only beside [`S_SKIN`]).
const S_JOINT_MAP: Known = Known {
    tag: 7,
    name: "joint map",
    required: false,
};
/// A built-in rig's LOD and the geometry it was built for: [`LodSection`].
const S_LOD: Known = Known {
    tag: 8,
    name: "LOD",
    required: false,
};
/// Each primitive's [`VertexLook`] (texture coordinates): [`LookSectionRef`]. Bit 31 clear
/// on purpose: a build that does not know it must not load the rig without it (and then
/// write it back without its texture coordinates).
const S_LOOK: Known = Known {
    tag: 9,
    name: "vertex appearance",
    required: false,
};
/// The rest of each primitive's [`VertexLook`] and the rig's [`Appearance`]:
/// [`AppearanceSectionRef`]. Bit 31 clear for the reason given at [`S_LOOK`].
const S_APPEARANCE: Known = Known {
    tag: 10,
    name: "appearance",
    required: false,
};
/// The clips' animated textures ([`crowdmorph_core::rig::AnimatedTexture`]), each by clip
/// name in its byte form (`AnimatedTexture::to_bytes`, the body of `PUT
/// /v1/rigs/{id}/clips/{clip}/texture`). Bit 31 clear for the reason given at [`S_LOOK`].
const S_CLIP_TEXTURES: Known = Known {
    tag: 11,
    name: "clip textures",
    required: false,
};
/// The sections of kind 12.
const RIG_SECTIONS: &[Known] = &[
    S_ID,
    S_RIG,
    S_CLIPS,
    S_CLIP_JOINTS,
    S_SKIN,
    S_JOINT_MAP,
    S_LOOK,
    S_APPEARANCE,
    S_CLIP_TEXTURES,
];
/// The sections of kind 13.
const BUILTIN_SECTIONS: &[Known] = &[S_ID, S_CLIPS, S_CLIP_JOINTS, S_LOD];
/// The sections of kind 14.
const CLIPS_SECTIONS: &[Known] = &[S_ID, S_SEQ, S_CLIPS, S_CLIP_JOINTS];
/// Extension of record files.
pub const EXT: &str = "cmrig";
/// Extension of clip files.
const CLIPS_EXT: &str = "cmclips";
/// Prefix of temporary files. Rig ids never start with a dot (`registry::valid_id`), so no
/// record name can ever carry it, whatever the id.
const TMP: &str = ".tmp-";

/// A rig as loaded: its registry id and the rig with all its clips.
#[derive(Clone, Debug, PartialEq)]
pub struct StoredRig {
    /// Registry id (also the file name).
    pub id: String,
    /// The rig.
    pub rig: Rig,
}

/// What is stored of a built-in rig, whose geometry comes with the binary: the clips added to
/// it and its LOD.
#[derive(Clone, Debug, PartialEq)]
pub struct StoredBuiltin {
    /// Id of the built-in rig.
    pub id: String,
    /// The clips, in the order they were added.
    pub clips: Vec<Clip>,
    /// The LOD it had, with the [`geometry_fingerprint`] of the rig it was built for (a LOD is
    /// only valid for that geometry, and a new build may change the built-in rig).
    pub lod: Option<(Lod, u32)>,
}

/// A checksum of what a LOD depends on: target names, triangles and base positions.
pub fn geometry_fingerprint(rig: &Rig) -> u32 {
    let mut h = crc32fast::Hasher::new();
    for t in &rig.targets {
        h.update(t.as_bytes());
        h.update(&[0]);
    }
    for p in rig.primitives.iter() {
        h.update(&(p.positions.len() as u64).to_le_bytes());
        for v in &p.positions {
            for c in v.to_array() {
                h.update(&c.to_le_bytes());
            }
        }
        for i in &p.indices {
            h.update(&i.to_le_bytes());
        }
    }
    h.finalize()
}

/// A record to write, borrowed so that a big rig is not cloned to be stored.
#[derive(Clone, Copy, Debug)]
pub enum RecordRef<'a> {
    /// An uploaded rig: geometry, LOD and the clips stored with it.
    Rig {
        /// Registry id.
        id: &'a str,
        /// The rig.
        rig: &'a Rig,
        /// The clips stored in this record (the rig's others are in clip files).
        clips: &'a [Clip],
    },
    /// Clips added to a rig after its record was written, as clip file `seq`.
    Clips {
        /// Registry id of the rig.
        id: &'a str,
        /// The file's sequence number (files load in this order).
        seq: u64,
        /// The clips.
        clips: &'a [Clip],
        /// The rig they belong to (a compressing store's budget is in its vertex space).
        rig: &'a Rig,
    },
    /// Extra clips and the LOD of a built-in rig.
    Builtin {
        /// Id of the built-in rig.
        id: &'a str,
        /// The clips stored in this record (the rig's others are built in or in clip files).
        clips: &'a [Clip],
        /// The whole rig as it is now (for its LOD and geometry fingerprint).
        rig: &'a Rig,
    },
}

#[derive(Deserialize)]
struct SkinRecord {
    skeleton: Skeleton,
    influences: Vec<Option<Influences>>,
    clip_joints: Vec<(String, JointTable)>,
    notes: Vec<String>,
}

impl SkinRecord {
    /// Puts the skeleton, the clips' joint tables, and its own joint map if it had one, back
    /// into `rig` (validated by the caller).
    fn apply(self, rig: &mut Rig, map: Option<JointMap>) -> Result<(), String> {
        let SkinRecord {
            skeleton,
            influences,
            clip_joints,
            notes,
        } = self;
        SkinSection {
            skeleton,
            influences,
            notes,
        }
        .apply(rig, map)?;
        attach_joint_tables(&mut rig.clips, clip_joints);
        Ok(())
    }
}

/// Section [`S_SKIN`]: the skeleton, each primitive's influences (serde skips them inside the
/// rig) and the import's notes, which are stored with a skeleton only (as [`Rig::import_notes`]
/// says).
#[derive(Serialize)]
struct SkinSectionRef<'a> {
    skeleton: &'a Skeleton,
    influences: Vec<Option<&'a Influences>>,
    notes: &'a [String],
}

/// Owned mirror of [`SkinSectionRef`].
#[derive(Deserialize)]
struct SkinSection {
    skeleton: Skeleton,
    influences: Vec<Option<Influences>>,
    notes: Vec<String>,
}

impl SkinSection {
    /// Puts the skeleton, and its own joint map if it had one, back into `rig` (validated by
    /// the caller).
    fn apply(self, rig: &mut Rig, map: Option<JointMap>) -> Result<(), String> {
        if self.influences.len() != rig.primitives.len() {
            return Err(format!(
                "{} influence sets for {} primitives",
                self.influences.len(),
                rig.primitives.len()
            ));
        }
        let mut prims = rig.primitives.as_ref().clone();
        for (p, i) in prims.iter_mut().zip(self.influences) {
            p.skin = i;
        }
        rig.primitives = std::sync::Arc::new(prims);
        let mut skeleton = self.skeleton;
        skeleton.map = map;
        rig.skeleton = Some(std::sync::Arc::new(skeleton));
        rig.import_notes = self.notes;
        Ok(())
    }
}

/// Section [`S_LOOK`]: per primitive, its texture coordinates of set 0 (serde skips
/// [`VertexLook`] inside the rig).
#[derive(Serialize)]
struct LookSectionRef<'a> {
    uv0: Vec<Option<&'a [glam::Vec2]>>,
}

/// Owned mirror of [`LookSectionRef`].
#[derive(Deserialize)]
struct LookSection {
    uv0: Vec<Option<Vec<glam::Vec2>>>,
}

impl<'a> LookSectionRef<'a> {
    /// The section of `rig`, when one of its primitives has something to keep.
    fn of(rig: &'a Rig) -> Option<Self> {
        let uv0: Vec<Option<&[glam::Vec2]>> = rig
            .primitives
            .iter()
            .map(|p| p.look.uv0.as_deref())
            .collect();
        uv0.iter()
            .any(Option::is_some)
            .then_some(LookSectionRef { uv0 })
    }
}

impl LookSection {
    /// Puts each primitive's data back into `rig` (lengths are checked by the caller's
    /// [`Rig::validate`]).
    fn apply(self, rig: &mut Rig) -> Result<(), String> {
        if self.uv0.len() != rig.primitives.len() {
            return Err(format!(
                "vertex appearance of {} primitives for {}",
                self.uv0.len(),
                rig.primitives.len()
            ));
        }
        let mut prims = rig.primitives.as_ref().clone();
        for (p, uv) in prims.iter_mut().zip(self.uv0) {
            p.look = VertexLook {
                uv0: uv,
                ..VertexLook::default()
            };
        }
        rig.primitives = std::sync::Arc::new(prims);
        Ok(())
    }
}

/// Section [`S_APPEARANCE`]: per primitive, the rest of its [`VertexLook`]; the rig's
/// [`Appearance`] tables as JSON (so a later field with a default still reads this one:
/// bincode is positional), and its images' encoded bytes. Decoded pixels are never stored.
#[derive(Serialize)]
struct AppearanceSectionRef<'a> {
    prims: Vec<PrimLookRef<'a>>,
    tables_json: String,
    images: Vec<&'a [u8]>,
}

/// One primitive's part of [`AppearanceSectionRef`].
#[derive(Serialize)]
struct PrimLookRef<'a> {
    uv1: Option<&'a [glam::Vec2]>,
    colors: Option<&'a [glam::Vec4]>,
    material: Option<u32>,
}

/// Owned mirror of [`AppearanceSectionRef`].
#[derive(Deserialize)]
struct AppearanceSection {
    prims: Vec<PrimLook>,
    tables_json: String,
    images: Vec<Vec<u8>>,
}

/// Owned mirror of [`PrimLookRef`].
#[derive(Deserialize)]
struct PrimLook {
    uv1: Option<Vec<glam::Vec2>>,
    colors: Option<Vec<glam::Vec4>>,
    material: Option<u32>,
}

/// The JSON part of [`AppearanceSectionRef`]: everything but the image bytes.
#[derive(Serialize, Deserialize)]
struct AppearanceTables {
    materials: Vec<Material>,
    textures: Vec<Texture>,
    samplers: Vec<Sampler>,
    images: Vec<ImageMeta>,
    notes: Vec<String>,
    /// Wrinkle maps; absent from records written before they existed (hence the default).
    #[serde(default)]
    target_textures: Vec<TargetTexture>,
}

/// An image of [`AppearanceTables`] without its bytes.
#[derive(Serialize, Deserialize)]
struct ImageMeta {
    mime: ImageMime,
    width: u32,
    height: u32,
    downscaled_from: Option<[u32; 2]>,
}

impl<'a> AppearanceSectionRef<'a> {
    /// The section of `rig`, when it has an appearance or a primitive has any of the data.
    fn of(rig: &'a Rig) -> Result<Option<Self>, StoreError> {
        let prims: Vec<PrimLookRef<'a>> = rig
            .primitives
            .iter()
            .map(|p| PrimLookRef {
                uv1: p.look.uv1.as_deref(),
                colors: p.look.colors.as_deref(),
                material: p.look.material,
            })
            .collect();
        let any_prim = prims
            .iter()
            .any(|p| p.uv1.is_some() || p.colors.is_some() || p.material.is_some());
        if rig.appearance.is_none() && !any_prim {
            return Ok(None);
        }
        static EMPTY: Appearance = Appearance {
            materials: Vec::new(),
            textures: Vec::new(),
            samplers: Vec::new(),
            images: Vec::new(),
            notes: Vec::new(),
            target_textures: Vec::new(),
            clip_textures: Vec::new(),
        };
        let a = rig.appearance.as_deref().unwrap_or(&EMPTY);
        let tables = AppearanceTables {
            materials: a.materials.clone(),
            textures: a.textures.clone(),
            samplers: a.samplers.clone(),
            images: a
                .images
                .iter()
                .map(|i| ImageMeta {
                    mime: i.mime,
                    width: i.width,
                    height: i.height,
                    downscaled_from: i.downscaled_from,
                })
                .collect(),
            notes: a.notes.clone(),
            target_textures: a.target_textures.clone(),
        };
        Ok(Some(AppearanceSectionRef {
            prims,
            tables_json: serde_json::to_string(&tables)
                .map_err(|e| StoreError::Encode(e.to_string()))?,
            images: a.images.iter().map(|i| &*i.bytes).collect(),
        }))
    }
}

impl AppearanceSection {
    /// Puts the data back into `rig` (indices and lengths are checked by the caller's
    /// [`Rig::validate`]). The images come back encoded: the server decodes them, charged,
    /// before the rig is served.
    fn apply(self, rig: &mut Rig) -> Result<(), String> {
        if self.prims.len() != rig.primitives.len() {
            return Err(format!(
                "appearance of {} primitives for {}",
                self.prims.len(),
                rig.primitives.len()
            ));
        }
        let t: AppearanceTables = serde_json::from_str(&self.tables_json)
            .map_err(|e| format!("appearance tables: {e}"))?;
        if t.images.len() != self.images.len() {
            return Err(format!(
                "appearance: {} images described, {} stored",
                t.images.len(),
                self.images.len()
            ));
        }
        let mut prims = rig.primitives.as_ref().clone();
        for (p, l) in prims.iter_mut().zip(self.prims) {
            p.look.uv1 = l.uv1;
            p.look.colors = l.colors;
            p.look.material = l.material;
        }
        rig.primitives = std::sync::Arc::new(prims);
        let images = t
            .images
            .into_iter()
            .zip(self.images)
            .map(|(m, bytes)| ImageData {
                mime: m.mime,
                bytes: bytes.into(),
                width: m.width,
                height: m.height,
                downscaled_from: m.downscaled_from,
                pixels: None,
            })
            .collect();
        let a = Appearance {
            materials: t.materials,
            textures: t.textures,
            samplers: t.samplers,
            images,
            notes: t.notes,
            target_textures: t.target_textures,
            clip_textures: Vec::new(),
        };
        rig.appearance = (a != Appearance::default()).then(|| std::sync::Arc::new(a));
        Ok(())
    }
}

/// Gives each of `clips` its joint table from `tables` (by clip name: a compressed clip that
/// does not decode is skipped alone, so not by position).
fn attach_joint_tables(clips: &mut [Clip], tables: Vec<(String, JointTable)>) {
    let mut tables: std::collections::HashMap<String, JointTable> = tables.into_iter().collect();
    for c in clips {
        c.joints = tables.remove(&c.name).map(std::sync::Arc::new);
    }
}

/// The joint tables of `clips` by clip name (section [`S_CLIP_JOINTS`], and kinds 9–11).
fn joint_tables(clips: &[Clip]) -> Vec<(&str, &JointTable)> {
    clips
        .iter()
        .filter_map(|c| c.joints.as_deref().map(|t| (c.name.as_str(), t)))
        .collect()
}

#[derive(Deserialize)]
struct StoredSkinnedOwned {
    id: String,
    rig: RigRecordV6,
    skin: SkinRecord,
}

/// Kind 10: kind 9 and the rig's own joint map.
#[derive(Deserialize)]
struct StoredSkinnedMapOwned {
    id: String,
    rig: RigRecordV6,
    skin: SkinRecord,
    map: JointMap,
}

/// One clip in a kind 6–8 record, and in section [`S_CLIPS`].
#[derive(Deserialize)]
enum ClipRecord {
    /// The table as it is.
    Plain(Clip),
    /// Curve-coded within the store's budget.
    Compressed(crowdmorph_anim::compress::Compressed),
    /// Transform-coded within the store's budget (codec 2, [`crowdmorph_anim::transform`]; a
    /// variant added last, so records written before it read as they did, and versioned
    /// inside, so a later layout is refused by name rather than misread).
    Transformed(crowdmorph_anim::transform::TransformCoded),
}

/// The written mirror of [`ClipRecord`].
#[derive(Serialize)]
enum ClipRecordRef<'a> {
    Plain(&'a Clip),
    Compressed(crowdmorph_anim::compress::Compressed),
    Transformed(crowdmorph_anim::transform::TransformCoded),
}

/// How a store writes clips: `None` plainly, `Some(E)` compressed within `E ×` diagonal where
/// a clip is already in that form.
fn clip_records<'a>(
    clips: &'a [Clip],
    rig: &Rig,
    max_error: Option<f32>,
) -> Result<Vec<ClipRecordRef<'a>>, StoreError> {
    clips
        .iter()
        .map(|clip| {
            let Some(e) = max_error else {
                return Ok(ClipRecordRef::Plain(clip));
            };
            // A transform-coded clip is written as the form it decodes from (kept when it
            // was put into stored form or read); any other as curves when it is that codec's
            // fixed point, else plainly.
            if let Some(t) = crowdmorph_anim::transform::recall(clip) {
                return Ok(ClipRecordRef::Transformed(t));
            }
            let (c, decoded) = crowdmorph_anim::compress::curves_stored_form(rig, clip, e)
                .map_err(|e| StoreError::Encode(e.to_string()))?;
            Ok(if decoded.weights == clip.weights {
                ClipRecordRef::Compressed(c)
            } else {
                ClipRecordRef::Plain(clip)
            })
        })
        .collect()
}

/// The clips of a kind 6–8 record or of section [`S_CLIPS`], decoded; a compressed one that does not decode is left out
/// and its reason added to `skipped`.
fn decode_clips(
    records: Vec<ClipRecord>,
    targets: Option<usize>,
    file: &Path,
    skipped: &mut Vec<String>,
) -> Vec<Clip> {
    records
        .into_iter()
        .filter_map(|r| match r {
            ClipRecord::Plain(c) => Some(c),
            ClipRecord::Compressed(c) => {
                let decoded = c.to_clip(targets.unwrap_or(c.targets as usize));
                kept(decoded, &c.name, file, skipped)
            }
            ClipRecord::Transformed(c) => {
                let decoded = c.to_clip(targets.unwrap_or(c.targets as usize));
                if let Ok(clip) = &decoded {
                    // So that writing the record again writes these bytes.
                    crowdmorph_anim::transform::remember(&c, clip);
                }
                kept(decoded, &c.name, file, skipped)
            }
        })
        .collect()
}

/// A decoded compressed clip, or `None` with the reason it does not decode added to `skipped`.
fn kept<E: std::fmt::Display>(
    decoded: Result<Clip, E>,
    name: &str,
    file: &Path,
    skipped: &mut Vec<String>,
) -> Option<Clip> {
    match decoded {
        Ok(clip) => Some(clip),
        Err(e) => {
            let why = format!("{}: compressed clip {name:?} skipped: {e}", file.display());
            tracing::error!(error = %why, "skipping a stored clip that does not decode");
            skipped.push(why);
            None
        }
    }
}

/// How a rig is stored. bincode is not self-describing, so a serde attribute that skips a
/// field when it is empty (as [`crowdmorph_core::rig::Lod`]'s newer fields do, for human-readable
/// formats) would make the bytes unreadable. The big arrays therefore go through bincode
/// field by field, and the LOD table, small and still growing, as JSON, which honours those
/// attributes and reads records written before a field existed.
#[derive(Deserialize)]
struct RigRecord {
    name: String,
    targets: Vec<String>,
    default_weights: Vec<f32>,
    primitives: Vec<crowdmorph_core::rig::Primitive>,
    clips: Vec<Clip>,
    lod_json: String,
}

/// Kind 6: kind 5 with [`ClipRecord`]s.
#[derive(Deserialize)]
struct RigRecordV6 {
    name: String,
    targets: Vec<String>,
    default_weights: Vec<f32>,
    primitives: Vec<crowdmorph_core::rig::Primitive>,
    clips: Vec<ClipRecord>,
    lod_json: String,
    base_colors: Vec<[f32; 4]>,
}

#[derive(Deserialize)]
struct StoredRigV6Owned {
    id: String,
    rig: RigRecordV6,
}

/// Kind 5: [`RigRecord`] and the primitives' base colours.
#[derive(Deserialize)]
struct RigRecordColors {
    name: String,
    targets: Vec<String>,
    default_weights: Vec<f32>,
    primitives: Vec<crowdmorph_core::rig::Primitive>,
    clips: Vec<Clip>,
    lod_json: String,
    base_colors: Vec<[f32; 4]>,
}

impl RigRecordColors {
    fn into_rig(self) -> Result<Rig, String> {
        if self.base_colors.len() != self.primitives.len() {
            return Err(format!(
                "{} base colours for {} primitives",
                self.base_colors.len(),
                self.primitives.len()
            ));
        }
        let mut primitives = self.primitives;
        for (p, c) in primitives.iter_mut().zip(self.base_colors) {
            p.base_color = c;
        }
        RigRecord {
            name: self.name,
            targets: self.targets,
            default_weights: self.default_weights,
            primitives,
            clips: self.clips,
            lod_json: self.lod_json,
        }
        .into_rig()
    }
}

#[derive(Deserialize)]
struct StoredRigColorsOwned {
    id: String,
    rig: RigRecordColors,
}

/// Section [`S_RIG`]: a rig without its clips ([`S_CLIPS`]) and skeleton ([`S_SKIN`]). The
/// LOD table goes as JSON for the reason given at [`RigRecord`].
#[derive(Serialize)]
struct RigSectionRef<'a> {
    name: &'a str,
    targets: &'a [String],
    default_weights: &'a [f32],
    primitives: &'a [crowdmorph_core::rig::Primitive],
    lod_json: String,
    /// Per primitive: serde skips it inside [`crowdmorph_core::rig::Primitive`].
    base_colors: Vec<[f32; 4]>,
}

/// Owned mirror of [`RigSectionRef`].
#[derive(Deserialize)]
struct RigSection {
    name: String,
    targets: Vec<String>,
    default_weights: Vec<f32>,
    primitives: Vec<crowdmorph_core::rig::Primitive>,
    lod_json: String,
    base_colors: Vec<[f32; 4]>,
}

impl<'a> RigSectionRef<'a> {
    fn new(rig: &'a Rig) -> Result<Self, StoreError> {
        // Exhaustive on purpose: a new Rig field must be added to the stored record (as a
        // field here or, better, a section of its own).
        let Rig {
            name,
            targets,
            default_weights,
            primitives,
            // Section `S_CLIPS` (and clip files).
            clips: _,
            lod,
            // Sections `S_SKIN` and `S_JOINT_MAP`.
            skeleton: _,
            // In `S_SKIN`.
            import_notes: _,
            // Section `S_APPEARANCE`.
            appearance: _,
        } = rig;
        Ok(RigSectionRef {
            name,
            targets,
            default_weights,
            primitives: primitives.as_slice(),
            lod_json: lod_to_json(lod)?,
            base_colors: primitives.iter().map(|p| p.base_color).collect(),
        })
    }
}

/// Section [`S_LOD`]: a built-in rig's LOD (JSON, see [`RigRecord`]) and the
/// [`geometry_fingerprint`] of the rig it was built for.
#[derive(Serialize, Deserialize)]
struct LodSection {
    lod_json: String,
    geometry: u32,
}

/// Writes section [`S_CLIPS`] of `clips` (as a store with `max_error` does), and
/// [`S_CLIP_JOINTS`] when one of them has a joint table.
fn write_clip_sections(
    w: &mut impl Write,
    clips: &[Clip],
    rig: &Rig,
    max_error: Option<f32>,
) -> Result<(), StoreError> {
    sections::write(w, S_CLIPS.tag, &clip_records(clips, rig, max_error)?)
        .map_err(StoreError::Encode)?;
    let tables = joint_tables(clips);
    if !tables.is_empty() {
        sections::write(w, S_CLIP_JOINTS.tag, &tables).map_err(StoreError::Encode)?;
    }
    Ok(())
}

/// Writes the sections of `record` (kinds 12–14) and says which kind it is.
fn write_sections(
    w: &mut impl Write,
    record: RecordRef<'_>,
    max_error: Option<f32>,
) -> Result<u32, StoreError> {
    let enc = StoreError::Encode;
    Ok(match record {
        RecordRef::Rig { id, rig, clips } => {
            sections::write(w, S_ID.tag, &id).map_err(enc)?;
            sections::write(w, S_RIG.tag, &RigSectionRef::new(rig)?).map_err(enc)?;
            write_clip_sections(w, clips, rig, max_error)?;
            if let Some(look) = LookSectionRef::of(rig) {
                sections::write(w, S_LOOK.tag, &look).map_err(enc)?;
            }
            if let Some(a) = AppearanceSectionRef::of(rig)? {
                sections::write(w, S_APPEARANCE.tag, &a).map_err(enc)?;
            }
            let textures: Vec<(&str, Vec<u8>)> = rig
                .appearance
                .iter()
                .flat_map(|a| a.clip_textures.iter())
                .map(|t| (t.clip.as_str(), t.to_bytes()))
                .collect();
            if !textures.is_empty() {
                sections::write(w, S_CLIP_TEXTURES.tag, &textures).map_err(enc)?;
            }
            if let Some(skeleton) = rig.skeleton.as_deref() {
                let skin = SkinSectionRef {
                    skeleton,
                    influences: rig.primitives.iter().map(|p| p.skin.as_ref()).collect(),
                    notes: &rig.import_notes,
                };
                sections::write(w, S_SKIN.tag, &skin).map_err(enc)?;
                if let Some(map) = &skeleton.map {
                    sections::write(w, S_JOINT_MAP.tag, map).map_err(enc)?;
                }
            }
            KIND_RIG_SECTIONS
        }
        RecordRef::Builtin { id, clips, rig } => {
            sections::write(w, S_ID.tag, &id).map_err(enc)?;
            write_clip_sections(w, clips, rig, max_error)?;
            let lod = LodSection {
                lod_json: lod_to_json(&rig.lod)?,
                geometry: geometry_fingerprint(rig),
            };
            sections::write(w, S_LOD.tag, &lod).map_err(enc)?;
            KIND_BUILTIN_SECTIONS
        }
        RecordRef::Clips {
            id,
            seq,
            clips,
            rig,
        } => {
            sections::write(w, S_ID.tag, &id).map_err(enc)?;
            sections::write(w, S_SEQ.tag, &seq).map_err(enc)?;
            write_clip_sections(w, clips, rig, max_error)?;
            KIND_CLIPS_SECTIONS
        }
    })
}

/// Reads a kind 12 payload: a rig (its id and invariants are checked by the caller).
fn read_rig_sections(
    payload: &[u8],
    file: &Path,
    skipped: &mut Vec<String>,
) -> Result<StoredRig, String> {
    let mut s = Sections::parse(payload, "rig record", RIG_SECTIONS)?;
    let id: String = s.require(S_ID)?;
    let r: RigSection = s.require(S_RIG)?;
    let clips: Vec<ClipRecord> = s.require(S_CLIPS)?;
    let tables: Option<Vec<(String, JointTable)>> = s.take(S_CLIP_JOINTS)?;
    let skin: Option<SkinSection> = s.take(S_SKIN)?;
    let map: Option<JointMap> = s.take(S_JOINT_MAP)?;
    let look: Option<LookSection> = s.take(S_LOOK)?;
    let appearance: Option<AppearanceSection> = s.take(S_APPEARANCE)?;
    // Borrowed from the payload: a texture's arrays are its floats verbatim, and its header's
    // declared size is checked against the bytes it has before anything is allocated
    // (`AnimatedTexture::from_bytes`), so decoding it holds its floats once beside the record
    // — within the twice-the-file the loader charged before reading it.
    let textures: Option<Vec<(&str, &[u8])>> = s.take_borrowed(S_CLIP_TEXTURES)?;
    let clips = decode_clips(clips, Some(r.targets.len()), file, skipped);
    let mut rig = RigRecordColors {
        name: r.name,
        targets: r.targets,
        default_weights: r.default_weights,
        primitives: r.primitives,
        clips,
        lod_json: r.lod_json,
        base_colors: r.base_colors,
    }
    .into_rig()?;
    attach_joint_tables(&mut rig.clips, tables.unwrap_or_default());
    if let Some(look) = look {
        look.apply(&mut rig)?;
    }
    if let Some(a) = appearance {
        a.apply(&mut rig)?;
    }
    if let Some(textures) = textures.filter(|t| !t.is_empty()) {
        let mut a = rig.appearance.as_deref().cloned().unwrap_or_default();
        for (clip, bytes) in textures {
            let t = crowdmorph_core::rig::AnimatedTexture::from_bytes(clip, bytes)
                .map_err(|e| format!("clip {clip:?}: {e}"))?;
            a.clip_textures.push(std::sync::Arc::new(t));
        }
        rig.appearance = Some(std::sync::Arc::new(a));
    }
    match skin {
        Some(skin) => skin.apply(&mut rig, map)?,
        None if map.is_some() => {
            return Err("rig record: a joint map section without a skin section".into());
        }
        None => {}
    }
    Ok(StoredRig { id, rig })
}

/// Reads a kind 13 payload: a built-in rig's clips and LOD.
fn read_builtin_sections(
    payload: &[u8],
    file: &Path,
    skipped: &mut Vec<String>,
) -> Result<StoredBuiltin, String> {
    let mut s = Sections::parse(payload, "built-in rig record", BUILTIN_SECTIONS)?;
    let id: String = s.require(S_ID)?;
    let clips: Vec<ClipRecord> = s.require(S_CLIPS)?;
    let tables: Option<Vec<(String, JointTable)>> = s.take(S_CLIP_JOINTS)?;
    let lod: Option<LodSection> = s.take(S_LOD)?;
    let mut clips = decode_clips(clips, None, file, skipped);
    attach_joint_tables(&mut clips, tables.unwrap_or_default());
    let lod = match lod {
        Some(l) => Some((lod_from_json(&l.lod_json)?, l.geometry)),
        None => None,
    };
    Ok(StoredBuiltin { id, clips, lod })
}

/// Reads a kind 14 payload: clips added to a rig.
fn read_clips_sections(
    payload: &[u8],
    file: &Path,
    skipped: &mut Vec<String>,
) -> Result<StoredClipsOwned, String> {
    let mut s = Sections::parse(payload, "clip file", CLIPS_SECTIONS)?;
    let id: String = s.require(S_ID)?;
    let seq: u64 = s.require(S_SEQ)?;
    let clips: Vec<ClipRecord> = s.require(S_CLIPS)?;
    let tables: Option<Vec<(String, JointTable)>> = s.take(S_CLIP_JOINTS)?;
    let mut clips = decode_clips(clips, None, file, skipped);
    attach_joint_tables(&mut clips, tables.unwrap_or_default());
    Ok(StoredClipsOwned { id, seq, clips })
}

/// The LOD table as stored (JSON, see [`RigRecord`]).
fn lod_to_json(lod: &Lod) -> Result<String, StoreError> {
    serde_json::to_string(lod).map_err(|e| StoreError::Encode(e.to_string()))
}

fn lod_from_json(json: &str) -> Result<Lod, String> {
    serde_json::from_str(json).map_err(|e| format!("LOD table: {e}"))
}

impl RigRecord {
    fn into_rig(self) -> Result<Rig, String> {
        Ok(Rig {
            name: self.name,
            targets: self.targets,
            default_weights: self.default_weights,
            primitives: std::sync::Arc::new(self.primitives),
            clips: self.clips,
            lod: lod_from_json(&self.lod_json)?,
            skeleton: None,
            import_notes: Vec::new(),
            appearance: None,
        })
    }
}

#[derive(Deserialize)]
struct StoredRigOwned {
    id: String,
    rig: RigRecord,
}

/// Kind 2, as older builds wrote it.
#[derive(Deserialize)]
struct StoredClipsV2 {
    id: String,
    clips: Vec<Clip>,
}

/// Kind 7 (kind 3 with [`ClipRecord`]s). The LOD goes as JSON for the reason given at
/// [`RigRecord`].
#[derive(Deserialize)]
struct StoredBuiltinV7Owned {
    id: String,
    clips: Vec<ClipRecord>,
    lod_json: String,
    geometry: u32,
}

/// Kind 3.
#[derive(Deserialize)]
struct StoredBuiltinOwned {
    id: String,
    clips: Vec<Clip>,
    lod_json: String,
    geometry: u32,
}

/// Kind 8: clips added to a rig.
#[derive(Deserialize)]
struct StoredClipsV8Owned {
    id: String,
    seq: u64,
    clips: Vec<ClipRecord>,
}

/// Kind 11: kind 8 and its clips' joint tables by clip name.
#[derive(Deserialize)]
struct StoredClipsJointsOwned {
    id: String,
    seq: u64,
    clips: Vec<ClipRecord>,
    clip_joints: Vec<(String, JointTable)>,
}

/// Clips added to a rig after its record was written, as loaded.
#[derive(Clone, Debug, PartialEq)]
pub struct StoredClips {
    /// Registry id of the rig.
    pub id: String,
    /// Sequence number of the file.
    pub seq: u64,
    /// The clips, in the order they were added.
    pub clips: Vec<Clip>,
}

#[derive(Deserialize)]
struct StoredClipsOwned {
    id: String,
    seq: u64,
    clips: Vec<Clip>,
}

/// What a store file holds.
#[derive(Clone, Debug, PartialEq)]
pub enum Record {
    /// Clips added to a rig (a clip file).
    Clips(StoredClips),
    /// A whole uploaded rig (boxed: it is much bigger than the other variant).
    Rig(Box<StoredRig>),
    /// Extra clips and LOD of a built-in rig.
    Builtin(StoredBuiltin),
}

/// A rig's motion graphs, named masks and mappings as stored (`data_dir/graphs/<rig>.json`,
/// the `graphs.json` object of a shared store): what a rig has by name beside its record.
/// Masks and mappings came later: a file without them reads as none.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StoredGraphs {
    /// The rig id.
    pub rig: String,
    /// Its graphs by name.
    pub graphs: std::collections::BTreeMap<String, crowdmorph_proto::MotionGraph>,
    /// Its masks by name (`PUT /v1/rigs/{id}/masks/{name}`).
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub masks: std::collections::BTreeMap<String, crowdmorph_proto::Mask>,
    /// Its mappings by name (`PUT /v1/rigs/{id}/mappings/{name}`, and `vrm`).
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub mappings: std::collections::BTreeMap<String, crowdmorph_proto::Mapping>,
}

impl StoredGraphs {
    /// Whether there is nothing to store (the file or object is removed).
    pub fn is_empty(&self) -> bool {
        self.graphs.is_empty() && self.masks.is_empty() && self.mappings.is_empty()
    }
}

/// Why the store failed.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// The file system refused an operation.
    #[error("{op} {path}: {source}")]
    Io {
        /// What was being done.
        op: &'static str,
        /// On which path.
        path: String,
        /// Why it failed.
        source: std::io::Error,
    },
    /// A record could not be encoded.
    #[error("cannot encode record: {0}")]
    Encode(String),
    /// A file is not a valid record.
    #[error("{path}: {problem}")]
    Corrupt {
        /// The file.
        path: String,
        /// What is wrong with it.
        problem: String,
    },
}

fn io<'a>(op: &'static str, path: &'a Path) -> impl FnOnce(std::io::Error) -> StoreError + 'a {
    move |source| StoreError::Io {
        op,
        path: path.display().to_string(),
        source,
    }
}

/// Writes the payload of a record to a file while computing its length and CRC-32.
struct Checksummed {
    inner: std::io::BufWriter<File>,
    crc: crc32fast::Hasher,
    len: u64,
}

impl Write for Checksummed {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.crc.update(&buf[..n]);
        self.len += n as u64;
        Ok(n)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush()
    }
}

/// The rigs directory of a data dir.
#[derive(Debug)]
pub struct Store {
    dir: PathBuf,
    tmp_counter: AtomicU64,
    /// `Some(E)`: clips are written compressed within `E ×` diagonal (module doc).
    clip_error: Option<f32>,
}

/// Result of loading every record at start.
#[derive(Debug, Default)]
pub struct Loaded {
    /// Records that loaded and validated.
    pub records: Vec<Record>,
    /// Files that did not, with the reason (already logged).
    pub skipped: Vec<String>,
}

impl Store {
    /// Opens (creating when needed) `data_dir/rigs`.
    pub fn open(data_dir: &Path) -> Result<Store, StoreError> {
        let dir = data_dir.join("rigs");
        fs::create_dir_all(&dir).map_err(io("create directory", &dir))?;
        Ok(Store {
            dir,
            tmp_counter: AtomicU64::new(0),
            clip_error: None,
        })
    }

    /// This store, writing clips compressed within `max_error ×` their rig's diagonal (the
    /// module doc says which and how they are read back).
    pub fn compress_clips(mut self, max_error: Option<f32>) -> Store {
        self.clip_error = max_error;
        self
    }

    /// The budget clips are compressed within, when they are.
    pub fn clip_error(&self) -> Option<f32> {
        self.clip_error
    }

    /// Directory holding the record files.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Path of the record for rig `id` (ids are restricted to `[A-Za-z0-9._-]`).
    pub fn path_of(&self, id: &str) -> PathBuf {
        self.dir.join(format!("{id}.{EXT}"))
    }

    /// Writes a record atomically (temp file, fsync, rename, fsync of the directory). The
    /// payload is encoded straight into the file through a checksumming writer, and the
    /// header (length, CRC) written last over a placeholder: a record as large as its rig is
    /// never held in memory a second time.
    pub fn put(&self, record: RecordRef<'_>) -> Result<(), StoreError> {
        let n = self.tmp_counter.fetch_add(1, Ordering::Relaxed);
        let path = match record {
            RecordRef::Rig { id, .. } | RecordRef::Builtin { id, .. } => self.path_of(id),
            RecordRef::Clips { id, seq, .. } => self.clips_path(id, seq),
        };
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let tmp = self
            .dir
            .join(format!("{TMP}{}-{n}-{name}", std::process::id()));
        let result = (|| {
            let file = File::create(&tmp).map_err(io("create", &tmp))?;
            let mut w = Checksummed {
                inner: std::io::BufWriter::with_capacity(1 << 20, file),
                crc: crc32fast::Hasher::new(),
                len: 0,
            };
            w.inner
                .write_all(&[0u8; HEADER])
                .map_err(io("write", &tmp))?;
            let kind = write_sections(&mut w, record, self.clip_error)?;
            let mut header = Vec::with_capacity(HEADER);
            header.extend_from_slice(MAGIC);
            header.extend_from_slice(&kind.to_le_bytes());
            header.extend_from_slice(&w.len.to_le_bytes());
            header.extend_from_slice(&w.crc.clone().finalize().to_le_bytes());
            let mut f = w
                .inner
                .into_inner()
                .map_err(|e| io("write", &tmp)(e.into_error()))?;
            f.seek(std::io::SeekFrom::Start(0))
                .map_err(io("seek", &tmp))?;
            f.write_all(&header).map_err(io("write", &tmp))?;
            f.sync_all().map_err(io("fsync", &tmp))?;
            drop(f);
            fs::rename(&tmp, &path).map_err(io("rename", &path))?;
            self.sync_dir()
        })();
        if result.is_err() {
            let _ = fs::remove_file(&tmp);
        }
        result
    }

    /// Directory of the rigs' motion graphs, next to the records' (`data_dir/graphs`).
    fn graphs_dir(&self) -> PathBuf {
        self.dir
            .parent()
            .map_or_else(|| self.dir.join("graphs"), |d| d.join("graphs"))
    }

    /// Writes rig `stored.rig`'s motion graphs, masks and mappings (all of them, replacing the
    /// file atomically), or removes the file when there are none. JSON: a graph is small, and
    /// a truncated or corrupt file fails to parse, so it is reported at start and skipped,
    /// never served.
    pub fn put_graphs(&self, stored: &StoredGraphs) -> Result<(), StoreError> {
        let id = stored.rig.as_str();
        let dir = self.graphs_dir();
        let path = dir.join(format!("{id}.json"));
        if stored.is_empty() {
            return self.remove_file(&path);
        }
        fs::create_dir_all(&dir).map_err(io("create directory", &dir))?;
        let bytes = serde_json::to_vec(stored).map_err(|e| StoreError::Encode(e.to_string()))?;
        let n = self.tmp_counter.fetch_add(1, Ordering::Relaxed);
        let tmp = dir.join(format!("{TMP}{}-{n}-{id}.json", std::process::id()));
        let result = (|| {
            let mut f = File::create(&tmp).map_err(io("create", &tmp))?;
            f.write_all(&bytes).map_err(io("write", &tmp))?;
            f.sync_all().map_err(io("fsync", &tmp))?;
            drop(f);
            fs::rename(&tmp, &path).map_err(io("rename", &path))?;
            File::open(&dir)
                .and_then(|d| d.sync_all())
                .map_err(io("fsync directory", &dir))
        })();
        if result.is_err() {
            let _ = fs::remove_file(&tmp);
        }
        result
    }

    /// Every rig's stored motion graphs, and the files that could not be read (with why).
    /// `charge` is asked for each file's memory (its size, the parsed graphs about as much
    /// again) before it is read; a file it refuses is skipped with its reason.
    pub fn load_graphs(
        &self,
        charge: impl Fn(u64, &Path) -> Result<(), String>,
    ) -> (Vec<StoredGraphs>, Vec<String>) {
        let dir = self.graphs_dir();
        let Ok(entries) = fs::read_dir(&dir) else {
            return (Vec::new(), Vec::new());
        };
        let mut ok = Vec::new();
        let mut skipped = Vec::new();
        for e in entries.filter_map(Result::ok) {
            let path = e.path();
            let name = e.file_name().to_string_lossy().into_owned();
            if name.starts_with(TMP) || !name.ends_with(".json") {
                continue;
            }
            // A graph file is a few kilobytes; a huge one is not ours.
            let parsed = match e.metadata() {
                Ok(m) if m.len() <= 64 << 20 => charge(2 * m.len(), &path)
                    .and_then(|()| fs::read(&path).map_err(|err| err.to_string()))
                    .and_then(|b| {
                        serde_json::from_slice::<StoredGraphs>(&b).map_err(|err| err.to_string())
                    }),
                Ok(m) => Err(format!("{} bytes is too large for a graph file", m.len())),
                Err(err) => Err(err.to_string()),
            };
            match parsed {
                Ok(g) => ok.push(g),
                Err(why) => skipped.push(format!("{}: {why}", path.display())),
            }
        }
        (ok, skipped)
    }

    /// Path of clip file `seq` of rig `id` (`@` cannot appear in an id).
    pub fn clips_path(&self, id: &str, seq: u64) -> PathBuf {
        self.dir.join(format!("{id}@{seq:010}.{CLIPS_EXT}"))
    }

    /// Deletes the record of rig `id` and then its clip files (no error when there are
    /// none). The record goes first: clip files whose rig has no record are leftovers that
    /// [`Store::record_files`] callers delete.
    pub fn remove(&self, id: &str) -> Result<(), StoreError> {
        self.remove_file(&self.path_of(id))?;
        self.remove_file(&self.graphs_dir().join(format!("{id}.json")))?;
        for path in self.clip_files_of(id)? {
            self.remove_file(&path)?;
        }
        Ok(())
    }

    /// Deletes clip file `seq` of rig `id`.
    pub fn remove_clips(&self, id: &str, seq: u64) -> Result<(), StoreError> {
        self.remove_file(&self.clips_path(id, seq))
    }

    /// Deletes a file (no error when there is none) and makes the deletion durable.
    pub fn remove_file(&self, path: &Path) -> Result<(), StoreError> {
        match fs::remove_file(path) {
            Ok(()) => self.sync_dir(),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
            Err(e) => Err(io("remove", path)(e)),
        }
    }

    /// The clip files of rig `id`.
    fn clip_files_of(&self, id: &str) -> Result<Vec<PathBuf>, StoreError> {
        let prefix = format!("{id}@");
        let suffix = format!(".{CLIPS_EXT}");
        Ok(fs::read_dir(&self.dir)
            .map_err(io("list", &self.dir))?
            .filter_map(|e| e.ok())
            .filter(|e| {
                let n = e.file_name().to_string_lossy().into_owned();
                n.starts_with(&prefix) && n.ends_with(&suffix)
            })
            .map(|e| e.path())
            .collect())
    }

    fn sync_dir(&self) -> Result<(), StoreError> {
        // Flushing a directory makes renames and deletions in it durable (POSIX).
        File::open(&self.dir)
            .and_then(|d| d.sync_all())
            .map_err(io("fsync directory", &self.dir))
    }

    /// Reads one record file, checking magic, length, checksum, payload and rig invariants
    /// (compressed clips that do not decode are left out: [`Store::read_reporting`] says which).
    pub fn read(path: &Path) -> Result<Record, StoreError> {
        Store::read_reporting(path).map(|(r, _)| r)
    }

    /// [`Store::read`], with a reason for each compressed clip it left out.
    pub fn read_reporting(path: &Path) -> Result<(Record, Vec<String>), StoreError> {
        let mut skipped = Vec::new();
        let record = Store::read_into(path, &mut skipped)?;
        Ok((record, skipped))
    }

    fn read_into(path: &Path, skipped: &mut Vec<String>) -> Result<Record, StoreError> {
        let bytes = fs::read(path).map_err(io("read", path))?;
        Store::decode_file(path, &bytes, skipped)
    }

    /// The record in `bytes`, the contents of file `path` (whose name it must match).
    fn decode_file(
        path: &Path,
        bytes: &[u8],
        skipped: &mut Vec<String>,
    ) -> Result<Record, StoreError> {
        let corrupt = |problem: String| StoreError::Corrupt {
            path: path.display().to_string(),
            problem,
        };
        if bytes.len() < HEADER || &bytes[..8] != MAGIC {
            return Err(corrupt("not a crowdmorph store file (bad magic)".into()));
        }
        let u32_at = |at: usize| {
            u32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]])
        };
        let kind = u32_at(8);
        let mut len = [0u8; 8];
        len.copy_from_slice(&bytes[12..20]);
        let len = u64::from_le_bytes(len);
        let crc = u32_at(20);
        let payload = &bytes[HEADER..];
        if payload.len() as u64 != len {
            return Err(corrupt(format!(
                "truncated or padded: header says {len} payload bytes, file has {}",
                payload.len()
            )));
        }
        if crc32fast::hash(payload) != crc {
            return Err(corrupt("checksum mismatch".into()));
        }
        let stem = path
            .file_name()
            .and_then(|n| n.to_str())
            .and_then(|n| n.strip_suffix(&format!(".{EXT}")))
            .unwrap_or_default()
            .to_string();
        match kind {
            KIND_CLIPS | KIND_CLIPS_V8 | KIND_CLIPS_JOINTS_V11 | KIND_CLIPS_SECTIONS => {
                let c: StoredClipsOwned = if kind == KIND_CLIPS_SECTIONS {
                    read_clips_sections(payload, path, skipped).map_err(corrupt)?
                } else if kind == KIND_CLIPS {
                    codec::from_stored(payload).map_err(|e| corrupt(e.to_string()))?
                } else if kind == KIND_CLIPS_JOINTS_V11 {
                    let c: StoredClipsJointsOwned =
                        codec::from_stored(payload).map_err(|e| corrupt(e.to_string()))?;
                    let mut tables: std::collections::HashMap<String, JointTable> =
                        c.clip_joints.into_iter().collect();
                    let mut clips = decode_clips(c.clips, None, path, skipped);
                    for clip in &mut clips {
                        clip.joints = tables.remove(&clip.name).map(std::sync::Arc::new);
                    }
                    StoredClipsOwned {
                        id: c.id,
                        seq: c.seq,
                        clips,
                    }
                } else {
                    let c: StoredClipsV8Owned =
                        codec::from_stored(payload).map_err(|e| corrupt(e.to_string()))?;
                    StoredClipsOwned {
                        id: c.id,
                        seq: c.seq,
                        clips: decode_clips(c.clips, None, path, skipped),
                    }
                };
                let want = path
                    .file_name()
                    .and_then(|n| n.to_str())
                    .and_then(|n| n.strip_suffix(&format!(".{CLIPS_EXT}")))
                    .unwrap_or_default();
                if want != format!("{}@{:010}", c.id, c.seq) {
                    return Err(corrupt(format!(
                        "clip file is for rig {:?} number {}, its name says {want:?}",
                        c.id, c.seq
                    )));
                }
                Ok(Record::Clips(StoredClips {
                    id: c.id,
                    seq: c.seq,
                    clips: c.clips,
                }))
            }
            KIND_RIG
            | KIND_RIG_COLORS
            | KIND_RIG_V6
            | KIND_RIG_SKINNED_V9
            | KIND_RIG_SKINNED_MAP_V10
            | KIND_RIG_SECTIONS => {
                let r = if kind == KIND_RIG_SECTIONS {
                    read_rig_sections(payload, path, skipped).map_err(corrupt)?
                } else if kind == KIND_RIG_SKINNED_V9 || kind == KIND_RIG_SKINNED_MAP_V10 {
                    let (id, r, skin, map) = if kind == KIND_RIG_SKINNED_MAP_V10 {
                        let StoredSkinnedMapOwned { id, rig, skin, map } =
                            codec::from_stored(payload).map_err(|e| corrupt(e.to_string()))?;
                        (id, rig, skin, Some(map))
                    } else {
                        let StoredSkinnedOwned { id, rig, skin } =
                            codec::from_stored(payload).map_err(|e| corrupt(e.to_string()))?;
                        (id, rig, skin, None)
                    };
                    let clips = decode_clips(r.clips, Some(r.targets.len()), path, skipped);
                    let mut rig = RigRecordColors {
                        name: r.name,
                        targets: r.targets,
                        default_weights: r.default_weights,
                        primitives: r.primitives,
                        clips,
                        lod_json: r.lod_json,
                        base_colors: r.base_colors,
                    }
                    .into_rig()
                    .map_err(corrupt)?;
                    skin.apply(&mut rig, map).map_err(corrupt)?;
                    StoredRig { id, rig }
                } else if kind == KIND_RIG {
                    let r: StoredRigOwned =
                        codec::from_stored(payload).map_err(|e| corrupt(e.to_string()))?;
                    StoredRig {
                        id: r.id,
                        rig: r.rig.into_rig().map_err(corrupt)?,
                    }
                } else if kind == KIND_RIG_V6 {
                    let StoredRigV6Owned { id, rig: r } =
                        codec::from_stored(payload).map_err(|e| corrupt(e.to_string()))?;
                    let clips = decode_clips(r.clips, Some(r.targets.len()), path, skipped);
                    let rig = RigRecordColors {
                        name: r.name,
                        targets: r.targets,
                        default_weights: r.default_weights,
                        primitives: r.primitives,
                        clips,
                        lod_json: r.lod_json,
                        base_colors: r.base_colors,
                    };
                    StoredRig {
                        id,
                        rig: rig.into_rig().map_err(corrupt)?,
                    }
                } else {
                    let r: StoredRigColorsOwned =
                        codec::from_stored(payload).map_err(|e| corrupt(e.to_string()))?;
                    StoredRig {
                        id: r.id,
                        rig: r.rig.into_rig().map_err(corrupt)?,
                    }
                };
                if r.id != stem {
                    return Err(corrupt(format!(
                        "record is for rig {:?}, file name says {stem:?}",
                        r.id
                    )));
                }
                r.rig
                    .validate()
                    .map_err(|e| corrupt(format!("invalid rig: {e}")))?;
                Ok(Record::Rig(Box::new(r)))
            }
            KIND_BUILTIN_CLIPS | KIND_BUILTIN | KIND_BUILTIN_V7 | KIND_BUILTIN_SECTIONS => {
                let c = if kind == KIND_BUILTIN_SECTIONS {
                    read_builtin_sections(payload, path, skipped).map_err(corrupt)?
                } else if kind == KIND_BUILTIN_V7 {
                    let c: StoredBuiltinV7Owned =
                        codec::from_stored(payload).map_err(|e| corrupt(e.to_string()))?;
                    StoredBuiltin {
                        id: c.id,
                        clips: decode_clips(c.clips, None, path, skipped),
                        lod: Some((lod_from_json(&c.lod_json).map_err(corrupt)?, c.geometry)),
                    }
                } else if kind == KIND_BUILTIN_CLIPS {
                    let c: StoredClipsV2 =
                        codec::from_stored(payload).map_err(|e| corrupt(e.to_string()))?;
                    StoredBuiltin {
                        id: c.id,
                        clips: c.clips,
                        lod: None,
                    }
                } else {
                    let c: StoredBuiltinOwned =
                        codec::from_stored(payload).map_err(|e| corrupt(e.to_string()))?;
                    StoredBuiltin {
                        id: c.id,
                        clips: c.clips,
                        lod: Some((lod_from_json(&c.lod_json).map_err(corrupt)?, c.geometry)),
                    }
                };
                if c.id != stem {
                    return Err(corrupt(format!(
                        "record is for rig {:?}, file name says {stem:?}",
                        c.id
                    )));
                }
                Ok(Record::Builtin(c))
            }
            other => Err(corrupt(format!("unknown record kind {other}"))),
        }
    }

    /// The record files with their sizes, in name order, after deleting stray temporary
    /// files (uploads interrupted before their rename). Callers read them one at a time with
    /// [`Store::read`], so loading never holds more than one record's bytes.
    pub fn record_files(&self) -> Result<Vec<(PathBuf, u64)>, StoreError> {
        let mut paths: Vec<PathBuf> = fs::read_dir(&self.dir)
            .map_err(io("list", &self.dir))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .collect();
        paths.sort();
        let mut files = Vec::new();
        for path in paths {
            let name = path
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            if name.starts_with(TMP) {
                tracing::warn!(file = %path.display(), "removing an interrupted write");
                let _ = fs::remove_file(&path);
                continue;
            }
            if !name.ends_with(&format!(".{EXT}")) && !name.ends_with(&format!(".{CLIPS_EXT}")) {
                continue;
            }
            let size = fs::metadata(&path).map(|m| m.len()).unwrap_or(0);
            files.push((path, size));
        }
        // Rig records before clip files (a rig's clip files attach to its record), clip files
        // by rig and sequence number (their names sort so).
        files.sort_by_key(|(p, _)| {
            let clips = p.extension().is_some_and(|e| e == CLIPS_EXT);
            (clips, p.clone())
        });
        Ok(files)
    }

    /// Loads every record, deleting stray temporary files and skipping, with a logged reason,
    /// every file that is not a valid record.
    pub fn load_all(&self) -> Result<Loaded, StoreError> {
        let mut loaded = Loaded::default();
        for (path, _) in self.record_files()? {
            match Store::read_into(&path, &mut loaded.skipped) {
                Ok(r) => loaded.records.push(r),
                Err(e) => {
                    tracing::error!(error = %e, "skipping a stored rig that cannot be loaded");
                    loaded.skipped.push(e.to_string());
                }
            }
        }
        Ok(loaded)
    }
}

#[cfg(test)]
mod format_tests;

#[cfg(test)]
mod tests {
    use super::*;

    fn tmpdir(tag: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!(
            "crowdmorph-store-{tag}-{}-{}",
            std::process::id(),
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map(|d| d.as_nanos())
                .unwrap_or(0)
        ));
        let _ = fs::remove_dir_all(&d);
        d
    }

    #[test]
    fn transform_coded_clips_read_back_exactly_and_are_written_again_as_they_were() {
        let dir = tmpdir("tc");
        let store = Store::open(&dir).expect("open").compress_clips(Some(3e-4));
        let mut rig = crowdmorph_core::embedded::default_rig();
        // Tracker-like noise on every channel, so that the clip is not the curve codec's
        // fixed point and only its transform-coded form can be written compressed.
        let mut rng = crowdmorph_core::rng::SplitMix64(48);
        let clip = &mut rig.clips[0];
        for w in std::sync::Arc::make_mut(&mut clip.weights).iter_mut() {
            *w = (*w + 0.02 * (rng.unit() - 0.5)).clamp(0.0, 1.0);
        }
        let metric = crowdmorph_anim::transform::Metric::of(&rig);
        let coded = crowdmorph_anim::transform::compress(&rig, &metric, &rig.clips[0], 3e-4)
            .expect("compresses")
            .expect("within budget");
        let decoded = coded.to_clip(rig.targets.len()).expect("decodes");
        crowdmorph_anim::transform::remember(&coded, &decoded);
        rig.clips[0] = decoded;
        store
            .put(RecordRef::Rig {
                id: "t",
                rig: &rig,
                clips: &rig.clips,
            })
            .expect("put");
        let first = fs::read(store.path_of("t")).expect("file");
        let bytes = codec::to_stored(&coded).expect("encodes");
        assert!(
            first.windows(bytes.len()).any(|w| w == &bytes[..]),
            "the record holds the transform-coded clip"
        );
        let (record, dropped) = Store::read_reporting(&store.path_of("t")).expect("read");
        assert!(dropped.is_empty(), "{dropped:?}");
        let Record::Rig(r) = record else {
            panic!("not a rig record")
        };
        assert_eq!(r.rig, rig, "bit for bit");
        // Written again from what was read (a restart, then a change to the rig): the same bytes.
        let again = Store::open(&dir.join("again"))
            .expect("open")
            .compress_clips(Some(3e-4));
        again
            .put(RecordRef::Rig {
                id: "t",
                rig: &r.rig,
                clips: &r.rig.clips,
            })
            .expect("put");
        assert_eq!(fs::read(again.path_of("t")).expect("file"), first);
    }

    #[test]
    fn compressed_clips_read_back_exactly_and_a_damaged_one_is_skipped_alone() {
        let dir = tmpdir("cc");
        let plain = Store::open(&dir.join("plain")).expect("open");
        let store = Store::open(&dir).expect("open").compress_clips(Some(3e-4));
        let mut rig = crowdmorph_core::embedded::default_rig();
        // Every clip but the last arrives in stored form; the last was stored exactly before
        // compression was switched on, and must stay exact.
        let n = rig.clips.len();
        assert!(n >= 3);
        let stored: Vec<Clip> = rig.clips[..n - 1]
            .iter()
            .map(|c| {
                crowdmorph_anim::compress::curves_stored_form(&rig, c, 3e-4)
                    .expect("form")
                    .1
            })
            .collect();
        rig.clips.splice(..n - 1, stored);
        for s in [&plain, &store] {
            s.put(RecordRef::Rig {
                id: "e",
                rig: &rig,
                clips: &rig.clips,
            })
            .expect("put");
        }
        let (small, big) = (
            fs::metadata(store.path_of("e")).expect("file").len(),
            fs::metadata(plain.path_of("e")).expect("file").len(),
        );
        let table_bytes: u64 = rig.clips[..n - 1]
            .iter()
            .map(|c| c.weights.len() as u64 * 4)
            .sum();
        assert!(
            big - small > table_bytes / 2,
            "compressed record {small} B, plain {big} B, tables {table_bytes} B"
        );
        let (record, dropped) = Store::read_reporting(&store.path_of("e")).expect("read");
        assert!(dropped.is_empty(), "{dropped:?}");
        match record {
            Record::Rig(r) => assert_eq!(r.rig, rig, "bit for bit"),
            other => panic!("unexpected record {other:?}"),
        }

        // Damage the first clip's first segment (a zstd frame, magic 28 B5 2F FD) and fix the
        // record's checksum over it, as a faulty writer would have: that clip is skipped and
        // named, the rig and its other clips load.
        let path = store.path_of("e");
        let mut b = fs::read(&path).expect("read");
        let magic = [0x28, 0xb5, 0x2f, 0xfd];
        let at = b
            .windows(4)
            .position(|w| w == magic)
            .expect("a zstd segment");
        b[at + 12] ^= 0x41;
        let crc = crc32fast::hash(&b[HEADER..]);
        b[20..24].copy_from_slice(&crc.to_le_bytes());
        fs::write(&path, &b).expect("write");
        let (record, dropped) = Store::read_reporting(&path).expect("the rest reads");
        assert_eq!(dropped.len(), 1, "{dropped:?}");
        assert!(
            dropped[0].contains(&format!("{:?}", rig.clips[0].name)),
            "{dropped:?}"
        );
        match record {
            Record::Rig(r) => assert_eq!(r.rig.clips[..], rig.clips[1..]),
            other => panic!("unexpected record {other:?}"),
        }
        let loaded = store.load_all().expect("load");
        assert_eq!((loaded.records.len(), loaded.skipped.len()), (1, 1));
        let _ = fs::remove_dir_all(&dir);
    }

    #[test]
    fn roundtrip_and_corruption_is_skipped() {
        let dir = tmpdir("rt");
        let store = Store::open(&dir).expect("open");
        let mut rig = crowdmorph_core::embedded::default_rig();
        rig.name = "copy".into();
        // With PCA levels, whose forms travel in the LOD table.
        let spec = crowdmorph_engine::lod::LodSpec {
            method: crowdmorph_engine::lod::OrderMethod::FileOrder,
            ..Default::default()
        };
        rig.lod = crowdmorph_engine::lod::build_lod(&rig, &spec, None, None).expect("lod");
        assert!(!rig.lod.pca.is_empty());
        store
            .put(RecordRef::Rig {
                id: "copy",
                rig: &rig,
                clips: &rig.clips,
            })
            .expect("put");
        store
            .put(RecordRef::Rig {
                id: "other",
                rig: &rig,
                clips: &rig.clips,
            })
            .expect("put");
        // An id that merely contains the temp marker is an ordinary record, never a stray.
        store
            .put(RecordRef::Rig {
                id: "face.tmp-1",
                rig: &rig,
                clips: &rig.clips,
            })
            .expect("put");
        // Flip one payload byte of "other", truncate a third, leave a stray temp file.
        let other = store.path_of("other");
        let mut b = fs::read(&other).expect("read");
        let last = b.len() - 1;
        b[last] ^= 0xFF;
        fs::write(&other, &b).expect("write");
        let short = store.path_of("short");
        fs::write(&short, &b[..b.len() / 2]).expect("write");
        let stray = store.dir().join(format!("{TMP}1-1-x.{EXT}"));
        fs::write(&stray, b"partial").expect("write");

        let loaded = store.load_all().expect("load");
        assert_eq!(loaded.records.len(), 2);
        let mut ids = Vec::new();
        for r in &loaded.records {
            match r {
                Record::Rig(r) => {
                    assert_eq!(r.rig, rig);
                    ids.push(r.id.clone());
                }
                other => panic!("unexpected record {other:?}"),
            }
        }
        ids.sort();
        assert_eq!(ids, ["copy", "face.tmp-1"]);
        assert_eq!(loaded.skipped.len(), 2, "{:?}", loaded.skipped);
        assert!(loaded.skipped.iter().any(|s| s.contains("checksum")));
        assert!(loaded.skipped.iter().any(|s| s.contains("truncated")));
        assert!(!stray.exists(), "stray temp file removed");

        store.remove("copy").expect("remove");
        store.remove("copy").expect("remove twice is fine");
        store.remove("face.tmp-1").expect("remove");
        assert!(store.load_all().expect("load").records.is_empty());
        let _ = fs::remove_dir_all(&dir);
    }

    #[test]
    fn clips_added_later_live_in_their_own_files() {
        let dir = tmpdir("clips");
        let store = Store::open(&dir).expect("open");
        let rig = crowdmorph_core::embedded::default_rig();
        // The record holds the first two clips; two clip files hold the others.
        store
            .put(RecordRef::Rig {
                id: "head",
                rig: &rig,
                clips: &rig.clips[..2],
            })
            .expect("put");
        let record = fs::read(store.path_of("head")).expect("read");
        store
            .put(RecordRef::Clips {
                id: "head",
                seq: 2,
                clips: &rig.clips[3..],
                rig: &rig,
            })
            .expect("put clips");
        store
            .put(RecordRef::Clips {
                id: "head",
                seq: 1,
                clips: &rig.clips[2..3],
                rig: &rig,
            })
            .expect("put clips");
        // Adding clips did not touch the rig's record.
        assert_eq!(fs::read(store.path_of("head")).expect("read"), record);
        let loaded = store.load_all().expect("load");
        assert!(loaded.skipped.is_empty(), "{:?}", loaded.skipped);
        // The record first, then the clip files in sequence order.
        let kinds: Vec<String> = loaded
            .records
            .iter()
            .map(|r| match r {
                Record::Rig(r) => format!("rig {} {}", r.id, r.rig.clips.len()),
                Record::Clips(c) => format!("clips {} {} {}", c.id, c.seq, c.clips[0].name),
                Record::Builtin(b) => format!("builtin {}", b.id),
            })
            .collect();
        assert_eq!(
            kinds,
            [
                "rig head 2".to_string(),
                format!("clips head 1 {}", rig.clips[2].name),
                format!("clips head 2 {}", rig.clips[3].name),
            ]
        );
        // A clip file renamed to another rig's name is refused, not attached to it.
        fs::copy(store.clips_path("head", 1), store.clips_path("else", 1)).expect("copy");
        let loaded = store.load_all().expect("load");
        assert_eq!(loaded.skipped.len(), 1, "{:?}", loaded.skipped);
        let _ = fs::remove_file(store.clips_path("else", 1));
        // Removing the rig removes its clip files too.
        store.remove("head").expect("remove");
        assert!(store.record_files().expect("list").is_empty());
        let _ = fs::remove_dir_all(&dir);
    }
}
