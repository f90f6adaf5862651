//! The gateway config file (`config/gangway.toml`): one table per pipeline
//! stage, each owned by its module (`[window]` by `locate::window`, `[planner]` by
//! `plan`, …); this file only composes them and resolves paths.
//!
//! Relative paths in the file resolve against the directory of the config file,
//! so a config and its site can move together.

use std::path::{Path, PathBuf};

use serde::Deserialize;

use crate::guide::GuidanceConfig;
use crate::latency;
use crate::locate::LocalizerConfig;
use crate::locate::tracker::TrackerConfig;
use crate::locate::window::{Orientation, WindowConfig};
use crate::mqtt::cluster::{ClusterConfig, Role};
use crate::mqtt::{self, MqttConfig};
use crate::pipeline::{LimitsConfig, PipelineConfig};
use crate::plan::PlannerConfig;
use crate::source::ble::BleConfig;
use crate::store::StoreConfig;
use crate::web::WebConfig;

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
    /// `[cluster]`: this gateway's part among many on one broker.
    #[serde(default)]
    pub cluster: ClusterConfig,
    /// `[store]`: the crowd-sourced learning store.
    #[serde(default)]
    pub store: StoreConfig,
    /// `[limits]`: what anyone on the air or the broker can make the gateway
    /// hold or do.
    #[serde(default)]
    pub limits: LimitsConfig,
    /// `[web]`: the browser UI (live map, site editor, survey).
    #[serde(default)]
    pub web: WebConfig,
}

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("{}: cannot read the config file: {source}", path.display())]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    /// A TOML or type error, told without the file's text: the line could
    /// hold a secret someone put in the wrong place.
    #[error("{}: {where_}{message}", path.display())]
    Toml {
        path: PathBuf,
        /// `line L, column C: `, when known.
        where_: String,
        message: String,
    },
    #[error("{}: {message}", path.display())]
    Invalid { path: PathBuf, message: String },
}

/// Keys whose values are secrets: never repeated in an error.
fn is_secret_key(key: &str) -> bool {
    let key = key.to_ascii_lowercase();
    [
        "password",
        "passwd",
        "secret",
        "token",
        "credential",
        "private_key",
    ]
    .iter()
    .any(|s| key.contains(s))
        && !key.ends_with("_file")
}

/// The values of secret-looking keys in `text`, as written and unquoted.
fn secret_values(text: &str) -> Vec<String> {
    let mut values = Vec::new();
    for line in text.lines() {
        let Some((key, value)) = line.split_once('=') else {
            continue;
        };
        let key = key.trim().trim_matches(['"', '\'']);
        if !is_secret_key(key) {
            continue;
        }
        let value = value.trim();
        let unquoted = value.trim_matches(['"', '\'']);
        for v in [value, unquoted] {
            if !v.is_empty() {
                values.push(v.to_owned());
            }
        }
    }
    // Longest first, so a quoted value goes before its unquoted part.
    values.sort_by_key(|v| std::cmp::Reverse(v.len()));
    values
}

/// A TOML error as `line, column: message`, without the snippet of the file
/// toml's own message carries, and with any secret value redacted.
fn toml_error(path: &Path, text: &str, e: &toml::de::Error) -> ConfigError {
    let where_ = e.span().map_or_else(String::new, |span| {
        let before = &text[..span.start.min(text.len())];
        let line = before.matches('\n').count() + 1;
        let column = before.rsplit('\n').next().map_or(0, |l| l.chars().count()) + 1;
        format!("line {line}, column {column}: ")
    });
    let mut message = e.message().trim().to_owned();
    for secret in secret_values(text) {
        message = message.replace(&secret, "<redacted>");
    }
    if let Some(key) = message
        .strip_prefix("unknown field `")
        .and_then(|rest| rest.split('`').next())
        .filter(|key| is_secret_key(key))
    {
        message = format!(
            "`{key}` cannot be set in the config (a secret does not belong in a file anyone \
             can read); put it in a file of its own and name that file with `{key}_file`, or \
             pass it as the systemd credential `mqtt-password`"
        );
    }
    ConfigError::Toml {
        path: path.to_owned(),
        where_,
        message,
    }
}

