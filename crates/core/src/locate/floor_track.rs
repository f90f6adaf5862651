//! Which floor each device of a building is on, fix after fix.
//!
//! What is heard says which floor is likely ([`super::floors`]: the floor
//! evidence of each window, filtered over the device's windows); the
//! building says which changes are possible. A device changes floor only
//! where a connector joins the two floors, and no sooner after it came onto
//! its floor than the quickest connector can carry it there (the moving
//! time; a lift's wait is not required, since nobody has to wait). Until
//! then it stays where it is, and the probability of that floor, which the
//! evidence now doubts, is what its fixes are published with. The tracker of
//! the new floor starts the device at that floor's stops of the connectors
//! it may have come by, never at a cell a staircase does not reach.
//!
//! A device's first floor is a guess, not somewhere it walked from: until the
//! evidence makes one floor [`SETTLED`] likely, the device follows it from
//! floor to floor (each time starting afresh there), and only from then on
//! does the connector rule hold. Without that, the first window's guess on
//! weak evidence would hold a device on the wrong floor for as long as it
//! is heard (in a building whose plans name no connectors, for ever).
//!
//! A device unheard for longer than the tracker's reset time may have gone
//! anywhere: its floor is taken afresh from what it hears.
//!
//! The table is per device and devices come from the air, so it is bounded
//! like the trackers ([`Bounds`]).

use std::sync::Arc;

use foldhash::HashMap;

use super::bounds::Bounds;
use super::floors::{FloorEvidence, FloorFilter};
use crate::site::{Building, Cell};

/// The probability of its floor from which a device is taken to be on it:
/// from then on it leaves the floor only through a connector. A fixed
/// odds of 99 to 1, not fitted to any building.
pub const SETTLED: f64 = 0.99;

/// The probability per window that a device changes floor, for the floor
/// filter: people change floor a few times in an hour of 2 s windows, and
/// the connectors' times keep one odd window from moving a device anyway.
pub const SWITCH: f64 = 0.01;

/// The probability of its floor from which a device's floor is published;
/// below it, `floor` is unknown (no floor is likelier than all the others
/// together).
pub const KNOWN: f64 = 0.5;

/// How a device's floor came about at a fix.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FloorChange {
    /// On the floor it was on.
    Stays,
    /// First heard (or heard again after a long gap), or its first guess
    /// corrected before it settled: its floor is new.
    Starts,
    /// Came from this floor through a connector.
    From(usize),
}

/// A device's floor at one fix.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FloorStep {
    /// Index into [`Building::floors`].
    pub floor: usize,
    /// The filter's probability that the device is on `floor`.
    pub probability: f64,
    pub change: FloorChange,
}

struct DeviceFloor {
    filter: FloorFilter,
    floor: usize,
    /// Whether `floor` has been [`SETTLED`] likely since it started.
    settled: bool,
    /// When it came onto `floor`.
    since: f64,
    last_t: f64,
}

/// The floors of every device of one building.
pub struct FloorTracks {
    evidence: FloorEvidence,
    switch: f64,
    /// `ride_s[a][b]`: the least moving time from floor `a` to floor `b`
    /// over the connectors, infinite where none leads there.
    ride_s: Vec<Vec<f64>>,
    /// `entries[a][b]`: the cells of floor `b` where a connector from floor
    /// `a` arrives (every connector stop on `b` when none joins them
    /// directly but some chain does).
    entries: Vec<Vec<Vec<Cell>>>,
    reset_after_s: f64,
    devices: HashMap<Arc<str>, DeviceFloor>,
    bounds: Bounds,
    scratch: Vec<f64>,
}

