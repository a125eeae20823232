//! The bincode 2 configuration of the protocol, shared by the server and clients.
//!
//! The standard configuration (little-endian, variable-length integers) is what
//! `proto/README.md` specifies. Decoding untrusted bytes uses a byte limit: bincode allocates a
//! byte string's declared length before reading it, so without the limit a 10-byte message
//! could ask for gigabytes.

use serde::Serialize;
use serde::de::DeserializeOwned;

/// Most bytes a decoded request may claim (strings and byte strings together).
pub const REQUEST_DECODE_LIMIT: usize = 64 << 20;

/// Most bytes a decoded response may claim; responses come from a trusted server but are big.
pub const RESPONSE_DECODE_LIMIT: usize = 1 << 34;

/// Why bytes could not be encoded or decoded.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum WireError {
    /// The bytes are not a valid encoding of the expected message.
    Decode(String),
    /// The bytes decode, but more bytes follow the message.
    Trailing(usize),
    /// The value could not be encoded.
    Encode(String),
}

impl std::error::Error for WireError {}

impl std::fmt::Display for WireError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            WireError::Decode(e) => write!(f, "malformed bincode: {e}"),
            WireError::Trailing(n) => write!(f, "malformed bincode: {n} bytes after the message"),
            WireError::Encode(e) => write!(f, "cannot encode: {e}"),
        }
    }
}

fn config() -> bincode::config::Configuration {
    bincode::config::standard()
}

/// Encodes a message with the protocol's bincode configuration.
pub fn to_bincode<T: Serialize>(value: &T) -> Result<Vec<u8>, WireError> {
    bincode::serde::encode_to_vec(value, config()).map_err(|e| WireError::Encode(e.to_string()))
}

/// Length of a message's encoding, computed without encoding it (so that its memory can be
/// charged before it is allocated).
pub fn bincode_len<T: Serialize>(value: &T) -> Result<usize, WireError> {
    let mut w = bincode::enc::write::SizeWriter::default();
    bincode::serde::encode_into_writer(value, &mut w, config())
        .map_err(|e| WireError::Encode(e.to_string()))?;
    Ok(w.bytes_written)
}

fn finish<T>(
    r: Result<(T, usize), bincode::error::DecodeError>,
    len: usize,
) -> Result<T, WireError> {
    let (value, used) = r.map_err(|e| WireError::Decode(e.to_string()))?;
    if used != len {
        return Err(WireError::Trailing(len - used));
    }
    Ok(value)
}

/// Decodes a request (untrusted bytes): the whole slice must be one message.
pub fn request_from_bincode<T: DeserializeOwned>(bytes: &[u8]) -> Result<T, WireError> {
    let cfg = config().with_limit::<REQUEST_DECODE_LIMIT>();
    finish(bincode::serde::decode_from_slice(bytes, cfg), bytes.len())
}

/// Decodes a response: the whole slice must be one message.
pub fn response_from_bincode<T: DeserializeOwned>(bytes: &[u8]) -> Result<T, WireError> {
    let cfg = config().with_limit::<RESPONSE_DECODE_LIMIT>();
    finish(bincode::serde::decode_from_slice(bytes, cfg), bytes.len())
}

/// Appends the protocol's variable-length encoding of `n` (1, 3, 5 or 9 bytes).
pub fn put_varint(out: &mut Vec<u8>, n: u64) {
    match n {
        0..=250 => out.push(n as u8),
        251..=0xFFFF => {
            out.push(251);
            out.extend_from_slice(&(n as u16).to_le_bytes());
        }
        0x1_0000..=0xFFFF_FFFF => {
            out.push(252);
            out.extend_from_slice(&(n as u32).to_le_bytes());
        }
        _ => {
            out.push(253);
            out.extend_from_slice(&n.to_le_bytes());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn varint_matches_bincode() {
        for n in [
            0u64,
            1,
            250,
            251,
            252,
            65535,
            65536,
            u32::MAX as u64,
            u32::MAX as u64 + 1,
            u64::MAX,
        ] {
            let mut mine = Vec::new();
            put_varint(&mut mine, n);
            assert_eq!(mine, to_bincode(&n).expect("encode"), "n = {n}");
        }
    }

    #[test]
    fn a_huge_declared_length_is_refused_without_allocating() {
        // A byte string that declares 2^40 bytes, then ends.
        let mut bytes = Vec::new();
        put_varint(&mut bytes, 1 << 40);
        let r: Result<Vec<u8>, _> = request_from_bincode(&bytes);
        assert!(r.is_err());
    }
}
