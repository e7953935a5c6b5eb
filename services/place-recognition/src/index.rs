//! The matching index of one robot: its own keyframes' descriptors in the int8 wire form,
//! and the nearest own keyframe of each received descriptor (paper §III-B, rendezvous
//! step 2: β matches α's descriptors against its own).
//!
//! A received descriptor matches its nearest own keyframe when their Euclidean distance,
//! computed on the int8 form with integer dot products ([`crate::matching::Quantized`]), is
//! below the threshold (one per descriptor: [`crate::Method::default_threshold`]). For
//! intra-robot use (a robot's own descriptors as queries: loop closures of one robot), the
//! keyframes within `temporal_exclusion` ids of the query are not candidates: neighbours in
//! time always look alike and are already joined by odometry.
//!
//! Brute force over all own keyframes: 1,000 received x 10,000 own in 0.14-0.18 s on one
//! core (BENCHMARKS.md); linear in both, so about 2 s at 10⁵ own keyframes per batch of
//! 1,000, where an inverted file or a graph index would have to replace it.

use doorslam_geometry::key;
use doorslam_ipc::wire::{Descriptor, Match, QuantizeError};

use crate::matching::Quantized;

/// Refusals of [`MatchIndex::insert`].
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum IndexError {
    #[error("descriptor key {key:#x} is not robot {robot}'s keyframe (its own keys only)")]
    NotOwn { key: u64, robot: u8 },
    #[error("descriptor of keyframe {key:#x}: scale {scale} is not finite and >= 0")]
    Scale { key: u64, scale: f32 },
    #[error("keyframe {index}: {source}")]
    Quantize {
        index: u64,
        #[source]
        source: QuantizeError,
    },
    #[error("keyframe {index}: {source}")]
    Key {
        index: u64,
        #[source]
        source: key::KeyError,
    },
}

/// One robot's keyframe descriptors, matched against received ones.
#[derive(Debug, Clone)]
pub struct MatchIndex {
    robot: u8,
    threshold: f32,
    temporal_exclusion: u64,
    /// In insertion order; keys unique (a re-inserted keyframe replaces its descriptor).
    own: Vec<Quantized>,
    /// Position in `own` of each keyframe index (sparse ids stay cheap).
    position: std::collections::BTreeMap<u64, usize>,
}

impl MatchIndex {
    /// An empty index of robot `robot` (index in the team, 0 = 'a'). `threshold`: largest
    /// distance of a match; `temporal_exclusion`: own keyframes within this many ids of an
    /// own query are not candidates.
    pub fn new(robot: u8, threshold: f32, temporal_exclusion: u64) -> Self {
        Self {
            robot,
            threshold,
            temporal_exclusion,
            own: Vec::new(),
            position: Default::default(),
        }
    }

    pub fn threshold(&self) -> f32 {
        self.threshold
    }

    /// Own keyframes in the index.
    pub fn len(&self) -> usize {
        self.own.len()
    }

    pub fn is_empty(&self) -> bool {
        self.own.is_empty()
    }

    /// Adds (or replaces) one own keyframe's wire descriptor.
    pub fn insert(&mut self, descriptor: Descriptor) -> Result<(), IndexError> {
        let k = descriptor.key;
        if key::robot(k) != Some(self.robot) {
            return Err(IndexError::NotOwn {
                key: k,
                robot: self.robot,
            });
        }
        if !descriptor.scale.is_finite() || descriptor.scale < 0.0 {
            return Err(IndexError::Scale {
                key: k,
                scale: descriptor.scale,
            });
        }
        let q = Quantized::new(descriptor);
        match self.position.get(&key::index(k)) {
            Some(&i) => self.own[i] = q,
            None => {
                self.position.insert(key::index(k), self.own.len());
                self.own.push(q);
            }
        }
        Ok(())
    }

    /// Quantizes and adds own keyframe `index`'s float descriptor (128 values).
    pub fn insert_f32(&mut self, index: u64, values: &[f32]) -> Result<(), IndexError> {
        let k =
            key::symbol(self.robot, index).map_err(|source| IndexError::Key { index, source })?;
        let d = Descriptor::quantize(k, values)
            .map_err(|source| IndexError::Quantize { index, source })?;
        self.insert(d)
    }

    /// The `k` nearest own keyframes of a descriptor nearer than `max_distance`, nearest
    /// first: `(own key, distance)`. A descriptor of this robot's own keyframe (intra-robot
    /// use) skips the keyframes within the temporal exclusion, and itself.
    pub fn top_k(&self, d: &Descriptor, k: usize, max_distance: f32) -> Vec<(u64, f32)> {
        let q = Quantized::new(d.clone());
        let intra = key::robot(d.key) == Some(self.robot);
        let qi = key::index(d.key);
        let mut best: Vec<(u64, f32)> = Vec::with_capacity(k + 1);
        for c in &self.own {
            let ci = key::index(c.descriptor.key);
            if intra && ci.abs_diff(qi) <= self.temporal_exclusion {
                continue;
            }
            let d2 = q.distance2(c);
            if d2 >= max_distance * max_distance
                || (best.len() == k && best.last().is_some_and(|b| d2 >= b.1))
            {
                continue;
            }
            // Insertion into the short sorted list (k is small); ties keep index order.
            let at = best.partition_point(|b| b.1 <= d2);
            best.insert(at, (c.descriptor.key, d2));
            best.truncate(k);
        }
        best.into_iter().map(|(c, d2)| (c, d2.sqrt())).collect()
    }

