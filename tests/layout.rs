//! The source tree keeps the shape ARCHITECTURE.md describes: no import cycle between the
//! folders of `src/`, no file over 900 lines and no function over 150 lines unless the file
//! says why, and no citation of documents outside the repository.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

const MAX_FILE_LINES: usize = 900;
const MAX_FUNCTION_LINES: usize = 150;

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).expect("readable source folder") {
        let path = entry.expect("readable entry").path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

fn sources() -> Vec<(PathBuf, String)> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    rust_files(&root, &mut files);
    files.sort();
    files
        .into_iter()
        .map(|path| {
            let text = std::fs::read_to_string(&path).expect("UTF-8 source");
            (path.strip_prefix(&root).expect("under src").to_path_buf(), text)
        })
        .collect()
}

/// The layer a source file belongs to: its folder under `src/`, or the file's stem for a file
/// directly in `src/` (`query`, `sys`, `lib`, `main`).
fn layer_of(relative: &Path) -> String {
    let first = relative.components().next().expect("non-empty path");
    let first = first.as_os_str().to_string_lossy();
    first.strip_suffix(".rs").unwrap_or(&first).to_string()
}

/// The layers a file's code names through `crate::LAYER` (comments and doc comments excluded).
fn imported_layers(text: &str) -> BTreeSet<String> {
    let mut layers = BTreeSet::new();
    for line in text.lines() {
        let code = line.split("//").next().unwrap_or_default();
        for (at, _) in code.match_indices("crate::") {
            let name: String = code[at + "crate::".len()..]
                .chars()
                .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                .collect();
            if name.chars().next().is_some_and(|c| c.is_ascii_lowercase()) {
                layers.insert(name);
            }
        }
    }
    layers
}

fn layer_imports() -> BTreeMap<String, BTreeSet<String>> {
    let mut graph: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for (path, text) in sources() {
        let layer = layer_of(&path);
        let imports = graph.entry(layer.clone()).or_default();
        imports.extend(imported_layers(&text).into_iter().filter(|l| *l != layer));
    }
    graph
}

/// A cycle through `node`, if the graph has one reachable from it.
fn find_cycle(
    graph: &BTreeMap<String, BTreeSet<String>>,
    node: &str,
    path: &mut Vec<String>,
    done: &mut BTreeSet<String>,
) -> Option<Vec<String>> {
    if let Some(at) = path.iter().position(|n| n == node) {
        let mut cycle = path[at..].to_vec();
        cycle.push(node.to_string());
        return Some(cycle);
    }
    if done.contains(node) {
        return None;
    }
    path.push(node.to_string());
    for next in graph.get(node).into_iter().flatten() {
        if let Some(cycle) = find_cycle(graph, next, path, done) {
            return Some(cycle);
        }
    }
    path.pop();
    done.insert(node.to_string());
    None
}

#[test]
fn folders_import_each_other_without_cycles() {
    let graph = layer_imports();
    let mut done = BTreeSet::new();
    for node in graph.keys() {
        if let Some(cycle) = find_cycle(&graph, node, &mut Vec::new(), &mut done) {
            panic!("import cycle between folders of src/: {}", cycle.join(" -> "));
        }
    }
    // The layering ARCHITECTURE.md states for the lower layers.
    let allowed: &[(&str, &[&str])] = &[
        ("format", &[]),
        ("store", &["format", "sys"]),
        ("inputs", &["format"]),
        ("kernels", &["format", "inputs", "sys"]),
        ("gpu", &["format", "inputs", "kernels"]),
        ("mesh", &["format"]),
        ("divide", &["format", "store", "inputs", "stages", "mesh", "sys"]),
    ];
    for (layer, may) in allowed {
        let imports = graph.get(*layer).cloned().unwrap_or_default();
        let extra: Vec<_> = imports.iter().filter(|l| !may.contains(&l.as_str())).collect();
        assert!(
            extra.is_empty(),
            "src/{layer} imports {extra:?}; ARCHITECTURE.md allows {may:?}"
        );
    }
}

