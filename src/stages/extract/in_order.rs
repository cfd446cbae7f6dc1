//! An in-order parallel map: workers compute pieces ahead (a bounded window) while one
//! consumer takes them strictly in item order.

use crate::store::{Result, StoreError};

/// Hands `consume` the results of `compute(item)` for every item, as an iterator in item
/// order, while `threads` workers compute the next ones: at most `window` results exist at
/// once (the one being consumed included), so memory stays bounded, and consuming overlaps
/// computing. The order does not depend on the workers' timing.
pub(super) fn in_order_while_computing<I: Copy + Send + Sync, T: Send, R>(
    items: &[I],
    threads: usize,
    window: usize,
    compute: impl Fn(I) -> Result<T> + Sync,
    consume: impl FnOnce(&mut dyn Iterator<Item = Result<T>>) -> R,
) -> R {
    let window = window.max(2);
    let shared = InOrder {
        state: std::sync::Mutex::new(InOrderState {
            next_item: 0,
            taken: 0,
            done: std::collections::BTreeMap::new(),
            stop: false,
            worker_panicked: false,
        }),
        changed: std::sync::Condvar::new(),
    };
    std::thread::scope(|scope| {
        for _ in 0..threads {
            scope.spawn(|| {
                let _guard = PanicFlag(&shared);
                while let Some(index) = shared.claim(items.len(), window) {
                    let Some(&item) = items.get(index) else {
                        break;
                    };
                    let result = compute(item);
                    shared.lock().done.insert(index, result);
                    shared.changed.notify_all();
                }
            });
        }
        let mut pieces = InOrderPieces {
            shared: &shared,
            count: items.len(),
        };
        consume(&mut pieces)
    })
}

struct InOrder<T> {
    state: std::sync::Mutex<InOrderState<T>>,
    changed: std::sync::Condvar,
}

struct InOrderState<T> {
    /// The next item a worker may claim.
    next_item: usize,
    /// Pieces handed to the consumer so far; piece `taken - 1` may still be in use.
    taken: usize,
    done: std::collections::BTreeMap<usize, Result<T>>,
    stop: bool,
    worker_panicked: bool,
}

impl<T> InOrder<T> {
    /// The state; a worker that panicked holds no lock across its work, so a poisoned lock
    /// still holds consistent state.
    fn lock(&self) -> std::sync::MutexGuard<'_, InOrderState<T>> {
        self.state.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// The next item for a worker, once it is within `window` of the consumer; `None` when
    /// all are claimed or the consumer has stopped.
    fn claim(&self, count: usize, window: usize) -> Option<usize> {
        let mut state = self.lock();
        loop {
            if state.stop || state.next_item >= count {
                return None;
            }
            // Pieces taken - 1 (in use) up to next_item must number at most `window`.
            if state.next_item + 1 < state.taken + window {
                state.next_item += 1;
                return Some(state.next_item - 1);
            }
            state = self
                .changed
                .wait(state)
                .unwrap_or_else(std::sync::PoisonError::into_inner);
        }
    }
}

/// Sets the worker-panicked flag when a worker unwinds, so the consumer does not wait forever.
struct PanicFlag<'a, T>(&'a InOrder<T>);

impl<T> Drop for PanicFlag<'_, T> {
    fn drop(&mut self) {
        if std::thread::panicking() {
            let mut state = self.0.lock();
            state.worker_panicked = true;
            state.stop = true;
            drop(state);
            self.0.changed.notify_all();
        }
    }
}

/// The consumer's side: pieces in item order. Dropping it stops the workers.
struct InOrderPieces<'a, T> {
    shared: &'a InOrder<T>,
    count: usize,
}

impl<T> Iterator for InOrderPieces<'_, T> {
    type Item = Result<T>;

    fn next(&mut self) -> Option<Result<T>> {
        let mut state = self.shared.lock();
        loop {
            let taken = state.taken;
            if let Some(piece) = state.done.remove(&taken) {
                state.taken += 1;
                drop(state);
                self.shared.changed.notify_all();
                return Some(piece);
            }
            if state.worker_panicked {
                return Some(Err(StoreError::Stage {
                    stage: "extract".into(),
                    unit: taken.to_string(),
                    message: "a worker thread panicked".into(),
                }));
            }
            if taken >= self.count {
                return None;
            }
            state = self
                .shared
                .changed
                .wait(state)
                .unwrap_or_else(std::sync::PoisonError::into_inner);
        }
    }
}

impl<T> Drop for InOrderPieces<'_, T> {
    fn drop(&mut self) {
        self.shared.lock().stop = true;
        self.shared.changed.notify_all();
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicUsize, Ordering};

    use super::*;

    /// Counts the pieces alive at once.
    struct Piece<'a> {
        item: usize,
        alive: &'a AtomicUsize,
    }

    impl Drop for Piece<'_> {
        fn drop(&mut self) {
            self.alive.fetch_sub(1, Ordering::SeqCst);
        }
    }

    #[test]
    fn pieces_come_in_item_order_and_at_most_a_window_exist_at_once() {
        let items: Vec<usize> = (0..300).collect();
        let (alive, most) = (AtomicUsize::new(0), AtomicUsize::new(0));
        let window = 4;
        let compute = |item: usize| -> Result<Piece<'_>> {
            let now = alive.fetch_add(1, Ordering::SeqCst) + 1;
            most.fetch_max(now, Ordering::SeqCst);
            // Uneven work, so pieces finish out of order.
            std::thread::sleep(std::time::Duration::from_micros((item * 7919 % 13) as u64 * 50));
            Ok(Piece { item, alive: &alive })
        };
        let seen = in_order_while_computing(&items, 3, window, compute, |pieces| {
            pieces.map(|piece| piece.map(|p| p.item)).collect::<Result<Vec<_>>>()
        })
        .expect("no piece fails");
        assert_eq!(seen, items);
        let most = most.load(Ordering::SeqCst);
        assert!(most <= window, "{most} pieces existed at once, window {window}");
        assert_eq!(alive.load(Ordering::SeqCst), 0);
    }

    #[test]
    fn a_failed_piece_ends_the_stream_with_its_error() {
        let items: Vec<usize> = (0..100).collect();
        let compute = |item: usize| -> Result<usize> {
            if item == 37 {
                return Err(StoreError::Stage {
                    stage: "extract".into(),
                    unit: item.to_string(),
                    message: "bad unit".into(),
                });
            }
            Ok(item)
        };
        let (before, error) = in_order_while_computing(&items, 2, 4, compute, |pieces| {
            let mut before = Vec::new();
            for piece in pieces {
                match piece {
                    Ok(item) => before.push(item),
                    Err(error) => return (before, Some(error.to_string())),
                }
            }
            (before, None)
        });
        assert_eq!(before, (0..37).collect::<Vec<_>>());
        assert!(error.is_some_and(|e| e.contains("bad unit")));
    }
}
