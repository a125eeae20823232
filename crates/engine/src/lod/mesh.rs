//! Feature-preserving mesh level of detail ("Multiresolution facial mesh for real-time
//! animation", §3).
//!
//! 1. **Feature points.** On an upright head (+Y up, face toward +Z) the paper's heuristics are
//!    run on the visible front surface, rendered as a depth map of the skin (the largest
//!    connected piece of the largest primitive): nose tip = highest z; nose top, nose bottom
//!    and the sides of the nose, the eye sockets, the lips, chin and throat are local extrema of
//!    depth along rays from earlier points. The lip contact line is the crease between the lips,
//!    traced sideways from its centre; its ends are the mouth corners. Any vertex whose deltas
//!    are large — each target's peak — is a feature too ("motion peaks"), so a rig that is not
//!    a face still keeps the points that animate most.
//! 2. **Simplification.** Garland–Heckbert quadric error metric edge collapse by `meshopt`
//!    (meshoptimizer's simplifier). It fits the paper's scheme: collapses are half-edge (a vertex
//!    merges into a neighbour, so the simplified mesh uses only original vertices and the vertex
//!    correspondence is exact); feature points are *locked* (the paper weights them so they are
//!    not removed; a lock guarantees it); their 1- and 2-ring neighbours carry meshopt's
//!    *priority* flag (the paper's neighbour weighting that enlarges the preserved region); and
//!    the deltas of the most energetic targets are attributes of the quadric, so collapses that
//!    would flatten motion — not only shape — cost more. Writing our own QEM would duplicate a
//!    well-kept library and still need all of this.
//! 3. **Appearance.** Texture coordinates are attributes too (within meshoptimizer's 32 floats,
//!    which caps the motion targets), UV seams are never collapsed across (no `Permissive`:
//!    equal-position vertices stay wedges of one point), and where primitives — materials —
//!    meet, their shared open-border vertices are locked. Feature points stay locked whatever
//!    the UVs say: a lock outranks every attribute cost.
//! 4. **Delta transfer.** Every vertex of a level is an original vertex, so it takes its deltas
//!    (and neutral normal, tangent, texture coordinates) directly; [`mesh_level_rig`] builds
//!    the derived [`Rig`] (fewer vertices, same targets, clips and LOD order) that any engine
//!    evaluates unchanged.

use std::collections::VecDeque;

use glam::Vec3;
use meshopt::{SimplifyOptions as MeshoptOptions, SimplifyVertex};
use serde::{Deserialize, Serialize};

use super::Progress;
use crate::lod::raster::{Camera, Frame, MeshView, NO_VERTEX, render};
use crowdmorph_core::rig::{
    Lod, MeshLevel, MeshLevelPrimitive, Primitive, Rig, RigError, SparseTarget, TargetId,
};

/// Why a mesh level could not be built or applied.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum MeshLodError {
    /// A triangle fraction outside (0, 1].
    #[error("mesh fraction {0} (of the triangles) is not in (0, 1]")]
    BadFraction(f32),
    /// The mesh level does not fit the rig (built for another rig).
    #[error("mesh level does not fit the rig: {0}")]
    Mismatch(String),
    /// The derived rig is not valid.
    #[error(transparent)]
    Rig(#[from] RigError),
    /// The job was cancelled through its [`Progress`] between two levels.
    #[error("cancelled")]
    Cancelled,
}

/// How to find feature points and simplify.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SimplifyOptions {
    /// Run the facial landmark heuristics (the rig is an upright head facing +Z).
    pub facial_landmarks: bool,
    /// Side of the depth map the landmarks are found on, in pixels.
    pub feature_image_size: u32,
    /// A vertex is a motion peak of a target when its displacement is at least this fraction
    /// of the target's largest.
    pub peak_fraction: f32,
    /// At most this many motion peaks per target (largest first).
    pub peaks_per_target: usize,
    /// Rings of neighbours around feature points that get simplification priority.
    pub priority_rings: u32,
    /// How many of the most energetic targets steer collapses through their deltas (≤ 10:
    /// their 3 floats each and a primitive's u, v share meshoptimizer's 32 attribute floats).
    pub motion_targets: usize,
    /// Weight of those deltas against position error (deltas are scaled by the rig extent,
    /// as positions are).
    pub motion_weight: f32,
    /// Weight of texture coordinates (set 0) against position error, where a primitive has
    /// them; 0 leaves them out of the quadric. UVs steer which collapses are cheap; seams are
    /// kept regardless (see [`simplify_level`]).
    #[serde(default = "default_uv_weight")]
    pub uv_weight: f32,
    /// Locks the vertices on a primitive's open border that another primitive also has (same
    /// position): a material boundary then neither opens a crack nor shifts at any level.
    #[serde(default = "default_true")]
    pub lock_material_borders: bool,
}

/// Options recorded before `uv_weight` existed read back with this value.
fn default_uv_weight() -> f32 {
    0.5
}

