//! Flows on a [`Mesh`], one step at a time.
//!
//! A [`Flow`] owns its state (positions, cached operators, factorizations) and no threads:
//! the caller drives it with [`Flow::step`] and decides between steps whether to go on
//! (cancellation, deadlines), which is how the CLI and the job service both use it.

pub mod classic;
pub mod constraints;
pub mod creases;
pub mod denoise;
pub mod dirac;
pub mod dirichlet;
pub mod exactness;
pub mod feature;
pub mod filter;
pub mod holes;
pub mod mobius;
pub mod prescribed;
pub mod region;
pub mod safeguard;
pub mod scale;
pub mod stopping;
pub mod willmore;

use crate::mesh::Mesh;
use crate::metrics::StepMetrics;
use serde::{Deserialize, Serialize};

/// Which flow to run. Read from any case (as [`Method::parse`]), written by [`Method::name`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Method {
    /// Conformal Willmore flow in curvature space (the paper).
    #[default]
    Conformal,
    /// Implicit mean curvature flow (Desbrun et al. 1999, backward Euler): the yardstick.
    Mcf,
    /// Conformalized mean curvature flow (Kazhdan, Solomon, Ben-Chen 2012); genus 0 only.
    Cmcf,
    /// Implicit bi-Laplacian flow (backward Euler on `ḟ = −Δ²f`).
    Bilaplacian,
    /// Taubin λ|μ smoothing (Taubin 1995), explicit.
    Taubin,
    /// Feature-preserving denoising: guided mesh normal filtering (Zhang et al. 2015) with the
    /// vertex update of Sun et al. 2007 ([`crate::denoise`], [`denoise::DenoiseFlow`]); its
    /// iteration count and whether there is noise at all are read off the mesh. What the
    /// service and the CLI run when no method is named.
    Denoise,
}

impl Method {
    /// Every method, in the order forms and errors list them. The match in [`Method::name`]
    /// makes a new method a compile error until it is named (and so listed here).
    pub const ALL: [Method; 6] = [
        Method::Conformal,
        Method::Mcf,
        Method::Cmcf,
        Method::Bilaplacian,
        Method::Taubin,
        Method::Denoise,
    ];

    /// The one name of a method, on every transport: JSON, query strings, the CLI, and (upper
    /// case, after `METHOD_`) the gRPC enum.
    pub const fn name(self) -> &'static str {
        match self {
            Method::Conformal => "conformal",
            Method::Mcf => "mcf",
            Method::Cmcf => "cmcf",
            Method::Bilaplacian => "bilaplacian",
            Method::Taubin => "taubin",
            Method::Denoise => "denoise",
        }
    }

    /// The method of a name (any case), or an error listing the names.
    pub fn parse(name: &str) -> Result<Method, String> {
        Method::ALL
            .into_iter()
            .find(|m| m.name().eq_ignore_ascii_case(name))
            .ok_or_else(|| {
                let names: Vec<String> = Method::ALL
                    .iter()
                    .map(|m| format!("`{}`", m.name()))
                    .collect();
                format!("expected one of {}, got `{name}`", names.join(", "))
            })
    }
}

impl std::str::FromStr for Method {
    type Err = String;
    fn from_str(s: &str) -> Result<Method, String> {
        Method::parse(s)
    }
}

/// Names in JSON are read as every other transport reads them: any case, and an unknown one
/// is refused with the list of names.
macro_rules! deserialize_by_parse {
    ($t:ty) => {
        impl<'de> Deserialize<'de> for $t {
            fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
                let name = std::borrow::Cow::<'de, str>::deserialize(d)?;
                <$t>::parse(&name).map_err(serde::de::Error::custom)
            }
        }
    };
}
pub(crate) use deserialize_by_parse;

deserialize_by_parse!(Method);
deserialize_by_parse!(Preserve);

/// What the scale policy ([`scale`]) gives back to each connected component after every step.
/// Every choice also puts the component's area-weighted centroid back where it was.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Preserve {
    /// Each component keeps its input area (docs/algorithm.md §6): what a CAD pipeline expects.
    #[default]
    Area,
    /// Each *closed* component keeps its input enclosed volume, by a uniform scale about its
    /// centroid (a similarity, so Q is untouched); components with boundary enclose nothing
    /// and keep their area as under [`Preserve::Area`].
    Volume,
    /// No rescaling: the size is whatever the flow makes it (implicit MCF shrinks; the
    /// conformal flow's λ normalization keeps the area roughly). The centroid is still
    /// restored: the conformal flow's Poisson solve (Table 1 step VII) fixes positions only up
    /// to a constant per component, so without it the translation would be a gauge artefact,
    /// not shape, and it would swamp the distance from the input.
    None,
}

