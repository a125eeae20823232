//! Turning a request's heads into work: each head resolved against one snapshot of the rig it
//! names (clip, frame and LOD checked), the unique jobs planned, and what they cost — output
//! bytes held, weight rows, the batcher's cost — priced before any of it is done.

use std::collections::HashMap;
use std::sync::Arc;

use crowdmorph_proto::{Format, Head};

use crate::plan::{JobKey, Plan};
use crate::rig::quoted_name;
use crate::rig::{ACTIVE_WEIGHT_EPSILON, FrameMode, Rig};
use crate::server::http::ApiError;
use crate::server::registry::{MAX_F16, Registry, RigEntry};
use crate::server::scheduler::JobRequest;

/// 404 for a rig id the registry does not have, listing (at most 20 of) the ones it has.
pub fn unknown_rig(registry: &Registry, id: &str) -> ApiError {
    let mut ids: Vec<String> = registry.all().iter().map(|e| e.id.clone()).collect();
    ids.truncate(20);
    ApiError::not_found(
        "unknown_rig",
        format!("no rig {} (rigs: {})", quoted_name(id), ids.join(", ")),
    )
}

/// 404 for a clip the rig does not have, listing at most 20 of its clips.
pub fn unknown_clip(entry: &RigEntry, clip: &str) -> ApiError {
    let names: Vec<&str> = entry
        .rig()
        .clips
        .iter()
        .take(20)
        .map(|c| c.name.as_str())
        .collect();
    ApiError::not_found(
        "unknown_clip",
        format!(
            "rig {:?} has no clip {} (clips: {})",
            entry.id,
            quoted_name(clip),
            names.join(", ")
        ),
    )
}

/// Largest coordinate (in absolute value) a rig's positions can reach, from its q16 box.
pub fn head_reach(entry: &RigEntry) -> f64 {
    let q = &entry.qbox;
    (0..3)
        .map(|a| {
            let lo = f64::from(q.min[a]);
            let hi = lo + f64::from(q.step[a]) * 65535.0;
            lo.abs().max(hi.abs())
        })
        .fold(0.0, f64::max)
}

/// Crowd heads resolved against one snapshot of each rig they name: what both crowd endpoints
/// compute from.
pub struct ResolvedHeads {
    /// The rigs, in order of first appearance; `JobKey::rig` indexes this.
    pub rigs: Vec<Arc<RigEntry>>,
    /// Unique jobs and each head's job.
    pub plan: Plan,
}

/// Bytes one job's output holds while it is computed and sent: positions (and normals) in the
/// wire format, three times that as JSON (base64 text and its escape), plus, with normals in a
/// 16-bit format on a rig whose normals are recomputed, the f32 positions and normals the CPU
/// engine blends before the normals pass and the encoding, and, for q16 on the GPU engine
/// (`gpu`), the f32 outputs it reads back and quantizes on the host. The job's weights are
/// counted too ([`JOB_WEIGHT_BYTES_PER_TARGET`] per rig target): on a rig of many targets and
/// few vertices they outweigh the output. Every admission (crowd frames, sessions, load tests)
/// charges this.
pub fn job_output_bytes(rig: &Rig, format: Format, normals: bool, json: bool, gpu: bool) -> u64 {
    let v3 = rig.vertex_count() as u64 * 3;
    let comp = format.component_bytes() as u64;
    let outputs = if normals { 2 } else { 1 };
    let wire = v3 * comp * outputs * if json { 3 } else { 1 };
    let f32_first =
        (normals && comp < 4 && rig.recomputes_normals()) || (gpu && format == Format::Q16);
    let weights = rig.targets.len() as u64 * JOB_WEIGHT_BYTES_PER_TARGET + 16;
    wire + if f32_first { v3 * 4 * outputs } else { 0 } + weights
}

/// What a batch holds per job and rig target besides the outputs: the job's row of the
/// gathered weights (`WeightBatch`, 4 bytes per target) and its lane of the CPU kernel's
/// group tables (4 bytes of weight and, per group of 8 jobs, a byte per target), rounded up.
/// The GPU engine gathers the same rows before it uploads them.
pub const JOB_WEIGHT_BYTES_PER_TARGET: u64 = 9;

/// Bytes `heads` hold decoded (each `Head` and its two names), plus `built` bytes a head of
/// what a handler builds from them: the per-head share a crowd frame keeps charged until its
/// response is sent, and a render until its frame is drawn.
pub fn heads_held_bytes(heads: &Vec<Head>, built: u64) -> u64 {
    // The vector's slots by capacity: decoding JSON grows it by doubling, up to twice its
    // length.
    let slots = heads.capacity() as u64 * size_of::<Head>() as u64;
    let names: u64 = heads
        .iter()
        .map(|h| h.rig.capacity() as u64 + h.clip.capacity() as u64)
        .sum();
    slots + heads.len() as u64 * built + names
}

