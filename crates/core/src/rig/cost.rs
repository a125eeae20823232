//! What a rig costs in memory, from its sizes alone: the model every budget check uses.
//!
//! A [`RigShape`] holds the counts that decide the cost (vertices, indices, stored deltas, clip
//! table cells, mesh levels). It can be read from a glTF file's headers before anything is
//! decoded (every delta counted as stored, an upper bound) or from a rig in memory (exact
//! counts). [`RigShape::cost`] turns it into bytes: the rig's own arrays, the CPU engine's
//! layout, the GPU copies, the transient peak of preparing it, and the stored file. The
//! formulas mirror the data structures they bound (`Rig`, `CpuRig`, `GpuRig`, the store's
//! record) and are upper bounds of the arrays, not of allocator overhead; the hostile-input
//! tests compare them with the process's measured peak.

use serde::Serialize;

use super::{Primitive, Rig};

/// Vertices per CPU engine tile.
const CPU_LANES: u64 = 16;
/// Bytes of one CPU delta block (16 lanes × xyz × f32) with its slot index: what the CPU
/// engine's layout spends per block (`CpuRig::blocks` counts them).
pub const CPU_BLOCK: u64 = 16 * 12 + 2;
/// Vertices per GPU tile (one workgroup), and bytes of one GPU delta block.
const GPU_LANES: u64 = 64;
const GPU_BLOCK: u64 = 64 * 12;
/// Bytes of one staging entry while the CPU layout is built (tile, slot, lane, delta).
const LAYOUT_ENTRY: u64 = 24;

/// The counts of one primitive that decide its cost.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct PrimShape {
    /// Vertices.
    pub vertices: u64,
    /// Triangle-list indices.
    pub indices: u64,
    /// Whether it has tangents.
    pub tangents: bool,
    /// Bytes per vertex of its appearance arrays ([`super::VertexLook`]: 8 per texture
    /// coordinate set, 16 for colours).
    pub look: u64,
    /// Morph targets it has.
    pub targets: u64,
    /// Stored position deltas over its targets (an upper bound: `targets × vertices`).
    pub deltas: u64,
    /// Stored normal deltas.
    pub normal_deltas: u64,
    /// Stored tangent deltas.
    pub tangent_deltas: u64,
    /// Delta blocks of the CPU engine's 16-vertex tiles of consecutive vertices (position and
    /// normal deltas): a bound of the engine's layout, whose regrouping only removes blocks.
    pub cpu_blocks: u64,
    /// Delta blocks of the GPU engine's 64-vertex tiles (position and normal deltas).
    pub gpu_blocks: u64,
}

/// Bytes per vertex of a primitive's [`super::VertexLook`] arrays.
fn look_per_vertex(l: &super::VertexLook) -> u64 {
    let set = |a: bool| if a { 8 } else { 0 };
    set(l.uv0.is_some()) + set(l.uv1.is_some()) + if l.colors.is_some() { 16 } else { 0 }
}

/// Distinct tiles of `lanes` vertices that `vertices` (ascending, offset by `first`) touch.
fn tiles_touched(vertices: &[u32], first: u64, lanes: u64) -> u64 {
    let mut n = 0;
    let mut last = u64::MAX;
    for &v in vertices {
        let t = (first + u64::from(v)) / lanes;
        if t != last {
            n += 1;
            last = t;
        }
    }
    n
}

impl PrimShape {
    /// Counts from a file's headers, before decoding: every target is taken to move every
    /// vertex (the most a sparse target can store), and each delta block to hold one delta
    /// unless a target has more deltas than tiles.
    #[allow(clippy::too_many_arguments)]
    pub fn upper_bound(
        vertices: u64,
        indices: u64,
        tangents: bool,
        look: u64,
        targets: u64,
        normal_targets: u64,
        tangent_targets: u64,
    ) -> PrimShape {
        let bound = |lanes: u64, with: u64| with.saturating_mul(vertices.div_ceil(lanes) + 1);
        PrimShape {
            vertices,
            indices,
            tangents,
            look,
            targets,
            deltas: targets.saturating_mul(vertices),
            normal_deltas: normal_targets.saturating_mul(vertices),
            tangent_deltas: tangent_targets.saturating_mul(vertices),
            cpu_blocks: bound(CPU_LANES, targets) + bound(CPU_LANES, normal_targets),
            gpu_blocks: bound(GPU_LANES, targets) + bound(GPU_LANES, normal_targets),
        }
    }

