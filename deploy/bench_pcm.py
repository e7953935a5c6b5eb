#!/usr/bin/env python3
"""`doorslam pcm` on the outlier benchmarks of ../shared/data/outliers: clique size against
the upstream expectation, precision and recall of the kept closures against the labels,
and time. Prints a Markdown table. Run through `deploy/bench-pcm`."""
import json
import os
import subprocess
import sys

SETS = [
    ("clean/example_2robots", 2, "== 10"),
    ("spoiled/example_2robots", 2, "<= 10"),
    ("spoiled_not_in_order/example_2robots", 2, "== 10"),
    ("spoiled/example_4robots", 4, "== 24"),
]


def labels(folder):
    truth, total = set(), 0
    for line in open(os.path.join(folder, "inter_robot_labels.txt")):
        if line.startswith("#") or not line.strip():
            continue
        f = line.split()
        total += 1
        if f[6] == "1":
            truth.add(frozenset([(f[2], int(f[3])), (f[4], int(f[5]))]))
    return truth, total


def label(key):
    return (chr(key >> 56), key & ((1 << 56) - 1))


def main():
    doorslam, data, threshold = sys.argv[1], sys.argv[2], sys.argv[3]
    print(f"| set | closures | consistent pairs | clique (expected) | precision | recall | exact | time |")
    print("| --- | ---: | ---: | --- | ---: | ---: | --- | ---: |")
    for rel, robots, expected in SETS:
        folder = os.path.join(data, "outliers/pcm_simulation", rel)
        files = [os.path.join(folder, f"{r}.g2o") for r in range(robots)]
        out = subprocess.run([doorslam, "pcm", *files, "--skip-unknown", "--threshold", threshold, "--json"],
                             check=True, capture_output=True, text=True).stdout
        r = json.loads(out)
        truth, total = labels(folder)
        kept = {frozenset([label(a), label(b)]) for a, b in r["inliers"]}
        tp = len(kept & truth)
        precision = tp / len(kept) if kept else 1.0
        recall = tp / len(truth) if truth else 1.0
        print(f"| {rel} | {r['closures']} | {r['consistent_pairs']} | {r['clique_size']} ({expected}) "
              f"| {precision:.3f} | {recall:.3f} | {r['exact']} | {r['time_s'] * 1e3:.2f} ms |")


if __name__ == "__main__":
    main()
