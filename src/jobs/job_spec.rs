//! What a job asks for: [`JobSpec`], its defaults, its checks (against the server's limits
//! and, once the file is read, against the mesh) and the flow parameters it makes.

use super::error::JobError;
use super::mesh_error;
use super::model::Config;
use super::spec;
use serde::{Deserialize, Serialize};
use willow::flow::holes::fill_asset_holes;
use willow::flow::region::{Region, Seam};
use willow::flow::{FlowParams, Method, Preserve};
use willow::mesh::io::{Asset, Format};
use willow::mesh::{Limits, MeshError};

/// What to run on an uploaded mesh. Transports turn their wire parameters into this and call
/// [`JobSpec::validate`] (which [`Jobs::submit`](super::Jobs::submit) calls again, so no transport can skip it).
///
/// Stored as JSON with the job: a field added later must have a default (`#[serde(default)]`
/// fills it in for rows written before it existed) and is appended at the end (see
/// `codec::request_hash`). Every field of [`FlowParams`] has one here.
///
/// Its OpenAPI schema is derived from this declaration: the field docs are the API's
/// descriptions (so they speak JSON: `null`, not `None`), the library's types are described
/// by the small mirrors in `api::schema`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(default, deny_unknown_fields)]
#[schema(
    description = "What to run on an uploaded mesh (a job's `params`, as reported and as accepted)."
)]
pub struct JobSpec {
    /// Which flow: `denoise` (the default: feature-preserving denoising, guided normal
    /// filtering; nothing moves on a mesh without noise), `conformal` (the paper's Willmore
    /// flow, toward the round sphere), `mcf` (the yardstick), `cmcf`, `bilaplacian` or
    /// `taubin`.
    #[schema(value_type = String, example = "denoise")]
    pub method: Method,
    /// Number of flow steps to take (step 0 is the input).
    #[schema(minimum = 1)]
    pub steps: usize,
    // The library's `FlowParams::tau`.
    /// Time step τ (conformal: the curvature update `u ← (1 − 2τ)u`, stable for τ < 1).
    pub tau: f64,
    /// Inverse power iterations per step (conformal flow).
    pub iterations: usize,
    // Kept frames are what `frames/{step}` serves and what watchers get `positions` for.
    /// Every `frame_interval`-th step (and step 0 and the last step) keeps its positions.
    pub frame_interval: usize,
    /// Whether live and replayed frames carry positions at all (metrics are always sent).
    pub include_positions: bool,
    /// Wall-clock budget from submission, in seconds; null takes the server default.
    pub deadline_secs: Option<f64>,
    /// Exactness constraints on surfaces of genus > 0 (§6.2, App. C); conformal flow only.
    pub exactness: bool,
    /// Möbius balancing toward the input's area distribution (App. E.1); conformal only.
    pub mobius_balancing: bool,
    /// Spectral filter of the flow direction (§4); null is the paper's plain flow.
    pub filter: Option<spec::FilterSpec>,
    /// Boundary condition (§6.3): `auto` (the default) holds an open surface's border under the
    /// conformal flow; anything but `auto` or `free` is for the conformal flow only.
    pub boundary: spec::BoundarySpec,
    // See `willow::flow::safeguard`.
    /// Safeguarded steps: a step that raises W or damages the mesh is retried at a smaller τ.
    pub safeguard: bool,
    // See `willow::flow::region`. Vertex lists are in the file's numbering (OBJ `v` lines
    // from 0, glTF accessor vertices); spheres and boxes in its world space.
    /// The part of the surface that moves (their union); empty: the whole surface. Every
    /// vertex outside stays bit-identical. Accepted as one region or a list; reported as a
    /// list. Conformal flow only.
    #[serde(deserialize_with = "spec::one_or_many_regions::deserialize")]
    #[schema(value_type = Vec<crate::api::schema::RegionSchema>)]
    pub region: Vec<Region>,
    /// How a region meets the surface around it: `smooth` (positions and tangent planes
    /// held) or `fixed` (positions only).
    #[schema(value_type = crate::api::schema::SeamSchema)]
    pub seam: Seam,
    /// What each connected component keeps after every step: `area` (default), `volume`
    /// (closed components keep their enclosed volume, by a uniform scale: Q is untouched) or
    /// `none`. Taubin smoothing refuses `volume`.
    #[schema(value_type = crate::api::schema::PreserveSchema)]
    pub preserve: Preserve,
    /// Stop once the Willmore energy is at most this (outcome `target_reached`); ≥ 0.
    pub until_willmore: Option<f64>,
    /// Stop once W has stopped falling: its relative change stayed below 1e-4 per step for 3
    /// steps (outcome `converged`). Default true; false runs every step.
    pub until_converged: bool,
    /// Stop before the first step that would move the surface further than this from the
    /// input, in model units (outcome `max_deviation`): the result is the last surface within
    /// it. ≥ 0; turns `measure_deviation` on.
    pub max_deviation: Option<f64>,
    /// Report each frame's two-sided distance from the input (`deviation_max`,
    /// `deviation_mean`, model units). Off by default: it costs a share of every step.
    pub measure_deviation: bool,
    // See `willow::flow::feature`.
    /// Remove the detail smaller than this length (model units, > 0, at least two mean edge
    /// lengths) and keep the shape above it: the spectral filter (§4) with its crossover at
    /// this size; the job ends `feature_scale_reached` once the detail is gone. Conformal flow
    /// only; `filter`, when given, replaces the derived σ and k.
    pub feature_size: Option<f64>,
    /// Width (model units, > 0) over which a region's motion blends to zero toward its
    /// border. Needs a region.
    pub falloff: Option<f64>,
    // `Asset::read_repaired`.
    /// Repair the upload before the flow: drop degenerate faces and split non-manifold
    /// vertices and edges; the submission's answer has `repairs` (what changed, in the file's
    /// numbering). Default true: raw scans come with a few bowties, and a file that needs no
    /// repair reads exactly as it is. False refuses such a file, naming its own vertex and
    /// face numbers.
    pub repair: bool,
    /// Loop-subdivide the upload toward ~16k triangles before the flow (UVs interpolated per
    /// corner), for tessellations too coarse to fair (`already_fair`). Frames then carry the
    /// refined mesh's vertices (the file's own first, then the new ones; `vertex_count` of
    /// them) and frame 0 says `connectivity_changed`: fetch its mesh for the faces.
    // `willow::mesh::io::Asset::refined`, at its default target edge.
    pub refine: bool,
    // Signed by `super::webhooks`; the address policy is `Config::allow_insecure_callbacks`.
    /// Where the job's end (`job.succeeded`, `job.failed`, `job.cancelled`) is POSTed as a
    /// Standard Webhooks event (`webhook-id`, `webhook-timestamp`, `webhook-signature:
    /// v1,<base64 HMAC-SHA256 of "{id}.{timestamp}.{body}">`, keyed by the tenant's webhook
    /// secret), retried with backoff until answered 2xx. `https` to a public address only,
    /// unless the server runs with `--allow-insecure-callbacks`.
    pub callback_url: Option<String>,
    /// The filter of method `denoise`; other methods refuse anything but its defaults.
    pub denoise: spec::DenoiseSpec,
    // `willow::flow::creases`, `willow::mesh::creases`.
    /// Sharp edges kept sharp: edges whose faces meet at more than this many degrees (0 < angle
    /// < 180), in chains of 8 or more, read off the denoised surface, are creases. `auto` (the
    /// default: 30°) finds the creases of CAD parts and none on organic meshes; `none` fairs
    /// across every edge. The conformal flow holds the crease vertices and fairs the smooth
    /// patches between them (not with a `prescribed` or `cmc` boundary, or `preserve: volume`);
    /// `denoise` reports the creases it sharpened. Each frame's `crease_edges` counts them.
    #[schema(value_type = crate::api::schema::FeatureAngleSchema)]
    pub feature_angle: willow::mesh::creases::FeatureAngle,
    // `willow::flow::holes::fill_asset_holes`, after `repair` and `refine`.
    /// Close the upload's holes before the flow: every boundary loop up to this size (`all`, an
    /// integer: boundary vertices, or a decimal: the loop's extent in model units, e.g. `0.25`)
    /// gets a patch (minimal-dihedral triangulation, refined to the surrounding edge length,
    /// faired by the conformal flow with the surface's frames held along the loop: G1). The
    /// file's vertices and faces keep their numbers, the patches' are appended (UVs
    /// interpolated, or absent with a note where a UV seam runs into the hole); frames then
    /// carry `vertex_count` positions and frame 0 says `connectivity_changed`. Null: no filling.
    #[schema(value_type = Option<String>, example = "all")]
    pub fill_holes: Option<willow::mesh::holes::HoleSize>,
    // `willow::mesh::refine::planned_levels`: ⌈log₂(mean edge / refine_edge)⌉ levels.
    /// With `refine`: the edge length (model units) to subdivide toward, instead of the ~16k
    /// triangles of the default; each level halves the edges. The plan's size is known from
    /// the upload before any level is built: past the server's limits the job is refused with
    /// 413 and `field: refine`. Null: the default target.
    pub refine_edge: Option<f64>,
}

