//! Motion graphs (Kovar et al. 2002; GPU Gems 3 ch. 15 sequences captured clips so): a
//! [`MotionGraph`] checked against a rig ([`Graph`]), and the [`Player`] that walks one for a
//! session head, cross-fading in weight space.
//!
//! **No pops.** Every change of what a head plays is a fade from the pose it shows: an edge
//! fades the target node in while the source keeps playing; a jump (a session `PATCH` sending
//! the head to a node, also in the middle of a fade) or a change of the head's own joint
//! overrides freezes the pose shown and fades from it. So weights and joints are continuous.
//! Their change per tick is bounded too: a fade's progress per tick is capped so that
//! `Δα × U ≤ 0.45 × D`, where `U` bounds how far a vertex moves per unit of `α` between the
//! two poses ([`Reach`]: `Σₖ |w_src,k − w_dst,k| × Lₖ` with `Lₖ` channel k's longest delta, and
//! on a skinned rig what each joint's change carries a vertex, skinning included) and `D` is
//! the largest per-frame vertex displacement inside the nodes involved (measured by the server
//! on the CPU engine, [`Graph::set_motion`]). Without a skeleton a vertex then moves per tick
//! by at most `(1 − α)·D_src + α·D_dst + Δα·U ≤ 1.45 × D` — within 1.5× the clips' own
//! motion, with room for the 1/4096 quantization of blend fractions. With one, the fade's
//! share is bounded the same way, while the frames' own motion inside a mix of two skeleton
//! poses is the clips' up to what the nlerp stretches (RobotExpressive's Sitting ⇄ Idle: at
//! most 0.78× of the clips' largest step per tick). A fade between poses far apart takes
//! longer than its edge's nominal `fade` frames.

use std::collections::{BTreeSet, HashMap};
use std::sync::Arc;

use crowdmorph_proto::{GraphPlay, MotionGraph};
use glam::{DMat4, Quat, Vec3};

use crowdmorph_core::cancel::{Cancel, Cancelled};
use crowdmorph_core::rig::{JointPose, MAX_TERMS, Pose, Rig, T_ONE, Term, Trs};
use crowdmorph_core::rng::SplitMix64;

/// Most nodes a graph may have.
pub const MAX_GRAPH_NODES: usize = 1024;
/// Most edges a graph may have.
pub const MAX_GRAPH_EDGES: usize = 16_384;
/// Cross-fade of a jump to a node that no edge from the current node reaches, in frames.
pub const DEFAULT_JUMP_FADE: u32 = 8;
/// Share of the involved clips' per-frame motion that a fade's progress may add per tick.
const STEP_SHARE: f64 = 0.45;

/// Why a graph does not fit its rig; each names the field.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum GraphError {
    /// A malformed graph (400 `invalid_graph`).
    #[error("{0}")]
    Invalid(String),
    /// A node names a clip the rig does not have (404 `unknown_clip`).
    #[error("node {node:?} plays clip {clip:?}, which the rig does not have")]
    UnknownClip {
        /// Node name.
        node: String,
        /// Clip name.
        clip: String,
    },
}

/// A node: `len` frames of clip `clip` from frame `first`.
#[derive(Clone, Debug, PartialEq)]
pub struct Node {
    /// Node name.
    pub name: String,
    /// Clip index in the rig.
    pub clip: u32,
    /// First frame played.
    pub first: u32,
    /// Frames played.
    pub len: u32,
    /// Frames per second of the clip.
    pub fps: f32,
    /// Edges leaving the node (indices into [`Graph::edges`]).
    pub out: Vec<u32>,
}

/// A transition.
#[derive(Clone, Debug, PartialEq)]
pub struct Edge {
    /// Source node.
    pub from: u32,
    /// Target node.
    pub to: u32,
    /// Nominal cross-fade, frames.
    pub fade: u32,
    /// Source-node frames where it may start, inclusive.
    pub window: [u32; 2],
}

/// A motion graph resolved against one version of a rig.
#[derive(Clone, Debug, PartialEq)]
pub struct Graph {
    /// The nodes.
    pub nodes: Vec<Node>,
    /// The edges.
    pub edges: Vec<Edge>,
    by_name: HashMap<String, u32>,
    /// Per node, the largest per-frame vertex displacement of its frames.
    motion: Vec<f32>,
    /// What bounds the vertex speed of a fade.
    reach: Reach,
}

impl Graph {
    /// Bytes a resolved `spec` holds at most (for the caller's charge).
    pub fn bytes(spec: &MotionGraph, rig: &Rig) -> u64 {
        let names: u64 = spec.nodes.iter().map(|n| n.name.len() as u64 + 64).sum();
        names
            + spec.nodes.len() as u64 * (size_of::<Node>() as u64 + 8)
            + spec.edges.len() as u64 * (size_of::<Edge>() as u64 + 4)
            + rig.targets.len() as u64 * 4
            + Reach::bytes(rig)
    }

    /// Checks `spec` against `rig` (`clip_index` finds a clip by name) and resolves it. Motion
    /// is zero until [`Graph::set_motion`].
    pub fn resolve(
        spec: &MotionGraph,
        rig: &Rig,
        clip_index: impl Fn(&str) -> Option<usize>,
    ) -> Result<Graph, GraphError> {
        let bad = |m: String| Err(GraphError::Invalid(m));
        if spec.nodes.is_empty() || spec.nodes.len() > MAX_GRAPH_NODES {
            return bad(format!(
                "nodes: {} nodes; a graph has 1 to {MAX_GRAPH_NODES}",
                spec.nodes.len()
            ));
        }
        if spec.edges.len() > MAX_GRAPH_EDGES {
            return bad(format!(
                "edges: {} edges, more than the limit of {MAX_GRAPH_EDGES}",
                spec.edges.len()
            ));
        }
        let mut nodes = Vec::with_capacity(spec.nodes.len());
        let mut by_name = HashMap::with_capacity(spec.nodes.len());
        for (i, n) in spec.nodes.iter().enumerate() {
            if n.name.is_empty() || n.name.len() > 64 {
                return bad(format!("nodes[{i}].name must be 1 to 64 bytes"));
            }
            if by_name.insert(n.name.clone(), i as u32).is_some() {
                return bad(format!("nodes[{i}].name {:?} is used twice", n.name));
            }
            let c = clip_index(&n.clip).ok_or_else(|| GraphError::UnknownClip {
                node: n.name.clone(),
                clip: n.clip.clone(),
            })?;
            let clip = &rig.clips[c];
            let [first, last] = n.frames.unwrap_or([0, clip.frames.saturating_sub(1)]);
            if first > last || last >= clip.frames {
                return bad(format!(
                    "nodes[{i}].frames [{first}, {last}] is not a range of clip {:?} (frames 0..{})",
                    n.clip, clip.frames
                ));
            }
            nodes.push(Node {
                name: n.name.clone(),
                clip: c as u32,
                first,
                len: last - first + 1,
                fps: clip.fps,
                out: Vec::new(),
            });
        }
        let mut edges = Vec::with_capacity(spec.edges.len());
        for (i, e) in spec.edges.iter().enumerate() {
            let node = |name: &str, field: &str| {
                by_name.get(name).copied().ok_or_else(|| {
                    GraphError::Invalid(format!("edges[{i}].{field} names no node: {name:?}"))
                })
            };
            let (from, to) = (node(&e.from, "from")?, node(&e.to, "to")?);
            let (lf, lt) = (nodes[from as usize].len, nodes[to as usize].len);
            if e.fade == 0 {
                return bad(format!(
                    "edges[{i}].fade is 0; a cross-fade lasts at least one frame"
                ));
            }
            if e.fade > lf || e.fade > lt {
                return bad(format!(
                    "edges[{i}].fade of {} frames is longer than node {:?} ({} frames) or {:?} ({})",
                    e.fade, e.from, lf, e.to, lt
                ));
            }
            let window = e.window.unwrap_or([lf - e.fade, lf - e.fade]);
            if window[0] > window[1] || window[1] >= lf {
                return bad(format!(
                    "edges[{i}].window {window:?} is not a range of node {:?}'s frames 0..{lf}",
                    e.from
                ));
            }
            nodes[from as usize].out.push(i as u32);
            edges.push(Edge {
                from,
                to,
                fade: e.fade,
                window,
            });
        }
        if let Some(n) = nodes.iter().find(|n| n.out.is_empty()) {
            return bad(format!(
                "node {:?} has no edge out: a head reaching it would have nowhere to go (every \
                 node needs one; a self-loop plays it again)",
                n.name
            ));
        }
        Ok(Graph {
            motion: vec![0.0; nodes.len()],
            nodes,
            edges,
            by_name,
            reach: Reach::of(rig),
        })
    }

    /// The node named `name`.
    pub fn node(&self, name: &str) -> Option<u32> {
        self.by_name.get(name).copied()
    }

    /// The first edge from `from` to `to`.
    pub fn edge(&self, from: u32, to: u32) -> Option<u32> {
        self.nodes[from as usize]
            .out
            .iter()
            .copied()
            .find(|&e| self.edges[e as usize].to == to)
    }

    /// Sets each node's largest per-frame vertex displacement (the server measures it).
    pub fn set_motion(&mut self, motion: Vec<f32>) {
        if motion.len() == self.nodes.len() {
            self.motion = motion;
        }
    }

