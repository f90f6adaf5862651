//! Occupancy: how many devices are at each named place of the site, followed
//! from the locations the gateway publishes (a device counts at the
//! place of its latest location, and at none once its location is unknown,
//! between places, or it is forgotten). Sent retained on `<prefix>/occupancy`
//! whenever a count changes (docs/schemas/occupancy.schema.json); Home
//! Assistant reads one sensor per place from it (`discovery`).
//!
//! On a building of several floors a place is counted under its floor's
//! name too (`B1/Store`: two floors may name a place alike), and every
//! floor has a count of the devices on it, known place or not.

use std::collections::HashMap;

use serde_json::json;

use crate::publish::Location;
use crate::site::Building;
use crate::topics::{Message, Topics};

pub(crate) const OCCUPANCY_SCHEMA: &str = "gangway.occupancy/1";

/// Most devices counted at named places at once. Device ids come from the air
/// and from phones: past this bound a device arriving at a place is left
/// uncounted (and logged) rather than growing the table without limit.
pub(crate) const MAX_DEVICES: usize = 65_536;

/// The name a place is counted and shown under: on a building of several
/// floors, with its floor's (`B1/Store`).
pub(crate) fn place_key(floor: Option<&str>, place: &str) -> String {
    match floor {
        Some(floor) => format!("{floor}/{place}"),
        None => place.to_owned(),
    }
}

/// The places counted in `building`, by [`place_key`], and its floors when
/// it has several (none for a one-floor site).
pub(crate) fn places_and_floors(building: &Building) -> (Vec<String>, Vec<String>) {
    let multi = building.is_multi_floor();
    let places = building
        .floors()
        .iter()
        .flat_map(|floor| {
            let name = multi.then_some(floor.name.as_str());
            floor
                .site
                .places()
                .keys()
                .map(move |place| place_key(name, place))
        })
        .collect();
    let floors = building
        .floors()
        .iter()
        .filter(|_| multi)
        .map(|f| f.name.clone())
        .collect();
    (places, floors)
}

/// A table of devices, each counted under one of several names.
struct Counts {
    names: Vec<String>,
    counts: Vec<u32>,
    /// Devices counted, and under which name.
    at: HashMap<String, usize>,
}

impl Counts {
    fn new(names: Vec<String>) -> Counts {
        Counts {
            counts: vec![0; names.len()],
            names,
            at: HashMap::new(),
        }
    }

    /// Moves `device` to be counted under `name` (none: nowhere); whether
    /// a count changed. `None` when the table is full and the device new.
    fn set(&mut self, device: &str, name: Option<&str>) -> Option<bool> {
        let index = name.and_then(|n| self.names.iter().position(|p| p == n));
        let was = self.at.get(device).copied();
        if was == index {
            return Some(false);
        }
        if index.is_some() && was.is_none() && self.at.len() >= MAX_DEVICES {
            return None;
        }
        if let Some(i) = was {
            self.counts[i] -= 1;
        }
        match index {
            Some(i) => {
                self.counts[i] += 1;
                self.at.insert(device.to_owned(), i);
            }
            None => {
                self.at.remove(device);
            }
        }
        Some(true)
    }

    fn json(&self) -> serde_json::Map<String, serde_json::Value> {
        self.names
            .iter()
            .zip(&self.counts)
            .map(|(name, &n)| (name.clone(), n.into()))
            .collect()
    }
}

/// Devices per named place, and per floor of a building.
pub(crate) struct Occupancy {
    /// By [`place_key`].
    places: Counts,
    /// Empty on a one-floor site.
    floors: Counts,
    /// Counts changed since the last [`Occupancy::update`].
    changed: bool,
    /// Devices left uncounted since the last warning about the bound.
    uncounted: u64,
}

impl Occupancy {
    /// Everyone away from every place (named by [`place_key`]) and floor
    /// (none on a one-floor site); the first [`Occupancy::update`] sends the
    /// zeros, so each sensor has a value from the start.
    pub(crate) fn new(places: Vec<String>, floors: Vec<String>) -> Self {
        Occupancy {
            places: Counts::new(places),
            floors: Counts::new(floors),
            changed: true,
            uncounted: 0,
        }
    }

