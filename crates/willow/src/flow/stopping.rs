//! Stopping rules: when a run of a [`Flow`] ends, and why ([`Outcome`]).
//!
//! [`Run`] drives a flow for at most a number of steps and stops earlier when
//!
//! - the Willmore energy reaches `FlowParams::until_willmore` ([`Outcome::TargetReached`]);
//! - W stopped falling (unless `FlowParams::until_converged` is off): its relative change `|W_k − W_{k−1}| / W_{k−1}`, scaled to the
//!   requested τ (a step the safeguard took at τ/8 counts eight times its change: the flow's
//!   rate, not the step's size, says whether it converged), stayed below
//!   [`CONVERGED_TOLERANCE`] for [`CONVERGED_WINDOW`] steps in a row, or the change itself is
//!   below the noise floor [`NOISE_FLOOR`] ([`Outcome::Converged`]). A window, not one step:
//!   three quiet steps in a row span a τ doubling (`safeguard::GROW_AFTER`);
//! - the safeguard held τ at or below `τ/2^`[`STALL_HALVINGS`] for [`STALL_WINDOW`] steps in a
//!   row while W still fell: the flow is crawling because every larger step would damage the
//!   surface ([`Outcome::Stalled`], with the safeguard's last reason). The result is the last
//!   sound surface (issue 26: before, such runs ended "converged" at W/4π 19 on cheburashka);
//! - the next step would move the surface further than `FlowParams::max_deviation` from the
//!   input (`StepMetrics::deviation_max`, model units) ([`Outcome::MaxDeviation`]): that step
//!   is undone (the flow is resumed from the checkpoint taken before it), so the result is
//!   the last surface within the bound, and no step past it is ever reported;
//! - the detail below `FlowParams::feature_size` is gone: the energy of the curvature in the
//!   band the feature scale removes has fallen to [`super::feature::DETAIL_TOLERANCE`] of the
//!   input's ([`Outcome::FeatureScaleReached`]);
//! - the safeguard found no acceptable step ([`FlowError::NoProgress`], [`Outcome::NoProgress`]):
//!   the flow is still on the last accepted surface; when every try was refused only for a
//!   rise of W within the solver's accuracy, that surface is a minimum and the run ends
//!   [`Outcome::Converged`] instead (issue 26, item 6);
//! - the mesh is too coarse to become fairer ([`Outcome::AlreadyFair`]): before any step, its
//!   Willmore energy is at or below the least any closed surface of its genus can have
//!   ([`Flow::willmore_lower_bound`]: 4π for a sphere, 2π² for genus ≥ 1 by Marques and Neves
//!   2014, 0 with boundary) — a discrete W there means the tessellation, not the shape, sets
//!   it (a cylinder with fan caps has W = 12.0 < 4π); or the first step moved nothing (W and
//!   area both unchanged to [`STILL_TOLERANCE`]: a flat washer, whose H vanishes).
//!
//! Otherwise it ends [`Outcome::Completed`] after its steps. When one step meets several
//! rules, the target beats the feature scale, which beats convergence, which beats completion
//! (the most specific reason).

use super::{Flow, FlowError, FlowParams, FlowState};
use crate::metrics::StepMetrics;
use serde::{Deserialize, Serialize};

/// Relative change of W per step below which a step counts as quiet.
pub const CONVERGED_TOLERANCE: f64 = 1e-4;
/// Quiet steps in a row after which a run has converged.
pub const CONVERGED_WINDOW: usize = 3;

/// A relative change of W this small is rounding and solver tolerance whatever τ was (ten
/// times the safeguard's `W_RISE`).
pub const NOISE_FLOOR: f64 = 1e-5;
/// A step taken at τ ≤ requested/2^this is a crawl.
pub const STALL_HALVINGS: i32 = 4;
/// Crawling steps in a row after which a run has stalled.
pub const STALL_WINDOW: usize = 5;
/// A run that ends at a "minimum" while its flow kept less than this part of the requested
/// curvature change ([`Flow::kept_share`]) says so: it stopped where its held border lets a
/// conformal flow go, not at a minimum of W (docs/algorithm.md §12).
pub const KEPT_SHARE_NOTE: f64 = 0.5;

