//! An independent f64 evaluator of skinned, node-animated glTF scenes (glTF 2.0 §3.5.3
//! transforms, §3.7.3 skins, Appendix C animation sampling), sharing no code with
//! `crowdmorph::import` or the engines.
//!
//! A pose is the scene at time `t` of one animation (or at rest): every node's local
//! translation, rotation and scale is its own value or the animation's sampled value; globals
//! are composed from the scene's roots. Each mesh instance then morphs (its default weights,
//! or the animation's weights) and is placed: a skinned mesh by `Σ w_k · global(joint_k) ·
//! inverseBind_k` (its own node transform ignored, as the spec says), any other mesh by its
//! node's global transform. Normals go through each joint's inverse transpose, weighted, then
//! normalized; that per-joint rule is the one crowdmorph documents (`crates/core/src/rig/skin.rs`).
//!
//! A blend is the engines' documented rule too: per node, translations and scales summed by
//! fraction and rotations nlerped (each flipped into the first term's hemisphere).

use glam::{DMat3, DMat4, DQuat, DVec3, DVec4};
use serde_json::Value;

use super::{RefDoc, normal_matrix};

fn u(v: &Value) -> usize {
    v.as_u64().expect("non-negative integer") as usize
}

/// A node's local transform, or its fixed matrix (a `matrix` node is never animated).
#[derive(Clone, Copy, Debug)]
pub enum Local {
    /// Translation, rotation, scale.
    Trs(DVec3, DQuat, DVec3),
    /// `node.matrix`.
    Matrix(DMat4),
}

impl Local {
    fn matrix(&self) -> DMat4 {
        match *self {
            Local::Trs(t, r, s) => DMat4::from_scale_rotation_translation(s, r.normalize(), t),
            Local::Matrix(m) => m,
        }
    }
}

/// One evaluated mesh primitive instance: positions and normals in the scene's space.
pub struct Posed {
    pub node: usize,
    pub positions: Vec<DVec3>,
    pub normals: Option<Vec<DVec3>>,
}

/// Samples a translation/rotation/scale sampler's `width` values at `t`; rotations are
/// slerped (LINEAR) and normalized, as Appendix C says.
fn sample(doc: &RefDoc, sampler: &Value, t: f64, rotation: bool) -> Vec<f64> {
    let times = doc.accessor(u(&sampler["input"])).0;
    let (values, width) = doc.accessor(u(&sampler["output"]));
    let interp = sampler["interpolation"].as_str().unwrap_or("LINEAR");
    let cubic = interp == "CUBICSPLINE";
    let val = |k: usize| -> Vec<f64> {
        let row = if cubic { 3 * k + 1 } else { k };
        values[row * width..(row + 1) * width].to_vec()
    };
    let n = times.len();
    let out = if t <= times[0] {
        val(0)
    } else if t >= times[n - 1] {
        val(n - 1)
    } else {
        let k = times.iter().rposition(|&x| x <= t).unwrap();
        let (t0, t1) = (times[k], times[k + 1]);
        let s = (t - t0) / (t1 - t0);
        match interp {
            "STEP" => val(k),
            "CUBICSPLINE" => {
                let td = t1 - t0;
                let (a, b) = (val(k), val(k + 1));
                let out_tan = &values[(3 * k + 2) * width..(3 * k + 3) * width];
                let in_tan = &values[(3 * (k + 1)) * width..(3 * (k + 1) + 1) * width];
                let (s2, s3) = (s * s, s * s * s);
                (0..width)
                    .map(|j| {
                        (2.0 * s3 - 3.0 * s2 + 1.0) * a[j]
                            + (s3 - 2.0 * s2 + s) * td * out_tan[j]
                            + (-2.0 * s3 + 3.0 * s2) * b[j]
                            + (s3 - s2) * td * in_tan[j]
                    })
                    .collect()
            }
            _ if rotation => {
                let q = |v: &[f64]| DQuat::from_xyzw(v[0], v[1], v[2], v[3]).normalize();
                let (a, mut b) = (q(&val(k)), q(&val(k + 1)));
                // The shorter arc (the spec's reference implementation).
                if a.dot(b) < 0.0 {
                    b = -b;
                }
                let d = a.dot(b).clamp(-1.0, 1.0);
                let r = if d > 1.0 - 1e-12 {
                    DQuat::from_vec4(DVec4::from(a).lerp(DVec4::from(b), s)).normalize()
                } else {
                    let th = d.acos();
                    let (wa, wb) = (((1.0 - s) * th).sin() / th.sin(), (s * th).sin() / th.sin());
                    DQuat::from_vec4(DVec4::from(a) * wa + DVec4::from(b) * wb)
                };
                r.to_array().to_vec()
            }
            _ => {
                let (a, b) = (val(k), val(k + 1));
                (0..width).map(|j| a[j] + (b[j] - a[j]) * s).collect()
            }
        }
    };
    if rotation {
        DQuat::from_xyzw(out[0], out[1], out[2], out[3])
            .normalize()
            .to_array()
            .to_vec()
    } else {
        out
    }
}

