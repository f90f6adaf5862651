//! `gangway replay`: the daemon's pipeline, fed from a log instead of a radio.

use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::{Duration, Instant};

use anyhow::Context;

use crate::mqtt::{self, Link};
use crate::pipeline::Pipeline;
use crate::publish::Message;
use crate::source::log::LogReader;

#[derive(clap::Args)]
pub struct Args {
    /// The advert log (JSON Lines).
    log: PathBuf,
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
    /// Skip and count bad log lines instead of stopping at the first.
    #[arg(long)]
    skip_bad: bool,
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    anyhow::ensure!(
        args.speed >= 0.0 && args.speed.is_finite(),
        "--speed must be 0 (as fast as possible) or a positive factor"
    );
    let (config, site) = super::load(&args.config)?;
    let mut pipeline = Pipeline::new(&config, site)?;
    let mut reader = LogReader::open(&args.log, args.skip_bad)?;
    let client_id = format!("{}-replay", config.client_id());

    super::runtime()?.block_on(async {
        // --print alone means stdout is the only sink.
        let url = match (args.mqtt_url.clone(), &config.mqtt.url, args.print) {
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
            skipped_lines = reader.skipped(),
            mqtt_dropped,
            seconds = started.elapsed().as_secs_f64(),
            "replay done"
        );
        anyhow::Ok(())
    })?;
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
