//! Shared test helpers: where the real rigs live, an independent glTF reader, and the f64
//! dense oracle every engine is compared against.
//!
//! The reference reader deliberately shares no code with `crowdmorph::import`: it parses the
//! JSON with `serde_json`, decodes accessors byte by byte in f64, and composes node transforms
//! in f64, so that "loaded data equals the file" is checked against a second implementation.

#![allow(dead_code)]

pub mod browser;
pub mod builder;
pub mod image;
pub mod pack;
pub mod skin;
pub mod wrinkle;

use std::path::{Path, PathBuf};

use base64::Engine as _;
use glam::{DMat3, DMat4, DQuat, DVec3};
use serde_json::Value;

/// The shared test rigs: `$CROWDMORPH_TEST_DATA`, else `../shared/data` next to the checkout.
pub fn data_dir() -> PathBuf {
    match std::env::var_os("CROWDMORPH_TEST_DATA") {
        Some(dir) => PathBuf::from(dir),
        None => Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data"),
    }
}

/// Every real rig file. Tests that call this carry
/// `#[cfg_attr(not(crowdmorph_test_data), ignore = "...")]`: `build.rs` sets that cfg when it
/// finds the data folder, so here a missing folder is a failure, not a reason to skip.
pub fn rig_files() -> Vec<PathBuf> {
    let dir = data_dir();
    assert!(
        dir.is_dir(),
        "{} not found: the shared test rigs are absent although this test needs them \
         (it runs when build.rs found them, or with --ignored); set CROWDMORPH_TEST_DATA",
        dir.display()
    );
    let mut files = vec![dir.join("ict-facekit/ict_facekit_53.glb")];
    for name in [
        "AnimatedMorphCube",
        "AnimatedMorphSphere",
        "MorphPrimitivesTest",
        "MorphStressTest",
        "SimpleMorph",
    ] {
        files.push(dir.join(format!("khronos/{name}/glTF/{name}.gltf")));
    }
    files
}

/// Declares a test that needs a GPU adapter: `gpu_test!(#[test] fn name() { ... });` (or
/// `#[tokio::test(...)] async fn`). Where `build.rs` found no Vulkan driver
/// (`crowdmorph_gpu_driver` unset) the test is listed as ignored with the line that installs
/// one; where it found one, the test runs and an adapter that does not open fails it. The
/// parentheses keep rustfmt formatting the test inside.
macro_rules! gpu_test {
    (#[$test:meta] $($item:tt)*) => {
        #[$test]
        #[cfg_attr(
            not(crowdmorph_gpu_driver),
            ignore = "needs a Vulkan adapter: apt-get install mesa-vulkan-drivers"
        )]
        $($item)*
    };
}
pub(crate) use gpu_test;

/// Opens a GPU context on any adapter, software ones (lavapipe) included. Tests that call this
/// are declared with [`gpu_test!`]: `build.rs` found a Vulkan driver, so an adapter that cannot
/// be opened is a broken GPU, and the test fails.
pub fn open_gpu(
    options: crowdmorph::engine::gpu::GpuOptions,
) -> crowdmorph::engine::gpu::GpuContext {
    match crowdmorph::engine::gpu::GpuContext::open(true, options) {
        Ok(ctx) => {
            eprintln!(
                "GPU tests run on {} ({:?}, {:?})",
                ctx.adapter().name,
                ctx.adapter().backend,
                ctx.adapter().device_type
            );
            ctx
        }
        Err(e) => panic!(
            "no GPU adapter ({e}), although a Vulkan driver is installed (or the test was run \
             with --ignored): a present but broken GPU is a failure"
        ),
    }
}

/// Deterministic numbers for test workloads (the library's SplitMix64).
pub use crowdmorph::rng::SplitMix64 as Rng;

/// A glTF document read independently of the library.
pub struct RefDoc {
    pub json: Value,
    pub buffers: Vec<Vec<u8>>,
}

