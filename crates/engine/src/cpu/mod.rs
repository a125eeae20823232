//! The CPU engine: the reference ("oracle") implementation of every blend pass, and the
//! production engine where there is no hardware GPU.
//!
//! Passes, named as their WGSL counterparts in `crates/engine/shaders/`:
//! - [`CpuRig::blend`] (`blend.wgsl`): positions, and normals where the rig has normal deltas,
//!   per Eq. 1 over the active slots of each job's LOD;
//! - [`CpuRig::recompute_normals`] (`face_normals.wgsl`, `vertex_normals.wgsl`): area-weighted normals from the blended
//!   positions for primitives whose targets carry no normal deltas;
//! - the output stage of `blend` (`pack_f16.wgsl` and `pack_q16.wgsl` on the GPU): binary16 or
//!   q16 output;
//! - on a skinned rig, `skin_lanes` in the same output stage (`skin.wgsl`): each vertex by
//!   its bones' matrices in its job's pose (glTF: morph targets first, then skinning), so the
//!   blended mesh is skinned while it is still in registers.
//!
//! # Layout
//! Vertices (all primitives concatenated) are cut into tiles of [`LANES`] = 16. For each tile
//! the targets that move any of its vertices store one [`Block`]: the 16 vertices' deltas as
//! x[16], y[16], z[16] (structure of arrays, so one vector load per component), zeros for
//! vertices the target does not move. A tile's blocks are sorted by LOD slot, so a LOD level is a prefix and
//! the loop stops at the first slot past it (the paper's early exit).
//!
//! Tiles do not take sixteen consecutive vertices: within each chunk of `CHUNK_TILES` tiles
//! (256 vertices, the unit of parallel work) vertices moved by the same targets are grouped
//! into the same tiles (`VertexOrder`), so blocks hold fewer padding zeros (ICT FaceKit: 76 %
//! of the lanes hold a delta instead of 60 %, 22 % fewer blocks to load and multiply), where
//! that saves more than the output stage's gathers cost. The output stage puts the vertices
//! back in the rig's order; nothing outside the kernel sees the layout's order.
//!
//! # Kernel
//! Jobs are sorted by LOD and grouped by [`GROUP`] = 8. For one tile and one group of Q jobs
//! (Q = 8 with AVX-512, 2 with AVX2, 4 portable: as many as the registers hold) the 3·Q
//! accumulators start at the neutral positions and stay in registers while the tile's blocks
//! stream past: each delta block is loaded once and serves all Q jobs (batch-aware), and a
//! block whose slot is inactive for the whole group is skipped (Lorach 2007); a group's last
//! jobs go 4, 2 or 1 at a time, so a batch of one job costs one job. Each tile's sums are
//! parked in L1 (a chunk's worth per job, in the layout's order, so the block loop keeps them
//! in registers). The output stage then takes a job's chunk sixteen vertices at a time through
//! vector registers: gathered from the park in the rig's vertex order, normalized for normal
//! blending, interleaved as x, y, z, encoded in the wire format (f32, binary16, or q16 in the
//! rig's box) and staged in L1; the job's part of the chunk is copied out contiguously
//! (streaming stores for outputs larger than the caches) — no transposing or converting pass
//! over the output. Only when
//! normals are recomputed from the blended positions are positions blended in f32 and
//! encoded after the normals pass.

mod simd;

pub use simd::{Isa, LANES};

use bytemuck::{Pod, Zeroable};
use glam::Vec3;
use rayon::prelude::*;

use self::simd::{Lanes, Portable, Q16Pattern};
use super::{
    BlendOutput, EngineError, OutputSpec, Precision, Q16Params, Q16Scale, VertexData, WeightBatch,
};
use crowdmorph_core::rig::{BoneMatrix, NO_BONE, Rig, SkinPoses, for_each_influence};

/// Jobs whose weights are stored together; kernels take them `Q` at a time (Q divides 8).
pub const GROUP: usize = 8;

/// Tiles per unit of parallel work (256 vertices).
const CHUNK_TILES: usize = 16;

/// Outputs larger than this are written with streaming stores: they would not stay in the
/// caches anyway, and skipping the read-for-ownership saves memory bandwidth. Smaller ones are
/// written normally so that the encoder that reads them next finds them in cache.
const STREAM_BYTES: usize = 8 << 20;

/// Largest output of one batch, in f32 components (8 GiB); bigger batches must be split.
const MAX_OUTPUT_COMPONENTS: usize = 1 << 31;

/// How a blend pass cuts its work when its output does not stay in the caches.
///
/// Without blocking, each unit of parallel work is one chunk (256 vertices) for every job of
/// the batch: the chunk's delta blocks stay in L2 while the job groups pass over them, but each
/// job's output is written 3 KB (f32) at a time, one piece per job, so a call of a thousand
/// jobs writes a thousand short streams at once, which the memory system serves far below its
/// streaming rate (a C model of the write alone, 320 MB of streaming stores on the 2-core
/// EPYC: 15.1 ms in 3 KB pieces, 9.1 ms in 12 KB runs). With blocking, a unit of work is a *span* of consecutive
/// chunks whose delta blocks together fit `span_bytes` (half the L2 of a core), and each group
/// of jobs goes over the whole span before the next: the blocks are still read from L2, and
/// each job's output is written in runs of a span's length. [`Blocking::detect`] does this
/// only for outputs over [`BLOCKING_MIN_OUTPUT`] (see there for why).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Blocking {
    /// Passes whose output is larger than this many bytes are cut into spans.
    pub min_output_bytes: usize,
    /// Delta-block bytes of one span's chunks (a span holds at least one chunk).
    pub span_bytes: usize,
}

impl Blocking {
    /// One chunk per unit of work whatever the output's size (the kernel before blocking).
    pub const NONE: Blocking = Blocking {
        min_output_bytes: usize::MAX,
        span_bytes: 0,
    };

    /// Spans of half this machine's per-core L2 (from `/sys` on Linux, else of 512 KiB) for
    /// outputs over [`BLOCKING_MIN_OUTPUT`].
    pub fn detect() -> Blocking {
        static L2: std::sync::OnceLock<usize> = std::sync::OnceLock::new();
        Blocking {
            min_output_bytes: BLOCKING_MIN_OUTPUT,
            span_bytes: *L2.get_or_init(|| l2_bytes().unwrap_or(1 << 20)) / 2,
        }
    }
}

/// Outputs from which [`Blocking::detect`] cuts spans (1 GiB). Measured on the loaded 2-core
/// EPYC (kernel at opt-level 3, paper-scale rig, alternating calls, load 4–6): spans gained
/// 0.95–1.40× at 4,096 jobs (2.1 GB of output) but lost in most runs at 1,000 jobs (525 MB:
/// 0.83–1.06×) and changed nothing at 100; the release bench (`bench cpu`, whose batch rows
/// time both cuts) has not been run yet to place this bound better.
pub const BLOCKING_MIN_OUTPUT: usize = 1 << 30;

/// The first CPU's level-2 data or unified cache, in bytes, from Linux's `/sys`.
fn l2_bytes() -> Option<usize> {
    let dir = std::path::Path::new("/sys/devices/system/cpu/cpu0/cache");
    for index in std::fs::read_dir(dir).ok()?.flatten() {
        let read = |name: &str| std::fs::read_to_string(index.path().join(name)).ok();
        if read("level")?.trim() != "2" || read("type")?.trim() == "Instruction" {
            continue;
        }
        let size = read("size")?;
        let size = size.trim();
        let (digits, unit) = size.split_at(size.find(|c: char| !c.is_ascii_digit())?);
        let n: usize = digits.parse().ok()?;
        return match unit {
            "K" => Some(n << 10),
            "M" => Some(n << 20),
            _ => None,
        };
    }
    None
}

/// Sixteen vertices' xyz, structure of arrays.
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
#[repr(C, align(64))]
pub struct Block {
    /// x of the sixteen vertices.
    pub x: [f32; LANES],
    /// y of the sixteen vertices.
    pub y: [f32; LANES],
    /// z of the sixteen vertices.
    pub z: [f32; LANES],
}

impl Default for Block {
    fn default() -> Self {
        Block::zeroed()
    }
}

/// Block-sparse deltas: per tile, the blocks of the targets that move it, sorted by slot.
#[derive(Clone, Debug, Default)]
pub struct TileBlocks {
    /// `tile_start[t]..tile_start[t + 1]` are tile `t`'s blocks.
    pub tile_start: Vec<u32>,
    /// LOD slot of each block.
    pub slot: Vec<u16>,
    /// Delta data of each block.
    pub data: Vec<Block>,
}

