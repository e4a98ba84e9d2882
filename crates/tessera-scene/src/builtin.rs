//! Built-in scenes, addressed as `builtin:NAME`.
//!
//! | name | what it is | why it exists |
//! |---|---|---|
//! | `cornell-box` | the classic Cornell box | the standard comparison scene |
//! | `veach-mis` | Veach & Guibas 1995 figure 2 | multiple importance sampling |
//! | `furnace` | a closed, uniformly emitting diffuse box | an analytic answer |
//! | `caustic` | a glass sphere on a floor under a small light | refraction and caustics |
//!
//! Every scene is in metres and radiometric units (radiance in W/(m² sr), linear RGB).
//! The functions below document their geometry, materials and emission.

use crate::{Camera, Material, MaterialKind, Mesh, Scene, SceneError, Sphere};
use glam::{Mat4, Vec3};

/// The names accepted by [`load`].
pub const NAMES: [&str; 4] = ["cornell-box", "veach-mis", "furnace", "caustic"];

/// Builds the built-in scene `name` (without the `builtin:` prefix).
pub fn load(name: &str) -> Result<Scene, SceneError> {
    let scene = match name {
        "cornell-box" => cornell_box(),
        "veach-mis" => veach_mis(),
        "furnace" => furnace(),
        "caustic" => caustic(),
        _ => {
            return Err(SceneError::Unknown(
                format!("builtin:{name}"),
                NAMES.map(|n| format!("builtin:{n}")).join(", "),
            ))
        }
    };
    scene.validate()?;
    Ok(scene)
}

/// A camera at `eye` looking at `target` with +Y up and the given vertical field of view
/// in degrees.
pub fn look_at_camera(eye: Vec3, target: Vec3, up: Vec3, yfov_degrees: f32) -> Camera {
    // glTF convention: the camera looks down its local -Z with +Y up.
    let forward = (target - eye).normalize();
    let right = forward.cross(up).normalize();
    let true_up = right.cross(forward);
    Camera {
        name: None,
        world_from_camera: Mat4::from_cols(
            right.extend(0.0),
            true_up.extend(0.0),
            (-forward).extend(0.0),
            eye.extend(1.0),
        ),
        yfov: yfov_degrees.to_radians(),
        aspect_ratio: None,
        aperture_radius: 0.0,
        focus_distance: 1.0,
    }
}

/// Appends a quad `a b c d` (counter-clockwise seen from the front) as two triangles.
fn quad(name: &str, material: u32, a: Vec3, b: Vec3, c: Vec3, d: Vec3) -> Mesh {
    Mesh {
        name: name.to_string(),
        positions: vec![a, b, c, d],
        normals: None,
        uvs: vec![],
        tangents: None,
        colors: None,
        indices: vec![[0, 1, 2], [0, 2, 3]],
        material,
    }
}

/// A convex block from its top face (four corners at height `top`, in order) extruded down to
/// y = 0: five quads (the bottom is hidden on the floor and omitted), outward-facing.
fn block(name: &str, material: u32, top: [[f32; 2]; 4], height: f32) -> Vec<Mesh> {
    let t = |i: usize| Vec3::new(top[i][0], height, top[i][1]);
    let b = |i: usize| Vec3::new(top[i][0], 0.0, top[i][1]);
    // Orient the top face upward: counter-clockwise seen from +y.
    let n = (t(1) - t(0)).cross(t(2) - t(0));
    let order: [usize; 4] = if n.y > 0.0 {
        [0, 1, 2, 3]
    } else {
        [3, 2, 1, 0]
    };
    let mut meshes = vec![quad(
        &format!("{name}-top"),
        material,
        t(order[0]),
        t(order[1]),
        t(order[2]),
        t(order[3]),
    )];
    for k in 0..4 {
        let (i, j) = (order[k], order[(k + 1) % 4]);
        // Side quad, counter-clockwise seen from outside (top face is CCW seen from above,
        // so walking i -> j the outside is on the right; b(j), b(i), t(i), t(j) faces out).
        meshes.push(quad(
            &format!("{name}-side{k}"),
            material,
            b(i),
            b(j),
            t(j),
            t(i),
        ));
    }
    meshes
}

