//! Cluster load run (issue #32): many simulated edges and tags through two
//! real locators on a real mosquitto, then the same tags through today's
//! all-to-all sharing, on loopback only, for a bounded time.
//!
//! ```sh
//! cargo build --release && cargo run --release --example cluster -- --edges 50 --tags 1000 --json
//! ```
//!
//! It starts mosquitto (Debian package `mosquitto`, `sys_interval 1` for its
//! `$SYS` PUBLISH counters), writes a site (the sample site, `waldo.toml`,
//! with a `[[gateway]]` per simulated edge on its walkable cells, several
//! edges to a cell when there are more edges than cells) and starts two
//! locators (`gangway run`, `[cluster] role = "locator"`). The simulated edges
//! are not gateways: one task publishes what each edge heard as an edge
//! would (the gateway's own encoder: every `[cluster] batch_s`, one message
//! per shard of the sightings that edge heard (each tag, at a fixed
//! cell, advertises `--hz` times a second and is heard by its three nearest
//! edges, RSSI by log-distance path loss) on
//! `<site prefix>/shards/<k>/sightings/<edge>`. Route requests go to random
//! tags at `--rate` a second. Half way through the measured span one locator
//! is killed (SIGKILL). Then the locators are stopped and one real gateway
//! in single mode (advertiser orientation) takes the sightings of
//! `--all-to-all-gateways` simulated gateways on `<site prefix>/sightings/<gw>`,
//! as each of them would in all-to-all sharing.
//!
//! With `--broker rabbitmq` the same run goes through a three-node RabbitMQ
//! cluster (Debian package `rabbitmq-server`, started as
//! `tests/it/mqtt_support/rabbitmq.rs` starts it for the tests): the
//! locators on nodes 0 and 1 with the others as fallbacks, the simulated
//! edges spread over all three, the watcher on node 2. A quarter of the way
//! through, node 0 is killed (SIGKILL); `broker_failover_s` is how long until
//! the locator that was on it is heard again through another node. RabbitMQ
//! has no `$SYS` counters, so broker messages and the all-to-all comparison
//! come from the mosquitto run only.
//!
//! With `--locator-cpu F` (root) each locator runs in a cgroup of its own
//! capped at F of one core, standing for a machine of its own: offered more
//! than one capped locator can take, the locations per second before and
//! after the kill are what two locators and one sustain.
//!
//! It prints what it measured (with `--json`, one JSON line): fixes published
//! twice, the longest gap between fixes of a tag, the failover time, route
//! requests unanswered within 10 s, broker messages and CPU per tag located
//! in both modes (and how each all-to-all figure was obtained). Everything it
//! starts, it stops.

#[path = "../tests/it/mqtt_support/rabbitmq.rs"]
mod rabbitmq;
mod support;

use std::collections::{BTreeSet, HashMap};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::Ordering::Relaxed;
use std::sync::atomic::{AtomicBool, AtomicU64};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use clap::Parser;
use gangway::mqtt::cluster::{self, ClusterConfig};
use gangway::mqtt::sightings;
use gangway::sighting::{BeaconId, Sighting};
use gangway::site::Site;
use gangway::topics::Message;
use rumqttc::{AsyncClient, Event, EventLoop, Packet, QoS};
use serde_json::json;
use support::{Guard, client, free_port, gangway, mosquitto, usage};

const TAG_UUID: &str = "0f0e0d0c-0b0a-4908-8706-050403020100";
/// The window stride of a gateway: gaps are counted in it.
const STRIDE_S: f64 = 2.0;
/// How long a route request may wait for its reply.
const REPLY_WAIT_S: f64 = 10.0;
/// Edges (or gateways) that hear each tag: its nearest.
const HEARERS: usize = 3;

#[derive(Parser)]
struct Args {
    /// Simulated edges, each publishing its sightings by shard every `[cluster] batch_s`.
    #[arg(long, default_value_t = 50)]
    edges: usize,
    /// Simulated tags, at fixed cells of the site.
    #[arg(long, default_value_t = 1000)]
    tags: usize,
    /// Adverts per second of each tag.
    #[arg(long, default_value_t = 1.0)]
    hz: f64,
    /// Measured span of the cluster run, after warm-up; one locator is killed half way.
    #[arg(long, default_value_t = 60)]
    seconds: u64,
    /// Route requests per second, to random tags, during the measured span.
    #[arg(long, default_value_t = 2.0)]
    rate: f64,
    /// `[cluster] shards` of the locators and the simulated edges.
    #[arg(long, default_value_t = ClusterConfig::default().shards)]
    shards: u16,
    /// Gateways of the all-to-all comparison (the first edges of the site).
    #[arg(long, default_value_t = 50)]
    all_to_all_gateways: usize,
    /// Measured span of the all-to-all comparison, after warm-up.
    #[arg(long, default_value_t = 20)]
    all_to_all_seconds: u64,
    /// The broker: one mosquitto, or a three-node RabbitMQ cluster with a node killed.
    #[arg(long, value_enum, default_value_t = BrokerKind::Mosquitto)]
    broker: BrokerKind,
    /// Caps each locator at this share of one core (a cgroup of its own;
    /// root), so that two locators stand for two machines on a machine with
    /// few cores: offered more than one capped locator can take, the
    /// locations per second before and after the kill are the sustained
    /// rates of two locators and of one.
    #[arg(long)]
    locator_cpu: Option<f64>,
    /// Print one JSON line instead of text.
    #[arg(long)]
    json: bool,
}

