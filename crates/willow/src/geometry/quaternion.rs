//! Quaternions `w + xi + yj + zk` (real part first everywhere, docs/algorithm.md pitfall 3).
//!
//! Vectors of R³ are imaginary quaternions (paper §2.3): `q̄ v q` rotates and scales `v`.

use faer::c64;
use std::ops::{Add, AddAssign, Mul, Neg, Sub};

#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct Quaternion {
    pub w: f64,
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

impl Quaternion {
    pub const ONE: Quaternion = Quaternion {
        w: 1.0,
        x: 0.0,
        y: 0.0,
        z: 0.0,
    };

    pub const fn new(w: f64, x: f64, y: f64, z: f64) -> Self {
        Quaternion { w, x, y, z }
    }

    /// The imaginary quaternion of a vector of R³.
    pub const fn imaginary(v: [f64; 3]) -> Self {
        Quaternion {
            w: 0.0,
            x: v[0],
            y: v[1],
            z: v[2],
        }
    }

    pub const fn real(w: f64) -> Self {
        Quaternion {
            w,
            x: 0.0,
            y: 0.0,
            z: 0.0,
        }
    }

    pub fn conj(self) -> Self {
        Quaternion {
            w: self.w,
            x: -self.x,
            y: -self.y,
            z: -self.z,
        }
    }

    pub fn norm2(self) -> f64 {
        self.w * self.w + self.x * self.x + self.y * self.y + self.z * self.z
    }

    pub fn scale(self, s: f64) -> Self {
        Quaternion {
            w: self.w * s,
            x: self.x * s,
            y: self.y * s,
            z: self.z * s,
        }
    }

    pub fn vector(self) -> [f64; 3] {
        [self.x, self.y, self.z]
    }

    /// The 3×3 matrix (row major) of `v ↦ q̄ v q` on imaginary quaternions: `|q|²` times a
    /// rotation (paper §2.3). Linear in `v`, so applying one map to many vectors, or a sum of
    /// such maps to one vector, costs a matrix product instead of two quaternion products each.
    pub fn sandwich_matrix(self) -> [[f64; 3]; 3] {
        let Quaternion { w, x, y, z } = self;
        let (ww, xx, yy, zz) = (w * w, x * x, y * y, z * z);
        let (xy, xz, yz) = (2.0 * x * y, 2.0 * x * z, 2.0 * y * z);
        let (wx, wy, wz) = (2.0 * w * x, 2.0 * w * y, 2.0 * w * z);
        [
            [ww + xx - yy - zz, xy + wz, xz - wy],
            [xy - wz, ww - xx + yy - zz, yz + wx],
            [xz + wy, yz - wx, ww - xx - yy + zz],
        ]
    }

    /// The first column of the 2×2 complex matrix of `self` (see [`Quaternion::to_complex`]):
    /// a quaternion vector becomes a complex vector of twice the length this way.
    pub fn to_complex_column(self) -> [c64; 2] {
        [c64::new(self.w, self.x), c64::new(-self.y, self.z)]
    }

    /// Inverse of [`Quaternion::to_complex_column`].
    pub fn from_complex_column(z: [c64; 2]) -> Self {
        Quaternion {
            w: z[0].re,
            x: z[0].im,
            y: -z[1].re,
            z: z[1].im,
        }
    }

    /// The 2×2 complex matrix `[[w + xi, y + zi], [−y + zi, w − xi]]` (row major).
    ///
    /// This map is an injective ring homomorphism from H into 2×2 complex matrices that sends
    /// conjugation to the conjugate transpose, so a quaternion-Hermitian |V|×|V| matrix becomes a
    /// complex Hermitian 2|V|×2|V| one with half the flops of the 4×4 real form (docs/solver.md).
    pub fn to_complex(self) -> [[c64; 2]; 2] {
        [
            [c64::new(self.w, self.x), c64::new(self.y, self.z)],
            [c64::new(-self.y, self.z), c64::new(self.w, -self.x)],
        ]
    }

    /// The 4×4 real matrix of left multiplication by `self` (row major), acting on
    /// `(w, x, y, z)` column vectors.
    pub fn to_real(self) -> [[f64; 4]; 4] {
        let Quaternion { w, x, y, z } = self;
        [[w, -x, -y, -z], [x, w, -z, y], [y, z, w, -x], [z, -y, x, w]]
    }
}

impl Mul for Quaternion {
    type Output = Quaternion;
    /// Hamilton product.
    fn mul(self, r: Quaternion) -> Quaternion {
        let (a, b) = (self, r);
        Quaternion {
            w: a.w * b.w - a.x * b.x - a.y * b.y - a.z * b.z,
            x: a.w * b.x + a.x * b.w + a.y * b.z - a.z * b.y,
            y: a.w * b.y - a.x * b.z + a.y * b.w + a.z * b.x,
            z: a.w * b.z + a.x * b.y - a.y * b.x + a.z * b.w,
        }
    }
}

