//! Fill-reducing orderings of a mesh's vertex graph, for the sparse Cholesky factorizations.
//!
//! Every matrix the flows factor lives on the vertex graph (one vertex ring per column), so one
//! vertex ordering, expanded to the matrix's blocks, serves the Laplacian and the Dirac matrix
//! alike (docs/solver.md: AMD on the vertex graph gives the same fill as AMD on the expanded pattern
//! at half the symbolic cost).
//!
//! Two orderings, chosen by size ([`Ordering::for_vertices`]): approximate minimum degree
//! (faer's) and nested dissection (METIS). On a surface mesh, nested dissection's separators are
//! curves of O(√n) vertices, so the factor of an n-vertex mesh has O(n log n) entries and costs
//! O(n^1.5) flops; minimum degree has no such bound and, measured on the bumpy icosphere, its
//! factor grows much faster (see [`ND_MIN_VERTICES`]).

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::sparse::linalg::amd;
use faer::sparse::SymbolicSparseColMatRef;

/// How the vertex graph is ordered before the symbolic factorization.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Ordering {
    /// faer's approximate minimum degree.
    Amd,
    /// METIS nested dissection (`METIS_NodeND`).
    NestedDissection,
}

/// From this many vertices on, nested dissection orders the vertex graph. Measured with
/// `willow bench` on the Dirac matrix (complex, 2|V|) of cheburashka (6.7k vertices), nefertiti
/// (50k) and bumpy icospheres of 41k, 164k and 655k vertices: see the figures in the issue-14
/// closing note; below this size AMD's factor is as small and AMD itself is cheaper.
pub const ND_MIN_VERTICES: usize = 20_000;

impl Ordering {
    /// The ordering that measured best for a vertex graph of `n` vertices.
    pub fn for_vertices(n: usize) -> Self {
        if n >= ND_MIN_VERTICES {
            Ordering::NestedDissection
        } else {
            Ordering::Amd
        }
    }
}

/// Why an ordering could not be computed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum OrderingError {
    #[error("out of memory for the ordering")]
    OutOfMemory,
    #[error("the graph is too large for METIS's 32-bit indices")]
    TooLarge,
    #[error("METIS failed with status {0}")]
    Metis(i32),
    #[error("AMD failed: {0}")]
    Amd(String),
}

/// A fill-reducing ordering `(fwd, inv)` of the symmetric graph whose adjacency is the CSC
/// pattern `col_ptr`/`row_idx` (diagonal entries allowed, rows sorted or not): `fwd[new] = old`
/// and `inv[old] = new`.
pub fn order(
    ordering: Ordering,
    col_ptr: &[usize],
    row_idx: &[usize],
) -> Result<(Vec<usize>, Vec<usize>), OrderingError> {
    match ordering {
        Ordering::Amd => minimum_degree(col_ptr, row_idx),
        Ordering::NestedDissection => {
            let (fwd, inv) = nested_dissection(col_ptr, row_idx)?;
            Ok(postorder(col_ptr, row_idx, &fwd, &inv))
        }
    }
}

