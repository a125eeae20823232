//! A batch cut into pieces and sub-batches and laid out on the device: the pieces, each staged
//! and read back on its own slot ([`plan_pieces`]); a piece's jobs per sub-batch and each
//! one's [`Region`] ([`plan_batch`]), and what a piece needs of a slot ([`slot_needs`]). Pure
//! functions of the batch's counts and the device's limits, so that the cuts and the sizes are
//! tested without a device.
//!
//! Invariants: every job is in exactly one piece and one sub-batch, in order; each piece's
//! staging and bone matrices fit the largest buffer and, where a room is given, its slot fits
//! half of it (two pieces' slots are alive at once); each sub-batch's outputs, face
//! normals, bone matrices and active lists fit one storage binding; ranges that a binding
//! starts at (live weights, the reference, each sub-batch's bone matrices) are aligned to the
//! device's storage offset alignment.

use std::ops::Range;

use super::layout::{GpuJob, JOBS_PER_GROUP};
use super::slot::SlotNeeds;

/// Where each sub-batch's results sit in the staging buffer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct Region {
    /// First job of the sub-batch.
    pub(super) job: usize,
    /// Jobs in it.
    pub(super) jobs: usize,
    pub(super) positions: u64,
    pub(super) normals: u64,
    /// Byte offset and length of the live weights in the jobs buffer (the same for every
    /// sub-batch).
    pub(super) live: (u64, u64),
    /// Byte offset and length of the sub-batch's bone matrices in the slot's bones buffer.
    pub(super) bones: (u64, u64),
    /// Byte offset and length of the residual reference in the jobs buffer, when the
    /// positions are coded against one (the same for every sub-batch).
    pub(super) reference: Option<(u64, u64)>,
}

/// What decides how a batch is cut into sub-batches ([`plan_batch`]).
#[derive(Clone, Copy, Debug)]
pub(super) struct BatchCounts {
    /// Jobs in the batch.
    pub(super) jobs: usize,
    /// Vertices per job.
    pub(super) vertices: u64,
    /// The rig's LOD slots (the active lists hold eight weights per slot and group).
    pub(super) slots: u32,
    /// Triangles whose face normals are recomputed (0: none are).
    pub(super) triangles: u64,
    /// Bytes of one job's bone matrices (0 on a rig without a skeleton).
    pub(super) bone_bytes: u64,
    /// Live weights uploaded with the batch.
    pub(super) live: usize,
    /// Components of the residual reference, when positions are coded against one.
    pub(super) reference: Option<usize>,
    /// Whether normals are read back too.
    pub(super) normals: bool,
    /// Whether outputs are 16-bit (packed on the device).
    pub(super) packed16: bool,
}

/// A batch's layout on the device: jobs per sub-batch, each sub-batch's [`Region`], where the
/// live weights and the reference follow the job records, and the staging and bone bytes.
#[derive(Debug, PartialEq)]
pub(super) struct BatchPlan {
    /// Jobs per sub-batch (the last may hold fewer).
    pub(super) sub: usize,
    /// One region per sub-batch, in job order.
    pub(super) regions: Vec<Region>,
    /// Byte offset of the live weights in the jobs buffer.
    pub(super) live_at: u64,
    /// Their bytes (at least one weight's).
    pub(super) live_bytes: u64,
    /// Byte offset of the residual reference in the jobs buffer.
    pub(super) reference_at: u64,
    /// Bytes of staging memory the read-back outputs take.
    pub(super) staging: u64,
    /// Bytes of the bone matrices' buffer.
    pub(super) bones_at: u64,
}

