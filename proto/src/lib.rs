//! Wire types of the crowdmorph protocol.
//!
//! This crate is deliberately small and dependency-light so that clients can share it with the
//! server. The byte-level specification lives in `proto/README.md`; the types here are the Rust
//! mirror of that document.

/// Version of the wire protocol spoken by this crate.
pub const PROTOCOL_VERSION: u32 = 1;
