//! Own keyframes' features, at most `[rendezvous] features_in_memory` of them in memory.
//!
//! Every own keyframe's features are needed for as long as the robot flies: a peer's
//! descriptor may match any of them (its verification packet is sent then, and the
//! peer's packet verified against it), and an own loop closes on any older keyframe. Kept
//! all in memory they grow with the map (~30 kB per keyframe: an hour's soak took the
//! team link from 60 to 90 MB). So memory holds the most recently used ones and the rest
//! is read back from the robot's keyframe store (`team.own`, [`crate::store`]), where
//! every keyframe's verification packet is appended anyway for restarts: **the least
//! recently used keyframe leaves memory** when a new one comes in beyond the bound; its
//! record's offset is kept (8 bytes and the map's node per keyframe) and the next use
//! reads it back (what a restart does too: the packet's strongest
//! `max_packet_features`, points rebuilt from their disparity). A keyframe whose packet
//! is not in the store (no store, or its append failed) is **forgotten** when it leaves
//! memory, and counted.

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;

use doorslam_frontend::packet::from_packet;
use doorslam_frontend::Feature;
use doorslam_ipc::wire::Body;
use serde::Serialize;

use crate::store::OwnStore;

/// Default of `[rendezvous] features_in_memory`: at ~30 kB a keyframe (1000 features at
/// most: 56 kB), 8-14 MB; four minutes of keyframes at one a second.
pub const DEFAULT_FEATURES_IN_MEMORY: usize = 256;

/// Counters of the own features (`pieces.own_features` in `status.json`).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct OwnFeatureStats {
    /// Keyframes whose features are in memory now (≤ `features_in_memory`).
    pub in_memory: u64,
    /// Keyframes whose packet is in the store (readable after leaving memory).
    pub on_disk: u64,
    /// Keyframes that left memory (least recently used) with their packet in the store.
    pub evicted: u64,
    /// Features read back from the store.
    pub loaded: u64,
    /// Keyframes that left memory with no packet in the store: unverifiable from then on.
    pub forgotten: u64,
    /// Reads from the store that failed (logged; the keyframe is unverifiable this time).
    pub load_errors: u64,
}

/// The bounded set of own keyframes' features.
#[derive(Debug)]
pub struct OwnFeatures {
    capacity: usize,
    /// Keyframe index → (last use, features).
    memory: HashMap<u64, (u64, Arc<[Feature]>)>,
    /// Last use → keyframe index: the least recently used first.
    recency: BTreeMap<u64, u64>,
    clock: u64,
    /// Keyframe index → offset of its packet's record in the store.
    on_disk: BTreeMap<u64, u64>,
    /// The highest keyframe index known.
    last: Option<u64>,
    stats: OwnFeatureStats,
}

impl OwnFeatures {
    /// At most `capacity` keyframes in memory (at least 1).
    pub fn new(capacity: usize) -> Self {
        Self {
            capacity: capacity.max(1),
            memory: HashMap::new(),
            recency: BTreeMap::new(),
            clock: 0,
            on_disk: BTreeMap::new(),
            last: None,
            stats: OwnFeatureStats::default(),
        }
    }

    pub fn stats(&self) -> OwnFeatureStats {
        let mut s = self.stats.clone();
        s.in_memory = self.memory.len() as u64;
        s.on_disk = self.on_disk.len() as u64;
        s
    }

    /// The highest keyframe index whose features were given (in memory or not).
    pub fn last(&self) -> Option<u64> {
        self.last
    }

    /// Whether keyframe `index`'s features can be had (in memory or in the store).
    pub fn contains(&self, index: u64) -> bool {
        self.memory.contains_key(&index) || self.on_disk.contains_key(&index)
    }

    /// A keyframe's features, now the most recently used.
    pub fn insert(&mut self, index: u64, features: Vec<Feature>) {
        self.put(index, features.into());
    }

    /// Keyframe `index`'s packet is in the store at `offset`.
    pub fn spilled(&mut self, index: u64, offset: u64) {
        self.on_disk.insert(index, offset);
        self.last = Some(self.last.map_or(index, |l| l.max(index)));
    }

    /// Keyframe `index`'s features: from memory, else read back from `store` (and kept in
    /// memory as the most recently used). `None` when neither has them or the read fails
    /// (logged and counted).
    pub fn get(
        &mut self,
        index: u64,
        store: Option<&OwnStore>,
        disparity_sigma_px: f64,
    ) -> Option<Arc<[Feature]>> {
        if let Some((used, features)) = self.memory.get_mut(&index) {
            self.recency.remove(used);
            self.clock += 1;
            *used = self.clock;
            self.recency.insert(self.clock, index);
            return Some(features.clone());
        }
        let offset = *self.on_disk.get(&index)?;
        let store = store?;
        let packet = match store.read_at(offset) {
            Ok(Body::VerificationFeatures(p)) => p,
            Ok(other) => {
                tracing::error!(
                    path = %store.path().display(),
                    offset,
                    "team: own keyframe {index}: a {} record where its packet was",
                    other.kind().name()
                );
                self.stats.load_errors += 1;
                return None;
            }
            Err(e) => {
                tracing::error!("team: own keyframe {index}: {e}");
                self.stats.load_errors += 1;
                return None;
            }
        };
        let (_, features) = from_packet(&packet, disparity_sigma_px);
        self.stats.loaded += 1;
        let features: Arc<[Feature]> = features.into();
        self.put(index, features.clone());
        Some(features)
    }

