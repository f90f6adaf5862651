//! `gangway replay`: the gateway's runtime with a capture as its only source
//! and no messages from others (requests come from the log), ending when the
//! capture does. Its sinks are what the flags ask for: stdout (`--print`), a
//! file (`--out`), the scorer (`--score`), a broker (`--mqtt-url`, `[mqtt]
//! url`, or an embedded one with `--embedded-broker`); with none, it only
//! reports its counts.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use tokio::sync::mpsc;

use crate::daemon::{self, state::Loaded};
use crate::mqtt;
use crate::pipeline::Pipeline;
use crate::score::Scorer;
use crate::sighting::heard::HeardBeacon;
use crate::sink::{Sink, jsonl::JsonLines};
use crate::source::capture::{CaptureReader, Format, ReadOptions};
use crate::source::playback::CaptureSource;
use crate::topics::Topics;

#[derive(clap::Args)]
#[command(group(clap::ArgGroup::new("reports").args(["score", "heard"]).multiple(true)))]
pub(super) struct Args {
    /// The capture: a JSON Lines advert log, a CSV scan log, a btsnoop file or
    /// a pcap/pcapng capture.
    log: PathBuf,
    /// The capture's format; by default btsnoop, pcap and pcapng files are
    /// recognised by their first bytes, `*.csv` is a scan log and anything else
    /// JSON Lines.
    #[arg(long, value_enum)]
    format: Option<Format>,
    /// Device id of CSV, btsnoop and pcap captures, which do not name their
    /// observer (default: `survey` for CSV, `capture` for btsnoop and pcap).
    #[arg(long)]
    device: Option<String>,
    /// RSSI value that means "not heard" in CSV scan logs.
    #[arg(long, default_value_t = -200, allow_negative_numbers = true)]
    not_heard: i16,
    #[command(flatten)]
    config: super::ConfigFile,
    /// Playback speed: 1 is real time, 10 ten times faster, 0 as fast as possible.
    #[arg(long, default_value_t = 0.0)]
    speed: f64,
    /// Write every outgoing message to stdout as {"topic": ..., "payload": ...}.
    #[arg(long)]
    print: bool,
    /// Write the same JSON Lines as --print to this file.
    #[arg(long, value_name = "FILE")]
    out: Option<PathBuf>,
    /// Publish to this broker (mqtt://host:port or mqtts://host:port),
    /// overriding [mqtt] url.
    #[arg(long)]
    mqtt_url: Option<String>,
    /// Start an embedded MQTT broker on 127.0.0.1:[mqtt] embedded_port for
    /// the replay's duration and publish to it (instead of [mqtt] url).
    #[arg(long, conflicts_with = "mqtt_url")]
    embedded_broker: bool,
    /// Skip and count bad log lines, CSV rows and columns, and a truncated last
    /// btsnoop record instead of stopping at the first.
    #[arg(long)]
    skip_bad: bool,
    /// Score the fixes against the log's `truth` events and print the score
    /// (instead of the messages).
    #[arg(long, conflicts_with = "print")]
    score: bool,
    /// After the replay, list every iBeacon heard, known to the site or not:
    /// UUID, major, minor, how often, RSSI median and maximum, who heard it.
    #[arg(long)]
    heard: bool,
    /// With --score or --heard: print each as one JSON object per line
    /// (`{"heard": [...]}` for --heard).
    #[arg(long, requires = "reports")]
    json: bool,
    /// Serve the live map (and route requests from it) at this address while
    /// the log plays, with --speed 1 as it happened; the replay then ends
    /// with Ctrl-C, so the map can still be looked at after the log's end.
    #[arg(long, value_name = "ADDR")]
    web: Option<std::net::SocketAddr>,
    /// With --score: how far in time (seconds) a truth may be from the fix it
    /// scores; default the fingerprint window length.
    #[arg(long, requires = "score")]
    tolerance_s: Option<f64>,
}

/// Opens a capture of any format for `args`.
fn open(args: &Args, building: &crate::site::Building) -> anyhow::Result<CaptureReader> {
    Ok(CaptureReader::open(
        &args.log,
        building,
        &ReadOptions {
            format: args.format,
            skip_bad: args.skip_bad,
            device: args.device.clone(),
            not_heard: args.not_heard,
        },
    )?)
}

