//! The gateway's runtime in-process, as `gangway run` wires it but with a
//! channel for its source and a sink that collects what it is given: a route
//! request gets its reply, bad input is answered and never stops it, a reload
//! swaps the config (and a broken one is refused), and shutdown makes every
//! sink deliver what it holds. A replay-like runtime ends with its sources
//! and closes the windows they left open.

use crate::common;

use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use futures::future::BoxFuture;
use gangway::daemon::{self, state};
use gangway::plan::{Destination, RouteErrorCode};
use gangway::publish::stats::Stats;
use gangway::publish::{Output, RouteOutcome};
use gangway::sighting::{BeaconId, Sighting};
use gangway::sink::Sink;
use gangway::source::{ChannelSource, Input};

use gangway::event::{Event, Feedback, Inbound, RouteRequest};
use tokio::sync::{Notify, mpsc, oneshot};

const WAIT: Duration = Duration::from_secs(30);

/// What the collecting sink was given, and whether it was shut down.
#[derive(Default)]
struct Seen {
    outputs: Vec<Output>,
    flushes: usize,
    shut_down: bool,
}

#[derive(Clone, Default)]
struct Collected {
    seen: Arc<Mutex<Seen>>,
    changed: Arc<Notify>,
}

impl Collected {
    /// The first output (from `from` on) that `wanted` picks, waiting for it.
    async fn wait_for<T>(&self, what: &str, mut wanted: impl FnMut(&Output) -> Option<T>) -> T {
        let deadline = tokio::time::Instant::now() + WAIT;
        let mut from = 0;
        loop {
            let changed = self.changed.notified();
            {
                let seen = self.seen.lock().unwrap();
                if let Some(found) = seen.outputs[from..].iter().find_map(&mut wanted) {
                    return found;
                }
                from = seen.outputs.len();
            }
            assert!(
                tokio::time::timeout_at(deadline, changed).await.is_ok(),
                "no {what} within {WAIT:?}"
            );
        }
    }

    /// The stats published after `pred` holds.
    async fn stats(&self, what: &str, pred: impl Fn(&Stats) -> bool) -> Stats {
        self.wait_for(what, |o| match o {
            Output::Stats(s) if pred(s) => Some((**s).clone()),
            _ => None,
        })
        .await
    }
}

impl Sink for Collected {
    fn name(&self) -> &'static str {
        "collect"
    }

    fn send(&mut self, outputs: &[Output]) -> anyhow::Result<()> {
        self.seen.lock().unwrap().outputs.extend_from_slice(outputs);
        self.changed.notify_waiters();
        Ok(())
    }

    fn flush(&mut self) -> BoxFuture<'_, anyhow::Result<()>> {
        self.seen.lock().unwrap().flushes += 1;
        Box::pin(std::future::ready(Ok(())))
    }

    fn shutdown(self: Box<Self>) -> BoxFuture<'static, anyhow::Result<()>> {
        self.seen.lock().unwrap().shut_down = true;
        self.changed.notify_waiters();
        Box::pin(std::future::ready(Ok(())))
    }
}

/// A config on the sample site with the file-free planner (so a reload is
/// quick); `extra` goes at the end.
fn write_config(path: &Path, extra: &str) {
    let site = common::root().join("config/sites/waldo.toml");
    std::fs::write(
        path,
        format!(
            "gateway_id = \"gw-test\"\nsite = \"{}\"\n[planner]\nmode = \"astar\"\n{extra}",
            site.display()
        ),
    )
    .unwrap();
}

/// A phone next to beacon b3008 (the help desk, J10) hearing three beacons
/// once a second for `seconds` from `t0`.
fn scans(device: &str, t0: f64, seconds: u32) -> Vec<Event> {
    let uuid = uuid::Uuid::parse_str("5e1a6f3c-2b1d-4c8e-9a70-3d2f1c0b9e84").unwrap();
    let observer: Arc<str> = device.into();
    (0..seconds)
        .flat_map(|s| {
            [(3008, -55), (3005, -72), (3010, -80)].map(|(minor, rssi)| {
                Event::Advert(Sighting {
                    advertiser_mac: None,
                    t: t0 + f64::from(s),
                    observer: observer.clone(),
                    advertiser: BeaconId {
                        uuid,
                        major: 1,
                        minor,
                    },
                    tx_power: None,
                    rssi,
                })
            })
        })
        .collect()
}

