"""dss-data real: the libcgal-demo meshes (data_prep/real_meshes.py), from a package built here."""

from __future__ import annotations

import io
import json
import tarfile
from pathlib import Path

import numpy as np
import pytest

from data_prep.real_meshes import (
    RealDataError,
    check_mesh,
    install_real,
    load_split,
    read_manifest,
    read_off,
    real_cases,
)

TETRA = b"""OFF
# a closed tetrahedron
4 4 0
0 0 0
1 0 0
0 1 0
0 0 1
3 0 2 1
3 0 1 3
3 0 3 2
3 1 2 3
"""
QUAD = b"OFF 4 1 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3 255 0 0\n"  # counts on the OFF line, colour


def _tar(members: dict[str, bytes], mode: str) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode=mode) as tf:
        for name, data in members.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))
    return buf.getvalue()


def _deb(meshes: dict[str, bytes]) -> bytes:
    """A Debian package as libcgal-demo lays it out: ar(data.tar.xz(.../data.tar.gz(data/meshes/*.off)))."""
    inner = _tar({f"data/meshes/{n}.off": d for n, d in meshes.items()}, "w:gz")
    data = _tar({"./usr/share/doc/libcgal-dev/data.tar.gz": inner}, "w:xz")
    out = b"!<arch>\n"
    for name, blob in (("debian-binary", b"2.0\n"), ("data.tar.xz", data)):
        out += f"{name:<16}{0:<12}{0:<6}{0:<6}{100644:<8}{len(blob):<10}`\n".encode() + blob + (b"\n" if len(blob) % 2 else b"")
    return out


def _split(tmp: Path, groups: dict) -> Path:
    import yaml

    p = tmp / "split.yaml"
    p.write_text(yaml.safe_dump({"source": {"package": "libcgal-demo", "archive": "usr/share/doc/libcgal-dev/data.tar.gz",
                                            "folder": "data/meshes"}, "groups": groups}))
    return p


def test_read_off_handles_comments_counts_on_the_header_line_and_polygons():
    v, f = read_off(TETRA)
    assert v.shape == (4, 3) and f.shape == (4, 3)
    v, f = read_off(QUAD)
    assert f.tolist() == [[0, 1, 2], [0, 2, 3]]  # a fan
    with pytest.raises(RealDataError, match="bad.off: not an OFF file"):
        read_off(b"PLY\n", "bad.off")
    with pytest.raises(RealDataError, match="short.off: OFF header declares 4 vertices"):
        read_off(b"OFF\n4 1 0\n0 0 0\n", "short.off")
    with pytest.raises(RealDataError, match="outside"):
        read_off(b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n", "x.off")


def test_check_mesh_counts_boundaries_degenerate_faces_and_components():
    v, f = read_off(TETRA)
    c = check_mesh(v, f)
    assert c["closed"] and c["boundary_edges"] == 0 and c["components"] == 1 and c["problem"] is None
    open_ = check_mesh(v, f[:3])
    assert not open_["closed"] and open_["boundary_edges"] == 3
    v2 = np.vstack([v, v + 5.0])
    deg = np.vstack([f, f + 4, [[0, 1, 1]]])  # two tetrahedra and a zero-area face
    c2 = check_mesh(v2, deg)
    assert c2["components"] == 2 and c2["degenerate_faces"] == 1
    assert check_mesh(v, np.zeros((0, 3), np.int64))["problem"] == "no vertices or no faces"
    assert "zero area" in check_mesh(v, np.array([[0, 0, 1]]))["problem"]


def test_install_from_a_package_file_writes_meshes_a_manifest_and_the_reasons_for_skips(tmp_path):
    deb = tmp_path / "libcgal-demo_1_all.deb"
    deb.write_bytes(_deb({"tet": TETRA, "quad": QUAD, "broken": b"OFF\n9 9 0\n"}))
    split = _split(tmp_path, {"tuning": ["tet"], "held_out": ["quad", "absent"], "open": ["broken"]})
    dest = tmp_path / "real"
    man = install_real(dest, deb, split)
    by = {m["name"]: m for m in man["meshes"]}
    assert by["tet"]["status"] == "ok" and by["tet"]["check"]["closed"]
    assert by["quad"]["status"] == "ok" and by["quad"]["check"]["boundary_edges"] == 4
    assert by["absent"]["status"] == "skipped" and "not in" in by["absent"]["reason"]
    assert by["broken"]["status"] == "skipped" and "broken.off" in by["broken"]["reason"]
    assert man["skipped"] == ["absent", "broken"] and read_manifest(dest) == json.loads((dest / "manifest.json").read_text())
    from dss.metrics import load_mesh

    v, f = load_mesh(dest / "tet.ply")
    assert v.dtype == np.float64 and len(f) == 4
    cases, skipped = real_cases(["tuning", "held_out"], dest)
    assert [c["name"] for c in cases] == ["tet", "quad"] and [c["held_out"] for c in cases] == [False, True]
    assert {s["name"] for s in skipped} == {"absent"}
    # a rerun keeps what is installed; a damaged file is installed again
    (dest / "tet.ply").write_bytes(b"damaged")
    again = install_real(dest, deb, split)
    assert {m["name"]: m for m in again["meshes"]}["tet"]["sha256"] == by["tet"]["sha256"]
    with pytest.raises(ValueError, match="unknown"):
        real_cases(["nope"], dest)


def test_a_split_with_a_mesh_in_two_groups_is_refused_and_the_shipped_split_is_disjoint(tmp_path):
    with pytest.raises(ValueError, match="'tet' is in groups"):
        load_split(_split(tmp_path, {"tuning": ["tet"], "held_out": ["tet"]}))
    shipped = load_split()
    assert len(shipped["groups"]["held_out"]) >= 8 and len(shipped["groups"]["tuning"]) >= 8


def test_dss_data_says_in_one_line_when_the_source_cannot_be_had(tmp_path, capsys):
    from experiments.apps.data import main

    assert main(["real", "--dest", str(tmp_path / "r"), "--source", str(tmp_path / "missing.deb")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("dss-data: error: source") and "missing.deb" in err[0]
    assert main(["real", "--dest", str(tmp_path / "r"), "--list"]) == 2
