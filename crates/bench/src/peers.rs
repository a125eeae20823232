//! The Python peers the benchmarks compare crowdmorph against, in the same run: the best plain
//! Python server a user could write instead (`clients/python/bench/dense_server.py`: aiohttp +
//! numpy, dense, same bincode request and response; `bench http --python-peer`) and a warm,
//! reused-buffer numpy blend (`clients/python/bench/numpy_blend.py`; `bench cpu --numpy`).
//!
//! Both read the rig as `.npy` files this module writes ([`export_rig`]): the neutral positions
//! (`V × 3` f32), every target's deltas as one dense `T × 3V` f32 matrix (the layout a numpy
//! user would build), each clip's weight table as `frames × T` rows (so that gathering a
//! frame's weights is one row), and a `levels × T` mask of the shapes each LOD level keeps.
//!
//! The scripts and the `crowdmorph` client package they import (its `wire` module decodes the
//! request and frames the response) are compiled into the binary and written next to the
//! export ([`write_scripts`]), so that the benchmark runs the code of this build wherever the
//! binary is. [`PythonPeer`] owns the server process and kills it when dropped, on error too.

use std::io::{BufRead, BufReader, Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use crowdmorph_proto::{CrowdFrameResponse, Format};

use crowdmorph_core::rig::Rig;

/// The peer scripts and the client package they import, as `(path under the script folder,
/// text)`: the layout of `clients/python`, so that `bench/dense_server.py` finds `src/`.
pub const SCRIPTS: &[(&str, &str)] = &[
    (
        "bench/dense_server.py",
        include_str!("../../../clients/python/bench/dense_server.py"),
    ),
    (
        "bench/numpy_blend.py",
        include_str!("../../../clients/python/bench/numpy_blend.py"),
    ),
    (
        "bench/blas_env.py",
        include_str!("../../../clients/python/bench/blas_env.py"),
    ),
    (
        "src/crowdmorph/__init__.py",
        include_str!("../../../clients/python/src/crowdmorph/__init__.py"),
    ),
    (
        "src/crowdmorph/arrays.py",
        include_str!("../../../clients/python/src/crowdmorph/arrays.py"),
    ),
    (
        "src/crowdmorph/client.py",
        include_str!("../../../clients/python/src/crowdmorph/client.py"),
    ),
    (
        "src/crowdmorph/errors.py",
        include_str!("../../../clients/python/src/crowdmorph/errors.py"),
    ),
    (
        "src/crowdmorph/messages.py",
        include_str!("../../../clients/python/src/crowdmorph/messages.py"),
    ),
    (
        "src/crowdmorph/obj.py",
        include_str!("../../../clients/python/src/crowdmorph/obj.py"),
    ),
    (
        "src/crowdmorph/results.py",
        include_str!("../../../clients/python/src/crowdmorph/results.py"),
    ),
    (
        "src/crowdmorph/sessions.py",
        include_str!("../../../clients/python/src/crowdmorph/sessions.py"),
    ),
    (
        "src/crowdmorph/wire.py",
        include_str!("../../../clients/python/src/crowdmorph/wire.py"),
    ),
];

/// The interpreter the peers run with unless told otherwise: the system's, which is where
/// Debian's `python3-numpy` and `python3-aiohttp` install.
pub const DEFAULT_PYTHON: &str = "/usr/bin/python3";

/// How long a peer may take to load the rig and listen.
const START_TIMEOUT: Duration = Duration::from_secs(60);

/// Writes a little-endian f32 `.npy` file (format version 1.0, C order) of `shape`.
pub fn write_npy_f32(path: &Path, shape: &[usize], data: &[f32]) -> Result<()> {
    let n: usize = shape.iter().product();
    if n != data.len() {
        bail!(
            "npy {}: shape {shape:?} holds {n} values, not {}",
            path.display(),
            data.len()
        );
    }
    let dims = match shape {
        [one] => format!("({one},)"),
        _ => format!(
            "({})",
            shape
                .iter()
                .map(usize::to_string)
                .collect::<Vec<_>>()
                .join(", ")
        ),
    };
    let mut header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {dims}, }}");
    // Magic (6) + version (2) + header length (2) + header, padded with spaces to a multiple
    // of 64 and ended by a newline.
    let unpadded = 10 + header.len() + 1;
    header.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    header.push('\n');
    let mut file = std::io::BufWriter::new(
        std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?,
    );
    file.write_all(b"\x93NUMPY\x01\x00")?;
    file.write_all(&u16::try_from(header.len())?.to_le_bytes())?;
    file.write_all(header.as_bytes())?;
    file.write_all(bytemuck::cast_slice(data))?;
    file.flush()?;
    Ok(())
}