/// Relative change of W and of the area below which the first step counts as not moving.
pub const STILL_TOLERANCE: f64 = 1e-12;

/// How a run ended (module docs).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Outcome {
    /// Ran all its steps.
    Completed,
    /// W stopped falling.
    Converged,
    /// The safeguard let only tiny steps through for several steps: larger ones would have
    /// damaged the surface (the reason says how). The result is the last sound surface.
    Stalled,
    /// W reached `until_willmore`.
    TargetReached,
    /// The next step would have passed `max_deviation`; the result is the step before.
    MaxDeviation,
    /// The safeguard found no acceptable step.
    NoProgress,
    /// The detail below `feature_size` is gone: the energy of its band fell to
    /// [`super::feature::DETAIL_TOLERANCE`] of the input's.
    FeatureScaleReached,
    /// The mesh is too coarse to be made fairer: its W is at or below its genus's bound, or
    /// the first step did not move it.
    AlreadyFair,
}

impl Outcome {
    /// Every outcome: the `match` in [`Outcome::name`] makes a new one a compile error until
    /// it is named, and so listed here.
    pub const ALL: [Outcome; 8] = [
        Outcome::Completed,
        Outcome::Converged,
        Outcome::TargetReached,
        Outcome::MaxDeviation,
        Outcome::NoProgress,
        Outcome::FeatureScaleReached,
        Outcome::AlreadyFair,
        Outcome::Stalled,
    ];

    /// The outcome of a name ([`Outcome::name`]); `None` for any other text.
    pub fn parse(name: &str) -> Option<Outcome> {
        Outcome::ALL.into_iter().find(|o| o.name() == name)
    }

    /// The one name of an outcome (its JSON form).
    pub const fn name(self) -> &'static str {
        match self {
            Outcome::Completed => "completed",
            Outcome::Converged => "converged",
            Outcome::TargetReached => "target_reached",
            Outcome::MaxDeviation => "max_deviation",
            Outcome::NoProgress => "no_progress",
            Outcome::FeatureScaleReached => "feature_scale_reached",
            Outcome::AlreadyFair => "already_fair",
            Outcome::Stalled => "stalled",
        }
    }
}

/// What [`Run::advance`] has to say.
#[derive(Clone, Debug, PartialEq)]
pub enum Event {
    /// A step was taken and kept: its metrics.
    Step(StepMetrics),
    /// The run is over; the flow holds its result. Returned again by every later call.
    Stopped { outcome: Outcome, reason: String },
}

/// A flow run to its end under the stopping rules of its [`FlowParams`] (module docs).
pub struct Run {
    flow: Box<dyn Flow>,
    steps: usize,
    until_willmore: Option<f64>,
    until_converged: bool,
    max_deviation: Option<f64>,
    /// The metrics of the surface the flow is on.
    last: StepMetrics,
    /// Consecutive steps whose relative change of W was below [`CONVERGED_TOLERANCE`].
    quiet: usize,
    /// Consecutive steps taken at τ ≤ requested/2^[`STALL_HALVINGS`].
    crawling: usize,
    /// The requested τ.
    tau: f64,
    /// Decided after the step just reported; returned by the next call.
    stop: Option<(Outcome, String)>,
    /// Where the flow was before the step being tried, when `max_deviation` may undo it.
    before: Option<FlowState>,
}

