//! `preserve: volume` (issue "Fairing a user can steer", first control): every closed
//! component keeps its input enclosed volume at every step, through a uniform scale about its
//! centroid, while the Willmore energy falls; the reported volume is the divergence-theorem
//! sum of the closed components.

use std::collections::{HashMap, HashSet};
use willow::flow::{new_flow, FlowError, FlowParams, Method, Preserve};
use willow::geometry::operators::enclosed_volume;
use willow::mesh::generate::{bumpy_cap, bumpy_sphere, torus};
use willow::mesh::topology::Topology;
use willow::mesh::Mesh;

/// The boundary faces of a union of unit voxels, each unit square split into two triangles,
/// wound counter-clockwise seen from outside. Voxels meet only through whole faces or not at
/// all (the callers' blobs are height fields over 4-connected footprints), so the surface is
/// a manifold with integer vertices, no T-junctions, and an exact integer volume.
fn voxel_surface(voxels: &HashSet<[i32; 3]>) -> Mesh {
    let mut index: HashMap<[i32; 3], usize> = HashMap::new();
    let mut positions = Vec::new();
    let mut triangles = Vec::new();
    let mut vertex = |p: [i32; 3], positions: &mut Vec<[f64; 3]>| {
        *index.entry(p).or_insert_with(|| {
            positions.push([p[0] as f64, p[1] as f64, p[2] as f64]);
            positions.len() - 1
        })
    };
    let mut sorted: Vec<[i32; 3]> = voxels.iter().copied().collect();
    sorted.sort_unstable();
    for v in sorted {
        for axis in 0..3 {
            let (u, w) = ((axis + 1) % 3, (axis + 2) % 3);
            for side in [0, 1] {
                let mut neighbour = v;
                neighbour[axis] += if side == 1 { 1 } else { -1 };
                if voxels.contains(&neighbour) {
                    continue;
                }
                // The face's corners in the (u, w) plane at `axis = v[axis] + side`; (u, w,
                // axis) is right-handed, so (0,0) → (1,0) → (1,1) → (0,1) faces +axis.
                let corner = |du: i32, dw: i32| {
                    let mut p = v;
                    p[axis] += side;
                    p[u] += du;
                    p[w] += dw;
                    p
                };
                let mut quad = [corner(0, 0), corner(1, 0), corner(1, 1), corner(0, 1)];
                if side == 0 {
                    quad.reverse();
                }
                let q = quad.map(|p| vertex(p, &mut positions));
                triangles.push([q[0], q[1], q[2]]);
                triangles.push([q[0], q[2], q[3]]);
            }
        }
    }
    Mesh::new(positions, triangles).expect("a voxel surface is a valid mesh")
}

/// A terraced blob: columns over a footprint, of the given heights (a height field).
fn terraces(heights: &[(i32, i32, i32)]) -> HashSet<[i32; 3]> {
    heights
        .iter()
        .flat_map(|&(x, y, h)| (0..h).map(move |z| [x, y, z]))
        .collect()
}

/// Genus 0: a 4 × 3 footprint stepped down from 4 voxels high to 1 (a staircase), with a
/// one-voxel tower on the top step.
fn staircase() -> (Mesh, f64) {
    let mut columns = Vec::new();
    for x in 0..4 {
        for y in 0..3 {
            let tower = (x, y) == (0, 1);
            columns.push((x, y, 4 - x + i32::from(tower)));
        }
    }
    let voxels = terraces(&columns);
    let n = voxels.len() as f64;
    (voxel_surface(&voxels), n)
}

/// Genus 1: a square ring (4 × 4 footprint around a 2 × 2 hole), one voxel high on two sides
/// and two or three on the others.
fn terraced_ring() -> (Mesh, f64) {
    let mut columns = Vec::new();
    for x in 0..4 {
        for y in 0..4 {
            if (1..3).contains(&x) && (1..3).contains(&y) {
                continue;
            }
            let h = match (x, y) {
                (0, _) => 3,
                (_, 0) => 2,
                _ => 1,
            };
            columns.push((x, y, h));
        }
    }
    let voxels = terraces(&columns);
    let n = voxels.len() as f64;
    (voxel_surface(&voxels), n)
}

