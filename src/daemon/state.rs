//! What the daemon serves from: config, site and the pipeline built on them,
//! loaded as one unit so that SIGHUP can swap them atomically. Everything the
//! pipeline loads (site now, trained models as they arrive) is checked by
//! [`Pipeline::new`], so a bad new file fails [`load`] and the old state keeps
//! serving. At start-up there is no old state: [`load_at_start`] serves with
//! the file-free localizer or planner instead of the one that failed.

use std::path::Path;
use std::sync::Arc;

use anyhow::Context;

use super::recalibration::Recalibrated;
use crate::config::Config;
use crate::locate::recalibrate;
use crate::pipeline::Pipeline;
use crate::site::{Building, Site};

pub struct Loaded {
    pub config: Config,
    /// What the pipeline serves: the config's `site`, a building of one
    /// floor or several.
    pub building: Arc<Building>,
    /// Its lowest floor, the only one of a one-floor site: what the sinks
    /// that show one floor (the map, the editor, Home Assistant's places)
    /// are given.
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
    let building = Arc::new(Building::load(&config.site)?);
    let site = building.floors()[0].site.clone();
    // What an earlier recalibration learned outlives restarts and reloads.
    let serving = super::recalibration::serving(&config.localizer, &config.store, &building);
    for file in &serving.files {
        if let Err(e) = &file.loaded {
            tracing::error!("{e}; serving the configured calibration instead");
        }
    }
    config.localizer = serving.config;
    let context = || format!("{}", config_path.display());
    let (pipeline, fallbacks) = if fall_back {
        Pipeline::with_fallbacks(&config.pipeline(), building.clone()).with_context(context)?
    } else {
        (
            Pipeline::for_building(&config.pipeline(), building.clone()).with_context(context)?,
            Vec::new(),
        )
    };
    Ok(Loaded {
        config,
        building,
        site,
        pipeline,
        fallbacks,
    })
}

/// The state of `config` on `building` with the survey-free model's
/// calibration of each floor recalibrated in `done` read from its file,
/// built whole or refused whole like a reload.
pub(crate) fn recalibrated(
    config: &Config,
    building: &Arc<Building>,
    done: &[Recalibrated],
) -> anyhow::Result<Loaded> {
    let mut config = config.clone();
    for floor in done {
        config.localizer =
            recalibrate::with_calibration(&config.localizer, floor.floor.as_deref(), &floor.path);
    }
    let pipeline = Pipeline::for_building(&config.pipeline(), building.clone())?;
    Ok(Loaded {
        config,
        building: building.clone(),
        site: building.floors()[0].site.clone(),
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
    } else if old.config.site_prefix(&old.building.name)
        != new.config.site_prefix(&new.building.name)
    {
        Some("the site name (and with it the shared-sightings prefix) changed")
    } else {
        None
    }
}
