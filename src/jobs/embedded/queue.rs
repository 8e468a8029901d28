//! The embedded [`WorkQueue`]: which accepted jobs wait for a worker, in order.
//!
//! A bounded `VecDeque` rather than an mpsc channel because a queued job can be cancelled, and
//! a channel cannot remove an item from its middle. Leases live as long as the process: a job
//! a worker holds when the process dies is found `running` in the store by the next start and
//! queued again ([`super::super::ports::JobStore::recover`]), so heartbeats have nothing to
//! renew.
//!
//! Fair between tenants: a lease goes to the waiting tenant served least recently (its oldest
//! job), so a tenant that queued fifty jobs delays another tenant's one job by at most one job
//! per worker. Within a tenant the order is first in, first out.

use super::super::ports::{Lease, LeaseControl, Recovered, WorkQueue};
use super::super::{JobError, JobId};
use async_trait::async_trait;
use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use tokio::sync::Notify;

/// The in-process queue. Waiters are woken by a [`Notify`]; `notify_one` stores a permit when
/// nobody waits, so a push between a worker's empty check and its wait is never lost.
pub struct EmbeddedQueue {
    items: Mutex<Items>,
    capacity: usize,
    notify: Notify,
    /// `items.len()`, readable without the lock (`depth` is read on every metrics scrape).
    depth: AtomicUsize,
}

/// The waiting jobs, in arrival order, and when each tenant was last served.
struct Items {
    /// Jobs with how often each was delivered before (by earlier processes or clean releases).
    waiting: VecDeque<Recovered>,
    /// Tenant → the turn it was last served at (a counter); a tenant never served sorts first.
    /// Tenants without waiting jobs are dropped once it grows past the waiting ones, so it
    /// stays as small as the queue.
    served: HashMap<String, u64>,
    turn: u64,
}

impl Items {
    /// The oldest job of the waiting tenant served least recently.
    fn take_fair(&mut self) -> Option<Recovered> {
        let mut best: Option<(u64, usize)> = None;
        for (i, job) in self.waiting.iter().enumerate() {
            let last = self.served.get(&job.tenant).copied().unwrap_or(0);
            // Strictly less: the first (oldest) job of each tenant wins its tenant's ties.
            if best.is_none_or(|(b, _)| last < b) {
                best = Some((last, i));
            }
        }
        let job = self.waiting.remove(best?.1)?;
        self.turn += 1;
        self.served.insert(job.tenant.clone(), self.turn);
        if self.served.len() > 2 * self.waiting.len() + 16 {
            let waiting: std::collections::HashSet<&str> =
                self.waiting.iter().map(|j| j.tenant.as_str()).collect();
            self.served.retain(|t, _| waiting.contains(t.as_str()));
        }
        Some(job)
    }
}

impl EmbeddedQueue {
    pub fn new(capacity: usize) -> EmbeddedQueue {
        EmbeddedQueue {
            items: Mutex::new(Items {
                waiting: VecDeque::with_capacity(capacity),
                served: HashMap::new(),
                turn: 0,
            }),
            capacity,
            notify: Notify::new(),
            depth: AtomicUsize::new(0),
        }
    }

    fn items(&self) -> std::sync::MutexGuard<'_, Items> {
        // A panic while holding this lock can only come from VecDeque itself (allocation
        // failure aborts anyway); the deque is still consistent, so recover the guard.
        self.items.lock().unwrap_or_else(|p| p.into_inner())
    }
}

impl EmbeddedQueue {
    fn try_push(&self, job: Recovered) -> bool {
        {
            let mut items = self.items();
            if items.waiting.len() >= self.capacity {
                return false;
            }
            items.waiting.push_back(job);
            self.depth.store(items.waiting.len(), Ordering::Relaxed);
        }
        self.notify.notify_one();
        true
    }

    fn push_back(&self, job: Recovered) {
        {
            let mut items = self.items();
            items.waiting.push_back(job);
            self.depth.store(items.waiting.len(), Ordering::Relaxed);
        }
        self.notify.notify_one();
    }