/// Reads a `.npy` file written by [`write_npy_f32`] (little-endian f32, C order): its shape
/// and values.
pub fn read_npy_f32(path: &Path) -> Result<(Vec<usize>, Vec<f32>)> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    if bytes.len() < 10 || &bytes[..8] != b"\x93NUMPY\x01\x00" {
        bail!("{} is not a version 1.0 .npy file", path.display());
    }
    let len = usize::from(u16::from_le_bytes([bytes[8], bytes[9]]));
    let header = bytes
        .get(10..10 + len)
        .and_then(|h| std::str::from_utf8(h).ok())
        .context("npy header")?;
    if !header.contains("'descr': '<f4'") || !header.contains("'fortran_order': False") {
        bail!("{}: not little-endian f32 in C order", path.display());
    }
    let dims = header
        .split("'shape': (")
        .nth(1)
        .and_then(|s| s.split(')').next())
        .context("npy shape")?;
    let shape = dims
        .split(',')
        .map(str::trim)
        .filter(|d| !d.is_empty())
        .map(str::parse)
        .collect::<Result<Vec<usize>, _>>()?;
    let data: Vec<f32> = bytes[10 + len..]
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    if data.len() != shape.iter().product::<usize>() {
        bail!(
            "{}: {} values for shape {shape:?}",
            path.display(),
            data.len()
        );
    }
    Ok((shape, data))
}

/// The neutral positions of every primitive, concatenated (`3V` values).
pub fn neutral(rig: &Rig) -> Vec<f32> {
    bytemuck::cast_slice(&crowdmorph_engine::lod::raster::neutral_positions(rig)).to_vec()
}

/// Every target's position deltas as a dense row-major `T × 3V` matrix.
pub fn dense_deltas(rig: &Rig) -> Vec<f32> {
    let n3 = rig.vertex_count() * 3;
    let mut d = vec![0f32; rig.targets.len() * n3];
    let offsets = rig.vertex_offsets();
    for (pi, p) in rig.primitives.iter().enumerate() {
        for t in &p.targets {
            for (i, &vert) in t.vertices.iter().enumerate() {
                let at = t.target as usize * n3 + (offsets[pi] + vert as usize) * 3;
                d[at..at + 3].copy_from_slice(&t.positions[i].to_array());
            }
        }
    }
    d
}

/// Writes `rig` (served as `id`) into `dir` as the Python peer reads it: `manifest.json`,
/// `neutral.npy`, `deltas.npy`, `clip_N.npy` per clip and `lod_masks.npy`.
pub fn export_rig(rig: &Rig, id: &str, dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let v = rig.vertex_count();
    let t = rig.targets.len();
    write_npy_f32(&dir.join("neutral.npy"), &[v, 3], &neutral(rig))?;
    write_npy_f32(&dir.join("deltas.npy"), &[t, 3 * v], &dense_deltas(rig))?;
    let mut clips = Vec::new();
    for (i, c) in rig.clips.iter().enumerate() {
        let frames = c.frames as usize;
        // Frame-major: row f is every target's weight at frame f.
        let mut rows = vec![0f32; frames * t];
        for (f, row) in rows.chunks_exact_mut(t.max(1)).enumerate() {
            c.frame_weights(f as u32, row);
        }
        let file = format!("clip_{i}.npy");
        write_npy_f32(&dir.join(&file), &[frames, t], &rows)?;
        clips.push(serde_json::json!({ "name": c.name, "file": file, "frames": frames }));
    }
    let levels = &rig.lod.levels;
    let mut masks = vec![0f32; levels.len() * t];
    for (l, level) in levels.iter().enumerate() {
        for &target in rig.lod.order.iter().take(level.shapes as usize) {
            masks[l * t + target as usize] = 1.0;
        }
    }
    write_npy_f32(&dir.join("lod_masks.npy"), &[levels.len(), t], &masks)?;
    let manifest = serde_json::json!({
        "rig": id,
        "vertices": v,
        "targets": t,
        "neutral": "neutral.npy",
        "deltas": "deltas.npy",
        "lod_masks": "lod_masks.npy",
        "lod_mesh": levels.iter().map(|l| l.mesh.is_some()).collect::<Vec<_>>(),
        "clips": clips,
    });
    std::fs::write(
        dir.join("manifest.json"),
        serde_json::to_vec_pretty(&manifest)?,
    )?;
    Ok(())
}