    /// Follows one published location: it moves its device to its place
    /// and floor, or out of every one.
    pub(crate) fn observe(&mut self, location: &Location) {
        let device = location.device.as_str();
        let floor = location
            .floor
            .as_ref()
            .map(|f| f.name.as_str())
            .filter(|_| !self.floors.names.is_empty());
        let place = location
            .place
            .as_deref()
            .filter(|_| location.cell.is_some())
            .map(|place| place_key(floor, place));
        for changed in [
            self.places.set(device, place.as_deref()),
            self.floors.set(device, floor),
        ] {
            match changed {
                Some(changed) => self.changed |= changed,
                None => {
                    self.uncounted += 1;
                    if self.uncounted.is_power_of_two() {
                        tracing::warn!(
                            device,
                            uncounted = self.uncounted,
                            "occupancy counts {MAX_DEVICES} devices at most; this one is left out"
                        );
                    }
                }
            }
        }
    }

    /// A device that is gone leaves its place.
    pub(crate) fn forget(&mut self, device: &str) {
        for counts in [&mut self.places, &mut self.floors] {
            self.changed |= counts.set(device, None) == Some(true);
        }
    }

    /// The retained counts at time `t` (seconds since the epoch), when they
    /// changed since the last call.
    pub(crate) fn update(&mut self, topics: &Topics, t: f64) -> Option<Message> {
        if !std::mem::take(&mut self.changed) {
            return None;
        }
        let mut counts = json!({"schema": OCCUPANCY_SCHEMA, "t": t, "places": self.places.json()});
        if !self.floors.names.is_empty() {
            counts["floors"] = self.floors.json().into();
        }
        Some(Message::json(topics.occupancy(), &counts, true))
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
        let mut o = Occupancy::new(vec!["desk".into(), "lab".into()], Vec::new());
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
        let mut o = Occupancy::new(vec!["desk".into()], Vec::new());
        for i in 0..MAX_DEVICES + 10 {
            o.observe(&location(&format!("d{i}"), Some("desk"), json!([0, 0])));
        }
        assert_eq!(counts(&mut o), Some(json!({"desk": MAX_DEVICES})));
        o.forget("d0");
        o.observe(&location("late", Some("desk"), json!([0, 0])));
        assert_eq!(counts(&mut o), Some(json!({"desk": MAX_DEVICES})));
    }

    #[test]
    fn a_building_counts_places_under_their_floor_and_devices_per_floor() {
        let mut o = Occupancy::new(
            vec!["B1/Store".into(), "G/Store".into()],
            vec!["B1".into(), "G".into()],
        );
        let on = |device: &str, floor: Option<&str>, place: Option<&str>| {
            let mut l = location(device, place, json!([1, 1]));
            l.floor = floor.map(|name| crate::publish::FloorName {
                name: name.into(),
                level: 0,
            });
            l
        };
        o.observe(&on("a", Some("B1"), Some("Store")));
        o.observe(&on("b", Some("G"), None));
        let counts = o.update(&Topics::new("gangway/gw"), 1.0).unwrap().value();
        assert_eq!(counts["places"], json!({"B1/Store": 1, "G/Store": 0}));
        assert_eq!(counts["floors"], json!({"B1": 1, "G": 1}));
        // Up to G's store; then an unknown floor counts nowhere.
        o.observe(&on("a", Some("G"), Some("Store")));
        o.observe(&on("b", None, None));
        let counts = o.update(&Topics::new("gangway/gw"), 2.0).unwrap().value();
        assert_eq!(counts["places"], json!({"B1/Store": 0, "G/Store": 1}));
        assert_eq!(counts["floors"], json!({"B1": 0, "G": 1}));
        o.forget("a");
        let counts = o.update(&Topics::new("gangway/gw"), 3.0).unwrap().value();
        assert_eq!(counts["floors"], json!({"B1": 0, "G": 0}));
    }
}
