//! The demo's settings, its world (rendered flights or a split dataset) and the robots'
//! configuration files.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use doorslam_backend::eval::Trajectory;

use crate::flights::{
    camera_for_resolution, robot_name, simulate_team, write_team, FlightConfig, FlightPlan,
    RangeEvent, RangeEventKind,
};

use super::{io_err, DemoError};

/// Kill one robot's processes mid-run (`--kill ROBOT@SECONDS`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Kill {
    pub robot: usize,
    /// Flight time (seconds) of the kill.
    pub at_s: f64,
}

impl std::str::FromStr for Kill {
    type Err = String;
    /// `b@12.5`: robot letter (or number) and flight seconds.
    fn from_str(s: &str) -> Result<Self, String> {
        let (robot, at) = s
            .split_once('@')
            .ok_or_else(|| format!("{s:?}: expected ROBOT@SECONDS, e.g. b@15"))?;
        let robot = match robot.as_bytes() {
            [c @ b'a'..=b'z'] => usize::from(c - b'a'),
            _ => robot
                .parse()
                .map_err(|_| format!("{s:?}: robot {robot:?} is neither a letter nor a number"))?,
        };
        let at_s: f64 = at
            .parse()
            .map_err(|_| format!("{s:?}: {at:?} is not a number of seconds"))?;
        if !(at_s.is_finite() && at_s >= 0.0) {
            return Err(format!("{s:?}: seconds must be >= 0"));
        }
        Ok(Kill { robot, at_s })
    }
}

/// Frames per robot of the default scenario: 90 s of flight at 10 Hz.
pub const DEFAULT_FRAMES: usize = 900;
/// The default scenario's slowest drone (m/s).
pub const DEFAULT_SPEED_MPS: f64 = 5.0;
/// Frames per second of the rendered flights.
pub const RATE_HZ: f64 = 10.0;

/// What to run.
#[derive(Debug, Clone, PartialEq)]
pub struct DemoConfig {
    /// The `doorslam` binary every robot runs.
    pub exe: PathBuf,
    /// The report folder (must not exist, or be empty).
    pub out: PathBuf,
    pub robots: usize,
    /// Frames per robot (rendered flights, at 10 Hz); with `dataset`, all its frames are
    /// used, with `world` its own.
    pub frames: usize,
    /// The slowest drone's speed (the others fly up to 10 % faster), rendered flights.
    pub speed_mps: f64,
    /// Radio range between drones (metres), rendered flights.
    pub radio_range_m: f64,
    /// A KITTI-layout folder split into `robots` consecutive parts instead of the town.
    pub dataset: Option<PathBuf>,
    /// A world rendered before (an earlier demo's `<out>/world`, or `doorslam sim world`):
    /// flown instead of rendering a new one.
    pub world: Option<PathBuf>,
    /// `--kill ROBOT@SECONDS`, any number (at most one per robot): each robot's processes
    /// killed at its time and restarted `restart_after_s` later.
    pub kills: Vec<Kill>,
    /// Probability that a packet between robots is lost (nftables, at random), or none.
    pub drop: Option<f64>,
    /// Seconds between a kill and the restart.
    pub restart_after_s: f64,
    /// Replay speed (1 = real time).
    pub rate: f64,
    /// Seed of the town and the flights.
    pub seed: u64,
    /// Seconds the robots get to open their services before the flight's clock starts.
    pub startup_s: f64,
    /// Most seconds to wait at base for the team estimate to settle.
    pub settle_s: f64,
    /// Robots' realistic camera (noise, exposure changes, blur) when rendering.
    pub realistic_camera: bool,
    /// Loopback mode (not root): robot r listens on `base_port + r`.
    pub base_port: u16,
    /// Extra lines appended to every robot's `robot.toml` (e.g. `[rendezvous]` settings).
    pub robot_toml_extra: String,
    /// `--insecure`: plain TCP between robots, open to any host on the network, instead of
    /// the default mutual TLS and access control.
    pub insecure: bool,
    /// `--ros2`: every robot publishes its state as ROS 2 topics (`[ros2] enabled`), its
    /// session listening on [`ros2_endpoint`].
    pub ros2: bool,
}

