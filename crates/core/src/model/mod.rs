//! Trained models as ONNX files: what they promise about themselves
//! ([`Metadata`], stored as ONNX `metadata_props`), how they are written
//! (`model::export` in gangway-offline) and how they are run with tract
//! ([`runtime`]).
//!
//! Every model names the site it was trained for: its name, grid size and the
//! hash of its access map. Loading compares them with the configured site and
//! refuses a model for another map, naming the field that differs.
//!
//! Input conventions shared by training and inference:
//! - path frames: `W·H` values, row-major (`y · W + x`); generators output and
//!   discriminators take ±1 frames, path classifiers take 0/1 frames ([`Kind`]);
//! - conditions: [`condition::encode`];
//! - RSSI: dBm, one value per site anchor (see [`CellClassifierInput`]).

pub mod checks;
pub mod condition;
pub mod desire;
pub mod export;
pub mod line_gan;
pub mod runtime;

use std::collections::BTreeMap;

use crate::site::{Cell, Site};

/// Version of the metadata and input conventions below; bumped when a model
/// written by an older gangway would be misread.
pub(crate) const FORMAT_VERSION: u32 = 1;

/// What a model does. Each kind fixes its inputs and output:
///
/// | kind | inputs | output |
/// | --- | --- | --- |
/// | `generator` | `noise` [N, noise_dim] standard normal | `frame` [N, W·H] in (−1, 1); a cell is on the path when > 0 |
/// | `conditional_generator` | `noise`, `condition` [N, 2·W·H] | `frame` as above |
/// | `discriminator` | `frame` [N, W·H] ±1 (+ `condition` when conditional) | `real` [N, 1] probability |
/// | `path_classifier` | `frame` [N, W·H] 0/1 | `probs` [N, classes] softmax |
/// | `cell_classifier` | `rssi` [N, anchors] dBm | `log_probs` [N, open cells] log-softmax |
/// | `desire_lines` | `endpoints` [N, 4] cell units (`ax, ay, bx, by`) | `points` [N, 2·P]: the line's P x then P y ([`desire`]) |
/// | `line_generator` | `noise`, `endpoints` [N, 4] in [−1, 1] ([`line_gan::endpoints`]) | `shape` [N, 2·(P − 2)]: the inner points' offsets from the straight line ([`line_gan`]) |
/// | `line_discriminator` | `shape`, `endpoints` as above | `real` [N, 1] probability |
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    Generator,
    ConditionalGenerator,
    Discriminator,
    ConditionalDiscriminator,
    PathClassifier,
    CellClassifier,
    DesireLines,
    LineGenerator,
    LineDiscriminator,
}

impl Kind {
    pub fn name(self) -> &'static str {
        match self {
            Kind::Generator => "generator",
            Kind::ConditionalGenerator => "conditional_generator",
            Kind::Discriminator => "discriminator",
            Kind::ConditionalDiscriminator => "conditional_discriminator",
            Kind::PathClassifier => "path_classifier",
            Kind::CellClassifier => "cell_classifier",
            Kind::DesireLines => "desire_lines",
            Kind::LineGenerator => "line_generator",
            Kind::LineDiscriminator => "line_discriminator",
        }
    }

    fn parse(s: &str) -> Option<Kind> {
        [
            Kind::Generator,
            Kind::ConditionalGenerator,
            Kind::Discriminator,
            Kind::ConditionalDiscriminator,
            Kind::PathClassifier,
            Kind::CellClassifier,
            Kind::DesireLines,
            Kind::LineGenerator,
            Kind::LineDiscriminator,
        ]
        .into_iter()
        .find(|k| k.name() == s)
    }
}

/// How the cell classifier's RSSI input is normalized inside its graph: values
/// are clipped to `[RSSI_FLOOR_DBM, RSSI_CEIL_DBM]` and mapped linearly to
/// [0, 1]. Anything at or below the floor (the window's `missing_dbm` of −105,
/// or the survey's −200) reads as "not heard". The clip is the first node of
/// the graph and the scaling is folded into the first layer, so callers pass
/// raw dBm.
pub struct CellClassifierInput;

