//! Liveliness for session heads (issue 47): a head's `alive` (its own, else its session's)
//! as `crowdmorph_core::rig::AliveParams`, applied by the tick over the head's layered pose
//! (after its layers, before its clamp), and the neutral pose a clip-less head shows.
//!
//! Per tick, each rig's [`AliveRig`] (its targets by loose ARKit name, its head, eye and
//! chest joints) is found once, and every buffer whose size a rig decides is charged to the
//! queue memory first; the charges live as long as the tick's resolved heads.

use std::collections::HashMap;

use crowdmorph_core::rig::{AliveParams, AliveRig, JointPose, Placement, Pose, Rig, Trs};
use crowdmorph_proto::{Alive, SessionHead};

use crate::admission::names::LiveNames;
use crate::admission::{Charge, QueueMemory};
use crate::http::ApiError;
use crate::registry::RigEntry;

/// Checks an `alive` object a request sends (400 `invalid_alive`): its look-at point finite,
/// within the coordinates a placement may have.
pub fn check_alive(alive: &Alive) -> Result<(), ApiError> {
    let max = crowdmorph_engine::render::scene::MAX_COORDINATE;
    if let Some(p) = alive.look_at
        && !p.iter().all(|c| c.is_finite() && c.abs() <= max)
    {
        return Err(ApiError::bad_request(
            "invalid_alive",
            format!("look_at {p:?} must be three finite numbers within ±{max}"),
        ));
    }
    Ok(())
}

/// The liveliness of one tick: the session's default, the clock, each rig's layers and
/// neutral pose, and what they hold.
pub(crate) struct AliveTick {
    default: Option<Alive>,
    /// The tick's time, seconds since the session's first tick (ticks quantize time).
    t: f64,
    rigs: HashMap<u32, AliveRig>,
    neutral: HashMap<u32, Pose>,
    charge: Option<Charge>,
}

impl AliveTick {
    /// Tick `tick` (from 1) of a session at `fps` whose heads without their own `alive` get
    /// `default`.
    pub(crate) fn new(default: Option<Alive>, tick: u64, fps: f32) -> AliveTick {
        AliveTick {
            default,
            t: tick.saturating_sub(1) as f64 / f64::from(fps),
            rigs: HashMap::new(),
            neutral: HashMap::new(),
            charge: None,
        }
    }

    /// Head `h`'s layers: its own `alive`, else the session's; `None` when neither enables
    /// any (a head's own with everything off stops the session's for it).
    pub(crate) fn params(&self, h: &SessionHead) -> Option<AliveParams> {
        let a = h.alive.as_ref().or(self.default.as_ref())?;
        (a.blink || a.saccades || a.look_at.is_some() || a.breathing).then(|| AliveParams {
            blink: a.blink,
            saccades: a.saccades,
            look_at: a.look_at,
            breathing: a.breathing,
            seed: a
                .seed
                .unwrap_or_else(|| crowdmorph_core::rig::head_seed(h.head)),
        })
    }

    /// Whether head `h` has layers to apply.
    pub(crate) fn on(&self, h: &SessionHead) -> bool {
        self.params(h).is_some()
    }

    fn reserve(&mut self, memory: &QueueMemory, bytes: u64) -> Option<()> {
        let more = memory.reserve(bytes).ok()?;
        match &mut self.charge {
            Some(c) => c.merge(more),
            None => self.charge = Some(more),
        }
        Some(())
    }

    /// The neutral pose of rig `ri` (every weight 0, joints at rest): what a head with an
    /// empty clip and no graph shows. One per rig a tick, shared by its heads.
    pub(crate) fn neutral(&mut self, memory: &QueueMemory, ri: u32, rig: &Rig) -> Option<Pose> {
        if let Some(p) = self.neutral.get(&ri) {
            return Some(p.clone());
        }
        self.reserve(memory, 64 + 4 * rig.targets.len() as u64)?;
        let p = Pose::live(&vec![0.0; rig.targets.len()]);
        self.neutral.insert(ri, p.clone());
        Some(p)
    }

    fn rig(&mut self, memory: &QueueMemory, ri: u32, rig: &Rig) -> Option<&AliveRig> {
        if !self.rigs.contains_key(&ri) {
            // Names matched as live weights and masks match them (loose spellings); dropped
            // once the rig's layers are found.
            self.reserve(memory, AliveRig::bytes_for(rig) + LiveNames::bytes(rig))?;
            let names = LiveNames::new(rig);
            self.rigs
                .insert(ri, AliveRig::new(rig, |n| names.ids(n).to_vec()));
        }
        self.rigs.get(&ri)
    }

    /// Applies head `h`'s layers (it must have some: [`AliveTick::on`]) to `w`, the weights of
    /// rig `ri` after the head's own layers.
    pub(crate) fn weights(
        &mut self,
        memory: &QueueMemory,
        ri: u32,
        rig: &Rig,
        h: &SessionHead,
        w: &mut [f32],
    ) -> Option<()> {
        let p = self.params(h)?;
        let t = self.t;
        self.rig(memory, ri, rig)?
            .apply_weights(&p, &placement(h), t, w);
        Some(())
    }

    /// Head `h`'s joint overrides with its layers' turns on top (head, eyes, chest): `joints`
    /// are the head's overrides over a live pose (the rest), as the layered path gives them.
    /// Unchanged on a rig without a skeleton or without such joints.
    pub(crate) fn joints(
        &mut self,
        memory: &QueueMemory,
        ri: u32,
        entry: &RigEntry,
        h: &SessionHead,
        joints: JointPose,
    ) -> Option<JointPose> {
        let rig = entry.rig();
        let (Some(sk), Some(p)) = (&rig.skeleton, self.params(h)) else {
            return Some(joints);
        };
        let t = self.t;
        let nodes = sk.nodes.len() as u64;
        let trs = size_of::<Trs>() as u64;
        let set = size_of::<crowdmorph_core::rig::JointSet>() as u64;
        if !self.rig(memory, ri, rig)?.has_joints() {
            return Some(joints);
        }
        // Rest and posed locals, and the overrides made of them (twice: built, then shared).
        self.reserve(memory, 2 * (16 + nodes * trs) + 2 * (16 + nodes * set) + 64)?;
        let ar = self.rigs.get(&ri)?;
        let rest = sk.rest();
        let mut locals = rest.clone();
        joints.apply(sk, &mut locals);
        ar.apply_locals(sk, &p, &placement(h), t, &mut locals);
        Some(JointPose::from_locals(&locals, &rest))
    }

    /// What the tick's liveliness holds, merged into `other` (the tick's other charges).
    pub(crate) fn charge_into(self, other: Option<Charge>) -> Option<Charge> {
        match (other, self.charge) {
            (Some(mut a), Some(b)) => {
                a.merge(b);
                Some(a)
            }
            (a, b) => a.or(b),
        }
    }
}

fn placement(h: &SessionHead) -> Placement {
    Placement {
        position: h.position,
        yaw_deg: h.yaw,
        scale: h.scale,
    }
}
