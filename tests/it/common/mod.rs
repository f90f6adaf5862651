//! Helpers shared by the integration tests: running the built `gangway` binary
//! from the repository root.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The repository root (tests run with it as the working directory).
pub(crate) fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Runs `gangway` with `args` from the repository root.
pub(crate) fn gangway(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_gangway"))
        .args(args)
        .current_dir(root())
        .env("RUST_LOG", "warn")
        .output()
        .expect("the gangway binary runs")
}

/// Runs `gangway` and returns its stdout, failing the test with stderr if it
/// exits non-zero.
pub(crate) fn gangway_ok(args: &[&str]) -> String {
    let out = gangway(args);
    assert!(
        out.status.success(),
        "gangway {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).expect("UTF-8 output")
}

/// Runs `gangway`, failing the test unless it exits non-zero saying `says`
/// on stderr.
pub(crate) fn gangway_refused(args: &[&str], says: &str) {
    let out = gangway(args);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && stderr.contains(says),
        "gangway {args:?} should have refused, saying `{says}`: {stderr}"
    );
}

/// The real survey beside the checkout (`../shared/data/uci-ble-rssi`);
/// without it the test cannot run ([`cannot_run`]).
pub(crate) fn uci_survey() -> Option<PathBuf> {
    shared_data("uci-ble-rssi/iBeacon_RSSI_Labeled.csv")
}

/// A file or directory under `../shared/data`, the real data beside the
/// checkout; without it the test cannot run ([`cannot_run`]).
pub(crate) fn shared_data(relative: &str) -> Option<PathBuf> {
    let p = root().join("../shared/data").join(relative);
    if p.exists() {
        return Some(p);
    }
    cannot_run(&format!(
        "no {} (the real data beside the checkout)",
        p.display()
    ));
    None
}

/// A test that cannot run here because what it needs is missing (`needs`
/// says what, and how to get it). That fails the test, so the summary says
/// so and a green run means every test ran; on a machine that lacks it on
/// purpose, `GANGWAY_ALLOW_SKIP=1` skips such tests with a note instead,
/// except under CI (`CI` set), which must have everything.
pub(crate) fn cannot_run(needs: &str) {
    let skip = std::env::var_os("CI").is_none() && std::env::var_os("GANGWAY_ALLOW_SKIP").is_some();
    assert!(
        skip,
        "cannot run: {needs}; .ci/run installs what the tests need (outside CI, \
         GANGWAY_ALLOW_SKIP=1 skips such tests instead)"
    );
    eprintln!("skipped: {needs}");
}

/// Writes `text` to `name` inside `dir` and returns the path.
pub(crate) fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).expect("write a test file");
    p
}

/// The model of `kind` in the JSON summary of `gangway train --json`.
pub(crate) fn trained<'a>(summary: &'a serde_json::Value, kind: &str) -> &'a serde_json::Value {
    summary["models"]
        .as_array()
        .expect("a train summary lists its models")
        .iter()
        .find(|m| m["kind"] == kind)
        .unwrap_or_else(|| panic!("no {kind} in {summary}"))
}
