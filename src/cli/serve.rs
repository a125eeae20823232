//! `crowdmorph serve`: the HTTP server. Its flags are [`ServerConfig`]'s own (each with its
//! environment variable), plus where to listen and where to keep rigs.

use std::path::PathBuf;

use anyhow::Result;
use crowdmorph::server::{self, ServerConfig};

/// Arguments of `serve`; every flag is also an environment variable.
#[derive(clap::Args)]
pub struct Args {
    /// Address to listen on.
    #[arg(long, env = "CROWDMORPH_ADDR", default_value = "127.0.0.1:8080")]
    addr: std::net::SocketAddr,
    /// Where rigs and clips are stored (default: crowdmorph under the user's data dir).
    #[arg(long, env = "CROWDMORPH_DATA_DIR")]
    data_dir: Option<PathBuf>,
    #[command(flatten)]
    config: ServerConfig,
}

impl Args {
    /// The server's configuration, as parsed.
    #[cfg(test)]
    pub fn config(&self) -> &ServerConfig {
        &self.config
    }
}

/// Runs the server until SIGINT or SIGTERM.
pub fn run(a: Args) -> Result<()> {
    let open_files = raise_open_file_limit();
    let mut config = a.config;
    config.data_dir = Some(a.data_dir.unwrap_or_else(server::default_data_dir));
    config.max_connections = Some(max_connections(config.max_connections, open_files));
    if let Some(d) = &config.data_dir {
        tracing::info!(data_dir = %d.display(), "data directory");
    }
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    runtime.block_on(async move {
        let listener = tokio::net::TcpListener::bind(a.addr)
            .await
            .map_err(|e| anyhow::anyhow!("cannot listen on {}: {e}", a.addr))?;
        server::run(listener, config, server::shutdown_signal()).await?;
        anyhow::Ok(())
    })
}

/// Descriptors kept for everything but connections: stored rig files, the engine's device
/// files, the listener, and the refused connections being answered.
const RESERVED_FILES: u64 = 320;

/// Raises the soft open-file limit to the hard one, as every connection holds a descriptor, and
/// returns the limit then in force (`None` where it cannot be read).
#[cfg(unix)]
#[allow(clippy::unnecessary_cast)] // rlim_t is u64 on Linux, not on every unix.
fn raise_open_file_limit() -> Option<u64> {
    let mut lim = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit writes one rlimit through a pointer to a live local.
    if unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut lim) } != 0 {
        return None;
    }
    if lim.rlim_cur >= lim.rlim_max {
        return Some(lim.rlim_cur as u64);
    }
    let raised = libc::rlimit {
        rlim_cur: lim.rlim_max,
        rlim_max: lim.rlim_max,
    };
    // SAFETY: setrlimit reads one rlimit through a pointer to a live local.
    if unsafe { libc::setrlimit(libc::RLIMIT_NOFILE, &raised) } == 0 {
        tracing::info!(
            from = lim.rlim_cur as u64,
            to = lim.rlim_max as u64,
            "raised the open-file limit"
        );
        Some(lim.rlim_max as u64)
    } else {
        // macOS, for one, refuses an unlimited hard limit as the soft one; the soft one stays.
        Some(lim.rlim_cur as u64)
    }
}

#[cfg(not(unix))]
fn raise_open_file_limit() -> Option<u64> {
    None
}

/// The connection cap: `--max-connections`, else the open-file limit less
/// [`RESERVED_FILES`] (at least half of it), at most 65,536 (choosing which connection to evict
/// scans the open ones).
fn max_connections(flag: Option<usize>, open_files: Option<u64>) -> usize {
    let derived = open_files.map(|limit| {
        limit
            .saturating_sub(RESERVED_FILES)
            .max(limit / 2)
            .clamp(1, 65_536)
    });
    let cap = match (flag, derived) {
        (Some(n), _) => n as u64,
        (None, Some(n)) => n,
        (None, None) => server::config::DEFAULT_MAX_CONNECTIONS as u64,
    };
    if let Some(limit) = open_files
        && cap + RESERVED_FILES > limit
    {
        tracing::warn!(
            max_connections = cap,
            open_file_limit = limit,
            "the connection cap leaves little room under the open-file limit"
        );
    }
    tracing::info!(max_connections = cap, open_file_limit = ?open_files, "connection cap");
    usize::try_from(cap).unwrap_or(usize::MAX)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_connection_cap_follows_the_flag_else_the_open_file_limit() {
        assert_eq!(max_connections(Some(10), Some(1024)), 10);
        assert_eq!(max_connections(None, Some(1024)), 704);
        assert_eq!(
            max_connections(None, Some(400)),
            200,
            "at least half the limit"
        );
        assert_eq!(max_connections(None, Some(1 << 20)), 65_536);
        assert_eq!(max_connections(None, None), 4096);
    }
}