impl Preserve {
    pub const ALL: [Preserve; 3] = [Preserve::Area, Preserve::Volume, Preserve::None];

    /// The one name of a choice: JSON and the CLI.
    pub const fn name(self) -> &'static str {
        match self {
            Preserve::Area => "area",
            Preserve::Volume => "volume",
            Preserve::None => "none",
        }
    }

    /// The choice of a name (any case), or an error listing the names.
    pub fn parse(name: &str) -> Result<Preserve, String> {
        Preserve::ALL
            .into_iter()
            .find(|p| p.name().eq_ignore_ascii_case(name))
            .ok_or_else(|| format!("expected one of `area`, `volume`, `none`, got `{name}`"))
    }
}

/// More inverse iterations per step than this buy nothing (§6.4.2 uses one) and only burn
/// CPU: the one cap, for the library and every transport.
pub const MAX_ITERATIONS: usize = 50;

/// What happens at the boundary of a surface with boundary (§6.3). Closed surfaces ignore it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Boundary {
    /// The boundary moves freely (§6.2: disks need no constraint). Not elliptic at the
    /// boundary (Bohle and Pinkall 2013): large steps may need a small τ there.
    #[default]
    Free,
    /// Boundary positions stay exactly where they are (§6.3.2): λ = 1 on the boundary and a
    /// Dirichlet Poisson problem for the positions.
    Fixed,
    /// Prescribed vectors (§6.3.1): at every boundary vertex a direction `V` of the
    /// boundary frame is mapped to a target `Ṽ`.
    Prescribed(PrescribedVectors),
    /// `V = B` held at the input's binormals (§6.3.1, last sentence): Willmore flow then
    /// converges to a surface of constant mean curvature with the input's boundary conormals.
    /// The same as `Prescribed` with every field at its default.
    Cmc,
}

/// §6.3.1: `V = cos φ·B + sin φ·N` in the boundary frame (`T` the boundary tangent, `N` the
/// normal, `B = T × N`), and the target `Ṽ` = `V` of the *input* surface rotated by an angle
/// about an axis. Targets are fixed in space when the flow is built; each step maps the
/// current `V` to them, so after the first step the boundary keeps them.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
#[serde(default)]
pub struct PrescribedVectors {
    /// φ in radians, |φ| < π/2: `V` must not be `±N`, where the boundary problem stops being
    /// elliptic; φ = 0 (`V = B`, perpendicular to `T`) is also self-adjoint (§6.3.1).
    pub frame_angle: f64,
    /// Axis of the rotation from `V` to `Ṽ`.
    pub axis: RotationAxis,
    /// Rotation angles in radians.
    pub angles: BoundaryAngles,
}

/// Axis of the rotation that makes the target `Ṽ` from the input's `V`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum RotationAxis {
    /// The boundary tangent `T` at each vertex: turns `V` within the N–B plane (flares or
    /// tucks the boundary; oscillating angles give Figure 14's hemisphere).
    #[default]
    Tangent,
    /// One fixed direction in space for every vertex (tilts a whole loop: the bend of
    /// Figure 14's cylinder). Need not be unit length; must not be zero.
    Fixed([f64; 3]),
}

/// Rotation angle per boundary vertex, in radians.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BoundaryAngles {
    /// The same angle everywhere.
    Uniform(f64),
    /// One angle per boundary loop, in the order of `Topology::boundary_loops`.
    PerLoop(Vec<f64>),
    /// Angles for listed boundary vertices (mesh vertex indices); unlisted ones get 0.
    PerVertex(Vec<(usize, f64)>),
}

impl Default for BoundaryAngles {
    fn default() -> Self {
        BoundaryAngles::Uniform(0.0)
    }
}