impl RefDoc {
    /// Every node's local transform at rest.
    pub fn rest_locals(&self) -> Vec<Local> {
        self.json["nodes"]
            .as_array()
            .unwrap()
            .iter()
            .map(|node| {
                if node.get("matrix").is_some() {
                    return Local::Matrix(Self::local_matrix(node));
                }
                let get = |k: &str, d: [f64; 4]| -> [f64; 4] {
                    let mut o = d;
                    for (i, x) in node[k].as_array().into_iter().flatten().enumerate() {
                        o[i] = x.as_f64().unwrap();
                    }
                    o
                };
                let t = get("translation", [0.0; 4]);
                let r = get("rotation", [0.0, 0.0, 0.0, 1.0]);
                let s = get("scale", [1.0; 4]);
                Local::Trs(
                    DVec3::new(t[0], t[1], t[2]),
                    DQuat::from_xyzw(r[0], r[1], r[2], r[3]),
                    DVec3::new(s[0], s[1], s[2]),
                )
            })
            .collect()
    }

    /// The animation called `name`'s node transforms at `t` seconds (rest where it has no
    /// channel).
    pub fn locals_at(&self, name: &str, t: f64) -> Vec<Local> {
        let mut locals = self.rest_locals();
        let anims = self.json["animations"].as_array().unwrap();
        let anim = anims
            .iter()
            .find(|a| a["name"].as_str() == Some(name))
            .unwrap_or_else(|| panic!("no animation {name:?}"));
        for c in anim["channels"].as_array().unwrap() {
            let path = c["target"]["path"].as_str().unwrap();
            if path == "weights" {
                continue;
            }
            let n = u(&c["target"]["node"]);
            let v = sample(
                self,
                &anim["samplers"][u(&c["sampler"])],
                t,
                path == "rotation",
            );
            if let Local::Trs(tr, r, s) = &mut locals[n] {
                match path {
                    "translation" => *tr = DVec3::new(v[0], v[1], v[2]),
                    "rotation" => *r = DQuat::from_xyzw(v[0], v[1], v[2], v[3]),
                    "scale" => *s = DVec3::new(v[0], v[1], v[2]),
                    p => panic!("channel path {p}"),
                }
            }
        }
        locals
    }

    /// The engines' blend of several poses: `(fraction, locals)` with fractions summing to one.
    pub fn blend_locals(terms: &[(f64, Vec<Local>)]) -> Vec<Local> {
        let n = terms[0].1.len();
        (0..n)
            .map(|i| {
                let Local::Trs(_, q0, _) = terms[0].1[i] else {
                    return terms[0].1[i];
                };
                let (mut t, mut q, mut s) = (DVec3::ZERO, DVec4::ZERO, DVec3::ZERO);
                for (f, locals) in terms {
                    let Local::Trs(ti, qi, si) = locals[i] else {
                        unreachable!("a matrix node is a matrix node in every pose")
                    };
                    let qi = if DVec4::from(qi).dot(DVec4::from(q0)) < 0.0 {
                        -DVec4::from(qi)
                    } else {
                        DVec4::from(qi)
                    };
                    t += *f * ti;
                    q += *f * qi;
                    s += *f * si;
                }
                Local::Trs(t, DQuat::from_vec4(q.normalize()), s)
            })
            .collect()
    }

