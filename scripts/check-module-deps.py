#!/usr/bin/python3
"""The worker's modules include only what they may: each pipeline/<module>/
file includes headers of its own module and of the modules its DEPS in
pipeline/CMakeLists.txt reach (aggscan_pipeline_module calls), and nothing
below the pipeline (common/, store/, config/, drivers/, daemon/) includes the
pipeline at all.
  check-module-deps.py [SOURCE_DIR]
Exit 1 naming each include that breaks the order, 0 when there is none."""

import os
import re
import sys

BELOW = ("common", "store", "config", "drivers", "daemon")


def modules(cmake_text):
    """{module: [direct deps]} from the aggscan_pipeline_module(...) calls."""
    mods = {}
    for m in re.finditer(r"aggscan_pipeline_module\((\w+)(.*?)\)", cmake_text, re.S):
        name, body = m.group(1), m.group(2)
        if name == "name":  # the function's own definition
            continue
        deps = re.search(r"\bDEPS\b(.*?)(?:\bLIBS\b|\bSOURCES\b|$)", body, re.S)
        mods[name] = deps.group(1).split() if deps else []
    return mods


def reach(mods, name, seen=None):
    seen = set() if seen is None else seen
    for d in mods.get(name, []):
        if d not in seen:
            seen.add(d)
            reach(mods, d, seen)
    return seen


def main():
    root = sys.argv[1] if len(sys.argv) > 1 else os.path.join(os.path.dirname(__file__), "..")
    mods = modules(open(os.path.join(root, "pipeline", "CMakeLists.txt")).read())
    if not mods:
        print("no aggscan_pipeline_module calls in pipeline/CMakeLists.txt")
        return 1
    for name, deps in mods.items():
        for d in deps:
            if d not in mods:
                print("pipeline/CMakeLists.txt: module %s depends on unknown module %s" % (name, d))
                return 1
        if name in reach(mods, name):
            print("pipeline/CMakeLists.txt: module %s depends on itself (a cycle)" % name)
            return 1
    include = re.compile(r'^\s*#\s*include\s+"pipeline/([^"/]+)(/[^"]*)?"', re.M)
    bad = []
    checked = 0
    for top in ("pipeline",) + BELOW:
        for dirpath, _, files in os.walk(os.path.join(root, top)):
            for f in files:
                if not f.endswith((".h", ".cpp")):
                    continue
                path = os.path.join(dirpath, f)
                rel = os.path.relpath(path, root)
                parts = rel.split(os.sep)
                text = open(path, encoding="utf-8", errors="replace").read()
                checked += 1
                for m in include.finditer(text):
                    target = m.group(1)
                    if top != "pipeline":
                        bad.append("%s includes pipeline/%s%s: %s/ is below the pipeline" %
                                   (rel, target, m.group(2) or "", top))
                        continue
                    if len(parts) < 3 or m.group(2) is None:
                        bad.append("%s includes pipeline/%s: headers live in pipeline/<module>/" %
                                   (rel, target))
                        continue
                    own = parts[1]
                    if own not in mods:
                        bad.append("%s: pipeline/%s/ is no module in pipeline/CMakeLists.txt" %
                                   (rel, own))
                        continue
                    if target != own and target not in reach(mods, own):
                        bad.append("%s includes pipeline/%s%s: module %s may use only %s" %
                                   (rel, target, m.group(2), own,
                                    ", ".join(sorted(reach(mods, own))) or "nothing else"))
    print("%d files checked against %d modules" % (checked, len(mods)))
    for b in bad:
        print("  " + b)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
