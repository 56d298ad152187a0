"""Real shapes for the benchmarks: detailed meshes from Debian's ``libcgal-demo`` package.

The package ships ``usr/share/doc/libcgal-dev/data.tar.gz``, whose ``data/meshes/`` holds about
140 OFF meshes, many of them detailed scanned or sculpted shapes (armadillo, bunny, dragon, camel,
...). :func:`install_real` takes the meshes named in ``data_prep/real_split.yaml`` out of it,
checks each one (:func:`check_mesh`: boundary and non-manifold edges, degenerate faces,
components, scale), writes them as binary triangle PLY files and a ``manifest.json`` into
``data/real/``. The package comes from ``apt-get download libcgal-demo`` (no root needed, Debian's
package registry) or from a file the user gives: the ``.deb``, its ``data.tar.gz``, or a folder
of ``.off`` files.

The split (``tuning`` / ``held_out`` / ``open`` / ``cad``) is fixed in the repository: settings
are chosen on ``tuning`` only (:func:`load_split`).
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import os
import shutil
import subprocess
import tarfile
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

log = logging.getLogger(__name__)

__all__ = ["SPLIT_FILE", "DEFAULT_ROOT", "RealDataError", "load_split", "read_off", "check_mesh",
           "install_real", "read_manifest", "real_cases", "load_training_mesh", "resolve_root"]

SPLIT_FILE = Path(__file__).with_name("real_split.yaml")
#: where ``dss-data real`` installs the meshes (relative to the repository root)
DEFAULT_ROOT = Path("data") / "real"
MANIFEST = "manifest.json"


class RealDataError(RuntimeError):
    """The real meshes cannot be had or read; the message is one line for the user."""


def load_split(path: str | os.PathLike = SPLIT_FILE) -> dict:
    """``{"source": {...}, "groups": {group: [mesh name, ...]}}`` from the split file; a name in
    two groups is refused (a held-out shape must never be a tuning shape)."""
    d = yaml.safe_load(Path(path).read_text())
    groups = {str(g): [str(n) for n in names] for g, names in (d.get("groups") or {}).items()}
    seen: dict[str, str] = {}
    for g, names in groups.items():
        for n in names:
            if n in seen:
                raise ValueError(f"{path}: mesh {n!r} is in groups {seen[n]!r} and {g!r}")
            seen[n] = g
    return {"source": dict(d.get("source") or {}), "groups": groups}


# ------------------------------------------------------------------------------ OFF meshes
def read_off(data: bytes | str | os.PathLike, name: str = "mesh") -> tuple[np.ndarray, np.ndarray]:
    """``(vertices (V, 3) float64, faces (F, 3) int64)`` of an ASCII OFF file (bytes or a path).

    Comments (``#``) and blank lines are skipped; the counts may follow ``OFF`` on its line;
    polygons are split into triangle fans; per-vertex or per-face colours are ignored.
    Raises :class:`RealDataError` naming ``name`` on a malformed file."""
    if not isinstance(data, bytes):
        name = str(data)
        data = Path(data).read_bytes()
    tokens: list[str] = []
    for line in data.decode("ascii", errors="replace").splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            tokens.append(line)
    if not tokens or not tokens[0].split()[0].endswith("OFF"):
        raise RealDataError(f"{name}: not an OFF file (no OFF header)")
    head = tokens[0].split()[1:]
    rows = tokens[1:]
    if not head:
        head, rows = rows[0].split(), rows[1:]
    try:
        nv, nf = int(head[0]), int(head[1])
    except (IndexError, ValueError):
        raise RealDataError(f"{name}: bad OFF counts line {' '.join(head)!r}") from None
    if len(rows) < nv + nf:
        raise RealDataError(f"{name}: OFF header declares {nv} vertices and {nf} faces, the file has {len(rows)} rows")
    try:
        v = np.array([[float(x) for x in r.split()[:3]] for r in rows[:nv]], np.float64).reshape(nv, 3)
    except ValueError as e:
        raise RealDataError(f"{name}: bad vertex row ({e})") from None
    tris: list[tuple[int, int, int]] = []
    for r in rows[nv:nv + nf]:
        parts = r.split()
        try:
            k = int(parts[0])
            idx = [int(x) for x in parts[1:1 + k]]
        except (IndexError, ValueError):
            raise RealDataError(f"{name}: bad face row {r!r}") from None
        if len(idx) != k or k < 3:
            raise RealDataError(f"{name}: bad face row {r!r}")
        tris += [(idx[0], idx[i], idx[i + 1]) for i in range(1, k - 1)]
    f = np.array(tris, np.int64).reshape(-1, 3)
    if len(f) and (f.min() < 0 or f.max() >= nv):
        raise RealDataError(f"{name}: a face refers to a vertex outside 0..{nv - 1}")
    return v, f


def check_mesh(v: np.ndarray, f: np.ndarray) -> dict:
    """What a benchmark needs to know of a mesh: counts, boundary and non-manifold edges,
    degenerate (zero-area) faces, connected components, unreferenced vertices, the bounding-box
    diagonal, and ``problem``: why it cannot be used (None when it can)."""
    out: dict = {"vertices": int(len(v)), "faces": int(len(f))}
    if len(v) == 0 or len(f) == 0:
        return {**out, "problem": "no vertices or no faces"}
    if not np.isfinite(v).all():
        return {**out, "problem": f"{int((~np.isfinite(v)).any(1).sum())} vertices are NaN/inf"}
    diag = float(np.linalg.norm(v.max(0) - v.min(0)))
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    degenerate = area <= 1e-12 * max(diag, 1e-300) ** 2
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    out.update(bbox_diagonal=diag, surface_area=float(area.sum()), degenerate_faces=int(degenerate.sum()),
               boundary_edges=int((counts == 1).sum()), nonmanifold_edges=int((counts > 2).sum()),
               unreferenced_vertices=int(len(v) - len(np.unique(f))), components=_components(len(v), f))
    out["closed"] = out["boundary_edges"] == 0 and out["nonmanifold_edges"] == 0
    if not diag > 0:
        out["problem"] = "zero-size bounding box"
    elif degenerate.all():
        out["problem"] = "every face is degenerate (zero area)"
    else:
        out["problem"] = None
    return out


def _components(nv: int, f: np.ndarray) -> int:
    """Connected components of the faces (vertices joined by edges; unreferenced ones left out)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]]])
    g = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(nv, nv))
    _, labels = connected_components(g, directed=False)
    return int(len(np.unique(labels[np.unique(f)])))