impl Default for JobSpec {
    fn default() -> Self {
        let flow = FlowParams::default();
        JobSpec {
            // The library's default is the paper's flow; an upload with no parameters is
            // denoised, which never makes a mesh worse (issue 39).
            method: Method::Denoise,
            steps: 20,
            tau: flow.tau,
            iterations: flow.iterations,
            frame_interval: 1,
            include_positions: true,
            deadline_secs: None,
            exactness: flow.exactness,
            mobius_balancing: flow.mobius_balancing,
            filter: None,
            boundary: spec::BoundarySpec::Auto,
            safeguard: flow.safeguard,
            region: Vec::new(),
            seam: flow.seam,
            preserve: flow.preserve,
            until_willmore: flow.until_willmore,
            until_converged: flow.until_converged,
            max_deviation: flow.max_deviation,
            measure_deviation: flow.measure_deviation,
            feature_size: flow.feature_size,
            falloff: flow.falloff,
            repair: true,
            refine: false,
            callback_url: None,
            denoise: spec::DenoiseSpec::from_flow(flow.denoise),
            feature_angle: flow.feature_angle,
            fill_holes: None,
            refine_edge: None,
        }
    }
}

impl JobSpec {
    /// The uploaded file as this job reads it: repaired, refined and its holes filled, when it
    /// asks for them.
    /// Deterministic, so the admission, the worker and every download see the same mesh.
    pub fn read_asset(
        &self,
        bytes: &[u8],
        format: Format,
        limits: &Limits,
    ) -> Result<Asset, JobError> {
        let asset = if self.repair {
            Asset::read_repaired(bytes, format, limits)
        } else {
            Asset::read(bytes, format, limits)
        }
        .map_err(mesh_error)?;
        let asset = if self.refine {
            // Refused from the plan, before the first level (`Asset::refined`): the error
            // names `refine`, the parameter that asked for the size.
            asset
                .refined(self.refine_edge, limits)
                .map_err(|e| match e {
                    MeshError::TooLarge { what, value, limit } => JobError::RefineTooLarge {
                        what: if what.starts_with("vertices") {
                            "vertices"
                        } else {
                            "triangles"
                        },
                        planned: value as u64,
                        limit: limit as u64,
                    },
                    other => mesh_error(other),
                })?
                .0
        } else {
            asset
        };
        match self.fill_holes {
            Some(size) => {
                let params = FlowParams::default();
                Ok(fill_asset_holes(&asset, size, &params, limits)
                    .map_err(mesh_error)?
                    .asset)
            }
            None => Ok(asset),
        }
    }