/// Options recorded before `lock_material_borders` existed lock material borders too.
fn default_true() -> bool {
    true
}

impl Default for SimplifyOptions {
    fn default() -> Self {
        SimplifyOptions {
            facial_landmarks: true,
            feature_image_size: 512,
            peak_fraction: 0.95,
            peaks_per_target: 2,
            priority_rings: 2,
            motion_targets: 10,
            motion_weight: 1.0,
            uv_weight: default_uv_weight(),
            lock_material_borders: true,
        }
    }
}

/// A named facial landmark.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Landmark {
    /// What it is (`nose_tip`, `mouth_corner_L`, ...; `_L` is the character's left, +X).
    pub name: String,
    /// Global vertex index (evaluation order).
    pub vertex: u32,
}

/// Feature points of a rig, as global vertex indices (evaluation order).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FeaturePoints {
    /// Named landmarks found by the facial heuristics.
    pub landmarks: Vec<Landmark>,
    /// Vertices along the lip contact line, from the character's right to left.
    pub lip_line: Vec<u32>,
    /// Vertices where targets move most.
    pub motion_peaks: Vec<u32>,
}

impl FeaturePoints {
    /// Every feature vertex, ascending, without repeats.
    pub fn vertices(&self) -> Vec<u32> {
        let mut v: Vec<u32> = self
            .landmarks
            .iter()
            .map(|l| l.vertex)
            .chain(self.lip_line.iter().copied())
            .chain(self.motion_peaks.iter().copied())
            .collect();
        v.sort_unstable();
        v.dedup();
        v
    }

    /// The landmark with this name.
    pub fn landmark(&self, name: &str) -> Option<u32> {
        self.landmarks
            .iter()
            .find(|l| l.name == name)
            .map(|l| l.vertex)
    }
}

/// Finds the feature points of `rig`.
pub fn detect_features(rig: &Rig, opts: &SimplifyOptions) -> FeaturePoints {
    let mut f = FeaturePoints {
        motion_peaks: motion_peaks(rig, opts.peak_fraction, opts.peaks_per_target),
        ..FeaturePoints::default()
    };
    if opts.facial_landmarks {
        facial_landmarks(rig, opts.feature_image_size, &mut f);
    }
    f
}

/// Per target, the vertices displaced at least `fraction` of its largest displacement, at most
/// `per_target` of them (largest first, then lowest index).
fn motion_peaks(rig: &Rig, fraction: f32, per_target: usize) -> Vec<u32> {
    let sparse = super::order::SparseIndex::new(rig);
    let mut out = Vec::new();
    for t in 0..rig.targets.len() as TargetId {
        let (vertices, deltas) = sparse.displacement(rig, t);
        let lens: Vec<f32> = deltas.iter().map(|d| d.length()).collect();
        let max = lens.iter().copied().fold(0.0f32, f32::max);
        if max <= 0.0 {
            continue;
        }
        let mut cand: Vec<(f32, u32)> = lens
            .iter()
            .zip(&vertices)
            .filter(|&(&l, _)| l >= fraction * max)
            .map(|(&l, &v)| (l, v))
            .collect();
        cand.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
        out.extend(cand.iter().take(per_target).map(|&(_, v)| v));
    }
    out.sort_unstable();
    out.dedup();
    out
}

/// The skin: the largest connected piece (by vertices) of the primitive with most vertices.
/// Returns the primitive index and a per-vertex membership mask.
fn skin(rig: &Rig) -> Option<(usize, Vec<bool>)> {
    let (pi, p) = rig.primitives.iter().enumerate().max_by(|a, b| {
        a.1.positions
            .len()
            .cmp(&b.1.positions.len())
            .then(b.0.cmp(&a.0))
    })?;
    let n = p.positions.len();
    let mut parent: Vec<u32> = (0..n as u32).collect();
    fn find(parent: &mut [u32], mut x: u32) -> u32 {
        while parent[x as usize] != x {
            let up = parent[parent[x as usize] as usize];
            parent[x as usize] = up;
            x = up;
        }
        x
    }
    for tri in p.indices.chunks_exact(3) {
        for (a, b) in [(tri[0], tri[1]), (tri[1], tri[2])] {
            let (ra, rb) = (find(&mut parent, a), find(&mut parent, b));
            if ra != rb {
                parent[ra.max(rb) as usize] = ra.min(rb);
            }
        }
    }
    let mut size = vec![0u32; n];
    let roots: Vec<u32> = (0..n as u32).map(|v| find(&mut parent, v)).collect();
    for &r in &roots {
        size[r as usize] += 1;
    }
    let best = (0..n).max_by(|&a, &b| size[a].cmp(&size[b]).then(b.cmp(&a)))? as u32;
    Some((pi, roots.iter().map(|&r| r == best).collect()))
}

/// Kind of turning point along a depth profile.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Turn {
    Min,
    Max,
}

