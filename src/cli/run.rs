//! `gangway run`: the daemon.

use std::path::PathBuf;
use std::process::ExitCode;

use crate::daemon::{self, source::Replay};

#[derive(clap::Args)]
pub struct Args {
    #[arg(long, default_value_os_t = super::default_config())]
    config: PathBuf,
    /// Use this broker (mqtt://host:port or mqtts://host:port), overriding
    /// [mqtt] url. Without either, an embedded broker starts on 127.0.0.1.
    #[arg(long)]
    mqtt_url: Option<String>,
    /// Play this advert log instead of scanning Bluetooth (demos, tests, and
    /// gateways fed by another recorder); MQTT is served as in a live run.
    #[arg(long, value_name = "LOG")]
    replay: Option<PathBuf>,
    /// Playback speed of --replay: 1 is real time, 0 as fast as possible.
    #[arg(long, default_value_t = 1.0, requires = "replay")]
    speed: f64,
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    keep_freed_memory_returnable();
    anyhow::ensure!(
        args.speed >= 0.0 && args.speed.is_finite(),
        "--speed must be 0 (as fast as possible) or a positive factor"
    );
    let options = daemon::Options {
        config_path: args.config,
        mqtt_url: args.mqtt_url,
        replay: args.replay.map(|log| Replay {
            log,
            speed: args.speed,
        }),
    };
    super::runtime()?.block_on(daemon::run(options))?;
    Ok(ExitCode::SUCCESS)
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
