//! The upload: a rig made resident on the device ([`GpuRig`]: delta blocks in chunks of whole
//! tiles, neutral mesh, LOD order, the topology of recomputed normals, a skinned rig's
//! influences) with its clip tables ([`ClipTables`], shared by the rig's mesh levels), the
//! checks that a rig fits the device ([`GpuRig::check_fits`]), and a job's record for a batch
//! ([`GpuRig::job`]).
//!
//! Invariants: everything a rig holds on the device is charged to the memory budget before any
//! buffer is made, and a rig the device cannot hold is refused (`DoesNotFit`) before anything
//! is uploaded, not in the middle of a batch; versions of a rig with new clips share its
//! geometry's buffers and charge.

use std::sync::Arc;

use super::GpuError;
use super::context::GpuContext;
use super::device::padded;
use super::layout::{
    self, Attribute, DeltaFormat, GpuJob, GpuTerm, NO_LIVE, build_chunks, pack_influences,
};
use crate::cpu::NormalTopology;
use crate::{BlendJob, OutputSpec, Precision};
use crowdmorph_core::budget::Charge;
use crowdmorph_core::rig::{BoneMatrix, LIVE_STEP, Pose, Rig};

/// One chunk of a resident rig.
pub(super) struct GpuChunk {
    pub(super) tile_begin: u32,
    pub(super) tiles: u32,
    pub(super) base: wgpu::Buffer,
    pub(super) blocks: wgpu::Buffer,
    pub(super) masks: wgpu::Buffer,
}

/// The topology of a rig's recomputed normals on the device: its triangles, the vertices
/// recomputed, and each one's incident triangles (CSR).
pub(super) struct GpuTopology {
    pub(super) triangles: wgpu::Buffer,
    pub(super) recomputed: wgpu::Buffer,
    pub(super) incident_start: wgpu::Buffer,
    pub(super) incident: wgpu::Buffer,
    pub(super) n_triangles: u32,
    pub(super) n_recomputed: u32,
}

/// A skinned rig's influences on the device.
pub(super) struct GpuSkin {
    /// [`layout::INFLUENCE_WORDS`] words per vertex.
    pub(super) influences: wgpu::Buffer,
    /// Bones of the rig: matrices per job in a batch.
    pub(super) bones: u32,
}

/// A rig resident on the GPU.
pub struct GpuRig {
    pub(super) vertices: u32,
    /// How its delta blocks are stored (both attributes alike).
    pub(super) deltas: DeltaFormat,
    pub(super) slots: u32,
    pub(super) words: u32,
    pub(super) positions: Vec<GpuChunk>,
    /// Empty when every vertex's normal is recomputed from positions.
    pub(super) normals: Vec<GpuChunk>,
    pub(super) order: wgpu::Buffer,
    /// The clip tables, shared by every mesh level of the rig.
    pub(super) tables: Arc<ClipTables>,
    pub(super) topology: Option<GpuTopology>,
    /// On a skinned rig, every vertex's bones for the `skin` pass.
    pub(super) skin: Option<GpuSkin>,
    /// LOD shape counts per level.
    lod_shapes: Vec<u32>,
    geometry_bytes: u64,
    /// The geometry's bytes in the device's memory budget, shared by the versions of the rig
    /// that share the geometry (new clips); given back when the last one is dropped.
    charge: Arc<Charge>,
}

/// A rig's clip tables resident on the device: every clip's `targets × frames` table, one
/// after another in one storage buffer. A rig's mesh levels evaluate the same clips, so they
/// share this buffer instead of holding copies (a clip table is often the largest array a rig
/// has).
pub struct ClipTables {
    pub(super) buffer: wgpu::Buffer,
    /// (offset in `buffer`, in f32, and frames) per clip.
    clips: Vec<(u32, u32)>,
    bytes: u64,
    /// Its bytes in the device's memory budget.
    _charge: Charge,
}

impl std::fmt::Debug for ClipTables {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ClipTables")
            .field("clips", &self.clips.len())
            .field("bytes", &self.bytes)
            .finish()
    }
}