    /// The largest per-frame displacement of node `n`.
    pub fn motion(&self, n: u32) -> f32 {
        self.motion[n as usize]
    }

    /// Checks a head's play (start and script nodes exist, each script step has an edge)
    /// and returns its start, script and seed.
    pub fn play(&self, p: &GraphPlay) -> Result<(u32, Vec<u32>, u64), String> {
        let start = self
            .node(&p.start)
            .ok_or_else(|| format!("graph {:?} has no node {:?}", p.name, p.start))?;
        let mut script = Vec::with_capacity(p.script.len());
        let mut at = start;
        for (i, name) in p.script.iter().enumerate() {
            let n = self
                .node(name)
                .ok_or_else(|| format!("script[{i}]: graph {:?} has no node {name:?}", p.name))?;
            if self.edge(at, n).is_none() {
                return Err(format!(
                    "script[{i}]: no edge from {:?} to {name:?}",
                    self.nodes[at as usize].name
                ));
            }
            script.push(n);
            at = n;
        }
        Ok((start, script, p.seed))
    }
}

/// What bounds how fast a vertex moves while a head fades from one pose to another (`U` of the
/// module doc), measured once per rig generation.
///
/// A pose is weights and, on a skinned rig, each skeleton node's local transform. A fade moves
/// the weights linearly and nlerps the transforms; per unit of progress `α`:
///
/// - the weights move a vertex by at most `Σₖ |Δwₖ| × Lₖ` (channel k's longest delta) in the
///   space the morph targets live in, which skinning stretches by at most
///   [`Reach::morph_gain`];
/// - node `n`'s transform `T + R S x` moves a point `x` of its own space by at most
///   `|ΔT| + max|ΔS| × r + 4 tan(θ/4) × s × r`, where θ is the angle between the two
///   rotations (an nlerp turns at most `4 tan(θ/4)` radians per unit of `α`), `s` the node's
///   largest scale and `r` how far from its origin a vertex it moves can be in its own space,
///   in any pose ([`SkeletonReach::radius`]); its ancestors stretch that by at most the product
///   of their largest scales ([`SkeletonReach::gain`]).
///
/// A skinned vertex is a convex combination of its bones' images, and a bone's image changes by
/// at most the sum of what each node of its chain adds, so the largest chain sum bounds every
/// vertex. Both parts are exact for a rig without a skeleton (the sum of `|Δwₖ| × Lₖ`), and
/// upper bounds otherwise: a fade is slowed by as much as they overestimate.
#[derive(Clone, Debug, Default, PartialEq)]
struct Reach {
    /// Per weight channel, its longest delta.
    channel: Vec<f32>,
    /// The most skinning stretches a morph delta: 1 without a skeleton.
    morph_gain: f64,
    /// On a skinned rig, what each node carries.
    skeleton: Option<SkeletonReach>,
}

/// Per skeleton node, what bounds how far changing its transform moves a vertex.
#[derive(Clone, Debug, PartialEq)]
struct SkeletonReach {
    /// Parent index, or `u32::MAX` for a root (parents come first).
    parent: Vec<u32>,
    /// Product of the ancestors' largest absolute scales: how much the node's parent space is
    /// stretched in the rig's space.
    gain: Vec<f64>,
    /// Largest absolute scale component of the node, at rest or in any clip.
    scale: Vec<f64>,
    /// The farthest from the node's origin, in its own space, that a vertex of a bone at or
    /// under it can be in any pose: a bone's vertices (with every morph its clips can apply) in
    /// bone space, then up the chain `|T + R S x| ≤ |T| + s |x|` with each node's largest
    /// translation and scale (at rest or in a clip; overrides may not exceed them).
    radius: Vec<f64>,
    /// The nodes bones hang from, where a vertex's chain ends.
    ends: Vec<u32>,
}

impl Reach {
    /// Bytes [`Reach::of`] holds while it measures `rig`, and keeps.
    fn bytes(rig: &Rig) -> u64 {
        let nodes = rig.skeleton.as_ref().map_or(0, |s| s.nodes.len() as u64);
        let longest_primitive = rig
            .primitives
            .iter()
            .map(|p| p.positions.len() as u64)
            .max()
            .unwrap_or(0);
        rig.targets.len() as u64 * 20 + nodes * 48 + longest_primitive * 8
    }

    /// Measures `rig`.
    fn of(rig: &Rig) -> Reach {
        let mut channel = vec![0f32; rig.targets.len()];
        for p in rig.primitives.iter() {
            for t in &p.targets {
                let longest = t.positions.iter().map(|d| d.length()).fold(0.0, f32::max);
                if let Some(r) = channel.get_mut(t.target as usize) {
                    *r = r.max(longest);
                }
            }
        }
        let Some(sk) = &rig.skeleton else {
            return Reach {
                channel,
                morph_gain: 1.0,
                skeleton: None,
            };
        };
        let n = sk.nodes.len();
        let (t_max, s_max) = sk.extents(&rig.clips);
        let parent: Vec<u32> = sk
            .nodes
            .iter()
            .enumerate()
            .map(|(i, node)| {
                if (node.parent as usize) < i {
                    node.parent
                } else {
                    u32::MAX
                }
            })
            .collect();
        let mut gain = vec![1f64; n];
        for i in 0..n {
            if let Some(&p) = parent.get(i).filter(|&&p| p != u32::MAX) {
                gain[i] = gain[p as usize] * s_max[p as usize];
            }
        }
        // The largest weight magnitude each channel has in any clip: a fade's weights stay
        // between clip frames'.
        let mut extreme = vec![0f64; rig.targets.len()];
        for c in &rig.clips {
            for (t, e) in extreme.iter_mut().enumerate().take(c.targets as usize) {
                for f in 0..c.frames {
                    *e = e.max(f64::from(c.weight(t, f)).abs());
                }
            }
        }
        // Per bone, the farthest its vertices (morphed as far as any clip morphs them) are from
        // its origin in bone space.
        let mut bone_radius = vec![0f64; sk.bones.len()];
        let mut used = vec![false; sk.bones.len()];
        let binds: Vec<DMat4> = sk
            .bones
            .iter()
            .map(|b| DMat4::from_cols_array(&b.bind.map(f64::from)))
            .collect();
        let norm = |m: &DMat4| {
            // The Frobenius norm of the linear part bounds its operator norm.
            (m.x_axis.truncate().length_squared()
                + m.y_axis.truncate().length_squared()
                + m.z_axis.truncate().length_squared())
            .sqrt()
        };
        let mut morphed = Vec::new();
        for p in rig.primitives.iter() {
            let Some(skin) = &p.skin else { continue };
            morphed.clear();
            morphed.resize(p.positions.len(), 0f64);
            for t in &p.targets {
                let w = extreme.get(t.target as usize).copied().unwrap_or(0.0);
                for (&v, d) in t.vertices.iter().zip(&t.positions) {
                    if let Some(m) = morphed.get_mut(v as usize) {
                        *m += w * f64::from(d.length());
                    }
                }
            }
            for (v, x) in p.positions.iter().enumerate() {
                let (Some(j), Some(w)) = (skin.joints.get(v), skin.weights.get(v)) else {
                    continue;
                };
                for (&b, &wb) in j.iter().zip(w) {
                    let b = b as usize;
                    if wb == 0.0 || b >= binds.len() {
                        continue;
                    }
                    let r = binds[b].transform_point3(x.as_dvec3()).length()
                        + norm(&binds[b]) * morphed[v];
                    bone_radius[b] = bone_radius[b].max(r);
                    used[b] = true;
                }
            }
        }
        let mut radius = vec![0f64; n];
        let mut morph_gain = 1f64;
        let mut ends = Vec::new();
        for (b, bone) in sk.bones.iter().enumerate() {
            let node = bone.node as usize;
            if !used[b] || node >= n {
                continue;
            }
            radius[node] = radius[node].max(bone_radius[b]);
            morph_gain = morph_gain.max(gain[node] * s_max[node] * norm(&binds[b]));
            ends.push(bone.node);
        }
        ends.sort_unstable();
        ends.dedup();
        for i in (0..n).rev() {
            if let Some(&p) = parent.get(i).filter(|&&p| p != u32::MAX) {
                let up = t_max[i] + s_max[i] * radius[i];
                radius[p as usize] = radius[p as usize].max(up);
            }
        }
        Reach {
            channel,
            morph_gain,
            skeleton: Some(SkeletonReach {
                parent,
                gain,
                scale: s_max,
                radius,
                ends,
            }),
        }
    }

