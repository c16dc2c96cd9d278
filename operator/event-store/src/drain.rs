//! Draining a write queue in batches: the event, open and close flushers each take what waits
//! and write it in one statement.

use tokio::sync::mpsc;

/// Waits for one item, then takes whatever else waits already, up to `max` in all; `None` once
/// every sender is gone.
pub(super) async fn next_batch<T>(rx: &mut mpsc::Receiver<T>, max: usize) -> Option<Vec<T>> {
    let mut batch = vec![rx.recv().await?];
    while batch.len() < max {
        match rx.try_recv() {
            Ok(item) => batch.push(item),
            Err(_) => break,
        }
    }
    Some(batch)
}
