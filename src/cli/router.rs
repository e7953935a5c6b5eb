//! `doorslam router [--config router.toml] [--listen EP]... [--connect EP]... [--team NAME]
//! [--ca F --cert F --key F --robots a,b,c] [--multicast-scouting]`: an embedded Zenoh
//! router for large fleets (logic in `doorslam_team::router`). Flags override the file.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use clap::Args;
use doorslam_team::router::{RouterFile, RouterSection};
use doorslam_team::security::TlsSection;

#[derive(Debug, Args)]
pub struct RouterArgs {
    /// Router configuration (TOML with a [router] section: team, listen, connect,
    /// multicast_scouting, [router.tls]); built-in defaults when absent.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Team name (key expressions doorslam/<team>/...).
    #[arg(long)]
    pub team: Option<String>,
    /// Endpoint to listen on, e.g. tls/0.0.0.0:7447 (repeatable; replaces the file's).
    #[arg(long)]
    pub listen: Vec<String>,
    /// Another router to connect to (repeatable; replaces the file's).
    #[arg(long)]
    pub connect: Vec<String>,
    /// Find and be found by peers with multicast scouting (off by default).
    #[arg(long)]
    pub multicast_scouting: bool,
    /// Team CA certificate (TLS; with --cert, --key and --robots).
    #[arg(long)]
    pub ca: Option<PathBuf>,
    /// This router's certificate (from doorslam team certs --routers).
    #[arg(long)]
    pub cert: Option<PathBuf>,
    /// This router's private key.
    #[arg(long)]
    pub key: Option<PathBuf>,
    /// Robot ids holding team certificates (comma-separated).
    #[arg(long, value_delimiter = ',')]
    pub robots: Vec<String>,
}

fn section(args: RouterArgs) -> Result<RouterSection> {
    let mut s = match &args.config {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("cannot read config {}", path.display()))?;
            toml::from_str::<RouterFile>(&text)
                .with_context(|| format!("invalid config {}", path.display()))?
                .router
        }
        None => RouterSection::default(),
    };
    if let Some(team) = args.team {
        s.team = team;
    }
    if !args.listen.is_empty() {
        s.listen = args.listen;
    }
    if !args.connect.is_empty() {
        s.connect = args.connect;
    }
    s.multicast_scouting |= args.multicast_scouting;
    let any_tls = args.ca.is_some() || args.cert.is_some() || args.key.is_some();
    if any_tls || !args.robots.is_empty() {
        let from_file = s.tls.take();
        let pick = |flag: Option<PathBuf>, file: Option<&PathBuf>, name: &str| -> Result<PathBuf> {
            match flag.or_else(|| file.cloned()) {
                Some(p) => Ok(p),
                None => bail!("--{name} is missing: TLS needs --ca, --cert, --key and --robots"),
            }
        };
        let robots = if args.robots.is_empty() {
            from_file
                .as_ref()
                .map(|t| t.robots.clone())
                .unwrap_or_default()
        } else {
            args.robots
        };
        if robots.is_empty() {
            bail!("--robots is missing: TLS needs --ca, --cert, --key and --robots");
        }
        s.tls = Some(TlsSection {
            ca: pick(args.ca, from_file.as_ref().map(|t| &t.ca), "ca")?,
            cert: pick(args.cert, from_file.as_ref().map(|t| &t.cert), "cert")?,
            key: pick(args.key, from_file.as_ref().map(|t| &t.key), "key")?,
            robots,
        });
    }
    Ok(s)
}

pub fn run(args: RouterArgs) -> Result<()> {
    let section = section(args)?;
    let stop = Arc::new(AtomicBool::new(false));
    let flag = stop.clone();
    ctrlc::set_handler(move || flag.store(true, Ordering::SeqCst))?;
    doorslam_team::router::run(&section, &stop)?;
    tracing::info!("router: stopped");
    Ok(())
}
