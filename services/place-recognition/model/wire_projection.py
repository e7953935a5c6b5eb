#!/usr/bin/env python3
"""Which 128-D wire form for the bag of words: the variants BENCHMARKS.md compares.

The bag-of-words vector (1,024 TF-IDF weights) must travel as 128 values. This script
fits candidate projections on the training towns' TF-IDF vectors and measures each on
held-out towns with the same precision-recall as `doorslam place eval` (checked: the
full-vector figures are identical):

  full               the 1,024-D TF-IDF vector (no wire form: the reference)
  pca w=P            128 principal components, whitened by sigma^-P, L2-normalized again
  pca w=P nonorm     the same, not normalized again (what `doorslam place vocabulary` fits, P = 0)
  random             a seeded Gaussian random projection (normalized again / not)
  ldp reg=R nonorm   a linear discriminant projection learned from pose-derived positives
                     of the training towns (difference vectors of inter-robot pairs within
                     2 m / 20 degrees whitened, then the leading directions of all
                     differences; R regularizes the whitening)

Float only (int8 costs under a point on top, BENCHMARKS.md). Usage, with the venv of
deploy/setup (numpy) and the cache build_model.py renders the training towns into:

  ~/.cache/doorslam/venv/bin/python services/place-recognition/model/wire_projection.py \\
      --doorslam target/release/doorslam --vocabulary "$DOORSLAM_BOW_VOCABULARY" \\
      --cache ~/.cache/doorslam/model-build --eval val201 --eval town1,town2
"""

import argparse
import subprocess
import tempfile
from pathlib import Path

import numpy as np

TRAIN_SEEDS = range(101, 107)  # build_model.py's TRAIN_TOWNS = 6
WIDEN_M, WIDEN_DEG = 2.0, 20.0  # eval.rs's SIM_WIDEN_M / SIM_WIDEN_DEG


