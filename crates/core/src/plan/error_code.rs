//! The stable codes of route error replies: the one place that names them.
//!
//! A code travels in `error.code` of a `path` reply (docs/schemas/path.schema.json
//! lists the same strings) and apps branch on it, so a code's text never
//! changes. Every part of the gateway that refuses a route request (the
//! planner, the pipeline, the inbound MQTT reader, the daemon's admission
//! control) picks a variant here instead of spelling the string, so the
//! compiler catches a typo and a `match` catches a new code.

use std::fmt;

use serde::{Serialize, Serializer};

/// Why a route request got an error reply instead of a route.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum RouteErrorCode {
    /// `to` names no place of the site.
    UnknownPlace,
    /// `to` is a cell outside the map.
    OffMap,
    /// `to` is not walkable.
    BlockedCell,
    /// No walkable route joins the device's cell and `to`.
    Unreachable,
    /// A route exists, but only over stairs or escalators (or stairs within
    /// a floor), and the walker needs a step-free one (wheelchair): they are
    /// never sent a staircase.
    NoStepFreeRoute,
    /// The device has no location yet.
    UnknownDevice,
    /// A `profile` the planner does not know.
    UnknownProfile,
    /// A model failed at run time.
    ModelFailed,
    /// The planner produced a route that failed validation (a bug).
    InvalidRoute,
    /// The request payload is not JSON.
    InvalidJson,
    /// JSON, but not a route request.
    InvalidRequest,
    /// The request payload is over `[mqtt] max_payload_bytes`.
    PayloadTooLarge,
    /// Too many requests waiting, or this one waited too long.
    Overloaded,
    /// Too many requests from this device.
    RateLimited,
}

impl RouteErrorCode {
    /// Every code, in the order the schema lists them.
    #[cfg(test)]
    pub(crate) const ALL: [RouteErrorCode; 14] = [
        RouteErrorCode::UnknownPlace,
        RouteErrorCode::OffMap,
        RouteErrorCode::BlockedCell,
        RouteErrorCode::Unreachable,
        RouteErrorCode::NoStepFreeRoute,
        RouteErrorCode::UnknownDevice,
        RouteErrorCode::UnknownProfile,
        RouteErrorCode::ModelFailed,
        RouteErrorCode::InvalidRoute,
        RouteErrorCode::InvalidJson,
        RouteErrorCode::InvalidRequest,
        RouteErrorCode::PayloadTooLarge,
        RouteErrorCode::Overloaded,
        RouteErrorCode::RateLimited,
    ];

    /// The code as sent in `error.code`.
    pub fn as_str(self) -> &'static str {
        match self {
            RouteErrorCode::UnknownPlace => "unknown_place",
            RouteErrorCode::OffMap => "off_map",
            RouteErrorCode::BlockedCell => "blocked_cell",
            RouteErrorCode::Unreachable => "unreachable",
            RouteErrorCode::NoStepFreeRoute => "no_step_free_route",
            RouteErrorCode::UnknownDevice => "unknown_device",
            RouteErrorCode::UnknownProfile => "unknown_profile",
            RouteErrorCode::ModelFailed => "model_failed",
            RouteErrorCode::InvalidRoute => "invalid_route",
            RouteErrorCode::InvalidJson => "invalid_json",
            RouteErrorCode::InvalidRequest => "invalid_request",
            RouteErrorCode::PayloadTooLarge => "payload_too_large",
            RouteErrorCode::Overloaded => "overloaded",
            RouteErrorCode::RateLimited => "rate_limited",
        }
    }
}

impl fmt::Display for RouteErrorCode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// Serialized as [`RouteErrorCode::as_str`], so payloads carry exactly the
/// strings the schema lists.
impl Serialize for RouteErrorCode {
    fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.serialize_str(self.as_str())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_codes_are_exactly_the_schemas_in_its_order() {
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../docs/schemas/path.schema.json"
        );
        let schema: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
        let listed = schema["oneOf"]
            .as_array()
            .unwrap()
            .iter()
            .find(|branch| branch["title"] == "error")
            .map(|branch| branch["properties"]["error"]["properties"]["code"]["enum"].clone())
            .unwrap();
        let ours: Vec<serde_json::Value> = RouteErrorCode::ALL
            .iter()
            .map(|code| serde_json::to_value(code).unwrap())
            .collect();
        assert_eq!(listed, serde_json::Value::Array(ours));
    }

    #[test]
    fn display_and_serde_agree_and_codes_are_distinct() {
        let mut seen = std::collections::HashSet::new();
        for code in RouteErrorCode::ALL {
            assert_eq!(serde_json::to_value(code).unwrap(), code.to_string());
            assert!(seen.insert(code.as_str()), "{code} twice");
        }
    }
}