/// One primitive instance of the default scene, decoded in f64 in its mesh's local space.
pub struct RefPrim {
    pub node: usize,
    pub mesh: usize,
    pub world: DMat4,
    pub positions: Vec<DVec3>,
    pub normals: Option<Vec<DVec3>>,
    /// xyz of the base tangents, when present.
    pub tangents: Option<Vec<DVec3>>,
    /// Triangle-list indices (the test files are all TRIANGLES).
    pub indices: Vec<u32>,
    pub targets: Vec<RefTarget>,
    /// Names of the mesh's targets (`extras.targetNames` or `target_<i>`).
    pub target_names: Vec<String>,
    /// The node's weights when no animation drives it (glTF 2.0 §3.7.2.1): `node.weights`,
    /// else `mesh.weights`, else zeros.
    pub default_weights: Vec<f64>,
}

/// Dense deltas of one morph target of a primitive.
pub struct RefTarget {
    pub positions: Vec<DVec3>,
    pub normals: Option<Vec<DVec3>>,
    pub tangents: Option<Vec<DVec3>>,
}

/// A `weights` animation channel.
pub struct RefChannel {
    pub node: usize,
    pub times: Vec<f64>,
    pub values: Vec<f64>,
    pub interpolation: String,
}

fn u(v: &Value) -> usize {
    v.as_u64().expect("non-negative integer") as usize
}

/// An accessor's values, decoded per the spec, and its component count.
pub type Accessor = (Vec<f64>, usize);

impl RefDoc {
    pub fn load(path: &Path) -> RefDoc {
        let bytes = std::fs::read(path).expect("read rig file");
        Self::from_bytes(&bytes, path.parent().unwrap_or(Path::new(".")))
    }

    /// A document from the bytes of a `.glb` or `.gltf` file; external buffers resolve in `dir`.
    pub fn from_bytes(bytes: &[u8], dir: &Path) -> RefDoc {
        let (json, bin): (Value, Option<Vec<u8>>) = if bytes.starts_with(b"glTF") {
            let jl = u32::from_le_bytes(bytes[12..16].try_into().unwrap()) as usize;
            let json = serde_json::from_slice(&bytes[20..20 + jl]).expect("GLB JSON");
            let at = 20 + jl;
            let bin = if at + 8 <= bytes.len() {
                let bl = u32::from_le_bytes(bytes[at..at + 4].try_into().unwrap()) as usize;
                Some(bytes[at + 8..at + 8 + bl].to_vec())
            } else {
                None
            };
            (json, bin)
        } else {
            (serde_json::from_slice(bytes).expect("glTF JSON"), None)
        };
        let mut buffers = Vec::new();
        for b in json["buffers"].as_array().into_iter().flatten() {
            let data = match b["uri"].as_str() {
                None => bin.clone().expect("GLB BIN chunk"),
                Some(uri) if uri.starts_with("data:") => {
                    let b64 = &uri[uri.find(',').expect("data URI comma") + 1..];
                    base64::engine::general_purpose::STANDARD
                        .decode(b64)
                        .expect("base64")
                }
                Some(uri) => std::fs::read(dir.join(uri)).expect("external buffer"),
            };
            buffers.push(data);
        }
        RefDoc { json, buffers }
    }

