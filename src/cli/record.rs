//! `gangway record`: what this host hears, written as an advert log.

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use tokio::sync::mpsc;

use crate::source::ble::{self, BleConfig};
use crate::source::log::LogWriter;

#[derive(clap::Args)]
pub struct Args {
    /// The log to write (JSON Lines).
    #[arg(long)]
    out: PathBuf,
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

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let observer: Arc<str> = args.observer.clone().unwrap_or_else(hostname).into();
    let mut writer = LogWriter::create(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    super::runtime()?.block_on(async {
        let adapter = ble::adapter(&BleConfig {
            adapter: args.adapter.clone(),
        })
        .await?;
        let (tx, mut rx) = mpsc::channel(4096);
        let scanner = tokio::spawn(async move { ble::scan(&adapter, observer, tx).await });
        let deadline =
            tokio::time::sleep(args.duration.map_or(Duration::MAX, Duration::from_secs_f64));
        tokio::pin!(deadline);
        let mut adverts = 0u64;
        loop {
            tokio::select! {
                event = rx.recv() => match event {
                    Some(event) => {
                        writer.write(&event)?;
                        adverts += 1;
                    }
                    None => break,
                },
                _ = &mut deadline => break,
                _ = tokio::signal::ctrl_c() => break,
            }
        }
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
