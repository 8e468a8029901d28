//! What users send (issue 26), generated with fixed seeds, and a soundness check that uses
//! none of Willow's own metrics: each triangle's share of the area against the input's, and
//! folded faces, both computed here from positions alone.
#![allow(dead_code)] // the probe and the tests use different subsets

use std::collections::HashMap;
use std::f64::consts::PI;
use willow::mesh::generate::{mean_edge_length, pretzel, torus};
use willow::mesh::Mesh;

/// SplitMix64 (Steele, Lea and Flood 2014): a seeded, portable stream of bits.
pub struct Rng(pub u64);

impl Rng {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in (0, 1).
    pub fn uniform(&mut self) -> f64 {
        ((self.next_u64() >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }
    pub fn gaussian(&mut self) -> f64 {
        let (u, v) = (self.uniform(), self.uniform());
        (-2.0 * u.ln()).sqrt() * (2.0 * PI * v).cos()
    }
    /// Laplace with unit standard deviation (scale 1/√2): heavy tails beside the Gaussian.
    pub fn laplace(&mut self) -> f64 {
        let u = self.uniform() - 0.5;
        -u.signum() * (1.0 - 2.0 * u.abs()).ln() / 2f64.sqrt()
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
fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

/// Area-weighted vertex normals (unnormalized sums of face cross products, then unit).
fn vertex_normals(p: &[[f64; 3]], t: &[[usize; 3]]) -> Vec<[f64; 3]> {
    let mut n = vec![[0.0; 3]; p.len()];
    for f in t {
        let c = cross(sub(p[f[1]], p[f[0]]), sub(p[f[2]], p[f[0]]));
        for &v in f {
            for k in 0..3 {
                n[v][k] += c[k];
            }
        }
    }
    for v in &mut n {
        let l = norm(*v).max(f64::MIN_POSITIVE);
        *v = [v[0] / l, v[1] / l, v[2] / l];
    }
    n
}

/// Which noise to add along the normal.
#[derive(Clone, Copy, Debug)]
pub enum Noise {
    Gaussian,
    Laplace,
}

/// `mesh` with noise along each vertex normal of standard deviation `normal` × the mean edge
/// length (Gaussian or heavy-tailed Laplace), plus a tangential jitter of standard deviation
/// `tangential` × the mean edge (Gaussian, in the tangent plane): a scan's noise, which moves
/// vertices along the surface as well as across it.
pub fn noisy(mesh: Mesh, noise: Noise, normal: f64, tangential: f64, seed: u64) -> Mesh {
    let h = mean_edge_length(&mesh);
    let normals = vertex_normals(&mesh.positions, &mesh.triangles);
    let mut rng = Rng(seed);
    let mut p = mesh.positions.clone();
    for (q, n) in p.iter_mut().zip(&normals) {
        let a = match noise {
            Noise::Gaussian => rng.gaussian(),
            Noise::Laplace => rng.laplace(),
        } * normal
            * h;
        // Two tangent directions: any vector not along n, made orthogonal to it.
        let helper = if n[0].abs() < 0.9 {
            [1.0, 0.0, 0.0]
        } else {
            [0.0, 1.0, 0.0]
        };
        let t1 = cross(*n, helper);
        let l1 = norm(t1);
        let t1 = [t1[0] / l1, t1[1] / l1, t1[2] / l1];
        let t2 = cross(*n, t1);
        let (b, c) = (
            rng.gaussian() * tangential * h,
            rng.gaussian() * tangential * h,
        );
        for k in 0..3 {
            q[k] += a * n[k] + b * t1[k] + c * t2[k];
        }
    }
    Mesh::new(p, mesh.triangles).expect("noisy mesh stays valid")
}

/// A 2.5:1 torus of 64 × 32.
pub fn base_torus() -> Mesh {
    torus(2.5, 1.0, 64, 32)
}

/// A smooth closed surface of genus `holes` (the crate's rounded slab).
pub fn base_pretzel(holes: usize) -> Mesh {
    pretzel(holes, 4)
}

/// What marching cubes on a binary voxel mask exports (CT segmentation, topology
/// optimization): `mesh` with its z coordinates pulled onto layers `layer` × the mean edge
/// apart, so every smooth slope becomes a staircase of nearly flat terraces (a tenth of the
/// original slope left, so no triangle on a terrace degenerates to a line) and steep risers.
/// Connectivity is unchanged.
pub fn terraced(mesh: Mesh, layer: f64) -> Mesh {
    let step = layer * mean_edge_length(&mesh);
    let p = mesh
        .positions
        .iter()
        .map(|q| {
            let level = (q[2] / step).round() * step;
            [q[0], q[1], level + 0.1 * (q[2] - level)]
        })
        .collect();
    Mesh::new(p, mesh.triangles).expect("terraced mesh stays valid")
}

/// A 2.5:1 torus exported as long strips: 32 × 128 samples of a 2.5:1 torus, so each triangle is
/// about ten times longer (around the axis) than it is wide.
pub fn strip_torus() -> Mesh {
    let m = torus(2.5, 1.0, 32, 128);
    Mesh::new(m.positions, m.triangles).expect("valid")
}

/// A CAD cylinder of radius 1 and height 2, `n` vertices per rim, its caps fanned from their
/// centres, and `rings` rings: coarse, W below 4π.
pub fn fan_capped_cylinder(n: usize, rings: usize) -> Mesh {
    let mut p = Vec::new();
    for r in 0..rings {
        let z = -1.0 + 2.0 * r as f64 / (rings - 1) as f64;
        for i in 0..n {
            let a = 2.0 * PI * i as f64 / n as f64;
            p.push([a.cos(), a.sin(), z]);
        }
    }
    let (bottom, top) = (p.len(), p.len() + 1);
    p.push([0.0, 0.0, -1.0]);
    p.push([0.0, 0.0, 1.0]);
    let mut t = Vec::new();
    for r in 0..rings - 1 {
        for i in 0..n {
            let (a, b) = (r * n + i, r * n + (i + 1) % n);
            t.push([a, b, b + n]);
            t.push([a, b + n, a + n]);
        }
    }
    for i in 0..n {
        let j = (i + 1) % n;
        t.push([bottom, j, i]);
        t.push([top, (rings - 1) * n + i, (rings - 1) * n + j]);
    }
    Mesh::new(p, t).expect("valid cylinder")
}

/// A flat washer (annulus) with `n` vertices per ring and `rings` rings from radius 1 to 2:
/// H vanishes, so there is nothing to fair.
pub fn washer(n: usize, rings: usize) -> Mesh {
    let mut p = Vec::new();
    for r in 0..rings {
        let radius = 1.0 + r as f64 / (rings - 1) as f64;
        for i in 0..n {
            let a = 2.0 * PI * i as f64 / n as f64;
            p.push([radius * a.cos(), radius * a.sin(), 0.0]);
        }
    }
    let mut t = Vec::new();
    for r in 0..rings - 1 {
        for i in 0..n {
            let (a, b) = (r * n + i, r * n + (i + 1) % n);
            t.push([a, b, b + n]);
            t.push([a, b + n, a + n]);
        }
    }
    Mesh::new(p, t).expect("valid washer")
}

/// Each triangle's share of the total area.
pub fn area_shares(p: &[[f64; 3]], t: &[[usize; 3]]) -> Vec<f64> {
    let a: Vec<f64> = t
        .iter()
        .map(|f| 0.5 * norm(cross(sub(p[f[1]], p[f[0]]), sub(p[f[2]], p[f[0]]))))
        .collect();
    let total: f64 = a.iter().sum();
    a.iter().map(|x| x / total).collect()
}

/// Triangles whose share of the area is below 1e-8 of their share in the input (or not
/// finite): collapsed.
pub fn collapsed(input: &[[f64; 3]], now: &[[f64; 3]], t: &[[usize; 3]]) -> usize {
    let (s0, s) = (area_shares(input, t), area_shares(now, t));
    s.iter()
        .zip(&s0)
        .filter(|&(&a, &b)| a.is_nan() || a < 1e-8 * b)
        .count()
}

/// Folded faces: a face whose unit normal makes more than 120° with the sum of its edge
/// neighbours' unit normals (a zero-area face counts as folded). Neighbours found through a
/// map of undirected edges.
pub fn folds(p: &[[f64; 3]], t: &[[usize; 3]]) -> usize {
    let mut by_edge: HashMap<(usize, usize), Vec<usize>> = HashMap::new();
    for (f, tri) in t.iter().enumerate() {
        for k in 0..3 {
            let (a, b) = (tri[k], tri[(k + 1) % 3]);
            by_edge.entry((a.min(b), a.max(b))).or_default().push(f);
        }
    }
    let unit: Vec<[f64; 3]> = t
        .iter()
        .map(|f| {
            let c = cross(sub(p[f[1]], p[f[0]]), sub(p[f[2]], p[f[0]]));
            let l = norm(c);
            if l > 0.0 {
                [c[0] / l, c[1] / l, c[2] / l]
            } else {
                [0.0; 3]
            }
        })
        .collect();
    let mut count = 0;
    for (f, tri) in t.iter().enumerate() {
        let mut sum = [0.0; 3];
        for k in 0..3 {
            let (a, b) = (tri[k], tri[(k + 1) % 3]);
            for &g in &by_edge[&(a.min(b), a.max(b))] {
                if g != f {
                    for i in 0..3 {
                        sum[i] += unit[g][i];
                    }
                }
            }
        }
        if norm(unit[f]) == 0.0 || dot(unit[f], sum) < -0.5 * norm(sum) {
            count += 1;
        }
    }
    count
}

/// Σ |(L f)_i|² / 4A_i (libigl's form of W) with this file's own cotan Laplacian and
/// barycentric areas: 4π for a round sphere, independent of Willow's metrics.
pub fn willmore_laplacian(p: &[[f64; 3]], t: &[[usize; 3]]) -> f64 {
    let mut lf = vec![[0.0f64; 3]; p.len()];
    let mut area = vec![0.0f64; p.len()];
    for f in t {
        let q = [p[f[0]], p[f[1]], p[f[2]]];
        let double_area = norm(cross(sub(q[1], q[0]), sub(q[2], q[0])));
        for k in 0..3 {
            area[f[k]] += double_area / 6.0;
            // Corner k's cotangent weighs the opposite edge (i, j).
            let (i, j) = ((k + 1) % 3, (k + 2) % 3);
            let cot = dot(sub(q[i], q[k]), sub(q[j], q[k])) / double_area;
            for d in 0..3 {
                let diff = q[i][d] - q[j][d];
                lf[f[i]][d] += 0.5 * cot * diff;
                lf[f[j]][d] -= 0.5 * cot * diff;
            }
        }
    }
    lf.iter()
        .zip(&area)
        .map(|(l, a)| dot(*l, *l) / (4.0 * a))
        .sum()
}
