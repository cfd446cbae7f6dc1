//! An in-order parallel map: workers compute pieces ahead (a bounded window) while one
//! consumer takes them strictly in item order.

use std::sync::atomic::{AtomicU64, Ordering};

use crate::store::StageError;
use crate::store::{Result, StoreError};

/// How far workers may run ahead of the consumer: at most `pieces` results exist at once (the
/// one being consumed included), and a worker claims a new item only while the finished
/// results that wait hold less than [`Window::allowed`]: `bytes` less what the consumer asks
/// them to give way to (`yielded`, which it may change at any time), but never less than
/// `least`. The item the consumer waits for is always claimable. So at most `bytes` plus one
/// result per worker wait, whatever the pieces' sizes.
#[derive(Clone, Copy, Debug)]
pub(super) struct Window<'a> {
    pub pieces: usize,
    pub bytes: u64,
    pub yielded: &'a AtomicU64,
    pub least: u64,
}

impl Window<'_> {
    /// What the waiting results may hold now.
    fn allowed(&self) -> u64 {
        let yielded = self.yielded.load(Ordering::Relaxed);
        self.bytes.saturating_sub(yielded).max(self.least.min(self.bytes))
    }
}

/// Hands `consume` the results of `compute(item)` for every item, as an iterator in item
/// order, while `threads` workers compute the next ones within `window` (each result's size as
/// `weigh` gives it), so memory stays bounded, and consuming overlaps computing. The order
/// does not depend on the workers' timing.
pub(super) fn in_order_while_computing<I: Copy + Send + Sync, T: Send, R>(
    items: &[I],
    threads: usize,
    window: Window<'_>,
    weigh: impl Fn(&T) -> u64 + Sync,
    compute: impl Fn(I) -> Result<T> + Sync,
    consume: impl FnOnce(&mut dyn Iterator<Item = Result<T>>) -> R,
) -> R {
    let window = Window {
        pieces: window.pieces.max(2),
        ..window
    };
    let shared = InOrder {
        state: std::sync::Mutex::new(InOrderState {
            next_item: 0,
            taken: 0,
            done: std::collections::BTreeMap::new(),
            waiting_bytes: 0,
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
                    let bytes = result.as_ref().map_or(0, &weigh);
                    let mut state = shared.lock();
                    state.waiting_bytes += bytes;
                    state.done.insert(index, (result, bytes));
                    drop(state);
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
    /// Finished results not yet taken, with their sizes.
    done: std::collections::BTreeMap<usize, (Result<T>, u64)>,
    /// The sum of `done`'s sizes.
    waiting_bytes: u64,
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
    /// all are claimed or the consumer has stopped. The item the consumer waits for is always
    /// claimable (no result after it can be waiting then), so the stream cannot stall.
    fn claim(&self, count: usize, window: Window<'_>) -> Option<usize> {
        let mut state = self.lock();
        loop {
            if state.stop || state.next_item >= count {
                return None;
            }
            // Pieces taken - 1 (in use) up to next_item must number at most `window.pieces`.
            let within_count = state.next_item + 1 < state.taken + window.pieces;
            let within_bytes = state.waiting_bytes < window.allowed() || state.next_item <= state.taken;
            if within_count && within_bytes {
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
            if let Some((piece, bytes)) = state.done.remove(&taken) {
                state.taken += 1;
                state.waiting_bytes -= bytes;
                drop(state);
                self.shared.changed.notify_all();
                return Some(piece);
            }
            if state.worker_panicked {
                return Some(Err(StoreError::Stage {
                    stage: "extract".into(),
                    unit: taken.to_string(),
                    error: Box::new(StageError::WorkerPanicked),
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
    use std::sync::atomic::AtomicUsize;

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
        let nothing = AtomicU64::new(0);
        let window = Window {
            pieces: 4,
            bytes: u64::MAX,
            yielded: &nothing,
            least: 0,
        };
        let compute = |item: usize| -> Result<Piece<'_>> {
            let now = alive.fetch_add(1, Ordering::SeqCst) + 1;
            most.fetch_max(now, Ordering::SeqCst);
            // Uneven work, so pieces finish out of order.
            std::thread::sleep(std::time::Duration::from_micros((item * 7919 % 13) as u64 * 50));
            Ok(Piece { item, alive: &alive })
        };
        let seen = in_order_while_computing(
            &items,
            3,
            window,
            |_| 1,
            compute,
            |pieces| pieces.map(|piece| piece.map(|p| p.item)).collect::<Result<Vec<_>>>(),
        )
        .expect("no piece fails");
        assert_eq!(seen, items);
        let most = most.load(Ordering::SeqCst);
        assert!(
            most <= window.pieces,
            "{most} pieces existed at once, window {window:?}"
        );
        assert_eq!(alive.load(Ordering::SeqCst), 0);
    }

    #[test]
    fn waiting_pieces_stay_within_the_byte_window() {
        // Pieces of uneven sizes (0 to 90 bytes), the largest the slowest, against a window
        // of 100 bytes and room for 50 pieces by count: the bytes bind.
        let items: Vec<usize> = (0..400).collect();
        let weight = |item: usize| (item * 37 % 10) as u64 * 10;
        let (held, most) = (AtomicUsize::new(0), AtomicUsize::new(0));
        let nothing = AtomicU64::new(0);
        let window = Window {
            pieces: 50,
            bytes: 100,
            yielded: &nothing,
            least: 0,
        };
        let threads = 3;
        let compute = |item: usize| -> Result<usize> {
            std::thread::sleep(std::time::Duration::from_micros(weight(item) * 5));
            let bytes = weight(item) as usize;
            most.fetch_max(held.fetch_add(bytes, Ordering::SeqCst) + bytes, Ordering::SeqCst);
            Ok(item)
        };
        let seen = in_order_while_computing(
            &items,
            threads,
            window,
            |&item| weight(item),
            compute,
            |pieces| {
                pieces
                    .map(|piece| {
                        // The consumer is done with a piece when it takes the next one.
                        piece.inspect(|&item| {
                            held.fetch_sub(weight(item) as usize, Ordering::SeqCst);
                        })
                    })
                    .collect::<Result<Vec<_>>>()
            },
        )
        .expect("no piece fails");
        assert_eq!(seen, items);
        // Less than 100 bytes waited when the last claim was made, then at most one 90-byte
        // piece per worker finished, and the one the consumer is taking.
        let bound = 100 + (threads + 1) * 90;
        let most = most.load(Ordering::SeqCst);
        assert!(most < bound, "{most} bytes of pieces existed at once, bound {bound}");
        assert!(
            most >= 100,
            "the window never filled ({most} bytes): the test proves nothing"
        );
    }

    #[test]
    fn waiting_pieces_give_way_to_what_the_consumer_yields() {
        // A slow consumer and instant pieces of 10 bytes: the window fills whenever it may.
        let items: Vec<usize> = (0..400).collect();
        let yielded = AtomicU64::new(u64::MAX);
        let window = Window {
            pieces: 64,
            bytes: 1000,
            yielded: &yielded,
            least: 20,
        };
        let threads = 3;
        let held = AtomicUsize::new(0);
        let most = [AtomicUsize::new(0), AtomicUsize::new(0)];
        let half = AtomicUsize::new(0);
        let compute = |item: usize| -> Result<usize> {
            let now = held.fetch_add(10, Ordering::SeqCst) + 10;
            if let Some(most) = most.get(half.load(Ordering::SeqCst)) {
                most.fetch_max(now, Ordering::SeqCst);
            }
            Ok(item)
        };
        in_order_while_computing(
            &items,
            threads,
            window,
            |_| 10,
            compute,
            |pieces| {
                for piece in pieces {
                    let item = piece?;
                    held.fetch_sub(10, Ordering::SeqCst);
                    if item == 200 {
                        // The consumer's own state shrank: the window opens again.
                        yielded.store(0, Ordering::SeqCst);
                        half.store(1, Ordering::SeqCst);
                    }
                    std::thread::sleep(std::time::Duration::from_micros(200));
                }
                Ok::<(), StoreError>(())
            },
        )
        .expect("no piece fails");
        // While everything was yielded, fewer than `least` bytes waited at each claim (one
        // piece), and then each worker finished one more.
        let [first, second] = most.map(|m| m.load(Ordering::SeqCst));
        assert!(
            first <= 10 * (1 + threads),
            "{first} bytes waited while all was yielded"
        );
        assert!(second > 100, "only {second} bytes waited once nothing was yielded");
    }

    #[test]
    fn a_failed_piece_ends_the_stream_with_its_error() {
        let items: Vec<usize> = (0..100).collect();
        let compute = |item: usize| -> Result<usize> {
            if item == 37 {
                return Err(StoreError::Stage {
                    stage: "extract".into(),
                    unit: item.to_string(),
                    error: Box::new(StageError::internal("bad unit")),
                });
            }
            Ok(item)
        };
        let nothing = AtomicU64::new(0);
        let window = Window {
            pieces: 4,
            bytes: 1,
            yielded: &nothing,
            least: 0,
        };
        let (before, error) = in_order_while_computing(
            &items,
            2,
            window,
            |_| 1,
            compute,
            |pieces| {
                let mut before = Vec::new();
                for piece in pieces {
                    match piece {
                        Ok(item) => before.push(item),
                        Err(error) => return (before, Some(error.to_string())),
                    }
                }
                (before, None)
            },
        );
        assert_eq!(before, (0..37).collect::<Vec<_>>());
        assert!(error.is_some_and(|e| e.contains("bad unit")));
    }
}