impl ClipTables {
    /// Uploads every clip table of `rig`, each written in place (no concatenated host copy).
    pub fn upload(ctx: &GpuContext, rig: &Rig) -> Result<Arc<ClipTables>, GpuError> {
        ctx.health()?;
        let total: u64 = rig.clips.iter().map(|c| c.weights.len() as u64 * 4).sum();
        if total > ctx.max_binding {
            return Err(GpuError::DoesNotFit(format!(
                "clip tables of {total} bytes exceed one storage binding of {} bytes",
                ctx.max_binding
            )));
        }
        let storage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST;
        let charge = ctx.charge(padded(total), || {
            format!("{} clip tables ({total} bytes) on the GPU", rig.clips.len())
        })?;
        let buffer = ctx.buffer("tables", total, storage);
        let mut clips = Vec::with_capacity(rig.clips.len());
        let mut at = 0u64;
        for c in &rig.clips {
            clips.push(((at / 4) as u32, c.frames));
            if !c.weights.is_empty() {
                ctx.queue
                    .write_buffer(&buffer, at, bytemuck::cast_slice(&c.weights[..]));
            }
            at += c.weights.len() as u64 * 4;
        }
        Ok(Arc::new(ClipTables {
            bytes: buffer.size(),
            buffer,
            clips,
            _charge: charge,
        }))
    }

    /// Bytes resident on the device.
    pub fn bytes(&self) -> u64 {
        self.bytes
    }
}

impl std::fmt::Debug for GpuRig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuRig")
            .field("vertices", &self.vertices)
            .field("chunks", &self.positions.len())
            .field("device_bytes", &self.device_bytes())
            .finish()
    }
}

impl GpuRig {
    /// Whether `blend_packed` writes a batch's output in `spec`'s 16-bit format (q16r's planes
    /// too) itself: where nothing reads f32 positions after the blend, that is no skin and no
    /// normals (recomputed from them, or blended by a second dispatch whose output the pack
    /// pass would then read). Its slot then needs no f32 output buffer.
    pub(super) fn blend_packs(&self, spec: OutputSpec) -> bool {
        matches!(spec.precision, Precision::Q16(_) | Precision::F16)
            && !spec.normals
            && self.skin.is_none()
    }

    /// Refuses (`DoesNotFit`) a rig with more vertices than one job's output binding holds,
    /// before anything is uploaded. It costs nothing; [`GpuRig::upload`] also checks the
    /// triangles of recomputed normals, once it has built their topology.
    pub fn check_fits(ctx: &GpuContext, rig: &Rig) -> Result<(), GpuError> {
        ctx.health()?;
        let vertices = rig.vertex_count();
        let per_job = (vertices * 3 * 4) as u64;
        if per_job > ctx.max_binding {
            return Err(GpuError::DoesNotFit(format!(
                "{vertices} vertices: one job's output ({per_job} bytes) exceeds the {}-byte \
                 storage binding",
                ctx.max_binding
            )));
        }
        let bones = rig.skeleton.as_ref().map_or(0, |s| s.bones.len()) as u64;
        let bone_bytes = bones * size_of::<BoneMatrix>() as u64;
        if bone_bytes > ctx.max_binding
            || (vertices * layout::INFLUENCE_WORDS * 4) as u64 > ctx.max_binding
        {
            return Err(GpuError::DoesNotFit(format!(
                "{bones} bones: one job's bone matrices or the influences exceed the \
                 {}-byte storage binding",
                ctx.max_binding
            )));
        }
        Ok(())
    }

    fn fits(ctx: &GpuContext, rig: &Rig, topology: &NormalTopology) -> Result<(), GpuError> {
        Self::check_fits(ctx, rig)?;
        let vertices = rig.vertex_count();
        let tri_bytes = topology.triangles.len() as u64 * 12;
        if tri_bytes > ctx.max_binding
            || topology.triangles.len() > 65_535 * 64
            || topology.vertices.len() > 65_535 * 64
            || vertices > 65_535 * 64 * 65_535
        {
            return Err(GpuError::DoesNotFit(format!(
                "{} triangles of recomputed normals exceed the device's dispatch or binding limits",
                topology.triangles.len()
            )));
        }
        Ok(())
    }

