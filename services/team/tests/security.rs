//! The team link with TLS and access control, over real Zenoh sessions on loopback (unique
//! ports and team names): a peer without a team certificate cannot open a link nor inject
//! anything; a team robot cannot publish as another robot, claim its token or its epoch;
//! a certificate of the team CA outside the roster can do nothing. Each test has a
//! positive control (a team robot does get through the same listener), so a broken link
//! cannot pass for a secure one.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use doorslam_ipc::wire::{Header, Hello, Kind, Message, RobotId};
use doorslam_team::certs::{TeamCa, Validity};
use doorslam_team::security::{Security, TlsSection};
use doorslam_team::zenoh_link::ZenohLink;
use doorslam_team::Node;
use zenoh::{Session, Wait};

mod common;
use common::tls::{checked, free_port, make_certs, make_certs_with, tls, zenoh_robot};

fn id(s: &str) -> RobotId {
    RobotId::new(s).unwrap()
}

const KEYFRAMES: u64 = 60;

/// A robot of the team (the stand-ins, `KEYFRAMES` made) on a Zenoh session with `security`.
fn robot(
    team: &str,
    name: &str,
    index: u8,
    listen: Vec<String>,
    connect: Vec<String>,
    security: Security,
) -> (Node, ZenohLink) {
    let r = zenoh_robot(team, name, index, KEYFRAMES, listen, connect, security);
    (r.node, r.link)
}

/// A malicious session: TLS with `section`'s files, its own access control switched off
/// (it does what it likes; only the receiving side's rules can stop it).
fn rogue_tls(team: &str, section: &TlsSection, connect: &str) -> Session {
    let security = Security {
        team: team.into(),
        ca: section.ca.clone(),
        cert: section.cert.clone(),
        key: section.key.clone(),
        roster: vec![],
        expires_unix_s: i64::MAX,
    };
    let mut config = zenoh::Config::default();
    config.insert_json5("mode", "\"peer\"").unwrap();
    config.insert_json5("listen/endpoints", "[]").unwrap();
    config
        .insert_json5("connect/endpoints", &format!("[\"{connect}\"]"))
        .unwrap();
    config
        .insert_json5("scouting/multicast/enabled", "false")
        .unwrap();
    security.apply(&mut config).unwrap();
    config
        .insert_json5("access_control/enabled", "false")
        .unwrap();
    zenoh::open(config).wait().unwrap()
}

/// A session with a raw Zenoh config (intruders without team certificates).
fn raw_session(settings: &[(&str, String)]) -> Session {
    let mut config = zenoh::Config::default();
    config.insert_json5("mode", "\"peer\"").unwrap();
    config.insert_json5("listen/endpoints", "[]").unwrap();
    config
        .insert_json5("scouting/multicast/enabled", "false")
        .unwrap();
    for (k, v) in settings {
        config.insert_json5(k, v).unwrap();
    }
    zenoh::open(config).wait().unwrap()
}

/// A well-formed Hello claiming to come from `sender` in a huge epoch: if it ever reached a
/// robot, that robot would take every later real message of `sender` for a stale one.
fn forged_hello(sender: &str) -> Vec<u8> {
    Message::new(
        Header {
            sender: id(sender),
            epoch: u64::MAX,
            sequence: 0,
        },
        Hello {
            robot: 0,
            heard: None,
            base: 0,
        },
    )
    .encode()
    .unwrap()
}

/// What an intruder tries: a's token, messages as a (forged epoch), and wildcard keys.
struct Injector {
    session: Session,
    _tokens: Vec<zenoh::liveliness::LivelinessToken>,
    puts: Vec<(String, Vec<u8>)>,
}

impl Injector {
    fn new(session: Session, team: &str, tokens: &[&str], puts: Vec<(String, Vec<u8>)>) -> Self {
        let tokens = tokens
            .iter()
            .map(|r| {
                session
                    .liveliness()
                    .declare_token(format!("doorslam/{team}/alive/{r}"))
                    .wait()
                    .unwrap()
            })
            .collect();
        Self {
            session,
            _tokens: tokens,
            puts,
        }
    }

