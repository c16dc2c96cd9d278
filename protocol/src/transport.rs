//! Which URLs carry credentials in plain text off this machine: the rule the agent and the CLI
//! share before they send a token anywhere.

use std::net::IpAddr;

/// Whether `host` (a URL's host: a name, an IPv4 address or a bracketed IPv6 address) is this
/// machine's loopback: `localhost`, 127.0.0.0/8 or `::1`. A name other than `localhost` is never
/// loopback, whatever it resolves to: resolution can be spoofed.
pub fn is_loopback_host(host: &str) -> bool {
    let host = host.trim_end_matches('.');
    if host.eq_ignore_ascii_case("localhost") {
        return true;
    }
    let bare = host
        .strip_prefix('[')
        .and_then(|h| h.strip_suffix(']'))
        .unwrap_or(host);
    bare.parse::<IpAddr>().is_ok_and(|ip| ip.is_loopback())
}

/// The host of `url` when it is plain text (`ws://` or `http://`) to a host other than the
/// loopback, i.e. when anyone on the path reads and changes what is sent; `None` for `wss://`,
/// `https://`, loopback URLs and anything without a `scheme://`.
pub fn plaintext_remote_host(url: &str) -> Option<&str> {
    let (scheme, rest) = url.split_once("://")?;
    if !(scheme.eq_ignore_ascii_case("ws") || scheme.eq_ignore_ascii_case("http")) {
        return None;
    }
    let authority = rest.split(['/', '?', '#']).next().unwrap_or_default();
    let host_port = authority.rsplit_once('@').map_or(authority, |(_, h)| h);
    let host = match host_port.find(']') {
        Some(end) if host_port.starts_with('[') => &host_port[..=end],
        _ => host_port.split(':').next().unwrap_or_default(),
    };
    (!is_loopback_host(host)).then_some(host)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn loopback_is_localhost_127_8_and_ipv6_one() {
        for host in [
            "localhost",
            "LOCALHOST",
            "localhost.",
            "127.0.0.1",
            "127.1.2.3",
            "127.255.255.255",
            "[::1]",
            "::1",
        ] {
            assert!(is_loopback_host(host), "{host}");
        }
        for host in [
            "192.0.2.1",
            "128.0.0.1",
            "10.0.0.1",
            "0.0.0.0",
            "[::]",
            "[::2]",
            "[::ffff:192.0.2.1]",
            "localhost.example.com",
            "mylocalhost",
            "127.0.0.1.nip.io",
            "",
        ] {
            assert!(!is_loopback_host(host), "{host}");
        }
    }

    #[test]
    fn plaintext_to_a_remote_host_is_named() {
        for (url, host) in [
            ("ws://192.0.2.1:9/v1/agent", "192.0.2.1"),
            ("http://192.0.2.1:9", "192.0.2.1"),
            ("HTTP://gw.example.com/v1", "gw.example.com"),
            ("ws://[2001:db8::1]:8081/v1/agent", "[2001:db8::1]"),
            ("ws://user@10.1.2.3/v1/agent", "10.1.2.3"),
            ("ws://127.0.0.1@evil.example/v1/agent", "evil.example"),
            ("http://localhost.evil.example:80", "localhost.evil.example"),
        ] {
            assert_eq!(plaintext_remote_host(url), Some(host), "{url}");
        }
        for url in [
            "ws://127.0.0.1:8081/v1/agent",
            "http://127.0.0.1:8081",
            "ws://localhost:8081/v1/agent",
            "http://[::1]:8081/x",
            "wss://192.0.2.1/v1/agent",
            "https://gw.example.com",
            "no scheme",
        ] {
            assert_eq!(plaintext_remote_host(url), None, "{url}");
        }
    }
}
