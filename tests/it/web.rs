//! The browser UI in a real browser: Debian's chromium driven over WebDriver
//! (chromedriver) by fantoccini, one browser session for every check.
//!
//! Without chromium and chromedriver (packages `chromium`, `chromium-driver`;
//! `.ci/run` installs them) the browser test prints a note and skips, except
//! in CI. The HTTP checks (headers, the token, cross-site writes) need no
//! browser. Screenshots of every page go to `target/web-screenshots/`.

use crate::common;
use crate::web_support;

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use crate::web_support::{Browser, Proc, free_port};
use fantoccini::Locator;
use serde_json::{Value, json};

const HOSTILE: &str = "<img src=x onerror=\"window.__pwned=1\">";

/// `gangway site edit` on a free port; returns it and its base URL.
fn editor(site: &Path, extra: &[&str]) -> (Proc, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_gangway"))
        .args(["site", "edit", "--site"])
        .arg(site)
        .args(extra)
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .spawn()
        .expect("gangway runs");
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let url = line
        .split_whitespace()
        .find(|w| w.starts_with("http://"))
        .unwrap_or_else(|| panic!("no URL in {line:?}"))
        .trim_end_matches("/edit")
        .to_owned();
    (Proc(child), url)
}

/// `PUT url` with a JSON body: the status and the JSON reply.
fn put_json(url: &str, body: &Value) -> (u16, Value) {
    let mut reply = ureq::put(url)
        .config()
        .http_status_as_error(false)
        .build()
        .send_json(body)
        .unwrap();
    (
        reply.status().as_u16(),
        reply.body_mut().read_json().unwrap(),
    )
}

/// `GET url`: the status and the JSON reply.
fn get_json(url: &str) -> (u16, Value) {
    let mut reply = ureq::get(url)
        .config()
        .http_status_as_error(false)
        .build()
        .call()
        .unwrap();
    (
        reply.status().as_u16(),
        reply.body_mut().read_json().unwrap(),
    )
}

