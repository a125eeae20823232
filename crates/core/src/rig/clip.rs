//! Animation clips: the paper's animation texture.
//!
//! A clip is a weight table of `targets × frames` float32 values (Costigan et al. 2016, Fig. 4:
//! one row per blendshape, one column per frame), sampled at a fixed rate. Rows cover every
//! rig-wide target so an engine can index the table without a per-clip map; targets a source does
//! not animate hold the rig's default weight.

use std::sync::Arc;

use serde::{Deserialize, Serialize};

/// Frames per second used when baking a keyframed timeline.
pub const DEFAULT_FPS: f32 = 30.0;

/// Most frames a clip may hold (about 15 minutes at 60 fps); bigger tables are refused.
pub const MAX_FRAMES: usize = 1 << 16;

/// A baked animation clip over all rig-wide targets.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Clip {
    /// Clip name (unique within a rig).
    pub name: String,
    /// Sampling rate of the table.
    pub fps: f32,
    /// Number of frames (columns).
    pub frames: u32,
    /// Number of targets (rows); equals the rig's target count.
    pub targets: u32,
    /// Row-major `targets × frames`: the weight of target `t` at frame `f` is
    /// `weights[t * frames + f]`. Shared, not copied, by every version of a rig and every
    /// mesh level derived from it: a clip table is often the largest array a rig has.
    pub weights: Arc<Vec<f32>>,
    /// The clip's node transforms, for a rig with a skeleton whose nodes it animates
    /// (skipped by serde: the store keeps it beside the clip).
    #[serde(skip)]
    pub joints: Option<Arc<super::JointTable>>,
}

/// What to do with a frame number past the end of a clip.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FrameMode {
    /// Loop: frame `f` plays frame `f mod frames` (negative frames count back from the end).
    #[default]
    Wrap,
    /// Hold the last (or first) frame.
    Clamp,
    /// Refuse frames outside `0..frames`.
    Strict,
}

/// Why a clip is not acceptable, or a frame cannot be played.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum ClipError {
    /// A table whose size does not match its declared shape.
    #[error("clip {clip:?}: {problem}")]
    Malformed {
        /// Clip name.
        clip: String,
        /// What is wrong.
        problem: String,
    },
    /// A frame outside the clip while the frame mode forbids wrapping or clamping.
    #[error("frame {frame} is past the end of clip {clip:?} ({frames} frames) and wrap is off")]
    FrameOutOfRange {
        /// Clip name.
        clip: String,
        /// Requested frame.
        frame: i64,
        /// Frames in the clip.
        frames: u32,
    },
}

impl Clip {
    /// Builds a clip from a row-major `targets × frames` table, checking its shape and values.
    pub fn new(
        name: impl Into<String>,
        fps: f32,
        targets: usize,
        frames: usize,
        weights: Vec<f32>,
    ) -> Result<Self, ClipError> {
        let clip = Clip {
            name: name.into(),
            fps,
            frames: u32::try_from(frames).unwrap_or(u32::MAX),
            targets: u32::try_from(targets).unwrap_or(u32::MAX),
            weights: Arc::new(weights),
            joints: None,
        };
        clip.validate(targets)?;
        Ok(clip)
    }

    /// Builds a clip from frame-major rows (one `Vec` of `targets` weights per frame), the shape
    /// CSV and JSON sources arrive in.
    pub fn from_frames(
        name: impl Into<String>,
        fps: f32,
        targets: usize,
        rows: &[Vec<f32>],
    ) -> Result<Self, ClipError> {
        let frames = rows.len();
        let mut weights = vec![0.0; targets * frames];
        for (f, row) in rows.iter().enumerate() {
            for (t, &w) in row.iter().enumerate().take(targets) {
                weights[t * frames + f] = w;
            }
        }
        Self::new(name, fps, targets, frames, weights)
    }

    /// Weight of target `t` at frame `f` (both in range).
    #[inline]
    pub fn weight(&self, target: usize, frame: u32) -> f32 {
        self.weights[target * self.frames as usize + frame as usize]
    }

    /// Copies the weights of every target at frame `f` into `out` (length = targets).
    pub fn frame_weights(&self, frame: u32, out: &mut [f32]) {
        let frames = self.frames as usize;
        for (t, w) in out.iter_mut().enumerate().take(self.targets as usize) {
            *w = self.weights[t * frames + frame as usize];
        }
    }

    /// Duration in seconds of the baked table (time of the last frame).
    pub fn duration(&self) -> f32 {
        (self.frames.saturating_sub(1)) as f32 / self.fps
    }

    /// Maps a requested frame to a frame of the table according to `mode`.
    pub fn resolve_frame(&self, frame: i64, mode: FrameMode) -> Result<u32, ClipError> {
        let n = i64::from(self.frames.max(1));
        match mode {
            FrameMode::Wrap => Ok(frame.rem_euclid(n) as u32),
            FrameMode::Clamp => Ok(frame.clamp(0, n - 1) as u32),
            FrameMode::Strict if (0..n).contains(&frame) => Ok(frame as u32),
            FrameMode::Strict => Err(ClipError::FrameOutOfRange {
                clip: self.name.clone(),
                frame,
                frames: self.frames,
            }),
        }
    }

