//! The [`Link`] over Zenoh: a peer session, this robot's liveliness token, a liveliness
//! subscriber with history (token put = [`LinkEvent::PeerAppeared`], delete =
//! [`LinkEvent::PeerLeft`]), a subscriber of everything addressed to this robot, and one
//! declared publisher per (peer, kind) so each message carries a numeric key id instead of
//! the key string (measured: see `ledger::ZENOH_FRAMING_BYTES`). No robot list, no team
//! size: whoever declares a token under the team's prefix is a peer.

use std::collections::HashMap;
use std::time::{Duration, Instant};

use doorslam_ipc::wire::{Kind, RobotId};
use zenoh::handlers::FifoChannelHandler;
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::{Publisher, Subscriber};
use zenoh::qos::Priority;
use zenoh::sample::{Sample, SampleKind};
use zenoh::{Session, Wait};

use crate::link::{
    alive_expr, alive_pattern, inbox_expr, key_expr, open_team_session, parse_alive,
    parse_message_key, LinkConfig, LinkMode, TeamError,
};
use crate::node::{Link, LinkError, LinkEvent};
use crate::security::Security;

/// How a robot joins its team over Zenoh.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ZenohLinkConfig {
    pub team: String,
    pub me: RobotId,
    pub link: LinkConfig,
    /// Peer (robots reach each other directly) or client of a router.
    pub mode: LinkMode,
    /// Zenoh link lease: a peer out of range is declared gone after this long.
    pub lease_ms: Option<u64>,
    /// TLS with mutual authentication and access control; None: plain TCP, open to anyone
    /// on the network.
    pub security: Option<Security>,
}

/// One robot's Zenoh end of the team link.
pub struct ZenohLink {
    session: Session,
    team: String,
    me: RobotId,
    _token: LivelinessToken,
    alive: Subscriber<FifoChannelHandler<Sample>>,
    inbox: Subscriber<FifoChannelHandler<Sample>>,
    publishers: HashMap<(RobotId, Kind), Publisher<'static>>,
    published_bytes: u64,
    published_messages: u64,
}

fn zerr(what: &'static str) -> impl Fn(zenoh::Error) -> TeamError {
    move |e| TeamError::Zenoh {
        what,
        reason: e.to_string(),
    }
}

impl ZenohLink {
    /// Opens the session, declares the token and both subscribers.
    pub fn open(config: &ZenohLinkConfig) -> Result<Self, TeamError> {
        let session = open_team_session(
            config.mode.zenoh(),
            &config.link,
            config.lease_ms,
            config.security.as_ref(),
        )?;
        let me = config.me.as_str();
        let inbox = session
            .declare_subscriber(inbox_expr(&config.team, me)?)
            .wait()
            .map_err(zerr("inbox subscriber"))?;
        let alive = session
            .liveliness()
            .declare_subscriber(alive_pattern(&config.team)?)
            .history(true)
            .wait()
            .map_err(zerr("liveliness subscriber"))?;
        let token = session
            .liveliness()
            .declare_token(alive_expr(&config.team, me)?)
            .wait()
            .map_err(zerr("liveliness token"))?;
        Ok(Self {
            session,
            team: config.team.clone(),
            me: config.me.clone(),
            _token: token,
            alive,
            inbox,
            publishers: HashMap::new(),
            published_bytes: 0,
            published_messages: 0,
        })
    }

    /// [`ZenohLink::open`], retried every second while a client's router is unreachable
    /// (a robot may start before it is in range of the router; a peer's session opens
    /// without anyone to talk to). `None`: `stop` was set first.
    pub fn open_until(
        config: &ZenohLinkConfig,
        stop: &std::sync::atomic::AtomicBool,
    ) -> Result<Option<Self>, TeamError> {
        let mut warned = false;
        loop {
            match Self::open(config) {
                Ok(link) => return Ok(Some(link)),
                Err(TeamError::Open { reason, .. }) if config.mode == LinkMode::Client => {
                    if !warned {
                        tracing::warn!(connect = ?config.link.connect, reason, "router unreachable: retrying every second");
                        warned = true;
                    }
                }
                Err(e) => return Err(e),
            }
            for _ in 0..10 {
                if stop.load(std::sync::atomic::Ordering::Acquire) {
                    return Ok(None);
                }
                std::thread::sleep(Duration::from_millis(100));
            }
        }
    }

    /// Bytes handed to Zenoh by [`Link::publish`], counted apart from the ledger.
    pub fn published_bytes(&self) -> u64 {
        self.published_bytes
    }

