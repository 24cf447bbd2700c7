"""The report links a case only to a recording inside the run folder: a tampered
case row (``mcap_path`` of ``javascript:…``, an absolute path, ``..``, a symlink
leading out) is shown as text, never as a link (issue 26, item 7)."""

from __future__ import annotations

import re
import sqlite3
from pathlib import Path

from hil.harness.record.run_folder import read_run
from hil.harness.report.case_section import cases_section
from tests.harness.report.test_report import CASES_SQL
from tests.harness.cases.test_replay_trust import foreign_run


def test_only_files_inside_the_run_folder_become_links(tmp_path: Path) -> None:
    run = foreign_run(tmp_path / "r", [])
    (run / "corner_cases.sqlite").unlink()
    (run / "corner_cases").mkdir()
    (run / "corner_cases" / "case-0001.mcap").write_bytes(b"x")
    evil = "javascript:alert(document.domain)"
    (run / evil).write_bytes(b"x")  # the tampered folder ships a file of that name too
    outside = tmp_path / "outside.mcap"
    outside.write_bytes(b"x")
    (run / "corner_cases" / "link.mcap").symlink_to(outside)
    paths = ["corner_cases/case-0001.mcap", evil, str(outside), "../outside.mcap", "corner_cases/link.mcap",
             "corner_cases/case-0099.mcap", "case\x00.mcap"]
    with sqlite3.connect(run / "corner_cases.sqlite") as con:
        con.execute(CASES_SQL)
        con.executemany("INSERT INTO cases VALUES (?,?,?,?,?,?,?,?,?,?,?)",
                        [(i, "r", "stopped_car", 0, "{}", "x", "ego0", 10**9, "state_mismatch", "s", p)
                         for i, p in enumerate(paths, 1)])
    con.close()
    html = cases_section(read_run(run))
    assert set(re.findall(r'<a href="([^"#]*)"', html)) == {"corner_cases/case-0001.mcap"}
    assert "javascript" not in "".join(re.findall(r"<a [^>]*>", html))
    assert html.count("(not a file in the run folder)") == 2 * 5  # table + case card, 5 tampered paths
    assert html.count("(not written)") == 2
