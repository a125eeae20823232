//! The registry of rigs the server holds: each one prepared for the engine, with what the API
//! reports about it and the box its q16 output is quantized in.
//!
//! Entries are immutable snapshots behind `Arc`s: adding or deleting a clip builds a new entry
//! (a new *generation*) and swaps it in, so a crowd request that resolved its heads against one
//! entry is computed against exactly that entry even if the rig changes meanwhile. Generations
//! are part of the batcher's job keys, so jobs of different versions of a rig never coalesce.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, RwLock};

use crowdmorph_proto::{
    Aabb, Blob, ClipInfo, LodInfo, LodLevelInfo, Memory, MeshPrimitive, MeshResponse,
    PrimitiveInfo, Quantization, RigInfo, SplitTarget,
};
use glam::DVec3;

use crowdmorph_core::budget::Charge;
use crowdmorph_core::rig::{ACTIVE_WEIGHT_EPSILON, Rig};
use crowdmorph_engine::PreparedRig;

/// Id of the embedded rig.
pub const BUILTIN_ID: &str = "default-head";

/// One registered rig at one generation.
#[derive(Debug)]
pub struct RigEntry {
    /// Registry id.
    pub id: String,
    /// Whether it is the embedded rig.
    pub builtin: bool,
    /// Number of the embedded rig's clips that came with it (the rest were uploaded).
    pub builtin_clips: usize,
    /// The rig, prepared for the engine.
    pub prepared: PreparedRig,
    /// Unique number of this version of the rig.
    pub generation: u64,
    /// The box q16 positions are quantized in.
    pub qbox: Quantization,
    /// Vertices over all primitives.
    pub vertices: usize,
    /// Where the rig's clips are stored.
    pub layout: ClipLayout,
    /// The rig's bytes in the server's memory pool. A new generation takes it over from the
    /// one it replaces (they share most of their memory); it is given back when the last
    /// generation of a deleted rig is dropped.
    pub charge: Mutex<Charge>,
    /// The rig's clips by name, built on the first lookup (see [`RigEntry::clip_index`]).
    pub clip_names: std::sync::OnceLock<crowdmorph_core::rig::ClipIndex>,
    /// The skeleton's nodes by name, built on the first lookup (see [`RigEntry::joint_node`]).
    joint_names: std::sync::OnceLock<crowdmorph_core::rig::JointIndex>,
    /// What each joint moves and which each LOD level holds at rest, measured on first use
    /// (see [`RigEntry::joint_lod`]).
    joint_lod: std::sync::OnceLock<crowdmorph_core::rig::JointLod>,
    /// Per LOD level its near-clone bound (`rig::near_clone_bound`), and the rig's diagonal,
    /// measured on first use (see [`RigEntry::near_clone`]).
    near_bounds: std::sync::OnceLock<NearBounds>,
    /// The joint map as live weights read it, built on first use (see
    /// [`RigEntry::live_angles`]).
    live_angles: std::sync::OnceLock<Option<Arc<LiveAngles>>>,
    /// The rig's face region, found on first use (see [`RigEntry::face_region`]).
    face_region: std::sync::OnceLock<crowdmorph_core::rig::Aabb>,
    /// The q16 references of [`Format::Q16R`](crowdmorph_proto::Format::Q16R) buffers, one
    /// per mesh level asked for, by the level's address (see [`RigEntry::q16_reference`]).
    q16_references: Mutex<Vec<(usize, Arc<[i16]>)>>,
}

/// A rig's near-clone bounds: per LOD level `M_L` (`rig::near_clone_bound`), and the
/// diagonal tolerances are stated in.
#[derive(Debug)]
pub struct NearBounds {
    /// Per level, the most a vertex moves per unit of error on every weight it evaluates.
    pub levels: Arc<[f32]>,
    /// The rig's bounding-box diagonal at rest.
    pub diagonal: f64,
}

/// A skinned rig's joint map, as live weights read it: a live head's weights may carry Live Link
/// Face's head and eye angles beside its blendshapes, which turn joints as they do in a CSV
/// clip (`rig::JointMap::local`).
#[derive(Debug)]
pub struct LiveAngles {
    map: crowdmorph_core::rig::JointMap,
    /// Every node's global rotation at rest.
    rest: Vec<glam::Quat>,
    /// Loose column spelling → channel of `map`.
    pub columns: std::collections::HashMap<String, usize>,
}

impl LiveAngles {
    fn new(rig: &Rig) -> Option<LiveAngles> {
        let sk = rig.skeleton.as_ref()?;
        let map = sk.joint_map().into_owned();
        let columns = map
            .channels
            .iter()
            .enumerate()
            .map(|(i, c)| (crowdmorph_import::clips::loose(&c.column), i))
            .collect();
        Some(LiveAngles {
            rest: crowdmorph_core::rig::rest_rotations(sk),
            map,
            columns,
        })
    }

