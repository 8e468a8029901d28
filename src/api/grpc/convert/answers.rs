//! Core types → responses: jobs, frames, metrics, operations and curves as the wire sends
//! them. The request side (and the names both sides share) is [`super`].

use super::*;

pub(super) fn timestamp(ms: u64) -> prost_types::Timestamp {
    prost_types::Timestamp {
        seconds: (ms / 1000) as i64,
        // < 1e9 by construction.
        nanos: ((ms % 1000) * 1_000_000) as i32,
    }
}

/// Saturating `usize` → `u32` for counts on the wire (steps are limited far below u32::MAX).
pub(super) fn count(n: usize) -> u32 {
    u32::try_from(n).unwrap_or(u32::MAX)
}

pub(super) fn state_pb(state: JobState) -> v1::job::State {
    match state {
        JobState::Queued => v1::job::State::Queued,
        JobState::Running => v1::job::State::Running,
        JobState::Succeeded => v1::job::State::Succeeded,
        JobState::Failed => v1::job::State::Failed,
        JobState::Cancelled => v1::job::State::Cancelled,
    }
}

pub(super) fn params_pb(spec: &JobSpec) -> v1::JobParams {
    v1::JobParams {
        method: method_pb(spec.method) as i32,
        steps: Some(count(spec.steps)),
        tau: Some(spec.tau),
        iterations: Some(count(spec.iterations)),
        frame_interval: Some(count(spec.frame_interval)),
        include_positions: Some(spec.include_positions),
        deadline: spec
            .deadline_secs
            .and_then(|s| Duration::try_from_secs_f64(s).ok())
            .and_then(|d| prost_types::Duration::try_from(d).ok()),
        exactness: Some(spec.exactness),
        mobius_balancing: Some(spec.mobius_balancing),
        filter: spec.filter.map(|f| v1::SpectralFilter {
            sigma: f.sigma,
            k: f.k,
        }),
        boundary: Some(boundary_pb(&spec.boundary)),
        safeguard: Some(spec.safeguard),
        region: spec.region.iter().map(region_pb).collect(),
        seam: match spec.seam {
            Seam::Smooth => v1::Seam::Smooth,
            Seam::Fixed => v1::Seam::Fixed,
        } as i32,
        preserve: match spec.preserve {
            Preserve::Area => v1::Preserve::Area,
            Preserve::Volume => v1::Preserve::Volume,
            Preserve::None => v1::Preserve::None,
        } as i32,
        until_willmore: spec.until_willmore,
        until_converged: Some(spec.until_converged),
        max_deviation: spec.max_deviation,
        measure_deviation: Some(spec.measure_deviation),
        feature_size: spec.feature_size,
        falloff: spec.falloff,
        repair: Some(spec.repair),
        refine: Some(spec.refine),
        refine_edge: spec.refine_edge,
        callback_url: spec.callback_url.clone(),
        feature_angle: Some(match spec.feature_angle {
            willow::mesh::creases::FeatureAngle::Auto => "auto".to_string(),
            willow::mesh::creases::FeatureAngle::None => "none".to_string(),
            willow::mesh::creases::FeatureAngle::Degrees(d) => d.to_string(),
        }),
        fill_holes: spec.fill_holes.map(|size| match size {
            willow::mesh::holes::HoleSize::Any => "all".to_string(),
            willow::mesh::holes::HoleSize::Vertices(n) => n.to_string(),
            willow::mesh::holes::HoleSize::Extent(d) => format!("{d:?}"),
        }),
        denoise: Some(v1::DenoiseParams {
            iterations: spec.denoise.iterations.map(count),
            vertex_iterations: Some(count(spec.denoise.vertex_iterations)),
            sigma_r: Some(spec.denoise.sigma_r),
            radius: Some(spec.denoise.radius),
            guided: Some(spec.denoise.guided),
        }),
    }
}

pub(super) fn curve_pb(points: &[[f64; 2]], closed: bool) -> v1::Curve {
    v1::Curve {
        xy: points.iter().flat_map(|p| [p[0], p[1]]).collect(),
        closed,
    }
}

