//! `doorslam team certs --out DIR --robots a,b,c [--routers r1] [--team NAME] [--days N | --clockless]`:
//! the team CA and one certificate per robot and router for the TLS team link (logic in
//! `doorslam_team::certs`); `doorslam team delivery-bench`: the team link's delivery
//! contract against zenoh-ext's, bytes counted on a relay that cuts the link (logic in
//! `doorslam_hil::delivery_bench`).

use std::path::PathBuf;

use std::time::Duration;

use anyhow::{bail, Context, Result};
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
    /// One stream of descriptor messages from robot a to robot b over two Zenoh sessions,
    /// carried by the team link's acknowledgements and resends and by zenoh-ext's
    /// AdvancedPublisher/AdvancedSubscriber, the link cut for a while: what each
    /// delivers and the bytes it costs both ways (Zenoh framing and control included).
    DeliveryBench(DeliveryBenchArgs),
}

#[derive(Debug, Args)]
pub struct DeliveryBenchArgs {
    /// Which layers, one run each, one after the other.
    #[arg(long, value_enum, value_delimiter = ',', default_values_t = [LayerArg::Acks, LayerArg::ZenohExt])]
    pub layers: Vec<LayerArg>,
    /// Messages robot a sends.
    #[arg(long, default_value_t = 300)]
    pub messages: u64,
    /// Descriptors per message (140 B each on the wire).
    #[arg(long, default_value_t = 2)]
    pub descriptors: usize,
    /// Messages per second.
    #[arg(long, default_value_t = 10.0)]
    pub rate_hz: f64,
    /// The link is cut this many seconds after the first message ...
    #[arg(long, default_value_t = 10.0)]
    pub cut_at_s: f64,
    /// ... for this many seconds (0: no cut).
    #[arg(long, default_value_t = 8.0)]
    pub cut_s: f64,
    /// zenoh-ext: samples the publisher keeps for recovery.
    #[arg(long, default_value_t = 128)]
    pub cache: usize,
    /// zenoh-ext: heartbeat period of sample-miss detection, seconds.
    #[arg(long, default_value_t = 0.5)]
    pub heartbeat_s: f64,
    /// zenoh-ext: the subscriber does not ask a publisher it detects again for its
    /// history (only the heartbeat's recovery of missed samples).
    #[arg(long)]
    pub no_history: bool,
    /// Acknowledgements: resend after this many milliseconds (doubling per resend).
    #[arg(long, default_value_t = 1000)]
    pub retransmit_ms: u64,
    /// Print one JSON object (`runs`: one report per layer) instead of the table.
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum LayerArg {
    Acks,
    ZenohExt,
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
        TeamCommand::DeliveryBench(a) => delivery_bench(a),
    }
}

fn seconds(flag: &str, s: f64) -> Result<Duration> {
    if !(0.0..=3600.0).contains(&s) {
        bail!("{flag} {s}: seconds between 0 and 3600");
    }
    Ok(Duration::from_secs_f64(s))
}

fn delivery_bench(args: DeliveryBenchArgs) -> Result<()> {
    use doorslam_hil::delivery_bench::{run, BenchOptions, Layer};
    if args.descriptors == 0 || args.descriptors > 256 {
        bail!("--descriptors {}: 1 to 256 per message", args.descriptors);
    }
    if !(1..=1_000_000).contains(&args.messages) {
        bail!("--messages {}: 1 to 1000000", args.messages);
    }
    if !(args.rate_hz > 0.0 && args.rate_hz <= 1000.0) {
        bail!("--rate-hz {}: more than 0, at most 1000", args.rate_hz);
    }
    if args.cache == 0 {
        bail!("--cache 0: zenoh-ext needs at least one sample to recover from");
    }
    let options = BenchOptions {
        messages: args.messages,
        descriptors: args.descriptors,
        rate_hz: args.rate_hz,
        cut_at: seconds("--cut-at-s", args.cut_at_s)?,
        cut_for: seconds("--cut-s", args.cut_s)?,
        cache: args.cache,
        heartbeat: seconds("--heartbeat-s", args.heartbeat_s)?,
        history: !args.no_history,
        retransmit_ms: args.retransmit_ms.max(1),
        ..BenchOptions::default()
    };
    let mut runs = Vec::new();
    for layer in &args.layers {
        let layer = match layer {
            LayerArg::Acks => Layer::Acks,
            LayerArg::ZenohExt => Layer::ZenohExt,
        };
        if !args.json {
            eprintln!(
                "{layer:?}: {} messages at {} Hz ...",
                options.messages, options.rate_hz
            );
        }
        runs.push(run(layer, &options).with_context(|| format!("delivery bench, {layer:?}"))?);
    }
    if args.json {
        println!("{}", serde_json::json!({ "runs": runs }));
        return Ok(());
    }
    println!("| layer | delivered | duplicates | out of order | missed (reported) | resends | bytes a→b | bytes b→a | × payload | recovered after cut (s) |");
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for r in &runs {
        println!(
            "| {:?} | {} / {} | {} | {} | {} | {} | {} | {} | {:.3} | {} |",
            r.layer,
            r.delivered,
            r.messages,
            r.duplicates,
            r.out_of_order,
            r.reported_missed,
            r.resends,
            r.bytes_a_to_b,
            r.bytes_b_to_a,
            r.overhead_ratio,
            r.recovered_after_s
                .map_or("-".into(), |s| format!("{s:.2}")),
        );
    }
    for r in runs.iter().filter(|r| !r.missing.is_empty()) {
        println!("{:?} never delivered: {:?}", r.layer, r.missing);
    }
    if let Some(r) = runs.first() {
        println!("payload: {} B ({} messages)", r.payload_bytes, r.messages);
    }
    Ok(())
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
