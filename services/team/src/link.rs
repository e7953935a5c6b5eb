//! Zenoh peer sessions and key expressions.

use doorslam_ipc::wire::RobotId;
use zenoh::{Session, Wait};

/// Failures of the inter-robot link.
#[derive(Debug, thiserror::Error)]
pub enum TeamError {
    #[error("zenoh config key {key}: {reason}")]
    Config { key: &'static str, reason: String },
    #[error("cannot open zenoh session (listen {listen:?}, connect {connect:?}): {reason}")]
    Open {
        listen: Vec<String>,
        connect: Vec<String>,
        reason: String,
    },
    #[error("invalid robot id {0:?}: use 1-32 characters of [a-z0-9_-]")]
    RobotId(String),
    #[error("invalid message kind {0:?} in a key expression: use [a-z0-9_-]+")]
    Kind(String),
}

/// How one robot joins the team network.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LinkConfig {
    /// Endpoints to listen on, e.g. `tcp/0.0.0.0:7447` (radio) or `tcp/127.0.0.1:PORT` (tests).
    pub listen: Vec<String>,
    /// Endpoints of peers to connect to.
    pub connect: Vec<String>,
    /// Multicast scouting finds peers on a shared radio LAN; off in tests so that
    /// concurrent test runs never discover each other.
    pub multicast_scouting: bool,
}

fn json_list(items: &[String]) -> String {
    let quoted: Vec<String> = items.iter().map(|s| format!("{s:?}")).collect();
    format!("[{}]", quoted.join(","))
}

/// Opens a Zenoh session in peer mode.
pub fn open_peer(link: &LinkConfig) -> Result<Session, TeamError> {
    let mut config = zenoh::Config::default();
    let mut set = |key: &'static str, value: String| {
        config
            .insert_json5(key, &value)
            .map_err(|e| TeamError::Config {
                key,
                reason: e.to_string(),
            })
    };
    set("mode", "\"peer\"".into())?;
    set("listen/endpoints", json_list(&link.listen))?;
    set("connect/endpoints", json_list(&link.connect))?;
    set(
        "scouting/multicast/enabled",
        link.multicast_scouting.to_string(),
    )?;
    zenoh::open(config).wait().map_err(|e| TeamError::Open {
        listen: link.listen.clone(),
        connect: link.connect.clone(),
        reason: e.to_string(),
    })
}

/// The one place key expressions are built: `doorslam/<to>/<kind>/<from>`, so a robot
/// subscribes to `doorslam/<me>/**` and sees who sent what.
pub fn key_expr(to: &str, kind: &str, from: &str) -> Result<String, TeamError> {
    // Robot ids follow the rule of the id in every wire header (one definition).
    for id in [to, from] {
        RobotId::new(id).map_err(|_| TeamError::RobotId(id.to_string()))?;
    }
    let kind_ok = !kind.is_empty()
        && kind
            .bytes()
            .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == b'_' || c == b'-');
    if !kind_ok {
        return Err(TeamError::Kind(kind.to_string()));
    }
    Ok(format!("doorslam/{to}/{kind}/{from}"))
}