/// Turning points of a profile with hysteresis `prominence`: a maximum is confirmed once the
/// profile falls `prominence` below it, a minimum once it rises `prominence` above it. The start
/// is never a turning point.
fn turning_points(z: &[f32], prominence: f32) -> Vec<(Turn, usize)> {
    let mut out = Vec::new();
    if z.is_empty() {
        return out;
    }
    let (mut hi, mut lo) = (0usize, 0usize);
    let mut trend: Option<Turn> = None; // Some(Max) = rising toward a max, Some(Min) = falling.
    for i in 1..z.len() {
        match trend {
            None => {
                if z[i] > z[hi] {
                    hi = i;
                }
                if z[i] < z[lo] {
                    lo = i;
                }
                if z[i] > z[lo] + prominence {
                    if lo > 0 {
                        out.push((Turn::Min, lo));
                    }
                    trend = Some(Turn::Max);
                    hi = i;
                } else if z[i] < z[hi] - prominence {
                    if hi > 0 {
                        out.push((Turn::Max, hi));
                    }
                    trend = Some(Turn::Min);
                    lo = i;
                }
            }
            Some(Turn::Max) => {
                if z[i] > z[hi] {
                    hi = i;
                } else if z[i] < z[hi] - prominence {
                    out.push((Turn::Max, hi));
                    trend = Some(Turn::Min);
                    lo = i;
                }
            }
            Some(Turn::Min) => {
                if z[i] < z[lo] {
                    lo = i;
                } else if z[i] > z[lo] + prominence {
                    out.push((Turn::Min, lo));
                    trend = Some(Turn::Max);
                    hi = i;
                }
            }
        }
    }
    out
}

/// A depth map of the skin with helpers to walk it.
struct DepthMap {
    camera: Camera,
    frame: Frame,
    prominence: f32,
}

impl DepthMap {
    fn size(&self) -> (i64, i64) {
        (self.camera.width as i64, self.camera.height as i64)
    }

    fn depth(&self, p: (i64, i64)) -> Option<f32> {
        let (w, h) = self.size();
        if p.0 < 0 || p.1 < 0 || p.0 >= w || p.1 >= h {
            return None;
        }
        let d = self.frame.depth[(p.1 * w + p.0) as usize];
        d.is_finite().then_some(d)
    }

    fn vertex(&self, p: (i64, i64)) -> Option<u32> {
        self.depth(p)?;
        let v = self.frame.vertex[(p.1 * self.size().0 + p.0) as usize];
        (v != NO_VERTEX).then_some(v)
    }

    /// Pixels and smoothed depths from `start` along `dir` (pixel steps) until the surface
    /// ends or `max_steps`.
    fn ray(
        &self,
        start: (i64, i64),
        dir: (i64, i64),
        max_steps: usize,
    ) -> (Vec<(i64, i64)>, Vec<f32>) {
        let mut pix = Vec::new();
        let mut z = Vec::new();
        let mut p = start;
        for _ in 0..max_steps {
            let Some(d) = self.depth(p) else { break };
            pix.push(p);
            z.push(d);
            p = (p.0 + dir.0, p.1 + dir.1);
        }
        // A 5-tap box filter: tessellation ripples are not anatomy.
        let smooth: Vec<f32> = (0..z.len())
            .map(|i| {
                let lo = i.saturating_sub(2);
                let hi = (i + 3).min(z.len());
                z[lo..hi].iter().sum::<f32>() / (hi - lo) as f32
            })
            .collect();
        (pix, smooth)
    }

    /// The `nth` (0-based) turning point of `kind` along a ray.
    fn find(
        &self,
        start: (i64, i64),
        dir: (i64, i64),
        kind: Turn,
        nth: usize,
    ) -> Option<(i64, i64)> {
        let max = self.size().0.max(self.size().1) as usize / 3;
        let (pix, z) = self.ray(start, dir, max);
        turning_points(&z, self.prominence)
            .into_iter()
            .filter(|&(k, _)| k == kind)
            .nth(nth)
            .map(|(_, i)| pix[i])
    }

    /// Whether pixel `p` sits in a horizontal crease: a vertical local minimum of depth at least
    /// a quarter of the prominence deeper than the surface within `reach` pixels above and
    /// below (lips meet in a shallower fold than the profile's features, and it fades toward
    /// the corners).
    fn crease_depth(&self, p: (i64, i64), reach: i64) -> Option<f32> {
        let z = self.depth(p)?;
        let up = (1..=reach)
            .filter_map(|k| self.depth((p.0, p.1 - k)))
            .fold(f32::NEG_INFINITY, f32::max);
        let down = (1..=reach)
            .filter_map(|k| self.depth((p.0, p.1 + k)))
            .fold(f32::NEG_INFINITY, f32::max);
        let rim = up.min(down);
        (rim.is_finite() && rim - z >= self.prominence * 0.25).then_some(rim - z)
    }

