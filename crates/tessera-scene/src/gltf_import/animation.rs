//! Step 3b, animation (spec "Animations" and "Appendix C: Interpolation"): the pose of the
//! scene at one time. Every channel of the chosen animations is sampled at
//! [`SceneTime::seconds`] once, when the scene is built, into a [`Pose`]: animated
//! translation, rotation and scale per node and animated morph-target weights per node.
//! The scene-graph walk then uses the pose instead of the node's own TRS, so cameras,
//! lights and meshes all move; skins and morph targets read the pose in the `deform` step.
//!
//! Rules:
//! - Which animations play: all of them (a file exported from Blender has one animation
//!   per action, e.g. one per object, and a user expects them all to move), unless the job
//!   names one ([`SceneTime::animation`]: its name, or else its index). When two channels
//!   target the same node property, the later one (animation order, then channel order)
//!   wins.
//! - The time is rounded to f32, the precision of the keyframe times, so a frame lands
//!   exactly on the keyframe written for it.
//! - Times outside an animation's keyframes clamp to its first or last keyframe (spec
//!   "Animations": "the animated values are clamped"), so t = 0 shows the first keyframe
//!   of a Blender export (which writes frame 1 at t = 1/24).
//! - `STEP` holds the keyframe value; `LINEAR` interpolates linearly, rotations by
//!   spherical linear interpolation along the shorter arc, normalized; `CUBICSPLINE`
//!   is the cubic Hermite spline of Appendix C, whose in- and out-tangents are per second
//!   and are therefore scaled by the keyframe interval `t_{k+1} - t_k`; its rotations
//!   are normalized after interpolation.
//! - An animated node must use TRS, not `matrix` (spec "Animations": a node targeted by
//!   an animation must not have a matrix); a `weights` channel needs a node with a mesh
//!   with morph targets. Keyframe times must be strictly increasing and finite, and every
//!   output accessor must have the count the interpolation implies; each violation is an
//!   error naming the animation, the channel and the field.
//!
//! A file without animations gives an empty pose, and the import is then exactly what it
//! was before animations existed.

use super::{Importer, Res};
use glam::{DQuat, DVec3};
use gltf::json;
use json::animation::{Interpolation, Property};
use json::validation::Checked;
use std::collections::HashMap;

/// The time at which a scene is evaluated, and which animation plays.
///
/// `Default` is t = 0 with every animation playing: the first keyframe of every channel.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SceneTime {
    /// Seconds since the start of the animations: `frame / fps` for a frame of a job.
    pub seconds: f64,
    /// The animation that plays, by name or else by index; `None`: all of them.
    pub animation: Option<String>,
}

impl SceneTime {
    /// The time of `frame` at `fps` frames per second, every animation playing.
    pub fn frame(frame: u32, fps: f64) -> Self {
        Self {
            seconds: f64::from(frame) / fps,
            animation: None,
        }
    }
}

/// Animated node properties at one time; what is not here keeps the node's own value.
#[derive(Debug, Default)]
pub(super) struct Pose {
    /// Per node: the animated translation, rotation and scale.
    pub(super) trs: HashMap<usize, AnimatedTrs>,
    /// Per node: the animated morph-target weights.
    pub(super) weights: HashMap<usize, Vec<f32>>,
}

/// The animated parts of one node's transform.
#[derive(Debug, Default, Clone, Copy)]
pub(super) struct AnimatedTrs {
    pub(super) translation: Option<DVec3>,
    pub(super) rotation: Option<DQuat>,
    pub(super) scale: Option<DVec3>,
}