def describe(doorslam, vocabulary, town, out):
    subprocess.run([doorslam, "place", "describe", str(town), "--method", "bow",
                    "--vocabulary", str(vocabulary), "--out", str(out), "--json"],
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    keys, rows = [], []
    for line in open(out):
        if line.startswith("#"):
            continue
        f = line.split()
        keys.append((f[0].split("/")[1], int(f[1])))
        rows.append(np.array(f[2:], dtype=np.float64))
    return keys, np.stack(rows)


def poses(town, robots):
    return {r: np.loadtxt(Path(town) / r / "poses.txt").reshape(-1, 3, 4) for r in robots}


def near(Ta, Tb, max_m=WIDEN_M, max_deg=WIDEN_DEG):
    d = np.linalg.norm(Ta[:, None, :, 3] - Tb[None, :, :, 3], axis=2)
    cos = (np.einsum("aij,bij->ab", Ta[:, :, :3], Tb[:, :, :3]) - 1) / 2
    return (d <= max_m) & (np.degrees(np.arccos(np.clip(cos, -1, 1))) <= max_deg)


def town_set(doorslam, vocabulary, town, tmp):
    """TF-IDF vectors, robot of each, and eval.rs's positives (closures.csv overlaps
    widened to the keyframes within 2 m / 20 degrees on each side)."""
    keys, X = describe(doorslam, vocabulary, town, Path(tmp) / (Path(town).name + ".txt"))
    rob = np.array([k[0] for k in keys])
    P = poses(town, sorted(set(rob)))
    T = np.stack([P[r][f] for r, f in keys])
    pos = np.zeros((len(keys), len(keys)), bool)
    for line in open(Path(town) / "closures.csv").read().splitlines()[1:]:
        ra, fa, rb, fb, kind = line.strip().split(",")
        if kind != "overlap":
            continue
        sa = np.where((rob == ra) & near(T, P[ra][int(fa)][None])[:, 0])[0]
        sb = np.where((rob == rb) & near(T, P[rb][int(fb)][None])[:, 0])[0]
        pos[np.ix_(sa, sb)] = True
        pos[np.ix_(sb, sa)] = True
    return X, rob, T, pos


def pooled(sets, names):
    """Several towns as one evaluation (eval.rs: robots named per folder, no positives
    across folders)."""
    X = np.concatenate([s[0] for s in sets])
    rob = np.concatenate([np.char.add(f"{n}/", s[1]) for n, s in zip(names, sets)])
    pos = np.zeros((len(X), len(X)), bool)
    o = 0
    for s in sets:
        n = len(s[0])
        pos[o:o + n, o:o + n] = s[3]
        o += n
    return X, rob, pos


def pr(Y, rob, pos):
    """eval.rs's pr_curve: each query's nearest other-robot keyframe, sorted by distance."""
    G = Y @ Y.T
    sq = np.diag(G)
    D = np.sqrt(np.maximum(sq[:, None] + sq[None] - 2 * G, 0))
    D[rob[:, None] == rob[None]] = np.inf
    nn = D.argmin(1)
    d = D[np.arange(len(Y)), nn]
    correct = pos[np.arange(len(Y)), nn]
    c = correct[np.argsort(d, kind="stable")]
    tp = np.cumsum(c)
    prec = tp / np.arange(1, len(c) + 1)
    rec = tp / pos.any(1).sum()
    auc = np.sum(prec * np.diff(np.concatenate([[0], rec])))
    p05 = prec[rec >= 0.5].max() if (rec >= 0.5).any() else 0.0
    return rec[-1], p05, auc


def normalize(Y):
    return Y / np.maximum(np.linalg.norm(Y, axis=1, keepdims=True), 1e-12)


def variants(X, pairs, d=128):
    """name -> function of the eval vectors."""
    mu = X.mean(0)
    C = np.cov((X - mu).T, bias=True)
    ev, U = np.linalg.eigh(C)
    o = np.argsort(ev)[::-1]
    ev, U = ev[o], U[:, o]
    print(f"the {d} leading components keep {ev[:d].sum() / ev.sum():.3f} of the variance")
    out = {"full": lambda V: V}
    for w in [0.0, 0.5, 1.0]:
        W = U[:, :d] / np.maximum(ev[:d], ev[0] * 1e-6) ** (w / 2)
        out[f"pca w={w}"] = lambda V, W=W: normalize((V - mu) @ W)
        out[f"pca w={w} nonorm"] = lambda V, W=W: (V - mu) @ W
    G = np.random.default_rng(1).standard_normal((X.shape[1], d)) / np.sqrt(d)
    out["random"] = lambda V: normalize(V @ G)
    out["random nonorm"] = lambda V: V @ G
    Dp = X[pairs[:, 0]] - X[pairs[:, 1]]
    Sp = Dp.T @ Dp / len(Dp)
    for reg in [0.1, 0.01]:
        e1, U1 = np.linalg.eigh(Sp)
        Wp = U1 / np.sqrt(np.maximum(e1, 0) + reg * e1.max())
        e2, V2 = np.linalg.eigh(Wp.T @ (2 * C) @ Wp)
        W = Wp @ V2[:, np.argsort(e2)[::-1][:d]]
        out[f"ldp reg={reg} nonorm"] = lambda V, W=W: (V - mu) @ W
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--doorslam", required=True)
    ap.add_argument("--vocabulary", required=True, type=Path)
    ap.add_argument("--cache", required=True, type=Path,
                    help="build_model.py's cache (train-town-<seed>-3x100 folders)")
    ap.add_argument("--eval", action="append", required=True,
                    help="sim world folder(s), comma-separated to pool them; repeatable")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        Xs, pairs, off = [], [], 0
        for seed in TRAIN_SEEDS:
            X, rob, T, _ = town_set(args.doorslam, args.vocabulary,
                                    args.cache / f"train-town-{seed}-3x100", tmp)
            # Pose-derived positives: other robots' keyframes within 2 m / 20 degrees.
            p = np.argwhere(near(T, T) & (rob[:, None] != rob[None]))
            Xs.append(X)
            pairs.append(p + off)
            off += len(X)
        X, pairs = np.concatenate(Xs), np.concatenate(pairs)
        print(f"training: {len(X)} vectors of {X.shape[1]}, {len(pairs)} positive pairs")
        fitted = variants(X, pairs)
        for spec in args.eval:
            names = spec.split(",")
            V, rob, pos = pooled([town_set(args.doorslam, args.vocabulary, n, tmp)
                                  for n in names], names)
            print(f"== {spec}: {len(V)} keyframes")
            for name, f in fitted.items():
                r1, p05, auc = pr(f(V), rob, pos)
                print(f"{name:22s} recall@1 {r1:.3f}  precision@recall0.5 {p05:.3f}  AUC {auc:.3f}",
                      flush=True)


if __name__ == "__main__":
    main()
