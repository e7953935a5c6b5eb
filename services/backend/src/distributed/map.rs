//! The team-map request: a robot that wants the team map asks its neighbours in range for
//! their latest keyframe trajectories (`TeamMap` messages of their own kind: a request, and
//! replies carrying every pose as a compact pose, as separator estimates travel). A request
//! names the version of the neighbour's trajectory already held, so asking again costs a
//! reply without poses when nothing changed. Requests and replies are acknowledged and
//! resent when lost, like every back-end message.

use std::collections::BTreeMap;

use doorslam_geometry::{key, SE3};
use doorslam_ipc::wire::{
    Body, CompactPose, Header, Kind, Message, TeamMap, Trajectory, MAX_TRAJECTORY_POSES,
};

use super::link::{Arrival, Outbox, Received};
use super::{Agent, DpgoError};

/// A neighbour's trajectory as it arrived.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TeamTrajectory {
    /// The robot whose first pose fixes the frame of these poses.
    pub anchor: u8,
    /// The sender's estimate revision.
    pub version: u64,
    /// Poses in the sender's trajectory at this version.
    pub total: u64,
    pub poses: BTreeMap<u64, SE3>,
}

impl TeamTrajectory {
    /// Every pose of this version arrived.
    pub fn complete(&self) -> bool {
        self.poses.len() as u64 == self.total
    }
}

/// A message in flight: a request, or one chunk of a reply (version, keys it carried).
#[derive(Debug, Clone)]
enum Sent {
    Request,
    Reply,
}

/// The team-map exchange with one neighbour.
#[derive(Debug, Default)]
pub(crate) struct MapLink {
    rx: Received,
    out: Outbox<Sent>,
    /// We want the neighbour's trajectory (a request is due or in flight).
    want: bool,
    /// The neighbour asked: the version of our trajectory it holds.
    asked: Option<u64>,
}

impl MapLink {
    pub fn ack_due(&self) -> bool {
        self.rx.ack_due
    }

    /// The transport restarted: what was in flight may be gone; a request is made again,
    /// a reply sent again in full.
    pub(crate) fn link_restarted(&mut self) {
        for s in self.out.items() {
            match s {
                Sent::Request => self.want = true,
                Sent::Reply => self.asked = Some(0),
            }
        }
        self.out.clear();
    }

    /// Nothing to send or waiting for an acknowledgement.
    pub fn idle(&self) -> bool {
        !self.want && self.asked.is_none() && self.out.is_empty()
    }
}

impl Agent {
    /// Asks every neighbour in range for its latest trajectory (see [`Self::team_map`]).
    /// Returns how many were asked.
    pub fn request_team_map(&mut self) -> usize {
        let mut n = 0;
        for link in self.neighbors.values_mut().filter(|l| l.present) {
            link.map.want = true;
            n += 1;
        }
        n
    }

    /// The neighbours' trajectories that arrived (robot → trajectory), this robot's own
    /// being [`Self::estimate`].
    pub fn team_map(&self) -> &BTreeMap<u8, TeamTrajectory> {
        &self.team_map
    }

    pub(crate) fn map_messages_for(&mut self, neighbor: u8) -> Result<Vec<Message>, DpgoError> {
        let now = self.now;
        let resend_after = self.options.resend_after;
        // A partial copy is asked for again in full.
        let known = self
            .team_map
            .get(&neighbor)
            .filter(|t| t.complete())
            .map_or(0, |t| t.version);
        let reply = match self.neighbors.get(&neighbor).and_then(|n| n.map.asked) {
            Some(held) => Some(self.trajectory_chunks(held)?),
            None => None,
        };
        let mut out = Vec::new();
        let header = |sequence| Header {
            sender: self.id.clone(),
            epoch: self.epoch,
            sequence,
        };
        let Some(n) = self.neighbors.get_mut(&neighbor) else {
            return Ok(out);
        };
        if let Some(ack) = n
            .map
            .rx
            .take_ack(&self.id, self.epoch, n.ack_sequence, Kind::TeamMap)
        {
            n.ack_sequence += 1;
            out.push(ack);
        }
        for lost in n.map.out.expire(now, resend_after) {
            self.stats.resent += 1;
            match lost {
                Sent::Request => n.map.want = true,
                // The whole trajectory again (a chunk alone would not complete it).
                Sent::Reply => n.map.asked = Some(0),
            }
        }
        let request_flying = n.map.out.items().any(|s| matches!(s, Sent::Request));
        if n.map.want && !request_flying {
            let s = n.map.out.send(now, Sent::Request);
            out.push(Message::new(
                header(s),
                Body::TeamMap(TeamMap::Request { known }),
            ));
        }
        if let Some(chunks) = reply {
            n.map.asked = None;
            for t in chunks {
                let s = n.map.out.send(now, Sent::Reply);
                out.push(Message::new(
                    header(s),
                    Body::TeamMap(TeamMap::Trajectory(t)),
                ));
            }
        }
        Ok(out)
    }