/// `gangway run --replay LOG --speed SPEED` in `dir` with the web UI on a
/// free port, the embedded broker and stats every second; `config` is the
/// rest of the config file (`gateway_id`, `site`, other tables). Returns it
/// and the UI's base URL.
fn replay_with_web(dir: &Path, config: &str, log: &Path, speed: u32) -> (Proc, String) {
    let file = dir.join("live.toml");
    std::fs::write(
        &file,
        format!(
            "{config}[mqtt]\nembedded_port = {}\nstats_interval_s = 1\n[web]\nbind = \"127.0.0.1:0\"\n",
            free_port()
        ),
    )
    .unwrap();
    let mut command = Command::new(env!("CARGO_BIN_EXE_gangway"));
    command
        .args(["run", "--config"])
        .arg(&file)
        .arg("--replay")
        .arg(log)
        .args(["--speed", &speed.to_string()]);
    web_support::with_web_ui(command)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_web_ui_in_a_real_browser() {
    let Some(plan) = common::shared_data("uci-ble-rssi/iBeacon_Layout.jpg") else {
        return;
    };
    let browser =
        match Browser::start_with(&common::root().join("target/web-screenshots"), &[]).await {
            Ok(browser) => browser,
            Err(missing) => return common::cannot_run(&missing),
        };
    let dir = tempfile::tempdir().unwrap();
    let site = dir.path().join("library.toml");
    let image = dir.path().join("iBeacon_Layout.jpg");
    the_editor_goes_from_a_plan_image_to_a_valid_site(&browser, &site, &plan, &image).await;
    the_live_map_follows_a_replay_and_routes_a_click(&browser, dir.path()).await;
    browser.client.close().await.unwrap();
}

/// `gangway run --replay` with the web UI: the map loads with every label
/// readable (no two overlap, none outside the plan, on a desktop and a
/// phone's width), devices move as the walk plays, a click on a device and a
/// place asks for a route through the same admission as MQTT and shows it
/// with its instructions, so does the keyboard alone, a device whose id is
/// markup shows it as text, survey mode records a spot, /metrics counts it
/// all, and the editor inside the gateway applies a saved site as a reload
/// does (and says when the gateway refuses it).
async fn the_live_map_follows_a_replay_and_routes_a_click(browser: &Browser, dir: &Path) {
    // The sample walk, plus a phone whose id is an HTML attack walking
    // beside walker-02.
    let walk = std::fs::read_to_string(common::root().join("fixtures/walk-waldo.jsonl")).unwrap();
    let mut log = String::new();
    for line in walk.lines() {
        log.push_str(line);
        log.push('\n');
        if line.contains("\"observer\":\"walker-02\"") {
            let hostile = serde_json::to_string(HOSTILE).unwrap();
            log.push_str(&line.replace("\"walker-02\"", &hostile));
            log.push('\n');
        }
        // A beacon the site file lacks, heard wherever walker-01 hears
        // minor 3001: the editor offers it to place.
        if line.contains("\"observer\":\"walker-01\"") && line.contains("\"minor\":3001") {
            log.push_str(&line.replace("\"minor\":3001", &format!("\"minor\":{STRANGER_MINOR}")));
            log.push('\n');
        }
    }
    let log_path = common::write(dir, "walk.jsonl", &log);
    // The gateway's own copy of the site: the editor saves it.
    let site_path = dir.join("waldo.toml");
    std::fs::copy(common::root().join("config/sites/waldo.toml"), &site_path).unwrap();
    let (_gateway, url) = replay_with_web(
        dir,
        "gateway_id = \"gw-web\"\nsite = \"waldo.toml\"\n[planner]\nmode = \"astar\"\n",
        &log_path,
        3,
    );
    browser.client.goto(&format!("{url}/")).await.unwrap();
    let listed = "return document.querySelectorAll('#devices li[data-device]').length >= 3";
    browser
        .until(
            "devices on the map",
            listed,
            "return document.getElementById('connection').textContent + ' ' + document.getElementById('devices').textContent",
        )
        .await;
    let labels = browser.label_problems().await;
    assert_eq!(labels["problems"], json!([]), "{labels}");
    assert!(labels["shown"].as_u64().unwrap() >= 10, "{labels}");

    // Within 4 s of the walk, some devices have moved.
    let positions =
        "return Object.fromEntries([...document.querySelectorAll('#devices li[data-device]')]
        .map(d => [d.dataset.device, d.dataset.cell]))";
    let before = browser.js(positions).await;
    tokio::time::sleep(Duration::from_secs(4)).await;
    let after = browser.js(positions).await;
    let moved = before
        .as_object()
        .unwrap()
        .iter()
        .filter(|(id, at)| after.get(id.as_str()).is_some_and(|now| now != *at))
        .count();
    assert!(moved >= 1, "no device moved in 4 s: {before} then {after}");

    // The hostile id is a device like any other, shown as text: in the
    // list, and in the tooltip when the pointer is on its dot.
    let hostile_cell = format!(
        "const li = [...document.querySelectorAll('#devices li[data-device]')].find(l => l.dataset.device === {});
         return li && li.dataset.cell ? li.dataset.cell.split(',').map(Number) : null",
        serde_json::to_string(HOSTILE).unwrap()
    );
    browser
        .until(
            "the hostile device",
            &format!("return (() => {{ {hostile_cell} }})() !== null"),
            "return document.getElementById('devices').textContent",
        )
        .await;
    // Devices move while the pointer goes to them: hover again until the
    // tip is the hostile device's.
    let deadline = Instant::now() + Duration::from_secs(10);
    let hostile = loop {
        browser.move_to(dot_of(browser, HOSTILE).await).await;
        let hostile = browser
            .js("return { imgs: document.querySelectorAll('img').length, pwned: window.__pwned === 1,
                          tip: document.getElementById('tip').textContent,
                          listed: document.getElementById('devices').textContent }")
            .await;
        if hostile["tip"].to_string().contains("onerror") || Instant::now() > deadline {
            break hostile;
        }
    };
    assert_eq!(hostile["imgs"], 0, "{hostile}");
    assert_eq!(hostile["pwned"], false, "{hostile}");
    assert!(
        hostile["listed"].to_string().contains("onerror"),
        "{hostile}"
    );
    assert!(hostile["tip"].to_string().contains("onerror"), "{hostile}");

    // Click walker-01's dot, then the help desk: a route and its instructions.
    let deadline = Instant::now() + Duration::from_secs(10);
    while !browser.text("route-pick").await.contains("walker-01") && Instant::now() < deadline {
        browser.click_at(dot_of(browser, "walker-01").await).await;
    }
    let desk = browser
        .js("const r = document.querySelector('.place[data-place=\"help desk\"] rect').getBoundingClientRect();
             return [r.x + r.width / 2, r.y + r.height / 2]")
        .await;
    browser
        .click_at(serde_json::from_value(desk.clone()).unwrap())
        .await;
    let route_shown = "return document.getElementById('route-pick').textContent.includes('(web-') && document.querySelectorAll('#route .instructions li').length > 0 && !!document.querySelector('.layer-route polyline')";
    let describe_route = "return document.getElementById('route-pick').textContent + ' | ' + document.getElementById('route').textContent";
    browser
        .until("the route", route_shown, describe_route)
        .await;
    let pick = browser.text("route-pick").await;
    assert!(
        pick.contains("walker-01") && pick.contains("help desk"),
        "{pick}"
    );
    let route = browser.text("route").await;
    assert!(route.contains(" m by astar"), "{route}");
    // The line drawn is the reply's line, from the walker's cell's centre
    // to the help desk's.
    let drawn = browser
        .js("return document.querySelector('.layer-route polyline').getAttribute('points')")
        .await;
    let vertices: Vec<Vec<f64>> = drawn
        .as_str()
        .unwrap()
        .split(' ')
        .map(|p| p.split(',').map(|v| v.parse().unwrap()).collect())
        .collect();
    let desk = gangway::site::Site::load(&site_path).unwrap().places()["help desk"];
    let last = vertices.last().unwrap();
    assert!(
        (last[0] - f64::from(desk.x) - 0.5).abs() < 1e-6
            && (last[1] - f64::from(desk.y) - 0.5).abs() < 1e-6,
        "{drawn}"
    );
    browser
        .until(
            "the page's own figures",
            "return Number(document.getElementById('page-stats').dataset.latencyP99) >= 0",
            "return document.getElementById('page-stats').textContent",
        )
        .await;
    browser.screenshot("map.png").await;

    // The keyboard alone: a device and a place from the lists (Enter on a
    // focused button), the same round trip.
    browser
        .enter_on(Locator::Css(
            "#devices li[data-device=\"walker-02\"] button",
        ))
        .await;
    browser
        .enter_on(Locator::XPath(
            "//ul[@id='places']//button[starts-with(., 'printers')]",
        ))
        .await;
    browser
        .until(
            "the route asked from the keyboard",
            "const p = document.getElementById('route-pick').textContent;
             return p.includes('walker-02') && p.includes('printers') && p.includes('(web-')",
            describe_route,
        )
        .await;

    // A phone's width: the map first, the panels below, labels still clear.
    browser.client.set_window_size(390, 844).await.unwrap();
    tokio::time::sleep(Duration::from_millis(500)).await;
    let labels = browser.label_problems().await;
    assert_eq!(labels["problems"], json!([]), "{labels}");
    let width = browser
        .js("return [document.documentElement.scrollWidth, window.innerWidth]")
        .await;
    assert!(
        width[0].as_f64() <= width[1].as_f64(),
        "scrolls sideways: {width}"
    );
    browser.screenshot("map-phone.png").await;
    browser.client.set_window_size(1500, 950).await.unwrap();

    // Survey mode: walker-01 stands at the help desk for two windows; the
    // survey file gets them in the generic layout, which the gateway's own
    // survey reader takes.
    browser.click_id("survey-on").await;
    browser.type_into("survey-samples", "2").await;
    browser
        .client
        .find(Locator::Css(
            "#devices li[data-device=\"walker-01\"] button",
        ))
        .await
        .unwrap()
        .click()
        .await
        .unwrap();
    let desk = browser
        .js("const r = document.querySelector('.place[data-place=\"help desk\"] rect').getBoundingClientRect();
             return [r.x + r.width / 2, r.y + r.height / 2]")
        .await;
    browser
        .click_at(serde_json::from_value(desk).unwrap())
        .await;
    browser
        .until(
            "two surveyed windows",
            "return document.getElementById('survey-status').textContent.includes('2 of 2 windows (done)')",
            "return document.getElementById('survey-status').textContent",
        )
        .await;
    let survey = dir.join("survey.csv");
    let text = std::fs::read_to_string(&survey).unwrap();
    assert!(text.starts_with("x_m,y_m,t,b3001,"), "{text}");
    assert_eq!(text.lines().count(), 3, "{text}");
    let site = gangway::site::Site::load(&site_path).unwrap();
    let anchors: Vec<String> = site.beacons.iter().map(|b| b.id.clone()).collect();
    let read = gangway::locate::survey::Survey::load(&survey, &site, &anchors, -200).unwrap();
    assert_eq!(read.samples.len(), 2);
    assert!(
        read.samples
            .iter()
            .all(|s| s.cell == gangway::site::Cell::new(9, 9))
    );
    let heat = browser.client.find(Locator::Id("heat")).await.unwrap();
    heat.select_by_value("samples").await.unwrap();
    browser
        .until(
            "the coverage map",
            "return document.querySelectorAll('.layer-heat rect').length >= 1",
            "return document.getElementById('heat-legend').textContent",
        )
        .await;
    browser.screenshot("survey-coverage.png").await;
    // The heat map of localization confidence covers every cell fixes fell in.
    heat.select_by_value("confidence").await.unwrap();
    browser
        .until(
            "the confidence map",
            "return document.querySelectorAll('.layer-heat rect').length >= 5",
            "return document.getElementById('heat-legend').textContent",
        )
        .await;
    browser.screenshot("survey.png").await;

    let metrics = ureq::get(&format!("{url}/metrics"))
        .call()
        .unwrap()
        .body_mut()
        .read_to_string()
        .unwrap();
    for series in [
        "# TYPE gangway_fixes_total counter",
        "# TYPE gangway_tracked gauge",
        "# TYPE gangway_fix_latency_seconds histogram",
        "# TYPE gangway_route_latency_seconds histogram",
    ] {
        assert!(metrics.contains(series), "{series} missing:\n{metrics}");
    }
    assert!(
        series(&metrics, "gangway_route_latency_seconds_count") >= 2.0,
        "{metrics}"
    );
    assert!(
        series(&metrics, "gangway_fix_latency_seconds_count") >= 10.0,
        "{metrics}"
    );

    the_editor_in_the_gateway_applies_a_save(browser, &url, &site).await;
}

/// The editor of the gateway's own site: a save the gateway cannot apply
/// (a new site name needs a restart) says so, and a save it can (a new
/// place) is served at once, the same reload as SIGHUP.
/// The minor of a beacon the replayed walk hears and the site lacks.
const STRANGER_MINOR: u16 = 4242;

async fn the_editor_in_the_gateway_applies_a_save(
    browser: &Browser,
    url: &str,
    site: &gangway::site::Site,
) {
    browser.client.goto(&format!("{url}/edit")).await.unwrap();
    let checked = "return document.getElementById('check-summary').textContent.startsWith('ok:')";
    let summary = "return document.getElementById('check-summary').textContent";
    browser.until("the site's check", checked, summary).await;
    assert!(browser.text("file").await.contains("saving applies it"));

    browser.type_into("name", "waldo-renamed").await;
    browser
        .until("the renamed site's check", checked, summary)
        .await;
    let status = browser.save("the refused reload").await;
    assert!(
        status.contains("refused") && status.contains("site name") && status.contains("restart"),
        "{status}"
    );

    browser.type_into("name", &site.name).await;
    let free = site
        .open_cells()
        .iter()
        .copied()
        .find(|c| !site.places().values().any(|p| p == c) && c.y > 2)
        .unwrap();
    browser.tool("place").await;
    browser.type_into("place-name", "new desk").await;
    let at = browser
        .grid_points(&[[f64::from(free.x) + 0.5, f64::from(free.y) + 0.5]])
        .await[0];
    browser.click_at(at).await;
    browser
        .until(
            "the new place's check",
            "return document.getElementById('check-summary').textContent.includes(' places') && document.getElementById('places').textContent.includes('new desk')",
            summary,
        )
        .await;
    browser.until("the site's check", checked, summary).await;
    let status = browser.save("the applied reload").await;
    assert!(
        status.contains("the gateway reloaded it and serves it now"),
        "{status}"
    );
    let labels = browser.label_problems().await;
    assert_eq!(labels["problems"], json!([]), "{labels}");
    browser.screenshot("editor-live.png").await;

    // What the gateway hears and the file lacks is offered: picked, then
    // placed with a click, it becomes a beacon with its own identity.
    browser
        .until(
            "the heard beacon the site lacks",
            &format!(
                "return document.getElementById('heard').textContent.includes('1/{STRANGER_MINOR}')"
            ),
            "return document.getElementById('heard-box').outerHTML",
        )
        .await;
    browser
        .js("document.getElementById('heard-box').scrollIntoView(); return true")
        .await;
    browser.screenshot("editor-heard.png").await;
    browser
        .js("document.querySelector('#heard button').click(); return true")
        .await;
    let spot = site.open_cells()[0];
    let at = browser
        .grid_points(&[[f64::from(spot.x) + 0.5, f64::from(spot.y) + 0.5]])
        .await[0];
    browser.click_at(at).await;
    browser
        .until(
            "the heard beacon placed",
            &format!(
                "return (document.getElementById('toml').textContent.match(/minor = {STRANGER_MINOR}\\b/) || []).length === 1 \
                 && document.getElementById('heard').children.length === 0"
            ),
            "return document.getElementById('toml').textContent",
        )
        .await;
    let served: Value = ureq::get(&format!("{url}/api/site"))
        .call()
        .unwrap()
        .body_mut()
        .read_json()
        .unwrap();
    assert!(
        served["places"].to_string().contains("new desk"),
        "{served}"
    );
}

/// Where a device's dot is (viewport coordinates), from the cell the list
/// shows (updated once a second, so callers retry while devices move).
async fn dot_of(browser: &Browser, device: &str) -> [f64; 2] {
    let script = format!(
        "const li = [...document.querySelectorAll('#devices li[data-device]')].find(l => l.dataset.device === {});
         return li.dataset.cell.split(',').map(Number)",
        serde_json::to_string(device).unwrap()
    );
    let cell: [f64; 2] = serde_json::from_value(browser.js(&script).await).unwrap();
    browser.grid_points(&[[cell[0] + 0.5, cell[1] + 0.5]]).await[0]
}

/// The value of a Prometheus series without labels.
fn series(metrics: &str, name: &str) -> f64 {
    metrics
        .lines()
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.parse().ok())
        .unwrap_or(0.0)
}

/// A new user, no TOML: open the plan, set the scale, paint the floor,
/// place beacons and places (one with a hostile name), save; `gangway check`
/// accepts the file, and opening and saving it again changes nothing.
async fn the_editor_goes_from_a_plan_image_to_a_valid_site(
    browser: &Browser,
    site: &Path,
    plan: &Path,
    image: &Path,
) {
    let (_server, url) = editor(site, &[]);
    browser.client.goto(&format!("{url}/edit")).await.unwrap();
    browser
        .until(
            "the first check",
            "return document.getElementById('problems').children.length > 0",
            "return document.getElementById('check-summary').textContent",
        )
        .await;
    assert!(
        browser
            .text("problems")
            .await
            .contains("the site needs a `map`"),
        "{}",
        browser.text("problems").await
    );

    // 1. The plan image, uploaded through the file picker. The dataset's
    // file is only copied into a temporary directory, never into the repo.
    let input = browser
        .client
        .find(Locator::Id("image-file"))
        .await
        .unwrap();
    let plan = std::fs::canonicalize(plan).unwrap();
    input.send_keys(plan.to_str().unwrap()).await.unwrap();
    browser
        .until(
            "the plan image",
            "return !!document.querySelector('.layer-floorplan image')",
            "return document.getElementById('save-status').textContent",
        )
        .await;
    assert_eq!(std::fs::read(image).unwrap(), std::fs::read(&plan).unwrap());

    // 2. The scale: the centres of survey cells A01 and W01 are 22 m apart
    // (one survey cell = 1 m, as in config/sites/waldo.toml).
    browser.tool("measure").await;
    let points = browser
        .image_points(&[
            [120.0, 118.0],
            [692.0, 118.0],
            [107.0, 105.0],
            [718.0, 495.0],
        ])
        .await;
    browser.click_at(points[0]).await;
    browser.click_at(points[1]).await;
    browser.type_into("scale-m", "22").await;
    browser.click_id("scale-apply").await;
    let info = browser.text("scale-info").await;
    assert!(info.contains("px per metre"), "{info}");
    browser
        .until(
            "the blocked grid's check",
            "return document.getElementById('problems').textContent.includes('no cell is walkable')",
            "return document.getElementById('problems').textContent",
        )
        .await;

    // 3. The surveyed floor, A01 to W15, painted walkable with a Shift-drag.
    let points = browser
        .image_points(&[[107.0, 105.0], [718.0, 495.0]])
        .await;
    browser.tool("paint").await;
    browser.shift_drag(points[0], points[1]).await;

    // 4. Beacons where the plan shows 2, 3 and 4; places, one named to attack.
    browser.tool("beacon").await;
    for p in browser
        .image_points(&[[361.0, 194.0], [469.0, 194.0], [587.0, 194.0]])
        .await
    {
        browser.click_at(p).await;
    }
    browser.tool("place").await;
    let places = browser
        .image_points(&[[360.0, 358.0], [700.0, 480.0]])
        .await;
    browser.type_into("place-name", HOSTILE).await;
    browser.click_at(places[0]).await;
    browser.type_into("place-name", "east entrance").await;
    browser.click_at(places[1]).await;
    // Each click is checked on its own: wait for the check of the last one
    // (under load, the check of the first place can come back first).
    browser
        .until(
            "a valid site with both places",
            "const s = document.getElementById('check-summary').textContent; \
             return s.startsWith('ok:') && s.includes('3 beacons, 2 places')",
            "return document.getElementById('check-summary').textContent + ' | ' + document.getElementById('problems').textContent",
        )
        .await;

    // The hostile name is text: no element made of it, no handler run.
    let hostile = browser
        .js(
            "return { imgs: document.querySelectorAll('img').length, pwned: window.__pwned === 1,
                      names: [...document.querySelectorAll('.place-name')].map(t => t.textContent),
                      listed: document.getElementById('places').textContent }",
        )
        .await;
    assert_eq!(hostile["imgs"], 0, "{hostile}");
    assert_eq!(hostile["pwned"], false, "{hostile}");
    assert!(
        hostile["names"]
            .as_array()
            .unwrap()
            .contains(&json!(HOSTILE)),
        "{hostile}"
    );
    assert!(
        hostile["listed"].as_str().unwrap().contains(HOSTILE),
        "{hostile}"
    );
    browser.screenshot("editor.png").await;

    // 5. Save; `gangway check` accepts the file.
    browser.save("the save").await;
    let saved = std::fs::read_to_string(site).unwrap();
    assert!(
        saved.contains("[floorplan]") && saved.contains("image = \"iBeacon_Layout.jpg\""),
        "{saved}"
    );
    let config = site.with_file_name("gangway.toml");
    std::fs::write(
        &config,
        "gateway_id = \"gw-test\"\nsite = \"library.toml\"\n[localizer]\nmethod = \"pathloss\"\n",
    )
    .unwrap();
    let out = common::gangway_ok(&["check", "--config", config.to_str().unwrap()]);
    assert!(out.starts_with("ok: "), "{out}");
    assert!(out.contains("3 beacons, 0 gateways, 2 places"), "{out}");

    // 6. Opened again and saved unchanged: the same bytes.
    browser.client.refresh().await.unwrap();
    browser
        .until(
            "the reopened site's check",
            "return document.getElementById('check-summary').textContent.startsWith('ok:')",
            "return document.getElementById('check-summary').textContent",
        )
        .await;
    browser.click_id("save").await;
    browser
        .until(
            "the second save",
            "return document.getElementById('save-status').textContent.startsWith('saved')",
            "return document.getElementById('save-status').textContent",
        )
        .await;
    assert_eq!(std::fs::read_to_string(site).unwrap(), saved);
}