impl CellClassifierInput {
    pub const RSSI_FLOOR_DBM: f32 = -105.0;
    pub const RSSI_CEIL_DBM: f32 = -45.0;

    pub fn normalize(dbm: f32) -> f32 {
        (dbm.clamp(Self::RSSI_FLOOR_DBM, Self::RSSI_CEIL_DBM) - Self::RSSI_FLOOR_DBM)
            / (Self::RSSI_CEIL_DBM - Self::RSSI_FLOOR_DBM)
    }
}

/// A path class: walks from `source` to `destination`.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, serde::Serialize, serde::Deserialize,
)]
pub struct PathClass {
    pub source: Cell,
    pub destination: Cell,
}

/// What a model file says about itself (ONNX `metadata_props`, keys
/// `gangway.*`).
#[derive(Clone, Debug, PartialEq)]
pub struct Metadata {
    pub kind: Kind,
    pub version: u32,
    pub site: String,
    pub width: u16,
    pub height: u16,
    pub map_hash: String,
    /// Path classes the model was trained on, in output order for classifiers.
    pub classes: Vec<PathClass>,
    /// Anchor ids in input order (cell classifiers).
    pub anchors: Vec<String>,
    /// Noise inputs (generators).
    pub noise_dim: usize,
    pub iterations: usize,
    pub seed: u64,
    /// Weight of the access penalty the GAN was trained with (0: the paper's
    /// plain loss, and what a file without the key was trained with).
    pub access_weight: f32,
    /// Measured quality, e.g. `heldout_error`; free-form numbers for the model card.
    pub metrics: BTreeMap<String, f64>,
}

/// Why a model file was refused.
#[derive(Debug, thiserror::Error)]
pub enum ModelError {
    /// The file is not there: a model not trained yet, which the learned
    /// planner passes over without alarm.
    #[error("{path}: no model there yet (`gangway train` writes one)")]
    Missing { path: String },
    #[error("{path}: cannot read the model: {reason}")]
    Read { path: String, reason: String },
    #[error("{path}: not a valid ONNX model ({reason}); is the file truncated or not ONNX?")]
    Corrupt { path: String, reason: String },
    #[error("{path}: metadata `{key}`: {reason}")]
    Metadata {
        path: String,
        key: &'static str,
        reason: String,
    },
    #[error(
        "{path}: the model was trained for {field} {trained}, but the configured site has \
         {configured}; retrain it for this site with `gangway train`"
    )]
    SiteMismatch {
        path: String,
        field: &'static str,
        trained: String,
        configured: String,
    },
    #[error("{path}: tract cannot run the model: {reason}")]
    Runtime { path: String, reason: String },
    #[error("model input: {0}")]
    Input(String),
}

const KEY_KIND: &str = "gangway.kind";
const KEY_VERSION: &str = "gangway.version";
const KEY_SITE: &str = "gangway.site";
const KEY_GRID: &str = "gangway.grid";
const KEY_MAP_HASH: &str = "gangway.map_hash";
const KEY_CLASSES: &str = "gangway.classes";
const KEY_ANCHORS: &str = "gangway.anchors";
const KEY_NOISE_DIM: &str = "gangway.noise_dim";
const KEY_ITERATIONS: &str = "gangway.iterations";
const KEY_SEED: &str = "gangway.seed";
const KEY_ACCESS_WEIGHT: &str = "gangway.access_weight";
const KEY_METRICS: &str = "gangway.metrics";

impl Metadata {
    /// Metadata for a model of `kind` trained on `site`.
    pub fn for_site(kind: Kind, site: &Site) -> Metadata {
        Metadata {
            kind,
            version: FORMAT_VERSION,
            site: site.name.clone(),
            width: site.width(),
            height: site.height(),
            map_hash: site.map_hash().to_owned(),
            classes: Vec::new(),
            anchors: Vec::new(),
            noise_dim: 0,
            iterations: 0,
            seed: 0,
            access_weight: 0.0,
            metrics: BTreeMap::new(),
        }
    }

