//! Scene layout of a rendered crowd: where each head stands and where the camera looks from.
//!
//! Pure functions of the request and the rigs' bounding boxes, shared by `POST /v1/crowd/render`
//! and `crowdmorph render`, so both draw the same picture of the same crowd. World units are the
//! rigs' units, +Y is up and heads face +Z (the glTF convention), so the default camera stands
//! on +Z looking down −Z.
//!
//! - A head with a [`Placement`] is drawn with `translate(position) · rotate_y(yaw) ·
//!   scale(scale)` applied to its rig.
//! - The other heads go on a grid, in request order: `ceil(sqrt(n))` columns, left to right
//!   then top to bottom, every cell the largest neutral bounding box among them (x and y) plus
//!   [`GRID_GAP`], each box centred in its cell at z = 0, the grid centred on the origin.
//! - Without a camera, [`default_view`] frames the box holding every drawn head from the front.
//!   With one, near and far planes it does not give are derived from the same box.
//! - A framing camera ([`CameraSpec::frame`]) is that front view fitted to another box:
//!   `bodies` to the same box as without a camera, `faces` to the box holding every head's
//!   face region (its rig's [`Rig::face_region`](crowdmorph_core::rig::Rig::face_region),
//!   placed as the head is). Its far plane still holds every head, so the bodies behind the
//!   faces are drawn, not cut.
//!
//! Validation errors name the field, so the server can answer a 400 that says what to fix.
//! "Finite" is not enough for a renderer: a camera at 3e38, a field of view of 1e-40° or clip
//! planes at 1e-45 are finite numbers whose matrices are not. So every number a request gives
//! is held to a stated range ([`MAX_COORDINATE`], [`MIN_SCALE`]..[`MAX_SCALE`],
//! [`MIN_FOV_Y`]..[`MAX_FOV_Y`], [`MIN_NEAR`], [`MAX_DEPTH_RATIO`]) and the view the layout
//! ends with is checked the way the renderer will use it: its reversed-Z view-projection
//! ([`View::clip_from_world`]) must be finite and invertible. What passes here draws.

use glam::{Mat4, Quat, Vec3};

use crowdmorph_core::rig::Aabb;
use crowdmorph_proto::{CameraFrame, CameraSpec, Placement};

/// Space between grid cells, as a fraction of a cell.
pub const GRID_GAP: f32 = 0.15;

/// Margin of the default camera around the crowd, as a fraction of the image.
pub const FRAME_MARGIN: f32 = 0.05;

/// Largest magnitude of any coordinate a request gives (camera position and target, placement
/// positions), in world units. A million rig units is 1,000 km of metre rigs and 10 km of
/// centimetre ones: every crowd fits, and f32 keeps sub-unit precision across it.
pub const MAX_COORDINATE: f32 = 1e6;

/// Smallest uniform scale of a placement.
pub const MIN_SCALE: f32 = 1e-4;

/// Largest uniform scale of a placement.
pub const MAX_SCALE: f32 = 1e4;

/// Narrowest vertical field of view, degrees (a long telephoto is about 1°).
pub const MIN_FOV_Y: f32 = 0.1;

/// Widest vertical field of view, degrees.
pub const MAX_FOV_Y: f32 = 179.0;

/// Nearest near clip plane, world units.
pub const MIN_NEAR: f32 = 1e-6;

/// Largest ratio of the far clip distance to the near one. The renderer's reversed-Z f32 depth
/// keeps precision far beyond this, but past it a near plane is a typo, not a camera.
pub const MAX_DEPTH_RATIO: f32 = 1e7;

/// Why a scene cannot be laid out.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum SceneError {
    /// A placement is malformed or names no head of the request.
    #[error("{0}")]
    Placement(String),
    /// The camera cannot produce a picture.
    #[error("{0}")]
    Camera(String),
}

/// A perspective view: where the eye is, what it looks at, and the clip planes. The one camera
/// type of rendered frames: the scene layout makes it, the GPU renderer draws with it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct View {
    /// Eye position, world units.
    pub eye: Vec3,
    /// Point at the centre of the image.
    pub target: Vec3,
    /// Up direction (not parallel to `target - eye`).
    pub up: Vec3,
    /// Vertical field of view, degrees, in (0, 180).
    pub fov_y_deg: f32,
    /// Near clip distance, > 0.
    pub near: f32,
    /// Far clip distance, > near.
    pub far: f32,
}

impl View {
    /// The matrix the renderer draws with: reversed-Z perspective (depth 1 at `near`, 0 at
    /// `far`; right-handed, as WebGPU) times the look-at view.
    pub fn clip_from_world(&self, aspect: f32) -> Mat4 {
        // Near and far swapped: reversed Z.
        let proj = glam::camera::rh::proj::directx::perspective(
            self.fov_y_deg.to_radians(),
            aspect,
            self.far,
            self.near,
        );
        proj * glam::camera::rh::view::look_at_mat4(self.eye, self.target, self.up)
    }

    /// Checks that the view can be drawn at `aspect`: its numbers are in range and
    /// [`View::clip_from_world`] is finite and invertible (a matrix of finite numbers can
    /// still overflow, underflow or collapse).
    pub fn check(&self, aspect: f32) -> Result<(), SceneError> {
        let bad = |m: String| Err(SceneError::Camera(format!("camera: {m}")));
        let finite = self.eye.is_finite()
            && self.target.is_finite()
            && self.up.is_finite()
            && self.fov_y_deg.is_finite()
            && self.near.is_finite()
            && self.far.is_finite();
        if !finite {
            return bad(format!("a view of non-finite numbers: {self:?}"));
        }
        if !(MIN_FOV_Y..=MAX_FOV_Y).contains(&self.fov_y_deg) {
            return bad(format!(
                "fov_y {} must be in [{MIN_FOV_Y}, {MAX_FOV_Y}] degrees",
                self.fov_y_deg
            ));
        }
        if !(self.near >= MIN_NEAR && self.far > self.near) {
            return bad(format!(
                "near {} and far {} must satisfy {MIN_NEAR} <= near < far",
                self.near, self.far
            ));
        }
        if self.far / self.near > MAX_DEPTH_RATIO {
            return bad(format!(
                "far {} is more than {MAX_DEPTH_RATIO} times near {}",
                self.far, self.near
            ));
        }
        let forward = (self.target - self.eye).normalize_or_zero();
        if forward == Vec3::ZERO || forward.cross(self.up).normalize_or_zero() == Vec3::ZERO {
            return bad("the eye is at the target, or up is parallel to the view direction".into());
        }
        if !(aspect.is_finite() && aspect > 0.0) {
            return bad(format!("an image aspect of {aspect}"));
        }
        let m = self.clip_from_world(aspect);
        let det = m.determinant();
        if !(m.is_finite() && det.is_finite() && det != 0.0 && m.inverse().is_finite()) {
            return bad(format!(
                "eye {:?}, target {:?}, fov_y {}, near {} and far {} give a projection that \
                 cannot be drawn (not finite or not invertible in f32)",
                self.eye.to_array(),
                self.target.to_array(),
                self.fov_y_deg,
                self.near,
                self.far
            ));
        }
        Ok(())
    }

