//! Fairing a part of a surface: the region moves, everything else stays exactly where it was.
//!
//! A region is a set of vertices (a sphere, a box, a list, a named group of the file's faces,
//! or several of them together). The
//! flow runs on the *submesh* around it, with the surrounding vertices held by the Dirichlet
//! conditions of a fixed boundary (§6.3.2: λ = 1 and the input position there), so a step
//! costs what the region costs, not what the whole mesh does. The seam decides how many rings
//! of the surroundings are held:
//! - [`Seam::Fixed`]: one ring, the vertices adjacent to the region: the border stays where it
//!   was (C0); the surface may meet it at an angle.
//! - [`Seam::Smooth`]: two rings: the held ring next to the region and the one beyond it fix the
//!   border's positions *and* its tangent planes, the discrete form of holding the boundary
//!   vectors at the surrounding surface's frame (§6.3.1); and the flow drives the region's
//!   mean curvature toward the harmonic extension of the held rings' (`flow/willmore/seam.rs`),
//!   whose fixed points (`ΔH = 0`, linearized Willmore) take both as boundary data, so the
//!   faired surface leaves the border tangent to the surface around it (G1 up to the mesh's
//!   resolution; without it the region converges to a minimal surface meeting the border at
//!   an angle).
//!
//! With a `falloff` width (`FlowParams::falloff`) each step's motion is weighted by a
//! smoothstep of the distance from the border along the mesh's edges ([`falloff_weights`]):
//! the region fades into its surroundings instead of moving up to the held ring.
//!
//! A region may hold every vertex of a closed component of a mesh with several: that
//! component has no border to hold, and flows as the whole-surface flow would flow it alone
//! (its constraints and scale policy; `flow/willmore/pinned.rs`). Every vertex of the whole
//! mesh is refused (leave the region out instead).
//!
//! Vertices outside the region are never written: they are bit-identical to the input. The
//! metrics a region flow reports are those of the submesh (the region and its held rings).

use super::safeguard::Safeguarded;
use super::willmore::ConformalFlow;
use super::{Boundary, Flow, FlowError, FlowParams, FlowState, Method, StepProfile};
use crate::mesh::io::Asset;
use crate::mesh::Mesh;
use crate::metrics::StepMetrics;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;

/// Most regions one flow may name. Matching costs regions × vertices (every sphere and box
/// tests every vertex): 400k spheres on a 50k-vertex mesh took 22 s of a request's CPU
/// (issue 42). 256 is far more than a person picks by hand or a pipeline sends (a union of
/// a few shapes, or one vertex list), and bounds the matching at 256 passes over the
/// vertices: half a second at the 2M-vertex limit.
pub const MAX_REGIONS: usize = 256;

/// One way to name vertices of the mesh, in its own units and numbering.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum Region {
    /// Every vertex within `radius` of `center` (the boundary included).
    Sphere { center: [f64; 3], radius: f64 },
    /// Every vertex with `min ≤ p ≤ max` in each coordinate.
    Box { min: [f64; 3], max: [f64; 3] },
    /// These vertices (indices into the mesh's vertices).
    Vertices(Vec<usize>),
    /// The vertices of a named group of the file's faces: an OBJ `g` or `o` name, a glTF
    /// node or mesh name. Only a file knows its groups: [`resolve_groups`] turns this into
    /// [`Region::Vertices`] against the [`Asset`] before a flow is built.
    Group(String),
}

/// How the region meets the surface around it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Seam {
    /// The border's positions stay (C0).
    Fixed,
    /// The border's positions and tangent planes stay (G1).
    #[default]
    Smooth,
}

impl Seam {
    /// `fixed` or `smooth`, any case: the one text form, for the CLI and the query string.
    pub fn parse(name: &str) -> Result<Seam, String> {
        match name.to_ascii_lowercase().as_str() {
            "fixed" => Ok(Seam::Fixed),
            "smooth" => Ok(Seam::Smooth),
            _ => Err(format!("expected `fixed` or `smooth`, got `{name}`")),
        }
    }

    /// Rings of the surroundings held by Dirichlet conditions.
    pub const fn held_rings(self) -> usize {
        match self {
            Seam::Fixed => 1,
            Seam::Smooth => 2,
        }
    }
}

super::deserialize_by_parse!(Seam);

