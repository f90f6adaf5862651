//! The committed walk fixture is exactly what its command (fixtures/README.md)
//! makes: regenerating gives the same bytes.

use std::path::PathBuf;

use gangway::site::Site;
use gangway::source::simulate::{WalkConfig, simulate_walks};
use gangway::train::trajectory;

#[test]
fn regenerating_the_walk_fixture_gives_the_same_bytes() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let site = Site::load(&root.join("config/sites/waldo.toml")).unwrap();
    // The flags of the command in fixtures/README.md.
    let config = WalkConfig {
        walks_per_pair: 50,
        random_walks: 600,
        seed: 1,
        ..WalkConfig::default()
    };
    let mut bytes = Vec::new();
    trajectory::write(&mut bytes, &simulate_walks(&site, &config)).unwrap();
    let committed = std::fs::read(root.join("fixtures/trajectories/waldo.jsonl")).unwrap();
    assert!(
        bytes == committed,
        "fixtures/trajectories/waldo.jsonl differs from what its command makes; \
         rerun the command in fixtures/README.md"
    );
}