    /// This robot's trajectory in wire chunks; no poses if the asker holds this version.
    fn trajectory_chunks(&self, held: u64) -> Result<Vec<Trajectory>, DpgoError> {
        let total = self.keys.len() as u64;
        let version = self.estimate_version;
        if held == version && held != 0 {
            return Ok(vec![Trajectory {
                anchor: self.anchor,
                version,
                total,
                poses: Vec::new(),
            }]);
        }
        let mut poses = Vec::with_capacity(self.keys.len());
        for (k, x) in self.keys.iter().zip(&self.poses) {
            let q = CompactPose::quantize(x).map_err(|source| DpgoError::Quantize {
                key: key::label(*k),
                source,
            })?;
            poses.push((*k, q));
        }
        if poses.is_empty() {
            return Ok(vec![Trajectory {
                anchor: self.anchor,
                version,
                total,
                poses,
            }]);
        }
        Ok(poses
            .chunks(MAX_TRAJECTORY_POSES)
            .map(|c| Trajectory {
                anchor: self.anchor,
                version,
                total,
                poses: c.to_vec(),
            })
            .collect())
    }

    pub(crate) fn map_receive(
        &mut self,
        neighbor: u8,
        h: &Header,
        m: &TeamMap,
    ) -> Result<bool, DpgoError> {
        let refuse = |reason: String| DpgoError::BadMessage {
            from: neighbor,
            reason,
        };
        if let TeamMap::Trajectory(t) = m {
            if let Some((k, _)) = t
                .poses
                .iter()
                .find(|(k, _)| key::robot(*k) != Some(neighbor))
            {
                self.stats.refused += 1;
                return Err(refuse(format!(
                    "trajectory pose {} is not the sender's",
                    key::label(*k)
                )));
            }
        }
        let Some(n) = self.neighbors.get_mut(&neighbor) else {
            self.stats.refused += 1;
            return Err(refuse("no closure with this robot".into()));
        };
        if n.map.rx.arrive(h.epoch, h.sequence) == Arrival::Stale {
            self.stats.ignored_stale += 1;
            return Ok(false);
        }
        match m {
            TeamMap::Request { known } => n.map.asked = Some(*known),
            TeamMap::Trajectory(t) => {
                let entry = self.team_map.entry(neighbor).or_default();
                if t.version != entry.version || t.anchor != entry.anchor {
                    // A new revision: its poses replace the old ones (an empty reply
                    // means the one we hold is current).
                    if !t.poses.is_empty() || entry.version == 0 {
                        entry.poses.clear();
                    }
                    entry.version = t.version;
                    entry.anchor = t.anchor;
                }
                entry.total = t.total;
                entry
                    .poses
                    .extend(t.poses.iter().map(|(k, q)| (*k, *q.se3())));
            }
        }
        Ok(true)
    }

    pub(crate) fn map_ack(
        &mut self,
        neighbor: u8,
        a: &doorslam_ipc::wire::Ack,
    ) -> Result<bool, DpgoError> {
        let Some(n) = self.neighbors.get_mut(&neighbor) else {
            return Ok(false);
        };
        if a.epoch != self.epoch {
            self.stats.ignored_stale += 1;
            return Ok(false);
        }
        let s = n.map.out.acknowledge(a);
        if s.delivered.iter().any(|x| matches!(x, Sent::Request)) {
            n.map.want = false;
        }
        for lost in s.lost {
            self.stats.resent += 1;
            match lost {
                Sent::Request => n.map.want = true,
                Sent::Reply => n.map.asked = Some(0),
            }
        }
        Ok(true)
    }
}
