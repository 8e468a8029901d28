//! Issue 29's first acceptance check, end to end through the service: a region of spot's ear,
//! of a genus-2 surface and of an open one, named each way (`sphere`/`box`, `vertices`,
//! `group`) with each seam (`smooth`, `fixed`, a `falloff`), submitted over HTTP (multipart
//! with a JSON `params` part) and over gRPC to one server, the result downloaded as OBJ and as
//! GLB. Every check is the test's own reading of the files (`measure.rs`), not Willow's:
//!
//! - every vertex outside the region is bit-identical to the uploaded file's, in the OBJ (f64)
//!   and in the GLB (the input's value as f32, the precision glTF stores);
//! - W of the region's vertices (cotan formula) falls;
//! - the mean normal jump across the region's border edges stays within 2× the input's;
//! - no face with a corner in the region turns over;
//! - Q inside ≤ 1.3: the area-weighted mean distortion of the map from each input triangle to
//!   its result, and on spot (which has UVs) the texture's, from the UV triangle to the 3D one.
//!
//! Those jobs run 5 steps; a second test runs the smooth seam on for 20 steps with
//! `until_converged`, where the seam must still hold and Q still ≤ 1.3.
//!
//! Set `WILLOW_TEST_DUMP=dir` to keep every input and OBJ result there (to render them).

mod measure;
#[path = "../service_http_support/mod.rs"]
mod service_http_support;

use std::time::Duration;

use measure::*;
use service_http_support::{is_terminal, obj_text, start, TestServer};
use tonic::transport::Channel;
use willow::mesh::generate::{bumpy_cap, pretzel, with_noise};
use willow_service::api::grpc::pb::willow::v1;
use willow_service::api::grpc::pb::willow::v1::fairing_client::FairingClient;

const PATIENCE: Duration = Duration::from_secs(180);

/// Spot's right ear (found by rendering spot with this sphere marked; see
/// crates/willow/tests/flow_region.rs).
const EAR: ([f64; 3], f64) = ([0.40, 0.72, -0.20], 0.15);

/// How a case names its region, in the file's units and numbering.
#[derive(Clone, Debug)]
enum Shape {
    Sphere([f64; 3], f64),
    Box([f64; 3], [f64; 3]),
    Vertices(Vec<usize>),
    Group(&'static str),
}

impl Shape {
    fn json(&self) -> serde_json::Value {
        use serde_json::json;
        match self {
            Shape::Sphere(c, r) => json!({"sphere": {"center": c, "radius": r}}),
            Shape::Box(lo, hi) => json!({"box": {"min": lo, "max": hi}}),
            Shape::Vertices(list) => json!({"vertices": list}),
            Shape::Group(name) => json!({"group": name}),
        }
    }

    fn grpc(&self) -> v1::Region {
        use v1::region::{Box as Cuboid, Shape as S, Sphere, VertexList};
        let vector = |p: &[f64; 3]| v1::Vector3 {
            x: p[0],
            y: p[1],
            z: p[2],
        };
        v1::Region {
            shape: Some(match self {
                Shape::Sphere(c, r) => S::Sphere(Sphere {
                    center: Some(vector(c)),
                    radius: *r,
                }),
                Shape::Box(lo, hi) => S::Box(Cuboid {
                    min: Some(vector(lo)),
                    max: Some(vector(hi)),
                }),
                Shape::Vertices(list) => S::Vertices(VertexList {
                    indices: list.iter().map(|&v| v as u64).collect(),
                }),
                Shape::Group(name) => S::Group(name.to_string()),
            }),
        }
    }

