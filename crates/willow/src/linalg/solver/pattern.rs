//! The fixed block sparsity pattern of a mesh's vertex graph, and the scatters that refill its
//! values each step (the cotan Laplacian, a diagonal).

use crate::linalg::ordering::{self, Ordering, OrderingError};
use faer::sparse::SymbolicSparseColMat;

/// The full (both triangles) sparsity pattern of a symmetric matrix over the vertex graph of a
/// triangle mesh, with every vertex-pair entry expanded to a dense `block × block` block
/// (1 for scalar Laplacians, 2 for the complex form of the quaternionic Dirac matrix).
///
/// Values are stored column-major per CSC column; for the block of row vertex `i` and column
/// vertex `j`, entry `(ri, rj)` lives at [`BlockPattern::entry`]`(slot, j, ri, rj)` where `slot`
/// is the block's base index (precomputed per face in [`BlockPattern::face_slots`]).
pub struct BlockPattern {
    pub block: usize,
    /// Vertex-level CSC: `vertex_col_ptr[j]..vertex_col_ptr[j+1]` indexes the sorted
    /// neighbours of `j` (itself included) in `vertex_row_idx`.
    pub(super) vertex_col_ptr: Vec<usize>,
    vertex_row_idx: Vec<usize>,
    /// The expanded pattern handed to faer.
    pub symbolic: SymbolicSparseColMat<usize>,
    /// For face `f` and ordered corner pair `(a, b)`, `face_slots[f][3a + b]` is the base index
    /// of the block at row vertex `tri[a]`, column vertex `tri[b]`.
    pub face_slots: Vec<[usize; 9]>,
    /// Base index of each vertex's diagonal block.
    diagonal_slots: Vec<usize>,
}

impl BlockPattern {
    pub fn new(n_vertices: usize, triangles: &[[usize; 3]], block: usize) -> Self {
        // Neighbour lists (sorted, deduplicated, diagonal included).
        let mut neighbours: Vec<Vec<usize>> = (0..n_vertices).map(|v| vec![v]).collect();
        for tri in triangles {
            for a in 0..3 {
                for b in 0..3 {
                    if a != b {
                        neighbours[tri[b]].push(tri[a]);
                    }
                }
            }
        }
        let mut vertex_col_ptr = Vec::with_capacity(n_vertices + 1);
        let mut vertex_row_idx = Vec::new();
        vertex_col_ptr.push(0);
        for list in &mut neighbours {
            list.sort_unstable();
            list.dedup();
            vertex_row_idx.extend_from_slice(list);
            vertex_col_ptr.push(vertex_row_idx.len());
        }
        drop(neighbours);

        let b = block;
        let n = b * n_vertices;
        let mut col_ptr = Vec::with_capacity(n + 1);
        let mut row_idx = Vec::with_capacity(b * b * vertex_row_idx.len());
        col_ptr.push(0);
        for j in 0..n_vertices {
            let rows = &vertex_row_idx[vertex_col_ptr[j]..vertex_col_ptr[j + 1]];
            for _rj in 0..b {
                for &i in rows {
                    for ri in 0..b {
                        row_idx.push(b * i + ri);
                    }
                }
                col_ptr.push(row_idx.len());
            }
        }
        let symbolic = SymbolicSparseColMat::new_checked(n, n, col_ptr, None, row_idx);

        let mut pattern = BlockPattern {
            block,
            vertex_col_ptr,
            vertex_row_idx,
            symbolic,
            face_slots: Vec::with_capacity(triangles.len()),
            diagonal_slots: Vec::with_capacity(n_vertices),
        };
        for v in 0..n_vertices {
            let slot = pattern.block_slot(v, v);
            pattern.diagonal_slots.push(slot);
        }
        for tri in triangles {
            let mut slots = [0usize; 9];
            for a in 0..3 {
                for bb in 0..3 {
                    slots[3 * a + bb] = pattern.block_slot(tri[a], tri[bb]);
                }
            }
            pattern.face_slots.push(slots);
        }
        pattern
    }

    /// Base index of the block at row vertex `i`, column vertex `j` (which must be adjacent).
    fn block_slot(&self, i: usize, j: usize) -> usize {
        let (start, end) = (self.vertex_col_ptr[j], self.vertex_col_ptr[j + 1]);
        let k = self.vertex_row_idx[start..end]
            .binary_search(&i)
            .expect("every face's vertex pairs are in the pattern by construction");
        self.block * self.block * start + self.block * k
    }

    /// The vertex graph (CSC, sorted, diagonal included): column pointers and rows.
    pub fn vertex_graph(&self) -> (&[usize], &[usize]) {
        (&self.vertex_col_ptr, &self.vertex_row_idx)
    }