impl DemoConfig {
    /// The defaults of `doorslam demo` for `exe` and `out`.
    pub fn new(exe: PathBuf, out: PathBuf) -> Self {
        Self {
            exe,
            out,
            robots: 3,
            frames: DEFAULT_FRAMES,
            speed_mps: DEFAULT_SPEED_MPS,
            radio_range_m: FlightConfig::default().radio_range_m,
            dataset: None,
            world: None,
            kills: Vec::new(),
            drop: None,
            restart_after_s: 3.0,
            rate: 1.0,
            seed: 1,
            startup_s: 6.0,
            settle_s: 30.0,
            realistic_camera: true,
            base_port: 17_447,
            robot_toml_extra: String::new(),
            insecure: false,
            ros2: false,
        }
    }

    pub fn validate(&self) -> Result<(), DemoError> {
        let bad = |m: String| Err(DemoError::Config(m));
        if !(1..=crate::flights::MAX_ROBOTS).contains(&self.robots) {
            return bad(format!("robots = {}: from 1 to 26", self.robots));
        }
        if self.frames < 10 {
            return bad(format!("frames = {}: at least 10", self.frames));
        }
        for (i, k) in self.kills.iter().enumerate() {
            if k.robot >= self.robots {
                return bad(format!(
                    "kill: robot {} is not in a team of {}",
                    robot_name(k.robot),
                    self.robots
                ));
            }
            if self.kills[..i].iter().any(|o| o.robot == k.robot) {
                return bad(format!(
                    "kill: robot {} is killed twice (one --kill per robot)",
                    robot_name(k.robot)
                ));
            }
        }
        if let Some(p) = self.drop {
            if !(p.is_finite() && (0.0..1.0).contains(&p)) {
                return bad(format!(
                    "drop = {p}: a probability from 0 to below 1 (0.3: three packets in ten lost)"
                ));
            }
        }
        if !(self.speed_mps.is_finite() && (0.5..=9.0).contains(&self.speed_mps)) {
            return bad(format!(
                "speed_mps = {}: from 0.5 to 9 (the fastest drone flies 10 % faster, at most 10 m/s)",
                self.speed_mps
            ));
        }
        if self.dataset.is_some() && self.world.is_some() {
            return bad("dataset and world: fly one of them".into());
        }
        for (name, v, max) in [
            ("radio_range_m", self.radio_range_m, 1e6),
            ("rate", self.rate, 100.0),
            ("startup_s", self.startup_s, 600.0),
            ("settle_s", self.settle_s, 3600.0),
            ("restart_after_s", self.restart_after_s, 600.0),
        ] {
            if !(v.is_finite() && v >= 0.0 && v <= max) {
                return bad(format!("{name} = {v}: from 0 to {max}"));
            }
        }
        if self.rate == 0.0 {
            return bad("rate = 0: the demo replays on a clock (use a positive speed)".into());
        }
        if !self.exe.is_file() {
            return bad(format!(
                "{}: the doorslam binary is not there",
                self.exe.display()
            ));
        }
        Ok(())
    }
}

/// Milliseconds since the Unix epoch.
pub fn unix_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

/// Creates the report folder, refusing one that holds anything (a demo never mixes runs).
pub fn prepare_out(out: &Path) -> Result<(), DemoError> {
    if out.exists() {
        let mut entries = std::fs::read_dir(out).map_err(io_err(out))?;
        if entries.next().is_some() {
            return Err(DemoError::Config(format!(
                "{} is not empty: give --out a new folder",
                out.display()
            )));
        }
    }
    std::fs::create_dir_all(out).map_err(io_err(out))
}