    /// Decodes accessor `i` to f64: `count × components`, normalized integers per the spec,
    /// sparse substitution applied.
    pub fn accessor(&self, i: usize) -> (Vec<f64>, usize) {
        let a = &self.json["accessors"][i];
        let comps = match a["type"].as_str().expect("accessor type") {
            "SCALAR" => 1,
            "VEC2" => 2,
            "VEC3" => 3,
            "VEC4" => 4,
            // Float MAT4 only (inverse bind matrices): no column padding.
            "MAT4" => 16,
            t => panic!("unexpected accessor type {t}"),
        };
        let ct = u(&a["componentType"]);
        let norm = a["normalized"].as_bool().unwrap_or(false);
        let csize = match ct {
            5120 | 5121 => 1,
            5122 | 5123 => 2,
            _ => 4,
        };
        let read = |b: &[u8]| -> f64 {
            match ct {
                5126 => f32::from_le_bytes(b[..4].try_into().unwrap()) as f64,
                5125 => u32::from_le_bytes(b[..4].try_into().unwrap()) as f64,
                5120 => {
                    let c = b[0] as i8 as f64;
                    if norm { (c / 127.0).max(-1.0) } else { c }
                }
                5121 => {
                    let c = b[0] as f64;
                    if norm { c / 255.0 } else { c }
                }
                5122 => {
                    let c = i16::from_le_bytes([b[0], b[1]]) as f64;
                    if norm { (c / 32767.0).max(-1.0) } else { c }
                }
                5123 => {
                    let c = u16::from_le_bytes([b[0], b[1]]) as f64;
                    if norm { c / 65535.0 } else { c }
                }
                _ => panic!("component type {ct}"),
            }
        };
        let count = u(&a["count"]);
        let mut out = vec![0.0; count * comps];
        if let Some(v) = a.get("bufferView") {
            let view = &self.json["bufferViews"][u(v)];
            let buf = &self.buffers[u(&view["buffer"])];
            let start = view["byteOffset"].as_u64().unwrap_or(0) as usize
                + a["byteOffset"].as_u64().unwrap_or(0) as usize;
            let stride = view["byteStride"]
                .as_u64()
                .map_or(comps * csize, |s| s as usize);
            for e in 0..count {
                for c in 0..comps {
                    out[e * comps + c] = read(&buf[start + e * stride + c * csize..]);
                }
            }
        }
        if let Some(sp) = a.get("sparse") {
            let n = u(&sp["count"]);
            let iv = &self.json["bufferViews"][u(&sp["indices"]["bufferView"])];
            let ibuf = &self.buffers[u(&iv["buffer"])];
            let istart = iv["byteOffset"].as_u64().unwrap_or(0) as usize
                + sp["indices"]["byteOffset"].as_u64().unwrap_or(0) as usize;
            let ict = u(&sp["indices"]["componentType"]);
            let vv = &self.json["bufferViews"][u(&sp["values"]["bufferView"])];
            let vbuf = &self.buffers[u(&vv["buffer"])];
            let vstart = vv["byteOffset"].as_u64().unwrap_or(0) as usize
                + sp["values"]["byteOffset"].as_u64().unwrap_or(0) as usize;
            for k in 0..n {
                let idx = match ict {
                    5121 => ibuf[istart + k] as usize,
                    5123 => u16::from_le_bytes([ibuf[istart + 2 * k], ibuf[istart + 2 * k + 1]])
                        as usize,
                    _ => u32::from_le_bytes(
                        ibuf[istart + 4 * k..istart + 4 * k + 4].try_into().unwrap(),
                    ) as usize,
                };
                for c in 0..comps {
                    out[idx * comps + c] = read(&vbuf[vstart + (k * comps + c) * csize..]);
                }
            }
        }
        (out, comps)
    }

    fn vec3s(&self, i: usize) -> Vec<DVec3> {
        let (v, c) = self.accessor(i);
        assert_eq!(c, 3);
        v.chunks_exact(3)
            .map(|p| DVec3::new(p[0], p[1], p[2]))
            .collect()
    }

    pub fn local_matrix(node: &Value) -> DMat4 {
        if let Some(m) = node["matrix"].as_array() {
            let m: Vec<f64> = m.iter().map(|x| x.as_f64().unwrap()).collect();
            return DMat4::from_cols_slice(&m);
        }
        let get = |k: &str, d: &[f64]| -> Vec<f64> {
            node[k].as_array().map_or(d.to_vec(), |a| {
                a.iter().map(|x| x.as_f64().unwrap()).collect()
            })
        };
        let t = get("translation", &[0.0, 0.0, 0.0]);
        let r = get("rotation", &[0.0, 0.0, 0.0, 1.0]);
        let s = get("scale", &[1.0, 1.0, 1.0]);
        DMat4::from_scale_rotation_translation(
            DVec3::new(s[0], s[1], s[2]),
            DQuat::from_xyzw(r[0], r[1], r[2], r[3]).normalize(),
            DVec3::new(t[0], t[1], t[2]),
        )
    }

    /// Each scene primitive's attribute `name` as the file has it (values decoded per the
    /// spec, and the component count), in [`RefDoc::scene_primitives`]' order; `None` for a
    /// primitive without. Also each primitive's material index.
    pub fn scene_attribute(&self, name: &str) -> Vec<(Option<Accessor>, Option<u64>)> {
        let mut out = Vec::new();
        let mut at = None;
        let mut k = 0;
        for p in self.scene_primitives() {
            // Consecutive primitives of one node's mesh are its primitives in order.
            k = if at == Some((p.node, p.mesh)) {
                k + 1
            } else {
                0
            };
            at = Some((p.node, p.mesh));
            let prim = &self.json["meshes"][p.mesh]["primitives"][k];
            let values = prim["attributes"][name]
                .as_u64()
                .map(|a| self.accessor(a as usize));
            out.push((values, prim["material"].as_u64()));
        }
        out
    }