    /// `U`: a bound on how far a vertex moves per unit of fade progress from pose `a` to pose
    /// `b` (weights, and on a skinned rig every node's local transform).
    fn speed(&self, wa: &[f32], wb: &[f32], joints: Option<(&[Trs], &[Trs])>) -> f64 {
        let morph: f64 = wa
            .iter()
            .zip(wb)
            .zip(&self.channel)
            .map(|((x, y), r)| f64::from((x - y).abs() * r))
            .sum();
        let mut u = morph * self.morph_gain;
        if let (Some(s), Some((la, lb))) = (&self.skeleton, joints) {
            let mut chain = vec![0f64; s.parent.len()];
            for (i, (a, b)) in la.iter().zip(lb).enumerate().take(chain.len()) {
                let dt = (Vec3::from(a.translation) - Vec3::from(b.translation)).length();
                let ds = (Vec3::from(a.scale) - Vec3::from(b.scale))
                    .abs()
                    .max_element();
                let qa = Quat::from_array(a.rotation).normalize();
                let qb = Quat::from_array(b.rotation).normalize();
                let theta = f64::from(qa.angle_between(qb)).clamp(0.0, std::f64::consts::PI);
                let turn = 4.0 * (theta / 4.0).tan();
                let here = s.gain[i]
                    * (f64::from(dt)
                        + f64::from(ds) * s.radius[i]
                        + turn * s.scale[i] * s.radius[i]);
                let above = match s.parent[i] {
                    u32::MAX => 0.0,
                    p => chain[p as usize],
                };
                chain[i] = above + here;
            }
            u += s
                .ends
                .iter()
                .map(|&e| chain.get(e as usize).copied().unwrap_or(0.0))
                .fold(0.0, f64::max);
        }
        u
    }
}

/// Where a fade comes from.
#[derive(Clone, Debug, PartialEq)]
enum Source {
    /// A node still playing (an edge's source).
    Node { node: u32, t: f64 },
    /// The pose a jump froze (its weights, the clip terms that gave them when it played
    /// clips — a frame, an edge's blend or an earlier jump's fade — and, on a skinned rig,
    /// every skeleton node's local transform), and the motion of the nodes it came from.
    Frozen {
        weights: Arc<[f32]>,
        terms: Option<Arc<[Term]>>,
        locals: Option<Arc<[Trs]>>,
        motion: f32,
    },
}

#[derive(Clone, Debug, PartialEq)]
struct Fade {
    source: Source,
    /// Progress, 0 → 1.
    alpha: f64,
    /// Nominal progress per frame (1 / fade).
    rate: f64,
}

/// One head walking a graph: the node it plays (the fade's target while fading), the frames
/// played in it, its next edge and where that starts, the fade in progress, and the head's own
/// joint overrides on top of what the graph plays.
#[derive(Clone, Debug, PartialEq)]
pub struct Player {
    node: u32,
    t: f64,
    rng: u64,
    script: Vec<u32>,
    script_at: usize,
    next: Option<(u32, f64)>,
    fade: Option<Fade>,
    overrides: JointPose,
}

impl Player {
    /// A head in node `start`, following `script` (from the node's first frame) then walking
    /// at random with `seed`. A walk starts at a frame of `start` its seed picks, so that a
    /// crowd on one graph does not move in lockstep; two players made alike stay alike, and
    /// clones cost one blend.
    pub fn new(g: &Graph, start: u32, script: Vec<u32>, seed: u64) -> Player {
        let mut rng = SplitMix64(seed);
        let t = if script.is_empty() {
            rng.below(g.nodes[start as usize].len as usize) as f64
        } else {
            0.0
        };
        let mut p = Player {
            node: start,
            t,
            rng: rng.0,
            script,
            script_at: 0,
            next: None,
            fade: None,
            overrides: JointPose::NONE,
        };
        p.plan(g);
        p
    }

    /// The same player with the head's own joint overrides from the start (no fade: a new
    /// head has shown nothing yet).
    pub fn with_overrides(mut self, overrides: JointPose) -> Player {
        self.overrides = overrides;
        self
    }

    /// Changes the head's own joint overrides (a session `PATCH` of its `joints`) the way a
    /// jump changes what it plays: the pose shown is frozen and faded from, to the same node
    /// and frames with the new overrides, under the same bound on the vertices' speed. The
    /// walk goes on where it was.
    pub fn set_overrides(&mut self, g: &Graph, rig: &Rig, overrides: JointPose) {
        if overrides == self.overrides {
            return;
        }
        if rig.skeleton.is_none() {
            // Overrides need a skeleton (the session checks it): nothing is shown of them.
            self.overrides = overrides;
            return;
        }
        let rate = match &self.fade {
            Some(f) => f.rate,
            None => {
                1.0 / f64::from(
                    DEFAULT_JUMP_FADE
                        .min(g.nodes[self.node as usize].len)
                        .max(1),
                )
            }
        };
        self.fade = Some(Fade {
            source: self.freeze(g, rig),
            alpha: 0.0,
            rate,
        });
        self.overrides = overrides;
    }

    /// The pose shown now as a fade's source: its weights, joints and the motion of the nodes
    /// it came from.
    fn freeze(&self, g: &Graph, rig: &Rig) -> Source {
        // Its clip terms carry what weights alone lose: which clip frames are shown, and so
        // their animated textures' coefficients (a fade from them blends those too). The
        // weights are then the terms' own, so that the fade starts exactly where it was.
        let pose = self.pose(g, rig);
        let terms: Option<Arc<[Term]>> = match &pose {
            Pose::Frame { clip, frame } => Some(Arc::from([Term {
                clip: *clip,
                frame: *frame,
                t: T_ONE,
            }])),
            Pose::Blend(t) => Some(t.clone()),
            Pose::Live(_) => None,
        };
        let weights: Arc<[f32]> = match terms {
            Some(_) => pose.weights(rig).into(),
            None => self.weights(g, rig).into(),
        };
        let locals = self.locals(g, rig).map(Arc::from);
        let motion = match &self.fade {
            Some(Fade {
                source: Source::Node { node, .. },
                ..
            }) => g.motion(*node),
            Some(Fade {
                source: Source::Frozen { motion, .. },
                ..
            }) => *motion,
            None => 0.0,
        }
        .max(g.motion(self.node));
        Source::Frozen {
            weights,
            terms,
            locals,
            motion,
        }
    }

    /// Picks the next edge out of the current node and the frame it starts at.
    fn plan(&mut self, g: &Graph) {
        let out = &g.nodes[self.node as usize].out;
        let mut rng = SplitMix64(self.rng);
        let (edge, scripted) = match self.script.get(self.script_at) {
            Some(&to) => match g.edge(self.node, to) {
                Some(e) => (e, true),
                None => (out[rng.below(out.len())], false),
            },
            None => (out[rng.below(out.len())], false),
        };
        if scripted {
            self.script_at += 1;
        }
        let [a, b] = g.edges[edge as usize].window;
        let at = if scripted {
            a
        } else {
            a + rng.below((b - a + 1) as usize) as u32
        };
        self.rng = rng.0;
        self.next = Some((edge, f64::from(at)));
    }

    /// The node the head plays now (the target while fading).
    pub fn node(&self) -> u32 {
        self.node
    }

    /// Whether a fade is in progress.
    pub fn fading(&self) -> bool {
        self.fade.is_some()
    }

    /// Whether a jump's fade (from a frozen pose) is in progress.
    #[cfg(test)]
    fn fading_from_frozen(&self) -> bool {
        matches!(
            self.fade,
            Some(Fade {
                source: Source::Frozen { .. },
                ..
            })
        )
    }

    fn frame(g: &Graph, node: u32, t: f64) -> (u32, u32) {
        let n = &g.nodes[node as usize];
        // The tiny bias keeps a clock that sums 1/fps steps from landing just below a whole
        // frame and then skipping one.
        let f = ((t.max(0.0) + 1e-6).floor() as u64).min(u64::from(n.len - 1)) as u32;
        (n.clip, n.first + f)
    }

    fn frame_weights(rig: &Rig, (clip, frame): (u32, u32)) -> Vec<f32> {
        let mut w = vec![0.0; rig.targets.len()];
        rig.clips[clip as usize].frame_weights(frame, &mut w);
        w
    }

    fn source_weights(g: &Graph, rig: &Rig, s: &Source) -> Vec<f32> {
        match s {
            Source::Node { node, t } => Self::frame_weights(rig, Self::frame(g, *node, *t)),
            Source::Frozen { weights, .. } => weights.to_vec(),
        }
    }

    /// Every skeleton node's local transform at a clip frame, with the head's overrides
    /// (`None` without a skeleton).
    fn frame_locals(&self, rig: &Rig, (clip, frame): (u32, u32)) -> Option<Vec<Trs>> {
        let sk = rig.skeleton.as_ref()?;
        let mut out = Vec::with_capacity(sk.nodes.len());
        sk.locals_at(rig.clips[clip as usize].joints.as_deref(), frame, &mut out);
        self.overrides.apply(sk, &mut out);
        Some(out)
    }

    fn source_locals(&self, g: &Graph, rig: &Rig, s: &Source) -> Option<Vec<Trs>> {
        match s {
            Source::Node { node, t } => self.frame_locals(rig, Self::frame(g, *node, *t)),
            Source::Frozen { locals, .. } => locals.as_deref().map(<[Trs]>::to_vec),
        }
    }