impl Importer<'_> {
    /// Samples every channel of the animations chosen by `time` (see the module docs).
    pub(super) fn evaluate_animations(&self, time: &SceneTime) -> Res<Pose> {
        let mut pose = Pose::default();
        if !time.seconds.is_finite() {
            return self.err(format!("time {} s is not finite", time.seconds));
        }
        let animations = &self.root.animations;
        let chosen: Vec<usize> = match &time.animation {
            None => (0..animations.len()).collect(),
            Some(wanted) => {
                let by_name = animations
                    .iter()
                    .position(|a| a.name.as_deref() == Some(wanted.as_str()));
                let by_index = wanted
                    .parse::<usize>()
                    .ok()
                    .filter(|&i| i < animations.len());
                match by_name.or(by_index) {
                    Some(i) => vec![i],
                    None => {
                        let names: Vec<String> = animations
                            .iter()
                            .enumerate()
                            .map(|(i, a)| format!("{i} {:?}", a.name.as_deref().unwrap_or("")))
                            .collect();
                        return self.err(format!(
                            "animation {wanted:?}: no animation has that name or index; {}",
                            if names.is_empty() {
                                "the file has no animations".to_string()
                            } else {
                                format!("available: {}", names.join(", "))
                            }
                        ));
                    }
                }
            }
        };
        // Keyframe times are f32 in the file (spec "Animations": input accessors are
        // floats); the time is rounded to f32 as well, so that frame F lands exactly on a
        // keyframe an exporter wrote at F / fps (11 / 24 in f64 is just below its f32).
        let t = f64::from(time.seconds as f32);
        for ai in chosen {
            let anim = &animations[ai];
            for (ci, channel) in anim.channels.iter().enumerate() {
                let what = format!("animation {ai} channel {ci}");
                self.evaluate_channel(anim, channel, &what, t, &mut pose)?;
            }
        }
        Ok(pose)
    }

    /// Samples one channel at `t` into `pose`.
    fn evaluate_channel(
        &self,
        anim: &json::Animation,
        channel: &json::animation::Channel,
        what: &str,
        t: f64,
        pose: &mut Pose,
    ) -> Res<()> {
        let si = channel.sampler.value();
        let Some(sampler) = anim.samplers.get(si) else {
            return self.err(format!(
                "{what}: sampler {si} is past the end ({} samplers)",
                anim.samplers.len()
            ));
        };
        let ni = channel.target.node.value();
        let Some(node) = self.root.nodes.get(ni) else {
            return self.err(format!(
                "{what}: target.node {ni} is past the end ({} nodes)",
                self.root.nodes.len()
            ));
        };
        let Checked::Valid(path) = channel.target.path else {
            return self.err(format!("{what}: invalid target.path"));
        };
        let Checked::Valid(interpolation) = sampler.interpolation else {
            return self.err(format!("{what}: sampler {si} has an invalid interpolation"));
        };
        if path != Property::MorphTargetWeights && node.matrix.is_some() {
            return self.err(format!(
                "{what}: node {ni} is animated but has a matrix; animated nodes must use \
                 translation/rotation/scale (spec \"Animations\")"
            ));
        }
        let times: Vec<f32> = self
            .read_floats::<1>(sampler.input.value(), &format!("{what} sampler {si} input"))?
            .into_iter()
            .map(|[v]| v)
            .collect();
        if times.is_empty() {
            return self.err(format!("{what}: sampler {si} input has no keyframes"));
        }
        if let Some(k) = times.windows(2).position(|w| w[1] <= w[0]) {
            return self.err(format!(
                "{what}: sampler {si} input times are not strictly increasing at keyframe {} \
                 ({} after {})",
                k + 1,
                times[k + 1],
                times[k]
            ));
        }
        let output = sampler.output.value();
        let out_what = format!("{what} sampler {si} output");
        let cubic = interpolation == Interpolation::CubicSpline;
        // Elements per keyframe: a value, or (in-tangent, value, out-tangent).
        let per_key = if cubic { 3 } else { 1 };
        let keys = times.len();
        let spline = Spline {
            times: &times,
            interpolation,
        };
        match path {
            Property::Translation | Property::Scale => {
                let v = self.read_floats::<3>(output, &out_what)?;
                self.check_output_count(v.len(), keys * per_key, &out_what)?;
                let flat: Vec<f64> = v.iter().flatten().map(|&c| f64::from(c)).collect();
                let mut out = [0.0; 3];
                spline.sample(&flat, 3, t, &mut out);
                let entry = pose.trs.entry(ni).or_default();
                if path == Property::Translation {
                    entry.translation = Some(DVec3::from(out));
                } else {
                    entry.scale = Some(DVec3::from(out));
                }
            }
            Property::Rotation => {
                let v = self.read_floats::<4>(output, &out_what)?;
                self.check_output_count(v.len(), keys * per_key, &out_what)?;
                let flat: Vec<f64> = v.iter().flatten().map(|&c| f64::from(c)).collect();
                let q = spline.sample_rotation(&flat, t);
                let Some(q) = q else {
                    return self.err(format!(
                        "{out_what}: the rotation at t = {t} s has zero length"
                    ));
                };
                pose.trs.entry(ni).or_default().rotation = Some(q);
            }
            Property::MorphTargetWeights => {
                let targets = self.morph_target_count(ni, what)?;
                let v = self.read_floats::<1>(output, &out_what)?;
                self.check_output_count(v.len(), keys * per_key * targets, &out_what)?;
                let flat: Vec<f64> = v.iter().map(|&[c]| f64::from(c)).collect();
                let mut out = vec![0.0; targets];
                spline.sample(&flat, targets, t, &mut out);
                pose.weights
                    .insert(ni, out.into_iter().map(|w| w as f32).collect());
            }
        }
        Ok(())
    }

    /// An error unless an output accessor has `want` elements.
    fn check_output_count(&self, got: usize, want: usize, what: &str) -> Res<()> {
        if got != want {
            return self.err(format!(
                "{what}: has {got} elements, but the keyframes and interpolation need {want}"
            ));
        }
        Ok(())
    }

    /// The number of morph targets of node `ni`'s mesh (the same for every primitive,
    /// spec "Meshes > Morph Targets"), for a `weights` channel.
    fn morph_target_count(&self, ni: usize, what: &str) -> Res<usize> {
        let mesh = self.root.nodes[ni]
            .mesh
            .and_then(|m| self.root.meshes.get(m.value()));
        let Some(mesh) = mesh else {
            return self.err(format!(
                "{what}: animates the weights of node {ni}, which has no mesh"
            ));
        };
        let count = mesh
            .primitives
            .first()
            .and_then(|p| p.targets.as_ref())
            .map_or(0, Vec::len);
        if count == 0 {
            return self.err(format!(
                "{what}: animates the weights of node {ni}, whose mesh has no morph targets"
            ));
        }
        Ok(count)
    }
}