/// Parameters of a flow run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct FlowParams {
    pub method: Method,
    /// Time step. For the conformal flow it has the paper's meaning (§4: the curvature update
    /// is `u ← (1 − 2τ)u`, stable for τ < 1). For MCF it is unitless: the backward Euler step is
    /// `τ · area / 4π`, so τ = 0.1 moves a unit sphere's radius by about 10%; the same for
    /// cMCF, `τ · (area / 4π)²` for the bi-Laplacian flow, and Taubin's λ for λ|μ smoothing
    /// (see `classic`).
    pub tau: f64,
    /// Inverse power iterations per step for the smallest eigenvector (§6.4.2 uses one).
    pub iterations: usize,
    /// Exactness constraints for surfaces of genus > 0 (§6.2, Appendix C). Switching them off
    /// is only useful to see what they prevent (Figure 12).
    pub exactness: bool,
    /// Möbius balancing toward the input's area distribution (§6.2, Appendix E.1).
    pub mobius_balancing: bool,
    /// Spectral filter of the flow direction (§4); `None` is the paper's plain flow.
    pub filter: Option<filter::SpectralFilter>,
    /// Boundary condition for surfaces with boundary (§6.3).
    pub boundary: Boundary,
    /// Safeguarded steps ([`safeguard`]): a step that raises W or damages the mesh is retried
    /// at a smaller τ. On by default; off, every step is taken at τ whatever it does.
    pub safeguard: bool,
    /// Threads a factorization may use: independent subtrees of its elimination tree run
    /// concurrently, and the result is bitwise the same for any count. 1 (the default) keeps
    /// the flow on the calling thread, so that many small flows share the cores; the service
    /// gives a large job more when workers are idle (`jobs::worker`).
    pub threads: usize,
    /// How the conformal flow factors the Dirac matrix X (see [`Precision`]).
    pub precision: Precision,
    /// The part of the surface that moves ([`region`]): empty, the whole surface; otherwise
    /// the union of these regions, everything else held exactly where it was.
    pub regions: Vec<region::Region>,
    /// How a region meets the surface around it (ignored without regions).
    pub seam: region::Seam,
    /// What each component keeps after every step: area (the default), enclosed volume, or
    /// nothing ([`Preserve`]). Taubin smoothing is never rescaled and a fixed boundary pins
    /// the size already: both refuse `volume` ([`FlowError::Unsupported`]). Under a
    /// `feature_size`, `area` keeps only the centroid: the area lost is the detail's
    /// ([`feature::scale_policy`]).
    pub preserve: Preserve,
    /// Stop once the Willmore energy is at most this ([`stopping::Run`]); `None`: no target.
    pub until_willmore: Option<f64>,
    /// Stop once W has stopped falling ([`stopping::Run`], outcome `converged`); on by
    /// default. Off, a run takes all its steps (a fixed-length animation, a benchmark).
    pub until_converged: bool,
    /// Stop before the first step that would move the surface further than this from the
    /// input (`StepMetrics::deviation_max`, model units); the result is the last surface
    /// within it ([`stopping::Run`]). `None`: no bound.
    pub max_deviation: Option<f64>,
    /// Report each step's distance from the input (`StepMetrics::deviation_max` and
    /// `deviation_mean`, the mean within 1% at 95% confidence), on the flow's `threads`. At
    /// 100k triangles (nefertiti) its slowest frame costs 7.3% of a conformal try at τ 0.5
    /// and 9.7% at τ 0.01 on one thread, 6–8.5% on two (issue 29 asks for ≤ 10%; `willow
    /// bench` prints it, docs/performance.md). Off by default all the same: a frame costs
    /// about 3,000 nearest-point queries whatever the mesh's size, which on a mesh of a few
    /// thousand triangles is as much as its millisecond step or more (spot 75% of a try, bob
    /// three times). `max_deviation` turns it on (and keeps the surface near the input).
    pub measure_deviation: bool,
    /// Remove the detail smaller than this length (model units) and keep the shape above it
    /// ([`feature`]): the conformal flow with the spectral filter's crossover at this size
    /// (`filter`, when given, replaces the derived σ and k), its low-frequency motion taken
    /// back each step, and the run ends `feature_scale_reached` once the detail is gone
    /// ([`stopping::Run`]). `None`: the flow as asked.
    pub feature_size: Option<f64>,
    /// Width (model units) over which a region's motion blends to zero toward its border
    /// ([`region`]); `None`: no blend. Needs a region.
    pub falloff: Option<f64>,
    /// The filter of [`Method::Denoise`] ([`crate::denoise::DenoiseParams`]); its default
    /// reads the iteration count off the mesh. Other methods refuse anything else.
    pub denoise: crate::denoise::DenoiseParams,
    /// Sharp edges kept sharp ([`creases`]): edges whose faces meet at more than this angle,
    /// in chains long enough to be a part's creases ([`crate::mesh::creases`]), read off the
    /// denoised surface. The conformal flow holds their vertices where they are and fairs
    /// each smooth patch between them; `denoise` reports the creases it sharpened. The
    /// default (`auto`) finds the creases of CAD parts and none on organic meshes.
    pub feature_angle: crate::mesh::creases::FeatureAngle,
}