    /// The file vertices it selects, by the region's definition (issue 29: a group is the
    /// faces under its `g` line, so their corners).
    fn select(&self, obj: &Obj) -> Vec<bool> {
        let mut inside = vec![false; obj.v.len()];
        match self {
            Shape::Sphere(c, r) => {
                for (s, p) in inside.iter_mut().zip(&obj.v) {
                    *s = dot(sub(*p, *c), sub(*p, *c)) <= r * r;
                }
            }
            Shape::Box(lo, hi) => {
                for (s, p) in inside.iter_mut().zip(&obj.v) {
                    *s = (0..3).all(|a| lo[a] <= p[a] && p[a] <= hi[a]);
                }
            }
            Shape::Vertices(list) => list.iter().for_each(|&v| inside[v] = true),
            Shape::Group(name) => {
                for (t, g) in obj.faces.iter().zip(&obj.face_group) {
                    if g == name {
                        t.iter().for_each(|&v| inside[v] = true);
                    }
                }
            }
        }
        inside
    }
}

/// An uploaded file and the region the cases use on it.
struct Input {
    name: &'static str,
    text: String,
    obj: Obj,
    region: Shape,
    /// The `falloff` its falloff case asks for: a width of a few edges.
    falloff: f64,
}

impl Input {
    fn new(name: &'static str, text: String, region: Shape, falloff: f64) -> Input {
        let obj = parse_obj(&text);
        Input {
            name,
            text,
            obj,
            region,
            falloff,
        }
    }

    /// The region's vertices as a list (the `vertices` cases).
    fn listed(&self) -> Shape {
        let inside = self.region.select(&self.obj);
        Shape::Vertices((0..inside.len()).filter(|&v| inside[v]).collect())
    }

    /// The same file with its faces in two OBJ groups, `g <name>` (every corner in the region)
    /// then `g rest`, every other line kept in place.
    fn grouped(&self, name: &'static str) -> Input {
        let inside = self.region.select(&self.obj);
        let (mut group, mut rest, mut head) = (String::new(), String::new(), String::new());
        for line in self.text.lines() {
            let target = match line.strip_prefix("f ") {
                Some(corners) => {
                    let all_in = corners.split_whitespace().all(|w| {
                        w.split('/')
                            .next()
                            .and_then(|i| i.parse::<usize>().ok())
                            .is_some_and(|i| inside[i - 1])
                    });
                    if all_in {
                        &mut group
                    } else {
                        &mut rest
                    }
                }
                None => &mut head,
            };
            target.push_str(line);
            target.push('\n');
        }
        let text = format!("{head}g {name}\n{group}g rest\n{rest}");
        Input::new(self.name, text, Shape::Group(name), self.falloff)
    }
}

fn spot() -> Input {
    let text = std::fs::read_to_string(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("crates/willow/tests/data/spot_triangulated.obj"),
    )
    .expect("spot is a fixture of the library's tests");
    let (c, r) = EAR;
    Input::new("spot", text, Shape::Sphere(c, r), 0.08)
}

/// A noisy genus-2 surface; the region a patch of the outer rim of one handle.
fn genus_two() -> Input {
    let mesh = with_noise(pretzel(2, 24), 0.05, 7);
    let far = mesh
        .positions
        .iter()
        .copied()
        .max_by(|a, b| a[0].total_cmp(&b[0]))
        .expect("vertices");
    Input::new("genus-2", obj_text(&mesh), Shape::Sphere(far, 0.35), 0.08)
}

/// A noisy bumpy disc (one boundary loop); the region its centre, away from the boundary.
fn open_cap() -> Input {
    let mesh = with_noise(bumpy_cap(4, 0.06), 0.05, 11);
    Input::new(
        "open cap",
        obj_text(&mesh),
        Shape::Box([-0.4, -0.4, -2.0], [0.4, 0.4, 2.0]),
        // Its edges are 0.076 long on average: 0.08 would blend over a single edge.
        0.2,
    )
}

struct Case<'a> {
    input: &'a Input,
    region: Shape,
    seam: &'static str,
    falloff: Option<f64>,
}

impl Case<'_> {
    fn name(&self) -> String {
        let how = match &self.region {
            Shape::Sphere(..) => "sphere",
            Shape::Box(..) => "box",
            Shape::Vertices(_) => "vertices",
            Shape::Group(_) => "group",
        };
        let falloff = self
            .falloff
            .map(|w| format!(" falloff {w}"))
            .unwrap_or_default();
        format!("{} {how} {}{falloff}", self.input.name, self.seam)
    }
}