    /// The view-projection matrix (right-handed, depth 0..1 as in WebGPU), for tests and
    /// anything that wants to know where a point lands.
    pub fn view_projection(&self, aspect: f32) -> Mat4 {
        let proj = glam::camera::rh::proj::directx::perspective(
            self.fov_y_deg.to_radians(),
            aspect,
            self.near,
            self.far,
        );
        proj * glam::camera::rh::view::look_at_mat4(self.eye, self.target, self.up)
    }
}

/// A laid-out crowd: one world transform per head (request order) and the view.
#[derive(Clone, Debug, PartialEq)]
pub struct Scene {
    /// World transform of each head's rig.
    pub transforms: Vec<Mat4>,
    /// The camera.
    pub view: View,
}

/// Lays out a crowd: `boxes[h]` is head `h`'s neutral bounding box and `ids[h]` its request id;
/// `aspect` is the image's width over its height. `faces[h]`, when given, is head `h`'s face
/// region in its rig's space, what a camera framing faces fits; without it (a caller whose
/// camera does not frame faces need not compute them) such a camera fits `boxes`.
pub fn layout(
    boxes: &[Aabb],
    faces: Option<&[Aabb]>,
    ids: &[u64],
    placements: Option<&[Placement]>,
    camera: Option<&CameraSpec>,
    aspect: f32,
) -> Result<Scene, SceneError> {
    let placed = placed_transforms(ids, placements.unwrap_or_default())?;
    let transforms = head_transforms(boxes, &placed);
    let bounds = world_bounds(boxes, &transforms);
    if let Some(b) = bounds
        && (b.max - b.min).max_element() > 4.0 * MAX_COORDINATE
    {
        // Only uploaded rigs of enormous coordinates get here: placements are bounded.
        return Err(SceneError::Camera(format!(
            "the crowd spans {:?} to {:?}, more than {} world units across",
            b.min.to_array(),
            b.max.to_array(),
            4.0 * MAX_COORDINATE
        )));
    }
    let view = match camera {
        Some(c @ CameraSpec { frame: Some(f), .. }) => {
            let fitted = match (f, faces) {
                (CameraFrame::Faces, Some(faces)) => world_bounds(faces, &transforms),
                _ => bounds,
            };
            framed_view(c, *f, fitted, bounds, aspect)?
        }
        Some(c) => camera_view(c, bounds)?,
        None => default_view(bounds, crowdmorph_proto::DEFAULT_FOV_Y, aspect),
    };
    view.check(aspect)?;
    Ok(Scene { transforms, view })
}

fn finite3(v: [f32; 3]) -> bool {
    v.iter().all(|c| c.is_finite())
}

/// Whether every coordinate is finite and within ±[`MAX_COORDINATE`].
fn in_range3(v: [f32; 3]) -> bool {
    v.iter().all(|c| c.is_finite() && c.abs() <= MAX_COORDINATE)
}

/// The transform of one placement: translate · rotate about +Y · uniform scale.
pub fn placement_matrix(p: &Placement) -> Result<Mat4, SceneError> {
    let bad = |what: String| SceneError::Placement(format!("placement of head {}: {what}", p.head));
    if !in_range3(p.position) {
        return Err(bad(format!(
            "position {:?} must be finite numbers within ±{MAX_COORDINATE}",
            p.position
        )));
    }
    if !p.yaw.is_finite() {
        return Err(bad(format!(
            "yaw {} must be a finite number of degrees",
            p.yaw
        )));
    }
    if !(p.scale.is_finite() && p.scale > 0.0) {
        return Err(bad(format!(
            "scale {} must be a finite number > 0",
            p.scale
        )));
    }
    if !(MIN_SCALE..=MAX_SCALE).contains(&p.scale) {
        return Err(bad(format!(
            "scale {} must be in [{MIN_SCALE}, {MAX_SCALE}]",
            p.scale
        )));
    }
    // Whole turns dropped first: any finite yaw is an angle (fmod is exact in f32).
    let yaw = p.yaw.rem_euclid(360.0);
    Ok(Mat4::from_scale_rotation_translation(
        Vec3::splat(p.scale),
        Quat::from_rotation_y(yaw.to_radians()),
        Vec3::from_array(p.position),
    ))
}

/// Most bytes [`placed_transforms`] allocates for `n` placements beyond its result (one per
/// head): its map of each placement's matrix and use, and the list of ids that name no head.
/// A caller charges this before the placements arrive at it.
pub fn placement_bytes(n: usize) -> u64 {
    crowdmorph_core::rig::map_bytes(n, size_of::<(u64, (Mat4, bool))>() as u64)
        + n as u64 * size_of::<u64>() as u64
}