    /// Primitive instances of the default scene, depth-first in child order.
    pub fn scene_primitives(&self) -> Vec<RefPrim> {
        let j = &self.json;
        let scene = j["scene"].as_u64().unwrap_or(0) as usize;
        let mut stack: Vec<(usize, DMat4)> = j["scenes"][scene]["nodes"]
            .as_array()
            .expect("scene nodes")
            .iter()
            .rev()
            .map(|n| (u(n), DMat4::IDENTITY))
            .collect();
        let mut out = Vec::new();
        while let Some((n, parent)) = stack.pop() {
            let node = &j["nodes"][n];
            let world = parent * Self::local_matrix(node);
            if let Some(m) = node.get("mesh") {
                let mesh = &j["meshes"][u(m)];
                let names: Option<Vec<String>> = mesh["extras"]["targetNames"]
                    .as_array()
                    .map(|a| a.iter().map(|s| s.as_str().unwrap().to_string()).collect());
                for p in mesh["primitives"].as_array().unwrap() {
                    let attrs = &p["attributes"];
                    let positions = self.vec3s(u(&attrs["POSITION"]));
                    let normals = attrs.get("NORMAL").map(|a| self.vec3s(u(a)));
                    let tangents = attrs.get("TANGENT").map(|a| {
                        let (t, c) = self.accessor(u(a));
                        assert_eq!(c, 4);
                        t.chunks_exact(4)
                            .map(|x| DVec3::new(x[0], x[1], x[2]))
                            .collect()
                    });
                    let indices = match p.get("indices") {
                        Some(i) => self.accessor(u(i)).0.iter().map(|&x| x as u32).collect(),
                        None => (0..positions.len() as u32).collect(),
                    };
                    let targets: Vec<RefTarget> = p["targets"]
                        .as_array()
                        .into_iter()
                        .flatten()
                        .map(|t| RefTarget {
                            positions: t
                                .get("POSITION")
                                .map_or(vec![DVec3::ZERO; positions.len()], |a| self.vec3s(u(a))),
                            normals: t.get("NORMAL").map(|a| self.vec3s(u(a))),
                            tangents: t.get("TANGENT").map(|a| self.vec3s(u(a))),
                        })
                        .collect();
                    let target_names = names
                        .clone()
                        .filter(|n| n.len() == targets.len())
                        .unwrap_or_else(|| {
                            (0..targets.len()).map(|i| format!("target_{i}")).collect()
                        });
                    let weights_of = |v: &Value| -> Option<Vec<f64>> {
                        v["weights"]
                            .as_array()
                            .map(|a| a.iter().map(|x| x.as_f64().unwrap()).collect::<Vec<f64>>())
                            .filter(|w| w.len() == targets.len())
                    };
                    let default_weights = weights_of(node)
                        .or_else(|| weights_of(mesh))
                        .unwrap_or_else(|| vec![0.0; targets.len()]);
                    out.push(RefPrim {
                        node: n,
                        mesh: u(m),
                        world,
                        positions,
                        normals,
                        tangents,
                        indices,
                        targets,
                        target_names,
                        default_weights,
                    });
                }
            }
            for c in node["children"].as_array().into_iter().flatten().rev() {
                stack.push((u(c), world));
            }
        }
        out
    }

    /// `(name, channels)` of every animation that has `weights` channels.
    pub fn weight_animations(&self) -> Vec<(String, Vec<RefChannel>)> {
        let mut out = Vec::new();
        for (i, a) in self.json["animations"]
            .as_array()
            .into_iter()
            .flatten()
            .enumerate()
        {
            let mut chans = Vec::new();
            for c in a["channels"].as_array().unwrap() {
                if c["target"]["path"] != "weights" {
                    continue;
                }
                let s = &a["samplers"][u(&c["sampler"])];
                chans.push(RefChannel {
                    node: u(&c["target"]["node"]),
                    times: self.accessor(u(&s["input"])).0,
                    values: self.accessor(u(&s["output"])).0,
                    interpolation: s["interpolation"].as_str().unwrap_or("LINEAR").to_string(),
                });
            }
            if !chans.is_empty() {
                let name = a["name"]
                    .as_str()
                    .filter(|n| !n.is_empty())
                    .map_or(format!("anim{i}"), str::to_string);
                out.push((name, chans));
            }
        }
        out
    }
}