/// Resolves every head against one snapshot of each rig it names (a rig changed or
/// deleted meanwhile does not change this request), checks clip, frame and LOD, and plans
/// the unique jobs. `f16` refuses rigs whose coordinates f16 cannot hold. Errors name the
/// head by position and id.
pub fn resolve_heads(
    registry: &Registry,
    max_heads: usize,
    heads: &[Head],
    mode: FrameMode,
    f16: bool,
) -> Result<ResolvedHeads, ApiError> {
    let n_heads = heads.len();
    if n_heads > max_heads {
        return Err(ApiError::bad_request(
            "too_many_heads",
            format!(
                "{n_heads} heads is more than the limit of {} per request",
                max_heads
            ),
        ));
    }
    let mut lookups = Lookups {
        registry,
        rigs: Vec::new(),
        rig_at: HashMap::new(),
        clip_at: HashMap::new(),
    };
    let mut keys = Vec::with_capacity(n_heads);
    for (h, head) in heads.iter().enumerate() {
        let ri = lookups.rig(h, head)?;
        let entry = &lookups.rigs[ri as usize];
        if f16 && head_reach(entry) > MAX_F16 {
            return Err(ApiError::bad_request(
                "format_overflow",
                format!(
                    "head {h} (id {}): rig {:?} reaches coordinates of {:e}, past the largest \
                     f16 ({}); ask for f32 or q16",
                    head.head,
                    entry.id,
                    head_reach(entry),
                    MAX_F16
                ),
            ));
        }
        let ci = lookups.clip(h, head, ri)?;
        let rig = lookups.rigs[ri as usize].rig();
        let frame = rig.clips[ci as usize]
            .resolve_frame(head.frame, mode)
            .map_err(|e| {
                ApiError::bad_request(
                    "frame_out_of_range",
                    format!("head {h} (id {}): {e}", head.head),
                )
            })?;
        if head.lod as usize >= rig.lod.levels.len() {
            return Err(ApiError::bad_request(
                "lod_out_of_range",
                format!(
                    "head {h} (id {}): LOD {} out of range: rig {:?} has levels 0..{}",
                    head.head,
                    head.lod,
                    lookups.rigs[ri as usize].id,
                    rig.lod.levels.len() - 1
                ),
            ));
        }
        keys.push(JobKey {
            rig: ri,
            clip: ci,
            frame,
            lod: head.lod,
        });
    }
    let rigs = lookups.rigs;
    Ok(ResolvedHeads {
        rigs,
        plan: Plan::new(keys),
    })
}

/// The rigs and clips a request names, each looked up once: a crowd of thousands of heads
/// names a handful.
struct Lookups<'h> {
    registry: &'h Registry,
    /// One snapshot per distinct rig, in order of first mention.
    rigs: Vec<Arc<RigEntry>>,
    rig_at: HashMap<&'h str, u32>,
    clip_at: HashMap<(u32, &'h str), u32>,
}

impl<'h> Lookups<'h> {
    /// The index of head `h`'s rig in `rigs`, or 404 naming the head.
    fn rig(&mut self, h: usize, head: &'h Head) -> Result<u32, ApiError> {
        if let Some(&i) = self.rig_at.get(head.rig.as_str()) {
            return Ok(i);
        }
        let e = self
            .registry
            .get(&head.rig)
            .ok_or_else(|| at_head(h, head, unknown_rig(self.registry, &head.rig)))?;
        self.rigs.push(e);
        let i = (self.rigs.len() - 1) as u32;
        self.rig_at.insert(head.rig.as_str(), i);
        Ok(i)
    }

    /// The index of head `h`'s clip in rig `ri`, or 404 naming the head.
    fn clip(&mut self, h: usize, head: &'h Head, ri: u32) -> Result<u32, ApiError> {
        if let Some(&c) = self.clip_at.get(&(ri, head.clip.as_str())) {
            return Ok(c);
        }
        let entry = &self.rigs[ri as usize];
        let c = entry
            .clip_index(&head.clip)
            .ok_or_else(|| at_head(h, head, unknown_clip(entry, &head.clip)))?
            as u32;
        self.clip_at.insert((ri, head.clip.as_str()), c);
        Ok(c)
    }
}

/// `e` with its message prefixed by the head it is about.
fn at_head(h: usize, head: &Head, e: ApiError) -> ApiError {
    ApiError {
        message: format!("head {h} (id {}): {}", head.head, e.message),
        ..e
    }
}

/// One unique job for the batcher, with its cost: vertices × (active shapes + 1) at the job's
/// frame and level of detail.
pub fn job_request(entry: &Arc<RigEntry>, clip: u32, frame: u32, lod: u32) -> JobRequest {
    let rig = entry.rig();
    let shapes = rig.lod.shapes_at(lod).unwrap_or(0) as usize;
    let table = &rig.clips[clip as usize];
    let active = rig.lod.order[..shapes.min(rig.lod.order.len())]
        .iter()
        .filter(|&&t| table.weight(t as usize, frame).abs() > ACTIVE_WEIGHT_EPSILON)
        .count() as u64;
    let v = entry.prepared.at_level(lod).rig().vertex_count() as u64;
    JobRequest {
        entry: entry.clone(),
        clip,
        frame,
        lod,
        cost: v * (active + 1),
    }
}
