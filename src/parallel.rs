//! Independent parts of one computation run on the machine's cores: scoped threads, the
//! results in the parts' order, so that a threaded run computes exactly what a serial one does.

/// Threads for work that splits into independent parts: the machine's cores, at most `cap`.
pub fn threads(cap: usize) -> usize {
    std::thread::available_parallelism().map_or(1, |t| t.get().min(cap))
}

/// Runs `job` on every part, the first on this thread and the others on their own; the
/// results in the parts' order.
pub fn in_parallel<P: Send, R: Send>(parts: Vec<P>, job: impl Fn(P) -> R + Sync) -> Vec<R> {
    let mut parts = parts.into_iter();
    let Some(first) = parts.next() else {
        return Vec::new();
    };
    let job = &job;
    std::thread::scope(|scope| {
        let others: Vec<_> = parts.map(|p| scope.spawn(move || job(p))).collect();
        let mut results = vec![job(first)];
        for handle in others {
            match handle.join() {
                Ok(r) => results.push(r),
                Err(panic) => std::panic::resume_unwind(panic),
            }
        }
        results
    })
}

/// `here` on this thread and `beside` on its own at the same time; both results.
pub fn join<A, B: Send>(here: impl FnOnce() -> A, beside: impl FnOnce() -> B + Send) -> (A, B) {
    std::thread::scope(|scope| {
        let other = scope.spawn(beside);
        let a = here();
        match other.join() {
            Ok(b) => (a, b),
            Err(panic) => std::panic::resume_unwind(panic),
        }
    })
}

/// `job` on every item, the items in at most `threads` consecutive groups each on its own
/// thread; the results in the items' order.
pub fn in_groups<T: Sync, R: Send>(
    items: &[T],
    threads: usize,
    job: impl Fn(&T) -> R + Sync,
) -> Vec<R> {
    let mut groups = Vec::new();
    let mut rest = items;
    for size in balanced_groups(items.len(), threads) {
        let (group, tail) = rest.split_at(size);
        groups.push(group);
        rest = tail;
    }
    in_parallel(groups, |group| group.iter().map(&job).collect::<Vec<_>>())
        .into_iter()
        .flatten()
        .collect()
}

/// [`in_groups`] on owned items: `job` takes each item by value.
pub fn in_groups_owned<T: Send, R: Send>(
    items: Vec<T>,
    threads: usize,
    job: impl Fn(T) -> R + Sync,
) -> Vec<R> {
    let mut groups = Vec::new();
    let mut rest = items.into_iter();
    for size in balanced_groups(rest.len(), threads) {
        groups.push(rest.by_ref().take(size).collect::<Vec<T>>());
    }
    in_parallel(groups, |group| {
        group.into_iter().map(&job).collect::<Vec<_>>()
    })
    .into_iter()
    .flatten()
    .collect()
}

/// Positions 0..n in consecutive blocks of `size` (the last one shorter).
pub fn position_blocks(n: usize, size: usize) -> impl Iterator<Item = Vec<usize>> {
    (0..n)
        .step_by(size.max(1))
        .map(move |first| (first..(first + size).min(n)).collect())
}

/// Splits `data` into consecutive pieces of the given lengths.
pub fn split_lengths<T>(mut data: &mut [T], lengths: impl Iterator<Item = usize>) -> Vec<&mut [T]> {
    let mut pieces = Vec::new();
    for len in lengths {
        let (piece, rest) = data.split_at_mut(len);
        pieces.push(piece);
        data = rest;
    }
    pieces
}

/// `count` items in at most `parts` consecutive groups of nearly equal size (none empty).
pub fn balanced_groups(count: usize, parts: usize) -> Vec<usize> {
    let parts = parts.clamp(1, count.max(1));
    (0..parts)
        .map(|k| (k + 1) * count / parts - k * count / parts)
        .filter(|&size| size > 0)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn groups_cover_every_item_once() {
        for count in 0..20 {
            for parts in 1..6 {
                let groups = balanced_groups(count, parts);
                assert_eq!(groups.iter().sum::<usize>(), count);
                assert!(groups.len() <= parts);
                assert!(groups.iter().all(|&g| g > 0));
            }
        }
    }

    #[test]
    fn join_gives_each_side_its_own_result_and_passes_a_panic_on() {
        let mut here_ran = false;
        let (a, b) = join(
            || {
                here_ran = true;
                std::thread::current().id()
            },
            || std::thread::current().id(),
        );
        assert!(here_ran);
        assert_eq!(a, std::thread::current().id());
        assert_ne!(b, a);
        let caught = std::panic::catch_unwind(|| join(|| 1, || -> i32 { panic!("beside") }));
        assert!(caught.is_err());
    }

    #[test]
    fn results_come_in_the_parts_order() {
        let out = in_parallel((0..7).collect(), |k: usize| k * k);
        assert_eq!(out, vec![0, 1, 4, 9, 16, 25, 36]);
        let items: Vec<usize> = (0..17).collect();
        for threads in 1..5 {
            let out = in_groups(&items, threads, |k| k * k);
            assert_eq!(out, items.iter().map(|k| k * k).collect::<Vec<_>>());
        }
    }
}