    /// Bytes it holds.
    fn bytes(&self) -> u64 {
        self.rest.len() as u64 * 16
            + self.map.bytes()
            + crowdmorph_core::rig::map_bytes(self.columns.len(), 32)
            + self.columns.keys().map(|k| k.len() as u64).sum::<u64>()
    }

    /// The joint transforms of `values` (channel, value): each turned node's local rotation.
    pub fn joints(&self, rig: &Rig, values: &[(usize, f32)]) -> crowdmorph_core::rig::JointPose {
        let Some(sk) = &rig.skeleton else {
            return crowdmorph_core::rig::JointPose::NONE;
        };
        let of: Vec<usize> = values.iter().map(|v| v.0).collect();
        let v: Vec<f32> = values.iter().map(|v| v.1).collect();
        crowdmorph_core::rig::JointPose::new(
            self.map
                .nodes(&of)
                .into_iter()
                .map(|n| {
                    let t = self.map.local(sk, &self.rest, n, &of, &v);
                    crowdmorph_core::rig::JointSet::new(n, None, Some(t.rotation), None)
                })
                .collect(),
        )
    }
}

/// Where a rig's clips are stored (see [`crowdmorph_store`]): some in the rig's record (for the
/// built-in rig, its record of extras), the rest in clip files, one per upload.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ClipLayout {
    /// Names of the clips the record holds.
    pub record: Vec<String>,
    /// Clip files: sequence number and the names of the clips each holds.
    pub files: Vec<(u64, Vec<String>)>,
}

impl ClipLayout {
    /// A layout with every clip of `clips` in the record.
    pub fn in_record(clips: &[crowdmorph_core::rig::Clip]) -> ClipLayout {
        ClipLayout {
            record: clips.iter().map(|c| c.name.clone()).collect(),
            files: Vec::new(),
        }
    }

    /// The sequence number of the next clip file.
    pub fn next_seq(&self) -> u64 {
        self.files.iter().map(|f| f.0).max().map_or(1, |s| s + 1)
    }

    /// The clip file holding `name`, if a file does (else the record does, or none).
    pub fn file_of(&self, name: &str) -> Option<u64> {
        self.files
            .iter()
            .find(|(_, names)| names.iter().any(|n| n == name))
            .map(|f| f.0)
    }

    /// This layout without clip `name`.
    pub fn without(&self, name: &str) -> ClipLayout {
        ClipLayout {
            record: self.record.iter().filter(|n| *n != name).cloned().collect(),
            files: self
                .files
                .iter()
                .map(|(s, names)| (*s, names.iter().filter(|n| *n != name).cloned().collect()))
                .collect(),
        }
    }
}

/// The clips of `rig` named in `names`, in the rig's order (through a set of the names: an
/// upload of thousands of clips onto a rig of thousands would otherwise compare every pair).
pub fn clips_named(rig: &Rig, names: &[String]) -> Vec<crowdmorph_core::rig::Clip> {
    let names: std::collections::HashSet<&str> = names.iter().map(String::as_str).collect();
    rig.clips
        .iter()
        .filter(|c| names.contains(c.name.as_str()))
        .cloned()
        .collect()
}

/// What a new rig entry is made of; [`RigEntry::new`] derives the vertex count from the
/// prepared rig. The q16 box is passed in because it reads every clip frame: callers compute
/// it with [`quantization_box`] on a blocking thread, beside the preparation.
#[derive(Debug)]
pub struct NewEntry {
    /// Registry id.
    pub id: String,
    /// Whether it is the embedded rig, and how many of its clips came with it.
    pub builtin: Option<usize>,
    /// The rig, prepared for the engine.
    pub prepared: PreparedRig,
    /// Its generation.
    pub generation: u64,
    /// Where its clips are stored.
    pub layout: ClipLayout,
    /// Its bytes in the memory pool.
    pub charge: Charge,
    /// The box its q16 output is quantized in.
    pub qbox: Quantization,
}

impl RigEntry {
    /// The clip and frame a buffer of `pose` names: a blend its largest term, live weights
    /// no clip (`""`, 0).
    pub(crate) fn shown(&self, pose: &crowdmorph_core::rig::Pose) -> (&str, u32) {
        match pose.shown() {
            Some((c, f)) => (self.rig().clips[c as usize].name.as_str(), f),
            None => ("", 0),
        }
    }

    /// A first generation of a rig.
    pub fn new(e: NewEntry) -> RigEntry {
        let rig = e.prepared.rig();
        RigEntry {
            vertices: rig.vertex_count(),
            qbox: e.qbox,
            id: e.id,
            builtin: e.builtin.is_some(),
            builtin_clips: e.builtin.unwrap_or(0),
            generation: e.generation,
            prepared: e.prepared,
            layout: e.layout,
            charge: Mutex::new(e.charge),
            clip_names: Default::default(),
            joint_names: Default::default(),
            joint_lod: Default::default(),
            near_bounds: Default::default(),
            live_angles: Default::default(),
            face_region: Default::default(),
            q16_references: Default::default(),
        }
    }

