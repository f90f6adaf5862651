//! `gangway record`: what this host hears, written as an advert log or a
//! btsnoop capture.

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use tokio::sync::mpsc;

use crate::source::ble::{self, BleConfig};
use crate::source::capture::{CaptureWriter, Format};
use crate::source::{Input, Shutdown, SourceContext};

#[derive(clap::Args)]
pub(super) struct Args {
    /// The file to write: JSON Lines, or btsnoop when named *.btsnoop.
    #[arg(long)]
    out: PathBuf,
    /// Write this format whatever the file's name: jsonl, or btsnoop (Linux
    /// monitor datalink, opens in Wireshark and btmon; the observer id is not
    /// stored, pass it to `replay --device`).
    #[arg(long, value_enum)]
    format: Option<Format>,
    /// Stop after this many seconds; without it, record until Ctrl-C.
    #[arg(long)]
    duration: Option<f64>,
    /// Adapter to scan with (`hci0`); the first one if not given.
    #[arg(long)]
    adapter: Option<String>,
    /// The observer id written on every advert; this host's name if not given.
    #[arg(long)]
    observer: Option<String>,
}

pub(super) fn run(args: Args) -> anyhow::Result<ExitCode> {
    let observer: Arc<str> = args.observer.clone().unwrap_or_else(hostname).into();
    let mut writer = CaptureWriter::create(&args.out, args.format)?;
    super::runtime()?.block_on(async {
        let config = BleConfig {
            adapter: args.adapter.clone(),
            ..BleConfig::default()
        };
        let manager = ble::connect().await?;
        let adapter = ble::adapter(&manager, &config).await?;
        let (tx, mut rx) = mpsc::channel(4096);
        let (stop, shutdown) = Shutdown::new();
        // A scan has no messages from others: that queue goes nowhere.
        let (nobody, _) = mpsc::channel(1);
        let mut cx = SourceContext::new(tx, nobody, shutdown);
        let silent_restart = config.silent_restart();
        let scan =
            async move { ble::scan(&adapter, observer, silent_restart, &mut cx, || {}).await };
        let scanner = tokio::spawn(scan);
        let deadline =
            tokio::time::sleep(args.duration.map_or(Duration::MAX, Duration::from_secs_f64));
        tokio::pin!(deadline);
        let mut adverts = 0u64;
        loop {
            tokio::select! {
                input = rx.recv() => match input {
                    Some(Input::Events(events)) => {
                        for event in &events {
                            writer.write(event).with_context(|| format!("writing {}", args.out.display()))?;
                        }
                        adverts += events.len() as u64;
                    }
                    Some(Input::Inbound(_)) => {}
                    None => break,
                },
                _ = &mut deadline => break,
                _ = tokio::signal::ctrl_c() => break,
            }
        }
        // The scan stops discovering before it returns.
        stop.trigger();
        drop(rx);
        writer.flush()?;
        scanner.await??;
        tracing::info!(adverts, out = %args.out.display(), "recording written");
        anyhow::Ok(())
    })?;
    Ok(ExitCode::SUCCESS)
}

fn hostname() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|h| h.trim().to_owned())
        .ok()
        .filter(|h| !h.is_empty())
        .unwrap_or_else(|| "gangway".to_owned())
}
