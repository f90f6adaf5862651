//! The code map in docs/architecture.md against the code: the crate table
//! against the crates' manifests and `Cargo.lock`, each crate's module table
//! against the `crate::…` paths its files use, and no circle between the
//! modules of one crate. The document is the rule; this makes it one the
//! build keeps.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use crate::common::root;

/// One row of the crate table.
struct CrateRow {
    name: String,
    path: PathBuf,
    depends_on: BTreeSet<String>,
    may_not_depend_on: BTreeSet<String>,
}

/// The names in a table cell: each `code span`, or none for "—".
fn names(cell: &str) -> BTreeSet<String> {
    cell.split('`')
        .skip(1)
        .step_by(2)
        .map(str::to_owned)
        .chain(
            // Third-party crates are listed bare, comma-separated.
            cell.split(',')
                .map(str::trim)
                .filter(|w| !w.is_empty() && !w.contains('`') && *w != "—")
                .filter(|w| {
                    w.chars()
                        .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
                })
                .map(str::to_owned),
        )
        .collect()
}

/// The rows of the markdown table that follows `heading` in `doc`, split into
/// cells, without the header and separator rows.
fn table_after(doc: &str, heading: &str) -> Vec<Vec<String>> {
    let start = doc
        .find(heading)
        .unwrap_or_else(|| panic!("docs/architecture.md has no {heading:?}"));
    doc[start..]
        .lines()
        .skip_while(|l| !l.starts_with('|'))
        .take_while(|l| l.starts_with('|'))
        .skip(2)
        .map(|l| {
            l.trim_matches('|')
                .split(" | ")
                .map(|c| c.trim().to_owned())
                .collect()
        })
        .collect()
}

fn architecture() -> String {
    std::fs::read_to_string(root().join("docs/architecture.md")).unwrap()
}

fn crate_rows(doc: &str) -> Vec<CrateRow> {
    table_after(doc, "## Crates")
        .into_iter()
        .map(|cells| {
            assert_eq!(cells.len(), 5, "crate table row {cells:?}");
            CrateRow {
                name: cells[0].trim_matches('`').to_owned(),
                path: root().join(cells[1].trim_matches('`')),
                depends_on: names(&cells[3]),
                may_not_depend_on: names(&cells[4]),
            }
        })
        .collect()
}

/// The workspace's own crates a manifest depends on (normal and dev).
fn workspace_dependencies(manifest: &Path) -> BTreeSet<String> {
    let text = std::fs::read_to_string(manifest).unwrap();
    let manifest: toml::Table = text.parse().unwrap();
    ["dependencies", "dev-dependencies"]
        .iter()
        .filter_map(|section| manifest.get(*section).and_then(|d| d.as_table()))
        .flat_map(|deps| deps.iter())
        .filter(|(_, spec)| spec.get("path").is_some())
        .map(|(name, _)| name.clone())
        .collect()
}

/// Every package `package` pulls in, by `Cargo.lock` (which lists each
/// package's dependencies for every target and feature in use: a superset,
/// so a crate absent from it is absent from every build of `package`).
fn lock_closure(package: &str) -> BTreeSet<String> {
    let text = std::fs::read_to_string(root().join("Cargo.lock")).unwrap();
    let lock: toml::Table = text.parse().unwrap();
    let mut edges: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for p in lock["package"].as_array().unwrap() {
        let name = p["name"].as_str().unwrap().to_owned();
        let deps = p.get("dependencies").and_then(|d| d.as_array());
        let entry = edges.entry(name).or_default();
        for d in deps.into_iter().flatten() {
            // "name" or "name version" when two versions are locked.
            let dep = d.as_str().unwrap().split(' ').next().unwrap();
            entry.insert(dep.to_owned());
        }
    }
    let mut seen = BTreeSet::new();
    let mut stack = vec![package.to_owned()];
    while let Some(p) = stack.pop() {
        if seen.insert(p.clone()) {
            stack.extend(edges.get(&p).into_iter().flatten().cloned());
        }
    }
    seen
}

#[test]
fn the_crates_depend_as_the_code_map_says() {
    let doc = architecture();
    let rows = crate_rows(&doc);
    let workspace: toml::Table = std::fs::read_to_string(root().join("Cargo.toml"))
        .unwrap()
        .parse()
        .unwrap();
    let members: BTreeSet<PathBuf> = workspace["workspace"]["members"]
        .as_array()
        .unwrap()
        .iter()
        .map(|m| root().join(m.as_str().unwrap()))
        .chain([root().join(".")])
        .collect();
    let documented: BTreeSet<PathBuf> = rows.iter().map(|r| r.path.clone()).collect();
    assert_eq!(
        documented, members,
        "the crate table lists every workspace member"
    );

    for row in &rows {
        let manifest = row.path.join("Cargo.toml");
        let declared: toml::Table = std::fs::read_to_string(&manifest).unwrap().parse().unwrap();
        assert_eq!(
            declared["package"]["name"].as_str(),
            Some(row.name.as_str())
        );
        assert_eq!(
            workspace_dependencies(&manifest),
            row.depends_on,
            "{}: its workspace dependencies against the crate table",
            row.name
        );
        let pulled_in = lock_closure(&row.name);
        let forbidden: Vec<_> = row.may_not_depend_on.intersection(&pulled_in).collect();
        assert!(
            forbidden.is_empty(),
            "{} pulls in {forbidden:?}, which the crate table forbids it",
            row.name
        );
    }
}