/// Cuts a batch into sub-batches that each fit one binding of `max_binding` bytes (outputs,
/// face normals, bone matrices, the active lists), in whole groups of eight jobs where that is
/// at least one group, and lays out each sub-batch's staging and bone ranges (bone ranges at
/// `align`, the device's storage offset alignment). A pure function of the counts, so that
/// the cut is tested without a device.
pub(super) fn plan_batch(c: &BatchCounts, max_binding: u64, align: u64) -> BatchPlan {
    let n = c.jobs;
    let v = c.vertices;
    // The live weights follow the job records in the same buffer, at the first offset a
    // storage binding may start at.
    let live_at = ((n.max(1) * size_of::<GpuJob>()) as u64).next_multiple_of(align);
    let live_bytes = (c.live.max(1) * 4) as u64;
    // Then the residual reference, two q16 values a word.
    let reference_at = (live_at + live_bytes).next_multiple_of(align);
    let reference_range = c
        .reference
        .map(|r| (reference_at, (r as u64 * 2).next_multiple_of(4)));
    let per_job_out = v * 12;
    // Jobs per sub-batch: what one binding holds (outputs, face normals, bone matrices and
    // the active lists' eight weights per slot and group), in whole groups where that is at
    // least one group; a sub-batch may start mid-group, the passes do not mind.
    let mut sub = max_binding / per_job_out.max(1);
    sub = sub.min(max_binding / (u64::from(c.slots.max(1)) * 4));
    if c.triangles > 0 {
        sub = sub.min(max_binding / (c.triangles * 12));
    }
    if let Some(fit) = max_binding.checked_div(c.bone_bytes) {
        sub = sub.min(fit);
    }
    let sub = sub.min(65_535) as usize;
    let sub = if sub >= JOBS_PER_GROUP {
        sub / JOBS_PER_GROUP * JOBS_PER_GROUP
    } else {
        sub.max(1)
    };
    let subs = n.div_ceil(sub).max(1);
    let elem = if c.packed16 { 2 } else { 4 };
    let mut regions = Vec::with_capacity(subs);
    let mut staging = 0u64;
    let mut bones_at = 0u64;
    for k in 0..subs {
        let job = k * sub;
        let count = sub.min(n - job);
        let bytes = (count as u64 * v * 3 * elem).next_multiple_of(4);
        let positions = staging;
        staging += bytes;
        let normals = staging;
        if c.normals {
            staging += bytes;
        }
        let bones = (bones_at, (count as u64 * c.bone_bytes).max(16));
        bones_at = (bones_at + bones.1).next_multiple_of(align);
        regions.push(Region {
            job,
            jobs: count,
            positions,
            normals,
            live: (live_at, live_bytes),
            bones,
            reference: reference_range,
        });
    }
    BatchPlan {
        sub,
        regions,
        live_at,
        live_bytes,
        reference_at,
        staging,
        bones_at,
    }
}

/// What a batch of `c`, cut as `plan` says, needs of a slot: buffers sized for the largest
/// sub-batch it has (not for `sub`, which for a small rig may be thousands of jobs), and only
/// for the outputs it asks for — no f32 stage where the blend writes the 16-bit output itself
/// (`fused`), no staging without `readback`, timestamp queries only where the device has
/// them (`timestamps`). Every pass writes only the jobs it was given, so outputs hold exactly
/// those; the active lists are per group of eight. A pure function, as [`plan_batch`].
pub(super) fn slot_needs(
    c: &BatchCounts,
    plan: &BatchPlan,
    fused: bool,
    readback: bool,
    timestamps: bool,
) -> SlotNeeds {
    let widest = plan.sub.min(c.jobs.max(1)) as u64;
    let output = widest * c.vertices * 12;
    let f16 = c.packed16;
    let reference_range = plan.regions.first().and_then(|r| r.reference);
    SlotNeeds {
        jobs: reference_range.map_or(plan.live_at + plan.live_bytes, |(at, len)| at + len),
        active: widest.div_ceil(JOBS_PER_GROUP as u64) * u64::from(c.slots.max(1)) * 4,
        // The blend writes the 16-bit output itself: no f32 stage.
        output: if fused { 4 } else { output },
        normals: if c.normals { output } else { 4 },
        packed: if f16 { output / 2 + 4 } else { 4 },
        packed_normals: if f16 && c.normals { output / 2 + 4 } else { 4 },
        faces: if c.triangles > 0 {
            widest * c.triangles * 12
        } else {
            4
        },
        staging: if readback { plan.staging } else { 4 },
        bones: if c.bone_bytes > 0 { plan.bones_at } else { 4 },
        queries: if timestamps {
            2 * plan.regions.len() as u32
        } else {
            0
        },
    }
}

/// What bounds a piece of a batch ([`plan_pieces`]).
#[derive(Clone, Copy, Debug)]
pub(super) struct PieceLimits {
    /// The storage binding's bytes (sub-batches) and the storage offset alignment.
    pub(super) max_binding: u64,
    pub(super) align: u64,
    /// Bytes of the largest buffer a piece's staging or bone matrices may take.
    pub(super) max_buffer: u64,
    /// Bytes of the memory budget a batch may use now (free plus idle slots), when pieces are
    /// also cut to fit it: a whole batch whose slot fits is one piece; otherwise each piece's
    /// slot fits half of it, since a piece's slot is made while the previous one is read back.
    pub(super) room: Option<u64>,
    /// Whether the blend writes 16-bit outputs itself, the outputs are read back and the
    /// device has timestamp queries ([`slot_needs`]).
    pub(super) fused: bool,
    pub(super) readback: bool,
    pub(super) timestamps: bool,
}