    /// The rig.
    pub fn rig(&self) -> &Rig {
        self.prepared.rig()
    }

    /// The index of the clip named `name`: a binary search over the clips sorted by name
    /// (four bytes per clip, built once per generation), where [`Rig::clip_index`] scans them.
    pub fn clip_index(&self, name: &str) -> Option<usize> {
        let clips = &self.rig().clips;
        self.clip_names
            .get_or_init(|| crowdmorph_core::rig::ClipIndex::new(clips))
            .find(clips, name)
    }

    /// The skeleton node named `name` (joint overrides name nodes): a bisection over the
    /// nodes sorted by name, built once per generation. `Missing` too on a rig without a
    /// skeleton.
    pub fn joint_node(&self, name: &str) -> Result<u32, crowdmorph_core::rig::JointLookup> {
        let Some(sk) = &self.rig().skeleton else {
            return Err(crowdmorph_core::rig::JointLookup::Missing);
        };
        self.joint_names
            .get_or_init(|| crowdmorph_core::rig::JointIndex::new(sk))
            .find(sk, name)
    }

    /// The rig's joint LOD and extents (empty without a skeleton), measured once per
    /// generation (a walk of every skinned vertex's bones, bounded by
    /// `rig::joint_lod::MAX_EFFECT_STEPS`, and of every clip's joint table), then added to the
    /// generation's memory charge as a q16 reference is.
    pub fn joint_lod(&self) -> &crowdmorph_core::rig::JointLod {
        self.joint_lod.get_or_init(|| {
            let lod = crowdmorph_core::rig::JointLod::of(self.rig());
            self.grow_charge(lod.bytes());
            lod
        })
    }

    /// `pose` as a near-clone at LOD level `lod` when each vertex may move by `tolerance`
    /// times the rig's diagonal: its weights rounded to the coarsest step whose worst case,
    /// `step/2 × M_L`, stays within that (`rig::Pose::near_clone`). `None` keeps the exact
    /// pose: no tolerance, too small a one for even one live step, a PCA level (its deltas
    /// are not the ones bounded), or a pose that moves joints.
    pub fn near_clone(
        &self,
        pose: &crowdmorph_core::rig::Pose,
        lod: u32,
        tolerance: f64,
    ) -> Option<crowdmorph_core::rig::Pose> {
        if tolerance.is_nan() || tolerance <= 0.0 {
            return None;
        }
        let b = self.near_bounds();
        let bound = *b.levels.get(lod as usize)?;
        let shift = crowdmorph_core::rig::near_clone_shift(bound, tolerance * b.diagonal)?;
        let rig = self.rig();
        let shapes = rig.lod.shapes_at(lod).ok()? as usize;
        pose.near_clone(rig, rig.lod.order.get(..shapes)?, shift)
    }

    /// Per LOD level its near-clone bound over the vertices the level evaluates (its mesh
    /// level's) and the shapes it keeps, `f32::INFINITY` for a PCA level; measured once per
    /// generation (a walk of every delta per level) and charged with it.
    pub fn near_bounds(&self) -> &NearBounds {
        self.near_bounds.get_or_init(|| {
            let rig = self.rig();
            let levels: Vec<f32> = (0..rig.lod.levels.len() as u32)
                .map(|l| {
                    let level = rig.lod.levels[l as usize];
                    if level.pca.is_some() {
                        return f32::INFINITY;
                    }
                    let shapes = (level.shapes as usize).min(rig.lod.order.len());
                    crowdmorph_core::rig::near_clone_bound(
                        self.prepared.at_level(l).rig(),
                        &rig.lod.order[..shapes],
                    )
                })
                .collect();
            self.grow_charge(16 + 4 * levels.len() as u64);
            NearBounds {
                levels: levels.into(),
                diagonal: f64::from(rig.bbox().diagonal()),
            }
        })
    }

    /// The rig's joint map as live weights read it (`None` without a skeleton): built once per
    /// generation and charged with it.
    pub fn live_angles(&self) -> Option<Arc<LiveAngles>> {
        self.live_angles
            .get_or_init(|| {
                let a = LiveAngles::new(self.rig())?;
                self.grow_charge(a.bytes());
                Some(Arc::new(a))
            })
            .clone()
    }

    /// The box a camera framing faces fits for this rig ([`Rig::face_region`]): found once per
    /// generation, by a walk of the skin weights or the stored deltas, and kept inline (no
    /// heap, so nothing is added to the charge).
    pub fn face_region(&self) -> crowdmorph_core::rig::Aabb {
        *self
            .face_region
            .get_or_init(|| self.rig().face_region().bbox)
    }

    /// Adds `bytes` the generation now holds to its charge (allocated already, so taken from
    /// the pool even past its limit).
    fn grow_charge(&self, bytes: u64) {
        if let Ok(mut c) = self.charge.lock() {
            let now = c.bytes() + bytes;
            c.set(now);
        }
    }