/// Per head (by position in `ids`), the transform its placement gives, if any. A placement
/// applies to every head with its id; one naming no head, or a second one for an id, is an
/// error.
pub fn placed_transforms(
    ids: &[u64],
    placements: &[Placement],
) -> Result<Vec<Option<Mat4>>, SceneError> {
    // Each placement's matrix and whether some head has its id. One pass over the placements
    // and one over the heads: checking every placement against every head was heads ×
    // placements compares per request (5e9 at 100,000 of each).
    let mut by_id: std::collections::HashMap<u64, (Mat4, bool)> =
        std::collections::HashMap::with_capacity(placements.len());
    for (i, p) in placements.iter().enumerate() {
        let m = placement_matrix(p).map_err(|e| match e {
            SceneError::Placement(m) => SceneError::Placement(format!("placements[{i}]: {m}")),
            other => other,
        })?;
        if by_id.insert(p.head, (m, false)).is_some() {
            return Err(SceneError::Placement(format!(
                "placements[{i}]: head {} is placed twice",
                p.head
            )));
        }
    }
    let placed: Vec<Option<Mat4>> = ids
        .iter()
        .map(|id| {
            by_id.get_mut(id).map(|(m, used)| {
                *used = true;
                *m
            })
        })
        .collect();
    // Sorted, so the message is the same on every run.
    let mut missing: Vec<u64> = by_id
        .iter()
        .filter(|(_, (_, used))| !used)
        .map(|(&id, _)| id)
        .collect();
    if !missing.is_empty() {
        missing.sort_unstable();
        missing.truncate(10);
        return Err(SceneError::Placement(format!(
            "placements name heads that are not in the request: {missing:?}"
        )));
    }
    Ok(placed)
}

/// Every head's world transform: its placement's, or its grid cell's.
pub fn head_transforms(boxes: &[Aabb], placed: &[Option<Mat4>]) -> Vec<Mat4> {
    let free: Vec<usize> = (0..boxes.len())
        .filter(|&h| placed.get(h).copied().flatten().is_none())
        .collect();
    let cells = grid_cells(free.len());
    let cell = free
        .iter()
        .map(|&h| boxes[h].max - boxes[h].min)
        .fold(Vec3::ZERO, Vec3::max)
        * (1.0 + GRID_GAP);
    let mut out: Vec<Mat4> = (0..boxes.len())
        .map(|h| placed.get(h).copied().flatten().unwrap_or(Mat4::IDENTITY))
        .collect();
    for (k, &h) in free.iter().enumerate() {
        let (col, row) = cells.at(k);
        let centre = Vec3::new(
            (col as f32 - (cells.cols - 1) as f32 * 0.5) * cell.x,
            ((cells.rows - 1) as f32 * 0.5 - row as f32) * cell.y,
            0.0,
        );
        let box_centre = (boxes[h].min + boxes[h].max) * 0.5;
        out[h] = Mat4::from_translation(centre - box_centre);
    }
    out
}

/// Columns and rows of a grid of `n` heads: as square as it gets, wider when not.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Grid {
    /// Columns.
    pub cols: usize,
    /// Rows.
    pub rows: usize,
}

impl Grid {
    /// Column and row of the `k`-th head (row 0 at the top).
    pub fn at(&self, k: usize) -> (usize, usize) {
        (k % self.cols, k / self.cols)
    }
}

/// The grid of `n` heads: `ceil(sqrt(n))` columns.
pub fn grid_cells(n: usize) -> Grid {
    let mut cols = (n as f64).sqrt().ceil() as usize;
    // Floating-point square roots of perfect squares are exact, but be sure.
    while cols * cols < n {
        cols += 1;
    }
    let cols = cols.max(1);
    Grid {
        cols,
        rows: n.div_ceil(cols).max(1),
    }
}

/// The box holding every head's transformed bounding box; `None` without heads.
pub fn world_bounds(boxes: &[Aabb], transforms: &[Mat4]) -> Option<Aabb> {
    let mut min = Vec3::splat(f32::INFINITY);
    let mut max = Vec3::splat(f32::NEG_INFINITY);
    for (b, m) in boxes.iter().zip(transforms) {
        for i in 0..8 {
            let corner = Vec3::new(
                if i & 1 == 0 { b.min.x } else { b.max.x },
                if i & 2 == 0 { b.min.y } else { b.max.y },
                if i & 4 == 0 { b.min.z } else { b.max.z },
            );
            let p = m.transform_point3(corner);
            min = min.min(p);
            max = max.max(p);
        }
    }
    (min.x <= max.x && min.is_finite() && max.is_finite()).then_some(Aabb { min, max })
}

/// A front view (looking down −Z) at `bounds`, from the distance at which the box's front face
/// fills the image but for [`FRAME_MARGIN`]; without heads, a unit view of the origin.
pub fn default_view(bounds: Option<Aabb>, fov_y_deg: f32, aspect: f32) -> View {
    let Some(b) = bounds else {
        return View {
            eye: Vec3::Z,
            target: Vec3::ZERO,
            up: Vec3::Y,
            fov_y_deg,
            near: 0.1,
            far: 10.0,
        };
    };
    let centre = (b.min + b.max) * 0.5;
    let half = (b.max - b.min) * 0.5;
    let tan = (fov_y_deg.to_radians() * 0.5).tan();
    let aspect = if aspect.is_finite() && aspect > 0.0 {
        aspect
    } else {
        1.0
    };
    // The front face is nearest the eye, so it is what must fit; everything behind it
    // projects smaller.
    let fit = (half.y / tan).max(half.x / (tan * aspect)) / (1.0 - 2.0 * FRAME_MARGIN);
    let size = (b.max - b.min).max_element();
    let distance = fit.max(size * 1e-3).max(1e-4);
    let depth = b.max.z - b.min.z;
    View {
        eye: Vec3::new(centre.x, centre.y, b.max.z + distance),
        target: centre,
        up: Vec3::Y,
        fov_y_deg,
        near: distance * 0.5,
        far: (distance + depth) * 1.5,
    }
}

