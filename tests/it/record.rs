//! `gangway record` on a machine without Bluetooth (CI, containers) fails with a
//! message that says what is missing, not a panic. Where an adapter exists it
//! records instead, which is just as fine.

use crate::common;

#[test]
fn recording_without_bluetooth_says_what_is_missing() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("rec.jsonl");
    let run = common::gangway(&["record", "--out", out.to_str().unwrap(), "--duration", "1"]);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(!stderr.contains("panicked"), "{stderr}");
    if !run.status.success() {
        assert!(
            stderr.contains("BlueZ") || stderr.contains("adapter"),
            "the error names what is missing: {stderr}"
        );
    }
}
