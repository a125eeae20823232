//! A minimal glTF 2.0 document builder for tests.
//!
//! A [`Builder`] holds the glTF JSON as a `serde_json::Value` and one binary buffer. Helpers add
//! buffer views, accessors (f32, normalized or plain integers, indices, sparse), meshes with
//! morph targets, nodes, a scene and `weights` animations; [`Builder::to_glb`] and
//! [`Builder::to_gltf_data_uri`] serialise the result. Bad-input tests reach past the helpers
//! with [`Builder::json_mut`] (and the `*_mut` accessors) to set any field to anything, and with
//! [`glb_from_parts`] to assemble a GLB container from arbitrary chunks.
//!
//! Every index the helpers return is the index of the object they appended, so tests can refer
//! to it in later calls.

use base64::Engine as _;
use serde_json::{Value, json};

/// glTF component types (`accessor.componentType`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Component {
    /// BYTE (5120).
    I8,
    /// UNSIGNED_BYTE (5121).
    U8,
    /// SHORT (5122).
    I16,
    /// UNSIGNED_SHORT (5123).
    U16,
    /// UNSIGNED_INT (5125).
    U32,
    /// FLOAT (5126).
    F32,
}

impl Component {
    /// The GL enum glTF stores in `componentType`.
    pub fn code(self) -> u32 {
        match self {
            Component::I8 => 5120,
            Component::U8 => 5121,
            Component::I16 => 5122,
            Component::U16 => 5123,
            Component::U32 => 5125,
            Component::F32 => 5126,
        }
    }

    /// Bytes per component.
    pub fn size(self) -> usize {
        match self {
            Component::I8 | Component::U8 => 1,
            Component::I16 | Component::U16 => 2,
            Component::U32 | Component::F32 => 4,
        }
    }

    /// Little-endian bytes of an integer component. Values are truncated to the type, so the
    /// caller is responsible for passing values in range.
    fn int_bytes(self, v: i64, out: &mut Vec<u8>) {
        match self {
            Component::I8 | Component::U8 => out.push(v as u8),
            Component::I16 | Component::U16 => out.extend_from_slice(&(v as u16).to_le_bytes()),
            Component::U32 => out.extend_from_slice(&(v as u32).to_le_bytes()),
            Component::F32 => out.extend_from_slice(&(v as f32).to_le_bytes()),
        }
    }
}

/// Number of components of a glTF accessor type name (`"SCALAR"`, `"VEC3"`, ...).
fn components_of(ty: &str) -> usize {
    match ty {
        "SCALAR" => 1,
        "VEC2" => 2,
        "VEC3" => 3,
        "VEC4" | "MAT2" => 4,
        "MAT3" => 9,
        "MAT4" => 16,
        other => panic!("unknown accessor type {other:?}"),
    }
}

/// The glTF JSON of a document under construction and its single binary buffer.
pub struct Builder {
    json: Value,
    bin: Vec<u8>,
}

impl Default for Builder {
    fn default() -> Self {
        Self::new()
    }
}

impl Builder {
    /// An empty glTF 2.0 document (only `asset.version`).
    pub fn new() -> Self {
        Builder {
            json: json!({
                "asset": { "version": "2.0", "generator": "crowdmorph tests" },
                "bufferViews": [],
                "accessors": [],
                "meshes": [],
                "nodes": [],
                "scenes": [],
                "animations": [],
            }),
            bin: Vec::new(),
        }
    }

    /// The whole JSON document, for tests that need to set fields the helpers do not cover.
    /// `buffers` is filled in on output unless the test sets it here.
    pub fn json_mut(&mut self) -> &mut Value {
        &mut self.json
    }

    /// Accessor `i` as raw JSON.
    pub fn accessor_mut(&mut self, i: usize) -> &mut Value {
        &mut self.json["accessors"][i]
    }

    /// Buffer view `i` as raw JSON.
    pub fn buffer_view_mut(&mut self, i: usize) -> &mut Value {
        &mut self.json["bufferViews"][i]
    }

