"""The NetVLAD head trained for places: metric learning on frozen backbone features, numpy.

The backbone (EfficientNet-Lite0 cut after block `STAGE_END`, build_model.py) stays frozen;
its L2-normalized local features X [N locations, C] of every training image are computed
once. The head on top of them, with every parameter trained:

    a_k(x) = softmax_k(w_k . x + b_k)                           soft assignment (K clusters)
    V_k    = sum_n a_k(x_n) (x_n - c_k)                          residuals (c_k decoupled from w_k)
    v      = L2(flatten(L2_rows(V)))                             intra- then L2-normalization
    z      = L2((v - mu) P)                                      projection to the 128-D descriptor

initialized as the untrained model was (k-means centroids, w_k = 2 alpha c_k, b_k = -alpha
||c_k||^2, PCA-whitening), then trained with the NetVLAD paper's weakly supervised triplet
loss on squared distances,

    L(q) = sum_{n in hard negatives(q)} max(0, m + |z_q - z_p*|^2 - |z_q - z_n|^2),

p* the nearest of q's positives under the current descriptor, the negatives mined each
epoch among q's nearest non-matching frames (aliased copies of buildings, the hardest,
among them). Labels come from the training towns' ground-truth poses (`Labels`): a
positive is another view within `POS_M` metres and `POS_DEG` degrees (another robot's, or
the same robot's at least `MIN_GAP_FRAMES` frames later), a negative is farther than
`NEG_M` or turned by more than `NEG_DEG`; frames of other towns and the real KITTI frames
are negatives of every simulated frame. Gradients are written out by hand (`backward`);
Adam updates them. Every random choice comes from one seeded generator and the BLAS runs
on a fixed number of threads, so two runs give the same bytes.
"""

import numpy as np

# Labels (metres, degrees, frames).
POS_M, POS_DEG = 6.0, 30.0
NEG_M, NEG_DEG = 25.0, 100.0
MIN_GAP_FRAMES = 10
# Training.
MARGIN = 0.1
NEGATIVES = 10  # hardest negatives per query and epoch
EPOCHS = 8
BATCH = 16  # queries per step
LEARNING_RATE = 1e-3
EPS = 1e-12


def l2(x, axis):
    n = np.sqrt((x * x).sum(axis, keepdims=True))
    return x / np.maximum(n, EPS), np.maximum(n, EPS)