pub(super) fn run(args: Args) -> anyhow::Result<ExitCode> {
    anyhow::ensure!(
        args.speed >= 0.0 && args.speed.is_finite(),
        "--speed must be 0 (as fast as possible) or a positive factor"
    );
    let (config, building) = super::load(&args.config.path)?;
    // What the sinks map: the lowest floor, the only one of a one-floor site.
    let site = building.floors()[0].site.clone();
    if std::fs::metadata(&args.log).is_ok_and(|m| m.len() == 0) {
        tracing::warn!(
            "{}: the capture is empty (0 bytes): nothing to replay",
            args.log.display()
        );
        return Ok(ExitCode::FAILURE);
    }
    let reader = open(&args, &building)?;
    let tolerance_s = args.tolerance_s.unwrap_or(config.window.length_s);
    anyhow::ensure!(
        tolerance_s >= 0.0 && tolerance_s.is_finite(),
        "--tolerance-s must be a number of seconds, 0 or more"
    );
    let pipeline = Pipeline::for_building(&config.pipeline(), building.clone())?;

    let replayed = super::batch_runtime()?.block_on(async {
        let topics = Topics::new(config.topic_prefix());
        let mut sinks: Vec<Box<dyn Sink>> = Vec::new();
        if args.print {
            sinks.push(Box::new(JsonLines::stdout(topics.clone())));
        }
        if let Some(out) = &args.out {
            sinks.push(Box::new(JsonLines::create(topics.clone(), out)?));
        }
        let score = args.score.then(|| {
            let (sink, score) = Scorer::new(tolerance_s).sink(building.clone());
            sinks.push(Box::new(sink));
            score
        });
        let url = match (args.mqtt_url.clone(), &config.mqtt.url) {
            (Some(url), _) => Some(url),
            (None, _) if args.embedded_broker => Some(mqtt::broker::start(
                config.mqtt.embedded_port,
                config.mqtt.max_payload_bytes,
            )?),
            (None, url) => url.clone(),
        };
        if let Some(url) = &url {
            sinks.push(Box::new(mqtt::sink::publisher(
                &config.mqtt,
                &config.broker_identity(&building.name),
                url,
            )?));
        }
        if sinks.is_empty() && !args.heard {
            tracing::warn!(
                "nothing to send the outputs to: only the counts are reported \
                 (--print, --out FILE, --score, --mqtt-url URL or --embedded-broker send them somewhere)"
            );
        }
        let source = CaptureSource::new(args.log.clone(), reader, args.speed);
        let mut sources: Vec<Box<dyn crate::source::Source>> = vec![Box::new(source)];
        let mut latency = None;
        if let Some(bind) = args.web {
            let config = crate::config::Config {
                web: crate::web::WebConfig { bind, ..config.web.clone() },
                ..config.clone()
            };
            if let Some(web) = crate::web::start(&config.web, &config.site, &config.window, config.limits.max_devices, building.clone(), &mut Vec::new(), None).await {
                latency = Some(web.add_to(&mut sources, &mut sinks));
            }
        }
        let serving = Loaded {
            config,
            building,
            site: site.clone(),
            pipeline,
            fallbacks: Vec::new(),
        };
        let options = daemon::Options {
            until_sources_end: true,
            // The live map's gateway panel shows the stats: from the first
            // snapshot on, as under `run`.
            stats: args.web.is_some(),
            latency,
            ..daemon::Options::default()
        };
        // No reloads: the replay plays one config.
        let (_, reloads) = mpsc::channel(1);
        // Ctrl-C ends the replay early, with every sink delivering what it holds.
        let interrupted = async {
            let _ = tokio::signal::ctrl_c().await;
        };
        let started = Instant::now();
        let finished = daemon::run(
            serving,
            options,
            sources,
            sinks,
            interrupted,
            reloads,
        )
        .await?;
        let stats = &finished.stats;
        tracing::info!(
            sightings = stats.sightings,
            unknown_anchor = stats.sightings_ignored,
            beacons_heard = stats.heard,
            beacons_not_in_site = stats.heard_unknown,
            fixes = stats.fixes,
            requests = stats.requests,
            routes = stats.routes,
            request_errors = stats.request_errors,
            mqtt_dropped = stats.queue_dropped,
            seconds = started.elapsed().as_secs_f64(),
            "replay done"
        );
        if stats.heard_unknown > 0 && !args.heard {
            tracing::warn!(
                "{} of the {} beacons heard are not in the site file, so their sightings \
                 located nothing; `gangway replay {} --heard` lists them",
                stats.heard_unknown,
                stats.heard,
                args.log.display()
            );
        }
        let score = match score {
            Some(score) => Some(score.await?),
            None => None,
        };
        anyhow::Ok((finished, score))
    })?;
    let (finished, score) = replayed;
    if let Some(score) = score {
        if args.json {
            println!("{}", serde_json::to_string(&score)?);
        } else {
            println!("{score}");
        }
    }
    if args.heard {
        if args.json {
            println!(
                "{}",
                serde_json::to_string(&serde_json::json!({ "heard": finished.heard }))?
            );
        } else {
            print!("{}", heard_table(&finished.heard));
        }
    }
    if finished.stats.sightings == 0 && finished.stats.requests == 0 {
        tracing::warn!(
            "{}: the capture held no sightings and no route requests: nothing was replayed",
            args.log.display()
        );
        return Ok(ExitCode::FAILURE);
    }
    Ok(ExitCode::SUCCESS)
}

/// The beacons heard, one line each, for a person at a terminal.
fn heard_table(heard: &[HeardBeacon]) -> String {
    use std::fmt::Write;
    let unknown = heard.iter().filter(|b| !b.known).count();
    let mut out = format!(
        "heard {} beacons, {unknown} of them not in the site\n{:<36} {:>5} {:>5} {:>7} {:>6} {:>4}  {:<7}  observers\n",
        heard.len(),
        "uuid",
        "major",
        "minor",
        "count",
        "median",
        "max",
        "site"
    );
    for b in heard {
        let more = if b.more_observers { ", …" } else { "" };
        let _ = writeln!(
            out,
            "{:<36} {:>5} {:>5} {:>7} {:>6} {:>4}  {:<7}  {}{more}",
            b.uuid.to_string(),
            b.major,
            b.minor,
            b.count,
            b.rssi_median,
            b.rssi_max,
            if b.known { "known" } else { "unknown" },
            b.observers.join(", ")
        );
    }
    out
}