/// Where each robot's frames and ground truth come from.
#[derive(Debug, Clone)]
pub struct World {
    /// Per robot: the folder its camera replays, and `[k, n]` when it plays part of it.
    pub sources: Vec<(PathBuf, Option<[usize; 2]>)>,
    /// Per robot: ground truth of the whole folder it replays (stamps as the replay's).
    pub truth: Vec<Trajectory>,
    /// Radio range changes, in time order.
    pub events: Vec<RangeEvent>,
    /// The simulator's closure candidates (`closures.csv`), when rendered.
    pub closures_csv: Option<PathBuf>,
    /// Each drone's own candidates (`revisits.csv`), when rendered.
    pub revisits_csv: Option<PathBuf>,
    /// `world.txt` of a rendered world: plan, roles, camera (key, value), in file order.
    pub description: Vec<(String, String)>,
    pub frames: usize,
    pub rate_hz: f64,
    /// Frames per robot (the split parts may differ by one).
    pub robot_frames: Vec<usize>,
}

impl World {
    pub fn robots(&self) -> usize {
        self.sources.len()
    }

    /// Flight time of the longest robot, seconds.
    pub fn duration_s(&self) -> f64 {
        self.robot_frames.iter().copied().max().unwrap_or(0) as f64 / self.rate_hz
    }

    /// Renders the town's flights into `<out>/world`, or splits the dataset.
    pub fn prepare(
        config: &DemoConfig,
        progress: &mut dyn FnMut(usize, usize),
    ) -> Result<World, DemoError> {
        match (&config.dataset, &config.world) {
            (Some(dir), _) => Self::split(dir, config.robots),
            (None, Some(dir)) => Self::load(dir, config.robots),
            (None, None) => Self::render(config, progress),
        }
    }

    fn render(
        config: &DemoConfig,
        progress: &mut dyn FnMut(usize, usize),
    ) -> Result<World, DemoError> {
        let dir = config.out.join("world");
        let camera = camera_for_resolution("euroc")?;
        let flight = FlightConfig {
            robots: config.robots,
            frames: config.frames,
            rate_hz: RATE_HZ,
            speed_mps: config.speed_mps,
            radio_range_m: config.radio_range_m,
            seed: config.seed,
            plan: FlightPlan::Sectors,
            ..FlightConfig::default()
        };
        let world = crate::World::town(config.seed);
        let team = simulate_team(&world, &camera, &flight)?;
        // Sensor noise, exposure changes and motion blur (hil's realistic camera) unless
        // the ideal pinhole is asked for.
        let camera_model = if config.realistic_camera {
            crate::sensor::CameraModel::default()
        } else {
            crate::sensor::CameraModel::Ideal
        };
        // Rendering runs on rayon's threads: they count, this thread reports.
        let done = std::sync::atomic::AtomicUsize::new(0);
        let total = config.robots * config.frames;
        let count = |d: usize, _: usize| {
            done.fetch_max(d, std::sync::atomic::Ordering::Relaxed);
        };
        std::thread::scope(|s| {
            let worker = s.spawn(|| write_team(&dir, &world, &team, &camera_model, &count));
            while !worker.is_finished() {
                progress(done.load(std::sync::atomic::Ordering::Relaxed), total);
                std::thread::sleep(std::time::Duration::from_millis(200));
            }
            worker.join().unwrap_or_else(|_| {
                Err(crate::flights::FlightError::Io {
                    path: dir.clone(),
                    source: std::io::Error::other("the rendering thread panicked"),
                })
            })
        })?;
        progress(total, total);
        Self::load(&dir, config.robots)
    }