    /// Whether frame 0's mesh differs from the upload's (refined, holes filled): its
    /// `connectivity_changed`, telling a client to fetch the faces.
    pub fn changes_connectivity(&self) -> bool {
        self.refine || self.fill_holes.is_some()
    }

    /// Check every field against the server's limits; the error names the field.
    pub fn validate(&self, config: &Config) -> Result<(), JobError> {
        self.validate_with(config.limits.max_steps, config.max_deadline.as_secs_f64())
    }

    /// [`JobSpec::validate`] with explicit limits (the CLI has none of a server's).
    pub fn validate_with(&self, max_steps: usize, max_deadline_secs: f64) -> Result<(), JobError> {
        let bad =
            |field: &'static str, reason: String| Err(JobError::InvalidSpec { field, reason });
        if self.steps == 0 {
            return bad("steps", "must be at least 1".into());
        }
        if self.steps > max_steps {
            return Err(JobError::TooLarge {
                what: "steps",
                limit: max_steps as u64,
            });
        }
        if self.method == Method::Conformal && self.tau >= 1.0 {
            // §4: the curvature update u ← (1 − 2τ)u is only stable for τ < 1. The library
            // lets a caller take such a step to see it diverge; a job would only fail.
            return bad(
                "tau",
                format!(
                    "must be < 1 for the conformal flow (paper §4), got {}",
                    self.tau
                ),
            );
        }
        if let Some(edge) = self.refine_edge {
            if !self.refine {
                return bad(
                    "refine_edge",
                    "is the target of `refine`: set `refine: true` too".into(),
                );
            }
            if !edge.is_finite() || edge <= 0.0 {
                return bad(
                    "refine_edge",
                    format!("must be a finite length > 0, got {edge}"),
                );
            }
        }
        if self.frame_interval == 0 {
            return bad("frame_interval", "must be at least 1".into());
        }
        if let Some(d) = self.deadline_secs {
            if !d.is_finite() || d <= 0.0 {
                return bad(
                    "deadline_secs",
                    format!("must be a finite number > 0, got {d}"),
                );
            }
            if d > max_deadline_secs {
                return bad(
                    "deadline_secs",
                    format!("must be at most {max_deadline_secs} (the server's maximum), got {d}"),
                );
            }
        }
        if let Some(url) = &self.callback_url {
            // The scheme and address policy needs the server's flag and a DNS lookup: it is
            // `webhooks::check_callback`'s, at submission. Here only the form.
            super::webhooks::parse_callback(url).map_err(|reason| JobError::InvalidSpec {
                field: "callback_url",
                reason,
            })?;
        }
        // The boundary first: its checks name the field path inside it, where the library
        // names `boundary` as a whole.
        if let Err((field, reason)) = spec::check_boundary(&self.boundary) {
            return bad(field, reason);
        }
        // Everything else about the flow is the library's to judge, by the same names.
        self.flow_params().validate().map_err(|e| match e {
            willow::flow::FlowError::InvalidParameter { name, reason } => JobError::InvalidSpec {
                field: name,
                reason,
            },
            other => JobError::InvalidSpec {
                field: "params",
                reason: other.to_string(),
            },
        })
    }

