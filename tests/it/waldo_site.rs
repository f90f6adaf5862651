//! The sample site is what its comments say it is: derived from the real survey
//! in ../shared (read at test time, never copied), and walkable end to end.

use crate::common;

use std::collections::HashMap;
use std::path::Path;
use std::sync::Arc;

use gangway::locate::survey::Survey;
use gangway::plan::{Connectivity, Planner, Profile, astar::AStar};
use gangway::site::Site;

fn waldo() -> Arc<Site> {
    Arc::new(Site::load(&common::root().join("config/sites/waldo.toml")).unwrap())
}

#[test]
fn every_place_reaches_every_other_place() {
    let site = waldo();
    assert!(site.places().len() >= 6);
    let planner = AStar::new(site.clone(), Connectivity::Eight);
    for (a, &from) in site.places() {
        for (b, &to) in site.places() {
            let route = planner
                .plan(from, to, Profile::Default)
                .unwrap_or_else(|e| panic!("{a} → {b}: {e}"));
            route
                .route
                .validate(&site, from, to, Connectivity::Eight)
                .unwrap();
        }
    }
}

#[test]
fn surveyed_cells_are_walkable_and_beacons_sit_where_they_are_heard_strongest() {
    let Some(path) = common::uci_survey() else {
        return;
    };
    let site = waldo();
    let anchors: Vec<String> = site.beacons.iter().map(|b| b.id.clone()).collect();
    let survey = Survey::load(Path::new(&path), &site, &anchors, -200).unwrap();
    assert_eq!(survey.samples.len(), 1420);
    for s in &survey.samples {
        assert!(
            site.walkable(s.cell),
            "surveyed cell {} is not walkable",
            s.cell
        );
    }
    for (i, beacon) in site.beacons.iter().enumerate() {
        // Strongest single reading; ties broken by the higher mean in the cell.
        let mut per_cell: HashMap<_, Vec<i16>> = HashMap::new();
        for s in &survey.samples {
            if let Some(r) = s.rssi[i] {
                per_cell.entry(s.cell).or_default().push(r);
            }
        }
        let score = |v: &Vec<i16>| {
            let mean = v.iter().map(|&r| f64::from(r)).sum::<f64>() / v.len() as f64;
            (*v.iter().max().unwrap(), mean)
        };
        let (&strongest, _) = per_cell
            .iter()
            .max_by(|a, b| score(a.1).partial_cmp(&score(b.1)).unwrap())
            .unwrap();
        assert_eq!(beacon.cell, Some(strongest), "beacon {}", beacon.id);
    }
}