/// One sampler's keyframe times and interpolation (spec "Animations", Appendix C).
pub(super) struct Spline<'a> {
    /// Strictly increasing keyframe times in seconds, at least one.
    pub(super) times: &'a [f32],
    /// How values between keyframes are found.
    pub(super) interpolation: Interpolation,
}

impl Spline<'_> {
    /// The keyframe interval containing `t` and the position within it: `(k, s)` with
    /// `times[k] <= t < times[k + 1]` and `s` in [0, 1); `None` when `t` clamps to
    /// keyframe `k` (before the first or at or after the last).
    fn locate(&self, t: f64) -> Result<(usize, f64, f64), usize> {
        let n = self.times.len();
        if t <= f64::from(self.times[0]) {
            return Err(0);
        }
        if t >= f64::from(self.times[n - 1]) {
            return Err(n - 1);
        }
        // The last keyframe at or before t.
        let k = self.times.partition_point(|&x| f64::from(x) <= t) - 1;
        let (t0, t1) = (f64::from(self.times[k]), f64::from(self.times[k + 1]));
        Ok((k, (t - t0) / (t1 - t0), t1 - t0))
    }

    /// Element `e` (of `width` components) of keyframe `k`'s value in `out` (`values` as
    /// stored: for CUBICSPLINE each keyframe is in-tangent, value, out-tangent).
    fn value<'v>(&self, values: &'v [f64], width: usize, k: usize) -> &'v [f64] {
        let at = if self.interpolation == Interpolation::CubicSpline {
            (3 * k + 1) * width
        } else {
            k * width
        };
        &values[at..at + width]
    }

    /// Samples a vector-valued (or weights) channel of `width` components at `t` into `out`.
    pub(super) fn sample(&self, values: &[f64], width: usize, t: f64, out: &mut [f64]) {
        let (k, s, dt) = match self.locate(t) {
            Ok(v) => v,
            Err(k) => {
                out.copy_from_slice(self.value(values, width, k));
                return;
            }
        };
        let v0 = self.value(values, width, k);
        let v1 = self.value(values, width, k + 1);
        match self.interpolation {
            Interpolation::Step => out.copy_from_slice(v0),
            Interpolation::Linear => {
                for (o, (a, b)) in out.iter_mut().zip(v0.iter().zip(v1)) {
                    *o = a + s * (b - a);
                }
            }
            Interpolation::CubicSpline => {
                // Appendix C: the out-tangent b_k of keyframe k and the in-tangent a_{k+1}
                // of keyframe k + 1, both per second, scaled by the interval dt.
                let b0 = &values[(3 * k + 2) * width..(3 * k + 3) * width];
                let a1 = &values[(3 * (k + 1)) * width..(3 * (k + 1) + 1) * width];
                let (s2, s3) = (s * s, s * s * s);
                let h00 = 2.0 * s3 - 3.0 * s2 + 1.0;
                let h10 = s3 - 2.0 * s2 + s;
                let h01 = -2.0 * s3 + 3.0 * s2;
                let h11 = s3 - s2;
                for (j, o) in out.iter_mut().enumerate() {
                    *o = h00 * v0[j] + h10 * dt * b0[j] + h01 * v1[j] + h11 * dt * a1[j];
                }
            }
        }
    }

    /// Samples a rotation channel (unit quaternions `x, y, z, w`) at `t`: LINEAR by
    /// spherical linear interpolation along the shorter arc, CUBICSPLINE componentwise
    /// (Appendix C), STEP held; normalized. `None` if the result has zero length.
    pub(super) fn sample_rotation(&self, values: &[f64], t: f64) -> Option<DQuat> {
        let quat = |v: &[f64]| DQuat::from_xyzw(v[0], v[1], v[2], v[3]);
        let q = match (self.interpolation, self.locate(t)) {
            (Interpolation::Linear, Ok((k, s, _))) => {
                let a = unit(quat(self.value(values, 4, k)))?;
                let b = unit(quat(self.value(values, 4, k + 1)))?;
                slerp(a, b, s)
            }
            _ => {
                let mut out = [0.0; 4];
                self.sample(values, 4, t, &mut out);
                DQuat::from_array(out)
            }
        };
        unit(q)
    }
}

