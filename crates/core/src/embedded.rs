//! The embedded default rig: a face-like head built in code.
//!
//! A fresh machine has no rig files, yet the server, the CLI and the README examples all need
//! something to animate. [`default_rig`] builds one procedurally, so it costs no download, no
//! file and no licence, and it is bit-for-bit the same on every call (no random numbers, no hash
//! map iteration).
//!
//! What it holds:
//! - `head`: a latitude/longitude ellipsoid about 20 units tall (centimetre-like units), +Y up and
//!   the face looking toward +Z as in glTF, sculpted with a brow ridge, eye sockets, a nose, lips,
//!   a chin, cheekbones and ears. Rings and columns are packed more densely over the face, where
//!   the targets act. The mesh is exactly mirror-symmetric across the x = 0 plane.
//! - `eye_L` and `eye_R`: small spheres with a corneal bulge sitting in the sockets, so the rig
//!   has several primitives and the `eyeLook*` targets (small rotations of an eyeball, stored as
//!   rotated minus neutral positions) are visible after shading.
//! - 51 targets with ARKit blendshape names (all but `tongueOut`, in ARKit's order, with `_L` and
//!   `_R` suffixes). Each is a smooth deformation of one facial region that is exactly zero
//!   outside a radius, so targets are sparse as in captured rigs. `_L` is the character's left
//!   (+X); every right target is the exact mirror image of its left twin.
//! - Four clips at 30 fps (`idle`, `talk`, `smile`, `surprise`) whose frames have only a few
//!   active weights, like captured facial animation, so active-weight skipping matters.

use glam::Vec3;

use crate::rig::{
    Clip, DEFAULT_DELTA_THRESHOLD, Lod, Primitive, Rig, SparseTarget, TargetId, sparsify,
    vertex_normals,
};

/// Name of the embedded rig, so reports and the server can tell it apart from uploaded rigs.
pub const DEFAULT_RIG_NAME: &str = "default-head";

/// Sampling rate of the embedded clips.
const FPS: f32 = 30.0;

/// Latitude intervals of the head grid, pole to pole.
const HEAD_RINGS: usize = 72;
/// Columns of the head grid around the vertical axis; even, so the grid is mirror-symmetric.
const HEAD_SEGMENTS: usize = 96;
/// Latitude intervals of an eyeball grid (poles on the gaze axis).
const EYE_RINGS: usize = 12;
/// Columns of an eyeball grid; even, for the same reason as [`HEAD_SEGMENTS`].
const EYE_SEGMENTS: usize = 20;

/// Semi-axes of the head ellipsoid before sculpting.
const HEAD_RADII: Vec3 = Vec3::new(7.4, 10.2, 8.8);
/// Centre of the left eye socket in the (x, y) plane of the face.
const EYE_X: f32 = 3.1;
/// Height of the eye centres.
const EYE_Y: f32 = 1.3;
/// Centre of the left eyeball; it sits in the socket with its cornea just proud of the skin.
const EYE_CENTER_L: Vec3 = Vec3::new(EYE_X, EYE_Y, 6.45);
/// Radius of an eyeball.
const EYE_RADIUS: f32 = 1.15;
/// Height of the line between the lips.
const MOUTH_Y: f32 = -5.1;
/// Distance of a mouth corner from the mid-plane.
const MOUTH_CORNER_X: f32 = 2.4;
/// Jaw hinge: the (y, z) of the axis, parallel to X, that `jawOpen` rotates about.
const JAW_PIVOT: (f32, f32) = (-0.5, -1.5);
/// How far `jawOpen` rotates the jaw, in radians.
const JAW_OPEN_ANGLE: f32 = 0.21;
/// How far `eyeLookUp`/`eyeLookDown` rotate an eyeball, in radians.
const EYE_PITCH: f32 = 0.3;
/// How far `eyeLookIn`/`eyeLookOut` rotate an eyeball, in radians.
const EYE_YAW: f32 = 0.35;

/// Builds the embedded head rig: three primitives, 51 sparse ARKit-named targets, four clips.
///
/// Used whenever no rig file is given, so the server and the examples work on a fresh machine.
/// The result is deterministic and valid (`validate()` passes); it takes a few milliseconds.
pub fn default_rig() -> Rig {
    let geo = Geometry::build();
    let n_targets = TARGETS.len();

    let mut per_prim: [Vec<SparseTarget>; 3] = [Vec::new(), Vec::new(), Vec::new()];
    for (id, &(_, make)) in TARGETS.iter().enumerate() {
        let dense = match make {
            Make::Own(shape) => geo.shape_deltas(shape),
            Make::Mirror(shape) => geo.mirrored(&geo.shape_deltas(shape)),
        };
        let ranges = geo.ranges();
        for (list, range) in per_prim.iter_mut().zip(ranges) {
            let sparse = sparsify(
                id as TargetId,
                &dense[range],
                None,
                None,
                DEFAULT_DELTA_THRESHOLD,
            );
            if !sparse.vertices.is_empty() {
                list.push(sparse);
            }
        }
    }

    let [head_targets, eye_l_targets, eye_r_targets] = per_prim;
    let primitives = vec![
        primitive("head", geo.head, geo.head_indices, head_targets, SKIN),
        primitive(
            "eye_L",
            geo.eye_l,
            geo.eye_indices.clone(),
            eye_l_targets,
            EYE,
        ),
        primitive("eye_R", geo.eye_r, geo.eye_indices, eye_r_targets, EYE),
    ];
    let lod = Lod::by_delta_energy(&primitives, n_targets);
    Rig {
        name: DEFAULT_RIG_NAME.to_string(),
        targets: TARGETS.iter().map(|&(name, _)| name.to_string()).collect(),
        default_weights: vec![0.0; n_targets],
        primitives: std::sync::Arc::new(primitives),
        clips: clips(n_targets),
        lod,
        skeleton: None,
        import_notes: Vec::new(),
        appearance: None,
    }
}

/// A neutral skin tone (linear RGB of sRGB 224, 172, 150), the head's base colour.
const SKIN: [f32; 4] = [0.745, 0.412, 0.305, 1.0];
/// The eyes' base colour: a slightly blue-grey white.
const EYE: [f32; 4] = [0.78, 0.80, 0.85, 1.0];

/// Wraps neutral geometry and its targets in a [`Primitive`] with computed normals.
fn primitive(
    name: &str,
    positions: Vec<Vec3>,
    indices: Vec<u32>,
    targets: Vec<SparseTarget>,
    base_color: [f32; 4],
) -> Primitive {
    Primitive {
        name: name.to_string(),
        normals: vertex_normals(&positions, &indices),
        positions,
        normals_from_file: false,
        tangents: None,
        indices,
        targets,
        base_color,
        skin: None,
        look: Default::default(),
    }
}

// ---------------------------------------------------------------------------------------------
// Targets
// ---------------------------------------------------------------------------------------------

/// A deformation written once, for the character's left side or for both sides at once.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Shape {
    EyeBlink,
    EyeLookDown,
    EyeLookIn,
    EyeLookOut,
    EyeLookUp,
    EyeSquint,
    EyeWide,
    JawForward,
    JawLeft,
    JawOpen,
    MouthClose,
    MouthFunnel,
    MouthPucker,
    MouthLeft,
    MouthSmile,
    MouthFrown,
    MouthDimple,
    MouthStretch,
    MouthRollLower,
    MouthRollUpper,
    MouthShrugLower,
    MouthShrugUpper,
    MouthPress,
    MouthLowerDown,
    MouthUpperUp,
    BrowDown,
    BrowInnerUp,
    BrowOuterUp,
    CheekPuff,
    CheekSquint,
    NoseSneer,
}

