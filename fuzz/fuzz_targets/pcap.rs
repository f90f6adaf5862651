//! Arbitrary bytes fed to the pcap/pcapng reader must give sightings, skip
//! counts or one block-numbered error at the end, never a panic or an
//! allocation past the reader's bounds; and behind a valid pcapng section and
//! interface (every BLE linktype) and a valid pcap header, the block and packet
//! decoders see arbitrary input.
#![no_main]

use std::path::Path;

use gangway::source::pcap::PcapReader;
use libfuzzer_sys::fuzz_target;

/// A little-endian pcapng block: type, total length, body, total length.
fn block(out: &mut Vec<u8>, kind: u32, body: &[u8]) {
    let total = (12 + body.len()) as u32;
    out.extend_from_slice(&kind.to_le_bytes());
    out.extend_from_slice(&total.to_le_bytes());
    out.extend_from_slice(body);
    out.extend_from_slice(&total.to_le_bytes());
}

fuzz_target!(|data: &[u8]| {
    let mut inputs = vec![data.to_vec()];
    for linktype in [201u16, 251, 256, 272] {
        let mut pcapng = Vec::new();
        block(&mut pcapng, 0x0A0D_0D0A, &[0x4D, 0x3C, 0x2B, 0x1A, 1, 0, 0, 0, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF]);
        let mut idb = linktype.to_le_bytes().to_vec();
        idb.extend_from_slice(&[0; 6]);
        block(&mut pcapng, 1, &idb);
        pcapng.extend_from_slice(data);
        inputs.push(pcapng);

        let mut pcap = 0xA1B2_C3D4u32.to_le_bytes().to_vec();
        pcap.extend_from_slice(&[2, 0, 4, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 4, 0]);
        pcap.extend_from_slice(&u32::from(linktype).to_le_bytes());
        pcap.extend_from_slice(data);
        inputs.push(pcap);
    }
    for input in &inputs {
        for skip_bad in [false, true] {
            let Ok(reader) =
                PcapReader::new(&input[..], Path::new("fuzz.pcapng"), "fuzz".into(), skip_bad)
            else {
                continue;
            };
            let errors = reader.filter(Result::is_err).count();
            assert!(errors <= 1, "the reader stops after its first error");
        }
    }
});
