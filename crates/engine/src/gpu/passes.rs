//! One sub-batch's compute passes, recorded into one timed compute pass
//! ([`GpuContext::record`]). Each pass is one function named after its WGSL entry point (and
//! so after its CPU mirror, which the shader's header names): [`build_active`], [`blend`]
//! (`blend` or `blend_packed`), [`skin`], [`face_normals`] and [`vertex_normals`], [`pack`]
//! (`pack_f16`, `pack_q16` or `pack_q16r`). Each makes its uniforms and bind groups and
//! returns its dispatches; `record` runs them in that order.
//!
//! Invariants: the order is the engine's (glTF's): the blend (positions, then normal deltas),
//! the skin, the normals recomputed from the skinned positions, then the 16-bit output; a pass
//! writes only the sub-batch's jobs, from the start of the slot's outputs; where the blend
//! writes the 16-bit output itself (`GpuRig::blend_packs`) the packed positions are cleared
//! first and there is no pack pass for them.

use super::batch::Region;
use super::context::GpuContext;
use super::layout::{
    ActiveParams, BlendParams, DeltaFormat, JOBS_PER_GROUP, NormalParams, PackParams,
    Q16PackParams, SkinParams,
};
use super::rig::{GpuChunk, GpuRig, GpuTopology};
use super::slot::Slot;
use crate::{OutputSpec, Precision};

/// One dispatch of a pass: its pipeline, its bind group and its workgroups.
struct Dispatch<'p> {
    pipeline: &'p wgpu::ComputePipeline,
    group: wgpu::BindGroup,
    workgroups: [u32; 3],
}

/// What every pass of one sub-batch reads.
struct SubBatch<'a> {
    ctx: &'a GpuContext,
    rig: &'a GpuRig,
    slot: &'a Slot,
    r: &'a Region,
    spec: OutputSpec,
    /// Jobs in the sub-batch.
    jobs: u32,
    /// Its groups of eight jobs.
    groups: u32,
    /// Whether `blend_packed` writes the 16-bit output itself ([`GpuRig::blend_packs`]).
    fused: bool,
}

impl SubBatch<'_> {
    fn bind(
        &self,
        pipeline: &wgpu::ComputePipeline,
        entries: &[wgpu::BindGroupEntry<'_>],
    ) -> wgpu::BindGroup {
        self.ctx
            .device
            .create_bind_group(&wgpu::BindGroupDescriptor {
                label: None,
                layout: &pipeline.get_bind_group_layout(0),
                entries,
            })
    }
}

fn entry(binding: u32, buffer: &wgpu::Buffer) -> wgpu::BindGroupEntry<'_> {
    wgpu::BindGroupEntry {
        binding,
        resource: buffer.as_entire_binding(),
    }
}

impl GpuContext {
    /// Records one sub-batch's passes into `encoder`, inside one timed compute pass.
    pub(super) fn record(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        rig: &GpuRig,
        slot: &Slot,
        r: &Region,
        spec: OutputSpec,
        k: u32,
    ) {
        let s = SubBatch {
            ctx: self,
            rig,
            slot,
            r,
            spec,
            jobs: r.jobs as u32,
            groups: r.jobs.div_ceil(JOBS_PER_GROUP) as u32,
            fused: rig.blend_packs(spec),
        };
        // Every pass makes its uniforms and bind groups (and `pack` its clear) before the
        // compute pass begins; they are dispatched in this order.
        let active = build_active(&s);
        let blends = blend(&s);
        let skinning = skin(&s);
        let normals = match (&rig.topology, spec.normals) {
            (Some(t), true) => {
                let params = self.uniform(&NormalParams {
                    vertices: rig.vertices,
                    triangles: t.n_triangles,
                    recomputed: t.n_recomputed,
                    jobs: s.jobs,
                });
                vec![face_normals(&s, t, &params), vertex_normals(&s, t, &params)]
            }
            _ => Vec::new(),
        };
        let packs = pack(&s, encoder);

        let timestamp_writes =
            slot.queries
                .as_ref()
                .map(|(qs, _, _)| wgpu::ComputePassTimestampWrites {
                    query_set: qs,
                    beginning_of_pass_write_index: Some(2 * k),
                    end_of_pass_write_index: Some(2 * k + 1),
                });
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("blend batch"),
            timestamp_writes,
        });
        let all = std::iter::once(&active)
            .chain(&blends)
            .chain(&skinning)
            .chain(&normals)
            .chain(&packs);
        for d in all {
            let [x, y, z] = d.workgroups;
            pass.set_pipeline(d.pipeline);
            pass.set_bind_group(0, &d.group, &[]);
            pass.dispatch_workgroups(x, y, z);
        }
    }
}