/// The view a [`CameraSpec`] asks for, checked; clip planes it leaves out are derived from
/// `bounds` so that every head lies between them.
pub fn camera_view(spec: &CameraSpec, bounds: Option<Aabb>) -> Result<View, SceneError> {
    let bad = |m: String| SceneError::Camera(format!("camera: {m}"));
    if let Some(f) = spec.frame {
        return Err(bad(format!(
            "frame {:?} places the camera itself; a camera that looks from a position is \
             one without frame",
            f.name()
        )));
    }
    let (Some(position), Some(target)) = (spec.position, spec.target) else {
        return Err(bad(
            "position and target are required, unless frame (\"faces\" or \"bodies\") \
             places the camera"
                .into(),
        ));
    };
    if !finite3(position) || !finite3(target) {
        return Err(bad(format!(
            "position {position:?} and target {target:?} must be finite numbers"
        )));
    }
    if !in_range3(position) || !in_range3(target) {
        return Err(bad(format!(
            "position {position:?} and target {target:?} must be within ±{MAX_COORDINATE}"
        )));
    }
    let eye = Vec3::from_array(position);
    let target_point = Vec3::from_array(target);
    let forward = target_point - eye;
    let reach = eye.abs().max(target_point.abs()).max_element().max(1.0);
    if forward.length() <= reach * 1e-6 {
        return Err(bad(format!(
            "target {target:?} is the camera's position; it must be a point to look at"
        )));
    }
    check_fov(spec)?;
    let forward = forward.normalize();
    let (near, far) = clip_planes(spec, derived_planes(eye, forward, bounds))?;
    // Looking straight up or down, +Y cannot be up: the image's top is then the direction
    // away from the heads' faces (−Z looking down, +Z looking up).
    let up = if forward.cross(Vec3::Y).length() < 1e-3 {
        if forward.y < 0.0 { -Vec3::Z } else { Vec3::Z }
    } else {
        Vec3::Y
    };
    Ok(View {
        eye,
        target: target_point,
        up,
        fov_y_deg: spec.fov_y,
        near,
        far,
    })
}

/// The view of a framing camera: [`default_view`] of `fitted` (the box of what `frame` fits:
/// the faces or the whole crowd), with its far plane pushed back to hold `crowd` (every head)
/// and the camera's own field of view and planes.
pub fn framed_view(
    spec: &CameraSpec,
    frame: CameraFrame,
    fitted: Option<Aabb>,
    crowd: Option<Aabb>,
    aspect: f32,
) -> Result<View, SceneError> {
    let given: Vec<String> = [("position", spec.position), ("target", spec.target)]
        .into_iter()
        .filter_map(|(name, v)| v.map(|v| format!("{name} {v:?}")))
        .collect();
    if !given.is_empty() {
        return Err(SceneError::Camera(format!(
            "camera: frame {:?} places the camera itself, so position and target must be \
             absent, not {}",
            frame.name(),
            given.join(" and ")
        )));
    }
    check_fov(spec)?;
    let mut view = default_view(fitted, spec.fov_y, aspect);
    // Faces are a part of each figure: what lies behind them (a body, a row further back)
    // is drawn to the crowd's end, not cut at the faces' far side. The depth ratio is kept,
    // so a tiny face in a vast crowd loses the far heads, not the picture.
    let forward = (view.target - view.eye).normalize_or_zero();
    if crowd.is_some() && forward != Vec3::ZERO {
        let (_, crowd_far) = derived_planes(view.eye, forward, crowd);
        view.far = view
            .far
            .max(crowd_far)
            .min(view.near * MAX_DEPTH_RATIO * 0.5);
    }
    let (near, far) = clip_planes(spec, (view.near, view.far))?;
    view.near = near;
    view.far = far;
    Ok(view)
}

fn check_fov(spec: &CameraSpec) -> Result<(), SceneError> {
    if !(spec.fov_y.is_finite() && (MIN_FOV_Y..=MAX_FOV_Y).contains(&spec.fov_y)) {
        return Err(SceneError::Camera(format!(
            "camera: fov_y {} must be in [{MIN_FOV_Y}, {MAX_FOV_Y}] degrees",
            spec.fov_y
        )));
    }
    Ok(())
}

/// The clip planes of a camera: those it gives, checked, and for those it leaves out the
/// `derived` ones (near, far), kept within [`MAX_DEPTH_RATIO`] of the one it gives so that
/// only the client's own numbers can be refused.
fn clip_planes(spec: &CameraSpec, derived: (f32, f32)) -> Result<(f32, f32), SceneError> {
    let bad = |m: String| SceneError::Camera(format!("camera: {m}"));
    for (name, v) in [("near", spec.near), ("far", spec.far)] {
        if let Some(v) = v
            && !(v.is_finite() && v > 0.0)
        {
            return Err(bad(format!("{name} {v} must be a finite number > 0")));
        }
    }
    if let Some(n) = spec.near
        && n < MIN_NEAR
    {
        return Err(bad(format!("near {n} must be at least {MIN_NEAR}")));
    }
    let (near_d, far_d) = derived;
    let (near, far) = match (spec.near, spec.far) {
        (Some(n), Some(f)) => (n, f),
        (Some(n), None) => (n, far_d.max(n * 2.0).min(n * MAX_DEPTH_RATIO)),
        (None, Some(f)) => {
            let n = if near_d < f { near_d } else { f * 1e-3 };
            (n.max(f / MAX_DEPTH_RATIO).max(MIN_NEAR), f)
        }
        (None, None) => (near_d.max(MIN_NEAR), far_d.max(MIN_NEAR * 2.0)),
    };
    if near >= far {
        return Err(bad(format!("near {near} must be less than far {far}")));
    }
    if far / near > MAX_DEPTH_RATIO {
        return Err(bad(format!(
            "far {far} is more than {MAX_DEPTH_RATIO} times near {near}"
        )));
    }
    Ok((near, far))
}