impl FlowParams {
    /// What an error about a conformal-only parameter adds under method `denoise`, the
    /// service's and the CLI's default: a caller who named no method learns why.
    fn default_method_hint(method: Method) -> &'static str {
        if method == Method::Denoise {
            " (`denoise` is the default method: ask for method `conformal`)"
        } else {
            ""
        }
    }

    /// Whether the flow measures its distance from the input each step.
    pub fn measures_deviation(&self) -> bool {
        self.measure_deviation || self.max_deviation.is_some()
    }

    /// The threads the distance from the input is measured on, if it is measured: the flow's
    /// own [`FlowParams::threads`], so that a job given idle cores measures it faster too
    /// ([`crate::geometry::distance::Deviation::with_threads`]).
    pub fn deviation_threads(&self) -> Option<usize> {
        self.measures_deviation().then_some(self.threads)
    }
}

impl FlowParams {
    /// Checks every parameter that does not need the mesh, naming the first bad one by its
    /// field path (`tau`, `filter.k`, `boundary`, ...). Every flow calls it when it is built; the CLI and the job service call it
    /// before a job is accepted. What needs the mesh (the per-loop angle count, a vertex on the
    /// boundary, Taubin's pass band) is checked when the flow is built.
    pub fn validate(&self) -> Result<(), FlowError> {
        let invalid =
            |name: &'static str, reason: String| FlowError::InvalidParameter { name, reason };
        if !(self.tau.is_finite() && self.tau > 0.0) {
            return Err(invalid(
                "tau",
                format!("must be a positive finite number, got {}", self.tau),
            ));
        }
        if self.iterations == 0 || self.iterations > MAX_ITERATIONS {
            return Err(invalid(
                "iterations",
                format!(
                    "must be between 1 and {MAX_ITERATIONS}, got {}",
                    self.iterations
                ),
            ));
        }
        if self.threads == 0 {
            return Err(invalid("threads", "must be at least 1, got 0".into()));
        }
        if self.method != Method::Conformal {
            // The other flows would run and silently ignore these: a caller who asks for them
            // should hear so.
            let ignored = [
                ("exactness", !self.exactness),
                ("mobius_balancing", self.mobius_balancing),
                ("filter", self.filter.is_some()),
                ("boundary", self.boundary != Boundary::Free),
                ("region", !self.regions.is_empty()),
            ];
            if let Some((name, _)) = ignored.iter().find(|(_, set)| *set) {
                return Err(invalid(
                    name,
                    format!(
                        "applies only to method `conformal`, got `{}`{}",
                        self.method.name(),
                        Self::default_method_hint(self.method)
                    ),
                ));
            }
        }
        // λ = τ, μ = −λ / (1 − k_PB λ): below this μ rounds to −λ and the filter passes
        // nothing (`tau=1e-320` was accepted, then failed naming `mu`).
        if self.method == Method::Taubin && self.tau < classic::MIN_TAUBIN_TAU {
            return Err(invalid(
                "tau",
                format!(
                    "Taubin λ = τ must be at least {:e}, got {:e}",
                    classic::MIN_TAUBIN_TAU,
                    self.tau
                ),
            ));
        }
        if self.method == Method::Taubin && self.preserve == Preserve::Volume {
            return Err(invalid(
                "preserve",
                "`volume` does not apply to Taubin smoothing: λ|μ is never rescaled (keeping \
                 the volume without rescaling is what it is for); use `area` or `none`"
                    .into(),
            ));
        }
        if !self.regions.is_empty() && self.boundary != Boundary::Free {
            return Err(invalid(
                "region",
                "a region holds its surroundings itself: leave `boundary` free".into(),
            ));
        }
        if let Some(f) = self.filter {
            if f.k > filter::MAX_K {
                return Err(invalid(
                    "filter.k",
                    format!("must be 0, 1, 2 or 3, got {}", f.k),
                ));
            }
            if !(f.sigma.is_finite() && f.sigma > 0.0) {
                return Err(invalid(
                    "filter.sigma",
                    format!("must be a finite number > 0, got {}", f.sigma),
                ));
            }
        }
        if self.regions.len() > region::MAX_REGIONS {
            return Err(invalid(
                "region",
                format!(
                    "at most {} regions, got {}: name their union as fewer shapes or one \
                     vertex list",
                    region::MAX_REGIONS,
                    self.regions.len()
                ),
            ));
        }
        for r in &self.regions {
            r.validate().map_err(|reason| invalid("region", reason))?;
        }
        for (name, value) in [
            ("until_willmore", self.until_willmore),
            ("max_deviation", self.max_deviation),
        ] {
            if let Some(v) = value {
                if !(v.is_finite() && v >= 0.0) {
                    return Err(invalid(
                        name,
                        format!("must be a finite number ≥ 0, got {v}"),
                    ));
                }
            }
        }
        for (name, value) in [
            ("feature_size", self.feature_size),
            ("falloff", self.falloff),
        ] {
            if let Some(v) = value {
                if !(v.is_finite() && v > 0.0) {
                    return Err(invalid(
                        name,
                        format!("must be a finite length > 0 (model units), got {v}"),
                    ));
                }
            }
        }
        if self.feature_size.is_some() && self.method != Method::Conformal {
            return Err(invalid(
                "feature_size",
                format!(
                    "is built on the conformal flow's spectral filter (§4), not on `{}`{}",
                    self.method.name(),
                    Self::default_method_hint(self.method)
                ),
            ));
        }
        self.denoise
            .validate()
            .map_err(|(name, reason)| invalid(name, reason))?;
        if self.method != Method::Denoise
            && self.denoise != crate::denoise::DenoiseParams::default()
        {
            return Err(invalid(
                "denoise",
                format!(
                    "sets the filter of method `denoise`, not of `{}`",
                    self.method.name()
                ),
            ));
        }
        if self.method == Method::Denoise && self.preserve == Preserve::Volume {
            return Err(invalid(
                "preserve",
                "`volume` does not apply to method `denoise`: the filter never rescales \
                 (its vertices move along the filtered normals only); use `area` or `none`"
                    .into(),
            ));
        }
        if self.falloff.is_some() && self.regions.is_empty() {
            return Err(invalid(
                "falloff",
                "blends a region's motion toward its border: it needs a region".into(),
            ));
        }
        self.feature_angle
            .validate()
            .map_err(|reason| invalid("feature_angle", reason))?;
        if let crate::mesh::creases::FeatureAngle::Degrees(_) = self.feature_angle {
            // `auto` steps aside where creases cannot be held; an angle the caller named is
            // refused there instead of being ignored.
            if let Some(reason) = creases::unheld_reason(self) {
                return Err(invalid("feature_angle", reason));
            }
        }
        // The library names the whole `boundary` (its errors always have); the job service
        // reports the field path that `PrescribedVectors::validate` gives.
        if let Boundary::Prescribed(p) = &self.boundary {
            p.validate()
                .map_err(|(_, e)| invalid("boundary", e.to_string()))?;
        }
        Ok(())
    }
}