#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum BrokerKind {
    Mosquitto,
    Rabbitmq,
}

/// The broker the run goes through, stopped on drop.
enum Brokers {
    /// The running broker (stopped when dropped) and its port.
    Mosquitto {
        _process: Guard,
        port: u16,
    },
    Rabbitmq(rabbitmq::RabbitCluster),
}

impl Brokers {
    /// The MQTT port of each node.
    fn ports(&self) -> Vec<u16> {
        match self {
            Brokers::Mosquitto { port, .. } => vec![*port],
            Brokers::Rabbitmq(cluster) => (0..3).map(|i| cluster.port(i)).collect(),
        }
    }
}

/// A cgroup capping one process's CPU, removed on drop (after the process:
/// a cgroup with a process in it cannot be removed). Written by hand: the
/// few files of cgroup v2's `cpu.max` or v1's `cpu.cfs_*` are all it takes.
struct CpuCap(PathBuf);

impl CpuCap {
    /// Moves `pid` (all its threads) into a new cgroup `name` capped at
    /// `share` of one core.
    fn new(name: &str, share: f64, pid: u32) -> CpuCap {
        const PERIOD_US: u64 = 100_000;
        let quota = (share * PERIOD_US as f64).round().max(1_000.0) as u64;
        let root = Path::new("/sys/fs/cgroup");
        let v2 = root.join("cgroup.controllers").exists();
        let dir = if v2 {
            root.join(name)
        } else {
            root.join("cpu").join(name)
        };
        let write = |file: &str, text: String| {
            std::fs::write(dir.join(file), text).unwrap_or_else(|e| {
                panic!("--locator-cpu: {}/{file}: {e} (run as root)", dir.display())
            })
        };
        if v2 {
            // The cpu controller must be enabled for the root's children.
            let _ = std::fs::write(root.join("cgroup.subtree_control"), "+cpu");
        }
        std::fs::create_dir(&dir)
            .unwrap_or_else(|e| panic!("--locator-cpu: {}: {e} (run as root)", dir.display()));
        if v2 {
            write("cpu.max", format!("{quota} {PERIOD_US}"));
        } else {
            write("cpu.cfs_period_us", PERIOD_US.to_string());
            write("cpu.cfs_quota_us", quota.to_string());
        }
        write("cgroup.procs", pid.to_string());
        CpuCap(dir)
    }
}

impl Drop for CpuCap {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir(&self.0);
    }
}

fn unix_now() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

/// A small deterministic generator (xorshift64*): which tags get requests.
struct Rng(u64);

impl Rng {
    fn below(&mut self, n: usize) -> usize {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 33) as usize % n
    }
}

/// The walkable cells of a site file's `map`.
fn walkable(site_text: &str) -> Vec<[u16; 2]> {
    let map = site_text
        .split_once("map = '''")
        .and_then(|(_, rest)| rest.split_once("'''"))
        .map_or("", |(map, _)| map);
    let mut cells = Vec::new();
    for (y, line) in map.trim_start_matches('\n').lines().enumerate() {
        for (x, c) in line.chars().enumerate() {
            if c == '#' {
                cells.push([x as u16, y as u16]);
            }
        }
    }
    cells
}

/// The sample site with a `[[gateway]]` per edge; returns its path and the
/// edges' cells.
fn write_site(dir: &Path, edges: &[String]) -> (PathBuf, Vec<[u16; 2]>) {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let waldo = std::fs::read_to_string(root.join("config/sites/waldo.toml"))
        .unwrap_or_else(|e| panic!("config/sites/waldo.toml: {e}"));
    let cells = walkable(&waldo);
    assert!(
        !cells.is_empty(),
        "config/sites/waldo.toml: no walkable cell"
    );
    let (body, places) = waldo
        .split_once("[places]")
        .expect("config/sites/waldo.toml has [places]");
    // Spread over the cells: edge i on every (cells / edges)-th cell.
    let at: Vec<[u16; 2]> = (0..edges.len())
        .map(|i| cells[(i * cells.len() / edges.len().max(1) + i / cells.len()) % cells.len()])
        .collect();
    let gateways: String = edges
        .iter()
        .zip(&at)
        .map(|(id, [x, y])| format!("[[gateway]]\nid = \"{id}\"\ncell = [{x}, {y}]\n\n"))
        .collect();
    let site = dir.join("site.toml");
    std::fs::write(&site, format!("{body}{gateways}[places]{places}")).unwrap();
    (site, at)
}

/// One tag: its id, shard, and the receivers that hear it with their RSSI.
struct Tag {
    id: String,
    minor: u16,
    shard: u16,
    phase: f64,
    heard_by: Vec<(usize, i16)>,
}