    /// The nearest own keyframe of each received descriptor, for those nearer than the
    /// threshold: `Match { query: received key, candidate: own key, distance }`, in the
    /// order received. Descriptors of this robot's own keyframes (intra-robot use) skip
    /// the keyframes within the temporal exclusion, and themselves.
    pub fn match_batch(&self, received: &[Descriptor]) -> Vec<Match> {
        received
            .iter()
            .filter_map(|d| {
                let q = Quantized::new(d.clone());
                let intra = key::robot(d.key) == Some(self.robot);
                let qi = key::index(d.key);
                let allowed = |c: &Quantized| {
                    !intra || key::index(c.descriptor.key).abs_diff(qi) > self.temporal_exclusion
                };
                self.own
                    .iter()
                    .filter(|c| allowed(c))
                    .map(|c| (c, q.distance2(c)))
                    .min_by(|a, b| a.1.total_cmp(&b.1))
                    .map(|(c, d2)| (c.descriptor.key, d2.sqrt()))
                    .filter(|&(_, distance)| distance < self.threshold)
                    .map(|(candidate, distance)| Match {
                        query: d.key,
                        candidate,
                        distance,
                    })
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::matching::random_unit_vectors;

    fn key(robot: u8, i: u64) -> u64 {
        key::symbol(robot, i).unwrap()
    }

    /// `v` moved a little: the same place seen again.
    fn nudge(v: &[f32], by: f32) -> Vec<f32> {
        let mut w: Vec<f32> = v
            .iter()
            .enumerate()
            .map(|(i, x)| x + by * if i % 3 == 0 { 1.0 } else { -0.5 })
            .collect();
        let n = w.iter().map(|x| x * x).sum::<f32>().sqrt();
        w.iter_mut().for_each(|x| *x /= n);
        w
    }

    #[test]
    fn received_descriptors_match_their_nearest_own_keyframe_below_the_threshold() {
        let own = random_unit_vectors(50, 128, 3);
        let mut index = MatchIndex::new(1, 0.5, 5);
        for (i, v) in own.iter().enumerate() {
            index.insert_f32(i as u64, v).unwrap();
        }
        assert_eq!(index.len(), 50);
        // Robot 'a' saw own keyframes 7 and 30 again, and one unrelated place.
        let unrelated = &random_unit_vectors(1, 128, 99)[0];
        let received: Vec<Descriptor> = [
            nudge(&own[7], 0.01),
            nudge(&own[30], 0.01),
            unrelated.clone(),
        ]
        .iter()
        .enumerate()
        .map(|(i, v)| Descriptor::quantize(key(0, 100 + i as u64), v).unwrap())
        .collect();
        let m = index.match_batch(&received);
        assert_eq!(m.len(), 2, "{m:?}");
        assert_eq!((m[0].query, m[0].candidate), (key(0, 100), key(1, 7)));
        assert_eq!((m[1].query, m[1].candidate), (key(0, 101), key(1, 30)));
        assert!(m.iter().all(|m| m.distance < 0.2), "{m:?}");
        // Random unit vectors in 128-D are ~√2 apart: far beyond any threshold.
        let strict = {
            let mut i = index.clone();
            i.threshold = 0.01;
            i
        };
        assert!(strict.match_batch(&received).is_empty());
    }

    #[test]
    fn intra_robot_queries_skip_temporal_neighbours() {
        // A robot flies a loop: keyframe 40 revisits keyframe 2's place; its neighbours
        // 38..=42 look like it too.
        let places = random_unit_vectors(60, 128, 5);
        let mut views: Vec<Vec<f32>> = places.clone();
        views[40] = nudge(&places[2], 0.02);
        for i in 36..=44 {
            if i != 40 {
                views[i] = nudge(&views[40], 0.005 * (i as f32 - 40.0).abs());
            }
        }
        let mut index = MatchIndex::new(0, 0.6, 5);
        for (i, v) in views.iter().enumerate() {
            index.insert_f32(i as u64, v).unwrap();
        }
        let query = Descriptor::quantize(key(0, 40), &views[40]).unwrap();
        let m = index.match_batch(std::slice::from_ref(&query));
        assert_eq!(m.len(), 1, "{m:?}");
        assert_eq!(m[0].candidate, key(0, 2), "{m:?}");
        // Without the exclusion its neighbours (or itself) win.
        let mut no_exclusion = MatchIndex::new(0, 0.6, 0);
        for (i, v) in views.iter().enumerate() {
            no_exclusion.insert_f32(i as u64, v).unwrap();
        }
        let m = no_exclusion.match_batch(&[query]);
        assert!(key::index(m[0].candidate).abs_diff(40) <= 4, "{m:?}");
    }

    #[test]
    fn foreign_keys_and_bad_scales_are_refused_and_reinsertion_replaces() {
        let v = &random_unit_vectors(2, 128, 8);
        let mut index = MatchIndex::new(2, 0.5, 0);
        let foreign = Descriptor::quantize(key(3, 1), &v[0]).unwrap();
        assert!(matches!(
            index.insert(foreign),
            Err(IndexError::NotOwn { robot: 2, .. })
        ));
        let mut bad = Descriptor::quantize(key(2, 1), &v[0]).unwrap();
        bad.scale = f32::NAN;
        assert!(matches!(index.insert(bad), Err(IndexError::Scale { .. })));
        assert!(matches!(
            index.insert_f32(1, &v[0][..100]),
            Err(IndexError::Quantize { index: 1, .. })
        ));
        index.insert_f32(1, &v[0]).unwrap();
        index.insert_f32(1, &v[1]).unwrap();
        assert_eq!(index.len(), 1);
        let q = Descriptor::quantize(key(0, 0), &v[1]).unwrap();
        assert!(index.match_batch(&[q])[0].distance < 0.02);
    }
}
