//! The batch planner: a crowd of heads becomes unique jobs plus a per-head index into them.
//!
//! Costigan et al. 2016 (§3.1) decouple animation from rendering so that heads sharing rig,
//! clip and frame are blended once. The planner is where that happens for every backend: heads
//! with the same [`JobKey`] map to one job, in order of first appearance, so results are
//! deterministic for a given crowd.

use std::collections::HashMap;

use crate::rig::{JointPose, Pose};

/// What makes two heads clones: same rig, pose (clip and resolved frame, or a canonical blend,
/// or quantized live weights), level of detail and joint overrides.
#[derive(Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct JobKey {
    /// Rig index in the caller's registry.
    pub rig: u32,
    /// The weights the job evaluates.
    pub pose: Pose,
    /// LOD level.
    pub lod: u32,
    /// Joint overrides (quantized, canonical; only on skinned rigs, only of joints the LOD
    /// level keeps).
    pub joints: JointPose,
}

impl JobKey {
    /// A job playing frame `frame` of clip `clip`.
    pub fn frame(rig: u32, clip: u32, frame: u32, lod: u32) -> JobKey {
        JobKey {
            rig,
            pose: Pose::Frame { clip, frame },
            lod,
            joints: JointPose::NONE,
        }
    }
}

/// Unique jobs and, for every head, which job computes it.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Plan {
    /// Unique jobs in order of first appearance.
    pub jobs: Vec<JobKey>,
    /// `head_job[h]` is the index into `jobs` of head `h`'s result.
    pub head_job: Vec<u32>,
}

impl Plan {
    /// Deduplicates `heads` into unique jobs.
    pub fn new(heads: impl IntoIterator<Item = JobKey>) -> Plan {
        let heads = heads.into_iter();
        let mut index: HashMap<JobKey, u32> =
            HashMap::with_capacity(heads.size_hint().0.min(1 << 16));
        let mut plan = Plan::default();
        for key in heads {
            let next = plan.jobs.len() as u32;
            let job = match index.get(&key) {
                Some(&j) => j,
                None => {
                    plan.jobs.push(key.clone());
                    index.insert(key, next);
                    next
                }
            };
            plan.head_job.push(job);
        }
        plan
    }

    /// Job indices grouped by rig, rigs in order of first appearance: one dispatch per rig.
    pub fn by_rig(&self) -> Vec<(u32, Vec<u32>)> {
        let mut groups: Vec<(u32, Vec<u32>)> = Vec::new();
        let mut at: HashMap<u32, usize> = HashMap::new();
        for (j, key) in self.jobs.iter().enumerate() {
            let g = *at.entry(key.rig).or_insert_with(|| {
                groups.push((key.rig, Vec::new()));
                groups.len() - 1
            });
            groups[g].1.push(j as u32);
        }
        groups
    }

    /// Heads per unique job (1.0 when every head is unique).
    pub fn clone_ratio(&self) -> f64 {
        if self.jobs.is_empty() {
            1.0
        } else {
            self.head_job.len() as f64 / self.jobs.len() as f64
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clones_share_jobs_in_first_appearance_order() {
        let k = |rig, frame| JobKey::frame(rig, 0, frame, 0);
        let plan = Plan::new([k(0, 1), k(1, 1), k(0, 1), k(0, 2), k(1, 1)]);
        assert_eq!(plan.jobs, vec![k(0, 1), k(1, 1), k(0, 2)]);
        assert_eq!(plan.head_job, vec![0, 1, 0, 2, 1]);
        assert_eq!(plan.by_rig(), vec![(0, vec![0, 2]), (1, vec![1])]);
    }
}
