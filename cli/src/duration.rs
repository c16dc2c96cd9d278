//! Durations on the command line, one syntax for every flag: jiff's friendly format (`30s`,
//! `5m`, `1h30m`, `500ms`, `1.5s`, `2d`, also `1 hour 30 minutes` and ISO 8601 `PT1H30M`); a
//! bare number is seconds.

use std::time::Duration;

use jiff::{Span, SpanRelativeTo};

/// Parses a duration (a day is 24 hours; weeks, months and years are refused).
pub fn parse(s: &str) -> Result<Duration, String> {
    let s = s.trim();
    let bare = !s.is_empty() && s.chars().all(|c| c.is_ascii_digit() || c == '.');
    let text = if bare { format!("{s}s") } else { s.to_owned() };
    let span: Span = text
        .parse()
        .map_err(|e| format!("{s:?} is not a duration such as 30s, 5m or 1h30m: {e}"))?;
    let signed = span
        .to_duration(SpanRelativeTo::days_are_24_hours())
        .map_err(|e| format!("{s:?}: use units from ms to days: {e}"))?;
    Duration::try_from(signed).map_err(|_| format!("{s:?}: a duration cannot be negative"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn units() {
        assert_eq!(parse("1.5s"), Ok(Duration::from_millis(1500)));
        assert_eq!(parse("250ms"), Ok(Duration::from_millis(250)));
        assert_eq!(parse("1h"), Ok(Duration::from_secs(3600)));
        assert_eq!(parse("1h30m"), Ok(Duration::from_secs(5400)));
        assert_eq!(parse("2d"), Ok(Duration::from_secs(172_800)));
        assert_eq!(parse("3"), Ok(Duration::from_secs(3)));
        assert_eq!(parse("0"), Ok(Duration::ZERO));
        assert_eq!(parse("PT5M"), Ok(Duration::from_secs(300)));
        assert!(parse("1y").is_err());
        assert!(parse("s").is_err());
        assert!(parse("-5s").is_err());
    }
}