    /// Mesh `i` as raw JSON.
    pub fn mesh_mut(&mut self, i: usize) -> &mut Value {
        &mut self.json["meshes"][i]
    }

    /// The binary buffer as built so far.
    pub fn bin(&self) -> &[u8] {
        &self.bin
    }

    /// Mutable binary buffer, for tests that overwrite stored values after the fact.
    pub fn bin_mut(&mut self) -> &mut [u8] {
        &mut self.bin
    }

    /// Appends `value` to the top-level array `key` and returns its index.
    fn push(&mut self, key: &str, value: Value) -> usize {
        let array = self.json[key]
            .as_array_mut()
            .unwrap_or_else(|| panic!("{key} is not an array"));
        array.push(value);
        array.len() - 1
    }

    /// Appends `bytes` to the binary buffer at a 4-byte aligned offset and returns the offset.
    pub fn add_buffer_data(&mut self, bytes: &[u8]) -> usize {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        let offset = self.bin.len();
        self.bin.extend_from_slice(bytes);
        offset
    }

    /// Adds a buffer view over `[offset, offset + length)` of buffer 0.
    pub fn buffer_view(&mut self, offset: usize, length: usize, stride: Option<usize>) -> usize {
        let mut view = json!({ "buffer": 0, "byteOffset": offset, "byteLength": length });
        if let Some(s) = stride {
            view["byteStride"] = json!(s);
        }
        self.push("bufferViews", view)
    }

    /// Appends `bytes` to the buffer and adds a (tightly packed) view over them.
    pub fn data_view(&mut self, bytes: &[u8]) -> usize {
        let offset = self.add_buffer_data(bytes);
        self.buffer_view(offset, bytes.len(), None)
    }

    /// Adds an accessor from raw JSON and returns its index (the escape hatch).
    pub fn accessor_json(&mut self, accessor: Value) -> usize {
        self.push("accessors", accessor)
    }

    /// A FLOAT accessor of type `ty` over `values` (`values.len()` must be a multiple of the
    /// type's component count).
    pub fn accessor_f32(&mut self, values: &[f32], ty: &str) -> usize {
        let comps = components_of(ty);
        assert!(
            values.len().is_multiple_of(comps),
            "{} floats is not a whole number of {ty}",
            values.len()
        );
        let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        let view = self.data_view(&bytes);
        self.accessor_json(json!({
            "bufferView": view,
            "componentType": Component::F32.code(),
            "count": values.len() / comps,
            "type": ty,
        }))
    }

    /// A FLOAT SCALAR accessor (animation times, float weights).
    pub fn accessor_scalar(&mut self, values: &[f32]) -> usize {
        self.accessor_f32(values, "SCALAR")
    }

    /// A FLOAT VEC3 accessor with `min`/`max` (the spec requires them on POSITION). Bounds are
    /// taken over the finite components only, since JSON cannot hold NaN or infinity.
    pub fn accessor_vec3(&mut self, values: &[[f32; 3]]) -> usize {
        let flat: Vec<f32> = values.iter().flatten().copied().collect();
        let acc = self.accessor_f32(&flat, "VEC3");
        let (min, max) = bounds(values);
        self.json["accessors"][acc]["min"] = json!(min);
        self.json["accessors"][acc]["max"] = json!(max);
        acc
    }

    /// An integer accessor of type `ty`; `normalized` makes it a normalized integer accessor
    /// (KHR_mesh_quantization style) whose values decode to [0, 1] or [-1, 1].
    pub fn accessor_ints(
        &mut self,
        component: Component,
        values: &[i64],
        ty: &str,
        normalized: bool,
    ) -> usize {
        let comps = components_of(ty);
        assert!(values.len().is_multiple_of(comps));
        let mut bytes = Vec::with_capacity(values.len() * component.size());
        for &v in values {
            component.int_bytes(v, &mut bytes);
        }
        let view = self.data_view(&bytes);
        let mut acc = json!({
            "bufferView": view,
            "componentType": component.code(),
            "count": values.len() / comps,
            "type": ty,
        });
        if normalized {
            acc["normalized"] = json!(true);
        }
        self.accessor_json(acc)
    }

