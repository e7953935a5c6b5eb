#!/usr/bin/env python3
"""Reads a run.mcap with decoders that are not doorslam's (the `mcap` reader and
`mcap-ros2-support`'s CDR decoder, which parses the file's own ros2msg schemas) and checks
it against the run folder it was made from:

- every robot's last /<robot>/team_path holds exactly its team_estimate.tum (stamps to the
  nanosecond, positions and quaternions as written), in frame "team";
- every robot's last /<robot>/odometry_path holds its odometry.tum;
- /<robot>/pose, /tf (team -> <robot>/odom) and /<robot>/loop_closures are there, schemas
  are ros2msg and payloads cdr;
- /team/bandwidth names every robot with a ledger.

    check_mcap.py RUN_MCAP RUN_DIR [--expect-closures ROBOT:KEPT:REJECTED ...]

Exit 0 and one "ok" line when all hold; else every failure on stderr and exit 1.
"""

import argparse
import sys
from collections import defaultdict
from pathlib import Path

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory


def read_tum(path):
    rows = []
    for line in path.read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        f = line.split()
        sec, _, frac = f[0].partition(".")
        ns = int(sec) * 10**9 + int((frac + "000000000")[:9])
        rows.append((ns, [float(x) for x in f[1:8]]))
    return rows


def path_rows(msg):
    return [
        (
            p.header.stamp.sec * 10**9 + p.header.stamp.nanosec,
            [
                p.pose.position.x,
                p.pose.position.y,
                p.pose.position.z,
                p.pose.orientation.x,
                p.pose.orientation.y,
                p.pose.orientation.z,
                p.pose.orientation.w,
            ],
        )
        for p in msg.poses
    ]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("mcap")
    ap.add_argument("run_dir")
    ap.add_argument("--expect-closures", nargs="*", default=[])
    a = ap.parse_args()
    run = Path(a.run_dir)
    robots = sorted(p.parent.name for p in run.glob("*/keyframes.csv"))
    errors = []
    last = {}
    counts = defaultdict(int)
    tf_children = set()
    with open(a.mcap, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, msg in reader.iter_decoded_messages():
            if schema.encoding != "ros2msg" or channel.message_encoding != "cdr":
                errors.append(f"{channel.topic}: {schema.encoding}/{channel.message_encoding}")
            counts[channel.topic] += 1
            last[channel.topic] = (schema.name, msg)
            if channel.topic == "/tf":
                for t in msg.transforms:
                    if t.header.frame_id != "team":
                        errors.append(f"/tf parent {t.header.frame_id!r}")
                    tf_children.add(t.child_frame_id)
    if not robots:
        errors.append(f"{run}: no robot folders")
    for r in robots:
        for topic, ty, file, frame in [
            (f"/{r}/team_path", "nav_msgs/msg/Path", "team_estimate.tum", "team"),
            (f"/{r}/odometry_path", "nav_msgs/msg/Path", "odometry.tum", f"{r}/odom"),
        ]:
            if topic not in last:
                errors.append(f"{topic}: no message")
                continue
            name, msg = last[topic]
            if name != ty:
                errors.append(f"{topic}: schema {name}")
            if msg.header.frame_id != frame:
                errors.append(f"{topic}: frame {msg.header.frame_id!r}, expected {frame!r}")
            want = read_tum(run / r / file)
            got = path_rows(msg)
            if got != want:
                errors.append(f"{topic}: last message differs from {r}/{file} ({len(got)} vs {len(want)} poses)")
        if f"/{r}/pose" not in last:
            errors.append(f"/{r}/pose: no message")
        if f"{r}/odom" not in tf_children:
            errors.append(f"/tf: no team -> {r}/odom")
        if f"/{r}/loop_closures" not in last:
            errors.append(f"/{r}/loop_closures: no message")
    for spec in a.expect_closures:
        r, kept, rejected = spec.split(":")
        _, msg = last.get(f"/{r}/loop_closures", (None, None))
        if msg is None:
            continue
        got = {m.ns: len(m.points) // 2 for m in msg.markers}
        if got != {"kept": int(kept), "rejected": int(rejected)}:
            errors.append(f"/{r}/loop_closures: {got}, expected kept {kept} rejected {rejected}")
    with_ledger = sorted(p.parent.name for p in run.glob("*/ledger.json"))
    if with_ledger:
        _, bw = last.get("/team/bandwidth", (None, None))
        names = sorted(s.hardware_id for s in bw.status) if bw else []
        if names != with_ledger:
            errors.append(f"/team/bandwidth: robots {names}, expected {with_ledger}")
    for e in errors:
        print(f"check_mcap: {e}", file=sys.stderr)
    if errors:
        return 1
    total = sum(counts.values())
    print(f"ok: {a.mcap}: {len(robots)} robots, {total} messages, final team_path = team_estimate.tum for each")
    return 0


if __name__ == "__main__":
    sys.exit(main())