/// The arithmetic of the Dirac matrix's factor in the conformal flow.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Precision {
    /// [`Precision::Mixed`] from [`willmore::MIXED_MIN_VERTICES`] vertices on (closed
    /// surfaces without exactness constraints), [`Precision::Double`] below.
    #[default]
    Auto,
    /// A double-precision Cholesky factor, refactored every step: exact solves.
    Double,
    /// A single-precision factor, kept across steps while it preconditions well, and
    /// conjugate gradients to double-precision accuracy (`solver::Mixed`): half the memory,
    /// a fraction of the time per step on large meshes. Falls back to `Double` by itself
    /// where single precision cannot factor X; flows that need X's exact factor (exactness
    /// constraints on genus > 0, fixed or prescribed boundaries) always use `Double`.
    Mixed,
}

impl Default for FlowParams {
    fn default() -> Self {
        FlowParams {
            method: Method::Conformal,
            tau: 0.5,
            iterations: 1,
            exactness: true,
            mobius_balancing: false,
            filter: None,
            boundary: Boundary::Free,
            safeguard: true,
            threads: 1,
            precision: Precision::Auto,
            regions: Vec::new(),
            seam: region::Seam::default(),
            preserve: Preserve::Area,
            until_willmore: None,
            until_converged: true,
            max_deviation: None,
            measure_deviation: false,
            feature_size: None,
            falloff: None,
            denoise: crate::denoise::DenoiseParams::default(),
            feature_angle: crate::mesh::creases::FeatureAngle::Auto,
        }
    }
}

