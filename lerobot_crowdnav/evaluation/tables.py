"""The results and baseline tables of README.md, docs/results.md and docs/simulator.md, generated
from one source.

    python -m lerobot_crowdnav.evaluation.tables                    # make tables: rewrite the docs' tables from docs/data/
    python -m lerobot_crowdnav.evaluation.tables --main=outputs/main --baselines=outputs/baselines
                                                                    # first refresh docs/data/ from those runs
    python -m lerobot_crowdnav.evaluation.tables --check=true       # exit 1 where a committed table differs

The source is ``docs/data/`` (committed): ``main/*.csv``, the CSV tables of ``make main``'s report
(``<run>/tables/``, copied as they are), and ``baselines/<table>.csv`` (+ ``<table>_wall_audit.csv``
for Bounded), each ``lerobot-crowdnav-baselines`` table's ``metrics.json`` files in the report's
CSV format (``report.csv_table``, ``report.wall_audit``); ``--baselines=DIR`` replaces only the
tables DIR holds, the others' files stay as they are. A doc's generated table sits between
``<!-- table:NAME -->`` and ``<!-- /table -->`` (NAME: a key of :data:`BLOCKS`); everything
outside the markers is left alone. Cells are formatted as in the report (``report.COLUMNS``: SR in
% with its 95 % Wilson interval, NT in s, ...), ``mean ± std`` where a row averages several seeds.
tests/test_tables.py fails when a committed table differs from what this writes.

``plain_bc/`` is frozen: ``make main``'s tables of the policies shipped until 2026-11-26, trained by
the paper's plain-BC recipes (the ``_paper_bc`` configs), kept so the docs can show what the
crowd-looking pretraining changed; their PDPO rows are relabelled as plain BC.

The generalization tables (``main/generalization_<task>.csv``, from a ``make main`` run with its
default ``--crowds``) are optional: until their file exists, their block says how to make it
(:data:`NOT_GENERATED`) and the command names what it skipped.
"""

from __future__ import annotations

import csv
import io
import json
import re
import shutil
from dataclasses import dataclass, field
from pathlib import Path

from ..cli import run_cli
from .generalization import generalization_markdown
from .generalization import read_csv as read_generalization
from .report import COLUMNS, RESULT_COLUMNS, WALL_AUDIT_HEADERS, Row, csv_table, wall_audit

ROOT = Path(__file__).resolve().parents[2]
# The files whose tables are generated, relative to the repository.
DOCS = ["README.md", "docs/results.md", "docs/simulator.md"]
MAIN_TABLES = ["results_bounded.csv", "results_original.csv", "wall_audit.csv", "boundary_audit.csv", "parameters.csv"]
GENERALIZATION_TABLES = ["generalization_bounded.csv", "generalization_original.csv"]  # optional
# The body of an optional block whose data file is missing ({file}: its path under docs/data).
NOT_GENERATED = ("*Not generated yet* (`docs/data/{file}` is missing): `make main` writes it to "
                 "`outputs/main/tables/`, then `make tables TABLES_ARGS=--main=outputs/main`.")
BASELINE_COLUMNS = ["SR", "SR95", "NT", "PL", "ITR", "SD", "CR", "TR", "OOB"]
BENCHMARKS = {"bounded": "Bounded", "original": "original"}  # a task's name in the tables' benchmark column
MARKER = re.compile(r"<!-- table:(?P<name>[\w-]+) -->\n(?P<body>.*?)<!-- /table -->", re.S)


# -- docs/data/ from the runs' outputs -----------------------------------------------------------
def import_main(run: Path, data: Path) -> list[Path]:
    """Copy the CSV tables of a ``make main`` run folder (``<run>/tables``) to ``data/main``."""
    out = data / "main"
    out.mkdir(parents=True, exist_ok=True)
    missing = [name for name in MAIN_TABLES if not (run / "tables" / name).exists()]
    if missing:
        raise FileNotFoundError(f"{run / 'tables'} lacks {', '.join(missing)}: is {run} a `make main` run folder?")
    names = [*MAIN_TABLES, *(name for name in GENERALIZATION_TABLES if (run / "tables" / name).exists())]
    for name in names:  # a run without other crowds (--crowds=[]) leaves the generalization data as it is
        shutil.copyfile(run / "tables" / name, out / name)
    return [out / name for name in names]