/// Every page and API reply carries the strict policy; the health check answers.
#[test]
fn every_reply_carries_the_content_security_policy() {
    let dir = tempfile::tempdir().unwrap();
    let (_server, url) = editor(&dir.path().join("s.toml"), &["--bind", "127.0.0.1:0"]);
    for path in [
        "/edit",
        "/assets/edit.js",
        "/api/editor",
        "/healthz",
        "/nope",
    ] {
        let reply = ureq::get(&format!("{url}{path}"))
            .config()
            .http_status_as_error(false)
            .build()
            .call()
            .unwrap();
        let csp = reply
            .headers()
            .get("content-security-policy")
            .and_then(|v| v.to_str().ok())
            .unwrap_or_default()
            .to_owned();
        assert_eq!(csp, gangway::web::CONTENT_SECURITY_POLICY, "{path}");
        assert!(
            csp.contains("script-src 'self'") && !csp.contains("unsafe"),
            "{csp}"
        );
        assert_eq!(reply.headers()["x-content-type-options"], "nosniff");
    }
    let health: Value = ureq::get(&format!("{url}/healthz"))
        .call()
        .unwrap()
        .body_mut()
        .read_json()
        .unwrap();
    assert_eq!(health["status"], "ok");
}

/// Bound off loopback, a write without the token is refused; with it, it
/// is taken. On loopback, another site's page cannot write (cross-origin)
/// and a rebound host name is not answered.
/// `gangway site edit` on a building file: the floors' site files one at a
/// time and the building's connectors. A building whose connectors have
/// problems (a stop written by hand into a wall) opens, listing them, so
/// they can be fixed there; saving the connectors rewrites them alone. A
/// one-floor site's editor has no connectors.
#[test]
fn site_edit_opens_a_building_with_its_connectors_problems_and_all() {
    let dir = tempfile::tempdir().unwrap();
    let file = crate::floors_support::write_building(dir.path());
    let shaft = crate::floors_support::cell_of([17.0, 8.0]);
    let stairs = crate::floors_support::cell_of([9.0, 8.25]);
    let g_stop = format!(
        "{{ floor = \"G\", cell = [{}, {}] }}]",
        stairs[0], stairs[1]
    );
    let text = std::fs::read_to_string(&file).unwrap();
    assert!(text.contains(&g_stop), "{text}");
    // The stairs get a stop on L1, in the lift shaft.
    let broken = text.replace(
        &g_stop,
        &format!(
            "{}, {{ floor = \"L1\", cell = [{}, {}] }}]",
            g_stop.trim_end_matches(']'),
            shaft[0],
            shaft[1]
        ),
    );
    std::fs::write(&file, &broken).unwrap();
    let (_editor, url) = editor(&file, &["--bind", "127.0.0.1:0"]);
    let get = |path: &str| get_json(&format!("{url}{path}"));
    let (_, opened) = get("/api/editor?floor=G");
    assert_eq!(opened["floor"], "G");
    assert!(
        opened["path"].as_str().unwrap().ends_with("G.toml"),
        "{opened}"
    );
    assert_eq!(opened["floors"].as_array().unwrap().len(), 3);
    let (_, got) = get("/api/editor/connectors");
    let problems = got["problems"].to_string();
    assert!(
        problems.contains("connector `stairs` stop on floor `L1`")
            && problems.contains("is a blocked cell"),
        "{got}"
    );
    // The stairs' stop moved off the shaft: saved, the floors untouched.
    let mut connectors = got["connectors"].clone();
    for stop in connectors[1]["stops"].as_array_mut().unwrap() {
        if stop["floor"] == "L1" {
            stop["cell"] = json!(stairs);
        }
    }
    let (status, saved) = put_json(
        &format!("{url}/api/editor/connectors"),
        &json!({ "connectors": connectors }),
    );
    assert_eq!(status, 200, "{saved}");
    assert_eq!(saved["applied"], Value::Null);
    let (_, after) = get("/api/editor/connectors");
    assert_eq!(after["problems"], json!([]), "{after}");
    assert_eq!(after["connectors"], connectors);
    let written = std::fs::read_to_string(&file).unwrap();
    let floors_part = |text: &str| text[..text.find("[[connectors]]").unwrap()].to_owned();
    assert_eq!(floors_part(&written), floors_part(&broken));
    let check = common::gangway(&["check", "--site", file.to_str().unwrap()]);
    assert!(
        check.status.success(),
        "{}",
        String::from_utf8_lossy(&check.stdout)
    );

    let (_one, one_url) = editor(&dir.path().join("G.toml"), &["--bind", "127.0.0.1:0"]);
    let (status, body) = get_json(&format!("{one_url}/api/editor/connectors"));
    assert_eq!(status, 404, "{body}");
    assert_eq!(body["error"]["code"], "not_a_building");
}