/// Exactly `N` comma-separated numbers.
fn numbers<const N: usize>(text: &str, what: &str) -> Result<[f64; N], String> {
    let values = text
        .split(',')
        .map(|t| {
            t.trim()
                .parse::<f64>()
                .map_err(|_| format!("`{}` is not a number", t.trim()))
        })
        .collect::<Result<Vec<f64>, String>>()?;
    let count = values.len();
    values
        .try_into()
        .map_err(|_| format!("expected {N} numbers {what}, got {count}"))
}

impl Region {
    /// The text form of a sphere, `x,y,z,r` (the CLI's `--region-sphere`, the query's
    /// `region.sphere`).
    pub fn parse_sphere(text: &str) -> Result<Region, String> {
        let v = numbers::<4>(text, "x,y,z,r")?;
        Ok(Region::Sphere {
            center: [v[0], v[1], v[2]],
            radius: v[3],
        })
    }

    /// The text form of a box, `xmin,ymin,zmin,xmax,ymax,zmax`.
    pub fn parse_box(text: &str) -> Result<Region, String> {
        let v = numbers::<6>(text, "xmin,ymin,zmin,xmax,ymax,zmax")?;
        Ok(Region::Box {
            min: [v[0], v[1], v[2]],
            max: [v[3], v[4], v[5]],
        })
    }

    /// The text form of a vertex list: numbers separated by commas or white space.
    pub fn parse_vertices(text: &str) -> Result<Region, String> {
        text.split(|c: char| c == ',' || c.is_whitespace())
            .filter(|t| !t.is_empty())
            .map(|t| {
                t.parse::<usize>()
                    .map_err(|_| format!("`{t}` is not a vertex number"))
            })
            .collect::<Result<Vec<usize>, String>>()
            .map(Region::Vertices)
    }

    /// The checks that need no mesh: finite numbers, a positive radius, an ordered box.
    pub fn validate(&self) -> Result<(), String> {
        let finite = |p: &[f64; 3]| p.iter().all(|x| x.is_finite());
        match self {
            Region::Sphere { center, radius } => {
                if !finite(center) {
                    return Err(format!("sphere center must be finite, got {center:?}"));
                }
                if !(radius.is_finite() && *radius > 0.0) {
                    return Err(format!(
                        "sphere radius must be a finite number > 0, got {radius}"
                    ));
                }
            }
            Region::Box { min, max } => {
                if !(finite(min) && finite(max)) {
                    return Err(format!("box corners must be finite, got {min:?}, {max:?}"));
                }
                if (0..3).any(|a| min[a] > max[a]) {
                    return Err(format!("box min must not exceed max, got {min:?}, {max:?}"));
                }
            }
            Region::Vertices(list) => {
                if list.is_empty() {
                    return Err("the vertex list is empty".into());
                }
            }
            Region::Group(name) => {
                if name.trim().is_empty() {
                    return Err("the group name is empty".into());
                }
            }
        }
        Ok(())
    }

    /// Marks the vertices this region names in `selected`; an index past the mesh is an error.
    pub fn select_into(&self, positions: &[[f64; 3]], selected: &mut [bool]) -> Result<(), String> {
        match self {
            Region::Sphere { center, radius } => {
                for (s, p) in selected.iter_mut().zip(positions) {
                    let d2 = (0..3).map(|a| (p[a] - center[a]).powi(2)).sum::<f64>();
                    *s |= d2 <= radius * radius;
                }
            }
            Region::Box { min, max } => {
                for (s, p) in selected.iter_mut().zip(positions) {
                    *s |= (0..3).all(|a| min[a] <= p[a] && p[a] <= max[a]);
                }
            }
            Region::Vertices(list) => {
                for &v in list {
                    let s = selected.get_mut(v).ok_or_else(|| {
                        format!(
                            "vertex {v} is outside the mesh ({} vertices)",
                            positions.len()
                        )
                    })?;
                    *s = true;
                }
            }
            Region::Group(name) => {
                return Err(format!(
                    "group `{name}` must be looked up in its file first (region::resolve_groups)"
                ))
            }
        }
        Ok(())
    }
}

