//! Step 6: the plan decision (the module documentation's "Integrator" and "Depth" rules):
//! the integrator, its path depth and Russian-roulette depth, and the reasons for them.

use super::direct::DirectSurvey;
use super::lights::Lights;
use super::transport::Transport;
use super::{
    Effect, EffectKind, PlannedIntegrator, RenderPlan, TechniquePilot, BRIGHT_ALBEDO,
    CLOSED_FRACTION, CLOSED_ROOM_DEPTH, DEFAULT_DEPTH, DEFAULT_RR_DEPTH, DIRECT_LIT_FRACTION,
    DIRECT_SURVEY_GRID, MNEE_MAX_CHAIN, OPEN_SCENE_RR_DEPTH, REFRACTION_DEPTH,
};
use crate::Camera;

/// Chooses the integrator and its settings for the effects found and assembles the plan.
pub(super) fn plan(
    camera: &Camera,
    animated: bool,
    lights: &Lights,
    transport: &Transport,
    lens_sampling: bool,
    mut effects: Vec<Effect>,
    direct: impl FnOnce() -> Option<DirectSurvey>,
) -> RenderPlan {
    let mut reasons: Vec<String> = Vec::new();
    let beyond_mnee = transport.beyond_mnee.clone();
    let mut integrator = choose_integrator(lights, transport, &beyond_mnee, &mut reasons);
    // Tiny finite lights: path tracing is correct too, and which technique is more
    // efficient (Veach & Guibas 1995, section 2: 1 / (variance x time)) depends on the
    // scene (their section 4.3 compares the two at equal time), so a measured pilot
    // decides; the reasons given for bdpt are swapped for path tracing's if it wins.
    let mut technique_pilot = (integrator == PlannedIntegrator::Bdpt && transport.tiny_lit_only)
        .then(|| {
            let mut path_reasons = Vec::new();
            path_reasons_into(transport, &mut path_reasons);
            TechniquePilot {
                bdpt_reasons: reasons.len(),
                path_reasons,
                lit_through_opening: false,
                mnee: false,
            }
        });
    // Light through an opening: the same question where the lights reach little of what
    // the camera sees (the survey runs only for a path-traced plan, the one it may change).
    if integrator == PlannedIntegrator::Path {
        if let Some(survey) = direct().filter(|d| d.fraction() < DIRECT_LIT_FRACTION) {
            let path_reasons = std::mem::take(&mut reasons);
            reasons.push(through_an_opening(&survey));
            reasons.push(
                "bdpt light-traces onto the film: one whole-frame tile, units split by passes"
                    .into(),
            );
            integrator = PlannedIntegrator::Bdpt;
            technique_pilot = Some(TechniquePilot {
                bdpt_reasons: reasons.len(),
                path_reasons,
                lit_through_opening: true,
                mnee: false,
            });
        }
    }
    // Caustics of small area lights within MNEE's reach: path tracing with manifold
    // next-event estimation may reach an error sooner; both are unbiased, so the pilot
    // measures the two.
    if integrator == PlannedIntegrator::Path && technique_pilot.is_none() {
        if let Some(evidence) = &transport.small_light_mnee {
            reasons.push(format!(
                "caustics of small area lights within the reach of manifold next-event \
                 estimation ({evidence}): path tracing with and without it is unbiased, so \
                 the technique pilot measures mnee against path tracing"
            ));
            technique_pilot = Some(TechniquePilot {
                bdpt_reasons: 0,
                path_reasons: Vec::new(),
                lit_through_opening: false,
                mnee: true,
            });
        }
    }
    let (max_depth, rr_depth) = depths(integrator, transport, &mut reasons);
    if integrator != PlannedIntegrator::Black {
        reasons.push(if lens_sampling {
            format!(
                "thin-lens camera (aperture radius {}): lens sampling on",
                camera.aperture_radius
            )
        } else {
            "pinhole camera: no lens sampling".into()
        });
        if transport.surfaces.refraction.is_empty() {
            reasons.push("nothing transmits: no refraction paths".into());
        }
        if !transport.caustics {
            reasons.push(if transport.surfaces.smooth_specular.is_empty() {
                "no specular surfaces: no caustic technique".into()
            } else {
                "no caustics (no diffuse receiver, or nothing for light to bounce between): no \
                 caustic technique"
                    .into()
            });
        }
    }
    reasons.push(if animated {
        "motion: animated scene, each frame evaluated at its own time t = frame / fps; a \
         job's shutter blurs what moves within it (time sampled only then)"
            .into()
    } else {
        "motion: static scene (the scene description has no animation)".into()
    });
    if integrator == PlannedIntegrator::Black {
        // An empty plan: no light is transported, so no transport effect, lens or texture
        // shows. Only the (invisible, unlit-upon) lights found stay as evidence.
        effects.retain(|e| e.kind <= EffectKind::DirectEnvironment);
    }

    let present: Vec<EffectKind> = effects.iter().map(|e| e.kind).collect();
    let absent = EffectKind::ALL
        .into_iter()
        .filter(|k| !present.contains(k))
        .collect();
    RenderPlan {
        effects,
        absent,
        integrator,
        max_depth,
        rr_depth,
        lens_sampling,
        reasons,
        overridden: None,
        warnings: Vec::new(),
        technique_pilot,
        beyond_mnee,
    }
}

