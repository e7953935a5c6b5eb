//! CPU time of the robots' processes, measured per process from `/proc/<pid>/stat`, and
//! of the whole machine from `/proc/stat`: what the demo reports as `robots_cpu_s`.
//!
//! - **Per robot, exact when it stops normally**: `up` reaps its services, so once `up`
//!   has exited — read as a zombie, before the demo reaps it — its `utime + stime +
//!   cutime + cstime` is the CPU of `up` and of every service it ran, to the tick.
//! - **Sampled otherwise** (a killed robot, whose services are reaped by init, and the
//!   per-service split): every process of the robot's process group is read a few times
//!   a second and keeps its last reading; what a process used after its last reading is
//!   missing (at most one sampling period per process).
//! - **The machine**: busy time of all cores (`/proc/stat`, everything but idle and
//!   iowait) over the flight, so a run on a machine shared with other work says so.

use std::collections::BTreeMap;
use std::path::Path;

/// Seconds per clock tick of `/proc` times.
fn tick_s() -> f64 {
    // SAFETY: sysconf has no preconditions.
    let hz = unsafe { libc::sysconf(libc::_SC_CLK_TCK) };
    if hz > 0 {
        1.0 / hz as f64
    } else {
        0.01
    }
}

/// The fields of `/proc/<pid>/stat` the demo needs (times in seconds).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProcStat {
    pub pid: i32,
    pub ppid: i32,
    pub pgrp: i32,
    /// CPU of the process itself (all its threads).
    pub own_s: f64,
    /// CPU of its children it has waited for.
    pub children_s: f64,
    /// Start time in ticks since boot: with the pid, names one process.
    pub start: u64,
}

