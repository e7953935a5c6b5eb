//! The [`Link`] over Zenoh: a peer session, this robot's liveliness token, a liveliness
//! subscriber with history (token put = [`LinkEvent::PeerAppeared`], delete =
//! [`LinkEvent::PeerLeft`]), a subscriber of everything addressed to this robot, and one
//! declared publisher per (peer, kind) so each message carries a numeric key id instead of
//! the key string (measured: see `ledger::ZENOH_FRAMING_BYTES`). No robot list, no team
//! size: whoever declares a token under the team's prefix is a peer. What the subscriber
//! reports is checked against liveliness queries ([`crate::presence`]): a missed put or
//! delete is mended, and a session whose tables lost a peer that still talks to it is
//! reopened.

use std::collections::{BTreeSet, HashMap};
use std::time::{Duration, Instant};

use doorslam_ipc::wire::{Kind, RobotId};
use zenoh::handlers::FifoChannelHandler;
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::{Publisher, Subscriber};
use zenoh::qos::Priority;
use zenoh::query::Reply;
use zenoh::sample::{Sample, SampleKind};
use zenoh::{Session, Wait};

use crate::link::{
    alive_expr, alive_pattern, inbox_expr, key_expr, open_team_session, parse_alive,
    parse_message_key, LinkConfig, LinkMode, TeamError,
};
use crate::node::{Link, LinkError, LinkEvent};
use crate::presence::{Presence, PresenceMends, PresenceRules};
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

/// The session and what is declared on it (replaced whole when the session is reopened).
struct Declared {
    session: Session,
    _token: LivelinessToken,
    alive: Subscriber<FifoChannelHandler<Sample>>,
    inbox: Subscriber<FifoChannelHandler<Sample>>,
    publishers: HashMap<(RobotId, Kind), Publisher<'static>>,
}

/// A liveliness query in flight and the robots it found so far.
struct Check {
    replies: FifoChannelHandler<Reply>,
    found: BTreeSet<RobotId>,
    timed_out: bool,
}

/// How long a liveliness query may take (for peers met it is answered locally).
const CHECK_TIMEOUT: Duration = Duration::from_secs(2);

