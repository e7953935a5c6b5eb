//! What the process-level tests share: a guard that kills a child the test started, the
//! child's stderr read as it comes (so tests wait for events in the log instead of
//! guessing how long a loaded machine takes), and the back-end journal read as keyframe
//! ids and odometry edges, a replayable noise dataset, a free port. Each test binary uses
//! the parts it needs.
#![allow(dead_code)]

use std::path::Path;
use std::process::Child;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use doorslam_backend::journal::{Entry, Journal};

/// Kills the process when dropped, so a failing test leaves no service running.
pub struct Guard(pub Child);

impl Drop for Guard {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

impl std::ops::Deref for Guard {
    type Target = Child;
    fn deref(&self) -> &Child {
        &self.0
    }
}

impl std::ops::DerefMut for Guard {
    fn deref_mut(&mut self) -> &mut Child {
        &mut self.0
    }
}

/// Sends `sig` to a child the test started.
pub fn signal(child: &Child, sig: i32) {
    // SAFETY: kill(2) on our own child.
    unsafe {
        libc::kill(child.id() as libc::pid_t, sig);
    }
}

/// Waits for `child` to exit; kills it and fails the test after `limit`.
pub fn wait_exit(child: &mut Child, limit: Duration) -> std::process::ExitStatus {
    let deadline = Instant::now() + limit;
    loop {
        if let Some(s) = child.try_wait().unwrap() {
            return s;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            panic!("process {} did not exit within {limit:?}", child.id());
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// A child's stderr, read line by line as it comes.
pub struct LogReader {
    text: Arc<Mutex<String>>,
    reader: std::thread::JoinHandle<()>,
}

impl LogReader {
    /// Takes `child`'s piped stderr.
    pub fn new(child: &mut Child) -> Self {
        let text = Arc::new(Mutex::new(String::new()));
        let (sink, stderr) = (text.clone(), child.stderr.take().unwrap());
        let reader = std::thread::spawn(move || {
            use std::io::BufRead;
            for line in std::io::BufReader::new(stderr)
                .lines()
                .map_while(Result::ok)
            {
                let mut log = sink.lock().unwrap();
                log.push_str(&line);
                log.push('\n');
            }
        });
        Self { text, reader }
    }

    /// The log so far.
    pub fn text(&self) -> String {
        self.text.lock().unwrap().clone()
    }

    /// Waits until every one of `needles` has appeared in the log (a needle listed twice
    /// must appear twice).
    pub fn wait_for(&self, needles: &[&str], timeout: Duration) {
        let deadline = Instant::now() + timeout;
        loop {
            let log = self.text();
            let seen = needles
                .iter()
                .all(|n| log.matches(n).count() >= needles.iter().filter(|m| *m == n).count());
            if seen {
                return;
            }
            assert!(
                Instant::now() < deadline,
                "never saw {needles:?} in the log:\n{log}"
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// The whole log, once the child has exited.
    pub fn finish(self) -> String {
        let Self { text, reader } = self;
        reader.join().unwrap();
        let log = text.lock().unwrap().clone();
        log
    }
}

/// The keyframe ids and the odometry edges (from, to) in a back-end journal, in journal
/// order; empty while the journal does not exist yet.
pub fn journaled(journal: &Path) -> (Vec<u64>, Vec<(u64, u64)>) {
    let Ok(r) = Journal::read(journal) else {
        return (vec![], vec![]);
    };
    let mut keyframes = Vec::new();
    let mut edges = Vec::new();
    for e in &r.entries {
        match e {
            Entry::Keyframe { id, .. } => keyframes.push(*id),
            Entry::Odometry { from, to, .. } => edges.push((*from, *to)),
            _ => {}
        }
    }
    (keyframes, edges)
}

/// A KITTI-layout stereo sequence of `frames` 64x48 noise images (the same seeded noise in
/// every call, left and right identical), stamped every `period_s`, the camera at
/// `position(k)` = (x, z) without rotation: enough for a replay and the simulated
/// keyframes, which read poses, never the pixels.
pub fn write_noise_dataset(
    dir: &Path,
    frames: usize,
    period_s: f64,
    position: impl Fn(usize) -> (f64, f64),
) {
    std::fs::create_dir_all(dir.join("image_0")).unwrap();
    std::fs::create_dir_all(dir.join("image_1")).unwrap();
    let mut state = 0x2545F4914F6CDD1Du64;
    let (mut times, mut poses) = (String::new(), String::new());
    for k in 0..frames {
        let px: Vec<u8> = (0..64 * 48)
            .map(|_| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                state as u8
            })
            .collect();
        let name = format!("{k:06}.png");
        doorslam_dataset::write_gray_png(&dir.join("image_0").join(&name), 64, 48, &px).unwrap();
        doorslam_dataset::write_gray_png(&dir.join("image_1").join(&name), 64, 48, &px).unwrap();
        times.push_str(&format!("{:.6}\n", k as f64 * period_s));
        let (x, z) = position(k);
        poses.push_str(&format!("1 0 0 {x} 0 1 0 0 0 0 1 {z}\n"));
    }
    std::fs::write(dir.join("times.txt"), times).unwrap();
    std::fs::write(dir.join("poses.txt"), poses).unwrap();
}

/// A TCP port nobody listens on now (the OS's pick), for a test's own endpoints.
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}