#[test]
fn writes_off_loopback_need_the_token() {
    let dir = tempfile::tempdir().unwrap();
    let token = "s3cret-token-for-the-test";
    let token_file = common::write(dir.path(), "token", &format!("{token}\n"));
    let site = dir.path().join("s.toml");
    let (_server, url) = editor(
        &site,
        &[
            "--bind",
            "0.0.0.0:0",
            "--token-file",
            token_file.to_str().unwrap(),
        ],
    );
    let doc = json!({ "doc": { "name": "s", "cell_m": 1.0, "map": "##\n" } });
    let put = |auth: Option<&str>| {
        let mut req = ureq::put(&format!("{url}/api/editor/site"))
            .config()
            .http_status_as_error(false)
            .build();
        if let Some(a) = auth {
            req = req.header("Authorization", a);
        }
        let mut reply = req.send_json(&doc).unwrap();
        let status = reply.status().as_u16();
        let body: Value = reply.body_mut().read_json().unwrap_or(Value::Null);
        (status, body)
    };
    let (status, body) = put(None);
    assert_eq!(status, 401, "{body}");
    assert_eq!(body["error"]["code"], "unauthorized");
    assert_eq!(put(Some("Bearer wrong-token-0123456789")).0, 401);
    assert!(!site.exists(), "nothing was written without the token");
    let (status, body) = put(Some(&format!("Bearer {token}")));
    assert_eq!(status, 200, "{body}");
    assert!(site.exists());
    // The token is never served.
    for path in ["/api/access", "/api/editor", "/edit", "/assets/edit.js"] {
        let text = ureq::get(&format!("{url}{path}"))
            .call()
            .unwrap()
            .body_mut()
            .read_to_string()
            .unwrap();
        assert!(!text.contains(token), "{path}");
    }

    let (_local, url) = editor(&dir.path().join("t.toml"), &["--bind", "127.0.0.1:0"]);
    let cross = ureq::put(&format!("{url}/api/editor/site"))
        .header("Origin", "http://evil.example")
        .config()
        .http_status_as_error(false)
        .build()
        .send_json(&doc)
        .unwrap();
    assert_eq!(cross.status().as_u16(), 403);
    let rebound = ureq::get(&format!("{url}/api/editor"))
        .header("Host", "evil.example")
        .config()
        .http_status_as_error(false)
        .build()
        .call()
        .unwrap();
    assert_eq!(rebound.status().as_u16(), 421);
}

