//! `systemd/gangway.service` passes `systemd-analyze verify`, and its
//! hardening keeps `systemd-analyze security` at an exposure of 2.0 or less.
//! Both run offline, so no systemd as PID 1 is needed (CI containers have
//! none); the unit's ExecStart is pointed at the binary under test, because
//! verify checks that the executable exists. The daemon's side of
//! `Type=notify` (READY=1, WATCHDOG=1, STOPPING=1) is checked on a socket of
//! the test's own.

use crate::mqtt_support;

use std::os::unix::net::UnixDatagram;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn analyze(args: &[&str], unit: &Path) -> std::process::Output {
    Command::new("systemd-analyze")
        .args(args)
        .arg(unit)
        .output()
        .expect(
            "systemd-analyze is missing: apt-get install systemd (the tests need only the tool)",
        )
}

#[test]
fn the_unit_verifies_and_is_hardened() {
    let repo = Path::new(env!("CARGO_MANIFEST_DIR"));
    let unit = std::fs::read_to_string(repo.join("systemd/gangway.service")).unwrap();
    assert!(unit.contains("ExecStart=/usr/bin/gangway run"));
    let dir = tempfile::tempdir().unwrap();
    let copy = dir.path().join("gangway.service");
    std::fs::write(
        &copy,
        unit.replace("/usr/bin/gangway", env!("CARGO_BIN_EXE_gangway")),
    )
    .unwrap();

    let verify = analyze(&["verify", "--man=no"], &copy);
    assert!(
        verify.status.success() && verify.stderr.is_empty(),
        "systemd-analyze verify: {}",
        String::from_utf8_lossy(&verify.stderr)
    );
    // The threshold is in tenths of the printed 0–10 exposure level.
    let security = analyze(&["security", "--offline=yes", "--threshold=20"], &copy);
    assert!(
        security.status.success(),
        "exposure above 2.0:\n{}",
        String::from_utf8_lossy(&security.stdout)
    );
    for key in [
        "Type=notify",
        "WatchdogSec=",
        "Restart=on-failure",
        "DynamicUser=yes",
        "StateDirectory=gangway",
        "LoadCredential=mqtt-password:",
        "ProtectSystem=strict",
        "ProtectHome=yes",
        "PrivateTmp=yes",
        "NoNewPrivileges=yes",
        "RestrictAddressFamilies=AF_UNIX AF_INET AF_INET6",
        "MemoryMax=",
        "TasksMax=",
    ] {
        assert!(unit.contains(key), "the unit lacks {key}");
    }
}

#[test]
fn the_daemon_notifies_readiness_and_pings_the_watchdog() {
    let broker = mqtt_support::Broker::start();
    let site = mqtt_support::repo().join("config/sites/waldo.toml");
    let config = mqtt_support::gateway_config("gw-notify", &site, &broker, "");
    mqtt_support::assert_web_ui_on_a_port_of_its_own(&config.path);
    let socket_path = config.dir.path().join("notify.sock");
    let socket = UnixDatagram::bind(&socket_path).unwrap();
    socket
        .set_read_timeout(Some(Duration::from_secs(1)))
        .unwrap();
    let mut child = Command::new(env!("CARGO_BIN_EXE_gangway"))
        .args(["run", "--config"])
        .arg(&config.path)
        .args(["--replay", "/dev/null"])
        .env("NOTIFY_SOCKET", &socket_path)
        .env("WATCHDOG_USEC", "400000")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut seen = Vec::new();
    let deadline = Instant::now() + Duration::from_secs(20);
    let mut buf = [0u8; 256];
    let mut stopping_asked = false;
    while Instant::now() < deadline && !seen.iter().any(|m: &String| m.contains("STOPPING=1")) {
        if let Ok(n) = socket.recv(&mut buf) {
            seen.push(String::from_utf8_lossy(&buf[..n]).into_owned());
        }
        let pings = seen.iter().filter(|m| m.contains("WATCHDOG=1")).count();
        let connected = seen.iter().any(|m| m.contains("STATUS=broker connected"));
        if pings >= 2 && connected && !stopping_asked {
            mqtt_support::signal(&child, "TERM");
            stopping_asked = true;
        }
    }
    let status = child.wait().unwrap();
    assert!(status.success());
    assert!(seen.iter().any(|m| m.contains("READY=1")), "{seen:?}");
    assert!(
        seen.iter().filter(|m| m.contains("WATCHDOG=1")).count() >= 2,
        "{seen:?}"
    );
    assert!(seen.iter().any(|m| m.contains("STOPPING=1")), "{seen:?}");
    // `systemctl status` tells how the broker connection is.
    assert!(
        seen.iter().any(|m| m.contains("STATUS=broker connected;")),
        "{seen:?}"
    );
}
