#!/usr/bin/env python3
"""Subscribes, with eclipse-zenoh, to what `doorslam ros2 replay` or a live robot's
`doorslam service ros2` publishes and checks it against rmw_zenoh's documented wire
format (docs/design.md), decoding the payloads with rosbags' CDR decoder (not doorslam's):

- node tokens `@ros2_lv/<domain>/<zid>/<id>/<id>/NN/%/%<robot>/doorslam`;
- publisher tokens `@ros2_lv/<domain>/<zid>/<node>/<entity>/MP/%/%<robot>/doorslam/
  <mangled topic>/<pkg::msg::dds_::Name_>/<RIHS01 hash as rosbags computes it>/<qos>`;
- every sample on `<domain>/<topic>/<dds type>/<hash>` of a declared publisher, with a
  33-byte attachment: sequence number i64 LE (1, 2, ... per publisher), source timestamp
  i64 LE (ns since the epoch, within a minute of now), GID length 16, GID = XXH3-128 of
  the publisher's token;
- every payload decodes as its type, in the frames doorslam documents (paths and poses in
  `team`, the odometry path in `<robot>/odom`, /tf `team` -> `<robot>/odom`); the last
  /<robot>/team_path equals the run folder's team_estimate.tum.

    check_live.py --listen EP --run-dir DIR --expect N [--domain 0] [--timeout-s 30]
    check_live.py --listen EP --run-dir STATE_DIR --live [--min-per-topic 2] [--timeout-s 50]

The first form (a replay) waits for exactly N samples, every publisher's sequence from 1.
`--live` (a running robot, STATE_DIR its `[backend] state_dir`) collects until a line on
stdin (the caller has seen the state settle), then also wants every robot's five topics
at least `--min-per-topic` times, consecutive sequence numbers from wherever it joined, and
the last /<robot>/pose equal to the last team path's last pose.

Prints "ready" once its subscribers are declared, "ok: ..." at the end; failures on
stderr, exit 1.
"""

import argparse
import json
import re
import sys
import threading
import time
from pathlib import Path

import xxhash
import zenoh
from rosbags.typesys import Stores, get_typestore

TS = get_typestore(Stores.ROS2_JAZZY)


def dds_to_ros(dds):
    pkg, kind, _, name = dds.split("::")
    return f"{pkg}/{kind}/{name[:-1]}"


def read_tum(path):
    rows = []
    for line in path.read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            f = line.split()
            sec, _, frac = f[0].partition(".")
            rows.append((int(sec) * 10**9 + int((frac + "000000000")[:9]), [float(x) for x in f[1:8]]))
    return rows


def pose_row(p):
    """A PoseStamped as (stamp ns, frame, x y z qx qy qz qw)."""
    o, q = p.pose.position, p.pose.orientation
    return (p.header.stamp.sec * 10**9 + p.header.stamp.nanosec, p.header.frame_id,
            [o.x, o.y, o.z, q.x, q.y, q.z, q.w])


