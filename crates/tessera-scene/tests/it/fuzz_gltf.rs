//! A deterministic mutation fuzzer for glTF/GLB import that runs on the stable toolchain
//! (docs/fuzzing.md, "glTF/GLB import"): every file of the committed corpus
//! `tests/fuzz/corpus/gltf/` (small fixtures and the robustness issue's minimized
//! crashers) is imported as it is, then mutated `ITERATIONS` times with a fixed seed. Each
//! import must return `Ok` or `Err` without panicking (the importer's own panic guard
//! would turn a panic into an error, so the guard's message is treated as a failure too),
//! and an `Ok` scene must validate and stay within the documented caps.
//!
//! `TESSERA_FUZZ_ITERATIONS` and `TESSERA_FUZZ_SEED` override the bounds for a longer
//! local run; a failing input is written to the temporary directory and named in the
//! failure message, to be minimized and added to the corpus.

use std::path::PathBuf;
use tessera_scene::gltf_import::load_slice;
use tessera_scene::{Scene, MAX_IMAGE_TEXELS, MAX_NODES, MAX_SCENE_TEXELS, MAX_TRIANGLES};

/// Mutated inputs per run in CI: 6 to 11 s in the test profile on 2 shared cores
/// (35,000 to 60,000 imports a second).
const ITERATIONS: u64 = 400_000;
const SEED: u64 = 0x7e55_e4a0_f022_0016;

use tessera_testkit::gltf_gen::glb as join_glb;
use tessera_testkit::SplitMix64 as Rng;

fn corpus() -> Vec<(String, Vec<u8>)> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/fuzz/corpus/gltf");
    let mut files: Vec<(String, Vec<u8>)> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.unwrap().path())
        .map(|p| {
            let name = p.file_name().unwrap().to_string_lossy().into_owned();
            (name, std::fs::read(&p).unwrap())
        })
        .collect();
    files.sort();
    assert!(files.len() >= 10, "the corpus has {} files", files.len());
    files
}

/// Numbers that have found bugs in parsers and geometry code.
const NUMBERS: &[&str] = &[
    "0",
    "-1",
    "1",
    "2",
    "3",
    "4",
    "255",
    "65535",
    "65536",
    "4294967295",
    "4294967296",
    "2147483648",
    "-2147483649",
    "1e38",
    "-1e38",
    "3.5e38",
    "1e-45",
    "1e308",
    "1e400",
    "0.5",
    "5126",
    "5125",
    "5123",
    "5121",
    "5120",
    "5122",
    "16384",
    "32768",
    "1048577",
];

/// JSON fragments spliced in at a random place.
const TOKENS: &[&str] = &[
    "null", "[]", "{}", "\"\"", "[0,0,0]", "[1e38,1e38,1e38]", ",", "\"nodes\":[0]",
    "\"children\":[0]", "\"mesh\":0", "\"matrix\":[0,0,0,0,0,0,0,0,0,0,0,0,0,0,0,0]",
    "\"sparse\":{\"count\":3,\"indices\":{\"bufferView\":0,\"componentType\":5125},\"values\":{\"bufferView\":0}}",
    "\"uri\":\"data:image/png;base64,iVBORw0KGgo=\"", "\"byteStride\":252",
    "\"extensionsRequired\":[\"KHR_x\"]",
];

/// The JSON and binary chunks of a .glb (`None` for anything else).
fn split_glb(bytes: &[u8]) -> Option<(Vec<u8>, Vec<u8>)> {
    if !bytes.starts_with(b"glTF") || bytes.len() < 20 {
        return None;
    }
    let u32_at = |at: usize| -> Option<usize> {
        let b = bytes.get(at..at + 4)?;
        Some(u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize)
    };
    let jlen = u32_at(12)?;
    let json = bytes.get(20..20 + jlen)?.to_vec();
    let bin = match u32_at(20 + jlen) {
        Some(blen) => bytes.get(28 + jlen..28 + jlen + blen)?.to_vec(),
        None => Vec::new(),
    };
    Some((json, bin))
}

/// One structured mutation of JSON text: a number replaced, a token spliced in, a span
/// deleted or duplicated, or a byte changed.
fn mutate_json(rng: &mut Rng, json: &mut Vec<u8>) {
    if json.is_empty() {
        json.extend_from_slice(b"{}");
    }
    match rng.index(6) {
        0 | 1 => {
            // Replace the number starting at or after a random position.
            let from = rng.index(json.len());
            let digit = |b: &u8| b.is_ascii_digit() || b"-+.eE".contains(b);
            if let Some(start) = json[from..].iter().position(digit).map(|p| p + from) {
                let len = json[start..].iter().take_while(|b| digit(b)).count();
                let with = NUMBERS[rng.index(NUMBERS.len())].as_bytes();
                json.splice(start..start + len, with.iter().copied());
            }
        }
        2 => {
            let at = rng.index(json.len());
            let t = TOKENS[rng.index(TOKENS.len())].as_bytes();
            json.splice(at..at, t.iter().copied());
        }
        3 => {
            let at = rng.index(json.len());
            let len = rng.index(16).min(json.len() - at);
            json.drain(at..at + len);
        }
        4 => {
            let at = rng.index(json.len());
            let len = rng.index(64).min(json.len() - at);
            let copy: Vec<u8> = json[at..at + len].to_vec();
            let to = rng.index(json.len());
            json.splice(to..to, copy);
        }
        _ => {
            let at = rng.index(json.len());
            json[at] = b"{}[],:\"0123456789-.e \\"[rng.index(22)];
        }
    }
}