    /// The pose shown now: a clip frame, a two-frame blend while an edge fades, and while a
    /// jump fades from a frozen pose the blend of its clip terms (× `1 − α`) and the target
    /// frame (× `α`) — live weights only when the frozen pose had no clip terms or the blend
    /// would need more than [`MAX_TERMS`] (jumps in quick succession).
    pub fn pose(&self, g: &Graph, rig: &Rig) -> Pose {
        let here = Self::frame(g, self.node, self.t);
        match &self.fade {
            None => Pose::Frame {
                clip: here.0,
                frame: here.1,
            },
            Some(Fade {
                source: Source::Node { node, t },
                alpha,
                ..
            }) => Pose::blend(
                Self::frame(g, *node, *t),
                &[(here.0, here.1, *alpha as f32)],
            ),
            Some(
                f @ Fade {
                    source:
                        Source::Frozen {
                            terms: Some(terms), ..
                        },
                    alpha,
                    ..
                },
            ) => {
                let keep = 1.0 - *alpha as f32;
                let layers: Vec<(u32, u32, f32)> = terms
                    .iter()
                    .map(|t| (t.clip, t.frame, t.fraction() * keep))
                    .collect();
                match Pose::blend(here, &layers) {
                    Pose::Blend(t) if t.len() > MAX_TERMS => {
                        Pose::live(&self.weights_with(g, rig, f))
                    }
                    // Frozen terms name clips of the rig they were frozen on: after the rig
                    // changed under a fade (a clip deleted or replaced), they may not fit it.
                    p if p.check(rig).is_err() => Pose::live(&self.weights_with(g, rig, f)),
                    p => p,
                }
            }
            Some(f) => Pose::live(&self.weights_with(g, rig, f)),
        }
    }

    /// Every skeleton node's local transform in the pose shown now (`None` without a
    /// skeleton): the clip frame's, a fading edge's two frames nlerped, or a jump's frozen
    /// transforms faded into the target frame's the same way; the head's own overrides on
    /// top of the frames (an edge's two frames both carry them, so its blend does too).
    pub fn locals(&self, g: &Graph, rig: &Rig) -> Option<Vec<Trs>> {
        let sk = rig.skeleton.as_ref()?;
        let table = |(clip, _): (u32, u32)| rig.clips[clip as usize].joints.as_deref();
        let here = Self::frame(g, self.node, self.t);
        let mut out = Vec::with_capacity(sk.nodes.len());
        match &self.fade {
            None => {
                sk.locals_at(table(here), here.1, &mut out);
                self.overrides.apply(sk, &mut out);
            }
            Some(Fade {
                source: Source::Node { node, t },
                alpha,
                ..
            }) => {
                let from = Self::frame(g, *node, *t);
                let a = *alpha as f32;
                sk.locals_blend(
                    &[(1.0 - a, table(from), from.1), (a, table(here), here.1)],
                    &mut out,
                );
                self.overrides.apply(sk, &mut out);
            }
            Some(Fade {
                source: Source::Frozen { locals, .. },
                alpha,
                ..
            }) => {
                sk.locals_at(table(here), here.1, &mut out);
                self.overrides.apply(sk, &mut out);
                if let Some(from) = locals {
                    let a = *alpha as f32;
                    for (o, f) in out.iter_mut().zip(from.iter()) {
                        *o = Trs::nlerp(f, o, a);
                    }
                }
            }
        }
        Some(out)
    }

    /// The joint transforms a pose of [`Player::pose`] cannot carry: while a jump fades from
    /// a frozen pose (its transforms nlerped into the target frame's, which neither live
    /// weights — the skeleton at rest — nor a blend of the frozen clip terms gives), every
    /// node whose faded transform is not what the pose's terms give, as overrides. Otherwise a clip frame or an
    /// edge's blend carries its joints itself, and this is the head's own overrides.
    pub fn joints(&self, g: &Graph, rig: &Rig) -> JointPose {
        let (Some(sk), Some(Fade { source, .. })) = (&rig.skeleton, &self.fade) else {
            return self.overrides.clone();
        };
        if !matches!(
            source,
            Source::Frozen {
                locals: Some(_),
                ..
            }
        ) {
            return self.overrides.clone();
        }
        let Some(locals) = self.locals(g, rig) else {
            return JointPose::NONE;
        };
        // What the pose's own terms give each node (the rest pose for live weights): only the
        // nodes where the fade shows something else need an override.
        let mut given = Vec::with_capacity(sk.nodes.len());
        sk.locals_of(&self.pose(g, rig).skin_terms(rig), &mut given);
        JointPose::from_locals(&locals, &given)
    }

    fn weights_with(&self, g: &Graph, rig: &Rig, f: &Fade) -> Vec<f32> {
        let here = Self::frame_weights(rig, Self::frame(g, self.node, self.t));
        let from = Self::source_weights(g, rig, &f.source);
        let a = f.alpha as f32;
        from.iter()
            .zip(&here)
            .map(|(s, d)| (1.0 - a) * s + a * d)
            .collect()
    }

    /// The weights shown now, per channel.
    pub fn weights(&self, g: &Graph, rig: &Rig) -> Vec<f32> {
        match &self.fade {
            Some(f) => self.weights_with(g, rig, f),
            None => Self::frame_weights(rig, Self::frame(g, self.node, self.t)),
        }
    }

    /// Advances `dt` seconds: every node playing moves by `dt × fps` frames, a fade by at most
    /// its nominal rate and at most what keeps the per-tick change bounded (module doc); an
    /// edge whose start frame is reached begins its fade.
    pub fn advance(&mut self, g: &Graph, rig: &Rig, dt: f64) {
        let frames = |n: u32| dt * f64::from(g.nodes[n as usize].fps);
        let step = frames(self.node);
        self.t += step;
        if let Some(mut f) = self.fade.take() {
            if let Source::Node { node, t } = &mut f.source {
                *t += dt * f64::from(g.nodes[*node as usize].fps);
            }
            let d = match &f.source {
                Source::Node { node, .. } => g.motion(*node),
                Source::Frozen { motion, .. } => *motion,
            }
            .max(g.motion(self.node));
            let target = Self::frame(g, self.node, self.t);
            let here = Self::frame_weights(rig, target);
            let from = Self::source_weights(g, rig, &f.source);
            let u = match (
                self.source_locals(g, rig, &f.source),
                self.frame_locals(rig, target),
            ) {
                (Some(a), Some(b)) => g.reach.speed(&from, &here, Some((&a, &b))),
                _ => g.reach.speed(&from, &here, None),
            };
            let mut da = f.rate * step;
            // An unbounded speed (a skeleton whose scales overflow the measure) cannot be
            // slowed into any bound: such a fade keeps its nominal rate.
            if u.is_finite() && u > 0.0 && d > 0.0 {
                da = da.min(STEP_SHARE * f64::from(d) / u);
            }
            f.alpha = (f.alpha + da).min(1.0);
            if f.alpha < 1.0 {
                self.fade = Some(f);
                return;
            }
        }
        if self.next.is_none() {
            self.plan(g);
        }
        if let Some((edge, at)) = self.next
            && self.t >= at
        {
            let e = &g.edges[edge as usize];
            self.fade = Some(Fade {
                source: Source::Node {
                    node: self.node,
                    t: self.t,
                },
                alpha: 0.0,
                rate: 1.0 / f64::from(e.fade),
            });
            self.node = e.to;
            self.t = 0.0;
            self.next = None;
        }
    }

    /// Sends the head to node `to` now: the pose shown is frozen and faded from, over the
    /// fade of an edge from the current node to `to` if there is one, else
    /// [`DEFAULT_JUMP_FADE`] frames (at most the node's length).
    pub fn jump(&mut self, g: &Graph, rig: &Rig, to: u32) {
        let source = self.freeze(g, rig);
        let fade = g
            .edge(self.node, to)
            .map_or(DEFAULT_JUMP_FADE, |e| g.edges[e as usize].fade)
            .min(g.nodes[to as usize].len)
            .max(1);
        self.fade = Some(Fade {
            source,
            alpha: 0.0,
            rate: 1.0 / f64::from(fade),
        });
        self.node = to;
        self.t = 0.0;
        self.next = None;
        // A jump replaces what the script asked for; the walk goes on from `to`.
        self.script_at = self.script.len();
    }
}

/// What [`build`] found: the graph, each edge's cost (the mean vertex distance, over the
/// fade's window, between the frames it blends, as a fraction of the rig's diagonal; 0 for an
/// edge that plays a clip on), and what the pruning dropped.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Built {
    /// The graph, ready to store.
    pub graph: MotionGraph,
    /// Per edge of `graph`, its cost.
    pub costs: Vec<f32>,
    /// Candidate transitions found (local minima under the threshold).
    pub candidates: usize,
    /// Nodes dropped because they were outside the largest strongly connected component.
    pub dropped_nodes: usize,
}

/// Options of [`build`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BuildOptions {
    /// Frames compared per candidate transition, and the fade of the transitions made.
    pub window: u32,
    /// Largest mean vertex distance of a transition, as a fraction of the rig's diagonal.
    pub threshold: f32,
    /// Most transitions kept per (source clip, target clip), cheapest first.
    pub per_pair: usize,
}

impl Default for BuildOptions {
    fn default() -> Self {
        BuildOptions {
            window: 5,
            threshold: 0.02,
            per_pair: 8,
        }
    }
}

/// Most (source frame, target frame) pairs [`build`] compares for one pair of clips: the
/// distance grid it keeps (8 bytes a pair) grows with it, so larger clips are refused
/// ([`build_bytes`] returns `None`).
pub const MAX_BUILD_PAIRS: u64 = 1 << 22;

/// Vertices at which [`build`] compares the frames of a skinned rig.
pub const BUILD_SAMPLES: usize = 256;

/// Numbers per frame that [`build`] compares: the rig's channels (a rig without a skeleton),
/// or three coordinates per sampled vertex.
fn feature_len(rig: &Rig) -> u64 {
    match rig.skeleton {
        None => rig.targets.len() as u64,
        Some(_) => 3 * rig.vertex_count().min(BUILD_SAMPLES) as u64,
    }
}

