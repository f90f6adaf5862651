//! `gangway replay`: the daemon's pipeline, fed from a log instead of a radio,
//! optionally scored against the log's ground truth.

use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::{Duration, Instant};

use anyhow::Context;

use crate::mqtt::{self, Link};
use crate::pipeline::Pipeline;
use crate::publish::Message;
use crate::score::Scorer;
use crate::source::Event;
use crate::source::capture::{CaptureReader, Format, ReadOptions};

#[derive(clap::Args)]
pub struct Args {
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
    #[arg(long, default_value_os_t = super::default_config())]
    config: PathBuf,
    /// Playback speed: 1 is real time, 10 ten times faster, 0 as fast as possible.
    #[arg(long, default_value_t = 0.0)]
    speed: f64,
    /// Write every outgoing message to stdout as {"topic": ..., "payload": ...}.
    #[arg(long)]
    print: bool,
    /// Publish to this broker (mqtt://host:port or mqtts://host:port),
    /// overriding [mqtt] url. With neither (and no --print), an embedded broker
    /// starts on 127.0.0.1 for the replay's duration.
    #[arg(long)]
    mqtt_url: Option<String>,
    /// Skip and count bad log lines, CSV rows and columns, and a truncated last
    /// btsnoop record instead of stopping at the first.
    #[arg(long)]
    skip_bad: bool,
    /// Score the fixes against the log's `truth` events and print the score
    /// (instead of the messages).
    #[arg(long, conflicts_with = "print")]
    score: bool,
    /// With --score: print the score as one JSON object.
    #[arg(long, requires = "score")]
    json: bool,
    /// With --score: how far in time (seconds) a truth may be from the fix it
    /// scores; default the fingerprint window length.
    #[arg(long, requires = "score")]
    tolerance_s: Option<f64>,
}

/// Opens a capture of any format for `args`.
fn open(args: &Args, site: &crate::site::Site) -> anyhow::Result<CaptureReader> {
    Ok(CaptureReader::open(
        &args.log,
        site,
        &ReadOptions {
            format: args.format,
            skip_bad: args.skip_bad,
            device: args.device.clone(),
            not_heard: args.not_heard,
        },
    )?)
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    anyhow::ensure!(
        args.speed >= 0.0 && args.speed.is_finite(),
        "--speed must be 0 (as fast as possible) or a positive factor"
    );
    let (config, site) = super::load(&args.config)?;
    let mut reader = open(&args, &site)?;
    let tolerance_s = args.tolerance_s.unwrap_or(config.window.length_s);
    anyhow::ensure!(
        tolerance_s >= 0.0 && tolerance_s.is_finite(),
        "--tolerance-s must be a number of seconds, 0 or more"
    );
    let mut scorer = args.score.then(|| Scorer::new(tolerance_s));
    let mut pipeline = Pipeline::new(&config, site.clone())?;
    let client_id = format!("{}-replay", config.client_id());

    super::batch_runtime()?.block_on(async {
        // --print or --score without a broker configured: stdout is the only sink.
        let url = match (
            args.mqtt_url.clone(),
            &config.mqtt.url,
            args.print || args.score,
        ) {
            (None, None, true) => None,
            (url, _, _) => Some(mqtt::broker_url(&config.mqtt, url)?),
        };
        let publisher = match &url {
            Some(url) => {
                let settings =
                    mqtt::link_settings(&config.mqtt, url, &client_id, None, Vec::new())?;
                Some(Link::start(settings).0)
            }
            None => None,
        };
        let stdout = std::io::stdout();
        let mut print = args.print.then(|| std::io::BufWriter::new(stdout.lock()));
        let mut out: Vec<Message> = Vec::new();
        let started = Instant::now();
        let mut first_t = None;
        let mut events = 0u64;
        loop {
            let event = match reader.next() {
                Some(event) => event?,
                None => {
                    pipeline.finish(&mut out);
                    if let Some(scorer) = scorer.as_mut() {
                        out.iter().for_each(|m| scorer.message(m));
                    }
                    send(&mut out, print.as_mut(), publisher.as_ref()).await?;
                    break;
                }
            };
            events += 1;
            if args.speed > 0.0 {
                let t0 = *first_t.get_or_insert(event.t());
                let due = Duration::from_secs_f64(((event.t() - t0) / args.speed).max(0.0));
                if let Some(wait) = due.checked_sub(started.elapsed()) {
                    if let Some(p) = print.as_mut() {
                        p.flush()?;
                    }
                    tokio::time::sleep(wait).await;
                }
            }
            pipeline.handle(&event, &mut out);
            if let Some(scorer) = scorer.as_mut() {
                if let Event::Truth(truth) = &event {
                    scorer.truth(truth);
                }
                out.iter().for_each(|m| scorer.message(m));
            }
            send(&mut out, print.as_mut(), publisher.as_ref()).await?;
        }
        if let Some(p) = print.as_mut() {
            p.flush()?;
        }
        let mqtt_dropped = publisher.as_ref().map_or(0, |p| {
            p.stats()
                .queue_dropped
                .load(std::sync::atomic::Ordering::Relaxed)
        });
        if let Some(publisher) = publisher {
            publisher.shutdown().await;
        }
        let stats = pipeline.stats();
        tracing::info!(
            events,
            sightings = stats.sightings,
            unknown_anchor = pipeline.unknown_anchor_sightings(),
            fixes = stats.fixes,
            requests = stats.requests,
            routes = stats.routes,
            request_errors = stats.request_errors,
            format = ?reader.format(),
            skipped = %reader.skipped(),
            mqtt_dropped,
            seconds = started.elapsed().as_secs_f64(),
            "replay done"
        );
        anyhow::Ok(())
    })?;
    if let Some(scorer) = scorer {
        let score = scorer.score(&site);
        if args.json {
            println!("{}", serde_json::to_string(&score)?);
        } else {
            println!("{score}");
        }
    }
    Ok(ExitCode::SUCCESS)
}

async fn send(
    out: &mut Vec<Message>,
    mut print: Option<&mut impl Write>,
    publisher: Option<&Link>,
) -> anyhow::Result<()> {
    for message in out.drain(..) {
        if let Some(p) = print.as_deref_mut() {
            serde_json::to_writer(&mut *p, &message)?;
            p.write_all(b"\n").context("writing to stdout")?;
        }
        if let Some(publisher) = publisher {
            publisher.wait_for_room().await;
            publisher.publish(&message);
        }
    }
    Ok(())
}
