//! Host-side preparation of the GPU layout, and the `#[repr(C)]` structs the shaders read.
//!
//! The GPU layout is the CPU engine's idea at GPU scale: vertices in tiles of [`TILE`] = 64 (one
//! workgroup), and per (tile, slot) that moves the tile one structure-of-arrays block of
//! x[64], y[64], z[64]. A per-tile bitmask over slots, with the running block count per 32-slot
//! word, finds a slot's block in O(1). Rigs whose blocks exceed one storage binding are cut into
//! chunks of whole tiles, each with its own buffers.

use bytemuck::{Pod, Zeroable};
use glam::Vec3;

use crowdmorph_core::rig::Rig;

/// Vertices per tile = invocations per workgroup of the blend pass.
pub const TILE: usize = 64;

/// Jobs per invocation of the blend pass (two vec4s of accumulators per component), as the CPU
/// engine's [`crate::cpu::GROUP`]: each delta loaded serves this many jobs.
pub const JOBS_PER_GROUP: usize = 8;

/// Floats per delta block: x, y, z for 64 vertices.
pub const BLOCK_FLOATS: usize = 3 * TILE;

/// One term of a job's pose as `build_active` reads it: `t ×` a clip table's frame.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable, PartialEq)]
pub struct GpuTerm {
    /// Offset of the term's clip table in the rig's table buffer.
    pub table: u32,
    /// Frames of that clip.
    pub frames: u32,
    /// Frame to play.
    pub frame: u32,
    /// Fraction of the term (1.0 for a plain frame; a multiple of 1/4096 in a blend).
    pub t: f32,
}

/// `GpuJob::live` of a job without live weights.
pub const NO_LIVE: u32 = u32::MAX;

/// One job as `build_active` reads it: a clip frame is one term, a blend up to
/// [`crowdmorph_core::rig::MAX_TERMS`], and live weights are a row of the batch's live buffer instead.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable, PartialEq)]
pub struct GpuJob {
    /// Length of the job's LOD prefix.
    pub shapes: u32,
    /// Terms in use.
    pub terms: u32,
    /// Index of the job's first weight in the live buffer, or [`NO_LIVE`].
    pub live: u32,
    /// Keeps `term` 16-byte aligned, as WGSL lays it out.
    pub _pad: u32,
    /// The pose's terms, summed in this order (the CPU's `Pose::weight` order).
    pub term: [GpuTerm; crowdmorph_core::rig::MAX_TERMS],
}

/// Uniforms of `build_active`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct ActiveParams {
    /// Jobs in the dispatch.
    pub jobs: u32,
    /// Groups of [`JOBS_PER_GROUP`] jobs (one workgroup each).
    pub groups: u32,
    /// Slots of the rig.
    pub slots: u32,
    /// Index of the dispatch's first job in the batch's job buffer.
    pub job_base: u32,
}

/// Uniforms of `blend`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct BlendParams {
    /// Vertices of the whole rig.
    pub vertices: u32,
    /// First tile of the chunk.
    pub tile_begin: u32,
    /// Tiles in the chunk.
    pub tiles: u32,
    /// Slots of the rig.
    pub slots: u32,
    /// Mask words per tile.
    pub words: u32,
    /// Jobs in the dispatch.
    pub jobs: u32,
    /// 1 to normalize results (normals).
    pub normalize: u32,
    /// Workgroups along y (tiles; x is the group of jobs).
    pub tiles_y: u32,
}

/// Uniforms of `face_normals` and `vertex_normals`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct NormalParams {
    /// Vertices of the rig.
    pub vertices: u32,
    /// Triangles of the recomputed primitives.
    pub triangles: u32,
    /// Recomputed vertices.
    pub recomputed: u32,
    /// Jobs in the dispatch.
    pub jobs: u32,
}