    /// A rendered world folder: `world.txt` (robots, frames, rate), `events.csv`, every
    /// robot's sequence with its ground truth, `closures.csv` and `revisits.csv`.
    fn load(dir: &Path, robots: usize) -> Result<World, DemoError> {
        let fail = |path: PathBuf, reason: String| DemoError::Io { path, reason };
        let world_txt = dir.join("world.txt");
        let text = std::fs::read_to_string(&world_txt).map_err(io_err(&world_txt))?;
        let description: Vec<(String, String)> = text
            .lines()
            .filter(|l| !l.starts_with('#'))
            .filter_map(|l| l.split_once(" = "))
            .map(|(k, v)| (k.trim().to_string(), v.trim().trim_matches('"').to_string()))
            .collect();
        let get = |key: &str| -> Result<&str, DemoError> {
            description
                .iter()
                .find(|(k, _)| k == key)
                .map(|(_, v)| v.as_str())
                .ok_or_else(|| fail(world_txt.clone(), format!("no {key} line")))
        };
        let number = |key: &str| -> Result<f64, DemoError> {
            let v = get(key)?;
            v.parse::<f64>()
                .ok()
                .filter(|x| x.is_finite() && *x > 0.0)
                .ok_or_else(|| {
                    fail(
                        world_txt.clone(),
                        format!("{key} = {v}: not a positive number"),
                    )
                })
        };
        let (n, frames, rate_hz) = (
            number("robots")? as usize,
            number("frames")? as usize,
            number("rate_hz")?,
        );
        if n != robots {
            return Err(fail(
                world_txt.clone(),
                format!("a world of {n} robots, the demo was asked for {robots}"),
            ));
        }
        let events = read_events(&dir.join("events.csv"), n, rate_hz)?;
        let per_robot = |r: usize| dir.join(robot_name(r).to_string());
        let truth: Vec<Trajectory> = (0..n)
            .map(|r| ground_truth(&per_robot(r)))
            .collect::<Result<_, _>>()?;
        for (r, t) in truth.iter().enumerate() {
            if t.len() != frames {
                return Err(fail(
                    per_robot(r),
                    format!("{} frames, world.txt says {frames}", t.len()),
                ));
            }
        }
        let optional = |name: &str| Some(dir.join(name)).filter(|p| p.is_file());
        Ok(World {
            sources: (0..n).map(|r| (per_robot(r), None)).collect(),
            truth,
            events,
            closures_csv: optional("closures.csv"),
            revisits_csv: optional("revisits.csv"),
            description,
            frames,
            rate_hz,
            robot_frames: vec![frames; n],
        })
    }

    fn split(dir: &Path, robots: usize) -> Result<World, DemoError> {
        let truth = ground_truth(dir)?;
        let frames = truth.len();
        if frames < 10 * robots {
            return Err(DemoError::Io {
                path: dir.to_path_buf(),
                reason: format!("{frames} frames: too few for {robots} robots (at least 10 each)"),
            });
        }
        let stamps = truth.timestamps();
        let span = stamps[frames - 1] - stamps[0];
        let rate_hz = if span > 0.0 {
            (frames - 1) as f64 / span
        } else {
            10.0
        };
        // The replay's split: part k holds frames [k n / parts, (k + 1) n / parts).
        let robot_frames = (0..robots)
            .map(|k| (k + 1) * frames / robots - k * frames / robots)
            .collect();
        Ok(World {
            sources: (0..robots)
                .map(|r| (dir.to_path_buf(), Some([r, robots])))
                .collect(),
            truth: vec![truth; robots],
            events: Vec::new(),
            closures_csv: None,
            revisits_csv: None,
            description: Vec::new(),
            frames,
            rate_hz,
            robot_frames,
        })
    }
}

/// `events.csv` (`time_s,event,robot_a,robot_b`) of a world of `robots` robots.
fn read_events(path: &Path, robots: usize, rate_hz: f64) -> Result<Vec<RangeEvent>, DemoError> {
    let text = std::fs::read_to_string(path).map_err(io_err(path))?;
    let mut events = Vec::new();
    for (line, row) in text.lines().enumerate().skip(1) {
        if row.trim().is_empty() {
            continue;
        }
        let bad = |what: &str| DemoError::Io {
            path: path.to_path_buf(),
            reason: format!("line {}: {what}: {row:?}", line + 1),
        };
        let f: Vec<&str> = row.split(',').map(str::trim).collect();
        let [time, kind, a, b] = f[..] else {
            return Err(bad("expected time_s,event,robot_a,robot_b"));
        };
        let time_s: f64 = time
            .parse()
            .ok()
            .filter(|t: &f64| t.is_finite() && *t >= 0.0)
            .ok_or_else(|| bad("not a time"))?;
        let kind = match kind {
            "enter" => RangeEventKind::Enter,
            "leave" => RangeEventKind::Leave,
            _ => return Err(bad("the event is neither enter nor leave")),
        };
        let robot = |s: &str| match s.as_bytes() {
            [c @ b'a'..=b'z'] if usize::from(c - b'a') < robots => Ok(usize::from(c - b'a')),
            _ => Err(bad("unknown robot")),
        };
        let (robot_a, robot_b) = (robot(a)?, robot(b)?);
        if robot_a >= robot_b {
            return Err(bad("robot_a must come before robot_b"));
        }
        if events
            .last()
            .is_some_and(|e: &RangeEvent| e.time_s > time_s)
        {
            return Err(bad("events out of time order"));
        }
        events.push(RangeEvent {
            time_s,
            frame: (time_s * rate_hz).round() as usize,
            kind,
            robot_a,
            robot_b,
        });
    }
    Ok(events)
}

