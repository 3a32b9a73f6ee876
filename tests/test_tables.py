"""The docs' results and baseline tables come from one source: ``make tables``
(``lerobot_crowdnav.evaluation.tables``) writes them from docs/data/, the CSV tables of
``make main``'s report and of ``lerobot-crowdnav-baselines``. A committed table that differs from
what the command writes fails here; so does a command that writes other numbers than it reads."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest

from lerobot_crowdnav.evaluation.baselines import TABLES, _slug
from lerobot_crowdnav.evaluation.report import (Row, boundary_audit, cell, csv_table, markdown_table, parameter_table,
                                                 wall_audit)
from lerobot_crowdnav.evaluation.tables import (BASELINE_COLUMNS, BLOCKS, DOCS, ROOT, MAIN_TABLES, TablesConfig,
                                                import_baselines, read_csv, regenerate, tables)

DATA = ROOT / "docs" / "data"


def blocks(text: str) -> dict[str, str]:
    return {m[1]: m[2] for m in re.finditer(r"<!-- table:([\w-]+) -->\n(.*?)\n?<!-- /table -->", text, re.S)}


def outside(text: str) -> str:
    return re.sub(r"<!-- table:([\w-]+) -->\n.*?<!-- /table -->", r"<\1>", text, flags=re.S)


def copy_repo(root: Path, data: bool = True) -> None:
    """The generated docs (and with ``data`` their docs/data) under ``root``, to rewrite there."""
    for doc in DOCS:
        (root / doc).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(ROOT / doc, root / doc)
    if data:
        shutil.copytree(DATA, root / "docs" / "data")


def test_committed_tables_are_what_make_tables_writes():
    """Run `make tables` (or python -m lerobot_crowdnav.evaluation.tables) and commit the result."""
    used = set()
    for doc in DOCS:
        text = (ROOT / doc).read_text()
        assert regenerate(text, DATA) == text, f"{doc}: a generated table differs from docs/data (run: make tables)"
        used |= set(blocks(text))
    assert used == set(BLOCKS), "every generated table appears in a doc"
    assert len((ROOT / "README.md").read_text().splitlines()) <= 150


def test_check_mode_finds_a_hand_edited_number_and_a_rerun_restores_it(tmp_path):
    copy_repo(tmp_path)
    results = tmp_path / "docs" / "results.md"
    committed = results.read_text()
    row = next(line for line in blocks(committed)["main-bounded"].splitlines() if line.startswith("| PDPO (H = 5"))
    sr = row.split(" | ")[1]
    results.write_text(committed.replace(row, row.replace(f" | {sr} | ", f" | {float(sr) + 0.1:.1f} | ", 1), 1))
    assert results.read_text() != committed
    with pytest.raises(SystemExit):
        tables(TablesConfig(root=tmp_path, check=True))
    assert tables(TablesConfig(root=tmp_path)) == [results] and results.read_text() == committed


def metrics(sr: float, n: int, *, bounded: bool, seed: int) -> dict:
    """Hand-made metrics.json: ``n`` episodes, the first ``round(sr * n)`` successes."""
    k = round(sr * n)
    events = ["success"] * k + ["human_collision", "wall_collision", "timeout"] * n
    episodes = [{"event": e, "steps": 1 if (i + seed) % 7 == 0 else 30, "goal": [5.9 if i % 5 == 0 else 1.0, 0.0],
                 "out_of_bounds": i % 3 == 0} for i, e in enumerate(events[:n])]
    return {"sr": k / n, "nt": 10.0 + seed / 3, "pl": 7.0 + seed / 7, "itr": 0.01 * seed, "sd": 0.3 + seed / 1000,
            "cr": 1 - k / n - 0.01 * seed, "tr": 0.01 * seed, "oob": None if bounded else 0.1 + seed / 100,
            "cr_human": 0.2, "cr_wall": 0.1, "n_episodes": n, "env": {"arena_size": 6.0, "robot_radius": 0.3},
            "episodes": episodes}


def test_the_command_writes_what_it_reads(tmp_path):
    """From hand-made runs: a `make main` run folder (the report's CSVs, two seeds in a row) and a
    lerobot-crowdnav-baselines output directory; every generated table carries their numbers, as
    the report itself writes them, and nothing outside the markers changes."""
    run, base, root = tmp_path / "main", tmp_path / "baselines", tmp_path / "repo"
    (run / "tables").mkdir(parents=True)
    main_rows = {}
    for i, short in enumerate(("bounded", "original")):
        labels = ["ORCA (look-ahead)", "ORCA (current-state)", "straight", "PDPO w/o action chunk (H = 1, fine-tuned)",
                  "PDPO (H = 5, fine-tuned)"]
        main_rows[short] = [Row(label, [metrics(0.1 + 0.2 * j + 0.05 * i, 40, bounded=short == "bounded", seed=j + s)
                                        for s in range(1 + (j == 3))]) for j, label in enumerate(labels)]
        (run / "tables" / f"results_{short}.csv").write_text(csv_table(main_rows[short]))
    (run / "tables" / "wall_audit.csv").write_text(wall_audit(main_rows["bounded"])[1])
    (run / "tables" / "boundary_audit.csv").write_text(boundary_audit(main_rows["original"])[1])
    counts = {"Bounded CrowdNav: PDPO (H = 5, fine-tuned)": {"actor": 831_803, "critic": 197_633}}
    (run / "tables" / "parameters.csv").write_text(parameter_table(counts)[1])
    baseline_rows = {}
    for t, key in enumerate(TABLES):
        _, env, names = TABLES[key]
        baseline_rows[key] = []
        for j, name in enumerate(names):
            m = metrics(0.3 + 0.1 * j + 0.02 * t, 50, bounded=env["task"] == "BoundedCrowdNav-v0", seed=10 + j)
            (base / key / _slug(name)).mkdir(parents=True)
            (base / key / _slug(name) / "metrics.json").write_text(json.dumps(m))
            baseline_rows[key].append(Row(name, [m]))
    copy_repo(root, data=False)
    for frozen in ("plain_bc", "look_ahead"):  # no run writes them
        shutil.copytree(DATA / frozen, root / "docs" / "data" / frozen)
    before = {doc: (root / doc).read_text() for doc in DOCS}

    tables(TablesConfig(main=run, baselines=base, root=root))
    data = root / "docs" / "data"
    for name in MAIN_TABLES:  # the report's CSVs, as they are
        assert (data / "main" / name).read_bytes() == (run / "tables" / name).read_bytes()
    after = {doc: (root / doc).read_text() for doc in DOCS}
    for doc in DOCS:
        assert outside(after[doc]) == outside(before[doc])
        assert blocks(after[doc]) != blocks(before[doc])
    got = {name: body for doc in DOCS for name, body in blocks(after[doc]).items()}

    # The main job's tables: exactly the report's own (markdown_table from the metrics themselves).
    assert got["main-bounded"] == markdown_table(main_rows["bounded"])
    assert got["main-original"] == markdown_table(main_rows["original"])
    assert "± " in got["main-bounded"]  # the two-seed row: mean ± std, as in the report
    readme = got["main"].splitlines()
    assert readme[0] == "| benchmark | Method | SR (%) | SR 95 % CI | NT (s) | PL (m) | ITR (%) | SD (m) |"
    assert readme[2:] == [f"| {b} |{line[1:]}" for b, short in (("Bounded", "bounded"), ("original", "original"))
                          for line in markdown_table(main_rows[short]).splitlines()[2:]]
    assert got["boundary-audit"] == boundary_audit(main_rows["original"])[0]
    assert got["parameters"] == parameter_table(counts)[0]
    assert got["wall-audit"] == wall_audit(main_rows["bounded"])[0]

    # The baselines: each cell as the report computes it from that row's metrics.json.
    def line(first: list[str], row: Row, columns: list[str], blank: str = "") -> str:
        return "| " + " | ".join([*first, row.label, *("-" if c == blank else cell(row, c)[0] for c in columns)]) + " |"

    columns = ["SR", "SR95", "NT", "PL", "ITR", "SD", "CR", "TR", "OOB"]
    assert got["baselines-paper"].splitlines()[2:] == (
        [line(["Bounded"], r, columns, "OOB") for r in baseline_rows["bounded_paper"]]
        + [line(["original"], r, columns) for r in baseline_rows["original_paper"]])
    assert got["crowdnavpp-orca-baseline"].splitlines()[2:] == [line([], baseline_rows["crowdnavpp_orca_baseline"][1],
                                                                     columns[:-1])]
    # docs/simulator.md: every row of each table (no OOB in Bounded), each Bounded one's wall audit.
    for key, (_, env, _) in TABLES.items():
        name, bounded = "baselines-" + key.replace("_", "-"), env["task"] == "BoundedCrowdNav-v0"
        if not key.endswith("_paper"):  # the `paper` tables are results.md's (baselines-paper), linked
            assert got[name].splitlines()[2:] == [line([], r, columns[:-1] if bounded else columns)
                                                  for r in baseline_rows[key]]
        if bounded:
            audit = wall_audit(baseline_rows[key])[0].splitlines()
            assert got[f"{name}-wall-audit"].splitlines() == [audit[0].replace("| Method |", "| policy |"), *audit[1:]]

    # Rerunning from the data now committed changes nothing.
    assert tables(TablesConfig(root=root)) == []


def test_a_baselines_import_replaces_only_the_tables_it_holds(tmp_path):
    """`--baselines=DIR` from a run of some tables (`--only=[...]`): their files are rewritten, every
    other table's files stay byte for byte; a table with a row missing is an error."""
    data = tmp_path / "data"
    shutil.copytree(DATA, data)
    before = {p.name: p.read_bytes() for p in (data / "baselines").iterdir()}
    base = tmp_path / "baselines"
    _, env, names = TABLES["bounded_crowdnavpp"]
    rows = []
    for j, name in enumerate(names):
        m = metrics(0.2 + 0.1 * j, 50, bounded=True, seed=j)
        (base / "bounded_crowdnavpp" / _slug(name)).mkdir(parents=True)
        (base / "bounded_crowdnavpp" / _slug(name) / "metrics.json").write_text(json.dumps(m))
        rows.append(Row(name, [m]))
    written = import_baselines(base, data)
    replaced = {"bounded_crowdnavpp.csv", "bounded_crowdnavpp_wall_audit.csv"}
    assert {p.name for p in written} == replaced
    assert (data / "baselines" / "bounded_crowdnavpp.csv").read_text() == csv_table(rows, BASELINE_COLUMNS)
    assert (data / "baselines" / "bounded_crowdnavpp_wall_audit.csv").read_text() == wall_audit(rows)[1]
    after = {p.name: p.read_bytes() for p in (data / "baselines").iterdir()}
    assert set(after) == set(before) | replaced
    kept = set(before) - replaced
    assert {n: after[n] for n in kept} == {n: before[n] for n in kept}

    (base / "bounded_crowdnavpp" / "straight" / "metrics.json").unlink()
    with pytest.raises(FileNotFoundError, match="bounded_crowdnavpp is incomplete"):
        import_baselines(base, data)


def test_every_baseline_table_is_generated():
    """Each lerobot-crowdnav-baselines table (but the generalization one, a `make main` table) has
    its data in docs/data/baselines, and each file there feeds a generated table."""
    files = {p.name for p in (DATA / "baselines").glob("*.csv")}
    assert {f"{key}.csv" for key in TABLES} <= files
    assert files == {part.file.removeprefix("baselines/") for block in BLOCKS.values() for part in block.parts
                     if part.file.startswith("baselines/")}


def test_bad_markers_and_missing_rows_are_errors(tmp_path):
    with pytest.raises(ValueError, match="unknown table"):
        regenerate("<!-- table:nope -->\n<!-- /table -->\n", DATA)
    with pytest.raises(ValueError, match="without its"):
        regenerate("<!-- table:main -->\n| a |\n", DATA)
    (tmp_path / "baselines").mkdir()
    (tmp_path / "baselines" / "crowdnavpp_orca_baseline.csv").write_text("method,SR_mean\nstraight,0.3\n")
    with pytest.raises(ValueError, match="no row 'ORCA current-state'"):
        regenerate("<!-- table:crowdnavpp-orca-baseline -->\n<!-- /table -->\n", tmp_path)


def test_generalization_tables_come_from_the_report_csv_and_wait_for_it(tmp_path, capsys):
    """The generalization blocks: until docs/data/main/generalization_<task>.csv exists, a
    placeholder naming the command that makes it (and the command says it skipped them); then
    exactly the report's table (same function on the same CSV lines), for any crowds."""
    from lerobot_crowdnav.evaluation.generalization import generalization_csv, generalization_markdown, read_csv
    from lerobot_crowdnav.evaluation.tables import GENERALIZATION_TABLES, NOT_GENERATED

    root = tmp_path / "repo"
    copy_repo(root)
    for name in GENERALIZATION_TABLES:
        (root / "docs" / "data" / "main" / name).unlink(missing_ok=True)
    assert tables(TablesConfig(root=root)) == [root / "docs" / "results.md"]  # back to the placeholders
    assert "skipped table generalization-bounded: docs/data/main/generalization_bounded.csv not generated yet" \
        in capsys.readouterr().out
    got = blocks((root / "docs" / "results.md").read_text())
    assert got["generalization-original"] == NOT_GENERATED.format(file="main/generalization_original.csv")

    run = tmp_path / "main"
    shutil.copytree(DATA / "main", run / "tables")
    crowds = ["orca", "reactive_orca", "social_force", "reactive_social_force"]
    expected = {}
    for short, bounded in (("bounded", True), ("original", False)):
        results = {label: {c: [metrics(0.2 + 0.1 * j + 0.05 * k, 50, bounded=bounded, seed=j + k + s) for s in range(1 + (j == 1))]
                           for k, c in enumerate(crowds)} for j, label in enumerate(["ORCA (look-ahead)", "PDPO (H = 5, fine-tuned)"])}
        text = generalization_csv(results, crowds)
        (run / "tables" / f"generalization_{short}.csv").write_text(text)
        expected[short] = generalization_markdown(read_csv(text), bounded)
    tables(TablesConfig(main=run, root=root))
    got = blocks((root / "docs" / "results.md").read_text())
    for short in ("bounded", "original"):
        assert (root / "docs" / "data" / "main" / f"generalization_{short}.csv").read_bytes() == \
            (run / "tables" / f"generalization_{short}.csv").read_bytes()
        assert got[f"generalization-{short}"] == expected[short]
    assert "| PDPO (H = 5, fine-tuned) | 30.0 ± " in expected["bounded"]  # two seeds: mean ± std, then the interval
    assert " / " in got["generalization-bounded"].splitlines()[2]
    assert tables(TablesConfig(root=root)) == []


def test_the_frozen_tables_keep_the_policies_shipped_before_whatever_main_run_is_imported(tmp_path):
    """docs/data/plain_bc and look_ahead are frozen: importing a new `make main` run rewrites the
    main tables, not theirs, which show the frozen files' PDPO rows, relabelled, with their own
    cells."""
    root = tmp_path / "repo"
    copy_repo(root)
    before = blocks((root / "docs" / "results.md").read_text())
    run = tmp_path / "main"
    shutil.copytree(DATA / "main", run / "tables")
    retrained = (run / "tables" / "results_bounded.csv").read_text().replace('"PDPO (H = 5, fine-tuned)",1,', '"PDPO (H = 5, fine-tuned)",1,9')
    (run / "tables" / "results_bounded.csv").write_text(retrained)  # a new SR: 9 before the old digits
    tables(TablesConfig(main=run, root=root))
    got = blocks((root / "docs" / "results.md").read_text())
    assert got["main-bounded"] != before["main-bounded"]
    assert all(got[name] == before[name] for name in got if name.startswith(("plain-bc", "look-ahead")))
    frozen = {r["method"]: r for r in read_csv(DATA / "plain_bc" / "results_bounded.csv")}
    sr = float(frozen["PDPO (H = 5, fine-tuned)"]["SR_mean"])
    assert f"| Bounded | PDPO (H = 5, plain BC, fine-tuned) | {sr:.1f} |" in got["plain-bc"]
    generalization = got["plain-bc-generalization-bounded"].splitlines()
    assert [line.split(" | ")[0] for line in generalization[2:]] == \
        ["| PDPO w/o action chunk (H = 1, plain BC, fine-tuned)", "| PDPO (H = 5, plain BC, fine-tuned)"]
    look_ahead = {r["method"]: r for r in read_csv(DATA / "look_ahead" / "results_bounded.csv")}
    sr = float(look_ahead["PDPO (H = 5, fine-tuned)"]["SR_mean"])
    assert f"| Bounded | PDPO (H = 5, look-ahead teacher, fine-tuned) | {sr:.1f} |" in got["look-ahead"]
    frozen = {r["method"]: r for r in read_csv(DATA / "look_ahead" / "results_original.csv")}
    sr = float(frozen["PDPO w/o action chunk (H = 1, fine-tuned)"]["SR_mean"])
    assert f"| original | PDPO w/o action chunk (H = 1, look-ahead teacher, fine-tuned) | {sr:.1f} |" in got["look-ahead"]
    assert got["look-ahead-generalization-original"].count("look-ahead teacher, fine-tuned)") == 2