/// Typed errors in the core (its lib.rs states the policy): `anyhow`, which
/// the crates below it pull in, is not one of its own dependencies.
#[test]
fn the_core_does_not_depend_on_anyhow() {
    let manifest: toml::Table = std::fs::read_to_string(root().join("crates/core/Cargo.toml"))
        .unwrap()
        .parse()
        .unwrap();
    for section in ["dependencies", "dev-dependencies"] {
        let deps = manifest.get(section).and_then(|d| d.as_table());
        assert!(
            deps.is_none_or(|d| !d.contains_key("anyhow")),
            "gangway-core [{section}] has anyhow: return the stage's own error type instead"
        );
    }
}

/// The first segment of every `crate::…` path in `source` (comments
/// skipped): `crate::a::b` and `crate::{a::b, c}` name `a` and `c`.
fn crate_paths(source: &str) -> BTreeSet<String> {
    let code: String = source
        .lines()
        .map(|l| l.split("//").next().unwrap())
        .collect::<Vec<_>>()
        .join("\n");
    let mut found = BTreeSet::new();
    let mut rest = code.as_str();
    while let Some(at) = rest.find("crate::") {
        let preceded_by_ident = rest[..at]
            .chars()
            .next_back()
            .is_some_and(|c| c.is_alphanumeric() || c == '_');
        rest = &rest[at + "crate::".len()..];
        if preceded_by_ident {
            continue; // `gangway_core::…` and the like
        }
        if let Some(group) = rest.strip_prefix('{') {
            // The top-level items of a (possibly nested) group.
            let (mut depth, mut item) = (0, String::new());
            for c in group.chars() {
                match c {
                    '{' => depth += 1,
                    '}' if depth == 0 => break,
                    '}' => depth -= 1,
                    ',' if depth == 0 => {
                        found.extend(first_ident(&item));
                        item.clear();
                        continue;
                    }
                    _ => {}
                }
                if depth == 0 {
                    item.push(c);
                }
            }
            found.extend(first_ident(&item));
        } else {
            found.extend(first_ident(rest));
        }
    }
    found
}

fn first_ident(text: &str) -> Option<String> {
    let ident: String = text
        .trim_start()
        .chars()
        .take_while(|c| c.is_alphanumeric() || *c == '_')
        .collect();
    (!ident.is_empty()).then_some(ident)
}

/// The `.rs` files of a module: `name.rs` and everything under `name/`.
fn module_files(src: &Path, module: &str) -> Vec<PathBuf> {
    let mut files = Vec::new();
    let file = src.join(format!("{module}.rs"));
    if file.exists() {
        files.push(file);
    }
    let mut dirs = vec![src.join(module)];
    while let Some(dir) = dirs.pop() {
        for entry in std::fs::read_dir(&dir).into_iter().flatten() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                dirs.push(path);
            } else if path.extension().is_some_and(|e| e == "rs") {
                files.push(path);
            }
        }
    }
    files
}

/// The top-level modules of a crate: the files and directories beside its
/// root file.
fn modules_in(src: &Path) -> BTreeSet<String> {
    std::fs::read_dir(src)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter_map(|p| {
            let stem = p.file_stem()?.to_str()?.to_owned();
            (p.is_dir() || p.extension().is_some_and(|e| e == "rs")).then_some(stem)
        })
        .filter(|m| m != "lib" && m != "main")
        .collect()
}