    /// The key/value pairs written to `metadata_props`, keys sorted.
    pub(crate) fn to_props(&self) -> Vec<(String, String)> {
        let mut props = vec![
            (KEY_KIND, self.kind.name().to_owned()),
            (KEY_VERSION, self.version.to_string()),
            (KEY_SITE, self.site.clone()),
            (KEY_GRID, format!("{}x{}", self.width, self.height)),
            (KEY_MAP_HASH, self.map_hash.clone()),
            (KEY_CLASSES, json(&self.classes)),
            (KEY_ANCHORS, json(&self.anchors)),
            (KEY_NOISE_DIM, self.noise_dim.to_string()),
            (KEY_ITERATIONS, self.iterations.to_string()),
            (KEY_SEED, self.seed.to_string()),
            (KEY_ACCESS_WEIGHT, self.access_weight.to_string()),
            (KEY_METRICS, json(&self.metrics)),
        ];
        props.sort();
        props.into_iter().map(|(k, v)| (k.to_owned(), v)).collect()
    }

    /// Reads the metadata back; `path` is only used in errors.
    pub(crate) fn from_props(
        props: &BTreeMap<String, String>,
        path: &str,
    ) -> Result<Metadata, ModelError> {
        let bad = |key: &'static str, reason: String| ModelError::Metadata {
            path: path.to_owned(),
            key,
            reason,
        };
        let get = |key: &'static str| {
            props.get(key).map(String::as_str).ok_or_else(|| {
                bad(
                    key,
                    "missing; only models written by `gangway train` carry it".into(),
                )
            })
        };
        fn parse<T: std::str::FromStr>(
            v: &str,
            key: &'static str,
            bad: &dyn Fn(&'static str, String) -> ModelError,
        ) -> Result<T, ModelError> {
            v.parse()
                .map_err(|_| bad(key, format!("{v:?} is not a valid value")))
        }
        fn json<T: serde::de::DeserializeOwned>(
            v: &str,
            key: &'static str,
            bad: &dyn Fn(&'static str, String) -> ModelError,
        ) -> Result<T, ModelError> {
            serde_json::from_str(v).map_err(|e| bad(key, format!("not valid JSON: {e}")))
        }
        let kind = Kind::parse(get(KEY_KIND)?)
            .ok_or_else(|| bad(KEY_KIND, format!("unknown kind {:?}", props[KEY_KIND])))?;
        let version: u32 = parse(get(KEY_VERSION)?, KEY_VERSION, &bad)?;
        if version != FORMAT_VERSION {
            return Err(bad(
                KEY_VERSION,
                format!(
                    "the model is format version {version}; this gangway reads version \
                     {FORMAT_VERSION}; retrain it with this gangway"
                ),
            ));
        }
        let grid = get(KEY_GRID)?;
        let (w, h) = grid
            .split_once('x')
            .ok_or_else(|| bad(KEY_GRID, format!("{grid:?} is not WxH")))?;
        Ok(Metadata {
            kind,
            version,
            site: get(KEY_SITE)?.to_owned(),
            width: parse(w, KEY_GRID, &bad)?,
            height: parse(h, KEY_GRID, &bad)?,
            map_hash: get(KEY_MAP_HASH)?.to_owned(),
            classes: json(get(KEY_CLASSES)?, KEY_CLASSES, &bad)?,
            anchors: json(get(KEY_ANCHORS)?, KEY_ANCHORS, &bad)?,
            noise_dim: parse(get(KEY_NOISE_DIM)?, KEY_NOISE_DIM, &bad)?,
            iterations: parse(get(KEY_ITERATIONS)?, KEY_ITERATIONS, &bad)?,
            seed: parse(get(KEY_SEED)?, KEY_SEED, &bad)?,
            // Optional: models written before the access penalty existed lack it.
            access_weight: props
                .get(KEY_ACCESS_WEIGHT)
                .map(|v| parse(v, KEY_ACCESS_WEIGHT, &bad))
                .transpose()?
                .unwrap_or(0.0),
            metrics: json(get(KEY_METRICS)?, KEY_METRICS, &bad)?,
        })
    }

    /// Refuses a model trained for another site, naming the first field that
    /// differs. The map hash is what matters; name and grid make the message
    /// clear.
    pub(crate) fn check_site(&self, site: &Site, path: &str) -> Result<(), ModelError> {
        let mismatch = |field: &'static str, trained: String, configured: String| {
            Err(ModelError::SiteMismatch {
                path: path.to_owned(),
                field,
                trained,
                configured,
            })
        };
        if (self.width, self.height) != (site.width(), site.height()) {
            return mismatch(
                "grid (gangway.grid)",
                format!("{}x{}", self.width, self.height),
                format!("{}x{}", site.width(), site.height()),
            );
        }
        if self.map_hash != site.map_hash() {
            return mismatch(
                "access map hash (gangway.map_hash)",
                self.map_hash.clone(),
                site.map_hash().to_owned(),
            );
        }
        if self.site != site.name {
            return mismatch(
                "site name (gangway.site)",
                self.site.clone(),
                site.name.clone(),
            );
        }
        if self.kind == Kind::CellClassifier {
            let anchors: Vec<String> = site.beacons.iter().map(|b| b.id.clone()).collect();
            if self.anchors != anchors {
                return mismatch(
                    "anchors (gangway.anchors)",
                    self.anchors.join(","),
                    anchors.join(","),
                );
            }
        }
        Ok(())
    }
}