    /// Traces the crease through `start` sideways (`dx` = ±1), following its row within ±2
    /// pixels, until it fades. Returns the traced pixels, nearest first.
    fn trace_crease(&self, start: (i64, i64), dx: i64, reach: i64) -> Vec<(i64, i64)> {
        let mut out = Vec::new();
        let mut p = start;
        let max = self.size().0 as usize / 4;
        for _ in 0..max {
            let x = p.0 + dx;
            let best = (-2..=2)
                .filter_map(|dy| {
                    let q = (x, p.1 + dy);
                    let z = self.depth(q)?;
                    let local_min = [q.1 - 1, q.1 + 1]
                        .iter()
                        .all(|&y| self.depth((x, y)).is_none_or(|n| n >= z));
                    if !local_min {
                        return None;
                    }
                    self.crease_depth(q, reach).map(|c| (q, c))
                })
                .max_by(|a, b| {
                    a.1.total_cmp(&b.1)
                        .then(b.0.1.abs_diff(p.1).cmp(&a.0.1.abs_diff(p.1)))
                });
            match best {
                Some((q, _)) => {
                    out.push(q);
                    p = q;
                }
                None => break,
            }
        }
        out
    }
}

/// The paper's landmark heuristics on the skin's front depth map.
fn facial_landmarks(rig: &Rig, size: u32, f: &mut FeaturePoints) {
    let Some((pi, mask)) = skin(rig) else { return };
    let prim = &rig.primitives[pi];
    let offsets = rig.vertex_offsets();
    let first = offsets[pi] as u32;
    let indices: Vec<u32> = prim
        .indices
        .chunks_exact(3)
        .filter(|t| t.iter().all(|&v| mask[v as usize]))
        .flatten()
        .copied()
        .collect();
    let normals = crowdmorph_core::rig::vertex_normals(&prim.positions, &indices);
    let mut bbox = crowdmorph_core::rig::Aabb {
        min: Vec3::splat(f32::INFINITY),
        max: Vec3::splat(f32::NEG_INFINITY),
    };
    for (p, _) in prim.positions.iter().zip(&mask).filter(|(_, m)| **m) {
        bbox.min = bbox.min.min(*p);
        bbox.max = bbox.max.max(*p);
    }
    let camera = Camera::front(bbox, size.clamp(64, 4096));
    let frame = render(
        &camera,
        &[MeshView {
            positions: &prim.positions,
            normals: &normals,
            indices: &indices,
            first_vertex: first,
        }],
    );
    let map = DepthMap {
        camera,
        frame,
        prominence: bbox.diagonal() * 5e-4,
    };
    let pixel = |v: u32| -> (i64, i64) {
        let p = camera.project(prim.positions[(v - first) as usize]);
        (p.x.floor() as i64, p.y.floor() as i64)
    };
    let mut found: Vec<Landmark> = Vec::new();
    let mut add = |name: &str, at: Option<(i64, i64)>| -> Option<(i64, i64)> {
        let at = at?;
        let v = map.vertex(at)?;
        found.push(Landmark {
            name: name.to_string(),
            vertex: v,
        });
        Some(at)
    };
    // Nose tip: the skin vertex nearest the viewer (ties: lowest index).
    let Some(tip_v) = (0..prim.positions.len())
        .filter(|&v| mask[v])
        .max_by(|&a, &b| {
            prim.positions[a]
                .z
                .total_cmp(&prim.positions[b].z)
                .then(b.cmp(&a))
        })
    else {
        return;
    };
    f.landmarks.push(Landmark {
        name: "nose_tip".into(),
        vertex: first + tip_v as u32,
    });
    let tip = pixel(first + tip_v as u32);
    // Collect the rest in `found`; whatever is found before a step fails is kept.
    landmarks_from_tip(&map, tip, &mut add, rig, &camera, &mut f.lip_line);
    f.landmarks.append(&mut found);
}