    /// The next generation of this rig: `prepared` (new clips or LOD) with its q16 box and
    /// clip layout. It takes over this generation's memory charge, plus `extra` (what the
    /// change reserved), and sets it to what the new generation holds.
    pub fn successor(
        &self,
        prepared: PreparedRig,
        qbox: Quantization,
        layout: ClipLayout,
        generation: u64,
        extra: Option<Charge>,
    ) -> RigEntry {
        let mut charge = self.take_charge();
        if let Some(extra) = extra {
            charge.absorb(extra);
        }
        charge.set(prepared.memory().host_bytes as u64);
        RigEntry {
            id: self.id.clone(),
            builtin: self.builtin,
            builtin_clips: self.builtin_clips,
            vertices: self.vertices,
            qbox,
            generation,
            prepared,
            layout,
            charge: Mutex::new(charge),
            clip_names: Default::default(),
            joint_names: Default::default(),
            joint_lod: Default::default(),
            near_bounds: Default::default(),
            live_angles: Default::default(),
            face_region: Default::default(),
            q16_references: Default::default(),
        }
    }

    /// The q16 reference of mesh level `level` (one of this generation's prepared levels):
    /// `compute`d on its first use, then kept with the generation and added to its memory
    /// charge (a new generation starts over, its charge set from what it holds). Computing it
    /// per batch cost a single-head blend per batch, 2.5 µs per head at 24 heads a batch.
    pub(crate) fn q16_reference(
        &self,
        level: &PreparedRig,
        compute: impl FnOnce() -> Result<Vec<i16>, String>,
    ) -> Result<Arc<[i16]>, String> {
        let key = std::ptr::from_ref(level) as usize;
        let kept = |refs: &Vec<(usize, Arc<[i16]>)>| {
            refs.iter().find(|(k, _)| *k == key).map(|(_, r)| r.clone())
        };
        if let Some(r) = self.q16_references.lock().ok().and_then(|g| kept(&g)) {
            return Ok(r);
        }
        let r: Arc<[i16]> = compute()?.into();
        let Ok(mut refs) = self.q16_references.lock() else {
            return Ok(r);
        };
        if let Some(other) = kept(&refs) {
            // Another batch computed it meanwhile: the same values.
            return Ok(other);
        }
        refs.push((key, r.clone()));
        self.grow_charge(size_of_val(&*r) as u64);
        Ok(r)
    }

    /// Moves this generation's memory charge out, for the generation that replaces it.
    pub fn take_charge(&self) -> Charge {
        self.charge.lock().map(|mut c| c.take()).unwrap_or_default()
    }

    /// Bytes charged to the pool for this rig.
    pub fn charged(&self) -> u64 {
        self.charge.lock().map(|c| c.bytes()).unwrap_or(0)
    }

    /// What the API reports about this rig.
    pub fn info(&self) -> RigInfo {
        let rig = self.rig();
        let bbox = rig.bbox();
        let mem = self.prepared.memory();
        RigInfo {
            id: self.id.clone(),
            name: rig.name.clone(),
            builtin: self.builtin,
            vertices: self.vertices as u32,
            triangles: rig.triangle_count() as u32,
            primitives: rig
                .primitives
                .iter()
                .map(|p| PrimitiveInfo {
                    name: p.name.clone(),
                    vertices: p.positions.len() as u32,
                    triangles: (p.indices.len() / 3) as u32,
                })
                .collect(),
            targets: rig.target_names().into_iter().map(str::to_string).collect(),
            clips: clip_infos(rig),
            lod: self.lod_info(),
            bbox: Aabb {
                min: bbox.min.to_array(),
                max: bbox.max.to_array(),
            },
            memory: Memory {
                host_bytes: mem.host_bytes as u64,
                device_bytes: mem.device_bytes as u64,
            },
            split_targets: rig
                .split_targets()
                .into_iter()
                .map(|(name, channels)| SplitTarget {
                    name: name.to_string(),
                    channels: channels as u32,
                })
                .collect(),
            graphs: Vec::new(),
            skeleton: skeleton_info(rig),
            import_notes: rig.import_notes.clone(),
        }
    }

    /// The rig's LOD as the API reports it; `status` is `imported` until the metric-based
    /// order has been computed, then `ready` (the API overlays `computing`/`failed` from the
    /// background job).
    pub fn lod_info(&self) -> LodInfo {
        let rig = self.rig();
        let lod = &rig.lod;
        // Channel labels: the target name, with `#k` for a name that has several channels,
        // so that an order read here can be sent back as an explicit order.
        let labels = rig.channel_labels();
        LodInfo {
            method: lod.method.clone(),
            status: if lod.method == crowdmorph_core::rig::IMPORT_LOD_METHOD {
                "imported".into()
            } else {
                "ready".into()
            },
            progress: 1.0,
            error: None,
            order: labels.of(&lod.order),
            pinned: labels.of(&lod.pinned),
            levels: (0..lod.levels.len() as u32)
                .map(|l| {
                    let at = self.prepared.at_level(l).rig();
                    LodLevelInfo {
                        shapes: lod.levels[l as usize].shapes,
                        mesh: lod.levels[l as usize].mesh,
                        vertices: at.vertex_count() as u32,
                        triangles: at.triangle_count() as u32,
                    }
                })
                .collect(),
        }
    }

