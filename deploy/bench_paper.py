#!/usr/bin/env python3
"""The DOOR-SLAM paper's back-end experiments through doorslam's distributed back-end
(`doorslam dpgo`: one agent per robot, every message encoded, PCM inside the loop); prints
BENCHMARKS.md's Markdown tables. Run through `deploy/bench-paper`.

    bench_paper.py DOORSLAM DATA ACCEPTANCE [sim] [kitti] ...

sim    paper Fig. 5/6: simulated 5-robot teams (`doorslam sim graph`, 30 % uniform outlier
       closures), PCM threshold sweep: % outliers / inliers rejected, ATE against the
       simulator's ground truth over the robots in robot a's frame.
kitti  paper §IV-B and Table III's thresholds: DOOR-SLAM's own KITTI 00 split into 5 robots
       (ACCEPTANCE/kitti00_5robots), uniform outliers injected as DOOR-SLAM's dataset
       simulation does, PCM at 1 %, 10 %, 25 %, 75 %, 99 % and none; ATE against the official
       KITTI 00 ground truth (DATA/trajectories/kitti_gt/00.txt, global frame = 908 r + k).
       The KITTI images are not available here: the front-end is not in this experiment,
       the loop closures are the split's own (as in DOOR-SLAM's dataset runs).

Only the standard library: ATE is `doorslam eval ate` (SE(3) alignment, evo's numbers)."""
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile

SIM_SEEDS = tuple(range(1, 101))
SIM_THRESHOLDS = (0.01, 0.05, 0.10, 0.25, 0.50, 0.75, 0.90, 0.99, None)
KITTI_SEEDS = (1, 2, 3)
KITTI_OUTLIERS = (0.3, 0.5)
KITTI_THRESHOLDS = (0.01, 0.10, 0.25, 0.75, 0.99, None)
KITTI_POSES_PER_ROBOT = 908


def run_json(*args):
    out = subprocess.run([*args, "--json"], check=True, capture_output=True, text=True)
    return json.loads(out.stdout)


def robot_of(key):
    c = key >> 56
    return chr(c), key & ((1 << 56) - 1)


def robot_index(c):
    return ord(c) - ord("a") if c.islower() else 26 + ord(c) - ord("A")


def read_estimate(path):
    """(robot → anchor, key → (x y z qx qy qz qw)) of `doorslam dpgo --out`."""
    anchors, poses = {}, {}
    with open(path) as f:
        for line in f:
            t = line.split()
            if not t:
                continue
            if t[0] == "#" and len(t) == 5 and t[1] == "robot" and t[3] == "anchor":
                anchors[t[2]] = t[4]
            elif t[0] == "VERTEX_SE3:QUAT":
                poses[int(t[1])] = [float(x) for x in t[2:9]]
    return anchors, poses


def quaternion(r):
    """(qx, qy, qz, qw) of a rotation matrix (rows)."""
    tr = r[0][0] + r[1][1] + r[2][2]
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        return ((r[2][1] - r[1][2]) / s, (r[0][2] - r[2][0]) / s, (r[1][0] - r[0][1]) / s, 0.25 * s)
    i = max(range(3), key=lambda j: r[j][j])
    j, k = (i + 1) % 3, (i + 2) % 3
    s = math.sqrt(1.0 + r[i][i] - r[j][j] - r[k][k]) * 2
    q = [0.0, 0.0, 0.0, (r[k][j] - r[j][k]) / s]
    q[i] = 0.25 * s
    q[j] = (r[j][i] + r[i][j]) / s
    q[k] = (r[k][i] + r[i][k]) / s
    return tuple(q)


def kitti_rows(path):
    """One (x y z qx qy qz qw) per line of a KITTI pose file."""
    rows = []
    with open(path) as f:
        for line in f:
            v = [float(x) for x in line.split()]
            if len(v) != 12:
                continue
            r = [v[0:3], v[4:7], v[8:11]]
            rows.append([v[3], v[7], v[11], *quaternion(r)])
    return rows


def write_tum(path, rows):
    with open(path, "w") as f:
        for t, p in sorted(rows):
            f.write(f"{t} " + " ".join(f"{x:.9g}" for x in p) + "\n")


def ate(doorslam, est_rows, gt_rows, tmp):
    """RMSE ATE (SE(3)-aligned) of the rows both have, by timestamp."""
    common = sorted(set(est_rows) & set(gt_rows))
    if len(common) < 3:
        return math.nan
    e, g = os.path.join(tmp, "est.tum"), os.path.join(tmp, "gt.tum")
    write_tum(e, [(t, est_rows[t]) for t in common])
    write_tum(g, [(t, gt_rows[t]) for t in common])
    return run_json(doorslam, "eval", "ate", e, g, "--max-time-diff", "0.1")["ate_rmse"]


def framed(anchors, poses, first_robot):
    """Robots in `first_robot`'s frame (the team's anchor) and their poses, by key."""
    robots = {r for r, a in anchors.items() if a == first_robot}
    return robots, {k: p for k, p in poses.items() if robot_of(k)[0] in robots}


def dpgo(doorslam, files, tmp, pcm, extra):
    est = os.path.join(tmp, "team.g2o")
    args = [doorslam, "dpgo", *files, "--out", est, *extra]
    if pcm is not None:
        args += ["--pcm", str(pcm)]
    report = run_json(*args)
    anchors, poses = read_estimate(est)
    return report, anchors, poses


