"""Tables in README.md and docs/*.md generated from the tracked result files, so that they
cannot drift from ``results/``.

A generated block in a markdown file is the text between two markers:

    <!-- generated: <generator> <source> [key="value" ...] -->
    | method | mean CD | ... |
    <!-- end generated -->

``<source>`` is a result file relative to the repository root (e.g.
``results/denoise/budgets_0.01_20000/table.json``); ``<generator>`` one of :data:`GENERATORS`,
which turns the loaded source and the options into markdown. The opening marker may span lines;
options are shell-quoted ``key=value`` words. ``dss-results --publish`` rewrites every block from
its source (:func:`update`), ``dss-results --check`` and ``tests/test_doc_blocks.py`` fail when a
block differs from what its source gives.

Adding a block: write the markers around the table (the body can be empty) naming a generator
and a source, run ``dss-results --publish``, and commit the doc. A new kind of table is a new
function registered with ``@generator("name")`` here: ``fn(data: dict, **options) -> list[str]``.

Generators for ``dss-denoise-table`` results (``table.json``):

- ``denoise_methods``: a row per method (``methods="name=label|..."``, in that order; the rows
  ``input`` and ``floor`` are the table's own), a column per ``columns="spec=header|..."`` entry:
  ``mean_cd``, ``mean_hd``, ``mean_p2m`` (means over the tuning cases), ``held_out_cd`` (over the
  held-out cases), ``case_cd:<case>``, ``case_hd:<case>`` (one case), ``cpu`` (CPU s per case,
  mean over every case), ``time`` (wall s per case over the tuning cases). ``sort=chamfer`` orders
  the method rows by mean CD.
- ``denoise_cases``: a row per case (held-out cases labelled so), the tuning and held-out means,
  a column per method; ``metrics=chamfer`` or ``chamfer,hausdorff`` (cells ``CD / HD``),
  ``ratio=<num>/<den>`` adds the two methods' Chamfer ratio, ``cpu=true`` a CPU-seconds row,
  ``cases="<case>=label|..."`` names cases.

In both, **bold** marks a column's (or case's) best value among the methods other than the
``control=<method>`` (shown in italics: a reference, not a contender) and the input and floor
rows; † marks a Chamfer distance worse than the noisy input's on that case.
"""

from __future__ import annotations

import json
import math
import re
import shlex
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

__all__ = ["GENERATORS", "Block", "find_blocks", "render_block", "update", "doc_files"]

BEGIN = re.compile(r"<!-- generated: (?P<spec>.*?)-->\n", re.S)
END = "<!-- end generated -->"

GENERATORS: dict[str, Callable[..., list[str]]] = {}


def generator(name: str):
    def register(fn):
        GENERATORS[name] = fn
        return fn

    return register


@dataclass
class Block:
    """One generated block: where it is (``path``, the opening marker's ``line``), what makes it
    (``generator``, ``source``, ``options``) and the text between the markers (``body``, span
    ``start``:``end`` of the file's text)."""

    path: Path
    line: int
    generator: str
    source: str
    options: dict[str, str]
    body: str
    start: int
    end: int


FENCE = re.compile(r"^ *(```|~~~)", re.M)


def _in_code(text: str, pos: int) -> bool:
    """Whether ``pos`` lies inside a fenced code block (an example of the markers, not a block)."""
    return len(FENCE.findall(text, 0, pos)) % 2 == 1


def find_blocks(path: Path) -> list[Block]:
    """The generated blocks of a markdown file (ValueError naming file and line for a malformed
    one); markers inside fenced code blocks are text."""
    text = Path(path).read_text()
    blocks, pos = [], 0
    while (m := BEGIN.search(text, pos)) is not None:
        if _in_code(text, m.start()):
            pos = m.end()
            continue
        line = text.count("\n", 0, m.start()) + 1
        where = f"{path}:{line}"
        try:
            words = shlex.split(m.group("spec"))
        except ValueError as e:
            raise ValueError(f"{where}: generated-block marker: {e}") from None
        if len(words) < 2:
            raise ValueError(f"{where}: a generated-block marker names a generator and a source file")
        name, source, *rest = words
        options = {}
        for w in rest:
            key, eq, value = w.partition("=")
            if not eq:
                raise ValueError(f"{where}: option {w!r} is not key=value")
            options[key] = value
        end = text.find(END, m.end())
        if end < 0:
            raise ValueError(f"{where}: no {END} after this generated block")
        blocks.append(Block(Path(path), line, name, source, options, text[m.end():end], m.end(), end))
        pos = end + len(END)
    return blocks


