//! Parsing of the `Range` and `Content-Range` headers.

use super::download::{ByteRange, parse_range};
use super::upload::parse_content_range;

#[test]
fn ranges() {
    let r = |h: &str| parse_range(Some(h), 100);
    assert_eq!(parse_range(None, 100), ByteRange::Full);
    assert_eq!(r("bytes=10-"), ByteRange::Part { start: 10, end: 99 });
    assert_eq!(r("bytes=10-19"), ByteRange::Part { start: 10, end: 19 });
    assert_eq!(r("bytes=90-500"), ByteRange::Part { start: 90, end: 99 });
    assert_eq!(r("bytes=-5"), ByteRange::Part { start: 95, end: 99 });
    assert_eq!(r("bytes=-500"), ByteRange::Part { start: 0, end: 99 });
    assert_eq!(r("bytes=100-"), ByteRange::Unsatisfiable);
    assert_eq!(r("bytes=-0"), ByteRange::Unsatisfiable);
    assert_eq!(r("bytes=0-1,5-6"), ByteRange::Full);
    assert_eq!(r("bytes=5-1"), ByteRange::Full);
    assert_eq!(r("items=1-2"), ByteRange::Full);
    assert_eq!(parse_range(Some("bytes=0-"), 0), ByteRange::Unsatisfiable);
}

#[test]
fn content_ranges() {
    assert_eq!(parse_content_range("bytes 0-9/20"), Some((0, Some(9), 20)));
    assert_eq!(
        parse_content_range("bytes 10-19/20"),
        Some((10, Some(19), 20))
    );
    assert_eq!(parse_content_range("bytes */20"), Some((20, None, 20)));
    assert_eq!(parse_content_range("bytes 10-20/20"), None);
    assert_eq!(parse_content_range("bytes 5-4/20"), None);
    assert_eq!(parse_content_range("bytes 0-9/*"), None);
}
