//! `doorslam team certs --out DIR --robots a,b,c [--routers r1] [--team NAME] [--days N | --clockless]`:
//! the team CA and one certificate per robot and router for the TLS team link (logic in
//! `doorslam_team::certs`).

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::{Args, Subcommand};

#[derive(Debug, Args)]
pub struct TeamArgs {
    #[command(subcommand)]
    pub command: TeamCommand,
}

#[derive(Debug, Subcommand)]
pub enum TeamCommand {
    /// Generate the team CA (or reuse the one in --out) and a certificate + key per robot
    /// and router, for `[team.tls]`.
    Certs(CertsArgs),
}

#[derive(Debug, Args)]
pub struct CertsArgs {
    /// Output folder: ca.pem, ca.key, robots/<id>/{cert,key}.pem, routers/<name>/{cert,key}.pem.
    #[arg(long)]
    pub out: PathBuf,
    /// Robot ids (comma-separated): each gets a certificate whose common name is its id.
    #[arg(long, value_delimiter = ',')]
    pub robots: Vec<String>,
    /// Router names (comma-separated), for `doorslam router`.
    #[arg(long, value_delimiter = ',')]
    pub routers: Vec<String>,
    /// Team name (recorded in the CA; an existing CA of another team is refused).
    #[arg(long, default_value = "doorslam")]
    pub team: String,
    /// Validity of the robots' and routers' certificates, in days.
    #[arg(long, default_value_t = 365, conflicts_with = "clockless")]
    pub days: u32,
    /// Certificates (and a CA) valid from 1970 to 9999, for robots without a real-time
    /// clock or NTP: authentication stays (CA signature, mutual TLS, roster), expiry by date
    /// is replaced by the roster and a new team CA.
    #[arg(long)]
    pub clockless: bool,
}

pub fn run(args: TeamArgs) -> Result<()> {
    match args.command {
        TeamCommand::Certs(a) => certs(a),
    }
}

fn certs(args: CertsArgs) -> Result<()> {
    let request = doorslam_team::certs::CertsRequest {
        team: args.team,
        robots: args.robots,
        routers: args.routers,
        days: args.days,
        clockless: args.clockless,
    };
    let issued = doorslam_team::certs::generate(&args.out, &request)
        .with_context(|| format!("doorslam team certs --out {}", args.out.display()))?;
    let out = args.out.display();
    if issued.ca_created {
        println!(
            "team CA: {} (its key {out}/ca.key stays with you, not on the robots)",
            issued.ca.display()
        );
    } else {
        println!("team CA reused: {}", issued.ca.display());
    }
    for (who, cert, key) in &issued.certificates {
        println!("{who}: {} {}", cert.display(), key.display());
    }
    let roster = doorslam_team::certs::roster(&args.out)?;
    if let Some(first) = roster.first() {
        let quoted: Vec<String> = roster.iter().map(|r| format!("{r:?}")).collect();
        println!(
            "\nin robot {first}'s robot.toml (copy ca.pem and its own cert and key to it):\n\n[team.tls]\nca = \"{out}/ca.pem\"\ncert = \"{out}/robots/{first}/cert.pem\"\nkey = \"{out}/robots/{first}/key.pem\"\nrobots = [{}]",
            quoted.join(", ")
        );
    }
    Ok(())
}
