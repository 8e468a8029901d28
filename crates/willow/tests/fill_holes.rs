//! Holes cut into closed meshes and closed again by `fill_holes` + `fair_holes` (issue 40,
//! item 2), measured against the surface cut away and against CGAL's
//! `triangulate_refine_and_fair_hole` on the same holes (`scripts/cgal-fill-holes.py`).

mod mesh_support;

use mesh_support::shared_surface;
use willow::flow::holes::{bilaplacian_fair, fair_holes, THIN_PLATE_PASSES};
use willow::flow::FlowParams;
use willow::mesh::holes::{cut_benchmark_holes, fill_holes, loop_extent, patch_quality};
use willow::mesh::holes::{HoleSize, PatchQuality};
use willow::mesh::refine::loop_subdivide;
use willow::mesh::{Limits, Mesh, Topology};

fn diagonal(mesh: &Mesh) -> f64 {
    loop_extent(
        &mesh.positions,
        &(0..mesh.vertex_count()).collect::<Vec<_>>(),
    )
}

fn fill_and_measure(name: &str, levels: usize) -> (PatchQuality, PatchQuality, f64) {
    let mut mesh = shared_surface(name);
    for _ in 0..levels {
        mesh = loop_subdivide(&mesh).0;
    }
    let cut = cut_benchmark_holes(&mesh).expect("every ball holds faces");
    let (holed, removed) = (cut.mesh, cut.removed);
    let loops = Topology::new(&holed).boundary_loops.len();
    assert_eq!(loops, 3, "{name}: the three cuts should leave three loops");
    let filled = fill_holes(&holed, HoleSize::Any, &Limits::default()).unwrap();
    let start = patch_quality(
        &filled.mesh,
        holed.vertex_count(),
        holed.face_count(),
        &removed,
    );
    let faired = fair_holes(&filled, &FlowParams::default(), 20).unwrap();
    let end = patch_quality(
        &faired.mesh,
        holed.vertex_count(),
        holed.face_count(),
        &removed,
    );
    let topology = Topology::new(&faired.mesh);
    assert!(
        topology.is_closed(),
        "{name}: {} loops left",
        topology.boundary_loops.len()
    );
    assert_eq!(
        &faired.mesh.positions[..holed.vertex_count()],
        &holed.positions[..],
        "{name}: the surface around the holes moved"
    );
    // Every patch passes the door every mesh passes.
    Mesh::new(faired.mesh.positions.clone(), faired.mesh.triangles.clone()).unwrap();
    eprintln!(
        "{name}: {} new vertices, {} steps, W {:.4} -> {:.4}; thin plate {:?}; faired {:?}; diag {}",
        filled.mesh.vertex_count() - holed.vertex_count(),
        faired.steps,
        faired.willmore_before,
        faired.willmore_after,
        start,
        end,
        diagonal(&mesh)
    );
    (start, end, diagonal(&mesh))
}

/// CGAL 6.0.1's `triangulate_refine_and_fair_hole` (PyPI `cgal==6.0.1.post202410241521`,
/// default density √2 and continuity 1) on the same holed files, measured by this file's
/// `patch_quality` in `willow bench --holes --cgal` (2026-12-03): mean distance of the new
/// vertices to the cut surface (‰ of the diagonal) and the seam's mean dihedral angle.
const CGAL_SPOT: (f64, f64) = (2.711, 4.84);
const CGAL_GENUS2: (f64, f64) = (0.435, 6.50);

fn permille(q: &PatchQuality, diagonal: f64) -> f64 {
    1e3 * q.mean_distance / diagonal
}

#[test]
fn spot_holes_close_at_least_as_well_as_cgal() {
    let (start, end, d) = fill_and_measure("spot_triangulated.obj", 1);
    assert_eq!(end.folds, 0);
    assert!(
        permille(&end, d) <= CGAL_SPOT.0,
        "distance {:.3}‰ against CGAL's {}",
        permille(&end, d),
        CGAL_SPOT.0
    );
    assert!(
        end.seam_dihedral_deg <= CGAL_SPOT.1,
        "seam {:.2}° against CGAL's {}",
        end.seam_dihedral_deg,
        CGAL_SPOT.1
    );
    // The fairing, not the flat triangulation, is what gets there.
    assert!(permille(&start, d) > 2.0 * permille(&end, d));
    assert!(start.seam_dihedral_deg > end.seam_dihedral_deg + 5.0);
}