/// The Cornell box, after the Cornell University measurements (axis-aligned variant, as in
/// Bitterli's and Mitsuba's renditions), in metres.
///
/// - Room: x in [0, 0.5528], y in [0, 0.5488], z in [0, 0.5592]; the open side faces -z.
///   Floor, ceiling and back wall white (albedo 0.725, 0.71, 0.68), the wall at x = 0.5528
///   red (0.63, 0.065, 0.05), the wall at x = 0 green (0.14, 0.45, 0.091). Seen from the
///   camera, red is on the left.
/// - Two white blocks: the short one 0.165 high, the tall one 0.33 high, rotated as in the
///   original data.
/// - Light: a one-sided quad x in [0.213, 0.343], z in [0.227, 0.332], 1 mm below the
///   ceiling, facing down, radiance (17, 12, 4) W/(m² sr); area 0.01365 m².
/// - Camera: at (0.278, 0.273, -0.8) looking along +z, vertical field of view 39.3077°
///   (35 mm lens on a 25 mm film); 512 x 512 by default.
pub fn cornell_box() -> Scene {
    let white = Vec3::new(0.725, 0.71, 0.68);
    let materials = vec![
        Material::diffuse("white", white),
        Material::diffuse("red", Vec3::new(0.63, 0.065, 0.05)),
        Material::diffuse("green", Vec3::new(0.14, 0.45, 0.091)),
        Material {
            name: "light".into(),
            kind: MaterialKind::Diffuse {
                albedo: Vec3::splat(0.78),
            },
            emission: Vec3::new(17.0, 12.0, 4.0),
            double_sided: false,
        },
    ];
    let (x1, y1, z1) = (0.5528, 0.5488, 0.5592);
    let v = Vec3::new;
    let mut meshes = vec![
        quad(
            "floor",
            0,
            v(0.0, 0.0, 0.0),
            v(0.0, 0.0, z1),
            v(x1, 0.0, z1),
            v(x1, 0.0, 0.0),
        ),
        quad(
            "ceiling",
            0,
            v(0.0, y1, 0.0),
            v(x1, y1, 0.0),
            v(x1, y1, z1),
            v(0.0, y1, z1),
        ),
        quad(
            "back",
            0,
            v(0.0, 0.0, z1),
            v(0.0, y1, z1),
            v(x1, y1, z1),
            v(x1, 0.0, z1),
        ),
        quad(
            "red-wall",
            1,
            v(x1, 0.0, 0.0),
            v(x1, 0.0, z1),
            v(x1, y1, z1),
            v(x1, y1, 0.0),
        ),
        quad(
            "green-wall",
            2,
            v(0.0, 0.0, 0.0),
            v(0.0, y1, 0.0),
            v(0.0, y1, z1),
            v(0.0, 0.0, z1),
        ),
        quad(
            "light",
            3,
            v(0.343, y1 - 0.001, 0.227),
            v(0.343, y1 - 0.001, 0.332),
            v(0.213, y1 - 0.001, 0.332),
            v(0.213, y1 - 0.001, 0.227),
        ),
    ];
    meshes.extend(block(
        "short-block",
        0,
        [
            [0.130, 0.065],
            [0.082, 0.225],
            [0.240, 0.272],
            [0.290, 0.114],
        ],
        0.165,
    ));
    meshes.extend(block(
        "tall-block",
        0,
        [
            [0.423, 0.247],
            [0.265, 0.296],
            [0.314, 0.456],
            [0.472, 0.406],
        ],
        0.330,
    ));
    Scene {
        name: "builtin:cornell-box".into(),
        camera: look_at_camera(
            v(0.278, 0.273, -0.8),
            v(0.278, 0.273, 0.0),
            Vec3::Y,
            39.3077,
        ),
        meshes,
        prototypes: Vec::new(),
        instances: Vec::new(),
        spheres: vec![],
        materials,
        textures: vec![],
        images: vec![],
        warnings: vec![],
        lights: vec![],
        environment: None,
        environment_map: None,
        default_resolution: (512, 512),
        animated: false,
    }
}