# ------------------------------------------------------------------------------ the package
def _ar_members(blob: bytes) -> dict[str, bytes]:
    """The members of a Unix ``ar`` archive (a ``.deb``): ``{name: bytes}``."""
    if not blob.startswith(b"!<arch>\n"):
        raise RealDataError("not a Debian package (no ar archive header)")
    out, pos = {}, 8
    while pos + 60 <= len(blob):
        hdr = blob[pos:pos + 60]
        name = hdr[:16].decode("ascii", "replace").strip().rstrip("/")
        size = int(hdr[48:58].decode("ascii").strip())
        out[name] = blob[pos + 60:pos + 60 + size]
        pos += 60 + size + (size % 2)
    return out


def _data_archive_from_deb(deb: Path, member: str) -> bytes:
    """The bytes of ``member`` (e.g. ``usr/share/doc/libcgal-dev/data.tar.gz``) inside the
    package's ``data.tar.*``."""
    members = _ar_members(deb.read_bytes())
    data = next((k for k in members if k.startswith("data.tar")), None)
    if data is None:
        raise RealDataError(f"{deb}: no data.tar.* member in the package")
    if data.endswith(".zst"):
        raise RealDataError(f"{deb}: data.tar.zst (zstd) cannot be read here; extract the package and "
                            f"give source=<folder>/{member}")
    with tarfile.open(fileobj=io.BytesIO(members[data])) as tf:
        for m in tf.getmembers():
            if m.name.lstrip("./") == member:
                return tf.extractfile(m).read()
    raise RealDataError(f"{deb}: the package holds no {member}")


def download_package(package: str, workdir: Path) -> Path:
    """``apt-get download <package>`` into ``workdir`` (no root needed); the ``.deb`` path."""
    if shutil.which("apt-get") is None:
        raise RealDataError(f"apt-get is not available to download {package}; give source=<{package}_*.deb, "
                            "its data.tar.gz, or a folder of .off meshes>")
    log.info("downloading %s with apt-get download", package)
    try:
        p = subprocess.run(["apt-get", "download", package], cwd=workdir, capture_output=True, text=True,
                           timeout=600)
    except subprocess.TimeoutExpired:
        raise RealDataError(f"apt-get download {package} took more than 10 minutes") from None
    debs = sorted(workdir.glob(f"{package}_*.deb"))
    if p.returncode != 0 or not debs:
        why = (p.stderr or p.stdout).strip().splitlines()
        raise RealDataError(f"apt-get download {package} failed ({why[-1] if why else f'exit {p.returncode}'}); "
                            f"give source=<{package}_*.deb, its data.tar.gz, or a folder of .off meshes>")
    return debs[-1]