    /// Topology and neutral geometry of the mesh LOD level `lod` uses (level 0: the full
    /// mesh), fetched once by clients.
    pub fn mesh(&self, lod: u32) -> MeshResponse {
        let full_bbox = self.rig().bbox();
        let rig = self.prepared.at_level(lod).rig();
        let vertices = rig.vertex_count();
        let bbox = full_bbox;
        let mut indices = Vec::with_capacity(rig.triangle_count() * 12);
        let mut positions = Vec::with_capacity(vertices * 12);
        let mut normals = Vec::with_capacity(vertices * 12);
        let mut uvs = LookColumn::new(rig, |p| p.look.uv0.as_deref(), [0.0; 2]);
        let mut uvs1 = LookColumn::new(rig, |p| p.look.uv1.as_deref(), [0.0; 2]);
        let mut colors = LookColumn::new(rig, |p| p.look.colors.as_deref(), [1.0; 4]);
        let mut prims = Vec::with_capacity(rig.primitives.len());
        let mut first_vertex = 0u32;
        let mut first_index = 0u32;
        for p in rig.primitives.iter() {
            for &i in &p.indices {
                indices.extend_from_slice(&(i + first_vertex).to_le_bytes());
            }
            for v in &p.positions {
                for c in v.to_array() {
                    positions.extend_from_slice(&c.to_le_bytes());
                }
            }
            for v in &p.normals {
                for c in v.to_array() {
                    normals.extend_from_slice(&c.to_le_bytes());
                }
            }
            uvs.push(p, |p| p.look.uv0.as_deref());
            uvs1.push(p, |p| p.look.uv1.as_deref());
            colors.push(p, |p| p.look.colors.as_deref());
            prims.push(MeshPrimitive {
                name: p.name.clone(),
                first_vertex,
                vertices: p.positions.len() as u32,
                first_index,
                indices: p.indices.len() as u32,
                material: p.look.material,
            });
            first_vertex += p.positions.len() as u32;
            first_index += p.indices.len() as u32;
        }
        MeshResponse {
            rig: self.id.clone(),
            lod,
            vertices: vertices as u32,
            primitives: prims,
            bbox: Aabb {
                min: bbox.min.to_array(),
                max: bbox.max.to_array(),
            },
            quantization: self.qbox,
            indices: Blob(indices),
            positions: Blob(positions),
            normals: Blob(normals),
            uvs: Blob(uvs.bytes),
            uvs1: Blob(uvs1.bytes),
            colors: Blob(colors.bytes),
        }
    }
}

/// The clips of a rig as the API lists them.
pub fn clip_infos(rig: &Rig) -> Vec<ClipInfo> {
    rig.clips.iter().map(clip_info).collect()
}

/// What the API (and `inspect`) reports about a skinned rig's skeleton.
pub fn skeleton_info(rig: &Rig) -> Option<crowdmorph_proto::SkeletonInfo> {
    let sk = rig.skeleton.as_ref()?;
    let (skinned, rigid) = rig.skinned_and_rigid_vertices();
    // A node that several skins list as a joint is one bone to a user (each skin has its own
    // bind matrix for it, hence its own entry in `sk.bones`).
    let mut followed: Vec<u32> = sk.bones.iter().map(|b| b.node).collect();
    followed.sort_unstable();
    followed.dedup();
    Some(crowdmorph_proto::SkeletonInfo {
        nodes: sk.nodes.len() as u32,
        bones: followed.len() as u32,
        skinned_vertices: skinned as u32,
        rigid_vertices: rigid as u32,
        animated_nodes: rig
            .animated_node_names()
            .into_iter()
            .map(str::to_string)
            .collect(),
        clips_with_joints: rig
            .clips
            .iter()
            .filter(|c| c.joints.is_some())
            .map(|c| c.name.clone())
            .collect(),
        node_names: sk.nodes.iter().map(|n| n.name.clone()).collect(),
    })
}

/// What the API reports about one clip.
pub fn clip_info(c: &crowdmorph_core::rig::Clip) -> ClipInfo {
    ClipInfo {
        name: c.name.clone(),
        frames: c.frames,
        fps: c.fps,
    }
}

/// Largest coordinate a rig may reach, in rig units. Past it, f32 blending, recomputed
/// normals (products of coordinate differences, summed over a vertex's faces) or a q16 box
/// could overflow to infinity; no real mesh comes near (it is a billion kilometres in metres).
pub const MAX_COORDINATE: f64 = 1e15;

/// Largest coordinate f16 output can carry (the largest finite binary16).
pub const MAX_F16: f64 = 65504.0;