impl FloorTracks {
    /// The floor tracks of `building`, judging windows by `evidence` and
    /// changing floor between two windows with probability `switch` at most;
    /// a device unheard for `reset_after_s` starts afresh.
    pub fn new(
        building: &Building,
        evidence: FloorEvidence,
        switch: f64,
        reset_after_s: f64,
    ) -> FloorTracks {
        let n = building.floors().len();
        let mut ride_s = vec![vec![f64::INFINITY; n]; n];
        let mut entries = vec![vec![Vec::new(); n]; n];
        for (a, row) in ride_s.iter_mut().enumerate() {
            row[a] = 0.0;
        }
        for connector in building.connectors() {
            for &from in &connector.stops {
                for &to in &connector.stops {
                    if from.floor == to.floor {
                        continue;
                    }
                    let moving = connector.seconds(building, from, to) - connector.wait_s;
                    let best = &mut ride_s[from.floor][to.floor];
                    *best = best.min(moving);
                    entries[from.floor][to.floor].push(to.cell);
                }
            }
        }
        // Chains of connectors (stairs from B1 to G, then from G to L1).
        for k in 0..n {
            for a in 0..n {
                for b in 0..n {
                    let through = ride_s[a][k] + ride_s[k][b];
                    if through < ride_s[a][b] {
                        ride_s[a][b] = through;
                    }
                }
            }
        }
        for (a, row) in entries.iter_mut().enumerate() {
            for (b, cells) in row.iter_mut().enumerate() {
                if a != b && cells.is_empty() && ride_s[a][b].is_finite() {
                    *cells = building
                        .connectors()
                        .iter()
                        .flat_map(|c| c.stops.iter())
                        .filter(|s| s.floor == b)
                        .map(|s| s.cell)
                        .collect();
                }
                cells.sort_unstable();
                cells.dedup();
            }
        }
        FloorTracks {
            scratch: vec![0.0; evidence.floors()],
            evidence,
            switch,
            ride_s,
            entries,
            reset_after_s,
            devices: HashMap::default(),
            bounds: Bounds::default(),
        }
    }

    /// Keeps at most `max` devices, and none unheard for `idle_s` seconds.
    pub(crate) fn bound(mut self, max: usize, idle_s: f64) -> Self {
        self.bounds = Bounds::new(max, idle_s);
        self
    }

    /// After a reload onto a building of the same floors: takes over the
    /// devices' floors of `old`, judged from now on by this one's evidence
    /// and connectors.
    pub(crate) fn take_over(&mut self, old: &mut FloorTracks) {
        self.devices = std::mem::take(&mut old.devices);
    }

    /// The cells of floor `to` where a device coming from floor `from`
    /// arrives.
    pub fn entries(&self, from: usize, to: usize) -> &[Cell] {
        &self.entries[from][to]
    }

    /// The device's floor now, if it has one.
    pub(crate) fn floor_of(&self, device: &str) -> Option<usize> {
        self.devices.get(device).map(|d| d.floor)
    }

    /// Forgets a device (its track was forgotten).
    pub(crate) fn forget(&mut self, device: &str) {
        self.devices.remove(device);
    }

