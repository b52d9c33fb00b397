"""The measured tables of README.md and docs/results.md, rebuilt from their result files.

    python benchmarks/readme_tables.py                       # rewrite both files' tables
    python benchmarks/readme_tables.py --check               # exit 1 if one is stale
    python benchmarks/readme_tables.py --take results=reports/quick/nrmse.csv \\
                                       --take learned=outputs/learned_table/cells.csv

Each table of :data:`FILES` (README.md and docs/results.md) that a command measured sits
between ``<!-- table: NAME -->`` and ``<!-- /table -->``; its numbers live in a tracked CSV
(:data:`SOURCES`, under ``docs/results/``), the file the measuring command wrote, and every
block of that name, in either file, is rendered from it; a file of :data:`FILES` that does
not exist under ``--root`` is skipped. ``--take NAME=FILE`` first copies a fresh result in
(several files of one name are joined, e.g. the learned table's own run and its carried
cell). ``make readme-tables`` runs the rewrite; the test suite runs ``--check``, so a table
edited by hand, or a result file changed without its table, fails it.
"""

from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Callable
from pathlib import Path

import pandas as pd

from lbo.core.atomic import write_text

ROOT = Path(__file__).resolve().parents[1]
ALPHAS = (1.0, 3.0, 6.0)
BLOCK = re.compile(r"(<!-- table: (?P<name>[a-z_]+) -->\n)(?P<body>.*?)(<!-- /table -->)",
                   re.DOTALL)


def sig3(v: float) -> str:
    """Three significant digits, trailing zeros kept: 1.00, 13.4, 0.997."""
    return f"{v:#.3g}".rstrip(".")


def results(frame: pd.DataFrame) -> str:
    """The Results table from a report's ``nrmse.csv`` (``python -m lbo.reproduce``): NRMSE
    at alpha 1, 3 and 6 of the paper's eight observers, the robust observer and the classical
    ones, in the report's units (our EKF at alpha = 1)."""
    nets = [f"{m}-N{n}" for m in ("cnn", "lstm") for n in (20, 40, 60, 80)]
    robust = sorted(o for o in frame.observer.unique() if o.startswith("filternet-N"))
    if len(robust) != 1:
        raise SystemExit(f"error: results: expected one robust observer (filternet-N*) in the "
                         f"report, got {robust or 'none'}")
    columns = [*nets, robust[0], "ekf", "oracle", "adaptive", "ukf", "pcrb"]
    heads = ["CNN N=20", "N=40", "N=60", "N=80", "LSTM N=20", "N=40", "N=60", "N=80", "robust",
             "EKF", "oracle EKF", "adaptive EKF", "UKF", "PCRB"]
    table = frame.pivot_table(index="alpha", columns="observer", values="nrmse")
    missing = [c for c in columns if c not in table.columns]
    absent = [a for a in ALPHAS if a not in table.index]
    if missing or absent:
        raise SystemExit(f"error: results: the report lacks observers {missing} or alphas "
                         f"{absent}; expected make reproduce's report (nrmse.csv)")
    lines = ["| alpha | " + " | ".join(heads) + " |", "|---" * (len(heads) + 1) + "|"]
    for a in ALPHAS:
        lines.append(f"| {a:g} | " + " | ".join(sig3(table.at[a, c]) for c in columns) + " |")
    return "\n".join(lines) + "\n"