    fn inject(&self) {
        for (key, bytes) in &self.puts {
            // Errors are the point for some intruders (no route): ignored.
            let _ = self.session.put(key, bytes.clone()).wait();
        }
    }

    fn links(&self) -> usize {
        self.session.info().peers_zid().wait().count()
    }
}

fn step(nodes: &mut [(&mut Node, &mut ZenohLink)], start: Instant) {
    let now = start.elapsed().as_millis() as u64;
    for (n, l) in nodes.iter_mut() {
        n.step(*l, now, Duration::from_millis(5));
    }
}

fn rendezvous_done(a: &Node, b: &Node) -> bool {
    let (ida, idb) = (id("a"), id("b"));
    let delivered = b
        .session(&ida)
        .map_or(0, |s| s.delivered_descriptors().len() as u64);
    let acked = a.session(&idb).is_some_and(|s| {
        [Kind::Descriptors, Kind::LoopClosures]
            .iter()
            .all(|&k| s.unacknowledged(k).is_empty())
    });
    delivered == KEYFRAMES && acked
}

#[test]
fn a_peer_without_the_team_certificate_cannot_connect_or_inject() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let team = format!("sx{}", std::process::id());
    make_certs(d, &team, &["a", "b"]);
    let roster = ["a", "b"];
    let endpoint = format!("tls/127.0.0.1:{}", free_port());
    let (mut b, mut lb) = robot(
        &team,
        "b",
        1,
        vec![endpoint.clone()],
        vec![],
        checked(&tls(d, "b", &roster), &team, "b"),
    );
    let tcp_endpoint = endpoint.replace("tls/", "tcp/");
    let msg_key = format!("doorslam/{team}/b/hello/a");
    let puts = vec![
        (msg_key.clone(), forged_hello("a")),
        (format!("doorslam/{team}/b/hello/*"), forged_hello("a")),
    ];

    // 1. A CA of its own ("the same team name"), a certificate for "a" signed by it.
    let rogue_dir = d.join("rogue");
    make_certs(&rogue_dir, &team, &["a"]);
    let rogue = Injector::new(
        rogue_tls(&team, &tls(&rogue_dir, "a", &roster), &endpoint),
        &team,
        &["a"],
        puts.clone(),
    );
    // 2. Plain TCP to the TLS port.
    let plain = Injector::new(
        raw_session(&[("connect/endpoints", format!("[\"{tcp_endpoint}\"]"))]),
        &team,
        &["a"],
        puts.clone(),
    );
    // 3. TLS trusting the team CA (it knows b's certificate is genuine) but with no client
    //    certificate of its own.
    let ca = d.join("ca.pem");
    let anonymous = Injector::new(
        raw_session(&[
            ("connect/endpoints", format!("[\"{endpoint}\"]")),
            (
                "transport/link/tls/root_ca_certificate",
                format!("{:?}", ca.to_str().unwrap()),
            ),
            ("transport/link/tls/verify_name_on_connect", "false".into()),
        ]),
        &team,
        &["a"],
        puts.clone(),
    );
    // 4. A self-signed certificate for "a" presented as a client certificate.
    let self_signed = TeamCa::create(&team, Validity::days_from_now(2)).unwrap();
    let (cert, key) = self_signed.issue("a", Validity::days_from_now(2)).unwrap();
    let (cp, kp) = (d.join("self.pem"), d.join("self.key"));
    std::fs::write(&cp, cert).unwrap();
    std::fs::write(&kp, key).unwrap();
    let path = |p: &PathBuf| format!("{:?}", p.to_str().unwrap());
    let self_signed = Injector::new(
        raw_session(&[
            ("connect/endpoints", format!("[\"{endpoint}\"]")),
            ("transport/link/tls/root_ca_certificate", path(&ca)),
            ("transport/link/tls/connect_certificate", path(&cp)),
            ("transport/link/tls/connect_private_key", path(&kp)),
            ("transport/link/tls/enable_mtls", "true".into()),
            ("transport/link/tls/verify_name_on_connect", "false".into()),
        ]),
        &team,
        &["a"],
        puts,
    );
    let intruders = [&rogue, &plain, &anonymous, &self_signed];

    // Three seconds of trying (Zenoh retries its connections meanwhile).
    let start = Instant::now();
    while start.elapsed() < Duration::from_secs(3) {
        for i in &intruders {
            i.inject();
        }
        step(&mut [(&mut b, &mut lb)], start);
    }
    for (name, i) in [
        "rogue CA",
        "plain TCP",
        "no client certificate",
        "self-signed",
    ]
    .iter()
    .zip(intruders.iter())
    {
        assert_eq!(i.links(), 0, "{name}: opened a link to b");
    }
    assert!(b.session(&id("a")).is_none(), "b saw a token of \"a\"");
    {
        let ledger = b.ledger().lock().to_file();
        assert!(ledger.traffic.is_empty(), "{:?}", ledger.traffic);
        assert!(ledger.dropped.is_empty(), "{:?}", ledger.dropped);
    }

    // Positive control: the real a, with its team certificate, gets through the same
    // listener and completes a rendezvous, in its own epoch (not the forged one).
    let (mut a, mut la) = robot(
        &team,
        "a",
        0,
        vec![],
        vec![endpoint],
        checked(&tls(d, "a", &roster), &team, "a"),
    );
    while !rendezvous_done(&a, &b) {
        assert!(
            start.elapsed() < Duration::from_secs(40),
            "rendezvous of the team robots incomplete: a {:?}, b {:?}",
            a.session(&id("b")).map(|s| s.stats().clone()),
            b.session(&id("a")).map(|s| s.stats().clone())
        );
        for i in &intruders {
            i.inject();
        }
        step(&mut [(&mut a, &mut la), (&mut b, &mut lb)], start);
    }
    let sb = b.session(&id("a")).unwrap().stats().clone();
    assert_eq!(sb.descriptors_delivered, KEYFRAMES);
    assert_eq!(sb.descriptors_redelivered, 0);
    let ledger = b.ledger().lock();
    // Not "unknown_peer": a's first message may overtake a's liveliness token (Zenoh orders
    // neither against the other); b drops it and a resends. The intruders never reach b at
    // all: they get no link (below).
    for reason in ["stale_epoch", "wrong_sender", "bad_key"] {
        assert_eq!(ledger.dropped_count(reason), 0, "{reason}");
    }
    drop(ledger);
    for i in &intruders {
        assert_eq!(i.links(), 0, "an intruder got a link while a was in");
    }
    la.close().unwrap();
    lb.close().unwrap();
}

