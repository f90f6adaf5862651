use std::io::IsTerminal;
use std::process::ExitCode;

use clap::Parser;
use tracing_subscriber::EnvFilter;

fn main() -> ExitCode {
    // RUST_LOG filters. The embedded broker's chatter stays at warn, and its
    // connection and routing modules are silenced: they log every client
    // disconnect as an error (`router-drop`, and at shutdown "no-connection
    // id 0 is already gone"), and its one real failure, a busy port, is
    // checked before it starts (`mqtt::broker`).
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| {
        EnvFilter::new("info,rumqttd=warn,rumqttd::server::broker=off,rumqttd::router::routing=off")
    });
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