/// A replay's /metrics has the runtime's latency histograms: wall time on
/// the gateway's clock, whatever the log's time says.
#[test]
fn a_replay_serves_fix_and_route_latency_on_metrics() {
    let dir = tempfile::tempdir().unwrap();
    let config = common::write(
        dir.path(),
        "gangway.toml",
        &format!(
            "gateway_id = \"gw-replay\"\nsite = \"{}\"\n[planner]\nmode = \"astar\"\n[web]\nbind = \"127.0.0.1:0\"\n",
            common::root().join("config/sites/waldo.toml").display()
        ),
    );
    let mut command = Command::new(env!("CARGO_BIN_EXE_gangway"));
    command
        .arg("replay")
        .arg(common::root().join("fixtures/walk-waldo.jsonl"))
        .arg("--config")
        .arg(&config)
        .args(["--speed", "0", "--web", "127.0.0.1:0"]);
    let (_replay, url) = web_support::with_web_ui(command);
    // The log plays as fast as it can; its six requests are routes (and
    // guidance re-routes walkers who leave theirs: routes too).
    let deadline = Instant::now() + Duration::from_secs(20);
    let metrics = loop {
        let text = ureq::get(&format!("{url}/metrics"))
            .call()
            .unwrap()
            .body_mut()
            .read_to_string()
            .unwrap();
        let played = series(&text, "gangway_route_latency_seconds_count") >= 6.0
            && series(&text, "gangway_fix_latency_seconds_count") >= 50.0;
        if played || Instant::now() > deadline {
            break text;
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    let fixes = series(&metrics, "gangway_fix_latency_seconds_count");
    assert!(fixes >= 50.0, "{metrics}");
    assert!(
        series(&metrics, "gangway_route_latency_seconds_count") >= 6.0,
        "{metrics}"
    );
    // Buckets are cumulative, up to the count.
    let buckets: Vec<f64> = metrics
        .lines()
        .filter_map(|l| l.strip_prefix("gangway_fix_latency_seconds_bucket{le=\""))
        .filter_map(|l| l.split_once("} ")?.1.parse().ok())
        .collect();
    assert_eq!(buckets.len(), 13, "{metrics}");
    assert!(buckets.windows(2).all(|w| w[0] <= w[1]), "{metrics}");
    assert_eq!(buckets.last(), Some(&fixes), "{metrics}");
    let sum = series(&metrics, "gangway_fix_latency_seconds_sum");
    assert!(sum > 0.0 && sum / fixes < 0.1, "{metrics}");
}

/// The packaged unit's /etc/gangway is read-only to the daemon: saving the
/// site it serves cannot write it, so the editor saves it in the state
/// directory and says how to put it in place. The site directory is made
/// read-only here as systemd makes it (a read-only bind mount, in a mount
/// namespace of the gateway's own).
#[test]
fn a_site_that_cannot_be_written_is_saved_in_the_state_directory() {
    let dir = tempfile::tempdir().unwrap();
    let etc = dir.path().join("etc");
    let state = dir.path().join("state");
    std::fs::create_dir_all(&etc).unwrap();
    std::fs::create_dir_all(&state).unwrap();
    let site = etc.join("waldo.toml");
    std::fs::copy(common::root().join("config/sites/waldo.toml"), &site).unwrap();
    let config = common::write(
        &etc,
        "gangway.toml",
        &format!(
            "gateway_id = \"gw-ro\"\nsite = \"waldo.toml\"\n[planner]\nmode = \"astar\"\n\
             [mqtt]\nembedded_port = {}\n[web]\nbind = \"127.0.0.1:0\"\n",
            free_port()
        ),
    );
    let read_only = "mount --bind \"$0\" \"$0\" && mount -o remount,bind,ro \"$0\" && exec \"$@\"";
    let probe = Command::new("unshare")
        .args(["-r", "-m", "sh", "-c", read_only])
        .arg(&etc)
        .args(["sh", "-c", "! touch \"$0/probe\" 2>/dev/null"])
        .arg(&etc)
        .status();
    if !probe.is_ok_and(|s| s.success()) {
        crate::common::cannot_run(
            "a read-only bind mount (unshare -r -m: util-linux and mount namespaces)",
        );
        return;
    }
    let mut command = Command::new("unshare");
    command
        .args(["-r", "-m", "sh", "-c", read_only])
        .arg(&etc)
        .arg(env!("CARGO_BIN_EXE_gangway"))
        .args(["run", "--config"])
        .arg(&config)
        .args(["--replay", "/dev/null"])
        .env("STATE_DIRECTORY", &state);
    let (_gateway, url) = web_support::with_web_ui(command);
    let opened: Value = ureq::get(&format!("{url}/api/editor"))
        .call()
        .unwrap()
        .body_mut()
        .read_json()
        .unwrap();
    assert_eq!(opened["served_by_gateway"], true, "{opened}");
    let mut doc = opened["doc"].clone();
    doc["places"]["new desk"] = json!([12, 3]);
    let (status, reply) = put_json(&format!("{url}/api/editor/site"), &json!({ "doc": doc }));
    assert_eq!(status, 200, "{reply}");
    let instead = state.join("waldo.toml");
    assert_eq!(reply["saved"], instead.display().to_string(), "{reply}");
    assert_eq!(reply["instead_of"], site.display().to_string(), "{reply}");
    assert_eq!(reply["applied"], false, "{reply}");
    let message = reply["message"].as_str().unwrap();
    assert!(
        message.contains("Read-only file system")
            && message.contains(&format!(
                "sudo install -m 644 {} {}",
                instead.display(),
                site.display()
            )),
        "{message}"
    );
    let saved = std::fs::read_to_string(&instead).unwrap();
    assert!(saved.contains("\"new desk\" = [12, 3]"), "{saved}");
    // The original is untouched.
    assert_eq!(
        std::fs::read(&site).unwrap(),
        std::fs::read(common::root().join("config/sites/waldo.toml")).unwrap()
    );
}

/// The live map of a building (the made-up B1, G, L1 of `floors_support`)
/// served by `gangway run --replay` of a phone riding the lift from B1 to
/// L1: a floor switcher lists the floors, each shows its own plan, the phone
/// is drawn on L1 only (and listed, saying where, on the others); the site
/// endpoints take `?floor=` and name the floors for one the building lacks;
/// the editor edits one floor's site file at a time and a save reloads the
/// building.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_map_of_a_building_switches_floors() {
    let browser =
        match Browser::start_with(&common::root().join("target/web-screenshots"), &[]).await {
            Ok(browser) => browser,
            Err(missing) => return common::cannot_run(&missing),
        };
    let browser = &browser;
    let dir = tempfile::tempdir().unwrap();
    crate::floors_support::write_building(dir.path());
    let walk = crate::floors_daemon::capture(dir.path(), &[]);
    // Every fix published: five beacons over three floors of 0.5 m cells.
    let (_gateway, url) = replay_with_web(
        dir.path(),
        "gateway_id = \"gw-floors\"\nsite = \"building.toml\"\n[localizer]\nmin_confidence = 0.0\n",
        &walk,
        10,
    );

    // The API: the floors, lowest first; `?floor=` names one, an unknown
    // one is a 404 that lists them.
    let get = |path: &str| get_json(&format!("{url}{path}"));
    let (_, floors) = get("/api/floors");
    assert_eq!(
        floors["floors"],
        json!([{ "name": "B1", "level": -1 }, { "name": "G", "level": 0 }, { "name": "L1", "level": 1 }]),
        "{floors}"
    );
    let (status, lowest) = get("/api/site");
    assert_eq!((status, &lowest["name"]), (200, &json!("made-up B1")));
    let (_, l1) = get("/api/site?floor=L1");
    assert_eq!(l1["name"], "made-up L1");
    assert_eq!(l1["floor"], json!({ "name": "L1", "level": 1 }));
    let lift = crate::floors_support::cell_of([17.0, 6.25]);
    assert_eq!(
        l1["connectors"],
        json!([{ "id": "lift", "kind": "lift", "cell": lift, "to": ["B1", "G"] }]),
        "{l1}"
    );
    let (status, unknown) = get("/api/site?floor=L9");
    assert_eq!(status, 404, "{unknown}");
    let message = unknown["error"]["message"].as_str().unwrap();
    assert!(
        message.contains("L9") && message.contains("B1, G, L1"),
        "{message}"
    );
    assert_eq!(get("/api/floorplan?floor=L9").0, 404);

    browser.client.goto(&format!("{url}/")).await.unwrap();
    let describe = "return document.getElementById('connection').textContent + ' | ' + \
                    document.getElementById('floor-switch').textContent + ' | ' + \
                    document.getElementById('devices').textContent";
    browser
        .until(
            "the floor switcher",
            "return document.querySelectorAll('#floor-switch button').length === 3",
            describe,
        )
        .await;
    let buttons = browser
        .js("return [...document.querySelectorAll('#floor-switch button')].map(b => [b.dataset.floor, b.getAttribute('aria-pressed')])")
        .await;
    assert_eq!(
        buttons,
        json!([["L1", "false"], ["G", "false"], ["B1", "true"]]),
        "highest on top, the lowest shown first"
    );
    assert_eq!(browser.text("site-name").await, "made-up");
    assert_eq!(browser.text("floor-name").await, "floor B1");
    // The phone ends the walk on L1: listed on B1, saying so, not drawn.
    browser
        .until(
            "the phone on L1",
            "const li = document.querySelector('#devices li[data-device=phone]'); return !!li && li.dataset.floor === 'L1' && li.textContent.includes('on floor L1')",
            describe,
        )
        .await;
    let drawn = "return document.getElementById('devices-layer').dataset.drawn";
    assert_eq!(browser.js(drawn).await, json!("0"));

    let show = |name: &'static str| async move {
        browser
            .js(&format!(
                "document.querySelector('#floor-switch button[data-floor={name}]').click(); return true"
            ))
            .await;
        browser
            .until(
                "the floor shown",
                &format!(
                    "return document.getElementById('plan').dataset.floor === '{name}' && \
                     document.getElementById('plan').dataset.site === 'made-up {name}' && \
                     document.getElementById('floor-name').textContent === 'floor {name}'"
                ),
                describe,
            )
            .await;
    };
    show("L1").await;
    browser
        .until(
            "the phone drawn on L1",
            &format!("{drawn} === '1'"),
            describe,
        )
        .await;
    let pressed = browser
        .js("return document.querySelector('#floor-switch button[aria-pressed=true]').dataset.floor")
        .await;
    assert_eq!(pressed, json!("L1"));
    assert!(
        browser
            .client
            .current_url()
            .await
            .unwrap()
            .as_str()
            .ends_with("?floor=L1")
    );
    let row = "return document.querySelector('#devices li[data-device=phone]').textContent";
    assert!(!browser.js(row).await.to_string().contains("on floor"));
    let connectors = browser
        .js("return [...document.querySelectorAll('#plan .connector-name')].map(l => l.textContent)")
        .await;
    assert_eq!(connectors, json!(["lift → B1, G"]));
    let labels = browser.label_problems().await;
    assert_eq!(labels["problems"], json!([]), "{labels}");
    browser.screenshot("map-building.png").await;
    show("G").await;
    browser
        .until(
            "the phone not drawn on G",
            &format!("{drawn} === '0'"),
            describe,
        )
        .await;
    assert!(browser.text("devices").await.contains("on floor L1"));

    // The editor of L1's site file: a place added there and saved reloads
    // the building, and L1 serves it; B1's file is untouched.
    let b1_before = std::fs::read_to_string(dir.path().join("B1.toml")).unwrap();
    browser
        .client
        .goto(&format!("{url}/edit?floor=L1"))
        .await
        .unwrap();
    let checked = "return document.getElementById('check-summary').textContent.startsWith('ok:')";
    let summary = "return document.getElementById('check-summary').textContent + ' | ' + document.getElementById('file').textContent";
    browser.until("L1's check", checked, summary).await;
    assert!(browser.text("file").await.contains("L1.toml"));
    let chosen = browser
        .js("return [document.getElementById('floor').value, document.getElementById('floor').options.length, document.getElementById('floor-box').hidden]")
        .await;
    assert_eq!(chosen, json!(["L1", 3, false]));
    browser.tool("place").await;
    browser.type_into("place-name", "reading room").await;
    let [x, y] = crate::floors_support::cell_of([12.0, 2.0]);
    let at = browser
        .grid_points(&[[f64::from(x) + 0.5, f64::from(y) + 0.5]])
        .await[0];
    browser.click_at(at).await;
    browser
        .until(
            "the new place",
            "return document.getElementById('places').textContent.includes('reading room')",
            summary,
        )
        .await;
    browser.until("L1's check", checked, summary).await;
    browser.screenshot("editor-building.png").await;
    let status = browser.save("the save").await;
    assert!(
        status.contains("L1.toml") && status.contains("the gateway reloaded it"),
        "{status}"
    );
    let l1_file = std::fs::read_to_string(dir.path().join("L1.toml")).unwrap();
    assert!(l1_file.contains("reading room"), "{l1_file}");
    assert_eq!(
        std::fs::read_to_string(dir.path().join("B1.toml")).unwrap(),
        b1_before
    );
    let (_, l1) = get("/api/site?floor=L1");
    assert!(l1["places"].to_string().contains("reading room"), "{l1}");
    the_editor_places_a_building_s_connectors(browser, dir.path(), &url).await;
    browser.client.clone().close().await.unwrap();
}