#[test]
fn a_team_robot_cannot_publish_as_another_and_an_unlisted_certificate_can_do_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let team = format!("sy{}", std::process::id());
    // z's certificate is signed by the team CA but z is not in the roster.
    make_certs(d, &team, &["a", "b", "c", "z"]);
    let roster = ["a", "b", "c"];
    let endpoint = format!("tls/127.0.0.1:{}", free_port());
    let (mut b, mut lb) = robot(
        &team,
        "b",
        1,
        vec![endpoint.clone()],
        vec![],
        checked(&tls(d, "b", &roster), &team, "b"),
    );
    let (mut a, mut la) = robot(
        &team,
        "a",
        0,
        vec![],
        vec![endpoint.clone()],
        checked(&tls(d, "a", &roster), &team, "a"),
    );
    // c, a team robot, impersonates a: a's token, a Hello with a's id and a huge epoch under
    // a's key, the same under a wildcard; and one garbage message under its own key (the
    // positive control: c's link to b works, so only the access control stops the rest).
    let c = Injector::new(
        rogue_tls(&team, &tls(d, "c", &roster), &endpoint),
        &team,
        &["a", "c"],
        vec![
            (format!("doorslam/{team}/b/hello/a"), forged_hello("a")),
            (
                format!("doorslam/{team}/b/descriptors/a"),
                forged_hello("a"),
            ),
            (format!("doorslam/{team}/b/hello/*"), forged_hello("a")),
            (format!("doorslam/{team}/b/hello/c"), vec![0xff; 8]),
        ],
    );
    let z = Injector::new(
        rogue_tls(&team, &tls(d, "z", &roster), &endpoint),
        &team,
        &["z", "a"],
        vec![
            (format!("doorslam/{team}/b/hello/z"), vec![0xff; 8]),
            (format!("doorslam/{team}/b/hello/a"), forged_hello("a")),
        ],
    );
    let start = Instant::now();
    let c_through = |b: &Node| {
        b.ledger()
            .lock()
            .to_file()
            .dropped
            .iter()
            .any(|e| e.peer == "c" && e.reason == "decode_error")
    };
    while !(rendezvous_done(&a, &b) && c_through(&b)) {
        assert!(
            start.elapsed() < Duration::from_secs(40),
            "incomplete after 40 s: rendezvous {}, c's own message through {}, b's sessions {:?}",
            rendezvous_done(&a, &b),
            c_through(&b),
            b.sessions()
                .map(|s| s.peer().to_string())
                .collect::<Vec<_>>()
        );
        c.inject();
        z.inject();
        step(&mut [(&mut a, &mut la), (&mut b, &mut lb)], start);
    }
    // A little longer with the impostors at it.
    let settle = Instant::now();
    while settle.elapsed() < Duration::from_secs(1) {
        c.inject();
        z.inject();
        step(&mut [(&mut a, &mut la), (&mut b, &mut lb)], start);
    }
    // z holds a certificate of the team CA: its link opens, but nothing it sends counts.
    assert!(
        z.links() > 0,
        "z (team CA, not in the roster) could not even connect"
    );
    assert!(c.links() > 0);
    let peers: Vec<String> = b.sessions().map(|s| s.peer().to_string()).collect();
    assert_eq!(peers, ["a", "c"], "b's peers (z's token must not count)");
    let sb = b.session(&id("a")).unwrap().stats().clone();
    assert_eq!(sb.descriptors_delivered, KEYFRAMES);
    assert_eq!(sb.descriptors_redelivered, 0);
    assert_eq!(sb.meetings, 1, "c's copy of a's token made a come and go");
    let ledger = b.ledger().lock().to_file();
    for e in &ledger.dropped {
        // The forged epoch would show as stale_epoch (a's real messages refused), a forged
        // header as wrong_sender, the wildcard as bad_key; z's as unknown_peer.
        assert!(
            e.peer == "c" && e.reason == "decode_error",
            "dropped at b: {e:?} (only c's own garbage should have reached b)"
        );
    }
    assert!(
        ledger
            .traffic
            .iter()
            .all(|t| t.peer == "a" || t.peer == "c"),
        "{:?}",
        ledger.traffic
    );
    la.close().unwrap();
    lb.close().unwrap();
}

