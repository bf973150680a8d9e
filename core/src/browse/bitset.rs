//! A growable bitset over dense `u32` world indices (§4.4.2: one per constraint, so that the
//! result of any set of constraints is a word-wise AND).

/// A set of world indices, one bit per world. Bits past the end are 0, so sets of different
/// lengths combine as if padded with zeros, and equality ignores trailing zero words.
#[derive(Debug, Clone, Default)]
pub struct WorldSet {
    words: Vec<u64>,
}

impl PartialEq for WorldSet {
    fn eq(&self, other: &Self) -> bool {
        let n = self.words.len().max(other.words.len());
        (0..n).all(|i| self.word(i) == other.word(i))
    }
}

impl Eq for WorldSet {}

impl WorldSet {
    pub fn new() -> Self {
        Self::default()
    }

    /// An empty set with room for worlds `0..capacity` without reallocating.
    pub fn with_capacity(capacity: u32) -> Self {
        Self {
            words: Vec::with_capacity(capacity.div_ceil(64) as usize),
        }
    }

    /// All worlds `0..n`.
    pub fn full(n: u32) -> Self {
        let mut words = vec![u64::MAX; (n / 64) as usize];
        if !n.is_multiple_of(64) {
            words.push((1u64 << (n % 64)) - 1);
        }
        Self { words }
    }

    /// The set whose world `64·i + b` is bit `b` of `words[i]`.
    pub fn from_words(words: Vec<u64>) -> Self {
        Self { words }
    }

    #[inline]
    fn word(&self, i: usize) -> u64 {
        self.words.get(i).copied().unwrap_or(0)
    }

    pub fn contains(&self, world: u32) -> bool {
        self.word((world / 64) as usize) & (1 << (world % 64)) != 0
    }

    /// Adds `world`, growing as needed; returns whether it was new.
    pub fn insert(&mut self, world: u32) -> bool {
        let w = (world / 64) as usize;
        if w >= self.words.len() {
            self.words.resize(w + 1, 0);
        }
        let bit = 1u64 << (world % 64);
        let new = self.words[w] & bit == 0;
        self.words[w] |= bit;
        new
    }

    /// Removes `world`; returns whether it was present.
    pub fn remove(&mut self, world: u32) -> bool {
        let w = (world / 64) as usize;
        let bit = 1u64 << (world % 64);
        match self.words.get_mut(w) {
            Some(word) if *word & bit != 0 => {
                *word &= !bit;
                true
            }
            _ => false,
        }
    }

    pub fn set(&mut self, world: u32, present: bool) {
        if present {
            self.insert(world);
        } else {
            self.remove(world);
        }
    }

    /// Number of worlds in the set.
    pub fn len(&self) -> usize {
        self.words.iter().map(|w| w.count_ones() as usize).sum()
    }

    pub fn is_empty(&self) -> bool {
        self.words.iter().all(|&w| w == 0)
    }

    pub fn clear(&mut self) {
        self.words.clear();
    }

    /// `self ← self ∩ other`.
    pub fn and_assign(&mut self, other: &WorldSet) {
        for (i, w) in self.words.iter_mut().enumerate() {
            *w &= other.word(i);
        }
    }

    /// `self ← self ∪ other`.
    pub fn or_assign(&mut self, other: &WorldSet) {
        if other.words.len() > self.words.len() {
            self.words.resize(other.words.len(), 0);
        }
        for (w, o) in self.words.iter_mut().zip(&other.words) {
            *w |= o;
        }
    }

    /// `self ← self \ other`.
    pub fn and_not_assign(&mut self, other: &WorldSet) {
        for (w, o) in self.words.iter_mut().zip(&other.words) {
            *w &= !o;
        }
    }

    pub fn and(&self, other: &WorldSet) -> WorldSet {
        let mut out = self.clone();
        out.and_assign(other);
        out
    }

    pub fn or(&self, other: &WorldSet) -> WorldSet {
        let mut out = self.clone();
        out.or_assign(other);
        out
    }

    pub fn and_not(&self, other: &WorldSet) -> WorldSet {
        let mut out = self.clone();
        out.and_not_assign(other);
        out
    }

