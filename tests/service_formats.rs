//! STL, PLY and OFF through every interface (issue 27, item 2): uploaded over HTTP by media
//! type, by `application/octet-stream` content and as multipart by file name, and over gRPC
//! by `MeshFormat`; faired; and downloaded by default in the input's own format with its
//! media type, keeping the file's vertex and triangle counts.

mod service_http_support;

use service_http_support::*;
use std::time::Duration;
use tonic::transport::Channel;
use willow::mesh::generate;
use willow::mesh::io::{Asset, Format, Limits};
use willow_service::api::grpc::pb::willow::v1;
use willow_service::jobs::{Config, Jobs, Shutdown};

const JOB_TIMEOUT: Duration = Duration::from_secs(120);

/// The small bumpy sphere in `format`, written by the library (binary STL, binary PLY, OFF).
fn sphere_as(format: Format) -> Vec<u8> {
    let a = Asset::from_mesh(generate::bumpy_sphere(2, 0.1), &Limits::default()).unwrap();
    a.write(&a.surface().positions, format).unwrap()
}

/// The sphere as a scanner's ASCII PLY with per-vertex colours, for the "kept" check.
fn coloured_ascii_ply() -> String {
    let m = generate::bumpy_sphere(2, 0.1);
    let mut s = format!(
        "ply\nformat ascii 1.0\nelement vertex {}\nproperty float x\nproperty float y\n\
         property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n\
         element face {}\nproperty list uchar int vertex_indices\nend_header\n",
        m.positions.len(),
        m.triangles.len()
    );
    for (i, p) in m.positions.iter().enumerate() {
        s += &format!(
            "{} {} {} {} {} {}\n",
            p[0],
            p[1],
            p[2],
            i % 256,
            (i * 3) % 256,
            7
        );
    }
    for t in &m.triangles {
        s += &format!("3 {} {} {}\n", t[0], t[1], t[2]);
    }
    s
}

/// Parses a result in `format` and returns (file vertices, faces).
fn counts(bytes: &[u8], format: Format) -> (usize, usize) {
    let a = Asset::read(bytes, format, &Limits::default()).expect("the result parses");
    (a.file_vertex_count(), a.surface().face_count())
}

async fn submit(srv: &TestServer, content_type: &str, body: Vec<u8>) -> serde_json::Value {
    let res = srv
        .client
        .post(srv.url("/v1/jobs?steps=3&method=conformal"))
        .header("content-type", content_type)
        .body(body)
        .send()
        .await
        .expect("POST /v1/jobs");
    let status = res.status();
    let json: serde_json::Value = res.json().await.unwrap_or_default();
    assert_eq!(status, 202, "{content_type}: {json}");
    json
}