impl TileBlocks {
    fn build(tiles: usize, mut entries: Vec<(u32, u16, u8, Vec3)>) -> TileBlocks {
        entries.sort_unstable_by_key(|&(tile, slot, lane, _)| (tile, slot, lane));
        let mut out = TileBlocks {
            tile_start: Vec::with_capacity(tiles + 1),
            slot: Vec::new(),
            data: Vec::new(),
        };
        let mut e = 0;
        for tile in 0..tiles as u32 {
            out.tile_start.push(out.slot.len() as u32);
            while e < entries.len() && entries[e].0 == tile {
                let slot = entries[e].1;
                let mut block = Block::default();
                while e < entries.len() && entries[e].0 == tile && entries[e].1 == slot {
                    let (_, _, lane, d) = entries[e];
                    let l = lane as usize;
                    block.x[l] = d.x;
                    block.y[l] = d.y;
                    block.z[l] = d.z;
                    e += 1;
                }
                out.slot.push(slot);
                out.data.push(block);
            }
        }
        out.tile_start.push(out.slot.len() as u32);
        out
    }

    fn bytes(&self) -> usize {
        self.tile_start.len() * 4 + self.slot.len() * 2 + self.data.len() * size_of::<Block>()
    }
}

/// One staged delta while the layout is built: (vertex, then tile; slot; lane; delta).
type Entry = (u32, u16, u8, Vec3);

/// The order of vertices inside each chunk of the layout.
///
/// A tile stores one block for every slot that moves any of its sixteen vertices, so sixteen
/// neighbours in the file's order, moved by different targets, make mostly-empty blocks (ICT
/// FaceKit: 60 % of the lanes hold a delta). Within each chunk (the unit of work whose sums the
/// output stage holds in L1) vertices are regrouped greedily so that vertices moved by the same
/// slots share tiles: a tile starts from the vertex with the most slots, and takes in turn the
/// vertex that adds the fewest slots the tile does not have yet. A chunk keeps the file's order
/// when that saves fewer than [`MIN_SAVED_PER_MOVED_TILE`] blocks per tile it changes (never
/// when it stores more: the layout never grows), or when it has more distinct slots than
/// [`ORDER_MAX_WORDS`] words of bits hold. The output stage gathers the sums of changed tiles
/// back into vertex order, so nothing outside the kernel sees the order.
struct VertexOrder {
    /// New position (chunk base + lane within the chunk) of each vertex.
    new_index: Vec<u32>,
    /// Per vertex, padded to whole tiles: its lane within its chunk.
    unperm: Vec<u16>,
    /// Per tile: whether its lanes come from other places of the chunk's layout.
    permuted: Vec<bool>,
    /// Position and normal blocks in the file's vertex order.
    natural_blocks: [usize; 2],
}

/// Vertices per chunk: the unit of parallel work, within which vertices may be reordered.
const CHUNK: usize = CHUNK_TILES * LANES;

/// A chunk is regrouped only when it saves at least this many blocks per tile whose vertices
/// move: each such tile costs three gathers per job in the output stage, about what eight
/// blocks' multiply-adds cost on the Xeon that measured it (ICT FaceKit keeps 84 % of the
/// blocks regrouping saves and 63 % of the gathers; the embedded head, whose tiles gain
/// less, mostly keeps vertex order).
const MIN_SAVED_PER_MOVED_TILE: usize = 8;

/// Chunks with more distinct slots than this many 64-bit words hold keep the file's order (the
/// greedy search costs `CHUNK² × words` per chunk).
const ORDER_MAX_WORDS: usize = 4;

impl VertexOrder {
    /// Sorts `pos` and `nrm` by (vertex, slot) and chooses each chunk's order (the file's
    /// order everywhere unless `regroup`).
    fn build(
        vertices: usize,
        tiles: usize,
        pos: &mut [Entry],
        nrm: &mut [Entry],
        regroup: bool,
    ) -> VertexOrder {
        pos.sort_unstable_by_key(|e| (e.0, e.1));
        nrm.sort_unstable_by_key(|e| (e.0, e.1));
        let chunks = tiles.div_ceil(CHUNK_TILES);
        let mut order = VertexOrder {
            new_index: (0..vertices as u32).collect(),
            unperm: (0..tiles * LANES).map(|i| (i % CHUNK) as u16).collect(),
            permuted: Vec::new(),
            natural_blocks: [natural_blocks(pos), natural_blocks(nrm)],
        };
        // Scratch reused by every chunk: slot → bit, the slots seen, the masks, the order.
        let max_slot = pos.iter().map(|e| usize::from(e.1) + 1).max().unwrap_or(0);
        let mut bit = vec![u16::MAX; max_slot];
        let mut seen: Vec<u16> = Vec::new();
        let (mut pm, mut nm) = (Vec::new(), Vec::new());
        let mut chosen = Vec::with_capacity(CHUNK);
        let (mut pe, mut ne) = (0, 0);
        for c in 0..chunks {
            let lo = c * CHUNK;
            let hi = (lo + CHUNK).min(vertices);
            let end = |e: &[Entry], from: usize| {
                from + e[from..].partition_point(|x| (x.0 as usize) < hi)
            };
            let (pr, nr) = (pe..end(pos, pe), ne..end(nrm, ne));
            (pe, ne) = (pr.end, nr.end);
            for e in &pos[pr.clone()] {
                if bit[usize::from(e.1)] == u16::MAX {
                    bit[usize::from(e.1)] = seen.len() as u16;
                    seen.push(e.1);
                }
            }
            let words = seen.len().div_ceil(64).max(1);
            let n = hi - lo;
            if regroup && seen.len() <= ORDER_MAX_WORDS * 64 {
                for (m, r) in [(&mut pm, &pos[pr]), (&mut nm, &nrm[nr])] {
                    m.clear();
                    m.resize(n * words, 0u64);
                    for e in r {
                        let b = usize::from(bit[usize::from(e.1)]);
                        m[(e.0 as usize - lo) * words + b / 64] |= 1 << (b % 64);
                    }
                }
                let masks = Masks {
                    pos: &pm,
                    nrm: &nm,
                    words,
                };
                masks.greedy(n, &mut chosen);
                let natural = masks.blocks((0..n as u16).collect::<Vec<_>>().as_slice());
                let saved = natural.saturating_sub(masks.blocks(&chosen));
                let moved = chosen
                    .chunks(LANES)
                    .enumerate()
                    .filter(|&(t, lanes)| {
                        lanes
                            .iter()
                            .enumerate()
                            .any(|(l, &v)| usize::from(v) != t * LANES + l)
                    })
                    .count();
                if saved > 0 && saved >= MIN_SAVED_PER_MOVED_TILE * moved {
                    for (lane, &v) in chosen.iter().enumerate() {
                        let v = usize::from(v);
                        order.new_index[lo + v] = (lo + lane) as u32;
                        order.unperm[lo + v] = lane as u16;
                    }
                }
            }
            for s in seen.drain(..) {
                bit[usize::from(s)] = u16::MAX;
            }
        }
        // Tiles that the regrouping left in place read their sums without a gather.
        order.permuted = order
            .unperm
            .chunks(LANES)
            .enumerate()
            .map(|(t, lanes)| {
                let first = t * LANES % CHUNK;
                lanes
                    .iter()
                    .enumerate()
                    .any(|(l, &u)| usize::from(u) != first + l)
            })
            .collect();
        order
    }
}

/// Blocks of `entries` (sorted by vertex) in the file's vertex order: distinct (tile, slot).
fn natural_blocks(entries: &[Entry]) -> usize {
    let mut n = 0;
    let mut slots: Vec<u16> = Vec::new();
    for tile in entries.chunk_by(|a, b| a.0 as usize / LANES == b.0 as usize / LANES) {
        slots.clear();
        slots.extend(tile.iter().map(|e| e.1));
        slots.sort_unstable();
        slots.dedup();
        n += slots.len();
    }
    n
}

/// One chunk's slots per vertex as bits (`words` per vertex), for position and normal deltas.
struct Masks<'a> {
    pos: &'a [u64],
    nrm: &'a [u64],
    words: usize,
}