    /// Vertex pairs (neighbours and diagonal) in the pattern: the range of
    /// [`BlockPattern::pair_index`].
    pub fn vertex_nnz(&self) -> usize {
        self.vertex_row_idx.len()
    }

    /// The position of the vertex pair whose block has base index `slot` in column vertex `j`
    /// among all vertex pairs: a dense index for per-pair tables.
    pub fn pair_index(&self, slot: usize, j: usize) -> usize {
        let start = self.vertex_col_ptr[j];
        start + (slot - self.block * self.block * start) / self.block
    }

    /// Base index of the diagonal block of vertex `v`.
    #[inline]
    pub fn diagonal_slot(&self, v: usize) -> usize {
        self.diagonal_slots[v]
    }

    /// Distance between consecutive columns of a block in column vertex `j`: entry
    /// `(ri, rj)` of a block with base index `slot` is at `slot + rj · stride + ri`.
    #[inline]
    pub fn column_stride(&self, j: usize) -> usize {
        self.block * (self.vertex_col_ptr[j + 1] - self.vertex_col_ptr[j])
    }

    /// Index of entry `(ri, rj)` of the block whose base index is `slot` in column vertex `j`.
    #[inline]
    pub fn entry(&self, slot: usize, j: usize, ri: usize, rj: usize) -> usize {
        let degree = self.vertex_col_ptr[j + 1] - self.vertex_col_ptr[j];
        slot + rj * self.block * degree + ri
    }

    pub fn nnz(&self) -> usize {
        self.symbolic.row_idx().len()
    }

    pub fn dim(&self) -> usize {
        self.symbolic.nrows()
    }

    /// A fill-reducing ordering of the vertex graph (AMD or nested dissection, see
    /// [`Ordering::for_vertices`]), expanded to blocks. Same fill as ordering the expanded
    /// pattern at a fraction of the symbolic cost (docs/solver.md).
    pub(super) fn block_order(
        &self,
        ordering: Ordering,
    ) -> Result<(Vec<usize>, Vec<usize>), OrderingError> {
        let (fwd, _) = self.vertex_order(ordering)?;
        Ok(self.expand_order(&fwd))
    }

    /// A fill-reducing ordering `(fwd, inv)` of the vertex graph alone: every pattern of the
    /// same mesh shares it ([`Cholesky::analyze_with_vertex_order`](super::Cholesky::analyze_with_vertex_order)), so a flow that factors
    /// several matrices orders its graph once.
    pub fn vertex_order(
        &self,
        ordering: Ordering,
    ) -> Result<(Vec<usize>, Vec<usize>), OrderingError> {
        ordering::order(ordering, &self.vertex_col_ptr, &self.vertex_row_idx)
    }

    /// A vertex ordering expanded to this pattern's blocks.
    pub(super) fn expand_order(&self, fwd: &[usize]) -> (Vec<usize>, Vec<usize>) {
        let nv = self.vertex_col_ptr.len() - 1;
        let b = self.block;
        let mut fwd_b = vec![0usize; b * nv];
        let mut inv_b = vec![0usize; b * nv];
        for k in 0..nv {
            for r in 0..b {
                fwd_b[b * k + r] = b * fwd[k] + r;
                inv_b[b * fwd[k] + r] = b * k + r;
            }
        }
        (fwd_b, inv_b)
    }
}

/// Refill `values` (on a block-1 `pattern`) with the PSD cotan Laplacian scaled by `scale`:
/// each corner with cotangent `c` adds `scale·c/2` to the diagonal entries of its opposite
/// edge's ends and subtracts it from the two off-diagonal entries.
pub fn assemble_cotan_laplacian_into(
    pattern: &BlockPattern,
    triangles: &[[usize; 3]],
    cotangents: &[[f64; 3]],
    scale: f64,
    values: &mut [f64],
) {
    values.fill(0.0);
    for ((tri, cots), slots) in triangles.iter().zip(cotangents).zip(&pattern.face_slots) {
        for c in 0..3 {
            let (a, b) = ((c + 1) % 3, (c + 2) % 3);
            let w = 0.5 * scale * cots[c];
            values[pattern.entry(slots[3 * a + b], tri[b], 0, 0)] -= w;
            values[pattern.entry(slots[3 * b + a], tri[a], 0, 0)] -= w;
            values[pattern.entry(slots[3 * a + a], tri[a], 0, 0)] += w;
            values[pattern.entry(slots[3 * b + b], tri[b], 0, 0)] += w;
        }
    }
}

/// Add `diagonal[v]` to the diagonal entry of every vertex `v` (block-1 pattern).
pub fn add_diagonal(
    pattern: &BlockPattern,
    diagonal: impl Iterator<Item = f64>,
    values: &mut [f64],
) {
    for (v, d) in diagonal.enumerate() {
        values[pattern.entry(pattern.diagonal_slot(v), v, 0, 0)] += d;
    }
}
