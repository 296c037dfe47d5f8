#!/usr/bin/env python3
"""The end of `./paddock test`: the ten slowest tests and the counts, read from the JUnit
report the test runner (cargo-nextest) wrote with its own timings.

    scripts/slowest.py target/nextest/default/junit.xml [N]
"""

import sys
import xml.etree.ElementTree as ET


def main() -> int:
    if len(sys.argv) < 2:
        print(__doc__.strip(), file=sys.stderr)
        return 2
    path, n = sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 10
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as e:
        print(f"slowest: {path}: {e}", file=sys.stderr)
        return 1
    cases = []
    failed = skipped = 0
    for case in root.iter("testcase"):
        binary = case.get("classname", "")
        name = case.get("name", "")
        seconds = float(case.get("time", "0") or 0)
        if case.find("failure") is not None or case.find("error") is not None:
            failed += 1
        if case.find("skipped") is not None:
            skipped += 1
        cases.append((seconds, binary, name))
    cases.sort(reverse=True)
    print(f"\nthe {min(n, len(cases))} slowest tests (runner's timing):")
    for seconds, binary, name in cases[:n]:
        print(f"  {seconds:8.1f} s  {binary} {name}")
    total = sum(s for s, _, _ in cases)
    print(f"  ({len(cases)} tests, {total:.0f} s of test time in all)")
    print(f"suite: {len(cases) - failed - skipped} passed, {failed} failed, {skipped} skipped")
    return 0


if __name__ == "__main__":
    sys.exit(main())
