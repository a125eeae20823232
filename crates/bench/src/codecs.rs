//! `bench codecs`: the ways a head's q16 buffer can travel, measured on real frames of a rig's
//! clips — bytes per head, and the CPU a server pays to encode and a client to decode, per
//! head, on one core. Each row is checked lossless (decoded = q16, bit for bit) before it is
//! reported.
//!
//! What is compared, all on the same frames:
//! - the reference a buffer is coded against: none (plain q16), the rig's neutral in the same
//!   box (HTTP's `q16r`), or the same head's previous frame (a session's temporal residuals);
//! - the coding of the residual: the wire's byte planes (`zigzag`, low bytes then high bytes),
//!   or meshoptimizer's vertex codec (what `EXT_meshopt_compression` and three.js decode; v1,
//!   vertices padded to 8 bytes as its 4-byte stride rule asks);
//! - the entropy coder after it: none, zstd at several levels (negative levels are zstd's fast
//!   modes), or zlib at its fastest (what a browser's `DecompressionStream("deflate")` reads).

use std::io::Write;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use serde::Serialize;

use crowdmorph_core::rig::Rig;
use crowdmorph_engine::{BlendJob, OutputSpec, Precision, VertexData, WeightBatch};
use crowdmorph_import::clips::{ClipOptions, clip_from_csv, clip_from_json};

/// What to measure (also `crowdmorph bench codecs`' flags).
#[derive(Clone, Debug, Default, clap::Args)]
pub struct CodecBenchOptions {
    /// Play these clips (`.csv`/`.json` files in a folder, named by file stem) instead of the
    /// rig's own (names the rig lacks are ignored, as `bench http --clips` uploads them).
    #[arg(long, value_name = "DIR")]
    pub clips: Option<std::path::PathBuf>,
    /// Frames in all, consecutive runs from every clip.
    #[arg(long, default_value_t = 240)]
    pub frames: usize,
    /// zstd levels of the residual rows (negative: its fast modes).
    #[arg(
        long,
        value_delimiter = ',',
        allow_hyphen_values = true,
        default_value = "-5,-1,1,3"
    )]
    pub zstd_levels: Vec<i32>,
}

/// One way of sending a head.
#[derive(Clone, Debug, Serialize)]
pub struct CodecRow {
    /// What the buffer is coded against: `none`, `neutral` or `previous`.
    pub reference: String,
    /// `q16`, `planes` (the wire's byte planes) or `meshopt` (vertex codec v1).
    pub coding: String,
    /// `none`, `zstd L` or `zlib 1`.
    pub entropy: String,
    /// Mean bytes per head.
    pub bytes_per_head: f64,
    /// q16's bytes ÷ this row's.
    pub smaller_than_q16: f64,
    /// Median encode time per head (residual, coding, entropy), microseconds, one core.
    pub encode_us: f64,
    /// Median decode time per head back to q16, microseconds, one core.
    pub decode_us: f64,
    /// q16 bytes encoded per second of one core, MB/s.
    pub encode_mb_per_s: f64,
}

/// The measurement.
#[derive(Clone, Debug, Serialize)]
pub struct CodecReport {
    /// The rig's name and vertices (all primitives).
    pub rig: String,
    /// Vertices of one buffer.
    pub vertices: usize,
    /// Frames measured (each row codes every one of them).
    pub frames: usize,
    /// Clips they came from.
    pub clips: Vec<String>,
    /// The rows, in the order of [`CodecReport::rows`]'s construction.
    pub rows: Vec<CodecRow>,
}

/// Reads every `.csv` and `.json` clip in `dir` for `rig` (names it lacks ignored).
pub fn read_clips(rig: &Rig, dir: &std::path::Path) -> Result<Vec<crowdmorph_core::rig::Clip>> {
    let options = ClipOptions {
        ignore_unknown: true,
        ..ClipOptions::default()
    };
    let mut clips = Vec::new();
    for (path, name, csv) in super::server::clip_files(dir)? {
        let bytes = std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
        let import = if csv {
            clip_from_csv(rig, &name, &bytes, &options)
        } else {
            clip_from_json(rig, &name, &bytes, &options)
        }
        .with_context(|| format!("importing {}", path.display()))?;
        clips.push(import.clip);
    }
    Ok(clips)
}

/// The frames measured: consecutive runs of every clip (so that each frame but a run's first
/// has its previous frame), as q16 in the server's box, and the neutral in the same box.
struct Frames {
    /// Per frame its components, and whether the frame before it in the list is its previous.
    q16: Vec<(Vec<i16>, bool)>,
    neutral: Vec<i16>,
    clips: Vec<String>,
}