def import_baselines(output_dir: Path, data: Path) -> list[Path]:
    """Each table of a ``lerobot-crowdnav-baselines`` output directory (``<table>/<row>/metrics.json``)
    as ``data/baselines/<table>.csv`` (+ ``<table>_wall_audit.csv`` in Bounded), in the report's
    CSV format; tables not run there are left as they are."""
    from .baselines import TABLES, _slug

    out = data / "baselines"
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for key, (_, env, names) in TABLES.items():
        paths = {name: output_dir / key / _slug(name) / "metrics.json" for name in names}
        if not any(p.exists() for p in paths.values()):
            continue
        missing = [str(p) for p in paths.values() if not p.exists()]
        if missing:
            raise FileNotFoundError(f"table {key} is incomplete (rerun lerobot-crowdnav-baselines): {', '.join(missing)}")
        rows = [Row(name, [json.loads(p.read_text())]) for name, p in paths.items()]
        written.append(out / f"{key}.csv")
        written[-1].write_text(csv_table(rows, BASELINE_COLUMNS))
        if env["task"] == "BoundedCrowdNav-v0":
            written.append(out / f"{key}_wall_audit.csv")
            written[-1].write_text(wall_audit(rows)[1])
    return written


# -- the tables from docs/data/ ------------------------------------------------------------------
def read_csv(path: Path) -> list[dict[str, str]]:
    return list(csv.DictReader(io.StringIO(path.read_text())))


def result_cell(row: dict[str, str], column: str) -> str:
    """A cell of a ``report.csv_table`` row, as ``report.markdown_table`` writes it."""
    digits = COLUMNS[column][2]
    if column == "SR95":
        lo, hi = row["SR95_low"], row["SR95_high"]
        return "n/a" if lo == "" else f"[{float(lo):.{digits}f}, {float(hi):.{digits}f}]"
    mean, std = row[f"{column}_mean"], row[f"{column}_std"]
    if mean == "":
        return "n/a"
    return f"{float(mean):.{digits}f}" + (f" ± {float(std):.{digits}f}" if int(row["n_seeds"]) > 1 else "")


def _share(value: str) -> str:
    return "n/a" if value == "" else f"{float(value):.1f}"


@dataclass(frozen=True)
class Part:
    """Rows of one CSV file (under docs/data) in a table: ``rows`` picks and orders them by their
    first column, ``{label in the file: label shown}`` (None: all, as labelled); ``first``: cells
    put before the label (e.g. the benchmark); ``blank``: columns shown as ``-`` (not measured)."""

    file: str
    rows: dict[str, str] | None = None
    first: tuple[str, ...] = ()
    blank: tuple[str, ...] = ()


@dataclass(frozen=True)
class Block:
    """One generated table: its ``kind`` (``results``: report columns ``columns``; ``wall_audit``,
    ``boundary_audit``, ``parameters``: the report's audit and parameter tables; ``generalization``:
    the report's generalization table of one benchmark, ``bounded`` or not, from one part's file,
    every row), the header of the leading cells and of the label, and its parts in order.
    ``optional``: a missing data file gives :data:`NOT_GENERATED` instead of an error."""

    kind: str
    parts: list[Part]
    lead: tuple[str, ...] = ()
    label: str = "Method"
    columns: list[str] = field(default_factory=lambda: list(RESULT_COLUMNS))
    optional: bool = False
    bounded: bool = False


def missing_files(block: Block, data: Path) -> list[str]:
    """The data files of ``block`` not under ``data`` (paths relative to it)."""
    return [part.file for part in block.parts if not (data / part.file).exists()]


def _rows(data: Path, part: Part) -> list[tuple[str, dict[str, str]]]:
    table = read_csv(data / part.file)
    key = next(iter(table[0])) if table else "method"
    by_label = {r[key]: r for r in table}
    if part.rows is None:
        return [(r[key], r) for r in table]
    missing = [label for label in part.rows if label not in by_label]
    if missing:
        raise ValueError(f"{data / part.file} has no row {', '.join(map(repr, missing))}")
    return [(shown, by_label[label]) for label, shown in part.rows.items()]