impl RefChannel {
    /// Samples the channel's `width` weights at `t` (glTF 2.0 Appendix C), in f64.
    pub fn sample(&self, t: f64, width: usize) -> Vec<f64> {
        let n = self.times.len();
        let cubic = self.interpolation == "CUBICSPLINE";
        let val = |k: usize, j: usize| {
            if cubic {
                self.values[(3 * k + 1) * width + j]
            } else {
                self.values[k * width + j]
            }
        };
        if t <= self.times[0] {
            return (0..width).map(|j| val(0, j)).collect();
        }
        if t >= self.times[n - 1] {
            return (0..width).map(|j| val(n - 1, j)).collect();
        }
        let k = self.times.iter().rposition(|&x| x <= t).unwrap();
        let (t0, t1) = (self.times[k], self.times[k + 1]);
        let s = (t - t0) / (t1 - t0);
        (0..width)
            .map(|j| match self.interpolation.as_str() {
                "STEP" => val(k, j),
                "CUBICSPLINE" => {
                    let td = t1 - t0;
                    let m0 = td * self.values[(3 * k + 2) * width + j];
                    let m1 = td * self.values[(3 * (k + 1)) * width + j];
                    let (s2, s3) = (s * s, s * s * s);
                    (2.0 * s3 - 3.0 * s2 + 1.0) * val(k, j)
                        + (s3 - 2.0 * s2 + s) * m0
                        + (-2.0 * s3 + 3.0 * s2) * val(k + 1, j)
                        + (s3 - s2) * m1
                }
                _ => val(k, j) + (val(k + 1, j) - val(k, j)) * s,
            })
            .collect()
    }
}

/// Normal matrix of a world transform (inverse transpose of its linear part).
pub fn normal_matrix(world: DMat4) -> DMat3 {
    DMat3::from_mat4(world).inverse().transpose()
}

/// Area-weighted vertex normals in f64 (+Z where undefined).
pub fn ref_vertex_normals(p: &[DVec3], indices: &[u32]) -> Vec<DVec3> {
    let mut acc = vec![DVec3::ZERO; p.len()];
    for t in indices.chunks_exact(3) {
        let [a, b, c] = [t[0] as usize, t[1] as usize, t[2] as usize];
        let n = (p[b] - p[a]).cross(p[c] - p[a]);
        acc[a] += n;
        acc[b] += n;
        acc[c] += n;
    }
    acc.into_iter()
        .map(|n| n.try_normalize().unwrap_or(DVec3::Z))
        .collect()
}

/// The f64 dense evaluation of one primitive instance: world positions and unit normals for
/// per-target weights `w` (indexed like `prim.targets`). Normals blend normal deltas when the
/// primitive's targets have them, are recomputed from the blended positions when it has
/// targets without them, and are the neutral normals otherwise.
pub fn ref_eval(prim: &RefPrim, w: &[f64]) -> (Vec<DVec3>, Vec<DVec3>) {
    let n = prim.positions.len();
    let mut p = prim.positions.clone();
    for (t, &wk) in prim.targets.iter().zip(w) {
        for (pv, d) in p.iter_mut().zip(&t.positions) {
            *pv += wk * *d;
        }
    }
    let world: Vec<DVec3> = p.iter().map(|&x| prim.world.transform_point3(x)).collect();
    let nm = normal_matrix(prim.world);
    let flip = DMat3::from_mat4(prim.world).determinant() < 0.0;
    let mut idx = prim.indices.clone();
    if flip {
        for t in idx.chunks_exact_mut(3) {
            t.swap(1, 2);
        }
    }
    let has_normal_deltas = prim.targets.iter().any(|t| t.normals.is_some());
    let normals = match (&prim.normals, has_normal_deltas, prim.targets.is_empty()) {
        (Some(base), true, _) => {
            let mut nn = base.clone();
            for (t, &wk) in prim.targets.iter().zip(w) {
                if let Some(d) = &t.normals {
                    for v in 0..n {
                        nn[v] += wk * d[v];
                    }
                }
            }
            nn.iter().map(|&x| (nm * x).normalize_or_zero()).collect()
        }
        (Some(base), false, true) => base.iter().map(|&x| (nm * x).normalize_or_zero()).collect(),
        (None, _, true) => ref_vertex_normals(&world, &idx),
        _ => ref_vertex_normals(&world, &idx),
    };
    (world, normals)
}