    async fn pop(&self) -> Recovered {
        loop {
            let notified = self.notify.notified();
            let (next, more) = {
                let mut items = self.items();
                let next = items.take_fair();
                self.depth.store(items.waiting.len(), Ordering::Relaxed);
                (next, !items.waiting.is_empty())
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
        match items.waiting.iter().position(|j| j.id == id) {
            Some(i) => {
                items.waiting.remove(i);
                self.depth.store(items.waiting.len(), Ordering::Relaxed);
                true
            }
            None => false,
        }
    }
}

/// A lease on the embedded queue: `release` puts the job back at the end.
struct EmbeddedLease {
    queue: Arc<EmbeddedQueue>,
    /// The job, with its deliveries before this one.
    job: Recovered,
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
        self.queue.push_back(self.job.clone());
        Ok(())
    }
}

/// [`EmbeddedQueue`] behind the port: the `Arc` lets a lease put its job back.
#[derive(Clone)]
pub struct SharedQueue(pub Arc<EmbeddedQueue>);

#[async_trait]
impl WorkQueue for SharedQueue {
    async fn push(&self, tenant: &str, id: &str) -> Result<(), JobError> {
        let job = Recovered {
            id: JobId::parse(id)?,
            tenant: tenant.to_string(),
            delivered: 0,
        };
        if self.0.try_push(job) {
            Ok(())
        } else {
            Err(JobError::QueueFull {
                retry_after_secs: 1,
                capacity: self.0.capacity,
            })
        }
    }

    async fn push_recovered(&self, job: Recovered) -> Result<(), JobError> {
        self.0.push_back(job);
        Ok(())
    }

    async fn lease(&self) -> Result<Lease, JobError> {
        let job = self.0.pop().await;
        Ok(Lease {
            id: job.id.to_string(),
            attempt: job.delivered.saturating_add(1),
            control: Arc::new(EmbeddedLease {
                queue: self.0.clone(),
                job,
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

    fn recovered(id: &str, delivered: u32) -> Recovered {
        Recovered {
            id: JobId::parse(id).expect("hex digits: an id"),
            tenant: "t".into(),
            delivered,
        }
    }

    #[tokio::test]
    async fn bounded_fifo_with_removal_and_release() {
        let q = SharedQueue(Arc::new(EmbeddedQueue::new(2)));
        q.push("t", "a").await.expect("room");
        q.push("t", "b").await.expect("room");
        assert!(
            matches!(
                q.push("t", "c").await,
                Err(JobError::QueueFull { capacity: 2, .. })
            ),
            "a full queue refuses"
        );
        assert!(q.withdraw("a").await.expect("withdraw"));
        assert!(!q.withdraw("a").await.expect("withdraw"));
        q.push("t", "c").await.expect("room again");
        let b = q.lease().await.expect("lease");
        assert_eq!(b.id, "b");
        assert_eq!(q.depth(), 1);
        // A released lease goes to the back of the queue, whatever the capacity.
        q.push("t", "d").await.expect("room");
        b.control.release().await.expect("release");
        assert_eq!(q.depth(), 3);
        let order: Vec<String> = [
            q.lease().await.expect("lease").id,
            q.lease().await.expect("lease").id,
            q.lease().await.expect("lease").id,
        ]
        .into();
        assert_eq!(order, ["c", "d", "b"]);
        for id in ["e", "f", "e0"] {
            q.push_recovered(recovered(id, 2)).await.expect("recovered");
        }
        assert_eq!(q.depth(), 3, "recovered jobs bypass the capacity");
        assert_eq!(
            q.lease().await.expect("lease").attempt,
            3,
            "a recovered job's lease counts its earlier deliveries"
        );
    }

    #[tokio::test]
    async fn tenants_take_turns() {
        let q = SharedQueue(Arc::new(EmbeddedQueue::new(100)));
        // A burst of tenant A, then one job each of B and C, then more of A.
        for i in 0..10 {
            q.push("A", &format!("a{i}")).await.expect("room");
        }
        q.push("B", "b0").await.expect("room");
        q.push("C", "c0").await.expect("room");
        q.push("B", "b1").await.expect("room");
        let mut order = Vec::new();
        for _ in 0..6 {
            order.push(q.lease().await.expect("lease").id);
        }
        // B's and C's first jobs run within the first three leases, not after A's ten.
        assert_eq!(order, ["a0", "b0", "c0", "a1", "b1", "a2"]);
        // Within a tenant: first in, first out.
        let rest: Vec<String> = {
            let mut v = Vec::new();
            while q.depth() > 0 {
                v.push(q.lease().await.expect("lease").id);
            }
            v
        };
        assert_eq!(rest, ["a3", "a4", "a5", "a6", "a7", "a8", "a9"]);
    }
}
