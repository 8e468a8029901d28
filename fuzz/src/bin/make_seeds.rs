//! Writes seed corpora for the targets whose inputs the repository has no files of:
//! `make-seeds OUT MESH.obj…` converts each OBJ to glTF and GLB (into `OUT/gltf/`) and writes
//! `OUT/grpc_upload/` (UploadMesh streams and CreateJob requests, framed as the target reads
//! them) and `OUT/http_params/` (query strings and `params` parts). scripts/fuzz.sh runs it
//! before fuzzing; nothing it writes is committed.
//!
//! It is built like the targets (cargo-fuzz builds every binary of this crate with coverage
//! instrumentation, whose hooks only libFuzzer defines), so it is a libFuzzer binary too: the
//! work is done in its initialization, which libFuzzer runs first, and the process exits
//! there without fuzzing.
#![no_main]

use prost::Message as _;
use std::path::{Path, PathBuf};
use willow_service::api::grpc::pb::willow::v1;
use willow::mesh::io::{Asset, Format, Limits};

type Error = Box<dyn std::error::Error>;

libfuzzer_sys::fuzz_target!(init: run_and_exit(), |_data: &[u8]| {});

/// Writes the seeds and ends the process (before libFuzzer starts fuzzing).
fn run_and_exit() {
    let code = match make_seeds() {
        Ok(()) => 0,
        Err(e) => {
            eprintln!("make-seeds: {e}");
            1
        }
    };
    std::process::exit(code)
}