// ---------------------------------------------------------------------------------------
// A robot whose wall clock is years off (a drone computer without RTC or NTP boots in
// 1970): it runs as a child process under libfaketime (LD_PRELOAD; the clock of the
// whole process, so also the one TLS checks certificates against), the rest of the team
// with the right clock. With clockless team certificates it authenticates its team and
// still refuses an outsider; with dated ones (the control) TLS refuses the link, which
// shows that the fake clock is in effect.

const FAKETIME_LIBS: [&str; 2] = [
    "/usr/lib/x86_64-linux-gnu/faketime/libfaketimeMT.so.1",
    "/usr/lib/aarch64-linux-gnu/faketime/libfaketimeMT.so.1",
];
/// The child's clock: a year and a half after the Unix epoch.
const CHILD_CLOCK: &str = "@1971-06-01 00:00:00";
const CHILD_ENV: &str = "DOORSLAM_TEST_CLOCK_CHILD";

/// Unix seconds of this process's wall clock.
fn wall_clock_s() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_secs()
}

/// The off-clock robot b. Run only as the child of
/// `a_robot_whose_clock_is_years_off_authenticates_its_team_and_refuses_an_outsider`
/// (which passes it `CHILD_ENV`); ignored in a plain run, where it has nothing to do.
#[test]
#[ignore = "the off-clock child of the clock test; started by that test"]
fn clock_off_child() {
    let Ok(arg) = std::env::var(CHILD_ENV) else {
        return;
    };
    let parts: Vec<&str> = arg.split('|').collect();
    let [dir, team, endpoint, how, seconds] = parts[..] else {
        panic!("{CHILD_ENV}={arg}: dir|team|endpoint|checked or unchecked|seconds");
    };
    let d = Path::new(dir);
    println!("CHILD clock {}", wall_clock_s());
    let section = tls(d, "b", &["a", "b"]);
    let security = if how == "checked" {
        // The robot's own start-up checks, at its own (wrong) clock.
        checked(&section, team, "b")
    } else {
        // Dated certificates fail that check at this clock: build the settings by hand
        // so that the link itself (TLS) is what is tried.
        Security {
            team: team.into(),
            ca: section.ca.clone(),
            cert: section.cert.clone(),
            key: section.key.clone(),
            roster: vec![id("a"), id("b")],
            expires_unix_s: i64::MAX,
        }
    };
    let (mut b, mut lb) = robot(team, "b", 1, vec![endpoint.into()], vec![], security);
    let start = Instant::now();
    let limit = Duration::from_secs(seconds.parse().unwrap());
    let mut done: Option<Instant> = None;
    // Up to `seconds`, or 3 s after it has every descriptor of a (time for a to get b's
    // acknowledgements and matches).
    while start.elapsed() < limit && done.is_none_or(|t| t.elapsed() < Duration::from_secs(3)) {
        step(&mut [(&mut b, &mut lb)], start);
        let delivered = b
            .session(&id("a"))
            .map_or(0, |s| s.delivered_descriptors().len() as u64);
        if delivered == KEYFRAMES && done.is_none() {
            done = Some(Instant::now());
            println!("CHILD got every descriptor of a");
        }
    }
    lb.close().unwrap();
}