/// Tags on walkable cells, each heard by its nearest `HEARERS` of `receivers`.
fn tags(n: usize, cells: &[[u16; 2]], receivers: &[[u16; 2]], shards: u16) -> Vec<Tag> {
    (0..n)
        .map(|i| {
            let at = cells[(i * 7) % cells.len()];
            let mut near: Vec<(usize, f64)> = receivers
                .iter()
                .enumerate()
                .map(|(r, c)| {
                    let d = f64::from(c[0].abs_diff(at[0])).hypot(f64::from(c[1].abs_diff(at[1])));
                    (r, d + r as f64 * 1e-6) // ties to the lower index
                })
                .collect();
            near.sort_by(|a, b| a.1.total_cmp(&b.1));
            near.truncate(HEARERS);
            let id = format!("{TAG_UUID}-7-{}", i + 1);
            Tag {
                shard: gangway::cluster::shard_of(&id, shards),
                id,
                minor: u16::try_from(i + 1).expect("at most 65,535 tags"),
                phase: i as f64 / n as f64,
                heard_by: near
                    .into_iter()
                    .map(|(r, d)| (r, (-59.0 - 20.0 * d.max(1.0).log10()).round() as i16))
                    .collect(),
            }
        })
        .collect()
}

/// Where the simulated receivers publish, as the gateway's own encoders
/// write it.
#[derive(Clone, Copy)]
enum Sharing {
    /// An edge's: every `[cluster] batch_s`, one message per shard on
    /// `<site>/shards/<k>/sightings/<edge>`.
    Shards(u16),
    /// A single gateway's today: every 250 ms, on `<site>/sightings/<gateway>`.
    AllToAll,
}

impl Sharing {
    fn every(self) -> Duration {
        match self {
            Sharing::Shards(_) => Duration::from_secs_f64(ClusterConfig::default().batch_s),
            Sharing::AllToAll => Duration::from_millis(250),
        }
    }

    fn messages(self, site: &str, gateway: &str, heard: &[Sighting]) -> Vec<Message> {
        match self {
            Sharing::Shards(shards) => cluster::encode_by_shard(site, gateway, shards, heard),
            Sharing::AllToAll => heard
                .chunks(sightings::MAX_PER_MESSAGE)
                .map(|chunk| sightings::encode(site, gateway, chunk))
                .collect(),
        }
    }
}

/// One MQTT client per broker node, each with whether its node still
/// answers.
struct Publishers(Vec<(AsyncClient, Arc<AtomicBool>)>);

impl Publishers {
    /// Clients `name-<node>` on `ports`, each polled by a task that marks it
    /// down when its connection fails.
    fn connect(name: &str, ports: &[u16]) -> Publishers {
        Publishers(
            ports
                .iter()
                .enumerate()
                .map(|(i, &port)| {
                    let (client, mut eventloop) = client(&format!("{name}-{i}"), port, 100_000);
                    let up = Arc::new(AtomicBool::new(true));
                    let flag = up.clone();
                    tokio::spawn(async move {
                        while eventloop.poll().await.is_ok() {}
                        flag.store(false, Relaxed);
                    });
                    (client, up)
                })
                .collect(),
        )
    }

    /// The client receiver `r` publishes through: its node's, or the next
    /// node's when that one is down (as an edge's `fallback_urls`).
    fn for_receiver(&self, r: usize) -> &AsyncClient {
        let n = self.0.len();
        (0..n)
            .map(|k| &self.0[(r + k) % n])
            .find(|(_, up)| up.load(Relaxed))
            .map_or(&self.0[r % n].0, |(client, _)| client)
    }
}

/// Stops the simulated receivers and counts what they published.
#[derive(Default)]
struct Switch {
    stop: AtomicBool,
    published: AtomicU64,
}

/// Publishes the receivers' sightings (every [`Sharing::every`]) until
/// `switch.stop`, counting its messages in `switch.published`.
async fn simulate(
    publishers: Publishers,
    site: String,
    receivers: Vec<String>,
    tags: Vec<Tag>,
    hz: f64,
    sharing: Sharing,
    switch: Arc<Switch>,
) {
    let mut tick = tokio::time::interval(sharing.every());
    let mut from = unix_now();
    let uuid: uuid::Uuid = TAG_UUID.parse().expect("a UUID");
    while !switch.stop.load(Relaxed) {
        tick.tick().await;
        let to = unix_now();
        // Receiver → sightings heard in [from, to).
        let mut heard: HashMap<usize, Vec<Sighting>> = HashMap::new();
        for tag in &tags {
            // Adverts at (k + phase) / hz.
            let mut k = ((from * hz) - tag.phase).ceil();
            while (k + tag.phase) / hz < to {
                let t = (k + tag.phase) / hz;
                for &(r, rssi) in &tag.heard_by {
                    heard.entry(r).or_default().push(Sighting {
                        advertiser_mac: None,
                        t,
                        observer: receivers[r].as_str().into(),
                        advertiser: BeaconId {
                            uuid,
                            major: 7,
                            minor: tag.minor,
                        },
                        tx_power: None,
                        rssi,
                    });
                }
                k += 1.0;
            }
        }
        from = to;
        for (r, heard) in heard {
            for m in sharing.messages(&site, &receivers[r], &heard) {
                if publishers
                    .for_receiver(r)
                    .publish(m.topic, QoS::AtMostOnce, false, m.payload)
                    .await
                    .is_ok()
                {
                    switch.published.fetch_add(1, Relaxed);
                }
            }
        }
    }
}

