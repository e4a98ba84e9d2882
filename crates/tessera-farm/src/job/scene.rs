//! The scene as a job sees it: which scene, from which camera, and on which clock.
//!
//! A job names its scene, optionally a glTF camera and an animation, and sets the clock
//! that maps its frames to scene time (frames per second, and a shutter for motion blur,
//! ARCHITECTURE.md §8 "Time"). Every component that loads a job's scene needs exactly
//! these five things, and needs to turn a frame into the same times: `tessera render`, the
//! coordinator (analysis and technique pilot), the worker (parsing, building and caching
//! scenes per lease). They travel together as one [`JobScene`], from the validated job to
//! the coordinator's lease data and the wire's `Lease`, so there is one rule for a frame's
//! time and one for the shutter's key times.

use super::choice::SceneRef;
use super::settings::Shutter;

/// The scene of a job and its clock.
///
/// ```
/// use tessera_farm::job::{JobScene, SceneRef, Shutter};
///
/// let s = JobScene {
///     source: SceneRef::Builtin("cornell-box".into()),
///     camera: None,
///     fps: 24.0,
///     animation: None,
///     shutter: Some(Shutter { open: -0.25, close: 0.25 }),
/// };
/// assert_eq!(s.frame_seconds(12), 0.5);
/// let keys = s.shutter_seconds(12);
/// assert_eq!(keys.len(), 9);
/// assert_eq!((keys[0], keys[8]), (11.75 / 24.0, 12.25 / 24.0));
/// ```
#[derive(Debug, Clone, PartialEq)]
pub struct JobScene {
    /// The scene: built in, or uploaded (by content hash).
    pub source: SceneRef,
    /// The glTF camera the job renders from, if it names one (default: the scene's first).
    pub camera: Option<String>,
    /// Frames per second, in (0, [`super::MAX_FPS`]]: frame `F` shows the scene at
    /// `F / fps` seconds.
    pub fps: f64,
    /// The glTF animation that plays (name, or else index); `None`: all of them.
    pub animation: Option<String>,
    /// The shutter for motion blur (checked by [`Shutter::check`]); `None`: no blur.
    pub shutter: Option<Shutter>,
}

impl JobScene {
    /// The time of `frame` in seconds: `frame / fps` (ARCHITECTURE.md §8, "Time").
    pub fn frame_seconds(&self, frame: u32) -> f64 {
        f64::from(frame) / self.fps
    }

    /// The shutter's key times of `frame` in seconds ([`Shutter::key_frames`] over the
    /// fps), at which motion blur evaluates the scene; empty without a shutter.
    pub fn shutter_seconds(&self, frame: u32) -> Vec<f64> {
        self.shutter.map_or_else(Vec::new, |s| {
            s.key_frames(frame)
                .into_iter()
                .map(|f| f / self.fps)
                .collect()
        })
    }

    /// What a parsed scene depends on besides time: the scene and the camera. A key for
    /// caches of parsed scenes (`SCENE` or `SCENE#CAMERA`).
    pub fn parse_key(&self) -> String {
        match &self.camera {
            Some(c) => format!("{}#{c}", self.source),
            None => self.source.to_string(),
        }
    }

    /// What the scene of `frame` depends on: [`JobScene::parse_key`], the frame's time,
    /// the animation and the shutter. A key for caches of scenes built at a frame (only
    /// animated scenes need it: a static scene is the same at every frame).
    pub fn frame_key(&self, frame: u32) -> String {
        format!(
            "{}@{}#{}#{:?}",
            self.parse_key(),
            self.frame_seconds(frame),
            self.animation.as_deref().unwrap_or(""),
            self.shutter.map(<[f64; 2]>::from)
        )
    }
}