/// The same elimination (same fill, same operations) in postorder of its elimination tree:
/// every subtree becomes a contiguous range of columns, which the parallel factorization
/// needs to hand each thread its own part of the factor (METIS's orders are topological,
/// children before parents, but interleave subtrees).
pub fn postorder(
    col_ptr: &[usize],
    row_idx: &[usize],
    fwd: &[usize],
    inv: &[usize],
) -> (Vec<usize>, Vec<usize>) {
    const NONE: usize = usize::MAX;
    let n = fwd.len();
    // Liu's elimination tree with path compression, in the permuted numbering.
    let mut parent = vec![NONE; n];
    let mut ancestor = vec![NONE; n];
    for k in 0..n {
        let old = fwd[k];
        for &old_i in &row_idx[col_ptr[old]..col_ptr[old + 1]] {
            let mut r = inv[old_i];
            if r >= k {
                continue;
            }
            while ancestor[r] != NONE && ancestor[r] != k {
                let next = ancestor[r];
                ancestor[r] = k;
                r = next;
            }
            if ancestor[r] == NONE {
                ancestor[r] = k;
                parent[r] = k;
            }
        }
    }
    // Children lists (ascending), then an iterative depth-first postorder from the roots.
    let mut child_ptr = vec![0usize; n + 1];
    for &p in &parent {
        if p != NONE {
            child_ptr[p + 1] += 1;
        }
    }
    for k in 0..n {
        child_ptr[k + 1] += child_ptr[k];
    }
    let mut next = child_ptr.clone();
    let mut children = vec![0usize; child_ptr[n]];
    for (k, &p) in parent.iter().enumerate() {
        if p != NONE {
            children[next[p]] = k;
            next[p] += 1;
        }
    }
    let mut order = Vec::with_capacity(n);
    let mut stack: Vec<(usize, usize)> = Vec::new();
    for root in (0..n).filter(|&k| parent[k] == NONE) {
        stack.push((root, child_ptr[root]));
        while let Some((node, cursor)) = stack.last_mut() {
            if *cursor < child_ptr[*node + 1] {
                let child = children[*cursor];
                *cursor += 1;
                stack.push((child, child_ptr[child]));
            } else {
                order.push(*node);
                stack.pop();
            }
        }
    }
    let new_fwd: Vec<usize> = order.iter().map(|&k| fwd[k]).collect();
    let mut new_inv = vec![0usize; n];
    for (new, &old) in new_fwd.iter().enumerate() {
        new_inv[old] = new;
    }
    (new_fwd, new_inv)
}

/// An ordering computed on a thread of its own while the caller does other setup work (or
/// at once, on the caller's thread, when it has no thread to spare).
pub enum Pending {
    Running(std::thread::JoinHandle<OrderResult>),
    Done(OrderResult),
}

/// A permutation `(fwd, inv)`, or why there is none.
pub type OrderResult = Result<(Vec<usize>, Vec<usize>), OrderingError>;

impl Pending {
    /// Start ordering the graph `col_ptr`/`row_idx` (owned: the thread outlives no borrow).
    pub fn start(
        ordering: Ordering,
        col_ptr: Vec<usize>,
        row_idx: Vec<usize>,
        spawn: bool,
    ) -> Self {
        if !spawn {
            return Pending::Done(order(ordering, &col_ptr, &row_idx));
        }
        Pending::Running(std::thread::spawn(move || {
            order(ordering, &col_ptr, &row_idx)
        }))
    }

    /// The ordering (waits for the thread).
    pub fn finish(self) -> OrderResult {
        match self {
            Pending::Done(result) => result,
            Pending::Running(handle) => handle
                .join()
                .unwrap_or_else(|panic| std::panic::resume_unwind(panic)),
        }
    }
}

/// faer's approximate minimum degree.
pub fn minimum_degree(
    col_ptr: &[usize],
    row_idx: &[usize],
) -> Result<(Vec<usize>, Vec<usize>), OrderingError> {
    let n = col_ptr.len().saturating_sub(1);
    let graph = SymbolicSparseColMatRef::new_checked(n, n, col_ptr, None, row_idx);
    let mut fwd = vec![0usize; n];
    let mut inv = vec![0usize; n];
    let mut mem = MemBuffer::try_new(amd::order_scratch::<usize>(n, row_idx.len()))
        .map_err(|_| OrderingError::OutOfMemory)?;
    amd::order(
        &mut fwd,
        &mut inv,
        graph,
        amd::Control::default(),
        MemStack::new(&mut mem),
    )
    .map_err(|e| OrderingError::Amd(format!("{e:?}")))?;
    Ok((fwd, inv))
}