    /// Takes the window of `device` at `t`, which heard `heard` (building
    /// anchor, RSSI dBm); returns its floor.
    pub fn update(&mut self, device: &Arc<str>, t: f64, heard: &[(usize, f32)]) -> FloorStep {
        self.evidence.window(heard, &mut self.scratch);
        let full = self.devices.len() >= self.bounds.max() && !self.devices.contains_key(device);
        self.bounds
            .make_room(&mut self.devices, t, full, |d| d.last_t, |_| {});
        let floors = self.evidence.floors();
        let switch = self.switch;
        let fresh = || DeviceFloor {
            filter: FloorFilter::new(floors, switch),
            floor: 0,
            settled: false,
            since: t,
            last_t: f64::NEG_INFINITY,
        };
        let device = self.devices.entry(device.clone()).or_insert_with(fresh);
        let starts = t - device.last_t > self.reset_after_s;
        if starts {
            *device = fresh();
        }
        device.last_t = t;
        let (best, _) = device.filter.update(&self.scratch);
        let change = if starts || (!device.settled && best != device.floor) {
            device.floor = best;
            device.since = t;
            FloorChange::Starts
        } else if best != device.floor && t - device.since >= self.ride_s[device.floor][best] {
            let from = device.floor;
            device.floor = best;
            device.since = t;
            FloorChange::From(from)
        } else {
            FloorChange::Stays
        };
        let probability = device.filter.probability(device.floor);
        device.settled |= probability >= SETTLED;
        FloorStep {
            floor: device.floor,
            probability,
            change,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    use crate::site::Site;

    /// Three floors of a 4 × 1 corridor; stairs join floors 0 and 1 at
    /// cell (0, 0), a lift joins floors 1 and 2 at cell (3, 0). Anchor `f`
    /// is heard on floor `f` only.
    fn building() -> Building {
        let text = r#"
            name = "b"
            floors = [
                { name = "B", level = -1, site = "f.toml" },
                { name = "G", level = 0, site = "f.toml" },
                { name = "L1", level = 1, site = "f.toml" },
            ]
            [[connectors]]
            id = "stairs"
            kind = "stairs"
            stops = [{ floor = "B", cell = [0, 0] }, { floor = "G", cell = [0, 0] }]
            [[connectors]]
            id = "lift"
            kind = "lift"
            stops = [{ floor = "G", cell = [3, 0] }, { floor = "L1", cell = [3, 0] }]
        "#;
        let floor = "name = \"f\"\ncell_m = 1.0\nmap = '''\n####\n'''\n";
        Building::parse(text, Path::new("b.toml"), |path| Site::parse(floor, path)).unwrap()
    }

    fn tracks() -> FloorTracks {
        let evidence = FloorEvidence::new(
            3,
            &[
                vec![1.0, 0.0, 0.0],
                vec![0.0, 1.0, 0.0],
                vec![0.0, 0.0, 1.0],
            ],
        );
        FloorTracks::new(&building(), evidence, 0.01, 30.0)
    }

    #[test]
    fn a_device_changes_floor_no_sooner_than_a_connector_takes_it_there() {
        let mut tracks = tracks();
        let device: Arc<str> = Arc::from("phone");
        let step = tracks.update(&device, 0.0, &[(0, -60.0)]);
        assert_eq!((step.floor, step.change), (0, FloorChange::Starts));
        let step = tracks.update(&device, 1.0, &[(0, -60.0)]);
        assert_eq!((step.floor, step.change), (0, FloorChange::Stays));
        assert!(step.probability >= SETTLED, "{step:?}");
        // Heard on G two seconds later: the stairs take 15 s, so it stays
        // on B, which the evidence now doubts.
        let mut t = 3.0;
        let mut step = tracks.update(&device, t, &[(1, -60.0)]);
        while step.change == FloorChange::Stays {
            assert_eq!(step.floor, 0);
            t += 2.0;
            step = tracks.update(&device, t, &[(1, -60.0)]);
        }
        assert!(t >= 15.0, "{t}");
        assert_eq!((step.floor, step.change), (1, FloorChange::From(0)));
        assert!(step.probability > 0.5, "{step:?}");
        assert_eq!(tracks.entries(0, 1), [Cell::new(0, 0)]);
        // From B to L1 takes the stairs then the lift: 15 s + 5 s moving.
        assert_eq!(tracks.ride_s[0][2], 20.0);
        assert_eq!(tracks.entries(0, 2), [Cell::new(3, 0)]);
    }

    #[test]
    fn a_first_guess_is_corrected_before_the_floor_settles() {
        let mut tracks = tracks();
        let device: Arc<str> = Arc::from("phone");
        // A faint beacon of B heard beside G's: B first, but not settled.
        let step = tracks.update(&device, 0.0, &[(0, -60.0), (1, -61.0)]);
        assert_eq!((step.floor, step.change), (0, FloorChange::Starts));
        assert!(step.probability < SETTLED, "{step:?}");
        // Then L1 alone: the guess is corrected sooner than the 20 s any
        // connector takes from B to L1, so not by a ride.
        let mut t = 2.0;
        let mut step = tracks.update(&device, t, &[(2, -60.0)]);
        while step.floor != 2 {
            assert_eq!(step.floor, 0);
            t += 2.0;
            step = tracks.update(&device, t, &[(2, -60.0)]);
        }
        assert!(t < tracks.ride_s[0][2], "{t}");
        assert_eq!(step.change, FloorChange::Starts);
        while step.probability < SETTLED {
            t += 2.0;
            step = tracks.update(&device, t, &[(2, -60.0)]);
            assert_eq!((step.floor, step.change), (2, FloorChange::Stays));
        }
        // Settled on L1: B heard now does not move it before a ride could.
        let step = tracks.update(&device, t + 2.0, &[(0, -60.0)]);
        assert_eq!((step.floor, step.change), (2, FloorChange::Stays));
    }

    #[test]
    fn after_a_long_gap_the_floor_starts_afresh_and_the_table_is_bounded() {
        let mut tracks = tracks().bound(2, 1000.0);
        let device: Arc<str> = Arc::from("phone");
        tracks.update(&device, 0.0, &[(0, -60.0)]);
        let step = tracks.update(&device, 100.0, &[(2, -60.0)]);
        assert_eq!((step.floor, step.change), (2, FloorChange::Starts));
        for k in 0..10 {
            tracks.update(&Arc::from(format!("d{k}")), 101.0 + f64::from(k), &[]);
        }
        assert!(tracks.devices.len() <= 2, "{}", tracks.devices.len());
    }
}
