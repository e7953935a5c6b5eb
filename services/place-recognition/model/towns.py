"""Simulated towns (`doorslam sim world` outputs) as the model build and its measurements see
them: frames, ground-truth poses, labelled pairs, and the precision-recall of
`doorslam place eval` (the same ground truth and the same curve as `src/eval.rs`, so a
figure measured here is the figure the Rust side reports; checked in model/README.md).
"""

import collections
from pathlib import Path

import numpy as np

# eval.rs: SIM_WIDEN_M / SIM_WIDEN_DEG (an overlap pair widened to the keyframes near it)
WIDEN_M, WIDEN_DEG = 2.0, 20.0


class Town:
    """One `sim world` output: every frame of every robot (a keyframe each, as `place
    eval` with stride 1), poses as 3x4 camera-to-world matrices."""

    def __init__(self, path, label=None, stride=1):
        self.path = Path(path)
        self.label = label if label is not None else self.path.name
        self.robots = sorted(p.name for p in self.path.iterdir() if (p / "image_0").is_dir())
        self.frames, self.robot, self.index, poses = [], [], [], []
        for r in self.robots:
            rows = np.loadtxt(self.path / r / "poses.txt").reshape(-1, 3, 4)
            images = sorted((self.path / r / "image_0").glob("*.png"))
            if len(images) != len(rows):
                raise ValueError(f"{self.path / r}: {len(images)} images, {len(rows)} poses")
            keep = range(0, len(rows), stride)
            self.frames += [images[k] for k in keep]
            self.robot += [r] * len(keep)
            self.index += list(keep)
            poses.append(rows[::stride])
        self.poses = np.concatenate(poses)
        self.robot = np.array(self.robot)
        self.index = np.array(self.index)
        self.pairs = {"overlap": [], "aliased": []}
        for line in (self.path / "closures.csv").read_text().splitlines()[1:]:
            ra, fa, rb, fb, kind = line.strip().split(",")
            if int(fa) % stride or int(fb) % stride:
                continue  # a frame left out (the pair's neighbours stand for it)
            self.pairs[kind].append((self.position(ra, int(fa)), self.position(rb, int(fb))))
        world = (self.path / "world.txt").read_text()
        self.seed = int(next(l.split("=")[1] for l in world.splitlines() if l.startswith("seed")))

    def position(self, robot, frame):
        return int(np.flatnonzero((self.robot == robot) & (self.index == frame))[0])

    def __len__(self):
        return len(self.frames)

    def near(self, i, max_m, max_deg, robot=None):
        """Frames within `max_m` metres and `max_deg` degrees of frame i's pose."""
        d = np.linalg.norm(self.poses[:, :, 3] - self.poses[i, :, 3], axis=1)
        cos = (np.einsum("nij,ij->n", self.poses[:, :, :3], self.poses[i, :, :3]) - 1) / 2
        ok = (d <= max_m) & (np.degrees(np.arccos(np.clip(cos, -1, 1))) <= max_deg)
        if robot is not None:
            ok &= self.robot == robot
        return np.flatnonzero(ok)

    def widened(self, kind):
        """The `kind` pairs widened as eval.rs does: every keyframe of robot a near the
        pair's frame a with every keyframe of robot b near frame b (both orders)."""
        out = set()
        for a, b in self.pairs[kind]:
            xa = self.near(a, WIDEN_M, WIDEN_DEG, self.robot[a])
            xb = self.near(b, WIDEN_M, WIDEN_DEG, self.robot[b])
            out.update((int(i), int(j)) for i in xa for j in xb)
            out.update((int(j), int(i)) for i in xa for j in xb)
        return out


def pooled(towns):
    """Towns pooled as `place eval town1 town2` pools them: robot names `t/r`, positives
    per town (different towns share no place)."""
    robots, positives, offset = [], set(), 0
    for t, town in enumerate(towns):
        robots += [f"{t}/{r}" for r in town.robot]
        positives.update((i + offset, j + offset) for i, j in town.widened("overlap"))
        offset += len(town)
    return np.array(robots), positives


def nearest_other_robot(desc, robots, block=512):
    """Each query's nearest keyframe of another robot: (index, Euclidean distance)."""
    desc = desc.astype(np.float32)
    sq = (desc ** 2).sum(1)
    nn = np.zeros(len(desc), np.int64)
    dist = np.zeros(len(desc), np.float64)
    for s in range(0, len(desc), block):
        d2 = sq[s:s + block, None] + sq[None] - 2.0 * desc[s:s + block] @ desc.T
        d2[robots[s:s + block, None] == robots[None]] = np.inf
        nn[s:s + block] = d2.argmin(1)
        dist[s:s + block] = np.sqrt(np.maximum(d2[np.arange(len(d2)), nn[s:s + block]], 0))
    return nn, dist


def pr_curve(nn, dist, positives, n):
    """recall@1, precision at recall 0.5 and AUC exactly as eval.rs's `pr_curve`."""
    has = np.zeros(n, bool)
    for q, _ in positives:
        has[q] = True
    denom = max(int(has.sum()), 1)
    correct = np.array([(q, int(nn[q])) in positives for q in range(n)])
    order = np.argsort(dist, kind="stable")
    tp = np.cumsum(correct[order])
    recall = tp / denom
    precision = tp / np.arange(1, n + 1)
    auc = float(np.sum(precision * np.diff(np.concatenate([[0.0], recall]))))
    at_half = precision[recall >= 0.5]
    return {"recall_at_1": float(tp[-1] / denom),
            "precision_at_recall_0_5": float(at_half.max()) if len(at_half) else 0.0,
            "auc": auc, "queries_with_positive": int(has.sum())}


def quantize(desc):
    """The int8 wire form (doorslam_ipc::wire::Descriptor::quantize): scale = max|v| / 127,
    values rounded; returned dequantized (integer dot products give the same distances)."""
    scale = np.abs(desc).max(1, keepdims=True) / 127.0
    scale[scale == 0] = 1.0
    return np.round(desc / scale).clip(-127, 127) * scale


def evaluate(desc, towns, int8=True):
    robots, positives = pooled(towns)
    d = quantize(desc) if int8 else desc
    nn, dist = nearest_other_robot(d, robots)
    return pr_curve(nn, dist, positives, len(d))


def failure_kinds(desc, towns, int8=True):
    """What each failed query's nearest neighbour is: an aliased copy, another town, the
    same town elsewhere, or a near miss (within 15 m and 45 degrees, not a labelled pair)."""
    robots, positives = pooled(towns)
    aliased, offset, town_of, local = set(), 0, [], []
    for t, town in enumerate(towns):
        aliased.update((i + offset, j + offset) for i, j in town.widened("aliased"))
        town_of += [t] * len(town)
        local += list(range(len(town)))
        offset += len(town)
    d = quantize(desc) if int8 else desc
    nn, _ = nearest_other_robot(d, robots)
    has = collections.Counter(q for q, _ in positives)
    kinds = collections.Counter()
    for q in range(len(d)):
        if not has[q] or (q, int(nn[q])) in positives:
            continue
        m = int(nn[q])
        if (q, m) in aliased:
            kinds["aliased"] += 1
        elif town_of[q] != town_of[m]:
            kinds["other_town"] += 1
        else:
            town = towns[town_of[q]]
            if local[m] in town.near(local[q], 15.0, 45.0):
                kinds["near_miss"] += 1
            else:
                kinds["same_town_elsewhere"] += 1
    return dict(kinds)