/// Largest absolute component difference between an f32 buffer and f64 reference vectors.
pub fn max_abs_diff(got: &[f32], want: &[DVec3]) -> f64 {
    assert_eq!(got.len(), want.len() * 3, "buffer length");
    got.chunks_exact(3)
        .zip(want)
        .map(|(g, w)| {
            (g[0] as f64 - w.x)
                .abs()
                .max((g[1] as f64 - w.y).abs())
                .max((g[2] as f64 - w.z).abs())
        })
        .fold(0.0, f64::max)
}

/// The f64 dense evaluation of a [`crowdmorph::rig::Rig`] from its own arrays, for rigs that
/// have no file (the embedded head, synthetic rigs): positions and unit normals of all
/// primitives concatenated, for weights indexed by target id.
pub fn rig_oracle(rig: &crowdmorph::rig::Rig, w: &[f64]) -> (Vec<DVec3>, Vec<DVec3>) {
    let mut pos_out = Vec::new();
    let mut nrm_out = Vec::new();
    for p in rig.primitives.iter() {
        let mut pos: Vec<DVec3> = p.positions.iter().map(|v| v.as_dvec3()).collect();
        let mut nrm: Vec<DVec3> = p.normals.iter().map(|v| v.as_dvec3()).collect();
        for t in &p.targets {
            let wk = w[t.target as usize];
            for (i, &v) in t.vertices.iter().enumerate() {
                pos[v as usize] += wk * t.positions[i].as_dvec3();
                if let Some(d) = &t.normals {
                    nrm[v as usize] += wk * d[i].as_dvec3();
                }
            }
        }
        let nrm = if p.has_normal_deltas() || p.targets.is_empty() {
            nrm.into_iter().map(|n| n.normalize_or_zero()).collect()
        } else {
            ref_vertex_normals(&pos, &p.indices)
        };
        pos_out.extend(pos);
        nrm_out.extend(nrm);
    }
    (pos_out, nrm_out)
}

/// Weights a job actually applies: zero past its LOD's first `shapes` targets of the order
/// and where inactive (|w| ≤ 1e-6), as the engines specify.
pub fn effective_weights(rig: &crowdmorph::rig::Rig, w: &[f64], lod: u32) -> Vec<f64> {
    let shapes = rig.lod.shapes_at(lod).expect("lod level") as usize;
    let mut out = vec![0.0; w.len()];
    for &t in &rig.lod.order[..shapes] {
        let x = w[t as usize];
        if x.abs() > 1e-6 {
            out[t as usize] = x;
        }
    }
    out
}

