"""``dss-data``: install data sets the benchmarks read.

    dss-data real                         # Debian's libcgal-demo meshes -> data/real/ (apt-get download)
    dss-data real --source libcgal-demo_5.5.1-2_all.deb   # ... from a package file (offline)
    dss-data real --source data.tar.gz    # ... or its data.tar.gz, or a folder of .off meshes
    dss-data real --list                  # what is installed, by group

``real``: the meshes named in ``data_prep/real_split.yaml`` (a fixed tuning split, a held-out
split, open surfaces and CAD parts), checked (boundary and non-manifold edges, degenerate faces,
components) and written as binary triangle PLY files with ``manifest.json``
(:mod:`data_prep.real_meshes`). A rerun keeps what is installed and fills in what is missing.
Where the package cannot be had, the command says so in one line and exits with status 2; the
rest of the project works without the meshes (the real-shape benchmark and its tests say they
are missing).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

__all__ = ["main"]

REPO_ROOT = Path(__file__).resolve().parents[2]


def _print_manifest(man: dict, dest: Path) -> None:
    by_group: dict[str, list[dict]] = {}
    for m in man["meshes"]:
        by_group.setdefault(m["group"], []).append(m)
    for g, ms in by_group.items():
        print(f"{g}:")
        for m in ms:
            if m["status"] != "ok":
                print(f"  {m['name']:22s} skipped: {m.get('reason')}")
                continue
            c = m["check"]
            shape = "closed" if c["closed"] else f"{c['boundary_edges']} boundary edges"
            print(f"  {m['name']:22s} {c['vertices']:6d} vertices {c['faces']:6d} faces, {shape}, "
                  f"{c['components']} component(s), {c['degenerate_faces']} degenerate faces")
    print(f"{man['installed']} meshes in {dest}" + (f"; skipped: {', '.join(man['skipped'])}" if man["skipped"] else ""))


def main(argv: list[str] | None = None) -> int:
    from data_prep.real_meshes import DEFAULT_ROOT, RealDataError, install_real, read_manifest

    ap = argparse.ArgumentParser(prog="dss-data", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="what", required=True)
    real = sub.add_parser("real", help="Debian's libcgal-demo meshes (tuning / held-out / open / cad groups)")
    real.add_argument("--dest", default=str(REPO_ROOT / DEFAULT_ROOT), help="install folder (default: data/real)")
    real.add_argument("--source", default=None,
                      help="libcgal-demo_*.deb, its data.tar.gz or a folder of .off files (default: apt-get download)")
    real.add_argument("--force", action="store_true", help="reinstall every mesh")
    real.add_argument("--list", action="store_true", help="show what is installed and exit")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    dest = Path(args.dest)
    try:
        man = read_manifest(dest) if args.list else install_real(dest, args.source, force=args.force)
    except (RealDataError, OSError, ValueError) as e:
        print(f"dss-data: error: {e}", file=sys.stderr)
        return 2
    _print_manifest(man, dest)
    return 0


if __name__ == "__main__":
    sys.exit(main())


def main_exit() -> None:
    """Console-script entry point (``dss-data``)."""
    sys.exit(main())
