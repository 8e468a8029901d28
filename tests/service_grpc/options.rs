//! Issues 4 and 10: the rest of `FlowParams` as `JobParams` fields, and safeguarded steps.

use super::*;

fn prescribed(
    frame_angle: f64,
    axis: Option<v1::rotation_axis::Axis>,
    angles: Option<v1::boundary_angles::Angles>,
) -> Option<v1::Boundary> {
    Some(v1::Boundary {
        condition: Some(v1::boundary::Condition::Prescribed(v1::PrescribedVectors {
            frame_angle,
            axis: Some(v1::RotationAxis { axis }),
            angles: Some(v1::BoundaryAngles { angles }),
        })),
    })
}

fn condition(c: v1::boundary::Condition) -> Option<v1::Boundary> {
    Some(v1::Boundary { condition: Some(c) })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn flow_options_are_reported_back_refused_by_field_and_run() {
    use v1::boundary::Condition;
    let server = Server::start(|_| {}).await;
    let mut client = server.fairing().await;
    let sphere = || inline(v1::MeshFormat::Obj, small_obj());
    let cap = || {
        inline(
            v1::MeshFormat::Obj,
            obj_text(&generate::bumpy_cap(3, 0.06)).into_bytes(),
        )
    };

    // Every field set: accepted, reported by CreateJob's metadata and by GetJob, and run.
    let options = v1::JobParams {
        exactness: Some(false),
        mobius_balancing: Some(true),
        filter: Some(v1::SpectralFilter { sigma: 0.01, k: 2 }),
        boundary: prescribed(
            0.2,
            Some(v1::rotation_axis::Axis::Fixed(v1::Vector3 {
                x: 0.0,
                y: 0.0,
                z: 1.0,
            })),
            Some(v1::boundary_angles::Angles::PerLoop(v1::AngleList {
                values: vec![0.15],
            })),
        ),
        ..params(v1::Method::Conformal, 2)
    };
    let op = create(&mut client, cap(), options.clone(), "")
        .await
        .expect("CreateJob with every option");
    let reported = job_from_any(op.metadata.as_ref().expect("metadata"))
        .params
        .expect("params");
    assert_eq!(reported.exactness, Some(false));
    assert_eq!(reported.mobius_balancing, Some(true));
    assert_eq!(reported.filter, options.filter);
    assert_eq!(reported.boundary, options.boundary);
    let done = poll_until(&mut client, &op.name, |j| {
        state(j) != v1::job::State::Queued && state(j) != v1::job::State::Running
    })
    .await;
    assert_eq!(state(&done), v1::job::State::Succeeded, "{:?}", done.error);
    assert_eq!(
        done.params.as_ref().map(|p| &p.boundary),
        Some(&options.boundary)
    );

    // Unset fields report their defaults; an empty Boundary is the default, `auto`.
    let op = create(
        &mut client,
        sphere(),
        v1::JobParams {
            boundary: Some(v1::Boundary::default()),
            ..params(v1::Method::Conformal, 1)
        },
        "",
    )
    .await
    .expect("CreateJob");
    let p = get_job(&mut client, &op.name)
        .await
        .expect("GetJob")
        .params
        .expect("params");
    assert_eq!(p.exactness, Some(true));
    assert_eq!(p.mobius_balancing, Some(false));
    assert_eq!(p.filter, None);
    assert_eq!(p.boundary, condition(Condition::Auto(())));

    // Taubin and a CMC boundary run to completion (CMC needs the prescribed-vectors solver).
    for (mesh, p) in [
        (
            sphere(),
            v1::JobParams {
                tau: Some(0.3),
                ..params(v1::Method::Taubin, 3)
            },
        ),
        (
            cap(),
            v1::JobParams {
                boundary: condition(Condition::Cmc(())),
                ..params(v1::Method::Conformal, 2)
            },
        ),
    ] {
        let op = create(&mut client, mesh, p.clone(), "")
            .await
            .expect("CreateJob");
        let done = poll_until(&mut client, &op.name, |j| {
            !matches!(state(j), v1::job::State::Queued | v1::job::State::Running)
        })
        .await;
        assert_eq!(
            state(&done),
            v1::job::State::Succeeded,
            "{p:?}: {:?}",
            done.error
        );
        assert_eq!(
            done.params.map(|q| q.boundary),
            Some(p.boundary.or(condition(Condition::Auto(()))))
        );
    }

    // Each bad value: INVALID_ARGUMENT naming the field's path in the request.
    let conformal = || params(v1::Method::Conformal, 1);
    let filter = |sigma, k| Some(v1::SpectralFilter { sigma, k });
    let fixed = |x, y, z| Some(v1::rotation_axis::Axis::Fixed(v1::Vector3 { x, y, z }));
    let uniform = |a| Some(v1::boundary_angles::Angles::Uniform(a));
    let cases: Vec<(Option<v1::create_job_request::Mesh>, v1::JobParams, &str)> = vec![
        (
            sphere(),
            v1::JobParams {
                filter: filter(0.1, 4),
                ..conformal()
            },
            "params.filter.k",
        ),
        (
            sphere(),
            v1::JobParams {
                filter: filter(0.0, 2),
                ..conformal()
            },
            "params.filter.sigma",
        ),
        (
            sphere(),
            v1::JobParams {
                filter: filter(f64::NAN, 2),
                ..conformal()
            },
            "params.filter.sigma",
        ),
        (
            cap(),
            v1::JobParams {
                boundary: prescribed(1.6, None, None),
                ..conformal()
            },
            "params.boundary.prescribed.frame_angle",
        ),
        (
            cap(),
            v1::JobParams {
                boundary: prescribed(-1.55, None, None),
                ..conformal()
            },
            "params.boundary.prescribed.frame_angle",
        ),
        (
            cap(),
            v1::JobParams {
                boundary: prescribed(0.0, fixed(0.0, 0.0, 0.0), None),
                ..conformal()
            },
            "params.boundary.prescribed.axis.fixed",
        ),
        (
            cap(),
            v1::JobParams {
                boundary: prescribed(0.0, fixed(f64::NAN, 0.0, 1.0), None),
                ..conformal()
            },
            "params.boundary.prescribed.axis.fixed",
        ),
        (
            cap(),
            v1::JobParams {
                boundary: prescribed(0.0, None, uniform(f64::INFINITY)),
                ..conformal()
            },
            "params.boundary.prescribed.angles.uniform",
        ),
        (
            sphere(),
            v1::JobParams {
                boundary: prescribed(
                    0.0,
                    None,
                    Some(v1::boundary_angles::Angles::PerLoop(v1::AngleList {
                        values: vec![0.1],
                    })),
                ),
                ..conformal()
            },
            "params.boundary.prescribed.angles.per_loop.values",
        ),
        (
            sphere(),
            v1::JobParams {
                filter: filter(0.1, 1),
                ..params(v1::Method::Mcf, 1)
            },
            "params.filter",
        ),
        (
            sphere(),
            v1::JobParams {
                exactness: Some(false),
                ..params(v1::Method::Taubin, 1)
            },
            "params.exactness",
        ),
        (
            sphere(),
            v1::JobParams {
                mobius_balancing: Some(true),
                ..params(v1::Method::Mcf, 1)
            },
            "params.mobius_balancing",
        ),
        (
            sphere(),
            v1::JobParams {
                boundary: condition(Condition::Fixed(())),
                ..params(v1::Method::Bilaplacian, 1)
            },
            "params.boundary",
        ),
    ];
    for (mesh, p, field) in cases {
        assert_bad_field(create(&mut client, mesh, p, "").await, field);
    }
    // The defaults of conformal-only options are fine with any method.
    let op = create(
        &mut client,
        sphere(),
        v1::JobParams {
            exactness: Some(true),
            mobius_balancing: Some(false),
            boundary: condition(Condition::Free(())),
            tau: Some(0.1),
            ..params(v1::Method::Mcf, 1)
        },
        "",
    )
    .await;
    assert!(op.is_ok(), "{op:?}");
}

/// The frames StreamFrames sent, in order.
fn frames_of(events: &[v1::stream_frames_response::Event]) -> Vec<v1::Frame> {
    use v1::stream_frames_response::Event;
    events
        .iter()
        .filter_map(|e| match e {
            Event::Frame(f) => Some(f.clone()),
            Event::Job(_) => None,
        })
        .collect()
}

/// `safeguard` is reported back by CreateJob and GetJob; frames carry the τ each step used
/// and its rejected tries; and a job whose flow can make no acceptable step (implicit MCF at
/// τ = 1000 on `bumpy_sphere(2, 0.4)`: steps 1 and 2 are kept, step 3 raises W even at
/// τ/1024) ends SUCCEEDED after step 2 with Job.stopped_early (reason NO_PROGRESS), and
/// DownloadResult gives the surface of the last frame.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn safeguard_option_frame_tau_and_no_progress_keeps_the_last_good_mesh() {
    let server = Server::start(|_| {}).await;
    let mut client = server.fairing().await;
    let bumpy = obj_text(&generate::bumpy_sphere(2, 0.4)).into_bytes();

    for (safeguard, reported) in [(None, true), (Some(false), false), (Some(true), true)] {
        let op = create(
            &mut client,
            inline(v1::MeshFormat::Obj, bumpy.clone()),
            v1::JobParams {
                tau: Some(0.5),
                safeguard,
                ..params(v1::Method::Conformal, 3)
            },
            "",
        )
        .await
        .expect("CreateJob");
        let created = job_from_any(op.metadata.as_ref().expect("metadata"));
        assert_eq!(
            created.params.as_ref().and_then(|p| p.safeguard),
            Some(reported),
            "{safeguard:?}"
        );
        let frames = frames_of(&stream_all(&mut client, &op.name, 0).await);
        assert_eq!(frames.len(), 4, "{safeguard:?}");
        let metrics: Vec<(f64, u32)> = frames
            .iter()
            .map(|f| {
                let m = f.metrics.as_ref().expect("metrics");
                (m.tau, m.rejected)
            })
            .collect();
        assert_eq!(metrics, vec![(0.0, 0), (0.5, 0), (0.5, 0), (0.5, 0)]);
        let done = get_job(&mut client, &op.name).await.expect("GetJob");
        assert_eq!(state(&done), v1::job::State::Succeeded);
        assert_eq!(done.params.and_then(|p| p.safeguard), Some(reported));
        assert_eq!(done.latest.map(|m| m.tau), Some(0.5));
        assert_eq!(done.stopped_early, None);
    }

    let op = create(
        &mut client,
        inline(v1::MeshFormat::Obj, bumpy.clone()),
        v1::JobParams {
            tau: Some(1000.0),
            ..params(v1::Method::Mcf, 6)
        },
        "",
    )
    .await
    .expect("CreateJob");
    let frames = frames_of(&stream_all(&mut client, &op.name, 0).await);
    assert_eq!(
        frames.iter().map(|f| f.step).collect::<Vec<_>>(),
        vec![0, 1, 2],
        "steps 1 and 2 kept"
    );
    let last = frames.last().expect("a frame");
    assert_eq!(last.metrics.as_ref().map(|m| m.tau), Some(1000.0));
    let done = get_job(&mut client, &op.name).await.expect("GetJob");
    assert_eq!(state(&done), v1::job::State::Succeeded, "{:?}", done.error);
    assert_eq!(done.error, None, "not a failure");
    assert_eq!((done.step, done.total_steps), (2, 6));
    let note = done.stopped_early.expect("Job.stopped_early");
    assert_eq!(note.code, Code::Ok as i32);
    assert!(
        note.message.contains("no progress at step 3")
            && note.message.contains("Willmore energy would rise"),
        "{}",
        note.message
    );
    let info = note
        .details
        .iter()
        .find(|d| d.type_url == "type.googleapis.com/google.rpc.ErrorInfo")
        .map(|d| tonic_types::pb::ErrorInfo::decode(d.value.as_ref()).expect("ErrorInfo"))
        .expect("ErrorInfo detail");
    assert_eq!(info.reason, "NO_PROGRESS");

    let text = download_obj(&mut client, &op.name).await;
    let frame = service_http_support::f32_triples(
        last.positions
            .as_ref()
            .expect("the last frame carries positions"),
    );
    service_http_support::assert_obj_result_is_frame(&text, &frame, 162);
}

