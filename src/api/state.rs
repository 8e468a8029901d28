//! The state every HTTP handler shares, the REST routes' and the web page's alike. It lives
//! apart from both so that neither imports the other.

use crate::jobs::Jobs;
use tokio_util::sync::CancellationToken;

/// Shared by all handlers.
#[derive(Clone)]
pub struct AppState {
    pub jobs: Jobs,
    /// Cancelled when the server stops: open SSE streams end so the graceful shutdown of the
    /// HTTP server does not wait for them forever.
    pub streams_stop: CancellationToken,
}
