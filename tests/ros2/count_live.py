#!/usr/bin/env python3
"""Connects (eclipse-zenoh, no ROS) to live robots' ROS 2 endpoints and counts, for a while,
the liveliness tokens under `@ros2_lv/<domain>/**` and the samples per data key under
`<domain>/**`: a quick look at a running team (e.g. `doorslam demo --ros2`, whose live
line names the endpoints) from the machine a laptop's router would run on.

    count_live.py [--seconds 15] [--domain 0] EP [EP...]

Prints one JSON object: tokens, and samples per key (the type hash left out).
"""

import argparse
import json
import threading
import time

import zenoh


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("endpoints", nargs="+")
    ap.add_argument("--seconds", type=float, default=15.0)
    ap.add_argument("--domain", type=int, default=0)
    a = ap.parse_args()
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps(a.endpoints))
    conf.insert_json5("scouting/multicast/enabled", "false")
    lock = threading.Lock()
    counts, tokens = {}, set()

    def on_sample(s):
        with lock:
            k = str(s.key_expr).split("/RIHS01_")[0]
            counts[k] = counts.get(k, 0) + 1

    def on_token(s):
        with lock:
            tokens.add(str(s.key_expr))

    session = zenoh.open(conf)
    sub = session.declare_subscriber(f"{a.domain}/**", on_sample)
    live = session.liveliness().declare_subscriber(f"@ros2_lv/{a.domain}/**", on_token, history=True)
    time.sleep(a.seconds)
    with lock:
        out = {"seconds": a.seconds, "tokens": len(tokens), "samples": dict(sorted(counts.items()))}
    sub.undeclare()
    live.undeclare()
    session.close()
    print(json.dumps(out))
    return 0 if counts else 1


if __name__ == "__main__":
    raise SystemExit(main())