/// Bytes [`build`] holds at most for `rig` (for the caller's charge): the frames' features,
/// the largest pair of clips' distance grid, the Gram matrix and its factor, the candidate
/// transitions. `None` when two clips are too long to compare ([`MAX_BUILD_PAIRS`]).
pub fn build_bytes(rig: &Rig, opt: BuildOptions) -> Option<u64> {
    let k = rig.targets.len() as u64;
    let frames: u64 = rig.clips.iter().map(|c| u64::from(c.frames)).sum();
    let longest = rig
        .clips
        .iter()
        .map(|c| u64::from(c.frames))
        .max()
        .unwrap_or(0);
    let pairs = longest * longest;
    let clips = rig.clips.len() as u64;
    (pairs <= MAX_BUILD_PAIRS).then(|| {
        frames * feature_len(rig) * 8
            + pairs * 8
            + k * k * 16
            + clips * clips * opt.per_pair as u64 * 64
            + rig.vertex_count().min(16 * BUILD_SAMPLES) as u64 * 24
            + 4096
    })
}

/// What [`build`] costs, in the unit of the server's `--max-graph-work` (about one multiply-add
/// each): every frame of every clip compared with every frame of every clip (the grid of each
/// ordered pair of clips, a clip with itself included, is frames × frames comparisons of
/// [`feature_len`] numbers, then the window's sums), plus turning the frames into features
/// (the Gram matrix, its factor and one projection per frame; or posing the sampled vertices)
/// and sorting the candidate transitions.
pub fn build_work(rig: &Rig, opt: BuildOptions) -> u64 {
    let k = rig.targets.len() as u64;
    let frames: u64 = rig.clips.iter().map(|c| u64::from(c.frames)).sum();
    let dims = feature_len(rig);
    let grid = frames
        .saturating_mul(frames)
        .saturating_mul(dims + u64::from(opt.window.max(1)));
    let features = match &rig.skeleton {
        None => {
            let deltas = rig.delta_count();
            deltas * k + k * k * k + frames * k * k
        }
        Some(sk) => {
            let samples = rig.vertex_count().min(BUILD_SAMPLES) as u64;
            16 * samples * samples * 16
                + samples * k * 32
                + frames * (64 * (sk.nodes.len() + sk.bones.len()) as u64 + samples * (k + 64))
        }
    };
    let clips = rig.clips.len() as u64;
    grid.saturating_add(features)
        .saturating_add(clips * clips * opt.per_pair as u64 * 64)
}

/// Per clip, every frame's features (`frames × len` numbers, frame-major), the length, and the
/// root of how many vertices a distance sums over: on a rig without a skeleton `Lᵀw` over all
/// vertices ([`projector`]); on a skinned rig the posed positions of [`BUILD_SAMPLES`]
/// vertices ([`Samples`]), where the joints move vertices as much as the weights do.
fn features(rig: &Rig, cancel: &Cancel) -> Result<(Vec<Vec<f64>>, usize, f64), Cancelled> {
    let mut wf = vec![0f32; rig.targets.len()];
    let mut out = Vec::with_capacity(rig.clips.len());
    match &rig.skeleton {
        None => {
            let project = projector(rig);
            cancel.check()?;
            for c in &rig.clips {
                let mut flat = Vec::with_capacity(c.frames as usize * rig.targets.len());
                for f in 0..c.frames {
                    c.frame_weights(f, &mut wf);
                    flat.extend(project(&wf));
                }
                cancel.check()?;
                out.push(flat);
            }
            Ok((
                out,
                rig.targets.len(),
                (rig.vertex_count().max(1) as f64).sqrt(),
            ))
        }
        Some(sk) => {
            let samples = Samples::of(rig);
            cancel.check()?;
            let (mut locals, mut globals, mut bones) = (Vec::new(), Vec::new(), Vec::new());
            for c in &rig.clips {
                let mut flat = Vec::with_capacity(c.frames as usize * samples.len() * 3);
                for f in 0..c.frames {
                    c.frame_weights(f, &mut wf);
                    sk.locals_at(c.joints.as_deref(), f, &mut locals);
                    bones.clear();
                    sk.bone_matrices(&locals, &mut globals, &mut bones);
                    samples.pose(rig, &wf, &bones, &mut flat);
                }
                cancel.check()?;
                out.push(flat);
            }
            Ok((out, samples.len() * 3, (samples.len().max(1) as f64).sqrt()))
        }
    }
}

/// The vertices a skinned rig's frames are compared at: [`BUILD_SAMPLES`] of them spread over
/// the mesh (farthest-point sampling of the bind positions, among at most 16 times as many
/// candidates taken evenly through the vertex order), each with the deltas that move it.
struct Samples {
    at: Vec<Sample>,
}

/// One sampled vertex: its primitive, its index there, and the (channel, delta) pairs that
/// move it.
type Sample = (usize, usize, Vec<(usize, Vec3)>);

impl Samples {
    fn of(rig: &Rig) -> Samples {
        let total = rig.vertex_count();
        let want = total.min(BUILD_SAMPLES);
        let stride = total.div_ceil((16 * BUILD_SAMPLES).max(1)).max(1);
        // (primitive, vertex, bind position) of the candidates.
        let mut candidates: Vec<(usize, usize, Vec3)> = Vec::new();
        let mut v = 0usize;
        for (pi, p) in rig.primitives.iter().enumerate() {
            for (i, x) in p.positions.iter().enumerate() {
                if v.is_multiple_of(stride) {
                    candidates.push((pi, i, *x));
                }
                v += 1;
            }
        }
        let mut chosen: Vec<usize> = Vec::with_capacity(want);
        let mut nearest = vec![f32::INFINITY; candidates.len()];
        let mut next = 0usize;
        while chosen.len() < want && next < candidates.len() {
            chosen.push(next);
            let c = candidates[next].2;
            let mut far = (0usize, -1f32);
            for (k, (d, cand)) in nearest.iter_mut().zip(&candidates).enumerate() {
                *d = d.min(cand.2.distance_squared(c));
                if *d > far.1 {
                    far = (k, *d);
                }
            }
            if far.1 <= 0.0 {
                // Every candidate left sits on a chosen one.
                break;
            }
            next = far.0;
        }
        chosen.sort_unstable();
        let at = chosen
            .into_iter()
            .map(|k| {
                let (pi, i, _) = candidates[k];
                let deltas = rig.primitives[pi]
                    .targets
                    .iter()
                    .filter_map(|t| {
                        let at = t.vertices.binary_search(&(i as u32)).ok()?;
                        Some((t.target as usize, *t.positions.get(at)?))
                    })
                    .collect();
                (pi, i, deltas)
            })
            .collect();
        Samples { at }
    }

    fn len(&self) -> usize {
        self.at.len()
    }

    /// Appends each sample's position with weights `w` and bones `bones`: morph targets, then
    /// skinning, as the engines pose it (a vertex that follows no bone stays as blended).
    fn pose(
        &self,
        rig: &Rig,
        w: &[f32],
        bones: &[crowdmorph_core::rig::BoneMatrix],
        out: &mut Vec<f64>,
    ) {
        for (pi, i, deltas) in &self.at {
            let p = &rig.primitives[*pi];
            let mut x = p.positions[*i];
            for &(t, d) in deltas {
                x += w.get(t).copied().unwrap_or(0.0) * d;
            }
            let posed = match &p.skin {
                Some(s) if s.weights.get(*i).is_some_and(|w| w[0] != 0.0) => {
                    s.skin(*i, bones, x, None).0
                }
                _ => x,
            };
            out.extend([posed.x, posed.y, posed.z].map(f64::from));
        }
    }
}

