//! Certificate rotation under load: a real operator serves wss:// from files laid out as a
//! Kubernetes Secret volume (`tls.crt -> ..data/tls.crt`, `..data -> ..<version>`), 50
//! simulated robots are connected, and the files are replaced as the kubelet replaces them (a
//! new `..data` symlink renamed over the old one). New connections get the new certificate
//! (a new serial from the same CA), on the robots' port and the API's, none of the 50 sessions drops or reconnects, the
//! expiry gauge follows the certificate served, and a pair that does not load is refused and
//! counted, the last good certificate still served.

use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use lekiwi_tests::{
    ControlPlane, OperatorProcess, SimProcess, SimSpec, enrollment_token_file, namespace, test_ca,
    wait_for, wait_online,
};

const ROBOTS: usize = 50;
const RELOADED: &str = "lekiwi_gateway_tls_reloads_total{kind=\"reloaded\"}";
const FAILED: &str = "lekiwi_gateway_tls_reloads_total{kind=\"failed\"}";
const EXPIRY: &str = "lekiwi_gateway_tls_certificate_expiry_timestamp_seconds";

fn sh(script: &str, dir: &Path) -> anyhow::Result<String> {
    let out = Command::new("bash")
        .args(["-c", script])
        .current_dir(dir)
        .output()?;
    if !out.status.success() {
        bail!("{script}: {}", String::from_utf8_lossy(&out.stderr));
    }
    Ok(String::from_utf8_lossy(&out.stdout).trim().to_owned())
}

/// Makes version `version` of the Secret in `dir/secret`: `..<version>/tls.crt` and `tls.key`
/// from `make` (a shell script run in that directory), then points `..data` at it by renaming
/// a new symlink over the old one, as the kubelet does; `tls.crt` and `tls.key` link through
/// `..data`.
fn secret_version(dir: &Path, version: &str, make: &str) -> anyhow::Result<()> {
    let secret = dir.join("secret");
    let data = secret.join(format!("..{version}"));
    std::fs::create_dir_all(&data)?;
    sh(make, &data)?;
    let tmp = secret.join("..data_tmp");
    std::os::unix::fs::symlink(format!("..{version}"), &tmp)?;
    std::fs::rename(&tmp, secret.join("..data"))?;
    for file in ["tls.crt", "tls.key"] {
        let link = secret.join(file);
        if std::fs::symlink_metadata(&link).is_err() {
            std::os::unix::fs::symlink(format!("..data/{file}"), &link)?;
        }
    }
    Ok(())
}

/// A new key and a certificate for 127.0.0.1 signed by the test CA in `ca_dir`, in the
/// current directory, valid a day longer than the test CA's first one.
fn signed_by(ca_dir: &Path) -> String {
    let ca = ca_dir.display();
    format!(
        "openssl req -newkey rsa:2048 -nodes -subj /CN=127.0.0.1 -keyout tls.key -out tls.csr 2>/dev/null && \
         openssl x509 -req -in tls.csr -CA {ca}/ca.crt -CAkey {ca}/ca.key -CAcreateserial -days 2 \
         -extfile {ca}/ext -out tls.crt 2>/dev/null"
    )
}

/// The serial of the certificate a new TLS connection to `port` is given.
fn served_serial(port: u16, dir: &Path) -> anyhow::Result<String> {
    sh(
        &format!(
            "openssl s_client -connect 127.0.0.1:{port} -CAfile ca.crt </dev/null 2>/dev/null \
             | openssl x509 -noout -serial"
        ),
        dir,
    )
}

/// The notAfter of the certificate in `file`, in Unix seconds, as openssl reads it.
fn file_not_after(file: &Path) -> anyhow::Result<f64> {
    let date = sh(
        &format!(
            "openssl x509 -noout -enddate -dateopt iso_8601 -in {}",
            file.display()
        ),
        Path::new("/"),
    )?;
    let at = date.strip_prefix("notAfter=").context("openssl -enddate")?;
    Ok(at.parse::<jiff::Timestamp>()?.as_second() as f64)
}

fn file_serial(file: &Path) -> anyhow::Result<String> {
    sh(
        &format!("openssl x509 -noout -serial -in {}", file.display()),
        Path::new("/"),
    )
}

async fn metric_reaches(op: &OperatorProcess, series: &str, value: f64) -> anyhow::Result<()> {
    wait_for(series, Duration::from_secs(20), || async {
        (op.metric(series).await == Some(value)).then_some(())
    })
    .await
}