/// The landmarks below and around the nose tip, each found from an earlier one.
fn landmarks_from_tip(
    map: &DepthMap,
    tip: (i64, i64),
    add: &mut impl FnMut(&str, Option<(i64, i64)>) -> Option<(i64, i64)>,
    rig: &Rig,
    camera: &Camera,
    lip_line: &mut Vec<u32>,
) {
    // Image directions: x right is the character's left (+X), y grows downward.
    const UP: (i64, i64) = (0, -1);
    const DOWN: (i64, i64) = (0, 1);
    const DOWN_L: (i64, i64) = (1, 1);
    const DOWN_R: (i64, i64) = (-1, 1);
    let nasion = add("nose_top", map.find(tip, UP, Turn::Min, 0));
    let subnasale = add("nose_bottom", map.find(tip, DOWN, Turn::Min, 0));
    add("nose_bottom_L", map.find(tip, DOWN_L, Turn::Min, 0));
    add("nose_bottom_R", map.find(tip, DOWN_R, Turn::Min, 0));
    if let Some(n) = nasion {
        add("eye_socket_L", map.find(n, DOWN_L, Turn::Min, 0));
        add("eye_socket_R", map.find(n, DOWN_R, Turn::Min, 0));
    } else {
        // No dip between the nose and the brow (a smooth, sculpted head): look for the sockets
        // from the tip instead, up and out along the diagonals.
        add("eye_socket_L", map.find(tip, (1, -1), Turn::Min, 0));
        add("eye_socket_R", map.find(tip, (-1, -1), Turn::Min, 0));
    }
    let Some(sub) = subnasale else { return };
    // Below the nose: the upper lip bulges (max), then the lips meet in a crease (min).
    let contact = map.find(sub, DOWN, Turn::Min, 0);
    let Some(contact) = contact else { return };
    add("lip_contact", Some(contact));
    add("lip_top", map.find(contact, UP, Turn::Max, 0));
    let lower = add("lip_bottom", map.find(contact, DOWN, Turn::Max, 0));
    if let Some(lower) = lower {
        // The paper's "second local minimum" below the contact line: the crease under the
        // lower lip; the chin is the next bulge below it, the throat the next hollow.
        let sulcus = add("lip_sulcus", map.find(lower, DOWN, Turn::Min, 0));
        if let Some(s) = sulcus {
            let chin = add("chin", map.find(s, DOWN, Turn::Max, 0));
            if let Some(c) = chin {
                add("throat", map.find(c, DOWN, Turn::Min, 0));
            }
        }
    }
    // The lip contact line: the crease traced both ways from its centre; its ends are the
    // mouth corners.
    let reach = ((rig.bbox().diagonal() * 0.004) / camera.units_per_pixel)
        .ceil()
        .max(2.0) as i64;
    let right = map.trace_crease(contact, -1, reach);
    let left = map.trace_crease(contact, 1, reach);
    let mut line: Vec<u32> = Vec::new();
    for p in right
        .iter()
        .rev()
        .chain(std::iter::once(&contact))
        .chain(left.iter())
    {
        if let Some(v) = map.vertex(*p)
            && line.last() != Some(&v)
            && !line.contains(&v)
        {
            line.push(v);
        }
    }
    if let Some(&p) = right.last() {
        add("mouth_corner_R", Some(p));
    }
    if let Some(&p) = left.last() {
        add("mouth_corner_L", Some(p));
    }
    *lip_line = line;
}

/// meshoptimizer's limit on attribute floats per vertex (`kMaxAttributes` in the vendored
/// simplifier.cpp; more is an assertion failure in C, not an error).
const MAX_ATTRIBUTES: usize = 32;

/// The options every level is simplified with. Never `Permissive`: without it meshoptimizer
/// treats vertices that share a position (a UV seam's two sides) as wedges of one point, and
/// a seam vertex only collapses along the seam together with its twin, onto a vertex that
/// shares a triangle with it; a point with more than two wedges is locked. So every collapse
/// stays inside one UV chart and the seam stays closed. `Permissive` turns seam vertices into
/// "complex" ones whose wedges may be sent to the target vertex itself, across the seam.
/// (Read in the vendored simplifier.cpp: `classifyVertices`, `kCanCollapse`,
/// `getComplexTarget`.)
const SEAM_SAFE: MeshoptOptions = MeshoptOptions::None;

/// Simplifies every primitive of `rig` to about `fraction` of its triangles, keeping `features`
/// (global vertex ids). Deterministic.
///
/// Feature points are locked and their rings get priority; UV seams are kept by meshoptimizer
/// itself ([`SEAM_SAFE`]); with [`SimplifyOptions::lock_material_borders`] the vertices a
/// primitive shares with another along its open border are locked too. Texture coordinates and
/// the deltas of the most energetic targets are attributes of the quadric.
pub fn simplify_level(
    rig: &Rig,
    features: &[u32],
    fraction: f32,
    opts: &SimplifyOptions,
) -> Result<MeshLevel, MeshLodError> {
    if !(fraction > 0.0 && fraction <= 1.0) {
        return Err(MeshLodError::BadFraction(fraction));
    }
    let offsets = rig.vertex_offsets();
    let extent = rig.bbox().diagonal().max(1e-12);
    let motion: Vec<TargetId> = if opts.motion_weight > 0.0 {
        Lod::by_delta_energy(&rig.primitives, rig.targets.len())
            .order
            .into_iter()
            .take(opts.motion_targets.min(MAX_ATTRIBUTES / 3))
            .collect()
    } else {
        Vec::new()
    };
    let shared = if opts.lock_material_borders && rig.primitives.len() > 1 {
        material_border_vertices(&rig.primitives)
    } else {
        Vec::new()
    };
    let mut primitives = Vec::with_capacity(rig.primitives.len());
    for (pi, p) in rig.primitives.iter().enumerate() {
        let n = p.positions.len();
        let first = offsets[pi] as u32;
        let mut flags = vec![SimplifyVertex::None; n];
        for &v in features {
            if (first..first + n as u32).contains(&v) {
                flags[(v - first) as usize] = SimplifyVertex::Lock;
            }
        }
        mark_priority_rings(p, &mut flags, opts.priority_rings);
        // After the rings: only feature points widen their neighbourhood's priority; a
        // material border is held in place, not made denser around.
        if let Some(border) = shared.get(pi) {
            for &v in border {
                flags[v as usize] |= SimplifyVertex::Lock;
            }
        }
        let tris = p.indices.len() / 3;
        let target_tris = ((tris as f64 * f64::from(fraction)).round() as usize).max(1);
        let positions: Vec<[f32; 3]> = p.positions.iter().map(|v| v.to_array()).collect();
        let indices = if target_tris >= tris {
            p.indices.clone()
        } else {
            let (attrs, weights) = attributes(p, &motion, extent, opts);
            if weights.is_empty() {
                meshopt::simplify::simplify_with_locks_decoder(
                    &p.indices,
                    &positions,
                    &flags,
                    target_tris * 3,
                    f32::MAX,
                    SEAM_SAFE,
                    None,
                )
            } else {
                meshopt::simplify::simplify_with_attributes_and_locks_decoder(
                    &p.indices,
                    &positions,
                    &attrs,
                    &weights,
                    weights.len() * size_of::<f32>(),
                    &flags,
                    target_tris * 3,
                    f32::MAX,
                    SEAM_SAFE,
                    None,
                )
            }
        };
        let indices = drop_folds(&indices);
        let mut kept: Vec<u32> = indices.clone();
        kept.sort_unstable();
        kept.dedup();
        let mut remap = vec![u32::MAX; n];
        for (new, &old) in kept.iter().enumerate() {
            remap[old as usize] = new as u32;
        }
        primitives.push(MeshLevelPrimitive {
            indices: indices.iter().map(|&i| remap[i as usize]).collect(),
            vertices: kept,
        });
    }
    Ok(MeshLevel {
        triangle_fraction: fraction,
        primitives,
    })
}