fn volume(mesh: &Mesh, positions: &[[f64; 3]]) -> f64 {
    enclosed_volume(positions, &mesh.triangles, positions[0])
}

/// Run `steps` steps with `preserve`, and check at every step that the reported volume is
/// the volume of the returned positions and W never rose. Returns (V₀, per-step volumes,
/// W₀, per-step W, per-step area).
fn flow(
    mesh: &Mesh,
    method: Method,
    tau: f64,
    preserve: Preserve,
    steps: usize,
) -> (f64, Vec<f64>, f64, Vec<f64>, Vec<f64>) {
    let params = FlowParams {
        method,
        tau,
        preserve,
        ..FlowParams::default()
    };
    let mut flow = new_flow(mesh, &params).expect("flow");
    let initial = flow.initial_metrics();
    let (mut volumes, mut energies, mut areas) = (Vec::new(), Vec::new(), Vec::new());
    let mut previous_w = initial.willmore_energy;
    for _ in 0..steps {
        let m = flow.step().expect("step");
        let v = volume(mesh, flow.positions());
        assert!(
            (m.volume.expect("reported") - v).abs() <= 1e-9 * v.abs(),
            "step {}: reported volume {} vs {v}",
            m.step,
            m.volume.expect("reported")
        );
        assert!(
            m.willmore_energy <= previous_w * (1.0 + 1e-6),
            "step {}: W rose from {previous_w} to {}",
            m.step,
            m.willmore_energy
        );
        previous_w = m.willmore_energy;
        volumes.push(m.volume.expect("reported"));
        energies.push(m.willmore_energy);
        areas.push(m.area);
    }
    (
        initial.volume.expect("reported"),
        volumes,
        initial.willmore_energy,
        energies,
        areas,
    )
}

fn assert_volume_kept(name: &str, mesh: &Mesh, method: Method, tau: f64, steps: usize) {
    let (v0, volumes, w0, energies, _) = flow(mesh, method, tau, Preserve::Volume, steps);
    for (k, v) in volumes.iter().enumerate() {
        assert!(
            (v / v0 - 1.0).abs() < 1e-6,
            "{name}: step {}: volume {v} vs {v0}",
            k + 1
        );
    }
    let w_end = energies[energies.len() - 1];
    assert!(w_end < 0.9 * w0, "{name}: W fell only from {w0} to {w_end}");
    // The same run keeping the area instead loses volume measurably: the volume above was
    // kept by the policy, not by the flow.
    let (_, area_volumes, _, _, _) = flow(mesh, method, tau, Preserve::Area, steps);
    let drift = (area_volumes[area_volumes.len() - 1] / v0 - 1.0).abs();
    assert!(
        drift > 1e-4,
        "{name}: keeping the area, the volume moved only {drift}"
    );
}

#[test]
fn voxel_surfaces_have_their_voxel_count_as_volume_and_the_expected_genus() {
    let (stairs, n) = staircase();
    assert_eq!(n, 31.0);
    assert!((volume(&stairs, &stairs.positions) - n).abs() < 1e-12);
    assert_eq!(Topology::new(&stairs).genus(), 0);
    let (ring, n) = terraced_ring();
    assert_eq!(n, 4.0 * 3.0 + 3.0 * 2.0 + 5.0);
    assert!((volume(&ring, &ring.positions) - n).abs() < 1e-12);
    assert_eq!(Topology::new(&ring).genus(), 1);
}

#[test]
fn conformal_flow_keeps_the_volume_of_a_bumpy_sphere() {
    assert_volume_kept(
        "bumpy sphere",
        &bumpy_sphere(3, 0.15),
        Method::Conformal,
        0.5,
        6,
    );
}

#[test]
fn conformal_flow_keeps_the_volume_of_a_torus() {
    // An elliptic-section torus (squashed in z) is not a critical point of W.
    let mut mesh = torus(2.0, 0.8, 36, 18);
    for p in &mut mesh.positions {
        p[2] *= 0.5;
    }
    assert_volume_kept("torus", &mesh, Method::Conformal, 0.5, 6);
}

#[test]
fn conformal_flow_keeps_the_volume_of_a_voxel_staircase() {
    let (mesh, _) = staircase();
    assert_volume_kept("staircase", &mesh, Method::Conformal, 0.5, 6);
}

