#!/usr/bin/env python3
"""Runs `doorslam demo` in the configurations BENCHMARKS.md reports (issue #31) and prints
their figures side by side as one Markdown table. Run through `deploy/bench-demo`.

    bench_demo.py DOORSLAM [OUT] [default] [drop] [kill] [five]

Every figure is read from the run's own summary.json (the demo's `--json`); wall times
are the demo's own, CPU times are measured per process by the demo (`cpu` section)."""
import json
import os
import subprocess
import sys
import time

RUNS = ("default", "drop", "kill", "five")


def demo(exe, out, *extra):
    """One demo run into `out` (must not exist); its summary and the wall seconds."""
    start = time.monotonic()
    run = subprocess.run(
        [exe, "demo", "--out", out, "--json", *extra],
        capture_output=True,
        text=True,
    )
    wall = time.monotonic() - start
    if run.returncode != 0:
        sys.exit(f"doorslam demo {' '.join(extra)} failed:\n{run.stderr[-4000:]}")
    return json.loads(run.stdout), wall


def fmt(v, digits=2):
    if v is None:
        return "—"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


def row(name, s, wall):
    per = s["per_robot"]
    vo = [x["ate_vo_m"] for x in per.values() if x["ate_vo_m"] is not None]
    c = s["closures"]
    bw = s["bandwidth"] or {}
    d = s["durations"]
    cpu = s["cpu"]
    rt = s["realtime"]
    return [
        name,
        f"{s['robots']} × {s['frames']}",
        fmt(wall, 0),
        fmt(d["render_s"], 0),
        fmt(d["flight_s"], 0),
        fmt(d["settle_s"], 0),
        fmt(sum(vo) / len(vo) if vo else None),
        fmt(s["team_ate_m"]),
        fmt(s["centralized_ate_m"]),
        fmt(s["team_gain"]),
        f"{s['robots_in_team_frame']}/{s['robots']}",
        f"{c['total']} ({c['true_accepted']}/{c['true_rejected']}/{c['false_accepted']}/{c['false_rejected']}, {c['aliased']} aliased)",
        fmt(bw.get("total_bytes", 0) / 1e3, 1),
        fmt(d["robots_cpu_s"], 0),
        fmt(cpu["render_s"], 0),
        fmt(rt["kept_up"]),
        fmt(cpu.get("machine_shared")),
    ]


HEADER = [
    "run",
    "robots × frames",
    "wall (s)",
    "render (s)",
    "flight (s)",
    "at base (s)",
    "odometry alone, mean ATE (m)",
    "team ATE, team frame (m)",
    "centralized oracle (m)",
    "team_gain",
    "in team frame",
    "closures (true kept/rejected, false kept/rejected)",
    "kB between robots",
    "robots' CPU (s)",
    "render CPU (s)",
    "real time",
    "machine shared",
]


def main():
    exe = sys.argv[1]
    args = sys.argv[2:]
    out = "/tmp/bench-demo"
    if args and args[0] not in RUNS:
        out, args = args[0], args[1:]
    runs = [r for r in RUNS if r in args] or list(RUNS)
    os.makedirs(out, exist_ok=True)
    world = os.path.join(out, "default", "world")
    rows = []
    for name in runs:
        dest = os.path.join(out, name)
        if os.path.exists(dest):
            sys.exit(f"{dest} exists: give a new OUT folder")
        if name == "default":
            s, wall = demo(exe, dest)
        elif name == "drop":
            s, wall = demo(exe, dest, "--world", world, "--drop", "0.3")
        elif name == "kill":
            s, wall = demo(exe, dest, "--world", world, "--kill", "b@45")
        else:
            s, wall = demo(exe, dest, "--robots", "5")
        rows.append(row(name, s, wall))
        print(f"{name}: {s['realtime']['verdict']}", file=sys.stderr)
    print("| " + " | ".join(HEADER) + " |")
    print("|" + "---|" * len(HEADER))
    for r in rows:
        print("| " + " | ".join(r) + " |")


if __name__ == "__main__":
    main()