/// `refine` over gRPC (issue 26 item 5): the icosahedron (20 faces) is Loop-subdivided before
/// the flow, the job's counts are the refined mesh's, frame 0 alone says the connectivity
/// changed and carries the refined vertices, and the result has the refined faces.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn refine_reports_the_refined_mesh_and_frame_zero_says_so() {
    let server = Server::start(|_| {}).await;
    let mut client = server.fairing().await;
    let mesh = inline(
        v1::MeshFormat::Obj,
        obj_text(&generate::icosphere(0)).into_bytes(),
    );
    let op = create(
        &mut client,
        mesh,
        v1::JobParams {
            refine: Some(true),
            ..long_running(2)
        },
        "",
    )
    .await
    .expect("CreateJob with refine");
    let job = job_from_any(op.metadata.as_ref().expect("metadata"));
    assert_eq!(job.params.as_ref().and_then(|p| p.refine), Some(true));
    let name = job.name.clone();
    let done = poll_until(&mut client, &name, |j| {
        state(j) == v1::job::State::Succeeded || state(j) == v1::job::State::Failed
    })
    .await;
    assert_eq!(state(&done), v1::job::State::Succeeded, "{done:?}");
    // 20 · 4^levels faces, V = F/2 + 2 vertices on a closed genus-0 surface.
    let faces = done.face_count as usize;
    assert!(faces >= 20 * 16 && faces.is_multiple_of(20), "{faces}");
    assert_eq!(done.vertex_count as usize, faces / 2 + 2);

    let frames: Vec<v1::Frame> = stream_all(&mut client, &name, 0)
        .await
        .into_iter()
        .filter_map(|e| match e {
            v1::stream_frames_response::Event::Frame(f) => Some(f),
            _ => None,
        })
        .collect();
    assert_eq!(frames[0].step, 0);
    assert!(frames[0].connectivity_changed);
    assert!(frames[1..].iter().all(|f| !f.connectivity_changed));
    let positions = frames[0].positions.as_ref().expect("frame 0 positions");
    assert_eq!(positions.len(), 12 * done.vertex_count as usize);

    let obj = download_obj(&mut client, &name).await;
    assert_eq!(obj.lines().filter(|l| l.starts_with("f ")).count(), faces);
}
