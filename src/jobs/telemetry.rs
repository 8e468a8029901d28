//! Prometheus metrics of the job core, in an explicit registry (not a process-global recorder,
//! so several servers in one test process each count their own jobs).

use super::{FailureCode, JobState};
use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{exponential_buckets, Histogram};
use prometheus_client::registry::Registry;

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct OutcomeLabels {
    /// `succeeded`, `failed` or `cancelled`.
    pub outcome: String,
    /// The error code of failed and cancelled jobs (`deadline_exceeded`, `numerical`, …), or
    /// `none`.
    pub code: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct PhaseLabels {
    /// A part of a submission: `parse` (reading and validating the mesh, on a blocking thread),
    /// `blob_put` (storing the file), `admission_wait` (waiting for this node's admission
    /// lock), `quota` (the tenant's usage), `insert` (the job record), `push` (the queue).
    pub phase: &'static str,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct QuotaLabels {
    /// `live_jobs`, `stored_bytes` or `uploads_per_minute`.
    pub quota: &'static str,
}

pub struct Telemetry {
    registry: Registry,
    pub queue_depth: Gauge,
    pub running: Gauge,
    pub submitted: Counter,
    pub rejected: Counter,
    pub outcomes: Family<OutcomeLabels, Counter>,
    pub step_seconds: Histogram,
    pub job_seconds: Histogram,
    pub checkpoint_seconds: Histogram,
    pub resumed: Counter,
    pub submit_phase_seconds: Family<PhaseLabels, Histogram>,
    pub rejected_quota: Family<QuotaLabels, Counter>,
}

impl Default for Telemetry {
    fn default() -> Self {
        Self::new()
    }
}

impl Telemetry {
    pub fn new() -> Telemetry {
        let mut registry = Registry::with_prefix("willow");
        let queue_depth = Gauge::default();
        let running = Gauge::default();
        let submitted = Counter::default();
        let rejected = Counter::default();
        let outcomes = Family::<OutcomeLabels, Counter>::default();
        // 1 ms .. ~65 s in doublings: a step on a small mesh takes milliseconds, on a 1M-face
        // mesh tens of seconds.
        let step_seconds = Histogram::new(exponential_buckets(0.001, 2.0, 17));
        // 10 ms .. ~5.8 h in quadruplings.
        let job_seconds = Histogram::new(exponential_buckets(0.01, 4.0, 12));
        // 0.1 ms .. ~3 s in doublings: a checkpoint is one blob of 24 bytes per vertex.
        let checkpoint_seconds = Histogram::new(exponential_buckets(0.0001, 2.0, 15));
        let resumed = Counter::default();
        // 50 µs .. ~3 s in doublings: where a submission's time goes, to find what makes the
        // slow ones slow under load.
        let submit_phase_seconds = Family::<PhaseLabels, Histogram>::new_with_constructor(|| {
            Histogram::new(exponential_buckets(0.00005, 2.0, 17))
        });
        let rejected_quota = Family::<QuotaLabels, Counter>::default();
        registry.register(
            "submit_phase_seconds",
            "Wall time of each part of a job submission",
            submit_phase_seconds.clone(),
        );
        registry.register(
            "jobs_rejected_quota",
            "Submissions refused because a tenant quota was spent, by quota",
            rejected_quota.clone(),
        );
        registry.register(
            "checkpoint_seconds",
            "Wall time of writing one flow checkpoint",
            checkpoint_seconds.clone(),
        );
        registry.register(
            "jobs_resumed",
            "Jobs that went on from a checkpoint after a crash, a restart or a shutdown",
            resumed.clone(),
        );
        registry.register(
            "queue_depth",
            "Jobs waiting for a worker",
            queue_depth.clone(),
        );
        registry.register(
            "jobs_running",
            "Jobs being run by a worker",
            running.clone(),
        );
        registry.register("jobs_submitted", "Jobs accepted", submitted.clone());
        registry.register(
            "jobs_rejected_queue_full",
            "Submissions refused because the queue was full",
            rejected.clone(),
        );
        registry.register(
            "jobs_finished",
            "Jobs that reached a terminal state",
            outcomes.clone(),
        );
        registry.register(
            "step_seconds",
            "Wall time of one flow step, metrics included",
            step_seconds.clone(),
        );
        registry.register(
            "job_seconds",
            "Wall time of a job from start to terminal state",
            job_seconds.clone(),
        );
        Telemetry {
            registry,
            queue_depth,
            running,
            submitted,
            rejected,
            outcomes,
            step_seconds,
            job_seconds,
            checkpoint_seconds,
            resumed,
            submit_phase_seconds,
            rejected_quota,
        }
    }

    /// Time `phase` of a submission took since `since`.
    pub fn phase(&self, phase: &'static str, since: std::time::Instant) {
        self.submit_phase_seconds
            .get_or_create(&PhaseLabels { phase })
            .observe(since.elapsed().as_secs_f64());
    }

    pub fn record_outcome(&self, state: JobState, code: Option<FailureCode>, run_ms: Option<u64>) {
        self.outcomes
            .get_or_create(&OutcomeLabels {
                outcome: state.as_str().to_string(),
                code: code.map_or("none", FailureCode::as_str).to_string(),
            })
            .inc();
        if let Some(ms) = run_ms {
            self.job_seconds.observe(ms as f64 / 1000.0);
        }
    }

    /// OpenMetrics text (which Prometheus scrapes as is).
    pub fn render(&self) -> String {
        let mut out = String::new();
        if prometheus_client::encoding::text::encode(&mut out, &self.registry).is_err() {
            // Writing into a String cannot fail; keep the endpoint answering regardless.
            out.push_str("# encoding failed\n");
        }
        out
    }
}