/// Writes [`SCRIPTS`] under `dir` and returns `dir`.
pub fn write_scripts(dir: &Path) -> Result<PathBuf> {
    for (path, text) in SCRIPTS {
        let at = dir.join(path);
        if let Some(parent) = at.parent() {
            std::fs::create_dir_all(parent)?;
        }
        std::fs::write(&at, text).with_context(|| format!("writing {}", at.display()))?;
    }
    Ok(dir.to_path_buf())
}

/// Runs `python -c CODE` and returns its stdout, or an error with its stderr (a missing
/// numpy or aiohttp is named there by the scripts).
pub fn run_python(python: &Path, args: &[&std::ffi::OsStr]) -> Result<String> {
    let out = Command::new(python)
        .args(args)
        .env("PYTHONDONTWRITEBYTECODE", "1")
        .stdin(Stdio::null())
        .output()
        .with_context(|| format!("starting {}", python.display()))?;
    if !out.status.success() {
        bail!(
            "{} failed ({}): {}",
            python.display(),
            out.status,
            String::from_utf8_lossy(&out.stderr).trim()
        );
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

/// The dense Python server, running; killed (and reaped) when dropped.
pub struct PythonPeer {
    child: Child,
    /// The loopback port it listens on.
    pub port: u16,
    /// numpy's version in the peer.
    pub numpy: String,
    /// The BLAS library numpy loaded there (a path fragment such as
    /// `openblas-pthread/libblas.so.3`): Debian's numpy runs on whichever `libblas.so.3` is
    /// installed, the reference BLAS unless OpenBLAS is.
    pub blas: String,
}

impl PythonPeer {
    /// Starts `dense_server.py` from `scripts` (see [`write_scripts`]) on the rig exported to
    /// `rig_dir`, with `compute` (`thread` or `inline`), and waits for its `port N` line.
    pub fn start(python: &Path, scripts: &Path, rig_dir: &Path, compute: &str) -> Result<Self> {
        let mut child = Command::new(python)
            .arg(scripts.join("bench/dense_server.py"))
            .arg(rig_dir)
            .args(["--port", "0", "--compute", compute])
            .env("PYTHONDONTWRITEBYTECODE", "1")
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .with_context(|| format!("starting the Python peer with {}", python.display()))?;
        let stdout = child.stdout.take().context("the peer's stdout")?;
        let stderr = child.stderr.take().context("the peer's stderr")?;
        // The guard owns the child from here: any error below kills it.
        let mut peer = PythonPeer {
            child,
            port: 0,
            numpy: String::new(),
            blas: String::new(),
        };
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let mut line = String::new();
            let got = BufReader::new(stdout).read_line(&mut line).map(|_| line);
            let _ = tx.send(got);
        });
        let line = match rx.recv_timeout(START_TIMEOUT) {
            Ok(Ok(line)) => line,
            Ok(Err(e)) => bail!("reading the Python peer's port: {e}"),
            Err(_) => bail!(
                "the Python peer did not listen within {} s",
                START_TIMEOUT.as_secs()
            ),
        };
        // `port N numpy V blas B`.
        let words: Vec<&str> = line.split_whitespace().collect();
        let after = |key: &str| {
            words
                .iter()
                .position(|w| *w == key)
                .and_then(|i| words.get(i + 1))
                .map(|w| w.to_string())
        };
        let Some(port) = after("port").and_then(|p| p.parse().ok()) else {
            // It exited: its stderr says why (a missing package is named there).
            let _ = peer.child.wait();
            let mut err = String::new();
            let _ = BufReader::new(stderr).read_to_string(&mut err);
            bail!("the Python peer did not start: {}", err.trim());
        };
        // Drain stderr so that a chatty peer never blocks on a full pipe.
        std::thread::spawn(move || {
            let mut sink = Vec::new();
            let _ = BufReader::new(stderr).read_to_end(&mut sink);
        });
        peer.port = port;
        peer.numpy = after("numpy").unwrap_or_default();
        peer.blas = after("blas").unwrap_or_default();
        Ok(peer)
    }

    /// The peer's base URL.
    pub fn url(&self) -> String {
        format!("http://127.0.0.1:{}", self.port)
    }
}

impl Drop for PythonPeer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A temporary directory removed when dropped.
pub fn temp_dir(prefix: &str) -> Result<tempfile::TempDir> {
    tempfile::Builder::new()
        .prefix(prefix)
        .tempdir()
        .context("creating a temporary directory")
}

