//! The CPU engine: the reference ("oracle") implementation of every blend pass, and the
//! production engine where there is no hardware GPU.
//!
//! Passes, named as their WGSL counterparts in `shaders/`:
//! - [`CpuRig::blend`] (`blend.wgsl`): positions, and normals where the rig has normal deltas,
//!   per Eq. 1 over the active slots of each job's LOD;
//! - [`CpuRig::recompute_normals`] (`face_normals.wgsl`, `vertex_normals.wgsl`): area-weighted normals from the blended
//!   positions for primitives whose targets carry no normal deltas;
//! - [`pack_f16`] (`pack_f16.wgsl`): binary16 output.
//!
//! # Layout
//! Vertices (all primitives concatenated) are cut into tiles of [`LANES`] = 16. For each tile
//! the targets that move any of its vertices store one [`Block`]: the 16 vertices' deltas as
//! x[16], y[16], z[16] (structure of arrays, so one vector load per component), zeros for
//! vertices the target does not move. A tile's blocks are sorted by LOD slot, so a LOD level is a prefix and
//! the loop stops at the first slot past it (the paper's early exit).
//!
//! # Kernel
//! Jobs are sorted by LOD and grouped by [`GROUP`] = 8. For one tile and one group of Q jobs
//! (Q = 8 with AVX-512, 2 with AVX2, 4 portable: as many as the registers hold) the 3·Q
//! accumulators start at the neutral positions and stay in registers while the tile's blocks
//! stream past: each delta block is loaded once and serves all Q jobs (batch-aware), and a
//! block whose slot is inactive for the whole group is skipped (Lorach 2007). Each job's 16
//! vertices are then written contiguously into that job's output, already interleaved as
//! x, y, z — no transposing pass over the output.

mod simd;

pub use simd::{Isa, LANES};

use bytemuck::{Pod, Zeroable};
use glam::Vec3;
use half::f16;
use rayon::prelude::*;

use self::simd::{Lanes, Portable};
use super::{BlendOutput, EngineError, OutputSpec, Precision, VertexData, WeightBatch};
use crate::rig::Rig;

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
}

#[derive(Clone, Copy)]
enum OutPtr {
    F32(*mut f32),
    F16(*mut f16),
}
// SAFETY: work items write disjoint vertex ranges of each job's output; see `blend`.
unsafe impl Send for OutPtr {}
// SAFETY: as above.
unsafe impl Sync for OutPtr {}

/// Where a blend pass writes: an f32 or an f16 buffer of `jobs × V × 3` components.
enum Dst<'a> {
    F32(&'a mut [f32]),
    F16(&'a mut [f16]),
}

impl Dst<'_> {
    fn len(&self) -> usize {
        match self {
            Dst::F32(v) => v.len(),
            Dst::F16(v) => v.len(),
        }
    }
    fn ptr(&mut self) -> OutPtr {
        match self {
            Dst::F32(v) => OutPtr::F32(v.as_mut_ptr()),
            Dst::F16(v) => OutPtr::F16(v.as_mut_ptr()),
        }
    }
}

/// The per-batch weights rearranged for the kernel: jobs sorted by LOD, grouped by [`GROUP`].
struct Groups {
    /// Per group: `slots × GROUP` weights, slot-major.
    weights: Vec<f32>,
    /// Per group: whether any job of the group uses each slot.
    active: Vec<u8>,
    /// Per group: slots past this are unused by every job of the group.
    end: Vec<u32>,
    /// Per group: the output job of each lane, or `u32::MAX` for padding.
    jobs: Vec<[u32; GROUP]>,
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

