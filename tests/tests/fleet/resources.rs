//! The CRDs on a real API server: apply, explain, categories, schema validation, examples, and
//! the kubectl plugin listing robots.

use lekiwi_tests::{ControlPlane, bin, namespace};

fn text(out: &std::process::Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}

#[tokio::test]
async fn crds_and_examples_apply_and_explain_reads_like_docs() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "res").await?;

    let out = cp.kubectl(&[
        "apply",
        "-n",
        &ns,
        "-f",
        "manifests/crds/",
        "-f",
        "manifests/examples/",
    ]);
    assert!(out.status.success(), "kubectl apply failed: {}", text(&out));
    let applied = text(&out);
    assert!(
        applied.contains("robot.fleet.lekiwi.io/kiwi-01 created"),
        "{applied}"
    );
    assert!(
        applied.contains("robotdeployment.fleet.lekiwi.io/lab-a-stable created"),
        "{applied}"
    );

    // The API server republishes its OpenAPI a moment after a CRD changes: poll briefly.
    let explain = |path: &'static str| {
        lekiwi_tests::wait_for(
            path,
            std::time::Duration::from_secs(20),
            move || async move {
                let out = cp.kubectl(&["explain", path]);
                let t = text(&out);
                (out.status.success() && t.contains("FIELDS")).then_some(t)
            },
        )
    };
    let release = explain("robot.spec.release").await?;
    assert!(
        release.contains("The release this robot should run"),
        "{release}"
    );
    assert!(
        release.contains("digest\t<string>") && release.contains("version\t<string>"),
        "{release}"
    );
    let spec = explain("robot.spec").await?;
    for field in [
        "displayName\t<string>",
        "hardware\t<Object>",
        "maintenance\t<boolean>",
        "release\t<Object>",
    ] {
        assert!(
            spec.contains(field),
            "kubectl explain robot.spec lacks {field}:\n{spec}"
        );
    }
    let strategy = explain("robotdeployment.spec.strategy").await?;
    let prose = strategy.split_whitespace().collect::<Vec<_>>().join(" ");
    assert!(
        prose.contains("below it every robot updated so far is rolled back"),
        "{strategy}"
    );

    // One category lists both kinds; short names work.
    let out = cp.kubectl(&["get", "lekiwi", "-n", &ns, "-o", "name"]);
    let names = text(&out);
    assert!(names.contains("robot.fleet.lekiwi.io/kiwi-03"), "{names}");
    assert!(
        names.contains("robotdeployment.fleet.lekiwi.io/lab-a-stable"),
        "{names}"
    );
    let out = cp.kubectl(&["get", "rb", "-n", &ns]);
    let table = text(&out);
    for col in [
        "NAME",
        "PHASE",
        "RELEASE",
        "DESIRED",
        "TELEOP",
        "HEARTBEAT",
        "AGE",
    ] {
        assert!(
            table.lines().next().unwrap_or("").contains(col),
            "missing column {col}: {table}"
        );
    }
    let out = cp.kubectl(&["get", "rdeploy", "-n", &ns]);
    let table = text(&out);
    assert!(
        table.contains("PROGRESS") && table.contains("lab-a-stable") && table.contains("1.1.0"),
        "{table}"
    );
    Ok(())
}

/// Each invalid object, and the words the API server must use to refuse it.
const INVALID: &[(&str, &str, &str)] = &[
    (
        "a deployment of a release and an agent at once",
        r#"{"apiVersion":"fleet.lekiwi.io/v1alpha1","kind":"RobotDeployment","metadata":{"name":"bad-both"},
            "spec":{"selector":{},"release":{"version":"1.0.0","digest":"sha256:0000000000000000000000000000000000000000000000000000000000000000"},
            "agent":{"version":"0.3.0","builds":[{"arch":"arm64","digest":"sha256:0000000000000000000000000000000000000000000000000000000000000000"}]}}}"#,
        "must validate one and only one schema (oneOf)",
    ),
    (
        "a deployment of nothing",
        r#"{"apiVersion":"fleet.lekiwi.io/v1alpha1","kind":"RobotDeployment","metadata":{"name":"bad-none"},
            "spec":{"selector":{}}}"#,
        "must validate one and only one schema (oneOf)",
    ),
    (
        "negative batch size",
        r#"{"apiVersion":"fleet.lekiwi.io/v1alpha1","kind":"RobotDeployment","metadata":{"name":"bad-batch"},
            "spec":{"selector":{},"release":{"version":"1.0.0","digest":"sha256:0000000000000000000000000000000000000000000000000000000000000000"},
            "strategy":{"batchSize":-3}}}"#,
        "spec.strategy.batchSize",
    ),
    (
        "percentage over 100",
        r#"{"apiVersion":"fleet.lekiwi.io/v1alpha1","kind":"RobotDeployment","metadata":{"name":"bad-pct"},
            "spec":{"selector":{},"release":{"version":"1.0.0","digest":"sha256:0000000000000000000000000000000000000000000000000000000000000000"},
            "strategy":{"batchSize":"150%"}}}"#,
        "spec.strategy.batchSize",
    ),
    (
        "threshold of 1.5",
        r#"{"apiVersion":"fleet.lekiwi.io/v1alpha1","kind":"RobotDeployment","metadata":{"name":"bad-threshold"},
            "spec":{"selector":{},"release":{"version":"1.0.0","digest":"sha256:0000000000000000000000000000000000000000000000000000000000000000"},
            "strategy":{"successThreshold":1.5}}}"#,
        "spec.strategy.successThreshold: Invalid value: 1.5: spec.strategy.successThreshold in body should be less than or equal to 1",
    ),
    (
        "empty version",
        r#"{"apiVersion":"fleet.lekiwi.io/v1alpha1","kind":"Robot","metadata":{"name":"bad-version"},
            "spec":{"release":{"version":"","digest":"sha256:0000000000000000000000000000000000000000000000000000000000000000"}}}"#,
        "spec.release.version",
    ),
    (
        "digest that is not sha256",
        r#"{"apiVersion":"fleet.lekiwi.io/v1alpha1","kind":"Robot","metadata":{"name":"bad-digest"},
            "spec":{"release":{"version":"1.0.0","digest":"md5:abc"}}}"#,
        "spec.release.digest in body should match",
    ),
    (
        "missing selector",
        r#"{"apiVersion":"fleet.lekiwi.io/v1alpha1","kind":"RobotDeployment","metadata":{"name":"no-selector"},
            "spec":{"release":{"version":"1.0.0","digest":"sha256:0000000000000000000000000000000000000000000000000000000000000000"}}}"#,
        "spec.selector: Required value",
    ),
    (
        "unknown teleoperation policy",
        r#"{"apiVersion":"fleet.lekiwi.io/v1alpha1","kind":"RobotDeployment","metadata":{"name":"bad-policy"},
            "spec":{"selector":{},"release":{"version":"1.0.0","digest":"sha256:0000000000000000000000000000000000000000000000000000000000000000"},
            "strategy":{"teleoperated":"Interrupt"}}}"#,
        "supported values: \"Wait\", \"Skip\"",
    ),
];

