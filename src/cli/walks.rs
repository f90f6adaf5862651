//! `gangway walks`: real walks in. `import` turns recorded tracks into the
//! training and held-out walks of a site; `site` builds the site of a
//! recorded scene from its obstacle image or from where people walked.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::Context;
use clap::Subcommand;

use crate::site::{Site, YAxis};
use crate::train::trajectory;
use crate::walks::scene::{self, ObstacleImage, Obstacles};
use crate::walks::{self, Format, Homography, PixelOrder, RasterOptions, RasterStats, ReadOptions};

#[derive(clap::Args)]
pub(super) struct Args {
    #[command(subcommand)]
    what: What,
}

#[derive(Subcommand)]
enum What {
    /// Recorded tracks (CSV or obsmat) as walks on a site, split by time.
    Import(ImportArgs),
    /// The site of a recorded scene: from its obstacle image, or the cells
    /// its walks pass through.
    Site(SiteArgs),
}

/// Where tracks come from and how their numbers become world metres.
#[derive(clap::Args)]
pub(super) struct TrackSource {
    /// `csv` (`track,t,x,y`) or `obsmat` (`frame person x z y vx vz vy`);
    /// guessed from the file name (`obsmat*.txt`) when not given.
    #[arg(long, value_enum)]
    format: Option<Format>,
    /// Obsmat files: annotated positions per second (ETH and UCY: 2.5).
    #[arg(long, default_value_t = 2.5)]
    annotation_hz: f64,
}

impl TrackSource {
    pub(super) fn read(
        &self,
        path: &Path,
        homography: Option<Homography>,
    ) -> anyhow::Result<Vec<walks::Track>> {
        anyhow::ensure!(
            self.annotation_hz.is_finite() && self.annotation_hz > 0.0,
            "--annotation-hz must be a positive rate"
        );
        let options = ReadOptions {
            format: self.format.unwrap_or_else(|| Format::guess(path)),
            homography,
            annotation_hz: self.annotation_hz,
        };
        Ok(walks::read(path, &options)?)
    }
}

#[derive(clap::Args)]
struct ImportArgs {
    /// The site the walks are put on (its frame maps world metres to cells).
    #[arg(long)]
    site: PathBuf,
    /// The recorded tracks.
    #[arg(long)]
    from: PathBuf,
    #[command(flatten)]
    source: TrackSource,
    /// Pixel → world homography (3 lines of 3 numbers, as `H.txt`) for tracks
    /// recorded in image pixels.
    #[arg(long)]
    homography: Option<PathBuf>,
    /// How the homography addresses pixels.
    #[arg(long, value_enum, default_value = "col-row")]
    pixel_order: PixelOrder,
    /// Walks (pieces of tracks) with fewer cells are dropped.
    #[arg(long, default_value_t = 4)]
    min_cells: usize,
    /// Extend each walk's ends to the nearest named place within this many
    /// metres, when the straight way there is walkable.
    #[arg(long)]
    snap_m: Option<f64>,
    /// Share of walks held out, the latest by start time.
    #[arg(long, default_value_t = 0.3)]
    holdout: f64,
    /// Training walks (trajectory JSON Lines).
    #[arg(long)]
    train: PathBuf,
    /// Held-out walks (trajectory JSON Lines); needed unless --holdout 0.
    #[arg(long)]
    heldout: Option<PathBuf>,
    /// Print the summary as JSON.
    #[arg(long)]
    json: bool,
}

#[derive(clap::Args)]
struct SiteArgs {
    /// The site's name (default: the --out file's stem).
    #[arg(long)]
    name: Option<String>,
    /// Metres per cell side.
    #[arg(long)]
    cell_m: f64,
    /// Obstacle image (e.g. `map.png`); needs --homography.
    #[arg(long, requires = "homography")]
    image: Option<PathBuf>,
    /// The image's pixel → world homography (3 lines of 3 numbers, `H.txt`).
    #[arg(long, requires = "image")]
    homography: Option<PathBuf>,
    /// How the homography addresses pixels (ETH's `H.txt`: row-col).
    #[arg(long, value_enum, default_value = "col-row")]
    pixel_order: PixelOrder,
    /// Which pixels of the image are obstacles.
    #[arg(long, value_enum, default_value = "dark")]
    obstacles: Obstacles,
    /// The scene's tracks in world metres: the site covers them plus
    /// --margin-m, and without --image their cells are the walkable ones.
    #[arg(long, required_unless_present = "image")]
    walks: Option<PathBuf>,
    #[command(flatten)]
    source: TrackSource,
    /// Metres of ground around the walks.
    #[arg(long, default_value_t = 1.0)]
    margin_m: f64,
    /// `up`: world y shrinks down the rows (the datasets' frames); `down`:
    /// grows.
    #[arg(long, value_parser = parse_y_axis, default_value = "up")]
    y_axis: YAxis,
    /// The site file to write.
    #[arg(long)]
    out: PathBuf,
}