impl Shape {
    /// Whether the shape acts on both sides at once; such shapes are made exactly symmetric.
    fn is_centered(self) -> bool {
        matches!(
            self,
            Shape::JawForward
                | Shape::JawOpen
                | Shape::MouthClose
                | Shape::MouthFunnel
                | Shape::MouthPucker
                | Shape::MouthRollLower
                | Shape::MouthRollUpper
                | Shape::MouthShrugLower
                | Shape::MouthShrugUpper
                | Shape::BrowInnerUp
                | Shape::CheekPuff
        )
    }
}

/// How a rig-wide target is made from a [`Shape`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Make {
    /// The shape itself (a left-side or a centred target).
    Own(Shape),
    /// The mirror image of the shape across x = 0 (a right-side target).
    Mirror(Shape),
}

/// The rig-wide targets, in ARKit's order (without `tongueOut`: the head has no tongue).
const TARGETS: [(&str, Make); 51] = [
    ("eyeBlink_L", Make::Own(Shape::EyeBlink)),
    ("eyeLookDown_L", Make::Own(Shape::EyeLookDown)),
    ("eyeLookIn_L", Make::Own(Shape::EyeLookIn)),
    ("eyeLookOut_L", Make::Own(Shape::EyeLookOut)),
    ("eyeLookUp_L", Make::Own(Shape::EyeLookUp)),
    ("eyeSquint_L", Make::Own(Shape::EyeSquint)),
    ("eyeWide_L", Make::Own(Shape::EyeWide)),
    ("eyeBlink_R", Make::Mirror(Shape::EyeBlink)),
    ("eyeLookDown_R", Make::Mirror(Shape::EyeLookDown)),
    ("eyeLookIn_R", Make::Mirror(Shape::EyeLookIn)),
    ("eyeLookOut_R", Make::Mirror(Shape::EyeLookOut)),
    ("eyeLookUp_R", Make::Mirror(Shape::EyeLookUp)),
    ("eyeSquint_R", Make::Mirror(Shape::EyeSquint)),
    ("eyeWide_R", Make::Mirror(Shape::EyeWide)),
    ("jawForward", Make::Own(Shape::JawForward)),
    ("jawLeft", Make::Own(Shape::JawLeft)),
    ("jawRight", Make::Mirror(Shape::JawLeft)),
    ("jawOpen", Make::Own(Shape::JawOpen)),
    ("mouthClose", Make::Own(Shape::MouthClose)),
    ("mouthFunnel", Make::Own(Shape::MouthFunnel)),
    ("mouthPucker", Make::Own(Shape::MouthPucker)),
    ("mouthLeft", Make::Own(Shape::MouthLeft)),
    ("mouthRight", Make::Mirror(Shape::MouthLeft)),
    ("mouthSmile_L", Make::Own(Shape::MouthSmile)),
    ("mouthSmile_R", Make::Mirror(Shape::MouthSmile)),
    ("mouthFrown_L", Make::Own(Shape::MouthFrown)),
    ("mouthFrown_R", Make::Mirror(Shape::MouthFrown)),
    ("mouthDimple_L", Make::Own(Shape::MouthDimple)),
    ("mouthDimple_R", Make::Mirror(Shape::MouthDimple)),
    ("mouthStretch_L", Make::Own(Shape::MouthStretch)),
    ("mouthStretch_R", Make::Mirror(Shape::MouthStretch)),
    ("mouthRollLower", Make::Own(Shape::MouthRollLower)),
    ("mouthRollUpper", Make::Own(Shape::MouthRollUpper)),
    ("mouthShrugLower", Make::Own(Shape::MouthShrugLower)),
    ("mouthShrugUpper", Make::Own(Shape::MouthShrugUpper)),
    ("mouthPress_L", Make::Own(Shape::MouthPress)),
    ("mouthPress_R", Make::Mirror(Shape::MouthPress)),
    ("mouthLowerDown_L", Make::Own(Shape::MouthLowerDown)),
    ("mouthLowerDown_R", Make::Mirror(Shape::MouthLowerDown)),
    ("mouthUpperUp_L", Make::Own(Shape::MouthUpperUp)),
    ("mouthUpperUp_R", Make::Mirror(Shape::MouthUpperUp)),
    ("browDown_L", Make::Own(Shape::BrowDown)),
    ("browDown_R", Make::Mirror(Shape::BrowDown)),
    ("browInnerUp", Make::Own(Shape::BrowInnerUp)),
    ("browOuterUp_L", Make::Own(Shape::BrowOuterUp)),
    ("browOuterUp_R", Make::Mirror(Shape::BrowOuterUp)),
    ("cheekPuff", Make::Own(Shape::CheekPuff)),
    ("cheekSquint_L", Make::Own(Shape::CheekSquint)),
    ("cheekSquint_R", Make::Mirror(Shape::CheekSquint)),
    ("noseSneer_L", Make::Own(Shape::NoseSneer)),
    ("noseSneer_R", Make::Mirror(Shape::NoseSneer)),
];

/// Index of a target in [`TARGETS`]; used in `const` blocks so a misspelt name fails the build.
const fn tid(name: &str) -> usize {
    let mut i = 0;
    while i < TARGETS.len() {
        if str_eq(TARGETS[i].0, name) {
            return i;
        }
        i += 1;
    }
    panic!("unknown embedded target name");
}

/// Byte-wise string equality usable in `const fn`.
const fn str_eq(a: &str, b: &str) -> bool {
    let (a, b) = (a.as_bytes(), b.as_bytes());
    if a.len() != b.len() {
        return false;
    }
    let mut i = 0;
    while i < a.len() {
        if a[i] != b[i] {
            return false;
        }
        i += 1;
    }
    true
}

