#!/usr/bin/env python3
"""A soak: two robots fly a closed route for an hour or more of flight time, accelerated
(`--rate` > 1), with every process's resident memory and open files sampled, to show
both flat after warm-up (issue #33: RSS growth < 10 % between the 10th minute and the
end, per process).

    deploy/soak [--world DIR] [--hours 1] [--rate 4] [--sample-s 10] [--out DIR]

What it runs: per robot `doorslam up` with every service of the demo's robots (camera
replay, frontend, place-recognition, backend, team), the two team links over mutual TLS
on loopback (certificates of `doorslam team certs --clockless`), each robot in its own
iceoryx2 services of one domain of this soak.

What it flies: rendering an hour of flight is too slow here, so each robot replays a
rendered flight (`--world`: an earlier `doorslam demo`'s `<out>/world`, or rendered now
with `doorslam sim world --plan sectors`) as a closed route: forward, then backward
(frames mirrored in time, so the trajectory is continuous: no jump at the turn), again
and again until `--hours` of flight. The images are symlinks, the stamps continue. So
the robots revisit the same places every lap: place recognition, verification and the
back-end see every place many times (closures accumulate), the team link has its
meetings, but nothing new is seen after the first lap.

Samples go to `<out>/soak.csv` (flight s, wall s, robot, process, pid, rss_kb, fds, and
RSS split as the kernel counts it: rss_anon_kb private memory (heap, stacks), rss_file_kb
mapped files (the binary, libraries), rss_shmem_kb shared memory (iceoryx2's segments,
counted in every process that touched their pages));
the summary (per process: RSS and open files at the 10th minute of flight and at the
end, growth, peak, and the growth of each part) is printed as a table and written to
`<out>/soak.json`. Exit status 1 when a process's RSS grew by 10 % or more after the
10th minute, or a robot's process died, or a robot's pipeline stalled: flat memory of a
pipeline that stopped working proves nothing, so each sample also records the frames the
front-end has processed and the keyframes the back-end holds (`frontend.json`,
`backend.json`), and a robot whose front-end or back-end made no progress over the last
`STALL_FLIGHT_S` of flight (or stopped rewriting its status file) is named as stalled.
"""

import argparse
import csv
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

WARMUP_FLIGHT_S = 600.0
MAX_GROWTH = 0.10
# A front-end or back-end that made no progress over this much flight (s) stalled.
STALL_FLIGHT_S = 600.0


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run(cmd):
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        sys.exit(f"soak: {' '.join(map(str, cmd))} failed:\n{r.stderr}")
    return r.stdout


def sequences(world):
    """The world's per-robot KITTI sequences, in robot order (folders with times.txt)."""
    seqs = sorted(p.parent for p in world.glob("*/times.txt"))
    if len(seqs) < 2:
        sys.exit(f"soak: {world}: fewer than two robot sequences (folders with times.txt)")
    return seqs[:2]


def closed_route(src, dst, flight_s):
    """`src` replayed forward then backward until at least `flight_s` of flight: image
    symlinks, stamps continuing at the source's period, poses of the frame shown."""
    times = [float(t) for t in (src / "times.txt").read_text().split()]
    poses = (src / "poses.txt").read_text().splitlines()
    n = len(times)
    if n < 3 or len(poses) != n:
        sys.exit(f"soak: {src}: {n} stamps, {len(poses)} poses")
    period = (times[-1] - times[0]) / (n - 1)
    lap = list(range(n)) + list(range(n - 2, 0, -1))
    order = []
    while len(order) * period < flight_s:
        order.extend(lap)
    for eye in ("image_0", "image_1"):
        (dst / eye).mkdir(parents=True)
    for k, i in enumerate(order):
        name = f"{i:06d}.png"
        for eye in ("image_0", "image_1"):
            os.symlink((src / eye / name).resolve(), dst / eye / f"{k:06d}.png")
    (dst / "times.txt").write_text("".join(f"{k * period:.6f}\n" for k in range(len(order))))
    (dst / "poses.txt").write_text("".join(poses[i] + "\n" for i in order))
    # Calibration and anything else the sequence carries, as it is.
    for f in src.iterdir():
        if f.is_file() and f.name not in ("times.txt", "poses.txt"):
            os.symlink(f.resolve(), dst / f.name)
    return len(order), period


