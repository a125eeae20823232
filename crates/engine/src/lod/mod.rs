//! Level of detail: importance-ordered blendshapes (Costigan et al. 2016 §4) and
//! feature-preserving simplified meshes (the multiresolution facial mesh paper).
//!
//! - [`metrics`]: the five §4.1 metrics (geometric MSE, Hausdorff, image MSE, SSIM, Yee 2004).
//! - [`order`]: scoring every target against the neutral face, per-metric and combined
//!   orders, pinning shapes to the front.
//! - [`mesh`]: facial feature points, QEM simplification that locks them, and the derived rig
//!   a mesh level is evaluated as.
//! - [`report`]: the error of each order's LOD levels against the full rig over a clip, as a
//!   table, JSON and a PNG plot; synthetic clips for rigs without animation.
//! - [`pca`]: the variable-PCA form of the deltas within an error budget, and where a LOD level
//!   would gain from it.
//! - [`build_lod`]: everything above turned into the [`Lod`] a rig persists, from a [`LodSpec`]
//!   (what `PUT /v1/rigs/{id}/lod` and `crowdmorph lod` ask for).
//!
//! Building a LOD is a background job on rig registration: it takes a [`Progress`] that counts
//! finished steps and can cancel it.

pub mod mesh;
pub mod metrics;
pub mod order;
pub mod pca;
pub mod plot;
pub mod raster;
pub mod report;

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

use serde::{Deserialize, Serialize};

pub use mesh::{
    FeaturePoints, MeshLodError, SimplifyOptions, build_mesh_levels, mesh_level_rig,
    mesh_level_rigs,
};
pub use order::{Metric, OrderMethod, ScoreOptions, Scores, TargetScore, pin_front, score_targets};

use crowdmorph_core::rig::{Lod, LodError, LodLevel, Rig, TargetId, default_lod_levels, map_bytes};

/// Why a LOD could not be built.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum LodBuildError {
    /// A name in the request is not a target of the rig (the name as
    /// [`crowdmorph_core::rig::quoted_name`] quotes it).
    #[error("unknown target {0}")]
    UnknownTarget(String),
    /// A target appears twice in an explicit order or pin list (quoted likewise).
    #[error("target {0} is listed twice")]
    DuplicateTarget(String),
    /// An explicit order does not list every target.
    #[error("explicit order lists {got} of the rig's {want} targets")]
    IncompleteOrder {
        /// Targets listed.
        got: usize,
        /// Targets in the rig.
        want: usize,
    },
    /// A level asks for something the rig cannot give.
    #[error("LOD level {level}: {problem}")]
    BadLevel {
        /// Level index.
        level: usize,
        /// What is wrong.
        problem: String,
    },
    /// More simplified meshes asked for than [`MAX_MESH_LEVELS`].
    #[error("{0} mesh levels asked for; at most {MAX_MESH_LEVELS}")]
    TooManyMeshes(usize),
    /// Mesh simplification failed.
    #[error(transparent)]
    Mesh(MeshLodError),
    /// The resulting table is not valid.
    #[error(transparent)]
    Lod(#[from] LodError),
    /// The job was cancelled through its [`Progress`].
    #[error("cancelled")]
    Cancelled,
}

impl From<MeshLodError> for LodBuildError {
    fn from(e: MeshLodError) -> LodBuildError {
        match e {
            MeshLodError::Cancelled => LodBuildError::Cancelled,
            e => LodBuildError::Mesh(e),
        }
    }
}

/// Most simplified meshes one LOD may carry. Each is a copy of the rig's topology and deltas
/// at a fraction of the size, so the cap bounds what one request can make the server hold.
pub const MAX_MESH_LEVELS: usize = 8;

/// Progress of a background LOD computation: finished and total steps, and a cancel flag.
/// Share it (e.g. in an `Arc`) between the worker and whoever reports progress.
#[derive(Debug, Default)]
pub struct Progress {
    done: AtomicUsize,
    total: AtomicUsize,
    cancelled: AtomicBool,
}

impl Progress {
    /// A fresh counter.
    pub fn new() -> Progress {
        Progress::default()
    }

    /// Adds `steps` to the total and is called by the worker as it learns its work.
    pub fn start(&self, steps: usize) {
        self.total.fetch_add(steps, Ordering::Relaxed);
    }

