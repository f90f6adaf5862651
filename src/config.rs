//! The gateway config file (`config/gangway.toml`): one table per pipeline
//! stage, each owned by its module (`[window]` by `locate::window`, `[planner]` by
//! `plan`, …); this file only composes them and resolves paths.
//!
//! Relative paths in the file resolve against the directory of the config file,
//! so a config and its site can move together.

use std::path::{Path, PathBuf};

use serde::Deserialize;

use crate::guide::GuidanceConfig;
use crate::locate::LocalizerConfig;
use crate::locate::tracker::TrackerConfig;
use crate::locate::window::WindowConfig;
use crate::mqtt::MqttConfig;
use crate::plan::PlannerConfig;
use crate::source::ble::BleConfig;
use crate::store::StoreConfig;

#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// This gateway's id: the observer name of what it hears, and part of the
    /// default MQTT topic prefix.
    pub gateway_id: String,
    /// The site file.
    pub site: PathBuf,
    #[serde(default)]
    pub ble: BleConfig,
    #[serde(default)]
    pub window: WindowConfig,
    #[serde(default)]
    pub localizer: LocalizerConfig,
    #[serde(default)]
    pub tracker: TrackerConfig,
    #[serde(default)]
    pub planner: PlannerConfig,
    #[serde(default)]
    pub guidance: GuidanceConfig,
    #[serde(default)]
    pub mqtt: MqttConfig,
    /// `[store]`: the crowd-sourced learning store.
    #[serde(default)]
    pub store: StoreConfig,
}

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("{path}: cannot read the config file: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: {source}")]
    Toml {
        path: PathBuf,
        source: toml::de::Error,
    },
    #[error("{path}: {message}")]
    Invalid { path: PathBuf, message: String },
}

impl Config {
    /// Reads a config file and resolves its relative paths.
    pub fn load(path: &Path) -> Result<Config, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.to_owned(),
            source,
        })?;
        let mut config: Config = toml::from_str(&text).map_err(|source| ConfigError::Toml {
            path: path.to_owned(),
            source,
        })?;
        let base = path.parent().unwrap_or(Path::new("."));
        config.site = base.join(&config.site);
        if let Some(survey) = &mut config.localizer.knn.survey {
            *survey = base.join(&*survey);
        }
        config.localizer.onnx.model = base.join(&config.localizer.onnx.model);
        if let Some(calibration) = &mut config.localizer.pathloss.calibration {
            *calibration = base.join(&*calibration);
        }
        config.mqtt.resolve_paths(base);
        config.planner.resolve_paths(base);
        if let Some(path) = &mut config.store.path {
            *path = base.join(&*path);
        }
        config.validate().map_err(|message| ConfigError::Invalid {
            path: path.to_owned(),
            message,
        })?;
        Ok(config)
    }

    fn validate(&self) -> Result<(), String> {
        if self.gateway_id.is_empty() || !crate::publish::valid_device_id(&self.gateway_id) {
            return Err(format!(
                "`gateway_id` {:?} cannot be used in MQTT topics; use letters, digits, '-' or '_'",
                self.gateway_id
            ));
        }
        let w = &self.window;
        if !(w.length_s > 0.0 && w.stride_s > 0.0) {
            return Err("[window] `length_s` and `stride_s` must be positive seconds".into());
        }
        if self.tracker.max_speed_mps.is_nan() || self.tracker.max_speed_mps <= 0.0 {
            return Err("[tracker] `max_speed_mps` must be positive".into());
        }
        if !(0.0..=1.0).contains(&self.tracker.stay_probability) {
            return Err("[tracker] `stay_probability` must be between 0 and 1".into());
        }
        if !(0.0..=1.0).contains(&self.localizer.min_confidence) {
            return Err("[localizer] `min_confidence` must be between 0 and 1".into());
        }
        self.localizer
            .pathloss
            .validate()
            .map_err(|e| format!("[localizer.pathloss] {e}"))?;
        self.guidance.validate()?;
        self.ble.validate()?;
        self.mqtt.validate().map_err(|e| e.to_string())?;
        self.store.validate()?;
        Ok(())
    }

    /// The MQTT topic prefix: `[mqtt] prefix`, or `gangway/<gateway_id>`.
    pub fn topic_prefix(&self) -> String {
        self.mqtt
            .prefix
            .clone()
            .unwrap_or_else(|| format!("gangway/{}", self.gateway_id))
    }

    /// The prefix shared by the gateways of one site: `[mqtt] site_prefix`, or
    /// `gangway/sites/<site name>`.
    pub fn site_prefix(&self, site_name: &str) -> String {
        self.mqtt
            .site_prefix
            .clone()
            .unwrap_or_else(|| format!("gangway/sites/{site_name}"))
    }

    /// The MQTT client id: `[mqtt] client_id`, or `gangway-<gateway_id>`.
    pub fn client_id(&self) -> String {
        self.mqtt
            .client_id
            .clone()
            .unwrap_or_else(|| format!("gangway-{}", self.gateway_id))
    }
}
