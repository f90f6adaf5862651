//! A three-node RabbitMQ cluster with its MQTT plugin (Debian's
//! `rabbitmq-server`): the clustered broker of the `[cluster]` tests.
//!
//! Why these settings (docs/scaling.md, "RabbitMQ", says the same to
//! users):
//! - `mqtt.durable_queue_type = quorum` on **every** node: a persistent MQTT
//!   session is a queue, and only a replicated one outlives its node. The
//!   node where a client first subscribes decides the queue's type, so one
//!   node without the line makes sessions that die with it.
//! - Each node runs as the test's user straight from `/usr/lib/rabbitmq/bin`
//!   (the `/usr/sbin` wrappers switch to the `rabbitmq` user and its home),
//!   with a private `epmd` port and a cookie in a `HOME` of the test's own,
//!   so the cluster touches nothing of a system broker and two test runs do
//!   not meet.
//! - `RUNNING_UNDER_SYSTEMD` makes the start script exec the Erlang VM, so
//!   the child is the broker itself and killing it is a real kill -9 of a
//!   node.
//!
//! A node accepts TCP on its MQTT port before its cluster is formed, so
//! [`RabbitCluster::start`] joins the nodes first and then waits for a real
//! QoS 1 round trip on every node.

use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use rumqttc::{AsyncClient, Event, MqttOptions, Packet, QoS};

// Only `free_port` from the parent: examples/cluster.rs includes this file
// too, to run its load on the same cluster.
use super::free_port;

/// How long the cluster may take to serve MQTT on every node: about 20–30 s
/// on a 2-core machine, more when the other tests run beside it.
const READY_WAIT: Duration = Duration::from_secs(120);

const BIN: &str = "/usr/lib/rabbitmq/bin";

struct Node {
    name: String,
    mqtt_port: u16,
    child: Option<Child>,
}

pub(crate) struct RabbitCluster {
    dir: tempfile::TempDir,
    epmd_port: u16,
    nodes: Vec<Node>,
}

impl RabbitCluster {
    /// Whether Debian's `rabbitmq-server` is installed.
    pub(crate) fn installed() -> bool {
        Path::new(BIN).join("rabbitmq-server").exists()
    }

    /// Three clustered nodes on loopback, once each serves MQTT. A start
    /// that fails (a node that exits, a free port taken by another test
    /// between our look and the node's bind) is retried once on new ports.
    pub(crate) async fn start() -> RabbitCluster {
        assert!(
            Self::installed(),
            "rabbitmq-server is not installed; the clustered-broker test needs it \
             (apt-get install rabbitmq-server; .ci/run does)"
        );
        let mut failures = Vec::new();
        for _ in 0..2 {
            match Self::try_start().await {
                Ok(cluster) => return cluster,
                Err(why) => {
                    eprintln!("RabbitMQ cluster: {why}");
                    failures.push(why);
                }
            }
        }
        panic!("the RabbitMQ cluster did not start: {failures:#?}");
    }

    async fn try_start() -> Result<RabbitCluster, String> {
        let dir = tempfile::tempdir().unwrap();
        let home = dir.path().join("home");
        std::fs::create_dir(&home).unwrap();
        let cookie = home.join(".erlang.cookie");
        std::fs::write(&cookie, "GANGWAYCLUSTERTEST").unwrap();
        // Erlang refuses a cookie others can read.
        std::fs::set_permissions(&cookie, std::fs::Permissions::from_mode(0o400)).unwrap();
        let mut cluster = RabbitCluster {
            epmd_port: free_port(),
            nodes: Vec::new(),
            dir,
        };
        for i in 1..=3 {
            let node = cluster.spawn(i);
            cluster.nodes.push(node);
        }
        let deadline = Instant::now() + READY_WAIT;
        for i in 0..3 {
            while !cluster.ctl(i, &["await_startup", "--timeout", "30"]) {
                let exited = cluster.nodes[i]
                    .child
                    .as_mut()
                    .and_then(|c| c.try_wait().ok().flatten());
                if exited.is_some() || Instant::now() >= deadline {
                    return Err(format!(
                        "node {} did not start within {READY_WAIT:?} ({}); its log ends:\n{}",
                        cluster.nodes[i].name,
                        exited.map_or("still running".to_owned(), |e| e.to_string()),
                        cluster.log_tail(i)
                    ));
                }
                std::thread::sleep(Duration::from_millis(500));
            }
        }
        let seed = cluster.nodes[0].name.clone();
        for i in 1..3 {
            for args in [&["stop_app"][..], &["join_cluster", &seed], &["start_app"]] {
                if !cluster.ctl(i, args) {
                    return Err(format!(
                        "rabbitmqctl {args:?} on {} failed; its log ends:\n{}",
                        cluster.nodes[i].name,
                        cluster.log_tail(i)
                    ));
                }
            }
        }
        for node in &cluster.nodes {
            while !round_trip(node.mqtt_port).await {
                if Instant::now() >= deadline {
                    return Err(format!(
                        "{} did not serve MQTT within {READY_WAIT:?}",
                        node.name
                    ));
                }
                tokio::time::sleep(Duration::from_millis(250)).await;
            }
        }
        Ok(cluster)
    }

