//! `gangway replay` on the capture formats people already have, and `--score`.

use crate::common;

use std::path::Path;

use crate::common::{gangway, gangway_ok, root};

use gangway::event::Event;
use gangway::sighting::Sighting;
use gangway::source::btsnoop::{BtsnoopWriter, Datalink};
use gangway::source::ibeacon::{self, IBeacon};
use gangway::source::log::{LogReader, LogWriter};
use serde_json::Value;

const FIXTURE: &str = "fixtures/walk-waldo.jsonl";
const SCORE_KEYS: [&str; 12] = [
    "exact",
    "within_1",
    "within_2",
    "mean_error_cells",
    "mean_error_m",
    "fixes",
    "matched",
    "truths",
    "tolerance_s",
    "reliability",
    "confidence_gap_max",
    "confidence_gap_mean",
];

/// The one JSON object `--score --json` prints.
fn score(args: &[&str]) -> Value {
    let stdout = gangway_ok(args);
    let mut lines = stdout.lines();
    let score: Value = serde_json::from_str(lines.next().expect("a score line")).unwrap();
    assert_eq!(lines.next(), None, "exactly one JSON object: {stdout}");
    let mut keys: Vec<&str> = score
        .as_object()
        .unwrap()
        .keys()
        .map(|k| k.as_str())
        .collect();
    let mut expected = SCORE_KEYS.to_vec();
    keys.sort_unstable();
    expected.sort_unstable();
    assert_eq!(keys, expected);
    score
}

fn fixture_events() -> Vec<Event> {
    LogReader::open(&root().join(FIXTURE), false)
        .unwrap()
        .map(Result::unwrap)
        .collect()
}

#[test]
fn score_counts_the_fixes_printed_and_the_truths_in_the_log() {
    let printed = gangway_ok(&["replay", FIXTURE, "--print"]);
    // Unknown locations (too little heard) name no cell and are not scored.
    let locations = printed
        .lines()
        .filter(|l| l.contains("/location\"") && !l.contains("\"cell\":null"))
        .count() as u64;
    let truths = fixture_events()
        .iter()
        .filter(|e| matches!(e, Event::Truth(_)))
        .count() as u64;

    let s = score(&["replay", FIXTURE, "--score", "--json"]);
    assert_eq!(s["fixes"], locations);
    assert_eq!(s["truths"], truths);
    // The simulator writes a truth per walker every few seconds, so every fix
    // has one within the default tolerance (the 4 s window).
    assert_eq!(s["matched"], locations);
    assert_eq!(s["tolerance_s"], 4.0);
    let shares: Vec<f64> = ["exact", "within_1", "within_2"]
        .iter()
        .map(|k| s[*k].as_f64().unwrap())
        .collect();
    assert!(shares[0] <= shares[1] && shares[1] <= shares[2], "{s}");
    assert!(shares[2] > 0.0, "{s}");

    // A tolerance of zero matches only fixes at the exact time of a truth.
    let strict = score(&["replay", FIXTURE, "--score", "--json", "--tolerance-s", "0"]);
    assert!(strict["matched"].as_u64().unwrap() < locations, "{strict}");
}

/// One walker's adverts, as one phone's or sniffer's capture would hold them.
fn walker_adverts() -> Vec<Event> {
    let adverts: Vec<Event> = fixture_events()
        .into_iter()
        .filter(|e| matches!(e, Event::Advert(s) if &*s.observer == "walker-02"))
        .collect();
    assert!(adverts.len() > 100);
    adverts
}

#[test]
fn a_btsnoop_capture_replays_like_the_log_it_was_written_from() {
    let adverts = walker_adverts();
    let dir = tempfile::tempdir().unwrap();
    let jsonl = dir.path().join("walker.jsonl");
    let mut log = LogWriter::create(&jsonl).unwrap();
    for datalink in [Datalink::H4, Datalink::Monitor] {
        // Android names its capture btsnoop_hci.log: found by its magic bytes.
        let capture = dir.path().join(format!("{datalink:?}-btsnoop_hci.log"));
        let mut writer = BtsnoopWriter::create(&capture, datalink).unwrap();
        for e in &adverts {
            if let Event::Advert(s) = e {
                writer.write(s).unwrap();
            }
        }
        writer.flush().unwrap();
        drop(writer);
        if datalink == Datalink::H4 {
            for e in &adverts {
                log.write(e).unwrap();
            }
            log.flush().unwrap();
        }
        let from_log = gangway_ok(&["replay", path(&jsonl), "--print"]);
        let from_capture =
            gangway_ok(&["replay", path(&capture), "--device", "walker-02", "--print"]);
        assert!(from_log.lines().count() > 10);
        assert_eq!(from_capture, from_log, "{datalink:?}");
    }
}

#[test]
fn a_csv_scan_log_replays_and_scores_against_its_labels() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("scan.csv");
    // Newest first like the UCI survey; the site's beacons b3001 (F08) and b3002 (J05).
    let mut text = String::from("location,date,b3001,b3002,b3099\n");
    for i in (0..30).rev() {
        let (label, rssi) = if i < 15 {
            ("F08", "-60,-200")
        } else {
            ("J05", "-200,-60")
        };
        text.push_str(&format!(
            "{label},10-18-2016 11:{:02}:{:02},{rssi},-70\n",
            10 + i / 30,
            (i * 2) % 60
        ));
    }
    std::fs::write(&csv, text).unwrap();

    // b3099 is no beacon of the site: refused, or ignored with --skip-bad.
    let out = gangway(&["replay", path(&csv), "--score"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains(":1: column `b3099`: names no beacon"), "{err}");

    let s = score(&["replay", path(&csv), "--skip-bad", "--score", "--json"]);
    assert_eq!(s["truths"], 30);
    assert!(s["fixes"].as_u64().unwrap() > 0, "{s}");
    assert_eq!(s["matched"], s["fixes"], "{s}");
}