    /// An UNSIGNED_SHORT index accessor.
    pub fn indices_u16(&mut self, indices: &[u16]) -> usize {
        let v: Vec<i64> = indices.iter().map(|&i| i64::from(i)).collect();
        self.accessor_ints(Component::U16, &v, "SCALAR", false)
    }

    /// An UNSIGNED_INT index accessor.
    pub fn indices_u32(&mut self, indices: &[u32]) -> usize {
        let v: Vec<i64> = indices.iter().map(|&i| i64::from(i)).collect();
        self.accessor_ints(Component::U32, &v, "SCALAR", false)
    }

    /// A sparse FLOAT VEC3 accessor of `count` elements: zeros (no buffer view) with
    /// `values[k]` substituted at element `indices[k]` (UNSIGNED_INT indices).
    pub fn accessor_sparse_vec3(
        &mut self,
        count: usize,
        indices: &[u32],
        values: &[[f32; 3]],
    ) -> usize {
        assert_eq!(indices.len(), values.len());
        let ibytes: Vec<u8> = indices.iter().flat_map(|i| i.to_le_bytes()).collect();
        let vbytes: Vec<u8> = values
            .iter()
            .flatten()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let iview = self.data_view(&ibytes);
        let vview = self.data_view(&vbytes);
        let mut all = vec![[0.0; 3]; 1];
        all.extend_from_slice(values);
        let (min, max) = bounds(&all);
        self.accessor_json(json!({
            "componentType": Component::F32.code(),
            "count": count,
            "type": "VEC3",
            "min": min,
            "max": max,
            "sparse": {
                "count": indices.len(),
                "indices": { "bufferView": iview, "componentType": Component::U32.code() },
                "values": { "bufferView": vview },
            },
        }))
    }

    /// A TRIANGLES primitive (as JSON, for [`Builder::mesh`]) with f32 positions, optional
    /// UNSIGNED_INT indices and one POSITION morph target per entry of `targets`.
    pub fn primitive(
        &mut self,
        positions: &[[f32; 3]],
        indices: Option<&[u32]>,
        targets: &[Vec<[f32; 3]>],
    ) -> Value {
        let pos = self.accessor_vec3(positions);
        let mut prim = json!({ "attributes": { "POSITION": pos } });
        if let Some(idx) = indices {
            prim["indices"] = json!(self.indices_u32(idx));
        }
        if !targets.is_empty() {
            let t: Vec<Value> = targets
                .iter()
                .map(|d| json!({ "POSITION": self.accessor_vec3(d) }))
                .collect();
            prim["targets"] = json!(t);
        }
        prim
    }

    /// A mesh from primitives, with optional `extras.targetNames`.
    pub fn mesh(&mut self, primitives: Vec<Value>, names: Option<&[&str]>) -> usize {
        let mut mesh = json!({ "primitives": primitives });
        if let Some(n) = names {
            mesh["extras"] = json!({ "targetNames": n });
        }
        self.push("meshes", mesh)
    }

    /// A one-primitive mesh with position morph targets (see [`Builder::primitive`]).
    pub fn mesh_with_targets(
        &mut self,
        positions: &[[f32; 3]],
        indices: Option<&[u32]>,
        targets: &[Vec<[f32; 3]>],
        names: Option<&[&str]>,
    ) -> usize {
        let prim = self.primitive(positions, indices, targets);
        self.mesh(vec![prim], names)
    }

    /// Sets `mesh.weights`, the default weight of each target.
    pub fn set_mesh_weights(&mut self, mesh: usize, weights: &[f32]) {
        self.json["meshes"][mesh]["weights"] = json!(weights);
    }

    /// A node instancing `mesh` (or an empty node).
    pub fn node(&mut self, mesh: Option<usize>) -> usize {
        let node = match mesh {
            Some(m) => json!({ "mesh": m }),
            None => json!({}),
        };
        self.push("nodes", node)
    }