/// Steps per job: enough for W to fall clearly, few enough for a debug build. The seam also
/// holds once the flow has run on: [`a_smooth_seam_holds_when_the_job_runs_until_converged`]
/// (20 steps with `until_converged`).
const STEPS: u32 = 5;

/// The result files of one job.
struct Files {
    obj: String,
    glb: Vec<u8>,
}

async fn over_http(srv: &TestServer, case: &Case<'_>) -> Files {
    over_http_steps(srv, case, STEPS).await
}

async fn over_http_steps(srv: &TestServer, case: &Case<'_>, steps: u32) -> Files {
    let mut params = serde_json::json!({
        "method": "conformal",
        "steps": steps,
        "include_positions": false,
        "region": case.region.json(),
        "seam": case.seam,
    });
    if let Some(w) = case.falloff {
        params["falloff"] = w.into();
    }
    let form = reqwest::multipart::Form::new()
        .part(
            "mesh",
            reqwest::multipart::Part::bytes(case.input.text.clone().into_bytes())
                .file_name("mesh.obj")
                .mime_str("model/obj")
                .expect("mime"),
        )
        .text("params", params.to_string());
    let res = srv
        .client
        .post(srv.url("/v1/jobs"))
        .multipart(form)
        .send()
        .await
        .expect("POST /v1/jobs");
    assert_eq!(res.status(), 202, "{}: {:?}", case.name(), res.text().await);
    let job: serde_json::Value = res.json().await.expect("job JSON");
    let id = job["id"].as_str().expect("id").to_string();
    let done = srv.poll_until(&id, PATIENCE, is_terminal).await;
    assert_eq!(done["state"], "succeeded", "{}: {done}", case.name());
    let download = |format: &'static str| {
        let url = srv.url(&format!("/v1/jobs/{id}/result?format={format}"));
        let client = srv.client.clone();
        async move {
            let res = client.get(url).send().await.expect("GET result");
            assert_eq!(res.status(), 200);
            res.bytes().await.expect("result body").to_vec()
        }
    };
    Files {
        obj: String::from_utf8(download("obj").await).expect("OBJ text"),
        glb: download("glb").await,
    }
}

async fn over_grpc(client: &mut FairingClient<Channel>, case: &Case<'_>) -> Files {
    let seam = match case.seam {
        "fixed" => v1::Seam::Fixed,
        _ => v1::Seam::Smooth,
    };
    let params = v1::JobParams {
        method: v1::Method::Conformal as i32,
        steps: Some(STEPS),
        region: vec![case.region.grpc()],
        seam: seam as i32,
        falloff: case.falloff,
        ..Default::default()
    };
    let op = client
        .create_job(v1::CreateJobRequest {
            mesh: Some(v1::create_job_request::Mesh::InlineMesh(v1::InlineMesh {
                format: v1::MeshFormat::Obj as i32,
                data: case.input.text.clone().into_bytes().into(),
            })),
            params: Some(params),
            request_id: String::new(),
        })
        .await
        .unwrap_or_else(|e| panic!("{}: CreateJob: {e:?}", case.name()))
        .into_inner();
    let name = op.name;
    let polling = async {
        loop {
            let job = client
                .get_job(v1::GetJobRequest { name: name.clone() })
                .await
                .expect("GetJob")
                .into_inner();
            match v1::job::State::try_from(job.state).expect("known state") {
                v1::job::State::Succeeded => return,
                v1::job::State::Failed | v1::job::State::Cancelled => {
                    panic!("{}: {job:?}", case.name())
                }
                _ => tokio::time::sleep(Duration::from_millis(25)).await,
            }
        }
    };
    tokio::time::timeout(PATIENCE, polling)
        .await
        .expect("the gRPC job ends");
    let download = |format: v1::MeshFormat| {
        let mut client = client.clone();
        let name = name.clone();
        async move {
            let mut stream = client
                .download_result(v1::DownloadResultRequest {
                    name,
                    format: format as i32,
                })
                .await
                .expect("DownloadResult")
                .into_inner();
            let mut file = Vec::new();
            while let Some(chunk) = stream.message().await.expect("download stream") {
                file.extend_from_slice(&chunk.data);
            }
            file
        }
    };
    Files {
        obj: String::from_utf8(download(v1::MeshFormat::Obj).await).expect("OBJ text"),
        glb: download(v1::MeshFormat::Glb).await,
    }
}

