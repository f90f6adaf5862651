//! Sources: where sightings (and scripted requests and ground truth) come from.
//!
//! Every source yields the same [`Event`]s, so the pipeline cannot tell a live
//! BLE scan from a replayed log or a simulation:
//! - [`ble`]: a live scan through btleplug on BlueZ;
//! - [`log`]: the JSON Lines advert log (`gangway record` writes it, `replay` reads it);
//! - [`csvlog`]: CSV scan logs such as the UCI survey (replay only);
//! - [`btsnoop`]: HCI captures from `btmon -w` or Android's HCI snoop log;
//! - [`pcap`]: pcap and pcapng captures from Wireshark, tcpdump and the nRF
//!   Sniffer (Bluetooth LE linktypes: [`pcap_link`]);
//! - [`adverts`]: what the btsnoop and pcap readers share, from advertising
//!   data to sightings and skip counts;
//! - [`capture`]: picks one of those formats for a file and opens it;
//! - [`simulate`]: walkers on a site, heard through a path-loss model or a survey.

pub mod adverts;
pub mod ble;
pub mod btsnoop;
pub mod capture;
pub mod csvlog;
pub mod ibeacon;
pub mod log;
pub mod pcap;
pub mod pcap_link;
pub mod simulate;

use serde::{Deserialize, Serialize};

use crate::plan::Destination;
use crate::sighting::Sighting;
use crate::site::Cell;

/// One thing that happened, in time order.
#[derive(Clone, Debug, PartialEq)]
pub enum Event {
    /// An advert was heard.
    Advert(Sighting),
    /// A device asked for a route (served exactly like an MQTT `route/set`).
    Request(RouteRequest),
    /// Where a device really was: the ground truth of a recorded or simulated walk.
    Truth(Truth),
}

impl Event {
    pub fn t(&self) -> f64 {
        match self {
            Event::Advert(s) => s.t,
            Event::Request(r) => r.t,
            Event::Truth(g) => g.t,
        }
    }
}

/// A route request: from the device's current location to `to`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RouteRequest {
    pub t: f64,
    pub device: String,
    pub to: Destination,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub profile: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub request_id: Option<String>,
}

/// Ground truth: `device` was in `cell` at `t`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Truth {
    pub t: f64,
    pub device: String,
    pub cell: Cell,
}