def robot_toml(out, name, index, seq, rate, start_ms, team, ends, certs, roster):
    others = ", ".join(f'"{e}"' for i, e in enumerate(ends) if i != index)
    roster = ", ".join(f'"{r}"' for r in roster)
    return f"""# doorslam soak: robot {name} (written by deploy/soak)
[robot]
id = "{name}"
index = {index}

[camera]
source = "replay"

[camera.replay]
path = "{seq}"
rate = {rate}
wait_for_subscribers_s = 30.0
start_unix_ms = {start_ms}
status_file = "{out}/{name}/camera.json"

[frontend]
run_dir = "{out}"

[backend]
state_dir = "{out}"
optimize_every = 10
distributed = true
write_every_s = 0.5

[team]
name = "{team}"
listen = ["{ends[index]}"]
connect = [{others}]
multicast_scouting = false
lease_ms = 3000
run_dir = "{out}"
retransmit_ms = 500
write_every_ms = 500

[team.tls]
ca = "{certs}/ca.pem"
cert = "{certs}/robots/{name}/cert.pem"
key = "{certs}/robots/{name}/key.pem"
robots = [{roster}]

[up]
services = ["backend", "frontend", "place-recognition", "team", "camera"]
"""


def process_name(pid):
    try:
        args = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return None
    args = [a.decode(errors="replace") for a in args if a]
    if "service" in args:
        i = args.index("service")
        return args[i + 1] if i + 1 < len(args) else "service"
    if "up" in args:
        return "up"
    return Path(args[0]).name if args else None


def progress(out, name):
    """(front-end frames processed, back-end keyframes), None where unreadable."""
    def read(f, key):
        try:
            return json.loads((out / name / f).read_text()).get(key)
        except (OSError, ValueError):
            return None
    return read("frontend.json", "frames"), read("backend.json", "keyframes")