    /// Worlds in increasing order.
    pub fn iter(&self) -> WorldSetIter<'_> {
        WorldSetIter {
            words: &self.words,
            index: 0,
            current: self.word(0),
        }
    }

    /// Heap bytes held, for memory accounting.
    pub fn heap_bytes(&self) -> usize {
        self.words.capacity() * size_of::<u64>()
    }
}

impl FromIterator<u32> for WorldSet {
    fn from_iter<I: IntoIterator<Item = u32>>(iter: I) -> Self {
        let mut s = WorldSet::new();
        for w in iter {
            s.insert(w);
        }
        s
    }
}

impl<'a> IntoIterator for &'a WorldSet {
    type Item = u32;
    type IntoIter = WorldSetIter<'a>;
    fn into_iter(self) -> Self::IntoIter {
        self.iter()
    }
}

/// Iterator over the worlds of a [`WorldSet`], increasing.
#[derive(Debug, Clone)]
pub struct WorldSetIter<'a> {
    words: &'a [u64],
    index: usize,
    current: u64,
}

impl Iterator for WorldSetIter<'_> {
    type Item = u32;
    fn next(&mut self) -> Option<u32> {
        while self.current == 0 {
            self.index += 1;
            self.current = *self.words.get(self.index)?;
        }
        let bit = self.current.trailing_zeros();
        self.current &= self.current - 1;
        Some(self.index as u32 * 64 + bit)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use std::collections::BTreeSet;

    fn model(s: &WorldSet) -> BTreeSet<u32> {
        s.iter().collect()
    }

    #[test]
    fn full_and_edges() {
        for n in [0, 1, 63, 64, 65, 200] {
            let f = WorldSet::full(n);
            assert_eq!(f.len(), n as usize);
            assert_eq!(f.iter().collect::<Vec<_>>(), (0..n).collect::<Vec<_>>());
        }
        let mut s = WorldSet::new();
        assert!(s.insert(1_000_000) && s.contains(1_000_000));
        assert_eq!(s.iter().collect::<Vec<_>>(), vec![1_000_000]);
        s.clear();
        assert!(s.insert(130));
        assert!(!s.insert(130));
        assert!(s.contains(130) && !s.contains(129) && !s.contains(100_000));
        assert!(s.remove(130) && !s.remove(130) && !s.remove(1_000_000));
        assert!(s.is_empty());
        // Trailing zero words do not make sets unequal.
        assert_eq!(s, WorldSet::new());
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 128, ..ProptestConfig::default() })]

        #[test]
        fn algebra_matches_a_set_model(
            a in prop::collection::btree_set(0u32..700, 0..120),
            b in prop::collection::btree_set(0u32..300, 0..120),
            c in prop::collection::btree_set(0u32..500, 0..120),
        ) {
            let (sa, sb, sc): (WorldSet, WorldSet, WorldSet) = (
                a.iter().copied().collect(), b.iter().copied().collect(), c.iter().copied().collect());
            prop_assert_eq!(model(&sa), a.clone());
            prop_assert_eq!(sa.len(), a.len());
            prop_assert_eq!(model(&sa.and(&sb)), a.intersection(&b).copied().collect::<BTreeSet<_>>());
            prop_assert_eq!(model(&sa.or(&sb)), a.union(&b).copied().collect::<BTreeSet<_>>());
            prop_assert_eq!(model(&sa.and_not(&sb)), a.difference(&b).copied().collect::<BTreeSet<_>>());
            prop_assert_eq!(model(&sb.and_not(&sa)), b.difference(&a).copied().collect::<BTreeSet<_>>());
            // Laws: commutativity, distributivity, A \ B = A ∩ ¬B over a universe, absorption.
            prop_assert_eq!(sa.and(&sb), sb.and(&sa));
            prop_assert_eq!(sa.or(&sb), sb.or(&sa));
            prop_assert_eq!(sa.and(&sb.or(&sc)), sa.and(&sb).or(&sa.and(&sc)));
            let universe = WorldSet::full(700);
            prop_assert_eq!(sa.and_not(&sb), sa.and(&universe.and_not(&sb)));
            prop_assert_eq!(sa.or(&sa.and(&sb)), sa.clone());
            prop_assert_eq!(sa.and_not(&sb).len() + sa.and(&sb).len(), sa.len());
            for w in 0..710 {
                prop_assert_eq!(sa.contains(w), a.contains(&w));
            }
        }
    }
}