impl Masks<'_> {
    /// Position plus normal blocks of the chunk's vertices laid out in `order`.
    fn blocks(&self, order: &[u16]) -> usize {
        let w = self.words;
        let mut n = 0;
        for tile in order.chunks(LANES) {
            for m in [self.pos, self.nrm] {
                for k in 0..w {
                    let or = tile
                        .iter()
                        .fold(0u64, |a, &v| a | m[usize::from(v) * w + k]);
                    n += or.count_ones() as usize;
                }
            }
        }
        n
    }

    /// Blocks `v` adds to a tile that already has the slots in `have`.
    fn added(&self, v: usize, have: &[[u64; ORDER_MAX_WORDS]; 2]) -> u32 {
        let w = self.words;
        (0..w)
            .map(|k| {
                (self.pos[v * w + k] & !have[0][k]).count_ones()
                    + (self.nrm[v * w + k] & !have[1][k]).count_ones()
            })
            .sum()
    }

    /// The greedy order of `n` vertices (see [`VertexOrder`]) into `order`.
    fn greedy(&self, n: usize, order: &mut Vec<u16>) {
        let none = [[0u64; ORDER_MAX_WORDS]; 2];
        let weight: Vec<u32> = (0..n).map(|v| self.added(v, &none)).collect();
        let mut left: Vec<u16> = (0..n as u16).collect();
        order.clear();
        while !left.is_empty() {
            let mut have = none;
            for lane in 0..LANES.min(left.len()) {
                // The seed: most slots; then fewest added slots, most slots, lowest index.
                let key = |v: u16| {
                    let v = usize::from(v);
                    let added = if lane == 0 { 0 } else { self.added(v, &have) };
                    (added, std::cmp::Reverse(weight[v]), v)
                };
                let (i, _) = left
                    .iter()
                    .enumerate()
                    .min_by_key(|&(_, &v)| key(v))
                    .unwrap_or((0, &0));
                let v = usize::from(left.swap_remove(i));
                let w = self.words;
                for (h, m) in have.iter_mut().zip([self.pos, self.nrm]) {
                    for (h, &b) in h.iter_mut().zip(&m[v * w..(v + 1) * w]) {
                        *h |= b;
                    }
                }
                order.push(v as u16);
            }
        }
    }
}

/// Topology for recomputing normals of the primitives whose targets have no normal deltas;
/// shared by the CPU pass and the GPU's `face_normals.wgsl` and `vertex_normals.wgsl`.
#[derive(Clone, Debug, Default)]
pub(crate) struct NormalTopology {
    /// Global vertex indices of the triangles of those primitives.
    pub(crate) triangles: Vec<[u32; 3]>,
    /// Vertices whose normal is recomputed, ascending.
    pub(crate) vertices: Vec<u32>,
    /// `incident_start[i]..incident_start[i + 1]` index `incident` for `vertices[i]`.
    pub(crate) incident_start: Vec<u32>,
    /// Triangle indices (into `triangles`) incident to each recomputed vertex.
    pub(crate) incident: Vec<u32>,
}

impl NormalTopology {
    /// Collects the primitives that move but carry no normal deltas: their normals come from
    /// the blended positions (the `recompute_normals` pass).
    pub(crate) fn of(rig: &Rig) -> NormalTopology {
        let mut topology = NormalTopology::default();
        let mut incident: Vec<Vec<u32>> = Vec::new();
        let offsets = rig.vertex_offsets();
        for (p, prim) in rig.primitives.iter().enumerate() {
            if prim.targets.is_empty() || prim.has_normal_deltas() {
                continue;
            }
            let off = offsets[p];
            let first = topology.vertices.len();
            topology
                .vertices
                .extend((off..off + prim.positions.len()).map(|v| v as u32));
            incident.resize(topology.vertices.len(), Vec::new());
            for tri in prim.indices.chunks_exact(3) {
                let t = topology.triangles.len() as u32;
                topology.triangles.push([
                    (off + tri[0] as usize) as u32,
                    (off + tri[1] as usize) as u32,
                    (off + tri[2] as usize) as u32,
                ]);
                for &v in tri {
                    incident[first + v as usize].push(t);
                }
            }
        }
        topology.incident_start.push(0);
        for list in incident {
            topology.incident.extend(list);
            topology.incident_start.push(topology.incident.len() as u32);
        }
        topology
    }
}

/// A rig prepared for the CPU engine.
#[derive(Clone, Debug)]
pub struct CpuRig {
    vertices: usize,
    tiles: usize,
    slots: usize,
    isa: Isa,
    base_positions: Vec<Block>,
    positions: TileBlocks,
    base_normals: Vec<Block>,
    normals: TileBlocks,
    topology: NormalTopology,
    /// Stored (non-zero) vertex deltas per slot.
    slot_nnz: Vec<usize>,
    /// Per vertex (padded to whole tiles), its lane within its chunk's layout: the output
    /// stage gathers each chunk's sums back into vertex order through it.
    unperm: Vec<u16>,
    /// Per tile, whether its vertices were moved (else `unperm` is the identity there).
    permuted: Vec<bool>,
    /// Position and normal blocks the layout would have in vertex order.
    vertex_order_blocks: [usize; 2],
    /// On a skinned rig, each tile's bones with their weights per lane.
    skin: Option<SkinTiles>,
    /// How large outputs are cut into spans of chunks.
    blocking: Blocking,
}

/// A skinned rig's influences as the output stage reads them: per tile of sixteen consecutive
/// vertices (the rig's order), the bones any of its vertices follows, each with its weight in
/// every lane (0 where the lane's vertex does not follow it). A vertex then becomes
/// `Σ_b W_b ⊙ (M_b p)` with each bone's matrix broadcast, not gathered per lane: a face's tile
/// follows one to three bones, so this is a few dozen multiply-adds per tile and job.
#[derive(Clone, Debug)]
struct SkinTiles {
    /// Tile `t`'s entries are `start[t]..start[t + 1]`.
    start: Vec<u32>,
    /// Per entry, its bone; [`NO_BONE`] for the vertices that follow none (kept as blended,
    /// weight 1).
    bone: Vec<u16>,
    /// Per entry, each lane's weight.
    weight: Vec<LaneWeights>,
}

/// Sixteen lane weights, aligned for a vector load.
#[repr(C, align(64))]
#[derive(Clone, Copy, Debug, Default)]
struct LaneWeights([f32; LANES]);

impl SkinTiles {
    fn build(rig: &Rig, tiles: usize) -> SkinTiles {
        let mut t = SkinTiles {
            start: Vec::with_capacity(tiles + 1),
            bone: Vec::new(),
            weight: Vec::new(),
        };
        t.start.push(0);
        let mut first = 0;
        for_each_influence(rig, |v, bone, w| {
            let (tile, lane) = (v / LANES, v % LANES);
            // A new tile: close the ones before it (tiles without vertices have no entries).
            while t.start.len() <= tile {
                t.start.push(t.bone.len() as u32);
                first = t.bone.len();
            }
            let e = match t.bone[first..].iter().position(|&b| b == bone) {
                Some(e) => first + e,
                None => {
                    t.bone.push(bone);
                    t.weight.push(LaneWeights::default());
                    t.bone.len() - 1
                }
            };
            t.weight[e].0[lane] += w;
        });
        while t.start.len() <= tiles {
            t.start.push(t.bone.len() as u32);
        }
        t
    }

    fn bytes(&self) -> usize {
        self.start.len() * 4 + self.bone.len() * 2 + self.weight.len() * size_of::<LaneWeights>()
    }
}

/// What the output stage skins with: the rig's tiles and each job's bone matrices
/// (`jobs × bones`), positions or normals.
#[derive(Clone, Copy)]
struct SkinCtx<'a> {
    tiles: &'a SkinTiles,
    matrices: &'a [BoneMatrix],
    bones: usize,
    /// The normal transforms (blended normals) rather than the position transforms.
    normals: bool,
}

/// Where a blend pass writes: `jobs × V × 3` components of `elem` bytes each, in the
/// pass's output format.
#[derive(Clone, Copy)]
struct OutPtr {
    bytes: *mut u8,
    elem: usize,
}
// SAFETY: work items write disjoint vertex ranges of each job's output; see `blend`.
unsafe impl Send for OutPtr {}
// SAFETY: as above.
unsafe impl Sync for OutPtr {}

/// The format a blend pass's output stage writes.
#[derive(Clone, Copy)]
enum Format<'a> {
    F32,
    F16,
    Q16(&'a Q16Pattern),
}

/// The per-batch weights rearranged for the kernel: jobs sorted by LOD, grouped by [`GROUP`].
struct Groups {
    /// Per group: `slots × GROUP` weights, slot-major.
    weights: Vec<f32>,
    /// Per group: whether any job of the group uses each slot.
    active: Vec<u8>,
    /// Per group: slots past this are unused by every job of the group.
    end: Vec<u32>,
    /// Per group: the output job of each lane, or `u32::MAX` for padding (valid jobs first).
    jobs: Vec<[u32; GROUP]>,
    /// Jobs in the batch.
    count: usize,
}

