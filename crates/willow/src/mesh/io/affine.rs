//! Node transforms of glTF (and the identity of every other format), in f64.

/// An affine map `p ↦ m·p + t` in f64 (`m` row-major).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Affine {
    pub(crate) m: [[f64; 3]; 3],
    pub(crate) t: [f64; 3],
}

impl Affine {
    pub(crate) const IDENTITY: Affine = Affine {
        m: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        t: [0.0; 3],
    };

    pub(crate) fn apply(&self, p: [f64; 3]) -> [f64; 3] {
        let m = &self.m;
        [
            m[0][0] * p[0] + m[0][1] * p[1] + m[0][2] * p[2] + self.t[0],
            m[1][0] * p[0] + m[1][1] * p[1] + m[1][2] * p[2] + self.t[1],
            m[2][0] * p[0] + m[2][1] * p[1] + m[2][2] * p[2] + self.t[2],
        ]
    }

    /// `mᵀ·n`: takes a world-space normal back to the local space of `self` (normals move
    /// with the inverse transpose, so the inverse of that is the transpose).
    pub(crate) fn transpose_apply(&self, n: [f64; 3]) -> [f64; 3] {
        let m = &self.m;
        [
            m[0][0] * n[0] + m[1][0] * n[1] + m[2][0] * n[2],
            m[0][1] * n[0] + m[1][1] * n[1] + m[2][1] * n[2],
            m[0][2] * n[0] + m[1][2] * n[1] + m[2][2] * n[2],
        ]
    }

    /// `self ∘ other`.
    pub(crate) fn then_after(&self, other: &Affine) -> Affine {
        let (a, b) = (&self.m, &other.m);
        let mut m = [[0.0; 3]; 3];
        for (i, row) in m.iter_mut().enumerate() {
            for (j, x) in row.iter_mut().enumerate() {
                *x = (0..3).map(|k| a[i][k] * b[k][j]).sum();
            }
        }
        Affine {
            m,
            t: self.apply(other.t),
        }
    }

    pub(crate) fn determinant(&self) -> f64 {
        let m = &self.m;
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    }

    /// The inverse map, or `None` when `m` is singular or not finite (a node scaled by zero
    /// cannot have its transform undone when writing).
    pub(crate) fn inverse(&self) -> Option<Affine> {
        let d = self.determinant();
        if !d.is_finite() || d == 0.0 {
            return None;
        }
        let m = &self.m;
        let c = |r0: usize, r1: usize, c0: usize, c1: usize| {
            m[r0][c0] * m[r1][c1] - m[r0][c1] * m[r1][c0]
        };
        let inv = [
            [c(1, 2, 1, 2) / d, -c(0, 2, 1, 2) / d, c(0, 1, 1, 2) / d],
            [-c(1, 2, 0, 2) / d, c(0, 2, 0, 2) / d, -c(0, 1, 0, 2) / d],
            [c(1, 2, 0, 1) / d, -c(0, 2, 0, 1) / d, c(0, 1, 0, 1) / d],
        ];
        let lin = Affine {
            m: inv,
            t: [0.0; 3],
        };
        let t = lin.apply(self.t);
        let out = Affine {
            m: inv,
            t: [-t[0], -t[1], -t[2]],
        };
        out.m
            .iter()
            .flatten()
            .chain(&out.t)
            .all(|x| x.is_finite())
            .then_some(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn affine_inverse_undoes_the_map() {
        let a = Affine {
            m: [[0.0, -2.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0.0, 0.5]],
            t: [1.0, 2.0, 3.0],
        };
        let inv = a.inverse().unwrap();
        let p = [0.3, -0.7, 4.0];
        let q = inv.apply(a.apply(p));
        for k in 0..3 {
            assert!((p[k] - q[k]).abs() < 1e-15);
        }
        let singular = Affine {
            m: [[0.0; 3]; 3],
            t: [0.0; 3],
        };
        assert!(singular.inverse().is_none());
    }
}