def render_block(block: Block, root: Path) -> str:
    """The text the block's generator writes from its source (ends with a newline)."""
    where = f"{block.path}:{block.line}"
    fn = GENERATORS.get(block.generator)
    if fn is None:
        raise ValueError(f"{where}: unknown generator {block.generator!r}; known: {sorted(GENERATORS)}")
    src = Path(root) / block.source
    if not src.is_file():
        raise ValueError(f"{where}: source {block.source} does not exist")
    try:
        data = json.loads(src.read_text())
    except ValueError as e:
        raise ValueError(f"{where}: source {block.source} is not JSON ({e})") from None
    try:
        lines = fn(data, **block.options)
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{where}: {block.generator} from {block.source}: {e}") from None
    return "\n".join(lines) + "\n"


def doc_files(root: Path) -> list[Path]:
    """The markdown files that may hold generated blocks: README.md and docs/*.md."""
    root = Path(root)
    return [p for p in [root / "README.md", *sorted((root / "docs").glob("*.md"))] if p.is_file()]


def update(root: Path, write: bool = False) -> list[Block]:
    """Regenerate every block of :func:`doc_files` under ``root``; returns the blocks whose text
    differs from their source's. With ``write``, rewrites those files (atomically)."""
    from dss.io_utils import atomic_write_text

    stale = []
    for path in doc_files(root):
        text = path.read_text()
        blocks = find_blocks(path)
        new, pos = [], 0
        for b in blocks:
            body = render_block(b, root)
            if body != b.body:
                stale.append(b)
            new += [text[pos:b.start], body]
            pos = b.end
        new.append(text[pos:])
        if write and any(b.path == path for b in stale):
            atomic_write_text(path, "".join(new))
    return stale


# ------------------------------------------------------------------------------- formatting
DIGITS = {"chamfer": 3, "p2m": 3, "hausdorff": 1, "cpu": 1, "time": 1, "ratio": 2}


def _num(x, kind: str) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{x:.{DIGITS[kind]}f}"


def _pairs(spec: str, what: str) -> list[tuple[str, str]]:
    """``"a=A|b=B"`` -> [("a", "A"), ("b", "B")] (a bare ``a`` is labelled ``a``)."""
    out = []
    for item in spec.split("|"):
        key, _, label = item.partition("=")
        if not key.strip():
            raise ValueError(f"empty entry in {what}={spec!r}")
        out.append((key.strip(), label.strip() or key.strip()))
    return out


def _rows(data: dict) -> dict[str, dict]:
    return {r["method"]: r for r in data.get("rows", [])}


def _case_names(data: dict, held_out: bool) -> list[str]:
    return [c["name"] for c in data.get("cases", []) if bool(c.get("held_out")) == held_out]


#: record statuses that carry metrics (dss-denoise-table's SCORED: the output exists and is finite)
SCORED = ("ok", "worse_than_input", "reference")


def _case_value(row: dict, case: str, metric: str):
    c = (row.get("cases") or {}).get(case)
    return c.get(metric) if isinstance(c, dict) and c.get("status", "ok") in SCORED else None


def _cpu_per_case(row: dict):
    v = [c["cpu_s"] for c in (row.get("cases") or {}).values() if isinstance(c, dict) and c.get("cpu_s") is not None]
    return sum(v) / len(v) if v else None


def _case_label(data: dict, case: str, names: dict[str, str] | None = None) -> str:
    """``torus_knot-0021`` -> ``torus knot`` (``held out: ...`` for a held-out case), or its
    entry in ``names``."""
    held = next((bool(c.get("held_out")) for c in data.get("cases", []) if c["name"] == case), None)
    if held is None:
        raise ValueError(f"no case {case!r} in the table (cases: {[c['name'] for c in data.get('cases', [])]})")
    label = (names or {}).get(case) or re.sub(r"-\d+$", "", case).replace("_", " ")
    return f"held out: {label}" if held else label


def _mark(cells: list[str], values: list, eligible: list[bool], lower: bool = True) -> None:
    """Bold the best of ``values`` among the ``eligible`` cells, in place."""
    cand = [v for v, ok in zip(values, eligible) if ok and v is not None]
    if not cand:
        return
    best = min(cand) if lower else max(cand)
    for i, (v, ok) in enumerate(zip(values, eligible)):
        if ok and v is not None and v == best:
            cells[i] = f"**{cells[i]}**"


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)] + ["| " + " | ".join(r) + " |" for r in rows]


