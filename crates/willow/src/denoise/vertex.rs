//! Moving the vertices to the filtered normals: the iterative update of Sun et al. 2007
//! ("Fast and effective feature-preserving mesh denoising", Eq. 8), which lets each vertex
//! slide toward the planes of its faces through their centroids with the filtered normals.

use super::neighbourhood::Rows;
use crate::geometry::vec3::{add, dot, norm, scale, sub};

/// One update: `x_i ← x_i + (1/|F_i|) Σ_{f ∋ i} n_f ⟨n_f, c_f − x_i⟩` for every vertex not
/// `held`, computed for all vertices before any moves (a Jacobi pass). Then each vertex is
/// kept within `max_displacement` of its `origin` (the closest point of that ball): every
/// point of the result then lies within that distance of the corresponding point of the
/// input and back, the two-sided bound `max_deviation` promises.
#[allow(clippy::too_many_arguments)]
pub fn update_vertices(
    positions: &mut [[f64; 3]],
    triangles: &[[usize; 3]],
    vertex_faces: &Rows,
    normals: &[[f64; 3]],
    held: &[bool],
    origin: &[[f64; 3]],
    max_displacement: Option<f64>,
    centroids: &mut [[f64; 3]],
    moved: &mut [[f64; 3]],
) {
    for (f, t) in triangles.iter().enumerate() {
        let [a, b, c] = t.map(|v| positions[v]);
        centroids[f] = scale(add(add(a, b), c), 1.0 / 3.0);
    }
    for (i, m) in moved.iter_mut().enumerate() {
        let x = positions[i];
        let faces = vertex_faces.row(i);
        if held.get(i).copied().unwrap_or(false) || faces.is_empty() {
            *m = x;
            continue;
        }
        let mut step = [0.0; 3];
        for &f in faces {
            let n = normals[f];
            step = add(step, scale(n, dot(n, sub(centroids[f], x))));
        }
        let mut y = add(x, scale(step, 1.0 / faces.len() as f64));
        if let Some(limit) = max_displacement {
            let d = sub(y, origin[i]);
            let len = norm(d);
            if len > limit {
                y = add(origin[i], scale(d, limit / len));
            }
        }
        *m = y;
    }
    positions.copy_from_slice(moved);
}

#[cfg(test)]
mod tests {
    use super::super::neighbourhood::vertex_faces;
    use super::*;

    /// Two triangles of the plane z = 0 and a vertex lifted off it.
    fn lifted_square() -> (Vec<[f64; 3]>, Vec<[usize; 3]>) {
        (
            vec![
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [1.0, 1.0, 0.3],
                [0.0, 1.0, 0.0],
            ],
            vec![[0, 1, 2], [0, 2, 3]],
        )
    }

    #[test]
    fn vertices_converge_onto_the_plane_of_the_filtered_normals() {
        let (mut p, t) = lifted_square();
        let origin = p.clone();
        let vf = vertex_faces(p.len(), &t);
        let up = [[0.0, 0.0, 1.0]; 2];
        let (mut c, mut m) = (vec![[0.0; 3]; 2], vec![[0.0; 3]; 4]);
        for _ in 0..200 {
            update_vertices(&mut p, &t, &vf, &up, &[], &origin, None, &mut c, &mut m);
        }
        // Every vertex lands on one plane z = const, and only along the normal: x, y stay.
        for (q, o) in p.iter().zip(&origin) {
            assert!((q[2] - p[0][2]).abs() < 1e-9, "{p:?}");
            assert_eq!((q[0], q[1]), (o[0], o[1]));
        }
    }

    #[test]
    fn held_vertices_stay_and_the_rest_stay_within_the_bound() {
        let (mut p, t) = lifted_square();
        let origin = p.clone();
        let vf = vertex_faces(p.len(), &t);
        let up = [[0.0, 0.0, 1.0]; 2];
        let (mut c, mut m) = (vec![[0.0; 3]; 2], vec![[0.0; 3]; 4]);
        let held = [true, false, false, false];
        for _ in 0..50 {
            update_vertices(
                &mut p,
                &t,
                &vf,
                &up,
                &held,
                &origin,
                Some(0.05),
                &mut c,
                &mut m,
            );
        }
        assert_eq!(p[0], origin[0]);
        for (q, o) in p.iter().zip(&origin) {
            assert!(norm(sub(*q, *o)) <= 0.05 + 1e-12);
        }
        // The lifted vertex used its whole allowance.
        assert!((norm(sub(p[2], origin[2])) - 0.05).abs() < 1e-9);
    }
}