impl Config {
    /// Reads a config file and resolves its relative paths.
    pub fn load(path: &Path) -> Result<Config, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.to_owned(),
            source,
        })?;
        let mut config: Config = toml::from_str(&text).map_err(|e| toml_error(path, &text, &e))?;
        let base = path.parent().unwrap_or(Path::new("."));
        config.site = base.join(&config.site);
        config.localizer.resolve_paths(base);
        config.mqtt.resolve_paths(base);
        config.planner.resolve_paths(base);
        config.planner.clock = latency::MONOTONIC;
        if let Some(path) = &mut config.store.path {
            *path = base.join(&*path);
        }
        config.web.resolve_paths(base);
        config.validate().map_err(|message| ConfigError::Invalid {
            path: path.to_owned(),
            message,
        })?;
        Ok(config)
    }

    fn validate(&self) -> Result<(), String> {
        if self.gateway_id.is_empty() || !crate::sighting::valid_device_id(&self.gateway_id) {
            return Err(format!(
                "`gateway_id` {:?} cannot be used in MQTT topics; use letters, digits, '-' or '_'",
                self.gateway_id
            ));
        }
        // Each section checks itself; what spans two sections is checked here.
        self.window.validate()?;
        self.tracker.validate()?;
        self.localizer.validate()?;
        if self.localizer.recalibration.enabled && !self.store.enabled {
            return Err(
                "[localizer.recalibration] `enabled` keeps what is heard in the learning \
                        store: set [store] enabled = true too"
                    .into(),
            );
        }
        self.guidance.validate()?;
        self.ble.validate()?;
        self.mqtt.validate().map_err(|e| e.to_string())?;
        if (self.mqtt.espresense.is_some() || self.mqtt.theengs.is_some())
            && self.window.orientation != Orientation::Advertiser
        {
            return Err(
                "[mqtt.espresense] and [mqtt.theengs] read fixed receivers that hear tags: \
                 set [window] orientation = \"advertiser\" (and place each receiver as a \
                 [[gateway]] of the site)"
                    .into(),
            );
        }
        self.cluster.validate()?;
        if self.cluster.role != Role::Single {
            if self.window.orientation != Orientation::Advertiser {
                return Err(
                    "[cluster] edges and locators share the work of fixed receivers hearing \
                     tags: set [window] orientation = \"advertiser\" (phones that scan are \
                     served by a single gateway)"
                        .into(),
                );
            }
            if self.cluster.role == Role::Locator
                && (self.mqtt.espresense.is_some() || self.mqtt.theengs.is_some())
            {
                return Err(
                    "[mqtt.espresense] and [mqtt.theengs] go on an edge, which passes their \
                     sightings to the locators by shard; a locator reads only its shards"
                        .into(),
                );
            }
        }
        self.store.validate()?;
        self.limits.validate()?;
        Ok(())
    }

    /// The sections a pipeline is built from.
    pub fn pipeline(&self) -> PipelineConfig {
        PipelineConfig {
            window: self.window.clone(),
            localizer: self.localizer.clone(),
            tracker: self.tracker.clone(),
            planner: self.planner.clone(),
            guidance: self.guidance.clone(),
            limits: self.limits.clone(),
        }
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
    fn client_id(&self) -> String {
        self.mqtt
            .client_id
            .clone()
            .unwrap_or_else(|| format!("gangway-{}", self.gateway_id))
    }

    /// Whether this gateway sends its sightings to the site's others: when
    /// the gateways are the anchors (`[window] orientation = "advertiser"`),
    /// unless it is a locator (it has no radio of its own).
    pub fn shares_sightings(&self) -> bool {
        self.window.orientation == Orientation::Advertiser && self.cluster.role != Role::Locator
    }

    /// Who this gateway is on the broker for `site`, for the MQTT sink.
    pub fn broker_identity(&self, site_name: &str) -> mqtt::sink::Identity {
        mqtt::sink::Identity {
            gateway_id: self.gateway_id.clone(),
            client_id: self.client_id(),
            topic_prefix: self.topic_prefix(),
            site_prefix: self.site_prefix(site_name),
            shares_sightings: self.shares_sightings(),
            role: self.cluster.role,
            shards: self.cluster.shards,
            max_devices: self.limits.max_devices,
            device_idle_s: self.limits.device_idle_s,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_password_in_the_config_is_refused_without_repeating_it() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("gangway.toml");
        for text in [
            "gateway_id = \"gw\"\nsite = \"s.toml\"\n[mqtt]\nusername = \"u\"\npassword = \"hunter2-secret\"\n",
            "gateway_id = \"gw\"\nsite = \"s.toml\"\n[mqtt]\nqos = \"hunter2-secret\"\npassword = \"hunter2-secret\"\n",
            "gateway_id = \"gw\"\nsite = \"s.toml\"\n[mqtt]\npassword = hunter2-secret\n",
        ] {
            std::fs::write(&path, text).unwrap();
            let err = Config::load(&path).unwrap_err().to_string();
            assert!(!err.contains("hunter2"), "{err}");
            assert!(err.contains("gangway.toml: line "), "{err}");
        }
        std::fs::write(
            &path,
            "gateway_id = \"gw\"\nsite = \"s.toml\"\n[mqtt]\npassword = \"hunter2\"\n",
        )
        .unwrap();
        let err = Config::load(&path).unwrap_err().to_string();
        assert!(err.contains("`password_file`"), "{err}");
    }
}