/// Veach & Guibas 1995, figure 2: glossy highlights from four spherical lights of equal
/// power on four plates of increasing smoothness.
///
/// - Lights: spheres at x = -3.75, -1.25, 1.25, 3.75 (y = 0, z = 0) of radius 0.9, 0.3, 0.1,
///   0.0333; radiance 1.2346, 11.111, 100, 901.8 W/(m² sr), so that L·r² = 1 and all four emit
///   the same power (4π²·L·r² ≈ 39.5 W per channel).
/// - Plates: four 8 m x 1.5 m rectangles below and in front of the lights, each tilted so
///   that it mirrors the light row toward the camera. Modified Phong, kd = 0.05 (grey),
///   ks = 0.75, exponents 50, 300, 2000, 15000 from the farthest (roughest) to the nearest
///   (smoothest).
/// - A dark diffuse floor (albedo 0.1) and back wall catch the diffuse light.
/// - Camera at (0, 2, 15) looking at (0, -2, 2.5), vertical field of view 28°; 768 x 512.
pub fn veach_mis() -> Scene {
    let v = Vec3::new;
    let eye = v(0.0, 2.0, 15.0);
    let radii = [0.9f32, 0.3, 0.1, 0.0333];
    let xs = [-3.75f32, -1.25, 1.25, 3.75];
    let mut materials = vec![Material::diffuse("floor", Vec3::splat(0.1))];
    let mut spheres = Vec::new();
    for (i, (&r, &x)) in radii.iter().zip(xs.iter()).enumerate() {
        materials.push(Material {
            name: format!("light{i}"),
            kind: MaterialKind::Diffuse { albedo: Vec3::ZERO },
            emission: Vec3::splat(1.0 / (r * r)),
            double_sided: false,
        });
        spheres.push(Sphere {
            center: v(x, 0.0, 0.0),
            radius: r,
            material: materials.len() as u32 - 1,
        });
    }
    let exponents = [50.0f32, 300.0, 2000.0, 15000.0];
    // Plate centres (far to near) and the point on the light row they mirror.
    // Chosen so the camera sees them at 12.5°, 17°, 21.5° and 26° below the horizon.
    let centers = [
        v(0.0, -1.10, 1.0),
        v(0.0, -1.91, 2.2),
        v(0.0, -2.57, 3.4),
        v(0.0, -3.07, 4.6),
    ];
    let light_row = v(0.0, 0.0, 0.0);
    let mut meshes = Vec::new();
    for (k, (&c, &n)) in centers.iter().zip(exponents.iter()).enumerate() {
        materials.push(Material {
            name: format!("plate{k}"),
            kind: MaterialKind::Phong {
                kd: Vec3::splat(0.05),
                ks: Vec3::splat(0.75),
                exponent: n,
            },
            emission: Vec3::ZERO,
            double_sided: false,
        });
        let m = materials.len() as u32 - 1;
        // The plate normal is the half vector between the directions to the camera and to
        // the light row, so the lights' reflections land on the plate.
        let normal = ((eye - c).normalize() + (light_row - c).normalize()).normalize();
        let along = Vec3::X;
        let across = normal.cross(along).normalize() * 0.75;
        let a = c - along * 4.0 - across;
        let b = c + along * 4.0 - across;
        let d = c + along * 4.0 + across;
        let e = c - along * 4.0 + across;
        let mut q = quad(&format!("plate{k}"), m, a, b, d, e);
        if (b - a).cross(d - a).dot(normal) < 0.0 {
            q.indices = vec![[0, 2, 1], [0, 3, 2]];
        }
        meshes.push(q);
    }
    meshes.push(quad(
        "floor",
        0,
        v(-10.0, -4.0, -4.0),
        v(-10.0, -4.0, 12.0),
        v(10.0, -4.0, 12.0),
        v(10.0, -4.0, -4.0),
    ));
    meshes.push(quad(
        "back",
        0,
        v(-10.0, -4.0, -4.0),
        v(10.0, -4.0, -4.0),
        v(10.0, 8.0, -4.0),
        v(-10.0, 8.0, -4.0),
    ));
    Scene {
        name: "builtin:veach-mis".into(),
        camera: look_at_camera(eye, v(0.0, -2.0, 2.5), Vec3::Y, 28.0),
        meshes,
        prototypes: Vec::new(),
        instances: Vec::new(),
        spheres,
        materials,
        textures: vec![],
        images: vec![],
        warnings: vec![],
        lights: vec![],
        environment: None,
        environment_map: None,
        default_resolution: (768, 512),
        animated: false,
    }
}

/// Albedo of the furnace's walls.
pub const FURNACE_ALBEDO: f32 = 0.8;
/// Emitted radiance of the furnace's walls, W/(m² sr).
pub const FURNACE_EMISSION: f32 = 0.5;

