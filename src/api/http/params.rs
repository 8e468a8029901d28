//! The request shapes: job parameters (the JSON `params` part and the query string of a raw
//! upload), the query strings of the other routes, and the query-string parser that names the
//! parameter in its 400.

use crate::api::problem::{clip, Problem};
use crate::jobs::spec::{AnglesSpec, AxisSpec, BoundarySpec, FilterSpec, PrescribedSpec};
use crate::jobs::{parse_format, JobSpec};
use axum::http::Uri;
use serde::Deserialize;
use utoipa::IntoParams;
use willow::flow::region::{Region, Seam};
use willow::flow::{Method, Preserve};
use willow::mesh::io::Format;

/// The `params` part of a multipart upload: a [`JobSpec`] in JSON, every field optional (the
/// server's defaults fill the rest), unknown fields refused. It is the shape of a job's
/// reported `params`, so those can be sent again as they are. A type error names its field
/// (`filter.k`, `region[0].sphere.radius`).
pub fn spec_from_json(text: &[u8]) -> Result<JobSpec, Problem> {
    if text.trim_ascii_start().first() != Some(&b'{') {
        return Err(bad_field(
            "params",
            "the `params` part must be a JSON object",
        ));
    }
    let mut de = serde_json::Deserializer::from_slice(text);
    let spec: JobSpec = serde_path_to_error::deserialize(&mut de).map_err(|e| {
        // The path names the field, an unknown one included (`filter.x`); a document that is
        // not a JSON object at all has none.
        let field = e.path().to_string();
        let reason = clip(&e.into_inner().to_string());
        let field = if field == "." || field.is_empty() {
            "params".to_string()
        } else {
            field
        };
        bad_field(&field, format!("in the `params` part: {reason}"))
    })?;
    de.end()
        .map_err(|e| bad_field("params", format!("trailing characters after the JSON: {e}")))?;
    Ok(spec)
}

/// A parsed name, or 400 naming the field it came from.
fn named<T>(field: &str, parsed: Result<T, String>) -> Result<T, Problem> {
    parsed.map_err(|e| bad_field(field, clip(&e)))
}

/// 400 `invalid_parameter` naming `field`, as the core's own parameter errors do.
fn bad_field(field: &str, reason: impl std::fmt::Display) -> Problem {
    Problem::bad_request(
        "invalid_parameter",
        format!("invalid parameter `{field}`: {reason}"),
    )
    .with("field", field)
}