# ------------------------------------------------------------------------------- generators
def _method_column(data: dict, row: dict, spec: str):
    """(value, kind) of one ``denoise_methods`` column for one method row."""
    key, _, case = spec.partition(":")
    if key in ("mean_cd", "mean_hd", "mean_p2m"):
        metric = {"mean_cd": "chamfer", "mean_hd": "hausdorff", "mean_p2m": "p2m"}[key]
        return (row.get("mean") or {}).get(metric), metric
    if key == "held_out_cd":
        return (row.get("mean_held_out") or {}).get("chamfer"), "chamfer"
    if key in ("case_cd", "case_hd"):
        _case_label(data, case)  # refuses an unknown case
        metric = "chamfer" if key == "case_cd" else "hausdorff"
        return _case_value(row, case, metric), metric
    if key == "cpu":
        return _cpu_per_case(row), "cpu"
    if key == "time":
        return row.get("time_s"), "time"
    raise ValueError(f"unknown column {spec!r} (mean_cd, mean_hd, mean_p2m, held_out_cd, case_cd:<case>, "
                     "case_hd:<case>, cpu, time)")


@generator("denoise_methods")
def denoise_methods(data: dict, methods: str, columns: str, control: str = "", sort: str = "") -> list[str]:
    by_name = _rows(data)
    wanted = _pairs(methods, "methods")
    missing = [m for m, _ in wanted if m not in by_name]
    if missing:
        raise ValueError(f"no rows {missing} in the table (rows: {sorted(by_name)})")
    if sort == "chamfer":
        fixed = {"input", "floor"}
        movable = sorted((p for p in wanted if p[0] not in fixed),
                         key=lambda p: (by_name[p[0]].get("mean") or {}).get("chamfer", math.inf))
        wanted = ([p for p in wanted if p[0] == "floor"] + movable + [p for p in wanted if p[0] == "input"])
    elif sort:
        raise ValueError(f"sort={sort!r}: only sort=chamfer")
    cols = _pairs(columns, "columns")
    inp = by_name.get("input")
    cells = [[label] for _, label in wanted]
    for spec, _ in cols:
        values, texts, marks = [], [], []
        for name, _ in wanted:
            v, kind = _method_column(data, by_name[name], spec)
            worse = False
            if spec.startswith("case_cd:") and inp is not None and name != "input" and v is not None:
                ref = _case_value(inp, spec.partition(":")[2], "chamfer")
                worse = ref is not None and v > ref
            values.append(v)
            texts.append(_num(v, kind))
            marks.append(" †" if worse else "")
        eligible = [n not in ("input", "floor", control) for n, _ in wanted]
        _mark(texts, values, eligible)
        for i, (name, _) in enumerate(wanted):
            text = f"*{texts[i]}*" if name == control and texts[i] != "-" else texts[i]
            cells[i].append(text + marks[i])
    return _table(["method", *[h for _, h in cols]], cells)