fn route(device: &str, to: &str, id: &str) -> Input {
    Input::Inbound(Inbound::Route(RouteRequest {
        t: 0.0,
        device: device.into(),
        to: Destination::Place(to.into()),
        floor: None,
        profile: None,
        request_id: Some(id.into()),
    }))
}

/// The reply to request `id`: its route's length, or its error code.
fn reply(id: &str) -> impl Fn(&Output) -> Option<Result<f64, RouteErrorCode>> + '_ {
    move |o| match o {
        Output::Route(r) if r.request_id.as_deref() == Some(id) => Some(match &r.outcome {
            RouteOutcome::Route(body) => Ok(body.length_m),
            RouteOutcome::Floors(body) => Ok(body.length_m),
            RouteOutcome::Error { error } => Err(error.code),
        }),
        _ => None,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_daemon_serves_survives_bad_input_reloads_and_flushes_at_shutdown() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("gangway.toml");
    write_config(&config, "");
    let serving = state::load_at_start(&config).unwrap();
    let (feed, source) = ChannelSource::new(64);
    let collected = Collected::default();
    let (stop, stopped) = oneshot::channel::<()>();
    let (reload, reloads) = mpsc::channel(1);
    let options = daemon::Options {
        config_path: Some(config.clone()),
        stats: true,
        ..daemon::Options::default()
    };
    let daemon = tokio::spawn(daemon::run(
        serving,
        options,
        vec![Box::new(source)],
        vec![Box::new(collected.clone())],
        async {
            let _ = stopped.await;
        },
        reloads,
    ));

    // Heard, located, and served a route.
    feed.send(Input::Events(scans("p1", 100.0, 12)))
        .await
        .unwrap();
    collected
        .wait_for("a location of p1", |o| match o {
            Output::Location(l) if l.device == "p1" && l.cell.is_some() => Some(()),
            _ => None,
        })
        .await;
    feed.send(route("p1", "printers", "r1")).await.unwrap();
    let length = collected.wait_for("the reply to r1", reply("r1")).await;
    assert!(length.unwrap() > 0.0);

    // Bad input is answered, and the gateway keeps serving.
    feed.send(Input::Inbound(Inbound::BadRoute {
        device: "p1".into(),
        request_id: Some("bad".into()),
        code: RouteErrorCode::InvalidJson,
        message: "the request is not JSON".into(),
    }))
    .await
    .unwrap();
    feed.send(route("ghost", "printers", "r2")).await.unwrap();
    feed.send(route("p1", "the moon", "r3")).await.unwrap();
    feed.send(Input::Inbound(Inbound::Feedback(Feedback {
        t: 1.0,
        device: "p1".into(),
        request_id: "never-given".into(),
        score: 5,
    })))
    .await
    .unwrap();
    feed.send(Input::Inbound(Inbound::Refused { oversized: true }))
        .await
        .unwrap();
    feed.send(Input::Inbound(Inbound::Scan(Vec::new())))
        .await
        .unwrap();
    assert_eq!(
        collected.wait_for("the reply to bad", reply("bad")).await,
        Err(RouteErrorCode::InvalidJson)
    );
    assert_eq!(
        collected.wait_for("the reply to r2", reply("r2")).await,
        Err(RouteErrorCode::UnknownDevice)
    );
    assert_eq!(
        collected.wait_for("the reply to r3", reply("r3")).await,
        Err(RouteErrorCode::UnknownPlace)
    );
    collected
        .wait_for("refused feedback", |o| match o {
            Output::FeedbackRefused(f) if f.request_id == "never-given" => Some(()),
            _ => None,
        })
        .await;
    // Feedback on the route given is taken.
    feed.send(Input::Inbound(Inbound::Feedback(Feedback {
        t: 2.0,
        device: "p1".into(),
        request_id: "r1".into(),
        score: 4,
    })))
    .await
    .unwrap();
    collected
        .wait_for("accepted feedback", |o| match o {
            Output::Feedback(f) if f.request_id == "r1" => Some(()),
            _ => None,
        })
        .await;

    // A reload swaps the config in; a broken one is refused and the old one
    // keeps serving.
    write_config(&config, "[tracker]\nmax_speed_mps = 1.2\n");
    reload.send(()).await.unwrap();
    let stats = collected.stats("a reload", |s| s.reloads == 1).await;
    assert_eq!(stats.reload_failures, 0);
    assert_eq!(stats.oversized_messages, 1, "{stats:?}");
    assert_eq!(stats.feedback_refused, 1);
    assert_eq!(stats.feedback, 1);
    assert!(
        stats.requests >= 4 && stats.request_errors >= 3,
        "{stats:?}"
    );
    std::fs::write(&config, "gateway_id = [broken\n").unwrap();
    reload.send(()).await.unwrap();
    collected
        .stats("a refused reload", |s| s.reload_failures == 1)
        .await;
    // Tracks carry over a reload: p1 is served where it was, unheard since.
    feed.send(route("p1", "help desk", "r3b")).await.unwrap();
    assert!(
        collected
            .wait_for("the reply to r3b", reply("r3b"))
            .await
            .is_ok(),
        "p1 lost its track in the reload"
    );
    feed.send(Input::Events(scans("p1", 200.0, 12)))
        .await
        .unwrap();
    collected
        .wait_for("a location after the reloads", |o| match o {
            Output::Location(l) if l.device == "p1" && l.t > 200.0 && l.cell.is_some() => Some(()),
            _ => None,
        })
        .await;
    feed.send(route("p1", "help desk", "r4")).await.unwrap();
    assert!(
        collected
            .wait_for("the reply to r4", reply("r4"))
            .await
            .is_ok()
    );

    // Shutdown: the sinks get the final stats and are shut down.
    stop.send(()).unwrap();
    let last = tokio::time::timeout(WAIT, daemon)
        .await
        .expect("the daemon stops")
        .unwrap()
        .unwrap()
        .stats;
    assert_eq!((last.reloads, last.reload_failures), (1, 1));
    let seen = collected.seen.lock().unwrap();
    assert!(seen.shut_down);
    assert!(seen.flushes > 0);
    assert!(matches!(seen.outputs.last(), Some(Output::Stats(_))));
}

