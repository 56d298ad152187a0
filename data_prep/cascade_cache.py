"""The ``dss-cascade/1`` cache: noisy training clouds after dss-denoise's classical stage, made
by ``python -m experiments.denoising.cascade`` and read by the on-the-fly training data
(``dss-train data=onthefly +data.cascade=<cache>``, :mod:`experiments.onthefly`).

Layout: ``<root>/manifest.json`` (``format``, source dataset and its fingerprint, settings, one
entry per item: ``shape_id``, ``split``, ``draw``, ``noise_std``, ``noise_seed``,
``estimated_noise``, ``file``, ``sha256``, ``cpu_s``) and ``<root>/<split>/<shape_id>-d<draw>.npz``
with ``points`` (N, 3) float32 and ``normals`` (N, 3) float32 in the clean cloud's frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["CASCADE_FORMAT", "read_cascade_manifest", "load_cascade_item"]

CASCADE_FORMAT = "dss-cascade/1"


def read_cascade_manifest(root) -> dict:
    """The manifest of a ``dss-cascade/1`` cache (ValueError when it is not one)."""
    from data_prep.clouds import read_format_manifest

    return read_format_manifest(root, CASCADE_FORMAT,
                                "no cascade cache (make it with python -m experiments.denoising.cascade)")


def load_cascade_item(root, entry: dict) -> tuple[np.ndarray, np.ndarray]:
    """(refined points (N, 3), normals (N, 3)) float32 of a manifest entry."""
    with np.load(Path(root) / entry["file"]) as z:
        return np.asarray(z["points"], np.float32), np.asarray(z["normals"], np.float32)