#[test]
fn conformal_flow_keeps_the_volume_of_a_terraced_ring() {
    let (mesh, _) = terraced_ring();
    assert_volume_kept("terraced ring", &mesh, Method::Conformal, 0.5, 6);
}

/// Implicit MCF shrinks: with `volume` the volume is given back every step, with `none` it
/// drains away (and the area with it).
#[test]
fn mean_curvature_flow_keeps_the_volume_or_shrinks_with_none() {
    let mesh = bumpy_sphere(3, 0.15);
    assert_volume_kept("MCF", &mesh, Method::Mcf, 0.05, 5);
    let (v0, volumes, _, _, areas) = flow(&mesh, Method::Mcf, 0.05, Preserve::None, 5);
    let a0 = new_flow(&mesh, &FlowParams::default())
        .expect("flow")
        .initial_metrics()
        .area;
    assert!(volumes[4] < 0.8 * v0, "{} vs {v0}", volumes[4]);
    assert!(areas[4] < 0.8 * a0, "{} vs {a0}", areas[4]);
}

/// A sphere beside an open cap: the volume is the sphere's alone (the cap adds 0) and is
/// kept; the cap keeps its area.
#[test]
fn an_open_component_adds_no_volume_and_keeps_its_area() {
    let mut mesh = bumpy_sphere(3, 0.15);
    let sphere_volume = volume(&mesh, &mesh.positions);
    let cap = bumpy_cap(3, 0.1);
    let offset = mesh.vertex_count();
    mesh.positions
        .extend(cap.positions.iter().map(|p| [p[0] + 4.0, p[1], p[2]]));
    mesh.triangles.extend(
        cap.triangles
            .iter()
            .map(|t| [t[0] + offset, t[1] + offset, t[2] + offset]),
    );
    let cap_faces = cap.triangles.len();
    let cap_area = |p: &[[f64; 3]]| -> f64 {
        mesh.triangles[mesh.triangles.len() - cap_faces..]
            .iter()
            .map(|t| willow::geometry::operators::triangle_area(p[t[0]], p[t[1]], p[t[2]]))
            .sum()
    };
    let params = FlowParams {
        preserve: Preserve::Volume,
        ..FlowParams::default()
    };
    let mut flow = new_flow(&mesh, &params).expect("flow");
    assert!(
        (flow.initial_metrics().volume.expect("reported") - sphere_volume).abs()
            < 1e-12 * sphere_volume
    );
    let a0 = cap_area(&mesh.positions);
    for _ in 0..3 {
        let m = flow.step().expect("step");
        assert!(
            (m.volume.expect("reported") / sphere_volume - 1.0).abs() < 1e-6,
            "{}",
            m.volume.expect("reported")
        );
        assert!((cap_area(flow.positions()) / a0 - 1.0).abs() < 1e-9);
    }
}

/// Where keeping the volume cannot mean anything the flow says so instead of ignoring it.
#[test]
fn volume_is_refused_where_the_flow_never_rescales() {
    let params = FlowParams {
        method: Method::Taubin,
        preserve: Preserve::Volume,
        ..FlowParams::default()
    };
    // Taubin is known without the mesh: the parameters are invalid, naming the field.
    assert!(matches!(
        new_flow(&bumpy_sphere(2, 0.1), &params),
        Err(FlowError::InvalidParameter {
            name: "preserve",
            ..
        })
    ));
    // A fixed boundary needs a mesh with a boundary to mean anything.
    let fixed = FlowParams {
        boundary: willow::flow::Boundary::Fixed,
        preserve: Preserve::Volume,
        ..FlowParams::default()
    };
    assert!(matches!(
        new_flow(&bumpy_cap(2, 0.1), &fixed),
        Err(FlowError::Unsupported(_))
    ));
}

#[test]
fn preserve_reads_and_writes_snake_case() {
    let params: FlowParams = serde_json::from_str(r#"{"preserve": "volume"}"#).expect("parses");
    assert_eq!(params.preserve, Preserve::Volume);
    assert_eq!(FlowParams::default().preserve, Preserve::Area);
    let json = serde_json::to_value(FlowParams::default()).expect("serializes");
    assert_eq!(json["preserve"], "area");
    assert_eq!(Preserve::parse("NONE"), Ok(Preserve::None));
    assert!(Preserve::parse("mass").is_err());
}