/// The ground truth of a dataset folder (`poses.txt`), stamped as the replay stamps its
/// frames (`times.txt`, or 10 Hz without it).
fn ground_truth(dir: &Path) -> Result<Trajectory, DemoError> {
    let fail = |reason: String| DemoError::Io {
        path: dir.to_path_buf(),
        reason,
    };
    let poses = dir.join("poses.txt");
    if !poses.is_file() {
        return Err(fail(
            "no poses.txt: the demo needs ground truth to report errors".into(),
        ));
    }
    let dataset = doorslam_dataset::Dataset::open(dir)
        .and_then(|d| d.with_truth(&poses))
        .map_err(|e| fail(e.to_string()))?;
    let truth = dataset.truth.clone().unwrap_or_default();
    let stamps = dataset
        .frames
        .iter()
        .map(|f| f.stamp_ns as f64 * 1e-9)
        .collect();
    Trajectory::new(stamps, truth).map_err(|e| fail(e.to_string()))
}

/// The team's name in every robot's config: one per demo process, so two demos on one
/// machine never join each other.
pub fn team_name() -> String {
    format!("demo{}", std::process::id())
}

/// The team's certificates of a secure demo.
#[derive(Debug, Clone)]
pub struct DemoTls {
    /// `<out>/certs`: the layout of `doorslam team certs` (ca.pem, robots/<id>/...).
    pub dir: PathBuf,
    /// Every robot id, the roster of `[team.tls] robots`.
    pub roster: Vec<String>,
}

/// Writes the team CA and one certificate per robot into `<out>/certs`, as `doorslam team
/// certs --clockless` does: the simulated drones, like real ones without a real-time
/// clock, authenticate whatever their clocks say (`doorslam_team::certs`, "Robots without a
/// synchronized clock"). The CA's key stays in the folder: a demo's team lives as long as its
/// run folder.
pub fn team_certs(out: &Path, robots: usize) -> Result<DemoTls, DemoError> {
    let dir = out.join("certs");
    let roster: Vec<String> = (0..robots).map(|r| robot_name(r).to_string()).collect();
    doorslam_team::certs::generate(
        &dir,
        &doorslam_team::certs::CertsRequest {
            team: team_name(),
            robots: roster.clone(),
            routers: vec![],
            days: 1,
            clockless: true,
        },
    )
    .map_err(|e| DemoError::Io {
        path: dir.clone(),
        reason: format!("team certificates: {e}"),
    })?;
    Ok(DemoTls { dir, roster })
}

/// The endpoint robot `r` listens on: `tcp/` or, with the team's certificates, `tls/`.
pub fn endpoint(address: &str, port: u16, tls: bool) -> String {
    format!("{}/{address}:{port}", if tls { "tls" } else { "tcp" })
}

/// Ports of a robot's ROS 2 session above its team link's: 7547 on a robot's own address,
/// `base_port + 100 + r` on the loopback (a team of at most 26 never reaches them).
pub const ROS2_PORT_OFFSET: u16 = 100;

/// The plain-TCP endpoint of the ROS 2 session (`doorslam service ros2`) of the robot whose
/// team link listens on `team_endpoint`: the same address, [`ROS2_PORT_OFFSET`] ports up.
/// Not TLS: a laptop's `rmw_zenohd` connects to it with rmw_zenoh's default settings.
pub fn ros2_endpoint(team_endpoint: &str) -> String {
    let address = team_endpoint
        .split_once('/')
        .map_or(team_endpoint, |(_, a)| a);
    match address.rsplit_once(':') {
        Some((host, port)) => {
            let port = port.parse::<u16>().unwrap_or(7447);
            format!("tcp/{host}:{}", port.saturating_add(ROS2_PORT_OFFSET))
        }
        None => format!("tcp/{address}:{}", 7447 + ROS2_PORT_OFFSET),
    }
}