class Head:
    """The head's parameters (float32): W [K, C], b [K], c [K, C], mu [R KC], P [R KC, D],
    and its pooling regions [R, N] (0/1 weights over the N feature-map locations; one
    region of ones: plain NetVLAD). With several regions (the whole view and its left and
    right halves, say) each region's VLAD is normalized on its own and the R vectors are
    concatenated (divided by sqrt(R): unit norm again) before the projection, so the
    descriptor keeps which side of the street looks like what."""

    NAMES = ("W", "b", "c", "mu", "P")

    def __init__(self, W, b, c, mu, P, regions=None):
        self.W, self.b, self.c, self.mu, self.P = (
            None if a is None else np.asarray(a, np.float32) for a in (W, b, c, mu, P))
        self.regions = None if regions is None else np.asarray(regions, np.float32)

    def params(self):
        return {n: getattr(self, n) for n in self.NAMES}

    def region_weights(self, n):
        return np.ones((1, n), np.float32) if self.regions is None else self.regions

    def vlad(self, X, mask=None):
        """Forward to the normalized (region-)VLAD vector; returns (v, cache for backward).
        `mask` [B, N] (0/1) drops locations (augmentation: a crop of the feature map)."""
        s = X @ self.W.T + self.b  # [B, N, K]
        s -= s.max(-1, keepdims=True)
        e = np.exp(s)
        a = e / e.sum(-1, keepdims=True)
        am = a if mask is None else a * mask[:, :, None]
        regions = self.region_weights(X.shape[1])
        parts, per_region = [], []
        for w in regions:
            ar = am * w[None, :, None]
            m = ar.sum(1)  # [B, K]
            V = np.matmul(ar.transpose(0, 2, 1), X) - m[:, :, None] * self.c[None]  # [B, K, C]
            Vn, r = l2(V, 2)
            v, q = l2(Vn.reshape(len(X), -1), 1)
            parts.append(v)
            per_region.append((m, Vn, r, v, q))
        v = np.concatenate(parts, 1) / np.float32(np.sqrt(len(regions)))
        return v, (X, a, mask, per_region, v)

    def forward(self, X, mask=None):
        v, cache = self.vlad(X, mask)
        if self.P is None:  # training on the VLAD vector itself (projection fitted later)
            return v, cache + (v, np.ones((len(v), 1), np.float32))
        y = (v - self.mu) @ self.P
        z, t = l2(y, 1)
        return z, cache + (z, t)

    def backward(self, dz, cache, train_projection=True):
        """Gradients of the parameters from dL/dz (the chain rule through `forward`)."""
        X, a, mask, per_region, v, z, t = cache
        B, _, C = X.shape
        K = self.W.shape[0]
        grads = {}
        if self.P is None:
            dv = dz
        else:
            dy = (dz - z * (z * dz).sum(1, keepdims=True)) / t
            if train_projection:
                grads["P"] = (v - self.mu).T @ dy
            dv = dy @ self.P.T
        regions = self.region_weights(X.shape[1])
        dv = dv / np.float32(np.sqrt(len(regions)))
        dc = np.zeros_like(self.c)
        da = np.zeros_like(a)
        for i, (w, (m, Vn, r, vr, q)) in enumerate(zip(regions, per_region)):
            dvr = dv[:, i * K * C:(i + 1) * K * C]
            du = (dvr - vr * (vr * dvr).sum(1, keepdims=True)) / q
            dVn = du.reshape(B, K, C)
            dV = (dVn - Vn * (Vn * dVn).sum(2, keepdims=True)) / r
            dc -= (m[:, :, None] * dV).sum(0)
            dar = np.matmul(X, dV.transpose(0, 2, 1)) - (dV * self.c[None]).sum(2)[:, None, :]
            da += dar * w[None, :, None]
        grads["c"] = dc
        if mask is not None:
            da = da * mask[:, :, None]
        ds = a * (da - (a * da).sum(-1, keepdims=True))
        grads["W"] = np.einsum("bnk,bnc->kc", ds, X, optimize=True)
        grads["b"] = ds.sum((0, 1))
        return grads

    def describe(self, X, batch=256):
        return np.concatenate([self.forward(X[i:i + batch])[0] for i in range(0, len(X), batch)])

    def vlads(self, X, batch=256):
        return np.concatenate([self.vlad(X[i:i + batch])[0] for i in range(0, len(X), batch)])


def split_regions(grid, kind):
    """Pooling regions over an h x w feature map: `whole`, or `halves` (the whole view, its
    left half and its right half), or `thirds` (whole, left, middle, right)."""
    h, w = grid
    cols = np.tile(np.arange(w), h)
    if kind == "whole":
        return np.ones((1, h * w), np.float32)
    if kind == "halves":
        return np.stack([np.ones(h * w), cols < w / 2, cols >= w / 2]).astype(np.float32)
    if kind == "thirds":
        return np.stack([np.ones(h * w), cols < w / 3, (cols >= w / 3) & (cols < 2 * w / 3),
                         cols >= 2 * w / 3]).astype(np.float32)
    raise ValueError(kind)


def kmeans(x, k, rng, iters):
    """Lloyd's k-means, k-means++ seeding from `rng`; float64 for reproducible sums."""
    centers = [x[rng.integers(len(x))]]
    d2 = ((x - centers[0]) ** 2).sum(1)
    for _ in range(1, k):
        centers.append(x[rng.choice(len(x), p=d2 / d2.sum())])
        d2 = np.minimum(d2, ((x - centers[-1]) ** 2).sum(1))
    c = np.array(centers)
    for _ in range(iters):
        label = np.argmin((c ** 2).sum(1)[None] - 2.0 * x @ c.T, axis=1)
        for j in range(k):
            members = x[label == j]
            if len(members):
                c[j] = members.mean(0)
    return c


