//! Wire conversion: requests → the core's types (names, formats, methods, parameters,
//! boundaries, request ids, filters, deadlines) and the core's types → responses (jobs,
//! operations, frames, metrics, curves, failures).

use std::collections::HashMap;
use std::time::Duration;

use bytes::Bytes;
use prost::Message as _;
use tonic::{Code, Request, Status};

use super::errors::{bad_request, clip, ERROR_DOMAIN};
use super::pb::google::longrunning as lro;
use super::pb::willow::v1;
use crate::jobs::curve::CurveOutcome;
use crate::jobs::spec::{AnglesSpec, AxisSpec, BoundarySpec, FilterSpec, PrescribedSpec};
use crate::jobs::{Frame, JobSpec, JobState, JobStatus};
use willow::flow::region::{Region, Seam};
use willow::flow::{Method, Preserve};
use willow::mesh::io::Format;
use willow::metrics::StepMetrics;

/// `type_url` of a `willow.v1.Job` packed in `google.protobuf.Any` (Operation metadata and
/// response). The `type.googleapis.com/` prefix is what every protobuf runtime expects.
const JOB_TYPE_URL: &str = "type.googleapis.com/willow.v1.Job";

/// `type_url` of `google.rpc.ErrorInfo`, attached to a failed job's `google.rpc.Status`.
const ERROR_INFO_TYPE_URL: &str = "type.googleapis.com/google.rpc.ErrorInfo";

// ---------------------------------------------------------------------------------------------
// Requests → core types.

/// The id in `{prefix}{id}` (`jobs/…`, `uploads/…`), or INVALID_ARGUMENT naming `field`.
pub(super) fn parse_name(field: &str, prefix: &str, name: &str) -> Result<String, Status> {
    match name.strip_prefix(prefix) {
        Some(id) if !id.is_empty() && !id.contains('/') => Ok(id.to_string()),
        _ => Err(bad_request(
            field,
            format!("must be `{prefix}{{id}}`, got `{}`", clip(name)),
        )),
    }
}

pub(super) fn page_size(raw: i32) -> Result<usize, Status> {
    usize::try_from(raw).map_err(|_| bad_request("page_size", format!("must be >= 0, got {raw}")))
}

pub(super) fn format_from_pb(field: &str, raw: i32) -> Result<Format, Status> {
    match v1::MeshFormat::try_from(raw) {
        Ok(v1::MeshFormat::Obj) => Ok(Format::Obj),
        Ok(v1::MeshFormat::Gltf) => Ok(Format::Gltf),
        Ok(v1::MeshFormat::Glb) => Ok(Format::Glb),
        Ok(v1::MeshFormat::Stl) => Ok(Format::Stl),
        Ok(v1::MeshFormat::Ply) => Ok(Format::Ply),
        Ok(v1::MeshFormat::Off) => Ok(Format::Off),
        Ok(v1::MeshFormat::Unspecified) => Err(bad_request(
            field,
            "required: MESH_FORMAT_OBJ, MESH_FORMAT_GLTF, MESH_FORMAT_GLB, MESH_FORMAT_STL, \
             MESH_FORMAT_PLY or MESH_FORMAT_OFF",
        )),
        Err(_) => Err(bad_request(field, format!("unknown mesh format {raw}"))),
    }
}

pub(super) fn format_pb(format: Format) -> v1::MeshFormat {
    match format {
        Format::Obj => v1::MeshFormat::Obj,
        Format::Gltf => v1::MeshFormat::Gltf,
        Format::Glb => v1::MeshFormat::Glb,
        Format::Stl => v1::MeshFormat::Stl,
        Format::Ply => v1::MeshFormat::Ply,
        Format::Off => v1::MeshFormat::Off,
    }
}