#[tokio::test]
async fn a_rotated_certificate_reaches_new_connections_and_no_robot_reconnects()
-> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "tlsrot").await?;
    let dir = tempfile::tempdir()?;
    let base = dir.path();
    test_ca(base)?;
    let first = format!("cp {0}/tls.crt {0}/tls.key .", base.display());
    secret_version(base, "v1", &first)?;
    let (cert, key) = (base.join("secret/tls.crt"), base.join("secret/tls.key"));
    // The Fleet API on a port of its own, with the same certificate.
    let api_port = lekiwi_tests::free_ports(1)[0];
    let api_addr = format!("127.0.0.1:{api_port}");
    let args = [
        "--api-addr",
        &api_addr,
        "--tls-cert",
        cert.to_str().unwrap(),
        "--tls-key",
        key.to_str().unwrap(),
        "--tls-reload-seconds",
        "1",
        "--heartbeat-grace-seconds",
        "60",
        "--enroll-burst",
        "100",
        "--heartbeat-interval-seconds",
        "2",
    ];
    let mut op = OperatorProcess::start(cp, &ns, "tlsrot", &args)?;
    op.wait_ready().await?;
    let token_file = base.join("enroll");
    enrollment_token_file(&client, &ns, &token_file).await?;
    let gateway = format!("wss://127.0.0.1:{}/v1/agent", op.gateway_port);
    let ca = base.join("ca.crt");
    let ca_arg = ["--ca-file", ca.to_str().unwrap()];
    let spec = SimSpec {
        gateway: &gateway,
        token_file: &token_file,
        namespace: &ns,
        robots: ROBOTS,
        prefix: "rot",
        extra: &ca_arg,
    };
    let mut sim = SimProcess::start(spec, base)?;
    wait_online(&client, &ns, ROBOTS, Duration::from_secs(120)).await?;
    let before = served_serial(op.gateway_port, base)?;
    assert_eq!(before, file_serial(&cert)?);
    let first_expiry = file_not_after(&cert)?;
    assert_eq!(op.metric(EXPIRY).await, Some(first_expiry));

    // The rotation: a new key and certificate from the same CA, swapped in as a Secret is.
    let swapped = Instant::now();
    secret_version(base, "v2", &signed_by(base))?;
    metric_reaches(&op, RELOADED, 1.0).await?;
    let reload_seconds = swapped.elapsed().as_secs_f64();
    let after = served_serial(op.gateway_port, base)?;
    assert_ne!(
        after, before,
        "a new connection still gets the old certificate"
    );
    assert_eq!(after, file_serial(&cert)?, "not the certificate on disk");
    assert_eq!(served_serial(api_port, base)?, after, "the API's port too");
    let second_expiry = file_not_after(&cert)?;
    assert!(second_expiry > first_expiry + 86_000.0, "a day later");
    assert_eq!(
        op.metric(EXPIRY).await,
        Some(second_expiry),
        "the expiry of the new certificate"
    );
    assert!(
        op.log_text().contains("gateway TLS certificate reloaded"),
        "no log line of the reload"
    );

    // A key that is not the certificate's: refused, counted, the good one kept.
    secret_version(
        base,
        "v3",
        &format!(
            "cp {0}/secret/..v2/tls.crt . && cp {0}/ca.key tls.key",
            base.display()
        ),
    )?;
    metric_reaches(&op, FAILED, 1.0).await?;
    assert_eq!(served_serial(op.gateway_port, base)?, after);
    assert_eq!(op.metric(RELOADED).await, Some(1.0));
    assert_eq!(
        op.metric(EXPIRY).await,
        Some(second_expiry),
        "still the served one's"
    );
    assert!(
        op.log_text().contains("do not load"),
        "no log line of the failure"
    );

    // Heartbeats went on over the old sessions meanwhile; none ended.
    tokio::time::sleep(Duration::from_secs(3)).await;
    assert_eq!(
        op.metric("lekiwi_gateway_connections").await,
        Some(ROBOTS as f64)
    );
    let summary = sim.stop().context("the simulator's summary")?;
    eprintln!(
        "{ROBOTS} robots connected; reload seen {reload_seconds:.1} s after the swap \
         (--tls-reload-seconds 1); summary: {summary}"
    );
    assert_eq!(summary["reconnects"], 0, "{summary}");
    assert_eq!(summary["connect_errors"], 0, "{summary}");
    assert_eq!(summary["robots"], ROBOTS, "{summary}");
    assert!(summary["heartbeats"].as_u64() > Some(0), "{summary}");
    op.terminate()?;
    Ok(())
}