def initial_assignment(X, k, rng, per_image, iters):
    """The untrained head's clusters: k-means on `per_image` random local features of each
    image, centroids normalized, alpha such that the nearest centroid outweighs the second
    by 100x on average (the NetVLAD reference code). Returns (W, b, c, alpha)."""
    samples = np.concatenate([f[rng.choice(len(f), min(per_image, len(f)), replace=False)]
                              for f in X]).astype(np.float64)
    c = kmeans(samples, k, rng, iters)
    c /= np.linalg.norm(c, axis=1, keepdims=True)
    d = (samples ** 2).sum(1)[:, None] + (c ** 2).sum(1)[None] - 2.0 * samples @ c.T
    d = np.sort(d, axis=1)
    alpha = float(-np.log(0.01) / np.mean(d[:, 1] - d[:, 0]))
    return 2.0 * alpha * c, -alpha * (c ** 2).sum(1), c, alpha


def whitening(v, dim, power=1.0, rng=None, max_samples=3000):
    """PCA(-whitening) of row vectors v to `dim`: (mean, projection [D_in, dim]); principal
    direction i divided by sigma_i^power; eigenvector signs fixed (largest entry positive).
    At most `max_samples` rows (a seeded subset) go into the decomposition: its cost grows
    with the square of the rows, and 3,000 of them pin 128 directions of the VLAD space."""
    if rng is not None and len(v) > max_samples:
        v = v[np.sort(rng.choice(len(v), max_samples, replace=False))]
    v = v.astype(np.float64)
    mean = v.mean(0)
    # The principal directions from the n x n Gram matrix (n rows << D_in columns): the same
    # right singular vectors as the SVD of the centred rows, a quarter of its cost.
    centred = v - mean
    lam, u = np.linalg.eigh(centred @ centred.T)
    top = np.argsort(lam)[::-1][:dim]
    s = np.sqrt(np.maximum(lam[top], 0.0))
    vt = (u[:, top].T @ centred) / np.maximum(s, EPS)[:, None]
    vt *= np.sign(vt[np.arange(dim), np.abs(vt).argmax(1)])[:, None]
    return mean, vt.T / ((s[:dim] / np.sqrt(len(v) - 1)) ** power + 1e-9)


class Labels:
    """Positives and negatives of the training images from ground truth.

    `towns`: list of towns.Town (simulated, poses known), `extra`: count of images after
    them without places (real frames: negatives of everything, no positives)."""

    def __init__(self, towns, extra=0):
        self.n = sum(len(t) for t in towns) + extra
        self.town = np.full(self.n, -1)
        self.positives = [np.zeros(0, np.int64)] * self.n
        self.cross = [np.zeros(0, np.int64)] * self.n  # positives of other robots
        self.ignore = [np.zeros(0, np.int64)] * self.n  # neither positive nor negative
        offset = 0
        for ti, t in enumerate(towns):
            self.town[offset:offset + len(t)] = ti
            centre = t.poses[:, :, 3]
            axis = t.poses[:, :, 2]  # optical axis in the world
            for i in range(len(t)):
                d = np.linalg.norm(centre - centre[i], axis=1)
                cos = np.clip(axis @ axis[i], -1, 1)
                angle = np.degrees(np.arccos(cos))
                other = (t.robot != t.robot[i]) | (np.abs(t.index - t.index[i]) >= MIN_GAP_FRAMES)
                pos = (d <= POS_M) & (angle <= POS_DEG) & other
                neg = (d > NEG_M) | (angle > NEG_DEG)
                self.positives[offset + i] = np.flatnonzero(pos) + offset
                self.cross[offset + i] = np.flatnonzero(pos & (t.robot != t.robot[i])) + offset
                self.ignore[offset + i] = np.flatnonzero(~pos & ~neg) + offset
            offset += len(t)

    def queries(self, cross_only=False):
        have = self.cross if cross_only else self.positives
        return np.array([i for i in range(self.n) if len(have[i])], np.int64)

    def negative_mask(self, i):
        """Boolean mask over all images: negatives of image i."""
        mask = np.ones(self.n, bool)
        mask[i] = False
        mask[self.positives[i]] = False
        mask[self.ignore[i]] = False
        return mask


class Adam:
    def __init__(self, params, lr, beta1=0.9, beta2=0.999, eps=1e-8):
        self.lr, self.b1, self.b2, self.eps, self.t = lr, beta1, beta2, eps, 0
        self.m = {k: np.zeros_like(v) for k, v in params.items()}
        self.v = {k: np.zeros_like(v) for k, v in params.items()}

    def step(self, head, grads):
        self.t += 1
        for k, g in grads.items():
            self.m[k] = self.b1 * self.m[k] + (1 - self.b1) * g
            self.v[k] = self.b2 * self.v[k] + (1 - self.b2) * g * g
            mh = self.m[k] / (1 - self.b1 ** self.t)
            vh = self.v[k] / (1 - self.b2 ** self.t)
            setattr(head, k, (getattr(head, k) - self.lr * mh / (np.sqrt(vh) + self.eps)).astype(np.float32))


