//! A bounded set of ids already processed, for the sets that only prevent processing a
//! thing twice (descriptors delivered, pairs verified, closures received): ids that come
//! roughly in increasing order over a flight (a robot's keyframes are numbered in order, and
//! the protocol sends them in that order), so instead of keeping every id of a long flight,
//! keep the newest `limit` of them above a floor; an id at or below the floor counts as
//! already seen. The floor rises as the window slides: memory stays at `limit` ids
//! whatever the flight's length, at the price that an id arriving for the first time after
//! `limit` newer ones is taken for a repeat (counted: [`SeenWindow::below_floor`]).

use std::collections::BTreeSet;

/// Ids seen, the newest `limit` of them kept, everything at or below `floor` taken as seen.
#[derive(Debug, Clone)]
pub struct SeenWindow<T> {
    ids: BTreeSet<T>,
    floor: Option<T>,
    limit: usize,
    forgotten: u64,
    below_floor: u64,
}

impl<T: Ord + Copy> SeenWindow<T> {
    /// At most `limit` ids kept (at least one: a window of none would take every id for a
    /// repeat after the first).
    pub fn new(limit: usize) -> Self {
        Self {
            ids: BTreeSet::new(),
            floor: None,
            limit: limit.max(1),
            forgotten: 0,
            below_floor: 0,
        }
    }

    /// Whether `id` counts as seen (kept, or at or below the floor).
    pub fn contains(&self, id: &T) -> bool {
        self.floor.is_some_and(|f| *id <= f) || self.ids.contains(id)
    }

    /// Records `id`: true when it is new. Beyond `limit` ids the lowest leaves and becomes
    /// the floor.
    pub fn insert(&mut self, id: T) -> bool {
        if self.floor.is_some_and(|f| id <= f) {
            self.below_floor += 1;
            return false;
        }
        if !self.ids.insert(id) {
            return false;
        }
        while self.ids.len() > self.limit {
            if let Some(low) = self.ids.pop_first() {
                self.floor = Some(low);
                self.forgotten += 1;
            }
        }
        true
    }

    /// The ids kept (above the floor), in order.
    pub fn ids(&self) -> &BTreeSet<T> {
        &self.ids
    }

    pub fn len(&self) -> usize {
        self.ids.len()
    }

    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }

    /// Everything at or below this counts as seen.
    pub fn floor(&self) -> Option<T> {
        self.floor
    }

    /// Ids that left the window (each raised the floor).
    pub fn forgotten(&self) -> u64 {
        self.forgotten
    }

    /// Inserts refused because the id was at or below the floor.
    pub fn below_floor(&self) -> u64 {
        self.below_floor
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Ten times the bound in order: the newest `limit` kept, every older one still counts
    /// as seen (none is processed twice), the forgotten ones counted.
    #[test]
    fn a_flood_keeps_the_newest_and_the_floor_remembers_the_rest() {
        let mut w = SeenWindow::new(16);
        for id in 0..160u64 {
            assert!(w.insert(id), "{id} is new");
            assert!(w.len() <= 16);
        }
        assert_eq!(w.len(), 16);
        assert_eq!(
            w.ids().iter().copied().collect::<Vec<_>>(),
            (144..160).collect::<Vec<_>>()
        );
        assert_eq!(w.floor(), Some(143));
        assert_eq!(w.forgotten(), 144);
        for id in 0..160u64 {
            assert!(w.contains(&id), "{id} counts as seen");
            assert!(!w.insert(id), "{id} is not new again");
        }
        assert_eq!(w.below_floor(), 144);
        assert!(w.insert(160));
    }

    /// Out of order within the window: a late id above the floor is still new once.
    #[test]
    fn a_late_id_above_the_floor_is_new() {
        let mut w = SeenWindow::new(4);
        for id in [10u64, 12, 13, 14] {
            assert!(w.insert(id));
        }
        assert!(w.insert(11), "11 is above the floor (none yet)");
        assert_eq!(w.floor(), Some(10));
        assert!(!w.insert(11));
        assert!(!w.insert(9), "below the floor");
        assert_eq!(w.len(), 4);
    }
}