/// The quadric's attributes of primitive `p`, interleaved per vertex, and their weights (empty:
/// none). The deltas of the `motion` targets that move `p` come first, scaled by the rig's
/// `extent` as positions are; then u, v of set 0 when `p` has them. Targets are dropped from
/// the end of `motion` until everything fits meshoptimizer's [`MAX_ATTRIBUTES`].
fn attributes(
    p: &Primitive,
    motion: &[TargetId],
    extent: f32,
    opts: &SimplifyOptions,
) -> (Vec<f32>, Vec<f32>) {
    let uv = p.look.uv0.as_deref().filter(|_| opts.uv_weight > 0.0);
    let uv_floats = if uv.is_some() { 2 } else { 0 };
    let here: Vec<&SparseTarget> = motion
        .iter()
        .filter_map(|&t| p.targets.iter().find(|s| s.target == t))
        .take((MAX_ATTRIBUTES - uv_floats) / 3)
        .collect();
    let k = here.len() * 3 + uv_floats;
    if k == 0 {
        return (Vec::new(), Vec::new());
    }
    let mut attrs = vec![0f32; p.positions.len() * k];
    for (j, s) in here.iter().enumerate() {
        for (&v, d) in s.vertices.iter().zip(&s.positions) {
            let at = v as usize * k + j * 3;
            attrs[at..at + 3].copy_from_slice(&(*d / extent).to_array());
        }
    }
    if let Some(uv) = uv {
        let at = here.len() * 3;
        for (a, t) in attrs.chunks_exact_mut(k).zip(uv) {
            a[at..at + 2].copy_from_slice(&t.to_array());
        }
    }
    let mut weights = vec![opts.motion_weight; here.len() * 3];
    weights.resize(k, opts.uv_weight);
    (attrs, weights)
}

/// Per primitive, its open-border vertices (on an edge of one triangle only) that some other
/// primitive also has a vertex at (bit-equal position, −0 = +0): where two materials meet. An
/// exporter writes such a boundary's vertices once per primitive with the same coordinates, and
/// each primitive is simplified alone, so without a lock either side may slide along it.
fn material_border_vertices(primitives: &[Primitive]) -> Vec<Vec<u32>> {
    use std::collections::HashMap;
    let key = |v: Vec3| (v + Vec3::ZERO).to_array().map(f32::to_bits);
    // Position → the lowest and highest primitive with a vertex there.
    let mut owners: HashMap<[u32; 3], (usize, usize)> = HashMap::new();
    for (pi, p) in primitives.iter().enumerate() {
        for &v in &p.positions {
            let e = owners.entry(key(v)).or_insert((pi, pi));
            e.0 = e.0.min(pi);
            e.1 = e.1.max(pi);
        }
    }
    primitives
        .iter()
        .enumerate()
        .map(|(pi, p)| {
            let mut edges: HashMap<(u32, u32), u32> = HashMap::new();
            for t in p.indices.chunks_exact(3) {
                for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
                    *edges.entry((a.min(b), a.max(b))).or_insert(0) += 1;
                }
            }
            let mut out: Vec<u32> = edges
                .iter()
                .filter(|&(_, &uses)| uses == 1)
                .flat_map(|(&(a, b), _)| [a, b])
                .filter(|&v| {
                    owners
                        .get(&key(p.positions[v as usize]))
                        .is_some_and(|&(lo, hi)| lo != pi || hi != pi)
                })
                .collect();
            out.sort_unstable();
            out.dedup();
            out
        })
        .collect()
}

