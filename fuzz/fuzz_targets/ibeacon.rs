//! Arbitrary manufacturer data must never panic the iBeacon parser, and every
//! frame it accepts must encode back to the same bytes.
#![no_main]

use gangway::source::ibeacon::{encode_manufacturer_data, parse_manufacturer_data, parse_payload};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Some(beacon) = parse_manufacturer_data(data) {
        assert_eq!(&encode_manufacturer_data(&beacon)[..], data);
    }
    let _ = parse_payload(data);
});
