#!/usr/bin/env python3
"""GTSAM (PyPI) versus `doorslam pgo`, side by side on the same files in one run.

Run through `deploy/bench-pgo`, which installs gtsam into the project venv and builds
doorslam. For every file:
  * GTSAM Levenberg-Marquardt from the file's poses (odometry chained where a file has no
    VERTEX lines), first pose fixed by a tight prior;
  * GTSAM chordal initialization (InitializePose3 in 3-D, LAGO in 2-D) + LM;
  * `doorslam pgo FILE --json` with its default options.
Each run is a separate process, so peak memory (max RSS) is per run. Times are the
optimization alone (initialization included, file reading excluded). All final costs are
evaluated by one definition, doorslam's chi2 = sum r^T Omega r (= 2x GTSAM's error): GTSAM's
result is written as g2o and re-scored by `doorslam pgo --init file --max-iterations 0`.

Files of the held-out set (--acceptance) are measured here, never tuned on. SE-Sync's cubicle
has 5,021 edges (of 16,869) whose information matrix is indefinite, so `doorslam pgo` refuses
it by default; it runs with `--information nearest-pd` (each such matrix projected onto the
nearest positive-definite one), and both results are scored under those repaired matrices.
GTSAM's reader takes the file without complaint but does not use the matrices as written
either: it whitens with the upper factor of an Eigen LLT without checking that the
factorization succeeded, which for an indefinite matrix is a partial, different factor. As
written (`--information as-is`) the objective is not a sum of squares and is unbounded below
(doorslam stops with stop_reason "negative_cost"), so there is no optimum to compare.
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

# (name, set, path under <set>/pose_graphs, 3-D, extra `doorslam pgo` arguments); set "data"
# is the developer set (--data), "acceptance" the held-out one (--acceptance).
FILES = [
    ("M3500", "data", "dpgo/input_M3500_g2o.g2o", False, []),
    ("intel", "data", "se-sync/intel.g2o", False, []),
    ("city10000", "data", "se-sync/city10000.g2o", False, []),
    ("kitti_00", "data", "dpgo/kitti_00.g2o", False, []),
    ("sphere2500", "data", "se-sync/sphere2500.g2o", True, []),
    ("torus3D", "data", "se-sync/torus3D.g2o", True, []),
    ("parking-garage", "data", "se-sync/parking-garage.g2o", True, []),
    ("cubicle (nearest-pd)", "acceptance", "se-sync/cubicle.g2o", True, ["--information", "nearest-pd"]),
]


def run_measured(cmd):
    """Runs a command under GNU time, so its own peak memory (max RSS) is known: a fork of
    this Python process would count the interpreter's pages as the child's."""
    proc = subprocess.run(["/usr/bin/time", "-f", "maxrss_kb=%M", *cmd], capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stderr}")
    rss = [l for l in proc.stderr.splitlines() if l.startswith("maxrss_kb=")][-1]
    return proc.stdout, int(rss.split("=")[1]) / 1024.0


def chain_odometry(gtsam, graph, initial, is3d):
    """Initial values for keys without a VERTEX line, composing between-factors outward."""
    between = []
    for k in range(graph.size()):
        f = graph.at(k)
        if f is None:
            continue
        keys = f.keys()
        if len(keys) == 2:
            between.append((keys[0], keys[1], f.measured()))
    at = initial.atPose3 if is3d else initial.atPose2
    keys = sorted({a for a, _, _ in between} | {b for _, b, _ in between})
    if all(initial.exists(k) for k in keys):
        return initial
    start = keys[0]
    if not initial.exists(start):
        initial.insert(start, gtsam.Pose3() if is3d else gtsam.Pose2())
    adj = {}
    for a, b, z in between:
        adj.setdefault(a, []).append((b, z, False))
        adj.setdefault(b, []).append((a, z, True))
    queue, seen = [start], {start}
    while queue:
        a = queue.pop(0)
        for b, z, backwards in adj.get(a, []):
            if b in seen:
                continue
            seen.add(b)
            queue.append(b)
            if not initial.exists(b):
                initial.insert(b, at(a).compose(z.inverse() if backwards else z))
    return initial


def gtsam_child(path, is3d, mode, out_g2o):
    import gtsam

    graph, initial = gtsam.readG2o(path, is3d)
    initial = chain_odometry(gtsam, graph, initial, is3d)
    first = min(initial.keys())
    with_prior = gtsam.NonlinearFactorGraph(graph)
    if is3d:
        noise = gtsam.noiseModel.Diagonal.Sigmas([1e-6] * 6)
        with_prior.add(gtsam.PriorFactorPose3(first, initial.atPose3(first), noise))
    else:
        noise = gtsam.noiseModel.Diagonal.Sigmas([1e-6] * 3)
        with_prior.add(gtsam.PriorFactorPose2(first, initial.atPose2(first), noise))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(100)
    t0 = time.perf_counter()
    if mode == "chordal":
        start = gtsam.InitializePose3.initialize(with_prior) if is3d else gtsam.lago.initialize(with_prior)
    else:
        start = initial
    optimizer = gtsam.LevenbergMarquardtOptimizer(with_prior, start, params)
    result = optimizer.optimize()
    elapsed = time.perf_counter() - t0
    write_full_precision(path, result, is3d, out_g2o)
    print(json.dumps({"time_s": elapsed, "iterations": optimizer.iterations(), "gtsam_chi2": 2.0 * graph.error(result)}))


def write_full_precision(source, values, is3d, out_g2o):
    """The source file's edges with GTSAM's estimate as vertices, at full precision
    (gtsam.writeG2o rounds, which changes the cost at the 1e-3 level)."""
    with open(source) as f, open(out_g2o, "w") as out:
        for key in sorted(values.keys()):
            if is3d:
                p = values.atPose3(key)
                t, q = p.translation(), p.rotation().toQuaternion()
                out.write(f"VERTEX_SE3:QUAT {key} {float(t[0])!r} {float(t[1])!r} {float(t[2])!r} {q.x()!r} {q.y()!r} {q.z()!r} {q.w()!r}\n")
            else:
                p = values.atPose2(key)
                out.write(f"VERTEX_SE2 {key} {p.x()!r} {p.y()!r} {p.theta()!r}\n")
        for line in f:
            if line.startswith("EDGE"):
                out.write(line)


def synthetic_grid(n, path, seed=1):
    """A 3-D grid world like smallGrid3D, n poses: a serpentine walk through a cube of side
    ceil(n^(1/3)), odometry plus loop closures to the pose one layer below. Noise:
    sigma_t = 0.1 m, sigma_R = 0.01 rad; the file's poses are odometry-chained (drifting)."""
    import math
    import random
    import numpy as np

    rng = random.Random(seed)
    side = math.ceil(n ** (1.0 / 3.0))
    cells = []
    for z in range(side):
        for y in range(side):
            row = [(x, y if z % 2 == 0 else side - 1 - y, z) for x in range(side)]
            cells.extend(row if y % 2 == 0 else row[::-1])
    cells = cells[:n]
    index = {c: i for i, c in enumerate(cells)}

    def rot(axis_angle):
        th = np.linalg.norm(axis_angle)
        if th < 1e-12:
            return np.eye(3)
        k = axis_angle / th
        kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        return np.eye(3) + math.sin(th) * kx + (1 - math.cos(th)) * kx @ kx

    truth = [(np.eye(3), np.array(c, dtype=float)) for c in cells]

    def noisy_between(i, j):
        (ri, ti), (rj, tj) = truth[i], truth[j]
        r = ri.T @ rj @ rot(np.array([rng.gauss(0, 0.01) for _ in range(3)]))
        t = ri.T @ (tj - ti) + np.array([rng.gauss(0, 0.1) for _ in range(3)])
        return r, t

    def quat(r):
        w = math.sqrt(max(0.0, 1 + r[0, 0] + r[1, 1] + r[2, 2])) / 2
        return ((r[2, 1] - r[1, 2]) / (4 * w), (r[0, 2] - r[2, 0]) / (4 * w), (r[1, 0] - r[0, 1]) / (4 * w), w)

    info = "100 0 0 0 0 0 100 0 0 0 0 100 0 0 0 10000 0 0 10000 0 10000"
    edges = [(i, i + 1, noisy_between(i, i + 1)) for i in range(n - 1)]
    for i, (x, y, z) in enumerate(cells):
        j = index.get((x, y, z - 1))
        if j is not None and abs(i - j) > 1:
            edges.append((j, i, noisy_between(j, i)))
    with open(path, "w") as f:
        pose_r, pose_t = np.eye(3), np.zeros(3)
        f.write("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n")
        num = lambda *vs: " ".join(repr(float(v)) for v in vs)
        for i, j, (r, t) in edges[: n - 1]:
            pose_t, pose_r = pose_t + pose_r @ t, pose_r @ r
            q = quat(pose_r)
            f.write(f"VERTEX_SE3:QUAT {j} {num(*pose_t, *q)}\n")
        for i, j, (r, t) in edges:
            q = quat(r)
            f.write(f"EDGE_SE3:QUAT {i} {j} {num(*t, *q)} {info}\n")
    return len(edges)