/// Removes degenerate triangles and folds from a simplified triangle list: a triangle that
/// repeats a vertex, and every triangle whose three vertices another triangle also uses with the
/// opposite winding. Thin closed pieces (ICT's eyelid and tear-duct shells) can collapse into
/// such back-to-back pairs; they cover no area from either side, and their face normals cancel
/// exactly, leaving their vertices without a normal (the engines would then disagree on an
/// arbitrary direction). A repeated triangle with the same winding is kept once. Order is kept.
fn drop_folds(indices: &[u32]) -> Vec<u32> {
    use std::collections::HashMap;
    let canonical = |t: &[u32]| -> ([u32; 3], bool) {
        // Rotate so the smallest index comes first; the winding is then (b, c) or (c, b).
        let k = (0..3).min_by_key(|&i| t[i]).unwrap_or(0);
        let (a, b, c) = (t[k], t[(k + 1) % 3], t[(k + 2) % 3]);
        if b < c {
            ([a, b, c], true)
        } else {
            ([a, c, b], false)
        }
    };
    let mut windings: HashMap<[u32; 3], (bool, bool)> = HashMap::new();
    for t in indices.chunks_exact(3) {
        let (key, w) = canonical(t);
        let e = windings.entry(key).or_insert((false, false));
        if w {
            e.0 = true;
        } else {
            e.1 = true;
        }
    }
    let mut seen = std::collections::HashSet::new();
    let mut out = Vec::with_capacity(indices.len());
    for t in indices.chunks_exact(3) {
        if t[0] == t[1] || t[1] == t[2] || t[0] == t[2] {
            continue;
        }
        let (key, _) = canonical(t);
        if windings.get(&key) == Some(&(true, true)) || !seen.insert(key) {
            continue;
        }
        out.extend_from_slice(t);
    }
    out
}

/// Gives the `rings` neighbourhoods of locked vertices the priority flag.
fn mark_priority_rings(p: &Primitive, flags: &mut [SimplifyVertex], rings: u32) {
    if rings == 0 {
        return;
    }
    let n = p.positions.len();
    let mut adj: Vec<Vec<u32>> = vec![Vec::new(); n];
    for t in p.indices.chunks_exact(3) {
        for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
            adj[a as usize].push(b);
            adj[b as usize].push(a);
        }
    }
    let mut dist = vec![u32::MAX; n];
    let mut queue = VecDeque::new();
    for (v, f) in flags.iter().enumerate() {
        if f.contains(SimplifyVertex::Lock) {
            dist[v] = 0;
            queue.push_back(v as u32);
        }
    }
    while let Some(v) = queue.pop_front() {
        let d = dist[v as usize];
        if d >= rings {
            continue;
        }
        for &u in &adj[v as usize] {
            if dist[u as usize] == u32::MAX {
                dist[u as usize] = d + 1;
                flags[u as usize] |= SimplifyVertex::Priority;
                queue.push_back(u);
            }
        }
    }
}

/// Detects the feature points once and simplifies the rig at each of `fractions`.
pub fn build_mesh_levels(
    rig: &Rig,
    fractions: &[f32],
    opts: &SimplifyOptions,
    progress: Option<&Progress>,
) -> Result<(Vec<MeshLevel>, FeaturePoints), MeshLodError> {
    if let Some(&f) = fractions.iter().find(|&&f| !(f > 0.0 && f <= 1.0)) {
        return Err(MeshLodError::BadFraction(f));
    }
    if let Some(p) = progress {
        p.start(fractions.len() + 1);
    }
    let features = detect_features(rig, opts);
    if let Some(p) = progress {
        p.advance();
    }
    let keep = features.vertices();
    let mut levels = Vec::with_capacity(fractions.len());
    for &f in fractions {
        // Each level takes seconds on a large rig, so a cancelled job stops between them.
        if progress.is_some_and(Progress::is_cancelled) {
            return Err(MeshLodError::Cancelled);
        }
        levels.push(simplify_level(rig, &keep, f, opts)?);
        if let Some(p) = progress {
            p.advance();
        }
    }
    Ok((levels, features))
}

/// The rig a mesh level is evaluated as (see [`MeshLevel::derive_rig`], which the engines use
/// directly: deriving is plain data work and lives in `rig/`).
pub fn mesh_level_rig(rig: &Rig, level: &MeshLevel) -> Result<Rig, MeshLodError> {
    Ok(level.derive_rig(rig)?)
}

