//! Fairing a region: only the region moves (bit for bit), it fairs, and its seam holds.
//!
//! Every check here is computed in the test from positions and faces (face normals, areas,
//! the triangle's affine map), not from Willow's metrics, except W, which the flow reports.

mod components;
#[path = "../mesh_support/mod.rs"]
mod mesh_support;

use willow::flow::region::{resolve_groups, select, Region, Seam};
use willow::flow::stopping::{Event, Outcome as RunOutcome, Run};
use willow::flow::{new_flow, FlowError, FlowParams, Method};
use willow::mesh::generate::{bumpy_cap, pretzel, with_noise};
use willow::mesh::io::{Asset, Format, Limits};
use willow::mesh::Mesh;

/// Spot's right ear (found by rendering the mesh with this sphere marked).
const EAR: Region = Region::Sphere {
    center: [0.40, 0.72, -0.20],
    radius: 0.15,
};

fn spot() -> Asset {
    let bytes = include_bytes!("../data/spot_triangulated.obj");
    Asset::read(bytes, Format::Obj, &Limits::default()).expect("spot reads")
}

fn params(regions: Vec<Region>, seam: Seam) -> FlowParams {
    FlowParams {
        regions,
        seam,
        ..FlowParams::default()
    }
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn face_normal(p: &[[f64; 3]], t: [usize; 3]) -> [f64; 3] {
    let n = cross(sub(p[t[1]], p[t[0]]), sub(p[t[2]], p[t[0]]));
    let l = dot(n, n).sqrt();
    [n[0] / l, n[1] / l, n[2] / l]
}

/// The quasi-conformal distortion of the affine map from the input triangle to the current
/// one: the ratio of its singular values, from the two triangles' edge vectors in their own
/// planes.
fn face_q(input: &[[f64; 3]], now: &[[f64; 3]], t: [usize; 3]) -> f64 {
    let frame = |p: &[[f64; 3]]| {
        let e1 = sub(p[t[1]], p[t[0]]);
        let e2 = sub(p[t[2]], p[t[0]]);
        let l1 = dot(e1, e1).sqrt();
        let u = [e1[0] / l1, e1[1] / l1, e1[2] / l1];
        let n = cross(e1, e2);
        let w = cross(n, e1);
        let lw = dot(w, w).sqrt();
        let v = [w[0] / lw, w[1] / lw, w[2] / lw];
        // Columns: e1 and e2 in the triangle's own orthonormal frame.
        [[l1, dot(e2, u)], [0.0, dot(e2, v)]]
    };
    let a = frame(input);
    let b = frame(now);
    // M = B A⁻¹ (2×2), then its singular value ratio.
    let det_a = a[0][0] * a[1][1] - a[0][1] * a[1][0];
    let inv = [
        [a[1][1] / det_a, -a[0][1] / det_a],
        [-a[1][0] / det_a, a[0][0] / det_a],
    ];
    let m = [
        [
            b[0][0] * inv[0][0] + b[0][1] * inv[1][0],
            b[0][0] * inv[0][1] + b[0][1] * inv[1][1],
        ],
        [
            b[1][0] * inv[0][0] + b[1][1] * inv[1][0],
            b[1][0] * inv[0][1] + b[1][1] * inv[1][1],
        ],
    ];
    let fro2 = m[0][0].powi(2) + m[0][1].powi(2) + m[1][0].powi(2) + m[1][1].powi(2);
    let det = (m[0][0] * m[1][1] - m[0][1] * m[1][0]).abs();
    let disc = (fro2 * fro2 - 4.0 * det * det).max(0.0).sqrt();
    let s1 = ((fro2 + disc) / 2.0).sqrt();
    let s2 = ((fro2 - disc) / 2.0).max(0.0).sqrt();
    s1 / s2
}

/// Mean angle between the normals of the two faces of each edge on the region's border (one
/// face touching a moving vertex, the other not).
fn border_normal_jump(mesh: &Mesh, moving: &[bool], p: &[[f64; 3]]) -> f64 {
    use std::collections::HashMap;
    let mut edges: HashMap<(usize, usize), Vec<usize>> = HashMap::new();
    for (f, t) in mesh.triangles.iter().enumerate() {
        for c in 0..3 {
            let (a, b) = (t[c], t[(c + 1) % 3]);
            edges.entry((a.min(b), a.max(b))).or_default().push(f);
        }
    }
    let touches = |f: usize| mesh.triangles[f].iter().any(|&v| moving[v]);
    let (mut sum, mut count) = (0.0, 0usize);
    for faces in edges.values() {
        if let [f, g] = faces[..] {
            if touches(f) != touches(g) {
                let c = dot(
                    face_normal(p, mesh.triangles[f]),
                    face_normal(p, mesh.triangles[g]),
                );
                sum += c.clamp(-1.0, 1.0).acos();
                count += 1;
            }
        }
    }
    assert!(count > 0, "the region has no border");
    sum / count as f64
}

struct Outcome {
    w0: f64,
    w: f64,
    positions: Vec<[f64; 3]>,
}

fn run(mesh: &Mesh, params: &FlowParams, steps: usize) -> Outcome {
    let mut flow = new_flow(mesh, params).expect("region flow");
    let w0 = flow.initial_metrics().willmore_energy;
    let mut w = w0;
    for step in 0..steps {
        match flow.step() {
            Ok(m) => w = m.willmore_energy,
            // Converged: the flow keeps the last accepted surface.
            Err(FlowError::NoProgress { .. }) if step > 0 => break,
            Err(e) => panic!("step {step}: {e}"),
        }
    }
    Outcome {
        w0,
        w,
        positions: flow.positions().to_vec(),
    }
}

/// Area-weighted mean Q of `faces` (input areas) between the input and `p`.
fn area_weighted_q(mesh: &Mesh, faces: &[[usize; 3]], p: &[[f64; 3]]) -> f64 {
    let (mut sum, mut total) = (0.0, 0.0);
    for &t in faces {
        let n = cross(
            sub(mesh.positions[t[1]], mesh.positions[t[0]]),
            sub(mesh.positions[t[2]], mesh.positions[t[0]]),
        );
        let area = dot(n, n).sqrt() / 2.0;
        sum += area * face_q(&mesh.positions, p, t);
        total += area;
    }
    sum / total
}

/// What every region run must show: the outside bit-identical, W down, no fold, Q near 1
/// inside, and the seam's normal jump no worse than twice the input's.
fn check(name: &str, mesh: &Mesh, regions: &[Region], out: &Outcome, max_jump_ratio: f64) {
    check_with(name, mesh, regions, out, max_jump_ratio, 1.3);
}

/// [`check`] with a bound on the area-weighted mean Q of the region's faces; returns the
/// border's normal jump before and after.
fn check_with(
    name: &str,
    mesh: &Mesh,
    regions: &[Region],
    out: &Outcome,
    max_jump_ratio: f64,
    max_q_mean: f64,
) -> (f64, f64) {
    let moving = select(&mesh.positions, regions).expect("valid region");
    let mut moved = 0;
    for (v, (p, q)) in out.positions.iter().zip(&mesh.positions).enumerate() {
        if moving[v] {
            moved += usize::from(p != q);
        } else {
            assert_eq!(
                p.map(f64::to_bits),
                q.map(f64::to_bits),
                "{name}: vertex {v} outside moved"
            );
        }
    }
    assert!(moved > 0, "{name}: nothing moved");
    assert!(out.w < out.w0, "{name}: W {} -> {}", out.w0, out.w);
    let mut folds = 0;
    let (mut q_sum, mut area_sum, mut q_max) = (0.0, 0.0, 1.0f64);
    for &t in &mesh.triangles {
        if !t.iter().any(|&v| moving[v]) {
            continue;
        }
        let before = face_normal(&mesh.positions, t);
        if dot(before, face_normal(&out.positions, t)) < 0.0 {
            folds += 1;
        }
        let n = cross(
            sub(mesh.positions[t[1]], mesh.positions[t[0]]),
            sub(mesh.positions[t[2]], mesh.positions[t[0]]),
        );
        let area = dot(n, n).sqrt() / 2.0;
        let q = face_q(&mesh.positions, &out.positions, t);
        q_sum += q * area;
        area_sum += area;
        q_max = q_max.max(q);
    }
    let q_mean = q_sum / area_sum;
    let jump0 = border_normal_jump(mesh, &moving, &mesh.positions);
    let jump = border_normal_jump(mesh, &moving, &out.positions);
    eprintln!(
        "{name}: W {:.3} -> {:.3}, {moved} moved, folds {folds}, Q mean {q_mean:.3} max \
         {q_max:.3}, border normal jump {:.2}° -> {:.2}°",
        out.w0,
        out.w,
        jump0.to_degrees(),
        jump.to_degrees()
    );
    assert_eq!(folds, 0, "{name}: faces folded");
    assert!(q_mean <= max_q_mean, "{name}: Q mean {q_mean}");
    assert!(
        jump <= max_jump_ratio * jump0,
        "{name}: border normal jump {jump0} -> {jump}"
    );
    (jump0, jump)
}

/// The run as a job runs it: at most `steps`, ending early once W has stopped falling
/// (`until_converged`, the default). Returns the result and how the run ended.
fn run_until_converged(mesh: &Mesh, params: &FlowParams, steps: usize) -> (Outcome, RunOutcome) {
    let flow = new_flow(mesh, params).expect("region flow");
    let w0 = flow.initial_metrics().willmore_energy;
    let mut run = Run::new(flow, params, steps).expect("run");
    let (mut w, mut steps) = (w0, 0);
    let outcome = loop {
        match run.advance().expect("step") {
            Event::Step(m) => (w, steps) = (m.willmore_energy, m.step),
            Event::Stopped { outcome, .. } => {
                eprintln!("stopped after {steps} steps: {outcome:?}");
                break outcome;
            }
        }
    };
    let out = Outcome {
        w0,
        w,
        positions: run.flow().positions().to_vec(),
    };
    (out, outcome)
}

/// The largest angle between the normals of two adjacent faces touching the region: above
/// 90° the surface folds over itself there.
fn largest_dihedral(mesh: &Mesh, moving: &[bool], p: &[[f64; 3]]) -> f64 {
    use std::collections::HashMap;
    let mut edges: HashMap<(usize, usize), Vec<usize>> = HashMap::new();
    for (f, t) in mesh.triangles.iter().enumerate() {
        for c in 0..3 {
            let (a, b) = (t[c], t[(c + 1) % 3]);
            edges.entry((a.min(b), a.max(b))).or_default().push(f);
        }
    }
    let touches = |f: usize| mesh.triangles[f].iter().any(|&v| moving[v]);
    edges
        .values()
        .filter_map(|faces| match faces[..] {
            [f, g] if touches(f) || touches(g) => Some(
                dot(
                    face_normal(p, mesh.triangles[f]),
                    face_normal(p, mesh.triangles[g]),
                )
                .clamp(-1.0, 1.0)
                .acos(),
            ),
            _ => None,
        })
        .fold(0.0, f64::max)
}

/// Issue 29 item 1 at convergence: a smooth seam keeps the border's normal jump within twice
/// the input's when the flow runs on (20 steps with `until_converged`, then up to 150), on
/// spot's ear, a genus-2 rim and an open cap, and below the fixed seam's (C0) after 20 steps;
/// and the texture inside keeps its look (Q, the area-weighted mean over the region's faces,
/// ≤ 1.3 at 20 steps and ≤ 1.35 on the long run). Without the curvature target of
/// `flow/willmore/seam.rs` the smooth seam measured 2.16× on the ear at 20 steps (18.9°).
///
/// Q crept before the held border's unrealizable curvature change was absorbed
/// (`flow/willmore/pinned.rs`): at 20 steps ear 1.43, genus-2 1.39, cap 1.05; ear 1.54 when
/// it converged (48 steps), genus-2 1.72 at 150. Measured with it: at 20 steps ear 1.19,
/// genus-2 1.01, cap 1.02 (normal jump ear 8.71° → 8.73°, fixed seam 11.45°; genus-2 5.66° →
/// 5.07°, fixed 6.21°; cap 4.45° → 5.30°, fixed 6.01°); the ear converges after 105 steps
/// (Q 1.28, jump 8.97°), the genus-2 rim and the cap still descend at 150 (Q 1.02, 1.03; W
/// −31% and −17% from step 20): slower than before, whose faster descent was the
/// non-conformal creep. Folds on the long run are checked between neighbouring faces.
#[test]
fn a_smooth_seam_stays_tangent_to_its_surroundings_at_convergence() {
    let spot = spot().surface().clone();
    let pretzel = with_noise(pretzel(2, 24), 0.05, 7);
    let far = (0..pretzel.vertex_count())
        .max_by(|&a, &b| pretzel.positions[a][0].total_cmp(&pretzel.positions[b][0]))
        .expect("vertices");
    let rim = Region::Sphere {
        center: pretzel.positions[far],
        radius: 0.35,
    };
    let cap = with_noise(bumpy_cap(4, 0.06), 0.05, 11);
    let centre = Region::Box {
        min: [-0.4, -0.4, -2.0],
        max: [0.4, 0.4, 2.0],
    };
    for (name, mesh, region) in [
        ("spot ear", &spot, EAR),
        ("genus-2 rim", &pretzel, rim),
        ("bumpy cap centre", &cap, centre),
    ] {
        let regions = vec![region];
        let moving = select(&mesh.positions, &regions).expect("valid");
        let smooth = params(regions.clone(), Seam::Smooth);
        // 20 steps with `until_converged`, as a job runs them: every check of a region.
        let (out, _) = run_until_converged(mesh, &smooth, 20);
        // W has fallen well, not just a little: the inside is still faired.
        assert!(out.w < 0.8 * out.w0, "{name}: W {} -> {}", out.w0, out.w);
        let (jump0, jump) = check_with(
            &format!("{name}, smooth, 20 steps"),
            mesh,
            &regions,
            &out,
            2.0,
            1.3,
        );
        // Far longer: on the ear until W has stopped falling by the run's own rule (105
        // steps); the genus-2 rim and the cap still descend at 150, the seam held all the
        // way and Q with it.
        let (done, outcome) = run_until_converged(mesh, &smooth, 150);
        let moving_faces: Vec<[usize; 3]> = mesh
            .triangles
            .iter()
            .copied()
            .filter(|t| t.iter().any(|&v| moving[v]))
            .collect();
        let q_long = area_weighted_q(mesh, &moving_faces, &done.positions);
        eprintln!("{name}, smooth, long run: Q mean {q_long:.3} ({outcome:?})");
        assert!(q_long <= 1.35, "{name}: Q mean {q_long} on the long run");
        if name == "spot ear" {
            assert_eq!(outcome, RunOutcome::Converged, "{name}");
        }
        let jump_done = border_normal_jump(mesh, &moving, &done.positions);
        let fold = largest_dihedral(mesh, &moving, &done.positions);
        eprintln!(
            "{name}, smooth, long run ({outcome:?}): W {:.3} -> {:.3}, border normal jump \
             {:.2}° -> {:.2}°, largest dihedral {:.1}°",
            done.w0,
            done.w,
            jump0.to_degrees(),
            jump_done.to_degrees(),
            fold.to_degrees()
        );
        assert!(jump_done <= 2.0 * jump0, "{name}: {jump0} -> {jump_done}");
        assert!(
            fold < std::f64::consts::FRAC_PI_2,
            "{name}: folds ({fold} rad)"
        );
        // A fixed seam (C0) meets its border at a larger angle than the smooth one.
        let fixed = run(mesh, &params(regions.clone(), Seam::Fixed), 20);
        let crease = border_normal_jump(mesh, &moving, &fixed.positions);
        eprintln!(
            "{name}, fixed, 20 steps: border normal jump {:.2}°",
            crease.to_degrees()
        );
        assert!(
            crease > jump,
            "{name}: the fixed seam's jump {crease} should exceed the smooth seam's {jump}"
        );
    }
}

#[test]
fn spot_ear_fairs_alone_with_a_smooth_seam() {
    let asset = spot();
    let mesh = asset.surface().clone();
    let regions = vec![EAR];
    let out = run(&mesh, &params(regions.clone(), Seam::Smooth), 5);
    check("spot ear, smooth", &mesh, &regions, &out, 2.0);

    // The files keep every vertex outside the region exactly: the OBJ as written, and the GLB
    // at the f32 it stores.
    let moving = select(&mesh.positions, &regions).expect("valid");
    for format in [Format::Obj, Format::Glb] {
        let bytes = asset.write(&out.positions, format).expect("writes");
        let back = Asset::read(&bytes, format, &Limits::default()).expect("re-reads");
        let back = back.surface();
        assert_eq!(back.vertex_count(), mesh.vertex_count());
        for (v, (p, q)) in back.positions.iter().zip(&mesh.positions).enumerate() {
            if moving[v] {
                continue;
            }
            let same = match format {
                Format::Obj => p.map(f64::to_bits) == q.map(f64::to_bits),
                _ => p.map(|x| (x as f32).to_bits()) == q.map(|x| (x as f32).to_bits()),
            };
            assert!(
                same,
                "{format:?}: vertex {v} outside changed: {p:?} vs {q:?}"
            );
        }
    }
}

#[test]
fn a_fixed_seam_and_a_vertex_list_hold_the_outside_too() {
    let mesh = spot().surface().clone();
    let out = run(&mesh, &params(vec![EAR], Seam::Fixed), 5);
    // A fixed seam holds positions only: the surface may meet its border at an angle, but
    // on the ear it stays within twice the input's normal jump too (measured: 1.09×).
    check("spot ear, fixed", &mesh, &[EAR], &out, 2.0);

    // The same vertices named one by one flow the same, bit for bit.
    let moving = select(&mesh.positions, &[EAR]).expect("valid");
    let list = Region::Vertices((0..moving.len()).filter(|&v| moving[v]).collect());
    let by_list = run(&mesh, &params(vec![list], Seam::Fixed), 5);
    assert_eq!(by_list.positions, out.positions);
}

#[test]
fn a_region_of_a_genus_two_surface_and_of_an_open_one() {
    let mesh = with_noise(pretzel(2, 24), 0.05, 7);
    // A patch around the vertex farthest along +x: the outer rim of one handle.
    let far = (0..mesh.vertex_count())
        .max_by(|&a, &b| mesh.positions[a][0].total_cmp(&mesh.positions[b][0]))
        .expect("vertices");
    let region = Region::Sphere {
        center: mesh.positions[far],
        radius: 0.35,
    };
    let out = run(&mesh, &params(vec![region.clone()], Seam::Smooth), 4);
    check(
        "genus-2 rim, smooth",
        &mesh,
        std::slice::from_ref(&region),
        &out,
        2.0,
    );
    let out = run(&mesh, &params(vec![region.clone()], Seam::Fixed), 4);
    check("genus-2 rim, fixed", &mesh, &[region], &out, 2.0);

    let cap = with_noise(bumpy_cap(4, 0.06), 0.05, 11);
    let region = Region::Box {
        min: [-0.4, -0.4, -2.0],
        max: [0.4, 0.4, 2.0],
    };
    let out = run(&cap, &params(vec![region.clone()], Seam::Smooth), 4);
    check(
        "bumpy cap centre, smooth",
        &cap,
        std::slice::from_ref(&region),
        &out,
        2.0,
    );
    // The same vertices as a list, with a fixed seam.
    let moving = select(&cap.positions, &[region]).expect("valid");
    let list = Region::Vertices((0..moving.len()).filter(|&v| moving[v]).collect());
    let out = run(&cap, &params(vec![list.clone()], Seam::Fixed), 4);
    check(
        "bumpy cap centre, vertices, fixed",
        &cap,
        &[list],
        &out,
        2.0,
    );
}

#[test]
fn regions_that_cannot_be_faired_are_refused_by_name() {
    let mesh = spot().surface().clone();
    let refuse = |params: FlowParams, needle: &str| match new_flow(&mesh, &params) {
        Err(FlowError::InvalidParameter { name, reason }) => {
            assert_eq!(name, "region");
            assert!(reason.contains(needle), "{reason:?} lacks {needle:?}");
        }
        Err(other) => panic!("wrong error {other:?}"),
        Ok(_) => panic!("accepted ({needle})"),
    };
    let far_away = Region::Sphere {
        center: [100.0, 0.0, 0.0],
        radius: 0.1,
    };
    refuse(params(vec![far_away], Seam::Smooth), "no vertex");
    let everything = Region::Box {
        min: [-10.0; 3],
        max: [10.0; 3],
    };
    refuse(params(vec![everything], Seam::Smooth), "every vertex");
    refuse(
        params(vec![Region::Vertices(vec![1_000_000])], Seam::Smooth),
        "vertex 1000000",
    );
    refuse(
        FlowParams {
            method: Method::Mcf,
            ..params(vec![EAR], Seam::Smooth)
        },
        "conformal",
    );
    refuse(
        params(
            vec![Region::Sphere {
                center: [0.0; 3],
                radius: f64::INFINITY,
            }],
            Seam::Smooth,
        ),
        "radius",
    );
    // Issue 42: a flood of regions is refused on its count, before any is matched (matching
    // costs regions × vertices: 100k spheres would be 100k passes over spot's vertices).
    let many = vec![EAR; willow::flow::region::MAX_REGIONS + 1];
    refuse(
        params(many.clone(), Seam::Smooth),
        "at most 256 regions, got 257",
    );
    let flood = vec![EAR; 100_000];
    assert!(matches!(
        params(flood, Seam::Smooth).validate(),
        Err(FlowError::InvalidParameter { name: "region", .. })
    ));
    // At the cap, the union is matched as before.
    let at_cap = vec![EAR; willow::flow::region::MAX_REGIONS];
    assert!(new_flow(&mesh, &params(at_cap, Seam::Smooth)).is_ok());
}

/// Euclidean distance from each vertex to the nearest vertex outside the region (an
/// independent stand-in for the flow's distance along edges, which can only be longer).
fn distance_to_outside(mesh: &Mesh, moving: &[bool]) -> Vec<f64> {
    let outside: Vec<[f64; 3]> = mesh
        .positions
        .iter()
        .zip(moving)
        .filter(|(_, &m)| !m)
        .map(|(p, _)| *p)
        .collect();
    mesh.positions
        .iter()
        .map(|p| {
            outside
                .iter()
                .map(|q| dot(sub(*p, *q), sub(*p, *q)).sqrt())
                .fold(f64::INFINITY, f64::min)
        })
        .collect()
}

/// Mean displacement of the region's vertices within `near` of the outside, and of those
/// farther in.
fn displacement_near_and_far(mesh: &Mesh, moving: &[bool], out: &Outcome, near: f64) -> (f64, f64) {
    let distance = distance_to_outside(mesh, moving);
    let (mut a, mut na, mut b, mut nb) = (0.0, 0usize, 0.0, 0usize);
    for v in (0..mesh.vertex_count()).filter(|&v| moving[v]) {
        let d = sub(out.positions[v], mesh.positions[v]);
        let len = dot(d, d).sqrt();
        if distance[v] < near {
            a += len;
            na += 1;
        } else {
            b += len;
            nb += 1;
        }
    }
    assert!(na > 0 && nb > 0, "both bands hold vertices");
    (a / na as f64, b / nb as f64)
}

/// `falloff`: the motion fades toward the border. On spot's ear, the region's vertices near
/// its border move far less than without a falloff, those farther in still move, and every
/// check of a region holds (outside bit-identical, W down, no fold, Q, the seam); the same on
/// the genus-2 surface and the open cap.
#[test]
fn a_falloff_blends_the_motion_to_zero_at_the_border() {
    let mesh = spot().surface().clone();
    let moving = select(&mesh.positions, &[EAR]).expect("valid");
    let width = 0.08;
    let with = |falloff: Option<f64>| FlowParams {
        falloff,
        ..params(vec![EAR], Seam::Smooth)
    };
    let sharp = run(&mesh, &with(None), 5);
    let blended = run(&mesh, &with(Some(width)), 5);
    check("spot ear, falloff", &mesh, &[EAR], &blended, 2.0);
    let near = 0.3 * width;
    let (sharp_near, sharp_far) = displacement_near_and_far(&mesh, &moving, &sharp, near);
    let (blend_near, blend_far) = displacement_near_and_far(&mesh, &moving, &blended, near);
    eprintln!(
        "mean motion within {near} of the border: {sharp_near:.3e} → {blend_near:.3e}; \
         farther in {sharp_far:.3e} → {blend_far:.3e}"
    );
    // Within 0.3 of the width the smoothstep weight is at most 0.22 (less along edges).
    assert!(
        blend_near < 0.5 * sharp_near,
        "{blend_near} vs {sharp_near}"
    );
    assert!(blend_far > 0.2 * sharp_far, "{blend_far} vs {sharp_far}");

    let pretzel_mesh = with_noise(pretzel(2, 24), 0.05, 7);
    let far = (0..pretzel_mesh.vertex_count())
        .max_by(|&a, &b| pretzel_mesh.positions[a][0].total_cmp(&pretzel_mesh.positions[b][0]))
        .expect("vertices");
    let region = Region::Sphere {
        center: pretzel_mesh.positions[far],
        radius: 0.35,
    };
    let p = FlowParams {
        falloff: Some(0.1),
        ..params(vec![region.clone()], Seam::Smooth)
    };
    let out = run(&pretzel_mesh, &p, 4);
    check("genus-2 rim, falloff", &pretzel_mesh, &[region], &out, 2.0);

    let cap = with_noise(bumpy_cap(4, 0.06), 0.05, 11);
    let region = Region::Box {
        min: [-0.4, -0.4, -2.0],
        max: [0.4, 0.4, 2.0],
    };
    let p = FlowParams {
        falloff: Some(0.1),
        ..params(vec![region.clone()], Seam::Fixed)
    };
    let out = run(&cap, &p, 4);
    check(
        "bumpy cap centre, fixed, falloff",
        &cap,
        &[region],
        &out,
        3.0,
    );

    // A falloff needs a region, and a positive finite width.
    for (falloff, regions) in [(0.0, vec![EAR]), (f64::NAN, vec![EAR]), (0.1, vec![])] {
        let p = FlowParams {
            falloff: Some(falloff),
            ..params(regions, Seam::Smooth)
        };
        match new_flow(&mesh, &p) {
            Err(FlowError::InvalidParameter { name, .. }) => assert_eq!(name, "falloff"),
            other => panic!("falloff {falloff}: {:?}", other.err()),
        }
    }
}

/// spot with its faces in two OBJ groups: `g ear` before the faces with every corner in the
/// ear sphere, `g body` before the rest (and an `o spot` line first).
fn spot_with_groups() -> String {
    let text = include_str!("../data/spot_triangulated.obj");
    let mut v: Vec<[f64; 3]> = Vec::new();
    let (mut ear, mut body) = (String::new(), String::new());
    let (c, r) = ([0.40, 0.72, -0.20], 0.15);
    let mut head = String::from("o spot\n");
    for line in text.lines() {
        if let Some(rest) = line.strip_prefix("v ") {
            let p: Vec<f64> = rest
                .split_whitespace()
                .filter_map(|t| t.parse().ok())
                .collect();
            v.push([p[0], p[1], p[2]]);
            head += line;
            head += "\n";
        } else if let Some(rest) = line.strip_prefix("f ") {
            let inside = rest.split_whitespace().all(|w| {
                let k: usize = w
                    .split('/')
                    .next()
                    .and_then(|i| i.parse().ok())
                    .unwrap_or(0);
                let p = v[k - 1];
                (0..3).map(|a| (p[a] - c[a]).powi(2)).sum::<f64>() <= r * r
            });
            let target = if inside { &mut ear } else { &mut body };
            *target += line;
            *target += "\n";
        } else {
            head += line;
            head += "\n";
        }
    }
    format!("{head}g ear\n{ear}g body\n{body}")
}

/// `{"group": "ear"}`: the OBJ group's faces are the region. Everything a region must show
/// holds (outside bit-identical, W down, no fold, Q, the seam); an unknown group is refused
/// naming it and listing the file's groups; glTF node and mesh names are groups too.
#[test]
fn a_named_group_of_the_file_is_a_region() {
    let text = spot_with_groups();
    let asset = Asset::read(text.as_bytes(), Format::Obj, &Limits::default()).expect("reads");
    assert_eq!(asset.group_names(), vec!["spot", "ear", "body"]);
    let mesh = asset.surface().clone();
    let regions = resolve_groups(&[Region::Group("ear".into())], &asset).expect("the group exists");
    let Region::Vertices(list) = &regions[0] else {
        panic!("a group resolves to vertices: {regions:?}");
    };
    // The group's vertices are the corners of the faces under `g ear`, counted here from the
    // text: every vertex within the ear sphere that a face wholly inside it uses.
    let in_ear = |p: &[f64; 3]| {
        let c = [0.40, 0.72, -0.20];
        (0..3).map(|a| (p[a] - c[a]).powi(2)).sum::<f64>() <= 0.15 * 0.15
    };
    assert!(list.iter().all(|&v| in_ear(&mesh.positions[v])));
    assert!(list.len() > 20, "{} vertices", list.len());
    for seam in [Seam::Smooth, Seam::Fixed] {
        let out = run(&mesh, &params(regions.clone(), seam), 5);
        check(
            &format!("spot ear group, {seam:?}"),
            &mesh,
            &regions,
            &out,
            3.0,
        );
    }

    let err = resolve_groups(&[Region::Group("tail".into())], &asset).expect_err("unknown");
    assert!(err.contains("`tail`") && err.contains("`ear`"), "{err}");
    // An unresolved group cannot select vertices: a flow built on it is refused by name.
    match new_flow(
        &mesh,
        &params(vec![Region::Group("ear".into())], Seam::Smooth),
    ) {
        Err(FlowError::InvalidParameter { name, reason }) => {
            assert_eq!(name, "region");
            assert!(reason.contains("ear"), "{reason}");
        }
        other => panic!("{:?}", other.err()),
    }

    let (mut json, bin, _, _) = mesh_support::textured_cube_gltf();
    json["meshes"][0]["name"] = serde_json::json!("box");
    let glb = mesh_support::glb_bytes(&json, &bin);
    let cube = Asset::read(&glb, Format::Glb, &Limits::default()).expect("cube reads");
    assert_eq!(cube.group_names(), vec!["child", "box"]);
    let all: Vec<usize> = (0..cube.surface().vertex_count()).collect();
    assert_eq!(cube.group_vertices("child"), Some(all.clone()));
    assert_eq!(cube.group_vertices("box"), Some(all));
    assert_eq!(
        cube.group_vertices("parent"),
        None,
        "a node without a mesh has no faces"
    );
}