impl Run {
    /// A run of at most `steps` steps of `flow`, stopping as `params` asks (its
    /// `until_willmore` and `max_deviation`, checked here as `FlowParams::validate` does).
    /// `max_deviation` needs a flow that can go back a step (every flow [`super::new_flow`]
    /// builds can); for one that cannot it is [`FlowError::Unsupported`].
    pub fn new(flow: Box<dyn Flow>, params: &FlowParams, steps: usize) -> Result<Run, FlowError> {
        params.validate()?;
        if params.max_deviation.is_some() && flow.checkpoint().is_none() {
            return Err(FlowError::Unsupported(
                "max_deviation needs a flow that can undo a step (checkpoint and resume)".into(),
            ));
        }
        Ok(Run {
            last: flow.initial_metrics(),
            flow,
            steps,
            until_willmore: params.until_willmore,
            until_converged: params.until_converged,
            max_deviation: params.max_deviation,
            quiet: 0,
            crawling: 0,
            tau: params.tau,
            stop: None,
            before: None,
        })
    }

    /// [`Run::new`] for a flow already put back on `state` ([`Flow::resume`]), a checkpoint
    /// of a run ([`Run::checkpoint`]): the run counts its steps from `state.metrics.step`,
    /// and the rules that look back (convergence, stalling) go on from the counts it holds
    /// (a flow's own checkpoint holds none: they start afresh there).
    pub fn resumed(
        flow: Box<dyn Flow>,
        params: &FlowParams,
        steps: usize,
        state: &FlowState,
    ) -> Result<Run, FlowError> {
        let mut run = Run::new(flow, params, steps)?;
        run.last = state.metrics;
        run.quiet = state.carried.quiet_steps as usize;
        run.crawling = state.carried.crawling_steps as usize;
        Ok(run)
    }

    /// The flow's checkpoint ([`Flow::checkpoint`]) with what the stopping rules have
    /// counted so far, so that [`Run::resumed`] stops where this run would have.
    pub fn checkpoint(&self) -> Option<FlowState> {
        let mut state = self.flow.checkpoint()?;
        state.carried.quiet_steps = u32::try_from(self.quiet).unwrap_or(u32::MAX);
        state.carried.crawling_steps = u32::try_from(self.crawling).unwrap_or(u32::MAX);
        Some(state)
    }

    /// Whether the run has decided to stop: the next [`Run::advance`] takes no step and says
    /// why. (A caller that checks for cancellation between steps has nothing to cancel then.)
    pub fn is_over(&self) -> bool {
        self.stop.is_some() || self.stop_before_stepping().is_some()
    }

    /// The flow, on the surface of the last step reported (or the input).
    pub fn flow(&self) -> &dyn Flow {
        self.flow.as_ref()
    }

    /// The flow, given back once the run is over (or abandoned).
    pub fn into_flow(self) -> Box<dyn Flow> {
        self.flow
    }

    /// The metrics of the surface the flow is on.
    pub fn last_metrics(&self) -> &StepMetrics {
        &self.last
    }