fn parse_y_axis(text: &str) -> Result<YAxis, String> {
    match text {
        "up" => Ok(YAxis::Up),
        "down" => Ok(YAxis::Down),
        _ => Err(format!("`{text}`: use up or down")),
    }
}

pub(super) fn run(args: Args) -> anyhow::Result<ExitCode> {
    match args.what {
        What::Import(args) => import(args),
        What::Site(args) => site(args),
    }
}

fn import(args: ImportArgs) -> anyhow::Result<ExitCode> {
    anyhow::ensure!(
        (0.0..1.0).contains(&args.holdout),
        "--holdout must be at least 0 and below 1"
    );
    anyhow::ensure!(
        args.holdout == 0.0 || args.heldout.is_some(),
        "--heldout FILE is needed to write the held-out walks (or give --holdout 0)"
    );
    if let Some(r) = args.snap_m {
        anyhow::ensure!(r.is_finite() && r >= 0.0, "--snap-m must be metres ≥ 0");
    }
    let site = Site::load(&args.site)?;
    let homography = args
        .homography
        .as_ref()
        .map(|p| Homography::load_ordered(p, args.pixel_order))
        .transpose()?;
    let tracks = args.source.read(&args.from, homography)?;
    let options = RasterOptions {
        min_cells: args.min_cells,
        snap_m: args.snap_m,
    };
    let mut stats = RasterStats::default();
    let all: Vec<_> = tracks
        .iter()
        .flat_map(|t| walks::rasterise(&site, t, &options, &mut stats))
        .collect();
    anyhow::ensure!(
        !all.is_empty(),
        "{}: no walk of {}+ cells lands on walkable cells of {} ({} tracks, {} of {} points \
         off the grid or blocked): check the site's origin_m/y_axis and the input's units",
        args.from.display(),
        args.min_cells,
        args.site.display(),
        stats.tracks,
        stats.points_outside,
        stats.points
    );
    let (train, heldout, cutoff) = walks::split_by_time(all, args.holdout);
    write_walks(&args.train, &train)?;
    if let Some(path) = &args.heldout {
        write_walks(path, &heldout)?;
    }
    let summary = serde_json::json!({
        "tracks": stats.tracks,
        "points": stats.points,
        "points_off_walkable": stats.points_outside,
        "walks": stats.walks,
        "short_pieces_dropped": stats.short_pieces,
        "snapped_ends": stats.snapped_ends,
        "train_walks": train.len(),
        "heldout_walks": heldout.len(),
        "heldout_from_s": cutoff,
    });
    if args.json {
        println!("{}", serde_json::to_string(&summary)?);
    } else {
        println!(
            "{} tracks ({} points, {} off walkable cells) → {} walks ({} short pieces dropped, \
             {} ends snapped); {} training, {} held out{}",
            stats.tracks,
            stats.points,
            stats.points_outside,
            stats.walks,
            stats.short_pieces,
            stats.snapped_ends,
            train.len(),
            heldout.len(),
            cutoff.map_or(String::new(), |t| format!(" (starting from t = {t:.1} s)"))
        );
    }
    Ok(ExitCode::SUCCESS)
}

fn write_walks(path: &Path, walks: &[trajectory::Trajectory]) -> anyhow::Result<()> {
    let file =
        std::fs::File::create(path).with_context(|| format!("cannot write {}", path.display()))?;
    trajectory::write(std::io::BufWriter::new(file), walks)
        .with_context(|| format!("cannot write {}", path.display()))
}

fn site(args: SiteArgs) -> anyhow::Result<ExitCode> {
    let image = match (&args.image, &args.homography) {
        (Some(image), Some(h)) => Some(ObstacleImage::load(
            image,
            Homography::load_ordered(h, args.pixel_order)?,
            args.obstacles,
        )?),
        _ => None,
    };
    let tracks = match &args.walks {
        Some(path) => args.source.read(path, None)?,
        None => Vec::new(),
    };
    let name = args.name.clone().unwrap_or_else(|| {
        args.out
            .file_stem()
            .map_or("scene".into(), |s| s.to_string_lossy().into_owned())
    });
    let command = std::env::args().collect::<Vec<_>>().join(" ");
    let (text, site) = scene::build(&scene::Scene {
        name,
        cell_m: args.cell_m,
        y_axis: args.y_axis,
        margin_m: args.margin_m,
        image: image.as_ref(),
        walks: &tracks,
        command,
    })?;
    std::fs::write(&args.out, text)
        .with_context(|| format!("cannot write {}", args.out.display()))?;
    let ([x0, y0], [x1, y1]) = site.extent_m();
    println!(
        "{}: {} × {} cells of {} m ({} walkable), world x {x0:.1}..{x1:.1}, y {y0:.1}..{y1:.1}",
        args.out.display(),
        site.width(),
        site.height(),
        site.cell_m,
        site.open_cells().len()
    );
    Ok(ExitCode::SUCCESS)
}
