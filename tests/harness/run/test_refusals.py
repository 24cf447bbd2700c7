"""Mistakes and hostile inputs refused before anything starts, with one line and
exit 2: a run folder another run holds or a full disk can't take, configs that can
never work, a YAML alias bomb, a target command that is not a program (issue 14)."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from hil.harness.config.loading import parse_config
from hil.harness.config.model import SEED_MAX
from hil.harness.record.out_dir import LOCK_NAME, PROBE_BYTES, held_claims, release_out_dir
from hil.harness.run.driver import prepare_out_dir
from tests.harness.cli.test_cli import ROOT, assert_one_line_error, hil
from hil.common.errors import ConfigError, TargetError
from hil.timing.clock import MonotonicClock


@pytest.fixture
def claimed(tmp_path: Path):
    """Folders this test claims are given back at its end."""
    out: list[Path] = []
    yield out
    for p in out:
        release_out_dir(p)


# --- item 4: one run per folder ----------------------------------------------------


def test_a_folder_held_by_a_run_is_refused_in_another_process(tmp_path: Path, claimed: list[Path]):
    out = tmp_path / "r"
    claimed.append(prepare_out_dir(out))
    code = ("import sys; from hil.harness.run.driver import prepare_out_dir; from hil.common.errors import ConfigError\n"
            "try:\n    prepare_out_dir(__import__('pathlib').Path(sys.argv[1]))\n"
            "except ConfigError as e:\n    print(e); sys.exit(2)\n")
    p = subprocess.run([sys.executable, "-c", code, str(out)], cwd=ROOT, capture_output=True, text=True,
                       timeout=60, check=False)
    assert p.returncode == 2, (p.stdout, p.stderr)
    assert f"pid {os.getpid()}" in p.stdout and "is writing there now" in p.stdout


def test_the_cli_refuses_a_folder_another_run_holds(tmp_path: Path, claimed: list[Path]):
    out = tmp_path / "r"
    claimed.append(prepare_out_dir(out))
    p = hil("run", "hil_configs/demo.yaml", "--out", str(out), "--set", "duration_s=0.5", "--no-progress")
    assert_one_line_error(p, str(out), "is writing there now")
    assert not (out / "run.mcap").exists() and not (out / "config.json").exists()


def test_claim_is_given_back_and_retaken(tmp_path: Path):
    out = tmp_path / "r"
    prepare_out_dir(out)
    assert out.resolve() in held_claims()
    with pytest.raises(ConfigError, match="a run of this process"):
        prepare_out_dir(out)
    release_out_dir(out)
    assert out.resolve() not in held_claims()
    (out / "FAILED").write_text("this run did not start: ...\n")
    prepare_out_dir(out)  # free again: no stale claim, and no stale note of a failed start
    assert not (out / "FAILED").exists()
    (out / "summary.json").write_text("{}")  # that run finished: its claim goes with the next claim
    prepare_out_dir(tmp_path / "other")
    assert out.resolve() not in held_claims()
    release_out_dir(tmp_path / "other")
    assert (out / LOCK_NAME).read_text().strip() == str(os.getpid())


# --- item 5: a disk that cannot take the bytes ------------------------------------


def test_a_disk_that_takes_no_bytes_is_refused_with_one_line(tmp_path: Path):
    # RLIMIT_FSIZE makes every non-empty write fail as a full disk does, without root:
    # an empty probe file still passes, real bytes do not.
    code = textwrap.dedent("""
        import resource, signal, sys
        from pathlib import Path
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096))
        from hil.common.errors import ConfigError
        from hil.harness.run.driver import prepare_out_dir
        try:
            prepare_out_dir(Path(sys.argv[1]))
        except ConfigError as e:
            print(e); sys.exit(2)
    """)
    out = tmp_path / "r"
    p = subprocess.run([sys.executable, "-c", code, str(out)], cwd=ROOT, capture_output=True, text=True,
                       timeout=60, check=False)
    assert p.returncode == 2, (p.stdout, p.stderr)
    assert "cannot write there" in p.stdout and "Traceback" not in p.stderr
    assert not (out / ".write-test").exists() and not (out / "config.json").exists()


@contextlib.contextmanager
def _full_tmpfs(where: Path):
    where.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(where)],
                                           capture_output=True, check=False).returncode != 0:
        pytest.skip("needs root to mount a small tmpfs")
    try:
        with contextlib.suppress(OSError), open(where / "filler", "wb") as f:
            while True:
                f.write(b"\0" * 4096)
                f.flush()
        yield where
    finally:
        subprocess.run(["umount", str(where)], check=False)


def test_a_full_filesystem_is_refused_with_one_line(tmp_path: Path):
    with _full_tmpfs(tmp_path / "full") as full:
        p = hil("run", "hil_configs/demo.yaml", "--out", str(full / "r"), "--no-progress")
        assert_one_line_error(p, "cannot write there", "No space left on device")
        assert not (full / "r" / "config.json").exists()
    assert PROBE_BYTES >= 4096


# --- item 8: a seed SQLite cannot store ---------------------------------------------


def test_seed_is_bounded_to_what_the_case_index_stores():
    assert parse_config({"seed": SEED_MAX}).seed == SEED_MAX
    with pytest.raises(ConfigError, match=r"config error at seed: got 1180591620717411303424"):
        parse_config({"seed": 2**70})


# --- item 9: a YAML alias bomb ------------------------------------------------------


def test_a_yaml_alias_bomb_is_refused_at_once(tmp_path: Path):
    levels = ["&a [x,x,x,x,x,x,x,x,x]"]
    for prev, name in zip("abcdefgh", "bcdefghi"):
        levels.append(f"&{name} [" + ",".join([f"*{prev}"] * 9) + "]")
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text("seed: [" + ", ".join(levels) + "]\n")  # 9 levels, 9**9 leaves
    assert bomb.stat().st_size < 400
    # Formatting the whole value took minutes and gigabytes; the limit leaves room for a loaded machine.
    p = hil("run", str(bomb), "--out", str(tmp_path / "r"), timeout=30)
    assert_one_line_error(p, "config error at seed", "expected a valid integer")


# --- item 11: configs that can never work -------------------------------------------


@pytest.mark.parametrize(("overrides", "needles"), [
    (["camera.width=4096", "camera.height=4096", "camera.encoding=raw"],
     ("camera.width", "payload limit", "camera.encoding: jpeg")),
    (["target.transport=zenoh", "target.zenoh.connect=[zzz]"], ("target.zenoh.connect[0]", "'zzz'")),
    (["target.transport=zenoh", "target.zenoh.connect=['tcp/10.0.0.1']"], ("the port is required",)),
    (["target.transport=zenoh", "target.zenoh.connect=['bogus/10.0.0.1:7447']"], ("known protocol",)),
    (["target.transport=zenoh", "target.zenoh.tls={root_ca: ca.pem}"],
     ("target.zenoh.tls.root_ca", "root_ca_certificate")),
])
def test_configs_that_can_never_work_are_refused_before_anything_starts(tmp_path: Path, overrides, needles):
    with pytest.raises(ConfigError) as info:
        parse_config({}, overrides=overrides)
    for n in needles:
        assert n in str(info.value), str(info.value)
    out = tmp_path / "r"
    args = [a for o in overrides for a in ("--set", o)]
    p = hil("run", "hil_configs/demo.yaml", *args, "--out", str(out), "--no-progress")
    assert_one_line_error(p, needles[0])
    assert not out.exists()  # refused before the folder, the simulator or a target


def test_endpoints_with_placeholders_and_tls_keys_pass():
    cfg = parse_config({"target": {"transport": "zenoh", "command": [], "zenoh": {
        "connect": ["tls/device.local:{port}", "tcp/[::1]:7447"], "listen": ["tcp/0.0.0.0:0"],
        "tls": {"root_ca_certificate": "ca.pem", "enable_mtls": True}}}})
    assert cfg.target.zenoh.tls == {"root_ca_certificate": "ca.pem", "enable_mtls": True}


# --- item 10: a target command that is not a program --------------------------------


@pytest.fixture
def not_a_program(tmp_path: Path) -> Path:
    exe = tmp_path / "not-a-program"
    exe.write_bytes(b"\x7fELF\x02\x01\x01" + b"\0" * 57)  # executable, but no shebang and no valid binary
    exe.chmod(0o755)
    return exe


def test_exec_format_error_is_a_target_error(tmp_path: Path, not_a_program: Path):
    from hil.adapters.link import open_link
    from hil.harness.run.target_launch import TargetProcess

    with pytest.raises(TargetError, match="cannot be started: Exec format error"):
        TargetProcess([str(not_a_program)], log_path=tmp_path / "t.log")
    link = open_link("local", command=[str(not_a_program)], vehicle_id=0, clock=MonotonicClock(),
                     log_path=tmp_path / "l.log")
    try:
        with pytest.raises(TargetError, match="cannot be started: Exec format error"):
            link.open(hello_timeout_s=5)
    finally:
        link.close()


@pytest.mark.slow
def test_the_cli_reports_exec_format_error_in_one_line(tmp_path: Path, not_a_program: Path):
    p = hil("run", "hil_configs/demo.yaml", "--set", f"target.command=[{not_a_program}]",
            "--out", str(tmp_path / "r"), "--no-progress")
    assert_one_line_error(p, "Exec format error", str(not_a_program))