/// What the watching client saw.
#[derive(Clone, Default)]
struct Seen {
    /// (arrived, tag index, fix time, from the all-to-all gateway).
    fixes: Vec<(Instant, usize, f64, bool)>,
    /// Locator → (state, owned shards), the latest heartbeat.
    beats: HashMap<String, (String, BTreeSet<u16>)>,
    /// (arrived, locator) of every heartbeat.
    beat_times: Vec<(Instant, String)>,
    /// Request id → when its first reply came and whether it was a route.
    replies: HashMap<String, (Instant, bool)>,
    /// `$SYS/broker/publish/messages/received` and `…/sent`, latest:
    /// PUBLISH packets only (`$SYS/broker/messages/…` also counts acks and pings).
    sys: (u64, u64),
    /// Messages this client received (the broker's `sent` counts them).
    received: u64,
}

fn watch(
    seen: Arc<Mutex<Seen>>,
    mut eventloop: EventLoop,
    site: String,
    ids: HashMap<String, usize>,
) {
    tokio::spawn(async move {
        loop {
            match eventloop.poll().await {
                Ok(Event::Incoming(Packet::Publish(p))) => {
                    let now = Instant::now();
                    let topic = p.topic.as_str();
                    let text = String::from_utf8_lossy(&p.payload);
                    let mut seen = seen.lock().unwrap();
                    seen.received += 1;
                    if let Some(n) = topic.strip_prefix("$SYS/broker/publish/messages/") {
                        let v = text.trim().parse().unwrap_or(0);
                        match n {
                            "received" => seen.sys.0 = v,
                            "sent" => seen.sys.1 = v,
                            _ => {}
                        }
                        continue;
                    }
                    let v: serde_json::Value = serde_json::from_str(&text).unwrap_or_default();
                    if let Some(locator) = topic.strip_prefix(&format!("{site}/locators/")) {
                        let owned = v["owned"]
                            .as_array()
                            .map(|a| {
                                a.iter()
                                    .filter_map(|s| s.as_u64())
                                    .map(|s| s as u16)
                                    .collect()
                            })
                            .unwrap_or_default();
                        let state = v["state"].as_str().unwrap_or("").to_owned();
                        seen.beats.insert(locator.to_owned(), (state, owned));
                        seen.beat_times.push((now, locator.to_owned()));
                    } else if let Some(device) = topic
                        .split_once("/devices/")
                        .and_then(|(_, r)| r.strip_suffix("/location"))
                    {
                        if let (Some(&tag), Some(t)) = (ids.get(device), v["t"].as_f64()) {
                            let all_to_all = !topic.starts_with(&site);
                            seen.fixes.push((now, tag, t, all_to_all));
                        }
                    } else if topic.ends_with("/path")
                        && let Some(id) = v["request_id"].as_str()
                    {
                        let routed = v["waypoints"].is_array();
                        seen.replies.entry(id.to_owned()).or_insert((now, routed));
                    }
                }
                Ok(_) => {}
                Err(_) => tokio::time::sleep(Duration::from_millis(50)).await,
            }
        }
    });
}

/// Starts `gangway run` with `config`, its log in `log`.
fn run_gateway(config: &Path, log: &Path) -> Guard {
    let log = std::fs::File::create(log).unwrap();
    Guard(
        Command::new(gangway())
            .arg("run")
            .arg("--config")
            .arg(config)
            .env("RUST_LOG", "warn")
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .expect("gangway run"),
    )
}

/// A gateway's config on the broker node at `ports[0]`, the others its
/// fallbacks.
fn write_config(dir: &Path, id: &str, site: &Path, ports: &[u16], extra: &str) -> PathBuf {
    let fallbacks: Vec<String> = ports[1..]
        .iter()
        .map(|p| format!("\"mqtt://127.0.0.1:{p}\""))
        .collect();
    let path = dir.join(format!("{id}.toml"));
    std::fs::write(
        &path,
        format!(
            "gateway_id = \"{id}\"\nsite = \"{}\"\n[window]\norientation = \"advertiser\"\n\
             [localizer]\nmin_confidence = 0.0\n{extra}\n[store]\nenabled = false\n\
             [web]\nenabled = false\n[mqtt]\nurl = \"mqtt://127.0.0.1:{}\"\n\
             fallback_urls = [{}]\n\
             ha_discovery = false\nstats_interval_s = 1\nreconnect_min_s = 0.2\nreconnect_max_s = 1.0\n",
            site.display(),
            ports[0],
            fallbacks.join(", ")
        ),
    )
    .unwrap();
    path
}

