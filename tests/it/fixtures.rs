//! Every fixture is reproducible from the command recorded in fixtures/README.md.

use crate::common::{gangway_ok, root};

/// The `gangway simulate …` lines of the fixtures README.
fn recorded_commands() -> Vec<Vec<String>> {
    let readme = std::fs::read_to_string(root().join("fixtures/README.md")).unwrap();
    readme
        .lines()
        .filter_map(|l| l.trim().strip_prefix("gangway simulate "))
        .map(|rest| {
            std::iter::once("simulate".to_owned())
                .chain(rest.split_whitespace().map(str::to_owned))
                .collect()
        })
        .collect()
}

#[test]
fn every_fixture_regenerates_byte_for_byte() {
    let commands = recorded_commands();
    assert!(!commands.is_empty(), "fixtures/README.md lists no commands");
    let dir = tempfile::tempdir().unwrap();
    for mut args in commands {
        let out = args.iter().position(|a| a == "--out").expect("--out") + 1;
        let committed = root().join(&args[out]);
        let fresh = dir.path().join(committed.file_name().unwrap());
        args[out] = fresh.to_str().unwrap().to_owned();
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        gangway_ok(&args);
        assert!(
            std::fs::read(&fresh).unwrap() == std::fs::read(&committed).unwrap(),
            "{} differs from what `gangway {}` makes now",
            committed.display(),
            args.join(" ")
        );
    }
}