impl Groups {
    /// The CPU side of the `build_active` pass: per group, which slots any job uses, with the
    /// jobs' weights (zero past a job's LOD or where inactive).
    fn build_active(batch: &WeightBatch) -> Groups {
        let slots = batch.slots;
        let mut order: Vec<u32> = (0..batch.jobs() as u32).collect();
        order.sort_by_key(|&j| (batch.shapes[j as usize], j));
        let n_groups = order.len().div_ceil(GROUP);
        let mut g = Groups {
            weights: vec![0.0; n_groups * slots * GROUP],
            active: vec![0; n_groups * slots],
            end: vec![0; n_groups],
            jobs: vec![[u32::MAX; GROUP]; n_groups],
            count: order.len(),
        };
        for (i, &j) in order.iter().enumerate() {
            let (gi, q) = (i / GROUP, i % GROUP);
            g.jobs[gi][q] = j;
            let row = batch.job(j as usize);
            let end = batch.shapes[j as usize].min(slots as u32);
            for (s, &w) in row.iter().enumerate().take(end as usize) {
                if w != 0.0 {
                    g.weights[(gi * slots + s) * GROUP + q] = w;
                    g.active[gi * slots + s] = 1;
                    g.end[gi] = g.end[gi].max(s as u32 + 1);
                }
            }
        }
        g
    }

    fn len(&self) -> usize {
        self.end.len()
    }
}

impl CpuRig {
    /// Prepares `rig` for evaluation with the best kernels this CPU supports.
    pub fn new(rig: &Rig) -> CpuRig {
        Self::with_isa(rig, Isa::detect())
    }

    /// Prepares `rig` for evaluation with a given kernel family (tests compare them).
    pub fn with_isa(rig: &Rig, isa: Isa) -> CpuRig {
        Self::build(rig, isa, true)
    }

    /// Prepares `rig` with tiles of consecutive vertices, without regrouping them: the same
    /// sums in the layout the regrouping replaces, for comparisons (tests check the outputs
    /// are bitwise the same; `bench cpu` times both).
    pub fn in_vertex_order(rig: &Rig, isa: Isa) -> CpuRig {
        Self::build(rig, isa, false)
    }

    fn build(rig: &Rig, isa: Isa, regroup: bool) -> CpuRig {
        let vertices = rig.vertex_count();
        let tiles = vertices.div_ceil(LANES);
        let slots = rig.targets.len();
        let slot_of = rig.lod.slots();
        let offsets = rig.vertex_offsets();

        let mut base_positions = vec![Block::default(); tiles];
        let mut base_normals = vec![Block::default(); tiles];
        // Sized up front: grown by doubling, the staging would briefly hold three times
        // the deltas (the memory model charges exactly one).
        let deltas = |with_normals: bool| -> usize {
            rig.primitives
                .iter()
                .flat_map(|p| &p.targets)
                .filter(|t| !with_normals || t.normals.is_some())
                .map(|t| t.vertices.len())
                .sum()
        };
        let mut pos_entries = Vec::with_capacity(deltas(false));
        let mut nrm_entries = Vec::with_capacity(deltas(true));
        let mut slot_nnz = vec![0usize; slots];

        // Deltas first keyed by vertex (the tile and lane are decided by the vertex order).
        for (p, prim) in rig.primitives.iter().enumerate() {
            let off = offsets[p];
            for target in &prim.targets {
                let slot = slot_of[target.target as usize] as u16;
                slot_nnz[slot as usize] += target.vertices.len();
                for (k, &v) in target.vertices.iter().enumerate() {
                    let g = (off + v as usize) as u32;
                    pos_entries.push((g, slot, 0, target.positions[k]));
                    if let Some(n) = &target.normals {
                        nrm_entries.push((g, slot, 0, n[k]));
                    }
                }
            }
        }
        let order =
            VertexOrder::build(vertices, tiles, &mut pos_entries, &mut nrm_entries, regroup);
        for e in pos_entries.iter_mut().chain(nrm_entries.iter_mut()) {
            let n = order.new_index[e.0 as usize] as usize;
            (e.0, e.2) = ((n / LANES) as u32, (n % LANES) as u8);
        }
        for (p, prim) in rig.primitives.iter().enumerate() {
            let off = offsets[p];
            for (i, (&pos, &nrm)) in prim.positions.iter().zip(&prim.normals).enumerate() {
                let n = order.new_index[off + i] as usize;
                let (t, l) = (n / LANES, n % LANES);
                base_positions[t].x[l] = pos.x;
                base_positions[t].y[l] = pos.y;
                base_positions[t].z[l] = pos.z;
                base_normals[t].x[l] = nrm.x;
                base_normals[t].y[l] = nrm.y;
                base_normals[t].z[l] = nrm.z;
            }
        }
        let topology = NormalTopology::of(rig);
        let skin = rig.is_skinned().then(|| SkinTiles::build(rig, tiles));

        CpuRig {
            vertices,
            tiles,
            slots,
            isa,
            base_positions,
            positions: TileBlocks::build(tiles, pos_entries),
            base_normals,
            normals: TileBlocks::build(tiles, nrm_entries),
            topology,
            slot_nnz,
            unperm: order.unperm,
            permuted: order.permuted,
            vertex_order_blocks: order.natural_blocks,
            skin,
            blocking: Blocking::detect(),
        }
    }

    /// The same rig with another [`Blocking`] (tests compare the cuts; `bench cpu` times
    /// them): every cut computes the same sums in the same order, so the outputs are bitwise
    /// the same.
    pub fn with_blocking(mut self, blocking: Blocking) -> CpuRig {
        self.blocking = blocking;
        self
    }

    /// How large outputs are cut into spans of chunks.
    pub fn blocking(&self) -> Blocking {
        self.blocking
    }

    /// The units of parallel work of a pass over `blocks` whose output is `output_bytes`
    /// long: ranges of chunks, one chunk each unless the output is larger than
    /// [`Blocking::min_output_bytes`], else consecutive chunks whose delta blocks together
    /// fit [`Blocking::span_bytes`] (at least one chunk each).
    fn spans(&self, blocks: &TileBlocks, output_bytes: usize) -> Vec<std::ops::Range<usize>> {
        let chunks = self.tiles.div_ceil(CHUNK_TILES);
        if output_bytes <= self.blocking.min_output_bytes {
            return (0..chunks).map(|c| c..c + 1).collect();
        }
        let chunk_bytes = |c: usize| {
            let first = blocks.tile_start[c * CHUNK_TILES] as usize;
            let last = blocks.tile_start[((c + 1) * CHUNK_TILES).min(self.tiles)] as usize;
            (last - first) * size_of::<Block>()
        };
        let mut spans = Vec::new();
        let (mut start, mut bytes) = (0, 0);
        for c in 0..chunks {
            let b = chunk_bytes(c);
            if c > start && bytes + b > self.blocking.span_bytes {
                spans.push(start..c);
                (start, bytes) = (c, 0);
            }
            bytes += b;
        }
        spans.push(start..chunks);
        spans
    }

    /// Vertices per job.
    pub fn vertex_count(&self) -> usize {
        self.vertices
    }

    /// Kernel family in use.
    pub fn isa(&self) -> Isa {
        self.isa
    }

    /// Stored vertex deltas per LOD slot.
    pub fn slot_nnz(&self) -> &[usize] {
        &self.slot_nnz
    }

    /// Bytes of the prepared layout.
    pub fn bytes(&self) -> usize {
        (self.base_positions.len() + self.base_normals.len()) * size_of::<Block>()
            + self.unperm.len() * 2
            + self.permuted.len()
            + self.positions.bytes()
            + self.normals.bytes()
            + self.topology.triangles.len() * 12
            + (self.topology.vertices.len() + self.topology.incident_start.len()) * 4
            + self.topology.incident.len() * 4
            + self.skin.as_ref().map_or(0, SkinTiles::bytes)
    }

    /// Position blocks of the slots below `shapes`: what the kernel loads per job when every
    /// one of those slots is active (each block is 48 multiply-adds per job).
    pub fn blocks_below(&self, shapes: u32) -> usize {
        self.positions
            .slot
            .iter()
            .filter(|&&s| u32::from(s) < shapes)
            .count()
    }

    /// Fraction of stored block lanes that hold a real delta (the rest are padding zeros).
    pub fn block_fill(&self) -> f64 {
        let lanes = self.positions.data.len() * LANES;
        if lanes == 0 {
            1.0
        } else {
            self.slot_nnz.iter().sum::<usize>() as f64 / lanes as f64
        }
    }

    /// What [`CpuRig::block_fill`] would be with the vertices in the rig's own order (tiles of
    /// sixteen consecutive vertices): the fill before the layout regroups them.
    pub fn block_fill_in_vertex_order(&self) -> f64 {
        let lanes = self.vertex_order_blocks[0] * LANES;
        if lanes == 0 {
            1.0
        } else {
            self.slot_nnz.iter().sum::<usize>() as f64 / lanes as f64
        }
    }

