//! Writes what the Debian package ships beside the binary and the repository's
//! own files (Cargo.toml, `[package.metadata.deb]`):
//!
//! - `man/gangway.1` and one page per subcommand (`gangway-run.1`, …);
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
    clap_mangen::generate_to(gangway::cli::Cli::command(), &man)
        .with_context(|| format!("writing man pages to {}", man.display()))?;

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
