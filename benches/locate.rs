//! Ingest and localization hot paths: advert parsing, window updates, one fix
//! through each localizer, one tracker step, and a fix end to end.
//!
//! The kNN figures use the real survey at ../shared/data/uci-ble-rssi (read in
//! place, never copied). Run: `cargo bench --bench locate`.

use std::path::Path;
use std::sync::Arc;

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use gangway::locate::knn::{Knn, KnnConfig};
use gangway::locate::pathloss::{PathLoss, PathLossConfig};
use gangway::locate::radiomap::{RadioMap, RadioMapConfig};
use gangway::locate::survey::Survey;
use gangway::locate::tracker::{Tracker, TrackerConfig};
use gangway::locate::window::{Orientation, WindowConfig, Windows, anchor_ids};
use gangway::locate::{Localizer, LocalizerConfig};
use gangway::sighting::Sighting;
use gangway::site::Site;
use gangway::source::ibeacon::{encode_manufacturer_data, parse_manufacturer_data};

fn site() -> Arc<Site> {
    Arc::new(
        Site::load(Path::new("config/sites/waldo.toml")).expect("run from the repository root"),
    )
}

const SURVEY: &str = "../shared/data/uci-ble-rssi/iBeacon_RSSI_Labeled.csv";

fn survey(site: &Site) -> Survey {
    Survey::load(
        Path::new(SURVEY),
        site,
        &anchor_ids(site, Orientation::Observer),
        -200,
    )
    .expect("the kNN benches need the survey at ../shared/data/uci-ble-rssi")
}

fn benches(c: &mut Criterion) {
    let site = site();
    let beacon = gangway::source::ibeacon::IBeacon {
        id: site.beacons[0].beacon,
        measured_power: -59,
    };
    let frame = encode_manufacturer_data(&beacon);
    c.bench_function("advert_parse", |b| {
        b.iter(|| parse_manufacturer_data(black_box(&frame)))
    });

    let mut windows = Windows::new(WindowConfig::default(), &site);
    let observer: Arc<str> = "phone".into();
    let mut t = 0.0;
    c.bench_function("window_update", |b| {
        b.iter(|| {
            t += 0.05; // 13 beacons at ~1.5 Hz: one window closes every 40 pushes
            let s = Sighting {
                advertiser_mac: None,
                t,
                observer: observer.clone(),
                advertiser: site.beacons[(t * 20.0) as usize % site.beacons.len()].beacon,
                tx_power: Some(-59),
                rssi: -70,
            };
            black_box(windows.push(&s))
        })
    });

    let survey = survey(&site);
    let samples: Vec<_> = survey.samples.iter().collect();
    let missing = WindowConfig::default().missing_dbm;
    let tracker_config = TrackerConfig::default();
    let mut knn = Knn::new(&KnnConfig::default(), &site, &samples, missing).unwrap();
    let mut radiomap = RadioMap::new(
        &RadioMapConfig::default(),
        &site,
        &anchor_ids(&site, Orientation::Observer),
        Orientation::Observer,
        &tracker_config,
        &samples,
    )
    .unwrap();
    let mut pathloss =
        PathLoss::new(&PathLossConfig::default(), &site, Orientation::Observer).unwrap();
    let fingerprints: Vec<(Vec<f32>, Vec<bool>, f64)> = survey
        .samples
        .iter()
        .map(|s| {
            (
                s.rssi
                    .iter()
                    .map(|r| r.map_or(missing, f32::from))
                    .collect(),
                s.rssi.iter().map(Option::is_some).collect(),
                s.t.unwrap_or(0.0),
            )
        })
        .collect();
    let mut ll = vec![0.0f32; site.open_cells().len()];
    let mut i = 0;
    c.bench_function("localize_knn", |b| {
        b.iter(|| {
            let (rssi, heard, _) = &fingerprints[i % fingerprints.len()];
            i += 1;
            knn.log_likelihood(rssi, heard, &mut ll);
            black_box(&ll);
        })
    });
    c.bench_function("localize_radiomap", |b| {
        b.iter(|| {
            let (rssi, heard, _) = &fingerprints[i % fingerprints.len()];
            i += 1;
            radiomap.log_likelihood(rssi, heard, &mut ll);
            black_box(&ll);
        })
    });
    c.bench_function("localize_pathloss", |b| {
        b.iter(|| {
            let (rssi, heard, _) = &fingerprints[i % fingerprints.len()];
            i += 1;
            pathloss.log_likelihood(rssi, heard, &mut ll);
            black_box(&ll);
        })
    });

    // One tracker step and one whole fix (kNN + HMM), walking the survey in time
    // order as one device, which is the eval's `us_per_fix`.
    let mut order: Vec<usize> = (0..fingerprints.len()).collect();
    order.sort_by(|&a, &b| fingerprints[a].2.total_cmp(&fingerprints[b].2));
    let mut tracker = Tracker::new(TrackerConfig::default(), site.clone());
    let device: Arc<str> = "surveyor".into();
    let mut step = 0;
    knn.log_likelihood(&fingerprints[0].0, &fingerprints[0].1, &mut ll);
    c.bench_function("tracker_step", |b| {
        b.iter(|| {
            step += 1;
            black_box(tracker.update(&device, step as f64 * 2.0, &ll))
        })
    });
    // The default method with this survey configured: the k-NN vote and the
    // radio map blended in the share cross-validation picks.
    let auto_config = LocalizerConfig {
        knn: KnnConfig {
            survey: Some(SURVEY.into()),
            ..KnnConfig::default()
        },
        ..LocalizerConfig::default()
    };
    let mut auto = gangway::locate::build(
        &auto_config,
        &site,
        &WindowConfig::default(),
        &tracker_config,
    )
    .unwrap();
    for (name, localizer) in [
        ("fix_knn_hmm", &mut knn as &mut dyn Localizer),
        ("fix_auto_hmm", auto.as_mut()),
    ] {
        let mut tracker = Tracker::new(TrackerConfig::default(), site.clone());
        let mut k = 0;
        c.bench_function(name, |b| {
            b.iter(|| {
                let (rssi, heard, t) = &fingerprints[order[k % order.len()]];
                let lap = (k / order.len()) as f64 * 1e6; // keep time moving forward
                k += 1;
                localizer.log_likelihood(rssi, heard, &mut ll);
                black_box(tracker.update(&device, t + lap, &ll))
            })
        });
    }
}

criterion_group!(locate, benches);
criterion_main!(locate);
