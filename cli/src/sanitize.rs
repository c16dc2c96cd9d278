//! Robot-supplied text made safe to print on a terminal.
//!
//! Robots report event kinds, messages and data, names and TXT records; a hostile robot could
//! embed escape sequences that clear the screen, rewrite earlier lines, set the window title or
//! hide text from whoever runs `kubectl lekiwi`. Every control character (C0 including ESC, DEL,
//! C1) and the Unicode bidirectional overrides that reorder what is shown are printed escaped
//! as Rust writes them (`\u{1b}`), so the text stays readable and nothing reaches the terminal
//! as a command.

use std::borrow::Cow;

/// Whether `c` must not reach a terminal as is.
fn unsafe_char(c: char) -> bool {
    c.is_control() || matches!(c, '\u{202a}'..='\u{202e}' | '\u{2066}'..='\u{2069}')
}

fn escape(s: &str, keep: impl Fn(char) -> bool) -> Cow<'_, str> {
    if !s.chars().any(|c| unsafe_char(c) && !keep(c)) {
        return Cow::Borrowed(s);
    }
    let mut out = String::with_capacity(s.len() + 8);
    for c in s.chars() {
        if unsafe_char(c) && !keep(c) {
            out.push_str(&format!("\\u{{{:x}}}", c as u32));
        } else {
            out.push(c);
        }
    }
    Cow::Owned(out)
}

/// One table cell or single-line field: every control character is escaped, tab and newline
/// included (they would break the table's columns and rows).
pub fn cell(s: &str) -> Cow<'_, str> {
    escape(s, |_| false)
}

/// Multi-line text: newlines and tabs are kept, every other control character is escaped.
pub fn text(s: &str) -> Cow<'_, str> {
    escape(s, |c| c == '\n' || c == '\t')
}

/// Serialized JSON with DEL and the C1 controls (U+007F to U+009F, which serde_json leaves raw)
/// written as `\u00XX` escapes: the same JSON value, and nothing a terminal acts on. Such
/// characters can only occur inside JSON strings, where the escape is valid.
pub fn json(s: String) -> String {
    if !s.chars().any(|c| matches!(c, '\u{7f}'..='\u{9f}')) {
        return s;
    }
    let mut out = String::with_capacity(s.len() + 16);
    for c in s.chars() {
        if matches!(c, '\u{7f}'..='\u{9f}') {
            out.push_str(&format!("\\u{:04x}", c as u32));
        } else {
            out.push(c);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plain_text_is_untouched_and_borrowed() {
        for s in ["", "agent_started", "wheel 3: 1.5 A", "ünïcødé ✓ 机器人"] {
            assert!(matches!(cell(s), Cow::Borrowed(x) if x == s));
            assert!(matches!(text(s), Cow::Borrowed(x) if x == s));
        }
    }

    #[test]
    fn escape_sequences_are_shown_escaped() {
        assert_eq!(cell("\x1b[2Jgone"), "\\u{1b}[2Jgone");
        assert_eq!(cell("\x1b]0;title\x07"), "\\u{1b}]0;title\\u{7}");
        assert_eq!(cell("a\rb\x08c\x7f"), "a\\u{d}b\\u{8}c\\u{7f}");
        // C1: the single-character CSI and OSC.
        assert_eq!(cell("\u{9b}2J\u{9d}"), "\\u{9b}2J\\u{9d}");
        // Bidirectional overrides reorder what is displayed.
        assert_eq!(cell("ok\u{202e}txt.exe"), "ok\\u{202e}txt.exe");
        assert_eq!(cell("\u{2066}x\u{2069}"), "\\u{2066}x\\u{2069}");
        assert_eq!(cell("\0"), "\\u{0}");
    }

    #[test]
    fn cells_escape_tabs_and_newlines_text_keeps_them() {
        assert_eq!(cell("a\tb\nc"), "a\\u{9}b\\u{a}c");
        assert_eq!(text("a\tb\nc\x1b[1m"), "a\tb\nc\\u{1b}[1m");
    }

    #[test]
    fn structured_output_holds_no_raw_control_character() {
        let value = serde_json::json!({ "m": "\x1b[2J\u{7f}\u{9b}1m\u{85}é" });
        let text = json(serde_json::to_string_pretty(&value).unwrap());
        assert!(!text.chars().any(|c| c.is_control() && c != '\n'), "{text}");
        assert!(text.contains(r"\u001b[2J\u007f\u009b1m\u0085é"), "{text}");
        assert_eq!(
            serde_json::from_str::<serde_json::Value>(&text).unwrap(),
            value
        );
        let yaml = serde_yaml::to_string(&value).unwrap();
        assert!(!yaml.chars().any(|c| c.is_control() && c != '\n'), "{yaml}");
        assert_eq!(
            serde_yaml::from_str::<serde_json::Value>(&yaml).unwrap(),
            value
        );
    }

    #[test]
    fn nothing_unsafe_survives() {
        let every: String = (0u32..0x3000).filter_map(char::from_u32).collect();
        for out in [cell(&every), text(&every)] {
            assert!(
                !out.chars()
                    .any(|c| unsafe_char(c) && c != '\n' && c != '\t')
            );
        }
        assert!(!cell(&every).contains(['\n', '\t']));
    }
}