    /// Sets `node.weights`, the node's own default weights (they win over `mesh.weights`).
    pub fn set_node_weights(&mut self, node: usize, weights: &[f32]) {
        self.json["nodes"][node]["weights"] = json!(weights);
    }

    /// A scene of root `nodes`; the first scene added becomes the default scene.
    pub fn scene(&mut self, nodes: &[usize]) -> usize {
        let s = self.push("scenes", json!({ "nodes": nodes }));
        if self.json.get("scene").is_none() {
            self.json["scene"] = json!(s);
        }
        s
    }

    /// An animation with one `weights` channel on `node`, from existing input (times) and
    /// output (values) accessors. `interpolation` is `"STEP"`, `"LINEAR"` or `"CUBICSPLINE"`.
    pub fn animation_weights_accessors(
        &mut self,
        name: &str,
        node: usize,
        input: usize,
        output: usize,
        interpolation: &str,
    ) -> usize {
        self.push(
            "animations",
            json!({
                "name": name,
                "samplers": [{ "input": input, "output": output, "interpolation": interpolation }],
                "channels": [{ "sampler": 0, "target": { "node": node, "path": "weights" } }],
            }),
        )
    }

    /// An animation with one `weights` channel on `node` and f32 key times and values. Values
    /// are key-major: per key one value per target (for CUBICSPLINE: in-tangents, values,
    /// out-tangents, each one per target).
    pub fn animation_weights(
        &mut self,
        name: &str,
        node: usize,
        times: &[f32],
        values: &[f32],
        interpolation: &str,
    ) -> usize {
        let input = self.accessor_scalar(times);
        let output = self.accessor_scalar(values);
        self.animation_weights_accessors(name, node, input, output, interpolation)
    }

    /// An animation with one `weights` channel per entry of `channels` — `(node, times,
    /// values, interpolation)`, each with its own sampler and f32 accessors — so that one clip
    /// drives several nodes, each with its own curve.
    pub fn animation_weights_nodes(
        &mut self,
        name: &str,
        channels: &[(usize, &[f32], &[f32], &str)],
    ) -> usize {
        let mut samplers = Vec::new();
        let mut chans = Vec::new();
        for (i, &(node, times, values, interpolation)) in channels.iter().enumerate() {
            let input = self.accessor_scalar(times);
            let output = self.accessor_scalar(values);
            samplers
                .push(json!({ "input": input, "output": output, "interpolation": interpolation }));
            chans.push(json!({ "sampler": i, "target": { "node": node, "path": "weights" } }));
        }
        self.push(
            "animations",
            json!({ "name": name, "samplers": samplers, "channels": chans }),
        )
    }

    /// An animation like [`Builder::animation_weights`] whose output is stored as normalized
    /// integers of `component` (raw integer codes in `values`).
    pub fn animation_weights_normalized(
        &mut self,
        name: &str,
        node: usize,
        times: &[f32],
        component: Component,
        values: &[i64],
        interpolation: &str,
    ) -> usize {
        let input = self.accessor_scalar(times);
        let output = self.accessor_ints(component, values, "SCALAR", true);
        self.animation_weights_accessors(name, node, input, output, interpolation)
    }

    /// The JSON document with `buffers` filled in: one buffer of the binary data, with `uri`
    /// when given (none for GLB). A `buffers` array set through [`Builder::json_mut`] is kept.
    pub fn document(&self, uri: Option<String>) -> Value {
        let mut doc = self.json.clone();
        // Empty arrays are legal in JSON but glTF requires arrays to have at least one
        // element, so drop the ones nothing was added to.
        if let Some(map) = doc.as_object_mut() {
            map.retain(|_, v| v.as_array().is_none_or(|a| !a.is_empty()));
        }
        if doc.get("buffers").is_none() && !self.bin.is_empty() {
            let mut buffer = json!({ "byteLength": self.bin.len() });
            if let Some(u) = uri {
                buffer["uri"] = json!(u);
            }
            doc["buffers"] = json!([buffer]);
        }
        doc
    }