    /// Checks that need the uploaded file: vertex regions name vertices of its triangles, the
    /// regions select some but not every vertex, one per-loop boundary angle per boundary loop,
    /// and the library's checks on the mesh's topology, resolution and size
    /// ([`willow::flow::check_for_mesh`]: `cmcf` on a torus, a `feature_size` the mesh cannot
    /// hold, `volume` where the border is held), so a job is refused now rather than failed
    /// later.
    pub fn validate_for_asset(&self, asset: &Asset) -> Result<(), JobError> {
        let mesh = asset.surface();
        if !self.region.is_empty() {
            let regions = self.surface_regions(asset)?;
            let selected =
                willow::flow::region::select(&mesh.positions, &regions).map_err(|reason| {
                    JobError::InvalidSpec {
                        field: "region",
                        reason,
                    }
                })?;
            let count = selected.iter().filter(|&&s| s).count();
            if count == 0 || count == selected.len() {
                return Err(JobError::InvalidSpec {
                    field: "region",
                    reason: if count == 0 {
                        "the region selects no vertex of the mesh".into()
                    } else {
                        "the region selects every vertex: leave it out to fair the whole \
                         surface"
                            .into()
                    },
                });
            }
        }
        let topology = willow::mesh::topology::Topology::new(mesh);
        if let spec::BoundarySpec::Prescribed(p) = &self.boundary {
            if matches!(p.angles, spec::AnglesSpec::PerLoop(_)) {
                spec::check_loop_count(&self.boundary, topology.boundary_loops.len())
                    .map_err(|(field, reason)| JobError::InvalidSpec { field, reason })?;
            }
        }
        let params = self.flow_params_for(asset)?;
        willow::flow::check_for_mesh(mesh, &topology, &params).map_err(|e| match e {
            willow::flow::FlowError::InvalidParameter { name, reason } => JobError::InvalidSpec {
                field: name,
                reason,
            },
            other => JobError::InvalidSpec {
                field: "params",
                reason: other.to_string(),
            },
        })
    }

