//! A table of optional values by index, held in fixed-size chunks.
//!
//! A store's world table grows one world at a time up to a million or more. In a `Vec` it
//! grows by doubling: up to half of its capacity stands empty (at 300 000 worlds the table
//! had room for 524 288), and the doubling itself copies the whole table in one go. Here the
//! slots live in chunks of [`CHUNK`] that are never moved or reallocated once made: at most
//! one chunk stands partly empty, a new world never copies the others, and a slot is still
//! one index computation away (the chunk list is small enough to stay in the caches).

/// Slots a chunk holds.
pub const CHUNK: usize = 1024;

/// Optional values by index `0..len`, in chunks of [`CHUNK`].
#[derive(Debug)]
pub struct Slots<T> {
    chunks: Vec<Box<[Option<T>]>>,
    len: usize,
}

impl<T> Default for Slots<T> {
    fn default() -> Self {
        Slots {
            chunks: Vec::new(),
            len: 0,
        }
    }
}

impl<T> Slots<T> {
    /// Slots in the table (filled or not): one past the highest index ever set.
    pub fn len(&self) -> usize {
        self.len
    }

    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The value at `index`, if that slot is filled.
    #[inline]
    pub fn get(&self, index: usize) -> Option<&T> {
        if index >= self.len {
            return None;
        }
        self.chunks.get(index / CHUNK)?.get(index % CHUNK)?.as_ref()
    }

    /// Puts `value` at `index` (the table grows to hold it, new slots empty) and returns what
    /// the slot held.
    pub fn set(&mut self, index: usize, value: T) -> Option<T> {
        let chunk = index / CHUNK;
        while self.chunks.len() <= chunk {
            self.chunks
                .push(std::iter::repeat_with(|| None).take(CHUNK).collect());
        }
        self.len = self.len.max(index + 1);
        self.chunks[chunk][index % CHUNK].replace(value)
    }

    /// Every slot from `first` on, in index order.
    pub fn iter_from(&self, first: usize) -> impl Iterator<Item = Option<&T>> {
        (first.min(self.len)..self.len).map(|i| self.chunks[i / CHUNK][i % CHUNK].as_ref())
    }

    /// Every filled slot's value, in index order.
    pub fn values(&self) -> impl Iterator<Item = &T> + Clone {
        self.chunks.iter().flat_map(|c| c.iter()).flatten()
    }

    /// Heap bytes: the chunks (every slot, filled or not) and the chunk list.
    pub fn heap_bytes(&self) -> usize {
        self.chunks.len() * CHUNK * std::mem::size_of::<Option<T>>()
            + self.chunks.capacity() * std::mem::size_of::<Box<[Option<T>]>>()
    }

    /// Bytes [`heap_bytes`](Self::heap_bytes) grows by when slot `index` is set.
    pub fn growth_bytes(&self, index: usize) -> usize {
        let needed = (index / CHUNK + 1).saturating_sub(self.chunks.len());
        if needed == 0 {
            return 0;
        }
        // The chunk list grows as pushes grow a `Vec`: doubling, from 4.
        let (mut capacity, total) = (self.chunks.capacity(), self.chunks.len() + needed);
        while capacity < total {
            capacity = (2 * capacity).max(4);
        }
        needed * CHUNK * std::mem::size_of::<Option<T>>()
            + (capacity - self.chunks.capacity()) * std::mem::size_of::<Box<[Option<T>]>>()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// Whatever the order of sets, the table answers as a map by index does, its length is
        /// one past the highest index set, and its bytes grow by what `growth_bytes` foretold.
        #[test]
        fn slots_answer_as_a_map_does(sets in proptest::collection::vec((0usize..5000, any::<u16>()), 0..200)) {
            let mut slots = Slots::default();
            let mut map = std::collections::BTreeMap::new();
            for &(i, v) in &sets {
                let grow = slots.growth_bytes(i);
                let before = slots.heap_bytes();
                prop_assert_eq!(slots.set(i, v), map.insert(i, v));
                prop_assert!(slots.heap_bytes() <= before + grow);
            }
            let len = map.keys().next_back().map_or(0, |&i| i + 1);
            prop_assert_eq!(slots.len(), len);
            for i in 0..len + CHUNK {
                prop_assert_eq!(slots.get(i), map.get(&i));
            }
            prop_assert_eq!(slots.values().copied().collect::<Vec<_>>(), map.values().copied().collect::<Vec<_>>());
            let from = len / 3;
            let tail: Vec<Option<u16>> = slots.iter_from(from).map(|v| v.copied()).collect();
            prop_assert_eq!(tail, (from..len).map(|i| map.get(&i).copied()).collect::<Vec<_>>());
            // Chunks only as far as the highest index set: at most one stands partly empty.
            prop_assert_eq!(slots.chunks.len(), len.div_ceil(CHUNK));
        }
    }
}