    /// Take the next step, or say why the run is over. Errors other than
    /// [`FlowError::NoProgress`] (a numerical failure) end the run as errors.
    pub fn advance(&mut self) -> Result<Event, FlowError> {
        if let Some((outcome, reason)) = &self.stop {
            return Ok(Event::Stopped {
                outcome: *outcome,
                reason: reason.clone(),
            });
        }
        if let Some(stop) = self.stop_before_stepping() {
            return Ok(self.finish(stop));
        }
        if self.max_deviation.is_some() {
            self.before = self.flow.checkpoint();
        }
        let metrics = match self.flow.step() {
            Ok(m) => m,
            Err(FlowError::NoProgress {
                at_minimum: true,
                step,
                tau,
                reason,
            }) => {
                let mut reason = format!(
                    "Willmore energy {:.6} is at a minimum to the solver's accuracy: no try of \
                     step {step} down to tau = {tau:e} lowered it, and the smallest raised it by \
                     less than {:e} (relative; last: {reason})",
                    self.last.willmore_energy,
                    super::safeguard::MINIMUM_RISE
                );
                if let Some(kept) = self.flow.kept_share().filter(|&k| k < KEPT_SHARE_NOTE) {
                    reason.push_str(&format!(
                        "; a minimum of what the held border lets a conformal flow do, not of W: \
                         the curvature change the border cannot realize, absorbed, left {kept:.2} \
                         of the requested change"
                    ));
                }
                return Ok(self.finish((Outcome::Converged, reason)));
            }
            Err(e @ FlowError::NoProgress { .. }) => {
                return Ok(self.finish((Outcome::NoProgress, e.to_string())));
            }
            Err(e) => return Err(e),
        };
        if let Some(bound) = self.max_deviation {
            // `max_deviation` turns the measurement on (`FlowParams::measures_deviation`).
            let deviation = metrics.deviation_max.unwrap_or(f64::INFINITY);
            if deviation > bound {
                let state = self.before.take().ok_or_else(|| {
                    FlowError::Unsupported("the flow gave no checkpoint to undo a step".into())
                })?;
                self.flow.resume(&state)?;
                let reason = format!(
                    "step {} would move the surface {:.6e} from the input, past max_deviation \
                     {bound:.6e}; the result is the surface after step {} ({:.6e} from the input)",
                    metrics.step,
                    deviation,
                    self.last.step,
                    self.last.deviation_max.unwrap_or(0.0)
                );
                return Ok(self.finish((Outcome::MaxDeviation, reason)));
            }
        }
        self.stop = self.stop_after(&metrics);
        self.last = metrics;
        Ok(Event::Step(metrics))
    }

    /// Rules decided on the surface the flow is on, before any step: a run of 0 steps, a
    /// run that has taken all of them, an input already at the target.
    fn stop_before_stepping(&self) -> Option<(Outcome, String)> {
        if let Some(target) = self.until_willmore {
            if self.last.step == 0 && self.last.willmore_energy <= target {
                return Some((
                    Outcome::TargetReached,
                    format!(
                        "the input's Willmore energy {:.6} is already at most until_willmore {target}",
                        self.last.willmore_energy
                    ),
                ));
            }
        }
        if let Some(d) = self.flow.feature_detail() {
            if self.last.step == 0 && d.reached() {
                return Some((
                    Outcome::FeatureScaleReached,
                    format!(
                        "the input holds no detail below feature_size (band energy {:.6e})",
                        d.current
                    ),
                ));
            }
        }
        if self.last.step == 0 && self.steps > 0 {
            if let Some(bound) = self.flow.willmore_lower_bound() {
                let w = self.last.willmore_energy;
                if w <= bound {
                    return Some((
                        Outcome::AlreadyFair,
                        format!(
                            "the mesh is too coarse to be made fairer: its Willmore energy \
                             {w:.6} is already at or below {bound:.6}, the least any smooth \
                             surface of its topology has, so its tessellation, not its shape, \
                             sets it (refine the mesh to fair it)"
                        ),
                    ));
                }
            }
        }
        if let Some(reason) = self.flow.finished() {
            let outcome = if self.last.step == 0 {
                Outcome::AlreadyFair
            } else {
                Outcome::Completed
            };
            return Some((outcome, reason));
        }
        (self.last.step >= self.steps)
            .then(|| (Outcome::Completed, format!("ran its {} steps", self.steps)))
    }

