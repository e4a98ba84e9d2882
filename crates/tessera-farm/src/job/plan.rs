//! The render plan as data: the light-transport effects found in a scene, with their
//! evidence, and the integrator and path depth chosen for exactly those (ARCHITECTURE.md
//! §4, "simulate only what the scene calls for").
//!
//! These are the types of the job contract; `tessera_scene::analysis::analyse` computes
//! them from a scene, and [`ValidatedJob::resolve`](super::ValidatedJob::resolve) turns
//! the chosen [`PlannedIntegrator`] into concrete settings. They depend on nothing that
//! parses scenes, so the coordinator, the wire format and the EXR header share them.

use std::fmt;

use super::choice::{Integrator, IntegratorChoice};

/// How [`RenderPlan::unsampled`] (and so an error estimate caveat that includes it) begins:
/// a stored caveat that starts with it marks a job whose integrator cannot sample a light
/// path class of its scene.
pub const UNSAMPLED_CAVEAT: &str = "cannot sample";

/// A light-transport effect a scene may contain.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum EffectKind {
    /// Direct light from emissive triangles.
    DirectArea,
    /// Direct light from emissive spheres.
    DirectSphere,
    /// Direct light from point lights.
    DirectPoint,
    /// Direct light from spot lights.
    DirectSpot,
    /// Direct light from directional lights.
    DirectDirectional,
    /// Direct light from the environment.
    DirectEnvironment,
    /// Diffuse interreflection: light reaching a diffuse surface after another bounce.
    IndirectDiffuse,
    /// Glossy (rough, non-delta) reflection.
    GlossyReflection,
    /// Specular or near-specular reflection.
    SpecularReflection,
    /// Transmission through a dielectric interface.
    Refraction,
    /// Total internal reflection inside a denser medium.
    TotalInternalReflection,
    /// Light reaching a diffuse surface through at least one specular or near-specular
    /// bounce.
    Caustics,
    /// Caustics lit by delta (point, spot, directional) or tiny lights.
    DeltaLitCaustics,
    /// Caustics of a delta light seen through specular surfaces: light reaching the
    /// camera as `L S+ D S+ E` (Heckbert 1990's notation) from a point, spot or
    /// directional light, e.g. a pool floor seen through the water. No technique of path
    /// tracing or bdpt samples such a path (each would connect at the diffuse vertex
    /// through a delta-BSDF neighbour); vertex merging does.
    DeltaLitSds,
    /// Images of a tiny light seen in or through specular surfaces: light reaching the
    /// camera as `E S+ L` (Heckbert 1990) from a tiny sphere or area light, e.g. a small
    /// lamp's reflection and refraction in a glass ball. Every technique here samples it
    /// as path tracing does, only when a camera path's specular chain happens to end on
    /// the light: light tracing cannot reach a pinhole through a specular chain and no
    /// connection crosses one.
    TinyLightImages,
    /// Depth of field from a thin-lens camera.
    DepthOfField,
    /// Motion blur from animated transforms within the shutter.
    Motion,
    /// Textured materials.
    Textures,
}

impl EffectKind {
    /// Every kind, in the order plans list them.
    pub const ALL: [EffectKind; 18] = [
        Self::DirectArea,
        Self::DirectSphere,
        Self::DirectPoint,
        Self::DirectSpot,
        Self::DirectDirectional,
        Self::DirectEnvironment,
        Self::IndirectDiffuse,
        Self::GlossyReflection,
        Self::SpecularReflection,
        Self::Refraction,
        Self::TotalInternalReflection,
        Self::Caustics,
        Self::DeltaLitCaustics,
        Self::DeltaLitSds,
        Self::TinyLightImages,
        Self::DepthOfField,
        Self::Motion,
        Self::Textures,
    ];

