//! What a session viewer's socket is sent, once the tick has decided it: temporal residuals
//! planned against what the viewer last took and packed messages ([`delta`]), and the messages
//! encoded ([`encode`]). Both take the queue memory, not the server state: they charge their
//! bytes and do nothing else of the server's.
//!
//! | module | what it is |
//! |---|---|
//! | [`delta`] | temporal residuals against each viewer's baseline, and packed (zstd, zlib) messages |
//! | [`encode`] | vertex, delta and layer messages encoded, their bytes charged before they are allocated |
//! | [`poses`] | a weights viewer's poses message encoded, charged before it is allocated |

pub(crate) mod delta;
pub(crate) mod encode;
pub(crate) mod poses;
