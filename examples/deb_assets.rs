//! Writes what the Debian package ships beside the binary and the repository's
//! own files (Cargo.toml, `[package.metadata.deb]`):
//!
//! - `man/gangway.1` and one page per subcommand (`gangway-run.1`, …): clap's
//!   sections, then EXAMPLES (the lines `--help` shows, from
//!   `gangway::cli::examples`), and for the commands that read the gateway
//!   config, ENVIRONMENT and FILES as the package lays them out;
//! - `completions/gangway.bash`, `completions/_gangway` (zsh),
//!   `completions/gangway.fish`;
//! - `gangway.toml`: `config/gangway.toml` with its model paths pointed at
//!   the packaged models in `/usr/share/gangway/models` (in the repository they
//!   are relative to the config, `../models/…`, which from `/etc/gangway`
//!   would name `/etc/models`).
//!
//! ```sh
//! cargo run --release --example deb_assets -- target/deb-assets && cargo deb
//! ```
//!
//! An example rather than a build script or a subcommand: pages and
//! completions come from the CLI's own clap definition in the library, which a
//! build script cannot compile (it runs before the crate it builds), and the
//! daemon's binary carries neither packaging code nor clap_mangen and
//! clap_complete.

use std::path::{Path, PathBuf};

use anyhow::{Context, ensure};
use clap::CommandFactory;
use clap_complete::Shell;
use roff::{Roff, bold, roman};

/// A roff request with no arguments (`.TP`).
const NO_ARGUMENTS: [&str; 0] = [];

/// Where the package installs the shipped models.
const PACKAGED_MODELS: &str = "/usr/share/gangway/models/";

fn main() -> anyhow::Result<()> {
    let out = PathBuf::from(
        std::env::args()
            .nth(1)
            .context("usage: deb_assets <output directory>")?,
    );
    let repo = Path::new(env!("CARGO_MANIFEST_DIR"));

    let man = out.join("man");
    std::fs::create_dir_all(&man).with_context(|| man.display().to_string())?;
    let mut cli = gangway::cli::Cli::command().disable_help_subcommand(true);
    cli.build();
    write_man_pages(&cli, &man)?;

    let completions = out.join("completions");
    std::fs::create_dir_all(&completions).with_context(|| completions.display().to_string())?;
    for shell in [Shell::Bash, Shell::Zsh, Shell::Fish] {
        clap_complete::generate_to(
            shell,
            &mut gangway::cli::Cli::command(),
            "gangway",
            &completions,
        )
        .with_context(|| format!("writing {shell} completions to {}", completions.display()))?;
    }

    let source = repo.join("config/gangway.toml");
    let config = std::fs::read_to_string(&source).with_context(|| source.display().to_string())?;
    let packaged = packaged_config(&config, &repo.join("models"))
        .with_context(|| source.display().to_string())?;
    std::fs::write(out.join("gangway.toml"), packaged)?;
    println!(
        "wrote man pages, completions and gangway.toml to {}",
        out.display()
    );
    Ok(())
}

/// Writes the page of `command` and of each of its subcommands into `dir`.
fn write_man_pages(command: &clap::Command, dir: &Path) -> anyhow::Result<()> {
    for sub in command.get_subcommands().filter(|s| !s.is_hide_set()) {
        write_man_pages(sub, dir)?;
    }
    let man = clap_mangen::Man::new(command.clone());
    let path = dir.join(man.get_filename());
    let mut page = Vec::new();
    man.render_title(&mut page)?;
    man.render_name_section(&mut page)?;
    man.render_synopsis_section(&mut page)?;
    man.render_description_section(&mut page)?;
    if command.get_arguments().any(|a| !a.is_hide_set()) {
        man.render_options_section(&mut page)?;
    }
    if command.has_subcommands() {
        man.render_subcommands_section(&mut page)?;
    }
    let mut roff = Roff::new();
    if let Some(examples) = command.get_after_long_help() {
        examples_section(&mut roff, &examples.to_string())
            .with_context(|| format!("{}: the examples", path.display()))?;
    }
    // The root page, and the commands that read the gateway config, say where
    // the package puts things and what the environment changes.
    let reads_config = command.get_arguments().any(|a| a.get_id() == "config");
    if command.get_name() == "gangway" || reads_config {
        environment_section(&mut roff);
        files_section(&mut roff);
    }
    roff.to_writer(&mut page)?;
    if command.get_version().is_some() {
        man.render_version_section(&mut page)?;
    }
    std::fs::write(&path, page).with_context(|| path.display().to_string())
}