/// `regions` with every [`Region::Group`] replaced by the surface vertices of its faces in
/// `asset` ([`Asset::group_vertices`]; the other regions as they are). The vertices are in
/// the surface's numbering, so this comes after any renumbering of file vertex lists. An
/// unknown group is an error that names it and the groups the file has.
pub fn resolve_groups(regions: &[Region], asset: &Asset) -> Result<Vec<Region>, String> {
    regions
        .iter()
        .map(|r| match r {
            Region::Group(name) => {
                asset
                    .group_vertices(name)
                    .map(Region::Vertices)
                    .ok_or_else(|| {
                        let names = asset.group_names();
                        if names.is_empty() {
                            format!("unknown group `{name}`: the file names no groups")
                        } else {
                            let list: Vec<String> =
                                names.iter().map(|n| format!("`{n}`")).collect();
                            format!(
                                "unknown group `{name}`: the file's groups are {}",
                                list.join(", ")
                            )
                        }
                    })
            }
            other => Ok(other.clone()),
        })
        .collect()
}

/// The vertices the union of `regions` names.
pub fn select(positions: &[[f64; 3]], regions: &[Region]) -> Result<Vec<bool>, String> {
    let mut selected = vec![false; positions.len()];
    for r in regions {
        r.select_into(positions, &mut selected)?;
    }
    Ok(selected)
}

/// The part of a mesh a region flows on.
#[derive(Clone, Debug)]
pub struct Submesh {
    /// The faces around the region, on their own vertices.
    pub mesh: Mesh,
    /// The full mesh's vertex of each submesh vertex.
    pub to_full: Vec<usize>,
    /// Submesh vertices held by Dirichlet conditions: every one outside the region.
    pub held: Vec<bool>,
}

/// The faces touching the region grown by `rings − 1` rings, and the stars of any vertex where
/// those faces would pinch (meet in two fans): the submesh must be a manifold surface.
pub fn submesh(mesh: &Mesh, moving: &[bool], rings: usize) -> Submesh {
    let n = mesh.vertex_count();
    let mut grown = moving.to_vec();
    for _ in 1..rings {
        let mut next = grown.clone();
        for t in &mesh.triangles {
            if t.iter().any(|&v| grown[v]) {
                for &v in t {
                    next[v] = true;
                }
            }
        }
        grown = next;
    }
    let mut in_sub: Vec<bool> = mesh
        .triangles
        .iter()
        .map(|t| t.iter().any(|&v| grown[v]))
        .collect();
    // Vertex → faces, to add a whole star where the submesh pinches.
    let mut star_ptr = vec![0usize; n + 1];
    for t in &mesh.triangles {
        for &v in t {
            star_ptr[v + 1] += 1;
        }
    }
    for v in 0..n {
        star_ptr[v + 1] += star_ptr[v];
    }
    let mut star = vec![0usize; star_ptr[n]];
    let mut fill = star_ptr.clone();
    for (f, t) in mesh.triangles.iter().enumerate() {
        for &v in t {
            star[fill[v]] = f;
            fill[v] += 1;
        }
    }
    loop {
        let pinched = pinched_vertices(mesh, &in_sub);
        if pinched.is_empty() {
            break;
        }
        for v in pinched {
            for &f in &star[star_ptr[v]..star_ptr[v + 1]] {
                in_sub[f] = true;
            }
        }
    }
    let mut local = vec![usize::MAX; n];
    let mut to_full = Vec::new();
    let mut triangles = Vec::new();
    for (t, _) in mesh.triangles.iter().zip(&in_sub).filter(|(_, &s)| s) {
        triangles.push(t.map(|v| {
            if local[v] == usize::MAX {
                local[v] = to_full.len();
                to_full.push(v);
            }
            local[v]
        }));
    }
    let positions = to_full.iter().map(|&v| mesh.positions[v]).collect();
    let held = to_full.iter().map(|&v| !moving[v]).collect();
    Submesh {
        mesh: Mesh {
            positions,
            triangles,
        },
        to_full,
        held,
    }
}

