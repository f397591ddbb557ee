#!/usr/bin/python3
"""Prepares a state directory with a batch of N reconstructed rocks for
timing `aggscan report --batch` (the QA report of a day's stones).

    bench/report_batch.py --from STATE_DIR --out BENCH_STATE_DIR [--rocks 40]

The rocks are the reconstructed samples of --from (e.g. the README demo's
state directory), each copied as often as needed under new ids with its
record, its morphology and its mesh; the copies are given lot "bench", a
specific gravity of 2.65 (bulk SSD) and half of them a reference volume, and
a batch "bench" of them is written. Then time, for instance:

    /usr/bin/time -v aggscan report --batch bench --state-dir BENCH_STATE_DIR \
        --spec en13383-lma5-40 --pdf /tmp/bench.pdf --html /tmp/bench.html
"""

import argparse
import json
import os
import shutil
import sys


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--from", dest="src", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--rocks", type=int, default=40)
    a = ap.parse_args()
    src = os.path.join(a.src, "samples")
    rocks = sorted(d for d in os.listdir(src)
                   if os.path.exists(os.path.join(src, d, "results", "morphology.json")))
    if not rocks:
        sys.exit(f"no reconstructed sample in {src}: run the README demo first")
    dst = os.path.join(a.out, "samples")
    shutil.rmtree(a.out, ignore_errors=True)
    os.makedirs(dst)
    ids = []
    for i in range(a.rocks):
        s = os.path.join(src, rocks[i % len(rocks)])
        sid = f"bench-{i + 1:03d}"
        d = os.path.join(dst, sid)
        os.makedirs(os.path.join(d, "results"))
        rec = json.load(open(os.path.join(s, "sample.json")))
        rec["id"] = sid
        rec["meta"] = {"lot": "bench", "operator": "bench",
                       "material": {"name": "granite", "specific_gravity": 2.65,
                                    "basis": "bulk-ssd"}}
        m = json.load(open(os.path.join(s, "results", "morphology.json")))
        m["sample_id"] = sid
        if i % 2 == 0:
            rec["meta"]["reference"] = {"volume_mm3": m["morphology_3d"]["volume_mm3"] * 1.01,
                                        "method": "water displacement"}
        json.dump(rec, open(os.path.join(d, "sample.json"), "w"))
        json.dump(m, open(os.path.join(d, "results", "morphology.json"), "w"))
        shutil.copy(os.path.join(s, "results", "mesh.ply"), os.path.join(d, "results"))
        ids.append(sid)
    os.makedirs(os.path.join(a.out, "batches"))
    json.dump({"name": "bench", "lot": "bench", "samples": []},
              open(os.path.join(a.out, "batches", "bench.json"), "w"))
    print(f"{len(ids)} rocks from {len(rocks)} reconstructed sample(s) in {a.out}")


if __name__ == "__main__":
    main()
