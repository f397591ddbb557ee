#!/usr/bin/env python3
"""Lists the tests a CTest run skipped, each with its reason, from the JUnit
file `ctest --output-junit FILE` wrote:

    scripts/skipped-tests.py build/ctest-junit.xml

The reason is what the test said: GoogleTest's skip message (the lines after
"file:line: Skipped"), else the last line of its output that says SKIP (the
exit-77 programs and scripts print one), else CTest's own note. Exit status 0
(also when nothing was skipped); 2 when the file cannot be read.
"""
import sys
import xml.etree.ElementTree as ET


def reason(out, fallback):
    lines = [l.rstrip() for l in out.splitlines()]
    for i, line in enumerate(lines):
        if line.endswith(": Skipped"):
            msg = []
            for nxt in lines[i + 1:]:
                if not nxt.strip() or nxt.startswith("["):
                    break
                msg.append(nxt.strip())
            if msg:
                return " ".join(msg)
    said = [l.strip() for l in lines if "SKIP" in l.upper() and not l.startswith("[  SKIPPED")]
    return said[-1] if said else fallback


def main():
    if len(sys.argv) != 2:
        print(__doc__.strip(), file=sys.stderr)
        return 2
    try:
        root = ET.parse(sys.argv[1]).getroot()
    except (OSError, ET.ParseError) as e:
        print(f"skipped-tests: cannot read {sys.argv[1]}: {e}", file=sys.stderr)
        return 2
    skipped = []
    for case in root.iter("testcase"):
        note = case.find("skipped")
        if note is None:
            continue
        out = case.findtext("system-out") or ""
        skipped.append((case.get("name", "?"), reason(out, note.get("message", "skipped"))))
    print(f"Skipped tests: {len(skipped)}")
    for name, why in skipped:
        print(f"  {name}: {why}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