/// Why a flow could not be built or could not go on.
#[derive(Debug, thiserror::Error, Clone, PartialEq)]
pub enum FlowError {
    #[error("invalid parameter `{name}`: {reason}")]
    InvalidParameter { name: &'static str, reason: String },
    #[error("not supported: {0}")]
    Unsupported(String),
    #[error("numerical failure at step {step}: {reason}")]
    Numerical { step: usize, reason: String },
    /// The safeguard found no acceptable step down to τ = `tau`; the flow is still on the
    /// last accepted surface. `at_minimum`: every try was refused only for raising W by less
    /// than `safeguard::MINIMUM_RISE`, so that surface is a minimum to the solver's accuracy
    /// (a run ends `converged` there, not `no_progress`).
    #[error(
        "no progress at step {step}: no acceptable step down to tau = {tau:e} (last try: {reason})"
    )]
    NoProgress {
        step: usize,
        tau: f64,
        reason: String,
        at_minimum: bool,
    },
}

/// One running flow. Steps are explicit; nothing runs in the background.
pub trait Flow: Send {
    /// Advance one step and report the metrics of the new surface.
    fn step(&mut self) -> Result<StepMetrics, FlowError>;
    /// Current positions, in the vertex order of the mesh the flow was built from.
    fn positions(&self) -> &[[f64; 3]];
    /// The metrics of the input surface (step 0).
    fn initial_metrics(&self) -> StepMetrics;
    /// Where the last try of the last step spent its time, phase by phase, when the flow
    /// keeps such a profile (the conformal flow does; `willow bench` prints it).
    fn profile(&self) -> Option<&StepProfile> {
        None
    }
    /// The least Willmore energy any smooth surface of the input's topology has, summed over
    /// its components: 4π for a closed genus-0 component, 2π² for a closed one of higher genus
    /// (Marques and Neves 2014 proved the Willmore conjecture, and W ≥ 2π² for every genus
    /// ≥ 1), 0 for one with boundary. A run whose input is already at or below it ends
    /// `already_fair` ([`stopping`]). `None` where the flow does not know its topology.
    fn willmore_lower_bound(&self) -> Option<f64> {
        None
    }
    /// Why the safeguard last refused a try (`None`: no refusal yet, or no safeguard).
    fn last_refusal(&self) -> Option<String> {
        None
    }
    /// Where building the flow spent its time, when the flow kept such a profile.
    fn setup_profile(&self) -> Option<&StepProfile> {
        None
    }
    /// The energy of the detail band a feature scale removes (`FlowParams::feature_size`),
    /// at the input and on the current surface; `None` without a feature scale.
    fn feature_detail(&self) -> Option<feature::FeatureDetail> {
        None
    }
    /// For a flow that absorbs the curvature change a held border cannot realize (a region,
    /// `flow/willmore/pinned.rs`): the part of the requested change its last try still aimed
    /// at, `⟨ρ, ρ_req⟩_M / |ρ_req|²_M` over the free vertices (1: nothing absorbed, ≤ 0: the
    /// absorbed change cancels or reverses the request); `None` for any other flow.
    fn kept_share(&self) -> Option<f64> {
        None
    }
    /// For a flow with an end of its own (the denoiser's iteration count): why it has taken
    /// its last step, once it has. A run then ends `completed` with this reason, or
    /// `already_fair` if it ends before any step ([`stopping::Run`]). `None`: not yet, or
    /// the flow goes on as long as it is stepped.
    fn finished(&self) -> Option<String> {
        None
    }
    /// What a later [`Flow::resume`] needs to go on from here: the surface, its metrics, the
    /// step-size control and what the flow carries between steps ([`Carried`]). `None` for a
    /// flow that cannot be resumed.
    fn checkpoint(&self) -> Option<FlowState> {
        None
    }

    /// The crease edges the flow keeps sharp or found (vertex pairs; [`creases`]): held by
    /// the conformal flow, sharpened by `denoise`. Empty without creases.
    fn creases(&self) -> &[[usize; 2]] {
        &[]
    }