    /// The exact counts of a primitive in memory whose first vertex is `first` in the rig's
    /// evaluation order (tiles are counted over the concatenated vertices).
    pub fn of(p: &Primitive, first: u64) -> PrimShape {
        let blocks = |lanes: u64| -> u64 {
            p.targets
                .iter()
                .map(|t| {
                    let n = tiles_touched(&t.vertices, first, lanes);
                    if t.normals.is_some() { 2 * n } else { n }
                })
                .sum()
        };
        PrimShape {
            cpu_blocks: blocks(CPU_LANES),
            gpu_blocks: blocks(GPU_LANES),
            vertices: p.positions.len() as u64,
            indices: p.indices.len() as u64,
            tangents: p.tangents.is_some(),
            look: look_per_vertex(&p.look),
            targets: p.targets.len() as u64,
            deltas: p.targets.iter().map(|t| t.vertices.len() as u64).sum(),
            normal_deltas: p
                .targets
                .iter()
                .filter_map(|t| t.normals.as_ref())
                .map(|n| n.len() as u64)
                .sum(),
            tangent_deltas: p
                .targets
                .iter()
                .filter_map(|t| t.tangents.as_ref())
                .map(|n| n.len() as u64)
                .sum(),
        }
    }

    /// Bytes of the primitive's arrays in a [`Rig`].
    pub fn rig_bytes(&self) -> u64 {
        let base = self.vertices * (12 + 12 + if self.tangents { 16 } else { 0 } + self.look);
        base + self.indices * 4
            + self.deltas * (4 + 12)
            + self.normal_deltas * 12
            + self.tangent_deltas * 12
    }
}

/// The counts of a whole rig that decide its cost.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize)]
pub struct RigShape {
    /// The primitives.
    pub primitives: Vec<PrimShape>,
    /// Rig-wide targets.
    pub targets: u64,
    /// Clip table cells over all clips (targets × frames each).
    pub clip_cells: u64,
    /// The shapes of the rig's mesh levels (derived rigs; they share the clip tables).
    pub mesh_levels: Vec<Vec<PrimShape>>,
    /// The shapes of the rigs of its PCA levels (`DeltaPca::derive_rig`), with their clip
    /// table cells (the clips in coefficients) and the bytes of the form itself.
    pub pca_levels: Vec<(Vec<PrimShape>, u64, u64)>,
    /// On a skinned rig, what its skeleton adds (zero otherwise).
    pub skin: SkinShape,
    /// Bytes of its [`super::Appearance`]: encoded images, their decoded mip chains and the
    /// tables (shared by its levels; zero without one).
    pub appearance: u64,
}

/// What a skinned rig adds to its cost: the influences (24 bytes a vertex: four bone ids and
/// weights, in the rig, and as six words on the GPU), the skeleton and joint tables, and the
/// CPU engine's per-tile bone entries (a 64-byte weight row and a bone id each).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct SkinShape {
    /// Vertices that carry influences (every vertex of a skinned rig), in the full mesh and in
    /// every mesh level and PCA level (each derived rig has its own copy).
    pub vertices: u64,
    /// The CPU layout's bone entries over the full mesh and its levels (at most four per
    /// vertex; exact for the full mesh, bounded for levels).
    pub tile_entries: u64,
    /// Bytes of the skeleton and of every clip's joint table.
    pub joints: u64,
}