/// Parses one `/proc/<pid>/stat` line (the command name may hold spaces and parentheses:
/// the fields start after the last `)`).
pub fn parse_stat(text: &str) -> Option<ProcStat> {
    let pid = text.split_whitespace().next()?.parse().ok()?;
    let rest = &text[text.rfind(')')? + 1..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    // After the name: state(0) ppid(1) pgrp(2) ... utime(11) stime(12) cutime(13)
    // cstime(14) ... starttime(19).
    let num = |i: usize| -> Option<f64> { f.get(i)?.parse::<f64>().ok() };
    let t = tick_s();
    Some(ProcStat {
        pid,
        ppid: f.get(1)?.parse().ok()?,
        pgrp: f.get(2)?.parse().ok()?,
        own_s: (num(11)? + num(12)?) * t,
        children_s: (num(13)? + num(14)?) * t,
        start: f.get(19)?.parse().ok()?,
    })
}

/// `/proc/<pid>/stat` of one process, if it (or its zombie) is there.
pub fn read_stat(pid: i32) -> Option<ProcStat> {
    parse_stat(&std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?)
}

/// The name of a process whose command line could not be read (or was still empty).
const UNNAMED: &str = "?";

/// The service a robot process runs: `doorslam service NAME` → NAME, `doorslam up` →
/// `up`, anything else by its program name.
fn process_name(pid: i32) -> String {
    let Ok(raw) = std::fs::read(format!("/proc/{pid}/cmdline")) else {
        return UNNAMED.into();
    };
    let args: Vec<String> = raw
        .split(|&b| b == 0)
        .map(|a| String::from_utf8_lossy(a).into_owned())
        .collect();
    if let Some(k) = args.iter().position(|a| a == "service") {
        if let Some(name) = args.get(k + 1) {
            return name.clone();
        }
    }
    if args.iter().any(|a| a == "up") {
        return "up".into();
    }
    args.first()
        .and_then(|p| Path::new(p).file_name())
        .filter(|n| !n.is_empty())
        .map_or(UNNAMED.into(), |n| n.to_string_lossy().into_owned())
}

/// Every robot process seen, with its last reading.
#[derive(Debug, Default)]
pub struct CpuMeter {
    /// (pid, start) → its robot, process group and name, CPU at the last reading.
    seen: BTreeMap<(i32, u64), Seen>,
    /// Per robot: exact totals of incarnations that exited normally.
    exact: BTreeMap<usize, f64>,
    /// Process groups whose CPU an exact total covers (their readings are not added).
    covered: Vec<i32>,
}

#[derive(Debug, Clone)]
struct Seen {
    robot: usize,
    pgrp: i32,
    name: String,
    cpu_s: f64,
}

impl CpuMeter {
    /// Reads every process whose process group is one of `groups` (robot, pgid).
    pub fn sample(&mut self, groups: &[(usize, i32)]) {
        if groups.is_empty() {
            return;
        }
        let Ok(entries) = std::fs::read_dir("/proc") else {
            return;
        };
        for e in entries.flatten() {
            let Some(pid) = e.file_name().to_str().and_then(|s| s.parse::<i32>().ok()) else {
                continue;
            };
            let Some(st) = read_stat(pid) else { continue };
            let Some(&(robot, _)) = groups.iter().find(|(_, g)| *g == st.pgrp) else {
                continue;
            };
            let key = (pid, st.start);
            match self.seen.get_mut(&key) {
                Some(entry) => {
                    entry.cpu_s = entry.cpu_s.max(st.own_s);
                    // First seen between fork and exec (no command line yet, or still
                    // its parent's `up`): named by its latest command line.
                    let name = process_name(pid);
                    if name != UNNAMED {
                        entry.name = name;
                    }
                }
                None => {
                    self.seen.insert(
                        key,
                        Seen {
                            robot,
                            pgrp: st.pgrp,
                            name: process_name(pid),
                            cpu_s: st.own_s,
                        },
                    );
                }
            }
        }
    }

    /// The exact total of an incarnation whose `up` (pid `pid`, leader of its process
    /// group) has exited and is not yet reaped: its own CPU and that of every service it
    /// waited for. Its group's readings are then left out of [`Self::robot_s`].
    pub fn exited(&mut self, robot: usize, pid: i32) -> bool {
        let Some(st) = read_stat(pid) else {
            return false;
        };
        *self.exact.entry(robot).or_default() += st.own_s + st.children_s;
        self.covered.push(pid);
        true
    }

    /// CPU seconds of robot `robot`: exact totals of incarnations that exited normally
    /// plus the last readings of the processes of the others.
    pub fn robot_s(&self, robot: usize) -> f64 {
        let sampled: f64 = self
            .seen
            .values()
            .filter(|v| v.robot == robot && !self.covered.contains(&v.pgrp))
            .map(|v| v.cpu_s)
            .sum();
        self.exact.get(&robot).copied().unwrap_or(0.0) + sampled
    }

    /// Sampled CPU seconds per process name of robot `robot` (every incarnation).
    pub fn per_process(&self, robot: usize) -> BTreeMap<String, f64> {
        let mut out = BTreeMap::new();
        for v in self.seen.values().filter(|v| v.robot == robot) {
            *out.entry(v.name.clone()).or_insert(0.0) += v.cpu_s;
        }
        out
    }

    /// Sampled CPU of every robot process so far (for differences over a phase).
    pub fn sampled_total_s(&self) -> f64 {
        self.seen.values().map(|v| v.cpu_s).sum()
    }
}

/// Busy CPU seconds of all cores since boot (`/proc/stat`: all but idle and iowait), and
/// the number of cores.
pub fn machine_busy_s() -> Option<(f64, usize)> {
    let text = std::fs::read_to_string("/proc/stat").ok()?;
    let first = text.lines().next()?;
    let v: Vec<f64> = first
        .split_whitespace()
        .skip(1)
        .filter_map(|x| x.parse().ok())
        .collect();
    // user nice system idle iowait irq softirq steal ...
    let busy: f64 = v.iter().take(8).sum::<f64>() - v.get(3)? - v.get(4).unwrap_or(&0.0);
    let cores = text
        .lines()
        .filter(|l| l.starts_with("cpu") && l.as_bytes().get(3).is_some_and(u8::is_ascii_digit))
        .count();
    Some((busy * tick_s(), cores.max(1)))
}

/// CPU seconds (user + system) of this process (all its threads: the rendering).
pub fn own_cpu_s() -> f64 {
    rusage_s(libc::RUSAGE_SELF)
}

/// CPU seconds of every child process this one has waited for (and of their own waited-for
/// children): what the demo reported as the robots' CPU before it measured per process;
/// kept in the summary to compare.
pub fn waited_children_cpu_s() -> f64 {
    rusage_s(libc::RUSAGE_CHILDREN)
}

fn rusage_s(who: libc::c_int) -> f64 {
    // SAFETY: getrusage fills the struct it is given; zeroed is a valid initial value.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: a valid pointer to a rusage, and `who` is RUSAGE_SELF or RUSAGE_CHILDREN.
    if unsafe { libc::getrusage(who, &mut usage) } != 0 {
        return 0.0;
    }
    let s = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    s(usage.ru_utime) + s(usage.ru_stime)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stat_lines_with_odd_names_parse() {
        let line = "4242 (doorslam (x) y) S 4200 4242 4242 0 -1 4194560 100 0 0 0 150 50 20 10 20 0 9 0 12345 0 0";
        let st = parse_stat(line).unwrap();
        let t = tick_s();
        assert_eq!(
            (st.pid, st.ppid, st.pgrp, st.start),
            (4242, 4200, 4242, 12345)
        );
        assert!((st.own_s - 200.0 * t).abs() < 1e-9);
        assert!((st.children_s - 30.0 * t).abs() < 1e-9);
        assert!(parse_stat("garbage").is_none());
    }

    #[test]
    fn a_waited_child_counts_in_the_zombie_parent() {
        // A shell that burns CPU in a child and waits for it: read as a zombie, before it
        // is reaped, the parent carries the child's CPU.
        let mut child = std::process::Command::new("sh")
            .args([
                "-c",
                "(i=0; while [ $i -lt 200000 ]; do i=$((i+1)); done); exit 0",
            ])
            .spawn()
            .unwrap();
        let pid = child.id() as i32;
        // SAFETY: waits for our own child without reaping it (WNOWAIT).
        let mut info: libc::siginfo_t = unsafe { std::mem::zeroed() };
        let rc = unsafe {
            libc::waitid(
                libc::P_PID,
                pid as libc::id_t,
                &mut info,
                libc::WEXITED | libc::WNOWAIT,
            )
        };
        assert_eq!(rc, 0);
        let st = read_stat(pid).expect("the zombie's stat");
        child.wait().unwrap();
        assert!(st.children_s > 0.05, "{st:?}");
        assert!(read_stat(pid).is_none());
    }
}
