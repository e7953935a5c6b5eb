//! `doorslam router`: a Zenoh router embedded in the binary, for fleets where peer-to-peer
//! discovery does not reach (no multicast on the network, robots behind different links,
//! many robots: each robot keeps one link to the router instead of one per robot). Robots
//! connect to it as Zenoh clients (`[team] mode = "client"`, `listen = []`,
//! `connect = ["tls/<router>:7447"]`: Zenoh 1.10 routers relay between clients, not
//! between peers); it forwards the team's messages and liveliness tokens between them. With TLS it holds a certificate of the
//! team CA (common name [`crate::certs::ROUTER_COMMON_NAME`]) and enforces the same access
//! control as every robot ([`crate::security`]), so a robot reaching others through it can
//! still publish only as itself.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use serde::Deserialize;
use zenoh::{Session, Wait};

use crate::link::{open_team_session, team_name, LinkConfig, TeamError};
use crate::security::{Holder, Security, TlsSection};

/// `[router]` of a router's config file.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RouterSection {
    /// The team whose prefix the access control opens (`doorslam/<team>/...`).
    #[serde(default = "default_team")]
    pub team: String,
    #[serde(default = "default_listen")]
    pub listen: Vec<String>,
    /// Other routers to connect to.
    #[serde(default)]
    pub connect: Vec<String>,
    /// Off by default: a router is for networks where multicast does not reach.
    #[serde(default)]
    pub multicast_scouting: bool,
    #[serde(default)]
    pub tls: Option<TlsSection>,
}

fn default_team() -> String {
    "doorslam".into()
}

fn default_listen() -> Vec<String> {
    vec!["tcp/0.0.0.0:7447".into()]
}

impl Default for RouterSection {
    fn default() -> Self {
        Self {
            team: default_team(),
            listen: default_listen(),
            connect: Vec::new(),
            multicast_scouting: false,
            tls: None,
        }
    }
}

/// A router's config file: one `[router]` section.
#[derive(Debug, Clone, Default, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RouterFile {
    #[serde(default)]
    pub router: RouterSection,
}

/// A running router.
pub struct Router {
    session: Session,
}

impl Router {
    /// Checks the section (TLS files included) and opens the router session.
    pub fn open(section: &RouterSection) -> Result<Self, TeamError> {
        let team = team_name(&section.team)?;
        if section.listen.is_empty() && section.connect.is_empty() {
            return Err(TeamError::Config {
                key: "listen",
                reason: "a router needs at least one endpoint to listen on (or connect to)".into(),
            });
        }
        let security = match &section.tls {
            Some(tls) => Some(Security::check(tls, &team, &Holder::Router)?),
            None => {
                tracing::warn!(team, "router is open: no TLS, anyone who reaches it can join the team and inject messages");
                None
            }
        };
        let link = LinkConfig {
            listen: section.listen.clone(),
            connect: section.connect.clone(),
            multicast_scouting: section.multicast_scouting,
        };
        let session = open_team_session("router", &link, None, security.as_ref())?;
        tracing::info!(
            team,
            zid = %session.zid(),
            listen = ?section.listen,
            tls = security.is_some(),
            "router up"
        );
        Ok(Self { session })
    }

    pub fn session(&self) -> &Session {
        &self.session
    }

    /// Closes the session: every link to it goes down.
    pub fn close(self) -> Result<(), TeamError> {
        self.session.close().wait().map_err(|e| TeamError::Zenoh {
            what: "close router",
            reason: e.to_string(),
        })
    }
}

/// Runs a router until `stop` is set (SIGTERM/SIGINT in the CLI); logs robots and routers
/// as they connect and leave.
pub fn run(section: &RouterSection, stop: &AtomicBool) -> Result<(), TeamError> {
    let router = Router::open(section)?;
    doorslam_ipc::lifecycle::sd_notify("READY=1\nSTATUS=router");
    let watchdog = doorslam_ipc::lifecycle::watchdog_interval();
    let mut last_ping = std::time::Instant::now();
    let mut known = 0usize;
    while !stop.load(Ordering::Acquire) {
        std::thread::sleep(Duration::from_millis(200));
        if watchdog.is_some_and(|period| last_ping.elapsed() >= period) {
            doorslam_ipc::lifecycle::sd_notify("WATCHDOG=1");
            last_ping = std::time::Instant::now();
        }
        let peers = router.session().info().peers_zid().wait().count()
            + router.session().info().routers_zid().wait().count();
        if peers != known {
            tracing::info!(connected = peers, "router: sessions connected");
            known = peers;
        }
    }
    doorslam_ipc::lifecycle::sd_notify("STOPPING=1");
    router.close()
}
