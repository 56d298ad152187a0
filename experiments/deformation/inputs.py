"""dss-deform's inputs: the target cloud (a point cloud, or samples of a mesh), the start shape,
and the fixed front camera of the 2D grid experiments."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from dss.cameras import fibonacci_sphere, look_at
from dss.pointcloud import (
    PointCloud,
    PointCloudError,
    centred_cloud,
    load_ply,
    normalize_unit_diagonal,
    read_ply_header,
)

__all__ = ["load_target", "start_shape", "FrontViewSampler"]


def load_target(path: str, n_mesh_samples: int, seed: int = 0) -> PointCloud:
    """A target cloud with normals: a point cloud file as is, or samples of a mesh."""
    p = Path(path)
    if not p.exists():
        raise PointCloudError(f"{p}: no such file (target.path)")
    suffix = p.suffix.lower()
    if suffix == ".ply":
        # a PLY without faces is a point cloud: read without open3d (not installed everywhere,
        # e.g. on the GPU machines of experiments/benchmarks/gpu_check.sh)
        face = read_ply_header(p).element("face")
        if face is None or face.count == 0:
            return load_ply(p)
    if suffix not in (".ply", ".obj", ".off", ".stl"):
        return load_ply(p)
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(p))
    if len(mesh.triangles) > 0:
        mesh.compute_triangle_normals()
        o3d.utility.random.seed(int(seed))
        pcd = mesh.sample_points_poisson_disk(int(n_mesh_samples), use_triangle_normal=True)
        # float64 samples: a mesh far from the origin is centred before they become float32
        return centred_cloud(np.asarray(pcd.points, np.float64), np.asarray(pcd.normals, np.float32), source=str(p))
    return load_ply(p)


def start_shape(cfg: DictConfig, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Start points/normals centred at the origin (target units: bbox diagonal 1)."""
    n = int(cfg.start.points)
    if n <= 0:
        raise ValueError(f"start.points must be positive, got {n}")
    s = float(cfg.start.scale)
    kind = cfg.start.shape
    if kind == "sphere":
        d = fibonacci_sphere(n)
        return d * (s / 2), d.clone()
    if kind == "cube":
        per_face = max(1, n // 6)
        m = int(math.ceil(math.sqrt(per_face)))
        g = (torch.arange(m, dtype=torch.float32) + 0.5) / m - 0.5
        u, v = torch.meshgrid(g, g, indexing="ij")
        u, v = u.flatten()[:per_face], v.flatten()[:per_face]
        pts, nrm = [], []
        for axis in range(3):
            for sign in (-1.0, 1.0):
                q = torch.zeros(len(u), 3)
                q[:, axis] = 0.5 * sign
                q[:, (axis + 1) % 3] = u
                q[:, (axis + 2) % 3] = v
                nn = torch.zeros(len(u), 3)
                nn[:, axis] = sign
                pts.append(q)
                nrm.append(nn)
        return torch.cat(pts) * s, torch.cat(nrm)
    if kind == "grid":
        m = int(round(math.sqrt(n)))
        g = (torch.arange(m, dtype=torch.float32) + 0.5) / m - 0.5
        u, v = torch.meshgrid(g, g, indexing="ij")
        pts = torch.stack([u.flatten(), v.flatten(), torch.zeros(m * m)], -1) * s
        return pts, torch.tensor([0.0, 0.0, 1.0]).expand(m * m, 3).clone()
    if kind == "ply":
        if not cfg.start.path:
            raise ValueError("start.shape=ply needs start.path")
        c = load_ply(cfg.start.path)
        p, _, _ = normalize_unit_diagonal(c.points)
        return p * s, c.normals
    raise ValueError(f"unknown start.shape {kind!r}: sphere | cube | grid | ply")


class FrontViewSampler:
    """One fixed camera on the +z axis (for the 2D-grid experiments)."""

    def __init__(self, distance: float, focal: float, size: int):
        self.cams = look_at(torch.tensor([[0.0, 0.0, distance]]), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), focal, (size, size))

    def sample(self):
        return self.cams
