//! Robots as hosts of their own: one Linux network namespace per robot, each with its own
//! address on a shared bridge (veth pairs), as drones on a radio LAN. Radio range is
//! emulated with nftables (a pair out of range drops each other's packets), a weak radio
//! with `tc tbf` (bandwidth cap) and nftables `numgen` (random loss); this kernel has no
//! `netem`.
//!
//! Needs root, `ip` (iproute2), `nft` (nftables) and `tc`: `deploy/setup` installs them.
//! Names are unique per process and tag; [`Net`]'s `Drop` removes every namespace, the
//! bridge and the processes started in them, also when the caller fails.

use std::process::{Child, Command};

/// Failures of the emulated network: the command and what it printed.
#[derive(Debug, thiserror::Error)]
pub enum NetError {
    #[error("network namespaces need root (this process runs as uid {0})")]
    NotRoot(u32),
    #[error("`{command}` failed: {reason}")]
    Command { command: String, reason: String },
    #[error("robot {0} is not on this network")]
    NoRobot(usize),
}

/// Runs a command; its stdout, or an error with its stderr.
pub fn sh(args: &[&str]) -> Result<String, NetError> {
    let out = Command::new(args[0])
        .args(&args[1..])
        .output()
        .map_err(|e| NetError::Command {
            command: args.join(" "),
            reason: e.to_string(),
        })?;
    if !out.status.success() {
        return Err(NetError::Command {
            command: args.join(" "),
            reason: String::from_utf8_lossy(&out.stderr).trim().to_string(),
        });
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

/// Whether this process may create network namespaces.
pub fn is_root() -> bool {
    // SAFETY: geteuid has no preconditions and cannot fail.
    unsafe { libc::geteuid() == 0 }
}

/// A bridge and one namespace per robot; removed on drop, with the processes in them.
pub struct Net {
    ns: Vec<String>,
    veth: Vec<String>,
    addr: Vec<String>,
    bridge: String,
    children: Vec<Child>,
}

impl Net {
    /// `robots` namespaces named after `tag` (a few letters, unique among concurrent
    /// users in this process), addresses `10.<subnet>.<robot + 1>` / 24.
    pub fn new(tag: &str, robots: usize, subnet: [u8; 2]) -> Result<Net, NetError> {
        if !is_root() {
            // SAFETY: as above.
            return Err(NetError::NotRoot(unsafe { libc::geteuid() }));
        }
        let id = std::process::id() % 100_000;
        let net = Net {
            ns: (0..robots).map(|i| format!("ds{tag}{id}n{i}")).collect(),
            veth: (0..robots).map(|i| format!("ds{tag}{id}v{i}")).collect(),
            addr: (0..robots)
                .map(|i| format!("10.{}.{}.{}", subnet[0], subnet[1], i + 1))
                .collect(),
            bridge: format!("ds{tag}{id}br"),
            children: Vec::new(),
        };
        // Interface names hold 15 bytes.
        for name in net.veth.iter().chain([&net.bridge]) {
            if name.len() + 1 > 15 {
                return Err(NetError::Command {
                    command: format!("ip link add {name}"),
                    reason: "interface name longer than 14 bytes: use a shorter tag".into(),
                });
            }
        }
        sh(&["ip", "link", "add", &net.bridge, "type", "bridge"])?;
        sh(&["ip", "link", "set", &net.bridge, "up"])?;
        for i in 0..robots {
            let (ns, veth) = (net.ns[i].clone(), net.veth[i].clone());
            let peer = format!("{veth}p");
            sh(&["ip", "netns", "add", &ns])?;
            sh(&[
                "ip", "link", "add", &veth, "type", "veth", "peer", "name", &peer,
            ])?;
            sh(&["ip", "link", "set", &peer, "master", &net.bridge, "up"])?;
            sh(&["ip", "link", "set", &veth, "netns", &ns])?;
            let cidr = format!("{}/24", net.addr[i]);
            sh(&["ip", "-n", &ns, "addr", "add", &cidr, "dev", &veth])?;
            sh(&["ip", "-n", &ns, "link", "set", &veth, "up"])?;
            sh(&["ip", "-n", &ns, "link", "set", "lo", "up"])?;
            // Multicast scouting (peers found without a list) leaves by the radio.
            sh(&["ip", "-n", &ns, "route", "add", "224.0.0.0/4", "dev", &veth])?;
        }
        Ok(net)
    }

    /// Gives this host an address on the robots' bridge (`10.<subnet>.254`), so a process
    /// here (a laptop's `rmw_zenohd`) reaches the robots' addresses; returns it. The
    /// robots' loss rules (`--drop`) apply to its packets as to any host's on the radio.
    pub fn attach_host(&self) -> Result<String, NetError> {
        let first = self.addr.first().ok_or(NetError::NoRobot(0))?;
        let prefix = first.rsplit_once('.').map_or(first.as_str(), |(p, _)| p);
        let host = format!("{prefix}.254");
        sh(&[
            "ip",
            "addr",
            "add",
            &format!("{host}/24"),
            "dev",
            &self.bridge,
        ])?;
        Ok(host)
    }

    pub fn robots(&self) -> usize {
        self.ns.len()
    }

    /// Robot `i`'s address.
    pub fn addr(&self, i: usize) -> &str {
        &self.addr[i]
    }

    /// Robot `i`'s namespace.
    pub fn namespace(&self, i: usize) -> &str {
        &self.ns[i]
    }

    /// A command that runs `program` inside robot `i`'s namespace.
    pub fn command(&self, i: usize, program: &std::path::Path) -> Result<Command, NetError> {
        let ns = self.ns.get(i).ok_or(NetError::NoRobot(i))?;
        let mut c = Command::new("ip");
        c.args(["netns", "exec", ns]).arg(program);
        Ok(c)
    }

    /// Keeps a child to kill when the network goes away.
    pub fn adopt(&mut self, child: Child) {
        self.children.push(child);
    }

    fn pair_table(i: usize, j: usize) -> String {
        format!("dscut{}x{}", i.min(j), i.max(j))
    }

    /// Robots `i` and `j` out of radio range: each drops the other's packets (both
    /// namespaces, so neither direction gets through). Idempotent.
    pub fn cut(&self, i: usize, j: usize) -> Result<(), NetError> {
        let table = Self::pair_table(i, j);
        for (me, other) in [(i, j), (j, i)] {
            let ns = self.ns.get(me).ok_or(NetError::NoRobot(me))?;
            let peer = self.addr.get(other).ok_or(NetError::NoRobot(other))?;
            let _ = sh(&[
                "ip", "netns", "exec", ns, "nft", "delete", "table", "inet", &table,
            ]);
            let rules = format!(
                "add table inet {table}; \
                 add chain inet {table} in {{ type filter hook input priority 0; }}; \
                 add rule inet {table} in ip saddr {peer} drop; \
                 add chain inet {table} out {{ type filter hook output priority 0; }}; \
                 add rule inet {table} out ip daddr {peer} drop"
            );
            sh(&["ip", "netns", "exec", ns, "nft", &rules])?;
        }
        Ok(())
    }

    /// Robots `i` and `j` in range again. Idempotent.
    pub fn join(&self, i: usize, j: usize) -> Result<(), NetError> {
        let table = Self::pair_table(i, j);
        for me in [i, j] {
            let ns = self.ns.get(me).ok_or(NetError::NoRobot(me))?;
            // Absent table: already in range.
            let _ = sh(&[
                "ip", "netns", "exec", ns, "nft", "delete", "table", "inet", &table,
            ]);
        }
        Ok(())
    }

    /// A radio-like link: every robot's interface capped at `kbit` (tc tbf) and each robot
    /// dropping `loss_percent` of the packets it receives from the others at random.
    pub fn radio(&self, kbit: u32, loss_percent: u32) -> Result<(), NetError> {
        for i in 0..self.robots() {
            let rate = format!("{kbit}kbit");
            sh(&[
                "ip",
                "netns",
                "exec",
                &self.ns[i],
                "tc",
                "qdisc",
                "add",
                "dev",
                &self.veth[i],
                "root",
                "tbf",
                "rate",
                &rate,
                "burst",
                "4kb",
                "latency",
                "400ms",
            ])?;
            let rules = format!(
                "add table inet dsloss; \
                 add chain inet dsloss in {{ type filter hook input priority 0; }}; \
                 add rule inet dsloss in ip saddr 10.0.0.0/8 numgen random mod 100 < {loss_percent} drop"
            );
            sh(&["ip", "netns", "exec", &self.ns[i], "nft", &rules])?;
        }
        Ok(())
    }

    /// The random loss of [`Self::radio`] ends (the cap stays).
    pub fn clear_loss(&self) -> Result<(), NetError> {
        for ns in &self.ns {
            sh(&[
                "ip", "netns", "exec", ns, "nft", "delete", "table", "inet", "dsloss",
            ])?;
        }
        Ok(())
    }

    /// Random loss between robots, and nothing else: every robot drops each packet it
    /// receives from another robot with `probability` (nftables `numgen random`),
    /// counting the packets it received and those it dropped ([`Self::dropped_packets`]).
    pub fn drop_packets(&self, probability: f64) -> Result<(), NetError> {
        const SCALE: u64 = 1_000_000;
        let below = (probability.clamp(0.0, 1.0) * SCALE as f64).round() as u64;
        for ns in &self.ns {
            let rules = format!(
                "add table inet dsdrop; \
                 add chain inet dsdrop in {{ type filter hook input priority -10; }}; \
                 add rule inet dsdrop in ip saddr 10.0.0.0/8 counter; \
                 add rule inet dsdrop in ip saddr 10.0.0.0/8 numgen random mod {SCALE} < {below} counter drop"
            );
            sh(&["ip", "netns", "exec", ns, "nft", &rules])?;
        }
        Ok(())
    }

    /// Packets from other robots every robot received, and of them those the random loss
    /// of [`Self::drop_packets`] dropped, summed over the robots (0, 0 without it).
    pub fn dropped_packets(&self) -> (u64, u64) {
        let (mut seen, mut dropped) = (0, 0);
        for ns in &self.ns {
            let Ok(text) = sh(&[
                "ip", "netns", "exec", ns, "nft", "list", "table", "inet", "dsdrop",
            ]) else {
                continue;
            };
            let counts: Vec<u64> = text
                .split_whitespace()
                .collect::<Vec<_>>()
                .windows(2)
                .filter(|w| w[0] == "packets")
                .filter_map(|w| w[1].parse().ok())
                .collect();
            if let [s, d, ..] = counts[..] {
                seen += s;
                dropped += d;
            }
        }
        (seen, dropped)
    }

    /// Bytes robot `i`'s interface sent.
    pub fn tx_bytes(&self, i: usize) -> u64 {
        let path = format!("/sys/class/net/{}/statistics/tx_bytes", self.veth[i]);
        sh(&["ip", "netns", "exec", &self.ns[i], "cat", &path])
            .ok()
            .and_then(|s| s.trim().parse().ok())
            .unwrap_or(0)
    }
}

impl Drop for Net {
    fn drop(&mut self) {
        for c in &mut self.children {
            let _ = c.kill();
            let _ = c.wait();
        }
        for ns in &self.ns {
            let _ = sh(&["ip", "netns", "del", ns]);
        }
        let _ = sh(&["ip", "link", "del", &self.bridge]);
    }
}