def frame_errors(key, ros_type, robot, msg):
    """The frames doorslam documents for each topic."""
    odom = f"{robot}/odom"
    if ros_type == "nav_msgs/msg/Path":
        want = odom if "/odometry_path/" in key else "team"
        frames = {msg.header.frame_id} | {p.header.frame_id for p in msg.poses}
        return [] if frames == {want} else [f"{key}: frames {sorted(frames)}, expected {want}"]
    if ros_type == "geometry_msgs/msg/PoseStamped":
        return [] if msg.header.frame_id == "team" else [f"{key}: frame {msg.header.frame_id}"]
    if ros_type == "tf2_msgs/msg/TFMessage":
        pairs = [(t.header.frame_id, t.child_frame_id) for t in msg.transforms]
        return [] if pairs == [("team", odom)] else [f"{key}: transforms {pairs}, expected team -> {odom}"]
    return []


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--listen", required=True)
    ap.add_argument("--run-dir", required=True)
    ap.add_argument("--expect", type=int)
    ap.add_argument("--live", action="store_true")
    ap.add_argument("--min-per-topic", type=int, default=2)
    ap.add_argument("--domain", type=int, default=0)
    ap.add_argument("--timeout-s", type=float, default=30.0)
    a = ap.parse_args()
    if (a.expect is None) == (not a.live):
        ap.error("give --expect N (a replay) or --live (a running robot)")
    run = Path(a.run_dir)

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", json.dumps([a.listen]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    lock = threading.Lock()
    tokens = set()
    samples = []
    done = threading.Event()

    def on_token(sample):
        if sample.kind == zenoh.SampleKind.PUT:
            with lock:
                tokens.add(str(sample.key_expr))

    def on_sample(sample):
        att = sample.attachment.to_bytes() if sample.attachment is not None else None
        with lock:
            samples.append((str(sample.key_expr), sample.payload.to_bytes(), att, time.time_ns()))
            if a.expect is not None and len(samples) >= a.expect:
                done.set()

    session = zenoh.open(conf)
    live = session.liveliness().declare_subscriber(f"@ros2_lv/{a.domain}/**", on_token, history=True)
    sub = session.declare_subscriber(f"{a.domain}/**", on_sample)
    print("ready", flush=True)
    if a.live:
        # The caller says when the robot's state has settled (a line, or EOF).
        reader = threading.Thread(target=lambda: (sys.stdin.readline(), done.set()), daemon=True)
        reader.start()
    done.wait(a.timeout_s)
    time.sleep(0.2)
    with lock:
        tokens_now, got = set(tokens), list(samples)
    sub.undeclare()
    live.undeclare()
    session.close()

    # Read at the end: a live robot's back-end may write its folder after this started.
    robots = sorted(p.parent.name for p in run.glob("*/keyframes.csv"))
    errors = []
    d = a.domain
    node_re = re.compile(rf"^@ros2_lv/{d}/([0-9a-f]+)/(\d+)/\2/NN/%/%(\w+)/doorslam$")
    pub_re = re.compile(
        rf"^@ros2_lv/{d}/([0-9a-f]+)/(\d+)/(\d+)/MP/%/%(\w+)/doorslam/(%[\w%]+)/"
        r"(\w+::msg::dds_::\w+_)/(RIHS01_[0-9a-f]{64})/(:{2},\d*:,:,:,,)$"
    )
    node_robots = {}
    pubs = {}
    ids = set()
    for t in sorted(tokens_now):
        m = node_re.match(t)
        if m:
            node_robots[m.group(3)] = m.group(2)
            ids.add(int(m.group(2)))
    for t in sorted(tokens_now):
        if node_re.match(t):
            continue
        m = pub_re.match(t)
        if not m:
            errors.append(f"token not in rmw_zenoh's format: {t}")
            continue
        zid, node, entity, robot, topic, dds, hash_, qos = m.groups()
        ros_type = dds_to_ros(dds)
        if TS.hash_rihs01(ros_type) != hash_:
            errors.append(f"{t}: hash is not {ros_type}'s ({TS.hash_rihs01(ros_type)})")
        if node_robots.get(robot) not in (None, node):
            errors.append(f"{t}: node id {node}, the node token says {node_robots.get(robot)}")
        ids.add(int(entity))
        key = f"{d}/{topic.replace('%', '/')[1:]}/{dds}/{hash_}"
        gid = xxhash.xxh3_128(t.encode()).intdigest().to_bytes(16, "little")
        pubs.setdefault(key, []).append((gid, ros_type, robot))
    if sorted(node_robots) != robots:
        errors.append(f"node tokens for {sorted(node_robots)}, expected {robots}")
    if len(ids) != len(node_robots) + sum(len(v) for v in pubs.values()):
        errors.append("node and entity ids are not unique in the session")

    if a.expect is not None and len(got) != a.expect:
        errors.append(f"{len(got)} samples, expected {a.expect}")
    if a.live and not done.is_set():
        errors.append(f"no word from the caller within {a.timeout_s} s")
    seqs = {}
    per_topic = {}
    last_pose = {}
    last_team = {}
    decoded = 0
    for key, payload, att, t_rx in got:
        if key not in pubs:
            errors.append(f"sample on {key}: no publisher token names it")
            continue
        if att is None or len(att) != 33 or att[16] != 16:
            errors.append(f"{key}: attachment {att!r} is not seq(8) ts(8) len(1)=16 gid(16)")
            continue
        seq = int.from_bytes(att[0:8], "little", signed=True)
        ts = int.from_bytes(att[8:16], "little", signed=True)
        gid = att[17:]
        match = [p for p in pubs[key] if p[0] == gid]
        if not match:
            errors.append(f"{key}: GID {gid.hex()} is no publisher token's XXH3-128")
            continue
        _, ros_type, robot = match[0]
        # A replay's subscriber is there from the first sample; a live one joins a
        # running publisher, anywhere in its sequence.
        first = gid not in seqs
        want = seqs.get(gid, 0) + 1
        if seq != want and not (a.live and first and seq >= 1):
            errors.append(f"{key}: sequence {seq} after {seqs.get(gid, 0)}")
        seqs[gid] = seq
        # `<domain>/<ns>/<topic>/<type>/<hash>`, `/tf` without a namespace.
        topic = (robot, key.split("/")[-3])
        per_topic[topic] = per_topic.get(topic, 0) + 1
        if abs(ts - t_rx) > 60 * 10**9:
            errors.append(f"{key}: source timestamp {ts} is not now")
        try:
            msg = TS.deserialize_cdr(payload, ros_type)
            decoded += 1
        except Exception as e:  # noqa: BLE001 - report every undecodable payload
            errors.append(f"{key}: rosbags cannot decode it as {ros_type}: {e}")
            continue
        errors.extend(frame_errors(key, ros_type, robot, msg))
        if key.startswith(f"{d}/{robot}/team_path/"):
            last_team[robot] = msg
        if key.startswith(f"{d}/{robot}/pose/"):
            last_pose[robot] = msg
    for r in robots:
        msg = last_team.get(r)
        want = read_tum(run / r / "team_estimate.tum")
        rows = [] if msg is None else [
            (p.header.stamp.sec * 10**9 + p.header.stamp.nanosec,
             [p.pose.position.x, p.pose.position.y, p.pose.position.z,
              p.pose.orientation.x, p.pose.orientation.y, p.pose.orientation.z, p.pose.orientation.w])
            for p in msg.poses
        ]
        if rows != want:
            errors.append(f"/{r}/team_path: last sample differs from {r}/team_estimate.tum")
        if a.live:
            for topic in ("team_path", "odometry_path", "pose", "loop_closures", "tf"):
                n = per_topic.get((r, topic), 0)
                if n < a.min_per_topic:
                    errors.append(f"{r}: {n} samples on {topic}, expected at least {a.min_per_topic}")
            pose = last_pose.get(r)
            if msg is not None and msg.poses and (pose is None or pose_row(pose) != pose_row(msg.poses[-1])):
                errors.append(f"/{r}/pose: the last is not the last team path's last pose")
    for e in errors:
        print(f"check_live: {e}", file=sys.stderr)
    if errors:
        return 1
    print(f"ok: {len(tokens_now)} tokens, {len(got)} samples on {len(pubs)} keys, {decoded} decoded by rosbags")
    return 0


if __name__ == "__main__":
    sys.exit(main())
