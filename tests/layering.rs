//! The library's modules form layers, and a module uses only modules on lower layers (data
//! flows one way: scene → render → estimate → output → experiment). This reads every
//! `crate::…` path in `src/` (the binary's `src/cli` excepted: it sits on top) and fails on an
//! arrow that points up or sideways. The layers are documented in docs/design.md.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

/// Lowest first. A module may use the modules of lower layers only.
const LAYERS: &[&[&str]] = &[
    &["checked", "error", "math"],
    &["cleanup", "memory"],
    &["accel", "imageio", "sampling"],
    &["envmap", "metrics", "noise"],
    &["scene"],
    &["render"],
    &["estimate"],
    &["output"],
    &["experiment"],
];

fn layer(module: &str) -> Option<usize> {
    LAYERS.iter().position(|l| l.contains(&module))
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            rust_files(&p, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
}

/// The top-level modules a file's code names through `crate::`: `crate::a::b`, and each item
/// of `use crate::{a, b::c}`. Comments (doc links) and the unit tests at the end of a file
/// (`#[cfg(test)] mod tests`, which may use any module) are not read.
fn used_modules(text: &str) -> BTreeSet<String> {
    let code = text.split("#[cfg(test)]\nmod tests").next().unwrap_or("");
    let code: String = code
        .lines()
        .filter(|l| !l.trim_start().starts_with("//"))
        .map(|l| format!("{l}\n"))
        .collect();
    let text = code.as_str();
    let mut out = BTreeSet::new();
    let ident = |s: &str| -> String {
        s.chars()
            .take_while(|c| c.is_alphanumeric() || *c == '_')
            .collect()
    };
    let mut rest = text;
    while let Some(i) = rest.find("crate::") {
        rest = &rest[i + "crate::".len()..];
        if let Some(group) = rest.strip_prefix('{') {
            // Top-level items of the group, split at commas outside nested braces.
            let mut depth = 0;
            let mut start = 0;
            for (j, c) in group.char_indices() {
                match c {
                    '{' => depth += 1,
                    '}' if depth == 0 => {
                        out.insert(ident(group[start..j].trim()));
                        break;
                    }
                    '}' => depth -= 1,
                    ',' if depth == 0 => {
                        out.insert(ident(group[start..j].trim()));
                        start = j + 1;
                    }
                    _ => {}
                }
            }
        } else {
            out.insert(ident(rest));
        }
    }
    out.remove("");
    out
}

#[test]
fn modules_use_only_lower_layers() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    rust_files(&src, &mut files);
    let mut arrows = Vec::new();
    let mut checked = 0;
    for f in &files {
        let rel = f.strip_prefix(&src).unwrap();
        let top = rel
            .components()
            .next()
            .unwrap()
            .as_os_str()
            .to_string_lossy()
            .trim_end_matches(".rs")
            .to_string();
        if matches!(top.as_str(), "lib" | "main" | "cli") {
            continue;
        }
        let own = layer(&top).unwrap_or_else(|| {
            panic!("src/{top} is on no layer: add it to LAYERS and to docs/design.md")
        });
        let text = std::fs::read_to_string(f).unwrap();
        for used in used_modules(&text) {
            checked += 1;
            if used == top || used == "VERSION" || used == "Error" || used == "Result" {
                continue;
            }
            match layer(&used) {
                Some(l) if l < own => {}
                Some(_) => arrows.push(format!("{} uses crate::{used}", rel.display())),
                None => arrows.push(format!("{} uses crate::{used}, on no layer", rel.display())),
            }
        }
    }
    assert!(
        checked > 50,
        "too few paths read ({checked}) to mean anything"
    );
    assert!(
        arrows.is_empty(),
        "arrows that point up or sideways:\n{}",
        arrows.join("\n")
    );
}

#[test]
fn the_reader_finds_grouped_and_nested_paths() {
    let m = used_modules(
        "use crate::{render::{Lights, Renderer}, scene::Scene};\nlet x = crate::math::atan2(1.0, 2.0);",
    );
    assert_eq!(
        m.into_iter().collect::<Vec<_>>(),
        ["math", "render", "scene"]
    );
}