class _Source:
    """Reads ``<name>.off`` from a ``.deb``, a ``data.tar.gz`` or a folder."""

    def __init__(self, path: Path, split: dict):
        self.path = path
        src = split["source"]
        self.folder = str(src.get("folder", "data/meshes")).strip("/")
        self.tar = None
        if path.is_dir():
            self.kind = "folder"
        elif path.suffix == ".deb":
            self.kind = "deb"
            self.tar = tarfile.open(fileobj=io.BytesIO(_data_archive_from_deb(path, src["archive"])))
        elif path.name.endswith((".tar.gz", ".tgz", ".tar")):
            self.kind = "tar"
            self.tar = tarfile.open(path)
        else:
            raise RealDataError(f"source {path}: expected a .deb, a data.tar.gz or a folder of .off files")
        self.names = {}
        if self.tar is not None:
            for m in self.tar.getmembers():
                n = m.name.lstrip("./")
                if m.isfile() and n.startswith(self.folder + "/") and n.endswith(".off"):
                    self.names[Path(n).stem] = m

    def read(self, name: str) -> bytes | None:
        if self.kind == "folder":
            p = self.path / f"{name}.off"
            return p.read_bytes() if p.is_file() else None
        m = self.names.get(name)
        return None if m is None else self.tar.extractfile(m).read()


def _write_mesh_ply(path: Path, v: np.ndarray, f: np.ndarray) -> None:
    """Binary triangle PLY (float64 vertices: the meshes' own precision)."""
    from dss.io_utils import atomic_write_bytes

    vert = np.ascontiguousarray(v, "<f8")
    face = np.empty(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    face["n"], face["i"] = 3, np.asarray(f, np.int32)
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(vert)}",
              "property double x", "property double y", "property double z", f"element face {len(face)}",
              "property list uchar int vertex_indices", "end_header"]
    atomic_write_bytes(path, ("\n".join(header) + "\n").encode("ascii") + vert.tobytes() + face.tobytes())


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def install_real(dest: str | os.PathLike = DEFAULT_ROOT, source: str | os.PathLike | None = None,
                 split_file: str | os.PathLike = SPLIT_FILE, force: bool = False) -> dict:
    """Install the split's meshes into ``dest`` and write ``dest/manifest.json``; returns it.

    ``source``: the package file, its ``data.tar.gz`` or a folder of ``.off`` files; None:
    ``apt-get download``. Meshes already installed with the same bytes are kept (a rerun only
    fills in what is missing, unless ``force``). A mesh that is missing from the source, cannot
    be read or cannot be used is recorded with ``status: "skipped"`` and its reason, never
    dropped silently. Degenerate (zero-area) faces are removed from the written file (and
    counted in the manifest)."""
    from dss.io_utils import atomic_write_json

    dest = Path(dest)
    split = load_split(split_file)
    old = read_manifest(dest, missing_ok=True) if not force else None
    old_meshes = {m["name"]: m for m in (old or {}).get("meshes", [])}
    wanted = [(g, n) for g, names in split["groups"].items() for n in names]
    todo = [(g, n) for g, n in wanted
            if force or n not in old_meshes or old_meshes[n].get("status") != "ok"
            or not (dest / old_meshes[n]["file"]).is_file()
            or _sha256(dest / old_meshes[n]["file"]) != old_meshes[n]["sha256"]]
    t0 = time.perf_counter()
    source_note = (old or {}).get("source", {})
    records = {n: {**old_meshes[n], "group": g} for g, n in wanted if (g, n) not in todo}
    if todo:
        with tempfile.TemporaryDirectory(prefix="dss-real-") as tmp:
            if source is None:
                path = download_package(str(split["source"].get("package", "libcgal-demo")), Path(tmp))
                how = "apt-get download"
            else:
                path, how = Path(source).expanduser(), "given"
                if not path.exists():
                    raise RealDataError(f"source {path}: no such file or folder")
            src = _Source(path, split)
            source_note = {"how": how, "file": path.name, "kind": src.kind,
                           "sha256": _sha256(path) if path.is_file() else None}
            dest.mkdir(parents=True, exist_ok=True)
            for g, n in todo:
                records[n] = _install_one(src, dest, g, n)
    meshes = [records[n] for _, n in wanted]
    manifest = {"split_file": str(split_file), "source": source_note, "groups": split["groups"],
                "meshes": meshes, "installed": sum(m["status"] == "ok" for m in meshes),
                "skipped": [m["name"] for m in meshes if m["status"] != "ok"],
                "seconds": round(time.perf_counter() - t0, 2)}
    dest.mkdir(parents=True, exist_ok=True)
    atomic_write_json(dest / MANIFEST, manifest)
    return manifest