    /// The kebab-case name used in summaries and JSON, e.g. `"direct-area"`.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::DirectArea => "direct-area",
            Self::DirectSphere => "direct-sphere",
            Self::DirectPoint => "direct-point",
            Self::DirectSpot => "direct-spot",
            Self::DirectDirectional => "direct-directional",
            Self::DirectEnvironment => "direct-environment",
            Self::IndirectDiffuse => "indirect-diffuse",
            Self::GlossyReflection => "glossy-reflection",
            Self::SpecularReflection => "specular-reflection",
            Self::Refraction => "refraction",
            Self::TotalInternalReflection => "total-internal-reflection",
            Self::Caustics => "caustics",
            Self::DeltaLitCaustics => "delta-lit-caustics",
            Self::DeltaLitSds => "delta-lit-sds",
            Self::TinyLightImages => "tiny-light-images",
            Self::DepthOfField => "depth-of-field",
            Self::Motion => "motion",
            Self::Textures => "textures",
        }
    }
}

impl fmt::Display for EffectKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// An effect found in the scene, with the evidence for it.
#[derive(Clone, Debug, PartialEq)]
pub struct Effect {
    /// What it is.
    pub kind: EffectKind,
    /// Why we think so, e.g. "2 emissive triangles in material 3 'light'".
    pub evidence: String,
}

/// The integrator a plan chooses.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum PlannedIntegrator {
    /// No light: the image is black; render it immediately without tracing.
    Black,
    /// Direct lighting only (one bounce).
    Direct,
    /// Unidirectional path tracing with next-event estimation and MIS.
    Path,
    /// Bidirectional path tracing (for caustics lit by delta or tiny lights).
    Bdpt,
    /// Vertex connection and merging (for caustics of delta lights seen through specular
    /// surfaces, [`EffectKind::DeltaLitSds`]).
    Vcm,
    /// Multiplexed Metropolis light transport over bdpt's techniques: never the
    /// analysis's own choice, only the technique pilot's, where it measured mlt the most
    /// efficient ([`PilotVerdict::mlt_wins`]).
    Mlt,
    /// Path tracing with manifold next-event estimation (for caustics of delta lights seen
    /// through specular surfaces, [`EffectKind::DeltaLitSds`], where every caustic of the
    /// scene's delta and tiny lights is within MNEE's reach: [`RenderPlan::beyond_mnee`]
    /// is empty). Unbiased, where vcm's merging is not.
    Mnee,
}

impl PlannedIntegrator {
    /// Lower-case name as the command line spells it (`black` for the empty plan).
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Black => "black",
            Self::Direct => "direct",
            Self::Path => "path",
            Self::Bdpt => "bdpt",
            Self::Vcm => "vcm",
            Self::Mlt => "mlt",
            Self::Mnee => "mnee",
        }
    }
}

