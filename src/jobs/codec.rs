//! The byte forms the backends share: request hashes for idempotency keys, step metrics,
//! position blobs and flow checkpoints. A record written by one node is read by another, and
//! after an upgrade by a newer binary: each form says how it stays readable.

use super::{format_name, FramePositions, JobError, JobSpec};
use sha2::{Digest, Sha256};
use willow::flow::{Carried, FlowState};
use willow::mesh::io::Format;
use willow::metrics::StepMetrics;

/// The hash an idempotency key is bound to: format, spec and mesh bytes.
pub fn request_hash(data: &[u8], format: Format, spec: &JobSpec) -> String {
    let mut h = Sha256::new();
    h.update(format_name(format).as_bytes());
    h.update([0]);
    h.update(hashed_spec(spec).unwrap_or_default());
    h.update([0]);
    h.update(data);
    h.finalize().iter().map(|b| format!("{b:02x}")).collect()
}

/// The fields of the first release's [`JobSpec`], in its order: always hashed.
const FIRST_RELEASE_FIELDS: [&str; 7] = [
    "method",
    "steps",
    "tau",
    "iterations",
    "frame_interval",
    "include_positions",
    "deadline_secs",
];

/// The spec as [`request_hash`] sees it: its compact JSON with the fields of the first
/// release always, in their order, then each later field (in declaration order) only when its
/// JSON differs from [`JobSpec::default`]'s. Keys are stored with their hash, so a request
/// sent again after an upgrade must hash as before, or its retry would be refused as a
/// different request: a field added to [`JobSpec`] (at the end, with a default) leaves every
/// existing request's bytes alone, with no edit here. The pinned hashes in the tests are the
/// contract.
///
/// Equal JSON stands for "at its default": exact for the later fields, which are flags,
/// enums, lists and optional numbers; `Some(NaN)` would print as `null` like `None`, but
/// [`JobSpec::validate`] refuses every non-finite number before a request is hashed.
fn hashed_spec(spec: &JobSpec) -> serde_json::Result<Vec<u8>> {
    let json = serde_json::to_string(spec)?;
    let default_json = serde_json::to_string(&hash_baseline())?;
    let entries: Entries = serde_json::from_str(&json)?;
    let defaults: Entries = serde_json::from_str(&default_json)?;
    let mut out = Vec::with_capacity(json.len());
    out.push(b'{');
    for (key, value) in &entries.0 {
        let at_default = defaults
            .0
            .iter()
            .any(|(k, v)| k == key && v.get() == value.get());
        if !FIRST_RELEASE_FIELDS.contains(&key.as_str()) && at_default {
            continue;
        }
        if out.len() > 1 {
            out.push(b',');
        }
        serde_json::to_writer(&mut out, key)?;
        out.push(b':');
        out.extend_from_slice(value.get().as_bytes());
    }
    out.push(b'}');
    Ok(out)
}

/// What "at its default" means for [`hashed_spec`]: each later field at the default it had
/// when it was added, not at today's. A default that changes must not change the hash of a
/// stored request that held the old one: `repair` was false and `boundary` free until issue
/// 39 made them true and `auto` (the first-release field `method` changed its default then
/// too, to `denoise`, but first-release fields are always hashed as they are).
fn hash_baseline() -> JobSpec {
    JobSpec {
        repair: false,
        boundary: crate::jobs::spec::BoundarySpec::Free,
        ..JobSpec::default()
    }
}

/// A JSON object's top-level entries in the order they were written, each value as its exact
/// bytes (a `serde_json::Value` would sort the keys of nested objects).
struct Entries<'a>(Vec<(String, &'a serde_json::value::RawValue)>);

impl<'de> serde::Deserialize<'de> for Entries<'de> {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct Visit;
        impl<'de> serde::de::Visitor<'de> for Visit {
            type Value = Entries<'de>;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("a JSON object")
            }
            fn visit_map<A: serde::de::MapAccess<'de>>(
                self,
                mut map: A,
            ) -> Result<Self::Value, A::Error> {
                let mut entries = Vec::new();
                while let Some(entry) = map.next_entry()? {
                    entries.push(entry);
                }
                Ok(Entries(entries))
            }
        }
        d.deserialize_map(Visit)
    }
}