/// One robot's Zenoh end of the team link.
pub struct ZenohLink {
    config: ZenohLinkConfig,
    d: Declared,
    presence: Presence,
    check: Option<Check>,
    opened: Instant,
    reopens: u64,
    /// The session was closed to be reopened; the next try is due then.
    reopen_due: Option<Instant>,
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
        Self::open_with(config, PresenceRules::default())
    }

    /// [`ZenohLink::open`] with the presence checks' rules.
    pub fn open_with(config: &ZenohLinkConfig, rules: PresenceRules) -> Result<Self, TeamError> {
        Ok(Self {
            d: Self::declare(config)?,
            presence: Presence::new(config.me.clone(), rules, 0),
            check: None,
            opened: Instant::now(),
            reopens: 0,
            reopen_due: None,
            config: config.clone(),
            published_bytes: 0,
            published_messages: 0,
        })
    }

    fn declare(config: &ZenohLinkConfig) -> Result<Declared, TeamError> {
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
        Ok(Declared {
            session,
            _token: token,
            alive,
            inbox,
            publishers: HashMap::new(),
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
        &self.d.session
    }

    /// Times the session was reopened because its tables lost a peer that kept talking.
    pub fn reopens(&self) -> u64 {
        self.reopens
    }

    /// What the presence checks mended so far.
    pub fn presence_mends(&self) -> PresenceMends {
        PresenceMends {
            found_by_check: self.presence.found_by_check,
            lost_by_check: self.presence.lost_by_check,
            reopens: self.reopens,
        }
    }

    /// Closes the session (the token goes with it: peers see this robot leave).
    pub fn close(self) -> Result<(), TeamError> {
        self.d.session.close().wait().map_err(zerr("close"))
    }

    fn now_ms(&self) -> u64 {
        self.opened.elapsed().as_millis() as u64
    }

    /// Starts a liveliness query when one is due, and takes in the replies of the one in
    /// flight; when it is done, applies its word ([`Presence::checked`]).
    fn check_presence(&mut self, out: &mut Vec<LinkEvent>) {
        if self.reopen_due.is_some() {
            self.try_reopen();
            return;
        }
        let now = self.now_ms();
        if self.check.is_none() && self.presence.start_check(now) {
            let started = alive_pattern(&self.config.team).and_then(|k| {
                self.d
                    .session
                    .liveliness()
                    .get(k)
                    .timeout(CHECK_TIMEOUT)
                    .wait()
                    .map_err(zerr("liveliness query"))
            });
            match started {
                Ok(replies) => {
                    self.check = Some(Check {
                        replies,
                        found: BTreeSet::new(),
                        timed_out: false,
                    })
                }
                Err(e) => {
                    tracing::warn!(error = %e, "presence check not started");
                    self.presence.checked(&BTreeSet::new(), false, now);
                }
            }
        }
        let Some(check) = &mut self.check else {
            return;
        };
        let done = loop {
            match check.replies.try_recv() {
                Ok(Some(reply)) => match reply.result() {
                    Ok(sample) => {
                        if let Some(peer) =
                            parse_alive(&self.config.team, sample.key_expr().as_str())
                        {
                            check.found.insert(peer);
                        }
                    }
                    Err(_) => check.timed_out = true,
                },
                Ok(None) => break false,
                Err(_) => break true,
            }
        };
        if !done {
            return;
        }
        let Some(Check {
            found, timed_out, ..
        }) = self.check.take()
        else {
            return;
        };
        let checked = self.presence.checked(&found, !timed_out, now);
        out.extend(checked.events);
        if checked.reopen {
            self.reopen();
        }
    }

    /// A new session in place of one whose routing tables lost a peer: new token, new
    /// subscribers (with history), new publishers. Peers see this robot leave and come
    /// back; what the protocol holds is resent on that meeting. The old session is closed
    /// first (the new one listens on the same endpoints); while no new one opens, the link
    /// tries again every second and publishing fails (the protocol resends later).
    fn reopen(&mut self) {
        if let Err(e) = self.d.session.close().wait() {
            tracing::debug!(error = %e, "old session close");
        }
        self.d.publishers.clear();
        self.reopen_due = Some(Instant::now());
        self.try_reopen();
    }

    fn try_reopen(&mut self) {
        match self.reopen_due {
            Some(due) if Instant::now() >= due => {}
            _ => return,
        }
        match Self::declare(&self.config) {
            Ok(d) => {
                self.d = d;
                self.reopen_due = None;
                self.reopens += 1;
                self.presence.reopened(self.now_ms());
                tracing::warn!(reopens = self.reopens, "team link: Zenoh session reopened");
            }
            Err(e) => {
                tracing::warn!(error = %e, "team link: Zenoh session not reopened; trying again in 1 s");
                self.reopen_due = Some(Instant::now() + Duration::from_secs(1));
            }
        }
    }

    /// One inbox sample as a link event; a message from a robot not counted present asks
    /// for a presence check.
    fn take_in(&mut self, s: Sample, out: &mut Vec<LinkEvent>) {
        let key = s.key_expr().as_str();
        let bytes = s.payload().to_bytes().into_owned();
        match parse_message_key(&self.config.team, self.config.me.as_str(), key) {
            Some((kind, from)) => {
                let now = self.now_ms();
                self.presence.heard_from(&from, now);
                out.push(LinkEvent::Message {
                    from,
                    kind: kind.to_string(),
                    bytes,
                })
            }
            None => out.push(LinkEvent::Malformed {
                key: key.to_string(),
                bytes: bytes.len(),
            }),
        }
    }

    fn drain(&mut self, out: &mut Vec<LinkEvent>) {
        while let Ok(Some(s)) = self.d.alive.try_recv() {
            let Some(peer) = parse_alive(&self.config.team, s.key_expr().as_str()) else {
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
            out.extend(self.presence.token(peer, s.kind() == SampleKind::Put));
        }
        while let Ok(Some(s)) = self.d.inbox.try_recv() {
            self.take_in(s, out);
        }
        self.check_presence(out);
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
        let publisher = match self.d.publishers.entry((to.clone(), kind)) {
            std::collections::hash_map::Entry::Occupied(o) => o.into_mut(),
            std::collections::hash_map::Entry::Vacant(v) => {
                let key = key_expr(
                    &self.config.team,
                    to.as_str(),
                    kind.name(),
                    self.config.me.as_str(),
                )
                .map_err(|e| err(e.to_string()))?;
                let p = self
                    .d
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
            if let Ok(Some(s)) = self.d.inbox.recv_timeout(slice) {
                self.take_in(s, &mut out);
            }
        }
    }
}