    /// The document as a binary GLB (JSON chunk + BIN chunk).
    pub fn to_glb(&self) -> Vec<u8> {
        let json = serde_json::to_vec(&self.document(None)).expect("JSON serialises");
        glb_from_parts(&json, (!self.bin.is_empty()).then_some(&self.bin[..]))
    }

    /// The document as `.gltf` JSON whose buffer is a base64 data URI.
    pub fn to_gltf_data_uri(&self) -> Vec<u8> {
        let data = base64::engine::general_purpose::STANDARD.encode(&self.bin);
        let uri = format!("data:application/octet-stream;base64,{data}");
        serde_json::to_vec(&self.document(Some(uri))).expect("JSON serialises")
    }

    /// The document as `.gltf` JSON whose buffer refers to the file `uri`.
    pub fn to_gltf_external(&self, uri: &str) -> Vec<u8> {
        serde_json::to_vec(&self.document(Some(uri.to_string()))).expect("JSON serialises")
    }
}

/// Component-wise bounds over the finite components of `values` (0 when none is finite).
fn bounds(values: &[[f32; 3]]) -> ([f32; 3], [f32; 3]) {
    let mut min = [f32::INFINITY; 3];
    let mut max = [f32::NEG_INFINITY; 3];
    for v in values {
        for c in 0..3 {
            if v[c].is_finite() {
                min[c] = min[c].min(v[c]);
                max[c] = max[c].max(v[c]);
            }
        }
    }
    for c in 0..3 {
        if min[c] > max[c] {
            min[c] = 0.0;
            max[c] = 0.0;
        }
    }
    (min, max)
}

/// Assembles a GLB container: 12-byte header, a JSON chunk padded with spaces and, when given,
/// a BIN chunk padded with zeros, as glTF 2.0 §4.4 lays them out.
pub fn glb_from_parts(json: &[u8], bin: Option<&[u8]>) -> Vec<u8> {
    let pad = |n: usize| (4 - n % 4) % 4;
    let json_len = json.len() + pad(json.len());
    let bin_len = bin.map(|b| b.len() + pad(b.len()));
    let total = 12 + 8 + json_len + bin_len.map_or(0, |l| 8 + l);
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(json_len as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(json);
    out.resize(out.len() + pad(json.len()), b' ');
    if let (Some(b), Some(len)) = (bin, bin_len) {
        out.extend_from_slice(&(len as u32).to_le_bytes());
        out.extend_from_slice(b"BIN\0");
        out.extend_from_slice(b);
        out.resize(out.len() + pad(b.len()), 0);
    }
    debug_assert_eq!(out.len(), total);
    out
}

/// A triangle in the z = 0 plane: the smallest useful rig.
pub const TRIANGLE: [[f32; 3]; 3] = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];

/// Two position targets for [`TRIANGLE`]: `a` lifts vertex 1 along +Z, `b` lifts vertex 2.
pub fn triangle_targets() -> Vec<Vec<[f32; 3]>> {
    vec![
        vec![[0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]],
        vec![[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 2.0]],
    ]
}

/// A builder holding [`TRIANGLE`] with targets `a` and `b` (see [`triangle_targets`]) as mesh 0,
/// instanced by node 0 in the default scene, ready for animations on node 0.
pub fn triangle_rig() -> Builder {
    let mut b = Builder::new();
    let mesh = b.mesh_with_targets(
        &TRIANGLE,
        Some(&[0, 1, 2]),
        &triangle_targets(),
        Some(&["a", "b"]),
    );
    let node = b.node(Some(mesh));
    b.scene(&[node]);
    b
}

/// Node indices of [`skinned_triangle_rig`].
pub struct SkinnedTriangle {
    /// The mesh node (it carries the skin).
    pub mesh_node: usize,
    /// The root joint.
    pub root: usize,
    /// The child joint, rotated by the `open` animation.
    pub jaw: usize,
    /// The JOINTS_0 accessor.
    pub joints: usize,
    /// The WEIGHTS_0 accessor.
    pub weights: usize,
    /// The inverse bind matrices accessor.
    pub ibm: usize,
}

