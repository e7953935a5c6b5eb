#!/usr/bin/env python3
"""`doorslam dpgo` and `doorslam pcm` on every team of BENCHMARKS.md's "Distributed pose-graph
optimization" section; prints its Markdown tables. Run through `deploy/bench-dpgo`.

    bench_dpgo.py DOORSLAM DATA ACCEPTANCE TABLE...

TABLE: teams (condensed and dgs per team), kinds (bytes per message kind, direct and over the
team link, with and without the standby copy), loss (drop 10 % / 30 %, a robot out of range),
pcm (plain PCM, PCM keeping singletons, 3-robot cycles), loop (PCM in the loop: bytes with
and without it, precision/recall), stream (keyframes arriving while the team runs: graph
updates vs whole graphs). Teams missing on disk are skipped with a note on stderr."""
import glob
import json
import os
import subprocess
import sys
import tempfile

SIM_SEEDS = (1, 2)
PCM_SEEDS = tuple(range(1, 11))


def run(doorslam, *args):
    # The tables before "link" were measured over the runner's own delivery (--link direct);
    # "link" compares it with the team link.
    if args[0] == "dpgo" and "--link" not in args and not LINK_TABLE[0]:
        args = (*args, "--link", "direct")
    out = subprocess.run([doorslam, *args, "--json"], check=True, capture_output=True, text=True)
    return json.loads(out.stdout)


def robot_files(folder):
    files = sorted(glob.glob(os.path.join(folder, "[0-9]*.g2o")),
                   key=lambda f: int(os.path.basename(f).split(".")[0]))
    return files


def teams(data, acceptance, tmp, doorslam):
    """(name, files, extra dpgo args, labels) of every team."""
    out = []
    dm = os.path.join(data, "multi_robot/distributed_mapper")
    for n in (2, 4, 9):
        out.append((f"example_{n}robots", robot_files(os.path.join(dm, f"example_{n}robots")), [], None))
    for seed in SIM_SEEDS:
        d = os.path.join(tmp, f"sim{seed}")
        subprocess.run([doorslam, "sim", "graph", "--robots", "5", "--poses", "300", "--outliers", "0",
                        "--seed", str(seed), "--out", d], check=True, capture_output=True)
        out.append((f"sim graph seed {seed}", [os.path.join(d, "graph.g2o")], [], None))
    for seed in SIM_SEEDS:
        d = os.path.join(tmp, f"simo{seed}")
        subprocess.run([doorslam, "sim", "graph", "--robots", "5", "--poses", "300", "--outliers", "0.3",
                        "--seed", str(seed), "--out", d], check=True, capture_output=True)
        out.append((f"sim graph seed {seed}, 30 % outliers, PCM", [os.path.join(d, "graph.g2o")],
                    ["--pcm", "0.99", "--labels", os.path.join(d, "labels.txt")], None))
    am = os.path.join(acceptance, "multi_robot/distributed_mapper")
    for n in (16, 25, 36, 49):
        out.append((f"acceptance example_{n}robots", robot_files(os.path.join(am, f"example_{n}robots")), [], None))
    kitti = robot_files(os.path.join(acceptance, "kitti00_5robots"))
    out.append(("acceptance kitti00_5robots", kitti, [], None))
    out.append(("kitti00_5robots, 30 % injected outliers, PCM", kitti,
                ["--inject-outliers", "0.3", "--pcm", "0.99"], None))
    return [t for t in out if t[1] or print(f"skipped {t[0]}: no files", file=sys.stderr)]


def fmt_gap(g):
    return f"{100 * g:.4f} %" if abs(g) < 0.01 else f"{100 * g:.3g} %"


