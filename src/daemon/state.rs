//! What the daemon serves from: config, site and the pipeline built on them,
//! loaded as one unit so that SIGHUP can swap them atomically. Everything the
//! pipeline loads (site now, trained models as they arrive) is checked by
//! [`Pipeline::new`], so a bad new file fails [`load`] and the old state keeps
//! serving.

use std::path::Path;
use std::sync::Arc;

use anyhow::Context;

use crate::config::Config;
use crate::pipeline::Pipeline;
use crate::site::Site;

pub struct Loaded {
    pub config: Config,
    pub site: Arc<Site>,
    pub pipeline: Pipeline,
}

/// Loads the config, its site and everything the pipeline needs.
pub fn load(config_path: &Path) -> anyhow::Result<Loaded> {
    let config = Config::load(config_path)?;
    let site = Arc::new(Site::load(&config.site)?);
    let pipeline = Pipeline::new(&config, site.clone())
        .with_context(|| format!("{}", config_path.display()))?;
    Ok(Loaded {
        config,
        site,
        pipeline,
    })
}

/// Why `new` cannot replace `old` without a restart: settings the live MQTT
/// connection and subscriptions were built from.
pub fn restart_needed(old: &Loaded, new: &Loaded) -> Option<&'static str> {
    if old.config.gateway_id != new.config.gateway_id {
        Some("`gateway_id` changed")
    } else if old.config.mqtt != new.config.mqtt {
        Some("[mqtt] changed")
    } else if old.config.store != new.config.store {
        Some("[store] changed")
    } else if old.config.window.orientation != new.config.window.orientation {
        Some("[window] orientation changed")
    } else if old.config.site_prefix(&old.site.name) != new.config.site_prefix(&new.site.name) {
        Some("the site name (and with it the shared-sightings prefix) changed")
    } else {
        None
    }
}