/// METIS keeps its random-number state (GKlib's Mersenne twister, `random.c`) in plain
/// process-wide statics, not thread-locals: two concurrent `METIS_NodeND` calls race on it,
/// so each gets a different sequence (a different ordering, different rounding in every
/// factorization) and the race itself is undefined behaviour (its index can step past the
/// state array). Every call holds this lock; it serializes only the ordering, which is a few
/// seconds at the largest meshes, while the factorizations of concurrent jobs still overlap.
static METIS: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// METIS nested dissection (`METIS_NodeND`) with its default options and a fixed seed, so the
/// same mesh always gets the same ordering (and the same rounding in every factorization),
/// whatever other threads order at the same time (see the `METIS` lock).
pub fn nested_dissection(
    col_ptr: &[usize],
    row_idx: &[usize],
) -> Result<(Vec<usize>, Vec<usize>), OrderingError> {
    use metis_sys as m;
    let n = col_ptr.len().saturating_sub(1);
    if n == 0 {
        return Ok((Vec::new(), Vec::new()));
    }
    let too_large = |_| OrderingError::TooLarge;
    // METIS wants the adjacency without self loops.
    let mut xadj: Vec<m::idx_t> = Vec::with_capacity(n + 1);
    let mut adjncy: Vec<m::idx_t> = Vec::with_capacity(row_idx.len());
    xadj.push(0);
    for j in 0..n {
        for &i in &row_idx[col_ptr[j]..col_ptr[j + 1]] {
            if i != j {
                adjncy.push(m::idx_t::try_from(i).map_err(too_large)?);
            }
        }
        xadj.push(m::idx_t::try_from(adjncy.len()).map_err(too_large)?);
    }
    let mut nvtxs = m::idx_t::try_from(n).map_err(too_large)?;
    let mut options = [0 as m::idx_t; m::METIS_NOPTIONS as usize];
    let mut perm: Vec<m::idx_t> = vec![0; n];
    let mut iperm: Vec<m::idx_t> = vec![0; n];
    // A panic elsewhere while holding the lock leaves no METIS state half-written that the
    // next call reads before reseeding, so a poisoned lock is still usable.
    let _only_caller = METIS
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    // SAFETY: `options` has METIS_NOPTIONS entries; `xadj` has n + 1 entries ending at
    // `adjncy.len()`, every `adjncy` entry is a vertex index below n (taken from a pattern of
    // n columns), and `perm`/`iperm` have n entries each, as METIS_NodeND requires. vwgt is
    // null (unit weights). METIS keeps no pointer past the call.
    let status = unsafe {
        m::METIS_SetDefaultOptions(options.as_mut_ptr());
        options[m::moptions_et_METIS_OPTION_SEED as usize] = 1;
        m::METIS_NodeND(
            &mut nvtxs,
            xadj.as_mut_ptr(),
            adjncy.as_mut_ptr(),
            std::ptr::null_mut(),
            options.as_mut_ptr(),
            perm.as_mut_ptr(),
            iperm.as_mut_ptr(),
        )
    };
    if status != m::rstatus_et_METIS_OK {
        return Err(OrderingError::Metis(status));
    }
    // METIS: row i of the permuted matrix is row perm[i] of the original.
    let fwd: Vec<usize> = perm.iter().map(|&p| p as usize).collect();
    let mut inv = vec![0usize; n];
    for (new, &old) in fwd.iter().enumerate() {
        if old >= n {
            return Err(OrderingError::Metis(m::rstatus_et_METIS_ERROR));
        }
        inv[old] = new;
    }
    Ok((fwd, inv))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The vertex graph of a `k × k` grid (4-neighbours), diagonal included.
    fn grid(k: usize) -> (Vec<usize>, Vec<usize>) {
        let mut col_ptr = vec![0];
        let mut row_idx = Vec::new();
        for y in 0..k {
            for x in 0..k {
                let mut rows = vec![y * k + x];
                if x > 0 {
                    rows.push(y * k + x - 1);
                }
                if x + 1 < k {
                    rows.push(y * k + x + 1);
                }
                if y > 0 {
                    rows.push((y - 1) * k + x);
                }
                if y + 1 < k {
                    rows.push((y + 1) * k + x);
                }
                rows.sort_unstable();
                row_idx.extend(rows);
                col_ptr.push(row_idx.len());
            }
        }
        (col_ptr, row_idx)
    }

    fn is_permutation(fwd: &[usize], inv: &[usize]) -> bool {
        fwd.len() == inv.len() && fwd.iter().enumerate().all(|(new, &old)| inv[old] == new)
    }

    /// In postorder every vertex's elimination-tree parent comes after it and every subtree
    /// is contiguous: checked through the tree of the postordered grid, which is its own
    /// postorder (each subtree ends at its root and starts at its first descendant).
    #[test]
    fn postorder_makes_subtrees_contiguous() {
        let (col_ptr, row_idx) = grid(25);
        let (fwd, inv) = nested_dissection(&col_ptr, &row_idx).expect("ordering");
        let (fwd, inv) = postorder(&col_ptr, &row_idx, &fwd, &inv);
        assert!(is_permutation(&fwd, &inv));
        // Postordering a postorder is the identity.
        let (again, _) = postorder(&col_ptr, &row_idx, &fwd, &inv);
        assert_eq!(again, fwd);
    }

    #[test]
    fn both_orderings_are_permutations() {
        let (col_ptr, row_idx) = grid(30);
        for ordering in [Ordering::Amd, Ordering::NestedDissection] {
            let (fwd, inv) = order(ordering, &col_ptr, &row_idx).expect("ordering");
            assert!(is_permutation(&fwd, &inv), "{ordering:?}");
        }
    }

    /// Threads ordering at the same time get the ordering one thread alone gets (METIS's
    /// random state is process-wide; without the lock this failed within a few rounds).
    #[test]
    fn concurrent_nested_dissections_give_the_sequential_ordering() {
        let (col_ptr, row_idx) = grid(60);
        let (alone, _) = nested_dissection(&col_ptr, &row_idx).expect("ordering");
        std::thread::scope(|scope| {
            let handles: Vec<_> = (0..4)
                .map(|_| {
                    scope.spawn(|| {
                        (0..10)
                            .map(|_| nested_dissection(&col_ptr, &row_idx).expect("ordering").0)
                            .collect::<Vec<_>>()
                    })
                })
                .collect();
            for handle in handles {
                for fwd in handle.join().expect("thread") {
                    assert!(fwd == alone, "a concurrent ordering differs");
                }
            }
        });
    }

    /// Nested dissection of a grid puts a separator last: the last vertices in the order split
    /// the grid, so removing them leaves it disconnected.
    #[test]
    fn nested_dissection_orders_a_separator_last() {
        let k = 40;
        let (col_ptr, row_idx) = grid(k);
        let (fwd, _) = nested_dissection(&col_ptr, &row_idx).expect("ordering");
        // The top separator of a 40 × 40 grid is a line of about 40 vertices.
        let removed: std::collections::HashSet<usize> =
            fwd[fwd.len() - k..].iter().copied().collect();
        let start = (0..k * k)
            .find(|v| !removed.contains(v))
            .expect("a vertex is left");
        let mut seen = vec![false; k * k];
        let mut stack = vec![start];
        seen[start] = true;
        while let Some(v) = stack.pop() {
            for &u in &row_idx[col_ptr[v]..col_ptr[v + 1]] {
                if !seen[u] && !removed.contains(&u) {
                    seen[u] = true;
                    stack.push(u);
                }
            }
        }
        let reached = seen.iter().filter(|&&s| s).count();
        assert!(
            reached < k * k - removed.len(),
            "the last {k} vertices do not separate the grid ({reached} of {} reached)",
            k * k - removed.len()
        );
    }
}
