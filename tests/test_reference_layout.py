"""The renderer's Python side is laid out like its kernels: every kernel op has its torch twin in
dss.reference under the op's name, and every custom autograd Function lives in dss.autograd."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import dss.reference as reference

ROOT = Path(__file__).resolve().parents[1]
CSRC = ROOT / "dss" / "csrc"


def _bound_ops() -> set[str]:
    ops = set()
    for bind in ("dss_cpu_bind.cpp", "dss_cuda_bind.cpp"):
        ops |= set(re.findall(r'm\.def\("(\w+)"', (CSRC / bind).read_text()))
    return ops


def test_every_kernel_op_is_in_the_twin_table():
    ops = _bound_ops()
    assert {"project_splats_forward", "rasterize_forward", "blend_backward", "local_frames_forward", "knn_grid"} <= ops
    assert ops == set(reference.TWINS), f"ops without an entry: {sorted(ops - set(reference.TWINS))}; " \
                                        f"entries without an op: {sorted(set(reference.TWINS) - ops)}"


def test_twins_live_in_dss_reference_under_the_op_names():
    for op, name in reference.TWINS.items():
        if name is None:
            continue
        stem = re.sub(r"_(forward|backward)$", "", op)
        assert name in (op, stem), f"{op}: twin {name!r} is not named after the op"
        fn = getattr(reference, name, None)
        assert callable(fn), f"dss.reference has no {name} (the twin of {op})"
        assert fn.__module__.startswith("dss.reference."), f"{name} is defined in {fn.__module__}"
        assert name in reference.__all__


def _classes_deriving_autograd_function(path: Path) -> list[str]:
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ClassDef):
            bases = [ast.unparse(b) for b in node.bases]
            if any(b.endswith("autograd.Function") or b == "Function" for b in bases):
                found.append(node.name)
    return found


def test_autograd_functions_live_in_one_module():
    by_file = {p.relative_to(ROOT).as_posix(): _classes_deriving_autograd_function(p)
               for p in (ROOT / "dss").rglob("*.py")}
    elsewhere = {f: c for f, c in by_file.items() if c and f != "dss/autograd.py"}
    assert not elsewhere, f"autograd Functions outside dss/autograd.py: {elsewhere}"
    assert {"KernelProject", "KernelBlend", "KernelSunShade", "VisibilityGradient", "PermuteRows",
            "NeighbourDiff", "FusedSmape"} <= set(by_file["dss/autograd.py"])


def test_the_rasterisers_dispatch_sits_beside_it():
    from dss import rasterizer, render

    assert render.rasterize is rasterizer.rasterize  # render calls the rasteriser's own dispatch
    assert not hasattr(render, "_blend_differentiable") and not hasattr(render, "_kernels")
