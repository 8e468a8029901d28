use super::*;
use tonic::transport::Channel;
use tonic::Code;
use tonic_types::StatusExt;
use v1::fairing_client::FairingClient;
use willow_service::api::grpc::pb::willow::v1;
use willow_service::jobs::{Config, Jobs};

async fn client() -> (FairingClient<Channel>, tempfile::TempDir) {
    let dir = tempfile::tempdir().expect("temp dir");
    let mut config = Config::new(dir.path());
    config.workers = 1;
    let (jobs, core) = Jobs::start(config).await.expect("job core starts");
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind loopback");
    let addr = format!("http://{}", listener.local_addr().expect("local addr"));
    let app = willow_service::api::auth::Auth::none().wrap(willow_service::api::grpc::routes(jobs));
    tokio::spawn(async move {
        let _core = core;
        axum::serve(listener, app).await
    });
    let channel = Channel::from_shared(addr)
        .expect("uri")
        .connect()
        .await
        .expect("connect");
    (FairingClient::new(channel), dir)
}

fn request(mesh: &Mesh, params: v1::JobParams) -> v1::CreateJobRequest {
    v1::CreateJobRequest {
        mesh: Some(v1::create_job_request::Mesh::InlineMesh(v1::InlineMesh {
            format: v1::MeshFormat::Obj as i32,
            data: obj_text(mesh).into_bytes().into(),
        })),
        params: Some(params),
        ..Default::default()
    }
}

async fn wait(client: &mut FairingClient<Channel>, name: &str) -> v1::Job {
    let polling = async {
        loop {
            let job = client
                .get_job(v1::GetJobRequest {
                    name: name.to_string(),
                })
                .await
                .expect("GetJob")
                .into_inner();
            if job.end_time.is_some() {
                return job;
            }
            tokio::time::sleep(Duration::from_millis(25)).await;
        }
    };
    tokio::time::timeout(JOB_TIMEOUT, polling)
        .await
        .expect("the job ends")
}

/// A region, its seam, volume, distance and the stopping rules go in as fields; the job
/// reports them back, the vertices outside the region stay put, frames carry volume and
/// distance, and the job says how it ended.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn controls_are_fields_and_the_job_reports_its_outcome() {
    let (mut client, _dir) = client().await;
    let mesh = bumpy();
    let center = mesh.positions[0];
    let region = v1::Region {
        shape: Some(v1::region::Shape::Sphere(v1::region::Sphere {
            center: Some(v1::Vector3 {
                x: center[0],
                y: center[1],
                z: center[2],
            }),
            radius: 0.6,
        })),
    };
    // Two steps: this wide fixed-seam cap reaches what its held border allows a conformal
    // flow at the third (flow/willmore/pinned.rs), and the job would end `converged`.
    let params = v1::JobParams {
        method: v1::Method::Conformal as i32,
        steps: Some(2),
        region: vec![region.clone()],
        seam: v1::Seam::Fixed as i32,
        until_converged: Some(false),
        measure_deviation: Some(true),
        ..Default::default()
    };
    let op = client
        .create_job(request(&mesh, params))
        .await
        .expect("CreateJob")
        .into_inner();
    let job = wait(&mut client, &op.name).await;
    assert_eq!(job.state, v1::job::State::Succeeded as i32, "{job:?}");
    assert_eq!(job.outcome, "completed");
    assert_eq!(job.outcome_reason, "ran its 2 steps");
    let p = job.params.as_ref().expect("params");
    assert_eq!(p.region, vec![region]);
    assert_eq!(p.seam, v1::Seam::Fixed as i32);
    assert_eq!(p.preserve, v1::Preserve::Area as i32);
    assert_eq!(
        (p.until_converged, p.measure_deviation),
        (Some(false), Some(true))
    );
    let latest = job.latest.as_ref().expect("metrics");
    // A region job's metrics are the region's patch (`flow::region`): open, so it encloses
    // no volume; the distance is measured all the same.
    assert_eq!(latest.volume, Some(0.0), "{latest:?}");
    assert!(latest.deviation_max.is_some_and(|d| d > 0.0), "{latest:?}");

    // until_willmore and preserve: the run ends target_reached, stopped_early says so.
    let target = 4.0 * std::f64::consts::PI * 1.05;
    let params = v1::JobParams {
        method: v1::Method::Conformal as i32,
        steps: Some(40),
        preserve: v1::Preserve::Volume as i32,
        until_willmore: Some(target),
        ..Default::default()
    };
    let op = client
        .create_job(request(&mesh, params))
        .await
        .expect("CreateJob")
        .into_inner();
    let job = wait(&mut client, &op.name).await;
    assert_eq!(job.outcome, "target_reached", "{job:?}");
    assert!(job.latest.as_ref().expect("metrics").willmore_energy <= target);
    let early = job.stopped_early.as_ref().expect("stopped early");
    assert!(early.message.contains("until_willmore"), "{early:?}");
    assert_eq!(
        job.params.as_ref().expect("params").preserve,
        v1::Preserve::Volume as i32
    );
}

