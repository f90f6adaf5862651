//! `gangway run`: the daemon. This file is wiring: the sources (the radio or
//! a capture, and the broker's subscriptions), the sinks (the broker, the
//! learning store, `--out`), and the process's signals, handed to
//! [`daemon::run`].

use std::future::Future;
use std::path::PathBuf;
use std::process::ExitCode;

use tokio::signal::unix::{SignalKind, signal};
use tokio::sync::{mpsc, watch};

use crate::daemon::{self, state};
use crate::mqtt;
use crate::mqtt::cluster::Role;
use crate::publish::stats::BleStatus;
use crate::sink::{Sink, jsonl::JsonLines, recorder::Recorder};
use crate::source::Source;
use crate::source::ble::BleSource;
use crate::source::capture::{CaptureReader, ReadOptions};
use crate::source::playback::CaptureSource;
use crate::source::unix_now;

#[derive(clap::Args)]
pub(super) struct Args {
    #[command(flatten)]
    config: super::ConfigFile,
    /// Use this broker (mqtt://host:port or mqtts://host:port), overriding
    /// [mqtt] url. Without either, an embedded broker starts on 127.0.0.1.
    #[arg(long)]
    mqtt_url: Option<String>,
    /// Play this capture instead of scanning Bluetooth (demos, tests, and
    /// gateways fed by another recorder): any format `replay` reads, bad
    /// lines skipped and counted; MQTT is served as in a live run.
    #[arg(long, value_name = "LOG")]
    replay: Option<PathBuf>,
    /// Playback speed of --replay: 1 is real time, 0 as fast as possible.
    #[arg(long, default_value_t = 1.0, requires = "replay")]
    speed: f64,
    /// Also write every published message to this file, as JSON Lines (what
    /// `replay --print` writes).
    #[arg(long, value_name = "FILE")]
    out: Option<PathBuf>,
}

pub(super) fn run(args: Args) -> anyhow::Result<ExitCode> {
    ignore_reloads_until_served();
    keep_freed_memory_returnable();
    anyhow::ensure!(
        args.speed >= 0.0 && args.speed.is_finite(),
        "--speed must be 0 (as fast as possible) or a positive factor"
    );
    super::runtime()?.block_on(serve(args))?;
    Ok(ExitCode::SUCCESS)
}

async fn serve(args: Args) -> anyhow::Result<()> {
    // First, before loading anything: a SIGHUP (a reload asked early, say
    // by the editor's unit or a config-management run) or a SIGTERM that
    // arrives while models load is then a request, not the end of the
    // process by the signal's default action.
    let (shutdown, reload, reloads, recalibrate) = signals()?;
    let serving = state::load_at_start(&args.config.path)?;
    let config = &serving.config;
    let site = serving.site.clone();
    let url = mqtt::broker_url(&config.mqtt, args.mqtt_url)?;
    let (broker, subscriptions) = mqtt::sink::gateway(
        &config.mqtt,
        &config.broker_identity(&serving.building.name),
        &serving.building,
        &url,
    )?;
    let mut sources: Vec<Box<dyn Source>> = vec![Box::new(subscriptions)];
    let mut sinks: Vec<Box<dyn Sink>> = vec![Box::new(broker)];
    let radio = match &args.replay {
        Some(log) => {
            // The daemon never stops on input: bad lines are skipped and counted.
            let options = ReadOptions {
                format: None,
                skip_bad: true,
                device: None,
                not_heard: -200,
            };
            let reader = CaptureReader::open(log, &serving.building, &options)?;
            sources.push(Box::new(CaptureSource::new(
                log.clone(),
                reader,
                args.speed,
            )));
            watch::channel(BleStatus {
                state: "replay",
                ..BleStatus::default()
            })
            .1
        }
        // A locator hears the air only through the edges.
        None if config.cluster.role == Role::Locator => {
            watch::channel(BleStatus {
                state: "none",
                ..BleStatus::default()
            })
            .1
        }
        None => {
            let (ble, status) =
                BleSource::new(config.ble.clone(), config.gateway_id.as_str().into());
            sources.push(Box::new(ble));
            status
        }
    };
    let mut fallbacks = Vec::new();
    // A store that cannot be opened never stops the gateway: it is moved
    // aside (or, if even that fails, the gateway serves without recording).
    if config.store.enabled {
        match Recorder::open(&config.store, unix_now()) {
            Ok(recorder) => sinks.push(Box::new(
                recorder.keep_heard(config.localizer.recalibration.max_windows),
            )),
            Err(e) => {
                let why = format!("[store] {e}; serving without recording");
                tracing::error!("{why}");
                fallbacks.push(why);
            }
        }
    }
    // The editor applies a saved site through the same reloads as SIGHUP.
    let web = crate::web::start(
        &config.web,
        &config.site,
        &config.window,
        config.limits.max_devices,
        serving.building.clone(),
        &mut fallbacks,
        Some(reload),
    )
    .await;
    let latency = web.map(|web| web.add_to(&mut sources, &mut sinks));
    if let Some(out) = &args.out {
        sinks.push(Box::new(JsonLines::create(
            config.broker_identity(&serving.building.name).topics(),
            out,
        )?));
    }
    tracing::info!(
        broker = %url,
        prefix = config.topic_prefix(),
        site = site.name,
        sharing = config.shares_sightings(),
        role = ?config.cluster.role,
        "gateway {} serving",
        config.gateway_id
    );
    let options = daemon::Options {
        config_path: Some(args.config.path.clone()),
        stats: true,
        until_sources_end: false,
        share_sightings: config.shares_sightings(),
        radio: Some(radio),
        fallbacks,
        latency,
        recalibrate: Some(recalibrate),
    };
    daemon::run(serving, options, sources, sinks, shutdown, reloads).await?;
    Ok(())
}