/// Builds a motion graph from the rig's clips the way Kovar et al. (2002) do: frame distances
/// in vertex space — on a rig without a skeleton `‖Dᵀ(w_a − w_b)‖` over the rig's deltas
/// (computed as `‖Lᵀ(w_a − w_b)‖` with `L` the Cholesky factor of the Gram matrix `DDᵀ`, so a
/// pair costs K operations, not a mesh), on a skinned rig the posed positions of
/// [`BUILD_SAMPLES`] vertices spread over it, so that what the joints move counts — averaged
/// over a window of frames; the local minima under the threshold become transitions; clips
/// are cut into nodes where transitions land, nodes of one clip play on into each other, and
/// the graph is pruned to its largest strongly connected component (so every node can reach
/// every other). `Ok(None)` when no clip has a window's frames; `Err` when `cancel` stops it
/// (checked after every row of a grid, a few milliseconds apart at most).
pub fn build(rig: &Rig, opt: BuildOptions, cancel: &Cancel) -> Result<Option<Built>, Cancelled> {
    if build_bytes(rig, opt).is_none() {
        return Ok(None);
    }
    let w = opt.window.max(1) as usize;
    let diag = f64::from(rig.bbox().diagonal()).max(1e-12);
    let (frames, dims, norm) = features(rig, cancel)?;
    let count = |c: usize| frames[c].len() / dims.max(1);
    // Candidate transitions (source clip, source frame, target clip, target frame, cost).
    let mut candidates: Vec<(usize, u32, usize, u32, f64)> = Vec::new();
    let mut grid: Vec<f64> = Vec::new();
    for a in 0..frames.len() {
        for b in 0..frames.len() {
            let (fa, fb) = (count(a), count(b));
            if fa < w || fb < w {
                continue;
            }
            // Every frame pair's distance, then in place each window's mean along the
            // diagonal: cell (i, j) reads cells (i + k, j + k), which later rows still hold.
            grid.clear();
            grid.resize(fa * fb, 0.0);
            for i in 0..fa {
                cancel.check()?;
                let x = &frames[a][i * dims..(i + 1) * dims];
                for j in 0..fb {
                    let y = &frames[b][j * dims..(j + 1) * dims];
                    grid[i * fb + j] = x
                        .iter()
                        .zip(y)
                        .map(|(p, q)| (p - q) * (p - q))
                        .sum::<f64>()
                        .sqrt();
                }
            }
            let (ni, nj) = (fa - w + 1, fb - w + 1);
            let scale = 1.0 / w as f64 / norm / diag;
            for i in 0..ni {
                for j in 0..nj {
                    let sum: f64 = (0..w).map(|k| grid[(i + k) * fb + j + k]).sum();
                    grid[i * fb + j] = sum * scale;
                }
            }
            let at = |i: isize, j: isize| -> f64 {
                if i < 0 || j < 0 || i as usize >= ni || j as usize >= nj {
                    f64::INFINITY
                } else {
                    grid[i as usize * fb + j as usize]
                }
            };
            let mut found = Vec::new();
            for i in 0..ni {
                for j in 0..nj {
                    // A clip's frame with itself, or its next few, is no transition.
                    if a == b && i.abs_diff(j) <= w {
                        continue;
                    }
                    let c = grid[i * fb + j];
                    if c > f64::from(opt.threshold) {
                        continue;
                    }
                    let (ii, jj) = (i as isize, j as isize);
                    let minimum = (-1..=1).all(|di| {
                        (-1..=1).all(|dj| (di == 0 && dj == 0) || at(ii + di, jj + dj) >= c)
                    });
                    if minimum {
                        found.push((a, i as u32, b, j as u32, c));
                    }
                }
            }
            found.sort_by(|x, y| x.4.total_cmp(&y.4));
            found.truncate(opt.per_pair);
            candidates.extend(found);
        }
    }
    drop(grid);
    cancel.check()?;
    // Transitions landing a few frames apart in one clip would cut it into slivers: the
    // cheapest lands, and others land on the same frame or at least a window away. (Sets and
    // maps, not scans: a rig with many clips has many candidates.)
    candidates.sort_by(|x, y| x.4.total_cmp(&y.4));
    let wu = w as u32;
    let mut landed: Vec<BTreeSet<u32>> = rig.clips.iter().map(|_| BTreeSet::new()).collect();
    let mut taken: HashMap<(usize, usize, u32), Vec<u32>> = HashMap::new();
    candidates.retain(|&(a, i, b, j, _)| {
        // The same landing from a few frames earlier or later of the same source is the same
        // transition.
        if taken
            .get(&(a, b, j))
            .is_some_and(|from| from.iter().any(|&ti| ti.abs_diff(i) < wu))
        {
            return false;
        }
        let here = &mut landed[b];
        if !here.contains(&j) {
            let near = here
                .range(j.saturating_sub(wu - 1)..=j.saturating_add(wu - 1))
                .next()
                .is_some();
            if near || (j < wu && j != 0) {
                return false;
            }
            here.insert(j);
        }
        taken.entry((a, b, j)).or_default().push(i);
        true
    });
    drop(taken);
    // Nodes: each clip cut where a transition lands.
    let mut cuts: Vec<Vec<u32>> = rig.clips.iter().map(|_| vec![0]).collect();
    for &(_, _, b, j, _) in &candidates {
        cuts[b].push(j);
    }
    for c in &mut cuts {
        c.sort_unstable();
        c.dedup();
    }
    // (clip, first, last) per node, and per clip the index of its first node.
    let mut nodes: Vec<(usize, u32, u32)> = Vec::new();
    let mut first_node: Vec<Option<usize>> = vec![None; rig.clips.len()];
    for (ci, c) in cuts.iter().enumerate() {
        let n = rig.clips[ci].frames;
        if (n as usize) < w {
            continue;
        }
        first_node[ci] = Some(nodes.len());
        for (k, &first) in c.iter().enumerate() {
            let last = c.get(k + 1).map_or(n - 1, |&x| x - 1);
            nodes.push((ci, first, last));
        }
    }
    let node_of = |clip: usize, frame: u32| -> Option<usize> {
        let start = first_node[clip]?;
        if frame >= rig.clips[clip].frames {
            return None;
        }
        let k = cuts[clip].partition_point(|&x| x <= frame).checked_sub(1)?;
        Some(start + k)
    };
    // Edges (from, to, fade, window start, cost).
    let mut edges: Vec<(usize, usize, u32, u32, f64)> = Vec::new();
    for (n, &(c, _, last)) in nodes.iter().enumerate() {
        if let Some(next) = node_of(c, last + 1) {
            let len = last + 1 - nodes[n].1;
            edges.push((n, next, 1, len - 1, 0.0));
        }
    }
    for &(a, i, b, j, cost) in &candidates {
        let (Some(from), Some(to)) = (node_of(a, i), node_of(b, j)) else {
            continue;
        };
        let (first, last) = (nodes[from].1, nodes[from].2);
        let fade = wu.min(last - first + 1).min(nodes[to].2 - nodes[to].1 + 1);
        edges.push((from, to, fade, i - first, cost));
    }
    let keep = largest_scc(nodes.len(), &edges);
    let kept: Vec<usize> = (0..nodes.len()).filter(|&n| keep[n]).collect();
    if kept.is_empty() {
        return Ok(None);
    }
    let name = |n: usize| {
        let (c, f, l) = nodes[n];
        format!("{}@{f}-{l}", rig.clips[c].name)
    };
    let mut graph = MotionGraph::default();
    for &n in &kept {
        let (c, f, l) = nodes[n];
        graph.nodes.push(crowdmorph_proto::GraphNode {
            name: name(n),
            clip: rig.clips[c].name.clone(),
            frames: Some([f, l]),
        });
    }
    let mut costs = Vec::new();
    for &(from, to, fade, at, cost) in &edges {
        if keep[from] && keep[to] {
            graph.edges.push(crowdmorph_proto::GraphEdge {
                from: name(from),
                to: name(to),
                fade,
                window: Some([at, at]),
            });
            costs.push(cost as f32);
        }
    }
    Ok(Some(Built {
        graph,
        costs,
        candidates: candidates.len(),
        dropped_nodes: nodes.len() - kept.len(),
    }))
}

/// `w ↦ Lᵀw` with `LLᵀ = DDᵀ` (the Gram matrix of the rig's position deltas over all
/// vertices), so that `‖Lᵀ(w_a − w_b)‖ = ‖Dᵀ(w_a − w_b)‖`. The factor is a Cholesky
/// decomposition that zeroes a column whose pivot vanishes (shapes that repeat others), which
/// keeps the identity for the positive semi-definite Gram matrix.
fn projector(rig: &Rig) -> impl Fn(&[f32]) -> Vec<f64> {
    let k = rig.targets.len();
    let mut g = vec![0f64; k * k];
    for p in rig.primitives.iter() {
        // Per vertex, the (channel, delta) pairs that move it.
        let mut by_vertex: HashMap<u32, Vec<(usize, Vec3)>> = HashMap::new();
        for t in &p.targets {
            for (&vtx, d) in t.vertices.iter().zip(&t.positions) {
                by_vertex
                    .entry(vtx)
                    .or_default()
                    .push((t.target as usize, *d));
            }
        }
        for list in by_vertex.values() {
            for &(a, da) in list {
                for &(b, db) in list {
                    g[a * k + b] += f64::from(da.dot(db));
                }
            }
        }
    }
    let mut l = vec![0f64; k * k];
    let scale = (0..k).map(|i| g[i * k + i]).fold(0.0, f64::max).max(1e-300);
    for j in 0..k {
        let d = g[j * k + j] - (0..j).map(|m| l[j * k + m] * l[j * k + m]).sum::<f64>();
        if d <= 1e-12 * scale {
            continue;
        }
        let ljj = d.sqrt();
        l[j * k + j] = ljj;
        for i in j + 1..k {
            let s = g[i * k + j] - (0..j).map(|m| l[i * k + m] * l[j * k + m]).sum::<f64>();
            l[i * k + j] = s / ljj;
        }
    }
    move |w: &[f32]| {
        // (Lᵀ w)_j = Σ_i L[i][j] w_i
        (0..k)
            .map(|j| (j..k).map(|i| l[i * k + j] * f64::from(w[i])).sum())
            .collect()
    }
}

