//! `mqtts://` against a mosquitto that requires TLS, a client certificate and
//! a password: the gateway connects with `ca_file`, `client_cert`,
//! `client_key`, `username` and `password_file`, and serves; a wrong password
//! is refused by the broker and the gateway keeps retrying instead of dying.

use std::path::Path;
use std::process::Command;

use crate::mqtt_support::*;
use gangway::mqtt::MqttConfig;
use rcgen::{BasicConstraints, CertificateParams, CertifiedIssuer, DnType, IsCa, KeyPair};

/// Writes ca.pem, server.pem/key, client.pem/key into `dir`.
fn make_certificates(dir: &Path) {
    let mut ca = CertificateParams::new(Vec::<String>::new()).unwrap();
    ca.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    // Distinct names: a certificate whose subject equals its issuer's looks
    // self-signed to OpenSSL (mosquitto) and is refused.
    ca.distinguished_name
        .push(DnType::CommonName, "gangway test CA");
    let ca = CertifiedIssuer::self_signed(ca, KeyPair::generate().unwrap()).unwrap();
    std::fs::write(dir.join("ca.pem"), ca.pem()).unwrap();
    for (name, names) in [
        (
            "server",
            vec!["localhost".to_owned(), "127.0.0.1".to_owned()],
        ),
        ("client", vec!["gw-tls".to_owned()]),
    ] {
        let key = KeyPair::generate().unwrap();
        let mut params = CertificateParams::new(names).unwrap();
        params
            .distinguished_name
            .push(DnType::CommonName, format!("gangway test {name}"));
        let cert = params.signed_by(&key, &ca).unwrap();
        std::fs::write(dir.join(format!("{name}.pem")), cert.pem()).unwrap();
        std::fs::write(dir.join(format!("{name}.key")), key.serialize_pem()).unwrap();
    }
}

fn tls_config(dir: &Path, password_file: &Path) -> MqttConfig {
    MqttConfig {
        ca_file: Some(dir.join("ca.pem")),
        client_cert: Some(dir.join("client.pem")),
        client_key: Some(dir.join("client.key")),
        username: Some("gw".into()),
        password_file: Some(password_file.to_owned()),
        ..MqttConfig::default()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_gateway_serves_over_mutual_tls_with_a_password() {
    let certs = tempfile::tempdir().unwrap();
    make_certificates(certs.path());
    let passwd = certs.path().join("passwd");
    let made = Command::new("mosquitto_passwd")
        .args(["-b", "-c"])
        .arg(&passwd)
        .args(["gw", "s3cret"])
        .status()
        .expect("mosquitto_passwd (package mosquitto)");
    assert!(made.success());
    let c = certs.path();
    let broker = Broker::start_with(|_| {
        format!(
            "cafile {0}/ca.pem\ncertfile {0}/server.pem\nkeyfile {0}/server.key\n\
             require_certificate true\nallow_anonymous false\npassword_file {1}\n",
            c.display(),
            passwd.display()
        )
    });
    let url = format!("mqtts://localhost:{}", broker.port);
    let good = certs.path().join("good-password");
    std::fs::write(&good, "s3cret\n").unwrap();
    let bad = certs.path().join("bad-password");
    std::fs::write(&bad, "nope\n").unwrap();

    // The test's own client goes through the same TLS setup as the gateway.
    let options = tls_config(c, &good).options(&url, "test-tls").unwrap();
    let prefix = "gangway/gw-tls";
    let mut client = Client::connect_with(options, &[&format!("{prefix}/#")]).await;

    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("gangway.toml");
    let site = repo().join("config/sites/waldo.toml");
    let write = |password: &Path| {
        std::fs::write(
            &config,
            format!(
                "gateway_id = \"gw-tls\"\nsite = \"{}\"\n[web]\nbind = \"127.0.0.1:0\"\n[mqtt]\nurl = \"{url}\"\nusername = \"gw\"\n\
                 password_file = \"{}\"\nca_file = \"{c}/ca.pem\"\nclient_cert = \"{c}/client.pem\"\n\
                 client_key = \"{c}/client.key\"\nstats_interval_s = 1\nreconnect_min_s = 0.2\n\
                 reconnect_max_s = 0.5\nshutdown_grace_s = 0.5\n",
                site.display(),
                password.display(),
                c = c.display()
            ),
        )
        .unwrap();
    };

    // A wrong password: refused, retried, never a crash.
    write(&bad);
    let mut refused = Gateway::start(&config, &["--replay", "/dev/null"]);
    tokio::time::sleep(std::time::Duration::from_secs(2)).await;
    assert!(
        refused.child.try_wait().unwrap().is_none(),
        "the gateway exited on a refused login"
    );
    client.drain();
    assert!(
        !client
            .seen
            .iter()
            .any(|m| m.topic == format!("{prefix}/status"))
    );
    assert!(refused.terminate().success());

    write(&good);
    let fixture = repo().join("fixtures/walk-waldo.jsonl");
    let mut gateway = Gateway::start(
        &config,
        &["--replay", fixture.to_str().unwrap(), "--speed", "10"],
    );
    client
        .wait_for("online over TLS", |m| {
            m.topic == format!("{prefix}/status") && m.text() == "online"
        })
        .await;
    client
        .wait_for("a location", |m| {
            m.topic == format!("{prefix}/devices/walker-01/location")
        })
        .await;
    let reply = client
        .route(prefix, "walker-01", "help desk", "tls-1")
        .await;
    assert!(reply["waypoints"].is_array(), "{reply}");
    assert!(gateway.terminate().success());
}