/// Positions of a buffer as f32 (f32 and f16 buffers).
fn positions(format: Format, b: &crowdmorph_proto::FrameBuffer) -> Result<Vec<f32>> {
    match format {
        Format::F32 => Ok(b.positions.to_f32()),
        Format::F16 => Ok(b
            .positions
            .to_u16()
            .into_iter()
            .map(|h| half::f16::from_bits(h).to_f32())
            .collect()),
        Format::Q16 | Format::Q16R => bail!("the Python peer does not serve q16"),
        Format::Weights => bail!("the Python peer does not serve weights"),
    }
}

/// Checks that `peer`'s response is `ours` (same format, buffers, heads) with positions within
/// `tolerance` (absolute, rig units; plus one f16 step of the value for f16 buffers, as the
/// two round slightly different f32 sums). Returns the largest difference found.
pub fn compare_responses(
    ours: &CrowdFrameResponse,
    peer: &CrowdFrameResponse,
    tolerance: f32,
) -> Result<f32> {
    if ours.format != peer.format || ours.normals != peer.normals {
        bail!("format or normals differ");
    }
    if ours.heads != peer.heads {
        bail!("the heads' buffer indices differ");
    }
    if ours.buffers.len() != peer.buffers.len() {
        bail!(
            "{} buffers against the peer's {}",
            ours.buffers.len(),
            peer.buffers.len()
        );
    }
    let mut worst = 0f32;
    for (i, (a, b)) in ours.buffers.iter().zip(&peer.buffers).enumerate() {
        if (&a.rig, &a.clip, a.frame, a.lod, a.vertices)
            != (&b.rig, &b.clip, b.frame, b.lod, b.vertices)
        {
            bail!(
                "buffer {i}: {}/{} frame {} LOD {} against the peer's {}/{} frame {} LOD {}",
                a.rig,
                a.clip,
                a.frame,
                a.lod,
                b.rig,
                b.clip,
                b.frame,
                b.lod
            );
        }
        let (pa, pb) = (positions(ours.format, a)?, positions(peer.format, b)?);
        if pa.len() != pb.len() || pa.len() != a.vertices as usize * 3 {
            bail!("buffer {i}: {} values against {}", pa.len(), pb.len());
        }
        for (x, y) in pa.iter().zip(&pb) {
            let d = (x - y).abs();
            let step = if ours.format == Format::F16 {
                x.abs().max(y.abs()) * f32::powi(2.0, -10)
            } else {
                0.0
            };
            // Written so that a NaN on either side fails too.
            if d.is_nan() || d > tolerance + step {
                bail!("buffer {i}: {x} against the peer's {y} (tolerance {tolerance})");
            }
            worst = worst.max(d);
        }
    }
    Ok(worst)
}

/// Milliseconds of the warm numpy blend (`np.matmul(W, D, out=OUT); OUT += neutral`) over
/// `weights` (`jobs × T`, by target id) on `rig`, median of runs for about `seconds`, timed by
/// `numpy_blend.py` in a `python` subprocess; also the BLAS library numpy loaded.
pub fn numpy_blend_ms(
    python: &Path,
    rig: &Rig,
    weights: &[Vec<f32>],
    seconds: f64,
) -> Result<NumpyTiming> {
    let dir = temp_dir("crowdmorph-numpy-")?;
    let scripts = write_scripts(&dir.path().join("py"))?;
    let data = dir.path().join("data");
    std::fs::create_dir_all(&data)?;
    let v = rig.vertex_count();
    let t = rig.targets.len();
    write_npy_f32(&data.join("neutral.npy"), &[v, 3], &neutral(rig))?;
    write_npy_f32(&data.join("deltas.npy"), &[t, 3 * v], &dense_deltas(rig))?;
    let w: Vec<f32> = weights
        .iter()
        .flat_map(|row| (0..t).map(|i| row.get(i).copied().unwrap_or(0.0)))
        .collect();
    write_npy_f32(&data.join("weights.npy"), &[weights.len(), t], &w)?;
    let started = Instant::now();
    let out = run_python(
        python,
        &[
            scripts.join("bench/numpy_blend.py").as_os_str(),
            data.as_os_str(),
            std::ffi::OsStr::new(&format!("{seconds}")),
        ],
    )?;
    let timing: NumpyTiming = serde_json::from_str(out.trim())
        .with_context(|| format!("numpy_blend.py printed {out:?}"))?;
    tracing::debug!(
        "numpy blend measured in {:.1} s",
        started.elapsed().as_secs_f64()
    );
    Ok(timing)
}

/// What `numpy_blend.py` measured.
#[derive(Clone, Debug, serde::Deserialize, serde::Serialize)]
pub struct NumpyTiming {
    /// Median ms of `np.matmul(W, D, out=OUT); OUT += neutral` into the warm `OUT`.
    pub warm_ms: f64,
    /// Median ms of `W @ D + neutral`, allocating its output each time.
    pub alloc_ms: f64,
    /// The BLAS library numpy loaded (file name), or `unknown`.
    pub blas: String,
    /// numpy's version.
    pub numpy: String,
}