impl fmt::Display for PlannedIntegrator {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// The result of `tessera_scene::analysis::analyse`: the effects in a scene and how to render exactly those.
#[derive(Clone, Debug, PartialEq)]
pub struct RenderPlan {
    /// Effects present, in [`EffectKind::ALL`] order, each with its evidence.
    pub effects: Vec<Effect>,
    /// Every effect kind not present, in [`EffectKind::ALL`] order.
    pub absent: Vec<EffectKind>,
    /// The integrator chosen.
    pub integrator: PlannedIntegrator,
    /// Maximum number of scattering events (0 for [`PlannedIntegrator::Black`]).
    pub max_depth: u32,
    /// Bounces before Russian roulette starts.
    pub rr_depth: u32,
    /// Whether camera rays sample the lens (thin-lens camera with aperture > 0).
    pub lens_sampling: bool,
    /// Why the integrator and its settings were chosen, and what machinery is left out.
    pub reasons: Vec<String>,
    /// Set when the user forced something else than the plan (e.g. `--integrator path`),
    /// saying what and what the plan had chosen.
    pub overridden: Option<String>,
    /// What the scene loader ignored (e.g. unsupported optional glTF extensions).
    pub warnings: Vec<String>,
    /// Set when the analysis chose bdpt but path tracing is as correct (the caustics' only
    /// lights are tiny finite ones, which BSDF sampling can hit, or the scene is lit
    /// through an opening, where the lights reach little of what the camera sees): the
    /// choice waits for a measured pilot of both (`tessera_render::pilot`), which settles it with
    /// [`RenderPlan::settle_technique`]. Also set when the analysis chose path tracing for
    /// caustics of small area lights that manifold next-event estimation reaches
    /// ([`TechniquePilot::mnee`]): the pilot then measures path tracing against mnee and
    /// [`RenderPlan::settle_mnee`] takes mnee if it wins. Not in [`RenderPlan::to_json`]:
    /// the verdict is.
    pub technique_pilot: Option<TechniquePilot>,
    /// Why manifold next-event estimation cannot sample every caustic of the scene's delta
    /// and tiny lights, each reason with its evidence (a reflection, a chain longer than
    /// MNEE's, a directional light, a caustic the camera sees only after a diffuse
    /// bounce); empty where it can, or where there are no such caustics. The plan chooses
    /// mnee over vcm only when it is empty; a job that asks for mnee where it is not is
    /// told what is missing ([`RenderPlan::unsampled`]). Not in [`RenderPlan::to_json`]:
    /// the reasons say it where it decided the choice.
    pub beyond_mnee: Vec<String>,
}

/// A plan's provisional choice between bdpt and path tracing, or between path tracing and
/// mnee ([`RenderPlan::technique_pilot`]).
#[derive(Clone, Debug, PartialEq)]
pub struct TechniquePilot {
    /// How many leading [`RenderPlan::reasons`] explain bdpt (replaced if path wins).
    pub bdpt_reasons: usize,
    /// The reasons that replace them if path tracing wins.
    pub path_reasons: Vec<String>,
    /// The question was asked because the scene is lit through an opening (the lights
    /// reach little of what the camera sees), not for tiny-light caustics: the pilot then
    /// scores each technique's squared error relative to the image's mean luminance (the
    /// efficiency `1 / (MSE x cost)`), not per pixel (`tessera_render::pilot`).
    pub lit_through_opening: bool,
    /// The question is path tracing (the analysis's provisional choice, its reasons kept)
    /// against mnee, path tracing with manifold next-event estimation: the scene's
    /// caustics are lit by small area lights through specular chains within MNEE's reach.
    /// Both are unbiased (BSDF sampling keeps every path MNEE does not claim), so only
    /// their efficiency is in question.
    pub mnee: bool,
}

/// The technique pilot's answer ([`RenderPlan::settle_technique`]): whether path tracing
/// wins, and what was measured. Written once here so that the renderer that runs the pilot
/// and the coordinator that runs it in a child process (`tessera pilot --technique`, which
/// prints this as JSON) read and write the same thing.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PilotVerdict {
    /// Path tracing wins (otherwise bdpt, the analysis's choice, stays, unless
    /// [`PilotVerdict::mlt_wins`]).
    pub path_wins: bool,
    /// Metropolis light transport wins over both (then `path_wins` is false). Absent in
    /// the JSON of a pilot that did not measure it: false.
    #[serde(default)]
    pub mlt_wins: bool,
    /// Mnee wins over path tracing ([`TechniquePilot::mnee`]; then `path_wins` is false).
    /// Absent in the JSON of a pilot that did not measure it: false.
    #[serde(default)]
    pub mnee_wins: bool,
    /// The plan's first reason: what was measured, or why nothing was.
    pub reason: String,
}

impl RenderPlan {
    /// Whether the plan found `kind`.
    pub fn has(&self, kind: EffectKind) -> bool {
        self.effects.iter().any(|e| e.kind == kind)
    }

    /// The evidence for `kind`, if present.
    pub fn evidence(&self, kind: EffectKind) -> Option<&str> {
        self.effects
            .iter()
            .find(|e| e.kind == kind)
            .map(|e| e.evidence.as_str())
    }

    /// Whether a job asking for `asked` waits for the technique pilot: the plan left the
    /// choice open ([`RenderPlan::technique_pilot`]) and the job asks for `auto`.
    pub fn awaits_technique_pilot(&self, asked: IntegratorChoice) -> bool {
        self.technique_pilot.is_some() && asked == IntegratorChoice::Auto
    }

