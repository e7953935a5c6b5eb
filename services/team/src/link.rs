//! Zenoh peer sessions and the key expressions robots publish under.
//!
//! # Key expressions (the only ones the team link uses)
//!
//! | key expression | what | who declares it |
//! |---|---|---|
//! | `doorslam/<team>/alive/<robot>` | liveliness token: present while `<robot>`'s team link runs | each robot, once |
//! | `doorslam/<team>/alive/*` | liveliness subscriber (with history): token put = peer appeared, delete = peer left; liveliness queries every 3 s check it (`crate::presence`) | each robot |
//! | `doorslam/<team>/<to>/<kind>/<from>` | one wire message from `<from>` to `<to>`; `<kind>` is `Kind::name()` (`hello`, `descriptors`, `matches`, `verification_features`, `loop_closures`, `pose_estimates`, `ack`, ...) | a publisher per (peer, kind) |
//! | `doorslam/<team>/<me>/*/*` | subscriber of everything addressed to `<me>` | each robot |
//!
//! `<team>`, `<to>` and `<from>` follow the wire header's robot-id rule (1-32 characters of
//! `[a-z0-9_-]`), so no id can contain `/`, `*` or `$` and change what a pattern matches.
//! Liveliness keys have four chunks and message keys five, so the two never overlap even
//! for a robot called `alive`.
//!
//! With [`Security`] every link is TLS with mutual authentication and Zenoh's access
//! control lets each robot publish only under its own `<from>` and declare only its own
//! token (the rules are in [`crate::security`]).

use doorslam_ipc::wire::RobotId;
use zenoh::{Session, Wait};

use crate::security::{check_endpoints, Security, SecurityError};

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
    #[error("invalid team name {0:?}: use 1-32 characters of [a-z0-9_-]")]
    Team(String),
    #[error("invalid message kind {0:?} in a key expression: use [a-z0-9_-]+")]
    Kind(String),
    #[error("zenoh {what}: {reason}")]
    Zenoh { what: &'static str, reason: String },
    #[error(transparent)]
    Security(#[from] SecurityError),
}

/// How one robot joins the team network.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LinkConfig {
    /// Endpoints to listen on, e.g. `tcp/0.0.0.0:7447` (radio) or `tcp/127.0.0.1:PORT` (tests);
    /// `tls/...` with [`Security`].
    pub listen: Vec<String>,
    /// Endpoints of peers to connect to.
    pub connect: Vec<String>,
    /// Multicast scouting finds peers on a shared radio LAN; off in tests so that
    /// concurrent test runs never discover each other.
    pub multicast_scouting: bool,
}

/// How a robot's session joins the team network (`[team] mode`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Deserialize, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum LinkMode {
    /// A Zenoh peer: finds the other robots (multicast scouting on the radio LAN, or
    /// `connect`) and talks to each directly.
    #[default]
    Peer,
    /// A Zenoh client of a router (`doorslam router`): every message goes through the
    /// router. Zenoh 1.10 routers relay between their clients, not between peers (peers of
    /// one router are assumed to reach each other directly).
    Client,
}

impl LinkMode {
    /// Zenoh's name of the mode.
    pub fn zenoh(self) -> &'static str {
        match self {
            LinkMode::Peer => "peer",
            LinkMode::Client => "client",
        }
    }
}

fn json_list(items: &[String]) -> String {
    let quoted: Vec<String> = items.iter().map(|s| format!("{s:?}")).collect();
    format!("[{}]", quoted.join(","))
}

/// Opens a Zenoh session in peer mode.
pub fn open_peer(link: &LinkConfig) -> Result<Session, TeamError> {
    open_peer_with_lease(link, None)
}

/// Opens a Zenoh session in peer mode; `lease_ms` (Zenoh's default: 10 s) is how long a
/// silent link lives before the peer is declared gone (its liveliness token deleted).
pub fn open_peer_with_lease(
    link: &LinkConfig,
    lease_ms: Option<u64>,
) -> Result<Session, TeamError> {
    open_team_session("peer", link, lease_ms, None)
}

