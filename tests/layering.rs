//! The layering of `src/` (docs/architecture.md), checked from the `crate::` paths of every
//! file outside its test module: a folder imports only folders of its own or a lower layer,
//! the folders' import graph has no circle, shared machinery imports no plan kind and a kind
//! imports no other kind. Any import that breaks a rule fails, unless listed in `KNOWN` (empty
//! today); an entry of `KNOWN` that no longer occurs fails too, so the list only shrinks.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// Top-level folders (or files) of `src/` by layer, lowest first.
const LAYERS: &[&[&str]] = &[
    &[
        "clock",
        "console",
        "solve",
        "model",
        "compensate",
        "progress_sink",
        "parallel",
        "allocator",
    ],
    &["session"],
    &["config"],
    &["plan"],
    &["extract"],
    &["sim", "sequencer", "devices"],
    &["method", "run", "document", "evaluate", "progress"],
    &["diagnose"],
    &["kinds"],
    &["replay", "monitor", "report", "history", "lib", "main"],
    &["serve", "export"],
];

/// The plan kinds: a path segment with one of these names belongs to that kind.
const KIND_NAMES: &[&str] = &[
    "multilateration",
    "rotary_tracer",
    "rotary_sphere",
    "probe_install",
    "hexapod",
];

/// Violations tolerated for now, as `file -> crate path: rule` (see the module comment):
/// none. An entry may be added only with the change that will remove it.
const KNOWN: &[&str] = &[];

/// The `.rs` files under `dir`, test modules kept in files of their own (`tests.rs`) left out.
fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.filter_map(Result::ok) {
        let path = entry.path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs")
            && path.file_name().is_some_and(|n| n != "tests.rs")
        {
            out.push(path);
        }
    }
}

/// The text before the file's test module.
fn without_tests(text: &str) -> &str {
    match text.find("#[cfg(test)]\nmod tests") {
        Some(i) => &text[..i],
        None => text,
    }
}

fn is_ident(c: char) -> bool {
    c.is_ascii_alphanumeric() || c == '_'
}

/// Module paths named after `crate::` in `text`, braces of `use` groups expanded; a path
/// stops at its first name that is not a module (one starting with a capital).
fn crate_paths(text: &str) -> Vec<Vec<String>> {
    fn parse(s: &[char], mut i: usize, prefix: &[String], out: &mut Vec<Vec<String>>) -> usize {
        let mut path = prefix.to_vec();
        loop {
            let start = i;
            while i < s.len() && is_ident(s[i]) {
                i += 1;
            }
            let name: String = s[start..i].iter().collect();
            if name.is_empty() || name.starts_with(|c: char| c.is_ascii_uppercase()) {
                if !name.is_empty() && !path.is_empty() {
                    out.push(path.clone());
                }
                break;
            }
            if i + 1 < s.len() && s[i] == ':' && s[i + 1] == ':' {
                path.push(name);
                i += 2;
                if i < s.len() && s[i] == '{' {
                    i += 1;
                    loop {
                        while i < s.len() && (s[i].is_whitespace() || s[i] == ',') {
                            i += 1;
                        }
                        if i >= s.len() || s[i] == '}' {
                            return i + 1;
                        }
                        i = parse(s, i, &path, out);
                        // Skip `as alias` and anything else up to the next item.
                        let mut depth = 0;
                        while i < s.len() {
                            match s[i] {
                                '{' => depth += 1,
                                '}' if depth == 0 => break,
                                '}' => depth -= 1,
                                ',' if depth == 0 => break,
                                _ => {}
                            }
                            i += 1;
                        }
                    }
                }
            } else {
                path.push(name);
                out.push(path.clone());
                break;
            }
        }
        i
    }
    let chars: Vec<char> = text.chars().collect();
    let mut out: Vec<Vec<String>> = Vec::new();
    let needle: Vec<char> = "crate::".chars().collect();
    let mut i = 0;
    while i + needle.len() <= chars.len() {
        let preceded_by_ident = i > 0 && (is_ident(chars[i - 1]) || chars[i - 1] == '$');
        if !preceded_by_ident && chars[i..i + needle.len()] == needle[..] {
            let mut found = Vec::new();
            i = parse(&chars, i + needle.len(), &[], &mut found).max(i + 1);
            for path in found {
                if !out.contains(&path) {
                    out.push(path);
                }
            }
        } else {
            i += 1;
        }
    }
    out
}

/// The kind a module path or a file (its segments under `src/`) belongs to: `kinds::<kind>`.
/// Models and numerical solvers named after a method (`solve::multilateration`,
/// `model::hexapod`) are shared machinery.
fn kind_of(segments: &[String]) -> Option<&'static str> {
    match segments {
        [first, second, ..] if first == "kinds" => {
            KIND_NAMES.iter().find(|k| *second == **k).copied()
        }
        _ => None,
    }
}

fn layer_of(folder: &str) -> Option<usize> {
    LAYERS.iter().position(|l| l.contains(&folder))
}