        for (p, prim) in rig.primitives.iter().enumerate() {
            let off = offsets[p];
            for (i, (&pos, &nrm)) in prim.positions.iter().zip(&prim.normals).enumerate() {
                let (t, l) = ((off + i) / LANES, (off + i) % LANES);
                base_positions[t].x[l] = pos.x;
                base_positions[t].y[l] = pos.y;
                base_positions[t].z[l] = pos.z;
                base_normals[t].x[l] = nrm.x;
                base_normals[t].y[l] = nrm.y;
                base_normals[t].z[l] = nrm.z;
            }
            for target in &prim.targets {
                let slot = slot_of[target.target as usize] as u16;
                slot_nnz[slot as usize] += target.vertices.len();
                for (k, &v) in target.vertices.iter().enumerate() {
                    let g = off + v as usize;
                    let (t, l) = ((g / LANES) as u32, (g % LANES) as u8);
                    pos_entries.push((t, slot, l, target.positions[k]));
                    if let Some(n) = &target.normals {
                        nrm_entries.push((t, slot, l, n[k]));
                    }
                }
            }
        }
        let topology = NormalTopology::of(rig);

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
        }
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
            + self.positions.bytes()
            + self.normals.bytes()
            + self.topology.triangles.len() * 12
            + (self.topology.vertices.len() + self.topology.incident_start.len()) * 4
            + self.topology.incident.len() * 4
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

        if spec.precision == Precision::F16 && !recompute {
            // Direct path: each staged chunk is rounded to binary16 as it is copied out.
            let mut positions = take_f16(&mut out.positions, len);
            self.blend(
                &groups,
                &self.base_positions,
                &self.positions,
                Dst::F16(&mut positions),
                Flags::POSITIONS,
            );
            out.positions = VertexData::F16(positions);
            out.normals = if spec.normals {
                let mut n = take_f16(out.normals.get_or_insert_with(VertexData::default), len);
                self.blend(
                    &groups,
                    &self.base_normals,
                    &self.normals,
                    Dst::F16(&mut n),
                    Flags::NORMALS,
                );
                Some(VertexData::F16(n))
            } else {
                None
            };
            return Ok(());
        }

        // f32 path (also used for f16 when normals are recomputed from f32 positions).
        let mut positions = take_f32(&mut out.positions, len);
        // Positions that the normals pass reads next must stay in cache (no streaming).
        let ctx_flags = Flags {
            normalize: false,
            read_next: recompute,
        };
        self.blend(
            &groups,
            &self.base_positions,
            &self.positions,
            Dst::F32(&mut positions),
            ctx_flags,
        );
        let normals = if spec.normals {
            let mut n = take_f32(out.normals.get_or_insert_with(VertexData::default), len);
            // Vertices whose normals are all recomputed need no blended normals first.
            if self.topology.vertices.len() < self.vertices {
                self.blend(
                    &groups,
                    &self.base_normals,
                    &self.normals,
                    Dst::F32(&mut n),
                    Flags::NORMALS,
                );
            }
            self.recompute_normals(&positions, &mut n, jobs);
            Some(n)
        } else {
            None
        };
        out.positions = finish(positions, spec.precision);
        out.normals = normals.map(|n| finish(n, spec.precision));
        Ok(())
    }

    /// The `blend` pass: `out[j] = base + Σ_slot w[j][slot] · Δ[slot]` over every tile, for
    /// every job; with `normalize`, each result is scaled to unit length (normal blending).
    fn blend(
        &self,
        groups: &Groups,
        base: &[Block],
        blocks: &TileBlocks,
        mut out: Dst<'_>,
        flags: Flags,
    ) {
        if groups.len() == 0 || self.vertices == 0 {
            return;
        }
        let tile_chunks = self.tiles.div_ceil(CHUNK_TILES);
        // Split the jobs too when the rig is too small to keep every thread busy.
        let want_items = 4 * rayon::current_num_threads();
        let group_chunks = want_items.div_ceil(tile_chunks).clamp(1, groups.len());
        let groups_per_chunk = groups.len().div_ceil(group_chunks);
        let ptr = out.ptr();
        let ctx = Ctx {
            rig: self,
            groups,
            base,
            blocks,
            out: ptr,
            normalize: flags.normalize,
            stream: !flags.read_next && out.len() * 4 > STREAM_BYTES,
        };
        (0..tile_chunks * group_chunks)
            .into_par_iter()
            .for_each(|item| {
                let (tc, gc) = (item % tile_chunks, item / tile_chunks);
                let tiles = tc * CHUNK_TILES..((tc + 1) * CHUNK_TILES).min(self.tiles);
                let gs = gc * groups_per_chunk..((gc + 1) * groups_per_chunk).min(groups.len());
                match self.isa {
                    #[cfg(target_arch = "x86_64")]
                    // SAFETY: `Isa::Avx512` is only chosen when the CPU has AVX-512F.
                    Isa::Avx512 => unsafe { blend_tiles_avx512(&ctx, tiles, gs) },
                    #[cfg(target_arch = "x86_64")]
                    // SAFETY: `Isa::Avx2Fma` is only chosen when the CPU has AVX2, FMA and F16C.
                    Isa::Avx2Fma => unsafe { blend_tiles_avx2(&ctx, tiles, gs) },
                    // SAFETY: the portable kernel needs no CPU feature.
                    _ => unsafe { blend_tiles::<Portable, 4>(&ctx, tiles, gs) },
                }
            });
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

/// How a blend pass treats its output.
#[derive(Clone, Copy)]
struct Flags {
    /// Scale each result to unit length (normal blending).
    normalize: bool,
    /// Another pass reads the output right away: keep it in cache.
    read_next: bool,
}

impl Flags {
    const POSITIONS: Flags = Flags {
        normalize: false,
        read_next: false,
    };
    const NORMALS: Flags = Flags {
        normalize: true,
        read_next: false,
    };
}

/// Everything a kernel invocation reads.
struct Ctx<'a> {
    rig: &'a CpuRig,
    groups: &'a Groups,
    base: &'a [Block],
    blocks: &'a TileBlocks,
    out: OutPtr,
    normalize: bool,
    stream: bool,
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn blend_tiles_avx512(
    ctx: &Ctx<'_>,
    tiles: std::ops::Range<usize>,
    groups: std::ops::Range<usize>,
) {
    // SAFETY: this function is only called when AVX-512F is present.
    unsafe { blend_tiles::<simd::Avx512, 8>(ctx, tiles, groups) }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,f16c")]
unsafe fn blend_tiles_avx2(
    ctx: &Ctx<'_>,
    tiles: std::ops::Range<usize>,
    groups: std::ops::Range<usize>,
) {
    // SAFETY: this function is only called when AVX2, FMA and F16C are present.
    unsafe { blend_tiles::<simd::Avx2, 2>(ctx, tiles, groups) }
}

/// The blend kernel over a range of tiles and job groups, `Q` jobs of a group at a time.
///
/// # Safety
/// `L`'s CPU features must be present and `Q` must divide [`GROUP`]. Concurrent calls must
/// cover disjoint tile ranges or disjoint group ranges, so that no output component is written
/// twice.
#[inline(always)]
unsafe fn blend_tiles<L: Lanes, const Q: usize>(
    ctx: &Ctx<'_>,
    tiles: std::ops::Range<usize>,
    groups: std::ops::Range<usize>,
) {
    let rig = ctx.rig;
    let slots = rig.slots;
    let stride = rig.vertices * 3;
    let blocks = ctx.blocks;
    // Groups outside, tiles inside: only Q output streams are being written at a time, which
    // the hardware prefetchers follow; the chunk's delta blocks stay in L2 between groups.
    // Each job's part of the chunk is staged in L1 and then copied out with streaming stores.
    let mut stage = Stage([[0.0; STAGE]; GROUP]);
    let first_vertex = tiles.start * LANES;
    let chunk_floats = (tiles.end * LANES)
        .min(rig.vertices)
        .saturating_sub(first_vertex)
        * 3;
    for g in groups {
        let weights = &ctx.groups.weights[g * slots * GROUP..(g + 1) * slots * GROUP];
        let active = &ctx.groups.active[g * slots..(g + 1) * slots];
        let end = ctx.groups.end[g] as usize;
        let jobs = &ctx.groups.jobs[g];
        for sub in (0..GROUP).step_by(Q) {
            if jobs[sub] == u32::MAX {
                break;
            }
            for (t, tile) in tiles.clone().enumerate() {
                let base = &ctx.base[tile];
                let first = blocks.tile_start[tile] as usize;
                let last = blocks.tile_start[tile + 1] as usize;
                let tile_slots = &blocks.slot[first..last];
                let tile_data = &blocks.data[first..last];
                let n_valid = (rig.vertices - tile * LANES).min(LANES);
                // SAFETY (whole block): `L`'s features are present (caller); `Block` is 64-byte
                // aligned, so its x, y, z arrays are too; the stage holds CHUNK_TILES tiles.
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
                    for (a, st) in acc.iter().zip(stage.0.iter_mut()) {
                        let dst = st.as_mut_ptr().add(t * LANES * 3);
                        L::store_xyz(a[0], a[1], a[2], dst, n_valid);
                    }
                }
            }
            for (q, &job) in jobs[sub..sub + Q].iter().enumerate() {
                if job == u32::MAX {
                    continue;
                }
                let staged = &mut stage.0[q][..chunk_floats];
                if ctx.normalize {
                    normalize_in_place(staged);
                }
                // SAFETY: the job's range of this chunk is inside the output and written by this
                // invocation only; the stage is a separate buffer.
                unsafe {
                    let at = job as usize * stride + first_vertex * 3;
                    match ctx.out {
                        OutPtr::F32(p) if ctx.stream => {
                            L::copy_out(p.add(at), staged.as_ptr(), chunk_floats)
                        }
                        OutPtr::F32(p) => {
                            std::ptr::copy_nonoverlapping(staged.as_ptr(), p.add(at), chunk_floats)
                        }
                        OutPtr::F16(p) => L::copy_out_f16(p.add(at), staged.as_ptr(), chunk_floats),
                    }
                }
            }
        }
    }
    // SAFETY: `L`'s features are present (caller).
    unsafe { L::fence() };
}

/// Floats of one job's part of a chunk.
const STAGE: usize = CHUNK_TILES * LANES * 3;

/// Per-job staging of a chunk's output, aligned for vector stores.
#[repr(C, align(64))]
struct Stage([[f32; STAGE]; GROUP]);

/// Scales each xyz triple to unit length (zero stays zero).
#[inline(never)]
fn normalize_in_place(v: &mut [f32]) {
    for n in v.chunks_exact_mut(3) {
        let len2 = n[0] * n[0] + n[1] * n[1] + n[2] * n[2];
        let inv = if len2 > 0.0 { len2.sqrt().recip() } else { 0.0 };
        n[0] *= inv;
        n[1] *= inv;
        n[2] *= inv;
    }
}

/// Takes the f32 buffer out of `data` (reusing its allocation) and sizes it to `len`.
fn take_f32(data: &mut VertexData, len: usize) -> Vec<f32> {
    let mut v = match std::mem::take(data) {
        VertexData::F32(v) => v,
        VertexData::F16(_) => Vec::new(),
    };
    v.resize(len, 0.0);
    v
}

/// Takes the f16 buffer out of `data` (reusing its allocation) and sizes it to `len`.
fn take_f16(data: &mut VertexData, len: usize) -> Vec<f16> {
    let mut v = match std::mem::take(data) {
        VertexData::F16(v) => v,
        VertexData::F32(_) => Vec::new(),
    };
    v.resize(len, f16::ZERO);
    v
}

fn finish(v: Vec<f32>, precision: Precision) -> VertexData {
    match precision {
        Precision::F32 => VertexData::F32(v),
        Precision::F16 => VertexData::F16(pack_f16(&v)),
    }
}

/// The `pack_f16` pass: round to nearest binary16, in parallel.
pub fn pack_f16(v: &[f32]) -> Vec<f16> {
    use half::slice::HalfFloatSliceExt;
    let mut out = vec![f16::ZERO; v.len()];
    out.par_chunks_mut(1 << 16)
        .zip(v.par_chunks(1 << 16))
        .for_each(|(o, i)| o.convert_from_f32_slice(i));
    out
}