def mean_std(xs):
    xs = [x for x in xs if not math.isnan(x)]
    if not xs:
        return "n/a"
    if len(xs) == 1:
        return f"{xs[0]:.3f}"
    return f"{statistics.mean(xs):.3f} ± {statistics.stdev(xs):.3f}"


def pct_str(xs):
    xs = [x for x in xs if not math.isnan(x)]
    return f"{statistics.mean(xs):.1f} ± {statistics.stdev(xs) if len(xs) > 1 else 0:.1f}" if xs else "n/a"


def label(p):
    return "none" if p is None else f"{100 * p:g} %"


def table_sim(doorslam, tmp):
    teams = []
    for seed in SIM_SEEDS:
        d = os.path.join(tmp, f"sim{seed}")
        subprocess.run([doorslam, "sim", "graph", "--robots", "5", "--poses", "100", "--outliers", "0.3",
                        "--seed", str(seed), "--out", d], check=True, capture_output=True)
        gt = {}
        for r in "abcde":
            with open(os.path.join(d, f"gt_{r}.tum")) as f:
                for line in f:
                    if line.startswith("#"):
                        continue
                    t = line.split()
                    gt[robot_index(r) * 100000 + int(float(t[0]))] = [float(x) for x in t[1:8]]
        teams.append((d, gt))
    print("| PCM threshold | outliers rejected (%) | inliers rejected (%) | ATE (m) | robots in a's frame | bytes | converged |")
    print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for p in SIM_THRESHOLDS:
        o, i, a, n, b, c = [], [], [], [], [], 0
        for d, gt in teams:
            report, anchors, poses = dpgo(doorslam, [os.path.join(d, "graph.g2o")], tmp, p,
                                                    ["--labels", os.path.join(d, "labels.txt")])
            o.append(100.0 * report["outliers_rejected"] / max(report["outliers"], 1))
            i.append(100.0 * report["inliers_rejected"] / max(report["inliers"], 1))
            robots, mine = framed(anchors, poses, "a")
            est = {robot_index(robot_of(k)[0]) * 100000 + robot_of(k)[1]: x for k, x in mine.items()}
            a.append(ate(doorslam, est, gt, tmp))
            n.append(len(robots))
            b.append(report["bytes"])
            c += bool(report["converged"])
        print(f"| {label(p)} | {pct_str(o)} | {pct_str(i)} | {mean_std(a)} | {statistics.mean(n):.1f} "
              f"| {statistics.mean(b):,.0f} | {c}/{len(teams)} |", flush=True)


def table_kitti(doorslam, data, acceptance, tmp):
    split = os.path.join(acceptance, "kitti00_5robots")
    files = [os.path.join(split, f"{r}.g2o") for r in range(5)]
    gt_path = os.path.join(data, "trajectories/kitti_gt/00.txt")
    if not all(os.path.isfile(f) for f in files + [gt_path]):
        print(f"skipped kitti: {split} or {gt_path} missing", file=sys.stderr)
        return
    gt = dict(enumerate(kitti_rows(gt_path)))

    def team_ate(anchors, poses):
        robots, mine = framed(anchors, poses, "a")
        est = {KITTI_POSES_PER_ROBOT * robot_index(robot_of(k)[0]) + robot_of(k)[1]: x
               for k, x in mine.items()}
        return ate(doorslam, est, gt, tmp), len(robots)

    print("| injected outliers | PCM threshold | outliers rejected (%) | inliers rejected (%) | ATE vs KITTI 00 ground truth (m) | robots in a's frame | bytes | converged |")
    print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for p in (0.01, None):
        report, anchors, poses = dpgo(doorslam, files, tmp, p, [])
        e, n = team_ate(anchors, poses)
        # No labels without injection: every closure of the split is taken as an inlier.
        inl = 100.0 * report["rejected_distributed"] / max(report["closures"], 1)
        print(f"| 0 | {label(p)} | n/a | {inl:.1f} | {e:.3f} | {n} | {report['bytes']:,} | {report['converged']} |",
              flush=True)
    for fraction, p in ((f, p) for f in KITTI_OUTLIERS for p in KITTI_THRESHOLDS):
        o, i, a, n, b, c = [], [], [], [], [], 0
        for seed in KITTI_SEEDS:
            report, anchors, poses = dpgo(
                doorslam, files, tmp, p,
                ["--inject-outliers", str(fraction), "--outlier-seed", str(seed)])
            # `--inject-outliers` labels every closure (the split's as inliers).
            o.append(100.0 * report["outliers_rejected"] / max(report["outliers"], 1))
            i.append(100.0 * report["inliers_rejected"] / max(report["inliers"], 1))
            e, r = team_ate(anchors, poses)
            a.append(e)
            n.append(r)
            b.append(report["bytes"])
            c += bool(report["converged"])
        print(f"| {100 * fraction:g} % | {label(p)} | {pct_str(o)} | {pct_str(i)} | {mean_std(a)} "
              f"| {statistics.mean(n):.1f} | {statistics.mean(b):,.0f} | {c}/{len(KITTI_SEEDS)} |", flush=True)


def main():
    doorslam, data, acceptance, *tables = sys.argv[1:]
    tables = tables or ["sim", "kitti"]
    with tempfile.TemporaryDirectory() as tmp:
        for t in tables:
            print(f"\n### {t}\n")
            if t == "sim":
                table_sim(doorslam, tmp)
            elif t == "kitti":
                table_kitti(doorslam, data, acceptance, tmp)
            else:
                sys.exit(f"unknown table {t!r}: sim or kitti")


if __name__ == "__main__":
    main()
