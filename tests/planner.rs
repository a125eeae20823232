//! The batch planner: clones are computed once and every head maps to the right buffer.

use crowdmorph::engine::cpu::CpuRig;
use crowdmorph::engine::{BlendJob, OutputSpec, WeightBatch};
use crowdmorph::plan::{JobKey, Plan};

use crate::util::Rng;

#[test]
fn thousand_heads_over_ten_jobs_evaluate_ten_jobs_and_map_every_head() {
    let rig = crowdmorph::embedded::default_rig();
    let talk = rig.clip_index("talk").expect("talk clip") as u32;
    let idle = rig.clip_index("idle").expect("idle clip") as u32;
    // Ten distinct (clip, frame, lod) keys, spread over 1,000 heads in a shuffled order.
    let keys: Vec<JobKey> = (0..10)
        .map(|i| JobKey::frame(0, if i % 2 == 0 { talk } else { idle }, 3 * i, i % 3))
        .collect();
    let mut rng = Rng(42);
    let heads: Vec<JobKey> = (0..1000)
        .map(|_| keys[rng.below(keys.len())].clone())
        .collect();
    let plan = Plan::new(heads.iter().cloned());
    assert_eq!(plan.jobs.len(), 10, "exactly the unique jobs");
    assert_eq!(plan.head_job.len(), 1000);
    for (h, key) in heads.iter().enumerate() {
        assert_eq!(
            plan.jobs[plan.head_job[h] as usize], *key,
            "head {h} maps to its own job"
        );
    }

    let jobs: Vec<BlendJob> = plan.jobs.iter().map(BlendJob::from).collect();
    let cpu = CpuRig::new(&rig);
    let batch = WeightBatch::gather(&rig, &jobs).expect("gather");
    let out = cpu
        .evaluate(&batch, OutputSpec::default())
        .expect("evaluate");
    assert_eq!(
        out.jobs, 10,
        "the engine evaluated ten jobs, not a thousand"
    );
    // Each head's buffer is exactly what evaluating its own key alone gives.
    for (h, key) in heads.iter().enumerate().step_by(37) {
        let alone = WeightBatch::gather(&rig, &[BlendJob::from(key)]).expect("gather");
        let want = cpu
            .evaluate(&alone, OutputSpec::default())
            .expect("evaluate");
        assert_eq!(
            out.job_positions(plan.head_job[h] as usize),
            want.job_positions(0),
            "head {h}"
        );
    }
}

#[test]
fn jobs_group_by_rig_in_order_of_first_appearance() {
    let k = |rig, frame| JobKey::frame(rig, 0, frame, 0);
    let plan = Plan::new([k(2, 0), k(0, 0), k(2, 1), k(2, 0), k(1, 5), k(0, 0)]);
    assert_eq!(plan.jobs.len(), 4);
    assert_eq!(
        plan.by_rig(),
        vec![(2, vec![0, 2]), (0, vec![1]), (1, vec![3])]
    );
    assert!((plan.clone_ratio() - 1.5).abs() < 1e-12);
}

#[test]
fn an_empty_crowd_plans_nothing() {
    let plan = Plan::new(std::iter::empty());
    assert!(plan.jobs.is_empty() && plan.head_job.is_empty());
    assert!(plan.by_rig().is_empty());
}