/// `q` normalized, or `None` if its length is zero or not finite.
fn unit(q: DQuat) -> Option<DQuat> {
    let len = q.length();
    (len.is_finite() && len > 1e-12).then(|| q / len)
}

/// Spherical linear interpolation from `a` to `b` along the shorter arc (`-b` is the same
/// rotation as `b`; spec "Animations": "the shortest path"), for unit quaternions.
fn slerp(a: DQuat, b: DQuat, s: f64) -> DQuat {
    let mut dot = a.dot(b);
    let b = if dot < 0.0 {
        dot = -dot;
        -b
    } else {
        b
    };
    if dot > 0.9995 {
        // Nearly parallel: the arc is a line to within rounding; normalized lerp.
        return (a + (b - a) * s).normalize();
    }
    let theta = dot.clamp(-1.0, 1.0).acos();
    let sin = theta.sin();
    let wa = ((1.0 - s) * theta).sin() / sin;
    let wb = (s * theta).sin() / sin;
    (a * wa + b * wb).normalize()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spline(times: &[f32], interpolation: Interpolation) -> Spline<'_> {
        Spline {
            times,
            interpolation,
        }
    }

    #[test]
    fn step_linear_and_clamping() {
        let times = [1.0, 2.0, 4.0];
        let values = [0.0, 10.0, 30.0];
        let mut out = [0.0];
        let lin = spline(&times, Interpolation::Linear);
        for (t, want) in [
            (0.0, 0.0),
            (1.5, 5.0),
            (3.0, 20.0),
            (4.0, 30.0),
            (9.0, 30.0),
        ] {
            lin.sample(&values, 1, t, &mut out);
            assert_eq!(out[0], want, "linear at {t}");
        }
        let step = spline(&times, Interpolation::Step);
        for (t, want) in [
            (0.5, 0.0),
            (1.99, 0.0),
            (2.0, 10.0),
            (3.9, 10.0),
            (5.0, 30.0),
        ] {
            step.sample(&values, 1, t, &mut out);
            assert_eq!(out[0], want, "step at {t}");
        }
    }

    #[test]
    fn cubic_spline_is_the_hermite_form_with_tangents_scaled_by_the_interval() {
        // Keys (in-tangent, value, out-tangent): value 0 at t = 0 leaving at slope 2 per
        // second, value 1 at t = 2 arriving at slope -1 per second.
        let times = [0.0, 2.0];
        let values = [9.0, 0.0, 2.0, -1.0, 1.0, 9.0];
        let mut out = [0.0];
        spline(&times, Interpolation::CubicSpline).sample(&values, 1, 0.5, &mut out);
        let s: f64 = 0.25;
        let want = (s.powi(3) - 2.0 * s * s + s) * 2.0 * 2.0 + (-2.0 * s.powi(3) + 3.0 * s * s)
            - (s.powi(3) - s * s) * 2.0;
        assert!((out[0] - want).abs() < 1e-12, "{} vs {want}", out[0]);
        // At the keys the values themselves.
        spline(&times, Interpolation::CubicSpline).sample(&values, 1, 2.0, &mut out);
        assert_eq!(out[0], 1.0);
    }

    #[test]
    fn rotations_slerp_along_the_shorter_arc() {
        let times = [0.0, 1.0];
        let h = std::f64::consts::FRAC_1_SQRT_2;
        // Identity to 90 degrees about Z, the second given as its negative (same rotation).
        let values = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, -h, -h];
        let q = spline(&times, Interpolation::Linear)
            .sample_rotation(&values, 0.5)
            .unwrap();
        let want = DQuat::from_rotation_z(std::f64::consts::FRAC_PI_4);
        assert!(q.dot(want).abs() > 1.0 - 1e-12, "{q:?}");
        assert!((q.length() - 1.0).abs() < 1e-12);
    }
}
