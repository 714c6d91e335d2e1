"""The caching compiler front end of the NMPC's JIT (`uavtrack_env.control.jit_cache`)."""

from __future__ import annotations

import stat
import sys
from pathlib import Path

import pytest

from uavtrack_env.control import jit_cache

FAKE_CC = """#!{python}
import pathlib, sys
args = sys.argv[1:]
log = pathlib.Path({log!r})
log.write_text(log.read_text() + "call\\n" if log.exists() else "call\\n")
src = next(a for a in args if a.endswith(".c"))
out = args[args.index("-o") + 1]
pathlib.Path(out).write_text("object of " + pathlib.Path(src).read_text())
sys.exit(1 if "FAIL" in pathlib.Path(src).read_text() else 0)
"""


@pytest.fixture
def fake_cc(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A 'compiler' that logs each call and writes the source into the object file."""
    log = tmp_path / "calls.log"
    cc = tmp_path / "fakecc"
    cc.write_text(FAKE_CC.format(python=sys.executable, log=str(log)))
    cc.chmod(cc.stat().st_mode | stat.S_IEXEC)
    monkeypatch.setenv("CC", str(cc))
    monkeypatch.setenv("UAVTRACK_JIT_CACHE", str(tmp_path / "cache"))
    return log


def _compile(tmp_path: Path, source: str, name: str, flags=("-O1",)) -> tuple[int, Path]:
    src, out = tmp_path / f"{name}.c", tmp_path / f"{name}.o"
    src.write_text(source)
    code = jit_cache.main([*flags, "-fPIC", "-c", str(src), "-o", str(out)])
    return code, out


def _calls(log: Path) -> int:
    return log.read_text().count("call") if log.exists() else 0


def test_same_source_is_compiled_once(tmp_path: Path, fake_cc: Path) -> None:
    code, out1 = _compile(tmp_path, "int f(void) { return 1; }", "a")
    assert code == 0 and _calls(fake_cc) == 1
    # same text under another file name (another process's build directory): a cache hit
    code, out2 = _compile(tmp_path, "int f(void) { return 1; }", "b")
    assert code == 0 and _calls(fake_cc) == 1
    assert out2.read_text() == out1.read_text()


def test_changed_source_or_flags_compile_again(tmp_path: Path, fake_cc: Path) -> None:
    _compile(tmp_path, "int f(void) { return 1; }", "a")
    code, out = _compile(tmp_path, "int f(void) { return 2; }", "b")
    assert code == 0 and _calls(fake_cc) == 2
    assert "return 2" in out.read_text()
    _compile(tmp_path, "int f(void) { return 2; }", "c", flags=("-O3",))
    assert _calls(fake_cc) == 3


def test_failed_compile_is_not_cached(tmp_path: Path, fake_cc: Path) -> None:
    code, _ = _compile(tmp_path, "FAIL", "a")
    assert code == 1
    code, _ = _compile(tmp_path, "FAIL", "b")
    assert code == 1 and _calls(fake_cc) == 2
    assert not list((tmp_path / "cache").glob("*.o"))
