//! Wording shared by the evidence and the reasons: material lists, plurals, verb agreement.

use super::classify::Classes;
use crate::Scene;

/// "material 1 'glass'" or "materials 4 'plate0', 5 'plate1' and 2 more", optionally with
/// each material's description in parentheses.
pub(super) fn material_list(
    scene: &Scene,
    indices: &[usize],
    classes: &[Classes],
    detail: bool,
) -> String {
    const SHOWN: usize = 6;
    let item = |&i: &usize| {
        let name = &scene.materials[i].name;
        // The glTF importer already names materials "material 3 'light'".
        let label = match name.strip_prefix(&format!("material {i}")) {
            Some(rest) if rest.is_empty() || rest.starts_with(' ') => format!("{i}{rest}"),
            _ => format!("{i} '{name}'"),
        };
        if detail {
            format!("{label} ({})", classes[i].describe)
        } else {
            label
        }
    };
    let mut s = String::from(if indices.len() == 1 {
        "material "
    } else {
        "materials "
    });
    s += &indices
        .iter()
        .take(SHOWN)
        .map(item)
        .collect::<Vec<_>>()
        .join(", ");
    if indices.len() > SHOWN {
        s += &format!(" and {} more", indices.len() - SHOWN);
    }
    s
}

/// `plural(2, "light", "lights")` is "2 lights".
pub(super) fn plural(n: usize, one: &str, many: &str) -> String {
    format!("{n} {}", if n == 1 { one } else { many })
}

/// Subject-verb agreement: `verb("reflect", 1)` is "reflects", otherwise "reflect".
pub(super) fn verb(v: &str, n: usize) -> String {
    if n == 1 {
        format!("{v}s")
    } else {
        v.to_string()
    }
}