/// Every check of the issue on one result: its OBJ positions and what failed (the bit checks
/// panic at once; the measured ones are collected so one run reports every case).
fn check(case: &Case<'_>, via: &str, result: &Files) -> (Vec<[f64; 3]>, Vec<String>) {
    let name = format!("{} via {via}", case.name());
    let input = &case.input.obj;
    let inside = case.region.select(input);
    let out = parse_obj(&result.obj);
    assert_eq!(out.v.len(), input.v.len(), "{name}: v lines");
    assert_eq!(out.faces, input.faces, "{name}: the faces are the file's");

    let mut moved = 0;
    for (k, (p, q)) in input.v.iter().zip(&out.v).enumerate() {
        if inside[k] {
            moved += usize::from(p != q);
        } else {
            assert_eq!(
                p.map(f64::to_bits),
                q.map(f64::to_bits),
                "{name}: OBJ v line {k} outside the region changed"
            );
        }
    }
    assert!(moved > 0, "{name}: nothing moved");

    // The GLB: its faces are the file's in order (corners split at UV seams), so each GLB
    // vertex is the file vertex at the same corner; outside, its f32 is the input's (relative
    // to the node's translation when the writer moved a far model's origin).
    let glb = parse_glb(&result.glb);
    assert_eq!(glb.triangles.len(), input.faces.len(), "{name}: GLB faces");
    let mut file_vertex = vec![usize::MAX; glb.positions.len()];
    for (g, f) in glb.triangles.iter().zip(&input.faces) {
        for c in 0..3 {
            let slot = &mut file_vertex[g[c]];
            assert!(
                *slot == usize::MAX || *slot == f[c],
                "{name}: GLB vertex {} is two file vertices",
                g[c]
            );
            *slot = f[c];
        }
    }
    for (i, (&v, q)) in file_vertex.iter().zip(&glb.positions).enumerate() {
        assert_ne!(v, usize::MAX, "{name}: GLB vertex {i} is on no face");
        let p = if inside[v] { out.v[v] } else { input.v[v] };
        let o = glb.origin;
        let expected = [0, 1, 2].map(|k| ((p[k] - o[k]) as f32).to_bits());
        assert_eq!(
            expected,
            q.map(f32::to_bits),
            "{name}: GLB vertex {i} (file vertex {v}, inside: {})",
            inside[v]
        );
    }

    let faces = &input.faces;
    let w0 = willmore(&input.v, faces, &inside);
    let w = willmore(&out.v, faces, &inside);
    let jump0 = border_normal_jump(&input.v, faces, &inside);
    let jump = border_normal_jump(&out.v, faces, &inside);
    let folded = folds(&input.v, &out.v, faces, &inside);
    let (q_mean, q_max) = q_between(&input.v, &out.v, faces, &inside);
    let texture = (!input.vt.is_empty()).then(|| {
        let before = q_texture(input, &input.v, &inside);
        let after = q_texture(input, &out.v, &inside);
        (before, after)
    });
    eprintln!(
        "{name}: {} of {} vertices inside, {moved} moved; W inside {w0:.4} -> {w:.4}; border \
         normal jump {:.2}° -> {:.2}°; folds {folded}; Q input->result mean {q_mean:.3} max \
         {q_max:.3}{}",
        inside.iter().filter(|&&s| s).count(),
        inside.len(),
        jump0.to_degrees(),
        jump.to_degrees(),
        texture
            .map(|((m0, x0), (m, x))| format!(
                "; texture Q mean {m0:.3} -> {m:.3}, max {x0:.3} -> {x:.3}"
            ))
            .unwrap_or_default()
    );
    let mut failed = Vec::new();
    if w >= w0 {
        failed.push(format!("{name}: W inside {w0} -> {w}"));
    }
    if jump > 2.0 * jump0 {
        failed.push(format!(
            "{name}: border normal jump {}° -> {}°",
            jump0.to_degrees(),
            jump.to_degrees()
        ));
    }
    if folded > 0 {
        failed.push(format!("{name}: {folded} faces turned over"));
    }
    if q_mean > 1.3 {
        failed.push(format!("{name}: Q mean {q_mean}"));
    }
    if let Some(((m0, _), (m, _))) = texture {
        if m > 1.3 * m0 {
            failed.push(format!("{name}: texture Q mean {m0} -> {m}"));
        }
    }
    (out.v, failed)
}