/// Waits until `done` holds of what was seen, or `limit` passes; whether it held.
async fn wait_for(seen: &Mutex<Seen>, limit: Duration, done: impl Fn(&Seen) -> bool) -> bool {
    let until = Instant::now() + limit;
    while Instant::now() < until {
        if done(&seen.lock().unwrap()) {
            return true;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    false
}

/// Tags with a fix arriving at or after `since` (from the cluster, or from the all-to-all gateway).
fn located_since(seen: &Seen, since: Instant, all_to_all: bool) -> usize {
    seen.fixes
        .iter()
        .filter(|f| f.0 >= since && f.3 == all_to_all)
        .map(|f| f.1)
        .collect::<BTreeSet<_>>()
        .len()
}

/// The broker's counters and what the watcher received, at a moment.
struct Snapshot {
    at: Instant,
    sys: (u64, u64),
    received: u64,
}

fn snapshot(seen: &Mutex<Seen>) -> Snapshot {
    let seen = seen.lock().unwrap();
    Snapshot {
        at: Instant::now(),
        sys: seen.sys,
        received: seen.received,
    }
}

/// Broker messages between two snapshots, not counting deliveries to the watcher.
fn broker_messages(a: &Snapshot, b: &Snapshot) -> f64 {
    let received = b.sys.0.saturating_sub(a.sys.0);
    let sent = b.sys.1.saturating_sub(a.sys.1);
    (received + sent.saturating_sub(b.received - a.received)) as f64
}

fn fixes_between(seen: &Seen, a: Instant, b: Instant, all_to_all: bool) -> usize {
    seen.fixes
        .iter()
        .filter(|f| f.0 >= a && f.0 < b && f.3 == all_to_all)
        .count()
}

fn cpu(pids: &[u32]) -> f64 {
    pids.iter().map(|&p| usage(p).0).sum()
}

/// What the all-to-all run needs of the cluster run's set-up.
struct AllToAllRun<'a> {
    dir: &'a Path,
    site: &'a Path,
    port: u16,
    prefix: &'a str,
    edges: &'a [String],
    edge_cells: &'a [[u16; 2]],
    cells: &'a [[u16; 2]],
}

/// The all-to-all run's figures.
#[derive(Default)]
struct AllToAll {
    gateways: usize,
    located: bool,
    span_s: f64,
    published: u64,
    delivered: f64,
    cpu_s: f64,
    msgs_per_tag: f64,
    cpu_ms_per_tag: f64,
}

/// One real gateway takes every simulated gateway's sightings, as each of
/// them would in all-to-all sharing.
async fn all_to_all(
    args: &Args,
    run: AllToAllRun<'_>,
    seen: &Mutex<Seen>,
    switch: &Arc<Switch>,
) -> AllToAll {
    let AllToAllRun {
        dir,
        site,
        port,
        prefix,
        edges,
        edge_cells,
        cells,
    } = run;
    let n = args.all_to_all_gateways;
    let a2a_receivers: Vec<String> = edges[..n].to_vec();
    let a2a_tags = tags(args.tags, cells, &edge_cells[..n], args.shards);
    let config = write_config(dir, "a2a", site, &[port], "");
    let gateway = run_gateway(&config, &dir.join("a2a.log"));
    let a2a_pid = gateway.0.id();
    tokio::time::sleep(Duration::from_secs(2)).await;
    switch.stop.store(false, Relaxed);
    let sim = tokio::spawn(simulate(
        Publishers::connect("cluster-a2a", &[port]),
        prefix.to_owned(),
        a2a_receivers,
        a2a_tags,
        args.hz,
        Sharing::AllToAll,
        switch.clone(),
    ));
    let warm = Instant::now();
    let a2a_located = wait_for(seen, Duration::from_secs(60), |s| {
        located_since(s, warm, true) == args.tags
    })
    .await;
    let a2a_start = snapshot(seen);
    let a2a_published_start = switch.published.load(Relaxed);
    let a2a_cpu_start = usage(a2a_pid).0;
    tokio::time::sleep(Duration::from_secs(args.all_to_all_seconds)).await;
    let a2a_end = snapshot(seen);
    let a2a_cpu = usage(a2a_pid).0 - a2a_cpu_start;
    let a2a_published = switch.published.load(Relaxed) - a2a_published_start;
    switch.stop.store(true, Relaxed);
    let _ = sim.await;
    drop(gateway);
    let s = seen.lock().unwrap();
    let a2a_fixes = fixes_between(&s, a2a_start.at, a2a_end.at, true).max(1) as f64;
    // What the one gateway took from the broker: the broker's deliveries but
    // the watcher's.
    let delivered = (a2a_end.sys.1 - a2a_start.sys.1)
        .saturating_sub(a2a_end.received - a2a_start.received) as f64;
    let nf = n as f64;
    let a2a_msgs_per_tag = (a2a_published as f64 + nf * delivered + nf * a2a_fixes) / a2a_fixes;
    let a2a_cpu_per_tag_ms = a2a_cpu * nf * 1e3 / a2a_fixes;
    let a2a_span = (a2a_end.at - a2a_start.at).as_secs_f64();

    AllToAll {
        gateways: n,
        located: a2a_located,
        span_s: a2a_span,
        published: a2a_published,
        delivered,
        cpu_s: a2a_cpu,
        msgs_per_tag: a2a_msgs_per_tag,
        cpu_ms_per_tag: a2a_cpu_per_tag_ms,
    }
}

fn round(x: f64, places: i32) -> f64 {
    let k = 10f64.powi(places);
    (x * k).round() / k
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    let args = Args::parse();
    assert!(
        args.edges > 0 && (1..=65_535).contains(&args.tags) && args.hz > 0.0 && args.shards > 0,
        "--edges, --hz and --shards must be above 0, --tags from 1 to 65535 (a tag is a minor)"
    );
    assert!(
        (HEARERS..=args.edges).contains(&args.all_to_all_gateways),
        "--all-to-all-gateways must be between {HEARERS} and --edges ({})",
        args.edges
    );
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let dir = tempfile::tempdir().unwrap();
    let edges: Vec<String> = (0..args.edges).map(|i| format!("edge-{i:03}")).collect();
    let (site, edge_cells) = write_site(dir.path(), &edges);
    let site_name = Site::load(&site).unwrap_or_else(|e| panic!("{e}"));
    let places: Vec<String> = site_name.places().keys().cloned().collect();
    let prefix = "gangway/sites/waldo-library".to_owned();
    let cells = walkable(&std::fs::read_to_string(&site).unwrap());

    let mut brokers = match args.broker {
        BrokerKind::Mosquitto => {
            let (guard, port) = mosquitto(dir.path(), "sys_interval 1\n");
            Brokers::Mosquitto {
                _process: guard,
                port,
            }
        }
        BrokerKind::Rabbitmq => Brokers::Rabbitmq(rabbitmq::RabbitCluster::start().await),
    };
    let ports = brokers.ports();
    // Node `i` first, then the others: a gateway's url and fallback_urls.
    let from_node = |i: usize| -> Vec<u16> {
        (0..ports.len())
            .map(|k| ports[(i + k) % ports.len()])
            .collect()
    };
    // The watcher and the requests on the node that never dies.
    let watch_port = ports[ports.len() - 1];
    let the_tags = tags(args.tags, &cells, &edge_cells, args.shards);
    let ids: HashMap<String, usize> = the_tags
        .iter()
        .enumerate()
        .map(|(i, t)| (t.id.clone(), i))
        .collect();
    let shard_of_tag: Vec<u16> = the_tags.iter().map(|t| t.shard).collect();

    // The watcher.
    let seen = Arc::new(Mutex::new(Seen::default()));
    let (watcher, eventloop) = client("cluster-watch", watch_port, 100_000);
    for topic in [
        format!("{prefix}/devices/+/location"),
        format!("{prefix}/devices/+/path"),
        format!("{prefix}/locators/+"),
        "gangway/a2a/devices/+/location".to_owned(),
        "$SYS/broker/publish/messages/+".to_owned(),
    ] {
        watcher.subscribe(topic, QoS::AtMostOnce).await.unwrap();
    }
    watch(seen.clone(), eventloop, prefix.clone(), ids);

    // Two locators.
    let cluster = format!(
        "[cluster]\nrole = \"locator\"\nshards = {}\nheartbeat_s = 1.0\nlease_s = 3.0\n",
        args.shards
    );
    // (id, process, pid, its CPU cap): the cap after the process, so that
    // it is removed once the process is gone.
    let mut locators: Vec<(String, Option<Guard>, u32, Option<CpuCap>)> = ["loc-1", "loc-2"]
        .iter()
        .enumerate()
        .map(|(i, id)| {
            let config = write_config(dir.path(), id, &site, &from_node(i), &cluster);
            let g = run_gateway(&config, &dir.path().join(format!("{id}.log")));
            let pid = g.0.id();
            let cap = args.locator_cpu.map(|share| {
                CpuCap::new(
                    &format!("gangway-cluster-{}-{id}", std::process::id()),
                    share,
                    pid,
                )
            });
            (id.to_string(), Some(g), pid, cap)
        })
        .collect();
    let split = wait_for(&seen, Duration::from_secs(30), |s| {
        let serving: Vec<&BTreeSet<u16>> = s
            .beats
            .values()
            .filter(|b| b.0 == "serving")
            .map(|b| &b.1)
            .collect();
        serving.len() == 2 && serving[0].len() + serving[1].len() == usize::from(args.shards)
    })
    .await;
    assert!(split, "the two locators never split the shards");

    // The edges.
    let switch = Arc::new(Switch::default());
    let sim = tokio::spawn(simulate(
        Publishers::connect("cluster-edges", &ports),
        prefix.clone(),
        edges.clone(),
        the_tags,
        args.hz,
        Sharing::Shards(args.shards),
        switch.clone(),
    ));
    let warm = Instant::now();
    let all_located = wait_for(&seen, Duration::from_secs(60), |s| {
        located_since(s, warm, false) == args.tags
    })
    .await;
    let warmup_s = warm.elapsed().as_secs_f64();

    // Measured span: route requests throughout, one locator killed half way
    // (and on a cluster, a broker node a quarter of the way).
    let start = snapshot(&seen);
    let published_start = switch.published.load(Relaxed);
    let cpu_start = cpu(&locators.iter().map(|l| l.2).collect::<Vec<_>>());
    let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
    let mut requests: Vec<(String, Instant)> = Vec::new();
    let half = Duration::from_secs(args.seconds / 2);
    let mut before_kill = None;
    let mut killed: Option<(Instant, f64, String, BTreeSet<u16>)> = None;
    let mut node_killed: Option<(Instant, f64)> = None;
    let every = Duration::from_secs_f64(1.0 / args.rate.max(0.01));
    let mut next = Instant::now();
    while start.at.elapsed() < Duration::from_secs(args.seconds) {
        if let Brokers::Rabbitmq(cluster) = &mut brokers
            && node_killed.is_none()
            && start.at.elapsed() >= half / 2
        {
            cluster.kill(0);
            node_killed = Some((Instant::now(), unix_now()));
        }
        if killed.is_none() && start.at.elapsed() >= half {
            before_kill = Some((
                snapshot(&seen),
                switch.published.load(Relaxed),
                cpu(&locators.iter().map(|l| l.2).collect::<Vec<_>>()),
            ));
            let victim = &mut locators[0];
            let owned = seen
                .lock()
                .unwrap()
                .beats
                .get(&victim.0)
                .map(|b| b.1.clone())
                .unwrap_or_default();
            drop(victim.1.take()); // SIGKILL
            killed = Some((Instant::now(), unix_now(), victim.0.clone(), owned));
        }
        if args.rate > 0.0 && Instant::now() >= next {
            let tag = rng.below(args.tags);
            let id = format!("r{}", requests.len());
            let to = &places[requests.len() % places.len()];
            let device = format!("{TAG_UUID}-7-{}", tag + 1);
            watcher
                .publish(
                    format!("{prefix}/devices/{device}/route/set"),
                    QoS::AtLeastOnce,
                    false,
                    json!({"to": to, "request_id": id}).to_string(),
                )
                .await
                .unwrap();
            requests.push((id, Instant::now()));
            next += every;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let end = snapshot(&seen);
    // Let the last requests be answered.
    tokio::time::sleep(Duration::from_secs_f64(REPLY_WAIT_S)).await;
    switch.stop.store(true, Relaxed);
    let _ = sim.await;
    drop(locators);

    // What the cluster did.
    let (kill_at, kill_unix, victim, victim_shards) = killed.expect("the span has a half");
    let (pre, published_pre, cpu_pre) = before_kill.expect("killed after the first half");
    // A copy, so that no lock is held while the run goes on.
    let s = seen.lock().unwrap().clone();
    let victim_tags: BTreeSet<usize> = (0..args.tags)
        .filter(|t| victim_shards.contains(&shard_of_tag[*t]))
        .collect();
    let mut back: HashMap<usize, Instant> = HashMap::new();
    for f in s.fixes.iter().filter(|f| !f.3 && f.0 > kill_at) {
        if victim_tags.contains(&f.1) {
            back.entry(f.1).or_insert(f.0);
        }
    }
    let locator_failover_s =
        (back.len() == victim_tags.len() && !victim_tags.is_empty()).then(|| {
            back.values()
                .map(|t| (*t - kill_at).as_secs_f64())
                .fold(0.0, f64::max)
        });
    // The broker node's failover: until the locator that was on it is heard
    // again, through another node.
    let broker_failover_s = node_killed.map(|(at, _)| {
        s.beat_times
            .iter()
            .find(|(heard, id)| *heard > at && *id == victim)
            .map(|(heard, _)| (*heard - at).as_secs_f64())
    });
    // Failover spans, in fix times: from a stride before a kill to a stride
    // after it was over (or the end, if it never was).
    let mut spans = vec![(
        kill_unix - STRIDE_S,
        kill_unix + locator_failover_s.unwrap_or(f64::INFINITY) + STRIDE_S,
    )];
    if let (Some((_, node_unix)), Some(failover)) = (node_killed, broker_failover_s) {
        spans.push((
            node_unix - STRIDE_S,
            node_unix + failover.unwrap_or(f64::INFINITY) + STRIDE_S,
        ));
    }
    let outside = |t: f64| spans.iter().all(|span| t < span.0 || t > span.1);
    let mut per_fix: HashMap<(usize, u64), usize> = HashMap::new();
    let mut per_tag: Vec<Vec<f64>> = vec![Vec::new(); args.tags];
    for f in s
        .fixes
        .iter()
        .filter(|f| !f.3 && f.0 >= start.at && f.0 < end.at)
    {
        *per_fix.entry((f.1, f.2.to_bits())).or_insert(0) += 1;
        per_tag[f.1].push(f.2);
    }
    let duplicates = per_fix
        .iter()
        .filter(|((_, t), n)| **n > 1 && outside(f64::from_bits(*t)))
        .count();
    let duplicates_in_failover = per_fix
        .iter()
        .filter(|((_, t), n)| **n > 1 && !outside(f64::from_bits(*t)))
        .count();
    let mut max_gap_windows: f64 = 0.0;
    let mut tags_with_gaps = 0;
    for times in &mut per_tag {
        times.sort_by(f64::total_cmp);
        times.dedup();
        let mut worst: f64 = 0.0;
        for w in times.windows(2) {
            let overlaps = spans.iter().any(|span| w[1] >= span.0 && w[0] <= span.1);
            if !overlaps {
                worst = worst.max((w[1] - w[0]) / STRIDE_S);
            }
        }
        if worst > 2.0 {
            tags_with_gaps += 1;
        }
        max_gap_windows = max_gap_windows.max(worst);
    }
    let unanswered: Vec<&String> = requests
        .iter()
        .filter(|(id, sent)| {
            s.replies
                .get(id)
                .is_none_or(|(at, _)| (*at - *sent).as_secs_f64() > REPLY_WAIT_S)
        })
        .map(|(id, _)| id)
        .collect();
    let routed = requests
        .iter()
        .filter(|(id, _)| s.replies.get(id).is_some_and(|r| r.1))
        .count();
    // Before the kill: two locators, steady.
    let steady_s = (pre.at - start.at).as_secs_f64();
    let fixes_two = fixes_between(&s, start.at, pre.at, false);
    let msgs_per_tag = broker_messages(&start, &pre) / fixes_two.max(1) as f64;
    let cpu_per_tag_ms = (cpu_pre - cpu_start) * 1e3 / fixes_two.max(1) as f64;
    // After failover: one locator.
    let one_from = kill_at + Duration::from_secs_f64(locator_failover_s.unwrap_or(0.0) + STRIDE_S);
    let one_s = (end.at - one_from).as_secs_f64().max(0.0);
    let fixes_one = fixes_between(&s, one_from, end.at, false);

    // All-to-all (mosquitto only: its `$SYS` counters count the messages).
    let all_to_all = match brokers {
        Brokers::Mosquitto { port, .. } => Some(
            all_to_all(
                &args,
                AllToAllRun {
                    dir: dir.path(),
                    site: &site,
                    port,
                    prefix: &prefix,
                    edges: &edges,
                    edge_cells: &edge_cells,
                    cells: &cells,
                },
                &seen,
                &switch,
            )
            .await,
        ),
        Brokers::Rabbitmq(_) => None,
    };
    let is_mosquitto = all_to_all.is_some();
    let a2a = all_to_all.unwrap_or_default();
    let mut notes = vec![
        "located_tags_per_s: locations published per second, offered load is tags / 2 s stride; the same as offered unless the locators fall behind: not a saturation measurement".to_owned(),
    ];
    if is_mosquitto {
        notes.extend([
            "cluster figures: mosquitto $SYS publish/messages received + sent (PUBLISH packets, no acks) (less what the watching client received) and both locators' CPU, over the half span before the kill, per location published".to_owned(),
            format!("all-to-all broker messages: the simulated gateways' publishes ({}) + {} x what the broker delivered to the one real gateway ({}) + {} x its location publishes, per location published; every gateway of all-to-all takes all the others' sightings and publishes every location", a2a.published, a2a.gateways, a2a.delivered, a2a.gateways),
            format!("all-to-all CPU: the one real gateway's CPU ({}) x {}, per location published", round(a2a.cpu_s, 2), a2a.gateways),
            "broker_failover_s: null, mosquitto is one node (--broker rabbitmq kills a node of a three-node cluster)".to_owned(),
        ]);
    } else {
        notes.extend([
            "broker_failover_s: from kill -9 of node 0 to the first heartbeat of the locator that was on it, through another node".to_owned(),
            "RabbitMQ has no $SYS counters: broker messages and the all-to-all comparison come from the mosquitto run (the default)".to_owned(),
            "cpu_ms_per_tag: both locators' CPU over the half span before the locator kill (the node kill is in it), per location published".to_owned(),
        ]);
    }
    let out = json!({
        "tags": args.tags,
        "edges": args.edges,
        "locators": 2,
        "locator_cpu": args.locator_cpu,
        "cores": cores,
        "hz": args.hz,
        "shards": args.shards,
        "seconds": args.seconds,
        "warmup_s": round(warmup_s, 1),
        "all_tags_located": all_located,
        "duplicates": duplicates,
        "duplicates_in_failover": duplicates_in_failover,
        "max_gap_windows": round(max_gap_windows, 2),
        "tags_with_gap_over_2_windows": tags_with_gaps,
        "locator_killed": victim,
        "locator_killed_tags": victim_tags.len(),
        "locator_failover_s": locator_failover_s.map(|x| round(x, 2)),
        "broker": if is_mosquitto { "mosquitto" } else { "rabbitmq, 3 nodes" },
        "broker_node_killed_at_s": node_killed.map(|(at, _)| round((at - start.at).as_secs_f64(), 1)),
        "broker_failover_s": broker_failover_s.flatten().map(|x| round(x, 2)),
        "requests": requests.len(),
        "requests_routed": routed,
        "requests_unanswered": unanswered.len(),
        "broker_msgs_per_tag": is_mosquitto.then(|| round(msgs_per_tag, 2)),
        "cpu_ms_per_tag": round(cpu_per_tag_ms, 3),
        "edge_publishes_per_s": round((published_pre - published_start) as f64 / steady_s.max(1e-9), 0),
        "located_tags_per_s_2_locators": round(fixes_two as f64 / steady_s.max(1e-9), 1),
        "located_tags_per_s_1_locator": round(fixes_one as f64 / one_s.max(1e-9), 1),
        "offered_tags_per_s": round(args.tags as f64 / STRIDE_S, 1),
        "all_to_all_gateways": is_mosquitto.then_some(a2a.gateways),
        "all_to_all_tags_located": is_mosquitto.then_some(a2a.located),
        "all_to_all_span_s": is_mosquitto.then(|| round(a2a.span_s, 1)),
        "broker_msgs_per_tag_all_to_all": is_mosquitto.then(|| round(a2a.msgs_per_tag, 2)),
        "cpu_ms_per_tag_all_to_all": is_mosquitto.then(|| round(a2a.cpu_ms_per_tag, 3)),
        "msgs_ratio": is_mosquitto.then(|| round(a2a.msgs_per_tag / msgs_per_tag.max(1e-9), 1)),
        "cpu_ratio": is_mosquitto.then(|| round(a2a.cpu_ms_per_tag / cpu_per_tag_ms.max(1e-9), 1)),
        "notes": notes,
    });
    drop(s);
    if args.json {
        println!("{out}");
    } else {
        println!("{}", serde_json::to_string_pretty(&out).unwrap());
    }
}