/// Bytes of a metrics row as the first release wrote it: step as u64, then nine f64
/// (`willmore_energy` … `step_ms`), all little-endian.
pub const METRICS_V1_BYTES: usize = 80;
/// Bytes of a metrics row's fixed part now: the first release's 80, then `tau` (f64) and
/// `rejected` (u32), little-endian. Rows are only ever appended to, so an old row is a prefix
/// of a new one.
pub const METRICS_BYTES: usize = METRICS_V1_BYTES + 8 + 4;

/// The optional metrics, each stored after the fixed part as a tag byte and an f64 when the
/// step has it: a metric added later takes the next tag, and a row without it reads as `None`.
type OptionalMetric = (u8, fn(&StepMetrics) -> Option<f64>);

/// The most bytes [`encode_metrics`] writes: every optional metric present.
pub const MAX_METRICS_BYTES: usize = METRICS_BYTES + 9 * OPTIONAL_METRICS.len();

const OPTIONAL_METRICS: [OptionalMetric; 8] = [
    (1, |m| m.volume),
    (2, |m| m.deviation_max),
    (3, |m| m.deviation_mean),
    (4, |m| m.willmore_energy_vector),
    (5, |m| m.log_area_ratio_p1),
    (6, |m| m.log_area_ratio_p99),
    (7, |m| m.collapsed_triangles.map(f64::from)),
    (8, |m| m.crease_edges.map(f64::from)),
];