/// `METHOD_CONFORMAL` ↔ [`Method::Conformal`] by name: the proto value is `METHOD_` + the
/// method's serde name upper-cased. Matching by name (not an exhaustive `match`) means a flow
/// added to the library is refused cleanly until its proto value is added, and adding the
/// value is all it takes to expose it; no Rust change here.
fn method_from_pb(raw: i32) -> Result<Method, Status> {
    let value = match v1::Method::try_from(raw) {
        Ok(v1::Method::Unspecified) => return Ok(JobSpec::default().method),
        Ok(value) => value,
        Err(_) => {
            return Err(bad_request(
                "params.method",
                format!("unknown method {raw}"),
            ))
        }
    };
    Method::parse(value.as_str_name().trim_start_matches("METHOD_")).map_err(|_| {
        bad_request(
            "params.method",
            format!("{} is not supported by this server", value.as_str_name()),
        )
    })
}

/// The inverse of [`method_from_pb`]; a method without a proto value yet reports
/// `METHOD_UNSPECIFIED`.
fn method_pb(method: Method) -> v1::Method {
    v1::Method::from_str_name(&format!("METHOD_{}", method.name().to_ascii_uppercase()))
        .unwrap_or(v1::Method::Unspecified)
}

pub(super) fn duration_from_pb(field: &str, d: &prost_types::Duration) -> Result<Duration, Status> {
    // prost-types checks sign consistency and nanos range for us.
    Duration::try_from(*d).map_err(|_| {
        bad_request(
            field,
            format!(
                "must be a non-negative duration, got {}s {}ns",
                d.seconds, d.nanos
            ),
        )
    })
}

/// Wire parameters → [`JobSpec`], unset fields taking the defaults. Range checks are the core's
/// ([`JobSpec::validate`], run by `submit`), so HTTP and gRPC refuse the same values.
pub(super) fn spec_from_pb(params: Option<v1::JobParams>) -> Result<JobSpec, Status> {
    let mut spec = JobSpec::default();
    let Some(p) = params else {
        return Ok(spec);
    };
    spec.method = method_from_pb(p.method)?;
    if let Some(steps) = p.steps {
        spec.steps = steps as usize;
    }
    if let Some(tau) = p.tau {
        spec.tau = tau;
    }
    if let Some(iterations) = p.iterations {
        spec.iterations = iterations as usize;
    }
    if let Some(interval) = p.frame_interval {
        spec.frame_interval = interval as usize;
    }
    if let Some(include) = p.include_positions {
        spec.include_positions = include;
    }
    if let Some(deadline) = p.deadline {
        let d = duration_from_pb("params.deadline", &deadline)?;
        if d.is_zero() {
            return Err(bad_request("params.deadline", "must be > 0 when set"));
        }
        spec.deadline_secs = Some(d.as_secs_f64());
    }
    if let Some(exactness) = p.exactness {
        spec.exactness = exactness;
    }
    if let Some(mobius) = p.mobius_balancing {
        spec.mobius_balancing = mobius;
    }
    spec.filter = p.filter.map(|f| FilterSpec {
        sigma: f.sigma,
        k: f.k,
    });
    if let Some(boundary) = p.boundary {
        spec.boundary = boundary_from_pb(boundary);
    }
    if let Some(safeguard) = p.safeguard {
        spec.safeguard = safeguard;
    }
    spec.region = p
        .region
        .into_iter()
        .enumerate()
        .map(|(i, r)| region_from_pb(i, r))
        .collect::<Result<_, _>>()?;
    spec.seam = match v1::Seam::try_from(p.seam) {
        Ok(v1::Seam::Unspecified) => spec.seam,
        Ok(v1::Seam::Smooth) => Seam::Smooth,
        Ok(v1::Seam::Fixed) => Seam::Fixed,
        Err(_) => {
            return Err(bad_request(
                "params.seam",
                format!("unknown seam {}", p.seam),
            ))
        }
    };
    spec.preserve = match v1::Preserve::try_from(p.preserve) {
        Ok(v1::Preserve::Unspecified) => spec.preserve,
        Ok(v1::Preserve::Area) => Preserve::Area,
        Ok(v1::Preserve::Volume) => Preserve::Volume,
        Ok(v1::Preserve::None) => Preserve::None,
        Err(_) => {
            return Err(bad_request(
                "params.preserve",
                format!("unknown preserve {}", p.preserve),
            ))
        }
    };
    spec.until_willmore = p.until_willmore;
    if let Some(v) = p.until_converged {
        spec.until_converged = v;
    }
    spec.max_deviation = p.max_deviation;
    if let Some(v) = p.measure_deviation {
        spec.measure_deviation = v;
    }
    spec.feature_size = p.feature_size;
    spec.falloff = p.falloff;
    if let Some(v) = p.repair {
        spec.repair = v;
    }
    if let Some(v) = p.refine {
        spec.refine = v;
    }
    spec.refine_edge = p.refine_edge;
    spec.callback_url = p.callback_url.filter(|u| !u.is_empty());
    if let Some(text) = p.fill_holes.as_deref().filter(|t| !t.is_empty()) {
        spec.fill_holes = Some(
            willow::mesh::holes::HoleSize::parse(text)
                .map_err(|reason| bad_request("params.fill_holes", reason))?,
        );
    }
    if let Some(text) = p.feature_angle.as_deref().filter(|t| !t.is_empty()) {
        spec.feature_angle = willow::mesh::creases::FeatureAngle::parse(text)
            .map_err(|reason| bad_request("params.feature_angle", reason))?;
    }
    if let Some(d) = p.denoise {
        if let Some(n) = d.iterations {
            spec.denoise.iterations = Some(n as usize);
        }
        if let Some(n) = d.vertex_iterations {
            spec.denoise.vertex_iterations = n as usize;
        }
        if let Some(v) = d.sigma_r {
            spec.denoise.sigma_r = v;
        }
        if let Some(v) = d.radius {
            spec.denoise.radius = v;
        }
        if let Some(v) = d.guided {
            spec.denoise.guided = v;
        }
    }
    Ok(spec)
}