/// A message over the server's limit is RESOURCE_EXHAUSTED with a QuotaFailure, as the
/// proto promises (tonic alone says OUT_OF_RANGE, without details).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_oversized_message_is_resource_exhausted_with_a_quota_failure() {
    let (mut client, _dir) = client().await;
    let request = v1::CreateJobRequest {
        mesh: Some(v1::create_job_request::Mesh::InlineMesh(v1::InlineMesh {
            format: v1::MeshFormat::Obj as i32,
            data: vec![b'#'; 5 << 20].into(),
        })),
        ..Default::default()
    };
    let status = client.create_job(request).await.expect_err("refused");
    assert_eq!(status.code(), Code::ResourceExhausted, "{status:?}");
    let quota = status.get_details_quota_failure().expect("a QuotaFailure");
    assert_eq!(quota.violations[0].subject, "request message bytes");
    assert!(
        status.message().contains("UploadMesh")
            || quota.violations[0].description.contains("UploadMesh")
    );
}

/// A `refine` plan past the limits (issue 42 item 2): RESOURCE_EXHAUSTED at CreateJob, with
/// the violation on `params.refine` and the planned size in the message.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_refine_past_the_limits_is_refused_at_create_job_naming_refine() {
    let (mut client, _dir) = client().await;
    let mesh = generate::icosphere(2);
    let params = v1::JobParams {
        refine: Some(true),
        refine_edge: Some(generate::mean_edge_length(&mesh) / 1e6),
        ..Default::default()
    };
    let status = client
        .create_job(request(&mesh, params))
        .await
        .expect_err("refused");
    assert_eq!(status.code(), Code::ResourceExhausted, "{status:?}");
    let fields: Vec<String> = status
        .get_details_bad_request()
        .map(|b| b.field_violations.into_iter().map(|v| v.field).collect())
        .unwrap_or_default();
    assert_eq!(fields, vec!["params.refine".to_string()], "{status:?}");
    let planned = (320u64 * 4u64.pow(20)).to_string();
    assert!(status.message().contains(&planned), "{status:?}");
}

/// Bad controls are INVALID_ARGUMENT naming the field.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_controls_are_invalid_arguments_naming_the_field() {
    let (mut client, _dir) = client().await;
    let mesh = generate::bumpy_sphere(2, 0.1);
    let cases = [
        (
            v1::JobParams {
                region: vec![v1::Region { shape: None }],
                ..Default::default()
            },
            "params.region[0]",
        ),
        (
            v1::JobParams {
                max_deviation: Some(-1.0),
                ..Default::default()
            },
            "params.max_deviation",
        ),
        (
            v1::JobParams {
                method: v1::Method::Taubin as i32,
                preserve: v1::Preserve::Volume as i32,
                ..Default::default()
            },
            "params.preserve",
        ),
        (
            v1::JobParams {
                seam: 42,
                ..Default::default()
            },
            "params.seam",
        ),
        (
            v1::JobParams {
                region: vec![v1::Region {
                    shape: Some(v1::region::Shape::Group("ears".into())),
                }],
                ..Default::default()
            },
            "params.region",
        ),
        (
            v1::JobParams {
                feature_size: Some(-1.0),
                ..Default::default()
            },
            "params.feature_size",
        ),
        (
            v1::JobParams {
                feature_angle: Some("sharp".into()),
                ..Default::default()
            },
            "params.feature_angle",
        ),
        (
            v1::JobParams {
                method: v1::Method::Conformal as i32,
                feature_angle: Some("200".into()),
                ..Default::default()
            },
            "params.feature_angle",
        ),
        (
            v1::JobParams {
                fill_holes: Some("2".into()),
                ..Default::default()
            },
            "params.fill_holes",
        ),
        (
            v1::JobParams {
                fill_holes: Some("-0.5".into()),
                ..Default::default()
            },
            "params.fill_holes",
        ),
        (
            v1::JobParams {
                refine_edge: Some(0.1),
                ..Default::default()
            },
            "params.refine_edge",
        ),
        (
            v1::JobParams {
                refine: Some(true),
                refine_edge: Some(f64::NAN),
                ..Default::default()
            },
            "params.refine_edge",
        ),
    ];
    for (params, field) in cases {
        let status = client
            .create_job(request(&mesh, params))
            .await
            .expect_err("refused");
        assert_eq!(status.code(), Code::InvalidArgument, "{field}: {status:?}");
        let fields: Vec<String> = status
            .get_details_bad_request()
            .map(|b| b.field_violations.into_iter().map(|v| v.field).collect())
            .unwrap_or_default();
        assert_eq!(fields, vec![field.to_string()], "{status:?}");
    }
}