def render(block: Block, data: Path) -> str:
    """The markdown table of ``block`` from the CSV files under ``data``."""
    missing = missing_files(block, data)
    if block.optional and missing:
        return NOT_GENERATED.format(file=missing[0])
    if block.kind == "generalization":
        (part,) = block.parts
        rows = read_generalization((data / part.file).read_text())
        if part.rows is not None:  # those rows, in that order, relabelled
            rows = [{**r, "method": shown} for label, shown in part.rows.items() for r in rows if r["method"] == label]
        return generalization_markdown(rows, block.bounded, block.label)
    if block.kind == "results":
        header = [*block.lead, block.label, *(COLUMNS[c][3] for c in block.columns)]
    elif block.kind == "wall_audit":
        header = [*block.lead, block.label, "episodes", *(f"{h} (%)" for h in WALL_AUDIT_HEADERS.values())]
    elif block.kind == "boundary_audit":
        header = [*block.lead, block.label, "successful episodes", "left the workspace", "share (%)"]
    elif block.kind == "parameters":
        header = [*block.lead, block.label, "actor (M)", "critic (M)"]
    else:
        raise ValueError(f"unknown table kind {block.kind!r}")
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for part in block.parts:
        for label, r in _rows(data, part):
            if block.kind == "results":
                cells = ["-" if c in part.blank else result_cell(r, c) for c in block.columns]
            elif block.kind == "wall_audit":
                cells = [r["episodes"], *(_share(r[o]) for o in WALL_AUDIT_HEADERS)]
            elif block.kind == "boundary_audit":
                cells = [r["successes"], r["out_of_bounds"], _share(r["share_percent"])]
            else:
                cells = [f"{int(r['actor']) / 1e6:.3f}", f"{int(r['critic']) / 1e6:.3f}"]
            lines.append("| " + " | ".join([*part.first, label, *cells]) + " |")
    if block.kind == "parameters":
        lines.append("| " + " | ".join([*("" for _ in block.lead), "paper (PDPO)", "0.848", "0.201"]) + " |")
    return "\n".join(lines)


def _same(*labels: str) -> dict[str, str]:
    return {label: label for label in labels}


def _baseline_blocks(key: str, *, bounded: bool, results: bool = True) -> dict[str, Block]:
    """The blocks of one ``lerobot-crowdnav-baselines`` table (``baselines/<key>.csv``), named
    ``baselines-<key>`` (``_`` as ``-``): every row, the baseline columns (no OOB in Bounded, where
    the robot cannot leave), and in Bounded ``baselines-<key>-wall-audit`` (``<key>_wall_audit.csv``).
    ``results=False``: the wall audit only."""
    name = "baselines-" + key.replace("_", "-")
    blocks = {}
    if results:
        blocks[name] = Block("results", [Part(f"baselines/{key}.csv")], label="policy",
                             columns=BASELINE_COLUMNS[:-1] if bounded else BASELINE_COLUMNS)
    if bounded:
        blocks[f"{name}-wall-audit"] = Block("wall_audit", [Part(f"baselines/{key}_wall_audit.csv")], label="policy")
    return blocks


def _shipped_before_blocks(key: str, recipe: str) -> dict[str, Block]:
    """The frozen ``make main`` tables of policies shipped before (``<key>/``), named ``<key>-*``
    (``_`` as ``-``): the results of both benchmarks, the wall audit and both generalization
    tables, the PDPO rows labelled with the ``recipe`` that made them."""
    relabel = {f"PDPO{h} ({horizon}, fine-tuned)": f"PDPO{h} ({horizon}, {recipe}, fine-tuned)"
               for h, horizon in ((" w/o action chunk", "H = 1"), ("", "H = 5"))}
    name = key.replace("_", "-")
    blocks = {name: Block("results", [Part(f"{key}/results_{task}.csv", relabel, first=(benchmark,))
                                      for task, benchmark in BENCHMARKS.items()], lead=("benchmark",)),
              f"{name}-wall-audit": Block("wall_audit", [Part(f"{key}/wall_audit.csv", relabel)])}
    for task in BENCHMARKS:
        blocks[f"{name}-generalization-{task}"] = Block(
            "generalization", [Part(f"{key}/generalization_{task}.csv", relabel)], bounded=task == "bounded")
    return blocks