/// Wire region → [`Region`]; an empty oneof or a missing vector names the field.
fn region_from_pb(i: usize, r: v1::Region) -> Result<Region, Status> {
    use v1::region::Shape;
    let field = |name: &str| format!("params.region[{i}]{name}");
    let xyz = |v: Option<v1::Vector3>, name: &str| {
        v.map(|v| [v.x, v.y, v.z])
            .ok_or_else(|| bad_request(&field(name), "must be set"))
    };
    match r.shape {
        None => Err(bad_request(
            &field(""),
            "set one of `sphere`, `box`, `vertices` or `group`",
        )),
        Some(Shape::Sphere(s)) => Ok(Region::Sphere {
            center: xyz(s.center, ".sphere.center")?,
            radius: s.radius,
        }),
        Some(Shape::Box(b)) => Ok(Region::Box {
            min: xyz(b.min, ".box.min")?,
            max: xyz(b.max, ".box.max")?,
        }),
        Some(Shape::Vertices(list)) => list
            .indices
            .into_iter()
            .map(|v| {
                usize::try_from(v).map_err(|_| {
                    bad_request(&field(".vertices"), format!("vertex {v} is out of range"))
                })
            })
            .collect::<Result<_, _>>()
            .map(Region::Vertices),
        Some(Shape::Group(name)) => Ok(Region::Group(name)),
    }
}

/// [`Region`] → wire.
fn region_pb(r: &Region) -> v1::Region {
    use v1::region::{Box as PbBox, Shape, Sphere, VertexList};
    let v = |[x, y, z]: [f64; 3]| Some(v1::Vector3 { x, y, z });
    v1::Region {
        shape: Some(match r {
            Region::Sphere { center, radius } => Shape::Sphere(Sphere {
                center: v(*center),
                radius: *radius,
            }),
            Region::Box { min, max } => Shape::Box(PbBox {
                min: v(*min),
                max: v(*max),
            }),
            Region::Vertices(list) => Shape::Vertices(VertexList {
                indices: list.iter().map(|&i| i as u64).collect(),
            }),
            Region::Group(name) => Shape::Group(name.clone()),
        }),
    }
}