/// Raw byte mutations (bit flips, interesting bytes, truncation), which also reach the
/// GLB container fields and embedded images.
fn mutate_bytes(rng: &mut Rng, bytes: &mut Vec<u8>) {
    if bytes.is_empty() {
        bytes.push(0);
    }
    for _ in 0..=rng.index(4) {
        let at = rng.index(bytes.len());
        match rng.index(4) {
            0 => bytes[at] ^= 1 << rng.index(8),
            1 => bytes[at] = [0, 1, 0x7f, 0x80, 0xff][rng.index(5)],
            2 => {
                let v = [0u32, 1, 0x7fff_ffff, 0xffff_ffff, 0x4000_0000][rng.index(5)];
                let end = (at + 4).min(bytes.len());
                bytes[at..end].copy_from_slice(&v.to_le_bytes()[..end - at]);
            }
            _ => bytes.truncate(at.max(1)),
        }
    }
}

/// One mutated input from `base`.
fn mutant(rng: &mut Rng, base: &[u8]) -> Vec<u8> {
    match split_glb(base) {
        Some((mut json, mut bin)) => match rng.index(4) {
            0 | 1 => {
                for _ in 0..=rng.index(3) {
                    mutate_json(rng, &mut json);
                }
                join_glb(&json, &bin)
            }
            2 => {
                mutate_bytes(rng, &mut bin);
                join_glb(&json, &bin)
            }
            _ => {
                let mut b = base.to_vec();
                mutate_bytes(rng, &mut b);
                b
            }
        },
        None => {
            let mut b = base.to_vec();
            if rng.index(4) == 0 {
                mutate_bytes(rng, &mut b);
            } else {
                for _ in 0..=rng.index(3) {
                    mutate_json(rng, &mut b);
                }
            }
            b
        }
    }
}

/// What an `Ok` import must satisfy: it validates, and stays within the caps.
fn check_scene(scene: &Scene) -> Result<(), String> {
    scene.validate().map_err(|e| e.to_string())?;
    let texels: u64 = scene
        .images
        .iter()
        .map(|i| u64::from(i.width) * u64::from(i.height))
        .collect::<Vec<_>>()
        .iter()
        .try_fold(0u64, |sum, &t| {
            (t <= MAX_IMAGE_TEXELS)
                .then_some(sum + t)
                .ok_or(format!("an image of {t} texels"))
        })?;
    if texels > MAX_SCENE_TEXELS {
        return Err(format!("{texels} texels in all"));
    }
    if scene.stored_triangle_count() as u64 > MAX_TRIANGLES {
        return Err(format!("{} triangles", scene.stored_triangle_count()));
    }
    if scene.instances.len() as u64 > MAX_NODES * 64 {
        return Err(format!("{} instances", scene.instances.len()));
    }
    Ok(())
}

/// How an import ended.
#[derive(Debug, PartialEq)]
enum Outcome {
    Loaded,
    Refused,
    /// Refused after the importer's guard caught a panic inside it.
    Contained,
}

/// Imports `bytes`; `Err` describes a failure of the importer (a panic, or an `Ok` scene
/// that breaks an invariant), not an input it refused.
fn import(bytes: &[u8], name: &str) -> Result<Outcome, String> {
    let r = std::panic::catch_unwind(|| load_slice(bytes, name, None, None))
        .map_err(|_| "the import panicked".to_string())?;
    match r {
        Ok(scene) => check_scene(&scene).map(|()| Outcome::Loaded),
        Err(e) if e.to_string().contains("made the reader fail") => Ok(Outcome::Contained),
        Err(_) => Ok(Outcome::Refused),
    }
}

#[test]
fn mutated_gltf_and_glb_files_import_without_panicking_and_within_the_caps() {
    let env = |k: &str, d: u64| {
        std::env::var(k)
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(d)
    };
    let iterations = env("TESSERA_FUZZ_ITERATIONS", ITERATIONS);
    let seed = env("TESSERA_FUZZ_SEED", SEED);
    let corpus = corpus();
    let (mut loaded, mut contained) = (0u64, 0u64);
    for (name, bytes) in &corpus {
        // The corpus as committed: fixtures load, crashers are refused, nothing panics.
        let outcome = import(bytes, name).unwrap_or_else(|e| panic!("corpus file {name}: {e}"));
        let expected = if name.starts_with("crasher-") {
            Outcome::Refused
        } else {
            Outcome::Loaded
        };
        assert_eq!(outcome, expected, "corpus file {name}");
    }
    let mut rng = Rng(seed);
    let start = std::time::Instant::now();
    for i in 0..iterations {
        let (name, base) = &corpus[rng.index(corpus.len())];
        let input = mutant(&mut rng, base);
        match import(&input, name) {
            Ok(Outcome::Loaded) => loaded += 1,
            Ok(Outcome::Refused) => {}
            Ok(Outcome::Contained) => contained += 1,
            Err(e) => {
                let path = std::env::temp_dir().join(format!("tessera-fuzz-{seed:x}-{i}.bin"));
                let _ = std::fs::write(&path, &input);
                panic!(
                    "iteration {i} (seed {seed:#x}, from {name}): {e}; input written to {}",
                    path.display()
                );
            }
        }
    }
    let seconds = start.elapsed().as_secs_f64();
    eprintln!(
        "{iterations} mutated imports in {seconds:.1} s ({:.0} per second), {loaded} loaded, \
         {contained} refused after a contained panic",
        iterations as f64 / seconds.max(1e-9)
    );
    // The mutations must leave enough inputs valid to reach past the parser.
    assert!(
        loaded * 20 > iterations,
        "only {loaded} of {iterations} mutants loaded"
    );
}