/// Uniforms of `skin`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct SkinParams {
    /// Vertices of the rig.
    pub vertices: u32,
    /// Jobs in the dispatch.
    pub jobs: u32,
    /// Bones of the rig (matrices per job).
    pub bones: u32,
    /// 1 when blended normals are skinned too.
    pub normals: u32,
    /// Invocations along x per row of vertices.
    pub row: u32,
    /// Padding.
    pub _pad: [u32; 3],
}

/// Words per vertex of the `skin` pass's influences: four 16-bit bone ids in two words, then
/// four f32 weights.
pub const INFLUENCE_WORDS: usize = 6;

/// Every vertex's influences as `skin` reads them, all primitives concatenated in evaluation
/// order, in the order and with the weights the CPU engine sums them (its skin tiles,
/// `SkinTiles`): per tile of [`crate::cpu::LANES`] vertices, the bones by first
/// appearance in the tile, a bone a vertex names twice once with the weights summed (and left
/// out where they cancel, as the CPU's zero-weight terms change nothing). With `skin.wgsl`'s
/// fused multiply-adds in the CPU's order, a skinned rig's neutral, the reference of `q16r`
/// residuals, is the same on both engines. Vertices that follow no bone get weight 0 and are
/// left as blended (the CPU multiplies them by 1).
pub fn pack_influences(rig: &Rig) -> Vec<u32> {
    use crate::cpu::LANES;
    use crowdmorph_core::rig::{NO_BONE, for_each_influence};
    let mut words = vec![0u32; rig.vertex_count() * INFLUENCE_WORDS];
    // The current tile's bones; the current vertex's (place in the tile, bone, summed weight).
    let mut tile = (usize::MAX, Vec::<u16>::new());
    let mut vertex: (usize, Vec<(usize, u16, f32)>) = (usize::MAX, Vec::new());
    let write = |words: &mut [u32], (v, infl): &mut (usize, Vec<(usize, u16, f32)>)| {
        if *v == usize::MAX {
            return;
        }
        infl.retain(|&(_, _, w)| w != 0.0);
        infl.sort_by_key(|&(at, _, _)| at);
        let mut ids = [0u16; 4];
        let mut ws = [0f32; 4];
        for (k, &(_, bone, w)) in infl.iter().take(4).enumerate() {
            ids[k] = bone;
            ws[k] = w;
        }
        let o = *v * INFLUENCE_WORDS;
        words[o] = u32::from(ids[0]) | u32::from(ids[1]) << 16;
        words[o + 1] = u32::from(ids[2]) | u32::from(ids[3]) << 16;
        for k in 0..4 {
            words[o + 2 + k] = ws[k].to_bits();
        }
        infl.clear();
    };
    for_each_influence(rig, |v, bone, w| {
        if v != vertex.0 {
            write(&mut words, &mut vertex);
            vertex.0 = v;
        }
        if v / LANES != tile.0 {
            tile = (v / LANES, Vec::new());
        }
        let at = match tile.1.iter().position(|&b| b == bone) {
            Some(at) => at,
            None => {
                tile.1.push(bone);
                tile.1.len() - 1
            }
        };
        if bone == NO_BONE {
            return;
        }
        match vertex.1.iter_mut().find(|(_, b, _)| *b == bone) {
            Some((_, _, sum)) => *sum += w,
            None => vertex.1.push((at, bone, w)),
        }
    });
    write(&mut words, &mut vertex);
    words
}

/// Uniforms of `pack_f16`.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct PackParams {
    /// f32 values to pack.
    pub count: u32,
    /// Invocations per dispatch row.
    pub row: u32,
    /// Padding.
    pub _pad0: u32,
    /// Padding.
    pub _pad1: u32,
}