    /// Checks the table's shape against the rig's target count, and its values.
    pub fn validate(&self, rig_targets: usize) -> Result<(), ClipError> {
        let bad = |problem: String| ClipError::Malformed {
            clip: self.name.clone(),
            problem,
        };
        if self.name.is_empty() {
            return Err(bad("clip name is empty".into()));
        }
        if !(self.fps.is_finite() && self.fps > 0.0 && self.fps <= 1000.0) {
            return Err(bad(format!("fps {} must be in (0, 1000]", self.fps)));
        }
        if self.frames == 0 {
            return Err(bad("clip has no frames".into()));
        }
        if self.frames as usize > MAX_FRAMES {
            return Err(bad(format!(
                "{} frames (at most {MAX_FRAMES})",
                self.frames
            )));
        }
        if self.targets as usize != rig_targets {
            return Err(bad(format!(
                "table has {} rows, rig has {rig_targets} targets",
                self.targets
            )));
        }
        let expected = self.targets as usize * self.frames as usize;
        if self.weights.len() != expected {
            return Err(bad(format!(
                "{} weights for {} targets × {} frames",
                self.weights.len(),
                self.targets,
                self.frames
            )));
        }
        if let Some(i) = self.weights.iter().position(|w| !w.is_finite()) {
            let frames = self.frames as usize;
            return Err(bad(format!(
                "weight of target {} at frame {} is not finite",
                i / frames,
                i % frames
            )));
        }
        Ok(())
    }
}

/// A rig's clips by name: clip indices sorted by name, so that finding a clip is a binary
/// search, not a scan of every clip. A crowd frame or a session tick looks up a clip for each
/// head, and a rig may hold hundreds of thousands of tiny clips (a one-frame clip of a
/// one-target rig is a few bytes of table): scanned per head, a 10,000-head tick on such a rig
/// compared billions of names. Four bytes per clip, built once per rig version.
#[derive(Clone, Debug, Default)]
pub struct ClipIndex {
    /// Clip indices ordered by name; equal names keep the clips' order.
    order: Vec<u32>,
}

impl ClipIndex {
    /// The index of `clips`.
    pub fn new(clips: &[Clip]) -> ClipIndex {
        let mut order: Vec<u32> = (0..clips.len() as u32).collect();
        // Stable: of two clips with one name the earlier comes first, as a scan finds it.
        order.sort_by(|&a, &b| clips[a as usize].name.cmp(&clips[b as usize].name));
        ClipIndex { order }
    }

    /// The first clip of `clips` (the slice the index was built from) named `name`.
    pub fn find(&self, clips: &[Clip], name: &str) -> Option<usize> {
        let name_of = |i: u32| clips.get(i as usize).map_or("", |c| c.name.as_str());
        let k = self.order.partition_point(|&i| name_of(i) < name);
        self.order
            .get(k)
            .filter(|&&i| name_of(i) == name && (i as usize) < clips.len())
            .map(|&i| i as usize)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_clip_index_finds_what_a_scan_finds() {
        let clip = |name: &str| Clip::new(name, 30.0, 1, 1, vec![0.0]).expect("a one-frame clip");
        // Unsorted names, a repeated name (the first one wins, as in a scan) and names that
        // sort around the ones present.
        let clips: Vec<Clip> = ["talk", "blink", "talk", "a", "smile", "Talk", "talk_2"]
            .into_iter()
            .map(clip)
            .collect();
        let index = ClipIndex::new(&clips);
        let scan = |name: &str| clips.iter().position(|c| c.name == name);
        for name in [
            "talk", "blink", "a", "smile", "Talk", "talk_2", "", "b", "zzz", "tal",
        ] {
            assert_eq!(index.find(&clips, name), scan(name), "{name:?}");
        }
        assert_eq!(index.find(&clips, "talk"), Some(0));
        assert_eq!(ClipIndex::new(&[]).find(&[], "talk"), None);
    }

    #[test]
    fn frame_modes() {
        let c = Clip::new("c", 30.0, 1, 4, vec![0.0, 1.0, 2.0, 3.0]).expect("valid clip");
        assert_eq!(c.resolve_frame(5, FrameMode::Wrap), Ok(1));
        assert_eq!(c.resolve_frame(-1, FrameMode::Wrap), Ok(3));
        assert_eq!(c.resolve_frame(9, FrameMode::Clamp), Ok(3));
        assert_eq!(c.resolve_frame(-9, FrameMode::Clamp), Ok(0));
        assert_eq!(c.resolve_frame(3, FrameMode::Strict), Ok(3));
        assert!(c.resolve_frame(4, FrameMode::Strict).is_err());
    }

    #[test]
    fn table_layout_is_targets_by_frames() {
        let rows = vec![vec![1.0, 2.0], vec![3.0, 4.0], vec![5.0, 6.0]];
        let c = Clip::from_frames("c", 30.0, 2, &rows).expect("valid clip");
        assert_eq!(*c.weights, vec![1.0, 3.0, 5.0, 2.0, 4.0, 6.0]);
        assert_eq!(c.weight(1, 2), 6.0);
        let mut w = [0.0; 2];
        c.frame_weights(1, &mut w);
        assert_eq!(w, [3.0, 4.0]);
    }

    #[test]
    fn rejects_bad_tables() {
        assert!(Clip::new("c", 30.0, 2, 2, vec![0.0; 3]).is_err());
        assert!(Clip::new("c", 30.0, 1, 1, vec![f32::NAN]).is_err());
        assert!(Clip::new("c", 0.0, 1, 1, vec![0.0]).is_err());
        assert!(Clip::new("c", 30.0, 1, 0, vec![]).is_err());
    }
}
