//! The agent's systemd unit is valid and hardened, as systemd itself judges it.

use std::process::Command;

#[test]
fn agent_systemd_unit_verifies_and_is_hardened() {
    let root = lekiwi_tests::repo_root();
    let unit =
        std::fs::read_to_string(root.join("manifests/systemd/lekiwi-agent.service")).unwrap();
    for key in [
        "Restart=on-failure",
        "MemoryMax=",
        "NoNewPrivileges=yes",
        "StateDirectory=lekiwi",
        "ConfigurationDirectory=lekiwi",
    ] {
        assert!(unit.contains(key), "unit lacks {key}");
    }
    let Ok(out) = Command::new("systemd-analyze").arg("--version").output() else {
        panic!("systemd-analyze is missing (Debian package systemd); scripts/setup.sh installs it");
    };
    assert!(out.status.success());
    // Verify a copy whose ExecStart points at a binary that exists on this machine.
    let dir = tempfile::tempdir().unwrap();
    let copy = dir.path().join("lekiwi-agent.service");
    std::fs::write(&copy, unit.replace("/usr/bin/lekiwi-agent", "/bin/true")).unwrap();
    let out = Command::new("systemd-analyze")
        .arg("verify")
        .arg(&copy)
        .output()
        .unwrap();
    let report = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        out.status.success() && report.trim().is_empty(),
        "systemd-analyze verify:\n{report}"
    );
    let out = Command::new("systemd-analyze")
        .args(["security", "--offline=yes"])
        .arg(&copy)
        .output()
        .unwrap();
    let report = String::from_utf8_lossy(&out.stdout);
    let exposure: f64 = report
        .lines()
        .find_map(|l| {
            l.split("Overall exposure level for lekiwi-agent.service: ")
                .nth(1)
        })
        .and_then(|rest| rest.split_whitespace().next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no exposure level in:\n{report}"));
    assert!(
        exposure <= 3.0,
        "exposure {exposure} (lower is better; 'OK' is below 3.0)"
    );
}
