//! What the daemon serves from: config, site and the pipeline built on them,
//! loaded as one unit so that SIGHUP can swap them atomically. Everything the
//! pipeline loads (site now, trained models as they arrive) is checked by
//! [`Pipeline::new`], so a bad new file fails [`load`] and the old state keeps
//! serving. At start-up there is no old state: [`load_at_start`] serves with
//! the file-free localizer or planner instead of the one that failed.

use std::path::Path;
use std::sync::Arc;

use anyhow::Context;

use crate::config::Config;
use crate::locate::recalibrate;
use crate::pipeline::Pipeline;
use crate::site::{Building, Site};

pub struct Loaded {
    pub config: Config,
    pub site: Arc<Site>,
    pub pipeline: Pipeline,
    /// Components that failed to load at start-up and what serves instead
    /// ([`Pipeline::with_fallbacks`]); empty after a successful reload.
    pub fallbacks: Vec<String>,
}

/// Loads the config, its site and everything the pipeline needs; any failure
/// is an error (a reload keeps the old state).
pub(crate) fn load(config_path: &Path) -> anyhow::Result<Loaded> {
    load_with(config_path, false)
}

/// [`load`] at start-up: a localizer or planner whose files fail to load falls
/// back to one that needs none. The config and the site must still load:
/// without them there is nothing to serve.
pub fn load_at_start(config_path: &Path) -> anyhow::Result<Loaded> {
    load_with(config_path, true)
}

fn load_with(config_path: &Path, fall_back: bool) -> anyhow::Result<Loaded> {
    let mut config = Config::load(config_path)?;
    let site = served_site(&config.site)?;
    // What an earlier recalibration learned outlives restarts and reloads.
    config.localizer = super::recalibration::serving(&config.localizer, &config.store, &site);
    let context = || format!("{}", config_path.display());
    let (pipeline, fallbacks) = if fall_back {
        Pipeline::with_fallbacks(&config.pipeline(), site.clone()).with_context(context)?
    } else {
        (
            Pipeline::new(&config.pipeline(), site.clone()).with_context(context)?,
            Vec::new(),
        )
    };
    Ok(Loaded {
        config,
        site,
        pipeline,
        fallbacks,
    })
}

/// The floor the daemon serves: the config's `site`, a site file or a
/// building file of one floor. A building of several floors is refused,
/// naming the file: tracking across floors and routes between them are
/// being built, and serving one floor of it silently would lose every
/// device on the others.
pub fn served_site(path: &Path) -> anyhow::Result<Arc<Site>> {
    let building = Building::load(path)?;
    if building.is_multi_floor() {
        let floors: Vec<&str> = building.floors().iter().map(|f| f.name.as_str()).collect();
        anyhow::bail!(
            "{}: a building of {} floors ({}); the gateway serves one floor for now: point \
             `site` in the config at one floor's site file (the `site` of one of its \
             [[floors]]), and run one gateway per floor",
            path.display(),
            floors.len(),
            floors.join(", ")
        );
    }
    Ok(building.floors()[0].site.clone())
}

/// The state of `config` on `site` with the survey-free model's calibration
/// read from `path` (a recalibration's file), built whole or refused whole
/// like a reload.
pub(crate) fn recalibrated(
    config: &Config,
    site: &Arc<Site>,
    path: &Path,
) -> anyhow::Result<Loaded> {
    let mut config = config.clone();
    config.localizer = recalibrate::with_calibration(&config.localizer, path);
    let pipeline = Pipeline::new(&config.pipeline(), site.clone())?;
    Ok(Loaded {
        config,
        site: site.clone(),
        pipeline,
        fallbacks: Vec::new(),
    })
}

/// Why `new` cannot replace `old` without a restart: settings the live MQTT
/// connection and subscriptions were built from, and the limits the daemon's
/// queues and rate limiters were.
pub(crate) fn restart_needed(old: &Loaded, new: &Loaded) -> Option<&'static str> {
    if old.config.gateway_id != new.config.gateway_id {
        Some("`gateway_id` changed")
    } else if old.config.mqtt != new.config.mqtt {
        Some("[mqtt] changed")
    } else if old.config.ble != new.config.ble {
        Some("[ble] changed")
    } else if old.config.store != new.config.store {
        Some("[store] changed")
    } else if old.config.limits != new.config.limits {
        Some("[limits] changed")
    } else if old.config.cluster != new.config.cluster {
        Some("[cluster] changed")
    } else if old.config.window.orientation != new.config.window.orientation {
        Some("[window] orientation changed")
    } else if old.config.site_prefix(&old.site.name) != new.config.site_prefix(&new.site.name) {
        Some("the site name (and with it the shared-sightings prefix) changed")
    } else {
        None
    }
}