fn make_seeds() -> Result<(), Error> {
    let mut args = std::env::args_os().skip(1);
    let out = PathBuf::from(args.next().ok_or("usage: make-seeds OUT MESH.obj…")?);
    let meshes: Vec<PathBuf> = args.map(PathBuf::from).collect();
    let dir = |name: &str| -> Result<PathBuf, Error> {
        let d = out.join(name);
        std::fs::create_dir_all(&d)?;
        Ok(d)
    };
    let (gltf, grpc, http) = (dir("gltf")?, dir("grpc_upload")?, dir("http_params")?);

    // A tetrahedron: a seed small enough for any -max_len, whatever meshes are given.
    let small_obj: &[u8] =
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n";
    let mut sources = vec![("tetra".to_string(), small_obj.to_vec())];
    for mesh in &meshes {
        sources.push((stem(mesh), std::fs::read(mesh)?));
    }
    for (stem, bytes) in &sources {
        let asset = Asset::read(bytes, Format::Obj, &Limits::default())?;
        let positions = asset.surface().positions.clone();
        for format in [Format::Gltf, Format::Glb] {
            let file = asset.write(&positions, format)?;
            std::fs::write(gltf.join(format!("{stem}.{}", format.extension())), file)?;
        }
    }

    // UploadMesh: a header, then the file in chunks (one seed per format).
    for (i, (format, data)) in [(v1::MeshFormat::Obj, small_obj)].into_iter().enumerate() {
        let header = v1::UploadMeshChunk {
            part: Some(v1::upload_mesh_chunk::Part::Header(v1::UploadHeader {
                format: format as i32,
                size_bytes: data.len() as u64,
            })),
        };
        let mut stream = vec![header.encode_to_vec()];
        for chunk in data.chunks(64) {
            let msg = v1::UploadMeshChunk {
                part: Some(v1::upload_mesh_chunk::Part::Data(chunk.to_vec().into())),
            };
            stream.push(msg.encode_to_vec());
        }
        std::fs::write(grpc.join(format!("upload-{i}")), frame(&stream))?;
    }
    // CreateJob requests (the first message is also decoded as one).
    let requests = [
        v1::CreateJobRequest {
            mesh: Some(v1::create_job_request::Mesh::Upload("uploads/0".into())),
            params: None,
            request_id: String::new(),
        },
        v1::CreateJobRequest {
            mesh: Some(v1::create_job_request::Mesh::InlineMesh(v1::InlineMesh {
                format: v1::MeshFormat::Obj as i32,
                data: small_obj.to_vec().into(),
            })),
            params: Some(v1::JobParams {
                method: v1::Method::Mcf as i32,
                steps: Some(3),
                tau: Some(0.25),
                iterations: Some(2),
                frame_interval: Some(1),
                include_positions: Some(true),
                deadline: Some(prost_types::Duration {
                    seconds: 30,
                    nanos: 5,
                }),
                exactness: Some(false),
                mobius_balancing: Some(true),
                filter: Some(v1::SpectralFilter { sigma: 0.01, k: 2 }),
                boundary: Some(v1::Boundary {
                    condition: Some(v1::boundary::Condition::Prescribed(v1::PrescribedVectors {
                        frame_angle: 0.2,
                        ..Default::default()
                    })),
                }),
                safeguard: Some(true),
                region: vec![v1::Region {
                    shape: Some(v1::region::Shape::Sphere(v1::region::Sphere {
                        center: Some(v1::Vector3 {
                            x: 0.0,
                            y: 0.0,
                            z: 1.0,
                        }),
                        radius: 0.5,
                    })),
                }],
                seam: v1::Seam::Fixed as i32,
                preserve: v1::Preserve::Volume as i32,
                until_willmore: Some(13.0),
                until_converged: Some(false),
                max_deviation: Some(0.1),
                measure_deviation: Some(true),
                feature_size: Some(0.2),
                falloff: Some(0.05),
                callback_url: Some("https://hooks.example/willow".into()),
                repair: Some(true),
                refine: Some(true),
                denoise: Some(v1::DenoiseParams {
                    iterations: Some(6),
                    vertex_iterations: Some(5),
                    sigma_r: Some(0.3),
                    radius: Some(1.5),
                    guided: Some(false),
                }),
                feature_angle: Some("45".into()),
                fill_holes: Some("120".into()),
                refine_edge: Some(0.05),
            }),
            request_id: "3f2504e0-4f89-41d3-9a0c-0305e82c3301".into(),
        },
    ];
    for (i, request) in requests.iter().enumerate() {
        std::fs::write(
            grpc.join(format!("create-{i}")),
            frame(&[request.encode_to_vec()]),
        )?;
    }

    // HTTP parameters: query strings, and `params` parts after a NUL byte.
    let http_seeds: [&[u8]; 6] = [
        b"steps=3&tau=0.25&method=mcf&iterations=2&frame_interval=1&include_positions=true",
        b"deadline_secs=30&exactness=false&mobius_balancing=true&safeguard=false&filter.sigma=0.01&filter.k=2",
        b"boundary=prescribed&boundary.prescribed.frame_angle=0.2&boundary.prescribed.angles.per_loop=0.1,-0.1",
        b"boundary.prescribed.axis.fixed=0,0,1&boundary.prescribed.angles.uniform=0.3",
        b"\0{\"method\":\"conformal\",\"steps\":5,\"tau\":0.5,\"filter\":{\"sigma\":0.1,\"k\":1},\"boundary\":\"cmc\"}",
        b"\0{\"boundary\":{\"prescribed\":{\"frame_angle\":0.1,\"axis\":{\"fixed\":[0,0,1]},\"angles\":{\"per_loop\":[0.1]}}}}",
    ];
    for (i, seed) in http_seeds.iter().enumerate() {
        std::fs::write(http.join(format!("seed-{i}")), seed)?;
    }
    Ok(())
}

/// Messages framed as the grpc_upload target reads them: 2-byte little-endian length, bytes.
fn frame(messages: &[Vec<u8>]) -> Vec<u8> {
    let mut out = Vec::new();
    for m in messages {
        let n = u16::try_from(m.len()).unwrap_or(u16::MAX);
        out.extend_from_slice(&n.to_le_bytes());
        out.extend_from_slice(&m[..usize::from(n)]);
    }
    out
}

fn stem(p: &Path) -> String {
    p.file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "mesh".into())
}