/// Job parameters in the query string of a raw upload: the [`JobSpec`] flattened, since a query
/// string has no nesting. The names are the JSON ones; nested fields are dotted paths (as Google's HTTP transcoding spells them), lists are comma
/// separated: `?filter.sigma=0.01&filter.k=2`,
/// `?boundary=prescribed&boundary.prescribed.frame_angle=0.2&boundary.prescribed.angles.per_loop=0.1,-0.1`.
/// Any `boundary.prescribed.*` parameter implies `boundary=prescribed`.
#[derive(Debug, Default, Clone, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct JobQuery {
    /// `conformal` (default), `mcf`, `cmcf`, `bilaplacian` or `taubin`.
    pub method: Option<String>,
    /// Flow steps to take (default 20).
    #[param(minimum = 1)]
    pub steps: Option<usize>,
    /// Time step τ (default 0.5; conformal needs 0 < τ < 1).
    pub tau: Option<f64>,
    /// Inverse iterations per step (default 1).
    pub iterations: Option<usize>,
    /// Keep positions every this many steps (default 1).
    pub frame_interval: Option<usize>,
    /// Send positions in frames (default true).
    pub include_positions: Option<bool>,
    /// Deadline in seconds from submission (default: the server's).
    pub deadline_secs: Option<f64>,
    /// Exactness constraints for genus > 0 (default true). Conformal flow only.
    pub exactness: Option<bool>,
    /// Möbius balancing (default false). Conformal flow only.
    pub mobius_balancing: Option<bool>,
    /// Spectral filter strength σ > 0, unitless; needs `filter.k`. Conformal flow only.
    #[serde(rename = "filter.sigma")]
    #[param(rename = "filter.sigma")]
    pub filter_sigma: Option<f64>,
    /// Spectral filter shape k, 0..=3; needs `filter.sigma`.
    #[serde(rename = "filter.k")]
    #[param(rename = "filter.k")]
    pub filter_k: Option<u32>,
    /// `free` (default), `fixed`, `cmc` or `prescribed`. Conformal flow only.
    pub boundary: Option<String>,
    /// Prescribed vectors: φ in radians, |φ| ≤ 1.5 (default 0).
    #[serde(rename = "boundary.prescribed.frame_angle")]
    #[param(rename = "boundary.prescribed.frame_angle")]
    pub frame_angle: Option<f64>,
    /// Prescribed vectors: `tangent` (the default rotation axis).
    #[serde(rename = "boundary.prescribed.axis")]
    #[param(rename = "boundary.prescribed.axis")]
    pub axis: Option<String>,
    /// Prescribed vectors: a fixed rotation axis `x,y,z`, finite and non-zero.
    #[serde(rename = "boundary.prescribed.axis.fixed")]
    #[param(rename = "boundary.prescribed.axis.fixed")]
    pub axis_fixed: Option<String>,
    /// Prescribed vectors: one rotation angle in radians for every boundary vertex (default 0).
    #[serde(rename = "boundary.prescribed.angles.uniform")]
    #[param(rename = "boundary.prescribed.angles.uniform")]
    pub angles_uniform: Option<f64>,
    /// Prescribed vectors: one angle per boundary loop, `a,b,…` (as many as the mesh has loops).
    #[serde(rename = "boundary.prescribed.angles.per_loop")]
    #[param(rename = "boundary.prescribed.angles.per_loop")]
    pub angles_per_loop: Option<String>,
    /// Safeguarded steps: a step that raises W or damages the mesh is retried at a smaller τ
    /// (default true). Every method.
    pub safeguard: Option<bool>,
    /// A spherical region that moves, `x,y,z,r` (everything else stays bit-identical).
    #[serde(rename = "region.sphere")]
    #[param(rename = "region.sphere")]
    pub region_sphere: Option<String>,
    /// A box region that moves, `xmin,ymin,zmin,xmax,ymax,zmax`.
    #[serde(rename = "region.box")]
    #[param(rename = "region.box")]
    pub region_box: Option<String>,
    /// A region of these file vertices, `i,j,k,...` (OBJ `v` lines from 0, glTF accessor
    /// vertices). Several `region.*` parameters name their union.
    #[serde(rename = "region.vertices")]
    #[param(rename = "region.vertices")]
    pub region_vertices: Option<String>,
    /// `smooth` (default) or `fixed`: how a region meets the surface around it.
    pub seam: Option<String>,
    /// What each component keeps after every step: `area` (default), `volume` or `none`.
    pub preserve: Option<String>,
    /// Stop once the Willmore energy is at most this (outcome `target_reached`).
    pub until_willmore: Option<f64>,
    /// Stop once W has stopped falling (default true; outcome `converged`).
    pub until_converged: Option<bool>,
    /// Stop before the first step that would move the surface further than this from the
    /// input, in model units (outcome `max_deviation`).
    pub max_deviation: Option<f64>,
    /// Report each frame's distance from the input (default false; on with `max_deviation`).
    pub measure_deviation: Option<bool>,
    /// Remove the detail smaller than this length, in model units, and keep the shape above
    /// it (outcome `feature_scale_reached`). Conformal flow only.
    pub feature_size: Option<f64>,
    /// Width, in model units, over which a region's motion blends to zero toward its border.
    pub falloff: Option<f64>,
    /// Where the job's end is POSTed as a signed Standard Webhooks event (https only unless
    /// the server allows insecure callbacks).
    pub callback_url: Option<String>,
    /// A region of the faces of this file group: an OBJ `g`/`o` name, a glTF node or mesh name.
    #[serde(rename = "region.group")]
    #[param(rename = "region.group")]
    pub region_group: Option<String>,
    /// Repair the upload first: drop degenerate faces, split non-manifold vertices and edges
    /// (default false); the answer's `repairs` says what changed.
    pub repair: Option<bool>,
    /// Loop-subdivide the upload (~16k triangles) before the flow, for tessellations too
    /// coarse to fair (default false); frame 0 then says `connectivity_changed`.
    pub refine: Option<bool>,
}