/// The weight of each vertex's motion under a falloff of `width` (model units): the
/// smoothstep `t²(3 − 2t)` of `t = min(d / width, 1)`, with `d` the distance from the nearest
/// `held` vertex along the mesh's edges (Dijkstra on the input surface, so a thin part does
/// not take its distance across the gap). Held vertices get 0, vertices `width` or more
/// inside the region 1; the slope is zero at both ends, so a smooth seam stays smooth.
pub fn falloff_weights(mesh: &Mesh, held: &[bool], width: f64) -> Vec<f64> {
    use std::cmp::Reverse;
    use std::collections::BinaryHeap;
    let n = mesh.vertex_count();
    let mut neighbours: Vec<Vec<usize>> = vec![Vec::new(); n];
    for t in &mesh.triangles {
        for c in 0..3 {
            let (a, b) = (t[c], t[(c + 1) % 3]);
            neighbours[a].push(b);
            neighbours[b].push(a);
        }
    }
    // Distances are non-negative finite floats: their bit patterns order as the values do.
    let mut distance = vec![f64::INFINITY; n];
    let mut queue = BinaryHeap::new();
    for (v, _) in held.iter().enumerate().filter(|(_, &h)| h) {
        distance[v] = 0.0;
        queue.push(Reverse((0u64, v)));
    }
    while let Some(Reverse((bits, v))) = queue.pop() {
        let d = f64::from_bits(bits);
        if d > distance[v] {
            continue;
        }
        for &u in &neighbours[v] {
            let p = mesh.positions[v];
            let q = mesh.positions[u];
            let edge =
                ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt();
            let next = d + edge;
            if next < distance[u] {
                distance[u] = next;
                queue.push(Reverse((next.to_bits(), u)));
            }
        }
    }
    distance
        .iter()
        .map(|&d| {
            let t = (d / width).min(1.0);
            t * t * (3.0 - 2.0 * t)
        })
        .collect()
}

/// Vertices where the faces marked `in_sub` meet in more than one fan: more than two of their
/// edges are boundary edges of the marked set.
fn pinched_vertices(mesh: &Mesh, in_sub: &[bool]) -> Vec<usize> {
    let mut edge_faces: HashMap<(usize, usize), u32> = HashMap::new();
    for (t, _) in mesh.triangles.iter().zip(in_sub).filter(|(_, &s)| s) {
        for c in 0..3 {
            let (a, b) = (t[c], t[(c + 1) % 3]);
            *edge_faces.entry((a.min(b), a.max(b))).or_default() += 1;
        }
    }
    let mut boundary_edges: HashMap<usize, u32> = HashMap::new();
    for (&(a, b), &count) in &edge_faces {
        if count == 1 {
            *boundary_edges.entry(a).or_default() += 1;
            *boundary_edges.entry(b).or_default() += 1;
        }
    }
    let mut pinched: Vec<usize> = boundary_edges
        .into_iter()
        .filter(|&(_, count)| count > 2)
        .map(|(v, _)| v)
        .collect();
    pinched.sort_unstable();
    pinched
}

/// The conformal flow of a region: its submesh flows with the surroundings held, and the
/// region's vertices are written back into the whole surface after each step.
pub struct RegionFlow {
    inner: Box<dyn Flow>,
    to_full: Vec<usize>,
    /// Submesh vertices inside the region: the only ones ever written back.
    moving: Vec<usize>,
    positions: Vec<[f64; 3]>,
    /// The crease edges held ([`super::creases`]), as vertex pairs of the whole mesh.
    creases: Vec<[usize; 2]>,
}

impl RegionFlow {
    pub fn new(mesh: &Mesh, params: &FlowParams) -> Result<Self, FlowError> {
        params.validate()?;
        let invalid = |reason: String| FlowError::InvalidParameter {
            name: "region",
            reason,
        };
        if params.method != Method::Conformal {
            return Err(invalid(format!(
                "a region is faired by the conformal flow only, not by `{}`",
                params.method.name()
            )));
        }
        let selected = select(&mesh.positions, &params.regions).map_err(invalid)?;
        let count = selected.iter().filter(|&&s| s).count();
        if count == 0 {
            return Err(invalid("the region selects no vertex of the mesh".into()));
        }
        if count == selected.len() {
            return Err(invalid(
                "the region selects every vertex: leave it out to fair the whole surface".into(),
            ));
        }
        Self::with_moving(mesh, params, &selected)
    }

