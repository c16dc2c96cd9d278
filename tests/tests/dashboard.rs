//! The web dashboard (issue 15) in a real browser: Debian's headless Chromium, driven over the
//! DevTools protocol, against a real operator (controller + gateway), real agents
//! (`lekiwi-fleet`) and a release pushed with the real CLI. Users are ServiceAccounts bound to
//! the chart's `lekiwi-operator-user` and `lekiwi-viewer` roles, logging in with tokens from
//! `kubectl create token`.
//!
//! What it shows, each without reloading the page: the fleet view counts and lists the robots
//! as they come Online; a robot's view has its conditions, CPU/memory charts from the event store
//! and its events; the rollouts view shows a rollout's batches filling up until it completes;
//! Pause and Resume work for the operator user; the viewer sees them disabled and a direct call
//! with its token is refused (403); robots going Offline appear in the fleet view. Screenshots
//! of each view go to `target/test-logs/dashboard-*.png` (the README's come from there).

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context as _, Result, ensure};
use k8s_openapi::apimachinery::pkg::apis::meta::v1::LabelSelector;
use kube::api::{Patch, PatchParams, PostParams};
use kube::{Api, Client};
use lekiwi_crds::{ReleaseRef, RobotDeployment, RobotDeploymentSpec};
use lekiwi_tests::browser::Browser;
use lekiwi_tests::{
    AgentProcess, ControlPlane, FleetProcess, FleetSpec, OperatorProcess, account, chart_roles,
    enrollment_token_file, gateway_url, http_request, log_dir, namespace, push_release,
    test_strategy, wait_for, wait_online,
};
use serde_json::json;

/// Robots of the `lekiwi-fleet` process (telemetry off) plus one `lekiwi-agent` with telemetry.
const ROBOTS: usize = 5;
/// The robot whose own view the test opens.
const SOLO: &str = "kiwi-solo";
/// An event message that would run script if the page parsed it as HTML.
const HOSTILE: &str = "<img src=x onerror=\"window.__xss=1\">restart done";
const LIVE: Duration = Duration::from_secs(60);
/// How soon the fleet view re-reads after a change announced during a refresh: under the
/// dashboard's `SUBSCRIBED_REFRESH_MS` (15 s) safety net, which must not be what catches up.
const CHANGE_REREAD: Duration = Duration::from_secs(10);

/// A release directory of a few files, differing by `tag`.
fn release_dir(root: &Path, tag: &str) -> Result<PathBuf> {
    let dir = root.join(format!("release-{tag}"));
    std::fs::create_dir_all(dir.join("lekiwi"))?;
    for i in 0..3 {
        std::fs::write(
            dir.join("lekiwi").join(format!("f{i}.py")),
            format!("# file {i} of release {tag}\n").repeat(50),
        )?;
    }
    Ok(dir)
}

async fn deploy(client: &Client, ns: &str, release: &ReleaseRef) -> Result<()> {
    let d = RobotDeployment::new(
        "demo",
        RobotDeploymentSpec {
            selector: LabelSelector::default(),
            release: Some(release.clone()),
            agent: None,
            strategy: test_strategy(2, 1),
            paused: false,
            analysis: None,
            priority: 0,
        },
    );
    Api::<RobotDeployment>::namespaced(client.clone(), ns)
        .create(&PostParams::default(), &d)
        .await?;
    Ok(())
}

/// Logs in through the page's form (the token typed as a user pastes it) and marks the page,
/// so a later check can tell it was never reloaded.
async fn log_in(browser: &mut Browser, base: &str, ns: &str, token: &str) -> Result<()> {
    browser.goto(&format!("{base}/dashboard/")).await?;
    browser
        .wait_for(
            "the login form",
            "!document.getElementById('login').hidden",
            LIVE,
        )
        .await?;
    // Before anyone logs in, the navigation (namespace, log out) is not shown at all.
    let nav_shown = browser
        .eval("(n => getComputedStyle(n).display !== 'none' || n.getClientRects().length > 0)(document.getElementById('nav'))")
        .await?;
    ensure!(
        nav_shown == json!(false),
        "the navigation shows on the login page"
    );
    let fill = format!(
        "document.getElementById('login-namespace').value = {ns};\
         document.getElementById('login-token').value = {token};\
         document.getElementById('login-form').requestSubmit(); true",
        ns = json!(ns),
        token = json!(token),
    );
    browser.eval(&fill).await?;
    browser
        .wait_for(
            "the navigation after login",
            "!document.getElementById('nav').hidden",
            LIVE,
        )
        .await?;
    browser.eval("window.__notReloaded = true").await?;
    Ok(())
}