impl Add for Quaternion {
    type Output = Quaternion;
    fn add(self, r: Quaternion) -> Quaternion {
        Quaternion::new(self.w + r.w, self.x + r.x, self.y + r.y, self.z + r.z)
    }
}

impl AddAssign for Quaternion {
    fn add_assign(&mut self, r: Quaternion) {
        *self = *self + r;
    }
}

impl Sub for Quaternion {
    type Output = Quaternion;
    fn sub(self, r: Quaternion) -> Quaternion {
        Quaternion::new(self.w - r.w, self.x - r.x, self.y - r.y, self.z - r.z)
    }
}

impl Neg for Quaternion {
    type Output = Quaternion;
    fn neg(self) -> Quaternion {
        self.scale(-1.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn q(w: f64, x: f64, y: f64, z: f64) -> Quaternion {
        Quaternion::new(w, x, y, z)
    }

    #[test]
    fn hamilton_units() {
        let (i, j, k) = (q(0., 1., 0., 0.), q(0., 0., 1., 0.), q(0., 0., 0., 1.));
        assert_eq!(i * j, k);
        assert_eq!(j * k, i);
        assert_eq!(k * i, j);
        assert_eq!(i * i, q(-1., 0., 0., 0.));
        assert_eq!(j * i, -k);
    }

    #[test]
    fn conjugate_rotation_rotates_vectors() {
        // q = cos(θ/2) − sin(θ/2)·w rotates by θ about w under q̄ v q (paper §2.3).
        let t = std::f64::consts::FRAC_PI_2;
        let r = q((t / 2.0).cos(), 0.0, 0.0, -(t / 2.0).sin());
        let v = r.conj() * Quaternion::imaginary([1.0, 0.0, 0.0]) * r;
        assert!((v.w).abs() < 1e-15 && (v.x).abs() < 1e-15);
        assert!((v.y - 1.0).abs() < 1e-15 && v.z.abs() < 1e-15);
    }

    #[test]
    fn sandwich_matrix_is_conjugation() {
        let a = q(0.3, -1.2, 0.7, 2.0);
        let v = [0.4, -1.1, 0.9];
        let expected = (a.conj() * Quaternion::imaginary(v) * a).vector();
        let m = a.sandwich_matrix();
        for r in 0..3 {
            let got: f64 = (0..3).map(|c| m[r][c] * v[c]).sum();
            assert!(
                (got - expected[r]).abs() < 1e-13,
                "row {r}: {got} vs {}",
                expected[r]
            );
        }
        // |q|² times a rotation: MᵀM = |q|⁴ I.
        let n4 = a.norm2() * a.norm2();
        for r in 0..3 {
            for c in 0..3 {
                let d: f64 = (0..3).map(|k| m[k][r] * m[k][c]).sum();
                let e = if r == c { n4 } else { 0.0 };
                assert!((d - e).abs() < 1e-12 * n4);
            }
        }
    }

    #[test]
    fn complex_form_is_a_homomorphism() {
        let a = q(0.3, -1.2, 0.7, 2.0);
        let b = q(-0.5, 0.4, 1.1, -0.9);
        let (ma, mb, mab) = (a.to_complex(), b.to_complex(), (a * b).to_complex());
        for r in 0..2 {
            for c in 0..2 {
                let p = ma[r][0] * mb[0][c] + ma[r][1] * mb[1][c];
                assert!((p - mab[r][c]).norm() < 1e-14);
            }
        }
        // Conjugation becomes the conjugate transpose.
        let mc = a.conj().to_complex();
        for r in 0..2 {
            for c in 0..2 {
                assert!((mc[r][c] - ma[c][r].conj()).norm() < 1e-15);
            }
        }
        // A quaternion vector maps to the first column, and back.
        let col = b.to_complex_column();
        assert_eq!(col, [mb[0][0], mb[1][0]]);
        assert_eq!(Quaternion::from_complex_column(col), b);
    }

    #[test]
    fn real_form_is_left_multiplication() {
        let a = q(0.3, -1.2, 0.7, 2.0);
        let b = q(-0.5, 0.4, 1.1, -0.9);
        let m = a.to_real();
        let v = [b.w, b.x, b.y, b.z];
        let p: Vec<f64> = (0..4)
            .map(|r| (0..4).map(|c| m[r][c] * v[c]).sum())
            .collect();
        let ab = a * b;
        assert!(
            (p[0] - ab.w).abs() + (p[1] - ab.x).abs() + (p[2] - ab.y).abs() + (p[3] - ab.z).abs()
                < 1e-14
        );
    }
}