    /// One more step done.
    pub fn advance(&self) {
        self.done.fetch_add(1, Ordering::Relaxed);
    }

    /// Steps done so far.
    pub fn done(&self) -> usize {
        self.done.load(Ordering::Relaxed)
    }

    /// Steps known so far.
    pub fn total(&self) -> usize {
        self.total.load(Ordering::Relaxed)
    }

    /// Done / total in [0, 1] (0 before the work is known).
    pub fn fraction(&self) -> f32 {
        let t = self.total();
        if t == 0 {
            0.0
        } else {
            (self.done() as f32 / t as f32).min(1.0)
        }
    }

    /// Asks the worker to stop at its next check.
    pub fn cancel(&self) {
        self.cancelled.store(true, Ordering::Relaxed);
    }

    /// Whether [`Progress::cancel`] was called.
    pub fn is_cancelled(&self) -> bool {
        self.cancelled.load(Ordering::Relaxed)
    }
}

/// One level of a requested table: a shape count or a fraction of the targets, and optionally
/// which simplified mesh (index into [`LodSpec::mesh_fractions`]) it uses.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LevelSpec {
    /// Shapes evaluated; takes precedence over `fraction`.
    #[serde(default)]
    pub shapes: Option<u32>,
    /// Fraction of the targets evaluated (rounded to nearest).
    #[serde(default)]
    pub fraction: Option<f32>,
    /// Simplified mesh this level evaluates; `None` = full mesh.
    #[serde(default)]
    pub mesh: Option<u32>,
}

/// A request for a rig's LOD: how to order, what to pin, the levels, the meshes.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LodSpec {
    /// How to order the targets (default: combined mean rank).
    #[serde(default)]
    pub method: OrderMethod,
    /// An explicit full order by target name (a name with several weight channels stands for
    /// all of them, or is listed once per channel as `name#k`); overrides `method` (pins
    /// still apply).
    #[serde(default)]
    pub order: Option<Vec<String>>,
    /// Targets moved to the front, in this order.
    #[serde(default)]
    pub pinned: Vec<String>,
    /// The table; default 100/50/25/10/0 % of the targets.
    #[serde(default)]
    pub levels: Option<Vec<LevelSpec>>,
    /// Simplified meshes to build, as fractions of the triangles (e.g. `[0.5, 0.25, 0.1]`).
    /// With the default table, level `i ≥ 1` uses mesh `min(i, meshes) − 1`.
    #[serde(default)]
    pub mesh_fractions: Vec<f32>,
    /// Scoring options.
    #[serde(default)]
    pub scoring: ScoreOptions,
    /// Let full-mesh levels use the variable-PCA form of the deltas where it is smaller and
    /// needs fewer multiply-adds at the level's error ([`pca`]). Default (`None`): with the
    /// default table, yes; with explicit `levels`, no — a level asked for as "the first N
    /// shapes" then is exactly that.
    #[serde(default)]
    pub pca: Option<bool>,
}

impl LodSpec {
    /// Whether full-mesh levels may become PCA levels ([`LodSpec::pca`]).
    pub fn uses_pca(&self) -> bool {
        self.pca.unwrap_or(self.levels.is_none())
    }

    /// The checks that need no rig: the number and range of mesh fractions. `build_lod` runs
    /// them first, so that a bad request is refused before seconds of scoring; the server
    /// runs them before it replaces a running job.
    pub fn check(&self) -> Result<(), LodBuildError> {
        if self.mesh_fractions.len() > MAX_MESH_LEVELS {
            return Err(LodBuildError::TooManyMeshes(self.mesh_fractions.len()));
        }
        match self
            .mesh_fractions
            .iter()
            .find(|&&f| !(f > 0.0 && f <= 1.0))
        {
            Some(&f) => Err(MeshLodError::BadFraction(f).into()),
            None => Ok(()),
        }
    }
}