/// A `falloff` blends the motion to zero toward the border: the region's vertices next to
/// the outside (an edge to a vertex outside) move less than without it, on average, and the
/// others about as much.
fn falloff_blends(case: &Case<'_>, sharp: &[[f64; 3]], blended: &[[f64; 3]]) -> Option<String> {
    let input = &case.input.obj;
    let inside = case.region.select(input);
    let mut ring = vec![false; inside.len()];
    for t in &input.faces {
        if t.iter().any(|&v| !inside[v]) {
            t.iter()
                .filter(|&&v| inside[v])
                .for_each(|&v| ring[v] = true);
        }
    }
    let motion = |out: &[[f64; 3]], in_ring: bool| {
        let moved: Vec<f64> = (0..inside.len())
            .filter(|&v| inside[v] && ring[v] == in_ring)
            .map(|v| dot(sub(out[v], input.v[v]), sub(out[v], input.v[v])).sqrt())
            .collect();
        moved.iter().sum::<f64>() / moved.len() as f64
    };
    let (ring_sharp, ring_blended) = (motion(sharp, true), motion(blended, true));
    let (rest_sharp, rest_blended) = (motion(sharp, false), motion(blended, false));
    eprintln!(
        "{}: mean motion next to the border {ring_sharp:.2e} -> {ring_blended:.2e} with the \
         falloff, farther in {rest_sharp:.2e} -> {rest_blended:.2e}",
        case.name()
    );
    (ring_blended > 0.8 * ring_sharp || rest_blended < 0.5 * rest_sharp).then(|| {
        format!(
            "{}: the falloff did not blend: next to the border {ring_sharp} -> {ring_blended}, \
             farther in {rest_sharp} -> {rest_blended}",
            case.name()
        )
    })
}

