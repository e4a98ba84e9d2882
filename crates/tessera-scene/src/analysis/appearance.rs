//! Step 5: camera and textures (the module documentation's "Camera, motion, textures"
//! rule): depth of field from a thin-lens camera, and textured materials.

use super::evidence::{material_list, verb};
use super::survey::Survey;
use super::{push, Effect, EffectKind};

/// Records [`EffectKind::DepthOfField`] and [`EffectKind::Textures`] when present, and
/// returns whether camera rays sample the lens.
pub(super) fn report(survey: &Survey, effects: &mut Vec<Effect>) -> bool {
    let scene = survey.scene;
    let cam = &scene.camera;
    let lens_sampling = cam.aperture_radius > 0.0;
    if lens_sampling {
        push(
            effects,
            EffectKind::DepthOfField,
            format!(
                "camera aperture radius {}, focused at {}",
                cam.aperture_radius, cam.focus_distance
            ),
        );
    }
    let textured: Vec<usize> = (0..survey.nmat())
        .filter(|&i| {
            survey.used[i]
                && scene.materials[i]
                    .as_gltf()
                    .is_some_and(|g| g.textures().next().is_some())
        })
        .collect();
    if !textured.is_empty() {
        push(
            effects,
            EffectKind::Textures,
            format!(
                "{} {} textures",
                material_list(scene, &textured, &survey.classes, false),
                verb("use", textured.len())
            ),
        );
    }
    lens_sampling
}
