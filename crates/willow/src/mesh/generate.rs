//! Meshes generated in code, for tests and benchmarks that must run without `../shared`.

use super::Mesh;
use std::collections::HashMap;

/// A unit icosphere: the icosahedron with every triangle split into four `subdivisions` times,
/// vertices projected onto the unit sphere. Faces wind counter-clockwise seen from outside.
pub fn icosphere(subdivisions: usize) -> Mesh {
    let t = (1.0 + 5f64.sqrt()) / 2.0;
    let mut positions: Vec<[f64; 3]> = [
        [-1.0, t, 0.0],
        [1.0, t, 0.0],
        [-1.0, -t, 0.0],
        [1.0, -t, 0.0],
        [0.0, -1.0, t],
        [0.0, 1.0, t],
        [0.0, -1.0, -t],
        [0.0, 1.0, -t],
        [t, 0.0, -1.0],
        [t, 0.0, 1.0],
        [-t, 0.0, -1.0],
        [-t, 0.0, 1.0],
    ]
    .iter()
    .map(|p| normalize(*p))
    .collect();
    let mut triangles: Vec<[usize; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..subdivisions {
        let mut midpoint: HashMap<(usize, usize), usize> = HashMap::new();
        let mut next = Vec::with_capacity(triangles.len() * 4);
        for &[a, b, c] in &triangles {
            let mut mid = |i: usize, j: usize| -> usize {
                let key = (i.min(j), i.max(j));
                *midpoint.entry(key).or_insert_with(|| {
                    let (p, q) = (positions[i], positions[j]);
                    positions.push(normalize([p[0] + q[0], p[1] + q[1], p[2] + q[2]]));
                    positions.len() - 1
                })
            };
            let (ab, bc, ca) = (mid(a, b), mid(b, c), mid(c, a));
            next.extend_from_slice(&[[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        triangles = next;
    }
    Mesh {
        positions,
        triangles,
    }
}

/// An icosphere pushed onto the radial profile `r = 1 + amplitude · s(p)`, where `s` is a sum of
/// smooth bumps of several frequencies: a genus-0 surface with a lot of Willmore energy.
pub fn bumpy_sphere(subdivisions: usize, amplitude: f64) -> Mesh {
    let mut mesh = icosphere(subdivisions);
    for p in &mut mesh.positions {
        let [x, y, z] = *p;
        let s = (3.0 * x + 1.0).sin() * (2.0 * y).sin() * (4.0 * z).cos()
            + 0.5 * (7.0 * y + 0.3).sin() * (5.0 * z).cos();
        let r = 1.0 + amplitude * s;
        *p = [x * r, y * r, z * r];
    }
    mesh
}

/// A bumpy spherical cap, a disk with one boundary loop: the faces of `icosphere(subdivisions)`
/// whose corners all lie above z = −0.3, pushed onto `r = 1 + amplitude · sin 7x · cos 6y`.
pub fn bumpy_cap(subdivisions: usize, amplitude: f64) -> Mesh {
    let sphere = icosphere(subdivisions);
    let keep: Vec<[usize; 3]> = sphere
        .triangles
        .iter()
        .copied()
        .filter(|t| t.iter().all(|&v| sphere.positions[v][2] > -0.3))
        .collect();
    let mut used = vec![usize::MAX; sphere.positions.len()];
    let mut positions = Vec::new();
    for t in &keep {
        for &v in t {
            if used[v] == usize::MAX {
                used[v] = positions.len();
                let [x, y, z] = sphere.positions[v];
                let r = 1.0 + amplitude * (7.0 * x).sin() * (6.0 * y).cos();
                positions.push([x * r, y * r, z * r]);
            }
        }
    }
    Mesh {
        positions,
        triangles: keep
            .iter()
            .map(|t| [used[t[0]], used[t[1]], used[t[2]]])
            .collect(),
    }
}

/// A torus of revolution around the z axis with tube radius `minor` and centre radius
/// `major`, sampled on a `u_segments × v_segments` grid and split into right triangles.
pub fn torus(major: f64, minor: f64, u_segments: usize, v_segments: usize) -> Mesh {
    let mut positions = Vec::with_capacity(u_segments * v_segments);
    for i in 0..u_segments {
        let u = 2.0 * std::f64::consts::PI * i as f64 / u_segments as f64;
        for j in 0..v_segments {
            let v = 2.0 * std::f64::consts::PI * j as f64 / v_segments as f64;
            let r = major + minor * v.cos();
            positions.push([r * u.cos(), r * u.sin(), minor * v.sin()]);
        }
    }
    let id = |i: usize, j: usize| (i % u_segments) * v_segments + (j % v_segments);
    let mut triangles = Vec::with_capacity(2 * u_segments * v_segments);
    for i in 0..u_segments {
        for j in 0..v_segments {
            let (a, b, c, d) = (id(i, j), id(i + 1, j), id(i + 1, j + 1), id(i, j + 1));
            triangles.push([a, b, c]);
            triangles.push([a, c, d]);
        }
    }
    Mesh {
        positions,
        triangles,
    }
}

/// A deliberately irregular sphere: an icosphere whose vertices slide along the surface toward
/// a few cluster centres, so triangle sizes vary by orders of magnitude (paper Figure 18).
/// Deterministic for a given `seed`.
pub fn irregular_sphere(subdivisions: usize, seed: u64) -> Mesh {
    let mut mesh = icosphere(subdivisions);
    let mut rng = SplitMix64(seed);
    let centres: Vec<[f64; 3]> = (0..6)
        .map(|_| normalize([rng.signed(), rng.signed(), rng.signed()]))
        .collect();
    for p in &mut mesh.positions {
        let mut q = *p;
        for c in &centres {
            let d2 = (q[0] - c[0]).powi(2) + (q[1] - c[1]).powi(2) + (q[2] - c[2]).powi(2);
            // Pull toward the centre: strong near it, vanishing far away, never crossing it.
            let w = 0.85 * (-d2 / 0.08).exp();
            q = [
                q[0] + w * (c[0] - q[0]),
                q[1] + w * (c[1] - q[1]),
                q[2] + w * (c[2] - q[2]),
            ];
        }
        let n = normalize(q);
        let r = 1.0 + 0.08 * (5.0 * n[0]).sin() * (4.0 * n[1]).cos();
        *p = [n[0] * r, n[1] * r, n[2] * r];
    }
    mesh
}

/// A closed surface of revolution about the z axis: the `profile` polyline of `(r, z)`
/// points, from a point on the axis (r = 0) to another, each segment split into pieces at
/// most `step` long, turned in `segments` steps. The vertices where the profile turns are
/// rings of creases (of the profile's turning angle); a run of short segments approximates
/// a fillet. Outward-oriented; what the crease tests make their CAD parts from.
pub fn revolved(profile: &[[f64; 2]], step: f64, segments: usize) -> Mesh {
    let mut points: Vec<[f64; 2]> = Vec::new();
    for w in profile.windows(2) {
        let (a, b) = (w[0], w[1]);
        let length = ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2)).sqrt();
        let pieces = ((length / step).ceil() as usize).max(1);
        for k in 0..pieces {
            let t = k as f64 / pieces as f64;
            points.push([a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])]);
        }
    }
    if let Some(&last) = profile.last() {
        points.push(last);
    }
    let mut positions = Vec::new();
    // Each profile point's vertices: one on the axis, else a ring of `segments`.
    let mut rows: Vec<Vec<usize>> = Vec::new();
    for &[r, z] in &points {
        if r.abs() < 1e-12 {
            rows.push(vec![positions.len()]);
            positions.push([0.0, 0.0, z]);
        } else {
            let start = positions.len();
            for j in 0..segments {
                let angle = std::f64::consts::TAU * j as f64 / segments as f64;
                positions.push([r * angle.cos(), r * angle.sin(), z]);
            }
            rows.push((start..start + segments).collect());
        }
    }
    let mut triangles = Vec::new();
    for w in rows.windows(2) {
        let (lower, upper) = (&w[0], &w[1]);
        let at = |row: &Vec<usize>, j: usize| row[if row.len() == 1 { 0 } else { j % segments }];
        for j in 0..segments {
            let (a, b) = (at(lower, j), at(lower, j + 1));
            let (c, d) = (at(upper, j + 1), at(upper, j));
            if a != b {
                triangles.push([a, b, c]);
            }
            if c != d {
                triangles.push([a, c, d]);
            }
        }
    }
    Mesh {
        positions,
        triangles,
    }
}

/// The CAD part of the crease tests and benchmarks: a cylinder of radius 1 and height 2 whose
/// rims are chamfered at 45° (0.2 wide), [`revolved`] with pieces at most `step` long and
/// `segments` around: four rings of 45° creases between flat disks, the chamfers and the
/// cylinder.
pub fn chamfered_cylinder(step: f64, segments: usize) -> Mesh {
    revolved(
        &[
            [0.0, 0.0],
            [0.8, 0.0],
            [1.0, 0.2],
            [1.0, 1.8],
            [0.8, 2.0],
            [0.0, 2.0],
        ],
        step,
        segments,
    )
}

/// `mesh` with independent Gaussian noise of standard deviation `relative` × the mean edge
/// length added to every coordinate: what a scan or a careless export uploads. Deterministic
/// for a given `seed`; connectivity is unchanged.
pub fn with_noise(mut mesh: Mesh, relative: f64, seed: u64) -> Mesh {
    let sigma = relative * mean_edge_length(&mesh);
    let mut rng = SplitMix64(seed);
    for p in &mut mesh.positions {
        for x in p.iter_mut() {
            *x += sigma * rng.gaussian();
        }
    }
    mesh
}

/// Mean length of the triangles' edges (interior edges counted twice).
pub fn mean_edge_length(mesh: &Mesh) -> f64 {
    let mut sum = 0.0;
    for t in &mesh.triangles {
        for k in 0..3 {
            let (a, b) = (mesh.positions[t[k]], mesh.positions[t[(k + 1) % 3]]);
            sum += ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt();
        }
    }
    sum / (3 * mesh.triangles.len().max(1)) as f64
}

/// A closed surface of genus `holes`: a slab `(2·holes + 1) × 3` cells wide with one square
/// hole through every other cell of the middle row, each cell split into `resolution²` quads,
/// its walls `resolution` rows high, then rounded by uniform Laplacian smoothing (a few
/// hundred Jacobi sweeps) so it is a smooth "pretzel" rather than a box. Faces wind
/// outward.
pub fn pretzel(holes: usize, resolution: usize) -> Mesh {
    let s = resolution.max(1);
    let (cells_x, cells_y) = (2 * holes + 1, 3);
    let (nx, ny) = (cells_x * s, cells_y * s);
    // A fine cell is solid unless it lies inside a hole cell (odd column, middle row).
    let solid = |i: usize, j: usize| -> bool {
        let (cx, cy) = (i / s, j / s);
        !(cy == 1 && cx % 2 == 1)
    };
    let h = 0.5 * cells_y as f64 / 3.0;
    let mut positions: Vec<[f64; 3]> = Vec::new();
    let mut index: HashMap<(usize, usize, usize), usize> = HashMap::new();
    // Layer 0 is the top face, layer `s` the bottom one; 1..s are wall rows.
    let mut vertex = |i: usize, j: usize, layer: usize, positions: &mut Vec<[f64; 3]>| -> usize {
        *index.entry((i, j, layer)).or_insert_with(|| {
            let z = h - 2.0 * h * layer as f64 / s as f64;
            positions.push([i as f64 / s as f64, j as f64 / s as f64, z]);
            positions.len() - 1
        })
    };
    let mut triangles = Vec::new();
    for i in 0..nx {
        for j in 0..ny {
            if !solid(i, j) {
                continue;
            }
            let top = [(i, j), (i + 1, j), (i + 1, j + 1), (i, j + 1)]
                .map(|(a, b)| vertex(a, b, 0, &mut positions));
            triangles.push([top[0], top[1], top[2]]);
            triangles.push([top[0], top[2], top[3]]);
            let bottom = [(i, j), (i + 1, j), (i + 1, j + 1), (i, j + 1)]
                .map(|(a, b)| vertex(a, b, s, &mut positions));
            triangles.push([bottom[0], bottom[2], bottom[1]]);
            triangles.push([bottom[0], bottom[3], bottom[2]]);
            // Walls on the sides of this cell that face a hole or the outside, walked so the
            // solid cell is on the left (counter-clockwise seen from above).
            let neighbours = [
                ((i, j), (i + 1, j), j == 0 || !solid(i, j - 1)),
                ((i + 1, j), (i + 1, j + 1), i + 1 == nx || !solid(i + 1, j)),
                ((i + 1, j + 1), (i, j + 1), j + 1 == ny || !solid(i, j + 1)),
                ((i, j + 1), (i, j), i == 0 || !solid(i - 1, j)),
            ];
            for (p, q, open) in neighbours {
                if !open {
                    continue;
                }
                for layer in 0..s {
                    let a = vertex(p.0, p.1, layer, &mut positions);
                    let b = vertex(q.0, q.1, layer, &mut positions);
                    let c = vertex(q.0, q.1, layer + 1, &mut positions);
                    let d = vertex(p.0, p.1, layer + 1, &mut positions);
                    triangles.push([a, d, c]);
                    triangles.push([a, c, b]);
                }
            }
        }
    }
    // Round the box: uniform Laplacian smoothing shrinks it toward a smooth handlebody.
    let mut neighbours = vec![Vec::new(); positions.len()];
    for t in &triangles {
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            if !neighbours[a].contains(&b) {
                neighbours[a].push(b);
                neighbours[b].push(a);
            }
        }
    }
    for _ in 0..20 * s {
        let next: Vec<[f64; 3]> = neighbours
            .iter()
            .zip(&positions)
            .map(|(nb, p)| {
                let mut m = [0.0; 3];
                for &v in nb {
                    for k in 0..3 {
                        m[k] += positions[v][k] / nb.len() as f64;
                    }
                }
                [
                    0.5 * (p[0] + m[0]),
                    0.5 * (p[1] + m[1]),
                    0.5 * (p[2] + m[2]),
                ]
            })
            .collect();
        positions = next;
    }
    Mesh {
        positions,
        triangles,
    }
}