/// Resolves target names to weight channels, refusing unknown and repeated ones. A name
/// stands for every channel it has (in channel order: usually one); a channel label
/// `name#k` ([`Rig::channel_label`], as LOD orders list the channels of a name that has
/// several) stands for that channel alone.
pub fn resolve_targets(rig: &Rig, names: &[String]) -> Result<Vec<TargetId>, LodBuildError> {
    // One name index and one seen-flag per channel: a request naming all of a 4,096-channel
    // rig's targets costs a hash probe per name, not a scan of every channel (and of every
    // id resolved so far) per name.
    let index = rig.target_index();
    let mut seen = vec![false; rig.targets.len()];
    let mut out = Vec::with_capacity(names.len());
    for n in names {
        let label;
        let ids = match index.ids(n) {
            [] => {
                label = index.channel_by_label(n);
                label.as_slice()
            }
            ids => ids,
        };
        if ids.is_empty() {
            return Err(LodBuildError::UnknownTarget(
                crowdmorph_core::rig::quoted_name(n),
            ));
        }
        for &id in ids {
            // Ids come from the rig's own channels, so they index `seen`.
            if std::mem::replace(&mut seen[id as usize], true) {
                return Err(LodBuildError::DuplicateTarget(
                    crowdmorph_core::rig::quoted_name(n),
                ));
            }
            out.push(id);
        }
    }
    Ok(out)
}

/// An upper bound of the transient memory [`build_lod`] holds for `rig`: per scoring thread a
/// posed copy of the mesh, one target's displacement and a render at the scoring size; shared,
/// the neutral mesh, its point index and the reference renders (Yee's pyramid included); and
/// the mesh simplifier's working copies. The server charges it before a build starts.
pub fn build_bytes(rig: &Rig, spec: &LodSpec) -> u64 {
    let v = rig.vertex_count() as u64;
    let i: u64 = rig.primitives.iter().map(|p| p.indices.len() as u64).sum();
    let size = u64::from(spec.scoring.image_size.clamp(16, 4096));
    let pixels = size * size;
    let threads = rayon::current_num_threads() as u64;
    let scoring = if spec.order.is_none() && spec.method != OrderMethod::FileOrder {
        112 * v + 64 * pixels + threads * (32 * v + 32 * pixels + 4 * i)
    } else {
        0
    };
    let meshes = if spec.mesh_fractions.is_empty() {
        0
    } else {
        64 * v + 32 * i
    };
    // Resolving names and pins (the name index, a flag per channel, the pin sets) and the
    // index of each target's sparse deltas.
    let n = rig.targets.len();
    let lookups = crowdmorph_core::rig::TargetIndex::bytes_for(n)
        + n as u64
        + 2 * map_bytes(n, 4)
        + order::SparseIndex::bytes_for(rig);
    let pca = if spec.uses_pca() {
        pca::build_bytes(rig)
    } else {
        0
    };
    scoring.max(meshes).max(pca) + lookups + (1 << 20)
}

/// The smallest error a PCA level is built within, as a fraction of the diagonal.
pub const PCA_FLOOR: f32 = 1e-4;

/// The table with a PCA form on each full-mesh level where one pays ([`pca::pays`]) at that
/// level's error on the test poses; the forms, in level order.
fn pca_levels(
    rig: &Rig,
    order: &[TargetId],
    mut levels: Vec<LodLevel>,
    progress: Option<&Progress>,
) -> Result<(Vec<LodLevel>, Vec<crowdmorph_core::rig::DeltaPca>), LodBuildError> {
    let n = rig.targets.len() as u32;
    let mut forms = Vec::new();
    for level in levels.iter_mut().skip(1) {
        if level.mesh.is_some() || level.shapes >= n {
            continue;
        }
        if progress.is_some_and(Progress::is_cancelled) {
            return Err(LodBuildError::Cancelled);
        }
        let error = pca::level_error(rig, order, level.shapes);
        if error <= f64::from(PCA_FLOOR) {
            continue;
        }
        let form = pca::build(rig, error as f32);
        let (madds, bytes) = (
            pca::level_madds(rig, order, level.shapes),
            pca::level_bytes(rig, order, level.shapes),
        );
        if pca::pays(&form, madds, bytes) {
            level.pca = Some(forms.len() as u32);
            forms.push(form);
        }
    }
    Ok((levels, forms))
}

/// What [`check_spec`] resolved: the pins, the explicit order if any, and the table.
struct Checked {
    pinned: Vec<TargetId>,
    explicit: Option<Vec<TargetId>>,
    levels: Vec<LodLevel>,
}