/// Uniforms of `pack_q16`: the arithmetic of [`crate::Q16Params`].
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct Q16PackParams {
    /// f32 values to pack.
    pub count: u32,
    /// Invocations per dispatch row.
    pub row: u32,
    /// Lower clamp of the scaled value.
    pub lo: f32,
    /// Upper clamp of the scaled value.
    pub hi: f32,
    /// Subtracted per axis (xyz; the fourth unused).
    pub sub: [f32; 4],
    /// Scale per axis (xyz; the fourth unused).
    pub mul: [f32; 4],
    /// Added to the rounded integer.
    pub add: i32,
    /// Components per job, where `pack_q16r` codes residual planes per job.
    pub per_job: u32,
    /// Padding.
    pub _pad: [u32; 2],
}

impl Q16PackParams {
    /// The uniforms that quantize `count` values with `q`, jobs of `per_job` components.
    pub fn new(q: &crate::Q16Params, count: u32, row: u32, per_job: u32) -> Q16PackParams {
        Q16PackParams {
            count,
            row,
            lo: q.lo,
            hi: q.hi,
            sub: [q.sub[0], q.sub[1], q.sub[2], 0.0],
            mul: [q.mul[0], q.mul[1], q.mul[2], 0.0],
            add: q.add,
            per_job,
            _pad: [0; 2],
        }
    }
}

/// How a rig's delta blocks are stored on the device (`--gpu-deltas`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum DeltaFormat {
    /// IEEE binary32, as imported: [`BLOCK_FLOATS`] words a block.
    #[default]
    F32,
    /// IEEE binary16, half the bytes and the memory traffic: x and y of a lane in one word
    /// (64 words), then the z of two neighbouring lanes in one word (32 words). Subnormal
    /// halves are flushed to zero on the host, so a device that flushes them reads the same.
    F16,
}

impl DeltaFormat {
    /// 32-bit words per block.
    pub fn block_words(self) -> usize {
        match self {
            DeltaFormat::F32 => BLOCK_FLOATS,
            DeltaFormat::F16 => BLOCK_FLOATS / 2,
        }
    }

    /// `x` as the device reads it back: itself, or rounded to the nearest binary16 (ties to
    /// even, subnormals to a signed zero). The CPU engine on a rig rounded this way is the
    /// GPU's oracle for f16 deltas.
    pub fn round(self, x: f32) -> f32 {
        match self {
            DeltaFormat::F32 => x,
            DeltaFormat::F16 => half::f16::from_bits(f16_bits(x)).to_f32(),
        }
    }

    /// Whether every delta of `rig` survives this format (binary16 ends at 65,504).
    pub fn holds(self, rig: &Rig) -> bool {
        self == DeltaFormat::F32
            || rig.primitives.iter().all(|p| {
                p.targets.iter().all(|t| {
                    t.positions
                        .iter()
                        .chain(t.normals.iter().flatten())
                        .all(|d| d.abs().max_element() <= f32::from(half::f16::MAX))
                })
            })
    }
}

impl std::str::FromStr for DeltaFormat {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "f32" => Ok(DeltaFormat::F32),
            "f16" => Ok(DeltaFormat::F16),
            _ => Err(format!("unknown delta format {s:?} (f32 or f16)")),
        }
    }
}

impl std::fmt::Display for DeltaFormat {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            DeltaFormat::F32 => "f32",
            DeltaFormat::F16 => "f16",
        })
    }
}

/// The binary16 bits of `x`, nearest, a subnormal result flushed to a zero of its sign.
fn f16_bits(x: f32) -> u16 {
    let h = half::f16::from_f32(x).to_bits();
    // Exponent field zero: zero or subnormal.
    if h & 0x7c00 == 0 { h & 0x8000 } else { h }
}

/// Appends one block (x[64], y[64], z[64]) in `format`'s words, as `blend` reads them.
fn push_block(block: &[f32; BLOCK_FLOATS], format: DeltaFormat, out: &mut Vec<u32>) {
    match format {
        DeltaFormat::F32 => out.extend(block.iter().map(|x| x.to_bits())),
        DeltaFormat::F16 => {
            let h = |i: usize| u32::from(f16_bits(block[i]));
            out.extend((0..TILE).map(|l| h(l) | h(TILE + l) << 16));
            out.extend((0..TILE / 2).map(|k| h(2 * TILE + 2 * k) | h(2 * TILE + 2 * k + 1) << 16));
        }
    }
}