/// The binary form of [`StepMetrics`]: [`METRICS_BYTES`], then the optional metrics the step
/// has (`OPTIONAL_METRICS`). Binary and not JSON because a metric may legitimately be NaN or
/// infinite, which JSON cannot carry.
pub fn encode_metrics(m: &StepMetrics) -> Vec<u8> {
    // `MAX_METRICS_BYTES` bounds this.
    let mut out = Vec::with_capacity(METRICS_BYTES + 9 * OPTIONAL_METRICS.len());
    out.extend_from_slice(&(m.step as u64).to_le_bytes());
    for v in [
        m.willmore_energy,
        m.q_mean,
        m.q_area_mean,
        m.q_p95,
        m.q_max,
        m.closure_residual,
        m.eigen_residual,
        m.area,
        m.step_ms,
        m.tau,
    ] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out.extend_from_slice(&m.rejected.to_le_bytes());
    for (tag, get) in OPTIONAL_METRICS {
        if let Some(v) = get(m) {
            out.push(tag);
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}

/// Reads a row of any length written so far: one written before the safeguard existed
/// ([`METRICS_V1_BYTES`]) has `tau = 0` and `rejected = 0`, as [`StepMetrics`] documents; one
/// written before the optional metrics has none of them.
pub fn decode_metrics(b: &[u8]) -> Result<StepMetrics, JobError> {
    let bad = |what: String| JobError::Internal(format!("stored metrics: {what}"));
    let tail = b.len().checked_sub(METRICS_BYTES);
    if b.len() != METRICS_V1_BYTES && tail.is_none_or(|t| t % 9 != 0) {
        return Err(bad(format!(
            "{} bytes, expected {METRICS_BYTES} and 9 per optional metric (or \
             {METRICS_V1_BYTES} for rows written before the safeguard)",
            b.len()
        )));
    }
    let u = |i: usize| {
        let mut a = [0u8; 8];
        a.copy_from_slice(&b[i * 8..i * 8 + 8]);
        a
    };
    let f = |i: usize| f64::from_le_bytes(u(i));
    let (tau, rejected) = if b.len() >= METRICS_BYTES {
        let mut r = [0u8; 4];
        r.copy_from_slice(&b[METRICS_V1_BYTES + 8..METRICS_BYTES]);
        (f(10), u32::from_le_bytes(r))
    } else {
        (0.0, 0)
    };
    let mut m = StepMetrics {
        step: u64::from_le_bytes(u(0)) as usize,
        willmore_energy: f(1),
        q_mean: f(2),
        q_area_mean: f(3),
        q_p95: f(4),
        q_max: f(5),
        closure_residual: f(6),
        eigen_residual: f(7),
        area: f(8),
        step_ms: f(9),
        tau,
        rejected,
        volume: None,
        deviation_max: None,
        deviation_mean: None,
        willmore_energy_vector: None,
        log_area_ratio_p1: None,
        log_area_ratio_p99: None,
        collapsed_triangles: None,
        crease_edges: None,
    };
    if b.len() > METRICS_BYTES {
        for entry in b[METRICS_BYTES..].chunks_exact(9) {
            let mut v = [0u8; 8];
            v.copy_from_slice(&entry[1..]);
            let v = Some(f64::from_le_bytes(v));
            match entry[0] {
                1 => m.volume = v,
                2 => m.deviation_max = v,
                3 => m.deviation_mean = v,
                4 => m.willmore_energy_vector = v,
                5 => m.log_area_ratio_p1 = v,
                6 => m.log_area_ratio_p99 = v,
                // A count, stored as the f64 it converts to exactly (below 2^53).
                7 => m.collapsed_triangles = v.map(|c| c as u32),
                8 => m.crease_edges = v.map(|c| c as u32),
                tag => return Err(bad(format!("unknown optional metric {tag}"))),
            }
        }
    }
    Ok(m)
}

pub fn f64s_to_bytes(p: &[[f64; 3]]) -> Vec<u8> {
    let mut out = Vec::with_capacity(p.len() * 24);
    for v in p {
        for c in v {
            out.extend_from_slice(&c.to_le_bytes());
        }
    }
    out
}

pub fn bytes_to_f64s(b: &[u8]) -> Result<Vec<[f64; 3]>, JobError> {
    if !b.len().is_multiple_of(24) {
        return Err(JobError::Internal("truncated f64 position blob".into()));
    }
    Ok(b.chunks_exact(24)
        .map(|c| {
            let g = |i: usize| {
                let mut a = [0u8; 8];
                a.copy_from_slice(&c[i * 8..i * 8 + 8]);
                f64::from_le_bytes(a)
            };
            [g(0), g(1), g(2)]
        })
        .collect())
}

/// Little-endian f32 xyz, the frame payload format.
pub fn f32s_to_bytes(p: &[[f32; 3]]) -> Vec<u8> {
    let mut out = Vec::with_capacity(p.len() * 12);
    for v in p {
        for c in v {
            out.extend_from_slice(&c.to_le_bytes());
        }
    }
    out
}

pub fn bytes_to_f32s(b: &[u8]) -> Result<Vec<[f32; 3]>, JobError> {
    if !b.len().is_multiple_of(12) {
        return Err(JobError::Internal("truncated f32 position blob".into()));
    }
    Ok(b.chunks_exact(12)
        .map(|c| {
            let g =
                |i: usize| f32::from_le_bytes([c[i * 4], c[i * 4 + 1], c[i * 4 + 2], c[i * 4 + 3]]);
            [g(0), g(1), g(2)]
        })
        .collect())
}

/// First bytes of a stored frame whose origin is not zero ([`encode_frame_positions`]).
const FRAME_ORIGIN_MAGIC: &[u8; 4] = b"WFO1";
/// The magic and three f64: 28 bytes, so such a blob's length is 4 mod 12 while a plain f32
/// blob's (every blob before origins, and every blob of a model around the origin) is 0 mod 12.
pub const FRAME_ORIGIN_HEADER: usize = 4 + 24;

/// A frame as stored: for a zero origin the plain f32 xyz it always was; otherwise
/// [`FRAME_ORIGIN_MAGIC`], the origin as three little-endian f64, then the f32 offsets.
pub fn encode_frame_positions(p: &FramePositions) -> Vec<u8> {
    if p.at_zero() {
        return f32s_to_bytes(&p.relative);
    }
    let mut out = Vec::with_capacity(FRAME_ORIGIN_HEADER + p.relative.len() * 12);
    out.extend_from_slice(FRAME_ORIGIN_MAGIC);
    for c in p.origin {
        out.extend_from_slice(&c.to_le_bytes());
    }
    out.extend_from_slice(&f32s_to_bytes(&p.relative));
    out
}

/// Reads [`encode_frame_positions`]' blobs and the plain f32 blobs stored before origins.
pub fn decode_frame_positions(b: &[u8]) -> Result<FramePositions, JobError> {
    if b.len() % 12 == FRAME_ORIGIN_HEADER % 12 && b.starts_with(FRAME_ORIGIN_MAGIC) {
        let (head, rest) = b.split_at(FRAME_ORIGIN_HEADER);
        let origin = bytes_to_f64s(&head[4..])?
            .first()
            .copied()
            .ok_or_else(|| JobError::Internal("frame blob without its origin".into()))?;
        return Ok(FramePositions {
            origin,
            relative: bytes_to_f32s(rest)?,
        });
    }
    Ok(FramePositions {
        origin: [0.0; 3],
        relative: bytes_to_f32s(b)?,
    })
}

/// First bytes of a checkpoint blob, with its version: a checkpoint some other version wrote
/// is not trusted (the job then restarts from step 0, which is always correct).
const CHECKPOINT_MAGIC: &[u8; 8] = b"WLWCKP03";
/// The second version: no carried state after the positions (it resumes with none,
/// [`willow::flow::Carried`]'s default).
const CHECKPOINT_MAGIC_V2: &[u8; 8] = b"WLWCKP02";
/// The first version: metrics of exactly [`METRICS_BYTES`], with no length before them.
const CHECKPOINT_MAGIC_V1: &[u8; 8] = b"WLWCKP01";

/// Bit of the carried state's flags: the safeguard resists damage (`Carried::resists_damage`).
const CARRIED_RESISTS_DAMAGE: u32 = 1;

/// A flow's state as a blob: magic, the length of the step's metrics (u32) and the metrics
/// ([`encode_metrics`]), `next_tau` (f64), `clean_steps` (u32), the vertex count (u64), the
/// welded positions as f64 xyz, then what the flow carries between steps
/// ([`willow::flow::Carried`]): flags (u32), the run's quiet and crawling steps (u32 each),
/// the length of the absorbed curvature change (u64) and its values (f64), all
/// little-endian.
pub fn encode_checkpoint(state: &FlowState) -> Vec<u8> {
    let metrics = encode_metrics(&state.metrics);
    let carried = &state.carried;
    let mut out = Vec::with_capacity(
        12 + metrics.len() + 20 + state.positions.len() * 24 + 20 + carried.absorbed.len() * 8,
    );
    out.extend_from_slice(CHECKPOINT_MAGIC);
    out.extend_from_slice(&(metrics.len() as u32).to_le_bytes());
    out.extend_from_slice(&metrics);
    out.extend_from_slice(&state.next_tau.to_le_bytes());
    out.extend_from_slice(&state.clean_steps.to_le_bytes());
    out.extend_from_slice(&(state.positions.len() as u64).to_le_bytes());
    out.extend_from_slice(&f64s_to_bytes(&state.positions));
    let flags = if carried.resists_damage {
        CARRIED_RESISTS_DAMAGE
    } else {
        0
    };
    out.extend_from_slice(&flags.to_le_bytes());
    out.extend_from_slice(&carried.quiet_steps.to_le_bytes());
    out.extend_from_slice(&carried.crawling_steps.to_le_bytes());
    out.extend_from_slice(&(carried.absorbed.len() as u64).to_le_bytes());
    for d in &carried.absorbed {
        out.extend_from_slice(&d.to_le_bytes());
    }
    out
}

/// The carried state after a checkpoint's positions ([`encode_checkpoint`]).
fn decode_carried(b: &[u8]) -> Result<Carried, JobError> {
    let bad = |why: &str| JobError::Internal(format!("checkpoint: {why}"));
    let (head, values) = b
        .split_at_checked(20)
        .ok_or_else(|| bad("truncated carried state"))?;
    let u32_at = |k: usize| u32::from_le_bytes([head[k], head[k + 1], head[k + 2], head[k + 3]]);
    let flags = u32_at(0);
    if flags & !CARRIED_RESISTS_DAMAGE != 0 {
        return Err(bad("unknown carried-state flags"));
    }
    let mut n = [0u8; 8];
    n.copy_from_slice(&head[12..20]);
    let count = u64::from_le_bytes(n);
    if values.len() as u64 != count.saturating_mul(8) {
        return Err(bad("truncated absorbed curvature change"));
    }
    Ok(Carried {
        absorbed: values
            .chunks_exact(8)
            .map(|c| {
                n.copy_from_slice(c);
                f64::from_le_bytes(n)
            })
            .collect(),
        resists_damage: flags & CARRIED_RESISTS_DAMAGE != 0,
        quiet_steps: u32_at(4),
        crawling_steps: u32_at(8),
    })
}

/// The inverse of [`encode_checkpoint`] (and of the earlier versions', whose jobs resume
/// after an upgrade, carrying nothing); an error for anything else (truncated, another
/// version), never a panic.
pub fn decode_checkpoint(b: &[u8]) -> Result<FlowState, JobError> {
    let bad = |why: &str| JobError::Internal(format!("checkpoint: {why}"));
    // Versions 2 and 3 give the metrics' length; version 3 carries state after the positions.
    fn with_length(rest: &[u8]) -> Result<(usize, &[u8]), JobError> {
        let (n, rest) = rest
            .split_first_chunk::<4>()
            .ok_or_else(|| JobError::Internal("checkpoint: truncated header".into()))?;
        Ok((u32::from_le_bytes(*n) as usize, rest))
    }
    let (metrics_len, rest, carries) = if let Some(rest) = b.strip_prefix(CHECKPOINT_MAGIC) {
        let (len, rest) = with_length(rest)?;
        (len, rest, true)
    } else if let Some(rest) = b.strip_prefix(CHECKPOINT_MAGIC_V2) {
        let (len, rest) = with_length(rest)?;
        (len, rest, false)
    } else if let Some(rest) = b.strip_prefix(CHECKPOINT_MAGIC_V1) {
        (METRICS_BYTES, rest, false)
    } else {
        return Err(bad("not a checkpoint of this version"));
    };
    if rest.len() < metrics_len.saturating_add(20) {
        return Err(bad("truncated header"));
    }
    let metrics = decode_metrics(&rest[..metrics_len])?;
    let rest = &rest[metrics_len..];
    let mut f = [0u8; 8];
    f.copy_from_slice(&rest[..8]);
    let next_tau = f64::from_le_bytes(f);
    let mut c = [0u8; 4];
    c.copy_from_slice(&rest[8..12]);
    let clean_steps = u32::from_le_bytes(c);
    f.copy_from_slice(&rest[12..20]);
    let n = u64::from_le_bytes(f);
    let rest = &rest[20..];
    let (positions, carried) = if carries {
        let end = usize::try_from(n)
            .ok()
            .and_then(|n| n.checked_mul(24))
            .filter(|&end| end <= rest.len())
            .ok_or_else(|| bad("truncated positions"))?;
        (bytes_to_f64s(&rest[..end])?, decode_carried(&rest[end..])?)
    } else {
        (bytes_to_f64s(rest)?, Carried::default())
    };
    if positions.len() as u64 != n {
        return Err(bad("truncated positions"));
    }
    Ok(FlowState {
        metrics,
        positions,
        next_tau,
        clean_steps,
        carried,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A spec with the later fields at their defaults hashes exactly as the first release
    /// hashed it (its JSON then), so stored idempotency keys survive the upgrade; a spec that
    /// sets one hashes differently.
    #[test]
    fn request_hash_is_stable_across_new_spec_fields() {
        let first_release = br#"{"method":"conformal","steps":20,"tau":0.5,"iterations":1,"frame_interval":1,"include_positions":true,"deadline_secs":null}"#;
        let mut h = Sha256::new();
        h.update(b"obj");
        h.update([0]);
        h.update(first_release);
        h.update([0]);
        h.update(b"mesh");
        let old: String = h.finalize().iter().map(|b| format!("{b:02x}")).collect();
        let spec = first_release_default();
        assert_eq!(request_hash(b"mesh", Format::Obj, &spec), old);
        // Today's default (method `denoise`, repair on) is another request.
        assert_ne!(request_hash(b"mesh", Format::Obj, &JobSpec::default()), old);
        let cmc = JobSpec {
            boundary: crate::jobs::spec::BoundarySpec::Cmc,
            ..first_release_default()
        };
        assert_ne!(request_hash(b"mesh", Format::Obj, &cmc), old);
        let unguarded = JobSpec {
            safeguard: false,
            ..first_release_default()
        };
        assert_ne!(request_hash(b"mesh", Format::Obj, &unguarded), old);
        // And an old stored spec (without the new fields) still loads, with today's defaults
        // (`repair` on: the file of a job accepted without repair needs none, and reads the
        // same either way; `boundary` auto: a first-release job on an open mesh resumed after
        // the upgrade keeps its border from then on).
        let stored: JobSpec =
            serde_json::from_slice(first_release).expect("a first-release spec loads");
        assert_eq!(
            stored,
            JobSpec {
                repair: true,
                boundary: crate::jobs::spec::BoundarySpec::Auto,
                ..spec
            }
        );
    }

    /// The spec a request with no parameters made before issue 39 changed the defaults:
    /// the conformal flow, no repair, a free boundary. The pinned hashes below were made from
    /// it.
    fn first_release_default() -> JobSpec {
        JobSpec {
            method: willow::flow::Method::Conformal,
            repair: false,
            boundary: crate::jobs::spec::BoundarySpec::Free,
            ..JobSpec::default()
        }
    }

    /// Specs with every later field in turn off its default, and a few together.
    fn varied_specs() -> Vec<(&'static str, JobSpec)> {
        use crate::jobs::spec::{AnglesSpec, AxisSpec, BoundarySpec, FilterSpec, PrescribedSpec};
        use willow::flow::region::{Region, Seam};
        use willow::flow::{Method, Preserve};
        let d = first_release_default;
        vec![
            ("default", d()),
            (
                "first-release fields",
                JobSpec {
                    method: Method::Mcf,
                    steps: 7,
                    tau: 0.125,
                    iterations: 3,
                    frame_interval: 2,
                    include_positions: false,
                    deadline_secs: Some(30.0),
                    ..d()
                },
            ),
            (
                "flags",
                JobSpec {
                    exactness: false,
                    mobius_balancing: true,
                    safeguard: false,
                    until_converged: false,
                    measure_deviation: true,
                    repair: true,
                    ..d()
                },
            ),
            (
                "filter",
                JobSpec {
                    filter: Some(FilterSpec { sigma: 0.01, k: 2 }),
                    ..d()
                },
            ),
            (
                "boundary cmc",
                JobSpec {
                    boundary: BoundarySpec::Cmc,
                    ..d()
                },
            ),
            (
                "boundary prescribed",
                JobSpec {
                    boundary: BoundarySpec::Prescribed(PrescribedSpec {
                        frame_angle: -0.3,
                        axis: AxisSpec::Fixed([1.0, 0.0, 0.0]),
                        angles: AnglesSpec::PerLoop(vec![0.2, -0.2]),
                    }),
                    ..d()
                },
            ),
            (
                "regions",
                JobSpec {
                    region: vec![
                        Region::Sphere {
                            center: [0.1, 0.2, 0.3],
                            radius: 0.5,
                        },
                        Region::Box {
                            min: [-1.0, -1.0, -1.0],
                            max: [1.0, 0.0, 1.0],
                        },
                        Region::Vertices(vec![0, 5, 9]),
                        Region::Group("ear".into()),
                    ],
                    seam: Seam::Fixed,
                    falloff: Some(0.05),
                    ..d()
                },
            ),
            (
                "stopping rules",
                JobSpec {
                    preserve: Preserve::Volume,
                    until_willmore: Some(12.6),
                    max_deviation: Some(0.02),
                    feature_size: Some(0.13),
                    ..d()
                },
            ),
            (
                "callback_url",
                JobSpec {
                    callback_url: Some("https://hooks.example/willow?x=\"1\"".into()),
                    ..d()
                },
            ),
            (
                "conformal with everything",
                JobSpec {
                    steps: 3,
                    mobius_balancing: true,
                    filter: Some(FilterSpec { sigma: 1e-3, k: 1 }),
                    boundary: BoundarySpec::Fixed,
                    region: vec![Region::Vertices(vec![1, 2, 3])],
                    preserve: Preserve::None,
                    until_willmore: Some(0.0),
                    callback_url: Some("https://a.example/".into()),
                    ..d()
                },
            ),
        ]
    }

    /// The compatibility contract of [`request_hash`]: idempotency keys are stored with the
    /// hash of their request, so these exact hex strings (computed by the release that wrote
    /// HashedSpec field by field) must come out of every later one, or a client's retry after
    /// an upgrade is refused as a different request. Never update a string here to make a
    /// change pass: the change is what is wrong.
    #[test]
    fn request_hashes_of_stored_keys_never_change() {
        let pinned = [
            (
                "default",
                "835e2ba51cd568d568798ce2a912fa9f203fc584229e4554cf05fdf32b8c02d1",
            ),
            (
                "first-release fields",
                "3f1b677369ee33667a2c90007bf7f3e455ff31bd553996cdb6871beb861a2549",
            ),
            (
                "flags",
                "351a136834624a12faf183f29670dd4a871779aee314232176fa12f09ee3e1ae",
            ),
            (
                "filter",
                "62d08df3ef07a74d9fb871820bcf05f8ff9f33c518bf77002701c1ff2657263e",
            ),
            (
                "boundary cmc",
                "367b6a126233fdb85a9e601082bc810ef158e44d014515e76101c3a3e33f430c",
            ),
            (
                "boundary prescribed",
                "de41c4c04a5a73143c21ae2d8c2ed8ee785abb563282b610db23f1610d92619b",
            ),
            (
                "regions",
                "5e2e3e83fe2efc39ad3db9ea033baae508da280f30c4fe0e828b81ba881c80fe",
            ),
            (
                "stopping rules",
                "79751c5ec590c6249816727ee745300ded1331b1858a16b89befcf93bf1529b6",
            ),
            (
                "callback_url",
                "41d01045b55f4aad4eec4c6fa9b3a273c503ff698021af7a66f73dae55912929",
            ),
            (
                "conformal with everything",
                "442096fab662859a81c19d0270459e923d742f026427d90ce5409894606bbbf8",
            ),
        ];
        let specs = varied_specs();
        assert_eq!(specs.len(), pinned.len());
        for ((name, spec), (pinned_name, hex)) in specs.iter().zip(pinned) {
            assert_eq!(*name, pinned_name);
            let got = request_hash(b"v 0 0 0\n", Format::Obj, spec);
            assert_eq!(got, hex, "{name}");
        }
    }

    #[test]
    fn metrics_round_trip_including_nan() {
        let m = StepMetrics {
            step: 7,
            willmore_energy: 12.5,
            q_mean: 1.0,
            q_area_mean: 1.01,
            q_p95: f64::NAN,
            q_max: f64::INFINITY,
            closure_residual: 1e-9,
            eigen_residual: 0.0,
            area: 4.0,
            step_ms: 3.25,
            tau: 0.125,
            rejected: 3,
            volume: None,
            deviation_max: None,
            deviation_mean: None,
            // Not stored yet (issue 26's new metrics).
            willmore_energy_vector: None,
            log_area_ratio_p1: None,
            log_area_ratio_p99: None,
            collapsed_triangles: None,
            crease_edges: None,
        };
        let blob = encode_metrics(&m);
        assert_eq!(blob.len(), METRICS_BYTES);
        let back = decode_metrics(&blob).expect("a new row decodes");
        assert_eq!(back.step, 7);
        assert_eq!(back.willmore_energy, 12.5);
        assert!(back.q_p95.is_nan());
        assert_eq!(back.q_max, f64::INFINITY);
        assert_eq!(back.step_ms, 3.25);
        assert_eq!(back.tau, 0.125);
        assert_eq!(back.rejected, 3);
    }

    /// A row as the first release stored it (80 bytes, built here by hand, not by
    /// `encode_metrics`) still decodes, with `tau = 0` and `rejected = 0`.
    #[test]
    fn metrics_stored_before_the_safeguard_decode_with_tau_zero() {
        let mut old = Vec::new();
        old.extend_from_slice(&5u64.to_le_bytes());
        for v in [14.0, 1.1, 1.05, 1.2, 1.5, 1e-8, 1e-10, 12.0, 4.5] {
            old.extend_from_slice(&f64::to_le_bytes(v));
        }
        assert_eq!(old.len(), 80);
        let m = decode_metrics(&old).expect("an old row decodes");
        assert_eq!(m.step, 5);
        assert_eq!(m.willmore_energy, 14.0);
        assert_eq!(m.area, 12.0);
        assert_eq!(m.step_ms, 4.5);
        assert_eq!(m.tau, 0.0);
        assert_eq!(m.rejected, 0);
        // The new form is the old one with tau and rejected appended.
        assert_eq!(encode_metrics(&m)[..80], old[..]);
        for bad in [79, 81, 91, 93] {
            assert!(
                decode_metrics(&vec![0; bad]).is_err(),
                "{bad} bytes accepted"
            );
        }
    }

    /// Volume and deviation survive a row and a checkpoint; a row without them (as the
    /// service wrote before it stored them) reads as `None`; an unknown tag is an error.
    #[test]
    fn optional_metrics_round_trip_and_old_rows_have_none() {
        let mut m = decode_metrics(&[0; METRICS_BYTES]).expect("zeros decode");
        m.step = 3;
        m.willmore_energy = 12.6;
        m.volume = Some(4.1887);
        m.deviation_max = Some(0.25);
        m.deviation_mean = Some(f64::NAN);
        let blob = encode_metrics(&m);
        assert_eq!(blob.len(), METRICS_BYTES + 3 * 9);
        let back = decode_metrics(&blob).expect("decodes");
        assert_eq!(back.volume, Some(4.1887));
        assert_eq!(back.deviation_max, Some(0.25));
        assert!(back.deviation_mean.is_some_and(f64::is_nan));
        let state = FlowState {
            metrics: back,
            positions: vec![[1.0, 2.0, 3.0]],
            next_tau: 0.25,
            clean_steps: 2,
            carried: Carried::default(),
        };
        let again = decode_checkpoint(&encode_checkpoint(&state)).expect("checkpoint");
        assert_eq!(again.metrics.volume, Some(4.1887));
        assert_eq!(again.positions, state.positions);
        // A first-version checkpoint: the fixed-length metrics and no length before them,
        // and nothing carried after the positions (20 bytes with nothing absorbed).
        m.volume = None;
        m.deviation_max = None;
        m.deviation_mean = None;
        let mut v1 = CHECKPOINT_MAGIC_V1.to_vec();
        v1.extend_from_slice(&encode_metrics(&m));
        let current = encode_checkpoint(&state);
        v1.extend_from_slice(&current[12 + blob.len()..current.len() - 20]);
        let old = decode_checkpoint(&v1).expect("a v1 checkpoint resumes");
        assert_eq!((old.metrics.step, old.metrics.volume), (3, None));
        assert_eq!(old.next_tau, 0.25);
        let plain = decode_metrics(&blob[..METRICS_BYTES]).expect("a row without them");
        assert_eq!(plain.volume, None);
        let mut unknown = blob[..METRICS_BYTES].to_vec();
        unknown.push(200);
        unknown.extend_from_slice(&1.0f64.to_le_bytes());
        assert!(decode_metrics(&unknown).is_err());
    }

    #[test]
    fn rfc3339_known_instants() {
        assert_eq!(super::super::rfc3339(0), "1970-01-01T00:00:00.000Z");
        // 2000-02-29T12:34:56.789Z (a leap day)
        assert_eq!(
            super::super::rfc3339(951_827_696_789),
            "2000-02-29T12:34:56.789Z"
        );
    }

    #[test]
    fn checkpoints_round_trip_and_damaged_ones_are_refused() {
        let state = FlowState {
            metrics: StepMetrics {
                step: 12,
                willmore_energy: 13.0,
                q_mean: 1.0,
                q_area_mean: 1.0,
                q_p95: 1.1,
                q_max: 1.2,
                closure_residual: 1e-9,
                eigen_residual: 1e-12,
                area: 4.0,
                step_ms: 2.0,
                tau: 0.25,
                rejected: 1,
                volume: None,
                deviation_max: None,
                deviation_mean: None,
                // Not stored yet (issue 26's new metrics).
                willmore_energy_vector: None,
                log_area_ratio_p1: None,
                log_area_ratio_p99: None,
                collapsed_triangles: None,
                crease_edges: None,
            },
            positions: vec![[1.0, -2.0, 3.5], [0.1, 0.2, f64::MIN_POSITIVE]],
            next_tau: 0.25,
            clean_steps: 2,
            carried: Carried {
                absorbed: vec![0.5, -1.25e-3],
                resists_damage: true,
                quiet_steps: 2,
                crawling_steps: 1,
            },
        };
        let blob = encode_checkpoint(&state);
        assert_eq!(decode_checkpoint(&blob).expect("decodes"), state);
        // The carried state is 20 bytes and 8 per absorbed value after the positions.
        let carried_len = 20 + 8 * state.carried.absorbed.len();
        for cut in [0, 7, 8, 50, blob.len() - carried_len, blob.len() - 1] {
            assert!(decode_checkpoint(&blob[..cut]).is_err(), "cut at {cut}");
        }
        let mut other = blob.clone();
        other[7] = b'9';
        assert!(decode_checkpoint(&other).is_err(), "another version");
        let mut flags = blob.clone();
        flags[blob.len() - carried_len] |= 2;
        assert!(decode_checkpoint(&flags).is_err(), "an unknown flag");
        // A second-version checkpoint (written before the carried state was kept) resumes
        // with nothing carried: no absorbed change, the rules' look-back afresh.
        let mut v2 = CHECKPOINT_MAGIC_V2.to_vec();
        v2.extend_from_slice(&blob[8..blob.len() - carried_len]);
        let old = decode_checkpoint(&v2).expect("a v2 checkpoint resumes");
        assert_eq!(old.carried, Carried::default());
        assert_eq!(
            (old.metrics, old.positions, old.next_tau, old.clean_steps),
            (
                state.metrics,
                state.positions.clone(),
                state.next_tau,
                state.clean_steps
            )
        );
    }
}