fn normalize(p: [f64; 3]) -> [f64; 3] {
    let n = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
    [p[0] / n, p[1] / n, p[2] / n]
}

/// A tiny deterministic PRNG (SplitMix64) so generated meshes are reproducible without a
/// dependency.
pub(crate) struct SplitMix64(pub u64);

impl SplitMix64 {
    pub(crate) fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [-1, 1).
    pub(crate) fn signed(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
    }

    /// Standard normal (Box–Muller; the second variate is dropped for simplicity).
    pub(crate) fn gaussian(&mut self) -> f64 {
        // (0, 1]: the logarithm stays finite.
        let u = ((self.next_u64() >> 11) as f64 + 1.0) / (1u64 << 53) as f64;
        let v = (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
        (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn icosphere_counts_follow_euler() {
        for s in 0..4 {
            let m = icosphere(s);
            let f = 20 * 4usize.pow(s as u32);
            assert_eq!(m.triangles.len(), f);
            assert_eq!(m.positions.len(), f / 2 + 2); // V - E + F = 2 with E = 3F/2
        }
    }

    #[test]
    fn torus_has_euler_characteristic_zero() {
        let m = torus(2.0, 0.7, 24, 12);
        assert_eq!(m.positions.len() * 2, m.triangles.len()); // V - 3F/2 + F = 0
    }
}