/// `build_active`: per group of eight jobs, the active slots and their weights, read from the
/// clip tables (and the live rows).
fn build_active<'a>(s: &SubBatch<'a>) -> Dispatch<'a> {
    let (live_at, live_bytes) = s.r.live;
    let p = &s.ctx.pipelines;
    // The whole job list (the sub-batch starts at record `job_base`), then the live rows.
    let job_bytes = wgpu::BufferBinding {
        buffer: &s.slot.jobs,
        offset: 0,
        size: std::num::NonZeroU64::new(live_at),
    };
    let live_rows = wgpu::BufferBinding {
        buffer: &s.slot.jobs,
        offset: live_at,
        size: std::num::NonZeroU64::new(live_bytes),
    };
    let active_params = s.ctx.uniform(&ActiveParams {
        jobs: s.jobs,
        groups: s.groups,
        slots: s.rig.slots,
        job_base: s.r.job as u32,
    });
    let active_bg = s.ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some("build_active"),
        layout: &p.active.get_bind_group_layout(0),
        entries: &[
            entry(0, &active_params),
            wgpu::BindGroupEntry {
                binding: 1,
                resource: wgpu::BindingResource::Buffer(job_bytes),
            },
            entry(2, &s.rig.tables.buffer),
            entry(3, &s.rig.order),
            entry(4, &s.slot.active_weights),
            entry(5, &s.slot.active_slots),
            entry(6, &s.slot.active_count),
            wgpu::BindGroupEntry {
                binding: 7,
                resource: wgpu::BindingResource::Buffer(live_rows),
            },
        ],
    });
    Dispatch {
        pipeline: &p.active,
        group: active_bg,
        workgroups: [s.groups, 1, 1],
    }
}

