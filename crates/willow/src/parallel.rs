//! Two pieces of work on two threads, or on one (the symbolic analyses of X and L in a flow's
//! setup, the BVH's halves and the distance measure's two sides). The library's other
//! threads are the factorization's subtrees (`linalg::supernodal`, a `std::thread::scope`)
//! and the ordering that runs beside a flow's setup (`linalg::ordering::Pending`, joined
//! before the setup returns). A [`crate::flow::Flow`] still owns no threads between calls:
//! every thread is joined before the call that started it returns.

/// `(a(), b())`, on two threads when `parallel` (a panic in either is re-raised here, as it
/// would be sequentially).
pub(crate) fn join<A: Send, B: Send>(
    parallel: bool,
    a: impl FnOnce() -> A + Send,
    b: impl FnOnce() -> B + Send,
) -> (A, B) {
    if !parallel {
        return (a(), b());
    }
    std::thread::scope(|scope| {
        let first = scope.spawn(a);
        let second = b();
        match first.join() {
            Ok(first) => (first, second),
            Err(panic) => std::panic::resume_unwind(panic),
        }
    })
}

#[cfg(test)]
mod tests {
    use super::join;

    #[test]
    fn join_returns_both_results_in_order_either_way() {
        for parallel in [false, true] {
            let (a, b) = join(parallel, || 1 + 1, || "two".len());
            assert_eq!((a, b), (2, 3));
        }
    }

    #[test]
    fn a_panic_on_the_spawned_side_reaches_the_caller() {
        let caught = std::panic::catch_unwind(|| {
            join(true, || panic!("left side"), || 0);
        });
        assert!(caught.is_err());
    }
}