    /// Global transforms of every node reachable from the default scene for `locals`.
    pub fn globals(&self, locals: &[Local]) -> Vec<Option<DMat4>> {
        let j = &self.json;
        let scene = j["scene"].as_u64().unwrap_or(0) as usize;
        let mut out = vec![None; locals.len()];
        let mut stack: Vec<(usize, DMat4)> = j["scenes"][scene]["nodes"]
            .as_array()
            .unwrap()
            .iter()
            .map(|n| (u(n), DMat4::IDENTITY))
            .collect();
        while let Some((n, parent)) = stack.pop() {
            let g = parent * locals[n].matrix();
            out[n] = Some(g);
            for c in j["nodes"][n]["children"].as_array().into_iter().flatten() {
                stack.push((u(c), g));
            }
        }
        out
    }

    /// Every mesh primitive instance of the default scene (the order of
    /// [`RefDoc::scene_primitives`]) posed by `locals`, morphed by each mesh's default
    /// weights (RobotExpressive's clips animate no weights; a file whose do is not evaluated
    /// here, and the caller asserts that).
    pub fn pose(&self, locals: &[Local]) -> Vec<Posed> {
        let globals = self.globals(locals);
        let j = &self.json;
        let mut out = Vec::new();
        for prim in self.scene_primitives() {
            let w = &prim.default_weights;
            let morph = |base: &[DVec3], deltas: &dyn Fn(usize) -> Option<DVec3>| -> Vec<DVec3> {
                base.iter()
                    .enumerate()
                    .map(|(v, &b)| {
                        b + prim
                            .targets
                            .iter()
                            .zip(w)
                            .map(|(_, &wt)| wt)
                            .enumerate()
                            .map(|(t, wt)| wt * deltas(t * base.len() + v).unwrap_or(DVec3::ZERO))
                            .sum::<DVec3>()
                    })
                    .collect()
            };
            let nv = prim.positions.len();
            let positions = morph(&prim.positions, &|k| {
                Some(prim.targets[k / nv].positions[k % nv])
            });
            let normals = prim.normals.as_ref().map(|n| {
                morph(n, &|k| {
                    prim.targets[k / nv].normals.as_ref().map(|d| d[k % nv])
                })
            });
            let node = &j["nodes"][prim.node];
            let posed = match node.get("skin") {
                Some(s) => {
                    let skin = &j["skins"][u(s)];
                    let joints: Vec<usize> =
                        skin["joints"].as_array().unwrap().iter().map(u).collect();
                    let ibm: Vec<DMat4> = match skin.get("inverseBindMatrices") {
                        Some(a) => self
                            .accessor(u(a))
                            .0
                            .chunks_exact(16)
                            .map(DMat4::from_cols_slice)
                            .collect(),
                        None => vec![DMat4::IDENTITY; joints.len()],
                    };
                    let mats: Vec<DMat4> = joints
                        .iter()
                        .zip(&ibm)
                        .map(|(&jn, m)| globals[jn].expect("joint in the scene") * *m)
                        .collect();
                    let nmats: Vec<DMat3> = mats.iter().map(|m| normal_matrix(*m)).collect();
                    let (js, ws) = self.influences(&prim.mesh_primitive_attributes(j));
                    let p = positions
                        .iter()
                        .enumerate()
                        .map(|(v, &p)| {
                            (0..js[v].len())
                                .map(|k| ws[v][k] * mats[js[v][k]].transform_point3(p))
                                .sum()
                        })
                        .collect();
                    let n = normals.map(|n| {
                        n.iter()
                            .enumerate()
                            .map(|(v, &x)| {
                                (0..js[v].len())
                                    .map(|k| ws[v][k] * (nmats[js[v][k]] * x))
                                    .sum::<DVec3>()
                                    .normalize()
                            })
                            .collect()
                    });
                    (p, n)
                }
                None => {
                    let g = globals[prim.node].expect("mesh node in the scene");
                    let nm = normal_matrix(g);
                    (
                        positions.iter().map(|&p| g.transform_point3(p)).collect(),
                        normals.map(|n| n.iter().map(|&x| (nm * x).normalize()).collect()),
                    )
                }
            };
            out.push(Posed {
                node: prim.node,
                positions: posed.0,
                normals: posed.1,
            });
        }
        out
    }

