//! The book's pages as the tests that run them read them: their fenced code blocks.

use pulldown_cmark::{CodeBlockKind, Event, Parser, Tag, TagEnd};

/// Fenced code blocks of `markdown`, in order: (info string, code).
pub fn code_blocks(markdown: &str) -> Vec<(String, String)> {
    let mut out = Vec::new();
    let mut current: Option<(String, String)> = None;
    for event in Parser::new(markdown) {
        match event {
            Event::Start(Tag::CodeBlock(CodeBlockKind::Fenced(info))) => {
                current = Some((info.to_string(), String::new()));
            }
            Event::Text(text) => {
                if let Some((_, code)) = current.as_mut() {
                    code.push_str(&text);
                }
            }
            Event::End(TagEnd::CodeBlock) => out.extend(current.take()),
            _ => {}
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fenced_blocks_come_with_their_info_string_and_indented_ones_do_not() {
        let page = "text\n\n```sh walk=one\necho a\n```\n\n    indented\n\n```yaml\nk: v\n```\n";
        assert_eq!(
            code_blocks(page),
            [
                ("sh walk=one".to_owned(), "echo a\n".to_owned()),
                ("yaml".to_owned(), "k: v\n".to_owned())
            ]
        );
    }
}