struct Child(std::process::Child);

impl Drop for Child {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Starts [`clock_off_child`] with its clock at [`CHILD_CLOCK`]; `None` (with the reason
/// printed) where libfaketime is not installed.
fn start_off_clock_child(arg: &str) -> Option<Child> {
    let Some(lib) = FAKETIME_LIBS.iter().find(|p| Path::new(p).exists()) else {
        eprintln!("libfaketime not installed (deploy/setup installs it): clock test not run");
        return None;
    };
    let child = std::process::Command::new(std::env::current_exe().unwrap())
        .args(["--ignored", "--exact", "clock_off_child", "--nocapture"])
        .env(CHILD_ENV, arg)
        .env("LD_PRELOAD", lib)
        .env("FAKETIME", CHILD_CLOCK)
        // Only the wall clock is off, as on a drone without RTC: timers keep running.
        .env("FAKETIME_DONT_FAKE_MONOTONIC", "1")
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::inherit())
        .spawn()
        .unwrap();
    Some(Child(child))
}

/// The child's output, once it has ended.
fn child_output(mut child: Child) -> String {
    use std::io::Read;
    let status = child.0.wait().unwrap();
    let mut out = String::new();
    child
        .0
        .stdout
        .take()
        .unwrap()
        .read_to_string(&mut out)
        .unwrap();
    assert!(status.success(), "off-clock child failed: {out}");
    out
}

/// Whether b acknowledged every descriptor of a, and a got b's matches back (so each
/// one's certificate passed the other's checks: the link is mutual).
fn a_got_b(a: &Node) -> bool {
    a.session(&id("b")).is_some_and(|s| {
        s.stats().descriptors_acknowledged == KEYFRAMES && s.stats().matches_received > 0
    })
}

#[test]
fn a_robot_whose_clock_is_years_off_authenticates_its_team_and_refuses_an_outsider() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let roster = ["a", "b"];