    /// Rules decided on a step just taken (most specific first: see the module docs).
    fn stop_after(&mut self, m: &StepMetrics) -> Option<(Outcome, String)> {
        let w0 = self.last.willmore_energy;
        let change = (w0 - m.willmore_energy).abs() / w0.abs().max(f64::MIN_POSITIVE);
        // τ of the step against the requested one (flows that do not report τ took it whole).
        let fraction = if m.tau > 0.0 {
            (m.tau / self.tau).min(1.0)
        } else {
            1.0
        };
        self.quiet = if change < NOISE_FLOOR || change < CONVERGED_TOLERANCE * fraction {
            self.quiet + 1
        } else {
            0
        };
        self.crawling = if fraction <= 0.5f64.powi(STALL_HALVINGS) {
            self.crawling + 1
        } else {
            0
        };
        if let Some(target) = self.until_willmore {
            if m.willmore_energy <= target {
                return Some((
                    Outcome::TargetReached,
                    format!(
                        "Willmore energy {:.6} at step {} is at most until_willmore {target}",
                        m.willmore_energy, m.step
                    ),
                ));
            }
        }
        if let Some(d) = self.flow.feature_detail() {
            if d.reached() {
                return Some((
                    Outcome::FeatureScaleReached,
                    format!(
                        "the detail below feature_size is gone at step {}: its band's energy \
                         {:.6e} is {:.2e} of the input's {:.6e} (at most {:e})",
                        m.step,
                        d.current,
                        d.current / d.initial,
                        d.initial,
                        super::feature::DETAIL_TOLERANCE
                    ),
                ));
            }
        }
        let relative = |a: f64, b: f64| (a - b).abs() / a.abs().max(b.abs()).max(f64::MIN_POSITIVE);
        if m.step == 1
            && relative(w0, m.willmore_energy) <= STILL_TOLERANCE
            && relative(self.last.area, m.area) <= STILL_TOLERANCE
        {
            return Some((
                Outcome::AlreadyFair,
                format!(
                    "the mesh is too coarse to be made fairer: the first step left its Willmore \
                     energy ({w0:.6}) and area unchanged, so there is nothing this \
                     tessellation can represent that is fairer (refine the mesh to fair it)"
                ),
            ));
        }
        if self.until_converged && self.quiet >= CONVERGED_WINDOW {
            return Some((
                Outcome::Converged,
                format!(
                    "Willmore energy changed by less than {CONVERGED_TOLERANCE:e} (relative) per \
                     step for {CONVERGED_WINDOW} steps, to {:.6} at step {}",
                    m.willmore_energy, m.step
                ),
            ));
        }
        if self.crawling >= STALL_WINDOW {
            let why = self
                .flow
                .last_refusal()
                .unwrap_or_else(|| "not kept".into());
            return Some((
                Outcome::Stalled,
                format!(
                    "stalled at step {}: the last {STALL_WINDOW} steps were taken at tau \
                     {:e} or less (requested {:e}): the safeguard refused larger ones (last \
                     refusal: {why}); the result is the last sound surface, Willmore \
                     energy {:.6}",
                    m.step,
                    self.tau * 0.5f64.powi(STALL_HALVINGS),
                    self.tau,
                    m.willmore_energy
                ),
            ));
        }
        (m.step >= self.steps)
            .then(|| (Outcome::Completed, format!("ran its {} steps", self.steps)))
    }

