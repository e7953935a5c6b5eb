//! A Zenoh session that publishes as rmw_zenoh does: nodes with their `NN` liveliness
//! token, publishers with their `MP` token and a Zenoh publisher on the topic's data key
//! expression, and every sample with rmw_zenoh's attachment (sequence number from 1 per
//! publisher, source time now, the publisher's GID). Node and entity ids come from one
//! counter, as in an rmw_zenoh context. Shared by the replay of a finished run and the
//! live publishers of a running robot.

use std::time::{SystemTime, UNIX_EPOCH};

use doorslam_ros2_wire::rmw::{Node, Publisher, Qos};
use doorslam_ros2_wire::{TypeDef, WireError};
use zenoh::liveliness::LivelinessToken;
use zenoh::qos::CongestionControl;
use zenoh::Wait;

/// Failures of the Zenoh side; each names its input.
#[derive(Debug, thiserror::Error)]
pub enum LiveError {
    #[error(transparent)]
    Record(#[from] crate::state::RecordError),
    #[error(transparent)]
    Wire(#[from] WireError),
    #[error("zenoh config {key}: {reason}")]
    Config { key: &'static str, reason: String },
    #[error("zenoh {what}: {reason}")]
    Zenoh { what: String, reason: String },
    #[error("--rate {0}: must be a finite number above 0")]
    Rate(f64),
    #[error("ros2.{key}: {reason}")]
    Section { key: &'static str, reason: String },
}

pub(crate) fn zerr(what: impl Into<String>) -> impl FnOnce(zenoh::Error) -> LiveError {
    let what = what.into();
    move |e| LiveError::Zenoh {
        what,
        reason: e.to_string(),
    }
}

/// Where the session listens and whom it connects to.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SessionOptions {
    /// `ROS_DOMAIN_ID` of the key expressions and tokens.
    pub domain_id: u32,
    /// Zenoh endpoints to listen on (`tcp/0.0.0.0:7447`) and to connect to (a laptop's
    /// `rmw_zenohd`, `tcp/<laptop>:7447`).
    pub listen: Vec<String>,
    pub connect: Vec<String>,
    pub multicast_scouting: bool,
}

fn json_list(items: &[String]) -> String {
    serde_json::to_string(items).unwrap_or_else(|_| "[]".into())
}

/// Nanoseconds since the Unix epoch: the attachment's source timestamp.
pub fn now_ns() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_nanos()).unwrap_or(i64::MAX))
}

/// One Zenoh session with its ROS graph entities; dropping it undeclares the tokens.
pub struct RosSession {
    session: zenoh::Session,
    zid: String,
    domain_id: u32,
    next_id: u64,
    /// Declared tokens (undeclared when dropped) and their key expressions, in order.
    tokens: Vec<LivelinessToken>,
    token_names: Vec<String>,
}

/// A publisher: rmw_zenoh's names for it, its Zenoh publisher and its last sequence number.
pub struct LivePublisher {
    pub wire: Publisher,
    zenoh: zenoh::pubsub::Publisher<'static>,
    sequence: i64,
    /// Bytes of payload put so far.
    pub bytes: u64,
}

impl LivePublisher {
    /// Puts one CDR payload with the next sequence number and the time now.
    pub fn put(&mut self, cdr: Vec<u8>) -> Result<(), LiveError> {
        self.sequence += 1;
        let attachment = self.wire.attachment(self.sequence, now_ns()).encode();
        self.bytes += cdr.len() as u64;
        self.zenoh
            .put(cdr)
            .attachment(attachment.to_vec())
            .wait()
            .map_err(zerr(format!("put {}", self.wire.key)))
    }

    /// Samples put so far.
    pub fn samples(&self) -> u64 {
        self.sequence as u64
    }
}

impl RosSession {
    /// Opens a peer session on `o`'s endpoints.
    pub fn open(o: &SessionOptions) -> Result<Self, LiveError> {
        let mut config = zenoh::Config::default();
        let mut set = |key: &'static str, value: String| {
            config
                .insert_json5(key, &value)
                .map_err(|e| LiveError::Config {
                    key,
                    reason: e.to_string(),
                })
        };
        set("mode", "\"peer\"".into())?;
        set("listen/endpoints", json_list(&o.listen))?;
        set("connect/endpoints", json_list(&o.connect))?;
        set(
            "scouting/multicast/enabled",
            o.multicast_scouting.to_string(),
        )?;
        let session = zenoh::open(config).wait().map_err(zerr("open session"))?;
        let zid = session.zid().to_string();
        Ok(Self {
            session,
            zid,
            domain_id: o.domain_id,
            next_id: 0,
            tokens: Vec::new(),
            token_names: Vec::new(),
        })
    }

    /// The session's id (the `<zid>` of every token).
    pub fn zid(&self) -> &str {
        &self.zid
    }

    /// Every token declared so far: nodes and publishers in declaration order.
    pub fn tokens(&self) -> &[String] {
        &self.token_names
    }

    fn declare_token(&mut self, token: String) -> Result<(), LiveError> {
        let t = self
            .session
            .liveliness()
            .declare_token(token.clone())
            .wait()
            .map_err(zerr(format!("token {token}")))?;
        self.tokens.push(t);
        self.token_names.push(token);
        Ok(())
    }

    /// Declares the node `<namespace>/<name>` and its token.
    pub fn node(&mut self, namespace: &str, name: &str) -> Result<Node, LiveError> {
        let node = Node::new(self.domain_id, &self.zid, self.next_id, namespace, name)?;
        self.next_id += 1;
        self.declare_token(node.token())?;
        Ok(node)
    }

    /// Declares a publisher of `node` on `topic` and its token. Samples that the network
    /// cannot take are dropped, never waited for: a slow laptop link must not hold up the
    /// process that publishes (the next sample carries the newer state).
    pub fn publisher(
        &mut self,
        node: &Node,
        topic: &str,
        ty: &'static TypeDef,
        qos: Qos,
    ) -> Result<LivePublisher, LiveError> {
        let wire = node.publisher(self.next_id, topic, ty, qos)?;
        self.next_id += 1;
        self.declare_token(wire.token.clone())?;
        let zenoh = self
            .session
            .declare_publisher(wire.key.clone())
            .congestion_control(CongestionControl::Drop)
            .wait()
            .map_err(zerr(format!("publisher {}", wire.key)))?;
        Ok(LivePublisher {
            wire,
            zenoh,
            sequence: 0,
            bytes: 0,
        })
    }

    /// Undeclares every token and closes the session.
    pub fn close(self) -> Result<(), LiveError> {
        let Self {
            session, tokens, ..
        } = self;
        drop(tokens);
        session.close().wait().map_err(zerr("close"))
    }
}

/// The QoS of a topic: tf2's listeners keep 100 transforms; the rest keep 10 (rclcpp's
/// usual depth).
pub fn qos_of(topic: &str) -> Qos {
    Qos::keep_last(if topic == "/tf" { 100 } else { 10 })
}