/// Every check of a request against `rig` that needs no scoring or simplifying: the spec's
/// own ([`LodSpec::check`]), its target names, and its table (with one mesh level per
/// fraction). [`build_lod`] runs it before its expensive work, so that a bad request is
/// refused at once; the server runs it before a `PUT` replaces the rig's running job.
pub fn check_request(rig: &Rig, spec: &LodSpec) -> Result<(), LodBuildError> {
    check_spec(rig, spec).map(drop)
}

fn check_spec(rig: &Rig, spec: &LodSpec) -> Result<Checked, LodBuildError> {
    let n = rig.targets.len();
    spec.check()?;
    let pinned = resolve_targets(rig, &spec.pinned)?;
    let explicit = match &spec.order {
        Some(names) => {
            let order = resolve_targets(rig, names)?;
            if order.len() != n {
                return Err(LodBuildError::IncompleteOrder {
                    got: order.len(),
                    want: n,
                });
            }
            Some(order)
        }
        None => None,
    };
    // The table needs only the number of mesh levels, one per fraction, so it is checked
    // here, before the build's seconds of scoring and simplifying, not after them.
    let meshes = spec.mesh_fractions.len();
    let levels = match &spec.levels {
        Some(specs) => specs
            .iter()
            .enumerate()
            .map(|(i, l)| {
                let shapes = match (l.shapes, l.fraction) {
                    (Some(s), _) => s,
                    (None, Some(f)) if (0.0..=1.0).contains(&f) => (n as f32 * f).round() as u32,
                    (None, Some(f)) => {
                        return Err(LodBuildError::BadLevel {
                            level: i,
                            problem: format!("fraction {f} is not in [0, 1]"),
                        });
                    }
                    (None, None) => {
                        return Err(LodBuildError::BadLevel {
                            level: i,
                            problem: "neither shapes nor fraction given".into(),
                        });
                    }
                };
                Ok(LodLevel {
                    shapes,
                    mesh: l.mesh,
                    pca: None,
                })
            })
            .collect::<Result<Vec<_>, _>>()?,
        None => default_lod_levels(n)
            .into_iter()
            .enumerate()
            .map(|(i, l)| LodLevel {
                mesh: (i > 0 && meshes > 0).then(|| (i.min(meshes) - 1) as u32),
                ..l
            })
            .collect(),
    };
    Lod::validate_levels(&levels, n, meshes, 0)?;
    Ok(Checked {
        pinned,
        explicit,
        levels,
    })
}