/// One chunk of tiles with everything its blend dispatch reads.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Chunk {
    /// First tile.
    pub tile_begin: u32,
    /// Number of tiles.
    pub tiles: u32,
    /// Neutral values of the chunk's vertices, x y z per vertex.
    pub base: Vec<f32>,
    /// Delta blocks, [`DeltaFormat::block_words`] words each.
    pub blocks: Vec<u32>,
    /// Per (tile, word): slot bits and index of the word's first block.
    pub masks: Vec<[u32; 2]>,
}

impl Chunk {
    /// Bytes of the chunk's three buffers.
    pub fn bytes(&self) -> u64 {
        ((self.base.len() + self.blocks.len()) * 4 + self.masks.len() * 8) as u64
    }
}

/// Which deltas a layout holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Attribute {
    /// Positions.
    Positions,
    /// Normals (normal deltas; base normals).
    Normals,
}

/// Builds the chunked tile layout of one attribute with deltas in `format`. Each chunk's
/// buffers stay at or below `max_binding` bytes (a chunk holds at least one tile).
pub fn build_chunks(
    rig: &Rig,
    attribute: Attribute,
    max_binding: u64,
    format: DeltaFormat,
) -> Vec<Chunk> {
    let vertices = rig.vertex_count();
    let tiles = vertices.div_ceil(TILE);
    let slots = rig.targets.len();
    let words = slots.div_ceil(32).max(1);
    let slot_of = rig.lod.slots();
    let offsets = rig.vertex_offsets();

    // (tile, slot, lane, delta) for every stored delta of the attribute.
    let mut base = vec![0f32; vertices * 3];
    let mut entries: Vec<(u32, u32, u8, Vec3)> = Vec::new();
    for (p, prim) in rig.primitives.iter().enumerate() {
        let off = offsets[p];
        let values = match attribute {
            Attribute::Positions => &prim.positions,
            Attribute::Normals => &prim.normals,
        };
        for (i, v) in values.iter().enumerate() {
            base[(off + i) * 3..(off + i) * 3 + 3].copy_from_slice(&v.to_array());
        }
        for t in &prim.targets {
            let deltas = match attribute {
                Attribute::Positions => Some(&t.positions),
                Attribute::Normals => t.normals.as_ref(),
            };
            let Some(deltas) = deltas else { continue };
            let slot = slot_of[t.target as usize];
            for (k, &v) in t.vertices.iter().enumerate() {
                let g = off + v as usize;
                entries.push(((g / TILE) as u32, slot, (g % TILE) as u8, deltas[k]));
            }
        }
    }
    entries.sort_unstable_by_key(|&(tile, slot, lane, _)| (tile, slot, lane));

    let mut chunks = Vec::new();
    let mut chunk = Chunk::default();
    let mut e = 0;
    for tile in 0..tiles as u32 {
        // Gather this tile's blocks first, then decide whether they fit in the current chunk.
        let mut masks = vec![[0u32; 2]; words];
        let mut blocks: Vec<u32> = Vec::new();
        let mut slots_here: Vec<u32> = Vec::new();
        while e < entries.len() && entries[e].0 == tile {
            let slot = entries[e].1;
            let mut block = [0f32; BLOCK_FLOATS];
            while e < entries.len() && entries[e].0 == tile && entries[e].1 == slot {
                let (_, _, lane, d) = entries[e];
                let l = lane as usize;
                block[l] = d.x;
                block[TILE + l] = d.y;
                block[2 * TILE + l] = d.z;
                e += 1;
            }
            slots_here.push(slot);
            push_block(&block, format, &mut blocks);
        }
        let first_v = tile as usize * TILE;
        let last_v = (first_v + TILE).min(vertices);
        let tile_bytes = (blocks.len() * 4 + (last_v - first_v) * 12 + words * 8) as u64;
        if chunk.tiles > 0 && chunk.bytes() + tile_bytes > max_binding {
            chunks.push(std::mem::take(&mut chunk));
        }
        if chunk.tiles == 0 {
            chunk.tile_begin = tile;
        }
        let first_block = (chunk.blocks.len() / format.block_words()) as u32;
        // Running count: blocks of this tile in earlier words.
        let mut before = 0u32;
        for (w, m) in masks.iter_mut().enumerate() {
            let in_word: Vec<u32> = slots_here
                .iter()
                .copied()
                .filter(|&s| s as usize / 32 == w)
                .collect();
            for s in &in_word {
                m[0] |= 1 << (s % 32);
            }
            m[1] = first_block + before;
            before += in_word.len() as u32;
        }
        chunk.masks.extend_from_slice(&masks);
        chunk.blocks.extend_from_slice(&blocks);
        chunk.base.extend_from_slice(&base[first_v * 3..last_v * 3]);
        chunk.tiles += 1;
    }
    if chunk.tiles > 0 {
        chunks.push(chunk);
    }
    chunks
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uniform_structs_match_the_wgsl_layouts() {
        // Sizes and field offsets as the WGSL structs declare them (all u32, 16-byte multiples).
        assert_eq!(size_of::<GpuTerm>(), 16);
        assert_eq!(std::mem::offset_of!(GpuTerm, t), 12);
        assert_eq!(size_of::<GpuJob>(), 96);
        assert_eq!(std::mem::offset_of!(GpuJob, live), 8);
        assert_eq!(std::mem::offset_of!(GpuJob, term), 16);
        assert_eq!(size_of::<ActiveParams>(), 16);
        assert_eq!(size_of::<BlendParams>(), 32);
        assert_eq!(std::mem::offset_of!(BlendParams, normalize), 24);
        assert_eq!(std::mem::offset_of!(BlendParams, tiles_y), 28);
        assert_eq!(size_of::<NormalParams>(), 16);
        assert_eq!(std::mem::offset_of!(NormalParams, jobs), 12);
        assert_eq!(size_of::<SkinParams>(), 32);
        assert_eq!(std::mem::offset_of!(SkinParams, normals), 12);
        assert_eq!(std::mem::offset_of!(SkinParams, row), 16);
        assert_eq!(size_of::<crowdmorph_core::rig::BoneMatrix>(), 96);
        assert_eq!(size_of::<PackParams>(), 16);
        assert_eq!(size_of::<Q16PackParams>(), 64);
        assert_eq!(std::mem::offset_of!(Q16PackParams, lo), 8);
        assert_eq!(std::mem::offset_of!(Q16PackParams, sub), 16);
        assert_eq!(std::mem::offset_of!(Q16PackParams, mul), 32);
        assert_eq!(std::mem::offset_of!(Q16PackParams, add), 48);
        assert_eq!(std::mem::offset_of!(Q16PackParams, per_job), 52);
    }

    /// Lane `lane`'s delta in block `b` of `words` laid out in `format`: what `blend` reads.
    fn read_block(words: &[u32], format: DeltaFormat, b: usize, lane: usize) -> Vec3 {
        let o = b * format.block_words();
        match format {
            DeltaFormat::F32 => Vec3::new(
                f32::from_bits(words[o + lane]),
                f32::from_bits(words[o + TILE + lane]),
                f32::from_bits(words[o + 2 * TILE + lane]),
            ),
            DeltaFormat::F16 => {
                let half = |w: u32, hi: bool| {
                    half::f16::from_bits(if hi { (w >> 16) as u16 } else { w as u16 }).to_f32()
                };
                let xy = words[o + lane];
                let z = words[o + TILE + lane / 2];
                Vec3::new(half(xy, false), half(xy, true), half(z, lane % 2 == 1))
            }
        }
    }

    #[test]
    fn f16_deltas_round_to_nearest_and_flush_subnormals() {
        let f = DeltaFormat::F16;
        assert_eq!(f.round(1.0), 1.0);
        assert_eq!(f.round(1.0 + 1.0 / 4096.0), 1.0);
        assert_eq!(f.round(1.0 + 2.0 / 4096.0), 1.0);
        assert_eq!(f.round(1.0 + 3.0 / 4096.0), 1.0 + 1.0 / 1024.0);
        assert_eq!(f.round(-0.1), -0.099_975_586);
        // Below 2^-14 binary16 is subnormal: flushed, keeping the sign.
        assert_eq!(f.round(3e-5).to_bits(), 0.0f32.to_bits());
        assert_eq!(f.round(-3e-5).to_bits(), (-0.0f32).to_bits());
        assert_eq!(f.round(65_504.0), 65_504.0);
        assert_eq!(DeltaFormat::F32.round(3e-5), 3e-5);
    }

    #[test]
    fn a_rig_with_a_delta_past_binary16_is_not_held_in_f16() {
        let rig = crowdmorph_core::embedded::default_rig();
        assert!(DeltaFormat::F16.holds(&rig));
        let mut primitives = (*rig.primitives).clone();
        primitives[0].targets[0].positions[0].y = 70_000.0;
        let far = Rig {
            primitives: std::sync::Arc::new(primitives),
            ..rig
        };
        assert!(!DeltaFormat::F16.holds(&far));
        assert!(DeltaFormat::F32.holds(&far));
    }

    #[test]
    fn masks_find_every_block_and_chunks_respect_the_limit() {
        for format in [DeltaFormat::F32, DeltaFormat::F16] {
            masks_find_every_block(format);
        }
    }

    fn masks_find_every_block(format: DeltaFormat) {
        let rig = crowdmorph_core::embedded::default_rig();
        let whole = build_chunks(&rig, Attribute::Positions, u64::MAX, format);
        assert_eq!(whole.len(), 1);
        let limit = whole[0].bytes() / 5;
        let chunks = build_chunks(&rig, Attribute::Positions, limit, format);
        assert!(chunks.len() >= 5, "{} chunks", chunks.len());
        assert!(chunks.iter().all(|c| c.bytes() <= limit));
        assert_eq!(
            chunks.iter().map(|c| c.tiles).sum::<u32>() as usize,
            rig.vertex_count().div_ceil(TILE)
        );
        // Every stored delta is found through the masks of its chunk.
        let slots = rig.lod.slots();
        let words = rig.targets.len().div_ceil(32);
        let offsets = rig.vertex_offsets();
        for (p, prim) in rig.primitives.iter().enumerate() {
            for t in &prim.targets {
                let s = slots[t.target as usize];
                for (k, &v) in t.vertices.iter().enumerate() {
                    let g = offsets[p] + v as usize;
                    let tile = (g / TILE) as u32;
                    let c = chunks
                        .iter()
                        .find(|c| (c.tile_begin..c.tile_begin + c.tiles).contains(&tile))
                        .expect("chunk of tile");
                    let m = c.masks[(tile - c.tile_begin) as usize * words + s as usize / 32];
                    let bit = 1u32 << (s % 32);
                    assert_ne!(m[0] & bit, 0, "slot {s} missing from tile {tile}");
                    let b = (m[1] + (m[0] & (bit - 1)).count_ones()) as usize;
                    let lane = g % TILE;
                    let want = t.positions[k].to_array().map(|x| format.round(x));
                    let got = read_block(&c.blocks, format, b, lane).to_array();
                    assert_eq!(got.map(f32::to_bits), want.map(f32::to_bits));
                }
            }
        }
    }
}