/// The corners of the box every position any clip of `rig` can produce at any LOD lies in
/// (f64, unwidened); see [`quantization_box`].
pub fn reachable_box(rig: &Rig) -> (DVec3, DVec3) {
    reachable_box_in_chunks(rig, BOX_CHUNK)
}

/// Vertices whose bounds [`reachable_box`] accumulates at a time: 3 MiB of f64 corners,
/// whatever the rig's size (one pair per vertex of a primitive was 48 bytes a vertex, four
/// times the positions, uncharged, on every upload).
const BOX_CHUNK: usize = 1 << 16;

/// [`reachable_box`] over `chunk` vertices at a time (each target's sparse list is walked
/// with a cursor, its vertices being ascending): the same sums in the same order.
fn reachable_box_in_chunks(rig: &Rig, chunk: usize) -> (DVec3, DVec3) {
    let n = rig.targets.len();
    let mut lo = vec![0f64; n];
    let mut hi = vec![0f64; n];
    for c in &rig.clips {
        for t in 0..n {
            for f in 0..c.frames {
                let w = f64::from(c.weight(t, f));
                if w.abs() > f64::from(ACTIVE_WEIGHT_EPSILON) {
                    lo[t] = lo[t].min(w);
                    hi[t] = hi[t].max(w);
                }
            }
        }
    }
    let chunk = chunk.max(1);
    let mut bmin = DVec3::splat(f64::INFINITY);
    let mut bmax = DVec3::splat(f64::NEG_INFINITY);
    let mut vmin: Vec<DVec3> = Vec::new();
    let mut vmax: Vec<DVec3> = Vec::new();
    // On a skinned rig, per bone the box of the blended intervals of the vertices it moves.
    let bones = rig.skeleton.as_ref().map_or(0, |s| s.bones.len());
    let mut bone_box = vec![(DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)); bones];
    for p in rig.primitives.iter() {
        let mut cursor = vec![0usize; p.targets.len()];
        for start in (0..p.positions.len()).step_by(chunk) {
            let end = start.saturating_add(chunk).min(p.positions.len());
            vmin.clear();
            vmin.extend(p.positions[start..end].iter().map(|v| v.as_dvec3()));
            vmax.clear();
            vmax.extend_from_slice(&vmin);
            for (t, c) in p.targets.iter().zip(cursor.iter_mut()) {
                let (wl, wh) = (lo[t.target as usize], hi[t.target as usize]);
                while let (Some(&v), Some(d)) = (t.vertices.get(*c), t.positions.get(*c)) {
                    let v = v as usize;
                    if v >= end {
                        break;
                    }
                    let d = d.as_dvec3();
                    let (a, b) = (d * wl, d * wh);
                    vmin[v - start] += a.min(b);
                    vmax[v - start] += a.max(b);
                    *c += 1;
                }
            }
            if let Some(skin) = &p.skin {
                for (i, (&lo, &hi)) in vmin.iter().zip(&vmax).enumerate() {
                    let (j, w) = (&skin.joints[start + i], &skin.weights[start + i]);
                    for k in (0..j.len()).filter(|&k| w[k] != 0.0) {
                        let b = &mut bone_box[j[k] as usize];
                        *b = (b.0.min(lo), b.1.max(hi));
                    }
                }
                continue;
            }
            for &v in &vmin {
                bmin = bmin.min(v);
            }
            for &v in &vmax {
                bmax = bmax.max(v);
            }
        }
    }
    if let Some(sk) = &rig.skeleton {
        let reach = skinned_reach(rig, sk, &bone_box);
        bmin = bmin.min(DVec3::splat(-reach));
        bmax = bmax.max(DVec3::splat(reach));
    }
    if bmin.x > bmax.x {
        bmin = DVec3::ZERO;
        bmax = DVec3::ZERO;
    }
    (bmin, bmax)
}