    fn put(&mut self, index: u64, features: Arc<[Feature]>) {
        self.clock += 1;
        if let Some((used, _)) = self.memory.insert(index, (self.clock, features)) {
            self.recency.remove(&used);
        }
        self.recency.insert(self.clock, index);
        self.last = Some(self.last.map_or(index, |l| l.max(index)));
        while self.memory.len() > self.capacity {
            let Some((_, oldest)) = self.recency.pop_first() else {
                break;
            };
            self.memory.remove(&oldest);
            if self.on_disk.contains_key(&oldest) {
                self.stats.evicted += 1;
            } else {
                self.stats.forgotten += 1;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use doorslam_dataset::StereoCalibration;
    use doorslam_frontend::packet::to_packet;
    use doorslam_geometry::key;

    fn calib() -> StereoCalibration {
        StereoCalibration {
            fx: 458.0,
            fy: 457.0,
            cx: 367.0,
            cy: 248.0,
            baseline_m: 0.11,
        }
    }

    /// Keyframe `i`'s features: `n` of them, told apart by their descriptors.
    fn features(i: u64, n: usize) -> Vec<Feature> {
        (0..n)
            .map(|j| Feature {
                pixel: [10.0 + j as f32, 20.0 + (i % 400) as f32],
                descriptor: [(i % 251) as u8; 32],
                point: [0.1 * j as f32, 0.2, 2.0 + (i % 7) as f32],
                depth_sigma_m: 0.01,
            })
            .collect()
    }

    /// Ten times the bound of keyframes, each appended to the store as the team link
    /// does: memory holds the bound (the most recently used), every keyframe is still
    /// had (read back from the store, the same features a restart reads), and the
    /// counters say what moved.
    #[test]
    fn ten_times_the_bound_keeps_the_bound_in_memory_and_the_rest_on_disk() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("team.own");
        let mut store = OwnStore::open(&path, |_, _| {}).unwrap();
        let (cap, n, sigma) = (8usize, 80u64, 0.5);
        let mut own = OwnFeatures::new(cap);
        let mut packets = Vec::new();
        for i in 0..n {
            let f = features(i, 20);
            let p = to_packet(key::symbol(1, i).unwrap(), &calib(), &f, 500).unwrap();
            own.insert(i, f);
            let at = store.append(Body::VerificationFeatures(p.clone())).unwrap();
            own.spilled(i, at);
            packets.push(p);
            assert!(own.stats().in_memory as usize <= cap);
        }
        let s = own.stats();
        assert_eq!((s.in_memory, s.on_disk), (cap as u64, n));
        assert_eq!(s.evicted, n - cap as u64);
        assert_eq!((s.loaded, s.forgotten, s.load_errors), (0, 0, 0));
        assert_eq!(own.last(), Some(n - 1));
        // The newest are in memory as given.
        let newest = own.get(n - 1, Some(&store), sigma).unwrap();
        assert_eq!(&newest[..], &features(n - 1, 20)[..]);
        // The oldest comes back from the store: what its packet holds.
        let oldest = own.get(0, Some(&store), sigma).unwrap();
        assert_eq!(own.stats().loaded, 1);
        let back = to_packet(key::symbol(1, 0).unwrap(), &calib(), &oldest, 500).unwrap();
        assert_eq!(back, packets[0]);
        // Read back, it is the most recently used: a second use is from memory, and the
        // least recently used one left instead (still within the bound).
        own.get(0, Some(&store), sigma).unwrap();
        assert_eq!(own.stats().loaded, 1);
        assert_eq!(own.stats().in_memory as usize, cap);
        assert_eq!(own.stats().evicted, n - cap as u64 + 1);
        // Every keyframe is still to be had.
        for i in 0..n {
            assert!(own.contains(i));
            assert!(own.get(i, Some(&store), sigma).is_some(), "keyframe {i}");
        }
        assert!(own.stats().in_memory as usize <= cap);
        assert!(own.get(n, Some(&store), sigma).is_none());
    }

    /// Without a store a keyframe that leaves memory is gone: forgotten, counted.
    #[test]
    fn without_a_store_the_least_recently_used_are_forgotten() {
        let mut own = OwnFeatures::new(4);
        for i in 0..40 {
            own.insert(i, features(i, 5));
            // Keyframe 0 used at every step stays.
            assert!(own.get(0, None, 0.5).is_some());
        }
        let s = own.stats();
        assert_eq!((s.in_memory, s.on_disk, s.evicted), (4, 0, 0));
        assert_eq!(s.forgotten, 36);
        assert!(own.contains(0) && own.contains(39) && !own.contains(35));
        assert!(own.get(1, None, 0.5).is_none());
        assert_eq!(own.last(), Some(39));
    }

    /// A record that is not a packet where the offset says one is: an error, counted,
    /// no panic.
    #[test]
    fn a_wrong_offset_is_a_counted_load_error() {
        let dir = tempfile::tempdir().unwrap();
        let mut store = OwnStore::open(&dir.path().join("team.own"), |_, _| {}).unwrap();
        use doorslam_ipc::wire::{Descriptor, Descriptors, DESCRIPTOR_DIM};
        let q = Descriptor::quantize(key::symbol(1, 0).unwrap(), &[0.1; DESCRIPTOR_DIM]).unwrap();
        let d = Descriptors {
            robot: 1,
            keyframes: 0..1,
            descriptors: vec![q],
        };
        let at = store.append(Body::Descriptors(d)).unwrap();
        let mut own = OwnFeatures::new(1);
        own.spilled(0, at);
        own.spilled(1, at + 3);
        assert!(own.get(0, Some(&store), 0.5).is_none());
        assert!(own.get(1, Some(&store), 0.5).is_none());
        assert_eq!(own.stats().load_errors, 2);
    }
}