def doorslam_chi2(doorslam, g2o, extra):
    out = subprocess.run([doorslam, "pgo", g2o, "--init", "file", "--max-iterations", "0", "--json", *extra],
                         check=True, capture_output=True, text=True).stdout
    return json.loads(out)["initial_chi2"]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--doorslam", required=True)
    ap.add_argument("--data", required=True)
    ap.add_argument("--acceptance", default="../shared/acceptance",
                    help="the held-out data set (cubicle lives there)")
    ap.add_argument("--gtsam-child", nargs=4, metavar=("PATH", "IS3D", "MODE", "OUT"))
    ap.add_argument("--only", help="comma-separated names")
    ap.add_argument("--grid", type=int, nargs="*", default=[],
                    help="also run synthetic 3-D grids with these numbers of poses (scaling)")
    args = ap.parse_args()
    if args.gtsam_child:
        path, is3d, mode, out = args.gtsam_child
        gtsam_child(path, is3d == "1", mode, out)
        return
    tmpdir = tempfile.mkdtemp(prefix="doorslam-bench-")
    rows = []
    roots = {"data": args.data, "acceptance": args.acceptance}
    # --only matches the first word of a name ("cubicle" for "cubicle (nearest-pd)").
    files = [(name, os.path.join(roots[root], "pose_graphs", rel), is3d, extra) for name, root, rel, is3d, extra in FILES
             if not args.only or name.split()[0] in args.only.split(",")]
    for n in args.grid:
        path = os.path.join(tmpdir, f"grid{n}.g2o")
        synthetic_grid(n, path)
        files.append((f"grid{n // 1000}k (synthetic)", path, True, []))
    for name, path, is3d, extra in files:
        if not os.path.exists(path):
            print(f"{name}: {path} not found, skipped", file=sys.stderr)
            continue
        row = {"name": name}
        for mode in ("file", "chordal"):
            out_g2o = os.path.join(tmpdir, f"{name.split()[0]}-{mode}.g2o")
            try:
                out, rss = run_measured([sys.executable, __file__, "--doorslam", args.doorslam, "--data", args.data,
                                         "--gtsam-child", path, "1" if is3d else "0", mode, out_g2o])
            except RuntimeError as e:
                # e.g. LAGO refuses non-diagonal information matrices (kitti_00).
                print(f"{name} gtsam {mode}: not available: {str(e).strip().splitlines()[-1]}", file=sys.stderr)
                row[mode] = None
                continue
            r = json.loads(out)
            try:
                r["chi2"] = doorslam_chi2(args.doorslam, out_g2o, extra)
            except subprocess.CalledProcessError:
                r["chi2"] = float("nan")  # GTSAM's result does not even parse (NaN poses)
            r["rss_mb"] = rss
            row[mode] = r
            print(f"{name} gtsam {mode}: {r}", file=sys.stderr)
        out, rss = run_measured([args.doorslam, "pgo", path, "--json", *extra])
        r = json.loads(out)
        r["rss_mb"] = rss
        row["ours"] = r
        row["poses"], row["edges"] = r["poses"], r["edges"]
        print(f"{name} doorslam: {r}", file=sys.stderr)
        rows.append(row)

    print("| file | poses | edges | GTSAM LM from file: chi2 / iters / s | GTSAM chordal+LM: chi2 / iters / s "
          "| doorslam: chi2 / iters / s | chi2 vs GTSAM best | speed-up vs best's time | peak RSS GTSAM / doorslam |")
    print("| --- | ---: | ---: | --- | --- | --- | ---: | ---: | --- |")
    for row in rows:
        candidates = [r for r in (row["file"], row["chordal"]) if r and r["chi2"] == r["chi2"]]
        best = min(candidates, key=lambda r: r["chi2"]) if candidates else None
        ours = row["ours"]
        rel = (ours["final_chi2"] - best["chi2"]) / best["chi2"] * 100.0 if best else float("nan")
        cell = lambda r: f"{r['chi2']:.6g} / {r['iterations']} / {r['time_s']:.3f}" if r else "n/a (LAGO: non-diagonal noise)"
        # A solve that did not converge says why (e.g. max_iterations, diverged).
        why = "" if ours.get("converged", True) else f" ({ours.get('stop_reason', 'not converged')})"
        print(f"| {row['name']} | {row['poses']} | {row['edges']} | {cell(row['file'])} | {cell(row['chordal'])} "
              f"| {ours['final_chi2']:.6g} / {ours['iterations']} / {ours['time_s']:.3f}{why} | {rel:+.4f} % "
              f"| {best['time_s'] / ours['time_s'] if best else float('nan'):.1f}x | {max(r['rss_mb'] for r in (row['file'], row['chordal']) if r):.0f} / "
              f"{ours['rss_mb']:.0f} MB |")


if __name__ == "__main__":
    main()