/// A rig with random localized sparse deltas, several primitives of awkward sizes (not
/// multiples of the 16-vertex tile), normal deltas on some primitives, a shuffled LOD order,
/// and one clip of random frames.
pub fn random_rig(seed: u64, sizes: &[usize], n_targets: usize) -> crowdmorph::rig::Rig {
    use crowdmorph::rig::{Primitive, sparsify, vertex_normals};
    use glam::Vec3;
    let mut rng = Rng(seed);
    let mut primitives = Vec::new();
    for (pi, &n) in sizes.iter().enumerate() {
        let positions: Vec<Vec3> = (0..n)
            .map(|i| {
                let a = i as f32 * 0.37;
                Vec3::new(a.cos() * (1.0 + i as f32 * 1e-3), a.sin(), i as f32 * 1e-3)
            })
            .collect();
        let indices: Vec<u32> = (0..n.saturating_sub(2) as u32)
            .flat_map(|i| [i, i + 1, i + 2])
            .collect();
        let normals = vertex_normals(&positions, &indices);
        let with_normal_deltas = pi % 2 == 1;
        let mut targets = Vec::new();
        for t in 0..n_targets {
            if rng.below(4) == 0 {
                continue; // Not every target moves every primitive.
            }
            let center = rng.below(n);
            let radius = 1 + rng.below(n / 3 + 1);
            let dir = Vec3::new(
                rng.f64() as f32 - 0.5,
                rng.f64() as f32 - 0.5,
                rng.f64() as f32 - 0.5,
            );
            let dp: Vec<Vec3> = (0..n)
                .map(|v| {
                    let d = (v as i64 - center as i64).unsigned_abs() as usize;
                    if d < radius {
                        dir * (1.0 - d as f32 / radius as f32)
                    } else {
                        Vec3::ZERO
                    }
                })
                .collect();
            let dn: Vec<Vec3> = dp.iter().map(|d| *d * 0.3).collect();
            let st = sparsify(
                t as u32,
                &dp,
                with_normal_deltas.then_some(&dn[..]),
                None,
                1e-6,
            );
            if !st.vertices.is_empty() {
                targets.push(st);
            }
        }
        primitives.push(Primitive {
            name: format!("p{pi}"),
            positions,
            normals,
            normals_from_file: false,
            tangents: None,
            indices,
            targets,
            base_color: Primitive::default_base_color(),
            skin: None,
            look: Default::default(),
        });
    }
    let mut rig = rig_with_random_clip(
        format!("random-{seed}"),
        primitives,
        n_targets,
        12,
        3,
        &mut rng,
    );
    rig.lod.method = "random".into();
    rig.validate().expect("random rig is valid");
    rig
}

/// A rig of `primitives` with targets `t0, t1, ...`, a shuffled LOD order and one clip
/// `random` of `frames` frames whose weights are zero one time in `zero_one_in`, else in
/// [−0.25, 1.25); drawn from `rng` in that order. Not validated.
pub fn rig_with_random_clip(
    name: String,
    primitives: Vec<crowdmorph::rig::Primitive>,
    n_targets: usize,
    frames: usize,
    zero_one_in: usize,
    rng: &mut Rng,
) -> crowdmorph::rig::Rig {
    use crowdmorph::rig::{Clip, Lod, Rig};
    let mut lod = Lod::file_order(n_targets);
    for i in (1..n_targets).rev() {
        lod.order.swap(i, rng.below(i + 1));
    }
    let weights: Vec<f32> = (0..n_targets * frames)
        .map(|_| {
            if rng.below(zero_one_in) == 0 {
                0.0
            } else {
                rng.f64() as f32 * 1.5 - 0.25
            }
        })
        .collect();
    Rig {
        name,
        targets: (0..n_targets).map(|t| format!("t{t}")).collect(),
        default_weights: vec![0.0; n_targets],
        primitives: std::sync::Arc::new(primitives),
        clips: vec![Clip::new("random", 30.0, n_targets, frames, weights).expect("clip")],
        lod,
        skeleton: None,
        import_notes: Vec::new(),
        appearance: None,
    }
}

/// The paper's rig size (Costigan et al. 2016: 72 blendshapes, 43,788 vertices) with
/// localized deltas (built by the library, shared with `bench gpu`).
pub fn paper_scale_rig() -> crowdmorph::rig::Rig {
    crowdmorph::synthetic::paper_scale_rig()
}

/// Gives a rig without clips a deterministic random one (the GPU reads weights from resident
/// clip tables, so every job needs a clip).
pub fn with_random_clip(rig: crowdmorph::rig::Rig, seed: u64) -> crowdmorph::rig::Rig {
    crowdmorph::synthetic::with_random_clip(rig, seed)
}

/// The CPU engine's positions (f32, LOD 0) of one `pose` of a prepared rig.
pub fn pose_positions(
    engine: &crowdmorph::engine::Engine,
    prepared: &crowdmorph::engine::PreparedRig,
    pose: crowdmorph::rig::Pose,
) -> Vec<f32> {
    engine
        .evaluate(
            prepared,
            &[crowdmorph::engine::BlendJob::posed(pose, 0)],
            crowdmorph::engine::OutputSpec::default(),
        )
        .expect("evaluate")
        .output
        .job_positions(0)
}