    // 1. Clockless team certificates: the off-clock b and the right-clock a meet.
    let team = format!("ck{}", std::process::id());
    make_certs_with(d, &team, &roster, true);
    let endpoint = format!("tls/127.0.0.1:{}", free_port());
    let child_s = 25;
    let arg = format!("{}|{team}|{endpoint}|checked|{child_s}", d.display());
    let Some(mut child) = start_off_clock_child(&arg) else {
        return;
    };
    let (mut a, mut la) = robot(
        &team,
        "a",
        0,
        vec![],
        vec![endpoint.clone()],
        checked(&tls(d, "a", &roster), &team, "a"),
    );
    // An outsider: its own CA (same team name), a certificate for "a".
    let rogue_dir = d.join("rogue");
    make_certs_with(&rogue_dir, &team, &["a"], true);
    let rogue = Injector::new(
        rogue_tls(&team, &tls(&rogue_dir, "a", &roster), &endpoint),
        &team,
        &["a"],
        vec![(format!("doorslam/{team}/b/hello/a"), forged_hello("a"))],
    );
    let start = Instant::now();
    while !a_got_b(&a) {
        assert!(
            start.elapsed() < Duration::from_secs(child_s - 5),
            "the off-clock robot and its team did not meet: a {:?}",
            a.session(&id("b")).map(|s| s.stats().clone())
        );
        rogue.inject();
        step(&mut [(&mut a, &mut la)], start);
    }
    // Keep a up until the child has what it needs (it ends on its own).
    while start.elapsed() < Duration::from_secs(child_s + 2) {
        rogue.inject();
        step(&mut [(&mut a, &mut la)], start);
        if let Ok(Some(_)) = child.0.try_wait() {
            break;
        }
    }
    assert_eq!(
        rogue.links(),
        0,
        "the outsider got a link to the off-clock robot"
    );
    let out = child_output(child);
    let clock: u64 = out
        .lines()
        .find_map(|l| l.strip_prefix("CHILD clock "))
        .and_then(|s| s.trim().parse().ok())
        .unwrap_or_else(|| panic!("child printed no clock: {out}"));
    assert!(
        clock < 2 * 365 * 86_400,
        "the child's clock was not set off ({clock} s after 1970): {out}"
    );
    assert!(out.contains("CHILD got every descriptor of a"), "{out}");
    la.close().unwrap();

    // 2. Control: dated certificates (valid from an hour ago), the same off clock: TLS
    //    itself refuses the link.
    let dated = d.join("dated");
    let team = format!("cd{}", std::process::id());
    make_certs_with(&dated, &team, &roster, false);
    let endpoint = format!("tls/127.0.0.1:{}", free_port());
    let control_s = 8;
    let arg = format!(
        "{}|{team}|{endpoint}|unchecked|{control_s}",
        dated.display()
    );
    let child = start_off_clock_child(&arg).unwrap();
    let (mut a, mut la) = robot(
        &team,
        "a",
        0,
        vec![],
        vec![endpoint],
        checked(&tls(&dated, "a", &roster), &team, "a"),
    );
    let start = Instant::now();
    while start.elapsed() < Duration::from_secs(control_s - 1) {
        step(&mut [(&mut a, &mut la)], start);
    }
    assert!(
        !a_got_b(&a),
        "dated certificates passed at a clock years off: the control is broken"
    );
    let out = child_output(child);
    assert!(!out.contains("CHILD got every descriptor of a"), "{out}");
    la.close().unwrap();
}
