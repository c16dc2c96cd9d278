//! Reading `/proc` for teleoperation detection: the lines of `/proc/net/tcp{,6}` and
//! `/proc/PID/cmdline`, and reads of `/proc` files that cost the kernel as little as possible.

use std::fs::{self, File};
use std::io::{self, Read as _};
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr};
use std::path::{Path, PathBuf};

/// `st` of an established connection in `/proc/net/tcp` (`include/net/tcp_states.h`).
pub const TCP_ESTABLISHED: u8 = 0x01;
/// `st` of a listening socket in `/proc/net/tcp`.
pub const TCP_LISTEN: u8 = 0x0A;

/// One socket line of `/proc/net/tcp` or `/proc/net/tcp6`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TcpSocket {
    /// This host's end.
    pub local: SocketAddr,
    /// The peer's end (unspecified for a listening socket).
    pub remote: SocketAddr,
    /// Kernel TCP state, e.g. [`TCP_ESTABLISHED`] or [`TCP_LISTEN`].
    pub state: u8,
}

/// Parses one line of `/proc/net/tcp` or `/proc/net/tcp6`; `None` for the header or a line
/// of another shape.
pub fn parse_tcp_line(line: &str) -> Option<TcpSocket> {
    let mut fields = line.split_ascii_whitespace();
    let _slot = fields.next()?;
    let local = parse_hex_socket_addr(fields.next()?)?;
    let remote = parse_hex_socket_addr(fields.next()?)?;
    let state = u8::from_str_radix(fields.next()?, 16).ok()?;
    Some(TcpSocket {
        local,
        remote,
        state,
    })
}

/// Parses `0100007F:15B3` (IPv4) or `00000000000000000000000001000000:15B3` (IPv6) as the
/// kernel prints them: the address as 32-bit words in host byte order, the port in hex.
pub fn parse_hex_socket_addr(s: &str) -> Option<SocketAddr> {
    let (addr, port) = s.split_once(':')?;
    let port = u16::from_str_radix(port, 16).ok()?;
    // The kernel prints each network-order word with `%08X` as a native integer, so the
    // native-endian bytes of the parsed word are the address bytes on either endianness.
    let word = |hex: &str| u32::from_str_radix(hex, 16).ok().map(u32::to_ne_bytes);
    let ip = match addr.len() {
        8 => IpAddr::V4(Ipv4Addr::from(word(addr)?)),
        32 => {
            let mut octets = [0u8; 16];
            for (i, chunk) in octets.chunks_exact_mut(4).enumerate() {
                chunk.copy_from_slice(&word(addr.get(i * 8..i * 8 + 8)?)?);
            }
            IpAddr::V6(Ipv6Addr::from(octets))
        }
        _ => return None,
    };
    Some(SocketAddr::new(ip, port))
}

/// Whether `cmdline` (the raw bytes of `/proc/PID/cmdline`, arguments separated by NULs)
/// contains `pattern` once NULs read as spaces. Rewrites `cmdline` in place.
pub fn cmdline_contains(cmdline: &mut [u8], pattern: &[u8]) -> bool {
    let end = cmdline
        .iter()
        .rposition(|&b| b != 0)
        .map_or(0, |last| last + 1);
    let cmdline = &mut cmdline[..end];
    for b in cmdline.iter_mut() {
        if *b == 0 {
            *b = b' ';
        }
    }
    !pattern.is_empty() && cmdline.windows(pattern.len()).any(|w| w == pattern)
}

/// Bytes asked for by each `read` of a `/proc` file (at least two pages).
pub(super) const READ_CHUNK: usize = 16 * 1024;
/// What one `read` of a seq_file returns at most when the table goes on (a page, 4 KiB or
/// more) ...
pub(super) const TABLE_PAGE: usize = 4096;
/// ... and more than the longest line of `/proc/net/tcp` or `/proc/net/tcp6` (150 and about
/// 180 bytes).
const TABLE_LINE_MAX: usize = 512;

/// Reads a `/proc/net/tcp{,6}` table into `buf`.
///
/// Each time a read of these files reaches the end of the table, the kernel walks its whole
/// TCP hash table (hundreds of thousands of buckets on a machine with much memory): that walk,
/// not the few lines, is the cost of a check, and the customary read that returns 0 to confirm
/// the end does it once more. A seq_file read returns whole lines until the table ends or the
/// next line would overflow its page, so a read shorter than a page by more than a line holds
/// the table's end, and no read follows it.
pub(super) fn read_table<'a>(path: &Path, buf: &'a mut Vec<u8>) -> io::Result<&'a str> {
    let len = read_proc(path, buf, TABLE_PAGE - TABLE_LINE_MAX + 1)?;
    std::str::from_utf8(&buf[..len]).map_err(|e| io::Error::new(io::ErrorKind::InvalidData, e))
}

/// Reads the file at `path` into `buf` (which keeps its length and capacity between calls)
/// and returns its length, taking a read of fewer than `end_below` bytes (of the at least
/// [`READ_CHUNK`] asked) as its end. Unlike `read_to_end`, no `statx`, `lseek` or final empty
/// read: a `/proc` file has no size, and the empty read is what costs in `/proc/net`.
pub(super) fn read_proc(path: &Path, buf: &mut Vec<u8>, end_below: usize) -> io::Result<usize> {
    let mut file = File::open(path)?;
    let mut len = 0;
    loop {
        if buf.len() < len + READ_CHUNK {
            buf.resize(len + READ_CHUNK, 0);
        }
        match file.read(&mut buf[len..]) {
            Ok(n) => {
                len += n;
                if n == 0 || n < end_below {
                    return Ok(len);
                }
            }
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
}

/// The canonical path of `path` if it exists and differs.
pub(super) fn canonical_if_different(path: &Path) -> Option<PathBuf> {
    fs::canonicalize(path).ok().filter(|c| c != path)
}

/// `root/parts...` in the reused `scratch`.
pub(super) fn join<'a>(scratch: &'a mut PathBuf, root: &Path, parts: &[&str]) -> &'a Path {
    scratch.as_mut_os_string().clear();
    scratch.push(root);
    for part in parts {
        scratch.push(part);
    }
    scratch
}

/// `root/pid/file` in the reused `scratch`.
pub(super) fn join_pid<'a>(
    scratch: &'a mut PathBuf,
    root: &Path,
    pid: u32,
    file: &str,
) -> &'a Path {
    // Decimal digits on the stack: a `to_string()` per process per check adds up.
    let mut digits = [0u8; 10];
    let mut start = digits.len();
    let mut n = pid;
    loop {
        start -= 1;
        digits[start] = b'0' + (n % 10) as u8;
        n /= 10;
        if n == 0 {
            break;
        }
    }
    let pid = std::str::from_utf8(&digits[start..]).unwrap_or_default();
    join(scratch, root, &[pid, file])
}