#[test]
fn modules_import_as_the_code_map_says_and_in_no_circle() {
    let doc = architecture();
    for row in crate_rows(&doc) {
        let src = row.path.join("src");
        let heading = format!("### `{}`", row.name);
        let table = table_after(&doc, &heading);
        let documented: BTreeSet<String> = table
            .iter()
            .map(|cells| cells[0].trim_matches('`').to_owned())
            .collect();
        assert_eq!(
            documented,
            modules_in(&src),
            "{}: the module table lists every module of {}",
            row.name,
            src.display()
        );

        // Which of its siblings each module uses.
        let mut uses: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
        for module in &documented {
            let mut used = BTreeSet::new();
            for file in module_files(&src, module) {
                let text = std::fs::read_to_string(&file).unwrap();
                used.extend(
                    crate_paths(&text)
                        .into_iter()
                        .filter(|m| m != module && documented.contains(m)),
                );
            }
            uses.insert(module.clone(), used);
        }
        for cells in &table {
            let module = cells[0].trim_matches('`');
            let forbidden: BTreeSet<String> = if cells[2] == "every other module" {
                documented
                    .iter()
                    .filter(|m| *m != module)
                    .cloned()
                    .collect()
            } else {
                names(&cells[2])
            };
            let unknown: Vec<_> = forbidden.difference(&documented).collect();
            assert!(
                unknown.is_empty(),
                "{}: `{module}` forbids unknown {unknown:?}",
                row.name
            );
            let broken: Vec<_> = uses[module].intersection(&forbidden).collect();
            assert!(
                broken.is_empty(),
                "{}: `{module}` imports {broken:?}, which its row in docs/architecture.md forbids",
                row.name
            );
        }
        if let Some(circle) = find_circle(&uses) {
            panic!(
                "{}: modules import each other: {}",
                row.name,
                circle.join(" → ")
            );
        }
    }
}

/// A circle in the module graph, if there is one (depth-first search).
fn find_circle(uses: &BTreeMap<String, BTreeSet<String>>) -> Option<Vec<String>> {
    fn visit(
        node: &str,
        uses: &BTreeMap<String, BTreeSet<String>>,
        path: &mut Vec<String>,
        done: &mut BTreeSet<String>,
    ) -> Option<Vec<String>> {
        if let Some(at) = path.iter().position(|p| p == node) {
            let mut circle = path[at..].to_vec();
            circle.push(node.to_owned());
            return Some(circle);
        }
        if done.contains(node) {
            return None;
        }
        path.push(node.to_owned());
        for next in uses.get(node).into_iter().flatten() {
            if let Some(circle) = visit(next, uses, path, done) {
                return Some(circle);
            }
        }
        path.pop();
        done.insert(node.to_owned());
        None
    }
    let mut done = BTreeSet::new();
    uses.keys()
        .find_map(|m| visit(m, uses, &mut Vec::new(), &mut done))
}

#[test]
fn the_import_scanner_reads_groups_and_skips_other_crates() {
    let source = "use crate::{a::b, c, d::{e, f}};\nuse crate::g::h;\n\
                  use gangway_core::site; // crate::commented\nlet x = crate::i::j();";
    let found: Vec<_> = crate_paths(source).into_iter().collect();
    assert_eq!(found, ["a", "c", "d", "g", "i"]);
    let circle: BTreeMap<String, BTreeSet<String>> = [
        ("a".to_owned(), BTreeSet::from(["b".to_owned()])),
        ("b".to_owned(), BTreeSet::from(["a".to_owned()])),
    ]
    .into();
    assert_eq!(find_circle(&circle).unwrap(), ["a", "b", "a"]);
}

/// The core reads no clock (what it measures comes through
/// `gangway_core::clock`, passed in). It reads files only where a site, a
/// floor plan's header, a survey, a calibration or a model is loaded, when
/// a pipeline is built and never while it serves: those loaders are listed
/// here, and a file read anywhere else fails (moving them behind a reader
/// the I/O crate passes in is the step left, docs/architecture.md).
#[test]
fn the_core_reads_no_clock_and_files_only_in_its_loaders() {
    const LOADERS: [&str; 6] = [
        "site.rs",
        "site/building.rs",
        "site/floorplan.rs",
        "locate/survey.rs",
        "locate/calibration.rs",
        "model/runtime.rs",
    ];
    let src = root().join("crates/core/src");
    let mut found = Vec::new();
    for module in modules_in(&src) {
        for file in module_files(&src, &module) {
            let text = std::fs::read_to_string(&file).unwrap();
            let relative = file
                .strip_prefix(&src)
                .unwrap()
                .to_str()
                .unwrap()
                .to_owned();
            let mut needles = vec!["Instant::now", "SystemTime"];
            if !LOADERS.contains(&relative.as_str()) {
                needles.extend(["std::fs", "File::open"]);
            }
            // Unit tests sit at the end of a file, in `mod tests`.
            let serving = text.split("#[cfg(test)]\nmod tests").next().unwrap();
            for (n, line) in serving.lines().enumerate() {
                let code = line.split("//").next().unwrap();
                for needle in &needles {
                    if code.contains(needle) {
                        found.push(format!("{relative}:{}: {needle}", n + 1));
                    }
                }
            }
        }
    }
    assert!(
        found.is_empty(),
        "the core reads a clock or a file:\n{}",
        found.join("\n")
    );
}