    /// The flow of the vertices marked `moving` (a region's selection, less the creases it
    /// holds), everything else held as the seam says.
    pub fn with_moving(
        mesh: &Mesh,
        params: &FlowParams,
        moving: &[bool],
    ) -> Result<Self, FlowError> {
        let selected = moving;
        let sub = submesh(mesh, selected, params.seam.held_rings());
        let inner_params = FlowParams {
            regions: Vec::new(),
            // The falloff reaches the inner flow as its weights (`blend` below).
            falloff: None,
            boundary: Boundary::Fixed,
            ..params.clone()
        };
        let blend = params
            .falloff
            .map(|width| falloff_weights(&sub.mesh, &sub.held, width));
        let mut flow =
            ConformalFlow::with_pinned(&sub.mesh, &inner_params, sub.held.clone(), blend)?;
        if params.seam == Seam::Smooth {
            flow.continue_pinned_curvature()?;
        }
        // The part of ρ the held border forbids would only distort the region
        // (`flow/willmore/pinned.rs`). Not under a feature scale: its filter already keeps
        // the low frequencies a held border cannot realize out of ρ (docs/algorithm.md §11),
        // and absorbing on top of it fought the filter's stopping rule (a bumpy ellipsoid's
        // box region: Q max 1.9 and no `feature_scale_reached` in 40 steps, against Q max
        // < 1.5 and the scale reached without absorbing; `flow_feature`).
        if params.feature_size.is_none() {
            flow.absorb_unrealizable_curvature()?;
        }
        let inner: Box<dyn Flow> = Box::new(Safeguarded::new(
            flow,
            &sub.mesh.triangles,
            params.safeguard,
        ));
        let moving = (0..sub.to_full.len()).filter(|&s| !sub.held[s]).collect();
        Ok(RegionFlow {
            inner,
            to_full: sub.to_full,
            moving,
            positions: mesh.positions.clone(),
            creases: Vec::new(),
        })
    }

    /// Records the crease edges this flow holds, for [`Flow::creases`].
    pub fn set_creases(&mut self, creases: Vec<[usize; 2]>) {
        self.creases = creases;
    }

    fn write_back(&mut self) {
        let sub = self.inner.positions();
        for &s in &self.moving {
            self.positions[self.to_full[s]] = sub[s];
        }
    }
}

impl Flow for RegionFlow {
    fn step(&mut self) -> Result<StepMetrics, FlowError> {
        let metrics = self.inner.step()?;
        self.write_back();
        Ok(super::creases::with_crease_count(metrics, &self.creases))
    }

    fn positions(&self) -> &[[f64; 3]] {
        &self.positions
    }

    fn initial_metrics(&self) -> StepMetrics {
        super::creases::with_crease_count(self.inner.initial_metrics(), &self.creases)
    }

    fn profile(&self) -> Option<&StepProfile> {
        self.inner.profile()
    }

    fn setup_profile(&self) -> Option<&StepProfile> {
        self.inner.setup_profile()
    }

    fn feature_detail(&self) -> Option<super::feature::FeatureDetail> {
        self.inner.feature_detail()
    }

    fn kept_share(&self) -> Option<f64> {
        self.inner.kept_share()
    }

    fn last_refusal(&self) -> Option<String> {
        self.inner.last_refusal()
    }

    fn creases(&self) -> &[[usize; 2]] {
        &self.creases
    }

    /// The whole surface's positions (so a resumed job writes the whole file), with the inner
    /// flow's metrics and step-size control.
    fn checkpoint(&self) -> Option<FlowState> {
        self.inner.checkpoint().map(|state| FlowState {
            positions: self.positions.clone(),
            ..state
        })
    }