/// The editor's connectors, on L1 of the building the gateway serves: the
/// building file's connectors and problems are listed; a stop on a blocked
/// cell is refused with the reason and nothing is written; the stairs,
/// chosen in the list, get a stop on L1 with the Connector tool, and saving
/// rewrites only the building file's `[[connectors]]`, reloads the gateway,
/// and the map of L1 draws the stairs.
async fn the_editor_places_a_building_s_connectors(browser: &Browser, dir: &Path, url: &str) {
    let file = dir.join("building.toml");
    let before = std::fs::read_to_string(&file).unwrap();
    let mut reply = ureq::get(&format!("{url}/api/editor/connectors"))
        .call()
        .unwrap();
    let got: Value = reply.body_mut().read_json().unwrap();
    assert_eq!(got["problems"], json!([]), "{got}");
    let stairs = crate::floors_support::cell_of([9.0, 8.25]);
    assert_eq!(
        got["connectors"][1],
        json!({ "id": "stairs", "kind": "stairs", "stops": [
            { "floor": "B1", "cell": stairs }, { "floor": "G", "cell": stairs }] }),
        "{got}"
    );
    // Into L1's lift shaft: refused, saying where and why; nothing written.
    let mut connectors = got["connectors"].clone();
    let shaft = crate::floors_support::cell_of([17.0, 8.0]);
    connectors[1]["stops"]
        .as_array_mut()
        .unwrap()
        .push(json!({ "floor": "L1", "cell": shaft }));
    let (status, refused) = put_json(
        &format!("{url}/api/editor/connectors"),
        &json!({ "connectors": connectors }),
    );
    assert_eq!(status, 422, "{refused}");
    let message = refused["error"]["message"].as_str().unwrap();
    assert!(
        message.starts_with("not saved: ")
            && message.contains(&format!(
                "connector `stairs` stop on floor `L1` at [{}, {}] is a blocked cell",
                shaft[0], shaft[1]
            )),
        "{message}"
    );
    assert_eq!(std::fs::read_to_string(&file).unwrap(), before);

    // In the page: the stairs chosen, then their cell on L1 clicked.
    browser
        .until(
            "the connectors listed",
            "return document.querySelectorAll('#connectors li').length === 2",
            "return document.getElementById('connectors-box').outerHTML",
        )
        .await;
    browser
        .js("document.querySelector('#connectors li[data-connector=stairs] button.link').click(); return true")
        .await;
    browser.tool("stop").await;
    let at = browser
        .grid_points(&[[f64::from(stairs[0]) + 0.5, f64::from(stairs[1]) + 0.5]])
        .await[0];
    browser.click_at(at).await;
    let listed =
        "return document.querySelector('#connectors li[data-connector=stairs]').textContent";
    assert_eq!(
        browser.js(listed).await,
        json!("stairs · stairs · B1, G, L1✕")
    );
    let drawn = browser
        .js("return [...document.querySelectorAll('#plan .connector-name')].map(l => l.textContent)")
        .await;
    assert_eq!(drawn, json!(["lift → B1, G", "stairs → B1, G"]));
    browser.screenshot("editor-connectors.png").await;
    browser.click_id("connectors-save").await;
    browser
        .until(
            "the connectors saved",
            "return document.getElementById('connectors-status').textContent.startsWith('saved')",
            "return document.getElementById('connectors-status').textContent",
        )
        .await;
    let status = browser.text("connectors-status").await;
    assert!(
        status.contains("building.toml") && status.contains("the gateway reloaded it"),
        "{status}"
    );
    // Only the connectors were rewritten; the gateway serves them.
    let after = std::fs::read_to_string(&file).unwrap();
    let floors_part = |text: &str| {
        text[..text.find("[[connectors]]").unwrap()]
            .trim_end()
            .to_owned()
    };
    assert_eq!(floors_part(&after), floors_part(&before));
    assert!(
        after.contains(&format!(
            "stops = [{{ floor = \"B1\", cell = [{0}, {1}] }}, {{ floor = \"G\", cell = [{0}, \
             {1}] }}, {{ floor = \"L1\", cell = [{0}, {1}] }}]",
            stairs[0], stairs[1]
        )),
        "{after}"
    );
    let mut reply = ureq::get(&format!("{url}/api/site?floor=L1"))
        .call()
        .unwrap();
    let l1: Value = reply.body_mut().read_json().unwrap();
    assert_eq!(
        l1["connectors"][1],
        json!({ "id": "stairs", "kind": "stairs", "cell": stairs, "to": ["B1", "G"] }),
        "{l1}"
    );
}