#[test]
fn the_cycle_check_finds_a_cycle() {
    let mut graph: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    graph.entry("a".into()).or_default().insert("b".into());
    graph.entry("b".into()).or_default().insert("c".into());
    graph.entry("c".into()).or_default().insert("a".into());
    let cycle = find_cycle(&graph, "a", &mut Vec::new(), &mut BTreeSet::new());
    assert_eq!(cycle, Some(vec!["a".into(), "b".into(), "c".into(), "a".into()]));
    assert_eq!(
        imported_layers("use crate::store::Store; // crate::gpu\nlet x = crate::mesh::clip;"),
        BTreeSet::from(["mesh".to_string(), "store".to_string()])
    );
}

/// Functions longer than the limit: (name, first line, lines). A function starts at a line
/// with `fn NAME` and ends at the first `}` at its indentation (the tree is rustfmt-formatted).
fn long_functions(text: &str) -> Vec<(String, usize, usize)> {
    let lines: Vec<&str> = text.lines().collect();
    let mut found = Vec::new();
    for (start, line) in lines.iter().enumerate() {
        let trimmed = line.trim_start();
        let indent = &line[..line.len() - trimmed.len()];
        let Some(at) = trimmed.find("fn ") else { continue };
        let prefix = &trimmed[..at];
        let is_item = prefix
            .split_whitespace()
            .all(|w| w == "pub" || w.starts_with("pub(") || w == "const" || w == "unsafe" || w == "async");
        if !is_item || trimmed.ends_with(';') {
            continue;
        }
        let name: String = trimmed[at + 3..]
            .chars()
            .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
            .collect();
        let closing = format!("{indent}}}");
        if let Some(end) = lines.iter().skip(start + 1).position(|l| *l == closing) {
            let length = end + 2;
            if length > MAX_FUNCTION_LINES {
                found.push((name, start + 1, length));
            }
        }
    }
    found
}

#[test]
fn files_and_functions_stay_short_or_say_why() {
    let mut problems = Vec::new();
    for (path, text) in sources() {
        let lines = text.lines().count();
        if lines > MAX_FILE_LINES && !text.contains("// long file: ") {
            problems.push(format!("src/{}: {lines} lines (over {MAX_FILE_LINES})", path.display()));
        }
        for (name, line, length) in long_functions(&text) {
            if !text.contains(&format!("// long function {name}: ")) {
                problems.push(format!(
                    "src/{}:{line}: fn {name} has {length} lines (over {MAX_FUNCTION_LINES}); split it or say why in a `// long function {name}: ...` line",
                    path.display()
                ));
            }
        }
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

#[test]
fn sources_cite_only_documents_in_the_repository() {
    for (path, text) in sources() {
        assert!(
            !text.contains("DESIGN.md"),
            "src/{} cites DESIGN.md, which is not in the repository (cite ARCHITECTURE.md or format-spec.md)",
            path.display()
        );
    }
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    for document in ["ARCHITECTURE.md", "format-spec.md", "README.md"] {
        assert!(root.join(document).is_file(), "{document} is missing");
    }
}

/// The inside stays private (ARCHITECTURE.md, "Public and private"): the crate root declares
/// the private layers without `pub`, and no module anywhere is public but hidden from the docs.
#[test]
fn private_layers_stay_private() {
    let private = ["gpu", "kernels", "quality", "stages"];
    for (path, text) in sources() {
        let code: Vec<&str> = text
            .lines()
            .map(|l| l.trim())
            .filter(|l| !l.starts_with("//"))
            .collect();
        for pair in code.windows(2) {
            let [attribute, item] = pair else { continue };
            assert!(
                !(attribute.contains("doc(hidden)") && item.starts_with("pub mod")),
                "src/{}: `{item}` is public but hidden from the docs: make it private and reach it from tests through src/testing.rs",
                path.display()
            );
        }
        if path == Path::new("lib.rs") {
            for layer in private {
                assert!(
                    code.contains(&format!("mod {layer};").as_str()),
                    "src/lib.rs must declare `mod {layer};` (private; tests reach it through `octstore::testing`)"
                );
            }
        }
    }
}