fn json(value: &impl serde::Serialize) -> String {
    serde_json::to_string(value).expect("metadata serializes")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn site(map: &str) -> Site {
        Site::of_map(map)
    }

    #[test]
    fn metadata_round_trips_and_checks_the_site() {
        let s = site("###\n#.#");
        let mut meta = Metadata::for_site(Kind::PathClassifier, &s);
        meta.classes = vec![PathClass {
            source: Cell::new(0, 0),
            destination: Cell::new(2, 1),
        }];
        meta.iterations = 10;
        meta.seed = 3;
        meta.access_weight = 0.25;
        meta.metrics.insert("heldout_error".into(), 0.01);
        let props: BTreeMap<String, String> = meta.to_props().into_iter().collect();
        assert_eq!(
            props["gangway.classes"],
            "[{\"source\":[0,0],\"destination\":[2,1]}]"
        );
        let back = Metadata::from_props(&props, "m.onnx").unwrap();
        assert_eq!(back, meta);
        back.check_site(&s, "m.onnx").unwrap();
        let mut older = props.clone();
        older.remove("gangway.access_weight");
        let back = Metadata::from_props(&older, "m.onnx").unwrap();
        assert_eq!(
            back.access_weight, 0.0,
            "a model without the key had no penalty"
        );
        let mut bad = props.clone();
        bad.insert("gangway.access_weight".into(), "heavy".into());
        let err = Metadata::from_props(&bad, "m.onnx")
            .unwrap_err()
            .to_string();
        assert!(err.contains("metadata `gangway.access_weight`"), "{err}");

        let other_map = site("###\n###");
        let err = back
            .check_site(&other_map, "m.onnx")
            .unwrap_err()
            .to_string();
        assert!(err.contains("access map hash (gangway.map_hash)"), "{err}");
        let other_grid = site("####\n#..#");
        let err = back
            .check_site(&other_grid, "m.onnx")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("grid (gangway.grid) 3x2, but the configured site has 4x2"),
            "{err}"
        );

        let mut missing = props.clone();
        missing.remove("gangway.map_hash");
        let err = Metadata::from_props(&missing, "m.onnx")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("metadata `gangway.map_hash`: missing"),
            "{err}"
        );
        let mut newer = props;
        newer.insert("gangway.version".into(), "99".into());
        let err = Metadata::from_props(&newer, "m.onnx")
            .unwrap_err()
            .to_string();
        assert!(err.contains("format version 99"), "{err}");
    }
}
