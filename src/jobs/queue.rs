//! The admission queue: which accepted jobs wait for a worker, in order.
//!
//! A trait, so a distributed backend (a work-queue stream) can replace the embedded one. The
//! embedded queue is a bounded `VecDeque` rather than an mpsc channel because a queued job can
//! be cancelled, and a channel cannot remove an item from its middle.

use super::JobId;
use std::collections::VecDeque;
use std::future::Future;
use std::pin::Pin;
use std::sync::Mutex;
use tokio::sync::Notify;

/// A bounded FIFO of job ids.
pub trait JobQueue: Send + Sync {
    /// Append if there is room; `false` when full (the caller answers "try later").
    fn try_push(&self, id: JobId) -> bool;
    /// Append regardless of capacity: jobs recovered at start were admitted before.
    fn push_recovered(&self, id: JobId);
    /// Wait for the next job id.
    fn pop(&self) -> Pin<Box<dyn Future<Output = JobId> + Send + '_>>;
    /// Remove a waiting job; `false` if it is not waiting (a worker took it, or it never was).
    fn remove(&self, id: &str) -> bool;
    fn len(&self) -> usize;
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    fn capacity(&self) -> usize;
}

/// The in-process queue. Waiters are woken by a [`Notify`]; `notify_one` stores a permit when
/// nobody waits, so a push between a worker's empty check and its wait is never lost.
pub struct EmbeddedQueue {
    items: Mutex<VecDeque<JobId>>,
    capacity: usize,
    notify: Notify,
}

impl EmbeddedQueue {
    pub fn new(capacity: usize) -> EmbeddedQueue {
        EmbeddedQueue {
            items: Mutex::new(VecDeque::with_capacity(capacity)),
            capacity,
            notify: Notify::new(),
        }
    }

    fn items(&self) -> std::sync::MutexGuard<'_, VecDeque<JobId>> {
        // A panic while holding this lock can only come from VecDeque itself (allocation
        // failure aborts anyway); the deque is still consistent, so recover the guard.
        self.items.lock().unwrap_or_else(|p| p.into_inner())
    }
}

impl JobQueue for EmbeddedQueue {
    fn try_push(&self, id: JobId) -> bool {
        {
            let mut items = self.items();
            if items.len() >= self.capacity {
                return false;
            }
            items.push_back(id);
        }
        self.notify.notify_one();
        true
    }

    fn push_recovered(&self, id: JobId) {
        self.items().push_back(id);
        self.notify.notify_one();
    }

    fn pop(&self) -> Pin<Box<dyn Future<Output = JobId> + Send + '_>> {
        Box::pin(async move {
            loop {
                let notified = self.notify.notified();
                let (next, more) = {
                    let mut items = self.items();
                    let next = items.pop_front();
                    (next, !items.is_empty())
                };
                if let Some(id) = next {
                    // Others may be waiting for further items.
                    if more {
                        self.notify.notify_one();
                    }
                    return id;
                }
                notified.await;
            }
        })
    }

    fn remove(&self, id: &str) -> bool {
        let mut items = self.items();
        match items.iter().position(|x| x == id) {
            Some(i) => {
                items.remove(i);
                true
            }
            None => false,
        }
    }

    fn len(&self) -> usize {
        self.items().len()
    }

    fn capacity(&self) -> usize {
        self.capacity
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn bounded_fifo_with_removal() {
        let q = EmbeddedQueue::new(2);
        assert!(q.try_push("a".into()));
        assert!(q.try_push("b".into()));
        assert!(!q.try_push("c".into()), "a full queue refuses");
        assert!(q.remove("a"));
        assert!(!q.remove("a"));
        assert!(q.try_push("c".into()));
        assert_eq!(q.pop().await, "b");
        assert_eq!(q.pop().await, "c");
        q.push_recovered("d".into());
        q.push_recovered("e".into());
        q.push_recovered("f".into());
        assert_eq!(q.len(), 3, "recovered jobs bypass the capacity");
    }
}