#[tokio::test]
async fn a_replay_ends_with_its_sources_and_closes_their_windows() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("gangway.toml");
    write_config(&config, "");
    let serving = state::load_at_start(&config).unwrap();
    let (feed, source) = ChannelSource::new(4);
    let collected = Collected::default();
    let (_, reloads) = mpsc::channel(1);
    let options = daemon::Options {
        until_sources_end: true,
        ..daemon::Options::default()
    };
    let replay = tokio::spawn(daemon::run(
        serving,
        options,
        vec![Box::new(source)],
        vec![Box::new(collected.clone())],
        std::future::pending(),
        reloads,
    ));
    // What the pipeline makes of the same events, with and without closing
    // the windows at the end.
    let events = scans("p2", 10.0, 5);
    let mut pipeline = state::load_at_start(&config).unwrap().pipeline;
    let mut out = Vec::new();
    events.iter().for_each(|e| pipeline.handle(e, &mut out));
    let open = out.len();
    pipeline.finish(&mut out);
    assert!(out.len() > open, "the last window is closed at the end");
    feed.send(Input::Events(events)).await.unwrap();
    drop(feed);
    let stats = tokio::time::timeout(WAIT, replay)
        .await
        .expect("the replay ends")
        .unwrap()
        .unwrap()
        .stats;
    assert_eq!(stats.sightings, 15);
    let seen = collected.seen.lock().unwrap();
    assert!(seen.shut_down);
    let fixes: Vec<_> = seen
        .outputs
        .iter()
        .filter(|o| matches!(o, Output::Location(l) if l.device == "p2"))
        .collect();
    assert_eq!(fixes.len(), out.len(), "{:?}", seen.outputs);
}
