//! kubectl's conventions for every list of the plugin: `-l/--selector`, `-w/--watch`,
//! `--no-headers` (with the global `-A` and `-o`), and the watch that prints what changes.

use std::collections::HashMap;
use std::fmt::Debug;
use std::io::Write as _;

use futures::TryStreamExt as _;
use kube::runtime::{WatchStreamExt as _, watcher};
use kube::{Api, Resource, ResourceExt as _};
use serde::Serialize;
use serde::de::DeserializeOwned;

use crate::Output;

/// Options every list of Kubernetes objects takes.
#[derive(Clone, Debug, Default, clap::Args)]
pub struct ListArgs {
    /// Label selector, as kubectl takes it (`-l site=lab,tier!=spare`, `-l 'arm in (a,b)'`).
    #[arg(short = 'l', long)]
    pub selector: Option<String>,
    /// After the list, watch: print each object again when it changes, until interrupted.
    #[arg(short = 'w', long)]
    pub watch: bool,
}

/// The list parameters for a selector.
pub fn params(selector: Option<&str>) -> kube::api::ListParams {
    let params = kube::api::ListParams::default();
    match selector {
        Some(s) => params.labels(s),
        None => params,
    }
}

/// A table without its header line when `--no-headers` was given.
pub fn headers(table: String, no_headers: bool) -> String {
    if !no_headers {
        return table;
    }
    table
        .split_once('\n')
        .map_or(String::new(), |(_, rest)| rest.to_owned())
}

/// `namespace/name`: the key under which a watch remembers what it printed.
fn key<K: Resource>(o: &K) -> String {
    format!("{}/{}", o.namespace().unwrap_or_default(), o.name_any())
}

/// The resource versions of `objects`, for [`watch`] to print only what changes after them.
pub fn seen<K: Resource>(objects: &[K]) -> HashMap<String, String> {
    objects
        .iter()
        .map(|o| (key(o), o.resource_version().unwrap_or_default()))
        .collect()
}

/// Watches `api` (narrowed by `selector`) until interrupted and prints each object whose
/// resource version differs from the one in `seen`: a table row (drawn by `row`, header cut
/// off) or the object alone in the structured formats, as `kubectl get -w` does. Lost
/// connections are retried with backoff (kube's watcher).
pub async fn watch<K>(
    api: Api<K>,
    selector: Option<&str>,
    mut seen: HashMap<String, String>,
    output: &Output,
    row: impl Fn(&K) -> String,
) -> anyhow::Result<()>
where
    K: Resource<DynamicType = ()> + Clone + DeserializeOwned + Serialize + Debug + Send + 'static,
{
    let config = watcher::Config {
        label_selector: selector.map(str::to_owned),
        ..watcher::Config::default()
    };
    let stream = watcher(api, config).default_backoff().applied_objects();
    let mut stream = std::pin::pin!(stream);
    while let Some(o) = stream.try_next().await? {
        let version = o.resource_version().unwrap_or_default();
        if seen.insert(key(&o), version.clone()).as_ref() == Some(&version) {
            continue;
        }
        let text = match output {
            Output::Table | Output::Wide => headers(row(&o), true),
            Output::Name => output
                .resources(std::slice::from_ref(&o))?
                .unwrap_or_default(),
            _ => output.structured(&o)?.unwrap_or_default(),
        };
        print!("{text}");
        std::io::stdout().flush()?;
    }
    Ok(())
}