    fn resume(&mut self, state: &FlowState) -> Result<(), FlowError> {
        if state.positions.len() != self.positions.len() {
            return Err(FlowError::InvalidParameter {
                name: "checkpoint",
                reason: format!(
                    "holds {} vertices, the mesh has {}",
                    state.positions.len(),
                    self.positions.len()
                ),
            });
        }
        let sub_state = FlowState {
            positions: self.to_full.iter().map(|&v| state.positions[v]).collect(),
            ..state.clone()
        };
        self.inner.resume(&sub_state)?;
        self.write_back();
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::generate::icosphere;
    use crate::mesh::Topology;

    #[test]
    fn a_sphere_region_selects_what_lies_within_its_radius() {
        let mesh = icosphere(2);
        let regions = [Region::Sphere {
            center: [0.0, 0.0, 1.0],
            radius: 0.5,
        }];
        let selected = select(&mesh.positions, &regions).expect("valid");
        for (p, &s) in mesh.positions.iter().zip(&selected) {
            let d = (p[0].powi(2) + p[1].powi(2) + (p[2] - 1.0).powi(2)).sqrt();
            assert_eq!(s, d <= 0.5, "{p:?} at {d}");
        }
        assert!(selected.iter().any(|&s| s));
    }

    #[test]
    fn regions_add_up_and_bad_indices_are_named() {
        let mesh = icosphere(1);
        let both = select(
            &mesh.positions,
            &[
                Region::Vertices(vec![0, 1]),
                Region::Box {
                    min: [-2.0, -2.0, 0.9],
                    max: [2.0, 2.0, 2.0],
                },
            ],
        )
        .expect("valid");
        assert!(both[0] && both[1]);
        let err = select(&mesh.positions, &[Region::Vertices(vec![10_000])]).unwrap_err();
        assert!(err.contains("vertex 10000"), "{err}");
    }

    #[test]
    fn the_submesh_is_a_disk_with_its_held_rings_outside_the_region() {
        let mesh = icosphere(3);
        let selected = select(
            &mesh.positions,
            &[Region::Sphere {
                center: [0.0, 0.0, 1.0],
                radius: 0.4,
            }],
        )
        .expect("valid");
        for seam in [Seam::Fixed, Seam::Smooth] {
            let sub = submesh(&mesh, &selected, seam.held_rings());
            let topology = Topology::new(&sub.mesh);
            assert_eq!(topology.boundary_loops.len(), 1, "{seam:?}");
            assert_eq!(topology.genus(), 0);
            // Every boundary vertex is held, and every region vertex is free.
            for v in topology
                .boundary_vertex_mask(sub.to_full.len())
                .iter()
                .enumerate()
            {
                if *v.1 {
                    assert!(sub.held[v.0], "{seam:?}: free boundary vertex");
                }
            }
            for (s, &full) in sub.to_full.iter().enumerate() {
                assert_eq!(sub.held[s], !selected[full]);
                assert_eq!(sub.mesh.positions[s], mesh.positions[full]);
            }
            let moving = selected.iter().filter(|&&s| s).count();
            assert_eq!(sub.held.iter().filter(|&&h| !h).count(), moving);
            let rings = sub.held.iter().filter(|&&h| h).count();
            assert!(rings > 0 && sub.to_full.len() < mesh.vertex_count());
        }
        let fixed = submesh(&mesh, &selected, 1).to_full.len();
        let smooth = submesh(&mesh, &selected, 2).to_full.len();
        assert!(smooth > fixed, "two held rings hold more than one");
    }

    #[test]
    fn text_forms_parse_and_name_what_is_wrong() {
        assert_eq!(
            Region::parse_sphere("1, 2,3,0.5"),
            Ok(Region::Sphere {
                center: [1.0, 2.0, 3.0],
                radius: 0.5
            })
        );
        assert_eq!(
            Region::parse_box("0,0,0,1,2,3"),
            Ok(Region::Box {
                min: [0.0; 3],
                max: [1.0, 2.0, 3.0]
            })
        );
        assert_eq!(
            Region::parse_vertices("3, 4\n5 6"),
            Ok(Region::Vertices(vec![3, 4, 5, 6]))
        );
        assert_eq!(Seam::parse("FIXED"), Ok(Seam::Fixed));
        let err = |r: Result<Region, String>| r.expect_err("refused");
        assert!(err(Region::parse_sphere("1,2,3")).contains("expected 4 numbers"));
        assert!(err(Region::parse_box("0,0,0,1,1,x")).contains("`x`"));
        assert!(err(Region::parse_vertices("1,-2")).contains("`-2`"));
        assert!(Seam::parse("wavy").is_err());
    }

    #[test]
    fn bad_regions_are_refused_with_the_reason() {
        let cases = [
            (
                Region::Sphere {
                    center: [0.0, f64::NAN, 0.0],
                    radius: 1.0,
                },
                "finite",
            ),
            (
                Region::Sphere {
                    center: [0.0; 3],
                    radius: 0.0,
                },
                "radius",
            ),
            (
                Region::Box {
                    min: [1.0, 0.0, 0.0],
                    max: [0.0, 1.0, 1.0],
                },
                "min",
            ),
            (Region::Vertices(vec![]), "empty"),
        ];
        for (region, needle) in cases {
            let err = region.validate().unwrap_err();
            assert!(err.contains(needle), "{err:?} lacks {needle:?}");
        }
    }
}
