//! A Robot watch whose list takes longer than the API server keeps its history of changes (its
//! watch cache: 75 s) lists once, shows changes while the list is read, and goes on watching:
//! the relist storm after an API server restart at 10,000 robots (lists of 90-137 s, each
//! followed by a watch refused as too old and a new list) cannot happen. The list is made slow
//! by a proxy that hands on the API server's answers at 64 KiB/s per connection; the history is
//! made to expire by writes to a Robot of another namespace, until a watch from before the list
//! is refused (checked, so the test cannot pass without the condition it is about).

use std::time::{Duration, Instant};

use futures::{StreamExt, TryStreamExt};
use kube::api::{ListParams, Patch, PatchParams, PostParams, WatchEvent, WatchParams};
use kube::{Api, Client, ResourceExt};
use lekiwi_crds::Robot;
use lekiwi_tests::lag_proxy::LagProxy;
use lekiwi_tests::{ControlPlane, create_robot, namespace, wait_for};
use serde_json::json;
use tokio_util::sync::CancellationToken;

/// Robots in the watched namespace, each padded to about [`PAD`] bytes: a list of ~7.5 MiB,
/// about two minutes at [`RATE`].
const ROBOTS: usize = 240;
const PAD: usize = 32 * 1024;
/// What the proxy hands on per connection, in bytes per second.
const RATE: u64 = 64 * 1024;
/// How long the API server keeps the changes a watch can resume from, at least.
const HISTORY: Duration = Duration::from_secs(75);

#[tokio::test]
async fn a_list_longer_than_the_watch_history_is_read_once_and_changes_show_during_it()
-> anyhow::Result<()> {
    let cp = ControlPlane::private()?;
    cp.install_crds()?;
    let client = cp.client().await?;
    let ns = namespace(&client, "slow-list").await?;
    let elsewhere = namespace(&client, "churn").await?;
    create_padded(&client, &ns, ROBOTS, PAD).await?;
    create_robot(&client, &elsewhere, "churn", &[]).await?;

    // The watch under test: the cache the gateway and the Fleet API read, through the proxy.
    let proxy = LagProxy::start(cp.api_server_addr()?).await?;
    proxy.set_rate(RATE);
    let dir = tempfile::tempdir()?;
    let kubeconfig = dir.path().join("kubeconfig");
    cp.kubeconfig_via(&format!("https://{}", proxy.addr), &kubeconfig)?;
    let slow = client_from(&kubeconfig).await?;
    let robots: Api<Robot> = Api::namespaced(client.clone(), &ns);
    let before = robots
        .list(&ListParams::default().limit(1))
        .await?
        .metadata
        .resource_version
        .expect("a list's version");
    let lists_before = robot_lists(&cp)?;
    let started = Instant::now();
    let cancel = CancellationToken::new();
    let (cache, _task) = lekiwi_core::cache::watch(
        Api::<Robot>::namespaced(slow, &ns),
        |r| r.managed_fields_mut().clear(),
        cancel.clone(),
    );

    // Changes made while the list is read show in the cache before the list is in.
    tokio::time::sleep(Duration::from_secs(2)).await;
    relabel(&robots, "r-000", "moved").await?;
    robots.delete("r-001", &Default::default()).await?;
    create_robot(&client, &ns, "r-new", &[]).await?;
    wait_for(
        "the watch's changes in the cache while the list is read",
        Duration::from_secs(30),
        || async {
            let moved = cache
                .get(&ns, "r-000")
                .is_some_and(|r| r.labels().get("room").is_some_and(|v| v == "moved"));
            (moved && cache.get(&ns, "r-001").is_none() && cache.get(&ns, "r-new").is_some())
                .then_some(())
        },
    )
    .await?;
    assert!(
        !cache.is_ready(),
        "the list was in within {:?}",
        started.elapsed()
    );

    // Outlive the history, then write elsewhere until a watch from before the list is refused.
    tokio::time::sleep_until((started + HISTORY + Duration::from_secs(5)).into()).await;
    let churn: Api<Robot> = Api::namespaced(client.clone(), &elsewhere);
    let writes = churn_until_expired(&churn, &robots, &before).await?;
    println!(
        "history expired after {writes} writes, {:?} in",
        started.elapsed()
    );
    assert!(
        !cache.is_ready(),
        "the list came in ({:?}) before the history expired: the test proves nothing",
        started.elapsed()
    );

    // The list comes in once, merged with what the watch brought.
    wait_for(
        "the list in the cache",
        Duration::from_secs(120),
        || async { cache.is_ready().then_some(()) },
    )
    .await?;
    println!("list in after {:?}", started.elapsed());
    let (all, _) = cache.page(Some(&ns), None, usize::MAX, |_| true);
    assert_eq!(all.len(), ROBOTS, "one deleted, one created");
    let r0 = cache.get(&ns, "r-000").expect("r-000");
    assert_eq!(
        r0.labels()["room"],
        "moved",
        "the watch's copy, newer than the list's"
    );
    assert!(
        cache.get(&ns, "r-001").is_none(),
        "deleted after the list's version"
    );
    assert!(
        cache.get(&ns, "r-new").is_some(),
        "created after the list's version"
    );
    let lists = robot_lists(&cp)? - lists_before;
    assert_eq!(
        lists, 2.0,
        "one list of nothing (where the cache stands) and one full list; more is a relist"
    );

    // The watch goes on after the merge.
    relabel(&robots, "r-002", "after").await?;
    wait_for(
        "a change after the list",
        Duration::from_secs(30),
        || async {
            cache
                .get(&ns, "r-002")
                .is_some_and(|r| r.labels().get("room").is_some_and(|v| v == "after"))
                .then_some(())
        },
    )
    .await?;
    assert_eq!(robot_lists(&cp)? - lists_before, 2.0, "no list since");
    cancel.cancel();
    Ok(())
}