/// The reason for bdpt where the lights reach little of what the camera sees.
fn through_an_opening(survey: &DirectSurvey) -> String {
    format!(
        "bdpt: the lights reach {:.1}% of the surfaces the camera sees directly ({} of {} \
         surveyed camera hits on diffuse or glossy surfaces or emitters see a light, from a \
         {DIRECT_SURVEY_GRID}x{DIRECT_SURVEY_GRID} grid of rays; below {:.0}%): the image is \
         lit through an opening, by paths a path tracer completes only after finding the \
         opening by BSDF sampling and bdpt's light subpaths start through it (Veach's door \
         ajar); path tracing is as correct, so the technique pilot decides",
        100.0 * survey.fraction(),
        survey.lit,
        survey.surfaces,
        100.0 * DIRECT_LIT_FRACTION
    )
}

/// Black, direct, MNEE, VCM, BDPT or path tracing, with the reason.
fn choose_integrator(
    lights: &Lights,
    transport: &Transport,
    beyond_mnee: &[String],
    reasons: &mut Vec<String>,
) -> PlannedIntegrator {
    let s = &transport.surfaces;
    let bouncing = &transport.bouncing;
    let more_than_direct = transport.indirect_diffuse
        || !s.glossy.is_empty()
        || !s.specular.is_empty()
        || !s.refraction.is_empty();
    if !lights.any() {
        reasons.push("no light: the image is black".into());
        PlannedIntegrator::Black
    } else if !lights.visible() && s.scattering.is_empty() {
        reasons.push(
            "no light reaches the camera: point, spot and directional lights are invisible and \
             no surface scatters their light; the image is black"
                .into(),
        );
        PlannedIntegrator::Black
    } else if !more_than_direct {
        reasons.push(format!(
            "direct lighting only: {} ({}) and nothing glossy, specular or transmissive, so no \
             light reaches the camera after a second bounce",
            bouncing.surfaces,
            if bouncing.triangles + bouncing.spheres == 0 {
                "nothing to bounce off"
            } else {
                "no two of them exchange light"
            }
        ));
        PlannedIntegrator::Direct
    } else if transport.delta_sds && beyond_mnee.is_empty() {
        reasons.push(format!(
            "mnee: light from delta lights reaches the camera as L S+ D S+ E (a caustic seen \
             through or in a specular surface), which no technique of plain path tracing or \
             bdpt samples; every caustic of the scene's delta and tiny lights crosses at most \
             {MNEE_MAX_CHAIN} refracting surfaces from a point, spot or small area light and \
             appears where the camera first meets a non-specular surface (a survey of specular \
             chains from the lights and the camera), so manifold next-event estimation (Hanika, \
             Droske & Fascione 2015) connects to the light through them there: unbiased, where \
             vcm's merging is biased"
        ));
        reasons.push(
            "mnee connects to the light at every non-specular vertex, so a caustic's light \
             after a further diffuse or glossy bounce (L S+ D .. D S* E, e.g. a pool floor's \
             light returned to it by the water's underside, about 15% of the pool's image at \
             depth 16) is sampled too, which a path tracer's BSDF-sampled rays never do for a \
             delta light"
                .into(),
        );
        reasons.push(
            "mnee estimates each pixel on its own: tiles and unit splits as for path tracing"
                .into(),
        );
        PlannedIntegrator::Mnee
    } else if transport.delta_sds {
        reasons.push(
            "vcm: light from delta lights reaches the camera as L S+ D S+ E (a caustic seen \
             through or in a specular surface), which no technique of path tracing or bdpt \
             samples; vertex merging does, and MIS keeps bdpt's connections where they are \
             better"
                .into(),
        );
        reasons.push(
            "vcm is biased: merging blurs light over a radius that shrinks with the passes \
             (consistent); a uniform render's error estimate adds an estimate of that bias (Hachisuka, Jarosz & Jensen 2010), an adaptive one's does not"
                .into(),
        );
        reasons.push(
            "vcm light-traces onto the film and merges with the whole pass's photons: one \
             whole-frame tile, units split by passes, each pass's photon map built in its unit"
                .into(),
        );
        reasons.push(format!(
            "not mnee: manifold next-event estimation cannot sample every caustic here: {}",
            beyond_mnee.join("; ")
        ));
        PlannedIntegrator::Vcm
    } else if transport.delta_lit {
        reasons.push(if transport.tiny_lit_only {
            "bdpt: caustics lit by tiny lights, which a path tracer with next-event estimation \
             finds only when a BSDF-sampled ray hits the light"
                .into()
        } else {
            "bdpt: caustics lit by delta lights, which a path tracer with next-event \
             estimation samples with zero probability"
                .into()
        });
        reasons.push(
            "bdpt light-traces onto the film: one whole-frame tile, units split by passes".into(),
        );
        PlannedIntegrator::Bdpt
    } else {
        path_reasons_into(transport, reasons);
        PlannedIntegrator::Path
    }
}

