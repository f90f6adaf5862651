//! `gangway replay`: the daemon's pipeline, fed from a log instead of a radio.

use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::{Duration, Instant};

use anyhow::Context;

use crate::mqtt::Publisher;
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
    /// Publish to this broker (mqtt://host:port), overriding [mqtt] url.
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
    let url = args.mqtt_url.clone().or_else(|| config.mqtt.url.clone());
    let client_id = config
        .mqtt
        .client_id
        .clone()
        .unwrap_or_else(|| format!("gangway-{}-replay", config.gateway_id));

    super::runtime()?.block_on(async {
        let publisher = match &url {
            Some(url) => Some(Publisher::connect(url, &client_id, &config.mqtt).await?),
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
        if let Some(publisher) = publisher {
            publisher.close().await?;
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
    publisher: Option<&Publisher>,
) -> anyhow::Result<()> {
    for message in out.drain(..) {
        if let Some(p) = print.as_deref_mut() {
            serde_json::to_writer(&mut *p, &message)?;
            p.write_all(b"\n").context("writing to stdout")?;
        }
        if let Some(publisher) = publisher {
            publisher.send(&message).await?;
        }
    }
    Ok(())
}
