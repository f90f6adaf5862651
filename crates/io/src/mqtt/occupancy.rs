//! Occupancy: how many devices are at each named place of the site, followed
//! from the locations the gateway publishes (a device counts at the
//! place of its latest location, and at none once its location is unknown,
//! between places, or it is forgotten). Sent retained on `<prefix>/occupancy`
//! whenever a count changes (docs/schemas/occupancy.schema.json); Home
//! Assistant reads one sensor per place from it (`discovery`).

use std::collections::HashMap;

use serde_json::json;

use crate::publish::Location;
use crate::topics::{Message, Topics};

pub(crate) const OCCUPANCY_SCHEMA: &str = "gangway.occupancy/1";

/// Most devices counted at named places at once. Device ids come from the air
/// and from phones: past this bound a device arriving at a place is left
/// uncounted (and logged) rather than growing the table without limit.
pub(crate) const MAX_DEVICES: usize = 65_536;

/// Devices per named place.
pub(crate) struct Occupancy {
    /// The site's named places; indexes into `counts`.
    places: Vec<String>,
    counts: Vec<u32>,
    /// Devices at a named place, and which.
    at: HashMap<String, usize>,
    /// Counts changed since the last [`Occupancy::update`].
    changed: bool,
    /// Devices left uncounted since the last warning about the bound.
    uncounted: u64,
}

impl Occupancy {
    /// Everyone away from every place; the first [`Occupancy::update`] sends
    /// the zeros, so each place's sensor has a value from the start.
    pub(crate) fn new<'a>(places: impl IntoIterator<Item = &'a str>) -> Self {
        let places: Vec<String> = places.into_iter().map(str::to_owned).collect();
        Occupancy {
            counts: vec![0; places.len()],
            places,
            at: HashMap::new(),
            changed: true,
            uncounted: 0,
        }
    }

    /// Follows one published location: it moves its device to its place, or
    /// out of every place.
    pub(crate) fn observe(&mut self, location: &Location) {
        let device = location.device.as_str();
        let place = location
            .place
            .as_deref()
            .filter(|_| location.cell.is_some())
            .and_then(|name| self.places.iter().position(|p| p == name));
        let was = self.at.get(device).copied();
        if was == place {
            return;
        }
        if place.is_some() && was.is_none() && self.at.len() >= MAX_DEVICES {
            self.uncounted += 1;
            if self.uncounted.is_power_of_two() {
                tracing::warn!(
                    device,
                    uncounted = self.uncounted,
                    "occupancy counts {MAX_DEVICES} devices at most; this one is left out"
                );
            }
            return;
        }
        if let Some(i) = was {
            self.counts[i] -= 1;
        }
        match place {
            Some(i) => {
                self.counts[i] += 1;
                self.at.insert(device.to_owned(), i);
            }
            None => {
                self.at.remove(device);
            }
        }
        self.changed = true;
    }

    /// A device that is gone leaves its place.
    pub(crate) fn forget(&mut self, device: &str) {
        if let Some(i) = self.at.remove(device) {
            self.counts[i] -= 1;
            self.changed = true;
        }
    }

    /// The retained counts at time `t` (seconds since the epoch), when they
    /// changed since the last call.
    pub(crate) fn update(&mut self, topics: &Topics, t: f64) -> Option<Message> {
        if !std::mem::take(&mut self.changed) {
            return None;
        }
        let places: serde_json::Map<String, serde_json::Value> = self
            .places
            .iter()
            .zip(&self.counts)
            .map(|(place, &n)| (place.clone(), n.into()))
            .collect();
        Some(Message::json(
            topics.occupancy(),
            &json!({"schema": OCCUPANCY_SCHEMA, "t": t, "places": places}),
            true,
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::site::Cell;

    fn location(device: &str, place: Option<&str>, cell: serde_json::Value) -> Location {
        let cell = serde_json::from_value::<Option<Cell>>(cell).unwrap();
        crate::test_support::location(device, 1.0, cell, place)
    }

    fn counts(o: &mut Occupancy) -> Option<serde_json::Value> {
        o.update(&Topics::new("gangway/gw"), 1.0)
            .map(|m| m.value()["places"].clone())
    }

    #[test]
    fn devices_move_between_places_and_leave_them() {
        let mut o = Occupancy::new(["desk", "lab"]);
        assert_eq!(counts(&mut o), Some(json!({"desk": 0, "lab": 0})));
        assert_eq!(counts(&mut o), None, "nothing changed");
        o.observe(&location("a", Some("desk"), json!([1, 1])));
        o.observe(&location("b", Some("desk"), json!([1, 2])));
        assert_eq!(counts(&mut o), Some(json!({"desk": 2, "lab": 0})));
        o.observe(&location("a", Some("desk"), json!([1, 1])));
        assert_eq!(counts(&mut o), None, "a stayed at the desk");
        o.observe(&location("a", Some("lab"), json!([5, 5])));
        o.observe(&location("b", None, json!([3, 3])));
        assert_eq!(counts(&mut o), Some(json!({"desk": 0, "lab": 1})));
        // Unknown (no cell), a place the site does not have, forgotten.
        o.observe(&location("c", Some("lab"), json!([5, 5])));
        o.observe(&location("c", Some("lab"), json!(null)));
        o.observe(&location("d", Some("moon"), json!([0, 0])));
        assert_eq!(counts(&mut o), Some(json!({"desk": 0, "lab": 1})));
        o.forget("a");
        o.forget("nobody");
        assert_eq!(counts(&mut o), Some(json!({"desk": 0, "lab": 0})));
    }

    #[test]
    fn the_table_is_bounded() {
        let mut o = Occupancy::new(["desk"]);
        for i in 0..MAX_DEVICES + 10 {
            o.observe(&location(&format!("d{i}"), Some("desk"), json!([0, 0])));
        }
        assert_eq!(counts(&mut o), Some(json!({"desk": MAX_DEVICES})));
        o.forget("d0");
        o.observe(&location("late", Some("desk"), json!([0, 0])));
        assert_eq!(counts(&mut o), Some(json!({"desk": MAX_DEVICES})));
    }
}