/// EXAMPLES: each `gangway …  # what it does` line of `--help`'s examples as
/// a tagged paragraph, the command in bold.
fn examples_section(roff: &mut Roff, examples: &str) -> anyhow::Result<()> {
    let mut lines = examples.lines();
    ensure!(
        lines.next() == Some(gangway::cli::examples::HEADING),
        "the examples do not start with {:?}",
        gangway::cli::examples::HEADING
    );
    roff.control("SH", ["EXAMPLES"]);
    for line in lines {
        let (command, what) = line
            .split_once("  # ")
            .with_context(|| format!("{line:?} has no `  # ` comment"))?;
        roff.control("TP", NO_ARGUMENTS);
        roff.text([bold(command.trim())]);
        roff.text([roman(what)]);
    }
    Ok(())
}

/// ENVIRONMENT: what the binary reads from its environment.
fn environment_section(roff: &mut Roff) {
    roff.control("SH", ["ENVIRONMENT"]);
    for (name, what) in [
        (
            "GANGWAY_CONFIG",
            "The gateway config, where --config is not given.",
        ),
        (
            "RUST_LOG",
            "Which log lines are written to standard error, as tracing-subscriber's \
             EnvFilter reads it (default: info).",
        ),
        (
            "GANGWAY_LOG_FORMAT",
            "json: one JSON object per log line, for log shippers.",
        ),
        (
            "STATE_DIRECTORY",
            "Set by systemd (StateDirectory=): where the learning store, the site \
             editor's backups and the survey the live map records are kept.",
        ),
        (
            "CREDENTIALS_DIRECTORY",
            "Set by systemd (LoadCredential=): the credentials mqtt-password and \
             web-token are read from here when the config names no file.",
        ),
    ] {
        roff.control("TP", NO_ARGUMENTS);
        roff.text([bold(name)]);
        roff.text([roman(what)]);
    }
}

/// FILES: where the package installs and the service keeps things.
fn files_section(roff: &mut Roff) {
    roff.control("SH", ["FILES"]);
    for (path, what) in [
        (
            "/etc/gangway/gangway.toml",
            "The gateway config (the default --config outside a checkout of the \
             repository).",
        ),
        (
            "/etc/gangway/sites/",
            "Site files: grid, floor plan, beacons, gateways and places; calibrations \
             written by gangway calibrate.",
        ),
        (
            "/etc/gangway/mqtt-password",
            "The broker password, handed to the service as a systemd credential.",
        ),
        (
            "/usr/share/gangway/models/",
            "The shipped ONNX models the config points at.",
        ),
        (
            "/var/lib/gangway/",
            "The service's state: learning.sqlite and the site editor's backups.",
        ),
        (
            "/usr/lib/systemd/system/gangway.service",
            "The unit: systemctl enable --now gangway once the config is set.",
        ),
        (
            "/usr/share/doc/gangway/",
            "The README, the guides and the JSON schemas of every MQTT payload.",
        ),
    ] {
        roff.control("TP", NO_ARGUMENTS);
        roff.text([bold(path)]);
        roff.text([roman(what)]);
    }
}

/// The config with every `"../models/<file>"` pointed at the packaged copy;
/// each such file must exist in `models` (the package ships that directory).
fn packaged_config(config: &str, models: &Path) -> anyhow::Result<String> {
    const RELATIVE: &str = "\"../models/";
    let mut files = 0;
    for (i, line) in config.lines().enumerate() {
        // A commented key (a model a mode other than the shipped one needs,
        // which `gangway train` writes) is rewritten below but need not ship.
        if line.trim_start().starts_with('#') {
            continue;
        }
        if let Some(start) = line.find(RELATIVE) {
            let rest = &line[start + RELATIVE.len()..];
            let file = &rest[..rest.find('"').context("unterminated string")?];
            ensure!(
                models.join(file).is_file(),
                "line {}: {file} is not in {}, so the package would not ship it",
                i + 1,
                models.display()
            );
            files += 1;
        }
    }
    ensure!(
        files > 0,
        "no \"../models/…\" path to point at {PACKAGED_MODELS}"
    );
    Ok(config.replace(RELATIVE, &format!("\"{PACKAGED_MODELS}")))
}
