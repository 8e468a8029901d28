//! The embedded [`WorkQueue`]: which accepted jobs wait for a worker, in order.
//!
//! A bounded `VecDeque` rather than an mpsc channel because a queued job can be cancelled, and
//! a channel cannot remove an item from its middle. Leases live as long as the process: a job
//! a worker holds when the process dies is found `running` in the store by the next start and
//! queued again ([`super::super::ports::JobStore::recover`]), so heartbeats have nothing to
//! renew.

use super::super::ports::{Lease, LeaseControl, WorkQueue};
use super::super::{JobError, JobId};
use async_trait::async_trait;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use tokio::sync::Notify;

/// The in-process queue. Waiters are woken by a [`Notify`]; `notify_one` stores a permit when
/// nobody waits, so a push between a worker's empty check and its wait is never lost.
pub struct EmbeddedQueue {
    /// Job ids with how often each was delivered before (by earlier processes).
    items: Mutex<VecDeque<(JobId, u32)>>,
    capacity: usize,
    notify: Notify,
    /// `items.len()`, readable without the lock (`depth` is read on every metrics scrape).
    depth: AtomicUsize,
}

impl EmbeddedQueue {
    pub fn new(capacity: usize) -> EmbeddedQueue {
        EmbeddedQueue {
            items: Mutex::new(VecDeque::with_capacity(capacity)),
            capacity,
            notify: Notify::new(),
            depth: AtomicUsize::new(0),
        }
    }

    fn items(&self) -> std::sync::MutexGuard<'_, VecDeque<(JobId, u32)>> {
        // A panic while holding this lock can only come from VecDeque itself (allocation
        // failure aborts anyway); the deque is still consistent, so recover the guard.
        self.items.lock().unwrap_or_else(|p| p.into_inner())
    }
}

impl EmbeddedQueue {
    fn try_push(&self, id: JobId) -> bool {
        {
            let mut items = self.items();
            if items.len() >= self.capacity {
                return false;
            }
            items.push_back((id, 0));
            self.depth.store(items.len(), Ordering::Relaxed);
        }
        self.notify.notify_one();
        true
    }

    fn push_back(&self, id: JobId, delivered: u32) {
        {
            let mut items = self.items();
            items.push_back((id, delivered));
            self.depth.store(items.len(), Ordering::Relaxed);
        }
        self.notify.notify_one();
    }

    async fn pop(&self) -> (JobId, u32) {
        loop {
            let notified = self.notify.notified();
            let (next, more) = {
                let mut items = self.items();
                let next = items.pop_front();
                self.depth.store(items.len(), Ordering::Relaxed);
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
    }

    fn remove(&self, id: &str) -> bool {
        let mut items = self.items();
        match items.iter().position(|(x, _)| x == id) {
            Some(i) => {
                items.remove(i);
                self.depth.store(items.len(), Ordering::Relaxed);
                true
            }
            None => false,
        }
    }
}

/// A lease on the embedded queue: `release` puts the job back at the end.
struct EmbeddedLease {
    queue: Arc<EmbeddedQueue>,
    id: JobId,
    /// Deliveries before this one.
    delivered: u32,
}

#[async_trait]
impl LeaseControl for EmbeddedLease {
    async fn heartbeat(&self) -> Result<(), JobError> {
        Ok(())
    }

    async fn ack(&self) -> Result<(), JobError> {
        Ok(())
    }

    async fn release(&self) -> Result<(), JobError> {
        // A clean hand-back: the next lease is not one more delivery.
        self.queue.push_back(self.id.clone(), self.delivered);
        Ok(())
    }
}

/// [`EmbeddedQueue`] behind the port: the `Arc` lets a lease put its job back.
#[derive(Clone)]
pub struct SharedQueue(pub Arc<EmbeddedQueue>);

#[async_trait]
impl WorkQueue for SharedQueue {
    async fn push(&self, id: &str) -> Result<(), JobError> {
        if self.0.try_push(id.to_string()) {
            Ok(())
        } else {
            Err(JobError::QueueFull {
                retry_after_secs: 1,
                capacity: self.0.capacity,
            })
        }
    }

    async fn push_recovered(&self, id: &str, delivered: u32) -> Result<(), JobError> {
        self.0.push_back(id.to_string(), delivered);
        Ok(())
    }

    async fn lease(&self) -> Result<Lease, JobError> {
        let (id, delivered) = self.0.pop().await;
        Ok(Lease {
            id: id.clone(),
            attempt: delivered.saturating_add(1),
            control: Arc::new(EmbeddedLease {
                queue: self.0.clone(),
                id,
                delivered,
            }),
        })
    }

    async fn withdraw(&self, id: &str) -> Result<bool, JobError> {
        Ok(self.0.remove(id))
    }

    fn depth(&self) -> usize {
        self.0.depth.load(Ordering::Relaxed)
    }

    fn capacity(&self) -> usize {
        self.0.capacity
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn bounded_fifo_with_removal_and_release() {
        let q = SharedQueue(Arc::new(EmbeddedQueue::new(2)));
        q.push("a").await.expect("room");
        q.push("b").await.expect("room");
        assert!(
            matches!(
                q.push("c").await,
                Err(JobError::QueueFull { capacity: 2, .. })
            ),
            "a full queue refuses"
        );
        assert!(q.withdraw("a").await.expect("withdraw"));
        assert!(!q.withdraw("a").await.expect("withdraw"));
        q.push("c").await.expect("room again");
        let b = q.lease().await.expect("lease");
        assert_eq!(b.id, "b");
        assert_eq!(q.depth(), 1);
        // A released lease goes to the back of the queue, whatever the capacity.
        q.push("d").await.expect("room");
        b.control.release().await.expect("release");
        assert_eq!(q.depth(), 3);
        let order: Vec<String> = [
            q.lease().await.expect("lease").id,
            q.lease().await.expect("lease").id,
            q.lease().await.expect("lease").id,
        ]
        .into();
        assert_eq!(order, ["c", "d", "b"]);
        for id in ["e", "f", "g"] {
            q.push_recovered(id, 2).await.expect("recovered");
        }
        assert_eq!(q.depth(), 3, "recovered jobs bypass the capacity");
        assert_eq!(
            q.lease().await.expect("lease").attempt,
            3,
            "a recovered job's lease counts its earlier deliveries"
        );
    }
}