/// `blend` (f32 out) or `blend_packed` (the 16-bit output itself, where `fused`): per chunk
/// of the rig, its positions, then, with normals, its normal deltas.
fn blend<'a>(s: &SubBatch<'a>) -> Vec<Dispatch<'a>> {
    let p = &s.ctx.pipelines;
    let (rig, slot, spec, jobs) = (s.rig, s.slot, s.spec, s.jobs);
    // A rig has f16 deltas only on a context made for them, which has these pipelines.
    let blends = match (rig.deltas, &p.blend_f16) {
        (DeltaFormat::F16, Some(f16)) => f16,
        _ => &p.blend,
    };
    let fused = s.fused;
    let blend = blends.writing(spec.precision, fused, s.r.reference.is_some());
    // What `blend_packed` reads besides the blend's own bindings: the box (used unless it
    // writes binary16) and the residual reference (a small range where there is none).
    let packing = fused.then(|| {
        let q16 = s.ctx.uniform(&match spec.precision {
            Precision::Q16(b) => Q16PackParams::new(
                &crate::Q16Params::new(b, false),
                jobs * rig.vertices * 3,
                0,
                rig.vertices * 3,
            ),
            _ => Q16PackParams::default(),
        });
        let (at, len) = s.r.reference.unwrap_or((0, 4));
        (q16, at, len)
    });
    let blend_groups = |chunks: &[GpuChunk],
                        out: &wgpu::Buffer,
                        packed: &wgpu::Buffer,
                        normalize: u32|
     -> Vec<Dispatch<'a>> {
        chunks
            .iter()
            .map(|c| {
                // Group first, so that the workgroups running side by side share a tile's
                // deltas in the cache.
                let tiles_y = c.tiles.min(65_535);
                let tiles_z = c.tiles.div_ceil(tiles_y.max(1));
                let params = s.ctx.uniform(&BlendParams {
                    vertices: rig.vertices,
                    tile_begin: c.tile_begin,
                    tiles: c.tiles,
                    slots: rig.slots,
                    words: rig.words,
                    jobs,
                    normalize,
                    tiles_y,
                });
                let mut entries = vec![
                    entry(0, &params),
                    entry(1, &c.base),
                    entry(2, &c.blocks),
                    entry(3, &c.masks),
                    entry(4, &slot.active_weights),
                    entry(5, &slot.active_slots),
                    entry(6, &slot.active_count),
                ];
                // `blend` writes f32 into `out`; `blend_packed` the wire format into
                // `packed`, with the box and (q16r) the reference.
                match &packing {
                    Some((q16, at, len)) => {
                        entries.push(entry(8, packed));
                        entries.push(entry(9, q16));
                        entries.push(wgpu::BindGroupEntry {
                            binding: 10,
                            resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                                buffer: &slot.jobs,
                                offset: *at,
                                size: std::num::NonZeroU64::new(*len),
                            }),
                        });
                    }
                    None => entries.push(entry(7, out)),
                }
                let bg = s.bind(blend, &entries);
                Dispatch {
                    pipeline: blend,
                    group: bg,
                    workgroups: [s.groups, tiles_y, tiles_z],
                }
            })
            .collect()
    };
    let mut dispatches = blend_groups(&rig.positions, &slot.positions, &slot.packed_positions, 0);
    if spec.normals {
        dispatches.extend(blend_groups(
            &rig.normals,
            &slot.normals,
            &slot.packed_normals,
            1,
        ));
    }
    dispatches
}

/// `skin`: on a skinned rig, each blended vertex (and blended normal) by its bones' matrices
/// in its job's pose.
fn skin<'a>(s: &SubBatch<'a>) -> Option<Dispatch<'a>> {
    let p = &s.ctx.pipelines;
    let (rig, slot, jobs) = (s.rig, s.slot, s.jobs);
    rig.skin.as_ref().map(|sk| {
        let tiles = rig.vertices.div_ceil(64);
        let x = tiles.clamp(1, 65_535);
        let params = s.ctx.uniform(&SkinParams {
            vertices: rig.vertices,
            jobs,
            bones: sk.bones,
            normals: u32::from(s.spec.normals && !rig.normals.is_empty()),
            row: x * 64,
            _pad: [0; 3],
        });
        let bones = wgpu::BufferBinding {
            buffer: &slot.bones,
            offset: s.r.bones.0,
            size: std::num::NonZeroU64::new(s.r.bones.1),
        };
        let bg = s.ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("skin"),
            layout: &p.skin.get_bind_group_layout(0),
            entries: &[
                entry(0, &params),
                entry(1, &sk.influences),
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: wgpu::BindingResource::Buffer(bones),
                },
                entry(3, &slot.positions),
                entry(4, &slot.normals),
            ],
        });
        Dispatch {
            pipeline: &p.skin,
            group: bg,
            workgroups: [x, jobs, tiles.div_ceil(x)],
        }
    })
}

/// `face_normals`: each triangle's area-weighted normal of the blended (and skinned)
/// positions, into the slot's scratch `faces`. `params` ([`NormalParams`]) is shared with
/// [`vertex_normals`].
fn face_normals<'a>(s: &SubBatch<'a>, t: &GpuTopology, params: &wgpu::Buffer) -> Dispatch<'a> {
    let p = &s.ctx.pipelines;
    let face = s.bind(
        &p.face,
        &[
            entry(0, params),
            entry(1, &s.slot.positions),
            entry(2, &t.triangles),
            entry(3, &s.slot.faces),
        ],
    );
    Dispatch {
        pipeline: &p.face,
        group: face,
        workgroups: [t.n_triangles.div_ceil(64), s.jobs, 1],
    }
}

