//! Arbitrary bytes fed to the advert log reader must give events or line-numbered
//! errors, never a panic, with and without skipping bad lines.
#![no_main]

use std::path::Path;

use gangway::source::log::LogReader;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    for skip_bad in [false, true] {
        for event in LogReader::new(data, Path::new("fuzz.jsonl"), skip_bad) {
            if let Err(e) = event {
                assert!(e.line >= 1);
            }
        }
    }
});