/// The derived rig for every mesh level of `rig.lod`, in order.
pub fn mesh_level_rigs(rig: &Rig) -> Result<Vec<Rig>, MeshLodError> {
    Ok(crowdmorph_core::rig::mesh_level_rigs(rig)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn folds_and_degenerate_triangles_are_dropped() {
        let tris = [
            0, 1, 2, // kept
            3, 4, 5, // a fold with the next one: both dropped
            4, 3, 5, //
            1, 2, 0, // the first one again, rotated: dropped as a repeat
            6, 6, 7, // degenerate
            2, 1, 8, // kept
        ];
        assert_eq!(drop_folds(&tris), vec![0, 1, 2, 2, 1, 8]);
    }

    /// A primitive of `positions` and `indices` with no targets, normals +Z.
    fn primitive(positions: Vec<Vec3>, indices: Vec<u32>) -> Primitive {
        Primitive {
            name: String::new(),
            normals: vec![Vec3::Z; positions.len()],
            positions,
            normals_from_file: false,
            tangents: None,
            indices,
            targets: Vec::new(),
            base_color: Primitive::default_base_color(),
            skin: None,
            look: Default::default(),
        }
    }

    #[test]
    fn attributes_fit_meshoptimizer_with_texture_coordinates() {
        let mut p = primitive(vec![Vec3::ZERO, Vec3::X, Vec3::Y], vec![0, 1, 2]);
        p.targets = (0..12)
            .map(|t| SparseTarget {
                target: t,
                vertices: vec![0],
                positions: vec![Vec3::X * (t + 1) as f32],
                normals: None,
                tangents: None,
            })
            .collect();
        let motion: Vec<TargetId> = (0..12).collect();
        let opts = SimplifyOptions::default();
        // No UVs: ten targets' deltas, 30 floats.
        let (attrs, weights) = attributes(&p, &motion, 2.0, &opts);
        assert_eq!(weights, vec![opts.motion_weight; 30]);
        assert_eq!(attrs.len(), 3 * 30);
        assert_eq!(
            attrs[27..30],
            [5.0, 0.0, 0.0],
            "target 9 moves vertex 0 by 10 / 2"
        );
        // UVs take the last two of meshoptimizer's 32 floats.
        let uv = [
            glam::Vec2::new(0.25, 0.5),
            glam::Vec2::ONE,
            glam::Vec2::ZERO,
        ];
        p.look.uv0 = Some(uv.to_vec());
        let (attrs, weights) = attributes(&p, &motion, 2.0, &opts);
        assert_eq!(weights.len(), MAX_ATTRIBUTES);
        assert_eq!(weights[30..], [opts.uv_weight; 2]);
        assert_eq!(attrs[30..32], [0.25, 0.5]);
        assert_eq!(attrs[32 + 30..32 + 32], [1.0, 1.0]);
        // A UV weight of 0 leaves them out; UVs alone are still attributes.
        let off = SimplifyOptions {
            uv_weight: 0.0,
            ..opts.clone()
        };
        assert_eq!(attributes(&p, &motion, 2.0, &off).1.len(), 30);
        let (attrs, weights) = attributes(&p, &[], 2.0, &opts);
        assert_eq!(weights, vec![opts.uv_weight; 2]);
        assert_eq!(attrs, vec![0.25, 0.5, 1.0, 1.0, 0.0, 0.0]);
    }

    #[test]
    fn material_borders_are_the_open_border_another_primitive_shares() {
        let quad = |x: f32| {
            primitive(
                vec![
                    Vec3::new(x, 0.0, 0.0),
                    Vec3::new(x + 1.0, 0.0, 0.0),
                    Vec3::new(x + 1.0, 1.0, 0.0),
                    Vec3::new(x, 1.0, 0.0),
                ],
                vec![0, 1, 2, 0, 2, 3],
            )
        };
        let mut right = quad(1.0);
        // −0 and +0 are one position.
        right.positions[0].y = -0.0;
        // A fan whose centre (inner, on no open edge) sits on a corner of the right quad.
        let fan = primitive(
            vec![
                Vec3::new(2.0, 1.0, 0.0),
                Vec3::new(3.0, 1.0, 0.0),
                Vec3::new(2.0, 2.0, 0.0),
                Vec3::new(1.5, 1.5, 5.0),
            ],
            vec![0, 1, 2, 0, 2, 3, 0, 3, 1],
        );
        let far = quad(10.0);
        let got = material_border_vertices(&[quad(0.0), right, fan, far]);
        assert_eq!(got, vec![vec![1, 2], vec![0, 2, 3], vec![], vec![]]);
    }

    #[test]
    fn turning_points_need_prominence() {
        let z = [0.0, 1.0, 2.0, 1.9, 2.05, 1.0, 0.5, 0.6, 1.5, 1.0];
        let t = turning_points(&z, 0.3);
        assert_eq!(t, vec![(Turn::Max, 4), (Turn::Min, 6), (Turn::Max, 8)]);
        // Starting downhill, the first turning point is a minimum.
        assert_eq!(
            turning_points(&[3.0, 2.0, 1.0, 2.0], 0.5),
            vec![(Turn::Min, 2)]
        );
        assert!(turning_points(&[], 0.1).is_empty());
    }
}