/// SIGTERM and SIGINT as the shutdown future, SIGHUP as reloads (and a
/// sender of more: the editor's saves) and SIGUSR1 as requests to
/// recalibrate (one more asked while one is pending is the same one).
#[allow(clippy::type_complexity)]
fn signals() -> anyhow::Result<(
    impl Future<Output = ()>,
    mpsc::Sender<()>,
    mpsc::Receiver<()>,
    mpsc::Receiver<()>,
)> {
    let mut terminate = signal(SignalKind::terminate())?;
    let mut interrupt = signal(SignalKind::interrupt())?;
    let (reload, reloads) = requests(signal(SignalKind::hangup())?);
    let (_, recalibrations) = requests(signal(SignalKind::user_defined1())?);
    let shutdown = async move {
        tokio::select! {
            _ = terminate.recv() => {}
            _ = interrupt.recv() => {}
        }
    };
    Ok((shutdown, reload, reloads, recalibrations))
}

/// Each delivery of a signal as one request, and a sender of more.
fn requests(mut signal: tokio::signal::unix::Signal) -> (mpsc::Sender<()>, mpsc::Receiver<()>) {
    let (send, requests) = mpsc::channel(1);
    let more = send.clone();
    tokio::spawn(async move {
        while signal.recv().await.is_some() {
            if let Err(mpsc::error::TrySendError::Closed(())) = send.try_send(()) {
                return;
            }
        }
    });
    (more, requests)
}

/// A SIGHUP's default action ends the process. Until the runtime's handler
/// takes over (first thing in `serve`), one is ignored instead: nothing has
/// been read yet, so the config about to be loaded is the one a reload would
/// load.
fn ignore_reloads_until_served() {
    // SAFETY: installs the kernel's own "ignore" disposition for SIGHUP, no
    // handler of ours; called before any other thread exists.
    unsafe {
        libc::signal(libc::SIGHUP, libc::SIG_IGN);
    }
}

/// glibc raises its mmap threshold each time a large block is freed; after
/// that, large blocks come from the heap and stay with the process when
/// freed. Loading a model frees several model-sized buffers (file, protobuf,
/// intermediate graphs), so with the dynamic threshold the daemon kept about
/// 7 MB it no longer used for each model set. A fixed threshold (glibc's
/// default starting value) gives it back.
///
/// Only for the daemon, a long-lived process whose memory is what counts:
/// with a fixed threshold every block over 128 KiB is mapped and unmapped
/// anew, and the matrix products of `train` (whose packing buffers are
/// allocated per call) spent a third of their time in page faults.
fn keep_freed_memory_returnable() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes allocator tuning and is called before any
    // other thread exists (the runtime starts after it).
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 128 * 1024);
    }
}