    /// The regions on the welded surface: vertex lists renumbered from the file's numbering.
    pub fn surface_regions(&self, asset: &Asset) -> Result<Vec<Region>, JobError> {
        self.region
            .iter()
            .map(|r| match r {
                Region::Vertices(list) => asset
                    .surface_vertices(list)
                    .map(Region::Vertices)
                    .map_err(|v| JobError::InvalidSpec {
                        field: "region",
                        reason: format!(
                            "vertex {v} is not a vertex of a triangle of the file ({} vertices)",
                            asset.file_vertex_count()
                        ),
                    }),
                // A group names faces of the file: its vertices on the welded surface.
                Region::Group(_) => {
                    willow::flow::region::resolve_groups(std::slice::from_ref(r), asset)
                        .map(|mut resolved| resolved.remove(0))
                        .map_err(|reason| JobError::InvalidSpec {
                            field: "region",
                            reason,
                        })
                }
                other => Ok(other.clone()),
            })
            .collect()
    }

    /// The flow parameters this spec asks for on `asset`: [`JobSpec::flow_params`] with the
    /// regions on its welded surface.
    pub fn flow_params_for(&self, asset: &Asset) -> Result<FlowParams, JobError> {
        Ok(FlowParams {
            regions: self.surface_regions(asset)?,
            ..self.flow_params()
        })
    }

    /// The flow parameters this spec asks for: every field of [`FlowParams`] (regions as the
    /// spec holds them, in file numbering: see [`JobSpec::flow_params_for`]).
    pub fn flow_params(&self) -> FlowParams {
        FlowParams {
            method: self.method,
            tau: self.tau,
            iterations: self.iterations,
            exactness: self.exactness,
            mobius_balancing: self.mobius_balancing,
            filter: self.filter.map(spec::FilterSpec::to_flow),
            boundary: self.boundary.to_flow(self.method, !self.region.is_empty()),
            safeguard: self.safeguard,
            // Not the client's to choose: the worker pool sets it (`worker::thread_budget`).
            threads: 1,
            precision: willow::flow::Precision::Auto,
            regions: self.region.clone(),
            seam: self.seam,
            preserve: self.preserve,
            until_willmore: self.until_willmore,
            until_converged: self.until_converged,
            max_deviation: self.max_deviation,
            measure_deviation: self.measure_deviation,
            feature_size: self.feature_size,
            falloff: self.falloff,
            denoise: self.denoise.to_flow(),
            feature_angle: self.feature_angle,
        }
    }

    /// Whether `step` keeps positions (step 0, every `frame_interval`-th, and the last).
    pub fn keeps_positions(&self, step: usize) -> bool {
        self.include_positions
            && (step.is_multiple_of(self.frame_interval.max(1)) || step == self.steps)
    }
}
