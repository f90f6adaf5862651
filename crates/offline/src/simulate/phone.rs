//! What a simulated phone hears in one scan where it stands: each beacon by
//! its radio model (detection, RSSI, shadowing, drop-outs, sensitivity), or
//! with a survey a real reading taken in (or nearest to) its cell.

use std::sync::Arc;

use rand::RngExt;
use rand::rngs::Xoshiro256PlusPlus;
use rand_distr::{Distribution, Normal};

use super::SimConfig;
use crate::event::Event;
use crate::locate::pathloss::{self, Radio};
use crate::locate::survey::Survey;
use crate::locate::window::Orientation;
use crate::sighting::Sighting;
use crate::site::{Cell, Site};

/// What a simulated phone hears in one scan: beacons by the path-loss
/// model, or with a survey a real reading taken in (or nearest to) its cell.
pub(crate) struct Phone<'a> {
    site: &'a Site,
    config: &'a SimConfig,
    survey: Option<&'a Survey>,
    /// Per beacon of the site, its radio and the spread of its RSSI; `None`
    /// for a beacon without a known position (never heard).
    beacons: Vec<Option<(Radio, Normal<f64>)>>,
    /// Scans in one fingerprint window.
    scans_per_window: f64,
}

impl<'a> Phone<'a> {
    pub(crate) fn new(site: &'a Site, config: &'a SimConfig, survey: Option<&'a Survey>) -> Self {
        let beacons = pathloss::anchors(
            site,
            Orientation::Observer,
            &config.pathloss,
            config.calibration.as_ref(),
        )
        .into_iter()
        .map(|anchor| {
            anchor.map(|(_, radio)| {
                let spread = Normal::new(0.0, radio.shadowing_db).expect("validated spread");
                (radio, spread)
            })
        })
        .collect();
        Phone {
            site,
            config,
            survey,
            beacons,
            scans_per_window: (config.scan_hz * config.window_s).max(1.0),
        }
    }

    /// One scan at `t` by `observer` in `cell`, at `pos` (in grid units, from
    /// the map's corner: see [`Site::world_of_grid`]): appends the adverts
    /// heard to `events`.
    pub(crate) fn scan(
        &self,
        cell: Cell,
        pos: (f64, f64),
        t: f64,
        observer: &Arc<str>,
        rng: &mut Xoshiro256PlusPlus,
        events: &mut Vec<Event>,
    ) {
        match self.survey {
            Some(survey) => hear_survey(self.site, survey, cell, t, observer, rng, events),
            None => self.hear_model(pos, t, observer, rng, events),
        }
    }

    /// One scan from the radio model at `pos` (grid units).
    fn hear_model(
        &self,
        (gx, gy): (f64, f64),
        t: f64,
        observer: &Arc<str>,
        rng: &mut Xoshiro256PlusPlus,
        events: &mut Vec<Event>,
    ) {
        let here = self.site.world_of_grid([gx, gy]);
        for (beacon, model) in self.site.beacons.iter().zip(&self.beacons) {
            let (Some(mount), Some((radio, spread))) = (beacon.mount, model) else {
                continue;
            };
            let distance_m = mount.distance_m(here);
            // Heard in a scan with the probability that makes a window of
            // `scans_per_window` scans hear it as often as the model says.
            let in_window = radio.detection(distance_m);
            let in_scan = 1.0 - (1.0 - in_window).powf(1.0 / self.scans_per_window);
            if !rng.random_bool(in_scan) || rng.random_bool(self.config.dropout) {
                continue;
            }
            let rssi = radio.expected_rssi(distance_m) + spread.sample(rng);
            if rssi < self.config.pathloss.sensitivity_dbm {
                continue;
            }
            events.push(Event::Advert(Sighting {
                advertiser_mac: beacon.mac,
                t,
                observer: observer.clone(),
                advertiser: beacon.beacon,
                // What the beacon's frame advertises, not what it measures.
                tx_power: Some(
                    beacon
                        .tx_power
                        .map_or(self.config.pathloss.tx_power_dbm, f64::from)
                        .round() as i8,
                ),
                rssi: rssi.round() as i16,
            }));
        }
    }
}

fn hear_survey(
    site: &Site,
    survey: &Survey,
    cell: Cell,
    t: f64,
    observer: &Arc<str>,
    rng: &mut Xoshiro256PlusPlus,
    events: &mut Vec<Event>,
) {
    // The survey's nearest surveyed cell stands in for cells it never visited.
    let nearest = survey
        .samples
        .iter()
        .map(|s| s.cell)
        .min_by(|a, b| a.distance(cell).total_cmp(&b.distance(cell)))
        .expect("a survey has samples");
    let rows: Vec<_> = survey
        .samples
        .iter()
        .filter(|s| s.cell == nearest)
        .collect();
    let row = rows[rng.random_range(0..rows.len())];
    for (beacon, rssi) in site.beacons.iter().zip(&row.rssi) {
        if let Some(rssi) = *rssi {
            events.push(Event::Advert(Sighting {
                advertiser_mac: beacon.mac,
                t,
                observer: observer.clone(),
                advertiser: beacon.beacon,
                tx_power: beacon.tx_power,
                rssi,
            }));
        }
    }
}