#[cfg(test)]
mod tests {
    // A test that meets an unexpected error should fail loudly, which is what unwrap does.
    #![allow(clippy::unwrap_used)]

    use super::*;

    #[test]
    fn npy_files_round_trip_their_shape_and_values() {
        let dir = temp_dir("crowdmorph-npy-").unwrap();
        for shape in [vec![7], vec![3, 5], vec![2, 3, 4], vec![0, 3]] {
            let n: usize = shape.iter().product();
            let data: Vec<f32> = (0..n).map(|i| i as f32 * 0.5 - 3.25).collect();
            let path = dir.path().join("a.npy");
            write_npy_f32(&path, &shape, &data).unwrap();
            let bytes = std::fs::read(&path).unwrap();
            // numpy requires the data to start at a multiple of 64 bytes.
            assert_eq!((bytes.len() - n * 4) % 64, 0, "header of {shape:?}");
            let (s, d) = read_npy_f32(&path).unwrap();
            assert_eq!((s, d), (shape, data));
        }
        assert!(write_npy_f32(&dir.path().join("b.npy"), &[2, 2], &[1.0]).is_err());
    }

    #[test]
    fn the_export_is_the_rig_dense() {
        let rig = crowdmorph_core::embedded::default_rig();
        let dir = temp_dir("crowdmorph-export-").unwrap();
        export_rig(&rig, "default-head", dir.path()).unwrap();
        let v = rig.vertex_count();
        let t = rig.targets.len();
        let (shape, n) = read_npy_f32(&dir.path().join("neutral.npy")).unwrap();
        assert_eq!(shape, vec![v, 3]);
        assert_eq!(n, neutral(&rig));
        let (shape, d) = read_npy_f32(&dir.path().join("deltas.npy")).unwrap();
        assert_eq!(shape, vec![t, 3 * v]);
        // Every stored sparse delta is at its dense place, and nothing else is non-zero.
        let offsets = rig.vertex_offsets();
        let mut stored = 0;
        for (pi, p) in rig.primitives.iter().enumerate() {
            for st in &p.targets {
                for (i, &vert) in st.vertices.iter().enumerate() {
                    let at = st.target as usize * 3 * v + (offsets[pi] + vert as usize) * 3;
                    assert_eq!(d[at..at + 3], st.positions[i].to_array());
                    stored += st.positions[i]
                        .to_array()
                        .iter()
                        .filter(|x| **x != 0.0)
                        .count();
                }
            }
        }
        assert_eq!(d.iter().filter(|x| **x != 0.0).count(), stored);
        for (i, c) in rig.clips.iter().enumerate() {
            let (shape, rows) = read_npy_f32(&dir.path().join(format!("clip_{i}.npy"))).unwrap();
            assert_eq!(shape, vec![c.frames as usize, t]);
            for f in [0, c.frames - 1] {
                for target in 0..t {
                    assert_eq!(rows[f as usize * t + target], c.weight(target, f));
                }
            }
        }
        let (shape, masks) = read_npy_f32(&dir.path().join("lod_masks.npy")).unwrap();
        assert_eq!(shape, vec![rig.lod.levels.len(), t]);
        for (l, level) in rig.lod.levels.iter().enumerate() {
            let kept = masks[l * t..(l + 1) * t]
                .iter()
                .filter(|m| **m == 1.0)
                .count();
            assert_eq!(kept, level.shapes as usize);
        }
        let manifest: serde_json::Value =
            serde_json::from_slice(&std::fs::read(dir.path().join("manifest.json")).unwrap())
                .unwrap();
        assert_eq!(manifest["rig"], "default-head");
        assert_eq!(manifest["clips"].as_array().unwrap().len(), rig.clips.len());
    }

    #[test]
    fn the_embedded_scripts_are_the_whole_client_package() {
        // A module added to the package but not to SCRIPTS would make the peer's imports fail
        // only at bench time.
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../clients/python");
        for folder in ["src/crowdmorph", "bench"] {
            for entry in std::fs::read_dir(root.join(folder)).unwrap() {
                let name = entry.unwrap().file_name().to_string_lossy().into_owned();
                if name.ends_with(".py") {
                    let path = format!("{folder}/{name}");
                    assert!(
                        SCRIPTS.iter().any(|(p, _)| *p == path),
                        "{path} is missing from pypeer::SCRIPTS"
                    );
                }
            }
        }
    }
}