/// Why path tracing: the effects that need more than one bounce.
fn path_reasons_into(transport: &Transport, reasons: &mut Vec<String>) {
    let s = &transport.surfaces;
    let mut why: Vec<&str> = Vec::new();
    if transport.indirect_diffuse {
        why.push("indirect diffuse");
    }
    if !s.glossy.is_empty() {
        why.push("glossy reflection");
    }
    if !s.specular.is_empty() {
        why.push("specular reflection");
    }
    if !s.refraction.is_empty() {
        why.push("refraction");
    }
    reasons.push(format!(
        "path tracing with next-event estimation and MIS: more than one bounce for {}",
        why.join(", ")
    ));
    if transport.caustics {
        reasons.push(
            "the caustics are lit only by finite lights: path tracing finds them by BSDF \
             sampling, no bidirectional technique needed"
                .into(),
        );
    }
}

/// `(max_depth, rr_depth)` for `integrator`, with the reasons.
fn depths(
    integrator: PlannedIntegrator,
    transport: &Transport,
    reasons: &mut Vec<String>,
) -> (u32, u32) {
    let (mean_albedo, enclosure) = (transport.mean_albedo, transport.enclosure);
    match integrator {
        PlannedIntegrator::Black => (0, 0),
        PlannedIntegrator::Direct => {
            reasons.push("max depth 1: one scattering event".into());
            (1, DEFAULT_RR_DEPTH)
        }
        PlannedIntegrator::Path
        | PlannedIntegrator::Bdpt
        | PlannedIntegrator::Vcm
        | PlannedIntegrator::Mlt
        | PlannedIntegrator::Mnee => {
            let closed_bright = transport.indirect_diffuse
                && mean_albedo > BRIGHT_ALBEDO
                && enclosure >= CLOSED_FRACTION;
            let mut depth = if closed_bright {
                reasons.push(format!(
                    "max depth {CLOSED_ROOM_DEPTH}: a closed bright room (diffuse albedo \
                     {mean_albedo:.2} > {BRIGHT_ALBEDO}, surfaces cover {:.0}% >= {:.0}% of the \
                     bounding box) keeps light bouncing",
                    100.0 * enclosure,
                    100.0 * CLOSED_FRACTION
                ));
                CLOSED_ROOM_DEPTH
            } else {
                reasons.push(format!(
                    "max depth {DEFAULT_DEPTH}: not a closed bright room (diffuse albedo \
                     {mean_albedo:.2}, surfaces cover {:.0}% of the bounding box)",
                    100.0 * enclosure
                ));
                DEFAULT_DEPTH
            };
            let refraction = !transport.surfaces.refraction.is_empty();
            if refraction && depth < REFRACTION_DEPTH {
                reasons.push(format!(
                    "max depth raised to {REFRACTION_DEPTH}: light needs several interfaces \
                     to pass through glass"
                ));
                depth = REFRACTION_DEPTH;
            }
            let rr = if closed_bright || refraction {
                reasons.push(format!(
                    "Russian roulette from depth {DEFAULT_RR_DEPTH} ({}), survival from the \
                     throughput (at most 95%)",
                    if closed_bright {
                        "later bounces of a closed bright room still carry light"
                    } else {
                        "paths through glass need their first bounces"
                    }
                ));
                DEFAULT_RR_DEPTH
            } else {
                reasons.push(format!(
                    "Russian roulette from depth {OPEN_SCENE_RR_DEPTH} (an open scene: paths \
                     carry little after a few bounces), survival from the throughput (at most \
                     95%)"
                ));
                OPEN_SCENE_RR_DEPTH
            };
            (depth, rr)
        }
    }
}
