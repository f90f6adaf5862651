//! Arbitrary bytes fed to the btsnoop reader must give sightings, skip counts or
//! one record-numbered error at the end, never a panic; and behind a valid
//! header (every datalink) the record decoder sees arbitrary records.
#![no_main]

use std::path::Path;

use gangway::source::btsnoop::{BtsnoopReader, MAGIC};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let mut inputs = vec![data.to_vec()];
    for datalink in [1001u32, 1002, 2001] {
        let mut file = MAGIC.to_vec();
        file.extend_from_slice(&1u32.to_be_bytes());
        file.extend_from_slice(&datalink.to_be_bytes());
        file.extend_from_slice(data);
        inputs.push(file);
    }
    for input in &inputs {
        for skip_bad in [false, true] {
            let Ok(reader) = BtsnoopReader::new(
                &input[..],
                Path::new("fuzz.btsnoop"),
                "fuzz".into(),
                skip_bad,
            ) else {
                continue;
            };
            let mut errors = 0;
            for item in reader {
                if item.is_err() {
                    errors += 1;
                }
            }
            assert!(errors <= 1, "the reader stops after its first error");
        }
    }
});