@generator("denoise_cases")
def denoise_cases(data: dict, methods: str, metrics: str = "chamfer", control: str = "", ratio: str = "",
                  cpu: str = "false", cases: str = "") -> list[str]:
    by_name = _rows(data)
    names = dict(_pairs(cases, "cases")) if cases else {}
    wanted = _pairs(methods, "methods")
    missing = [m for m, _ in wanted if m not in by_name]
    if missing:
        raise ValueError(f"no rows {missing} in the table (rows: {sorted(by_name)})")
    mets = [m.strip() for m in metrics.split(",")]
    if not set(mets) <= {"chamfer", "hausdorff", "p2m"}:
        raise ValueError(f"metrics={metrics!r}: chamfer, hausdorff, p2m")
    num = den = None
    if ratio:
        num, _, den = ratio.partition("/")
        if num not in by_name or den not in by_name:
            raise ValueError(f"ratio={ratio!r}: both must be rows of the table")
    label = dict(wanted)
    inp = by_name.get("input")
    eligible = [n not in ("input", "floor", control) for n, _ in wanted]

    def line(title: str, value_of) -> list[str]:
        """One row: per method the metrics' values (value_of(row, metric)), best in bold."""
        parts = {m: [_num(value_of(by_name[n], m), m) for n, _ in wanted] for m in mets}
        for m in mets:
            _mark(parts[m], [value_of(by_name[n], m) for n, _ in wanted], eligible)
        cells = []
        for i, (n, _) in enumerate(wanted):
            text = " / ".join(parts[m][i] for m in mets)
            cells.append(f"*{text}*" if n == control else text)
        return [title, *cells]

    rows = []
    for held in (False, True):
        for case in _case_names(data, held):
            def value_of(row, m, case=case):
                return _case_value(row, case, m)

            r = line(_case_label(data, case, names), value_of)
            ref = _case_value(inp, case, "chamfer") if inp is not None else None
            for i, (n, _) in enumerate(wanted):
                v = _case_value(by_name[n], case, "chamfer")
                if ref is not None and v is not None and v > ref:
                    r[1 + i] += " †"
            if num:
                a, b = _case_value(by_name[num], case, "chamfer"), _case_value(by_name[den], case, "chamfer")
                r.append(_num(a / b if a is not None and b else None, "ratio"))
            rows.append(r)
        key = "mean_held_out" if held else "mean"
        r = line(f"**mean, {'held out' if held else 'tuning'}**", lambda row, m, key=key: (row.get(key) or {}).get(m))
        if num:
            a = (by_name[num].get(key) or {}).get("chamfer")
            b = (by_name[den].get(key) or {}).get("chamfer")
            r.append(_num(a / b if a is not None and b else None, "ratio"))
        rows.append(r)
    if cpu == "true":
        cpus = [_cpu_per_case(by_name[n]) for n, _ in wanted]
        texts = [_num(v, "cpu") for v in cpus]
        _mark(texts, cpus, eligible)
        rows.append(["CPU s per case (mean)", *[f"*{t}*" if n == control else t for t, (n, _) in zip(texts, wanted)]]
                    + ([""] if num else []))
    elif cpu != "false":
        raise ValueError(f"cpu={cpu!r}: true or false")
    header = ["case", *[label[n] for n, _ in wanted]]
    if num:
        header.append(f"{label[num]} / {label[den]} (CD)")
    return _table(header, rows)


@generator("real_levels")
def real_levels(data: dict, group: str, methods: str, points: str = "") -> list[str]:
    """A row per noise level of ``dss-real-bench``'s ``report.json`` for one ``group`` (and, with
    ``points``, one point count): the noisy input's and the per-case best classical CD / HD, each
    of ``methods`` (``"name=label|..."``) as CD / HD, the first method's ratios to the best
    classical, how many of its cases end above the input's Hausdorff, and its CPU seconds."""
    wanted = _pairs(methods, "methods")
    levels = [lv for lv in data["summary"]["levels"] if lv["group"] == group
              and (not points or int(lv["points"]) == int(points))]
    if not levels:
        raise ValueError(f"no level of group {group!r}{f' at {points} points' if points else ''} in the report")
    first = wanted[0][0]
    rows = []
    for lv in levels:
        m = lv["mean"]
        missing = [n for n, _ in wanted if n not in m]
        if missing:
            raise ValueError(f"methods {missing} are not in the report (it has {sorted(m)})")

        def pair(name, m=m):
            return f"{_num(m[name]['chamfer'], 'chamfer')} / {_num(m[name]['hausdorff'], 'hausdorff')}"

        best = m["best_classical"]
        a, b = m[first], best
        rows.append([f"{100 * lv['noise']:g}% ({100 * lv['noise'] * data.get('paper_label_factor', 2.0):g}%)",
                     str(lv["points"]), f"{lv['n']}", pair("input"), pair("best_classical"),
                     *[pair(n) for n, _ in wanted],
                     _num(a["chamfer"] / b["chamfer"] if b["chamfer"] else None, "ratio"),
                     _num(a["hausdorff"] / b["hausdorff"] if b["hausdorff"] else None, "ratio"),
                     f"{lv['hd_above_input'][first]}/{lv['n']}", _num(lv["cpu_s"].get(first), "cpu")])
    label = dict(wanted)
    header = ["noise (paper's label)", "points", "cases", "input CD / HD", "best classical CD / HD",
              *[f"{label[n]} CD / HD" for n, _ in wanted], f"{label[first]} / best CD", f"{label[first]} / best HD",
              "HD above input", f"{label[first]} CPU s"]
    return _table(header, rows)