/// How far from the origin a skinned vertex can be in any pose: `max_b |G_b × bind_b × q|`
/// over every bone `b` and every blended position `q` of a vertex it moves (`bone_box`).
///
/// A skinned vertex is a convex combination of its bones' images, so the largest image
/// bounds it. A node's local transform moves a point `x` to `T + R S x`, of length at most
/// `|T| + s |x|` with `s` its largest absolute scale component; down the chain from the root,
/// `|G x| ≤ A + B |x|` with `A = A_parent + B_parent |T|` and `B = B_parent s`. Poses blend
/// translations and scales convexly and rotations keep lengths, so the largest `|T|` and `s`
/// over the rest pose and every clip frame bound every pose a request can ask for (a blend,
/// live weights at rest). The bound is a sphere about the origin, looser than the exact box
/// of each frame, but it holds for blends, whose nlerped rotations no frame has.
fn skinned_reach(
    rig: &Rig,
    sk: &crowdmorph_core::rig::Skeleton,
    bone_box: &[(DVec3, DVec3)],
) -> f64 {
    let (t_max, s_max) = sk.extents(&rig.clips);
    let mut a = vec![0f64; sk.nodes.len()];
    let mut b = vec![1f64; sk.nodes.len()];
    for (i, n) in sk.nodes.iter().enumerate() {
        let (pa, pb) = match n.parent as usize {
            p if p < i => (a[p], b[p]),
            _ => (0.0, 1.0),
        };
        a[i] = pa + pb * t_max[i];
        b[i] = pb * s_max[i];
    }
    let mut reach = 0f64;
    for (bone, &(lo, hi)) in sk.bones.iter().zip(bone_box) {
        if lo.x > hi.x {
            continue;
        }
        let bind = glam::DMat4::from_cols_array(&bone.bind.map(f64::from));
        let corners = (0..8).map(|c| {
            DVec3::new(
                if c & 1 == 0 { lo.x } else { hi.x },
                if c & 2 == 0 { lo.y } else { hi.y },
                if c & 4 == 0 { lo.z } else { hi.z },
            )
        });
        let r = corners
            .map(|q| bind.transform_point3(q).length())
            .fold(0f64, f64::max);
        let n = bone.node as usize;
        reach = reach.max(a[n] + b[n] * r);
    }
    reach
}

/// Refuses a rig (or a rig with new clips) whose reachable positions exceed
/// [`MAX_COORDINATE`], naming how far they reach.
pub fn check_output_range(rig: &Rig) -> Result<(), String> {
    let (bmin, bmax) = reachable_box(rig);
    let reach = bmin.abs().max(bmax.abs()).max_element();
    if reach.is_finite() && reach <= MAX_COORDINATE {
        Ok(())
    } else {
        Err(format!(
            "positions (with every clip's weights) reach {reach:e}, past the limit of {MAX_COORDINATE:e}: \
             blending, normals and q16 output would overflow f32"
        ))
    }
}

/// The box that contains every position any clip of `rig` can produce at any LOD.
///
/// Per target, the weights a job can apply lie in `[min(0, w_min), max(0, w_max)]` over all
/// clip frames (0 because a LOD or the activity threshold can switch the target off); a
/// vertex then moves at most by the sum over targets of the extreme weight times its delta, per
/// component. The union of those per-vertex intervals is the box, so quantizing in it never
/// clamps. Computed in f64 and widened by a relative 1e-6 to absorb f32 rounding.
pub fn quantization_box(rig: &Rig) -> Quantization {
    let (bmin, bmax) = reachable_box(rig);
    let margin = (bmax - bmin).length().max(1e-30) * 1e-6;
    let bmin = bmin - DVec3::splat(margin);
    let bmax = bmax + DVec3::splat(margin);
    let step = (bmax - bmin) / 65535.0;
    let min = bmin.as_vec3().to_array();
    let step = step.as_vec3().to_array();
    // Half a step, plus what f32 arithmetic can add: the engine quantizes in f32 (at most
    // 3 × 2^-24 × |x - min| ≤ 3 units in the last place of the largest coordinate, see
    // `engine::Q16Params`) and a reader dequantizes in f32 (at most 1.5 more); 8 units in the
    // last place of the largest coordinate cover both.
    let ulp = (bmin.abs().max(bmax.abs())) * f64::from(f32::EPSILON) * 8.0;
    Quantization {
        min,
        step,
        max_error: [0, 1, 2].map(|a| (f64::from(step[a]) * 0.5 + ulp[a]) as f32),
    }
}

/// The rigs, by id.
#[derive(Debug, Default)]
pub struct Registry {
    rigs: RwLock<BTreeMap<String, Arc<RigEntry>>>,
    next_generation: AtomicU64,
    /// Each rig's named masks and mappings, beside its generations: a change of them is no
    /// new generation (the rig's data does not change), and heads resolve them by name.
    pub maps: crate::rig_maps::RigMaps,
}

impl Registry {
    /// A fresh generation number.
    pub fn generation(&self) -> u64 {
        self.next_generation.fetch_add(1, Ordering::Relaxed)
    }

    /// The entry of rig `id`.
    pub fn get(&self, id: &str) -> Option<Arc<RigEntry>> {
        self.rigs.read().ok()?.get(id).cloned()
    }

    /// Every entry, ordered by id.
    pub fn all(&self) -> Vec<Arc<RigEntry>> {
        self.rigs
            .read()
            .map(|m| m.values().cloned().collect())
            .unwrap_or_default()
    }

    /// Number of rigs.
    pub fn len(&self) -> usize {
        self.rigs.read().map(|m| m.len()).unwrap_or(0)
    }

    /// Whether no rig is registered.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Inserts or replaces an entry.
    pub fn insert(&self, entry: Arc<RigEntry>) {
        if let Ok(mut m) = self.rigs.write() {
            m.insert(entry.id.clone(), entry);
        }
    }

    /// Removes an entry, returning it.
    pub fn remove(&self, id: &str) -> Option<Arc<RigEntry>> {
        self.rigs.write().ok()?.remove(id)
    }
}

