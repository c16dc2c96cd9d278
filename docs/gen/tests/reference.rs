//! The committed reference pages must be exactly what the generator writes from today's code.

#[test]
fn reference_pages_match_the_code() {
    let root = lekiwi_docgen::repo_root();
    let stale = lekiwi_docgen::stale(&root).unwrap();
    assert!(
        stale.is_empty(),
        "reference pages out of date: {stale:?}\nrun `cargo run -p lekiwi-docgen` and commit the result"
    );
}

/// Every metric the hand-written pages and the README name exists in the registry (a counter
/// with `_total`, a histogram's series with their suffixes, a prefix only when some metric has
/// it): a renamed metric breaks the test, not a lab's alert.
#[test]
fn the_pages_name_only_metrics_that_exist() {
    let metrics = lekiwi_metrics::Metrics::new(true);
    let mut known = Vec::new();
    for m in metrics.catalogue() {
        match m.kind.as_str() {
            "counter" => known.push(format!("{}_total", m.name)),
            "histogram" => {
                for suffix in ["", "_bucket", "_sum", "_count"] {
                    known.push(format!("{}{suffix}", m.name));
                }
            }
            _ => known.push(m.name.clone()),
        }
    }
    // Names of the product that are not metrics: the robot's host process, crates.
    let other = [
        "lekiwi_host",
        "lekiwi_protocol",
        "lekiwi_operator",
        "lekiwi_agent",
    ];
    let root = lekiwi_docgen::repo_root();
    let mut files = vec![root.join("README.md")];
    let mut dirs = vec![root.join("docs/src")];
    while let Some(dir) = dirs.pop() {
        for entry in std::fs::read_dir(&dir).unwrap().flatten() {
            let path = entry.path();
            if path.is_dir() && !path.ends_with("generated") && !path.is_symlink() {
                dirs.push(path);
            } else if path.extension().is_some_and(|e| e == "md") {
                files.push(path);
            }
        }
    }
    let mut unknown = Vec::new();
    for file in files {
        let text = std::fs::read_to_string(&file).unwrap();
        for (at, _) in text.match_indices("lekiwi_") {
            if text[..at].ends_with(|c: char| c.is_ascii_alphanumeric() || c == '_') {
                continue;
            }
            let name: String = text[at..]
                .chars()
                .take_while(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || *c == '_')
                .collect();
            let exists = known.contains(&name)
                || other.contains(&name.as_str())
                || known
                    .iter()
                    .any(|k| k.starts_with(&name) && !name.ends_with('_'));
            if !exists {
                unknown.push(format!("{}: {name}", file.display()));
            }
        }
    }
    assert!(
        unknown.is_empty(),
        "metrics that do not exist: {unknown:#?}"
    );
}