    /// The last lines of node `i`'s log, for a failure message (the
    /// directory goes with the cluster).
    fn log_tail(&self, i: usize) -> String {
        let log = self
            .node_dir(i)
            .join("log")
            .join(format!("{}.log", self.nodes[i].name));
        let text =
            std::fs::read_to_string(&log).unwrap_or_else(|e| format!("{}: {e}", log.display()));
        let lines: Vec<&str> = text.lines().collect();
        lines[lines.len().saturating_sub(30)..].join("\n")
    }

    fn node_dir(&self, i: usize) -> PathBuf {
        self.dir.path().join(format!("n{i}"))
    }

    /// Starts node `i` (1-based in its name) with a config of its own.
    fn spawn(&self, i: usize) -> Node {
        let dir = self.node_dir(i - 1);
        std::fs::create_dir_all(dir.join("log")).unwrap();
        let mqtt_port = free_port();
        let conf = dir.join("rabbitmq.conf");
        std::fs::write(
            &conf,
            format!(
                "listeners.tcp.default = 127.0.0.1:{}\n\
                 mqtt.listeners.tcp.default = 127.0.0.1:{mqtt_port}\n\
                 mqtt.allow_anonymous = true\n\
                 mqtt.default_user = guest\n\
                 mqtt.default_pass = guest\n\
                 mqtt.durable_queue_type = quorum\n\
                 log.console = false\n",
                free_port()
            ),
        )
        .unwrap();
        let plugins = dir.join("enabled_plugins");
        std::fs::write(&plugins, "[rabbitmq_mqtt].\n").unwrap();
        let name = format!("gangway{i}@localhost");
        let child = self
            .command("rabbitmq-server")
            .env("RABBITMQ_NODENAME", &name)
            .env("RABBITMQ_NODE_IP_ADDRESS", "127.0.0.1")
            .env("RABBITMQ_DIST_PORT", free_port().to_string())
            .env("RABBITMQ_CONFIG_FILE", &conf)
            .env("RABBITMQ_ENABLED_PLUGINS_FILE", &plugins)
            .env("RABBITMQ_MNESIA_BASE", dir.join("mnesia"))
            .env("RABBITMQ_LOG_BASE", dir.join("log"))
            .env("RABBITMQ_PID_FILE", dir.join("pid"))
            .env("RABBITMQ_ADVANCED_CONFIG_FILE", dir.join("advanced.config"))
            .env("RABBITMQ_CONF_ENV_FILE", dir.join("rabbitmq-env.conf"))
            .env("RUNNING_UNDER_SYSTEMD", "true")
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("start rabbitmq-server");
        Node {
            name,
            mqtt_port,
            child: Some(child),
        }
    }

    /// A RabbitMQ program with this cluster's cookie and `epmd`.
    fn command(&self, program: &str) -> Command {
        let mut command = Command::new(Path::new(BIN).join(program));
        command
            .env("HOME", self.dir.path().join("home"))
            .env("ERL_EPMD_PORT", self.epmd_port.to_string())
            .stdin(Stdio::null());
        command
    }

    /// Whether `rabbitmqctl ARGS` on node `i` succeeded.
    fn ctl(&self, i: usize, args: &[&str]) -> bool {
        self.command("rabbitmqctl")
            .arg("-n")
            .arg(&self.nodes[i].name)
            .args(args)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|s| s.success())
    }

    /// The MQTT port of node `i`.
    pub(crate) fn port(&self, i: usize) -> u16 {
        self.nodes[i].mqtt_port
    }

    /// kill -9 node `i` (`Child::kill` is SIGKILL).
    pub(crate) fn kill(&mut self, i: usize) {
        if let Some(mut child) = self.nodes[i].child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

impl Drop for RabbitCluster {
    fn drop(&mut self) {
        for i in 0..self.nodes.len() {
            self.kill(i);
        }
        // The nodes started their own epmd daemon on the private port.
        let _ = Command::new("epmd")
            .arg("-port")
            .arg(self.epmd_port.to_string())
            .arg("-kill")
            .env("ERL_EPMD_PORT", self.epmd_port.to_string())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status();
    }
}

/// Whether a QoS 1 message published on the node at `port` comes back to a
/// subscriber there within a few seconds.
async fn round_trip(port: u16) -> bool {
    let mut options = MqttOptions::new(format!("ready-{port}"), "127.0.0.1", port);
    options.set_keep_alive(Duration::from_secs(5));
    let (client, mut events) = AsyncClient::new(options, 10);
    let topic = format!("ready/{port}");
    let attempt = async {
        loop {
            match events.poll().await {
                Ok(Event::Incoming(Packet::ConnAck(_))) => {
                    client.subscribe(&topic, QoS::AtLeastOnce).await.ok()?;
                }
                Ok(Event::Incoming(Packet::SubAck(_))) => {
                    client
                        .publish(&topic, QoS::AtLeastOnce, false, "ready")
                        .await
                        .ok()?;
                }
                Ok(Event::Incoming(Packet::Publish(p))) if p.topic == topic => return Some(()),
                Ok(_) => {}
                Err(_) => return None,
            }
        }
    };
    let ok = tokio::time::timeout(Duration::from_secs(6), attempt)
        .await
        .ok()
        .flatten()
        .is_some();
    let _ = client.try_disconnect();
    ok
}