def table_teams(doorslam, all_teams):
    print("| team | robots / poses | method | converged, rounds | χ² gap | ATE to centralized (m) "
          "| messages | bytes | centralized: direct / relayed / as LoopClosures | ratio (direct) | ratio (relayed) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name, files, extra, _ in all_teams:
        methods = ["condensed"] if "--pcm" in extra or "36" in name or "49" in name else ["condensed", "dgs"]
        for m in methods:
            r = run(doorslam, "dpgo", *files, *extra, "--method", m)
            who = f"{name} | {r['robots']} / {r['poses']}" if m == "condensed" else " | "
            print(f"| {who} | {m} | {'yes' if r['converged'] else 'no'}, {r['iterations']} "
                  f"| {fmt_gap(r['chi2_gap'])} | {r['ate_to_centralized']:.4f} | {r['messages']:,} | {r['bytes']:,} "
                  f"| {r['bytes_centralized']:,} / {r['bytes_centralized_relayed']:,} / {r['bytes_centralized_loop_closures']:,} "
                  f"| {r['bytes_ratio']:.3f} | {r['bytes'] / max(1, r['bytes_centralized_relayed']):.3f} |")


def table_loss(doorslam, all_teams):
    cases = [("clean", []), ("drop 10 %", ["--drop", "0.1"]), ("drop 30 %", ["--drop", "0.3"]),
             ("b out, rounds 2-22", ["--outage", "b@2..22"]),
             ("a (solver) out, rounds 2-22", ["--outage", "a@2..22"])]
    print("| team | " + " | ".join(c for c, _ in cases) + " |")
    print("|---|" + "---|" * len(cases))
    for name, files, extra, _ in all_teams:
        cells = []
        for _, args in cases:
            r = run(doorslam, "dpgo", *files, *extra, *args)
            cells.append(f"{'' if r['converged'] else 'NOT converged, '}{r['iterations']} rounds, "
                         f"{fmt_gap(r['chi2_gap'])}, {r['bytes']:,} B")
        print(f"| {name} | " + " | ".join(cells) + " |")


def table_pcm(doorslam, data, acceptance, tmp):
    variants = [("plain (min clique 2)", ["--no-cycles"]), ("singletons kept (min clique 1)",
                ["--no-cycles", "--min-clique", "1"]), ("3-robot cycles (default)", [])]
    print("| team | closures | " + " | ".join(f"{v}: P / R" for v, _ in variants) + " |")
    print("|---|---|" + "---|" * len(variants))
    sets = []
    for seed in PCM_SEEDS:
        d = os.path.join(tmp, f"pcm{seed}")
        subprocess.run([doorslam, "sim", "graph", "--robots", "5", "--outliers", "0.3", "--seed", str(seed),
                        "--out", d], check=True, capture_output=True)
        sets.append((f"sim graph 5 robots, 30 % outliers, seed {seed}", [os.path.join(d, "graph.g2o")],
                     os.path.join(d, "labels.txt")))
    for base, rel in [(data, "pcm_simulation/spoiled/example_4robots"),
                      (acceptance, "pcm_simulation/spoiled/example_8robots"),
                      (acceptance, "pcm_simulation/spoiled/example_16robots")]:
        folder = os.path.join(base, "outliers", rel)
        if os.path.isdir(folder):
            sets.append((rel, robot_files(folder), os.path.join(folder, "inter_robot_labels.txt")))
    for name, files, labels in sets:
        cells = []
        closures = 0
        for _, args in variants:
            r = run(doorslam, "pcm", *files, "--skip-unknown", "--labels", labels, *args)
            closures = r["closures"]
            cells.append(f"{r['precision']:.3f} / {r['recall']:.3f}")
        print(f"| {name} | {closures} | " + " | ".join(cells) + " |")


def table_loop(doorslam, all_teams):
    print("| team | PCM in the loop | bytes | per kind | rejected (loop / oracle) | precision / recall |")
    print("|---|---|---|---|---|---|")
    picked = [t for t in all_teams if "kitti" in t[0] or "seed 1" in t[0]]
    for name, files, extra, _ in picked:
        base = [a for a in extra if a not in ("--pcm", "0.99")]
        for label, args in [("without", []), ("with (p = 0.99)", ["--pcm", "0.99"])]:
            r = run(doorslam, "dpgo", *files, *base, *args)
            pr = (f"{r['pcm_precision']:.3f} / {r['pcm_recall']:.3f}" if "pcm_precision" in r else "")
            kinds = ", ".join(f"{k} {v:,}" for k, v in sorted(r["bytes_by_kind"].items()))
            rej = f"{r['rejected_distributed']} / {r['rejected_centralized']}" if args else ""
            print(f"| {name} | {label} | {r['bytes']:,} | {kinds} | {rej} | {pr} |")


def table_stream(doorslam, all_teams):
    print("| team | keyframes per round | graph messages | separator_graph bytes (updates / whole graphs) | total bytes (updates / whole) | rounds | χ² gap |")
    print("|---|---|---|---|---|---|---|")
    picked = [t for t in all_teams if t[0] in ("example_9robots", "sim graph seed 1", "acceptance kitti00_5robots")]
    for name, files, extra, _ in picked:
        n = "20" if "kitti" in name else "5"
        u = run(doorslam, "dpgo", *files, *extra, "--stream", n)
        w = run(doorslam, "dpgo", *files, *extra, "--stream", n, "--whole-graphs")
        print(f"| {name} | {n} | {u['messages_by_kind'].get('separator_graph', 0)} "
              f"| {u['bytes_by_kind'].get('separator_graph', 0):,} / {w['bytes_by_kind'].get('separator_graph', 0):,} "
              f"| {u['bytes']:,} / {w['bytes']:,} | {u['iterations']} | {fmt_gap(u['chi2_gap'])} |")


LINK_TABLE = [False]


def table_link(doorslam, all_teams):
    """The team link robots run (PeerSession, its acknowledgements and resends in the bytes)
    against the runner's own delivery, clean and faulty, and the solver out mid-stream."""
    cases = [("direct (agents' own acks)", ["--link", "direct"]),
             ("session", []),
             ("session, drop 0.3 reorder 0.3 dup 0.1", ["--drop", "0.3", "--reorder", "0.3", "--duplicate", "0.1"]),
             ("session, --stream, a (solver) out rounds 10-40", ["--stream", "10", "--outage", "a@10..40"])]
    print("| team | " + " | ".join(c for c, _ in cases) + " |")
    print("|---|" + "---|" * len(cases))
    LINK_TABLE[0] = True
    picked = [t for t in all_teams if "outliers" not in t[0] and "36" not in t[0]]
    for name, files, extra, _ in picked:
        cells = []
        for _, args in cases:
            r = run(doorslam, "dpgo", *files, *extra, *args)
            cells.append(f"{'' if r['converged'] else 'NOT converged (' + r['stop_reason'] + '), '}{r['iterations']} rounds, "
                         f"{fmt_gap(r['chi2_gap'])}, {r['bytes']:,} B = {r['bytes_ratio']:.3f}x")
        print(f"| {name} | " + " | ".join(cells) + " |")


def table_kinds(doorslam, all_teams):
    """Where the bytes go: per message kind, over the runner's delivery (`--link direct`) and
    the team link (session), with and without the standby copy, against both centralized
    baselines."""
    kinds = ["separator_graph", "pose_estimates", "route", "ack", "hello"]
    print("| team | link | standby copy | " + " | ".join(kinds) + " | bytes | ratio (direct) | ratio (relayed) | converged (stop, every robot told) |")
    print("|---|---|---|" + "---|" * len(kinds) + "---|---|---|---|")
    LINK_TABLE[0] = True
    for name, files, extra, _ in all_teams:
        for link, largs in [("direct", ["--link", "direct"]), ("session", [])]:
            # The copy is on by default (`--no-standby-copy` turns it off).
            for copy, cargs in [("no", ["--no-standby-copy"]), ("yes", [])]:
                r = run(doorslam, "dpgo", *files, *extra, *largs, *cargs)
                told = set(r.get("stop_reasons", {}).values())
                cells = [f"{r['bytes_by_kind'].get(k, 0):,}" for k in kinds]
                print(f"| {name} | {link} | {copy} | " + " | ".join(cells) + f" | {r['bytes']:,} "
                      f"| {r['bytes_ratio']:.3f} | {r['bytes'] / max(1, r['bytes_centralized_relayed']):.3f} "
                      f"| {'yes' if r['converged'] else 'no'} ({r['stop_reason']}; {', '.join(sorted(told))}) |")
                sys.stdout.flush()
    LINK_TABLE[0] = False


def main():
    doorslam, data, acceptance, *tables = sys.argv[1:]
    with tempfile.TemporaryDirectory(prefix="doorslam-bench-dpgo-") as tmp:
        all_teams = teams(data, acceptance, tmp, doorslam)
        for t in tables or ["teams", "loss", "pcm", "loop", "stream", "link"]:
            print(f"\n### {t}\n")
            {"teams": lambda: table_teams(doorslam, all_teams),
             "loss": lambda: table_loss(doorslam, all_teams),
             "pcm": lambda: table_pcm(doorslam, data, acceptance, tmp),
             "loop": lambda: table_loop(doorslam, all_teams),
             "stream": lambda: table_stream(doorslam, all_teams),
             "link": lambda: table_link(doorslam, all_teams),
             "kinds": lambda: table_kinds(doorslam, all_teams)}[t]()
            sys.stdout.flush()


if __name__ == "__main__":
    main()