/// Builds the LOD a rig persists: scores the targets when the method needs them (pass
/// `scores` to reuse an earlier scoring), orders, pins, lays out the table and simplifies the
/// meshes. The result passes `Lod::validate` and `Lod::validate_meshes` for this rig.
pub fn build_lod(
    rig: &Rig,
    spec: &LodSpec,
    scores: Option<&Scores>,
    progress: Option<&Progress>,
) -> Result<Lod, LodBuildError> {
    let n = rig.targets.len();
    let Checked {
        pinned,
        explicit,
        levels,
    } = check_spec(rig, spec)?;
    let (base, method) = match explicit {
        Some(order) => (order, "explicit".to_string()),
        None => match spec.method {
            OrderMethod::FileOrder => ((0..n as TargetId).collect(), "file-order".to_string()),
            m => {
                let owned;
                let s = match scores {
                    Some(s) if s.targets.len() == n => s,
                    _ => {
                        owned = score_targets(rig, &spec.scoring, progress)?;
                        &owned
                    }
                };
                (s.order(m), m.name().to_string())
            }
        },
    };
    let order = pin_front(&base, &pinned);
    let method = if pinned.is_empty() {
        method
    } else {
        format!("{method}+pinned")
    };
    let meshes = if spec.mesh_fractions.is_empty() {
        Vec::new()
    } else {
        if progress.is_some_and(Progress::is_cancelled) {
            return Err(LodBuildError::Cancelled);
        }
        let (levels, _) = build_mesh_levels(
            rig,
            &spec.mesh_fractions,
            &SimplifyOptions::default(),
            progress,
        )?;
        // A rig of points only simplifies to nothing, which no engine can evaluate.
        if levels
            .iter()
            .any(|l| l.primitives.iter().all(|p| p.vertices.is_empty()))
        {
            return Err(MeshLodError::Rig(crowdmorph_core::rig::RigError::NoVertices).into());
        }
        levels
    };
    let (levels, pca) = if spec.uses_pca() {
        pca_levels(rig, &order, levels, progress)?
    } else {
        (levels, Vec::new())
    };
    let lod = Lod {
        order,
        levels,
        method,
        pinned,
        meshes,
        pca,
    };
    lod.validate(n)?;
    let counts: Vec<usize> = rig.primitives.iter().map(|p| p.positions.len()).collect();
    lod.validate_meshes(&counts)?;
    Ok(lod)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `resolve_targets` as it was before the name index: a scan of every channel (and of
    /// the ids resolved so far) per name. The indexed one must agree with it exactly.
    fn resolve_targets_by_scan(
        rig: &Rig,
        names: &[String],
    ) -> Result<Vec<TargetId>, LodBuildError> {
        let mut out = Vec::with_capacity(names.len());
        for n in names {
            let mut ids = rig.target_ids(n);
            if ids.is_empty() {
                ids.extend(rig.channel_by_label(n));
            }
            if ids.is_empty() {
                return Err(LodBuildError::UnknownTarget(
                    crowdmorph_core::rig::quoted_name(n),
                ));
            }
            for id in ids {
                if out.contains(&id) {
                    return Err(LodBuildError::DuplicateTarget(
                        crowdmorph_core::rig::quoted_name(n),
                    ));
                }
                out.push(id);
            }
        }
        Ok(out)
    }

    #[test]
    fn indexed_resolution_agrees_with_the_scan() {
        let mut rig = crowdmorph_core::embedded::default_rig();
        let names: Vec<String> = rig.targets.clone();
        // A name with two channels (`jawOpen#1`, `jawOpen#2`) and one with three, so that
        // labels and whole names of split targets are both resolved.
        let split = rig.targets[0].clone();
        rig.targets[1] = split.clone();
        let triple = rig.targets[2].clone();
        rig.targets[3] = triple.clone();
        rig.targets[4] = triple.clone();
        let all = |v: Vec<&str>| v.into_iter().map(String::from).collect::<Vec<_>>();
        let cases: Vec<Vec<String>> = vec![
            Vec::new(),
            rig.target_names().into_iter().map(String::from).collect(),
            rig.channel_labels().into_vec(),
            rig.channel_labels().into_vec().into_iter().rev().collect(),
            all(vec![&split, &names[5]]),
            all(vec![
                &format!("{split}#2"),
                &format!("{triple}#3"),
                &names[6],
            ]),
            // Duplicates: a name twice, a label and its name, a label twice.
            all(vec![&names[6], &names[7], &names[6]]),
            all(vec![&format!("{split}#1"), &split]),
            all(vec![&split, &format!("{split}#2")]),
            all(vec![&format!("{triple}#2"), &format!("{triple}#2")]),
            // Unknown: no such name, labels past a name's channels or of a single-channel
            // name, malformed labels.
            all(vec![&names[5], "noSuchShape"]),
            all(vec![&format!("{split}#3")]),
            all(vec![&format!("{split}#0")]),
            all(vec![&format!("{}#1", names[5])]),
            all(vec![&format!("{split}#x"), &names[5]]),
            all(vec!["#1", "", "#"]),
        ];
        for names in cases {
            assert_eq!(
                resolve_targets(&rig, &names),
                resolve_targets_by_scan(&rig, &names),
                "{names:?}"
            );
        }
        // Every case above that should succeed did, and the failures were of both kinds.
        assert!(resolve_targets(&rig, &rig.channel_labels().into_vec()).is_ok());
        assert_eq!(
            resolve_targets(&rig, &all(vec![&split, &format!("{split}#2")])),
            Err(LodBuildError::DuplicateTarget(
                crowdmorph_core::rig::quoted_name(&format!("{split}#2"))
            ))
        );
    }

    #[test]
    fn a_bad_table_is_refused_before_any_scoring() {
        let rig = crowdmorph_core::embedded::default_rig();
        let n = rig.targets.len() as u32;
        let level = |shapes, mesh| LevelSpec {
            shapes: Some(shapes),
            fraction: None,
            mesh,
        };
        let bad = [
            (vec![level(n, None); 65], "more than 64 levels"),
            (vec![level(n, None), level(n + 1, None)], "shapes of"),
            (vec![level(n, None), level(3, Some(1))], "names mesh 1 of 1"),
            (vec![level(3, None)], "level 0 must evaluate"),
        ];
        for (levels, needle) in bad {
            let spec = LodSpec {
                levels: Some(levels),
                mesh_fractions: vec![0.5],
                ..LodSpec::default()
            };
            let progress = Progress::new();
            let e = build_lod(&rig, &spec, None, Some(&progress)).expect_err("a bad table");
            assert!(e.to_string().contains(needle), "{e} should say {needle:?}");
            assert_eq!(check_request(&rig, &spec), Err(e));
            // Neither the scoring nor the simplifier started (each counts its steps first).
            assert_eq!(
                progress.total(),
                0,
                "{needle}: work started before the refusal"
            );
        }
        // A good table passes the same check.
        let good = LodSpec {
            levels: Some(vec![level(n, None), level(3, Some(0))]),
            mesh_fractions: vec![0.5],
            ..LodSpec::default()
        };
        assert_eq!(check_request(&rig, &good), Ok(()));
    }

    #[test]
    fn progress_counts_and_cancels() {
        let p = Progress::new();
        assert_eq!(p.fraction(), 0.0);
        p.start(4);
        p.advance();
        assert_eq!((p.done(), p.total()), (1, 4));
        assert!((p.fraction() - 0.25).abs() < 1e-6);
        assert!(!p.is_cancelled());
        p.cancel();
        assert!(p.is_cancelled());
    }

    #[test]
    fn mesh_levels_are_capped_and_cancellable() {
        let rig = crowdmorph_core::embedded::default_rig();
        let many = LodSpec {
            method: OrderMethod::FileOrder,
            mesh_fractions: vec![0.5; MAX_MESH_LEVELS + 1],
            ..LodSpec::default()
        };
        assert_eq!(
            build_lod(&rig, &many, None, None),
            Err(LodBuildError::TooManyMeshes(MAX_MESH_LEVELS + 1))
        );
        // Cancelled between levels: the simplifier stops before the next one.
        let p = Progress::new();
        p.cancel();
        let r = build_mesh_levels(&rig, &[0.5, 0.25], &SimplifyOptions::default(), Some(&p));
        assert!(matches!(r, Err(MeshLodError::Cancelled)), "{r:?}");
        assert_eq!(
            LodBuildError::from(MeshLodError::Cancelled),
            LodBuildError::Cancelled
        );
    }

    #[test]
    fn explicit_orders_and_pins_are_checked() {
        let rig = crowdmorph_core::embedded::default_rig();
        let spec = LodSpec {
            method: OrderMethod::FileOrder,
            pinned: vec!["eyeBlink_L".into(), "eyeBlink_R".into()],
            ..LodSpec::default()
        };
        let lod = build_lod(&rig, &spec, None, None).expect("file order with pins");
        let bl = rig.target_id("eyeBlink_L").expect("blink");
        let br = rig.target_id("eyeBlink_R").expect("blink");
        assert_eq!(&lod.order[..2], &[bl, br]);
        assert_eq!(lod.pinned, vec![bl, br]);
        assert_eq!(lod.method, "file-order+pinned");
        assert_eq!(lod.levels.len(), 5);
        let bad = LodSpec {
            pinned: vec!["noSuchShape".into()],
            ..spec.clone()
        };
        assert_eq!(
            build_lod(&rig, &bad, None, None),
            Err(LodBuildError::UnknownTarget("\"noSuchShape\"".into()))
        );
        let short = LodSpec {
            order: Some(vec!["jawOpen".into()]),
            ..spec.clone()
        };
        assert!(matches!(
            build_lod(&rig, &short, None, None),
            Err(LodBuildError::IncompleteOrder { got: 1, .. })
        ));
        let levels = LodSpec {
            levels: Some(vec![
                LevelSpec {
                    fraction: Some(1.0),
                    ..LevelSpec::default()
                },
                LevelSpec {
                    shapes: Some(3),
                    ..LevelSpec::default()
                },
            ]),
            ..spec
        };
        let lod = build_lod(&rig, &levels, None, None).expect("custom table");
        assert_eq!(
            lod.levels.iter().map(|l| l.shapes).collect::<Vec<_>>(),
            vec![rig.targets.len() as u32, 3]
        );
    }
}