    /// Delta blocks (positions and normals) of the layout, and the blocks the same deltas take
    /// in the rig's vertex order: the memory model bounds the latter.
    pub fn blocks(&self) -> (usize, usize) {
        (
            self.positions.data.len() + self.normals.data.len(),
            self.vertex_order_blocks.iter().sum(),
        )
    }

    /// Evaluates a batch into a new output.
    pub fn evaluate(
        &self,
        batch: &WeightBatch,
        spec: OutputSpec,
    ) -> Result<BlendOutput, EngineError> {
        let mut out = BlendOutput::default();
        self.evaluate_into(batch, spec, &mut out)?;
        Ok(out)
    }

    /// Evaluates a batch, reusing `out`'s buffers (no page faults on a warm buffer).
    pub fn evaluate_into(
        &self,
        batch: &WeightBatch,
        spec: OutputSpec,
        out: &mut BlendOutput,
    ) -> Result<(), EngineError> {
        if batch.slots != self.slots {
            return Err(EngineError::SlotMismatch {
                got: batch.slots,
                want: self.slots,
            });
        }
        let jobs = batch.jobs();
        let len = jobs
            .checked_mul(self.vertices * 3)
            .filter(|&n| n <= MAX_OUTPUT_COMPONENTS)
            .ok_or(EngineError::TooLarge(
                jobs.saturating_mul(self.vertices * 12),
            ))?;
        let groups = Groups::build_active(batch);
        out.vertices = self.vertices;
        out.jobs = jobs;
        let recompute = spec.normals && !self.topology.vertices.is_empty();
        let matrices = match (&self.skin, &batch.skin) {
            (Some(_), Some(poses)) if poses.jobs.len() == jobs => Some(bone_matrices(poses)),
            (None, None) => None,
            _ => return Err(EngineError::SkinMismatch),
        };
        // The output stage skins (positions by the bones' affine transforms, blended normals
        // by their normal transforms) before it encodes.
        let skin = |normals: bool| {
            let (tiles, m) = (self.skin.as_ref()?, matrices.as_ref()?);
            Some(SkinCtx {
                tiles,
                matrices: &m.0,
                bones: m.1,
                normals,
            })
        };

        if recompute {
            // Normals come from the blended (and skinned) f32 positions: blend in f32 (kept
            // in cache for the normals pass), recompute, then encode both in the wire format.
            let mut positions = take_f32(&mut out.positions, len);
            let mut normals = take_f32(out.normals.get_or_insert_with(VertexData::default), len);
            let pos = Pass {
                base: &self.base_positions,
                blocks: &self.positions,
                normalize: false,
                read_next: true,
                skin: skin(false),
            };
            self.blend(&groups, pos, OutPtr::of_f32(&mut positions), Format::F32);
            // Vertices whose normals are all recomputed need no blended normals first.
            if self.topology.vertices.len() < self.vertices {
                let nrm = Pass {
                    base: &self.base_normals,
                    blocks: &self.normals,
                    normalize: true,
                    read_next: true,
                    skin: skin(true),
                };
                self.blend(&groups, nrm, OutPtr::of_f32(&mut normals), Format::F32);
            }
            if spec.normals {
                self.recompute_normals(&positions, &mut normals, jobs);
                out.normals = Some(VertexData::F32(normals));
            } else {
                out.normals = None;
            }
            out.positions = VertexData::F32(positions);
            out.encode_as(spec);
            return Ok(());
        }

        // Every other case: the kernel's output stage writes the wire format from registers.
        let pos = Pass {
            base: &self.base_positions,
            blocks: &self.positions,
            normalize: false,
            read_next: false,
            skin: skin(false),
        };
        out.positions = self.blend_into(&groups, pos, spec.precision, false, &mut out.positions);
        out.normals = if spec.normals {
            let nrm = Pass {
                base: &self.base_normals,
                blocks: &self.normals,
                normalize: true,
                read_next: false,
                skin: skin(true),
            };
            let mut n = out.normals.take().unwrap_or_default();
            Some(self.blend_into(&groups, nrm, spec.precision, true, &mut n))
        } else {
            None
        };
        Ok(())
    }

    /// Runs one blend pass into `buffer`'s allocation (reused when it is of the same kind),
    /// encoding in `precision`; `normals` selects the q16 scale of unit normals.
    fn blend_into(
        &self,
        groups: &Groups,
        pass: Pass<'_>,
        precision: Precision,
        normals: bool,
        buffer: &mut VertexData,
    ) -> VertexData {
        // The pass writes every component of its output, so a reused buffer is not cleared
        // first: growing it with zeros would write up to the whole output once more (a batch
        // larger than the buffer's last one).
        match precision {
            Precision::F32 => {
                let mut v = match std::mem::take(buffer) {
                    VertexData::F32(v) => v,
                    _ => Vec::new(),
                };
                self.blend_uninit(groups, pass, &mut v, Format::F32);
                VertexData::F32(v)
            }
            Precision::F16 => {
                let mut v = match std::mem::take(buffer) {
                    VertexData::F16(v) => v,
                    _ => Vec::new(),
                };
                self.blend_uninit(groups, pass, &mut v, Format::F16);
                VertexData::F16(v)
            }
            Precision::Q16(b) => {
                let mut v = match std::mem::take(buffer) {
                    VertexData::Q16(v, _) => v,
                    _ => Vec::new(),
                };
                let pattern = Q16Pattern::new(&Q16Params::new(b, normals));
                self.blend_uninit(groups, pass, &mut v, Format::Q16(&pattern));
                let scale = if normals {
                    Q16Scale::Unit
                } else {
                    Q16Scale::Box(b)
                };
                VertexData::Q16(v, scale)
            }
        }
    }

    /// Runs `pass` into `v`'s allocation, grown to the pass's `groups.count × V × 3`
    /// components of the format's size (`T` is f32, f16 or i16, as `format` says), without
    /// initializing it first: the pass writes every one of them, and `v`'s length is set only
    /// after it has.
    fn blend_uninit<T: Copy>(
        &self,
        groups: &Groups,
        pass: Pass<'_>,
        v: &mut Vec<T>,
        format: Format<'_>,
    ) {
        // The caller checked that this product fits (`MAX_OUTPUT_COMPONENTS`).
        let len = groups.count * self.vertices * 3;
        debug_assert_eq!(
            size_of::<T>(),
            if matches!(format, Format::F32) { 4 } else { 2 }
        );
        v.clear();
        v.reserve(len);
        let out = OutPtr {
            bytes: v.as_mut_ptr().cast(),
            elem: size_of::<T>(),
        };
        self.blend(groups, pass, out, format);
        // SAFETY: `v` has capacity for `len` elements, and `blend` has written all of them:
        // every job of every group, every tile's vertices (it returns early only when there
        // are no jobs or no vertices, that is when `len` is 0).
        unsafe { v.set_len(len) };
    }

    /// The `blend` pass: `out[j] = base + Σ_slot w[j][slot] · Δ[slot]` over every tile, for
    /// every job; with `normalize`, each result is scaled to unit length (normal blending).
    /// `out` must hold `jobs × V × 3` components of the format's size.
    fn blend(&self, groups: &Groups, pass: Pass<'_>, out: OutPtr, format: Format<'_>) {
        if groups.len() == 0 || self.vertices == 0 {
            return;
        }
        let bytes = groups.count * self.vertices * 3 * out.elem;
        let spans = self.spans(pass.blocks, bytes);
        // Split the jobs too when the rig is too small to keep every thread busy.
        let want_items = 4 * rayon::current_num_threads();
        let group_chunks = want_items.div_ceil(spans.len()).clamp(1, groups.len());
        let groups_per_chunk = groups.len().div_ceil(group_chunks);
        let ctx = Ctx {
            rig: self,
            groups,
            base: pass.base,
            blocks: pass.blocks,
            out,
            format,
            normalize: pass.normalize,
            stream: !pass.read_next && bytes > STREAM_BYTES,
            skin: pass.skin,
        };
        let run = |item: usize| {
            let (sc, gc) = (item % spans.len(), item / spans.len());
            let chunks = spans[sc].clone();
            let gs = gc * groups_per_chunk..((gc + 1) * groups_per_chunk).min(groups.len());
            match self.isa {
                #[cfg(target_arch = "x86_64")]
                // SAFETY: `Isa::Avx512` is only chosen when the CPU has AVX-512F.
                Isa::Avx512 => unsafe { blend_tiles_avx512(&ctx, chunks, gs) },
                #[cfg(target_arch = "x86_64")]
                // SAFETY: `Isa::Avx2Fma` is only chosen when the CPU has AVX2, FMA and F16C.
                Isa::Avx2Fma => unsafe { blend_tiles_avx2(&ctx, chunks, gs) },
                // SAFETY: the portable kernel needs no CPU feature.
                _ => unsafe { blend_tiles::<Portable, 4>(&ctx, chunks, gs) },
            }
        };
        let items = spans.len() * group_chunks;
        if items == 1 {
            // One unit of work (a small rig, one group): no thread hand-off.
            run(0);
        } else {
            (0..items).into_par_iter().for_each(run);
        }
    }