    /// Put a flow freshly built on the same input and parameters back where
    /// [`Flow::checkpoint`] left another one. Every quantity a step reads is recomputed from
    /// the surface (the inverse iteration starts from λ = 1 each step, App. G) or put back
    /// from [`FlowState::carried`], so the steps that follow are those the first flow would
    /// have taken.
    fn resume(&mut self, state: &FlowState) -> Result<(), FlowError> {
        let _ = state;
        Err(FlowError::Unsupported(
            "this flow cannot resume from a checkpoint".into(),
        ))
    }
}

/// [`Flow::willmore_lower_bound`] of a mesh's topology.
pub fn willmore_lower_bound(topology: &crate::mesh::topology::Topology) -> f64 {
    use std::f64::consts::PI;
    topology
        .components
        .iter()
        .map(|c| match (c.is_closed(), c.genus) {
            (false, _) => 0.0,
            (true, 0) => 4.0 * PI,
            (true, _) => 2.0 * PI * PI,
        })
        .sum()
}

/// A flow's resumable state after some step (see [`Flow::checkpoint`]).
#[derive(Clone, Debug, PartialEq)]
pub struct FlowState {
    /// The metrics of the surface after `metrics.step` steps (the step the state is at).
    pub metrics: StepMetrics,
    /// The surface after that step, in the flow's (welded) vertex order.
    pub positions: Vec<[f64; 3]>,
    /// τ of the next step's first try (the safeguard's control, [`safeguard`]).
    pub next_tau: f64,
    /// Steps accepted at their first try since τ last changed.
    pub clean_steps: u32,
    /// What the flow and its run carry from step to step beyond the surface: without it a
    /// resumed region job would not take the steps an uninterrupted one takes.
    pub carried: Carried,
}

/// A flow's memory between steps that its surface does not determine ([`FlowState`]). A
/// checkpoint written before it was kept (the service's version 2) resumes with the default:
/// nothing absorbed, the plain Poisson weights, the stopping rules' look-back afresh.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Carried {
    /// The curvature change a held border cannot realize, absorbed per unit τ and carried to
    /// the next step (a region's flow: `flow/willmore/pinned.rs`, `ABSORB_MEMORY`), per
    /// vertex of the flow's own mesh (a region's submesh); empty: nothing absorbed.
    pub absorbed: Vec<f64>,
    /// The safeguard switched the Poisson solve to non-negative weights on crowded faces
    /// for the rest of the run ([`safeguard::Retry::resist_damage`]).
    pub resists_damage: bool,
    /// Quiet steps in a row ([`stopping::Run`]'s convergence window), as the run counted
    /// them at the checkpoint; 0 from a flow's own [`Flow::checkpoint`].
    pub quiet_steps: u32,
    /// Crawling steps in a row ([`stopping::Run`]'s stall window), likewise.
    pub crawling_steps: u32,
}