fn frames(rig: Rig, opt: &CodecBenchOptions) -> Result<Frames> {
    let mut rig = rig;
    if let Some(dir) = &opt.clips {
        rig.clips = read_clips(&rig, dir)?;
    }
    rig.validate().context("the rig with its clips")?;
    if rig.clips.is_empty() {
        bail!("the rig has no clips to play (give --clips DIR)");
    }
    let qbox = crowdmorph_server::registry::quantization_box(&rig);
    let rig = Arc::new(rig);
    let prepared = crowdmorph_engine::Engine::cpu()
        .prepare(rig.clone())
        .context("preparing the rig")?;
    let spec = OutputSpec {
        normals: false,
        precision: Precision::Q16(qbox),
    };
    let total: usize = rig.clips.iter().map(|c| c.frames as usize).sum();
    let budget = opt.frames.max(2);
    let mut jobs = Vec::new();
    let mut firsts = Vec::new();
    for (ci, c) in rig.clips.iter().enumerate() {
        // Each clip's share of the frames, from its start.
        let n = ((c.frames as usize * budget).div_ceil(total.max(1))).clamp(1, c.frames as usize);
        for f in 0..n {
            firsts.push(f == 0);
            jobs.push(BlendJob::frame(ci as u32, f as u32, 0));
        }
    }
    jobs.truncate(budget);
    firsts.truncate(budget);
    let mut q16 = Vec::with_capacity(jobs.len());
    for (chunk, first) in jobs.chunks(64).zip(firsts.chunks(64)) {
        let batch = WeightBatch::gather(&rig, chunk)?;
        let out = prepared.cpu().evaluate(&batch, spec)?;
        let VertexData::Q16(all, _) = out.positions else {
            bail!("the engine did not write q16");
        };
        let v3 = out.vertices * 3;
        for (j, f) in first.iter().enumerate() {
            q16.push((all[j * v3..(j + 1) * v3].to_vec(), !f));
        }
    }
    let neutral = prepared.q16_reference(qbox)?;
    Ok(Frames {
        q16,
        neutral,
        clips: rig.clips.iter().map(|c| c.name.clone()).collect(),
    })
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Reference {
    None,
    Neutral,
    Previous,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Coding {
    Q16,
    Planes,
    Meshopt,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Entropy {
    None,
    Zstd(i32),
    Zlib,
}

fn name_of(r: Reference, c: Coding, e: Entropy) -> (String, String, String) {
    let r = match r {
        Reference::None => "none",
        Reference::Neutral => "neutral",
        Reference::Previous => "previous",
    };
    let c = match c {
        Coding::Q16 => "q16",
        Coding::Planes => "planes",
        Coding::Meshopt => "meshopt",
    };
    let e = match e {
        Entropy::None => "none".to_string(),
        Entropy::Zstd(l) => format!("zstd {l}"),
        Entropy::Zlib => "zlib 1".to_string(),
    };
    (r.to_string(), c.to_string(), e)
}

/// `q` coded against `reference` (or alone) the `c` way: the bytes before entropy coding.
fn code(q: &[i16], reference: Option<&[i16]>, c: Coding) -> Result<Vec<u8>> {
    match c {
        Coding::Q16 => Ok(bytemuck::cast_slice(q).to_vec()),
        Coding::Planes => {
            let zero;
            let r = match reference {
                Some(r) => r,
                None => {
                    zero = vec![0i16; q.len()];
                    &zero
                }
            };
            let mut out = vec![0u8; 2 * q.len()];
            crowdmorph_proto::q16r_encode(q, r, &mut out);
            Ok(out)
        }
        Coding::Meshopt => {
            let vertices: Vec<[i16; 4]> = q
                .chunks_exact(3)
                .enumerate()
                .map(|(v, p)| {
                    let d = |a: usize| match reference {
                        Some(r) => p[a].wrapping_sub(r[3 * v + a]),
                        None => p[a],
                    };
                    [d(0), d(1), d(2), 0]
                })
                .collect();
            meshopt::encode_vertex_buffer_level(&vertices, 2, Some(1))
                .map_err(|e| anyhow::anyhow!("meshopt: {e:?}"))
        }
    }
}

/// The inverse of [`code`].
fn uncode(bytes: &[u8], n: usize, reference: Option<&[i16]>, c: Coding) -> Result<Vec<i16>> {
    match c {
        Coding::Q16 => Ok(bytemuck::pod_collect_to_vec(bytes)),
        Coding::Planes => {
            let zero;
            let r = match reference {
                Some(r) => r,
                None => {
                    zero = vec![0i16; n];
                    &zero
                }
            };
            crowdmorph_proto::q16r_decode(bytes, r).map_err(|e| anyhow::anyhow!("{e}"))
        }
        Coding::Meshopt => {
            let v: Vec<[i16; 4]> = meshopt::decode_vertex_buffer(bytes, n / 3)
                .map_err(|e| anyhow::anyhow!("meshopt: {e:?}"))?;
            Ok(v.iter()
                .enumerate()
                .flat_map(|(i, p)| {
                    [0, 1, 2].map(|a| match reference {
                        Some(r) => p[a].wrapping_add(r[3 * i + a]),
                        None => p[a],
                    })
                })
                .collect())
        }
    }
}

fn squeeze(bytes: Vec<u8>, e: Entropy) -> Result<Vec<u8>> {
    Ok(match e {
        Entropy::None => bytes,
        Entropy::Zstd(l) => zstd::bulk::compress(&bytes, l)?,
        Entropy::Zlib => {
            let mut z = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::fast());
            z.write_all(&bytes)?;
            z.finish()?
        }
    })
}

fn unsqueeze(bytes: &[u8], len: usize, e: Entropy) -> Result<Vec<u8>> {
    Ok(match e {
        Entropy::None => bytes.to_vec(),
        Entropy::Zstd(_) => zstd::bulk::decompress(bytes, len)?,
        Entropy::Zlib => {
            use std::io::Read;
            let mut out = Vec::with_capacity(len);
            flate2::read::ZlibDecoder::new(bytes).read_to_end(&mut out)?;
            out
        }
    })
}

/// Runs the benchmark on `rig` (its own clips, or `opt.clips`).
pub fn bench_codecs(rig: Rig, opt: &CodecBenchOptions) -> Result<CodecReport> {
    let name = rig.name.clone();
    let f = frames(rig, opt)?;
    let Some((first, _)) = f.q16.first() else {
        bail!("no frames");
    };
    let n = first.len();
    let q16_bytes = (2 * n) as f64;
    let mut variants: Vec<(Reference, Coding, Entropy)> = vec![
        (Reference::None, Coding::Q16, Entropy::None),
        (Reference::None, Coding::Q16, Entropy::Zstd(1)),
        (Reference::None, Coding::Meshopt, Entropy::None),
        (Reference::None, Coding::Meshopt, Entropy::Zstd(1)),
    ];
    for r in [Reference::Neutral, Reference::Previous] {
        for &l in &opt.zstd_levels {
            variants.push((r, Coding::Planes, Entropy::Zstd(l)));
        }
        variants.push((r, Coding::Planes, Entropy::Zlib));
        variants.push((r, Coding::Meshopt, Entropy::None));
        variants.push((r, Coding::Meshopt, Entropy::Zstd(1)));
        variants.push((r, Coding::Meshopt, Entropy::Zlib));
    }
    let mut rows = Vec::new();
    for (r, c, e) in variants {
        let mut bytes = 0usize;
        let mut heads = 0usize;
        let mut enc = Vec::new();
        let mut dec = Vec::new();
        for (i, (q, has_prev)) in f.q16.iter().enumerate() {
            let reference: Option<&[i16]> = match r {
                Reference::None => None,
                Reference::Neutral => Some(&f.neutral),
                Reference::Previous if *has_prev => Some(&f.q16[i - 1].0),
                // A run's first frame has no previous one: not a temporal residual.
                Reference::Previous => continue,
            };
            let t = Instant::now();
            let coded = code(q, reference, c)?;
            let raw_len = coded.len();
            let wire = squeeze(coded, e)?;
            enc.push(t.elapsed().as_secs_f64() * 1e6);
            let t = Instant::now();
            let back = uncode(&unsqueeze(&wire, raw_len, e)?, n, reference, c)?;
            dec.push(t.elapsed().as_secs_f64() * 1e6);
            if back != *q {
                bail!("{r:?} {c:?} {e:?} is not lossless at frame {i}");
            }
            bytes += wire.len();
            heads += 1;
        }
        let per_head = bytes as f64 / heads.max(1) as f64;
        let (reference, coding, entropy) = name_of(r, c, e);
        let encode_us = super::sample::Samples::new(enc).median();
        rows.push(CodecRow {
            reference,
            coding,
            entropy,
            bytes_per_head: per_head,
            smaller_than_q16: q16_bytes / per_head.max(1.0),
            encode_us,
            decode_us: super::sample::Samples::new(dec).median(),
            encode_mb_per_s: q16_bytes / encode_us.max(1e-9),
        });
    }
    Ok(CodecReport {
        rig: name,
        vertices: n / 3,
        frames: f.q16.len(),
        clips: f.clips,
        rows,
    })
}

impl std::fmt::Display for CodecReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "bench codecs: rig {} ({} vertices), {} frames of clips {}; one core, positions only",
            self.rig,
            self.vertices,
            self.frames,
            self.clips.join(", ")
        )?;
        writeln!(
            f,
            "  {:<9} {:<8} {:<8} {:>11} {:>8} {:>10} {:>10} {:>10}",
            "reference",
            "coding",
            "entropy",
            "bytes/head",
            "× q16",
            "encode µs",
            "decode µs",
            "enc MB/s"
        )?;
        for r in &self.rows {
            writeln!(
                f,
                "  {:<9} {:<8} {:<8} {:>11.0} {:>8.2} {:>10.1} {:>10.1} {:>10.0}",
                r.reference,
                r.coding,
                r.entropy,
                r.bytes_per_head,
                r.smaller_than_q16,
                r.encode_us,
                r.decode_us,
                r.encode_mb_per_s
            )?;
        }
        Ok(())
    }
}