    /// Uploads everything a batch of this rig reads, with clip tables `tables` (uploaded with
    /// [`ClipTables::upload`], and shared with the rig's other mesh levels). Refuses
    /// (`DoesNotFit`) rigs the device cannot hold, instead of failing later in the middle of a
    /// batch.
    pub fn upload(
        ctx: &GpuContext,
        rig: &Rig,
        tables: Arc<ClipTables>,
    ) -> Result<GpuRig, GpuError> {
        let vertices = rig.vertex_count();
        let topology = NormalTopology::of(rig);
        Self::fits(ctx, rig, &topology)?;
        if tables.clips.len() != rig.clips.len() {
            return Err(GpuError::DoesNotFit(format!(
                "{} clip tables for a rig with {} clips",
                tables.clips.len(),
                rig.clips.len()
            )));
        }
        // Laid out on the host first, so that everything the device will hold is charged to
        // its memory budget before any buffer is created.
        let deltas = if ctx.deltas.holds(rig) {
            ctx.deltas
        } else {
            tracing::warn!(
                rig = %rig.name,
                "a delta exceeds binary16's range (65,504): this rig keeps f32 deltas on the GPU"
            );
            DeltaFormat::F32
        };
        let position_chunks = build_chunks(rig, Attribute::Positions, ctx.max_chunk, deltas);
        let normal_chunks = if topology.vertices.len() < vertices {
            build_chunks(rig, Attribute::Normals, ctx.max_chunk, deltas)
        } else {
            Vec::new()
        };
        let chunk_bytes: u64 = position_chunks
            .iter()
            .chain(&normal_chunks)
            .map(|c| {
                GpuContext::init_bytes(&c.base)
                    + GpuContext::init_bytes(&c.blocks)
                    + GpuContext::init_bytes(&c.masks)
            })
            .sum();
        let topology_bytes = if topology.vertices.is_empty() {
            0
        } else {
            GpuContext::init_bytes(&topology.triangles)
                + GpuContext::init_bytes(&topology.vertices)
                + GpuContext::init_bytes(&topology.incident_start)
                + GpuContext::init_bytes(&topology.incident)
        };
        let influences = rig.is_skinned().then(|| pack_influences(rig));
        let skin_bytes = influences.as_deref().map_or(0, GpuContext::init_bytes);
        let charge = Arc::new(ctx.charge(
            chunk_bytes + topology_bytes + skin_bytes + GpuContext::init_bytes(&rig.lod.order),
            || {
                format!(
                    "a rig of {vertices} vertices and {} targets on the GPU",
                    rig.targets.len()
                )
            },
        )?);
        let scope = ctx.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let storage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST;
        let upload_chunks = |chunks: Vec<layout::Chunk>| -> Vec<GpuChunk> {
            chunks
                .into_iter()
                .map(|c| GpuChunk {
                    tile_begin: c.tile_begin,
                    tiles: c.tiles,
                    base: ctx.init("base", bytemuck::cast_slice(&c.base), storage),
                    blocks: ctx.init("blocks", bytemuck::cast_slice(&c.blocks), storage),
                    masks: ctx.init("masks", bytemuck::cast_slice(&c.masks), storage),
                })
                .collect()
        };
        let positions = upload_chunks(position_chunks);
        let normals = upload_chunks(normal_chunks);
        let order: Vec<u32> = rig.lod.order.clone();
        let topo = (!topology.vertices.is_empty()).then(|| GpuTopology {
            triangles: ctx.init(
                "triangles",
                bytemuck::cast_slice(&topology.triangles),
                storage,
            ),
            recomputed: ctx.init(
                "recomputed",
                bytemuck::cast_slice(&topology.vertices),
                storage,
            ),
            incident_start: ctx.init(
                "incident_start",
                bytemuck::cast_slice(&topology.incident_start),
                storage,
            ),
            incident: ctx.init(
                "incident",
                bytemuck::cast_slice(&topology.incident),
                storage,
            ),
            n_triangles: topology.triangles.len() as u32,
            n_recomputed: topology.vertices.len() as u32,
        });
        let chunk_bytes = |cs: &[GpuChunk]| -> u64 {
            cs.iter()
                .map(|c| c.base.size() + c.blocks.size() + c.masks.size())
                .sum()
        };
        let topo_bytes = topo.as_ref().map_or(0, |t| {
            t.triangles.size() + t.recomputed.size() + t.incident_start.size() + t.incident.size()
        });
        let skin = influences.map(|words| GpuSkin {
            influences: ctx.init("influences", bytemuck::cast_slice(&words), storage),
            bones: rig.skeleton.as_ref().map_or(0, |s| s.bones.len()) as u32,
        });
        let skin_bytes = skin.as_ref().map_or(0, |s| s.influences.size());
        let gpu = GpuRig {
            vertices: vertices as u32,
            deltas,
            slots: rig.targets.len() as u32,
            words: rig.targets.len().div_ceil(32).max(1) as u32,
            geometry_bytes: chunk_bytes(&positions)
                + chunk_bytes(&normals)
                + topo_bytes
                + skin_bytes
                + order.len() as u64 * 4,
            positions,
            normals,
            order: ctx.init("order", bytemuck::cast_slice(&order), storage),
            tables,
            topology: topo,
            skin,
            lod_shapes: rig.lod.levels.iter().map(|l| l.shapes).collect(),
            charge,
        };
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::OutOfMemory(e.to_string()));
        }
        ctx.health()?;
        Ok(gpu)
    }

    /// A copy of this resident rig with new clip tables (geometry and LOD order unchanged).
    pub fn with_clips(
        &self,
        ctx: &GpuContext,
        tables: Arc<ClipTables>,
    ) -> Result<GpuRig, GpuError> {
        ctx.health()?;
        Ok(GpuRig {
            vertices: self.vertices,
            deltas: self.deltas,
            slots: self.slots,
            words: self.words,
            positions: self.positions.iter().map(GpuChunk::share).collect(),
            normals: self.normals.iter().map(GpuChunk::share).collect(),
            order: self.order.clone(),
            tables,
            topology: self.topology.as_ref().map(|t| GpuTopology {
                triangles: t.triangles.clone(),
                recomputed: t.recomputed.clone(),
                incident_start: t.incident_start.clone(),
                incident: t.incident.clone(),
                n_triangles: t.n_triangles,
                n_recomputed: t.n_recomputed,
            }),
            skin: self.skin.as_ref().map(|s| GpuSkin {
                influences: s.influences.clone(),
                bones: s.bones,
            }),
            lod_shapes: self.lod_shapes.clone(),
            charge: self.charge.clone(),
            geometry_bytes: self.geometry_bytes,
        })
    }

    /// Bytes resident on the device: geometry and clip tables.
    pub fn device_bytes(&self) -> u64 {
        self.geometry_bytes + self.tables.bytes
    }

    /// Bytes of the geometry alone (what a mesh level adds: it shares the clip tables).
    pub fn geometry_bytes(&self) -> u64 {
        self.geometry_bytes
    }

    /// How its deltas are stored on the device.
    pub fn deltas(&self) -> DeltaFormat {
        self.deltas
    }

    /// The clip tables this rig reads.
    pub fn tables(&self) -> &Arc<ClipTables> {
        &self.tables
    }

    /// Storage-binding chunks the rig was split into.
    pub fn chunks(&self) -> usize {
        self.positions.len()
    }

    /// Bones per job of a skinned rig (0 otherwise): how many matrices
    /// [`GpuContext::submit`] takes per job.
    pub fn bones(&self) -> usize {
        self.skin.as_ref().map_or(0, |s| s.bones as usize)
    }

    /// The job record for `job`; `None` if its clips, frames or LOD level are out of range.
    /// Live weights are appended to `live` (one per channel, by target id) and the record
    /// points at them.
    pub fn job(&self, job: &BlendJob, live: &mut Vec<f32>) -> Option<GpuJob> {
        let shapes = *self.lod_shapes.get(job.lod as usize)?;
        let mut out = GpuJob {
            shapes,
            live: NO_LIVE,
            ..GpuJob::default()
        };
        let term = |clip: u32, frame: u32, t: f32| -> Option<GpuTerm> {
            let &(table, frames) = self.tables.clips.get(clip as usize)?;
            (frame < frames).then_some(GpuTerm {
                table,
                frames,
                frame,
                t,
            })
        };
        match &job.pose {
            &Pose::Frame { clip, frame } => {
                out.terms = 1;
                out.term[0] = term(clip, frame, 1.0)?;
            }
            Pose::Blend(terms) => {
                if terms.len() > out.term.len() {
                    return None;
                }
                out.terms = terms.len() as u32;
                for (slot, t) in out.term.iter_mut().zip(terms.iter()) {
                    *slot = term(t.clip, t.frame, t.fraction())?;
                }
            }
            Pose::Live(w) => {
                if w.len() != self.slots as usize {
                    return None;
                }
                out.live = u32::try_from(live.len()).ok()?;
                live.extend(w.iter().map(|&q| q as f32 * LIVE_STEP));
            }
        }
        Some(out)
    }
}

impl GpuChunk {
    fn share(&self) -> GpuChunk {
        GpuChunk {
            tile_begin: self.tile_begin,
            tiles: self.tiles,
            base: self.base.clone(),
            blocks: self.blocks.clone(),
            masks: self.masks.clone(),
        }
    }
}