async fn result_of(srv: &TestServer, id: &str) -> (String, String, Vec<u8>) {
    let done = srv.poll_until(id, JOB_TIMEOUT, is_terminal).await;
    assert_eq!(done["state"], "succeeded", "{done}");
    let res = srv
        .client
        .get(srv.url(&format!("/v1/jobs/{id}/result")))
        .send()
        .await
        .expect("GET result");
    assert_eq!(res.status(), 200);
    let header = |h: &str| {
        res.headers()
            .get(h)
            .and_then(|v| v.to_str().ok())
            .unwrap_or("")
            .to_string()
    };
    let (ct, cd) = (header("content-type"), header("content-disposition"));
    (ct, cd, res.bytes().await.expect("body").to_vec())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn http_uploads_each_format_and_returns_it_in_kind() {
    let srv = start(|_| {}).await;
    let ply = coloured_ascii_ply();
    let cases: Vec<(&str, Vec<u8>, Format)> = vec![
        ("model/stl", sphere_as(Format::Stl), Format::Stl),
        (
            "application/vnd.ms-pki.stl",
            sphere_as(Format::Stl),
            Format::Stl,
        ),
        ("model/x-ply", sphere_as(Format::Ply), Format::Ply),
        ("application/ply", ply.clone().into_bytes(), Format::Ply),
        ("model/x-off", sphere_as(Format::Off), Format::Off),
        (
            "application/octet-stream",
            sphere_as(Format::Off),
            Format::Off,
        ),
        (
            "application/octet-stream",
            sphere_as(Format::Stl),
            Format::Stl,
        ),
    ];
    for (ct, body, format) in cases {
        let expected = counts(&body, format);
        let job = submit(&srv, ct, body).await;
        assert_eq!(job["input_format"], format.extension(), "{ct}: {job}");
        let id = job["id"].as_str().expect("id").to_string();
        let (got_ct, cd, bytes) = result_of(&srv, &id).await;
        assert_eq!(got_ct, format.mime(), "{ct}");
        assert!(cd.ends_with(&format!(".{}\"", format.extension())), "{cd}");
        assert_eq!(counts(&bytes, format), expected, "{ct}: same counts back");
        assert_eq!(Format::sniff(&bytes), Some(format));
    }

    // The coloured PLY comes back with its colours: only x y z changed on each vertex line.
    let job = submit(&srv, "model/x-ply", ply.clone().into_bytes()).await;
    let (_, _, bytes) = result_of(&srv, job["id"].as_str().expect("id")).await;
    let out = String::from_utf8(bytes).expect("ASCII PLY");
    let (a, b): (Vec<&str>, Vec<&str>) = (ply.lines().collect(), out.lines().collect());
    assert_eq!(a.len(), b.len());
    let mut moved = 0;
    for (x, y) in a.iter().zip(&b) {
        let (xw, yw): (Vec<&str>, Vec<&str>) = (x.split(' ').collect(), y.split(' ').collect());
        if xw.len() == 6 && xw[0].parse::<f64>().is_ok() {
            assert_eq!(xw[3..], yw[3..], "colour kept");
            moved += usize::from(xw[..3] != yw[..3]);
        } else {
            assert_eq!(x, y);
        }
    }
    assert!(moved > 100, "the flow moved the vertices ({moved})");

    // Multipart by file name (browsers send application/octet-stream for .ply); an OBJ named
    // .stl is named as the OBJ it is; an unknown explicit type is still 415.
    for (name, body, code) in [
        ("scan.ply", sphere_as(Format::Ply), 202),
        ("part.stl", small_obj().into_bytes(), 422),
    ] {
        let form = reqwest::multipart::Form::new().part(
            "mesh",
            reqwest::multipart::Part::bytes(body)
                .file_name(name)
                .mime_str("application/octet-stream")
                .expect("mime"),
        );
        let res = srv
            .client
            .post(srv.url("/v1/jobs"))
            .multipart(form)
            .send()
            .await
            .expect("send");
        let status = res.status().as_u16();
        let json: serde_json::Value = res.json().await.unwrap_or_default();
        assert_eq!(status, code, "{name}: {json}");
        if code == 422 {
            assert_eq!(json["code"], "format_mismatch", "{json}");
            assert!(
                json["detail"].as_str().unwrap_or("").contains("it is OBJ"),
                "{json}"
            );
        }
    }
    let res = srv
        .client
        .post(srv.url("/v1/jobs"))
        .header("content-type", "application/octet-stream")
        .body(vec![0x1f, 0x8b, 8, 0, 0, 0, 0, 0, 0, 3])
        .send()
        .await
        .expect("send");
    assert_eq!(res.status(), 415);
    let json: serde_json::Value = res.json().await.unwrap_or_default();
    assert!(
        json["detail"].as_str().unwrap_or("").contains("gzip"),
        "{json}"
    );
}

// ---------------------------------------------------------------------------------------------
// gRPC

struct Grpc {
    addr: String,
    _jobs: Jobs,
    _core: Shutdown,
    _dir: tempfile::TempDir,
}

async fn grpc_server() -> Grpc {
    let dir = tempfile::tempdir().expect("temp dir");
    let mut config = Config::new(dir.path());
    config.workers = 1;
    let (jobs, core) = Jobs::start(config).await.expect("job core starts");
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind loopback");
    let addr = format!("http://{}", listener.local_addr().expect("local addr"));
    let app = willow_service::api::auth::Auth::none()
        .wrap(willow_service::api::grpc::routes(jobs.clone()));
    tokio::spawn(async move { axum::serve(listener, app).await });
    Grpc {
        addr,
        _jobs: jobs,
        _core: core,
        _dir: dir,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn grpc_takes_each_format_and_downloads_it_in_kind() {
    let srv = grpc_server().await;
    let channel = Channel::from_shared(srv.addr.clone())
        .expect("uri")
        .connect()
        .await
        .expect("connect");
    let mut client = v1::fairing_client::FairingClient::new(channel);
    for (pb, format) in [
        (v1::MeshFormat::Stl, Format::Stl),
        (v1::MeshFormat::Ply, Format::Ply),
        (v1::MeshFormat::Off, Format::Off),
    ] {
        let body = sphere_as(format);
        let expected = counts(&body, format);
        let op = client
            .create_job(v1::CreateJobRequest {
                mesh: Some(v1::create_job_request::Mesh::InlineMesh(v1::InlineMesh {
                    format: pb as i32,
                    data: body.into(),
                })),
                params: Some(v1::JobParams {
                    method: v1::Method::Conformal as i32,
                    steps: Some(3),
                    ..Default::default()
                }),
                request_id: String::new(),
            })
            .await
            .expect("CreateJob")
            .into_inner();
        let waiting = async {
            loop {
                let job = client
                    .get_job(v1::GetJobRequest {
                        name: op.name.clone(),
                    })
                    .await
                    .expect("GetJob")
                    .into_inner();
                if job.state == v1::job::State::Succeeded as i32 {
                    return job;
                }
                assert_ne!(job.state, v1::job::State::Failed as i32, "{:?}", job.error);
                tokio::time::sleep(Duration::from_millis(25)).await;
            }
        };
        let job = tokio::time::timeout(JOB_TIMEOUT, waiting)
            .await
            .expect("the job finishes");
        assert_eq!(job.input_format, pb as i32);
        let mut download = client
            .download_result(v1::DownloadResultRequest {
                name: op.name.clone(),
                format: v1::MeshFormat::Unspecified as i32,
            })
            .await
            .expect("DownloadResult")
            .into_inner();
        let mut file = Vec::new();
        let mut first_format = None;
        while let Some(chunk) = download.message().await.expect("stream") {
            first_format.get_or_insert(chunk.format);
            file.extend_from_slice(&chunk.data);
        }
        assert_eq!(
            first_format,
            Some(pb as i32),
            "the input's format by default"
        );
        assert_eq!(counts(&file, format), expected, "{format:?}");
    }
}