/// Bytes a rig costs, by where they live and when.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct RigCost {
    /// The rig's own arrays: geometry, sparse deltas, clip tables, LOD.
    pub rig: u64,
    /// The CPU engine's layouts (the full mesh and every mesh level); kept on every backend,
    /// since the CPU engine is the fallback.
    pub layout: u64,
    /// Resident on the GPU (0 without one).
    pub device: u64,
    /// Most transient host memory while preparing (layout staging, GPU upload copies) or
    /// checking and persisting the rig, beyond the resident bytes.
    pub transient: u64,
    /// The stored file.
    pub stored: u64,
}

impl RigCost {
    /// Host bytes resident once the rig is prepared.
    pub fn resident(&self) -> u64 {
        self.rig + self.layout
    }

    /// Most host bytes held at once while the rig is prepared and persisted.
    pub fn peak(&self) -> u64 {
        self.resident() + self.transient
    }
}

impl RigShape {
    /// The exact counts of a rig in memory (with its mesh levels, when they exist).
    pub fn of(rig: &Rig) -> RigShape {
        let shapes = |r: &Rig| -> Vec<PrimShape> {
            let offsets = r.vertex_offsets();
            r.primitives
                .iter()
                .zip(offsets)
                .map(|(p, first)| PrimShape::of(p, first as u64))
                .collect()
        };
        RigShape {
            appearance: rig.appearance.as_ref().map_or(0, |a| {
                a.bytes() as u64 + a.decoded_bytes()
                    - a.images
                        .iter()
                        .filter_map(|i| i.pixels.as_ref())
                        .map(|p| p.bytes() as u64)
                        .sum::<u64>()
            }),
            skin: SkinShape::of(rig),
            primitives: shapes(rig),
            targets: rig.targets.len() as u64,
            clip_cells: rig.clips.iter().map(|c| c.weights.len() as u64).sum(),
            mesh_levels: rig
                .lod
                .meshes
                .iter()
                .map(|level| Self::level_shapes(rig, level))
                .collect(),
            pca_levels: rig
                .lod
                .pca
                .iter()
                .map(|form| Self::pca_shapes(rig, form))
                .collect(),
        }
    }

    /// The counts of the rig a PCA level derives, counted in place: each component a target
    /// over its region's consecutive vertices, no normal deltas.
    fn pca_shapes(rig: &Rig, form: &super::DeltaPca) -> (Vec<PrimShape>, u64, u64) {
        let offsets = rig.vertex_offsets();
        let prims = rig
            .primitives
            .iter()
            .zip(&offsets)
            .map(|(p, &first)| {
                let end = first + p.positions.len();
                let mut shape = PrimShape {
                    vertices: p.positions.len() as u64,
                    indices: p.indices.len() as u64,
                    tangents: p.tangents.is_some(),
                    look: look_per_vertex(&p.look),
                    ..PrimShape::default()
                };
                for r in form
                    .regions
                    .iter()
                    .filter(|r| (first..end).contains(&(r.first as usize)))
                {
                    let (c, n) = (u64::from(r.components), u64::from(r.count));
                    let tiles = |lanes: u64| {
                        let a = u64::from(r.first) / lanes;
                        let b = (u64::from(r.first) + n).div_ceil(lanes);
                        b - a
                    };
                    shape.targets += c;
                    shape.deltas += c * n;
                    shape.cpu_blocks += c * tiles(CPU_LANES);
                    shape.gpu_blocks += c * tiles(GPU_LANES);
                }
                shape
            })
            .collect();
        let frames: u64 = rig.clips.iter().map(|c| u64::from(c.frames)).sum();
        (
            prims,
            frames * form.components() as u64,
            form.bytes() as u64,
        )
    }