/// Creates `count` robots `r-000`, ... in `ns`, each padded by `pad` bytes.
async fn create_padded(client: &Client, ns: &str, count: usize, pad: usize) -> anyhow::Result<()> {
    let api: Api<Robot> = Api::namespaced(client.clone(), ns);
    let pad = "x".repeat(pad);
    futures::stream::iter(0..count)
        .map(|i| {
            let (api, pad) = (api.clone(), pad.clone());
            async move {
                let robot: Robot = serde_json::from_value(json!({
                    "apiVersion": "fleet.lekiwi.io/v1alpha1",
                    "kind": "Robot",
                    "metadata": {
                        "name": format!("r-{i:03}"),
                        "labels": {"room": "lab"},
                        "annotations": {"test.lekiwi.io/pad": pad},
                    },
                    "spec": {},
                }))?;
                api.create(&PostParams::default(), &robot).await?;
                anyhow::Ok(())
            }
        })
        .buffer_unordered(16)
        .try_collect::<Vec<_>>()
        .await?;
    Ok(())
}

async fn relabel(api: &Api<Robot>, name: &str, room: &str) -> anyhow::Result<()> {
    let patch = json!({"metadata": {"labels": {"room": room}}});
    api.patch(name, &PatchParams::default(), &Patch::Merge(&patch))
        .await?;
    Ok(())
}

/// Patches the Robot `churn` in rounds of 100 until a watch of `watched` from `version` is
/// refused as too old; the writes it took.
async fn churn_until_expired(
    api: &Api<Robot>,
    watched: &Api<Robot>,
    version: &str,
) -> anyhow::Result<usize> {
    let mut writes = 0;
    while writes < 5_000 {
        futures::stream::iter(0..100)
            .map(|i| {
                let api = api.clone();
                async move {
                    let patch = json!({"metadata": {"labels": {"n": format!("{}", writes + i)}}});
                    api.patch("churn", &PatchParams::default(), &Patch::Merge(&patch))
                        .await
                }
            })
            .buffered(8)
            .try_collect::<Vec<_>>()
            .await?;
        writes += 100;
        if expired(watched, version).await? {
            return Ok(writes);
        }
    }
    anyhow::bail!("a watch from {version} still starts after {writes} writes")
}

/// Whether the API server refuses a watch of `api` from `version` as too old.
async fn expired(api: &Api<Robot>, version: &str) -> anyhow::Result<bool> {
    match api.watch(&WatchParams::default().timeout(1), version).await {
        Err(kube::Error::Api(status)) => Ok(status.code == 410),
        Err(e) => Err(e.into()),
        Ok(events) => {
            let mut events = std::pin::pin!(events);
            while let Some(event) = events.next().await {
                if let WatchEvent::Error(status) = event? {
                    return Ok(status.code == 410);
                }
            }
            Ok(false)
        }
    }
}

/// The Robot lists the API server has served.
fn robot_lists(cp: &ControlPlane) -> anyhow::Result<f64> {
    Ok(cp
        .requests(&["LIST"])?
        .get("robots")
        .copied()
        .unwrap_or(0.0))
}

async fn client_from(kubeconfig: &std::path::Path) -> anyhow::Result<Client> {
    let kc = kube::config::Kubeconfig::read_from(kubeconfig)?;
    let config =
        kube::Config::from_custom_kubeconfig(kc, &kube::config::KubeConfigOptions::default())
            .await?;
    Ok(Client::try_from(lekiwi_core::api_client::with_timeouts(
        config,
    ))?)
}