_MAIN_ROWS = {"bounded": "main/results_bounded.csv", "original": "main/results_original.csv"}
BLOCKS: dict[str, Block] = {
    # README.md: both benchmarks in one table.
    "main": Block("results", [Part(rows, first=(BENCHMARKS[task],)) for task, rows in _MAIN_ROWS.items()],
                  lead=("benchmark",)),
    # docs/results.md
    "main-bounded": Block("results", [Part(_MAIN_ROWS["bounded"])]),
    "main-original": Block("results", [Part(_MAIN_ROWS["original"])]),
    "wall-audit": Block("wall_audit", [Part("main/wall_audit.csv")]),
    "boundary-audit": Block("boundary_audit", [Part("main/boundary_audit.csv")]),
    "parameters": Block("parameters", [Part("main/parameters.csv")], label="Policy"),
    "baselines-paper": Block("results", [Part("baselines/bounded_paper.csv", first=("Bounded",), blank=("OOB",)),
                                         Part("baselines/original_paper.csv", first=("original",))],
                             lead=("variant",), label="policy", columns=BASELINE_COLUMNS),
    "crowdnavpp-orca-baseline": Block("results", [Part("baselines/crowdnavpp_orca_baseline.csv",
                                                       _same("ORCA current-state"))],
                                      label="policy", columns=BASELINE_COLUMNS[:-1]),
    # docs/results.md: the policies shipped until 2026-11-26, by the paper's plain-BC recipes (frozen data)
    **_shipped_before_blocks("plain_bc", "plain BC"),
    # docs/results.md: the pairs shipped until 2026-11-29, taught by the look-ahead ORCA robot (frozen data)
    **_shipped_before_blocks("look_ahead", "look-ahead teacher"),
    # docs/results.md: make main's generalization tables (optional until a run with --crowds made them)
    "generalization-bounded": Block("generalization", [Part("main/generalization_bounded.csv")], optional=True,
                                    bounded=True),
    "generalization-original": Block("generalization", [Part("main/generalization_original.csv")], optional=True),
    # docs/simulator.md, "Baselines": the lerobot-crowdnav-baselines tables results.md does not show
    # (its `paper` tables are linked there, not repeated), each Bounded one with its wall audit
    # (the human / wall collision split); the wall times of baselines.md are not deterministic.
    **_baseline_blocks("bounded_paper", bounded=True, results=False),
    **_baseline_blocks("bounded_crowdnavpp", bounded=True),
    **_baseline_blocks("original_crowdnavpp", bounded=False),
    **_baseline_blocks("bounded_crowdnavpp_fixed", bounded=True),
    **_baseline_blocks("original_crowdnavpp_fixed", bounded=False),
    **_baseline_blocks("crowdnavpp_orca_baseline", bounded=False),  # both robots (results.md: current-state)
}


def regenerate(text: str, data: Path, blocks: dict[str, Block] = BLOCKS) -> str:
    """``text`` with every generated block rewritten from ``data``."""
    def block(match: re.Match) -> str:
        name = match["name"]
        if name not in blocks:
            raise ValueError(f"unknown table {name!r} (known: {', '.join(blocks)})")
        return f"<!-- table:{name} -->\n{render(blocks[name], data)}\n<!-- /table -->"

    if text.count("<!-- table:") != text.count("<!-- /table -->"):
        raise ValueError("a <!-- table:NAME --> marker without its <!-- /table --> (or the other way round)")
    return MARKER.sub(block, text)


@dataclass
class TablesConfig:
    # A `make main` run folder whose tables/*.csv replace docs/data/main/ first (default: keep them).
    main: Path | None = None
    # A lerobot-crowdnav-baselines output directory whose tables replace theirs in docs/data/baselines/
    # first (tables it does not hold keep their files).
    baselines: Path | None = None
    # Only report the docs whose tables differ from docs/data/ (exit 1 if any), rewrite nothing.
    check: bool = False
    # The repository (README.md, docs/).
    root: Path = ROOT
    # The data directory, relative to the repository.
    data: Path = Path("docs/data")


def tables(cfg: TablesConfig) -> list[Path]:
    """Rewrite (or with ``check`` only compare) the generated tables of :data:`DOCS`; returns the
    docs that were (or would be) changed."""
    data = cfg.root / cfg.data
    if cfg.main is not None:
        import_main(cfg.main, data)
    if cfg.baselines is not None:
        import_baselines(cfg.baselines, data)
    skipped = {name: missing_files(block, data)[0] for name, block in BLOCKS.items()
               if block.optional and missing_files(block, data)}
    for name, file in skipped.items():
        print(f"skipped table {name}: docs/data/{file} not generated yet (make main, then "
              "make tables TABLES_ARGS=--main=outputs/main)")
    changed = []
    for doc in DOCS:
        path = cfg.root / doc
        text = path.read_text()
        new = regenerate(text, data)
        if new != text:
            changed.append(path)
            if not cfg.check:
                path.write_text(new)
    verb = "differ from docs/data (run: make tables)" if cfg.check else "rewritten"
    print(f"{len(changed)} of {len(DOCS)} docs {verb}" + "".join(f"\n  {p}" for p in changed))
    if cfg.check and changed:
        raise SystemExit(1)
    return changed


def main(argv: list[str] | None = None) -> None:
    run_cli(TablesConfig, tables, argv)


if __name__ == "__main__":
    main()