/// The `robot.toml` of robot `r`.
pub fn robot_toml(
    config: &DemoConfig,
    world: &World,
    r: usize,
    addresses: &[String],
    start_unix_ms: u64,
    netns: bool,
    tls: Option<&DemoTls>,
) -> String {
    let out = config.out.display();
    let (path, split) = &world.sources[r];
    let mut t = String::new();
    let _ = write!(
        t,
        r#"# doorslam demo: robot {name} (written by `doorslam demo`)
[robot]
id = "{name}"
index = {r}

[camera]
source = "replay"

[camera.replay]
path = "{path}"
rate = {rate}
wait_for_subscribers_s = 30.0
start_unix_ms = {start_unix_ms}
status_file = "{out}/{name}/camera.json"
"#,
        name = robot_name(r),
        path = path.display(),
        rate = config.rate,
    );
    if let Some([k, n]) = split {
        let _ = writeln!(t, "split = [{k}, {n}]");
    }
    let _ = write!(
        t,
        r#"
[frontend]
run_dir = "{out}"

[backend]
state_dir = "{out}"
optimize_every = 10
distributed = true
write_every_s = 0.5

[team]
name = "{team}"
listen = ["{listen}"]
"#,
        team = team_name(),
        listen = addresses[r],
    );
    let others: Vec<String> = addresses
        .iter()
        .enumerate()
        .filter(|(i, _)| *i != r)
        .map(|(_, a)| format!("{a:?}"))
        .collect();
    // In network namespaces peers are found on the shared radio LAN, and the roster's
    // addresses are dialled too: Zenoh's multicast scouting asks once every 8 s after its
    // first few seconds, so under 30 % loss (a scout and its answer both through: one in
    // two) a robot back in range met the team 12-48 s later; a listed peer is dialled
    // again every 1-4 s.
    if !netns {
        t.push_str("# loopback (not root): no multicast between test robots, peers listed\n");
    }
    let _ = writeln!(
        t,
        "connect = [{}]\nmulticast_scouting = {netns}",
        others.join(", ")
    );
    let _ = write!(
        t,
        r#"lease_ms = 3000
run_dir = "{out}"
retransmit_ms = 500
write_every_ms = 500
"#
    );
    if let Some(tls) = tls {
        let name = robot_name(r);
        let d = tls.dir.display();
        let roster: Vec<String> = tls.roster.iter().map(|x| format!("{x:?}")).collect();
        let _ = write!(
            t,
            r#"
# Mutual TLS + access control (`doorslam team certs --clockless`, in {d}).
[team.tls]
ca = "{d}/ca.pem"
cert = "{d}/robots/{name}/cert.pem"
key = "{d}/robots/{name}/key.pem"
robots = [{roster}]
"#,
            roster = roster.join(", ")
        );
    }
    let _ = write!(
        t,
        r#"
[up]
services = ["backend", "frontend", "place-recognition", "team", "camera"]
"#
    );
    if config.ros2 {
        // `up` adds the `ros2` service; no router on the simulated robot: a laptop's
        // `rmw_zenohd` connects to this endpoint instead.
        let _ = write!(
            t,
            r#"
[ros2]
enabled = true
listen = ["{}"]
connect = []
"#,
            ros2_endpoint(&addresses[r])
        );
    }
    t.push_str(&config.robot_toml_extra);
    t
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_ros2_endpoint_is_the_team_address_a_hundred_ports_up_in_plain_tcp() {
        assert_eq!(ros2_endpoint("tls/10.77.0.2:7447"), "tcp/10.77.0.2:7547");
        assert_eq!(ros2_endpoint("tcp/127.0.0.1:17449"), "tcp/127.0.0.1:17549");
    }
}