    /// Per vertex, its (joint, weight) pairs from every `JOINTS_n`/`WEIGHTS_n` set, zero
    /// weights left out.
    fn influences(&self, attrs: &Value) -> (Vec<Vec<usize>>, Vec<Vec<f64>>) {
        let mut js: Vec<Vec<usize>> = Vec::new();
        let mut ws: Vec<Vec<f64>> = Vec::new();
        for set in 0.. {
            let (Some(ja), Some(wa)) = (
                attrs.get(format!("JOINTS_{set}")),
                attrs.get(format!("WEIGHTS_{set}")),
            ) else {
                break;
            };
            let (jv, _) = self.accessor(u(ja));
            let (wv, _) = self.accessor(u(wa));
            let n = jv.len() / 4;
            js.resize(n, Vec::new());
            ws.resize(n, Vec::new());
            for v in 0..n {
                for k in 0..4 {
                    if wv[v * 4 + k] != 0.0 {
                        js[v].push(jv[v * 4 + k] as usize);
                        ws[v].push(wv[v * 4 + k]);
                    }
                }
            }
        }
        (js, ws)
    }
}

impl super::RefPrim {
    /// This instance's primitive's `attributes` object. The reader keeps no primitive index,
    /// so it is found as the primitive of the mesh whose POSITION decodes to the same count.
    fn mesh_primitive_attributes(&self, json: &Value) -> Value {
        let prims = json["meshes"][self.mesh]["primitives"].as_array().unwrap();
        assert_eq!(
            prims.len(),
            1,
            "the skinned reference handles one primitive per skinned mesh"
        );
        prims[0]["attributes"].clone()
    }
}

/// The nodes vertices follow in a glTF document, read from its JSON alone: every skin's joints
/// (a node several skins list, once) and each mesh node without a skin that an animation
/// moves, itself or through an ancestor (it hangs rigidly from itself).
pub fn followed_nodes(json: &Value) -> std::collections::BTreeSet<usize> {
    let nodes = json["nodes"].as_array().expect("nodes");
    let mut parent = vec![None; nodes.len()];
    for (i, n) in nodes.iter().enumerate() {
        for c in n["children"].as_array().into_iter().flatten() {
            parent[c.as_u64().expect("child") as usize] = Some(i);
        }
    }
    let animated: std::collections::BTreeSet<usize> = json["animations"]
        .as_array()
        .into_iter()
        .flatten()
        .flat_map(|a| a["channels"].as_array().into_iter().flatten())
        .filter(|c| c["target"]["path"] != "weights")
        .filter_map(|c| c["target"]["node"].as_u64().map(|n| n as usize))
        .collect();
    let mut out: std::collections::BTreeSet<usize> = json["skins"]
        .as_array()
        .into_iter()
        .flatten()
        .flat_map(|s| s["joints"].as_array().into_iter().flatten())
        .map(|j| j.as_u64().expect("joint") as usize)
        .collect();
    for (i, n) in nodes.iter().enumerate() {
        if n.get("mesh").is_none() || n.get("skin").is_some() {
            continue;
        }
        let mut at = Some(i);
        while let Some(k) = at {
            if animated.contains(&k) {
                out.insert(i);
                break;
            }
            at = parent[k];
        }
    }
    out
}