    /// The `recompute_normals` pass: for vertices of primitives without normal deltas, the
    /// normalized sum of the (area-weighted) normals of their triangles in the blended mesh.
    fn recompute_normals(&self, positions: &[f32], normals: &mut [f32], jobs: usize) {
        let topo = &self.topology;
        if topo.vertices.is_empty() {
            return;
        }
        let stride = self.vertices * 3;
        normals
            .par_chunks_mut(stride)
            .zip(positions.par_chunks(stride))
            .take(jobs)
            .for_each_init(Vec::new, |face: &mut Vec<Vec3>, (nrm, pos)| {
                let p: &[Vec3] = bytemuck::cast_slice(pos);
                let n: &mut [Vec3] = bytemuck::cast_slice_mut(nrm);
                face.clear();
                face.extend(topo.triangles.iter().map(|&[a, b, c]| {
                    let pa = p[a as usize];
                    (p[b as usize] - pa).cross(p[c as usize] - pa)
                }));
                for (i, &v) in topo.vertices.iter().enumerate() {
                    let r = topo.incident_start[i] as usize..topo.incident_start[i + 1] as usize;
                    let sum: Vec3 = topo.incident[r].iter().map(|&f| face[f as usize]).sum();
                    n[v as usize] = sum.try_normalize().unwrap_or(Vec3::Z);
                }
            });
    }
}

/// One blend pass: which neutral and deltas, and how its output is used.
#[derive(Clone, Copy)]
struct Pass<'a> {
    base: &'a [Block],
    blocks: &'a TileBlocks,
    /// Scale each result to unit length (normal blending).
    normalize: bool,
    /// Another pass reads the output right away: keep it in cache.
    read_next: bool,
    /// On a skinned rig, what the output stage skins with.
    skin: Option<SkinCtx<'a>>,
}

impl OutPtr {
    fn of_f32(v: &mut [f32]) -> OutPtr {
        OutPtr {
            bytes: v.as_mut_ptr().cast(),
            elem: 4,
        }
    }
}

