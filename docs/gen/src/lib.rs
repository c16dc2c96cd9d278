//! The book's reference pages, generated from the code so that they cannot go stale: CRD
//! fields from the resource types, flags and environment variables from the binaries' `clap`
//! definitions, metrics from the operator's registry, chart values from `values.schema.json`.

pub mod chart;
pub mod crd;
pub mod flags;
pub mod md;
pub mod metrics;

use std::path::{Path, PathBuf};

use anyhow::Result;

/// Where the generated pages live, relative to the repository.
pub const REFERENCE_DIR: &str = "docs/src/reference/generated";

/// The repository this crate was built from.
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// Every generated page: `(path relative to the repository, Markdown)`.
pub fn pages(root: &Path) -> Result<Vec<(PathBuf, String)>> {
    let mut pages = crd::pages()?;
    pages.extend(flags::pages()?);
    pages.push(("metrics.md".into(), metrics::page()));
    pages.extend(chart::pages(root)?);
    Ok(pages
        .into_iter()
        .map(|(name, text)| (Path::new(REFERENCE_DIR).join(name), text))
        .collect())
}

/// The pages whose committed text differs from the generated one (missing ones included), and
/// committed pages the generator no longer writes.
pub fn stale(root: &Path) -> Result<Vec<PathBuf>> {
    let pages = pages(root)?;
    let mut stale: Vec<PathBuf> = pages
        .iter()
        .filter(|(path, text)| std::fs::read_to_string(root.join(path)).ok().as_ref() != Some(text))
        .map(|(path, _)| path.clone())
        .collect();
    if let Ok(dir) = std::fs::read_dir(root.join(REFERENCE_DIR)) {
        for entry in dir.flatten() {
            let path = Path::new(REFERENCE_DIR).join(entry.file_name());
            if !pages.iter().any(|(p, _)| *p == path) {
                stale.push(path);
            }
        }
    }
    stale.sort();
    Ok(stale)
}