/// Hermite smoothstep from `e0` to `e1`; `e0 > e1` gives a falling step.
fn smoothstep(e0: f32, e1: f32, x: f32) -> f32 {
    let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// Smooth compact falloff of a normalized distance: 1 up to `inner`, exactly 0 from 1 on.
fn falloff(d: f32, inner: f32) -> f32 {
    smoothstep(1.0, inner, d)
}

/// Falloff over an axis-aligned ellipse in the (x, y) plane of the face.
fn ellipse(x: f32, y: f32, center: (f32, f32), radii: (f32, f32), inner: f32) -> f32 {
    let d = ((x - center.0) / radii.0).hypot((y - center.1) / radii.1);
    falloff(d, inner)
}

/// Weight of the front of the head, from the vertex's direction on the unit sphere; keeps the
/// (x, y) ellipses of facial regions off the back of the head.
fn front_mask(dir: Vec3) -> f32 {
    smoothstep(0.25, 0.6, dir.z)
}

/// Region that moves with the lower jaw: below the lips (lower toward the cheeks), in front of
/// the ears, forward of the neck.
fn jaw_mask(p: Vec3) -> f32 {
    let ax = p.x.abs();
    let side = smoothstep(MOUTH_CORNER_X, 5.5, ax);
    let top = MOUTH_Y + 0.25 - 0.4 * side;
    let full = MOUTH_Y - 0.35 - 1.6 * side;
    smoothstep(top, full, p.y) * (1.0 - smoothstep(5.0, 7.2, ax)) * smoothstep(-4.0, 0.0, p.z)
}

/// Rotates `v` about the X axis by `a` radians (positive turns +Z toward -Y).
fn rot_x(v: Vec3, a: f32) -> Vec3 {
    let (s, c) = a.sin_cos();
    Vec3::new(v.x, v.y * c - v.z * s, v.y * s + v.z * c)
}

/// Rotates `v` about the Y axis by `a` radians (positive turns +Z toward +X).
fn rot_y(v: Vec3, a: f32) -> Vec3 {
    let (s, c) = a.sin_cos();
    Vec3::new(v.x * c + v.z * s, v.y, v.z * c - v.x * s)
}

/// Delta of a head vertex at neutral position `p` (direction `dir` on the unit sphere) under a
/// shape at weight 1. Left shapes act around +X landmarks; centred ones are symmetric in x.
fn head_delta(shape: Shape, p: Vec3, dir: Vec3) -> Vec3 {
    let front = front_mask(dir);
    let (x, y) = (p.x, p.y);
    let ax = x.abs();
    let region = |center: (f32, f32), radii: (f32, f32), inner: f32| {
        ellipse(x, y, center, radii, inner) * front
    };
    // Eyelids: the skin above and below the left eye opening.
    let upper_lid =
        || region((EYE_X, EYE_Y + 0.6), (2.3, 1.4), 0.35) * smoothstep(EYE_Y - 0.5, EYE_Y + 0.1, y);
    let lower_lid =
        || region((EYE_X, EYE_Y - 0.75), (2.2, 0.95), 0.3) * smoothstep(EYE_Y, EYE_Y - 0.5, y);
    let corner = MOUTH_CORNER_X;
    match shape {
        Shape::EyeBlink => {
            upper_lid() * Vec3::new(0.0, -1.4, 0.55) + lower_lid() * Vec3::new(0.0, 0.5, 0.25)
        }
        Shape::EyeWide => upper_lid() * Vec3::new(0.0, 0.45, 0.05),
        Shape::EyeSquint => {
            lower_lid() * Vec3::new(0.0, 0.4, 0.15) + upper_lid() * Vec3::new(0.0, -0.2, 0.05)
        }
        // The lids follow the eyeball a little when it looks up or down.
        Shape::EyeLookUp => upper_lid() * Vec3::new(0.0, 0.25, 0.0),
        Shape::EyeLookDown => {
            upper_lid() * Vec3::new(0.0, -0.4, 0.12) + lower_lid() * Vec3::new(0.0, -0.12, 0.0)
        }
        Shape::EyeLookIn | Shape::EyeLookOut => Vec3::ZERO,
        Shape::JawOpen => {
            // A hinge rotation about the jaw pivot (chin down and back) plus the forward glide
            // of the condyles, which keeps the chin from swinging too far back.
            let (s, c) = JAW_OPEN_ANGLE.sin_cos();
            let (ry, rz) = (y - JAW_PIVOT.0, p.z - JAW_PIVOT.1);
            let rotated = Vec3::new(0.0, ry * c - rz * s - ry, ry * s + rz * c - rz);
            jaw_mask(p) * (rotated + Vec3::new(0.0, -0.2, 0.9))
        }
        Shape::JawForward => jaw_mask(p) * Vec3::new(0.0, 0.0, 0.8),
        Shape::JawLeft => jaw_mask(p) * Vec3::new(0.9, 0.0, -0.05),
        Shape::MouthClose => {
            // Meant on top of jawOpen: lifts the lower lip back to the upper one.
            region((0.0, MOUTH_Y - 0.45), (2.6, 0.8), 0.2) * Vec3::new(0.0, 1.2, 0.4)
                + region((0.0, MOUTH_Y + 0.45), (2.6, 0.7), 0.2) * Vec3::new(0.0, -0.25, 0.0)
        }
        Shape::MouthFunnel => {
            region((0.0, MOUTH_Y), (3.4, 1.6), 0.35)
                * Vec3::new(-0.25 * x, 0.3 * (y - MOUTH_Y), 0.7)
        }
        Shape::MouthPucker => {
            region((0.0, MOUTH_Y), (3.4, 1.8), 0.3)
                * Vec3::new(-0.35 * x, -0.2 * (y - MOUTH_Y), 0.9)
        }
        Shape::MouthLeft => {
            region((0.0, MOUTH_Y - 0.2), (4.2, 2.4), 0.3) * Vec3::new(1.0, 0.05, -0.1)
        }
        Shape::MouthSmile => {
            region((corner, MOUTH_Y), (2.4, 1.9), 0.15) * Vec3::new(0.55, 0.85, -0.3)
                + region((corner + 1.0, MOUTH_Y + 1.7), (1.8, 1.4), 0.0) * Vec3::new(0.0, 0.35, 0.3)
        }
        Shape::MouthFrown => {
            region((corner, MOUTH_Y - 0.2), (2.0, 1.8), 0.0) * Vec3::new(0.1, -0.75, -0.05)
        }
        Shape::MouthDimple => {
            region((corner + 0.2, MOUTH_Y), (1.4, 1.3), 0.0) * Vec3::new(0.25, 0.05, -0.45)
        }
        Shape::MouthStretch => {
            region((corner + 0.1, MOUTH_Y - 0.2), (2.4, 2.0), 0.0) * Vec3::new(0.75, -0.35, -0.25)
        }
        Shape::MouthRollLower => {
            region((0.0, MOUTH_Y - 0.4), (2.6, 0.75), 0.3) * Vec3::new(0.0, 0.35, -0.6)
        }
        Shape::MouthRollUpper => {
            region((0.0, MOUTH_Y + 0.4), (2.6, 0.75), 0.3) * Vec3::new(0.0, -0.35, -0.6)
        }
        Shape::MouthShrugLower => {
            region((0.0, MOUTH_Y - 1.1), (2.8, 1.8), 0.0) * Vec3::new(0.0, 0.55, 0.35)
        }
        Shape::MouthShrugUpper => {
            region((0.0, MOUTH_Y + 0.5), (2.6, 0.9), 0.0) * Vec3::new(0.0, 0.4, 0.2)
        }
        Shape::MouthPress => {
            // Squeezes both lips toward the line between them on the left half of the mouth.
            region((1.3, MOUTH_Y), (1.9, 1.0), 0.0) * Vec3::new(0.0, -0.9 * (y - MOUTH_Y), -0.35)
        }
        Shape::MouthLowerDown => {
            region((1.2, MOUTH_Y - 0.45), (1.8, 0.9), 0.0) * Vec3::new(0.0, -0.7, 0.05)
        }
        Shape::MouthUpperUp => {
            region((1.2, MOUTH_Y + 0.5), (1.8, 0.9), 0.0) * Vec3::new(0.0, 0.7, 0.1)
        }
        Shape::BrowDown => region((2.7, 3.5), (2.6, 1.4), 0.0) * Vec3::new(-0.3, -0.7, 0.2),
        Shape::BrowInnerUp => {
            ellipse(ax, y, (1.4, 3.6), (1.9, 1.6), 0.0) * front * Vec3::new(0.0, 0.85, 0.05)
        }
        Shape::BrowOuterUp => region((4.6, 3.4), (2.0, 1.5), 0.0) * Vec3::new(0.05, 0.75, 0.0),
        Shape::CheekPuff => {
            let w = ellipse(ax, y, (3.6, -3.9), (2.4, 2.1), 0.2) * front;
            w * Vec3::new(0.8 * x.signum(), -0.1, 0.45)
        }
        Shape::CheekSquint => region((3.6, -0.6), (2.0, 1.4), 0.0) * Vec3::new(0.05, 0.5, 0.25),
        Shape::NoseSneer => region((1.0, -1.5), (1.4, 1.7), 0.0) * Vec3::new(0.05, 0.5, 0.05),
    }
}

/// Delta of a left-eyeball vertex (`local`: position relative to the eye centre) under a shape
/// at weight 1: the rotated position minus the neutral one.
fn eye_delta(shape: Shape, local: Vec3) -> Vec3 {
    let rotated = match shape {
        // A negative angle about X turns the gaze (+Z) up toward +Y.
        Shape::EyeLookUp => rot_x(local, -EYE_PITCH),
        Shape::EyeLookDown => rot_x(local, EYE_PITCH),
        // The left eye sits at +X, so looking in (toward the nose) turns the gaze toward -X.
        Shape::EyeLookIn => rot_y(local, -EYE_YAW),
        Shape::EyeLookOut => rot_y(local, EYE_YAW),
        _ => return Vec3::ZERO,
    };
    rotated - local
}

// ---------------------------------------------------------------------------------------------
// Geometry
// ---------------------------------------------------------------------------------------------

/// A closed latitude/longitude grid: one vertex per pole and `rings - 1` rings of `segments`
/// vertices. Vertex 0 is the first pole, then ring after ring, then the last pole.
#[derive(Clone, Copy)]
struct Grid {
    rings: usize,
    segments: usize,
}

impl Grid {
    fn vertex_count(self) -> usize {
        (self.rings - 1) * self.segments + 2
    }

    /// Vertex of ring `ring` (0 and `rings` are the poles) and column `col` (wrapping).
    fn index(self, ring: usize, col: usize) -> u32 {
        let i = if ring == 0 {
            0
        } else if ring == self.rings {
            self.vertex_count() - 1
        } else {
            1 + (ring - 1) * self.segments + col % self.segments
        };
        i as u32
    }

    /// Ring and column of every vertex, in vertex order (poles report column 0).
    fn cells(self) -> Vec<(usize, usize)> {
        let mut out = Vec::with_capacity(self.vertex_count());
        out.push((0, 0));
        for ring in 1..self.rings {
            out.extend((0..self.segments).map(|col| (ring, col)));
        }
        out.push((self.rings, 0));
        out
    }

    /// The vertex each vertex maps to under the mirror x → -x (column `j` ↔ `segments - j`).
    fn mirror_map(self) -> Vec<u32> {
        self.cells()
            .into_iter()
            .map(|(ring, col)| self.index(ring, (self.segments - col) % self.segments))
            .collect()
    }

    /// Triangle list, counter-clockwise seen from outside when the parametrization's
    /// (d/d ring) × (d/d column) points outward. Quads in the x < 0 half are split along the
    /// other diagonal so the triangulation itself is mirror-symmetric; the two triangles that a
    /// pole collapses are skipped.
    fn indices(self) -> Vec<u32> {
        let mut out = Vec::with_capacity(self.rings * self.segments * 6);
        for r in 0..self.rings {
            for j in 0..self.segments {
                let a = self.index(r, j);
                let b = self.index(r, j + 1);
                let c = self.index(r + 1, j);
                let d = self.index(r + 1, j + 1);
                let tris = if j < self.segments / 2 {
                    [[c, d, b], [c, b, a]]
                } else {
                    [[c, d, a], [a, d, b]]
                };
                for t in tris {
                    if t[0] != t[1] && t[1] != t[2] && t[0] != t[2] {
                        out.extend_from_slice(&t);
                    }
                }
            }
        }
        out
    }

    /// (sin, cos) of the azimuth of each column; exactly mirror-symmetric, with columns 0 and
    /// `segments / 2` exactly on the x = 0 plane. `warp` in [0, 1) packs columns toward
    /// azimuth 0.
    fn azimuths(self, warp: f64) -> Vec<(f32, f32)> {
        let n = self.segments;
        let mut out = vec![(0.0f32, 1.0f32); n];
        for (j, slot) in out.iter_mut().enumerate().take(n / 2 + 1) {
            let t = std::f64::consts::TAU * j as f64 / n as f64;
            let phi = t - warp * t.sin();
            *slot = if j == 0 {
                (0.0, 1.0)
            } else if j == n / 2 {
                (0.0, -1.0)
            } else {
                (phi.sin() as f32, phi.cos() as f32)
            };
        }
        for j in n / 2 + 1..n {
            let (s, c) = out[n - j];
            out[j] = (-s, c);
        }
        out
    }
}

/// Polar angles of the head's rings, packed densely over the face band (between the brow and
/// the chin) by inverting the cumulative of a bumped density.
fn head_ring_angles(rings: usize) -> Vec<f32> {
    const STEPS: usize = 4096;
    let density = |theta: f64| 1.0 + 1.2 * (-((theta - 1.95) / 0.6).powi(2)).exp();
    let dt = std::f64::consts::PI / STEPS as f64;
    let mut cumulative = Vec::with_capacity(STEPS + 1);
    let mut acc = 0.0;
    cumulative.push(0.0);
    for k in 0..STEPS {
        acc += density((k as f64 + 0.5) * dt) * dt;
        cumulative.push(acc);
    }
    let mut out = Vec::with_capacity(rings + 1);
    let mut k = 0;
    for r in 0..=rings {
        let target = acc * r as f64 / rings as f64;
        while k + 1 < STEPS && cumulative[k + 1] < target {
            k += 1;
        }
        let span = cumulative[k + 1] - cumulative[k];
        let frac = if span > 0.0 {
            ((target - cumulative[k]) / span).clamp(0.0, 1.0)
        } else {
            0.0
        };
        out.push(((k as f64 + frac) * dt) as f32);
    }
    out[0] = 0.0;
    out[rings] = std::f32::consts::PI;
    out
}

/// Sculpted head surface for a direction `dir` on the unit sphere with `dir.x >= 0`.
fn head_surface(dir: Vec3) -> Vec3 {
    let mut x = HEAD_RADII.x * dir.x;
    let y = HEAD_RADII.y * dir.y;
    let z = HEAD_RADII.z * dir.z;
    // The jaw is narrower than the cranium.
    x *= 1.0 - 0.2 * smoothstep(-1.0, -9.5, y);
    let front = front_mask(dir);
    let e = |cx: f32, cy: f32, rx: f32, ry: f32| ellipse(x, y, (cx, cy), (rx, ry), 0.0);

    let mut dz = 0.0;
    // Lower face pushed forward (maxilla and mandible), then the finer features on top.
    dz += 1.4 * ellipse(x, y, (0.0, -6.0), (5.5, 5.0), 0.0);
    dz -= 1.3 * e(EYE_X, EYE_Y, 2.1, 1.6);
    dz += 0.7 * e(2.9, 3.3, 3.4, 1.1);
    dz += 0.45 * e(4.2, -0.3, 1.8, 1.3);
    dz += 0.5 * e(1.1, -2.6, 0.7, 0.6);
    dz += 0.45 * e(0.0, MOUTH_Y + 0.45, 2.5, 0.75);
    dz += 0.5 * e(0.0, MOUTH_Y - 0.5, 2.3, 0.8);
    dz -= 0.3 * e(0.0, MOUTH_Y, 2.6, 0.4);
    dz += 1.2 * e(0.0, -8.2, 2.2, 1.4);
    // The nose: a ridge rising from the bridge to the tip, widening toward the nostrils, with
    // a steep underside.
    let height = if y >= -2.3 {
        (0.5 + 2.1 * smoothstep(1.6, -2.3, y)) * smoothstep(2.6, 1.6, y)
    } else {
        2.6 * smoothstep(-3.4, -2.3, y)
    };
    let width = 0.7 + 0.6 * smoothstep(0.0, -2.6, y);
    dz += height * falloff(x / width, 0.0);

    let mut dx = 0.3 * e(4.2, -0.3, 1.8, 1.3) * front;
    // Ears on the sides, a little behind the middle.
    let side = smoothstep(0.72, 0.9, dir.x);
    dx += 0.9 * falloff(((y - 0.3) / 2.3).hypot((z + 0.8) / 1.2), 0.0) * side;

    Vec3::new(x + dx, y, z + dz * front)
}

/// All neutral geometry, plus the mirror map over the concatenated vertex space
/// (head, then `eye_L`, then `eye_R`).
struct Geometry {
    head: Vec<Vec3>,
    /// Direction on the unit sphere each head vertex was sculpted from.
    head_dirs: Vec<Vec3>,
    head_indices: Vec<u32>,
    /// Eyeball positions relative to the eye centre (shared by both eyes).
    eye_local: Vec<Vec3>,
    eye_indices: Vec<u32>,
    eye_l: Vec<Vec3>,
    eye_r: Vec<Vec3>,
    /// Concatenated vertex → its mirror image's concatenated index.
    mirror: Vec<u32>,
}

impl Geometry {
    fn build() -> Self {
        let head_grid = Grid {
            rings: HEAD_RINGS,
            segments: HEAD_SEGMENTS,
        };
        let thetas = head_ring_angles(HEAD_RINGS);
        let columns = head_grid.azimuths(0.45);
        let head_cells = head_grid.cells();
        let head_mirror = head_grid.mirror_map();
        let mut head = Vec::with_capacity(head_cells.len());
        let mut head_dirs = Vec::with_capacity(head_cells.len());
        for &(ring, col) in &head_cells {
            let (st, ct) = thetas[ring].sin_cos();
            let (st, ct) = if ring == 0 {
                (0.0, 1.0)
            } else if ring == HEAD_RINGS {
                (0.0, -1.0)
            } else {
                (st, ct)
            };
            let (sp, cp) = columns[col];
            // Azimuth 0 faces +Z; columns with sp >= 0 are on the +X side and sculpted
            // directly, the others are copied from their mirror image below.
            let dir = Vec3::new(st * sp, ct, st * cp);
            head_dirs.push(dir);
            head.push(head_surface(Vec3::new(dir.x.abs(), dir.y, dir.z)));
        }
        for i in 0..head.len() {
            let m = head_mirror[i] as usize;
            if head_dirs[i].x < 0.0 {
                head[i] = flip_x(head[m]);
            } else if head_dirs[i].x == 0.0 {
                head[i].x = 0.0;
            }
        }

        let eye_grid = Grid {
            rings: EYE_RINGS,
            segments: EYE_SEGMENTS,
        };
        let eye_mirror = eye_grid.mirror_map();
        let eye_columns = eye_grid.azimuths(0.0);
        let eye_local: Vec<Vec3> = eye_grid
            .cells()
            .into_iter()
            .map(|(ring, col)| {
                let theta = std::f32::consts::PI * ring as f32 / EYE_RINGS as f32;
                let (st, ct) = if ring == 0 {
                    (0.0, 1.0)
                } else if ring == EYE_RINGS {
                    (0.0, -1.0)
                } else {
                    theta.sin_cos()
                };
                let (sp, cp) = eye_columns[col];
                // The pole at ring 0 looks along +Z; the cornea bulges around it.
                let radius = EYE_RADIUS * (1.0 + 0.12 * falloff(theta / 0.6, 0.0));
                radius * Vec3::new(st * sp, -st * cp, ct)
            })
            .collect();
        let eye_l: Vec<Vec3> = eye_local.iter().map(|&v| v + EYE_CENTER_L).collect();
        let eye_r: Vec<Vec3> = eye_local
            .iter()
            .map(|&v| v + flip_x(EYE_CENTER_L))
            .collect();

        let h = head.len() as u32;
        let e = eye_l.len() as u32;
        let mut mirror = head_mirror;
        mirror.extend(eye_mirror.iter().map(|&m| h + e + m));
        mirror.extend(eye_mirror.iter().map(|&m| h + m));

        Geometry {
            head,
            head_dirs,
            head_indices: head_grid.indices(),
            eye_local,
            eye_indices: eye_grid.indices(),
            eye_l,
            eye_r,
            mirror,
        }
    }

    /// Vertex ranges of the primitives in the concatenated vertex space.
    fn ranges(&self) -> [std::ops::Range<usize>; 3] {
        let h = self.head.len();
        let e = self.eye_l.len();
        [0..h, h..h + e, h + e..h + 2 * e]
    }

    /// Dense deltas of a shape over the concatenated vertex space; centred shapes are made
    /// exactly mirror-symmetric.
    fn shape_deltas(&self, shape: Shape) -> Vec<Vec3> {
        let mut out: Vec<Vec3> = self
            .head
            .iter()
            .zip(&self.head_dirs)
            .map(|(&p, &dir)| head_delta(shape, p, dir))
            .collect();
        out.extend(self.eye_local.iter().map(|&v| eye_delta(shape, v)));
        out.extend(std::iter::repeat_n(Vec3::ZERO, self.eye_r.len()));
        if shape.is_centered() {
            // Copy the +X half onto the -X half so rounding cannot break the symmetry.
            let head_len = self.head.len();
            for i in 0..head_len {
                let x = self.head[i].x;
                if x < 0.0 {
                    out[i] = flip_x(out[self.mirror[i] as usize]);
                } else if x == 0.0 {
                    out[i].x = 0.0;
                }
            }
        }
        out
    }

    /// The mirror image of dense deltas: the delta at a vertex is the x-flipped delta at its
    /// mirror vertex.
    fn mirrored(&self, deltas: &[Vec3]) -> Vec<Vec3> {
        self.mirror
            .iter()
            .map(|&m| flip_x(deltas[m as usize]))
            .collect()
    }
}

/// Reflects a point or vector across the x = 0 plane.
fn flip_x(v: Vec3) -> Vec3 {
    Vec3::new(-v.x, v.y, v.z)
}

// ---------------------------------------------------------------------------------------------
// Clips
// ---------------------------------------------------------------------------------------------

/// Shorthand for a compile-time checked target index.
macro_rules! t {
    ($name:literal) => {
        const { tid($name) }
    };
}

/// A clip under construction: frame-major rows of weights.
struct Sheet {
    rows: Vec<Vec<f32>>,
}

impl Sheet {
    fn new(seconds: f32, n_targets: usize) -> Self {
        let frames = (seconds * FPS).round() as usize;
        Sheet {
            rows: vec![vec![0.0; n_targets]; frames],
        }
    }

    /// Adds `curve(t)` (t in seconds) to a target's weight on every frame.
    fn add(&mut self, target: usize, curve: impl Fn(f32) -> f32) {
        for (f, row) in self.rows.iter_mut().enumerate() {
            row[target] += curve(f as f32 / FPS);
        }
    }

    /// Adds the same curve to both targets of a left/right pair.
    fn add_pair(&mut self, left: usize, right: usize, curve: impl Fn(f32) -> f32) {
        self.add(left, &curve);
        self.add(right, curve);
    }

    /// Clamps weights to [0, 1] and snaps negligible ones to exactly zero (inactive).
    fn finish(mut self, name: &str) -> Clip {
        for w in self.rows.iter_mut().flatten() {
            *w = if *w < 1e-3 { 0.0 } else { w.min(1.0) };
        }
        let n_targets = self.rows.first().map_or(0, Vec::len);
        Clip::from_frames(name, FPS, n_targets, &self.rows).expect(
            "embedded clips have a fixed shape, fps 30, at least one frame and finite weights",
        )
    }
}

/// A smooth bump over `[start, end]`: sin² of the phase, zero outside.
fn window(t: f32, start: f32, end: f32) -> f32 {
    if t <= start || t >= end {
        0.0
    } else {
        (std::f32::consts::PI * (t - start) / (end - start))
            .sin()
            .powi(2)
    }
}

/// Rises over `attack` seconds from `start`, holds for `hold`, falls over `release`.
fn pulse(t: f32, start: f32, attack: f32, hold: f32, release: f32) -> f32 {
    let rise = smoothstep(start, start + attack, t);
    let fall_start = start + attack + hold;
    rise * (1.0 - smoothstep(fall_start, fall_start + release, t))
}

/// A blink closing at `at` seconds: quick close, brief hold, slower open (about 0.25 s).
fn blink(t: f32, at: f32) -> f32 {
    pulse(t, at, 0.07, 0.05, 0.13)
}

/// Piecewise-constant gaze with quick (0.1 s) saccades: keys are (time, x, y), x toward the
/// character's left, y up, as fractions of a full eyeLook weight.
fn gaze(t: f32, keys: &[(f32, f32, f32)]) -> (f32, f32) {
    let mut prev = (0.0, 0.0);
    let mut out = (0.0, 0.0);
    for &(at, gx, gy) in keys {
        let s = smoothstep(at, at + 0.1, t);
        out.0 += (gx - prev.0) * s;
        out.1 += (gy - prev.1) * s;
        prev = (gx, gy);
    }
    out
}

/// Drives the eight eyeLook targets from a gaze curve, both eyes looking the same way.
fn add_gaze(sheet: &mut Sheet, keys: &[(f32, f32, f32)]) {
    // Looking toward +X is "out" for the left eye and "in" for the right one.
    sheet.add(t!("eyeLookOut_L"), |t| gaze(t, keys).0.max(0.0));
    sheet.add(t!("eyeLookIn_R"), |t| gaze(t, keys).0.max(0.0));
    sheet.add(t!("eyeLookIn_L"), |t| (-gaze(t, keys).0).max(0.0));
    sheet.add(t!("eyeLookOut_R"), |t| (-gaze(t, keys).0).max(0.0));
    sheet.add_pair(t!("eyeLookUp_L"), t!("eyeLookUp_R"), |t| {
        gaze(t, keys).1.max(0.0)
    });
    sheet.add_pair(t!("eyeLookDown_L"), t!("eyeLookDown_R"), |t| {
        (-gaze(t, keys).1).max(0.0)
    });
}

/// Mouth shape of one syllable, as target weights at its peak.
#[derive(Clone, Copy)]
struct Viseme {
    jaw: f32,
    funnel: f32,
    pucker: f32,
    smile: f32,
    stretch: f32,
    press: f32,
    close: f32,
    roll_lower: f32,
    lower_down: f32,
    upper_up: f32,
}

const AA: Viseme = Viseme {
    jaw: 0.6,
    lower_down: 0.3,
    upper_up: 0.1,
    ..ZERO_VISEME
};
const EE: Viseme = Viseme {
    jaw: 0.2,
    smile: 0.3,
    stretch: 0.35,
    ..ZERO_VISEME
};
const EH: Viseme = Viseme {
    jaw: 0.35,
    stretch: 0.25,
    lower_down: 0.15,
    ..ZERO_VISEME
};
const OH: Viseme = Viseme {
    jaw: 0.4,
    funnel: 0.55,
    ..ZERO_VISEME
};
const OO: Viseme = Viseme {
    jaw: 0.12,
    pucker: 0.7,
    funnel: 0.2,
    ..ZERO_VISEME
};
const MBP: Viseme = Viseme {
    jaw: 0.1,
    press: 0.55,
    close: 0.1,
    roll_lower: 0.15,
    ..ZERO_VISEME
};
const FV: Viseme = Viseme {
    jaw: 0.08,
    roll_lower: 0.5,
    upper_up: 0.2,
    ..ZERO_VISEME
};
const ZERO_VISEME: Viseme = Viseme {
    jaw: 0.0,
    funnel: 0.0,
    pucker: 0.0,
    smile: 0.0,
    stretch: 0.0,
    press: 0.0,
    close: 0.0,
    roll_lower: 0.0,
    lower_down: 0.0,
    upper_up: 0.0,
};

/// The clips of the embedded rig.
fn clips(n: usize) -> Vec<Clip> {
    vec![idle(n), talk(n), smile(n), surprise(n)]
}

/// Six seconds of resting: two breaths, two blinks, a few saccades and a brief lip press.
fn idle(n: usize) -> Clip {
    let mut s = Sheet::new(6.0, n);
    // Breathing: active half of each 3 s cycle, so the loop closes exactly.
    let breath = |t: f32| (std::f32::consts::TAU * t / 3.0).sin().max(0.0).powi(2);
    s.add(t!("jawOpen"), move |t| 0.04 * breath(t));
    s.add(t!("browInnerUp"), move |t| 0.08 * breath(t - 0.3));
    s.add_pair(t!("eyeBlink_L"), t!("eyeBlink_R"), |t| {
        blink(t, 1.1) + blink(t, 4.3)
    });
    add_gaze(
        &mut s,
        &[
            (1.5, 0.35, 0.05),
            (2.9, 0.1, -0.3),
            (3.9, -0.3, 0.0),
            (5.4, 0.0, 0.0),
        ],
    );
    s.add_pair(t!("mouthPress_L"), t!("mouthPress_R"), |t| {
        0.2 * pulse(t, 2.9, 0.3, 0.8, 0.4)
    });
    s.add_pair(t!("mouthSmile_L"), t!("mouthSmile_R"), |t| {
        0.12 * pulse(t, 4.6, 0.3, 0.3, 0.4)
    });
    s.finish("idle")
}

/// Four seconds of speech: two phrases of syllables with a pause, brow emphasis and a blink.
fn talk(n: usize) -> Clip {
    const SYLLABLES: [(f32, f32, Viseme); 16] = [
        (0.12, 0.22, AA),
        (0.34, 0.18, EE),
        (0.52, 0.24, OH),
        (0.76, 0.15, MBP),
        (0.91, 0.22, AA),
        (1.13, 0.20, OO),
        (1.33, 0.20, EH),
        (2.00, 0.18, FV),
        (2.18, 0.26, AA),
        (2.44, 0.18, EE),
        (2.62, 0.22, OH),
        (2.84, 0.15, MBP),
        (2.99, 0.28, AA),
        (3.27, 0.22, OO),
        (3.49, 0.20, EH),
        (3.69, 0.14, MBP),
    ];
    // Each syllable's envelope overlaps its neighbours a little (coarticulation).
    let track = |pick: fn(&Viseme) -> f32| {
        move |t: f32| {
            SYLLABLES
                .iter()
                .map(|(start, dur, v)| pick(v) * window(t, start - 0.05, start + dur + 0.05))
                .sum::<f32>()
        }
    };
    let mut s = Sheet::new(4.0, n);
    s.add(t!("jawOpen"), track(|v| v.jaw));
    s.add(t!("mouthFunnel"), track(|v| v.funnel));
    s.add(t!("mouthPucker"), track(|v| v.pucker));
    s.add(t!("mouthClose"), track(|v| v.close));
    s.add(t!("mouthRollLower"), track(|v| v.roll_lower));
    s.add_pair(t!("mouthSmile_L"), t!("mouthSmile_R"), track(|v| v.smile));
    s.add_pair(
        t!("mouthStretch_L"),
        t!("mouthStretch_R"),
        track(|v| v.stretch),
    );
    s.add_pair(t!("mouthPress_L"), t!("mouthPress_R"), track(|v| v.press));
    s.add_pair(
        t!("mouthLowerDown_L"),
        t!("mouthLowerDown_R"),
        track(|v| v.lower_down),
    );
    s.add_pair(
        t!("mouthUpperUp_L"),
        t!("mouthUpperUp_R"),
        track(|v| v.upper_up),
    );
    s.add(t!("browInnerUp"), |t| 0.35 * pulse(t, 0.85, 0.2, 0.4, 0.3));
    s.add_pair(t!("browOuterUp_L"), t!("browOuterUp_R"), |t| {
        0.25 * pulse(t, 0.85, 0.2, 0.4, 0.3)
    });
    s.add_pair(t!("eyeBlink_L"), t!("eyeBlink_R"), |t| blink(t, 1.75));
    s.finish("talk")
}

/// Three seconds: a smile builds, holds with squinting cheeks and eyes, then releases.
fn smile(n: usize) -> Clip {
    let e = |t: f32| smoothstep(0.1, 0.8, t) * (1.0 - smoothstep(2.0, 2.8, t));
    let mut s = Sheet::new(3.0, n);
    // A slightly stronger left side keeps the expression from looking mechanical.
    s.add(t!("mouthSmile_L"), move |t| 0.85 * e(t));
    s.add(t!("mouthSmile_R"), move |t| 0.8 * e(t));
    s.add_pair(t!("cheekSquint_L"), t!("cheekSquint_R"), move |t| {
        0.5 * e(t)
    });
    s.add_pair(t!("eyeSquint_L"), t!("eyeSquint_R"), move |t| 0.3 * e(t));
    s.add_pair(t!("mouthDimple_L"), t!("mouthDimple_R"), move |t| {
        0.15 * e(t)
    });
    s.add(t!("jawOpen"), move |t| 0.08 * e(t));
    s.add_pair(t!("eyeBlink_L"), t!("eyeBlink_R"), |t| blink(t, 1.5));
    s.finish("smile")
}

/// Two and a half seconds: brows and lids fly up, the jaw drops, then everything settles.
fn surprise(n: usize) -> Clip {
    let e = |t: f32| pulse(t, 0.15, 0.2, 1.2, 0.6);
    let mut s = Sheet::new(2.5, n);
    s.add(t!("browInnerUp"), move |t| 0.8 * e(t));
    s.add_pair(t!("browOuterUp_L"), t!("browOuterUp_R"), move |t| {
        0.7 * e(t)
    });
    s.add_pair(t!("eyeWide_L"), t!("eyeWide_R"), move |t| 0.7 * e(t));
    s.add(t!("jawOpen"), move |t| 0.35 * e(t));
    s.add(t!("mouthFunnel"), move |t| 0.25 * e(t));
    s.finish("surprise")
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use super::*;

    /// Bit pattern of a position, with -0.0 folded onto 0.0, for exact mirror look-ups.
    fn key(v: Vec3) -> [u32; 3] {
        [
            (v.x + 0.0).to_bits(),
            (v.y + 0.0).to_bits(),
            (v.z + 0.0).to_bits(),
        ]
    }

    /// Concatenated positions and, for each vertex, the vertex at its exact mirror position.
    fn mirror_lookup(rig: &Rig) -> (Vec<Vec3>, Vec<usize>) {
        let all: Vec<Vec3> = rig
            .primitives
            .iter()
            .flat_map(|p| p.positions.iter().copied())
            .collect();
        let by_key: BTreeMap<[u32; 3], usize> =
            all.iter().enumerate().map(|(i, &v)| (key(v), i)).collect();
        assert_eq!(by_key.len(), all.len(), "no two vertices share a position");
        let mirror = all
            .iter()
            .map(|&v| {
                *by_key
                    .get(&key(flip_x(v)))
                    .expect("every vertex has an exact mirror image")
            })
            .collect();
        (all, mirror)
    }

    /// Dense concatenated deltas of a rig-wide target.
    fn dense(rig: &Rig, target: usize) -> Vec<Vec3> {
        let offsets = rig.vertex_offsets();
        let mut out = vec![Vec3::ZERO; rig.vertex_count()];
        for (p, &off) in rig.primitives.iter().zip(&offsets) {
            for t in p.targets.iter().filter(|t| t.target as usize == target) {
                for (&v, &d) in t.vertices.iter().zip(&t.positions) {
                    out[off + v as usize] = d;
                }
            }
        }
        out
    }

    fn twin(name: &str) -> Option<String> {
        match name {
            "jawLeft" => Some("jawRight".into()),
            "mouthLeft" => Some("mouthRight".into()),
            _ => name.strip_suffix("_L").map(|s| format!("{s}_R")),
        }
    }

    #[test]
    fn sizes_and_validity() {
        let rig = default_rig();
        rig.validate().expect("the embedded rig is valid");
        assert_eq!(rig.name, DEFAULT_RIG_NAME);
        assert!(
            rig.vertex_count() >= 5000,
            "{} vertices",
            rig.vertex_count()
        );
        assert!(rig.targets.len() >= 24);
        assert!(rig.clips.len() >= 3);
        let names: Vec<&str> = rig.primitives.iter().map(|p| p.name.as_str()).collect();
        assert_eq!(names, ["head", "eye_L", "eye_R"]);
        assert_eq!(rig.default_weights, vec![0.0; rig.targets.len()]);
        // Every target moves something, and names are unique.
        assert!(rig.target_nnz().iter().all(|&n| n > 0));
        let unique: std::collections::BTreeSet<&String> = rig.targets.iter().collect();
        assert_eq!(unique.len(), rig.targets.len());
        for p in rig.primitives.iter() {
            assert!(!p.normals_from_file && p.tangents.is_none());
            assert!(
                p.targets
                    .iter()
                    .all(|t| t.normals.is_none() && t.tangents.is_none())
            );
        }
    }

    #[test]
    fn deterministic() {
        assert_eq!(default_rig(), default_rig());
    }

    #[test]
    fn head_is_about_twenty_units_tall_and_faces_plus_z() {
        let rig = default_rig();
        let head = &rig.primitives[0];
        let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
        for &p in &head.positions {
            lo = lo.min(p);
            hi = hi.max(p);
        }
        let size = hi - lo;
        assert!((18.0..23.0).contains(&size.y), "height {}", size.y);
        // The nose tip is the most forward point of the head, and lies in the mid-plane.
        let tip = head
            .positions
            .iter()
            .copied()
            .fold(Vec3::splat(f32::NEG_INFINITY), |a, b| {
                if b.z > a.z { b } else { a }
            });
        assert!(
            tip.x.abs() < 0.5 && tip.y < 0.0 && tip.y > -4.0,
            "nose tip at {tip}"
        );
    }

    #[test]
    fn triangles_wind_outward_and_are_not_degenerate() {
        let rig = default_rig();
        for p in rig.primitives.iter() {
            let center = p.positions.iter().copied().sum::<Vec3>() / p.positions.len() as f32;
            let mut total = 0.0f64;
            let mut outward = 0usize;
            let tris = p.indices.chunks_exact(3);
            let n_tris = tris.len();
            for tri in tris {
                let [a, b, c] = [0, 1, 2].map(|k| p.positions[tri[k] as usize]);
                let n = (b - a).cross(c - a);
                assert!(n.length() > 1e-6, "{}: degenerate triangle {tri:?}", p.name);
                let d = n.dot((a + b + c) / 3.0 - center);
                total += f64::from(d);
                outward += usize::from(d > 0.0);
            }
            assert!(total > 0.0, "{}", p.name);
            assert!(
                outward * 100 >= n_tris * 99,
                "{}: {outward} of {n_tris} outward",
                p.name
            );
            assert!(p.positions.iter().chain(&p.normals).all(|v| v.is_finite()));
        }
    }

    #[test]
    fn mesh_is_mirror_symmetric() {
        let rig = default_rig();
        let (_, mirror) = mirror_lookup(&rig);
        // Mirroring is an involution, and each eye maps onto the other.
        assert!(mirror.iter().enumerate().all(|(i, &m)| mirror[m] == i));
        let offsets = rig.vertex_offsets();
        assert!((offsets[1]..offsets[2]).all(|i| (offsets[2]..offsets[3]).contains(&mirror[i])));
    }

    #[test]
    fn targets_are_localized() {
        let rig = default_rig();
        let head = &rig.primitives[0];
        let n = head.positions.len();
        let height = rig.bbox().max.y - rig.bbox().min.y;
        for t in &head.targets {
            let name = &rig.targets[t.target as usize];
            assert!(
                t.vertices.len() * 2 < n,
                "{name} touches {} of {n}",
                t.vertices.len()
            );
        }
        for id in 0..rig.targets.len() {
            let max = dense(&rig, id)
                .iter()
                .map(|d| d.length())
                .fold(0.0f32, f32::max);
            let name = &rig.targets[id];
            assert!(
                max > 0.015 * height && max < 0.15 * height,
                "{name}: max delta {max}"
            );
        }
    }

    #[test]
    fn left_and_right_targets_are_mirror_images() {
        let rig = default_rig();
        let (_, mirror) = mirror_lookup(&rig);
        let nnz = rig.target_nnz();
        let mut pairs = 0;
        for (l, name) in rig.targets.iter().enumerate() {
            let Some(r_name) = twin(name) else { continue };
            let r = rig
                .target_id(&r_name)
                .expect("every left target has a right twin") as usize;
            pairs += 1;
            assert_eq!(nnz[l], nnz[r], "{name} vs {r_name}");
            let (dl, dr) = (dense(&rig, l), dense(&rig, r));
            for (i, &m) in mirror.iter().enumerate() {
                let diff = (dr[m] - flip_x(dl[i])).abs().max_element();
                assert!(diff <= 1e-6, "{name} vs {r_name} at vertex {i}: {diff}");
            }
        }
        assert!(pairs >= 15, "{pairs} pairs");
        // Centred targets are their own mirror images.
        for id in [
            t!("jawOpen"),
            t!("mouthPucker"),
            t!("browInnerUp"),
            t!("cheekPuff"),
        ] {
            let d = dense(&rig, id);
            for (i, &m) in mirror.iter().enumerate() {
                assert!(
                    (d[m] - flip_x(d[i])).abs().max_element() <= 1e-6,
                    "{}",
                    rig.targets[id]
                );
            }
        }
    }

    #[test]
    fn deltas_point_the_plausible_way() {
        let rig = default_rig();
        let sum = |name: &str| {
            let id = rig.target_id(name).expect("target exists") as usize;
            dense(&rig, id).iter().copied().sum::<Vec3>()
        };
        let jaw = sum("jawOpen");
        assert!(jaw.y < 0.0 && jaw.z < 0.0 && jaw.y < jaw.z, "jawOpen {jaw}");
        let smile = sum("mouthSmile_L");
        assert!(smile.y > 0.0 && smile.x > 0.0, "mouthSmile_L {smile}");
        assert!(sum("eyeBlink_L").y < 0.0);
        assert!(sum("browInnerUp").y > 0.0);
        assert!(sum("mouthPucker").z > 0.0);
        // eyeLook targets move only an eyeball; eyeLookIn_L turns the left eye toward the nose.
        let id = rig.target_id("eyeLookIn_L").expect("target exists");
        let movers: Vec<&str> = rig
            .primitives
            .iter()
            .filter(|p| p.targets.iter().any(|t| t.target == id))
            .map(|p| p.name.as_str())
            .collect();
        assert_eq!(movers, ["eye_L"]);
        let eye = &rig.primitives[1];
        let cornea = eye
            .targets
            .iter()
            .find(|t| t.target == id)
            .and_then(|t| {
                let front = eye
                    .positions
                    .iter()
                    .enumerate()
                    .max_by(|a, b| a.1.z.total_cmp(&b.1.z))?
                    .0;
                let k = t.vertices.iter().position(|&v| v as usize == front)?;
                Some(t.positions[k])
            })
            .expect("the cornea moves");
        assert!(cornea.x < 0.0);
    }

    #[test]
    fn clips_are_bounded_sparse_and_loop() {
        let rig = default_rig();
        let names: Vec<&str> = rig.clips.iter().map(|c| c.name.as_str()).collect();
        assert_eq!(names, ["idle", "talk", "smile", "surprise"]);
        let n = rig.targets.len();
        for c in &rig.clips {
            assert_eq!(c.fps, 30.0);
            assert!(
                (60..=180).contains(&c.frames),
                "{}: {} frames",
                c.name,
                c.frames
            );
            assert!(c.weights.iter().all(|w| (0.0..=1.0).contains(w)));
            let mut active = 0usize;
            let mut w = vec![0.0; n];
            let (mut first, mut last) = (vec![0.0; n], vec![0.0; n]);
            c.frame_weights(0, &mut first);
            c.frame_weights(c.frames - 1, &mut last);
            for f in 0..c.frames {
                c.frame_weights(f, &mut w);
                active += w.iter().filter(|&&x| x != 0.0).count();
            }
            let mean = active as f32 / c.frames as f32;
            assert!(
                mean < n as f32 / 4.0,
                "{}: {mean} active weights per frame",
                c.name
            );
            assert!(active > 0);
            let jump = first
                .iter()
                .zip(&last)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max);
            assert!(jump < 0.1, "{}: loop jump {jump}", c.name);
        }
    }
}
