//! The book builds with mdBook and every internal link and anchor of the built HTML resolves:
//! a link to a page that does not exist, or to a heading that is not on it, fails the test.
//! (External links are not followed: the test bed has no network.)

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::Command;

use scraper::{Html, Selector};

/// mdBook as scripts/setup.sh builds it (`$LEKIWI_CACHE/cargo-tools/bin`), else from the PATH.
fn mdbook() -> PathBuf {
    let cache = std::env::var_os("LEKIWI_CACHE")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| Path::new(&h).join(".cache/lekiwi")))
        .unwrap_or_default();
    let cached = cache.join("cargo-tools/bin/mdbook");
    if cached.is_file() {
        cached
    } else {
        PathBuf::from("mdbook")
    }
}

/// Builds the book into a fresh directory and returns it.
fn build() -> tempfile::TempDir {
    let out = tempfile::tempdir().unwrap();
    let book = lekiwi_docgen::repo_root().join("docs");
    let run = Command::new(mdbook())
        .arg("build")
        .arg(&book)
        .arg("--dest-dir")
        .arg(out.path())
        .output()
        .unwrap_or_else(|e| panic!("mdbook: {e} (scripts/setup.sh test builds it)"));
    let log = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "mdbook build failed:\n{log}");
    // mdBook reports a failed {{#include}} or a broken link of SUMMARY.md as an error line but
    // still exits 0.
    assert!(
        !log.contains("ERROR"),
        "mdbook build reported errors:\n{log}"
    );
    out
}

/// Every HTML page of `dir` with the ids on it.
fn pages(dir: &Path) -> BTreeMap<PathBuf, (Html, BTreeSet<String>)> {
    let ids = Selector::parse("[id], a[name]").unwrap();
    let mut pages = BTreeMap::new();
    let mut todo = vec![dir.to_path_buf()];
    while let Some(d) = todo.pop() {
        for entry in std::fs::read_dir(&d).unwrap().flatten() {
            let path = entry.path();
            if path.is_dir() {
                todo.push(path);
            } else if path.extension().is_some_and(|e| e == "html") {
                let html = Html::parse_document(&std::fs::read_to_string(&path).unwrap());
                let found = html
                    .select(&ids)
                    .filter_map(|e| e.value().attr("id").or(e.value().attr("name")))
                    .map(str::to_owned)
                    .collect();
                pages.insert(path, (html, found));
            }
        }
    }
    pages
}

/// What is wrong with `link` on `page`, if anything.
fn check(
    dir: &Path,
    page: &Path,
    link: &str,
    pages: &BTreeMap<PathBuf, (Html, BTreeSet<String>)>,
) -> Option<String> {
    if link.contains("://") || link.starts_with("//") || link.starts_with("mailto:") {
        return None;
    }
    let (path, fragment) = link.split_once('#').unwrap_or((link, ""));
    let path = path.split('?').next().unwrap_or_default();
    let target = if path.is_empty() {
        page.to_path_buf()
    } else {
        let joined = page.parent().unwrap_or(dir).join(path);
        let joined = if path.ends_with('/') {
            joined.join("index.html")
        } else {
            joined
        };
        normalize(&joined)
    };
    if !target.starts_with(dir) || !target.exists() {
        return Some(format!("no such file {}", target.display()));
    }
    if fragment.is_empty() {
        return None;
    }
    match pages.get(&target) {
        Some((_, ids)) if ids.contains(fragment) => None,
        Some(_) => Some(format!("no anchor #{fragment} on {}", target.display())),
        None => Some(format!(
            "#{fragment} on {}, which is not a page",
            target.display()
        )),
    }
}

/// `a/b/../c` as `a/c`, without touching the file system.
fn normalize(path: &Path) -> PathBuf {
    let mut out = PathBuf::new();
    for part in path.components() {
        match part {
            std::path::Component::ParentDir => {
                out.pop();
            }
            std::path::Component::CurDir => {}
            p => out.push(p),
        }
    }
    out
}

#[test]
fn the_book_builds_and_every_internal_link_resolves() {
    let out = build();
    let dir = out.path();
    let pages = pages(dir);
    assert!(pages.len() > 20, "only {} pages built", pages.len());
    let links = Selector::parse("a[href], img[src], link[href], script[src]").unwrap();
    let mut broken = Vec::new();
    let mut checked = 0;
    for (page, (html, _)) in &pages {
        // mdBook's 404 page links relative to the site's root URL, wherever it is served.
        if page.file_name().is_some_and(|n| n == "404.html") {
            continue;
        }
        for element in html.select(&links) {
            let v = element.value();
            let Some(link) = v.attr("href").or(v.attr("src")) else {
                continue;
            };
            checked += 1;
            if let Some(problem) = check(dir, page, link, &pages) {
                let page = page.strip_prefix(dir).unwrap_or(page).display();
                broken.push(format!("{page}: {link}: {problem}"));
            }
        }
    }
    assert!(checked > 100, "only {checked} links found");
    assert!(
        broken.is_empty(),
        "{} broken links:\n{}",
        broken.len(),
        broken.join("\n")
    );
}

/// The checker itself: a page that links to a missing page and a missing anchor is caught.
#[test]
fn a_broken_link_or_anchor_is_reported() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("a.html"),
        r#"<h1 id="top">A</h1><a href="b.html">b</a>"#,
    )
    .unwrap();
    let pages = pages(dir.path());
    let page = dir.path().join("a.html");
    assert!(check(dir.path(), &page, "#top", &pages).is_none());
    assert!(check(dir.path(), &page, "a.html#top", &pages).is_none());
    assert!(check(dir.path(), &page, "https://example.com/x", &pages).is_none());
    assert!(
        check(dir.path(), &page, "b.html", &pages)
            .unwrap()
            .contains("no such file")
    );
    assert!(
        check(dir.path(), &page, "#nowhere", &pages)
            .unwrap()
            .contains("no anchor")
    );
    assert!(check(dir.path(), &page, "../outside.html", &pages).is_some());
}