/// The furnace: the inside of a closed unit cube whose walls are Lambertian with albedo
/// [`FURNACE_ALBEDO`] and emit [`FURNACE_EMISSION`] uniformly, seen from its centre.
///
/// Analytic answer: in a closed enclosure with uniform emission `Le` and albedo `a` the
/// radiance is the same everywhere and in every direction, `L = Le + a L`, so
/// `L = Le / (1 - a) = 2.5` W/(m² sr) in every pixel and channel (with unlimited path depth).
/// The walls face inward; 128 x 128 by default.
pub fn furnace() -> Scene {
    let v = Vec3::new;
    let materials = vec![Material {
        name: "wall".into(),
        kind: MaterialKind::Diffuse {
            albedo: Vec3::splat(FURNACE_ALBEDO),
        },
        emission: Vec3::splat(FURNACE_EMISSION),
        double_sided: false,
    }];
    let (l, h) = (-0.5, 0.5);
    // Inward-facing quads (counter-clockwise seen from inside).
    let mut meshes = vec![
        quad("floor", 0, v(l, l, l), v(h, l, l), v(h, l, h), v(l, l, h)),
        quad("ceiling", 0, v(l, h, l), v(l, h, h), v(h, h, h), v(h, h, l)),
        quad("back", 0, v(l, l, l), v(l, h, l), v(h, h, l), v(h, l, l)),
        quad("front", 0, v(l, l, h), v(h, l, h), v(h, h, h), v(l, h, h)),
        quad("left", 0, v(l, l, l), v(l, l, h), v(l, h, h), v(l, h, l)),
        quad("right", 0, v(h, l, l), v(h, h, l), v(h, h, h), v(h, l, h)),
    ];
    // Orient every triangle toward the centre, whatever order the corners were listed in.
    for m in &mut meshes {
        for t in &mut m.indices {
            let [a, b, c] = t.map(|i| m.positions[i as usize]);
            if (b - a).cross(c - a).dot(-(a + b + c)) < 0.0 {
                t.swap(1, 2);
            }
        }
    }
    Scene {
        name: "builtin:furnace".into(),
        camera: look_at_camera(Vec3::ZERO, v(0.0, 0.0, -1.0), Vec3::Y, 60.0),
        meshes,
        prototypes: Vec::new(),
        instances: Vec::new(),
        spheres: vec![],
        materials,
        textures: vec![],
        images: vec![],
        warnings: vec![],
        lights: vec![],
        environment: None,
        environment_map: None,
        default_resolution: (128, 128),
        animated: false,
    }
}

/// The caustic scene: a smooth glass sphere (ior 1.5, radius 0.5, resting on the floor at the
/// origin) on a white diffuse floor (albedo 0.8, 10 m x 10 m at y = 0), lit from above and
/// slightly behind by a small spherical light (radius 0.05 at (0.3, 2.5, -0.5), radiance
/// 2000 W/(m² sr)), plus a dim uniform environment (0.02) so the floor is not black away from
/// the light. The glass focuses the light into a bright caustic on the floor.
/// Camera at (0, 1.6, 4) looking at (0, 0.4, 0), 40°; 640 x 480.
pub fn caustic() -> Scene {
    let v = Vec3::new;
    let materials = vec![
        Material::diffuse("floor", Vec3::splat(0.8)),
        Material {
            name: "glass".into(),
            kind: MaterialKind::Dielectric {
                ior: 1.5,
                roughness: 0.0,
                tint: Vec3::ONE,
            },
            emission: Vec3::ZERO,
            double_sided: false,
        },
        Material {
            name: "light".into(),
            kind: MaterialKind::Diffuse { albedo: Vec3::ZERO },
            emission: Vec3::splat(2000.0),
            double_sided: false,
        },
    ];
    let meshes = vec![quad(
        "floor",
        0,
        v(-5.0, 0.0, -5.0),
        v(-5.0, 0.0, 5.0),
        v(5.0, 0.0, 5.0),
        v(5.0, 0.0, -5.0),
    )];
    let spheres = vec![
        Sphere {
            center: v(0.0, 0.5, 0.0),
            radius: 0.5,
            material: 1,
        },
        Sphere {
            center: v(0.3, 2.5, -0.5),
            radius: 0.05,
            material: 2,
        },
    ];
    Scene {
        name: "builtin:caustic".into(),
        camera: look_at_camera(v(0.0, 1.6, 4.0), v(0.0, 0.4, 0.0), Vec3::Y, 40.0),
        meshes,
        prototypes: Vec::new(),
        instances: Vec::new(),
        spheres,
        materials,
        textures: vec![],
        images: vec![],
        warnings: vec![],
        lights: vec![],
        environment: Some(Vec3::splat(0.02)),
        environment_map: None,
        default_resolution: (640, 480),
        animated: false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_builtin_loads_and_validates() {
        for name in NAMES {
            let s = load(name).unwrap();
            assert!(s.triangle_count() > 0, "{name}");
        }
        assert!(load("nope").is_err());
    }

    #[test]
    fn cornell_light_faces_down_and_walls_face_in() {
        let s = cornell_box();
        let light = s.meshes.iter().find(|m| m.name == "light").unwrap();
        let [a, b, c] = light.indices[0].map(|i| light.positions[i as usize]);
        assert!((b - a).cross(c - a).y < 0.0);
        let floor = &s.meshes[0];
        let [a, b, c] = floor.indices[0].map(|i| floor.positions[i as usize]);
        assert!((b - a).cross(c - a).y > 0.0);
    }

    #[test]
    fn furnace_walls_face_inward() {
        let s = furnace();
        for m in &s.meshes {
            for t in &m.indices {
                let [a, b, c] = t.map(|i| m.positions[i as usize]);
                let n = (b - a).cross(c - a);
                let centroid = (a + b + c) / 3.0;
                assert!(n.dot(-centroid) > 0.0, "{} faces outward", m.name);
            }
        }
    }
}