    /// The counts of the rig a mesh level derives (`MeshLevel::derive_rig`), counted in place:
    /// deriving the rigs would copy every level's geometry just to measure it, doubling the
    /// memory the estimate is meant to bound.
    fn level_shapes(rig: &Rig, level: &super::MeshLevel) -> Vec<PrimShape> {
        let mut first = 0u64;
        let mut out = Vec::with_capacity(rig.primitives.len());
        for (p, l) in rig.primitives.iter().zip(&level.primitives) {
            // New index of each kept vertex (u32::MAX: dropped), as derive_rig renumbers them.
            let mut remap = vec![u32::MAX; p.positions.len()];
            for (new, &old) in l.vertices.iter().enumerate() {
                if let Some(r) = remap.get_mut(old as usize) {
                    *r = new as u32;
                }
            }
            let mut shape = PrimShape {
                vertices: l.vertices.len() as u64,
                indices: l.indices.len() as u64,
                tangents: p.tangents.is_some(),
                look: look_per_vertex(&p.look),
                ..PrimShape::default()
            };
            let mut kept = Vec::new();
            for t in &p.targets {
                kept.clear();
                kept.extend(
                    t.vertices
                        .iter()
                        .filter_map(|&v| remap.get(v as usize).copied())
                        .filter(|&r| r != u32::MAX),
                );
                if kept.is_empty() {
                    continue;
                }
                let m = kept.len() as u64;
                shape.targets += 1;
                shape.deltas += m;
                let blocks = |lanes| {
                    let n = tiles_touched(&kept, first, lanes);
                    if t.normals.is_some() { 2 * n } else { n }
                };
                shape.cpu_blocks += blocks(CPU_LANES);
                shape.gpu_blocks += blocks(GPU_LANES);
                if t.normals.is_some() {
                    shape.normal_deltas += m;
                }
                if t.tangents.is_some() {
                    shape.tangent_deltas += m;
                }
            }
            first += shape.vertices;
            out.push(shape);
        }
        out
    }

    /// Vertices over all primitives.
    pub fn vertices(&self) -> u64 {
        self.primitives.iter().map(|p| p.vertices).sum()
    }

    /// CPU layout bytes and staging bytes of one (full or mesh level) rig.
    fn cpu_layout(prims: &[PrimShape]) -> (u64, u64) {
        let vertices: u64 = prims.iter().map(|p| p.vertices).sum();
        let tiles = vertices.div_ceil(CPU_LANES);
        // Base blocks, tile starts, and each vertex's lane in its chunk with a flag per chunk.
        let base = 2 * tiles * CPU_BLOCK + (tiles + 1) * 4 * 2 + tiles * CPU_LANES * 2 + tiles;
        let blocks: u64 = prims.iter().map(|p| p.cpu_blocks * CPU_BLOCK).sum();
        // Normals recomputed from triangles: triangles, incident lists, vertex lists.
        let topology: u64 = prims
            .iter()
            .filter(|p| p.normal_deltas == 0)
            .map(|p| p.indices * 4 + p.indices * 4 + (2 * p.vertices + 1) * 4)
            .sum();
        let staging: u64 = prims
            .iter()
            .map(|p| (p.deltas + p.normal_deltas) * LAYOUT_ENTRY)
            .sum();
        (base + blocks + topology, staging)
    }

    /// GPU geometry bytes of one (full or mesh level) rig: 64-vertex tiles of base and delta
    /// blocks with per-tile slot masks, and the topology of recomputed normals.
    fn gpu_geometry(prims: &[PrimShape], targets: u64) -> u64 {
        let vertices: u64 = prims.iter().map(|p| p.vertices).sum();
        let tiles = vertices.div_ceil(GPU_LANES) + 1;
        let words = targets.div_ceil(32).max(1);
        let attributes = if prims.iter().any(|p| p.normal_deltas > 0) {
            2
        } else {
            1
        };
        let base = attributes * tiles * (GPU_BLOCK + words * 8);
        let blocks: u64 = prims.iter().map(|p| p.gpu_blocks * GPU_BLOCK).sum();
        let topology: u64 = prims
            .iter()
            .map(|p| p.indices * 8 + (2 * p.vertices + 1) * 4)
            .sum();
        base + blocks + topology + targets * 4
    }

    /// What the rig costs, on a GPU or not.
    pub fn cost(&self, gpu: bool) -> RigCost {
        let mut cost = self.cost_unskinned(gpu);
        let s = &self.skin;
        cost.rig += s.vertices * 24 + s.joints;
        cost.layout += s.tile_entries * (64 + 2) + s.vertices.div_ceil(16) * 4;
        if gpu {
            cost.device += s.vertices * 24;
        }
        cost.stored += s.vertices * 30 + s.joints;
        cost
    }

