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
