#!/usr/bin/env python3
"""What the live ROS 2 publishers cost a robot: `doorslam service ros2` on a state folder of
N keyframes that is rewritten the way the back-end rewrites it (every file atomically,
every --write-every-s, the team estimate moved a little each time, so every read is new),
with an eclipse-zenoh subscriber on `<domain>/**` receiving what it publishes.

    deploy/bench-ros2 [--keyframes 2000] [--seconds 20] [--rate-hz 2] [--doorslam BIN]

Prints one JSON object: the service's CPU (user + system seconds over wall seconds, from
/proc/<pid>/stat), its peak resident memory, the samples and bytes the subscriber got per
second, and the service's own counters (its `ros2: stopped` log line).
"""

import argparse
import json
import math
import os
import re
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import zenoh


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def write_atomic(path, text):
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def write_state(d, n, shift):
    """keyframes.csv, odometry.tum, team_estimate.tum (odometry moved by `shift`),
    graph.g2o with a closure every 50 keyframes, backend.json."""
    kf, odo, team, g2o = ["id,stamp_ns"], [], [], []
    for i in range(n):
        t = 1_700_000_000_000_000_000 + i * 500_000_000
        x, y = 0.5 * i, 10 * math.sin(i / 100)
        kf.append(f"{i},{t}")
        stamp = f"{t // 10**9}.{t % 10**9:09d}"
        odo.append(f"{stamp} {x:.6f} {y:.6f} 0 0 0 0 1")
        team.append(f"{stamp} {x + shift:.6f} {y:.6f} 0.1 0 0 0 1")
        g2o.append(f"VERTEX_SE3:QUAT {(ord('a') << 56) | i} {x:.6f} {y:.6f} 0 0 0 0 1")
    info = " ".join(["100 0 0 0 0 0", "100 0 0 0 0", "100 0 0 0", "100 0 0", "100 0", "100"])
    for i in range(1, n):
        g2o.append(f"EDGE_SE3:QUAT {(ord('a') << 56) | (i - 1)} {(ord('a') << 56) | i} 0.5 0 0 0 0 0 1 {info}")
    for i in range(0, n, 50):
        g2o.append(f"EDGE_SE3:QUAT {(ord('a') << 56) | i} {(ord('b') << 56) | i} 1 2 0 0 0 0 1 {info}")
    write_atomic(d / "odometry.tum", "\n".join(odo) + "\n")
    write_atomic(d / "keyframes.csv", "\n".join(kf) + "\n")
    write_atomic(d / "team_estimate.tum", "\n".join(team) + "\n")
    write_atomic(d / "graph.g2o", "\n".join(g2o) + "\n")
    write_atomic(d / "backend.json", json.dumps({"team": {"rejected_closures": [["a0", "b0"]]}}))


def cpu_s(pid):
    f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")


def rss_peak_kb(pid):
    m = re.search(r"VmHWM:\s+(\d+)", Path(f"/proc/{pid}/status").read_text())
    return int(m.group(1)) if m else None


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--keyframes", type=int, default=2000)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--rate-hz", type=float, default=2.0)
    ap.add_argument("--write-every-s", type=float, default=0.5)
    ap.add_argument("--doorslam", default="target/release/doorslam")
    a = ap.parse_args()

    tmp = Path(tempfile.mkdtemp(prefix="bench-ros2-"))
    robot = f"bench{os.getpid()}"
    state = tmp / "state"
    (state / robot).mkdir(parents=True)
    write_state(state / robot, a.keyframes, 0.0)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    (tmp / "robot.toml").write_text(
        f'[robot]\nid = "{robot}"\n[backend]\nstate_dir = "{state}"\n'
        f'[ros2]\nenabled = true\nrate_hz = {a.rate_hz}\nlisten = ["{endpoint}"]\nconnect = []\n'
    )

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    got = {"samples": 0, "bytes": 0}
    lock = threading.Lock()

    def on_sample(s):
        with lock:
            got["samples"] += 1
            got["bytes"] += len(s.payload.to_bytes())

    env = dict(os.environ, RUST_LOG="info,zenoh=warn")
    svc = subprocess.Popen([a.doorslam, "service", "ros2", "--config", str(tmp / "robot.toml")],
                           stderr=subprocess.PIPE, text=True, env=env)
    log = []
    threading.Thread(target=lambda: log.extend(svc.stderr), daemon=True).start()
    time.sleep(1.0)
    session = zenoh.open(conf)
    sub = session.declare_subscriber("0/**", on_sample)
    time.sleep(1.0)
    with lock:
        got.update(samples=0, bytes=0)
    c0, t0 = cpu_s(svc.pid), time.time()
    next_write, k = t0, 0
    while time.time() - t0 < a.seconds:
        if time.time() >= next_write:
            k += 1
            write_state(state / robot, a.keyframes, 0.001 * k)
            next_write += a.write_every_s
        time.sleep(0.01)
    wall, cpu = time.time() - t0, cpu_s(svc.pid) - c0
    with lock:
        samples, nbytes = got["samples"], got["bytes"]
    rss = rss_peak_kb(svc.pid)
    svc.send_signal(signal.SIGINT)
    svc.wait(timeout=20)
    sub.undeclare()
    session.close()
    stopped = next((l.strip() for l in log if "ros2: stopped" in l), None)
    print(json.dumps({
        "keyframes": a.keyframes, "rate_hz": a.rate_hz, "write_every_s": a.write_every_s,
        "seconds": round(wall, 2), "cpu_percent": round(100 * cpu / wall, 2),
        "peak_rss_mb": None if rss is None else round(rss / 1024, 1),
        "received_samples_per_s": round(samples / wall, 2),
        "received_kbytes_per_s": round(nbytes / wall / 1024, 1),
        "state_rewrites": k, "service_log": stopped,
    }))
    return 0 if svc.returncode == 0 and samples > 0 else 1


if __name__ == "__main__":
    sys.exit(main())