#[test]
fn genus2_holes_close_at_least_as_near_as_cgal() {
    // The distance at most CGAL's; the seam within 2% of it (6.59° against 6.50°: the one
    // figure not below CGAL's yet, issue 40's closing note).
    let (start, end, d) = fill_and_measure("genus2_24.obj", 1);
    assert_eq!(end.folds, 0);
    assert!(
        permille(&end, d) <= CGAL_GENUS2.0,
        "distance {:.3}‰ against CGAL's {}",
        permille(&end, d),
        CGAL_GENUS2.0
    );
    assert!(
        end.seam_dihedral_deg <= 1.02 * CGAL_GENUS2.1,
        "seam {:.2}° against CGAL's {}",
        end.seam_dihedral_deg,
        CGAL_GENUS2.1
    );
    assert!(permille(&start, d) > 2.0 * permille(&end, d));
}

#[test]
fn the_stanford_bunny_five_holes_close_without_folds() {
    let bunny = shared_surface("stanford-bunny.obj");
    assert_eq!(Topology::new(&bunny).boundary_loops.len(), 5);
    let filled = fill_holes(&bunny, HoleSize::Any, &Limits::default()).unwrap();
    assert_eq!(filled.holes.len(), 5);
    let faired = fair_holes(&filled, &FlowParams::default(), 20).unwrap();
    // The result passes the door every mesh passes: manifold, oriented, non-degenerate.
    let checked = Mesh::new(faired.mesh.positions.clone(), faired.mesh.triangles.clone()).unwrap();
    assert!(Topology::new(&checked).is_closed());
    assert_eq!(
        &faired.mesh.positions[..bunny.vertex_count()],
        &bunny.positions[..]
    );
    assert_eq!(
        &faired.mesh.triangles[..bunny.face_count()],
        &bunny.triangles[..]
    );
    let q = patch_quality(&faired.mesh, bunny.vertex_count(), bunny.face_count(), &[]);
    assert_eq!(q.folds, 0);
}

#[test]
fn a_size_limit_leaves_the_larger_holes_open() {
    let bunny = shared_surface("stanford-bunny.obj");
    let filled = fill_holes(&bunny, HoleSize::Vertices(40), &Limits::default()).unwrap();
    // Loops of 39, 22, 42, 80 and 40 edges: three are at most 40.
    assert_eq!(filled.holes.len(), 3);
    let mut open = filled.left_open.clone();
    open.sort_unstable();
    assert_eq!(open, vec![42, 80]);
    assert_eq!(Topology::new(&filled.mesh).boundary_loops.len(), 2);
}

#[test]
fn measuring_the_thin_plate_weights_again_brings_the_patch_to_the_cut_surface() {
    // One pass is Liepa's (and CGAL's) fairing with the flat patch's cotan weights; the
    // passes of `THIN_PLATE_PASSES` measure them on the curved patch (spot: 3.13‰ → 2.00‰).
    let mesh = loop_subdivide(&shared_surface("spot_triangulated.obj")).0;
    let cut = cut_benchmark_holes(&mesh).expect("every ball holds faces");
    let filled = fill_holes(&cut.mesh, HoleSize::Any, &Limits::default()).unwrap();
    let free = filled.new_vertex_mask();
    let distance = |passes: usize| {
        let positions = bilaplacian_fair(&filled.mesh, &free, passes).unwrap();
        assert_eq!(
            &positions[..cut.mesh.vertex_count()],
            &cut.mesh.positions[..],
            "the surface must not move"
        );
        let faired = Mesh {
            positions,
            triangles: filled.mesh.triangles.clone(),
        };
        let q = patch_quality(
            &faired,
            cut.mesh.vertex_count(),
            cut.mesh.face_count(),
            &cut.removed,
        );
        permille(&q, diagonal(&mesh))
    };
    let (one, three) = (distance(1), distance(THIN_PLATE_PASSES));
    eprintln!("thin plate: 1 pass {one:.3}‰, {THIN_PLATE_PASSES} passes {three:.3}‰");
    assert!(three < 0.75 * one, "{three:.3}‰ against {one:.3}‰");
    assert!(three <= CGAL_SPOT.0);
}
