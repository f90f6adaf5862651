//! Arbitrary payloads on every subscribed topic (route requests, feedback, phone
//! scans, shared sightings) must be read or rejected, never panic.
#![no_main]

use gangway::mqtt::inbound::Inbox;
use gangway::topics::Topics;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|input: (u8, &[u8])| {
    let (which, payload) = input;
    let inbox = Inbox::new(
        Topics::new("gangway/gw"),
        "gangway/sites/fuzz".to_owned(),
        "gw".to_owned(),
        16 * 1024,
        true,
    );
    let topic = match which % 5 {
        0 => "gangway/gw/devices/phone-1/route/set",
        1 => "gangway/gw/devices/phone-1/feedback",
        2 => "gangway/gw/scans/phone-1",
        3 => "gangway/sites/fuzz/sightings/gw-2",
        _ => "gangway/gw/devices/a+b/route/set",
    };
    let _ = inbox.read(topic, payload, 1.0e9);
});