/// Near and far distances along `forward` that hold `bounds` (a little inside and beyond); a
/// unit range without heads or with every head behind the eye.
fn derived_planes(eye: Vec3, forward: Vec3, bounds: Option<Aabb>) -> (f32, f32) {
    let Some(b) = bounds else {
        return (0.01, 10.0);
    };
    let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
    for i in 0..8 {
        let corner = Vec3::new(
            if i & 1 == 0 { b.min.x } else { b.max.x },
            if i & 2 == 0 { b.min.y } else { b.max.y },
            if i & 4 == 0 { b.min.z } else { b.max.z },
        );
        let d = (corner - eye).dot(forward);
        lo = lo.min(d);
        hi = hi.max(d);
    }
    if hi <= 0.0 {
        return (0.01, 10.0);
    }
    let far = hi * 1.05;
    // With the eye inside the crowd, the nearest head may be at any distance: a near plane a
    // thousandth of the far one keeps depth precision without cutting much away.
    let near = if lo > 0.0 { lo * 0.95 } else { far * 1e-3 };
    (near.max(far * 1e-5), far)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit_box() -> Aabb {
        Aabb {
            min: Vec3::new(-0.1, -0.15, -0.05),
            max: Vec3::new(0.1, 0.15, 0.12),
        }
    }

    fn corners(b: &Aabb) -> Vec<Vec3> {
        (0..8)
            .map(|i| {
                Vec3::new(
                    if i & 1 == 0 { b.min.x } else { b.max.x },
                    if i & 2 == 0 { b.min.y } else { b.max.y },
                    if i & 4 == 0 { b.min.z } else { b.max.z },
                )
            })
            .collect()
    }

    /// Normalized device coordinates of every corner of every head's box.
    fn ndc(scene: &Scene, boxes: &[Aabb], aspect: f32) -> Vec<Vec3> {
        let vp = scene.view.view_projection(aspect);
        boxes
            .iter()
            .zip(&scene.transforms)
            .flat_map(|(b, m)| corners(b).into_iter().map(move |c| m.transform_point3(c)))
            .map(|p| vp.project_point3(p))
            .collect()
    }

    fn placement(head: u64, position: [f32; 3], yaw: f32, scale: f32) -> Placement {
        Placement {
            head,
            position,
            yaw,
            scale,
        }
    }

    #[test]
    fn grids_are_square_enough_and_hold_every_head() {
        for n in 0..200 {
            let g = grid_cells(n);
            assert!(g.cols * g.rows >= n, "{n}: {g:?}");
            assert!(g.cols >= g.rows, "{n}: {g:?}");
            assert!(
                g.cols * (g.rows - 1) < n.max(1),
                "{n}: a whole empty row in {g:?}"
            );
        }
        assert_eq!(grid_cells(9), Grid { cols: 3, rows: 3 });
        assert_eq!(grid_cells(10), Grid { cols: 4, rows: 3 });
        assert_eq!(grid_cells(100), Grid { cols: 10, rows: 10 });
    }

    #[test]
    fn a_crowd_without_placements_is_a_centred_grid_in_reading_order() {
        let boxes = vec![unit_box(); 9];
        let t = head_transforms(&boxes, &[None; 9]);
        let centre = |m: &Mat4| m.transform_point3((unit_box().min + unit_box().max) * 0.5);
        let step = (unit_box().max - unit_box().min) * (1.0 + GRID_GAP);
        // Head 0 top left, head 2 top right, head 6 bottom left; the middle one at the origin.
        assert!((centre(&t[0]) - Vec3::new(-step.x, step.y, 0.0)).length() < 1e-6);
        assert!((centre(&t[2]) - Vec3::new(step.x, step.y, 0.0)).length() < 1e-6);
        assert!((centre(&t[6]) - Vec3::new(-step.x, -step.y, 0.0)).length() < 1e-6);
        assert!(centre(&t[4]).length() < 1e-6);
        // No two heads overlap: neighbours are a cell apart, and a cell is larger than a box.
        let b = world_bounds(&boxes, &t).expect("a valid scene");
        assert!((b.max.x - b.min.x - (2.0 * step.x + 0.2)).abs() < 1e-5);
        // Only translations: every head faces +Z at its rig's size.
        for m in &t {
            assert!((m.transform_vector3(Vec3::Z) - Vec3::Z).length() < 1e-6);
        }
        // Deterministic.
        assert_eq!(t, head_transforms(&boxes, &[None; 9]));
    }

    #[test]
    fn the_grid_cell_is_the_largest_box_and_placed_heads_keep_their_place() {
        let big = Aabb {
            min: Vec3::splat(-1.0),
            max: Vec3::splat(1.0),
        };
        let boxes = vec![unit_box(), big, unit_box()];
        let at = placement_matrix(&placement(9, [5.0, 0.0, 0.0], 0.0, 1.0)).expect("a valid scene");
        let t = head_transforms(&boxes, &[None, Some(at), None]);
        assert_eq!(t[1], at);
        // Two free heads: one row of two, cells as large as the larger free box (the unit
        // box), not the placed one.
        let step = (unit_box().max.x - unit_box().min.x) * (1.0 + GRID_GAP);
        let c0 = t[0].transform_point3((unit_box().min + unit_box().max) * 0.5);
        let c2 = t[2].transform_point3((unit_box().min + unit_box().max) * 0.5);
        assert!((c2.x - c0.x - step).abs() < 1e-6 && (c2.y - c0.y).abs() < 1e-6);
    }

    #[test]
    fn a_placement_translates_turns_about_y_and_scales() {
        let m = placement_matrix(&placement(1, [1.0, 2.0, 3.0], 90.0, 2.0)).expect("a valid scene");
        // The face's +Z turns to +X, doubled, then moved.
        let p = m.transform_point3(Vec3::Z);
        assert!((p - Vec3::new(3.0, 2.0, 3.0)).length() < 1e-5, "{p}");
        let up = m.transform_vector3(Vec3::Y);
        assert!((up - Vec3::new(0.0, 2.0, 0.0)).length() < 1e-5, "{up}");
        assert_eq!(
            placement_matrix(&placement(1, [0.0; 3], 0.0, 1.0)).expect("a valid scene"),
            Mat4::IDENTITY
        );
    }

    #[test]
    fn bad_placements_are_refused_naming_the_field() {
        let msg = |r: Result<Vec<Option<Mat4>>, SceneError>| match r {
            Err(SceneError::Placement(m)) => m,
            other => panic!("expected a placement error, got {other:?}"),
        };
        let ids = [1u64, 2, 2];
        let m = msg(placed_transforms(&ids, &[placement(1, [0.0; 3], 0.0, 0.0)]));
        assert!(m.contains("placements[0]") && m.contains("scale 0"), "{m}");
        let m = msg(placed_transforms(
            &ids,
            &[placement(2, [0.0; 3], 0.0, -1.0)],
        ));
        assert!(m.contains("scale -1"), "{m}");
        let m = msg(placed_transforms(
            &ids,
            &[placement(1, [f32::NAN, 0.0, 0.0], 0.0, 1.0)],
        ));
        assert!(m.contains("position"), "{m}");
        let m = msg(placed_transforms(
            &ids,
            &[placement(1, [0.0; 3], f32::INFINITY, 1.0)],
        ));
        assert!(m.contains("yaw"), "{m}");
        let m = msg(placed_transforms(&ids, &[placement(7, [0.0; 3], 0.0, 1.0)]));
        assert!(m.contains("not in the request") && m.contains('7'), "{m}");
        let twice = [
            placement(1, [0.0; 3], 0.0, 1.0),
            placement(1, [1.0; 3], 0.0, 1.0),
        ];
        let m = msg(placed_transforms(&ids, &twice));
        assert!(m.contains("placements[1]") && m.contains("twice"), "{m}");
        // A placement applies to every head with its id.
        let ok = placed_transforms(&ids, &[placement(2, [1.0, 0.0, 0.0], 0.0, 1.0)])
            .expect("a valid scene");
        assert!(ok[0].is_none() && ok[1].is_some() && ok[1] == ok[2]);
    }

    #[test]
    fn many_placements_match_their_heads_and_name_the_first_missing_ids_sorted() {
        // A large crowd with repeated ids: every even id is placed at x = id, odd ids go on
        // the grid, and each head with a placed id gets that placement's transform.
        let ids: Vec<u64> = (0..5_000u64).map(|k| k % 2_500).collect();
        let placements: Vec<Placement> = (0..2_500u64)
            .rev()
            .filter(|id| id % 2 == 0)
            .map(|id| placement(id, [id as f32, 0.0, 0.0], 0.0, 1.0))
            .collect();
        let placed = placed_transforms(&ids, &placements).expect("every placement names a head");
        assert_eq!(placed.len(), ids.len());
        for (id, m) in ids.iter().zip(&placed) {
            if id % 2 == 0 {
                let want = Mat4::from_translation(Vec3::new(*id as f32, 0.0, 0.0));
                assert_eq!(*m, Some(want), "head {id}");
            } else {
                assert_eq!(*m, None, "head {id}");
            }
        }
        // Fifteen placements name no head, given in descending order: the message lists the
        // ten smallest, ascending, whatever the order of the request.
        let mut with_strays = placements.clone();
        with_strays.extend(
            (0..15u64)
                .rev()
                .map(|k| placement(10_000 + 3 * k, [0.0; 3], 0.0, 1.0)),
        );
        let m = match placed_transforms(&ids, &with_strays) {
            Err(SceneError::Placement(m)) => m,
            other => panic!("expected a placement error, got {other:?}"),
        };
        assert_eq!(
            m,
            "placements name heads that are not in the request: \
             [10000, 10003, 10006, 10009, 10012, 10015, 10018, 10021, 10024, 10027]"
        );
        // More placements than heads: still the same message, not a shortcut.
        let m = match placed_transforms(&ids[..1], &placements[..3]) {
            Err(SceneError::Placement(m)) => m,
            other => panic!("expected a placement error, got {other:?}"),
        };
        assert_eq!(
            m,
            "placements name heads that are not in the request: [2494, 2496, 2498]"
        );
    }

    #[test]
    fn the_default_camera_frames_every_head_for_any_aspect() {
        for (n, aspect) in [
            (1usize, 4.0 / 3.0),
            (9, 4.0 / 3.0),
            (100, 16.0 / 9.0),
            (7, 0.5),
        ] {
            let boxes = vec![unit_box(); n];
            let ids: Vec<u64> = (0..n as u64).collect();
            let scene = layout(&boxes, None, &ids, None, None, aspect).expect("a valid scene");
            let v = &scene.view;
            assert!(
                (v.target - v.eye).normalize().dot(-Vec3::Z) > 0.9999,
                "front view"
            );
            let points = ndc(&scene, &boxes, aspect);
            let (mut mx, mut my) = (0.0f32, 0.0f32);
            for p in &points {
                assert!(
                    p.x.abs() <= 1.0 && p.y.abs() <= 1.0,
                    "{n} heads: {p} off screen"
                );
                assert!(p.z > 0.0 && p.z < 1.0, "{n} heads: {p} clipped by near/far");
                mx = mx.max(p.x.abs());
                my = my.max(p.y.abs());
            }
            // Framed, not lost in the middle: one axis reaches the margin.
            assert!(
                mx.max(my) > 0.85,
                "{n} heads: the crowd fills only {mx} × {my}"
            );
        }
    }

    #[test]
    fn a_scene_without_heads_still_has_a_valid_view() {
        let scene = layout(&[], None, &[], None, None, 1.0).expect("a valid scene");
        assert!(scene.transforms.is_empty());
        assert!(scene.view.near > 0.0 && scene.view.near < scene.view.far);
        assert!(scene.view.view_projection(1.0).is_finite());
    }

    fn camera(position: [f32; 3], target: [f32; 3], fov_y: f32) -> CameraSpec {
        CameraSpec {
            fov_y,
            ..CameraSpec::looking(position, target)
        }
    }

    #[test]
    fn a_given_camera_gets_planes_that_hold_the_crowd() {
        let boxes = vec![unit_box(); 4];
        let ids = [1, 2, 3, 4];
        for spec in [
            camera([0.0, 0.5, 2.0], [0.0; 3], 40.0),
            camera([3.0, 1.0, -2.0], [0.0; 3], 60.0),
            // Inside the crowd.
            camera([0.0, 0.0, 0.0], [0.0, 0.0, -1.0], 90.0),
        ] {
            let scene = layout(&boxes, None, &ids, None, Some(&spec), 1.0).expect("a valid scene");
            let v = scene.view;
            assert!(v.near > 0.0 && v.near < v.far, "{v:?}");
            let forward = (v.target - v.eye).normalize();
            let placed = world_bounds(&boxes, &scene.transforms).expect("a valid scene");
            for c in corners(&placed) {
                let d = (c - v.eye).dot(forward);
                assert!(d <= v.far, "{c} beyond far in {v:?}");
                if spec.position != Some([0.0; 3]) {
                    assert!(d >= v.near, "{c} before near in {v:?}");
                }
            }
        }
        // Given planes are kept.
        let spec = CameraSpec {
            near: Some(0.5),
            far: Some(7.0),
            ..camera([0.0, 0.0, 2.0], [0.0; 3], 30.0)
        };
        let v = camera_view(&spec, None).expect("a valid scene");
        assert_eq!((v.near, v.far), (0.5, 7.0));
    }

    #[test]
    fn looking_straight_down_has_an_up_direction() {
        let v = camera_view(&camera([0.0, 5.0, 0.0], [0.0; 3], 30.0), None).expect("a valid scene");
        assert_eq!(v.up, -Vec3::Z);
        assert!(v.view_projection(1.0).is_finite());
        let v =
            camera_view(&camera([0.0, -5.0, 0.0], [0.0; 3], 30.0), None).expect("a valid scene");
        assert_eq!(v.up, Vec3::Z);
    }

    #[test]
    fn bad_cameras_are_refused_naming_the_field() {
        let msg = |spec: CameraSpec| match camera_view(&spec, None) {
            Err(SceneError::Camera(m)) => m,
            other => panic!("expected a camera error for {spec:?}, got {other:?}"),
        };
        assert!(msg(camera([1.0, 2.0, 3.0], [1.0, 2.0, 3.0], 30.0)).contains("target"));
        for fov in [0.0, 180.0, -5.0, 200.0, f32::NAN] {
            assert!(msg(camera([0.0; 3], [0.0, 0.0, -1.0], fov)).contains("fov_y"));
        }
        assert!(msg(camera([f32::INFINITY, 0.0, 0.0], [0.0; 3], 30.0)).contains("finite"));
        let planes = |near, far| CameraSpec {
            near,
            far,
            ..camera([0.0, 0.0, 1.0], [0.0; 3], 30.0)
        };
        assert!(msg(planes(Some(2.0), Some(1.0))).contains("near 2"));
        assert!(msg(planes(Some(0.0), None)).contains("near 0"));
        assert!(msg(planes(None, Some(-1.0))).contains("far -1"));
        assert!(msg(planes(Some(1.0), Some(1.0))).contains("less than far"));
        // Finite but absurd: each is refused by the number that makes it so.
        assert!(msg(camera([3e38, 0.0, 5.0], [0.0; 3], 30.0)).contains("within"));
        assert!(msg(camera([0.0, 0.0, 5.0], [0.0; 3], 1e-40)).contains("fov_y"));
        assert!(msg(camera([0.0, 0.0, 5.0], [0.0; 3], 179.5)).contains("fov_y"));
        assert!(msg(planes(Some(1e-45), Some(1e-44))).contains("near"));
        assert!(msg(planes(Some(1e-3), Some(1e30))).contains("times near"));
        // The limits themselves draw, planes derived or not.
        for spec in [
            camera([0.0, 0.0, MAX_COORDINATE], [0.0; 3], MIN_FOV_Y),
            camera([0.0, 0.0, 5.0], [0.0; 3], MAX_FOV_Y),
            planes(Some(MIN_NEAR), Some(MIN_NEAR * MAX_DEPTH_RATIO)),
            planes(Some(MIN_NEAR), None),
            planes(None, Some(1e9)),
        ] {
            let v = camera_view(&spec, Some(unit_box())).expect("a valid camera");
            for aspect in [1.0 / 4096.0, 1.0, 4096.0] {
                assert_eq!(v.check(aspect), Ok(()), "{spec:?} at {aspect}");
            }
        }
    }

    #[test]
    fn absurd_placements_are_refused_and_huge_yaws_are_angles() {
        let bad = |p: Placement| match placement_matrix(&p) {
            Err(SceneError::Placement(m)) => m,
            other => panic!("expected a placement error for {p:?}, got {other:?}"),
        };
        assert!(bad(placement(1, [1e20, 0.0, 0.0], 0.0, 1.0)).contains("position"));
        assert!(bad(placement(1, [0.0, -1e7, 0.0], 0.0, 1.0)).contains("position"));
        assert!(bad(placement(1, [0.0; 3], 0.0, 1e-30)).contains("scale"));
        assert!(bad(placement(1, [0.0; 3], 0.0, 1e30)).contains("scale"));
        let turned = placement_matrix(&placement(1, [0.0; 3], 1e30, 1.0)).expect("an angle");
        assert!(turned.is_finite());
        let same = placement_matrix(&placement(1, [0.0; 3], 370.0, 1.0)).expect("an angle");
        let ten = placement_matrix(&placement(1, [0.0; 3], 10.0, 1.0)).expect("an angle");
        assert!(same.abs_diff_eq(ten, 1e-5), "whole turns are dropped");
        // A crowd laid out at the limits has a view that draws.
        let boxes = vec![unit_box(); 2];
        let far = [
            placement(
                1,
                [MAX_COORDINATE, MAX_COORDINATE, -MAX_COORDINATE],
                0.0,
                MAX_SCALE,
            ),
            placement(2, [-MAX_COORDINATE, 0.0, MAX_COORDINATE], 0.0, MIN_SCALE),
        ];
        let scene = layout(&boxes, None, &[1, 2], Some(&far), None, 16.0 / 9.0).expect("a scene");
        assert_eq!(scene.view.check(16.0 / 9.0), Ok(()));
    }

    /// A standing figure 1.8 tall, feet at y = 0, with a pack on its back, and its face near
    /// the top, at the front.
    fn figure() -> (Aabb, Aabb) {
        (
            Aabb {
                min: Vec3::new(-0.4, 0.0, -0.6),
                max: Vec3::new(0.4, 1.8, 0.25),
            },
            Aabb {
                min: Vec3::new(-0.1, 1.5, 0.0),
                max: Vec3::new(0.1, 1.75, 0.2),
            },
        )
    }

    /// The smallest and largest normalized device coordinates of `boxes` placed by `scene`.
    fn ndc_range(scene: &Scene, boxes: &[Aabb], aspect: f32) -> (Vec3, Vec3) {
        ndc(scene, boxes, aspect)
            .into_iter()
            .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), p| {
                (lo.min(p), hi.max(p))
            })
    }

    #[test]
    fn framing_bodies_is_the_default_view() {
        let (body, _) = figure();
        for (n, aspect) in [(1usize, 4.0 / 3.0), (5, 16.0 / 9.0), (9, 0.5)] {
            let boxes = vec![body; n];
            let ids: Vec<u64> = (0..n as u64).collect();
            let default = layout(&boxes, None, &ids, None, None, aspect).expect("a scene");
            let bodies = CameraSpec::framing(CameraFrame::Bodies);
            let framed = layout(&boxes, None, &ids, None, Some(&bodies), aspect).expect("a scene");
            assert_eq!(framed, default, "{n} heads at {aspect}");
        }
    }

    #[test]
    fn framing_faces_fits_every_placed_face_and_leaves_the_feet_out() {
        let (body, face) = figure();
        let faces = CameraSpec::framing(CameraFrame::Faces);
        let aspect = 4.0 / 3.0;
        // One figure: its face fills the image but for the margin; its feet are below it.
        let scene =
            layout(&[body], Some(&[face]), &[1], None, Some(&faces), aspect).expect("a scene");
        let (lo, hi) = ndc_range(&scene, &[face], aspect);
        assert!(
            lo.x >= -1.0 && lo.y >= -1.0 && hi.x <= 1.0 && hi.y <= 1.0,
            "{lo} {hi}"
        );
        assert!(
            (hi.y - lo.y).max(hi.x - lo.x) > 2.0 * 0.85,
            "the face fills the image: {lo} {hi}"
        );
        let feet = scene
            .view
            .view_projection(aspect)
            .project_point3(scene.transforms[0].transform_point3(Vec3::ZERO));
        assert!(feet.y < -1.0, "the feet are out of the picture: {feet}");
        // The far plane holds the whole figure behind the face (nothing is cut), the near
        // plane is in front of it.
        let forward = (scene.view.target - scene.view.eye).normalize();
        for c in corners(&body) {
            let d = (scene.transforms[0].transform_point3(c) - scene.view.eye).dot(forward);
            assert!(
                d > scene.view.near && d < scene.view.far,
                "{c} at {d} outside {:?}",
                scene.view
            );
        }
        // Looking at the face from the front, not at the figure's middle.
        let face_centre = scene.transforms[0].transform_point3((face.min + face.max) * 0.5);
        assert!(
            (scene.view.target - face_centre).length() < 1e-4,
            "{face_centre} {:?}",
            scene.view
        );
        assert!(
            (scene.view.target - scene.view.eye)
                .normalize()
                .dot(-Vec3::Z)
                > 0.9999
        );

        // A gridded crowd and a placed, turned and scaled one: every face inside, and drawn
        // larger than in the view of the bodies.
        let boxes = vec![body; 4];
        let face_boxes = vec![face; 4];
        let ids = [1, 2, 3, 4];
        let placements = [
            placement(1, [-3.0, 0.0, 0.0], 30.0, 1.0),
            placement(2, [2.0, 0.5, -4.0], -20.0, 2.0),
        ];
        for placed in [None, Some(&placements[..])] {
            let scene = layout(
                &boxes,
                Some(&face_boxes),
                &ids,
                placed,
                Some(&faces),
                aspect,
            )
            .expect("a scene");
            let (lo, hi) = ndc_range(&scene, &face_boxes, aspect);
            assert!(
                lo.x >= -1.0 && lo.y >= -1.0 && hi.x <= 1.0 && hi.y <= 1.0,
                "{placed:?}: {lo} {hi}"
            );
            // The front of the faces' box fits the image; faces placed further back look
            // smaller, so only the grid (every face at one depth) fills it.
            assert!(
                placed.is_some() || (hi.y - lo.y).max(hi.x - lo.x) > 2.0 * 0.85,
                "the faces fill the image: {lo} {hi}"
            );
            let bodies =
                layout(&boxes, Some(&face_boxes), &ids, placed, None, aspect).expect("a scene");
            let (blo, bhi) = ndc_range(&bodies, &face_boxes, aspect);
            assert!(
                (hi.y - lo.y) > 1.2 * (bhi.y - blo.y),
                "{placed:?}: faces {lo} {hi} against the default view's {blo} {bhi}"
            );
        }
        // Without face boxes (a caller that has none), the full boxes stand in.
        let stand_in = layout(&[body], None, &[1], None, Some(&faces), aspect).expect("a scene");
        let bodies = layout(&[body], None, &[1], None, None, aspect).expect("a scene");
        assert_eq!(stand_in, bodies);
    }

    #[test]
    fn a_framing_camera_keeps_its_field_of_view_and_planes_and_refuses_a_position() {
        let (body, face) = figure();
        let spec = CameraSpec {
            fov_y: 50.0,
            near: Some(0.01),
            far: Some(100.0),
            ..CameraSpec::framing(CameraFrame::Faces)
        };
        let scene = layout(&[body], Some(&[face]), &[1], None, Some(&spec), 1.0).expect("a scene");
        assert_eq!(
            (scene.view.fov_y_deg, scene.view.near, scene.view.far),
            (50.0, 0.01, 100.0)
        );
        let msg =
            |spec: CameraSpec| match layout(&[body], Some(&[face]), &[1], None, Some(&spec), 1.0) {
                Err(SceneError::Camera(m)) => m,
                other => panic!("expected a camera error for {spec:?}, got {other:?}"),
            };
        let framing = CameraSpec::framing(CameraFrame::Faces);
        let m = msg(CameraSpec {
            position: Some([0.0, 0.0, 5.0]),
            ..framing
        });
        assert!(
            m.contains("frame \"faces\"") && m.contains("position [0.0, 0.0, 5.0]"),
            "{m}"
        );
        let m = msg(CameraSpec {
            target: Some([0.0; 3]),
            ..CameraSpec::framing(CameraFrame::Bodies)
        });
        assert!(
            m.contains("bodies") && m.contains("target") && !m.contains("position ["),
            "{m}"
        );
        for fov in [0.0, 180.0, f32::NAN] {
            assert!(
                msg(CameraSpec {
                    fov_y: fov,
                    ..framing
                })
                .contains("fov_y")
            );
        }
        assert!(
            msg(CameraSpec {
                near: Some(2.0),
                far: Some(1.0),
                ..framing
            })
            .contains("near 2")
        );
        // Without a frame, position and target are required.
        let m = msg(CameraSpec {
            frame: None,
            ..framing
        });
        assert!(m.contains("position and target are required"), "{m}");
        let m = msg(CameraSpec {
            target: None,
            ..CameraSpec::looking([0.0, 0.0, 5.0], [0.0; 3])
        });
        assert!(m.contains("position and target are required"), "{m}");
    }
}
