"""Two runs of ``bench_vs_shader.py`` (a library before a change, and after it) as one table per frame.

Each cell reads ``before → after``: CPU ms and the ratio to the row's reference as each run printed them (a ratio in
bold misses its target), and the peak memory column likewise. Rows and columns are the after run's; a row the before
run lacks keeps the after run's cell alone.

    python benchmarks/bench_vs_shader.py --library /tmp/before --backend auto ... > before.md
    python benchmarks/bench_vs_shader.py ... > after.md
    python benchmarks/before_after.py before.md after.md
"""
from __future__ import annotations

import argparse
import sys


def tables(text: str) -> dict[str, list[list[str]]]:
    """``{title: rows}``: each Markdown table of a ``bench_vs_shader.py`` run under its bold title line."""
    out: dict[str, list[list[str]]] = {}
    title = None
    for line in text.splitlines():
        if line.startswith("**"):
            title = line
            out[title] = []
        elif line.startswith("|") and title is not None:
            out[title].append([cell.strip() for cell in line.strip().strip("|").split("|")])
    return out


def merged(before: str, after: str) -> str:
    """The after run's tables with each cell the before run's ``→`` the after run's (where they differ)."""
    old, new = tables(before), tables(after)
    lines = []
    for title, rows in new.items():
        if len(rows) < 2:
            continue
        previous = {row[0]: row for row in old.get(title, [])[2:]}
        lines += [title.replace("(ratio)", "(ratio), before → after"), "", "| " + " | ".join(rows[0]) + " |",
                  "|---|---|" + "---:|" * (len(rows[0]) - 2)]
        for row in rows[2:]:
            was = previous.get(row[0])
            cells = row[:2] + [cell if was is None or i >= len(was) or not was[i] or was[i] == cell
                               else f"{was[i]} → {cell}" for i, cell in enumerate(row) if i >= 2]
            lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before", help="the earlier library's run (Markdown, bench_vs_shader.py's stdout)")
    ap.add_argument("after", help="the later library's run")
    args = ap.parse_args(argv)
    with open(args.before, encoding="utf-8") as b, open(args.after, encoding="utf-8") as a:
        sys.stdout.write(merged(b.read(), a.read()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