    fn cost_unskinned(&self, gpu: bool) -> RigCost {
        let geometry = |prims: &[PrimShape]| prims.iter().map(PrimShape::rig_bytes).sum::<u64>();
        let clips = self.clip_cells * 4;
        let lod = self.targets * 4
            + 64 * 8
            + self
                .mesh_levels
                .iter()
                .flatten()
                .map(|p| p.vertices * 4 + p.indices * 4)
                .sum::<u64>();
        let pca_clips: u64 = self.pca_levels.iter().map(|l| l.1 * 4).sum();
        let lod = lod + self.pca_levels.iter().map(|l| l.2).sum::<u64>();
        let rig = geometry(&self.primitives)
            + self.appearance
            + self.mesh_levels.iter().map(|l| geometry(l)).sum::<u64>()
            + self.pca_levels.iter().map(|l| geometry(&l.0)).sum::<u64>()
            + clips
            + pca_clips
            + lod;
        let (mut layout, mut staging) = Self::cpu_layout(&self.primitives);
        for level in self
            .mesh_levels
            .iter()
            .chain(self.pca_levels.iter().map(|l| &l.0))
        {
            let (l, s) = Self::cpu_layout(level);
            layout += l;
            staging = staging.max(s);
        }
        let device = if gpu {
            Self::gpu_geometry(&self.primitives, self.targets)
                + self
                    .mesh_levels
                    .iter()
                    .map(|l| Self::gpu_geometry(l, self.targets))
                    .sum::<u64>()
                + self
                    .pca_levels
                    .iter()
                    .map(|l| Self::gpu_geometry(&l.0, l.0.iter().map(|p| p.targets).sum()))
                    .sum::<u64>()
                + clips
                + pca_clips
        } else {
            0
        };
        // The GPU upload builds each chunk host-side and queues a copy of it.
        let upload = if gpu { 2 * device } else { 0 };
        // The stored record: bincode writes f32 in 4 bytes and integers in at most 5 (varint),
        // so never more than 5/4 of the arrays, plus names and headers.
        let stored =
            geometry(&self.primitives) * 5 / 4 + self.appearance + clips + lod * 5 / 4 + 64 * 1024;
        // The server's range check keeps per-vertex f64 bounds (two DVec3 per vertex); the
        // store encodes records straight into the file through a 1 MiB buffer.
        let range_check = 48 * self.vertices();
        RigCost {
            rig,
            layout,
            device,
            transient: staging.max(upload).max(range_check).max(1 << 20),
            stored,
        }
    }
}

impl SkinShape {
    /// The exact counts of `rig` (zero without a skeleton).
    pub fn of(rig: &Rig) -> SkinShape {
        let Some(sk) = &rig.skeleton else {
            return SkinShape::default();
        };
        let full = rig.vertex_count() as u64;
        let levels: u64 = rig
            .lod
            .meshes
            .iter()
            .map(|m| m.vertex_count() as u64)
            .sum::<u64>()
            + rig.lod.pca.len() as u64 * full;
        // The full mesh's entries, counted as `SkinTiles` builds them: per tile of sixteen
        // consecutive vertices, its distinct bones (and one entry for vertices that follow
        // none).
        let mut entries = 0u64;
        let mut tile: Vec<u16> = Vec::with_capacity(64);
        let mut at = 0;
        super::for_each_influence(rig, |v, bone, _| {
            if v / 16 != at {
                entries += tile.len() as u64;
                tile.clear();
                at = v / 16;
            }
            if !tile.contains(&bone) {
                tile.push(bone);
            }
        });
        entries += tile.len() as u64;
        let joints = sk.bytes()
            + rig
                .clips
                .iter()
                .filter_map(|c| c.joints.as_deref())
                .map(|t| t.bytes())
                .sum::<u64>();
        SkinShape {
            vertices: full + levels,
            tile_entries: entries + 4 * levels,
            joints,
        }
    }
}
