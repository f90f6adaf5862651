//! `gangway site edit`: the site editor in the browser, without a gateway.
//! Opens (or starts) one site file, serves the editor until Ctrl-C, and
//! saves there.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::ExitCode;

use crate::web::{Editor, Server, Ui, WebConfig};

#[derive(clap::Args)]
pub(super) struct Args {
    #[command(subcommand)]
    command: Command,
}

#[derive(clap::Subcommand)]
enum Command {
    /// Edit a site file over its floor plan in the browser (a new file when
    /// it does not exist yet): scale, walkable cells, obstacles, walls,
    /// beacons and places, checked as `gangway check` checks them.
    Edit(EditArgs),
}

#[derive(clap::Args)]
struct EditArgs {
    /// The site file to edit (created on the first save).
    #[arg(long)]
    site: PathBuf,
    /// A floor-plan image (PNG, JPEG or WebP) to draw the site over, when
    /// the file names none yet.
    #[arg(long)]
    image: Option<PathBuf>,
    /// Where to listen. Off loopback, saving needs --token-file.
    #[arg(long, default_value = "127.0.0.1:8080")]
    bind: SocketAddr,
    /// The token a browser must send to save, when bound off loopback.
    #[arg(long)]
    token_file: Option<PathBuf>,
}

pub(super) fn run(args: Args) -> anyhow::Result<ExitCode> {
    let Command::Edit(args) = args.command;
    let editor = Editor::open(&args.site, args.image.as_deref())?;
    let config = WebConfig {
        bind: args.bind,
        token_file: args.token_file,
        ..WebConfig::default()
    };
    super::runtime()?.block_on(async move {
        let server = Server::bind(&config).await?;
        let addr = server.addr();
        let host = if addr.ip().is_unspecified() {
            "127.0.0.1".to_owned()
        } else {
            addr.ip().to_string()
        };
        let shown = if addr.is_ipv6() {
            format!("[{host}]")
        } else {
            host
        };
        println!(
            "editing {} at http://{shown}:{}/edit (Ctrl-C to stop)",
            editor.path().display(),
            addr.port()
        );
        let shutdown = async {
            let _ = tokio::signal::ctrl_c().await;
        };
        let stop = async {
            use tokio::signal::unix::{SignalKind, signal};
            match signal(SignalKind::terminate()) {
                Ok(mut term) => {
                    tokio::select! {
                        () = shutdown => {}
                        _ = term.recv() => {}
                    }
                }
                Err(_) => shutdown.await,
            }
        };
        server.serve(Ui::editor(editor), stop).await
    })?;
    Ok(ExitCode::SUCCESS)
}