/// Everything a kernel invocation reads.
struct Ctx<'a> {
    rig: &'a CpuRig,
    groups: &'a Groups,
    base: &'a [Block],
    blocks: &'a TileBlocks,
    out: OutPtr,
    format: Format<'a>,
    normalize: bool,
    stream: bool,
    skin: Option<SkinCtx<'a>>,
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn blend_tiles_avx512(
    ctx: &Ctx<'_>,
    chunks: std::ops::Range<usize>,
    groups: std::ops::Range<usize>,
) {
    // SAFETY: this function is only called when AVX-512F is present.
    unsafe { blend_tiles::<simd::Avx512, 8>(ctx, chunks, groups) }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,f16c")]
unsafe fn blend_tiles_avx2(
    ctx: &Ctx<'_>,
    chunks: std::ops::Range<usize>,
    groups: std::ops::Range<usize>,
) {
    // SAFETY: this function is only called when AVX2, FMA and F16C are present.
    unsafe { blend_tiles::<simd::Avx2, 2>(ctx, chunks, groups) }
}

/// The blend kernel over a range of chunks (a span, see [`Blocking`]) and job groups, at most
/// `QMAX` jobs of a group at a time (as many as the registers hold; a group's last few jobs go
/// `4`, `2` or `1` at a time, so that a batch of one job does one job's work).
///
/// # Safety
/// `L`'s CPU features must be present and `QMAX` must be 1, 2, 4 or 8. Concurrent calls must
/// cover disjoint chunk ranges or disjoint group ranges, so that no output component is
/// written twice.
#[inline(always)]
unsafe fn blend_tiles<L: Lanes, const QMAX: usize>(
    ctx: &Ctx<'_>,
    chunks: std::ops::Range<usize>,
    groups: std::ops::Range<usize>,
) {
    // Groups outside, chunks inside: only Q output streams are being written at a time, each
    // for the span's length, which the hardware prefetchers and the memory's pages follow; the
    // span's delta blocks stay in L2 between groups. Each job's part of a chunk is staged in
    // L1 and then copied out with streaming stores.
    let mut stage = Stage([0.0; STAGE]);
    let mut park = Park([[0.0; 3 * CHUNK]; GROUP]);
    let n_tiles = ctx.rig.tiles;
    for g in groups {
        let jobs = &ctx.groups.jobs[g];
        let valid = jobs.iter().take_while(|&&j| j != u32::MAX).count();
        for c in chunks.clone() {
            let tiles = c * CHUNK_TILES..((c + 1) * CHUNK_TILES).min(n_tiles);
            let mut sub = 0;
            while sub < valid {
                let left = valid - sub;
                // SAFETY: forwarded from the caller; `sub + Q <= valid <= GROUP`.
                unsafe {
                    sub += if QMAX >= 8 && left >= 8 {
                        blend_sub::<L, 8>(ctx, tiles.clone(), g, sub, &mut park, &mut stage)
                    } else if QMAX >= 4 && left >= 4 {
                        blend_sub::<L, 4>(ctx, tiles.clone(), g, sub, &mut park, &mut stage)
                    } else if QMAX >= 2 && left >= 2 {
                        blend_sub::<L, 2>(ctx, tiles.clone(), g, sub, &mut park, &mut stage)
                    } else {
                        blend_sub::<L, 1>(ctx, tiles.clone(), g, sub, &mut park, &mut stage)
                    };
                }
            }
        }
    }
    // SAFETY: `L`'s features are present (caller).
    unsafe { L::fence() };
}

/// Jobs `sub..sub + Q` of group `g` over the tiles of one chunk: accumulate in registers and
/// park the sums in L1 (in the layout's vertex order), then per job the output stage (gather
/// back into the rig's vertex order, normalize, interleave, encode) into the stage, and copy
/// the job's part of the chunk out. Returns `Q`.
///
/// Every job's sum runs over the same blocks in the same order whatever `Q` is, so a job and
/// its clone come out bitwise identical wherever they fall in a batch.
///
/// # Safety
/// As [`blend_tiles`]; `tiles` must be one chunk (or the rig's last, shorter one); `sub + Q`
/// must not pass the group's valid jobs.
#[inline(always)]
unsafe fn blend_sub<L: Lanes, const Q: usize>(
    ctx: &Ctx<'_>,
    tiles: std::ops::Range<usize>,
    g: usize,
    sub: usize,
    park: &mut Park,
    stage: &mut Stage,
) -> usize {
    let rig = ctx.rig;
    let slots = rig.slots;
    let blocks = ctx.blocks;
    let weights = &ctx.groups.weights[g * slots * GROUP..(g + 1) * slots * GROUP];
    let active = &ctx.groups.active[g * slots..(g + 1) * slots];
    let end = ctx.groups.end[g] as usize;
    let jobs = &ctx.groups.jobs[g][sub..sub + Q];
    let first_vertex = tiles.start * LANES;
    let chunk_floats = (tiles.end * LANES)
        .min(rig.vertices)
        .saturating_sub(first_vertex)
        * 3;
    let n_tiles = tiles.len();
    let unperm = &rig.unperm[first_vertex..first_vertex + n_tiles * LANES];
    let permuted = &rig.permuted[tiles.start..tiles.end];
    for (t, tile) in tiles.enumerate() {
        let base = &ctx.base[tile];
        let first = blocks.tile_start[tile] as usize;
        let last = blocks.tile_start[tile + 1] as usize;
        let tile_slots = &blocks.slot[first..last];
        let tile_data = &blocks.data[first..last];
        // SAFETY (whole block): `L`'s features are present (caller); `Block` is 64-byte
        // aligned, so its x, y, z arrays are too; the park holds a whole chunk per job, and
        // `t < CHUNK_TILES`.
        unsafe {
            let bx = L::load(base.x.as_ptr());
            let by = L::load(base.y.as_ptr());
            let bz = L::load(base.z.as_ptr());
            let mut acc = [[bx, by, bz]; Q];
            for (&s, d) in tile_slots.iter().zip(tile_data) {
                let s = s as usize;
                if s >= end {
                    break;
                }
                if active[s] == 0 {
                    continue;
                }
                let dx = L::load(d.x.as_ptr());
                let dy = L::load(d.y.as_ptr());
                let dz = L::load(d.z.as_ptr());
                let w = &weights[s * GROUP + sub..s * GROUP + sub + Q];
                for (a, &wq) in acc.iter_mut().zip(w) {
                    let wq = L::splat(wq);
                    a[0] = L::mul_add(wq, dx, a[0]);
                    a[1] = L::mul_add(wq, dy, a[1]);
                    a[2] = L::mul_add(wq, dz, a[2]);
                }
            }
            // Park the accumulators in L1 (three stores per job, a loop small enough to be
            // unrolled): the output stage below reads them in the rig's vertex order, and
            // indexing `acc` there would keep it in memory for the hot loop above.
            for (a, p) in acc.iter().zip(park.0.iter_mut()) {
                for (c, v) in a.iter().enumerate() {
                    L::store(*v, p.as_mut_ptr().add(c * CHUNK + t * LANES));
                }
            }
        }
    }
    let elem = ctx.out.elem;
    let stride = rig.vertices * 3;
    for (&job, p) in jobs.iter().zip(park.0.iter()) {
        let p = p.as_ptr();
        for (o, &moved) in permuted.iter().enumerate() {
            // SAFETY (whole block): `L`'s features are present (caller); the park rows are
            // 64-byte aligned and hold `n_tiles` tiles per component; `unperm` holds lanes
            // below `n_tiles × LANES` for the chunk's `n_tiles × LANES` vertices; the stage
            // holds CHUNK_TILES whole tiles of 48 components (a rig's last, partial tile
            // included: the lanes past its vertices are computed from whatever the park holds
            // and never copied out).
            unsafe {
                let (mut x, mut y, mut z) = if moved {
                    let i = unperm.as_ptr().add(o * LANES);
                    (
                        L::gather(p, i),
                        L::gather(p.add(CHUNK), i),
                        L::gather(p.add(2 * CHUNK), i),
                    )
                } else {
                    (
                        L::load(p.add(o * LANES)),
                        L::load(p.add(CHUNK + o * LANES)),
                        L::load(p.add(2 * CHUNK + o * LANES)),
                    )
                };
                if ctx.normalize {
                    (x, y, z) = L::normalize(x, y, z);
                }
                if let Some(sk) = &ctx.skin {
                    (x, y, z) =
                        skin_lanes::<L>(sk, job as usize, first_vertex / LANES + o, x, y, z);
                    if ctx.normalize {
                        (x, y, z) = L::normalize(x, y, z);
                    }
                }
                let r = L::interleave(x, y, z);
                let at = o * LANES * 3;
                match ctx.format {
                    Format::F32 => {
                        let dst = stage.0.as_mut_ptr().add(at);
                        for (k, v) in r.into_iter().enumerate() {
                            L::store(v, dst.add(LANES * k));
                        }
                    }
                    Format::F16 => {
                        let dst = stage.0.as_mut_ptr().cast::<u16>().add(at);
                        for (k, v) in r.into_iter().enumerate() {
                            L::store_f16(v, dst.add(LANES * k));
                        }
                    }
                    Format::Q16(q) => {
                        let dst = stage.0.as_mut_ptr().cast::<i16>().add(at);
                        for (k, v) in r.into_iter().enumerate() {
                            L::store_q16(v, q, LANES * k, dst.add(LANES * k));
                        }
                    }
                }
            }
        }
        let n = chunk_floats * elem;
        // SAFETY: the job's range of this chunk is inside the output and written by this
        // invocation only; the stage is a separate buffer of at least `n` bytes.
        unsafe {
            let at = (job as usize * stride + first_vertex * 3) * elem;
            let dst = ctx.out.bytes.add(at);
            let src = stage.0.as_ptr().cast::<u8>();
            if ctx.stream {
                L::copy_out(dst, src, n);
            } else {
                std::ptr::copy_nonoverlapping(src, dst, n);
            }
        }
    }
    Q
}

/// Each job's bone matrices (`jobs × bones`, job-major) and the bones per job: resolved once
/// per unique job, on every core, before the blend's output stage reads them.
fn bone_matrices(poses: &SkinPoses) -> (Vec<BoneMatrix>, usize) {
    (super::resolve_bones(poses), poses.skeleton.bones.len())
}

/// The `skin` pass (`skin.wgsl`), in the output stage of `blend`: the sixteen vertices of
/// `tile` (x, y, z lanes, blended) of job `job` become `Σ_b W_b ⊙ (M_b p)` over the bones the
/// tile's vertices follow, each matrix broadcast to every lane (`W_b` is 0 in lanes whose
/// vertex does not follow `b`); lanes that follow no bone keep `p`. Normals use the bones'
/// normal transforms (the caller normalizes).
///
/// # Safety
/// `L`'s CPU features must be present; `tile` and `job` must be in range of `sk`.
#[inline(always)]
unsafe fn skin_lanes<L: Lanes>(
    sk: &SkinCtx<'_>,
    job: usize,
    tile: usize,
    x: L,
    y: L,
    z: L,
) -> (L, L, L) {
    let t = sk.tiles;
    let entries = t.start[tile] as usize..t.start[tile + 1] as usize;
    let mats = &sk.matrices[job * sk.bones..(job + 1) * sk.bones];
    // SAFETY (whole block): `L`'s features are present (caller); every weight row is 64-byte
    // aligned and sixteen floats long.
    unsafe {
        let zero = L::splat(0.0);
        let (mut ax, mut ay, mut az) = (zero, zero, zero);
        for (&bone, w) in t.bone[entries.clone()].iter().zip(&t.weight[entries]) {
            let w = L::load(w.0.as_ptr());
            if bone == NO_BONE {
                ax = L::mul_add(w, x, ax);
                ay = L::mul_add(w, y, ay);
                az = L::mul_add(w, z, az);
                continue;
            }
            let m = &mats[bone as usize];
            let rows = if sk.normals { &m.normal } else { &m.position };
            ax = L::mul_add(w, skin_row::<L>(&rows[0], x, y, z), ax);
            ay = L::mul_add(w, skin_row::<L>(&rows[1], x, y, z), ay);
            az = L::mul_add(w, skin_row::<L>(&rows[2], x, y, z), az);
        }
        (ax, ay, az)
    }
}

/// One row of a bone's transform applied to every lane: `r0 x + r1 y + r2 z + r3`.
///
/// # Safety
/// `L`'s CPU features must be present.
#[inline(always)]
unsafe fn skin_row<L: Lanes>(r: &[f32; 4], x: L, y: L, z: L) -> L {
    // SAFETY: forwarded from the caller.
    unsafe {
        L::mul_add(
            L::splat(r[0]),
            x,
            L::mul_add(
                L::splat(r[1]),
                y,
                L::mul_add(L::splat(r[2]), z, L::splat(r[3])),
            ),
        )
    }
}

/// Runs `iterations` rounds of independent multiply-adds in registers with `isa`'s kernels on
/// the calling thread and returns the floating-point operations done (2 per lane per
/// multiply-add): the machine's FMA peak, for the roofline of `bench cpu`.
pub fn fma_probe(isa: Isa, iterations: usize) -> u64 {
    match isa {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `Isa::Avx512` is only offered when the CPU has AVX-512F.
        Isa::Avx512 => unsafe { fma_probe_avx512(iterations) },
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `Isa::Avx2Fma` is only offered when the CPU has AVX2, FMA and F16C.
        Isa::Avx2Fma => unsafe { fma_probe_avx2(iterations) },
        // SAFETY: the portable lanes need no CPU feature.
        _ => unsafe { fma_chains::<Portable, 4>(iterations) },
    }
}

/// Writes zeros over all of `dst` on every worker thread, as the output stage writes a large
/// output: from a chunk-sized buffer in L1, with `isa`'s streaming stores, each thread in long
/// runs. The output write of a blend pass with nothing else in it: the physical limit beside
/// the copy bandwidth in the roofline of `bench cpu`.
pub fn stream_probe(isa: Isa, dst: &mut [u8]) {
    dst.par_chunks_mut(1 << 20).for_each(|run| match isa {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `Isa::Avx512` is only offered when the CPU has AVX-512F.
        Isa::Avx512 => unsafe { stream_zeros_avx512(run) },
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `Isa::Avx2Fma` is only offered when the CPU has AVX2, FMA and F16C.
        Isa::Avx2Fma => unsafe { stream_zeros_avx2(run) },
        // SAFETY: the portable lanes need no CPU feature.
        _ => unsafe { stream_zeros::<Portable>(run) },
    });
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn stream_zeros_avx512(dst: &mut [u8]) {
    // SAFETY: AVX-512F is present (caller).
    unsafe { stream_zeros::<simd::Avx512>(dst) }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,f16c")]
unsafe fn stream_zeros_avx2(dst: &mut [u8]) {
    // SAFETY: AVX2, FMA and F16C are present (caller).
    unsafe { stream_zeros::<simd::Avx2>(dst) }
}

/// `dst` zeroed a stage at a time with `L`'s streaming copy.
///
/// # Safety
/// `L`'s CPU features must be present.
#[inline(always)]
unsafe fn stream_zeros<L: Lanes>(dst: &mut [u8]) {
    let stage = Stage([0.0; STAGE]);
    let src = stage.0.as_ptr().cast::<u8>();
    for piece in dst.chunks_mut(STAGE * 4) {
        // SAFETY: the stage holds `STAGE * 4 >= piece.len()` bytes and is a separate buffer;
        // `L`'s features are present (caller).
        unsafe { L::copy_out(piece.as_mut_ptr(), src, piece.len()) };
    }
    // SAFETY: as above.
    unsafe { L::fence() };
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn fma_probe_avx512(iterations: usize) -> u64 {
    // SAFETY: AVX-512F is present (caller).
    unsafe { fma_chains::<simd::Avx512, 12>(iterations) }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,f16c")]
unsafe fn fma_probe_avx2(iterations: usize) -> u64 {
    // SAFETY: AVX2, FMA and F16C are present (caller).
    unsafe { fma_chains::<simd::Avx2, 6>(iterations) }
}

/// `C` independent multiply-add chains (enough to hide the latency, few enough to stay in
/// registers).
///
/// # Safety
/// `L`'s CPU features must be present.
#[inline(always)]
unsafe fn fma_chains<L: Lanes, const C: usize>(iterations: usize) -> u64 {
    // SAFETY: forwarded from the caller.
    unsafe {
        let m = L::splat(std::hint::black_box(0.999_999));
        let c = L::splat(std::hint::black_box(1e-7));
        let mut acc = [L::splat(1.0); C];
        for _ in 0..iterations {
            for a in &mut acc {
                *a = L::mul_add(*a, m, c);
            }
        }
        std::hint::black_box(&acc);
    }
    (iterations * C * LANES * 2) as u64
}

/// One chunk's accumulators per job (x[256], y[256], z[256], in the layout's vertex order),
/// between the sums and the output stage: 24 KiB for a group, in L1.
#[repr(C, align(64))]
struct Park([[f32; 3 * CHUNK]; GROUP]);

/// Floats of one job's part of a chunk.
const STAGE: usize = CHUNK * 3;

/// One job's part of a chunk in the wire format, aligned for vector stores; 16-bit formats use
/// the first half of the bytes.
#[repr(C, align(64))]
struct Stage([f32; STAGE]);

/// Takes the f32 buffer out of `data` (reusing its allocation) and sizes it to `len`.
fn take_f32(data: &mut VertexData, len: usize) -> Vec<f32> {
    let mut v = match std::mem::take(data) {
        VertexData::F32(v) => v,
        _ => Vec::new(),
    };
    v.resize(len, 0.0);
    v
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::BlendJob;
    use crowdmorph_core::rng::SplitMix64;
    use crowdmorph_core::synthetic::{banded_rig, skinned_head};

    /// `n` clip frames at random LOD levels (and, on a skinned rig, the clip's joint poses).
    fn random_batch(rig: &Rig, n: usize, seed: u64) -> WeightBatch {
        let mut rng = SplitMix64(seed);
        let jobs: Vec<BlendJob> = (0..n)
            .map(|_| {
                let clip = rng.below(rig.clips.len());
                BlendJob::frame(
                    clip as u32,
                    rng.below(rig.clips[clip].frames as usize) as u32,
                    rng.below(rig.lod.levels.len()) as u32,
                )
            })
            .collect();
        WeightBatch::gather(rig, &jobs).expect("gather")
    }

    #[test]
    fn every_cut_of_the_work_into_spans_gives_the_same_bits() {
        // The unblocked kernel is the oracle (itself checked against the f64 oracle in
        // `tests/engine.rs`): spans of one chunk, of a few, and of the whole rig, for batches
        // that end on every sub-group path (1, 7, 9) and span several groups and items (300,
        // 1,100), with LOD levels mixed in each batch, skinning, blended and recomputed normals
        // and both float formats, on every kernel family this CPU has.
        let rigs = [
            (skinned_head(), vec![1, 7, 9, 300]),
            (banded_rig("banded", 3000, 50, 24), vec![1, 9, 1100]),
        ];
        for (rig, sizes) in rigs {
            assert!(rig.lod.levels.len() > 1, "{}: one LOD level", rig.name);
            for isa in Isa::available() {
                let plain = CpuRig::with_isa(&rig, isa).with_blocking(Blocking::NONE);
                let chunks = plain.tiles.div_ceil(CHUNK_TILES);
                let cuts = [0, 3 * plain.positions.bytes() / chunks, usize::MAX];
                for &n in &sizes {
                    let batch = random_batch(&rig, n, n as u64);
                    for (normals, precision) in [
                        (false, Precision::F32),
                        (true, Precision::F32),
                        (true, Precision::F16),
                    ] {
                        let spec = OutputSpec { normals, precision };
                        let want = plain.evaluate(&batch, spec).expect("unblocked");
                        for span_bytes in cuts {
                            let cut = plain.clone().with_blocking(Blocking {
                                min_output_bytes: 0,
                                span_bytes,
                            });
                            let spans = cut.spans(&cut.positions, 1);
                            assert!(spans.len() < chunks || span_bytes == 0);
                            assert_eq!(spans.first().map(|s| s.start), Some(0));
                            assert_eq!(spans.last().map(|s| s.end), Some(chunks));
                            let got = cut.evaluate(&batch, spec).expect("blocked");
                            let ctx = format!(
                                "{} {} {n} jobs, spans of {span_bytes} bytes, {spec:?}",
                                rig.name,
                                isa.name()
                            );
                            assert_eq!(got.positions, want.positions, "{ctx}");
                            assert_eq!(got.normals, want.normals, "{ctx}");
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn spans_fit_the_budget_and_small_outputs_keep_one_chunk_each() {
        let rig = banded_rig("banded", 3000, 50, 24);
        let cpu = CpuRig::new(&rig).with_blocking(Blocking {
            min_output_bytes: 1000,
            span_bytes: 20_000,
        });
        let chunks = cpu.tiles.div_ceil(CHUNK_TILES);
        let one_each: Vec<_> = (0..chunks).map(|c| c..c + 1).collect();
        assert_eq!(cpu.spans(&cpu.positions, 1000), one_each);
        let spans = cpu.spans(&cpu.positions, 1001);
        let block_bytes = |c: std::ops::Range<usize>| {
            let t = &cpu.positions.tile_start;
            let end = (c.end * CHUNK_TILES).min(cpu.tiles);
            (t[end] - t[c.start * CHUNK_TILES]) as usize * size_of::<Block>()
        };
        for w in spans.windows(2) {
            assert_eq!(w[0].end, w[1].start, "spans are consecutive");
            // A span holds one chunk, or no more than the budget; the next chunk would not
            // have fitted.
            assert!(w[0].len() == 1 || block_bytes(w[0].clone()) <= 20_000);
            assert!(block_bytes(w[0].start..w[1].start + 1) > 20_000);
        }
        assert!(spans.len() > 1 && spans.len() < chunks, "{spans:?}");
    }

    #[test]
    fn the_cost_model_counts_the_skin_tiles_the_layout_builds() {
        let rig = skinned_head();
        assert!(rig.lod.meshes.is_empty() && rig.lod.pca.is_empty());
        let tiles = SkinTiles::build(&rig, rig.vertex_count().div_ceil(LANES));
        assert_eq!(tiles.start.len(), rig.vertex_count().div_ceil(LANES) + 1);
        assert_eq!(
            tiles.bone.len() as u64,
            crowdmorph_core::rig::SkinShape::of(&rig).tile_entries
        );
        // Every lane's weights sum to one: its bones', or the blended vertex kept.
        for t in 0..tiles.start.len() - 1 {
            let e = tiles.start[t] as usize..tiles.start[t + 1] as usize;
            for lane in 0..LANES.min(rig.vertex_count() - t * LANES) {
                let sum: f32 = tiles.weight[e.clone()].iter().map(|w| w.0[lane]).sum();
                assert!((sum - 1.0).abs() < 1e-5, "tile {t} lane {lane}: {sum}");
            }
        }
    }
}
