use std::io::IsTerminal;
use std::process::ExitCode;

use clap::Parser;
use tracing_subscriber::EnvFilter;

fn main() -> ExitCode {
    keep_freed_memory_returnable();
    // RUST_LOG filters. The embedded broker's chatter stays at warn, and its
    // connection module is silenced: it logs every client disconnect as an
    // error (`router-drop`), and its one real failure, a busy port, is
    // checked before it starts (`mqtt::broker`).
    let filter = EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| EnvFilter::new("info,rumqttd=warn,rumqttd::server::broker=off"));
    // GANGWAY_LOG_FORMAT=json gives one JSON object per line (log shippers,
    // files); otherwise the human format, coloured only on a terminal.
    let json = std::env::var("GANGWAY_LOG_FORMAT").is_ok_and(|f| f.eq_ignore_ascii_case("json"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr);
    if json {
        builder.json().init();
    } else {
        builder.with_ansi(std::io::stderr().is_terminal()).init();
    }
    match gangway::cli::Cli::parse().run() {
        Ok(code) => code,
        Err(e) => {
            eprintln!("gangway: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// glibc raises its mmap threshold each time a large block is freed; after
/// that, large blocks come from the heap and stay with the process when
/// freed. Loading a model frees several model-sized buffers (file, protobuf,
/// intermediate graphs), so with the dynamic threshold the daemon kept about
/// 7 MB it no longer used for each model set. A fixed threshold (glibc's
/// default starting value) gives it back.
fn keep_freed_memory_returnable() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes allocator tuning and is called before any
    // other thread exists.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 128 * 1024);
    }
}