impl JobQuery {
    /// The job spec these parameters ask for (validated later by the core).
    pub fn into_spec(self) -> Result<JobSpec, Problem> {
        let filter = match (self.filter_sigma, self.filter_k) {
            (None, None) => None,
            (Some(sigma), Some(k)) => Some(FilterSpec { sigma, k }),
            (Some(_), None) => return Err(bad_field("filter.k", "required with `filter.sigma`")),
            (None, Some(_)) => return Err(bad_field("filter.sigma", "required with `filter.k`")),
        };
        let prescribed_given = self.frame_angle.is_some()
            || self.axis.is_some()
            || self.axis_fixed.is_some()
            || self.angles_uniform.is_some()
            || self.angles_per_loop.is_some();
        let boundary = match self.boundary.as_deref().map(str::to_ascii_lowercase) {
            None if !prescribed_given => None,
            None => Some(BoundarySpec::Prescribed(PrescribedSpec::default())),
            Some(name) => Some(match name.as_str() {
                "free" => BoundarySpec::Free,
                "fixed" => BoundarySpec::Fixed,
                "cmc" => BoundarySpec::Cmc,
                "prescribed" => BoundarySpec::Prescribed(PrescribedSpec::default()),
                other => {
                    return Err(bad_field(
                        "boundary",
                        format!("expected `free`, `fixed`, `cmc` or `prescribed`, got `{other}`"),
                    ))
                }
            }),
        };
        let boundary = match boundary {
            Some(BoundarySpec::Prescribed(mut p)) => {
                if let Some(a) = self.frame_angle {
                    p.frame_angle = a;
                }
                p.axis = match (self.axis.as_deref(), self.axis_fixed.as_deref()) {
                    (Some(_), Some(_)) => {
                        return Err(bad_field(
                            "boundary.prescribed.axis",
                            "give either `boundary.prescribed.axis=tangent` or `boundary.prescribed.axis.fixed=x,y,z`, not both",
                        ))
                    }
                    (Some(name), None) if name.eq_ignore_ascii_case("tangent") => {
                        AxisSpec::Tangent
                    }
                    (Some(other), None) => {
                        return Err(bad_field(
                            "boundary.prescribed.axis",
                            format!(
                                "expected `tangent` (a fixed axis is `boundary.prescribed.axis.fixed=x,y,z`), got `{other}`"
                            ),
                        ))
                    }
                    (None, Some(text)) => {
                        let field = "boundary.prescribed.axis.fixed";
                        let v = parse_list(field, text)?;
                        let xyz: [f64; 3] = v.try_into().map_err(|v: Vec<f64>| {
                            bad_field(field, format!("expected 3 numbers x,y,z, got {}", v.len()))
                        })?;
                        AxisSpec::Fixed(xyz)
                    }
                    (None, None) => AxisSpec::Tangent,
                };
                p.angles = match (self.angles_uniform, self.angles_per_loop.as_deref()) {
                    (Some(_), Some(_)) => {
                        return Err(bad_field(
                            "boundary.prescribed.angles",
                            "give either `angles.uniform` or `angles.per_loop`, not both",
                        ))
                    }
                    (Some(a), None) => AnglesSpec::Uniform(a),
                    (None, Some(text)) => AnglesSpec::PerLoop(parse_list(
                        "boundary.prescribed.angles.per_loop",
                        text,
                    )?),
                    (None, None) => AnglesSpec::default(),
                };
                Some(BoundarySpec::Prescribed(p))
            }
            Some(other) if prescribed_given => {
                return Err(bad_field(
                    "boundary",
                    format!(
                        "`boundary.prescribed.*` parameters need `boundary=prescribed`, got `{}`",
                        serde_json::to_string(&other)
                            .unwrap_or_default()
                            .trim_matches('"')
                    ),
                ))
            }
            other => other,
        };
        let defaults = JobSpec::default();
        Ok(JobSpec {
            method: match self.method {
                Some(m) => named("method", Method::parse(&m))?,
                None => defaults.method,
            },
            steps: self.steps.unwrap_or(defaults.steps),
            tau: self.tau.unwrap_or(defaults.tau),
            iterations: self.iterations.unwrap_or(defaults.iterations),
            frame_interval: self.frame_interval.unwrap_or(defaults.frame_interval),
            include_positions: self.include_positions.unwrap_or(defaults.include_positions),
            deadline_secs: self.deadline_secs,
            exactness: self.exactness.unwrap_or(defaults.exactness),
            mobius_balancing: self.mobius_balancing.unwrap_or(defaults.mobius_balancing),
            filter,
            boundary: boundary.unwrap_or(defaults.boundary),
            safeguard: self.safeguard.unwrap_or(defaults.safeguard),
            region: query_regions(
                self.region_sphere.as_deref(),
                self.region_box.as_deref(),
                self.region_vertices.as_deref(),
            )?
            .unwrap_or_default()
            .into_iter()
            .chain(self.region_group.map(Region::Group))
            .collect(),
            seam: match self.seam {
                Some(v) => named("seam", Seam::parse(&v))?,
                None => defaults.seam,
            },
            preserve: match self.preserve {
                Some(v) => named("preserve", Preserve::parse(&v))?,
                None => defaults.preserve,
            },
            until_willmore: self.until_willmore,
            until_converged: self.until_converged.unwrap_or(defaults.until_converged),
            max_deviation: self.max_deviation,
            measure_deviation: self.measure_deviation.unwrap_or(defaults.measure_deviation),
            feature_size: self.feature_size,
            falloff: self.falloff,
            repair: self.repair.unwrap_or(defaults.repair),
            refine: self.refine.unwrap_or(defaults.refine),
            callback_url: self.callback_url.clone(),
        })
    }
}

