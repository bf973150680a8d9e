//! The recorder's queue between the bus and the writer thread, bounded in messages *and* bytes
//! (a burst of 8 MiB segments must not fill memory any more than a burst of job states).
//!
//! What happens when it is full is the caller's choice ([`Overflow`]): drop the message (the
//! bus never waits for the disk; the caller counts and reports it) or block (the subscriber
//! waits, which with blocking congestion control slows the publishers down — nothing is lost
//! but the cluster runs at disk speed).

use std::collections::VecDeque;
use std::sync::{Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

/// What a full queue does with a new message.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Overflow {
    /// Refuse it: [`Pushed::Dropped`].
    #[default]
    Drop,
    /// Wait until it fits.
    Block,
}

/// The outcome of [`BoundedQueue::push`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pushed {
    /// Queued, after waiting this long for room (zero unless [`Overflow::Block`]).
    Queued { waited: Duration },
    /// The queue was full ([`Overflow::Drop`]).
    Dropped,
    /// The consumer is gone.
    Closed,
}

struct State<T> {
    items: VecDeque<(T, usize)>,
    bytes: usize,
    closed: bool,
    /// Producers waiting for room ([`Overflow::Block`]); they still get in after `close`.
    waiting: usize,
    /// The consumer is gone: nothing gets in any more.
    abandoned: bool,
}

/// A multi-producer, single-consumer queue with two bounds.
pub struct BoundedQueue<T> {
    state: Mutex<State<T>>,
    not_empty: Condvar,
    not_full: Condvar,
    max_items: usize,
    max_bytes: usize,
}

impl<T> BoundedQueue<T> {
    /// At most `max_items` messages and `max_bytes` bytes (a single message larger than
    /// `max_bytes` is still taken when the queue is empty, or it could never pass).
    pub fn new(max_items: usize, max_bytes: usize) -> Self {
        Self {
            state: Mutex::new(State {
                items: VecDeque::new(),
                bytes: 0,
                closed: false,
                waiting: 0,
                abandoned: false,
            }),
            not_empty: Condvar::new(),
            not_full: Condvar::new(),
            max_items: max_items.max(1),
            max_bytes,
        }
    }