/// Which nodes belong to the largest strongly connected component of the edges (Tarjan's
/// algorithm, iterative); a lone node counts only with a self-loop.
fn largest_scc(n: usize, edges: &[(usize, usize, u32, u32, f64)]) -> Vec<bool> {
    let mut out: Vec<Vec<usize>> = vec![Vec::new(); n];
    for &(a, b, ..) in edges {
        out[a].push(b);
    }
    let mut index = vec![usize::MAX; n];
    let mut low = vec![0; n];
    let mut on = vec![false; n];
    let mut stack = Vec::new();
    let mut next = 0;
    let mut best: Vec<usize> = Vec::new();
    for root in 0..n {
        if index[root] != usize::MAX {
            continue;
        }
        let mut call: Vec<(usize, usize)> = vec![(root, 0)];
        index[root] = next;
        low[root] = next;
        next += 1;
        stack.push(root);
        on[root] = true;
        while let Some(&mut (v, ref mut e)) = call.last_mut() {
            if let Some(&u) = out[v].get(*e) {
                *e += 1;
                if index[u] == usize::MAX {
                    index[u] = next;
                    low[u] = next;
                    next += 1;
                    stack.push(u);
                    on[u] = true;
                    call.push((u, 0));
                } else if on[u] {
                    low[v] = low[v].min(index[u]);
                }
                continue;
            }
            call.pop();
            if let Some(&(parent, _)) = call.last() {
                low[parent] = low[parent].min(low[v]);
            }
            if low[v] == index[v] {
                let mut comp = Vec::new();
                while let Some(x) = stack.pop() {
                    on[x] = false;
                    comp.push(x);
                    if x == v {
                        break;
                    }
                }
                let cyclic = comp.len() > 1 || out[v].contains(&v);
                if cyclic && comp.len() > best.len() {
                    best = comp;
                }
            }
        }
    }
    let mut keep = vec![false; n];
    for x in best {
        keep[x] = true;
    }
    keep
}

#[cfg(test)]
mod tests {
    use super::*;
    use crowdmorph_proto::{GraphEdge, GraphNode};

    fn spec() -> MotionGraph {
        let node = |name: &str, clip: &str| GraphNode {
            name: name.into(),
            clip: clip.into(),
            frames: None,
        };
        let edge = |from: &str, to: &str, fade| GraphEdge {
            from: from.into(),
            to: to.into(),
            fade,
            window: None,
        };
        MotionGraph {
            nodes: vec![node("talk", "talk"), node("smile", "smile")],
            edges: vec![edge("talk", "smile", 10), edge("smile", "talk", 10)],
        }
    }

    fn graph(spec: &MotionGraph) -> Result<Graph, GraphError> {
        let rig = crowdmorph_core::embedded::default_rig();
        Graph::resolve(spec, &rig, |n| rig.clip_index(n))
    }

    /// Every vertex of `rig` posed with weights `w` and node transforms `locals`: morph
    /// targets, then skinning, written out here from the glTF rule rather than taken from an
    /// engine.
    fn posed(rig: &Rig, w: &[f32], locals: &[Trs]) -> Vec<Vec3> {
        let sk = rig.skeleton.as_ref().expect("skinned");
        let mut bones = Vec::new();
        sk.bone_matrices(locals, &mut Vec::new(), &mut bones);
        let mut out = Vec::new();
        for p in rig.primitives.iter() {
            let mut x = p.positions.clone();
            for t in &p.targets {
                for (&v, d) in t.vertices.iter().zip(&t.positions) {
                    x[v as usize] += w[t.target as usize] * *d;
                }
            }
            for (i, x) in x.into_iter().enumerate() {
                out.push(match &p.skin {
                    Some(s) if s.weights[i][0] != 0.0 => {
                        let mut sum = Vec3::ZERO;
                        for k in 0..4 {
                            let b = &bones[s.joints[i][k] as usize];
                            sum += s.weights[i][k] * b.point(x);
                        }
                        sum
                    }
                    _ => x,
                });
            }
        }
        out
    }

    fn largest_step(a: &[Vec3], b: &[Vec3]) -> f32 {
        a.iter()
            .zip(b)
            .map(|(p, q)| p.distance(*q))
            .fold(0.0, f32::max)
    }

    #[test]
    fn a_skinned_heads_fades_and_override_changes_stay_within_the_bound() {
        // The skinned face with its clips' weights removed: only the joints move it, as on
        // RobotExpressive, whose clips animate no weights. A bound that counts weights alone
        // lets every fade and every change of overrides through in one tick.
        let mut rig = crowdmorph_core::synthetic::skinned_head();
        for c in &mut rig.clips {
            c.weights = Arc::new(vec![0.0; c.weights.len()]);
        }
        let sk = rig.skeleton.clone().expect("skinned");
        let mut g = Graph::resolve(&spec(), &rig, |n| rig.clip_index(n)).expect("graph");
        // Each node's motion as the server measures it (its largest per-frame step), here from
        // the rule above.
        let mut motion = Vec::new();
        for n in &g.nodes {
            let clip = &rig.clips[n.clip as usize];
            let frame = |f: u32| {
                let mut l = Vec::new();
                sk.locals_at(clip.joints.as_deref(), f, &mut l);
                let mut w = vec![0.0; rig.targets.len()];
                clip.frame_weights(f, &mut w);
                posed(&rig, &w, &l)
            };
            let mut largest = 0f32;
            for f in n.first + 1..n.first + n.len {
                largest = largest.max(largest_step(&frame(f - 1), &frame(f)));
            }
            motion.push(largest);
        }
        let bound = 1.5 * motion.iter().copied().fold(0.0, f32::max);
        assert!(bound > 0.0, "the clips move the joints");
        g.set_motion(motion);
        let mut p = Player::new(&g, 0, Vec::new(), 11);
        let shown = |p: &Player| {
            posed(
                &rig,
                &p.weights(&g, &rig),
                &p.locals(&g, &rig).expect("skinned"),
            )
        };
        let mut prev = shown(&p);
        let head = sk
            .nodes
            .iter()
            .position(|n| n.name == "Head")
            .expect("a Head joint") as u32;
        let turn = JointPose::new(vec![crowdmorph_core::rig::JointSet::new(
            head,
            None,
            Some(Quat::from_rotation_y(0.8).to_array()),
            None,
        )]);
        let (mut largest, mut fades) = (0f32, 0);
        for tick in 0..900 {
            match tick {
                100 => p.jump(&g, &rig, 1),
                103 => p.jump(&g, &rig, 0),
                300 => p.set_overrides(&g, &rig, turn.clone()),
                500 => {
                    p.set_overrides(&g, &rig, JointPose::NONE);
                    p.jump(&g, &rig, 1);
                }
                _ => {}
            }
            p.advance(&g, &rig, 1.0 / 30.0);
            fades += usize::from(p.fading());
            let now = shown(&p);
            let d = largest_step(&prev, &now);
            largest = largest.max(d);
            assert!(d <= bound, "tick {tick}: a vertex moved {d}, past {bound}");
            prev = now;
        }
        assert!(fades > 20, "the walk faded ({fades} ticks)");
        assert!(!p.fading() || p.overrides.is_none());
        eprintln!("largest per-tick step {largest}, bound {bound}");
        // The override change was shown in full once its fade ended.
        let mut p = Player::new(&g, 0, Vec::new(), 11);
        p.set_overrides(&g, &rig, turn.clone());
        for _ in 0..2000 {
            if !p.fading() {
                break;
            }
            p.advance(&g, &rig, 1.0 / 30.0);
        }
        assert!(!p.fading(), "the change's fade ends");
        assert_eq!(p.joints(&g, &rig), turn);
    }

    #[test]
    fn a_build_stops_at_its_cancellation() {
        let rig = crowdmorph_core::embedded::default_rig();
        let (cancel, guard) = Cancel::new(None);
        drop(guard);
        assert_eq!(
            build(&rig, BuildOptions::default(), &cancel),
            Err(Cancelled::Dropped)
        );
        let (late, _guard) = Cancel::new(Some(std::time::Instant::now()));
        assert_eq!(
            build(&rig, BuildOptions::default(), &late),
            Err(Cancelled::Deadline)
        );
        assert!(build_work(&rig, BuildOptions::default()) > 0);
    }

    #[test]
    fn a_skinned_rigs_build_compares_what_the_joints_move() {
        // Only the joints move the skinned face (its clips' weights removed): a distance of
        // weights alone would make every transition free.
        let mut rig = crowdmorph_core::synthetic::skinned_head();
        for c in &mut rig.clips {
            c.weights = Arc::new(vec![0.0; c.weights.len()]);
        }
        let opt = BuildOptions {
            threshold: 1.0,
            ..BuildOptions::default()
        };
        let built = build(&rig, opt, &Cancel::never())
            .expect("not cancelled")
            .expect("a graph");
        let transitions: Vec<f32> = built
            .graph
            .edges
            .iter()
            .zip(&built.costs)
            .filter(|(e, _)| e.fade > 1)
            .map(|(_, &c)| c)
            .collect();
        assert!(!transitions.is_empty(), "{built:?}");
        assert!(
            transitions.iter().all(|&c| c > 0.0),
            "every transition between different poses costs something: {transitions:?}"
        );
    }

    #[test]
    fn malformed_graphs_name_the_field() {
        assert!(graph(&spec()).is_ok());
        let mut s = spec();
        s.edges[0].fade = 0;
        assert!(matches!(graph(&s), Err(GraphError::Invalid(m)) if m.contains("edges[0].fade")));
        let mut s = spec();
        s.edges[1].fade = 100_000;
        assert!(matches!(graph(&s), Err(GraphError::Invalid(m)) if m.contains("longer")));
        let mut s = spec();
        s.edges.pop();
        assert!(matches!(graph(&s), Err(GraphError::Invalid(m)) if m.contains("no edge out")));
        let mut s = spec();
        s.nodes[1].clip = "nope".into();
        assert!(matches!(graph(&s), Err(GraphError::UnknownClip { .. })));
        let mut s = spec();
        s.edges[0].to = "nobody".into();
        assert!(matches!(graph(&s), Err(GraphError::Invalid(m)) if m.contains("edges[0].to")));
        let mut s = spec();
        s.edges[0].window = Some([5, 100_000]);
        assert!(matches!(graph(&s), Err(GraphError::Invalid(m)) if m.contains("window")));
    }

