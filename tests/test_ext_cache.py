"""The kernel cache: builds are named by their sources' hash, so installs coexist (fast)."""

from __future__ import annotations

import logging
import re
import threading
import time
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


def test_a_first_compile_logs_its_elapsed_time(tmp_path, monkeypatch, caplog):
    """A first-use compile says that it started, then its elapsed time every PROGRESS_EVERY_S
    (15 s; here shortened), then that it is done; its seconds count in build_seconds()."""
    import torch.utils.cpp_extension as cpp_extension

    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(_ext, "PROGRESS_EVERY_S", 0.01)
    ticks = threading.Event()

    class Ticks(logging.Handler):
        seen = 0

        def emit(self, record):
            if "so far" in record.getMessage():
                Ticks.seen += 1
                if Ticks.seen >= 3:
                    ticks.set()

    def slow_load(**kw):  # a compile that lasts until three progress lines were logged
        assert ticks.wait(30), "no progress lines while compiling"
        return "module"

    monkeypatch.setattr(cpp_extension, "load", slow_load)
    handler = Ticks()
    logging.getLogger("dss._ext").addHandler(handler)
    before = _ext.build_seconds()
    try:
        with caplog.at_level(logging.WARNING, logger="dss._ext"):
            assert _ext.load_hashed("probe", [_install(tmp_path / "src", 1)], what="a test kernel",
                                    expected=_ext.BUILD_TIME) == "module"
    finally:
        logging.getLogger("dss._ext").removeHandler(handler)
    lines = [r.getMessage() for r in caplog.records]
    assert lines[0].startswith("compiling a test kernel") and "once" in lines[0] and "2-core machine" in lines[0]
    progress = [ln for ln in lines if re.fullmatch(r"compiling a test kernel: \d+ s so far", ln)]
    assert len(progress) >= 3 and re.fullmatch(r"compiling a test kernel: done after \d+ s", lines[-1])
    assert _ext.build_seconds() > before


def test_a_compile_inside_a_stage_is_counted_as_kernel_build(monkeypatch):
    """metrics.json's profile: a compile that a stage started (reading a cloud whose normals need
    the kNN kernel) lands under kernel_build, not under that stage, nor in "other"."""
    from dss.timing import KERNEL_BUILD, StageClock

    real = time.perf_counter
    offset = [0.0]
    monkeypatch.setattr(time, "perf_counter", lambda: real() + offset[0])
    monkeypatch.setattr(_ext, "_build_seconds", [0.0])
    clock = StageClock()
    with clock("load"):
        offset[0] += 100.0  # a 100 s compile on a shifted clock
        _ext._build_seconds[0] += 100.0
    with clock("write"):
        pass
    assert clock.seconds[KERNEL_BUILD] == 100.0 and 0 <= clock.seconds["load"] < 1.0
    total = clock.seconds["load"] + clock.seconds["write"] + 2.0  # the job's time without the build
    assert re.search(r"other 2\.00 s$", clock.summary(total))


def test_prepare_kernels_reports_a_compile_since_the_run_started(monkeypatch, tmp_path):
    """time_s.kernel_build: a compile that an earlier step of the run started (JobStart marks the
    run's start under Hydra) is reported by the app's later prepare_kernels call."""
    from hydra.types import RunMode
    from omegaconf import OmegaConf

    from experiments import common

    monkeypatch.setattr(_ext, "_build_seconds", [5.0])  # an earlier compile in this process
    monkeypatch.setattr(_ext, "load_cpu", lambda: None)
    monkeypatch.setattr(common, "_RUN_BUILD_MARK", [None])
    job = OmegaConf.create({"hydra": {"mode": RunMode.MULTIRUN, "runtime": {"output_dir": str(tmp_path)}}})
    common.JobStart().on_job_start(job)
    _ext._build_seconds[0] += 30.0  # the input's normal estimation compiled the kNN kernel
    assert common.prepare_kernels() == 30.0
    common.JobStart().on_job_end(job, None)  # without a run mark: only what this call compiled
    assert common.prepare_kernels() == 0.0