    fn finish(&mut self, stop: (Outcome, String)) -> Event {
        let event = Event::Stopped {
            outcome: stop.0,
            reason: stop.1.clone(),
        };
        self.stop = Some(stop);
        event
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::flow::{new_flow, Method};
    use crate::geometry::distance::Deviation;
    use crate::geometry::operators::face_areas_into;
    use crate::mesh::generate::bumpy_sphere;
    use crate::mesh::topology::Topology;
    use crate::mesh::Mesh;

    /// Every event of a run until it stops.
    fn drive(mesh: &Mesh, params: &FlowParams, steps: usize) -> (Vec<StepMetrics>, Outcome, Run) {
        let flow = new_flow(mesh, params).expect("flow");
        let mut run = Run::new(flow, params, steps).expect("run");
        let mut metrics = Vec::new();
        loop {
            match run.advance().expect("no numerical failure") {
                Event::Step(m) => metrics.push(m),
                Event::Stopped { outcome, reason } => {
                    assert!(!reason.is_empty());
                    // Asking again gives the same answer and takes no step.
                    assert!(matches!(
                        run.advance(),
                        Ok(Event::Stopped { outcome: o, .. }) if o == outcome
                    ));
                    return (metrics, outcome, run);
                }
            }
        }
    }

    #[test]
    fn a_run_without_rules_completes_its_steps() {
        let mesh = bumpy_sphere(2, 0.1);
        let (metrics, outcome, _) = drive(&mesh, &FlowParams::default(), 2);
        assert_eq!(outcome, Outcome::Completed);
        assert_eq!(metrics.len(), 2);
        let (metrics, outcome, _) = drive(&mesh, &FlowParams::default(), 0);
        assert_eq!((metrics.len(), outcome), (0, Outcome::Completed));
    }

    /// A run resumed from a checkpoint after step 2 reports steps 3 and 4 of a 4-step run,
    /// the surfaces of the run that never stopped, and completes.
    #[test]
    fn a_resumed_run_counts_from_its_checkpoint() {
        let mesh = bumpy_sphere(2, 0.1);
        let params = FlowParams::default();
        let (whole, _, _) = drive(&mesh, &params, 4);
        let mut first = Run::new(new_flow(&mesh, &params).expect("flow"), &params, 2).expect("run");
        while let Event::Step(_) = first.advance().expect("steps") {}
        let state = first.checkpoint().expect("a checkpoint");
        let mut flow = new_flow(&mesh, &params).expect("flow");
        flow.resume(&state).expect("resumes");
        let mut run = Run::resumed(flow, &params, 4, &state).expect("run");
        let mut steps = Vec::new();
        let outcome = loop {
            match run.advance().expect("steps") {
                Event::Step(m) => steps.push(m),
                Event::Stopped { outcome, .. } => break outcome,
            }
        };
        assert_eq!(outcome, Outcome::Completed);
        assert_eq!(steps.iter().map(|m| m.step).collect::<Vec<_>>(), [3, 4]);
        // The same surface up to rounding (the resumed flow rebuilds its factorizations).
        let (resumed, straight) = (steps[1].willmore_energy, whole[3].willmore_energy);
        assert!(
            (resumed - straight).abs() <= 1e-12 * straight,
            "{resumed} vs {straight}"
        );
    }

    /// A run checkpointed inside its convergence window ([`Run::checkpoint`]) and resumed
    /// stops `converged` at the step the uninterrupted run stops at, not a whole window
    /// later: the quiet steps counted before the checkpoint still count.
    #[test]
    fn a_resumed_run_converges_where_the_uninterrupted_one_does() {
        let mesh = bumpy_sphere(3, 0.05);
        let params = FlowParams::default();
        let (whole, outcome, _) = drive(&mesh, &params, 100);
        assert_eq!(outcome, Outcome::Converged);
        let last = whole.len();
        // One step before the end: the window holds CONVERGED_WINDOW − 1 quiet steps.
        let at = last - 1;
        let mut first =
            Run::new(new_flow(&mesh, &params).expect("flow"), &params, 100).expect("run");
        for _ in 0..at {
            assert!(matches!(first.advance().expect("steps"), Event::Step(_)));
        }
        let state = first.checkpoint().expect("a checkpoint");
        assert_eq!(state.metrics.step, at);
        assert_eq!(state.carried.quiet_steps as usize, CONVERGED_WINDOW - 1);
        let resume = |state: &FlowState| {
            let mut flow = new_flow(&mesh, &params).expect("flow");
            flow.resume(state).expect("resumes");
            let mut run = Run::resumed(flow, &params, 100, state).expect("run");
            let mut steps = 0;
            loop {
                match run.advance().expect("steps") {
                    Event::Step(_) => steps += 1,
                    Event::Stopped { outcome, .. } => return (steps, outcome),
                }
            }
        };
        assert_eq!(resume(&state), (1, Outcome::Converged));
        // A flow's own checkpoint counts nothing: its run needs a whole window again.
        let plain = first.flow().checkpoint().expect("a checkpoint");
        assert_eq!(plain.carried.quiet_steps, 0);
        assert!(resume(&plain).0 >= CONVERGED_WINDOW);
    }

    /// A wide fixed-seam cap on a bumpy sphere: its held border forbids most of what the
    /// flow asks, the absorbed change comes to reverse the request (kept share −0.19 at step
    /// 3, docs/algorithm.md §12), every try of step 3 raises W, and the run ends `converged`
    /// saying that this is the border's limit, not a minimum of W.
    #[test]
    fn a_region_stopped_by_its_held_border_says_so() {
        use crate::flow::region::{Region, Seam};
        let mesh = bumpy_sphere(3, 0.15);
        let params = FlowParams {
            regions: vec![Region::Sphere {
                center: mesh.positions[0],
                radius: 0.6,
            }],
            seam: Seam::Fixed,
            until_converged: false,
            ..FlowParams::default()
        };
        let flow = new_flow(&mesh, &params).expect("flow");
        let mut run = Run::new(flow, &params, 10).expect("run");
        let (outcome, reason) = loop {
            match run.advance().expect("steps") {
                Event::Step(_) => {}
                Event::Stopped { outcome, reason } => break (outcome, reason),
            }
        };
        assert_eq!(outcome, Outcome::Converged, "{reason}");
        assert!(run.last_metrics().step < 10, "{reason}");
        assert!(reason.contains("held border"), "{reason}");
        let kept = run.flow().kept_share().expect("a region flow absorbs");
        eprintln!("{reason}; kept {kept}");
        assert!(kept < KEPT_SHARE_NOTE, "kept {kept}");
        // A whole-surface flow absorbs nothing.
        let whole = new_flow(&mesh, &FlowParams::default()).expect("flow");
        assert_eq!(whole.kept_share(), None);
    }

    /// A slightly bumpy sphere at τ 0.5 reaches its round minimum within a few steps and
    /// stays there: the run ends `converged` long before its 100 steps, with W near 4π and
    /// the last steps quiet.
    #[test]
    fn a_converging_flow_ends_converged() {
        let mesh = bumpy_sphere(3, 0.05);
        let (metrics, outcome, _) = drive(&mesh, &FlowParams::default(), 100);
        assert_eq!(outcome, Outcome::Converged, "after {} steps", metrics.len());
        assert!(metrics.len() < 30, "{} steps", metrics.len());
        let n = metrics.len();
        for pair in metrics[n - CONVERGED_WINDOW - 1..].windows(2) {
            let change =
                (pair[0].willmore_energy - pair[1].willmore_energy).abs() / pair[0].willmore_energy;
            assert!(change < CONVERGED_TOLERANCE, "{change}");
        }
        let w = metrics[n - 1].willmore_energy;
        assert!(
            (w / (4.0 * std::f64::consts::PI) - 1.0).abs() < 0.01,
            "W = {w}"
        );
    }

    /// The run stops at the first step whose W is at most the target, not before, not after.
    #[test]
    fn until_willmore_ends_target_reached_at_the_first_step_below() {
        let mesh = bumpy_sphere(3, 0.15);
        let free = drive(&mesh, &FlowParams::default(), 8).0;
        // A target between the energies after steps 2 and 3 of the same flow.
        let target = 0.5 * (free[1].willmore_energy + free[2].willmore_energy);
        let params = FlowParams {
            until_willmore: Some(target),
            ..FlowParams::default()
        };
        let (metrics, outcome, _) = drive(&mesh, &params, 8);
        assert_eq!(outcome, Outcome::TargetReached);
        assert_eq!(metrics.len(), 3);
        assert!(metrics[2].willmore_energy <= target);
        assert!(metrics[1].willmore_energy > target);
        // An input already below the target takes no step.
        let params = FlowParams {
            until_willmore: Some(1e9),
            ..FlowParams::default()
        };
        let (metrics, outcome, _) = drive(&mesh, &params, 8);
        assert_eq!((metrics.len(), outcome), (0, Outcome::TargetReached));
    }

    /// With a bound between the deviations after steps 2 and 3 of the free flow, the run
    /// reports steps 1 and 2 only, ends `max_deviation`, and the flow is back on the surface
    /// after step 2: within the bound, measured afresh.
    #[test]
    fn max_deviation_never_returns_a_surface_past_the_bound() {
        let mesh = bumpy_sphere(3, 0.15);
        let measured = FlowParams {
            measure_deviation: true,
            ..FlowParams::default()
        };
        let free = drive(&mesh, &measured, 4).0;
        let d = |m: &StepMetrics| m.deviation_max.expect("measured");
        assert!(d(&free[2]) > d(&free[1]));
        let bound = 0.5 * (d(&free[1]) + d(&free[2]));
        let params = FlowParams {
            max_deviation: Some(bound),
            ..FlowParams::default()
        };
        let (metrics, outcome, run) = drive(&mesh, &params, 10);
        assert_eq!(outcome, Outcome::MaxDeviation);
        assert_eq!(metrics.len(), 2);
        assert!(metrics.iter().all(|m| d(m) <= bound));
        let topology = Topology::new(&mesh);
        let mut areas = vec![0.0; mesh.face_count()];
        face_areas_into(&mesh.positions, &mesh.triangles, &mut areas);
        let mut deviation = Deviation::new(&mesh.positions, &mesh.triangles, &topology, &areas);
        let result = run.flow().positions().to_vec();
        face_areas_into(&result, &mesh.triangles, &mut areas);
        let (max, _) = deviation.measure(&result, &mesh.triangles, &areas);
        assert!(
            max <= bound,
            "the result is {max} from the input, bound {bound}"
        );
        assert!((max - d(&metrics[1])).abs() < 1e-12);
        assert_eq!(run.last_metrics().step, 2);
        // A bound of 0 keeps the input itself.
        let params = FlowParams {
            max_deviation: Some(0.0),
            ..FlowParams::default()
        };
        let (metrics, outcome, run) = drive(&mesh, &params, 10);
        assert_eq!((metrics.len(), outcome), (0, Outcome::MaxDeviation));
        assert_eq!(run.flow().positions(), &mesh.positions[..]);
    }

    /// Implicit MCF at τ = 1000 on a bumpy sphere: the safeguard gives up at step 3 (as the
    /// CLI's test shows), and the run says so instead of failing.
    #[test]
    fn no_acceptable_step_ends_no_progress() {
        let mesh = bumpy_sphere(2, 0.4);
        let params = FlowParams {
            method: Method::Mcf,
            tau: 1000.0,
            ..FlowParams::default()
        };
        let (metrics, outcome, _) = drive(&mesh, &params, 6);
        assert_eq!(outcome, Outcome::NoProgress);
        assert_eq!(metrics.len(), 2);
    }

    #[test]
    fn bad_bounds_are_refused_by_name() {
        for (params, name) in [
            (
                FlowParams {
                    until_willmore: Some(-1.0),
                    ..FlowParams::default()
                },
                "until_willmore",
            ),
            (
                FlowParams {
                    max_deviation: Some(f64::NAN),
                    ..FlowParams::default()
                },
                "max_deviation",
            ),
            (
                FlowParams {
                    max_deviation: Some(f64::INFINITY),
                    ..FlowParams::default()
                },
                "max_deviation",
            ),
        ] {
            match params.validate() {
                Err(FlowError::InvalidParameter { name: n, .. }) => assert_eq!(n, name),
                other => panic!("{name}: {other:?}"),
            }
        }
        let json = serde_json::to_string(&Outcome::TargetReached).expect("serializes");
        assert_eq!(json, "\"target_reached\"");
        assert_eq!(Outcome::MaxDeviation.name(), "max_deviation");
        for o in Outcome::ALL {
            assert_eq!(Outcome::parse(o.name()), Some(o));
        }
        assert_eq!(Outcome::parse("Converged"), None);
    }
}