pub(in crate::api::grpc) fn curve_response_pb(outcome: &CurveOutcome) -> v1::FairCurveResponse {
    let closed = outcome.curve.closed;
    v1::FairCurveResponse {
        curve: Some(curve_pb(&outcome.curve.points, closed)),
        metrics: outcome
            .metrics
            .iter()
            .map(|m| v1::CurveStepMetrics {
                step: count(m.step),
                energy: m.energy,
                curvature_std_over_mean: m.curvature_std_over_mean,
                max_edge_length_distortion: m.max_edge_length_distortion,
                closure_gap: m.closure_gap,
                poisson_residual: m.poisson_residual,
                total_length: m.total_length,
                total_curvature: m.total_curvature,
                step_ms: m.step_ms,
            })
            .collect(),
        frames: outcome
            .frames
            .iter()
            .map(|f| v1::CurveFrame {
                step: count(f.step),
                curve: Some(curve_pb(&f.points, closed)),
            })
            .collect(),
        steps: count(outcome.spec.steps),
        tau: outcome.spec.tau,
        frame_interval: outcome.spec.frame_interval.map_or(0, count),
        deadline: outcome
            .spec
            .deadline_secs
            .and_then(|s| Duration::try_from_secs_f64(s).ok())
            .and_then(|d| prost_types::Duration::try_from(d).ok()),
    }
}

pub(super) fn metrics_pb(m: &StepMetrics) -> v1::StepMetrics {
    v1::StepMetrics {
        step: count(m.step),
        willmore_energy: m.willmore_energy,
        q_mean: m.q_mean,
        q_area_mean: m.q_area_mean,
        q_p95: m.q_p95,
        q_max: m.q_max,
        closure_residual: m.closure_residual,
        eigen_residual: m.eigen_residual,
        area: m.area,
        step_ms: m.step_ms,
        tau: m.tau,
        rejected: m.rejected,
        volume: m.volume,
        deviation_max: m.deviation_max,
        deviation_mean: m.deviation_mean,
        willmore_energy_vector: m.willmore_energy_vector,
        log_area_ratio_p1: m.log_area_ratio_p1,
        log_area_ratio_p99: m.log_area_ratio_p99,
        collapsed_triangles: m.collapsed_triangles,
        crease_edges: m.crease_edges,
    }
}

/// Positions as the proto documents them: packed little-endian f32 x, y, z per vertex.
pub(super) fn positions_bytes(positions: &[[f32; 3]]) -> Bytes {
    let mut out = Vec::with_capacity(positions.len() * 12);
    for p in positions {
        for c in p {
            out.extend_from_slice(&c.to_le_bytes());
        }
    }
    Bytes::from(out)
}

pub(in crate::api::grpc) fn frame_pb(frame: &Frame) -> v1::Frame {
    v1::Frame {
        step: count(frame.step),
        metrics: Some(metrics_pb(&frame.metrics)),
        positions: frame
            .positions
            .as_deref()
            .map(|p| positions_bytes(&p.relative)),
        origin: frame
            .positions
            .as_deref()
            .filter(|p| !p.at_zero())
            .map(|p| {
                let [x, y, z] = p.origin;
                v1::Vector3 { x, y, z }
            }),
        connectivity_changed: frame.connectivity_changed,
    }
}