def _install_one(src: _Source, dest: Path, group: str, name: str) -> dict:
    rec = {"name": name, "group": group, "file": f"{name}.ply"}
    raw = src.read(name)
    if raw is None:
        log.warning("%s: not in %s; skipped", name, src.path)
        return {**rec, "status": "skipped", "reason": f"not in {src.path.name}"}
    try:
        v, f = read_off(raw, f"{name}.off")
    except RealDataError as e:
        log.warning("%s; skipped", e)
        return {**rec, "status": "skipped", "reason": str(e)}
    chk = check_mesh(v, f)
    if chk["problem"]:
        log.warning("%s: %s; skipped", name, chk["problem"])
        return {**rec, "status": "skipped", "reason": chk["problem"], "check": chk}
    if chk["degenerate_faces"]:
        area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
        f = f[area > 1e-12 * chk["bbox_diagonal"] ** 2]
    _write_mesh_ply(dest / rec["file"], v, f)
    return {**rec, "status": "ok", "sha256": _sha256(dest / rec["file"]), "check": chk}


def read_manifest(root: str | os.PathLike = DEFAULT_ROOT, missing_ok: bool = False) -> dict | None:
    """``root/manifest.json`` (None when absent and ``missing_ok``)."""
    p = Path(root) / MANIFEST
    if not p.is_file():
        if missing_ok:
            return None
        raise RealDataError(f"{p} not found: install the real meshes with `dss-data real`")
    try:
        return json.loads(p.read_text())
    except json.JSONDecodeError as e:
        raise RealDataError(f"{p}: not valid JSON ({e}); reinstall with `dss-data real --force`") from None


def real_cases(groups, root: str | os.PathLike = DEFAULT_ROOT) -> tuple[list[dict], list[dict]]:
    """(cases, skipped) for the benchmark: ``{name, mesh, group, held_out}`` per installed mesh of
    ``groups`` (in the split's order; ``held_out`` for every group but ``tuning``), and
    ``{name, group, reason}`` per mesh of those groups that is not usable."""
    man = read_manifest(root)
    groups = list(groups)
    bad = [g for g in groups if g not in man["groups"]]
    if bad:
        raise ValueError(f"real groups {bad} unknown; the split has {sorted(man['groups'])}")
    cases, skipped = [], []
    for m in man["meshes"]:
        if m["group"] not in groups:
            continue
        path = Path(root) / m["file"]
        if m["status"] != "ok" or not path.is_file():
            skipped.append({"name": m["name"], "group": m["group"],
                            "reason": m.get("reason") or f"{path} missing: reinstall with `dss-data real`"})
            continue
        cases.append({"name": m["name"], "mesh": str(path), "group": m["group"],
                      "held_out": m["group"] != "tuning"})
    order = {g: i for i, g in enumerate(groups)}
    cases.sort(key=lambda c: order[c["group"]])
    return cases, skipped


def resolve_root(root: str | os.PathLike = DEFAULT_ROOT) -> Path:
    """``root`` as given when absolute, else relative to the repository root (where ``dss-data
    real`` installs ``data/real``), whatever the working directory."""
    p = Path(root).expanduser()
    return p if p.is_absolute() else Path(__file__).resolve().parents[1] / p


def load_training_mesh(name: str, root: str | os.PathLike = DEFAULT_ROOT, trainable=("tuning",)):
    """The installed real mesh ``name`` for training data (``dss-prep shapes.real``), as a
    :class:`data_prep.shapes.Mesh` normalised to a unit bounding-box diagonal.

    Only meshes of the ``trainable`` groups of the split file are handed out: a held-out or open
    mesh (or one the split does not list) raises :class:`RealDataError`, so that no
    configuration can render it for training. The file must match the manifest's sha256."""
    from dss.metrics import load_mesh

    from .shapes.meshing import Mesh, normalize_mesh

    groups = load_split()["groups"]
    group = next((g for g, names in groups.items() if name in names), None)
    if group not in trainable:
        raise RealDataError(f"real mesh {name!r} is in group {group!r} of {SPLIT_FILE.name}: only "
                            f"{list(trainable)} meshes may be rendered for training")
    root = resolve_root(root)
    man = read_manifest(root)
    entry = next((m for m in man["meshes"] if m["name"] == name), None)
    path = root / (entry or {}).get("file", f"{name}.ply")
    if entry is None or entry.get("status") != "ok" or not path.is_file():
        raise RealDataError(f"real mesh {name!r} is not installed in {root}: run `dss-data real`")
    if entry.get("sha256") and _sha256(path) != entry["sha256"]:
        raise RealDataError(f"{path}: does not match its manifest's sha256; reinstall with `dss-data real --force`")
    v, f = load_mesh(str(path))
    return normalize_mesh(Mesh(np.asarray(v, np.float64), np.asarray(f, np.int64)))