async fn screenshot(browser: &mut Browser, view: &str) -> Result<()> {
    let path = log_dir().join(format!("dashboard-{view}.png"));
    let bytes = browser.screenshot(&path).await?;
    ensure!(bytes > 10_000, "{view} screenshot is only {bytes} bytes");
    Ok(())
}

/// `document.querySelectorAll(selector).length` as a JavaScript expression.
fn count(selector: &str) -> String {
    format!("document.querySelectorAll({}).length", json!(selector))
}

#[tokio::test]
async fn dashboard_shows_the_fleet_live_and_obeys_rbac() -> Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "dash").await?;
    let dir = tempfile::tempdir()?;
    let blobs = dir.path().join("blobs");
    std::fs::create_dir_all(&blobs)?;
    let mut op = OperatorProcess::start(cp, &ns, "dash", &["--blob-dir", blobs.to_str().unwrap()])?;
    op.wait_ready().await?;
    let [viewer_role, user_role] = chart_roles(cp, &client, &ns).await?;
    let user = account(cp, &client, &ns, "ops", Some(&user_role)).await?;
    let viewer = account(cp, &client, &ns, "watcher", Some(&viewer_role)).await?;
    let token_file = dir.path().join("enroll");
    enrollment_token_file(&client, &ns, &token_file).await?;
    let server = format!("http://127.0.0.1:{}", op.gateway_port);
    let v1 = push_release(
        &cp.kubeconfig(),
        &ns,
        &server,
        None,
        &release_dir(dir.path(), "1")?,
        "1.0.0",
    )?;
    let v2 = push_release(
        &cp.kubeconfig(),
        &ns,
        &server,
        None,
        &release_dir(dir.path(), "2")?,
        "2.0.0",
    )?;

    let mut browser = Browser::start("dashboard", 1280, 900).await?;
    log_in(&mut browser, &server, &ns, &user).await?;

    // The fleet view fills in as real agents enroll and come Online.
    let mut fleet = FleetProcess::start(FleetSpec {
        gateway: &gateway_url(&op),
        token_file: &token_file,
        namespace: &ns,
        robots: ROBOTS - 1,
        state_root: &dir.path().join("robots"),
        health_command: "true",
        report_every: "5",
        rust_log: "warn",
        extra: &["--restart-command", "sleep 1"],
    })?;
    let quick = [
        "--telemetry-cpu-interval-s",
        "1",
        "--telemetry-memory-interval-s",
        "1",
    ];
    let solo_state = dir.path().join("solo");
    let mut solo = AgentProcess::start(
        &gateway_url(&op),
        &format!("{ns}/{SOLO}"),
        &token_file,
        &solo_state,
        &[&quick[..], &["--telemetry-batch-interval-s", "1"]].concat(),
    )?;
    wait_online(&client, &ns, ROBOTS, Duration::from_secs(120)).await?;
    // Text a robot reports is shown as text: this event's message must not become markup.
    solo.emit("note", HOSTILE, &json!({"why": "markup in a message"}))?;
    browser
        .wait_for(
            "every robot Online in the table",
            &format!("{} === {ROBOTS}", count("#robots tr[data-phase=Online]")),
            LIVE,
        )
        .await?;
    browser
        .wait_for(
            "the fleet view on its subscription",
            "document.getElementById('status').textContent.startsWith('Live (subscription)')",
            LIVE,
        )
        .await?;
    // The counts and the rows are two reads: a robot that came Online between them is counted
    // by the re-read its announced change scheduled, well within the 15 s safety-net refresh
    // (so a view that dropped changes announced during a refresh would fail here).
    browser
        .wait_for(
            "every robot in the Online count",
            &format!("document.querySelector('#count-Online .n')?.textContent === '{ROBOTS}'"),
            CHANGE_REREAD,
        )
        .await?;

    // A rollout of v1 then v2: the rollouts view follows it to Completed without a reload.
    deploy(&client, &ns, &v1).await?;
    browser.eval("location.hash = '#/rollouts'").await?;
    browser
        .wait_for(
            "rollout demo Completed on v1",
            "document.querySelector('[data-rollout=demo]')?.dataset.phase === 'Completed'",
            Duration::from_secs(120),
        )
        .await?;
    let rollouts = Api::<RobotDeployment>::namespaced(client.clone(), &ns);
    rollouts
        .patch(
            "demo",
            &PatchParams::default(),
            &Patch::Merge(&json!({"spec": {"release": v2}})),
        )
        .await?;
    browser
        .wait_for(
            "rollout demo Progressing on v2",
            "document.querySelector('[data-rollout=demo]')?.dataset.phase === 'Progressing'",
            LIVE,
        )
        .await?;
    screenshot(&mut browser, "rollouts-progressing").await?;
    let batches = browser
        .wait_for(
            "every batch of demo complete",
            "document.querySelector('[data-rollout=demo]')?.dataset.phase === 'Completed' && \
             [...document.querySelectorAll('[data-rollout=demo] [data-batch]')]\
               .map(b => b.dataset.updated + '/' + b.dataset.total)",
            Duration::from_secs(120),
        )
        .await?;
    ensure!(batches == json!(["1/1", "2/2", "2/2"]), "batches {batches}");
    screenshot(&mut browser, "rollouts").await?;

    // Pause and Resume through the buttons, as the operator user.
    browser
        .eval("document.querySelector('[data-rollout=demo] [data-action=pause]').click(); true")
        .await?;
    wait_for("spec.paused true", LIVE, || async {
        let d = rollouts.get("demo").await.ok()?;
        d.spec.paused.then_some(())
    })
    .await?;
    browser
        .wait_for(
            "the Resume button",
            "!!document.querySelector('[data-rollout=demo] [data-action=resume]:not([disabled])')",
            LIVE,
        )
        .await?;
    browser
        .eval("document.querySelector('[data-rollout=demo] [data-action=resume]').click(); true")
        .await?;
    wait_for("spec.paused false", LIVE, || async {
        let d = rollouts.get("demo").await.ok()?;
        (!d.spec.paused).then_some(())
    })
    .await?;

    // One robot: conditions, charts from the event store, events.
    browser
        .eval(&format!("location.hash = '#/robots/{ns}/{SOLO}'"))
        .await?;
    for (what, expr) in [
        (
            "the robot's conditions",
            count("#conditions tr[data-condition]"),
        ),
        (
            "its CPU chart",
            "Number(document.querySelector('svg[data-metric=cpu_percent]')?.dataset.samples)"
                .into(),
        ),
        ("its events", count("#events tr[data-seq]")),
    ] {
        browser.wait_for(what, &expr, LIVE).await?;
    }
    let shown = browser
        .wait_for(
            "the hostile event, as text",
            &format!(
                "[...document.querySelectorAll('#events td')].some(td => td.textContent === {})",
                json!(HOSTILE)
            ),
            LIVE,
        )
        .await?;
    ensure!(shown == json!(true));
    ensure!(
        browser
            .eval("window.__xss === undefined && !document.querySelector('#events img')")
            .await?
            == json!(true),
        "an event's message became markup"
    );
    screenshot(&mut browser, "robot").await?;
    ensure!(
        browser.eval("window.__notReloaded === true").await? == json!(true),
        "the page reloaded"
    );

    // The viewer: buttons disabled, and the API refuses the call the button would make.
    browser
        .eval("document.getElementById('logout').click(); true")
        .await?;
    log_in(&mut browser, &server, &ns, &viewer).await?;
    browser.eval("location.hash = '#/rollouts'").await?;
    let disabled = browser
        .wait_for(
            "demo's buttons for the viewer",
            "(b => b.length ? b : null)([...document.querySelectorAll('[data-rollout=demo] button')].map(b => b.disabled))",
            LIVE,
        )
        .await?;
    ensure!(
        disabled == json!([true, true]),
        "viewer's buttons {disabled}"
    );
    let auth = format!("Bearer {viewer}");
    let (code, _, body) = http_request(
        op.gateway_port,
        "POST",
        &format!("/api/v1/namespaces/{ns}/rollouts/demo/pause"),
        &[("authorization", auth.as_str())],
        Some(b""),
    )
    .await?;
    ensure!(
        code == 403,
        "the viewer's pause answered {code}: {}",
        String::from_utf8_lossy(&body)
    );

    // Robots going Offline appear in the viewer's fleet view without a reload.
    browser.eval("location.hash = '#/fleet'").await?;
    browser
        .wait_for(
            "the fleet table",
            &format!("{} === {ROBOTS}", count("#robots tr[data-robot]")),
            LIVE,
        )
        .await?;
    screenshot(&mut browser, "fleet").await?;
    browser
        .wait_for(
            "the viewer's fleet view on its subscription",
            "document.getElementById('status').textContent.startsWith('Live (subscription)')",
            LIVE,
        )
        .await?;
    fleet.kill();
    solo.kill();
    browser
        .wait_for(
            "every robot Offline in the table",
            &format!("{} === {ROBOTS}", count("#robots tr[data-phase=Offline]")),
            Duration::from_secs(90),
        )
        .await
        .context("robots did not show Offline")?;
    ensure!(
        browser.eval("window.__notReloaded === true").await? == json!(true),
        "the page reloaded"
    );
    screenshot(&mut browser, "fleet-offline").await?;
    Ok(())
}