/// Why a job failed or was cancelled, as a `google.rpc.Status` (Job.error, Operation.error).
/// The core's machine-readable `error_code` picks the canonical code (in the one table,
/// [`crate::api::status::of_failure`]) and rides along as `ErrorInfo.reason`.
pub(super) fn job_failure(status: &JobStatus) -> Option<tonic_types::pb::Status> {
    if !matches!(status.state, JobState::Failed | JobState::Cancelled) {
        return None;
    }
    let reason = status.error_code.as_deref().unwrap_or(match status.state {
        JobState::Cancelled => "cancelled",
        _ => "unknown",
    });
    let code = crate::api::status::of_failure(status.state, status.failure());
    let info = tonic_types::pb::ErrorInfo {
        reason: reason.to_ascii_uppercase(),
        domain: ERROR_DOMAIN.to_string(),
        metadata: HashMap::new(),
    };
    Some(tonic_types::pb::Status {
        code: code as i32,
        message: status.error.clone().unwrap_or_default(),
        details: vec![prost_types::Any {
            type_url: ERROR_INFO_TYPE_URL.to_string(),
            value: info.encode_to_vec(),
        }],
    })
}

/// Why a succeeded job stopped before its last step (Job.stopped_early): the core's note
/// (code `no_progress`) as a `google.rpc.Status` with code OK and the code as
/// `ErrorInfo.reason`.
pub(super) fn job_stopped_early(status: &JobStatus) -> Option<tonic_types::pb::Status> {
    if status.state != JobState::Succeeded {
        return None;
    }
    let reason = status.error_code.as_deref()?;
    let info = tonic_types::pb::ErrorInfo {
        reason: reason.to_ascii_uppercase(),
        domain: ERROR_DOMAIN.to_string(),
        metadata: HashMap::new(),
    };
    Some(tonic_types::pb::Status {
        code: Code::Ok as i32,
        message: status.error.clone().unwrap_or_default(),
        details: vec![prost_types::Any {
            type_url: ERROR_INFO_TYPE_URL.to_string(),
            value: info.encode_to_vec(),
        }],
    })
}

pub(in crate::api::grpc) fn job_pb(status: &JobStatus) -> v1::Job {
    v1::Job {
        name: format!("jobs/{}", status.id),
        state: state_pb(status.state) as i32,
        step: count(status.step),
        total_steps: count(status.total_steps),
        params: Some(params_pb(&status.spec)),
        input_format: format_pb(status.input_format) as i32,
        latest: status.latest.as_ref().map(metrics_pb),
        error: job_failure(status),
        create_time: Some(timestamp(status.created_at)),
        start_time: status.started_at.map(timestamp),
        end_time: status.finished_at.map(timestamp),
        expire_time: status.expires_at.map(timestamp),
        vertex_count: status.vertex_count as u64,
        face_count: status.face_count as u64,
        stopped_early: job_stopped_early(status),
        outcome: status.outcome().map(|o| o.0).unwrap_or_default(),
        outcome_reason: status.outcome().map(|o| o.1).unwrap_or_default(),
        percent_complete: status.percent_complete(),
        repairs: status.repairs.as_ref().map(repairs_pb),
        notes: status.notes.clone(),
    }
}

pub(super) fn repairs_pb(r: &willow::mesh::io::Repairs) -> v1::Repairs {
    let list = |v: &[usize]| v.iter().map(|&i| i as u64).collect();
    v1::Repairs {
        dropped_face_count: r.dropped_faces.count as u64,
        dropped_faces: list(&r.dropped_faces.first),
        split_vertex_count: r.split_vertices.count as u64,
        split_vertices: list(&r.split_vertices.first),
        added_vertices: r.added_vertices as u64,
    }
}

/// The job as a `google.longrunning.Operation`: metadata is always the Job; when done, the
/// result is the Job (SUCCEEDED) or its error (FAILED, CANCELLED).
pub(in crate::api::grpc) fn operation(status: &JobStatus) -> lro::Operation {
    let job = job_pb(status);
    let packed = prost_types::Any {
        type_url: JOB_TYPE_URL.to_string(),
        value: job.encode_to_vec(),
    };
    let result = match status.state {
        JobState::Succeeded => Some(lro::operation::Result::Response(packed.clone())),
        JobState::Failed | JobState::Cancelled => job.error.map(lro::operation::Result::Error),
        JobState::Queued | JobState::Running => None,
    };
    lro::Operation {
        name: job.name,
        metadata: Some(packed),
        done: status.state.is_terminal(),
        result,
    }
}