    fn lock(&self) -> MutexGuard<'_, State<T>> {
        // A panic while holding the lock cannot leave the deque inconsistent (every mutation is
        // one call), so a poisoned lock is still usable.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn fits(&self, s: &State<T>, bytes: usize) -> bool {
        s.items.is_empty()
            || (s.items.len() < self.max_items && s.bytes.saturating_add(bytes) <= self.max_bytes)
    }

    pub fn push(&self, item: T, bytes: usize, overflow: Overflow) -> Pushed {
        // Only time spent waiting for room counts, not taking the lock.
        let mut waited_since = None;
        let mut s = self.lock();
        if s.closed {
            return Pushed::Closed;
        }
        while !self.fits(&s, bytes) {
            match overflow {
                Overflow::Drop => return Pushed::Dropped,
                Overflow::Block => {
                    // A message already waiting when the queue closes is still taken: it
                    // arrived before the end, and the consumer drains until nobody waits.
                    waited_since.get_or_insert_with(Instant::now);
                    s.waiting += 1;
                    s = self.not_full.wait(s).unwrap_or_else(|p| p.into_inner());
                    s.waiting -= 1;
                    if s.abandoned {
                        drop(s);
                        self.not_empty.notify_all();
                        return Pushed::Closed;
                    }
                }
            }
        }
        s.items.push_back((item, bytes));
        s.bytes += bytes;
        drop(s);
        self.not_empty.notify_one();
        Pushed::Queued {
            waited: waited_since.map_or(Duration::ZERO, |t| t.elapsed()),
        }
    }

    /// The next message; waits at most `timeout`. `Err(true)` once closed, empty and with no
    /// producer waiting to get in, `Err(false)` on timeout.
    pub fn pop_timeout(&self, timeout: Duration) -> Result<T, bool> {
        let deadline = Instant::now() + timeout;
        let mut s = self.lock();
        loop {
            if let Some((item, bytes)) = s.items.pop_front() {
                s.bytes -= bytes;
                drop(s);
                self.not_full.notify_all();
                return Ok(item);
            }
            if s.closed && s.waiting == 0 {
                return Err(true);
            }
            let now = Instant::now();
            if now >= deadline {
                return Err(false);
            }
            s = self
                .not_empty
                .wait_timeout(s, deadline - now)
                .unwrap_or_else(|p| p.into_inner())
                .0;
        }
    }

    /// No more new pushes; the consumer drains what is queued and what was waiting.
    pub fn close(&self) {
        self.lock().closed = true;
        self.not_empty.notify_all();
        self.not_full.notify_all();
    }

    /// The consumer gives up: every push fails from now on, waiting ones too. Returns what was
    /// queued, for the caller to count.
    pub fn abandon(&self) -> Vec<T> {
        let mut s = self.lock();
        s.closed = true;
        s.abandoned = true;
        s.bytes = 0;
        let left = s.items.drain(..).map(|(t, _)| t).collect();
        drop(s);
        self.not_full.notify_all();
        left
    }

    /// Messages and bytes queued now.
    pub fn len(&self) -> (usize, usize) {
        let s = self.lock();
        (s.items.len(), s.bytes)
    }

    pub fn is_empty(&self) -> bool {
        self.len().0 == 0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    #[test]
    fn both_bounds_hold_and_drop_says_so() {
        let q = BoundedQueue::new(3, 100);
        let queued = |p| {
            p == Pushed::Queued {
                waited: Duration::ZERO,
            }
        };
        assert!(queued(q.push(1, 40, Overflow::Drop)));
        assert!(queued(q.push(2, 40, Overflow::Drop)));
        // 40 + 40 + 40 > 100 bytes.
        assert_eq!(q.push(3, 40, Overflow::Drop), Pushed::Dropped);
        assert!(queued(q.push(4, 10, Overflow::Drop)));
        // Three messages.
        assert_eq!(q.push(5, 1, Overflow::Drop), Pushed::Dropped);
        assert_eq!(q.len(), (3, 90));
        assert_eq!(q.pop_timeout(Duration::ZERO), Ok(1));
        assert_eq!(q.pop_timeout(Duration::ZERO), Ok(2));
        assert_eq!(q.pop_timeout(Duration::ZERO), Ok(4));
        assert_eq!(q.pop_timeout(Duration::from_millis(5)), Err(false));
        // Larger than the byte bound, but alone: taken.
        assert!(queued(q.push(6, 1000, Overflow::Drop)));
        q.close();
        assert_eq!(q.push(7, 1, Overflow::Block), Pushed::Closed);
        assert_eq!(q.pop_timeout(Duration::ZERO), Ok(6));
        assert_eq!(q.pop_timeout(Duration::ZERO), Err(true));
    }

    #[test]
    fn block_waits_for_the_consumer_and_loses_nothing() {
        let q = Arc::new(BoundedQueue::new(2, usize::MAX));
        let producer = {
            let q = q.clone();
            std::thread::spawn(move || {
                let mut waited = Duration::ZERO;
                for i in 0..50u32 {
                    match q.push(i, 1, Overflow::Block) {
                        Pushed::Queued { waited: w } => waited += w,
                        other => panic!("push {i}: {other:?}"),
                    }
                }
                q.close();
                waited
            })
        };
        let mut got = Vec::new();
        loop {
            match q.pop_timeout(Duration::from_secs(5)) {
                Ok(i) => {
                    got.push(i);
                    std::thread::sleep(Duration::from_millis(1));
                }
                Err(true) => break,
                Err(false) => panic!("consumer starved"),
            }
        }
        let waited = producer.join().unwrap();
        assert_eq!(got, (0..50).collect::<Vec<_>>());
        // The slow consumer made the producer wait.
        assert!(waited > Duration::ZERO);
    }

    #[test]
    fn a_producer_waiting_at_close_still_gets_in_unless_the_consumer_gives_up() {
        for abandon in [false, true] {
            let q = Arc::new(BoundedQueue::new(1, usize::MAX));
            assert!(matches!(
                q.push(0, 1, Overflow::Block),
                Pushed::Queued { .. }
            ));
            let producer = {
                let q = q.clone();
                std::thread::spawn(move || q.push(1, 1, Overflow::Block))
            };
            while q.lock().waiting == 0 {
                std::thread::sleep(Duration::from_millis(1));
            }
            if abandon {
                assert_eq!(q.abandon(), vec![0]);
                assert_eq!(producer.join().unwrap(), Pushed::Closed);
                assert_eq!(q.pop_timeout(Duration::ZERO), Err(true));
            } else {
                q.close();
                // New pushes are refused, the waiting one is not.
                assert_eq!(q.push(2, 1, Overflow::Block), Pushed::Closed);
                assert_eq!(q.pop_timeout(Duration::from_secs(5)), Ok(0));
                assert_eq!(q.pop_timeout(Duration::from_secs(5)), Ok(1));
                assert!(matches!(producer.join().unwrap(), Pushed::Queued { .. }));
                assert_eq!(q.pop_timeout(Duration::ZERO), Err(true));
            }
        }
    }
}