def learned(frame: pd.DataFrame) -> str:
    """The learned observers' table from ``benchmarks/learned_table.py``'s ``cells.csv``
    (one row per data set and observer): the ratio to the oracle at alpha 1 / 3 / 6 on each
    data set (on the car that slips, to the EKF told the car), and the parameter counts."""
    from learned_table import LABELS, PROTOCOLS

    sets = list(PROTOCOLS)

    def ratios(row: pd.Series, key: str = "") -> str:
        return " / ".join(f"{row[f'{key}ratio_{a:g}']:.2f}" for a in ALPHAS)

    heads = {"paper": "paper", "robust": "robust", "dynamic": "car that slips"}
    lines = ["| observer | " + " | ".join(heads[s] for s in sets) + " | parameters |",
             "|---|" + "---|" * len(sets) + "---:|"]
    first = frame.drop_duplicates("data").set_index("data")
    lines.append("| EKF, R at alpha = 1 | " + " | ".join(
        ratios(first.loc[s], "ekf_") if s in first.index else "not run" for s in sets) + " |  |")
    for observer in [o for o in LABELS if o in set(frame.observer)]:
        rows = frame[frame.observer == observer].set_index("data")
        counts = list(dict.fromkeys(f"{rows.at[s, 'parameters'] / 1000:.1f} K"
                                    for s in sets if s in rows.index))
        lines.append(f"| {LABELS[observer]} | " + " | ".join(
            ratios(rows.loc[s]) if s in rows.index else "not run" for s in sets)
            + f" | {', '.join(counts)} |")
    return "\n".join(lines) + "\n"


SOURCES: dict[str, tuple[str, Callable[[pd.DataFrame], str]]] = {
    "results": ("docs/results/quick_nrmse.csv", results),
    "learned": ("docs/results/learned_cells.csv", learned),
}
"""Each table's name in :data:`FILES`, its tracked result file, and how it is rendered."""

FILES = ("README.md", "docs/results.md")
"""The files whose marked tables are rendered, relative to the repository (``--root``)."""


def rebuild(text: str, root: Path = ROOT) -> str:
    """``text`` (README.md or docs/results.md) with every marked table rendered afresh from
    its result file."""
    def render(match: re.Match) -> str:
        name = match["name"]
        if name not in SOURCES:
            raise SystemExit(f"error: README table {name!r}: expected one of {sorted(SOURCES)}")
        path, renderer = SOURCES[name]
        if not (root / path).is_file():
            raise SystemExit(f"error: README table {name!r}: {path} is missing; measure it and "
                             f"give it with --take {name}=<file>")
        return match[1] + renderer(pd.read_csv(root / path)) + match[4]

    return BLOCK.sub(render, text)


def take(name: str, files: list[Path], root: Path = ROOT) -> None:
    """Copy fresh result files in as table ``name``'s source (several are joined)."""
    if name not in SOURCES:
        raise SystemExit(f"error: --take {name}: expected one of {sorted(SOURCES)}")
    for f in files:
        if not f.is_file():
            raise SystemExit(f"error: --take {name}: {f} is not a file")
    frame = pd.concat([pd.read_csv(f) for f in files], ignore_index=True)
    SOURCES[name][1](frame)  # refuse a file its table cannot be rendered from, before writing
    write_text(root / SOURCES[name][0], frame.to_csv(index=False))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true",
                    help="write nothing; exit 1 naming the stale tables")
    ap.add_argument("--take", action="append", default=[], metavar="NAME=FILE",
                    help="copy a fresh result file in as table NAME's source first")
    ap.add_argument("--root", type=Path, default=ROOT,
                    help="the repository whose README.md, docs/results.md and result files "
                         "these are")
    args = ap.parse_args(argv)
    fresh: dict[str, list[Path]] = {}
    for item in args.take:
        name, sep, file = item.partition("=")
        if not sep:
            raise SystemExit(f"error: --take {item}: expected NAME=FILE")
        fresh.setdefault(name, []).append(Path(file))
    for name, files in fresh.items():
        take(name, files, args.root)
    texts = {f: (args.root / f).read_text() for f in FILES if (args.root / f).is_file()}
    news = {f: rebuild(text, args.root) for f, text in texts.items()}  # all, before writing
    if args.check:
        failed = False
        for f, text in texts.items():
            stale = [m["name"] for m, n in zip(BLOCK.finditer(text), BLOCK.finditer(news[f]))
                     if m["body"] != n["body"]]
            if stale:
                print(f"error: {f}: tables {', '.join(stale)} differ from their result files; "
                      "run make readme-tables", file=sys.stderr)
                failed = True
        return 1 if failed else 0
    for f, new in news.items():
        if new != texts[f]:
            write_text(args.root / f, new)
        sources = ", ".join(SOURCES[m["name"]][0] for m in BLOCK.finditer(new))
        print(f"{f}: {len(BLOCK.findall(new))} tables rebuilt from {sources}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
