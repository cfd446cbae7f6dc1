//! Docs that cannot drift: every `octstore` command line the README and the guide (`docs/`)
//! show names a verb and options that the command's `--help` lists, and the guide's `sh`
//! blocks run as written, in order, in one empty folder with the built binaries first on the
//! `PATH`.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::Command;

/// The binaries a document may call, by name.
fn binaries() -> BTreeMap<&'static str, PathBuf> {
    BTreeMap::from([
        ("octstore", PathBuf::from(env!("CARGO_BIN_EXE_octstore"))),
        (
            "octstore-gt-render",
            PathBuf::from(env!("CARGO_BIN_EXE_octstore-gt-render")),
        ),
        (
            "octstore-evaluate",
            PathBuf::from(env!("CARGO_BIN_EXE_octstore-evaluate")),
        ),
    ])
}

/// The README and every page of the guide, with their text.
fn documents() -> Vec<(PathBuf, String)> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut paths = vec![root.join("README.md")];
    let mut pages: Vec<PathBuf> = std::fs::read_dir(root.join("docs"))
        .expect("docs/ exists")
        .map(|entry| entry.expect("docs/ is readable").path())
        .filter(|path| path.extension().is_some_and(|e| e == "md"))
        .collect();
    pages.sort();
    assert!(pages.len() >= 5, "the guide in docs/ has {} pages", pages.len());
    paths.extend(pages);
    paths
        .into_iter()
        .map(|path| {
            let text = std::fs::read_to_string(&path).expect("a document is readable");
            (path, text)
        })
        .collect()
}

/// A fenced code block: its info string (`sh`, `python`, empty, ...) and its lines.
struct Block {
    info: String,
    lines: Vec<String>,
}

fn code_blocks(text: &str) -> Vec<Block> {
    let mut blocks = Vec::new();
    let mut open: Option<Block> = None;
    for line in text.lines() {
        let trimmed = line.trim_start();
        if let Some(info) = trimmed.strip_prefix("```") {
            match open.take() {
                Some(block) => blocks.push(block),
                None => {
                    open = Some(Block {
                        info: info.trim().to_string(),
                        lines: Vec::new(),
                    })
                }
            }
        } else if let Some(block) = open.as_mut() {
            block.lines.push(line.to_string());
        }
    }
    assert!(open.is_none(), "a code block is not closed");
    blocks
}

/// The inline code spans of a text (outside fenced blocks).
fn inline_spans(text: &str) -> Vec<String> {
    let mut spans = Vec::new();
    let mut in_block = false;
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            in_block = !in_block;
            continue;
        }
        if !in_block {
            spans.extend(line.split('`').skip(1).step_by(2).map(str::to_string));
        }
    }
    spans
}

/// One command line a document shows: the binary, its verb (for `octstore`) and the options.
#[derive(Debug)]
struct Shown {
    binary: String,
    verb: Option<String>,
    options: Vec<String>,
    line: String,
}

/// Options of `octstore` that come before the verb and take a value.
const GLOBAL_WITH_VALUE: [&str; 2] = ["--memory-budget", "--threads"];

/// The commands in a line of shell: each `octstore...` binary (also as `cargo run --release
/// [--bin NAME] --`) with the words after it up to the end of its pipeline stage.
fn commands_in(line: &str, verbs: &BTreeSet<String>) -> Vec<Shown> {
    let code = match line.find(" #") {
        Some(comment) => line.get(..comment).unwrap_or(line),
        None => line,
    };
    let words: Vec<&str> = code.split_whitespace().collect();
    let mut shown = Vec::new();
    let mut index = 0;
    while index < words.len() {
        let word = words.get(index).copied().unwrap_or_default();
        let binary = if word == "cargo" && words.get(index + 1) == Some(&"run") {
            // cargo run --release [--bin NAME] -- ARGS
            let rest = words.get(index..).unwrap_or_default();
            let Some(dashes) = rest.iter().position(|w| *w == "--") else {
                break;
            };
            let name = rest
                .iter()
                .position(|w| *w == "--bin")
                .and_then(|at| rest.get(at + 1))
                .copied();
            index += dashes;
            name.unwrap_or("octstore").to_string()
        } else {
            // `octstore` or a path to it, not a variable's value (`OCTSTORE_BIN=.../octstore`).
            let name = word.rsplit('/').next().unwrap_or(word);
            if word.contains('=') || !binaries().contains_key(name) {
                index += 1;
                continue;
            }
            name.to_string()
        };
        index += 1;
        let mut arguments = Vec::new();
        while let Some(argument) = words.get(index) {
            if matches!(*argument, "|" | "&&" | ";" | ">" | "2>&1" | "||") {
                break;
            }
            arguments.push(*argument);
            index += 1;
        }
        let mut verb = None;
        if binary == "octstore" {
            let mut at = 0;
            while let Some(argument) = arguments.get(at) {
                if GLOBAL_WITH_VALUE.contains(argument) {
                    at += 2;
                } else if argument.starts_with('-') {
                    at += 1;
                } else {
                    verb = Some(argument.to_string());
                    break;
                }
            }
            // A placeholder (`octstore VERB`, `octstore ...`) names no verb; a word does.
            if verb
                .as_ref()
                .is_some_and(|v| !v.chars().all(|c| c.is_ascii_lowercase() || c == '-'))
            {
                verb = None;
            }
            if let Some(unknown) = verb.as_ref().filter(|v| !verbs.contains(*v)) {
                panic!("{line}: `octstore {unknown}` is not a verb of octstore");
            }
        }
        let options = arguments
            .iter()
            .filter_map(|argument| option_name(argument))
            .filter(|option| option.len() > 2)
            .collect();
        shown.push(Shown {
            binary,
            verb,
            options,
            line: line.to_string(),
        });
    }
    shown
}

