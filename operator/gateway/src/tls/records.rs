//! Moving bytes between rustls's unbuffered states and the connection's buffers: decrypted
//! records out, encrypted records and handshake messages in, each buffer grown to what rustls
//! says it needs.

use std::io;

use rustls::unbuffered::{EncodeError, EncryptError, ReadTraffic, WriteTraffic};

use super::{MAX_FRAGMENT, RECORD_OVERHEAD, Step, Want};

/// Appends the decrypted records `traffic` holds to `plaintext`; gives the extra bytes to
/// discard from the received ones.
pub(super) fn take_records<D>(
    traffic: &mut ReadTraffic<'_, '_, D>,
    plaintext: &mut Vec<u8>,
) -> Result<usize, rustls::Error> {
    let mut discard = 0;
    while let Some(record) = traffic.next_record() {
        let record = record?;
        discard += record.discard;
        plaintext.extend_from_slice(record.payload);
    }
    Ok(discard)
}

/// Does what the connection wants when it may send: encrypts (at most one record of) the data
/// to write, or a close_notify, into `outgoing`; a read has nothing to do here.
pub(super) fn write_traffic<D>(
    traffic: &mut WriteTraffic<'_, D>,
    want: Want<'_>,
    outgoing: &mut Vec<u8>,
    close_sent: &mut bool,
) -> io::Result<Step> {
    match want {
        Want::Read => Ok(Step::Blocked),
        Want::Write(data) => {
            let n = data.len().min(MAX_FRAGMENT);
            append(outgoing, n + RECORD_OVERHEAD, |out| {
                traffic.encrypt(&data[..n], out)
            })?;
            Ok(Step::Wrote(n))
        }
        Want::Close => {
            append(outgoing, RECORD_OVERHEAD, |out| {
                traffic.queue_close_notify(out)
            })?;
            *close_sent = true;
            Ok(Step::Wrote(0))
        }
    }
}

/// rustls's errors that say a buffer was too small, and how large it must be.
pub(super) trait NeedsRoom: std::fmt::Display {
    fn required(&self) -> Option<usize>;
}

impl NeedsRoom for EncodeError {
    fn required(&self) -> Option<usize> {
        match self {
            EncodeError::InsufficientSize(e) => Some(e.required_size),
            _ => None,
        }
    }
}

impl NeedsRoom for EncryptError {
    fn required(&self) -> Option<usize> {
        match self {
            EncryptError::InsufficientSize(e) => Some(e.required_size),
            _ => None,
        }
    }
}

/// Appends what `encode` writes to `out`, first offering `room` bytes, then as many as it says
/// it needs.
pub(super) fn append<E: NeedsRoom>(
    out: &mut Vec<u8>,
    mut room: usize,
    mut encode: impl FnMut(&mut [u8]) -> Result<usize, E>,
) -> io::Result<()> {
    let start = out.len();
    loop {
        out.resize(start + room, 0);
        match encode(&mut out[start..]) {
            Ok(n) => {
                out.truncate(start + n);
                return Ok(());
            }
            Err(e) => match e.required() {
                Some(needed) if needed > room => room = needed,
                _ => {
                    out.truncate(start);
                    return Err(io::Error::other(format!("cannot encode a TLS record: {e}")));
                }
            },
        }
    }
}