def mine(z, labels, queries, negatives, margin, rng, positive="nearest"):
    """Per query: a positive (its nearest, hardest or a random one, of other robots when it
    has some) and its hardest negatives that violate the margin."""
    triplets = []
    for q in queries:
        d2 = 2.0 - 2.0 * (z @ z[q])
        pos = labels.cross[q] if len(labels.cross[q]) else labels.positives[q]
        if positive == "nearest":
            p = int(pos[np.argmin(d2[pos])])
        elif positive == "hardest":
            p = int(pos[np.argmax(d2[pos])])
        else:
            p = int(pos[rng.integers(len(pos))])
        mask = labels.negative_mask(q)
        cand = np.flatnonzero(mask & (d2 < d2[p] + margin))
        if len(cand) == 0:
            continue
        hard = cand[np.argsort(d2[cand], kind="stable")[:negatives]]
        triplets.append((int(q), p, hard))
    return triplets


def crops(n, grid, rng, keep):
    """Masks [n, h*w] of random crops keeping at least `keep` of each side of the grid: a
    view shifted or turned a little (NetVLAD pools without order, so a crop is a subset)."""
    h, w = grid
    out = np.zeros((n, h, w), np.float32)
    for i in range(n):
        ch, cw = rng.integers(int(keep * h), h + 1), rng.integers(int(keep * w), w + 1)
        y, x = rng.integers(h - ch + 1), rng.integers(w - cw + 1)
        out[i, y:y + ch, x:x + cw] = 1.0
    return out.reshape(n, -1)


def triplet_step(head, X, batch, margin, train_projection, mask=None):
    """Loss and gradients of one batch of (query, positive, negatives) triplets."""
    images = sorted({i for q, p, ns in batch for i in (q, p, *ns)})
    where = {i: k for k, i in enumerate(images)}
    z, cache = head.forward(X[images], None if mask is None else mask(len(images)))
    dz = np.zeros_like(z)
    loss = 0.0
    for q, p, ns in batch:
        zq, zp = z[where[q]], z[where[p]]
        dp = ((zq - zp) ** 2).sum()
        for n in ns:
            zn = z[where[n]]
            h = margin + dp - ((zq - zn) ** 2).sum()
            if h <= 0:
                continue
            loss += h
            # d/dz of |zq - zp|^2 - |zq - zn|^2
            dz[where[q]] += 2 * (zq - zp) - 2 * (zq - zn)
            dz[where[p]] += -2 * (zq - zp)
            dz[where[n]] += 2 * (zq - zn)
    return loss, head.backward(dz / len(batch), cache, train_projection)


def train(head, X, labels, rng, epochs=EPOCHS, lr=LEARNING_RATE, margin=MARGIN,
          negatives=NEGATIVES, batch=BATCH, train_projection=True, log=print, on_epoch=None,
          positive="nearest", cross_only=False, grid=None, keep=None):
    """Trains `head` in place; each epoch mines triplets with the current descriptor."""
    params = {k: v for k, v in head.params().items() if v is not None}
    if not train_projection:
        params = {k: v for k, v in params.items() if k != "P"}
    params.pop("mu", None)
    opt = Adam(params, lr)
    queries = labels.queries(cross_only)
    mask = None if keep is None else (lambda n: crops(n, grid, rng, keep))
    for epoch in range(epochs):
        z = head.describe(X)
        triplets = mine(z, labels, queries, negatives, margin, rng, positive)
        order = rng.permutation(len(triplets))
        total = 0.0
        for s in range(0, len(order), batch):
            loss, grads = triplet_step(head, X, [triplets[i] for i in order[s:s + batch]],
                                       margin, train_projection, mask)
            grads.pop("mu", None)
            opt.step(head, grads)
            total += loss
        log(f"epoch {epoch + 1}/{epochs}: {len(triplets)} queries with a violating negative, "
            f"mean loss {total / max(len(triplets), 1):.4f}")
        if on_epoch:
            on_epoch(epoch, head)
    return head