/// `--name` from an argument such as `--name`, `--name=VALUE`, `[--name`, `--a|--b]`.
fn option_name(argument: &str) -> Option<String> {
    let start = argument.find("--")?;
    let name: String = argument
        .get(start..)?
        .chars()
        .enumerate()
        .take_while(|(i, c)| *i < 2 || c.is_ascii_alphanumeric() || *c == '-')
        .map(|(_, c)| c)
        .collect();
    (name.len() > 2).then_some(name)
}

fn help_of(binary: &Path, verb: Option<&str>) -> String {
    let mut command = Command::new(binary);
    command.args(verb).arg("--help");
    let output = command.output().expect("the binary runs");
    assert!(output.status.success(), "{} {verb:?} --help failed", binary.display());
    String::from_utf8(output.stdout).expect("help is UTF-8")
}

fn octstore_verbs() -> BTreeSet<String> {
    let help = help_of(&binaries()["octstore"], None);
    let commands = help
        .split("Commands:")
        .nth(1)
        .expect("octstore --help lists its commands");
    let commands = commands.split("Options:").next().unwrap_or_default();
    commands
        .lines()
        .filter_map(|line| line.split_whitespace().next())
        .map(str::to_string)
        .collect()
}

#[test]
fn every_option_the_docs_show_is_in_the_help() {
    let verbs = octstore_verbs();
    assert!(
        verbs.contains("ingest") && verbs.contains("extract"),
        "verbs: {verbs:?}"
    );
    let mut helps: BTreeMap<(String, Option<String>), String> = BTreeMap::new();
    let mut problems = Vec::new();
    let mut checked = 0;
    for (path, text) in documents() {
        let mut lines: Vec<String> = code_blocks(&text)
            .into_iter()
            .filter(|block| !matches!(block.info.as_str(), "python" | "json" | "rust"))
            .flat_map(|block| block.lines)
            .collect();
        // Inline spans that show a command line: `octstore VERB ...` or `VERB --option ...`.
        for span in inline_spans(&text) {
            let first = span.split_whitespace().next().unwrap_or_default();
            if binaries().contains_key(first) {
                lines.push(span);
            } else if verbs.contains(first) && span.contains("--") && first != "help" {
                lines.push(format!("octstore {span}"));
            }
        }
        for line in &lines {
            for shown in commands_in(line, &verbs) {
                let key = (shown.binary.clone(), shown.verb.clone());
                let help = helps
                    .entry(key)
                    .or_insert_with(|| help_of(&binaries()[shown.binary.as_str()], shown.verb.as_deref()));
                for option in &shown.options {
                    checked += 1;
                    let listed = help.match_indices(option.as_str()).any(|(at, _)| {
                        !help
                            .get(at + option.len()..)
                            .unwrap_or_default()
                            .starts_with(|c: char| c.is_ascii_alphanumeric() || c == '-')
                    });
                    if !listed {
                        problems.push(format!(
                            "{}: `{}`: {} {} --help lists no {option}",
                            path.display(),
                            shown.line.trim(),
                            shown.binary,
                            shown.verb.as_deref().unwrap_or("")
                        ));
                    }
                }
            }
        }
    }
    assert!(
        checked > 100,
        "only {checked} options found in the docs: is the parser reading them?"
    );
    assert!(
        problems.is_empty(),
        "options the docs name that the commands do not have:\n{}",
        problems.join("\n")
    );
}

#[test]
fn the_guides_shell_blocks_run_as_written() {
    let bin_dir = binaries()["octstore"]
        .parent()
        .expect("the binary has a folder")
        .to_path_buf();
    let path = std::env::var_os("PATH").unwrap_or_default();
    let mut path_with_bins = vec![bin_dir];
    path_with_bins.extend(std::env::split_paths(&path));
    let path = std::env::join_paths(path_with_bins).expect("PATH joins");
    let mut ran = 0;
    for (document, text) in documents() {
        let script: Vec<String> = code_blocks(&text)
            .into_iter()
            .filter(|block| block.info == "sh")
            .flat_map(|block| block.lines)
            .collect();
        if script.is_empty() {
            continue;
        }
        let folder = tempfile::tempdir().expect("a temporary folder");
        for line in &script {
            let output = Command::new("bash")
                .args(["-euo", "pipefail", "-c", line])
                .current_dir(folder.path())
                .env("PATH", &path)
                .env("OCTSTORE_LOG", "warn")
                .output()
                .expect("bash runs");
            assert!(
                output.status.success(),
                "{}: `{line}` failed ({}):\n{}{}",
                document.display(),
                output.status,
                String::from_utf8_lossy(&output.stdout),
                String::from_utf8_lossy(&output.stderr)
            );
            ran += 1;
        }
    }
    assert!(ran >= 10, "only {ran} commands of the guide ran");
}