#[tokio::test]
async fn nonsense_is_refused_with_the_reason() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "invalid").await?;
    let dir = tempfile::tempdir()?;
    for (what, body, reason) in INVALID {
        let path = dir.path().join("obj.json");
        std::fs::write(&path, body)?;
        // --validate=false: the API server itself must refuse, not kubectl's client-side check.
        let out = cp.kubectl(&[
            "create",
            "--validate=false",
            "-n",
            &ns,
            "-f",
            path.to_str().unwrap(),
        ]);
        let msg = text(&out);
        assert!(!out.status.success(), "{what} was accepted: {msg}");
        assert!(
            msg.contains(reason),
            "{what}: expected {reason:?} in:\n{msg}"
        );
    }
    // A valid count and a valid percentage are both accepted.
    for (name, batch) in [("count", "3"), ("percent", "\"20%\"")] {
        let body = format!(
            r#"{{"apiVersion":"fleet.lekiwi.io/v1alpha1","kind":"RobotDeployment","metadata":{{"name":"ok-{name}"}},
            "spec":{{"selector":{{}},"release":{{"version":"1.0.0","digest":"sha256:0000000000000000000000000000000000000000000000000000000000000000"}},
            "strategy":{{"batchSize":{batch}}}}}}}"#
        );
        let path = dir.path().join("ok.json");
        std::fs::write(&path, body)?;
        let out = cp.kubectl(&["apply", "-n", &ns, "-f", path.to_str().unwrap()]);
        assert!(
            out.status.success(),
            "batchSize {batch} refused: {}",
            text(&out)
        );
    }
    // Defaults are filled in by the API server.
    let out = cp.kubectl(&["get", "rdeploy", "ok-count", "-n", &ns, "-o", "jsonpath={.spec.strategy.successThreshold} {.spec.strategy.canary} {.spec.strategy.teleoperated}"]);
    assert_eq!(text(&out), "0.8 1 Wait");
    Ok(())
}

#[tokio::test]
async fn kubectl_plugin_lists_robots() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "plugin").await?;
    let out = cp.kubectl(&["apply", "-n", &ns, "-f", "manifests/examples/robots.yaml"]);
    assert!(out.status.success(), "{}", text(&out));

    // kubectl finds the plugin on PATH, as users run it.
    let plugin_dir = tempfile::tempdir()?;
    std::os::unix::fs::symlink(
        bin("kubectl-lekiwi"),
        plugin_dir.path().join("kubectl-lekiwi"),
    )?;
    let path = format!(
        "{}:{}",
        plugin_dir.path().display(),
        std::env::var("PATH").unwrap_or_default()
    );
    let out = std::process::Command::new(lekiwi_tests::tool("kubectl"))
        .args(["lekiwi", "robots", "-n", &ns])
        .env("KUBECONFIG", cp.kubeconfig())
        .env("PATH", path)
        .output()?;
    let table = text(&out);
    assert!(out.status.success(), "{table}");
    let lines: Vec<&str> = table.lines().collect();
    assert_eq!(lines.len(), 4, "{table}");
    assert!(lines[0].starts_with("NAME") && lines[0].contains("PHASE"));
    assert!(lines[1].starts_with("kiwi-01"), "{table}");

    let out = std::process::Command::new(bin("kubectl-lekiwi"))
        .args(["robots", "-n", &ns, "-o", "json"])
        .env("KUBECONFIG", cp.kubeconfig())
        .output()?;
    let robots: Vec<lekiwi_crds::Robot> = lekiwi_tests::list_items(&out.stdout)?;
    assert_eq!(robots.len(), 3);

    let out = std::process::Command::new(bin("kubectl-lekiwi"))
        .arg("--help")
        .output()?;
    assert!(text(&out).contains("robots"));
    Ok(())
}

#[test]
fn every_binary_has_help() {
    for (name, expect) in [
        ("lekiwi-operator", "--heartbeat-grace-seconds"),
        ("kubectl-lekiwi", "robots"),
        ("lekiwi-agent", "--gateway"),
        ("crdgen", "manifests/crds"),
    ] {
        let out = std::process::Command::new(bin(name))
            .arg("--help")
            .output()
            .unwrap();
        let help = String::from_utf8_lossy(&out.stdout);
        assert!(
            out.status.success() && help.contains(expect),
            "{name} --help:\n{help}"
        );
    }
}