    #[test]
    fn clips_too_long_to_compare_are_refused_before_any_work() {
        let rig = crowdmorph_core::embedded::default_rig();
        let opt = BuildOptions::default();
        assert!(build_bytes(&rig, opt).is_some());
        let long = crowdmorph_core::synthetic::with_random_clip_of(rig, "long", 3000, 1);
        assert_eq!(build_bytes(&long, opt), None);
        assert_eq!(build(&long, opt, &Cancel::never()), Ok(None));
    }

    #[test]
    fn players_alike_stay_alike_and_fades_end_in_the_target() {
        let rig = crowdmorph_core::embedded::default_rig();
        let mut g = graph(&spec()).expect("a valid graph");
        g.set_motion(vec![0.01, 0.01]);
        let mut a = Player::new(&g, 0, Vec::new(), 7);
        let mut b = a.clone();
        let mut seen_fade = false;
        for _ in 0..2000 {
            a.advance(&g, &rig, 1.0 / 30.0);
            b.advance(&g, &rig, 1.0 / 30.0);
            assert_eq!(a.pose(&g, &rig), b.pose(&g, &rig));
            seen_fade |= a.fading();
        }
        assert!(seen_fade, "the walk took an edge");
    }

    #[test]
    fn a_jump_fades_a_skinned_heads_joints_from_where_they_were() {
        // The skinned face's clips turn its head and eyes. A jump fades from the frozen pose,
        // shown as a blend of its clip terms into the target's frames; the joints it froze go
        // along as overrides wherever that blend's terms would show something else: the
        // skeleton does not snap, it fades into the target.
        let rig = crowdmorph_core::synthetic::skinned_head();
        let mut g = Graph::resolve(&spec(), &rig, |n| rig.clip_index(n)).expect("graph");
        g.set_motion(vec![0.01, 0.01]);
        let mut p = Player::new(&g, 0, Vec::new(), 3);
        for _ in 0..17 {
            p.advance(&g, &rig, 1.0 / 30.0);
        }
        let before = p.locals(&g, &rig).expect("skinned");
        p.jump(&g, &rig, 1);
        assert!(
            !matches!(p.pose(&g, &rig), Pose::Live(_)),
            "a jump fades from the clip terms shown"
        );
        let sk = rig.skeleton.as_ref().expect("skinned");
        // What the engine draws: the pose's joint terms, then the overrides.
        let shown = |p: &Player| {
            let mut out = Vec::new();
            sk.locals_of(&p.pose(&g, &rig).skin_terms(&rig), &mut out);
            p.joints(&g, &rig).apply(sk, &mut out);
            out
        };
        // Right after the jump the drawn joints are the frozen transforms.
        for (a, b) in shown(&p).iter().zip(&before) {
            let qa = Quat::from_array(a.rotation);
            let qb = Quat::from_array(b.rotation);
            assert!(qa.angle_between(qb) < 1e-4, "{a:?} vs {b:?}");
        }
        assert!(
            before.iter().zip(&sk.nodes).any(|(l, n)| *l != n.rest),
            "the clip had turned some joint"
        );
        // Through the fade the drawn joints are the player's own nlerp of the two.
        let mut steps = 0;
        while p.fading_from_frozen() {
            let want = p.locals(&g, &rig).expect("skinned");
            for (a, b) in shown(&p).iter().zip(&want) {
                // Overrides are quantized: equal to their step, in any hemisphere.
                let d = Quat::from_array(a.rotation).dot(Quat::from_array(b.rotation));
                assert!(d.abs() > 1.0 - 1e-6, "step {steps}: {a:?} vs {b:?}");
                let t = Vec3::from(a.translation).distance(Vec3::from(b.translation));
                assert!(t < 1e-3, "step {steps}: {a:?} vs {b:?}");
            }
            p.advance(&g, &rig, 1.0 / 30.0);
            steps += 1;
            assert!(steps < 2000, "the jump's fade ends");
        }
        assert!(steps > 1, "the jump faded");
        assert!(p.joints(&g, &rig).is_none());
    }

    /// A two-pixel animated texture of `frames` frames for clip `clip`, one component whose
    /// coefficient is the frame number (so a blend of frames shows as a blend of numbers).
    fn frame_texture(clip: &str, frames: u32) -> crowdmorph_core::rig::AnimatedTexture {
        crowdmorph_core::rig::AnimatedTexture {
            clip: clip.into(),
            material: 0,
            width: 2,
            height: 1,
            frames,
            regions: vec![crowdmorph_core::rig::TextureRegion {
                name: "all".into(),
                rect: [0, 0, 2, 1],
                components: 1,
            }],
            mean: vec![0.5; 6],
            components: vec![vec![0.01; 6]],
            component_region: vec![0],
            coefficients: (0..frames).map(|f| f as f32).collect(),
        }
    }

    #[test]
    fn a_jump_fades_the_clips_animated_textures_with_their_weights() {
        // A clip's animated texture reads its coefficients from the clip terms of the pose
        // (`layer_inputs`): a jump's fade must keep the frozen pose's clip terms, or the
        // texture would drop to the base colour for the whole fade while the weights fade.
        use crowdmorph_core::rig::{Appearance, Material, layer_inputs};
        let mut rig = crowdmorph_core::embedded::default_rig();
        let frames = |name: &str| rig.clips[rig.clip_index(name).expect("clip")].frames;
        let (talk, smile) = (frames("talk"), frames("smile"));
        rig.appearance = Some(Arc::new(Appearance {
            materials: vec![Material::default()],
            clip_textures: vec![
                Arc::new(frame_texture("talk", talk)),
                Arc::new(frame_texture("smile", smile)),
            ],
            ..Appearance::default()
        }));
        let g = graph(&spec()).expect("graph");
        let mut p = Player::new(&g, 0, Vec::new(), 5);
        for _ in 0..3 {
            p.advance(&g, &rig, 1.0 / 30.0);
        }
        let t = rig.targets.len();
        // Per clip texture: the clip's share, then its one coefficient.
        let shares = |p: &Player| {
            let v = layer_inputs(&rig, &p.pose(&g, &rig), 0);
            (v[t], v[t + 1], v[t + 2], v[t + 3])
        };
        let (talk_share, talk_c, ..) = shares(&p);
        assert!(!p.fading() && talk_share == 1.0, "plays talk: {talk_share}");
        p.jump(&g, &rig, 1);
        // The first frame of the fade still shows talk's texture where it was.
        assert_eq!(shares(&p), (1.0, talk_c, 0.0, 0.0));
        let mut seen_mixed = false;
        let mut steps = 0;
        while p.fading_from_frozen() {
            p.advance(&g, &rig, 1.0 / 30.0);
            let (ts, tc, ss, sc) = shares(&p);
            // The shares fade as the weights do, and always sum to one: the surface never
            // falls back to the base colour.
            assert!((ts + ss - 1.0).abs() < 1e-6, "shares {ts} + {ss}");
            assert!(
                (tc - ts * talk_c).abs() < 1e-3,
                "talk's coefficient stays frozen"
            );
            let w = p.weights(&g, &rig);
            let drawn = p.pose(&g, &rig).weights(&rig);
            for (a, b) in w.iter().zip(&drawn) {
                assert!((a - b).abs() < 2e-3, "the pose draws the fade's weights");
            }
            let _ = sc;
            seen_mixed |= ts > 0.1 && ss > 0.1;
            steps += 1;
            assert!(steps < 2000, "the fade ends");
        }
        assert!(seen_mixed, "the fade blended the two textures");
        assert_eq!(shares(&p).2, 1.0, "ends on smile's texture");
        // A rig changed under a fade (talk replaced by a one-frame clip): the frozen terms no
        // longer fit it, and the fade goes on as live weights instead of reading past the
        // clip's end.
        p.jump(&g, &rig, 0);
        for _ in 0..5 {
            p.advance(&g, &rig, 1.0 / 30.0);
        }
        let mut shorter = rig.clone();
        let ti = shorter.clip_index("talk").expect("talk");
        let one = crowdmorph_core::rig::Clip::from_frames(
            "talk",
            30.0,
            shorter.targets.len(),
            &[vec![0.0; shorter.targets.len()]],
        )
        .expect("clip");
        shorter.clips[ti] = one;
        p.jump(&g, &rig, 1);
        assert!(matches!(p.pose(&g, &shorter), Pose::Live(_)));
        p.advance(&g, &rig, 1.0 / 30.0);
        while p.fading_from_frozen() {
            p.advance(&g, &rig, 1.0 / 30.0);
        }
        // A jump in the middle of a jump's fade keeps all the clip terms it shows.
        p.jump(&g, &rig, 0);
        p.advance(&g, &rig, 1.0 / 30.0);
        p.jump(&g, &rig, 1);
        let (ts, _, ss, _) = shares(&p);
        assert!(
            (ts + ss - 1.0).abs() < 1e-6 && ts > 0.0,
            "the second jump froze a blend: {ts} + {ss}"
        );
    }
}
