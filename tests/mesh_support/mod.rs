//! Small meshes built in code for the `mesh_*` integration tests.
#![allow(dead_code)] // each test crate uses a different subset

use std::f64::consts::PI;

/// Axis-aligned unit cube, 12 triangles wound outward.
pub fn cube() -> (Vec<[f64; 3]>, Vec<[usize; 3]>) {
    let p = vec![
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [1.0, 1.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, 0.0, 1.0],
        [1.0, 0.0, 1.0],
        [1.0, 1.0, 1.0],
        [0.0, 1.0, 1.0],
    ];
    let t = vec![
        [0, 2, 1],
        [0, 3, 2], // z = 0, normal -z
        [4, 5, 6],
        [4, 6, 7], // z = 1, normal +z
        [0, 1, 5],
        [0, 5, 4], // y = 0, normal -y
        [2, 3, 7],
        [2, 7, 6], // y = 1, normal +y
        [1, 2, 6],
        [1, 6, 5], // x = 1, normal +x
        [0, 4, 7],
        [0, 7, 3], // x = 0, normal -x
    ];
    (p, t)
}

/// A flat disk: a centre vertex and a ring of `n` vertices, fanned.
pub fn disk(n: usize) -> (Vec<[f64; 3]>, Vec<[usize; 3]>) {
    let mut p = vec![[0.0, 0.0, 0.0]];
    for i in 0..n {
        let a = 2.0 * PI * i as f64 / n as f64;
        p.push([a.cos(), a.sin(), 0.0]);
    }
    let t = (0..n).map(|i| [0, 1 + i, 1 + (i + 1) % n]).collect();
    (p, t)
}

/// An open cylinder (a tube) with `rings` rings of `n` vertices: two boundary loops.
pub fn cylinder(n: usize, rings: usize) -> (Vec<[f64; 3]>, Vec<[usize; 3]>) {
    let mut p = Vec::new();
    for r in 0..rings {
        for i in 0..n {
            let a = 2.0 * PI * i as f64 / n as f64;
            p.push([a.cos(), a.sin(), r as f64 * 0.5]);
        }
    }
    let mut t = Vec::new();
    for r in 0..rings - 1 {
        for i in 0..n {
            let (a, b) = (r * n + i, r * n + (i + 1) % n);
            let (c, d) = (a + n, b + n);
            t.push([a, b, d]);
            t.push([a, d, c]);
        }
    }
    (p, t)
}

/// A Möbius strip of `n` quads: non-orientable, one boundary loop.
pub fn mobius(n: usize) -> (Vec<[f64; 3]>, Vec<[usize; 3]>) {
    let mut p = Vec::new();
    for i in 0..n {
        let u = 2.0 * PI * i as f64 / n as f64;
        for w in [-0.3, 0.3] {
            let r = 1.0 + w * (u / 2.0).cos();
            p.push([r * u.cos(), r * u.sin(), w * (u / 2.0).sin()]);
        }
    }
    let mut t = Vec::new();
    for i in 0..n {
        let (a, b) = (2 * i, 2 * i + 1);
        // After a full turn the strip comes back upside down: w = -0.3 meets w = +0.3.
        let (c, d) = if i + 1 < n {
            (2 * (i + 1), 2 * (i + 1) + 1)
        } else {
            (1, 0)
        };
        t.push([a, c, d]);
        t.push([a, d, b]);
    }
    (p, t)
}

/// Signed volume (positive when wound outward).
pub fn signed_volume(p: &[[f64; 3]], t: &[[usize; 3]]) -> f64 {
    t.iter()
        .map(|&[a, b, c]| {
            let (a, b, c) = (p[a], p[b], p[c]);
            a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0])
                + a[2] * (b[0] * c[1] - b[1] * c[0])
        })
        .sum::<f64>()
        / 6.0
}

/// True if every interior edge is traversed in opposite directions by its two faces.
pub fn consistently_wound(t: &[[usize; 3]]) -> bool {
    let mut directed = std::collections::HashSet::new();
    for tri in t {
        for k in 0..3 {
            if !directed.insert((tri[k], tri[(k + 1) % 3])) {
                return false;
            }
        }
    }
    true
}

/// Where the shared test meshes live, or `None` (with a note) when this checkout has none.
pub fn shared_mesh(name: &str) -> Option<std::path::PathBuf> {
    let dir = std::env::var_os("WILLOW_SHARED_MESHES")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| std::path::PathBuf::from("/work/shared/meshes"));
    let path = dir.join(name);
    if path.is_file() {
        Some(path)
    } else {
        eprintln!("note: {} not found; skipping this check", path.display());
        None
    }
}