/// Whether `id` is acceptable as a rig id or clip name in URLs and file names:
/// 1–64 characters of `A-Z a-z 0-9 . _ -`, not starting with a dot.
pub fn valid_id(id: &str) -> bool {
    !id.is_empty()
        && id.len() <= 64
        && !id.starts_with('.')
        && id
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-'))
}

/// Turns a free-form name into a valid id (invalid characters become `-`).
pub fn sanitize_id(name: &str) -> String {
    let s: String = name
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-') {
                c
            } else {
                '-'
            }
        })
        .take(64)
        .collect();
    let s = s.trim_start_matches('.').to_string();
    if s.is_empty() { "rig".to_string() } else { s }
}

/// One optional per-vertex column of a mesh response (texture coordinates, colours) as f32
/// little-endian bytes over every primitive: empty when no primitive has it, else `missing`
/// for the vertices of a primitive without.
struct LookColumn<const N: usize> {
    any: bool,
    missing: [f32; N],
    bytes: Vec<u8>,
}

impl<const N: usize> LookColumn<N> {
    fn new<T>(
        rig: &Rig,
        column: impl Fn(&crowdmorph_core::rig::Primitive) -> Option<&[T]>,
        missing: [f32; N],
    ) -> Self {
        let any = rig.primitives.iter().any(|p| column(p).is_some());
        let n = if any { rig.vertex_count() * N * 4 } else { 0 };
        LookColumn {
            any,
            missing,
            bytes: Vec::with_capacity(n),
        }
    }

    fn push<T: Copy + Into<[f32; N]>>(
        &mut self,
        p: &crowdmorph_core::rig::Primitive,
        column: impl Fn(&crowdmorph_core::rig::Primitive) -> Option<&[T]>,
    ) {
        if !self.any {
            return;
        }
        match column(p) {
            Some(values) => {
                for v in values {
                    let a: [f32; N] = (*v).into();
                    for c in a {
                        self.bytes.extend_from_slice(&c.to_le_bytes());
                    }
                }
            }
            None => {
                for _ in 0..p.positions.len() {
                    for c in self.missing {
                        self.bytes.extend_from_slice(&c.to_le_bytes());
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_reachable_box_is_the_same_in_chunks_of_any_size() {
        // The embedded head: its clips move its targets both ways over three primitives.
        let head = crowdmorph_core::embedded::default_rig();
        let whole = reachable_box_in_chunks(&head, usize::MAX);
        for chunk in [1, 7, 256, 4096, BOX_CHUNK] {
            assert_eq!(
                reachable_box_in_chunks(&head, chunk),
                whole,
                "chunks of {chunk}"
            );
        }
        assert_eq!(reachable_box(&head), whole);
        assert!(whole.0.x < whole.1.x, "a real box: {whole:?}");
    }

    #[test]
    fn quantization_box_covers_every_clip_frame() {
        use crowdmorph_engine::{OutputSpec, Precision, VertexData};
        let rig = crowdmorph_core::embedded::default_rig();
        let q = quantization_box(&rig);
        let cpu = crowdmorph_engine::cpu::CpuRig::new(&rig);
        for (ci, c) in rig.clips.iter().enumerate() {
            let jobs: Vec<_> = (0..c.frames)
                .step_by(7)
                .map(|f| crowdmorph_engine::BlendJob::frame(ci as u32, f, 0))
                .collect();
            let batch = crowdmorph_engine::WeightBatch::gather(&rig, &jobs).expect("batch");
            let out = cpu.evaluate(&batch, OutputSpec::default()).expect("eval");
            let xyz = out.positions.to_f32();
            // The kernel's q16 output stage, from the same registers.
            let spec = OutputSpec {
                normals: false,
                precision: Precision::Q16(q),
            };
            let quantized = cpu.evaluate(&batch, spec).expect("eval q16");
            let VertexData::Q16(qs, _) = &quantized.positions else {
                panic!("q16 asked, {:?} returned", quantized.positions.len());
            };
            assert_eq!(
                quantized.positions,
                VertexData::encode(&xyz, spec.precision, false),
                "the kernel encodes as the scalar reference does"
            );
            let back = q.dequantize(qs);
            for (i, (a, b)) in xyz.iter().zip(&back).enumerate() {
                let axis = i % 3;
                assert!(*a >= q.min[axis], "inside the box");
                let err = (a - b).abs();
                assert!(
                    err <= q.max_error[axis],
                    "error {err} > {}",
                    q.max_error[axis]
                );
            }
        }
    }

    #[test]
    fn ids() {
        assert!(valid_id("ict_facekit-53.v2"));
        assert!(!valid_id("../etc"));
        assert!(!valid_id(".hidden"));
        assert!(!valid_id(""));
        assert_eq!(sanitize_id("My Rig/1"), "My-Rig-1");
        assert_eq!(sanitize_id("..."), "rig");
    }
}