/// Wire boundary → [`BoundarySpec`]. Unset oneofs take the defaults the proto documents
/// (auto; tangent axis; uniform 0); the numbers are checked by [`JobSpec::validate`].
fn boundary_from_pb(boundary: v1::Boundary) -> BoundarySpec {
    use v1::boundary::Condition;
    match boundary.condition {
        None | Some(Condition::Auto(())) => BoundarySpec::Auto,
        Some(Condition::Free(())) => BoundarySpec::Free,
        Some(Condition::Fixed(())) => BoundarySpec::Fixed,
        Some(Condition::Cmc(())) => BoundarySpec::Cmc,
        Some(Condition::Prescribed(p)) => BoundarySpec::Prescribed(PrescribedSpec {
            frame_angle: p.frame_angle,
            axis: match p.axis.and_then(|a| a.axis) {
                None | Some(v1::rotation_axis::Axis::Tangent(())) => AxisSpec::Tangent,
                Some(v1::rotation_axis::Axis::Fixed(v)) => AxisSpec::Fixed([v.x, v.y, v.z]),
            },
            angles: match p.angles.and_then(|a| a.angles) {
                None => AnglesSpec::default(),
                Some(v1::boundary_angles::Angles::Uniform(a)) => AnglesSpec::Uniform(a),
                Some(v1::boundary_angles::Angles::PerLoop(list)) => {
                    AnglesSpec::PerLoop(list.values)
                }
            },
        }),
    }
}

/// [`BoundarySpec`] → wire, every oneof set (GetJob reports the effective condition).
fn boundary_pb(boundary: &BoundarySpec) -> v1::Boundary {
    use v1::boundary::Condition;
    let condition = match boundary {
        BoundarySpec::Auto => Condition::Auto(()),
        BoundarySpec::Free => Condition::Free(()),
        BoundarySpec::Fixed => Condition::Fixed(()),
        BoundarySpec::Cmc => Condition::Cmc(()),
        BoundarySpec::Prescribed(p) => Condition::Prescribed(v1::PrescribedVectors {
            frame_angle: p.frame_angle,
            axis: Some(v1::RotationAxis {
                axis: Some(match p.axis {
                    AxisSpec::Tangent => v1::rotation_axis::Axis::Tangent(()),
                    AxisSpec::Fixed([x, y, z]) => {
                        v1::rotation_axis::Axis::Fixed(v1::Vector3 { x, y, z })
                    }
                }),
            }),
            angles: Some(v1::BoundaryAngles {
                angles: Some(match &p.angles {
                    AnglesSpec::Uniform(a) => v1::boundary_angles::Angles::Uniform(*a),
                    AnglesSpec::PerLoop(values) => {
                        v1::boundary_angles::Angles::PerLoop(v1::AngleList {
                            values: values.clone(),
                        })
                    }
                }),
            }),
        }),
    };
    v1::Boundary {
        condition: Some(condition),
    }
}

/// AIP-155: `request_id` is optional and, when set, a UUID (any version, any case).
pub(super) fn request_id(raw: &str) -> Result<Option<String>, Status> {
    if raw.is_empty() {
        return Ok(None);
    }
    let bytes = raw.as_bytes();
    let is_uuid = bytes.len() == 36
        && bytes.iter().enumerate().all(|(i, b)| match i {
            8 | 13 | 18 | 23 => *b == b'-',
            _ => b.is_ascii_hexdigit(),
        });
    if !is_uuid {
        return Err(bad_request(
            "request_id",
            format!("must be a UUID (AIP-155), got `{}`", clip(raw)),
        ));
    }
    // Case-insensitive: the same UUID in upper case is the same request.
    Ok(Some(raw.to_ascii_lowercase()))
}