def group(pgid):
    """(pid, name, rss_kb, fds, anon_kb, file_kb, shmem_kb) of every process in the
    process group."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            fields = stat[stat.rindex(")") + 2 :].split()
            if int(fields[2]) != pgid or fields[0] == "Z":
                continue
            kb = {}
            for line in (d / "status").read_text().splitlines():
                key = line.split(":", 1)[0]
                if key in ("VmRSS", "RssAnon", "RssFile", "RssShmem"):
                    kb[key] = int(line.split()[1])
            rss = kb.get("VmRSS", 0)
            fds = len(os.listdir(d / "fd"))
            name = process_name(int(d.name))
        except (OSError, ValueError, IndexError):
            continue
        if name:
            out.append((int(d.name), name, rss, fds, kb.get("RssAnon", 0),
                        kb.get("RssFile", 0), kb.get("RssShmem", 0)))
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--doorslam", required=True)
    ap.add_argument("--world", type=Path, help="a rendered world (a demo's <out>/world)")
    ap.add_argument("--hours", type=float, default=1.0, help="flight time per robot")
    ap.add_argument("--rate", type=float, default=4.0, help="replay speed (> 1: accelerated)")
    ap.add_argument("--sample-s", type=float, default=10.0, help="wall seconds between samples")
    ap.add_argument("--out", type=Path, default=Path(f"/tmp/doorslam-soak-{int(time.time())}"))
    a = ap.parse_args()
    if a.rate <= 1.0:
        sys.exit("soak: --rate must be above 1 (an accelerated run)")
    if a.hours * 3600 <= WARMUP_FLIGHT_S:
        sys.exit(f"soak: --hours must give more than the {WARMUP_FLIGHT_S:.0f} s of warm-up")
    out = a.out.resolve()
    if out.exists() and any(out.iterdir()):
        sys.exit(f"soak: {out} is not empty")
    out.mkdir(parents=True, exist_ok=True)
    exe = str(Path(a.doorslam).resolve())

    world = a.world
    if world is None:
        world = out / "world"
        print("soak: rendering a 2-robot flight (doorslam sim world --plan sectors)", file=sys.stderr)
        run([exe, "sim", "world", "--plan", "sectors", "--robots", "2", "--frames", "600",
             "--speed-mps", "5", "--out", str(world)])
    names, seqs, flight_s = ["a", "b"], [], 0.0
    for name, src in zip(names, sequences(world.resolve())):
        dst = out / "route" / name
        frames, period = closed_route(src, dst, a.hours * 3600)
        seqs.append(dst)
        flight_s = max(flight_s, frames * period)
    team = f"soak{os.getpid()}"
    certs = out / "certs"
    run([exe, "team", "certs", "--out", str(certs), "--robots", ",".join(names),
         "--team", team, "--clockless"])
    ends = [f"tls/127.0.0.1:{free_port()}" for _ in names]
    start_ms = int(time.time() * 1000) + 8000
    env = dict(os.environ, DOORSLAM_IPC_DOMAIN=f"soak{os.getpid()}", RUST_LOG="info,zenoh=warn")
    robots = []
    for i, (name, seq) in enumerate(zip(names, seqs)):
        (out / name).mkdir(exist_ok=True)
        cfg = out / name / "robot.toml"
        cfg.write_text(robot_toml(out, name, i, seq, a.rate, start_ms, team, ends, certs, names))
        log = open(out / name / "robot.log", "w")
        p = subprocess.Popen([exe, "up", "--config", str(cfg)], stdout=log, stderr=log,
                             env=env, process_group=0)
        robots.append((name, p, log))
    print(f"soak: {len(names)} robots, {flight_s / 3600:.2f} h of flight each at rate {a.rate} "
          f"(about {flight_s / a.rate / 60:.0f} min), samples in {out}/soak.csv", file=sys.stderr)

    samples, died = [], []
    seen = {name: [] for name in names}  # (flight s, frames, keyframes) per sample
    t0 = time.time()
    with open(out / "soak.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["flight_s", "wall_s", "robot", "process", "pid", "rss_kb", "fds",
                    "rss_anon_kb", "rss_file_kb", "rss_shmem_kb"])
        while True:
            now = time.time()
            flight = (now - start_ms / 1000) * a.rate
            for name, p, _ in robots:
                seen[name].append((flight, *progress(out, name)))
                if p.poll() is not None:
                    died.append(f"robot {name}: doorslam up exited ({p.returncode}) at {flight:.0f} s of flight")
                for pid, proc, rss, fds, anon, mapped, shmem in group(p.pid):
                    row = (round(flight, 1), round(now - t0, 1), name, proc, pid, rss, fds,
                           anon, mapped, shmem)
                    w.writerow(row)
                    samples.append(row)
            f.flush()
            if died or flight > flight_s + 30 * a.rate:
                break
            print(f"\rsoak: {max(flight, 0) / 60:6.1f} of {flight_s / 60:.0f} min of flight", end="", file=sys.stderr)
            time.sleep(a.sample_s)
    print(file=sys.stderr)
    for _, p, _ in robots:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
    for name, p, log in robots:
        try:
            p.wait(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
            died.append(f"robot {name}: did not stop within 60 s of SIGINT")
        log.close()

    # Progress: the front-end's frames and the back-end's keyframes must still move in the
    # last STALL_FLIGHT_S of the route (the replay stops at its end).
    stalled, progress_rows = [], {}
    for name in names:
        xs = [x for x in seen[name] if x[0] <= flight_s]
        if not xs:
            continue
        last = xs[-1]
        before = [x for x in xs if x[0] <= last[0] - STALL_FLIGHT_S] or xs[:1]
        ref = before[-1]
        at10 = next((x for x in xs if x[0] >= WARMUP_FLIGHT_S), last)
        progress_rows[name] = {
            "frames_at_10_min": at10[1], "frames_end": last[1],
            "keyframes_at_10_min": at10[2], "keyframes_end": last[2],
        }
        for what, i in (("front-end frames", 1), ("back-end keyframes", 2)):
            if ref[i] is not None and last[i] is not None and last[i] <= ref[i]:
                stalled.append(f"robot {name}: {what} stuck at {last[i]} from {ref[0] / 60:.0f} "
                               f"to {last[0] / 60:.0f} min of flight")

    # Per process: the sample at the 10th minute of flight, the last one, the peak.
    per = {}
    for flight, _, robot, proc, pid, rss, fds, anon, mapped, shmem in samples:
        per.setdefault((robot, proc), []).append((flight, pid, rss, fds, anon, mapped, shmem))
    rows, grew = [], []
    for (robot, proc), xs in sorted(per.items()):
        after = [x for x in xs if x[0] >= WARMUP_FLIGHT_S]
        if not after:
            continue
        first, last = after[0], after[-1]
        growth = (last[2] - first[2]) / max(first[2], 1)
        row = {
            "robot": robot,
            "process": proc,
            "pids": sorted({x[1] for x in xs}),
            "rss_kb_at_10_min": first[2],
            "rss_kb_end": last[2],
            "rss_kb_peak": max(x[2] for x in xs),
            "rss_growth": round(growth, 4),
            "fds_at_10_min": first[3],
            "fds_end": last[3],
            "fds_peak": max(x[3] for x in xs),
            "end_flight_s": last[0],
            # What grew: private memory, mapped files, shared memory (kB, end - 10 min).
            "anon_kb_at_10_min": first[4],
            "anon_kb_end": last[4],
            "anon_growth": round((last[4] - first[4]) / max(first[4], 1), 4),
            "file_kb_delta": last[5] - first[5],
            "shmem_kb_at_10_min": first[6],
            "shmem_kb_end": last[6],
        }
        rows.append(row)
        if growth >= MAX_GROWTH:
            grew.append(f"{robot}/{proc}: RSS {first[2]} kB -> {last[2]} kB ({100 * growth:+.1f} %)")
    status = {}
    for name in names:
        for f in ("camera.json", "backend.json", "frontend.json", "status.json"):
            try:
                status.setdefault(name, {})[f] = json.loads((out / name / f).read_text())
            except (OSError, ValueError):
                pass
    summary = {
        "robots": names,
        "rate": a.rate,
        "flight_s": flight_s,
        "wall_s": round(time.time() - t0, 1),
        "sample_s": a.sample_s,
        "world": str(world),
        "warmup_flight_s": WARMUP_FLIGHT_S,
        "max_growth": MAX_GROWTH,
        "processes": rows,
        "grew": grew,
        "died": died,
        "progress": progress_rows,
        "stalled": stalled,
        "ok": not grew and not died and not stalled,
    }
    (out / "soak.json").write_text(json.dumps(summary, indent=1) + "\n")
    print(f"| robot | process | RSS at 10 min (kB) | RSS end (kB) | growth | RSS peak (kB) | open files 10 min / end / peak "
          f"| private (anon) 10 min / end (kB) | shared memory 10 min / end (kB) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['robot']} | {r['process']} | {r['rss_kb_at_10_min']} | {r['rss_kb_end']} | "
              f"{100 * r['rss_growth']:+.1f} % | {r['rss_kb_peak']} | {r['fds_at_10_min']} / {r['fds_end']} / {r['fds_peak']} "
              f"| {r['anon_kb_at_10_min']} / {r['anon_kb_end']} ({100 * r['anon_growth']:+.1f} %) "
              f"| {r['shmem_kb_at_10_min']} / {r['shmem_kb_end']} |")
    for name in names:
        cam = status.get(name, {}).get("camera.json", {})
        print(f"{name}: camera {json.dumps(cam)[:300]}")
    for name, r in progress_rows.items():
        print(f"{name}: front-end frames {r['frames_at_10_min']} at 10 min, {r['frames_end']} at the end; "
              f"back-end keyframes {r['keyframes_at_10_min']} / {r['keyframes_end']}")
    for line in grew + died + stalled:
        print(f"soak: {line}", file=sys.stderr)
    print(f"soak: {'flat' if summary['ok'] else 'NOT flat'}; {out}/soak.json", file=sys.stderr)
    sys.exit(0 if summary["ok"] else 1)


if __name__ == "__main__":
    main()
