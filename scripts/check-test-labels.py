#!/usr/bin/python3
"""Every CTest test carries exactly one of the suite's labels, so that
`ctest -L unit` (the quick run) and the other lanes together run everything:
  check-test-labels.py BUILD_DIR
Exit 1 naming the tests without a label, with an unknown one or with two."""

import json
import subprocess
import sys

LABELS = {"unit", "scenario", "colmap", "vm", "browser"}


def main():
    if len(sys.argv) != 2:
        print(__doc__)
        return 2
    out = subprocess.run(["ctest", "--show-only=json-v1"], cwd=sys.argv[1], check=True,
                         capture_output=True, text=True).stdout
    tests = json.loads(out)["tests"]
    bad = []
    count = {k: 0 for k in LABELS}
    for t in tests:
        labels = []
        for p in t.get("properties", []):
            if p["name"] == "LABELS":
                labels = p["value"]
        known = [x for x in labels if x in LABELS]
        if len(known) != 1 or len(labels) != 1:
            bad.append("%s: %s" % (t["name"], labels or "no label"))
        else:
            count[known[0]] += 1
    print("tests by label: " + ", ".join("%s %d" % (k, count[k]) for k in sorted(count)))
    if bad:
        print("tests need exactly one label of %s (tests/CMakeLists.txt, aggscan_add_test "
              "LABEL, or set_tests_properties LABELS):" % sorted(LABELS))
        for b in bad:
            print("  " + b)
        return 1
    if not tests:
        print("no tests found in " + sys.argv[1])
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
