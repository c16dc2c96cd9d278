//! Identity and authority against hostile peers (issue 12, points 1, 2 and 12): an enrollment
//! token creates robots but never takes over one that has credentials, never speaks for a robot
//! in a legacy poll, and robot names the gateway cannot give a token are refused up front.

use std::time::Duration;

use kube::Api;
use kube::api::{ListParams, Patch, PatchParams};
use lekiwi_crds::Robot;
use lekiwi_tests::{
    ControlPlane, OperatorProcess, create_robot, enrollment_token, get_robot, http_get_with,
    namespace,
};
use serde_json::json;

async fn start(cp: &ControlPlane, ns: &str, id: &str) -> anyhow::Result<OperatorProcess> {
    let mut op = OperatorProcess::start(cp, ns, id, &["--heartbeat-grace-seconds", "60"])?;
    op.wait_ready().await?;
    Ok(op)
}

/// A legacy poll with the enrollment token gets 401 and leaves the Robot's status as it was.
#[tokio::test]
async fn poll_with_the_enrollment_token_is_refused_and_fakes_nothing() -> anyhow::Result<()> {
    let cp = ControlPlane::shared();
    let client = cp.client().await?;
    let ns = namespace(&client, "hipoll").await?;
    let op = start(cp, &ns, "hi-poll").await?;
    let enroll = enrollment_token(&client, &ns).await?;
    create_robot(&client, &ns, "kiwi-1", &[]).await?;
    let release = json!({"version": "2.0.0", "digest": format!("sha256:{}", "b".repeat(64))});
    Api::<Robot>::namespaced(client.clone(), &ns)
        .patch(
            "kiwi-1",
            &PatchParams::default(),
            &Patch::Merge(json!({"spec": {"release": release}})),
        )
        .await?;
    let auth = format!("Bearer {enroll}");
    for path in [
        format!("/v1/poll?robot={ns}/kiwi-1&version=2.0.0&agent=forged"),
        "/v1/poll?robot=kiwi-1&version=2.0.0".to_owned(),
    ] {
        let (code, _, body) =
            http_get_with(op.gateway_port, &path, &[("authorization", &auth)]).await?;
        assert_eq!(code, 401, "{path}: {body}");
        assert!(body.contains("robot's own token"), "{body}");
    }
    // Presence is written within a second of a poll; give it three.
    tokio::time::sleep(Duration::from_secs(3)).await;
    let status = get_robot(&client, &ns, "kiwi-1")
        .await?
        .status
        .unwrap_or_default();
    assert_ne!(status.connected, Some(true), "{status:?}");
    assert_eq!(status.current_release, None, "{status:?}");
    assert_eq!(status.agent_version, None, "{status:?}");
    let robots = Api::<Robot>::namespaced(client.clone(), &ns)
        .list(&ListParams::default())
        .await?;
    assert_eq!(robots.items.len(), 1);
    Ok(())
}