/// [`TRIANGLE`] with targets `a` and `b`, skinned to two joints: `Root` at the origin and its
/// child `Jaw` at (0, 1, 0) (vertex 0 follows `Root`, vertex 1 `Jaw`, vertex 2 both half);
/// animation `open` turns `Jaw` about +X by up to 0.8 rad over one second (LINEAR) and
/// moves `Root` by +Z (STEP), `wag` turns `Jaw` about +Z (CUBICSPLINE). Tests edit the
/// returned accessors and nodes to make it hostile.
pub fn skinned_triangle_rig() -> (Builder, SkinnedTriangle) {
    let mut b = Builder::new();
    let prim = b.primitive(&TRIANGLE, Some(&[0, 1, 2]), &triangle_targets());
    let joints = b.accessor_ints(
        Component::U8,
        &[0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0],
        "VEC4",
        false,
    );
    let weights = b.accessor_f32(
        &[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.5, 0.5, 0.0, 0.0],
        "VEC4",
    );
    let mut prim = prim;
    prim["attributes"]["JOINTS_0"] = json!(joints);
    prim["attributes"]["WEIGHTS_0"] = json!(weights);
    let mesh = b.mesh(vec![prim], Some(&["a", "b"]));
    let mesh_node = b.node(Some(mesh));
    let root = b.node(None);
    let jaw = b.node(None);
    b.json_mut()["nodes"][root]["name"] = json!("Root");
    b.json_mut()["nodes"][root]["children"] = json!([jaw]);
    b.json_mut()["nodes"][jaw]["name"] = json!("Jaw");
    b.json_mut()["nodes"][jaw]["translation"] = json!([0.0, 1.0, 0.0]);
    // Inverse binds: Root is the identity, Jaw's bind is at (0, 1, 0).
    #[rustfmt::skip]
    let ibm_values: [f32; 32] = [
        1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0,
        1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, -1.0, 0.0, 1.0,
    ];
    let ibm = b.accessor_f32(&ibm_values, "MAT4");
    b.json_mut()["skins"] = json!([{ "joints": [root, jaw], "inverseBindMatrices": ibm }]);
    b.json_mut()["nodes"][mesh_node]["skin"] = json!(0);
    b.scene(&[mesh_node, root]);
    let (s, c) = (0.4f32.sin(), 0.4f32.cos());
    let times = b.accessor_scalar(&[0.0, 1.0]);
    let rot = b.accessor_f32(&[0.0, 0.0, 0.0, 1.0, s, 0.0, 0.0, c], "VEC4");
    let step_times = b.accessor_scalar(&[0.0, 0.5]);
    let lift = b.accessor_f32(&[0.0, 0.0, 0.0, 0.0, 0.0, 0.25], "VEC3");
    // CUBICSPLINE: (in-tangent, value, out-tangent) per key.
    let (s2, c2) = (0.3f32.sin(), 0.3f32.cos());
    #[rustfmt::skip]
    let wag = b.accessor_f32(&[
        0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.5, 0.0,
        0.0, 0.0, -0.5, 0.0, 0.0, 0.0, s2, c2, 0.0, 0.0, 0.0, 0.0,
    ], "VEC4");
    let anims = json!([
        {
            "name": "open",
            "samplers": [
                { "input": times, "output": rot, "interpolation": "LINEAR" },
                { "input": step_times, "output": lift, "interpolation": "STEP" },
            ],
            "channels": [
                { "sampler": 0, "target": { "node": jaw, "path": "rotation" } },
                { "sampler": 1, "target": { "node": root, "path": "translation" } },
            ],
        },
        {
            "name": "wag",
            "samplers": [{ "input": times, "output": wag, "interpolation": "CUBICSPLINE" }],
            "channels": [{ "sampler": 0, "target": { "node": jaw, "path": "rotation" } }],
        },
    ]);
    b.json_mut()["animations"] = anims;
    (
        b,
        SkinnedTriangle {
            mesh_node,
            root,
            jaw,
            joints,
            weights,
            ibm,
        },
    )
}