fn dump(dir: &str, case: &Case<'_>, via: &str, result: &Files) {
    let stem = case.name().replace(' ', "_");
    let dir = std::path::Path::new(dir);
    std::fs::create_dir_all(dir).expect("dump dir");
    std::fs::write(dir.join(format!("{stem}.in.obj")), &case.input.text).expect("dump");
    std::fs::write(dir.join(format!("{stem}.{via}.obj")), &result.obj).expect("dump");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_region_fairs_alone_over_http_and_grpc_in_obj_and_glb() {
    let inputs = [spot(), genus_two(), open_cap()];
    let grouped: Vec<Input> = inputs.iter().map(|i| i.grouped("patch")).collect();
    let mut cases = Vec::new();
    for (input, grouped) in inputs.iter().zip(&grouped) {
        let case = |region: Shape, seam, falloff| Case {
            input,
            region,
            seam,
            falloff,
        };
        cases.push(case(input.region.clone(), "smooth", None));
        cases.push(case(input.region.clone(), "fixed", None));
        cases.push(case(input.region.clone(), "smooth", Some(input.falloff)));
        cases.push(case(input.listed(), "smooth", None));
        cases.push(Case {
            input: grouped,
            region: grouped.region.clone(),
            seam: "smooth",
            falloff: None,
        });
    }

    let srv = start(|_| {}).await;
    let channel = Channel::from_shared(srv.base.clone())
        .expect("uri")
        .connect()
        .await
        .expect("gRPC over h2c on the same port");
    let mut grpc = FairingClient::new(channel);
    let dump_dir = std::env::var("WILLOW_TEST_DUMP").ok();
    let mut failures = Vec::new();
    // The result of the input's plain smooth case, for its falloff case to compare with.
    let mut sharp: Option<Vec<[f64; 3]>> = None;
    for case in &cases {
        let by_http = over_http(&srv, case).await;
        let by_grpc = over_grpc(&mut grpc, case).await;
        if let Some(dir) = &dump_dir {
            dump(dir, case, "http", &by_http);
        }
        let (a, mut failed) = check(case, "HTTP", &by_http);
        let (b, also) = check(case, "gRPC", &by_grpc);
        failures.append(&mut failed);
        failures.extend(also);
        let plain =
            matches!(case.region, Shape::Sphere(..) | Shape::Box(..)) && case.seam == "smooth";
        match case.falloff {
            None if plain => sharp = Some(a.clone()),
            Some(_) => failures.extend(falloff_blends(
                case,
                sharp.as_deref().expect("the plain smooth case runs first"),
                &a,
            )),
            None => {}
        }
        // One spec, one result, whichever door it came in by.
        assert_eq!(a, b, "{}: HTTP and gRPC results differ", case.name());
    }
    srv.stop().await;
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// Steps of the long jobs: enough for the flow to have stopped fairing on the ear, where W
/// falls by under 0.04% a step from step 20 on.
const LONG_STEPS: u32 = 20;

/// Issue 29 item 1 once the flow has run on (20 steps, `until_converged` at its default): the
/// smooth seam keeps the border's normal jump within twice the input's on spot's ear, the
/// genus-2 rim and the open cap, the outside stays bit-identical, W inside falls well and no
/// face turns over, and Q inside stays ≤ 1.3 as at 5 steps. (It crept before the flow
/// absorbed the curvature change a held border cannot realize, `flow/willmore/pinned.rs`:
/// 1.43 on the ear, 1.39 on the genus-2 rim at 20 steps, bounded here by 1.5 then; measured
/// in crates/willow/tests/flow_region.rs now: 1.19, 1.01, cap 1.02.)
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_smooth_seam_holds_when_the_job_runs_until_converged() {
    let inputs = [spot(), genus_two(), open_cap()];
    let srv = start(|_| {}).await;
    let mut failures = Vec::new();
    for input in &inputs {
        let case = Case {
            input,
            region: input.region.clone(),
            seam: "smooth",
            falloff: None,
        };
        let name = format!("{}, {LONG_STEPS} steps", case.name());
        let result = over_http_steps(&srv, &case, LONG_STEPS).await;
        let before = &input.obj;
        let inside = case.region.select(before);
        let out = parse_obj(&result.obj);
        assert_eq!(out.v.len(), before.v.len(), "{name}: v lines");
        for (k, (p, q)) in before.v.iter().zip(&out.v).enumerate() {
            if !inside[k] {
                assert_eq!(
                    p.map(f64::to_bits),
                    q.map(f64::to_bits),
                    "{name}: OBJ v line {k} outside the region changed"
                );
            }
        }
        let faces = &before.faces;
        let w0 = willmore(&before.v, faces, &inside);
        let w = willmore(&out.v, faces, &inside);
        let jump0 = border_normal_jump(&before.v, faces, &inside);
        let jump = border_normal_jump(&out.v, faces, &inside);
        let folded = folds(&before.v, &out.v, faces, &inside);
        let (q_mean, q_max) = q_between(&before.v, &out.v, faces, &inside);
        eprintln!(
            "{name}: W inside {w0:.4} -> {w:.4}; border normal jump {:.2}° -> {:.2}°; folds \
             {folded}; Q mean {q_mean:.3} max {q_max:.3}",
            jump0.to_degrees(),
            jump.to_degrees()
        );
        if w >= 0.8 * w0 {
            failures.push(format!("{name}: W inside {w0} -> {w}"));
        }
        if jump > 2.0 * jump0 {
            failures.push(format!(
                "{name}: border normal jump {}° -> {}°",
                jump0.to_degrees(),
                jump.to_degrees()
            ));
        }
        if folded > 0 {
            failures.push(format!("{name}: {folded} faces turned over"));
        }
        if q_mean > 1.3 {
            failures.push(format!("{name}: Q mean {q_mean}"));
        }
    }
    srv.stop().await;
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