/// A pcapng block: type, total length, body padded to 4 bytes, total length
/// (little-endian, as Wireshark writes on x86).
fn pcapng_block(out: &mut Vec<u8>, kind: u32, body: &[u8]) {
    let padded = body.len().next_multiple_of(4);
    let total = ((12 + padded) as u32).to_le_bytes();
    out.extend_from_slice(&kind.to_le_bytes());
    out.extend_from_slice(&total);
    out.extend_from_slice(body);
    out.resize(out.len() + padded - body.len(), 0);
    out.extend_from_slice(&total);
}

/// What the nRF Sniffer hands Wireshark for one iBeacon advert: the Nordic
/// header (version 3, RSSI as a magnitude) and an ADV_NONCONN_IND on the
/// advertising access address.
fn nrf_sniffer_packet(s: &Sighting) -> Vec<u8> {
    let frame = ibeacon::encode_manufacturer_data(&IBeacon {
        id: s.advertiser,
        measured_power: s.tx_power.unwrap(),
    });
    let mut pdu = vec![
        0x42, 0, 0x11, 0x22, 0x33, 0x44, 0x55, 0xC6, 0x02, 0x01, 0x06,
    ];
    pdu.push(frame.len() as u8 + 1);
    pdu.push(0xFF);
    pdu.extend_from_slice(&frame);
    pdu[1] = (pdu.len() - 2) as u8;
    let mut ll = 0x8E89_BED6u32.to_le_bytes().to_vec();
    ll.extend_from_slice(&pdu);
    ll.extend_from_slice(&[0x12, 0x34, 0x56]); // CRC
    let mut packet = vec![0x01];
    packet.extend_from_slice(&((10 + ll.len()) as u16).to_le_bytes());
    let rssi = u8::try_from(-s.rssi).unwrap();
    packet.extend_from_slice(&[3, 0, 0, 0x02, 10, 0x01, 37, rssi, 0, 0, 0, 0, 0, 0]);
    packet.extend_from_slice(&ll);
    packet
}

#[test]
fn an_nrf_sniffer_pcapng_replays_like_the_log_it_was_written_from() {
    let adverts = walker_adverts();
    let dir = tempfile::tempdir().unwrap();
    let jsonl = dir.path().join("walker.jsonl");
    let mut log = LogWriter::create(&jsonl).unwrap();
    // Section header, one NORDIC_BLE interface (microseconds), a packet per advert.
    let mut pcapng = Vec::new();
    let mut shb = 0x1A2B_3C4Du32.to_le_bytes().to_vec();
    shb.extend_from_slice(&[1, 0, 0, 0, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF]);
    pcapng_block(&mut pcapng, 0x0A0D_0D0A, &shb);
    pcapng_block(&mut pcapng, 1, &[0x10, 0x01, 0, 0, 0, 0, 0, 0]);
    for e in &adverts {
        let Event::Advert(s) = e else { unreachable!() };
        log.write(e).unwrap();
        let micros = (s.t * 1e6).round() as u64;
        let mut epb = 0u32.to_le_bytes().to_vec();
        epb.extend_from_slice(&((micros >> 32) as u32).to_le_bytes());
        epb.extend_from_slice(&(micros as u32).to_le_bytes());
        let packet = nrf_sniffer_packet(s);
        epb.extend_from_slice(&(packet.len() as u32).to_le_bytes());
        epb.extend_from_slice(&(packet.len() as u32).to_le_bytes());
        epb.extend_from_slice(&packet);
        pcapng_block(&mut pcapng, 6, &epb);
    }
    log.flush().unwrap();
    // Any name: the magic number tells.
    let capture = dir.path().join("walk-nrf-sniffer.cap");
    std::fs::write(&capture, &pcapng).unwrap();

    let from_log = gangway_ok(&["replay", path(&jsonl), "--print"]);
    assert!(from_log.lines().count() > 10);
    let from_capture = gangway_ok(&["replay", path(&capture), "--device", "walker-02", "--print"]);
    assert_eq!(from_capture, from_log);
    let named = gangway_ok(&[
        "replay",
        path(&capture),
        "--format",
        "pcapng",
        "--device",
        "walker-02",
        "--print",
    ]);
    assert_eq!(named, from_log);

    // A file named .pcapng that is not one is reported as such, not read as JSON Lines.
    let fake = dir.path().join("fake.pcapng");
    std::fs::write(&fake, "{}\n").unwrap();
    let out = gangway(&["replay", path(&fake), "--print"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("fake.pcapng: not a pcap or pcapng capture"),
        "{err}"
    );
}

/// The UCI survey as published, newest row first, replayed through the default
/// pipeline. Skipped outside CI when ../shared is not there (a clone without
/// the data); in CI the data must be there.
#[test]
fn the_uci_survey_replays_as_published() {
    let Some(survey) = common::uci_survey() else {
        return;
    };
    let s = score(&["replay", path(&survey), "--score", "--json"]);
    assert_eq!(s["truths"], 1420);
    // Sorted into time order, the survey's ~2 s readings give about a fix per
    // 2 s window stride (in file order, newest first, the windows see time run
    // backwards and a single fix comes out).
    assert!(s["fixes"].as_u64().unwrap() > 1000, "{s}");
    assert_eq!(s["matched"], s["fixes"], "{s}");
}

fn path(p: &Path) -> &str {
    p.to_str().unwrap()
}