/// `vertex_normals`: each recomputed vertex's normal, summed from its triangles' and
/// normalized.
fn vertex_normals<'a>(s: &SubBatch<'a>, t: &GpuTopology, params: &wgpu::Buffer) -> Dispatch<'a> {
    let p = &s.ctx.pipelines;
    let vertex = s.bind(
        &p.vertex,
        &[
            entry(0, params),
            entry(4, &s.slot.faces),
            entry(5, &t.recomputed),
            entry(6, &t.incident_start),
            entry(7, &t.incident),
            entry(8, &s.slot.normals),
        ],
    );
    Dispatch {
        pipeline: &p.vertex,
        group: vertex,
        workgroups: [t.n_recomputed.div_ceil(64), s.jobs, 1],
    }
}

/// `pack_f16`, `pack_q16` or `pack_q16r`: the 16-bit output of whatever the blend did not
/// write itself. Where it did (`fused`), clears the packed positions in `encoder` first, for
/// the blend to or its halves into.
fn pack<'a>(s: &SubBatch<'a>, encoder: &mut wgpu::CommandEncoder) -> Vec<Dispatch<'a>> {
    let p = &s.ctx.pipelines;
    let (rig, slot, spec, jobs) = (s.rig, s.slot, s.spec, s.jobs);
    // 16-bit output: positions and normals packed by `pack_f16`, or by `pack_q16` with the
    // box's parameters for positions and the unit scale for normals; positions coded
    // against a reference by `pack_q16r` (the same words: two bytes a component).
    let count = jobs * rig.vertices * 3;
    let pairs = count.div_ceil(2);
    let (px, py) = {
        let x = pairs.div_ceil(64).clamp(1, 65_535);
        (x, pairs.div_ceil(x * 64).max(1))
    };
    let pack_uniform = |normals: bool| match spec.precision {
        Precision::Q16(b) => Some(s.ctx.uniform(&Q16PackParams::new(
            &crate::Q16Params::new(b, normals),
            count,
            px * 64,
            rig.vertices * 3,
        ))),
        Precision::F16 => Some(s.ctx.uniform(&PackParams {
            count,
            row: px * 64,
            _pad0: 0,
            _pad1: 0,
        })),
        Precision::F32 => None,
    };
    let pack_pipeline = match spec.precision {
        Precision::Q16(_) => &p.pack_q16,
        _ => &p.pack,
    };
    let mut pack_groups = Vec::new();
    let mut buffers = Vec::new();
    if !s.fused {
        buffers.push((false, &slot.positions, &slot.packed_positions));
    } else {
        // The blend or-s the halves that two invocations share into cleared words.
        let bytes = (u64::from(count) * 2).next_multiple_of(4);
        encoder.clear_buffer(&slot.packed_positions, 0, Some(bytes));
    }
    if spec.normals {
        buffers.push((true, &slot.normals, &slot.packed_normals));
    }
    for (normals, src, dst) in buffers {
        let Some(params) = pack_uniform(normals) else {
            continue;
        };
        let mut entries = vec![entry(0, &params), entry(1, src), entry(2, dst)];
        let pipeline = match s.r.reference {
            Some((at, len)) if !normals => {
                entries.push(wgpu::BindGroupEntry {
                    binding: 3,
                    resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                        buffer: &slot.jobs,
                        offset: at,
                        size: std::num::NonZeroU64::new(len),
                    }),
                });
                &p.pack_q16r
            }
            _ => pack_pipeline,
        };
        pack_groups.push(Dispatch {
            pipeline,
            group: s.bind(pipeline, &entries),
            workgroups: [px, py, 1],
        });
    }
    pack_groups
}