pub(super) fn state_from_pb(state: v1::job::State) -> JobState {
    match state {
        v1::job::State::Unspecified | v1::job::State::Queued => JobState::Queued,
        v1::job::State::Running => JobState::Running,
        v1::job::State::Succeeded => JobState::Succeeded,
        v1::job::State::Failed => JobState::Failed,
        v1::job::State::Cancelled => JobState::Cancelled,
    }
}

/// `ListOperations.filter`: empty, `done=true|false` is not offered (a state says more), so we
/// accept `state=QUEUED|RUNNING|SUCCEEDED|FAILED|CANCELLED` (case-insensitive, spaces allowed).
pub(super) fn parse_operation_filter(filter: &str) -> Result<Option<JobState>, Status> {
    let filter = filter.trim();
    if filter.is_empty() {
        return Ok(None);
    }
    let value = filter
        .split_once('=')
        .filter(|(key, _)| key.trim().eq_ignore_ascii_case("state"))
        .map(|(_, value)| value.trim().trim_matches('"').to_ascii_uppercase());
    match value.as_deref().and_then(v1::job::State::from_str_name) {
        Some(v1::job::State::Unspecified) | None => Err(bad_request(
            "filter",
            format!(
                "supported: `state=QUEUED|RUNNING|SUCCEEDED|FAILED|CANCELLED`, got `{}`",
                clip(filter)
            ),
        )),
        Some(state) => Ok(Some(state_from_pb(state))),
    }
}

/// The client's deadline from the `grpc-timeout` header (`<digits><unit>`, gRPC over HTTP/2
/// spec). tonic's own server reads it, but behind `axum::serve` nobody does, so we parse it.
pub(super) fn grpc_timeout<T>(request: &Request<T>) -> Option<Duration> {
    let value = request.metadata().get("grpc-timeout")?.to_str().ok()?;
    let split = value.len().checked_sub(1)?;
    let (digits, unit) = value.split_at(split);
    let n: u64 = digits.parse().ok()?;
    Some(match unit {
        "H" => Duration::from_secs(n.saturating_mul(3600)),
        "M" => Duration::from_secs(n.saturating_mul(60)),
        "S" => Duration::from_secs(n),
        "m" => Duration::from_millis(n),
        "u" => Duration::from_micros(n),
        "n" => Duration::from_nanos(n),
        _ => return None,
    })
}

mod answers;
pub(super) use answers::*;

#[cfg(test)]
mod tests {
    use super::*;
    use tonic_types::StatusExt;

    #[test]
    fn methods_round_trip_through_their_proto_names() {
        for m in [
            Method::Conformal,
            Method::Mcf,
            Method::Cmcf,
            Method::Bilaplacian,
            Method::Taubin,
            Method::Denoise,
        ] {
            let wire = method_pb(m);
            assert_ne!(wire, v1::Method::Unspecified, "{m:?} has no proto value");
            assert_eq!(method_from_pb(wire as i32).ok(), Some(m));
        }
        assert_eq!(
            method_from_pb(0).ok(),
            Some(JobSpec::default().method),
            "unspecified takes the default"
        );
        assert_eq!(
            method_from_pb(999).map_err(|s| s.code()).err(),
            Some(Code::InvalidArgument)
        );
    }

    #[test]
    fn names_must_have_their_collection_prefix() {
        assert_eq!(
            parse_name("name", "jobs/", "jobs/abc").ok().as_deref(),
            Some("abc")
        );
        for bad in ["abc", "jobs/", "jobs/a/b", "uploads/abc", ""] {
            let status = parse_name("name", "jobs/", bad).err();
            let status = status.unwrap_or_else(|| panic!("`{bad}` was accepted"));
            assert_eq!(status.code(), Code::InvalidArgument);
            let violations = status
                .get_details_bad_request()
                .map(|b| b.field_violations)
                .unwrap_or_default();
            assert_eq!(violations.len(), 1);
            assert_eq!(violations[0].field, "name");
        }
    }