/// Opens a Zenoh session of the team link in `mode` (`peer` or `client` for robots,
/// [`LinkMode`]; `router` for [`crate::router`]); with `security`, TLS with mutual authentication and the team's
/// access control ([`crate::security`]), and only `tls/` endpoints.
pub fn open_team_session(
    mode: &str,
    link: &LinkConfig,
    lease_ms: Option<u64>,
    security: Option<&Security>,
) -> Result<Session, TeamError> {
    check_endpoints(&link.listen, "listen", security.is_some())?;
    check_endpoints(&link.connect, "connect", security.is_some())?;
    let mut config = zenoh::Config::default();
    let mut set = |key: &'static str, value: String| {
        config
            .insert_json5(key, &value)
            .map_err(|e| TeamError::Config {
                key,
                reason: e.to_string(),
            })
    };
    set("mode", format!("{mode:?}"))?;
    set("listen/endpoints", json_list(&link.listen))?;
    set("connect/endpoints", json_list(&link.connect))?;
    set(
        "scouting/multicast/enabled",
        link.multicast_scouting.to_string(),
    )?;
    // Between robots every byte crosses the radio: no shared-memory shortcut for large
    // payloads even when two robots' processes share a host (tests, HIL), or the ledger's
    // framing and the bytes on the link would not be what a real link carries.
    set("transport/shared_memory/enabled", "false".into())?;
    if let Some(lease) = lease_ms {
        set("transport/link/tx/lease", lease.to_string())?;
    }
    if let Some(security) = security {
        security.apply(&mut config)?;
    }
    zenoh::open(config).wait().map_err(|e| TeamError::Open {
        listen: link.listen.clone(),
        connect: link.connect.clone(),
        reason: e.to_string(),
    })
}

fn check_id(id: &str) -> Result<(), TeamError> {
    // Robot ids follow the rule of the id in every wire header (one definition).
    RobotId::new(id)
        .map(|_| ())
        .map_err(|_| TeamError::RobotId(id.to_string()))
}

fn check_team(team: &str) -> Result<(), TeamError> {
    RobotId::new(team)
        .map(|_| ())
        .map_err(|_| TeamError::Team(team.to_string()))
}

/// A team name: the robot-id rule, checked once.
pub fn team_name(team: &str) -> Result<String, TeamError> {
    check_team(team)?;
    Ok(team.to_string())
}

/// The key expression of one message: `doorslam/<team>/<to>/<kind>/<from>`, so a robot
/// subscribes to `doorslam/<team>/<me>/*/*` and sees who sent what.
pub fn key_expr(team: &str, to: &str, kind: &str, from: &str) -> Result<String, TeamError> {
    check_team(team)?;
    for id in [to, from] {
        check_id(id)?;
    }
    let kind_ok = !kind.is_empty()
        && kind
            .bytes()
            .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == b'_' || c == b'-');
    if !kind_ok {
        return Err(TeamError::Kind(kind.to_string()));
    }
    Ok(format!("doorslam/{team}/{to}/{kind}/{from}"))
}

/// Everything addressed to `me`: `doorslam/<team>/<me>/*/*`.
pub fn inbox_expr(team: &str, me: &str) -> Result<String, TeamError> {
    check_team(team)?;
    check_id(me)?;
    Ok(format!("doorslam/{team}/{me}/*/*"))
}

/// The liveliness token of `robot`: `doorslam/<team>/alive/<robot>`.
pub fn alive_expr(team: &str, robot: &str) -> Result<String, TeamError> {
    check_team(team)?;
    check_id(robot)?;
    Ok(format!("doorslam/{team}/alive/{robot}"))
}

/// The liveliness tokens of the whole team: `doorslam/<team>/alive/*`.
pub fn alive_pattern(team: &str) -> Result<String, TeamError> {
    check_team(team)?;
    Ok(format!("doorslam/{team}/alive/*"))
}

/// The robot a liveliness key names, if it is `doorslam/<team>/alive/<robot>` with a valid id.
pub fn parse_alive(team: &str, key: &str) -> Option<RobotId> {
    let rest = key.strip_prefix("doorslam/")?.strip_prefix(team)?;
    let robot = rest.strip_prefix("/alive/")?;
    RobotId::new(robot).ok()
}

/// `(kind, from)` of a message key `doorslam/<team>/<me>/<kind>/<from>`, if it has that form.
pub fn parse_message_key<'k>(team: &str, me: &str, key: &'k str) -> Option<(&'k str, RobotId)> {
    let rest = key.strip_prefix("doorslam/")?.strip_prefix(team)?;
    let rest = rest
        .strip_prefix('/')?
        .strip_prefix(me)?
        .strip_prefix('/')?;
    let (kind, from) = rest.split_once('/')?;
    Some((kind, RobotId::new(from).ok()?))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_round_trip_and_refuse_bad_ids() {
        let k = key_expr("t1", "b", "descriptors", "a").unwrap();
        assert_eq!(k, "doorslam/t1/b/descriptors/a");
        let (kind, from) = parse_message_key("t1", "b", &k).unwrap();
        assert_eq!((kind, from.as_str()), ("descriptors", "a"));
        assert!(parse_message_key("t1", "c", &k).is_none());
        assert!(parse_message_key("t", "b", &k).is_none());
        let alive = alive_expr("t1", "a").unwrap();
        assert_eq!(parse_alive("t1", &alive).unwrap().as_str(), "a");
        assert!(parse_alive("t1", "doorslam/t1/alive/A").is_none());
        assert!(key_expr("t/x", "b", "hello", "a").is_err());
        assert!(inbox_expr("t", "*").is_err());
    }
}