/// The slot a piece of `jobs` jobs of the batch `c` needs, and whether its staging and bone
/// matrices fit the largest buffer.
fn piece_needs(c: &BatchCounts, jobs: usize, l: &PieceLimits) -> (SlotNeeds, bool) {
    let p = BatchCounts { jobs, ..*c };
    let plan = plan_batch(&p, l.max_binding, l.align);
    let fits = (!l.readback || plan.staging <= l.max_buffer) && plan.bones_at <= l.max_buffer;
    let needs = slot_needs(&p, &plan, l.fused, l.readback, l.timestamps);
    (needs, fits)
}

/// Cuts a batch into pieces, each run on a slot of its own and read back on its own: the
/// whole batch when its staging and bone matrices fit the largest buffer and its slot fits
/// `room`; otherwise the fewest pieces of equal size (the last may be smaller) whose staging
/// and bone matrices fit and whose slots fit half the room, in whole sub-batches (or groups of
/// eight jobs) where a piece holds at least one. When no piece of one job fits the room, the
/// room is ignored (its slot's charge then says the budget is full); `None` when not even one
/// job's staging or bone matrices fit the largest buffer. Each piece has the batch's live
/// weights and reference, so it is laid out as a batch of its jobs ([`plan_batch`]).
pub(super) fn plan_pieces(c: &BatchCounts, l: &PieceLimits) -> Option<Vec<Range<usize>>> {
    let n = c.jobs;
    let fits = |jobs: usize, slot: Option<u64>| {
        let (needs, fits) = piece_needs(c, jobs, l);
        fits && slot.is_none_or(|max| needs.bytes(l.timestamps) <= max)
    };
    if n <= 1 || fits(n, l.room) {
        return fits(n.max(1), None).then(|| std::iter::once(0..n).collect());
    }
    let half = l.room.map(|r| r / 2);
    let slot = if fits(1, half) { half } else { None };
    if !fits(1, slot) {
        return None;
    }
    // The largest piece that fits (sizes grow with the jobs), by bisection.
    let (mut lo, mut hi) = (1, n);
    while hi - lo > 1 {
        let mid = lo + (hi - lo) / 2;
        if fits(mid, slot) {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    if fits(hi, slot) {
        lo = hi;
    }
    if lo == n {
        // Only where the room was ignored: the whole batch fits the largest buffer.
        return Some(std::iter::once(0..n).collect());
    }
    // Whole sub-batches (or groups): the passes of a piece run full dispatches.
    let sub = plan_batch(&BatchCounts { jobs: lo, ..*c }, l.max_binding, l.align).sub;
    let unit = if lo >= sub {
        sub
    } else if lo >= JOBS_PER_GROUP {
        JOBS_PER_GROUP
    } else {
        1
    };
    let piece = lo / unit * unit;
    Some(
        (0..n.div_ceil(piece))
            .map(|k| k * piece..((k + 1) * piece).min(n))
            .collect(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn counts(jobs: usize) -> BatchCounts {
        BatchCounts {
            jobs,
            vertices: 1000,
            slots: 51,
            triangles: 0,
            bone_bytes: 0,
            live: 0,
            reference: None,
            normals: false,
            packed16: false,
        }
    }

    /// Every job is in exactly one region, in order; the regions' staging ranges follow each
    /// other and each sub-batch's outputs fit one binding.
    fn check(c: &BatchCounts, max_binding: u64, align: u64) -> BatchPlan {
        let p = plan_batch(c, max_binding, align);
        let mut next_job = 0;
        let mut next_staging = 0;
        let elem = if c.packed16 { 2 } else { 4 };
        for r in &p.regions {
            assert_eq!(r.job, next_job, "{c:?}");
            assert!(r.jobs >= 1 && r.jobs <= p.sub);
            assert!(r.jobs as u64 * c.vertices * 12 <= max_binding.max(c.vertices * 12));
            assert_eq!(r.positions, next_staging);
            let bytes = (r.jobs as u64 * c.vertices * 3 * elem).next_multiple_of(4);
            next_staging = r.positions + bytes * if c.normals { 2 } else { 1 };
            assert_eq!(r.bones.0 % align, 0, "bone ranges start aligned");
            next_job += r.jobs;
        }
        assert_eq!(next_job, c.jobs);
        assert_eq!(p.staging, next_staging);
        assert_eq!(p.live_at % align, 0);
        assert_eq!(p.reference_at % align, 0);
        assert!(p.reference_at >= p.live_at + p.live_bytes);
        p
    }

    #[test]
    fn a_batch_that_fits_one_binding_is_one_sub_batch() {
        let p = check(&counts(100), 128 << 20, 256);
        assert_eq!(p.regions.len(), 1);
        assert_eq!(p.regions[0].jobs, 100);
        assert_eq!(p.staging, 100 * 1000 * 12);
    }

    #[test]
    fn a_batch_past_the_binding_is_cut_in_whole_groups() {
        // 12,000 bytes a job: a 1 MiB binding holds 87 jobs, cut to 80 (ten groups of eight).
        let p = check(&counts(1000), 1 << 20, 256);
        assert_eq!(p.sub, 80);
        assert_eq!(p.regions.len(), 13);
        assert_eq!(p.regions.last().map(|r| r.jobs), Some(1000 - 12 * 80));
        // 16-bit outputs with normals: half the bytes per output, two outputs each.
        let c = BatchCounts {
            packed16: true,
            normals: true,
            ..counts(1000)
        };
        let p = check(&c, 1 << 20, 256);
        assert_eq!(p.staging, 2 * (1000 * 1000 * 3 * 2));
    }

    #[test]
    fn face_normals_bones_and_small_bindings_bound_the_cut() {
        // Recomputed face normals of 50,000 triangles: 600,000 bytes a job, one job a binding.
        let c = BatchCounts {
            triangles: 50_000,
            ..counts(20)
        };
        let p = check(&c, 1 << 20, 256);
        assert_eq!((p.sub, p.regions.len()), (1, 20));
        // Bone matrices: each sub-batch's range aligned, and the buffer holds them all.
        let c = BatchCounts {
            bone_bytes: 5 * 48,
            ..counts(300)
        };
        let p = check(&c, 1 << 20, 256);
        let last = p.regions.last().expect("regions");
        assert!(p.bones_at >= last.bones.0 + last.bones.1);
        // A live row and a reference follow the job records, each at the alignment.
        let c = BatchCounts {
            live: 51 * 300,
            reference: Some(3000),
            ..counts(300)
        };
        let p = check(&c, 1 << 20, 256);
        assert_eq!(p.live_bytes, 51 * 300 * 4);
        assert_eq!(p.regions[0].reference, Some((p.reference_at, 6000)));
    }

    #[test]
    fn a_slot_is_sized_for_the_widest_sub_batch_and_the_outputs_asked_for() {
        // 20 jobs of a small rig: `sub` is thousands of jobs, the slot holds 20.
        let c = counts(20);
        let p = check(&c, 128 << 20, 256);
        assert!(p.sub > 20);
        let n = slot_needs(&c, &p, false, true, false);
        assert_eq!(n.output, 20 * 1000 * 12);
        assert_eq!(
            (n.normals, n.packed, n.packed_normals, n.faces),
            (4, 4, 4, 4)
        );
        assert_eq!((n.staging, n.bones, n.queries), (p.staging, 4, 0));
        assert_eq!(n.jobs, p.live_at + p.live_bytes);
        assert_eq!(n.active, 3 * 51 * 4, "three groups of eight jobs");
        // Cut in sub-batches: the widest one, with timestamps two queries each.
        let c = counts(1000);
        let p = check(&c, 1 << 20, 256);
        let n = slot_needs(&c, &p, false, true, true);
        assert_eq!(n.output, 80 * 1000 * 12);
        assert_eq!(n.queries, 2 * 13);
    }

    #[test]
    fn a_slot_has_no_stage_a_batch_does_not_use() {
        // 16-bit outputs the blend writes itself, with normals, recomputed, left on the device.
        let c = BatchCounts {
            packed16: true,
            normals: true,
            triangles: 2000,
            reference: Some(3000),
            ..counts(20)
        };
        let p = check(&c, 128 << 20, 256);
        let n = slot_needs(&c, &p, true, false, false);
        let output = 20 * 1000 * 12;
        assert_eq!((n.output, n.normals), (4, output));
        assert_eq!(
            (n.packed, n.packed_normals),
            (output / 2 + 4, output / 2 + 4)
        );
        assert_eq!(n.faces, 20 * 2000 * 12);
        assert_eq!(n.staging, 4);
        // The jobs buffer ends with the reference, after the live weights.
        assert_eq!(n.jobs, p.reference_at + 6000);
    }

    fn limits(max_buffer: u64, room: Option<u64>) -> PieceLimits {
        PieceLimits {
            max_binding: 1 << 20,
            align: 256,
            max_buffer,
            room,
            fused: false,
            readback: true,
            timestamps: true,
        }
    }

    /// Every job in exactly one piece, in order, and each piece within the limits.
    fn check_pieces(c: &BatchCounts, l: &PieceLimits) -> Vec<Range<usize>> {
        let pieces = plan_pieces(c, l).expect("pieces");
        let mut next = 0;
        for p in &pieces {
            assert_eq!(p.start, next, "{c:?}: pieces in order, none skipped");
            assert!(p.end > p.start || c.jobs == 0);
            let (needs, fits) = piece_needs(c, p.len(), l);
            assert!(fits, "{c:?}: piece {p:?} fits the largest buffer");
            // Where one job's slot fits half the room, two pieces' slots fit the room.
            if pieces.len() > 1
                && let Some(room) = l.room
                && piece_needs(c, 1, l).0.bytes(l.timestamps) <= room / 2
            {
                assert!(
                    needs.bytes(l.timestamps) <= room / 2,
                    "two pieces' slots fit"
                );
            }
            // The staging the piece's own plan lays out is what was checked.
            let plan = plan_batch(
                &BatchCounts {
                    jobs: p.len(),
                    ..*c
                },
                l.max_binding,
                l.align,
            );
            assert!(plan.staging <= l.max_buffer && plan.bones_at <= l.max_buffer);
            next = p.end;
        }
        assert_eq!(next, c.jobs);
        pieces
    }

    #[test]
    fn a_batch_that_fits_is_one_piece() {
        let whole = |n: usize| std::iter::once(0..n).collect::<Vec<_>>();
        let c = counts(1000);
        assert_eq!(check_pieces(&c, &limits(1 << 31, None)), whole(1000));
        let room = limits(1 << 31, Some(1 << 30));
        assert_eq!(check_pieces(&c, &room), whole(1000));
        assert_eq!(check_pieces(&counts(0), &limits(1 << 31, None)), whole(0));
    }

    #[test]
    fn staging_past_the_largest_buffer_is_cut_in_whole_sub_batches() {
        // 12,000 bytes a job, 80 jobs a sub-batch (1 MiB bindings): 4 MB of staging holds
        // 333 jobs, cut to 320 (four sub-batches); 1,000 jobs take four pieces.
        let c = counts(1000);
        let p = check_pieces(&c, &limits(4_000_000, None));
        assert_eq!(p, vec![0..320, 320..640, 640..960, 960..1000]);
        // q16 with normals: the same bytes, 1000 × 1000 × 3 × 2 × 2.
        let c = BatchCounts {
            packed16: true,
            normals: true,
            ..counts(1000)
        };
        assert_eq!(check_pieces(&c, &limits(4_000_000, None)).len(), 4);
        // Bone matrices bound a piece too, and without readback only they do.
        let c = BatchCounts {
            bone_bytes: 10_000,
            ..counts(1000)
        };
        let l = PieceLimits {
            readback: false,
            ..limits(1_000_000, None)
        };
        let p = check_pieces(&c, &l);
        assert!(p.len() >= 10, "{p:?}");
        // A piece smaller than a sub-batch is cut in groups of eight, or single jobs.
        let p = check_pieces(&counts(30), &limits(12_000 * 20, None));
        assert_eq!(p, vec![0..16, 16..30]);
        let p = check_pieces(&counts(5), &limits(12_000 * 3, None));
        assert_eq!(p, vec![0..3, 3..5]);
    }

    #[test]
    fn a_batch_over_the_room_is_cut_so_two_slots_fit() {
        let c = counts(1000);
        let whole = piece_needs(&c, 1000, &limits(1 << 31, None)).0.bytes(true);
        // Room for the whole batch: one piece; for a third of it: pieces of a sixth or less.
        assert_eq!(check_pieces(&c, &limits(1 << 31, Some(whole))).len(), 1);
        let p = check_pieces(&c, &limits(1 << 31, Some(whole / 3)));
        assert!(p.len() >= 6, "{p:?}");
        // A room too small for one job's slot is ignored: the charge will refuse it.
        let p = check_pieces(&c, &limits(4_000_000, Some(1000)));
        assert_eq!(p.len(), 4);
        // One job's staging over the largest buffer cannot be cut.
        assert_eq!(plan_pieces(&c, &limits(11_999, None)), None);
    }
}
