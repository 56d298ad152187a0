"""The kernel cache: builds are named by their sources' hash, so installs coexist (fast)."""

from __future__ import annotations

import logging
from pathlib import Path

from dss import _ext

PROBE = 'extern "C" int dss_probe_answer() { return %d; }\n'


def _install(root: Path, answer: int) -> Path:
    """A stand-in for one install's kernel source (a plain C function: compiles in a second)."""
    root.mkdir(parents=True)
    src = root / "probe.cpp"
    src.write_text(PROBE % answer)
    return src


def test_installs_share_equal_builds_and_keep_different_ones(tmp_path, monkeypatch, caplog):
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "cache"))
    first, clone, changed = (_install(tmp_path / "first", 42), _install(tmp_path / "clone", 42),
                             _install(tmp_path / "changed", 7))
    kw = {"extra_cflags": ["-O0"], "is_python_module": False}
    names = {k: _ext.hashed_name("probe", [s], ["-O0", "|", "|"]) for k, s in
             (("first", first), ("clone", clone), ("changed", changed))}
    assert names["first"] == names["clone"] != names["changed"]  # by content, not by path

    def build(src) -> bool:
        """Whether loading ``src`` compiled (the first-use line was logged)."""
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="dss._ext"):
            _ext.load_hashed("probe", [src], **kw)
        return any("compiling" in r.getMessage() and "once" in r.getMessage() for r in caplog.records)

    before = _ext.build_seconds()
    assert build(first)
    assert _ext.build_seconds() > before
    lib = next((tmp_path / "cache").glob(f"{names['first']}/{names['first']}.so"))
    stamp = lib.stat().st_mtime_ns
    # a second install with the same kernel loads the first one's build: no compile, no rewrite
    assert not build(clone)
    assert lib.stat().st_mtime_ns == stamp
    # a different kernel gets its own build, and the first one stays valid beside it
    assert build(changed)
    assert not build(first) and lib.stat().st_mtime_ns == stamp
    assert sorted(p.name for p in (tmp_path / "cache").iterdir()) == sorted({names["first"], names["changed"]})