    /// Settles a provisional choice ([`RenderPlan::technique_pilot`]) by a pilot's
    /// measurement: path tracing if `path_wins`, bdpt otherwise, with `verdict` (what was
    /// measured) as the first reason. Does nothing on a plan without a pilot.
    pub fn settle_technique(&mut self, path_wins: bool, verdict: String) {
        let Some(pilot) = self.technique_pilot.take() else {
            return;
        };
        let n = pilot.bdpt_reasons.min(self.reasons.len());
        if path_wins {
            self.integrator = PlannedIntegrator::Path;
            self.reasons.splice(0..n, pilot.path_reasons);
        }
        self.reasons.insert(0, verdict);
    }

    /// Settles a provisional choice between path tracing and mnee
    /// ([`TechniquePilot::mnee`]) by a pilot that measured mnee the more efficient: mnee,
    /// which is path tracing with manifold next-event estimation, so path tracing's reasons
    /// stay, after `verdict`. Does nothing on a plan without a pilot.
    pub fn settle_mnee(&mut self, verdict: String) {
        if self.technique_pilot.take().is_none() {
            return;
        }
        self.integrator = PlannedIntegrator::Mnee;
        self.reasons.insert(0, verdict);
    }

    /// Settles a provisional choice by a pilot that measured Metropolis light transport the
    /// most efficient: mlt, whose chains sample bdpt's techniques, so the reasons given for
    /// bdpt stay, after `verdict`. Does nothing on a plan without a pilot.
    pub fn settle_metropolis(&mut self, verdict: String) {
        if self.technique_pilot.take().is_none() {
            return;
        }
        self.integrator = PlannedIntegrator::Mlt;
        self.reasons.insert(0, verdict);
    }

    /// Why the pass-variance error estimate may be optimistic for a render of this scene
    /// with `used`, or `None`. Path tracing (and direct lighting) finds light that reaches
    /// a diffuse surface through a specular chain from a delta or tiny light only when a
    /// BSDF-sampled ray happens to hit the light ([`EffectKind::DeltaLitCaustics`]), so at
    /// practical budgets most pixels have no pass that found it and no sample shows what
    /// is missing: on `builtin:caustic`, path-traced, the pixels' pooled intervals cover
    /// 44-89% and the image estimate is 0.3-1.0 of the measured error, where bdpt covers
    /// 93-96% (docs/benchmarks.md, "The caustic against a converged reference").
    /// Bidirectional path tracing reaches those caustics by light tracing.
    ///
    /// Before that, in this order: what `used` cannot sample at all
    /// ([`RenderPlan::unsampled`]), and for a biased integrator (vcm, ppm) that its estimate
    /// has a bias the pass spread does not see. Joined by "; ".
    pub fn error_estimate_caveat(&self, used: Integrator) -> Option<String> {
        if self.integrator == PlannedIntegrator::Black {
            return None;
        }
        let mut parts: Vec<String> = Vec::new();
        parts.extend(self.unsampled(used));
        if used.is_biased() {
            parts.push(
                "biased: vertex merging blurs light over a radius that shrinks with the passes \
                 (r_k = r_1 (k + 1)^-0.125, Knaus & Zwicker 2011); the pass spread does not see \
                 the bias the passes share, which vanishes as passes are added (consistent)"
                    .to_string(),
            );
        }
        // MNEE samples the caustics within its reach at every non-specular vertex; the
        // caustics the survey found beyond it have no technique in it.
        if used == Integrator::Mnee {
            if let Some(evidence) = self.evidence(EffectKind::DeltaLitCaustics) {
                let beyond = if self.beyond_mnee.is_empty() {
                    String::new()
                } else {
                    format!(", nor where {}", self.beyond_mnee.join("; nor where "))
                };
                parts.push(format!(
                    "may be optimistic: mnee samples the caustics of point, spot and small area \
                     lights ({evidence}) through at most two specular surfaces from the light, \
                     at every non-specular vertex; not longer chains, reflections it does not \
                     seed, nor other roots of the chain{beyond}; light that no pass found is in \
                     neither the image nor its error estimate, and bdpt and vcm sample it"
                ));
            }
        }
        // bdpt finds those caustics by light tracing, vcm and ppm by merging, and mlt's chains
        // sample bdpt's techniques, light tracing included.
        else if used != Integrator::Bdpt && used != Integrator::Mlt && !used.merges() {
            if let Some(evidence) = self.evidence(EffectKind::DeltaLitCaustics) {
                parts.push(format!(
                    "may be optimistic: {} reaches the scene's caustics of tiny or delta lights only \
                     when a BSDF-sampled ray happens to hit the light, or never ({evidence}); light \
                     that no pass found is in neither the image nor its error estimate, and bdpt \
                     finds it by light tracing",
                    used.as_str()
                ));
            }
        }
        // The images of a tiny light in specular surfaces (`E S+ L`) have no technique but
        // the camera path's own in any integrator: the passes that missed them show nothing.
        if let Some(evidence) = self.evidence(EffectKind::TinyLightImages) {
            parts.push(format!(
                "may be optimistic: {evidence}; {} finds that light only when a camera path's \
                 specular chain happens to end on the light (no technique connects a pinhole \
                 camera through a specular chain), so a pixel whose passes all missed it shows \
                 neither the light nor its error; on such a scene (a 5 cm light seen in a glass \
                 ball, bdpt) the image estimate was 0.2-0.7 of the measured error",
                used.as_str()
            ));
        }
        (!parts.is_empty()).then(|| parts.join("; "))
    }