/// The regions the `region.*` query parameters name (`None` if none is given), each in the
/// library's text form.
fn query_regions(
    sphere: Option<&str>,
    cuboid: Option<&str>,
    vertices: Option<&str>,
) -> Result<Option<Vec<Region>>, Problem> {
    type Parse = fn(&str) -> Result<Region, String>;
    let forms: [(&str, Option<&str>, Parse); 3] = [
        ("region.sphere", sphere, Region::parse_sphere),
        ("region.box", cuboid, Region::parse_box),
        ("region.vertices", vertices, Region::parse_vertices),
    ];
    let mut regions = Vec::new();
    for (field, text, parse) in forms {
        if let Some(text) = text {
            regions.push(parse(text).map_err(|e| bad_field(field, clip(&e)))?);
        }
    }
    Ok((!regions.is_empty()).then_some(regions))
}

/// Comma-separated numbers (`0.1,-0.2`); empty text is an empty list.
fn parse_list(field: &str, text: &str) -> Result<Vec<f64>, Problem> {
    if text.trim().is_empty() {
        return Ok(Vec::new());
    }
    text.split(',')
        .map(|t| {
            t.trim()
                .parse::<f64>()
                .map_err(|_| bad_field(field, format!("`{}` is not a number", t.trim())))
        })
        .collect()
}

#[derive(Debug, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct ListQuery {
    /// Only jobs in this state.
    pub state: Option<String>,
    /// 1..1000 (default 50).
    pub page_size: Option<usize>,
    pub page_token: Option<String>,
}

#[derive(Debug, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct FramesQuery {
    /// First step to return (default 0).
    pub from_step: Option<usize>,
    /// 1..10000 (default 100).
    pub page_size: Option<usize>,
}

#[derive(Debug, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct FormatQuery {
    /// `glb`, `gltf` or `obj`. Default: a frame is `glb`; the result is in the input's own
    /// format, as gRPC `DownloadResult` sends it (what you upload is what you get back).
    pub format: Option<String>,
}

#[derive(Debug, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct EventsQuery {
    /// First step to replay (default 0). The `Last-Event-ID` header, when sent, wins: the
    /// stream resumes after that step.
    pub from_step: Option<usize>,
}

/// The query string as `T`. Parsed here rather than by axum's `Query`, whose rejection is text
/// without the parameter's name: a type error (`?tau=abc`, `?steps=1.5`) becomes 400
/// `invalid_parameter` with `field` = the parameter, as every other parameter error does.
pub(super) fn query<T: serde::de::DeserializeOwned>(uri: &Uri) -> Result<T, Problem> {
    let raw = uri.query().unwrap_or("");
    let de = serde_urlencoded::Deserializer::new(form_urlencoded::parse(raw.as_bytes()));
    serde_path_to_error::deserialize(de).map_err(|e| {
        let field = e.path().to_string();
        let inner = e.into_inner().to_string();
        // An unknown parameter has no path (it is not a field of `T`): name it from the message.
        let field = if field.is_empty() || field == "." || field == "?" {
            unknown_field_name(&inner).unwrap_or_default()
        } else {
            field
        };
        if field.is_empty() {
            Problem::bad_request(
                "invalid_parameter",
                format!("invalid query string: {}", clip(&inner)),
            )
        } else {
            bad_field(&field, clip(&inner))
        }
    })
}

/// The name in serde's "unknown field `x`, expected …".
fn unknown_field_name(message: &str) -> Option<String> {
    let rest = message.strip_prefix("unknown field `")?;
    Some(rest.split_once('`')?.0.to_string())
}

/// The requested output format; `None` when the query names none (each route has its default).
pub(super) fn parse_out_format(q: &FormatQuery) -> Result<Option<Format>, Problem> {
    match &q.format {
        None => Ok(None),
        Some(f) => parse_format(f).map(Some).ok_or_else(|| {
            Problem::bad_request(
                "invalid_parameter",
                format!(
                    "invalid parameter `format`: expected `glb`, `gltf`, `obj`, `stl`, `ply` or `off`, got `{}`",
                    clip(f)
                ),
            )
            .with("field", "format")
        }),
    }
}