    #[test]
    fn request_ids_must_be_uuids() {
        assert_eq!(request_id("").ok(), Some(None));
        assert_eq!(
            request_id("3F2504E0-4F89-11D3-9A0C-0305E82C3301").ok(),
            Some(Some("3f2504e0-4f89-11d3-9a0c-0305e82c3301".to_string()))
        );
        for bad in [
            "retry-1",
            "3f2504e0-4f89-11d3-9a0c-0305e82c330",
            "3f2504e0x4f89-11d3-9a0c-0305e82c3301",
        ] {
            assert_eq!(
                request_id(bad).err().map(|s| s.code()),
                Some(Code::InvalidArgument)
            );
        }
    }

    #[test]
    fn grpc_timeout_header_units() {
        let mut r = Request::new(());
        assert_eq!(grpc_timeout(&r), None);
        for (text, want) in [
            ("5S", Duration::from_secs(5)),
            ("250m", Duration::from_millis(250)),
            ("2M", Duration::from_secs(120)),
            ("7u", Duration::from_micros(7)),
        ] {
            r.metadata_mut()
                .insert("grpc-timeout", text.parse().expect("ascii header value"));
            assert_eq!(grpc_timeout(&r), Some(want), "{text}");
        }
        r.metadata_mut()
            .insert("grpc-timeout", "5x".parse().expect("ascii"));
        assert_eq!(grpc_timeout(&r), None);
    }

    #[test]
    fn positions_are_packed_little_endian_xyz() {
        let bytes = positions_bytes(&[[1.0, -2.0, 0.5], [3.0, 4.0, 5.0]]);
        assert_eq!(bytes.len(), 24);
        assert_eq!(&bytes[0..4], &1.0f32.to_le_bytes());
        assert_eq!(&bytes[4..8], &(-2.0f32).to_le_bytes());
        assert_eq!(&bytes[20..24], &5.0f32.to_le_bytes());
    }

    #[test]
    fn operation_filter() {
        assert_eq!(parse_operation_filter("").ok(), Some(None));
        assert_eq!(
            parse_operation_filter(" state = running ").ok(),
            Some(Some(JobState::Running))
        );
        assert!(parse_operation_filter("done=true").is_err());
        assert!(parse_operation_filter("state=STATE_UNSPECIFIED").is_err());
    }

    #[test]
    fn boundaries_round_trip_through_the_wire() {
        for b in [
            BoundarySpec::Auto,
            BoundarySpec::Free,
            BoundarySpec::Fixed,
            BoundarySpec::Cmc,
            BoundarySpec::Prescribed(PrescribedSpec {
                frame_angle: -0.4,
                axis: AxisSpec::Fixed([1.0, 0.0, 0.5]),
                angles: AnglesSpec::PerLoop(vec![0.25, -0.5]),
            }),
            BoundarySpec::Prescribed(PrescribedSpec {
                frame_angle: 0.1,
                axis: AxisSpec::Tangent,
                angles: AnglesSpec::Uniform(0.3),
            }),
        ] {
            assert_eq!(boundary_from_pb(boundary_pb(&b)), b);
        }
        // Empty messages take the documented defaults.
        assert_eq!(
            boundary_from_pb(v1::Boundary::default()),
            BoundarySpec::Auto
        );
        let bare = v1::Boundary {
            condition: Some(v1::boundary::Condition::Prescribed(
                v1::PrescribedVectors::default(),
            )),
        };
        assert_eq!(
            boundary_from_pb(bare),
            BoundarySpec::Prescribed(PrescribedSpec::default())
        );
    }
}