    /// The light path class of the scene that `used` cannot sample at all, said in words
    /// that start with [`UNSAMPLED_CAVEAT`], or `None`: light from a delta light that
    /// reaches the camera only as `L S+ D S+ E` ([`EffectKind::DeltaLitSds`]) has no
    /// technique in path tracing, direct lighting or bdpt (nor in mnee where
    /// [`RenderPlan::beyond_mnee`] says why), so the image lacks it and no pass shows that
    /// it does. No render with such an integrator reports its target
    /// error reached ([`crate::job::StopVerdict::target_reached`]).
    pub fn unsampled(&self, used: Integrator) -> Option<String> {
        // Merging (vcm, ppm) samples L S+ D S+ E at the diffuse vertex.
        if used.merges() || self.integrator == PlannedIntegrator::Black {
            return None;
        }
        let evidence = self.evidence(EffectKind::DeltaLitSds)?;
        // MNEE samples it at the non-specular vertices where the survey of specular
        // chains found every caustic within its reach.
        if used == Integrator::Mnee {
            if self.beyond_mnee.is_empty() {
                return None;
            }
            return Some(format!(
                "{UNSAMPLED_CAVEAT} every light path of this scene: mnee samples L S+ D S+ E \
                 ({evidence}) only where its manifold connection reaches the light, and here \
                 {}; that light is missing from the image and from its error estimate, so no \
                 target error counts as reached; vcm and ppm sample it by vertex merging",
                self.beyond_mnee.join("; ")
            ));
        }
        Some(format!(
            "{UNSAMPLED_CAVEAT} every light path of this scene: {} has no technique for light \
             from a delta light that reaches the camera as L S+ D S+ E ({evidence}); that \
             light is missing from the image and from its error estimate, so no target error \
             counts as reached; vcm and ppm sample it by vertex merging",
            used.as_str()
        ))
    }

    /// Why the error estimate of an adaptive render of this scene may be optimistic, or
    /// `None` for a scene without rare bright paths. Adaptive stopping selects: the pixels
    /// that stop early (sequential: on a low estimate, Kirk & Arvo 1991) or get the fewest
    /// fresh passes (unbiased: from a low pilot) are the ones whose passes missed the rare
    /// paths that glossy and specular reflection, refraction and caustics make, so their
    /// estimates are low where the error is. Measured (docs/benchmarks.md, "The error
    /// estimate under adaptive sampling"): sequential 0.73-0.89 of the measured error on
    /// path-traced `builtin:veach-mis` (glossy plates lit by small lights) and 0.86 on the
    /// glass caustic; unbiased, with its pooled estimator
    /// ([`crate::ErrorEstimator::PooledPerPass`]), 0.85-1.02 on veach-mis but 0.61-0.83 on
    /// a small light's highlight in a glossy floor and 0.34 on the caustic; on the diffuse
    /// Cornell box 1.01-1.05 in either mode.
    pub fn adaptive_error_estimate_caveat(&self) -> Option<String> {
        if self.integrator == PlannedIntegrator::Black {
            return None;
        }
        let evidence = [
            EffectKind::DeltaLitCaustics,
            EffectKind::Caustics,
            EffectKind::GlossyReflection,
            EffectKind::SpecularReflection,
            EffectKind::Refraction,
        ]
        .into_iter()
        .find_map(|kind| self.evidence(kind))?;
        Some(format!(
            "may be optimistic under adaptive stopping: the pixels that stop early \
             (sequential) or get the fewest fresh passes (unbiased) are the ones whose passes \
             missed rare bright paths, which this scene makes ({evidence}); measured \
             between 0.3 (a glass caustic of a small light) and 0.9 of the true error on \
             such scenes"
        ))
    }