/// Milliseconds per phase of one step, in the order the phases ran. Refilled in place each
/// step: no allocation in the step loop once the first step has run.
#[derive(Debug, Clone, Default)]
pub struct StepProfile {
    phases: Vec<(&'static str, f64)>,
    counts: Vec<(&'static str, f64)>,
    mark: Option<std::time::Instant>,
}

impl StepProfile {
    /// Forget the last step's phases and start timing the next one.
    pub fn start(&mut self) {
        self.phases.clear();
        self.counts.clear();
        self.mark = Some(std::time::Instant::now());
    }

    /// Close the phase `name`: the time since the last mark is added to it.
    pub fn lap(&mut self, name: &'static str) {
        let now = std::time::Instant::now();
        let Some(mark) = self.mark.replace(now) else {
            return;
        };
        let ms = (now - mark).as_secs_f64() * 1e3;
        match self.phases.iter_mut().find(|(n, _)| *n == name) {
            Some((_, total)) => *total += ms,
            None => self.phases.push((name, ms)),
        }
    }

    pub fn phases(&self) -> &[(&'static str, f64)] {
        &self.phases
    }

    /// Add `value` to the count `name` (e.g. solver iterations) of this step.
    pub fn count(&mut self, name: &'static str, value: f64) {
        match self.counts.iter_mut().find(|(n, _)| *n == name) {
            Some((_, total)) => *total += value,
            None => self.counts.push((name, value)),
        }
    }

    pub fn counts(&self) -> &[(&'static str, f64)] {
        &self.counts
    }
}

/// The checks of `params` that need the mesh (its topology, resolution and size), cheap
/// enough for a request path: a service runs them when a job is submitted, so that a job
/// never fails later for what the upload already showed (issue 42: each of these was
/// accepted, then failed). The flows' constructors keep their own guards.
pub fn check_for_mesh(
    mesh: &Mesh,
    topology: &crate::mesh::topology::Topology,
    params: &FlowParams,
) -> Result<(), FlowError> {
    let invalid = |name: &'static str, reason: String| FlowError::InvalidParameter { name, reason };
    if params.method == Method::Cmcf {
        if let Some((index, c)) = topology
            .components
            .iter()
            .enumerate()
            .find(|(_, c)| c.genus != 0 || !c.is_closed())
        {
            return Err(invalid(
                "method",
                format!(
                    "`cmcf` applies only to spherical topology (closed, genus 0); component \
                     {index} has genus {} and {} boundary loop(s)",
                    c.genus,
                    c.boundary_loops.len()
                ),
            ));
        }
    }
    if params.method != Method::Conformal {
        return Ok(());
    }
    if let Some(length) = params.feature_size {
        feature::check_resolution(length, crate::mesh::generate::mean_edge_length(mesh))?;
        let diagonal = bounding_diagonal(&mesh.positions);
        if length > diagonal {
            return Err(invalid(
                "feature_size",
                format!(
                    "{length} is larger than the mesh itself (its bounding-box diagonal is \
                     {diagonal:.6}): detail that large is its shape; leave feature_size out \
                     to fair the whole shape"
                ),
            ));
        }
    }
    // A region or a held border pins the surface's position and size, and the step does not
    // rescale (`willmore::ConformalFlow::new`).
    let held_border = params.boundary == Boundary::Fixed && !topology.boundary_loops.is_empty();
    if params.preserve == Preserve::Volume && (held_border || !params.regions.is_empty()) {
        return Err(invalid(
            "preserve",
            format!(
                "`volume` cannot be kept {}: the held vertices pin position and size and the \
                 flow does not rescale; use `area` or `none`{}",
                if params.regions.is_empty() {
                    "on an open surface whose border is held"
                } else {
                    "with a region"
                },
                if params.regions.is_empty() {
                    " (or `boundary: free`, which lets the border move)"
                } else {
                    ""
                }
            ),
        ));
    }
    Ok(())
}

/// The length of the diagonal of the positions' axis-aligned bounding box.
fn bounding_diagonal(positions: &[[f64; 3]]) -> f64 {
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for p in positions {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    (0..3).map(|k| (hi[k] - lo[k]).powi(2)).sum::<f64>().sqrt()
}

/// Build the flow `params.method` names on `mesh` (validated: see [`Mesh::new`]), with its
/// steps safeguarded unless `params.safeguard` is off ([`safeguard`]).
pub fn new_flow(mesh: &Mesh, params: &FlowParams) -> Result<Box<dyn Flow>, FlowError> {
    fn guard<F: safeguard::Retry + 'static>(
        flow: F,
        mesh: &Mesh,
        params: &FlowParams,
    ) -> Box<dyn Flow> {
        Box::new(safeguard::Safeguarded::new(
            flow,
            &mesh.triangles,
            params.safeguard,
        ))
    }
    if let Some(flow) = creases::crease_flow(mesh, params)? {
        return Ok(flow);
    }
    if !params.regions.is_empty() {
        return Ok(Box::new(region::RegionFlow::new(mesh, params)?));
    }
    Ok(match params.method {
        Method::Conformal => guard(willmore::ConformalFlow::new(mesh, params)?, mesh, params),
        Method::Mcf => guard(
            classic::ImplicitMeanCurvatureFlow::new(mesh, params)?,
            mesh,
            params,
        ),
        Method::Cmcf => guard(
            classic::ConformalizedMeanCurvatureFlow::new(mesh, params)?,
            mesh,
            params,
        ),
        Method::Bilaplacian => guard(
            classic::ImplicitBilaplacianFlow::new(mesh, params)?,
            mesh,
            params,
        ),
        Method::Taubin => guard(classic::TaubinSmoothing::new(mesh, params)?, mesh, params),
        // Not safeguarded: it never raises its step, and a fold the filter makes is one the
        // normals asked for (a crease), not a step to retry smaller.
        Method::Denoise => Box::new(denoise::DenoiseFlow::new(mesh, params)?),
    })
}