/// Every rule broken under `src`, as `file -> crate path: rule`.
fn violations(src: &Path) -> Vec<String> {
    let mut files = Vec::new();
    rust_files(src, &mut files);
    files.sort();
    let mut out = BTreeSet::new();
    let mut graph: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for file in &files {
        let rel = file.strip_prefix(src).unwrap_or(file);
        let segments: Vec<String> = rel
            .iter()
            .map(|s| s.to_string_lossy().trim_end_matches(".rs").to_string())
            .collect();
        let folder = segments[0].clone();
        let file_kind = kind_of(&segments);
        let Ok(text) = std::fs::read_to_string(file) else {
            out.insert(format!("{}: unreadable", rel.display()));
            continue;
        };
        for path in crate_paths(without_tests(&text)) {
            let target = &path[0];
            let shown = format!("{} -> crate::{}", rel.display(), path.join("::"));
            if target != &folder {
                graph
                    .entry(folder.clone())
                    .or_default()
                    .insert(target.clone());
                match (layer_of(&folder), layer_of(target)) {
                    (Some(from), Some(to)) if to > from => {
                        out.insert(format!("{shown}: imports a higher layer"));
                    }
                    (None, _) | (_, None) => {
                        out.insert(format!("{shown}: folder without a layer"));
                    }
                    _ => {}
                }
            }
            // The registry is the one list that names every kind.
            let is_registry = segments == ["kinds", "registry"];
            match (file_kind, kind_of(&path)) {
                (None, Some(kind)) if !is_registry => {
                    out.insert(format!("{shown}: shared machinery imports kind {kind}"));
                }
                (Some(a), Some(b)) if a != b => {
                    out.insert(format!("{shown}: kind {a} imports kind {b}"));
                }
                _ => {}
            }
        }
    }
    for cycle in cycles(&graph) {
        out.insert(format!("import circle: {}", cycle.join(" -> ")));
    }
    out.into_iter().collect()
}

/// The folders' import circles, each as the folders on it (smallest first).
fn cycles(graph: &BTreeMap<String, BTreeSet<String>>) -> Vec<Vec<String>> {
    let reaches = |from: &str, to: &str| {
        let mut seen = BTreeSet::new();
        let mut stack = vec![from.to_string()];
        while let Some(n) = stack.pop() {
            if n == to {
                return true;
            }
            if seen.insert(n.clone()) {
                stack.extend(graph.get(&n).into_iter().flatten().cloned());
            }
        }
        false
    };
    // Strongly connected groups of more than one folder.
    let mut groups: Vec<Vec<String>> = Vec::new();
    for node in graph.keys() {
        if groups.iter().any(|g| g.contains(node)) {
            continue;
        }
        let group: Vec<String> = graph
            .keys()
            .filter(|other| *other == node || (reaches(node, other) && reaches(other, node)))
            .cloned()
            .collect();
        if group.len() > 1 {
            groups.push(group);
        }
    }
    groups
}

#[test]
fn the_source_tree_keeps_its_layering() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let found = violations(&src);
    let known: BTreeSet<&str> = KNOWN.iter().copied().collect();
    let new: Vec<&String> = found
        .iter()
        .filter(|v| !known.contains(v.as_str()))
        .collect();
    let gone: Vec<&&str> = known
        .iter()
        .filter(|k| !found.iter().any(|v| v == **k))
        .collect();
    assert!(
        new.is_empty() && gone.is_empty(),
        "layering (docs/architecture.md):\nnew violations:\n  {}\nno longer found (remove from KNOWN):\n  {}",
        new.iter().map(|s| s.as_str()).collect::<Vec<_>>().join("\n  "),
        gone.iter().map(|s| **s).collect::<Vec<_>>().join("\n  ")
    );
}

fn tree(files: &[(&str, &str)]) -> tempfile::TempDir {
    let dir = tempfile::tempdir().expect("tempdir");
    for (path, text) in files {
        let path = dir.path().join(path);
        std::fs::create_dir_all(path.parent().expect("parent")).expect("mkdir");
        std::fs::write(path, text).expect("write");
    }
    dir
}

#[test]
fn a_shared_folder_that_imports_a_kind_fails() {
    let dir = tree(&[
        (
            "session/reader.rs",
            "use crate::kinds::hexapod::{config::HexapodConfig, plan};\n",
        ),
        (
            "kinds/hexapod/config.rs",
            "use crate::session::reader::Session;\n",
        ),
    ]);
    let found = violations(dir.path());
    assert_eq!(
        found,
        vec![
            "import circle: kinds -> session".to_string(),
            "session/reader.rs -> crate::kinds::hexapod::config: imports a higher layer"
                .to_string(),
            "session/reader.rs -> crate::kinds::hexapod::config: shared machinery imports kind hexapod"
                .to_string(),
            "session/reader.rs -> crate::kinds::hexapod::plan: imports a higher layer".to_string(),
            "session/reader.rs -> crate::kinds::hexapod::plan: shared machinery imports kind hexapod"
                .to_string(),
        ]
    );
}

#[test]
fn a_kind_that_imports_another_kind_fails_and_the_registry_may_name_them_all() {
    let dir = tree(&[
        (
            "kinds/hexapod/solve.rs",
            "fn f() { let _ = crate::kinds::probe_install::solve::solve; }\n",
        ),
        (
            "kinds/registry.rs",
            "use crate::kinds::{hexapod::Hexapod, probe_install::ProbeInstall};\n",
        ),
        ("run/mod.rs", "use crate::kinds::registry::KINDS;\n"),
    ]);
    // `run` (layer of the run machinery) importing `kinds` goes up a layer.
    assert_eq!(
        violations(dir.path()),
        vec![
            "kinds/hexapod/solve.rs -> crate::kinds::probe_install::solve::solve: kind hexapod \
             imports kind probe_install"
                .to_string(),
            "run/mod.rs -> crate::kinds::registry: imports a higher layer".to_string(),
        ]
    );
}

#[test]
fn use_groups_are_expanded() {
    let paths = crate_paths(
        "use crate::config::{hexapod as hx, probe_install::{Config, KIND}, Config as C};\n\
         let x = crate::sim::world::World::new(); let y = other_crate::sim::x;",
    );
    let shown: Vec<String> = paths.iter().map(|p| p.join("::")).collect();
    assert_eq!(
        shown,
        vec![
            "config::hexapod",
            "config::probe_install",
            "config",
            "sim::world"
        ]
    );
}
