//! Arbitrary text as a site file must load or be refused with an error, never
//! panic; a site that loads must be self-consistent.
#![no_main]

use std::path::Path;

use gangway::site::Site;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|text: &str| {
    if let Ok(site) = Site::parse(text, Path::new("fuzz.toml")) {
        for &cell in site.open_cells() {
            assert!(site.walkable(cell));
        }
        for cell in site.places().values() {
            assert!(site.walkable(*cell));
        }
    }
});
