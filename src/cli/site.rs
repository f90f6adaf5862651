//! `gangway site edit`: the site editor in the browser, without a gateway.
//! Opens (or starts) one site file, serves the editor until Ctrl-C, and
//! saves there. `gangway site import`: a building's GeoJSON floor plans as
//! its floors' site files and a building file (`survey::building`).

use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::ExitCode;

use crate::survey::building;
use crate::web::{Editors, Server, Ui, WebConfig};

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
    /// A building's floor plans as site files: DIR holds one folder per
    /// floor named after it (B1, F1, …), each with `geojson_map.json`,
    /// `floor_info.json` and `floor_image.png`; writes each floor's site
    /// beside --out and the building file --out listing them, with the
    /// stairs, lifts, escalators and ramps the plans name as connectors.
    Import(ImportArgs),
}

#[derive(clap::Args)]
struct ImportArgs {
    /// The directory of floor folders.
    #[arg(long, value_name = "DIR")]
    geojson: PathBuf,
    /// The building file to write; each floor's site goes in
    /// `<its folder>/<floor>/site.toml` (files of those names are replaced).
    #[arg(long, value_name = "SITE.toml")]
    out: PathBuf,
    /// Metres per cell side, on every floor.
    #[arg(long, default_value_t = 1.0)]
    cell_m: f64,
    /// The building's name [default: DIR's name].
    #[arg(long)]
    name: Option<String>,
    /// Print one JSON object with what was written instead of lines.
    #[arg(long)]
    json: bool,
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
    match args.command {
        Command::Edit(args) => edit(args),
        Command::Import(args) => import(&args),
    }
}

fn import(args: &ImportArgs) -> anyhow::Result<ExitCode> {
    let options = building::Options {
        name: args.name.clone(),
        cell_m: args.cell_m,
    };
    let json = args.json;
    let report = building::import(&args.geojson, &args.out, &options, &mut |floor| {
        if !json {
            println!(
                "floor {} (level {}, from its {}): wrote {}: {} of {} cells walkable at {} m, {} \
                 places, {} stairs/lift/escalator/ramp areas",
                floor.name,
                floor.level,
                floor.level_from,
                floor.site.display(),
                floor.walkable_cells,
                floor.cells,
                options.cell_m,
                floor.places,
                floor.connector_areas
            );
        }
    })?;
    if json {
        println!("{}", serde_json::to_value(&report)?);
        return Ok(ExitCode::SUCCESS);
    }
    for skipped in &report.skipped {
        println!(
            "skipped {}: no geojson_map.json, so not a floor",
            skipped.display()
        );
    }
    for c in &report.connectors {
        println!(
            "connector `{}` ({}): {}",
            c.id,
            c.kind.name(),
            c.floors.join(", ")
        );
    }
    for area in &report.unjoined {
        println!(
            "not joined: {area} lines up with no area of its kind on the next floor within {} m",
            building::JOIN_M
        );
    }
    if report.connectors.is_empty() {
        println!(
            "no connectors found: no area of the plans is named or categorised as stairs, lift, \
             elevator, escalator or ramp on two floors. Until the building file has some, no \
             route or walker can change floor: add a [[connectors]] entry per stair, lift, \
             escalator or ramp to {} (id, kind, stops = [{{ floor = \"B1\", cell = [x, y] }}, …]; \
             see docs/floors.md), or place them on the plans with `gangway site edit --site {}`",
            args.out.display(),
            args.out.display()
        );
    }
    println!(
        "wrote {}: building `{}`, {} floors, {} connectors; check it with `gangway check --site \
         {}`",
        report.building.display(),
        report.name,
        report.floors.len(),
        report.connectors.len(),
        report.building.display()
    );
    Ok(ExitCode::SUCCESS)
}

fn edit(args: EditArgs) -> anyhow::Result<ExitCode> {
    let editor = Editors::open(&args.site, args.image.as_deref())?;
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
