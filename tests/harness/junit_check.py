"""An independent reader of JUnit XML for the tests: ``xml.etree`` and a schema check
of the layout CI systems read (Ant's JUnit schema as Jenkins and GitLab take it, with
pytest's per-testcase ``<properties>``), never the library that wrote the file."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

_CASE_CHILDREN = {"properties", "failure", "error", "skipped", "system-out", "system-err"}
_SUITE_CHILDREN = {"properties", "testcase", "testsuite", "system-out", "system-err"}


@dataclass
class Case:
    classname: str
    failed: bool
    message: str | None
    properties: dict[str, str] = field(default_factory=dict)
    system_out: str | None = None


@dataclass
class Suite:
    name: str
    properties: dict[str, str]
    cases: dict[str, Case]


def _props(elem: ET.Element, where: str) -> dict[str, str]:
    out: dict[str, str] = {}
    for props in elem.findall("properties"):
        for p in props:
            assert p.tag == "property", f"{where}: <{p.tag}> in <properties>"
            assert set(p.attrib) == {"name", "value"}, f"{where}: property attributes {p.attrib}"
            out[p.attrib["name"]] = p.attrib["value"]
    return out


def read_junit(path: Path) -> list[Suite]:
    """Parse ``path`` and check the schema: a ``testsuites`` (or ``testsuite``) root;
    each suite's ``tests``/``failures``/``errors``/``skipped`` are integers equal to
    its cases; each case has ``name`` and ``classname`` and only the allowed
    children; a failure has a ``message``.

    Raises:
        AssertionError: the file breaks the schema (says where).
    """
    root = ET.parse(path).getroot()
    assert root.tag in ("testsuites", "testsuite"), root.tag
    suites = [root] if root.tag == "testsuite" else root.findall("testsuite")
    assert suites and all(s.tag == "testsuite" for s in root if root.tag == "testsuites"), [s.tag for s in root]
    out = []
    for s in suites:
        name = s.attrib.get("name")
        assert name, "testsuite without a name"
        for child in s:
            assert child.tag in _SUITE_CHILDREN, f"suite {name}: <{child.tag}>"
        cases: dict[str, Case] = {}
        counts = {"failures": 0, "errors": 0, "skipped": 0}
        for tc in s.findall("testcase"):
            assert {"name", "classname"} <= set(tc.attrib), f"suite {name}: testcase attributes {tc.attrib}"
            where = f"{name} / {tc.attrib['name']}"
            for child in tc:
                assert child.tag in _CASE_CHILDREN, f"{where}: <{child.tag}>"
            failure = tc.find("failure")
            if failure is not None:
                assert failure.attrib.get("message"), f"{where}: a failure without a message"
                counts["failures"] += 1
            counts["errors"] += tc.find("error") is not None
            counts["skipped"] += tc.find("skipped") is not None
            out_elem = tc.find("system-out")
            assert tc.attrib["name"] not in cases, f"{where}: twice"
            cases[tc.attrib["name"]] = Case(tc.attrib["classname"], failure is not None,
                                            None if failure is None else failure.attrib["message"],
                                            _props(tc, where), None if out_elem is None else out_elem.text)
        assert int(s.attrib["tests"]) == len(cases), (name, s.attrib["tests"], len(cases))
        for k, n in counts.items():
            assert int(s.attrib.get(k, "0")) == n, (name, k, s.attrib.get(k), n)
        out.append(Suite(name, _props(s, name), cases))
    return out