    /// Records that the user forced `what` (e.g. "--integrator path") instead of the plan,
    /// and what the plan had chosen.
    pub fn set_override(&mut self, what: &str) {
        self.overridden = Some(format!(
            "{what} overrides the plan, which chose {}{}",
            self.integrator,
            match self.integrator {
                PlannedIntegrator::Black => String::new(),
                _ => format!(" with max depth {}", self.max_depth),
            }
        ));
    }

    /// Multi-line human-readable text: the integrator and its settings, the effects with
    /// their evidence, the absent effects, the reasons, and any override.
    pub fn summary(&self) -> String {
        let mut s = String::new();
        let settings = match self.integrator {
            PlannedIntegrator::Black => "nothing to trace".to_string(),
            _ => format!(
                "max depth {}, Russian roulette from depth {}, {}",
                self.max_depth,
                self.rr_depth,
                if self.lens_sampling {
                    "lens sampling"
                } else {
                    "no lens sampling"
                }
            ),
        };
        s += &format!("render plan: {} ({settings})\n", self.integrator);
        s += "effects:\n";
        if self.effects.is_empty() {
            s += "  none\n";
        }
        for e in &self.effects {
            s += &format!("  {}: {}\n", e.kind, e.evidence);
        }
        s += &format!(
            "absent: {}\n",
            if self.absent.is_empty() {
                "nothing".to_string()
            } else {
                self.absent
                    .iter()
                    .map(|k| k.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            }
        );
        s += "why:\n";
        for r in &self.reasons {
            s += &format!("  - {r}\n");
        }
        if let Some(o) = &self.overridden {
            s += &format!("overridden: {o}\n");
        }
        if !self.warnings.is_empty() {
            s += "warnings:\n";
            for w in &self.warnings {
                s += &format!("  - {w}\n");
            }
        }
        s
    }

    /// The plan as one compact JSON object with a stable key order: `integrator`,
    /// `max_depth`, `rr_depth`, `lens_sampling`, `effects` (array of `{kind, evidence}`),
    /// `absent` (array of kinds), `reasons`, `overridden` (string or null), and `warnings`
    /// (array of strings) only when there are any. Kinds are the
    /// [`EffectKind::as_str`] names. The text is pure ASCII (other characters are `\u`
    /// escaped), so it fits Latin-1 file headers such as EXR attributes.
    pub fn to_json(&self) -> String {
        let strings =
            |v: &mut dyn Iterator<Item = &str>| v.map(json_string).collect::<Vec<_>>().join(",");
        let effects = self
            .effects
            .iter()
            .map(|e| {
                format!(
                    "{{\"kind\":{},\"evidence\":{}}}",
                    json_string(e.kind.as_str()),
                    json_string(&e.evidence)
                )
            })
            .collect::<Vec<_>>()
            .join(",");
        let warnings = if self.warnings.is_empty() {
            String::new()
        } else {
            format!(
                ",\"warnings\":[{}]",
                strings(&mut self.warnings.iter().map(String::as_str))
            )
        };
        format!(
            "{{\"integrator\":{},\"max_depth\":{},\"rr_depth\":{},\"lens_sampling\":{},\
             \"effects\":[{effects}],\"absent\":[{}],\"reasons\":[{}],\"overridden\":{}{warnings}}}",
            json_string(self.integrator.as_str()),
            self.max_depth,
            self.rr_depth,
            self.lens_sampling,
            strings(&mut self.absent.iter().map(|k| k.as_str())),
            strings(&mut self.reasons.iter().map(String::as_str)),
            self.overridden
                .as_deref()
                .map_or_else(|| "null".to_string(), json_string)
        )
    }
}

/// A JSON string literal, ASCII only (other characters are `\u` escaped), so that it
/// fits Latin-1 file headers such as EXR attributes.
pub(crate) fn json_string(s: &str) -> String {
    let mut out = String::with_capacity(s.len() + 2);
    out.push('"');
    for c in s.chars() {
        match c {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            '\n' => out.push_str("\\n"),
            '\r' => out.push_str("\\r"),
            '\t' => out.push_str("\\t"),
            c if (c as u32) < 0x20 || (c as u32) > 0x7e => {
                let mut buf = [0u16; 2];
                for unit in c.encode_utf16(&mut buf) {
                    out.push_str(&format!("\\u{unit:04x}"));
                }
            }
            c => out.push(c),
        }
    }
    out.push('"');
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn provisional() -> RenderPlan {
        RenderPlan {
            effects: vec![],
            absent: vec![],
            integrator: PlannedIntegrator::Bdpt,
            max_depth: 12,
            rr_depth: 5,
            lens_sampling: false,
            reasons: vec![
                "bdpt: tiny lights".into(),
                "bdpt light-traces onto the film".into(),
                "max depth 12".into(),
            ],
            overridden: None,
            warnings: vec![],
            technique_pilot: Some(TechniquePilot {
                bdpt_reasons: 2,
                path_reasons: vec!["path tracing: refraction".into()],
                lit_through_opening: false,
                mnee: false,
            }),
            beyond_mnee: vec![],
        }
    }

    #[test]
    fn settling_swaps_the_reasons_of_the_technique_that_lost() {
        let mut plan = provisional();
        plan.settle_technique(true, "pilot: path".into());
        assert_eq!(plan.integrator, PlannedIntegrator::Path);
        assert_eq!(
            plan.reasons,
            ["pilot: path", "path tracing: refraction", "max depth 12"]
        );
        assert!(plan.technique_pilot.is_none());
        // Settled once: a second verdict changes nothing.
        plan.settle_technique(false, "again".into());
        assert_eq!(plan.integrator, PlannedIntegrator::Path);
        assert_eq!(plan.reasons.len(), 3);

        let mut plan = provisional();
        plan.settle_technique(false, "pilot: bdpt".into());
        assert_eq!(plan.integrator, PlannedIntegrator::Bdpt);
        assert_eq!(
            plan.reasons,
            [
                "pilot: bdpt",
                "bdpt: tiny lights",
                "bdpt light-traces onto the film",
                "max depth 12"
            ]
        );
    }

    /// The mnee question (a provisional path-traced plan): mnee won, path tracing's reasons
    /// stay after the verdict; path won, the plan is unchanged but for the verdict; either
    /// settles once. A verdict without `mnee_wins` in its JSON reads as not mnee.
    #[test]
    fn settling_the_mnee_question_keeps_path_tracings_reasons() {
        let path_plan = || RenderPlan {
            integrator: PlannedIntegrator::Path,
            reasons: vec!["path tracing: refraction".into(), "max depth 12".into()],
            technique_pilot: Some(TechniquePilot {
                bdpt_reasons: 0,
                path_reasons: vec![],
                lit_through_opening: false,
                mnee: true,
            }),
            ..provisional()
        };
        let mut plan = path_plan();
        plan.settle_mnee("pilot: mnee".into());
        assert_eq!(plan.integrator, PlannedIntegrator::Mnee);
        assert_eq!(
            plan.reasons,
            ["pilot: mnee", "path tracing: refraction", "max depth 12"]
        );
        plan.settle_technique(true, "again".into());
        assert_eq!(plan.integrator, PlannedIntegrator::Mnee);
        let mut plan = path_plan();
        plan.settle_technique(true, "pilot: path".into());
        assert_eq!(plan.integrator, PlannedIntegrator::Path);
        assert_eq!(
            plan.reasons,
            ["pilot: path", "path tracing: refraction", "max depth 12"]
        );
        plan.settle_mnee("again".into());
        assert_eq!(plan.integrator, PlannedIntegrator::Path);
        let v: PilotVerdict =
            serde_json::from_str(r#"{"path_wins":true,"mlt_wins":false,"reason":"r"}"#).unwrap();
        assert!(!v.mnee_wins);
    }

    /// mlt won: it renders, bdpt's reasons stay after the verdict (its chains sample
    /// bdpt's techniques), and a second verdict changes nothing. A verdict written before
    /// the pilot measured mlt (no `mlt_wins` in its JSON) reads as bdpt or path.
    #[test]
    fn settling_on_metropolis_keeps_bdpts_reasons() {
        let mut plan = provisional();
        plan.settle_metropolis("pilot: mlt".into());
        assert_eq!(plan.integrator, PlannedIntegrator::Mlt);
        assert_eq!(plan.integrator.as_str(), "mlt");
        assert_eq!(
            plan.reasons,
            [
                "pilot: mlt",
                "bdpt: tiny lights",
                "bdpt light-traces onto the film",
                "max depth 12"
            ]
        );
        assert!(plan.technique_pilot.is_none());
        plan.settle_metropolis("again".into());
        plan.settle_technique(true, "again".into());
        assert_eq!(plan.integrator, PlannedIntegrator::Mlt);
        assert_eq!(plan.reasons.len(), 4);

        let old: PilotVerdict = serde_json::from_str(r#"{"path_wins":true,"reason":"r"}"#).unwrap();
        assert!(old.path_wins && !old.mlt_wins);
    }

    #[test]
    fn the_caveat_names_caustics_of_tiny_lights_rendered_without_bdpt() {
        let mut plan = provisional();
        assert_eq!(plan.error_estimate_caveat(Integrator::Path), None);
        plan.effects.push(Effect {
            kind: EffectKind::DeltaLitCaustics,
            evidence: "lit by sphere light 1".into(),
        });
        for used in [Integrator::Path, Integrator::Direct] {
            let caveat = plan.error_estimate_caveat(used).unwrap();
            assert!(caveat.contains(used.as_str()), "{caveat}");
            assert!(caveat.contains("lit by sphere light 1"), "{caveat}");
        }
        assert_eq!(plan.error_estimate_caveat(Integrator::Bdpt), None);
        // Caustics of large lights are found by BSDF sampling often enough.
        plan.effects[0].kind = EffectKind::Caustics;
        assert_eq!(plan.error_estimate_caveat(Integrator::Path), None);
    }

    /// A tiny light's images in specular surfaces (`E S+ L`) are sampled only from the
    /// camera by every integrator, so every one of them carries the caveat, bdpt too.
    #[test]
    fn the_caveat_names_a_tiny_lights_images_for_every_integrator() {
        let mut plan = provisional();
        plan.effects.push(Effect {
            kind: EffectKind::TinyLightImages,
            evidence: "the camera sees specular material 1 'glass'".into(),
        });
        for used in [
            Integrator::Path,
            Integrator::Direct,
            Integrator::Bdpt,
            Integrator::Vcm,
            Integrator::Mlt,
            Integrator::Mnee,
        ] {
            let caveat = plan.error_estimate_caveat(used).unwrap();
            assert!(caveat.contains("material 1 'glass'"), "{caveat}");
            assert!(
                caveat.contains(&format!("; {} finds that light only", used.as_str())),
                "{caveat}"
            );
            assert!(caveat.is_ascii(), "{caveat}");
        }
    }

    #[test]
    fn the_adaptive_caveat_names_what_makes_rare_paths() {
        let mut plan = provisional();
        // A diffuse scene: calibrated under adaptive stopping (the Cornell box).
        assert_eq!(plan.adaptive_error_estimate_caveat(), None);
        plan.effects.push(Effect {
            kind: EffectKind::GlossyReflection,
            evidence: "material 5 'plate0' reflects glossily".into(),
        });
        let caveat = plan.adaptive_error_estimate_caveat().unwrap();
        assert!(caveat.contains("adaptive stopping"), "{caveat}");
        assert!(caveat.contains("'plate0' reflects glossily"), "{caveat}");
        assert!(caveat.is_ascii(), "{caveat}");
    }
}