/// Survey mode on a floor above the lowest of a building (the made-up B1,
/// G, L1): a phone standing on L1, shown on the map at `?floor=L1`, is
/// surveyed where the operator clicks; its windows go to L1's own file
/// (`survey-L1.csv` beside the config, L1's beacon as the only column, the
/// spot in L1's metres), which L1's survey reader takes; G shows its own
/// empty file, and the API names the floors for one the building lacks.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn survey_mode_records_each_floor_into_its_own_file() {
    let browser =
        match Browser::start_with(&common::root().join("target/web-screenshots"), &[]).await {
            Ok(browser) => browser,
            Err(missing) => return common::cannot_run(&missing),
        };
    let dir = tempfile::tempdir().unwrap();
    crate::floors_support::write_building(dir.path());
    // A minute of a phone by L1's beacon, hearing G's atrium through the
    // floor, played in real time.
    let advert = |t: u32, minor: u16, rssi: i32| {
        json!({
            "type": "advert", "t": 1_767_225_600.0 + f64::from(t), "observer": "phone",
            "uuid": crate::floors_support::UUID, "major": 7, "minor": minor, "rssi": rssi,
        })
        .to_string()
    };
    let lines: Vec<String> = (0..60u32)
        .flat_map(|t| [advert(t, 5, -70 - (t % 3) as i32), advert(t, 4, -92)])
        .collect();
    let walk = common::write(dir.path(), "standing.jsonl", &(lines.join("\n") + "\n"));
    let (_gateway, url) = replay_with_web(
        dir.path(),
        "gateway_id = \"gw-survey\"\nsite = \"building.toml\"\n[localizer]\nmin_confidence = 0.0\n",
        &walk,
        1,
    );
    let (status, unknown) = get_json(&format!("{url}/api/survey?floor=L9"));
    assert_eq!(status, 404, "{unknown}");
    assert!(
        unknown["error"]["message"]
            .as_str()
            .unwrap()
            .contains("B1, G, L1"),
        "{unknown}"
    );

    browser
        .client
        .goto(&format!("{url}/?floor=L1"))
        .await
        .unwrap();
    let describe = "return document.getElementById('survey-status').textContent + ' | ' + \
                    document.getElementById('devices').textContent";
    browser
        .until(
            "survey mode on L1 and the phone listed",
            "return !document.getElementById('survey').hidden && \
             !!document.querySelector('#devices li[data-device=phone] button')",
            describe,
        )
        .await;
    browser.click_id("survey-on").await;
    browser.type_into("survey-samples", "2").await;
    browser
        .client
        .find(Locator::Css("#devices li[data-device=phone] button"))
        .await
        .unwrap()
        .click()
        .await
        .unwrap();
    let [x, y] = crate::floors_support::cell_of([16.0, 3.0]);
    let spot = browser
        .grid_points(&[[f64::from(x) + 0.5, f64::from(y) + 0.5]])
        .await[0];
    browser.click_at(spot).await;
    browser
        .until(
            "two windows surveyed on L1",
            "const s = document.getElementById('survey-status').textContent; \
             return s.includes('2 of 2 windows (done)') && s.includes('survey-L1.csv')",
            describe,
        )
        .await;
    browser.screenshot("survey-building.png").await;

    let file = dir.path().join("survey-L1.csv");
    let text = std::fs::read_to_string(&file).unwrap();
    assert!(text.starts_with("x_m,y_m,t,l1-east\n"), "{text}");
    assert_eq!(text.lines().count(), 3, "{text}");
    let l1 = gangway::site::Site::load(&dir.path().join("L1.toml")).unwrap();
    let read =
        gangway::locate::survey::Survey::load(&file, &l1, &["l1-east".into()], -200).unwrap();
    assert_eq!(read.samples.len(), 2);
    assert!(
        read.samples
            .iter()
            .all(|s| s.cell == gangway::site::Cell::new(x, y) && s.rssi[0].is_some()),
        "{text}"
    );
    for other in ["survey-B1.csv", "survey-G.csv", "survey.csv"] {
        assert!(!dir.path().join(other).exists(), "{other} written");
    }

    // G: its own (empty) file, and the RSSI layers of its beacons.
    browser
        .js("document.querySelector('#floor-switch button[data-floor=G]').click(); return true")
        .await;
    browser
        .until(
            "G's survey",
            "return document.getElementById('survey-status').textContent.includes('0 cells surveyed in') && \
             document.getElementById('survey-status').textContent.includes('survey-G.csv')",
            describe,
        )
        .await;
    let layers = browser
        .js("return [...document.querySelectorAll('#heat option')].map(o => o.textContent).filter(t => t.startsWith('RSSI'))")
        .await;
    assert_eq!(layers, json!(["RSSI of g-west", "RSSI of atrium"]));
    browser.client.clone().close().await.unwrap();
}