    pub fn published_messages(&self) -> u64 {
        self.published_messages
    }

    pub fn session(&self) -> &Session {
        &self.session
    }

    /// Closes the session (the token goes with it: peers see this robot leave).
    pub fn close(self) -> Result<(), TeamError> {
        self.session.close().wait().map_err(zerr("close"))
    }

    fn drain(&self, out: &mut Vec<LinkEvent>) {
        while let Ok(Some(s)) = self.alive.try_recv() {
            let Some(peer) = parse_alive(&self.team, s.key_expr().as_str()) else {
                // A token under the team's prefix that names no valid robot: counted once
                // (when declared, not again when it goes).
                if s.kind() == SampleKind::Put {
                    out.push(LinkEvent::Malformed {
                        key: s.key_expr().to_string(),
                        bytes: 0,
                    });
                }
                continue;
            };
            if peer == self.me {
                continue;
            }
            out.push(match s.kind() {
                SampleKind::Put => LinkEvent::PeerAppeared(peer),
                SampleKind::Delete => LinkEvent::PeerLeft(peer),
            });
        }
        while let Ok(Some(s)) = self.inbox.try_recv() {
            let key = s.key_expr().as_str();
            let bytes = s.payload().to_bytes().into_owned();
            match parse_message_key(&self.team, self.me.as_str(), key) {
                Some((kind, from)) => out.push(LinkEvent::Message {
                    from,
                    kind: kind.to_string(),
                    bytes,
                }),
                None => out.push(LinkEvent::Malformed {
                    key: key.to_string(),
                    bytes: bytes.len(),
                }),
            }
        }
    }
}

/// The Zenoh transmission queue of a message kind. Zenoh serves its queues in priority
/// order, so on a radio that cannot keep up, the small messages that keep the team
/// together (sessions, acknowledgements, routes, graphs, estimates, closures) do not wait
/// behind, nor are dropped for, the bulk of verification packets, which are resent
/// anyway and only cost a candidate closure some delay.
fn priority(kind: Kind) -> Priority {
    match kind {
        Kind::VerificationFeatures => Priority::DataLow,
        Kind::Descriptors | Kind::Matches => Priority::Data,
        Kind::Hello
        | Kind::Ack
        | Kind::LoopClosures
        | Kind::PoseEstimates
        | Kind::SeparatorGraph
        | Kind::Route
        | Kind::TeamMap => Priority::DataHigh,
    }
}

impl Link for ZenohLink {
    fn publish(&mut self, to: &RobotId, kind: Kind, bytes: &[u8]) -> Result<(), LinkError> {
        let err = |reason: String| LinkError::Publish {
            to: to.to_string(),
            kind: kind.name(),
            reason,
        };
        let publisher = match self.publishers.entry((to.clone(), kind)) {
            std::collections::hash_map::Entry::Occupied(o) => o.into_mut(),
            std::collections::hash_map::Entry::Vacant(v) => {
                let key = key_expr(&self.team, to.as_str(), kind.name(), self.me.as_str())
                    .map_err(|e| err(e.to_string()))?;
                let p = self
                    .session
                    .declare_publisher(key)
                    .priority(priority(kind))
                    .wait()
                    .map_err(|e| err(e.to_string()))?;
                v.insert(p)
            }
        };
        publisher
            .put(bytes.to_vec())
            .wait()
            .map_err(|e| err(e.to_string()))?;
        self.published_bytes += bytes.len() as u64;
        self.published_messages += 1;
        Ok(())
    }

    fn poll_events(&mut self, timeout: Duration) -> Vec<LinkEvent> {
        let deadline = Instant::now() + timeout;
        let mut out = Vec::new();
        loop {
            self.drain(&mut out);
            let now = Instant::now();
            if !out.is_empty() || now >= deadline {
                return out;
            }
            // Two channels to wait on: block on the inbox in short slices, checking the
            // liveliness channel between them.
            let slice = (deadline - now).min(Duration::from_millis(5));
            if let Ok(Some(s)) = self.inbox.recv_timeout(slice) {
                let key = s.key_expr().as_str();
                let bytes = s.payload().to_bytes().into_owned();
                match parse_message_key(&self.team, self.me.as_str(), key) {
                    Some((kind, from)) => out.push(LinkEvent::Message {
                        from,
                        kind: kind.to_string(),
                        bytes,
                    }),
                    None => out.push(LinkEvent::Malformed {
                        key: key.to_string(),
                        bytes: bytes.len(),
                    }),
                }
            }
        }
    }
}
