//! The chart's optional PrometheusRule: rendered only when enabled, its rules pass
//! `promtool check rules`, every alert fires (and only then) in `promtool test rules` on series
//! shaped as the operator exports them, and every metric the rules read is one the operator
//! registers.

use std::collections::BTreeSet;
use std::process::Command;

use lekiwi_metrics::Metrics;
use lekiwi_tests::repo_root;

const CHART: &str = "charts/lekiwi-operator";

fn helm(args: &[&str]) -> String {
    // Rendered without a cluster: the chart's own CA would be new each time, which it refuses
    // unless told (the alerts do not depend on it).
    let offline: &[&str] = if args.first() == Some(&"template") {
        &["--set", "gateway.tls.allowNewCaWithoutCluster=true"]
    } else {
        &[]
    };
    let out = Command::new(lekiwi_tests::tool("helm"))
        .args(args)
        .args(offline)
        .current_dir(repo_root())
        .output()
        .expect("run helm");
    assert!(
        out.status.success(),
        "helm {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// The rule groups of the rendered PrometheusRule, as a Prometheus rule file.
fn rule_file() -> String {
    let rendered = helm(&[
        "template",
        "r",
        CHART,
        "-n",
        "fleet",
        "--set",
        "prometheusRule.enabled=true",
        "--set",
        "prometheusRule.labels.release=prom",
        "--show-only",
        "templates/prometheusrule.yaml",
    ]);
    let rule: serde_yaml::Value = serde_yaml::from_str(&rendered).expect("YAML");
    assert_eq!(rule["kind"], "PrometheusRule");
    assert_eq!(rule["apiVersion"], "monitoring.coreos.com/v1");
    assert_eq!(rule["metadata"]["labels"]["release"], "prom");
    let groups =
        serde_yaml::Mapping::from_iter([("groups".into(), rule["spec"]["groups"].clone())]);
    serde_yaml::to_string(&groups).expect("YAML")
}

/// Series as the operator exports them (plus the `instance` label Prometheus adds): replica `a`
/// leads, replica `b` is a standby with a stale view of the fleet.
const TESTS: &str = r#"
rule_files: [rules.yaml]
evaluation_interval: 1m
tests:
  - interval: 1m
    input_series:
      - series: 'lekiwi_leader_election_is_leader{instance="a"}'
        values: '1x90'
      - series: 'lekiwi_leader_election_is_leader{instance="b"}'
        values: '0x90'
      - series: 'lekiwi_robots{phase="Online",instance="a"}'
        values: '7x90'
      - series: 'lekiwi_robots{phase="Offline",instance="a"}'
        values: '2x90'
      - series: 'lekiwi_robots{phase="Unknown",instance="a"}'
        values: '1x90'
      - series: 'lekiwi_robots{phase="Offline",instance="b"}'
        values: '100x90'
      - series: 'lekiwi_rollout_phase{namespace="lab",deployment="bad",phase="RolledBack",instance="a"}'
        values: '1x90'
      - series: 'lekiwi_rollout_phase{namespace="lab",deployment="bad",phase="RolledBack",instance="b"}'
        values: '1x90'
      - series: 'lekiwi_rollout_phase{namespace="lab",deployment="stuck",phase="Progressing",instance="a"}'
        values: '1x90'
      - series: 'lekiwi_rollout_updated_robots{namespace="lab",deployment="stuck",instance="a"}'
        values: '2x90'
      - series: 'lekiwi_rollout_current_batch{namespace="lab",deployment="stuck",instance="a"}'
        values: '1x90'
      - series: 'lekiwi_rollout_phase{namespace="lab",deployment="moving",phase="Progressing",instance="a"}'
        values: '1x90'
      - series: 'lekiwi_rollout_updated_robots{namespace="lab",deployment="moving",instance="a"}'
        values: '0+1x90'
      - series: 'lekiwi_rollout_current_batch{namespace="lab",deployment="moving",instance="a"}'
        values: '1x90'
      - series: 'lekiwi_gateway_status_writes_total{priority="low",result="ok",instance="a"}'
        values: '0+60x90'
      - series: 'lekiwi_gateway_status_writes_total{priority="low",result="error",instance="a"}'
        values: '0+15x90'
      - series: 'lekiwi_gateway_status_writes_total{priority="high",result="ok",instance="b"}'
        values: '0+60x90'
      - series: 'lekiwi_gateway_event_store_errors_total{kind="write",instance="a"}'
        values: '0+5x90'
      - series: 'lekiwi_gateway_event_store_errors_total{kind="write",instance="b"}'
        values: '0x90'
      - series: 'lekiwi_gateway_blob_volume_free_bytes{instance="a"}'
        values: '5000000000x90'
      - series: 'lekiwi_gateway_blob_volume_size_bytes{instance="a"}'
        values: '100000000000x90'
      - series: 'lekiwi_gateway_blob_volume_free_bytes{instance="b"}'
        values: '50000000000x90'
      - series: 'lekiwi_gateway_blob_volume_size_bytes{instance="b"}'
        values: '100000000000x90'
      # Replica a serves a certificate that expires 5 days after the test's start, b one of 30
      # days; c has not loaded one (0: plain HTTP or before the first load).
      - series: 'lekiwi_gateway_tls_certificate_expiry_timestamp_seconds{instance="a"}'
        values: '432000x90'
      - series: 'lekiwi_gateway_tls_certificate_expiry_timestamp_seconds{instance="b"}'
        values: '2592000x90'
      - series: 'lekiwi_gateway_tls_certificate_expiry_timestamp_seconds{instance="c"}'
        values: '0x90'
    alert_rule_test:
      # Pending before its `for`, firing after.
      - {eval_time: 5m, alertname: LekiwiRobotsOffline, exp_alerts: []}
      - eval_time: 15m
        alertname: LekiwiRobotsOffline
        exp_alerts:
          - exp_labels: {severity: warning}
            exp_annotations:
              summary: More than a share of 0.2 of the robots are Offline or Unknown.
              description: 30% of the robots are Offline or Unknown (kubectl lekiwi robot list; a gateway down makes its robots Unknown).
      - eval_time: 1m
        alertname: LekiwiRolloutRolledBack
        exp_alerts:
          - exp_labels: {severity: warning, namespace: lab, deployment: bad, phase: RolledBack, instance: a}
            exp_annotations:
              summary: A rollout was rolled back.
              description: 'RobotDeployment bad rolled back (kubectl lekiwi rollout get bad: the message says why).'
      - {eval_time: 20m, alertname: LekiwiRolloutNotProgressing, exp_alerts: []}
      - eval_time: 75m
        alertname: LekiwiRolloutNotProgressing
        exp_alerts:
          - exp_labels: {severity: warning, namespace: lab, deployment: stuck, phase: Progressing, instance: a}
            exp_annotations:
              summary: A rollout is not progressing.
              description: RobotDeployment stuck has been progressing for 30m with no robot updated and no batch started.
      - eval_time: 20m
        alertname: LekiwiGatewayStatusWriteErrors
        exp_alerts:
          - exp_labels: {severity: warning, instance: a}
            exp_annotations:
              summary: A gateway's Robot status writes fail.
              description: "20% of the status writes of a fail: robots' phases and reports lag (its log says why)."
      - eval_time: 15m
        alertname: LekiwiEventStoreErrors
        exp_alerts:
          - exp_labels: {severity: warning, instance: a}
            exp_annotations:
              summary: The gateway cannot write to its event store.
              description: a fails event store operations; agents keep their events and resend them, but history and telemetry stop.
      - eval_time: 15m
        alertname: LekiwiBlobStoreNearlyFull
        exp_alerts:
          - exp_labels: {severity: warning, instance: a}
            exp_annotations:
              summary: The release blob store's volume is nearly full.
              description: 'Under 10% free on the blob volume of a: delete releases (kubectl lekiwi release list, release delete), lower gateway.releases.retention or grow the volume.'
      - {eval_time: 5m, alertname: LekiwiGatewayCertificateExpiring, exp_alerts: []}
      - eval_time: 15m
        alertname: LekiwiGatewayCertificateExpiring
        exp_alerts:
          - exp_labels: {severity: warning, instance: a}
            exp_annotations:
              summary: The gateway's TLS certificate expires within 14 days.
              description: 'The certificate a serves expires in 4d 23h 45m 0s: robots cannot connect once it has. cert-manager renews its own (kubectl describe certificate); the chart''s CA signs a new one on helm upgrade with another gateway.tls.validityDays; a Secret of yours is yours to replace. The gateway reloads it without restarting.'
"#;

fn promtool(dir: &std::path::Path, args: &[&str]) {
    let out = Command::new("promtool")
        .args(args)
        .current_dir(dir)
        .output()
        .expect("run promtool (Debian's prometheus package; scripts/setup.sh installs it)");
    assert!(
        out.status.success(),
        "promtool {args:?}:\n{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

/// The series names the operator exports: counters with `_total`, histograms with their parts.
fn exported() -> BTreeSet<String> {
    let mut names = BTreeSet::new();
    for m in Metrics::new(true).catalogue() {
        match m.kind.as_str() {
            "counter" => {
                names.insert(format!("{}_total", m.name));
            }
            "histogram" => {
                for part in ["_bucket", "_sum", "_count"] {
                    names.insert(format!("{}{part}", m.name));
                }
            }
            _ => {
                names.insert(m.name.clone());
            }
        }
    }
    names
}

#[test]
fn the_alerts_fire_on_the_series_the_operator_exports() {
    let off = helm(&["template", "r", CHART, "-n", "fleet"]);
    assert!(!off.contains("kind: PrometheusRule"), "off by default");
    let rules = rule_file();
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("rules.yaml"), &rules).unwrap();
    std::fs::write(dir.path().join("tests.yaml"), TESTS).unwrap();
    promtool(dir.path(), &["check", "rules", "rules.yaml"]);
    promtool(dir.path(), &["test", "rules", "tests.yaml"]);

    let exported = exported();
    let used: BTreeSet<&str> = rules
        .split(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
        .filter(|w| w.starts_with("lekiwi_"))
        .collect();
    assert!(used.len() >= 8, "{used:?}");
    for name in &used {
        assert!(
            exported.contains(*name),
            "the rules read {name}, which the operator does not export"
        );
    }
    // Every alert named in the rules is tested above.
    for alert in rules
        .lines()
        .filter_map(|l| l.trim().strip_prefix("- alert: "))
    {
        assert!(
            TESTS.contains(&format!("alertname: {alert}")),
            "{alert} untested"
        );
    }
}
